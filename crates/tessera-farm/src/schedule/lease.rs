//! Leasing units: who gets which unit and how many (the tail rule, [`tail_share`]),
//! deadlines extended by heartbeats, expiry returning units to the queue at their
//! canonical position, leases given back, and the lapsed leases a late result may still
//! answer (a lease id is a fencing token: unique and increasing over the scheduler's life,
//! and across restarts through the high-water mark given to [`Scheduler::new`]).

use super::job::Job;
use super::{Lease, Scheduler};
use crate::ids::{JobId, WorkerId};

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

impl Scheduler {
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
        self.note_leasing(worker, alone);
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
    /// worker is left rendering a large batch alone while the others wait (ARCHITECTURE.md
    /// §9, "The worker's pipeline"). Only who renders which unit depends on it, never what
    /// a unit is, so the image is the same.
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

    /// Ends lease `lease_id` (lapsed, given back or revoked): it is remembered as lapsed,
    /// so a late result may still answer it, and its unit returns to the queue unless it
    /// is merged or its job canceled.
    pub(super) fn release(&mut self, lease_id: u64) {
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

    /// The job a lease was issued for, whether it is outstanding or has lapsed.
    pub fn lease_job(&self, lease_id: u64) -> Option<JobId> {
        self.leases
            .get(&lease_id)
            .map(|l| l.job)
            .or_else(|| self.lapsed.get(&lease_id).map(|(j, _)| *j))
    }

    /// The outstanding lease `lease_id` (`None` once it lapsed, was given back or
    /// answered).
    pub fn outstanding(&self, lease_id: u64) -> Option<&Lease> {
        self.leases.get(&lease_id)
    }

    /// All outstanding leases.
    pub fn leases(&self) -> impl Iterator<Item = &Lease> {
        self.leases.values()
    }
}
