//! The SQLite implementation of [`Store`](super::Store): its connections, checks at
//! open, migrations and commit marker; the statements are the shared SQL layer's
//! ([`sql`](super::sql)).

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use async_trait::async_trait;
use sqlx::sqlite::{
    SqliteConnectOptions, SqliteJournalMode, SqlitePool, SqlitePoolOptions, SqliteSynchronous,
};
use sqlx::Connection;

use super::marker::{self, CommitMark};
use super::rows::int_col;
use super::sql::{self, stmt, Conn, Dialect, SqlBackend, Tx, Write};
use super::{StoreError, StoreResult};

/// Name of the database file inside the data directory.
pub const DATABASE_FILE: &str = "tessera.sqlite3";

/// Schema migrations: (version, SQL). Applied in order, each in the same transaction as
/// the bump of `schema_version`. Never edit a released migration; append a new one.
const MIGRATIONS: &[(i64, &str)] = &[
    (1, include_str!("migrations/0001_initial.sql")),
    (2, include_str!("migrations/0002_rejected_samples.sql")),
    (3, include_str!("migrations/0003_integrity.sql")),
    (4, include_str!("migrations/0004_adaptive_policy.sql")),
    (5, include_str!("migrations/0005_quarantine.sql")),
    (6, include_str!("migrations/0006_render_plan.sql")),
    (
        CHECKSUM_SCHEMA,
        include_str!("migrations/0007_checksums.sql"),
    ),
    (8, include_str!("migrations/0008_scene_uploads.sql")),
    (9, include_str!("migrations/0009_error_estimator.sql")),
];

/// The schema version that added row checksums (filled for existing rows as it is
/// applied).
const CHECKSUM_SCHEMA: i64 = 7;

/// A job resumed this many times in a row after a crash without a new merged pass is
/// failed instead of resumed again (docs/store.md, "No crash loop").
pub const MAX_RESUMES_WITHOUT_PROGRESS: u32 = 5;

/// How long a statement waits for a lock held by another connection before failing.
const BUSY_TIMEOUT: Duration = Duration::from_secs(10);

/// Read connections. SQLite serializes writers, so there is exactly one write connection.
const READ_CONNECTIONS: u32 = 4;

/// The farm's state in one SQLite file, `DIR/tessera.sqlite3`.
///
/// The database runs in WAL mode with `synchronous=FULL` (every commit is fsynced before it
/// returns, so a committed write survives `kill -9` and power loss) and foreign keys on.
/// All writes go through one connection (SQLite allows one writer at a time; serializing
/// them in-process avoids lock contention), each write transaction starting with
/// `BEGIN IMMEDIATE`; reads use a small pool of `query_only` connections and proceed
/// concurrently with writes. One coordinator process per data directory.
///
/// The statements are the shared SQL layer's (`store/sql/`), as for
/// [`PostgresStore`](super::PostgresStore).
///
/// Cloning is cheap and shares the connections.
#[derive(Debug, Clone)]
pub struct SqliteStore {
    writer: SqlitePool,
    reader: SqlitePool,
    /// Held by a write from its `BEGIN IMMEDIATE` until its commit is recorded in the
    /// marker, so the marker follows the commits in order.
    turn: Arc<tokio::sync::Mutex<()>>,
    path: PathBuf,
    dir: PathBuf,
}

impl SqliteStore {
    /// The newest schema version this build knows (and migrates every store to).
    pub const SUPPORTED_SCHEMA: i64 = MIGRATIONS[MIGRATIONS.len() - 1].0;

