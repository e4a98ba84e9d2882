//! `tessera`: the one binary. `tessera render` renders a scene on this machine with the
//! same plan, per-unit rendering and canonical merge the farm uses; `tessera bench`
//! measures throughput.

mod accuracy;
mod adaptive;
mod bench_plan;

use anyhow::{bail, Context, Result};
use clap::{Args, Parser, Subcommand};
use std::io::IsTerminal;
use std::path::PathBuf;
use std::time::Instant;
use tessera_farm::{FrameImage, FramePlan};
use tessera_render::integrator::{IntegratorKind, MisHeuristic};
use tessera_render::render::{render_frame, render_frame_counted, RenderSettings};
use tessera_render::sampling::SamplerKind;
use tessera_render::scene::RenderScene;
use tessera_scene::analysis::{analyse, PlannedIntegrator, RenderPlan};

mod farm;

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
    /// Measure rendering throughput (paths per second).
    Bench(BenchArgs),
    /// Compare the render plan's configuration with the general one (and bdpt with path on
    /// the caustic scene): time to reach a target error, side by side.
    BenchPlan(bench_plan::BenchPlanArgs),
    /// The whole farm on this machine: a coordinator and local workers over loopback gRPC.
    Serve(farm::ServeArgs),
    /// Run a coordinator: HTTP API and dashboard, gRPC port for workers, SQLite store.
    Coordinator(farm::CoordinatorArgs),
    /// Run a worker that leases and renders work units from a coordinator.
    Worker(farm::WorkerArgs),
    /// Submit a job to a coordinator (optionally wait for it and download the image).
    Submit(farm::SubmitArgs),
    /// Show jobs of a coordinator.
    Status(farm::StatusArgs),
    /// Measure the farm's overhead: `tessera serve` against `tessera render`, side by side.
    BenchFarm(farm::BenchFarmArgs),
}

#[derive(Args, Clone)]
struct JobArgs {
    /// A .gltf/.glb file or builtin:NAME (cornell-box, veach-mis, furnace, caustic).
    scene: String,
    /// glTF camera to render from (by camera or node name).
    #[arg(long)]
    camera: Option<String>,
    /// Samples per pixel (rounded up to whole passes).
    #[arg(long, default_value_t = 64)]
    spp: u32,
    /// Image width (default: the scene's).
    #[arg(long)]
    width: Option<u32>,
    /// Image height (default: the scene's).
    #[arg(long)]
    height: Option<u32>,
    /// auto (follow the scene's render plan), path, direct or bdpt. An explicit integrator
    /// overrides the plan and renders with the general configuration (max depth 16 unless
    /// --max-depth is given).
    #[arg(long, default_value = "auto")]
    integrator: String,
    /// MIS heuristic: balance, power, cutoff[:ALPHA] or maximum.
    #[arg(long, default_value = "power")]
    mis: MisHeuristic,
    /// Sampler: sobol (randomized QMC) or independent.
    #[arg(long, default_value = "sobol")]
    sampler: SamplerKind,
    /// Job seed.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Worker threads (0 = all cores). The image does not depend on it.
    #[arg(long, default_value_t = 0)]
    threads: usize,
    /// Maximum path depth (number of bounces). Default: the render plan's with
    /// --integrator auto, 16 otherwise.
    #[arg(long)]
    max_depth: Option<u32>,
    /// Tile edge in pixels.
    #[arg(long, default_value_t = 32)]
    tile_size: u32,
}

