//! Spot checks and quarantine, the scheduler's side (ARCHITECTURE.md §6, "Spot checks and
//! quarantine"): a spot-checked unit's copies are held unmerged, grouped by digest, until
//! two different workers' copies agree ([`SpotCheck::agreed`]); the agreed copy is merged
//! and every worker whose copy differs is quarantined ([`Scheduler::quarantine`]). A
//! quarantine revokes the worker's leases and drops every tile of a live frame it merged
//! a unit into on its word alone, so the tile is merged again from other workers' copies.
//!
//! Which units are checked ([`crate::is_spot_checked`], [`crate::spot::worker_selects`],
//! [`crate::spot::unit_is_outlier`]) and what is reported ([`SpotEvent`]) are the leaf
//! module [`crate::spot`]; each worker's record of matching checks, which sets its check
//! rate, is kept here ([`WorkerRecord`]).

use super::job::{FrameSlot, Job};
use super::{Scheduler, SubmitError, Submitted};
use crate::ids::{JobId, WorkerId};
use crate::merge::Offer;
use crate::plan::WorkUnit;
use crate::result::UnitResult;
use crate::spot::{is_spot_checked, unit_is_outlier, worker_selects, SpotEvent, SpotOutcome};
use std::collections::BTreeSet;

/// A worker's spot-check record: its copies that matched another worker's, which set the
/// rate its units are checked at ([`crate::spot::worker_check_rate`]).
#[derive(Clone, Copy, Debug, Default)]
pub(super) struct WorkerRecord {
    /// Checks its copy passed: another worker's copy had the same digest.
    pub(super) verified: u64,
    /// It leased last as the only worker sharing the queue: no one could verify its
    /// copies, so they are not all checked (a farm of one worker renders each unit once;
    /// the job-wide sample still re-renders some on the worker itself).
    pub(super) alone: bool,
}

/// Copies of one spot-checked unit that are waiting for agreement, grouped by digest.
#[derive(Debug, Default)]
pub(super) struct SpotCheck {
    pub(super) groups: Vec<CopyGroup>,
}

/// The copies of a unit with one digest: who rendered them and the result (kept once).
#[derive(Debug)]
pub(super) struct CopyGroup {
    pub(super) digest: u64,
    /// One entry per copy; the same worker twice when it re-rendered the unit alone.
    pub(super) workers: Vec<WorkerId>,
    /// The leases the copies answered: a result submitted again for the same lease (a
    /// worker retrying after a lost answer) is not a second copy.
    pub(super) leases: Vec<u64>,
    pub(super) result: UnitResult,
}

impl SpotCheck {
    /// Whether `worker` has rendered a copy.
    pub(super) fn has(&self, worker: WorkerId) -> bool {
        self.groups.iter().any(|g| g.workers.contains(&worker))
    }

    /// Whether `worker` may render the next copy: one it has no copy of, or, when it is
    /// the only worker sharing the queue (`alone`), a second copy of an undisputed unit
    /// (re-rendering its own copy catches faults that do not repeat; a dispute needs a
    /// third, different worker).
    pub(super) fn eligible(&self, worker: WorkerId, alone: bool) -> bool {
        !self.has(worker) || (alone && self.groups.len() == 1)
    }

    /// The index of the group the copies agree on, if any: two different workers with the
    /// same digest, or (undisputed) two copies of the same worker.
    pub(super) fn agreed(&self) -> Option<usize> {
        let distinct = |g: &CopyGroup| {
            g.workers
                .iter()
                .any(|w| g.workers.first().is_some_and(|f| f != w))
        };
        if let Some(k) = self.groups.iter().position(distinct) {
            return Some(k);
        }
        (self.groups.len() == 1 && self.groups[0].workers.len() >= 2).then_some(0)
    }

    /// Adds `worker`'s copy, answering `lease_id`, to the group of its digest or to a new
    /// group; whether it made a new group. `None` (nothing added) if a copy answering that
    /// lease is held already: a worker retrying after a lost answer sends no second copy.
    pub(super) fn add(
        &mut self,
        worker: WorkerId,
        lease_id: u64,
        digest: u64,
        result: UnitResult,
    ) -> Option<bool> {
        if self.groups.iter().any(|g| g.leases.contains(&lease_id)) {
            return None;
        }
        match self.groups.iter_mut().find(|g| g.digest == digest) {
            Some(g) => {
                g.workers.push(worker);
                g.leases.push(lease_id);
                Some(false)
            }
            None => {
                self.groups.push(CopyGroup {
                    digest,
                    workers: vec![worker],
                    leases: vec![lease_id],
                    result,
                });
                Some(true)
            }
        }
    }

