//! The SQL layer both stores share: every statement of the [`Store`] contract written
//! once, with PostgreSQL's `$1` placeholders, and the row mapping of [`rows`](super::rows).
//!
//! A store implements [`SqlBackend`]: where reads go, how a write transaction begins
//! and ends, and its [`Dialect`] for the few places the two databases spell SQL
//! differently. What the backends do differently around a write:
//!
//! | | [`SqliteStore`](super::SqliteStore) | [`PostgresStore`](super::PostgresStore) |
//! |---|---|---|
//! | begin | the writer's turn, then `BEGIN IMMEDIATE` on the one write connection | `BEGIN`, then the fencing check (`FOR SHARE` on the leader epoch) |
//! | rows read to update | already locked: SQLite has one writer | `SELECT ... FOR UPDATE` |
//! | commit | bumps the commit generation if the write is one the commit marker records, commits, writes the marker, then ends the turn | commits |
//!
//! Statements run through [`Conn`], a closed enum over the four executors (a pool or a
//! transaction of either database), which binds [`Arg`]s, rewrites placeholders for
//! SQLite and maps every database error to a [`StoreError`] in one place,
//! [`store_error`].

use std::borrow::Cow;

use async_trait::async_trait;
use sqlx::postgres::{PgArguments, PgConnection, PgPool, PgRow, Postgres};
use sqlx::sqlite::{Sqlite, SqliteArguments, SqliteConnection, SqlitePool, SqliteRow};
use sqlx::{Arguments, Decode, Encode, Executor, Row as _, Transaction, Type};
use tessera_api::{FrameRange, HistoryPoint, JobState};
use tessera_farm::{FramePlan, JobId};

use super::checksum::{scene_checksum, verify, JobSum, TileSum};
use super::codec::{encode_adaptive, encode_stats, encode_units};
use super::rows::{
    check_finite, check_new_job, check_tile_to_save, decode_job, fault_from_row, fault_where,
    identity_col, int_col, job_from_row, now_unix_ms, parse_state, plan_from_row,
    quarantine_from_row, state_count_from_row, summary_from_row, tile_from_parts, to_i64,
    JOB_COLUMNS, PLAN_COLUMNS, QUARANTINE_COLUMNS,
};
use super::{
    FaultEvent, FaultFilter, JobOrder, JobQuery, JobRecord, NewJob, PreviousRun, QuarantineRecord,
    Store, StoreError, StoreResult, TileCheckpoint, TileCheckpointRef, TileSummary,
};

/// Where the two databases spell SQL differently.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Dialect {
    /// SQLite ([`SqliteStore`](super::SqliteStore)).
    Sqlite,
    /// PostgreSQL ([`PostgresStore`](super::PostgresStore)).
    Postgres,
}

impl Dialect {
    /// `sql`, written with `$1` placeholders, as this database takes it. SQLite parses
    /// `$1` too, but as a named parameter numbered by its first appearance, which would
    /// bind the values of `... $2 ... $1` in the wrong order: it gets `?1`.
    fn placeholders(self, sql: &str) -> Cow<'_, str> {
        match self {
            Self::Sqlite => Cow::Owned(sql.replace('$', "?")),
            Self::Postgres => Cow::Borrowed(sql),
        }
    }

    /// The suffix of a `SELECT` of rows the transaction then updates. PostgreSQL's
    /// writers run concurrently, so the rows are locked until the transaction ends;
    /// SQLite's `BEGIN IMMEDIATE` already holds the database's one write lock.
    pub fn for_update(self) -> &'static str {
        match self {
            Self::Sqlite => "",
            Self::Postgres => " FOR UPDATE",
        }
    }

    /// The larger of two values (SQLite has no `GREATEST`; its two-argument `MAX` is it).
    pub fn greatest(self) -> &'static str {
        match self {
            Self::Sqlite => "MAX",
            Self::Postgres => "GREATEST",
        }
    }

    /// A collation that orders text by its bytes: SQLite's default, and `"C"` on
    /// PostgreSQL whatever the database's locale, so both list rows in one order.
    pub fn byte_order(self) -> &'static str {
        match self {
            Self::Sqlite => "",
            Self::Postgres => " COLLATE \"C\"",
        }
    }

    /// The `schema_version` table (SQLite's tables are `STRICT`).
    fn schema_version_table(self) -> &'static str {
        match self {
            Self::Sqlite => {
                "CREATE TABLE IF NOT EXISTS schema_version (\
                     version INTEGER PRIMARY KEY, applied_unix_ms INTEGER NOT NULL) STRICT"
            }
            Self::Postgres => {
                "CREATE TABLE IF NOT EXISTS schema_version (\
                     version BIGINT PRIMARY KEY, applied_unix_ms BIGINT NOT NULL)"
            }
        }
    }
}

/// The one place a database error becomes a [`StoreError`]. `server` is the URL of a
/// PostgreSQL server (without its password), `None` for SQLite: there a lost or refused
/// connection is [`StoreError::Unreachable`], which is transient (the pool reconnects),
/// where a failing SQLite file stays failed; anything else is [`StoreError::Database`].
pub fn store_error(server: Option<&str>, e: sqlx::Error) -> StoreError {
    match server {
        Some(url) if is_connection_error(&e) => unreachable(url, e),
        _ => StoreError::Database(e),
    }
}

/// Whether `e` says the server could not be reached or the connection was lost.
fn is_connection_error(e: &sqlx::Error) -> bool {
    matches!(
        e,
        sqlx::Error::Io(_)
            | sqlx::Error::Tls(_)
            | sqlx::Error::PoolTimedOut
            | sqlx::Error::PoolClosed
            | sqlx::Error::WorkerCrashed
    ) || matches!(e, sqlx::Error::Database(d) if d.code().is_some_and(|c| {
        // Class 08: connection exception; 28: invalid authorization (wrong user or
        // password); 3D000: the database does not exist; 57P: the server is shutting
        // down or cannot accept connections now.
        c.starts_with("08") || c.starts_with("28") || c == "3D000" || c.starts_with("57P")
    }))
}

/// [`StoreError::Unreachable`] for the server at `url` (already redacted).
pub fn unreachable(url: &str, e: sqlx::Error) -> StoreError {
    StoreError::Unreachable {
        url: url.to_string(),
        detail: e.to_string(),
    }
}

/// A value to bind, in the Rust type both databases encode it from (a 64-bit integer,
/// a float, text or bytes, each nullable).
#[derive(Debug, Clone)]
pub enum Arg<'a> {
    /// An integer column.
    Int(Option<i64>),
    /// A floating-point column.
    Real(Option<f64>),
    /// A text column.
    Text(Option<&'a str>),
    /// A BLOB (SQLite) or BYTEA (PostgreSQL) column.
    Bytes(Option<Cow<'a, [u8]>>),
}

impl From<i64> for Arg<'_> {
    fn from(v: i64) -> Self {
        Self::Int(Some(v))
    }
}

impl From<Option<i64>> for Arg<'_> {
    fn from(v: Option<i64>) -> Self {
        Self::Int(v)
    }
}

