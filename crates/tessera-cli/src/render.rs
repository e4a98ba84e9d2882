//! `tessera render`: a job rendered on this machine. The flags become a
//! [`JobSettings`], validated and resolved against the scene exactly as the coordinator
//! does ([`tessera_scene::job::resolve_job`] with the in-process technique pilot,
//! [`tessera_render::pilot::verdict`]), and the EXR header is the resolved job's
//! [`ResolvedJob::metadata_json`], so a local render and a farm job with the same settings
//! write byte-identical files (docs/ARCHITECTURE.md §2).

use anyhow::{anyhow, bail, Context, Result};
use clap::Args;
use sha2::{Digest, Sha256};
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::time::Instant;
use tessera_farm::job::{
    EnvironmentSettings, FrameRange, JobError, JobSettings, ResolvedJob, SceneRef, Shutter,
    StopVerdict, DEFAULT_FPS, DEFAULT_MIN_PASSES,
};
use tessera_farm::{FrameImage, FramePlan};
use tessera_render::render::render_frame_counted;
use tessera_render::scene::RenderScene;
use tessera_scene::environment::SceneEnvironment;
use tessera_scene::job::ResolveError;
use tessera_scene::{Scene, SceneTime};

use crate::adaptive;

/// The job flags shared by `tessera render` and the benches: one flag per
/// [`JobSettings`] field it renders with.
#[derive(Args, Clone, Debug)]
pub struct JobArgs {
    /// A .gltf/.glb file or builtin:NAME (cornell-box, veach-mis, furnace, caustic).
    pub scene: String,
    /// glTF camera to render from (by camera or node name).
    #[arg(long)]
    pub camera: Option<String>,
    /// Samples per pixel (rounded up to whole passes).
    #[arg(long, default_value_t = 64)]
    pub spp: u32,
    /// Image width (default: the scene's).
    #[arg(long)]
    pub width: Option<u32>,
    /// Image height (default: the scene's).
    #[arg(long)]
    pub height: Option<u32>,
    /// auto (follow the scene's render plan), path, direct, bdpt, vcm, ppm, mlt or mnee. An
    /// explicit integrator overrides the plan and renders with the general configuration
    /// (max depth 16 unless --max-depth is given).
    #[arg(long, default_value = "auto")]
    pub integrator: String,
    /// MIS heuristic: balance, power, cutoff (cutoff:ALPHA sets the threshold) or maximum.
    #[arg(long, default_value = "power")]
    pub mis: String,
    /// Sampler: sobol (randomized QMC) or independent.
    #[arg(long, default_value = "sobol")]
    pub sampler: String,
    /// Job seed.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Maximum path depth (number of bounces). Default: the render plan's with
    /// --integrator auto, 16 otherwise.
    #[arg(long)]
    pub max_depth: Option<u32>,
    /// Tile edge in pixels.
    #[arg(long, default_value_t = 32)]
    pub tile_size: u32,
    /// Frames per second: frame F shows the scene at t = F / fps seconds (glTF
    /// animations; Blender's exporter writes frame 1 at t = 1/24).
    #[arg(long, default_value_t = DEFAULT_FPS)]
    pub fps: f64,
    /// The glTF animation that plays, by name or index (default: every animation).
    #[arg(long)]
    pub animation: Option<String>,
    /// Motion blur: the shutter's opening and closing in frames relative to the frame,
    /// e.g. --shutter=-0.25,0.25 (default: none). Time is sampled only where the scene
    /// moves within it.
    #[arg(long, value_name = "OPEN,CLOSE", value_parser = parse_shutter, allow_hyphen_values = true)]
    pub shutter: Option<Shutter>,
    /// Light from every direction rays leave the scene in: an equirectangular HDR image
    /// (Radiance .hdr or OpenEXR, top row up) or a uniform radiance R,G,B in W/(m² sr),
    /// e.g. --environment 1,1,1. Default: none (the scene's own lights only).
    #[arg(long, value_name = "FILE|R,G,B")]
    pub environment: Option<String>,
    /// Factor on the environment's radiance.
    #[arg(long, default_value_t = 1.0)]
    pub environment_strength: f64,
    /// Rotation of the environment image about the up axis, degrees (counter-clockwise
    /// seen from above).
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub environment_rotation: f64,
}

