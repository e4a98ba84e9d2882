//! Accepting a worker's result (ARCHITECTURE.md §9, steps 8 to 10): checked against its
//! lease, merged in pass order, the tile's checkpoint committed, faults recorded; only
//! then is the worker told whether it was accepted.
//!
//! [`Coordinator::accept_result`] runs these steps, each a function with one job:
//! `submit` (validate against the lease and merge), `record_merge` (rejected-sample
//! counts, tile error, the checkpoint to write), `history_point`, `record_fault`,
//! `apply_spot_events` (spot-check outcomes, quarantines and the tiles they dropped),
//! and `Coordinator::write_back` (the store writes, in that order).

use std::sync::{Arc, OnceLock};

use tessera_api::{HistoryPoint, JobState};
use tessera_farm::{
    JobId, SpotEvent, SpotOutcome, SubmitError, Submitted, UnitResult, WorkUnit, WorkerId,
};

use super::jobs::spp_so_far;
use super::Coordinator;
use crate::state::{now_ms, quarantine_key, tile_error, Farm, TileRejected};
use crate::store::{
    FaultEvent, FaultKind, QuarantineRecord, StoreError, TileCheckpoint, UnitDigest,
};

/// History points are recorded at most this often per job (plus the last one).
const HISTORY_INTERVAL_MS: u64 = 200;
/// Seconds a worker may report rendering a unit beyond the time since its lease was
/// issued (clocks, the lease's trip to the worker): more is not counted.
pub const RENDER_SECONDS_SLACK: f64 = 60.0;

/// What a worker delivered for a lease, decoded by the gRPC service.
#[derive(Debug)]
pub struct Delivery {
    /// The worker.
    pub worker: WorkerId,
    /// The lease (fencing token) the result answers.
    pub lease_id: u64,
    /// The lease's seal as the worker sent it back (`SubmitResultRequest.fence`): the
    /// result is taken only if it verifies for the lease, its job, the result's unit and
    /// the worker's registered name ([`crate::trust::FenceKey`]).
    pub fence: Vec<u8>,
    /// The job the worker says the lease is of: only trusted for leases of the previous
    /// run, which this run's scheduler never issued (ARCHITECTURE.md §9, restart).
    pub job_hint: JobId,
    /// The result, or why it did not decode.
    pub result: Result<UnitResult, String>,
    /// Seconds the worker spent rendering it, as it reports them; counted at most as the
    /// time since the lease was issued plus [`RENDER_SECONDS_SLACK`].
    pub render_seconds: f64,
    /// Pixel-passes the worker says it traced for it (0: not reported), for `/metrics`.
    pub traced_pixel_passes: u64,
}

/// A result the coordinator took: merged (and checkpointed), or an identical copy of a
/// unit already merged.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Accepted {
    /// Merged, or buffered until the passes before it arrive; durable.
    Merged,
    /// A duplicate of a merged unit, identical to it by digest.
    Duplicate,
    /// A copy of a unit of a frame that is complete and released from memory: the unit
    /// is merged; this copy is not compared.
    Late,
    /// A valid copy of a spot-checked unit, held until another worker's copy agrees
    /// (ARCHITECTURE.md §6); not durable yet.
    Held,
}

impl Accepted {
    /// The reason text sent to the worker with `accepted = true`.
    pub fn reason(self) -> &'static str {
        match self {
            Self::Merged => "",
            Self::Duplicate => "duplicate (identical)",
            Self::Late => "late: the frame is complete",
            Self::Held => "held for a spot check",
        }
    }
}

/// Why a result was refused. The text is the reason sent to the worker.
#[derive(Debug, thiserror::Error)]
pub enum Rejected {
    /// The result is malformed: it did not decode, or has the wrong size or non-finite
    /// or negative values. A fault of the worker.
    #[error("{0}")]
    InvalidResult(String),
    /// The lease is of no job this coordinator knows. A fault of the worker.
    #[error("lease {0} is unknown")]
    UnknownLease(u64),
    /// The scheduler did not issue this lease for exactly this unit. A fault of the
    /// worker.
    #[error("{0}")]
    StaleLease(SubmitError),
    /// The lease's seal does not verify: the lease was not issued for this job and unit
    /// to a worker of this name (or the seal is missing). A fault of the worker that
    /// submitted it, never of the lease's holder.
    #[error("lease {0} was not issued to this worker for this unit (its fence does not verify)")]
    NotSealed(u64),
    /// A lease of the previous run delivered after the restart's grace period: its run is
    /// over. Not counted as a fault (a worker may have rendered long); the unit is
    /// leased again.
    #[error("lease {0} is of the coordinator's previous run, whose grace period is over")]
    PreviousRunOver(u64),
    /// The job was canceled; not the worker's fault.
    #[error("job {0} was canceled")]
    Canceled(JobId),
    /// A previous run's lease for a frame waiting for the memory budget; not the
    /// worker's fault, the unit is leased again.
    #[error("{0}")]
    Deferred(SubmitError),
    /// A duplicate of a merged unit that differs from it. A fault of the worker.
    #[error("duplicate differs from the merged copy: faulty worker")]
    Mismatch,
    /// The worker is quarantined: its results are not used (the fault that quarantined
    /// it was counted once, then).
    #[error("quarantined: {0}")]
    Quarantined(String),
    /// The checkpoint could not be written; the unit will be leased again.
    #[error("the coordinator could not store the result: {0}")]
    Store(StoreError),
    /// The farm state's lock was poisoned.
    #[error("farm state poisoned")]
    Poisoned,
}

