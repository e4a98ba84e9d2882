//! The durable store of the farm: the truth that survives `kill -9` (ARCHITECTURE.md §6).
//!
//! The coordinator keeps its working state in memory (the [`Scheduler`](tessera_farm::Scheduler)
//! and its accumulators) and writes everything that must survive a crash through the
//! [`Store`] trait:
//!
//! - **jobs** ([`NewJob`] in, [`JobRecord`] out): accepted submissions with their plan,
//!   frame range, priority and life-cycle state, optionally deduplicated by an idempotency
//!   key;
//! - **scenes**: uploaded scene files by content hash;
//! - **tile checkpoints** ([`TileCheckpointRef`] in, [`TileCheckpoint`] out): the merged
//!   per-pixel statistics of one tile of one frame, with the digests of the merged units,
//!   upserted as passes merge;
//! - the **lease high-water mark**, so fencing tokens never repeat after a restart;
//! - **convergence history** points per job ([`HistoryPoint`]);
//! - **worker fault events** ([`FaultEvent`]);
//! - the **quarantine list** ([`QuarantineRecord`]): workers a spot check found faulty,
//!   until an operator lifts their quarantine.
//!
//! Two implementations share one contract and one test suite (`tests/it/store.rs`):
//! [`SqliteStore`], the embedded default, on one SQLite file (WAL, `synchronous=FULL`), and
//! [`PostgresStore`] on a PostgreSQL database (docs/store.md, "PostgreSQL"). [`StoreUrl`]
//! is the coordinator's `--store` choice between them and [`open`] opens either as
//! `Arc<dyn Store>`.
//!
//! # Tile checkpoint format (version 1)
//!
//! A checkpoint row holds two little-endian binary blobs. The statistics blob:
//!
//! | bytes | content |
//! |-------|---------|
//! | 1     | format version, `1` |
//! | 4     | pixel count `n` (u32) |
//! | 68 n  | per pixel, row-major within the tile: `passes` (u32), then `mean[0..3]`, `m2[0..3]`, `mean_lum`, `m2_lum` (8 f64, IEEE 754 bits) |
//! | 20 n  | only for a tile with a bias channel (vcm, ppm; `TileCheckpoint::bias`): per pixel, `passes` (u32), then the bias estimates' `mean` and `m2` (2 f64; [`tessera_farm::BiasStats`]) |
//!
//! A blob without the bias records is byte for byte what it was before they existed; a
//! coordinator that predates them refuses a blob with them (its length does not match).
//!
//! The unit digest blob:
//!
//! | bytes | content |
//! |-------|---------|
//! | 1     | format version, `1` |
//! | 4     | unit count `u` (u32) |
//! | 16 u  | per merged unit in pass order: `first_pass` (u32), `pass_count` (u32), `digest` (u64) |
//!
//! A tile of an adaptive job also holds the adaptive policy's state after the same merge
//! (schema version 4; `NULL` for other jobs and for checkpoints written before), so a
//! restart resumes the policy where it was and a finished job's image is the
//! policy's, rebuilt from the store:
//!
//! | bytes | content |
//! |-------|---------|
//! | 1     | format version, `1` |
//! | 4     | pixel count `n` (u32) |
//! | 4     | passes consumed by the policy (u32) |
//! | 80 n  | per pixel, row-major within the tile: its kept statistics as in the statistics blob (68 bytes), then `stopped_at`, `needed`, `traced` (u32; [`tessera_farm::AdaptivePixel`]) |
//! | 20 n  | only for a tile with a bias channel (vcm, ppm; [`tessera_farm::AdaptiveTileCheckpoint::bias`]): per pixel, the bias records of the passes it keeps, laid out as in the statistics blob |
//!
//! As for the statistics blob, a policy blob without the bias records is what it was
//! before they existed (it restores a tile that estimates from the pass spread alone), and
//! a coordinator that predates them refuses one with them.
//!
//! f64 values are stored by their bits, so a round trip is bit-exact. Decoding checks the
//! version, the lengths, that the pixel count matches the tile of the job's plan, that
//! every value is finite, that no pixel has more passes than the tile merged, and that the
//! units cover passes `0..merged_passes` contiguously; any violation is
//! [`StoreError::CorruptTile`] naming the job, frame and tile.
//!
//! # Row checksums (schema version 7; PostgreSQL 6)
//!
//! Every row of `jobs`, `tiles` and `scenes` also holds a SHA-256 of the columns an image
//! depends on (`checksum.rs`; docs/store.md, "Checksums"), written with the row and
//! verified on every read after decoding, so a byte changed in a value that still decodes
//! is [`StoreError::CorruptTile`] or [`StoreError::Corrupt`] naming the row, never a
//! wrong image. The migration that added the column computed it for existing rows.

mod checksum;
mod codec;
pub mod maintenance;
pub mod marker;
mod postgres;
mod rows;
mod scene_quota;
mod sql;
mod sqlite;
mod watch;

pub use marker::{CommitMark, MARKER_FILE};
pub use postgres::PostgresStore;
pub use sql::DamagedRow;
pub use sqlite::{SqliteStore, DATABASE_FILE, MAX_RESUMES_WITHOUT_PROGRESS};
pub use watch::WatchedStore;

