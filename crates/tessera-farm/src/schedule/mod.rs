//! Leasing work units to workers: priorities, coarse-to-fine order, deadlines, fencing
//! tokens, re-leasing after expiry, and one merge per unit however often it is rendered.
//!
//! The [`Scheduler`] is pure: the caller passes the clock (`now_ms`) into every call, so
//! the coordinator drives it from real time and tests drive it from a counter.
//!
//! Order (ARCHITECTURE.md §9, "Plan tiles and passes"): jobs of higher priority first,
//! then first come first served; within a job, frames in order and, within a frame,
//! coarse to fine — the first pass chunk of every tile before any tile's second chunk —
//! so a preview covers the whole frame early.
//!
//! A lease carries a unique, increasing `lease_id` that acts as a fencing token: a result
//! is only merged if it answers a lease the scheduler issued for exactly that unit. A lease
//! whose deadline passes returns its unit to the queue (at its canonical position, so the
//! order stays coarse to fine). A late result for a re-leased unit is still useful: being
//! deterministic, it is merged if the unit is not merged yet, and compared with the merged
//! copy otherwise (a mismatch is a faulty-worker event).
//!
//! Adaptive jobs ([`Scheduler::add_adaptive_job`], ARCHITECTURE.md §3, "Adaptive
//! stopping"): each frame also keeps an [`AdaptiveFrame`] fed with every merged result.
//! Its decisions are taken at fixed pass indices from each tile's own merged state, so the
//! scheduler never leases a unit *beyond an open decision*: a unit whose first pass is at
//! or past its tile's [`crate::AdaptiveTile::lease_horizon`] waits (in canonical order)
//! until the passes before the boundary are merged and the decision is made, and units of
//! a finished tile are dropped without being leased. No speculative work is leased, so
//! nothing has to be thrown away, and which units exist is a function of the job alone:
//! the image is bit-identical with any number of workers. The cost is a short pipeline
//! stall per tile at each boundary (other tiles' units fill it when there are enough
//! tiles).
//!
//! Spot checks ([`crate::spot`], ARCHITECTURE.md §6, "Spot checks and quarantine"): with
//! [`Scheduler::set_spot_check_fraction`] a deterministic fraction of the units is
//! rendered by two different workers. The first copy is held unmerged
//! ([`Submitted::Held`]) and the unit leased again to a worker that has no copy; it is
//! merged once two different workers' copies agree, and a worker whose copy differs is
//! quarantined ([`Scheduler::quarantine`]): no more leases, its leases revoked, its
//! results refused, and every tile it merged a unit into on its word alone dropped and
//! merged again from units other workers render, until an operator lifts it
//! ([`Scheduler::lift_quarantine`]). What happened is reported as [`crate::SpotEvent`]s
//! ([`Scheduler::take_spot_events`]).
//!
//! Memory (ARCHITECTURE.md §6, "Memory: budgeted, never assumed"): a frame's per-pixel
//! merge state is allocated when its first unit is leased and released by
//! [`Scheduler::release_frame`] once the frame is complete and its tiles are
//! checkpointed. Allocations are charged to one budget for all jobs
//! ([`Scheduler::set_memory_budget`]): a frame that does not fit waits (its units are not
//! leased) until completed frames free their memory, so the scheduler's per-pixel state
//! is bounded by the budget plus one frame, whatever the jobs.
//!
//! # Where things are
//!
//! One [`Scheduler`], its `impl` spread over this folder by concern; each file opens with
//! what it owns:
//!
//! - `mod.rs` (here): the scheduler's state and result types; adding, canceling and
//!   removing jobs; progress.
//! - `job.rs`: one job's work queue: the canonical unit order, the cursor, returned
//!   units, and the adaptive gate that holds units back until their decision is made.
//! - `lease.rs`: leasing (and the tail rule, [`tail_share`]), deadlines and expiry,
//!   leases given back, the lapsed leases a late result may still answer.
//! - `submit.rs`: results: the fencing check, the pixels a lease named, one merge per unit.
//! - `spot.rs`: spot checks and quarantine: held copies, agreement, repair of the tiles a
//!   faulty worker merged into. Which units are checked, and the events, are the leaf
//!   module [`crate::spot`], which depends on nothing here.
//! - `memory.rs`: the memory budget, where each frame's merge state is, releasing frames.
//! - `resume.rs`: jobs brought back from their checkpoints after a restart.
//! - `tests/`: the tests, one file per concern.

mod job;
mod lease;
mod memory;
mod resume;
mod spot;
mod submit;
#[cfg(test)]
mod tests;

