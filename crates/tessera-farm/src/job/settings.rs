//! Job settings in two stages: [`JobSettings`] as submitted (strings, optional fields,
//! defaults) and [`ValidatedJob`], every field checked and every choice parsed. Errors are
//! [`JobError`]s naming the field.

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Serialize};

use super::choice::{
    AdaptiveMode, Integrator, IntegratorChoice, MisHeuristic, SamplerKind, SceneRef,
};
use super::environment::{EnvironmentSettings, JobEnvironment};
use super::scene::JobScene;
use crate::adaptive::{adaptive_plan, AdaptiveSettings};
use crate::plan::{
    FramePlan, PlanError, MAX_AUTO_SAMPLES_PER_PASS, MAX_DIMENSION, MAX_PASSES, MAX_TILE_SIZE,
    MIN_TILE_SIZE,
};

/// Largest accepted samples per pixel: what [`FramePlan::for_spp`],
/// [`FramePlan::whole_frame`] and [`adaptive_plan`] can all plan (the shorter passes of the
/// last two are the limit).
pub const MAX_SPP: u32 = 1_048_576;
const _: () = assert!(MAX_SPP <= MAX_AUTO_SAMPLES_PER_PASS * MAX_PASSES);
const _: () = assert!(MAX_SPP == crate::plan::WHOLE_FRAME_MAX_SAMPLES_PER_PASS * MAX_PASSES);
const _: () = assert!(MAX_SPP == crate::adaptive::ADAPTIVE_MAX_SAMPLES_PER_PASS * MAX_PASSES);
/// Largest accepted `max_depth`.
pub const MAX_DEPTH_LIMIT: u32 = 1024;
/// Most frames one job may render.
pub const MAX_FRAMES: u64 = 100_000;
/// Longest accepted job name, in characters.
pub const MAX_NAME_CHARS: usize = 200;
/// Longest accepted camera name, in characters.
pub const MAX_CAMERA_CHARS: usize = 200;
/// Longest accepted animation name, in characters.
pub const MAX_ANIMATION_CHARS: usize = 200;
/// Default frames per second: frame `F` is the scene at `t = F / 24` s (Blender's glTF
/// exporter writes frame 1 at t = 1/24).
pub const DEFAULT_FPS: f64 = 24.0;
/// Largest accepted frames per second.
pub const MAX_FPS: f64 = 1_000_000.0;
/// Largest accepted distance of the shutter's opening or closing from its frame, in
/// frames.
pub const MAX_SHUTTER_FRAMES: f64 = 1.0;
/// Segments of linear motion over an open shutter: the scene is evaluated at
/// `SHUTTER_SEGMENTS + 1` key times spread evenly over it (motion blur; ARCHITECTURE.md
/// §8, "Time"). Eight keep a point turning by 90° within the shutter within 0.5% of its
/// distance from the axis (the chord error `r (1 - cos(θ/16))`).
pub const SHUTTER_SEGMENTS: u32 = 8;

/// When the shutter is open, relative to its frame, in frames: `[open, close]` with
/// `open < close`, e.g. `[-0.25, 0.25]` (a 180° shutter centred on the frame, Blender's
/// `motion_blur_shutter` 0.5 at position "center").
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(from = "[f64; 2]", into = "[f64; 2]")]
pub struct Shutter {
    /// Opening, in frames from the frame (negative: before it).
    pub open: f64,
    /// Closing, in frames from the frame.
    pub close: f64,
}

impl From<[f64; 2]> for Shutter {
    fn from([open, close]: [f64; 2]) -> Self {
        Self { open, close }
    }
}

impl From<Shutter> for [f64; 2] {
    fn from(s: Shutter) -> Self {
        [s.open, s.close]
    }
}

impl Shutter {
    /// Checks `open < close`, both finite and within [`MAX_SHUTTER_FRAMES`] of the frame.
    pub fn check(&self) -> Result<(), JobError> {
        let within = |v: f64| v.is_finite() && v.abs() <= MAX_SHUTTER_FRAMES;
        if !within(self.open) || !within(self.close) {
            return Err(JobError::new(
                "shutter",
                format_args!(
                    "opening and closing must be within {MAX_SHUTTER_FRAMES} frame of the \
                     frame, got [{}, {}]",
                    self.open, self.close
                ),
            ));
        }
        if self.open >= self.close {
            return Err(JobError::new(
                "shutter",
                format_args!(
                    "must open before it closes, got [{}, {}]",
                    self.open, self.close
                ),
            ));
        }
        Ok(())
    }

