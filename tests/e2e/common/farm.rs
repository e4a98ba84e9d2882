//! A farm of real processes on loopback for the end-to-end suites: a coordinator on port 0
//! listeners (its addresses read from its output), workers, and waiting for a job.

use std::path::Path;
use std::time::Duration;

use tessera_api::client::Client;
use tessera_api::{JobSettings, JobState, JobStatus};

use super::{output_ok, tessera, Proc};

/// How long a job may take before the test fails.
pub const TIMEOUT: Duration = Duration::from_secs(240);

/// A running coordinator and its addresses.
pub struct Coord {
    /// The process.
    pub proc: Proc,
    /// Base URL of the HTTP API, e.g. `http://127.0.0.1:PORT`.
    pub http: String,
    /// URL of the gRPC port for workers.
    pub grpc: String,
}

impl Coord {
    /// Waits until the coordinator is the active one (`/readyz` 200): at once on SQLite;
    /// on PostgreSQL once it holds the store's leadership (docs/store.md, "High
    /// availability"), which a start after `kill -9` of the previous coordinator waits for.
    pub fn wait_active(&self) {
        super::wait_for(
            "the coordinator to be active",
            Duration::from_secs(30),
            || match super::http_get(&self.http, "/readyz") {
                (200, _) => Ok(()),
                (status, body) => Err(format!("{status} {body}")),
            },
        );
    }
}

/// Starts `tessera coordinator` on `data` with short leases and waits for its addresses.
pub fn start_coordinator(data: &Path, http: &str, grpc: &str, extra: &[&str]) -> Coord {
    spawn_coordinator(tessera(), data, http, grpc, extra, None)
}

/// [`start_coordinator`] on loopback port 0 with its address space (`ulimit -v`) limited
/// to `bytes`, by util-linux's `prlimit`, which execs the coordinator in its own process.
pub fn start_coordinator_limited(data: &Path, bytes: u64, extra: &[&str]) -> Coord {
    let mut cmd = std::process::Command::new("prlimit");
    cmd.arg(format!("--as={bytes}"))
        .arg("--")
        .arg(env!("CARGO_BIN_EXE_tessera"));
    spawn_coordinator(cmd, data, "127.0.0.1:0", "127.0.0.1:0", extra, None)
}

/// [`start_coordinator`] through `cmd`, a program that runs `tessera` with the arguments
/// appended (`prlimit`, `ip netns exec`), with its stderr in `stderr_log` if given.
pub fn spawn_coordinator(
    mut cmd: std::process::Command,
    data: &Path,
    http: &str,
    grpc: &str,
    extra: &[&str],
    stderr_log: Option<&Path>,
) -> Coord {
    let mut proc = Proc::spawn(
        "coordinator",
        cmd.args(["coordinator", "--http", http, "--grpc", grpc, "--data"])
            .arg(data)
            .args([
                "--lease-ms",
                "1500",
                "--heartbeat-ms",
                "250",
                "--grace-ms",
                "1000",
            ])
            .args(extra)
            .env_remove("TESSERA_API_TOKEN")
            .env_remove("TESSERA_WORKER_TOKEN"),
        stderr_log,
    );
    let v = proc.wait_lines(&["http: ", "grpc: "]);
    let http = v[0].trim_end_matches("/api/v1").to_string();
    Coord {
        proc,
        http,
        grpc: v[1].clone(),
    }
}

/// Starts `tessera worker` with one thread against the gRPC URL `grpc`.
pub fn start_worker(grpc: &str, name: &str, extra: &[&str]) -> Proc {
    spawn_worker(tessera(), &[grpc], name, extra, None)
}

/// Starts `tessera worker` with one thread that knows the coordinators `grpc` (one
/// `--coordinator` each, for failover), its standard error into `stderr_log` if given.
pub fn start_worker_of(
    grpc: &[&str],
    name: &str,
    extra: &[&str],
    stderr_log: Option<&Path>,
) -> Proc {
    spawn_worker(tessera(), grpc, name, extra, stderr_log)
}

/// [`start_worker_of`] through `cmd`, a program that runs `tessera` with the arguments
/// appended (`ip netns exec`).
pub fn spawn_worker(
    mut cmd: std::process::Command,
    grpc: &[&str],
    name: &str,
    extra: &[&str],
    stderr_log: Option<&Path>,
) -> Proc {
    cmd.arg("worker");
    for url in grpc {
        cmd.args(["--coordinator", url]);
    }
    Proc::spawn(
        name,
        cmd.args(["--threads", "1", "--name", name])
            .args(extra)
            .env_remove("TESSERA_WORKER_TOKEN"),
        stderr_log,
    )
}

