//! Tests of the BSDFs against the sampling contract of [`super`].
//!
//! - **Chi-squared** (Marschner, CS 6630 notes, section 2): the directions produced by [`Bsdf::sample`] must be
//!   distributed with the density [`Bsdf::pdf`] claims, for every lobe with a density, at
//!   several incident angles. All cases form one family with a Šidák correction; negative
//!   controls show that a slightly wrong pdf is rejected at the same threshold. The bins
//!   live on a square mapped smoothly onto the hemisphere (see "The bins" below).
//! - **Consistency**: the sample weight is `eval / pdf` (the estimator `f cos / p` is then
//!   unbiased whatever the sampling strategy), and `pdf > 0` wherever `eval > 0` (otherwise
//!   some light could never be found by BSDF sampling).
//! - **Energy**: the directional albedo `∫ f cos dωi = E[weight]` is at most one.
//! - **Reciprocity** (Helmholtz): `f(wo, wi) = f(wi, wo)`.
//! - **Delta lobes**: mirror directions, the Fresnel split of glass, Snell's law, total
//!   internal reflection and the radiance scaling `1/η²` of refraction.

use super::diffuse::Diffuse;
use super::microfacet::{Conductor, GltfDielectric};
use super::phong::Phong;
use super::specular::{Glass, Mirror};
use super::{fresnel_dielectric, fresnel_schlick, Bsdf, Lobe};
use crate::chi2::{chi2_plane, Chi2Config, Chi2Report, SplitMix64};
use crate::sampling::warp::{square_to_cosine_hemisphere, square_to_uniform_sphere, Frame};
use glam::{DVec3, Vec2, Vec3};
use std::f64::consts::PI;

// ---------------------------------------------------------------------------------------
// Materials and directions
// ---------------------------------------------------------------------------------------

/// Incident angles (degrees from the normal) at which every lobe is tested: normal, oblique
/// and grazing incidence.
const ANGLES: [f32; 3] = [0.0, 40.0, 75.0];

/// A unit direction at `theta_deg` from the normal, at an azimuth off the x and y axes so
/// that no test relies on a symmetry of the frame; `below` puts it under the surface.
fn dir(theta_deg: f32, below: bool) -> Vec3 {
    let (s, c) = theta_deg.to_radians().sin_cos();
    let z = if below { -c } else { c };
    Vec3::new(0.6 * s, 0.8 * s, z).normalize()
}

/// Mirror direction of `w` about the normal (the centre of the specular lobes).
fn mirror(w: Vec3) -> Vec3 {
    Vec3::new(-w.x, -w.y, w.z)
}

fn diffuse(albedo: f32) -> Lobe {
    Lobe::Diffuse(Diffuse {
        albedo: Vec3::splat(albedo),
    })
}

fn phong(kd: f32, ks: f32, exponent: f32) -> Lobe {
    Lobe::Phong(Phong {
        kd: Vec3::splat(kd),
        ks: Vec3::splat(ks),
        exponent,
    })
}

/// Gold-like reflectance at normal incidence (coloured, to exercise all channels).
const GOLD: Vec3 = Vec3::new(1.0, 0.78, 0.34);

fn conductor(f0: Vec3, alpha: f32) -> Lobe {
    Lobe::Conductor(Conductor { f0, alpha })
}

fn gltf(base: f32, alpha: f32) -> Lobe {
    gltf_specular(base, alpha, 1.0)
}

/// The glTF dielectric with a KHR_materials_specular factor.
fn gltf_specular(base: f32, alpha: f32, specular: f32) -> Lobe {
    Lobe::GltfDielectric(GltfDielectric {
        base: Vec3::splat(base),
        alpha,
        f0: 0.04,
        specular,
    })
}

/// `cos` of a cone about the mirror direction holding all but ~1e-3 of a Phong lobe of
/// exponent `n`: `P(cos α > c) = 1 - c^(n + 1)`.
fn phong_cap(n: f32) -> f32 {
    1e-3f32.powf(1.0 / (n + 1.0))
}

/// `cos` of a cone about the mirror direction holding ~90% of a GGX reflection lobe: the
/// normals with `tan θm < 3 α` carry `9/10` of `D cos θm`, and reflection doubles angles.
fn ggx_cap(alpha: f32) -> f32 {
    (2.0 * (3.0 * alpha).atan()).cos()
}

/// One BSDF at one incident direction.
#[derive(Clone)]
struct Case {
    name: String,
    bsdf: Bsdf,
    wo: Vec3,
    /// For lobes too narrow for hemisphere-wide bins: a cap `(axis, 1 - cos Θ)` about the
    /// mirror direction holding the peak, clipped at the horizon.
    cap: Option<(Vec3, f64)>,
}

impl Case {
    /// `lobe_cap` is the `cos` of the cone about the mirror direction holding the
    /// concentrated (specular) part of the BSDF, if any. Cones narrower than 70° get a
    /// second, cap-binned test that resolves the peak; the cap stops at the horizon, where
    /// the density jumps (a jump inside the bins costs the adaptive cubature its maximal
    /// depth along the whole curve).
    fn new(name: String, bsdf: Bsdf, wo: Vec3, lobe_cap: Option<f32>) -> Self {
        let axis = mirror(wo);
        let cap = lobe_cap
            .map(|c| (c as f64).acos())
            .filter(|&angle| angle < 70f64.to_radians())
            .map(|angle| {
                let elevation = (axis.z.abs() as f64).asin();
                (axis, 1.0 - angle.min(elevation).cos())
            });
        Case {
            name,
            bsdf,
            wo,
            cap,
        }
    }
}

