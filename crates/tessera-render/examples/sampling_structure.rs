//! How a pixel's samples are grouped into replicates, measured: the noise variance of the
//! pixel mean and the calibration of its error estimate, for each candidate structure
//! (the table is in `docs/benchmarks.md`, "Sampling structure").
//!
//! ```text
//! cargo run --release -p tessera-render --example sampling_structure [-- SIZE REF_SPP]
//! ```
//!
//! Scene `builtin:cornell-box` at SIZE x SIZE (default 64), path tracer, default depth.
//! For every requested spp `N` in {64, 256, 1024} and every structure the frame is rendered
//! with two seeds, and:
//!
//! - **noise** is the variance of a pixel channel's mean, measured as `(m_1 - m_2)^2 / 2`
//!   over the two seeds and averaged over pixel channels, reported relative to the
//!   independent sampler (lower is better). Channels whose passes are all identical in
//!   both renders (the light seen directly) are left out.
//! - **rel noise** is the same for the luminance in relative units, `(l_1 - l_2)^2 / 2 /
//!   (l_ref + REL_EPS)^2` averaged over pixels (the square of ARCHITECTURE.md §3's `rel`),
//!   which the bright pixels on the edge of the light do not dominate; **rel est/noise**
//!   likewise.
//! - **est/noise** is the mean estimated variance of the mean divided by that measured
//!   variance (1 = unbiased variance estimate).
//! - **cover** is the fraction of pixel channels within 2 estimated standard errors of a
//!   converged reference (`z = (m - r) / sqrt(v + v_r)`), beside the fraction Student's t
//!   with `K - 1` degrees of freedom predicts (**t(K-1)**), and **cover3x3**, the same
//!   with each channel's variance replaced by the mean over its 3x3 neighbourhood (pooling).
//! - **img est/meas** is the estimated image error (RMS relative error, ARCHITECTURE.md §3)
//!   over the measured one against the reference, as in `tests/calibration.rs`.
//!
//! Structures (each pass's randomization is seeded by `hash(seed, frame, pixel, pass)`
//! through [`PixelSampler::new`]):
//!
//! - `indep SxK`: independent uniform numbers, `K` passes of `S` samples.
//! - `sobol SxK`: `K` independently Owen-scrambled Sobol' sets of `S` points (Owen 2001,
//!   section 6.7: independent randomized QMC replicates). This is option (a) for `S`
//!   larger than the current plan's.
//! - `blocks SxK`: option (b), one scrambled sequence per pixel (pass seed 0), pass `k`
//!   drawing sample indices `kS .. (k+1)S`; with Burley's (2020) index shuffle every such
//!   block is an aligned block of the sequence, so the union of all passes is one
//!   `(0, log2 N, 2)`-net. The error is estimated with the plain between-pass formula.
//!
//! Option (c), `R` independent scrambles each rendered as several consecutive blocks,
//! draws exactly the samples of `sobol (N/R)xR` (the union of a replicate's blocks is its
//! first `N/R` shuffled indices), so its numbers are that row's.

use rayon::prelude::*;
use std::time::Instant;
use tessera_farm::{luminance, REL_EPS};
use tessera_render::integrator::path::{radiance, PathSettings};
use tessera_render::integrator::RenderConfig;
use tessera_render::sampling::{PixelSampler, SamplerKind};
use tessera_render::scene::RenderScene;

/// One candidate structure: `k` units of `s` samples each.
#[derive(Clone, Copy)]
struct Layout {
    kind: SamplerKind,
    s: u32,
    k: u32,
    /// Units are consecutive blocks of one scrambled sequence instead of independent sets.
    one_sequence: bool,
}

impl Layout {
    fn name(&self) -> String {
        let what = match (self.kind, self.one_sequence) {
            (SamplerKind::Independent, _) => "indep",
            (SamplerKind::Sobol, false) => "sobol",
            (SamplerKind::Sobol, true) => "blocks",
        };
        format!("{what} {}x{}", self.s, self.k)
    }
}

