//! Per-pixel running statistics over passes (ARCHITECTURE.md §3).

use serde::{Deserialize, Serialize};

/// Radiance floor in the denominator of the relative error,
/// `rel = sqrt(Var[lum(mean)]) / (lum(mean) + REL_EPS)`.
///
/// Without it a black or nearly black pixel would have an infinite or huge relative error
/// from a tiny absolute one and would dominate the image error and any adaptive decision.
/// With it, pixels much darker than `REL_EPS` (1% of white, in linear radiance) are judged by
/// their absolute error divided by `REL_EPS`, and pixels much brighter by their true relative
/// error.
pub const REL_EPS: f64 = 1e-2;

/// The error estimator of uniform and sequential renders ([`ErrorEstimator::Robust`]), as
/// the EXR header (`error_estimator`), the job status and `tessera render` name it
/// (ARCHITECTURE.md §3): the image error is the RMS of the pixels'
/// relative errors from the spread of their independent passes, each divided by a robust
/// scale ([`robust_scale`]: the pixel's mean, allowed down to the level of its neighbours,
/// [`neighbours_level`], but never below the mean minus one standard error); a pixel's
/// interval uses the variance pooled over its 3x3 neighbourhood
/// ([`crate::FrameImage::interval_variance`]). Still optimistic where no pass has caught
/// the rare paths that carry the error (path-traced caustics of small lights):
/// `docs/benchmarks.md`, "Calibration suite".
///
/// Renamed when the level changed from the 3x3 mean with the pixel to the neighbours'
/// level (`docs/benchmarks.md`, "Sampling structure", 2026-12-06 evening): frames written
/// before name their estimate `pass-spread, robust scale; pixel intervals pooled 3x3`.
/// Nothing parses the name, so those frames read as before; the name says which level
/// their estimate was computed with.
pub const ERROR_ESTIMATOR: &str =
    "pass-spread, robust scale at the neighbours' level; pixel intervals pooled 3x3";

/// The error estimator of unbiased adaptive renders ([`ErrorEstimator::PooledPerPass`]),
/// named as [`ERROR_ESTIMATOR`] is (and renamed with it: frames written before name it
/// `pass-spread, robust scale, per-pass variance pooled 3x3; pixel intervals pooled 3x3`).
pub const ERROR_ESTIMATOR_POOLED: &str = "pass-spread, robust scale at the neighbours' level, per-pass variance pooled 3x3; pixel intervals pooled 3x3";

/// Which image error estimate a render reports (ARCHITECTURE.md §3).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ErrorEstimator {
    /// [`image_relative_error`]: each pixel's own pass spread over its robust scale.
    /// Uniform and sequential renders.
    Robust,
    /// [`image_relative_error_pooled`]: each pixel's per-pass relative variance pooled
    /// over its 3x3 neighbourhood, over its own pass count. Unbiased adaptive renders,
    /// whose pass counts follow a pilot that missed rare paths where the error is.
    PooledPerPass,
}

impl ErrorEstimator {
    /// The estimator of a render with adaptive mode `mode`.
    pub fn for_mode(mode: crate::job::AdaptiveMode) -> Self {
        match mode {
            crate::job::AdaptiveMode::Unbiased => Self::PooledPerPass,
            crate::job::AdaptiveMode::Off | crate::job::AdaptiveMode::Sequential => Self::Robust,
        }
    }

    /// The name in the EXR header (`error_estimator`), the job status and `tessera render`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Robust => ERROR_ESTIMATOR,
            Self::PooledPerPass => ERROR_ESTIMATOR_POOLED,
        }
    }

    /// This estimate of a `width` x `height` image: [`image_relative_error`] or
    /// [`image_relative_error_pooled`], where `pixel(x, y)` gives a pixel's mean
    /// luminance, the estimated variance of that mean and its passes, or `None` for a pixel
    /// with fewer than 2 passes (the plain estimate ignores the passes).
    pub fn image_error(
        self,
        width: usize,
        height: usize,
        pixel: impl Fn(usize, usize) -> Option<(f64, f64, u32)>,
    ) -> f64 {
        match self {
            Self::Robust => {
                image_relative_error(width, height, |x, y| pixel(x, y).map(|(m, v, _)| (m, v)))
            }
            Self::PooledPerPass => image_relative_error_pooled(width, height, pixel),
        }
    }

    /// This estimate of a biased render (vcm, ppm: one with bias layers) with the
    /// merging bias term added: [`image_relative_error_biased`] for
    /// [`ErrorEstimator::Robust`], [`image_relative_error_pooled_biased`] for
    /// [`ErrorEstimator::PooledPerPass`]. `pixel(x, y)` gives a pixel's mean luminance
    /// `m`, the estimated variance of that mean `v`, its passes `k`, the mean of its passes'
    /// bias estimates `b` and that mean's estimated variance `v_b`, or `None` for a pixel
    /// with fewer than 2 passes.
    pub fn image_error_biased(
        self,
        width: usize,
        height: usize,
        pixel: impl Fn(usize, usize) -> Option<(f64, f64, u32, f64, f64)>,
    ) -> f64 {
        match self {
            Self::Robust => image_relative_error_biased(width, height, |x, y| {
                pixel(x, y).map(|(m, v, _, b, vb)| (m, v, b, vb))
            }),
            Self::PooledPerPass => image_relative_error_pooled_biased(width, height, pixel),
        }
    }
}

/// The luminance scale a pixel's standard error is divided by in the image error
/// estimate: `max(m - se, min(m, level))`, clamped at 0, plus [`REL_EPS`], where `m` is the
/// pixel's mean luminance, `se` its estimated standard error and `level` the local image
/// level around it: [`neighbours_level`] in the library's estimates.
///
/// Why not `m` alone (the pixel's own `rel`): with heavy-tailed radiance (a glossy
/// caustic, a small light in a glossy floor) a pass that catches a rare bright path raises
/// the mean and the spread together, so `se / m` stays below 1 however far the mean is
/// from the truth, and the image estimate was 0.5-0.85 of the measured error
/// (`docs/benchmarks.md`, "Calibration suite"). Such a pixel is brighter than its
/// neighbourhood, so its scale falls towards the level, an estimate of its expected value
/// from eight times the passes. A pixel that is genuinely brighter than its neighbours
/// (a highlight, an emitter's edge) has consistent passes and a small `se`, and the floor
/// `m - se` keeps its scale close to `m`: by Samuelson's inequality (Samuelson 1968) the
/// largest of `K` passes is at most `m + s (K - 1) / sqrt(K)`, so `m - se` is a lower
/// bound of the mean of the other `K - 1` passes, exact when one pass alone departs from
/// the rest. Darker pixels than their neighbourhood keep `m`.
#[inline]
pub fn robust_scale(mean_lum: f64, lum_variance_of_mean: f64, level: f64) -> f64 {
    let m = mean_lum.max(0.0);
    let floor = m - lum_variance_of_mean.max(0.0).sqrt();
    floor.max(m.min(level)).max(0.0) + REL_EPS
}

