//! Image environments against known answers: a furnace (a white Lambertian sphere inside a
//! constant image environment of radiance 1 is invisible: every pixel is 1), and an image
//! that is black but for one small bright texel lights a floor as a directional light of
//! the same irradiance does. z-tests of image means with their estimated standard errors.

use crate::common::{image_mean, render};
use glam::Vec3;
use tessera_render::integrator::Integrator;
use tessera_render::render::RenderConfig;
use tessera_scene::builtin::{self, look_at_camera};
use tessera_scene::{EnvironmentMap, Material, Mesh, PunctualLight, Scene, Sphere};

fn config(integrator: Integrator) -> RenderConfig {
    RenderConfig {
        integrator,
        seed: 11,
        max_depth: 1000,
        rr_depth: 3,
        ..RenderConfig::default()
    }
}

/// A scene with nothing but `meshes`, `spheres` (material 0, Lambertian of `albedo`) and
/// a camera at `eye` looking at `target`.
fn bare(meshes: Vec<Mesh>, spheres: Vec<Sphere>, albedo: f32, eye: Vec3, target: Vec3) -> Scene {
    let mut s = builtin::furnace();
    s.name = "environment test".into();
    s.meshes = meshes;
    s.spheres = spheres;
    s.materials = vec![Material::diffuse("white", Vec3::splat(albedo))];
    s.camera = look_at_camera(eye, target, Vec3::Y, 40.0);
    s.lights.clear();
    s.environment = None;
    s.environment_map = None;
    s
}

#[test]
fn a_white_sphere_vanishes_in_a_constant_image_furnace() {
    // 8x4 texels of 1 (with a rotation, which must not matter): the image environment's
    // importance sampling, MIS and light-tree selection on a furnace with answer 1.
    let map = EnvironmentMap::new("ones", 8, 4, vec![Vec3::ONE; 32])
        .unwrap()
        .rotated(30.0);
    let sphere = Sphere {
        center: Vec3::ZERO,
        radius: 1.0,
        material: 0,
    };
    let mut scene = bare(
        vec![],
        vec![sphere],
        1.0,
        Vec3::new(0.0, 0.0, 4.0),
        Vec3::ZERO,
    );
    scene.environment = Some(Vec3::ONE);
    scene.environment_map = Some(map);
    scene.validate().unwrap();
    for integrator in [Integrator::Path, Integrator::Bdpt] {
        let acc = render(&scene, 16, 16, 64, &config(integrator));
        for c in 0..3 {
            let (mean, se) = image_mean(&acc, c);
            let z = (mean - 1.0) / se.max(1e-9);
            eprintln!("furnace {integrator:?} channel {c}: {mean:.5} ± {se:.5} (z = {z:.2})");
            assert!(z.abs() < 4.0, "{integrator:?}: {mean} ± {se}, expected 1");
        }
    }
}

/// A floor of albedo 0.5 (y = 0, 40 units wide) seen from above, lit by `light` or by
/// `env`.
fn floor(env: Option<EnvironmentMap>, light: Option<PunctualLight>) -> Scene {
    let v = Vec3::new;
    let s = 20.0;
    let mesh = Mesh {
        name: "floor".into(),
        positions: vec![v(-s, 0.0, -s), v(-s, 0.0, s), v(s, 0.0, s), v(s, 0.0, -s)],
        indices: vec![[0, 1, 2], [0, 2, 3]],
        ..Mesh::default()
    };
    let mut scene = bare(vec![mesh], vec![], 0.5, v(0.0, 2.0, 0.5), Vec3::ZERO);
    if let Some(m) = env {
        scene.environment = Some(Vec3::ONE);
        scene.environment_map = Some(m);
    }
    scene.lights.extend(light);
    scene.validate().unwrap();
    scene
}

#[test]
fn one_bright_texel_lights_like_a_directional_light_of_equal_irradiance() {
    // A 512x256 map, black but for texel (col, row) of radiance L: a cone of ~0.7°.
    let (w, h) = (512u32, 256u32);
    let (col, row) = (200u32, 60u32);
    let l = 5000.0f32;
    let mut texels = vec![Vec3::ZERO; (w * h) as usize];
    texels[(row * w + col) as usize] = Vec3::new(l, 0.5 * l, 0.25 * l);
    let rotation = 20.0f32;
    let map = EnvironmentMap::new("one texel", w, h, texels)
        .unwrap()
        .rotated(rotation);
    // The texel's centre direction and solid angle (module docs of the environment).
    let pi = std::f64::consts::PI;
    let theta = pi * (row as f64 + 0.5) / h as f64;
    let phi = 2.0 * pi * ((col as f64 + 0.5) / w as f64 - 0.5);
    let d = glam::DVec3::new(
        theta.sin() * phi.cos(),
        theta.cos(),
        theta.sin() * phi.sin(),
    );
    let d = glam::DMat3::from_rotation_y((rotation as f64).to_radians()) * d;
    let omega = 2.0 * pi / w as f64
        * ((pi * row as f64 / h as f64).cos() - (pi * (row + 1) as f64 / h as f64).cos());
    // Irradiance on a surface facing the texel: L Ω (the cosine varies by < 1e-4 over it).
    let e = Vec3::new(l, 0.5 * l, 0.25 * l) * omega as f32;
    let directional = PunctualLight::Directional {
        direction: -d.as_vec3(),
        irradiance: e,
    };
    for integrator in [Integrator::Direct, Integrator::Path, Integrator::Bdpt] {
        let spp = 64;
        let a = render(
            &floor(Some(map.clone()), None),
            12,
            12,
            spp,
            &config(integrator),
        );
        let b = render(
            &floor(None, Some(directional)),
            12,
            12,
            spp,
            &config(integrator),
        );
        for c in 0..3 {
            let (ma, sa) = image_mean(&a, c);
            let (mb, sb) = image_mean(&b, c);
            let z = (ma - mb) / (sa * sa + sb * sb).sqrt().max(1e-9);
            eprintln!(
                "one texel vs directional, {integrator:?} channel {c}: {ma:.6} ± {sa:.6} vs \
                 {mb:.6} ± {sb:.6} (z = {z:.2}, relative difference {:.1e})",
                (ma - mb) / mb
            );
            assert!(mb > 0.0, "the directional light must reach the floor");
            // Statistics, plus the texel's extent (cosine over 0.7°: < 1e-4 relative).
            assert!(
                z.abs() < 4.0 || (ma - mb).abs() < 2e-4 * mb,
                "{integrator:?} channel {c}: {ma} ± {sa} vs {mb} ± {sb}"
            );
        }
    }
}