pub use lease::tail_share;
pub use memory::{frame_state_bytes, frame_state_bytes_with_bias, Residency};
pub use resume::{Resumed, ResumedAdaptive};
pub use spot::EXACT_SPOT_COUNT;

use crate::adaptive::{AdaptiveError, AdaptiveFrame, AdaptiveSettings};
use crate::ids::{JobId, WorkerId};
use crate::merge::MergeError;
use crate::plan::{FramePlan, WorkUnit};
use crate::spot::SpotEvent;
use job::{AdaptiveQueue, FrameSlot, Job};
use memory::Memory;
use std::collections::{BTreeMap, BTreeSet};

/// A unit leased to a worker until `deadline_ms`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Lease {
    /// Fencing token: unique and increasing over the scheduler's life.
    pub lease_id: u64,
    /// The job.
    pub job: JobId,
    /// The unit to render.
    pub unit: WorkUnit,
    /// The worker holding it.
    pub worker: WorkerId,
    /// When the lease lapses unless extended by a heartbeat.
    pub deadline_ms: u64,
    /// When it was issued (the scheduler's clock): how long its unit has been rendering.
    pub leased_ms: u64,
}

/// What became of a submitted result.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Submitted {
    /// Merged (or buffered until the passes before it arrive).
    Accepted,
    /// The unit had already been merged; `identical` tells whether the copies agree
    /// (rendering is deterministic, so a mismatch means a faulty worker).
    Duplicate {
        /// The copies are bit-identical.
        identical: bool,
    },
    /// The unit's frame is complete and released from memory
    /// ([`Scheduler::release_frame`]): the unit was merged, this copy is not compared.
    Late,
    /// A copy of a spot-checked unit, valid and kept unmerged until a copy from another
    /// worker agrees with it ([`crate::spot`]); not durable (after a restart the unit is
    /// rendered again).
    Held,
}

/// Why a submission was refused.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum SubmitError {
    /// No lease with this id was ever issued for this unit (or the job is gone).
    #[error("lease {0} is unknown or does not cover this unit")]
    UnknownLease(u64),
    /// The job was canceled.
    #[error("job {0} was canceled")]
    Canceled(JobId),
    /// A previous run's lease for a frame whose merge state is not in memory yet (it
    /// waits for the memory budget): not the worker's fault; the unit is leased again.
    #[error("frame {0} is waiting for memory; its units will be leased again")]
    NotResident(u32),
    /// The result is malformed (wrong size, non-finite values, ...): counted against the
    /// worker.
    #[error("rejected result: {0}")]
    Invalid(#[from] MergeError),
    /// The worker is quarantined ([`Scheduler::quarantine`]): its results are refused.
    #[error("worker {0} is quarantined: its results are not used")]
    Quarantined(WorkerId),
}

/// Progress of one job.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub struct Progress {
    /// Units in the whole job.
    pub units_total: u64,
    /// Units merged (including buffered ones).
    pub units_done: u64,
    /// Units currently leased.
    pub units_leased: u64,
    /// Tile-passes merged over all frames.
    pub passes_done: u64,
    /// Tile-passes planned over all frames.
    pub passes_planned: u64,
    /// Frames whose every tile has all its passes.
    pub frames_done: u32,
    /// Second copies the spot checks will render over the whole job (one per checked
    /// unit): counted exactly for up to [`EXACT_SPOT_COUNT`] units, as the expected
    /// `units_total x fraction` (rounded) beyond.
    pub copies_total: u64,
    /// Copies of spot-checked units rendered so far beyond those counted in `units_done`.
    pub copies_done: u64,
}

/// The lease table and work queues of all jobs.
pub struct Scheduler {
    lease_ms: u64,
    jobs: BTreeMap<JobId, Job>,
    leases: BTreeMap<u64, Lease>,
    /// A lower bound of every lease's deadline (`u64::MAX` with none): deadlines only
    /// grow (extend, grace), so a new lease's deadline is all that can lower it, and
    /// [`Scheduler::expire`], called before every lease, looks at the lease table only
    /// when the bound has passed instead of scanning a fleet's thousand leases each time.
    next_expiry_ms: u64,
    /// Leases that lapsed or were given back, with their (job, canonical unit index): a
    /// late result may still answer one of them, and only them.
    lapsed: BTreeMap<u64, (JobId, u64)>,
    memory: Memory,
    next_lease_id: u64,
    next_seq: u64,
    /// The largest lease id issued by an earlier run of the coordinator (the high-water
    /// mark it was restarted with); results answering such leases are adopted.
    previous_run_max_lease: u64,
    /// The fraction of units spot-checked ([`crate::spot`]); 0 disables.
    spot_fraction: f64,
    /// Workers found faulty: no leases, results refused.
    quarantined: BTreeSet<WorkerId>,
    /// What spot checks found since the last [`Scheduler::take_spot_events`].
    spot_events: Vec<SpotEvent>,
    /// Each worker's spot-check record, for its check rate ([`crate::spot::worker_check_rate`]).
    records: BTreeMap<WorkerId, spot::WorkerRecord>,
}

