//! Metropolis light transport against a closed form, against bdpt, against itself across
//! thread counts, and its efficiency on Veach's door-ajar room.
//!
//! Statistics as in `bdpt.rs`: a pass's chains cross pixels, so the pixels of one pass are
//! correlated; block means are formed per pass and their spread is taken across passes,
//! which are independent replicates (each with its own bootstrap and chains).

use crate::common::{assert_blocks_agree, block_passes, block_stats};
use tessera_farm::FramePlan;
use tessera_render::integrator::Integrator;
use tessera_render::render::{render_frame, render_unit, RenderConfig};
use tessera_render::scene::{rays_traced, RenderScene};
use tessera_scene::builtin::{FURNACE_ALBEDO, FURNACE_EMISSION};

fn settings(integrator: Integrator, seed: u64, max_depth: u32) -> RenderConfig {
    RenderConfig {
        integrator,
        seed,
        max_depth,
        rr_depth: 3,
        ..RenderConfig::default()
    }
}

fn door_ajar() -> tessera_scene::Scene {
    tessera_scene::load(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../scenes/door-ajar.gltf"
    ))
    .unwrap()
}

/// The furnace (a closed sphere of emission `E` and albedo `a`, seen from inside) has the
/// radiance `E (1 - a^(D+1)) / (1 - a)` everywhere for paths of at most `D` bounces: every
/// block and the whole image, by z-tests at family-wise level 0.01 (Bonferroni) with the
/// spread across passes.
#[test]
fn mlt_furnace_matches_its_closed_form() {
    let scene = tessera_scene::load("builtin:furnace").unwrap();
    let (w, h) = (16, 16);
    let depth = 6;
    let rs = RenderScene::build(&scene, w, h).unwrap();
    let plan = FramePlan::new(w, h, w, 4, 32).unwrap();
    let mut passes = block_passes(&rs, &settings(Integrator::Mlt, 3, depth), &plan, 4);
    // The whole image as one more block.
    for p in &mut passes {
        let whole = p.iter().sum::<f64>() / p.len() as f64;
        p.push(whole);
    }
    let stats = block_stats(&passes);
    let a = FURNACE_ALBEDO as f64;
    let expected = FURNACE_EMISSION as f64 * (1.0 - a.powi(depth as i32 + 1)) / (1.0 - a);
    let reference = vec![(expected, 0.0); stats.len()];
    let worst = assert_blocks_agree("furnace mlt vs closed form", &stats, &reference);
    let (mean, var) = stats[stats.len() - 1];
    eprintln!(
        "furnace mlt mean {mean:.5} ± {:.5} (expected {expected:.5}), max |z| {worst:.2}",
        var.sqrt()
    );
}

/// mlt and bdpt estimate the same image: on the Cornell box (area light, every technique
/// in play; 16 blocks) and on the door-ajar room (light only through the gap; 4 blocks of
/// 12 x 12 pixels: a small block that no chain of a pass visits is black in most passes
/// and bright in a few, a spread too skewed for a z-test on 32 passes).
#[test]
fn mlt_agrees_with_bdpt_block_by_block() {
    for (name, scene, (w, h), spp, block) in [
        (
            "cornell box",
            tessera_scene::load("builtin:cornell-box").unwrap(),
            (24, 24),
            8,
            6,
        ),
        ("door ajar", door_ajar(), (24, 24), 16, 12),
    ] {
        let rs = RenderScene::build(&scene, w, h).unwrap();
        let plan = FramePlan::new(w, h, w, spp, 32).unwrap();
        let mlt = block_stats(&block_passes(
            &rs,
            &settings(Integrator::Mlt, 21, 5),
            &plan,
            block,
        ));
        let bdpt = block_stats(&block_passes(
            &rs,
            &settings(Integrator::Bdpt, 22, 5),
            &plan,
            block,
        ));
        assert!(mlt.iter().any(|b| b.0 > 0.0), "{name}: a black image");
        assert_blocks_agree(&format!("{name}: mlt vs bdpt"), &mlt, &bdpt);
    }
}

