//! What the farm commands share: logging, the async runtime, and the wording of the
//! coordinator's refusals.

use anyhow::{Context, Result};
use tessera_api::client::ClientError;

/// Logs to standard error, `warn` and above unless `RUST_LOG` says otherwise.
pub fn init_tracing() {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn"));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .try_init();
}

/// The async runtime of the coordinator and the worker: two threads are plenty, the
/// rendering runs on its own pool.
pub fn runtime() -> Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("starting the async runtime")
}

/// A client error as the user reads it.
pub fn client_error(e: ClientError) -> anyhow::Error {
    match e {
        ClientError::Api { status, error } => {
            anyhow::anyhow!("the coordinator refused the request ({status}): {error}")
        }
        ClientError::Transport(m) => anyhow::anyhow!("{m}"),
    }
}

/// The API client of `tessera submit` and `tessera status`: with `--tls-ca`, an
/// `https://` server's certificate must be issued by that CA.
pub fn api_client(
    server: &str,
    token: Option<String>,
    tls_ca: Option<&std::path::Path>,
) -> Result<tessera_api::client::Client> {
    let client = tessera_api::client::Client::new(server, token);
    let Some(ca) = tls_ca else {
        return Ok(client);
    };
    if !server.starts_with("https://") {
        anyhow::bail!(
            "--tls-ca {} needs an https:// --server, not {server}",
            ca.display()
        );
    }
    let pem = std::fs::read(ca).with_context(|| format!("reading --tls-ca {}", ca.display()))?;
    client
        .with_tls_ca(&pem)
        .map_err(|e| anyhow::anyhow!("--tls-ca {}: {}", ca.display(), client_error(e)))
}

/// CPU seconds (user + system) of process `pid` so far, from `/proc/PID/stat` (fields 14
/// and 15, in the kernel's USER_HZ ticks, 100 per second on Linux); 0 where unavailable.
/// The peak resident memory of this process so far in bytes (`VmHWM` of
/// /proc/self/status, what `/usr/bin/time -v` reports as "Maximum resident set size"),
/// or `None` where /proc does not say.
pub(crate) fn peak_resident_bytes() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: u64 = line
        .trim_start_matches("VmHWM:")
        .trim()
        .trim_end_matches("kB")
        .trim()
        .parse()
        .ok()?;
    Some(kib * 1024)
}

pub(crate) fn cpu_seconds(pid: &str) -> f64 {
    let Ok(stat) = std::fs::read_to_string(format!("/proc/{pid}/stat")) else {
        return 0.0;
    };
    // The command name (field 2) may contain spaces; the fields after it do not.
    let Some(rest) = stat.rsplit_once(')').map(|(_, r)| r) else {
        return 0.0;
    };
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks = |i: usize| f.get(i).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    // `rest` starts at field 3 (state), so fields 14 and 15 are at 11 and 12.
    (ticks(11) + ticks(12)) / 100.0
}
