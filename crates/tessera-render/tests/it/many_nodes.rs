//! Scenes with very many nodes or primitives, loaded from .glb bytes as a worker loads
//! them.
//!
//! 300,000 instancing nodes (one small mesh placed by every node) import as one prototype
//! with 300,000 instances, analyse and build their two-level BVH, and a ray finds them.
//! The time of each step is printed (run with `--nocapture`), never asserted: every step
//! is linear in the node count (about 2 s in all for 300,000 nodes on the CI machine).
//!
//! Coincident geometry (one triangle repeated, or one mesh instanced many times at one
//! place) builds in `O(n log n)` and a shallow tree, on a thread with tokio's 2 MiB
//! `spawn_blocking` stack: the work is bounded through the geometry's build statistics,
//! not by wall-clock time.

use glam::Vec3;
use std::time::Instant;
use tessera_farm::job::SceneRef;
use tessera_render::geometry::{BvhBuildStats, Primitive, NO_INSTANCE};
use tessera_render::scene::RenderScene;

/// A .glb of `n` nodes on a cubic grid, each placing mesh 0 (a unit cube, 12 triangles)
/// at half scale, plus a point light.
fn grid_of_cubes(n: usize) -> Vec<u8> {
    let mut bin: Vec<u8> = Vec::new();
    for x in [0.0f32, 1.0] {
        for y in [0.0f32, 1.0] {
            for z in [0.0f32, 1.0] {
                for v in [x, y, z] {
                    bin.extend_from_slice(&v.to_le_bytes());
                }
            }
        }
    }
    let idx: [u16; 36] = [
        0, 1, 3, 0, 3, 2, 4, 6, 7, 4, 7, 5, 0, 4, 5, 0, 5, 1, 2, 3, 7, 2, 7, 6, 0, 2, 6, 0, 6, 4,
        1, 5, 7, 1, 7, 3,
    ];
    for i in idx {
        bin.extend_from_slice(&i.to_le_bytes());
    }
    let side = (n as f64).cbrt().ceil() as usize;
    let mut nodes: Vec<serde_json::Value> = (0..n)
        .map(|i| {
            let (x, y, z) = (i % side, (i / side) % side, i / (side * side));
            serde_json::json!({"mesh": 0, "scale": [0.5, 0.5, 0.5],
                "translation": [2.0 * x as f64, 2.0 * y as f64, -2.0 * z as f64 - 5.0]})
        })
        .collect();
    nodes.push(serde_json::json!({"translation": [0, 0, 10],
        "extensions": {"KHR_lights_punctual": {"light": 0}}}));
    let doc = serde_json::json!({
        "asset": {"version": "2.0"}, "scene": 0,
        "scenes": [{"nodes": (0..=n).collect::<Vec<usize>>()}],
        "nodes": nodes,
        "extensionsUsed": ["KHR_lights_punctual"],
        "extensions": {"KHR_lights_punctual": {"lights": [{"type": "point", "intensity": 1000}]}},
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 8, "type": "VEC3",
             "min": [0, 0, 0], "max": [1, 1, 1]},
            {"bufferView": 1, "componentType": 5123, "count": 36, "type": "SCALAR"}],
        "bufferViews": [{"buffer": 0, "byteLength": 96},
                        {"buffer": 0, "byteOffset": 96, "byteLength": 72}],
        "buffers": [{"byteLength": bin.len()}],
    });
    glb(&doc, bin)
}

/// A binary glTF of the JSON `doc` and its buffer `bin` (the test kit's packer).
fn glb(doc: &serde_json::Value, bin: Vec<u8>) -> Vec<u8> {
    tessera_testkit::gltf_gen::glb(&serde_json::to_vec(doc).unwrap(), &bin)
}

#[test]
fn a_scene_of_300000_instancing_nodes_imports_and_builds() {
    const N: usize = 300_000;
    let t = Instant::now();
    let glb = grid_of_cubes(N);
    let generated = t.elapsed();
    let t = Instant::now();
    let scene = tessera_scene::gltf_import::load_slice(&glb, "grid.glb", None, None).unwrap();
    let imported = t.elapsed();
    assert_eq!(scene.prototypes.len(), 1);
    assert_eq!(scene.instances.len(), N);
    assert_eq!(scene.stored_triangle_count(), 12);
    assert_eq!(scene.triangle_count(), 12 * N);
    let t = Instant::now();
    let plan = tessera_scene::analysis::analyse(&scene);
    let analysed = t.elapsed();
    assert!(plan.summary().contains("light"), "{}", plan.summary());
    let t = Instant::now();
    let rs = RenderScene::build(&scene, 16, 16).unwrap();
    let built = t.elapsed();
    // A ray down -Z through the first column of cubes hits the front face of cube 0,
    // whose front (z = -5 + 0.5) faces the camera.
    let origin = glam::Vec3::new(0.25, 0.25, 10.0);
    let hit = rs.intersect(origin, -glam::Vec3::Z, f32::INFINITY).unwrap();
    assert!((hit.t - 14.5).abs() < 1e-3, "{}", hit.t);
    eprintln!(
        "{N} nodes ({} bytes): generate {generated:.2?}, import {imported:.2?}, \
         analyse {analysed:.2?}, build {built:.2?}",
        glb.len()
    );
}

