//! The farm commands: `tessera coordinator`, `tessera worker`, `tessera serve`,
//! `tessera submit` and `tessera status`.

use anyhow::{bail, Context, Result};
use clap::Args;
use std::io::{BufRead, Write};
use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;
use tessera_api::client::{Client, ClientError};
use tessera_api::{FrameRange, JobSettings, JobState, JobStatus};
use tessera_coordinator::service::{Coordinator, CoordinatorConfig};

use crate::render::{JobArgs, StopArgs};

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

/// `tessera worker`.
#[derive(Args, Clone, Debug)]
pub struct WorkerArgs {
    /// The coordinator's gRPC URL.
    #[arg(long, default_value = "http://127.0.0.1:50051")]
    pub coordinator: String,
    /// Rendering threads (0 = all cores).
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
    /// Name shown in the worker list (default: host name and process id).
    #[arg(long)]
    pub name: Option<String>,
    /// Bearer token of the coordinator's worker port.
    #[arg(long, env = "TESSERA_WORKER_TOKEN")]
    pub token: Option<String>,
    /// Exit when standard input closes (used by `tessera serve` for its local workers, so
    /// they never outlive it).
    #[arg(long, hide = true)]
    pub exit_with_stdin: bool,
}

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
}

/// Job options of `tessera submit` (the same meaning as `tessera render`'s).
#[derive(Args, Clone, Debug)]
pub struct SubmitArgs {
    /// The job, with the same flags as `tessera render` (SCENE is builtin:NAME, or a
    /// .gltf/.glb file, uploaded first).
    #[command(flatten)]
    pub job: JobArgs,
    /// When the job stops before its budget, as with `tessera render`.
    #[command(flatten)]
    pub stop: StopArgs,
    /// The coordinator's HTTP URL.
    #[arg(long, default_value = "http://127.0.0.1:8080", env = "TESSERA_SERVER")]
    pub server: String,
    /// API bearer token.
    #[arg(long, env = "TESSERA_API_TOKEN")]
    pub token: Option<String>,
    /// First frame.
    #[arg(long, default_value_t = 0)]
    pub frame_start: u32,
    /// Last frame (inclusive; default the first).
    #[arg(long)]
    pub frame_end: Option<u32>,
    /// Higher runs first.
    #[arg(long, default_value_t = 0)]
    pub priority: i32,
    /// A name for the job.
    #[arg(long)]
    pub name: Option<String>,
    /// Idempotency key: a retried submission with the same key returns the same job.
    #[arg(long)]
    pub idempotency_key: Option<String>,
    /// Wait until the job is done, showing progress.
    #[arg(long)]
    pub wait: bool,
    /// With --wait: write the final image here (.exr or .png).
    #[arg(short, long)]
    pub output: Option<PathBuf>,
    /// With --wait: give up after this many seconds.
    #[arg(long, default_value_t = 86_400.0)]
    pub wait_timeout: f64,
}

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
    /// Print the JSON the API returned.
    #[arg(long)]
    pub json: bool,
    /// How many jobs to list.
    #[arg(long, default_value_t = 20)]
    pub limit: u32,
}

fn init_tracing() {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn"));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .try_init();
}

fn runtime() -> Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("starting the async runtime")
}

async fn shutdown_signal() {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{signal, SignalKind};
        match signal(SignalKind::terminate()) {
            Ok(mut term) => {
                tokio::select! {
                    _ = term.recv() => {}
                    _ = tokio::signal::ctrl_c() => {}
                }
            }
            Err(_) => {
                let _ = tokio::signal::ctrl_c().await;
            }
        }
    }
    #[cfg(not(unix))]
    {
        let _ = tokio::signal::ctrl_c().await;
    }
}

/// A running coordinator: both listeners bound, their real addresses known.
struct Running {
    http: SocketAddr,
    grpc: SocketAddr,
    core: Coordinator,
    tasks: Vec<tokio::task::JoinHandle<()>>,
}