/// The image relative error estimate (ARCHITECTURE.md §3): the root mean square over the
/// pixels with an estimate of `sqrt(v) / robust_scale(m, v, level)`, where `pixel(x, y)`
/// gives, for pixel `(x, y)` of a `width` x `height` frame, its mean luminance `m` and
/// estimated variance of that mean `v`, or `None` for a pixel with fewer than 2 passes.
/// The `level` is [`neighbours_level`], over the neighbours that have an estimate. 0 when
/// no pixel has one; never NaN.
///
/// It is a function of the merged statistics alone, so every renderer of a frame (local,
/// farm, restored from checkpoints) gets the same number from the same passes. The
/// statistics are read where they are (tiles, image layers) rather than copied into a
/// frame-sized buffer: the coordinator calls this for its status and history, and a
/// 16384x16384 frame's copy would be 6 GiB beside the budgeted merge state.
pub fn image_relative_error(
    width: usize,
    height: usize,
    pixel: impl Fn(usize, usize) -> Option<(f64, f64)>,
) -> f64 {
    let (mut sum, mut count) = (0.0f64, 0u64);
    for y in 0..height {
        for x in 0..width {
            let Some((m, v)) = pixel(x, y) else {
                continue;
            };
            sum += robust_relative_variance(width, height, x, y, m, v, |qx, qy| {
                pixel(qx, qy).map(|q| q.0)
            });
            count += 1;
        }
    }
    root_mean(sum, count)
}

/// The image relative error estimate of an unbiased adaptive render (ARCHITECTURE.md §3,
/// [`ErrorEstimator::PooledPerPass`]): the root mean square over the pixels with an
/// estimate of `sqrt(q_3x3 / k)`, where `k` is the pixel's pass count and `q_3x3` the mean
/// over its 3x3 neighbourhood (the neighbours with an estimate, the pixel included) of the
/// per-pass relative variance `q = k v / robust_scale(m, v, level)²` ([`neighbours_level`]). `pixel(x, y)` gives
/// the mean luminance `m`, the estimated variance of that mean `v` and the passes `k`, or
/// `None` for a pixel with fewer than 2 passes. 0 when no pixel has an estimate; never NaN.
///
/// Why: in Kirk & Arvo's two-stage scheme a pixel's fresh pass count follows its pilot,
/// and a pixel whose pilot missed the rare bright paths near it gets the fewest; its few
/// fresh passes mostly miss them too, so its own variance is low exactly where its error is
/// high, and the plain estimate was 0.59-0.71 of the measured error on path-traced
/// veach-mis (docs/benchmarks.md, "the error estimate under adaptive sampling"). Its neighbours'
/// per-pass variance is an estimate of its own that does not depend on its luck (the
/// pilot already pools it for the allocation, `pooled_pilot_variance`). With equal pass
/// counts the mean over pixels of `q_3x3 / k` is the mean of `v / scale²` up to the
/// image's border, so a uniform render would get the plain estimate back. Measured: 0.85-1.10
/// of the measured error on veach-mis at 64x64 and 128x128 (plain 0.60-0.77); it
/// overstates where a neighbourhood spans a sharp change of the variance (1.24-1.29 at
/// 32x32), and it cannot find rare paths the neighbours missed too (a small light's
/// highlight in a glossy floor: 0.61, plain 0.57).
pub fn image_relative_error_pooled(
    width: usize,
    height: usize,
    pixel: impl Fn(usize, usize) -> Option<(f64, f64, u32)>,
) -> f64 {
    // Rows y - 1, y and y + 1 of the per-pass relative variances, in a ring: each is
    // computed once, and nothing frame-sized is allocated.
    let mut rows: [Vec<Option<f64>>; 3] = Default::default();
    let per_pass_row = |y: usize, out: &mut Vec<Option<f64>>| {
        out.clear();
        out.extend((0..width).map(|x| {
            pixel(x, y).map(|(m, v, k)| {
                let q = robust_relative_variance(width, height, x, y, m, v, |qx, qy| {
                    pixel(qx, qy).map(|p| p.0)
                });
                q * f64::from(k)
            })
        }));
    };
    let (mut sum, mut count) = (0.0f64, 0u64);
    for y in 0..height {
        if y == 0 {
            per_pass_row(0, &mut rows[0]);
        }
        if y + 1 < height {
            per_pass_row(y + 1, &mut rows[(y + 1) % 3]);
        }
        for x in 0..width {
            let Some((_, _, k)) = pixel(x, y) else {
                continue;
            };
            let (mut qsum, mut n) = (0.0f64, 0u32);
            let columns = x.saturating_sub(1)..(x + 2).min(width);
            for qy in y.saturating_sub(1)..(y + 2).min(height) {
                for q in rows[qy % 3][columns.clone()].iter().flatten() {
                    qsum += q;
                    n += 1;
                }
            }
            // n >= 1: the pixel itself has an estimate.
            sum += qsum / f64::from(n) / f64::from(k.max(1));
            count += 1;
        }
    }
    root_mean(sum, count)
}

/// `(sqrt(v) / robust_scale(m, v, level))²` of pixel `(x, y)`, where `level` is
/// [`neighbours_level`] of `mean_at`.
fn robust_relative_variance(
    width: usize,
    height: usize,
    x: usize,
    y: usize,
    m: f64,
    v: f64,
    mean_at: impl Fn(usize, usize) -> Option<f64>,
) -> f64 {
    let level = neighbours_level(width, height, x, y, m, mean_at);
    // The square of `sqrt(v) / scale`, in that order: the estimate's bits stay those of
    // the relative error it always summed.
    let rel = v.max(0.0).sqrt() / robust_scale(m, v, level);
    rel * rel
}

/// The local image level the robust and bias scales ([`robust_scale`], [`bias_scale`])
/// compare the mean `m` of pixel `(x, y)` with: `max(m_8, m / 9)`, where `m_8` is the mean
/// of `mean_at` (clamped at 0) over the pixel's 8 neighbours that have one, the pixel
/// itself left out (0 when none has one), summed row by row.
///
/// Why the pixel is left out: a pixel whose pass caught a rare bright path would raise a
/// level that includes it by a ninth of its own catch, so the scale it is divided by
/// would grow with its own error and its relative error be understated; its neighbours'
/// passes are independent of its own, so `m_8` does not. With the 3x3 mean the image
/// estimate at 64 spp as 2 passes of 32 was 0.79 of the measured error on path-traced
/// veach-mis and 0.67 on the glossy floor (suite seeds 8-11; the glossy floor 0.69 as 4 x
/// 16 over 8 seeds); with this level 1.00 and 0.92, and every check of the calibration
/// suite holds at 2 passes (`docs/benchmarks.md`, "Sampling structure", 2026-12-06
/// evening). The floor `m / 9` is
/// what the 3x3 mean gave where every neighbour is black: the scale is never above the
/// one the 3x3 mean gave (so the estimate never lower), and a pixel's relative error never
/// more than 9 times its own `rel`.
pub fn neighbours_level(
    width: usize,
    height: usize,
    x: usize,
    y: usize,
    m: f64,
    mean_at: impl Fn(usize, usize) -> Option<f64>,
) -> f64 {
    let (mut sum, mut n) = (0.0f64, 0u32);
    for qy in y.saturating_sub(1)..(y + 2).min(height) {
        for qx in x.saturating_sub(1)..(x + 2).min(width) {
            if (qx, qy) == (x, y) {
                continue;
            }
            if let Some(q) = mean_at(qx, qy) {
                sum += q.max(0.0);
                n += 1;
            }
        }
    }
    let m_8 = sum / f64::from(n.max(1));
    m_8.max(m.max(0.0) / 9.0)
}

/// `sqrt(sum / count)`, 0 for no pixels or a non-finite result.
fn root_mean(sum: f64, count: u64) -> f64 {
    if count == 0 {
        return 0.0;
    }
    let e = (sum / count as f64).sqrt();
    if e.is_finite() {
        e
    } else {
        0.0
    }
}