use async_trait::async_trait;
use tessera_api::{FrameRange, HistoryPoint, JobState};
use tessera_farm::{AdaptiveTileCheckpoint, BiasStats, FramePlan, JobId, PixelStats};

/// Current version of the tile checkpoint blob formats (the leading byte of each blob).
pub const CHECKPOINT_FORMAT_VERSION: u8 = 1;

/// Why a store operation failed.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// The database reported an error (I/O, locking, constraint, ...).
    #[error("database error: {0}")]
    Database(#[from] sqlx::Error),
    /// A `--store` URL that cannot be used (the message names it and says why).
    #[error("invalid store URL {url:?}: {reason}")]
    BadUrl {
        /// The URL as given (without a password).
        url: String,
        /// What is wrong with it.
        reason: String,
    },
    /// The database server cannot be reached, refused the login, or the connection was
    /// lost (PostgreSQL). Transient: not a [`StoreError::is_write_failure`].
    #[error("cannot reach the PostgreSQL store {url}: {detail}")]
    Unreachable {
        /// The server's URL (without a password).
        url: String,
        /// The underlying error.
        detail: String,
    },
    /// The data directory could not be created.
    #[error("cannot create data directory {path}: {source}")]
    DataDir {
        /// The directory.
        path: std::path::PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// The job does not exist.
    #[error("job {0} does not exist")]
    JobNotFound(JobId),
    /// The caller passed a value the store refuses to write (the message names it).
    #[error("invalid store input: {0}")]
    InvalidInput(String),
    /// A stored tile checkpoint cannot be decoded or does not fit its job's plan.
    #[error("corrupt checkpoint of job {job}, frame {frame}, tile {tile}: {reason}")]
    CorruptTile {
        /// The job.
        job: JobId,
        /// The frame.
        frame: u32,
        /// The tile index.
        tile: u32,
        /// What is wrong.
        reason: String,
    },
    /// Another stored record is invalid (the message names the table, row and field).
    #[error("corrupt store record: {0}")]
    Corrupt(String),
    /// The database was written by a newer build with a schema this build does not know.
    #[error("database schema version {found} is newer than the newest this build knows ({supported}); use a newer tessera")]
    SchemaTooNew {
        /// Version found in the database.
        found: i64,
        /// Newest version this build can migrate to.
        supported: i64,
    },
    /// The database file is damaged (SQLite's check failed, or it is not a database).
    /// The coordinator refuses to start on it.
    #[error(
        "the store {path} is damaged: {detail}. The coordinator will not start on it. \
         Recover (docs/store.md): with the coordinator stopped, either restore a backup \
         with `tessera store restore --data {dir} BACKUP_FILE`, or move the database and \
         its -wal and -shm files out of the data directory (keep them for inspection) and \
         run `tessera store accept-loss --data {dir}` to start with an empty store that \
         never issues a job id again",
        dir = dir_of(path)
    )]
    Damaged {
        /// The database file.
        path: std::path::PathBuf,
        /// What the check found.
        detail: String,
    },
    /// The database is behind its commit marker ([`marker`]): acknowledged commits are
    /// missing (a deleted or damaged `-wal` file, a database replaced by an older copy).
    #[error(
        "the store {path} is behind its commit marker {marker_path}: the database has \
         {database}, the marker recorded {marker} when the last acknowledged commit \
         returned. Jobs that were accepted are missing (was the {path}-wal file deleted \
         or damaged, or the database replaced by an older copy?). The coordinator will \
         not start on it. Recover (docs/store.md): with the coordinator stopped, restore \
         a backup with `tessera store restore --data {dir} BACKUP_FILE`, or accept the \
         loss with `tessera store accept-loss --data {dir}` (the missing commits stay \
         lost; job ids are never issued again)",
        dir = dir_of(path)
    )]
    BehindMarker {
        /// The database file.
        path: std::path::PathBuf,
        /// The marker file.
        marker_path: std::path::PathBuf,
        /// What the database holds.
        database: CommitMark,
        /// What the marker recorded.
        marker: CommitMark,
    },
    /// The commit marker is missing although the database has a commit generation: the
    /// database was opened by a coordinator that wrote a marker, so the marker was
    /// deleted, and acknowledged commits may have been deleted with it (the `-wal` file)
    /// with nothing left to tell how many.
    #[error(
        "the commit marker {marker_path} of the store {path} is missing, but the database \
         has {database}: a coordinator wrote a marker for it, so the marker was deleted, \
         and acknowledged commits may have been lost with it (a deleted {path}-wal file) \
         without a trace. The coordinator will not start on it. Recover (docs/store.md): \
         with the coordinator stopped, restore the marker if you have it, or restore a \
         backup with `tessera store restore --data {dir} BACKUP_FILE`, or, if only the \
         marker was deleted (the -wal file was kept), accept the store as it is with \
         `tessera store accept-loss --data {dir}`",
        dir = dir_of(path)
    )]
    MarkerMissing {
        /// The database file.
        path: std::path::PathBuf,
        /// The missing marker file.
        marker_path: std::path::PathBuf,
        /// What the database holds.
        database: CommitMark,
    },
    /// The marker file exists but cannot be read.
    #[error(
        "the commit marker of the store cannot be read: {0}. Recover (docs/store.md): \
         check the store with `tessera store check --data DIR`, then restore a backup or \
         run `tessera store accept-loss --data DIR`"
    )]
    BadMarker(String),
    /// A write of a coordinator that is no longer the active one (high availability on
    /// PostgreSQL: another coordinator took the leadership and raised the fencing epoch,
    /// docs/store.md). Refused so that a deposed coordinator never overwrites the new
    /// one's state.
    #[error(
        "this coordinator is no longer the active one (fencing epoch {ours}, the store's \
         is {current}): another coordinator took over; the write was refused"
    )]
    NotLeader {
        /// The epoch this coordinator took.
        ours: i64,
        /// The store's epoch now.
        current: i64,
    },
    /// A write failed earlier while the coordinator ran ([`WatchedStore`]): it accepts no
    /// new work until it is restarted.
    #[error(
        "the store stopped taking writes ({0}); this coordinator accepts no new work until \
         it is restarted (free space or fix permissions first; docs/store.md)"
    )]
    Failing(String),
    /// A write failed at open (the probe) or the commit marker could not be written: the
    /// store cannot take writes (read-only file, directory or filesystem; full disk).
    #[error(
        "the store {path} is not writable: {detail}. Check that the data directory and \
         the files in it are writable by this user, that the filesystem is mounted \
         read-write and that it has free space"
    )]
    NotWritable {
        /// The database or marker file.
        path: std::path::PathBuf,
        /// The underlying error.
        detail: String,
    },
    /// The store's disk is full: a write failed for want of space (SQLite's `FULL`, or
    /// `ENOSPC`), or the coordinator started on a full disk and serves reads only. Writes
    /// resume by themselves once space is freed (docs/store.md, "When the disk is full").
    #[error(
        "the disk of the store is full ({0}): this coordinator serves reads and accepts no \
         new work until space is freed; it resumes by itself then (docs/store.md)"
    )]
    DiskFull(String),
}

