//! The Khronos sample models in `tests/fixtures/khronos/` (files nobody here wrote, none with
//! a light) under an environment: every one renders finite, and no brighter than the sky,
//! under a uniform white sky; and the ones with a Cycles reference (`environment/cycles_environment.py` there:
//! Blender's importer, the same `sky.hdr` or uniform colour as the world) agree with it
//! region by region on a 4x4 grid, within the tolerance given plus four standard errors of
//! Tessera's estimate, as `blender_references.rs` judges the Blender fixtures.

use crate::common::{reference_config, regions, render};
use glam::Vec3;
use tessera_scene::environment::load_environment;
use tessera_scene::Scene;

const DIR: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../tests/fixtures/khronos");

/// `STEM.gltf` from the Khronos folder, or from `environment/` (variants made there).
fn load(stem: &str) -> Scene {
    let variant = format!("{DIR}/environment/{stem}.gltf");
    let path = if std::path::Path::new(&variant).exists() {
        variant
    } else {
        format!("{DIR}/{stem}.gltf")
    };
    tessera_scene::load(&path).unwrap_or_else(|e| panic!("{stem}: {e}"))
}

/// `scene` lit by environment `env`: `white` (uniform radiance 1) or `sky` (`sky.hdr`).
fn lit(mut scene: Scene, env: &str) -> Scene {
    scene.environment = Some(Vec3::ONE);
    scene.environment_map = match env {
        "white" => None,
        "sky" => Some(load_environment(format!("{DIR}/environment/sky.hdr").as_ref()).unwrap()),
        _ => unreachable!("{env}"),
    };
    scene
}

#[test]
fn every_model_renders_finite_under_a_white_sky() {
    let mut stems: Vec<String> = std::fs::read_dir(DIR)
        .unwrap()
        .filter_map(|e| {
            let name = e.unwrap().file_name().into_string().unwrap();
            name.strip_suffix(".gltf").map(str::to_owned)
        })
        .collect();
    stems.sort();
    assert!(stems.len() >= 7, "{stems:?}");
    for stem in stems {
        let scene = lit(load(&stem), "white");
        let image = render(&scene, 16, 16, 8, &reference_config()).image();
        assert!(
            image
                .mean
                .iter()
                .flatten()
                .all(|v| v.is_finite() && *v >= 0.0),
            "{stem}: a pixel is not finite"
        );
        // Radiance 1 from every direction and nothing that emits: no surface can send more
        // than 1 back (energy conservation), and these materials absorb little.
        for c in 0..3 {
            let mean = image.mean.iter().map(|p| p[c] as f64).sum::<f64>() / 256.0;
            assert!(
                (0.3..1.02).contains(&mean),
                "{stem}: channel {c} averages {mean}"
            );
        }
    }
}

