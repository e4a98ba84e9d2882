//! What `tessera store check|backup|restore|accept-loss|reindex` does (docs/store.md):
//! check a store without changing it, take a consistent backup of a live store, replace a
//! stopped coordinator's store with a checked backup, accept a store that lost commits,
//! and rebuild damaged indexes.
//!
//! The check runs the start's own checks ([`preflight`]), so what it reports as a
//! refusal is what the coordinator refuses with, message for message, and the rows a
//! read refuses ([`sql::damaged_rows`]), with what the coordinator does about each.
//!
//! Restore and accept-loss keep the rule that job ids never repeat: the job id sequence
//! of the store they leave behind is raised to the highest id the commit marker (and the
//! replaced database, if it can still be read) recorded, so a job id handed out after the
//! backup was taken is not handed out again.

use std::path::{Path, PathBuf};

use sqlx::sqlite::{SqliteConnectOptions, SqlitePool, SqlitePoolOptions};
use sqlx::Connection;

use tessera_api::JobState;

use super::marker::{self, CommitMark};
use super::sql::{self, Conn, DamagedRow};
use super::sqlite::{
    classify, commit_mark, connect_writer, open_error, preflight, quick_check, SqliteStore,
};
use super::{StoreError, StoreResult, DATABASE_FILE};

/// What [`check`] found. `Display` prints it for people, one finding per line.
#[derive(Debug, Clone, PartialEq)]
pub struct CheckReport {
    /// The database file.
    pub path: PathBuf,
    /// Whether the file exists.
    pub exists: bool,
    /// SQLite's `integrity_check`: `Ok` or the problems found.
    pub integrity: Result<(), String>,
    /// The schema version, if it could be read.
    pub schema_version: Option<i64>,
    /// The newest schema version this build knows.
    pub supported_version: i64,
    /// The database's commit generation and highest job id, if they could be read
    /// (stores older than schema version 3 have no generation until opened once).
    pub database: Option<CommitMark>,
    /// The commit marker: `Ok(None)` if there is none.
    pub marker: Result<Option<CommitMark>, String>,
    /// Jobs per state, if they could be read.
    pub jobs: Vec<(String, u64)>,
    /// Why a coordinator refuses to start on this store: the message of the start's
    /// error ([`preflight`]), word for word; `None` when it starts.
    pub refusal: Option<String>,
    /// The rows a read refuses (a checksum that does not match, a value that does not
    /// decode); `Err` if they could not be checked (the reason).
    pub damaged: Result<Vec<DamagedRow>, String>,
}

impl CheckReport {
    /// Whether a coordinator starts on this store (exit status other than 1 of
    /// `store check`).
    pub fn healthy(&self) -> bool {
        self.refusal.is_none()
    }

    /// Whether a coordinator starts on this store and every row reads back (exit status
    /// 0 of `store check`).
    pub fn clean(&self) -> bool {
        self.healthy() && self.damaged.as_ref().is_ok_and(Vec::is_empty)
    }

    /// Whether the database is behind its marker (one without a generation is behind
    /// any marker).
    pub fn behind(&self) -> bool {
        match (&self.database, &self.marker) {
            (Some(db), Ok(Some(m))) => db.is_behind(m),
            (None, Ok(Some(_))) => true,
            _ => false,
        }
    }
}

