//! Resolving a job against its scene: the render plan (DESIGN §4) turns `auto` into
//! concrete render settings, and the frame plan follows from the scene's resolution.
//!
//! `tessera render` and the coordinator both call [`resolve_job`], so a job gives the same
//! settings, the same frame plan and the same EXR metadata ([`render_metadata_json`])
//! however it is rendered: locally or through the farm (DESIGN §2).

use tessera_farm::FramePlan;
use tessera_scene::analysis::{analyse, PlannedIntegrator, RenderPlan};
use tessera_scene::Scene;

use crate::error::ApiError;
use crate::settings::{IntegratorChoice, RenderConfig, ValidatedJob};

/// Maximum path depth of the general configuration (an explicit integrator).
pub const GENERAL_MAX_DEPTH: u32 = 16;
/// Russian roulette start depth of the general configuration.
pub const GENERAL_RR_DEPTH: u32 = 3;

/// A job resolved against its scene.
#[derive(Debug, Clone, PartialEq)]
pub struct ResolvedJob {
    /// Concrete render settings: never [`IntegratorChoice::Auto`].
    pub config: RenderConfig,
    /// The frame plan for the resolved resolution.
    pub plan: FramePlan,
    /// The scene analysis, with `overridden` set when the job forced other settings.
    pub render_plan: RenderPlan,
    /// The plan found no light: the image is black and nothing needs tracing.
    pub black: bool,
    /// The scene's name (used in the EXR metadata).
    pub scene_name: String,
}

/// Resolves `job` against `scene`.
///
/// With `integrator` auto the render plan decides: black (no light), direct lighting with
/// one bounce, path or bdpt with the plan's depth and Russian roulette depth. An explicit
/// integrator uses the general configuration (depth [`GENERAL_MAX_DEPTH`], roulette from
/// [`GENERAL_RR_DEPTH`]) and is recorded as an override. `max_depth_given` is the depth the
/// user asked for, if any (`None` keeps the plan's or the general default); a depth other
/// than the chosen one is recorded as an override too.
pub fn resolve_job(
    job: &ValidatedJob,
    max_depth_given: Option<u32>,
    scene: &Scene,
) -> Result<ResolvedJob, ApiError> {
    let (width, height) = job.resolution(scene.default_resolution);
    let mut render_plan = analyse(scene);
    let mut forced = Vec::new();
    let mut black = false;
    let (integrator, plan_depth, rr_depth) = match job.render.integrator {
        IntegratorChoice::Auto => match render_plan.integrator {
            PlannedIntegrator::Black => {
                black = true;
                // Nothing is traced; these settings only fill the metadata.
                (IntegratorChoice::Direct, 1, render_plan.rr_depth)
            }
            PlannedIntegrator::Direct => (IntegratorChoice::Direct, 1, render_plan.rr_depth),
            PlannedIntegrator::Path => (
                IntegratorChoice::Path,
                render_plan.max_depth,
                render_plan.rr_depth,
            ),
            PlannedIntegrator::Bdpt => (
                IntegratorChoice::Bdpt,
                render_plan.max_depth,
                render_plan.rr_depth,
            ),
        },
        other => {
            forced.push(format!("--integrator {other}"));
            (other, GENERAL_MAX_DEPTH, GENERAL_RR_DEPTH)
        }
    };
    if let Some(d) = max_depth_given {
        if d != plan_depth {
            forced.push(format!("--max-depth {d}"));
        }
    }
    if !forced.is_empty() {
        render_plan.set_override(&forced.join(" "));
    }
    let config = RenderConfig {
        integrator,
        max_depth: max_depth_given.unwrap_or(plan_depth),
        rr_depth,
        ..job.render
    };
    config.validate()?;
    // The frame plan follows the resolved integrator: bdpt (chosen by the plan or asked
    // for) gets one whole-frame tile, see `ValidatedJob::plan`.
    let plan = ValidatedJob {
        render: config,
        ..job.clone()
    }
    .plan(width, height)?;
    Ok(ResolvedJob {
        config,
        plan,
        render_plan,
        black,
        scene_name: scene.name.clone(),
    })
}