/// Every non-delta BSDF of the tests, at every incident angle.
fn cases() -> Vec<Case> {
    let mut cases = Vec::new();
    let single = Bsdf::single;
    for theta in ANGLES {
        let wo = dir(theta, false);
        cases.push(Case::new(
            format!("diffuse wo {theta}"),
            single(diffuse(0.7)),
            wo,
            None,
        ));
        for (kd, ks) in [(0.3, 0.6), (0.0, 0.9)] {
            for n in [5.0, 50.0, 500.0] {
                cases.push(Case::new(
                    format!("phong kd {kd} ks {ks} n {n} wo {theta}"),
                    single(phong(kd, ks, n)),
                    wo,
                    Some(phong_cap(n)),
                ));
            }
        }
        for alpha in [0.05, 0.2, 0.6] {
            cases.push(Case::new(
                format!("conductor alpha {alpha} wo {theta}"),
                single(conductor(GOLD, alpha)),
                wo,
                Some(ggx_cap(alpha)),
            ));
        }
        for base in [0.5, 0.9] {
            for alpha in [0.05, 0.3, 0.8] {
                cases.push(Case::new(
                    format!("gltf base {base} alpha {alpha} wo {theta}"),
                    single(gltf(base, alpha)),
                    wo,
                    Some(ggx_cap(alpha)),
                ));
            }
        }
        // KHR_materials_specular: a weaker Fresnel layer shifts the lobe choice.
        cases.push(Case::new(
            format!("gltf base 0.5 alpha 0.3 specular 0.5 wo {theta}"),
            single(gltf_specular(0.5, 0.3, 0.5)),
            wo,
            Some(ggx_cap(0.3)),
        ));
        // Two and three lobes: the mixture pdf is the weighted sum (one-sample MIS).
        cases.push(Case::new(
            format!("mix conductor+gltf wo {theta}"),
            Bsdf::mixture(&[(conductor(GOLD, 0.2), 0.6), (gltf(0.5, 0.4), 0.4)]),
            wo,
            None,
        ));
        cases.push(Case::new(
            format!("mix phong+conductor+diffuse wo {theta}"),
            Bsdf::mixture(&[
                (phong(0.2, 0.5, 20.0), 0.3),
                (conductor(GOLD, 0.3), 0.5),
                (diffuse(0.8), 0.2),
            ]),
            wo,
            None,
        ));
    }
    // Opaque lobes are two-sided: seen from below, the frame is mirrored.
    let below = dir(40.0, true);
    cases.push(Case::new(
        "diffuse wo below".into(),
        Bsdf::single(diffuse(0.7)),
        below,
        None,
    ));
    cases.push(Case::new(
        "phong kd 0.3 ks 0.6 n 50 wo below".into(),
        Bsdf::single(phong(0.3, 0.6, 50.0)),
        below,
        Some(phong_cap(50.0)),
    ));
    cases.push(Case::new(
        "conductor alpha 0.2 wo below".into(),
        Bsdf::single(conductor(GOLD, 0.2)),
        below,
        Some(ggx_cap(0.2)),
    ));
    cases.push(Case::new(
        "gltf base 0.5 alpha 0.3 wo below".into(),
        Bsdf::single(gltf(0.5, 0.3)),
        below,
        None,
    ));
    cases.push(Case::new(
        "mix phong+conductor+diffuse wo below".into(),
        Bsdf::mixture(&[
            (phong(0.2, 0.5, 20.0), 0.3),
            (conductor(GOLD, 0.3), 0.5),
            (diffuse(0.8), 0.2),
        ]),
        below,
        None,
    ));
    // A mixture with a delta lobe: the mirror samples are not in the density (the harness
    // sees them as invalid), so the pdf integrates to the diffuse weight 0.6.
    for theta in [0.0, 40.0] {
        cases.push(Case::new(
            format!("mix diffuse+mirror wo {theta}"),
            Bsdf::mixture(&[
                (diffuse(0.8), 0.6),
                (
                    Lobe::Mirror(Mirror {
                        reflectance: Vec3::splat(0.9),
                    }),
                    0.4,
                ),
            ]),
            dir(theta, false),
            None,
        ));
    }
    cases
}

// ---------------------------------------------------------------------------------------
// Chi-squared family
// ---------------------------------------------------------------------------------------

/// Chi-squared settings of the BSDF family: 16 x 16 bins on the square (below), 100k
/// samples (~390 expected per bin for a uniform density), so that ~90 tests run in a couple
/// of seconds on two cores.
fn family_config(tests_in_family: usize) -> Chi2Config {
    Chi2Config {
        theta_bins: 16,
        phi_bins: 16,
        samples: 100_000,
        ..Chi2Config::new(tests_in_family)
    }
}

// The bins. Every lobe here lives in one hemisphere (the side of `wo`), so directions are
// binned on a square mapped onto the hemisphere, or onto a cap `1 - cos θ <= h` about an
// axis, in two smooth steps:
//
// 1. Fong's elliptical grid map of the square [-1, 1]² onto the unit disk,
//    `(x, y) = (a sqrt(1 - b²/2), b sqrt(1 - a²/2))`: analytic inside, with the boundary on
//    the circle, and singular only at the four corners (points, which cost the cubature
//    nothing);
// 2. the equal-area lift of the disk onto the cap, `1 - cos θ = h r²` at the same azimuth
//    (Archimedes: `dω = 2h dx dy`).
//
// The harness's own (cos θ, φ) bins would do too, but the pole is a whole bin edge there,
// along which any density with a gradient across the pole (every oblique lobe) has a
// square-root singularity, and the adaptive cubature then runs to its maximal depth along
// it; on the square, the horizon is the boundary and nothing else is singular. The map
// only has to be a bijection with a known Jacobian: the density on the square is the
// solid-angle pdf times `2h |∂(x, y)/∂(a, b)|`.

/// Elliptical grid map of the square onto the unit disk.
fn square_to_disk(a: f64, b: f64) -> (f64, f64) {
    (
        a * (1.0 - 0.5 * b * b).sqrt(),
        b * (1.0 - 0.5 * a * a).sqrt(),
    )
}

/// Inverse of [`square_to_disk`] (Fong 2015, "Analytical methods for squaring the disc").
fn disk_to_square(x: f64, y: f64) -> (f64, f64) {
    let t = x * x - y * y;
    let r8 = 8f64.sqrt();
    let half_diff = |p: f64, q: f64| 0.5 * (p.max(0.0).sqrt() - q.max(0.0).sqrt());
    (
        half_diff(2.0 + t + r8 * x, 2.0 + t - r8 * x),
        half_diff(2.0 - t + r8 * y, 2.0 - t - r8 * y),
    )
}

/// `|∂(x, y)/∂(a, b)|` of [`square_to_disk`].
fn square_to_disk_jacobian(a: f64, b: f64) -> f64 {
    let sa = (1.0 - 0.5 * a * a).sqrt();
    let sb = (1.0 - 0.5 * b * b).sqrt();
    sa * sb - a * a * b * b / (4.0 * sa * sb)
}

/// The bins of one test: a frame whose `+z` is the cap's axis and the cap size `h`.
struct CapBins {
    s: DVec3,
    t: DVec3,
    n: DVec3,
    h: f64,
}

impl CapBins {
    fn new(axis: Vec3, h: f64) -> Self {
        let f = Frame::from_normal(axis);
        CapBins {
            s: f.s.as_dvec3(),
            t: f.t.as_dvec3(),
            n: f.n.as_dvec3(),
            h,
        }
    }

    /// The square point of a world direction, `None` outside the cap.
    fn to_square(&self, w: Vec3) -> Option<(f64, f64)> {
        let w = w.as_dvec3();
        let (x, y, z) = (w.dot(self.s), w.dot(self.t), w.dot(self.n));
        // 1 - cos θ = sin² θ / (1 + cos θ), accurate for narrow caps.
        let one_minus_cos = if z > 0.0 {
            (x * x + y * y) / (1.0 + z)
        } else {
            1.0 - z
        };
        if one_minus_cos > self.h {
            return None;
        }
        // Lift inverse: the disk point has radius sqrt((1 - cos θ) / h) at the same azimuth.
        let k = (self.h * (1.0 + z)).sqrt();
        let (a, b) = disk_to_square(x / k, y / k);
        // Rounding may put a point on the horizon a hair outside the square.
        Some((a.clamp(-1.0, 1.0), b.clamp(-1.0, 1.0)))
    }