async fn start_coordinator(args: &CoordinatorArgs) -> Result<Running> {
    if args.lease_ms < 100 || u64::from(args.heartbeat_ms) * 2 > args.lease_ms {
        bail!(
            "--lease-ms {} must be at least 100 and at least twice --heartbeat-ms {}",
            args.lease_ms,
            args.heartbeat_ms
        );
    }
    let cfg = CoordinatorConfig {
        data_dir: args.data.clone(),
        api_token: args.api_token.clone().filter(|t| !t.is_empty()),
        worker_token: args.worker_token.clone().filter(|t| !t.is_empty()),
        lease_ms: args.lease_ms,
        heartbeat_ms: args.heartbeat_ms,
        grace_ms: args.grace_ms,
        passes_per_unit: 1,
    };
    let core = Coordinator::open(cfg)
        .await
        .with_context(|| format!("opening the store in {}", args.data.display()))?;
    let http = tokio::net::TcpListener::bind(args.http)
        .await
        .with_context(|| format!("binding the HTTP port {}", args.http))?;
    let grpc = tokio::net::TcpListener::bind(args.grpc)
        .await
        .with_context(|| format!("binding the gRPC port {}", args.grpc))?;
    let (http_addr, grpc_addr) = (http.local_addr()?, grpc.local_addr()?);
    let app = tessera_coordinator::http::router(core.clone());
    let mut tasks = vec![core.spawn_ticker()];
    tasks.push(tokio::spawn(async move {
        if let Err(e) = axum::serve(http, app).await {
            tracing::error!(error = %e, "HTTP server failed");
        }
    }));
    let svc = tessera_coordinator::grpc::WorkerGrpc::for_coordinator(core.clone()).into_server();
    tasks.push(tokio::spawn(async move {
        if let Err(e) = tonic::transport::Server::builder()
            .add_service(svc)
            // TCP_NODELAY: results and leases are small request/response exchanges, and
            // Nagle's algorithm with delayed ACKs would stall each by tens of milliseconds.
            .serve_with_incoming(
                tonic::transport::server::TcpIncoming::from(grpc).with_nodelay(Some(true)),
            )
            .await
        {
            tracing::error!(error = %e, "gRPC server failed");
        }
    }));
    Ok(Running {
        http: http_addr,
        grpc: grpc_addr,
        core,
        tasks,
    })
}

fn print_addresses(r: &Running) {
    println!("http: http://{}/api/v1", r.http);
    println!("grpc: http://{}", r.grpc);
    println!("dashboard: http://{}/", r.http);
    let _ = std::io::stdout().flush();
}

/// `tessera coordinator`.
pub fn coordinator(args: CoordinatorArgs) -> Result<()> {
    init_tracing();
    runtime()?.block_on(async {
        let r = start_coordinator(&args).await?;
        print_addresses(&r);
        shutdown_signal().await;
        for t in &r.tasks {
            t.abort();
        }
        r.core.store().close().await;
        Ok(())
    })
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
    let config = tessera_worker::WorkerConfig {
        coordinator: args.coordinator.clone(),
        threads,
        name,
        token: args.token.clone().filter(|t| !t.is_empty()),
    };
    let exit_with_stdin = args.exit_with_stdin;
    runtime()?.block_on(async move {
        let stop = async move {
            if exit_with_stdin {
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
            } else {
                shutdown_signal().await;
            }
        };
        tessera_worker::run(config, stop)
            .await
            .map_err(anyhow::Error::from)
    })
}

