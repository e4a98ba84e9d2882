//! The coordinator's integration tests, one binary (linking the crate once, not once per
//! file): each file below is a module, so a test is named `FILE::TEST`, e.g.
//! `cargo test -p tessera-coordinator --test it store::` runs the store suite. Shared
//! helpers (the fuzz generator, the wait bound, the test CA, PostgreSQL schemas) are in
//! the `tessera-testkit` crate.

mod fuzz_grpc;
mod fuzz_http;
mod http_api;
mod http_limits;
mod openapi;
mod poison_scenes;
mod resume_guard;
mod scene_storage;
mod serve;
mod store;
mod store_integrity;
mod tls;
mod worker_trust;