/// Waits until job `id` is done (failing the test if it ends otherwise).
pub fn wait_done(client: &Client, id: u64) -> JobStatus {
    let s = match client.wait(id, Duration::from_millis(100), TIMEOUT, |_| {}) {
        Ok(s) => s,
        // A stalled job: say where it stood and who was there, so that a failure in CI
        // can be understood from its log.
        Err(e) => panic!(
            "job {id}: {e}\nstatus: {:?}\nworkers: {:?}",
            client.job(id),
            client.workers()
        ),
    };
    assert_eq!(
        s.state,
        JobState::Done,
        "job ended {:?}: {:?}",
        s.state,
        s.error
    );
    s
}

/// A Cornell box job of `width` x `height` pixels at `spp` samples per pixel, seed 5.
pub fn cornell_job(width: u32, height: u32, spp: u32) -> JobSettings {
    let mut s = JobSettings::new("builtin:cornell-box");
    s.width = Some(width);
    s.height = Some(height);
    s.spp = spp;
    s.seed = 5;
    s
}

/// `tessera render` of the same job into `dir/local.exr`: the reference EXR bytes.
pub fn local_render(dir: &Path, s: &JobSettings) -> Vec<u8> {
    local_render_with(dir, "local.exr", s, &[])
}

/// `tessera render` of the same job with the adaptive settings of `s` (`adaptive`,
/// `target_error`) into `dir/NAME`: the reference EXR bytes of an adaptive job.
pub fn local_render_adaptive(dir: &Path, name: &str, s: &JobSettings) -> Vec<u8> {
    let target = s.target_error.map(|t| t.to_string());
    let mut extra = vec!["--adaptive", s.adaptive.as_str()];
    if let Some(t) = &target {
        extra.extend(["--target-error", t]);
    }
    local_render_with(dir, name, s, &extra)
}

/// [`local_render`] into `dir/NAME` with `extra` arguments.
pub fn local_render_with(dir: &Path, name: &str, s: &JobSettings, extra: &[&str]) -> Vec<u8> {
    let out = dir.join(name);
    output_ok(
        tessera()
            .args(["render", &s.scene, "--width"])
            .arg(s.width.unwrap().to_string())
            .arg("--height")
            .arg(s.height.unwrap().to_string())
            .arg("--spp")
            .arg(s.spp.to_string())
            .arg("--seed")
            .arg(s.seed.to_string())
            .args(extra)
            .arg("-o")
            .arg(&out),
    );
    std::fs::read(out).unwrap()
}

/// The passes of `job` that a store holds: its tiles' committed checkpoints, read from the
/// database directly (`store`: a `postgres://` URL, or the path of a SQLite store file).
/// The job status counts a pass when it is merged; its checkpoint is committed in the next
/// group commit, and its worker hears "accepted" only then (ARCHITECTURE.md §9). A `kill
/// -9` between the two loses nothing (the worker delivers again), but the restarted
/// coordinator shows fewer passes than the killed one did: tests that kill a coordinator
/// wait for this count, not the status's.
pub fn stored_passes(store: &str, job: u64) -> i64 {
    use sqlx::Connection;
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap()
        .block_on(async {
            if store.starts_with("postgres://") {
                let mut conn = sqlx::PgConnection::connect(store).await.unwrap();
                let n: i64 = sqlx::query_scalar(
                    "SELECT COALESCE(SUM(merged_passes), 0)::BIGINT FROM tiles WHERE job = $1",
                )
                .bind(job as i64)
                .fetch_one(&mut conn)
                .await
                .unwrap();
                let _ = conn.close().await;
                n
            } else {
                let options = sqlx::sqlite::SqliteConnectOptions::new()
                    .filename(store)
                    .read_only(true);
                let mut conn = sqlx::SqliteConnection::connect_with(&options)
                    .await
                    .unwrap();
                let n: i64 = sqlx::query_scalar(
                    "SELECT COALESCE(SUM(merged_passes), 0) FROM tiles WHERE job = ?1",
                )
                .bind(job as i64)
                .fetch_one(&mut conn)
                .await
                .unwrap();
                let _ = conn.close().await;
                n
            }
        })
}
