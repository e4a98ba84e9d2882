//! The PostgreSQL implementation of [`Store`] (docs/store.md, "PostgreSQL").
//!
//! The same tables, semantics and row decoding ([`rows`](super::rows)) as the SQLite
//! store, in PostgreSQL's types. What differs, and why:
//!
//! - durability is PostgreSQL's (its WAL, fsynced at commit with the server's default
//!   `synchronous_commit = on`); there is no `quick_check`, commit marker or write probe,
//!   which guard against damage to a local file that the server guards against itself;
//! - writes are not serialized in-process: each write is one transaction and the rows it
//!   must not race on are locked in it (`ON CONFLICT`, `SELECT ... FOR UPDATE`,
//!   `GREATEST` in one `UPDATE`), so several connections, and several coordinators, may
//!   write at once;
//! - a lost or refused connection is [`StoreError::Unreachable`], which is transient
//!   (not [`StoreError::is_write_failure`]): the pool reconnects and the next request
//!   may succeed, where a failing SQLite file stays failed.

use std::str::FromStr;
use std::sync::atomic::{AtomicI64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use async_trait::async_trait;
use sqlx::postgres::{PgConnectOptions, PgPool, PgPoolOptions};
use sqlx::Row;
use tessera_api::{FrameRange, HistoryPoint, JobState};
use tessera_farm::{FramePlan, JobId};

use super::codec::{encode_adaptive, encode_stats, encode_units};
use super::rows::{
    check_finite, check_new_job, check_tile_to_save, fault_from_row, fault_where, identity_col,
    int_col, job_from_row, now_unix_ms, plan_from_row, quarantine_from_row, state_count_from_row,
    summary_from_row, tile_from_parts, to_i64, JOB_COLUMNS, PLAN_COLUMNS, QUARANTINE_COLUMNS,
};
use super::{
    FaultEvent, FaultFilter, JobOrder, JobQuery, JobRecord, NewJob, PreviousRun, QuarantineRecord,
    Store, StoreError, StoreResult, TileCheckpoint, TileCheckpointRef, TileSummary,
};

/// Schema migrations of the PostgreSQL store: (version, SQL), applied in order in one
/// transaction. Its versions are its own (version 1 has the tables of SQLite's version 3).
/// Never edit a released migration; append a new one.
const MIGRATIONS: &[(i64, &str)] = &[
    (1, include_str!("migrations/postgres/0001_initial.sql")),
    (2, include_str!("migrations/postgres/0002_leader_epoch.sql")),
    (
        3,
        include_str!("migrations/postgres/0003_adaptive_policy.sql"),
    ),
    (4, include_str!("migrations/postgres/0004_quarantine.sql")),
    (5, include_str!("migrations/postgres/0005_render_plan.sql")),
];

/// Connections in the pool: the coordinator's concurrent requests, merges and the ticker.
const MAX_CONNECTIONS: u32 = 8;

/// How long getting a connection (connecting, or waiting for a free one) may take before
/// the operation fails with [`StoreError::Unreachable`].
const ACQUIRE_TIMEOUT: Duration = Duration::from_secs(10);

/// Key of the transaction-level advisory lock taken while migrating, so that two
/// coordinators opening one new database do not both create the tables.
const MIGRATION_LOCK: i64 = 0x7465_7373_6572_6131; // "tessera1"

/// The farm's state in a PostgreSQL database (`postgres://user@host:port/db`).
///
/// Cloning is cheap and shares the pool and the fencing epoch.
#[derive(Debug, Clone)]
pub struct PostgresStore {
    pool: PgPool,
    /// The URL without its password, for messages.
    url: String,
    /// The fencing epoch this store's coordinator took as the active one
    /// ([`PostgresStore::take_leadership`]); 0 before, when writes are not fenced.
    epoch: Arc<AtomicI64>,
}

impl PostgresStore {
    /// The newest schema version this build knows (and migrates every database to).
    pub const SUPPORTED_SCHEMA: i64 = MIGRATIONS[MIGRATIONS.len() - 1].0;

    /// Connects to the database at `url` (`postgres://` or `postgresql://`, with the
    /// usual libpq URL parameters sqlx understands, e.g. `?options=-c search_path=s`) and
    /// brings its schema up to date.
    ///
    /// [`StoreError::BadUrl`] for a URL that cannot be parsed, [`StoreError::Unreachable`]
    /// when the server cannot be reached or refuses the login, [`StoreError::SchemaTooNew`]
    /// if a newer build migrated the database.
    pub async fn open(url: &str) -> StoreResult<Self> {
        let shown = redact(url);
        let options = PgConnectOptions::from_str(url).map_err(|e| StoreError::BadUrl {
            url: shown.clone(),
            reason: e.to_string(),
        })?;
        // A coordinator frozen inside a write transaction (a suspended VM, SIGSTOP) would
        // hold its row locks, and so block a standby's takeover, until TCP gave up: the
        // server ends such a session after 5 s, as the lock session's idle timeout does.
        let options = options
            .application_name("tessera-coordinator")
            .options([("idle_in_transaction_session_timeout", "5000")]);
        let pool = PgPoolOptions::new()
            .max_connections(MAX_CONNECTIONS)
            .acquire_timeout(ACQUIRE_TIMEOUT)
            .connect_with(options)
            .await
            .map_err(|e| unreachable(&shown, e))?;
        let store = Self {
            pool,
            url: shown,
            epoch: Arc::new(AtomicI64::new(0)),
        };
        store.lift(migrate(&store.pool).await)?;
        Ok(store)
    }

    /// Makes this store's coordinator the writer of the database: raises the store's
    /// fencing epoch by one and returns it. From then on every state-changing write of
    /// this store (and its clones) first checks, in its own transaction, that the epoch
    /// is still this one, and fails with [`StoreError::NotLeader`] once another
    /// coordinator took the leadership after it (docs/store.md, "High availability").
    ///
    /// The check reads the epoch `FOR SHARE` and this `UPDATE` locks it, so the raise
    /// waits for every write of the previous leader that passed its check to commit:
    /// when this returns, nothing the previous leader writes can land any more, and the
    /// new leader reads its state after everything the old one committed.
    ///
    /// Call it while holding the leadership lock (`crate::ha`), before reading the
    /// state to resume.
    pub async fn take_leadership(&self) -> StoreResult<i64> {
        let epoch: Option<i64> = sqlx::query_scalar(
            "UPDATE counters SET value = value + 1 WHERE name = 'leader_epoch' RETURNING value",
        )
        .fetch_optional(&self.pool)
        .await
        .map_err(|e| self.error(e))?;
        let epoch = epoch.ok_or_else(|| {
            StoreError::Corrupt("counters: the leader_epoch row is missing".into())
        })?;
        self.epoch.store(epoch, Ordering::SeqCst);
        Ok(epoch)
    }

    /// The fencing check of a write transaction: fails with [`StoreError::NotLeader`]
    /// when another coordinator took the leadership after this one
    /// ([`PostgresStore::take_leadership`]); nothing to check before this store took it.
    async fn fence(&self, tx: &mut sqlx::PgConnection) -> StoreResult<()> {
        let ours = self.epoch.load(Ordering::SeqCst);
        if ours == 0 {
            return Ok(());
        }
        let current: Option<i64> =
            sqlx::query_scalar("SELECT value FROM counters WHERE name = 'leader_epoch' FOR SHARE")
                .fetch_optional(&mut *tx)
                .await?;
        match current {
            Some(current) if current == ours => Ok(()),
            Some(current) => Err(StoreError::NotLeader { ours, current }),
            None => Err(StoreError::Corrupt(
                "counters: the leader_epoch row is missing".into(),
            )),
        }
    }

    /// The URL of the database, without its password.
    pub fn url(&self) -> &str {
        &self.url
    }

    /// The schema version of the database (the newest applied migration).
    pub async fn schema_version(&self) -> StoreResult<i64> {
        let v: Option<i64> = sqlx::query_scalar("SELECT MAX(version) FROM schema_version")
            .fetch_one(&self.pool)
            .await
            .map_err(|e| self.error(e))?;
        Ok(v.unwrap_or(0))
    }

    /// A database error of this store: connection failures become
    /// [`StoreError::Unreachable`] naming the server.
    fn error(&self, e: sqlx::Error) -> StoreError {
        if is_connection_error(&e) {
            unreachable(&self.url, e)
        } else {
            StoreError::Database(e)
        }
    }

    /// [`PostgresStore::error`] applied to a store result.
    fn lift<T>(&self, r: StoreResult<T>) -> StoreResult<T> {
        r.map_err(|e| match e {
            StoreError::Database(e) => self.error(e),
            e => e,
        })
    }

    /// The plan and frame range of a job, read through `executor`.
    async fn job_plan<'e, E>(executor: E, job: JobId) -> StoreResult<(FramePlan, FrameRange)>
    where
        E: sqlx::Executor<'e, Database = sqlx::Postgres>,
    {
        let row = sqlx::query(&format!("SELECT {PLAN_COLUMNS} FROM jobs WHERE id = $1"))
            .bind(to_i64(job, "job id")?)
            .fetch_optional(executor)
            .await?
            .ok_or(StoreError::JobNotFound(job))?;
        plan_from_row(&row, job)
    }
}

/// `url` with its password replaced by `***`, for messages and logs.
pub(super) fn redact(url: &str) -> String {
    // postgres://user:password@host/...: the password sits between the first ':' after
    // the scheme and the last '@' before the path.
    let Some(scheme_end) = url.find("://").map(|i| i + 3) else {
        return url.to_string();
    };
    let rest = &url[scheme_end..];
    let authority_end = rest.find('/').unwrap_or(rest.len());
    let authority = &rest[..authority_end];
    match (authority.rfind('@'), authority.find(':')) {
        (Some(at), Some(colon)) if colon < at => format!(
            "{}{}:***{}",
            &url[..scheme_end],
            &authority[..colon],
            &rest[at..]
        ),
        _ => url.to_string(),
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
fn unreachable(url: &str, e: sqlx::Error) -> StoreError {
    StoreError::Unreachable {
        url: url.to_string(),
        detail: e.to_string(),
    }
}

/// Creates `schema_version` if needed and applies the missing migrations, all in one
/// transaction under an advisory lock.
async fn migrate(pool: &PgPool) -> StoreResult<()> {
    let supported = MIGRATIONS.last().map_or(0, |m| m.0);
    let mut tx = pool.begin().await?;
    sqlx::query("SELECT pg_advisory_xact_lock($1)")
        .bind(MIGRATION_LOCK)
        .execute(&mut *tx)
        .await?;
    sqlx::query(
        "CREATE TABLE IF NOT EXISTS schema_version (\
             version BIGINT PRIMARY KEY, applied_unix_ms BIGINT NOT NULL)",
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
        sqlx::query("INSERT INTO schema_version (version, applied_unix_ms) VALUES ($1, $2)")
            .bind(version)
            .bind(now_unix_ms())
            .execute(&mut *tx)
            .await?;
    }
    tx.commit().await?;
    Ok(())
}

/// Reads a row of `counters`, locking it until the transaction ends.
async fn counter(tx: &mut sqlx::PgConnection, name: &str) -> StoreResult<i64> {
    sqlx::query_scalar("SELECT value FROM counters WHERE name = $1 FOR UPDATE")
        .bind(name)
        .fetch_optional(&mut *tx)
        .await?
        .ok_or_else(|| StoreError::Corrupt(format!("counters: the {name} row is missing")))
}

/// Sets a row of `counters`.
async fn set_counter(tx: &mut sqlx::PgConnection, name: &str, value: i64) -> StoreResult<()> {
    let n = sqlx::query("UPDATE counters SET value = $2 WHERE name = $1")
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

impl PostgresStore {
    async fn insert_job_(&self, job: NewJob) -> StoreResult<(JobId, bool)> {
        let created = check_new_job(&job)?;
        let mut tx = self.pool.begin().await?;
        self.fence(&mut tx).await?;
        let inserted: Option<i64> = sqlx::query_scalar(
            "INSERT INTO jobs (idempotency_key, name, scene_ref, settings_json, \
                 plan_width, plan_height, plan_tile_size, plan_samples_per_pass, plan_passes, \
                 first_frame, last_frame, passes_per_unit, priority, state, created_unix_ms, \
                 render_plan_json, error_estimate_caveat) \
             VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11, $12, $13, 'queued', $14, \
                 $15, $16) \
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
        .bind(job.error_estimate_caveat.as_deref())
        .fetch_optional(&mut *tx)
        .await?;
        let (id, created) = match inserted {
            Some(id) => (id, true),
            None => {
                // Only a conflicting idempotency key makes the insert do nothing; under
                // READ COMMITTED this statement sees the conflicting row, committed.
                let id: i64 = sqlx::query_scalar("SELECT id FROM jobs WHERE idempotency_key = $1")
                    .bind(job.idempotency_key.as_deref())
                    .fetch_one(&mut *tx)
                    .await?;
                (id, false)
            }
        };
        tx.commit().await?;
        let id = JobId::try_from(id)
            .map_err(|_| StoreError::Corrupt(format!("jobs: negative id {id}")))?;
        Ok((id, created))
    }

    async fn get_job_(&self, id: JobId) -> StoreResult<Option<JobRecord>> {
        let Ok(key) = i64::try_from(id) else {
            return Ok(None);
        };
        sqlx::query(&format!("SELECT {JOB_COLUMNS} FROM jobs WHERE id = $1"))
            .bind(key)
            .fetch_optional(&self.pool)
            .await?
            .as_ref()
            .map(job_from_row)
            .transpose()
    }

    async fn list_jobs_(&self, query: JobQuery) -> StoreResult<Vec<JobRecord>> {
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
            "SELECT {JOB_COLUMNS} FROM jobs WHERE id {cmp} $1 \
             AND ($2::TEXT IS NULL OR state = $2::TEXT) ORDER BY id {dir} LIMIT $3"
        );
        let rows = sqlx::query(&sql)
            .bind(cursor)
            .bind(query.state.map(JobState::as_str))
            .bind(i64::from(query.limit))
            .fetch_all(&self.pool)
            .await?;
        rows.iter().map(job_from_row).collect()
    }

    async fn set_job_state_(
        &self,
        id: JobId,
        state: JobState,
        error: Option<String>,
        now_unix_ms: u64,
    ) -> StoreResult<bool> {
        let key = i64::try_from(id).map_err(|_| StoreError::JobNotFound(id))?;
        let now = to_i64(now_unix_ms, "now_unix_ms")?;
        let mut tx = self.pool.begin().await?;
        self.fence(&mut tx).await?;
        let changed = sqlx::query(
            "UPDATE jobs SET state = $2::TEXT, error = $3, \
                 started_unix_ms = CASE WHEN $2::TEXT = 'running' AND started_unix_ms IS NULL \
                     THEN $4 ELSE started_unix_ms END, \
                 finished_unix_ms = CASE WHEN $2::TEXT IN ('done', 'failed', 'canceled') \
                     THEN $4 ELSE finished_unix_ms END \
             WHERE id = $1 AND state IN ('queued', 'running')",
        )
        .bind(key)
        .bind(state.as_str())
        .bind(error.as_deref())
        .bind(now)
        .execute(&mut *tx)
        .await?
        .rows_affected();
        let exists = changed > 0
            || sqlx::query_scalar::<_, bool>("SELECT EXISTS (SELECT 1 FROM jobs WHERE id = $1)")
                .bind(key)
                .fetch_one(&mut *tx)
                .await?;
        tx.commit().await?;
        if exists {
            Ok(changed > 0)
        } else {
            Err(StoreError::JobNotFound(id))
        }
    }

    async fn count_jobs_by_state_(&self) -> StoreResult<Vec<(JobState, u64)>> {
        let rows = sqlx::query("SELECT state, COUNT(*) AS n FROM jobs GROUP BY state")
            .fetch_all(&self.pool)
            .await?;
        rows.iter().map(state_count_from_row).collect()
    }

    async fn jobs_to_resume_(&self) -> StoreResult<Vec<JobRecord>> {
        let rows = sqlx::query(&format!(
            "SELECT {JOB_COLUMNS} FROM jobs WHERE state IN ('queued', 'running') ORDER BY id"
        ))
        .fetch_all(&self.pool)
        .await?;
        rows.iter().map(job_from_row).collect()
    }

    async fn put_scene_(&self, hash: &str, bytes: &[u8]) -> StoreResult<bool> {
        if hash.is_empty() {
            return Err(StoreError::InvalidInput("scene hash is empty".into()));
        }
        let size = to_i64(bytes.len() as u64, "scene size")?;
        let mut tx = self.pool.begin().await?;
        self.fence(&mut tx).await?;
        let stored = sqlx::query(
            "INSERT INTO scenes (hash, size, data, stored_unix_ms) VALUES ($1, $2, $3, $4) \
             ON CONFLICT (hash) DO NOTHING",
        )
        .bind(hash)
        .bind(size)
        .bind(bytes)
        .bind(now_unix_ms())
        .execute(&mut *tx)
        .await?
        .rows_affected();
        tx.commit().await?;
        Ok(stored > 0)
    }

    async fn save_tiles_(&self, tiles: &[TileCheckpointRef<'_>]) -> StoreResult<()> {
        if tiles.is_empty() {
            return Ok(());
        }
        let mut tx = self.pool.begin().await?;
        self.fence(&mut tx).await?;
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
                 VALUES ($1, $2, $3, $4, $5, $6, $7, $8) \
                 ON CONFLICT (job, frame, tile) DO UPDATE SET \
                     merged_passes = EXCLUDED.merged_passes, \
                     stats = EXCLUDED.stats, \
                     units = EXCLUDED.units, \
                     rejected_samples = EXCLUDED.rejected_samples, \
                     adaptive = EXCLUDED.adaptive",
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

    async fn load_tiles_(
        &self,
        job: JobId,
        frame: Option<u32>,
    ) -> StoreResult<Vec<TileCheckpoint>> {
        let key = i64::try_from(job).map_err(|_| StoreError::JobNotFound(job))?;
        let (plan, frames) = Self::job_plan(&self.pool, job).await?;
        let rows = sqlx::query(
            "SELECT frame, tile, merged_passes, stats, units, rejected_samples, adaptive \
             FROM tiles \
             WHERE job = $1 AND ($2::BIGINT IS NULL OR frame = $2::BIGINT) ORDER BY frame, tile",
        )
        .bind(key)
        .bind(frame.map(i64::from))
        .fetch_all(&self.pool)
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

    async fn tile_summaries_(&self, job: JobId) -> StoreResult<Vec<TileSummary>> {
        let key = i64::try_from(job).map_err(|_| StoreError::JobNotFound(job))?;
        let rows = sqlx::query(
            "SELECT frame, tile, merged_passes, rejected_samples FROM tiles \
             WHERE job = $1 ORDER BY frame, tile",
        )
        .bind(key)
        .fetch_all(&self.pool)
        .await?;
        rows.iter().map(|row| summary_from_row(row, job)).collect()
    }

    async fn max_lease_id_(&self) -> StoreResult<u64> {
        let v: Option<i64> =
            sqlx::query_scalar("SELECT value FROM counters WHERE name = 'lease_high_water'")
                .fetch_optional(&self.pool)
                .await?;
        let v = v.ok_or_else(|| {
            StoreError::Corrupt("counters: the lease_high_water row is missing".into())
        })?;
        u64::try_from(v)
            .map_err(|_| StoreError::Corrupt(format!("counters: lease_high_water = {v}")))
    }

    async fn record_lease_high_water_(&self, lease_id: u64) -> StoreResult<()> {
        let v = to_i64(lease_id, "lease id")?;
        let mut tx = self.pool.begin().await?;
        // A deposed coordinator reserves no more lease ids: the new one's ids start
        // above everything this one could have granted.
        self.fence(&mut tx).await?;
        // One statement: the row lock makes concurrent raises keep the largest value.
        let n = sqlx::query(
            "UPDATE counters SET value = GREATEST(value, $1) WHERE name = 'lease_high_water'",
        )
        .bind(v)
        .execute(&mut *tx)
        .await?
        .rows_affected();
        tx.commit().await?;
        if n != 1 {
            return Err(StoreError::Corrupt(
                "counters: the lease_high_water row is missing".into(),
            ));
        }
        Ok(())
    }

    async fn fence_key_(&self, fresh: [u8; 32]) -> StoreResult<[u8; 32]> {
        let mut tx = self.pool.begin().await?;
        // Kept if absent, in one transaction: concurrent coordinators agree on one key
        // (the primary key makes the later insert do nothing).
        for (i, word) in fresh.chunks_exact(8).enumerate() {
            let v = i64::from_le_bytes(word.try_into().expect("8 bytes"));
            sqlx::query(
                "INSERT INTO counters (name, value) VALUES ($1, $2) ON CONFLICT (name) DO NOTHING",
            )
            .bind(format!("fence_key_{i}"))
            .bind(v)
            .execute(&mut *tx)
            .await?;
        }
        let mut key = [0u8; 32];
        for (i, word) in key.chunks_exact_mut(8).enumerate() {
            let v: i64 = sqlx::query_scalar("SELECT value FROM counters WHERE name = $1")
                .bind(format!("fence_key_{i}"))
                .fetch_one(&mut *tx)
                .await?;
            word.copy_from_slice(&v.to_le_bytes());
        }
        tx.commit().await?;
        Ok(key)
    }

    async fn append_history_(&self, job: JobId, point: HistoryPoint) -> StoreResult<()> {
        let key = i64::try_from(job).map_err(|_| StoreError::JobNotFound(job))?;
        let elapsed = check_finite(point.elapsed_seconds, "history elapsed_seconds")?;
        let spp = check_finite(point.spp, "history spp")?;
        let error = point
            .error_estimate
            .map(|e| check_finite(e, "history error_estimate"))
            .transpose()?;
        let mut tx = self.pool.begin().await?;
        self.fence(&mut tx).await?;
        let n = sqlx::query(
            "INSERT INTO history (job, elapsed_seconds, spp, error_estimate) \
             SELECT $1, $2, $3, $4 WHERE EXISTS (SELECT 1 FROM jobs WHERE id = $1)",
        )
        .bind(key)
        .bind(elapsed)
        .bind(spp)
        .bind(error)
        .execute(&mut *tx)
        .await?
        .rows_affected();
        tx.commit().await?;
        if n == 0 {
            return Err(StoreError::JobNotFound(job));
        }
        Ok(())
    }

    async fn list_history_(&self, job: JobId) -> StoreResult<Vec<HistoryPoint>> {
        let Ok(key) = i64::try_from(job) else {
            return Ok(Vec::new());
        };
        let rows = sqlx::query(
            "SELECT elapsed_seconds, spp, error_estimate FROM history WHERE job = $1 ORDER BY seq",
        )
        .bind(key)
        .fetch_all(&self.pool)
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

    async fn record_fault_(&self, fault: &FaultEvent) -> StoreResult<()> {
        let job = fault.job.map(|j| to_i64(j, "fault job")).transpose()?;
        let unix_ms = to_i64(fault.unix_ms, "fault unix_ms")?;
        let mut tx = self.pool.begin().await?;
        self.fence(&mut tx).await?;
        sqlx::query(
            "INSERT INTO faults (worker, job, kind, message, unix_ms) VALUES ($1, $2, $3, $4, $5)",
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

    async fn count_faults_(&self, filter: &FaultFilter) -> StoreResult<u64> {
        let (clause, job) = fault_where(filter, |i| format!("${i}"))?;
        let sql = format!("SELECT COUNT(*) AS n FROM faults {clause}");
        let mut q = sqlx::query(&sql);
        if let Some(job) = job {
            q = q.bind(job);
        }
        if let Some(worker) = &filter.worker {
            q = q.bind(worker.as_str());
        }
        let row = q.fetch_one(&self.pool).await?;
        int_col(&row, "n", &|| "faults".to_string())
    }

    async fn list_faults_(&self, filter: &FaultFilter, limit: u32) -> StoreResult<Vec<FaultEvent>> {
        let (clause, job) = fault_where(filter, |i| format!("${i}"))?;
        let sql = format!(
            "SELECT worker, job, kind, message, unix_ms FROM faults {clause} \
             ORDER BY id DESC LIMIT {limit}"
        );
        let mut q = sqlx::query(&sql);
        if let Some(job) = job {
            q = q.bind(job);
        }
        if let Some(worker) = &filter.worker {
            q = q.bind(worker.as_str());
        }
        let rows = q.fetch_all(&self.pool).await?;
        rows.iter().map(fault_from_row).collect()
    }

    async fn record_quarantine_(&self, q: &QuarantineRecord) -> StoreResult<bool> {
        let unix_ms = to_i64(q.unix_ms, "quarantine unix_ms")?;
        let mut tx = self.pool.begin().await?;
        self.fence(&mut tx).await?;
        let n = sqlx::query(
            "INSERT INTO quarantines (worker, identity, reason, unix_ms) \
             VALUES ($1, $2, $3, $4) ON CONFLICT (worker, identity) DO NOTHING",
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

    async fn list_quarantines_(&self) -> StoreResult<Vec<QuarantineRecord>> {
        // `COLLATE "C"`: byte order, as SQLite sorts text, whatever the database's locale.
        let sql = format!(
            "SELECT {QUARANTINE_COLUMNS} FROM quarantines \
             ORDER BY worker COLLATE \"C\", identity COLLATE \"C\""
        );
        let rows = sqlx::query(&sql).fetch_all(&self.pool).await?;
        rows.iter().map(quarantine_from_row).collect()
    }

    async fn delete_quarantines_(&self, worker: &str) -> StoreResult<u64> {
        let mut tx = self.pool.begin().await?;
        self.fence(&mut tx).await?;
        let n = sqlx::query("DELETE FROM quarantines WHERE worker = $1")
            .bind(worker)
            .execute(&mut *tx)
            .await?
            .rows_affected();
        tx.commit().await?;
        Ok(n)
    }

    async fn job_ids_to_resume_(&self) -> StoreResult<Vec<JobId>> {
        let ids: Vec<i64> = sqlx::query_scalar(
            "SELECT id FROM jobs WHERE state IN ('queued', 'running') ORDER BY id",
        )
        .fetch_all(&self.pool)
        .await?;
        ids.into_iter()
            .map(|id| {
                JobId::try_from(id).map_err(|_| StoreError::Corrupt(format!("jobs: id {id}")))
            })
            .collect()
    }

    async fn begin_run_(&self) -> StoreResult<PreviousRun> {
        let mut tx = self.pool.begin().await?;
        self.fence(&mut tx).await?;
        let clean = counter(&mut tx, "clean_shutdown").await? != 0;
        let resuming = counter(&mut tx, "resuming_job").await?;
        set_counter(&mut tx, "clean_shutdown", 0).await?;
        tx.commit().await?;
        Ok(PreviousRun {
            clean,
            resuming: u64::try_from(resuming).ok().filter(|&j| j > 0),
        })
    }

    async fn end_run_(&self) -> StoreResult<()> {
        let mut tx = self.pool.begin().await?;
        self.fence(&mut tx).await?;
        set_counter(&mut tx, "clean_shutdown", 1).await?;
        set_counter(&mut tx, "resuming_job", 0).await?;
        tx.commit().await?;
        Ok(())
    }

    async fn record_resume_(&self, job: JobId, count: bool) -> StoreResult<u32> {
        let key = i64::try_from(job).map_err(|_| StoreError::JobNotFound(job))?;
        let mut tx = self.pool.begin().await?;
        self.fence(&mut tx).await?;
        let row = sqlx::query(
            "SELECT resumes, resume_passes, \
                 (SELECT COALESCE(SUM(merged_passes), 0)::BIGINT FROM tiles WHERE job = $1) \
                     AS merged \
             FROM jobs WHERE id = $1 FOR UPDATE",
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
        sqlx::query("UPDATE jobs SET resumes = $2, resume_passes = $3 WHERE id = $1")
            .bind(key)
            .bind(i64::from(resumes))
            .bind(merged)
            .execute(&mut *tx)
            .await?;
        set_counter(&mut tx, "resuming_job", key).await?;
        tx.commit().await?;
        Ok(resumes)
    }

    async fn resumes_done_(&self) -> StoreResult<()> {
        let mut tx = self.pool.begin().await?;
        self.fence(&mut tx).await?;
        set_counter(&mut tx, "resuming_job", 0).await?;
        tx.commit().await?;
        Ok(())
    }
}

/// Every method runs its `_` twin above and turns connection failures into
/// [`StoreError::Unreachable`] (`PostgresStore::lift`).
#[async_trait]
impl Store for PostgresStore {
    async fn insert_job(&self, job: NewJob) -> StoreResult<(JobId, bool)> {
        self.lift(self.insert_job_(job).await)
    }

    async fn get_job(&self, id: JobId) -> StoreResult<Option<JobRecord>> {
        self.lift(self.get_job_(id).await)
    }

    async fn list_jobs(&self, query: JobQuery) -> StoreResult<Vec<JobRecord>> {
        self.lift(self.list_jobs_(query).await)
    }

    async fn set_job_state(
        &self,
        id: JobId,
        state: JobState,
        error: Option<String>,
        now_unix_ms: u64,
    ) -> StoreResult<bool> {
        self.lift(self.set_job_state_(id, state, error, now_unix_ms).await)
    }

    async fn count_jobs_by_state(&self) -> StoreResult<Vec<(JobState, u64)>> {
        self.lift(self.count_jobs_by_state_().await)
    }

    async fn jobs_to_resume(&self) -> StoreResult<Vec<JobRecord>> {
        self.lift(self.jobs_to_resume_().await)
    }

    async fn put_scene(&self, hash: &str, bytes: &[u8]) -> StoreResult<bool> {
        self.lift(self.put_scene_(hash, bytes).await)
    }

    async fn get_scene(&self, hash: &str) -> StoreResult<Option<Vec<u8>>> {
        sqlx::query_scalar("SELECT data FROM scenes WHERE hash = $1")
            .bind(hash)
            .fetch_optional(&self.pool)
            .await
            .map_err(|e| self.error(e))
    }

    async fn scene_exists(&self, hash: &str) -> StoreResult<bool> {
        sqlx::query_scalar("SELECT EXISTS (SELECT 1 FROM scenes WHERE hash = $1)")
            .bind(hash)
            .fetch_one(&self.pool)
            .await
            .map_err(|e| self.error(e))
    }

    async fn save_tiles(&self, tiles: &[TileCheckpointRef<'_>]) -> StoreResult<()> {
        self.lift(self.save_tiles_(tiles).await)
    }

    async fn load_tiles(&self, job: JobId, frame: Option<u32>) -> StoreResult<Vec<TileCheckpoint>> {
        self.lift(self.load_tiles_(job, frame).await)
    }

    async fn tile_summaries(&self, job: JobId) -> StoreResult<Vec<TileSummary>> {
        self.lift(self.tile_summaries_(job).await)
    }

    async fn max_lease_id(&self) -> StoreResult<u64> {
        self.lift(self.max_lease_id_().await)
    }

    async fn record_lease_high_water(&self, lease_id: u64) -> StoreResult<()> {
        self.lift(self.record_lease_high_water_(lease_id).await)
    }

    async fn fence_key(&self, fresh: [u8; 32]) -> StoreResult<[u8; 32]> {
        self.lift(self.fence_key_(fresh).await)
    }

    async fn append_history(&self, job: JobId, point: HistoryPoint) -> StoreResult<()> {
        self.lift(self.append_history_(job, point).await)
    }

    async fn list_history(&self, job: JobId) -> StoreResult<Vec<HistoryPoint>> {
        self.lift(self.list_history_(job).await)
    }

    async fn record_fault(&self, fault: &FaultEvent) -> StoreResult<()> {
        self.lift(self.record_fault_(fault).await)
    }

    async fn count_faults(&self, filter: &FaultFilter) -> StoreResult<u64> {
        self.lift(self.count_faults_(filter).await)
    }

    async fn list_faults(&self, filter: &FaultFilter, limit: u32) -> StoreResult<Vec<FaultEvent>> {
        self.lift(self.list_faults_(filter, limit).await)
    }

    async fn record_quarantine(&self, quarantine: &QuarantineRecord) -> StoreResult<bool> {
        self.lift(self.record_quarantine_(quarantine).await)
    }

    async fn list_quarantines(&self) -> StoreResult<Vec<QuarantineRecord>> {
        self.lift(self.list_quarantines_().await)
    }

    async fn delete_quarantines(&self, worker: &str) -> StoreResult<u64> {
        self.lift(self.delete_quarantines_(worker).await)
    }

    async fn job_ids_to_resume(&self) -> StoreResult<Vec<JobId>> {
        self.lift(self.job_ids_to_resume_().await)
    }

    async fn begin_run(&self) -> StoreResult<PreviousRun> {
        self.lift(self.begin_run_().await)
    }

    async fn end_run(&self) -> StoreResult<()> {
        self.lift(self.end_run_().await)
    }

    async fn record_resume(&self, job: JobId, count: bool) -> StoreResult<u32> {
        self.lift(self.record_resume_(job, count).await)
    }

    async fn resumes_done(&self) -> StoreResult<()> {
        self.lift(self.resumes_done_().await)
    }

    async fn ping(&self) -> StoreResult<()> {
        sqlx::query("SELECT 1")
            .execute(&self.pool)
            .await
            .map_err(|e| self.error(e))?;
        Ok(())
    }

    async fn close(&self) {
        self.pool.close().await;
    }
}

#[cfg(test)]
mod tests {
    use super::redact;

    #[test]
    fn passwords_are_not_shown() {
        assert_eq!(
            redact("postgres://u:secret@h:5432/db"),
            "postgres://u:***@h:5432/db"
        );
        assert_eq!(redact("postgres://u@h/db"), "postgres://u@h/db");
        assert_eq!(redact("postgresql://h/db"), "postgresql://h/db");
        assert_eq!(
            redact("postgres://u:p@ss@h/db?x=a:b"),
            "postgres://u:***@h/db?x=a:b"
        );
    }
}
