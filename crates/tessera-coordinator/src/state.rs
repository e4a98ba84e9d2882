//! The coordinator's working state in memory (ARCHITECTURE.md §9): the farm's lease
//! [`Scheduler`] with the jobs' accumulators, the registered workers, the scene bytes
//! workers fetch, and what the life cycle tracks per job ([`JobRuntime`]).
//!
//! Everything here is lost on a crash and rebuilt from the store by
//! [`Coordinator::open`](crate::service::Coordinator::open); the store is the truth
//! (ARCHITECTURE.md §6). Neither the gRPC service nor the HTTP API touches this state
//! directly: both go through the [`Coordinator`](crate::service::Coordinator), which holds
//! it behind one mutex.

use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;
use std::time::{SystemTime, UNIX_EPOCH};

use tessera_api::{HistoryPoint, JobSettings, JobState, ResolvedJob, ValidatedJob};
use tessera_farm::job::{JobScene, RenderConfig};
use tessera_farm::{FramePlan, JobId, Lease, Scheduler, TileAccumulator, WorkUnit, WorkerId};

use crate::store::QuarantineRecord;

/// Milliseconds since the Unix epoch.
pub fn now_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

/// What the coordinator knows about a worker.
#[derive(Clone, Debug, Default)]
pub struct WorkerEntry {
    /// Name given at registration.
    pub name: String,
    /// Rendering threads.
    pub threads: u32,
    /// Last heartbeat or request, Unix ms.
    pub last_seen_ms: u64,
    /// When its last result arrived, Unix ms (0 before any): a worker renders its next
    /// batch from about then (the job status ETA's units in flight).
    pub last_result_ms: u64,
    /// Units merged from it (a spot-checked unit counts once, for the worker whose copy
    /// completed the agreement; a held copy does not count).
    pub units_done: u64,
    /// Its last reported throughput.
    pub paths_per_second: f64,
    /// Rejected results and mismatching duplicates.
    pub faults: u64,
    /// The worker's Tessera version.
    pub version: String,
    /// Set when the worker announced it is shutting down.
    pub draining: bool,
    /// Seconds spent rendering the units it delivered, as it reported them.
    pub render_seconds: f64,
    /// Pixel-passes it traced for the units merged from it, as it reported them (
    /// an adaptive lease's stopped pixels are not traced).
    pub pixel_passes: u64,
    /// The common name of its TLS client certificate, under mutual TLS.
    pub identity: Option<String>,
    /// Why it is quarantined (a spot check found a copy of its unlike the others'): it
    /// gets no leases and its results are refused (ARCHITECTURE.md §6). `None` if trusted.
    pub quarantined: Option<String>,
    /// The session secret issued at registration (`RegisterResponse.session`): every later
    /// call under this worker's id must carry it ([`crate::trust`]).
    pub session: String,
    /// How many of its fault events are still stored and logged in this window
    /// ([`crate::trust::FaultBudget`]).
    pub fault_budget: crate::trust::FaultBudget,
}

/// A job as the gRPC service needs it to hand out leases: what a worker must know to
/// render any of its units.
#[derive(Clone, Debug)]
pub struct JobEntry {
    /// The scene, its camera and its clock.
    pub scene: JobScene,
    /// Render settings.
    pub settings: RenderConfig,
    /// Frame plan.
    pub plan: FramePlan,
    /// The environment lighting the scene, if any.
    pub environment: Option<tessera_farm::job::JobEnvironment>,
}

impl JobEntry {
    /// The lease data of a job validated as `job` and resolved as `resolved`.
    pub fn of(resolved: &ResolvedJob) -> Self {
        let job = &resolved.job;
        Self {
            scene: job.scene.clone(),
            settings: resolved.config,
            plan: resolved.plan,
            environment: job.environment.clone(),
        }
    }
}

