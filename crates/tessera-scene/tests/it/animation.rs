//! Animation, skins and morph targets on files made in Blender 5.0 and exported
//! with its glTF exporter (`tests/fixtures/animation/make_animation.py`): a keyframed
//! cube's position in each interpolation mode against values computed by hand from the
//! file's keyframes, and a skinned cylinder and a morph target against the world-space
//! vertices Blender itself evaluated at three frames (in the fixtures' JSON); and bad
//! animation, skin and morph-target input, generated, refused with errors naming the field.

use glam::Vec3;
use serde_json::json;
use std::path::PathBuf;
use tessera_scene::gltf_import::{load_path_at, load_slice_at, SceneTime};
use tessera_scene::Scene;
use tessera_testkit::gltf_gen::Gen;

/// Frames per second of the fixtures (Blender's default, 24).
const FPS: f64 = 24.0;

fn fixture(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../tests/fixtures/animation")
        .join(name)
}

fn at_frame(file: &str, frame: u32) -> Scene {
    load_path_at(&fixture(file), None, &SceneTime::frame(frame, FPS))
        .unwrap_or_else(|e| panic!("{file} at frame {frame}: {e}"))
}

/// The world-space vertices of the mesh whose name contains `mesh`.
fn vertices<'s>(scene: &'s Scene, mesh: &str) -> &'s [Vec3] {
    let m = scene
        .meshes
        .iter()
        .find(|m| m.name.contains(mesh))
        .unwrap_or_else(|| panic!("no mesh {mesh} in {}", scene.name));
    &m.positions
}

fn centroid(v: &[Vec3]) -> Vec3 {
    v.iter().copied().sum::<Vec3>() / v.len() as f32
}

fn assert_near(got: Vec3, want: [f32; 3], what: &str) {
    let want = Vec3::from(want);
    assert!(
        (got - want).abs().max_element() < 1e-5,
        "{what}: got {got}, want {want}"
    );
}

/// The keys of every cube (glTF axes): frame 1 at +0, frame 11 at (2, 0, -1), frame 21 at
/// (2, 1, -3), offset by (0, 3 i, 0). Hand-computed: LINEAR halfway between keys, STEP
/// holding the earlier key, CUBICSPLINE from the file's tangents (0 at the ends, -5.4 per
/// second in z at frame 11) in the Hermite form of glTF Appendix C with s = 1/2 and the
/// tangents scaled by the interval dt = 10/24 s:
/// `z(frame 6) = 1/2 * (-1) - 1/8 * dt * (-5.4) = -0.21875`,
/// `z(frame 16) = 1/2 * (-1) + 1/8 * dt * (-5.4) + 1/2 * (-3) = -2.28125`.
#[test]
fn keyframed_cube_follows_each_interpolation_mode() {
    let cases: [(u32, [[f32; 3]; 3]); 6] = [
        // frame: linear, step, bezier
        (0, [[0.0, 0.0, 0.0], [0.0, 3.0, 0.0], [0.0, 6.0, 0.0]]),
        (1, [[0.0, 0.0, 0.0], [0.0, 3.0, 0.0], [0.0, 6.0, 0.0]]),
        (6, [[1.0, 0.0, -0.5], [0.0, 3.0, 0.0], [1.0, 6.0, -0.21875]]),
        (11, [[2.0, 0.0, -1.0], [2.0, 3.0, -1.0], [2.0, 6.0, -1.0]]),
        (
            16,
            [[2.0, 0.5, -2.0], [2.0, 3.0, -1.0], [2.0, 6.5, -2.28125]],
        ),
        (30, [[2.0, 1.0, -3.0], [2.0, 4.0, -3.0], [2.0, 7.0, -3.0]]),
    ];
    let blender: serde_json::Value =
        serde_json::from_slice(&std::fs::read(fixture("anim_cube.json")).expect("anim_cube.json"))
            .unwrap();
    for (frame, want) in cases {
        let scene = at_frame("anim_cube.glb", frame);
        for (i, mesh) in ["'Cube'", "'Cube.001'", "'Cube.002'"].iter().enumerate() {
            let got = centroid(vertices(&scene, mesh));
            assert_near(got, want[i], &format!("frame {frame} cube {mesh}"));
            // Blender's own evaluation agrees where it was recorded (frame 0 is not
            // Blender's: before the first key it also holds the first value).
            let name = ["linear", "step", "bezier"][i];
            if let Some(b) = blender["objects"][name]["location"][frame.to_string()].as_array() {
                let b: Vec<f32> = b.iter().map(|v| v.as_f64().unwrap() as f32).collect();
                assert_near(
                    got,
                    [b[0], b[1], b[2]],
                    &format!("frame {frame} {name} vs Blender"),
                );
            }
        }
    }
    // The LINEAR cube also turns 90 degrees about +Y (Blender's +Z) from frame 1 to 21,
    // slerped: 45 degrees at frame 11, where its x extent is 0.25 * sqrt(2).
    for (frame, half_width) in [(1, 0.25), (11, 0.25 * 2f32.sqrt()), (21, 0.25)] {
        let scene = at_frame("anim_cube.glb", frame);
        let v = vertices(&scene, "'Cube'");
        let c = centroid(v);
        let extent = v.iter().map(|p| (p.x - c.x).abs()).fold(0.0, f32::max);
        assert!(
            (extent - half_width).abs() < 1e-5,
            "frame {frame}: x half extent {extent}, want {half_width}"
        );
    }
}

