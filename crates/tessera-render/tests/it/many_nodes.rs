//! The robustness issue's scene of 300,000 instancing nodes (one small mesh placed by
//! every node): it imports as one prototype with 300,000 instances, analyses and builds
//! its two-level BVH, and a ray finds it. The time of each step is printed (run with
//! `--nocapture`), never asserted: every step is linear in the node count (about 2 s in
//! all for 300,000 nodes on the CI machine).

use std::time::Instant;
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
    tessera_testkit::gltf_gen::glb(&serde_json::to_vec(&doc).unwrap(), &bin)
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
