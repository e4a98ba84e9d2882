//! `tessera estimate`: what accuracy costs, before rendering.
//!
//! The job is resolved exactly as `tessera render` resolves it ([`crate::render::prepare`]),
//! then a pilot renders [`PILOT_PASSES`] passes of a deterministic subset of the job's own
//! tiles ([`pilot_tiles`]) with the job's own pass size on this machine, timing every unit.
//! The prediction is [`tessera_farm::quote::quote`], the one copy of the maths: the
//! 1/sqrt(passes) law from the pilot's image error, the measured cost per pixel-pass, and
//! the intervals from their spreads. Units are timed by the wall clock and scaled by the
//! pilot's share of CPU time, so a machine loaded by other work quotes what it would take
//! alone.

use anyhow::{bail, Context, Result};
use clap::Args;
use std::time::Instant;
use tessera_farm::job::FrameRange;
use tessera_farm::quote::{
    pilot_groups, pilot_tiles, quote, Interval, PilotMeasurement, PilotUnit, Quote, QuoteJob,
    TailClass, Tails, DEFAULT_TARGETS, PILOT_PASSES,
};
use tessera_farm::{FrameAccumulator, FramePlan, WorkUnit};
use tessera_render::render::render_unit;

use sha2::{Digest, Sha256};

use crate::render::{prepare, prepare_settings_with, JobArgs, Prepared, SceneSource, StopArgs};

/// `tessera estimate`'s arguments: the job flags of `tessera render` and `tessera submit`.
#[derive(Args)]
pub struct EstimateArgs {
    #[command(flatten)]
    pub job: JobArgs,
    /// --target-error E quotes that error alone; without it, 10%, 5%, 2% and 1%.
    #[command(flatten)]
    pub stop: StopArgs,
    /// First frame (the pilot renders this one).
    #[arg(long, default_value_t = 0)]
    pub frame_start: u32,
    /// Last frame (inclusive; default the first).
    #[arg(long)]
    pub frame_end: Option<u32>,
    /// Workers the job will run on, each as fast as this machine with --threads: wall
    /// seconds are worker-seconds over workers.
    #[arg(long, default_value_t = 1)]
    pub workers: u32,
    /// Threads of the pilot (0 = all cores): a worker-second is a second of this machine
    /// with that many threads.
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
    /// The farm's spot-check fraction (`tessera serve --spot-check-fraction`): that
    /// fraction of the units is rendered twice, which the quote's seconds count. 0 for a
    /// farm without spot checks.
    #[arg(long, default_value_t = tessera_farm::DEFAULT_SPOT_CHECK_FRACTION)]
    pub spot_check_fraction: f64,
    /// Print the quote as JSON.
    #[arg(long)]
    pub json: bool,
}

/// What a quote is for, and the quote: printed as one JSON object with `--json`, and
/// what a coordinator's dry run answers (with `dry_run` and `fleet` besides).
struct EstimateOutput {
    scene: String,
    width: u32,
    height: u32,
    frames: u64,
    spp: u32,
    passes: u32,
    samples_per_pass: u32,
    integrator: String,
    adaptive: String,
    workers: u32,
    threads: usize,
    worker_threads: usize,
    pilot_tiles: usize,
    pilot_seconds: f64,
    pilot_cpu_seconds: f64,
    setup_seconds: f64,
    /// The farm's spot-check fraction the seconds count.
    spot_check_fraction: f64,
    black: bool,
    quote: Option<Quote>,
    /// Why the quoted errors may be optimistic, when the render plan knows
    /// ([`tessera_farm::job::ResolvedJob::error_estimate_caveat`]).
    error_estimate_caveat: Option<String>,
}