impl std::fmt::Display for CheckReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(f, "store: {}", self.path.display())?;
        if !self.exists {
            writeln!(f, "database: missing (a coordinator creates an empty one)")?;
        }
        match &self.integrity {
            _ if !self.exists => {}
            Ok(()) => writeln!(f, "integrity: ok")?,
            Err(e) => writeln!(f, "integrity: DAMAGED: {e}")?,
        }
        match self.schema_version {
            Some(v) if v <= self.supported_version => writeln!(
                f,
                "schema version: {v} (this build knows up to {})",
                self.supported_version
            )?,
            Some(v) => writeln!(
                f,
                "schema version: {v} is NEWER than this build knows ({}); use a newer tessera",
                self.supported_version
            )?,
            None => writeln!(f, "schema version: unreadable")?,
        }
        match &self.database {
            Some(db) => writeln!(f, "database: {db}")?,
            None => writeln!(
                f,
                "database: no commit generation (not opened by this build yet)"
            )?,
        }
        match &self.marker {
            Ok(Some(m)) => writeln!(f, "commit marker: {m}")?,
            Ok(None) => writeln!(f, "commit marker: none")?,
            Err(e) => writeln!(f, "commit marker: UNREADABLE: {e}")?,
        }
        if self.behind() {
            writeln!(
                f,
                "commit marker: the database is BEHIND its marker: acknowledged commits are missing"
            )?;
        }
        if !self.jobs.is_empty() {
            let jobs: Vec<String> = self.jobs.iter().map(|(s, n)| format!("{n} {s}")).collect();
            writeln!(f, "jobs: {}", jobs.join(", "))?;
        }
        match &self.damaged {
            Ok(rows) if rows.is_empty() => writeln!(
                f,
                "rows: ok (every job, tile checkpoint and scene reads back and matches its checksum)"
            )?,
            Ok(rows) => {
                writeln!(f, "rows: {} DAMAGED:", rows.len())?;
                for r in rows {
                    writeln!(f, "  {} {}: {}; {}", r.table, r.key, r.reason, action(r))?;
                }
            }
            Err(e) => writeln!(f, "rows: not checked: {e}")?,
        }
        match (&self.refusal, &self.damaged) {
            (Some(why), _) => write!(
                f,
                "verdict: NOT OK: a coordinator refuses to start on this store: {why}"
            ),
            (None, Ok(rows)) if !rows.is_empty() => write!(
                f,
                "verdict: DAMAGED ROWS: a coordinator starts on this store and handles the {} \
                 damaged rows as said above (docs/store.md, \"Checksums\")",
                rows.len()
            ),
            (None, _) => write!(f, "verdict: ok"),
        }
    }
}

/// A read-only connection to `path` (no journal-mode change, no migration: a check and
/// a backup change nothing).
async fn read_only(path: &Path) -> StoreResult<SqlitePool> {
    SqlitePoolOptions::new()
        .max_connections(1)
        .connect_with(
            SqliteConnectOptions::new()
                .filename(path)
                .read_only(true)
                .busy_timeout(std::time::Duration::from_secs(10)),
        )
        .await
        .map_err(|e| open_error(path, e))
}

/// What the coordinator does about a damaged row at its next start and after.
fn action(r: &DamagedRow) -> &'static str {
    let running = matches!(r.job, Some((_, Some(JobState::Queued | JobState::Running))));
    match (r.table, running) {
        ("tiles", true) => {
            "the coordinator drops this checkpoint at its next start and renders the tile again"
        }
        ("tiles", false) => {
            "reads of this frame's image are refused with this error (restore a backup to \
             recover it)"
        }
        ("jobs", true) => "the coordinator fails this job at its next start with this error",
        ("jobs", false) => "reads of this job (status, list, images) are refused with this error",
        _ => "jobs that render this scene fail with this error when they load it",
    }
}

/// Checks the store in `dir` without changing it: the start's checks ([`preflight`]:
/// SQLite's full `integrity_check`, the schema version, the commit marker), then every
/// row's checksum and decoding, and the jobs per state. Safe while a coordinator runs on
/// it.
pub async fn check(dir: &Path) -> CheckReport {
    let path = dir.join(DATABASE_FILE);
    let mut report = inspect(&path, Some(dir)).await;
    report.marker = marker::read_marker(dir);
    if !report.exists {
        // The start creates an empty database, which is behind any marker.
        report.refusal = match &report.marker {
            Ok(Some(m)) => Some(
                StoreError::BehindMarker {
                    path,
                    marker_path: marker::marker_path(dir),
                    database: CommitMark::default(),
                    marker: *m,
                }
                .to_string(),
            ),
            Ok(None) => None,
            Err(e) => Some(StoreError::BadMarker(e.clone()).to_string()),
        };
        report.damaged = Ok(Vec::new());
    }
    report
}

