//! [`WatchedStore`]: a [`Store`] that remembers the first failed write.
//!
//! A full disk, an I/O error or a file made read-only under a running coordinator makes
//! every later write fail too. Rather than answer 500 to every request forever, the
//! coordinator wraps its store in a `WatchedStore` and, once a write failed that way
//! ([`StoreError::is_write_failure`]), stops accepting work: submissions, scene uploads
//! and leases answer "unavailable" naming the error, `/healthz` reports unhealthy, and
//! reads keep working (docs/store.md, "When a write fails while running"). The fault
//! stays until the coordinator restarts, whose open probes a write again; a fault of a
//! full disk ([`WatchedStore::disk_full`]) is cured by the coordinator itself once space
//! is freed (`crate::server`, docs/store.md "When the disk is full").

use std::sync::{Arc, Mutex};

use async_trait::async_trait;
use tessera_api::{HistoryPoint, JobState};
use tessera_farm::JobId;

use super::{
    FaultEvent, FaultFilter, JobQuery, JobRecord, NewJob, PreviousRun, QuarantineRecord,
    SceneDeletion, Store, StoreError, StoreResult, TileCheckpoint, TileCheckpointRef, TileSummary,
};

/// A store wrapper that records the first write failure (see the module docs).
pub struct WatchedStore {
    inner: Arc<dyn Store>,
    fault: Mutex<Option<String>>,
    /// Whether the fault is a full disk (507, and cured by freeing space).
    disk_full: std::sync::atomic::AtomicBool,
}

impl WatchedStore {
    /// Watches `inner`.
    pub fn new(inner: Arc<dyn Store>) -> Self {
        Self {
            inner,
            fault: Mutex::new(None),
            disk_full: std::sync::atomic::AtomicBool::new(false),
        }
    }

    /// Watches `inner`, failing from the start: a coordinator started on a full disk
    /// over a read-only view of its store (`what` says why).
    pub fn failing(inner: Arc<dyn Store>, what: String) -> Self {
        let me = Self::new(inner);
        if let Ok(mut f) = me.fault.lock() {
            *f = Some(what);
        }
        me.mark_disk_full();
        me
    }

    /// Whether the recorded fault is a full disk: a write failed with
    /// [`StoreError::is_disk_full`], or [`WatchedStore::mark_disk_full`] was called.
    pub fn disk_full(&self) -> bool {
        self.fault().is_some() && self.disk_full.load(std::sync::atomic::Ordering::SeqCst)
    }

    /// Records that the fault is a full disk (found by probing the data directory when
    /// the error itself did not say so, e.g. an I/O error extending a file).
    pub fn mark_disk_full(&self) {
        self.disk_full
            .store(true, std::sync::atomic::Ordering::SeqCst);
    }

    /// The first write failure, as text, if a write failed.
    pub fn fault(&self) -> Option<String> {
        self.fault
            .lock()
            .map_or_else(|_| Some("store fault state poisoned".into()), |f| f.clone())
    }

    /// Passes a write's result through, recording a write failure.
    fn watch<T>(&self, what: &str, r: StoreResult<T>) -> StoreResult<T> {
        if let Err(e) = &r {
            if e.is_write_failure() {
                if let Ok(mut f) = self.fault.lock() {
                    if f.is_none() {
                        tracing::error!(
                            error = %e,
                            write = what,
                            "store write failed: no longer accepting work until restarted"
                        );
                        *f = Some(format!("{what}: {e}"));
                        if e.is_disk_full() {
                            self.mark_disk_full();
                        }
                    }
                }
            }
        }
        r
    }
}

#[async_trait]
impl Store for WatchedStore {
    async fn insert_job(&self, job: NewJob) -> StoreResult<(JobId, bool)> {
        self.watch("storing a job", self.inner.insert_job(job).await)
    }

    async fn get_job(&self, id: JobId) -> StoreResult<Option<JobRecord>> {
        self.inner.get_job(id).await
    }

    async fn list_jobs(&self, query: JobQuery) -> StoreResult<Vec<JobRecord>> {
        self.inner.list_jobs(query).await
    }

    async fn set_job_state(
        &self,
        id: JobId,
        state: JobState,
        error: Option<String>,
        now_unix_ms: u64,
    ) -> StoreResult<bool> {
        let r = self
            .inner
            .set_job_state(id, state, error, now_unix_ms)
            .await;
        self.watch("storing a job state", r)
    }

    async fn jobs_to_resume(&self) -> StoreResult<Vec<JobRecord>> {
        self.inner.jobs_to_resume().await
    }

    async fn put_scene(&self, hash: &str, bytes: &[u8]) -> StoreResult<bool> {
        self.watch("storing a scene", self.inner.put_scene(hash, bytes).await)
    }

