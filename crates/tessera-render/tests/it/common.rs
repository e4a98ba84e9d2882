//! Helpers shared by the rendering tests: render a scene through the real plan, unit
//! renderer and canonical merge, and summarise pixel statistics.
#![allow(dead_code)]

use rayon::prelude::*;
use tessera_farm::{FrameAccumulator, FramePlan};
use tessera_render::render::{render_frame, render_unit, RenderConfig};
use tessera_render::scene::RenderScene;
use tessera_scene::Scene;

/// A small deterministic generator (a 64-bit LCG with Knuth's MMIX constants) for test
/// rays and placements: the same stream on every run.
pub struct Rng(pub u64);

impl Rng {
    /// The next value in [0, 1), from the top 24 bits. (Not an `Iterator`: the stream is
    /// endless and callers want a plain `f32`.)
    #[allow(clippy::should_implement_trait)]
    pub fn next(&mut self) -> f32 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((self.0 >> 40) as f32) / (1u64 << 24) as f32
    }

    /// A direction uniform on the unit sphere.
    pub fn dir(&mut self) -> glam::Vec3 {
        let z = 2.0 * self.next() - 1.0;
        let phi = std::f32::consts::TAU * self.next();
        let r = (1.0 - z * z).max(0.0).sqrt();
        glam::Vec3::new(r * phi.cos(), r * phi.sin(), z)
    }
}

/// Renders `scene` at `w` x `h`, `spp` samples per pixel, on all cores.
pub fn render(
    scene: &Scene,
    w: u32,
    h: u32,
    spp: u32,
    settings: &RenderConfig,
) -> FrameAccumulator {
    let rs = RenderScene::build(scene, w, h).unwrap();
    let plan = FramePlan::for_spp(w, h, spp, 16).unwrap();
    render_frame(&rs, settings, &plan, 0, 0, |_, _| {})
}

/// Mean of one channel over all pixels, and its standard error from the per-pixel
/// variances of the mean (pixels are independent estimates).
pub fn image_mean(acc: &FrameAccumulator, channel: usize) -> (f64, f64) {
    let img = acc.image();
    let n = img.mean.len() as f64;
    let mean = img.mean.iter().map(|p| p[channel] as f64).sum::<f64>() / n;
    let var = img
        .variance_of_mean
        .iter()
        .map(|v| v[channel] as f64)
        .sum::<f64>()
        / (n * n);
    (mean, var.sqrt())
}

/// Luminance of the per-pass means of `block x block` pixel blocks: `[pass][block]`.
pub fn block_passes(
    rs: &RenderScene,
    s: &RenderConfig,
    plan: &FramePlan,
    block: u32,
) -> Vec<Vec<f64>> {
    let units = plan.units(0, 1);
    let (bx, by) = (plan.width.div_ceil(block), plan.height.div_ceil(block));
    let mut per_pass: Vec<(u32, Vec<f64>)> = units
        .par_iter()
        .map(|u| {
            let r = render_unit(rs, s, plan, *u);
            let rect = plan.tile(u.tile);
            let mut sums = vec![0.0f64; (bx * by) as usize];
            let mut counts = vec![0u32; (bx * by) as usize];
            for y in 0..rect.height {
                for x in 0..rect.width {
                    let m = r.pass_means[(y * rect.width + x) as usize];
                    let (gx, gy) = (rect.x0 + x, rect.y0 + y);
                    let b = ((gy / block) * bx + gx / block) as usize;
                    sums[b] += 0.2126 * m[0] as f64 + 0.7152 * m[1] as f64 + 0.0722 * m[2] as f64;
                    counts[b] += 1;
                }
            }
            (u.first_pass * 1_000_000 + u.tile, {
                sums.iter()
                    .zip(&counts)
                    .map(|(s, &c)| s / c as f64)
                    .collect()
            })
        })
        .collect();
    assert_eq!(plan.tile_count(), 1, "block_passes wants one tile per pass");
    per_pass.sort_by_key(|p| p.0);
    per_pass.into_iter().map(|p| p.1).collect()
}

/// Mean and variance of the mean of each block across passes.
pub fn block_stats(passes: &[Vec<f64>]) -> Vec<(f64, f64)> {
    let k = passes.len() as f64;
    (0..passes[0].len())
        .map(|b| {
            let mean = passes.iter().map(|p| p[b]).sum::<f64>() / k;
            let var = passes.iter().map(|p| (p[b] - mean).powi(2)).sum::<f64>() / (k - 1.0);
            (mean, var / k)
        })
        .collect()
}

