//! `tessera worker`: leases work units from a coordinator and renders them on all cores
//! until Ctrl-C, SIGTERM or the coordinator's shutdown (finishing the units in hand).

use anyhow::Result;
use clap::Args;
use std::io::BufRead;
use std::path::PathBuf;
use tessera_coordinator::shutdown_signal;

use crate::common::{init_tracing, runtime};

/// `tessera worker`.
#[derive(Args, Clone, Debug)]
pub struct WorkerArgs {
    /// The coordinator's gRPC URL. Give it several times (or comma-separated) for
    /// failover between an active coordinator and its standbys: on a lost connection or
    /// an answer "not the active coordinator" the worker tries the next one.
    #[arg(
        long = "coordinator",
        value_name = "URL",
        default_value = "http://127.0.0.1:50051",
        value_delimiter = ','
    )]
    pub coordinators: Vec<String>,
    /// Rendering threads (0 = all cores).
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
    /// Name shown in the worker list (default: host name and process id).
    #[arg(long)]
    pub name: Option<String>,
    /// Bearer token of the coordinator's worker port.
    #[arg(long, env = "TESSERA_WORKER_TOKEN")]
    pub token: Option<String>,
    /// CA certificate(s) (PEM) the coordinator's certificate must be issued by; needed
    /// for an `https://` --coordinator.
    #[arg(long, value_name = "FILE")]
    pub tls_ca: Option<PathBuf>,
    /// The worker's certificate chain (PEM), for a coordinator with --tls-client-ca.
    #[arg(long, value_name = "FILE", requires = "tls_key")]
    pub tls_cert: Option<PathBuf>,
    /// The private key (PEM) of --tls-cert.
    #[arg(long, value_name = "FILE", requires = "tls_cert")]
    pub tls_key: Option<PathBuf>,
    // Testing aids: none in a release build (tessera-worker's `fault-injection` feature).
    // (A comment, not a doc comment: the flattened arguments carry their own help.)
    #[command(flatten)]
    pub faults: FaultArgs,
    /// Exit when standard input closes (used by `tessera serve` for its local workers, so
    /// they never outlive it).
    #[arg(long, hide = true)]
    pub exit_with_stdin: bool,
}

tessera_worker::with_fault_injection! {
    /// The testing aids of `tessera worker`, in a build with tessera-worker's
    /// `fault-injection` feature (the test builds; `--features fault-injection`).
    #[derive(Args, Clone, Debug)]
    pub struct FaultArgs {
        /// TESTING AID, never for production: corrupt this fraction (0 to 1) of the units
        /// this worker renders, chosen by a hash of each unit (the same units every run), by
        /// flipping the lowest bit of one value. The results stay well-formed, so only the
        /// coordinator's spot checks (--spot-check-fraction) catch them and quarantine the
        /// worker (docs/ARCHITECTURE.md §6, "Spot checks and quarantine").
        #[arg(long, value_name = "FRACTION", default_value_t = 0.0, value_parser = parse_fraction)]
        pub inject_faults: f64,
    }

    impl FaultArgs {
        /// The fraction of units to corrupt.
        fn inject_faults(&self) -> f64 {
            self.inject_faults
        }
    }
}

tessera_worker::without_fault_injection! {
    /// The testing aids of `tessera worker`: none in this build (tessera-worker's
    /// `fault-injection` feature is off).
    #[derive(Args, Clone, Debug)]
    pub struct FaultArgs {}

    impl FaultArgs {
        /// No unit is corrupted.
        fn inject_faults(&self) -> f64 {
            0.0
        }
    }
}

/// `tessera worker`.
pub fn worker(args: WorkerArgs) -> Result<()> {
    init_tracing();
    let threads = if args.threads == 0 {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    } else {
        args.threads
    };
    let name = args.name.clone().unwrap_or_else(|| {
        let host = std::fs::read_to_string("/etc/hostname")
            .map(|h| h.trim().to_string())
            .unwrap_or_else(|_| "worker".into());
        format!("{host}-{}", std::process::id())
    });
    let identity = args.tls_cert.as_deref().zip(args.tls_key.as_deref());
    let tls = match &args.tls_ca {
        Some(ca) => Some(tessera_worker::WorkerTls::from_files(ca, identity)?),
        None if identity.is_some() => anyhow::bail!("--tls-cert and --tls-key need --tls-ca"),
        None => None,
    };
    let config = tessera_worker::WorkerConfig {
        coordinators: args.coordinators.clone(),
        threads,
        name,
        token: args.token.clone().filter(|t| !t.is_empty()),
        tls,
        inject_faults: args.faults.inject_faults(),
    };
    let exit_with_stdin = args.exit_with_stdin;
    runtime()?.block_on(async move {
        tessera_worker::run(config, stop(exit_with_stdin))
            .await
            .map_err(anyhow::Error::from)
    })
}

/// A fraction between 0 and 1.
pub(crate) fn parse_fraction(s: &str) -> std::result::Result<f64, String> {
    match s.trim().parse::<f64>() {
        Ok(f) if (0.0..=1.0).contains(&f) => Ok(f),
        _ => Err(format!("{s:?} is not a fraction between 0 and 1")),
    }
}

/// Completes on Ctrl-C or SIGTERM, or (with `exit_with_stdin`) when standard input closes.
async fn stop(exit_with_stdin: bool) {
    if !exit_with_stdin {
        return shutdown_signal().await;
    }
    let (tx, rx) = tokio::sync::oneshot::channel::<()>();
    std::thread::spawn(move || {
        let mut sink = Vec::new();
        let _ = std::io::stdin().lock().read_until(0, &mut sink);
        let _ = tx.send(());
    });
    tokio::select! {
        _ = shutdown_signal() => {}
        _ = rx => {}
    }
}
