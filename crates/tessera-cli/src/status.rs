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
    let eta = eta_text(s);
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

/// The ETA as the progress line gives it: "12 s", with its 95% interval for a job that
/// stops at its target ("12 s [8, 20 s]"), or "not predictable (at least 5 s, at most
/// 120 s)" when the passes so far cannot predict the error ([`JobStatus::eta_note`] says
/// why); "-" when there is none.
pub fn eta_text(s: &JobStatus) -> String {
    let interval = s.eta_low_seconds.zip(s.eta_high_seconds);
    match (s.eta_seconds, interval) {
        (Some(e), Some((lo, hi))) => format!("{e:.0} s [{lo:.0}, {hi:.0} s]"),
        (Some(e), None) => format!("{e:.0} s"),
        (None, Some((lo, hi))) if s.eta_tail_class.as_deref() == Some("unpredictable") => {
            format!("not predictable (at least {lo:.0} s, at most {hi:.0} s)")
        }
        (None, _) => "-".into(),
    }
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
                if let Some(n) = s.eta_note.as_ref().filter(|_| !s.state.is_terminal()) {
                    println!("eta: {n}");
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

#[cfg(test)]
mod tests {
    use super::*;

    fn running() -> JobStatus {
        serde_json::from_value(serde_json::json!({
            "id": 7, "name": null, "state": "running", "scene": "builtin:caustic",
            "settings": {"scene": "builtin:caustic"},
            "frames_total": 1, "frames_done": 0, "tiles_total": 1, "passes_planned": 64,
            "passes_done": 8, "spp_so_far": 128.0, "error_estimate": 0.2,
            "target_error": 0.05, "elapsed_seconds": 4.0, "eta_seconds": 60.0,
            "created_unix_ms": 0, "priority": 0, "faults": 0, "adaptive": "sequential"
        }))
        .unwrap()
    }

    /// The progress line's ETA: the point alone from an older server, with its interval
    /// for a job that stops at its target, and "not predictable" with its bounds.
    #[test]
    fn the_progress_line_gives_the_eta_interval_or_says_not_predictable() {
        let old = running();
        assert!(
            progress_line(&old).ends_with("eta 60 s"),
            "{}",
            progress_line(&old)
        );
        let light = JobStatus {
            eta_low_seconds: Some(50.0),
            eta_high_seconds: Some(75.0),
            eta_tail_class: Some("light".into()),
            ..running()
        };
        assert!(progress_line(&light).ends_with("eta 60 s [50, 75 s]"));
        let not = JobStatus {
            eta_seconds: None,
            eta_low_seconds: Some(12.0),
            eta_high_seconds: Some(500.0),
            eta_tail_class: Some("unpredictable".into()),
            eta_note: Some("not predictable from the passes so far: ...".into()),
            ..running()
        };
        assert!(
            progress_line(&not).ends_with("eta not predictable (at least 12 s, at most 500 s)"),
            "{}",
            progress_line(&not)
        );
    }
}