    /// Opens (creating if needed) the store in `dir`, refusing a store the coordinator
    /// must not run on (docs/store.md, "What is checked at start"):
    ///
    /// 1. creates the directory and opens (or creates) `dir/tessera.sqlite3`;
    /// 2. the checks of [`preflight`], which `tessera store check` runs too, so that
    ///    both refuse the same stores with the same message: SQLite's full
    ///    `integrity_check` ([`StoreError::Damaged`]), the schema version
    ///    ([`StoreError::SchemaTooNew`]), the commit marker ([`StoreError::BadMarker`],
    ///    [`StoreError::BehindMarker`], [`StoreError::MarkerMissing`]);
    /// 3. brings the schema up to date (computing the checksums of older rows);
    /// 4. probes a write: one committed transaction and a marker write
    ///    ([`StoreError::NotWritable`] for a read-only file, directory or filesystem, or a
    ///    full disk), so such a store fails here rather than at the first request;
    /// 5. copies the WAL into the main database file, so the file itself carries a
    ///    generation above 0 and a later loss of both the marker and the `-wal` file is
    ///    refused ([`marker`]).
    pub async fn open(dir: &Path) -> StoreResult<Self> {
        let (writer, path) = connect_writer(dir, true).await?;
        // Checked before migrating: a database that lost everything (even its schema)
        // is refused as it is, not first filled with an empty schema.
        let had_marker = preflight(&writer, &path, Some(dir)).await?.is_some();
        migrate(&writer).await.map_err(|e| classify(&path, e))?;
        let store = Self::from_writer(writer, path, dir).await?;
        if !had_marker {
            // A new store (or one of a build before the marker): the marker is written
            // before the generation first rises, so a crash right after that rise does
            // not leave a database with a generation and no marker.
            let mark = store.commit_mark().await?;
            store.publish(mark).await?;
        }
        // The write probe: a generation bump, committed, then recorded in the marker.
        let mut conn = store.writer.acquire().await?;
        let mut tx = conn
            .begin_with("BEGIN IMMEDIATE")
            .await
            .map_err(|e| store.probe_error(e))?;
        let mark = bump_generation(&mut Conn::Sqlite(&mut tx))
            .await
            .map_err(|e| store.probe_error(e))?;
        tx.commit().await.map_err(|e| store.probe_error(e))?;
        store.publish(mark).await?;
        drop(conn);
        sqlx::query("PRAGMA wal_checkpoint(TRUNCATE)")
            .execute(&store.writer)
            .await
            .map_err(|e| store.probe_error(e))?;
        Ok(store)
    }

    /// Opens the existing store in `dir` for reading only, for a coordinator that starts
    /// on a full disk (docs/store.md, "When the disk is full"): nothing is created or
    /// written, no migration runs, every write fails (`READONLY`). SQLite's WAL mode needs
    /// a writable shared-memory file even to read; when the database has no WAL content
    /// (the last coordinator stopped cleanly, or its WAL was checkpointed) the file is
    /// opened `immutable`, needing none. Otherwise the existing `-wal` and `-shm` files are
    /// read in place (`mode=ro`), and if even that needs space, the database alone is read
    /// `immutable`, without the commits still in its WAL (logged as a warning: they come
    /// back once space is freed and the store is opened normally).
    ///
    /// Refused with [`StoreError::NotWritable`] (`detail` says why) when there is no
    /// database yet, or its schema is not this build's (a start on a full disk migrates
    /// nothing).
    pub async fn open_read_only(dir: &Path) -> StoreResult<Self> {
        let path = dir.join(DATABASE_FILE);
        let refuse = |detail: String| StoreError::NotWritable {
            path: path.clone(),
            detail,
        };
        if !path.is_file() {
            return Err(refuse(
                "there is no store to read yet and none can be created".into(),
            ));
        }
        let wal = PathBuf::from(format!("{}-wal", path.display()));
        let wal_empty = std::fs::metadata(&wal).map_or(true, |m| m.len() == 0);
        let base = || {
            SqliteConnectOptions::new()
                .filename(&path)
                .read_only(true)
                .foreign_keys(true)
                .busy_timeout(BUSY_TIMEOUT)
        };
        let connect = |options: SqliteConnectOptions| async move {
            SqlitePoolOptions::new()
                .max_connections(READ_CONNECTIONS)
                .connect_with(options)
                .await
        };
        let pool = if wal_empty {
            connect(base().immutable(true)).await
        } else {
            let in_place = match connect(base()).await {
                Ok(pool) => match sqlx::query("SELECT 1 FROM counters LIMIT 1")
                    .execute(&pool)
                    .await
                {
                    Ok(_) => Ok(pool),
                    Err(e) => {
                        pool.close().await;
                        Err(e)
                    }
                },
                Err(e) => Err(e),
            };
            match in_place {
                Ok(pool) => Ok(pool),
                Err(e) => {
                    tracing::warn!(
                        error = %e,
                        "the store's WAL cannot be read without free space: serving the \
                         database without its newest commits until space is freed"
                    );
                    connect(base().immutable(true)).await
                }
            }
        }
        .map_err(|e| refuse(format!("cannot open it read-only: {e}")))?;
        let version = sql::schema_version(&mut Conn::SqlitePool(&pool))
            .await
            .map_err(|e| refuse(format!("cannot read it: {e}")))?;
        if version != Self::SUPPORTED_SCHEMA {
            return Err(refuse(format!(
                "its schema version {version} is not this build's {}: it is migrated at \
                 the next start with free space",
                Self::SUPPORTED_SCHEMA
            )));
        }
        Ok(Self {
            writer: pool.clone(),
            reader: pool,
            turn: Arc::default(),
            path,
            dir: dir.to_path_buf(),
        })
    }

