//! The worker-facing gRPC service (`tessera.v1.WorkerService`, ARCHITECTURE.md §5, §9).
//!
//! Each method does four things and no more: authorize the bearer token, decode the
//! request (`tessera-proto` checks every field), call the [`Coordinator`], encode the
//! answer. The job life cycle — leases, merges, checkpoints, faults — lives in
//! [`crate::service`]; errors become a `tonic::Status` through the one mapping in
//! [`crate::error`]. When a worker token is configured, requests without it are refused
//! with `UNAUTHENTICATED`. Every call after Register that names a worker id must carry
//! that worker's session secret (metadata `x-tessera-session`, [`crate::trust`]); a
//! missing or wrong one is refused with `PERMISSION_DENIED` before anything of the
//! worker's state is read or changed.
//!
//! Every leased unit and every delivered result gets a `unit` span with the job, frame,
//! tile, passes, lease id and worker, so a unit's story can be followed in the logs.

use std::pin::Pin;
use std::time::Duration;

use tessera_farm::UnitResult;
use tessera_proto::v1;
use tonic::{Request, Response, Status};
use tracing::Instrument;

use crate::error::CoordError;
use crate::service::{Coordinator, Delivery, MAX_LEASE_WAIT_MS};

/// The gRPC service of a [`Coordinator`].
#[derive(Clone)]
pub struct WorkerGrpc {
    core: Coordinator,
}

/// Size of the chunks scenes are streamed in.
const SCENE_CHUNK: usize = 1 << 20;
/// Largest gRPC message either way: a whole-frame unit's result can be large.
const MAX_MESSAGE: usize = 64 << 20;

impl WorkerGrpc {
    /// The service of a [`Coordinator`]: its farm, its worker token and timings, and its
    /// durable bookkeeping.
    pub fn for_coordinator(core: Coordinator) -> Self {
        Self { core }
    }

    /// The tonic server wrapper of this service.
    pub fn into_server(self) -> v1::worker_service_server::WorkerServiceServer<Self> {
        v1::worker_service_server::WorkerServiceServer::new(self)
            .max_decoding_message_size(MAX_MESSAGE)
            .max_encoding_message_size(MAX_MESSAGE)
    }

    /// Checks the worker token, then that this coordinator is still the active one: a
    /// deposed coordinator (`crate::ha`) answers every worker request `UNAVAILABLE`, so
    /// the worker keeps its results and takes them to the active one.
    fn authorize<T>(&self, req: &Request<T>) -> Result<(), Status> {
        self.check_token(req)?;
        self.core.active().map_err(status)
    }

    /// Checks that the call carries the session secret issued to `worker`: NOT_FOUND for a
    /// worker this run does not know (it registers again), PERMISSION_DENIED for a missing
    /// or wrong secret. Compared in constant time.
    fn check_session<T>(&self, req: &Request<T>, worker: u64) -> Result<(), Status> {
        let given = req
            .metadata()
            .get(tessera_proto::SESSION_METADATA)
            .map(|v| v.as_bytes())
            .unwrap_or_default();
        let Some(expected) = self.core.worker_session(worker).map_err(status)? else {
            return Err(Status::not_found(format!(
                "unknown worker {worker}: register again"
            )));
        };
        if crate::trust::same_secret(given, expected.as_bytes()) {
            Ok(())
        } else {
            // Not UNAUTHENTICATED, which tells a worker its token is wrong and to stop: a
            // worker of a previous run may hold an id this run gave another worker, and must
            // register again.
            Err(Status::permission_denied(format!(
                "the session of worker {worker} is missing or wrong: register again"
            )))
        }
    }

    fn check_token<T>(&self, req: &Request<T>) -> Result<(), Status> {
        let Some(token) = &self.core.config().worker_token else {
            return Ok(());
        };
        let given = req
            .metadata()
            .get("authorization")
            .and_then(|v| v.to_str().ok());
        if crate::auth::bearer_matches(given, token) {
            Ok(())
        } else {
            Err(Status::unauthenticated("a valid worker token is required"))
        }
    }
}

/// A coordinator error as the worker sees it; server faults are logged here, once.
fn status(e: CoordError) -> Status {
    if e.is_server_fault() {
        tracing::error!(error = %e, "worker request failed");
    }
    e.into()
}

