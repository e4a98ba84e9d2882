//! Bidirectional path tracing against the path tracer, analytic answers and itself.
//!
//! Statistics (Marschner, CS 6630 notes, section 2, Owen 2001, section 6.7): passes are independent replicates, so the
//! spread of a quantity across passes estimates the error of its mean. Light tracing splats
//! make the pixels of one bdpt pass correlated, so block means are formed *per pass* and
//! their variance is taken across passes (summing per-pixel variances would ignore the
//! correlation). Each comparison is a two-sided z-test per block, Bonferroni-corrected over
//! the blocks for a family-wise level of 1%, with at least 32 passes so that the estimated
//! standard errors are close to exact.

use crate::common::{assert_blocks_agree, block_passes, block_stats, normal_sf, z_critical};
use glam::Vec3;
use rayon::prelude::*;
use tessera_farm::{FrameAccumulator, FramePlan};
use tessera_render::integrator::Integrator;
use tessera_render::render::{render_frame, render_unit, render_unit_where, RenderConfig};
use tessera_render::scene::RenderScene;
use tessera_scene::builtin::{look_at_camera, FURNACE_ALBEDO, FURNACE_EMISSION};
use tessera_scene::{Material, MaterialKind, Mesh, PunctualLight, Scene, Sphere};

fn settings(integrator: Integrator, seed: u64, max_depth: u32) -> RenderConfig {
    RenderConfig {
        integrator,
        seed,
        max_depth,
        rr_depth: 3,
        ..RenderConfig::default()
    }
}

/// One tile covering the whole (small) frame: the bdpt plan.
fn whole_frame_plan(w: u32, h: u32, spp_per_pass: u32, passes: u32) -> FramePlan {
    FramePlan::new(w, h, w.max(h).max(4), spp_per_pass, passes).unwrap()
}

#[test]
fn z_critical_is_right() {
    assert!((z_critical(0.05, 1) - 1.95996).abs() < 1e-3);
    assert!((z_critical(0.01, 1) - 2.57583).abs() < 1e-3);
    assert!((normal_sf(3.0) - 0.0013499).abs() < 1e-6);
}

fn compare_with_path(scene_name: &str, w: u32, h: u32, spp: u32, passes: u32, block: u32) {
    let scene = tessera_scene::load(scene_name).unwrap();
    let rs = RenderScene::build(&scene, w, h).unwrap();
    let plan = whole_frame_plan(w, h, spp, passes);
    let bd_passes = block_passes(&rs, &settings(Integrator::Bdpt, 1, 16), &plan, block);
    let pt_passes = block_passes(&rs, &settings(Integrator::Path, 2, 16), &plan, block);
    // The whole image as one block too.
    let image = |p: &[Vec<f64>]| -> Vec<Vec<f64>> {
        p.iter()
            .map(|b| vec![b.iter().sum::<f64>() / b.len() as f64])
            .collect()
    };
    assert_blocks_agree(
        &format!("{scene_name} bdpt vs path, whole image"),
        &block_stats(&image(&bd_passes)),
        &block_stats(&image(&pt_passes)),
    );
    let bd = block_stats(&bd_passes);
    let pt = block_stats(&pt_passes);
    let mb: f64 = bd.iter().map(|b| b.0).sum::<f64>() / bd.len() as f64;
    let mp: f64 = pt.iter().map(|b| b.0).sum::<f64>() / pt.len() as f64;
    eprintln!("{scene_name}: image mean luminance bdpt {mb:.5}, path {mp:.5}");
    assert_blocks_agree(&format!("{scene_name} bdpt vs path"), &bd, &pt);
}

fn compare_scene_with_path(name: &str, scene: &Scene, w: u32, h: u32, max_depth: u32) {
    let rs = RenderScene::build(scene, w, h).unwrap();
    let plan = whole_frame_plan(w, h, 4, 32);
    let bd = block_stats(&block_passes(
        &rs,
        &settings(Integrator::Bdpt, 31, max_depth),
        &plan,
        4,
    ));
    let pt = block_stats(&block_passes(
        &rs,
        &settings(Integrator::Path, 32, max_depth),
        &plan,
        4,
    ));
    assert_blocks_agree(&format!("{name} bdpt vs path"), &bd, &pt);
}

