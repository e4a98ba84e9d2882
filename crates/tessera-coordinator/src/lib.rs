//! The Tessera coordinator: accepts render jobs, leases work units to workers, merges
//! their results and keeps the durable state of the farm (ARCHITECTURE.md §1, §5, §6).
//!
//! - [`store`]: the durable store (jobs, scenes, merged tile checkpoints, lease fencing
//!   high-water mark, convergence history, worker faults) behind the [`store::Store`]
//!   trait, with the SQLite implementation [`store::SqliteStore`].
//! - [`grpc`]: the worker-facing gRPC service over the farm's lease scheduler.
//! - [`service`]: the job life cycle over both: submission, durable checkpoints as passes
//!   merge, resume after a restart, status, images, cancel.
//! - [`http`]: the axum HTTP API v1 (ARCHITECTURE.md §5) and the dashboard routes.
//! - [`dashboard`]: the browser dashboard's static files, embedded, served at `/`.
//! - [`server`]: [`serve`], which runs both servers and the ticker on bound listeners and
//!   shuts them down gracefully (workers told to stop, requests in flight finished).
#![deny(missing_docs)]

/// The browser dashboard's static files (HTML, CSS, JavaScript modules), embedded.
pub mod dashboard;
pub mod grpc;
pub mod http;
pub mod server;
pub mod service;
pub mod store;

pub use server::{serve, serve_coordinator, shutdown_signal, Listeners, ServeError};