    /// The `SHUTTER_SEGMENTS + 1` key times of `frame`, in frames: evenly from the
    /// opening to the closing.
    pub fn key_frames(&self, frame: u32) -> Vec<f64> {
        (0..=SHUTTER_SEGMENTS)
            .map(|i| {
                let u = f64::from(i) / f64::from(SHUTTER_SEGMENTS);
                f64::from(frame) + self.open + (self.close - self.open) * u
            })
            .collect()
    }
}

/// Default samples per pixel.
pub const DEFAULT_SPP: u32 = 64;
/// Default tile edge in pixels.
pub const DEFAULT_TILE_SIZE: u32 = 32;
/// Maximum path depth of the general configuration: an explicit integrator without
/// `max_depth`.
pub const DEFAULT_MAX_DEPTH: u32 = 16;
/// Bounces before Russian roulette starts in the general configuration (an explicit
/// integrator) and in render plans where later bounces matter (closed bright rooms,
/// refraction; open scenes start at 3, see tessera_scene's analysis). From there a path
/// survives each bounce with probability `min(0.95, max throughput)` (tessera_render's path
/// integrator), Mitsuba 3's policy. On the Cornell box, starting at 5 rather than 3 measured
/// 24% less noise for about 27% more render instructions (docs/benchmarks.md, "Russian
/// roulette").
pub const DEFAULT_RR_DEPTH: u32 = 5;
/// Default passes before the first adaptive decision (sequential) or of the pilot
/// (unbiased).
pub const DEFAULT_MIN_PASSES: u32 = 8;
/// Largest accepted `min_passes`.
pub const MAX_MIN_PASSES: u32 = 1024;

/// A setting that failed validation: which field, and what is wrong with it.
///
/// Its text is `"{field}: {problem}"`, e.g. `"spp: must be between 1 and 1048576, got 0"`;
/// the HTTP API sends it as an `invalid_field` error, the command line prints it.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{field}: {problem}")]
pub struct JobError {
    /// The field, e.g. `"spp"` or `"frames.end"`.
    pub field: String,
    /// What is wrong, e.g. `"must be between 1 and 1048576, got 0"`.
    pub problem: String,
}

impl JobError {
    /// An error of `field`.
    pub fn new(field: impl Into<String>, problem: impl fmt::Display) -> Self {
        Self {
            field: field.into(),
            problem: problem.to_string(),
        }
    }
}

/// What a job asks of the renderer before its scene is known: the integrator may be
/// `auto` and the depth may be left to the render plan. [`ValidatedJob::resolve`] turns it
/// into a [`RenderConfig`].
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct RenderRequest {
    /// The integrator asked for.
    pub integrator: IntegratorChoice,
    /// The MIS heuristic.
    pub mis: MisHeuristic,
    /// The sampler.
    pub sampler: SamplerKind,
    /// Job seed.
    pub seed: u64,
    /// Maximum number of bounces, 1..=[`MAX_DEPTH_LIMIT`], if given; otherwise the render
    /// plan's (with `auto`) or [`DEFAULT_MAX_DEPTH`].
    pub max_depth: Option<u32>,
}

/// Everything that decides the value of a sample besides the scene and the plan, resolved:
/// the integrator is concrete. The renderer renders with it, and `tessera-proto` carries
/// it to workers in the gRPC `RenderSettings` message.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RenderConfig {
    /// The integrator.
    pub integrator: Integrator,
    /// The MIS heuristic (path and direct).
    pub mis: MisHeuristic,
    /// The sampler.
    pub sampler: SamplerKind,
    /// Job seed.
    pub seed: u64,
    /// Maximum number of bounces, 1..=[`MAX_DEPTH_LIMIT`].
    pub max_depth: u32,
    /// Bounces before Russian roulette starts, 0..=[`MAX_DEPTH_LIMIT`].
    pub rr_depth: u32,
}