/// The thin lens: importance and lens sampling of `t = 1` for an open aperture.
#[test]
fn bdpt_agrees_with_path_through_a_thin_lens() {
    let mut scene = tessera_scene::load("builtin:cornell-box").unwrap();
    scene.camera.aperture_radius = 0.03;
    scene.camera.focus_distance = 1.0;
    compare_scene_with_path("cornell-box, thin lens", &scene, 24, 24, 8);
}

/// Emission sampling of the distant and cone lights in a full render: a diffuse ball and
/// a glossy-free floor under a directional light, a spot light and a uniform environment.
#[test]
fn bdpt_agrees_with_path_under_directional_spot_and_environment_light() {
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
    let scene = Scene {
        name: "test:distant-lights".into(),
        camera: look_at_camera(v(0.0, 1.5, 3.0), v(0.0, 0.3, 0.0), Vec3::Y, 45.0),
        meshes: vec![floor],
        prototypes: Vec::new(),
        instances: Vec::new(),
        spheres: vec![Sphere {
            center: v(0.0, 0.5, 0.0),
            radius: 0.5,
            material: 1,
        }],
        materials: vec![
            Material::diffuse("floor", Vec3::splat(0.6)),
            Material::diffuse("ball", Vec3::new(0.8, 0.3, 0.2)),
        ],
        textures: vec![],
        images: vec![],
        warnings: vec![],
        lights: vec![
            PunctualLight::Directional {
                direction: v(0.4, -1.0, -0.3).normalize(),
                irradiance: Vec3::splat(1.5),
            },
            PunctualLight::Spot {
                position: v(-1.0, 2.0, 1.0),
                direction: v(0.5, -1.0, -0.5).normalize(),
                intensity: Vec3::splat(4.0),
                inner_angle: 0.3,
                outer_angle: 0.5,
            },
        ],
        environment: Some(Vec3::splat(0.3)),
        environment_map: None,
        default_resolution: (24, 24),
        animated: false,
    };
    compare_scene_with_path("distant lights", &scene, 24, 24, 8);
}

#[test]
fn bdpt_agrees_with_path_on_the_cornell_box() {
    compare_with_path("builtin:cornell-box", 32, 32, 4, 32, 4);
}

#[test]
fn bdpt_agrees_with_path_on_veach_mis() {
    compare_with_path("builtin:veach-mis", 48, 32, 4, 32, 4);
}

#[test]
fn bdpt_furnace_is_uniform_2_5() {
    let scene = tessera_scene::load("builtin:furnace").unwrap();
    let (w, h) = (16, 16);
    let rs = RenderScene::build(&scene, w, h).unwrap();
    let plan = whole_frame_plan(w, h, 4, 32);
    let s = settings(Integrator::Bdpt, 3, 32);
    let stats = block_stats(&block_passes(&rs, &s, &plan, 4));
    let expected = (FURNACE_EMISSION / (1.0 - FURNACE_ALBEDO)) as f64;
    let reference = vec![(expected, 0.0); stats.len()];
    let worst = assert_blocks_agree("furnace bdpt vs 2.5", &stats, &reference);
    let mean = stats.iter().map(|b| b.0).sum::<f64>() / stats.len() as f64;
    eprintln!("furnace bdpt mean {mean:.5} (expected {expected}), max |z| {worst:.2}");
    assert!((mean - expected).abs() < 0.01 * expected);
}