/// `OPEN,CLOSE` in frames, for `--shutter` (the range is checked with the job).
fn parse_shutter(s: &str) -> Result<Shutter, String> {
    let (open, close) = s
        .split_once(',')
        .ok_or_else(|| format!("expected OPEN,CLOSE in frames, e.g. -0.25,0.25, got {s:?}"))?;
    let num = |v: &str| {
        v.trim()
            .parse::<f64>()
            .map_err(|_| format!("{v:?} is not a number of frames"))
    };
    Ok(Shutter {
        open: num(open)?,
        close: num(close)?,
    })
}

impl JobArgs {
    /// Flags for `scene` with every other setting at its default.
    pub fn new(scene: &str) -> Self {
        Self {
            scene: scene.to_string(),
            camera: None,
            spp: 64,
            width: None,
            height: None,
            integrator: "auto".into(),
            mis: "power".into(),
            sampler: "sobol".into(),
            seed: 0,
            max_depth: None,
            tile_size: 32,
            fps: DEFAULT_FPS,
            animation: None,
            shutter: None,
            environment: None,
            environment_strength: 1.0,
            environment_rotation: 0.0,
        }
    }
}

impl JobArgs {
    /// The job these flags describe, for the scene reference `scene` (`builtin:NAME` or
    /// the content hash of the file): the one mapping from flags to [`JobSettings`], used
    /// by `tessera render` and `tessera submit` alike.
    pub fn settings(&self, scene: String, stop: &StopArgs) -> JobSettings {
        let mut s = JobSettings::new(scene);
        s.camera = self.camera.clone();
        s.width = self.width;
        s.height = self.height;
        s.spp = self.spp;
        s.integrator = self.integrator.clone();
        s.mis = self.mis.clone();
        s.sampler = self.sampler.clone();
        s.seed = self.seed;
        s.max_depth = self.max_depth;
        s.tile_size = self.tile_size;
        s.fps = self.fps;
        s.animation = self.animation.clone();
        s.shutter = self.shutter;
        // The flag's text for now; [`environment_source`] puts a file's hash in its place.
        s.environment = self.environment.as_ref().map(|e| EnvironmentSettings {
            source: e.clone(),
            strength: self.environment_strength,
            rotation_degrees: self.environment_rotation,
        });
        s.target_error = stop.target_error;
        s.adaptive = stop.adaptive.clone();
        s.time_limit_seconds = stop.time_limit;
        s.min_passes = stop.min_passes;
        s
    }
}

/// When a job stops before its sample budget: the stopping fields of [`JobSettings`].
#[derive(Args, Clone, Debug)]
pub struct StopArgs {
    /// Target relative RMS error, e.g. 0.01. With --adaptive sequential or unbiased each
    /// pixel stops at it; with --adaptive off the whole image stops once its estimated
    /// error reaches it. --spp stays the upper bound.
    #[arg(long)]
    pub target_error: Option<f64>,
    /// Adaptive stopping: off, sequential (stop converged pixels at fixed pass boundaries;
    /// fast, slightly biased) or unbiased (a discarded pilot fixes each pixel's passes).
    #[arg(long, default_value = "off")]
    pub adaptive: String,
    /// Stop after this many seconds (checked between rounds; the image then depends on
    /// the machine's speed).
    #[arg(long)]
    pub time_limit: Option<f64>,
    /// Passes before the first adaptive decision (sequential) or of the pilot (unbiased).
    #[arg(long, default_value_t = DEFAULT_MIN_PASSES)]
    pub min_passes: u32,
}

impl Default for StopArgs {
    /// No stopping before the budget.
    fn default() -> Self {
        Self {
            target_error: None,
            adaptive: "off".into(),
            time_limit: None,
            min_passes: DEFAULT_MIN_PASSES,
        }
    }
}

