//! The end-to-end suites, one test binary of the `tessera-cli` package (linking the
//! workspace once, not once per suite): each file below is a module, so a test is named
//! `SUITE::TEST`, e.g. `cargo test -p tessera-cli --test e2e farm_e2e::` runs the farm
//! suite. `common` starts the real `tessera` binary and waits on it.
//!
//! The suites can share a process: none sets environment variables or a panic hook, the
//! netns suite moves only threads of its own into namespaces (`Hosts::within`), the memory
//! suite limits and measures its child coordinator rather than this process, the
//! dashboard suite serialises its browsers itself, and every temporary directory is
//! named after its suite.

mod common;

mod adaptive_cli;
mod dashboard_browser;
mod dry_run;
mod estimate_cli;
mod farm_e2e;
mod ha_failover;
mod local_and_farm;
mod memory_budget;
mod netns_partition;
mod plan_cli;
mod poison_scenes_cli;
mod postgres_e2e;
mod python_clients;
mod render_cli;
mod store_cli;
mod tls_e2e;
mod worker_token;
