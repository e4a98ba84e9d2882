//! `tessera bench-fleet`: the coordinator under a fleet of simulated workers.
//!
//! A real `tessera coordinator` process is driven over real gRPC on loopback by N
//! simulated workers, each its own connection, registering, heartbeating, leasing one
//! unit at a time and answering it at once (or after `--unit-ms`) with a valid result of
//! the right size (a flat synthetic radiance: the coordinator validates and merges it like
//! any other). No ray is traced, so what is measured is the coordinator: merged units per
//! second, lease latency, and its CPU and memory, for each fleet size. A benchmark, not a
//! test: nothing asserts a speed.

use anyhow::{bail, Context, Result};
use clap::Args;
use std::io::BufRead;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tessera_api::client::Client;
use tessera_api::{JobSettings, JobState};
use tessera_farm::job::FrameRange;
use tessera_farm::FramePlan;
use tessera_proto::v1;
use tessera_proto::v1::worker_service_client::WorkerServiceClient;

use crate::bench_farm::quantile;
use crate::common::{client_error, cpu_seconds};

/// `tessera bench-fleet`.
#[derive(Args, Clone, Debug)]
pub struct BenchFleetArgs {
    /// Fleet sizes to measure, one fresh coordinator each.
    #[arg(long, value_delimiter = ',', default_value = "10,100,1000")]
    pub workers: Vec<usize>,
    /// Frames of the job (64 x 64 pixels, 16 tiles each); the units are what the
    /// coordinator's plan makes of them.
    #[arg(long, default_value_t = 400)]
    pub frames: u32,
    /// Samples per pixel of the job (more means more passes, so more units per tile).
    #[arg(long, default_value_t = 64)]
    pub spp: u32,
    /// The `tessera` binary that runs the coordinator (default: this one).
    #[arg(long)]
    pub coordinator_binary: Option<std::path::PathBuf>,
    /// Each simulated worker's render time per unit, ms: 0 answers at once (the
    /// coordinator saturated, every worker always waiting on it, so latency is the queue
    /// Little's law says); e.g. 150 offers 1,000 workers' 6,000 units/s at most, a fleet
    /// rendering real units, which is where lease latency means something.
    #[arg(long, default_value_t = 0)]
    pub unit_ms: u64,
}

/// What one fleet size measured.
struct FleetRun {
    workers: usize,
    units: u64,
    seconds: f64,
    /// Latency of every lease call that returned a unit, seconds, sorted.
    lease_latency: Vec<f64>,
    coordinator_cpu: f64,
    coordinator_peak_rss: u64,
    bench_cpu: f64,
}