/// The rest (bind-pose) positions of a mesh's first primitive as the file stores them,
/// in the order the importer keeps.
fn rest_positions(file: &str) -> Vec<Vec3> {
    let (doc, buffers, _) = gltf::import(fixture(file)).expect("fixture parses");
    let mesh = doc.meshes().next().expect("a mesh");
    let prim = mesh.primitives().next().expect("a primitive");
    let reader = prim.reader(|b| Some(&buffers[b.index()]));
    reader
        .read_positions()
        .expect("POSITION")
        .map(Vec3::from)
        .collect()
}

/// Max vertex error, relative to the object's size, of Tessera's world-space vertices
/// of `mesh` against Blender's evaluated vertices at each recorded frame. Vertices are
/// matched through their rest positions (the exporter splits Blender's vertices at UV
/// seams and sharp edges, so several glTF vertices may share one of Blender's).
fn compare_with_blender(file: &str, json: &str, object: &str, mesh: &str) -> Vec<(u32, f64)> {
    let data: serde_json::Value =
        serde_json::from_slice(&std::fs::read(fixture(json)).unwrap()).unwrap();
    let obj = &data["objects"][object];
    let vec3 = |v: &serde_json::Value| {
        let a = v.as_array().unwrap();
        Vec3::new(
            a[0].as_f64().unwrap() as f32,
            a[1].as_f64().unwrap() as f32,
            a[2].as_f64().unwrap() as f32,
        )
    };
    let rest: Vec<Vec3> = obj["rest"].as_array().unwrap().iter().map(vec3).collect();
    let size = obj["size"].as_f64().unwrap();
    let ours = rest_positions(file);
    let matched: Vec<usize> = ours
        .iter()
        .map(|p| {
            let (j, d) = rest
                .iter()
                .enumerate()
                .map(|(j, r)| (j, r.distance(*p)))
                .min_by(|a, b| a.1.total_cmp(&b.1))
                .unwrap();
            assert!(
                d < 1e-5,
                "{file}: vertex at {p} has no Blender vertex ({d})"
            );
            j
        })
        .collect();
    let mut errors = Vec::new();
    for f in data["frames"].as_array().unwrap() {
        let frame = f.as_u64().unwrap() as u32;
        let blender: Vec<Vec3> = obj["frames"][frame.to_string()]
            .as_array()
            .unwrap()
            .iter()
            .map(vec3)
            .collect();
        let scene = at_frame(file, frame);
        let got = vertices(&scene, mesh);
        assert_eq!(got.len(), ours.len());
        let max = got
            .iter()
            .zip(&matched)
            .map(|(p, &j)| f64::from(p.distance(blender[j])))
            .fold(0.0, f64::max);
        errors.push((frame, max / size));
    }
    errors
}

#[test]
fn skinned_cylinder_matches_blender_at_three_frames() {
    let errors = compare_with_blender(
        "skin_cylinder.glb",
        "skin_cylinder.json",
        "cylinder",
        "'Cylinder'",
    );
    println!("skin_cylinder relative max vertex error per frame: {errors:?}");
    assert_eq!(errors.len(), 3);
    for (frame, e) in errors {
        assert!(
            e < 1e-4,
            "frame {frame}: max vertex error {e} of the object's size"
        );
    }
    // And it does bend: frame 24 is far from frame 1.
    let a = at_frame("skin_cylinder.glb", 1);
    let b = at_frame("skin_cylinder.glb", 24);
    let moved = vertices(&a, "'Cylinder'")
        .iter()
        .zip(vertices(&b, "'Cylinder'"))
        .map(|(p, q)| p.distance(*q))
        .fold(0.0, f32::max);
    assert!(moved > 0.5, "the tip moved only {moved}");
}

#[test]
fn morph_target_matches_blender_at_three_frames() {
    let errors = compare_with_blender("morph_plane.glb", "morph_plane.json", "plane", "'Grid'");
    println!("morph_plane relative max vertex error per frame: {errors:?}");
    assert_eq!(errors.len(), 3);
    for (frame, e) in errors {
        assert!(
            e < 1e-4,
            "frame {frame}: max vertex error {e} of the object's size"
        );
    }
}