impl From<f64> for Arg<'_> {
    fn from(v: f64) -> Self {
        Self::Real(Some(v))
    }
}

impl From<Option<f64>> for Arg<'_> {
    fn from(v: Option<f64>) -> Self {
        Self::Real(v)
    }
}

impl<'a> From<&'a str> for Arg<'a> {
    fn from(v: &'a str) -> Self {
        Self::Text(Some(v))
    }
}

impl<'a> From<&'a String> for Arg<'a> {
    fn from(v: &'a String) -> Self {
        Self::Text(Some(v))
    }
}

impl<'a> From<Option<&'a str>> for Arg<'a> {
    fn from(v: Option<&'a str>) -> Self {
        Self::Text(v)
    }
}

impl<'a> From<&'a [u8]> for Arg<'a> {
    fn from(v: &'a [u8]) -> Self {
        Self::Bytes(Some(Cow::Borrowed(v)))
    }
}

impl<'a> From<Option<&'a [u8]>> for Arg<'a> {
    fn from(v: Option<&'a [u8]>) -> Self {
        Self::Bytes(v.map(Cow::Borrowed))
    }
}

impl From<Vec<u8>> for Arg<'_> {
    fn from(v: Vec<u8>) -> Self {
        Self::Bytes(Some(Cow::Owned(v)))
    }
}

impl From<Option<Vec<u8>>> for Arg<'_> {
    fn from(v: Option<Vec<u8>>) -> Self {
        Self::Bytes(v.map(Cow::Owned))
    }
}

/// A statement and the values of its placeholders `$1`, `$2`, ... in order.
#[derive(Debug, Clone)]
pub struct Stmt<'a> {
    sql: Cow<'a, str>,
    args: Vec<Arg<'a>>,
}

/// A statement without values yet ([`Stmt::bind`] adds them).
pub fn stmt<'a>(sql: impl Into<Cow<'a, str>>) -> Stmt<'a> {
    Stmt {
        sql: sql.into(),
        args: Vec::new(),
    }
}

impl<'a> Stmt<'a> {
    /// Binds the next placeholder.
    pub fn bind(mut self, v: impl Into<Arg<'a>>) -> Self {
        self.args.push(v.into());
        self
    }

    /// The values as the arguments of database `A::Database` (both encode these four
    /// types).
    fn arguments<'q, A>(&'q self) -> Result<A, sqlx::Error>
    where
        A: Arguments<'q>,
        Option<i64>: Encode<'q, A::Database> + Type<A::Database>,
        Option<f64>: Encode<'q, A::Database> + Type<A::Database>,
        Option<&'q str>: Encode<'q, A::Database> + Type<A::Database>,
        Option<&'q [u8]>: Encode<'q, A::Database> + Type<A::Database>,
    {
        let mut out = A::default();
        for a in &self.args {
            match a {
                Arg::Int(v) => out.add(*v),
                Arg::Real(v) => out.add(*v),
                Arg::Text(v) => out.add(*v),
                Arg::Bytes(v) => out.add(v.as_deref()),
            }
            .map_err(sqlx::Error::Encode)?;
        }
        Ok(out)
    }
}

/// A row of either database.
pub enum Row {
    /// A SQLite row.
    Sqlite(SqliteRow),
    /// A PostgreSQL row.
    Postgres(PgRow),
}

impl Row {
    /// The value of column `col`, in a type both databases decode.
    pub fn try_get<T>(&self, col: &str) -> Result<T, sqlx::Error>
    where
        T: for<'r> Decode<'r, Sqlite>
            + Type<Sqlite>
            + for<'r> Decode<'r, Postgres>
            + Type<Postgres>,
    {
        match self {
            Self::Sqlite(r) => r.try_get(col),
            Self::Postgres(r) => r.try_get(col),
        }
    }
}

/// What a statement returns.
#[derive(Clone, Copy)]
enum Fetch {
    /// The number of rows it changed.
    Affected,
    /// Its first row, if any.
    Optional,
    /// All its rows.
    All,
}

/// Runs `s` on a SQLite executor: (rows changed, rows returned).
async fn run_sqlite<'c>(
    e: impl Executor<'c, Database = Sqlite>,
    s: &Stmt<'_>,
    fetch: Fetch,
) -> Result<(u64, Vec<Row>), sqlx::Error> {
    let sql = Dialect::Sqlite.placeholders(&s.sql);
    let q = sqlx::query_with(&sql, s.arguments::<SqliteArguments>()?);
    Ok(match fetch {
        Fetch::Affected => (q.execute(e).await?.rows_affected(), Vec::new()),
        Fetch::Optional => (
            0,
            q.fetch_optional(e)
                .await?
                .map(Row::Sqlite)
                .into_iter()
                .collect(),
        ),
        Fetch::All => (
            0,
            q.fetch_all(e).await?.into_iter().map(Row::Sqlite).collect(),
        ),
    })
}

/// Runs `s` on a PostgreSQL executor: (rows changed, rows returned).
async fn run_pg<'c>(
    e: impl Executor<'c, Database = Postgres>,
    s: &Stmt<'_>,
    fetch: Fetch,
) -> Result<(u64, Vec<Row>), sqlx::Error> {
    let q = sqlx::query_with(&s.sql, s.arguments::<PgArguments>()?);
    Ok(match fetch {
        Fetch::Affected => (q.execute(e).await?.rows_affected(), Vec::new()),
        Fetch::Optional => (
            0,
            q.fetch_optional(e)
                .await?
                .map(Row::Postgres)
                .into_iter()
                .collect(),
        ),
        Fetch::All => (
            0,
            q.fetch_all(e)
                .await?
                .into_iter()
                .map(Row::Postgres)
                .collect(),
        ),
    })
}

/// Where a statement runs: a pool or a transaction's connection, of either database.
/// The PostgreSQL variants carry the server's URL for [`store_error`].
#[derive(Debug)]
pub enum Conn<'a> {
    /// A SQLite pool.
    SqlitePool(&'a SqlitePool),
    /// A SQLite connection (in a transaction).
    Sqlite(&'a mut SqliteConnection),
    /// A PostgreSQL pool, and its URL without the password.
    PgPool(&'a PgPool, &'a str),
    /// A PostgreSQL connection (in a transaction), and its URL without the password.
    Pg(&'a mut PgConnection, &'a str),
}

impl Conn<'_> {
    /// Runs `s`; database errors pass through [`store_error`].
    async fn run(&mut self, s: &Stmt<'_>, fetch: Fetch) -> StoreResult<(u64, Vec<Row>)> {
        let (r, server) = match self {
            Self::SqlitePool(p) => (run_sqlite(*p, s, fetch).await, None),
            Self::Sqlite(c) => (run_sqlite(&mut **c, s, fetch).await, None),
            Self::PgPool(p, url) => (run_pg(*p, s, fetch).await, Some(*url)),
            Self::Pg(c, url) => (run_pg(&mut **c, s, fetch).await, Some(*url)),
        };
        r.map_err(|e| store_error(server, e))
    }

    /// Runs `s`; returns how many rows it changed.
    pub async fn execute(&mut self, s: Stmt<'_>) -> StoreResult<u64> {
        Ok(self.run(&s, Fetch::Affected).await?.0)
    }

    /// Runs `s`; returns its first row, if any.
    pub async fn fetch_optional(&mut self, s: Stmt<'_>) -> StoreResult<Option<Row>> {
        Ok(self.run(&s, Fetch::Optional).await?.1.pop())
    }

    /// Runs `s`; returns its first row (`RowNotFound` if there is none).
    pub async fn fetch_one(&mut self, s: Stmt<'_>) -> StoreResult<Row> {
        self.fetch_optional(s)
            .await?
            .ok_or(StoreError::Database(sqlx::Error::RowNotFound))
    }

    /// Runs `s`; returns all its rows.
    pub async fn fetch_all(&mut self, s: Stmt<'_>) -> StoreResult<Vec<Row>> {
        Ok(self.run(&s, Fetch::All).await?.1)
    }
}

