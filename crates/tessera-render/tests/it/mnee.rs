//! Manifold next-event estimation (`integrator::mnee`): the solver and its generalized
//! geometry term against the closed form of a point light's irradiance through flat
//! water, path tracing with MNEE on the SDS pool against that closed form, and against
//! plain path tracing (a z test per image block) on a glass ball under a small area light,
//! where the two must agree because MNEE's paths are left out of BSDF sampling exactly
//! when MNEE finds them.

use crate::common::{block_stats, z_critical};
use crate::vcm::{expected_blocks, floor_irradiance, pool, pool_errors, X_LIGHT};
use glam::{Vec2, Vec3};
use rayon::prelude::*;
use tessera_farm::FramePlan;
use tessera_render::integrator::mnee::{
    claims, connect, sample_end, shadow_ray_clear, Anchor, LightEnd,
};
use tessera_render::integrator::{render_unit_path_mnee, Integrator};
use tessera_render::render::{render_unit, RenderConfig};
use tessera_render::scene::RenderScene;
use tessera_scene::{Material, MaterialKind, Mesh, Scene};

/// The pool's floor irradiance by MNEE at floor points at distance `r` from the light's
/// foot, with no Monte Carlo: one connection per point (the point light needs no light
/// sample), `E = T I |dω_x/dA⊥_y| cos θ_x`, where `T` carries the Fresnel
/// transmittance and the radiance's `n²` entering the water, against
/// `vcm::floor_irradiance` (flux conservation through the refraction): within 0.2%.
#[test]
fn mnee_irradiance_through_flat_water_is_the_closed_form() {
    let rs = RenderScene::build(&pool(), 24, 24).unwrap();
    let mut worst = 0.0f64;
    for (r, phi) in [
        (0.0f32, 0.0f32),
        (0.1, 1.0),
        (0.35, 2.0),
        (0.8, 3.0),
        (1.3, 3.1),
        (1.9, 3.0),
        (0.6, -1.2),
    ] {
        let target = Vec3::new(X_LIGHT as f32 + r * phi.cos(), 0.0, r * phi.sin());
        // The floor point, found from below (nothing else is there).
        let o = target - Vec3::Y;
        let hit = rs.intersect(o, Vec3::Y, 2.0).expect("floor");
        let sp = rs.surface(&hit, o, Vec3::Y);
        let x = Anchor::of(&sp);
        let (end, pdf) = sample_end(&rs, sp.p, 0, 1.0, Vec2::ZERO).unwrap();
        assert!(matches!(end, LightEnd::Point { .. }) && pdf == 1.0);
        let c = connect(&rs, &x, &end, 0.0, 2).expect("a connection through the water");
        assert_eq!(c.chain.len(), 1);
        let e = (c.throughput.x * c.emission.x * c.geometry * c.wi.y.abs()) as f64;
        let rr = ((sp.p.x as f64 - X_LIGHT).powi(2) + (sp.p.z as f64).powi(2)).sqrt();
        let expect = floor_irradiance(rr);
        let rel = e / expect - 1.0;
        eprintln!("floor r = {rr:.3}: MNEE {e:.6}, closed form {expect:.6} ({rel:+.2e})");
        assert!(rel.abs() < 2e-3, "r = {rr}: {e} vs {expect}");
        worst = worst.max(rel.abs());
    }
    eprintln!("worst relative error {worst:.2e}");
}

/// Per-pass luminance means of `block x block` blocks, `[pass][block]`, of path tracing
/// with (`mnee`) or without MNEE; one tile per pass.
fn passes(
    rs: &RenderScene,
    s: &RenderConfig,
    plan: &FramePlan,
    block: u32,
    mnee: bool,
) -> Vec<Vec<f64>> {
    assert_eq!(plan.tile_count(), 1);
    let (bx, by) = (plan.width.div_ceil(block), plan.height.div_ceil(block));
    let mut out: Vec<(u32, Vec<f64>)> = plan
        .units(0, 1)
        .par_iter()
        .map(|u| {
            let r = unit(rs, s, plan, *u, mnee);
            let mut sums = vec![0.0f64; (bx * by) as usize];
            let mut counts = vec![0u32; (bx * by) as usize];
            for y in 0..plan.height {
                for x in 0..plan.width {
                    let m = r.pass_means[(y * plan.width + x) as usize];
                    let b = ((y / block) * bx + x / block) as usize;
                    sums[b] += 0.2126 * m[0] as f64 + 0.7152 * m[1] as f64 + 0.0722 * m[2] as f64;
                    counts[b] += 1;
                }
            }
            let means = sums
                .iter()
                .zip(&counts)
                .map(|(s, &c)| s / c as f64)
                .collect();
            (u.first_pass, means)
        })
        .collect();
    out.sort_by_key(|p| p.0);
    out.into_iter().map(|p| p.1).collect()
}

