//! The Tessera worker: a gRPC client loop around [`tessera_render::render::render_unit`].
//!
//! A worker registers with the coordinator, then repeatedly leases work units, renders
//! them on all its threads and submits the per-pass results, while a heartbeat task keeps
//! its leases alive. Scenes are fetched once by content hash (in chunks, verified against
//! their SHA-256) and cached together with their built BVH, so a worker pays for a scene
//! once however many units of it it renders. When the coordinator is away the worker
//! reconnects with exponential backoff and registers again; on shutdown (its own, or a
//! heartbeat answering `shutdown` because the coordinator is stopping) it finishes the
//! units in hand, submits them, returns anything it has not started, and exits.
//!
//! # Failover (docs/deploy.md, "High availability")
//! A worker may know several coordinators ([`WorkerConfig::coordinators`]): the active
//! one and standbys on one PostgreSQL store. On a connection failure, or an answer
//! `UNAVAILABLE` (a standby, or a coordinator that lost the leadership), it tries the next
//! one at once, and backs off exponentially only after every one failed in a row, forever
//! until it is stopped. Results rendered for a coordinator that went away are kept and
//! submitted first to whichever coordinator it registers with next: a new active
//! coordinator adopts results of its predecessor's leases (they are below its lease
//! high-water mark) and merges each once, or compares it with the merged copy.
//!
//! Rendering is deterministic (docs/ARCHITECTURE.md §2): the bytes a worker submits for a unit depend
//! only on the scene, the settings and the unit, so the coordinator can compare duplicates.
#![deny(missing_docs)]

use rayon::prelude::*;
use sha2::{Digest, Sha256};
use std::collections::HashMap;
use std::future::Future;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tessera_farm::job::SceneRef;
use tessera_proto::v1;
use tessera_proto::LeasedUnit;
use tessera_render::render::render_unit;
use tessera_render::scene::RenderScene;
use tessera_scene::{Scene, SceneTime};
use tonic::metadata::MetadataValue;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::{Certificate, Channel, ClientTlsConfig, Endpoint, Identity};
use tonic::{Request, Status};

/// How to run a worker.
#[derive(Clone, Debug)]
pub struct WorkerConfig {
    /// The coordinators' gRPC URLs, e.g. `http://127.0.0.1:50051`, tried in this order
    /// (at least one; several for failover between an active coordinator and standbys).
    pub coordinators: Vec<String>,
    /// Rendering threads.
    pub threads: usize,
    /// A name shown in the coordinator's worker list.
    pub name: String,
    /// Bearer token for the coordinator's worker port, if it requires one.
    pub token: Option<String>,
    /// TLS for an `https://` coordinator URL: the CA to trust and, for mutual TLS, the
    /// worker's certificate and key. `None` for `http://`.
    pub tls: Option<WorkerTls>,
}

/// A worker's TLS settings, read from PEM files by [`WorkerTls::from_files`].
#[derive(Clone)]
pub struct WorkerTls {
    /// The CA certificates (PEM) the coordinator's certificate must be issued by.
    pub ca_pem: Vec<u8>,
    /// The worker's certificate chain and private key (PEM), for mutual TLS.
    pub identity: Option<(Vec<u8>, Vec<u8>)>,
}

impl std::fmt::Debug for WorkerTls {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("WorkerTls")
            .field("ca_pem_bytes", &self.ca_pem.len())
            .field("client_certificate", &self.identity.is_some())
            .finish()
    }
}