/// The data directory of a database path, for the recovery commands in messages.
fn dir_of(path: &std::path::Path) -> std::path::Display<'_> {
    path.parent().unwrap_or(std::path::Path::new(".")).display()
}

impl StoreError {
    /// Whether this error means the store cannot take writes any more (a full disk, an
    /// I/O error, a read-only or damaged file), as opposed to a bad input, a missing row
    /// or a transient lock: the coordinator then stops accepting work (docs/store.md).
    pub fn is_write_failure(&self) -> bool {
        // SQLite primary result codes (the low byte of the extended code).
        const PERM: i64 = 3;
        const READONLY: i64 = 8;
        const IOERR: i64 = 10;
        const CORRUPT: i64 = 11;
        const FULL: i64 = 13;
        const CANTOPEN: i64 = 14;
        const NOTADB: i64 = 26;
        match self {
            Self::Database(sqlx::Error::Io(_)) => true,
            Self::Database(sqlx::Error::Database(e))
                if e.try_downcast_ref::<sqlx::postgres::PgDatabaseError>()
                    .is_some() =>
            {
                // PostgreSQL SQLSTATEs: disk full, I/O error, data or index corrupted, a
                // read-only transaction (the server is a hot standby).
                e.code()
                    .is_some_and(|c| matches!(&*c, "53100" | "58030" | "XX001" | "XX002" | "25006"))
            }
            Self::Database(sqlx::Error::Database(e)) => e
                .code()
                .and_then(|c| c.parse::<i64>().ok())
                .is_some_and(|c| {
                    matches!(
                        c & 0xff,
                        PERM | READONLY | IOERR | CORRUPT | FULL | CANTOPEN | NOTADB
                    )
                }),
            // A deposed coordinator must stop accepting work as if its store had failed.
            Self::NotWritable { .. }
            | Self::DiskFull(_)
            | Self::Damaged { .. }
            | Self::Failing(_)
            | Self::NotLeader { .. } => true,
            _ => false,
        }
    }
}

impl StoreError {
    /// Whether this error says the disk is full (SQLite's `FULL`, PostgreSQL's
    /// `53100 disk_full`, an `ENOSPC` I/O error, [`StoreError::DiskFull`]): a write
    /// failure that freeing space cures, answered 507 rather than 503.
    pub fn is_disk_full(&self) -> bool {
        const FULL: i64 = 13;
        match self {
            Self::DiskFull(_) => true,
            // The write probe and the commit marker keep the I/O error as text: ENOSPC
            // and EDQUOT as `std::io::Error` shows them, or SQLite's FULL.
            Self::NotWritable { detail, .. } => {
                ["os error 28)", "os error 122)", "database or disk is full"]
                    .iter()
                    .any(|m| detail.contains(m))
            }
            Self::Database(sqlx::Error::Io(e)) => e.kind() == std::io::ErrorKind::StorageFull,
            Self::Database(sqlx::Error::Database(e)) => e.code().is_some_and(|c| {
                &*c == "53100" || c.parse::<i64>().is_ok_and(|c| c & 0xff == FULL)
            }),
            _ => false,
        }
    }
}