/// One unit of path tracing with (`mnee`) or without MNEE.
fn unit(
    rs: &RenderScene,
    s: &RenderConfig,
    plan: &FramePlan,
    u: tessera_farm::WorkUnit,
    mnee: bool,
) -> tessera_farm::UnitResult {
    if mnee {
        render_unit_path_mnee(rs, s, plan, u)
    } else {
        render_unit(rs, s, plan, u)
    }
}

fn settings(seed: u64, max_depth: u32) -> RenderConfig {
    RenderConfig {
        integrator: Integrator::Path,
        seed,
        max_depth,
        rr_depth: 8,
        ..RenderConfig::default()
    }
}

/// Each pool block's mean `(mean, variance of the mean)` in `stats` within `z σ` of the
/// closed form's `exact` (Bonferroni 1% over the blocks) plus 0.5%: the closed form's 4 x 4
/// film points per pixel against a render's random ones.
pub(crate) fn pool_blocks_match_closed_form(stats: &[(f64, f64)], exact: &[f64], label: &str) {
    let crit = z_critical(0.01, stats.len());
    for (b, &(mean, var)) in stats.iter().enumerate() {
        let se = var.sqrt();
        eprintln!(
            "pool block {b}: {label} {mean:.5} ± {se:.5}, closed form {:.5} ({:+.3}%)",
            exact[b],
            100.0 * (mean / exact[b] - 1.0)
        );
        assert!(
            (mean - exact[b]).abs() <= crit * se + 5e-3 * exact[b],
            "block {b}: {mean} vs {}",
            exact[b]
        );
    }
}

/// Path tracing with MNEE renders the SDS pool (no technique of path tracing or bdpt
/// samples it) to its closed form: each 6 x 6 block within `z σ` (Bonferroni 1%) plus
/// 0.5% (the closed form's 4 x 4 film points per pixel against the render's random ones),
/// and the image mean within 1%.
#[test]
fn path_with_mnee_renders_the_pool_to_its_closed_form() {
    let (w, h, block) = (24, 24, 6);
    let rs = RenderScene::build(&pool(), w, h).unwrap();
    let plan = FramePlan::new(w, h, w, 4, 16).unwrap();
    let s = settings(3, 3);
    let stats = block_stats(&passes(&rs, &s, &plan, block, true));
    let exact = expected_blocks(&rs, w, h, block, floor_irradiance);
    pool_blocks_match_closed_form(&stats, &exact, "path+MNEE");
    let mean: f64 = stats.iter().map(|s| s.0).sum::<f64>() / stats.len() as f64;
    let expect: f64 = exact.iter().sum::<f64>() / exact.len() as f64;
    eprintln!(
        "pool image: path+MNEE {mean:.5}, closed form {expect:.5} ({:+.3}%)",
        100.0 * (mean / expect - 1.0)
    );
    assert!(
        expect > 0.01 && (mean / expect - 1.0).abs() < 0.01,
        "{mean} vs {expect}"
    );
    // Not vacuous: plain path tracing leaves the floor black.
    let plain = block_stats(&passes(&rs, &s, &plan, block, false));
    let plain_mean: f64 = plain.iter().map(|s| s.0).sum::<f64>() / plain.len() as f64;
    assert!(plain_mean < 1e-3 * expect, "{plain_mean}");
}