impl Scheduler {
    /// A scheduler whose leases last `lease_ms` unless extended; lease ids start after
    /// `first_lease_id` (pass the largest id ever issued when restarting, so fencing tokens
    /// never repeat).
    pub fn new(lease_ms: u64, first_lease_id: u64) -> Self {
        Self {
            lease_ms,
            jobs: BTreeMap::new(),
            leases: BTreeMap::new(),
            next_expiry_ms: u64::MAX,
            lapsed: BTreeMap::new(),
            memory: Memory::unbounded(),
            next_lease_id: first_lease_id + 1,
            next_seq: 0,
            previous_run_max_lease: first_lease_id,
            spot_fraction: 0.0,
            quarantined: BTreeSet::new(),
            spot_events: Vec::new(),
            records: BTreeMap::new(),
        }
    }

    /// A job `id` with its frame slots, nothing leased or merged, queued after every job
    /// added so far among equal priorities; its spot-check copies counted at the
    /// scheduler's fraction.
    fn new_job(
        &mut self,
        id: JobId,
        priority: i32,
        plan: FramePlan,
        first_frame: u32,
        passes_per_unit: u32,
        frames: Vec<FrameSlot>,
    ) -> Job {
        self.next_seq += 1;
        let mut job = Job {
            priority,
            seq: self.next_seq,
            plan,
            first_frame,
            passes_per_unit: passes_per_unit.max(1),
            frames,
            frame_bytes: frame_state_bytes(&plan, false),
            cursor: 0,
            returned: BTreeSet::new(),
            done: BTreeSet::new(),
            leased: BTreeMap::new(),
            canceled: false,
            evicted: false,
            adaptive: None,
            checks: BTreeMap::new(),
            extra_copies: 0,
            copies_total: 0,
            unverified: BTreeMap::new(),
            suspect: BTreeMap::new(),
        };
        job.copies_total = job.spot_copies(self.spot_fraction, id);
        job
    }

    /// Adds a job rendering `frames` (inclusive range) of `plan`, cut into units of
    /// `passes_per_unit` passes. Jobs added earlier run first among equal priorities.
    pub fn add_job(
        &mut self,
        id: JobId,
        priority: i32,
        plan: FramePlan,
        frames: std::ops::RangeInclusive<u32>,
        passes_per_unit: u32,
    ) {
        // Nothing is allocated yet: each frame's merge state comes with its first lease.
        let first_frame = *frames.start();
        let frames: Vec<FrameSlot> = frames.map(|_| FrameSlot::Pending).collect();
        let job = self.new_job(id, priority, plan, first_frame, passes_per_unit, frames);
        self.jobs.insert(id, job);
    }

    /// Adds an adaptive job (ARCHITECTURE.md §3, "Adaptive stopping"): like
    /// [`Scheduler::add_job`], but each tile stops being leased once `adaptive`'s policy
    /// says it is finished, and the job is complete when every tile of every frame is (see
    /// the module docs for how units wait for decisions). Decision boundaries must fall on unit boundaries, so `min_passes` and
    /// `interval` are rounded up to multiples of `passes_per_unit`; the settings actually
    /// used are returned ([`AdaptiveSettings::for_units`]). Fails if the settings do not fit
    /// the plan (e.g. an unbiased pilot leaving no fresh passes). A restart brings such a
    /// job back with [`Scheduler::add_resumed_adaptive_job`].
    ///
    /// The image of an adaptive job is [`Scheduler::adaptive_frame`]'s, not
    /// [`Scheduler::frame`]'s (which still merges every leased pass of every pixel, and is
    /// used for validation and duplicate comparison).
    pub fn add_adaptive_job(
        &mut self,
        id: JobId,
        priority: i32,
        plan: FramePlan,
        frames: std::ops::RangeInclusive<u32>,
        passes_per_unit: u32,
        adaptive: AdaptiveSettings,
    ) -> Result<AdaptiveSettings, AdaptiveError> {
        let ppu = passes_per_unit.max(1);
        let settings = adaptive.for_units(ppu);
        // Checked once here; each frame's state is allocated with its first lease.
        AdaptiveFrame::new(plan, *frames.start(), settings)?;
        let count = frames.clone().count();
        self.add_job(id, priority, plan, frames, ppu);
        if let Some(job) = self.jobs.get_mut(&id) {
            job.frame_bytes = frame_state_bytes(&plan, true);
            job.adaptive = Some(AdaptiveQueue::new(settings, count));
        }
        Ok(settings)
    }

