//! The technique pilot (ARCHITECTURE.md §4): where path tracing and bdpt are both correct,
//! the plan takes the one measured to be more efficient, deterministically, and says what
//! it measured.

use glam::Vec3;
use tessera_farm::job::{Integrator, JobSettings, PlannedIntegrator, ResolvedJob, ValidatedJob};
use tessera_render::pilot;
use tessera_scene::job::ResolveError;

/// The resolve path every renderer takes, with the in-process pilot.
fn resolve_job(
    job: &ValidatedJob,
    scene: &tessera_scene::Scene,
) -> Result<ResolvedJob, ResolveError> {
    tessera_scene::job::resolve_job(job, scene, pilot::verdict)
}

fn job(settings: &str) -> tessera_farm::job::ValidatedJob {
    let raw: JobSettings = serde_json::from_str(settings).unwrap();
    raw.validate().unwrap()
}

/// The caustic scene with its glass ball shrunk to a pebble at the edge of the view and
/// a bright sky: the caustic is a few pixels, the rest is lit by the sky, which path
/// tracing samples well and bdpt's light subpaths from the tiny light do not help.
fn pebble_under_the_sky() -> tessera_scene::Scene {
    let mut s = tessera_scene::builtin::caustic();
    s.spheres[0].center = Vec3::new(-1.2, 0.1, 0.5);
    s.spheres[0].radius = 0.1;
    s.environment = Some(Vec3::splat(1.0));
    s
}