    /// The store over an open writer pool, without any check (for the maintenance
    /// commands, which check what they need themselves).
    pub(super) async fn from_writer(
        writer: SqlitePool,
        path: PathBuf,
        dir: &Path,
    ) -> StoreResult<Self> {
        let reader = SqlitePoolOptions::new()
            .max_connections(READ_CONNECTIONS)
            .connect_with(connect_options(&path).pragma("query_only", "ON"))
            .await
            .map_err(|e| open_error(&path, e))?;
        Ok(Self {
            writer,
            reader,
            turn: Arc::default(),
            path,
            dir: dir.to_path_buf(),
        })
    }

    /// The write probe's failure: a write failure makes the store not writable.
    fn probe_error(&self, e: impl Into<StoreError>) -> StoreError {
        let e = e.into();
        if e.is_write_failure() {
            StoreError::NotWritable {
                path: self.path.clone(),
                detail: e.to_string(),
            }
        } else {
            e
        }
    }

    /// Records `mark` in the commit marker (off the async runtime: it fsyncs).
    pub(super) async fn publish(&self, mark: CommitMark) -> StoreResult<()> {
        let dir = self.dir.clone();
        let not_writable = |detail: String| StoreError::NotWritable {
            path: marker::marker_path(&self.dir),
            detail,
        };
        tokio::task::spawn_blocking(move || marker::write_marker(&dir, mark))
            .await
            .map_err(|e| not_writable(e.to_string()))?
            .map_err(|e| not_writable(e.to_string()))
    }

    /// The database's commit generation and highest job id ever issued.
    pub async fn commit_mark(&self) -> StoreResult<CommitMark> {
        commit_mark(&mut self.reader()).await
    }

    /// The writer pool (for the maintenance commands).
    pub(super) fn writer(&self) -> &SqlitePool {
        &self.writer
    }

    /// Path of the database file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The schema version of the database (the newest applied migration).
    pub async fn schema_version(&self) -> StoreResult<i64> {
        sql::schema_version(&mut self.reader()).await
    }

    /// Runs SQLite's full `PRAGMA integrity_check` (as the start does, [`preflight`]);
    /// [`StoreError::Damaged`] lists the problems.
    pub async fn integrity_check(&self) -> StoreResult<()> {
        run_check(&self.reader, &self.path, "integrity_check").await
    }
}

/// The connection options of every connection to `path`.
fn connect_options(path: &Path) -> SqliteConnectOptions {
    SqliteConnectOptions::new()
        .filename(path)
        .journal_mode(SqliteJournalMode::Wal)
        .synchronous(SqliteSynchronous::Full)
        .foreign_keys(true)
        .busy_timeout(BUSY_TIMEOUT)
}

/// Creates `dir` if needed and opens the one write connection to its database (creating
/// the file if `create`). Returns it with the database's path.
pub(super) async fn connect_writer(dir: &Path, create: bool) -> StoreResult<(SqlitePool, PathBuf)> {
    std::fs::create_dir_all(dir).map_err(|source| StoreError::DataDir {
        path: dir.to_path_buf(),
        source,
    })?;
    let path = dir.join(DATABASE_FILE);
    let writer = SqlitePoolOptions::new()
        .max_connections(1)
        .connect_with(connect_options(&path).create_if_missing(create))
        .await
        .map_err(|e| open_error(&path, e))?;
    Ok((writer, path))
}

/// [`open_error`] of a store error that is a database error; others pass through.
pub(super) fn classify(path: &Path, e: StoreError) -> StoreError {
    match e {
        StoreError::Database(e) => open_error(path, e),
        e => e,
    }
}

