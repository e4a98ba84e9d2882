//! Scenes made the way users make them, against the renderer they came from: each fixture
//! in `tests/fixtures/blender/` was built in Blender 5.0, exported with Blender's glTF
//! exporter, re-imported with Blender's glTF importer and rendered with Cycles
//! (`make_fixtures.py` there; CI never runs Blender, it compares against the committed
//! `NAME.cycles.exr`). Tessera renders the same `.glb` and the means of a 4x4 grid of
//! regions (and of the whole image) must agree within the fixture's tolerance plus four
//! standard errors of Tessera's own estimate. Fixtures whose models differ on purpose
//! (the README there says why) are rendered and reported, not asserted.

mod common;

use common::render;
use tessera_render::integrator::Integrator;
use tessera_render::render::RenderConfig;

const DIR: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../tests/fixtures/blender");

/// How a fixture is judged.
#[derive(Clone, Copy)]
enum Judge {
    /// Every region within this relative tolerance (plus noise).
    Within(f64),
    /// Rendered and printed only, for the reason given.
    Report(&'static str),
}

/// (fixture, Tessera samples per pixel, judgement).
const FIXTURES: &[(&str, u32, Judge)] = &[
    ("light_point", 64, Judge::Within(0.02)),
    ("light_spot", 64, Judge::Within(0.02)),
    ("light_sun", 64, Judge::Within(0.02)),
    ("base_color_texture", 64, Judge::Within(0.02)),
    ("metallic_roughness_texture", 256, Judge::Within(0.02)),
    ("emissive_texture", 256, Judge::Within(0.02)),
    ("normal_map", 64, Judge::Within(0.02)),
    ("wrap_modes", 64, Judge::Within(0.02)),
    ("alpha_blend", 128, Judge::Within(0.02)),
    ("alpha_mask", 64, Judge::Within(0.02)),
    ("texture_transform", 64, Judge::Within(0.02)),
    ("texcoord1", 64, Judge::Within(0.02)),
    ("glass_copper", 256, Judge::Within(0.02)),
    ("rough_glass", 256, Judge::Within(0.02)),
    (
        "volume",
        256,
        Judge::Report("Cycles absorbs with (1 - colour) density, not the extension's -ln(colour)/distance"),
    ),
    ("clearcoat", 256, Judge::Within(0.02)),
    (
        "sheen",
        256,
        Judge::Report("Cycles' sheen is not the extension's Charlie sheen"),
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
        Judge::Report("caustics from the point, spot and sun lights through the glass, which Cycles does not render"),
    ),
];

/// Per-region means (4x4 grid, then the whole image) of channel c of a row-major RGB
/// image, and for Tessera the standard error from its per-pixel variances.
fn regions(w: usize, h: usize, value: impl Fn(usize, usize) -> (f64, f64)) -> Vec<(f64, f64)> {
    let mut out = Vec::new();
    let grid = |k: usize, n: usize, i: usize| (i * n / k, (i + 1) * n / k);
    for gy in 0..=4 {
        for gx in 0..4 {
            let ((x0, x1), (y0, y1)) = if gy == 4 {
                if gx > 0 {
                    continue;
                }
                ((0, w), (0, h))
            } else {
                (grid(4, w, gx), grid(4, h, gy))
            };
            let (mut sum, mut var) = (0.0, 0.0);
            for y in y0..y1 {
                for x in x0..x1 {
                    let (m, v) = value(x, y);
                    sum += m;
                    var += v;
                }
            }
            let n = ((x1 - x0) * (y1 - y0)) as f64;
            out.push((sum / n, var.sqrt() / n));
        }
    }
    out
}

#[test]
fn blender_fixtures_match_their_cycles_references() {
    let config = RenderConfig {
        integrator: Integrator::Path,
        seed: 11,
        max_depth: 64,
        rr_depth: 5,
        ..RenderConfig::default()
    };
    let mut failures = Vec::new();
    for &(name, spp, judge) in FIXTURES {
        let reference = std::fs::read(format!("{DIR}/{name}.cycles.exr"))
            .unwrap_or_else(|e| panic!("{name}.cycles.exr: {e}"));
        let reference = tessera_image::read_exr(&reference).unwrap();
        let (w, h) = (reference.width, reference.height);
        let scene = tessera_scene::load(&format!("{DIR}/{name}.glb"))
            .unwrap_or_else(|e| panic!("{name}.glb: {e}"));
        let acc = render(&scene, w as u32, h as u32, spp, &config);
        let image = acc.image();
        let mut worst = (0.0f64, String::new());
        let mut failed = false;
        for (c, channel) in ["R", "G", "B"].iter().enumerate() {
            let cy = reference.get(channel).unwrap();
            let ours = regions(w, h, |x, y| {
                let i = y * w + x;
                (image.mean[i][c] as f64, image.variance_of_mean[i][c] as f64)
            });
            let theirs = regions(w, h, |x, y| (cy[y * w + x] as f64, 0.0));
            let whole = theirs.last().unwrap().0;
            for (r, ((m, se), (want, _))) in ours.iter().zip(&theirs).enumerate() {
                // Regions that are nearly black say nothing about the model.
                if *want < 0.02 * whole.max(1e-6) || *want <= 1e-6 {
                    continue;
                }
                let rel = m / want - 1.0;
                if rel.abs() > worst.0.abs() {
                    worst = (rel, format!("{channel} region {r}"));
                }
                if let Judge::Within(tol) = judge {
                    if (m - want).abs() > tol * want + 4.0 * se {
                        failed = true;
                    }
                }
            }
        }
        let verdict = match judge {
            Judge::Within(_) if failed => "FAIL",
            Judge::Within(_) => "ok",
            Judge::Report(why) => why,
        };
        eprintln!(
            "{name:28} worst {:+.2}% ({}) {verdict}",
            100.0 * worst.0,
            worst.1
        );
        if failed {
            failures.push(format!("{name}: worst {:+.2}% at {}", 100.0 * worst.0, worst.1));
        }
    }
    assert!(failures.is_empty(), "fixtures off their Cycles reference: {failures:#?}");
}