    /// The world direction of a square point and the Jacobian `dω / (da db)`.
    fn to_world(&self, a: f64, b: f64) -> (DVec3, f64) {
        let (x, y) = square_to_disk(a, b);
        let r2 = (x * x + y * y).min(1.0);
        let one_minus_cos = self.h * r2;
        let k = (self.h * (2.0 - one_minus_cos)).sqrt();
        let w = self.s * (x * k) + self.t * (y * k) + self.n * (1.0 - one_minus_cos);
        (w, 2.0 * self.h * square_to_disk_jacobian(a, b))
    }
}

/// Chi-squared test of sampling `bsdf` at `wo` against `pdf` (a density of world
/// directions, evaluated in f64) on the cap `(axis, h)`; `h = 1` is the hemisphere of
/// `axis`, which must then hold every valid sample.
///
/// On a proper cap, the test is conditioned on it: samples outside count as invalid and
/// the pdf integrates to the probability of the cap (the harness checks that the fraction of
/// samples in the cap matches).
fn chi2_bsdf(
    name: &str,
    cfg: &Chi2Config,
    bsdf: &Bsdf,
    wo: Vec3,
    (axis, h): (Vec3, f64),
    pdf: impl Fn(DVec3) -> f64,
) -> Result<Chi2Report, String> {
    let bins = CapBins::new(axis, h);
    let hemisphere = h >= 1.0;
    chi2_plane(
        name,
        cfg,
        (Vec2::splat(-1.0), Vec2::splat(1.0)),
        |u2, u1| {
            // Delta samples have no density: they count as invalid, like `None`.
            let s = bsdf.sample(wo, u1, u2).filter(|s| !s.delta)?;
            match bins.to_square(s.wi) {
                Some((a, b)) => Some(Vec2::new(a as f32, b as f32)),
                // A sample on the wrong side of the surface: a point outside the square
                // makes the harness report it.
                None if hemisphere => Some(Vec2::splat(2.0)),
                None => None,
            }
        },
        |p| {
            let (w, jacobian) = bins.to_world(p.x as f64, p.y as f64);
            (pdf(w) * jacobian) as f32
        },
    )
}

/// One member of the chi-squared family: a case on its hemisphere or on its cap.
struct Chi2Test<'a> {
    name: String,
    case: &'a Case,
    bins: (Vec3, f64),
}

fn chi2_tests(cases: &[Case]) -> Vec<Chi2Test<'_>> {
    let mut tests = Vec::new();
    for c in cases {
        let up = if c.wo.z < 0.0 { -Vec3::Z } else { Vec3::Z };
        tests.push(Chi2Test {
            name: format!("{} (hemisphere)", c.name),
            case: c,
            bins: (up, 1.0),
        });
        if let Some(cap) = c.cap {
            tests.push(Chi2Test {
                name: format!("{} (cap h {:.4})", c.name, cap.1),
                case: c,
                bins: cap,
            });
        }
    }
    tests
}

/// True for BSDFs whose f32 pdf is too rough for the cubature (see the reference
/// densities below): a Phong lobe of exponent above 100.
fn needs_reference_pdf(bsdf: &Bsdf) -> bool {
    bsdf.lobes[..bsdf.count]
        .iter()
        .any(|l| matches!(l, Lobe::Phong(p) if p.exponent > 100.0))
}

/// Tests against `Bsdf::pdf`, or against the f64 reference density for the sharpest
/// lobes.
fn run_chi2(t: &Chi2Test, cfg: &Chi2Config) -> Result<Chi2Report, String> {
    let c = t.case;
    if needs_reference_pdf(&c.bsdf) {
        let wo = c.wo.as_dvec3();
        chi2_bsdf(&t.name, cfg, &c.bsdf, c.wo, t.bins, |wi| {
            reference_pdf(&c.bsdf, wo, wi)
        })
    } else {
        chi2_bsdf(&t.name, cfg, &c.bsdf, c.wo, t.bins, |wi| {
            c.bsdf.pdf(c.wo, wi.as_vec3()) as f64
        })
    }
}

/// Runs the tests on two threads (the test machine has two cores); returns the failures.
fn run_family(tests: &[Chi2Test], cfg: &Chi2Config) -> Vec<String> {
    let run = |part: Vec<&Chi2Test>| -> Vec<String> {
        part.into_iter()
            .filter_map(|t| match run_chi2(t, cfg) {
                Ok(report) => {
                    assert!(report.p_value >= cfg.single_test_significance());
                    None
                }
                Err(msg) => Some(msg),
            })
            .collect()
    };
    let even = tests.iter().step_by(2).collect();
    let odd = tests.iter().skip(1).step_by(2).collect();
    std::thread::scope(|s| {
        let h = s.spawn(|| run(odd));
        let mut failures = run(even);
        failures.extend(h.join().expect("chi2 thread panicked"));
        failures
    })
}

#[test]
fn square_map_is_a_bijection_with_the_right_jacobian() {
    // Round trip and the total area: the Jacobian integrates to π over the square.
    for i in 0..=20 {
        for j in 0..=20 {
            let (a, b) = (i as f64 / 10.0 - 1.0, j as f64 / 10.0 - 1.0);
            let (x, y) = square_to_disk(a, b);
            assert!(x * x + y * y <= 1.0 + 1e-12);
            let (a2, b2) = disk_to_square(x, y);
            assert!((a - a2).abs() < 1e-6 && (b - b2).abs() < 1e-6, "{a} {b}");
        }
    }
    let n = 400;
    let area: f64 = (0..n * n)
        .map(|k| {
            let a = -1.0 + (2 * (k % n) + 1) as f64 / n as f64;
            let b = -1.0 + (2 * (k / n) + 1) as f64 / n as f64;
            square_to_disk_jacobian(a, b) * 4.0 / (n * n) as f64
        })
        .sum();
    assert!((area - PI).abs() < 1e-4, "{area}");
    // And the cap map: world directions round-trip.
    let bins = CapBins::new(dir(40.0, false), 0.3);
    for (a, b) in [(0.0, 0.0), (0.5, -0.25), (-0.9, 0.99)] {
        let (w, _) = bins.to_world(a, b);
        let (a2, b2) = bins.to_square(w.as_vec3()).expect("inside the cap");
        assert!((a - a2).abs() < 1e-3 && (b - b2).abs() < 1e-3, "{a} {b}");
    }
}