    /// The workers with a copy, group by group (a worker's copies in a row named once).
    fn workers(&self) -> Vec<WorkerId> {
        let mut workers: Vec<WorkerId> = self
            .groups
            .iter()
            .flat_map(|g| g.workers.iter().copied())
            .collect();
        workers.dedup();
        workers
    }

    /// Settles the check on group `k`, the one [`SpotCheck::agreed`] found.
    fn settle(mut self, k: usize) -> Verdict {
        let agreed = self.groups.swap_remove(k);
        // Every worker with a copy unlike the agreed one (even if it also rendered the
        // agreed one: a worker whose copies differ is faulty).
        let dissenters: BTreeSet<WorkerId> = self
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
        Verdict {
            agreed,
            dissenters,
            outcome,
        }
    }
}

/// How a spot check was settled.
struct Verdict {
    /// The copies agreed on.
    agreed: CopyGroup,
    /// The workers whose copy differs from the agreed one.
    dissenters: BTreeSet<WorkerId>,
    outcome: SpotOutcome,
}

/// Jobs of up to this many units have their spot-checked units counted one by one when
/// added (a hash each); larger ones use the expected count, whose
/// relative error is then below `1 / sqrt(EXACT_SPOT_COUNT x fraction)`.
pub const EXACT_SPOT_COUNT: u64 = 4096;

