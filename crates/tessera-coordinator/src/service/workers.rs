//! Workers: registration, leases (ARCHITECTURE.md §9, step 7), heartbeats that extend
//! them, leases given back, and the worker list of `GET /workers`.
//!
//! The gRPC service decodes a worker's request, calls one of these and encodes the
//! answer; nothing here knows the wire format beyond the farm's [`LeasedUnit`].

use std::sync::atomic::Ordering;
use std::time::Duration;

use tessera_api::{JobState, QuarantineInfo, WorkerInfo, WorkerList, WorkerState};
use tessera_farm::{JobId, WorkerId};
use tessera_proto::LeasedUnit;

use super::{Coordinator, LEASE_ID_BLOCK};
use crate::error::{CoordError, CoordResult};
use crate::state::{now_ms, quarantine_key, Farm, WorkerEntry};

/// Longest worker name accepted at registration, in characters.
const MAX_WORKER_NAME: usize = 200;
/// Most units one lease request gets.
const MAX_UNITS_PER_LEASE: u32 = 256;
/// The most render threads a worker is taken to have: more claimed at registration are
/// counted as this many, so one worker's word cannot claim the farm's whole share of
/// work (the tail rule sizes leases by threads).
pub const MAX_WORKER_THREADS: u32 = 1024;
/// Units one worker may hold per render thread it claims: a batch rendering, one
/// prefetched and one being delivered, of at most 64 units per thread each (what the
/// worker asks for), so an honest worker never reaches it.
const HELD_UNITS_PER_THREAD: u64 = 3 * 64;
/// Units one worker may hold at all: three full lease requests. A worker claiming many
/// threads (or lying about them) still leaves the rest of a large job to the others.
const MAX_HELD_UNITS: u64 = 3 * MAX_UNITS_PER_LEASE as u64;
/// How soon a worker asks again during the restart grace period, ms.
const RETRY_IN_GRACE_MS: u32 = 250;
/// How soon an idle worker asks again, ms: a new job starts within ~50 ms.
const RETRY_IDLE_MS: u32 = 50;

/// The longest a lease request is held waiting for work ([`Coordinator::lease_waiting`]):
/// short enough that a worker's request never nears a gRPC deadline and a shutdown
/// never waits long on it.
pub const MAX_LEASE_WAIT_MS: u32 = 2000;
/// How soon a quarantined worker asks again, ms: it gets nothing, so rarely.
const RETRY_QUARANTINED_MS: u32 = 5_000;
/// Returns of a job's leases as unusable (a worker could not load or build its scene)
/// after which the job fails, if enough distinct workers made them
/// ([`UNUSABLE_WORKERS`]).
pub const MAX_UNUSABLE_RETURNS: u32 = 3;
/// Distinct workers (by name and TLS identity) that must have returned a job's leases as
/// unusable before it fails; fewer suffice when fewer live workers are registered (a farm
/// of one worker still fails a scene it cannot use). So one worker, faulty or hostile,
/// cannot fail a job the others render.
pub const UNUSABLE_WORKERS: usize = 3;
/// Longest "unusable" reason kept, in characters.
const MAX_UNUSABLE_REASON: usize = 500;

/// The answer to a heartbeat.
#[derive(Debug, Clone, Default)]
pub struct Heartbeat {
    /// Leases extended: (lease id, new deadline, Unix ms).
    pub extended: Vec<(u64, u64)>,
    /// Leases the worker should drop without submitting: of a canceled job, or unknown.
    /// A lapsed lease of a live job is in neither list (the worker may still deliver it).
    pub cancel: Vec<u64>,
    /// The coordinator is shutting down: finish and deliver the units in hand, then stop.
    pub shutdown: bool,
}

/// The answer to a lease request.
#[derive(Debug, Clone, Default)]
pub struct LeaseGrant {
    /// The units leased, each with what the worker needs to render it.
    pub units: Vec<LeasedUnit>,
    /// When to ask again if `units` is empty, ms (0: at once).
    pub retry_after_ms: u32,
}

impl Coordinator {
    /// Registers a worker; returns its id. The name is at most 200 characters; the
    /// version is cut to 64; the threads are counted as at most [`MAX_WORKER_THREADS`]. A
    /// session secret is issued with the id ([`Coordinator::worker_session`]).
    pub fn register_worker(
        &self,
        name: String,
        threads: u32,
        version: &str,
    ) -> CoordResult<WorkerId> {
        self.register_worker_as(name, threads, version, None)
    }