#[test]
fn a_named_animation_plays_alone_and_an_unknown_one_is_an_error() {
    let time = SceneTime {
        seconds: 30.0 / FPS,
        animation: Some("stepAction".into()),
    };
    let scene = load_path_at(&fixture("anim_cube.glb"), None, &time).unwrap();
    // The step cube moved to its last key, the linear one stayed at its node's rest.
    assert_near(
        centroid(vertices(&scene, "'Cube.001'")),
        [2.0, 4.0, -3.0],
        "step",
    );
    assert_near(
        centroid(vertices(&scene, "'Cube'")),
        [0.0, 0.0, 0.0],
        "linear",
    );
    let by_index = SceneTime {
        seconds: 30.0 / FPS,
        animation: Some("1".into()),
    };
    let s2 = load_path_at(&fixture("anim_cube.glb"), None, &by_index).unwrap();
    assert_eq!(vertices(&s2, "'Cube.001'"), vertices(&scene, "'Cube.001'"));
    let wrong = SceneTime {
        seconds: 0.0,
        animation: Some("walk".into()),
    };
    let e = load_path_at(&fixture("anim_cube.glb"), None, &wrong)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("animation \"walk\"") && e.contains("\"stepAction\""),
        "{e}"
    );
}

/// A triangle at node 0 (in the scene) with an accessor of `times` and one of `values`
/// for animations to use; returns the generator and the two accessor indices.
fn animated_triangle(times: &[f32], values: &[[f32; 3]]) -> (Gen, usize, usize) {
    let mut g = Gen::new();
    let mesh = g.triangle_mesh(
        "tri",
        &[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
        None,
        None,
    );
    g.root(json!({"mesh": mesh}));
    let view = g.view(
        &times
            .iter()
            .flat_map(|t| t.to_le_bytes())
            .collect::<Vec<u8>>(),
    );
    let input = g.push(
        "accessors",
        json!({"bufferView": view, "componentType": 5126, "count": times.len(), "type": "SCALAR"}),
    );
    let output = g.vec3(values);
    (g, input, output)
}

/// The error of loading `g` at `seconds`.
fn error_at(g: &Gen, seconds: f64) -> String {
    let time = SceneTime {
        seconds,
        animation: None,
    };
    match load_slice_at(&g.gltf(), "bad.gltf", None, None, &time) {
        Ok(_) => panic!("expected an error"),
        Err(e) => e.to_string(),
    }
}

#[test]
fn bad_animation_input_is_an_error_naming_the_field() {
    let translate = |g: &mut Gen, input, output, interpolation: &str| {
        g.push(
            "animations",
            json!({"channels": [{"sampler": 0, "target": {"node": 0, "path": "translation"}}],
                   "samplers": [{"input": input, "output": output, "interpolation": interpolation}]}),
        );
    };
    // A working one first: LINEAR halfway.
    let (mut g, i, o) = animated_triangle(&[0.0, 1.0], &[[0.0; 3], [2.0, 0.0, 0.0]]);
    translate(&mut g, i, o, "LINEAR");
    let time = SceneTime {
        seconds: 0.5,
        animation: None,
    };
    let s = load_slice_at(&g.gltf(), "ok.gltf", None, None, &time).unwrap();
    assert!(s.animated);
    assert_eq!(s.meshes[0].positions[0], Vec3::new(1.0, 0.0, 0.0));
    // Times not increasing.
    let (mut g, i, o) = animated_triangle(&[0.0, 0.0], &[[0.0; 3], [2.0, 0.0, 0.0]]);
    translate(&mut g, i, o, "LINEAR");
    let e = error_at(&g, 0.5);
    assert!(
        e.contains("animation 0 channel 0") && e.contains("not strictly increasing"),
        "{e}"
    );
    // CUBICSPLINE needs three outputs per key.
    let (mut g, i, o) = animated_triangle(&[0.0, 1.0], &[[0.0; 3], [2.0, 0.0, 0.0]]);
    translate(&mut g, i, o, "CUBICSPLINE");
    let e = error_at(&g, 0.5);
    assert!(
        e.contains("sampler 0 output") && e.contains("has 2 elements") && e.contains("need 6"),
        "{e}"
    );
    // A matrix on an animated node.
    let (mut g, i, o) = animated_triangle(&[0.0, 1.0], &[[0.0; 3], [2.0, 0.0, 0.0]]);
    translate(&mut g, i, o, "LINEAR");
    g.doc["nodes"][0]["matrix"] = json!([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]);
    let e = error_at(&g, 0.5);
    assert!(e.contains("node 0 is animated but has a matrix"), "{e}");
    // Weights on a node whose mesh has no morph targets.
    let (mut g, i, _) = animated_triangle(&[0.0, 1.0], &[[0.0; 3], [2.0, 0.0, 0.0]]);
    g.push(
        "animations",
        json!({"channels": [{"sampler": 0, "target": {"node": 0, "path": "weights"}}],
               "samplers": [{"input": i, "output": i}]}),
    );
    let e = error_at(&g, 0.5);
    assert!(e.contains("whose mesh has no morph targets"), "{e}");
}

#[test]
fn bad_skins_and_morph_targets_are_errors_naming_the_field() {
    // A skinned triangle whose vertex 2 names joint 3 of a one-joint skin.
    let skinned = |joints: [u8; 12], weights: [[f32; 4]; 3]| {
        let (mut g, _, _) = animated_triangle(&[0.0], &[[0.0; 3]]);
        let jv = g.view(&joints);
        let ja = g.push(
            "accessors",
            json!({"bufferView": jv, "componentType": 5121, "count": 3, "type": "VEC4"}),
        );
        let wb: Vec<u8> = weights
            .iter()
            .flatten()
            .flat_map(|w| w.to_le_bytes())
            .collect();
        let wv = g.view(&wb);
        let wa = g.push(
            "accessors",
            json!({"bufferView": wv, "componentType": 5126, "count": 3, "type": "VEC4"}),
        );
        g.doc["meshes"][0]["primitives"][0]["attributes"]["JOINTS_0"] = json!(ja);
        g.doc["meshes"][0]["primitives"][0]["attributes"]["WEIGHTS_0"] = json!(wa);
        let joint = g.root(json!({"translation": [0.0, 0.0, 1.0]}));
        g.push("skins", json!({"joints": [joint]}));
        g.doc["nodes"][0]["skin"] = json!(0);
        g
    };
    let one = [1.0, 0.0, 0.0, 0.0];
    // Good: every vertex on joint 0, moved by its translation.
    let g = skinned([0; 12], [one, one, one]);
    let s = load_slice_at(&g.gltf(), "skin.gltf", None, None, &SceneTime::default()).unwrap();
    assert_eq!(s.meshes[0].positions[1], Vec3::new(1.0, 0.0, 1.0));
    // Weights are normalized: (2, 0, 0, 0) is joint 0 at full weight.
    let g = skinned([0; 12], [[2.0, 0.0, 0.0, 0.0], one, one]);
    let s = load_slice_at(&g.gltf(), "skin.gltf", None, None, &SceneTime::default()).unwrap();
    assert_eq!(s.meshes[0].positions[0], Vec3::new(0.0, 0.0, 1.0));
    // A mirroring joint (scale -1 along x) mirrors the triangle: it is re-wound, so its
    // geometric normal agrees with its normals (moved by the inverse transpose).
    let mut g = skinned([0; 12], [one, one, one]);
    g.doc["nodes"][1]["scale"] = json!([-1.0, 1.0, 1.0]);
    let s = load_slice_at(&g.gltf(), "skin.gltf", None, None, &SceneTime::default()).unwrap();
    let m = &s.meshes[0];
    let [a, b, c] = m.indices[0].map(|i| m.positions[i as usize]);
    assert_eq!(m.positions[1], Vec3::new(-1.0, 0.0, 1.0));
    assert!((b - a).cross(c - a).z > 0.0, "winding {:?}", m.indices[0]);
    let mut joints = [0u8; 12];
    joints[8] = 3;
    let e = error_at(&skinned(joints, [one, one, one]), 0.0);
    assert!(
        e.contains("JOINTS_0 vertex 2 names joint 3 of skin 0, which has 1 joints"),
        "{e}"
    );
    let e = error_at(&skinned([0; 12], [one, [0.0; 4], one]), 0.0);
    assert!(e.contains("vertex 1: its skin weights sum to 0"), "{e}");
    let e = error_at(&skinned([0; 12], [one, [-1.0, 0.0, 0.0, 0.0], one]), 0.0);
    assert!(
        e.contains("WEIGHTS_0 vertex 1 has a negative weight"),
        "{e}"
    );
    // A morph target whose POSITION has too few elements, and weights of the wrong count.
    let (mut g, _, deltas) = animated_triangle(&[0.0], &[[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]);
    g.doc["meshes"][0]["primitives"][0]["targets"] = json!([{"POSITION": deltas}]);
    g.doc["meshes"][0]["weights"] = json!([1.0]);
    let e = error_at(&g, 0.0);
    assert!(
        e.contains("target 0 POSITION has 2 elements but POSITION has 3"),
        "{e}"
    );
    g.doc["meshes"][0]["weights"] = json!([1.0, 0.5]);
    let e = error_at(&g, 0.0);
    assert!(
        e.contains("mesh weights has 2 values but the primitive has 1 morph targets"),
        "{e}"
    );
}