/// `builtin:caustic` with its small sphere light replaced by an emissive square of the
/// same radiance facing down (a triangle light, which MNEE samples) and no environment.
pub fn glass_ball() -> Scene {
    let mut scene = tessera_scene::load("builtin:caustic").unwrap();
    let light = scene.spheres.pop().unwrap();
    let (c, h) = (light.center, 0.05f32);
    let v = Vec3::new;
    scene.materials.push(Material {
        name: "square light".into(),
        kind: MaterialKind::Diffuse { albedo: Vec3::ZERO },
        emission: Vec3::splat(2000.0),
        double_sided: false,
    });
    scene.meshes.push(Mesh {
        name: "square light".into(),
        positions: vec![
            c + v(-h, 0.0, -h),
            c + v(-h, 0.0, h),
            c + v(h, 0.0, h),
            c + v(h, 0.0, -h),
        ],
        normals: None,
        uvs: vec![],
        tangents: None,
        // Wound clockwise seen from above: the normal, and the emission, face down.
        indices: vec![[0, 2, 1], [0, 3, 2]],
        colors: None,
        material: scene.materials.len() as u32 - 1,
    });
    scene.environment = None;
    scene
}

/// Path tracing with and without MNEE converge to the same image on the glass ball (the
/// caustic under it is light -> glass -> glass -> floor): each 8 x 8 block's means, over
/// 64 passes each, differ by at most the Bonferroni 1% z of their combined standard
/// error. MNEE must also find the caustic: its share of the image is checked against the
/// plain path tracer's total.
#[test]
fn path_with_mnee_agrees_with_path_tracing_on_the_glass_ball() {
    let (w, h, block) = (32, 32, 8);
    let rs = RenderScene::build(&glass_ball(), w, h).unwrap();
    let plan = FramePlan::new(w, h, w, 16, 64).unwrap();
    let plain = block_stats(&passes(&rs, &settings(11, 8), &plan, block, false));
    let with = block_stats(&passes(&rs, &settings(12, 8), &plan, block, true));
    let crit = z_critical(0.01, plain.len());
    let mut worst = 0.0f64;
    for (b, (p, m)) in plain.iter().zip(&with).enumerate() {
        let se = (p.1 + m.1).sqrt();
        if se == 0.0 {
            // Black in every pass of both (the sky: no environment).
            assert_eq!(p.0, m.0, "block {b}");
            continue;
        }
        let z = (m.0 - p.0) / se;
        eprintln!(
            "block {b}: path {:.5} ± {:.5}, path+MNEE {:.5} ± {:.5}, z = {z:+.2}",
            p.0,
            p.1.sqrt(),
            m.0,
            m.1.sqrt()
        );
        assert!(z.abs() <= crit, "block {b}: z = {z}");
        worst = worst.max(z.abs());
    }
    let var_plain: f64 = plain.iter().map(|s| s.1).sum();
    let var_with: f64 = with.iter().map(|s| s.1).sum();
    eprintln!(
        "worst |z| {worst:.2} (critical {crit:.2}); summed block variance path {var_plain:.3e}, \
         path+MNEE {var_with:.3e}"
    );
}

/// The path tracer runs MNEE only where next-event estimation's shadow ray was blocked,
/// while [`claims`] decides which BSDF-sampled paths MNEE owns: a path claimed but never
/// generated would be light lost. On the glass ball, for floor points across the ball's
/// shadow and its caustic (a 48 x 48 grid) and 5 x 5 points of the light: wherever the
/// shadow ray is clear, no specular connection exists and nothing is claimed; where a
/// connection exists, the shadow ray is blocked and `claims` accepts the solved chain.
/// Not vacuous: hundreds of pairs connect through the ball.
#[test]
fn mnee_runs_wherever_it_claims_on_the_glass_ball() {
    let rs = RenderScene::build(&glass_ball(), 8, 8).unwrap();
    let light = Vec3::new(0.3, 2.5, -0.5);
    let (mut connected, mut clear) = (0, 0);
    for i in 0..48 {
        for j in 0..48 {
            // Floor points over [-1.2, 1.0] x [-0.9, 1.3] about the shadow's centre.
            let target = Vec3::new(
                -1.2 + 2.2 * (i as f32 + 0.5) / 48.0,
                0.0,
                -0.9 + 2.2 * (j as f32 + 0.5) / 48.0,
            );
            // The floor point, found from below (nothing else is there).
            let o = target - Vec3::Y;
            let hit = rs.intersect(o, Vec3::Y, 2.0).expect("floor");
            let x = Anchor::of(&rs.surface(&hit, o, Vec3::Y));
            for a in 0..5 {
                for b in 0..5 {
                    let y = light
                        + Vec3::new(-0.045 + 0.0225 * a as f32, 0.0, -0.045 + 0.0225 * b as f32);
                    // The light point as a ray from below finds it (its surface point).
                    let from = y - Vec3::Y * 0.1;
                    let lh = rs.intersect(from, Vec3::Y, 0.2).expect("the light square");
                    let lsp = rs.surface(&lh, from, Vec3::Y);
                    let end = LightEnd::Area {
                        li: lsp.light as usize,
                        p: lsp.p,
                        n: lsp.ng,
                    };
                    let is_clear = shadow_ray_clear(&rs, &x, lsp.p, lsp.p_error, lsp.ng, 0.0);
                    let c = connect(&rs, &x, &end, 0.0, 2);
                    if is_clear {
                        clear += 1;
                        assert!(
                            c.is_none(),
                            "x {}, y {}: a chain past a clear shadow ray",
                            x.p,
                            lsp.p
                        );
                    }
                    let claimed = c.is_some_and(|c| {
                        let path: Vec<Vec3> = c.chain.positions().collect();
                        claims(&rs, &x, Vec3::Y, 2, &path, &lsp, 0.0)
                    });
                    assert_eq!(claimed, c.is_some() && !is_clear, "x {}, y {}", x.p, lsp.p);
                    connected += usize::from(c.is_some());
                }
            }
        }
    }
    eprintln!("{connected} connections through the ball, {clear} clear shadow rays");
    assert!(connected > 200 && clear > 10_000, "{connected} {clear}");
}