/// What [`Store::delete_scene`] did.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum SceneDeletion {
    /// The scene was deleted.
    Deleted,
    /// No scene has this hash.
    Missing,
    /// Unfinished (queued or running) jobs need the scene: these, lowest id first.
    /// Nothing was deleted.
    Needed(Vec<JobId>),
}

/// Where the coordinator keeps its store: the value of `--store`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum StoreUrl {
    /// `sqlite:DIR`: a [`SqliteStore`] in the data directory `DIR` (the database file is
    /// `DIR/tessera.sqlite3`, beside its commit marker).
    Sqlite(std::path::PathBuf),
    /// `postgres://...` or `postgresql://...`: a [`PostgresStore`] (the URL verbatim).
    Postgres(String),
}

impl StoreUrl {
    /// Parses `sqlite:PATH`, `postgres://...` or `postgresql://...`.
    /// [`StoreError::BadUrl`] names the URL and what is wrong.
    pub fn parse(s: &str) -> StoreResult<Self> {
        let bad = |reason: &str| StoreError::BadUrl {
            url: postgres::redact(s),
            reason: reason.to_string(),
        };
        if let Some(path) = s.strip_prefix("sqlite:") {
            // `sqlite://PATH` is accepted too (sqlx's spelling).
            let path = path.strip_prefix("//").unwrap_or(path);
            if path.is_empty() {
                return Err(bad(
                    "sqlite: needs a data directory, e.g. sqlite:tessera-data",
                ));
            }
            Ok(Self::Sqlite(path.into()))
        } else if s.starts_with("postgres://") || s.starts_with("postgresql://") {
            use std::str::FromStr;
            sqlx::postgres::PgConnectOptions::from_str(s).map_err(|e| bad(&e.to_string()))?;
            Ok(Self::Postgres(s.to_string()))
        } else {
            Err(bad(
                "expected sqlite:PATH, postgres://USER@HOST:PORT/DB or postgresql://...",
            ))
        }
    }
}

impl std::fmt::Display for StoreUrl {
    /// The URL as `--store` takes it, without a password.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Sqlite(dir) => write!(f, "sqlite:{}", dir.display()),
            Self::Postgres(url) => f.write_str(&postgres::redact(url)),
        }
    }
}

impl std::str::FromStr for StoreUrl {
    type Err = StoreError;
    fn from_str(s: &str) -> StoreResult<Self> {
        Self::parse(s)
    }
}

/// Opens the store at `url` ([`SqliteStore::open`] or [`PostgresStore::open`]).
pub async fn open(url: &StoreUrl) -> StoreResult<std::sync::Arc<dyn Store>> {
    Ok(match url {
        StoreUrl::Sqlite(dir) => std::sync::Arc::new(SqliteStore::open(dir).await?),
        StoreUrl::Postgres(url) => std::sync::Arc::new(PostgresStore::open(url).await?),
    })
}

/// Shorthand for results of store operations.
pub type StoreResult<T> = Result<T, StoreError>;

/// A job to insert: everything the coordinator needs to resume it after a restart.
#[derive(Debug, Clone, PartialEq)]
pub struct NewJob {
    /// The settings as submitted, in canonical JSON (the store keeps the text verbatim).
    pub settings_json: String,
    /// The frame plan (resolution, tiles, passes).
    pub plan: FramePlan,
    /// Frames to render (inclusive); `start <= end`.
    pub frames: FrameRange,
    /// Passes per work unit (at least 1), so units are cut the same way after a restart.
    pub passes_per_unit: u32,
    /// Scheduling priority (higher first).
    pub priority: i32,
    /// `"builtin:NAME"` or the content hash of an uploaded scene.
    pub scene_ref: String,
    /// A label for people.
    pub name: Option<String>,
    /// Deduplication key of the submission: a second insert with the same key returns the
    /// first job.
    pub idempotency_key: Option<String>,
    /// When the job was accepted, Unix milliseconds (at most `i64::MAX`).
    pub created_unix_ms: u64,
    /// The render plan's JSON (`tessera_farm::RenderPlan::to_json`), kept for the status
    /// of the job once it is read back from the store.
    pub render_plan_json: Option<String>,
    /// Why the job's error estimate may be optimistic, if the plan says so
    /// (`tessera_farm::job::ResolvedJob::error_estimate_caveat`).
    pub error_estimate_caveat: Option<String>,
}