impl WorkerTls {
    /// Reads the CA file and, for mutual TLS, the certificate and key files, checking
    /// that each holds what it should (errors name the file).
    pub fn from_files(
        ca: &std::path::Path,
        cert_and_key: Option<(&std::path::Path, &std::path::Path)>,
    ) -> Result<Self, WorkerError> {
        use rustls::pki_types::pem::PemObject;
        use rustls::pki_types::{CertificateDer, PrivateKeyDer};
        let read = |p: &std::path::Path| {
            std::fs::read(p)
                .map_err(|e| WorkerError::Config(format!("cannot read {}: {e}", p.display())))
        };
        let certs = |p: &std::path::Path, bytes: &[u8]| {
            let n = CertificateDer::pem_slice_iter(bytes)
                .collect::<Result<Vec<_>, _>>()
                .map_err(|e| {
                    WorkerError::Config(format!("{}: malformed PEM certificate: {e}", p.display()))
                })?
                .len();
            if n == 0 {
                return Err(WorkerError::Config(format!(
                    "{}: no PEM certificate in the file",
                    p.display()
                )));
            }
            Ok(())
        };
        let ca_pem = read(ca)?;
        certs(ca, &ca_pem)?;
        let identity = match cert_and_key {
            None => None,
            Some((cert, key)) => {
                let cert_pem = read(cert)?;
                certs(cert, &cert_pem)?;
                let key_pem = read(key)?;
                PrivateKeyDer::from_pem_slice(&key_pem).map_err(|e| {
                    WorkerError::Config(format!(
                        "{}: no usable PEM private key: {e}",
                        key.display()
                    ))
                })?;
                Some((cert_pem, key_pem))
            }
        };
        Ok(Self { ca_pem, identity })
    }

    fn client_config(&self) -> ClientTlsConfig {
        let mut cfg = ClientTlsConfig::new().ca_certificate(Certificate::from_pem(&self.ca_pem));
        if let Some((cert, key)) = &self.identity {
            cfg = cfg.identity(Identity::from_pem(cert, key));
        }
        cfg
    }
}

/// Errors that end a worker.
#[derive(Debug, thiserror::Error)]
pub enum WorkerError {
    /// The configuration is unusable.
    #[error("invalid worker configuration: {0}")]
    Config(String),
    /// The coordinator refused this worker's credentials.
    #[error("the coordinator refused the worker token: {0}")]
    Unauthenticated(String),
}

/// Adds the bearer token to every request.
#[derive(Clone)]
struct Auth(Option<MetadataValue<tonic::metadata::Ascii>>);

impl tonic::service::Interceptor for Auth {
    fn call(&mut self, mut req: Request<()>) -> Result<Request<()>, Status> {
        if let Some(v) = &self.0 {
            req.metadata_mut().insert("authorization", v.clone());
        }
        Ok(req)
    }
}

type Client = v1::worker_service_client::WorkerServiceClient<InterceptedService<Channel, Auth>>;

/// An error and its causes, `: `-separated (tonic's transport errors hide the cause).
fn error_chain(e: &dyn std::error::Error) -> String {
    let mut out = e.to_string();
    let mut cur = e.source();
    while let Some(c) = cur {
        out.push_str(": ");
        out.push_str(&c.to_string());
        cur = c.source();
    }
    out
}

/// Scenes and their built forms, by scene reference and camera (`SCENE#CAMERA`).
#[derive(Default)]
struct SceneCache {
    /// Static scenes, parsed.
    scenes: HashMap<String, Arc<Scene>>,
    /// Animated scenes: their bytes (none for built-ins), parsed at each frame's time.
    animated: HashMap<String, Option<Arc<Vec<u8>>>>,
    /// Built render scenes by (scene and camera, width, height); a handful at most.
    built: Vec<(String, u32, u32, Arc<RenderScene>)>,
    /// Keys of `scenes` and `animated`, oldest first: a worker that serves job after job
    /// keeps the last [`SCENE_CACHE`] of them, not every scene it ever saw.
    order: std::collections::VecDeque<String>,
}

const BUILT_CACHE: usize = 4;
/// Parsed static scenes and animated scenes' bytes kept, together.
const SCENE_CACHE: usize = 8;

impl SceneCache {
    /// Records that `key` was just added to `scenes` or `animated`, and forgets the
    /// oldest entries beyond [`SCENE_CACHE`] (a lease still rendering one keeps its own
    /// `Arc`; a later lease fetches it again).
    fn added(&mut self, key: &str) {
        self.order.retain(|k| k != key);
        self.order.push_back(key.to_string());
        while self.order.len() > SCENE_CACHE {
            if let Some(old) = self.order.pop_front() {
                self.scenes.remove(&old);
                self.animated.remove(&old);
            }
        }
    }
}