/// `1 - Φ(z)` (complementary error function of Numerical Recipes §6.2, relative error
/// below 1.2e-7).
pub fn normal_sf(z: f64) -> f64 {
    let x = z / std::f64::consts::SQRT_2;
    let t = 1.0 / (1.0 + 0.5 * x.abs());
    // Horner's rule over the coefficients, highest power first. (Written as a loop: the
    // nested expression made rustfmt take seconds per file that includes this module.)
    const C: [f64; 10] = [
        0.17087277,
        -0.82215223,
        1.48851587,
        -1.13520398,
        0.27886807,
        -0.18628806,
        0.09678418,
        0.37409196,
        1.00002368,
        -1.26551223,
    ];
    let poly = C.iter().fold(0.0, |acc, c| acc * t + c);
    let y = t * (-x * x + poly).exp();
    let erfc = if x >= 0.0 { y } else { 2.0 - y };
    0.5 * erfc
}

/// Two-sided critical |z| for `tests` comparisons at family-wise level `alpha` (Bonferroni).
pub fn z_critical(alpha: f64, tests: usize) -> f64 {
    let target = alpha / (2.0 * tests as f64);
    let (mut lo, mut hi) = (0.0f64, 40.0f64);
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if normal_sf(mid) > target {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    0.5 * (lo + hi)
}

/// z-tests of two block images; returns the largest |z| after asserting it is below the
/// Bonferroni threshold. Blocks where both estimates are exactly zero are skipped.
pub fn assert_blocks_agree(name: &str, a: &[(f64, f64)], b: &[(f64, f64)]) -> f64 {
    let tested: Vec<usize> = (0..a.len()).filter(|&i| a[i].1 + b[i].1 > 0.0).collect();
    let crit = z_critical(0.01, tested.len());
    let mut worst = 0.0f64;
    let mut sum_z2 = 0.0;
    for &i in &tested {
        let z = (a[i].0 - b[i].0) / (a[i].1 + b[i].1).sqrt();
        sum_z2 += z * z;
        worst = worst.max(z.abs());
        assert!(
            z.abs() < crit,
            "{name}: block {i}: {:.5} ± {:.5} vs {:.5} ± {:.5}, z = {z:.2} (critical {crit:.2})",
            a[i].0,
            a[i].1.sqrt(),
            b[i].0,
            b[i].1.sqrt()
        );
    }
    eprintln!(
        "{name}: {} blocks, max |z| = {worst:.2} (critical {crit:.2}), mean z² = {:.2}",
        tested.len(),
        sum_z2 / tested.len().max(1) as f64
    );
    worst
}

/// Per-region means (4x4 grid, then the whole image) of `value(x, y) = (mean, variance
/// of the mean)` over the pixels whose mean is not NaN (masked out), with the standard
/// error of the region mean; a region without pixels is NaN.
pub fn regions(w: usize, h: usize, value: impl Fn(usize, usize) -> (f64, f64)) -> Vec<(f64, f64)> {
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
            let (mut sum, mut var, mut n) = (0.0, 0.0, 0usize);
            for y in y0..y1 {
                for x in x0..x1 {
                    let (m, v) = value(x, y);
                    if !m.is_nan() {
                        sum += m;
                        var += v;
                        n += 1;
                    }
                }
            }
            let n = n as f64;
            out.push((sum / n, var.sqrt() / n));
        }
    }
    out
}

/// The path tracer as the Blender-reference tests run it: seed 11, 64 bounces, Russian
/// roulette from depth 5 (Cycles' references use 64 bounces and unbiased roulette).
pub fn reference_config() -> RenderConfig {
    RenderConfig {
        integrator: tessera_render::integrator::Integrator::Path,
        seed: 11,
        max_depth: 64,
        rr_depth: 5,
        ..RenderConfig::default()
    }
}

/// Every bit of a frame's result, pixel by pixel: the mean, the variance of the mean and
/// the pass count. Two renders are the same render when these are equal.
pub fn frame_bits(acc: &FrameAccumulator) -> Vec<u32> {
    let img = acc.image();
    let mut out = Vec::new();
    for i in 0..img.mean.len() {
        out.extend(img.mean[i].map(f32::to_bits));
        out.extend(img.variance_of_mean[i].map(f32::to_bits));
        out.push(img.passes[i]);
        if let Some(b) = &img.bias {
            out.extend(b[i].map(f32::to_bits));
        }
    }
    out
}