    async fn get_scene(&self, hash: &str) -> StoreResult<Option<Vec<u8>>> {
        self.inner.get_scene(hash).await
    }

    async fn scene_exists(&self, hash: &str) -> StoreResult<bool> {
        self.inner.scene_exists(hash).await
    }

    async fn scene_bytes(&self, owner: Option<&str>) -> StoreResult<u64> {
        self.inner.scene_bytes(owner).await
    }

    async fn record_scene_upload(&self, hash: &str, owner: &str) -> StoreResult<()> {
        let r = self.inner.record_scene_upload(hash, owner).await;
        self.watch("recording a scene upload", r)
    }

    async fn delete_scene(&self, hash: &str) -> StoreResult<SceneDeletion> {
        self.watch("deleting a scene", self.inner.delete_scene(hash).await)
    }

    async fn unused_scenes(&self, cutoff_unix_ms: u64, limit: u32) -> StoreResult<Vec<String>> {
        self.inner.unused_scenes(cutoff_unix_ms, limit).await
    }

    async fn save_tiles(&self, tiles: &[TileCheckpointRef<'_>]) -> StoreResult<()> {
        self.watch(
            "storing a tile checkpoint",
            self.inner.save_tiles(tiles).await,
        )
    }

    async fn load_tiles(&self, job: JobId, frame: Option<u32>) -> StoreResult<Vec<TileCheckpoint>> {
        self.inner.load_tiles(job, frame).await
    }

    async fn count_jobs_by_state(&self) -> StoreResult<Vec<(JobState, u64)>> {
        self.inner.count_jobs_by_state().await
    }

    async fn tile_summaries(&self, job: JobId) -> StoreResult<Vec<TileSummary>> {
        self.inner.tile_summaries(job).await
    }

    async fn max_lease_id(&self) -> StoreResult<u64> {
        self.inner.max_lease_id().await
    }

    async fn record_lease_high_water(&self, lease_id: u64) -> StoreResult<()> {
        let r = self.inner.record_lease_high_water(lease_id).await;
        self.watch("reserving lease ids", r)
    }

    async fn fence_key(&self, fresh: [u8; 32]) -> StoreResult<[u8; 32]> {
        self.inner.fence_key(fresh).await
    }

    async fn append_history(
        &self,
        job: JobId,
        point: HistoryPoint,
        estimator: Option<&str>,
    ) -> StoreResult<()> {
        let r = self.inner.append_history(job, point, estimator).await;
        self.watch("storing a history point", r)
    }

    async fn list_history(&self, job: JobId) -> StoreResult<Vec<HistoryPoint>> {
        self.inner.list_history(job).await
    }

    async fn record_fault(&self, fault: &FaultEvent) -> StoreResult<()> {
        self.watch(
            "storing a fault event",
            self.inner.record_fault(fault).await,
        )
    }

    async fn count_faults(&self, filter: &FaultFilter) -> StoreResult<u64> {
        self.inner.count_faults(filter).await
    }

    async fn list_faults(&self, filter: &FaultFilter, limit: u32) -> StoreResult<Vec<FaultEvent>> {
        self.inner.list_faults(filter, limit).await
    }

    async fn record_quarantine(&self, quarantine: &QuarantineRecord) -> StoreResult<bool> {
        let r = self.inner.record_quarantine(quarantine).await;
        self.watch("storing a quarantine", r)
    }

    async fn list_quarantines(&self) -> StoreResult<Vec<QuarantineRecord>> {
        self.inner.list_quarantines().await
    }

    async fn delete_quarantines(&self, worker: &str) -> StoreResult<u64> {
        let r = self.inner.delete_quarantines(worker).await;
        self.watch("lifting a quarantine", r)
    }

    async fn job_ids_to_resume(&self) -> StoreResult<Vec<JobId>> {
        self.inner.job_ids_to_resume().await
    }

    async fn begin_run(&self) -> StoreResult<PreviousRun> {
        self.watch("starting a run", self.inner.begin_run().await)
    }

    async fn end_run(&self) -> StoreResult<()> {
        self.watch("ending a run", self.inner.end_run().await)
    }

    async fn record_resume(&self, job: JobId, count: bool) -> StoreResult<u32> {
        let r = self.inner.record_resume(job, count).await;
        self.watch("recording a resume", r)
    }

    async fn resumes_done(&self) -> StoreResult<()> {
        self.watch("recording a resume", self.inner.resumes_done().await)
    }

    async fn ping(&self) -> StoreResult<()> {
        if let Some(f) = self.fault() {
            return Err(if self.disk_full() {
                StoreError::DiskFull(f)
            } else {
                StoreError::Failing(f)
            });
        }
        self.inner.ping().await
    }

    async fn close(&self) {
        self.inner.close().await;
    }
}
