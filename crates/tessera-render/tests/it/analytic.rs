//! Renders of scenes with analytic answers: the furnace, and a diffuse plane under a
//! spherical light (irradiance π L sin² α). z-tests at 3 standard errors with the error
//! estimated from independent passes (Marschner, CS 6630 notes, statistical testing).

use crate::common::{image_mean, render};
use glam::Vec3;
use tessera_render::integrator::{Integrator, MisHeuristic};
use tessera_render::render::RenderConfig;
use tessera_render::sampling::SamplerKind;
use tessera_scene::builtin::{self, look_at_camera, FURNACE_ALBEDO, FURNACE_EMISSION};
use tessera_scene::{Material, MaterialKind, Mesh, Scene, Sphere};

fn settings(integrator: Integrator, mis: MisHeuristic, sampler: SamplerKind) -> RenderConfig {
    RenderConfig {
        integrator,
        mis,
        sampler,
        seed: 7,
        max_depth: 1000,
        rr_depth: 3,
    }
}

fn scaled_furnace(scale: f32) -> Scene {
    let mut s = builtin::furnace();
    for m in &mut s.meshes {
        for p in &mut m.positions {
            *p *= scale;
        }
    }
    s
}

#[test]
fn furnace_matches_analytic_radiance_at_every_scale() {
    let expected = (FURNACE_EMISSION / (1.0 - FURNACE_ALBEDO)) as f64;
    for scale in [1.0f32, 1e-4, 1e4] {
        for mis in [MisHeuristic::Power, MisHeuristic::Balance] {
            let acc = render(
                &scaled_furnace(scale),
                16,
                16,
                64,
                &settings(Integrator::Path, mis, SamplerKind::Sobol),
            );
            for c in 0..3 {
                let (mean, se) = image_mean(&acc, c);
                let z = (mean - expected) / se;
                eprintln!(
                    "furnace scale {scale} {mis} channel {c}: {mean:.5} ± {se:.5} (z = {z:.2})"
                );
                assert!(
                    z.abs() < 3.0,
                    "scale {scale}: {mean} vs {expected}, z = {z}"
                );
                assert!(
                    (mean - expected).abs() < 0.005 * expected,
                    "scale {scale}: {mean} vs {expected}"
                );
            }
        }
    }
}

/// A large diffuse plane at y = 0 under a spherical light of radius `r` centred at height
/// `h`, seen straight down through a very narrow camera so every pixel sees the point
/// under the centre.
fn plane_under_sphere(r: f32, h: f32, radiance: f32, albedo: f32) -> Scene {
    let v = Vec3::new;
    let materials = vec![
        Material::diffuse("plane", Vec3::splat(albedo)),
        Material {
            name: "light".into(),
            kind: MaterialKind::Diffuse { albedo: Vec3::ZERO },
            emission: Vec3::splat(radiance),
            double_sided: false,
        },
    ];
    let s = 100.0;
    let mesh = Mesh {
        name: "plane".into(),
        positions: vec![v(-s, 0.0, -s), v(-s, 0.0, s), v(s, 0.0, s), v(s, 0.0, -s)],
        normals: None,
        uvs: vec![],
        tangents: None,
        colors: None,
        indices: vec![[0, 1, 2], [0, 2, 3]],
        material: 0,
    };
    // The camera sits between the plane and the light, looking straight down.
    let camera = look_at_camera(v(0.0, 0.5 * (h - r), 0.0), Vec3::ZERO, Vec3::Z, 0.2);
    Scene {
        name: "plane-under-sphere".into(),
        camera,
        meshes: vec![mesh],
        prototypes: Vec::new(),
        instances: Vec::new(),
        spheres: vec![Sphere {
            center: v(0.0, h, 0.0),
            radius: r,
            material: 1,
        }],
        materials,
        textures: vec![],
        images: vec![],
        warnings: vec![],
        lights: vec![],
        environment: None,
        environment_map: None,
        default_resolution: (8, 8),
        animated: false,
    }
}

#[test]
fn plane_under_spherical_light_matches_pi_l_sin2_alpha() {
    // Irradiance from a sphere of radiance L subtending half-angle α: E = π L sin² α; a
    // Lambertian plane of albedo ρ reflects radiance ρ E / π = ρ L sin² α.
    let (albedo, radiance) = (0.5f32, 10.0f32);
    for (r, h) in [(0.5f32, 2.0f32), (0.02, 3.0), (1.5, 2.0)] {
        let sin2 = (r / h) * (r / h);
        let expected = (albedo * radiance * sin2) as f64;
        let scene = plane_under_sphere(r, h, radiance, albedo);
        for (integrator, mis, sampler) in [
            (Integrator::Direct, MisHeuristic::Power, SamplerKind::Sobol),
            (
                Integrator::Path,
                MisHeuristic::Balance,
                SamplerKind::Independent,
            ),
            (
                Integrator::Direct,
                MisHeuristic::Maximum,
                SamplerKind::Sobol,
            ),
            (
                Integrator::Direct,
                MisHeuristic::Cutoff(0.1),
                SamplerKind::Independent,
            ),
        ] {
            let acc = render(&scene, 8, 8, 256, &settings(integrator, mis, sampler));
            let (mean, se) = image_mean(&acc, 0);
            let z = (mean - expected) / se.max(1e-12);
            eprintln!("sphere r {r} h {h} {integrator} {mis}: {mean:.6e} ± {se:.3e} vs {expected:.6e} (z = {z:.2}, rel {:.2e})", (mean - expected) / expected);
            // The cone estimator is nearly exact for tiny lights; allow f32 rounding (1e-4).
            assert!(
                (mean - expected).abs() < 3.0 * se + 1e-4 * expected,
                "r {r} h {h} {integrator} {mis}: {mean} vs {expected}, z = {z}"
            );
        }
    }
}