impl EstimateOutput {
    fn to_json(&self) -> serde_json::Value {
        serde_json::json!({
            "scene": self.scene,
            "width": self.width,
            "height": self.height,
            "frames": self.frames,
            "spp": self.spp,
            "passes": self.passes,
            "samples_per_pass": self.samples_per_pass,
            "integrator": self.integrator,
            "adaptive": self.adaptive,
            "workers": self.workers,
            "threads": self.threads,
            "worker_threads": self.worker_threads,
            "pilot_tiles": self.pilot_tiles,
            "pilot_seconds": self.pilot_seconds,
            "pilot_cpu_seconds": self.pilot_cpu_seconds,
            "setup_seconds": self.setup_seconds,
            "spot_check_fraction": self.spot_check_fraction,
            "black": self.black,
            "quote": self.quote,
            "error_estimate_caveat": self.error_estimate_caveat,
        })
    }

    /// The inverse of [`EstimateOutput::to_json`] (a dry run's answer has more fields).
    fn from_json(v: &serde_json::Value) -> Result<Self> {
        let int = |k: &str| {
            v[k].as_u64()
                .with_context(|| format!("the quote has no whole number {k:?}"))
        };
        let num = |k: &str| v[k].as_f64().unwrap_or(0.0);
        let text = |k: &str| v[k].as_str().unwrap_or("").to_string();
        Ok(Self {
            scene: text("scene"),
            width: int("width")? as u32,
            height: int("height")? as u32,
            frames: int("frames")?,
            spp: int("spp")? as u32,
            passes: int("passes")? as u32,
            samples_per_pass: int("samples_per_pass")? as u32,
            integrator: text("integrator"),
            adaptive: text("adaptive"),
            workers: int("workers")? as u32,
            threads: int("threads")? as usize,
            worker_threads: int("worker_threads")? as usize,
            pilot_tiles: int("pilot_tiles")? as usize,
            pilot_seconds: num("pilot_seconds"),
            pilot_cpu_seconds: num("pilot_cpu_seconds"),
            setup_seconds: num("setup_seconds"),
            spot_check_fraction: num("spot_check_fraction"),
            black: v["black"].as_bool().unwrap_or(false),
            error_estimate_caveat: v["error_estimate_caveat"].as_str().map(str::to_string),
            quote: match &v["quote"] {
                serde_json::Value::Null => None,
                q => Some(serde_json::from_value(q.clone()).context("reading the quote")?),
            },
        })
    }
}

/// Prints a coordinator's dry-run answer (`tessera submit --dry-run`) as `tessera
/// estimate` prints its quote, after the fleet it assumes.
pub fn print_dry_run(v: serde_json::Value) -> Result<()> {
    let fleet = v["fleet"].as_str().unwrap_or("").to_string();
    let out = EstimateOutput::from_json(&v)?;
    println!("dry run on the coordinator; assumes {fleet}");
    match &out.quote {
        Some(q) => print_quote(&out, q),
        None => println!("the image is black (no light reaches the camera): nothing to render"),
    }
    Ok(())
}

/// Renders the pilot's units on `threads` threads (each takes the next unit), timing each
/// unit on the thread that renders it.
fn render_pilot(
    scene: &tessera_render::scene::RenderScene,
    config: &tessera_render::render::RenderConfig,
    plan: &FramePlan,
    units: &[WorkUnit],
    threads: usize,
) -> Vec<(tessera_farm::UnitResult, f64)> {
    let next = std::sync::atomic::AtomicUsize::new(0);
    let mut out: Vec<_> = std::thread::scope(|s| {
        let handles: Vec<_> = (0..threads.min(units.len()).max(1))
            .map(|_| {
                s.spawn(|| {
                    let mut mine = Vec::new();
                    loop {
                        let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                        let Some(&unit) = units.get(i) else { break };
                        let t = Instant::now();
                        let r = render_unit(scene, config, plan, unit);
                        mine.push((i, r, t.elapsed().as_secs_f64()));
                    }
                    mine
                })
            })
            .collect();
        handles
            .into_iter()
            .flat_map(|h| h.join().unwrap_or_else(|p| std::panic::resume_unwind(p)))
            .collect()
    });
    // Merged in unit order, so the pilot's image does not depend on the threads.
    out.sort_by_key(|(i, _, _)| *i);
    out.into_iter().map(|(_, r, t)| (r, t)).collect()
}

