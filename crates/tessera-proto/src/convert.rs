//! Checked conversions between wire messages and domain types.

use std::fmt;

use tessera_farm::job::{
    EnvironmentSource, Integrator, JobEnvironment, JobScene, MisHeuristic, RenderConfig,
    SamplerKind, SceneRef, Shutter, DEFAULT_FPS, MAX_ANIMATION_CHARS, MAX_CAMERA_CHARS,
    MAX_ENVIRONMENT_RADIANCE, MAX_ENVIRONMENT_STRENGTH, MAX_FPS,
};
use tessera_farm::{
    FramePlan, PixelRuns, PlanError, UnitResult, WorkUnit, MAX_DIMENSION, MAX_PASSES,
};
use tessera_farm::{MAX_TILE_SIZE, MAX_WHOLE_FRAME_PIXELS, MIN_TILE_SIZE};

use crate::v1;

/// Largest tile index any valid plan can have: a 16384 x 16384 image cut into 4-pixel
/// tiles has 4096 x 4096 tiles.
pub const MAX_TILE_INDEX: u32 = {
    let per_side = MAX_DIMENSION.div_ceil(MIN_TILE_SIZE);
    per_side * per_side - 1
};

/// A wire message failed validation: which field (a dotted path such as `"plan.width"`)
/// and why.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ProtoError {
    /// The offending field, as a dotted path from the converted message.
    pub field: String,
    /// What is wrong with it.
    pub reason: String,
}

impl ProtoError {
    /// An error for `field`.
    pub fn new(field: impl Into<String>, reason: impl fmt::Display) -> Self {
        Self {
            field: field.into(),
            reason: reason.to_string(),
        }
    }

    /// The same error seen from the enclosing message: `field` becomes `parent.field`.
    pub fn within(mut self, parent: &str) -> Self {
        self.field = format!("{parent}.{}", self.field);
        self
    }

    fn missing(field: &str) -> Self {
        Self::new(field, "missing")
    }
}

impl fmt::Display for ProtoError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}: {}", self.field, self.reason)
    }
}

impl std::error::Error for ProtoError {}

impl From<ProtoError> for tonic::Status {
    /// `INVALID_ARGUMENT` with the message `"field: reason"`.
    fn from(e: ProtoError) -> Self {
        tonic::Status::invalid_argument(e.to_string())
    }
}

// ---------------------------------------------------------------------------------------
// FramePlan

impl From<&FramePlan> for v1::FramePlan {
    fn from(p: &FramePlan) -> Self {
        Self {
            width: p.width,
            height: p.height,
            tile_size: p.tile_size,
            samples_per_pass: p.samples_per_pass,
            passes: p.passes,
        }
    }
}

impl From<FramePlan> for v1::FramePlan {
    fn from(p: FramePlan) -> Self {
        Self::from(&p)
    }
}

impl TryFrom<v1::FramePlan> for FramePlan {
    type Error = ProtoError;

    /// Validates with [`FramePlan::new`]; the error names the field out of range
    /// (`passes` when the total amount of work is too large).
    fn try_from(p: v1::FramePlan) -> Result<Self, ProtoError> {
        FramePlan::new(p.width, p.height, p.tile_size, p.samples_per_pass, p.passes).map_err(|e| {
            let field = match &e {
                PlanError::Size { width, .. } if !(1..=MAX_DIMENSION).contains(width) => "width",
                PlanError::Size { .. } => "height",
                PlanError::TileSize(_) | PlanError::WholeFrameTooLarge { .. } => "tile_size",
                PlanError::SamplesPerPass(_) | PlanError::Spp { .. } => "samples_per_pass",
                PlanError::Passes(_) | PlanError::TooMuchWork { .. } => "passes",
            };
            ProtoError::new(field, e)
        })
    }
}

// ---------------------------------------------------------------------------------------
// WorkUnit

impl From<&WorkUnit> for v1::WorkUnit {
    fn from(u: &WorkUnit) -> Self {
        Self {
            frame: u.frame,
            tile: u.tile,
            first_pass: u.first_pass,
            pass_count: u.pass_count,
        }
    }
}

impl From<WorkUnit> for v1::WorkUnit {
    fn from(u: WorkUnit) -> Self {
        Self::from(&u)
    }
}

impl TryFrom<v1::WorkUnit> for WorkUnit {
    type Error = ProtoError;