/// A transaction of either database. Dropped without [`Tx::commit`], it rolls back.
pub enum Tx<'s> {
    /// A SQLite transaction.
    Sqlite(Transaction<'static, Sqlite>),
    /// A PostgreSQL transaction, and the server's URL without the password.
    Postgres(Transaction<'static, Postgres>, &'s str),
}

impl Tx<'_> {
    /// Where the transaction's statements run.
    pub fn conn(&mut self) -> Conn<'_> {
        match self {
            Self::Sqlite(t) => Conn::Sqlite(t),
            Self::Postgres(t, url) => Conn::Pg(t, url),
        }
    }

    /// The dialect of the transaction's database.
    fn dialect(&self) -> Dialect {
        match self {
            Self::Sqlite(_) => Dialect::Sqlite,
            Self::Postgres(..) => Dialect::Postgres,
        }
    }

    /// Runs a script of several statements without values (a migration).
    async fn execute_script(&mut self, sql: &str) -> StoreResult<()> {
        match self {
            Self::Sqlite(t) => {
                sqlx::raw_sql(sql)
                    .execute(&mut **t)
                    .await
                    .map_err(|e| store_error(None, e))?;
            }
            Self::Postgres(t, url) => {
                sqlx::raw_sql(sql)
                    .execute(&mut **t)
                    .await
                    .map_err(|e| store_error(Some(url), e))?;
            }
        }
        Ok(())
    }

    /// Commits the transaction.
    pub async fn commit(self) -> StoreResult<()> {
        match self {
            Self::Sqlite(t) => t.commit().await.map_err(|e| store_error(None, e)),
            Self::Postgres(t, url) => t.commit().await.map_err(|e| store_error(Some(url), e)),
        }
    }
}

/// A write transaction begun by [`SqlBackend::begin_write`], to end with
/// [`SqlBackend::finish_write`] (dropped, it rolls back).
pub struct Write<'s> {
    /// The transaction.
    pub tx: Tx<'s>,
    /// SQLite: the writer's turn, held until the commit marker is written, so that
    /// marker writes follow the order of the commits they record.
    pub turn: Option<tokio::sync::MutexGuard<'s, ()>>,
}

impl Write<'_> {
    /// Where the transaction's statements run.
    pub fn conn(&mut self) -> Conn<'_> {
        self.tx.conn()
    }

    /// [`Conn::execute`] in the transaction.
    async fn execute(&mut self, s: Stmt<'_>) -> StoreResult<u64> {
        self.conn().execute(s).await
    }

    /// [`Conn::fetch_optional`] in the transaction.
    async fn fetch_optional(&mut self, s: Stmt<'_>) -> StoreResult<Option<Row>> {
        self.conn().fetch_optional(s).await
    }
}

/// What a store backend supplies to the shared [`Store`] implementation.
#[async_trait]
pub trait SqlBackend: Send + Sync {
    /// How its database spells what differs.
    const DIALECT: Dialect;

    /// Where reads go (SQLite: the read-only connections; PostgreSQL: the pool).
    fn reader(&self) -> Conn<'_>;

    /// Begins a write transaction (SQLite: takes the writer's turn, `BEGIN IMMEDIATE`;
    /// PostgreSQL: `BEGIN`, then the fencing check).
    async fn begin_write(&self) -> StoreResult<Write<'_>>;

    /// Commits `write`. `recorded`: the write is one the commit marker records (a new
    /// job, a job's state change, a newly stored scene); SQLite then bumps the commit
    /// generation in the transaction and writes the marker once it committed.
    async fn finish_write(&self, write: Write<'_>, recorded: bool) -> StoreResult<()>;

    /// Closes the connections ([`Store::close`]).
    async fn close_pools(&self);
}

/// Creates `schema_version` if needed and applies the missing `migrations` in `tx`,
/// which the caller holds exclusively (SQLite: `BEGIN IMMEDIATE`; PostgreSQL: an
/// advisory lock), so two processes opening one new database cannot both migrate.
/// Applying version `checksum_schema` (the one that adds the `checksum` columns) also
/// fills them for every existing row, in the same transaction ([`backfill_checksums`]).
pub async fn migrate(
    tx: &mut Tx<'_>,
    migrations: &[(i64, &str)],
    checksum_schema: i64,
) -> StoreResult<()> {
    let supported = migrations.last().map_or(0, |m| m.0);
    let ddl = tx.dialect().schema_version_table();
    tx.conn().execute(stmt(ddl)).await?;
    let current = schema_version(&mut tx.conn()).await?;
    if current > supported {
        return Err(StoreError::SchemaTooNew {
            found: current,
            supported,
        });
    }
    for &(version, sql) in migrations.iter().filter(|m| m.0 > current) {
        tx.execute_script(sql).await?;
        tx.conn()
            .execute(
                stmt("INSERT INTO schema_version (version, applied_unix_ms) VALUES ($1, $2)")
                    .bind(version)
                    .bind(now_unix_ms()),
            )
            .await?;
        if version == checksum_schema {
            backfill_checksums(&mut tx.conn()).await?;
        }
    }
    Ok(())
}

/// Computes the checksum of every row of `jobs`, `tiles` and `scenes` that has none (the
/// rows of a store older than the checksums), one row at a time so that a large store
/// is never held in memory. A job row that cannot be decoded keeps no checksum: it is
/// reported as damaged whenever it is read, as it was before.
async fn backfill_checksums(conn: &mut Conn<'_>) -> StoreResult<()> {
    let jobs = conn
        .fetch_all(stmt(
            "SELECT id FROM jobs WHERE checksum IS NULL ORDER BY id",
        ))
        .await?;
    for id in jobs {
        let id: i64 = id.try_get("id")?;
        let row = conn
            .fetch_one(stmt(format!("SELECT {JOB_COLUMNS} FROM jobs WHERE id = $1")).bind(id))
            .await?;
        if let Ok(job) = decode_job(&row) {
            let sum = JobSum::from(&job).checksum();
            conn.execute(
                stmt("UPDATE jobs SET checksum = $2 WHERE id = $1")
                    .bind(id)
                    .bind(sum),
            )
            .await?;
        }
    }
    let tiles = conn
        .fetch_all(stmt(
            "SELECT job, frame, tile FROM tiles WHERE checksum IS NULL ORDER BY job, frame, tile",
        ))
        .await?;
    for key in tiles {
        let (job, frame, tile): (i64, i64, i64) = (
            key.try_get("job")?,
            key.try_get("frame")?,
            key.try_get("tile")?,
        );
        let row = conn
            .fetch_one(
                stmt(format!(
                    "SELECT {TILE_COLUMNS} FROM tiles WHERE job = $1 AND frame = $2 AND tile = $3"
                ))
                .bind(job)
                .bind(frame)
                .bind(tile),
            )
            .await?;
        let (stats, units, adaptive) = tile_blobs(&row)?;
        let sum = tile_sum(&row, &stats, &units, adaptive.as_deref())?.checksum();
        conn.execute(
            stmt("UPDATE tiles SET checksum = $4 WHERE job = $1 AND frame = $2 AND tile = $3")
                .bind(job)
                .bind(frame)
                .bind(tile)
                .bind(sum),
        )
        .await?;
    }
    let scenes = conn
        .fetch_all(stmt(
            "SELECT hash FROM scenes WHERE checksum IS NULL ORDER BY hash",
        ))
        .await?;
    for hash in scenes {
        let hash: String = hash.try_get("hash")?;
        let row = conn
            .fetch_one(stmt("SELECT data FROM scenes WHERE hash = $1").bind(&hash))
            .await?;
        let data: Vec<u8> = row.try_get("data")?;
        conn.execute(
            stmt("UPDATE scenes SET checksum = $2 WHERE hash = $1")
                .bind(&hash)
                .bind(scene_checksum(&hash, &data)),
        )
        .await?;
    }
    Ok(())
}

/// Columns of `tiles` read by [`tile_from_parts`] and [`tile_sum`].
const TILE_COLUMNS: &str =
    "job, frame, tile, merged_passes, stats, units, rejected_samples, adaptive, checksum";

/// The blobs of a `tiles` row: stats, units, adaptive.
type TileBlobs = (Vec<u8>, Vec<u8>, Option<Vec<u8>>);

/// The blobs of a `tiles` row ([`TILE_COLUMNS`]).
fn tile_blobs(row: &Row) -> StoreResult<TileBlobs> {
    Ok((
        row.try_get("stats")?,
        row.try_get("units")?,
        row.try_get("adaptive")?,
    ))
}

/// The checksummed columns of a `tiles` row ([`TILE_COLUMNS`]) as stored.
fn tile_sum<'a>(
    row: &Row,
    stats: &'a [u8],
    units: &'a [u8],
    adaptive: Option<&'a [u8]>,
) -> StoreResult<TileSum<'a>> {
    Ok(TileSum {
        job: row.try_get("job")?,
        frame: row.try_get("frame")?,
        tile: row.try_get("tile")?,
        merged_passes: row.try_get("merged_passes")?,
        rejected_samples: row.try_get("rejected_samples")?,
        stats,
        units,
        adaptive,
    })
}

