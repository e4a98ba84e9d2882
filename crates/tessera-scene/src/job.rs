//! Jobs meet scenes: loading a job's scene (with its camera) and resolving the job against
//! it, the one path both `tessera render` and the coordinator take (ARCHITECTURE.md §2).
//!
//! The job contract itself lives in [`tessera_farm::job`]; this module adds the two steps
//! that need a parsed scene: [`load_job_scene`] and [`resolve_job`] (the render plan of
//! [`crate::analysis::analyse`] fed to [`ValidatedJob::resolve`]).

use tessera_farm::job::{JobError, ResolvedJob, SceneFacts, SceneRef, Shutter, ValidatedJob};

use crate::{builtin, gltf_import, Scene, SceneError, SceneTime};

/// The scene of a job: a built-in scene, or an uploaded self-contained glTF/GLB given as
/// its `bytes`, rendered from the glTF camera named `camera` (default: its first camera).
///
/// Built-in scenes have one camera, so naming one is an error rather than silently ignored.
/// Uploaded scenes are named `scene HASH` (their content hash), as everywhere in the farm.
/// The scene is evaluated at t = 0 ([`load_job_scene_at`] for a frame's time).
pub fn load_job_scene(
    scene: &SceneRef,
    bytes: Option<&[u8]>,
    camera: Option<&str>,
) -> Result<Scene, SceneError> {
    load_job_scene_at(scene, bytes, camera, &SceneTime::default())
}

/// [`load_job_scene`] evaluated at `time` (a frame of the job: [`frame_time`]); built-in
/// scenes are static.
pub fn load_job_scene_at(
    scene: &SceneRef,
    bytes: Option<&[u8]>,
    camera: Option<&str>,
    time: &SceneTime,
) -> Result<Scene, SceneError> {
    match (scene, bytes) {
        (SceneRef::Builtin(name), _) => {
            if let Some(c) = camera {
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
        (SceneRef::Hash(h), Some(b)) => {
            gltf_import::load_slice_at(b, &format!("scene {h}"), None, camera, time)
        }
        (SceneRef::Hash(h), None) => Err(SceneError::Invalid {
            scene: format!("scene {h}"),
            message: "its bytes are not stored".into(),
        }),
    }
}

/// The time of `frame` of `job`: `frame / fps` seconds with the job's animation
/// (ARCHITECTURE.md §8, "Time"). Every renderer of a frame (`tessera render --frame`, the
/// coordinator, the workers) loads the scene at this time.
pub fn frame_time(job: &ValidatedJob, frame: u32) -> SceneTime {
    SceneTime {
        seconds: job.frame_seconds(frame),
        animation: job.animation.clone(),
    }
}

/// The shutter's key times of `frame` ([`tessera_farm::job::Shutter::key_frames`] over
/// the job's fps, with the job's animation), at which motion blur evaluates the scene;
/// empty when the job has no shutter.
pub fn shutter_times(job: &ValidatedJob, frame: u32) -> Vec<SceneTime> {
    shutter_times_of(job.shutter, job.fps, job.animation.as_deref(), frame)
}

/// [`shutter_times`] from a lease's fields: the shutter, fps and animation of its job.
pub fn shutter_times_of(
    shutter: Option<Shutter>,
    fps: f64,
    animation: Option<&str>,
    frame: u32,
) -> Vec<SceneTime> {
    shutter.map_or_else(Vec::new, |s| {
        s.key_frames(frame)
            .into_iter()
            .map(|f| SceneTime {
                seconds: f / fps,
                animation: animation.map(str::to_owned),
            })
            .collect()
    })
}

/// The scene at the shutter's key times of `frame` ([`shutter_times`]), loaded by `load`;
/// empty when the job has no shutter or `scene` (the frame's scene) is not animated, so a
/// static scene never pays for them.
pub fn shutter_scenes<E>(
    job: &ValidatedJob,
    frame: u32,
    scene: &Scene,
    load: impl FnMut(&SceneTime) -> Result<Scene, E>,
) -> Result<Vec<Scene>, E> {
    shutter_scenes_of(&shutter_times(job, frame), scene, load)
}

/// [`shutter_scenes`] at the key times `times` ([`shutter_times_of`]).
pub fn shutter_scenes_of<E>(
    times: &[SceneTime],
    scene: &Scene,
    load: impl FnMut(&SceneTime) -> Result<Scene, E>,
) -> Result<Vec<Scene>, E> {
    if !scene.animated {
        return Ok(Vec::new());
    }
    times.iter().map(load).collect()
}

/// Resolves `job` against `scene`: [`ValidatedJob::resolve`] with the scene's default
/// resolution and its render plan ([`crate::analysis::analyse`]).
pub fn resolve_job(job: &ValidatedJob, scene: &Scene) -> Result<ResolvedJob, JobError> {
    let facts = SceneFacts {
        default_resolution: scene.default_resolution,
    };
    job.resolve(facts, crate::analysis::analyse(scene))
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
        let scene = load_job_scene(&job.scene, None, None).unwrap();
        resolve_job(&job, &scene).unwrap()
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
        let r = resolve(
            r#"{"scene": "builtin:caustic", "width": 320, "height": 240, "integrator": "path"}"#,
        );
        assert_eq!(r.plan.tile_size, 32);
    }

    /// Regression (redesign issue): bdpt with adaptive stopping kept tiles in
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

    /// Issue 15: an adaptive render's estimate is optimistic where rare paths carry the
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
        // Issue 15: a render whose pixels ran out of passes above the target says so.
        let short = StopVerdict {
            time_limit: false,
            target: Some(0.1),
            estimate: Some(0.125),
            spp: 256,
            unbiased: false,
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
        let e = load_job_scene(&SceneRef::Builtin("cornell-box".into()), None, Some("side"))
            .unwrap_err();
        assert!(e.to_string().contains("camera \"side\""), "{e}");
    }
}
