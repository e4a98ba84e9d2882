//! Leasing work units to workers: priorities, coarse-to-fine order, deadlines, fencing
//! tokens, re-leasing after expiry, and one merge per unit however often it is rendered.
//!
//! The [`Scheduler`] is pure: the caller passes the clock (`now_ms`) into every call, so
//! the coordinator drives it from real time and tests drive it from a counter.
//!
//! Order (issue 3): jobs of higher priority first, then first come first served; within a
//! job, frames in order and, within a frame, coarse to fine — the first pass chunk of every
//! tile before any tile's second chunk — so a preview covers the whole frame early.
//!
//! A lease carries a unique, increasing `lease_id` that acts as a fencing token: a result
//! is only merged if it answers a lease the scheduler issued for exactly that unit. A lease
//! whose deadline passes returns its unit to the queue (at its canonical position, so the
//! order stays coarse to fine). A late result for a re-leased unit is still useful: being
//! deterministic, it is merged if the unit is not merged yet, and compared with the merged
//! copy otherwise (a mismatch is a faulty-worker event).
//!
//! Adaptive jobs ([`Scheduler::add_adaptive_job`], issue 4): each frame also keeps an
//! [`AdaptiveFrame`] fed with every merged result. Its decisions are taken at fixed pass
//! indices from each tile's own merged state, so the scheduler never leases a unit
//! *beyond an open decision*: a unit whose first pass is at or past its tile's
//! [`crate::AdaptiveTile::lease_horizon`] waits (in canonical order) until the passes
//! before the boundary are merged and the decision is made, and units of a finished tile
//! are dropped without being leased. No speculative work is leased, so nothing has to be
//! thrown away, and which units exist is a function of the job alone: the image is
//! bit-identical with any number of workers. The cost is a short pipeline stall per tile at
//! each boundary (other tiles' units fill it when there are enough tiles).
//!
//! Spot checks (issue 15, [`crate::spot`]): with [`Scheduler::set_spot_check_fraction`]
//! a deterministic fraction of the units is rendered by two different workers. The first
//! copy is held unmerged ([`Submitted::Held`]) and the unit leased again to a worker that
//! has no copy; it is merged once two different workers' copies agree, and a worker whose
//! copy differs is quarantined ([`Scheduler::quarantine`]): no more leases, its leases
//! revoked, its results refused, and every tile it merged a unit into on its word alone
//! dropped and merged again from units other workers render, until an operator lifts it
//! ([`Scheduler::lift_quarantine`]). What happened is reported as [`crate::SpotEvent`]s
//! ([`Scheduler::take_spot_events`]).
//!
//! Memory (issue 16): a frame's per-pixel merge state is allocated when its first unit is
//! leased and released by [`Scheduler::release_frame`]
//! once the frame is complete and its tiles are checkpointed. Allocations are charged to
//! one budget for all jobs ([`Scheduler::set_memory_budget`]): a frame that does not fit
//! waits (its units are not leased) until completed frames free their memory, so the
//! scheduler's per-pixel state is bounded by the budget plus one frame, whatever the jobs.

use crate::adaptive::{AdaptiveError, AdaptiveFrame, AdaptiveSettings};
use crate::merge::{FrameAccumulator, MergeError, Offer};
use crate::plan::{FramePlan, WorkUnit};
use crate::result::UnitResult;
use crate::spot::{is_spot_checked, CopyGroup, SpotCheck, SpotEvent, SpotOutcome};
use std::collections::{BTreeMap, BTreeSet};

/// Identifier of a job.
pub type JobId = u64;
/// Identifier of a worker.
pub type WorkerId = u64;

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

/// Jobs of up to this many units have their spot-checked units counted one by one when
/// added (a hash each); larger ones use the expected count, whose
/// relative error is then below `1 / sqrt(EXACT_SPOT_COUNT x fraction)`.
pub const EXACT_SPOT_COUNT: u64 = 4096;

/// What a restart restored of a job for [`Scheduler::add_resumed_job`].
#[derive(Debug)]
pub struct Resumed {
    /// The frames the job renders (inclusive range).
    pub frames: std::ops::RangeInclusive<u32>,
    /// The accumulators of frames with checkpoints that are not complete, restored from
    /// them; frames neither here nor in `complete` have nothing merged.
    pub restored: Vec<FrameAccumulator>,
    /// Frames every tile of which has all its passes: not loaded, their images are in the
    /// store.
    pub complete: Vec<u32>,
}

/// What a restart restored of an adaptive job for [`Scheduler::add_resumed_adaptive_job`].
#[derive(Debug)]
pub struct ResumedAdaptive {
    /// The frames the job renders (inclusive range).
    pub frames: std::ops::RangeInclusive<u32>,
    /// The adaptive settings as submitted (rounded to the units again when added).
    pub settings: AdaptiveSettings,
    /// Each unfinished frame with checkpoints: its merged passes and, per tile in tile
    /// order, the policy state saved with them (`None`: nothing consumed).
    pub restored: Vec<(FrameAccumulator, Vec<Option<crate::AdaptiveTileCheckpoint>>)>,
    /// Frames whose restored policy had finished every tile: not loaded, released at once
    /// (their images are restored from the store when asked for, as after a release in
    /// the running job).
    pub complete: Vec<u32>,
}

/// Where a frame's merge state is ([`Scheduler::residency`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Residency {
    /// No unit of the frame was leased yet: nothing merged, nothing allocated.
    Pending,
    /// In memory ([`Scheduler::frame`]).
    Live,
    /// Complete, checkpointed and dropped from memory: read it from the store.
    Released,
}

/// One frame of a job in the scheduler (see [`Residency`]).
enum FrameSlot {
    Pending,
    Live(Box<FrameAccumulator>),
    Released,
}

impl FrameSlot {
    fn live(&self) -> Option<&FrameAccumulator> {
        match self {
            Self::Live(f) => Some(f),
            _ => None,
        }
    }
}

/// The memory budget for per-pixel merge state, shared by all jobs.
#[derive(Clone, Copy, Debug)]
struct Memory {
    budget: u64,
    resident: u64,
}

/// Bytes of merge state one frame of `plan` holds in memory: a [`crate::PixelStats`] per
/// pixel, and the adaptive policy's per-pixel state for adaptive jobs.
pub fn frame_state_bytes(plan: &FramePlan, adaptive: bool) -> u64 {
    let per_pixel = FrameAccumulator::BYTES_PER_PIXEL
        + if adaptive {
            AdaptiveFrame::BYTES_PER_PIXEL
        } else {
            0
        };
    u64::from(plan.width) * u64::from(plan.height) * per_pixel
}

struct Job {
    priority: i32,
    seq: u64,
    plan: FramePlan,
    first_frame: u32,
    passes_per_unit: u32,
    frames: Vec<FrameSlot>,
    /// Bytes charged to the budget for each live frame ([`frame_state_bytes`]).
    frame_bytes: u64,
    /// Canonical index of the next never-leased unit.
    cursor: u64,
    /// Units returned to the queue (expired or given back), by canonical index.
    returned: BTreeSet<u64>,
    /// Canonical indices of merged units.
    done: BTreeSet<u64>,
    /// Outstanding leases by canonical unit index.
    leased: BTreeMap<u64, u64>,
    canceled: bool,
    /// A finished adaptive job whose state was dropped to make room
    /// ([`Scheduler::lease`]): complete, with every frame released.
    evicted: bool,
    /// Adaptive jobs only: the policy state and the units it holds back.
    adaptive: Option<AdaptiveQueue>,
    /// Spot-checked units with copies waiting for agreement, by canonical index.
    checks: BTreeMap<u64, SpotCheck>,
    /// Copies of spot-checked units received beyond the one a merged unit counts in
    /// `done`: the work the spot checks have added so far ([`Progress::copies_done`]).
    extra_copies: u64,
    /// Second copies the spot checks render over the whole job ([`Progress::copies_total`]),
    /// counted when the job is added or the fraction changes, not per status request.
    copies_total: u64,
    /// Units merged (or buffered) on one worker's word: that worker and the digest. If
    /// the worker is quarantined, their tiles are merged again.
    unverified: BTreeMap<u64, (WorkerId, u64)>,
    /// Units of dropped tiles that a quarantined worker had merged: that worker and its
    /// copy's digest, compared with the copy that replaces it.
    suspect: BTreeMap<u64, (WorkerId, u64)>,
}

/// The adaptive part of a job: one policy state per frame, units waiting for a decision
/// and units a decision made unnecessary (both by canonical index).
struct AdaptiveQueue {
    settings: AdaptiveSettings,
    /// One per frame, allocated with the frame's accumulator.
    frames: Vec<Option<AdaptiveFrame>>,
    waiting: BTreeSet<u64>,
    skipped: BTreeSet<u64>,
}

/// What the adaptive policy says about leasing a unit now.
#[derive(PartialEq)]
enum Gate {
    Lease,
    Wait,
    Skip,
}

impl Job {
    /// The units of job `id` spot-checked at `fraction`: counted one by one for up to
    /// [`EXACT_SPOT_COUNT`] units, the expected `units x fraction` (rounded) beyond.
    fn spot_copies(&self, fraction: f64, id: JobId) -> u64 {
        let units = self.units_total();
        if fraction <= 0.0 {
            0
        } else if units <= EXACT_SPOT_COUNT {
            (0..units)
                .filter(|&i| is_spot_checked(fraction, id, &self.unit(i)))
                .count() as u64
        } else {
            (units as f64 * fraction).round() as u64
        }
    }

    /// Whether unit `i` may be leased now, must wait for a decision, or is not needed.
    fn gate(&self, i: u64) -> Gate {
        let Some(a) = &self.adaptive else {
            return Gate::Lease;
        };
        let u = self.unit(i);
        let tile = a
            .frames
            .get((u.frame - self.first_frame) as usize)
            .and_then(Option::as_ref)
            .and_then(|f| f.tile(u.tile));
        match tile {
            None => Gate::Skip,
            Some(t) if t.finished() || u.first_pass >= t.end_pass() => Gate::Skip,
            Some(t) if u.first_pass < t.lease_horizon() => Gate::Lease,
            Some(_) => Gate::Wait,
        }
    }

    /// The next adaptive unit to lease: a returned or waiting unit whose decision is made,
    /// else the next one from the cursor (holding back those that must wait).
    fn next_adaptive_index(
        &mut self,
        mem: &mut Memory,
        worker: WorkerId,
        alone: bool,
    ) -> Option<u64> {
        let candidates = self
            .returned
            .iter()
            .chain(
                self.adaptive
                    .as_ref()
                    .map(|a| &a.waiting)
                    .into_iter()
                    .flatten(),
            )
            .copied()
            .collect::<Vec<u64>>();
        let mut candidates = candidates;
        // Canonical (coarse-to-fine) order across both sets.
        candidates.sort_unstable();
        candidates.dedup();
        for i in candidates {
            let gate = self.gate(i);
            if gate == Gate::Wait || (gate == Gate::Lease && !self.may_render(i, worker, alone)) {
                continue;
            }
            self.returned.remove(&i);
            let a = self.adaptive.as_mut()?;
            a.waiting.remove(&i);
            if gate == Gate::Lease {
                return Some(i);
            }
            a.skipped.insert(i);
        }
        while let Some(i) = self.next_from_cursor(mem) {
            let gate = self.gate(i);
            let a = self.adaptive.as_mut()?;
            match gate {
                Gate::Lease => return Some(i),
                Gate::Wait => a.waiting.insert(i),
                Gate::Skip => a.skipped.insert(i),
            };
        }
        None
    }

    fn is_complete(&self) -> bool {
        if self.evicted {
            return true;
        }
        match &self.adaptive {
            // A released frame was finished when it was released (its state is in the
            // store now).
            Some(a) => a.frames.iter().zip(&self.frames).all(|(f, slot)| {
                matches!(slot, FrameSlot::Released)
                    || f.as_ref().is_some_and(AdaptiveFrame::finished)
            }),
            None => self.frames.iter().all(|f| match f {
                FrameSlot::Pending => false,
                FrameSlot::Live(f) => f.complete(),
                FrameSlot::Released => true,
            }),
        }
    }

    /// Index into `frames` of the frame of canonical unit `i`.
    fn frame_index(&self, i: u64) -> usize {
        (i / self.units_per_frame()) as usize
    }

    /// Allocates frame `k`'s merge state if it is pending and fits the budget; whether
    /// it is live now.
    fn make_live(&mut self, k: usize, mem: &mut Memory) -> bool {
        match self.frames.get(k) {
            Some(FrameSlot::Live(_)) => return true,
            Some(FrameSlot::Pending) => {}
            Some(FrameSlot::Released) | None => return false,
        }
        if mem.resident.saturating_add(self.frame_bytes) > mem.budget && mem.resident > 0 {
            return false;
        }
        let frame = self.first_frame + k as u32;
        if let Some(a) = self.adaptive.as_mut() {
            // Validated when the job was added; cannot fail.
            match AdaptiveFrame::new(self.plan, frame, a.settings) {
                Ok(f) => a.frames[k] = Some(f),
                Err(_) => return false,
            }
        }
        self.frames[k] = FrameSlot::Live(Box::new(FrameAccumulator::for_frame(self.plan, frame)));
        mem.resident += self.frame_bytes;
        true
    }

    fn chunks(&self) -> u64 {
        self.plan.chunks_per_tile(self.passes_per_unit) as u64
    }

    fn units_per_frame(&self) -> u64 {
        self.chunks() * self.plan.tile_count() as u64
    }

    fn units_total(&self) -> u64 {
        self.units_per_frame() * self.frames.len() as u64
    }

    /// Bytes of this job's live frames.
    fn resident_bytes(&self) -> u64 {
        let live = self
            .frames
            .iter()
            .filter(|f| matches!(f, FrameSlot::Live(_)))
            .count() as u64;
        live * self.frame_bytes
    }

    /// The unit with canonical index `i`: frame-major, then pass chunk, then tile.
    fn unit(&self, i: u64) -> WorkUnit {
        let per_frame = self.units_per_frame();
        let frame = (i / per_frame) as u32;
        let r = i % per_frame;
        let tiles = self.plan.tile_count() as u64;
        let chunk = (r / tiles) as u32;
        let tile = (r % tiles) as u32;
        let first_pass = chunk * self.passes_per_unit;
        let pass_count = self.passes_per_unit.min(self.plan.passes - first_pass);
        WorkUnit {
            frame: self.first_frame + frame,
            tile,
            first_pass,
            pass_count,
        }
    }

    /// Inverse of [`Job::unit`]; `None` if `u` is not one of this job's units.
    fn index(&self, u: &WorkUnit) -> Option<u64> {
        let frame = u.frame.checked_sub(self.first_frame)? as u64;
        if frame >= self.frames.len() as u64
            || u.tile >= self.plan.tile_count()
            || !u.first_pass.is_multiple_of(self.passes_per_unit)
        {
            return None;
        }
        let i = frame * self.units_per_frame()
            + (u.first_pass / self.passes_per_unit) as u64 * self.plan.tile_count() as u64
            + u.tile as u64;
        (i < self.units_total() && self.unit(i) == *u).then_some(i)
    }

    fn next_index(&mut self, mem: &mut Memory, worker: WorkerId, alone: bool) -> Option<u64> {
        if self.adaptive.is_some() {
            return self.next_adaptive_index(mem, worker, alone);
        }
        // A returned unit was leased before, so its frame is live.
        if let Some(i) = self
            .returned
            .iter()
            .copied()
            .find(|&i| self.may_render(i, worker, alone))
        {
            self.returned.remove(&i);
            return Some(i);
        }
        self.next_from_cursor(mem)
    }