/// A stored job.
#[derive(Debug, Clone, PartialEq)]
pub struct JobRecord {
    /// Job id: assigned by the store, increasing, never reused.
    pub id: JobId,
    /// The settings as submitted, verbatim.
    pub settings_json: String,
    /// The frame plan.
    pub plan: FramePlan,
    /// Frames to render (inclusive).
    pub frames: FrameRange,
    /// Passes per work unit.
    pub passes_per_unit: u32,
    /// Scheduling priority (higher first).
    pub priority: i32,
    /// `"builtin:NAME"` or the content hash of an uploaded scene.
    pub scene_ref: String,
    /// A label for people.
    pub name: Option<String>,
    /// The idempotency key it was submitted with, if any.
    pub idempotency_key: Option<String>,
    /// Life-cycle state.
    pub state: JobState,
    /// Why it failed (or any message stored with the last state change).
    pub error: Option<String>,
    /// When it was accepted, Unix milliseconds.
    pub created_unix_ms: u64,
    /// When it first became `running`, Unix milliseconds.
    pub started_unix_ms: Option<u64>,
    /// When it reached a terminal state, Unix milliseconds.
    pub finished_unix_ms: Option<u64>,
    /// The render plan's JSON as accepted; `None` for jobs stored by builds before schema
    /// version 6 (PostgreSQL 5).
    pub render_plan_json: Option<String>,
    /// Why the job's error estimate may be optimistic; `None` when it has no caveat or
    /// was stored before schema version 6 (PostgreSQL 5).
    pub error_estimate_caveat: Option<String>,
    /// The estimator the last stored history point's error estimate was computed with
    /// (as [`Store::append_history`] was given it); `None` when every point was stored
    /// before schema version 9 (PostgreSQL 8), or none named one. Not covered by the
    /// row's checksum: it changes as the job runs.
    pub error_estimator: Option<String>,
}

/// Order of [`Store::list_jobs`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash)]
pub enum JobOrder {
    /// Highest id first (the API's `GET /jobs` order). The default.
    #[default]
    NewestFirst,
    /// Lowest id first (submission order).
    OldestFirst,
}

/// One page request of [`Store::list_jobs`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct JobQuery {
    /// Only jobs strictly after this id in the chosen order (the last id of the previous
    /// page); `None` for the first page.
    pub cursor: Option<JobId>,
    /// Page size; 0 gives an empty page.
    pub limit: u32,
    /// Only jobs in this state.
    pub state: Option<JobState>,
    /// Order of the page.
    pub order: JobOrder,
}

impl JobQuery {
    /// The first page of `limit` jobs, newest first, any state.
    pub fn first(limit: u32) -> Self {
        Self {
            cursor: None,
            limit,
            state: None,
            order: JobOrder::NewestFirst,
        }
    }
}

/// One merged unit of a tile: its pass range and [`UnitResult::digest`](tessera_farm::UnitResult::digest),
/// kept so that a late duplicate of it can still be compared after a restart.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct UnitDigest {
    /// First pass of the unit.
    pub first_pass: u32,
    /// Number of passes (at least 1).
    pub pass_count: u32,
    /// Digest of the unit's result.
    pub digest: u64,
}

/// A tile checkpoint to save, borrowing the accumulator's data.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TileCheckpointRef<'a> {
    /// The job.
    pub job: JobId,
    /// The frame (within the job's frame range).
    pub frame: u32,
    /// The tile index (within the job's plan).
    pub tile: u32,
    /// Passes merged: the statistics cover passes `0..merged_passes`.
    pub merged_passes: u32,
    /// Per-pixel statistics, row-major within the tile (`rect.pixel_count()` entries).
    pub pixels: &'a [PixelStats],
    /// The merged units in pass order, tiling `0..merged_passes` exactly.
    pub units: &'a [UnitDigest],
    /// Samples the renderers dropped as invalid (NaN, infinite, negative) in those units.
    pub rejected_samples: u64,
    /// Adaptive jobs: the policy's state after the same merge; `None` for other jobs.
    pub adaptive: Option<&'a AdaptiveTileCheckpoint>,
    /// Biased techniques (vcm, ppm): the bias channel's per-pixel statistics
    /// (`TileAccumulator::bias`), stored after the pixels' records; `None` for other jobs.
    pub bias: Option<&'a [BiasStats]>,
}

/// What a status needs of a tile checkpoint, without its pixels.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TileSummary {
    /// The frame.
    pub frame: u32,
    /// The tile index.
    pub tile: u32,
    /// Passes merged.
    pub merged_passes: u32,
    /// Samples rejected as invalid in the merged passes.
    pub rejected_samples: u64,
}

/// A stored tile checkpoint (see the [module docs](self) for the format).
#[derive(Debug, Clone, PartialEq)]
pub struct TileCheckpoint {
    /// The job.
    pub job: JobId,
    /// The frame.
    pub frame: u32,
    /// The tile index.
    pub tile: u32,
    /// Passes merged: the statistics cover passes `0..merged_passes`.
    pub merged_passes: u32,
    /// Per-pixel statistics, row-major within the tile.
    pub pixels: Vec<PixelStats>,
    /// The merged units in pass order, tiling `0..merged_passes` exactly.
    pub units: Vec<UnitDigest>,
    /// Samples the renderers dropped as invalid (NaN, infinite, negative) in those units;
    /// 0 for checkpoints stored before schema version 2.
    pub rejected_samples: u64,
    /// Adaptive jobs: the policy's state after the same merge; `None` for other jobs and
    /// for checkpoints stored before schema version 4.
    pub adaptive: Option<AdaptiveTileCheckpoint>,
    /// Biased techniques: the bias channel's per-pixel statistics; `None` for other jobs
    /// and for checkpoints stored before the channel existed.
    pub bias: Option<Vec<BiasStats>>,
}