/// `tessera estimate`.
pub fn estimate(args: EstimateArgs) -> Result<()> {
    if args.workers == 0 {
        bail!("--workers must be at least 1");
    }
    if !(0.0..=1.0).contains(&args.spot_check_fraction) {
        bail!(
            "--spot-check-fraction {} must be 0 to 1",
            args.spot_check_fraction
        );
    }
    if args.threads > 4096 {
        bail!(
            "--threads {} must be at most 4096 (0 = all cores)",
            args.threads
        );
    }
    let frames = FrameRange {
        start: args.frame_start,
        end: args.frame_end.unwrap_or(args.frame_start),
    };
    if frames.end < frames.start {
        bail!(
            "--frame-end {} is before --frame-start {}",
            frames.end,
            frames.start
        );
    }
    let targets: Vec<f64> = match args.stop.target_error {
        Some(t) => vec![t],
        None => DEFAULT_TARGETS.to_vec(),
    };
    // Validates every job flag (naming it) and resolves the job as `tessera render` does.
    let p = prepare(&args.job, &args.stop, frames.start)?;
    let threads = if args.threads == 0 {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    } else {
        args.threads
    };
    let run = PilotRun {
        scene: args.job.scene.clone(),
        frames,
        targets,
        adaptive: args.stop.adaptive.clone(),
        workers: args.workers,
        threads,
        worker_threads: threads,
        spot_check_fraction: args.spot_check_fraction,
        passes_per_unit: 1,
        stop_interval: stop_interval(args.stop.target_error, 1),
    };
    let out = run_pilot(&p, &run).map_err(|e| match e {
        PilotError::Target(m) => anyhow::anyhow!("--target-error: {m}"),
        PilotError::Other(e) => e,
    })?;
    match (&out.quote, args.json) {
        (_, true) => println!("{}", serde_json::to_string_pretty(&out.to_json())?),
        (Some(q), false) => print_quote(&out, q),
        // The plan found no light: nothing is traced, every target is met at once.
        (None, false) => {
            println!("the image is black (no light reaches the camera): nothing to render")
        }
    }
    Ok(())
}

/// `tessera pilot`'s arguments. The job's settings come as JSON on standard input.
#[derive(Args)]
pub struct PilotArgs {
    /// The uploaded scene the job names by hash (its SHA-256 must be that hash); not
    /// needed for a built-in scene.
    #[arg(long)]
    pub scene_file: Option<std::path::PathBuf>,
    /// The uploaded environment image the job's `environment.source` names by hash (its
    /// SHA-256 must be that hash); not needed for a uniform colour or no environment.
    #[arg(long)]
    pub environment_file: Option<std::path::PathBuf>,
    /// Workers the job will run on.
    #[arg(long, default_value_t = 1)]
    pub workers: u32,
    /// Threads of each of those workers: the pilot's thread-seconds are divided by them.
    #[arg(long, default_value_t = 1)]
    pub worker_threads: usize,
    /// Threads the pilot renders on.
    #[arg(long, default_value_t = 1)]
    pub threads: usize,
    /// The coordinator's spot-check fraction (units rendered twice).
    #[arg(long, default_value_t = tessera_farm::DEFAULT_SPOT_CHECK_FRACTION)]
    pub spot_check_fraction: f64,
    /// The coordinator's passes per work unit.
    #[arg(long, default_value_t = 1)]
    pub passes_per_unit: u32,
    /// Run the technique pilot instead of a quote (`tessera_render::pilot`): print
    /// `{"path_wins":BOOL,"mlt_wins":BOOL,"mnee_wins":BOOL,"reason":TEXT}`, or `{}` when the job's plan leaves no choice.
    #[arg(long)]
    pub technique: bool,
}

/// The largest job settings document `tessera pilot` reads: the coordinator's own limit on
/// a job's JSON body.
const MAX_SETTINGS_BYTES: u64 = 1 << 20;