    /// Unit `i`, a suspect of a quarantined worker, merged again with `digest`: the
    /// comparison with the suspect copy.
    fn reverified(&mut self, job: JobId, i: u64, digest: u64) -> Option<SpotEvent> {
        let (worker, old) = self.suspect.remove(&i)?;
        Some(SpotEvent::Reverified {
            job,
            unit: self.unit(i),
            worker,
            identical: old == digest,
        })
    }

    /// Whether `worker` may render unit `i`: a spot-checked unit's next copy goes to a
    /// worker without a copy of it (see [`SpotCheck::eligible`] for a worker alone).
    fn may_render(&self, i: u64, worker: WorkerId, alone: bool) -> bool {
        self.checks
            .get(&i)
            .is_none_or(|c| c.eligible(worker, alone))
    }

    /// Drops tile `tile` of live frame `k` (spot-check repair): its merged and buffered
    /// passes and its adaptive state are cleared and every one of its units is leased
    /// again (those leased now are merged when they arrive). Units `quarantined` had
    /// merged are remembered as suspect, to compare with their new copies.
    fn reset_tile(&mut self, k: usize, tile: u32, quarantined: WorkerId) {
        if let Some(FrameSlot::Live(acc)) = self.frames.get_mut(k) {
            acc.reset_tile(tile);
        }
        if let Some(Some(f)) = self.adaptive.as_mut().and_then(|a| a.frames.get_mut(k)) {
            f.reset_tile(tile);
        }
        let tiles = self.plan.tile_count() as u64;
        let base = k as u64 * self.units_per_frame() + u64::from(tile);
        for c in 0..self.chunks() {
            let i = base + c * tiles;
            self.done.remove(&i);
            if let Some((w, d)) = self.unverified.remove(&i) {
                if w == quarantined {
                    self.suspect.insert(i, (w, d));
                }
            }
            if let Some(a) = self.adaptive.as_mut() {
                a.skipped.remove(&i);
                a.waiting.remove(&i);
            }
            // Units past the cursor were never leased: the cursor reaches them anyway.
            if i < self.cursor && !self.leased.contains_key(&i) {
                self.returned.insert(i);
            }
        }
    }

    /// The never-leased unit at the cursor, advancing it: units merged before a restart
    /// are skipped (a resumed job's `done` set is not a prefix of the canonical order), and
    /// so are the units of a released frame; a unit whose frame does not fit the budget
    /// yet waits, with the cursor on it (`None`).
    ///
    /// A released adaptive frame can have units the cursor has not reached: its policy
    /// finished every tile before the passes past the tiles' ends were visited (skipped).
    /// They have nothing to render, and waiting on them stalled the job's later frames.
    fn next_from_cursor(&mut self, mem: &mut Memory) -> Option<u64> {
        while self.cursor < self.units_total() {
            let i = self.cursor;
            if self.done.contains(&i) {
                self.cursor += 1;
                continue;
            }
            let k = self.frame_index(i);
            if matches!(self.frames.get(k), Some(FrameSlot::Released)) {
                self.cursor = (k as u64 + 1) * self.units_per_frame();
                continue;
            }
            if !self.make_live(k, mem) {
                return None;
            }
            self.cursor += 1;
            return Some(i);
        }
        None
    }

    /// Units that wait to be leased: returned ones, the never-leased ones from the cursor
    /// on (less those merged before a restart) and, for adaptive jobs, those waiting for a
    /// decision (an upper bound: a decision may make some unnecessary).
    fn queued(&self) -> u64 {
        if self.canceled {
            return 0;
        }
        let ahead = self.units_total().saturating_sub(self.cursor);
        let merged_ahead = self.done.range(self.cursor..).count() as u64;
        let waiting = self.adaptive.as_ref().map_or(0, |a| a.waiting.len() as u64);
        let queued = self.returned.len() as u64 + ahead.saturating_sub(merged_ahead) + waiting;
        self.adaptive_open_units()
            .map_or(queued, |open| queued.min(open))
    }

    /// For an adaptive job: the units its policy lets be rendered before the next
    /// decisions, leased or not, which bounds those leasable now: per unfinished tile of
    /// a live frame, the units covering passes `[consumed, lease_horizon)`; per tile of a
    /// frame not yet live, those before its first decision. `None` for other jobs.
    ///
    /// Why: the units ahead of the cursor are not leasable while they wait for a
    /// decision. Counted as queued, they made [`tail_share`] give the first worker to ask
    /// the whole window before a decision (on a whole-frame bdpt tile: every open pass),
    /// and the other workers waited for it.
    fn adaptive_open_units(&self) -> Option<u64> {
        let a = self.adaptive.as_ref()?;
        let ppu = self.passes_per_unit.max(1);
        let first_window = a
            .settings
            .next_boundary(0)
            .unwrap_or(self.plan.passes)
            .min(self.plan.passes)
            .div_ceil(ppu);
        let mut open = 0u64;
        for (f, slot) in a.frames.iter().zip(&self.frames) {
            match (f, slot) {
                (_, FrameSlot::Released) => {}
                (Some(f), _) => {
                    for t in f.tiles().iter().filter(|t| !t.finished()) {
                        let passes = t.lease_horizon().saturating_sub(t.consumed_passes());
                        open += u64::from(passes.div_ceil(ppu));
                    }
                }
                (None, _) => {
                    open += u64::from(self.plan.tile_count()) * u64::from(first_window);
                }
            }
        }
        Some(open)
    }

    fn has_work(&self) -> bool {
        let waiting = self
            .adaptive
            .as_ref()
            .is_some_and(|a| !a.waiting.is_empty());
        !self.canceled && (!self.returned.is_empty() || self.cursor < self.units_total() || waiting)
    }
}

/// How many of `queued` waiting units a worker with `threads` of the farm's
/// `total_threads` render threads may lease at once, when it asks for `max_units`: half
/// its share of the queue, `ceil(queued * threads / (2 * total_threads))`, and at least one
/// unit ("factoring", Hummel, Schonberg and Flynn 1992).
///
/// Early in a job the share is large and a worker gets the batch it asked for; as the
/// queue drains, batches halve round by round, so the work still held when the queue
/// runs dry is a few units per worker and every worker finishes at about the same time.
/// Half rather than the whole share because workers are not equally fast and a worker
/// that prefetches holds two batches. A worker alone (its threads are all the threads)
/// has no one to wait for and gets what it asked for.
///
/// ```
/// use tessera_farm::tail_share;
/// assert_eq!(tail_share(1000, 1, 2, 32), 32); // early: what was asked
/// assert_eq!(tail_share(40, 1, 2, 32), 10); // the tail: a quarter each of two workers
/// assert_eq!(tail_share(40, 3, 4, 32), 15); // a worker with 3 of the 4 threads
/// assert_eq!(tail_share(3, 1, 2, 32), 1); // the last units one at a time
/// assert_eq!(tail_share(3, 4, 4, 32), 32); // a worker alone
/// assert_eq!(tail_share(0, 0, 0, 0), 1); // never zero
/// ```
pub fn tail_share(queued: u64, threads: u64, total_threads: u64, max_units: usize) -> usize {
    if threads >= total_threads {
        return max_units.max(1);
    }
    let total = total_threads.max(1);
    let share = (u128::from(queued) * u128::from(threads.max(1)))
        .div_ceil(2 * u128::from(total))
        .max(1);
    usize::try_from(share)
        .unwrap_or(usize::MAX)
        .min(max_units.max(1))
}