/// Runs a worker until `shutdown` completes. Transport failures are retried with backoff;
/// only a configuration error or a refused token ends it early.
pub async fn run(
    config: WorkerConfig,
    shutdown: impl Future<Output = ()>,
) -> Result<(), WorkerError> {
    if config.threads == 0 || config.threads > 4096 {
        return Err(WorkerError::Config(format!(
            "threads {} must be between 1 and 4096",
            config.threads
        )));
    }
    if config.coordinators.is_empty() {
        return Err(WorkerError::Config(
            "no coordinator URL: give at least one (--coordinator)".into(),
        ));
    }
    let endpoints = config
        .coordinators
        .iter()
        .map(|url| endpoint(url, config.tls.as_ref()))
        .collect::<Result<Vec<_>, _>>()?;
    let auth = match &config.token {
        Some(t) => Some(
            format!("Bearer {t}")
                .parse()
                .map_err(|_| WorkerError::Config("the token must be printable ASCII".into()))?,
        ),
        None => None,
    };
    let pool = Arc::new(
        rayon::ThreadPoolBuilder::new()
            .num_threads(config.threads)
            .thread_name(|i| format!("tessera-render-{i}"))
            .build()
            .map_err(|e| WorkerError::Config(format!("thread pool: {e}")))?,
    );
    let cache = Arc::new(Mutex::new(SceneCache::default()));
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    let session = async {
        let n = endpoints.len();
        let mut carry = Carry::default();
        let mut backoff = Duration::from_millis(100);
        // Which coordinator to try next, and how many failed in a row.
        let (mut next, mut failed) = (0usize, 0usize);
        // Attempts made since the stop was asked for, to deliver results still in hand.
        let mut after_stop = 0usize;
        loop {
            if *stop_rx.borrow() {
                if carry.results.is_empty() || after_stop >= n {
                    if !carry.results.is_empty() {
                        tracing::warn!(
                            results = carry.results.len(),
                            "stopping with results no coordinator took; they are rendered again"
                        );
                    }
                    return Ok(());
                }
                after_stop += 1;
            }
            let url = &config.coordinators[next];
            carry.registered = false;
            match endpoints[next].connect().await {
                Ok(channel) => {
                    let client = v1::worker_service_client::WorkerServiceClient::with_interceptor(
                        channel,
                        Auth(auth.clone()),
                    );
                    match serve(&config, client, &pool, &cache, stop_rx.clone(), &mut carry).await {
                        Ok(()) => return Ok(()),
                        Err(s) if s.code() == tonic::Code::Unauthenticated => {
                            return Err(WorkerError::Unauthenticated(s.message().to_string()))
                        }
                        Err(s) if s.code() == tonic::Code::Unavailable && !carry.registered => {
                            // A standby, or a coordinator that lost the leadership.
                            tracing::debug!(coordinator = %url, error = %s.message(), "coordinator not active");
                        }
                        Err(s) => {
                            tracing::warn!(coordinator = %url, error = %s, "coordinator connection lost");
                        }
                    }
                }
                Err(e) => {
                    // A refused TLS handshake (a wrong CA, a missing client certificate)
                    // looks like this too: say it at the longest backoff, not only in
                    // debug logs.
                    let cause = error_chain(&e);
                    if backoff >= Duration::from_secs(5) {
                        tracing::warn!(coordinator = %url, error = %cause, "coordinator not reachable");
                    } else {
                        tracing::debug!(coordinator = %url, error = %cause, "coordinator not reachable");
                    }
                }
            }
            if carry.registered {
                // It served for a while: start over with short waits.
                failed = 0;
                backoff = Duration::from_millis(100);
            }
            failed += 1;
            next = (next + 1) % n;
            if failed < n {
                // Another coordinator may be the active one: try it at once.
                continue;
            }
            failed = 0;
            let mut stop = stop_rx.clone();
            tokio::select! {
                _ = tokio::time::sleep(backoff) => {}
                _ = stop.changed() => {}
            }
            backoff = (backoff * 2).min(Duration::from_secs(5));
        }
    };
    tokio::pin!(session);
    tokio::pin!(shutdown);
    tokio::select! {
        r = &mut session => r,
        _ = &mut shutdown => {
            // Ask the session to finish what it holds, then wait for it.
            let _ = stop_tx.send(true);
            session.await
        }
    }
}