/// How a comparison is judged.
#[derive(Clone, Copy)]
enum Judge {
    /// Every region within this relative tolerance (plus noise): the models agree.
    Within(f64),
    /// Every region within this looser tolerance, for the reason given: the models differ
    /// by design, and gross errors (a mirrored environment, colours ignored) still fail.
    Near(f64, &'static str),
}

/// Why a rough metal lit by a non-uniform sky differs by several per cent. In the white
/// furnace the two agree (0.2%), and a white rough dielectric under the same sky agrees
/// to 0.6% (`CamerasDielectric`), so the environment is lit and sampled alike; but a white
/// metal reflects the sky brighter than Cycles, increasingly with roughness (the
/// `Cameras` quad, worst region: +4.9% at roughness 0.5, +7.5% at 0.75, +12.9% at 1).
/// The two model multiple scattering differently, and a random walk on the Smith
/// microsurface (Heitz et al. 2016; `environment/rough_metal_reference.py`) sides with
/// Tessera: within 1.6% of it, Cycles up to 13% darker (docs/conformance.md).
const ROUGH_METAL: &str = "rough metal under a non-uniform sky: Tessera's multiple scattering \
     (Kulla & Conty) agrees with a random walk on the microsurface, Cycles' albedo scaling is \
     darker (docs/conformance.md)";

/// (model, environment, Tessera samples per pixel, judgement). Sizes are the references'.
/// The Khronos models here have no material: glTF's default one (white metal, roughness 1).
const COMPARISONS: &[(&str, &str, u32, Judge)] = &[
    // The coloured faces (base colour = COLOR_0) reflect 1-3% more where the colour is
    // dark: multiple scattering between coloured facets, modelled differently.
    (
        "BoxVertexColors",
        "white",
        256,
        Judge::Near(
            0.04,
            "coloured rough metal: multiple scattering modelled differently",
        ),
    ),
    (
        "BoxVertexColors",
        "sky",
        256,
        Judge::Near(0.07, ROUGH_METAL),
    ),
    ("SimpleMeshes", "white", 256, Judge::Within(0.02)),
    ("SimpleMeshes", "sky", 256, Judge::Near(0.06, ROUGH_METAL)),
    (
        "TriangleWithoutIndices",
        "sky",
        256,
        Judge::Near(0.06, ROUGH_METAL),
    ),
    // The quad faces 45 degrees up, into the bright sky: the largest difference.
    ("Cameras", "sky", 256, Judge::Near(0.16, ROUGH_METAL)),
    // Cameras.gltf with a white rough dielectric (environment/CamerasDielectric.gltf).
    ("CamerasDielectric", "sky", 256, Judge::Within(0.02)),
    // Stand-ins for Khronos' material test models, made by environment/make_variants.py:
    // metallic 0..1 by roughness 0.1..1 spheres (the rough metallic ones differ as above:
    // +1.5..3.7% where metallic and rough), and COLOR_0 as float VEC3 and VEC4, normalized
    // unsigned byte VEC4 and unsigned short VEC3 on a white dielectric.
    (
        "MetalRoughSpheres",
        "sky",
        256,
        Judge::Near(0.06, ROUGH_METAL),
    ),
    ("VertexColors", "sky", 256, Judge::Within(0.02)),
    ("VertexColors", "white", 256, Judge::Within(0.02)),
];

#[test]
fn khronos_models_match_cycles_under_the_same_environment() {
    let mut failures = Vec::new();
    for &(stem, env, spp, judge) in COMPARISONS {
        let name = format!("{stem}.{env}");
        let reference = std::fs::read(format!("{DIR}/environment/{name}.cycles.exr"))
            .unwrap_or_else(|e| panic!("{name}.cycles.exr: {e}"));
        let reference = tessera_image::read_exr(&reference).unwrap();
        let (w, h) = (reference.width, reference.height);
        let scene = lit(load(stem), env);
        let image = render(&scene, w as u32, h as u32, spp, &reference_config()).image();
        let mut worst = (0.0f64, String::new());
        let mut failed = false;
        for (c, channel) in ["R", "G", "B"].iter().enumerate() {
            let cy = reference.get(channel).unwrap();
            let ours = regions(w, h, |x, y| {
                let i = y * w + x;
                (image.mean[i][c] as f64, image.variance_of_mean[i][c] as f64)
            });
            let theirs = regions(w, h, |x, y| (cy[y * w + x] as f64, 0.0));
            for (r, ((m, se), (want, _))) in ours.iter().zip(&theirs).enumerate() {
                let rel = m / want - 1.0;
                if rel.abs() > worst.0.abs() {
                    worst = (rel, format!("{channel} region {r}"));
                }
                let (Judge::Within(tol) | Judge::Near(tol, _)) = judge;
                if (m - want).abs() > tol * want + 4.0 * se {
                    failed = true;
                }
            }
        }
        let verdict = match judge {
            _ if failed => "FAIL".to_string(),
            Judge::Within(t) => format!("ok (within {:.0}%)", 100.0 * t),
            Judge::Near(t, why) => format!("ok (within {:.0}%): {why}", 100.0 * t),
        };
        eprintln!(
            "{name:28} worst {:+.2}% ({}) {verdict}",
            100.0 * worst.0,
            worst.1
        );
        if failed {
            failures.push(format!(
                "{name}: worst {:+.2}% at {}",
                100.0 * worst.0,
                worst.1
            ));
        }
    }
    assert!(
        failures.is_empty(),
        "models off their Cycles reference: {failures:#?}"
    );
}
