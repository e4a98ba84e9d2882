//! Chi-squared goodness-of-fit harness for sampling routines (test-only).
//!
//! Statistical software testing as in Marschner, CS 6630 notes, section 2 ("Chi-squared test"): divide the domain into
//! bins, integrate the claimed pdf over each bin to get expected counts, draw many samples,
//! count them, and ask whether the differences are plausibly random. The design follows the
//! `chi2.py` harness of Mitsuba (Jakob et al.):
//!
//! - directions are binned in `(cos theta, phi)`, where bins of equal size have equal solid
//!   angle (`d omega = d cos(theta) d phi`, Archimedes' hat-box theorem), so no Jacobian is
//!   needed and bins near the poles are not starved;
//! - expected counts come from adaptive 2D Gauss–Legendre cubature of the pdf over each bin;
//! - bins with expected count below 5 are pooled (the chi-squared approximation of the
//!   multinomial needs roughly 5 expected per cell);
//! - the p-value is the regularized upper incomplete gamma function
//!   `Q(dof/2, statistic/2)`, implemented here (series + continued fraction, Numerical
//!   Recipes §6.2);
//! - a family of `k` tests run at family-wise significance `alpha` rejects one test when its
//!   p-value is below the Šidák threshold `1 - (1 - alpha)^(1/k)`.
//!
//! Invalid samples (`None`) are not an error: a sub-stochastic sampler must have a pdf that
//! integrates to the fraction of valid samples. They enter the statistic as one extra cell
//! whose expected probability is `1 - integral of the pdf over the binned region`, and are
//! also checked directly. Pdfs with delta components cannot be tested this way; callers skip
//! those.
//!
//! Samples come from a fixed-seed SplitMix64 stream, so every run is reproducible.

use glam::{Vec2, Vec3};

/// Minimum expected count per cell; cells below are pooled (Cochran's rule of thumb).
const MIN_EXPECTED: f64 = 5.0;
/// Fraction of samples allowed to land where the pdf is zero or not finite: rounding on the
/// boundary of a support (e.g. a microfacet normal exactly on the visible horizon) may put a
/// handful there, a real bug puts far more.
const ZERO_PDF_TOLERANCE: f64 = 1e-5;
/// Relative tolerance of the cubature of one bin.
const CUBATURE_REL_TOL: f64 = 1e-6;
/// Absolute tolerance (probability) of the cubature of one bin.
const CUBATURE_ABS_TOL: f64 = 1e-10;
/// Maximal subdivision depth of one bin (cells of 1/1024 of the bin side).
const CUBATURE_MAX_DEPTH: u32 = 10;
/// Levels of subdivision that are always done: an adaptive rule can be fooled when a jump of
/// the integrand clips a cell between the nodes of both of its estimates.
const CUBATURE_MIN_DEPTH: u32 = 2;
/// Slack on the total probability (cubature error near discontinuities).
const INTEGRAL_TOLERANCE: f64 = 1e-3;

/// Settings of one chi-squared test.
#[derive(Clone, Debug)]
pub struct Chi2Config {
    /// Number of bins along the first coordinate: `cos theta` on the sphere, `x` on the plane.
    pub theta_bins: usize,
    /// Number of bins along the second coordinate: `phi` on the sphere, `y` on the plane.
    pub phi_bins: usize,
    /// Number of samples drawn.
    pub samples: usize,
    /// Base seed of the sample stream; the test name is hashed into it so that the tests of
    /// one family draw independent streams (Šidák's correction assumes independent tests).
    pub seed: u64,
    /// Family-wise significance level, e.g. 0.01: the probability that a correct family of
    /// samplers has any test rejected.
    pub significance: f64,
    /// Number of tests in the family, for the Šidák correction.
    pub tests_in_family: usize,
}

impl Chi2Config {
    /// Defaults for a family of `tests_in_family` tests: 40 x 80 bins, one million samples,
    /// family-wise significance 0.01.
    pub fn new(tests_in_family: usize) -> Self {
        Chi2Config {
            theta_bins: 40,
            phi_bins: 80,
            samples: 1_000_000,
            seed: 0x7e55_e7a0_c41c_5eed,
            significance: 0.01,
            tests_in_family,
        }
    }

