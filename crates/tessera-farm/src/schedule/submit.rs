//! Results: a result is taken only if it answers a lease issued for exactly its unit
//! (outstanding, lapsed, or of an earlier run of the coordinator), is made canonical (the
//! pixels its lease did not name are zeroed) and is merged once; later copies are compared
//! with the merged one. Copies of spot-checked units go to [`Scheduler::hold_copy`]
//! instead (`spot.rs`).

use super::job::FrameSlot;
use super::{Scheduler, SubmitError, Submitted};
use crate::ids::{JobId, WorkerId};
use crate::merge::{MergeError, Offer};
use crate::plan::FramePlan;
use crate::result::UnitResult;

/// `result` with the pixels outside the set its lease named set to 0 (their pass means
/// and, for vcm and ppm, their bias channel), after checking it whole (a worker is still
/// faulted for a NaN in a pixel it did not have to trace).
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
    // The bias channel is digested too: a worker that traced every pixel reports bias
    // estimates where one that traced only the named pixels reports 0.
    for (k, b) in result.bias.iter_mut().flatten().enumerate() {
        if !wanted.contains(k % n) {
            *b = 0.0;
        }
    }
    Ok(result)
}

impl Scheduler {
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
        // The pixels the unit's lease named, to make every copy canonical.
        let wanted = job
            .adaptive
            .as_ref()
            .and_then(|a| a.frames.get(frame)?.as_ref()?.tile(result.unit.tile))
            .and_then(|t| t.wanted_pixels(result.unit.first_pass, result.unit.pass_count));
        match &job.frames[frame] {
            FrameSlot::Live(_) => {}
            // Complete and checkpointed: the unit is merged; its copy cannot be compared
            // without reading the checkpoint back.
            FrameSlot::Released => {
                self.leases.remove(&lease_id);
                self.lapsed.remove(&lease_id);
                job.forget_lease(i, lease_id);
                return Ok(Submitted::Late);
            }
            // It does not fit: the unit is leased again once it does.
            FrameSlot::Pending => return Err(SubmitError::NotResident(result.unit.frame)),
        }
        let plan = job.plan;
        let result = canonical_masked(result, wanted.as_ref(), &plan)?;
        if self.wants_check(worker, job_id, i, frame, &result) {
            // A live frame's accumulator has the job's plan.
            result.validate(&plan).map_err(MergeError::from)?;
            return self.hold_copy(worker, lease_id, job_id, i, result);
        }
        let job = self
            .jobs
            .get_mut(&job_id)
            .ok_or(SubmitError::UnknownLease(lease_id))?;
        let digest = result.digest();
        let outcome = job.offer(frame, result)?;
        // The unit is done: drop its lease (if the live lease is another worker's, that
        // worker's copy will be compared when it arrives).
        self.leases.remove(&lease_id);
        self.lapsed.remove(&lease_id);
        job.forget_lease(i, lease_id);
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
}
