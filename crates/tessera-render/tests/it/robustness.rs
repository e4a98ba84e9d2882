//! Numerical robustness of ray tracing: no self-intersection of spawned rays at grazing
//! angles, at scene scales from 1e-4 to 1e4 and far from the origin (pbrt 3rd ed. §3.9
//! error bounds and ray-origin offsets).

use crate::common::Rng;
use glam::Vec3;
use tessera_render::geometry::Primitive;
use tessera_render::math::offset_ray_origin;
use tessera_render::scene::RenderScene;
use tessera_scene::builtin::look_at_camera;
use tessera_scene::{Material, Mesh, Scene, Sphere};

/// A tilted, irregular triangle mesh patch (a gently folded sheet) plus a sphere, scaled by
/// `scale` and translated by `offset`.
fn scene(scale: f32, offset: Vec3) -> Scene {
    let n = 8;
    let mut positions = Vec::new();
    for j in 0..=n {
        for i in 0..=n {
            let (x, z) = (i as f32 / n as f32 - 0.5, j as f32 / n as f32 - 0.5);
            let y = 0.05 * (3.0 * x).sin() * (2.0 * z).cos() + 0.3 * x;
            positions.push(Vec3::new(x, y, z) * scale + offset);
        }
    }
    let mut indices = Vec::new();
    for j in 0..n {
        for i in 0..n {
            let a = (j * (n + 1) + i) as u32;
            let (b, c, d) = (a + 1, a + n as u32 + 2, a + n as u32 + 1);
            indices.push([a, d, c]);
            indices.push([a, c, b]);
        }
    }
    Scene {
        name: "robustness".into(),
        camera: look_at_camera(
            offset + Vec3::new(0.0, 2.0, 2.0) * scale,
            offset,
            Vec3::Y,
            40.0,
        ),
        prototypes: Vec::new(),
        instances: Vec::new(),
        meshes: vec![Mesh {
            name: "sheet".into(),
            positions,
            normals: None,
            uvs: vec![],
            tangents: None,
            colors: None,
            indices,
            material: 0,
        }],
        spheres: vec![Sphere {
            center: offset + Vec3::new(0.0, 2.0, 0.0) * scale,
            radius: 0.5 * scale,
            material: 0,
        }],
        materials: vec![Material::diffuse("grey", Vec3::splat(0.5))],
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
fn spawned_rays_never_hit_their_own_surface() {
    for scale in [1e-4f32, 1.0, 1e4] {
        for offset in [Vec3::ZERO, Vec3::new(3.0, -7.0, 11.0) * scale * 100.0] {
            let s = scene(scale, offset);
            let rs = RenderScene::build(&s, 8, 8).unwrap();
            let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
            let (mut tested, mut self_hits, mut sphere_tested) = (0, 0, 0);
            for _ in 0..20000 {
                // Aim at a random point of the sheet from a random direction above it, at
                // grazing angles as often as not.
                let target =
                    offset + Vec3::new(rng.next() - 0.5, 0.0, rng.next() - 0.5) * 0.9 * scale;
                let target = target + Vec3::new(0.0, 0.3 * (target.x - offset.x), 0.0);
                let elevation = if rng.next() < 0.5 {
                    1e-3 + 0.05 * rng.next()
                } else {
                    rng.next()
                };
                let phi = std::f32::consts::TAU * rng.next();
                let dir_to = Vec3::new(
                    phi.cos() * (1.0 - elevation * elevation).sqrt(),
                    elevation,
                    phi.sin() * (1.0 - elevation * elevation).sqrt(),
                );
                let origin = target + dir_to * 0.7 * scale;
                let d = (target - origin).normalize();
                let Some(hit) = rs.geometry.intersect(origin, d, f32::INFINITY) else {
                    continue;
                };
                let Primitive::Triangle { index, .. } = hit.primitive else {
                    continue;
                };
                let sp = rs.surface(&hit, origin, d);
                // Reflect (leave on the incoming side) and transmit (continue through).
                let reflected = d - 2.0 * d.dot(sp.ng) * sp.ng;
                for w in [reflected, d] {
                    let o = offset_ray_origin(sp.p, sp.p_error, sp.ng, w);
                    tested += 1;
                    if let Some(h2) = rs.geometry.intersect(o, w, f32::INFINITY) {
                        if let Primitive::Triangle { index: i2, .. } = h2.primitive {
                            // Re-hitting the same triangle is always a self-intersection; a
                            // neighbour within a tiny distance is one too.
                            if i2 == index || h2.t < 1e-3 * scale {
                                self_hits += 1;
                            }
                        }
                    }
                }
                // A shadow ray from the hit back to the origin must be unoccluded.
                let o = offset_ray_origin(sp.p, sp.p_error, sp.ng, -d);
                let back = origin - o;
                let dist = back.length();
                if rs.geometry.occluded(o, back / dist, dist * (1.0 - 1e-4)) {
                    self_hits += 1;
                }
            }
            // Rays leaving the sphere outward never re-hit it; rays entering reach the far side.
            let sphere = s.spheres[0];
            for _ in 0..5000 {
                let u = Vec3::new(rng.next() - 0.5, rng.next() - 0.5, rng.next() - 0.5).normalize();
                let origin = sphere.center + u * sphere.radius * 3.0;
                let target = sphere.center
                    + (Vec3::new(rng.next(), rng.next(), rng.next()) - 0.5).normalize()
                        * sphere.radius
                        * 0.999;
                let d = (target - origin).normalize();
                let Some(hit) = rs.geometry.intersect(origin, d, f32::INFINITY) else {
                    continue;
                };
                let Primitive::Sphere { .. } = hit.primitive else {
                    continue;
                };
                let sp = rs.surface(&hit, origin, d);
                sphere_tested += 1;
                let out = d - 2.0 * d.dot(sp.ng) * sp.ng;
                let o = offset_ray_origin(sp.p, sp.p_error, sp.ng, out);
                if let Some(h2) = rs.geometry.intersect(o, out, f32::INFINITY) {
                    if matches!(h2.primitive, Primitive::Sphere { index: 0 }) {
                        self_hits += 1;
                    }
                }
                let o = offset_ray_origin(sp.p, sp.p_error, sp.ng, d);
                match rs.geometry.intersect(o, d, f32::INFINITY) {
                    Some(h2) if matches!(h2.primitive, Primitive::Sphere { index: 0 }) => {
                        // The far side: a chord, not a re-hit at the entry point.
                        if h2.t < 1e-4 * sphere.radius {
                            self_hits += 1;
                        }
                    }
                    _ => self_hits += 1,
                }
            }
            eprintln!(
                "scale {scale} offset {offset}: {tested} triangle rays, {sphere_tested} sphere hits, \
                 {self_hits} self-intersections"
            );
            assert!(tested > 10000 && sphere_tested > 1000);
            assert_eq!(self_hits, 0, "scale {scale}, offset {offset}");
        }
    }
}
