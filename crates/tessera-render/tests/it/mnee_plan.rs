//! Path tracing with manifold next-event estimation as a technique of the job contract and
//! the render plan: the plan's survey of MNEE's reach reads the renderer's chain length,
//! and the SDS pool resolved through the plan renders with `mnee`, in tiles, to its closed
//! form within its own error estimate.

use crate::common::{block_stats, z_critical};
use crate::vcm::{expected_blocks, floor_irradiance, pool};
use tessera_farm::job::{Integrator, JobSettings};
use tessera_farm::FramePlan;
use tessera_render::integrator::mnee::MAX_CHAIN;
use tessera_render::render::render_unit;
use tessera_render::scene::RenderScene;
use tessera_scene::analysis::MNEE_MAX_CHAIN;

/// The plan decides what MNEE reaches with the chain length the renderer's solver holds.
#[test]
fn the_plan_reads_the_solvers_chain_length() {
    assert_eq!(MNEE_MAX_CHAIN, MAX_CHAIN);
}

/// The pool resolved through the plan (`auto`): mnee at the plan's depth (16: the floor and
/// the water cover 80% of their bounding box) and Russian roulette (from 5), tiled like path
/// tracing. Rendered at 24 x 24 in 4 tiles of 12, 16 passes
/// of 4 spp: each 6 x 6 block within `z σ` (Bonferroni 1%) plus 0.5% (the closed form's 4 x
/// 4 film points per pixel against the render's random ones) of the closed form, and the
/// image mean within `z σ` (1%, σ its standard error over the passes: the render's own
/// error estimate) plus the same 0.5%. The closed form counts `L S D S E` only, so the
/// plan's settings are rendered at depth 3: at the plan's depth MNEE at the later
/// non-specular vertices adds the floor's light returned to it by the water's underside
/// (`L S D S D S E`, about 15%), which
/// [`mnee_at_depth_16_finds_the_light_returned_under_the_water`] checks.
#[test]
fn the_pool_through_the_plan_renders_to_its_closed_form() {
    let scene = pool();
    let (w, h, block, passes) = (24u32, 24u32, 6u32, 16u32);
    let mut settings = JobSettings::new("builtin:test-pool");
    settings.width = Some(w);
    settings.height = Some(h);
    settings.tile_size = 12;
    settings.seed = 11;
    let job = settings.validate().unwrap();
    let resolved = tessera_scene::job::resolve_job(
        &job,
        &scene,
        tessera_scene::job::no_pilot("not asked on the pool"),
    )
    .unwrap();
    assert_eq!(resolved.config.integrator, Integrator::Mnee);
    assert_eq!(
        (resolved.config.max_depth, resolved.config.rr_depth),
        (16, 5)
    );
    assert_eq!(resolved.render_plan.unsampled(Integrator::Mnee), None);
    assert!(resolved.plan.tile_count() > 1, "mnee tiles like path");
    let plan = FramePlan::new(w, h, 12, 4, passes).unwrap();
    let rs = RenderScene::build(&scene, w, h).unwrap();
    let config = tessera_render::render::RenderConfig {
        max_depth: 3,
        ..resolved.config
    };
    let (bx, by) = (w / block, h / block);
    let lum = |p: [f32; 3]| 0.2126 * p[0] as f64 + 0.7152 * p[1] as f64 + 0.0722 * p[2] as f64;
    // Per pass, the sum of each block's pixel luminances.
    let mut sums = vec![vec![0.0f64; (bx * by) as usize]; passes as usize];
    for unit in plan.units(0, 4) {
        let r = render_unit(&rs, &config, &plan, unit);
        let rect = plan.tile(unit.tile);
        let n = (rect.width * rect.height) as usize;
        for k in 0..unit.pass_count {
            let pass = (unit.first_pass + k) as usize;
            for (i, m) in r.pass_means[k as usize * n..(k as usize + 1) * n]
                .iter()
                .enumerate()
            {
                let (x, y) = (
                    rect.x0 + i as u32 % rect.width,
                    rect.y0 + i as u32 / rect.width,
                );
                sums[pass][((y / block) * bx + x / block) as usize] += lum(*m);
            }
        }
    }
    let per = (block * block) as f64;
    let means: Vec<Vec<f64>> = sums
        .iter()
        .map(|p| p.iter().map(|s| s / per).collect())
        .collect();
    let stats = block_stats(&means);
    let exact = expected_blocks(&rs, w, h, block, floor_irradiance);
    crate::mnee::pool_blocks_match_closed_form(&stats, &exact, "mnee (plan)");
    // The image mean, per pass, and its standard error over the passes.
    let image: Vec<Vec<f64>> = means
        .iter()
        .map(|p| vec![p.iter().sum::<f64>() / p.len() as f64])
        .collect();
    let (mean, var) = block_stats(&image)[0];
    let expect: f64 = exact.iter().sum::<f64>() / exact.len() as f64;
    let z = (mean - expect) / var.sqrt();
    eprintln!(
        "pool image: mnee (plan) {mean:.5} ± {:.5}, closed form {expect:.5} ({:+.3}%, z = {z:+.2})",
        var.sqrt(),
        100.0 * (mean / expect - 1.0)
    );
    assert!(expect > 0.01, "the floor is lit: {expect}");
    assert!(
        (mean - expect).abs() <= z_critical(0.01, 1) * var.sqrt() + 5e-3 * expect,
        "{mean} vs {expect}"
    );
}