#[test]
fn the_caustic_scene_keeps_bdpt_as_path_tracings_error_is_a_heavy_tail() {
    let scene = tessera_scene::load("builtin:caustic").unwrap();
    let analysed = tessera_scene::analysis::analyse(&scene);
    assert_eq!(analysed.integrator, PlannedIntegrator::Bdpt);
    assert!(analysed.technique_pilot.is_some(), "a tiny finite light");
    let j = job(r#"{"scene":"builtin:caustic","width":64,"height":48,"spp":16}"#);
    let r = resolve_job(&j, &scene).unwrap();
    assert_eq!(r.config.integrator, Integrator::Bdpt);
    let first = &r.render_plan.reasons[0];
    assert!(
        first.starts_with("technique pilot") && first.ends_with("bdpt chosen"),
        "{first}"
    );
    assert!(r.render_plan.technique_pilot.is_none(), "settled");
    // Deterministic: the same verdict, to the digit, every time (it is in the EXR header).
    let again = resolve_job(&j, &scene).unwrap();
    assert_eq!(again.render_plan, r.render_plan);
    assert_eq!(again.metadata_json(None), r.metadata_json(None));
}

#[test]
fn a_small_caustic_under_a_bright_sky_is_path_traced() {
    let scene = pebble_under_the_sky();
    let analysed = tessera_scene::analysis::analyse(&scene);
    assert_eq!(
        analysed.integrator,
        PlannedIntegrator::Bdpt,
        "{:?}",
        analysed.reasons
    );
    let j = job(r#"{"scene":"builtin:caustic","width":64,"height":48,"spp":16}"#);
    let v = pilot::run(&scene, &j, &analysed, (64, 48)).unwrap();
    println!("{}", v.reason());
    assert!(v.path_wins(), "{}", v.reason());
    let r = resolve_job(&j, &scene).unwrap();
    assert_eq!(r.config.integrator, Integrator::Path);
    assert!(
        !r.plan.is_whole_frame(),
        "path tracing keeps the tiled plan"
    );
    let reasons = r.render_plan.reasons.join("\n");
    assert!(reasons.contains("path chosen"), "{reasons}");
    assert!(!reasons.contains("bdpt light-traces"), "{reasons}");
    assert!(
        reasons.contains("path tracing with next-event estimation"),
        "{reasons}"
    );
}

#[test]
fn an_explicit_integrator_or_a_delta_light_runs_no_pilot() {
    let scene = tessera_scene::load("builtin:caustic").unwrap();
    let j = job(r#"{"scene":"builtin:caustic","width":32,"height":24,"integrator":"path"}"#);
    let r = resolve_job(&j, &scene).unwrap();
    assert_eq!(r.config.integrator, Integrator::Path);
    assert!(
        !r.render_plan
            .reasons
            .iter()
            .any(|r| r.starts_with("technique pilot")),
        "{:?}",
        r.render_plan.reasons
    );
    // A spot light through glass, the caustic seen through the glass: path tracing and
    // bdpt cannot find all of it, vcm is the only correct choice and no pilot is asked for.
    let spot = tessera_scene::load(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../scenes/glass-spot.gltf"
    ))
    .unwrap();
    let plan = tessera_scene::analysis::analyse(&spot);
    assert_eq!(plan.integrator, PlannedIntegrator::Vcm);
    assert!(plan.technique_pilot.is_none());
    assert!(
        plan.reasons[0].contains("delta lights"),
        "{}",
        plan.reasons[0]
    );
}

#[test]
fn the_pilot_frame_keeps_the_aspect_ratio() {
    assert_eq!(pilot::pilot_size(640, 480), (64, 48));
    assert_eq!(pilot::pilot_size(48, 32), (48, 32));
    assert_eq!(pilot::pilot_size(4000, 10), (64, 1));
    assert_eq!(pilot::pilot_size(1, 1), (1, 1));
}

/// One failure policy: a pilot that fails refuses the job (locally and on the farm), with
/// the way around it; a job that names its integrator never asks the pilot.
#[test]
fn a_failed_pilot_refuses_the_job_and_an_explicit_integrator_never_asks() {
    let scene = tessera_scene::load("builtin:caustic").unwrap();
    let j = job(r#"{"scene":"builtin:caustic","width":32,"height":24}"#);
    let e =
        tessera_scene::job::resolve_job(&j, &scene, |_| Err("it timed out".into())).unwrap_err();
    assert!(matches!(e, ResolveError::Pilot(_)), "{e}");
    let message = e.to_string();
    assert!(
        message.contains("it timed out") && message.contains("name an integrator"),
        "{message}"
    );
    let j = job(r#"{"scene":"builtin:caustic","width":32,"height":24,"integrator":"bdpt"}"#);
    let r = tessera_scene::job::resolve_job(&j, &scene, |_| panic!("no pilot for bdpt")).unwrap();
    assert_eq!(r.config.integrator, Integrator::Bdpt);
}

/// Veach's door-ajar room is lit through an opening (the lights reach 0.4% of what the
/// camera sees): the analysis leaves the choice to the pilot, which scores errors against
/// the image's mean there and keeps bdpt, the better of bdpt and path tracing by the
/// measured efficiency `1 / (MSE x s)` (docs/benchmarks.md, "Metropolis light
/// transport"); per-pixel relative errors chose path tracing.
#[test]
fn the_door_ajar_room_asks_the_pilot_and_keeps_bdpt() {
    let scene = tessera_scene::load(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../scenes/door-ajar.gltf"
    ))
    .unwrap();
    let plan = tessera_scene::analysis::analyse(&scene);
    assert_eq!(
        plan.integrator,
        PlannedIntegrator::Bdpt,
        "{:?}",
        plan.reasons
    );
    assert!(
        plan.technique_pilot
            .as_ref()
            .is_some_and(|t| t.lit_through_opening),
        "{:?}",
        plan.reasons
    );
    assert!(
        plan.reasons[0].contains("lit through an opening"),
        "{}",
        plan.reasons[0]
    );
    let j = job(r#"{"scene":"builtin:cornell-box","width":64,"height":64,"spp":16}"#);
    let r = resolve_job(&j, &scene).unwrap();
    let first = &r.render_plan.reasons[0];
    println!("{first}");
    assert!(first.contains("relative to the image's mean"), "{first}");
    assert_eq!(r.config.integrator, Integrator::Bdpt, "{first}");
    assert!(r.plan.is_whole_frame());
    // The scenes asked before keep their per-pixel scoring.
    let caustic =
        tessera_scene::analysis::analyse(&tessera_scene::load("builtin:caustic").unwrap());
    assert!(caustic
        .technique_pilot
        .is_some_and(|t| !t.lit_through_opening));
}

/// Veach's door-ajar room (a point light, the seen room lit only through a gap), where
/// path tracing, bdpt and mlt can all sample every path: the pilot's choice is the measured
/// best of the three, or the measured best failed the margin or the spread the pilot asks
/// of a technique over the one it would replace (module documentation of the pilot); the
/// verdict is the same on a second run.
#[test]
fn on_the_door_ajar_room_the_pilot_picks_the_measured_best() {
    let scene = tessera_scene::load(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../scenes/door-ajar.gltf"
    ))
    .unwrap();
    let plan = tessera_scene::analysis::analyse(&scene);
    // The job's scene name is only validated; the pilot renders the scene it is given.
    let j = job(r#"{"scene":"builtin:cornell-box","width":64,"height":64,"spp":16}"#);
    let v = pilot::run(&scene, &j, &plan, (64, 64)).unwrap();
    println!("{}", v.reason());
    let candidates = [
        (PlannedIntegrator::Path, v.path),
        (PlannedIntegrator::Bdpt, v.bdpt),
        (PlannedIntegrator::Mlt, v.mlt),
    ];
    let (best, best_m) = candidates
        .iter()
        .copied()
        .max_by(|a, b| a.1.efficiency().total_cmp(&b.1.efficiency()))
        .unwrap();
    let chosen = v.choice();
    let chosen_m = candidates.iter().find(|c| c.0 == chosen).unwrap().1;
    assert!(
        chosen == best
            || best_m.efficiency() <= pilot::PATH_MARGIN * chosen_m.efficiency()
            || best_m.spread < pilot::MIN_PATH_SPREAD,
        "{}",
        v.reason()
    );
    assert!(v.reason().ends_with(&format!("{chosen} chosen")));
    assert_eq!(pilot::run(&scene, &j, &plan, (64, 64)).unwrap(), v);
}

/// bench/compare's glass ball in small: `builtin:caustic`'s ball under a 0.2 m square light
/// (0.02 of the scene's radius: small, not tiny) and no sky. The analysis path-traces it and
/// asks the pilot about mnee; the pilot measures mnee the more efficient (its caustic is
/// the image's noise) and the job renders with mnee, path tracing's reasons kept,
/// deterministically.
#[test]
fn the_glass_ball_under_a_small_square_light_is_rendered_with_mnee() {
    let mut scene = crate::mnee::glass_ball();
    let light = scene.meshes.last_mut().unwrap();
    let c = light.positions.iter().copied().sum::<Vec3>() / 4.0;
    for p in &mut light.positions {
        *p = c + 2.0 * (*p - c);
    }
    let last = scene.materials.len() - 1;
    scene.materials[last].emission = Vec3::splat(500.0);
    let analysed = tessera_scene::analysis::analyse(&scene);
    assert_eq!(
        analysed.integrator,
        PlannedIntegrator::Path,
        "{}",
        analysed.summary()
    );
    assert!(analysed.technique_pilot.as_ref().is_some_and(|t| t.mnee));
    let j = job(r#"{"scene":"builtin:caustic","width":64,"height":48,"spp":16}"#);
    let v = pilot::run_mnee(&scene, &j, &analysed, (64, 48)).unwrap();
    println!("{}", v.reason());
    assert!(v.mnee_wins(), "{}", v.reason());
    let r = resolve_job(&j, &scene).unwrap();
    assert_eq!(r.config.integrator, Integrator::Mnee);
    let reasons = &r.render_plan.reasons;
    assert!(reasons[0].ends_with("mnee chosen"), "{reasons:?}");
    assert!(
        reasons
            .iter()
            .any(|r| r.starts_with("path tracing with next-event estimation")),
        "{reasons:?}"
    );
    let again = resolve_job(&j, &scene).unwrap();
    assert_eq!(again.metadata_json(None), r.metadata_json(None));
}
