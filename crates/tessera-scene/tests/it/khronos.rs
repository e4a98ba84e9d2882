//! The Khronos glTF sample models in `tests/fixtures/khronos/` (their README names the
//! source and licence of each): files nobody here wrote. Every one loads; a static model
//! is the same scene at every time; an animated, skinned or morphed one differs between
//! frames, as the specification's animation says.

use std::path::PathBuf;
use tessera_scene::gltf_import::{load_path_at, SceneTime};
use tessera_scene::Scene;

const DIR: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../tests/fixtures/khronos");

/// (file stem, whether the model moves over time).
const MODELS: &[(&str, bool)] = &[
    ("TriangleWithoutIndices", false),
    ("SimpleMeshes", false),
    ("AnimatedTriangle", true),
    ("SimpleMorph", true),
    ("SimpleSkin", true),
    ("Cameras", false),
    ("BoxVertexColors", false),
];

fn load(stem: &str, seconds: f64) -> Scene {
    let path = PathBuf::from(DIR).join(format!("{stem}.gltf"));
    let time = SceneTime {
        seconds,
        ..SceneTime::default()
    };
    load_path_at(&path, None, &time).unwrap_or_else(|e| panic!("{stem} does not load: {e}"))
}

/// What of a scene moves: its meshes' world-space data and its instances.
fn geometry(scene: &Scene) -> String {
    format!("{:?} {:?}", scene.meshes, scene.instances)
}

#[test]
fn every_model_in_the_directory_is_listed() {
    let mut on_disk: Vec<String> = std::fs::read_dir(DIR)
        .unwrap()
        .filter_map(|e| {
            let name = e.unwrap().file_name().into_string().unwrap();
            name.strip_suffix(".gltf").map(str::to_owned)
        })
        .collect();
    on_disk.sort();
    let mut listed: Vec<String> = MODELS.iter().map(|(m, _)| m.to_string()).collect();
    listed.sort();
    assert_eq!(on_disk, listed);
    let readme = std::fs::read_to_string(PathBuf::from(DIR).join("README.md")).unwrap();
    for (m, _) in MODELS {
        assert!(
            readme.contains(&format!("`{m}.gltf`")),
            "{m} has no attribution"
        );
    }
}

#[test]
fn every_model_loads_and_moves_exactly_when_animated() {
    for &(stem, moves) in MODELS {
        let start = load(stem, 0.0);
        assert!(start.triangle_count() > 0, "{stem}: no triangles");
        start.validate().unwrap_or_else(|e| panic!("{stem}: {e}"));
        let later = load(stem, 0.5);
        assert_eq!(
            geometry(&start) != geometry(&later),
            moves,
            "{stem}: expected it {} between t = 0 and t = 0.5 s",
            if moves { "to move" } else { "not to move" }
        );
        assert_eq!(start.animated, moves, "{stem}: animated flag");
    }
}

#[test]
fn cameras_gltf_renders_from_its_perspective_camera() {
    // The model's two camera nodes stand at (0.5, 0.5, 3) looking down -z at the quad: a
    // perspective one (yfov 0.7, the first, used by default) and an orthographic one,
    // which Tessera does not model (perspective and thin-lens cameras only).
    let scene = load("Cameras", 0.0);
    assert!((scene.camera.yfov - 0.7).abs() < 1e-6, "{:?}", scene.camera);
    let eye = scene.camera.world_from_camera.w_axis.truncate();
    assert!(
        (eye - glam::Vec3::new(0.5, 0.5, 3.0)).length() < 1e-6,
        "{eye}"
    );
}

#[test]
fn box_vertex_colors_keeps_its_colours() {
    // COLOR_0 is each vertex's position (glTF 2.0 §3.7.2.1: it multiplies the base colour).
    let scene = load("BoxVertexColors", 0.0);
    let mesh = &scene.meshes[0];
    let colors = mesh.colors.as_ref().expect("COLOR_0 is imported");
    assert_eq!(colors.len(), mesh.positions.len());
    for (c, p) in colors.iter().zip(&mesh.positions) {
        // The node has no transform: world-space positions are the file's.
        assert!((c.truncate() - *p).abs().max_element() < 1e-6, "{c} {p}");
        assert_eq!(c.w, 1.0, "a VEC3 colour has alpha 1");
    }
    assert!(colors.iter().any(|c| c.x != c.y), "not grey");
}