impl Rejected {
    /// The fault recorded against the worker, if it is one.
    pub fn fault_kind(&self) -> Option<FaultKind> {
        match self {
            Self::InvalidResult(_) => Some(FaultKind::InvalidResult),
            Self::UnknownLease(_) | Self::StaleLease(_) | Self::NotSealed(_) => {
                Some(FaultKind::LeaseViolation)
            }
            Self::Mismatch => Some(FaultKind::DuplicateMismatch),
            Self::Canceled(_)
            | Self::Deferred(_)
            | Self::Quarantined(_)
            | Self::PreviousRunOver(_)
            | Self::Store(_)
            | Self::Poisoned => None,
        }
    }
}

/// What accepting a result leaves to write to the store, taken under the farm lock.
#[derive(Default)]
struct Writes {
    /// Tiles dropped by a quarantine, in their state after this result (written before
    /// `checkpoint`, which is newer).
    resets: Vec<TileCheckpoint>,
    checkpoint: Option<TileCheckpoint>,
    history: Option<StoredPoint>,
    faults: Vec<FaultEvent>,
    /// Workers quarantined by this result's spot checks, for the store's quarantine list.
    quarantines: Vec<QuarantineRecord>,
    finished: Option<JobId>,
}

/// A result the scheduler took.
struct Merged {
    job: JobId,
    unit: WorkUnit,
    /// The tile's merged passes before it.
    before: u32,
    submitted: Submitted,
}

impl Coordinator {
    /// Validates, merges and durably checkpoints a worker's result (ARCHITECTURE.md §9,
    /// steps 8 to 10).
    ///
    /// Checkpoints are group-committed: the merge queues the tile's checkpoint (under the
    /// farm lock, so the queue is in merge order), and whoever next holds the store's
    /// write lock with its own checkpoint still queued writes every queued checkpoint in
    /// one transaction (the newest of each tile only) and tells each waiter how it went.
    /// So a fleet's results cost one commit per batch, not one per result, and no worker
    /// hears "accepted" before its result is durable.
    pub async fn accept_result(&self, d: Delivery) -> Result<Accepted, Rejected> {
        let (outcome, writes, queued) = {
            let mut farm = self.inner.farm.lock().map_err(|_| Rejected::Poisoned)?;
            let trust = Trust {
                fence: &self.inner.fence,
                previous_run_until_ms: self.inner.previous_run_until_ms,
                uptime_seconds: self.uptime_seconds(),
            };
            let (outcome, mut writes) = merge_delivery(&mut farm, d, now_ms(), &trust);
            // Pushed together, so they are committed in one batch: waiting for the last
            // one's outcome waits for all.
            let mut queued = None;
            let all = std::mem::take(&mut writes.resets)
                .into_iter()
                .chain(writes.checkpoint.take());
            let mut pending = self.inner.pending.lock().map_err(|_| Rejected::Poisoned)?;
            for checkpoint in all {
                let key = (checkpoint.job, checkpoint.frame);
                let slot = Arc::new(OnceLock::new());
                pending.push(PendingCheckpoint {
                    checkpoint,
                    outcome: slot.clone(),
                });
                queued = Some((key, slot));
            }
            drop(pending);
            (outcome, writes, queued)
        };
        // A merge may open units (an adaptive decision, a tile emptied for repair after a
        // quarantine): tell the lease requests waiting for work. A copy held for a spot
        // check opens its unit to the other workers only: one wake-up could go to a request
        // of the worker that delivered it, which may not take the copy, so all are woken
        // (a spot-checked last unit otherwise finished a long poll late).
        let held = matches!(outcome, Ok(Accepted::Held));
        self.work_changed(held || !writes.quarantines.is_empty());
        // One writer at a time, taking the queue in merge order: a newer checkpoint of a
        // tile is never overwritten by an older one.
        let write = self.inner.write.lock().await;
        if let Some(((job, frame), slot)) = &queued {
            if slot.get().is_none() {
                self.commit_pending().await?;
            }
            let failure = match slot.get() {
                Some(Ok(())) => None,
                Some(Err(e)) => Some(e.clone()),
                None => Some("the checkpoint was not written".to_string()),
            };
            if let Some(e) = failure {
                if let Ok(mut farm) = self.inner.farm.lock() {
                    if let Some(rt) = farm.runtime.get_mut(job) {
                        rt.unsaved_checkpoints = true;
                    }
                }
                return Err(Rejected::Store(StoreError::Failing(e)));
            }
            // A complete frame's checkpoints are durable now: its memory goes back to
            // the budget, its image is read from the store (ARCHITECTURE.md §6, memory).
            // Not after a failed checkpoint of the job: memory then holds passes the
            // store does not.
            let mut farm = self.inner.farm.lock().map_err(|_| Rejected::Poisoned)?;
            let saved = farm
                .runtime
                .get(job)
                .is_some_and(|rt| !rt.unsaved_checkpoints);
            if saved {
                // An adaptive job's status and history read the first frame's policy
                // state: keep its final figures before the state leaves memory.
                let first = farm.runtime.get(job).map(|rt| rt.job().frames.start);
                let summary = farm
                    .scheduler
                    .adaptive_frame(*job, *frame)
                    .filter(|a| first == Some(*frame) && a.finished())
                    .map(adaptive_summary);
                if farm.scheduler.release_frame(*job, *frame) {
                    tracing::debug!(job, frame, "frame complete and released");
                    // Its memory may admit the job's next frame.
                    self.work_changed(true);
                    if let (Some(summary), Some(rt)) = (summary, farm.runtime.get_mut(job)) {
                        rt.adaptive_summary = summary;
                    }
                }
            }
        }
        self.write_back(&writes).await;
        drop(write);
        if let Some(job) = writes.finished {
            match self.set_state(job, JobState::Done, None).await {
                Ok(()) => tracing::info!(job, "job done"),
                Err(e) => tracing::error!(job, error = %e, "cannot mark job done"),
            }
        }
        outcome
    }