/// The endpoint of one coordinator URL, with TLS for `https://` (and only then).
fn endpoint(url: &str, tls: Option<&WorkerTls>) -> Result<Endpoint, WorkerError> {
    let mut endpoint = Endpoint::from_shared(url.to_string())
        .map_err(|e| WorkerError::Config(format!("coordinator URL {url:?}: {e}")))?
        .connect_timeout(Duration::from_secs(5))
        // HTTP/2 pings find a connection whose peer vanished without closing it (a cut
        // link, a frozen host): without them a call waits on TCP retransmission for many
        // minutes instead of failing over to the next coordinator.
        .http2_keep_alive_interval(Duration::from_secs(10))
        .keep_alive_timeout(Duration::from_secs(10))
        .keep_alive_while_idle(true)
        .tcp_nodelay(true);
    let https = url.starts_with("https://");
    match (tls, https) {
        (Some(tls), true) => {
            endpoint = endpoint
                .tls_config(tls.client_config())
                .map_err(|e| WorkerError::Config(format!("TLS: {e}")))?;
        }
        (Some(_), false) => {
            return Err(WorkerError::Config(format!(
                "TLS files were given but the coordinator URL {url:?} is not https://"
            )))
        }
        (None, true) => {
            return Err(WorkerError::Config(format!(
                "the coordinator URL {url:?} is https://: give the CA to trust (--tls-ca)"
            )))
        }
        (None, false) => {}
    }
    Ok(endpoint)
}

/// A rendered unit waiting to be submitted.
struct Rendered {
    lease_id: u64,
    job_id: u64,
    result: tessera_farm::UnitResult,
    seconds: f64,
}

/// What outlives one session with a coordinator.
#[derive(Default)]
struct Carry {
    /// Results rendered and not yet answered by a coordinator: submitted first in the
    /// next session, whichever coordinator it is with.
    results: Vec<Rendered>,
    /// Whether the last session got as far as registering (then the coordinator was the
    /// active one).
    registered: bool,
}

/// Submits `results` in order; on a failure returns the status with the results not yet
/// answered (the failed one first), for the next session.
async fn submit_all(
    client: &mut Client,
    worker_id: u64,
    results: Vec<Rendered>,
) -> Result<(), (Status, Vec<Rendered>)> {
    let mut rest = results.into_iter();
    while let Some(r) = rest.next() {
        let mut req =
            v1::SubmitResultRequest::from_result(worker_id, r.lease_id, &r.result, r.seconds);
        req.job_id = r.job_id;
        match client.submit_result(req).await {
            Ok(resp) => {
                let resp = resp.into_inner();
                if !resp.accepted {
                    tracing::warn!(lease_id = r.lease_id, reason = %resp.reason, "result not accepted");
                }
            }
            Err(s) => {
                let mut left = vec![r];
                left.extend(rest);
                return Err((s, left));
            }
        }
    }
    Ok(())
}

type Submitting = tokio::task::JoinHandle<Result<(), (Status, Vec<Rendered>)>>;

/// One registered session with a coordinator. Returns `Ok` when asked to stop, or the
/// status that broke the connection; results it could not deliver are left in `carry`.
async fn serve(
    config: &WorkerConfig,
    client: Client,
    pool: &Arc<rayon::ThreadPool>,
    cache: &Arc<Mutex<SceneCache>>,
    stop: tokio::sync::watch::Receiver<bool>,
    carry: &mut Carry,
) -> Result<(), Status> {
    let mut in_flight: Option<Submitting> = None;
    let r = session(config, client, pool, cache, stop, carry, &mut in_flight).await;
    // A batch still being submitted when the session broke: keep what it did not deliver.
    if let Some(h) = in_flight.take() {
        if let Ok(Err((_, left))) = h.await {
            carry.results.extend(left);
        }
    }
    r
}