/// An error while opening `path`: a damaged file and an unwritable one get their own
/// variants (with the recovery steps); anything else stays a database error.
pub(super) fn open_error(path: &Path, e: sqlx::Error) -> StoreError {
    const CORRUPT: i64 = 11;
    const NOTADB: i64 = 26;
    let code = match &e {
        sqlx::Error::Database(d) => d.code().and_then(|c| c.parse::<i64>().ok()),
        _ => None,
    };
    let e = StoreError::Database(e);
    match code.map(|c| c & 0xff) {
        Some(CORRUPT | NOTADB) => StoreError::Damaged {
            path: path.to_path_buf(),
            detail: e.to_string(),
        },
        _ if e.is_write_failure() => StoreError::NotWritable {
            path: path.to_path_buf(),
            detail: e.to_string(),
        },
        _ => e,
    }
}

/// Runs `PRAGMA quick_check` (every page and record well-formed; not the index
/// cross-check of `integrity_check`, measured in docs/store.md).
pub(super) async fn quick_check(pool: &SqlitePool, path: &Path) -> StoreResult<()> {
    run_check(pool, path, "quick_check").await
}

/// The checks a coordinator's start makes before it changes anything, in order, the
/// first failure returned (docs/store.md, "What is checked at start"); `tessera store
/// check` runs the same function on a read-only connection, so what it reports as a
/// refusal is exactly what the start refuses, with the same message:
///
/// 1. SQLite's full `integrity_check`, including the cross-check of every index against
///    its table ([`StoreError::Damaged`]): an index that lost or gained entries passes
///    `quick_check` but makes queries fail or miss rows;
/// 2. the schema version is one this build knows ([`StoreError::SchemaTooNew`]);
/// 3. with `dir` (the data directory; `None` for a backup file): the commit marker can
///    be read ([`StoreError::BadMarker`]), the database is not behind it
///    ([`StoreError::BehindMarker`]), and a database with a commit generation has one
///    ([`StoreError::MarkerMissing`]).
///
/// Returns the marker, if there is one.
pub(super) async fn preflight(
    pool: &SqlitePool,
    path: &Path,
    dir: Option<&Path>,
) -> StoreResult<Option<CommitMark>> {
    run_check(pool, path, "integrity_check").await?;
    let no_table = |e: &StoreError| {
        matches!(e, StoreError::Database(sqlx::Error::Database(d))
            if d.message().contains("no such table"))
    };
    let found = match sql::schema_version(&mut Conn::SqlitePool(pool)).await {
        Ok(v) => v,
        Err(e) if no_table(&e) => 0,
        Err(e) => return Err(classify(path, e)),
    };
    if found > SqliteStore::SUPPORTED_SCHEMA {
        return Err(StoreError::SchemaTooNew {
            found,
            supported: SqliteStore::SUPPORTED_SCHEMA,
        });
    }
    let Some(dir) = dir else {
        return Ok(None);
    };
    let marker = marker::read_marker(dir).map_err(StoreError::BadMarker)?;
    // A database without the generation (empty, or older than schema 3) has none.
    let db = match commit_mark(&mut Conn::SqlitePool(pool)).await {
        Ok(db) => db,
        Err(e) if no_table(&e) => CommitMark::default(),
        Err(StoreError::Corrupt(_)) => CommitMark::default(),
        Err(e) => return Err(classify(path, e)),
    };
    match marker {
        Some(m) if db.is_behind(&m) => Err(StoreError::BehindMarker {
            path: path.to_path_buf(),
            marker_path: marker::marker_path(dir),
            database: db,
            marker: m,
        }),
        None if db.generation > 0 => Err(StoreError::MarkerMissing {
            path: path.to_path_buf(),
            marker_path: marker::marker_path(dir),
            database: db,
        }),
        m => Ok(m),
    }
}

/// Runs `PRAGMA {pragma}` (`quick_check` or `integrity_check`); [`StoreError::Damaged`]
/// lists the first problems it reports.
async fn run_check(pool: &SqlitePool, path: &Path, pragma: &str) -> StoreResult<()> {
    let rows: Vec<String> = sqlx::query_scalar(&format!("PRAGMA {pragma}(20)"))
        .fetch_all(pool)
        .await
        .map_err(|e| open_error(path, e))?;
    if rows.len() == 1 && rows[0] == "ok" {
        return Ok(());
    }
    // Entries missing from or extra in an index: the tables are whole, and rebuilding the
    // indexes from them repairs the store without losing anything.
    let only_indexes = rows.iter().all(|r| r.contains(" index "));
    let hint = if only_indexes {
        format!(
            " (only indexes are affected: with the coordinator stopped, `tessera store \
             reindex --data {}` rebuilds them from the tables and loses nothing)",
            path.parent().unwrap_or(Path::new(".")).display()
        )
    } else {
        String::new()
    };
    Err(StoreError::Damaged {
        path: path.to_path_buf(),
        detail: format!("SQLite's {pragma} reports: {}{hint}", rows.join("; ")),
    })
}