    /// Writes every queued checkpoint in one transaction, the newest of each tile only,
    /// and sets each one's outcome. The caller holds the write lock.
    async fn commit_pending(&self) -> Result<(), Rejected> {
        let batch =
            std::mem::take(&mut *self.inner.pending.lock().map_err(|_| Rejected::Poisoned)?);
        // Later in the queue is newer (merge order): keep the last of each tile.
        let mut seen = std::collections::HashSet::new();
        let mut newest: Vec<&PendingCheckpoint> = batch
            .iter()
            .rev()
            .filter(|p| seen.insert((p.checkpoint.job, p.checkpoint.frame, p.checkpoint.tile)))
            .collect();
        newest.reverse();
        let refs: Vec<_> = newest.iter().map(|p| p.checkpoint.as_ref()).collect();
        let result = self.inner.store.save_tiles(&refs).await;
        if let Err(e) = &result {
            tracing::error!(checkpoints = refs.len(), error = %e, "checkpoint failed");
            // Another coordinator took the store over (`crate::ha`): stop at once rather
            // than when the lock check notices, so that these results' workers are told
            // to take them to the new one instead of "not accepted".
            if matches!(e, StoreError::NotLeader { .. }) {
                self.depose(e.to_string());
            }
        }
        let shared = result.map_err(|e| e.to_string());
        for p in &batch {
            let _ = p.outcome.set(shared.clone());
        }
        Ok(())
    }

    /// Writes the history point, the fault events and the quarantines; none refuses the
    /// result. A quarantine that is not stored still holds in memory until a restart.
    async fn write_back(&self, w: &Writes) {
        let store = &self.inner.store;
        if let Some((job, point, estimator)) = &w.history {
            if let Err(e) = store.append_history(*job, *point, Some(estimator)).await {
                tracing::warn!(job, error = %e, "history point not stored");
            }
        }
        for f in &w.faults {
            if let Err(e) = store.record_fault(f).await {
                tracing::warn!(error = %e, "fault event not stored");
            }
        }
        for q in &w.quarantines {
            if let Err(e) = store.record_quarantine(q).await {
                tracing::error!(
                    name = %q.worker,
                    error = %e,
                    "quarantine not stored: a restarted coordinator will trust the worker again"
                );
            }
        }
    }
}

/// A merged tile's checkpoint waiting for the next group commit
/// ([`Coordinator::accept_result`]), and where its outcome goes.
pub(crate) struct PendingCheckpoint {
    checkpoint: TileCheckpoint,
    outcome: Arc<OnceLock<Result<(), String>>>,
}