impl TileCheckpoint {
    /// A borrowed view, e.g. to save it again.
    pub fn as_ref(&self) -> TileCheckpointRef<'_> {
        TileCheckpointRef {
            job: self.job,
            frame: self.frame,
            tile: self.tile,
            merged_passes: self.merged_passes,
            pixels: &self.pixels,
            units: &self.units,
            rejected_samples: self.rejected_samples,
            adaptive: self.adaptive.as_ref(),
            bias: self.bias.as_deref(),
        }
    }
}

/// What a faulty worker did.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum FaultKind {
    /// A result was refused: wrong size, non-finite or negative values, bad pass range.
    InvalidResult,
    /// A duplicate result differed from the merged copy of the same unit.
    DuplicateMismatch,
    /// A result answered a lease the worker does not hold (wrong fencing token).
    LeaseViolation,
    /// A spot check found the worker's copy of a unit unlike the copy other workers
    /// agree on; the worker was quarantined (ARCHITECTURE.md §6).
    SpotCheckMismatch,
}

impl FaultKind {
    /// The stored string form, e.g. `"invalid_result"`.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::InvalidResult => "invalid_result",
            Self::DuplicateMismatch => "duplicate_mismatch",
            Self::LeaseViolation => "lease_violation",
            Self::SpotCheckMismatch => "spot_check_mismatch",
        }
    }

    /// Parses [`FaultKind::as_str`] output.
    pub fn parse(s: &str) -> Option<Self> {
        [
            Self::InvalidResult,
            Self::DuplicateMismatch,
            Self::LeaseViolation,
            Self::SpotCheckMismatch,
        ]
        .into_iter()
        .find(|k| k.as_str() == s)
    }
}

/// A faulty-worker event.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FaultEvent {
    /// The name the worker registered with.
    pub worker: String,
    /// The job concerned, if known (the store does not require it to exist).
    pub job: Option<JobId>,
    /// What happened.
    pub kind: FaultKind,
    /// Details for people (e.g. the validation error).
    pub message: String,
    /// When, Unix milliseconds (at most `i64::MAX`).
    pub unix_ms: u64,
}

/// Which fault events [`Store::count_faults`] and [`Store::list_faults`] consider; the
/// default matches all.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct FaultFilter {
    /// Only events of this job.
    pub job: Option<JobId>,
    /// Only events of the worker with this name.
    pub worker: Option<String>,
}

/// A quarantined worker as the store keeps it (schema version 5; ARCHITECTURE.md §6):
/// keyed by what a quarantine follows, the name the worker registers with and its TLS
/// identity, so that a coordinator restarted on the store quarantines the worker again
/// as soon as it registers.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct QuarantineRecord {
    /// The name the worker registered with.
    pub worker: String,
    /// The common name of its TLS client certificate (mutual TLS); `None` without one.
    /// Stored as `''` for `None`, so an empty common name reads back as `None`.
    pub identity: Option<String>,
    /// Why it was quarantined (the spot check that found its copy unlike the others').
    pub reason: String,
    /// When, Unix milliseconds (at most `i64::MAX`).
    pub unix_ms: u64,
}

/// How the previous coordinator run on a store ended ([`Store::begin_run`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash)]
pub struct PreviousRun {
    /// It shut down gracefully ([`Store::end_run`]), or there was none.
    pub clean: bool,
    /// It died while resuming this job at its start.
    pub resuming: Option<JobId>,
}

/// The durable state of the farm.
///
/// Contract shared by every implementation:
/// - **Durability**: when a method that writes returns `Ok`, the write is committed and
///   survives a crash of the process (and, for [`SqliteStore`], of the machine; for
///   [`PostgresStore`], of the database server, with its default `synchronous_commit`). A method
///   that returns `Err` wrote nothing. Multi-row writes ([`Store::save_tiles`]) are atomic.
/// - **Validation**: inputs the store could not read back are refused with
///   [`StoreError::InvalidInput`] (invalid plans, tile checkpoints that do not fit their
///   job's plan, non-finite history values, integers above `i64::MAX`). Stored data that
///   cannot be decoded or does not match its row checksum is reported as
///   [`StoreError::CorruptTile`] or [`StoreError::Corrupt`] naming the row, never a panic
///   and never a wrong value.
/// - **Concurrency**: every method may be called concurrently from many tasks; writes are
///   serialized by the store. Concurrent saves of the *same* tile are not ordered: the
///   caller must not race them (the last committed save wins).
/// - **Ids**: job ids are assigned by the store, increase with insertion order and are
///   never reused, even after a restart.
/// - **Commit marker** ([`SqliteStore`]): a new job, a job's state change, a newly
///   stored scene and a raised lease-id high-water mark are also recorded in the commit marker ([`marker`]) before the method
///   returns. If that write fails the method returns [`StoreError::NotWritable`] although
///   the transaction committed (the store is failing; the coordinator stops accepting
///   work).
///
/// The trait is object safe; hold it as `Arc<dyn Store>`.
#[async_trait]
pub trait Store: Send + Sync {
    /// Inserts a job in state [`JobState::Queued`].
    ///
    /// Returns `(id, true)` for a new job. If `idempotency_key` is set and a job with the
    /// same key exists, nothing is written and `(existing id, false)` is returned, whatever
    /// the other fields (compare them with [`Store::get_job`] to detect a conflicting
    /// reuse of a key). Refuses an invalid plan, `frames.start > frames.end` and
    /// `passes_per_unit == 0`.
    async fn insert_job(&self, job: NewJob) -> StoreResult<(JobId, bool)>;

