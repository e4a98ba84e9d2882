//! Job submission: the raw settings as submitted ([`JobSettings`]) and their validated form
//! ([`ValidatedJob`]).

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Deserializer, Serialize, Serializer};
use tessera_farm::{
    FramePlan, PlanError, MAX_AUTO_SAMPLES_PER_PASS, MAX_DIMENSION, MAX_PASSES, MAX_TILE_SIZE,
    MIN_TILE_SIZE,
};

use crate::error::ApiError;

/// Largest accepted samples per pixel (what [`FramePlan::for_spp`] can plan).
pub const MAX_SPP: u32 = 1_048_576;
const _: () = assert!(MAX_SPP == MAX_AUTO_SAMPLES_PER_PASS * MAX_PASSES);
/// Largest accepted `max_depth`.
pub const MAX_DEPTH_LIMIT: u32 = 1024;
/// Most frames one job may render.
pub const MAX_FRAMES: u64 = 100_000;
/// Longest accepted job name, in characters.
pub const MAX_NAME_CHARS: usize = 200;
/// Longest accepted built-in scene name, in characters.
pub const MAX_BUILTIN_NAME_CHARS: usize = 64;

/// Default samples per pixel (as `tessera render`).
pub const DEFAULT_SPP: u32 = 64;
/// Default tile edge in pixels (as `tessera render`).
pub const DEFAULT_TILE_SIZE: u32 = 32;
/// Default maximum path depth (as `tessera render`).
pub const DEFAULT_MAX_DEPTH: u32 = 16;
/// Bounces before Russian roulette starts (as `tessera render`).
pub const DEFAULT_RR_DEPTH: u32 = 3;
/// Threshold of the cutoff heuristic when `mis` is plain `"cutoff"`.
pub const DEFAULT_CUTOFF_ALPHA: f32 = 0.1;

/// Implements `Serialize`/`Deserialize` as the type's string form (`Display`/`FromStr`).
macro_rules! string_serde {
    ($t:ty) => {
        impl Serialize for $t {
            fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
                s.collect_str(self)
            }
        }
        impl<'de> Deserialize<'de> for $t {
            fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
                let s = String::deserialize(d)?;
                s.parse().map_err(serde::de::Error::custom)
            }
        }
    };
}

/// A reference to a scene: built into every worker, or uploaded and stored by content hash.
///
/// Its string form is `"builtin:NAME"` or the 64 lowercase hex digits of the SHA-256 of the
/// scene bytes (as returned by `POST /api/v1/scenes`). Parsing accepts upper-case hex and
/// normalizes it.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub enum SceneRef {
    /// A built-in scene, e.g. `Builtin("cornell-box")` for `"builtin:cornell-box"`.
    Builtin(String),
    /// An uploaded scene: lowercase hex SHA-256 of its bytes.
    Hash(String),
}

impl SceneRef {
    /// The string form, `"builtin:NAME"` or the hex hash.
    pub fn as_wire(&self) -> String {
        self.to_string()
    }

    /// The content hash of an uploaded scene; `None` for a built-in one.
    pub fn hash(&self) -> Option<&str> {
        match self {
            Self::Hash(h) => Some(h),
            Self::Builtin(_) => None,
        }
    }

    /// Whether `s` is 64 hex digits.
    fn is_sha256_hex(s: &str) -> bool {
        s.len() == 64 && s.bytes().all(|b| b.is_ascii_hexdigit())
    }
}

impl FromStr for SceneRef {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        if s.is_empty() {
            return Err("must not be empty".into());
        }
        if let Some(name) = s.strip_prefix("builtin:") {
            let ok = !name.is_empty()
                && name.chars().count() <= MAX_BUILTIN_NAME_CHARS
                && name
                    .bytes()
                    .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'-' | b'_' | b'.'));
            if !ok {
                return Err(format!(
                    "built-in scene name {name:?} is invalid: expected 1 to \
                     {MAX_BUILTIN_NAME_CHARS} letters, digits, '-', '_' or '.'"
                ));
            }
            return Ok(Self::Builtin(name.to_owned()));
        }
        if Self::is_sha256_hex(s) {
            return Ok(Self::Hash(s.to_ascii_lowercase()));
        }
        Err(format!(
            "expected \"builtin:NAME\" or the 64-hex-digit hash of an uploaded scene, got {s:?}"
        ))
    }
}

impl fmt::Display for SceneRef {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Builtin(name) => write!(f, "builtin:{name}"),
            Self::Hash(h) => f.write_str(h),
        }
    }
}

string_serde!(SceneRef);

/// The light transport algorithm requested for a job.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum IntegratorChoice {
    /// Chosen from the scene's effect analysis (DESIGN §4). The default.
    #[default]
    Auto,
    /// Path tracing with next-event estimation and MIS.
    Path,
    /// Direct lighting only.
    Direct,
    /// Bidirectional path tracing.
    Bdpt,
}

impl IntegratorChoice {
    /// The string form: `"auto"`, `"path"`, `"direct"` or `"bdpt"`.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Auto => "auto",
            Self::Path => "path",
            Self::Direct => "direct",
            Self::Bdpt => "bdpt",
        }
    }
}