/// At the plan's depth (16) MNEE at the later non-specular vertices finds the floor's light
/// returned to it by the water's underside (`L S D S D S E`), which from a point light no
/// BSDF-sampled ray can: mnee's image mean at depth 16 against vcm's (merging samples that
/// light too; its blur moves light between pixels, barely in or out of the image), within
/// 4 standard errors of the difference plus 3% (vcm's merging bias), and more than 5% above
/// mnee's at depth 3 (the closed form's `L S D S E` alone; about 15% measured at 256 x 256).
/// With MNEE at the first non-specular vertex only, depth 16 renders what depth 3 does and
/// this fails.
#[test]
fn mnee_at_depth_16_finds_the_light_returned_under_the_water() {
    let scene = pool();
    let (w, h, passes) = (16u32, 16u32, 16u32);
    let mut settings = JobSettings::new("builtin:test-pool");
    settings.width = Some(w);
    settings.height = Some(h);
    settings.seed = 5;
    let job = settings.validate().unwrap();
    let resolved =
        tessera_scene::job::resolve_job(&job, &scene, tessera_scene::job::no_pilot("")).unwrap();
    assert_eq!(resolved.config.integrator, Integrator::Mnee);
    assert_eq!(resolved.config.max_depth, 16);
    let rs = RenderScene::build(&scene, w, h).unwrap();
    let lum = |p: [f32; 3]| 0.2126 * p[0] as f64 + 0.7152 * p[1] as f64 + 0.0722 * p[2] as f64;
    // The image mean of each pass, then their mean and the variance of that mean.
    let image_mean = |integrator: Integrator, depth: u32, tile: u32, spp: u32| -> (f64, f64) {
        let config = tessera_render::render::RenderConfig {
            integrator,
            max_depth: depth,
            ..resolved.config
        };
        let plan = FramePlan::new(w, h, tile, spp, passes).unwrap();
        let mut sums = vec![vec![0.0f64]; passes as usize];
        for unit in plan.units(0, 1) {
            let r = render_unit(&rs, &config, &plan, unit);
            let n = (plan.tile(unit.tile).width * plan.tile(unit.tile).height) as usize;
            for k in 0..unit.pass_count {
                let pass = (unit.first_pass + k) as usize;
                sums[pass][0] += r.pass_means[k as usize * n..(k as usize + 1) * n]
                    .iter()
                    .map(|m| lum(*m))
                    .sum::<f64>();
            }
        }
        let means: Vec<Vec<f64>> = sums.iter().map(|p| vec![p[0] / (w * h) as f64]).collect();
        block_stats(&means)[0]
    };
    let (m16, v16) = image_mean(Integrator::Mnee, 16, 8, 4);
    let (m3, v3) = image_mean(Integrator::Mnee, 3, 8, 4);
    let (vcm, vv) = image_mean(Integrator::Vcm, 16, w, 4);
    eprintln!(
        "pool {w}x{h}: mnee depth 16 {m16:.5} ± {:.5}, depth 3 {m3:.5} ± {:.5}, vcm depth 16 \
         {vcm:.5} ± {:.5}",
        v16.sqrt(),
        v3.sqrt(),
        vv.sqrt()
    );
    assert!(
        m16 > 1.05 * m3 + 4.0 * (v16 + v3).sqrt(),
        "mnee at depth 16 ({m16}) finds the light returned under the water beyond depth 3's \
         ({m3})"
    );
    assert!(
        (m16 - vcm).abs() <= 4.0 * (v16 + vv).sqrt() + 0.03 * vcm,
        "mnee at depth 16 ({m16}) against vcm at depth 16 ({vcm})"
    );
}