#[test]
fn bsdf_sampling_matches_pdf_chi2() {
    let cases = cases();
    let tests = chi2_tests(&cases);
    let cfg = family_config(tests.len());
    let failures = run_family(&tests, &cfg);
    assert!(
        failures.is_empty(),
        "{} of {} chi2 tests failed:\n{}",
        failures.len(),
        tests.len(),
        failures.join("\n")
    );
}

#[test]
fn chi2_rejects_mismatched_pdfs() {
    // Negative controls, at the threshold of the family above: the tests can fail.
    let cases = cases();
    let cfg = family_config(chi2_tests(&cases).len());
    let wo = dir(40.0, false);
    let wo64 = wo.as_dvec3();
    let reject = |r: Result<Chi2Report, String>| {
        // Either by the statistic or by the fraction of samples in the binned region.
        let err = r.expect_err("a mismatched pdf must be rejected");
        assert!(err.contains("rejected") || err.contains("differs"), "{err}");
    };
    // Phong sampling at exponent 50 against the pdf of exponent 60, on the hemisphere and
    // on the cap, against `Bsdf::pdf` and against the f64 reference.
    let sampled = Bsdf::single(phong(0.0, 0.9, 50.0));
    let claimed = Bsdf::single(phong(0.0, 0.9, 60.0));
    for (name, bins) in [
        ("control phong 50 vs 60", (Vec3::Z, 1.0)),
        ("control phong 50 vs 60 cap", (mirror(wo), 0.1)),
    ] {
        reject(chi2_bsdf(name, &cfg, &sampled, wo, bins, |wi| {
            claimed.pdf(wo, wi.as_vec3()) as f64
        }));
        reject(chi2_bsdf(
            &format!("{name} reference"),
            &cfg,
            &sampled,
            wo,
            bins,
            |wi| reference_pdf(&claimed, wo64, wi),
        ));
    }
    // GGX conductor sampling at alpha 0.2 against the pdf of alpha 0.22.
    let sampled = Bsdf::single(conductor(GOLD, 0.2));
    let claimed = Bsdf::single(conductor(GOLD, 0.22));
    reject(chi2_bsdf(
        "control conductor 0.2 vs 0.22",
        &cfg,
        &sampled,
        wo,
        (Vec3::Z, 1.0),
        |wi| claimed.pdf(wo, wi.as_vec3()) as f64,
    ));
    // A mixture sampled with weights 0.5 / 0.5 against the pdf with weights 0.55 / 0.45.
    let mix = |w: f32| Bsdf::mixture(&[(diffuse(0.8), w), (phong(0.0, 0.9, 20.0), 1.0 - w)]);
    let (sampled, claimed) = (mix(0.5), mix(0.55));
    reject(chi2_bsdf(
        "control mixture weights",
        &cfg,
        &sampled,
        wo,
        (Vec3::Z, 1.0),
        |wi| claimed.pdf(wo, wi.as_vec3()) as f64,
    ));
    // Phong 500 sampled against the reference of exponent 550 (the path of the sharpest
    // lobes in the family).
    let sampled = Bsdf::single(phong(0.0, 0.9, 500.0));
    let claimed = Bsdf::single(phong(0.0, 0.9, 550.0));
    reject(chi2_bsdf(
        "control phong 500 vs 550 reference",
        &cfg,
        &sampled,
        wo,
        (mirror(wo), 0.0137),
        |wi| reference_pdf(&claimed, wo64, wi),
    ));
}

// ---------------------------------------------------------------------------------------
// Reference densities in f64
// ---------------------------------------------------------------------------------------
//
// The chi-squared expected counts need the pdf integrated over each bin to a relative
// accuracy of 1e-6. The f32 pdf of a sharp Phong lobe is a staircase at that level
// (`cos^500 α` amplifies the 6e-8 rounding of `cos α` 500 times), on which the harness's
// adaptive cubature never converges and runs for a minute per test. For those lobes the
// expected counts come from the formulas of the lobe documentation evaluated in f64,
// written here independently of the lobe code, and `Bsdf::pdf` is checked against them
// pointwise for every case (`pdf_matches_reference`): `sample ~ reference` and
// `pdf == reference` give `sample ~ pdf`. (All other lobes are tested against `Bsdf::pdf`
// directly; run against the reference, the whole family passes as well.)

fn lum(c: Vec3) -> f64 {
    0.2126 * c.x as f64 + 0.7152 * c.y as f64 + 0.0722 * c.z as f64
}

/// Cosine-weighted hemisphere density.
fn ref_cosine(wi: DVec3) -> f64 {
    wi.z.max(0.0) / PI
}

/// GGX density of sampling `wi` by reflecting `wo` about a visible normal (Heitz 2018):
/// `D_wo(h) / (4 wo·h)` with `D_wo(h) = G1(wo) (wo·h) D(h) / cos θo`, i.e.
/// `G1(wo) D(h) / (4 cos θo)`.
fn ref_ggx_reflection(wo: DVec3, wi: DVec3, alpha: f64) -> f64 {
    if wi.z <= 0.0 {
        return 0.0;
    }
    let h = (wo + wi).normalize();
    let a2 = alpha * alpha;
    let k = h.x * h.x + h.y * h.y + a2 * h.z * h.z;
    let d = a2 / (PI * k * k);
    let tan2 = (wo.x * wo.x + wo.y * wo.y) / (wo.z * wo.z);
    let g1 = 2.0 / (1.0 + (1.0 + a2 * tan2).sqrt());
    g1 * d / (4.0 * wo.z)
}

/// The density of one lobe, `wo` in the upper hemisphere.
fn reference_lobe_pdf(lobe: &Lobe, wo: DVec3, wi: DVec3) -> f64 {
    if wi.z <= 0.0 {
        return 0.0;
    }
    match lobe {
        Lobe::Diffuse(_) => ref_cosine(wi),
        Lobe::Phong(p) => {
            // Diffuse part chosen by luminance, the rest from (n+1)/(2π) cos^n α about the
            // mirror direction.
            let (d, s) = (lum(p.kd), lum(p.ks));
            let pd = if d + s > 0.0 { d / (d + s) } else { 1.0 };
            let n = p.exponent as f64;
            let cos_a = DVec3::new(-wo.x, -wo.y, wo.z).dot(wi);
            let spec = if cos_a > 0.0 {
                (n + 1.0) / (2.0 * PI) * cos_a.powf(n)
            } else {
                0.0
            };
            pd * ref_cosine(wi) + (1.0 - pd) * spec
        }
        Lobe::Conductor(c) => ref_ggx_reflection(wo, wi, c.alpha as f64),
        Lobe::GltfDielectric(g) => {
            // Specular chosen with the Schlick Fresnel weight at cos θo against the
            // Fresnel-attenuated diffuse albedo, clamped to [0.05, 1].
            // KHR_materials_specular scales the Fresnel weight; without it the specular
            // lobe is never chosen.
            let f0 = g.f0 as f64;
            let f = g.specular as f64 * (f0 + (1.0 - f0) * (1.0 - wo.z).powi(5));
            let ps = if g.specular > 0.0 {
                (f / (f + (1.0 - f) * lum(g.base))).clamp(0.05, 1.0)
            } else {
                0.0
            };
            ps * ref_ggx_reflection(wo, wi, g.alpha as f64) + (1.0 - ps) * ref_cosine(wi)
        }
        Lobe::Mirror(_) | Lobe::Glass(_) => 0.0,
    }
}