/// A row that fails its checks (its checksum, or the decoding and plan checks of a read),
/// found by [`damaged_rows`] or [`damaged_tiles`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DamagedRow {
    /// `jobs`, `tiles` or `scenes`.
    pub table: &'static str,
    /// The row's key for people: `job 3`, `job 3, frame 0, tile 5`, `scene HASH`.
    pub key: String,
    /// The job the row belongs to (`None` for a scene) and its state, if readable.
    pub job: Option<(JobId, Option<JobState>)>,
    /// What is wrong (the error a read of the row gives).
    pub reason: String,
}

/// The tiles of `job` that a read refuses (checksum, decoding, the job's plan), one frame
/// at a time: (frame, tile, the error). When the job's plan cannot be read, the
/// checksums alone are checked.
pub async fn damaged_tiles(
    conn: &mut Conn<'_>,
    job: JobId,
) -> StoreResult<Vec<(i64, i64, StoreError)>> {
    let key = to_i64(job, "job id")?;
    let plan = job_plan(conn, job).await.ok();
    let frames = conn
        .fetch_all(stmt("SELECT DISTINCT frame FROM tiles WHERE job = $1 ORDER BY frame").bind(key))
        .await?;
    let mut damaged = Vec::new();
    for f in frames {
        let frame: i64 = f.try_get("frame")?;
        let rows = conn
            .fetch_all(
                stmt(format!(
                    "SELECT {TILE_COLUMNS} FROM tiles WHERE job = $1 AND frame = $2 ORDER BY tile"
                ))
                .bind(key)
                .bind(frame),
            )
            .await?;
        for row in rows {
            let tile: i64 = row.try_get("tile")?;
            let (stats, units, adaptive) = tile_blobs(&row)?;
            let problem = match plan {
                Some((plan, frames)) => tile_from_parts(
                    &plan,
                    frames,
                    job,
                    &row,
                    &stats,
                    &units,
                    adaptive.as_deref(),
                )
                .err(),
                None => {
                    let sum = tile_sum(&row, &stats, &units, adaptive.as_deref())?.checksum();
                    let stored: Option<Vec<u8>> = row.try_get("checksum")?;
                    verify(stored.as_deref(), &sum)
                        .err()
                        .map(|reason| StoreError::CorruptTile {
                            job,
                            frame: u32::try_from(frame).unwrap_or(u32::MAX),
                            tile: u32::try_from(tile).unwrap_or(u32::MAX),
                            reason,
                        })
                }
            };
            if let Some(e) = problem {
                damaged.push((frame, tile, e));
            }
        }
    }
    Ok(damaged)
}

/// Every row of `jobs`, `tiles` and `scenes` that a read refuses: the checks of
/// `tessera store check` (read-only; one job's or scene's rows in memory at a time).
pub async fn damaged_rows(conn: &mut Conn<'_>) -> StoreResult<Vec<DamagedRow>> {
    let mut out = Vec::new();
    let jobs = conn
        .fetch_all(stmt("SELECT id, state FROM jobs ORDER BY id"))
        .await?;
    for j in jobs {
        let id: i64 = j.try_get("id")?;
        let Ok(job) = JobId::try_from(id) else {
            out.push(DamagedRow {
                table: "jobs",
                key: format!("job {id}"),
                job: None,
                reason: format!("negative id {id}"),
            });
            continue;
        };
        let state = parse_state(&j.try_get::<String>("state")?);
        let row = conn
            .fetch_one(stmt(format!("SELECT {JOB_COLUMNS} FROM jobs WHERE id = $1")).bind(id))
            .await?;
        if let Err(e) = job_from_row(&row) {
            out.push(DamagedRow {
                table: "jobs",
                key: format!("job {job}"),
                job: Some((job, state)),
                reason: e.to_string(),
            });
        }
        for (frame, tile, e) in damaged_tiles(conn, job).await? {
            out.push(DamagedRow {
                table: "tiles",
                key: format!("job {job}, frame {frame}, tile {tile}"),
                job: Some((job, state)),
                reason: e.to_string(),
            });
        }
    }
    let scenes = conn
        .fetch_all(stmt("SELECT hash FROM scenes ORDER BY hash"))
        .await?;
    for s in scenes {
        let hash: String = s.try_get("hash")?;
        if let Err(e) = read_scene(conn, &hash).await {
            out.push(DamagedRow {
                table: "scenes",
                key: format!("scene {hash}"),
                job: None,
                reason: e.to_string(),
            });
        }
    }
    Ok(out)
}