/// Shared state of the farm behind the coordinator.
pub struct Farm {
    /// Leases and merged frames.
    pub scheduler: Scheduler,
    /// Registered workers.
    pub workers: BTreeMap<WorkerId, WorkerEntry>,
    /// Jobs by id, as leases describe them.
    pub jobs: BTreeMap<JobId, JobEntry>,
    /// Uploaded scene bytes by content hash.
    pub scenes: HashMap<String, Arc<Vec<u8>>>,
    /// What the coordinator tracks per job besides the scheduler.
    pub runtime: BTreeMap<JobId, JobRuntime>,
    /// What workers removed from `workers` had done, so that `/metrics` counters stay
    /// monotonic when lost workers are forgotten.
    pub forgotten: ForgottenWorkers,
    /// Leases that lapsed without a result and whose units went back to the queue
    /// (`tessera_leases_expired_total`): workers that died, stalled or lost their network.
    pub leases_expired: u64,
    /// What spot checks found (`/metrics`).
    pub spot: SpotCounters,
    /// The quarantine list (ARCHITECTURE.md §6) by what a quarantine follows, the worker's
    /// name and TLS identity ([`quarantine_key`]): loaded from the store at start, added to
    /// when a worker is quarantined (and stored then), emptied of a name when an operator
    /// lifts it. A worker registering under a listed key is quarantined at once.
    pub quarantines: BTreeMap<(String, Option<String>), QuarantineRecord>,
    /// Jobs to fail because one of their units was lost too often ([`Farm::expire_leases`],
    /// [`LOST_UNIT_LEASES`]), with the reason; the ticker fails them.
    pub lost_jobs: Vec<(JobId, String)>,
    next_worker: WorkerId,
    /// The last count of [`Farm::sharing_threads`].
    sharing: Option<SharingCount>,
}

/// Workers by what a quarantine follows, their name and TLS identity ([`quarantine_key`]).
pub type WorkerKeys = std::collections::BTreeSet<(String, Option<String>)>;

/// Lapsed leases of one unit, without a result, that fail its job ([`Farm::expire_leases`]).
pub const LOST_UNIT_LEASES: u32 = 3;
/// Distinct workers among them that fail its job (or every registered trusted worker,
/// when fewer are registered).
pub const LOST_UNIT_WORKERS: usize = 3;

/// How often [`Farm::sharing_threads`] counts the fleet again when no worker registered,
/// was removed or was quarantined, ms.
pub const SHARING_RECOUNT_MS: u64 = 250;

/// A count of the render threads sharing the queue, and what it was counted from.
#[derive(Debug, Clone, Copy)]
struct SharingCount {
    at_ms: u64,
    next_worker: WorkerId,
    workers: usize,
    quarantined: usize,
    threads: u64,
}

/// The key of [`Farm::quarantines`] for a worker registered as `name` with `identity`: an
/// empty TLS identity counts as none, as the store keeps it
/// ([`QuarantineRecord::identity`]).
pub fn quarantine_key(name: &str, identity: Option<&str>) -> (String, Option<String>) {
    (
        name.to_string(),
        identity.filter(|i| !i.is_empty()).map(str::to_string),
    )
}

/// Counters of the spot checks (ARCHITECTURE.md §6), for `/metrics`.
#[derive(Clone, Copy, Debug, Default)]
pub struct SpotCounters {
    /// Spot checks ended with two different workers agreeing and no copy differing.
    pub matched: u64,
    /// Spot checks ended with a copy unlike the agreed one (its worker quarantined).
    pub mismatched: u64,
    /// Spot checks of a worker alone, which re-rendered its own copy.
    pub alone: u64,
    /// Workers quarantined.
    pub quarantined: u64,
    /// Quarantines lifted by an operator (`DELETE /workers/{name}/quarantine`).
    pub lifted: u64,
    /// Tiles dropped and merged again because a quarantined worker had merged into them.
    pub tiles_reset: u64,
    /// Units of quarantined workers rendered again whose new copy equals the old one.
    pub reverified_identical: u64,
    /// Units of quarantined workers rendered again whose new copy differs: corrupt
    /// copies that had been merged, repaired.
    pub reverified_differed: u64,
    /// Unverified units of quarantined workers that could not be rendered again (their
    /// frame or job was finished).
    pub unrepaired: u64,
}

/// Totals of the workers forgotten after being lost (`Coordinator::tick`).
#[derive(Clone, Copy, Debug, Default)]
pub struct ForgottenWorkers {
    /// Workers removed from the listing.
    pub workers: u64,
    /// Units they had delivered.
    pub units_done: u64,
    /// Faults they had been counted.
    pub faults: u64,
    /// Seconds they had spent rendering the units they delivered.
    pub render_seconds: f64,
    /// Pixel-passes they had traced for the units merged from them.
    pub pixel_passes: u64,
}