/// The mixture density: the weighted sum over the lobes; opaque lobes are two-sided (the
/// frame is mirrored when `wo` is below the surface).
fn reference_pdf(bsdf: &Bsdf, wo: DVec3, wi: DVec3) -> f64 {
    let flip = |v: DVec3| DVec3::new(v.x, v.y, -v.z);
    let (wo, wi) = if wo.z < 0.0 {
        (flip(wo), flip(wi))
    } else {
        (wo, wi)
    };
    (0..bsdf.count)
        .map(|i| bsdf.weights[i] as f64 * reference_lobe_pdf(&bsdf.lobes[i], wo, wi))
        .sum()
}

// ---------------------------------------------------------------------------------------
// Consistency and energy
// ---------------------------------------------------------------------------------------

/// `|a - b| <= rel * max(|a|, |b|)` per channel, with a tiny absolute floor for zeros.
fn close3(a: Vec3, b: Vec3, rel: f32) -> bool {
    let d = (a - b).abs();
    let m = a.abs().max(b.abs());
    (0..3).all(|i| d[i] <= rel * m[i] + 1e-12)
}

fn close(a: f32, b: f32, rel: f32) -> bool {
    (a - b).abs() <= rel * a.abs().max(b.abs()) + 1e-12
}

fn uniforms(rng: &mut SplitMix64) -> (f32, Vec2) {
    let u1 = rng.next_f32();
    (u1, Vec2::new(rng.next_f32(), rng.next_f32()))
}

