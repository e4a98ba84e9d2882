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

mod integrity;
mod store;

pub use integrity::{damaged_rows, migrate, DamagedRow};

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
    JOB_COLUMNS, JOB_COLUMNS_BEFORE_ESTIMATOR, PLAN_COLUMNS, QUARANTINE_COLUMNS,
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
