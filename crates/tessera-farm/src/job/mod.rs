//! The job contract: one vocabulary for what a render job asks for, shared by the
//! command line, the HTTP API, the coordinator, the wire format and the renderer
//! (ARCHITECTURE.md §1, "one job vocabulary").
//!
//! A job goes through three stages, each a type:
//!
//! 1. [`JobSettings`]: as submitted (the body of `POST /api/v1/jobs`, or what
//!    `tessera render` builds from its flags): strings, optional fields, defaults.
//! 2. [`ValidatedJob`]: every field checked, every choice parsed
//!    ([`JobSettings::validate`], errors are [`JobError`]s naming the field).
//! 3. [`ResolvedJob`]: resolved against the scene ([`ValidatedJob::resolve`]) with its
//!    [`RenderPlan`]: the integrator is concrete ([`Integrator`], never `auto`), the
//!    depths are chosen, the [`FramePlan`](crate::FramePlan) is cut; its
//!    [`ResolvedJob::metadata_json`] is the EXR header every renderer writes.
//!
//! The choices ([`IntegratorChoice`], [`Integrator`], [`MisHeuristic`], [`SamplerKind`],
//! [`AdaptiveMode`], [`SceneRef`]) each have one string form (`Display`/`FromStr`, and
//! serde through it). Nothing here parses scenes: `tessera_scene::analysis` computes the
//! render plan, and this module only consumes it.
//!
//! ```
//! use tessera_farm::job::{Integrator, JobSettings, RenderPlan, PlannedIntegrator, SceneFacts};
//!
//! let mut settings = JobSettings::new("builtin:cornell-box");
//! settings.width = Some(64);
//! settings.integrator = "bdpt".into();
//! let job = settings.validate()?;
//! let plan = RenderPlan {
//!     effects: vec![],
//!     absent: vec![],
//!     integrator: PlannedIntegrator::Path,
//!     max_depth: 8,
//!     rr_depth: 3,
//!     lens_sampling: false,
//!     reasons: vec![],
//!     overridden: None,
//!     warnings: vec![],
//!     technique_pilot: None,
//!     beyond_mnee: vec![],
//! };
//! let resolved = job.resolve(SceneFacts { default_resolution: (512, 256) }, plan)?;
//! assert_eq!(resolved.config.integrator, Integrator::Bdpt);
//! // Height follows the scene's aspect ratio; bdpt renders one whole-frame tile.
//! assert_eq!((resolved.plan.width, resolved.plan.height, resolved.plan.tile_count()), (64, 32, 1));
//! assert!(resolved.render_plan.overridden.is_some());
//! # Ok::<(), tessera_farm::job::JobError>(())
//! ```

mod choice;
mod environment;
pub mod plan;
mod resolve;
mod scene;
mod settings;

pub use choice::{
    AdaptiveMode, Integrator, IntegratorChoice, MisHeuristic, SamplerKind, SceneRef,
    DEFAULT_CUTOFF_ALPHA, MAX_BUILTIN_NAME_CHARS,
};
pub use environment::{
    EnvironmentSettings, EnvironmentSource, JobEnvironment, MAX_ENVIRONMENT_RADIANCE,
    MAX_ENVIRONMENT_STRENGTH,
};
pub use plan::{Effect, EffectKind, PilotVerdict, PlannedIntegrator, RenderPlan, TechniquePilot};
pub use resolve::{ResolvedJob, SceneFacts, StopVerdict};
pub use scene::JobScene;
pub use settings::{
    resolve_resolution, FrameRange, JobError, JobSettings, RenderConfig, RenderRequest, Shutter,
    ValidatedJob, DEFAULT_FPS, DEFAULT_MAX_DEPTH, DEFAULT_MIN_PASSES, DEFAULT_RR_DEPTH,
    DEFAULT_SPP, DEFAULT_TILE_SIZE, MAX_ANIMATION_CHARS, MAX_CAMERA_CHARS, MAX_DEPTH_LIMIT,
    MAX_FPS, MAX_FRAMES, MAX_MIN_PASSES, MAX_NAME_CHARS, MAX_SHUTTER_FRAMES, MAX_SPP,
    SHUTTER_SEGMENTS,
};

#[cfg(test)]
mod tests;
