//! The SQLite implementation of [`Store`].

use std::path::{Path, PathBuf};
use std::time::Duration;

use async_trait::async_trait;
use sqlx::sqlite::{
    SqliteConnectOptions, SqliteJournalMode, SqlitePool, SqlitePoolOptions, SqliteSynchronous,
};
use sqlx::{Connection, Row};
use tessera_api::{FrameRange, HistoryPoint, JobState};
use tessera_farm::{FramePlan, JobId};

use super::codec::{encode_adaptive, encode_stats, encode_units};
use super::marker::{self, CommitMark};
use super::rows::{
    check_finite, check_new_job, check_tile_to_save, fault_from_row, fault_where, identity_col,
    int_col, job_from_row, now_unix_ms, plan_from_row, quarantine_from_row, state_count_from_row,
    summary_from_row, tile_from_parts, to_i64, JOB_COLUMNS, PLAN_COLUMNS, QUARANTINE_COLUMNS,
};
use super::{
    FaultEvent, FaultFilter, JobOrder, JobQuery, JobRecord, NewJob, PreviousRun, QuarantineRecord,
    Store, StoreError, StoreResult, TileCheckpoint, TileCheckpointRef, TileSummary,
};

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
];

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
/// Cloning is cheap and shares the connections.
#[derive(Debug, Clone)]
pub struct SqliteStore {
    writer: SqlitePool,
    reader: SqlitePool,
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
    /// 2. runs SQLite's `PRAGMA quick_check` ([`StoreError::Damaged`] if it finds
    ///    anything, or if the file is not a database);
    /// 3. brings the schema up to date ([`StoreError::SchemaTooNew`] if a newer build
    ///    wrote it);
    /// 4. compares the database with its commit marker ([`marker`]):
    ///    [`StoreError::BehindMarker`] if acknowledged commits are missing;
    /// 5. probes a write: one committed transaction and a marker write
    ///    ([`StoreError::NotWritable`] for a read-only file, directory or filesystem, or a
    ///    full disk), so such a store fails here rather than at the first request.
    pub async fn open(dir: &Path) -> StoreResult<Self> {
        let (writer, path) = connect_writer(dir, true).await?;
        quick_check(&writer, &path).await?;
        // Compared before migrating: a database that lost everything (even its schema)
        // is refused as it is, not first filled with an empty schema.
        if let Some(m) = marker::read_marker(dir).map_err(StoreError::BadMarker)? {
            // A database without the generation (empty, or older than schema 3 while a
            // marker exists) is behind any marker.
            let db = match commit_mark(&writer).await {
                Ok(db) => db,
                Err(StoreError::Database(sqlx::Error::Database(e)))
                    if e.message().contains("no such table") =>
                {
                    CommitMark::default()
                }
                Err(StoreError::Corrupt(_)) => CommitMark::default(),
                Err(e) => return Err(classify(&path, e)),
            };
            if db.is_behind(&m) {
                return Err(StoreError::BehindMarker {
                    path,
                    marker_path: marker::marker_path(dir),
                    database: db,
                    marker: m,
                });
            }
        }
        migrate(&writer).await.map_err(|e| classify(&path, e))?;
        let store = Self::from_writer(writer, path, dir).await?;
        // The write probe: a generation bump, committed, then recorded in the marker.
        let mut conn = store.writer.acquire().await?;
        let mut tx = conn
            .begin_with("BEGIN IMMEDIATE")
            .await
            .map_err(|e| store.probe_error(e))?;
        let mark = bump_generation(&mut tx)
            .await
            .map_err(|e| store.probe_error(e))?;
        tx.commit().await.map_err(|e| store.probe_error(e))?;
        store.publish(mark).await?;
        drop(conn);
        Ok(store)
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
        commit_mark(&self.reader).await
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
        let v: Option<i64> = sqlx::query_scalar("SELECT MAX(version) FROM schema_version")
            .fetch_one(&self.reader)
            .await?;
        Ok(v.unwrap_or(0))
    }