impl Job {
    /// The units of job `id` spot-checked at `fraction`: counted one by one for up to
    /// [`EXACT_SPOT_COUNT`] units, the expected `units x fraction` (rounded) beyond.
    pub(super) fn spot_copies(&self, fraction: f64, id: JobId) -> u64 {
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

    /// Whether `worker` may render unit `i`: a spot-checked unit's next copy goes to a
    /// worker without a copy of it (see [`SpotCheck::eligible`] for a worker alone).
    pub(super) fn may_render(&self, i: u64, worker: WorkerId, alone: bool) -> bool {
        self.checks
            .get(&i)
            .is_none_or(|c| c.eligible(worker, alone))
    }

    /// Drops tile `tile` of live frame `k` (spot-check repair): its merged and buffered
    /// passes and its adaptive state are cleared and every one of its units is leased
    /// again (those leased now are merged when they arrive). Units `quarantined` had
    /// merged are remembered as suspect, to compare with their new copies.
    pub(super) fn reset_tile(&mut self, k: usize, tile: u32, quarantined: WorkerId) {
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

    /// Unit `i`, a suspect of a quarantined worker, merged again with `digest`: the
    /// comparison with the suspect copy.
    pub(super) fn reverified(&mut self, job: JobId, i: u64, digest: u64) -> Option<SpotEvent> {
        let (worker, old) = self.suspect.remove(&i)?;
        Some(SpotEvent::Reverified {
            job,
            unit: self.unit(i),
            worker,
            identical: old == digest,
        })
    }
}

impl Scheduler {
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

    /// Checks `worker` has passed (its copy matched another worker's): what its units'
    /// check rate is set by ([`crate::spot::worker_check_rate`]). 0 for a worker never seen.
    pub fn verified_checks(&self, worker: WorkerId) -> u64 {
        self.records.get(&worker).map_or(0, |r| r.verified)
    }

    /// Notes how `worker` leases: alone (the only worker sharing the queue) or not.
    pub(super) fn note_leasing(&mut self, worker: WorkerId, alone: bool) {
        self.records.entry(worker).or_default().alone = alone;
    }

    /// Whether `worker`'s copy of unit `i` of `job_id` (a live frame `frame`), not merged
    /// yet, is held for a comparison with another worker's: a unit with copies held
    /// already, one of the job-wide sample ([`is_spot_checked`]), one of the worker's
    /// own schedule ([`worker_selects`], not for a worker alone), or a statistical outlier
    /// against its tile ([`unit_is_outlier`], not for adaptive jobs, whose passes are not
    /// independent of the decision to render them). Spot checks disabled (fraction 0):
    /// none.
    pub(super) fn wants_check(
        &self,
        worker: WorkerId,
        job_id: JobId,
        i: u64,
        frame: usize,
        result: &UnitResult,
    ) -> bool {
        let f = self.spot_fraction;
        let Some(job) = self.jobs.get(&job_id) else {
            return false;
        };
        if f <= 0.0 || job.done.contains(&i) {
            return false;
        }
        let unit: &WorkUnit = &result.unit;
        if job.checks.contains_key(&i) || is_spot_checked(f, job_id, unit) {
            return true;
        }
        let by_record = worker != WorkerId::MAX
            && self
                .records
                .get(&worker)
                .is_some_and(|r| !r.alone && worker_selects(r.verified, f, job_id, unit));
        by_record
            || (job.adaptive.is_none()
                && match job.frames.get(frame) {
                    Some(FrameSlot::Live(acc)) => acc
                        .tiles()
                        .get(unit.tile as usize)
                        .is_some_and(|t| unit_is_outlier(t.pixels(), &result.pass_means)),
                    _ => false,
                })
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
    /// same worker neither counts them twice nor tries to repair what cannot be. Its
    /// check record starts again from nothing ([`crate::spot::BURN_IN_CHECKS`]). Returns
    /// false if it was not quarantined.
    pub fn lift_quarantine(&mut self, worker: WorkerId) -> bool {
        if !self.quarantined.remove(&worker) {
            return false;
        }
        // Back on probation: all its units are checked again until it passes the burn-in.
        self.records.remove(&worker);
        for job in self.jobs.values_mut() {
            job.unverified.retain(|_, (w, _)| *w != worker);
        }
        true
    }

    /// A validated copy of spot-checked unit `i` (not merged yet) from `worker`: held
    /// with the others; once two agree ([`SpotCheck::agreed`]) the workers whose copy
    /// differs are quarantined and the agreed copy is merged.
    pub(super) fn hold_copy(
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
        job.forget_lease(i, lease_id);
        if !job.checks.contains_key(&i) && !is_spot_checked(self.spot_fraction, job_id, &unit) {
            // Held by the worker's schedule or the outlier test: one more copy to render
            // than the job-wide sample counted.
            job.copies_total += 1;
        }
        let check = job.checks.entry(i).or_default();
        let Some(fresh) = check.add(worker, lease_id, digest, result) else {
            return Ok(Submitted::Held);
        };
        job.extra_copies += 1;
        let Some(k) = check.agreed() else {
            if fresh && check.groups.len() > 1 {
                self.spot_events.push(SpotEvent::Disputed {
                    job: job_id,
                    unit,
                    workers: check.workers(),
                });
            }
            // Wanted again, from a worker with no copy (unless a lease is out already).
            if !job.leased.contains_key(&i) {
                job.returned.insert(i);
            }
            return Ok(Submitted::Held);
        };
        let Some(check) = job.checks.remove(&i) else {
            return Ok(Submitted::Held);
        };
        let verdict = check.settle(k);
        for &w in &verdict.dissenters {
            let reason = format!(
                "spot check: its copy of job {job_id} frame {} tile {} passes {}..{} differs \
                 from the copy {} other worker(s) agree on",
                unit.frame,
                unit.tile,
                unit.first_pass,
                unit.end_pass(),
                verdict.agreed.workers.len()
            );
            self.quarantine(w, &reason);
        }
        self.merge_agreed(job_id, lease_id, i, digest, verdict)
    }

    /// Merges the copy spot-checked unit `i` was settled on (`digest`: of the copy that
    /// settled it) and reports the check. A copy only its own worker vouched for
    /// ([`SpotOutcome::Alone`]) stays unverified, repaired if that worker is found faulty.
    fn merge_agreed(
        &mut self,
        job_id: JobId,
        lease_id: u64,
        i: u64,
        digest: u64,
        verdict: Verdict,
    ) -> Result<Submitted, SubmitError> {
        let Verdict {
            agreed, outcome, ..
        } = verdict;
        // Every copy held for `i` is of the same unit (`Job::index` is a bijection).
        let unit = agreed.result.unit;
        // Quarantine may have dropped this unit's tile; the frame is still live.
        let job = self
            .jobs
            .get_mut(&job_id)
            .ok_or(SubmitError::UnknownLease(lease_id))?;
        let frame = job.frame_index(i);
        let offered = job.offer(frame, agreed.result)?;
        job.returned.remove(&i);
        job.done.insert(i);
        // The unit counts in `done` now; its other copies stay extra work.
        job.extra_copies = job.extra_copies.saturating_sub(1);
        if outcome == SpotOutcome::Alone {
            // Not verified by anyone else: repaired if its worker is found faulty later.
            job.unverified.insert(i, (agreed.workers[0], digest));
        } else {
            // Every worker whose copy is the agreed one passed a check.
            let agreeing: BTreeSet<WorkerId> = agreed.workers.iter().copied().collect();
            for w in agreeing {
                if w != WorkerId::MAX {
                    self.records.entry(w).or_default().verified += 1;
                }
            }
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
}