/// What [`merge_delivery`] checks a delivery's lease against.
struct Trust<'a> {
    /// The key of the lease seals.
    fence: &'a crate::trust::FenceKey,
    /// Leases of the previous run are taken until this, Unix ms.
    previous_run_until_ms: u64,
    /// Seconds since this run started: the longest a lease this run no longer holds can
    /// have been rendering in it.
    uptime_seconds: f64,
}

/// Everything done under the farm lock: find the lease's job, check the lease's seal,
/// merge, and collect what the store must learn.
fn merge_delivery(
    farm: &mut Farm,
    d: Delivery,
    now: u64,
    trust: &Trust<'_>,
) -> (Result<Accepted, Rejected>, Writes) {
    let mut writes = Writes::default();
    // The scheduler knows the job of this run's leases, outstanding or lapsed; a lease of
    // the previous run is adopted under the job the worker names (its seal says whether
    // that is the job it was issued for).
    let this_run = farm.scheduler.lease_job(d.lease_id);
    let previous_run = this_run.is_none() && farm.scheduler.is_previous_run_lease(d.lease_id);
    let job = this_run.or_else(|| (previous_run && d.job_hint != 0).then_some(d.job_hint));
    let (worker, lease_id) = (d.worker, d.lease_id);
    // The longest the worker can have rendered it: since the lease was issued, or since
    // this run started for a lease it no longer holds.
    let max_seconds = farm
        .scheduler
        .outstanding(lease_id)
        .map_or(trust.uptime_seconds, |l| {
            now.saturating_sub(l.leased_ms) as f64 / 1000.0
        })
        + RENDER_SECONDS_SLACK;
    let render_seconds = d.render_seconds.min(max_seconds);
    let known = farm.workers.contains_key(&worker);
    let worker_name = farm
        .workers
        .get(&worker)
        .map(|w| w.name.clone())
        .unwrap_or_else(|| format!("worker {worker}"));
    if !known {
        // A worker forgotten after it was lost, or one of a previous run: its result is
        // still checked and merged like any other, and said so.
        tracing::warn!(
            worker,
            lease_id,
            "result from an unknown or forgotten worker"
        );
    }
    // A diagnostic the worker reports, not validated by the farm: a unit cannot drop
    // more samples than it traced, and an absurd count must neither overflow the sums nor
    // fail the checkpoint after the merge (found by tests/fuzz_grpc.rs).
    let per_pass = job
        .and_then(|j| farm.jobs.get(&j))
        .map_or(1, |e| u64::from(e.plan.samples_per_pass));
    let rejected_samples = d.result.as_ref().map_or(0, |r| {
        r.rejected_samples
            .min((r.pass_means.len() as u64).saturating_mul(per_pass))
    });
    // The seal binds the lease to its job, its unit and the name of the worker it was
    // issued to: a guessed lease id, another worker's lease or a previous run's lease
    // replayed for another unit is refused here, as the submitter's fault (ARCHITECTURE.md
    // §6). A malformed result or an unknown lease is left to `submit` to name.
    let sealed = match (&d.result, job) {
        (Ok(r), Some(j)) => {
            known
                && trust
                    .fence
                    .verify(&d.fence, lease_id, j, &r.unit, &worker_name)
        }
        _ => true,
    };
    let merged = if !sealed {
        Err(Rejected::NotSealed(lease_id))
    } else if previous_run && now >= trust.previous_run_until_ms {
        Err(Rejected::PreviousRunOver(lease_id))
    } else {
        submit(farm, (worker, lease_id), job, d.result)
    };
    // Spot checks may have ended, quarantined a worker and dropped tiles, whatever became
    // of this result.
    apply_spot_events(farm, now, &mut writes);
    let merged = match merged {
        // Not the worker's fault: the job went away. Nothing is recorded.
        Err(Rejected::Canceled(j)) => {
            tracing::info!(
                worker,
                lease_id,
                job = j,
                "late result for a canceled job dropped"
            );
            return (Err(Rejected::Canceled(j)), writes);
        }
        other => other,
    };
    // Only a registered worker is credited; an unknown id must not create a listing.
    let mut w = farm.workers.get_mut(&worker);
    if let Some(w) = w.as_deref_mut() {
        w.last_seen_ms = now;
        w.last_result_ms = now;
    }
    if let Ok(m) = &merged {
        // Rendering time spent for the job, merged or held for a spot check: the worker's
        // and the job's (the ETA's unit time).
        if matches!(m.submitted, Submitted::Accepted | Submitted::Held)
            && render_seconds.is_finite()
            && render_seconds > 0.0
        {
            if let Some(w) = w.as_deref_mut() {
                w.render_seconds += render_seconds;
            }
            if let Some(rt) = farm.runtime.get_mut(&m.job) {
                rt.unit_seconds.0 += render_seconds;
                rt.unit_seconds.1 += 1;
            }
        }
    }
    let outcome = match merged {
        Ok(m) => match m.submitted {
            Submitted::Accepted => {
                if let Some(w) = w {
                    w.units_done += 1;
                    // Bounded by the unit's size when decoded.
                    w.pixel_passes = w.pixel_passes.saturating_add(d.traced_pixel_passes);
                }
                writes.checkpoint = record_merge(farm, &m, rejected_samples);
                if let Some(rt) = farm.runtime.get_mut(&m.job) {
                    rt.merges += 1;
                }
                let complete = farm.scheduler.is_complete(m.job);
                writes.history = history_point(farm, m.job, now, complete);
                writes.finished = complete.then_some(m.job);
                Ok(Accepted::Merged)
            }
            Submitted::Duplicate { identical: true } => {
                // Typically a worker that stalled past its lease while another rendered
                // the unit: harmless, but visible.
                tracing::warn!(
                    worker,
                    lease_id,
                    job = m.job,
                    "late result: the unit was already merged (identical copy dropped)"
                );
                Ok(Accepted::Duplicate)
            }
            Submitted::Duplicate { identical: false } => Err(Rejected::Mismatch),
            Submitted::Late => {
                tracing::info!(
                    worker = d.worker,
                    lease = d.lease_id,
                    "late result for a complete frame"
                );
                Ok(Accepted::Late)
            }
            Submitted::Held => {
                // Rendering time spent (counted above), but not a merged unit (`units_done`
                // and `tessera_units_merged_total` count each unit once, when it merges).
                tracing::debug!(worker, lease_id, job = m.job, "copy held for a spot check");
                Ok(Accepted::Held)
            }
        },
        Err(r) => Err(r),
    };
    if let Err(r) = &outcome {
        writes.faults.extend(record_fault(
            farm,
            (worker, lease_id),
            worker_name,
            job,
            r,
            now,
        ));
    }
    (outcome, writes)
}