    /// Šidák-corrected significance of a single test: `1 - (1 - alpha)^(1/k)`, so that
    /// `k` independent tests of correct samplers all pass with probability `1 - alpha`.
    pub fn single_test_significance(&self) -> f64 {
        let k = self.tests_in_family.max(1) as f64;
        // 1 - (1 - a)^(1/k) = -expm1(ln(1 - a) / k), without cancellation for small a.
        -((-self.significance).ln_1p() / k).exp_m1()
    }
}

/// Outcome of a chi-squared test.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Chi2Report {
    /// Pearson's statistic `sum (observed - expected)^2 / expected` over the (pooled) cells.
    pub statistic: f64,
    /// Degrees of freedom: number of cells minus one (the counts sum to the sample count).
    pub dof: usize,
    /// Probability of a statistic at least this large if the pdf is right.
    pub p_value: f64,
}

/// Tests a sampler of directions on the unit sphere against its solid-angle pdf.
///
/// `sample(u2, u1)` maps uniform random numbers to a unit direction, or `None` for an
/// invalid sample; `pdf(direction)` is the density with respect to solid angle. Bins are
/// `theta_bins` equal intervals of `cos theta` in `[-1, 1]` times `phi_bins` of `phi`.
/// Put discontinuities of the pdf on bin edges where possible (e.g. an even `theta_bins` for
/// hemispherical pdfs); elsewhere the adaptive cubature resolves them.
pub fn chi2_sphere(
    name: &str,
    cfg: &Chi2Config,
    sample: impl FnMut(Vec2, f32) -> Option<Vec3>,
    pdf: impl Fn(Vec3) -> f32,
) -> Result<Chi2Report, String> {
    chi2_sphere_cap(name, cfg, -1.0, sample, pdf)
}

/// Like [`chi2_sphere`] but the bins cover only the cap `cos theta >= cos_min`, for
/// concentrated lobes (narrow cones, high Phong exponents, small GGX roughness) whose
/// structure would otherwise fall into a single bin. Valid samples outside the cap join the
/// `None` samples in one cell whose expected probability is one minus the integral of the pdf
/// over the cap; the pdf is also integrated over the rest of the sphere for the total-mass
/// checks.
pub fn chi2_sphere_cap(
    name: &str,
    cfg: &Chi2Config,
    cos_min: f64,
    mut sample: impl FnMut(Vec2, f32) -> Option<Vec3>,
    pdf: impl Fn(Vec3) -> f32,
) -> Result<Chi2Report, String> {
    use std::f64::consts::PI;
    let dir = |z: f64, phi: f64| {
        let r = (1.0 - z * z).max(0.0).sqrt();
        Vec3::new((r * phi.cos()) as f32, (r * phi.sin()) as f32, z as f32)
    };
    // (cos theta, phi) coordinates: d omega = d(cos theta) d(phi), so the solid-angle pdf is
    // also the density in these coordinates.
    let density = |z: f64, phi: f64| pdf(dir(z, phi)) as f64;
    let lo = [cos_min, -PI];
    let hi = [1.0, PI];
    let rest = if cos_min > -1.0 {
        integrate_grid(
            &density,
            [-1.0, -PI],
            [cos_min, PI],
            cfg.theta_bins,
            cfg.phi_bins,
        )
        .iter()
        .sum()
    } else {
        0.0
    };
    run(
        name,
        cfg,
        Domain { lo, hi, rest },
        |u2, u1| match sample(u2, u1) {
            None => Ok(None),
            Some(d) => {
                if !d.is_finite() || (d.length() - 1.0).abs() > 1e-3 {
                    return Err(format!(
                        "sample {d:?} is not a unit vector (u = {u2:?}, {u1})"
                    ));
                }
                let z = (d.z as f64).clamp(-1.0, 1.0);
                let phi = (d.y as f64).atan2(d.x as f64);
                Ok(Some(([z, phi], pdf(d) as f64)))
            }
        },
        density,
    )
}

