//! The worker-facing gRPC service (`tessera.v1.WorkerService`) over the farm's
//! [`Scheduler`].
//!
//! Workers register, lease units, heartbeat to extend their leases, submit results and
//! fetch scenes by content hash. Every result is validated (lease, unit, dimensions,
//! finite values) before the scheduler merges it in canonical pass order; a rejected or
//! mismatching result counts as a fault against the worker. When a bearer token is
//! configured, requests without it are refused with `UNAUTHENTICATED`.

use std::collections::{BTreeMap, HashMap};
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::time::{SystemTime, UNIX_EPOCH};
use tessera_farm::job::{RenderConfig, SceneRef};
use tessera_farm::{FramePlan, JobId, Scheduler, SubmitError, Submitted, UnitResult, WorkerId};
use tessera_proto::v1;
use tessera_proto::LeasedUnit;
use tonic::{Request, Response, Status};

use crate::service::{Coordinator, JobRuntime};

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
    /// Units accepted from it.
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
}

/// A job as the service needs it to hand out leases.
#[derive(Clone, Debug)]
pub struct JobEntry {
    /// The scene.
    pub scene: SceneRef,
    /// The glTF camera the job renders from, if it names one.
    pub camera: Option<String>,
    /// Render settings.
    pub settings: RenderConfig,
    /// Frame plan.
    pub plan: FramePlan,
}

/// Shared state of the farm behind the service.
pub struct Farm {
    /// Leases and merged frames.
    pub scheduler: Scheduler,
    /// Registered workers.
    pub workers: BTreeMap<WorkerId, WorkerEntry>,
    /// Jobs by id.
    pub jobs: BTreeMap<JobId, JobEntry>,
    /// Uploaded scene bytes by content hash.
    pub scenes: HashMap<String, Arc<Vec<u8>>>,
    /// What the coordinator tracks per job besides the scheduler (empty when the service
    /// runs without a [`Coordinator`]).
    pub runtime: BTreeMap<JobId, JobRuntime>,
    next_worker: WorkerId,
}

impl Farm {
    /// An empty farm whose leases last `lease_ms`.
    pub fn new(lease_ms: u64) -> Self {
        Self::with_first_lease(lease_ms, 0)
    }

    /// An empty farm whose lease ids start after `high_water` (the largest id an earlier
    /// run may have issued), so fencing tokens never repeat across restarts.
    pub fn with_first_lease(lease_ms: u64, high_water: u64) -> Self {
        Self {
            scheduler: Scheduler::new(lease_ms, high_water),
            workers: BTreeMap::new(),
            jobs: BTreeMap::new(),
            scenes: HashMap::new(),
            runtime: BTreeMap::new(),
            next_worker: 1,
        }
    }
}

/// The gRPC service.
#[derive(Clone)]
pub struct WorkerGrpc {
    farm: Arc<Mutex<Farm>>,
    token: Option<String>,
    heartbeat_ms: u32,
    lease_ms: u32,
    /// With a coordinator, results are checkpointed in its store before they are
    /// acknowledged, and lease ids are reserved durably.
    core: Option<Coordinator>,
}

/// Size of the chunks scenes are streamed in.
const SCENE_CHUNK: usize = 1 << 20;

impl WorkerGrpc {
    /// A service over `farm`; workers must present `token` if one is given.
    pub fn new(
        farm: Arc<Mutex<Farm>>,
        token: Option<String>,
        heartbeat_ms: u32,
        lease_ms: u32,
    ) -> Self {
        Self {
            farm,
            token,
            heartbeat_ms,
            lease_ms,
            core: None,
        }
    }

    /// The service of a [`Coordinator`]: its farm, its worker token and timings, and its
    /// durable bookkeeping.
    pub fn for_coordinator(core: Coordinator) -> Self {
        let cfg = core.config();
        Self {
            farm: core.farm(),
            token: cfg.worker_token.clone(),
            heartbeat_ms: cfg.heartbeat_ms,
            lease_ms: cfg.lease_ms.min(u64::from(u32::MAX)) as u32,
            core: Some(core),
        }
    }

    /// The tonic server wrapper of this service.
    pub fn into_server(self) -> v1::worker_service_server::WorkerServiceServer<Self> {
        v1::worker_service_server::WorkerServiceServer::new(self)
            .max_decoding_message_size(64 << 20)
            .max_encoding_message_size(64 << 20)
    }

    fn authorize<T>(&self, req: &Request<T>) -> Result<(), Status> {
        let Some(token) = &self.token else {
            return Ok(());
        };
        let given = req
            .metadata()
            .get("authorization")
            .and_then(|v| v.to_str().ok());
        match given.and_then(|g| g.strip_prefix("Bearer ")) {
            Some(g) if constant_time_eq(g.as_bytes(), token.as_bytes()) => Ok(()),
            _ => Err(Status::unauthenticated("a valid worker token is required")),
        }
    }

