//! `tessera serve`: the whole farm on this machine, a coordinator and local worker
//! processes over loopback gRPC. Ctrl-C or SIGTERM stops the workers first (they finish
//! the units in hand and deliver them), then the coordinator.

use anyhow::{bail, Context, Result};
use clap::Args;
use std::io::Write;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};
use tessera_api::JobSettings;
use tessera_coordinator::service::Coordinator;
use tessera_coordinator::shutdown_signal;

use crate::common::{init_tracing, runtime};
use crate::coordinator::{print_addresses, CoordinatorArgs, Opened};

/// How long local workers get to finish their units before they are killed.
const WORKER_STOP: Duration = Duration::from_secs(10);

/// `tessera serve`.
#[derive(Args, Clone, Debug)]
pub struct ServeArgs {
    #[command(flatten)]
    pub coordinator: CoordinatorArgs,
    /// Local worker processes.
    #[arg(long, default_value_t = 1)]
    pub workers: usize,
    /// Threads per local worker (0 = all cores divided among the workers).
    #[arg(long, default_value_t = 0)]
    pub threads_per_worker: usize,
    /// Submit this job when the store has no job yet, so a fresh farm has something to
    /// show ("none" to disable).
    #[arg(long, default_value = "builtin:cornell-box")]
    pub demo: String,
    /// With --tls-cert: the CA certificate(s) (PEM) the local workers trust for the
    /// coordinator's certificate.
    #[arg(long, value_name = "FILE")]
    pub tls_ca: Option<PathBuf>,
    /// With --tls-client-ca: the certificate chain (PEM) the local workers present.
    #[arg(long, value_name = "FILE", requires = "worker_tls_key")]
    pub worker_tls_cert: Option<PathBuf>,
    /// The private key (PEM) of --worker-tls-cert.
    #[arg(long, value_name = "FILE", requires = "worker_tls_cert")]
    pub worker_tls_key: Option<PathBuf>,
}

impl ServeArgs {
    /// Checks that the local workers can connect to a TLS (or mutual TLS) gRPC port.
    fn check_tls(&self) -> Result<()> {
        if self.workers == 0 {
            return Ok(());
        }
        let c = &self.coordinator;
        if c.tls_cert.is_some() && self.tls_ca.is_none() {
            bail!("with --tls-cert, give --tls-ca: the CA the local workers trust");
        }
        if c.tls_client_ca.is_some() && self.worker_tls_cert.is_none() {
            bail!(
                "with --tls-client-ca, give --worker-tls-cert and --worker-tls-key for the local workers"
            );
        }
        Ok(())
    }
}

/// `tessera serve`: a coordinator and local worker processes over loopback gRPC.
pub fn serve(mut args: ServeArgs) -> Result<()> {
    init_tracing();
    if args.workers > 256 {
        bail!("--workers {} must be at most 256", args.workers);
    }
    args.check_tls()?;
    // Before the local workers start: they are handed the same token.
    args.coordinator.require_worker_credentials()?;
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let threads = if args.threads_per_worker == 0 {
        (cores / args.workers.max(1)).max(1)
    } else {
        args.threads_per_worker
    };
    runtime()?.block_on(async move {
        let (opened, listeners) = args.coordinator.open().await?;
        let children = spawn_workers(&args, listeners.grpc.local_addr()?, threads)?;
        match &opened {
            Opened::Single(core) if args.demo != "none" => submit_demo(core, &args.demo).await,
            // A standby cannot submit: the demo job is for the SQLite farm of a first try.
            _ => {}
        }
        print_addresses(&listeners, args.coordinator.scheme())?;
        println!(
            "{} local worker(s) with {threads} thread(s) each; Ctrl-C stops the farm",
            args.workers
        );
        let _ = std::io::stdout().flush();
        let shutdown = async move {
            shutdown_signal().await;
            stop_workers(children).await;
        };
        opened.serve(listeners, shutdown).await
    })
}

/// Starts `args.workers` local `tessera worker` processes that exit when their standard
/// input closes.
fn spawn_workers(args: &ServeArgs, grpc: SocketAddr, threads: usize) -> Result<Vec<Child>> {
    let exe = std::env::current_exe().context("locating the tessera binary")?;
    let mut children = Vec::new();
    for i in 0..args.workers {
        let mut cmd = Command::new(&exe);
        cmd.arg("worker")
            .arg("--coordinator")
            .arg(format!("{}://{grpc}", args.coordinator.scheme()))
            .arg("--threads")
            .arg(threads.to_string())
            .arg("--name")
            .arg(format!("local-{}", i + 1))
            .arg("--exit-with-stdin")
            .stdin(Stdio::piped());
        if args.coordinator.tls_cert.is_some() {
            if let Some(ca) = &args.tls_ca {
                cmd.arg("--tls-ca").arg(ca);
            }
            if let (Some(cert), Some(key)) = (&args.worker_tls_cert, &args.worker_tls_key) {
                cmd.arg("--tls-cert").arg(cert).arg("--tls-key").arg(key);
            }
        }
        if let Some(t) = &args.coordinator.worker_token {
            cmd.env("TESSERA_WORKER_TOKEN", t);
        } else {
            cmd.env_remove("TESSERA_WORKER_TOKEN");
        }
        children.push(
            cmd.spawn()
                .with_context(|| format!("starting local worker {}", i + 1))?,
        );
    }
    Ok(children)
}

/// Submits the demo job when the store has no job yet.
async fn submit_demo(core: &Coordinator, scene: &str) {
    let empty = core
        .list(tessera_api::JobListQuery {
            limit: Some(1),
            ..Default::default()
        })
        .await
        .map(|l| l.jobs.is_empty())
        .unwrap_or(false);
    if !empty {
        return;
    }
    let mut s = JobSettings::new(scene.to_string());
    s.name = Some("demo".into());
    match core.submit(s, Some("tessera-serve-demo".into())).await {
        Ok((job, _)) => println!("submitted demo job {} ({scene})", job.id),
        Err(e) => eprintln!("demo job not submitted: {e}"),
    }
}

/// Closes the workers' standard input, which asks them to finish and exit, and waits for
/// them ([`WORKER_STOP`] at most, then kills them).
async fn stop_workers(mut children: Vec<Child>) {
    for c in &mut children {
        drop(c.stdin.take());
    }
    let deadline = Instant::now() + WORKER_STOP;
    for mut c in children {
        loop {
            match c.try_wait() {
                Ok(Some(_)) => break,
                Ok(None) if Instant::now() < deadline => {
                    tokio::time::sleep(Duration::from_millis(50)).await
                }
                _ => {
                    let _ = c.kill();
                    let _ = c.wait();
                    break;
                }
            }
        }
    }
}
