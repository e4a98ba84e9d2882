//! The Tessera worker: a gRPC client loop around [`tessera_render::render::render_unit`].
//!
//! A worker registers with the coordinator, then repeatedly leases work units, renders
//! them on all its threads and submits the per-pass results, while heartbeats keep its
//! leases alive. It leases the next batch while one renders and submits results in the
//! background, so its threads do not wait on the network; batches are sized from the
//! measured time of a unit (docs/ARCHITECTURE.md §9, "The worker's pipeline"). Scenes are fetched once by content hash (in chunks, verified against
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
use std::collections::{HashMap, HashSet};
use std::future::Future;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tessera_farm::job::SceneRef;
use tessera_proto::v1;
use tessera_proto::LeasedUnit;
use tessera_render::render::{render_unit, render_unit_where};
use tessera_render::scene::RenderScene;
use tessera_scene::Scene;
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
    /// A testing aid (`--inject-faults`): the fraction of units whose result this worker
    /// corrupts ([`injects_fault`]), 0 for none. The corrupt results stay well-formed, so
    /// only the coordinator's spot checks catch them. Never set it in production.
    pub inject_faults: f64,
}

/// Salt of the `--inject-faults` selection, independent of the spot-check selection.
pub const INJECT_FAULTS_SALT: u64 = 0x496e_6a46_6175_6c74; // "InjFault"

/// Whether a worker started with `--inject-faults fraction` corrupts `unit` of job `job`:
/// a hash of the unit's identity against the fraction ([`tessera_farm::unit_selected`]),
/// so the same units on every run and every worker, and a test can compute which.
pub fn injects_fault(fraction: f64, job: u64, unit: &tessera_farm::WorkUnit) -> bool {
    tessera_farm::unit_selected(INJECT_FAULTS_SALT, fraction, job, unit)
}

/// Corrupts a result the way `--inject-faults` does: the lowest bit of the first traced value
/// flipped (of its absolute value, so it stays finite and non-negative): well-formed, so
/// validation accepts it, and a different digest, so a comparison does not.
fn corrupt(result: &mut tessera_farm::UnitResult) {
    // A traced pixel (nonzero): an untraced one of an adaptive lease is zeroed by the
    // coordinator before copies are compared, which would hide the fault.
    let first_traced = result
        .pass_means
        .iter()
        .position(|v| v[0] != 0.0)
        .unwrap_or(0);
    if let Some(v) = result.pass_means.get_mut(first_traced) {
        v[0] = f32::from_bits(v[0].abs().to_bits() ^ 1);
    }
}

/// A worker's TLS settings, read from PEM files by [`WorkerTls::from_files`].
///
/// Read from files, they are read again before every connection to a coordinator
/// ([`WorkerTls::reread`]): a certificate that rotates under a running worker (a
/// per-pod certificate that cert-manager's csi-driver renews before it expires,
/// docs/deploy.md) is presented on the next connection, without a restart.
#[derive(Clone)]
pub struct WorkerTls {
    /// The CA certificates (PEM) the coordinator's certificate must be issued by.
    pub ca_pem: Vec<u8>,
    /// The worker's certificate chain and private key (PEM), for mutual TLS.
    pub identity: Option<(Vec<u8>, Vec<u8>)>,
    /// The files they were read from, if they were: the CA, then the certificate and key.
    pub files: Option<TlsFiles>,
}