    /// The job with this id, if it exists.
    async fn get_job(&self, id: JobId) -> StoreResult<Option<JobRecord>>;

    /// One page of jobs (see [`JobQuery`]). Pass the last id of a page as the next
    /// page's cursor; a page shorter than `limit` is the last one.
    async fn list_jobs(&self, query: JobQuery) -> StoreResult<Vec<JobRecord>>;

    /// Changes the state of a job and stores `error` with it (`None` clears it).
    ///
    /// `now_unix_ms` is recorded as the start time on the first change to
    /// [`JobState::Running`] and as the finish time on a change to a terminal state.
    /// A terminal state is final: on a job that is already done, failed or canceled
    /// nothing changes and `Ok(false)` is returned; otherwise `Ok(true)`.
    /// [`StoreError::JobNotFound`] if the job does not exist.
    async fn set_job_state(
        &self,
        id: JobId,
        state: JobState,
        error: Option<String>,
        now_unix_ms: u64,
    ) -> StoreResult<bool>;

    /// How many jobs the store holds in each state (states without jobs omitted): the
    /// job counts of `/metrics`, right after a restart too.
    async fn count_jobs_by_state(&self) -> StoreResult<Vec<(JobState, u64)>>;

    /// The jobs to resume after a restart: every queued or running job, oldest first (the
    /// order to add them to the scheduler so first-come-first-served is kept).
    async fn jobs_to_resume(&self) -> StoreResult<Vec<JobRecord>>;

    /// Stores a scene file under its content hash (computed by the caller). Idempotent:
    /// returns `true` if it was stored now, `false` if the hash was already present (the
    /// stored bytes are kept).
    async fn put_scene(&self, hash: &str, bytes: &[u8]) -> StoreResult<bool>;

    /// The scene file with this hash, if stored.
    async fn get_scene(&self, hash: &str) -> StoreResult<Option<Vec<u8>>>;

    /// Whether a scene with this hash is stored (without reading it).
    async fn scene_exists(&self, hash: &str) -> StoreResult<bool>;

    /// Bytes the stored scenes hold: all of them (`owner` `None`), or those first
    /// uploaded by `owner` ([`Store::record_scene_upload`]). Reads sizes, not bytes.
    async fn scene_bytes(&self, owner: Option<&str>) -> StoreResult<u64>;

    /// Records that `owner` (an API client's name) uploaded the stored scene `hash` now:
    /// the first uploader stays its owner; the time is the newest upload's.
    async fn record_scene_upload(&self, hash: &str, owner: &str) -> StoreResult<()>;

    /// Deletes the scene `hash` and its upload record, unless a queued or running job
    /// refers to it ([`SceneDeletion::Needed`], nothing deleted); checked in the write's
    /// transaction.
    async fn delete_scene(&self, hash: &str) -> StoreResult<SceneDeletion>;

    /// Up to `limit` stored scenes, oldest first, that no queued or running job needs
    /// and nothing used since `cutoff_unix_ms` (stored or uploaded again, or a job of
    /// them created or finished): what scene retention deletes.
    async fn unused_scenes(&self, cutoff_unix_ms: u64, limit: u32) -> StoreResult<Vec<String>>;