    /// Checks what can be checked without the plan: `pass_count >= 1`, the passes end
    /// within the largest plan (65536 passes) and the tile index is below
    /// [`MAX_TILE_INDEX`]. Whether the unit belongs to a given plan is checked by
    /// [`LeasedUnit`] and by `UnitResult::validate`.
    fn try_from(u: v1::WorkUnit) -> Result<Self, ProtoError> {
        if u.pass_count == 0 {
            return Err(ProtoError::new("pass_count", "must be at least 1, got 0"));
        }
        let end = u64::from(u.first_pass) + u64::from(u.pass_count);
        if end > u64::from(MAX_PASSES) {
            return Err(ProtoError::new(
                "pass_count",
                format_args!(
                    "passes {}..{end} exceed the limit of {MAX_PASSES} passes",
                    u.first_pass
                ),
            ));
        }
        if u.tile > MAX_TILE_INDEX {
            return Err(ProtoError::new(
                "tile",
                format_args!("must be at most {MAX_TILE_INDEX}, got {}", u.tile),
            ));
        }
        Ok(WorkUnit {
            frame: u.frame,
            tile: u.tile,
            first_pass: u.first_pass,
            pass_count: u.pass_count,
        })
    }
}

/// Checks that `unit` is a unit of `plan`: its tile exists and its passes lie within the
/// plan's. Field names are relative to the unit.
fn check_unit_in_plan(unit: &WorkUnit, plan: &FramePlan) -> Result<(), ProtoError> {
    if unit.tile >= plan.tile_count() {
        return Err(ProtoError::new(
            "tile",
            format_args!(
                "tile {} is not in the plan, which has {} tiles",
                unit.tile,
                plan.tile_count()
            ),
        ));
    }
    if unit.end_pass() > u64::from(plan.passes) {
        return Err(ProtoError::new(
            "pass_count",
            format_args!(
                "passes {}..{} exceed the plan's {} passes",
                unit.first_pass,
                unit.end_pass(),
                plan.passes
            ),
        ));
    }
    Ok(())
}

// ---------------------------------------------------------------------------------------
// UnitResult <-> SubmitResultRequest

impl v1::SubmitResultRequest {
    /// The request submitting `result`, rendered in `render_seconds` under lease
    /// `lease_id` by worker `worker_id`. The pass means are flattened to r, g, b
    /// interleaved floats.
    pub fn from_result(
        worker_id: u64,
        lease_id: u64,
        result: &UnitResult,
        render_seconds: f64,
    ) -> Self {
        Self {
            worker_id,
            lease_id,
            unit: Some(result.unit.into()),
            width: result.width,
            height: result.height,
            pass_means: means_to_bytes(result.pass_means.as_flattened()),
            render_seconds,
            job_id: 0,
            rejected_samples: result.rejected_samples,
            traced_pixel_passes: 0,
            fence: Vec::new(),
            bias: result.bias.as_deref().map_or_else(Vec::new, means_to_bytes),
        }
    }

    /// Checks the fields other than the pass means themselves and returns the unit.
    fn check_shape(&self) -> Result<WorkUnit, ProtoError> {
        let unit: WorkUnit = self
            .unit
            .ok_or_else(|| ProtoError::missing("unit"))?
            .try_into()
            .map_err(|e: ProtoError| e.within("unit"))?;
        for (field, v) in [("width", self.width), ("height", self.height)] {
            if !(1..=MAX_TILE_SIZE).contains(&v) {
                // A whole-frame tile (bdpt) may be larger, within its pixel bound.
                let pixels = u64::from(self.width) * u64::from(self.height);
                if (1..=MAX_DIMENSION).contains(&v) && pixels <= MAX_WHOLE_FRAME_PIXELS {
                    continue;
                }
                return Err(ProtoError::new(
                    field,
                    format_args!(
                        "must be between 1 and {MAX_TILE_SIZE} (a tile), or up to {MAX_DIMENSION} for a whole-frame tile of at most {MAX_WHOLE_FRAME_PIXELS} pixels, got {v}"
                    ),
                ));
            }
        }
        let bytes = self.pass_means.len();
        if !bytes.is_multiple_of(12) {
            return Err(ProtoError::new(
                "pass_means",
                format_args!("has {bytes} bytes, not a multiple of 12 (r, g, b as 4-byte floats)"),
            ));
        }
        let len = bytes / 4;
        let expected =
            3 * u64::from(unit.pass_count) * u64::from(self.width) * u64::from(self.height);
        if len as u64 != expected {
            return Err(ProtoError::new(
                "pass_means",
                format_args!(
                    "has {len} values, expected 3 x {} passes x {} x {} pixels = {expected}",
                    unit.pass_count, self.width, self.height
                ),
            ));
        }
        let cells = u64::from(unit.pass_count) * u64::from(self.width) * u64::from(self.height);
        if !self.bias.is_empty() && self.bias.len() as u64 != 4 * cells {
            return Err(ProtoError::new(
                "bias",
                format_args!(
                    "has {} bytes, expected none or 4 x {} passes x {} x {} pixels = {}",
                    self.bias.len(),
                    unit.pass_count,
                    self.width,
                    self.height,
                    4 * cells
                ),
            ));
        }
        if self.traced_pixel_passes > cells {
            return Err(ProtoError::new(
                "traced_pixel_passes",
                format_args!(
                    "is {}, more than the unit's {cells} pixel-passes",
                    self.traced_pixel_passes
                ),
            ));
        }
        if !(self.render_seconds >= 0.0 && self.render_seconds.is_finite()) {
            return Err(ProtoError::new(
                "render_seconds",
                format_args!("must be finite and >= 0, got {}", self.render_seconds),
            ));
        }
        Ok(unit)
    }
}