type SceneStream = Pin<Box<dyn tokio_stream::Stream<Item = Result<v1::SceneChunk, Status>> + Send>>;

#[tonic::async_trait]
impl v1::worker_service_server::WorkerService for WorkerGrpc {
    async fn register(
        &self,
        req: Request<v1::RegisterRequest>,
    ) -> Result<Response<v1::RegisterResponse>, Status> {
        self.authorize(&req)?;
        // Under mutual TLS, the certificate's common name (`crate::tls`).
        let identity = req
            .extensions()
            .get::<crate::tls::PeerInfo>()
            .and_then(|p| p.identity.clone());
        let r = req.into_inner();
        let id = self
            .core
            .register_worker_as(r.name, r.threads, &r.version, identity)
            .map_err(status)?;
        let session = self
            .core
            .worker_session(id)
            .map_err(status)?
            .unwrap_or_default();
        let cfg = self.core.config();
        Ok(Response::new(v1::RegisterResponse {
            worker_id: id,
            heartbeat_interval_ms: cfg.heartbeat_ms,
            lease_duration_ms: cfg.lease_ms.min(u64::from(u32::MAX)) as u32,
            session,
        }))
    }

    async fn heartbeat(
        &self,
        req: Request<v1::HeartbeatRequest>,
    ) -> Result<Response<v1::HeartbeatResponse>, Status> {
        self.authorize(&req)?;
        self.check_session(&req, req.get_ref().worker_id)?;
        let r = req.into_inner();
        let hb = self
            .core
            .heartbeat(r.worker_id, r.paths_per_second, &r.lease_ids)
            .map_err(status)?;
        Ok(Response::new(v1::HeartbeatResponse {
            extended: hb
                .extended
                .into_iter()
                .map(|(lease_id, deadline_unix_ms)| v1::LeaseExtension {
                    lease_id,
                    deadline_unix_ms,
                })
                .collect(),
            cancel: hb.cancel,
            shutdown: hb.shutdown,
        }))
    }

    async fn lease_work(
        &self,
        req: Request<v1::LeaseRequest>,
    ) -> Result<Response<v1::LeaseResponse>, Status> {
        self.authorize(&req)?;
        self.check_session(&req, req.get_ref().worker_id)?;
        let r = req.into_inner();
        let grant = self
            .core
            .lease_waiting(
                r.worker_id,
                r.max_units,
                Duration::from_millis(u64::from(r.wait_ms.min(MAX_LEASE_WAIT_MS))),
            )
            .await
            .map_err(status)?;
        let leases = grant
            .units
            .into_iter()
            .map(|l| {
                let u = l.unit;
                let span = tracing::info_span!(
                    "unit",
                    job = l.job_id,
                    frame = u.frame,
                    tile = u.tile,
                    passes = %format_args!("{}..{}", u.first_pass, u.end_pass()),
                    lease_id = l.lease_id,
                    worker = r.worker_id,
                );
                span.in_scope(|| tracing::debug!("unit leased"));
                v1::Lease::from(l)
            })
            .collect();
        Ok(Response::new(v1::LeaseResponse {
            leases,
            retry_after_ms: grant.retry_after_ms,
        }))
    }

