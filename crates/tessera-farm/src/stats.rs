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
mod tests;