/// The little-endian bytes of `values` (the wire form of `SubmitResultRequest.pass_means`).
pub fn means_to_bytes(values: &[f32]) -> Vec<u8> {
    let mut out = vec![0u8; 4 * values.len()];
    for (b, v) in out.chunks_exact_mut(4).zip(values) {
        b.copy_from_slice(&v.to_le_bytes());
    }
    out
}

/// The floats of `bytes` (4 little-endian bytes each; a trailing partial value is
/// ignored): the inverse of [`means_to_bytes`].
pub fn means_from_bytes(bytes: &[u8]) -> Vec<f32> {
    bytes
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect()
}

/// Pixels `[r, g, b]` from the wire bytes of `pass_means` (a multiple of 12 bytes, which
/// `check_shape` has verified).
fn unflatten(bytes: &[u8]) -> Vec<[f32; 3]> {
    let f = |b: &[u8]| f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
    bytes
        .chunks_exact(12)
        .map(|c| [f(&c[0..4]), f(&c[4..8]), f(&c[8..12])])
        .collect()
}

impl v1::SubmitResultRequest {
    /// The pass means as floats (see [`means_from_bytes`]).
    pub fn means(&self) -> Vec<f32> {
        means_from_bytes(&self.pass_means)
    }

    /// Replaces the pass means by `values` (see [`means_to_bytes`]).
    pub fn set_means(&mut self, values: &[f32]) {
        self.pass_means = means_to_bytes(values);
    }
}

impl TryFrom<&v1::SubmitResultRequest> for UnitResult {
    type Error = ProtoError;

    /// Checks the message's own consistency: the unit (as for [`WorkUnit`]), `width` and
    /// `height` in 1..=256, `pass_means` holding exactly `3 * pass_count * width * height`
    /// values, `bias` empty or holding `pass_count * width * height` values,
    /// `render_seconds` finite and non-negative. The values themselves (finite,
    /// non-negative) and the fit to the plan are checked by `UnitResult::validate`, which
    /// the merge runs before anything is merged.
    fn try_from(r: &v1::SubmitResultRequest) -> Result<Self, ProtoError> {
        let unit = r.check_shape()?;
        Ok(UnitResult {
            unit,
            width: r.width,
            height: r.height,
            pass_means: unflatten(&r.pass_means),
            rejected_samples: r.rejected_samples,
            bias: (!r.bias.is_empty()).then(|| means_from_bytes(&r.bias)),
        })
    }
}

impl TryFrom<v1::SubmitResultRequest> for UnitResult {
    type Error = ProtoError;

    /// As the conversion from a reference.
    fn try_from(r: v1::SubmitResultRequest) -> Result<Self, ProtoError> {
        UnitResult::try_from(&r)
    }
}

// ---------------------------------------------------------------------------------------
// RenderSettings <-> RenderConfig

impl From<Integrator> for v1::Integrator {
    fn from(i: Integrator) -> Self {
        match i {
            Integrator::Path => Self::Path,
            Integrator::Direct => Self::Direct,
            Integrator::Bdpt => Self::Bdpt,
            Integrator::Vcm => Self::Vcm,
            Integrator::Ppm => Self::Ppm,
            Integrator::Mlt => Self::Mlt,
            Integrator::Mnee => Self::Mnee,
        }
    }
}