/// ARCHITECTURE.md §2 for mlt: a pass's bootstrap and chains run in a fixed order inside
/// its unit, so thread counts and unit splits change nothing.
#[test]
fn mlt_is_bit_identical_across_threads_and_unit_splits() {
    let scene = door_ajar();
    let (w, h) = (16, 12);
    let rs = RenderScene::build(&scene, w, h).unwrap();
    let plan = FramePlan::new(w, h, w.max(h), 2, 4).unwrap();
    assert_eq!(plan.tile_count(), 1);
    let s = settings(Integrator::Mlt, 9, 6);
    let bits = super::common::frame_bits;
    let one = render_frame(&rs, &s, &plan, 0, 1, |_, _| {});
    let two = render_frame(&rs, &s, &plan, 0, 2, |_, _| {});
    assert!(bits(&one) == bits(&two), "2 threads differ from 1");
    let mut acc = tessera_farm::FrameAccumulator::new(plan);
    let mut units = plan.units(0, 1);
    units.reverse();
    for u in units {
        acc.offer(render_unit(&rs, &s, &plan, u)).unwrap();
    }
    assert!(bits(&acc) == bits(&one), "units in reverse order differ");
    // Smaller tiles: each tile's pixels from the whole frame's chains, the same values.
    let tiled = FramePlan::new(w, h, 8, 2, 4).unwrap();
    assert!(tiled.tile_count() > 1);
    let split = render_frame(&rs, &s, &tiled, 0, 2, |_, _| {});
    assert!(bits(&split) == bits(&one), "a tiled plan differs");
    assert!(one.image().mean.iter().any(|p| p[0] > 0.0), "a black image");
}