impl Default for RenderConfig {
    /// The general configuration: path, power, sobol, seed 0, depth 16, roulette after 3
    /// bounces.
    fn default() -> Self {
        Self {
            integrator: Integrator::Path,
            mis: MisHeuristic::Power,
            sampler: SamplerKind::Sobol,
            seed: 0,
            max_depth: DEFAULT_MAX_DEPTH,
            rr_depth: DEFAULT_RR_DEPTH,
        }
    }
}

impl RenderConfig {
    /// Checks the numeric ranges (the enums are valid by construction): `max_depth` in
    /// 1..=1024, `rr_depth` <= 1024, a cutoff threshold in (0, 1]. Errors name the field.
    pub fn validate(&self) -> Result<(), JobError> {
        if !(1..=MAX_DEPTH_LIMIT).contains(&self.max_depth) {
            return Err(range_error("max_depth", 1, MAX_DEPTH_LIMIT, self.max_depth));
        }
        if self.rr_depth > MAX_DEPTH_LIMIT {
            return Err(range_error("rr_depth", 0, MAX_DEPTH_LIMIT, self.rr_depth));
        }
        check_mis(self.mis)
    }
}

fn check_mis(mis: MisHeuristic) -> Result<(), JobError> {
    if let MisHeuristic::Cutoff(a) = mis {
        if !(a > 0.0 && a <= 1.0) {
            return Err(JobError::new(
                "mis",
                format_args!("cutoff threshold must be in (0, 1], got {a}"),
            ));
        }
    }
    Ok(())
}

/// An inclusive range of frame numbers, `{"start": 0, "end": 0}` by default (frame 0 only).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FrameRange {
    /// First frame.
    pub start: u32,
    /// Last frame (inclusive).
    pub end: u32,
}

impl FrameRange {
    /// Number of frames (0 if `end < start`, which validation rejects).
    pub fn count(&self) -> u64 {
        if self.end < self.start {
            0
        } else {
            u64::from(self.end - self.start) + 1
        }
    }

    /// The frame numbers in order.
    pub fn iter(&self) -> std::ops::RangeInclusive<u32> {
        self.start..=self.end
    }
}

fn default_spp() -> u32 {
    DEFAULT_SPP
}
fn default_tile_size() -> u32 {
    DEFAULT_TILE_SIZE
}
fn default_min_passes() -> u32 {
    DEFAULT_MIN_PASSES
}
fn default_integrator() -> String {
    IntegratorChoice::default().to_string()
}
fn default_mis() -> String {
    MisHeuristic::default().to_string()
}
fn default_sampler() -> String {
    SamplerKind::default().to_string()
}
fn default_adaptive() -> String {
    AdaptiveMode::default().to_string()
}
fn is_default_min_passes(v: &u32) -> bool {
    *v == DEFAULT_MIN_PASSES
}
fn default_fps() -> f64 {
    DEFAULT_FPS
}
fn is_default_fps(v: &f64) -> bool {
    *v == DEFAULT_FPS
}