/// `tessera serve`: a coordinator and local worker processes over loopback gRPC.
pub fn serve(args: ServeArgs) -> Result<()> {
    init_tracing();
    if args.workers > 256 {
        bail!("--workers {} must be at most 256", args.workers);
    }
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let threads = if args.threads_per_worker == 0 {
        (cores / args.workers.max(1)).max(1)
    } else {
        args.threads_per_worker
    };
    runtime()?.block_on(async move {
        let r = start_coordinator(&args.coordinator).await?;
        let exe = std::env::current_exe().context("locating the tessera binary")?;
        let mut children = Vec::new();
        for i in 0..args.workers {
            let mut cmd = std::process::Command::new(&exe);
            cmd.arg("worker")
                .arg("--coordinator")
                .arg(format!("http://{}", r.grpc))
                .arg("--threads")
                .arg(threads.to_string())
                .arg("--name")
                .arg(format!("local-{}", i + 1))
                .arg("--exit-with-stdin")
                .stdin(std::process::Stdio::piped());
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
        if args.demo != "none" {
            let empty = r
                .core
                .list(tessera_api::JobListQuery {
                    limit: Some(1),
                    ..Default::default()
                })
                .await
                .map(|l| l.jobs.is_empty())
                .unwrap_or(false);
            if empty {
                let mut s = JobSettings::new(args.demo.clone());
                s.name = Some("demo".into());
                match r.core.submit(s, Some("tessera-serve-demo".into())).await {
                    Ok((job, _)) => println!("submitted demo job {} ({})", job.id, args.demo),
                    Err(e) => eprintln!("demo job not submitted: {e}"),
                }
            }
        }
        print_addresses(&r);
        println!(
            "{} local worker(s) with {threads} thread(s) each; Ctrl-C stops the farm",
            args.workers
        );
        let _ = std::io::stdout().flush();
        shutdown_signal().await;
        // Closing their stdin asks the workers to finish and exit.
        for c in &mut children {
            drop(c.stdin.take());
        }
        for mut c in children {
            let deadline = std::time::Instant::now() + Duration::from_secs(10);
            loop {
                match c.try_wait() {
                    Ok(Some(_)) => break,
                    Ok(None) if std::time::Instant::now() < deadline => {
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
        for t in &r.tasks {
            t.abort();
        }
        r.core.store().close().await;
        Ok(())
    })
}

fn client_error(e: ClientError) -> anyhow::Error {
    match e {
        ClientError::Api { status, error } => {
            anyhow::anyhow!("the coordinator refused the request ({status}): {error}")
        }
        ClientError::Transport(m) => anyhow::anyhow!("{m}"),
    }
}

fn progress_line(s: &JobStatus) -> String {
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

/// `tessera submit`.
pub fn submit(args: SubmitArgs) -> Result<()> {
    let client = Client::new(&args.server, args.token.clone());
    let scene = if args.job.scene.starts_with("builtin:") {
        args.job.scene.clone()
    } else {
        let path = PathBuf::from(&args.job.scene);
        let bytes = std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?;
        let up = client.upload_scene(&bytes).map_err(client_error)?;
        println!(
            "uploaded {} ({} bytes, {} triangles): {}",
            path.display(),
            up.bytes,
            up.triangles,
            up.hash
        );
        up.hash
    };
    let mut s = args.job.settings(scene, &args.stop);
    s.frames = FrameRange {
        start: args.frame_start,
        end: args.frame_end.unwrap_or(args.frame_start),
    };
    s.priority = args.priority;
    s.name = args.name.clone();
    if let Some(out) = &args.output {
        if !args.wait {
            bail!("-o/--output needs --wait");
        }
        let ext = out.extension().and_then(|e| e.to_str()).unwrap_or("");
        if !matches!(ext, "exr" | "png") {
            bail!("output {} must end in .exr or .png", out.display());
        }
    }
    let job = client
        .submit(&s, args.idempotency_key.as_deref())
        .map_err(client_error)?;
    println!("job {} {}", job.id, job.state.as_str());
    if !args.wait {
        return Ok(());
    }
    let mut last = String::new();
    let done = client
        .wait(
            job.id,
            Duration::from_millis(500),
            Duration::from_secs_f64(args.wait_timeout.max(1.0)),
            |st| {
                let line = progress_line(st);
                if line != last {
                    eprintln!("{line}");
                    last = line;
                }
            },
        )
        .map_err(client_error)?;
    println!("{}", progress_line(&done));
    if done.state != JobState::Done {
        bail!(
            "job {} ended {}{}",
            done.id,
            done.state.as_str(),
            done.error
                .as_deref()
                .map(|e| format!(": {e}"))
                .unwrap_or_default()
        );
    }
    if let Some(out) = &args.output {
        let format = if out.extension().and_then(|e| e.to_str()) == Some("exr") {
            "exr"
        } else {
            "png"
        };
        let bytes = client.image(done.id, format).map_err(client_error)?;
        std::fs::write(out, &bytes).with_context(|| format!("writing {}", out.display()))?;
        println!("wrote {}", out.display());
    }
    Ok(())
}

/// `tessera status`.
pub fn status(args: StatusArgs) -> Result<()> {
    let client = Client::new(&args.server, args.token.clone());
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
        // Local render.
        let out = dir.join("local.exr");
        let t = std::time::Instant::now();
        let o = std::process::Command::new(&exe)
            .arg("render")
            .arg(&args.scene)
            .args(["--width", &args.width.to_string()])
            .args(["--height", &args.height.to_string()])
            .args(["--spp", &args.spp.to_string()])
            .args(["--threads", &args.threads.to_string()])
            .arg("-o")
            .arg(&out)
            .output()?;
        if !o.status.success() {
            bail!(
                "tessera render failed: {}",
                String::from_utf8_lossy(&o.stderr)
            );
        }
        let l = t.elapsed().as_secs_f64();
        // The farm.
        let data = dir.join(format!("data{rep}"));
        let _ = std::fs::remove_dir_all(&data);
        let mut child = std::process::Command::new(&exe)
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
            .arg(&data)
            .stdout(std::process::Stdio::piped())
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
        let client = Client::new(&url, None);
        // Wait until the workers registered, so their start-up is not timed.
        let start = std::time::Instant::now();
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
        let t = std::time::Instant::now();
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