/// The commit generation and the highest job id ever issued (the larger of the
/// AUTOINCREMENT sequence and the largest id present).
pub(super) async fn commit_mark(conn: &mut Conn<'_>) -> StoreResult<CommitMark> {
    let row = conn
        .fetch_one(stmt(
            "SELECT (SELECT value FROM counters WHERE name = 'commit_generation') AS generation, \
                 MAX(COALESCE((SELECT seq FROM sqlite_sequence WHERE name = 'jobs'), 0), \
                     COALESCE((SELECT MAX(id) FROM jobs), 0)) AS max_job_id, \
                 COALESCE((SELECT value FROM counters WHERE name = 'lease_high_water'), 0) \
                     AS lease_high_water",
        ))
        .await?;
    let place = || "counters".to_string();
    let generation: Option<i64> = row.try_get("generation")?;
    let generation = generation.ok_or_else(|| {
        StoreError::Corrupt("counters: the commit_generation row is missing".into())
    })?;
    Ok(CommitMark {
        generation: u64::try_from(generation).map_err(|_| {
            StoreError::Corrupt(format!("counters: commit_generation = {generation}"))
        })?,
        max_job_id: int_col(&row, "max_job_id", &place)?,
        lease_high_water: int_col(&row, "lease_high_water", &place)?,
    })
}

/// Increments the commit generation inside a write transaction; returns the mark to
/// publish once the transaction committed.
pub(super) async fn bump_generation(tx: &mut Conn<'_>) -> StoreResult<CommitMark> {
    let n = tx
        .execute(stmt(
            "UPDATE counters SET value = value + 1 WHERE name = 'commit_generation'",
        ))
        .await?;
    if n != 1 {
        return Err(StoreError::Corrupt(
            "counters: the commit_generation row is missing".into(),
        ));
    }
    commit_mark(tx).await
}

/// Creates `schema_version` if needed and applies the missing migrations, all in one
/// `BEGIN IMMEDIATE` transaction (two processes opening the same new directory cannot
/// both migrate).
pub(super) async fn migrate(pool: &SqlitePool) -> StoreResult<()> {
    let mut tx = Tx::Sqlite(pool.begin_with("BEGIN IMMEDIATE").await?);
    sql::migrate(&mut tx, MIGRATIONS, CHECKSUM_SCHEMA).await?;
    tx.commit().await
}

/// SQLite's side of the shared SQL layer ([`sql`]): one writer at a time, and the commit
/// marker written after the commits it records.
#[async_trait]
impl SqlBackend for SqliteStore {
    const DIALECT: Dialect = Dialect::Sqlite;

    fn reader(&self) -> Conn<'_> {
        Conn::SqlitePool(&self.reader)
    }

    async fn begin_write(&self) -> StoreResult<Write<'_>> {
        let turn = self.turn.lock().await;
        let tx = self.writer.begin_with("BEGIN IMMEDIATE").await?;
        Ok(Write {
            tx: Tx::Sqlite(tx),
            turn: Some(turn),
        })
    }

    async fn finish_write(&self, mut write: Write<'_>, recorded: bool) -> StoreResult<()> {
        let mark = if recorded {
            Some(bump_generation(&mut write.conn()).await?)
        } else {
            None
        };
        write.tx.commit().await?;
        if let Some(mark) = mark {
            self.publish(mark).await?;
        }
        drop(write.turn);
        Ok(())
    }

    async fn close_pools(&self) {
        // Fold the WAL into the database file now rather than relying on the last
        // connection's close to do it: a stopped coordinator leaves one self-contained
        // file (what `tessera store backup` and an operator copying the file expect).
        if let Err(e) = sqlx::query("PRAGMA wal_checkpoint(TRUNCATE)")
            .execute(&self.writer)
            .await
        {
            tracing::warn!(error = %e, "WAL checkpoint at close failed");
        }
        self.reader.close().await;
        self.writer.close().await;
    }
}