/// Validates a result against its lease and offers it to the scheduler, which checks the
/// unit, the size and the values and merges it in pass order (ARCHITECTURE.md §2).
fn submit(
    farm: &mut Farm,
    (worker, lease_id): (WorkerId, u64),
    job: Option<JobId>,
    result: Result<UnitResult, String>,
) -> Result<Merged, Rejected> {
    let result = result.map_err(Rejected::InvalidResult)?;
    let job = job.ok_or(Rejected::UnknownLease(lease_id))?;
    let unit = result.unit;
    let before = farm
        .scheduler
        .frame(job, unit.frame)
        .and_then(|f| f.tile(unit.tile))
        .map_or(0, |t| t.merged_passes());
    match farm.scheduler.submit_from(worker, lease_id, job, result) {
        Ok(submitted) => Ok(Merged {
            job,
            unit,
            before,
            submitted,
        }),
        Err(SubmitError::Invalid(e)) => Err(Rejected::InvalidResult(e.to_string())),
        Err(SubmitError::Canceled(j)) => Err(Rejected::Canceled(j)),
        Err(e @ SubmitError::NotResident(_)) => Err(Rejected::Deferred(e)),
        Err(SubmitError::Quarantined(w)) => Err(Rejected::Quarantined(
            farm.workers
                .get(&w)
                .and_then(|e| e.quarantined.clone())
                .unwrap_or_else(|| "found faulty by a spot check".into()),
        )),
        Err(e) => Err(Rejected::StaleLease(e)),
    }
}

/// After a merge: counts the unit's rejected samples, updates the tile's error, and
/// returns the tile's checkpoint if its merged pass count changed (a buffered unit
/// changes nothing durable yet).
fn record_merge(farm: &mut Farm, m: &Merged, rejected_samples: u64) -> Option<TileCheckpoint> {
    let (job, unit) = (m.job, m.unit);
    let acc = farm.scheduler.frame(job, unit.frame)?;
    let rt = farm.runtime.get_mut(&job)?;
    let tile = &acc.tiles()[unit.tile as usize];
    let fi = (unit.frame - rt.job().frames.start) as usize;
    let rejected = rt
        .tile_rejected
        .get_mut(fi)
        .and_then(|f| f.get_mut(unit.tile as usize))
        .map(|r| {
            r.accept(unit.first_pass, rejected_samples, tile.merged_passes());
            r.merged
        })
        .unwrap_or(0);
    if tile.merged_passes() == m.before {
        return None;
    }
    if let Some(slot) = rt
        .tile_error
        .get_mut(fi)
        .and_then(|f| f.get_mut(unit.tile as usize))
    {
        *slot = tile_error(tile);
    }
    Some(checkpoint_of(farm, job, unit.frame, tile, rejected))
}