/// `tessera render`'s arguments.
#[derive(Args)]
pub struct RenderArgs {
    #[command(flatten)]
    pub job: JobArgs,
    #[command(flatten)]
    pub stop: StopArgs,
    /// Worker threads (0 = all cores). The image does not depend on it.
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
    /// Output file: .exr (multi-layer float) or .png (sRGB).
    #[arg(short, long)]
    pub output: PathBuf,
    /// The frame to render: the scene at t = frame / fps seconds (times before the first
    /// keyframe clamp to it), with the frame's own sample seeds, as frame F of a farm job.
    #[arg(long, default_value_t = 0)]
    pub frame: u32,
    /// Also write the samples traced per pixel as a heat-map PNG (log scale).
    #[arg(long)]
    pub spp_map: Option<PathBuf>,
}

/// A resolved job with its scene, ready to render.
pub struct Prepared {
    /// The frame rendered.
    pub frame: u32,
    /// The scene as loaded, at the frame's time.
    pub scene: Scene,
    /// The renderable scene; not built for a black render.
    pub render_scene: Option<RenderScene>,
    /// The job resolved against the scene: settings, frame plan, render plan.
    pub resolved: ResolvedJob,
    /// Seconds spent building `render_scene` (acceleration structures, light tables).
    pub build_seconds: f64,
}

/// The [`SceneRef`] of a scene argument: `builtin:NAME` as it is; a file by the SHA-256 of
/// its bytes, the reference the farm gives the same file once uploaded.
fn scene_ref(arg: &str) -> Result<String> {
    if arg.starts_with("builtin:") {
        return Ok(arg.to_string());
    }
    // Streamed: the hash needs no copy of the file in memory (the loader bounds its size).
    let mut file = std::fs::File::open(arg).with_context(|| format!("reading scene {arg}"))?;
    let mut hasher = Sha256::new();
    std::io::copy(&mut file, &mut hasher).with_context(|| format!("reading scene {arg}"))?;
    Ok(hasher
        .finalize()
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect())
}

/// The command-line spelling of a [`JobSettings`] field, for error messages.
fn flag(field: &str) -> &'static str {
    match field {
        "scene" => "SCENE",
        "camera" => "--camera",
        "width" => "--width",
        "height" => "--height",
        "spp" => "--spp",
        "integrator" => "--integrator",
        "mis" => "--mis (MIS heuristic)",
        "sampler" => "--sampler",
        "max_depth" => "--max-depth",
        "target_error" => "--target-error",
        "adaptive" => "--adaptive",
        "min_passes" => "--min-passes",
        "time_limit_seconds" => "--time-limit",
        "tile_size" => "--tile-size",
        "fps" => "--fps",
        "animation" => "--animation",
        "shutter" => "--shutter",
        "environment.source" => "--environment",
        "environment.strength" => "--environment-strength",
        "environment.rotation_degrees" => "--environment-rotation",
        _ => "setting",
    }
}

/// A [`JobError`] in the command line's words: `invalid --spp: must be between ...`.
fn job_error(e: JobError, settings: &JobSettings) -> anyhow::Error {
    if e.field == "adaptive" {
        // The plan has too few passes for the mode: the budget is the remedy.
        return anyhow!(
            "invalid --adaptive {} with --spp {}: {}",
            settings.adaptive,
            settings.spp,
            e.problem
        );
    }
    anyhow!("invalid {}: {}", flag(&e.field), e.problem)
}

/// Validates and resolves `job` with the stopping settings `stop` exactly as the
/// coordinator does, loads its scene at the time of `frame` and builds it unless the plan
/// found no light.
///
/// The job is resolved against the scene at t = 0, as the coordinator resolves every job
/// (its render plan and resolution do not depend on the frame, so frame F of a farm job
/// and `tessera render --frame F` write the same header); the frame is then rendered from
/// the scene at `frame / fps`.
pub fn prepare(job: &JobArgs, stop: &StopArgs, frame: u32) -> Result<Prepared> {
    let mut settings = job.settings(scene_ref(&job.scene)?, stop);
    let image = environment_source(&mut settings)?;
    prepare_settings_with(
        settings,
        SceneSource::Path(&job.scene),
        image.as_deref(),
        frame,
    )
}

/// Whether `--environment`'s value is a colour `R,G,B` (three numbers) rather than a file.
fn is_colour(value: &str) -> bool {
    let parts: Vec<&str> = value.split(',').collect();
    parts.len() == 3 && parts.iter().all(|p| p.trim().parse::<f64>().is_ok())
}