/// The bytes of the scene `hash`, checked against the row's checksum.
async fn read_scene(conn: &mut Conn<'_>, hash: &str) -> StoreResult<Option<Vec<u8>>> {
    let Some(row) = conn
        .fetch_optional(stmt("SELECT data, checksum FROM scenes WHERE hash = $1").bind(hash))
        .await?
    else {
        return Ok(None);
    };
    let data: Vec<u8> = row.try_get("data")?;
    let stored: Option<Vec<u8>> = row.try_get("checksum")?;
    verify(stored.as_deref(), &scene_checksum(hash, &data))
        .map_err(|reason| StoreError::Corrupt(format!("scenes row {hash}: {reason}")))?;
    Ok(Some(data))
}

/// The schema version of the database (the newest applied migration; 0 for none).
pub async fn schema_version(conn: &mut Conn<'_>) -> StoreResult<i64> {
    let row = conn
        .fetch_one(stmt("SELECT MAX(version) AS v FROM schema_version"))
        .await?;
    Ok(row.try_get::<Option<i64>>("v")?.unwrap_or(0))
}

/// Reads a row of `counters` in a write transaction (locked until it ends).
async fn counter(w: &mut Write<'_>, name: &str) -> StoreResult<i64> {
    let sql = format!(
        "SELECT value FROM counters WHERE name = $1{}",
        w.tx.dialect().for_update()
    );
    match w.fetch_optional(stmt(sql).bind(name)).await? {
        Some(row) => Ok(row.try_get("value")?),
        None => Err(StoreError::Corrupt(format!(
            "counters: the {name} row is missing"
        ))),
    }
}

/// Sets a row of `counters` in a write transaction.
async fn set_counter(w: &mut Write<'_>, name: &str, value: i64) -> StoreResult<()> {
    let n = w
        .execute(
            stmt("UPDATE counters SET value = $2 WHERE name = $1")
                .bind(name)
                .bind(value),
        )
        .await?;
    if n == 1 {
        Ok(())
    } else {
        Err(StoreError::Corrupt(format!(
            "counters: the {name} row is missing"
        )))
    }
}

/// The plan and frame range of a job.
async fn job_plan(conn: &mut Conn<'_>, job: JobId) -> StoreResult<(FramePlan, FrameRange)> {
    let row = conn
        .fetch_optional(
            stmt(format!("SELECT {PLAN_COLUMNS} FROM jobs WHERE id = $1"))
                .bind(to_i64(job, "job id")?),
        )
        .await?
        .ok_or(StoreError::JobNotFound(job))?;
    plan_from_row(&row, job)
}

/// `SELECT {columns} FROM faults` with the filter's `WHERE` clause and values, then
/// `tail`.
fn faults_stmt<'a>(columns: &str, filter: &'a FaultFilter, tail: &str) -> StoreResult<Stmt<'a>> {
    let (clause, job) = fault_where(filter)?;
    let mut s = stmt(format!("SELECT {columns} FROM faults {clause}{tail}"));
    if let Some(job) = job {
        s = s.bind(job);
    }
    if let Some(worker) = &filter.worker {
        s = s.bind(worker.as_str());
    }
    Ok(s)
}

/// Deletes the tile checkpoints of every queued or running job that a read would refuse
/// (a checksum that does not match, a blob that does not decode or fit the plan), each
/// logged as an error naming the row: the job's resume then finds the tile without a
/// checkpoint and renders its units again, instead of failing the job or merging into
/// damaged statistics (docs/store.md, "Checksums"). Called by [`Store::begin_run`], so a
/// start drops exactly what `tessera store check` reports for such jobs. Checkpoints of
/// finished jobs are kept: their image is refused with the error naming the tile.
async fn drop_damaged_checkpoints<B: SqlBackend>(store: &B) -> StoreResult<()> {
    let jobs = store
        .reader()
        .fetch_all(stmt(
            "SELECT id FROM jobs WHERE state IN ('queued', 'running') ORDER BY id",
        ))
        .await?;
    for j in jobs {
        let id: i64 = j.try_get("id")?;
        let Ok(job) = JobId::try_from(id) else {
            continue;
        };
        let damaged = damaged_tiles(&mut store.reader(), job).await?;
        if damaged.is_empty() {
            continue;
        }
        let mut w = store.begin_write().await?;
        for (frame, tile, e) in &damaged {
            tracing::error!(
                table = "tiles",
                job,
                frame,
                tile,
                error = %e,
                "damaged tile checkpoint dropped; its units are rendered again"
            );
            w.execute(
                stmt("DELETE FROM tiles WHERE job = $1 AND frame = $2 AND tile = $3")
                    .bind(id)
                    .bind(*frame)
                    .bind(*tile),
            )
            .await?;
        }
        store.finish_write(w, false).await?;
    }
    Ok(())
}

/// The [`Store`] contract on a SQL database, once for both backends.
#[async_trait]
impl<B: SqlBackend> Store for B {
    async fn insert_job(&self, job: NewJob) -> StoreResult<(JobId, bool)> {
        let created = check_new_job(&job)?;
        let mut w = self.begin_write().await?;
        let inserted = w
            .fetch_optional(
                stmt(
                    "INSERT INTO jobs (idempotency_key, name, scene_ref, settings_json, \
                         plan_width, plan_height, plan_tile_size, plan_samples_per_pass, \
                         plan_passes, first_frame, last_frame, passes_per_unit, priority, state, \
                         created_unix_ms, render_plan_json, error_estimate_caveat) \
                     VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11, $12, $13, 'queued', \
                         $14, $15, $16) \
                     ON CONFLICT (idempotency_key) DO NOTHING \
                     RETURNING id",
                )
                .bind(job.idempotency_key.as_deref())
                .bind(job.name.as_deref())
                .bind(&job.scene_ref)
                .bind(&job.settings_json)
                .bind(i64::from(job.plan.width))
                .bind(i64::from(job.plan.height))
                .bind(i64::from(job.plan.tile_size))
                .bind(i64::from(job.plan.samples_per_pass))
                .bind(i64::from(job.plan.passes))
                .bind(i64::from(job.frames.start))
                .bind(i64::from(job.frames.end))
                .bind(i64::from(job.passes_per_unit))
                .bind(i64::from(job.priority))
                .bind(created)
                .bind(job.render_plan_json.as_deref())
                .bind(job.error_estimate_caveat.as_deref()),
            )
            .await?;
        let (id, created): (i64, bool) = match inserted {
            Some(row) => {
                let id: i64 = row.try_get("id")?;
                // The id is the database's, so the checksum that covers it is written
                // in a second statement of the same transaction.
                let sum = JobSum {
                    id,
                    idempotency_key: job.idempotency_key.as_deref(),
                    name: job.name.as_deref(),
                    scene_ref: &job.scene_ref,
                    settings_json: &job.settings_json,
                    plan: job.plan,
                    frames: job.frames,
                    passes_per_unit: job.passes_per_unit,
                    priority: job.priority,
                    created_unix_ms: created,
                    render_plan_json: job.render_plan_json.as_deref(),
                    error_estimate_caveat: job.error_estimate_caveat.as_deref(),
                };
                w.execute(
                    stmt("UPDATE jobs SET checksum = $2 WHERE id = $1")
                        .bind(id)
                        .bind(sum.checksum()),
                )
                .await?;
                (id, true)
            }
            None => {
                // Only a conflicting idempotency key makes the insert do nothing; under
                // PostgreSQL's READ COMMITTED this statement sees the conflicting row,
                // committed.
                let row = w
                    .conn()
                    .fetch_one(
                        stmt("SELECT id FROM jobs WHERE idempotency_key = $1")
                            .bind(job.idempotency_key.as_deref()),
                    )
                    .await?;
                (row.try_get("id")?, false)
            }
        };
        self.finish_write(w, created).await?;
        let id = JobId::try_from(id)
            .map_err(|_| StoreError::Corrupt(format!("jobs: negative id {id}")))?;
        Ok((id, created))
    }