/// Tests a sampler of points in the plane against its area pdf, binning
/// `theta_bins x phi_bins` cells over `bounds = (min, max)`, which must contain every valid
/// sample (for the unit disk `(-1, -1)..(1, 1)`, for barycentrics `(0, 0)..(1, 1)`).
pub fn chi2_plane(
    name: &str,
    cfg: &Chi2Config,
    bounds: (Vec2, Vec2),
    mut sample: impl FnMut(Vec2, f32) -> Option<Vec2>,
    pdf: impl Fn(Vec2) -> f32,
) -> Result<Chi2Report, String> {
    let lo = [bounds.0.x as f64, bounds.0.y as f64];
    let hi = [bounds.1.x as f64, bounds.1.y as f64];
    run(
        name,
        cfg,
        Domain { lo, hi, rest: 0.0 },
        |u2, u1| match sample(u2, u1) {
            None => Ok(None),
            Some(p) => {
                let (x, y) = (p.x as f64, p.y as f64);
                if !p.is_finite() || x < lo[0] || x > hi[0] || y < lo[1] || y > hi[1] {
                    return Err(format!(
                        "sample {p:?} outside the bounds (u = {u2:?}, {u1})"
                    ));
                }
                Ok(Some(([x, y], pdf(p) as f64)))
            }
        },
        |x, y| pdf(Vec2::new(x as f32, y as f32)) as f64,
    )
}

/// The binned rectangle and the probability the pdf puts outside it.
struct Domain {
    lo: [f64; 2],
    hi: [f64; 2],
    /// Integral of the pdf over the part of the domain that is not binned.
    rest: f64,
}

/// A mapped sample: `None` when invalid, else its coordinates and the pdf there.
type Mapped = Option<([f64; 2], f64)>;

fn run(
    name: &str,
    cfg: &Chi2Config,
    domain: Domain,
    mut sample: impl FnMut(Vec2, f32) -> Result<Mapped, String>,
    density: impl Fn(f64, f64) -> f64,
) -> Result<Chi2Report, String> {
    let fail = |msg: String| {
        let msg = format!("chi2 {name}: {msg}");
        eprintln!("{msg}");
        Err(msg)
    };
    let (nx, ny) = (cfg.theta_bins, cfg.phi_bins);
    if nx == 0 || ny == 0 || cfg.samples == 0 {
        return fail("empty configuration".into());
    }
    let Domain { lo, hi, rest } = domain;
    let span = [hi[0] - lo[0], hi[1] - lo[1]];

    // Observed counts; the last cell collects invalid samples and valid ones outside the
    // binned region.
    let mut observed = vec![0u64; nx * ny + 1];
    let mut invalid = 0u64;
    let mut zero_pdf = 0u64;
    let mut rng = SplitMix64::new(cfg.seed ^ fnv1a(name));
    for _ in 0..cfg.samples {
        let u2 = Vec2::new(rng.next_f32(), rng.next_f32());
        let u1 = rng.next_f32();
        match sample(u2, u1) {
            Err(msg) => return fail(msg),
            Ok(None) => {
                invalid += 1;
                observed[nx * ny] += 1;
            }
            Ok(Some(([x, y], p))) => {
                if !(p > 0.0 && p.is_finite()) {
                    zero_pdf += 1;
                }
                if x < lo[0] || x > hi[0] || y < lo[1] || y > hi[1] {
                    observed[nx * ny] += 1;
                    continue;
                }
                let ix = (((x - lo[0]) / span[0] * nx as f64) as usize).min(nx - 1);
                let iy = (((y - lo[1]) / span[1] * ny as f64) as usize).min(ny - 1);
                observed[ix * ny + iy] += 1;
            }
        }
    }
    let n = cfg.samples as f64;
    if zero_pdf as f64 > ZERO_PDF_TOLERANCE * n {
        return fail(format!(
            "{zero_pdf} of {} samples have pdf zero or not finite",
            cfg.samples
        ));
    }

    // Expected probabilities.
    let mut prob = integrate_grid(&density, lo, hi, nx, ny);
    if let Some(bad) = prob.iter().find(|p| !(p.is_finite() && **p >= 0.0)) {
        return fail(format!("pdf integrates to {bad} over a bin"));
    }
    let binned: f64 = prob.iter().sum();
    let total = binned + rest;
    if total > 1.0 + INTEGRAL_TOLERANCE {
        return fail(format!("pdf integrates to {total} > 1"));
    }
    // The fraction of valid samples must equal the total probability (a sub-stochastic
    // sampler's missing mass is its fraction of invalid samples); five binomial standard
    // errors plus the cubature slack.
    let valid = (n - invalid as f64) / n;
    let sigma = (total.clamp(0.0, 1.0) * (1.0 - total.clamp(0.0, 1.0)) / n).sqrt();
    if (valid - total).abs() > 5.0 * sigma + INTEGRAL_TOLERANCE {
        return fail(format!(
            "fraction of valid samples {valid:.6} differs from the integral of the pdf {total:.6}"
        ));
    }
    prob.push((1.0 - binned).max(0.0));

    // Pearson's statistic with pooling of small cells (Mitsuba's chi2.py): visit cells by
    // increasing expected count; cells below MIN_EXPECTED accumulate in a pool, and the pool
    // keeps absorbing cells until it reaches MIN_EXPECTED itself.
    let mut order: Vec<usize> = (0..prob.len()).collect();
    order.sort_by(|&a, &b| prob[a].total_cmp(&prob[b]));
    let (mut statistic, mut cells) = (0.0f64, 0usize);
    let (mut pool_obs, mut pool_exp, mut pooled) = (0.0f64, 0.0f64, 0usize);
    for i in order {
        let exp = prob[i] * n;
        let obs = observed[i] as f64;
        if exp < MIN_EXPECTED || (pooled > 0 && pool_exp < MIN_EXPECTED) {
            // Cells with nothing expected and nothing observed carry no information.
            if exp > 0.0 || obs > 0.0 {
                pool_obs += obs;
                pool_exp += exp;
                pooled += 1;
            }
        } else {
            statistic += (obs - exp) * (obs - exp) / exp;
            cells += 1;
        }
    }
    if pooled > 0 {
        if pool_exp <= 0.0 {
            return fail(format!(
                "{pool_obs} samples fell where the pdf integrates to zero"
            ));
        }
        statistic += (pool_obs - pool_exp) * (pool_obs - pool_exp) / pool_exp;
        cells += 1;
    }
    if cells < 2 {
        return fail("fewer than two cells with enough expected samples; refine the bins".into());
    }
    let dof = cells - 1;
    let p_value = chi2_survival(statistic, dof);
    let report = Chi2Report {
        statistic,
        dof,
        p_value,
    };
    let threshold = cfg.single_test_significance();
    let line = format!(
        "chi2 {name}: statistic {statistic:.2}, dof {dof}, p {p_value:.4} (reject below {threshold:.2e}); \
         valid {valid:.6}, pdf mass {total:.6}"
    );
    eprintln!("{line}");
    if p_value < threshold {
        return Err(format!("{line}: rejected"));
    }
    Ok(report)
}

