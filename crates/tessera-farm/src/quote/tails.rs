//! Heavy tails: whether a pilot can predict what accuracy costs (ARCHITECTURE.md §3,
//! "Quotes and ETA").
//!
//! The quote's law `E(n) = sqrt(M P / n)` holds once the pilot's per-pass variance is the
//! estimator's. Where light arrives along rare paths (a path-traced caustic of a small
//! light, a glossy highlight of a tiny one) a pass's value in a pixel is usually small and
//! now and then huge: a few pilot passes see too few of those fireflies to size the
//! variance, and the variance they see grows with every pass that catches one (on the
//! glass ball under a small area light a pilot quoted 8.9 s and the render took 858 s).
//! [`Tails::measure`] reads three statistics off the pilot's per-pixel pass values, and
//! [`Tails::verdict`] says from them whether the quote's interval stands, must be widened,
//! or cannot be given.
//!
//! # The statistics
//!
//! Each pilot pixel `i` has `P` pass values `x_ik` (luminance of the pass mean).
//!
//! - **Tail index** (Hill 1975): each value over its pixel's *other* passes' mean,
//!   `y_ik = x_ik / max(mean_{j != k} x_ij, f)` with `f` [`DARK_FLOOR`] times the pilot's
//!   mean value (leaving the value out, so one firefly is not divided by a mean it made
//!   itself; the floor, so a dark pixel's tiny values do not make large ratios). Over the
//!   `k` largest of all the `y` (`k = max(`[`HILL_MIN_K`]`, round(sqrt(N)))` of `N` values,
//!   a common choice for an unknown tail), Hill's estimator is
//!   `alpha = k / sum_{j <= k} ln(y_(j) / y_(k+1))`. A Pareto tail `P(Y > y) ~ y^-alpha`
//!   has a finite variance only for `alpha > 2`, and a variance *estimate* with a finite
//!   variance (the quote's interval) only for `alpha > 4`; light tails (Gaussian,
//!   exponential) give large `alpha` (about `ln(N / k)` for an exponential tail, 5 at the
//!   pilot's sizes).
//! - **Share of the brightest**: the pixels' squared relative deviations
//!   `(x_ik - m_i)² / (m_i + REL_EPS)²` (the terms of the quote's `M`, `m_i` the pixel's
//!   mean) in the largest 1% of all, as a share of their sum. Gaussian noise puts about 9%
//!   of the sum there; rare paths most of it.
//! - **Variance growth between pilot sizes**: the quote's per-pass figure `M P` from all
//!   `P` passes over the same from each half of them (`P / 2` passes, the halves'
//!   average): `g = M_P P / (M_{P/2} P/2)`. For passes of finite variance both estimate the
//!   same per-pass variance (up to the ratio estimator's small bias) and `g` is about 1.
//!   Where the error is carried by rare fireflies, a pixel whose one firefly in four passes
//!   is all its light has `M P = 4` over the four and `1` over the half that caught it
//!   (0 over the other): the per-pass error grows with the passes, `g` near 4. With the
//!   error growing like `n^gamma` per pass, `gamma = log2 g`, the error after `n` passes
//!   falls like `n^((gamma - 1) / 2)`, and not at all for `gamma >= 1`.
//!
//! # The verdict
//!
//! - [`TailClass::Unpredictable`]: `alpha <` [`ALPHA_UNPREDICTABLE`] (2.5: the pass
//!   values' variance may not exist, or barely does, and there is no `1/sqrt(n)` law the
//!   pilot can extrapolate), or `g >=`
//!   [`GROWTH_UNPREDICTABLE`] (the error estimate doubled when the pilot doubled: it
//!   does not fall with the passes the pilot can see). The quote says "not predictable
//!   from the pilot" with the reason, and its figures are what the pilot's own law says,
//!   a lower bound, not a prediction.
//! - [`TailClass::Heavy`]: `alpha <` [`ALPHA_HEAVY`], `g >` [`GROWTH_HEAVY`] or a share
//!   over [`SHARE_HEAVY`]: the variance exists but its pilot estimate is unreliable. The
//!   interval's high end is the larger of the `1/sqrt(n)` law's and the law extrapolated
//!   with the measured growth, `gamma = max(log2 g, 2 / alpha - 1/2, 0)`: a per-pass error
//!   still growing as the pilot's did, or as fast as the typical variance estimate of an
//!   `alpha` tail grows (like `n^(2/alpha - 1)` for `alpha < 2`; the half a power more
//!   covers the pre-asymptotic growth of `2 < alpha < 4`, where the estimate converges
//!   but its spread does not shrink like `1/sqrt(n)`).
//! - [`TailClass::Light`]: the quote stands as the module documentation derives it.
//!
//! [`crate::quote::quote`] also makes a heavy verdict unpredictable when the pilot's
//! groups of pixels disagree on its error ([`crate::quote::REL_M_UNPREDICTABLE`]): the
//! statistics here see the pass values, not how the error spreads over the frame.
//!
//! The thresholds are where these statistics sit on the calibration scenes
//! (docs/benchmarks.md, "Quotes where paths are rare" and "Quotes at 5% and 2% on the
//! calibration suite"); the pilot is deterministic, so a scene's class does not depend on
//! the machine, but it does on the pixels' size: a larger pixel averages its rare paths
//! over more area.