impl FromStr for IntegratorChoice {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "auto" => Ok(Self::Auto),
            "path" => Ok(Self::Path),
            "direct" => Ok(Self::Direct),
            "bdpt" => Ok(Self::Bdpt),
            _ => Err(format!(
                "expected one of \"auto\", \"path\", \"direct\", \"bdpt\", got {s:?}"
            )),
        }
    }
}

impl fmt::Display for IntegratorChoice {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

string_serde!(IntegratorChoice);

/// The MIS weighting heuristic requested for a job.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum MisChoice {
    /// Balance heuristic.
    Balance,
    /// Power heuristic (exponent 2). The default.
    #[default]
    Power,
    /// Cutoff heuristic with threshold alpha in (0, 1]; `"cutoff"` alone means
    /// [`DEFAULT_CUTOFF_ALPHA`].
    Cutoff(f32),
    /// Maximum heuristic (`"max"` is accepted as an alias).
    Maximum,
}

impl FromStr for MisChoice {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "balance" => Ok(Self::Balance),
            "power" => Ok(Self::Power),
            "maximum" | "max" => Ok(Self::Maximum),
            "cutoff" => Ok(Self::Cutoff(DEFAULT_CUTOFF_ALPHA)),
            _ => {
                if let Some(a) = s.strip_prefix("cutoff:") {
                    let alpha: f32 = a
                        .parse()
                        .map_err(|_| format!("cutoff threshold {a:?} is not a number"))?;
                    if alpha > 0.0 && alpha <= 1.0 {
                        return Ok(Self::Cutoff(alpha));
                    }
                    return Err(format!("cutoff threshold must be in (0, 1], got {a}"));
                }
                Err(format!(
                    "expected one of \"balance\", \"power\", \"cutoff\", \"cutoff:ALPHA\", \
                     \"maximum\", got {s:?}"
                ))
            }
        }
    }
}

impl fmt::Display for MisChoice {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Balance => f.write_str("balance"),
            Self::Power => f.write_str("power"),
            // `{}` of an f32 prints the shortest string that parses back to the same value.
            Self::Cutoff(a) => write!(f, "cutoff:{a}"),
            Self::Maximum => f.write_str("maximum"),
        }
    }
}

string_serde!(MisChoice);

/// The sample generator requested for a job.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum SamplerChoice {
    /// Owen-scrambled Sobol' (randomized QMC). The default.
    #[default]
    Sobol,
    /// Independent uniform random numbers.
    Independent,
}

impl SamplerChoice {
    /// The string form: `"sobol"` or `"independent"`.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Sobol => "sobol",
            Self::Independent => "independent",
        }
    }
}

impl FromStr for SamplerChoice {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "sobol" => Ok(Self::Sobol),
            "independent" => Ok(Self::Independent),
            _ => Err(format!(
                "expected one of \"sobol\", \"independent\", got {s:?}"
            )),
        }
    }
}

impl fmt::Display for SamplerChoice {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

string_serde!(SamplerChoice);

/// Adaptive stopping (DESIGN §3).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum AdaptiveMode {
    /// Every pixel gets every planned pass. The default.
    #[default]
    Off,
    /// Stop tiles at fixed pass boundaries once their estimate is good enough (fast,
    /// slightly biased).
    Sequential,
    /// A discarded pilot fixes each pixel's pass count; only fresh passes form the image.
    Unbiased,
}

impl AdaptiveMode {
    /// The string form: `"off"`, `"sequential"` or `"unbiased"`.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Off => "off",
            Self::Sequential => "sequential",
            Self::Unbiased => "unbiased",
        }
    }
}

impl FromStr for AdaptiveMode {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "off" => Ok(Self::Off),
            "sequential" => Ok(Self::Sequential),
            "unbiased" => Ok(Self::Unbiased),
            _ => Err(format!(
                "expected one of \"off\", \"sequential\", \"unbiased\", got {s:?}"
            )),
        }
    }
}

impl fmt::Display for AdaptiveMode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

string_serde!(AdaptiveMode);

/// Everything that decides the value of a sample besides the scene and the plan: the
/// renderer-independent mirror of `tessera_render::render::RenderSettings`, carried to
/// workers in the gRPC `RenderSettings` message (see `tessera-proto`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RenderConfig {
    /// The integrator.
    pub integrator: IntegratorChoice,
    /// The MIS heuristic.
    pub mis: MisChoice,
    /// The sampler.
    pub sampler: SamplerChoice,
    /// Job seed.
    pub seed: u64,
    /// Maximum number of bounces, 1..=[`MAX_DEPTH_LIMIT`].
    pub max_depth: u32,
    /// Bounces before Russian roulette starts, 0..=[`MAX_DEPTH_LIMIT`].
    pub rr_depth: u32,
}

impl Default for RenderConfig {
    /// The defaults of `tessera render`: auto, power, sobol, seed 0, depth 16, roulette
    /// after 3 bounces.
    fn default() -> Self {
        Self {
            integrator: IntegratorChoice::Auto,
            mis: MisChoice::Power,
            sampler: SamplerChoice::Sobol,
            seed: 0,
            max_depth: DEFAULT_MAX_DEPTH,
            rr_depth: DEFAULT_RR_DEPTH,
        }
    }
}

