//! The coordinator's job life cycle over the store and the in-memory farm state
//! (ARCHITECTURE.md §9): submission, leases, durable checkpoints as passes merge, resume
//! after a restart, status, images, cancel. One file per responsibility:
//!
//! | file | what it does |
//! |---|---|
//! | [`scenes`] | scene upload, and loading a job's scene (cache, store, parse off the runtime) |
//! | [`jobs`] | submit, status, list, cancel, history |
//! | [`workers`] | registration, leases, heartbeats, returned leases, `GET /workers` |
//! | [`results`] | accepting a worker's result: lease check, merge, checkpoint, faults |
//! | [`resume`] | a stored job resolved again, tile checkpoints restored, the restart |
//! | [`images`] | a frame's merged state, its image and its tile map |
//! | [`metrics`] | the Prometheus exposition |
//! | [`quote`] | dry runs: a job quoted from a pilot rendered in a child process |
//!
//! # Durability (ARCHITECTURE.md §6)
//! The store is the truth. A job is inserted before `POST /jobs` answers. A result is
//! merged in memory and its tile's checkpoint committed *before* the worker is told the
//! result was accepted, so an accepted pass survives `kill -9`. Each snapshot is taken
//! under the farm lock and queued in merge order; checkpoints are group-committed (one
//! transaction for every checkpoint queued, the newest of each tile) by whoever next holds
//! the one async write lock with its own still queued, so a newer snapshot of a tile can
//! never be overwritten by an older one and a fleet pays one commit per batch, not per
//! result. Lease ids are reserved in blocks ([`LEASE_ID_BLOCK`]) whose end is committed
//! before any lease of the block is handed out (the next block once half of one is
//! used), so fencing tokens never repeat after a restart.
//!
//! # Restart
//! [`Coordinator::open`] reloads every job that was not finished, rebuilds its
//! accumulators from the tile checkpoints (bit-exact Welford state) and puts the rest of
//! its units back in the queue. For a grace period no new lease is handed out, so workers
//! that were rendering when the coordinator died can reconnect and deliver their results;
//! those answer leases of the previous run and are adopted (validated, merged once).

use std::path::PathBuf;
use std::sync::{Arc, Mutex, MutexGuard, OnceLock};
use std::time::{Duration, Instant};

use tessera_api::JobState;
use tessera_farm::JobId;

use crate::connections::HttpLimits;
use crate::error::{CoordError, CoordResult};
use crate::state::{now_ms, Farm, Stop};
use crate::store::{Store, StoreError, StoreUrl, WatchedStore};

mod child;
pub mod images;
pub mod jobs;
pub mod metrics;
pub mod quote;
pub mod results;
pub mod resume;
pub mod scenes;
mod technique;
pub mod workers;

pub use results::{Accepted, Delivery, Rejected};
pub use tessera_farm::quote::job_eta_seconds;
pub use workers::{
    Heartbeat, LeaseGrant, MAX_LEASE_WAIT_MS, MAX_UNUSABLE_RETURNS, MAX_WORKER_THREADS,
    UNUSABLE_WORKERS,
};

/// Lease ids are reserved in blocks of this many (one store write per block).
pub const LEASE_ID_BLOCK: u64 = 4096;
/// Largest accepted scene upload: the default of [`CoordinatorConfig::max_scene_bytes`],
/// and the most it may be.
pub const MAX_SCENE_BYTES: usize = 256 << 20;
/// Default of [`CoordinatorConfig::scene_quota_bytes`]: 10 GiB of stored scenes.
pub const DEFAULT_SCENE_QUOTA: u64 = 10 << 30;
/// Default of [`CoordinatorConfig::forget_lost_ms`]: ten minutes.
pub const FORGET_LOST_MS: u64 = 10 * 60 * 1000;
/// Largest page of `GET /jobs`.
pub const MAX_PAGE: u32 = 200;

