//! Jobs meet scenes: loading a job's scene at a time, and resolving the job against it.
//!
//! The job contract lives in [`tessera_farm::job`]; this module adds the steps that need a
//! parsed scene, each written once and used by every renderer of a job (`tessera render`,
//! `tessera estimate`, the coordinator and the worker), so that local and farm images agree
//! bit for bit (ARCHITECTURE.md §2):
//!
//! - [`load_job_scene_at`]: a job's [`JobScene`] (the scene, its camera) parsed at a
//!   [`SceneTime`]: [`resolution_time`] to resolve the job, [`frame_time`] for a frame,
//!   [`shutter_times`] for motion blur's key times;
//! - [`resolve_job`]: the analysis's render plan ([`crate::analysis::analyse`]), the
//!   technique pilot where the plan leaves the choice between path tracing and bdpt to a
//!   measurement (the pilot is passed in: `tessera_render::pilot::verdict` in process, a
//!   child process on the coordinator), then [`ValidatedJob::resolve`].
//!
//! One failure policy (ARCHITECTURE.md §4): a pilot that fails refuses the job
//! ([`ResolveError::Pilot`]), locally and on the farm alike. A pilot fails only when the
//! job's scene does not render at the pilot's size or the pilot could not finish; falling
//! back to another integrator there would let the same job resolve differently on another
//! attempt (a coordinator that restarts resolves stored jobs again), and its units would
//! then merge two techniques. A job that names its integrator never waits for a pilot.

use tessera_farm::job::{
    JobError, JobScene, PilotVerdict, RenderPlan, ResolvedJob, SceneFacts, SceneRef, ValidatedJob,
};

use crate::{builtin, gltf_import, Scene, SceneError, SceneTime};

/// The scene of a job: a built-in scene, or an uploaded self-contained glTF/GLB given as
/// its `bytes`, rendered from the glTF camera `scene.camera` names (default: its first
/// camera), evaluated at `time`.
///
/// Built-in scenes have one camera, so naming one is an error rather than silently ignored;
/// they are static. Uploaded scenes are named `scene HASH` (their content hash), as
/// everywhere in the farm.
pub fn load_job_scene_at(
    scene: &JobScene,
    bytes: Option<&[u8]>,
    time: &SceneTime,
) -> Result<Scene, SceneError> {
    match (&scene.source, bytes) {
        (SceneRef::Builtin(name), _) => {
            if let Some(c) = &scene.camera {
                return Err(SceneError::Invalid {
                    scene: format!("builtin:{name}"),
                    message: format!(
                        "camera {c:?}: built-in scenes have only their own camera; \
                         a camera can be chosen in glTF scenes"
                    ),
                });
            }
            builtin::load(name)
        }
        (SceneRef::Hash(h), Some(b)) => gltf_import::load_slice_at(
            b,
            &format!("scene {h}"),
            None,
            scene.camera.as_deref(),
            time,
        ),
        (SceneRef::Hash(h), None) => Err(SceneError::Invalid {
            scene: format!("scene {h}"),
            message: "its bytes are not stored".into(),
        }),
    }
}

/// The scene time at `seconds`, with the job's animation.
pub fn scene_time(scene: &JobScene, seconds: f64) -> SceneTime {
    SceneTime {
        seconds,
        animation: scene.animation.clone(),
    }
}

/// The time a job is resolved at: t = 0 with its animation. The render plan, the default
/// resolution and the technique pilot see the scene at this time on every renderer.
pub fn resolution_time(scene: &JobScene) -> SceneTime {
    scene_time(scene, 0.0)
}

/// The time of `frame`: [`JobScene::frame_seconds`] with the job's animation
/// (ARCHITECTURE.md §8, "Time"). Every renderer of a frame (`tessera render --frame`, the
/// workers) loads the scene at this time.
pub fn frame_time(scene: &JobScene, frame: u32) -> SceneTime {
    scene_time(scene, scene.frame_seconds(frame))
}

/// The shutter's key times of `frame` ([`JobScene::shutter_seconds`], with the job's
/// animation), at which motion blur evaluates the scene; empty when the job has no shutter.
pub fn shutter_times(scene: &JobScene, frame: u32) -> Vec<SceneTime> {
    scene
        .shutter_seconds(frame)
        .into_iter()
        .map(|t| scene_time(scene, t))
        .collect()
}