/// Probabilities of the `nx x ny` grid cells of the rectangle `lo..hi` under `density`.
fn integrate_grid(
    density: &impl Fn(f64, f64) -> f64,
    lo: [f64; 2],
    hi: [f64; 2],
    nx: usize,
    ny: usize,
) -> Vec<f64> {
    let dx = (hi[0] - lo[0]) / nx as f64;
    let dy = (hi[1] - lo[1]) / ny as f64;
    let mut out = Vec::with_capacity(nx * ny);
    for ix in 0..nx {
        let (x0, x1) = (lo[0] + ix as f64 * dx, lo[0] + (ix + 1) as f64 * dx);
        for iy in 0..ny {
            let (y0, y1) = (lo[1] + iy as f64 * dy, lo[1] + (iy + 1) as f64 * dy);
            let whole = gauss_legendre_cell(density, x0, x1, y0, y1);
            out.push(adaptive_cell(
                density,
                [x0, x1, y0, y1],
                whole,
                CUBATURE_ABS_TOL,
                CUBATURE_MAX_DEPTH,
            ));
        }
    }
    out
}

/// Nodes and weights of 4-point Gauss–Legendre quadrature on `[0, 1]`.
///
/// Gauss–Legendre rather than Simpson: the nodes are interior, so a jump of the pdf exactly
/// on a bin edge (hemisphere boundary, cone boundary on a grid line) costs no accuracy, and
/// the rule is exact for polynomials of degree 7 in each coordinate.
const GL4: [(f64, f64); 4] = {
    // Nodes (1 +- sqrt(3/7 -+ 2/7 sqrt(6/5))) / 2, weights (18 +- sqrt 30) / 72.
    const A: f64 = 0.069_431_844_202_973_71;
    const B: f64 = 0.330_009_478_207_571_87;
    const WA: f64 = 0.173_927_422_568_726_93;
    const WB: f64 = 0.326_072_577_431_273_07;
    [(A, WA), (B, WB), (1.0 - B, WB), (1.0 - A, WA)]
};