/// How to run a coordinator. Its `Debug` form hides the tokens.
#[derive(Clone)]
pub struct CoordinatorConfig {
    /// Directory of the SQLite store (when [`CoordinatorConfig::store`] is `None`).
    pub data_dir: PathBuf,
    /// Where the store is (`--store`); `None` is the SQLite store in
    /// [`CoordinatorConfig::data_dir`].
    pub store: Option<StoreUrl>,
    /// Bearer token required on the HTTP API, if any.
    pub api_token: Option<String>,
    /// Bearer token workers must present, if any.
    pub worker_token: Option<String>,
    /// How long a lease lasts without a heartbeat, ms.
    pub lease_ms: u64,
    /// How often workers heartbeat, ms.
    pub heartbeat_ms: u32,
    /// After a restart: how long to wait for workers to reconnect before leasing again, ms.
    pub grace_ms: u64,
    /// Passes per work unit.
    pub passes_per_unit: u32,
    /// Bytes of per-pixel merge state the coordinator holds in memory for all jobs
    /// together (ARCHITECTURE.md §6, memory): frames beyond it wait for completed ones to be
    /// released, and a job one frame of which does not fit is refused at submission.
    pub memory_budget: u64,
    /// The HTTP port's connection limits and timeouts.
    pub http_limits: HttpLimits,
    /// How long a worker stays listed (as `lost`) after it was marked lost, ms; then it is
    /// forgotten and counted in `tessera_workers_forgotten_total`.
    pub forget_lost_ms: u64,
    /// TLS on both ports, and mutual TLS for workers with a client CA (`crate::tls`);
    /// `None` serves plain text.
    pub tls: Option<crate::tls::TlsFiles>,
    /// The program a dry run's pilot runs as (`PROGRAM pilot ...`, normally the coordinator's
    /// own `tessera` binary; [`quote`]); `None` refuses dry runs with 503.
    pub pilot_program: Option<PathBuf>,
    /// How long a dry run's pilot may render before it is killed, ms.
    pub pilot_timeout_ms: u64,
    /// The fraction of units rendered a second time by a different worker and compared
    /// (spot checks, ARCHITECTURE.md §6; `--spot-check-fraction`), 0 to 1; 0 disables.
    pub spot_check_fraction: f64,
    /// Largest scene upload, bytes (`--max-scene-size`; at most [`MAX_SCENE_BYTES`]): a
    /// larger one is refused with 413.
    pub max_scene_bytes: usize,
    /// Bytes all stored scenes together may hold (`--scene-quota`): an upload that would
    /// go beyond is refused with 507 (docs/store.md, "Scene storage").
    pub scene_quota_bytes: u64,
    /// Bytes the scenes first uploaded with one API token may hold
    /// (`--scene-quota-per-token`; without an API token, all uploads are one client's).
    pub scene_quota_per_token: u64,
    /// Scenes no queued or running job needs and unused for this long are deleted by the
    /// coordinator's maintenance (`--scene-retention`), ms; `None` keeps them until
    /// deleted (`DELETE /api/v1/scenes/{hash}`).
    pub scene_retention_ms: Option<u64>,
}

impl std::fmt::Debug for CoordinatorConfig {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let hidden = |t: &Option<String>| t.as_ref().map(|_| "<hidden>");
        f.debug_struct("CoordinatorConfig")
            .field("data_dir", &self.data_dir)
            .field("store", &self.store.as_ref().map(ToString::to_string))
            .field("api_token", &hidden(&self.api_token))
            .field("worker_token", &hidden(&self.worker_token))
            .field("lease_ms", &self.lease_ms)
            .field("heartbeat_ms", &self.heartbeat_ms)
            .field("grace_ms", &self.grace_ms)
            .field("passes_per_unit", &self.passes_per_unit)
            .field("memory_budget", &self.memory_budget)
            .field("http_limits", &self.http_limits)
            .field("forget_lost_ms", &self.forget_lost_ms)
            .field("tls", &self.tls)
            .field("pilot_program", &self.pilot_program)
            .field("pilot_timeout_ms", &self.pilot_timeout_ms)
            .field("spot_check_fraction", &self.spot_check_fraction)
            .field("max_scene_bytes", &self.max_scene_bytes)
            .field("scene_quota_bytes", &self.scene_quota_bytes)
            .field("scene_quota_per_token", &self.scene_quota_per_token)
            .field("scene_retention_ms", &self.scene_retention_ms)
            .finish()
    }
}

