//! Scenes made the way users make them, against the renderer they came from: each fixture
//! in `tests/fixtures/blender/` was built in Blender 5.0, exported with Blender's glTF
//! exporter, re-imported with Blender's glTF importer and rendered with Cycles
//! (`make_fixtures.py` there; CI never runs Blender, it compares against the committed
//! `NAME.cycles.exr`). Tessera renders the same `.glb` and the means of a 4x4 grid of
//! regions (and of the whole image) must agree within the fixture's tolerance plus four
//! standard errors of Tessera's own estimate. Fixtures whose models differ on purpose
//! (the README there says why) are rendered and reported, not asserted.

use crate::common::{reference_config, regions, render};

const DIR: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../tests/fixtures/blender");

/// How a fixture is judged.
#[derive(Clone, Copy)]
enum Judge {
    /// Every region within this relative tolerance (plus noise): the models agree.
    Within(f64),
    /// Like `Within`, over the pixels whose 3x3 neighbourhood in the reference is smooth
    /// (within 5%), for the reason given: the renderers filter texel edges differently.
    Interior(f64, &'static str),
    /// Every region within this looser tolerance, for the reason given: the models
    /// differ by design but not by much, and gross errors (a texture ignored) still fail.
    Near(f64, &'static str),
    /// Rendered and printed only, for the reason given.
    Report(&'static str),
}

impl Judge {
    /// The tolerance asserted, if any.
    fn tolerance(self) -> Option<f64> {
        match self {
            Judge::Within(t) | Judge::Interior(t, _) | Judge::Near(t, _) => Some(t),
            Judge::Report(_) => None,
        }
    }
}

/// Why the Principled BSDF fixtures agree to several percent, not two.
const PRINCIPLED: &str = "Cycles' Principled BSDF (v2) is not the glTF model: F82-tint metal \
     Fresnel, its own multiple-scattering GGX and layering of coat and glass";

/// (fixture, Tessera samples per pixel, judgement).
const FIXTURES: &[(&str, u32, Judge)] = &[
    ("light_point", 64, Judge::Within(0.02)),
    ("light_spot", 64, Judge::Within(0.02)),
    ("light_sun", 64, Judge::Within(0.02)),
    (
        "base_color_texture",
        64,
        Judge::Interior(
            0.02,
            "Cycles interpolates 8-bit sRGB texels before decoding them; glTF (and Tessera) \
             decode, then filter, so checker edges differ",
        ),
    ),
    (
        "metallic_roughness_texture",
        256,
        Judge::Near(0.08, PRINCIPLED),
    ),
    ("emissive_texture", 256, Judge::Within(0.02)),
    (
        "normal_map",
        64,
        Judge::Report(
            "Cycles darkens normal-mapped Lambert surfaces: at a quarter of this amplitude it \
             is 4.4% below the analytic max(0, n'.l) answer; Tessera meets that answer times \
             its energy compensation 2/(1 + n'.n) to 0.1% (see gltf_materials.rs for the \
             analytic test), so it is brighter than Cycles by that factor too",
        ),
    ),
    ("wrap_modes", 64, Judge::Within(0.02)),
    ("alpha_blend", 128, Judge::Within(0.02)),
    ("alpha_mask", 64, Judge::Within(0.02)),
    ("texture_transform", 64, Judge::Within(0.02)),
    ("texcoord1", 64, Judge::Within(0.02)),
    ("glass_copper", 256, Judge::Near(0.08, PRINCIPLED)),
    ("rough_glass", 256, Judge::Near(0.1, PRINCIPLED)),
    (
        "volume",
        256,
        Judge::Report(
            "Cycles absorbs with (1 - colour) density, not the extension's -ln(colour)/distance",
        ),
    ),
    ("clearcoat", 256, Judge::Near(0.08, PRINCIPLED)),
    (
        "sheen",
        256,
        Judge::Report("Cycles' sheen is not the extension's Charlie sheen"),
    ),
    (
        "anisotropy",
        256,
        Judge::Report(
            "Blender's importer puts anisotropyStrength straight into the Principled BSDF's \
             Anisotropic input, whose stretch of roughness 0.25 stays within a few times \
             alpha; the extension's mix(alpha, 1, strength^2) makes alpha along the tangent \
             0.66 for strength 0.8, so Tessera's highlight is far wider along the sphere \
             (r11 +83%, r12 -10%; ignoring the extension: r11 -13%, r12 +4%)",
        ),
    ),
    ("specular_color", 256, Judge::Within(0.02)),
    ("emissive_strength", 64, Judge::Within(0.02)),
    (
        "unlit",
        64,
        Judge::Report("Cycles' unlit node setup casts no shadow; a glTF unlit surface is opaque"),
    ),
    ("gpu_instancing", 64, Judge::Within(0.02)),
    (
        "room",
        256,
        Judge::Report(
            "the differences above together (checker edges filtered in sRGB codes, the \
             normal-mapped floor, Principled v2 metal and glass): whole image -1.0%, regions \
             -11% to +8%",
        ),
    ),
];

#[test]
fn blender_fixtures_match_their_cycles_references() {
    let config = reference_config();
    let mut failures = Vec::new();
    // TESSERA_FIXTURES=a,b renders only those fixtures (to look at one by hand).
    let only = std::env::var("TESSERA_FIXTURES").ok();
    let chosen = |name: &str| {
        only.as_deref()
            .is_none_or(|o| o.split(',').any(|n| n == name))
    };
    for &(name, spp, judge) in FIXTURES.iter().filter(|f| chosen(f.0)) {
        let reference = std::fs::read(format!("{DIR}/{name}.cycles.exr"))
            .unwrap_or_else(|e| panic!("{name}.cycles.exr: {e}"));
        let reference = tessera_image::read_exr(&reference).unwrap();
        let (w, h) = (reference.width, reference.height);
        let scene = tessera_scene::load(&format!("{DIR}/{name}.glb"))
            .unwrap_or_else(|e| panic!("{name}.glb: {e}"));
        let acc = render(&scene, w as u32, h as u32, spp, &config);
        let image = acc.image();
        // TESSERA_FIXTURE_OUT=DIR keeps Tessera's images for a look beside the references.
        if let Ok(dir) = std::env::var("TESSERA_FIXTURE_OUT") {
            let exr = tessera_image::encode_exr(&image, None).unwrap();
            std::fs::write(format!("{dir}/{name}.tessera.exr"), exr).unwrap();
        }
        let mut worst = (0.0f64, String::new());
        let mut failed = false;
        for (c, channel) in ["R", "G", "B"].iter().enumerate() {
            let cy = reference.get(channel).unwrap();
            // Interior judging keeps the pixels whose reference neighbourhood is smooth.
            let smooth = |x: usize, y: usize| -> bool {
                let v = cy[y * w + x];
                (y.saturating_sub(1)..(y + 2).min(h)).all(|yy| {
                    (x.saturating_sub(1)..(x + 2).min(w))
                        .all(|xx| (cy[yy * w + xx] - v).abs() <= 0.05 * v.abs() + 1e-4)
                })
            };
            let keep = |x, y| !matches!(judge, Judge::Interior(..)) || smooth(x, y);
            let ours = regions(w, h, |x, y| {
                let i = y * w + x;
                if keep(x, y) {
                    (image.mean[i][c] as f64, image.variance_of_mean[i][c] as f64)
                } else {
                    (f64::NAN, 0.0)
                }
            });
            let theirs = regions(w, h, |x, y| {
                if keep(x, y) {
                    (cy[y * w + x] as f64, 0.0)
                } else {
                    (f64::NAN, 0.0)
                }
            });
            let whole = theirs.last().unwrap().0;
            for (r, ((m, se), (want, _))) in ours.iter().zip(&theirs).enumerate() {
                // Regions that are nearly black (or masked out) say nothing about the model.
                if want.is_nan() || *want < 0.02 * whole.max(1e-6) || *want <= 1e-6 {
                    continue;
                }
                let rel = m / want - 1.0;
                if rel.abs() > worst.0.abs() {
                    worst = (rel, format!("{channel} region {r}"));
                }
                if let Some(tol) = judge.tolerance() {
                    if (m - want).abs() > tol * want + 4.0 * se {
                        failed = true;
                    }
                }
            }
        }
        let verdict = match judge {
            _ if failed => "FAIL".to_string(),
            Judge::Within(t) => format!("ok (within {}%)", 100.0 * t),
            Judge::Interior(t, why) | Judge::Near(t, why) => {
                format!("ok (within {}%): {why}", 100.0 * t)
            }
            Judge::Report(why) => format!("reported: {why}"),
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
        "fixtures off their Cycles reference: {failures:#?}"
    );
}

/// The room's normal-mapped floor, seen along its length, has no black holes: pixels
/// below 30% of Cycles' (where Cycles is not dark). A shading normal that faces away from
/// the grazing view used to send the path below the geometric surface, where it ended:
/// 141 such pixels at 256 spp (139 with bdpt), and the floor's regions from 9.4% darker
/// than Cycles to 7.1% brighter.
/// Turning the normal just enough to face the view (`scene::view_facing_normal`)
/// leaves none; the floor regions then agree with Cycles like the rest of the room, but
/// for the normal map's energy compensation.
#[test]
fn room_floor_has_no_black_holes_at_grazing_views() {
    use tessera_render::integrator::Integrator;
    use tessera_render::render::RenderConfig;
    let reference = std::fs::read(format!("{DIR}/room.cycles.exr")).unwrap();
    let reference = tessera_image::read_exr(&reference).unwrap();
    let (w, h) = (reference.width, reference.height);
    let scene = tessera_scene::load(&format!("{DIR}/room.glb")).unwrap();
    let lum = |p: [f32; 3]| (p[0] + p[1] + p[2]) / 3.0;
    let [r, g, b] = ["R", "G", "B"].map(|c| reference.get(c).unwrap());
    let theirs = regions(w, h, |x, y| {
        let i = y * w + x;
        (lum([r[i], g[i], b[i]]) as f64, 0.0)
    });
    for integrator in [Integrator::Path, Integrator::Bdpt] {
        let config = RenderConfig {
            integrator,
            ..reference_config()
        };
        let image = render(&scene, w as u32, h as u32, 256, &config).image();
        let mut holes = 0;
        for i in 0..w * h {
            let ours = lum(image.mean[i]);
            assert!(ours.is_finite(), "{integrator:?} pixel {i}: {ours}");
            if lum([r[i], g[i], b[i]]) > 0.05 && ours < 0.3 * lum([r[i], g[i], b[i]]) {
                holes += 1;
            }
        }
        // The floor's regions (rows 2 and 3 of the 4x4 grid), luminance.
        let ours = regions(w, h, |x, y| (lum(image.mean[y * w + x]) as f64, 0.0));
        let rel: Vec<f64> = (8..16).map(|k| ours[k].0 / theirs[k].0 - 1.0).collect();
        eprintln!("room {integrator:?}: {holes} hole pixels; floor regions vs Cycles {rel:+.3?}");
        assert!(
            holes <= 15,
            "{integrator:?}: {holes} pixels below 30% of Cycles'"
        );
        if matches!(integrator, Integrator::Bdpt) {
            // bdpt and path disagree by several percent on this floor before and after
            // (shading normals make the BSDF non-reciprocal, and bdpt's light subpaths
            // see it from the other side): only the holes are judged.
            continue;
        }
        // Each floor region within 16% of Cycles, and all of them within 13% of each
        // other (before the bend: -9.4% to +7.1%). The offset is Cycles' own darkening of
        // normal-mapped Lambert surfaces (see the `normal_map` fixture) plus Tessera's
        // energy compensation of them, `2 / (1 + ns·ng)` on the Lambertian base, which
        // Cycles does not have and which varies with the floor's tilts: +1.4% to +8.6%
        // without it, +3.2% to +14.9% with it (docs/rendering.md, "Normal maps and
        // energy").
        let (lo, hi) = rel
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &r| {
                (lo.min(r), hi.max(r))
            });
        assert!(
            lo > -0.1 && hi < 0.16 && hi - lo < 0.13,
            "{integrator:?}: floor regions {lo:+.3} to {hi:+.3} off Cycles"
        );
    }
}
