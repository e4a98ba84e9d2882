//! Frames that move, against Blender: `tests/fixtures/motion/motion_ball.glb`
//! was animated in Blender 5.0 and exported with its glTF exporter; its Cycles references
//! were rendered from the re-imported file (`make_motion.py` there; CI never runs
//! Blender). A sphere crosses the view, fast between frames 11 and 13, while a cube turns
//! behind it.
//!
//! - Frames 1 and 24 (no shutter): the 4x4 region means within 2% (plus four standard
//!   errors of Tessera's estimate) of Cycles'.
//! - Frame 12 with a shutter of one frame centred on it (Cycles' `motion_blur_shutter`
//!   1.0, position CENTER; Tessera's `[-0.5, 0.5]`): the region means, and the profile of
//!   the blurred streak across the image (column means over the rows the motion
//!   touches), within 2% of Cycles'. The unblurred frame 12 is far off that profile, so
//!   the comparison sees blur.
//! - A shutter over a moment when nothing moves draws no time: the same pixels as no
//!   shutter, bit for bit.

use crate::common::{reference_config, regions};
use tessera_farm::job::Shutter;
use tessera_farm::{FrameImage, FramePlan};
use tessera_render::render::render_frame;
use tessera_render::scene::RenderScene;
use tessera_scene::{Scene, SceneTime};

const DIR: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../tests/fixtures");
const FPS: f64 = 24.0;
const SPP: u32 = 256;

fn load(file: &str, frame: f64) -> Scene {
    let time = SceneTime {
        seconds: frame / FPS,
        animation: None,
    };
    tessera_scene::load_at(&format!("{DIR}/{file}"), None, &time)
        .unwrap_or_else(|e| panic!("{file}: {e}"))
}

/// The scene at the shutter's key times of `frame`, as `tessera render` loads them.
fn keys(file: &str, frame: u32, shutter: Shutter) -> Vec<Scene> {
    shutter
        .key_frames(frame)
        .into_iter()
        .map(|f| load(file, f))
        .collect()
}

fn render(rs: &RenderScene) -> FrameImage {
    let config = reference_config();
    let plan = FramePlan::for_spp(rs.width, rs.height, SPP, 16).unwrap();
    render_frame(rs, &config, &plan, 0, 0, |_, _| {}).image()
}

fn reference(name: &str) -> tessera_image::ExrChannels {
    let bytes = std::fs::read(format!("{DIR}/motion/{name}.cycles.exr"))
        .unwrap_or_else(|e| panic!("{name}.cycles.exr: {e}"));
    tessera_image::read_exr(&bytes).unwrap()
}

/// Regions (and whole image) of `ours` off `theirs` by more than 2% plus four standard
/// errors, per channel, as "channel region: relative difference"; regions darker than 2%
/// of the image mean are skipped.
fn off_regions(what: &str, ours: &FrameImage, theirs: &tessera_image::ExrChannels) -> Vec<String> {
    let (w, h) = (theirs.width, theirs.height);
    let mut off = Vec::new();
    let mut worst = 0.0f64;
    for (c, channel) in ["R", "G", "B"].iter().enumerate() {
        let cy = theirs.get(channel).unwrap();
        let a = regions(w, h, |x, y| {
            let i = y * w + x;
            (ours.mean[i][c] as f64, ours.variance_of_mean[i][c] as f64)
        });
        let b = regions(w, h, |x, y| (cy[y * w + x] as f64, 0.0));
        let whole = b.last().unwrap().0;
        for (r, ((m, se), (want, _))) in a.iter().zip(&b).enumerate() {
            if *want < 0.02 * whole {
                continue;
            }
            if (m / want - 1.0).abs() > worst.abs() {
                worst = m / want - 1.0;
            }
            if (m - want).abs() > 0.02 * want + 4.0 * se {
                off.push(format!(
                    "{channel} region {r}: {:+.2}%",
                    100.0 * (m / want - 1.0)
                ));
            }
        }
    }
    eprintln!("{what}: worst region {:+.2}% against Cycles", 100.0 * worst);
    off
}

/// Luminance-like sum of the three channels at pixel `i`.
fn sum_rgb(img: &tessera_image::ExrChannels, i: usize) -> f64 {
    ["R", "G", "B"]
        .iter()
        .map(|c| img.get(c).unwrap()[i] as f64)
        .sum()
}

#[test]
fn frames_1_and_24_match_cycles() {
    for (frame, name) in [(1u32, "motion_ball.f01"), (24, "motion_ball.f24")] {
        let scene = load("motion/motion_ball.glb", f64::from(frame));
        let theirs = reference(name);
        let rs = RenderScene::build(&scene, theirs.width as u32, theirs.height as u32).unwrap();
        let off = off_regions(name, &render(&rs), &theirs);
        assert!(off.is_empty(), "frame {frame} off Cycles: {off:#?}");
    }
}