/// Tensor-product 4x4 Gauss–Legendre estimate of the integral over a rectangle.
fn gauss_legendre_cell(f: &impl Fn(f64, f64) -> f64, x0: f64, x1: f64, y0: f64, y1: f64) -> f64 {
    let (dx, dy) = (x1 - x0, y1 - y0);
    let mut sum = 0.0;
    for (sx, wx) in GL4 {
        for (sy, wy) in GL4 {
            sum += wx * wy * f(x0 + sx * dx, y0 + sy * dy);
        }
    }
    sum * dx * dy
}

/// Adaptive cubature: compare the estimate of a cell with the sum of the estimates of its
/// four quadrants and recurse where they disagree (discontinuities, sharp peaks).
fn adaptive_cell(
    f: &impl Fn(f64, f64) -> f64,
    [x0, x1, y0, y1]: [f64; 4],
    whole: f64,
    abs_tol: f64,
    depth: u32,
) -> f64 {
    let (xm, ym) = (0.5 * (x0 + x1), 0.5 * (y0 + y1));
    let quads = [
        [x0, xm, y0, ym],
        [xm, x1, y0, ym],
        [x0, xm, ym, y1],
        [xm, x1, ym, y1],
    ];
    let parts = quads.map(|[a, b, c, d]| gauss_legendre_cell(f, a, b, c, d));
    let sum: f64 = parts.iter().sum();
    let forced = depth > CUBATURE_MAX_DEPTH - CUBATURE_MIN_DEPTH;
    let converged = (sum - whole).abs() <= abs_tol.max(CUBATURE_REL_TOL * sum.abs());
    if depth == 0 || (converged && !forced) {
        return sum;
    }
    quads
        .iter()
        .zip(parts)
        .map(|(q, p)| adaptive_cell(f, *q, p, 0.5 * abs_tol, depth - 1))
        .sum()
}

/// Survival function of the chi-squared distribution with `dof` degrees of freedom:
/// `P(X >= statistic) = Q(dof / 2, statistic / 2)`.
pub fn chi2_survival(statistic: f64, dof: usize) -> f64 {
    gamma_q(0.5 * dof as f64, 0.5 * statistic)
}

/// Regularized upper incomplete gamma function `Q(a, x) = Gamma(a, x) / Gamma(a)` for
/// `a > 0`, `x >= 0` (Numerical Recipes §6.2 `gammq`): the series of `P = 1 - Q` converges
/// fast for `x < a + 1`, Legendre's continued fraction for `Q` (modified Lentz) otherwise.
pub fn gamma_q(a: f64, x: f64) -> f64 {
    assert!(a > 0.0 && x >= 0.0, "gamma_q({a}, {x})");
    if x == 0.0 {
        1.0
    } else if x < a + 1.0 {
        1.0 - gamma_p_series(a, x)
    } else {
        gamma_q_continued_fraction(a, x)
    }
}

/// `x^a e^-x / Gamma(a)`, the common prefactor of both expansions, in logarithms.
fn gamma_prefactor(a: f64, x: f64) -> f64 {
    (a * x.ln() - x - ln_gamma(a)).exp()
}

/// `P(a, x) = x^a e^-x / Gamma(a) * sum_n x^n / (a (a+1) ... (a+n))`.
fn gamma_p_series(a: f64, x: f64) -> f64 {
    let (mut ap, mut term) = (a, 1.0 / a);
    let mut sum = term;
    // Terms shrink like exp(-n^2 / 2a) once n exceeds x - a, so ~sqrt(a) terms are needed.
    for _ in 0..100_000 {
        ap += 1.0;
        term *= x / ap;
        sum += term;
        if term.abs() < sum.abs() * 1e-16 {
            break;
        }
    }
    sum * gamma_prefactor(a, x)
}

/// `Q(a, x) = x^a e^-x / Gamma(a) * 1 / (x + 1 - a - 1 (1 - a) / (x + 3 - a - ...))`.
fn gamma_q_continued_fraction(a: f64, x: f64) -> f64 {
    const TINY: f64 = 1e-300;
    let mut b = x + 1.0 - a;
    let mut c = 1.0 / TINY;
    let mut d = 1.0 / b;
    let mut h = d;
    for i in 1..100_000 {
        let an = -(i as f64) * (i as f64 - a);
        b += 2.0;
        d = an * d + b;
        if d.abs() < TINY {
            d = TINY;
        }
        c = b + an / c;
        if c.abs() < TINY {
            c = TINY;
        }
        d = 1.0 / d;
        let delta = d * c;
        h *= delta;
        if (delta - 1.0).abs() < 1e-16 {
            break;
        }
    }
    gamma_prefactor(a, x) * h
}