    async fn submit_result(
        &self,
        req: Request<v1::SubmitResultRequest>,
    ) -> Result<Response<v1::SubmitResultResponse>, Status> {
        self.authorize(&req)?;
        self.check_session(&req, req.get_ref().worker_id)?;
        let mut r = req.into_inner();
        let fence = std::mem::take(&mut r.fence);
        let span = tracing::info_span!(
            "unit",
            job = r.job_id,
            frame = tracing::field::Empty,
            tile = tracing::field::Empty,
            passes = tracing::field::Empty,
            lease_id = r.lease_id,
            worker = r.worker_id,
        );
        let (worker, lease_id, job_hint, render_seconds, traced_pixel_passes) = (
            r.worker_id,
            r.lease_id,
            r.job_id,
            r.render_seconds,
            r.traced_pixel_passes,
        );
        let result = UnitResult::try_from(r).map_err(|e| e.to_string());
        if let Ok(res) = &result {
            let u = res.unit;
            span.record("frame", u.frame);
            span.record("tile", u.tile);
            span.record(
                "passes",
                tracing::field::display(format_args!("{}..{}", u.first_pass, u.end_pass())),
            );
        }
        let delivery = Delivery {
            worker,
            lease_id,
            fence,
            job_hint,
            result,
            render_seconds,
            traced_pixel_passes,
        };
        let outcome = self
            .core
            .accept_result(delivery)
            .instrument(span.clone())
            .await;
        if outcome.is_err() {
            // Deposed while it was being accepted (`crate::ha`): UNAVAILABLE, so the worker
            // keeps the result and delivers it to the active coordinator.
            self.core.active().map_err(status)?;
        }
        let (accepted, reason) = match outcome {
            Ok(a) => {
                span.in_scope(|| tracing::debug!(reason = a.reason(), "result accepted"));
                (true, a.reason().to_string())
            }
            Err(e) => (false, e.to_string()),
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
        let bytes = self.core.scene_bytes(&hash).map_err(status)?;
        Ok(Response::new(Box::pin(tokio_stream::iter(scene_chunks(
            &bytes, &hash,
        )))))
    }

    async fn return_leases(
        &self,
        req: Request<v1::ReturnLeasesRequest>,
    ) -> Result<Response<v1::ReturnLeasesResponse>, Status> {
        self.authorize(&req)?;
        self.check_session(&req, req.get_ref().worker_id)?;
        let r = req.into_inner();
        let returned = if r.unusable.is_empty() {
            self.core.return_leases(r.worker_id, &r.lease_ids)
        } else {
            self.core
                .return_unusable(r.worker_id, &r.lease_ids, &r.unusable)
                .await
        }
        .map_err(status)?;
        Ok(Response::new(v1::ReturnLeasesResponse { returned }))
    }
}

/// The gRPC service of a standby coordinator (`crate::ha`): every request is answered
/// `UNAVAILABLE` with a message naming the state, so a worker moves on to the next
/// coordinator it knows. No token is checked: nothing is served.
#[derive(Clone)]
pub struct StandbyGrpc {
    message: &'static str,
}

impl StandbyGrpc {
    /// A standby service answering `message`.
    pub fn new(message: &'static str) -> Self {
        Self { message }
    }

    /// The tonic server wrapper of this service.
    pub fn into_server(self) -> v1::worker_service_server::WorkerServiceServer<Self> {
        v1::worker_service_server::WorkerServiceServer::new(self)
            .max_decoding_message_size(MAX_MESSAGE)
    }

    fn refuse<T>(&self) -> Result<Response<T>, Status> {
        Err(Status::unavailable(self.message))
    }
}

#[tonic::async_trait]
impl v1::worker_service_server::WorkerService for StandbyGrpc {
    async fn register(
        &self,
        _: Request<v1::RegisterRequest>,
    ) -> Result<Response<v1::RegisterResponse>, Status> {
        self.refuse()
    }

    async fn heartbeat(
        &self,
        _: Request<v1::HeartbeatRequest>,
    ) -> Result<Response<v1::HeartbeatResponse>, Status> {
        self.refuse()
    }

    async fn lease_work(
        &self,
        _: Request<v1::LeaseRequest>,
    ) -> Result<Response<v1::LeaseResponse>, Status> {
        self.refuse()
    }

    async fn submit_result(
        &self,
        _: Request<v1::SubmitResultRequest>,
    ) -> Result<Response<v1::SubmitResultResponse>, Status> {
        self.refuse()
    }

    type FetchSceneStream = SceneStream;

    async fn fetch_scene(
        &self,
        _: Request<v1::FetchSceneRequest>,
    ) -> Result<Response<SceneStream>, Status> {
        self.refuse()
    }

    async fn return_leases(
        &self,
        _: Request<v1::ReturnLeasesRequest>,
    ) -> Result<Response<v1::ReturnLeasesResponse>, Status> {
        self.refuse()
    }
}

/// A scene's bytes in [`SCENE_CHUNK`] pieces; the last one carries the hash so the
/// worker can check what it assembled (one empty chunk for an empty scene).
fn scene_chunks(bytes: &[u8], hash: &str) -> Vec<Result<v1::SceneChunk, Status>> {
    let total = bytes.len() as u64;
    if bytes.is_empty() {
        return vec![Ok(v1::SceneChunk {
            offset: 0,
            data: Vec::new(),
            total_size: 0,
            sha256: hash.to_string(),
        })];
    }
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
                sha256: if last {
                    hash.to_string()
                } else {
                    String::new()
                },
            })
        })
        .collect()
}