use serde::{Deserialize, Serialize};

use crate::REL_EPS;

/// Below this fraction of the pilot's mean value a pixel's scale is floored (the tail
/// index's ratios): the technique pilot's floor, `tessera_render::pilot`.
pub const DARK_FLOOR: f64 = 0.1;
/// The fewest order statistics Hill's estimator uses.
pub const HILL_MIN_K: usize = 16;
/// Below this tail index the quote is not given. Below 2 the variance of a pass may not
/// exist; just above it, it exists but the `1/sqrt(n)` law sets in only after many more
/// passes than a pilot renders: on `scenes/glossy-highlight.gltf` (64x64, 5%) the pilot
/// measured 2.03 and the render needed 9 times the law's passes, beyond even the heavy
/// class's extrapolation (docs/benchmarks.md, "Quotes where paths are rare").
pub const ALPHA_UNPREDICTABLE: f64 = 2.5;
/// Below this tail index the quote's interval is widened (its variance estimate's own
/// variance may not exist).
pub const ALPHA_HEAVY: f64 = 4.0;
/// At or above this growth of the per-pass error between the pilot's halves and the whole
/// pilot, the quote is not given.
pub const GROWTH_UNPREDICTABLE: f64 = 2.0;
/// Above this growth the interval is widened.
pub const GROWTH_HEAVY: f64 = 1.25;
/// Above this share of the squared deviations in the brightest 1% of the pass values the
/// interval is widened.
pub const SHARE_HEAVY: f64 = 0.5;
/// The brightest fraction of pass values whose share is measured.
pub const TOP_FRACTION: f64 = 0.01;

/// What the pilot's pass values say of their tail (module documentation).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Tails {
    /// Pass values measured (pixels times passes).
    pub values: u64,
    /// Hill's tail index of the values over their pixels' other passes; `None` when fewer
    /// than `k + 1` values are positive.
    pub tail_index: Option<f64>,
    /// Order statistics Hill's estimator used.
    pub hill_k: u64,
    /// Share of the squared relative deviations in the brightest [`TOP_FRACTION`].
    pub top_share: f64,
    /// Growth of the per-pass error from half the pilot's passes to all of them; `None`
    /// when the halves show no error.
    pub variance_growth: Option<f64>,
}

/// How far a quote can be trusted, by its pilot's tails.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TailClass {
    /// Light tails: the interval stands (also a quote whose pilot measured no tails).
    #[default]
    Light,
    /// Heavy tails: the interval is widened by the measured growth.
    Heavy,
    /// Not predictable from the pilot: the figures are a lower bound.
    Unpredictable,
}

/// Squared relative error of the mean of `x` as `PixelStats::relative_error` computes it:
/// `Var[mean] / (mean + REL_EPS)²`, the mean clamped at 0.
fn rel_sq(x: &[f64]) -> f64 {
    let n = x.len() as f64;
    if x.len() < 2 {
        return 0.0;
    }
    let mean = x.iter().sum::<f64>() / n;
    let ss: f64 = x.iter().map(|v| (v - mean).powi(2)).sum();
    let scale = mean.max(0.0) + REL_EPS;
    ss / (n * (n - 1.0)) / (scale * scale)
}

