//! The Tessera coordinator: accepts render jobs, leases work units to workers, merges
//! their results and keeps the durable state of the farm (ARCHITECTURE.md §1, §5, §6, §9).
//!
//! Where things live:
//!
//! - [`store`]: the durable store (jobs, scenes, merged tile checkpoints, lease fencing
//!   high-water mark, convergence history, worker faults) behind the [`store::Store`]
//!   trait, with the SQLite implementation [`store::SqliteStore`].
//! - [`state`]: the working state in memory: the farm's lease scheduler with the jobs'
//!   accumulators, the workers, the scene cache, and per-job bookkeeping.
//! - [`service`]: the job life cycle over both, one file per responsibility (scenes,
//!   jobs, workers and leases, results, resume, images, metrics); the [`Coordinator`]
//!   is its handle.
//! - [`error`]: the one error type of the service, with its one mapping to an HTTP
//!   error and its one mapping to a gRPC status.
//! - [`grpc`]: the worker-facing gRPC service: authorize, decode, call the service,
//!   encode.
//! - [`http`]: the axum HTTP API v1 (ARCHITECTURE.md §5) and the dashboard routes.
//! - [`dashboard`]: the browser dashboard's static files, embedded, served at `/`.
//! - [`auth`]: the bearer-token rule both ports share.
//! - [`connections`]: the HTTP port's accept loop with its connection limits and read,
//!   body and idle timeouts ([`HttpLimits`]).
//! - [`server`]: [`serve`], which runs both servers and the ticker on bound listeners and
//!   shuts them down gracefully (workers told to stop, requests in flight finished).
//! - [`space`]: whether the data directory's disk is full, probed by writing.
//! - [`ha`]: high availability on PostgreSQL: [`ha::serve_ha`] runs a coordinator as a
//!   standby until it holds the store's leadership lock, then as the active one.
//!
//! Dependencies point one way: `http` and `grpc` call `service`, which owns `state` and
//! `store`; nothing below `service` knows HTTP or gRPC.
//!
//! [`Coordinator`]: service::Coordinator
#![deny(missing_docs)]

/// The browser dashboard's static files (HTML, CSS, JavaScript modules), embedded.
pub mod auth;
pub mod connections;
pub mod dashboard;
pub mod error;
pub mod grpc;
pub mod ha;
pub mod http;
pub mod server;
pub mod service;
pub mod space;
pub mod state;
pub mod store;
pub mod tls;
pub mod trust;

pub use connections::HttpLimits;
pub use ha::serve_ha;
pub use server::{serve, serve_coordinator, shutdown_signal, Listeners, ServeError};
pub use tls::{ServerTls, TlsError, TlsFiles};
