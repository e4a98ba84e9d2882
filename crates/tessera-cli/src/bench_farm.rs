//! `tessera bench-farm`: the farm's overhead, measured side by side in one run.

use anyhow::{bail, Context, Result};
use clap::Args;
use std::io::BufRead;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};
use tessera_api::client::Client;
use tessera_api::{JobSettings, JobState};

use crate::common::{client_error, cpu_seconds};

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
    /// Also time the farm while this many dashboard-like pollers watch the job (each,
    /// once a second: the status, and the PNG, tile map and history when the status
    /// changed), and report their request latencies.
    #[arg(long, default_value_t = 0)]
    pub pollers: usize,
    /// The `tessera` binary that runs the farm (default: this one), e.g. an older build
    /// to compare against in the same run.
    #[arg(long)]
    pub farm_binary: Option<std::path::PathBuf>,
    /// A second `tessera` binary whose farm is also timed in every round, right after the
    /// first one's (e.g. the build before a change), so both are compared with the same
    /// local runs on the same machine load.
    #[arg(long)]
    pub compare_binary: Option<std::path::PathBuf>,
    /// An extra argument for the farm's `tessera serve` (repeatable), e.g.
    /// `--serve-arg=--http-max-connections-per-address=1024` so that many pollers from
    /// this one address are not refused.
    #[arg(long, allow_hyphen_values = true)]
    pub serve_arg: Vec<String>,
}