impl Farm {
    /// An empty farm whose leases last `lease_ms` and whose lease ids start after
    /// `high_water` (the largest id an earlier run may have issued), so fencing tokens
    /// never repeat across restarts (ARCHITECTURE.md §9, step 7).
    pub fn with_first_lease(lease_ms: u64, high_water: u64) -> Self {
        Self {
            scheduler: Scheduler::new(lease_ms, high_water),
            workers: BTreeMap::new(),
            jobs: BTreeMap::new(),
            scenes: HashMap::new(),
            runtime: BTreeMap::new(),
            forgotten: ForgottenWorkers::default(),
            leases_expired: 0,
            spot: SpotCounters::default(),
            quarantines: BTreeMap::new(),
            lost_jobs: Vec::new(),
            next_worker: 1,
            sharing: None,
        }
    }

    /// The render threads of the workers that share the queue (live: heard from within
    /// `lost_after_ms`; not draining; not quarantined), for the scheduler's tail rule
    /// ([`tessera_farm::Scheduler::lease_among`]).
    ///
    /// Counted again when a worker registered, was removed or was quarantined or lifted
    /// since the last count, and otherwise at most every [`SHARING_RECOUNT_MS`]: every
    /// lease asks, and counting a fleet of a thousand workers for each was a few percent
    /// of the coordinator's CPU (docs/bench-fleet.md). What a stale count can change is
    /// only who renders a unit, for a quarter of a second after a worker fell silent or
    /// stopped, never an image.
    pub fn sharing_threads(&mut self, now_ms: u64, lost_after_ms: u64) -> u64 {
        let quarantined = self.scheduler.quarantined().count();
        if let Some(c) = self.sharing {
            if c.next_worker == self.next_worker
                && c.workers == self.workers.len()
                && c.quarantined == quarantined
                && now_ms >= c.at_ms
                && now_ms - c.at_ms < SHARING_RECOUNT_MS
            {
                return c.threads;
            }
        }
        let threads = self
            .workers
            .values()
            .filter(|w| {
                !w.draining
                    && w.quarantined.is_none()
                    && now_ms.saturating_sub(w.last_seen_ms) <= lost_after_ms
            })
            .map(|w| u64::from(w.threads.max(1)))
            .sum();
        self.sharing = Some(SharingCount {
            at_ms: now_ms,
            next_worker: self.next_worker,
            workers: self.workers.len(),
            quarantined,
            threads,
        });
        threads
    }

    /// Marks a worker as draining (it gave its leases back because it is stopping) or not
    /// (it asked for work again), for /workers and the tail rule's count of the threads
    /// sharing the queue, which is counted again when the flag changes. Unknown workers
    /// are ignored.
    pub fn set_draining(&mut self, worker: WorkerId, draining: bool) {
        if let Some(w) = self.workers.get_mut(&worker) {
            if w.draining != draining {
                w.draining = draining;
                self.sharing = None;
            }
        }
    }

    /// Returns the units of every lapsed lease to the queue ([`Scheduler::expire`]),
    /// counting and logging them: a re-lease is the farm's only sign of a worker cut off
    /// mid-unit, so operators should see it. Returns how many lapsed.
    pub fn expire_leases(&mut self, now_ms: u64) -> usize {
        let expired = self.scheduler.expire(now_ms);
        if expired.is_empty() {
            return 0;
        }
        self.leases_expired += expired.len() as u64;
        self.count_lost_units(&expired);
        let workers: std::collections::BTreeSet<WorkerId> =
            expired.iter().map(|l| l.worker).collect();
        tracing::warn!(
            leases = expired.len(),
            ?workers,
            "leases expired without a result; their units are leased again"
        );
        expired.len()
    }

    /// The distinct trusted (not quarantined) workers, by name and TLS identity
    /// ([`quarantine_key`]), heard from within `lost_after_ms` before `now_ms`: who may
    /// vote that a job's scene cannot be rendered (one worker alone cannot fail a job).
    pub fn trusted_workers(&self, now_ms: u64, lost_after_ms: u64) -> usize {
        self.workers
            .values()
            .filter(|w| {
                w.quarantined.is_none() && now_ms.saturating_sub(w.last_seen_ms) <= lost_after_ms
            })
            .map(|w| quarantine_key(&w.name, w.identity.as_deref()))
            .collect::<std::collections::BTreeSet<_>>()
            .len()
    }