impl Tails {
    /// Measures `values`, pixel-major with `passes` values per pixel (luminance of each
    /// pass's mean). `None` with fewer than 4 passes (no halves of 2), no pixel, a
    /// non-finite value or no light at all.
    pub fn measure(values: &[f64], passes: usize) -> Option<Self> {
        if passes < 4 || values.len() < passes || values.iter().any(|v| !v.is_finite()) {
            return None;
        }
        let n = values.len() / passes * passes;
        let values = &values[..n];
        let mean_value = values.iter().map(|v| v.max(0.0)).sum::<f64>() / n as f64;
        if mean_value <= 0.0 {
            return None;
        }
        let floor = DARK_FLOOR * mean_value;
        let half = passes / 2;
        let mut ratios = Vec::with_capacity(n);
        let mut deviations = Vec::with_capacity(n);
        let (mut full, mut halves) = (0.0, 0.0);
        for pixel in values.chunks_exact(passes) {
            let sum: f64 = pixel.iter().sum();
            let mean = sum / passes as f64;
            let scale = mean.max(0.0) + REL_EPS;
            for &x in pixel {
                let others = (sum - x) / (passes - 1) as f64;
                ratios.push(x.max(0.0) / others.max(floor));
                deviations.push(((x - mean) / scale).powi(2));
            }
            full += rel_sq(pixel) * passes as f64;
            halves += 0.5 * (rel_sq(&pixel[..half]) + rel_sq(&pixel[half..2 * half])) * half as f64;
        }
        let k = HILL_MIN_K.max((n as f64).sqrt().round() as usize);
        let tail_index = hill(&mut ratios, k);
        let top = ((n as f64 * TOP_FRACTION).ceil() as usize).clamp(1, n);
        let total: f64 = deviations.iter().sum();
        let top_share = if total > 0.0 {
            deviations.select_nth_unstable_by(n - top, f64::total_cmp);
            deviations[n - top..].iter().sum::<f64>() / total
        } else {
            0.0
        };
        Some(Self {
            values: n as u64,
            tail_index,
            hill_k: k as u64,
            top_share,
            variance_growth: (halves > 0.0).then(|| full / halves),
        })
    }

    /// The growth exponent of the per-pass error the interval's high end extrapolates
    /// with (module documentation, "The verdict"), at least 0.
    pub fn gamma(&self) -> f64 {
        let from_growth = self.variance_growth.map_or(0.0, |g| g.max(1.0).log2());
        let from_index = self.tail_index.map_or(0.0, |a| 2.0 / a - 0.5);
        from_growth.max(from_index).max(0.0)
    }

    /// The statistics in words, for a quote's note.
    fn figures(&self) -> String {
        format!(
            "tail index {} (Hill, k = {}), {:.0}% of the squared error in the brightest 1% \
             of {} pass values, per-pass error x{} from half the pilot's passes to all",
            self.tail_index.map_or("n/a".into(), |a| format!("{a:.2}")),
            self.hill_k,
            self.top_share * 100.0,
            self.values,
            self.variance_growth
                .map_or("n/a".into(), |g| format!("{g:.2}")),
        )
    }

    /// The note of a quote that is not predictable from its pilot, for the reason `why`,
    /// with the figures.
    pub fn unpredictable_note(&self, why: &str) -> String {
        format!(
            "not predictable from the pilot: {why}, the mark of rare paths (fireflies) a \
             short pilot cannot size; the figures below are what the pilot's 1/sqrt(passes) \
             law says, a lower bound ({})",
            self.figures()
        )
    }

    /// The class and, unless light, the reason in words with the figures.
    pub fn verdict(&self) -> (TailClass, Option<String>) {
        let figures = self.figures();
        let alpha = self.tail_index.unwrap_or(f64::INFINITY);
        let growth = self.variance_growth.unwrap_or(1.0);
        if alpha < ALPHA_UNPREDICTABLE || growth >= GROWTH_UNPREDICTABLE {
            let why = if alpha < ALPHA_UNPREDICTABLE {
                "the brightest pass values have a tail so heavy that their variance may not \
                 exist or settles only after many more passes than a pilot's"
            } else {
                "the error estimate grew with the pilot's passes instead of falling"
            };
            return (TailClass::Unpredictable, Some(self.unpredictable_note(why)));
        }
        if alpha < ALPHA_HEAVY || growth > GROWTH_HEAVY || self.top_share > SHARE_HEAVY {
            return (
                TailClass::Heavy,
                Some(format!(
                    "heavy-tailed pilot: the intervals' high ends extrapolate the per-pass \
                     error growing like passes^{:.2} ({figures})",
                    self.gamma()
                )),
            );
        }
        (TailClass::Light, None)
    }
}