/// The image error estimate `estimator` of a frame of `plan` held as tiles: `tile(t)` gives tile `t`'s
/// pixels' statistics, row-major within the tile ([`crate::FramePlan::get_tile`]). Pixels
/// with fewer than 2 passes have no estimate.
pub(crate) fn image_relative_error_of_tiles<'a>(
    plan: &crate::FramePlan,
    estimator: ErrorEstimator,
    tile: impl Fn(usize) -> Option<&'a [PixelStats]>,
) -> f64 {
    let (width, height) = (plan.width as usize, plan.height as usize);
    let edge = plan.tile_size.max(1) as usize;
    let tiles_x = plan.tiles_x() as usize;
    let stats = |x: usize, y: usize| {
        let (lx, ly) = (x % edge, y % edge);
        let tile_width = edge.min(width - (x - lx));
        let s = tile((y / edge) * tiles_x + x / edge)?.get(ly * tile_width + lx)?;
        (s.passes >= 2).then_some(s)
    };
    estimator.image_error(width, height, |x, y| {
        stats(x, y).map(|s| (s.mean_lum, s.lum_variance_of_mean(), s.passes))
    })
}

/// The coverage every per-pixel interval aims for, `P(|Z| <= 2) = 0.9545`: the normal
/// 2-sigma interval's, so that a pixel whose variance has many degrees of freedom keeps
/// `mean +- 2 sqrt(variance)` (ARCHITECTURE.md §3).
pub const INTERVAL_COVERAGE: f64 = 0.954_499_736_103_641_6;

/// Student's t quantiles `q` with `P(|T| <= q) =` [`INTERVAL_COVERAGE`] for 1 to 32 degrees
/// of freedom, computed to 40 digits with mpmath (the regularized incomplete beta
/// function, Abramowitz & Stegun 1964, 26.7.1) and rounded to f64.
const INTERVAL_QUANTILES: [f64; 32] = [
    13.967730199244548,
    4.526536687430165,
    3.306822175005652,
    2.869309414628827,
    2.648649430702703,
    2.5165240556531185,
    2.4288051304035685,
    2.3664157840419837,
    2.319805898259143,
    2.2836782024779305,
    2.2548626967799055,
    2.231348094024051,
    2.211797543352617,
    2.1952881909318083,
    2.1811626350751743,
    2.1689399911863836,
    2.158260432909182,
    2.1488493882329394,
    2.1404937230531993,
    2.1330254804541875,
    2.126310521380297,
    2.1202404265211148,
    2.1147266175578676,
    2.1096960195183114,
    2.1050878128603885,
    2.1008509688651746,
    2.0969423565481864,
    2.0933252722843507,
    2.0899682860171875,
    2.086844327310369,
    2.0839299550417882,
    2.0812047690983384,
];

/// The half-width, in estimated standard errors, of an interval covering
/// [`INTERVAL_COVERAGE`] under Student's t with `dof` degrees of freedom: 13.97 for 1,
/// 2.32 for 9, 2.10 for 27, towards 2 for many. `f64::INFINITY` for 0 (no estimate).
///
/// An exact table up to 32 degrees of freedom; beyond, the Cornish-Fisher expansion of the
/// t quantile in powers of `1 / dof` to the fourth (Abramowitz & Stegun 1964, 26.7.5) at
/// `z = 2`, whose coefficients are exact rationals: off by less than 3e-8 at 33 and
/// shrinking like `dof^-5`, below the f32 rounding of the layers it scales. Only `+`, `*`
/// and `/`, no library functions, so every machine computes the same bits (ARCHITECTURE.md
/// §2).
pub fn interval_quantile(dof: u64) -> f64 {
    match dof {
        0 => f64::INFINITY,
        d if d <= INTERVAL_QUANTILES.len() as u64 => INTERVAL_QUANTILES[d as usize - 1],
        d => {
            // A&S 26.7.5's g_1..g_4 at z = 2: 10/4, 294/96, 1098/384, 169950/92160.
            const G: [f64; 4] = [2.5, 3.0625, 2.859375, 169_950.0 / 92_160.0];
            let v = 1.0 / d as f64;
            2.0 + v * (G[0] + v * (G[1] + v * (G[2] + v * G[3])))
        }
    }
}

/// A pixel's interval variance from its 3x3 pool ([`crate::FrameImage::interval_variance`],
/// ARCHITECTURE.md §3): `sum` the per-pass variances weighted by their degrees of freedom,
/// `dof` their total, `own` the pixel's passes. The pooled variance of the mean
/// `sum / dof / own`, widened by `(q / 2)^2` for the t quantile `q` of `dof`
/// ([`interval_quantile`]) so that `mean +- 2 sqrt(interval variance)` covers
/// [`INTERVAL_COVERAGE`]. One function for the image and the streaming EXR writer, so both
/// give the same bits.
pub fn pooled_interval_variance(sum: [f64; 3], dof: f64, own: f64) -> [f32; 3] {
    // dof is a sum of whole pass counts minus one each, exact in f64.
    let half = 0.5 * interval_quantile(dof as u64);
    let widen = half * half;
    sum.map(|s| (s / dof / own * widen) as f32)
}

/// [`image_relative_error_of_tiles`] of a frame whose tiles may carry bias statistics:
/// `bias(t)` gives tile `t`'s, and where every tile has them the estimate is
/// [`ErrorEstimator::image_error_biased`] ([`image_relative_error_biased`] for
/// [`ErrorEstimator::Robust`]). Pixels with fewer than 2 passes have no estimate.
pub(crate) fn image_error_of_tiles_with_bias<'a>(
    plan: &crate::FramePlan,
    estimator: ErrorEstimator,
    tile: impl Fn(usize) -> Option<&'a [PixelStats]>,
    bias: impl Fn(usize) -> Option<&'a [BiasStats]>,
) -> f64 {
    let tiles = plan.tile_count() as usize;
    if tiles == 0 || (0..tiles).any(|t| bias(t).is_none()) {
        return image_relative_error_of_tiles(plan, estimator, tile);
    }
    let (width, height) = (plan.width as usize, plan.height as usize);
    let edge = plan.tile_size.max(1) as usize;
    let tiles_x = plan.tiles_x() as usize;
    estimator.image_error_biased(width, height, |x, y| {
        let (lx, ly) = (x % edge, y % edge);
        let tile_width = edge.min(width - (x - lx));
        let t = (y / edge) * tiles_x + x / edge;
        let i = ly * tile_width + lx;
        let s = tile(t)?.get(i)?;
        let b = bias(t)?.get(i)?;
        (s.passes >= 2).then(|| {
            (
                s.mean_lum,
                s.lum_variance_of_mean(),
                s.passes,
                b.mean,
                b.variance_of_mean(),
            )
        })
    })
}

/// Appended (after "; ") to the error estimator's name ([`ErrorEstimator::name`]) in the
/// EXR header, the job status and `tessera render`'s summary when the render carries a
/// bias channel ([`crate::UnitResult::bias`]: vcm and ppm): its estimate is
/// [`image_relative_error_biased`].
pub const BIAS_TERM: &str = "plus the merging bias estimated from the photons (Hachisuka, Jarosz & Jensen 2010), over the bias-corrected mean";