/// The checks of [`check`] on one database file (of any name, e.g. a backup); with `dir`
/// its data directory (the marker is compared), without it the file alone.
async fn inspect(file: &Path, dir: Option<&Path>) -> CheckReport {
    let mut report = CheckReport {
        path: file.to_path_buf(),
        exists: file.exists(),
        integrity: Err("the database file does not exist".into()),
        schema_version: None,
        supported_version: SqliteStore::SUPPORTED_SCHEMA,
        database: None,
        marker: Ok(None),
        jobs: Vec::new(),
        refusal: Some(format!(
            "the database file {} does not exist",
            file.display()
        )),
        damaged: Err("the database file does not exist".into()),
    };
    if !report.exists {
        return report;
    }
    let pool = match read_only(file).await {
        Ok(p) => p,
        Err(e) => {
            report.integrity = Err(e.to_string());
            report.refusal = Some(e.to_string());
            return report;
        }
    };
    let verdict = preflight(&pool, file, dir).await;
    report.integrity = match &verdict {
        Err(StoreError::Damaged { detail, .. }) => Err(detail.clone()),
        _ => Ok(()),
    };
    report.refusal = verdict.err().map(|e| e.to_string());
    report.schema_version = sqlx::query_scalar("SELECT MAX(version) FROM schema_version")
        .fetch_one(&pool)
        .await
        .ok()
        .flatten();
    report.database = commit_mark(&mut Conn::SqlitePool(&pool)).await.ok();
    let jobs: Vec<(String, i64)> =
        sqlx::query_as("SELECT state, COUNT(*) FROM jobs GROUP BY state ORDER BY state")
            .fetch_all(&pool)
            .await
            .unwrap_or_default();
    report.jobs = jobs
        .into_iter()
        .map(|(s, n)| (s, u64::try_from(n).unwrap_or(0)))
        .collect();
    report.damaged = match report.schema_version {
        _ if report.integrity.is_err() => {
            Err("the database is damaged (integrity check above)".into())
        }
        Some(v) if v >= CHECKSUM_SCHEMA => sql::damaged_rows(&mut Conn::SqlitePool(&pool))
            .await
            .map_err(|e| e.to_string()),
        _ => Err(format!(
            "the store has no row checksums yet (schema version below {CHECKSUM_SCHEMA}); the \
             coordinator computes them at its next start"
        )),
    };
    pool.close().await;
    report
}

/// The schema version that added row checksums.
const CHECKSUM_SCHEMA: i64 = 7;

/// Writes a consistent copy of the store in `dir` to `out` (which must not exist) with
/// SQLite's `VACUUM INTO`, safe while a coordinator runs on the store: it reads one
/// snapshot, so the copy holds every commit made before it started and none after.
/// The copy is fsynced and checked; returns its check report.
pub async fn backup(dir: &Path, out: &Path) -> StoreResult<CheckReport> {
    if out.exists() {
        return Err(StoreError::InvalidInput(format!(
            "{} exists: the backup goes to a new file",
            out.display()
        )));
    }
    let path = dir.join(DATABASE_FILE);
    if !path.exists() {
        return Err(StoreError::InvalidInput(format!(
            "there is no store at {}",
            path.display()
        )));
    }
    let out_str = out
        .to_str()
        .ok_or_else(|| StoreError::InvalidInput(format!("{} is not UTF-8", out.display())))?;
    let pool = read_only(&path).await?;
    sqlx::query("VACUUM INTO ?1")
        .bind(out_str)
        .execute(&pool)
        .await?;
    pool.close().await;
    std::fs::File::open(out)
        .and_then(|f| f.sync_all())
        .map_err(|e| StoreError::NotWritable {
            path: out.to_path_buf(),
            detail: e.to_string(),
        })?;
    Ok(inspect(out, None).await)
}