    /// Counts the units of `expired` leases as lost by their workers. A unit whose leases
    /// lapsed without a result [`LOST_UNIT_LEASES`] times, from [`LOST_UNIT_WORKERS`]
    /// distinct workers (by name and TLS identity, [`quarantine_key`]; or from every
    /// registered trusted worker, when fewer are registered), kills or hangs the workers
    /// that render it: its job is canceled and queued in [`Farm::lost_jobs`] to fail with
    /// the reason, instead of being leased again forever. A worker that dies once, or one
    /// whose network failed, loses a unit once; that alone fails nothing.
    fn count_lost_units(&mut self, expired: &[Lease]) {
        // Every registered trusted worker may vote here, not only the live ones: the
        // workers a unit kills stop being live, and must not lower the bar.
        let needed = LOST_UNIT_WORKERS
            .min(self.trusted_workers(u64::MAX, u64::MAX))
            .max(1);
        for l in expired {
            let who = self.workers.get(&l.worker).map_or_else(
                || (format!("worker {}", l.worker), None),
                |w| quarantine_key(&w.name, w.identity.as_deref()),
            );
            let Some(rt) = self.runtime.get_mut(&l.job) else {
                continue;
            };
            if rt.state.is_terminal() || self.lost_jobs.iter().any(|(j, _)| *j == l.job) {
                continue;
            }
            let (times, by) = rt.lost_units.entry(l.unit).or_default();
            *times += 1;
            by.insert(who);
            if *times >= LOST_UNIT_LEASES && by.len() >= needed {
                let u = l.unit;
                let reason = format!(
                    "unit (frame {}, tile {}, passes {}..{}) was lost {times} times by {} \
                     distinct workers: their leases lapsed without a result, so rendering it \
                     kills or hangs workers (a scene too large or too slow to build, or a \
                     crash); the job is failed rather than leased again forever",
                    u.frame,
                    u.tile,
                    u.first_pass,
                    u.end_pass(),
                    by.len()
                );
                self.scheduler.cancel(l.job);
                self.lost_jobs.push((l.job, reason));
            }
        }
    }

    /// Registers a worker and returns its new id (ids are never reused in a run).
    pub fn register_worker(&mut self, entry: WorkerEntry) -> WorkerId {
        let id = self.next_worker;
        self.next_worker += 1;
        self.workers.insert(id, entry);
        id
    }
}