/// `ln Gamma(x)` for `x > 0` by the Lanczos approximation (g = 7, 9 terms; relative error
/// about 1e-15), with the reflection formula below 1/2.
pub fn ln_gamma(x: f64) -> f64 {
    use std::f64::consts::PI;
    const G: f64 = 7.0;
    const C: [f64; 9] = [
        0.999_999_999_999_809_9,
        676.520_368_121_885_1,
        -1_259.139_216_722_402_8,
        771.323_428_777_653_1,
        -176.615_029_162_140_6,
        12.507_343_278_686_905,
        -0.138_571_095_265_720_12,
        9.984_369_578_019_572e-6,
        1.505_632_735_149_311_6e-7,
    ];
    if x < 0.5 {
        // Gamma(x) Gamma(1 - x) = pi / sin(pi x).
        return (PI / (PI * x).sin()).ln() - ln_gamma(1.0 - x);
    }
    let x = x - 1.0;
    let mut s = C[0];
    for (i, c) in C.iter().enumerate().skip(1) {
        s += c / (x + i as f64);
    }
    let t = x + G + 0.5;
    0.5 * (2.0 * PI).ln() + (x + 0.5) * t.ln() - t + s.ln()
}

/// SplitMix64 (Steele, Lea & Flood 2014): a tiny, fast, statistically solid generator whose
/// whole state is one `u64`, so a seed reproduces the stream exactly.
#[derive(Clone, Debug)]
pub struct SplitMix64(u64);

impl SplitMix64 {
    /// A generator starting from `seed`.
    pub fn new(seed: u64) -> Self {
        SplitMix64(seed)
    }

    /// The next 64 uniform bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        crate::sampling::hash_u64(self.0)
    }

    /// A uniform `f32` in `[0, 1)` on the grid of multiples of `2^-24`.
    pub fn next_f32(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 * (1.0 / 16_777_216.0)
    }
}