/// What [`restore`] and [`accept_loss`] did.
#[derive(Debug, Clone, PartialEq)]
pub struct Resealed {
    /// Where the replaced database files were moved (restore only, if there were any).
    pub moved_to: Option<PathBuf>,
    /// The job ids the store will never issue again (its sequence was raised to this).
    pub max_job_id: u64,
    /// The new commit marker.
    pub mark: CommitMark,
}

/// The highest job id and lease id the store in `dir` ever recorded: its marker's and,
/// if the database can still be read, its own.
async fn id_floor(dir: &Path) -> CommitMark {
    let from_marker = marker::read_marker(dir).ok().flatten().unwrap_or_default();
    let path = dir.join(DATABASE_FILE);
    let from_db = if path.exists() {
        match read_only(&path).await {
            Ok(pool) => {
                let m = commit_mark(&mut Conn::SqlitePool(&pool))
                    .await
                    .unwrap_or_default();
                pool.close().await;
                m
            }
            Err(_) => CommitMark::default(),
        }
    } else {
        CommitMark::default()
    };
    CommitMark {
        generation: 0,
        max_job_id: from_marker.max_job_id.max(from_db.max_job_id),
        lease_high_water: from_marker.lease_high_water.max(from_db.lease_high_water),
    }
}

/// Replaces the store in `dir` with the backup `file`, for a coordinator that is
/// **stopped**: the backup is checked first (integrity, schema version); the current
/// database and its `-wal`/`-shm` files are moved to `dir/replaced-UNIX_MS/`; the backup
/// is copied in, migrated, its job id sequence raised above every id the old store issued,
/// and the commit marker written for it.
pub async fn restore(dir: &Path, file: &Path) -> StoreResult<Resealed> {
    let report = inspect(file, None).await;
    if !report.healthy() {
        return Err(StoreError::InvalidInput(format!(
            "the backup {} is not usable:\n{report}",
            file.display()
        )));
    }
    std::fs::create_dir_all(dir).map_err(|source| StoreError::DataDir {
        path: dir.to_path_buf(),
        source,
    })?;
    let floor = id_floor(dir).await;
    let io = |path: &Path, e: std::io::Error| StoreError::NotWritable {
        path: path.to_path_buf(),
        detail: e.to_string(),
    };
    let incoming = dir.join(format!("{DATABASE_FILE}.restoring"));
    std::fs::copy(file, &incoming).map_err(|e| io(&incoming, e))?;
    std::fs::File::open(&incoming)
        .and_then(|f| f.sync_all())
        .map_err(|e| io(&incoming, e))?;
    let mut moved_to = None;
    let stamp = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis());
    for suffix in ["", "-wal", "-shm"] {
        let name = format!("{DATABASE_FILE}{suffix}");
        let from = dir.join(&name);
        if from.exists() {
            let aside = dir.join(format!("replaced-{stamp}"));
            std::fs::create_dir_all(&aside).map_err(|e| io(&aside, e))?;
            std::fs::rename(&from, aside.join(&name)).map_err(|e| io(&from, e))?;
            moved_to = Some(aside);
        }
    }
    let path = dir.join(DATABASE_FILE);
    std::fs::rename(&incoming, &path).map_err(|e| io(&path, e))?;
    std::fs::File::open(dir)
        .and_then(|f| f.sync_all())
        .map_err(|e| io(dir, e))?;
    let (max_job_id, mark) = reseal(dir, floor).await?;
    Ok(Resealed {
        moved_to,
        max_job_id,
        mark,
    })
}