/// What the coordinator keeps about a job besides the scheduler's state.
#[derive(Debug, Clone)]
pub struct JobRuntime {
    /// The settings as submitted (defaults filled in).
    pub settings: JobSettings,
    /// The job resolved against its scene (its validated settings are `resolved.job`).
    pub resolved: ResolvedJob,
    /// Life-cycle state.
    pub state: JobState,
    /// When it was accepted, Unix ms.
    pub created_unix_ms: u64,
    /// When it started running, Unix ms.
    pub started_unix_ms: Option<u64>,
    /// When it finished, Unix ms.
    pub finished_unix_ms: Option<u64>,
    /// Why it failed.
    pub error: Option<String>,
    /// Faulty-worker events on it.
    pub faults: u64,
    /// Leases of this job that workers returned because they could not load or build
    /// its scene.
    pub unusable_returns: u32,
    /// The distinct workers (by name and TLS identity, [`quarantine_key`]) among them:
    /// one worker alone cannot fail a job by returning its units (ARCHITECTURE.md §6).
    pub unusable_workers: std::collections::BTreeSet<(String, Option<String>)>,
    /// Per unit whose leases lapsed without a result: how often, and the distinct workers
    /// (by name and TLS identity) that lost it ([`Farm::expire_leases`]).
    pub lost_units: BTreeMap<WorkUnit, (u32, WorkerKeys)>,
    /// Per frame, per tile: (sum of squared relative errors, pixel count) of the tiles with
    /// at least two passes, kept incrementally so the image error costs O(tiles).
    pub(crate) tile_error: Vec<Vec<(f64, u64)>>,
    /// Per frame: the image error estimate its status names (the robust scale,
    /// `FrameAccumulator::image_error`), as of the frame's last history point while it
    /// was live (a walk over its pixels and their neighbours, too slow per request);
    /// `None` before. Jobs without adaptive stopping.
    pub(crate) frame_error: Vec<Option<f64>>,
    /// Per frame, per tile: the samples its renderers rejected as invalid.
    pub(crate) tile_rejected: Vec<Vec<TileRejected>>,
    /// When the last convergence-history point was recorded, Unix ms.
    pub(crate) last_history_ms: u64,
    /// Convergence history (also in the store).
    pub history: Vec<HistoryPoint>,
    /// The render plan as JSON for the status, made once.
    pub(crate) plan_json: Option<serde_json::Value>,
    /// An adaptive job's (mean spp, image error once every pixel has an estimate), as
    /// last computed with a history point: the status reads it instead of walking every
    /// pixel per request.
    pub(crate) adaptive_summary: (f64, Option<f64>),
    /// An adaptive job with a target: what its merged passes say of its error's tail
    /// (`tessera_farm::quote::EtaTrend`), as of its last history point, for the ETA.
    pub(crate) eta_trend: Option<tessera_farm::quote::EtaTrend>,
    /// The same job's mean per-pass relative variance at each history point of this run,
    /// as (spp, figure): the trend's growth compares the last with the one at half its spp.
    pub(crate) per_pass_history: Vec<(f64, f64)>,
    /// The same job's pixel work (`tessera_farm::quote::AdaptiveEta`) as of its last
    /// history point, and when that was (Unix ms), for the ETA.
    pub(crate) eta_adaptive: Option<(tessera_farm::quote::AdaptiveEta, u64)>,
    /// Its pixel work per frame as last measured (`None` for a frame not seen live): a
    /// released frame keeps what it traced.
    pub(crate) eta_frames: Vec<Option<tessera_farm::quote::PixelWork>>,
    /// Its measurements at each history point of this run, for the rate and the drift.
    pub(crate) eta_samples: Vec<tessera_farm::quote::EtaSample>,
    /// Results merged into this job so far in this run: the version of its images
    /// (the image cache's key, `service::images`).
    pub(crate) merges: u64,
    /// The render seconds workers reported for this job's units in this run, and how many
    /// units: the mean time of a unit, with which the ETA credits units in flight.
    pub(crate) unit_seconds: (f64, u64),
    /// A checkpoint of this job failed to write: its frames stay in memory (they hold
    /// passes the store may not have) instead of being released when complete.
    pub(crate) unsaved_checkpoints: bool,
    /// A lease is recording that this queued job started running (the others that lease
    /// meanwhile do not write it again).
    pub(crate) starting: bool,
    /// Why a done job stopped; with the image's error estimate it gives the
    /// [`tessera_farm::job::StopVerdict`] of the status and of the EXR header.
    pub stopped: Option<Stop>,
}

/// Why a job stopped.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stop {
    /// Every planned pass merged, or every tile finished under adaptive stopping.
    Finished,
    /// Its time limit.
    TimeLimit,
}

impl Stop {
    /// The message stored with a job's `done` state when its time limit stopped it
    /// ([`crate::store::JobRecord::error`] holds the message of the last state change), so
    /// that a restarted coordinator still says why it stopped: the rest of the verdict
    /// (target, estimate, budget) is recomputed from the stored job and its history.
    pub const TIME_LIMIT_MESSAGE: &'static str = "stopped by its time limit";

    /// The message to store with the `done` state.
    pub fn stored_message(self) -> Option<String> {
        match self {
            Self::Finished => None,
            Self::TimeLimit => Some(Self::TIME_LIMIT_MESSAGE.to_string()),
        }
    }

    /// Why a stored job stopped: `None` unless it is done.
    pub fn of_stored(state: JobState, message: Option<&str>) -> Option<Self> {
        (state == JobState::Done).then_some(match message {
            Some(Self::TIME_LIMIT_MESSAGE) => Self::TimeLimit,
            _ => Self::Finished,
        })
    }
}

impl JobRuntime {
    /// A job with nothing merged yet, in `state`, accepted at `created_unix_ms`.
    pub fn new(
        settings: JobSettings,
        resolved: ResolvedJob,
        state: JobState,
        created_unix_ms: u64,
    ) -> Self {
        let tiles = resolved.plan.tile_count() as usize;
        let frames = resolved.job.frames.count() as usize;
        let plan_json = serde_json::from_str(&resolved.render_plan.to_json()).ok();
        Self {
            settings,
            resolved,
            state,
            created_unix_ms,
            started_unix_ms: None,
            finished_unix_ms: None,
            error: None,
            faults: 0,
            unusable_returns: 0,
            unusable_workers: std::collections::BTreeSet::new(),
            lost_units: BTreeMap::new(),
            tile_error: vec![vec![(0.0, 0); tiles]; frames],
            frame_error: vec![None; frames],
            tile_rejected: vec![vec![TileRejected::default(); tiles]; frames],
            last_history_ms: 0,
            history: Vec::new(),
            plan_json,
            adaptive_summary: (0.0, None),
            eta_trend: None,
            per_pass_history: Vec::new(),
            eta_adaptive: None,
            eta_frames: Vec::new(),
            eta_samples: Vec::new(),
            merges: 0,
            unit_seconds: (0.0, 0),
            unsaved_checkpoints: false,
            stopped: None,
            starting: false,
        }
    }