/// The default [`CoordinatorConfig::memory_budget`]: 4 GiB, the merge state of a
/// 7680 x 7680 frame (72 bytes per pixel).
pub const DEFAULT_MEMORY_BUDGET: u64 = 4 << 30;

impl CoordinatorConfig {
    /// Defaults for a data directory: 10 s leases, 1 s heartbeats, 3 s restart grace, one
    /// pass per unit, no tokens, the default HTTP limits ([`HttpLimits::default`]), lost
    /// workers forgotten after ten minutes, a [`DEFAULT_MEMORY_BUDGET`], spot checks of
    /// [`tessera_farm::DEFAULT_SPOT_CHECK_FRACTION`] (2%) of the units, no pilot program
    /// (no dry runs), a [`quote::PILOT_TIMEOUT_MS`] pilot timeout, uploads up to
    /// [`MAX_SCENE_BYTES`], [`DEFAULT_SCENE_QUOTA`] of scenes in all and per token, and
    /// no scene retention.
    pub fn new(data_dir: impl Into<PathBuf>) -> Self {
        Self {
            data_dir: data_dir.into(),
            store: None,
            api_token: None,
            worker_token: None,
            lease_ms: 10_000,
            heartbeat_ms: 1_000,
            grace_ms: 3_000,
            passes_per_unit: 1,
            memory_budget: DEFAULT_MEMORY_BUDGET,
            http_limits: HttpLimits::default(),
            forget_lost_ms: FORGET_LOST_MS,
            tls: None,
            pilot_program: None,
            pilot_timeout_ms: quote::PILOT_TIMEOUT_MS,
            spot_check_fraction: tessera_farm::DEFAULT_SPOT_CHECK_FRACTION,
            max_scene_bytes: MAX_SCENE_BYTES,
            scene_quota_bytes: DEFAULT_SCENE_QUOTA,
            scene_quota_per_token: DEFAULT_SCENE_QUOTA,
            scene_retention_ms: None,
        }
    }
}

impl CoordinatorConfig {
    /// The store to open: [`CoordinatorConfig::store`], or the SQLite store in
    /// [`CoordinatorConfig::data_dir`].
    pub fn store_url(&self) -> StoreUrl {
        self.store
            .clone()
            .unwrap_or_else(|| StoreUrl::Sqlite(self.data_dir.clone()))
    }
}

/// The coordinator: shared by the HTTP routes, the gRPC service and the ticker.
#[derive(Clone)]
pub struct Coordinator {
    inner: Arc<Inner>,
}

