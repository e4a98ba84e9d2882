//! `tessera bench-farm`: the farm's overhead, measured side by side in one run.

use anyhow::{bail, Context, Result};
use clap::Args;
use std::io::BufRead;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};
use tessera_api::client::Client;
use tessera_api::{JobSettings, JobState};

use crate::common::client_error;

/// `tessera bench-farm`: the farm's overhead, measured side by side in one run.
#[derive(Args, Clone, Debug)]
pub struct BenchFarmArgs {
    /// Scene to render.
    #[arg(default_value = "builtin:cornell-box")]
    pub scene: String,
    /// Image width.
    #[arg(long, default_value_t = 256)]
    pub width: u32,
    /// Image height.
    #[arg(long, default_value_t = 256)]
    pub height: u32,
    /// Samples per pixel.
    #[arg(long, default_value_t = 64)]
    pub spp: u32,
    /// Threads in total: `tessera render --threads N` against `tessera serve --workers N`
    /// with one thread each.
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
    /// Alternating repetitions of each (the median is reported).
    #[arg(long, default_value_t = 3)]
    pub repeat: u32,
}

/// Runs the benchmark: alternately renders the job with `tessera render` and through a
/// fresh `tessera serve` (timed from submission to done, so the farm's start-up is not
/// counted but its scene loading, leasing, gRPC transfers, merging and store commits are),
/// and prints the throughput ratio.
pub fn bench_farm(args: BenchFarmArgs) -> Result<()> {
    let exe = std::env::current_exe().context("locating the tessera binary")?;
    let dir = std::env::temp_dir().join(format!("tessera-bench-farm-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let mut local = Vec::new();
    let mut farm = Vec::new();
    for rep in 0..args.repeat.max(1) {
        let l = time_local(&exe, &args, &dir.join("local.exr"))?;
        let data = dir.join(format!("data{rep}"));
        let _ = std::fs::remove_dir_all(&data);
        let f = time_farm(&exe, &args, &data)?;
        println!(
            "run {}: tessera render --threads {}: {l:.3} s; tessera serve --workers {} (1 thread each): {f:.3} s; farm/local throughput {:.3}",
            rep + 1,
            args.threads,
            args.threads,
            l / f
        );
        local.push(l);
        farm.push(f);
    }
    local.sort_by(f64::total_cmp);
    farm.sort_by(f64::total_cmp);
    let (l, f) = (local[local.len() / 2], farm[farm.len() / 2]);
    let paths = f64::from(args.width) * f64::from(args.height) * f64::from(args.spp);
    println!(
        "bench-farm {} {}x{} {} spp: median local {l:.3} s ({:.0} paths/s), farm {f:.3} s ({:.0} paths/s); farm throughput {:.1}% of local (overhead {:+.1}%)",
        args.scene,
        args.width,
        args.height,
        args.spp,
        paths / l,
        paths / f,
        100.0 * l / f,
        100.0 * (f / l - 1.0)
    );
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}

/// Seconds `tessera render` takes for the job, writing `out`.
fn time_local(exe: &Path, args: &BenchFarmArgs, out: &Path) -> Result<f64> {
    let t = Instant::now();
    let o = Command::new(exe)
        .arg("render")
        .arg(&args.scene)
        .args(["--width", &args.width.to_string()])
        .args(["--height", &args.height.to_string()])
        .args(["--spp", &args.spp.to_string()])
        .args(["--threads", &args.threads.to_string()])
        .arg("-o")
        .arg(out)
        .output()?;
    if !o.status.success() {
        bail!(
            "tessera render failed: {}",
            String::from_utf8_lossy(&o.stderr)
        );
    }
    Ok(t.elapsed().as_secs_f64())
}

/// Seconds a fresh `tessera serve` on `data` takes from the job's submission to done.
fn time_farm(exe: &Path, args: &BenchFarmArgs, data: &Path) -> Result<f64> {
    let (mut child, url) = start_farm(exe, args, data)?;
    let client = Client::new(&url, None);
    // Wait until the workers registered, so their start-up is not timed.
    let start = Instant::now();
    while client.workers().map_or(0, |w| w.workers.len()) < args.threads {
        if start.elapsed() > Duration::from_secs(30) {
            bail!("the local workers did not register");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let mut s = JobSettings::new(args.scene.clone());
    s.width = Some(args.width);
    s.height = Some(args.height);
    s.spp = args.spp;
    let t = Instant::now();
    let job = client.submit(&s, None).map_err(client_error)?;
    let done = client
        .wait(
            job.id,
            Duration::from_millis(10),
            Duration::from_secs(3600),
            |_| {},
        )
        .map_err(client_error)?;
    let f = t.elapsed().as_secs_f64();
    let _ = child.kill();
    let _ = child.wait();
    if done.state != JobState::Done {
        bail!("the farm job ended {}", done.state.as_str());
    }
    Ok(f)
}

/// Starts `tessera serve` with one single-threaded worker per benchmark thread on port-0
/// listeners, and reads its dashboard URL once its workers are started.
fn start_farm(exe: &Path, args: &BenchFarmArgs, data: &Path) -> Result<(Child, String)> {
    let mut child = Command::new(exe)
        .arg("serve")
        .args(["--workers", &args.threads.to_string()])
        .args(["--threads-per-worker", "1"])
        .args([
            "--http",
            "127.0.0.1:0",
            "--grpc",
            "127.0.0.1:0",
            "--demo",
            "none",
        ])
        .arg("--data")
        .arg(data)
        .stdout(Stdio::piped())
        .spawn()?;
    let stdout = child.stdout.take().context("serve stdout")?;
    let mut url = None;
    let mut lines = std::io::BufReader::new(stdout).lines();
    for line in lines.by_ref() {
        let line = line?;
        if let Some(u) = line.strip_prefix("dashboard: ") {
            url = Some(u.trim().trim_end_matches('/').to_string());
        }
        if line.contains("local worker") {
            break;
        }
    }
    std::thread::spawn(move || for _ in lines {});
    let url = url.context("tessera serve printed no URL")?;
    Ok((child, url))
}
