//! `tessera`: the one binary. `tessera render` renders a scene on this machine with the
//! same plan, per-unit rendering and canonical merge the farm uses; `tessera bench`
//! measures throughput.

use anyhow::{bail, Context, Result};
use clap::{Args, Parser, Subcommand};
use std::io::IsTerminal;
use std::path::PathBuf;
use std::time::Instant;
use tessera_farm::FramePlan;
use tessera_render::integrator::{IntegratorKind, MisHeuristic};
use tessera_render::render::{render_frame, RenderSettings};
use tessera_render::sampling::SamplerKind;
use tessera_render::scene::RenderScene;

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
    /// auto, path or direct.
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
    /// Maximum path depth (number of bounces).
    #[arg(long, default_value_t = 16)]
    max_depth: u32,
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
}

#[derive(Args)]
struct BenchArgs {
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

fn main() {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Render(args) => render(args),
        Command::Bench(args) => bench(args),
    };
    if let Err(e) = result {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

/// A validated job: the scene, its render scene, the plan and the settings.
struct Prepared {
    scene: tessera_scene::Scene,
    render_scene: RenderScene,
    plan: FramePlan,
    settings: RenderSettings,
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
    let plan = FramePlan::for_spp(width, height, job.spp, job.tile_size)
        .context("invalid image or sampling settings")?;
    let integrator = match job.integrator.as_str() {
        // The scene-analysis plan will refine this; for now every scene gets the path tracer.
        "auto" => IntegratorKind::Path,
        other => other
            .parse::<IntegratorKind>()
            .map_err(anyhow::Error::msg)?,
    };
    if job.max_depth == 0 || job.max_depth > 1024 {
        bail!("--max-depth {} must be between 1 and 1024", job.max_depth);
    }
    let settings = RenderSettings {
        integrator,
        mis: job.mis,
        sampler: job.sampler,
        seed: job.seed,
        max_depth: job.max_depth,
        rr_depth: 3,
    };
    let render_scene = RenderScene::build(&scene, width, height)?;
    Ok(Prepared {
        scene,
        render_scene,
        plan,
        settings,
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
    let p = prepare(&args.job)?;
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
    let acc = render_frame(
        &p.render_scene,
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
    Ok(())
}

/// The render settings as one JSON object for the EXR header (stable key order).
fn metadata_json(p: &Prepared) -> String {
    format!(
        "{{\"scene\":{:?},\"width\":{},\"height\":{},\"spp\":{},\"samples_per_pass\":{},\"passes\":{},\"integrator\":\"{}\",\"mis\":\"{}\",\"sampler\":\"{}\",\"seed\":{},\"max_depth\":{}}}",
        p.scene.name,
        p.plan.width,
        p.plan.height,
        p.plan.spp(),
        p.plan.samples_per_pass,
        p.plan.passes,
        p.settings.integrator,
        p.settings.mis,
        p.settings.sampler.as_str(),
        p.settings.seed,
        p.settings.max_depth
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
        max_depth: args.max_depth,
        tile_size: 32,
    };
    let p = prepare(&job)?;
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
            &p.render_scene,
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