struct Inner {
    farm: Arc<Mutex<Farm>>,
    /// The store: `watch`, as the trait object every service file uses.
    store: Arc<dyn Store>,
    /// The store, watched: after a failed write the coordinator stops accepting work
    /// (docs/store.md).
    watch: Arc<WatchedStore>,
    cfg: CoordinatorConfig,
    /// Serializes store writes of merged state (see the module docs).
    write: tokio::sync::Mutex<()>,
    /// Checkpoints merged and not yet committed, in merge order (group commit,
    /// [`Coordinator::accept_result`]).
    pending: Mutex<Vec<results::PendingCheckpoint>>,
    /// Lease ids up to this are reserved in the store.
    lease_reserved: Mutex<u64>,
    /// No leases are handed out before this (Unix ms): the restart grace period.
    lease_blocked_until_ms: u64,
    /// Results answering leases of the previous run are taken until this (Unix ms): the
    /// grace period and one lease duration after it (the resumed leases' deadline,
    /// [`tessera_farm::Scheduler::grace`]); 0 when nothing was resumed.
    previous_run_until_ms: u64,
    /// Seals leases (`Lease.fence`), kept in the store ([`crate::trust::FenceKey`]).
    fence: crate::trust::FenceKey,
    /// Set when the coordinator started, for uptime.
    started: Instant,
    /// Permits for image requests that restore or encode a frame
    /// ([`images::HEAVY_REQUESTS`]).
    heavy: tokio::sync::Semaphore,
    /// The one permit of a dry run's pilot ([`quote`]).
    pilots: tokio::sync::Semaphore,
    /// Technique pilots and their verdicts ([`technique`]).
    technique: Arc<technique::TechniquePilots>,
    /// Encoded images for pollers.
    images: Mutex<images::ImageCache>,
    /// Set once a graceful shutdown began: heartbeats tell workers to stop and no new
    /// units are leased (ARCHITECTURE.md §9).
    stopping: std::sync::atomic::AtomicBool,
    /// Set, with the reason, when this coordinator lost the leadership of its
    /// PostgreSQL store (`crate::ha`): from then on it grants nothing and takes nothing.
    deposed: OnceLock<String>,
    /// Wakes lease requests waiting for work ([`Coordinator::lease_waiting`]).
    work: tokio::sync::Notify,
    /// Lease requests waiting for work now, and how the waits ended: woken (something
    /// may have become leasable) or at their deadline (`/metrics`).
    lease_waits: LeaseWaits,
    /// Scene uploads and submissions of uploaded scenes hold it shared, a scene's
    /// deletion exclusively: no job is stored against a scene being deleted, and two
    /// uploads do not both pass the quota for the same free bytes ([`scenes`]).
    scene_lock: tokio::sync::RwLock<()>,
    /// Serializes uploads' quota checks with their writes.
    uploads: tokio::sync::Mutex<()>,
    /// When scene retention last ran (Unix ms).
    retention_ran_ms: std::sync::atomic::AtomicU64,
    /// Started on a full disk over a read-only view of the store: nothing was resumed,
    /// and the coordinator is opened again once space is freed (`crate::server`).
    read_only: bool,
}

/// The long polls' gauge and counters ([`Coordinator::lease_waiting`]).
#[derive(Default)]
struct LeaseWaits {
    waiting: std::sync::atomic::AtomicU64,
    woken: std::sync::atomic::AtomicU64,
    expired: std::sync::atomic::AtomicU64,
}

impl Coordinator {
    /// Opens the store ([`CoordinatorConfig::store_url`]) and resumes every unfinished job
    /// in it.
    ///
    /// On a SQLite store whose disk is full (the open's write probe fails and the data
    /// directory takes no bytes), the coordinator starts all the same over a read-only
    /// view of the store ([`SqliteStore::open_read_only`](crate::store::SqliteStore::open_read_only)):
    /// it serves reads (status, images, the dashboard) and answers every write 507 naming
    /// the full disk, and [`serve_coordinator`](crate::serve_coordinator) opens it again
    /// normally once space is freed (docs/store.md, "When the disk is full").
    pub async fn open(cfg: CoordinatorConfig) -> Result<Self, StoreError> {
        let url = cfg.store_url();
        match crate::store::open(&url).await {
            Ok(store) => Self::with_store(cfg, store).await,
            Err(e @ StoreError::NotWritable { .. }) => {
                let crate::store::StoreUrl::Sqlite(dir) = &url else {
                    return Err(e);
                };
                if !crate::space::is_full(dir).await {
                    return Err(e);
                }
                let store = crate::store::SqliteStore::open_read_only(dir).await?;
                tracing::error!(
                    error = %e,
                    "the disk of the store is full: serving reads only; new work is refused \
                     until space is freed, then the store is opened again"
                );
                Self::build(cfg, Arc::new(store), Some(e.to_string())).await
            }
            Err(e) => Err(e),
        }
    }

    /// Whether this coordinator started on a full disk and serves reads only (see
    /// [`Coordinator::open`]).
    pub fn read_only(&self) -> bool {
        self.inner.read_only
    }

    /// Whether writes failed for want of space, or the coordinator started on a full
    /// disk: what freeing space cures.
    pub fn disk_full(&self) -> bool {
        self.inner.watch.disk_full()
    }

    /// Whether a write failed (the coordinator accepts no new work).
    pub fn store_failing(&self) -> bool {
        self.inner.watch.fault().is_some()
    }

    /// Records that the store's write failure is a full disk (probed by the caller).
    pub(crate) fn mark_disk_full(&self) {
        self.inner.watch.mark_disk_full();
    }