    /// Runs SQLite's full `PRAGMA integrity_check` (the start runs the cheaper
    /// `quick_check`); [`StoreError::Damaged`] lists the problems.
    pub async fn integrity_check(&self) -> StoreResult<()> {
        run_check(&self.reader, &self.path, "integrity_check").await
    }

    /// The plan and frame range of a job, read through `executor`.
    async fn job_plan<'e, E>(executor: E, job: JobId) -> StoreResult<(FramePlan, FrameRange)>
    where
        E: sqlx::Executor<'e, Database = sqlx::Sqlite>,
    {
        let row = sqlx::query(&format!("SELECT {PLAN_COLUMNS} FROM jobs WHERE id = ?1"))
            .bind(to_i64(job, "job id")?)
            .fetch_optional(executor)
            .await?
            .ok_or(StoreError::JobNotFound(job))?;
        plan_from_row(&row, job)
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

/// Runs `PRAGMA {pragma}` (`quick_check` or `integrity_check`); [`StoreError::Damaged`]
/// lists the first problems it reports.
async fn run_check(pool: &SqlitePool, path: &Path, pragma: &str) -> StoreResult<()> {
    let rows: Vec<String> = sqlx::query_scalar(&format!("PRAGMA {pragma}(20)"))
        .fetch_all(pool)
        .await
        .map_err(|e| open_error(path, e))?;
    if rows.len() == 1 && rows[0] == "ok" {
        Ok(())
    } else {
        Err(StoreError::Damaged {
            path: path.to_path_buf(),
            detail: format!("SQLite's {pragma} reports: {}", rows.join("; ")),
        })
    }
}

/// The commit generation and the highest job id ever issued (the larger of the
/// AUTOINCREMENT sequence and the largest id present), read through `executor`.
pub(super) async fn commit_mark<'e, E>(executor: E) -> StoreResult<CommitMark>
where
    E: sqlx::Executor<'e, Database = sqlx::Sqlite>,
{
    let row = sqlx::query(
        "SELECT (SELECT value FROM counters WHERE name = 'commit_generation') AS generation, \
             MAX(COALESCE((SELECT seq FROM sqlite_sequence WHERE name = 'jobs'), 0), \
                 COALESCE((SELECT MAX(id) FROM jobs), 0)) AS max_job_id",
    )
    .fetch_one(executor)
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
    })
}

/// Increments the commit generation inside a write transaction; returns the mark to
/// publish once the transaction committed.
pub(super) async fn bump_generation(tx: &mut sqlx::SqliteConnection) -> StoreResult<CommitMark> {
    let n = sqlx::query("UPDATE counters SET value = value + 1 WHERE name = 'commit_generation'")
        .execute(&mut *tx)
        .await?
        .rows_affected();
    if n != 1 {
        return Err(StoreError::Corrupt(
            "counters: the commit_generation row is missing".into(),
        ));
    }
    commit_mark(&mut *tx).await
}

/// Reads a row of `counters` (through a write transaction).
async fn counter(tx: &mut sqlx::SqliteConnection, name: &str) -> StoreResult<i64> {
    sqlx::query_scalar("SELECT value FROM counters WHERE name = ?1")
        .bind(name)
        .fetch_optional(&mut *tx)
        .await?
        .ok_or_else(|| StoreError::Corrupt(format!("counters: the {name} row is missing")))
}

/// Sets a row of `counters` (through a write transaction).
async fn set_counter(tx: &mut sqlx::SqliteConnection, name: &str, value: i64) -> StoreResult<()> {
    let n = sqlx::query("UPDATE counters SET value = ?2 WHERE name = ?1")
        .bind(name)
        .bind(value)
        .execute(&mut *tx)
        .await?
        .rows_affected();
    if n == 1 {
        Ok(())
    } else {
        Err(StoreError::Corrupt(format!(
            "counters: the {name} row is missing"
        )))
    }
}