#[test]
fn the_blurred_streak_matches_cycles_motion_blur() {
    let file = "motion/motion_ball.glb";
    let shutter = Shutter {
        open: -0.5,
        close: 0.5,
    };
    let blurred = reference("motion_ball.f12_blur");
    let sharp = reference("motion_ball.f12");
    let (w, h) = (blurred.width, blurred.height);
    let base = load(file, 12.0);
    let rs =
        RenderScene::build_in_motion(&base, &keys(file, 12, shutter), w as u32, h as u32).unwrap();
    assert!(rs.has_motion());
    assert!(!rs.camera_moves(), "the camera stands still");
    // The sphere (48 x 24 UV sphere: 2,208 triangles) and the cube (12) move; the floor
    // does not.
    assert_eq!(rs.moving_triangles(), 48 * 22 * 2 + 2 * 48 + 12);
    assert!(rs.motion_warnings.is_empty(), "{:?}", rs.motion_warnings);
    let ours = render(&rs);
    let off = off_regions("motion_ball.f12_blur", &ours, &blurred);
    assert!(off.is_empty(), "blurred frame 12 off Cycles: {off:#?}");

    // The rows the motion touches: where Cycles' blurred and sharp frames differ by more
    // than a tenth of the largest difference.
    let diff: Vec<f64> = (0..h)
        .map(|y| {
            (0..w)
                .map(|x| (sum_rgb(&blurred, y * w + x) - sum_rgb(&sharp, y * w + x)).abs())
                .fold(0.0, f64::max)
        })
        .collect();
    let peak = diff.iter().cloned().fold(0.0, f64::max);
    let rows: Vec<usize> = (0..h).filter(|&y| diff[y] > 0.1 * peak).collect();
    assert!(rows.len() >= 8, "the streak spans {} rows", rows.len());
    // Column means over those rows: Cycles' blurred, ours, and Cycles' sharp.
    let profile = |f: &dyn Fn(usize) -> f64| -> Vec<f64> {
        (0..w)
            .map(|x| rows.iter().map(|&y| f(y * w + x)).sum::<f64>() / rows.len() as f64)
            .collect()
    };
    let want = profile(&|i| sum_rgb(&blurred, i));
    let got = profile(&|i| ours.mean[i].iter().map(|&v| v as f64).sum());
    let se = profile(&|i| ours.variance_of_mean[i].iter().map(|&v| v as f64).sum());
    let unblurred = profile(&|i| sum_rgb(&sharp, i));
    let top = want.iter().cloned().fold(0.0, f64::max);
    let tol = |x: usize| 0.02 * top + 4.0 * (se[x] / rows.len() as f64).sqrt();
    let worst = (0..w)
        .map(|x| (got[x] - want[x]).abs() - tol(x))
        .fold(f64::NEG_INFINITY, f64::max);
    let rel = (0..w)
        .map(|x| (got[x] - want[x]).abs() / top)
        .fold(0.0, f64::max);
    let rel_sharp = (0..w)
        .map(|x| (unblurred[x] - want[x]).abs() / top)
        .fold(0.0, f64::max);
    eprintln!(
        "streak over {} rows: largest column difference {:.2}% of the peak (unblurred: {:.2}%)",
        rows.len(),
        100.0 * rel,
        100.0 * rel_sharp
    );
    assert!(
        worst <= 0.0,
        "the streak's profile is off Cycles' by {:.4} beyond 2% of its peak {top:.4}",
        worst
    );
    // The unblurred frame is far from the blurred profile: the test sees blur.
    let sharp_off = (0..w)
        .filter(|&x| (unblurred[x] - want[x]).abs() > tol(x))
        .count();
    assert!(
        sharp_off >= 10,
        "only {sharp_off} columns tell the blurred frame from the sharp one"
    );
}

#[test]
fn a_shutter_over_a_still_moment_draws_no_time() {
    // The cubes' last keyframe is frame 21: around frame 30 nothing moves.
    let file = "animation/anim_cube.glb";
    let shutter = Shutter {
        open: -0.25,
        close: 0.25,
    };
    let base = load(file, 30.0);
    assert!(base.animated);
    let still = RenderScene::build_in_motion(&base, &keys(file, 30, shutter), 24, 16).unwrap();
    assert!(!still.has_motion());
    let plain = RenderScene::build(&base, 24, 16).unwrap();
    let (a, b) = (render(&still), render(&plain));
    assert!(
        a.mean == b.mean && a.variance_of_mean == b.variance_of_mean,
        "a shutter over a still moment changed the pixels"
    );
    // Around frame 11 they move, and the shutter is sampled.
    let moving =
        RenderScene::build_in_motion(&load(file, 11.0), &keys(file, 11, shutter), 24, 16).unwrap();
    assert!(moving.has_motion());
    assert!(moving.moving_triangles() > 0);
}

/// The determinism contract across traversal kernels (ARCHITECTURE.md §2) for moving
/// triangles: the blurred frame 12 (sphere and cube walked through the motion segments'
/// wide BVHs) renders to the same bits with every kernel this CPU has.
#[test]
fn every_kernel_renders_the_blurred_frame_bit_identically() {
    use tessera_render::geometry::Isa;
    let file = "motion/motion_ball.glb";
    let shutter = Shutter {
        open: -0.5,
        close: 0.5,
    };
    let mut rs =
        RenderScene::build_in_motion(&load(file, 12.0), &keys(file, 12, shutter), 32, 24).unwrap();
    assert!(rs.moving_triangles() > 2000);
    let plan = FramePlan::for_spp(rs.width, rs.height, 16, 16).unwrap();
    let mut reference = None;
    for isa in Isa::ALL.into_iter().filter(|i| i.available()) {
        rs.geometry.set_isa(isa).unwrap();
        let bits = crate::common::frame_bits(&render_frame(
            &rs,
            &reference_config(),
            &plan,
            0,
            0,
            |_, _| {},
        ));
        match &reference {
            None => reference = Some(bits),
            Some(r) => assert!(*r == bits, "{} differs from scalar", isa.name()),
        }
    }
}