#[test]
fn sample_weight_is_eval_over_pdf() {
    let mut rng = SplitMix64::new(0xc0_5157_e1c7);
    let mut failures = Vec::new();
    for c in cases() {
        let mut bad = 0usize;
        let mut first = None;
        for _ in 0..20_000 {
            let (u1, u2) = uniforms(&mut rng);
            let Some(s) = c.bsdf.sample(c.wo, u1, u2) else {
                continue;
            };
            if s.delta {
                continue; // delta lobes are checked separately
            }
            let f = c.bsdf.eval(c.wo, s.wi);
            let p = c.bsdf.pdf(c.wo, s.wi);
            let ok = p > 0.0
                && p.is_finite()
                && s.weight.is_finite()
                && close(s.pdf, p, 1e-3)
                && close3(s.weight, f / p, 1e-3);
            if !ok {
                bad += 1;
                first.get_or_insert(format!(
                    "wi {:?}: weight {:?} vs eval/pdf {:?} (eval {:?}, pdf {p}, sample pdf {})",
                    s.wi,
                    s.weight,
                    f / p,
                    f,
                    s.pdf
                ));
            }
        }
        // Every direction with eval > 0 must be reachable by sampling.
        for _ in 0..20_000 {
            let wi = square_to_uniform_sphere(Vec2::new(rng.next_f32(), rng.next_f32()));
            let f = c.bsdf.eval(c.wo, wi);
            let p = c.bsdf.pdf(c.wo, wi);
            let ok = f.min_element() >= 0.0 && (f.max_element() <= 0.0 || p > 0.0);
            if !ok {
                bad += 1;
                first.get_or_insert(format!("wi {wi:?}: eval {f:?} but pdf {p}"));
            }
        }
        if let Some(first) = first {
            failures.push(format!("{}: {bad} bad, first: {first}", c.name));
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

#[test]
fn pdf_matches_reference() {
    // `Bsdf::pdf` (f32) against the f64 reference densities that the chi-squared family
    // integrates, at sampled directions (where the mass is) and uniform ones (the tails).
    let mut rng = SplitMix64::new(0x9df);
    let mut failures = Vec::new();
    for c in cases() {
        let mut worst = (0.0f64, String::new());
        for i in 0..20_000 {
            let wi = if i % 2 == 0 {
                let (u1, u2) = uniforms(&mut rng);
                match c.bsdf.sample(c.wo, u1, u2) {
                    Some(s) if !s.delta => s.wi,
                    _ => continue,
                }
            } else {
                square_to_uniform_sphere(Vec2::new(rng.next_f32(), rng.next_f32()))
            };
            let p = c.bsdf.pdf(c.wo, wi) as f64;
            let r = reference_pdf(&c.bsdf, c.wo.as_dvec3(), wi.as_dvec3());
            let err = (p - r).abs() / (p.abs().max(r.abs()) + 1e-9);
            if err > worst.0 {
                worst = (err, format!("wi {wi:?}: pdf {p} vs reference {r}"));
            }
        }
        if worst.0 > 1e-3 {
            failures.push(format!("{}: {}", c.name, worst.1));
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// Monte Carlo estimate of the directional albedo `∫ f(wo, wi) |cos θi| dωi = E[weight]`
/// (invalid samples contribute zero) and its standard error, per channel.
fn albedo(bsdf: &Bsdf, wo: Vec3, n: usize, rng: &mut SplitMix64) -> (Vec3, Vec3) {
    let (mut sum, mut sum2) = (glam::DVec3::ZERO, glam::DVec3::ZERO);
    for _ in 0..n {
        let (u1, u2) = uniforms(rng);
        if let Some(s) = bsdf.sample(wo, u1, u2) {
            let w = s.weight.as_dvec3();
            sum += w;
            sum2 += w * w;
        }
    }
    let n = n as f64;
    let mean = sum / n;
    let var = (sum2 / n - mean * mean).max(glam::DVec3::ZERO);
    (mean.as_vec3(), (var / n).map(f64::sqrt).as_vec3())
}

/// `∫ eval(wo, wi) dωi` over the hemisphere of `wo` by the midpoint rule on the square
/// map of the chi-squared bins (smooth, so the rule converges like `1/n²`): the directional
/// albedo computed without any sampling.
fn albedo_quadrature(bsdf: &Bsdf, wo: Vec3, n: usize) -> Vec3 {
    let bins = CapBins::new(if wo.z < 0.0 { -Vec3::Z } else { Vec3::Z }, 1.0);
    let mut sum = DVec3::ZERO;
    for i in 0..n {
        for j in 0..n {
            let a = -1.0 + (2 * i + 1) as f64 / n as f64;
            let b = -1.0 + (2 * j + 1) as f64 / n as f64;
            let (w, jacobian) = bins.to_world(a, b);
            sum += bsdf.eval(wo, w.as_vec3()).as_dvec3() * jacobian;
        }
    }
    (sum * 4.0 / (n * n) as f64).as_vec3()
}

#[test]
fn albedo_never_exceeds_one() {
    // No energy is created: E[weight] <= 1 within 3 standard errors, for every case but the
    // glTF dielectric (see `gltf_dielectric_energy`).
    let mut rng = SplitMix64::new(0xa1bed0);
    let mut failures = Vec::new();
    let gltf_free = |b: &Bsdf| {
        !b.lobes[..b.count]
            .iter()
            .any(|l| matches!(l, Lobe::GltfDielectric(_)))
    };
    for c in cases().into_iter().filter(|c| gltf_free(&c.bsdf)) {
        let (mean, se) = albedo(&c.bsdf, c.wo, 100_000, &mut rng);
        if (0..3).any(|i| mean[i] > 1.0 + 3.0 * se[i]) {
            failures.push(format!("{}: albedo {mean:?} +- {se:?}", c.name));
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

#[test]
fn gltf_dielectric_energy() {
    // The glTF 2.0 dielectric `(1 - F(wo·h)) base/π + F(wo·h) spec` (appendix B
    // fresnel_mix) is what other glTF renderers implement, so we keep it. It attenuates the
    // diffuse layer by the Fresnel factor of the half vector; at grazing wo, wo·h stays
    // large, so the diffuse layer keeps most of its albedo while the coating reflects
    // F(cos θo): the sum can exceed one (1.09 for base 0.9, alpha 0.05 at 75°). Pin down
    // both facts: no gain up to 40° for bases up to 0.9, and a bounded gain at 75°.
    let mut rng = SplitMix64::new(0x91f);
    let mut failures = Vec::new();
    for base in [0.5, 0.9] {
        for alpha in [0.05, 0.3, 0.8] {
            for theta in ANGLES {
                let b = Bsdf::single(gltf(base, alpha));
                let (mean, se) = albedo(&b, dir(theta, false), 100_000, &mut rng);
                let bound = if theta <= 45.0 { 1.0 } else { 1.12 };
                if mean.x > bound + 3.0 * se.x {
                    failures.push(format!(
                        "gltf base {base} alpha {alpha} wo {theta}: albedo {} +- {} > {bound}",
                        mean.x, se.x
                    ));
                }
            }
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

#[test]
fn albedo_estimate_matches_quadrature_of_eval() {
    // E[weight] = ∫ f cos dωi: the sampling weights are an unbiased estimator of the
    // integral of `eval`. Checked against deterministic quadrature for the lobes wide
    // enough for a 300 x 300 midpoint rule.
    let mut rng = SplitMix64::new(0x9ad);
    let mut failures = Vec::new();
    let mut cases = cases();
    cases.push(Case::new(
        "furnace alpha 0.6 wo 0".into(),
        Bsdf::single(conductor(Vec3::ONE, 0.6)),
        Vec3::Z,
        None,
    ));
    cases.push(Case::new(
        "gltf base 0.9 alpha 0.3 wo 75".into(),
        Bsdf::single(gltf(0.9, 0.3)),
        dir(75.0, false),
        None,
    ));
    for c in cases.iter().filter(|c| c.cap.is_none()) {
        let (mean, se) = albedo(&c.bsdf, c.wo, 100_000, &mut rng);
        // A mirror lobe adds its mixture weight times its reflectance (not part of eval).
        let b = &c.bsdf;
        let delta: Vec3 = (0..b.count)
            .map(|i| match b.lobes[i] {
                Lobe::Mirror(m) => b.weights[i] * m.reflectance,
                _ => Vec3::ZERO,
            })
            .sum();
        let exact = albedo_quadrature(b, c.wo, 300) + delta;
        eprintln!(
            "{}: albedo {} +- {} vs quadrature {}",
            c.name, mean.x, se.x, exact.x
        );
        // 3 standard errors plus the quadrature error.
        if (0..3).any(|i| (mean[i] - exact[i]).abs() > 3.0 * se[i] + 1e-3) {
            failures.push(format!(
                "{}: estimate {mean:?} +- {se:?}, quadrature {exact:?}",
                c.name
            ));
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

#[test]
fn diffuse_weight_is_its_albedo() {
    // Cosine-weighted sampling cancels f cos / p exactly: every weight is the albedo.
    let albedo = Vec3::new(0.2, 0.5, 0.8);
    let b = Bsdf::single(Lobe::Diffuse(Diffuse { albedo }));
    let mut rng = SplitMix64::new(0xd1ff);
    for wo in [dir(0.0, false), dir(75.0, false), dir(40.0, true)] {
        let mut valid = 0;
        for _ in 0..10_000 {
            let (u1, u2) = uniforms(&mut rng);
            if let Some(s) = b.sample(wo, u1, u2) {
                assert_eq!(s.weight, albedo, "wo {wo:?}");
                // Same side as wo (two-sided lobe).
                assert!(s.wi.z * wo.z > 0.0, "wo {wo:?} wi {:?}", s.wi);
                valid += 1;
            }
        }
        assert!(valid >= 9_990, "only {valid} valid samples at wo {wo:?}");
    }
}

#[test]
fn phong_albedo_at_normal_incidence_is_ks() {
    // At normal incidence the lobe is centred on the normal, so none of it is below the
    // horizon and `∫ ks (n + 2)/(2π) cos^n θ cos θ dω = ks` exactly: the modified Phong
    // model's normalisation.
    let mut rng = SplitMix64::new(0x9407);
    for n in [50.0, 500.0] {
        let b = Bsdf::single(phong(0.0, 0.9, n));
        let (mean, se) = albedo(&b, Vec3::Z, 200_000, &mut rng);
        eprintln!("phong n {n}: albedo {} +- {}", mean.x, se.x);
        assert!(
            (mean.x - 0.9).abs() <= 3.0 * se.x + 1e-4,
            "n {n}: {mean:?} +- {se:?}"
        );
    }
}

#[test]
fn conductor_white_furnace() {
    // f0 = 1: a perfect mirror microsurface. A smooth one reflects nearly everything; the
    // single-scattering Smith model loses the energy of inter-reflections at high roughness
    // (at alpha 0.6 and normal incidence ~40%: a quarter of the reflected directions point
    // below the horizon, and the rest are partly shadowed), so only `<= 1` is asserted there.
    // `albedo_estimate_matches_quadrature_of_eval` shows that the loss is the model's.
    let mut rng = SplitMix64::new(0xf0f0);
    let white = |alpha| Bsdf::single(conductor(Vec3::ONE, alpha));
    let (mean, se) = albedo(&white(0.05), Vec3::Z, 100_000, &mut rng);
    eprintln!("furnace alpha 0.05 normal: {} +- {}", mean.x, se.x);
    assert!((mean.x - 1.0).abs() < 0.02, "{mean:?} +- {se:?}");
    for alpha in [0.05, 0.2, 0.6] {
        for theta in ANGLES {
            let (mean, se) = albedo(&white(alpha), dir(theta, false), 100_000, &mut rng);
            eprintln!("furnace alpha {alpha} wo {theta}: {} +- {}", mean.x, se.x);
            assert!(
                mean.x <= 1.0 + 3.0 * se.x,
                "alpha {alpha} wo {theta}: {mean:?}"
            );
        }
    }
}

// ---------------------------------------------------------------------------------------
// Reciprocity
// ---------------------------------------------------------------------------------------

#[test]
fn reflection_lobes_are_reciprocal() {
    // Helmholtz reciprocity: f(wo, wi) = f(wi, wo), i.e. eval / |cos θi| is symmetric. The
    // glTF dielectric is included: its Fresnel term uses wo·h = wi·h.
    let lobes = [
        ("diffuse", Bsdf::single(diffuse(0.7))),
        ("phong 5", Bsdf::single(phong(0.3, 0.6, 5.0))),
        ("phong 50", Bsdf::single(phong(0.3, 0.6, 50.0))),
        ("phong 500", Bsdf::single(phong(0.0, 0.9, 500.0))),
        ("conductor 0.05", Bsdf::single(conductor(GOLD, 0.05))),
        ("conductor 0.2", Bsdf::single(conductor(GOLD, 0.2))),
        ("conductor 0.6", Bsdf::single(conductor(GOLD, 0.6))),
        ("gltf 0.05", Bsdf::single(gltf(0.9, 0.05))),
        ("gltf 0.3", Bsdf::single(gltf(0.5, 0.3))),
        ("gltf 0.8", Bsdf::single(gltf(0.5, 0.8))),
        (
            "mixture",
            Bsdf::mixture(&[(conductor(GOLD, 0.2), 0.6), (gltf(0.5, 0.4), 0.4)]),
        ),
    ];
    let mut rng = SplitMix64::new(0x4ec1);
    let mut failures = Vec::new();
    for (name, b) in lobes {
        let mut worst = (0.0f32, String::new());
        for i in 0..20_000 {
            // Half the pairs near the specular peak, where the lobes are largest.
            let wo = square_to_uniform_sphere(Vec2::new(rng.next_f32(), rng.next_f32()));
            let wi = if i % 2 == 0 {
                square_to_uniform_sphere(Vec2::new(rng.next_f32(), rng.next_f32()))
            } else {
                let jitter = 0.05 * square_to_uniform_sphere(Vec2::new(rng.next_f32(), 0.5));
                (mirror(wo) + jitter).normalize()
            };
            // Two-sided lobes: both below gives the same as both above. Within ~1° of the
            // horizon, wo + wi cancels for the mirror pair and the f32 half vector loses
            // digits: wo·h and wi·h then differ by ~1e-4 relative (the glTF Fresnel term
            // uses the former, so its (1 - F) diffuse factor inherits that).
            if wo.z * wi.z <= 0.0 || wo.z.abs() < 0.02 || wi.z.abs() < 0.02 {
                continue;
            }
            let a = b.eval(wo, wi) / wi.z.abs();
            let r = b.eval(wi, wo) / wo.z.abs();
            let d = (a - r).abs() / a.abs().max(r.abs()).max(Vec3::splat(1e-30));
            let d = d.max_element();
            if d > worst.0 {
                worst = (d, format!("wo {wo:?} wi {wi:?}: {a:?} vs {r:?}"));
            }
        }
        eprintln!("reciprocity {name}: worst relative difference {}", worst.0);
        if worst.0 > 1e-4 {
            failures.push(format!("{name}: {}", worst.1));
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

// ---------------------------------------------------------------------------------------
// Delta lobes and Fresnel
// ---------------------------------------------------------------------------------------

#[test]
fn mirror_reflects_with_its_reflectance() {
    let reflectance = Vec3::new(0.9, 0.8, 0.5);
    let b = Bsdf::single(Lobe::Mirror(Mirror { reflectance }));
    for wo in [
        dir(0.0, false),
        dir(40.0, false),
        dir(89.0, false),
        dir(40.0, true),
    ] {
        let s = b
            .sample(wo, 0.3, Vec2::new(0.1, 0.7))
            .expect("mirror sample");
        assert!(s.delta);
        assert_eq!(s.wi, mirror(wo));
        assert_eq!(s.weight, reflectance);
        assert_eq!(s.pdf, 1.0);
        // A delta lobe has no density and contributes nothing to eval.
        assert_eq!(b.eval(wo, s.wi), Vec3::ZERO);
        assert_eq!(b.pdf(wo, s.wi), 0.0);
    }
    // In a mixture the delta sample's pdf is its selection probability; its weight is
    // unchanged (f_mix / p_mix = w f / (w p)).
    let mix = Bsdf::mixture(&[
        (diffuse(0.5), 0.75),
        (Lobe::Mirror(Mirror { reflectance }), 0.25),
    ]);
    let s = mix
        .sample(dir(30.0, false), 0.9, Vec2::new(0.2, 0.2))
        .expect("mirror sample");
    assert!(s.delta);
    assert_eq!(s.weight, reflectance);
    assert!(close(s.pdf, 0.25, 1e-6));
}

const GLASS_ETA: f32 = 1.5;

fn glass() -> (Bsdf, Vec3) {
    let tint = Vec3::new(1.0, 0.9, 0.8);
    (
        Bsdf::single(Lobe::Glass(Glass {
            eta: GLASS_ETA,
            tint,
        })),
        tint,
    )
}

#[test]
fn glass_splits_by_fresnel_and_obeys_snell() {
    let (b, tint) = glass();
    let mut rng = SplitMix64::new(0x91a55);
    let n = 100_000;
    // From outside (wo.z > 0, entering) and from inside below the critical angle
    // asin(1/1.5) = 41.8° (leaving).
    let setups = [
        (0.0, false),
        (30.0, false),
        (60.0, false),
        (85.0, false),
        (0.0, true),
        (20.0, true),
        (40.0, true),
    ];
    for (theta, inside) in setups {
        let wo = dir(theta, inside);
        // Indices on wo's side and on the far side.
        let (n_o, n_t) = if inside {
            (GLASS_ETA, 1.0)
        } else {
            (1.0, GLASS_ETA)
        };
        let f = fresnel_dielectric(wo.z, GLASS_ETA);
        let mut reflected = 0usize;
        for _ in 0..n {
            let (u1, u2) = uniforms(&mut rng);
            let s = b.sample(wo, u1, u2).expect("glass always scatters");
            assert!(s.delta);
            assert!((s.wi.length() - 1.0).abs() < 1e-5);
            if s.wi.z * wo.z > 0.0 {
                // Reflection: the mirror direction, weight F / F = 1.
                reflected += 1;
                assert!((s.wi - mirror(wo)).length() < 1e-6);
                assert_eq!(s.weight, Vec3::ONE);
                assert!(close(s.pdf, f, 1e-6));
            } else {
                // Refraction: Snell's law n_o sin θo = n_t sin θt, in the plane of
                // incidence on the other side of the normal.
                let sin_o = wo.truncate().length();
                let sin_t = s.wi.truncate().length();
                assert!(
                    (n_o * sin_o - n_t * sin_t).abs() < 1e-5,
                    "Snell: {n_o} * {sin_o} vs {n_t} * {sin_t}"
                );
                assert!(wo.truncate().dot(s.wi.truncate()) <= 1e-7);
                assert!(wo.truncate().perp_dot(s.wi.truncate()).abs() < 1e-6);
                // Radiance scaling: radiance / n² is invariant, so the camera path picks up
                // (n_o / n_t)² = 1/η² with η the relative index seen from wo.
                let eta = n_t / n_o;
                assert!(
                    close3(s.weight, tint / (eta * eta), 1e-5),
                    "weight {:?}, expected {:?}",
                    s.weight,
                    tint / (eta * eta)
                );
                assert!(close(s.pdf, 1.0 - f, 1e-5));
            }
        }
        // Binomial z-test of the reflected fraction against the exact Fresnel reflectance.
        let sigma = (n as f64 * f as f64 * (1.0 - f as f64)).sqrt();
        let z = (reflected as f64 - n as f64 * f as f64) / sigma;
        eprintln!(
            "glass theta {theta} inside {inside}: F {f}, reflected {reflected}/{n}, z {z:.2}"
        );
        assert!(z.abs() < 3.0, "theta {theta} inside {inside}: z = {z}");
    }
}

#[test]
fn glass_total_internal_reflection() {
    // From inside beyond the critical angle asin(1/η) = 41.8°, every sample reflects,
    // including u1 just below 1.
    let (b, _) = glass();
    for theta in [42.5, 60.0, 89.0] {
        let wo = dir(theta, true);
        assert_eq!(fresnel_dielectric(wo.z, GLASS_ETA), 1.0);
        for u1 in [0.0, 0.5, 0.999, 1.0 - f32::EPSILON / 2.0] {
            let s = b.sample(wo, u1, Vec2::splat(0.5)).expect("TIR reflects");
            assert!(s.delta);
            assert!((s.wi - mirror(wo)).length() < 1e-6, "theta {theta} u {u1}");
            assert_eq!(s.weight, Vec3::ONE);
        }
    }
}

#[test]
fn fresnel_dielectric_known_values() {
    // Normal incidence: ((η - 1)/(η + 1))², from either side.
    for eta in [1.33f32, 1.5, 2.4] {
        let r0 = ((eta - 1.0) / (eta + 1.0)).powi(2);
        assert!(close(fresnel_dielectric(1.0, eta), r0, 1e-5));
        assert!(close(fresnel_dielectric(-1.0, eta), r0, 1e-5));
        // Schlick's approximation is exact at normal incidence.
        assert!(close(fresnel_schlick(Vec3::splat(r0), 1.0).x, r0, 1e-6));
        // Grazing incidence from outside reflects everything.
        assert!(close(fresnel_dielectric(0.0, eta), 1.0, 1e-6));
    }
    // Brewster's angle tan θB = η: the p-polarised reflectance vanishes, so R = R_s / 2 with
    // R_s = ((1 - η²)/(1 + η²))² there (cos θt = sin θB).
    let eta = 1.5f32;
    let cos_b = 1.0 / (1.0 + eta * eta).sqrt();
    let rs = ((1.0 - eta * eta) / (1.0 + eta * eta)).powi(2);
    assert!(close(fresnel_dielectric(cos_b, eta), 0.5 * rs, 1e-4));
    assert!(close(0.5 * rs, 0.073_964, 1e-4));
    // Inside Brewster angle: tan θ = 1/η.
    let cos_bi = eta / (1.0 + eta * eta).sqrt();
    assert!(close(fresnel_dielectric(-cos_bi, eta), 0.5 * rs, 1e-4));
    // Symmetry: light crossing the interface either way between θi and θt reflects the
    // same fraction (Stokes relations); and inverting the side inverts η.
    for i in 0..=40 {
        let cos_i = i as f32 / 40.0;
        let sin_t = (1.0 - cos_i * cos_i).sqrt() / eta;
        let cos_t = (1.0 - sin_t * sin_t).sqrt();
        let outside = fresnel_dielectric(cos_i, eta);
        assert!(
            (outside - fresnel_dielectric(-cos_t, eta)).abs() < 1e-5,
            "cos {cos_i}"
        );
        assert_eq!(
            fresnel_dielectric(-cos_i, eta),
            fresnel_dielectric(cos_i, 1.0 / eta)
        );
        assert!((0.0..=1.0).contains(&outside));
    }
    // Total internal reflection beyond the critical angle.
    assert_eq!(fresnel_dielectric(-0.5, eta), 1.0);
}

/// KHR_materials_specular with `specularFactor` 0 (Blender's Specular IOR Level 0) is the
/// Lambertian base alone: the same value, density and sample weight as a diffuse lobe of
/// the base colour, and no Fresnel layer on top (glTF issue report: a 4% coat shifted a
/// Cornell box by 1.7% against Mitsuba 3 and Cycles).
#[test]
fn gltf_dielectric_without_specular_is_lambertian() {
    let base = 0.7;
    let g = Bsdf::single(gltf_specular(base, 0.3, 0.0));
    let d = Bsdf::single(diffuse(base));
    let mut rng = SplitMix64::new(0x5bec);
    for wo in [
        dir(0.0, false),
        dir(60.0, false),
        dir(85.0, false),
        dir(40.0, true),
    ] {
        for _ in 0..2_000 {
            let (_, u2) = uniforms(&mut rng);
            let wi = square_to_cosine_hemisphere(u2);
            let wi = if wo.z < 0.0 { -wi } else { wi };
            assert!(
                close3(g.eval(wo, wi), d.eval(wo, wi), 1e-6),
                "wo {wo:?} wi {wi:?}"
            );
            assert!(
                close(g.pdf(wo, wi), d.pdf(wo, wi), 1e-6),
                "wo {wo:?} wi {wi:?}"
            );
        }
        for _ in 0..2_000 {
            let (u1, u2) = uniforms(&mut rng);
            if let Some(s) = g.sample(wo, u1, u2) {
                assert!(
                    close3(s.weight, Vec3::splat(base), 1e-5),
                    "weight {:?}",
                    s.weight
                );
            }
        }
    }
    // With the factor 1 the coat is there: more than the base at grazing incidence.
    let coated = Bsdf::single(gltf_specular(base, 0.3, 1.0));
    let (wo, wi) = (dir(80.0, false), mirror(dir(80.0, false)));
    assert!(coated.eval(wo, wi).x > d.eval(wo, wi).x);
}