/// `tessera pilot`: the pilot of a dry run (`POST /api/v1/jobs?dry_run=true`), run by the
/// coordinator as a child process so that rendering user content never shares its
/// address space (a scene that crashes the renderer takes only the pilot down). Reads the
/// job's settings as JSON on standard input, prints `tessera estimate --json`'s object.
/// An error goes to standard error as one line naming what is wrong, with exit code 1.
pub fn pilot(args: PilotArgs) -> Result<()> {
    use std::io::Read;
    use tessera_api::FromJson;
    use tessera_farm::job::{EnvironmentSource, JobSettings, SceneRef};

    if args.threads == 0 || args.threads > 4096 {
        bail!("--threads {} must be 1 to 4096", args.threads);
    }
    if !(0.0..=1.0).contains(&args.spot_check_fraction) || args.passes_per_unit == 0 {
        bail!(
            "--spot-check-fraction {} must be 0 to 1 and --passes-per-unit {} at least 1",
            args.spot_check_fraction,
            args.passes_per_unit
        );
    }
    if args.worker_threads == 0 || args.worker_threads > 65536 {
        bail!(
            "--worker-threads {} must be 1 to 65536",
            args.worker_threads
        );
    }
    let mut body = Vec::new();
    std::io::stdin()
        .take(MAX_SETTINGS_BYTES + 1)
        .read_to_end(&mut body)
        .context("reading the job settings from standard input")?;
    if body.len() as u64 > MAX_SETTINGS_BYTES {
        bail!("the job settings are larger than {MAX_SETTINGS_BYTES} bytes");
    }
    let settings = JobSettings::from_json(&body).map_err(|e| anyhow::anyhow!("{e}"))?;
    let validated = settings
        .validate()
        .map_err(|e| anyhow::anyhow!("invalid {}: {}", e.field, e.problem))?;
    let bytes = match (&validated.scene.source, &args.scene_file) {
        (SceneRef::Builtin(_), _) => None,
        (SceneRef::Hash(h), Some(path)) => Some(read_hashed(path, h, "scene")?),
        (SceneRef::Hash(h), None) => bail!("the job names scene {h}: give --scene-file"),
    };
    let image = match (
        validated.environment.as_ref().map(|e| &e.source),
        &args.environment_file,
    ) {
        (Some(EnvironmentSource::Image(h)), Some(path)) => {
            Some(read_hashed(path, h, "environment image")?)
        }
        (Some(EnvironmentSource::Image(h)), None) => {
            bail!("the job names environment image {h}: give --environment-file")
        }
        _ => None,
    };
    if args.technique {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(args.threads)
            .build()
            .context("starting the pilot's threads")?;
        return pool.install(|| technique(&validated, bytes.as_deref(), image.as_deref()));
    }
    let source = match &bytes {
        Some(b) => SceneSource::Bytes(b),
        None => SceneSource::Path(&settings.scene),
    };
    let frames = validated.frames;
    let p = prepare_settings_with(settings.clone(), source, image.as_deref(), frames.start)?;
    let run = PilotRun {
        scene: settings.scene.clone(),
        frames,
        targets: match settings.target_error {
            Some(t) => vec![t],
            None => DEFAULT_TARGETS.to_vec(),
        },
        adaptive: settings.adaptive.clone(),
        workers: args.workers.max(1),
        threads: args.threads,
        worker_threads: args.worker_threads,
        spot_check_fraction: args.spot_check_fraction,
        passes_per_unit: args.passes_per_unit,
        // On the farm only an adaptive job stops at its target (`job_eta_seconds`).
        stop_interval: stop_interval(
            settings.target_error.filter(|_| settings.adaptive != "off"),
            args.passes_per_unit,
        ),
    };
    let out = run_pilot(&p, &run).map_err(|e| match e {
        PilotError::Target(m) => anyhow::anyhow!("invalid target_error: {m}"),
        PilotError::Other(e) => e,
    })?;
    println!("{}", serde_json::to_string(&out.to_json())?);
    Ok(())
}