/// The unbiased estimate of a pixel's squared bias from its bias layers: `b² - v_b`, where
/// `b` is the mean of its passes' bias estimates and `v_b` the estimated variance of that
/// mean. Each pass's estimate is noisy (on a smooth field its variance is about three times
/// the pass mean's own, the weights `6 d²/r² - 3` having mean square 3), so `b²` alone
/// would charge that noise as bias: `E[b²] = bias² + Var(b)`. Not clamped, and may be
/// negative: the image estimate sums it over pixels before clamping
/// ([`image_relative_error_biased`]), so that the noise cancels instead of piling up as
/// `max(0, ·)` per pixel would make it. 0 with fewer than 2 passes (no spread to
/// subtract).
#[inline]
pub fn bias_squared(mean: f64, variance_of_mean: f64) -> f64 {
    if variance_of_mean.is_finite() {
        mean * mean - variance_of_mean
    } else {
        0.0
    }
}

/// The luminance scale of a biased render's pixel: `min(robust_scale(m, v, level),
/// max(m - b, 0) + sqrt(v_b) + REL_EPS)`, where `b` is the pixel's mean bias estimate and
/// `v_b` its estimated variance ([`BiasStats`]).
///
/// Why: the relative error divides by the pixel's true value, and where merging blurs a
/// bright caustic into a dark shadow the pixel's mean is mostly bias (0.8 where the truth
/// is 0.03 on `builtin:caustic` at 32 x 32): divided by its own mean, an exact bias would
/// count as a relative error of 1 where it is 20, and the image estimate was 0.12 of the
/// measured error with the bias term (docs/benchmarks.md, "The merging bias term"). `m -
/// b` is the bias-corrected mean; one standard error of the correction keeps the noise of
/// `b` from dragging the scale to `REL_EPS` (without it the estimate was 3 times the
/// measured error). Never above the robust scale, so a negative `b` does not lower the
/// estimate.
#[inline]
pub fn bias_scale(
    mean_lum: f64,
    lum_variance_of_mean: f64,
    level: f64,
    bias: f64,
    bias_variance_of_mean: f64,
) -> f64 {
    let robust = robust_scale(mean_lum, lum_variance_of_mean, level);
    if !(bias.is_finite() && bias_variance_of_mean.is_finite()) {
        return robust;
    }
    let corrected = (mean_lum - bias).max(0.0) + bias_variance_of_mean.max(0.0).sqrt() + REL_EPS;
    robust.min(corrected)
}

/// The image relative error estimate of a biased render (vcm, ppm; ARCHITECTURE.md §3):
/// the mean squared error is the variance plus the squared bias, so the estimate is
/// `sqrt((Σ v / s² + max(0, Σ bias² / s²)) / n)` over the `n` pixels with an estimate,
/// where `v` is the estimated variance of a pixel's mean from the pass spread, `bias²`
/// its [`bias_squared`] (summed over the pixels before the clamp, so the noise of the
/// per-pixel estimates cancels) and `s` its [`bias_scale`]. `pixel(x, y)` gives the mean
/// luminance `m`, its variance `v`, the mean bias estimate `b` and its variance `v_b`, or
/// `None` for a pixel with fewer than 2 passes. 0 when no pixel has an estimate; never
/// NaN. Used whatever the [`ErrorEstimator`] when a render carries bias layers.
pub fn image_relative_error_biased(
    width: usize,
    height: usize,
    pixel: impl Fn(usize, usize) -> Option<(f64, f64, f64, f64)>,
) -> f64 {
    let (mut spread, mut bias, mut count) = (0.0f64, 0.0f64, 0u64);
    for y in 0..height {
        for x in 0..width {
            let Some((m, v, b, vb)) = pixel(x, y) else {
                continue;
            };
            let level =
                neighbours_level(width, height, x, y, m, |qx, qy| pixel(qx, qy).map(|q| q.0));
            let s = bias_scale(m, v, level, b, vb);
            spread += v.max(0.0) / (s * s);
            bias += bias_squared(b, vb) / (s * s);
            count += 1;
        }
    }
    if !bias.is_finite() {
        bias = 0.0;
    }
    root_mean(spread + bias.max(0.0), count)
}

/// The image relative error estimate of an unbiased adaptive render of a biased technique
/// (vcm, ppm; ARCHITECTURE.md §3): [`image_relative_error_pooled`]'s spread term and
/// [`image_relative_error_biased`]'s bias term, both over the pixel's [`bias_scale`]:
/// `sqrt((Σ q_3x3 / k + max(0, Σ bias² / s²)) / n)`, where `q = k v / s²` is a pixel's
/// per-pass relative variance, `q_3x3` its mean over the 3x3 neighbourhood (the neighbours
/// with an estimate, the pixel included), `k` the pixel's passes and `bias²` its
/// [`bias_squared`]. `pixel(x, y)` gives `(m, v, k, b, v_b)` as for
/// [`ErrorEstimator::image_error_biased`], or `None` for a pixel with fewer than 2 passes.
/// 0 when no pixel has an estimate; never NaN.
///
/// Why both: the fresh passes of Kirk & Arvo's two-stage scheme follow a pilot that may
/// have missed rare bright paths, which the pooled spread answers
/// ([`image_relative_error_pooled`]); the merging bias is shared by every pass, which no
/// spread sees, and the bias term answers it as in a uniform render. The bias term is a
/// pixel's own, not pooled: it is an estimate of that pixel's squared bias, already
/// unbiased (`b² - v_b`), and summed over the pixels before the clamp.
pub fn image_relative_error_pooled_biased(
    width: usize,
    height: usize,
    pixel: impl Fn(usize, usize) -> Option<(f64, f64, u32, f64, f64)>,
) -> f64 {
    // Rows y - 1, y and y + 1 of (q, bias² / s²), in a ring, as
    // `image_relative_error_pooled` keeps them: nothing frame-sized is allocated.
    let mut rows: [Vec<Option<(f64, f64)>>; 3] = Default::default();
    let terms_row = |y: usize, out: &mut Vec<Option<(f64, f64)>>| {
        out.clear();
        out.extend((0..width).map(|x| {
            let (m, v, k, b, vb) = pixel(x, y)?;
            let level =
                neighbours_level(width, height, x, y, m, |qx, qy| pixel(qx, qy).map(|q| q.0));
            let s = bias_scale(m, v, level, b, vb);
            let s2 = s * s;
            Some((v.max(0.0) / s2 * f64::from(k), bias_squared(b, vb) / s2))
        }));
    };
    let (mut spread, mut bias, mut count) = (0.0f64, 0.0f64, 0u64);
    for y in 0..height {
        if y == 0 {
            terms_row(0, &mut rows[0]);
        }
        if y + 1 < height {
            terms_row(y + 1, &mut rows[(y + 1) % 3]);
        }
        for x in 0..width {
            let Some((_, _, k, _, _)) = pixel(x, y) else {
                continue;
            };
            let (mut qsum, mut n) = (0.0f64, 0u32);
            let columns = x.saturating_sub(1)..(x + 2).min(width);
            for qy in y.saturating_sub(1)..(y + 2).min(height) {
                for (q, _) in rows[qy % 3][columns.clone()].iter().flatten() {
                    qsum += q;
                    n += 1;
                }
            }
            // n >= 1: the pixel itself has an estimate.
            spread += qsum / f64::from(n) / f64::from(k.max(1));
            if let Some((_, b)) = rows[y % 3][x] {
                bias += b;
            }
            count += 1;
        }
    }
    if !bias.is_finite() {
        bias = 0.0;
    }
    root_mean(spread + bias.max(0.0), count)
}