/// Creates `schema_version` if needed and applies the missing migrations, all in one
/// `BEGIN IMMEDIATE` transaction (two processes opening the same new directory cannot
/// both migrate).
pub(super) async fn migrate(pool: &SqlitePool) -> StoreResult<()> {
    let supported = MIGRATIONS.last().map_or(0, |m| m.0);
    let mut conn = pool.acquire().await?;
    let mut tx = conn.begin_with("BEGIN IMMEDIATE").await?;
    sqlx::query(
        "CREATE TABLE IF NOT EXISTS schema_version (\
             version INTEGER PRIMARY KEY, applied_unix_ms INTEGER NOT NULL) STRICT",
    )
    .execute(&mut *tx)
    .await?;
    let current: Option<i64> = sqlx::query_scalar("SELECT MAX(version) FROM schema_version")
        .fetch_one(&mut *tx)
        .await?;
    let current = current.unwrap_or(0);
    if current > supported {
        return Err(StoreError::SchemaTooNew {
            found: current,
            supported,
        });
    }
    for &(version, sql) in MIGRATIONS.iter().filter(|m| m.0 > current) {
        sqlx::raw_sql(sql).execute(&mut *tx).await?;
        sqlx::query("INSERT INTO schema_version (version, applied_unix_ms) VALUES (?1, ?2)")
            .bind(version)
            .bind(now_unix_ms())
            .execute(&mut *tx)
            .await?;
    }
    tx.commit().await?;
    Ok(())
}