/// `tessera pilot --technique`: the coordinator's technique pilot, in a child process for
/// the reason a dry run's is. The scene is loaded as the coordinator loads it (at
/// [`tessera_scene::job::resolution_time`], with the job's camera) and resolved on the
/// same path as `tessera render` ([`tessera_scene::job::resolve_job`] with
/// [`tessera_render::pilot::verdict`]), so the verdict printed (a
/// [`tessera_farm::job::PilotVerdict`] as JSON, or `null` when the job asks for none) is
/// the one a local render reaches.
fn technique(
    job: &tessera_farm::job::ValidatedJob,
    bytes: Option<&[u8]>,
    image: Option<&[u8]>,
) -> Result<()> {
    let time = tessera_scene::job::resolution_time(&job.scene);
    let mut scene = tessera_scene::job::load_job_scene_at(&job.scene, bytes, &time)?;
    // Lit as `tessera render` lights it before resolving (`render::prepare_settings_with`).
    if let Some(e) = &job.environment {
        tessera_scene::environment::SceneEnvironment::from_job(e, image)
            .context("loading the environment")?
            .apply(&mut scene);
    }
    let mut asked = None;
    let resolved = tessera_scene::job::resolve_job(job, &scene, |q| {
        let v = tessera_render::pilot::verdict(q);
        asked = Some(v.clone());
        v
    });
    match resolved {
        // The settings' own problems are the coordinator's to report, as it resolves the
        // job itself with this verdict.
        Ok(_) | Err(tessera_scene::job::ResolveError::Job(_)) => {
            println!(
                "{}",
                serde_json::to_string(&asked.transpose().map_err(anyhow::Error::msg)?)?
            )
        }
        Err(e) => return Err(e.into()),
    }
    Ok(())
}