impl RenderConfig {
    /// Checks the numeric ranges (the enums are valid by construction): `max_depth` in
    /// 1..=1024, `rr_depth` <= 1024, a cutoff threshold in (0, 1]. Errors name the field.
    pub fn validate(&self) -> Result<(), ApiError> {
        if !(1..=MAX_DEPTH_LIMIT).contains(&self.max_depth) {
            return Err(range_error("max_depth", 1, MAX_DEPTH_LIMIT, self.max_depth));
        }
        if self.rr_depth > MAX_DEPTH_LIMIT {
            return Err(range_error("rr_depth", 0, MAX_DEPTH_LIMIT, self.rr_depth));
        }
        if let MisChoice::Cutoff(a) = self.mis {
            if !(a > 0.0 && a <= 1.0) {
                return Err(ApiError::invalid_field(
                    "mis",
                    format_args!("cutoff threshold must be in (0, 1], got {a}"),
                ));
            }
        }
        Ok(())
    }
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
fn default_integrator() -> String {
    IntegratorChoice::default().to_string()
}
fn default_mis() -> String {
    MisChoice::default().to_string()
}
fn default_sampler() -> String {
    SamplerChoice::default().to_string()
}
fn default_adaptive() -> String {
    AdaptiveMode::default().to_string()
}

/// The body of `POST /api/v1/jobs`, as submitted: the first stage of the two-stage
/// configuration. Nothing here has been checked; [`JobSettings::validate`] produces the
/// [`ValidatedJob`] the server works with.
///
/// Every field but `scene` has a default, and unknown fields are rejected (a typo must not
/// silently fall back to a default). The idempotency key is not a field: it is the
/// [`IDEMPOTENCY_KEY_HEADER`](crate::IDEMPOTENCY_KEY_HEADER) header.
///
/// ```
/// let s: tessera_api::JobSettings =
///     serde_json::from_str(r#"{"scene": "builtin:cornell-box", "spp": 16}"#).unwrap();
/// let job = s.validate().unwrap();
/// assert_eq!((job.spp, job.tile_size, job.frames.count()), (16, 32, 1));
/// ```
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JobSettings {
    /// `"builtin:NAME"` or the content hash returned by `POST /api/v1/scenes`.
    pub scene: String,
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
    /// `"auto"` (default), `"path"`, `"direct"` or `"bdpt"`.
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
    /// Maximum path depth, 1..=1024; default 16.
    #[serde(default)]
    pub max_depth: Option<u32>,
    /// Frames to render, inclusive, at most 100000. Default frame 0 only.
    #[serde(default)]
    pub frames: FrameRange,
    /// Higher runs first; equal priorities run first come, first served. Default 0.
    #[serde(default)]
    pub priority: i32,
    /// Stop once the image error estimate (RMS relative error) is at most this, in (0, 1].
    #[serde(default)]
    pub target_error: Option<f64>,
    /// `"off"` (default), `"sequential"` or `"unbiased"` (DESIGN §3).
    #[serde(default = "default_adaptive")]
    pub adaptive: String,
    /// Stop after this many seconds of rendering, > 0.
    #[serde(default)]
    pub time_limit_seconds: Option<f64>,
    /// Tile edge in pixels, 4..=256. Default 32.
    #[serde(default = "default_tile_size")]
    pub tile_size: u32,
    /// A label for people, at most 200 characters, no control characters.
    #[serde(default)]
    pub name: Option<String>,
}

impl JobSettings {
    /// Settings for `scene` with every other field at its default.
    pub fn new(scene: impl Into<String>) -> Self {
        Self {
            scene: scene.into(),
            width: None,
            height: None,
            spp: DEFAULT_SPP,
            integrator: default_integrator(),
            mis: default_mis(),
            sampler: default_sampler(),
            seed: 0,
            max_depth: None,
            frames: FrameRange::default(),
            priority: 0,
            target_error: None,
            adaptive: default_adaptive(),
            time_limit_seconds: None,
            tile_size: DEFAULT_TILE_SIZE,
            name: None,
        }
    }

    /// Parses a request body. Errors are [`ApiError`]s ready to send: `invalid_request`
    /// for malformed JSON, `invalid_field` naming the field for a wrong type, an unknown
    /// or a missing field.
    pub fn from_json(body: &[u8]) -> Result<Self, ApiError> {
        parse_json(body)
    }