/// Running statistics of one pixel's per-pass bias estimates ([`crate::UnitResult::bias`]):
/// Welford updates in f64, like [`PixelStats`], merged in pass order.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct BiasStats {
    /// Number of passes pushed.
    pub passes: u32,
    /// Mean of the passes' bias estimates (signed luminance).
    pub mean: f64,
    /// Sum of squared deviations from the mean.
    pub m2: f64,
}

impl BiasStats {
    /// Adds one pass's bias estimate.
    #[inline]
    pub fn push(&mut self, b: f32) {
        self.passes = self.passes.saturating_add(1);
        let n = f64::from(self.passes);
        let x = f64::from(b);
        let d = x - self.mean;
        self.mean += d / n;
        self.m2 += d * (x - self.mean);
    }

    /// Estimated variance of the mean, `m2 / (n (n - 1))`; `f64::INFINITY` with fewer than
    /// 2 passes.
    pub fn variance_of_mean(&self) -> f64 {
        if self.passes < 2 {
            return f64::INFINITY;
        }
        let n = f64::from(self.passes);
        self.m2 / (n * (n - 1.0))
    }

    /// The pixel's `bias.Y` and `bias.variance.Y` layer values: the mean and the variance of
    /// the mean, 0 for the variance with fewer than 2 passes (an EXR layer holds no
    /// infinity). Every image of a biased render writes them so: uniform, adaptive, stored.
    pub fn layers(&self) -> [f32; 2] {
        let v = if self.passes >= 2 {
            self.variance_of_mean() as f32
        } else {
            0.0
        };
        [self.mean as f32, v]
    }
}

/// Luminance weights of linear Rec. 709 / sRGB primaries.
pub const LUMINANCE_WEIGHTS: [f64; 3] = [0.2126, 0.7152, 0.0722];

/// Luminance of a linear Rec. 709 / sRGB colour: `0.2126 R + 0.7152 G + 0.0722 B`.
pub fn luminance(rgb: [f64; 3]) -> f64 {
    LUMINANCE_WEIGHTS[0] * rgb[0] + LUMINANCE_WEIGHTS[1] * rgb[1] + LUMINANCE_WEIGHTS[2] * rgb[2]
}

/// Running statistics of one pixel over its passes: Welford updates in f64 of the pass
/// means, per RGB channel and for luminance.
///
/// Each pass mean is one independent replicate of the pixel (ARCHITECTURE.md §3), so after `n`
/// passes the mean of the replicates estimates the pixel and `m2 / (n (n - 1))` estimates
/// the variance of that mean. Luminance has its own accumulator because its variance
/// involves the covariances between channels, which per-channel statistics do not keep.
///
/// The result depends on the order of [`PixelStats::push`] calls; the merge code always
/// pushes in pass order, which makes the statistics bit-reproducible.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct PixelStats {
    /// Number of passes pushed.
    pub passes: u32,
    /// Mean of the pass means, per channel.
    pub mean: [f64; 3],
    /// Sum of squared deviations from the mean, per channel.
    pub m2: [f64; 3],
    /// Mean of the luminance of the pass means.
    pub mean_lum: f64,
    /// Sum of squared deviations of the luminance from `mean_lum`.
    pub m2_lum: f64,
}

impl PixelStats {
    /// Adds one pass mean (Welford: `n += 1; d = x - mean; mean += d / n;
    /// m2 += d * (x - mean)`), computed in f64. Never allocates.
    #[inline]
    pub fn push(&mut self, rgb: [f32; 3]) {
        self.passes = self.passes.saturating_add(1);
        let n = f64::from(self.passes);
        let x = [f64::from(rgb[0]), f64::from(rgb[1]), f64::from(rgb[2])];
        for (c, &xc) in x.iter().enumerate() {
            let d = xc - self.mean[c];
            self.mean[c] += d / n;
            self.m2[c] += d * (xc - self.mean[c]);
        }
        let lum = luminance(x);
        let d = lum - self.mean_lum;
        self.mean_lum += d / n;
        self.m2_lum += d * (lum - self.mean_lum);
    }

    /// Estimated variance of the mean per channel, `m2 / (n (n - 1))`;
    /// `f64::INFINITY` with fewer than 2 passes (nothing is known about the error).
    pub fn variance_of_mean(&self) -> [f64; 3] {
        match self.denominator() {
            Some(d) => self.m2.map(|m2| m2 / d),
            None => [f64::INFINITY; 3],
        }
    }

    /// Estimated variance of the luminance of the mean, `m2_lum / (n (n - 1))`;
    /// `f64::INFINITY` with fewer than 2 passes.
    pub fn lum_variance_of_mean(&self) -> f64 {
        match self.denominator() {
            Some(d) => self.m2_lum / d,
            None => f64::INFINITY,
        }
    }

    /// Relative error of the pixel, `sqrt(lum_variance_of_mean) / (lum(mean) + REL_EPS)`,
    /// with `lum(mean)` taken as `mean_lum` (equal up to rounding, luminance being linear)
    /// and clamped at 0; `f64::INFINITY` with fewer than 2 passes.
    pub fn relative_error(&self) -> f64 {
        self.lum_variance_of_mean().max(0.0).sqrt() / (self.mean_lum.max(0.0) + REL_EPS)
    }