/// Per pixel (row-major), the `k` unit means of `layout`, as `[r, g, b]`.
fn render(rs: &RenderScene, size: u32, seed: u64, layout: Layout) -> Vec<Vec<[f64; 3]>> {
    let d = RenderConfig::default();
    let path = PathSettings {
        mis: d.mis,
        max_depth: d.max_depth,
        rr_depth: d.rr_depth,
    };
    (0..size * size)
        .into_par_iter()
        .map(|pixel| {
            let (x, y) = (pixel % size, pixel / size);
            (0..layout.k)
                .map(|unit| {
                    let (pass, first) = if layout.one_sequence {
                        (0, unit * layout.s)
                    } else {
                        (unit, 0)
                    };
                    let mut sampler = PixelSampler::new(layout.kind, seed, 0, pixel, pass);
                    let mut sum = [0.0f64; 3];
                    for i in 0..layout.s {
                        sampler.start_sample(first + i);
                        let film = glam::Vec2::new(x as f32, y as f32) + sampler.next_2d();
                        let (o, dir) = rs.camera.generate_ray(film, glam::Vec2::ZERO);
                        let l = radiance(rs, &path, o, dir, 0.0, &mut sampler);
                        if l.is_finite() && l.min_element() >= 0.0 {
                            sum[0] += f64::from(l.x);
                            sum[1] += f64::from(l.y);
                            sum[2] += f64::from(l.z);
                        }
                    }
                    sum.map(|v| v / f64::from(layout.s))
                })
                .collect()
        })
        .collect()
}

/// A pixel's mean, the estimated variance of the mean per channel and of the luminance.
struct Pixel {
    mean: [f64; 3],
    var: [f64; 3],
    lum_var: f64,
}

/// Between-unit estimate: `Var[mean] = sum (m_k - mean)^2 / (K (K - 1))` (Owen 2001, 6.7).
fn stats(units: &[[f64; 3]]) -> Pixel {
    let k = units.len() as f64;
    let mut mean = [0.0; 3];
    for u in units {
        for c in 0..3 {
            mean[c] += u[c] / k;
        }
    }
    let lum_mean = luminance(mean);
    let (mut var, mut lum_var) = ([0.0; 3], 0.0);
    if units.len() > 1 {
        for u in units {
            for c in 0..3 {
                var[c] += (u[c] - mean[c]).powi(2) / (k * (k - 1.0));
            }
            lum_var += (luminance(*u) - lum_mean).powi(2) / (k * (k - 1.0));
        }
    }
    Pixel { mean, var, lum_var }
}

/// P(|T| <= 2) for Student's t with `nu` degrees of freedom: with `t = sqrt(nu) tan(a)` the
/// density becomes proportional to `cos(a)^(nu - 1)`, integrated here by Simpson's rule.
fn t_within_2(nu: f64) -> f64 {
    let integral = |b: f64| {
        let n = 20_000;
        let h = b / n as f64;
        let f = |a: f64| a.cos().powf(nu - 1.0);
        let mut s = f(0.0) + f(b);
        for i in 1..n {
            s += f(i as f64 * h) * if i % 2 == 1 { 4.0 } else { 2.0 };
        }
        s * h / 3.0
    };
    integral((2.0 / nu.sqrt()).atan()) / integral(std::f64::consts::FRAC_PI_2)
}