/// The scene at the key times `times` ([`shutter_times`]), loaded by `load`; empty when
/// `frame_scene` (the frame's scene) is not animated, so a static scene never pays for
/// them.
pub fn shutter_scenes<E>(
    times: &[SceneTime],
    frame_scene: &Scene,
    load: impl FnMut(&SceneTime) -> Result<Scene, E>,
) -> Result<Vec<Scene>, E> {
    if !frame_scene.animated {
        return Ok(Vec::new());
    }
    times.iter().map(load).collect()
}

/// What the technique pilot is asked to measure: the job, its scene at
/// [`resolution_time`], and the analysis's plan, whose choice between path tracing and
/// bdpt waits for it ([`RenderPlan::awaits_technique_pilot`]).
#[derive(Clone, Copy, Debug)]
pub struct PilotQuestion<'a> {
    /// The job.
    pub job: &'a ValidatedJob,
    /// Its scene at [`resolution_time`].
    pub scene: &'a Scene,
    /// The analysis's plan (its depths are the pilot's).
    pub plan: &'a RenderPlan,
}

impl PilotQuestion<'_> {
    /// The job's image size (the pilot renders the same view, smaller).
    pub fn resolution(&self) -> (u32, u32) {
        self.job.resolution(self.scene.default_resolution)
    }

    /// What the verdict depends on, as a key for caches of verdicts: the scene, its camera
    /// and animation (the scene at [`resolution_time`]), the image size (the pilot's view
    /// has its aspect), the depth asked for, the MIS heuristic and the sampler. The pilot's
    /// seed and size are constants, so nothing else changes its verdict.
    pub fn key(&self) -> String {
        let (w, h) = self.resolution();
        let (s, r) = (&self.job.scene, &self.job.render);
        format!(
            "{}|{:?}|{:?}|{w}x{h}|{:?}|{}|{}",
            s.source, s.camera, s.animation, r.max_depth, r.mis, r.sampler
        )
    }
}

/// Why a job did not resolve against its scene.
#[derive(Debug, thiserror::Error)]
pub enum ResolveError {
    /// The settings do not resolve against the scene (a [`JobError`] naming the field).
    #[error("{0}")]
    Job(#[from] JobError),
    /// The technique pilot failed: the scene does not render at the pilot's size, or the
    /// pilot could not finish. The job is refused (the module's failure policy).
    #[error(
        "the technique pilot, which measures path tracing against bdpt for this scene, \
         failed: {0} (name an integrator to render without it)"
    )]
    Pilot(String),
}