    /// The validated settings.
    pub fn job(&self) -> &ValidatedJob {
        &self.resolved.job
    }

    /// The image error estimate of a job without adaptive stopping, the estimator its
    /// status and its EXR header name (`ResolvedJob::error_estimator_name`: the robust
    /// scale at the neighbours' level, not each pixel's error over its own mean, which the
    /// status gave before): each frame's as of its last history point (`frame_error`),
    /// their RMS over all pixels; once every tile has two passes and each frame's has
    /// been computed.
    pub(crate) fn error_estimate(&self) -> Option<f64> {
        // Every tile of every frame with two passes: every pixel has an estimate.
        if self.tile_error.iter().flatten().any(|&(_, c)| c == 0) {
            return None;
        }
        let (mut sum, mut n) = (0.0, 0u64);
        for (tiles, e) in self.tile_error.iter().zip(&self.frame_error) {
            let pixels: u64 = tiles.iter().map(|&(_, c)| c).sum();
            sum += e.as_ref()?.powi(2) * pixels as f64;
            n += pixels;
        }
        (n > 0).then(|| (sum / n as f64).sqrt())
    }

    /// Samples rejected as invalid by the renderers, merged or buffered.
    pub(crate) fn rejected_samples(&self) -> u64 {
        self.tile_rejected
            .iter()
            .flatten()
            .map(TileRejected::total)
            .sum()
    }

    /// Seconds between the start and the end (or `now`) of the job.
    pub(crate) fn elapsed_seconds(&self, now: u64) -> f64 {
        match self.started_unix_ms {
            Some(s) => (self.finished_unix_ms.unwrap_or(now).saturating_sub(s)) as f64 / 1e3,
            None => 0.0,
        }
    }
}

/// The samples a tile's renderers rejected as invalid (`UnitResult::rejected_samples`),
/// kept so that a restart neither loses nor double-counts them: the count of the merged
/// passes is checkpointed with the tile; units buffered ahead of a missing earlier pass
/// are lost on a restart and rendered again, so their counts wait apart until they merge.
#[derive(Debug, Clone, Default)]
pub(crate) struct TileRejected {
    /// In the merged passes (what the checkpoint stores).
    pub(crate) merged: u64,
    /// Of accepted units not merged yet: (first pass, count), non-zero counts only.
    buffered: Vec<(u32, u64)>,
}

impl TileRejected {
    /// A tile restored from its checkpoint: `merged` rejected samples, nothing buffered.
    pub(crate) fn with_merged(merged: u64) -> Self {
        Self {
            merged,
            buffered: Vec::new(),
        }
    }

    /// Records an accepted unit starting at `first_pass` with `count` rejected samples,
    /// the tile having `merged_passes` merged passes after it.
    pub(crate) fn accept(&mut self, first_pass: u32, count: u64, merged_passes: u32) {
        if count > 0 {
            self.buffered.push((first_pass, count));
        }
        let merged = &mut self.merged;
        self.buffered.retain(|&(pass, n)| {
            let done = pass < merged_passes;
            if done {
                *merged = merged.saturating_add(n);
            }
            !done
        });
    }

    fn total(&self) -> u64 {
        self.buffered
            .iter()
            .fold(self.merged, |acc, b| acc.saturating_add(b.1))
    }
}

