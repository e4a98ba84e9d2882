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