    /// Checks every field and parses the enumerations; the first problem found (in field
    /// order) is returned as an `invalid_field` error naming the field, e.g.
    /// `"spp: must be between 1 and 1048576, got 0"`.
    ///
    /// When both `width` and `height` are given the frame plan is checked too (the total
    /// amount of work is bounded); otherwise that happens in [`ValidatedJob::plan`] once
    /// the scene's resolution is known.
    pub fn validate(&self) -> Result<ValidatedJob, ApiError> {
        let scene: SceneRef = self
            .scene
            .parse()
            .map_err(|e| ApiError::invalid_field("scene", e))?;
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
        let integrator: IntegratorChoice = parse_field("integrator", &self.integrator)?;
        let mis: MisChoice = parse_field("mis", &self.mis)?;
        let sampler: SamplerChoice = parse_field("sampler", &self.sampler)?;
        let max_depth = self.max_depth.unwrap_or(DEFAULT_MAX_DEPTH);
        let render = RenderConfig {
            integrator,
            mis,
            sampler,
            seed: self.seed,
            max_depth,
            rr_depth: DEFAULT_RR_DEPTH,
        };
        render.validate()?;
        if self.frames.end < self.frames.start {
            return Err(ApiError::invalid_field(
                "frames.end",
                format_args!(
                    "must not be less than frames.start ({}), got {}",
                    self.frames.start, self.frames.end
                ),
            ));
        }
        if self.frames.count() > MAX_FRAMES {
            return Err(ApiError::invalid_field(
                "frames",
                format_args!(
                    "at most {MAX_FRAMES} frames per job, got {} ({}..={})",
                    self.frames.count(),
                    self.frames.start,
                    self.frames.end
                ),
            ));
        }
        if let Some(e) = self.target_error {
            if !(e > 0.0 && e <= 1.0) {
                return Err(ApiError::invalid_field(
                    "target_error",
                    format_args!("must be in (0, 1], got {e}"),
                ));
            }
        }
        let adaptive: AdaptiveMode = parse_field("adaptive", &self.adaptive)?;
        if let Some(t) = self.time_limit_seconds {
            if !(t > 0.0 && t.is_finite()) {
                return Err(ApiError::invalid_field(
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
            let chars = name.chars().count();
            if chars > MAX_NAME_CHARS {
                return Err(ApiError::invalid_field(
                    "name",
                    format_args!("must be at most {MAX_NAME_CHARS} characters, got {chars}"),
                ));
            }
            if name.chars().any(char::is_control) {
                return Err(ApiError::invalid_field(
                    "name",
                    "must not contain control characters",
                ));
            }
        }
        let job = ValidatedJob {
            scene,
            width: self.width,
            height: self.height,
            spp: self.spp,
            render,
            frames: self.frames,
            priority: self.priority,
            target_error: self.target_error,
            adaptive,
            time_limit_seconds: self.time_limit_seconds,
            tile_size: self.tile_size,
            name: self.name.clone(),
        };
        if let (Some(w), Some(h)) = (job.width, job.height) {
            job.plan(w, h)?;
        }
        Ok(job)
    }
}

/// `"{field}: must be between {min} and {max}, got {value}"`.
fn range_error(field: &str, min: u32, max: u32, value: u32) -> ApiError {
    ApiError::invalid_field(
        field,
        format_args!("must be between {min} and {max}, got {value}"),
    )
}

fn parse_field<T: FromStr<Err = String>>(field: &str, value: &str) -> Result<T, ApiError> {
    value.parse().map_err(|e| ApiError::invalid_field(field, e))
}

/// Parses JSON into `T`, mapping failures to [`ApiError`]s that name the field.
pub(crate) fn parse_json<T: serde::de::DeserializeOwned>(body: &[u8]) -> Result<T, ApiError> {
    // Structs would also deserialize from JSON arrays (positionally); only objects are
    // meant.
    if body.iter().find(|b| !b.is_ascii_whitespace()) != Some(&b'{') {
        return Err(ApiError::invalid_request(
            "request body must be a JSON object",
        ));
    }
    let mut de = serde_json::Deserializer::from_slice(body);
    let result: Result<T, _> = serde_path_to_error::deserialize(&mut de);
    let err = match result {
        Ok(v) => {
            // Trailing garbage after the value.
            return match de.end() {
                Ok(()) => Ok(v),
                Err(e) => Err(ApiError::invalid_request(format!(
                    "request body is not valid JSON: {e}"
                ))),
            };
        }
        Err(err) => err,
    };
    let path = err.path().to_string();
    let inner = err.into_inner();
    if !inner.is_data() {
        return Err(ApiError::invalid_request(format!(
            "request body is not valid JSON: {inner}"
        )));
    }
    let text = inner.to_string();
    // Unknown and missing fields are reported at the enclosing object; name the field.
    let named = ["unknown field `", "missing field `"]
        .iter()
        .find_map(|prefix| text.strip_prefix(prefix))
        .and_then(|rest| rest.split('`').next());
    // serde_path_to_error already includes an unknown field in the path, not a missing one.
    let field = match (named, path.as_str()) {
        (Some(name), "." | "") => name.to_owned(),
        (Some(name), p) if p == name || p.ends_with(&format!(".{name}")) => p.to_owned(),
        (Some(name), parent) => format!("{parent}.{name}"),
        (None, "." | "") => {
            return Err(ApiError::invalid_request(format!(
                "request body is not valid: {inner}"
            )))
        }
        (None, p) => p.to_owned(),
    };
    // Drop serde_json's " at line L column C" suffix: the field name says where.
    let message = match text.rfind(" at line ") {
        Some(i) => &text[..i],
        None => &text,
    };
    Err(ApiError::invalid_field(field, message))
}

/// A job whose settings passed [`JobSettings::validate`]: the second stage of the two-stage
/// configuration. Construct it only through validation (or with the same checks).
#[derive(Debug, Clone, PartialEq)]
pub struct ValidatedJob {
    /// The scene.
    pub scene: SceneRef,
    /// Requested image width; `None`: from the scene ([`resolve_resolution`]).
    pub width: Option<u32>,
    /// Requested image height; `None`: from the scene ([`resolve_resolution`]).
    pub height: Option<u32>,
    /// Samples per pixel, 1..=[`MAX_SPP`].
    pub spp: u32,
    /// How samples are computed.
    pub render: RenderConfig,
    /// Frames to render, `start <= end`, at most [`MAX_FRAMES`].
    pub frames: FrameRange,
    /// Scheduling priority (higher first).
    pub priority: i32,
    /// Target image error in (0, 1].
    pub target_error: Option<f64>,
    /// Adaptive stopping mode.
    pub adaptive: AdaptiveMode,
    /// Time limit in seconds, positive and finite.
    pub time_limit_seconds: Option<f64>,
    /// Tile edge in pixels, 4..=256.
    pub tile_size: u32,
    /// A label for people.
    pub name: Option<String>,
}

impl ValidatedJob {
    /// The frame plan for the resolved image size ([`FramePlan::for_spp`] with this job's
    /// spp and tile size; for `bdpt`, [`FramePlan::whole_frame`]: one tile, because light
    /// tracing splats anywhere on the film), with failures as `invalid_field` errors
    /// (`width`, `height`, `tile_size` or `spp`, the last when the total work is too large;
    /// `width` when a bdpt frame is too large for one tile).
    pub fn plan(&self, width: u32, height: u32) -> Result<FramePlan, ApiError> {
        let plan = if self.render.integrator == IntegratorChoice::Bdpt {
            FramePlan::whole_frame(width, height, self.spp)
        } else if self.adaptive != AdaptiveMode::Off {
            // Adaptive decisions fall between passes: many short ones, as `tessera render
            // --adaptive` plans them.
            tessera_farm::adaptive_plan(width, height, self.spp, self.tile_size)
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
            ApiError::invalid_field(field, e)
        })
    }

    /// The image size for a scene whose default resolution is `scene_default`; see
    /// [`resolve_resolution`].
    pub fn resolution(&self, scene_default: (u32, u32)) -> (u32, u32) {
        resolve_resolution(self.width, self.height, scene_default)
    }

    /// The canonical raw form: every field explicit, enumerations in their canonical
    /// spelling. `to_settings().validate()` gives back an equal job; the server can store
    /// and echo this.
    pub fn to_settings(&self) -> JobSettings {
        JobSettings {
            scene: self.scene.to_string(),
            width: self.width,
            height: self.height,
            spp: self.spp,
            integrator: self.render.integrator.to_string(),
            mis: self.render.mis.to_string(),
            sampler: self.render.sampler.to_string(),
            seed: self.render.seed,
            max_depth: Some(self.render.max_depth),
            frames: self.frames,
            priority: self.priority,
            target_error: self.target_error,
            adaptive: self.adaptive.to_string(),
            time_limit_seconds: self.time_limit_seconds,
            tile_size: self.tile_size,
            name: self.name.clone(),
        }
    }
}

/// The image size of a job: both requested dimensions if given; one of them with the
/// other following the scene's aspect ratio (rounded down, at least 1); or the scene's
/// default. The same rule as `tessera render`, so farm and local renders agree.
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error::ErrorCode;

    const HASH: &str = "9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08";

    fn base() -> JobSettings {
        JobSettings::new("builtin:cornell-box")
    }

    /// `f` makes a setting bad: it must be rejected, naming `field`, with a message
    /// starting with the field name.
    fn rejects(field: &str, f: impl FnOnce(&mut JobSettings)) -> ApiError {
        let mut s = base();
        f(&mut s);
        let e = s.validate().expect_err(field);
        assert_eq!(e.code, ErrorCode::InvalidField, "{e}");
        assert_eq!(e.field.as_deref(), Some(field), "{e}");
        assert!(e.message.starts_with(&format!("{field}: ")), "{e}");
        assert_eq!(e.status(), 400);
        e
    }

    fn accepts(f: impl FnOnce(&mut JobSettings)) -> ValidatedJob {
        let mut s = base();
        f(&mut s);
        match s.validate() {
            Ok(j) => j,
            Err(e) => panic!("rejected: {e}"),
        }
    }

    #[test]
    fn defaults() {
        let s: JobSettings = serde_json::from_str(r#"{"scene":"builtin:cornell-box"}"#).unwrap();
        assert_eq!(s, base());
        let j = s.validate().unwrap();
        assert_eq!(j.scene, SceneRef::Builtin("cornell-box".into()));
        assert_eq!((j.width, j.height), (None, None));
        assert_eq!(j.spp, 64);
        assert_eq!(j.render, RenderConfig::default());
        assert_eq!(j.render.max_depth, 16);
        assert_eq!(j.render.rr_depth, 3);
        assert_eq!(j.frames, FrameRange { start: 0, end: 0 });
        assert_eq!(j.priority, 0);
        assert_eq!(j.adaptive, AdaptiveMode::Off);
        assert_eq!(j.tile_size, 32);
        assert_eq!((j.target_error, j.time_limit_seconds), (None, None));
        assert_eq!(j.name, None);
    }

    #[test]
    fn full_json_round_trip() {
        let json = serde_json::json!({
            "scene": HASH, "width": 640, "height": 480, "spp": 256,
            "integrator": "bdpt", "mis": "cutoff:0.25", "sampler": "independent",
            "seed": u64::MAX, "max_depth": 32, "frames": {"start": 2, "end": 9},
            "priority": -5, "target_error": 0.02, "adaptive": "unbiased",
            "time_limit_seconds": 12.5, "tile_size": 64, "name": "turntable"
        });
        let s: JobSettings = serde_json::from_value(json.clone()).unwrap();
        assert_eq!(serde_json::to_value(&s).unwrap(), json);
        let j = s.validate().unwrap();
        assert_eq!(j.scene, SceneRef::Hash(HASH.into()));
        assert_eq!(j.render.integrator, IntegratorChoice::Bdpt);
        assert_eq!(j.render.mis, MisChoice::Cutoff(0.25));
        assert_eq!(j.render.sampler, SamplerChoice::Independent);
        assert_eq!(j.render.seed, u64::MAX);
        assert_eq!(j.render.max_depth, 32);
        assert_eq!(j.frames.count(), 8);
        assert_eq!(j.adaptive, AdaptiveMode::Unbiased);
        // The canonical form validates to the same job and is stable.
        let canon = j.to_settings();
        assert_eq!(canon, s);
        assert_eq!(canon.validate().unwrap(), j);
    }

    #[test]
    fn canonical_form_normalizes_spellings() {
        let j = accepts(|s| {
            s.scene = HASH.to_ascii_uppercase();
            s.mis = "max".into();
        });
        let c = j.to_settings();
        assert_eq!(c.scene, HASH);
        assert_eq!(c.mis, "maximum");
        assert_eq!(c.max_depth, Some(16));
        assert_eq!(c.validate().unwrap(), j);
        let j = accepts(|s| s.mis = "cutoff".into());
        assert_eq!(j.render.mis, MisChoice::Cutoff(0.1));
        assert_eq!(j.to_settings().mis, "cutoff:0.1");
        assert_eq!(j.to_settings().validate().unwrap(), j);
    }

    #[test]
    fn scene() {
        rejects("scene", |s| s.scene = String::new());
        rejects("scene", |s| s.scene = "builtin:".into());
        rejects("scene", |s| s.scene = "builtin:../etc/passwd".into());
        rejects("scene", |s| s.scene = "builtin:a b".into());
        rejects("scene", |s| s.scene = format!("builtin:{}", "x".repeat(65)));
        rejects("scene", |s| s.scene = HASH[..63].into());
        rejects("scene", |s| s.scene = format!("{HASH}0"));
        rejects("scene", |s| s.scene = format!("{}g", &HASH[..63]));
        rejects("scene", |s| s.scene = "scenes/room.gltf".into());
        accepts(|s| s.scene = "builtin:veach-mis".into());
        accepts(|s| s.scene = format!("builtin:{}", "x".repeat(64)));
        assert_eq!(accepts(|s| s.scene = HASH.into()).scene.hash(), Some(HASH));
    }

    #[test]
    fn width_and_height() {
        for field in ["width", "height"] {
            let set = |s: &mut JobSettings, v| {
                if field == "width" {
                    s.width = Some(v)
                } else {
                    s.height = Some(v)
                }
            };
            let e = rejects(field, |s| set(s, 0));
            assert_eq!(
                e.message,
                format!("{field}: must be between 1 and 16384, got 0")
            );
            rejects(field, |s| set(s, 16385));
            rejects(field, |s| set(s, u32::MAX));
            accepts(|s| set(s, 1));
            accepts(|s| set(s, 16384));
        }
    }

    #[test]
    fn spp() {
        let e = rejects("spp", |s| s.spp = 0);
        assert_eq!(e.message, "spp: must be between 1 and 1048576, got 0");
        assert_eq!(
            serde_json::to_value(&e).unwrap(),
            serde_json::json!({"error": {
                "code": "invalid_field",
                "message": "spp: must be between 1 and 1048576, got 0",
                "field": "spp"
            }})
        );
        rejects("spp", |s| s.spp = 1_048_577);
        accepts(|s| s.spp = 1);
        accepts(|s| s.spp = 1_048_576);
        // Absurd total work with a known size is refused up front, naming spp.
        let e = rejects("spp", |s| {
            s.width = Some(16384);
            s.height = Some(16384);
            s.spp = 1_048_576;
        });
        assert!(e.message.contains("more than the limit"), "{e}");
        accepts(|s| {
            s.width = Some(16384);
            s.height = Some(16384);
            s.spp = 4096;
        });
    }

    #[test]
    fn enumerations() {
        for (field, good, bad) in [
            (
                "integrator",
                &["auto", "path", "direct", "bdpt"][..],
                &["", "Path", "pt", "photon"][..],
            ),
            (
                "mis",
                &[
                    "balance",
                    "power",
                    "cutoff",
                    "cutoff:0.5",
                    "cutoff:1",
                    "maximum",
                    "max",
                ][..],
                &[
                    "",
                    "cutoff:0",
                    "cutoff:1.5",
                    "cutoff:-0.1",
                    "cutoff:x",
                    "cutoff:NaN",
                    "heuristic",
                ][..],
            ),
            (
                "sampler",
                &["sobol", "independent"][..],
                &["", "halton", "Sobol"][..],
            ),
            (
                "adaptive",
                &["off", "sequential", "unbiased"][..],
                &["", "on", "true"][..],
            ),
        ] {
            let set = |s: &mut JobSettings, v: &str| match field {
                "integrator" => s.integrator = v.into(),
                "mis" => s.mis = v.into(),
                "sampler" => s.sampler = v.into(),
                _ => s.adaptive = v.into(),
            };
            for v in good {
                accepts(|s| set(s, v));
            }
            for v in bad {
                let e = rejects(field, |s| set(s, v));
                assert!(
                    e.message.contains("expected") || e.message.contains("cutoff"),
                    "{e}"
                );
            }
        }
    }

    #[test]
    fn max_depth() {
        rejects("max_depth", |s| s.max_depth = Some(0));
        rejects("max_depth", |s| s.max_depth = Some(1025));
        assert_eq!(accepts(|s| s.max_depth = Some(1)).render.max_depth, 1);
        assert_eq!(accepts(|s| s.max_depth = Some(1024)).render.max_depth, 1024);
    }

    #[test]
    fn frames() {
        let e = rejects("frames.end", |s| s.frames = FrameRange { start: 5, end: 4 });
        assert_eq!(
            e.message,
            "frames.end: must not be less than frames.start (5), got 4"
        );
        rejects("frames", |s| {
            s.frames = FrameRange {
                start: 0,
                end: 100_000,
            }
        });
        rejects("frames", |s| {
            s.frames = FrameRange {
                start: 0,
                end: u32::MAX,
            }
        });
        let j = accepts(|s| {
            s.frames = FrameRange {
                start: 0,
                end: 99_999,
            }
        });
        assert_eq!(j.frames.count(), 100_000);
        let j = accepts(|s| {
            s.frames = FrameRange {
                start: u32::MAX,
                end: u32::MAX,
            }
        });
        assert_eq!(j.frames.iter().collect::<Vec<_>>(), vec![u32::MAX]);
    }

    #[test]
    fn target_error() {
        for bad in [0.0, -0.1, 1.0001, f64::NAN, f64::INFINITY] {
            rejects("target_error", |s| s.target_error = Some(bad));
        }
        for good in [1e-6, 0.01, 1.0] {
            accepts(|s| s.target_error = Some(good));
        }
    }

    #[test]
    fn time_limit() {
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            rejects("time_limit_seconds", |s| s.time_limit_seconds = Some(bad));
        }
        accepts(|s| s.time_limit_seconds = Some(0.001));
        accepts(|s| s.time_limit_seconds = Some(86_400.0));
    }

    #[test]
    fn tile_size() {
        rejects("tile_size", |s| s.tile_size = 3);
        rejects("tile_size", |s| s.tile_size = 257);
        rejects("tile_size", |s| s.tile_size = 0);
        accepts(|s| s.tile_size = 4);
        accepts(|s| s.tile_size = 256);
    }

    #[test]
    fn name() {
        rejects("name", |s| s.name = Some("x".repeat(201)));
        rejects("name", |s| s.name = Some("line\nbreak".into()));
        accepts(|s| s.name = Some("x".repeat(200)));
        // Characters, not bytes.
        accepts(|s| s.name = Some("é".repeat(200)));
        accepts(|s| s.name = Some(String::new()));
    }

    #[test]
    fn priority_and_seed_take_any_value() {
        for p in [i32::MIN, -1, 0, i32::MAX] {
            assert_eq!(accepts(|s| s.priority = p).priority, p);
        }
        assert_eq!(accepts(|s| s.seed = u64::MAX).render.seed, u64::MAX);
    }

    #[test]
    fn render_config_validate() {
        assert!(RenderConfig::default().validate().is_ok());
        let bad = |f: fn(&mut RenderConfig), field: &str| {
            let mut c = RenderConfig::default();
            f(&mut c);
            assert_eq!(c.validate().unwrap_err().field.as_deref(), Some(field));
        };
        bad(|c| c.max_depth = 0, "max_depth");
        bad(|c| c.rr_depth = 1025, "rr_depth");
        bad(|c| c.mis = MisChoice::Cutoff(0.0), "mis");
        bad(|c| c.mis = MisChoice::Cutoff(f32::NAN), "mis");
    }

    #[test]
    fn json_unknown_missing_and_mistyped_fields_name_the_field() {
        let e = JobSettings::from_json(br#"{"scene":"builtin:x","spx":5}"#).unwrap_err();
        assert_eq!(e.code, ErrorCode::InvalidField);
        assert_eq!(e.field.as_deref(), Some("spx"), "{e}");
        assert!(e.message.starts_with("spx: unknown field `spx`"), "{e}");
        // Also with serde_json directly (what an axum Json extractor does).
        assert!(serde_json::from_str::<JobSettings>(r#"{"scene":"builtin:x","spx":5}"#).is_err());

        let e = JobSettings::from_json(br#"{"scene":"builtin:x","frames":{"start":0,"stop":1}}"#)
            .unwrap_err();
        assert_eq!(e.field.as_deref(), Some("frames.stop"), "{e}");

        let e = JobSettings::from_json(br#"{"spp":5}"#).unwrap_err();
        assert_eq!(e.field.as_deref(), Some("scene"), "{e}");
        assert_eq!(e.message, "scene: missing field `scene`");

        let e = JobSettings::from_json(br#"{"scene":"builtin:x","spp":-1}"#).unwrap_err();
        assert_eq!(e.field.as_deref(), Some("spp"), "{e}");
        assert!(!e.message.contains("line"), "{e}");

        let e = JobSettings::from_json(br#"{"scene":"builtin:x","width":"wide"}"#).unwrap_err();
        assert_eq!(e.field.as_deref(), Some("width"), "{e}");

        let e =
            JobSettings::from_json(br#"{"scene":"builtin:x","frames":{"start":1}}"#).unwrap_err();
        assert_eq!(e.field.as_deref(), Some("frames.end"), "{e}");

        for bad in [
            &b"{"[..],
            b"",
            b"not json",
            br#"{"scene":"builtin:x"} trailing"#,
        ] {
            let e = JobSettings::from_json(bad).unwrap_err();
            assert_eq!(e.code, ErrorCode::InvalidRequest, "{e}");
            assert_eq!(e.field, None);
        }
        let e = JobSettings::from_json(b"[1, 2]").unwrap_err();
        assert_eq!(e.code, ErrorCode::InvalidRequest, "{e}");

        let ok = JobSettings::from_json(br#" {"scene":"builtin:x","spp":5} "#).unwrap();
        assert_eq!(ok.spp, 5);
    }

    #[test]
    fn plan_errors_name_fields() {
        let j = base().validate().unwrap();
        let p = j.plan(640, 480).unwrap();
        assert_eq!(
            (p.width, p.height, p.tile_size, p.spp()),
            (640, 480, 32, 64)
        );
        assert_eq!(j.plan(0, 480).unwrap_err().field.as_deref(), Some("width"));
        // bdpt plans one whole-frame tile, and refuses frames too large for it by name.
        let mut b = j.clone();
        b.render.integrator = IntegratorChoice::Bdpt;
        let p = b.plan(640, 480).unwrap();
        assert_eq!((p.tile_count(), p.tile_size), (1, 640));
        assert_eq!(p.spp(), j.plan(640, 480).unwrap().spp());
        let e = b.plan(2048, 2048).unwrap_err();
        assert_eq!(e.field.as_deref(), Some("width"));
        assert!(e.to_string().contains("whole-frame tile"), "{e}");
        assert_eq!(j.plan(640, 0).unwrap_err().field.as_deref(), Some("height"));
        let mut big = j.clone();
        big.spp = MAX_SPP;
        assert_eq!(
            big.plan(16384, 16384).unwrap_err().field.as_deref(),
            Some("spp")
        );
    }

    #[test]
    fn resolution_follows_the_scene_aspect() {
        assert_eq!(resolve_resolution(None, None, (400, 300)), (400, 300));
        assert_eq!(resolve_resolution(Some(800), None, (400, 300)), (800, 600));
        assert_eq!(resolve_resolution(None, Some(150), (400, 300)), (200, 150));
        assert_eq!(resolve_resolution(Some(1), None, (400, 300)), (1, 1));
        assert_eq!(resolve_resolution(Some(7), Some(9), (400, 300)), (7, 9));
        let j = accepts(|s| s.width = Some(100));
        assert_eq!(j.resolution((512, 256)), (100, 50));
    }

    #[test]
    fn choices_parse_their_display() {
        for m in [
            MisChoice::Balance,
            MisChoice::Power,
            MisChoice::Cutoff(0.1),
            MisChoice::Cutoff(0.3333333),
            MisChoice::Maximum,
        ] {
            assert_eq!(m.to_string().parse::<MisChoice>().unwrap(), m);
            let json = serde_json::to_string(&m).unwrap();
            assert_eq!(serde_json::from_str::<MisChoice>(&json).unwrap(), m);
        }
        for i in [
            IntegratorChoice::Auto,
            IntegratorChoice::Path,
            IntegratorChoice::Direct,
            IntegratorChoice::Bdpt,
        ] {
            assert_eq!(i.as_str().parse::<IntegratorChoice>().unwrap(), i);
        }
        let c = RenderConfig::default();
        let json = serde_json::to_string(&c).unwrap();
        assert_eq!(
            json,
            r#"{"integrator":"auto","mis":"power","sampler":"sobol","seed":0,"max_depth":16,"rr_depth":3}"#
        );
        assert_eq!(serde_json::from_str::<RenderConfig>(&json).unwrap(), c);
        assert!(serde_json::from_str::<SceneRef>(r#""builtin:""#).is_err());
    }
}