    fn lock(&self) -> Result<std::sync::MutexGuard<'_, Farm>, Status> {
        self.farm
            .lock()
            .map_err(|_| Status::internal("farm state poisoned"))
    }
}

/// Compares secrets without an early exit.
fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

type SceneStream = Pin<Box<dyn tokio_stream::Stream<Item = Result<v1::SceneChunk, Status>> + Send>>;

#[tonic::async_trait]
impl v1::worker_service_server::WorkerService for WorkerGrpc {
    async fn register(
        &self,
        req: Request<v1::RegisterRequest>,
    ) -> Result<Response<v1::RegisterResponse>, Status> {
        self.authorize(&req)?;
        let r = req.into_inner();
        if r.name.len() > 200 {
            return Err(Status::invalid_argument("name: at most 200 characters"));
        }
        let mut farm = self.lock()?;
        let id = farm.next_worker;
        farm.next_worker += 1;
        farm.workers.insert(
            id,
            WorkerEntry {
                name: r.name,
                threads: r.threads,
                last_seen_ms: now_ms(),
                version: r.version.chars().take(64).collect(),
                ..WorkerEntry::default()
            },
        );
        Ok(Response::new(v1::RegisterResponse {
            worker_id: id,
            heartbeat_interval_ms: self.heartbeat_ms,
            lease_duration_ms: self.lease_ms,
        }))
    }

    async fn heartbeat(
        &self,
        req: Request<v1::HeartbeatRequest>,
    ) -> Result<Response<v1::HeartbeatResponse>, Status> {
        self.authorize(&req)?;
        let r = req.into_inner();
        let now = now_ms();
        let mut farm = self.lock()?;
        let Some(w) = farm.workers.get_mut(&r.worker_id) else {
            return Err(Status::not_found("unknown worker: register again"));
        };
        w.last_seen_ms = now;
        if r.paths_per_second.is_finite() && r.paths_per_second >= 0.0 {
            w.paths_per_second = r.paths_per_second;
        }
        let extended = farm.scheduler.extend(r.worker_id, &r.lease_ids, now);
        // Leases not extended are lapsed or canceled: tell the worker to drop them. Leases
        // of a previous run of the coordinator (before a restart) are unknown here but their
        // results are still adopted, so the worker keeps rendering them.
        let cancel = r
            .lease_ids
            .iter()
            .copied()
            .filter(|id| {
                !extended.iter().any(|(e, _)| e == id) && !farm.scheduler.is_previous_run_lease(*id)
            })
            .collect();
        Ok(Response::new(v1::HeartbeatResponse {
            extended: extended
                .into_iter()
                .map(|(lease_id, deadline_unix_ms)| v1::LeaseExtension {
                    lease_id,
                    deadline_unix_ms,
                })
                .collect(),
            cancel,
            shutdown: false,
        }))
    }

    async fn lease_work(
        &self,
        req: Request<v1::LeaseRequest>,
    ) -> Result<Response<v1::LeaseResponse>, Status> {
        self.authorize(&req)?;
        let r = req.into_inner();
        let now = now_ms();
        if self.core.as_ref().is_some_and(|c| c.leasing_paused()) {
            // A restarted coordinator waits for workers to deliver what they were rendering.
            if !self.lock()?.workers.contains_key(&r.worker_id) {
                return Err(Status::not_found("unknown worker: register again"));
            }
            return Ok(Response::new(v1::LeaseResponse {
                leases: Vec::new(),
                retry_after_ms: 250,
            }));
        }
        let out = {
            let mut farm = self.lock()?;
            if !farm.workers.contains_key(&r.worker_id) {
                return Err(Status::not_found("unknown worker: register again"));
            }
            farm.scheduler.expire(now);
            let leases = farm
                .scheduler
                .lease(r.worker_id, now, r.max_units.clamp(1, 256) as usize);
            let mut out = Vec::with_capacity(leases.len());
            for l in leases {
                let Some(job) = farm.jobs.get(&l.job) else {
                    continue;
                };
                out.push(v1::Lease::from(LeasedUnit {
                    lease_id: l.lease_id,
                    deadline_unix_ms: l.deadline_ms,
                    job_id: l.job,
                    scene: job.scene.clone(),
                    camera: job.camera.clone(),
                    settings: job.settings,
                    plan: job.plan,
                    unit: l.unit,
                }));
            }
            if let Some(w) = farm.workers.get_mut(&r.worker_id) {
                w.last_seen_ms = now;
            }
            out
        };
        if let Some(core) = &self.core {
            let mut jobs: Vec<u64> = out.iter().map(|l| l.job_id).collect();
            jobs.dedup();
            if let Err(e) = core.after_lease(jobs).await {
                // The reservation of lease ids could not be made durable: hand nothing out
                // (the leases lapse and are issued again).
                return Err(Status::unavailable(format!("coordinator store: {e}")));
            }
        }
        // Idle workers ask again soon, so a new job starts within ~50 ms.
        let retry_after_ms = if out.is_empty() { 50 } else { 0 };
        Ok(Response::new(v1::LeaseResponse {
            leases: out,
            retry_after_ms,
        }))
    }