#[async_trait]
impl Store for SqliteStore {
    async fn insert_job(&self, job: NewJob) -> StoreResult<(JobId, bool)> {
        let created = check_new_job(&job)?;
        let mut conn = self.writer.acquire().await?;
        let mut tx = conn.begin_with("BEGIN IMMEDIATE").await?;
        let inserted: Option<i64> = sqlx::query_scalar(
            "INSERT INTO jobs (idempotency_key, name, scene_ref, settings_json, \
                 plan_width, plan_height, plan_tile_size, plan_samples_per_pass, plan_passes, \
                 first_frame, last_frame, passes_per_unit, priority, state, created_unix_ms, \
                 render_plan_json, error_estimate_caveat) \
             VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13, 'queued', ?14, \
                 ?15, ?16) \
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
        .bind(job.priority)
        .bind(created)
        .bind(job.render_plan_json.as_deref())
        .bind(job.error_estimate_caveat.as_deref())
        .fetch_optional(&mut *tx)
        .await?;
        let (id, created) = match inserted {
            Some(id) => (id, true),
            None => {
                // Only a conflicting idempotency key makes the insert do nothing.
                let id: i64 = sqlx::query_scalar("SELECT id FROM jobs WHERE idempotency_key = ?1")
                    .bind(job.idempotency_key.as_deref())
                    .fetch_one(&mut *tx)
                    .await?;
                (id, false)
            }
        };
        let mark = if created {
            Some(bump_generation(&mut tx).await?)
        } else {
            None
        };
        tx.commit().await?;
        if let Some(mark) = mark {
            self.publish(mark).await?;
        }
        drop(conn);
        let id = JobId::try_from(id)
            .map_err(|_| StoreError::Corrupt(format!("jobs: negative id {id}")))?;
        Ok((id, created))
    }

    async fn get_job(&self, id: JobId) -> StoreResult<Option<JobRecord>> {
        let Ok(key) = i64::try_from(id) else {
            return Ok(None);
        };
        sqlx::query(&format!("SELECT {JOB_COLUMNS} FROM jobs WHERE id = ?1"))
            .bind(key)
            .fetch_optional(&self.reader)
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
        let sql = format!(
            "SELECT {JOB_COLUMNS} FROM jobs WHERE id {cmp} ?1 AND (?2 IS NULL OR state = ?2) \
             ORDER BY id {dir} LIMIT ?3"
        );
        let rows = sqlx::query(&sql)
            .bind(cursor)
            .bind(query.state.map(JobState::as_str))
            .bind(i64::from(query.limit))
            .fetch_all(&self.reader)
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
        let mut conn = self.writer.acquire().await?;
        let mut tx = conn.begin_with("BEGIN IMMEDIATE").await?;
        let changed = sqlx::query(
            "UPDATE jobs SET state = ?2, error = ?3, \
                 started_unix_ms = CASE WHEN ?2 = 'running' AND started_unix_ms IS NULL \
                     THEN ?4 ELSE started_unix_ms END, \
                 finished_unix_ms = CASE WHEN ?2 IN ('done', 'failed', 'canceled') \
                     THEN ?4 ELSE finished_unix_ms END \
             WHERE id = ?1 AND state IN ('queued', 'running')",
        )
        .bind(key)
        .bind(state.as_str())
        .bind(error.as_deref())
        .bind(now)
        .execute(&mut *tx)
        .await?
        .rows_affected();
        let exists = changed > 0
            || sqlx::query_scalar::<_, i64>("SELECT EXISTS (SELECT 1 FROM jobs WHERE id = ?1)")
                .bind(key)
                .fetch_one(&mut *tx)
                .await?
                != 0;
        let mark = if changed > 0 {
            Some(bump_generation(&mut tx).await?)
        } else {
            None
        };
        tx.commit().await?;
        if let Some(mark) = mark {
            self.publish(mark).await?;
        }
        drop(conn);
        if exists {
            Ok(changed > 0)
        } else {
            Err(StoreError::JobNotFound(id))
        }
    }

    async fn count_jobs_by_state(&self) -> StoreResult<Vec<(JobState, u64)>> {
        let rows = sqlx::query("SELECT state, COUNT(*) AS n FROM jobs GROUP BY state")
            .fetch_all(&self.reader)
            .await?;
        rows.iter().map(state_count_from_row).collect()
    }

    async fn jobs_to_resume(&self) -> StoreResult<Vec<JobRecord>> {
        let rows = sqlx::query(&format!(
            "SELECT {JOB_COLUMNS} FROM jobs WHERE state IN ('queued', 'running') ORDER BY id"
        ))
        .fetch_all(&self.reader)
        .await?;
        rows.iter().map(job_from_row).collect()
    }

    async fn put_scene(&self, hash: &str, bytes: &[u8]) -> StoreResult<bool> {
        if hash.is_empty() {
            return Err(StoreError::InvalidInput("scene hash is empty".into()));
        }
        let size = to_i64(bytes.len() as u64, "scene size")?;
        let mut conn = self.writer.acquire().await?;
        let mut tx = conn.begin_with("BEGIN IMMEDIATE").await?;
        let stored = sqlx::query(
            "INSERT INTO scenes (hash, size, data, stored_unix_ms) VALUES (?1, ?2, ?3, ?4) \
             ON CONFLICT (hash) DO NOTHING",
        )
        .bind(hash)
        .bind(size)
        .bind(bytes)
        .bind(now_unix_ms())
        .execute(&mut *tx)
        .await?
        .rows_affected();
        let mark = if stored > 0 {
            Some(bump_generation(&mut tx).await?)
        } else {
            None
        };
        tx.commit().await?;
        if let Some(mark) = mark {
            self.publish(mark).await?;
        }
        drop(conn);
        Ok(stored > 0)
    }

    async fn get_scene(&self, hash: &str) -> StoreResult<Option<Vec<u8>>> {
        Ok(
            sqlx::query_scalar("SELECT data FROM scenes WHERE hash = ?1")
                .bind(hash)
                .fetch_optional(&self.reader)
                .await?,
        )
    }

    async fn scene_exists(&self, hash: &str) -> StoreResult<bool> {
        let exists: i64 =
            sqlx::query_scalar("SELECT EXISTS (SELECT 1 FROM scenes WHERE hash = ?1)")
                .bind(hash)
                .fetch_one(&self.reader)
                .await?;
        Ok(exists != 0)
    }

    async fn save_tiles(&self, tiles: &[TileCheckpointRef<'_>]) -> StoreResult<()> {
        if tiles.is_empty() {
            return Ok(());
        }
        let mut conn = self.writer.acquire().await?;
        let mut tx = conn.begin_with("BEGIN IMMEDIATE").await?;
        let mut plans: Vec<(JobId, FramePlan, FrameRange)> = Vec::new();
        for t in tiles {
            let (plan, frames) = match plans.iter().find(|p| p.0 == t.job) {
                Some(&(_, plan, frames)) => (plan, frames),
                None => {
                    let (plan, frames) = Self::job_plan(&mut *tx, t.job).await?;
                    plans.push((t.job, plan, frames));
                    (plan, frames)
                }
            };
            check_tile_to_save(&plan, frames, t)?;
            sqlx::query(
                "INSERT INTO tiles (job, frame, tile, merged_passes, stats, units, \
                     rejected_samples, adaptive) \
                 VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8) \
                 ON CONFLICT (job, frame, tile) DO UPDATE SET \
                     merged_passes = excluded.merged_passes, \
                     stats = excluded.stats, \
                     units = excluded.units, \
                     rejected_samples = excluded.rejected_samples, \
                     adaptive = excluded.adaptive",
            )
            .bind(to_i64(t.job, "job id")?)
            .bind(i64::from(t.frame))
            .bind(i64::from(t.tile))
            .bind(i64::from(t.merged_passes))
            .bind(encode_stats(t.pixels))
            .bind(encode_units(t.units))
            .bind(to_i64(t.rejected_samples, "rejected_samples")?)
            .bind(t.adaptive.map(encode_adaptive))
            .execute(&mut *tx)
            .await?;
        }
        tx.commit().await?;
        Ok(())
    }

    async fn load_tiles(&self, job: JobId, frame: Option<u32>) -> StoreResult<Vec<TileCheckpoint>> {
        let key = i64::try_from(job).map_err(|_| StoreError::JobNotFound(job))?;
        let (plan, frames) = Self::job_plan(&self.reader, job).await?;
        let rows = sqlx::query(
            "SELECT frame, tile, merged_passes, stats, units, rejected_samples, adaptive \
             FROM tiles \
             WHERE job = ?1 AND (?2 IS NULL OR frame = ?2) ORDER BY frame, tile",
        )
        .bind(key)
        .bind(frame.map(i64::from))
        .fetch_all(&self.reader)
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
        let rows = sqlx::query(
            "SELECT frame, tile, merged_passes, rejected_samples FROM tiles \
             WHERE job = ?1 ORDER BY frame, tile",
        )
        .bind(key)
        .fetch_all(&self.reader)
        .await?;
        rows.iter().map(|row| summary_from_row(row, job)).collect()
    }

    async fn max_lease_id(&self) -> StoreResult<u64> {
        let v: Option<i64> =
            sqlx::query_scalar("SELECT value FROM counters WHERE name = 'lease_high_water'")
                .fetch_optional(&self.reader)
                .await?;
        let v = v.ok_or_else(|| {
            StoreError::Corrupt("counters: the lease_high_water row is missing".into())
        })?;
        u64::try_from(v)
            .map_err(|_| StoreError::Corrupt(format!("counters: lease_high_water = {v}")))
    }

    async fn record_lease_high_water(&self, lease_id: u64) -> StoreResult<()> {
        let v = to_i64(lease_id, "lease id")?;
        let mut conn = self.writer.acquire().await?;
        let mut tx = conn.begin_with("BEGIN IMMEDIATE").await?;
        let n = sqlx::query(
            "UPDATE counters SET value = MAX(value, ?1) WHERE name = 'lease_high_water'",
        )
        .bind(v)
        .execute(&mut *tx)
        .await?
        .rows_affected();
        if n != 1 {
            return Err(StoreError::Corrupt(
                "counters: the lease_high_water row is missing".into(),
            ));
        }
        tx.commit().await?;
        Ok(())
    }

    async fn fence_key(&self, fresh: [u8; 32]) -> StoreResult<[u8; 32]> {
        let mut conn = self.writer.acquire().await?;
        let mut tx = conn.begin_with("BEGIN IMMEDIATE").await?;
        // Kept if absent, in one transaction: two coordinators never end up with two keys.
        for (i, word) in fresh.chunks_exact(8).enumerate() {
            let v = i64::from_le_bytes(word.try_into().expect("8 bytes"));
            sqlx::query(
                "INSERT INTO counters (name, value) VALUES (?1, ?2) ON CONFLICT (name) DO NOTHING",
            )
            .bind(format!("fence_key_{i}"))
            .bind(v)
            .execute(&mut *tx)
            .await?;
        }
        let mut key = [0u8; 32];
        for (i, word) in key.chunks_exact_mut(8).enumerate() {
            let v: i64 = sqlx::query_scalar("SELECT value FROM counters WHERE name = ?1")
                .bind(format!("fence_key_{i}"))
                .fetch_one(&mut *tx)
                .await?;
            word.copy_from_slice(&v.to_le_bytes());
        }
        tx.commit().await?;
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
        let mut conn = self.writer.acquire().await?;
        let mut tx = conn.begin_with("BEGIN IMMEDIATE").await?;
        let n = sqlx::query(
            "INSERT INTO history (job, elapsed_seconds, spp, error_estimate) \
             SELECT ?1, ?2, ?3, ?4 WHERE EXISTS (SELECT 1 FROM jobs WHERE id = ?1)",
        )
        .bind(key)
        .bind(elapsed)
        .bind(spp)
        .bind(error)
        .execute(&mut *tx)
        .await?
        .rows_affected();
        if n == 0 {
            return Err(StoreError::JobNotFound(job));
        }
        tx.commit().await?;
        Ok(())
    }

    async fn list_history(&self, job: JobId) -> StoreResult<Vec<HistoryPoint>> {
        let Ok(key) = i64::try_from(job) else {
            return Ok(Vec::new());
        };
        let rows = sqlx::query(
            "SELECT elapsed_seconds, spp, error_estimate FROM history WHERE job = ?1 ORDER BY seq",
        )
        .bind(key)
        .fetch_all(&self.reader)
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
        let mut conn = self.writer.acquire().await?;
        let mut tx = conn.begin_with("BEGIN IMMEDIATE").await?;
        sqlx::query(
            "INSERT INTO faults (worker, job, kind, message, unix_ms) VALUES (?1, ?2, ?3, ?4, ?5)",
        )
        .bind(&fault.worker)
        .bind(job)
        .bind(fault.kind.as_str())
        .bind(&fault.message)
        .bind(unix_ms)
        .execute(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(())
    }

    async fn count_faults(&self, filter: &FaultFilter) -> StoreResult<u64> {
        let (clause, job) = fault_where(filter, |i| format!("?{i}"))?;
        let sql = format!("SELECT COUNT(*) AS n FROM faults {clause}");
        let mut q = sqlx::query(&sql);
        if let Some(job) = job {
            q = q.bind(job);
        }
        if let Some(worker) = &filter.worker {
            q = q.bind(worker.as_str());
        }
        let row = q.fetch_one(&self.reader).await?;
        int_col(&row, "n", &|| "faults".to_string())
    }

    async fn list_faults(&self, filter: &FaultFilter, limit: u32) -> StoreResult<Vec<FaultEvent>> {
        let (clause, job) = fault_where(filter, |i| format!("?{i}"))?;
        let sql = format!(
            "SELECT worker, job, kind, message, unix_ms FROM faults {clause} \
             ORDER BY id DESC LIMIT {}",
            limit
        );
        let mut q = sqlx::query(&sql);
        if let Some(job) = job {
            q = q.bind(job);
        }
        if let Some(worker) = &filter.worker {
            q = q.bind(worker.as_str());
        }
        let rows = q.fetch_all(&self.reader).await?;
        rows.iter().map(fault_from_row).collect()
    }

    async fn record_quarantine(&self, q: &QuarantineRecord) -> StoreResult<bool> {
        let unix_ms = to_i64(q.unix_ms, "quarantine unix_ms")?;
        let mut conn = self.writer.acquire().await?;
        let mut tx = conn.begin_with("BEGIN IMMEDIATE").await?;
        let n = sqlx::query(
            "INSERT INTO quarantines (worker, identity, reason, unix_ms) \
             VALUES (?1, ?2, ?3, ?4) ON CONFLICT (worker, identity) DO NOTHING",
        )
        .bind(&q.worker)
        .bind(identity_col(q.identity.as_deref()))
        .bind(&q.reason)
        .bind(unix_ms)
        .execute(&mut *tx)
        .await?
        .rows_affected();
        tx.commit().await?;
        Ok(n == 1)
    }

    async fn list_quarantines(&self) -> StoreResult<Vec<QuarantineRecord>> {
        let sql = format!("SELECT {QUARANTINE_COLUMNS} FROM quarantines ORDER BY worker, identity");
        let rows = sqlx::query(&sql).fetch_all(&self.reader).await?;
        rows.iter().map(quarantine_from_row).collect()
    }

    async fn delete_quarantines(&self, worker: &str) -> StoreResult<u64> {
        let mut conn = self.writer.acquire().await?;
        let mut tx = conn.begin_with("BEGIN IMMEDIATE").await?;
        let n = sqlx::query("DELETE FROM quarantines WHERE worker = ?1")
            .bind(worker)
            .execute(&mut *tx)
            .await?
            .rows_affected();
        tx.commit().await?;
        Ok(n)
    }

    async fn job_ids_to_resume(&self) -> StoreResult<Vec<JobId>> {
        let ids: Vec<i64> = sqlx::query_scalar(
            "SELECT id FROM jobs WHERE state IN ('queued', 'running') ORDER BY id",
        )
        .fetch_all(&self.reader)
        .await?;
        ids.into_iter()
            .map(|id| {
                JobId::try_from(id).map_err(|_| StoreError::Corrupt(format!("jobs: id {id}")))
            })
            .collect()
    }

    async fn begin_run(&self) -> StoreResult<PreviousRun> {
        let mut conn = self.writer.acquire().await?;
        let mut tx = conn.begin_with("BEGIN IMMEDIATE").await?;
        let clean = counter(&mut tx, "clean_shutdown").await? != 0;
        let resuming = counter(&mut tx, "resuming_job").await?;
        set_counter(&mut tx, "clean_shutdown", 0).await?;
        tx.commit().await?;
        Ok(PreviousRun {
            clean,
            resuming: u64::try_from(resuming).ok().filter(|&j| j > 0),
        })
    }

    async fn end_run(&self) -> StoreResult<()> {
        let mut conn = self.writer.acquire().await?;
        let mut tx = conn.begin_with("BEGIN IMMEDIATE").await?;
        set_counter(&mut tx, "clean_shutdown", 1).await?;
        set_counter(&mut tx, "resuming_job", 0).await?;
        tx.commit().await?;
        Ok(())
    }

    async fn record_resume(&self, job: JobId, count: bool) -> StoreResult<u32> {
        let key = i64::try_from(job).map_err(|_| StoreError::JobNotFound(job))?;
        let mut conn = self.writer.acquire().await?;
        let mut tx = conn.begin_with("BEGIN IMMEDIATE").await?;
        let row = sqlx::query(
            "SELECT resumes, resume_passes, \
                 (SELECT COALESCE(SUM(merged_passes), 0) FROM tiles WHERE job = ?1) AS merged \
             FROM jobs WHERE id = ?1",
        )
        .bind(key)
        .fetch_optional(&mut *tx)
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
        sqlx::query("UPDATE jobs SET resumes = ?2, resume_passes = ?3 WHERE id = ?1")
            .bind(key)
            .bind(i64::from(resumes))
            .bind(merged)
            .execute(&mut *tx)
            .await?;
        set_counter(&mut tx, "resuming_job", key).await?;
        tx.commit().await?;
        Ok(resumes)
    }

    async fn resumes_done(&self) -> StoreResult<()> {
        let mut conn = self.writer.acquire().await?;
        let mut tx = conn.begin_with("BEGIN IMMEDIATE").await?;
        set_counter(&mut tx, "resuming_job", 0).await?;
        tx.commit().await?;
        Ok(())
    }

    async fn ping(&self) -> StoreResult<()> {
        sqlx::query("SELECT 1").execute(&self.reader).await?;
        Ok(())
    }

    async fn close(&self) {
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