/// Accepts the store in `dir` as it is, for a coordinator that is **stopped**: after
/// lost commits (the database is behind its marker) or to start empty (after the damaged
/// files were moved away; a new database is created). The database must pass the
/// integrity check. Its job id sequence is raised above every id the marker recorded, and
/// the marker rewritten for it.
pub async fn accept_loss(dir: &Path) -> StoreResult<Resealed> {
    let path = dir.join(DATABASE_FILE);
    if path.exists() {
        let report = check(dir).await;
        if let Err(e) = report.integrity {
            return Err(StoreError::Damaged { path, detail: e });
        }
    }
    let floor = id_floor(dir).await;
    let (max_job_id, mark) = reseal(dir, floor).await?;
    Ok(Resealed {
        moved_to: None,
        max_job_id,
        mark,
    })
}

/// Opens the database of `dir` (creating it if missing), brings its schema up to date,
/// raises its job id sequence and its lease-id high-water mark to `floor`'s, records
/// that no coordinator runs on it, bumps its generation and writes the marker. Returns
/// the highest job id and the new mark.
async fn reseal(dir: &Path, floor: CommitMark) -> StoreResult<(u64, CommitMark)> {
    let lease_floor = i64::try_from(floor.lease_high_water).map_err(|_| {
        StoreError::Corrupt(format!(
            "commit marker: lease_high_water {}",
            floor.lease_high_water
        ))
    })?;
    let floor = floor.max_job_id;
    let (writer, path) = connect_writer(dir, true).await?;
    quick_check(&writer, &path).await?;
    super::sqlite::migrate(&writer)
        .await
        .map_err(|e| classify(&path, e))?;
    let store = SqliteStore::from_writer(writer, path, dir).await?;
    let floor_i = i64::try_from(floor)
        .map_err(|_| StoreError::Corrupt(format!("commit marker: max_job_id {floor}")))?;
    let mark = {
        let mut conn = store.writer().acquire().await?;
        let mut tx = conn.begin_with("BEGIN IMMEDIATE").await?;
        // sqlite_sequence is an ordinary table: AUTOINCREMENT issues max(seq, max id) + 1.
        let n = sqlx::query("UPDATE sqlite_sequence SET seq = MAX(seq, ?1) WHERE name = 'jobs'")
            .bind(floor_i)
            .execute(&mut *tx)
            .await?
            .rows_affected();
        if n == 0 {
            sqlx::query("INSERT INTO sqlite_sequence (name, seq) VALUES ('jobs', ?1)")
                .bind(floor_i)
                .execute(&mut *tx)
                .await?;
        }
        sqlx::query(
            "UPDATE counters SET value = CASE name WHEN 'clean_shutdown' THEN 1 ELSE 0 END \
             WHERE name IN ('clean_shutdown', 'resuming_job')",
        )
        .execute(&mut *tx)
        .await?;
        // Fencing tokens never repeat either.
        sqlx::query("UPDATE counters SET value = MAX(value, ?1) WHERE name = 'lease_high_water'")
            .bind(lease_floor)
            .execute(&mut *tx)
            .await?;
        let mark = super::sqlite::bump_generation(&mut Conn::Sqlite(&mut tx)).await?;
        tx.commit().await?;
        mark
    };
    store.publish(mark).await?;
    use super::Store;
    store.close().await;
    Ok((mark.max_job_id, mark))
}

/// Rebuilds every index of the store in `dir` from its tables (SQLite's `REINDEX`), for a
/// coordinator that is **stopped**: the repair when SQLite's integrity check finds only
/// index problems (entries missing from or extra in an index), which the tables
/// themselves do not share. Returns the check of the store afterwards.
pub async fn reindex(dir: &Path) -> StoreResult<CheckReport> {
    let path = dir.join(DATABASE_FILE);
    if !path.exists() {
        return Err(StoreError::InvalidInput(format!(
            "there is no store at {}",
            path.display()
        )));
    }
    let (writer, path) = connect_writer(dir, false).await?;
    sqlx::query("REINDEX")
        .execute(&writer)
        .await
        .map_err(|e| open_error(&path, e))?;
    writer.close().await;
    Ok(check(dir).await)
}
