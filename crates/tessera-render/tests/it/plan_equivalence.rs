//! Evidence for the render plan (ARCHITECTURE.md §4): where the render plan drops machinery (direct lighting only, a
//! reduced maximum depth), its image has the same expected value as the general
//! configuration (`--integrator path`, max depth 16). Both are rendered here at modest
//! sample counts and compared tile by tile (8 x 8 pixel blocks) with a z-test; the errors
//! come from the spread of independent passes (ARCHITECTURE.md §3), Bonferroni-corrected over the
//! tiles for a family-wise level of 1% (the critical |z| is about 3.4 for 16 tiles). The
//! time per sample is the benchmark's business (`tessera bench-plan`), not a test's.

use crate::common::{assert_blocks_agree, block_passes, block_stats};
use glam::Vec3;
use tessera_farm::FramePlan;
use tessera_render::integrator::Integrator;
use tessera_render::render::RenderConfig;
use tessera_render::scene::RenderScene;
use tessera_scene::analysis::{analyse, PlannedIntegrator};
use tessera_scene::builtin::look_at_camera;
use tessera_scene::{Material, Mesh, PunctualLight, Scene};

/// The plan's render settings, as `tessera render --integrator auto` derives them.
fn planned(scene: &Scene) -> (RenderConfig, PlannedIntegrator) {
    let plan = analyse(scene);
    let (integrator, max_depth) = match plan.integrator {
        PlannedIntegrator::Direct => (Integrator::Direct, 1),
        PlannedIntegrator::Path => (Integrator::Path, plan.max_depth),
        PlannedIntegrator::Bdpt => (Integrator::Bdpt, plan.max_depth),
        PlannedIntegrator::Vcm => (Integrator::Vcm, plan.max_depth),
        PlannedIntegrator::Mlt => (Integrator::Mlt, plan.max_depth),
        PlannedIntegrator::Mnee => (Integrator::Mnee, plan.max_depth),
        PlannedIntegrator::Black => (Integrator::Direct, 1),
    };
    (
        RenderConfig {
            integrator,
            max_depth,
            rr_depth: plan.rr_depth,
            seed: 21,
            ..RenderConfig::default()
        },
        plan.integrator,
    )
}

fn general() -> RenderConfig {
    RenderConfig {
        integrator: Integrator::Path,
        max_depth: 16,
        rr_depth: 3,
        seed: 22,
        ..RenderConfig::default()
    }
}

/// Renders `scene` with the plan's and the general settings and z-tests 8 x 8 tiles.
fn plan_matches_general(name: &str, scene: &Scene, expect: PlannedIntegrator) {
    let (w, h) = (32, 32);
    let rs = RenderScene::build(scene, w, h).unwrap();
    let plan = FramePlan::new(w, h, 32, 4, 32).unwrap();
    let (ps, chosen) = planned(scene);
    assert_eq!(chosen, expect, "{name}: the plan changed");
    let a = block_stats(&block_passes(&rs, &ps, &plan, 8));
    let b = block_stats(&block_passes(&rs, &general(), &plan, 8));
    let worst = assert_blocks_agree(
        &format!(
            "{name}: plan ({} depth {}) vs general (path depth 16)",
            ps.integrator, ps.max_depth
        ),
        &a,
        &b,
    );
    assert!(worst.is_finite());
}

#[test]
fn veach_mis_plan_depth_8_matches_depth_16() {
    let scene = tessera_scene::load("builtin:veach-mis").unwrap();
    plan_matches_general("veach-mis", &scene, PlannedIntegrator::Path);
}

/// A single diffuse plane under a point light and a dim environment: light reaches the
/// camera after one bounce at most (nothing else to bounce off), so the plan is direct
/// lighting only, one bounce instead of sixteen.
fn plane_under_point_light() -> Scene {
    let v = Vec3::new;
    let floor = Mesh {
        name: "floor".into(),
        positions: vec![
            v(-2.0, 0.0, -2.0),
            v(-2.0, 0.0, 2.0),
            v(2.0, 0.0, 2.0),
            v(2.0, 0.0, -2.0),
        ],
        normals: None,
        uvs: vec![],
        tangents: None,
        colors: None,
        indices: vec![[0, 1, 2], [0, 2, 3]],
        material: 0,
    };
    Scene {
        name: "test:plane-under-point-light".into(),
        camera: look_at_camera(v(0.0, 2.0, 3.0), v(0.0, 0.0, 0.0), Vec3::Y, 40.0),
        meshes: vec![floor],
        prototypes: Vec::new(),
        instances: Vec::new(),
        spheres: vec![],
        materials: vec![Material::diffuse("floor", Vec3::splat(0.7))],
        textures: vec![],
        images: vec![],
        warnings: vec![],
        lights: vec![PunctualLight::Point {
            position: v(0.3, 1.5, 0.2),
            intensity: Vec3::splat(5.0),
        }],
        environment: Some(Vec3::splat(0.1)),
        environment_map: None,
        default_resolution: (32, 32),
        animated: false,
    }
}

#[test]
fn direct_only_plan_matches_the_path_tracer() {
    plan_matches_general(
        "plane under a point light",
        &plane_under_point_light(),
        PlannedIntegrator::Direct,
    );
}

#[test]
fn gltf_cornell_box_plan_matches_general() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../scenes/cornell-box.gltf");
    let scene = tessera_scene::load(path).unwrap();
    plan_matches_general("cornell-box.gltf", &scene, PlannedIntegrator::Path);
}