/// Replaces an environment image's file name in `settings` by the SHA-256 of its bytes
/// (the reference the farm gives the same file once uploaded) and returns the bytes;
/// colours stay as they are.
pub fn environment_source(settings: &mut JobSettings) -> Result<Option<Vec<u8>>> {
    let Some(env) = &mut settings.environment else {
        return Ok(None);
    };
    if is_colour(&env.source) {
        return Ok(None);
    }
    let path = env.source.clone();
    let size = std::fs::metadata(&path)
        .with_context(|| format!("reading environment {path}"))?
        .len();
    if size > tessera_scene::MAX_INPUT_BYTES {
        bail!(
            "environment {path}: {size} bytes is larger than the limit of {} bytes",
            tessera_scene::MAX_INPUT_BYTES
        );
    }
    let bytes = std::fs::read(&path).with_context(|| format!("reading environment {path}"))?;
    env.source = Sha256::digest(&bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect();
    Ok(Some(bytes))
}

/// Where [`prepare_settings_with`] reads a scene that is not built in.
#[derive(Clone, Copy)]
pub enum SceneSource<'a> {
    /// A file named on the command line, which may refer to files beside it.
    Path(&'a str),
    /// The bytes of an uploaded scene, loaded as a farm worker loads them (no external
    /// files).
    Bytes(&'a [u8]),
}

/// [`prepare`] for settings that are already a [`JobSettings`] (a dry run's pilot reads
/// them as JSON from the coordinator), with the bytes of the job's environment image if it
/// has one: the frame range is set to `frame` alone.
pub fn prepare_settings_with(
    mut settings: JobSettings,
    source: SceneSource,
    environment_image: Option<&[u8]>,
    frame: u32,
) -> Result<Prepared> {
    settings.frames = FrameRange {
        start: frame,
        end: frame,
    };
    let validated = settings.validate().map_err(|e| job_error(e, &settings))?;
    let js = &validated.scene;
    let name = match source {
        SceneSource::Path(path) => path.to_string(),
        SceneSource::Bytes(_) => js.source.to_string(),
    };
    // Decoded once for every scene of the frame (shutter keys included).
    let environment = validated
        .environment
        .as_ref()
        .map(|e| SceneEnvironment::from_job(e, environment_image))
        .transpose()
        .context("loading the environment")?;
    let load = |time: &SceneTime| {
        match (&js.source, source) {
            // The farm's loader: it refuses a camera name for a built-in scene.
            (SceneRef::Builtin(_), _) => tessera_scene::job::load_job_scene_at(js, None, time),
            // A file may refer to files beside it, which an upload may not.
            (SceneRef::Hash(_), SceneSource::Path(path)) => {
                tessera_scene::load_at(path, js.camera.as_deref(), time)
            }
            (SceneRef::Hash(_), SceneSource::Bytes(bytes)) => {
                tessera_scene::job::load_job_scene_at(js, Some(bytes), time)
            }
        }
        .map(|mut scene| {
            if let Some(e) = &environment {
                e.apply(&mut scene);
            }
            scene
        })
        .with_context(|| format!("loading scene {name}"))
    };
    let at_zero = tessera_scene::job::resolution_time(js);
    let first = load(&at_zero)?;
    let resolved =
        tessera_scene::job::resolve_job(&validated, &first, tessera_render::pilot::verdict)
            .map_err(|e| match e {
                ResolveError::Job(e) => job_error(e, &settings),
                e @ ResolveError::Pilot(_) => anyhow!("{e}"),
            })?;
    let time = tessera_scene::job::frame_time(js, frame);
    let scene = if first.animated && time != at_zero {
        load(&time)?
    } else {
        first
    };
    let times = tessera_scene::job::shutter_times(js, frame);
    let keys = tessera_scene::job::shutter_scenes(&times, &scene, load)?;
    let start = Instant::now();
    let render_scene = if resolved.black {
        None
    } else {
        Some(RenderScene::build_in_motion(
            &scene,
            &keys,
            resolved.plan.width,
            resolved.plan.height,
        )?)
    };
    Ok(Prepared {
        frame,
        scene,
        render_scene,
        resolved,
        build_seconds: start.elapsed().as_secs_f64(),
    })
}

impl Prepared {
    /// Frees what the render scene holds its own copy of (meshes, prototypes and their
    /// instances, textures, images), keeping what the summaries read (the name, the
    /// environment): a large scene is not held twice while it renders.
    pub fn release_scene_data(&mut self) {
        if self.render_scene.is_none() {
            return;
        }
        let s = &mut self.scene;
        s.meshes = Vec::new();
        s.prototypes = Vec::new();
        s.instances = Vec::new();
        s.textures = Vec::new();
        s.images = Vec::new();
    }
}

fn check_output(path: &Path) -> Result<()> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(|e| e.to_ascii_lowercase());
    if !matches!(ext.as_deref(), Some("exr") | Some("png")) {
        bail!("output {} must end in .exr or .png", path.display());
    }
    Ok(())
}

/// `tessera render`.
pub fn render(args: RenderArgs) -> Result<()> {
    check_output(&args.output)?;
    if args.threads > 4096 {
        bail!(
            "--threads {} must be at most 4096 (0 = all cores)",
            args.threads
        );
    }
    if let Some(path) = &args.spp_map {
        adaptive::check_png("--spp-map", path)?;
    }
    let mut p = prepare(&args.job, &args.stop, args.frame)?;
    print!("{}", p.resolved.render_plan.summary());
    print_scene_line(&p);
    if p.resolved.black {
        return render_black(&p, &args);
    }
    p.release_scene_data();
    if p.resolved.job.stops_early() {
        return adaptive::render(&p, &args);
    }
    let plan = p.resolved.plan;
    let bar = std::io::stderr().is_terminal().then(|| {
        let bar = indicatif::ProgressBar::new(plan.unit_count(1));
        bar.set_style(
            indicatif::ProgressStyle::with_template(
                "{elapsed_precise} [{bar:40}] {pos}/{len} units, eta {eta}",
            )
            .expect("static template")
            .progress_chars("=> "),
        );
        bar
    });
    let start = Instant::now();
    let cpu_start = crate::common::cpu_seconds("self");
    let render_scene = p.render_scene.as_ref().expect("built unless black");
    let rendered = render_frame_counted(
        render_scene,
        &p.resolved.config,
        &plan,
        p.frame,
        args.threads,
        |done, _| {
            if let Some(b) = &bar {
                b.set_position(done as u64);
            }
        },
    );
    let seconds = start.elapsed().as_secs_f64();
    let cpu_seconds = crate::common::cpu_seconds("self") - cpu_start;
    if let Some(b) = bar {
        b.finish_and_clear();
    }
    let acc = &rendered.accumulator;
    let image = acc.image();
    tessera_image::write_image(&args.output, &image, Some(&p.resolved.metadata_json(None)))?;
    let paths = plan.width as f64 * plan.height as f64 * plan.spp() as f64;
    let c = &p.resolved.config;
    println!(
        "rendered {} ({}x{}, {} integrator, {} sampler, {} MIS) to {}",
        p.scene.name,
        plan.width,
        plan.height,
        c.integrator,
        c.sampler,
        c.mis,
        args.output.display()
    );
    print_totals(
        &plan,
        seconds,
        acc.image_error(),
        paths / seconds,
        &p.resolved.error_estimator_name(),
    );
    print_caveat(&p.resolved);
    // CPU time of all render threads: what a comparison on a loaded machine can trust
    // (bench/compare divides noise by it), at the 10 ms resolution of /proc.
    println!("cpu seconds: {cpu_seconds:.2}");
    println!(
        "rays: {} ({:.0} per second, {:.2} per path)",
        rendered.rays,
        rendered.rays as f64 / seconds,
        rendered.rays as f64 / paths
    );
    print_rejected_samples(rendered.rejected_samples);
    if let Some(map) = &args.spp_map {
        adaptive::write_spp_map(map, &image)?;
    }
    Ok(())
}

/// `scene: T triangles, built in S s, B MiB of geometry (b bytes per stored triangle)`
/// and `build: peak memory P MiB (p bytes per stored triangle), C CPU seconds loading and
/// building` (per triangle from 10,000 stored triangles), the process's peak resident memory and CPU time up to the end of the build
/// (scene decoding and BVH temporaries included): what a large scene costs before the
/// first ray (the large-scene figures in
/// docs/benchmarks.md come from them).
fn print_scene_line(p: &Prepared) {
    let Some(rs) = &p.render_scene else {
        return;
    };
    let triangles = p.scene.triangle_count();
    let stored = p.scene.stored_triangle_count().max(1) as f64;
    let bytes = rs.geometry.bytes();
    println!(
        "scene: {triangles} triangles, built in {:.3} s, {:.1} MiB of geometry ({:.0} bytes per stored triangle)",
        p.build_seconds,
        bytes as f64 / (1024.0 * 1024.0),
        bytes as f64 / stored
    );
    if let Some(peak) = crate::common::peak_resident_bytes() {
        // Per triangle only where triangles make the peak: below PER_TRIANGLE_FROM the
        // process's own few MiB (code, threads, the film) would dominate the quotient.
        const PER_TRIANGLE_FROM: f64 = 10_000.0;
        let per_triangle = if stored >= PER_TRIANGLE_FROM {
            format!(" ({:.0} bytes per stored triangle)", peak as f64 / stored)
        } else {
            String::new()
        };
        // CPU seconds beside the wall-clock build time: what a loaded machine can trust.
        println!(
            "build: peak memory {:.1} MiB{per_triangle}, {:.2} CPU seconds loading and building",
            peak as f64 / (1024.0 * 1024.0),
            crate::common::cpu_seconds("self")
        );
    }
    if let Some(s) = p.resolved.job.scene.shutter {
        println!(
            "motion blur: shutter [{}, {}] frames: {}",
            s.open,
            s.close,
            rs.motion_summary()
        );
        for w in &rs.motion_warnings {
            println!("warning: {w}");
        }
    }
}

/// The summary lines every render without adaptive stopping ends with (scripts read them);
/// `estimator` names the error estimate ([`tessera_farm::job::ResolvedJob::error_estimator_name`]).
fn print_totals(
    plan: &FramePlan,
    seconds: f64,
    error: f64,
    paths_per_second: f64,
    estimator: &str,
) {
    println!(
        "samples per pixel: {} ({} passes of {})",
        plan.spp(),
        plan.passes,
        plan.samples_per_pass
    );
    println!("seconds: {seconds:.3}");
    println!("estimated relative error: {error:.4} (estimator: {estimator})");
    println!("paths per second: {paths_per_second:.0}");
}

/// Why the estimate just printed may be optimistic, when the plan knows
/// ([`tessera_farm::job::ResolvedJob::error_estimate_caveat`]); nothing otherwise.
pub fn print_caveat(resolved: &tessera_farm::job::ResolvedJob) {
    if let Some(caveat) = resolved.error_estimate_caveat() {
        println!("error estimate caveat: {caveat}");
    }
}

/// The summary line for samples the integrator dropped as invalid; nothing when there
/// were none (a healthy render).
pub fn print_rejected_samples(n: u64) {
    if n > 0 {
        println!(
            "rejected samples: {n} (NaN, infinite or negative radiance, counted as black: a renderer bug)"
        );
    }
}

/// The render plan found no light: the image is black, and no ray is traced.
fn render_black(p: &Prepared, args: &RenderArgs) -> Result<()> {
    let start = Instant::now();
    let plan = p.resolved.plan;
    let image = FrameImage::black(&plan);
    let stopped =
        (p.resolved.job.stops_early()).then(|| StopVerdict::of_image(&p.resolved, &image, false));
    tessera_image::write_image(
        &args.output,
        &image,
        Some(&p.resolved.metadata_json(stopped.as_ref())),
    )?;
    let seconds = start.elapsed().as_secs_f64();
    println!(
        "rendered {} ({}x{}, black: the render plan found no light, no ray traced) to {}",
        p.scene.name,
        plan.width,
        plan.height,
        args.output.display()
    );
    print_totals(&plan, seconds, 0.0, 0.0, tessera_farm::ERROR_ESTIMATOR);
    if p.scene.environment.is_none() {
        // Most downloaded models carry no light of their own.
        println!(
            "hint: light the scene with an environment: --environment FILE.hdr (or .exr, an \
             equirectangular HDR image) or --environment 1,1,1 (a uniform white sky)"
        );
    }
    if let Some(map) = &args.spp_map {
        adaptive::write_spp_map(map, &image)?;
    }
    Ok(())
}
