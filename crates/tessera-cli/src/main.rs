//! `tessera`: the one binary. `tessera render` renders a scene on this machine with the
//! same plan, per-unit rendering and canonical merge the farm uses; `tessera bench`
//! measures throughput.

mod accuracy;
mod adaptive;
mod bench_farm;
mod bench_fleet;
mod bench_plan;
mod common;
mod coordinator;
mod estimate;
mod render;
mod serve;
mod status;
mod store;
mod submit;
mod worker;

use anyhow::Result;
use clap::{Args, Parser, Subcommand};
use std::time::Instant;
use tessera_render::render::render_frame_counted;

use render::{prepare, JobArgs, RenderArgs, StopArgs};

#[derive(Parser)]
#[command(
    name = "tessera",
    version,
    about = "Tessera: a distributed Monte Carlo render farm"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Render a scene on this machine to an EXR or PNG file.
    Render(RenderArgs),
    /// Quote a job before rendering it: a short pilot on this machine predicts the seconds
    /// and worker-seconds to reach 10%, 5%, 2% and 1% error (or --target-error).
    Estimate(estimate::EstimateArgs),
    /// The pilot of a coordinator's dry run (internal): job settings as JSON on standard
    /// input, the quote as JSON on standard output.
    #[command(hide = true)]
    Pilot(estimate::PilotArgs),
    /// Measure rendering throughput (paths and rays per second).
    Bench(BenchArgs),
    /// Compare the render plan's configuration with the general one (and bdpt with path on
    /// the caustic scene): time to reach a target error, side by side.
    BenchPlan(bench_plan::BenchPlanArgs),
    /// The whole farm on this machine: a coordinator and local workers over loopback gRPC.
    Serve(serve::ServeArgs),
    /// Run a coordinator: HTTP API and dashboard, gRPC port for workers, SQLite store.
    Coordinator(coordinator::CoordinatorArgs),
    /// Run a worker that leases and renders work units from a coordinator.
    Worker(worker::WorkerArgs),
    /// Submit a job to a coordinator (optionally wait for it and download the image).
    Submit(submit::SubmitArgs),
    /// Show jobs of a coordinator.
    Status(status::StatusArgs),
    /// Check, back up and restore a coordinator's store (docs/store.md).
    Store(store::StoreArgs),
    /// Measure the farm's overhead: `tessera serve` against `tessera render`, side by side.
    BenchFarm(bench_farm::BenchFarmArgs),
    /// Drive a real coordinator with many simulated workers over gRPC: merged units per
    /// second, lease latency, coordinator CPU and memory per fleet size.
    BenchFleet(bench_fleet::BenchFleetArgs),
}

#[derive(Args)]
#[command(args_conflicts_with_subcommands = true)]
struct BenchArgs {
    /// `tessera bench accuracy ...`; without a subcommand, the throughput bench.
    #[command(subcommand)]
    what: Option<BenchCommand>,
    /// Scene to render.
    #[arg(default_value = "builtin:cornell-box")]
    scene: String,
    /// Image width.
    #[arg(long, default_value_t = 256)]
    width: u32,
    /// Image height.
    #[arg(long, default_value_t = 256)]
    height: u32,
    /// Samples per pixel.
    #[arg(long, default_value_t = 64)]
    spp: u32,
    /// Maximum path depth.
    #[arg(long, default_value_t = 8)]
    max_depth: u32,
    /// Worker threads (0 = all cores).
    #[arg(long, default_value_t = 0)]
    threads: usize,
    /// Timed repetitions (the median is reported).
    #[arg(long, default_value_t = 3)]
    repeat: u32,
}

#[derive(Subcommand)]
enum BenchCommand {
    /// What accuracy costs in time: error against a reference for a ladder of budgets per
    /// configuration (CSV, SVG, Markdown), and Veach & Guibas 1995 figure 5.
    Accuracy(accuracy::AccuracyArgs),
}

