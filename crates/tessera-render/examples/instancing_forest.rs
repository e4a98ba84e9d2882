//! Memory and build time of instancing against flattening, side by side in one run: a
//! forest of procedurally generated trees (a few thousand triangles each) on a grid, each
//! with a random rotation about the vertical and a random scale from a fixed seed, built
//! into a [`RenderScene`] once with the tree stored once (two-level BVH) and once
//! flattened to world space (one BVH over every copy), then traced with the same rays.
//!
//! ```text
//! cargo run --release -p tessera-render --example instancing_forest [-- TREES]
//! ```
//!
//! Memory is reported two ways: the bytes of the acceleration structures and triangle
//! records computed from their lengths ([`tessera_render::geometry::Geometry::bytes`]),
//! and the growth of the resident set (`VmRSS` in `/proc/self/status`) while the built
//! scene is alive, which also counts the scene description and the shading copies.

use glam::{Affine3A, Quat, Vec3};
use std::time::Instant;
use tessera_render::scene::RenderScene;
use tessera_scene::builtin::look_at_camera;
use tessera_scene::{Instance, Material, Mesh, PunctualLight, Scene};

/// A small deterministic generator (PCG-style LCG), so every run builds the same forest.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> f32 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((self.0 >> 40) as f32) / (1u64 << 24) as f32
    }
}

/// A tree: a trunk (cylinder, 24 sides) and a lumpy crown (a latitude–longitude sphere of
/// 48 x 24 quads displaced by a few sines), 2,352 triangles with smooth normals.
fn tree() -> Mesh {
    let mut positions = Vec::new();
    let mut indices = Vec::new();
    let sides = 24u32;
    // Trunk: rings at y = 0 and y = 1.2 of radius 0.12.
    for ring in 0..2 {
        for i in 0..sides {
            let a = i as f32 / sides as f32 * std::f32::consts::TAU;
            positions.push(Vec3::new(0.12 * a.cos(), 1.2 * ring as f32, 0.12 * a.sin()));
        }
    }
    for i in 0..sides {
        let j = (i + 1) % sides;
        indices.push([i, sides + j, j]);
        indices.push([i, sides + i, sides + j]);
    }
    // Crown: centre (0, 2, 0), radius about 0.9.
    let (nu, nv) = (48u32, 24u32);
    let base = positions.len() as u32;
    for v in 0..=nv {
        let theta = v as f32 / nv as f32 * std::f32::consts::PI;
        for u in 0..=nu {
            let phi = u as f32 / nu as f32 * std::f32::consts::TAU;
            let d = Vec3::new(
                theta.sin() * phi.cos(),
                theta.cos(),
                theta.sin() * phi.sin(),
            );
            let r = 0.9 + 0.08 * (5.0 * phi).sin() * (4.0 * theta).sin();
            positions.push(Vec3::new(0.0, 2.0, 0.0) + d * r);
        }
    }
    for v in 0..nv {
        for u in 0..nu {
            let a = base + v * (nu + 1) + u;
            let b = a + nu + 1;
            indices.push([a, a + 1, b + 1]);
            indices.push([a, b + 1, b]);
        }
    }
    // Smooth normals: area-weighted face normals summed per vertex.
    let mut normals = vec![Vec3::ZERO; positions.len()];
    for t in &indices {
        let p = t.map(|i| positions[i as usize]);
        let n = (p[1] - p[0]).cross(p[2] - p[0]);
        for &i in t {
            normals[i as usize] += n;
        }
    }
    let normals = normals
        .into_iter()
        .map(|n| n.try_normalize().unwrap_or(Vec3::Y))
        .collect();
    Mesh {
        name: "tree".into(),
        positions,
        normals: Some(normals),
        uvs: vec![],
        tangents: None,
        colors: None,
        indices,
        material: 0,
    }
}