/// `result` with the pixels outside the set its lease named set to 0, after checking it
/// whole (a worker is still faulted for a NaN in a pixel it did not have to trace).
///
/// Why: a worker that traces only the named pixels reports 0 for the others, but one
/// that predates `Lease.wanted` reports real values there, and bdpt reports the splats
/// that landed on them (it skips their camera subpaths, not the light subpaths). The
/// policy reads neither, yet the digests that compare copies of a unit would differ;
/// zeroing here makes every valid copy of a unit the same bytes.
fn canonical_masked(
    mut result: UnitResult,
    wanted: Option<&crate::PixelRuns>,
    plan: &FramePlan,
) -> Result<UnitResult, SubmitError> {
    let Some(wanted) = wanted else {
        return Ok(result);
    };
    result
        .validate(plan)
        .map_err(|e| SubmitError::Invalid(e.into()))?;
    let n = plan.tile(result.unit.tile).pixel_count().max(1);
    for (k, m) in result.pass_means.iter_mut().enumerate() {
        if !wanted.contains(k % n) {
            *m = [0.0; 3];
        }
    }
    Ok(result)
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
            memory: Memory {
                budget: u64::MAX,
                resident: 0,
            },
            next_lease_id: first_lease_id + 1,
            next_seq: 0,
            previous_run_max_lease: first_lease_id,
            spot_fraction: 0.0,
            quarantined: BTreeSet::new(),
            spot_events: Vec::new(),
        }
    }

    /// Sets the fraction of units spot-checked (0 by default: none; clamped to 0..=1, NaN
    /// is 0). Which units are checked is [`crate::is_spot_checked`] of the job and unit,
    /// so it is the same after a restart with the same fraction.
    pub fn set_spot_check_fraction(&mut self, fraction: f64) {
        self.spot_fraction = if fraction.is_nan() {
            0.0
        } else {
            fraction.clamp(0.0, 1.0)
        };
        let f = self.spot_fraction;
        for (&id, job) in &mut self.jobs {
            job.copies_total = job.spot_copies(f, id);
        }
    }

    /// The fraction of units spot-checked.
    pub fn spot_check_fraction(&self) -> f64 {
        self.spot_fraction
    }

    /// Whether `worker` is quarantined.
    pub fn is_quarantined(&self, worker: WorkerId) -> bool {
        self.quarantined.contains(&worker)
    }

    /// The quarantined workers.
    pub fn quarantined(&self) -> impl Iterator<Item = WorkerId> + '_ {
        self.quarantined.iter().copied()
    }

    /// Spot-checked units whose copies wait for agreement, over all jobs, and how many of
    /// them are disputed (copies that differ, waiting for a third worker).
    pub fn spot_checks_waiting(&self) -> (u64, u64) {
        self.jobs
            .values()
            .flat_map(|j| j.checks.values())
            .fold((0, 0), |(n, d), c| {
                (n + 1, d + u64::from(c.groups.len() > 1))
            })
    }

    /// What spot checks found since the last call, oldest first.
    pub fn take_spot_events(&mut self) -> Vec<SpotEvent> {
        std::mem::take(&mut self.spot_events)
    }

    /// Quarantines `worker` (found faulty by a spot check, or by the caller): it gets no
    /// more leases, its outstanding leases are revoked (their units return to the queue),
    /// its results are refused ([`SubmitError::Quarantined`]), its copies of spot-checked
    /// units no longer count, and every tile of a live frame of an unfinished job into
    /// which it merged a unit on its word alone is dropped and merged again from scratch
    /// (a tile's statistics are a running accumulation, so a corrupt pass cannot be taken
    /// out). Its units in released frames or finished jobs cannot be rendered again; they
    /// are counted in the [`SpotEvent::Quarantined`] this pushes. Returns false if the
    /// worker was already quarantined.
    pub fn quarantine(&mut self, worker: WorkerId, reason: &str) -> bool {
        if !self.quarantined.insert(worker) {
            return false;
        }
        let held: Vec<u64> = self
            .leases
            .values()
            .filter(|l| l.worker == worker)
            .map(|l| l.lease_id)
            .collect();
        for id in held {
            self.release(id);
        }
        let mut reset_tiles = Vec::new();
        let mut unrepaired_units = 0u64;
        for (&job_id, job) in &mut self.jobs {
            for check in job.checks.values_mut() {
                for g in &mut check.groups {
                    g.workers.retain(|&w| w != worker);
                }
                check.groups.retain(|g| !g.workers.is_empty());
            }
            job.checks.retain(|_, c| !c.groups.is_empty());
            let units: Vec<u64> = job
                .unverified
                .iter()
                .filter(|(_, (w, _))| *w == worker)
                .map(|(&i, _)| i)
                .collect();
            if units.is_empty() || job.canceled {
                continue;
            }
            if job.is_complete() {
                unrepaired_units += units.len() as u64;
                continue;
            }
            let mut tiles = BTreeSet::new();
            for i in units {
                let k = job.frame_index(i);
                if matches!(job.frames.get(k), Some(FrameSlot::Live(_))) {
                    tiles.insert((k, job.unit(i).tile));
                } else {
                    unrepaired_units += 1;
                }
            }
            for (k, tile) in tiles {
                job.reset_tile(k, tile, worker);
                reset_tiles.push((job_id, job.first_frame + k as u32, tile));
            }
        }
        self.spot_events.push(SpotEvent::Quarantined {
            worker,
            reason: reason.to_string(),
            reset_tiles,
            unrepaired_units,
        });
        true
    }

    /// Lifts the quarantine of `worker` (an operator decided to trust it again): it is
    /// leased units and its results are taken again. Nothing the quarantine did is undone:
    /// its dropped tiles stay dropped (their units were or are being rendered again by
    /// others), its revoked leases stay lapsed, its discarded spot-check copies stay gone,
    /// and its old copies that the repair compares with their new ones
    /// ([`SpotEvent::Reverified`]) are still compared. Its units the quarantine could not
    /// repair (in released frames or finished jobs, counted then in
    /// [`SpotEvent::Quarantined`]) are forgotten as its own, so a later quarantine of the
    /// same worker neither counts them twice nor tries to repair what cannot be. Returns
    /// false if it was not quarantined.
    pub fn lift_quarantine(&mut self, worker: WorkerId) -> bool {
        if !self.quarantined.remove(&worker) {
            return false;
        }
        for job in self.jobs.values_mut() {
            job.unverified.retain(|_, (w, _)| *w != worker);
        }
        true
    }

    /// Adds a job resumed after a restart (see [`Resumed`]), cut into units of
    /// `passes_per_unit` passes as before the restart. Units whose passes
    /// every checkpoint already merged are done; everything else is leased again in
    /// canonical order.
    ///
    /// Checkpoints whose merged passes do not end on a unit boundary (impossible with the
    /// same `passes_per_unit`) are refused: their next unit would overlap merged passes.
    ///
    /// Memory: complete frames are released at once (their checkpoints are in the store),
    /// frames with no merged pass are left pending, the rest stay live and are charged to
    /// the budget even beyond it (what a run merged, the next keeps).
    pub fn add_resumed_job(
        &mut self,
        id: JobId,
        priority: i32,
        plan: FramePlan,
        resumed: Resumed,
        passes_per_unit: u32,
    ) -> Result<(), String> {
        let Resumed {
            frames,
            restored,
            complete,
        } = resumed;
        let passes_per_unit = passes_per_unit.max(1);
        if frames.is_empty() {
            return Err(format!("job {id}: no frames to resume"));
        }
        let first_frame = *frames.start();
        let mut slots: Vec<FrameSlot> = frames.clone().map(|_| FrameSlot::Pending).collect();
        for f in complete {
            match f
                .checked_sub(first_frame)
                .and_then(|k| slots.get_mut(k as usize))
            {
                Some(slot) => *slot = FrameSlot::Released,
                None => return Err(format!("job {id}: frame {f} is outside the job")),
            }
        }
        for f in &restored {
            if *f.plan() != plan {
                return Err(format!("job {id}: frame {} has another plan", f.frame()));
            }
            if !frames.contains(&f.frame()) {
                return Err(format!("job {id}: frame {} is outside the job", f.frame()));
            }
            for t in f.tiles() {
                let m = t.merged_passes();
                if m > plan.passes || (m % passes_per_unit != 0 && m != plan.passes) {
                    return Err(format!(
                        "job {id}: frame {} tile {} merged {m} passes, not a whole number of \
                         {passes_per_unit}-pass units",
                        f.frame(),
                        t.rect().index
                    ));
                }
            }
        }
        for f in restored {
            let k = (f.frame() - first_frame) as usize;
            slots[k] = FrameSlot::Live(Box::new(f));
        }
        let mut job = self.new_job(id, priority, plan, first_frame, passes_per_unit, slots);
        for i in 0..job.units_total() {
            let u = job.unit(i);
            let merged = match &job.frames[(u.frame - first_frame) as usize] {
                FrameSlot::Pending => continue,
                FrameSlot::Live(f) => f.tiles()[u.tile as usize].merged_passes(),
                FrameSlot::Released => plan.passes,
            };
            if u64::from(merged) >= u.end_pass() {
                job.done.insert(i);
            }
        }
        for slot in &mut job.frames {
            let state = slot.live().map(|f| (f.complete(), f.merged_pass_count()));
            *slot = match state {
                Some((true, _)) => FrameSlot::Released,
                Some((false, 0)) => FrameSlot::Pending,
                _ => std::mem::replace(slot, FrameSlot::Pending),
            };
        }
        self.memory.resident += job.resident_bytes();
        self.jobs.insert(id, job);
        Ok(())
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

    /// Adds an adaptive job (issue 4): like [`Scheduler::add_job`], but each tile stops
    /// being leased once `adaptive`'s policy says it is finished, and the job is complete
    /// when every tile of every frame is (see the module docs for how units wait for
    /// decisions). Decision boundaries must fall on unit boundaries, so `min_passes` and
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
            job.adaptive = Some(AdaptiveQueue {
                settings,
                frames: (0..count).map(|_| None).collect(),
                waiting: BTreeSet::new(),
                skipped: BTreeSet::new(),
            });
        }
        Ok(settings)
    }

    /// Adds an adaptive job resumed after a restart (issue 15): like
    /// [`Scheduler::add_adaptive_job`], with each frame in `restored` brought back from its
    /// checkpoints: the merged passes (the accumulator) and, per tile in tile order, the
    /// policy state saved with them (`None`: nothing consumed). Units whose passes a tile
    /// merged are done; the rest are gated by the restored decisions exactly as they
    /// would have been without the restart (leased, waiting for a decision, or skipped),
    /// so the job ends with the image an uninterrupted run makes, bit for bit.
    ///
    /// Refuses (naming the frame and tile) a policy state that the settings could not have
    /// produced ([`AdaptiveFrame::restore`]), one that consumed other passes than its tile
    /// merged (an unfinished tile consumes every merged pass; a finished one may have
    /// merged a unit past its end), a frame outside the job or of another plan, and merged
    /// passes that do not end on a unit boundary. Restored frames are live and charged to
    /// the memory budget even beyond it (the caller restores only the unfinished ones);
    /// `complete` frames are released, their units never leased again.
    pub fn add_resumed_adaptive_job(
        &mut self,
        id: JobId,
        priority: i32,
        plan: FramePlan,
        passes_per_unit: u32,
        resumed: ResumedAdaptive,
    ) -> Result<AdaptiveSettings, String> {
        let ResumedAdaptive {
            frames,
            settings: adaptive,
            restored,
            complete,
        } = resumed;
        let ppu = passes_per_unit.max(1);
        let settings = adaptive.for_units(ppu);
        AdaptiveFrame::new(plan, *frames.start(), settings)
            .map_err(|e| format!("job {id}: {e}"))?;
        let first_frame = *frames.start();
        let mut live = Vec::with_capacity(restored.len());
        for (acc, checkpoints) in restored {
            let f = acc.frame();
            if *acc.plan() != plan {
                return Err(format!("job {id}: frame {f} has another plan"));
            }
            if !frames.contains(&f) {
                return Err(format!("job {id}: frame {f} is outside the job"));
            }
            let policy = AdaptiveFrame::restore(plan, f, settings, &checkpoints)
                .map_err(|e| format!("job {id}: frame {f}: {e}"))?;
            for (t, a) in acc.tiles().iter().zip(policy.tiles()) {
                let (merged, consumed) = (t.merged_passes(), a.consumed_passes());
                let consistent = if a.finished() {
                    consumed <= merged
                } else {
                    consumed == merged
                };
                if !consistent || (merged % ppu != 0 && merged != plan.passes) {
                    return Err(format!(
                        "job {id}: frame {f} tile {}: {merged} passes merged in units of \
                         {ppu}, {consumed} consumed by the adaptive policy{}",
                        t.rect().index,
                        if a.finished() { " (finished)" } else { "" }
                    ));
                }
            }
            live.push((acc, policy));
        }
        for &f in &complete {
            if !frames.contains(&f) {
                return Err(format!("job {id}: frame {f} is outside the job"));
            }
            if live.iter().any(|(acc, _)| acc.frame() == f) {
                return Err(format!(
                    "job {id}: frame {f} is both finished and in progress"
                ));
            }
        }
        let count = frames.clone().count();
        self.add_job(id, priority, plan, frames, ppu);
        let frame_bytes = frame_state_bytes(&plan, true);
        let Some(job) = self.jobs.get_mut(&id) else {
            return Err(format!("job {id}: not added"));
        };
        job.frame_bytes = frame_bytes;
        let mut queue = AdaptiveQueue {
            settings,
            frames: (0..count).map(|_| None).collect(),
            waiting: BTreeSet::new(),
            skipped: BTreeSet::new(),
        };
        for &f in &complete {
            job.frames[(f - first_frame) as usize] = FrameSlot::Released;
        }
        for (acc, policy) in live {
            let k = (acc.frame() - first_frame) as usize;
            job.frames[k] = FrameSlot::Live(Box::new(acc));
            queue.frames[k] = Some(policy);
            self.memory.resident += frame_bytes;
        }
        job.adaptive = Some(queue);
        for i in 0..job.units_total() {
            let u = job.unit(i);
            if let FrameSlot::Live(f) = &job.frames[(u.frame - first_frame) as usize] {
                if u64::from(f.tiles()[u.tile as usize].merged_passes()) >= u.end_pass() {
                    job.done.insert(i);
                }
            }
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

    /// The pixels a leased unit of an adaptive job must trace (issue 15): those its tile's
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

    /// Leases up to `max_units` units to `worker`.
    ///
    /// Under memory pressure (more than half the budget resident while a job has work),
    /// finished adaptive jobs, oldest first, give their frames back first: their policy
    /// state is not checkpointed (so they are not released as their frames complete),
    /// and their images then come from the store's checkpoints, as after a restart.
    ///
    /// The worker is not taken to be alone: a spot-checked unit it has a copy of waits
    /// for another worker ([`Scheduler::lease_among`] knows better). A quarantined worker
    /// gets nothing.
    pub fn lease(&mut self, worker: WorkerId, now_ms: u64, max_units: usize) -> Vec<Lease> {
        self.lease_as(worker, now_ms, max_units, false)
    }

    fn lease_as(
        &mut self,
        worker: WorkerId,
        now_ms: u64,
        max_units: usize,
        alone: bool,
    ) -> Vec<Lease> {
        if self.quarantined.contains(&worker) {
            return Vec::new();
        }
        self.evict_finished_adaptive();
        let mut order: Vec<(i32, u64, JobId)> = self
            .jobs
            .iter()
            .filter(|(_, j)| j.has_work())
            .map(|(&id, j)| (-j.priority, j.seq, id))
            .collect();
        order.sort_unstable();
        let mut out = Vec::new();
        for (_, _, id) in order {
            let job = self.jobs.get_mut(&id).expect("listed job exists");
            while out.len() < max_units {
                let Some(i) = job.next_index(&mut self.memory, worker, alone) else {
                    break;
                };
                let lease = Lease {
                    lease_id: self.next_lease_id,
                    job: id,
                    unit: job.unit(i),
                    worker,
                    deadline_ms: now_ms.saturating_add(self.lease_ms),
                    leased_ms: now_ms,
                };
                self.next_lease_id += 1;
                job.leased.insert(i, lease.lease_id);
                self.leases.insert(lease.lease_id, lease);
                self.next_expiry_ms = self.next_expiry_ms.min(lease.deadline_ms);
                out.push(lease);
            }
            if out.len() >= max_units {
                break;
            }
        }
        out
    }

    /// [`Scheduler::lease`] for a worker with `threads` of the `total_threads` render
    /// threads of the workers sharing the queue: at most [`tail_share`] of the units
    /// waiting, so that near the end of the work leases shrink to single units and no
    /// worker is left rendering a large batch alone while the others wait (issue 14).
    /// Only who renders which unit depends on it, never what a unit is, so the image is
    /// the same.
    ///
    /// A worker alone (`threads >= total_threads`) may render the second copy of a
    /// spot-checked unit it rendered first: there is no one else to compare with, and a
    /// farm of one worker must still finish its jobs.
    pub fn lease_among(
        &mut self,
        worker: WorkerId,
        now_ms: u64,
        max_units: usize,
        threads: u64,
        total_threads: u64,
    ) -> Vec<Lease> {
        let queued = self
            .jobs
            .values()
            .filter(|j| j.has_work())
            .map(Job::queued)
            .sum();
        let max = tail_share(queued, threads, total_threads, max_units);
        self.lease_as(worker, now_ms, max, threads >= total_threads)
    }

    fn evict_finished_adaptive(&mut self) {
        let pressure = |m: &Memory| m.resident > m.budget / 2;
        if !pressure(&self.memory) || !self.jobs.values().any(Job::has_work) {
            return;
        }
        let mut finished: Vec<(u64, JobId)> = self
            .jobs
            .iter()
            .filter(|(_, j)| j.adaptive.is_some() && !j.evicted && j.is_complete())
            .map(|(&id, j)| (j.seq, id))
            .collect();
        finished.sort_unstable();
        for (_, id) in finished {
            if !pressure(&self.memory) {
                break;
            }
            let Some(job) = self.jobs.get_mut(&id) else {
                continue;
            };
            self.memory.resident = self.memory.resident.saturating_sub(job.resident_bytes());
            job.frames.iter_mut().for_each(|f| *f = FrameSlot::Released);
            if let Some(a) = job.adaptive.as_mut() {
                a.frames.iter_mut().for_each(|f| *f = None);
            }
            job.evicted = true;
        }
    }

    /// Extends the given leases held by `worker`; returns the ones extended with their new
    /// deadlines (leases that lapsed or belong to someone else are not).
    pub fn extend(&mut self, worker: WorkerId, lease_ids: &[u64], now_ms: u64) -> Vec<(u64, u64)> {
        let mut out = Vec::new();
        for id in lease_ids {
            if let Some(l) = self.leases.get_mut(id) {
                if l.worker == worker && l.deadline_ms >= now_ms {
                    l.deadline_ms = now_ms.saturating_add(self.lease_ms);
                    // Only a clock that went back can lower a deadline; keep the bound
                    // of `expire` true even then.
                    self.next_expiry_ms = self.next_expiry_ms.min(l.deadline_ms);
                    out.push((*id, l.deadline_ms));
                }
            }
        }
        out
    }

    /// Returns the units of every lease whose deadline has passed to the queue.
    pub fn expire(&mut self, now_ms: u64) -> Vec<Lease> {
        if self.next_expiry_ms >= now_ms {
            return Vec::new();
        }
        let expired: Vec<Lease> = self
            .leases
            .values()
            .filter(|l| l.deadline_ms < now_ms)
            .copied()
            .collect();
        for l in &expired {
            self.release(l.lease_id);
        }
        self.next_expiry_ms = self
            .leases
            .values()
            .map(|l| l.deadline_ms)
            .min()
            .unwrap_or(u64::MAX);
        expired
    }

    /// Gives leases back (a worker shutting down): their units return to the queue.
    pub fn give_back(&mut self, worker: WorkerId, lease_ids: &[u64]) {
        for id in lease_ids {
            if self.leases.get(id).is_some_and(|l| l.worker == worker) {
                self.release(*id);
            }
        }
    }

    /// Extends every lease deadline to at least `deadline_ms` (a restarted coordinator's
    /// grace period for workers to reconnect).
    pub fn grace(&mut self, deadline_ms: u64) {
        for l in self.leases.values_mut() {
            l.deadline_ms = l.deadline_ms.max(deadline_ms);
        }
    }

    fn release(&mut self, lease_id: u64) {
        let Some(l) = self.leases.remove(&lease_id) else {
            return;
        };
        if let Some(job) = self.jobs.get_mut(&l.job) {
            if let Some(i) = job.index(&l.unit) {
                self.lapsed.insert(lease_id, (l.job, i));
                if job.leased.get(&i) == Some(&lease_id) {
                    job.leased.remove(&i);
                    if !job.done.contains(&i) && !job.canceled {
                        job.returned.insert(i);
                    }
                }
            }
        }
    }

    /// Accepts the result of `lease_id` from the worker that holds the lease (see
    /// [`Scheduler::submit_from`]; a lapsed lease's worker is not known here, so spot
    /// checks count such a copy as one of an unknown worker, [`WorkerId::MAX`]).
    pub fn submit(
        &mut self,
        lease_id: u64,
        job_id: JobId,
        result: UnitResult,
    ) -> Result<Submitted, SubmitError> {
        let worker = self
            .leases
            .get(&lease_id)
            .map_or(WorkerId::MAX, |l| l.worker);
        self.submit_from(worker, lease_id, job_id, result)
    }

    /// Accepts `worker`'s result for `lease_id`. The lease must have been issued for
    /// exactly the result's unit (it may have lapsed: a late result is still merged once or
    /// compared). A spot-checked unit's copy is held until a copy from another worker
    /// agrees ([`Submitted::Held`]; see the module docs); a quarantined worker's result is
    /// refused.
    pub fn submit_from(
        &mut self,
        worker: WorkerId,
        lease_id: u64,
        job_id: JobId,
        result: UnitResult,
    ) -> Result<Submitted, SubmitError> {
        let spot_fraction = self.spot_fraction;
        let quarantined = self.quarantined.contains(&worker);
        let job = self
            .jobs
            .get_mut(&job_id)
            .ok_or(SubmitError::UnknownLease(lease_id))?;
        if job.canceled {
            return Err(SubmitError::Canceled(job_id));
        }
        let i = job
            .index(&result.unit)
            .ok_or(SubmitError::UnknownLease(lease_id))?;
        let issued = match self.leases.get(&lease_id) {
            Some(l) => l.job == job_id && l.unit == result.unit,
            // A lapsed lease answers only for the unit it was issued for. A lease of an
            // earlier run of the coordinator (before a restart) is unknown to this one; its
            // result is adopted: rendering is deterministic and the result is validated,
            // then merged once or compared like any other.
            None => {
                self.lapsed.get(&lease_id) == Some(&(job_id, i))
                    || (lease_id <= self.previous_run_max_lease && lease_id > 0)
            }
        };
        if !issued {
            return Err(SubmitError::UnknownLease(lease_id));
        }
        if quarantined {
            return Err(SubmitError::Quarantined(worker));
        }
        let frame = (result.unit.frame - job.first_frame) as usize;
        // A lease of the previous run may be for a frame nothing of which was merged
        // before the restart (pending again): adopted if it fits the budget.
        job.make_live(frame, &mut self.memory);
        // The pixels the unit's lease named (issue 15), to make every copy canonical.
        let wanted = job
            .adaptive
            .as_ref()
            .and_then(|a| a.frames.get(frame)?.as_ref()?.tile(result.unit.tile))
            .and_then(|t| t.wanted_pixels(result.unit.first_pass, result.unit.pass_count));
        let acc = match &mut job.frames[frame] {
            FrameSlot::Live(acc) => acc,
            // Complete and checkpointed: the unit is merged; its copy cannot be compared
            // without reading the checkpoint back.
            FrameSlot::Released => {
                self.leases.remove(&lease_id);
                self.lapsed.remove(&lease_id);
                if job.leased.get(&i) == Some(&lease_id) {
                    job.leased.remove(&i);
                }
                return Ok(Submitted::Late);
            }
            // It does not fit: the unit is leased again once it does.
            FrameSlot::Pending => return Err(SubmitError::NotResident(result.unit.frame)),
        };
        let result = canonical_masked(result, wanted.as_ref(), &job.plan)?;
        if !job.done.contains(&i) && is_spot_checked(spot_fraction, job_id, &result.unit) {
            result.validate(acc.plan()).map_err(MergeError::from)?;
            return self.hold_copy(worker, lease_id, job_id, i, result);
        }
        let digest = result.digest();
        let copy = job.adaptive.as_ref().map(|_| result.clone());
        let outcome = acc.offer(result)?;
        if let (Some(a), Some(copy)) = (job.adaptive.as_mut(), copy) {
            if !matches!(outcome, Offer::Duplicate { .. }) {
                if let Some(Some(f)) = a.frames.get_mut(frame) {
                    // Validated by the offer above; cannot fail.
                    let _ = f.offer(&copy);
                }
            }
        }
        // The unit is done: drop its lease (if the live lease is another worker's, that
        // worker's copy will be compared when it arrives).
        self.leases.remove(&lease_id);
        self.lapsed.remove(&lease_id);
        if job.leased.get(&i) == Some(&lease_id) {
            job.leased.remove(&i);
        }
        job.returned.remove(&i);
        job.done.insert(i);
        Ok(match outcome {
            Offer::Duplicate { identical } => Submitted::Duplicate { identical },
            Offer::Merged { .. } | Offer::Buffered => {
                job.unverified.insert(i, (worker, digest));
                if let Some(e) = job.reverified(job_id, i, digest) {
                    self.spot_events.push(e);
                }
                Submitted::Accepted
            }
        })
    }

    /// A validated copy of spot-checked unit `i` (not merged yet) from `worker`: held
    /// with the others; once two agree ([`SpotCheck::agreed`]) the workers whose copy
    /// differs are quarantined and the agreed copy is merged.
    fn hold_copy(
        &mut self,
        worker: WorkerId,
        lease_id: u64,
        job_id: JobId,
        i: u64,
        result: UnitResult,
    ) -> Result<Submitted, SubmitError> {
        let unit = result.unit;
        let digest = result.digest();
        self.leases.remove(&lease_id);
        self.lapsed.remove(&lease_id);
        let job = self
            .jobs
            .get_mut(&job_id)
            .ok_or(SubmitError::UnknownLease(lease_id))?;
        if job.leased.get(&i) == Some(&lease_id) {
            job.leased.remove(&i);
        }
        let check = job.checks.entry(i).or_default();
        if check.groups.iter().any(|g| g.leases.contains(&lease_id)) {
            return Ok(Submitted::Held);
        }
        job.extra_copies += 1;
        let fresh = match check.groups.iter_mut().find(|g| g.digest == digest) {
            Some(g) => {
                g.workers.push(worker);
                g.leases.push(lease_id);
                false
            }
            None => {
                check.groups.push(CopyGroup {
                    digest,
                    workers: vec![worker],
                    leases: vec![lease_id],
                    result,
                });
                true
            }
        };
        let Some(k) = check.agreed() else {
            if fresh && check.groups.len() > 1 {
                let mut workers: Vec<WorkerId> = check
                    .groups
                    .iter()
                    .flat_map(|g| g.workers.iter().copied())
                    .collect();
                workers.dedup();
                self.spot_events.push(SpotEvent::Disputed {
                    job: job_id,
                    unit,
                    workers,
                });
            }
            // Wanted again, from a worker with no copy (unless a lease is out already).
            if !job.leased.contains_key(&i) {
                job.returned.insert(i);
            }
            return Ok(Submitted::Held);
        };
        let Some(mut check) = job.checks.remove(&i) else {
            return Ok(Submitted::Held);
        };
        let agreed = check.groups.swap_remove(k);
        // Every worker with a copy unlike the agreed one (even if it also rendered the
        // agreed one: a worker whose copies differ is faulty).
        let dissenters: BTreeSet<WorkerId> = check
            .groups
            .iter()
            .flat_map(|g| g.workers.iter().copied())
            .collect();
        let distinct = agreed.workers.iter().any(|w| *w != agreed.workers[0]);
        let outcome = if !dissenters.is_empty() {
            SpotOutcome::Mismatch
        } else if distinct {
            SpotOutcome::Match
        } else {
            SpotOutcome::Alone
        };
        for &w in &dissenters {
            let reason = format!(
                "spot check: its copy of job {job_id} frame {} tile {} passes {}..{} differs \
                 from the copy {} other worker(s) agree on",
                unit.frame,
                unit.tile,
                unit.first_pass,
                unit.end_pass(),
                agreed.workers.len()
            );
            self.quarantine(w, &reason);
        }
        // Quarantine may have dropped this unit's tile; the frame is still live.
        let job = self
            .jobs
            .get_mut(&job_id)
            .ok_or(SubmitError::UnknownLease(lease_id))?;
        let frame = job.frame_index(i);
        let Some(FrameSlot::Live(acc)) = job.frames.get_mut(frame) else {
            return Err(SubmitError::NotResident(unit.frame));
        };
        let copy = job.adaptive.as_ref().map(|_| agreed.result.clone());
        let offered = acc.offer(agreed.result)?;
        if let (Some(a), Some(copy)) = (job.adaptive.as_mut(), copy) {
            if !matches!(offered, Offer::Duplicate { .. }) {
                if let Some(Some(f)) = a.frames.get_mut(frame) {
                    // Validated by the offer above; cannot fail.
                    let _ = f.offer(&copy);
                }
            }
        }
        job.returned.remove(&i);
        job.done.insert(i);
        // The unit counts in `done` now; its other copies stay extra work.
        job.extra_copies = job.extra_copies.saturating_sub(1);
        if outcome == SpotOutcome::Alone {
            // Not verified by anyone else: repaired if its worker is found faulty later.
            job.unverified.insert(i, (agreed.workers[0], digest));
        }
        let reverified = job.reverified(job_id, i, agreed.digest);
        self.spot_events.push(SpotEvent::Checked {
            job: job_id,
            unit,
            outcome,
        });
        self.spot_events.extend(reverified);
        Ok(match offered {
            Offer::Duplicate { identical } => Submitted::Duplicate { identical },
            Offer::Merged { .. } | Offer::Buffered => Submitted::Accepted,
        })
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

    /// Sets the memory budget for per-pixel merge state of all jobs, in bytes (unbounded
    /// by default). Frames that do not fit wait for completed frames to be released; one
    /// frame is always allowed when nothing is resident, so no job waits forever.
    pub fn set_memory_budget(&mut self, bytes: u64) {
        self.memory.budget = bytes;
    }

    /// Bytes of per-pixel merge state in memory, over all jobs.
    pub fn resident_bytes(&self) -> u64 {
        self.memory.resident
    }

    /// Drops a complete frame's merge state from memory, once the caller has made its
    /// checkpoints durable; later results for it are [`Submitted::Late`] and its image
    /// comes from the store. A frame of an adaptive job is complete when its policy has
    /// finished every tile (issue 15): the policy state is checkpointed with each tile, so
    /// the frame's image is restored from the store like any other, and the frames of an
    /// animation no longer hold memory until the whole job ends (with a budget of one
    /// frame, the next frame waited for that forever). Returns whether the frame was
    /// released now.
    pub fn release_frame(&mut self, job_id: JobId, frame: u32) -> bool {
        let Some(job) = self.jobs.get_mut(&job_id) else {
            return false;
        };
        let Some(k) = frame.checked_sub(job.first_frame).map(|k| k as usize) else {
            return false;
        };
        let Some(acc) = job.frames.get(k).and_then(FrameSlot::live) else {
            return false;
        };
        let complete = match &job.adaptive {
            Some(a) => a
                .frames
                .get(k)
                .and_then(Option::as_ref)
                .is_some_and(AdaptiveFrame::finished),
            None => acc.complete(),
        };
        if !complete {
            return false;
        }
        job.frames[k] = FrameSlot::Released;
        if let Some(a) = job.adaptive.as_mut() {
            a.frames[k] = None;
        }
        self.memory.resident = self.memory.resident.saturating_sub(job.frame_bytes);
        true
    }

    /// Where one frame's merge state is; `None` for an unknown job or frame.
    pub fn residency(&self, job_id: JobId, frame: u32) -> Option<Residency> {
        let job = self.jobs.get(&job_id)?;
        Some(
            match job
                .frames
                .get(frame.checked_sub(job.first_frame)? as usize)?
            {
                FrameSlot::Pending => Residency::Pending,
                FrameSlot::Live(_) => Residency::Live,
                FrameSlot::Released => Residency::Released,
            },
        )
    }

    /// The merged state of one frame of a job, while it is live (see [`Residency`]).
    pub fn frame(&self, job_id: JobId, frame: u32) -> Option<&FrameAccumulator> {
        let job = self.jobs.get(&job_id)?;
        job.frames
            .get(frame.checked_sub(job.first_frame)? as usize)?
            .live()
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

    /// The job's outstanding leases: who holds each and since when
    /// ([`Lease::leased_ms`]), in unit order. Empty for an unknown job.
    pub fn in_flight(&self, job_id: JobId) -> Vec<(WorkerId, u64)> {
        self.jobs.get(&job_id).map_or_else(Vec::new, |job| {
            job.leased
                .values()
                .filter_map(|id| self.leases.get(id))
                .map(|l| (l.worker, l.leased_ms))
                .collect()
        })
    }

    /// True once every frame of the job is complete.
    pub fn is_complete(&self, job_id: JobId) -> bool {
        self.jobs.get(&job_id).is_some_and(Job::is_complete)
    }

    /// Whether `lease_id` lapsed (or was given back) while its job goes on: its unit was
    /// returned to the queue, but a result for it is still wanted, merged if the unit is
    /// not merged yet and compared with the merged copy otherwise ([`Scheduler::submit`]).
    /// False for leases of canceled jobs, which nobody wants a result for.
    pub fn is_lapsed_and_wanted(&self, lease_id: u64) -> bool {
        self.lapsed
            .get(&lease_id)
            .is_some_and(|(job, _)| self.jobs.get(job).is_some_and(|j| !j.canceled))
    }

    /// Whether `lease_id` was issued by an earlier run of the coordinator (at or below the
    /// high-water mark this scheduler was created with).
    pub fn is_previous_run_lease(&self, lease_id: u64) -> bool {
        lease_id > 0 && lease_id <= self.previous_run_max_lease
    }

    /// The largest lease id issued so far (to persist as the high-water mark).
    pub fn max_issued_lease_id(&self) -> u64 {
        self.next_lease_id - 1
    }

    /// The ids of the jobs the scheduler holds.
    pub fn job_ids(&self) -> impl Iterator<Item = JobId> + '_ {
        self.jobs.keys().copied()
    }

    /// The job a lease was issued for, whether it is outstanding or has lapsed.
    pub fn lease_job(&self, lease_id: u64) -> Option<JobId> {
        self.leases
            .get(&lease_id)
            .map(|l| l.job)
            .or_else(|| self.lapsed.get(&lease_id).map(|(j, _)| *j))
    }

    /// All outstanding leases.
    pub fn leases(&self) -> impl Iterator<Item = &Lease> {
        self.leases.values()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One step of Knuth's MMIX linear congruential generator: the fixed pseudo-random
    /// delivery order of the scheduler's property tests.
    fn lcg_step(rng: &mut u64) {
        *rng = rng
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
    }
    use crate::merge::TileAccumulator;
    use crate::stats::PixelStats;
    use crate::FrameImage;

    fn result(plan: &FramePlan, unit: WorkUnit, value: f32) -> UnitResult {
        let rect = plan.tile(unit.tile);
        let n = rect.pixel_count() * unit.pass_count as usize;
        let pass_means = (0..n).map(|k| [value + (k % 7) as f32 * 0.01; 3]).collect();
        UnitResult {
            unit,
            width: rect.width,
            height: rect.height,
            pass_means,
            rejected_samples: 0,
        }
    }

    fn plan() -> FramePlan {
        FramePlan::new(40, 30, 16, 4, 6).unwrap() // 6 tiles, 6 passes
    }

    #[test]
    fn priority_then_fifo_then_coarse_to_fine() {
        let p = plan();
        let mut s = Scheduler::new(1000, 0);
        s.add_job(1, 0, p, 0..=0, 2);
        s.add_job(2, 5, p, 0..=0, 2);
        s.add_job(3, 0, p, 0..=0, 2);
        let leases = s.lease(9, 0, 100);
        assert_eq!(leases.len(), 3 * 18);
        let jobs: Vec<JobId> = leases.iter().map(|l| l.job).collect();
        assert!(jobs[..18].iter().all(|&j| j == 2));
        assert!(jobs[18..36].iter().all(|&j| j == 1));
        assert!(jobs[36..].iter().all(|&j| j == 3));
        // Coarse to fine: every tile's first chunk before any second chunk.
        let firsts: Vec<u32> = leases[..18].iter().map(|l| l.unit.first_pass).collect();
        assert_eq!(firsts, [[0; 6], [2; 6], [4; 6]].concat());
        // Fencing tokens are unique and increasing.
        assert!(leases.windows(2).all(|w| w[0].lease_id < w[1].lease_id));
    }

    #[test]
    fn expired_leases_are_released_in_canonical_order_and_merged_once() {
        let p = plan();
        let mut s = Scheduler::new(100, 0);
        s.add_job(1, 0, p, 0..=1, 3);
        let a = s.lease(1, 0, 3);
        // Heartbeat keeps lease a[0] alive; the others lapse.
        assert_eq!(s.extend(1, &[a[0].lease_id], 50).len(), 1);
        assert!(
            s.extend(2, &[a[1].lease_id], 50).is_empty(),
            "not the holder"
        );
        let expired = s.expire(120);
        assert_eq!(expired.len(), 2);
        // The next lease hands out the expired units first, in canonical order.
        let b = s.lease(2, 130, 2);
        assert_eq!(
            b.iter().map(|l| l.unit).collect::<Vec<_>>(),
            vec![a[1].unit, a[2].unit]
        );
        // Both the late worker and the new holder submit: merged once, compared once.
        assert_eq!(
            s.submit(a[1].lease_id, 1, result(&p, a[1].unit, 0.5)),
            Ok(Submitted::Accepted)
        );
        assert_eq!(
            s.submit(b[0].lease_id, 1, result(&p, b[0].unit, 0.5)),
            Ok(Submitted::Duplicate { identical: true })
        );
        // A copy that differs is flagged.
        assert_eq!(
            s.submit(b[1].lease_id, 1, result(&p, b[1].unit, 0.5)),
            Ok(Submitted::Accepted)
        );
        assert_eq!(
            s.submit(a[2].lease_id, 1, result(&p, a[2].unit, 0.25)),
            Ok(Submitted::Duplicate { identical: false })
        );
    }

    /// `expire` looks at the lease table only once the earliest deadline may have passed
    /// (`next_expiry_ms`); every lease must still lapse at its own deadline, whatever was
    /// leased, extended or expired before it.
    #[test]
    fn every_lease_lapses_at_its_deadline_after_extensions_and_earlier_expiries() {
        let p = plan();
        let mut s = Scheduler::new(100, 0);
        s.add_job(1, 0, p, 0..=1, 3);
        let a = s.lease(1, 0, 2); // deadlines 100
        assert!(s.expire(100).is_empty(), "a deadline is inclusive");
        // a[0] is extended to 150: the bound (100) is stale-low, a scan finds a[1] only.
        assert_eq!(s.extend(1, &[a[0].lease_id], 50).len(), 1);
        let e = s.expire(101);
        assert_eq!(
            e.iter().map(|l| l.lease_id).collect::<Vec<_>>(),
            [a[1].lease_id]
        );
        assert!(s.expire(150).is_empty());
        assert_eq!(s.expire(151).len(), 1, "the extended lease lapses at 150");
        // With no lease left the bound is open; a new lease must lower it again.
        assert!(s.expire(10_000).is_empty());
        let b = s.lease(2, 10_000, 1);
        assert_eq!(b.len(), 1);
        assert!(s.expire(10_100).is_empty());
        let e = s.expire(10_101);
        assert_eq!(
            e.iter().map(|l| l.lease_id).collect::<Vec<_>>(),
            [b[0].lease_id]
        );
        // A lease taken while an earlier one is held, then the earlier one delivered:
        // the later deadline is still found.
        let c = s.lease(3, 20_000, 1);
        let d = s.lease(3, 20_050, 1);
        assert_eq!(
            s.submit(c[0].lease_id, 1, result(&p, c[0].unit, 0.5)),
            Ok(Submitted::Accepted)
        );
        assert!(
            s.expire(20_101).is_empty(),
            "c was delivered, d lapses at 20,150"
        );
        let e = s.expire(20_151);
        assert_eq!(
            e.iter().map(|l| l.lease_id).collect::<Vec<_>>(),
            [d[0].lease_id]
        );
    }

    #[test]
    fn a_lapsed_lease_is_wanted_until_its_result_arrives_or_its_job_is_canceled() {
        let p = plan();
        let mut s = Scheduler::new(100, 0);
        s.add_job(1, 0, p, 0..=0, 3);
        s.add_job(2, 0, p, 0..=0, 3);
        let a = s.lease(1, 0, 2);
        let b: Vec<Lease> = s
            .lease(1, 0, 100)
            .into_iter()
            .filter(|l| l.job == 2)
            .take(1)
            .collect();
        // Live leases are not lapsed.
        assert!(!s.is_lapsed_and_wanted(a[0].lease_id));
        s.expire(200);
        assert!(s.is_lapsed_and_wanted(a[0].lease_id));
        assert!(s.is_lapsed_and_wanted(b[0].lease_id));
        // Delivered: nothing more is wanted for it.
        assert_eq!(
            s.submit(a[0].lease_id, 1, result(&p, a[0].unit, 0.5)),
            Ok(Submitted::Accepted)
        );
        assert!(!s.is_lapsed_and_wanted(a[0].lease_id));
        assert!(s.is_lapsed_and_wanted(a[1].lease_id));
        // A canceled job wants no result; an id never issued is not lapsed.
        s.cancel(2);
        assert!(!s.is_lapsed_and_wanted(b[0].lease_id));
        assert!(!s.is_lapsed_and_wanted(999_999));
    }

    #[test]
    fn bad_submissions_are_refused_and_change_nothing() {
        let p = plan();
        let mut s = Scheduler::new(100, 0);
        s.add_job(1, 0, p, 0..=0, 6);
        let l = s.lease(1, 0, 2);
        // A lease id never issued.
        assert_eq!(
            s.submit(999, 1, result(&p, l[0].unit, 0.5)),
            Err(SubmitError::UnknownLease(999))
        );
        // A lease for another unit.
        assert!(s
            .submit(l[0].lease_id, 1, result(&p, l[1].unit, 0.5))
            .is_err());
        // Wrong size and NaN.
        let mut r = result(&p, l[0].unit, 0.5);
        r.width -= 1;
        assert!(matches!(
            s.submit(l[0].lease_id, 1, r),
            Err(SubmitError::Invalid(_))
        ));
        let mut r = result(&p, l[0].unit, 0.5);
        r.pass_means[3][1] = f32::NAN;
        assert!(matches!(
            s.submit(l[0].lease_id, 1, r),
            Err(SubmitError::Invalid(_))
        ));
        assert_eq!(s.progress(1).unwrap().units_done, 0);
        // The genuine result still goes in.
        assert_eq!(
            s.submit(l[0].lease_id, 1, result(&p, l[0].unit, 0.5)),
            Ok(Submitted::Accepted)
        );
        assert_eq!(s.progress(1).unwrap().units_done, 1);
    }

    /// Renders job 7 to completion, but "crashes" after `crash_after` submissions: the
    /// merged tiles are checkpointed (as the coordinator's store does), a new scheduler is
    /// built from them with the old high-water mark, and one late result of the earlier
    /// run is delivered to it.
    fn run_with_restart(crash_after: usize) -> (FrameImage, u64) {
        let p = plan();
        let mut s = Scheduler::new(100, 0);
        s.add_job(7, 0, p, 0..=0, 2);
        let mut submitted = 0;
        let mut late = None;
        while submitted < crash_after {
            let mut ls = s.lease(1, 0, 2);
            // Hold the last lease of the batch across the crash.
            if submitted + ls.len() > crash_after {
                late = ls.pop();
            }
            for l in ls {
                s.submit(l.lease_id, 7, result(&p, l.unit, 0.5 + l.unit.tile as f32))
                    .unwrap();
                submitted += 1;
            }
            if late.is_some() {
                break;
            }
        }
        // Checkpoint what is merged, as the store would hold it.
        let mut restored = FrameAccumulator::new(p);
        for t in s.frame(7, 0).map_or(&[][..], FrameAccumulator::tiles) {
            let units: Vec<_> = t.merged_units().collect();
            let tile =
                TileAccumulator::restore(t.rect(), t.merged_passes(), t.pixels().to_vec(), &units)
                    .unwrap();
            restored.restore_tile(tile).unwrap();
        }
        let high_water = s.max_issued_lease_id();
        let mut s2 = Scheduler::new(100, high_water);
        let resumed = Resumed {
            frames: 0..=0,
            restored: vec![restored],
            complete: Vec::new(),
        };
        s2.add_resumed_job(7, 0, p, resumed, 2).unwrap();
        let mut adopted = 0;
        if let Some(l) = late {
            assert!(s2.is_previous_run_lease(l.lease_id));
            s2.submit(l.lease_id, 7, result(&p, l.unit, 0.5 + l.unit.tile as f32))
                .unwrap();
            adopted += 1;
        }
        while !s2.is_complete(7) {
            let ls = s2.lease(2, 0, 3);
            assert!(!ls.is_empty(), "incomplete job with nothing to lease");
            for l in ls {
                assert!(
                    l.lease_id > high_water,
                    "fencing tokens repeat after a restart"
                );
                let _ = s2.submit(l.lease_id, 7, result(&p, l.unit, 0.5 + l.unit.tile as f32));
            }
        }
        (s2.frame(7, 0).unwrap().image(), adopted)
    }

    #[test]
    fn a_resumed_job_completes_bit_identically() {
        let (reference, _) = run_with_restart(0);
        for crash_after in [1, 5, 9, 17] {
            let (image, adopted) = run_with_restart(crash_after);
            assert_eq!(adopted, 1, "crash after {crash_after}");
            assert_eq!(image, reference, "crash after {crash_after}");
        }
        // A checkpoint that does not end on a unit boundary is refused.
        let p = plan();
        let mut f = FrameAccumulator::new(p);
        let rect = p.tile(0);
        let units = [(0, 1, 0)];
        let mut px = vec![PixelStats::default(); rect.pixel_count()];
        px.iter_mut().for_each(|s| s.push([1.0; 3]));
        f.restore_tile(TileAccumulator::restore(rect, 1, px, &units).unwrap())
            .unwrap();
        let mut s = Scheduler::new(100, 0);
        let resumed = Resumed {
            frames: 0..=0,
            restored: vec![f],
            complete: Vec::new(),
        };
        assert!(s.add_resumed_job(1, 0, p, resumed, 2).is_err());
        // Units that do not tile the merged passes are refused.
        let px = vec![PixelStats::default(); rect.pixel_count()];
        assert!(TileAccumulator::restore(rect, 4, px.clone(), &[(0, 2, 0)]).is_err());
        assert!(TileAccumulator::restore(rect, 2, px, &[(1, 1, 0)]).is_err());
    }

    #[test]
    fn a_job_completes_bit_identically_whatever_the_worker_interleaving() {
        let p = plan();
        let run = |workers: u64, seed: u64| {
            let mut s = Scheduler::new(100, 0);
            s.add_job(7, 0, p, 0..=0, 2);
            let mut now = 0;
            let mut rng = seed;
            let mut held: Vec<Lease> = Vec::new();
            while !s.is_complete(7) {
                now += 10;
                for w in 0..workers {
                    held.extend(s.lease(w, now, 1));
                }
                lcg_step(&mut rng);
                // Deliver a pseudo-random held lease; sometimes drop one (a dead worker).
                if held.is_empty() {
                    s.expire(now + 1000);
                    continue;
                }
                let k = (rng >> 33) as usize % held.len();
                let l = held.swap_remove(k);
                if rng.is_multiple_of(5) {
                    continue;
                }
                let _ = s.submit(l.lease_id, 7, result(&p, l.unit, 0.5 + l.unit.tile as f32));
                if rng.is_multiple_of(3) {
                    s.expire(now + 1000);
                }
            }
            s.frame(7, 0).unwrap().image()
        };
        let a = run(1, 1);
        for (w, seed) in [(3, 2), (5, 3)] {
            let b = run(w, seed);
            assert!(a
                .mean
                .iter()
                .zip(&b.mean)
                .all(|(x, y)| x.map(f32::to_bits) == y.map(f32::to_bits)));
            assert!(a
                .variance_of_mean
                .iter()
                .zip(&b.variance_of_mean)
                .all(|(x, y)| x.map(f32::to_bits) == y.map(f32::to_bits)));
        }
    }

    #[test]
    fn the_tail_share_halves_the_even_share_and_never_exceeds_the_request() {
        // Early: what was asked; then half the worker's share, at least one unit.
        assert_eq!(tail_share(10_000, 1, 2, 64), 64);
        assert_eq!(tail_share(100, 1, 2, 64), 25);
        assert_eq!(tail_share(7, 1, 2, 64), 2);
        assert_eq!(tail_share(1, 1, 2, 64), 1);
        // A worker's share grows with its threads (2 of 6 threads: a third, halved).
        assert_eq!(tail_share(60, 2, 6, 64), 10);
        // A worker alone gets what it asks for, also with inconsistent counts (a worker
        // not counted among the sharing ones).
        assert_eq!(tail_share(3, 2, 2, 64), 64);
        assert_eq!(tail_share(60, 4, 2, 64), 64);
        // No overflow at the extremes: half of everything.
        let half = (u64::MAX / 2) as usize;
        assert_eq!(
            tail_share(u64::MAX, u64::MAX - 1, u64::MAX, usize::MAX),
            half
        );
        // Non-increasing as the queue drains.
        let mut last = usize::MAX;
        for q in (0..500).rev() {
            let n = tail_share(q, 1, 3, 16);
            assert!(n <= last && (1..=16).contains(&n));
            last = n;
        }
    }

    #[test]
    fn leases_shrink_to_single_units_at_the_end_of_the_queue() {
        let p = plan(); // 6 tiles x 6 passes: 36 units
        let mut s = Scheduler::new(1000, 0);
        s.add_job(1, 0, p, 0..=0, 1);
        let mut sizes = Vec::new();
        let mut leased = BTreeSet::new();
        // Two one-thread workers take turns asking for 8 units each.
        for w in (0..2).cycle() {
            let got = s.lease_among(w, 0, 8, 1, 2);
            if got.is_empty() {
                break;
            }
            sizes.push(got.len());
            for l in got {
                assert!(
                    leased.insert((l.unit.tile, l.unit.first_pass)),
                    "leased twice"
                );
            }
        }
        assert_eq!(leased.len(), 36);
        // 36 waiting: ceil(36 / 4) = 9, capped to the 8 asked for; then 28 -> 7, ...
        assert_eq!(sizes, [8, 7, 6, 4, 3, 2, 2, 1, 1, 1, 1]);
        // Units returned to the queue count as waiting; merged ones do not.
        let mut s = Scheduler::new(100, 0);
        s.add_job(1, 0, p, 0..=0, 1);
        let all = s.lease(5, 0, 100);
        for l in &all[..20] {
            s.submit(l.lease_id, 1, result(&p, l.unit, 0.5)).unwrap();
        }
        s.expire(1000);
        // 16 returned, shared by 2 one-thread workers: 4 each.
        assert_eq!(s.lease_among(5, 1000, 64, 1, 2).len(), 4);
    }

    /// An adaptive job's units waiting for a decision are not queued work: with one
    /// whole-frame tile (bdpt) the first worker to ask used to get every unit before the
    /// next decision, and the other waited (the tail rule counted the whole plan).
    #[test]
    fn adaptive_windows_are_shared_between_workers() {
        use crate::adaptive::{AdaptiveMode, AdaptiveSettings};
        // One 16-pixel tile covering the frame: the plan of a bdpt job.
        let p = FramePlan::new(16, 16, 16, 4, 64).unwrap();
        assert_eq!(p.tile_count(), 1);
        let settings = AdaptiveSettings {
            mode: AdaptiveMode::Sequential,
            target_error: 0.05,
            ..AdaptiveSettings::default()
        };
        let mut s = Scheduler::new(100, 0);
        s.add_adaptive_job(3, 0, p, 0..=0, 1, settings).unwrap();
        // Before the first decision (min_passes 8): 8 units of one pass open. Two
        // one-thread workers asking for 8 each get 2 each (half their share of 8).
        let a = s.lease_among(0, 0, 8, 1, 2);
        let b = s.lease_among(1, 0, 8, 1, 2);
        assert_eq!(
            (a.len(), b.len()),
            (2, 2),
            "the first worker took the window"
        );
        // The window is all there is: the rest of it is shared out, then nothing is left.
        let mut leased: Vec<_> = a.into_iter().chain(b).collect();
        for w in (0..2).cycle().take(8) {
            leased.extend(s.lease_among(w, 0, 8, 1, 2));
        }
        assert_eq!(leased.len(), 8);
        assert!(leased.iter().all(|l| l.unit.first_pass < 8));
    }

    #[test]
    fn batches_cut_by_the_tail_rule_give_the_same_image() {
        let p = plan();
        let run = |batch: usize, workers: u64| {
            let mut s = Scheduler::new(100, 0);
            s.add_job(7, 0, p, 0..=0, 1);
            let mut held: Vec<Lease> = Vec::new();
            let mut round = 0u64;
            while !s.is_complete(7) {
                round += 1;
                for w in 0..workers {
                    held.extend(s.lease_among(w, round, batch, 1, workers));
                }
                // The newest leases are delivered first: an order unlike the canonical one.
                while let Some(l) = held.pop() {
                    let r = result(&p, l.unit, 0.5 + l.unit.tile as f32);
                    s.submit(l.lease_id, 7, r).unwrap();
                }
            }
            s.frame(7, 0).unwrap().image()
        };
        let a = run(1, 1);
        for (batch, workers) in [(4, 2), (16, 3), (64, 2)] {
            let b = run(batch, workers);
            let bits = |img: &FrameImage| {
                img.mean
                    .iter()
                    .chain(&img.variance_of_mean)
                    .flat_map(|p| p.map(f32::to_bits))
                    .collect::<Vec<u32>>()
            };
            assert_eq!(bits(&a), bits(&b), "batch {batch}, {workers} workers");
        }
    }

    /// What a coordinator's store holds of an adaptive job at a crash: per live frame, the
    /// tiles' merged state (as restored from their checkpoints) and the policy state saved
    /// with it; a tile with nothing merged has no checkpoint.
    fn adaptive_snapshot(
        s: &Scheduler,
        job: JobId,
        plan: FramePlan,
        frames: std::ops::RangeInclusive<u32>,
    ) -> Vec<(FrameAccumulator, Vec<Option<crate::AdaptiveTileCheckpoint>>)> {
        let mut out = Vec::new();
        for f in frames {
            let Some(acc) = s.frame(job, f) else {
                continue;
            };
            let policy = s.adaptive_frame(job, f).unwrap();
            let mut restored = FrameAccumulator::for_frame(plan, f);
            let mut cps = Vec::new();
            for (t, a) in acc.tiles().iter().zip(policy.tiles()) {
                let units: Vec<_> = t.merged_units().collect();
                let tile = TileAccumulator::restore(
                    t.rect(),
                    t.merged_passes(),
                    t.pixels().to_vec(),
                    &units,
                )
                .unwrap();
                restored.restore_tile(tile).unwrap();
                cps.push((t.merged_passes() > 0).then(|| a.checkpoint()));
            }
            out.push((restored, cps));
        }
        out
    }

    /// Issue 15: an adaptive job survives a coordinator crash at any point. The store's
    /// view at the crash (merged passes and the policy state checkpointed with them;
    /// buffered results and outstanding leases are lost) is resumed by a new scheduler,
    /// which redoes only the lost units and ends with the image of an uninterrupted run
    /// bit for bit, for both modes and crashes early, mid-decision and late, in a
    /// two-frame job with one frame possibly not started.
    /// The adaptive settings of the resume tests.
    fn resume_settings(mode: crate::adaptive::AdaptiveMode) -> crate::adaptive::AdaptiveSettings {
        crate::adaptive::AdaptiveSettings {
            mode,
            target_error: 0.05,
            min_passes: 8,
            interval: 4,
            ..crate::adaptive::AdaptiveSettings::default()
        }
    }

    /// Each frame of `frames` rendered by one uninterrupted adaptive frame, units of 2
    /// passes: what a resumed job must end with.
    fn local_adaptive_images(
        p: &FramePlan,
        frames: std::ops::RangeInclusive<u32>,
        settings: crate::adaptive::AdaptiveSettings,
    ) -> Vec<FrameImage> {
        frames
            .map(|f| {
                let mut local = AdaptiveFrame::new(*p, f, settings).unwrap();
                for u in p.units(f, 2) {
                    local.offer(&noisy_result(p, u)).unwrap();
                }
                local.image()
            })
            .collect()
    }

    #[test]
    fn adaptive_jobs_resume_from_checkpoints_bit_identically() {
        use crate::adaptive::AdaptiveMode;
        let p = FramePlan::new(24, 16, 8, 1, 48).unwrap(); // 6 tiles
        let frames = 3..=4u32;
        for mode in [AdaptiveMode::Sequential, AdaptiveMode::Unbiased] {
            let settings = resume_settings(mode);
            let references = local_adaptive_images(&p, frames.clone(), settings);
            for (crash_at, seed) in [(5usize, 11u64), (40, 12), (90, 13), (150, 14)] {
                let mut s = Scheduler::new(100, 0);
                s.add_adaptive_job(7, 0, p, frames.clone(), 2, settings)
                    .unwrap();
                let (mut now, mut rng, mut submitted) = (0u64, seed, 0usize);
                let mut held: Vec<Lease> = Vec::new();
                let mut crashed = false;
                let mut merged_before = 0u64;
                while !s.is_complete(7) {
                    now += 10;
                    assert!(now < 1_000_000, "{mode}: the job stalls");
                    if submitted == crash_at && !crashed {
                        crashed = true;
                        merged_before = s.progress(7).unwrap().passes_done;
                        let snapshot = adaptive_snapshot(&s, 7, p, frames.clone());
                        s = Scheduler::new(100, 1_000);
                        s.add_resumed_adaptive_job(
                            7,
                            0,
                            p,
                            2,
                            ResumedAdaptive {
                                frames: frames.clone(),
                                settings,
                                restored: snapshot,
                                complete: Vec::new(),
                            },
                        )
                        .unwrap();
                        held.clear();
                        // Merged passes are restored, not rendered again.
                        assert_eq!(s.progress(7).unwrap().passes_done, merged_before);
                    }
                    for w in 0..3 {
                        held.extend(s.lease(w, now, 2));
                    }
                    if deliver_random(&mut s, 7, &p, &mut held, &mut rng, now, (7, 4)) {
                        submitted += 1;
                    }
                }
                assert!(
                    crashed,
                    "{mode}: the job ended before the crash at {crash_at}"
                );
                assert!(
                    crash_at < 10 || merged_before > 0,
                    "{mode}: nothing merged before the crash at {crash_at}"
                );
                for (f, reference) in frames.clone().zip(&references) {
                    let image = s.adaptive_frame(7, f).unwrap().image();
                    assert_eq!(
                        &image, reference,
                        "{mode}, crash after {crash_at} results: frame {f}"
                    );
                }
            }
        }
    }

    /// Issue 15: a restart releases the frames its restored policy had finished. The
    /// store keeps a released frame's checkpoints, so a restart finds every frame the job
    /// finished; restored live, they held the memory budget until the job ended (under a
    /// budget of one frame the frame in progress came back beyond it, and an adaptive job
    /// had to fit the budget with all its frames). Here frame 0 comes back released,
    /// frame 1 live, and the job ends with the images of an uninterrupted run, one frame
    /// in memory at a time, never leasing frame 0 again.
    #[test]
    fn a_resumed_adaptive_job_releases_its_finished_frames() {
        use crate::adaptive::AdaptiveMode;
        let p = FramePlan::new(24, 16, 8, 1, 48).unwrap(); // 6 tiles
        let frames = 0..=2u32;
        let budget = frame_state_bytes(&p, true);
        for mode in [AdaptiveMode::Sequential, AdaptiveMode::Unbiased] {
            let settings = resume_settings(mode);
            let references = local_adaptive_images(&p, frames.clone(), settings);
            // One unit at a time until frame 0 is released and frame 1 has merged passes.
            let mut s = Scheduler::new(100, 0);
            s.set_memory_budget(budget);
            s.add_adaptive_job(7, 0, p, frames.clone(), 2, settings)
                .unwrap();
            while s.residency(7, 0) != Some(Residency::Released)
                || s.frame(7, 1).is_none_or(|f| f.merged_pass_count() == 0)
            {
                let l = s.lease(1, 0, 1).pop().expect("the job has work");
                s.submit(l.lease_id, 7, noisy_result(&p, l.unit)).unwrap();
                if s.adaptive_frame(7, 0).is_some_and(AdaptiveFrame::finished) {
                    assert!(s.release_frame(7, 0));
                }
            }
            let restored = adaptive_snapshot(&s, 7, p, frames.clone());
            assert_eq!(restored.len(), 1, "{mode}: frame 1 only");
            let resumed = |complete: Vec<u32>| ResumedAdaptive {
                frames: frames.clone(),
                settings,
                restored: restored.clone(),
                complete,
            };
            let err = Scheduler::new(100, 0)
                .add_resumed_adaptive_job(7, 0, p, 2, resumed(vec![0, 1]))
                .unwrap_err();
            assert!(
                err.contains("frame 1 is both finished and in progress"),
                "{err}"
            );
            let err = Scheduler::new(100, 0)
                .add_resumed_adaptive_job(7, 0, p, 2, resumed(vec![3]))
                .unwrap_err();
            assert!(err.contains("frame 3 is outside the job"), "{err}");

            let mut s = Scheduler::new(100, 0);
            s.set_memory_budget(budget);
            s.add_resumed_adaptive_job(7, 0, p, 2, resumed(vec![0]))
                .unwrap();
            assert_eq!(s.residency(7, 0), Some(Residency::Released), "{mode}");
            assert!(s.adaptive_frame(7, 0).is_none(), "{mode}");
            assert_eq!(s.resident_bytes(), budget, "{mode}: frame 1 alone");
            let mut order = Vec::new();
            for _ in 0..10_000 {
                let Some(l) = s.lease(1, 0, 1).pop() else {
                    break;
                };
                let f = l.unit.frame;
                if order.last() != Some(&f) {
                    order.push(f);
                }
                s.submit(l.lease_id, 7, noisy_result(&p, l.unit)).unwrap();
                assert!(s.resident_bytes() <= budget, "{mode}: one frame at a time");
                if let Some(a) = s.adaptive_frame(7, f).filter(|a| a.finished()) {
                    assert_eq!(a.image(), references[f as usize], "{mode}: frame {f}");
                    assert!(s.release_frame(7, f));
                }
            }
            assert_eq!(order, [1, 2], "{mode}");
            assert!(s.is_complete(7), "{mode}");
            assert_eq!(s.progress(7).unwrap().frames_done, 3, "{mode}");
        }
    }

    /// A restored policy state that its tile's merged passes contradict is refused.
    #[test]
    fn a_policy_state_out_of_step_with_its_tile_is_refused() {
        use crate::adaptive::{AdaptiveMode, AdaptiveSettings};
        let p = FramePlan::new(16, 8, 8, 1, 48).unwrap(); // 2 tiles
        let settings = AdaptiveSettings {
            mode: AdaptiveMode::Sequential,
            target_error: 0.05,
            ..AdaptiveSettings::default()
        };
        let mut s = Scheduler::new(100, 0);
        s.add_adaptive_job(7, 0, p, 0..=0, 2, settings).unwrap();
        // Tile 1 (noisy) takes its first 4 passes.
        for _ in 0..8 {
            for l in s.lease(0, 0, 4) {
                let _ = s.submit(l.lease_id, 7, noisy_result(&p, l.unit));
            }
        }
        let good = adaptive_snapshot(&s, 7, p, 0..=0);
        assert!(Scheduler::new(100, 0)
            .add_resumed_adaptive_job(
                7,
                0,
                p,
                2,
                ResumedAdaptive {
                    frames: 0..=0,
                    settings,
                    restored: good.clone(),
                    complete: Vec::new(),
                }
            )
            .is_ok());
        // The policy state of an older checkpoint beside newer merged passes.
        let mut stale = good;
        let mut fresh = AdaptiveFrame::new(p, 0, settings).unwrap();
        for u in p
            .units(0, 2)
            .into_iter()
            .filter(|u| u.tile == 1 && u.first_pass < 2)
        {
            fresh.offer(&noisy_result(&p, u)).unwrap();
        }
        stale[0].1[1] = Some(fresh.tile(1).unwrap().checkpoint());
        let err = Scheduler::new(100, 0)
            .add_resumed_adaptive_job(
                7,
                0,
                p,
                2,
                ResumedAdaptive {
                    frames: 0..=0,
                    settings,
                    restored: stale,
                    complete: Vec::new(),
                },
            )
            .unwrap_err();
        assert!(err.contains("frame 0 tile 1"), "{err}");
    }

    /// A reproducible noisy pass mean: tile 0 is constant (converges at once), the others
    /// noisy with occasional fireflies (some pixels converge, some never do).
    fn noisy_result(plan: &FramePlan, unit: WorkUnit) -> UnitResult {
        let rect = plan.tile(unit.tile);
        let mut pass_means = Vec::new();
        for pass in unit.first_pass..unit.first_pass + unit.pass_count {
            for i in 0..rect.pixel_count() {
                let mut rng = crate::test_util::Rng::new(
                    (u64::from(unit.tile) << 40) ^ (u64::from(pass) << 20) ^ i as u64,
                );
                let v = if unit.tile == 0 {
                    0.5
                } else {
                    let firefly = if rng.uniform() < 0.02 * (i % 4) as f64 {
                        40.0
                    } else {
                        0.0
                    };
                    0.3 + 0.5 * rng.uniform() + firefly
                };
                pass_means.push([v as f32; 3]);
            }
        }
        UnitResult {
            unit,
            width: rect.width,
            height: rect.height,
            pass_means,
            rejected_samples: 0,
        }
    }

    /// One delivery of a randomly interleaved farm: a lease of `held` chosen by `rng`
    /// delivers its [`noisy_result`], except one in `odds.0` whose result is lost (its
    /// unit is leased again after expiry); after one delivery in `odds.1`, and whenever
    /// nothing is held, the outstanding leases lapse. Returns whether a result was
    /// submitted.
    fn deliver_random(
        s: &mut Scheduler,
        job: JobId,
        plan: &FramePlan,
        held: &mut Vec<Lease>,
        rng: &mut u64,
        now: u64,
        odds: (u64, u64),
    ) -> bool {
        lcg_step(rng);
        if held.is_empty() {
            s.expire(now + 1000);
            return false;
        }
        let k = (*rng >> 33) as usize % held.len();
        let l = held.swap_remove(k);
        if rng.is_multiple_of(odds.0) {
            return false;
        }
        let _ = s.submit(l.lease_id, job, noisy_result(plan, l.unit));
        if rng.is_multiple_of(odds.1) {
            s.expire(now + 1000);
        }
        true
    }

    /// Issue 4: adaptive farm jobs. Whatever the number of workers and the interleaving
    /// (with lost leases re-leased after expiry), no unit is leased beyond an open decision,
    /// finished tiles stop being leased, and the image equals the local adaptive render of
    /// the same passes bit for bit.
    #[test]
    fn adaptive_jobs_stop_tiles_and_stay_bit_identical() {
        use crate::adaptive::{AdaptiveMode, AdaptiveSettings};
        let p = FramePlan::new(24, 16, 8, 1, 48).unwrap(); // 6 tiles
        for mode in [AdaptiveMode::Sequential, AdaptiveMode::Unbiased] {
            let settings = AdaptiveSettings {
                mode,
                target_error: 0.05,
                min_passes: 7, // rounded up to 8 (units of 2 passes)
                interval: 3,   // rounded up to 4
                ..AdaptiveSettings::default()
            };
            // The local render of the same job: the policy fed every planned pass.
            let used_local = {
                let mut s = settings;
                s.min_passes = 8;
                s.interval = 4;
                s
            };
            let mut local = AdaptiveFrame::new(p, 0, used_local).unwrap();
            for u in p.units(0, 2) {
                local.offer(&noisy_result(&p, u)).unwrap();
            }
            let reference = local.image();
            for (workers, seed) in [(1u64, 1u64), (3, 2), (5, 3)] {
                let mut s = Scheduler::new(100, 0);
                let used = s.add_adaptive_job(7, 0, p, 0..=0, 2, settings).unwrap();
                assert_eq!((used.min_passes, used.interval), (8, 4));
                let (mut now, mut rng) = (0u64, seed);
                let mut held: Vec<Lease> = Vec::new();
                let mut leased_units = BTreeSet::new();
                while !s.is_complete(7) {
                    now += 10;
                    assert!(now < 1_000_000, "{mode}: the job stalls");
                    for w in 0..workers {
                        let new = s.lease(w, now, 1);
                        let f = s.adaptive_frame(7, 0).unwrap();
                        for l in &new {
                            let t = f.tile(l.unit.tile).unwrap();
                            assert!(
                                l.unit.first_pass < t.lease_horizon(),
                                "{mode}: unit {:?} leased beyond the open decision at {}",
                                l.unit,
                                t.lease_horizon()
                            );
                        }
                        leased_units.extend(new.iter().map(|l| l.unit));
                        held.extend(new);
                    }
                    deliver_random(&mut s, 7, &p, &mut held, &mut rng, now, (5, 3));
                }
                let image = s.adaptive_frame(7, 0).unwrap().image();
                assert_eq!(image, reference, "{mode} with {workers} workers");
                // Tile 0 (constant) stopped at the first decision (sequential: 4 of its 24
                // units) or after the pilot and the minimum 4 fresh passes (unbiased: 6).
                let f = s.adaptive_frame(7, 0).unwrap();
                assert!(f.tile(0).unwrap().finished());
                let end0 = if mode == AdaptiveMode::Sequential {
                    8
                } else {
                    12
                };
                assert!(leased_units
                    .iter()
                    .all(|u| u.tile != 0 || u.first_pass < end0));
                let total = p.unit_count(2) as usize;
                assert!(
                    leased_units.len() < total,
                    "{mode}: adaptivity saved nothing"
                );
                assert!(
                    s.lease(1, now, 10).is_empty(),
                    "{mode}: work after completion"
                );
            }
        }
        // Settings that do not fit the plan are refused.
        let mut s = Scheduler::new(100, 0);
        let bad = AdaptiveSettings {
            mode: AdaptiveMode::Unbiased,
            target_error: 0.05,
            min_passes: 48,
            ..AdaptiveSettings::default()
        };
        assert!(s.add_adaptive_job(1, 0, p, 0..=0, 2, bad).is_err());
        assert!(s.lease(1, 0, 1).is_empty());
    }

    /// Issue 15: leases of adaptive jobs name the pixels still wanted. Workers that trace
    /// only those (the rest black) give the local image bit for bit; the set of every unit
    /// is the same whatever the workers and the interleaving (expiry, re-leases, copies
    /// compared), and the same when asked again after the job finished, so it is a pure
    /// function of the merged state; and the pixel-passes traced are those the local
    /// render used (one pass per unit), far fewer than whole tiles.
    #[test]
    fn leased_pixel_sets_are_deterministic_and_save_the_stopped_pixels() {
        use crate::adaptive::{AdaptiveMode, AdaptiveSettings};
        let p = FramePlan::new(24, 16, 8, 1, 48).unwrap(); // 6 tiles of 64 pixels
        let masked = |unit: WorkUnit, wanted: &Option<crate::PixelRuns>| {
            let mut r = noisy_result(&p, unit);
            let n = p.tile(unit.tile).pixel_count();
            for (k, m) in r.pass_means.iter_mut().enumerate() {
                if wanted.as_ref().is_some_and(|w| !w.contains(k % n)) {
                    *m = [0.0; 3];
                }
            }
            r
        };
        for (mode, ppu) in [
            (AdaptiveMode::Sequential, 1),
            (AdaptiveMode::Unbiased, 1),
            (AdaptiveMode::Sequential, 2),
            (AdaptiveMode::Unbiased, 2),
        ] {
            let settings = AdaptiveSettings {
                mode,
                // The unbiased mode's optimal allocation gives a tile's quiet pixels
                // passes in proportion to the tile's mean deviation, which the fireflies
                // raise: at 0.05 every pixel of a noisy tile would take all 40 fresh
                // passes and no lease would name a set.
                target_error: if mode == AdaptiveMode::Unbiased {
                    0.2
                } else {
                    0.05
                },
                min_passes: 8,
                interval: 4,
                ..AdaptiveSettings::default()
            };
            let mut local = AdaptiveFrame::new(p, 0, settings).unwrap();
            for u in p.units(0, ppu) {
                local.offer(&noisy_result(&p, u)).unwrap();
            }
            let reference = local.image();
            let local_traced: u64 = local
                .tiles()
                .iter()
                .flat_map(|t| t.traced_passes())
                .map(u64::from)
                .sum();
            let mut sets: Option<BTreeMap<WorkUnit, Option<crate::PixelRuns>>> = None;
            for (workers, seed) in [(1u64, 1u64), (3, 2), (4, 9)] {
                let mut s = Scheduler::new(100, 0);
                s.add_adaptive_job(7, 0, p, 0..=0, ppu, settings).unwrap();
                let (mut now, mut rng) = (0u64, seed);
                let mut held: Vec<(Lease, Option<crate::PixelRuns>)> = Vec::new();
                let mut seen: BTreeMap<WorkUnit, Option<crate::PixelRuns>> = BTreeMap::new();
                let mut traced = 0u64;
                while !s.is_complete(7) {
                    now += 10;
                    assert!(now < 1_000_000, "{mode}: the job stalls");
                    for w in 0..workers {
                        for l in s.lease(w, now, 1) {
                            let set = s.wanted_pixels(7, &l.unit);
                            // Every copy of a unit gets the same set.
                            let first = seen.entry(l.unit).or_insert_with(|| set.clone());
                            assert_eq!(*first, set, "{mode}: unit {:?} changed its set", l.unit);
                            held.push((l, set));
                        }
                    }
                    lcg_step(&mut rng);
                    if held.is_empty() {
                        s.expire(now + 1000);
                        continue;
                    }
                    let k = (rng >> 33) as usize % held.len();
                    let (l, set) = held.swap_remove(k);
                    if rng.is_multiple_of(5) {
                        continue; // a lost result: re-leased after expiry
                    }
                    let n = p.tile(l.unit.tile).pixel_count() as u64;
                    // Some copies come from workers that trace whole tiles (older ones)
                    // or carry values outside the set (bdpt splats): the same unit.
                    let r = if rng.is_multiple_of(7) {
                        noisy_result(&p, l.unit)
                    } else {
                        masked(l.unit, &set)
                    };
                    let outcome = s.submit(l.lease_id, 7, r).unwrap();
                    match outcome {
                        Submitted::Accepted => {
                            traced += set.as_ref().map_or(n, crate::PixelRuns::count)
                                * u64::from(l.unit.pass_count);
                        }
                        // Masked pixels are deterministic zeros: copies agree.
                        other => assert_eq!(other, Submitted::Duplicate { identical: true }),
                    }
                    if rng.is_multiple_of(3) {
                        s.expire(now + 1000);
                    }
                }
                let f = s.adaptive_frame(7, 0).unwrap();
                assert_eq!(f.image(), reference, "{mode}/{ppu} with {workers} workers");
                // Asked again now that every decision is taken, each set is unchanged.
                for (u, set) in &seen {
                    assert_eq!(s.wanted_pixels(7, u), *set, "{mode}: {u:?} after the end");
                }
                match &sets {
                    None => sets = Some(seen),
                    Some(first) => assert_eq!(*first, seen, "{mode}: sets differ by workers"),
                }
                let full = u64::from(p.width * p.height * p.passes);
                if ppu == 1 {
                    assert_eq!(traced, local_traced, "{mode}: traced vs the local render");
                } else {
                    // A pixel wanted for one pass of a unit is traced for both.
                    assert!(traced >= local_traced, "{mode}/{ppu}");
                }
                // Tile 0 (constant) stops at the first decision; the noisy ones later.
                assert!(traced < full, "{mode}/{ppu}: traced {traced} of {full}");
            }
            let sets = sets.unwrap();
            assert!(
                sets.values().any(Option::is_some),
                "{mode}: no lease named a pixel set"
            );
        }
    }

    #[test]
    fn cancel_stops_leasing_and_returns_outstanding_leases() {
        let p = plan();
        let mut s = Scheduler::new(100, 0);
        s.add_job(1, 0, p, 0..=0, 1);
        let l = s.lease(1, 0, 4);
        let dropped = s.cancel(1);
        assert_eq!(dropped.len(), 4);
        assert!(s.lease(1, 10, 4).is_empty());
        assert_eq!(
            s.submit(l[0].lease_id, 1, result(&p, l[0].unit, 0.5)),
            Err(SubmitError::Canceled(1))
        );
    }

    #[test]
    fn frames_wait_for_the_memory_budget_and_release_it_when_complete() {
        let p = plan();
        let frame = frame_state_bytes(&p, false);
        assert_eq!(frame, 40 * 30 * FrameAccumulator::BYTES_PER_PIXEL);
        let mut s = Scheduler::new(1000, 0);
        // Room for one frame and a half: three frames of job 1, then job 2, take turns.
        s.set_memory_budget(frame + frame / 2);
        s.add_job(1, 0, p, 0..=2, 2);
        s.add_job(2, 0, p, 0..=0, 2);
        assert_eq!(s.resident_bytes(), 0, "nothing is allocated before a lease");
        assert_eq!(s.residency(1, 1), Some(Residency::Pending));
        let mut order = Vec::new();
        loop {
            let ls = s.lease(1, 0, 100);
            if ls.is_empty() {
                break;
            }
            assert!(s.resident_bytes() <= frame + frame / 2);
            // Only one frame is ever live: every lease of a batch is of one frame.
            assert!(ls
                .iter()
                .all(|l| (l.job, l.unit.frame) == (ls[0].job, ls[0].unit.frame)));
            order.push((ls[0].job, ls[0].unit.frame));
            for l in &ls {
                assert_eq!(
                    s.submit(l.lease_id, l.job, result(&p, l.unit, 0.5)),
                    Ok(Submitted::Accepted)
                );
            }
            // The frame is complete; until its checkpoints are durable it stays.
            assert!(
                s.lease(1, 0, 100).is_empty(),
                "the next frame waits for memory"
            );
            assert!(s.release_frame(ls[0].job, ls[0].unit.frame));
            assert_eq!(s.resident_bytes(), 0);
        }
        assert_eq!(order, vec![(1, 0), (1, 1), (1, 2), (2, 0)]);
        assert!(s.is_complete(1) && s.is_complete(2));
        let pr = s.progress(1).unwrap();
        assert_eq!((pr.frames_done, pr.passes_done), (3, pr.passes_planned));
        assert_eq!(s.residency(1, 2), Some(Residency::Released));
        assert!(s.frame(1, 2).is_none());
    }

    /// Issue 15: a finished frame of a running adaptive job gives its memory back, so an
    /// adaptive animation under a budget of one frame renders frame after frame (before,
    /// adaptive frames stayed until the job ended and the second frame never fit).
    #[test]
    fn finished_adaptive_frames_are_released_and_the_next_frame_fits() {
        use crate::adaptive::{AdaptiveMode, AdaptiveSettings};
        let p = FramePlan::new(16, 8, 8, 1, 48).unwrap(); // 2 tiles, 48 passes
        for mode in [AdaptiveMode::Sequential, AdaptiveMode::Unbiased] {
            let settings = AdaptiveSettings {
                mode,
                target_error: 0.05,
                ..AdaptiveSettings::default()
            };
            let frame = frame_state_bytes(&p, true);
            let mut s = Scheduler::new(1000, 0);
            s.set_memory_budget(frame);
            s.add_adaptive_job(7, 0, p, 0..=2, 2, settings).unwrap();
            let mut order = Vec::new();
            for _ in 0..1000 {
                let ls = s.lease(1, 0, 100);
                if ls.is_empty() {
                    break;
                }
                assert!(s.resident_bytes() <= frame, "{mode}: one frame at a time");
                for l in &ls {
                    if order.last() != Some(&l.unit.frame) {
                        order.push(l.unit.frame);
                    }
                    assert_eq!(
                        s.submit(l.lease_id, 7, result(&p, l.unit, 0.5)),
                        Ok(Submitted::Accepted)
                    );
                }
                let f = ls[0].unit.frame;
                if s.adaptive_frame(7, f).is_some_and(AdaptiveFrame::finished) {
                    // Not before its checkpoints are durable: the caller says when.
                    assert_eq!(s.residency(7, f), Some(Residency::Live));
                    assert!(s.release_frame(7, f), "{mode}: frame {f}");
                    assert_eq!(s.residency(7, f), Some(Residency::Released));
                    assert!(s.adaptive_frame(7, f).is_none());
                    assert_eq!(s.resident_bytes(), 0);
                }
            }
            assert_eq!(order, [0, 1, 2], "{mode}");
            assert!(s.is_complete(7), "{mode}");
            let pr = s.progress(7).unwrap();
            assert_eq!(pr.frames_done, 3, "{mode}");
        }
    }

    /// A frame released while the cursor is still inside it (one unit per lease: the
    /// cursor stops at each leasable unit, so the passes past the tiles' ends are not
    /// visited yet when the policy finishes) does not hold the cursor: the later frames
    /// are rendered. Before the fix the job stalled after frame 0's first units.
    #[test]
    fn a_frame_released_ahead_of_the_cursor_does_not_stall_the_job() {
        use crate::adaptive::{AdaptiveMode, AdaptiveSettings};
        let p = FramePlan::new(16, 8, 8, 1, 48).unwrap();
        for mode in [AdaptiveMode::Sequential, AdaptiveMode::Unbiased] {
            let settings = AdaptiveSettings {
                mode,
                target_error: 0.05,
                ..AdaptiveSettings::default()
            };
            let mut s = Scheduler::new(1000, 0);
            s.set_memory_budget(frame_state_bytes(&p, true));
            s.add_adaptive_job(7, 0, p, 0..=2, 2, settings).unwrap();
            let mut order = Vec::new();
            for _ in 0..10_000 {
                let Some(l) = s.lease(1, 0, 1).pop() else {
                    break;
                };
                if order.last() != Some(&l.unit.frame) {
                    order.push(l.unit.frame);
                }
                assert_eq!(
                    s.submit(l.lease_id, 7, result(&p, l.unit, 0.5)),
                    Ok(Submitted::Accepted)
                );
                let f = l.unit.frame;
                if s.adaptive_frame(7, f).is_some_and(AdaptiveFrame::finished) {
                    assert!(s.release_frame(7, f));
                }
            }
            assert_eq!(order, [0, 1, 2], "{mode}");
            assert!(s.is_complete(7), "{mode}");
        }
    }

    /// An unfinished adaptive frame is not released.
    #[test]
    fn an_unfinished_adaptive_frame_is_not_released() {
        use crate::adaptive::{AdaptiveMode, AdaptiveSettings};
        let p = FramePlan::new(16, 8, 8, 1, 48).unwrap();
        let settings = AdaptiveSettings {
            mode: AdaptiveMode::Sequential,
            target_error: 0.05,
            ..AdaptiveSettings::default()
        };
        let mut s = Scheduler::new(1000, 0);
        s.add_adaptive_job(7, 0, p, 0..=0, 2, settings).unwrap();
        let ls = s.lease(1, 0, 1);
        s.submit(ls[0].lease_id, 7, result(&p, ls[0].unit, 0.5))
            .unwrap();
        assert!(!s.release_frame(7, 0));
        assert!(!s.release_frame(7, 5), "no such frame");
        assert!(s.adaptive_frame(7, 0).is_some());
    }

    #[test]
    fn a_late_result_for_a_released_frame_is_late_not_a_fault() {
        let p = plan();
        let mut s = Scheduler::new(10, 0);
        s.add_job(1, 0, p, 0..=0, 6);
        let first = s.lease(1, 0, 100);
        // Every lease lapses and the units go to a second worker, which completes them.
        s.expire(100);
        let second = s.lease(2, 100, 100);
        assert_eq!(first.len(), second.len());
        for l in &second {
            s.submit(l.lease_id, 1, result(&p, l.unit, 0.5)).unwrap();
        }
        assert!(s.release_frame(1, 0));
        assert!(!s.release_frame(1, 0), "released once");
        for l in &first {
            assert_eq!(
                s.submit(l.lease_id, 1, result(&p, l.unit, 0.5)),
                Ok(Submitted::Late)
            );
        }
    }

    #[test]
    fn an_incomplete_frame_is_not_released() {
        let p = plan();
        let mut s = Scheduler::new(1000, 0);
        s.add_job(1, 0, p, 0..=0, 2);
        let ls = s.lease(1, 0, 1);
        s.submit(ls[0].lease_id, 1, result(&p, ls[0].unit, 0.5))
            .unwrap();
        assert!(!s.release_frame(1, 0));
        assert_eq!(s.residency(1, 0), Some(Residency::Live));
        assert_eq!(s.resident_bytes(), frame_state_bytes(&p, false));
        s.remove_job(1);
        assert_eq!(s.resident_bytes(), 0);
    }

    #[test]
    fn finished_adaptive_jobs_make_room_for_waiting_ones() {
        let p = plan();
        let adaptive = AdaptiveSettings {
            target_error: 1.0,
            ..AdaptiveSettings::default()
        };
        let mut s = Scheduler::new(1000, 0);
        s.set_memory_budget(frame_state_bytes(&p, true));
        s.add_adaptive_job(1, 0, p, 0..=0, 1, adaptive).unwrap();
        while !s.is_complete(1) {
            let ls = s.lease(1, 0, 100);
            assert!(!ls.is_empty(), "the adaptive job stalled");
            for l in ls {
                s.submit(l.lease_id, 1, result(&p, l.unit, 0.5)).unwrap();
            }
        }
        assert!(
            s.adaptive_frame(1, 0).is_some(),
            "kept while nobody needs room"
        );
        s.add_job(2, 0, p, 0..=0, 2);
        let ls = s.lease(1, 0, 100);
        assert!(!ls.is_empty(), "job 2 waits forever");
        assert!(ls.iter().all(|l| l.job == 2));
        assert!(s.is_complete(1));
        assert_eq!(s.residency(1, 0), Some(Residency::Released));
        assert!(s.adaptive_frame(1, 0).is_none());
    }
}

/// Spot checks and quarantine (issue 15).
#[cfg(test)]
mod spot_tests {
    use super::*;
    use crate::spot::SpotOutcome;
    use crate::FrameImage;

    fn plan() -> FramePlan {
        FramePlan::new(40, 30, 16, 4, 6).unwrap() // 6 tiles, 6 passes: 36 units
    }

    /// What an honest worker renders: a pure function of the unit.
    fn honest(plan: &FramePlan, unit: WorkUnit) -> UnitResult {
        let rect = plan.tile(unit.tile);
        let n = rect.pixel_count() * unit.pass_count as usize;
        let base = 0.5 + unit.tile as f32 + unit.first_pass as f32 * 0.1;
        let pass_means = (0..n).map(|k| [base + (k % 7) as f32 * 0.01; 3]).collect();
        UnitResult {
            unit,
            width: rect.width,
            height: rect.height,
            pass_means,
            rejected_samples: 0,
        }
    }

    /// What a faulty worker renders: well-formed, one value off.
    fn corrupt(plan: &FramePlan, unit: WorkUnit) -> UnitResult {
        let mut r = honest(plan, unit);
        r.pass_means[3][1] += 0.25;
        r
    }

    fn bits(img: &FrameImage) -> Vec<u32> {
        img.mean
            .iter()
            .chain(&img.variance_of_mean)
            .flat_map(|p| p.map(f32::to_bits))
            .chain(img.passes.iter().copied())
            .collect()
    }

    /// The image of the job rendered by honest workers without spot checks.
    fn reference() -> Vec<u32> {
        let p = plan();
        let mut s = Scheduler::new(100, 0);
        s.add_job(1, 0, p, 0..=0, 1);
        while !s.is_complete(1) {
            for l in s.lease(1, 0, 100) {
                s.submit(l.lease_id, 1, honest(&p, l.unit)).unwrap();
            }
        }
        bits(&s.frame(1, 0).unwrap().image())
    }

    /// Drives `workers` (id, faulty) round-robin, each leasing up to 2 units as one of
    /// `workers.len()` one-thread workers and delivering them the next round (so copies
    /// of one unit are in flight at once), until the job completes or `rounds` pass.
    /// Asserts that no worker is ever leased a spot-checked unit it already delivered a
    /// copy of. Returns the events.
    fn drive(s: &mut Scheduler, workers: &[(WorkerId, bool)], rounds: u32) -> Vec<SpotEvent> {
        let p = plan();
        let mut delivered: BTreeSet<(WorkUnit, WorkerId)> = BTreeSet::new();
        let mut held: Vec<Lease> = Vec::new();
        let mut events = Vec::new();
        let live = workers
            .iter()
            .filter(|(w, _)| !s.is_quarantined(*w))
            .count() as u64;
        for round in 0..rounds {
            if s.is_complete(1) {
                break;
            }
            for &(w, faulty) in workers {
                // Deliver what this worker leased last round.
                let mine: Vec<Lease> = held.iter().filter(|l| l.worker == w).copied().collect();
                held.retain(|l| l.worker != w);
                for l in mine {
                    let r = if faulty {
                        corrupt(&p, l.unit)
                    } else {
                        honest(&p, l.unit)
                    };
                    match s.submit_from(w, l.lease_id, 1, r) {
                        Ok(_) | Err(SubmitError::Quarantined(_)) => {}
                        Err(e) => panic!("worker {w}: {e}"),
                    }
                    delivered.insert((l.unit, w));
                    events.extend(s.take_spot_events());
                }
                let got = s.lease_among(w, u64::from(round), 2, 1, live);
                for l in &got {
                    if is_spot_checked(s.spot_check_fraction(), 1, &l.unit) {
                        assert!(
                            !delivered.contains(&(l.unit, w)) || live == 1,
                            "worker {w} leased a second copy of {:?}",
                            l.unit
                        );
                    }
                }
                held.extend(got);
            }
        }
        events
    }

    #[test]
    fn a_faulty_worker_is_quarantined_and_the_image_stays_identical() {
        let p = plan();
        let expected = reference();
        for fraction in [0.3, 1.0] {
            let mut s = Scheduler::new(100, 0);
            s.set_spot_check_fraction(fraction);
            s.add_job(1, 0, p, 0..=0, 1);
            let events = drive(&mut s, &[(3, true), (1, false), (2, false)], 500);
            assert!(s.is_complete(1), "fraction {fraction}: the job stalled");
            assert_eq!(
                bits(&s.frame(1, 0).unwrap().image()),
                expected,
                "fraction {fraction}: the image differs from the honest render"
            );
            assert!(s.is_quarantined(3));
            assert!(!s.is_quarantined(1) && !s.is_quarantined(2));
            assert!(
                s.lease(3, 1000, 10).is_empty(),
                "a quarantined worker leases"
            );
            let mismatches = events
                .iter()
                .filter(|e| {
                    matches!(
                        e,
                        SpotEvent::Checked {
                            outcome: SpotOutcome::Mismatch,
                            ..
                        }
                    )
                })
                .count();
            assert!(mismatches >= 1, "fraction {fraction}: {events:?}");
            let q: Vec<_> = events
                .iter()
                .filter(|e| matches!(e, SpotEvent::Quarantined { worker: 3, .. }))
                .collect();
            assert_eq!(q.len(), 1, "quarantined once");
            // The faulty worker delivered first (it leads the round), so at 0.3 some of
            // its corrupt units were merged unchecked: their tiles were dropped and every
            // re-rendered copy of its units differs from its own.
            if fraction < 1.0 {
                let SpotEvent::Quarantined { reset_tiles, .. } = q[0] else {
                    unreachable!()
                };
                assert!(!reset_tiles.is_empty());
                let reverified: Vec<bool> = events
                    .iter()
                    .filter_map(|e| match e {
                        SpotEvent::Reverified { identical, .. } => Some(*identical),
                        _ => None,
                    })
                    .collect();
                assert!(!reverified.is_empty() && reverified.iter().all(|i| !i));
            }
            assert_eq!(s.spot_checks_waiting(), (0, 0));
        }
    }

    #[test]
    fn a_worker_alone_checks_itself_and_finishes() {
        let p = plan();
        let mut s = Scheduler::new(100, 0);
        s.set_spot_check_fraction(0.3);
        s.add_job(1, 0, p, 0..=0, 1);
        let events = drive(&mut s, &[(1, false)], 500);
        assert!(s.is_complete(1));
        assert_eq!(bits(&s.frame(1, 0).unwrap().image()), reference());
        let checked = (0..36u64)
            .filter(|&i| {
                let u = WorkUnit {
                    frame: 0,
                    tile: (i % 6) as u32,
                    first_pass: (i / 6) as u32,
                    pass_count: 1,
                };
                is_spot_checked(0.3, 1, &u)
            })
            .count();
        assert!(checked > 0);
        let alone = events
            .iter()
            .filter(|e| {
                matches!(
                    e,
                    SpotEvent::Checked {
                        outcome: SpotOutcome::Alone,
                        ..
                    }
                )
            })
            .count();
        assert_eq!(alone, checked);
        // The copies are counted as work: one more per checked unit, all rendered.
        let progress = s.progress(1).unwrap();
        assert_eq!(progress.copies_total, checked as u64);
        assert_eq!(
            (progress.units_done, progress.copies_done),
            (36, checked as u64)
        );
        // The plain lease (no knowledge of the others) never gives a worker its own
        // spot-checked unit again.
        let mut s = Scheduler::new(100, 0);
        s.set_spot_check_fraction(1.0);
        s.add_job(1, 0, p, 0..=0, 1);
        let first = s.lease(1, 0, 100);
        assert_eq!(first.len(), 36);
        for l in &first {
            assert_eq!(
                s.submit_from(1, l.lease_id, 1, honest(&p, l.unit)),
                Ok(Submitted::Held)
            );
        }
        assert!(s.lease(1, 0, 100).is_empty());
        let progress = s.progress(1).unwrap();
        assert_eq!(
            (
                progress.units_done,
                progress.copies_total,
                progress.copies_done
            ),
            (0, 36, 36),
            "36 first copies held: half the work"
        );
        let second = s.lease(2, 0, 100);
        assert_eq!(second.len(), 36);
        for l in &second {
            assert_eq!(
                s.submit_from(2, l.lease_id, 1, honest(&p, l.unit)),
                Ok(Submitted::Accepted)
            );
        }
        assert!(s.is_complete(1));
        let progress = s.progress(1).unwrap();
        assert_eq!((progress.units_done, progress.copies_done), (36, 36));
    }

    #[test]
    fn a_dispute_waits_for_a_third_worker() {
        let p = plan();
        let mut s = Scheduler::new(100, 0);
        s.set_spot_check_fraction(1.0);
        s.add_job(1, 0, p, 0..=0, 1);
        // Two workers, one faulty: every unit is disputed and nobody can decide.
        drive(&mut s, &[(1, false), (2, true)], 100);
        assert!(!s.is_complete(1));
        assert!(!s.is_quarantined(1) && !s.is_quarantined(2));
        let (waiting, disputed) = s.spot_checks_waiting();
        assert!(waiting > 0 && disputed > 0, "{waiting} {disputed}");
        assert_eq!(
            s.progress(1).unwrap().passes_done,
            0,
            "nothing disputed is merged"
        );
        // A third worker decides by majority.
        drive(&mut s, &[(1, false), (2, true), (3, false)], 500);
        assert!(s.is_complete(1));
        assert!(s.is_quarantined(2) && !s.is_quarantined(1) && !s.is_quarantined(3));
        assert_eq!(bits(&s.frame(1, 0).unwrap().image()), reference());
        // The quarantined worker's late results are refused.
        let l = s.leases().next().copied();
        assert!(l.is_none(), "its leases were revoked");
    }

    #[test]
    fn quarantine_drops_the_tiles_of_unverified_units_and_revokes_leases() {
        let p = plan();
        let mut s = Scheduler::new(100, 0);
        s.add_job(1, 0, p, 0..=0, 1);
        // Worker 9 merges the first pass of every tile (unchecked: no spot checks), and
        // holds a lease.
        for l in s.lease(9, 0, 6) {
            s.submit_from(9, l.lease_id, 1, corrupt(&p, l.unit))
                .unwrap();
        }
        let out = s.lease(9, 0, 1);
        assert_eq!(s.progress(1).unwrap().passes_done, 6);
        assert!(s.quarantine(9, "test"));
        assert!(!s.quarantine(9, "again"));
        assert_eq!(s.progress(1).unwrap().passes_done, 0);
        assert_eq!(s.progress(1).unwrap().units_leased, 0);
        assert_eq!(
            s.submit_from(9, out[0].lease_id, 1, honest(&p, out[0].unit)),
            Err(SubmitError::Quarantined(9))
        );
        let ev = s.take_spot_events();
        assert!(
            matches!(&ev[..], [SpotEvent::Quarantined { reset_tiles, unrepaired_units: 0, .. }] if reset_tiles.len() == 6)
        );
        while !s.is_complete(1) {
            for l in s.lease(1, 0, 100) {
                s.submit_from(1, l.lease_id, 1, honest(&p, l.unit)).unwrap();
            }
        }
        assert_eq!(bits(&s.frame(1, 0).unwrap().image()), reference());
        let again = s.take_spot_events();
        assert_eq!(again.len(), 6);
        assert!(again.iter().all(|e| matches!(
            e,
            SpotEvent::Reverified {
                worker: 9,
                identical: false,
                ..
            }
        )));
    }

    #[test]
    fn a_lifted_quarantine_leases_again_and_takes_results() {
        let p = plan();
        let mut s = Scheduler::new(100, 0);
        s.add_job(1, 0, p, 0..=0, 1);
        assert!(!s.lift_quarantine(9), "not quarantined");
        let held = s.lease(9, 0, 1);
        assert!(s.quarantine(9, "test"));
        s.take_spot_events();
        assert!(s.lease(9, 0, 1).is_empty());
        assert_eq!(
            s.submit_from(9, held[0].lease_id, 1, honest(&p, held[0].unit)),
            Err(SubmitError::Quarantined(9))
        );
        assert!(s.lift_quarantine(9));
        assert!(!s.is_quarantined(9));
        assert!(!s.lift_quarantine(9), "lifted once");
        // Leased again, and its result merged.
        let again = s.lease(9, 0, 1);
        assert_eq!(again.len(), 1);
        assert_eq!(
            s.submit_from(9, again[0].lease_id, 1, honest(&p, again[0].unit)),
            Ok(Submitted::Accepted)
        );
        assert_eq!(s.progress(1).unwrap().passes_done, 1);
        // Quarantined again: the unit it merged since is dropped and repaired as before.
        assert!(s.quarantine(9, "again"));
        assert!(matches!(
            &s.take_spot_events()[..],
            [SpotEvent::Quarantined { reset_tiles, unrepaired_units: 0, .. }] if reset_tiles.len() == 1
        ));
        assert_eq!(s.progress(1).unwrap().passes_done, 0);
    }
}