/// A job as submitted: the body of `POST /api/v1/jobs`, and what `tessera render` builds
/// from its flags. The first stage of the two-stage configuration: nothing here has been
/// checked; [`JobSettings::validate`] produces the [`ValidatedJob`] everything downstream
/// works with.
///
/// Every field but `scene` has a default, and unknown fields are rejected (a typo must not
/// silently fall back to a default).
///
/// ```
/// let s: tessera_farm::job::JobSettings =
///     serde_json::from_str(r#"{"scene": "builtin:cornell-box", "spp": 16}"#).unwrap();
/// let job = s.validate().unwrap();
/// assert_eq!((job.spp, job.tile_size, job.frames.count()), (16, 32, 1));
/// ```
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JobSettings {
    /// `"builtin:NAME"` or the content hash returned by `POST /api/v1/scenes`.
    pub scene: String,
    /// The glTF camera to render from, by camera or node name; default: the scene's
    /// first camera.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera: Option<String>,
    /// Image width in pixels, 1..=16384; default: from the scene (keeping its aspect ratio
    /// when only `height` is given).
    #[serde(default)]
    pub width: Option<u32>,
    /// Image height in pixels, 1..=16384; default: from the scene.
    #[serde(default)]
    pub height: Option<u32>,
    /// Samples per pixel, 1..=1048576 (rounded up to whole passes). Default 64.
    #[serde(default = "default_spp")]
    pub spp: u32,
    /// `"auto"` (default), `"path"`, `"direct"`, `"bdpt"`, `"vcm"`, `"ppm"`, `"mlt"` or
    /// `"mnee"`.
    #[serde(default = "default_integrator")]
    pub integrator: String,
    /// `"balance"`, `"power"` (default), `"cutoff"`, `"cutoff:ALPHA"` or `"maximum"`.
    #[serde(default = "default_mis")]
    pub mis: String,
    /// `"sobol"` (default) or `"independent"`.
    #[serde(default = "default_sampler")]
    pub sampler: String,
    /// Job seed. Default 0.
    #[serde(default)]
    pub seed: u64,
    /// Maximum path depth, 1..=1024; default: the render plan's with `integrator` auto,
    /// 16 otherwise.
    #[serde(default)]
    pub max_depth: Option<u32>,
    /// Frames to render, inclusive, at most 100000. Default frame 0 only.
    #[serde(default)]
    pub frames: FrameRange,
    /// Frames per second: frame `F` shows the scene at `t = F / fps` seconds
    /// (ARCHITECTURE.md §8, "Time"), in (0, 1000000]. Default 24.
    #[serde(default = "default_fps", skip_serializing_if = "is_default_fps")]
    pub fps: f64,
    /// The glTF animation that plays, by name (or else by index); default: every
    /// animation of the file plays.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub animation: Option<String>,
    /// Motion blur: the shutter's opening and closing in frames relative to the frame,
    /// e.g. `[-0.25, 0.25]`, each within 1 frame; default none (every sample at the
    /// frame's time). Time is sampled only where the scene moves within the shutter.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub shutter: Option<Shutter>,
    /// Higher runs first; equal priorities run first come, first served. Default 0.
    #[serde(default)]
    pub priority: i32,
    /// Stop once the image error estimate (RMS relative error) is at most this, in (0, 1].
    #[serde(default)]
    pub target_error: Option<f64>,
    /// `"off"` (default), `"sequential"` or `"unbiased"` (ARCHITECTURE.md §3).
    #[serde(default = "default_adaptive")]
    pub adaptive: String,
    /// Passes before the first adaptive decision (sequential) or of the discarded pilot
    /// (unbiased), 2..=1024. Default 8.
    #[serde(
        default = "default_min_passes",
        skip_serializing_if = "is_default_min_passes"
    )]
    pub min_passes: u32,
    /// Stop after this many seconds of rendering, > 0.
    #[serde(default)]
    pub time_limit_seconds: Option<f64>,
    /// Tile edge in pixels, 4..=256. Default 32.
    #[serde(default = "default_tile_size")]
    pub tile_size: u32,
    /// A label for people, at most 200 characters, no control characters.
    #[serde(default)]
    pub name: Option<String>,
    /// Light from every direction rays leave the scene in: a uniform colour or an
    /// uploaded HDR image, with strength and rotation. Default none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub environment: Option<EnvironmentSettings>,
}

impl JobSettings {
    /// Settings for `scene` with every other field at its default.
    pub fn new(scene: impl Into<String>) -> Self {
        Self {
            scene: scene.into(),
            camera: None,
            width: None,
            height: None,
            spp: DEFAULT_SPP,
            integrator: default_integrator(),
            mis: default_mis(),
            sampler: default_sampler(),
            seed: 0,
            max_depth: None,
            frames: FrameRange::default(),
            fps: DEFAULT_FPS,
            animation: None,
            shutter: None,
            priority: 0,
            target_error: None,
            adaptive: default_adaptive(),
            min_passes: DEFAULT_MIN_PASSES,
            time_limit_seconds: None,
            tile_size: DEFAULT_TILE_SIZE,
            name: None,
            environment: None,
        }
    }