/// CPU seconds (user + system) this process has used, from `/proc/self/stat`.
fn cpu_seconds() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").expect("/proc/self/stat");
    let rest = &stat[stat.rfind(')').expect("comm") + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    (f[11].parse::<f64>().unwrap() + f[12].parse::<f64>().unwrap()) / 100.0
}

/// The glass ball of bench/compare (`python3 bench/compare/make_scenes.py` writes it) at
/// 256 x 256, 64 spp (4 passes of 16, the plan's), depth 16, 2 threads: the noise variance
/// of path tracing with and without MNEE from seed pairs (the per-pixel variance of one
/// render, from `(a - b)² / 2`, pixels that see the light left out) and the CPU seconds.
/// A measurement, run by hand under the heavy lock:
/// `cargo test -p tessera-render --test it -- --ignored mnee::glass_area_efficiency --nocapture`
#[test]
#[ignore]
fn glass_area_efficiency() {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../bench/compare/scenes/glass-area.gltf"
    );
    let scene = tessera_scene::load(path).expect("run bench/compare/make_scenes.py first");
    let (w, h) = (256, 256);
    let rs = RenderScene::build(&scene, w, h).unwrap();
    let plan = FramePlan::new(w, h, 32, 16, 4).unwrap();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .unwrap();
    let pairs: u64 = std::env::var("MNEE_PAIRS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(4);
    for mnee in [false, true] {
        let mut noise = Vec::new();
        let mut cpu = 0.0;
        for pair in 0..pairs {
            let mut images = Vec::new();
            for seed in [2 * pair + 1, 2 * pair + 2] {
                let s = RenderConfig {
                    max_depth: 16,
                    ..settings(seed, 16)
                };
                let c0 = cpu_seconds();
                let image = pool.install(|| frame(&rs, &s, &plan, mnee));
                cpu += cpu_seconds() - c0;
                images.push(image);
            }
            let mut sum = 0.0;
            let mut n = 0;
            // The noise in the caustic under the ball (rows 150-165, columns 108-147:
            // docs/benchmarks.md, "the glass ball with 16 seeds") and in the 700 worst
            // pixels.
            let (mut caustic, mut per_pixel) = (0.0, Vec::new());
            for (i, (a, b)) in images[0].iter().zip(&images[1]).enumerate() {
                // Pixels that see the light directly (far brighter than anything lit).
                if a.max(*b) > 100.0 {
                    continue;
                }
                let v = (a - b).powi(2) / 2.0;
                let (x, y) = (i as u32 % w, i as u32 / w);
                if (150..=165).contains(&y) && (108..=147).contains(&x) {
                    caustic += v;
                }
                per_pixel.push(v);
                sum += v;
                n += 1;
            }
            per_pixel.sort_by(|a, b| b.total_cmp(a));
            let worst: f64 = per_pixel[..700].iter().sum();
            eprintln!(
                "  pair {pair}: noise {:.4e}, {:.1}% of it in the caustic, {:.1}% in the 700 worst pixels",
                sum / n as f64,
                100.0 * caustic / sum,
                100.0 * worst / sum
            );
            noise.push(sum / n as f64);
        }
        let k = noise.len() as f64;
        let mean = noise.iter().sum::<f64>() / k;
        let sd = (noise.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (k - 1.0)).sqrt();
        let cpu = cpu / (2.0 * k);
        eprintln!(
            "glass-area {}: noise variance {mean:.5e} ± {:.0}% ({} pairs), {cpu:.2} CPU s per render, \
             efficiency 1/(var s) {:.3}",
            if mnee { "path+MNEE" } else { "path" },
            100.0 * sd / k.sqrt() / mean,
            k,
            1.0 / (mean * cpu)
        );
    }
}