/// A point light 2.2 m above a floating glass ball (radius 0.5, centre 0.8 m above a
/// diffuse floor): the ball focuses the light into a caustic on the floor below it. There
/// is no other light, so every path of the caustic is `L S* D E` from a delta light: a path
/// tracer with next-event estimation cannot sample it (the shadow ray is blocked by glass,
/// and BSDF sampling cannot hit a point).
fn point_light_caustic() -> Scene {
    let v = Vec3::new;
    let materials = vec![
        Material::diffuse("floor", Vec3::splat(0.8)),
        Material {
            name: "glass".into(),
            kind: MaterialKind::Dielectric {
                ior: 1.5,
                roughness: 0.0,
                tint: Vec3::ONE,
            },
            emission: Vec3::ZERO,
            double_sided: false,
        },
    ];
    let floor = Mesh {
        name: "floor".into(),
        positions: vec![
            v(-3.0, 0.0, -3.0),
            v(-3.0, 0.0, 3.0),
            v(3.0, 0.0, 3.0),
            v(3.0, 0.0, -3.0),
        ],
        normals: None,
        uvs: vec![],
        tangents: None,
        colors: None,
        indices: vec![[0, 1, 2], [0, 2, 3]],
        material: 0,
    };
    Scene {
        name: "test:point-light-caustic".into(),
        camera: look_at_camera(v(0.0, 2.5, 2.5), v(0.0, 0.0, 0.0), Vec3::Y, 30.0),
        meshes: vec![floor],
        prototypes: Vec::new(),
        instances: Vec::new(),
        spheres: vec![Sphere {
            center: v(0.0, 0.8, 0.0),
            radius: 0.5,
            material: 1,
        }],
        materials,
        textures: vec![],
        images: vec![],
        warnings: vec![],
        lights: vec![PunctualLight::Point {
            position: v(0.0, 3.0, 0.0),
            intensity: Vec3::splat(10.0),
        }],
        environment: None,
        environment_map: None,
        default_resolution: (32, 32),
        animated: false,
    }
}

#[test]
fn bdpt_renders_a_point_light_caustic_that_path_tracing_misses() {
    let scene = point_light_caustic();
    let (w, h) = (32, 32);
    let rs = RenderScene::build(&scene, w, h).unwrap();
    let block = 4;
    let plan = whole_frame_plan(w, h, 4, 32);
    let bd = block_stats(&block_passes(
        &rs,
        &settings(Integrator::Bdpt, 11, 8),
        &plan,
        block,
    ));
    // The converged reference: bdpt with another seed and 4x the samples.
    let ref_plan = whole_frame_plan(w, h, 16, 32);
    let reference = block_stats(&block_passes(
        &rs,
        &settings(Integrator::Bdpt, 12, 8),
        &ref_plan,
        block,
    ));
    assert_blocks_agree("point-light caustic bdpt vs reference", &bd, &reference);
    let pt = block_stats(&block_passes(
        &rs,
        &settings(Integrator::Path, 13, 8),
        &plan,
        block,
    ));
    // The caustic region: blocks the ball's shadow covers for a path tracer (direct light
    // blocked) but that bdpt finds bright.
    let lit = reference.iter().map(|b| b.0).fold(0.0f64, f64::max);
    let mut caustic = 0;
    let (mut e_bdpt, mut e_path) = (0.0, 0.0);
    for i in 0..reference.len() {
        if reference[i].0 > 0.2 * lit && pt[i].0 < 0.2 * reference[i].0 {
            caustic += 1;
            e_bdpt += bd[i].0;
            e_path += pt[i].0;
        }
    }
    eprintln!(
        "caustic region: {caustic} blocks, brightest block {lit:.4}; energy bdpt {e_bdpt:.4}, path {e_path:.6} ({:.2}% of bdpt)",
        100.0 * e_path / e_bdpt.max(1e-30)
    );
    assert!(caustic >= 2, "no caustic found: {caustic} blocks");
    assert!(e_path < 0.05 * e_bdpt, "path {e_path} vs bdpt {e_bdpt}");
}

use super::common::frame_bits as bits;

#[test]
fn bdpt_is_deterministic_across_threads_splits_and_reruns() {
    let scene = tessera_scene::load("builtin:cornell-box").unwrap();
    let (w, h) = (24, 20);
    let rs = RenderScene::build(&scene, w, h).unwrap();
    let plan = whole_frame_plan(w, h, 2, 6);
    let s = settings(Integrator::Bdpt, 42, 8);
    let one = render_frame(&rs, &s, &plan, 0, 1, |_, _| {});
    let two = render_frame(&rs, &s, &plan, 0, 2, |_, _| {});
    assert!(bits(&one) == bits(&two), "1 and 2 threads differ");
    // Pass ranges of 4 + 2, offered in reverse order.
    let mut units = plan.units(0, 4);
    units.reverse();
    let mut acc = FrameAccumulator::new(plan);
    for u in units {
        acc.offer(render_unit(&rs, &s, &plan, u)).unwrap();
    }
    assert!(bits(&acc) == bits(&one), "split units differ");
    let u = plan.units(0, 1)[3];
    assert_eq!(
        render_unit(&rs, &s, &plan, u).digest(),
        render_unit(&rs, &s, &plan, u).digest()
    );
    let other = render_frame(
        &rs,
        &settings(Integrator::Bdpt, 43, 8),
        &plan,
        0,
        2,
        |_, _| {},
    );
    assert!(bits(&other) != bits(&one));
}