    /// Checks every field and parses the choices; the first problem found (in field
    /// order) is returned as a [`JobError`] naming the field, e.g.
    /// `"spp: must be between 1 and 1048576, got 0"`.
    ///
    /// When both `width` and `height` are given the frame plan is checked too (the total
    /// amount of work is bounded); otherwise that happens in [`ValidatedJob::resolve`] once
    /// the scene's resolution is known.
    pub fn validate(&self) -> Result<ValidatedJob, JobError> {
        let scene: SceneRef = parse_field("scene", &self.scene)?;
        if let Some(c) = &self.camera {
            check_label("camera", c, MAX_CAMERA_CHARS)?;
            if c.is_empty() {
                return Err(JobError::new("camera", "must not be empty"));
            }
        }
        for (field, value) in [("width", self.width), ("height", self.height)] {
            if let Some(v) = value {
                if !(1..=MAX_DIMENSION).contains(&v) {
                    return Err(range_error(field, 1, MAX_DIMENSION, v));
                }
            }
        }
        if !(1..=MAX_SPP).contains(&self.spp) {
            return Err(range_error("spp", 1, MAX_SPP, self.spp));
        }
        let render = RenderRequest {
            integrator: parse_field("integrator", &self.integrator)?,
            mis: parse_field("mis", &self.mis)?,
            sampler: parse_field("sampler", &self.sampler)?,
            seed: self.seed,
            max_depth: self.max_depth,
        };
        check_mis(render.mis)?;
        if let Some(d) = self.max_depth {
            if !(1..=MAX_DEPTH_LIMIT).contains(&d) {
                return Err(range_error("max_depth", 1, MAX_DEPTH_LIMIT, d));
            }
        }
        self.check_frames()?;
        if !(self.fps > 0.0 && self.fps <= MAX_FPS) {
            return Err(JobError::new(
                "fps",
                format_args!("must be in (0, {MAX_FPS}], got {}", self.fps),
            ));
        }
        if let Some(a) = &self.animation {
            check_label("animation", a, MAX_ANIMATION_CHARS)?;
            if a.is_empty() {
                return Err(JobError::new("animation", "must not be empty"));
            }
        }
        if let Some(s) = &self.shutter {
            s.check()?;
        }
        if let Some(e) = self.target_error {
            if !(e > 0.0 && e <= 1.0) {
                return Err(JobError::new(
                    "target_error",
                    format_args!("must be in (0, 1], got {e}"),
                ));
            }
        }
        let adaptive: AdaptiveMode = parse_field("adaptive", &self.adaptive)?;
        if adaptive != AdaptiveMode::Off && self.target_error.is_none() {
            return Err(JobError::new(
                "target_error",
                format_args!(
                    "adaptive {adaptive} needs a target error (the relative error at which \
                     pixels stop)"
                ),
            ));
        }
        if !(2..=MAX_MIN_PASSES).contains(&self.min_passes) {
            return Err(range_error(
                "min_passes",
                2,
                MAX_MIN_PASSES,
                self.min_passes,
            ));
        }
        if let Some(t) = self.time_limit_seconds {
            if !(t > 0.0 && t.is_finite()) {
                return Err(JobError::new(
                    "time_limit_seconds",
                    format_args!("must be a positive, finite number of seconds, got {t}"),
                ));
            }
        }
        if !(MIN_TILE_SIZE..=MAX_TILE_SIZE).contains(&self.tile_size) {
            return Err(range_error(
                "tile_size",
                MIN_TILE_SIZE,
                MAX_TILE_SIZE,
                self.tile_size,
            ));
        }
        if let Some(name) = &self.name {
            check_label("name", name, MAX_NAME_CHARS)?;
        }
        let environment = self
            .environment
            .as_ref()
            .map(EnvironmentSettings::validate)
            .transpose()?;
        let job = ValidatedJob {
            scene: JobScene {
                source: scene,
                camera: self.camera.clone(),
                fps: self.fps,
                animation: self.animation.clone(),
                shutter: self.shutter,
            },
            width: self.width,
            height: self.height,
            spp: self.spp,
            render,
            frames: self.frames,
            priority: self.priority,
            target_error: self.target_error,
            adaptive,
            min_passes: self.min_passes,
            time_limit_seconds: self.time_limit_seconds,
            tile_size: self.tile_size,
            name: self.name.clone(),
            environment,
        };
        if let (Some(w), Some(h)) = (job.width, job.height) {
            job.plan_for(job.render.integrator, w, h)?;
        }
        Ok(job)
    }

