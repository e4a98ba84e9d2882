//! The Tessera worker: a gRPC client loop around [`tessera_render::render::render_unit`].
//!
//! A worker registers with the coordinator, then repeatedly leases work units, renders
//! them on all its threads and submits the per-pass results, while heartbeats keep its
//! leases alive. It leases the next batch while one renders and submits results in the
//! background, so its threads do not wait on the network; batches are sized from the
//! measured time of a unit (docs/ARCHITECTURE.md §9, "The worker's pipeline"). Scenes are
//! fetched once by content hash (in chunks, verified against their SHA-256) and cached
//! together with their built BVH, so a worker pays for a scene once however many units of
//! it it renders. When the coordinator is away the worker reconnects with exponential
//! backoff and registers again; on shutdown (its own, or a heartbeat answering `shutdown`
//! because the coordinator is stopping) it finishes the units in hand, submits them,
//! returns anything it has not started, and exits.
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
//! Rendering is deterministic (docs/ARCHITECTURE.md §2): the bytes a worker submits for a
//! unit depend only on the scene, the settings and the unit, so the coordinator can
//! compare duplicates.
//!
//! # Where things are
//! - this file: the configuration, the errors and [`run`], which checks the configuration
//!   and runs sessions until it is stopped;
//! - `session.rs`: the sessions — connecting to one coordinator after another
//!   (`connect.rs`: endpoints, the bearer token, the failover order and its backoff),
//!   registering, and the loop that drives the unit pipeline;
//! - `pipeline.rs`: the unit pipeline as a plain state machine (what renders, what is
//!   prefetched, what waits for its submission, how many units to ask for), tested
//!   without a network;
//! - `lease.rs`: lease requests and leases given back; `render.rs`: a batch rendering on
//!   the thread pool, a renderer's panic contained to its unit;
//! - `scene_cache.rs`: scenes fetched by hash, parsed and built once, and the time a
//!   lease's scene is loaded at;
//! - `tls.rs`: the worker's TLS files; `faults.rs`: the test hooks below.
//!
//! # Test hooks: the `fault-injection` feature
//! Two testing aids exist only when the crate is built with the cargo feature
//! `fault-injection`: [`WorkerConfig::inject_faults`] (the `--inject-faults` flag of
//! `tessera worker`) corrupts a fraction of the results, and the variable
//! `TESSERA_WORKER_TEST_PANIC_SEED` makes rendering a job's units panic. The feature is
//! off by default, so a release worker has no such flag, reads no variable per unit, and
//! [`run`] refuses a non-zero `inject_faults`. The test builds turn it on: this crate's
//! through a dev-dependency on itself, `tessera-cli`'s (whose `tessera` binary the
//! end-to-end tests run) through a dev-dependency with the feature; `tessera-cli` also
//! forwards a feature of the same name for a build by hand
//! (`cargo build -p tessera-cli --features fault-injection`). The CLI declares the flag
//! inside [`with_fault_injection!`], so it exists exactly when the hooks do.
#![deny(missing_docs)]

mod connect;
mod faults;
mod lease;
mod pipeline;
mod render;
mod scene_cache;
mod session;
mod tls;

use std::future::Future;
use std::sync::{Arc, Mutex};

#[cfg(feature = "fault-injection")]
pub use faults::{injects_fault, INJECT_FAULTS_SALT, TEST_PANIC_SEED_VAR};
pub use tls::{TlsFiles, WorkerTls};

/// Expands to the items given only in a build with the `fault-injection` feature: for a
/// dependent crate's code that exists exactly when the hooks do, whichever package turned
/// the feature on (the `--inject-faults` flag of `tessera worker` is declared in one).
#[cfg(feature = "fault-injection")]
#[macro_export]
macro_rules! with_fault_injection {
    ($($item:item)*) => { $($item)* };
}

/// Expands to the items given only in a build with the `fault-injection` feature: for a
/// dependent crate's code that exists exactly when the hooks do, whichever package turned
/// the feature on (the `--inject-faults` flag of `tessera worker` is declared in one).
#[cfg(not(feature = "fault-injection"))]
#[macro_export]
macro_rules! with_fault_injection {
    ($($item:item)*) => {};
}

/// Expands to the items given only in a build without the `fault-injection` feature:
/// the counterpart of [`with_fault_injection!`].
#[cfg(feature = "fault-injection")]
#[macro_export]
macro_rules! without_fault_injection {
    ($($item:item)*) => {};
}

/// Expands to the items given only in a build without the `fault-injection` feature:
/// the counterpart of [`with_fault_injection!`].
#[cfg(not(feature = "fault-injection"))]
#[macro_export]
macro_rules! without_fault_injection {
    ($($item:item)*) => { $($item)* };
}

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
    /// corrupts (`injects_fault`), 0 for none. The corrupt results stay well-formed, so
    /// only the coordinator's spot checks catch them. Never set it in production. Only a
    /// build with the `fault-injection` feature honours it; any other refuses to [`run`]
    /// with a value other than 0. (The field exists in every build so that enabling the
    /// feature changes no code that constructs a configuration.)
    pub inject_faults: f64,
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
    let hooks = faults::Hooks::new(config.inject_faults)?;
    if config.coordinators.is_empty() {
        return Err(WorkerError::Config(
            "no coordinator URL: give at least one (--coordinator)".into(),
        ));
    }
    let endpoints = connect::endpoints(&config.coordinators, config.tls.as_ref())?;
    let auth = connect::Auth::bearer(config.token.as_deref())?;
    let pool = Arc::new(
        rayon::ThreadPoolBuilder::new()
            .num_threads(config.threads)
            .thread_name(|i| format!("tessera-render-{i}"))
            .build()
            .map_err(|e| WorkerError::Config(format!("thread pool: {e}")))?,
    );
    hooks.announce();
    let worker = session::Worker {
        config,
        auth,
        pool,
        cache: Arc::new(Mutex::new(scene_cache::SceneCache::default())),
        hooks,
    };
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    let sessions = session::sessions(&worker, endpoints, stop_rx);
    tokio::pin!(sessions);
    tokio::pin!(shutdown);
    tokio::select! {
        r = &mut sessions => r,
        _ = &mut shutdown => {
            // Ask the session to finish what it holds, then wait for it.
            let _ = stop_tx.send(true);
            sessions.await
        }
    }
}