/// The checkpoint of a tile's merged state, with the adaptive policy's state of the tile
/// after the same merge for an adaptive job (both are taken under the farm lock,
/// so they are always of the same merge).
fn checkpoint_of(
    farm: &Farm,
    job: JobId,
    frame: u32,
    tile: &tessera_farm::TileAccumulator,
    rejected_samples: u64,
) -> TileCheckpoint {
    let adaptive = farm
        .scheduler
        .adaptive_frame(job, frame)
        .and_then(|f| f.tile(tile.rect().index))
        .map(tessera_farm::AdaptiveTile::checkpoint);
    TileCheckpoint {
        job,
        frame,
        tile: tile.rect().index,
        merged_passes: tile.merged_passes(),
        pixels: tile.pixels().to_vec(),
        units: tile
            .merged_units()
            .map(|(first_pass, pass_count, digest)| UnitDigest {
                first_pass,
                pass_count,
                digest,
            })
            .collect(),
        rejected_samples,
        adaptive,
        bias: tile.bias().map(<[_]>::to_vec),
    }
}

/// Takes what the scheduler's spot checks found during the last submission
/// (ARCHITECTURE.md §6): counts outcomes, marks quarantined workers (a fault event each,
/// and an entry of the quarantine list to store), and for every tile a quarantine
/// dropped, resets the job's per-tile error and rejected-sample counts and queues the
/// tile's checkpoint, so a restart does not bring back the dropped passes.
fn apply_spot_events(farm: &mut Farm, now: u64, writes: &mut Writes) {
    for event in farm.scheduler.take_spot_events() {
        match event {
            SpotEvent::Checked { job, unit, outcome } => match outcome {
                SpotOutcome::Match => farm.spot.matched += 1,
                SpotOutcome::Alone => farm.spot.alone += 1,
                SpotOutcome::Mismatch => {
                    farm.spot.mismatched += 1;
                    if let Some(rt) = farm.runtime.get_mut(&job) {
                        rt.faults += 1;
                    }
                    tracing::warn!(
                        job,
                        ?unit,
                        "spot check mismatch: the agreed copy was merged"
                    );
                }
            },
            SpotEvent::Disputed { job, unit, workers } => {
                tracing::warn!(
                    job,
                    ?unit,
                    ?workers,
                    "spot check: copies differ; waiting for another worker to decide"
                );
            }
            SpotEvent::Quarantined {
                worker,
                reason,
                reset_tiles,
                unrepaired_units,
            } => {
                farm.spot.quarantined += 1;
                farm.spot.tiles_reset += reset_tiles.len() as u64;
                farm.spot.unrepaired += unrepaired_units;
                let name = match farm.workers.get_mut(&worker) {
                    Some(w) => {
                        w.quarantined = Some(reason.clone());
                        w.faults += 1;
                        // Listed by what it registers as, so that it stays quarantined
                        // under a new id, after a restart too. A worker unknown here (a
                        // forgotten one) has no name to list; its id is not reused.
                        let key = quarantine_key(&w.name, w.identity.as_deref());
                        if let std::collections::btree_map::Entry::Vacant(slot) =
                            farm.quarantines.entry(key)
                        {
                            let (worker, identity) = slot.key().clone();
                            let record = QuarantineRecord {
                                worker,
                                identity,
                                reason: reason.clone(),
                                unix_ms: now,
                            };
                            writes.quarantines.push(slot.insert(record).clone());
                        }
                        w.name.clone()
                    }
                    None => format!("worker {worker}"),
                };
                tracing::error!(
                    worker,
                    name = %name,
                    reason = %reason,
                    tiles_reset = reset_tiles.len(),
                    unrepaired_units,
                    "worker quarantined"
                );
                writes.faults.push(FaultEvent {
                    worker: name,
                    job: reset_tiles.first().map(|t| t.0),
                    kind: FaultKind::SpotCheckMismatch,
                    message: reason,
                    unix_ms: now,
                });
                for (job, frame, tile) in reset_tiles {
                    writes.resets.extend(reset_tile(farm, job, frame, tile));
                }
            }
            SpotEvent::Reverified { identical, .. } => {
                if identical {
                    farm.spot.reverified_identical += 1;
                } else {
                    farm.spot.reverified_differed += 1;
                }
            }
        }
    }
}