/// Resolves `job` against `scene` (loaded at [`resolution_time`]): the render plan of
/// [`crate::analysis::analyse`]; where the plan leaves the choice between path tracing
/// and bdpt to a measurement and the job asks for `auto`, `pilot`'s verdict settles it
/// ([`RenderPlan::settle_technique`]); then [`ValidatedJob::resolve`] with the scene's
/// default resolution. `pilot` is called at most once; its error refuses the job.
pub fn resolve_job(
    job: &ValidatedJob,
    scene: &Scene,
    pilot: impl FnOnce(&PilotQuestion<'_>) -> Result<PilotVerdict, String>,
) -> Result<ResolvedJob, ResolveError> {
    let mut plan = crate::analysis::analyse(scene);
    if plan.awaits_technique_pilot(job.render.integrator) {
        let verdict = pilot(&PilotQuestion {
            job,
            scene,
            plan: &plan,
        })
        .map_err(ResolveError::Pilot)?;
        if verdict.mnee_wins {
            plan.settle_mnee(verdict.reason);
        } else if verdict.mlt_wins {
            plan.settle_metropolis(verdict.reason);
        } else {
            plan.settle_technique(verdict.path_wins, verdict.reason);
        }
    }
    let facts = SceneFacts {
        default_resolution: scene.default_resolution,
    };
    Ok(job.resolve(facts, plan)?)
}

/// A pilot that does not measure: the analysis's choice (bdpt, which samples every path
/// path tracing does; or path tracing where the question was mnee) stands, and the plan's
/// first reason says why, with `why`. For
/// renderers that cannot run the pilot (a coordinator without a pilot program) and for
/// tests of resolution alone.
pub fn no_pilot(why: &str) -> impl FnOnce(&PilotQuestion<'_>) -> Result<PilotVerdict, String> + '_ {
    move |q| {
        Ok(PilotVerdict {
            path_wins: false,
            mlt_wins: false,
            mnee_wins: false,
            reason: format!(
                "technique pilot not run ({why}): {}, the analysis's choice",
                q.plan.integrator
            ),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tessera_farm::job::{
        Integrator, JobSettings, StopVerdict, DEFAULT_MAX_DEPTH, DEFAULT_RR_DEPTH,
    };

    fn resolve(settings: &str) -> ResolvedJob {
        let raw: JobSettings = serde_json::from_str(settings).unwrap();
        let job = raw.validate().unwrap();
        let scene = load_job_scene_at(&job.scene, None, &resolution_time(&job.scene)).unwrap();
        resolve_job(&job, &scene, no_pilot("a test of resolution")).unwrap()
    }

    #[test]
    fn auto_follows_the_plan_and_overrides_are_recorded() {
        let r = resolve(r#"{"scene": "builtin:cornell-box", "width": 16, "height": 16}"#);
        assert_eq!(r.config.integrator, Integrator::Path);
        assert_eq!(r.config.max_depth, r.render_plan.max_depth);
        assert!(r.render_plan.overridden.is_none());
        assert!(!r.black);
        let r = resolve(
            r#"{"scene": "builtin:cornell-box", "width": 16, "height": 16, "integrator": "path"}"#,
        );
        assert_eq!(
            (r.config.max_depth, r.config.rr_depth),
            (DEFAULT_MAX_DEPTH, DEFAULT_RR_DEPTH)
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
        assert_eq!(r.config.integrator, Integrator::Bdpt);
        assert_eq!((r.plan.tile_count(), r.plan.tile_size), (1, 320));
        // ... or asked for; other integrators keep their tiles.
        let r = resolve(
            r#"{"scene": "builtin:cornell-box", "width": 300, "height": 200, "integrator": "bdpt"}"#,
        );
        assert_eq!((r.plan.tile_count(), r.plan.tile_size), (1, 300));
        // vcm splats too, and merges with the whole pass's photons.
        let r = resolve(
            r#"{"scene": "builtin:cornell-box", "width": 300, "height": 200, "integrator": "vcm"}"#,
        );
        assert_eq!(r.config.integrator, Integrator::Vcm);
        assert_eq!((r.plan.tile_count(), r.plan.tile_size), (1, 300));
        let r = resolve(
            r#"{"scene": "builtin:caustic", "width": 320, "height": 240, "integrator": "path"}"#,
        );
        assert_eq!(r.plan.tile_size, 32);
    }

    /// Regression: bdpt with adaptive stopping once kept tiles in
    /// `tessera render` but one whole-frame tile on the farm; now both resolve here.
    #[test]
    fn bdpt_with_adaptive_stopping_keeps_one_whole_frame_tile() {
        let r = resolve(
            r#"{"scene": "builtin:caustic", "width": 64, "height": 48, "spp": 256,
                "adaptive": "sequential", "target_error": 0.05}"#,
        );
        assert_eq!(r.config.integrator, Integrator::Bdpt);
        assert_eq!((r.plan.tile_count(), r.plan.tile_size), (1, 64));
    }

    /// An adaptive render's estimate is optimistic where rare paths carry the
    /// error (glossy veach-mis), calibrated on the diffuse Cornell box; the header says so
    /// only where it applies.
    #[test]
    fn adaptive_jobs_of_scenes_with_rare_paths_carry_a_caveat() {
        let caveat = |json: &str| {
            let r = resolve(json);
            let v: serde_json::Value = serde_json::from_str(&r.metadata_json(None)).unwrap();
            assert_eq!(
                v["error_estimate_caveat"].as_str(),
                r.error_estimate_caveat().as_deref()
            );
            r.error_estimate_caveat()
        };
        let adaptive = r#", "spp": 1024, "adaptive": "unbiased", "target_error": 0.05}"#;
        let veach =
            format!(r#"{{"scene": "builtin:veach-mis", "width": 32, "height": 32{adaptive}"#);
        // The unbiased mode reports the pooled per-pass estimator; the header names it.
        let header = |json: &str| -> serde_json::Value {
            serde_json::from_str(&resolve(json).metadata_json(None)).unwrap()
        };
        assert_eq!(
            header(&veach)["error_estimator"],
            tessera_farm::ERROR_ESTIMATOR_POOLED
        );
        assert_eq!(
            header(&veach.replace("unbiased", "sequential"))["error_estimator"],
            tessera_farm::ERROR_ESTIMATOR
        );
        let c = caveat(&veach).expect("glossy plates under adaptive stopping");
        assert!(
            c.contains("adaptive stopping") && c.contains("glossily"),
            "{c}"
        );
        assert_eq!(
            caveat(r#"{"scene": "builtin:veach-mis", "width": 32, "height": 32, "spp": 64}"#),
            None
        );
        let cornell =
            format!(r#"{{"scene": "builtin:cornell-box", "width": 32, "height": 32{adaptive}"#);
        assert_eq!(caveat(&cornell), None);
        // Path-traced caustics of a tiny light under adaptive stopping: both reasons.
        let caustic = format!(
            r#"{{"scene": "builtin:caustic", "width": 32, "height": 32, "integrator": "path"{adaptive}"#
        );
        let c = caveat(&caustic).unwrap();
        assert!(
            c.contains("BSDF-sampled ray") && c.contains("; may be optimistic under adaptive"),
            "{c}"
        );
    }

    #[test]
    fn metadata_is_json_with_the_settings() {
        let r = resolve(r#"{"scene": "builtin:furnace", "width": 8, "height": 4, "spp": 16}"#);
        let v: serde_json::Value = serde_json::from_str(&r.metadata_json(None)).unwrap();
        assert_eq!(v["scene"], "builtin:furnace");
        assert_eq!(v["width"], 8);
        assert_eq!(v["spp"], 16);
        assert_eq!(v["mis"], "power");
        assert_eq!(v["error_estimator"], tessera_farm::ERROR_ESTIMATOR);
        assert!(v["plan"].is_object());
        assert!(v.get("adaptive").is_none());
        let r = resolve(
            r#"{"scene": "builtin:furnace", "width": 8, "height": 4, "spp": 256,
                "adaptive": "unbiased", "target_error": 0.1}"#,
        );
        let v: serde_json::Value = serde_json::from_str(&r.metadata_json(None)).unwrap();
        assert_eq!(v["stopped"], serde_json::Value::Null);
        assert_eq!(v["target_reached"], serde_json::Value::Null);
        // A render whose pixels ran out of passes above the target says so.
        let short = StopVerdict {
            time_limit: false,
            target: Some(0.1),
            estimate: Some(0.125),
            spp: 256,
            unbiased: false,
            unsampled: false,
        };
        let v: serde_json::Value = serde_json::from_str(&r.metadata_json(Some(&short))).unwrap();
        assert_eq!(v["adaptive"], "unbiased");
        assert_eq!(v["min_passes"], 8);
        assert_eq!(v["stopped"], "finished");
        assert_eq!(v["target_reached"], false);
        assert_eq!(v["error_reached"], 0.125);
        assert_eq!(
            short.summary(),
            "target error 0.1 not reached: the estimate is 0.1250 when the sample budget (256 spp) ran out"
        );
        let met = StopVerdict {
            estimate: Some(0.0625),
            ..short
        };
        let v: serde_json::Value = serde_json::from_str(&r.metadata_json(Some(&met))).unwrap();
        assert_eq!(v["stopped"], "target error reached");
        assert_eq!(v["target_reached"], true);
        // An integrator that cannot sample a light path class of the scene never reaches a
        // target, whatever its (blind) estimate says.
        let blind = StopVerdict {
            unsampled: true,
            ..met
        };
        assert_eq!(blind.target_reached(), Some(false));
        assert_eq!(blind.stopped(), "finished");
        assert!(
            blind.summary().contains("cannot sample"),
            "{}",
            blind.summary()
        );
        let timed = StopVerdict {
            time_limit: true,
            estimate: None,
            ..short
        };
        assert_eq!(timed.stopped(), "time limit reached");
        assert_eq!(
            timed.summary(),
            "target error 0.1 not reached: no estimate yet when the time limit ran out"
        );
        assert_eq!(timed.target_reached(), Some(false));
        // An unbiased render adds no passes after its pilot's plan: that is why it ended.
        let planned = StopVerdict {
            unbiased: true,
            ..short
        };
        assert_eq!(
            planned.summary(),
            "target error 0.1 not reached: the estimate is 0.1250 when the passes its pilot \
             planned (within the sample budget of 256 spp) were done"
        );
        let planned_timed = StopVerdict {
            time_limit: true,
            ..planned
        };
        assert!(planned_timed
            .summary()
            .ends_with("when the time limit ran out"));
    }

    #[test]
    fn builtin_scenes_refuse_a_camera_name() {
        let scene = JobScene {
            source: SceneRef::Builtin("cornell-box".into()),
            camera: Some("side".into()),
            fps: 24.0,
            animation: None,
            shutter: None,
        };
        let e = load_job_scene_at(&scene, None, &SceneTime::default()).unwrap_err();
        assert!(e.to_string().contains("camera \"side\""), "{e}");
    }
}