impl From<SamplerKind> for v1::Sampler {
    fn from(s: SamplerKind) -> Self {
        match s {
            SamplerKind::Sobol => Self::Sobol,
            SamplerKind::Independent => Self::Independent,
        }
    }
}

impl From<&RenderConfig> for v1::RenderSettings {
    fn from(c: &RenderConfig) -> Self {
        let (mis, alpha) = match c.mis {
            MisHeuristic::Balance => (v1::MisHeuristic::Balance, 0.0),
            MisHeuristic::Power => (v1::MisHeuristic::Power, 0.0),
            MisHeuristic::Cutoff(a) => (v1::MisHeuristic::Cutoff, a),
            MisHeuristic::Maximum => (v1::MisHeuristic::Maximum, 0.0),
        };
        Self {
            integrator: v1::Integrator::from(c.integrator).into(),
            mis: mis.into(),
            mis_cutoff_alpha: alpha,
            sampler: v1::Sampler::from(c.sampler).into(),
            seed: c.seed,
            max_depth: c.max_depth,
            rr_depth: c.rr_depth,
        }
    }
}

impl From<RenderConfig> for v1::RenderSettings {
    fn from(c: RenderConfig) -> Self {
        Self::from(&c)
    }
}

/// Decodes an enum field: unknown values and the UNSPECIFIED zero are errors.
fn enum_field<E: TryFrom<i32> + PartialEq>(
    field: &str,
    value: i32,
    unspecified: E,
) -> Result<E, ProtoError> {
    match E::try_from(value) {
        Ok(e) if e == unspecified => Err(ProtoError::new(field, "not set (UNSPECIFIED)")),
        Ok(e) => Ok(e),
        Err(_) => Err(ProtoError::new(
            field,
            format_args!("unknown value {value} (a newer peer?)"),
        )),
    }
}

impl TryFrom<v1::RenderSettings> for RenderConfig {
    type Error = ProtoError;

    /// Rejects UNSPECIFIED and unknown enum values (guessing would break determinism), a
    /// cutoff threshold outside (0, 1], `max_depth` outside 1..=1024 and `rr_depth` above
    /// 1024.
    fn try_from(s: v1::RenderSettings) -> Result<Self, ProtoError> {
        let integrator = match enum_field("integrator", s.integrator, v1::Integrator::Unspecified)?
        {
            // The coordinator resolves `auto` against the scene before leasing: a lease
            // that still says auto would make every worker guess.
            v1::Integrator::Auto => {
                return Err(ProtoError::new(
                    "integrator",
                    "auto is resolved by the coordinator and never leased",
                ))
            }
            v1::Integrator::Path => Integrator::Path,
            v1::Integrator::Direct => Integrator::Direct,
            v1::Integrator::Bdpt => Integrator::Bdpt,
            v1::Integrator::Vcm => Integrator::Vcm,
            v1::Integrator::Ppm => Integrator::Ppm,
            v1::Integrator::Mlt => Integrator::Mlt,
            v1::Integrator::Mnee => Integrator::Mnee,
            v1::Integrator::Unspecified => unreachable!("rejected by enum_field"),
        };
        let mis = match enum_field("mis", s.mis, v1::MisHeuristic::Unspecified)? {
            v1::MisHeuristic::Balance => MisHeuristic::Balance,
            v1::MisHeuristic::Power => MisHeuristic::Power,
            v1::MisHeuristic::Maximum => MisHeuristic::Maximum,
            v1::MisHeuristic::Cutoff => {
                let a = s.mis_cutoff_alpha;
                if !(a > 0.0 && a <= 1.0) {
                    return Err(ProtoError::new(
                        "mis_cutoff_alpha",
                        format_args!("must be in (0, 1] with the cutoff heuristic, got {a}"),
                    ));
                }
                MisHeuristic::Cutoff(a)
            }
            v1::MisHeuristic::Unspecified => unreachable!("rejected by enum_field"),
        };
        let sampler = match enum_field("sampler", s.sampler, v1::Sampler::Unspecified)? {
            v1::Sampler::Sobol => SamplerKind::Sobol,
            v1::Sampler::Independent => SamplerKind::Independent,
            v1::Sampler::Unspecified => unreachable!("rejected by enum_field"),
        };
        let config = RenderConfig {
            integrator,
            mis,
            sampler,
            seed: s.seed,
            max_depth: s.max_depth,
            rr_depth: s.rr_depth,
        };
        config
            .validate()
            .map_err(|e| ProtoError::new(e.field, e.problem))?;
        Ok(config)
    }
}

