//! One job's work queue: its units in canonical order (frame-major, then pass chunk, then
//! tile: coarse to fine within a frame), the cursor over the never-leased ones, the units
//! returned to the queue, and for adaptive jobs the gate that holds a unit back until the
//! decision before it is made ([`Gate`]).
//!
//! A unit is named by its canonical index everywhere in the scheduler ([`Job::unit`],
//! [`Job::index`]); the sets of a job (returned, done, leased, checked) are sets of
//! indices.

use super::memory::Memory;
use super::spot::SpotCheck;
use super::SubmitError;
use crate::adaptive::{AdaptiveFrame, AdaptiveSettings};
use crate::ids::WorkerId;
use crate::merge::{FrameAccumulator, Offer};
use crate::plan::{FramePlan, WorkUnit};
use crate::result::UnitResult;
use std::collections::{BTreeMap, BTreeSet};

/// One frame of a job in the scheduler (see [`super::Residency`]).
pub(super) enum FrameSlot {
    Pending,
    Live(Box<FrameAccumulator>),
    Released,
}

impl FrameSlot {
    pub(super) fn live(&self) -> Option<&FrameAccumulator> {
        match self {
            Self::Live(f) => Some(f),
            _ => None,
        }
    }
}

/// One job in the scheduler: its plan and frames, and the state of each of its units by
/// canonical index.
pub(super) struct Job {
    pub(super) priority: i32,
    pub(super) seq: u64,
    pub(super) plan: FramePlan,
    pub(super) first_frame: u32,
    pub(super) passes_per_unit: u32,
    pub(super) frames: Vec<FrameSlot>,
    /// Bytes charged to the budget for each live frame ([`super::frame_state_bytes`]).
    pub(super) frame_bytes: u64,
    /// Canonical index of the next never-leased unit.
    pub(super) cursor: u64,
    /// Units returned to the queue (expired or given back), by canonical index.
    pub(super) returned: BTreeSet<u64>,
    /// Canonical indices of merged units.
    pub(super) done: BTreeSet<u64>,
    /// Outstanding leases by canonical unit index.
    pub(super) leased: BTreeMap<u64, u64>,
    pub(super) canceled: bool,
    /// A finished adaptive job whose state was dropped to make room
    /// ([`super::Scheduler::lease`]): complete, with every frame released.
    pub(super) evicted: bool,
    /// Adaptive jobs only: the policy state and the units it holds back.
    pub(super) adaptive: Option<AdaptiveQueue>,
    /// Spot-checked units with copies waiting for agreement, by canonical index.
    pub(super) checks: BTreeMap<u64, SpotCheck>,
    /// Copies of spot-checked units received beyond the one a merged unit counts in
    /// `done`: the work the spot checks have added so far ([`super::Progress::copies_done`]).
    pub(super) extra_copies: u64,
    /// Second copies the spot checks render over the whole job ([`super::Progress::copies_total`]),
    /// counted when the job is added or the fraction changes, not per status request.
    pub(super) copies_total: u64,
    /// Units merged (or buffered) on one worker's word: that worker and the digest. If
    /// the worker is quarantined, their tiles are merged again.
    pub(super) unverified: BTreeMap<u64, (WorkerId, u64)>,
    /// Units of dropped tiles that a quarantined worker had merged: that worker and its
    /// copy's digest, compared with the copy that replaces it.
    pub(super) suspect: BTreeMap<u64, (WorkerId, u64)>,
}

/// The adaptive part of a job: one policy state per frame, units waiting for a decision
/// and units a decision made unnecessary (both by canonical index).
pub(super) struct AdaptiveQueue {
    pub(super) settings: AdaptiveSettings,
    /// One per frame, allocated with the frame's accumulator.
    pub(super) frames: Vec<Option<AdaptiveFrame>>,
    pub(super) waiting: BTreeSet<u64>,
    pub(super) skipped: BTreeSet<u64>,
}