/// The PEM files of a [`WorkerTls`].
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TlsFiles {
    /// The CA certificates.
    pub ca: std::path::PathBuf,
    /// For mutual TLS: the worker's certificate chain and its private key.
    pub cert_and_key: Option<(std::path::PathBuf, std::path::PathBuf)>,
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
        let files = Some(TlsFiles {
            ca: ca.to_path_buf(),
            cert_and_key: cert_and_key.map(|(c, k)| (c.to_path_buf(), k.to_path_buf())),
        });
        Ok(Self {
            ca_pem,
            identity,
            files,
        })
    }

    /// The settings read again from the files they came from, if the files now hold
    /// something else; `None` when they did not come from files or are unchanged. An
    /// error (a file missing or half written during a rotation) names the file; the
    /// caller keeps the settings it has.
    pub fn reread(&self) -> Option<Result<Self, WorkerError>> {
        let files = self.files.as_ref()?;
        let cert_and_key = files
            .cert_and_key
            .as_ref()
            .map(|(c, k)| (c.as_path(), k.as_path()));
        match Self::from_files(&files.ca, cert_and_key) {
            Ok(fresh) if fresh.ca_pem == self.ca_pem && fresh.identity == self.identity => None,
            other => Some(other),
        }
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

/// Adds the bearer token to every request, and the session secret of the current
/// registration (worker.proto, "Sessions"; set by [`session`] once registered).
#[derive(Clone)]
struct Auth(Option<MetadataValue<tonic::metadata::Ascii>>, Session);

/// The session secret of the current registration, shared by the clones of a client.
type Session = Arc<Mutex<Option<MetadataValue<tonic::metadata::Ascii>>>>;

impl tonic::service::Interceptor for Auth {
    fn call(&mut self, mut req: Request<()>) -> Result<Request<()>, Status> {
        if let Some(v) = &self.0 {
            req.metadata_mut().insert("authorization", v.clone());
        }
        if let Some(v) = self.1.lock().ok().and_then(|s| s.clone()) {
            req.metadata_mut()
                .insert(tessera_proto::SESSION_METADATA, v);
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
    if !(0.0..=1.0).contains(&config.inject_faults) {
        return Err(WorkerError::Config(format!(
            "inject_faults {} must be between 0 and 1",
            config.inject_faults
        )));
    }
    if config.coordinators.is_empty() {
        return Err(WorkerError::Config(
            "no coordinator URL: give at least one (--coordinator)".into(),
        ));
    }
    let endpoints_for = |tls: Option<&WorkerTls>| {
        config
            .coordinators
            .iter()
            .map(|url| endpoint(url, tls))
            .collect::<Result<Vec<_>, _>>()
    };
    let mut tls = config.tls.clone();
    let mut endpoints = endpoints_for(tls.as_ref())?;
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
    if config.inject_faults > 0.0 {
        tracing::warn!(
            fraction = config.inject_faults,
            "--inject-faults: this worker corrupts a fraction of its results (a testing aid)"
        );
    }
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
            // Certificates rotate under a running worker: each connection presents the
            // files as they are now. Bad new files leave the current ones in use.
            if let Some(fresh) = tls.as_ref().and_then(WorkerTls::reread) {
                match fresh.and_then(|f| Ok((endpoints_for(Some(&f))?, f))) {
                    Ok((e, f)) => {
                        tracing::info!("TLS files changed: the next connections present them");
                        endpoints = e;
                        tls = Some(f);
                    }
                    Err(e) => {
                        tracing::warn!(error = %e, "TLS files changed but cannot be used; keeping the ones in force");
                    }
                }
            }
            match endpoints[next].connect().await {
                Ok(channel) => {
                    let session = Session::default();
                    let client = v1::worker_service_client::WorkerServiceClient::with_interceptor(
                        channel,
                        Auth(auth.clone(), session.clone()),
                    );
                    let serving = serve(
                        &config,
                        client,
                        &session,
                        &pool,
                        &cache,
                        stop_rx.clone(),
                        &mut carry,
                    );
                    match serving.await {
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
    /// The lease's seal, sent back with the result.
    fence: Vec<u8>,
    result: tessera_farm::UnitResult,
    seconds: f64,
    /// Pixel-passes traced (reported with the result).
    pixel_passes: u64,
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
        req.traced_pixel_passes = r.pixel_passes;
        req.fence = r.fence.clone();
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
    session_secret: &Session,
    pool: &Arc<rayon::ThreadPool>,
    cache: &Arc<Mutex<SceneCache>>,
    stop: tokio::sync::watch::Receiver<bool>,
    carry: &mut Carry,
) -> Result<(), Status> {
    let mut in_flight: Option<Submitting> = None;
    let r = session(
        config,
        client,
        session_secret,
        pool,
        cache,
        stop,
        carry,
        &mut in_flight,
    )
    .await;
    // A batch still being submitted when the session broke: keep what it did not deliver.
    if let Some(h) = in_flight.take() {
        if let Ok(Err((_, left))) = h.await {
            carry.results.extend(left);
        }
    }
    r
}

/// [`serve`]'s loop; `in_flight` is the batch being submitted in the background.
#[allow(clippy::too_many_arguments)]
async fn session(
    config: &WorkerConfig,
    mut client: Client,
    session_secret: &Session,
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
    let secret = MetadataValue::try_from(reg.session.as_str())
        .map_err(|_| Status::internal("the coordinator sent a session that is not ASCII"))?;
    if let Ok(mut s) = session_secret.lock() {
        *s = Some(secret);
    }
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
    // The pipeline (issue 14): one batch renders while the next one is leased and its
    // scenes loaded (`fetching`, then `next`), and the results of the one before are
    // submitted (`in_flight`, then `to_submit` while a submission is under way), so the
    // render threads wait on the network only when the coordinator has no work.
    let mut rendering: Option<Rendering> = None;
    let mut next: Option<Batch> = None;
    let mut fetching: Option<tokio::task::JoinHandle<Result<Fetched, Status>>> = None;
    // When to ask again after a lease request brought no unit.
    let mut retry_at: Option<tokio::time::Instant> = None;
    let mut to_submit: Vec<Rendered> = Vec::new();
    // The leases of the submission in flight: heartbeated until it ends, so a result
    // queued behind a slow submission does not lapse on the way.
    let mut submitting: Vec<u64> = Vec::new();
    // Leases the coordinator told us to drop (their job was canceled).
    let mut canceled: HashSet<u64> = HashSet::new();
    // Seconds one unit takes on one thread, measured (a moving average): sizes the batches.
    let mut unit_seconds: Option<f64> = None;
    // Whatever broke the session: the units in hand are finished anyway and kept for the
    // next coordinator, then the session ends with this status.
    let mut broken: Option<Status> = None;
    let mut stop = stop;
    // Whether the coordinator was told this worker is stopping.
    let mut drain_announced = false;
    let outcome = loop {
        let stopping = told_to_stop || *stop.borrow();
        if *stop.borrow() && !drain_announced && broken.is_none() {
            // Stopping (SIGTERM): say so at once, giving back the prefetched batch if any,
            // so /workers shows the worker draining while it finishes the units rendering
            // and the tail rule stops counting its threads.
            drain_announced = true;
            let b = next.take().unwrap_or_default();
            give_back(&mut client, worker_id, b).await;
        }
        // The pool is free: start the prefetched batch, or give it back when stopping.
        if rendering.is_none() && broken.is_none() {
            if let Some(mut b) = next.take() {
                b.units.retain(|(l, _)| !canceled.remove(&l.lease_id));
                if stopping {
                    if !b.units.is_empty() {
                        give_back(&mut client, worker_id, b).await;
                    }
                } else if !b.units.is_empty() {
                    rendering = Some(Rendering::start(pool, b, config.inject_faults));
                }
            }
        }
        // Lease the next batch while this one renders.
        let may_lease = retry_at.is_none_or(|t| t <= tokio::time::Instant::now());
        if !stopping && broken.is_none() && next.is_none() && fetching.is_none() && may_lease {
            retry_at = None;
            let max_units = units_to_ask(config.threads, unit_seconds);
            fetching = Some(tokio::spawn(fetch_batch(
                client.clone(),
                cache.clone(),
                worker_id,
                max_units,
            )));
        }
        // Submit in the background: the coordinator commits each result to its store
        // before acknowledging it, and the worker's threads should not wait for that. One
        // submission is in flight at a time; its errors end the session (what it did not
        // deliver goes to the next one).
        if in_flight.is_none() && !to_submit.is_empty() && broken.is_none() {
            let (mut c2, batch) = (client.clone(), std::mem::take(&mut to_submit));
            submitting = batch.iter().map(|r| r.lease_id).collect();
            *in_flight = Some(tokio::spawn(async move {
                submit_all(&mut c2, worker_id, batch).await
            }));
        }
        if rendering.is_none() && fetching.is_none() && in_flight.is_none() {
            if let Some(s) = broken.take() {
                // The prefetched batch, not started, is dropped: its leases lapse.
                carry.results.append(&mut to_submit);
                break Err(s);
            }
            if stopping && next.is_none() && to_submit.is_empty() {
                break Ok(());
            }
        }
        tokio::select! {
            r = join(rendering.as_mut().map(|r| &mut r.task)), if rendering.is_some() => {
                let done = rendering.take().map(|r| r.started.elapsed());
                let results = match r {
                    Ok(results) => results,
                    Err(e) => {
                        broken = Some(Status::internal(format!("render task failed: {e}")));
                        continue;
                    }
                };
                let seconds = done.unwrap_or_default().as_secs_f64().max(1e-9);
                let paths: f64 = results.iter().map(|r| r.paths).sum();
                paths_per_second = paths / seconds;
                unit_seconds = measured_unit_seconds(unit_seconds, &results);
                let (rendered, panicked, why) = sort_results(results, &mut canceled);
                if !panicked.is_empty() && broken.is_none() {
                    // A unit whose rendering panicked is a fault of its scene, not of this
                    // worker: give its lease back as unusable, so the coordinator fails the
                    // job after a few such returns instead of leasing the unit forever
                    // (docs/ARCHITECTURE.md §6).
                    let returned = client
                        .return_leases(v1::ReturnLeasesRequest {
                            worker_id,
                            lease_ids: panicked,
                            unusable: why,
                        })
                        .await;
                    if let Err(s) = returned {
                        broken = Some(s);
                    }
                }
                match &broken {
                    Some(_) => carry.results.extend(rendered),
                    None => to_submit.extend(rendered),
                }
            }
            f = join(fetching.as_mut()), if fetching.is_some() => {
                fetching = None;
                match f {
                    Ok(Ok(Fetched::Batch(b))) if broken.is_some() => drop(b),
                    Ok(Ok(Fetched::Batch(b))) => next = Some(b),
                    Ok(Ok(Fetched::Empty(wait))) => {
                        retry_at = Some(tokio::time::Instant::now() + wait);
                    }
                    Ok(Err(s)) => {
                        broken.get_or_insert(s);
                    }
                    Err(e) => {
                        broken.get_or_insert(Status::internal(format!("lease task failed: {e}")));
                    }
                }
            }
            s = join(in_flight.as_mut()), if in_flight.is_some() => {
                *in_flight = None;
                submitting.clear();
                match s {
                    Ok(Ok(())) => {}
                    Ok(Err((s, left))) => {
                        carry.results.extend(left);
                        broken.get_or_insert(s);
                    }
                    Err(e) => {
                        broken.get_or_insert(Status::internal(format!("submit task failed: {e}")));
                    }
                }
            }
            _ = beat.tick(), if broken.is_none() => {
                let lease_ids: Vec<u64> = rendering
                    .iter()
                    .flat_map(|r| r.lease_ids.iter().copied())
                    .chain(next.iter().flat_map(Batch::lease_ids))
                    .chain(to_submit.iter().map(|r| r.lease_id))
                    .chain(submitting.iter().copied())
                    .collect();
                match client
                    .heartbeat(v1::HeartbeatRequest { worker_id, lease_ids, paths_per_second })
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
            _ = sleep_until(retry_at), if retry_at.is_some() && !stopping => {}
            _ = stop.changed(), if !*stop.borrow() => {}
        }
        if broken.is_some() {
            // Nothing new is started; a lease request under way is abandoned (the units it
            // may bring lapse and are leased again).
            if let Some(f) = fetching.take() {
                f.abort();
            }
            next = None;
        }
    };
    outcome
}

/// Awaits the task `h`; never completes for `None` (the `select!` branches check).
async fn join<T>(h: Option<&mut tokio::task::JoinHandle<T>>) -> Result<T, tokio::task::JoinError> {
    match h {
        Some(h) => h.await,
        None => std::future::pending().await,
    }
}

/// Sleeps until `at`, forever if `None`.
async fn sleep_until(at: Option<tokio::time::Instant>) {
    match at {
        Some(at) => tokio::time::sleep_until(at).await,
        None => std::future::pending().await,
    }
}

/// Seconds of rendering one lease request aims to bring each thread (issue 14): long
/// enough that the coordinator's work per lease request is small beside it, short enough
/// that the scheduler's tail rule (`tessera_farm::tail_share`) has small batches to hand
/// out. The lease's round trip itself is hidden by prefetching.
const BATCH_SECONDS: f64 = 0.5;
/// Units per thread asked for before any unit was measured.
const FIRST_UNITS_PER_THREAD: u32 = 4;
/// Most units per thread asked for at once, however short they are.
const MAX_UNITS_PER_THREAD: u32 = 64;

/// How many units to ask for: about [`BATCH_SECONDS`] of rendering per thread at the
/// measured seconds per unit, [`FIRST_UNITS_PER_THREAD`] per thread before a measure.
///
/// Only the number of units leased at once depends on the clock, never what a unit is:
/// units are fixed when the job is planned (a tile and a pass range, checkpointed and
/// resumed by index), so the image does not depend on this.
fn units_to_ask(threads: usize, unit_seconds: Option<f64>) -> u32 {
    let per_thread = match unit_seconds {
        Some(s) if s.is_finite() && s > 0.0 => (BATCH_SECONDS / s)
            .round()
            .clamp(1.0, f64::from(MAX_UNITS_PER_THREAD))
            as u32,
        _ => FIRST_UNITS_PER_THREAD,
    };
    (threads as u32).saturating_mul(per_thread)
}

/// The moving average of seconds per unit after a batch: the batch's mean, weighted by
/// half against what was measured before (so a change of scene shows within a few
/// batches). Units that panicked are not counted.
fn measured_unit_seconds(before: Option<f64>, results: &[Outcome]) -> Option<f64> {
    let times: Vec<f64> = results
        .iter()
        .filter(|r| r.result.is_ok())
        .map(|r| r.seconds)
        .collect();
    if times.is_empty() {
        return before;
    }
    let mean = times.iter().sum::<f64>() / times.len() as f64;
    Some(match before {
        Some(b) => 0.5 * b + 0.5 * mean,
        None => mean,
    })
}

/// Splits a batch's outcomes into the results to submit (without those of canceled
/// leases, whose ids leave `canceled`) and the leases whose rendering panicked, with the
/// first panic's message.
fn sort_results(
    results: Vec<Outcome>,
    canceled: &mut HashSet<u64>,
) -> (Vec<Rendered>, Vec<u64>, String) {
    let mut rendered = Vec::with_capacity(results.len());
    let mut panicked = Vec::new();
    let mut why = String::new();
    for o in results {
        let dropped = canceled.remove(&o.lease_id);
        match o.result {
            Ok(result) if !dropped => rendered.push(Rendered {
                lease_id: o.lease_id,
                job_id: o.job_id,
                fence: o.fence,
                result,
                seconds: o.seconds,
                pixel_passes: o.pixel_passes,
            }),
            Ok(_) => {}
            Err(message) => {
                tracing::error!(lease_id = o.lease_id, job_id = o.job_id, error = %message, "rendering panicked; returning lease");
                if !dropped {
                    panicked.push(o.lease_id);
                }
                if why.is_empty() {
                    why = format!("rendering panicked: {message}");
                }
            }
        }
    }
    (rendered, panicked, why)
}

/// Leased units whose scenes are loaded and built, ready to render.
#[derive(Default)]
struct Batch {
    units: Vec<(LeasedUnit, Arc<RenderScene>)>,
}

impl Batch {
    fn lease_ids(&self) -> impl Iterator<Item = u64> + '_ {
        self.units.iter().map(|(l, _)| l.lease_id)
    }
}

/// What one lease request brought.
enum Fetched {
    /// Units to render.
    Batch(Batch),
    /// No unit (none usable): ask again after this long.
    Empty(Duration),
}

/// How long a lease request may wait at the coordinator for work (a long poll,
/// `LeaseRequest.wait_ms`). Without it an idle worker asks again every 50 ms, and a unit
/// that becomes leasable in between (an adaptive decision taken, a job queued) waits for
/// the next ask.
const LEASE_WAIT_MS: u32 = 1000;

/// Leases up to `max_units` units and makes sure every scene is here and built before
/// the clock starts; the leases of units whose scene cannot be used are returned as
/// unusable, saying why, so that the coordinator fails a job whose scene no worker can
/// use.
async fn fetch_batch(
    mut client: Client,
    cache: Arc<Mutex<SceneCache>>,
    worker_id: u64,
    max_units: u32,
) -> Result<Fetched, Status> {
    let resp = client
        .lease_work(v1::LeaseRequest {
            worker_id,
            max_units,
            wait_ms: LEASE_WAIT_MS,
        })
        .await?
        .into_inner();
    let wait = Duration::from_millis(u64::from(resp.retry_after_ms.clamp(20, 2000)));
    let mut units = Vec::with_capacity(resp.leases.len());
    let mut unusable = Vec::new();
    let mut why = String::new();
    for l in resp.leases {
        let l = match LeasedUnit::try_from(l) {
            Ok(l) => l,
            Err(e) => {
                tracing::warn!(error = %e, "coordinator sent an invalid lease");
                continue;
            }
        };
        match scene_for(&mut client, &cache, &l).await {
            Ok(rs) => units.push((l, rs)),
            Err(e) => {
                tracing::warn!(scene = %l.scene.source, error = %e, "cannot load scene; returning lease");
                unusable.push(l.lease_id);
                if why.is_empty() {
                    why = format!("scene {}: {e}", l.scene.source);
                }
            }
        }
    }
    if !unusable.is_empty() {
        client
            .return_leases(v1::ReturnLeasesRequest {
                worker_id,
                lease_ids: unusable,
                unusable: why,
            })
            .await?;
    }
    Ok(if units.is_empty() {
        Fetched::Empty(wait)
    } else {
        Fetched::Batch(Batch { units })
    })
}

/// Gives a batch that was never started back to the coordinator (a worker stopping):
/// its units are leased again at once instead of when their leases lapse. Sent with an
/// empty batch too, which tells the coordinator the worker is draining.
async fn give_back(client: &mut Client, worker_id: u64, batch: Batch) {
    let lease_ids: Vec<u64> = batch.lease_ids().collect();
    let n = lease_ids.len();
    match client
        .return_leases(v1::ReturnLeasesRequest {
            worker_id,
            lease_ids,
            unusable: String::new(),
        })
        .await
    {
        Ok(_) => tracing::info!(
            worker_id,
            leases = n,
            "draining: returned the units not started"
        ),
        Err(s) => {
            tracing::warn!(worker_id, leases = n, error = %s, "could not return the units not started; they lapse")
        }
    }
}

/// One unit's outcome on the pool.
struct Outcome {
    lease_id: u64,
    job_id: u64,
    /// The lease's seal.
    fence: Vec<u8>,
    /// The result, or the message of the renderer's panic.
    result: Result<tessera_farm::UnitResult, String>,
    /// Seconds it took on its thread.
    seconds: f64,
    /// Camera paths traced (0 if it panicked).
    paths: f64,
    /// Pixel-passes traced (0 if it panicked).
    pixel_passes: u64,
}

/// A batch rendering on the pool.
struct Rendering {
    task: tokio::task::JoinHandle<Vec<Outcome>>,
    lease_ids: Vec<u64>,
    started: Instant,
}

impl Rendering {
    /// Renders every unit of `batch` on the pool, on a blocking thread (never on the
    /// async runtime).
    /// `inject_faults` is [`WorkerConfig::inject_faults`].
    fn start(pool: &Arc<rayon::ThreadPool>, batch: Batch, inject_faults: f64) -> Self {
        let lease_ids = batch.lease_ids().collect();
        let pool = pool.clone();
        let task = tokio::task::spawn_blocking(move || {
            pool.install(|| {
                batch
                    .units
                    .par_iter()
                    .map(|(l, rs)| {
                        let t = Instant::now();
                        let (mut result, pixel_passes) = match render_contained(rs, l) {
                            Ok((r, n)) => (Ok(r), n),
                            Err(e) => (Err(e), 0),
                        };
                        if let Ok(r) = &mut result {
                            if injects_fault(inject_faults, l.job_id, &l.unit) {
                                corrupt(r);
                            }
                        }
                        Outcome {
                            lease_id: l.lease_id,
                            job_id: l.job_id,
                            fence: l.fence.clone(),
                            result,
                            seconds: t.elapsed().as_secs_f64(),
                            // Only the pixels traced count towards the throughput.
                            paths: pixel_passes as f64 * f64::from(l.plan.samples_per_pass),
                            pixel_passes,
                        }
                    })
                    .collect()
            })
        });
        Self {
            task,
            lease_ids,
            started: Instant::now(),
        }
    }
}

/// Set to a job seed, makes rendering every unit of jobs with that seed panic. For tests
/// of the panic containment only (no input is known to make the renderer panic); never set
/// it in production.
pub const TEST_PANIC_SEED_VAR: &str = "TESSERA_WORKER_TEST_PANIC_SEED";

/// Renders one leased unit, turning a panic of the renderer into `Err(message)`, so one
/// unit cannot end the worker's session (a panic would otherwise unwind through the rayon
/// pool into the blocking task and break the connection, and the unit would be leased
/// again forever). Also returns the pixel-passes traced.
///
/// Only the lease's wanted pixels are traced (issue 15); the others are left black, which
/// keeps the result's size, and the coordinator's adaptive policy never reads them. The
/// set was validated against the tile when the lease was decoded.
fn render_contained(
    rs: &RenderScene,
    l: &LeasedUnit,
) -> Result<(tessera_farm::UnitResult, u64), String> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        if std::env::var(TEST_PANIC_SEED_VAR).is_ok_and(|v| v == l.settings.seed.to_string()) {
            panic!("{TEST_PANIC_SEED_VAR} is {}", l.settings.seed);
        }
        let pixels = l.plan.tile(l.unit.tile).pixel_count() as u64;
        let all = pixels * u64::from(l.unit.pass_count);
        let Some(wanted) = &l.wanted else {
            return (render_unit(rs, &l.settings, &l.plan, l.unit), all);
        };
        // Counted where the renderer asks, so the figure is what was traced. The per-pixel
        // test is a binary search over the runs: nothing is allocated per pixel.
        let traced = std::cell::Cell::new(0u64);
        let result = render_unit_where(rs, &l.settings, &l.plan, l.unit, |i, _| {
            let yes = wanted.contains(i);
            traced.set(traced.get() + u64::from(yes));
            yes
        });
        // bdpt asks too: it traces camera subpaths for the wanted pixels only (the light
        // subpaths of every pixel still run, since their splats land anywhere).
        (result, traced.get())
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
/// frame's time ([`tessera_scene::job::frame_time`], the rule every renderer uses), from
/// its bytes kept in the cache; the built scenes of the last few times are kept.
async fn scene_for(
    client: &mut Client,
    cache: &Arc<Mutex<SceneCache>>,
    l: &LeasedUnit,
) -> Result<Arc<RenderScene>, String> {
    let (js, plan, frame) = (&l.scene, &l.plan, l.unit.frame);
    let key = js.parse_key();
    let time = tessera_scene::job::frame_time(js, frame);
    // The key of the built scene: the scene and camera, and the time (with the shutter)
    // for animated scenes.
    let timed_key = js.frame_key(frame);
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
            let bytes = match (&js.source, raw) {
                (SceneRef::Builtin(_), _) => None,
                (_, Some(b)) => b,
                (SceneRef::Hash(hash), None) => Some(Arc::new(fetch_scene(client, hash).await?)),
            };
            // The same loader as the coordinator's, so both see the same scene.
            let (js2, b2, t) = (js.clone(), bytes.clone(), time.clone());
            let parsed = tokio::task::spawn_blocking(move || {
                tessera_scene::job::load_job_scene_at(&js2, b2.as_deref().map(Vec::as_slice), &t)
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
    let raw = if parsed.animated && js.shutter.is_some() {
        lock()?.animated.get(&key).cloned().flatten()
    } else {
        None
    };
    let times = tessera_scene::job::shutter_times(js, frame);
    let js2 = js.clone();
    let built = tokio::task::spawn_blocking(move || {
        let keys = tessera_scene::job::shutter_scenes(&times, &parsed, |t| {
            tessera_scene::job::load_job_scene_at(&js2, raw.as_deref().map(Vec::as_slice), t)
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
