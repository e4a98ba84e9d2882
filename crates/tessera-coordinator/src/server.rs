//! Serving a coordinator: the HTTP API and the workers' gRPC port on listeners the caller
//! bound, the ticker, and a graceful shutdown (ARCHITECTURE.md §1, §9).
//!
//! [`serve`] (or [`serve_coordinator`] for a coordinator already open) runs until its
//! `shutdown` future completes, then stops in this order:
//!
//! 1. The HTTP server stops accepting connections and lets the requests in flight finish
//!    (hyper's graceful shutdown; the connection loop with its limits and timeouts is in
//!    [`crate::connections`]).
//! 2. Workers are told to stop ([`Coordinator::begin_shutdown`]): from now on every
//!    heartbeat answers `shutdown = true` and no new unit is leased, so a worker rendering
//!    units finishes them, delivers the results and exits. The gRPC port
//!    stays open until no worker holds a lease any more, or for [`WORKER_DRAIN`] at most.
//! 3. The gRPC server drains (tonic's graceful shutdown: no new connections, the calls in
//!    flight finish).
//! 4. The ticker stops, the graceful end is recorded in the store (so the next start
//!    does not count it as a crash, docs/store.md) and the store is closed.
//!
//! Steps 1 and 3 together are bounded by [`SERVER_SHUTDOWN`]; after it the servers are
//! abandoned and `serve` returns anyway.
//!
//! ```no_run
//! # async fn run() -> Result<(), tessera_coordinator::ServeError> {
//! use tessera_coordinator::{serve, shutdown_signal, Listeners};
//! use tessera_coordinator::service::CoordinatorConfig;
//!
//! let listeners = Listeners {
//!     http: tokio::net::TcpListener::bind("127.0.0.1:0").await?,
//!     grpc: tokio::net::TcpListener::bind("127.0.0.1:0").await?,
//! };
//! println!("http: http://{}/api/v1", listeners.http.local_addr()?);
//! serve(CoordinatorConfig::new("tessera-data"), listeners, shutdown_signal()).await
//! # }
//! ```

use std::future::Future;
use std::sync::Arc;
use std::time::Duration;

use tessera_api::WorkerState;
use tokio::net::TcpListener;
use tokio::sync::{mpsc, oneshot};
use tokio::task::JoinHandle;

use crate::connections::{serve_http, ConnectionStats};
use crate::grpc::WorkerGrpc;
use crate::service::{Coordinator, CoordinatorConfig};
use crate::store::StoreError;
use crate::tls::{ServerTls, TlsError};
use tessera_proto::v1;

/// How long a shutting-down coordinator waits for workers to deliver the units they hold.
pub const WORKER_DRAIN: Duration = Duration::from_secs(5);

/// How long the HTTP and gRPC servers get to finish their requests in flight once told to
/// stop.
pub const SERVER_SHUTDOWN: Duration = Duration::from_secs(5);

/// The two bound listeners a coordinator serves on (bind port 0 to let the system choose,
/// then read `local_addr`).
#[derive(Debug)]
pub struct Listeners {
    /// The HTTP API v1 and the dashboard.
    pub http: TcpListener,
    /// The workers' gRPC port.
    pub grpc: TcpListener,
}