/// FNV-1a hash of a test name, to give each test of a family its own sample stream.
fn fnv1a(s: &str) -> u64 {
    s.bytes().fold(0xcbf2_9ce4_8422_2325, |h, b| {
        (h ^ b as u64).wrapping_mul(0x0000_0100_0000_01b3)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64, tol: f64) -> bool {
        (a - b).abs() <= tol * b.abs().max(1e-300)
    }

    #[test]
    fn ln_gamma_known_values() {
        let pi = std::f64::consts::PI;
        assert!(close(ln_gamma(0.5), 0.5 * pi.ln(), 1e-14));
        assert!(close(ln_gamma(1.0).exp(), 1.0, 1e-14));
        assert!(close(ln_gamma(10.0), 362_880f64.ln(), 1e-14));
        assert!(close(ln_gamma(0.1), 2.252_712_651_734_206, 1e-13));
        // Stirling regime: ln Gamma(1001) = ln(1000!).
        let ln_fact: f64 = (1..=1000).map(|k| (k as f64).ln()).sum();
        assert!(close(ln_gamma(1001.0), ln_fact, 1e-13));
    }

    #[test]
    fn gamma_q_known_values() {
        // Q(1, x) = e^-x; Q(1/2, x) = erfc(sqrt x).
        for x in [0.01, 0.5, 1.0, 3.0, 20.0] {
            assert!(close(gamma_q(1.0, x), (-x).exp(), 1e-13), "x = {x}");
        }
        assert!(close(gamma_q(0.5, 1.0), 0.157_299_207_050_285_13, 1e-13));
        // Integer a: Q(a, x) = e^-x sum_{k<a} x^k / k! (both branches: x < a + 1 and beyond).
        for (a, x) in [(3u32, 2.0), (3, 9.0), (50, 40.0), (50, 60.0)] {
            let (mut term, mut sum) = (1.0f64, 0.0f64);
            for k in 0..a {
                if k > 0 {
                    term *= x / k as f64;
                }
                sum += term;
            }
            let exact = (-x).exp() * sum;
            assert!(close(gamma_q(a as f64, x), exact, 1e-12), "Q({a}, {x})");
        }
        // Reference values computed with mpmath at 30 digits.
        for (a, x, q) in [
            (2.5, 0.3, 0.988_003_242_794_093_7),
            (2.5, 7.0, 0.015_609_416_100_266_915),
            (1600.0, 1500.0, 0.994_546_917_701_168_9),
            (1600.0, 1700.0, 0.006_985_121_109_730_868),
        ] {
            assert!(close(gamma_q(a, x), q, 1e-10), "Q({a}, {x})");
        }
        // Textbook chi-squared critical values at p = 0.05.
        for (dof, x) in [
            (1usize, 3.841_458_820_694_124),
            (10, 18.307_038_053_275_146),
            (100, 124.342_113_404_004_07),
            (1000, 1_074.679_448_803_441),
        ] {
            assert!(close(chi2_survival(x, dof), 0.05, 1e-10), "dof {dof}");
        }
    }

    #[test]
    fn sidak_threshold() {
        let cfg = Chi2Config::new(20);
        let a = cfg.single_test_significance();
        assert!(close(1.0 - (1.0 - a).powi(20), 0.01, 1e-12));
        assert!(close(
            Chi2Config::new(1).single_test_significance(),
            0.01,
            1e-12
        ));
    }

    #[test]
    fn cubature_is_accurate() {
        let total = |f: &dyn Fn(f64, f64) -> f64, n: usize| {
            integrate_grid(&f, [0.0, 0.0], [1.0, 1.0], n, n + 2)
                .iter()
                .sum::<f64>()
        };
        // Smooth: 4-point Gauss-Legendre is exact for this polynomial.
        assert!(close(total(&|x, y| 4.0 * x * y, 3), 1.0, 1e-13));
        // A disk of radius 1/2 cutting through bins: area pi / 4. The jump is resolved by
        // subdivision; on coarse bins a little of the boundary escapes every node, on bins
        // the size the chi-squared tests use the error is far below one count in 1e6.
        let disk = |x: f64, y: f64| {
            if (x - 0.5).powi(2) + (y - 0.5).powi(2) < 0.25 {
                1.0
            } else {
                0.0
            }
        };
        let quarter_pi = std::f64::consts::PI / 4.0;
        assert!(close(total(&disk, 3), quarter_pi, 1e-3));
        assert!(close(total(&disk, 40), quarter_pi, 1e-5));
    }

    #[test]
    fn uniform_sphere_passes_and_wrong_pdf_fails() {
        // Self-test of the harness on the simplest case; warp.rs holds the real family.
        let mut cfg = Chi2Config::new(1);
        cfg.samples = 200_000;
        cfg.theta_bins = 10;
        cfg.phi_bins = 20;
        let sphere = |u: Vec2, _: f32| {
            let z = 1.0 - 2.0 * u.x;
            let r = (1.0 - z * z).max(0.0).sqrt();
            let phi = std::f32::consts::TAU * u.y;
            Some(Vec3::new(r * phi.cos(), r * phi.sin(), z))
        };
        let uniform = |_: Vec3| 0.25 * std::f32::consts::FRAC_1_PI;
        assert!(chi2_sphere("self uniform", &cfg, sphere, uniform).is_ok());
        let tilted = |d: Vec3| (1.0 + 0.1 * d.z) * 0.25 * std::f32::consts::FRAC_1_PI;
        let err = chi2_sphere("self tilted", &cfg, sphere, tilted).unwrap_err();
        assert!(err.contains("rejected"), "{err}");
        // Sub-stochastic sampler whose pdf claims full mass.
        let lossy = |u: Vec2, v: f32| {
            if v < 0.1 {
                None
            } else {
                sphere(u, v)
            }
        };
        let err = chi2_sphere("self lossy", &cfg, lossy, uniform).unwrap_err();
        assert!(err.contains("valid"), "{err}");
        // ... and the same with a pdf that accounts for the loss passes.
        let ok = chi2_sphere(
            "self lossy ok",
            &cfg,
            |u, v| if v < 0.1 { None } else { sphere(u, v) },
            |d| 0.9 * uniform(d),
        );
        assert!(ok.is_ok(), "{ok:?}");
    }
}
