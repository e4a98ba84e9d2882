//! The glTF Cornell box (`scenes/cornell-box.gltf`) is the built-in Cornell box written as
//! glTF: importing it must give the same image in physical units. The glTF material model
//! (metallic 0, roughness 1: a diffuse base under a rough Fresnel layer) is not exactly
//! Lambertian, so the means agree to a few percent, not to the noise level.

use crate::common::{image_mean, render};
use tessera_farm::FrameAccumulator;
use tessera_render::render::RenderConfig;
use tessera_scene::Scene;

const CORNELL_GLTF: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../scenes/cornell-box.gltf");

/// The built-in Cornell box and `gltf`, rendered alike (32x32, 64 spp, seed 1).
fn render_with_builtin(gltf: &Scene) -> (FrameAccumulator, FrameAccumulator) {
    let builtin = tessera_scene::load("builtin:cornell-box").unwrap();
    let settings = RenderConfig {
        seed: 1,
        ..RenderConfig::default()
    };
    (
        render(&builtin, 32, 32, 64, &settings),
        render(gltf, 32, 32, 64, &settings),
    )
}

#[test]
fn gltf_cornell_box_has_the_builtin_radiance() {
    let (a, b) = render_with_builtin(&tessera_scene::load(CORNELL_GLTF).unwrap());
    for c in 0..3 {
        let (ma, sa) = image_mean(&a, c);
        let (mb, sb) = image_mean(&b, c);
        eprintln!(
            "channel {c}: builtin {ma:.4} ± {sa:.4}, glTF {mb:.4} ± {sb:.4}, ratio {:.4}",
            mb / ma
        );
        assert!(
            (mb / ma - 1.0).abs() < 0.05,
            "channel {c}: builtin {ma} vs glTF {mb}"
        );
    }
}

/// Regression (glTF materials issue, "fix this first"): Blender writes
/// `KHR_materials_specular` with `specularFactor: 0` for a purely diffuse material. With the
/// extension honoured, the same Cornell box with that factor on every material is the
/// Lambertian built-in box: equal image means (the random decisions are the same, so only
/// float rounding separates them), where the 4% Fresnel layer shifted red by about 1% and
/// the red wall's green and blue by over 30%.
#[test]
fn gltf_cornell_box_without_specular_is_the_lambertian_box() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../scenes/cornell-box.gltf");
    let mut doc: serde_json::Value = serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap();
    for m in doc["materials"].as_array_mut().unwrap() {
        m["extensions"]["KHR_materials_specular"] = serde_json::json!({"specularFactor": 0.0});
    }
    doc["extensionsUsed"] = serde_json::json!(["KHR_materials_specular"]);
    let bytes = serde_json::to_vec(&doc).unwrap();
    let gltf =
        tessera_scene::gltf_import::load_slice(&bytes, "cornell-specular-0.gltf", None, None)
            .unwrap();
    let (a, b) = render_with_builtin(&gltf);
    for c in 0..3 {
        let (ma, _) = image_mean(&a, c);
        let (mb, _) = image_mean(&b, c);
        assert!(
            (mb / ma - 1.0).abs() < 1e-4,
            "channel {c}: builtin {ma} vs glTF without specular {mb}"
        );
    }
}