    /// Like [`Coordinator::open`] over a given store.
    pub async fn with_store(
        cfg: CoordinatorConfig,
        store: Arc<dyn Store>,
    ) -> Result<Self, StoreError> {
        Self::build(cfg, store, None).await
    }

    /// [`Coordinator::with_store`]; with `full_disk` (why the store cannot be written) a
    /// read-only coordinator: failing from the start, nothing resumed.
    async fn build(
        cfg: CoordinatorConfig,
        store: Arc<dyn Store>,
        full_disk: Option<String>,
    ) -> Result<Self, StoreError> {
        let read_only = full_disk.is_some();
        let watch = Arc::new(match full_disk {
            None => WatchedStore::new(store),
            Some(why) => WatchedStore::failing(store, format!("starting the coordinator: {why}")),
        });
        let store: Arc<dyn Store> = watch.clone();
        let high_water = store.max_lease_id().await?;
        // The same key for every run on the store: a restarted coordinator verifies the
        // seals of the leases its predecessor issued (ARCHITECTURE.md §6). A read-only
        // coordinator leases nothing: a key of its own does.
        let fresh = crate::trust::random_bytes();
        let fence = crate::trust::FenceKey::new(&if read_only {
            fresh
        } else {
            store.fence_key(fresh).await?
        });
        let mut state = Farm::with_first_lease(cfg.lease_ms, high_water);
        state.scheduler.set_memory_budget(cfg.memory_budget);
        state
            .scheduler
            .set_spot_check_fraction(cfg.spot_check_fraction);
        // The quarantine list outlives the run: a worker quarantined before the restart
        // is quarantined again as soon as it registers (ARCHITECTURE.md §6).
        for q in store.list_quarantines().await? {
            let key = crate::state::quarantine_key(&q.worker, q.identity.as_deref());
            state.quarantines.insert(key, q);
        }
        let farm = Arc::new(Mutex::new(state));
        let technique = Arc::new(technique::TechniquePilots::new(
            cfg.pilot_program.clone(),
            std::time::Duration::from_millis(cfg.pilot_timeout_ms.max(1)),
        ));
        let resumed = !read_only && resume::resume_all(&*store, &farm, &technique).await?;
        if let (Some(f), false) = (watch.fault(), read_only) {
            return Err(StoreError::Failing(f));
        }
        let blocked = if resumed { now_ms() + cfg.grace_ms } else { 0 };
        // Leases of the previous run may still be held by reconnecting workers.
        if let Ok(mut f) = farm.lock() {
            f.scheduler.grace(blocked + cfg.lease_ms);
        }
        let previous_run_until_ms = if resumed {
            blocked.saturating_add(cfg.lease_ms)
        } else {
            0
        };
        let coordinator = Self {
            inner: Arc::new(Inner {
                farm,
                store,
                watch,
                cfg,
                write: tokio::sync::Mutex::new(()),
                pending: Mutex::new(Vec::new()),
                lease_reserved: Mutex::new(high_water),
                lease_blocked_until_ms: blocked,
                previous_run_until_ms,
                fence,
                started: Instant::now(),
                heavy: tokio::sync::Semaphore::new(images::HEAVY_REQUESTS),
                pilots: tokio::sync::Semaphore::new(1),
                technique,
                images: Mutex::new(images::ImageCache::default()),
                stopping: std::sync::atomic::AtomicBool::new(false),
                deposed: OnceLock::new(),
                work: tokio::sync::Notify::new(),
                lease_waits: LeaseWaits::default(),
                scene_lock: tokio::sync::RwLock::new(()),
                uploads: tokio::sync::Mutex::new(()),
                retention_ran_ms: std::sync::atomic::AtomicU64::new(now_ms()),
                read_only,
            }),
        };
        coordinator.finish_complete_jobs().await?;
        Ok(coordinator)
    }