/// [`serve`]'s loop; `in_flight` is the batch being submitted in the background.
async fn session(
    config: &WorkerConfig,
    mut client: Client,
    pool: &Arc<rayon::ThreadPool>,
    cache: &Arc<Mutex<SceneCache>>,
    stop: tokio::sync::watch::Receiver<bool>,
    carry: &mut Carry,
    in_flight: &mut Option<Submitting>,
) -> Result<(), Status> {
    let reg = client
        .register(v1::RegisterRequest {
            name: config.name.clone(),
            threads: config.threads as u32,
            version: env!("CARGO_PKG_VERSION").to_string(),
            capabilities: vec!["path".into(), "direct".into()],
        })
        .await?
        .into_inner();
    let worker_id = reg.worker_id;
    let heartbeat_every =
        Duration::from_millis(u64::from(reg.heartbeat_interval_ms.clamp(50, 60_000)));
    tracing::info!(worker_id, name = %config.name, "registered");
    carry.registered = true;
    if !carry.results.is_empty() {
        // Rendered for a coordinator that went away (or this one before it restarted).
        let results = std::mem::take(&mut carry.results);
        tracing::warn!(
            worker_id,
            results = results.len(),
            "submitting results rendered before the reconnection"
        );
        if let Err((s, left)) = submit_all(&mut client, worker_id, results).await {
            carry.results = left;
            return Err(s);
        }
    }
    let mut paths_per_second = 0.0f64;
    // Set when a heartbeat says the coordinator is shutting down: finish the units in hand
    // as on our own shutdown.
    let mut told_to_stop = false;
    // One heartbeat clock for the whole session, so batches shorter than the interval
    // still heartbeat (a timer restarted per batch would never fire).
    let mut beat = tokio::time::interval_at(
        tokio::time::Instant::now() + heartbeat_every,
        heartbeat_every,
    );
    beat.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        if told_to_stop || *stop.borrow() {
            // Deliver what is rendered before leaving.
            if let Some(h) = in_flight.take() {
                finish(h, carry).await?;
            }
            return Ok(());
        }
        let resp = client
            .lease_work(v1::LeaseRequest {
                worker_id,
                // Four units per thread: a batch long enough that the lease round trip is small
                // beside it, short enough that coarse-to-fine order stays fine-grained.
                max_units: (config.threads * 4) as u32,
            })
            .await?
            .into_inner();
        if resp.leases.is_empty() {
            let wait = Duration::from_millis(u64::from(resp.retry_after_ms.clamp(20, 2000)));
            let mut stop = stop.clone();
            tokio::select! {
                _ = tokio::time::sleep(wait) => {}
                _ = stop.changed() => {}
            }
            continue;
        }
        let mut leases = Vec::with_capacity(resp.leases.len());
        for l in resp.leases {
            match LeasedUnit::try_from(l) {
                Ok(l) => leases.push(l),
                Err(e) => tracing::warn!(error = %e, "coordinator sent an invalid lease"),
            }
        }
        // Make sure every scene is here and built before the clock starts.
        let mut jobs: Vec<(LeasedUnit, Arc<RenderScene>)> = Vec::with_capacity(leases.len());
        let mut unusable = Vec::new();
        let mut why = String::new();
        for l in leases {
            match scene_for(&mut client, cache, &l).await {
                Ok(rs) => jobs.push((l, rs)),
                Err(e) => {
                    tracing::warn!(scene = %l.scene, error = %e, "cannot load scene; returning lease");
                    unusable.push(l.lease_id);
                    if why.is_empty() {
                        why = format!("scene {}: {e}", l.scene);
                    }
                }
            }
        }
        if !unusable.is_empty() {
            // Saying why lets the coordinator fail a job whose scene no worker can use.
            client
                .return_leases(v1::ReturnLeasesRequest {
                    worker_id,
                    lease_ids: unusable,
                    unusable: why,
                })
                .await?;
        }
        // Render on the pool while heartbeats keep the leases alive.
        let lease_ids: Vec<u64> = jobs.iter().map(|(l, _)| l.lease_id).collect();
        let pool2 = pool.clone();
        let started = Instant::now();
        let mut render = tokio::task::spawn_blocking(move || {
            pool2.install(|| {
                jobs.par_iter()
                    .map(|(l, rs)| {
                        let t = Instant::now();
                        let r = render_contained(rs, l);
                        let paths = r.as_ref().map_or(0.0, |r| {
                            r.pass_means.len() as f64 * f64::from(l.plan.samples_per_pass)
                        });
                        (l.lease_id, l.job_id, r, t.elapsed().as_secs_f64(), paths)
                    })
                    .collect::<Vec<_>>()
            })
        });
        let mut canceled: Vec<u64> = Vec::new();
        // A heartbeat that failed: the units in hand are finished anyway and kept for the
        // next coordinator, then the session ends with this status.
        let mut broken: Option<Status> = None;
        let results = loop {
            tokio::select! {
                r = &mut render => break r.map_err(|e| Status::internal(format!("render task failed: {e}")))?,
                _ = beat.tick(), if broken.is_none() => {
                    match client
                        .heartbeat(v1::HeartbeatRequest { worker_id, lease_ids: lease_ids.clone(), paths_per_second })
                        .await
                    {
                        Ok(hb) => {
                            let hb = hb.into_inner();
                            canceled.extend(hb.cancel);
                            if hb.shutdown && !told_to_stop {
                                tracing::info!(worker_id, "the coordinator is shutting down; finishing the units in hand");
                                told_to_stop = true;
                            }
                        }
                        Err(s) => {
                            tracing::warn!(worker_id, error = %s, "heartbeat failed; finishing the units in hand to deliver them elsewhere");
                            broken = Some(s);
                        }
                    }
                }
            }
        };
        let seconds = started.elapsed().as_secs_f64().max(1e-9);
        let paths: f64 = results.iter().map(|r| r.4).sum();
        paths_per_second = paths / seconds;
        // A unit whose rendering panicked is a fault of its scene, not of this worker:
        // give its lease back as unusable, so the coordinator fails the job after a few
        // such returns instead of leasing the unit forever (docs/ARCHITECTURE.md §6).
        let mut rendered = Vec::with_capacity(results.len());
        let mut panicked = Vec::new();
        let mut why = String::new();
        for (lease_id, job_id, result, secs, paths) in results {
            match result {
                Ok(r) => rendered.push((lease_id, job_id, r, secs, paths)),
                Err(message) => {
                    tracing::error!(lease_id, job_id, error = %message, "rendering panicked; returning lease");
                    if !canceled.contains(&lease_id) {
                        panicked.push(lease_id);
                    }
                    if why.is_empty() {
                        why = format!("rendering panicked: {message}");
                    }
                }
            }
        }
        let rendered: Vec<Rendered> = rendered
            .into_iter()
            .filter(|r| !canceled.contains(&r.0))
            .map(|(lease_id, job_id, result, seconds, _)| Rendered {
                lease_id,
                job_id,
                result,
                seconds,
            })
            .collect();
        if let Some(s) = broken {
            carry.results.extend(rendered);
            return Err(s);
        }
        if !panicked.is_empty() {
            let returned = client
                .return_leases(v1::ReturnLeasesRequest {
                    worker_id,
                    lease_ids: panicked,
                    unusable: why,
                })
                .await;
            if let Err(s) = returned {
                carry.results.extend(rendered);
                return Err(s);
            }
        }
        // Submit in the background while the next units render: the coordinator commits
        // each result to its store before acknowledging it, and the worker's threads should
        // not wait for that. One batch is in flight at a time; its errors end the session
        // (what it did not deliver goes to the next one).
        if let Some(h) = in_flight.take() {
            if let Err(s) = finish(h, carry).await {
                carry.results.extend(rendered);
                return Err(s);
            }
        }
        let mut c2 = client.clone();
        *in_flight = Some(tokio::spawn(async move {
            submit_all(&mut c2, worker_id, rendered).await
        }));
    }
}