/// The bytes of `path`, which must hash (SHA-256) to `hash`: the coordinator's upload
/// named `what`.
fn read_hashed(path: &std::path::Path, hash: &str, what: &str) -> Result<Vec<u8>> {
    let bytes =
        std::fs::read(path).with_context(|| format!("reading {what} file {}", path.display()))?;
    let digest: String = Sha256::digest(&bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect();
    if digest != hash {
        bail!(
            "{what} file {} has SHA-256 {digest}, not the job's {what} {hash}",
            path.display()
        );
    }
    Ok(bytes)
}

/// What a pilot is for: the job beyond its resolved plan, and the machine it predicts.
struct PilotRun {
    scene: String,
    frames: FrameRange,
    targets: Vec<f64>,
    adaptive: String,
    workers: u32,
    /// Threads the pilot renders on.
    threads: usize,
    /// Threads of each worker the job will run on: a worker-second is a second of a worker
    /// with that many threads, each as fast as one of this machine's.
    worker_threads: usize,
    /// The farm's spot-check fraction: units rendered twice.
    spot_check_fraction: f64,
    /// The farm's passes per work unit.
    passes_per_unit: u32,
    /// Passes between a target-stopped job's checks ([`QuoteJob::stop_interval`]), 0 for a
    /// job that runs its planned passes.
    stop_interval: u32,
}

/// [`QuoteJob::stop_interval`] of a job: the adaptive policy's rounds (rounded up to the
/// farm's units, as [`tessera_farm::AdaptiveSettings::for_units`] does) when it stops at
/// a target error, else 0.
fn stop_interval(target_error: Option<f64>, passes_per_unit: u32) -> u32 {
    match target_error {
        Some(_) => {
            tessera_farm::AdaptiveSettings::default()
                .for_units(passes_per_unit)
                .interval
        }
        None => 0,
    }
}

/// Why a pilot gave no quote.
enum PilotError {
    /// A target error the quote cannot use (the message says why).
    Target(String),
    Other(anyhow::Error),
}

impl From<anyhow::Error> for PilotError {
    fn from(e: anyhow::Error) -> Self {
        Self::Other(e)
    }
}

/// Renders the pilot of the prepared job and quotes it ([`tessera_farm::quote::quote`]).
fn run_pilot(p: &Prepared, run: &PilotRun) -> Result<EstimateOutput, PilotError> {
    let plan = p.resolved.plan;
    let threads = run.threads.max(1);
    let frames = run.frames;
    let mut out = EstimateOutput {
        scene: run.scene.clone(),
        width: plan.width,
        height: plan.height,
        frames: frames.count(),
        spp: plan.spp(),
        passes: plan.passes,
        samples_per_pass: plan.samples_per_pass,
        integrator: p.resolved.config.integrator.to_string(),
        adaptive: run.adaptive.clone(),
        workers: run.workers,
        threads,
        worker_threads: run.worker_threads.max(1),
        pilot_tiles: 0,
        pilot_seconds: 0.0,
        pilot_cpu_seconds: 0.0,
        setup_seconds: p.build_seconds,
        spot_check_fraction: run.spot_check_fraction,
        black: p.resolved.black,
        quote: None,
        error_estimate_caveat: p.resolved.error_estimate_caveat(),
    };
    let Some(render_scene) = p.render_scene.as_ref() else {
        // The plan found no light: nothing is traced, every target is met at once.
        return Ok(out);
    };
    // The job's tiles and pass size, with the pilot's passes.
    let pilot_plan = FramePlan::new(
        plan.width,
        plan.height,
        plan.tile_size,
        plan.samples_per_pass,
        PILOT_PASSES,
    )
    .context("pilot plan")?;
    let tiles = pilot_tiles(plan.tile_count(), plan.tile(0).pixel_count() as u64);
    let units: Vec<WorkUnit> = tiles
        .iter()
        .flat_map(|&tile| {
            (0..PILOT_PASSES).map(move |pass| WorkUnit {
                frame: frames.start,
                tile,
                first_pass: pass,
                pass_count: 1,
            })
        })
        .collect();
    let start = Instant::now();
    let cpu_start = crate::common::cpu_seconds("self");
    let rendered = render_pilot(
        render_scene,
        &p.resolved.config,
        &pilot_plan,
        &units,
        threads,
    );
    let cpu = crate::common::cpu_seconds("self") - cpu_start;
    // On a machine shared with other work a unit's wall time includes waiting for a core;
    // the pilot's CPU time (all threads, from /proc at 10 ms resolution) over the units'
    // summed wall time is the share it got, and scales every unit to what a dedicated
    // worker would take. Without a usable CPU figure (no /proc, a pilot under 10 ms), 1.
    let thread_seconds: f64 = rendered.iter().map(|(_, t)| t).sum();
    let share = if cpu > 0.0 && thread_seconds > 0.0 {
        (cpu / thread_seconds).min(1.0)
    } else {
        1.0
    };
    out.pilot_cpu_seconds = cpu;
    out.pilot_seconds = start.elapsed().as_secs_f64();
    out.pilot_tiles = tiles.len();
    let tails = pilot_tails(&rendered);
    let mut acc = FrameAccumulator::for_frame(pilot_plan, frames.start);
    let mut pilot_units = Vec::with_capacity(rendered.len());
    for (result, seconds) in rendered {
        let pixels = plan.tile(result.unit.tile).pixel_count() as u64;
        pilot_units.push(PilotUnit {
            pixel_passes: pixels,
            // A worker renders on all its threads at once: a unit's thread-seconds are
            // 1/threads of a worker-second.
            worker_seconds: seconds * share / out.worker_threads as f64,
        });
        acc.offer(result).context("merging the pilot")?;
    }
    let groups = pilot_groups(&acc, &tiles);
    let pilot = PilotMeasurement {
        passes: PILOT_PASSES,
        groups,
        units: pilot_units,
        tails,
    };
    let job = QuoteJob {
        pixels_per_frame: u64::from(plan.width) * u64::from(plan.height),
        frames: frames.count(),
        planned_passes: plan.passes,
        samples_per_pass: plan.samples_per_pass,
        workers: run.workers,
        setup_seconds: p.build_seconds,
        tiles_per_frame: plan.tile_count(),
        passes_per_unit: run.passes_per_unit,
        spot_check_fraction: run.spot_check_fraction,
        stop_interval: run.stop_interval,
    };
    out.quote = Some(quote(&pilot, &job, &run.targets).map_err(|e| match e {
        tessera_farm::quote::QuoteError::Field("target_error", m) => {
            PilotError::Target(m.to_string())
        }
        e => PilotError::Other(anyhow::anyhow!(e)),
    })?);
    Ok(out)
}

/// The tails of the pilot's pass values ([`Tails::measure`]): every pilot pixel's
/// luminance in each of its passes, gathered from the units (one pass of one tile each).
fn pilot_tails(rendered: &[(tessera_farm::UnitResult, f64)]) -> Option<Tails> {
    let passes = PILOT_PASSES as usize;
    let lum = |c: &[f32; 3]| tessera_farm::luminance(c.map(f64::from));
    let mut by_tile = std::collections::BTreeMap::<u32, Vec<f64>>::new();
    for (r, _) in rendered {
        let px = r.width as usize * r.height as usize;
        let values = by_tile
            .entry(r.unit.tile)
            .or_insert_with(|| vec![0.0; px * passes]);
        for p in 0..r.unit.pass_count as usize {
            let pass = r.unit.first_pass as usize + p;
            let Some(means) = r.pass_means.get(p * px..(p + 1) * px) else {
                continue;
            };
            if pass >= passes || values.len() != px * passes {
                continue;
            }
            for (i, c) in means.iter().enumerate() {
                values[i * passes + pass] = lum(c);
            }
        }
    }
    let values: Vec<f64> = by_tile.into_values().flatten().collect();
    Tails::measure(&values, passes)
}

fn secs(i: &Interval) -> String {
    format!(
        "{} [{}, {}]",
        human(i.estimate),
        human(i.low),
        human(i.high)
    )
}

fn human(s: f64) -> String {
    if s < 100.0 {
        format!("{s:.2} s")
    } else if s < 7200.0 {
        format!("{:.1} min", s / 60.0)
    } else {
        format!("{:.1} h", s / 3600.0)
    }
}

fn print_quote(o: &EstimateOutput, q: &Quote) {
    let frames = if o.frames == 1 {
        "1 frame".to_string()
    } else {
        format!("{} frames", o.frames)
    };
    println!(
        "quote for {}: {}x{}, {frames}, {} spp planned ({} passes of {}), {} integrator, {} worker(s), {}% of units spot-checked",
        o.scene,
        o.width,
        o.height,
        o.spp,
        o.passes,
        o.samples_per_pass,
        o.integrator,
        o.workers,
        o.spot_check_fraction * 100.0
    );
    println!(
        "pilot: {} tiles ({} pixels), {} passes, {:.2} s ({:.2} CPU s) on {} threads; image error {:.4}",
        o.pilot_tiles,
        q.pilot_pixels,
        q.pilot_passes,
        o.pilot_seconds,
        o.pilot_cpu_seconds,
        o.threads,
        q.pilot_error
    );
    let row = |label: &str, c: &tessera_farm::quote::Cost| {
        println!("{label}");
        println!(
            "  error {:.4} [{:.4}, {:.4}], {} spp [{}, {}]",
            c.error.estimate, c.error.low, c.error.high, c.spp.estimate, c.spp.low, c.spp.high
        );
        println!(
            "  per frame: {} worker-seconds, {} wall",
            secs(&c.worker_seconds_per_frame),
            secs(&c.seconds_per_frame)
        );
        println!(
            "  whole job: {} worker-seconds, {} wall",
            secs(&c.worker_seconds),
            secs(&c.seconds)
        );
    };
    if q.tail_class == TailClass::Unpredictable {
        if let Some(note) = &q.tail_note {
            println!("{note}");
        }
    }
    row(&format!("as planned ({} spp):", o.spp), &q.planned);
    for t in &q.targets {
        let note = if t.within_plan {
            ""
        } else {
            " (beyond the planned spp: raise --spp)"
        };
        row(&format!("to reach error {}{note}:", t.target), &t.cost);
    }
    println!("intervals are 95%; assumes {}", q.assumes);
    if q.tail_class == TailClass::Heavy {
        if let Some(note) = &q.tail_note {
            println!("{note}");
        }
    }
    if let Some(caveat) = &o.error_estimate_caveat {
        println!("error estimate caveat: the quoted errors {caveat}");
    }
}
