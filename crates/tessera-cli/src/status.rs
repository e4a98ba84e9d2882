//! `tessera status`: a job of a coordinator, or its newest jobs, one progress line each.

use anyhow::Result;
use clap::Args;
use std::path::PathBuf;
use tessera_api::JobStatus;

use crate::common::client_error;

/// `tessera status`.
#[derive(Args, Clone, Debug)]
pub struct StatusArgs {
    /// A job id; without it, the newest jobs.
    pub job: Option<u64>,
    /// The coordinator's HTTP URL.
    #[arg(long, default_value = "http://127.0.0.1:8080", env = "TESSERA_SERVER")]
    pub server: String,
    /// API bearer token.
    #[arg(long, env = "TESSERA_API_TOKEN")]
    pub token: Option<String>,
    /// CA certificate(s) (PEM) an `https://` server's certificate must be issued by.
    #[arg(long, value_name = "FILE")]
    pub tls_ca: Option<PathBuf>,
    /// Print the JSON the API returned.
    #[arg(long)]
    pub json: bool,
    /// How many jobs to list.
    #[arg(long, default_value_t = 20)]
    pub limit: u32,
}

/// One line of a job's progress, as `tessera status` and `tessera submit --wait` print it.
pub fn progress_line(s: &JobStatus) -> String {
    let err = s
        .error_estimate
        .map_or("-".into(), |e| format!("{:.2}%", e * 100.0));
    let eta = s.eta_seconds.map_or("-".into(), |e| format!("{e:.0} s"));
    format!(
        "job {} {}: passes {}/{}, {:.1} spp, error {}, {:.1} s, eta {}",
        s.id,
        s.state.as_str(),
        s.passes_done,
        s.passes_planned,
        s.spp_so_far,
        err,
        s.elapsed_seconds,
        eta
    )
}

/// `tessera status`.
pub fn status(args: StatusArgs) -> Result<()> {
    let client =
        crate::common::api_client(&args.server, args.token.clone(), args.tls_ca.as_deref())?;
    match args.job {
        Some(id) => {
            let s = client.job(id).map_err(client_error)?;
            if args.json {
                println!("{}", serde_json::to_string_pretty(&s)?);
            } else {
                println!("{}", progress_line(&s));
                if let Some(e) = &s.error {
                    println!("error: {e}");
                }
                if let Some(r) = &s.stop_reason {
                    println!("stopped: {r}");
                }
                if let Some(c) = &s.error_estimate_caveat {
                    println!("error estimate caveat: {c}");
                }
            }
        }
        None => {
            let list = client.jobs(args.limit, None).map_err(client_error)?;
            if args.json {
                println!("{}", serde_json::to_string_pretty(&list)?);
            } else if list.jobs.is_empty() {
                println!("no jobs");
            } else {
                for s in &list.jobs {
                    println!("{}", progress_line(s));
                }
            }
        }
    }
    Ok(())
}