    fn check_frames(&self) -> Result<(), JobError> {
        if self.frames.end < self.frames.start {
            return Err(JobError::new(
                "frames.end",
                format_args!(
                    "must not be less than frames.start ({}), got {}",
                    self.frames.start, self.frames.end
                ),
            ));
        }
        if self.frames.count() > MAX_FRAMES {
            return Err(JobError::new(
                "frames",
                format_args!(
                    "at most {MAX_FRAMES} frames per job, got {} ({}..={})",
                    self.frames.count(),
                    self.frames.start,
                    self.frames.end
                ),
            ));
        }
        Ok(())
    }
}

/// A label for people: at most `max` characters, no control characters.
fn check_label(field: &str, value: &str, max: usize) -> Result<(), JobError> {
    let chars = value.chars().count();
    if chars > max {
        return Err(JobError::new(
            field,
            format_args!("must be at most {max} characters, got {chars}"),
        ));
    }
    if value.chars().any(char::is_control) {
        return Err(JobError::new(field, "must not contain control characters"));
    }
    Ok(())
}

/// `"{field}: must be between {min} and {max}, got {value}"`.
fn range_error(field: &str, min: u32, max: u32, value: u32) -> JobError {
    JobError::new(
        field,
        format_args!("must be between {min} and {max}, got {value}"),
    )
}

fn parse_field<T: FromStr<Err = String>>(field: &str, value: &str) -> Result<T, JobError> {
    value.parse().map_err(|e| JobError::new(field, e))
}

/// A job whose settings passed [`JobSettings::validate`]: the second stage of the two-stage
/// configuration. Construct it only through validation (or with the same checks).
#[derive(Debug, Clone, PartialEq)]
pub struct ValidatedJob {
    /// The scene, its camera and its clock (frames per second, animation, shutter).
    pub scene: JobScene,
    /// Requested image width; `None`: from the scene ([`resolve_resolution`]).
    pub width: Option<u32>,
    /// Requested image height; `None`: from the scene ([`resolve_resolution`]).
    pub height: Option<u32>,
    /// Samples per pixel, 1..=[`MAX_SPP`].
    pub spp: u32,
    /// How samples are to be computed.
    pub render: RenderRequest,
    /// Frames to render, `start <= end`, at most [`MAX_FRAMES`].
    pub frames: FrameRange,
    /// Scheduling priority (higher first).
    pub priority: i32,
    /// Target image error in (0, 1].
    pub target_error: Option<f64>,
    /// Adaptive stopping mode.
    pub adaptive: AdaptiveMode,
    /// Passes before the first adaptive decision or of the pilot, 2..=1024.
    pub min_passes: u32,
    /// Time limit in seconds, positive and finite.
    pub time_limit_seconds: Option<f64>,
    /// Tile edge in pixels, 4..=256.
    pub tile_size: u32,
    /// A label for people.
    pub name: Option<String>,
    /// The environment lighting the scene, if any.
    pub environment: Option<JobEnvironment>,
}

impl ValidatedJob {
    /// The frame plan of this job for the image size `width` x `height` when it is
    /// rendered with `integrator` (`auto` plans like path tracing):
    /// - `bdpt`, `vcm`, `ppm` and `mlt`: [`FramePlan::whole_frame`], one tile, because light
    ///   tracing splats anywhere on the film, merging reads the whole pass's photon map and
    ///   mlt's Markov chains wander over the whole frame (whether chosen by the plan or
    ///   asked for, adaptive or not; the photon map is rebuilt per pass inside the unit);
    ///   `path`, `direct` and `mnee` estimate each pixel on its own and tile;
    /// - adaptive stopping: [`adaptive_plan`], many short passes, since decisions fall
    ///   between passes (for the whole-frame techniques too, with the one whole-frame tile:
    ///   unbiased stopping needs a pilot of 8 passes and fresh ones after it, which
    ///   [`FramePlan::whole_frame`]'s 4 passes of 16 at 64 spp do not leave room for);
    /// - otherwise [`FramePlan::for_spp`] with this job's spp and tile size.
    ///
    /// Failures are errors of `width`, `height`, `tile_size` or `spp` (the last when the
    /// total work is too large; `width` when a bdpt frame is too large for one tile).
    pub fn plan_for(
        &self,
        integrator: IntegratorChoice,
        width: u32,
        height: u32,
    ) -> Result<FramePlan, JobError> {
        let whole_frame = match integrator {
            IntegratorChoice::Fixed(i) => i.whole_frame(),
            IntegratorChoice::Auto => false,
        };
        let plan = if whole_frame && self.adaptive != AdaptiveMode::Off {
            let tile = width.max(height).max(crate::plan::MIN_TILE_SIZE);
            adaptive_plan(width, height, self.spp, tile)
        } else if whole_frame {
            FramePlan::whole_frame(width, height, self.spp)
        } else if self.adaptive != AdaptiveMode::Off {
            adaptive_plan(width, height, self.spp, self.tile_size)
        } else {
            FramePlan::for_spp(width, height, self.spp, self.tile_size)
        };
        plan.map_err(|e| {
            let field = match &e {
                PlanError::Size { width, .. } if !(1..=MAX_DIMENSION).contains(width) => "width",
                PlanError::Size { .. } => "height",
                PlanError::WholeFrameTooLarge { .. } => "width",
                PlanError::TileSize(_) => "tile_size",
                PlanError::Spp { .. }
                | PlanError::SamplesPerPass(_)
                | PlanError::Passes(_)
                | PlanError::TooMuchWork { .. } => "spp",
            };
            JobError::new(field, e)
        })
    }