    fn denominator(&self) -> Option<f64> {
        if self.passes < 2 {
            return None;
        }
        let n = f64::from(self.passes);
        Some(n * (n - 1.0))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_util::Rng;

    fn rel_close(a: f64, b: f64, tol: f64) -> bool {
        (a - b).abs() <= tol * a.abs().max(b.abs()).max(f64::MIN_POSITIVE)
    }

    /// The interval quantiles against closed forms and tabulated values. For 1 degree of
    /// freedom t is Cauchy, `q = tan(pi P / 2)`; for 2, `P(|T| <= x) = x / sqrt(2 + x^2)`,
    /// so `q = P sqrt(2 / (1 - P^2))`. Beyond the table, the expansion against quantiles
    /// computed to 40 digits with mpmath (`findroot` on the regularized incomplete beta),
    /// within 3e-8; at the join it continues the table's decrease.
    #[test]
    fn interval_quantile_matches_tables() {
        let p = INTERVAL_COVERAGE;
        assert!(rel_close(
            interval_quantile(1),
            (std::f64::consts::FRAC_PI_2 * p).tan(),
            1e-12
        ));
        assert!(rel_close(
            interval_quantile(2),
            p * (2.0 / (1.0 - p * p)).sqrt(),
            1e-12
        ));
        for (dof, q) in [
            (33, 2.078_650_932_879_389_4),
            (40, 2.064_459_469_246_798_6),
            (48, 2.053_438_749_432_929_4),
            (64, 2.039_821_199_050_100_3),
            (100, 2.025_309_127_903_459_4),
            (135, 2.018_687_724_669_141_5),
            (1000, 2.002_503_065_361_22),
            (1_000_000, 2.000_002_500_003_062_3),
        ] {
            let got = interval_quantile(dof);
            assert!((got - q).abs() < 3e-8, "dof {dof}: {got} against {q}");
        }
        let q: Vec<f64> = (1..=40).map(interval_quantile).collect();
        assert!(q.windows(2).all(|w| w[1] < w[0]), "{q:?}");
        assert!(interval_quantile(u64::MAX) >= 2.0);
        assert_eq!(interval_quantile(0), f64::INFINITY);
    }

    /// The robust scale of a firefly, a highlight and a dark pixel next to a bright one.
    #[test]
    fn robust_scale_cases() {
        // A firefly: 4 passes 0, 0, 0, 8 in a neighbourhood of mean 0.5. Its mean is 2,
        // its standard error 2 (s^2 = 16, v = 4), so the floor is 0 and the scale falls
        // to the neighbourhood's 0.5: rel = 2 / 0.51 instead of 2 / 2.01.
        let mut s = PixelStats::default();
        for x in [0.0, 0.0, 0.0, 8.0] {
            s.push([x; 3]);
        }
        assert!((s.mean_lum - 2.0).abs() < 1e-12 && (s.lum_variance_of_mean() - 4.0).abs() < 1e-12);
        assert!((robust_scale(2.0, 4.0, 0.5) - 0.51).abs() < 1e-12);
        // The floor is exactly the mean of the other passes when one pass departs from
        // equal others (Samuelson's bound is attained): passes 1, 1, 1, 9.
        let mut s = PixelStats::default();
        for x in [1.0, 1.0, 1.0, 9.0] {
            s.push([x; 3]);
        }
        let floor = s.mean_lum - s.lum_variance_of_mean().sqrt();
        assert!((floor - 1.0).abs() < 1e-12, "{floor}");
        // A highlight: consistent passes (mean 10, se 0.5) among dark neighbours keeps a
        // scale of at least 9.5.
        assert!((robust_scale(10.0, 0.25, 1.2) - 9.51).abs() < 1e-12);
        // A dark pixel next to bright ones keeps its own mean.
        assert!((robust_scale(0.2, 0.01, 5.0) - 0.21).abs() < 1e-12);
        // Negative means (never produced, but clamped) and zero variance.
        assert_eq!(robust_scale(-1.0, 0.0, -3.0), REL_EPS);
    }

    /// The level leaves the pixel out: a firefly does not raise the level it is divided
    /// by, and where every neighbour is black (or has no estimate) the level is `m / 9`,
    /// what the 3x3 mean with the pixel gave.
    #[test]
    fn neighbours_level_leaves_the_pixel_out() {
        // 3x3, the centre a firefly of mean 3.6 among neighbours of mean 0.5 (one without an
        // estimate): the level is 0.5 (above 3.6 / 9), where the 3x3 mean would be
        // (3.5 + 3.6) / 8 = 0.8875.
        let at = |x: usize, y: usize| match (x, y) {
            (1, 1) => Some(3.6),
            (0, 0) => None,
            _ => Some(0.5),
        };
        assert!((neighbours_level(3, 3, 1, 1, 3.6, at) - 0.5).abs() < 1e-12);
        // Black neighbours: m / 9. A corner pixel has 3 neighbours; none at all gives m / 9.
        let black = |x: usize, y: usize| Some(if (x, y) == (0, 0) { 9.0 } else { 0.0 });
        assert!((neighbours_level(3, 3, 0, 0, 9.0, black) - 1.0).abs() < 1e-12);
        assert!((neighbours_level(1, 1, 0, 0, 9.0, |_, _| Some(9.0)) - 1.0).abs() < 1e-12);
        // A corner pixel darker than its 3 neighbours: their mean. Negative means clamp.
        let corner = |x: usize, y: usize| Some(if (x, y) == (0, 0) { 0.1 } else { 3.0 });
        assert!((neighbours_level(5, 5, 0, 0, 0.1, corner) - 3.0).abs() < 1e-12);
        assert_eq!(neighbours_level(3, 3, 1, 1, -1.0, |_, _| Some(-2.0)), 0.0);
        // The firefly's estimate: its standard error 3.6 over the level 0.5 (its floor
        // 3.6 - 3.6 = 0); the exact neighbours add 0 over 8 pixels.
        let e = image_relative_error(3, 3, |x, y| {
            at(x, y).map(|m| (m, if (x, y) == (1, 1) { 3.6 * 3.6 } else { 0.0 }))
        });
        let firefly = 3.6 / (0.5 + REL_EPS);
        assert!((e - (firefly * firefly / 8.0).sqrt()).abs() < 1e-9, "{e}");
    }

    /// On a flat image the robust estimate equals the RMS of the pixels' own `rel`;
    /// pixels without an estimate are left out of the sum and of their neighbours' means.
    #[test]
    fn image_relative_error_flat_and_missing() {
        let px = Some((1.0, 0.01));
        let mut pixels = vec![px; 12];
        let own = 0.1 / 1.01;
        let of =
            |pixels: &[Option<(f64, f64)>]| image_relative_error(4, 3, |x, y| pixels[y * 4 + x]);
        assert!((of(&pixels) - own).abs() < 1e-12);
        pixels[5] = None;
        pixels[6] = Some((100.0, 0.0));
        // Pixel 6 is exact (v = 0) but raises its neighbours' means; they are darker
        // than it and keep their own means, so the estimate over 11 pixels is 10 x own^2.
        let e = of(&pixels);
        assert!((e - (10.0 * own * own / 11.0).sqrt()).abs() < 1e-12, "{e}");
        assert_eq!(image_relative_error(2, 1, |_, _| None), 0.0);
    }

    /// The pooled estimate against a direct, frame-sized computation of its definition,
    /// on random images with holes and unequal pass counts (the ring of rows must see the
    /// right neighbours at every row and at the borders); on a flat image with equal passes
    /// it is the plain estimate.
    #[test]
    fn pooled_estimate_matches_its_definition() {
        let mut rng = Rng::new(15);
        for case in 0..50 {
            let (w, h) = (1 + case % 7, 1 + (case / 7) % 6);
            let pixels: Vec<Option<(f64, f64, u32)>> = (0..w * h)
                .map(|_| {
                    (rng.uniform() > 0.15).then(|| {
                        let m = 10f64.powf(-3.0 + 4.0 * rng.uniform());
                        let v = m * m * 10f64.powf(-4.0 + 4.0 * rng.uniform());
                        (m, v, 2 + (rng.next_u64() % 60) as u32)
                    })
                })
                .collect();
            let at = |x: usize, y: usize| pixels[y * w + x];
            let neighbours = |x: usize, y: usize| {
                (y.saturating_sub(1)..(y + 2).min(h)).flat_map(move |qy| {
                    (x.saturating_sub(1)..(x + 2).min(w)).map(move |qx| (qx, qy))
                })
            };
            let q: Vec<Option<f64>> = (0..w * h)
                .map(|i| {
                    let (x, y) = (i % w, i / w);
                    let (m, v, k) = at(x, y)?;
                    // The neighbours' level: their mean without the pixel, floored at m / 9.
                    let ms: Vec<f64> = neighbours(x, y)
                        .filter(|&q| q != (x, y))
                        .filter_map(|(qx, qy)| at(qx, qy).map(|p| p.0))
                        .collect();
                    let m8 = ms.iter().sum::<f64>() / ms.len().max(1) as f64;
                    let level = m8.max(m / 9.0);
                    Some(v / robust_scale(m, v, level).powi(2) * f64::from(k))
                })
                .collect();
            let (mut sum, mut count) = (0.0, 0);
            for i in 0..w * h {
                let (x, y) = (i % w, i / w);
                let Some((_, _, k)) = at(x, y) else { continue };
                let qs: Vec<f64> = neighbours(x, y)
                    .filter_map(|(qx, qy)| q[qy * w + qx])
                    .collect();
                sum += qs.iter().sum::<f64>() / qs.len() as f64 / f64::from(k);
                count += 1;
            }
            let expected = if count == 0 {
                0.0
            } else {
                (sum / count as f64).sqrt()
            };
            let got = image_relative_error_pooled(w, h, at);
            assert!(
                rel_close(got, expected, 1e-12),
                "case {case}: {got} != {expected}"
            );
        }
        let flat = |_, _| Some((1.0, 0.01, 4));
        let plain = image_relative_error(5, 4, |_, _| Some((1.0, 0.01)));
        assert!(rel_close(
            image_relative_error_pooled(5, 4, flat),
            plain,
            1e-12
        ));
        assert_eq!(image_relative_error_pooled(3, 2, |_, _| None), 0.0);
    }

    /// What the pooling is for: a pixel left with few passes, whose own spread is small,
    /// beside pixels whose many passes show a large per-pass variance, is estimated from
    /// theirs; the plain estimate trusts its own.
    #[test]
    fn pooled_estimate_lends_neighbours_variance_to_a_lucky_pixel() {
        // 3x1: two noisy pixels (per-pass relative variance 1, 100 passes) around a pixel
        // with 4 passes that all missed (variance 0).
        let px = |x: usize, _| {
            Some(if x == 1 {
                (1.0, 0.0, 4)
            } else {
                (1.0, 1.01f64.powi(2) / 100.0, 100)
            })
        };
        let plain = image_relative_error(3, 1, |x, y| px(x, y).map(|(m, v, _)| (m, v)));
        let pooled = image_relative_error_pooled(3, 1, px);
        assert!(rel_close(plain, (2.0f64 / 300.0).sqrt(), 1e-12), "{plain}");
        // Per-pass relative variances: 1 at the edges (0.01 x 100 passes), 0 in the
        // middle. Each edge pools itself and the middle, (1 + 0) / 2 over 100 passes; the
        // middle pools all three, (1 + 0 + 1) / 3 over its 4 passes.
        let expected = ((2.0 * 0.5 / 100.0 + (2.0 / 3.0) / 4.0) / 3.0f64).sqrt();
        assert!(rel_close(pooled, expected, 1e-12), "{pooled} != {expected}");
        assert!(pooled > 2.5 * plain, "{pooled} against {plain}");
    }

    #[test]
    fn luminance_weights() {
        assert_eq!(luminance([1.0, 0.0, 0.0]), 0.2126);
        assert_eq!(luminance([0.0, 1.0, 0.0]), 0.7152);
        assert_eq!(luminance([0.0, 0.0, 1.0]), 0.0722);
        assert!((luminance([1.0, 1.0, 1.0]) - 1.0).abs() < 1e-15);
    }

    #[test]
    fn fewer_than_two_passes() {
        let mut s = PixelStats::default();
        assert_eq!(s.variance_of_mean(), [f64::INFINITY; 3]);
        assert_eq!(s.relative_error(), f64::INFINITY);
        s.push([1.0, 2.0, 3.0]);
        assert_eq!(s.mean, [1.0, 2.0, 3.0]);
        assert_eq!(s.lum_variance_of_mean(), f64::INFINITY);
        s.push([1.0, 2.0, 3.0]);
        assert_eq!(s.variance_of_mean(), [0.0; 3]);
        assert_eq!(s.relative_error(), 0.0);
    }

    /// Welford agrees with the two-pass formula (mean, then sum of squared deviations).
    #[test]
    fn welford_matches_two_pass_reference() {
        let mut rng = Rng::new(0x5eed);
        for case in 0..200 {
            let n = 2 + (rng.next_u64() % 300) as usize;
            // Radiance-like data: offsets up to 10, spreads from 0.1 to 10 (so the mean is
            // up to ~350 standard deviations from zero, which exercises cancellation).
            let offset = 10.0 * rng.uniform();
            let spread = 10f64.powf(-1.0 + 2.0 * rng.uniform());
            let xs: Vec<[f32; 3]> = (0..n)
                .map(|_| [0, 1, 2].map(|_| (offset + spread * rng.uniform()) as f32))
                .collect();
            let mut s = PixelStats::default();
            for &x in &xs {
                s.push(x);
            }
            assert_eq!(s.passes as usize, n);
            let nf = n as f64;
            for c in 0..4 {
                let val = |x: &[f32; 3]| {
                    let x = x.map(f64::from);
                    if c < 3 {
                        x[c]
                    } else {
                        luminance(x)
                    }
                };
                let mean = xs.iter().map(val).sum::<f64>() / nf;
                let m2 = xs.iter().map(|x| (val(x) - mean).powi(2)).sum::<f64>();
                let (wm, wm2) = if c < 3 {
                    (s.mean[c], s.m2[c])
                } else {
                    (s.mean_lum, s.m2_lum)
                };
                assert!(
                    rel_close(wm, mean, 1e-12),
                    "case {case} c {c}: {wm} vs {mean}"
                );
                assert!(
                    rel_close(wm2, m2, 1e-12),
                    "case {case} c {c}: {wm2} vs {m2}"
                );
                let var = if c < 3 {
                    s.variance_of_mean()[c]
                } else {
                    s.lum_variance_of_mean()
                };
                assert!(
                    rel_close(var, m2 / (nf * (nf - 1.0)), 1e-9),
                    "case {case} c {c}"
                );
            }
        }
    }

    /// The variance of the mean is calibrated for iid replicates (ARCHITECTURE.md §3).
    ///
    /// 2000 replicates of K = 16 normal passes (mu = 5, sigma = 2). For each, v =
    /// s^2 / K with (K - 1) s^2 / sigma^2 ~ chi^2_{K-1}, so E[v] = sigma^2 / K and
    /// Var[v] = 2 sigma^4 / ((K - 1) K^2).
    /// 1. z-test: the mean of v over replicates is sigma^2 / K within 4 standard errors,
    ///    and (the required accuracy) within 5%;
    /// 2. chi-square shape: the spread of v matches Var[v] (the standard error of a sample
    ///    variance is sqrt((kurtosis - 1) / R) relative, kurtosis of chi^2_15 = 3 + 12/15);
    /// 3. coverage: (mean - mu) / sqrt(v) ~ Student t with 15 degrees of freedom, so
    ///    P(|mean - mu| <= 2 sqrt(v)) = 0.93605; the observed fraction must lie within a
    ///    binomial 3-sigma band.
    #[test]
    fn variance_of_mean_is_calibrated() {
        const R: usize = 2000;
        const K: u32 = 16;
        let (mu, sigma) = (5.0f64, 2.0f64);
        let mut rng = Rng::new(42);
        let mut vs = Vec::with_capacity(R);
        let mut covered = 0usize;
        for _ in 0..R {
            let mut s = PixelStats::default();
            for _ in 0..K {
                let x = [0, 1, 2].map(|_| (mu + sigma * rng.normal()) as f32);
                s.push(x);
            }
            let v = s.variance_of_mean()[1];
            if (s.mean[1] - mu).abs() <= 2.0 * v.sqrt() {
                covered += 1;
            }
            vs.push(v);
        }
        let k = f64::from(K);
        let r = R as f64;
        let expected = sigma * sigma / k;
        let var_v = 2.0 * sigma.powi(4) / ((k - 1.0) * k * k);

        let mean_v = vs.iter().sum::<f64>() / r;
        let z = (mean_v - expected) / (var_v / r).sqrt();
        assert!(z.abs() < 4.0, "mean of v {mean_v} vs {expected}: z = {z}");
        assert!(
            (mean_v / expected - 1.0).abs() < 0.05,
            "mean of v {mean_v} vs {expected}"
        );

        let sample_var_v = vs.iter().map(|v| (v - mean_v).powi(2)).sum::<f64>() / (r - 1.0);
        let kurtosis = 3.0 + 12.0 / (k - 1.0);
        let rel_se = ((kurtosis - 1.0) / r).sqrt();
        let z_shape = (sample_var_v / var_v - 1.0) / rel_se;
        assert!(
            z_shape.abs() < 4.0,
            "Var[v] {sample_var_v} vs {var_v}: z = {z_shape}"
        );

        let p = 0.936_055;
        let frac = covered as f64 / r;
        let band = 3.0 * (p * (1.0 - p) / r).sqrt();
        assert!((frac - p).abs() <= band, "coverage {frac} vs {p} +- {band}");
    }

    /// The unbiased adaptive estimate of a biased render: the pooled spread of
    /// `image_relative_error_pooled` plus the bias term of `image_relative_error_biased`.
    #[test]
    fn pooled_biased_estimate_is_the_pooled_spread_plus_the_bias_term() {
        let (w, h) = (7usize, 5usize);
        let mean = |x: usize, y: usize| 0.2 + 0.1 * ((x * 3 + y * 5) % 7) as f64;
        let var = |x: usize, y: usize| 1e-3 * ((x + 2 * y) % 4) as f64;
        let k = |x: usize, y: usize| 2 + ((x * y) % 5) as u32;
        // Without bias it is the pooled estimate.
        let pooled =
            image_relative_error_pooled(w, h, |x, y| Some((mean(x, y), var(x, y), k(x, y))));
        let no_bias = image_relative_error_pooled_biased(w, h, |x, y| {
            Some((mean(x, y), var(x, y), k(x, y), 0.0, 0.0))
        });
        assert!(
            (no_bias / pooled - 1.0).abs() < 1e-12,
            "{no_bias} vs {pooled}"
        );
        // A flat image with equal pass counts: pooling changes nothing, so it is the
        // robust biased estimate, bias term included.
        let flat = |b: f64, vb: f64| {
            (
                image_relative_error_pooled_biased(w, h, move |_, _| Some((0.5, 4e-3, 4, b, vb))),
                image_relative_error_biased(w, h, move |_, _| Some((0.5, 4e-3, b, vb))),
            )
        };
        for (b, vb) in [(0.0, 0.0), (0.2, 1e-3), (-0.1, 0.0), (0.05, 0.01)] {
            let (p, r) = flat(b, vb);
            assert!((p / r - 1.0).abs() < 1e-12, "b {b}: {p} vs {r}");
        }
        assert!(flat(0.2, 1e-3).0 > flat(0.0, 0.0).0);
        // A negative bias leaves the scale the robust one, so the bias term is the same
        // sum in both, added to the pooled spread in one and the own spread in the other.
        let px = |x: usize, y: usize| Some((mean(x, y), var(x, y), k(x, y), -0.1, 1e-4));
        let pooled = image_relative_error_pooled_biased(w, h, px);
        let own = image_relative_error_biased(w, h, |x, y| px(x, y).map(|p| (p.0, p.1, p.3, p.4)));
        let own_spread = image_relative_error(w, h, |x, y| px(x, y).map(|p| (p.0, p.1)));
        let pooled_spread =
            image_relative_error_pooled(w, h, |x, y| px(x, y).map(|p| (p.0, p.1, p.2)));
        assert!(
            (pooled_spread / own_spread - 1.0).abs() > 1e-3,
            "pooling changed nothing"
        );
        let term = |e: f64, spread: f64| e * e - spread * spread;
        assert!(term(own, own_spread) > 0.0);
        assert!(
            (term(pooled, pooled_spread) / term(own, own_spread) - 1.0).abs() < 1e-9,
            "{pooled} {pooled_spread} {own} {own_spread}"
        );
        assert_eq!(image_relative_error_pooled_biased(3, 3, |_, _| None), 0.0);
        // The estimator dispatches to the two.
        let e = ErrorEstimator::PooledPerPass.image_error_biased(w, h, px);
        assert_eq!(e.to_bits(), pooled.to_bits());
        let e = ErrorEstimator::Robust.image_error_biased(w, h, px);
        assert_eq!(e.to_bits(), own.to_bits());
    }

    /// The squared bias estimate is unbiased where the per-pass estimates are pure noise
    /// (their mean over many pixels is near 0, where `mean²` alone would be `Var`), and
    /// recovers a constant bias; the image estimate adds it to the spread's over the
    /// bias-corrected scale.
    #[test]
    fn bias_squared_removes_the_noise_and_keeps_the_bias() {
        let mut rng = Rng::new(40);
        let (pixels, k) = (4000, 4);
        for (bias, sigma) in [(0.0f64, 1.0f64), (0.5, 1.0), (2.0, 0.5)] {
            let mut sum = 0.0;
            let mut naive = 0.0;
            for _ in 0..pixels {
                let mut b = BiasStats::default();
                for _ in 0..k {
                    b.push((bias + sigma * rng.normal()) as f32);
                }
                sum += bias_squared(b.mean, b.variance_of_mean());
                naive += b.mean * b.mean;
            }
            let got = sum / pixels as f64;
            // Var(mean) = sigma² / k; the estimate's spread over pixels is about
            // sqrt(2 (sigma²/k)² (1 + 1/(k-1)) + 4 bias² sigma²/k) / sqrt(pixels).
            let v = sigma * sigma / k as f64;
            let se = ((2.0 * v * v * (1.0 + 1.0 / (k as f64 - 1.0)) + 4.0 * bias * bias * v)
                / pixels as f64)
                .sqrt();
            assert!(
                (got - bias * bias).abs() < 4.0 * se,
                "bias {bias}: {got} +- {se}"
            );
            assert!((naive / pixels as f64 - bias * bias - v).abs() < 4.0 * se + 0.02);
        }
        assert_eq!(bias_squared(3.0, f64::INFINITY), 0.0);
        // Flat 2x2 image of mean 1 - REL_EPS, no variance, no bias: the scale is 1 and
        // the estimate the spread's.
        let flat = |b: f64, vb: f64| {
            image_relative_error_biased(2, 2, move |_, _| Some((1.0 - REL_EPS, 0.09, b, vb)))
        };
        let robust = image_relative_error(2, 2, |_, _| Some((1.0 - REL_EPS, 0.09)));
        assert!((flat(0.0, 0.0) - robust).abs() < 1e-12);
        // A bias of 0.5 with no noise: the scale falls to the corrected mean 0.5 - REL_EPS
        // + REL_EPS, and the error is sqrt(0.09 + 0.25) / 0.5.
        assert!((flat(0.5, 0.0) - (0.34f64).sqrt() / 0.5).abs() < 1e-12);
        // A negative bias never raises the scale above the robust one.
        assert!(flat(-0.5, 0.0) >= robust);
        // Pure noise in the bias (b² < v_b) never lowers the spread's part: the bias sum
        // is clamped at 0 (the scale may still fall by the noise's standard error).
        assert!(flat(0.1, 0.04) >= robust);
        assert_eq!(image_relative_error_biased(2, 2, |_, _| None), 0.0);
        // The scale: the corrected mean plus the correction's standard error, at most
        // the robust scale.
        assert!((bias_scale(1.0, 0.0, 1.0, 0.7, 0.01) - (0.3 + 0.1 + REL_EPS)).abs() < 1e-12);
        assert_eq!(
            bias_scale(1.0, 0.0, 1.0, -0.7, 0.0),
            robust_scale(1.0, 0.0, 1.0)
        );
        assert_eq!(
            bias_scale(1.0, 0.0, 1.0, 2.0, f64::INFINITY),
            robust_scale(1.0, 0.0, 1.0)
        );
    }
}