// ---------------------------------------------------------------------------------------
// Lease

/// A validated [`v1::Lease`]: one leased work unit and everything needed to render it.
#[derive(Debug, Clone, PartialEq)]
pub struct LeasedUnit {
    /// The lease id (fencing token).
    pub lease_id: u64,
    /// The lease deadline, Unix milliseconds.
    pub deadline_unix_ms: u64,
    /// The job.
    pub job_id: u64,
    /// The job's scene, its camera and its clock (the wire's `scene_hash`, `camera`,
    /// `fps`, `animation` and `shutter`).
    pub scene: JobScene,
    /// How samples are computed.
    pub settings: RenderConfig,
    /// The job's frame plan.
    pub plan: FramePlan,
    /// The unit to render; a unit of `plan`.
    pub unit: WorkUnit,
    /// The pixels of the unit's tile to trace (adaptive jobs, ARCHITECTURE.md §3); `None`: every
    /// pixel. Checked against the tile: canonical runs inside it.
    pub wanted: Option<PixelRuns>,
    /// The lease's seal (`Lease.fence`): opaque to the worker, which sends it back with
    /// the result (`SubmitResultRequest.fence`). At most [`MAX_FENCE_BYTES`].
    pub fence: Vec<u8>,
    /// The job's environment (`Lease.environment`); `None`: the scene's own lights only.
    pub environment: Option<JobEnvironment>,
}

/// The longest `Lease.fence` / `SubmitResultRequest.fence` accepted: the coordinator's
/// seal is an HMAC-SHA256 (32 bytes); anything much longer is not one.
pub const MAX_FENCE_BYTES: usize = 64;

impl From<&LeasedUnit> for v1::Lease {
    fn from(l: &LeasedUnit) -> Self {
        Self {
            lease_id: l.lease_id,
            deadline_unix_ms: l.deadline_unix_ms,
            job_id: l.job_id,
            scene_hash: l.scene.source.to_string(),
            camera: l.scene.camera.clone().unwrap_or_default(),
            fps: l.scene.fps,
            animation: l.scene.animation.clone().unwrap_or_default(),
            shutter: l.scene.shutter.map(|s| v1::Shutter {
                open: s.open,
                close: s.close,
            }),
            settings: Some((&l.settings).into()),
            plan: Some((&l.plan).into()),
            unit: Some((&l.unit).into()),
            wanted: l.wanted.as_ref().map(|w| v1::PixelRuns { runs: w.flat() }),
            fence: l.fence.clone(),
            environment: l.environment.as_ref().map(Into::into),
        }
    }
}

impl From<LeasedUnit> for v1::Lease {
    fn from(l: LeasedUnit) -> Self {
        Self::from(&l)
    }
}

impl TryFrom<v1::Lease> for LeasedUnit {
    type Error = ProtoError;