/// The luminance image of one render.
fn frame(rs: &RenderScene, s: &RenderConfig, plan: &FramePlan, mnee: bool) -> Vec<f64> {
    let w = plan.width;
    let mut image = vec![0.0f64; (w * plan.height) as usize];
    let results: Vec<_> = plan
        .units(0, plan.passes)
        .par_iter()
        .map(|u| {
            let r = unit(rs, s, plan, *u, mnee);
            (*u, r)
        })
        .collect();
    for (u, r) in results {
        let rect = plan.tile(u.tile);
        let n = (rect.width * rect.height) as usize;
        for (i, m) in r.pass_means.iter().enumerate() {
            let (x, y) = ((i % n) as u32 % rect.width, (i % n) as u32 / rect.width);
            let l = 0.2126 * m[0] as f64 + 0.7152 * m[1] as f64 + 0.0722 * m[2] as f64;
            image[((rect.y0 + y) * w + rect.x0 + x) as usize] += l / plan.passes as f64;
        }
    }
    image
}

/// The SDS pool goal (docs/benchmarks.md, "The SDS pool in one minute") with path tracing
/// plus MNEE: 256 x 256, depth 3, seed 11, `TESSERA_POOL_PASSES` passes (default 4) of 1
/// sample, 2 threads; the RMS over the pixels of the relative error against the closed
/// form (box-filtered per pixel), the reported image estimate and the CPU seconds. A
/// measurement, run by hand:
/// `cargo test -p tessera-render --test it -- --ignored mnee::pool_goal --nocapture`
#[test]
#[ignore]
fn pool_goal() {
    let passes = std::env::var("TESSERA_POOL_PASSES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(4);
    let (w, h) = (256, 256);
    let rs = RenderScene::build(&pool(), w, h).unwrap();
    let exact = expected_blocks(&rs, w, h, 1, floor_irradiance);
    let plan = FramePlan::new(w, h, 32, 1, passes).unwrap();
    let s = settings(11, 3);
    let threads = rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .unwrap();
    let c0 = cpu_seconds();
    let results: Vec<_> = threads.install(|| {
        plan.units(0, passes)
            .par_iter()
            .map(|u| render_unit_path_mnee(&rs, &s, &plan, *u))
            .collect()
    });
    let cpu = cpu_seconds() - c0;
    let (measured, estimate, offset) = pool_errors(plan, results, &exact);
    eprintln!(
        "pool, path+MNEE, {passes} passes of 1 spp: {cpu:.2} CPU s, measured {measured:.4}, \
         estimate {estimate:?}, image mean vs closed form {:+.3}%",
        100.0 * offset
    );
}

/// Path tracing with MNEE keeps the determinism contract: the same bits whatever the
/// tile size (so whatever the unit split and thread count, each pixel's samples being a
/// pure function of the seed, pixel and pass).
#[test]
fn path_with_mnee_is_deterministic_across_unit_splits() {
    let (w, h) = (24, 24);
    let rs = RenderScene::build(&glass_ball(), w, h).unwrap();
    let s = settings(5, 8);
    let image = |tile: u32| {
        let plan = FramePlan::new(w, h, tile, 4, 2).unwrap();
        let mut acc = tessera_farm::FrameAccumulator::new(plan);
        let results: Vec<_> = plan
            .units(0, 1)
            .par_iter()
            .map(|u| render_unit_path_mnee(&rs, &s, &plan, *u))
            .collect();
        for r in results {
            acc.offer(r).unwrap();
        }
        acc.image().mean
    };
    let (a, b) = (image(24), image(8));
    assert!(a.iter().any(|p| p[0] > 0.0));
    assert!(a
        .iter()
        .zip(&b)
        .all(|(p, q)| p.map(f32::to_bits) == q.map(f32::to_bits)));
}
