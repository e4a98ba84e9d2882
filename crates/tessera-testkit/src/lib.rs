//! Helpers shared by Tessera's test suites, kept once instead of copied into each suite:
//! the fuzz harnesses' generator ([`splitmix`]), a glTF/GLB builder ([`gltf_gen`]), a
//! Prometheus sample reader ([`metrics`]) and, behind features so that a suite builds only
//! what it uses, an async wait bound ([`bounded`], feature `tokio`), the HTTP API's error
//! unpacking ([`api`], feature `api`), a test certificate authority ([`test_ca`], feature
//! `tls`) and a fresh PostgreSQL schema per test ([`postgres`], feature `postgres`).
//!
//! Only ever a dev-dependency: `.ci/check-deps` fails if a crate's normal dependencies
//! reach it. Helpers that start the `tessera` binary stay with the end-to-end suites
//! (`tests/e2e/common/`), since only the `tessera-cli` package's tests know its path.

#[cfg(feature = "api")]
pub mod api;
#[cfg(feature = "tokio")]
pub mod bounded;
pub mod gltf_gen;
pub mod metrics;
#[cfg(feature = "postgres")]
pub mod postgres;
pub mod splitmix;
#[cfg(feature = "tls")]
pub mod test_ca;

#[cfg(feature = "api")]
pub use api::api_error;
#[cfg(feature = "tokio")]
pub use bounded::{bounded, HANG};
pub use metrics::{metric, require_metric};
pub use splitmix::SplitMix64;
