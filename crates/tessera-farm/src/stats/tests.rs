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
    let of = |pixels: &[Option<(f64, f64)>]| image_relative_error(4, 3, |x, y| pixels[y * 4 + x]);
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
            (y.saturating_sub(1)..(y + 2).min(h))
                .flat_map(move |qy| (x.saturating_sub(1)..(x + 2).min(w)).map(move |qx| (qx, qy)))
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
    let pooled = image_relative_error_pooled(w, h, |x, y| Some((mean(x, y), var(x, y), k(x, y))));
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
    let pooled_spread = image_relative_error_pooled(w, h, |x, y| px(x, y).map(|p| (p.0, p.1, p.2)));
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
