//! `tessera render` shows the scene's render plan, follows it with `--integrator auto`,
//! reports overrides, and renders a scene without light black without tracing.

use crate::common;

use std::path::Path;

use common::{output_ok, read_exr, temp_dir, tessera};

/// Renders `scene` tiny (16 x 16, 4 spp) to `out` with extra arguments; returns stdout.
fn render(scene: &str, out: &Path, extra: &[&str]) -> String {
    output_ok(
        tessera()
            .args([
                "render", scene, "--width", "16", "--height", "16", "--spp", "4", "-o",
            ])
            .arg(out)
            .args(extra),
    )
}

fn assert_contains(text: &str, needles: &[&str]) {
    for needle in needles {
        assert!(text.contains(needle), "lacks {needle:?}:\n{text}");
    }
}

fn metadata(out: &Path) -> String {
    read_exr(out).metadata.expect("EXR metadata")
}

#[test]
fn auto_follows_and_shows_the_plan() {
    let dir = temp_dir("plan", "auto");
    let out = dir.join("cornell.exr");
    let stdout = render("builtin:cornell-box", &out, &[]);
    assert_contains(
        &stdout,
        &[
            "render plan: path (max depth 16, Russian roulette from depth 5, no lens sampling)",
            "direct-area: 2 emissive triangles in material 3 'light'",
            "indirect-diffuse: ",
            "absent: direct-sphere",
            "caustics",
            "pinhole camera: no lens sampling",
            "path integrator",
            // The closing summary lines stay as they were.
            "samples per pixel: 4",
            "seconds: ",
            "estimated relative error: ",
            "paths per second: ",
        ],
    );
    assert!(!stdout.contains("overridden"), "{stdout}");
    // The plan comes before the closing summary.
    assert!(stdout.find("render plan:").unwrap() < stdout.find("samples per pixel:").unwrap());
    // The plan travels in the EXR header, with the settings it chose.
    let meta = metadata(&out);
    assert_contains(
        &meta,
        &[
            "\"integrator\":\"path\"",
            "\"max_depth\":16",
            "\"plan\":{\"integrator\":\"path\",\"max_depth\":16,\"rr_depth\":5",
            "\"overridden\":null",
        ],
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn explicit_integrator_and_depth_override_the_plan() {
    let dir = temp_dir("plan", "override");
    let out = dir.join("direct.exr");
    let stdout = render("builtin:cornell-box", &out, &["--integrator", "direct"]);
    assert_contains(
        &stdout,
        &[
            "render plan: path",
            "overridden: --integrator direct overrides the plan, which chose path with max depth 16",
            "direct integrator",
        ],
    );
    let meta = metadata(&out);
    assert_contains(
        &meta,
        &[
            "\"integrator\":\"direct\"",
            "\"overridden\":\"--integrator direct overrides the plan",
        ],
    );

    let out = dir.join("shallow.exr");
    let stdout = render("builtin:cornell-box", &out, &["--max-depth", "3"]);
    assert_contains(
        &stdout,
        &[
            "overridden: --max-depth 3 overrides the plan",
            "path integrator",
        ],
    );
    assert_contains(&metadata(&out), &["\"max_depth\":3,"]);

    // Asking for what the plan would choose anyway is no override.
    let out = dir.join("same.exr");
    let stdout = render("builtin:cornell-box", &out, &["--max-depth", "16"]);
    assert!(!stdout.contains("overridden"), "{stdout}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn delta_lit_caustics_plan_bdpt() {
    let dir = temp_dir("plan", "bdpt");
    let out = dir.join("caustic.exr");
    let stdout = render("builtin:caustic", &out, &[]);
    assert_contains(
        &stdout,
        &["render plan: bdpt (max depth 12", "delta-lit-caustics: "],
    );
    // The plan is followed: bdpt, no fallback note.
    assert_contains(&stdout, &["bdpt integrator"]);
    assert!(!stdout.contains("note: the plan chose bdpt"), "{stdout}");
    assert_contains(
        &metadata(&out),
        &[
            "\"integrator\":\"bdpt\"",
            "\"max_depth\":12,\"rr_depth\":5,",
        ],
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// One triangle at z = 0 seen by a camera at z = 2, no light: glTF with an embedded buffer
/// (three float positions and three u16 indices).
const DARK_GLTF: &str = r#"{
  "asset": {"version": "2.0"},
  "scene": 0,
  "scenes": [{"nodes": [0, 1]}],
  "nodes": [
    {"name": "triangle", "mesh": 0},
    {"name": "camera", "camera": 0, "translation": [0.0, 0.0, 2.0]}
  ],
  "cameras": [{"type": "perspective", "perspective": {"yfov": 1.0, "znear": 0.01}}],
  "materials": [{"name": "grey", "pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.5, 0.5, 1.0], "metallicFactor": 0.0, "roughnessFactor": 1.0}}],
  "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "material": 0}]}],
  "buffers": [{"byteLength": 44, "uri": "data:application/octet-stream;base64,AACAvwAAgL8AAAAAAACAPwAAgL8AAAAAAAAAAAAAgD8AAAAAAAABAAIAAAA="}],
  "bufferViews": [
    {"buffer": 0, "byteOffset": 0, "byteLength": 36},
    {"buffer": 0, "byteOffset": 36, "byteLength": 6}
  ],
  "accessors": [
    {"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3", "min": [-1.0, -1.0, 0.0], "max": [1.0, 1.0, 0.0]},
    {"bufferView": 1, "componentType": 5123, "count": 3, "type": "SCALAR"}
  ]
}"#;

#[test]
fn a_scene_without_light_renders_black_without_tracing() {
    let dir = temp_dir("plan", "dark");
    let scene = dir.join("dark.gltf");
    std::fs::write(&scene, DARK_GLTF).unwrap();
    let out = dir.join("dark.exr");
    let stdout = render(scene.to_str().unwrap(), &out, &[]);
    assert_contains(
        &stdout,
        &[
            "render plan: black (nothing to trace)",
            "no light: the image is black",
            "no ray traced",
            "samples per pixel: 4",
            "estimated relative error: 0.0000",
            "paths per second: 0",
        ],
    );
    let exr = read_exr(&out);
    assert_eq!((exr.width, exr.height), (16, 16));
    for name in [
        "R",
        "G",
        "B",
        "variance.R",
        "variance.G",
        "variance.B",
        "pooled_variance.G",
        "relerr.Y",
    ] {
        assert!(exr.get(name).unwrap().iter().all(|&v| v == 0.0), "{name}");
    }
    assert!(exr.get("samples.Y").unwrap().iter().all(|&s| s == 4.0));
    assert!(exr.get("passes.Y").unwrap().iter().all(|&s| s == 4.0));
    let meta = exr.metadata.unwrap();
    assert_contains(
        &meta,
        &[
            "\"integrator\":\"black\"",
            "\"plan\":{\"integrator\":\"black\"",
        ],
    );

    // Forcing an integrator traces anyway (and still finds nothing).
    let out = dir.join("forced.png");
    let stdout = render(scene.to_str().unwrap(), &out, &["--integrator", "path"]);
    assert_contains(
        &stdout,
        &[
            "overridden: --integrator path overrides the plan, which chose black",
            "path integrator",
        ],
    );
    let _ = std::fs::remove_dir_all(&dir);
}