/// The job's bookkeeping of a tile the scheduler dropped: its error and rejected-sample
/// counts start again, its images change, and its checkpoint (of what is merged in it now)
/// is returned to be written.
fn reset_tile(farm: &mut Farm, job: JobId, frame: u32, tile: u32) -> Option<TileCheckpoint> {
    let t = farm.scheduler.frame(job, frame)?.tile(tile)?;
    let rt = farm.runtime.get_mut(&job)?;
    let fi = frame.checked_sub(rt.job().frames.start)? as usize;
    if let Some(slot) = rt
        .tile_error
        .get_mut(fi)
        .and_then(|f| f.get_mut(tile as usize))
    {
        *slot = tile_error(t);
    }
    if let Some(slot) = rt
        .tile_rejected
        .get_mut(fi)
        .and_then(|f| f.get_mut(tile as usize))
    {
        *slot = TileRejected::default();
    }
    rt.merges += 1;
    Some(checkpoint_of(farm, job, frame, t, 0))
}

/// An adaptive frame's figures for the job's status and history: its mean samples per
/// pixel and its image error estimate, once every pixel has one.
pub(crate) fn adaptive_summary(a: &tessera_farm::AdaptiveFrame) -> (f64, Option<f64>) {
    (
        a.samples_per_pixel().0,
        a.every_pixel_estimated().then(|| a.image_error()),
    )
}

/// The ETA's trend of an adaptive job with a target (`tessera_farm::quote::EtaTrend`):
/// the spread of its first frame's error over the tiles, and the growth of its per-pass
/// figure since half of `spp`. Walks every pixel once, as the history point's summary does.
fn record_trend(rt: &mut crate::state::JobRuntime, a: &tessera_farm::AdaptiveFrame, spp: f64) {
    use tessera_farm::quote::{error_groups, EtaTrend};
    let groups = error_groups(a.tiles().iter().map(|t| (t.rect().width, t.pixels())));
    let (rel_m, per_pass) = EtaTrend::of_groups(&groups);
    rt.eta_trend = Some(EtaTrend::with_growth(
        rel_m,
        per_pass,
        spp,
        rt.per_pass_history.iter().copied(),
    ));
    if let Some(q) = per_pass {
        rt.per_pass_history.push((spp, q));
    }
}

/// The ETA's measurement of an adaptive job with a target (`tessera_farm::quote::AdaptiveEta`,
/// ARCHITECTURE.md §3 "The ETA"): each live frame's pixel work (`quote::pixel_work`, with the
/// heavy extrapolation's exponent from the trend just recorded), frames released since
/// their last measurement counted as done, frames not begun as the mean of those measured;
/// the rate and the drift read against the job's earlier measurements. Walks every pixel
/// of the live frames once.
fn record_pixel_work(farm: &mut Farm, job: JobId, now: u64) {
    use tessera_farm::quote::{pixel_work, AdaptiveEta, EtaSample, PixelWork, TailClass};
    let Some(rt) = farm.runtime.get(&job) else {
        return;
    };
    let first = rt.job().frames.start;
    let count = rt.job().frames.count() as usize;
    let trend = rt.eta_trend.unwrap_or_default();
    let gamma = match trend.verdict().0 {
        TailClass::Heavy => trend.growth.map_or(0.0, |g| g.max(1.0).log2()),
        _ => 0.0,
    };
    let live: Vec<(usize, PixelWork)> = (0..count)
        .filter_map(|k| {
            let f = farm.scheduler.adaptive_frame(job, first + k as u32)?;
            Some((k, pixel_work(f, gamma)))
        })
        .collect();
    let Some(rt) = farm.runtime.get_mut(&job) else {
        return;
    };
    if rt.eta_frames.len() != count {
        rt.eta_frames = vec![None; count];
    }
    // A frame measured before and not live now was released: done, nothing left.
    for (k, slot) in rt.eta_frames.iter_mut().enumerate() {
        if let Some(w) = slot {
            if !live.iter().any(|(j, _)| *j == k) {
                *w = PixelWork {
                    done: w.done,
                    ..PixelWork::default()
                };
            }
        }
    }
    for (k, w) in &live {
        rt.eta_frames[*k] = Some(*w);
    }
    let seen: Vec<PixelWork> = rt.eta_frames.iter().flatten().copied().collect();
    if seen.is_empty() {
        return;
    }
    let unseen = rt.eta_frames.iter().filter(|f| f.is_none()).count() as f64;
    let n = seen.len() as f64;
    let mean = |f: fn(&PixelWork) -> f64| seen.iter().map(f).sum::<f64>() / n;
    let mut work = seen.iter().fold(PixelWork::default(), |a, w| a.plus(*w));
    if unseen > 0.0 {
        // Frames not begun: each as the frames measured so far, done and left.
        let total = mean(|w| w.total());
        work.left += unseen * total;
        work.left_heavy += unseen * (total - mean(|w| w.left) + mean(|w| w.left_heavy));
        work.left_mean += unseen * (total - mean(|w| w.left) + mean(|w| w.left_mean));
        work.left_var += unseen * mean(|w| w.left_var);
        work.budget += unseen * total.max(mean(|w| w.done + w.budget));
    }
    let elapsed = rt.elapsed_seconds(now);
    let measured = AdaptiveEta::measure(work, elapsed, &rt.eta_samples, 0.0);
    rt.eta_samples.push(EtaSample {
        elapsed_seconds: elapsed,
        done: work.done,
        total: work.total(),
    });
    rt.eta_adaptive = Some((measured, now));
}