    async fn submit_result(
        &self,
        req: Request<v1::SubmitResultRequest>,
    ) -> Result<Response<v1::SubmitResultResponse>, Status> {
        self.authorize(&req)?;
        let r = req.into_inner();
        let (worker_id, lease_id) = (r.worker_id, r.lease_id);
        if let Some(core) = &self.core {
            let (job_hint, secs) = (r.job_id, r.render_seconds);
            let result = UnitResult::try_from(r).map_err(|e| e.to_string());
            let (accepted, reason) = core
                .accept_result(worker_id, lease_id, job_hint, result, secs)
                .await;
            return Ok(Response::new(v1::SubmitResultResponse { accepted, reason }));
        }
        let result: Result<UnitResult, _> = UnitResult::try_from(r);
        let mut farm = self.lock()?;
        // The scheduler knows the job of outstanding and lapsed leases alike, and checks
        // that the lease was issued for exactly this unit.
        let outcome = match (result, farm.scheduler.lease_job(lease_id)) {
            (Err(e), _) => Err(e.to_string()),
            (Ok(result), Some(job)) => farm
                .scheduler
                .submit(lease_id, job, result)
                .map_err(|e| e.to_string()),
            (Ok(_), None) => Err(SubmitError::UnknownLease(lease_id).to_string()),
        };
        let w = farm.workers.entry(worker_id).or_default();
        w.last_seen_ms = now_ms();
        let (accepted, reason) = match outcome {
            Ok(Submitted::Accepted) => {
                w.units_done += 1;
                (true, String::new())
            }
            Ok(Submitted::Duplicate { identical: true }) => (true, "duplicate (identical)".into()),
            Ok(Submitted::Duplicate { identical: false }) => {
                w.faults += 1;
                tracing::warn!(
                    worker_id,
                    lease_id,
                    "duplicate result differs from the merged copy"
                );
                (
                    false,
                    "duplicate differs from the merged copy: faulty worker".into(),
                )
            }
            Err(e) => {
                w.faults += 1;
                tracing::warn!(worker_id, lease_id, error = %e, "result rejected");
                (false, e)
            }
        };
        Ok(Response::new(v1::SubmitResultResponse { accepted, reason }))
    }

    type FetchSceneStream = SceneStream;

    async fn fetch_scene(
        &self,
        req: Request<v1::FetchSceneRequest>,
    ) -> Result<Response<SceneStream>, Status> {
        self.authorize(&req)?;
        let hash = req.into_inner().scene_hash;
        let bytes = self
            .lock()?
            .scenes
            .get(&hash)
            .cloned()
            .ok_or_else(|| Status::not_found(format!("no scene {hash}")))?;
        let total = bytes.len() as u64;
        let chunks: Vec<Result<v1::SceneChunk, Status>> = if bytes.is_empty() {
            vec![Ok(v1::SceneChunk {
                offset: 0,
                data: Vec::new(),
                total_size: 0,
                sha256: hash.clone(),
            })]
        } else {
            bytes
                .chunks(SCENE_CHUNK)
                .enumerate()
                .map(|(i, c)| {
                    let offset = (i * SCENE_CHUNK) as u64;
                    let last = offset + c.len() as u64 == total;
                    Ok(v1::SceneChunk {
                        offset,
                        data: c.to_vec(),
                        total_size: total,
                        sha256: if last { hash.clone() } else { String::new() },
                    })
                })
                .collect()
        };
        Ok(Response::new(Box::pin(tokio_stream::iter(chunks))))
    }

    async fn return_leases(
        &self,
        req: Request<v1::ReturnLeasesRequest>,
    ) -> Result<Response<v1::ReturnLeasesResponse>, Status> {
        self.authorize(&req)?;
        let r = req.into_inner();
        let mut farm = self.lock()?;
        let before = farm.scheduler.leases().count();
        farm.scheduler.give_back(r.worker_id, &r.lease_ids);
        let returned = (before - farm.scheduler.leases().count()) as u32;
        Ok(Response::new(v1::ReturnLeasesResponse { returned }))
    }
}