fn main() {
    let args: Vec<u32> = std::env::args()
        .skip(1)
        .map(|a| a.parse().expect("SIZE and REF_SPP are integers"))
        .collect();
    let size = args.first().copied().unwrap_or(64);
    let ref_spp = args.get(1).copied().unwrap_or(16384);
    let scene = tessera_scene::load("builtin:cornell-box").unwrap();
    let rs = RenderScene::build(&scene, size, size).unwrap();
    assert!(!rs.camera.has_lens(), "the loop above draws no lens sample");
    let t0 = Instant::now();
    let reference: Vec<Pixel> = render(
        &rs,
        size,
        1000,
        Layout {
            kind: SamplerKind::Sobol,
            s: 16,
            k: ref_spp / 16,
            one_sequence: false,
        },
    )
    .iter()
    .map(|u| stats(u))
    .collect();
    eprintln!(
        "reference {size}x{size} at {ref_spp} spp: {:.0} s",
        t0.elapsed().as_secs_f64()
    );
    println!("| spp | structure | noise vs indep | est/noise | rel noise vs indep | rel est/noise | cover | t(K-1) | cover3x3 | img est/meas |");
    println!("|---|---|---|---|---|---|---|---|---|---|");
    for n in [64u32, 256, 1024] {
        let current = tessera_farm::FramePlan::for_spp(size, size, n, 8).unwrap();
        let (s0, k0) = (current.samples_per_pass, current.passes);
        let mut layouts = vec![
            Layout {
                kind: SamplerKind::Independent,
                s: s0,
                k: k0,
                one_sequence: false,
            },
            Layout {
                kind: SamplerKind::Sobol,
                s: s0,
                k: k0,
                one_sequence: false,
            },
        ];
        for k in [16u32, 8, 4, 2] {
            if k < k0 {
                layouts.push(Layout {
                    kind: SamplerKind::Sobol,
                    s: n / k,
                    k,
                    one_sequence: false,
                });
            }
        }
        layouts.push(Layout {
            kind: SamplerKind::Sobol,
            s: s0,
            k: k0,
            one_sequence: true,
        });
        let mut indep_noise = None;
        for layout in layouts {
            let t = Instant::now();
            let runs: Vec<Vec<Pixel>> = [1u64, 2]
                .iter()
                .map(|&seed| {
                    render(&rs, size, seed, layout)
                        .iter()
                        .map(|u| stats(u))
                        .collect()
                })
                .collect();
            let (mut noise, mut est, mut counted) = (0.0, 0.0, 0usize);
            // The same in relative luminance units (ARCHITECTURE.md §3's `rel`, squared), so
            // bright pixels (the edge of the light) do not dominate the average.
            let (mut rel_noise, mut rel_est, mut rel_counted) = (0.0, 0.0, 0usize);
            for p in 0..runs[0].len() {
                let (a, b) = (&runs[0][p], &runs[1][p]);
                if a.lum_var == 0.0 && b.lum_var == 0.0 {
                    continue;
                }
                let scale = (luminance(reference[p].mean) + REL_EPS).powi(2);
                rel_counted += 1;
                rel_noise += (luminance(a.mean) - luminance(b.mean)).powi(2) / 2.0 / scale;
                rel_est += (a.lum_var + b.lum_var) / 2.0 / scale;
            }
            rel_noise /= rel_counted as f64;
            rel_est /= rel_counted as f64;
            let (mut inside, mut inside_pooled, mut zs) = (0usize, 0usize, 0usize);
            let mut img_ratio = 0.0;
            for (a, b) in runs[0].iter().zip(&runs[1]) {
                for c in 0..3 {
                    if a.var[c] == 0.0 && b.var[c] == 0.0 {
                        continue;
                    }
                    counted += 1;
                    noise += (a.mean[c] - b.mean[c]).powi(2) / 2.0;
                    est += (a.var[c] + b.var[c]) / 2.0;
                }
            }
            for run in &runs {
                for p in 0..run.len() {
                    let (x, y) = ((p as u32 % size) as i64, (p as u32 / size) as i64);
                    for c in 0..3 {
                        let r = &reference[p];
                        let v = run[p].var[c] + r.var[c];
                        if v == 0.0 {
                            continue;
                        }
                        let d = run[p].mean[c] - r.mean[c];
                        zs += 1;
                        inside += usize::from(d.abs() <= 2.0 * v.sqrt());
                        let (mut pooled, mut m) = (0.0, 0.0);
                        for dy in -1..=1i64 {
                            for dx in -1..=1i64 {
                                let (qx, qy) = (x + dx, y + dy);
                                if qx >= 0 && qy >= 0 && qx < size as i64 && qy < size as i64 {
                                    pooled += run[(qy * size as i64 + qx) as usize].var[c];
                                    m += 1.0;
                                }
                            }
                        }
                        let vp = pooled / m + r.var[c];
                        inside_pooled += usize::from(d.abs() <= 2.0 * vp.sqrt());
                    }
                }
                // Image error, estimated and measured (tests/calibration.rs).
                let np = run.len() as f64;
                let (mut e2, mut m2) = (0.0, 0.0);
                for (q, r) in run.iter().zip(&reference) {
                    e2 += q.lum_var / (luminance(q.mean) + REL_EPS).powi(2);
                    let d = luminance(q.mean) - luminance(r.mean);
                    m2 += (d * d - r.lum_var) / (luminance(r.mean) + REL_EPS).powi(2);
                }
                img_ratio += (e2 / np).sqrt() / (m2 / np).max(0.0).sqrt() / 2.0;
            }
            noise /= counted as f64;
            est /= counted as f64;
            let (base, rel_base) = *indep_noise.get_or_insert((noise, rel_noise));
            println!(
                "| {n} | {} | {:.3} | {:.3} | {:.3} | {:.3} | {:.1}% | {:.1}% | {:.1}% | {:.3} |",
                layout.name(),
                noise / base,
                est / noise,
                rel_noise / rel_base,
                rel_est / rel_noise,
                100.0 * inside as f64 / zs as f64,
                100.0 * t_within_2(f64::from(layout.k - 1)),
                100.0 * inside_pooled as f64 / zs as f64,
                img_ratio,
            );
            eprintln!("  ({:.0} s)", t.elapsed().as_secs_f64());
        }
    }
}