/// A .glb: mesh 0 is `triangles` copies of the triangle (0,0,0), (1,0,0), (0,1,0) (the
/// last index repeated), placed by `nodes` nodes without transform (so with two or more
/// nodes it is instanced), plus a point light.
fn coincident_glb(triangles: usize, nodes: usize) -> Vec<u8> {
    let mut bin: Vec<u8> = Vec::new();
    for v in [0.0f32, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0] {
        bin.extend_from_slice(&v.to_le_bytes());
    }
    for _ in 0..triangles {
        for i in [0u32, 1, 2] {
            bin.extend_from_slice(&i.to_le_bytes());
        }
    }
    let mut node_list: Vec<serde_json::Value> =
        (0..nodes).map(|_| serde_json::json!({"mesh": 0})).collect();
    node_list.push(serde_json::json!({"translation": [0, 0, 10],
        "extensions": {"KHR_lights_punctual": {"light": 0}}}));
    let doc = serde_json::json!({
        "asset": {"version": "2.0"}, "scene": 0,
        "scenes": [{"nodes": (0..=nodes).collect::<Vec<usize>>()}],
        "nodes": node_list,
        "extensionsUsed": ["KHR_lights_punctual"],
        "extensions": {"KHR_lights_punctual": {"lights": [{"type": "point", "intensity": 1000}]}},
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
             "min": [0, 0, 0], "max": [1, 1, 0]},
            {"bufferView": 1, "componentType": 5125, "count": 3 * triangles, "type": "SCALAR"}],
        "bufferViews": [{"buffer": 0, "byteLength": 36},
                        {"buffer": 0, "byteOffset": 36, "byteLength": 12 * triangles}],
        "buffers": [{"byteLength": bin.len()}],
    });
    glb(&doc, bin)
}

/// Loads `glb` as an uploaded scene and builds it on a 2 MiB stack, as a worker does.
fn build_like_a_worker(glb: Vec<u8>) -> RenderScene {
    std::thread::Builder::new()
        .stack_size(2 << 20)
        .spawn(move || {
            let job_scene = tessera_farm::job::JobScene {
                source: SceneRef::Hash("coincident".into()),
                camera: None,
                fps: tessera_farm::job::DEFAULT_FPS,
                animation: None,
                shutter: None,
            };
            let time = tessera_scene::job::resolution_time(&job_scene);
            let scene = tessera_scene::job::load_job_scene_at(&job_scene, Some(&glb), &time)
                .expect("the scene loads");
            RenderScene::build(&scene, 16, 16).expect("the scene builds")
        })
        .unwrap()
        .join()
        .expect("the build does not overflow a 2 MiB stack")
}

/// `⌈log2 n⌉`.
fn ceil_log2(n: u64) -> u64 {
    u64::from(u64::BITS - n.saturating_sub(1).leading_zeros())
}

/// The build's work is within the documented `2 n ⌈log2 n⌉ + 6 n` and its trees are
/// `O(log n)` deep; `crowd` primitives were clustered.
fn assert_n_log_n(stats: &BvhBuildStats, crowd: u64) {
    let n = stats.primitives;
    assert!(stats.clustered >= crowd, "{stats:?}");
    assert!(stats.work <= 2 * n * ceil_log2(n) + 6 * n, "{stats:?}");
    assert!(u64::from(stats.max_depth) <= ceil_log2(n) + 4, "{stats:?}");
    assert!(
        stats.ploc_inputs <= n - crowd + 1 + stats.clusters,
        "{stats:?}"
    );
}

/// A ray down onto the triangle hits it at distance 10; one beside it misses.
fn assert_rays(rs: &RenderScene, instanced: bool) {
    let hit = rs
        .intersect(Vec3::new(0.2, 0.3, 10.0), -Vec3::Z, f32::INFINITY)
        .expect("the coincident triangles are hit");
    assert!((hit.t - 10.0).abs() < 1e-5, "t {}", hit.t);
    match hit.primitive {
        Primitive::Triangle { instance, .. } => {
            assert_eq!(instance != NO_INSTANCE, instanced, "{:?}", hit.primitive)
        }
        other => panic!("hit {other:?}"),
    }
    assert!(rs.occluded(Vec3::new(0.2, 0.3, 10.0), -Vec3::Z, 20.0));
    assert!(rs
        .intersect(Vec3::new(0.8, 0.8, 10.0), -Vec3::Z, f32::INFINITY)
        .is_none());
}

#[test]
fn coincident_triangles_build_in_n_log_n() {
    for n in [10_000usize, 40_000, 300_000] {
        let rs = build_like_a_worker(coincident_glb(n, 1));
        let stats = rs.geometry.build_stats();
        println!("{n} coincident triangles: {stats:?}");
        assert_eq!(stats.primitives, n as u64);
        assert_n_log_n(&stats, n as u64);
        assert_rays(&rs, false);
    }
}

#[test]
fn instances_of_one_mesh_at_the_origin_build_in_n_log_n() {
    for n in [10_000usize, 40_000, 300_000] {
        let rs = build_like_a_worker(coincident_glb(1, n));
        let stats = rs.geometry.build_stats();
        println!("{n} instances at the origin: {stats:?}");
        assert_eq!(rs.geometry.instances.len(), n);
        assert_n_log_n(&stats, n as u64);
        assert_rays(&rs, true);
    }
}