fn main() {
    let cli = Cli::parse();
    // The commands that trace rays check `TESSERA_ISA` (the traversal kernel,
    // docs/ARCHITECTURE.md §2) before anything else: a kernel this CPU lacks, or a name
    // that is none, is refused with the reason, never silently replaced.
    let traces = !matches!(
        cli.command,
        Command::Submit(_) | Command::Status(_) | Command::Store(_) | Command::Coordinator(_)
    );
    if traces {
        if let Err(e) = tessera_render::geometry::Isa::from_env() {
            eprintln!("error: {e}");
            std::process::exit(1);
        }
    }
    let result = match cli.command {
        Command::Render(args) => contained("rendering", || render::render(args)),
        Command::Bench(mut args) => match args.what.take() {
            Some(BenchCommand::Accuracy(a)) => accuracy::bench_accuracy(a),
            None => bench(args),
        },
        Command::Estimate(args) => contained("estimating", || estimate::estimate(args)),
        Command::Pilot(args) => contained("piloting", || estimate::pilot(args)),
        Command::BenchPlan(args) => bench_plan::bench_plan(args),
        Command::Serve(args) => serve::serve(args),
        Command::Coordinator(args) => coordinator::coordinator(args),
        Command::Worker(args) => worker::worker(args),
        Command::Submit(args) => submit::submit(args),
        Command::Status(args) => status::status(args),
        Command::Store(args) => store::store(args),
        Command::BenchFarm(args) => bench_farm::bench_farm(args),
        Command::BenchFleet(args) => bench_fleet::bench_fleet(args),
    };
    if let Err(e) = result {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

/// Runs `f`, turning a panic into an error, so that no scene file makes `tessera render`
/// exit with a panic (code 101): scene import and validation return errors, and a panic
/// past them (building the BVH, tracing) is a bug reported as one, with exit code 1. The
/// default panic hook has already printed the location by then.
fn contained(what: &str, f: impl FnOnce() -> Result<()>) -> Result<()> {
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)) {
        Ok(r) => r,
        Err(payload) => {
            let message = payload
                .downcast_ref::<&str>()
                .map(|s| (*s).to_string())
                .or_else(|| payload.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "a panic without a message".into());
            Err(anyhow::anyhow!(
                "{what} panicked: {message} (a bug in Tessera: please report it with the scene)"
            ))
        }
    }
}

fn bench(args: BenchArgs) -> Result<()> {
    let job = JobArgs {
        spp: args.spp,
        width: Some(args.width),
        height: Some(args.height),
        integrator: "path".into(),
        max_depth: Some(args.max_depth),
        ..JobArgs::new(&args.scene)
    };
    let p = prepare(&job, &StopArgs::default(), 0)?;
    let plan = p.resolved.plan;
    // An explicit integrator never takes the black shortcut.
    let render_scene = p.render_scene.as_ref().expect("built unless black");
    let threads = if args.threads == 0 {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    } else {
        args.threads
    };
    let paths = plan.width as f64 * plan.height as f64 * plan.spp() as f64;
    let mut rates = Vec::new();
    let mut rays = 0;
    for i in 0..args.repeat.max(1) {
        let start = Instant::now();
        let rendered = render_frame_counted(
            render_scene,
            &p.resolved.config,
            &plan,
            0,
            args.threads,
            |_, _| {},
        );
        let s = start.elapsed().as_secs_f64();
        rates.push(paths / s);
        // The same every run: the render is deterministic.
        rays = rendered.rays;
        println!(
            "run {}: {:.3} s, {:.0} paths/s, {:.0} rays/s, estimated error {:.4}",
            i + 1,
            s,
            paths / s,
            rays as f64 / s,
            rendered.accumulator.image_error()
        );
    }
    rates.sort_by(f64::total_cmp);
    let median = rates[rates.len() / 2];
    // Paths per second depends on the path length; rays per second (closest hits and
    // shadow rays) much less so.
    let rays_per_path = rays as f64 / paths;
    println!(
        "bench {} {}x{} {} spp max-depth {} on {} threads: median {:.0} paths/s ({:.0} paths/s per thread), {:.0} rays/s ({:.2} rays per path)",
        args.scene,
        args.width,
        args.height,
        plan.spp(),
        args.max_depth,
        threads,
        median,
        median / threads as f64,
        median * rays_per_path,
        rays_per_path
    );
    Ok(())
}