/// Runs the benchmark for each fleet size and prints one line each and a table.
pub fn bench_fleet(args: BenchFleetArgs) -> Result<()> {
    let exe = match &args.coordinator_binary {
        Some(p) => p.clone(),
        None => std::env::current_exe().context("locating the tessera binary")?,
    };
    let dir = std::env::temp_dir().join(format!("tessera-bench-fleet-{}", std::process::id()));
    let mut runs = Vec::new();
    for &n in &args.workers {
        if n == 0 || n > 10_000 {
            bail!("--workers: {n} is not between 1 and 10000");
        }
        let data = dir.join(format!("w{n}"));
        let _ = std::fs::remove_dir_all(&data);
        let r = run_fleet(&exe, &args, &data, n)?;
        println!(
            "bench-fleet {} workers: {} units in {:.2} s = {:.0} units/s merged; lease p50 {:.2} ms, p99 {:.2} ms; coordinator {:.2} s CPU ({:.0}% of one core), peak RSS {} MiB; simulated workers {:.2} s CPU",
            r.workers,
            r.units,
            r.seconds,
            r.units as f64 / r.seconds,
            1e3 * quantile(&r.lease_latency, 0.5),
            1e3 * quantile(&r.lease_latency, 0.99),
            r.coordinator_cpu,
            100.0 * r.coordinator_cpu / r.seconds,
            r.coordinator_peak_rss >> 20,
            r.bench_cpu
        );
        runs.push(r);
    }
    println!();
    println!(
        "| workers | units | units/s merged | lease p50 | lease p99 | coordinator CPU | peak RSS |"
    );
    println!("|---|---|---|---|---|---|---|");
    for r in &runs {
        println!(
            "| {} | {} | {:.0} | {:.2} ms | {:.2} ms | {:.0}% of a core | {} MiB |",
            r.workers,
            r.units,
            r.units as f64 / r.seconds,
            1e3 * quantile(&r.lease_latency, 0.5),
            1e3 * quantile(&r.lease_latency, 0.99),
            100.0 * r.coordinator_cpu / r.seconds,
            r.coordinator_peak_rss >> 20
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}

/// One fresh coordinator on `data`, one job, `n` simulated workers until it is done.
fn run_fleet(exe: &Path, args: &BenchFleetArgs, data: &Path, n: usize) -> Result<FleetRun> {
    let (mut child, http, grpc) = start_coordinator(exe, data)?;
    let pid = child.id().to_string();
    let result = (|| {
        let client = Client::new(&http, None);
        let mut s = JobSettings::new("builtin:cornell-box");
        s.width = Some(64);
        s.height = Some(64);
        s.tile_size = 16;
        s.spp = args.spp;
        s.frames = FrameRange {
            start: 0,
            end: args.frames.max(1) - 1,
        };
        let rt = tokio::runtime::Builder::new_multi_thread()
            .enable_all()
            .build()?;
        let stop = Arc::new(AtomicBool::new(false));
        let merged = Arc::new(AtomicU64::new(0));
        // Connect and register the whole fleet before the job exists, so start-up is not
        // timed.
        let fleet = rt.block_on(connect_fleet(&grpc, n))?;
        let bench_cpu0 = cpu_seconds("self");
        let t = Instant::now();
        let job = client.submit(&s, None).map_err(client_error)?;
        let tasks: Vec<_> = fleet
            .into_iter()
            .map(|w| rt.spawn(simulate(w, stop.clone(), merged.clone(), args.unit_ms)))
            .collect();
        let done = client
            .wait(
                job.id,
                Duration::from_millis(20),
                Duration::from_secs(3600),
                |_| {},
            )
            .map_err(client_error)?;
        let seconds = t.elapsed().as_secs_f64();
        stop.store(true, Ordering::Relaxed);
        let mut lease_latency = Vec::new();
        for task in tasks {
            lease_latency.extend(rt.block_on(task)??);
        }
        let bench_cpu = cpu_seconds("self") - bench_cpu0;
        if done.state != JobState::Done {
            bail!("the job ended {}", done.state.as_str());
        }
        lease_latency.sort_by(f64::total_cmp);
        Ok(FleetRun {
            workers: n,
            units: merged.load(Ordering::Relaxed),
            seconds,
            lease_latency,
            coordinator_cpu: cpu_seconds(&pid),
            coordinator_peak_rss: peak_rss(&pid),
            bench_cpu,
        })
    })();
    let _ = child.kill();
    let _ = child.wait();
    result
}

/// A registered simulated worker.
struct SimWorker {
    /// Carries the worker's session secret on every call (worker.proto, "Sessions").
    client: WorkerServiceClient<
        tonic::service::interceptor::InterceptedService<
            tonic::transport::Channel,
            tessera_proto::WithSession,
        >,
    >,
    id: u64,
    heartbeat: Duration,
}

/// Connects and registers `n` workers, each over its own connection.
async fn connect_fleet(grpc: &str, n: usize) -> Result<Vec<SimWorker>> {
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        let channel = tonic::transport::Endpoint::from_shared(grpc.to_string())?
            .tcp_nodelay(true)
            .connect()
            .await
            .with_context(|| format!("connecting simulated worker {i} to {grpc}"))?;
        let reg = WorkerServiceClient::new(channel.clone())
            .register(v1::RegisterRequest {
                name: format!("sim-{i}"),
                threads: 1,
                version: env!("CARGO_PKG_VERSION").to_string(),
                capabilities: vec!["path".into(), "direct".into()],
            })
            .await?
            .into_inner();
        let session = tessera_proto::WithSession::new(&reg.session)?;
        out.push(SimWorker {
            client: WorkerServiceClient::with_interceptor(channel, session),
            id: reg.worker_id,
            heartbeat: Duration::from_millis(u64::from(reg.heartbeat_interval_ms.max(50))),
        });
    }
    Ok(out)
}

/// One simulated worker until `stop`: lease a unit, answer it after `unit_ms` (at once
/// for 0) with a flat valid result, heartbeat on time. Returns the latency of every lease
/// call that got a unit.
async fn simulate(
    mut w: SimWorker,
    stop: Arc<AtomicBool>,
    merged: Arc<AtomicU64>,
    unit_ms: u64,
) -> Result<Vec<f64>> {
    let mut latency = Vec::new();
    let mut last_beat = Instant::now();
    while !stop.load(Ordering::Relaxed) {
        if last_beat.elapsed() >= w.heartbeat {
            w.client
                .heartbeat(v1::HeartbeatRequest {
                    worker_id: w.id,
                    lease_ids: Vec::new(),
                    paths_per_second: 0.0,
                })
                .await?;
            last_beat = Instant::now();
        }
        let t = Instant::now();
        let resp = w
            .client
            .lease_work(v1::LeaseRequest {
                worker_id: w.id,
                max_units: 1,
                wait_ms: 0,
            })
            .await?
            .into_inner();
        if resp.leases.is_empty() {
            let wait = u64::from(resp.retry_after_ms).clamp(10, 200);
            tokio::time::sleep(Duration::from_millis(wait)).await;
            continue;
        }
        latency.push(t.elapsed().as_secs_f64());
        for lease in resp.leases {
            let (Some(plan), Some(unit)) = (lease.plan, lease.unit) else {
                bail!("lease {} has no plan or unit", lease.lease_id);
            };
            let plan = FramePlan::try_from(plan).map_err(|e| anyhow::anyhow!("{e}"))?;
            let Some(rect) = plan.get_tile(unit.tile) else {
                bail!(
                    "lease {}: tile {} is not in the plan",
                    lease.lease_id,
                    unit.tile
                );
            };
            if unit_ms > 0 {
                // Rendering: the worker has no request at the coordinator meanwhile.
                tokio::time::sleep(Duration::from_millis(unit_ms)).await;
            }
            let values = 3 * unit.pass_count as usize * rect.pixel_count();
            let r = w
                .client
                .submit_result(v1::SubmitResultRequest {
                    worker_id: w.id,
                    lease_id: lease.lease_id,
                    unit: Some(unit),
                    width: rect.width,
                    height: rect.height,
                    pass_means: tessera_proto::means_to_bytes(&vec![0.5; values]),
                    render_seconds: 0.0,
                    job_id: lease.job_id,
                    rejected_samples: 0,
                    traced_pixel_passes: 0,
                    fence: lease.fence.clone(),
                    bias: Vec::new(),
                })
                .await?
                .into_inner();
            if r.accepted {
                merged.fetch_add(1, Ordering::Relaxed);
            }
        }
    }
    Ok(latency)
}

/// Peak resident set (`VmHWM`) of process `pid`, bytes; 0 where unavailable.
fn peak_rss(pid: &str) -> u64 {
    std::fs::read_to_string(format!("/proc/{pid}/status"))
        .ok()
        .and_then(|s| {
            s.lines()
                .find_map(|l| l.strip_prefix("VmHWM:"))
                .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
        })
        .map_or(0, |kb| kb * 1024)
}

/// Starts `tessera coordinator` on port-0 listeners and reads its URLs.
fn start_coordinator(exe: &Path, data: &Path) -> Result<(Child, String, String)> {
    let mut child = Command::new(exe)
        .args([
            "coordinator",
            "--http",
            "127.0.0.1:0",
            "--grpc",
            "127.0.0.1:0",
        ])
        .arg("--data")
        .arg(data)
        .stdout(Stdio::piped())
        .spawn()?;
    let stdout = child.stdout.take().context("coordinator stdout")?;
    let mut lines = std::io::BufReader::new(stdout).lines();
    let (mut http, mut grpc) = (None, None);
    for line in lines.by_ref() {
        let line = line?;
        if let Some(u) = line.strip_prefix("http: ") {
            http = Some(u.trim().trim_end_matches("/api/v1").to_string());
        }
        if let Some(u) = line.strip_prefix("grpc: ") {
            grpc = Some(u.trim().to_string());
        }
        if http.is_some() && grpc.is_some() {
            break;
        }
    }
    std::thread::spawn(move || for _ in lines {});
    match (http, grpc) {
        (Some(h), Some(g)) => Ok((child, h, g)),
        _ => {
            let _ = child.kill();
            bail!("tessera coordinator printed no http:/grpc: URLs")
        }
    }
}