/// A tile's (sum of squared relative errors, pixel count), zero below two passes (a
/// variance needs two replicates, ARCHITECTURE.md §3). A tile with bias statistics (vcm,
/// ppm) adds its pixels' squared bias over the bias-corrected mean, as
/// `tessera_farm::image_relative_error_biased` does (the pixel's own mean standing for
/// its neighbourhood's), the bias sum clamped at 0 per tile.
pub(crate) fn tile_error(tile: &TileAccumulator) -> (f64, u64) {
    if tile.merged_passes() < 2 {
        return (0.0, 0);
    }
    let mut sum = 0.0;
    let Some(bias) = tile.bias() else {
        for p in tile.pixels() {
            let r = p.relative_error();
            sum += r * r;
        }
        return (sum, tile.pixels().len() as u64);
    };
    let mut bias_sum = 0.0;
    for (p, b) in tile.pixels().iter().zip(bias) {
        let (m, v) = (p.mean_lum, p.lum_variance_of_mean());
        let (bm, bv) = (b.mean, b.variance_of_mean());
        let s = tessera_farm::bias_scale(m, v, m, bm, bv);
        sum += v.max(0.0) / (s * s);
        bias_sum += tessera_farm::bias_squared(bm, bv) / (s * s);
    }
    if bias_sum.is_finite() {
        sum += bias_sum.max(0.0);
    }
    (sum, tile.pixels().len() as u64)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rejected_samples_of_buffered_units_wait_until_they_merge() {
        let mut r = TileRejected::default();
        // Passes 2..4 arrive first and are buffered (0 passes merged).
        r.accept(2, 5, 0);
        assert_eq!((r.merged, r.total()), (0, 5));
        // Passes 0..2 merge, and with them the buffered unit: 4 passes merged.
        r.accept(0, 1, 4);
        assert_eq!((r.merged, r.total()), (6, 6));
        assert!(r.buffered.is_empty());
        r.accept(4, 0, 6);
        assert_eq!((r.merged, r.total()), (6, 6));
    }

    /// Whether a job fails when the workers named `losers` (indices into `workers`), in
    /// turn, each lease its first unit and let the lease lapse without a result.
    fn fails_after_losses(workers: &[&str], losers: &[usize]) -> Option<String> {
        let settings: JobSettings = serde_json::from_str(
            r#"{"scene": "builtin:cornell-box", "width": 16, "height": 16, "spp": 8}"#,
        )
        .unwrap();
        let job = settings.validate().unwrap();
        let time = tessera_scene::job::resolution_time(&job.scene);
        let scene = tessera_scene::job::load_job_scene_at(&job.scene, None, &time).unwrap();
        let resolved =
            tessera_scene::job::resolve_job(&job, &scene, tessera_scene::job::no_pilot("a test"))
                .unwrap();
        let mut farm = Farm::with_first_lease(1_000, 0);
        let ids: Vec<WorkerId> = workers
            .iter()
            .map(|name| {
                farm.register_worker(WorkerEntry {
                    name: (*name).to_string(),
                    threads: 1,
                    ..WorkerEntry::default()
                })
            })
            .collect();
        farm.scheduler.add_job(1, 0, resolved.plan, 0..=0, 1);
        farm.runtime
            .insert(1, JobRuntime::new(settings, resolved, JobState::Running, 0));
        let mut now = 0;
        let mut first = None;
        for &w in losers {
            let leases = farm.scheduler.lease(ids[w], now, 1);
            assert_eq!(leases.len(), 1, "the job has work");
            // The lapsed unit goes back to the queue at its canonical place: leased again.
            assert_eq!(*first.get_or_insert(leases[0].unit), leases[0].unit);
            now += 2_000;
            assert_eq!(farm.expire_leases(now), 1);
        }
        farm.lost_jobs.pop().map(|(job, reason)| {
            assert_eq!(job, 1);
            reason
        })
    }

    /// A unit that kills or hangs every worker that renders it fails its job once three
    /// distinct workers lost it; one worker losing it (a crash, a cut network) does not,
    /// however often, while others are registered; a farm of one fails after three losses.
    #[test]
    fn a_unit_lost_by_distinct_workers_fails_its_job() {
        let three = ["a", "b", "c"];
        let reason = fails_after_losses(&three, &[0, 1, 2]).expect("three workers lost it");
        assert!(
            reason.contains("lost 3 times by 3 distinct workers"),
            "{reason}"
        );
        assert_eq!(fails_after_losses(&three, &[0, 1]), None);
        assert_eq!(fails_after_losses(&three, &[0, 0, 0, 0]), None);
        assert_eq!(fails_after_losses(&three, &[0, 0, 1, 1]), None);
        assert!(fails_after_losses(&["alone"], &[0, 0, 0]).is_some());
        assert_eq!(fails_after_losses(&["alone"], &[0, 0]), None);
    }
}