    /// Validates every part (field names are dotted paths such as `"plan.width"`) and that
    /// the unit lies within the plan.
    fn try_from(l: v1::Lease) -> Result<Self, ProtoError> {
        let scene: SceneRef = l
            .scene_hash
            .parse()
            .map_err(|e| ProtoError::new("scene_hash", e))?;
        let camera = match l.camera.as_str() {
            "" => None,
            c if c.chars().count() > MAX_CAMERA_CHARS || c.chars().any(char::is_control) => {
                return Err(ProtoError::new(
                    "camera",
                    format_args!(
                        "must be at most {MAX_CAMERA_CHARS} characters without control characters"
                    ),
                ))
            }
            c => Some(c.to_owned()),
        };
        let fps = match l.fps {
            0.0 => DEFAULT_FPS,
            f if f > 0.0 && f <= MAX_FPS => f,
            f => {
                return Err(ProtoError::new(
                    "fps",
                    format_args!("must be in (0, {MAX_FPS}], got {f}"),
                ))
            }
        };
        let animation = match l.animation.as_str() {
            "" => None,
            a if a.chars().count() > MAX_ANIMATION_CHARS || a.chars().any(char::is_control) => {
                return Err(ProtoError::new(
                    "animation",
                    format_args!(
                        "must be at most {MAX_ANIMATION_CHARS} characters without control characters"
                    ),
                ))
            }
            a => Some(a.to_owned()),
        };
        let shutter = match l.shutter {
            None => None,
            Some(s) => {
                let s = Shutter {
                    open: s.open,
                    close: s.close,
                };
                s.check()
                    .map_err(|e| ProtoError::new("shutter", e.problem))?;
                Some(s)
            }
        };
        let settings: RenderConfig = l
            .settings
            .ok_or_else(|| ProtoError::missing("settings"))?
            .try_into()
            .map_err(|e: ProtoError| e.within("settings"))?;
        let plan: FramePlan = l
            .plan
            .ok_or_else(|| ProtoError::missing("plan"))?
            .try_into()
            .map_err(|e: ProtoError| e.within("plan"))?;
        let unit: WorkUnit = l
            .unit
            .ok_or_else(|| ProtoError::missing("unit"))?
            .try_into()
            .map_err(|e: ProtoError| e.within("unit"))?;
        check_unit_in_plan(&unit, &plan).map_err(|e| e.within("unit"))?;
        // An empty list means every pixel, like an absent one (the field's contract).
        let wanted = match l.wanted {
            Some(w) if !w.runs.is_empty() => Some(
                PixelRuns::from_flat(&w.runs, plan.tile(unit.tile).pixel_count())
                    .map_err(|e| ProtoError::new("wanted.runs", e))?,
            ),
            _ => None,
        };
        if l.fence.len() > MAX_FENCE_BYTES {
            return Err(ProtoError::new(
                "fence",
                format_args!(
                    "must be at most {MAX_FENCE_BYTES} bytes, got {}",
                    l.fence.len()
                ),
            ));
        }
        let environment = l
            .environment
            .map(JobEnvironment::try_from)
            .transpose()
            .map_err(|e| e.within("environment"))?;
        Ok(Self {
            lease_id: l.lease_id,
            deadline_unix_ms: l.deadline_unix_ms,
            job_id: l.job_id,
            scene: JobScene {
                source: scene,
                camera,
                fps,
                animation,
                shutter,
            },
            settings,
            plan,
            unit,
            wanted,
            fence: l.fence,
            environment,
        })
    }
}

impl From<&JobEnvironment> for v1::Environment {
    fn from(e: &JobEnvironment) -> Self {
        let (image_hash, colour) = match &e.source {
            EnvironmentSource::Colour(c) => (String::new(), c.to_vec()),
            EnvironmentSource::Image(h) => (h.clone(), Vec::new()),
        };
        Self {
            image_hash,
            colour,
            strength: e.strength,
            rotation_degrees: e.rotation_degrees,
        }
    }
}

impl TryFrom<v1::Environment> for JobEnvironment {
    type Error = ProtoError;

    /// Checks the ranges the job setting is validated with; the floats cross the wire
    /// as they are, so the worker lights the scene with exactly the job's values.
    fn try_from(e: v1::Environment) -> Result<Self, ProtoError> {
        let source = if e.image_hash.is_empty() {
            let ok = |c: &f32| c.is_finite() && (0.0..=MAX_ENVIRONMENT_RADIANCE as f32).contains(c);
            match e.colour[..] {
                [r, g, b] if [r, g, b].iter().all(ok) => EnvironmentSource::Colour([r, g, b]),
                _ => {
                    return Err(ProtoError::new(
                        "colour",
                        format_args!(
                            "must be 3 values in [0, {MAX_ENVIRONMENT_RADIANCE}] without an \
                             image_hash, got {:?}",
                            e.colour
                        ),
                    ))
                }
            }
        } else {
            let h = &e.image_hash;
            if h.len() != 64 || !h.bytes().all(|b| matches!(b, b'0'..=b'9' | b'a'..=b'f')) {
                return Err(ProtoError::new(
                    "image_hash",
                    "must be 64 lowercase hex digits",
                ));
            }
            if !e.colour.is_empty() {
                return Err(ProtoError::new(
                    "colour",
                    "must be empty with an image_hash",
                ));
            }
            EnvironmentSource::Image(h.clone())
        };
        let s = e.strength;
        if !(s.is_finite() && (0.0..=MAX_ENVIRONMENT_STRENGTH as f32).contains(&s)) {
            return Err(ProtoError::new(
                "strength",
                format_args!("must be in [0, {MAX_ENVIRONMENT_STRENGTH}], got {s}"),
            ));
        }
        let r = e.rotation_degrees;
        if !(r.is_finite() && r.abs() <= 360.0) {
            return Err(ProtoError::new(
                "rotation_degrees",
                format_args!("must be in [-360, 360], got {r}"),
            ));
        }
        Ok(Self {
            source,
            strength: s,
            rotation_degrees: r,
        })
    }
}

#[cfg(test)]
mod tests;