/// Waits for a background submission; what it did not deliver goes into `carry`.
async fn finish(h: Submitting, carry: &mut Carry) -> Result<(), Status> {
    match h.await {
        Ok(Ok(())) => Ok(()),
        Ok(Err((s, left))) => {
            carry.results.extend(left);
            Err(s)
        }
        Err(e) => Err(Status::internal(format!("submit task failed: {e}"))),
    }
}

/// Set to a job seed, makes rendering every unit of jobs with that seed panic. For tests
/// of the panic containment only (no input is known to make the renderer panic); never set
/// it in production.
pub const TEST_PANIC_SEED_VAR: &str = "TESSERA_WORKER_TEST_PANIC_SEED";

/// Renders one leased unit, turning a panic of the renderer into `Err(message)`, so one
/// unit cannot end the worker's session (a panic would otherwise unwind through the rayon
/// pool into the blocking task and break the connection, and the unit would be leased
/// again forever).
fn render_contained(rs: &RenderScene, l: &LeasedUnit) -> Result<tessera_farm::UnitResult, String> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        if std::env::var(TEST_PANIC_SEED_VAR).is_ok_and(|v| v == l.settings.seed.to_string()) {
            panic!("{TEST_PANIC_SEED_VAR} is {}", l.settings.seed);
        }
        render_unit(rs, &l.settings, &l.plan, l.unit)
    }))
    .map_err(|payload| panic_message(payload.as_ref()))
}

