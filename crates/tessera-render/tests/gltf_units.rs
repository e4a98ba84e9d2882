//! The glTF Cornell box (`scenes/cornell-box.gltf`) is the built-in Cornell box written as
//! glTF: importing it must give the same image in physical units. The glTF material model
//! (metallic 0, roughness 1: a diffuse base under a rough Fresnel layer) is not exactly
//! Lambertian, so the means agree to a few percent, not to the noise level.

mod common;

use common::{image_mean, render};
use tessera_render::render::RenderConfig;

#[test]
fn gltf_cornell_box_has_the_builtin_radiance() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../scenes/cornell-box.gltf");
    let gltf = tessera_scene::load(path).unwrap();
    let builtin = tessera_scene::load("builtin:cornell-box").unwrap();
    let settings = RenderConfig {
        seed: 1,
        ..RenderConfig::default()
    };
    let a = render(&builtin, 32, 32, 64, &settings);
    let b = render(&gltf, 32, 32, 64, &settings);
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