/// `trees` instances of [`tree`] on a square grid 3 units apart, rotated about +Y and
/// scaled by 0.7 to 1.3, over a ground quad.
fn forest(trees: usize) -> Scene {
    let side = (trees as f32).sqrt().ceil() as usize;
    let extent = side as f32 * 3.0;
    let mut rng = Rng(20261202);
    let instances = (0..trees)
        .map(|i| {
            let (x, z) = ((i % side) as f32 * 3.0, (i / side) as f32 * 3.0);
            let q = Quat::from_rotation_y(std::f32::consts::TAU * rng.next());
            let s = 0.7 + 0.6 * rng.next();
            Instance {
                prototype: 0,
                world_from_object: Affine3A::from_scale_rotation_translation(
                    Vec3::splat(s),
                    q,
                    Vec3::new(x, 0.0, z),
                ),
            }
        })
        .collect();
    let ground = Mesh {
        name: "ground".into(),
        positions: vec![
            Vec3::new(-2.0, 0.0, -2.0),
            Vec3::new(extent, 0.0, -2.0),
            Vec3::new(extent, 0.0, extent),
            Vec3::new(-2.0, 0.0, extent),
        ],
        normals: None,
        uvs: vec![],
        tangents: None,
        colors: None,
        indices: vec![[0, 2, 1], [0, 3, 2]],
        material: 1,
    };
    Scene {
        name: format!("forest of {trees}"),
        camera: look_at_camera(
            Vec3::new(-10.0, 20.0, -10.0),
            Vec3::new(extent * 0.5, 0.0, extent * 0.5),
            Vec3::Y,
            50.0,
        ),
        meshes: vec![ground],
        prototypes: vec![tree()],
        instances,
        spheres: vec![],
        materials: vec![
            Material::diffuse("leaves", Vec3::new(0.2, 0.5, 0.2)),
            Material::diffuse("ground", Vec3::splat(0.4)),
        ],
        textures: vec![],
        images: vec![],
        warnings: vec![],
        lights: vec![PunctualLight::Directional {
            direction: Vec3::new(0.3, -1.0, 0.2).normalize(),
            irradiance: Vec3::splat(3.0),
        }],
        environment: Some(Vec3::splat(0.3)),
        environment_map: None,
        default_resolution: (64, 64),
        animated: false,
    }
}

/// A field of `/proc/self/status` in bytes (`VmRSS`, `VmHWM`), 0 where unavailable.
fn status_bytes(field: &str) -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with(field))
                .and_then(|l| l.split_whitespace().nth(1)?.parse::<u64>().ok())
        })
        .map_or(0, |kb| kb * 1024)
}

/// What one representation cost.
struct Figures {
    stored_triangles: usize,
    geometry_bytes: usize,
    rss_growth: u64,
    build_seconds: f64,
    trace_seconds: f64,
    hits: usize,
}

/// Builds `scene` and traces `rays` through it.
fn measure(scene: Scene, rays: &[(Vec3, Vec3)]) -> Figures {
    let stored_triangles = scene.stored_triangle_count();
    let rss_before = status_bytes("VmRSS:");
    let start = Instant::now();
    let rs = RenderScene::build(&scene, 64, 64).expect("forest builds");
    let build_seconds = start.elapsed().as_secs_f64();
    drop(scene);
    let rss_growth = status_bytes("VmRSS:").saturating_sub(rss_before);
    let start = Instant::now();
    let hits = rays
        .iter()
        .filter(|(o, d)| rs.intersect(*o, *d, f32::INFINITY).is_some())
        .count();
    let trace_seconds = start.elapsed().as_secs_f64();
    Figures {
        stored_triangles,
        geometry_bytes: rs.geometry.bytes(),
        rss_growth,
        build_seconds,
        trace_seconds,
        hits,
    }
}

fn main() {
    let trees: usize = std::env::args()
        .nth(1)
        .map_or(10_000, |a| a.parse().expect("TREES is a number"));
    let instanced = forest(trees);
    instanced.validate().expect("valid forest");
    let rendered = instanced.triangle_count();
    // Rays from above the forest at random points of it, slanting down.
    let extent = (trees as f32).sqrt().ceil() * 3.0;
    let mut rng = Rng(7);
    let rays: Vec<(Vec3, Vec3)> = (0..1_000_000)
        .map(|_| {
            let o = Vec3::new(rng.next() * extent, 6.0, rng.next() * extent);
            let d = Vec3::new(rng.next() - 0.5, -1.0, rng.next() - 0.5).normalize();
            (o, d)
        })
        .collect();
    let start = Instant::now();
    let flat = instanced.flattened();
    let flatten_seconds = start.elapsed().as_secs_f64();
    drop(flat);
    println!(
        "forest: {trees} trees of {} triangles, {rendered} triangles rendered",
        instanced.prototypes[0].indices.len()
    );
    println!("(flattening the scene description itself took {flatten_seconds:.2} s)");
    let two_level = measure(instanced.clone(), &rays);
    let flattened = measure(instanced.flattened(), &rays);
    assert_eq!(two_level.hits, flattened.hits, "both see the same forest");
    let mib = |b: f64| b / (1024.0 * 1024.0);
    println!("| | stored triangles | geometry (BVH + triangles) | RSS growth | build | 1 M rays |");
    println!("|---|---:|---:|---:|---:|---:|");
    for (name, f) in [("two-level", &two_level), ("flattened", &flattened)] {
        println!(
            "| {name} | {} | {:.1} MiB | {:.1} MiB | {:.3} s | {:.3} s |",
            f.stored_triangles,
            mib(f.geometry_bytes as f64),
            mib(f.rss_growth as f64),
            f.build_seconds,
            f.trace_seconds
        );
    }
    println!(
        "ratio flattened / two-level: geometry {:.0}x, build time {:.0}x; peak RSS {:.0} MiB",
        flattened.geometry_bytes as f64 / two_level.geometry_bytes as f64,
        flattened.build_seconds / two_level.build_seconds,
        mib(status_bytes("VmHWM:") as f64)
    );
}