    /// Registers a worker whose TLS client certificate named it `identity` (its common
    /// name, under mutual TLS), recorded in the worker list.
    pub fn register_worker_as(
        &self,
        name: String,
        threads: u32,
        version: &str,
        identity: Option<String>,
    ) -> CoordResult<WorkerId> {
        if name.chars().count() > MAX_WORKER_NAME {
            return Err(CoordError::invalid_field(
                "name",
                format!("at most {MAX_WORKER_NAME} characters"),
            ));
        }
        let threads = threads.min(MAX_WORKER_THREADS);
        let entry = WorkerEntry {
            name,
            threads,
            last_seen_ms: now_ms(),
            version: version.chars().take(64).collect(),
            identity: identity.map(|i| i.chars().take(MAX_WORKER_NAME).collect()),
            session: crate::trust::new_session(),
            ..WorkerEntry::default()
        };
        let identity = entry.identity.clone();
        let mut farm = self.lock()?;
        // A quarantined worker that registers again (a reconnection, a restart of the
        // worker or of the coordinator: the list is loaded from the store) under the same
        // name and identity stays quarantined: a new id must not launder it.
        let inherited = farm
            .quarantines
            .get(&quarantine_key(&entry.name, entry.identity.as_deref()))
            .map(|q| q.reason.clone());
        let id = farm.register_worker(entry);
        if let Some(reason) = inherited {
            farm.scheduler.quarantine(id, &reason);
            // Nothing of its own to repair: it has rendered nothing under this id.
            farm.scheduler.take_spot_events();
            if let Some(w) = farm.workers.get_mut(&id) {
                w.quarantined = Some(reason);
            }
            tracing::warn!(
                worker = id,
                "quarantined worker registered again; still quarantined"
            );
        }
        drop(farm);
        tracing::info!(
            worker = id,
            threads,
            identity = identity.as_deref(),
            "worker registered"
        );
        Ok(id)
    }

    /// The session secret issued to worker `worker` at registration; `None` for a worker
    /// this run does not know (NOT_FOUND: it must register again).
    pub fn worker_session(&self, worker: WorkerId) -> CoordResult<Option<String>> {
        Ok(self.lock()?.workers.get(&worker).map(|w| w.session.clone()))
    }

    /// Whether a result for lease `lease_id` of the previous run may still be taken
    /// (ARCHITECTURE.md §6): during the restart grace period and one lease duration after
    /// it, and only for a lease id at or below the previous run's high-water mark.
    pub(crate) fn previous_run_open(&self, farm: &Farm, lease_id: u64) -> bool {
        farm.scheduler.is_previous_run_lease(lease_id)
            && now_ms() < self.inner.previous_run_until_ms
    }

    /// A worker's heartbeat: records its throughput and extends the leases it holds.
    pub fn heartbeat(
        &self,
        worker: WorkerId,
        paths_per_second: f64,
        lease_ids: &[u64],
    ) -> CoordResult<Heartbeat> {
        let now = now_ms();
        let mut farm = self.lock()?;
        let w = farm
            .workers
            .get_mut(&worker)
            .ok_or_else(CoordError::unknown_worker)?;
        w.last_seen_ms = now;
        if paths_per_second.is_finite() && paths_per_second >= 0.0 {
            w.paths_per_second = paths_per_second;
        }
        let quarantined = w.quarantined.is_some();
        let extended = farm.scheduler.extend(worker, lease_ids, now);
        // Leases not extended are lapsed, canceled or unknown. Only the last two are
        // cancelled (worker.proto: "drop without submitting"): a lapsed lease of a live job
        // is left out of both lists, so the worker still delivers what it rendered, and
        // the result is merged once or compared with the copy of the worker the unit went
        // to (a worker cut off past its lease, tests/netns_partition.rs). Leases of a
        // previous run of the coordinator (before a restart) are unknown here but their
        // results are still adopted, so the worker keeps rendering them (ARCHITECTURE.md §9).
        let cancel = lease_ids
            .iter()
            .copied()
            .filter(|id| {
                // A quarantined worker's leases were revoked and its results are refused:
                // it should stop rendering them.
                quarantined
                    || !extended.iter().any(|(e, _)| e == id)
                        && !self.previous_run_open(&farm, *id)
                        && !farm.scheduler.is_lapsed_and_wanted(*id)
            })
            .collect();
        Ok(Heartbeat {
            extended,
            cancel,
            shutdown: self.shutting_down(),
        })
    }

