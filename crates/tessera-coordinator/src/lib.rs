//! The Tessera coordinator: accepts render jobs, leases work units to workers, merges
//! their results and keeps the durable state of the farm (DESIGN §1, §5, §6).
//!
//! - [`store`]: the durable store (jobs, scenes, merged tile checkpoints, lease fencing
//!   high-water mark, convergence history, worker faults) behind the [`store::Store`]
//!   trait, with the SQLite implementation [`store::SqliteStore`].
//! - [`grpc`]: the worker-facing gRPC service over the farm's lease scheduler.
#![deny(missing_docs)]

pub mod grpc;
pub mod store;