/// Why [`serve`] failed.
#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    /// The store could not be opened.
    #[error("opening the store: {0}")]
    Open(#[from] StoreError),
    /// A listener's address could not be read.
    #[error("{0}")]
    Io(#[from] std::io::Error),
    /// The gRPC server stopped with an error before it was asked to stop.
    #[error("the gRPC server failed: {0}")]
    Grpc(tonic::transport::Error),
    /// The TLS files could not be loaded.
    #[error("TLS: {0}")]
    Tls(#[from] TlsError),
}

/// Opens the coordinator described by `config` and serves it on `listeners` until
/// `shutdown` completes (see the module documentation for the shutdown order). On a
/// PostgreSQL store it is [`crate::ha::serve_ha`]: a standby until it holds the store's
/// leadership.
///
/// The compiler cannot prove this future `Send` (the store's open trips rustc's
/// higher-ranked `Send` check on sqlx futures), so await it on the task that owns it
/// (`block_on`, `join!`); to spawn the server, open the [`Coordinator`] first and spawn
/// [`serve_coordinator`], whose future is `Send`.
pub async fn serve(
    config: CoordinatorConfig,
    listeners: Listeners,
    shutdown: impl Future<Output = ()>,
) -> Result<(), ServeError> {
    if let crate::store::StoreUrl::Postgres(url) = config.store_url() {
        let store = crate::store::PostgresStore::open(&url).await?;
        return crate::ha::serve_ha(config, store, &url, listeners, shutdown).await;
    }
    let core = Coordinator::open(config).await?;
    serve_coordinator(core, listeners, shutdown).await
}

/// Serves an open coordinator on `listeners` until `shutdown` completes, or until one of
/// the servers fails (then the other is shut down the same way and the failure returned).
///
/// On a SQLite store whose disk is full — the coordinator started on it over a read-only
/// view ([`Coordinator::open`]), or its writes failed for want of space — the data
/// directory is probed every [`SPACE_POLL`] ([`crate::space`]); once space is freed the
/// coordinator is opened again, as a restart would (unfinished jobs resumed, workers'
/// leases adopted during the grace period), on the same listeners, so connections wait
/// in the kernel's backlog rather than being refused (docs/store.md, "When the disk is
/// full").
pub async fn serve_coordinator(
    core: Coordinator,
    listeners: Listeners,
    shutdown: impl Future<Output = ()>,
) -> Result<(), ServeError> {
    let tls = match &core.config().tls {
        Some(files) => Some(Arc::new(ServerTls::load(files.clone())?)),
        None => None,
    };
    let reloader = tls.clone().map(ServerTls::reload_on_sighup);
    let dir = match core.config().store_url() {
        crate::store::StoreUrl::Sqlite(dir) => Some(dir),
        crate::store::StoreUrl::Postgres(_) => None,
    };
    let sockets = Sockets::new(listeners)?;
    tokio::pin!(shutdown);
    let mut core = core;
    let result = loop {
        let store = core.store();
        let freed = space_freed(core.clone(), dir.clone());
        let end = async {
            tokio::select! {
                _ = &mut shutdown => Ended::Shutdown,
                _ = freed => Ended::Reopen,
            }
        };
        let ended = match sockets.listeners() {
            Ok(l) => serve_phase(core.clone(), l, tls.clone(), end).await,
            Err(e) => Err(e.into()),
        };
        store.close().await;
        match ended {
            Ok(Ended::Reopen) => {
                tracing::warn!("space was freed in the store's directory: opening the store again");
                match reopen(core.config().clone()).await {
                    Ok(c) => core = c,
                    Err(e) => break Err(e),
                }
                if core.read_only() {
                    tracing::error!("the disk of the store is full again: serving reads only");
                }
            }
            other => break other.map(|_| ()),
        }
    };
    if let Some(r) = reloader {
        r.abort();
    }
    result
}

/// How often a coordinator whose disk is full probes for free space.
pub const SPACE_POLL: Duration = Duration::from_secs(2);

/// Completes once `core`'s store failed for want of space and the data directory `dir`
/// takes writes again; never without a directory (PostgreSQL). A write failure whose
/// error did not say "full" (an I/O error extending a file) counts as a full disk when
/// a probe finds the directory full; any other failure waits for a restart.
async fn space_freed(core: Coordinator, dir: Option<std::path::PathBuf>) {
    let Some(dir) = dir else {
        return std::future::pending().await;
    };
    let dir = dir.as_path();
    loop {
        tokio::time::sleep(SPACE_POLL).await;
        if !core.store_failing() {
            continue;
        }
        if core.disk_full() {
            if crate::space::probe(dir).await.is_ok() {
                return;
            }
        } else if crate::space::is_full(dir).await {
            tracing::error!(
                "the disk of the store is full: new work is refused until space is freed"
            );
            core.mark_disk_full();
        }
    }
}

/// [`Coordinator::open`] for [`serve_coordinator`], whose future must stay `Send` (it is
/// spawned): the open's future trips rustc's higher-ranked `Send` check on sqlx futures
/// (see [`serve`]), so it runs on a blocking thread driving it on this runtime, where
/// the store's connections are made as they would be here.
async fn reopen(config: CoordinatorConfig) -> Result<Coordinator, ServeError> {
    let rt = tokio::runtime::Handle::current();
    tokio::task::spawn_blocking(move || rt.block_on(Coordinator::open(config)))
        .await
        .map_err(|e| ServeError::Io(std::io::Error::other(e.to_string())))?
        .map_err(ServeError::Open)
}

/// The bound sockets, kept for the whole run; each phase serves duplicates of them.
pub(crate) struct Sockets {
    http: std::net::TcpListener,
    grpc: std::net::TcpListener,
}

impl Sockets {
    /// Keeps `listeners`' sockets.
    pub(crate) fn new(listeners: Listeners) -> std::io::Result<Self> {
        // `into_std` leaves the sockets non-blocking, as `from_std` needs them (the mode
        // is shared by their duplicates).
        Ok(Self {
            http: listeners.http.into_std()?,
            grpc: listeners.grpc.into_std()?,
        })
    }

    /// Duplicates of the sockets, for one phase.
    pub(crate) fn listeners(&self) -> std::io::Result<Listeners> {
        Ok(Listeners {
            http: TcpListener::from_std(self.http.try_clone()?)?,
            grpc: TcpListener::from_std(self.grpc.try_clone()?)?,
        })
    }
}

/// How a coordinator's serving ended ([`serve_phase`]).
#[derive(Debug)]
pub(crate) enum Ended {
    /// Asked to stop: the graceful shutdown of the module documentation.
    Shutdown,
    /// It lost the leadership of its store (`crate::ha`), for this reason.
    Deposed(String),
    /// Space was freed under a coordinator whose disk was full: stop serving and open
    /// the coordinator again ([`serve_coordinator`]).
    Reopen,
}

/// Serves `core` on `listeners` until `end` completes or a server fails, then stops
/// both servers and the ticker; the store stays open (the caller closes it).
///
/// [`Ended::Shutdown`] is the graceful shutdown of the module documentation, ending with
/// the clean end recorded in the store. [`Ended::Deposed`] stops at once: the
/// coordinator is deposed first (nothing granted or taken from then on), workers are not
/// waited for (they deliver to the new active coordinator) and no clean end is recorded
/// (the store is the new leader's).
pub(crate) async fn serve_phase(
    core: Coordinator,
    listeners: Listeners,
    tls: Option<Arc<ServerTls>>,
    end: impl Future<Output = Ended>,
) -> Result<Ended, ServeError> {
    let (failed_tx, mut failed_rx) = mpsc::channel::<ServeError>(2);
    let (http_stop, http_stopped) = oneshot::channel::<()>();
    let (grpc_stop, grpc_stopped) = oneshot::channel::<()>();
    let ticker = core.spawn_ticker();
    let http = spawn_http(&core, listeners.http, tls.clone(), http_stopped);
    let grpc = spawn_grpc(&core, listeners.grpc, tls, grpc_stopped, failed_tx);
    let (ended, failure) = tokio::select! {
        e = end => (e, None),
        e = failed_rx.recv() => (Ended::Shutdown, e),
    };
    match &ended {
        Ended::Shutdown => {
            tracing::info!("coordinator shutting down");
            let _ = http_stop.send(());
            core.begin_shutdown();
            drain_workers(&core, WORKER_DRAIN).await;
            let _ = grpc_stop.send(());
            join_servers(http, grpc, SERVER_SHUTDOWN).await;
            ticker.abort();
            // A graceful end: the next start does not count it as a crash of the jobs in
            // hand (docs/store.md, "No crash loop").
            if let Err(e) = core.store().end_run().await {
                tracing::warn!(error = %e, "cannot record the graceful shutdown in the store");
            }
            tracing::info!("coordinator stopped");
        }
        Ended::Reopen => {
            // As a restart: the workers' leases are adopted by the coordinator opened
            // next, during its grace period; nothing is drained.
            ticker.abort();
            let _ = http_stop.send(());
            let _ = grpc_stop.send(());
            join_servers(http, grpc, SERVER_SHUTDOWN).await;
            // A read-only coordinator began no run to end.
            if !core.read_only() {
                if let Err(e) = core.store().end_run().await {
                    tracing::warn!(error = %e, "cannot record the end of the run in the store");
                }
            }
        }
        Ended::Deposed(reason) => {
            core.depose(reason.clone());
            ticker.abort();
            let _ = http_stop.send(());
            let _ = grpc_stop.send(());
            join_servers(http, grpc, SERVER_SHUTDOWN).await;
        }
    }
    match failure.or_else(|| failed_rx.try_recv().ok()) {
        Some(e) => Err(e),
        None => Ok(ended),
    }
}

/// The stand-in servers of a standby coordinator (`crate::ha`): gRPC answers every
/// worker request `UNAVAILABLE`, HTTP serves the probes and answers the rest 503.
pub(crate) struct Standby {
    stop: Vec<oneshot::Sender<()>>,
    http: JoinHandle<()>,
    grpc: JoinHandle<()>,
}

impl Standby {
    /// Stops both servers (the requests in flight finish; [`SERVER_SHUTDOWN`] at most).
    pub(crate) async fn stop(self) {
        for s in self.stop {
            let _ = s.send(());
        }
        join_servers(self.http, self.grpc, SERVER_SHUTDOWN).await;
    }
}

/// Starts the stand-in servers of a standby on `listeners`.
pub(crate) fn spawn_standby(
    config: &CoordinatorConfig,
    listeners: Listeners,
    tls: Option<Arc<ServerTls>>,
) -> Standby {
    let (http_stop, http_stopped) = oneshot::channel::<()>();
    let (grpc_stop, grpc_stopped) = oneshot::channel::<()>();
    let stats = Arc::new(ConnectionStats::default());
    let app = crate::http::standby_router(crate::ha::STANDBY_MESSAGE);
    let limits = config.http_limits;
    let http_tls = tls.clone();
    let http = tokio::spawn(async move {
        let graceful = async move {
            let _ = http_stopped.await;
        };
        serve_http(listeners.http, app, limits, stats, http_tls, graceful).await;
    });
    let svc = crate::grpc::StandbyGrpc::new(crate::ha::STANDBY_MESSAGE).into_server();
    let (failed, _) = mpsc::channel::<ServeError>(1);
    let grpc = tokio::spawn(run_grpc(svc, listeners.grpc, tls, grpc_stopped, failed));
    Standby {
        stop: vec![http_stop, grpc_stop],
        http,
        grpc,
    }
}

fn spawn_http(
    core: &Coordinator,
    listener: TcpListener,
    tls: Option<Arc<ServerTls>>,
    stop: oneshot::Receiver<()>,
) -> JoinHandle<()> {
    let stats = Arc::new(ConnectionStats::default());
    let app = crate::http::router(core.clone()).layer(axum::Extension(stats.clone()));
    let limits = core.config().http_limits;
    tokio::spawn(async move {
        let graceful = async move {
            let _ = stop.await;
        };
        serve_http(listener, app, limits, stats, tls, graceful).await;
    })
}

fn spawn_grpc(
    core: &Coordinator,
    listener: TcpListener,
    tls: Option<Arc<ServerTls>>,
    stop: oneshot::Receiver<()>,
    failed: mpsc::Sender<ServeError>,
) -> JoinHandle<()> {
    let svc = WorkerGrpc::for_coordinator(core.clone()).into_server();
    tokio::spawn(run_grpc(svc, listener, tls, stop, failed))
}

/// Serves the worker service `svc` (the coordinator's, or a standby's) on `listener`
/// until `stop`; a failure before it is sent to `failed`.
async fn run_grpc<S>(
    svc: v1::worker_service_server::WorkerServiceServer<S>,
    listener: TcpListener,
    tls: Option<Arc<ServerTls>>,
    stop: oneshot::Receiver<()>,
    failed: mpsc::Sender<ServeError>,
) where
    S: v1::worker_service_server::WorkerService,
{
    {
        let graceful = async move {
            let _ = stop.await;
        };
        let server = tonic::transport::Server::builder().add_service(svc);
        let served = match tls {
            // TCP_NODELAY: results and leases are small request/response exchanges, and
            // Nagle's algorithm with delayed ACKs would stall each by tens of milliseconds.
            None => {
                let incoming =
                    tonic::transport::server::TcpIncoming::from(listener).with_nodelay(Some(true));
                server
                    .serve_with_incoming_shutdown(incoming, graceful)
                    .await
            }
            Some(tls) => {
                let incoming = crate::tls::grpc_incoming(listener, tls);
                server
                    .serve_with_incoming_shutdown(incoming, graceful)
                    .await
            }
        };
        if let Err(e) = served {
            tracing::error!(error = %e, "gRPC server failed");
            let _ = failed.send(ServeError::Grpc(e)).await;
        }
    }
}

/// Waits until no live worker holds a lease, for `timeout` at most.
async fn drain_workers(core: &Coordinator, timeout: Duration) {
    let deadline = tokio::time::Instant::now() + timeout;
    loop {
        let busy = core.workers().map_or(0, |list| {
            list.workers
                .iter()
                .filter(|w| w.state == WorkerState::Busy)
                .count()
        });
        if busy == 0 {
            return;
        }
        if tokio::time::Instant::now() >= deadline {
            tracing::warn!(busy, "workers still hold leases; stopping without them");
            return;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// Waits for both servers to finish, for `timeout` at most; then abandons them.
async fn join_servers(http: JoinHandle<()>, grpc: JoinHandle<()>, timeout: Duration) {
    let (http_abort, grpc_abort) = (http.abort_handle(), grpc.abort_handle());
    if tokio::time::timeout(timeout, async {
        let _ = http.await;
        let _ = grpc.await;
    })
    .await
    .is_err()
    {
        tracing::warn!("connections still open after the shutdown timeout; closing them");
        http_abort.abort();
        grpc_abort.abort();
    }
}

/// Completes on Ctrl-C, or on SIGTERM on Unix: the signals that stop `tessera coordinator`,
/// `tessera serve` and `tessera worker`.
pub async fn shutdown_signal() {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{signal, SignalKind};
        match signal(SignalKind::terminate()) {
            Ok(mut term) => {
                tokio::select! {
                    _ = term.recv() => {}
                    _ = tokio::signal::ctrl_c() => {}
                }
            }
            Err(_) => {
                let _ = tokio::signal::ctrl_c().await;
            }
        }
    }
    #[cfg(not(unix))]
    {
        let _ = tokio::signal::ctrl_c().await;
    }
}