impl ResolvedJob {
    /// The EXR header metadata of this job: [`render_metadata_json`].
    pub fn metadata_json(&self) -> String {
        render_metadata_json(
            &self.scene_name,
            &self.plan,
            &self.config,
            self.black,
            &self.render_plan.to_json(),
        )
    }
}

/// The render settings and the render plan as one JSON object for the EXR header, with a
/// stable key order so that a farm render and a local render of the same job write
/// byte-identical files. A black render (no light) has integrator `"black"`.
pub fn render_metadata_json(
    scene_name: &str,
    plan: &FramePlan,
    config: &RenderConfig,
    black: bool,
    render_plan_json: &str,
) -> String {
    let integrator = if black {
        "black"
    } else {
        config.integrator.as_str()
    };
    format!(
        "{{\"scene\":{},\"width\":{},\"height\":{},\"spp\":{},\"samples_per_pass\":{},\"passes\":{},\"integrator\":\"{}\",\"mis\":\"{}\",\"sampler\":\"{}\",\"seed\":{},\"max_depth\":{},\"rr_depth\":{},\"plan\":{}}}",
        serde_json::Value::String(scene_name.to_string()),
        plan.width,
        plan.height,
        plan.spp(),
        plan.samples_per_pass,
        plan.passes,
        integrator,
        config.mis,
        config.sampler.as_str(),
        config.seed,
        config.max_depth,
        config.rr_depth,
        render_plan_json
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::JobSettings;

    fn resolve(settings: &str) -> ResolvedJob {
        let raw = JobSettings::from_json(settings.as_bytes()).unwrap();
        let job = raw.validate().unwrap();
        let scene = tessera_scene::load(&raw.scene).unwrap();
        resolve_job(&job, raw.max_depth, &scene).unwrap()
    }

    #[test]
    fn auto_follows_the_plan_and_overrides_are_recorded() {
        let r = resolve(r#"{"scene": "builtin:cornell-box", "width": 16, "height": 16}"#);
        assert_eq!(r.config.integrator, IntegratorChoice::Path);
        assert_eq!(r.config.max_depth, r.render_plan.max_depth);
        assert!(r.render_plan.overridden.is_none());
        assert!(!r.black);
        let r = resolve(
            r#"{"scene": "builtin:cornell-box", "width": 16, "height": 16, "integrator": "path"}"#,
        );
        assert_eq!(
            (r.config.max_depth, r.config.rr_depth),
            (GENERAL_MAX_DEPTH, GENERAL_RR_DEPTH)
        );
        assert!(r
            .render_plan
            .overridden
            .as_deref()
            .unwrap()
            .starts_with("--integrator path overrides the plan"));
        let r = resolve(
            r#"{"scene": "builtin:cornell-box", "width": 16, "height": 16, "max_depth": 3}"#,
        );
        assert_eq!(r.config.max_depth, 3);
        assert!(r.render_plan.overridden.is_some());
    }

    #[test]
    fn bdpt_gets_one_whole_frame_tile() {
        // Chosen by the plan (a caustic lit by a tiny light) ...
        let r = resolve(r#"{"scene": "builtin:caustic", "width": 320, "height": 240}"#);
        assert_eq!(r.config.integrator, IntegratorChoice::Bdpt);
        assert_eq!((r.plan.tile_count(), r.plan.tile_size), (1, 320));
        // ... or asked for; other integrators keep their tiles.
        let r = resolve(
            r#"{"scene": "builtin:cornell-box", "width": 300, "height": 200, "integrator": "bdpt"}"#,
        );
        assert_eq!((r.plan.tile_count(), r.plan.tile_size), (1, 300));
        let r = resolve(
            r#"{"scene": "builtin:caustic", "width": 320, "height": 240, "integrator": "path"}"#,
        );
        assert_eq!(r.plan.tile_size, 32);
    }

    #[test]
    fn metadata_is_json_with_the_settings() {
        let r = resolve(r#"{"scene": "builtin:furnace", "width": 8, "height": 4, "spp": 16}"#);
        let v: serde_json::Value = serde_json::from_str(&r.metadata_json()).unwrap();
        assert_eq!(v["width"], 8);
        assert_eq!(v["spp"], 16);
        assert_eq!(v["mis"], "power");
        assert!(v["plan"].is_object());
    }
}