/// The pool at 256 x 256 through the plan, before and after it chose mnee: the plan's
/// choice now (mnee, depth 16, roulette from 5, tiles of 32) against its choice before
/// (vcm at the same depth, one whole-frame tile) and vcm at depth 3 (the closed form's
/// `L S D S E` alone), each `TESSERA_POOL_PASSES` passes (default 16) of 1 sample on 2
/// threads, seed 11: CPU seconds, the measured relative RMS error per pixel against the
/// closed form (box filtered), the image mean against the closed form's, and the reported
/// estimate (the pass spread, `tessera_farm::image_relative_error`; vcm's bias term is
/// not in it). At depth 16 vcm also renders the floor's light returned to it under the
/// water (`L S D S D S E`), which the closed form and mnee leave out: its offset is that
/// light. A measurement, run by hand under the heavy lock:
/// `cargo test --release -p tessera-render --test it -- --ignored mnee_plan::pool_through_the_plan_measurement --nocapture`
#[test]
#[ignore = "a measurement: the pool through the plan, mnee against vcm"]
fn pool_through_the_plan_measurement() {
    let passes = std::env::var("TESSERA_POOL_PASSES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(16);
    let scene = pool();
    let (w, h) = (256u32, 256u32);
    let mut settings = JobSettings::new("builtin:test-pool");
    settings.width = Some(w);
    settings.height = Some(h);
    settings.seed = 11;
    let job = settings.validate().unwrap();
    let resolved =
        tessera_scene::job::resolve_job(&job, &scene, tessera_scene::job::no_pilot("")).unwrap();
    assert_eq!(resolved.config.integrator, Integrator::Mnee);
    let rs = RenderScene::build(&scene, w, h).unwrap();
    let exact = expected_blocks(&rs, w, h, 1, floor_irradiance);
    let threads = rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .unwrap();
    let cases = [
        ("mnee (the plan now), depth 16", Integrator::Mnee, 16, 32),
        ("vcm (the plan before), depth 16", Integrator::Vcm, 16, w),
        ("vcm, depth 3", Integrator::Vcm, 3, w),
    ];
    for (name, integrator, depth, tile) in cases {
        let config = tessera_render::render::RenderConfig {
            integrator,
            max_depth: depth,
            ..resolved.config
        };
        let plan = FramePlan::new(w, h, tile, 1, passes).unwrap();
        let c0 = crate::vcm::cpu_seconds();
        let results: Vec<_> = threads.install(|| {
            use rayon::prelude::*;
            plan.units(0, passes)
                .par_iter()
                .map(|u| render_unit(&rs, &config, &plan, *u))
                .collect()
        });
        let cpu = crate::vcm::cpu_seconds() - c0;
        let (measured, estimate, offset) = crate::vcm::pool_errors(plan, results, &exact);
        eprintln!(
            "pool 256x256, {name}: {passes} passes x 1 spp, {cpu:.1} CPU s; measured rel. RMS \
             error {measured:.4}, estimate {estimate:.4} (ratio {:.2}); image mean {:+.2}% off \
             the closed form",
            estimate / measured,
            100.0 * offset
        );
    }
}