    async fn get_job(&self, id: JobId) -> StoreResult<Option<JobRecord>> {
        let Ok(key) = i64::try_from(id) else {
            return Ok(None);
        };
        self.reader()
            .fetch_optional(stmt(format!("SELECT {JOB_COLUMNS} FROM jobs WHERE id = $1")).bind(key))
            .await?
            .as_ref()
            .map(job_from_row)
            .transpose()
    }

    async fn list_jobs(&self, query: JobQuery) -> StoreResult<Vec<JobRecord>> {
        if query.limit == 0 {
            return Ok(Vec::new());
        }
        let (cmp, dir, default_cursor) = match query.order {
            JobOrder::NewestFirst => ("<", "DESC", i64::MAX),
            JobOrder::OldestFirst => (">", "ASC", 0),
        };
        let cursor = match (query.cursor.map(i64::try_from), query.order) {
            (None, _) => default_cursor,
            (Some(Ok(c)), _) => c,
            // A cursor above every possible id: all ids come after it newest first, none
            // oldest first.
            (Some(Err(_)), JobOrder::NewestFirst) => i64::MAX,
            (Some(Err(_)), JobOrder::OldestFirst) => return Ok(Vec::new()),
        };
        // The casts give PostgreSQL the type of a parameter that may be NULL.
        let sql = format!(
            "SELECT {JOB_COLUMNS} FROM jobs WHERE id {cmp} $1 \
             AND (CAST($2 AS TEXT) IS NULL OR state = CAST($2 AS TEXT)) \
             ORDER BY id {dir} LIMIT $3"
        );
        let rows = self
            .reader()
            .fetch_all(
                stmt(sql)
                    .bind(cursor)
                    .bind(query.state.map(JobState::as_str))
                    .bind(i64::from(query.limit)),
            )
            .await?;
        rows.iter().map(job_from_row).collect()
    }

    async fn set_job_state(
        &self,
        id: JobId,
        state: JobState,
        error: Option<String>,
        now_unix_ms: u64,
    ) -> StoreResult<bool> {
        let key = i64::try_from(id).map_err(|_| StoreError::JobNotFound(id))?;
        let now = to_i64(now_unix_ms, "now_unix_ms")?;
        let mut w = self.begin_write().await?;
        let changed = w
            .execute(
                stmt(
                    "UPDATE jobs SET state = CAST($2 AS TEXT), error = $3, \
                         started_unix_ms = CASE WHEN CAST($2 AS TEXT) = 'running' \
                             AND started_unix_ms IS NULL THEN $4 ELSE started_unix_ms END, \
                         finished_unix_ms = CASE WHEN CAST($2 AS TEXT) \
                             IN ('done', 'failed', 'canceled') \
                             THEN $4 ELSE finished_unix_ms END \
                     WHERE id = $1 AND state IN ('queued', 'running')",
                )
                .bind(key)
                .bind(state.as_str())
                .bind(error.as_deref())
                .bind(now),
            )
            .await?
            > 0;
        let exists = changed
            || w.fetch_optional(stmt("SELECT 1 AS one FROM jobs WHERE id = $1").bind(key))
                .await?
                .is_some();
        self.finish_write(w, changed).await?;
        if exists {
            Ok(changed)
        } else {
            Err(StoreError::JobNotFound(id))
        }
    }

    async fn count_jobs_by_state(&self) -> StoreResult<Vec<(JobState, u64)>> {
        let rows = self
            .reader()
            .fetch_all(stmt("SELECT state, COUNT(*) AS n FROM jobs GROUP BY state"))
            .await?;
        rows.iter().map(state_count_from_row).collect()
    }

    async fn jobs_to_resume(&self) -> StoreResult<Vec<JobRecord>> {
        let rows = self
            .reader()
            .fetch_all(stmt(format!(
                "SELECT {JOB_COLUMNS} FROM jobs WHERE state IN ('queued', 'running') ORDER BY id"
            )))
            .await?;
        rows.iter().map(job_from_row).collect()
    }

    async fn put_scene(&self, hash: &str, bytes: &[u8]) -> StoreResult<bool> {
        if hash.is_empty() {
            return Err(StoreError::InvalidInput("scene hash is empty".into()));
        }
        let size = to_i64(bytes.len() as u64, "scene size")?;
        let mut w = self.begin_write().await?;
        let stored = w
            .execute(
                stmt(
                    "INSERT INTO scenes (hash, size, data, stored_unix_ms, checksum) \
                     VALUES ($1, $2, $3, $4, $5) ON CONFLICT (hash) DO NOTHING",
                )
                .bind(hash)
                .bind(size)
                .bind(bytes)
                .bind(now_unix_ms())
                .bind(scene_checksum(hash, bytes)),
            )
            .await?
            > 0;
        self.finish_write(w, stored).await?;
        Ok(stored)
    }

    async fn get_scene(&self, hash: &str) -> StoreResult<Option<Vec<u8>>> {
        read_scene(&mut self.reader(), hash).await
    }

    async fn scene_exists(&self, hash: &str) -> StoreResult<bool> {
        // The key alone: the scene's bytes are not read.
        Ok(self
            .reader()
            .fetch_optional(stmt("SELECT 1 AS one FROM scenes WHERE hash = $1").bind(hash))
            .await?
            .is_some())
    }

    async fn scene_bytes(&self, owner: Option<&str>) -> StoreResult<u64> {
        super::scene_quota::scene_bytes(self, owner).await
    }

    async fn record_scene_upload(&self, hash: &str, owner: &str) -> StoreResult<()> {
        super::scene_quota::record_scene_upload(self, hash, owner).await
    }

    async fn delete_scene(&self, hash: &str) -> StoreResult<super::SceneDeletion> {
        super::scene_quota::delete_scene(self, hash).await
    }

    async fn unused_scenes(&self, cutoff_unix_ms: u64, limit: u32) -> StoreResult<Vec<String>> {
        super::scene_quota::unused_scenes(self, cutoff_unix_ms, limit).await
    }