/// A job's history point to store, with the name of the estimator of its error estimate.
pub(crate) type StoredPoint = (JobId, HistoryPoint, String);

/// A convergence-history point (spp, image error, elapsed seconds), at most every
/// [`HISTORY_INTERVAL_MS`] and at completion (ARCHITECTURE.md §9, step 10), with the name
/// of the estimator its error estimate is (stored with it: a job read back from the
/// store names the estimate it shows, not the reading build's estimator).
pub(crate) fn history_point(
    farm: &mut Farm,
    job: JobId,
    now: u64,
    complete: bool,
) -> Option<StoredPoint> {
    let p = farm.scheduler.progress(job)?;
    let rt = farm.runtime.get_mut(&job)?;
    if !complete && now < rt.last_history_ms + HISTORY_INTERVAL_MS {
        return None;
    }
    rt.last_history_ms = now;
    let (spp, error_estimate) = match farm.scheduler.adaptive_frame(job, rt.job().frames.start) {
        Some(a) => {
            let summary = adaptive_summary(a);
            rt.adaptive_summary = summary;
            if rt.job().target_error.is_some() {
                record_trend(rt, a, summary.0);
            }
            summary
        }
        // The first frame finished and was released: its final figures.
        None if rt.job().adaptive_settings().is_some() => rt.adaptive_summary,
        None => {
            // The estimate the status names, of each live frame every pixel of which has
            // an estimate (a walk over its pixels, as the adaptive summary's).
            let first = rt.job().frames.start;
            for (k, slot) in rt.frame_error.iter_mut().enumerate() {
                let tiles = rt.tile_error.get(k).map(Vec::as_slice).unwrap_or(&[]);
                if tiles.iter().any(|&(_, c)| c == 0) {
                    continue;
                }
                if let Some(acc) = farm.scheduler.frame(job, first + k as u32) {
                    *slot = Some(acc.image_error()).filter(|e| e.is_finite());
                }
            }
            (
                spp_so_far(&rt.resolved, p.passes_done, rt.job().frames.count()),
                rt.error_estimate(),
            )
        }
    };
    let point = HistoryPoint {
        elapsed_seconds: rt.elapsed_seconds(now),
        spp,
        error_estimate,
    };
    rt.history.push(point);
    let name = rt.resolved.error_estimator_name();
    if rt.job().target_error.is_some() && rt.job().adaptive_settings().is_some() && !complete {
        record_pixel_work(farm, job, now);
    }
    Some((job, point, name))
}

/// Counts a refused result against the worker and its job, and returns the fault event
/// to store (none if the refusal is not the worker's fault).
fn record_fault(
    farm: &mut Farm,
    (worker, lease_id): (WorkerId, u64),
    worker_name: String,
    job: Option<JobId>,
    r: &Rejected,
    now: u64,
) -> Option<FaultEvent> {
    let kind = r.fault_kind()?;
    // Every fault is counted; a worker's fault events are stored and logged at most
    // `FAULTS_PER_WINDOW` per window, so a flood of bogus results costs neither the
    // store's rows nor the log's lines (ARCHITECTURE.md §6).
    let mut allowed = true;
    if let Some(w) = farm.workers.get_mut(&worker) {
        w.faults += 1;
        allowed = w.fault_budget.allow(now);
    }
    if let Some(rt) = job.and_then(|j| farm.runtime.get_mut(&j)) {
        rt.faults += 1;
    }
    if !allowed {
        let first = farm
            .workers
            .get(&worker)
            .is_some_and(|w| w.fault_budget.first_refused_in_window());
        if first {
            tracing::warn!(
                worker,
                per_window = crate::trust::FAULTS_PER_WINDOW,
                window_ms = crate::trust::FAULT_WINDOW_MS,
                "this worker's faults are coming too fast: counted, neither stored nor logged, for the rest of the window"
            );
        }
        return None;
    }
    tracing::warn!(worker, lease_id, kind = kind.as_str(), error = %r, "result refused");
    Some(FaultEvent {
        worker: worker_name,
        job,
        kind,
        message: r.to_string(),
        unix_ms: now,
    })
}