    /// Saves tile checkpoints atomically: one row per (job, frame, tile), replacing any
    /// earlier checkpoint of the same tile.
    ///
    /// Each checkpoint is checked against its job's plan: the job exists
    /// ([`StoreError::JobNotFound`]), the frame is in its range, the tile exists, there is
    /// one statistic per tile pixel, `merged_passes` is within the plan, no pixel has more
    /// passes than `merged_passes`, every value is finite and the units tile
    /// `0..merged_passes` in order ([`StoreError::InvalidInput`]). On any error nothing is
    /// saved.
    async fn save_tiles(&self, tiles: &[TileCheckpointRef<'_>]) -> StoreResult<()>;

    /// Saves one tile checkpoint; see [`Store::save_tiles`].
    async fn save_tile(&self, tile: TileCheckpointRef<'_>) -> StoreResult<()> {
        self.save_tiles(std::slice::from_ref(&tile)).await
    }

    /// The tile checkpoints of a job (of one frame if `frame` is given), ordered by frame
    /// then tile. [`StoreError::JobNotFound`] if the job does not exist;
    /// [`StoreError::CorruptTile`] if a checkpoint cannot be decoded or does not fit the
    /// plan.
    async fn load_tiles(&self, job: JobId, frame: Option<u32>) -> StoreResult<Vec<TileCheckpoint>>;

    /// The merged pass and rejected sample counts of every checkpointed tile of a job,
    /// ordered by frame then tile: what a status needs, without reading pixels.
    async fn tile_summaries(&self, job: JobId) -> StoreResult<Vec<TileSummary>>;

    /// The lease-id high-water mark: the largest value ever passed to
    /// [`Store::record_lease_high_water`], 0 initially.
    ///
    /// A restarted coordinator starts issuing lease ids above it
    /// ([`Scheduler::new`](tessera_farm::Scheduler::new)`(lease_ms, max_lease_id)`). To keep
    /// this cheap, reserve ids in blocks: record `next_id + BLOCK` before issuing ids up
    /// to it, so fencing tokens never repeat even after `kill -9`.
    async fn max_lease_id(&self) -> StoreResult<u64>;

    /// Raises the lease-id high-water mark to `lease_id` (a lower value changes nothing).
    async fn record_lease_high_water(&self, lease_id: u64) -> StoreResult<()>;

    /// The key that seals leases (`Lease.fence`, ARCHITECTURE.md §6): stored beside the
    /// lease-id high-water mark, as the four 64-bit counters `fence_key_0..3`. The first
    /// call on a store keeps `fresh` (random bytes the caller drew) and returns it; every
    /// later call, of any coordinator on the store, returns that same key, so a restarted
    /// or succeeding coordinator recognises the leases of the one before.
    async fn fence_key(&self, fresh: [u8; 32]) -> StoreResult<[u8; 32]>;

    /// Appends a convergence history point to a job, and with it the name of the
    /// estimator its error estimate was computed with, if given (the job's
    /// [`JobRecord::error_estimator`] from then on). Values must be finite
    /// ([`StoreError::InvalidInput`]); [`StoreError::JobNotFound`] if the job does not
    /// exist.
    async fn append_history(
        &self,
        job: JobId,
        point: HistoryPoint,
        estimator: Option<&str>,
    ) -> StoreResult<()>;

    /// A job's history points in the order they were appended (empty for an unknown job).
    async fn list_history(&self, job: JobId) -> StoreResult<Vec<HistoryPoint>>;

    /// Records a faulty-worker event.
    async fn record_fault(&self, fault: &FaultEvent) -> StoreResult<()>;

    /// Number of fault events matching the filter.
    async fn count_faults(&self, filter: &FaultFilter) -> StoreResult<u64>;

    /// The newest `limit` fault events matching the filter, newest first.
    async fn list_faults(&self, filter: &FaultFilter, limit: u32) -> StoreResult<Vec<FaultEvent>>;

    /// Records that a worker is quarantined. One row per (worker, identity): if one is
    /// stored already it is kept as it is (the first reason and time, since when the
    /// worker is distrusted) and `Ok(false)` is returned; `Ok(true)` for a new row.
    async fn record_quarantine(&self, quarantine: &QuarantineRecord) -> StoreResult<bool>;

    /// Every stored quarantine, ordered by worker name then identity (`None` first).
    async fn list_quarantines(&self) -> StoreResult<Vec<QuarantineRecord>>;

    /// Removes the stored quarantines of the worker named `worker`, under any identity
    /// (an operator lifted it); returns how many rows were removed, 0 if none (so a
    /// second call changes nothing).
    async fn delete_quarantines(&self, worker: &str) -> StoreResult<u64>;

    /// Ids of the jobs to resume (every queued or running job), oldest first. Unlike
    /// [`Store::jobs_to_resume`] a row that cannot be decoded does not fail the call:
    /// [`Store::get_job`] then fails for that id alone, and that job alone can be failed.
    async fn job_ids_to_resume(&self) -> StoreResult<Vec<JobId>>;

    /// Starts a coordinator run: returns how the previous run ended and records that a
    /// run is in progress, so the next start can tell whether this one crashed. Also
    /// deletes the tile checkpoints of queued and running jobs that a read would refuse
    /// (damaged: a checksum mismatch, a blob that does not decode), each logged naming
    /// it, so that resuming the job renders those tiles again instead of failing it.
    async fn begin_run(&self) -> StoreResult<PreviousRun>;

    /// Records that the run ended gracefully (called once the coordinator stopped).
    async fn end_run(&self) -> StoreResult<()>;

    /// Called by a starting coordinator just before it resumes `job`: records that it is
    /// resuming it (see [`PreviousRun::resuming`]) and returns the job's count of
    /// consecutive resumes without progress. The count restarts from 0 when the job's
    /// merged passes changed since its previous resume, then goes up by one if `count`
    /// (the previous run crashed while this job was in hand).
    /// [`StoreError::JobNotFound`] if the job does not exist.
    async fn record_resume(&self, job: JobId, count: bool) -> StoreResult<u32>;

    /// Records that the start finished resuming jobs (clears [`PreviousRun::resuming`]).
    async fn resumes_done(&self) -> StoreResult<()>;

    /// Checks that the store answers (for `/healthz`).
    async fn ping(&self) -> StoreResult<()>;

    /// Waits for pending writes and closes the store; later calls fail. Dropping the store
    /// without closing it loses nothing that was committed.
    async fn close(&self);
}