/// The message of a panic payload (`panic!` with a literal or a formatted string).
fn panic_message(payload: &(dyn std::any::Any + Send)) -> String {
    if let Some(s) = payload.downcast_ref::<&str>() {
        (*s).to_string()
    } else if let Some(s) = payload.downcast_ref::<String>() {
        s.clone()
    } else {
        "a panic without a message".to_string()
    }
}

/// The built scene for a lease, from the cache or fetched and built now.
///
/// A static scene is parsed once and built once per image size, whatever the frame. An
/// animated one (glTF animations, [`Scene::animated`]) is parsed and built at each
/// frame's time (`frame / fps`, [`tessera_scene::job::frame_time`]'s rule), from its bytes
/// kept in the cache; the built scenes of the last few times are kept.
async fn scene_for(
    client: &mut Client,
    cache: &Arc<Mutex<SceneCache>>,
    l: &LeasedUnit,
) -> Result<Arc<RenderScene>, String> {
    let (scene, plan) = (&l.scene, &l.plan);
    let key = match l.camera.as_deref() {
        Some(c) => format!("{scene}#{c}"),
        None => scene.to_string(),
    };
    let time = SceneTime {
        seconds: f64::from(l.unit.frame) / l.fps,
        animation: l.animation.clone(),
    };
    // The key of the built scene: the scene and camera, and the time (with the shutter)
    // for animated scenes.
    let timed_key = format!(
        "{key}@{}#{}#{:?}",
        time.seconds,
        time.animation.as_deref().unwrap_or(""),
        l.shutter.map(<[f64; 2]>::from)
    );
    let lock = || cache.lock().map_err(|_| "scene cache poisoned".to_string());
    let built_key = {
        let c = lock()?;
        let built_key = if c.animated.contains_key(&key) {
            timed_key.clone()
        } else {
            key.clone()
        };
        if let Some((_, _, _, rs)) = c
            .built
            .iter()
            .find(|(k, w, h, _)| *k == built_key && *w == plan.width && *h == plan.height)
        {
            return Ok(rs.clone());
        }
        built_key
    };
    let (cached, raw) = {
        let c = lock()?;
        (c.scenes.get(&key).cloned(), c.animated.get(&key).cloned())
    };
    let (parsed, built_key) = match cached {
        Some(s) => (s, built_key),
        None => {
            let bytes = match (scene, raw) {
                (SceneRef::Builtin(_), _) => None,
                (_, Some(b)) => b,
                (SceneRef::Hash(hash), None) => Some(Arc::new(fetch_scene(client, hash).await?)),
            };
            // The same loader as the coordinator's, so both see the same scene.
            let (sref, cam, b2, t) = (scene.clone(), l.camera.clone(), bytes.clone(), time.clone());
            let parsed = tokio::task::spawn_blocking(move || {
                tessera_scene::job::load_job_scene_at(
                    &sref,
                    b2.as_deref().map(Vec::as_slice),
                    cam.as_deref(),
                    &t,
                )
            })
            .await
            .map_err(|e| e.to_string())?
            .map_err(|e| e.to_string())?;
            let parsed = Arc::new(parsed);
            let mut c = lock()?;
            if parsed.animated {
                // Parsed again for every time: keep the bytes, not the scene.
                c.animated.insert(key.clone(), bytes);
                c.added(&key);
                (parsed, timed_key)
            } else {
                c.scenes.insert(key.clone(), parsed.clone());
                c.added(&key);
                (parsed, key.clone())
            }
        }
    };
    let (w, h) = (plan.width, plan.height);
    // Motion blur: an animated scene with a shutter is also loaded at the shutter's key
    // times (from the bytes kept for it), as `tessera render` does.
    let raw = if parsed.animated && l.shutter.is_some() {
        lock()?.animated.get(&key).cloned().flatten()
    } else {
        None
    };
    let times = tessera_scene::job::shutter_times_of(
        l.shutter,
        l.fps,
        l.animation.as_deref(),
        l.unit.frame,
    );
    let (sref, cam) = (scene.clone(), l.camera.clone());
    let built = tokio::task::spawn_blocking(move || {
        let keys = tessera_scene::job::shutter_scenes_of(&times, &parsed, |t| {
            tessera_scene::job::load_job_scene_at(
                &sref,
                raw.as_deref().map(Vec::as_slice),
                cam.as_deref(),
                t,
            )
        })
        .map_err(|e| e.to_string())?;
        RenderScene::build_in_motion(&parsed, &keys, w, h).map_err(|e| e.to_string())
    })
    .await
    .map_err(|e| e.to_string())??;
    let built = Arc::new(built);
    let mut c = lock()?;
    c.built.push((built_key, w, h, built.clone()));
    if c.built.len() > BUILT_CACHE {
        c.built.remove(0);
    }
    Ok(built)
}