/// Runs the benchmark: alternately renders the job with `tessera render` and through a
/// fresh `tessera serve` (timed from submission to done, so the farm's start-up is not
/// counted but its scene loading, leasing, gRPC transfers, merging and store commits are),
/// and prints the throughput ratio.
pub fn bench_farm(args: BenchFarmArgs) -> Result<()> {
    let exe = match &args.farm_binary {
        Some(p) => p.clone(),
        None => std::env::current_exe().context("locating the tessera binary")?,
    };
    let dir = std::env::temp_dir().join(format!("tessera-bench-farm-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let mut local = Vec::new();
    let mut farm = Vec::new();
    // Of the farm runs: the fraction of the workers' thread time spent rendering.
    let mut busy = Vec::new();
    // Of the farm runs: throughput per unit of work rendered, spot checks' second copies
    // counted as work (the farm's own overhead, without the checks' deliberate cost).
    let mut per_work = Vec::new();
    // The compared binary's farm: seconds and busy fractions.
    let mut compared = Vec::new();
    let mut compared_busy = Vec::new();
    let mut polled = Vec::new();
    let mut latencies = Vec::new();
    let mut requests = 0usize;
    // CPU seconds of the coordinator (alone, polled) and of the pollers themselves: the
    // pollers run in this process on the farm's cores, which a real dashboard does not.
    let mut cpu = [0.0f64; 3];
    for rep in 0..args.repeat.max(1) {
        let l = time_local(&exe, &args, &dir.join("local.exr"))?;
        let data = dir.join(format!("data{rep}"));
        let _ = std::fs::remove_dir_all(&data);
        let alone = time_farm(&exe, &args, &data, 0)?;
        let f = alone.seconds;
        cpu[0] += alone.coordinator_cpu;
        busy.push(alone.busy);
        per_work.push(l / f * (1.0 + alone.rendered_twice));
        if args.pollers > 0 {
            let data = dir.join(format!("polled{rep}"));
            let _ = std::fs::remove_dir_all(&data);
            let polled_run = time_farm(&exe, &args, &data, args.pollers)?;
            let (p, mut lat) = (polled_run.seconds, polled_run.latencies);
            cpu[1] += polled_run.coordinator_cpu;
            cpu[2] += polled_run.pollers_cpu;
            requests += lat.len();
            let mut sorted = lat.clone();
            sorted.sort_by(f64::total_cmp);
            println!(
                "run {}: farm with {} pollers: {p:.3} s ({:.2}x the farm alone); {} requests ({:.0}/s), p50 {:.1} ms, p99 {:.1} ms",
                rep + 1,
                args.pollers,
                p / f,
                sorted.len(),
                sorted.len() as f64 / p,
                1e3 * quantile(&sorted, 0.5),
                1e3 * quantile(&sorted, 0.99)
            );
            polled.push(p);
            latencies.append(&mut lat);
        }
        println!(
            "run {}: tessera render --threads {}: {l:.3} s; tessera serve --workers {} (1 thread each): {f:.3} s; farm/local throughput {:.3}; workers rendering {:.1}% of the time; spot checks rendered {:.1}% of the units twice",
            rep + 1,
            args.threads,
            args.threads,
            l / f,
            100.0 * alone.busy,
            100.0 * alone.rendered_twice
        );
        if let Some(other) = &args.compare_binary {
            let data = dir.join(format!("compared{rep}"));
            let _ = std::fs::remove_dir_all(&data);
            let c = time_farm(other, &args, &data, 0)?;
            println!(
                "run {}: compared farm ({}): {:.3} s; farm/local throughput {:.3}; workers rendering {}",
                rep + 1,
                other.display(),
                c.seconds,
                l / c.seconds,
                busy_text(c.busy)
            );
            compared.push(c.seconds);
            compared_busy.push(c.busy);
        }
        local.push(l);
        farm.push(f);
    }
    for v in [&mut busy, &mut per_work, &mut compared, &mut compared_busy] {
        v.sort_by(f64::total_cmp);
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
    println!(
        "bench-farm per unit of work: farm throughput {:.1}% of local counting the units spot checks rendered twice as work (median)",
        100.0 * per_work[per_work.len() / 2]
    );
    println!(
        "bench-farm workers: rendering {:.1}% of the farm's wall time (median; the rest is waiting on leases, scenes and the start and end of the job)",
        100.0 * busy[busy.len() / 2]
    );
    if let Some(other) = &args.compare_binary {
        let c = compared[compared.len() / 2];
        println!(
            "bench-farm compared: median farm {c:.3} s ({:.0} paths/s) with {}; farm throughput {:.1}% of local (this binary {:.1}%); workers rendering {}",
            paths / c,
            other.display(),
            100.0 * l / c,
            100.0 * l / f,
            busy_text(compared_busy[compared_busy.len() / 2])
        );
    }
    if args.pollers > 0 {
        polled.sort_by(f64::total_cmp);
        latencies.sort_by(f64::total_cmp);
        let p = polled[polled.len() / 2];
        println!(
            "bench-farm pollers: {} pollers, {requests} requests; median farm {f:.3} s alone, {p:.3} s polled (render slowed {:+.1}%); latency p50 {:.1} ms, p99 {:.1} ms, max {:.1} ms",
            args.pollers,
            100.0 * (p / f - 1.0),
            1e3 * quantile(&latencies, 0.5),
            1e3 * quantile(&latencies, 0.99),
            1e3 * latencies.last().copied().unwrap_or(0.0)
        );
        let n = f64::from(args.repeat.max(1));
        println!(
            "bench-farm pollers CPU (per run): coordinator {:.2} s alone, {:.2} s polled ({:.0} us per request); the pollers themselves {:.2} s",
            cpu[0] / n,
            cpu[1] / n,
            1e6 * (cpu[1] - cpu[0]) / requests.max(1) as f64,
            cpu[2] / n
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}

/// The `q` quantile of sorted values (nearest rank); 0 for none.
pub(crate) fn quantile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    let i = ((q * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len()) - 1;
    sorted[i]
}

/// One dashboard-like poller of job `id` until `stop`: once a second the status, and
/// when it changed the PNG, the tile map and the history, as `job.js` does. Returns the
/// latency of every request, seconds.
fn poll_like_the_dashboard(url: &str, id: u64, stop: &std::sync::atomic::AtomicBool) -> Vec<f64> {
    let client = Client::new(url, None);
    let mut lat = Vec::new();
    let mut last = None;
    let mut timed = |f: &mut dyn FnMut() -> bool| {
        let t = Instant::now();
        let ok = f();
        lat.push(t.elapsed().as_secs_f64());
        ok
    };
    while !stop.load(std::sync::atomic::Ordering::Relaxed) {
        let tick = Instant::now();
        let mut key = None;
        timed(&mut || {
            key = client.job(id).ok().map(|s| (s.passes_done, s.state));
            key.is_some()
        });
        if key.is_some() && key != last {
            timed(&mut || client.image(id, "png").is_ok());
            timed(&mut || client.tiles(id).is_ok());
            timed(&mut || client.history(id).is_ok());
            last = key;
        }
        if let Some(rest) = Duration::from_secs(1).checked_sub(tick.elapsed()) {
            std::thread::sleep(rest);
        }
    }
    lat
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

/// One timed farm run.
struct FarmRun {
    /// From the job's submission to done.
    seconds: f64,
    /// Every poller request's latency, seconds.
    latencies: Vec<f64>,
    /// CPU seconds (user + system) the coordinator process used, start-up included (its
    /// workers are separate processes and not counted).
    coordinator_cpu: f64,
    /// CPU seconds this process used while the job ran: the pollers' own cost.
    pollers_cpu: f64,
    /// The workers' reported render seconds over their threads' wall time from
    /// submission to done (`tessera_worker_render_seconds_total` in `/metrics`).
    busy: f64,
    /// Units rendered a second time by spot checks over the units merged.
    rendered_twice: f64,
}

/// A fresh `tessera serve` on `data` from the job's submission to done, with `pollers`
/// dashboard-like pollers watching.
fn time_farm(exe: &Path, args: &BenchFarmArgs, data: &Path, pollers: usize) -> Result<FarmRun> {
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
    let self_cpu = cpu_seconds("self");
    let t = Instant::now();
    let t_unix_ms = unix_ms();
    let job = client.submit(&s, None).map_err(client_error)?;
    // A coordinator that reports when the job finished (`finished_unix_ms`, the same
    // host's clock) is polled every 100 ms and timed by that, to the millisecond, without
    // a status request every 10 ms on the farm's cores (no real client polls that often;
    // the difference was within the run-to-run spread, docs/benchmarks.md). An older
    // binary (`--compare-binary`) is timed by the poll.
    let reports_finish = client
        .get_raw(&format!("/jobs/{}", job.id))
        .is_ok_and(|b| String::from_utf8_lossy(&b).contains("\"finished_unix_ms\""));
    let every = Duration::from_millis(if reports_finish { 100 } else { 10 });
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let watchers: Vec<_> = (0..pollers)
        .map(|_| {
            let (url, stop) = (url.clone(), stop.clone());
            std::thread::spawn(move || poll_like_the_dashboard(&url, job.id, &stop))
        })
        .collect();
    let done = client
        .wait(job.id, every, Duration::from_secs(3600), |_| {})
        .map_err(client_error)?;
    let f = match done.finished_unix_ms {
        Some(end) if reports_finish => end.saturating_sub(t_unix_ms) as f64 / 1e3,
        _ => t.elapsed().as_secs_f64(),
    };
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    let mut latencies = Vec::new();
    for w in watchers {
        latencies.extend(w.join().unwrap_or_default());
    }
    let pollers_cpu = cpu_seconds("self") - self_cpu;
    let coordinator_cpu = cpu_seconds(&child.id().to_string());
    // An older binary without the counters reports 0.
    let metrics = client
        .get_raw("/metrics")
        .map(|m| String::from_utf8_lossy(&m).into_owned())
        .unwrap_or_default();
    let render_seconds = metric(&metrics, "tessera_worker_render_seconds_total").unwrap_or(0.0);
    // Spot checks (`--spot-check-fraction`, 2% by default) lease some units a second
    // time on purpose: work the local render does not do.
    let merged = metric(&metrics, "tessera_units_merged_total").unwrap_or(0.0);
    let spot_checked: f64 = metrics
        .lines()
        .filter(|l| l.starts_with("tessera_spot_checks_total{"))
        .filter_map(|l| l.rsplit(' ').next()?.parse::<f64>().ok())
        .sum();
    let _ = child.kill();
    let _ = child.wait();
    if done.state != JobState::Done {
        bail!("the farm job ended {}", done.state.as_str());
    }
    Ok(FarmRun {
        seconds: f,
        latencies,
        coordinator_cpu,
        pollers_cpu,
        busy: render_seconds / (f * args.threads.max(1) as f64),
        rendered_twice: if merged > 0.0 {
            spot_checked / merged
        } else {
            0.0
        },
    })
}

/// The wall clock, Unix milliseconds.
fn unix_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

/// A busy fraction as printed: "not reported" by a coordinator without the counter.
fn busy_text(busy: f64) -> String {
    if busy > 0.0 {
        format!("{:.1}% of the time", 100.0 * busy)
    } else {
        "not reported (no tessera_worker_render_seconds_total)".to_string()
    }
}

/// The value of an unlabelled sample `name` in a Prometheus text exposition.
fn metric(text: &str, name: &str) -> Option<f64> {
    text.lines()
        .filter(|l| !l.starts_with('#'))
        .find_map(|l| l.strip_prefix(name)?.strip_prefix(' ')?.trim().parse().ok())
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
        .args(&args.serve_arg)
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