    /// The adaptive settings an adaptive job runs with (rounded to its units,
    /// [`AdaptiveSettings::for_units`]); `None` for other or unknown jobs.
    pub fn adaptive_settings(&self, job_id: JobId) -> Option<AdaptiveSettings> {
        Some(self.jobs.get(&job_id)?.adaptive.as_ref()?.settings)
    }

    /// The adaptive state (and image) of one frame of an adaptive job.
    pub fn adaptive_frame(&self, job_id: JobId, frame: u32) -> Option<&AdaptiveFrame> {
        let job = self.jobs.get(&job_id)?;
        let a = job.adaptive.as_ref()?;
        a.frames
            .get(frame.checked_sub(job.first_frame)? as usize)?
            .as_ref()
    }

    /// The pixels a leased unit of an adaptive job must trace: those its tile's
    /// policy wants for any of the unit's passes ([`crate::AdaptiveTile::wanted_pixels`]).
    /// `None` means every pixel: a job without adaptive stopping, a tile all of whose
    /// pixels are still wanted, or a frame whose policy state is gone.
    ///
    /// A unit is leased only below its tile's lease horizon, where every decision the set
    /// reads is final; so the set is a pure function of the job, the same for every copy
    /// of the unit whenever it is asked (a re-lease after expiry, a duplicate), and the
    /// copies stay byte-identical.
    pub fn wanted_pixels(&self, job_id: JobId, unit: &WorkUnit) -> Option<crate::PixelRuns> {
        self.adaptive_frame(job_id, unit.frame)?
            .tile(unit.tile)?
            .wanted_pixels(unit.first_pass, unit.pass_count)
    }

    /// Cancels a job: nothing more is leased; returns the outstanding leases to drop.
    pub fn cancel(&mut self, job_id: JobId) -> Vec<Lease> {
        let Some(job) = self.jobs.get_mut(&job_id) else {
            return Vec::new();
        };
        job.canceled = true;
        job.returned.clear();
        let ids: Vec<u64> = job.leased.values().copied().collect();
        // Remember them so a late result is answered "canceled", not "unknown lease".
        for (&i, &id) in &job.leased {
            self.lapsed.insert(id, (job_id, i));
        }
        job.leased.clear();
        ids.iter().filter_map(|id| self.leases.remove(id)).collect()
    }

    /// Removes a job entirely (after it is done and stored, or canceled), freeing its
    /// memory.
    pub fn remove_job(&mut self, job_id: JobId) {
        self.cancel(job_id);
        if let Some(job) = self.jobs.remove(&job_id) {
            self.memory.resident = self.memory.resident.saturating_sub(job.resident_bytes());
        }
        self.lapsed.retain(|_, (j, _)| *j != job_id);
    }

    /// Progress of a job.
    pub fn progress(&self, job_id: JobId) -> Option<Progress> {
        let job = self.jobs.get(&job_id)?;
        let tiles = job.plan.tile_count() as u64;
        let full = tiles * u64::from(job.plan.passes);
        let (mut passes_done, mut frames_done) = (0, 0);
        for f in &job.frames {
            match f {
                FrameSlot::Pending => {}
                FrameSlot::Live(f) => {
                    passes_done += f.merged_pass_count();
                    frames_done += u32::from(f.complete());
                }
                FrameSlot::Released => {
                    passes_done += full;
                    frames_done += 1;
                }
            }
        }
        Some(Progress {
            units_total: job.units_total(),
            units_done: job.done.len() as u64,
            units_leased: job.leased.len() as u64,
            passes_done,
            passes_planned: full * job.frames.len() as u64,
            frames_done,
            copies_total: job.copies_total,
            copies_done: job.extra_copies,
        })
    }

    /// True once every frame of the job is complete.
    pub fn is_complete(&self, job_id: JobId) -> bool {
        self.jobs.get(&job_id).is_some_and(Job::is_complete)
    }

    /// The ids of the jobs the scheduler holds.
    pub fn job_ids(&self) -> impl Iterator<Item = JobId> + '_ {
        self.jobs.keys().copied()
    }
}