    /// Marks done the resumed jobs that were complete when the last run stopped: every
    /// frame merged and checkpointed, the `done` state not yet written (a crash between
    /// the last checkpoint and the state change). No result would come to finish them, so
    /// they would stay `running` for ever.
    async fn finish_complete_jobs(&self) -> Result<(), StoreError> {
        let complete: Vec<(JobId, Option<results::StoredPoint>)> = {
            let Ok(mut farm) = self.inner.farm.lock() else {
                return Ok(());
            };
            let ids: Vec<JobId> = farm
                .runtime
                .iter()
                .filter(|(_, rt)| matches!(rt.state, JobState::Queued | JobState::Running))
                .map(|(id, _)| *id)
                .filter(|id| farm.scheduler.is_complete(*id))
                .collect();
            ids.into_iter()
                .map(|id| (id, results::history_point(&mut farm, id, now_ms(), true)))
                .collect()
        };
        for (id, point) in complete {
            if let Some((job, point, estimator)) = point {
                let stored = self
                    .inner
                    .store
                    .append_history(job, point, Some(&estimator));
                if let Err(e) = stored.await {
                    tracing::warn!(job, error = %e, "history point not stored");
                }
            }
            match self.set_state(id, JobState::Done, None).await {
                Ok(()) => tracing::info!(job = id, "resumed job was complete: done"),
                Err(CoordError::Store(e)) => return Err(e),
                Err(e) => tracing::error!(job = id, error = %e, "cannot mark job done"),
            }
        }
        Ok(())
    }

    /// Begins a graceful shutdown: from now on heartbeats answer `shutdown` (workers
    /// finish and deliver the units in hand, then stop) and no new units are leased.
    pub fn begin_shutdown(&self) {
        self.inner
            .stopping
            .store(true, std::sync::atomic::Ordering::SeqCst);
        // Lease requests waiting for work answer now (with no unit).
        self.work_changed(true);
    }

    /// Whether [`Coordinator::begin_shutdown`] was called.
    pub fn shutting_down(&self) -> bool {
        self.inner
            .stopping
            .load(std::sync::atomic::Ordering::SeqCst)
    }

    /// The configuration.
    pub fn config(&self) -> &CoordinatorConfig {
        &self.inner.cfg
    }

    /// The store.
    pub fn store(&self) -> Arc<dyn Store> {
        self.inner.store.clone()
    }

    /// Marks this coordinator as no longer the active one (it lost the leadership lock,
    /// `crate::ha`): every worker request and every request for new work is refused from
    /// now on with [`CoordError::NotActive`] naming `reason`, so no lease is granted and
    /// no result taken after the loss. The first reason is kept.
    pub fn depose(&self, reason: String) {
        let _ = self.inner.deposed.set(reason);
        self.work_changed(true);
    }

    /// `Ok` while this coordinator is the active one; [`CoordError::NotActive`] once it
    /// was deposed ([`Coordinator::depose`]).
    pub fn active(&self) -> CoordResult<()> {
        match self.inner.deposed.get() {
            Some(reason) => Err(CoordError::NotActive(format!(
                "not the active coordinator: {reason}"
            ))),
            None => Ok(()),
        }
    }

    /// Refuses new work once a store write failed ([`WatchedStore`]) or the coordinator
    /// was deposed ([`Coordinator::active`]): the error names the failed write or the
    /// state, and maps to 503 (HTTP) and `UNAVAILABLE` (gRPC).
    ///
    /// A full disk ([`Coordinator::disk_full`]) is [`StoreError::DiskFull`] instead:
    /// 507 (HTTP) and `RESOURCE_EXHAUSTED` (gRPC), cured by freeing space.
    pub fn accepting_work(&self) -> CoordResult<()> {
        self.active()?;
        match self.inner.watch.fault() {
            Some(f) if self.inner.watch.disk_full() => {
                Err(CoordError::Store(StoreError::DiskFull(f)))
            }
            Some(f) => Err(CoordError::Store(StoreError::Failing(f))),
            None => Ok(()),
        }
    }