/// Efficiency `1 / (MSE x seconds)` of mlt, bdpt and path on the door-ajar room (and vcm
/// and ppm when `MLT_ONLY` names them), per pixel against a converged bdpt reference (its
/// own variance subtracted). Prints a table; run with `--ignored --nocapture`. CPU time,
/// so not an assertion.
#[test]
#[ignore = "a measurement: prints the efficiency table"]
fn mlt_efficiency_table() {
    use std::time::Instant;
    // Seconds of CPU the process spent (both threads), from /proc/self/stat: on a shared
    // machine less disturbed by the load than wall time. MLT_WALL=1 takes wall time.
    let cpu = || -> Option<f64> {
        let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
        let after = stat.rsplit(')').next().unwrap_or("");
        let f: Vec<f64> = after
            .split_whitespace()
            .skip(11)
            .take(2)
            .filter_map(|v| v.parse().ok())
            .collect();
        (f.len() == 2).then(|| f.iter().sum::<f64>() / 100.0)
    };
    let wall = std::env::var("MLT_WALL").is_ok();
    // One thread, the units rendered on this one in order, so that its ray counter
    // (`rays_traced`) brackets the render: CPU seconds per ray give each technique's cost
    // per ray, the pilot's `BDPT_RAY_COST` and `MLT_RAY_COST`.
    let rays = std::cell::Cell::new(0u64);
    let time = |rs: &RenderScene, s: &RenderConfig, plan: &FramePlan| {
        let (t, c, r) = (Instant::now(), cpu(), rays_traced());
        let mut acc = tessera_farm::FrameAccumulator::new(*plan);
        for u in plan.units(0, 1) {
            acc.offer(render_unit(rs, s, plan, u)).unwrap();
        }
        rays.set(rays_traced() - r);
        let secs = match (wall, c, cpu()) {
            (false, Some(c0), Some(c1)) => c1 - c0,
            _ => t.elapsed().as_secs_f64(),
        };
        (acc.image(), secs)
    };
    let lum = |p: [f32; 3]| 0.2126 * p[0] as f64 + 0.7152 * p[1] as f64 + 0.0722 * p[2] as f64;
    let env = |k: &str, d: u32| -> u32 {
        std::env::var(k)
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(d)
    };
    let (w, h) = (env("MLT_SIZE", 32), env("MLT_SIZE", 32));
    let depth = 8;
    let rs = RenderScene::build(&door_ajar(), w, h).unwrap();
    let ref_passes = env("MLT_REF_PASSES", 256);
    // The reference, optionally cached in the file MLT_REF_CACHE (luminance mean and
    // variance of the mean per pixel, little-endian f64) between runs.
    let cache = std::env::var("MLT_REF_CACHE").ok();
    let cached = cache.as_ref().and_then(|p| std::fs::read(p).ok());
    let (ref_mean, ref_varm, ref_secs): (Vec<f64>, Vec<f64>, f64) = match cached {
        Some(bytes) if bytes.len() == (w * h * 16) as usize => {
            let v: Vec<f64> = bytes
                .chunks(8)
                .map(|c| f64::from_le_bytes(c.try_into().unwrap()))
                .collect();
            let (m, var) = v.split_at((w * h) as usize);
            (m.to_vec(), var.to_vec(), 0.0)
        }
        _ => {
            let (img, secs) = time(
                &rs,
                &settings(Integrator::Bdpt, 99, depth),
                &FramePlan::new(w, h, w, 8, ref_passes).unwrap(),
            );
            let m: Vec<f64> = img.mean.iter().map(|p| lum(*p)).collect();
            let var: Vec<f64> = img.variance_of_mean.iter().map(|p| lum(*p)).collect();
            if let Some(p) = &cache {
                let bytes: Vec<u8> = m.iter().chain(&var).flat_map(|x| x.to_le_bytes()).collect();
                std::fs::write(p, bytes).unwrap();
            }
            (m, var, secs)
        }
    };
    let n = ref_mean.len() as f64;
    let ref_var: f64 = ref_varm.iter().sum::<f64>() / n;
    let truth = ref_mean.iter().sum::<f64>() / n;
    eprintln!(
        "door-ajar {w}x{h}: reference bdpt {} spp in {ref_secs:.1} s, mean {truth:.5}, its \
         rel. RMSE {:.4}",
        8 * ref_passes,
        ref_var.sqrt() / truth
    );
    let spp_per_pass = 8;
    let passes = env("MLT_PASSES", 16);
    let only = std::env::var("MLT_ONLY").unwrap_or_default();
    let plan = FramePlan::new(w, h, w, spp_per_pass, passes).unwrap();
    let mut rows = Vec::new();
    // vcm and ppm only when asked for by name (MLT_ONLY): their merges are biased, and
    // the MSE here counts that bias with the noise, as the goal's efficiency does.
    let all = [
        Integrator::Path,
        Integrator::Bdpt,
        Integrator::Mlt,
        Integrator::Vcm,
        Integrator::Ppm,
    ];
    for integrator in all {
        let by_name = only.split(',').any(|o| o == integrator.as_str());
        let biased = matches!(integrator, Integrator::Vcm | Integrator::Ppm);
        if (!only.is_empty() && !by_name) || (only.is_empty() && biased) {
            continue;
        }
        let mut s = settings(integrator, u64::from(env("MLT_SEED", 4)), depth);
        s.rr_depth = 5;
        // mlt's chains grow with the samples per pass (MLT_SPP_PER_PASS, the same total).
        let mlt_spp = env("MLT_SPP_PER_PASS", spp_per_pass);
        let plan = if integrator == Integrator::Mlt {
            FramePlan::new(w, h, w, mlt_spp, spp_per_pass * passes / mlt_spp).unwrap()
        } else {
            plan
        };
        let (img, secs) = time(&rs, &s, &plan);
        let mse = img
            .mean
            .iter()
            .zip(&ref_mean)
            .map(|(p, r)| (lum(*p) - r).powi(2))
            .sum::<f64>()
            / n
            - ref_var;
        let mean = img.mean.iter().map(|p| lum(*p)).sum::<f64>() / n;
        let eff = 1.0 / (mse.max(1e-30) * secs);
        rows.push((integrator, eff));
        eprintln!(
            "door-ajar {w}x{h}, {} spp, {integrator}: {secs:.2} s, mean {mean:.5}, rel. RMSE \
             {:.4}, 1/(MSE s) {eff:.4e}, {} rays, {:.1} ns per ray",
            spp_per_pass * passes,
            mse.max(0.0).sqrt() / truth,
            rays.get(),
            secs * 1e9 / rays.get().max(1) as f64,
        );
    }
    let path = rows[0].1;
    for (i, e) in rows {
        eprintln!("  {i}: {:.2}x path", e / path);
    }
}
