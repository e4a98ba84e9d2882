//! `tessera coordinator`: the HTTP API and dashboard, the workers' gRPC port and the SQLite
//! store, served by [`tessera_coordinator::serve`] until Ctrl-C or SIGTERM.

use anyhow::{bail, Context, Result};
use clap::Args;
use std::io::Write;
use std::net::SocketAddr;
use std::path::PathBuf;
use tessera_coordinator::service::{Coordinator, CoordinatorConfig};
use tessera_coordinator::{serve_coordinator, shutdown_signal, Listeners};

use crate::common::{init_tracing, runtime};

/// Options shared by `tessera coordinator` and `tessera serve`.
#[derive(Args, Clone, Debug)]
pub struct CoordinatorArgs {
    /// Address of the HTTP API and dashboard.
    #[arg(long, default_value = "127.0.0.1:8080")]
    pub http: SocketAddr,
    /// Address of the gRPC port for workers.
    #[arg(long, default_value = "127.0.0.1:50051")]
    pub grpc: SocketAddr,
    /// Directory of the SQLite store (created if missing).
    #[arg(long, default_value = "tessera-data")]
    pub data: PathBuf,
    /// Bearer token required on the HTTP API.
    #[arg(long, env = "TESSERA_API_TOKEN")]
    pub api_token: Option<String>,
    /// Bearer token workers must present.
    #[arg(long, env = "TESSERA_WORKER_TOKEN")]
    pub worker_token: Option<String>,
    /// Lease duration without a heartbeat, milliseconds.
    #[arg(long, default_value_t = 10_000)]
    pub lease_ms: u64,
    /// Worker heartbeat interval, milliseconds.
    #[arg(long, default_value_t = 1_000)]
    pub heartbeat_ms: u32,
    /// After a restart, how long workers have to deliver what they were rendering before
    /// their units are leased again, milliseconds.
    #[arg(long, default_value_t = 3_000)]
    pub grace_ms: u64,
    /// Memory for the per-pixel merge state of all jobs (72 bytes per pixel of each frame
    /// in progress), e.g. `4GiB`, `512MiB` or a byte count. A job one frame of which
    /// needs more is refused; frames beyond it wait for others to complete.
    #[arg(long, default_value = "4GiB", value_parser = parse_bytes)]
    pub memory_budget: u64,
}

/// A byte count with an optional binary or decimal unit: `4GiB`, `512MiB`, `2GB`, `1024`.
fn parse_bytes(s: &str) -> std::result::Result<u64, String> {
    let t = s.trim();
    let split = t.find(|c: char| !c.is_ascii_digit()).unwrap_or(t.len());
    let (num, unit) = t.split_at(split);
    let n: u64 = num
        .parse()
        .map_err(|_| format!("{s:?} is not a byte count such as 4GiB or 1073741824"))?;
    let scale: u64 = match unit.trim().to_ascii_lowercase().as_str() {
        "" | "b" => 1,
        "k" | "kb" => 1_000,
        "kib" => 1 << 10,
        "m" | "mb" => 1_000_000,
        "mib" => 1 << 20,
        "g" | "gb" => 1_000_000_000,
        "gib" => 1 << 30,
        "t" | "tb" => 1_000_000_000_000,
        "tib" => 1 << 40,
        other => {
            return Err(format!(
                "unknown unit {other:?} in {s:?} (use B, KiB, MiB, GiB, TiB)"
            ))
        }
    };
    n.checked_mul(scale)
        .filter(|&b| b > 0)
        .ok_or_else(|| format!("{s:?} must be between 1 byte and 16 EiB"))
}

impl CoordinatorArgs {
    /// The validated coordinator configuration.
    fn config(&self) -> Result<CoordinatorConfig> {
        if self.lease_ms < 100 || u64::from(self.heartbeat_ms) * 2 > self.lease_ms {
            bail!(
                "--lease-ms {} must be at least 100 and at least twice --heartbeat-ms {}",
                self.lease_ms,
                self.heartbeat_ms
            );
        }
        Ok(CoordinatorConfig {
            data_dir: self.data.clone(),
            api_token: self.api_token.clone().filter(|t| !t.is_empty()),
            worker_token: self.worker_token.clone().filter(|t| !t.is_empty()),
            lease_ms: self.lease_ms,
            heartbeat_ms: self.heartbeat_ms,
            grace_ms: self.grace_ms,
            passes_per_unit: 1,
            memory_budget: self.memory_budget,
        })
    }

    /// Opens the store, then binds both ports (so their real addresses are known before
    /// anything is printed).
    pub async fn open(&self) -> Result<(Coordinator, Listeners)> {
        let core = Coordinator::open(self.config()?)
            .await
            .with_context(|| format!("opening the store in {}", self.data.display()))?;
        let http = tokio::net::TcpListener::bind(self.http)
            .await
            .with_context(|| format!("binding the HTTP port {}", self.http))?;
        let grpc = tokio::net::TcpListener::bind(self.grpc)
            .await
            .with_context(|| format!("binding the gRPC port {}", self.grpc))?;
        Ok((core, Listeners { http, grpc }))
    }
}

/// Prints the addresses scripts and tests read: `http: `, `grpc: ` and `dashboard: `.
pub fn print_addresses(listeners: &Listeners) -> Result<()> {
    let (http, grpc) = (listeners.http.local_addr()?, listeners.grpc.local_addr()?);
    println!("http: http://{http}/api/v1");
    println!("grpc: http://{grpc}");
    println!("dashboard: http://{http}/");
    let _ = std::io::stdout().flush();
    Ok(())
}

/// `tessera coordinator`.
pub fn coordinator(args: CoordinatorArgs) -> Result<()> {
    init_tracing();
    runtime()?.block_on(async {
        let (core, listeners) = args.open().await?;
        print_addresses(&listeners)?;
        serve_coordinator(core, listeners, shutdown_signal()).await?;
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::parse_bytes;

    #[test]
    fn byte_counts_parse_with_units() {
        assert_eq!(parse_bytes("4GiB"), Ok(4 << 30));
        assert_eq!(parse_bytes("512 MiB"), Ok(512 << 20));
        assert_eq!(parse_bytes("2gb"), Ok(2_000_000_000));
        assert_eq!(parse_bytes("1073741824"), Ok(1 << 30));
        for bad in ["", "GiB", "4 parsecs", "0", "99999999999TiB", "-1"] {
            assert!(parse_bytes(bad).is_err(), "{bad:?}");
        }
    }
}