/// Adaptive stopping: a bdpt unit asked for some pixels traces camera subpaths
/// only for them, and each of them gets bit for bit the value it has when every pixel is
/// rendered (the splats of the skipped pixels' light subpaths included). The caustic scene
/// has light-tracing splats everywhere on its floor, so a skipped light subpath would show.
#[test]
fn masked_bdpt_units_keep_the_wanted_pixels_bit_for_bit() {
    let scene = tessera_scene::load("builtin:caustic").unwrap();
    let (w, h) = (24, 16);
    let rs = RenderScene::build(&scene, w, h).unwrap();
    let plan = whole_frame_plan(w, h, 4, 3);
    let s = settings(Integrator::Bdpt, 7, 8);
    let pixels = (w * h) as usize;
    // A different set each pass, as the policy's decisions make it.
    let wanted = |i: usize, pass: u32| (i * 7 + pass as usize * 3) % 5 < 2;
    let asked = std::cell::Cell::new(0usize);
    for unit in plan.units(0, 3) {
        let full = render_unit(&rs, &s, &plan, unit);
        let masked = render_unit_where(&rs, &s, &plan, unit, |i, pass| {
            asked.set(asked.get() + 1);
            wanted(i, pass)
        });
        masked.validate(&plan).unwrap();
        let (mut kept, mut differ) = (0, 0);
        for (k, (f, m)) in full.pass_means.iter().zip(&masked.pass_means).enumerate() {
            let (i, pass) = (k % pixels, unit.first_pass + (k / pixels) as u32);
            if wanted(i, pass) {
                assert_eq!(
                    f.map(f32::to_bits),
                    m.map(f32::to_bits),
                    "pixel {i}, pass {pass}"
                );
                kept += 1;
            } else if f != m {
                differ += 1;
            }
        }
        assert!(kept > pixels / 2, "{kept}");
        // The skipped pixels really skipped their camera subpaths (their values changed).
        assert!(
            differ > pixels / 2,
            "{differ} of the skipped pixels changed"
        );
    }
    // Asked once per tile pixel and pass, not per sample.
    assert_eq!(asked.get(), pixels * plan.passes as usize);
}

/// A tiled plan (splats outside a unit's tile are produced by the other units' light
/// tracing of the whole frame) has the same expectation as the whole-frame plan.
#[test]
fn bdpt_with_small_tiles_matches_the_whole_frame_tile() {
    let scene = tessera_scene::load("builtin:cornell-box").unwrap();
    let (w, h) = (16, 16);
    let rs = RenderScene::build(&scene, w, h).unwrap();
    let s = settings(Integrator::Bdpt, 5, 8);
    let tiled = FramePlan::new(w, h, 8, 4, 32).unwrap();
    // 8 x 8 blocks (one per tile) per pass, whole frame vs tiles.
    let whole = block_stats(&block_passes(&rs, &s, &whole_frame_plan(w, h, 4, 32), 8));
    let tiled_blocks = {
        let units = tiled.units(0, 1);
        let results: Vec<_> = units
            .par_iter()
            .map(|u| {
                (
                    *u,
                    render_unit(&rs, &settings(Integrator::Bdpt, 6, 8), &tiled, *u),
                )
            })
            .collect();
        let mut per_pass = vec![vec![0.0f64; 4]; tiled.passes as usize];
        for (u, r) in results {
            let lum: f64 = r
                .pass_means
                .iter()
                .map(|m| 0.2126 * m[0] as f64 + 0.7152 * m[1] as f64 + 0.0722 * m[2] as f64)
                .sum::<f64>()
                / r.pass_means.len() as f64;
            per_pass[u.first_pass as usize][u.tile as usize] = lum;
        }
        block_stats(&per_pass)
    };
    assert_blocks_agree("bdpt tiled vs whole frame", &tiled_blocks, &whole);
}