    /// The farm state, locked. Never held across an `.await`.
    fn lock(&self) -> CoordResult<MutexGuard<'_, Farm>> {
        self.inner.farm.lock().map_err(|_| CoordError::poisoned())
    }

    /// Seconds since this coordinator started.
    pub fn uptime_seconds(&self) -> f64 {
        self.inner.started.elapsed().as_secs_f64()
    }

    /// Moves a job to `state`: in the store first, then in memory (ARCHITECTURE.md §9). The
    /// message of a `done` state is why it stopped ([`Stop::stored_message`]), not an
    /// error: it is stored, and kept out of the status's `error`.
    async fn set_state(
        &self,
        id: JobId,
        state: JobState,
        error: Option<String>,
    ) -> CoordResult<()> {
        let now = now_ms();
        self.inner
            .store
            .set_job_state(id, state, error.clone(), now)
            .await?;
        let mut farm = self.lock()?;
        if let Some(rt) = farm.runtime.get_mut(&id) {
            rt.state = state;
            if state == JobState::Running && rt.started_unix_ms.is_none() {
                rt.started_unix_ms = Some(now);
            }
            if state == JobState::Done && rt.stopped.is_none() {
                rt.stopped = Some(Stop::Finished);
            }
            if state.is_terminal() {
                rt.finished_unix_ms = Some(now);
                if rt.started_unix_ms.is_none() {
                    rt.started_unix_ms = Some(now);
                }
            }
            rt.error = if state == JobState::Done { None } else { error };
        }
        Ok(())
    }

    /// Tells the lease requests waiting for work ([`Coordinator::lease_waiting`]) that
    /// units may have become leasable: all of them (`everyone`: a job queued, leases
    /// returned or lapsed, a shutdown), or one (a result merged; a request that gets
    /// units wakes the next).
    pub(crate) fn work_changed(&self, everyone: bool) {
        if everyone {
            self.inner.work.notify_waiters();
        } else {
            self.inner.work.notify_one();
        }
    }

    /// Periodic housekeeping: expire lapsed leases, stop jobs past their time limit
    /// (ARCHITECTURE.md §9, step 11).
    pub async fn tick(&self) {
        let now = now_ms();
        let mut over_time = Vec::new();
        let mut final_points = Vec::new();
        let mut lost = Vec::new();
        if let Ok(mut farm) = self.inner.farm.lock() {
            // During the grace period leases of the previous run are not expired.
            if !self.leasing_paused() && farm.expire_leases(now) > 0 {
                self.work_changed(true);
            }
            for (&id, rt) in &farm.runtime {
                if let (Some(limit), JobState::Running) = (rt.job().time_limit_seconds, rt.state) {
                    if rt.elapsed_seconds(now) >= limit {
                        over_time.push(id);
                    }
                }
            }
            for id in &over_time {
                farm.scheduler.cancel(*id);
                if let Some(rt) = farm.runtime.get_mut(id) {
                    rt.stopped = Some(Stop::TimeLimit);
                }
                // The final point, as at completion: a restarted coordinator reads the
                // stopped job's estimate from its history.
                if let Some(point) = results::history_point(&mut farm, *id, now, true) {
                    final_points.push(point);
                }
            }
            self.forget_lost_workers(&mut farm, now);
            lost = std::mem::take(&mut farm.lost_jobs);
        }
        // Units that kill or hang every worker that renders them fail their job
        // (`Farm::expire_leases`), as scenes no worker can use do.
        for (job, error) in lost {
            tracing::error!(job, error = %error, "job failed");
            if let Err(e) = self.set_state(job, JobState::Failed, Some(error)).await {
                tracing::warn!(job, error = %e, "cannot fail the job");
            }
        }
        for (job, point, estimator) in final_points {
            let stored = self
                .inner
                .store
                .append_history(job, point, Some(&estimator));
            if let Err(e) = stored.await {
                tracing::warn!(job, error = %e, "history point not stored");
            }
        }
        for id in over_time {
            tracing::info!(job = id, "time limit reached");
            let _ = self
                .set_state(id, JobState::Done, Stop::TimeLimit.stored_message())
                .await;
        }
        self.scene_retention(now).await;
    }

    /// Runs [`Coordinator::tick`] every 200 ms until the returned handle is dropped.
    pub fn spawn_ticker(&self) -> tokio::task::JoinHandle<()> {
        let me = self.clone();
        tokio::spawn(async move {
            let mut iv = tokio::time::interval(Duration::from_millis(200));
            loop {
                iv.tick().await;
                me.tick().await;
            }
        })
    }
}