impl AdaptiveQueue {
    /// The adaptive part of a job of `frames` frames run with `settings`: nothing allocated
    /// (each frame's policy state comes with its first lease), nothing waiting.
    pub(super) fn new(settings: AdaptiveSettings, frames: usize) -> Self {
        Self {
            settings,
            frames: (0..frames).map(|_| None).collect(),
            waiting: BTreeSet::new(),
            skipped: BTreeSet::new(),
        }
    }
}

/// What the adaptive policy says about leasing a unit now.
#[derive(PartialEq)]
enum Gate {
    Lease,
    Wait,
    Skip,
}

impl Job {
    /// The unit with canonical index `i`: frame-major, then pass chunk, then tile.
    pub(super) fn unit(&self, i: u64) -> WorkUnit {
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
    pub(super) fn index(&self, u: &WorkUnit) -> Option<u64> {
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

    /// Units per tile of a frame: its passes cut into chunks of `passes_per_unit`.
    pub(super) fn chunks(&self) -> u64 {
        self.plan.chunks_per_tile(self.passes_per_unit) as u64
    }

    /// Units per frame: a chunk of every tile, per chunk.
    pub(super) fn units_per_frame(&self) -> u64 {
        self.chunks() * self.plan.tile_count() as u64
    }

    /// Units in the whole job.
    pub(super) fn units_total(&self) -> u64 {
        self.units_per_frame() * self.frames.len() as u64
    }

    /// Index into `frames` of the frame of canonical unit `i`.
    pub(super) fn frame_index(&self, i: u64) -> usize {
        (i / self.units_per_frame()) as usize
    }

    /// The next unit `worker` may render, by canonical index: a returned unit first (in
    /// canonical order), else the next one from the cursor; `None` when nothing can be
    /// leased to it now.
    pub(super) fn next_index(
        &mut self,
        mem: &mut Memory,
        worker: WorkerId,
        alone: bool,
    ) -> Option<u64> {
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

    /// Units that wait to be leased: returned ones, the never-leased ones from the cursor
    /// on (less those merged before a restart) and, for adaptive jobs, those waiting for a
    /// decision (an upper bound: a decision may make some unnecessary).
    pub(super) fn queued(&self) -> u64 {
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
    /// decision. Counted as queued, they made [`super::tail_share`] give the first worker to ask
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

    /// Whether the job may have a unit to lease (not canceled, and units returned, ahead
    /// of the cursor or waiting for a decision).
    pub(super) fn has_work(&self) -> bool {
        let waiting = self
            .adaptive
            .as_ref()
            .is_some_and(|a| !a.waiting.is_empty());
        !self.canceled && (!self.returned.is_empty() || self.cursor < self.units_total() || waiting)
    }

    /// Whether every frame is complete (for an adaptive job: every tile finished by its
    /// policy), released, or the job was evicted finished.
    pub(super) fn is_complete(&self) -> bool {
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

    /// Drops the record of lease `lease_id` on unit `i` if it is the unit's outstanding
    /// one (a copy answering an older, lapsed lease leaves the newer lease in place).
    pub(super) fn forget_lease(&mut self, i: u64, lease_id: u64) {
        if self.leased.get(&i) == Some(&lease_id) {
            self.leased.remove(&i);
        }
    }

    /// Offers `result` to live frame `k`'s accumulator and, unless it is a duplicate of a
    /// merged unit, to the frame's adaptive policy (which sees every merged pass once).
    /// A frame that is not live refuses it ([`SubmitError::NotResident`]).
    pub(super) fn offer(&mut self, k: usize, result: UnitResult) -> Result<Offer, SubmitError> {
        let Some(FrameSlot::Live(acc)) = self.frames.get_mut(k) else {
            return Err(SubmitError::NotResident(result.unit.frame));
        };
        let copy = self.adaptive.as_ref().map(|_| result.clone());
        let outcome = acc.offer(result)?;
        if let (Some(a), Some(copy)) = (self.adaptive.as_mut(), copy) {
            if !matches!(outcome, Offer::Duplicate { .. }) {
                if let Some(Some(f)) = a.frames.get_mut(k) {
                    // Validated by the offer above; cannot fail.
                    let _ = f.offer(&copy);
                }
            }
        }
        Ok(outcome)
    }
}