    /// Leases up to `max_units` units (clamped to 1..=256) to a worker, in canonical
    /// order, after expiring lapsed leases. The lease ids are reserved durably before
    /// this returns; if that fails, nothing is handed out (the leases lapse).
    pub async fn lease(&self, worker: WorkerId, max_units: u32) -> CoordResult<LeaseGrant> {
        self.lease_waiting(worker, max_units, Duration::ZERO).await
    }

    /// [`Coordinator::lease`] as a long poll: when no unit is available, waits up to
    /// `wait` (at most [`MAX_LEASE_WAIT_MS`]) for one and answers as soon as it may be
    /// (`LeaseRequest.wait_ms`).
    ///
    /// Why: an idle worker otherwise asks again after `RETRY_IDLE_MS`, and a unit that
    /// opens in between waits for that ask. An adaptive job opens units only as its
    /// decisions are taken, a few passes at a time; with one whole-frame tile (bdpt) every
    /// merge is such a moment.
    ///
    /// Wake-ups (`Coordinator::work_changed`): a merged result wakes one waiting request
    /// (and a request that got units wakes the next, so a decision that opens several
    /// units reaches as many workers as take them, without waking every idle worker of a
    /// large fleet for each result); a job queued, leases lapsed or returned, a worker
    /// quarantined or a shutdown wake them all.
    pub async fn lease_waiting(
        &self,
        worker: WorkerId,
        max_units: u32,
        wait: Duration,
    ) -> CoordResult<LeaseGrant> {
        let deadline = tokio::time::Instant::now()
            + wait.min(Duration::from_millis(u64::from(MAX_LEASE_WAIT_MS)));
        loop {
            // Registered before looking, so a wake-up between the look and the wait is
            // not lost.
            let notified = self.inner.work.notified();
            tokio::pin!(notified);
            notified.as_mut().enable();
            let grant = self.lease_now(worker, max_units).await?;
            if !grant.units.is_empty() {
                // There may be more for the next waiting worker.
                self.inner.work.notify_one();
                return Ok(grant);
            }
            if grant.retry_after_ms != RETRY_IDLE_MS || tokio::time::Instant::now() >= deadline {
                // Not idle for want of work (draining, the grace period, quarantine), or
                // waited long enough: the worker asks again later.
                return Ok(grant);
            }
            let waits = &self.inner.lease_waits;
            waits.waiting.fetch_add(1, Ordering::Relaxed);
            let woken = tokio::select! {
                () = &mut notified => true,
                () = tokio::time::sleep_until(deadline) => false,
            };
            waits.waiting.fetch_sub(1, Ordering::Relaxed);
            let ended = if woken { &waits.woken } else { &waits.expired };
            ended.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// Lease requests waiting for work now, and the waits that ended woken and at their
    /// deadline ([`Coordinator::lease_waiting`]; `/metrics`).
    pub fn lease_wait_counts(&self) -> (u64, u64, u64) {
        let w = &self.inner.lease_waits;
        (
            w.waiting.load(Ordering::Relaxed),
            w.woken.load(Ordering::Relaxed),
            w.expired.load(Ordering::Relaxed),
        )
    }

    /// One look at the queue for [`Coordinator::lease_waiting`].
    async fn lease_now(&self, worker: WorkerId, max_units: u32) -> CoordResult<LeaseGrant> {
        let now = now_ms();
        if self.shutting_down() || self.accepting_work().is_err() {
            // Draining, or the store takes no writes (no checkpoint could be saved): the
            // units in hand are delivered, none are started.
            return Ok(LeaseGrant {
                units: Vec::new(),
                retry_after_ms: RETRY_IN_GRACE_MS,
            });
        }
        if self.leasing_paused() {
            // A restarted coordinator waits for workers to deliver what they were rendering.
            if !self.lock()?.workers.contains_key(&worker) {
                return Err(CoordError::unknown_worker());
            }
            return Ok(LeaseGrant {
                units: Vec::new(),
                retry_after_ms: RETRY_IN_GRACE_MS,
            });
        }
        let units = {
            let mut farm = self.lock()?;
            match farm.workers.get_mut(&worker) {
                None => return Err(CoordError::unknown_worker()),
                Some(w) if w.quarantined.is_some() => {
                    w.last_seen_ms = now;
                    return Ok(LeaseGrant {
                        units: Vec::new(),
                        retry_after_ms: RETRY_QUARANTINED_MS,
                    });
                }
                Some(_) => {}
            }
            // A worker asking for work is not draining (any more).
            farm.set_draining(worker, false);
            farm.expire_leases(now);
            let total = farm.sharing_threads(now, self.lost_after_ms());
            let (threads, name) = farm.workers.get(&worker).map_or((1, String::new()), |w| {
                (u64::from(w.threads.max(1)), w.name.clone())
            });
            // What it holds already counts against what one worker may hold.
            let held = farm
                .scheduler
                .leases()
                .filter(|l| l.worker == worker)
                .count() as u64;
            let room = threads
                .saturating_mul(HELD_UNITS_PER_THREAD)
                .min(MAX_HELD_UNITS)
                .saturating_sub(held);
            let max = u64::from(max_units.clamp(1, MAX_UNITS_PER_LEASE)).min(room) as usize;
            let leases = if max == 0 {
                Vec::new()
            } else {
                farm.scheduler.lease_among(worker, now, max, threads, total)
            };
            let fence = &self.inner.fence;
            let units: Vec<LeasedUnit> = leases
                .into_iter()
                .filter_map(|l| {
                    let job = farm.jobs.get(&l.job)?;
                    Some(LeasedUnit {
                        fence: fence.seal(l.lease_id, l.job, &l.unit, &name),
                        lease_id: l.lease_id,
                        deadline_unix_ms: l.deadline_ms,
                        job_id: l.job,
                        scene: job.scene.clone(),
                        settings: job.settings,
                        plan: job.plan,
                        unit: l.unit,
                        // Adaptive jobs: only the pixels still wanted (ARCHITECTURE.md §3).
                        wanted: farm.scheduler.wanted_pixels(l.job, &l.unit),
                        environment: job.environment.clone(),
                    })
                })
                .collect();
            if let Some(w) = farm.workers.get_mut(&worker) {
                w.last_seen_ms = now;
            }
            units
        };
        let mut jobs: Vec<JobId> = units.iter().map(|l| l.job_id).collect();
        jobs.dedup();
        self.after_lease(jobs).await?;
        let retry_after_ms = if units.is_empty() { RETRY_IDLE_MS } else { 0 };
        Ok(LeaseGrant {
            units,
            retry_after_ms,
        })
    }

    /// Leases a worker gives back unrendered (it is shutting down); returns how many
    /// were outstanding. The worker is draining from then on (/workers) until it asks for
    /// work again; a worker stopping announces it this way even with no lease to give
    /// back.
    pub fn return_leases(&self, worker: WorkerId, lease_ids: &[u64]) -> CoordResult<u32> {
        let returned = {
            let mut farm = self.lock()?;
            farm.set_draining(worker, true);
            let before = farm.scheduler.leases().count();
            farm.scheduler.give_back(worker, lease_ids);
            (before - farm.scheduler.leases().count()) as u32
        };
        if returned > 0 {
            self.work_changed(true);
        }
        Ok(returned)
    }

    /// Leases a worker gives back because it cannot render them (`reason`: it could not
    /// load or build their scene). Each job's count of such returns grows; a job that
    /// reaches [`MAX_UNUSABLE_RETURNS`] returns from [`UNUSABLE_WORKERS`] distinct workers
    /// (or from every live worker, when fewer are registered) fails with the reason, so a
    /// scene no worker can use ends its job instead of being leased again forever, and one
    /// worker alone cannot fail a job the others render. The reason is cut to 500
    /// characters and its control characters escaped before it is logged or shown.
    pub async fn return_unusable(
        &self,
        worker: WorkerId,
        lease_ids: &[u64],
        reason: &str,
    ) -> CoordResult<u32> {
        let reason = crate::trust::printable(reason, MAX_UNUSABLE_REASON);
        let now = now_ms();
        let lost_after = self.lost_after_ms();
        let (returned, to_fail) = {
            let mut farm = self.lock()?;
            let who = farm
                .workers
                .get(&worker)
                .map(|w| quarantine_key(&w.name, w.identity.as_deref()));
            // The workers that could vote: registered, heard from lately, trusted.
            let live = farm.trusted_workers(now, lost_after);
            let needed = UNUSABLE_WORKERS.min(live).max(1);
            let jobs: Vec<JobId> = lease_ids
                .iter()
                .filter(|id| {
                    farm.scheduler
                        .leases()
                        .any(|l| l.lease_id == **id && l.worker == worker)
                })
                .filter_map(|id| farm.scheduler.lease_job(*id))
                .collect();
            let before = farm.scheduler.leases().count();
            farm.scheduler.give_back(worker, lease_ids);
            let returned = (before - farm.scheduler.leases().count()) as u32;
            let mut to_fail = Vec::new();
            for job in jobs {
                if let Some(rt) = farm.runtime.get_mut(&job) {
                    rt.unusable_returns += 1;
                    if let Some(who) = &who {
                        rt.unusable_workers.insert(who.clone());
                    }
                    if rt.unusable_returns >= MAX_UNUSABLE_RETURNS
                        && rt.unusable_workers.len() >= needed
                        && !rt.state.is_terminal()
                        && !to_fail.contains(&job)
                    {
                        to_fail.push(job);
                    }
                }
            }
            for &job in &to_fail {
                farm.scheduler.cancel(job);
            }
            (returned, to_fail)
        };
        tracing::warn!(worker, returned, reason = %reason, "worker could not use its leases");
        if returned > 0 {
            self.work_changed(true);
        }
        for job in to_fail {
            let error = format!(
                "workers could not use the scene (load, build or render it) {MAX_UNUSABLE_RETURNS} times: {reason}"
            );
            tracing::error!(job, error = %error, "job failed");
            self.set_state(job, JobState::Failed, Some(error)).await?;
        }
        Ok(returned)
    }

    /// `DELETE /workers/{name}/quarantine`: an operator lifts the quarantine of the
    /// worker named `name`, under any TLS identity (ARCHITECTURE.md §6). The stored
    /// quarantines go first, so a failed write changes nothing; then the quarantine list
    /// in memory, and every listed worker of that name gets leases and has its results
    /// taken again ([`tessera_farm::Scheduler::lift_quarantine`]). What the quarantine
    /// dropped is not restored: its units were rendered again. [`CoordError::NotFound`]
    /// naming the worker if no quarantine of that name is stored or in force.
    pub async fn lift_quarantine(&self, name: &str) -> CoordResult<()> {
        self.active()?;
        // Under the write lock, so that a quarantine being recorded by a result
        // (`write_back`) is not interleaved with the removal.
        let write = self.inner.write.lock().await;
        let stored = self.inner.store.delete_quarantines(name).await?;
        let lifted = {
            let mut farm = self.lock()?;
            let listed = farm.quarantines.len();
            farm.quarantines.retain(|(n, _), _| n != name);
            let mut lifted = farm.quarantines.len() < listed;
            let ids: Vec<WorkerId> = farm
                .workers
                .iter_mut()
                .filter(|(_, w)| w.name == name && w.quarantined.is_some())
                .map(|(&id, w)| {
                    w.quarantined = None;
                    id
                })
                .collect();
            for &id in &ids {
                farm.scheduler.lift_quarantine(id);
            }
            lifted |= !ids.is_empty() || stored > 0;
            if lifted {
                farm.spot.lifted += 1;
            }
            lifted
        };
        drop(write);
        if !lifted {
            return Err(CoordError::NotFound(format!(
                "worker {name:?} is not quarantined"
            )));
        }
        tracing::warn!(name = %name, stored, "quarantine lifted by an operator");
        Ok(())
    }

    /// Commits the reservation of lease ids before any of them reaches a worker, and
    /// marks jobs that started running (ARCHITECTURE.md §9, step 7).
    async fn after_lease(&self, jobs: Vec<JobId>) -> CoordResult<()> {
        let max = self.lock()?.scheduler.max_issued_lease_id();
        // The next block is reserved when half of this one is used, so that under a
        // fleet's load one lease waits for the commit instead of every lease that
        // crosses the block's end; and checked again under the write lock, so that the
        // callers that queued for it meanwhile do not commit it once each.
        let reserved = || -> CoordResult<u64> {
            Ok(*self
                .inner
                .lease_reserved
                .lock()
                .map_err(|_| CoordError::poisoned())?)
        };
        if max + LEASE_ID_BLOCK / 2 > reserved()? {
            let _w = self.inner.write.lock().await;
            if max + LEASE_ID_BLOCK / 2 > reserved()? {
                let upto = max + LEASE_ID_BLOCK;
                self.inner.store.record_lease_high_water(upto).await?;
                let mut r = self
                    .inner
                    .lease_reserved
                    .lock()
                    .map_err(|_| CoordError::poisoned())?;
                *r = (*r).max(upto);
            }
        }
        for id in jobs {
            // One caller records the start: a fleet's first leases all find the job
            // queued, and would otherwise queue a store write each.
            let first = self.lock()?.runtime.get_mut(&id).is_some_and(|rt| {
                let first = rt.state == JobState::Queued && !rt.starting;
                rt.starting |= first;
                first
            });
            if first {
                let r = self.set_state(id, JobState::Running, None).await;
                if let Some(rt) = self.lock()?.runtime.get_mut(&id) {
                    rt.starting = false;
                }
                r?;
            }
        }
        Ok(())
    }

    /// Whether leasing is paused (the restart grace period).
    pub(crate) fn leasing_paused(&self) -> bool {
        now_ms() < self.inner.lease_blocked_until_ms
    }

    /// A worker silent for longer than this is `lost`, ms: five missed heartbeats and two
    /// seconds of slack.
    pub(crate) fn lost_after_ms(&self) -> u64 {
        u64::from(self.inner.cfg.heartbeat_ms) * 5 + 2_000
    }

    /// Removes workers that have been lost for [`CoordinatorConfig::forget_lost_ms`] and
    /// hold no lease, keeping their totals in [`Farm::forgotten`] (called by `tick`);
    /// quarantined workers are kept.
    ///
    /// [`CoordinatorConfig::forget_lost_ms`]: super::CoordinatorConfig::forget_lost_ms
    pub(crate) fn forget_lost_workers(&self, farm: &mut Farm, now: u64) {
        let silent = self
            .lost_after_ms()
            .saturating_add(self.inner.cfg.forget_lost_ms);
        let gone: Vec<WorkerId> = farm
            .workers
            .iter()
            .filter(|(&id, w)| {
                // A quarantined worker stays listed, so that the operator sees it (the
                // quarantine list, not the listing, keeps it quarantined when it
                // registers again).
                w.quarantined.is_none()
                    && now.saturating_sub(w.last_seen_ms) > silent
                    && !farm.scheduler.leases().any(|l| l.worker == id)
            })
            .map(|(&id, _)| id)
            .collect();
        for id in gone {
            if let Some(w) = farm.workers.remove(&id) {
                farm.forgotten.workers += 1;
                farm.forgotten.units_done += w.units_done;
                farm.forgotten.faults += w.faults;
                farm.forgotten.render_seconds += w.render_seconds;
                farm.forgotten.pixel_passes += w.pixel_passes;
                tracing::info!(worker = id, name = %w.name, "lost worker forgotten");
            }
        }
    }

    /// `GET /workers`: the workers this run knows, and the quarantine list.
    pub fn workers(&self) -> CoordResult<WorkerList> {
        let farm = self.lock()?;
        let now = now_ms();
        let lost_after = self.lost_after_ms();
        let workers = farm
            .workers
            .iter()
            .map(|(&id, w)| {
                let leases = farm.scheduler.leases().filter(|l| l.worker == id).count();
                let state = if now.saturating_sub(w.last_seen_ms) > lost_after {
                    WorkerState::Lost
                } else if w.draining {
                    WorkerState::Draining
                } else if leases > 0 {
                    WorkerState::Busy
                } else {
                    WorkerState::Idle
                };
                WorkerInfo {
                    id,
                    name: w.name.clone(),
                    threads: w.threads,
                    state,
                    last_heartbeat_unix_ms: w.last_seen_ms,
                    units_done: w.units_done,
                    paths_per_second: w.paths_per_second,
                    faults: w.faults,
                    version: w.version.clone(),
                    identity: w.identity.clone(),
                    quarantined: w.quarantined.is_some(),
                    quarantine_reason: w.quarantined.clone(),
                }
            })
            .collect();
        let quarantines = farm
            .quarantines
            .values()
            .map(|q| QuarantineInfo {
                name: q.worker.clone(),
                identity: q.identity.clone(),
                reason: q.reason.clone(),
                since_unix_ms: q.unix_ms,
            })
            .collect();
        Ok(WorkerList {
            workers,
            quarantines,
        })
    }
}