#[derive(Args)]
struct RenderArgs {
    #[command(flatten)]
    job: JobArgs,
    /// Output file: .exr (multi-layer float) or .png (sRGB).
    #[arg(short, long)]
    output: PathBuf,
    #[command(flatten)]
    adaptive: adaptive::AdaptiveArgs,
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
    let result = match cli.command {
        Command::Render(args) => render(args),
        Command::Bench(mut args) => match args.what.take() {
            Some(BenchCommand::Accuracy(a)) => accuracy::bench_accuracy(a),
            None => bench(args),
        },
        Command::BenchPlan(args) => bench_plan::bench_plan(args),
        Command::Serve(args) => farm::serve(args),
        Command::Coordinator(args) => farm::coordinator(args),
        Command::Worker(args) => farm::worker(args),
        Command::Submit(args) => farm::submit(args),
        Command::Status(args) => farm::status(args),
        Command::BenchFarm(args) => farm::bench_farm(args),
    };
    if let Err(e) = result {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

/// Maximum path depth of the general configuration (an explicit `--integrator`).
const GENERAL_MAX_DEPTH: u32 = 16;
/// Russian roulette start depth of the general configuration.
const GENERAL_RR_DEPTH: u32 = 3;

/// A validated job: the scene, its render scene, the plan and the settings.
struct Prepared {
    scene: tessera_scene::Scene,
    /// The renderable scene; not built for a black render.
    render_scene: Option<RenderScene>,
    plan: FramePlan,
    settings: RenderSettings,
    /// The scene analysis (DESIGN §4), with `overridden` set if the user forced settings.
    render_plan: RenderPlan,
    /// Render an all-black image without tracing a ray (the plan found no light).
    black: bool,
    /// How this build follows the plan, when it cannot do so exactly (bdpt fallback).
    notes: Vec<String>,
}

fn prepare(job: &JobArgs) -> Result<Prepared> {
    let scene = tessera_scene::load_with_camera(&job.scene, job.camera.as_deref())
        .with_context(|| format!("loading scene {}", job.scene))?;
    let (dw, dh) = scene.default_resolution;
    let (width, height) = match (job.width, job.height) {
        (Some(w), Some(h)) => (w, h),
        (Some(w), None) => (w, ((w as u64 * dh as u64) / dw as u64).max(1) as u32),
        (None, Some(h)) => (((h as u64 * dw as u64) / dh as u64).max(1) as u32, h),
        (None, None) => (dw, dh),
    };
    if job.spp == 0 {
        bail!("--spp must be at least 1");
    }
    if job.threads > 4096 {
        bail!(
            "--threads {} must be at most 4096 (0 = all cores)",
            job.threads
        );
    }
    if let Some(d) = job.max_depth {
        if d == 0 || d > 1024 {
            bail!("--max-depth {d} must be between 1 and 1024");
        }
    }
    // Analyse the scene (DESIGN §4); `auto` follows the plan, anything else overrides it.
    let mut render_plan = analyse(&scene);
    let notes = Vec::new();
    let mut black = false;
    let mut forced = Vec::new();
    let (integrator, plan_depth, rr_depth) = match job.integrator.as_str() {
        "auto" => match render_plan.integrator {
            PlannedIntegrator::Black => {
                black = true;
                // Nothing is traced; these settings only fill the metadata.
                (IntegratorKind::Direct, 1, render_plan.rr_depth)
            }
            PlannedIntegrator::Direct => (IntegratorKind::Direct, 1, render_plan.rr_depth),
            PlannedIntegrator::Path => (
                IntegratorKind::Path,
                render_plan.max_depth,
                render_plan.rr_depth,
            ),
            PlannedIntegrator::Bdpt => (
                IntegratorKind::Bdpt,
                render_plan.max_depth,
                render_plan.rr_depth,
            ),
        },
        other => {
            let kind = other
                .parse::<IntegratorKind>()
                .map_err(anyhow::Error::msg)?;
            forced.push(format!("--integrator {other}"));
            (kind, GENERAL_MAX_DEPTH, GENERAL_RR_DEPTH)
        }
    };
    if let Some(d) = job.max_depth {
        if d != plan_depth {
            forced.push(format!("--max-depth {d}"));
        }
    }
    if !forced.is_empty() {
        render_plan.set_override(&forced.join(" "));
    }
    // bdpt splats light tracing anywhere on the film: one whole-frame tile keeps every
    // splat in the unit being rendered (see tessera_render::integrator::bdpt).
    let plan = if integrator == IntegratorKind::Bdpt {
        FramePlan::whole_frame(width, height, job.spp)
    } else {
        FramePlan::for_spp(width, height, job.spp, job.tile_size)
    }
    .context("invalid image or sampling settings")?;
    let settings = RenderSettings {
        integrator,
        mis: job.mis,
        sampler: job.sampler,
        seed: job.seed,
        max_depth: job.max_depth.unwrap_or(plan_depth),
        rr_depth,
    };
    let render_scene = if black {
        None
    } else {
        Some(RenderScene::build(&scene, width, height)?)
    };
    Ok(Prepared {
        scene,
        render_scene,
        plan,
        settings,
        render_plan,
        black,
        notes,
    })
}

fn render(args: RenderArgs) -> Result<()> {
    let ext = args
        .output
        .extension()
        .and_then(|e| e.to_str())
        .map(|e| e.to_ascii_lowercase());
    if !matches!(ext.as_deref(), Some("exr") | Some("png")) {
        bail!("output {} must end in .exr or .png", args.output.display());
    }
    adaptive::check(&args.adaptive)?;
    let mut p = prepare(&args.job)?;
    print!("{}", p.render_plan.summary());
    for note in &p.notes {
        println!("note: {note}");
    }
    if p.black {
        let start = Instant::now();
        let image = FrameImage::black(&p.plan);
        tessera_image::write_image(&args.output, &image, Some(&metadata_json(&p)))?;
        let seconds = start.elapsed().as_secs_f64();
        println!(
            "rendered {} ({}x{}, black: the render plan found no light, no ray traced) to {}",
            p.scene.name,
            p.plan.width,
            p.plan.height,
            args.output.display()
        );
        println!(
            "samples per pixel: {} ({} passes of {})",
            p.plan.spp(),
            p.plan.passes,
            p.plan.samples_per_pass
        );
        println!("seconds: {seconds:.3}");
        println!("estimated relative error: {:.4}", 0.0);
        println!("paths per second: 0");
        if let Some(map) = &args.adaptive.spp_map {
            adaptive::write_spp_map(map, &image)?;
        }
        return Ok(());
    }
    if args.adaptive.active() {
        return adaptive::render(&mut p, &args);
    }
    let bar = if std::io::stderr().is_terminal() {
        let bar = indicatif::ProgressBar::new(p.plan.unit_count(1));
        bar.set_style(
            indicatif::ProgressStyle::with_template(
                "{elapsed_precise} [{bar:40}] {pos}/{len} units, eta {eta}",
            )
            .expect("static template")
            .progress_chars("=> "),
        );
        Some(bar)
    } else {
        None
    };
    let start = Instant::now();
    let render_scene = p.render_scene.as_ref().expect("built unless black");
    let rendered = render_frame_counted(
        render_scene,
        &p.settings,
        &p.plan,
        0,
        args.job.threads,
        |done, _| {
            if let Some(b) = &bar {
                b.set_position(done as u64);
            }
        },
    );
    let acc = rendered.accumulator;
    let seconds = start.elapsed().as_secs_f64();
    if let Some(b) = bar {
        b.finish_and_clear();
    }
    let image = acc.image();
    tessera_image::write_image(&args.output, &image, Some(&metadata_json(&p)))?;
    let paths = p.plan.width as f64 * p.plan.height as f64 * p.plan.spp() as f64;
    println!(
        "rendered {} ({}x{}, {} integrator, {} sampler, {} MIS) to {}",
        p.scene.name,
        p.plan.width,
        p.plan.height,
        p.settings.integrator,
        p.settings.sampler.as_str(),
        p.settings.mis,
        args.output.display()
    );
    println!(
        "samples per pixel: {} ({} passes of {})",
        p.plan.spp(),
        p.plan.passes,
        p.plan.samples_per_pass
    );
    println!("seconds: {seconds:.3}");
    println!("estimated relative error: {:.4}", acc.image_error());
    println!("paths per second: {:.0}", paths / seconds);
    print_rejected_samples(rendered.rejected_samples);
    if let Some(map) = &args.adaptive.spp_map {
        adaptive::write_spp_map(map, &image)?;
    }
    Ok(())
}

/// The summary line for samples the integrator dropped as invalid; nothing when there
/// were none (a healthy render).
fn print_rejected_samples(n: u64) {
    if n > 0 {
        println!(
            "rejected samples: {n} (NaN, infinite or negative radiance, counted as black: a renderer bug)"
        );
    }
}

/// The render settings and the render plan as one JSON object for the EXR header (stable
/// key order). A black render (no light) has integrator "black".
fn metadata_json(p: &Prepared) -> String {
    let integrator = if p.black {
        "black".to_string()
    } else {
        p.settings.integrator.to_string()
    };
    format!(
        "{{\"scene\":{:?},\"width\":{},\"height\":{},\"spp\":{},\"samples_per_pass\":{},\"passes\":{},\"integrator\":\"{}\",\"mis\":\"{}\",\"sampler\":\"{}\",\"seed\":{},\"max_depth\":{},\"rr_depth\":{},\"plan\":{}}}",
        p.scene.name,
        p.plan.width,
        p.plan.height,
        p.plan.spp(),
        p.plan.samples_per_pass,
        p.plan.passes,
        integrator,
        p.settings.mis,
        p.settings.sampler.as_str(),
        p.settings.seed,
        p.settings.max_depth,
        p.settings.rr_depth,
        p.render_plan.to_json()
    )
}

fn bench(args: BenchArgs) -> Result<()> {
    let job = JobArgs {
        scene: args.scene.clone(),
        camera: None,
        spp: args.spp,
        width: Some(args.width),
        height: Some(args.height),
        integrator: "path".into(),
        mis: MisHeuristic::Power,
        sampler: SamplerKind::Sobol,
        seed: 0,
        threads: args.threads,
        max_depth: Some(args.max_depth),
        tile_size: 32,
    };
    let p = prepare(&job)?;
    // An explicit integrator never takes the black shortcut.
    let render_scene = p.render_scene.as_ref().expect("built unless black");
    let threads = if args.threads == 0 {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    } else {
        args.threads
    };
    let paths = p.plan.width as f64 * p.plan.height as f64 * p.plan.spp() as f64;
    let mut rates = Vec::new();
    for i in 0..args.repeat.max(1) {
        let start = Instant::now();
        let acc = render_frame(
            render_scene,
            &p.settings,
            &p.plan,
            0,
            args.threads,
            |_, _| {},
        );
        let s = start.elapsed().as_secs_f64();
        rates.push(paths / s);
        println!(
            "run {}: {:.3} s, {:.0} paths/s, estimated error {:.4}",
            i + 1,
            s,
            paths / s,
            acc.image_error()
        );
    }
    rates.sort_by(f64::total_cmp);
    let median = rates[rates.len() / 2];
    println!(
        "bench {} {}x{} {} spp max-depth {} on {} threads: median {:.0} paths/s ({:.0} paths/s per thread)",
        args.scene,
        args.width,
        args.height,
        p.plan.spp(),
        args.max_depth,
        threads,
        median,
        median / threads as f64
    );
    Ok(())
}