    async fn save_tiles(&self, tiles: &[TileCheckpointRef<'_>]) -> StoreResult<()> {
        if tiles.is_empty() {
            return Ok(());
        }
        let mut w = self.begin_write().await?;
        let mut plans: Vec<(JobId, FramePlan, FrameRange)> = Vec::new();
        for t in tiles {
            let (plan, frames) = match plans.iter().find(|p| p.0 == t.job) {
                Some(&(_, plan, frames)) => (plan, frames),
                None => {
                    let (plan, frames) = job_plan(&mut w.conn(), t.job).await?;
                    plans.push((t.job, plan, frames));
                    (plan, frames)
                }
            };
            check_tile_to_save(&plan, frames, t)?;
            let (stats, units) = (encode_stats(t.pixels), encode_units(t.units));
            let adaptive = t.adaptive.map(encode_adaptive);
            let sum = TileSum {
                job: to_i64(t.job, "job id")?,
                frame: i64::from(t.frame),
                tile: i64::from(t.tile),
                merged_passes: i64::from(t.merged_passes),
                rejected_samples: to_i64(t.rejected_samples, "rejected_samples")?,
                stats: &stats,
                units: &units,
                adaptive: adaptive.as_deref(),
            };
            let checksum = sum.checksum();
            w.execute(
                stmt(
                    "INSERT INTO tiles (job, frame, tile, merged_passes, stats, units, \
                         rejected_samples, adaptive, checksum) \
                     VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9) \
                     ON CONFLICT (job, frame, tile) DO UPDATE SET \
                         merged_passes = excluded.merged_passes, \
                         stats = excluded.stats, \
                         units = excluded.units, \
                         rejected_samples = excluded.rejected_samples, \
                         adaptive = excluded.adaptive, \
                         checksum = excluded.checksum",
                )
                .bind(sum.job)
                .bind(sum.frame)
                .bind(sum.tile)
                .bind(sum.merged_passes)
                .bind(&stats[..])
                .bind(&units[..])
                .bind(sum.rejected_samples)
                .bind(adaptive.as_deref())
                .bind(checksum),
            )
            .await?;
        }
        self.finish_write(w, false).await
    }

    async fn load_tiles(&self, job: JobId, frame: Option<u32>) -> StoreResult<Vec<TileCheckpoint>> {
        let key = i64::try_from(job).map_err(|_| StoreError::JobNotFound(job))?;
        let (plan, frames) = job_plan(&mut self.reader(), job).await?;
        let rows = self
            .reader()
            .fetch_all(
                stmt(format!(
                    "SELECT {TILE_COLUMNS} FROM tiles WHERE job = $1 \
                     AND (CAST($2 AS BIGINT) IS NULL OR frame = CAST($2 AS BIGINT)) \
                     ORDER BY frame, tile"
                ))
                .bind(key)
                .bind(frame.map(i64::from)),
            )
            .await?;
        rows.iter()
            .map(|row| {
                let stats: Vec<u8> = row.try_get("stats")?;
                let units: Vec<u8> = row.try_get("units")?;
                let adaptive: Option<Vec<u8>> = row.try_get("adaptive")?;
                tile_from_parts(&plan, frames, job, row, &stats, &units, adaptive.as_deref())
            })
            .collect()
    }

    async fn tile_summaries(&self, job: JobId) -> StoreResult<Vec<TileSummary>> {
        let key = i64::try_from(job).map_err(|_| StoreError::JobNotFound(job))?;
        let rows = self
            .reader()
            .fetch_all(
                stmt(
                    "SELECT frame, tile, merged_passes, rejected_samples FROM tiles \
                     WHERE job = $1 ORDER BY frame, tile",
                )
                .bind(key),
            )
            .await?;
        rows.iter().map(|row| summary_from_row(row, job)).collect()
    }

    async fn max_lease_id(&self) -> StoreResult<u64> {
        let row = self
            .reader()
            .fetch_optional(stmt(
                "SELECT value FROM counters WHERE name = 'lease_high_water'",
            ))
            .await?;
        let v: i64 = row
            .ok_or_else(|| {
                StoreError::Corrupt("counters: the lease_high_water row is missing".into())
            })?
            .try_get("value")?;
        u64::try_from(v)
            .map_err(|_| StoreError::Corrupt(format!("counters: lease_high_water = {v}")))
    }

    async fn record_lease_high_water(&self, lease_id: u64) -> StoreResult<()> {
        let v = to_i64(lease_id, "lease id")?;
        // Fenced like every write: a deposed PostgreSQL coordinator reserves no more
        // lease ids, so the new one's ids start above everything this one could grant.
        let mut w = self.begin_write().await?;
        // One statement: the row lock makes concurrent raises keep the largest value.
        let sql = format!(
            "UPDATE counters SET value = {}(value, $1) WHERE name = 'lease_high_water'",
            B::DIALECT.greatest()
        );
        if w.execute(stmt(sql).bind(v)).await? != 1 {
            return Err(StoreError::Corrupt(
                "counters: the lease_high_water row is missing".into(),
            ));
        }
        // Recorded in the commit marker too (SQLite): a reservation lost with a `-wal`
        // file would let fencing tokens repeat. Reservations come in blocks, so this is
        // one marker write per block.
        self.finish_write(w, true).await
    }

    async fn fence_key(&self, fresh: [u8; 32]) -> StoreResult<[u8; 32]> {
        // Kept if absent, in one write: concurrent coordinators agree on one key (the
        // primary key makes a later insert do nothing), and every later call returns it.
        let mut w = self.begin_write().await?;
        let mut key = [0u8; 32];
        for (i, (word, out)) in fresh
            .chunks_exact(8)
            .zip(key.chunks_exact_mut(8))
            .enumerate()
        {
            let name = format!("fence_key_{i}");
            let v = i64::from_le_bytes(word.try_into().expect("8 bytes"));
            w.execute(
                stmt("INSERT INTO counters (name, value) VALUES ($1, $2) ON CONFLICT (name) DO NOTHING")
                    .bind(&name)
                    .bind(v),
            )
            .await?;
            let kept: i64 = w
                .fetch_optional(stmt("SELECT value FROM counters WHERE name = $1").bind(&name))
                .await?
                .ok_or_else(|| StoreError::Corrupt(format!("counters: the {name} row is missing")))?
                .try_get("value")?;
            out.copy_from_slice(&kept.to_le_bytes());
        }
        self.finish_write(w, false).await?;
        Ok(key)
    }

    async fn append_history(&self, job: JobId, point: HistoryPoint) -> StoreResult<()> {
        let key = i64::try_from(job).map_err(|_| StoreError::JobNotFound(job))?;
        let elapsed = check_finite(point.elapsed_seconds, "history elapsed_seconds")?;
        let spp = check_finite(point.spp, "history spp")?;
        let error = point
            .error_estimate
            .map(|e| check_finite(e, "history error_estimate"))
            .transpose()?;
        let mut w = self.begin_write().await?;
        let n = w
            .execute(
                stmt(
                    "INSERT INTO history (job, elapsed_seconds, spp, error_estimate) \
                     SELECT $1, $2, $3, $4 WHERE EXISTS (SELECT 1 FROM jobs WHERE id = $1)",
                )
                .bind(key)
                .bind(elapsed)
                .bind(spp)
                .bind(error),
            )
            .await?;
        if n == 0 {
            return Err(StoreError::JobNotFound(job));
        }
        self.finish_write(w, false).await
    }

    async fn list_history(&self, job: JobId) -> StoreResult<Vec<HistoryPoint>> {
        let Ok(key) = i64::try_from(job) else {
            return Ok(Vec::new());
        };
        let rows = self
            .reader()
            .fetch_all(
                stmt(
                    "SELECT elapsed_seconds, spp, error_estimate FROM history \
                     WHERE job = $1 ORDER BY seq",
                )
                .bind(key),
            )
            .await?;
        rows.iter()
            .map(|r| {
                Ok(HistoryPoint {
                    elapsed_seconds: r.try_get("elapsed_seconds")?,
                    spp: r.try_get("spp")?,
                    error_estimate: r.try_get("error_estimate")?,
                })
            })
            .collect()
    }

    async fn record_fault(&self, fault: &FaultEvent) -> StoreResult<()> {
        let job = fault.job.map(|j| to_i64(j, "fault job")).transpose()?;
        let unix_ms = to_i64(fault.unix_ms, "fault unix_ms")?;
        let mut w = self.begin_write().await?;
        w.execute(
            stmt(
                "INSERT INTO faults (worker, job, kind, message, unix_ms) \
                 VALUES ($1, $2, $3, $4, $5)",
            )
            .bind(&fault.worker)
            .bind(job)
            .bind(fault.kind.as_str())
            .bind(&fault.message)
            .bind(unix_ms),
        )
        .await?;
        self.finish_write(w, false).await
    }

    async fn count_faults(&self, filter: &FaultFilter) -> StoreResult<u64> {
        let s = faults_stmt("COUNT(*) AS n", filter, "")?;
        let row = self.reader().fetch_one(s).await?;
        int_col(&row, "n", &|| "faults".to_string())
    }

    async fn list_faults(&self, filter: &FaultFilter, limit: u32) -> StoreResult<Vec<FaultEvent>> {
        let tail = format!(" ORDER BY id DESC LIMIT {limit}");
        let s = faults_stmt("worker, job, kind, message, unix_ms", filter, &tail)?;
        let rows = self.reader().fetch_all(s).await?;
        rows.iter().map(fault_from_row).collect()
    }

    async fn record_quarantine(&self, q: &QuarantineRecord) -> StoreResult<bool> {
        let unix_ms = to_i64(q.unix_ms, "quarantine unix_ms")?;
        let mut w = self.begin_write().await?;
        let n = w
            .execute(
                stmt(
                    "INSERT INTO quarantines (worker, identity, reason, unix_ms) \
                     VALUES ($1, $2, $3, $4) ON CONFLICT (worker, identity) DO NOTHING",
                )
                .bind(&q.worker)
                .bind(identity_col(q.identity.as_deref()))
                .bind(&q.reason)
                .bind(unix_ms),
            )
            .await?;
        self.finish_write(w, false).await?;
        Ok(n == 1)
    }

    async fn list_quarantines(&self) -> StoreResult<Vec<QuarantineRecord>> {
        let c = B::DIALECT.byte_order();
        let sql =
            format!("SELECT {QUARANTINE_COLUMNS} FROM quarantines ORDER BY worker{c}, identity{c}");
        let rows = self.reader().fetch_all(stmt(sql)).await?;
        rows.iter().map(quarantine_from_row).collect()
    }

    async fn delete_quarantines(&self, worker: &str) -> StoreResult<u64> {
        let mut w = self.begin_write().await?;
        let n = w
            .execute(stmt("DELETE FROM quarantines WHERE worker = $1").bind(worker))
            .await?;
        self.finish_write(w, false).await?;
        Ok(n)
    }

    async fn job_ids_to_resume(&self) -> StoreResult<Vec<JobId>> {
        let rows = self
            .reader()
            .fetch_all(stmt(
                "SELECT id FROM jobs WHERE state IN ('queued', 'running') ORDER BY id",
            ))
            .await?;
        rows.iter()
            .map(|row| {
                let id: i64 = row.try_get("id")?;
                JobId::try_from(id).map_err(|_| StoreError::Corrupt(format!("jobs: id {id}")))
            })
            .collect()
    }

    async fn begin_run(&self) -> StoreResult<PreviousRun> {
        let mut w = self.begin_write().await?;
        let clean = counter(&mut w, "clean_shutdown").await? != 0;
        let resuming = counter(&mut w, "resuming_job").await?;
        set_counter(&mut w, "clean_shutdown", 0).await?;
        self.finish_write(w, false).await?;
        drop_damaged_checkpoints(self).await?;
        Ok(PreviousRun {
            clean,
            resuming: u64::try_from(resuming).ok().filter(|&j| j > 0),
        })
    }

    async fn end_run(&self) -> StoreResult<()> {
        let mut w = self.begin_write().await?;
        set_counter(&mut w, "clean_shutdown", 1).await?;
        set_counter(&mut w, "resuming_job", 0).await?;
        self.finish_write(w, false).await
    }

    async fn record_resume(&self, job: JobId, count: bool) -> StoreResult<u32> {
        let key = i64::try_from(job).map_err(|_| StoreError::JobNotFound(job))?;
        let mut w = self.begin_write().await?;
        // The cast: PostgreSQL sums BIGINTs as NUMERIC.
        let sql = format!(
            "SELECT resumes, resume_passes, \
                 (SELECT CAST(COALESCE(SUM(merged_passes), 0) AS BIGINT) FROM tiles \
                     WHERE job = $1) AS merged \
             FROM jobs WHERE id = $1{}",
            B::DIALECT.for_update()
        );
        let row = w
            .fetch_optional(stmt(sql).bind(key))
            .await?
            .ok_or(StoreError::JobNotFound(job))?;
        let place = || format!("jobs row {job}");
        let resumes: u32 = int_col(&row, "resumes", &place)?;
        let before: i64 = row.try_get("resume_passes")?;
        let merged: i64 = row.try_get("merged")?;
        // Any change of the merged passes is progress (an adaptive job starts again from
        // its first pass after a restart, so its total can also go down).
        let resumes = if merged != before { 0 } else { resumes };
        let resumes = resumes.saturating_add(u32::from(count));
        w.execute(
            stmt("UPDATE jobs SET resumes = $2, resume_passes = $3 WHERE id = $1")
                .bind(key)
                .bind(i64::from(resumes))
                .bind(merged),
        )
        .await?;
        set_counter(&mut w, "resuming_job", key).await?;
        self.finish_write(w, false).await?;
        Ok(resumes)
    }

    async fn resumes_done(&self) -> StoreResult<()> {
        let mut w = self.begin_write().await?;
        set_counter(&mut w, "resuming_job", 0).await?;
        self.finish_write(w, false).await
    }

    async fn ping(&self) -> StoreResult<()> {
        self.reader().execute(stmt("SELECT 1")).await?;
        Ok(())
    }

    async fn close(&self) {
        self.close_pools().await;
    }
}