    /// The image size for a scene whose default resolution is `scene_default`; see
    /// [`resolve_resolution`].
    pub fn resolution(&self, scene_default: (u32, u32)) -> (u32, u32) {
        resolve_resolution(self.width, self.height, scene_default)
    }

    /// The adaptive policy's settings, if the job stops adaptively (ARCHITECTURE.md §3).
    pub fn adaptive_settings(&self) -> Option<AdaptiveSettings> {
        (self.adaptive != AdaptiveMode::Off).then(|| AdaptiveSettings {
            mode: self.adaptive,
            target_error: self.target_error.unwrap_or(1.0),
            min_passes: self.min_passes,
            ..AdaptiveSettings::default()
        })
    }

    /// Whether the job stops early at all: adaptive stopping, a target error or a time
    /// limit. Such jobs record their stopping settings in the EXR header.
    pub fn stops_early(&self) -> bool {
        self.adaptive != AdaptiveMode::Off
            || self.target_error.is_some()
            || self.time_limit_seconds.is_some()
    }

    /// The canonical raw form: every field explicit, choices in their canonical spelling.
    /// `to_settings().validate()` gives back an equal job; the server can store and echo
    /// this.
    pub fn to_settings(&self) -> JobSettings {
        JobSettings {
            scene: self.scene.source.to_string(),
            camera: self.scene.camera.clone(),
            width: self.width,
            height: self.height,
            spp: self.spp,
            integrator: self.render.integrator.to_string(),
            mis: self.render.mis.to_string(),
            sampler: self.render.sampler.to_string(),
            seed: self.render.seed,
            max_depth: self.render.max_depth,
            frames: self.frames,
            fps: self.scene.fps,
            animation: self.scene.animation.clone(),
            shutter: self.scene.shutter,
            priority: self.priority,
            target_error: self.target_error,
            adaptive: self.adaptive.to_string(),
            min_passes: self.min_passes,
            time_limit_seconds: self.time_limit_seconds,
            tile_size: self.tile_size,
            name: self.name.clone(),
            environment: self.environment.as_ref().map(JobEnvironment::to_settings),
        }
    }
}

/// The image size of a job: both requested dimensions if given; one of them with the
/// other following the scene's aspect ratio (rounded down, at least 1); or the scene's
/// default.
pub fn resolve_resolution(
    width: Option<u32>,
    height: Option<u32>,
    scene_default: (u32, u32),
) -> (u32, u32) {
    let (dw, dh) = (
        u64::from(scene_default.0.max(1)),
        u64::from(scene_default.1.max(1)),
    );
    let clamp = |v: u64| v.clamp(1, u64::from(u32::MAX)) as u32;
    match (width, height) {
        (Some(w), Some(h)) => (w, h),
        (Some(w), None) => (w, clamp(u64::from(w) * dh / dw)),
        (None, Some(h)) => (clamp(u64::from(h) * dw / dh), h),
        (None, None) => scene_default,
    }
}