/// Fetches a scene's bytes by content hash and checks them against it.
async fn fetch_scene(client: &mut Client, hash: &str) -> Result<Vec<u8>, String> {
    let mut stream = client
        .fetch_scene(v1::FetchSceneRequest {
            scene_hash: hash.to_string(),
        })
        .await
        .map_err(|s| format!("fetch scene {hash}: {}", s.message()))?
        .into_inner();
    let mut bytes = Vec::new();
    while let Some(chunk) = stream
        .message()
        .await
        .map_err(|s| format!("fetch scene {hash}: {}", s.message()))?
    {
        if chunk.offset != bytes.len() as u64 {
            return Err(format!(
                "scene {hash}: chunk at offset {} after {} bytes",
                chunk.offset,
                bytes.len()
            ));
        }
        if chunk.total_size > tessera_scene::MAX_INPUT_BYTES {
            return Err(format!(
                "scene {hash}: {} bytes is too large",
                chunk.total_size
            ));
        }
        bytes.extend_from_slice(&chunk.data);
    }
    let digest = Sha256::digest(&bytes);
    let hex: String = digest.iter().map(|b| format!("{b:02x}")).collect();
    if hex != hash {
        return Err(format!("scene {hash}: received bytes hash to {hex}"));
    }
    Ok(bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_scene_cache_keeps_the_newest_scenes() {
        let mut c = SceneCache::default();
        let scene = Arc::new(tessera_scene::load("builtin:furnace").unwrap());
        for i in 0..SCENE_CACHE + 3 {
            let key = format!("s{i}");
            if i % 2 == 0 {
                c.scenes.insert(key.clone(), scene.clone());
            } else {
                c.animated.insert(key.clone(), None);
            }
            c.added(&key);
        }
        assert_eq!(c.scenes.len() + c.animated.len(), SCENE_CACHE);
        // The oldest three are gone, the newest are kept.
        for i in 0..3 {
            let key = format!("s{i}");
            assert!(!c.scenes.contains_key(&key) && !c.animated.contains_key(&key));
        }
        let newest = format!("s{}", SCENE_CACHE + 2);
        assert!(c.scenes.contains_key(&newest) || c.animated.contains_key(&newest));
        // Adding a key again moves it to the back instead of counting it twice.
        c.added("s3");
        assert_eq!(c.order.len(), SCENE_CACHE);
        assert_eq!(c.order.back().map(String::as_str), Some("s3"));
    }
}