/// Hill's estimator over the `k` largest of `y` (reordered). `None` unless `k + 1` of them
/// are positive.
fn hill(y: &mut [f64], k: usize) -> Option<f64> {
    let n = y.len();
    if n < k + 1 {
        return None;
    }
    y.select_nth_unstable_by(n - k - 1, f64::total_cmp);
    let threshold = y[n - k - 1];
    if threshold <= 0.0 {
        return None;
    }
    let sum: f64 = y[n - k..].iter().map(|v| (v / threshold).ln()).sum();
    (sum > 0.0).then(|| k as f64 / sum)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_util::Rng;

    /// `pixels` pixels of `passes` pass values each, every pixel's values drawn by `draw`
    /// around a mean that differs over the image (a gradient), as a render's would.
    fn pilot(
        rng: &mut Rng,
        pixels: usize,
        passes: usize,
        draw: impl Fn(&mut Rng) -> f64,
    ) -> Vec<f64> {
        (0..pixels * passes)
            .map(|i| {
                let level = 0.2 + (i / passes) as f64 / pixels as f64;
                level * draw(rng)
            })
            .collect()
    }

    /// A light-tailed estimator (Gaussian noise of 30% on every pass) is judged light; a
    /// heavy-tailed one (a pass finds the light with probability 2% and then carries 50
    /// times the pixel's mean, Pareto-distributed with index 1.5) is not predictable. Fixed
    /// seeds, the pilot's size (8192 pixels, 4 passes).
    #[test]
    fn heavy_tailed_pilots_are_flagged_and_light_ones_are_not() {
        let mut rng = Rng::new(0x7a11_5eed);
        let light = pilot(&mut rng, 8192, 4, |r| (1.0 + 0.3 * r.normal()).max(0.0));
        let t = Tails::measure(&light, 4).unwrap();
        assert_eq!(t.verdict().0, TailClass::Light, "{t:?}");
        assert!(t.tail_index.unwrap() > ALPHA_HEAVY, "{t:?}");
        assert!((t.variance_growth.unwrap() - 1.0).abs() < 0.1, "{t:?}");
        assert!(t.top_share < 0.15, "{t:?}");

        let heavy = pilot(&mut rng, 8192, 4, |r| {
            if r.uniform() < 0.02 {
                // Pareto with index 1.5 and mean 50: x_m alpha / (alpha - 1) = 50.
                let u = 1.0 - r.uniform();
                50.0 / 3.0 * u.powf(-1.0 / 1.5)
            } else {
                0.0
            }
        });
        let t = Tails::measure(&heavy, 4).unwrap();
        let (class, reason) = t.verdict();
        assert_eq!(class, TailClass::Unpredictable, "{t:?}");
        assert!(reason
            .unwrap()
            .starts_with("not predictable from the pilot"));
        assert!(t.variance_growth.unwrap() > GROWTH_UNPREDICTABLE, "{t:?}");
        // A firefly is at most (P - 1) / P of its own pixel's squared deviations, and 2%
        // of the values are fireflies: the brightest 1% hold about a third of the sum,
        // against Gaussian noise's tenth.
        assert!(t.top_share > 0.25, "{t:?}");
    }

    /// Hill's estimator recovers a Pareto index, and a pure exponential tail reads light.
    #[test]
    fn hill_recovers_a_pareto_index() {
        let mut rng = Rng::new(0x0411_1975);
        for alpha in [1.0, 1.5, 3.0] {
            let mut y: Vec<f64> = (0..40_000)
                .map(|_| (1.0 - rng.uniform()).powf(-1.0 / alpha))
                .collect();
            let a = hill(&mut y, 200).unwrap();
            // k = 200: Hill's standard error is alpha / sqrt(k), 7%.
            assert!((a / alpha - 1.0).abs() < 0.25, "alpha {alpha}: {a}");
        }
        let mut e: Vec<f64> = (0..40_000).map(|_| -(1.0 - rng.uniform()).ln()).collect();
        assert!(hill(&mut e, 200).unwrap() > ALPHA_HEAVY);
    }

    /// No light, too few passes or a non-finite value: nothing measured, no panic.
    #[test]
    fn degenerate_pilots_measure_nothing() {
        assert_eq!(Tails::measure(&[0.0; 64], 4), None);
        assert_eq!(Tails::measure(&[1.0; 64], 2), None);
        assert_eq!(Tails::measure(&[1.0, f64::NAN, 1.0, 1.0], 4), None);
        assert_eq!(Tails::measure(&[], 4), None);
        // Constant values: no error anywhere, light.
        let t = Tails::measure(&[1.0; 64], 4).unwrap();
        assert_eq!(t.variance_growth, None);
        assert_eq!(t.verdict().0, TailClass::Light);
    }
}
