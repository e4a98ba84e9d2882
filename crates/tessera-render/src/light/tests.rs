//! Tests of light sampling against the contract of [`super`].
//!
//! - **Chi-squared** (Marschner, CS 6630 notes, section 2): from a reference point, [`Light::sample_li`] maps
//!   uniform numbers to directions; their distribution must be the solid-angle density
//!   [`Light::pdf_li`] claims. One family with a Šidák correction, and a negative control.
//! - **Unbiased next-event estimation**: the irradiance `E = ∫ L cos θ dω` estimated as the
//!   mean of `li cos θ / pdf` must equal its closed form (a z-test at 3 standard errors).
//! - **Light selection** is proportional to power, never picks a dark light, and reports
//!   the probability it used.
//! - **Punctual lights**: inverse-square law and the glTF spot falloff.

use super::environment::Environment;
use super::punctual::{spot_falloff, Punctual};
use super::sphere::SphereLight;
use super::triangle::TriangleLight;
use super::{Light, LightSet};
use crate::chi2::{
    chi2_sphere, chi2_sphere_cap, chi2_survival, Chi2Config, Chi2Report, SplitMix64,
};
use crate::math::luminance;
use crate::sampling::warp::Frame;
use glam::{DVec3, Vec2, Vec3};
use std::f64::consts::PI;

// ---------------------------------------------------------------------------------------
// Scenes
// ---------------------------------------------------------------------------------------

/// Radiance of the test emitters (coloured, so that channels are not confused).
const RADIANCE: Vec3 = Vec3::new(2.0, 1.0, 0.5);

/// A one-sided triangle around `z = 1`, emitting downward (clockwise seen from above).
fn triangle(two_sided: bool) -> TriangleLight {
    TriangleLight::new(
        [
            Vec3::new(-1.0, -0.5, 1.0),
            Vec3::new(0.3, 1.2, 1.1),
            Vec3::new(1.2, -0.8, 0.9),
        ],
        RADIANCE,
        two_sided,
    )
    .expect("non-degenerate triangle")
}

/// Reference points for the triangle, with a receiver normal that sees the whole triangle
/// above its horizon (Lambert's formula below needs no clipping then).
struct TrianglePoint {
    name: &'static str,
    p: Vec3,
    n: Vec3,
    two_sided: bool,
}

fn triangle_points() -> [TrianglePoint; 5] {
    [
        // 0.7 below the triangle: it subtends a large solid angle.
        TrianglePoint {
            name: "near",
            p: Vec3::new(0.1, 0.0, 0.3),
            n: Vec3::new(0.2, -0.1, 1.0).normalize(),
            two_sided: false,
        },
        // Far to the side, just below the plane: the triangle is seen at ~85° from its
        // normal, a thin sliver of directions with a strongly varying pdf.
        TrianglePoint {
            name: "grazing",
            p: Vec3::new(4.0, 0.5, 0.6),
            n: Vec3::new(-1.0, 0.0, 0.3).normalize(),
            two_sided: false,
        },
        // Above a two-sided triangle: its back emits too.
        TrianglePoint {
            name: "two-sided back",
            p: Vec3::new(0.2, 0.1, 1.8),
            n: Vec3::new(0.1, 0.0, -1.0).normalize(),
            two_sided: true,
        },
        // 0.15 below the triangle: ~4.5 sr, close to the spherical warp's upper limit.
        TrianglePoint {
            name: "very near",
            p: Vec3::new(0.1, 0.0, 0.85),
            n: Vec3::new(0.0, 0.0, 1.0),
            two_sided: false,
        },
        // 88 below: ~2.6e-4 sr, far under the spherical warp's lower limit: area sampling.
        TrianglePoint {
            name: "far",
            p: Vec3::new(0.1, 0.0, -88.0),
            n: Vec3::new(0.0, 0.0, 1.0),
            two_sided: false,
        },
    ]
}

/// Ray–triangle intersection in f64 (Möller–Trumbore), with a barycentric slack of
/// `1e-5` so that samples on an edge, whose direction is rounded to f32, still hit.
fn hit_triangle(o: DVec3, d: DVec3, p: &[Vec3; 3]) -> Option<DVec3> {
    let [p0, p1, p2] = p.map(|v| v.as_dvec3());
    let (e1, e2) = (p1 - p0, p2 - p0);
    let q = d.cross(e2);
    let det = e1.dot(q);
    if det.abs() < 1e-300 {
        return None;
    }
    let s = o - p0;
    let b1 = s.dot(q) / det;
    let r = s.cross(e1);
    let b2 = d.dot(r) / det;
    let t = e2.dot(r) / det;
    const SLACK: f64 = 1e-5;
    if t <= 0.0 || b1 < -SLACK || b2 < -SLACK || b1 + b2 > 1.0 + SLACK {
        return None;
    }
    Some(o + t * d)
}

/// A sphere light of radius 1 seen from distance `dist` (in radii) along direction `axis`
/// from the reference point at `p_ref`.
fn sphere_at(p_ref: Vec3, axis: Vec3, dist: f32) -> SphereLight {
    SphereLight {
        center: p_ref + axis.normalize() * dist,
        radius: 1.0,
        radiance: RADIANCE,
    }
}

/// `1 - cos θmax` of the cone a unit sphere at distance `d` subtends, in f64.
fn cone_one_minus_cos(d: f64) -> f64 {
    let sin2 = 1.0 / (d * d);
    sin2 / (1.0 + (1.0 - sin2).sqrt())
}

// ---------------------------------------------------------------------------------------
// Chi-squared family
// ---------------------------------------------------------------------------------------

/// One member of the family: a name and the test, run with the family's configuration.
type Case = (
    String,
    Box<dyn Fn(&str, &Chi2Config) -> Result<Chi2Report, String> + Sync>,
);

/// 16 x 32 bins and 100k samples per test: the family runs in well under a second.
fn family_config(tests_in_family: usize) -> Chi2Config {
    Chi2Config {
        theta_bins: 16,
        phi_bins: 32,
        samples: 100_000,
        ..Chi2Config::new(tests_in_family)
    }
}

/// Chi-squared test of `light.sample_li` from `p_ref` against `pdf` (a density of world
/// directions), binned on the cap `cos θ >= cos_min` about `axis`. Rotating the samples
/// into a frame with `axis` on `+z` preserves solid angle.
fn chi2_light(
    name: &str,
    cfg: &Chi2Config,
    light: &Light,
    p_ref: Vec3,
    axis: Vec3,
    cos_min: f64,
    pdf: impl Fn(Vec3) -> f32,
) -> Result<Chi2Report, String> {
    let frame = Frame::from_normal(axis.normalize());
    chi2_sphere_cap(
        name,
        cfg,
        cos_min,
        |u2, _| light.sample_li(p_ref, u2).map(|s| frame.to_local(s.wi)),
        |d| pdf(frame.to_world(d)),
    )
}

/// Solid-angle pdf of a triangle light for the direction `w` from `p_ref`: `pdf_li` at the
/// point where the ray hits the triangle, zero if it misses (or the side is dark).
fn triangle_pdf(light: &TriangleLight, p_ref: Vec3, w: Vec3) -> f32 {
    match hit_triangle(p_ref.as_dvec3(), w.as_dvec3().normalize(), &light.p) {
        Some(hit) if light.emitted(-w) != Vec3::ZERO => {
            Light::Triangle(*light).pdf_li(p_ref, w, hit.as_vec3(), light.n)
        }
        _ => 0.0,
    }
}

/// The axis and extent of the cap of bins for a triangle seen from `p`. The pdf must
/// vanish around the pole: a density with a gradient across the pole of the `(cos θ, φ)`
/// bins has a square-root singularity there, which the harness's adaptive cubature refines
/// to its maximal depth. And the triangle should cover its bins well: a thin sliver passing
/// near the pole is a cusp-shaped region in `(cos θ, φ)` that the cubature's nodes can
/// miss (a few % error in those bins, enough to reject a correct sampler).
///
/// - A wide triangle: the pole just beyond vertex 0, in the triangle's plane.
/// - A sliver (grazing view): the pole off to the side of its middle, by its half-length,
///   so that the sliver runs across the bins at roughly constant `θ`.
fn triangle_bins(light: &TriangleLight, p: Vec3, sliver: bool) -> (Vec3, f64) {
    let c = (light.p[0] + light.p[1] + light.p[2]) / 3.0;
    let dirs = light.p.map(|v| (v - p).normalize());
    let axis = if sliver {
        let cd = (c - p).normalize();
        // The long axis: between the two vertex directions furthest apart.
        let (a, b) = [(0, 1), (1, 2), (2, 0)]
            .into_iter()
            .max_by(|x, y| {
                let dx = dirs[x.0].dot(dirs[x.1]);
                let dy = dirs[y.0].dot(dirs[y.1]);
                dy.total_cmp(&dx)
            })
            .expect("three edges");
        let long = dirs[a] - dirs[b];
        let side = cd.cross(long).normalize();
        let half_length = 0.5 * dirs[a].dot(dirs[b]).clamp(-1.0, 1.0).acos();
        (cd * half_length.cos() + side * half_length.sin()).normalize()
    } else {
        let beyond = c + 1.3 * (light.p[0] - c);
        (beyond - p).normalize()
    };
    let min_cos = dirs.iter().map(|d| axis.dot(*d) as f64).fold(1.0, f64::min);
    // A cap of angle below 90° is convex, so it holds the triangle when it holds the
    // vertices; wider ones are replaced by the whole sphere.
    let cos_min = if min_cos > 0.05 {
        1.0 - 1.1 * (1.0 - min_cos)
    } else {
        -1.0
    };
    (axis, cos_min)
}

fn triangle_cases() -> Vec<Case> {
    triangle_points()
        .into_iter()
        .map(|tp| {
            let light = triangle(tp.two_sided);
            let (axis, cos_min) = triangle_bins(&light, tp.p, tp.name == "grazing");
            let p = tp.p;
            let case: Case = (
                format!("triangle {}", tp.name),
                Box::new(move |name, cfg| {
                    chi2_light(name, cfg, &Light::Triangle(light), p, axis, cos_min, |w| {
                        triangle_pdf(&light, p, w)
                    })
                }),
            );
            case
        })
        .collect()
}

/// Seen through the f32 rotation into the bins' frame, a cone sample on the cone's edge
/// may land outside it by ~1e-7 in cos θ (in f64, none of 1e6 samples does); the test
/// density accepts those. This adds `1.5e-7 / h` to its mass, below the harness's 1e-3
/// integral tolerance even at 50 radii (h = 2e-4).
const CONE_SLACK: f64 = 1.5e-7;

/// Sphere lights from outside at 1.5, 5 and 50 radii (cone sampling). The bins are a cap
/// twice the cone's size about its axis: the cone boundary falls on the middle bin edge
/// and half the cap must stay empty.
fn sphere_cases() -> Vec<Case> {
    let p_ref = Vec3::new(0.3, -0.2, 0.1);
    // The far sphere sits straight up: its frame is exact, which keeps the 2e-4-wide cone
    // free of rotation rounding. The near ones are off-axis.
    [
        (1.5f32, Vec3::new(0.3, 0.5, 0.8)),
        (5.0, Vec3::new(-0.6, 0.2, 0.4)),
        (50.0, Vec3::Z),
    ]
    .into_iter()
    .map(|(dist, axis)| {
        let light = sphere_at(p_ref, axis, dist);
        let h = cone_one_minus_cos(dist as f64);
        let axis = axis.normalize();
        let case: Case = (
            format!("sphere cone at {dist} radii"),
            Box::new(move |name, cfg| {
                let l = Light::Sphere(light);
                chi2_light(name, cfg, &l, p_ref, axis, 1.0 - 2.0 * h, |w| {
                    sphere_cone_pdf(&light, p_ref, w, h, 0.0)
                })
            }),
        );
        case
    })
    .collect()
}

/// The cone-sampling density of a sphere light for direction `w`: `pdf_li` (constant) inside
/// the cone `1 - cos θ <= h`, zero outside. A nonzero `tilt` makes it a linear ramp in
/// `1 - cos θ` of the same mass (negative control).
fn sphere_cone_pdf(light: &SphereLight, p_ref: Vec3, w: Vec3, h: f64, tilt: f64) -> f32 {
    let to_c = (light.center - p_ref).as_dvec3();
    let d = to_c.length();
    let w = w.as_dvec3().normalize();
    let cos = w.dot(to_c / d);
    if 1.0 - cos > h + CONE_SLACK {
        return 0.0;
    }
    // The near intersection (or, in the slack band, the closest point of the ray).
    let r = light.radius as f64;
    let b = w.dot(to_c);
    let t = b - (r * r - (d * d - b * b)).max(0.0).sqrt();
    let p = p_ref.as_dvec3() + t * w;
    let n = (p - light.center.as_dvec3()).normalize();
    let pdf = Light::Sphere(*light).pdf_li(p_ref, w.as_vec3(), p.as_vec3(), n.as_vec3());
    (pdf as f64 * (1.0 + tilt * (0.5 - (1.0 - cos) / h))) as f32
}

/// The whole family.
fn family() -> Vec<Case> {
    let mut cases = triangle_cases();
    cases.extend(sphere_cases());
    cases.push((
        "environment".into(),
        Box::new(|name, cfg| {
            let env = Light::Environment(Environment::uniform(RADIANCE, 10.0));
            chi2_sphere(
                name,
                cfg,
                |u2, _| env.sample_li(Vec3::ZERO, u2).map(|s| s.wi),
                |w| env.pdf_li(Vec3::ZERO, w, Vec3::ZERO, Vec3::ZERO),
            )
        }),
    ));
    cases
}

#[test]
fn light_sampling_matches_pdf_chi2() {
    let cases = family();
    let cfg = family_config(cases.len());
    // Two threads (the test machine has two cores).
    let (even, odd): (Vec<_>, Vec<_>) = cases.iter().enumerate().partition(|(i, _)| i % 2 == 0);
    let run = |part: Vec<(usize, &Case)>| -> Vec<String> {
        part.into_iter()
            .filter_map(|(_, (name, f))| f(name, &cfg).err())
            .collect()
    };
    let failures = std::thread::scope(|s| {
        let h = s.spawn(|| run(odd));
        let mut failures = run(even);
        failures.extend(h.join().expect("chi2 thread panicked"));
        failures
    });
    assert!(
        failures.is_empty(),
        "{} of {} chi2 tests failed:\n{}",
        failures.len(),
        cases.len(),
        failures.join("\n")
    );
}

#[test]
fn chi2_rejects_mismatched_light_pdfs() {
    // Negative controls at the family's threshold.
    let cfg = family_config(family().len());
    let reject = |r: Result<Chi2Report, String>| {
        let err = r.expect_err("a mismatched pdf must be rejected");
        assert!(err.contains("rejected") || err.contains("differs"), "{err}");
    };
    // Uniform cone samples against a density ramping by ±5% across the cone.
    let p_ref = Vec3::ZERO;
    let sphere = sphere_at(p_ref, Vec3::new(0.2, 0.1, 1.0), 5.0);
    let h = cone_one_minus_cos(5.0);
    let axis = (sphere.center - p_ref).normalize();
    reject(chi2_light(
        "control tilted cone",
        &cfg,
        &Light::Sphere(sphere),
        p_ref,
        axis,
        1.0 - 2.0 * h,
        |w| sphere_cone_pdf(&sphere, p_ref, w, h, 0.1),
    ));
    // Triangle samples by solid angle (the near point is inside the spherical warp's
    // range) against the density of *area* sampling: the d² / cos factor matters.
    let tp = &triangle_points()[0];
    let light = triangle(false);
    assert!(light.spherical_solid_angle(tp.p).is_some());
    reject(chi2_light(
        "control triangle area density",
        &cfg,
        &Light::Triangle(light),
        tp.p,
        Vec3::Z,
        -1.0,
        |w| match hit_triangle(tp.p.as_dvec3(), w.as_dvec3().normalize(), &light.p) {
            Some(hit) => {
                let d = hit - tp.p.as_dvec3();
                let cos = light.n.as_dvec3().dot(d.normalize()).abs();
                (d.length_squared() / (cos * light.area as f64)) as f32
            }
            None => 0.0,
        },
    ));
}

// ---------------------------------------------------------------------------------------
// Sample consistency
// ---------------------------------------------------------------------------------------

#[test]
fn light_samples_are_consistent() {
    // Every sample: a unit direction toward a point on the light, at the reported distance,
    // with the light's radiance and `pdf == pdf_li` at that point.
    let mut rng = SplitMix64::new(0x11c);
    let u = |rng: &mut SplitMix64| Vec2::new(rng.next_f32(), rng.next_f32());
    for tp in triangle_points() {
        let light = triangle(tp.two_sided);
        let l = Light::Triangle(light);
        for _ in 0..10_000 {
            let s = l.sample_li(tp.p, u(&mut rng)).expect("front side");
            assert!((s.wi.length() - 1.0).abs() < 1e-5);
            assert!((tp.p + s.wi * s.dist - s.p).length() < 1e-4 * s.dist);
            assert!(hit_triangle(tp.p.as_dvec3(), s.wi.as_dvec3(), &light.p).is_some());
            assert_eq!(s.li, RADIANCE);
            assert_eq!(s.n, light.n);
            assert!(!s.delta);
            let pdf = l.pdf_li(tp.p, s.wi, s.p, s.n);
            assert!((s.pdf - pdf).abs() <= 1e-4 * pdf, "{} vs {pdf}", s.pdf);
        }
    }
    // Behind a one-sided triangle nothing is emitted: no valid sample.
    let l = Light::Triangle(triangle(false));
    for _ in 0..1000 {
        assert!(l.sample_li(Vec3::new(0.2, 0.1, 1.8), u(&mut rng)).is_none());
    }
    // Spheres from outside: the sample point is on the sphere, faces the reference point,
    // and lies along wi; every cone sample hits.
    let p_ref = Vec3::new(0.3, -0.2, 0.1);
    for dist in [1.01f32, 1.5, 5.0, 50.0, 1e4] {
        let sphere = sphere_at(p_ref, Vec3::new(0.3, 0.5, 0.8), dist);
        let l = Light::Sphere(sphere);
        let h = cone_one_minus_cos(dist as f64);
        let expected_pdf = 1.0 / (2.0 * PI * h);
        for _ in 0..10_000 {
            let s = l.sample_li(p_ref, u(&mut rng)).expect("cone samples hit");
            let r = (s.p - sphere.center).length();
            assert!(
                (r - 1.0).abs() < 1e-4 * dist.max(1.0),
                "radius {r} at {dist}"
            );
            assert!(s.n.dot(s.wi) <= 1e-3, "faces away at {dist}");
            let along = (s.p - p_ref).normalize();
            assert!((along - s.wi).length() < 1e-4, "{along:?} vs {:?}", s.wi);
            assert_eq!(s.li, RADIANCE);
            assert!((s.pdf as f64 - expected_pdf).abs() < 1e-4 * expected_pdf);
            assert_eq!(s.pdf, l.pdf_li(p_ref, s.wi, s.p, s.n));
        }
    }
}

#[test]
fn sphere_light_is_dark_from_inside() {
    // The sphere emits outward only: from inside, every area sample faces away (invalid)
    // and pdf_li is zero, consistently.
    let sphere = SphereLight {
        center: Vec3::new(1.0, 2.0, 3.0),
        radius: 2.0,
        radiance: RADIANCE,
    };
    let l = Light::Sphere(sphere);
    let mut rng = SplitMix64::new(0x1d);
    for p_ref in [sphere.center, sphere.center + Vec3::new(0.5, -1.0, 1.2)] {
        for _ in 0..10_000 {
            let u = Vec2::new(rng.next_f32(), rng.next_f32());
            assert!(l.sample_li(p_ref, u).is_none());
            // A point on the sphere hit from inside.
            let n = crate::sampling::warp::square_to_uniform_sphere(u);
            let p = sphere.center + n * sphere.radius;
            assert_eq!(l.pdf_li(p_ref, (p - p_ref).normalize(), p, n), 0.0);
        }
    }
}

// ---------------------------------------------------------------------------------------
// Unbiased next-event estimation
// ---------------------------------------------------------------------------------------

/// Monte Carlo irradiance `E = ∫ L cos θ dω` at `x` with normal `n`: the mean of
/// `li max(0, n·wi) / pdf` (invalid samples contribute zero) and its standard error, per
/// channel.
fn irradiance_estimate(
    light: &Light,
    x: Vec3,
    n: Vec3,
    samples: usize,
    seed: u64,
) -> (DVec3, DVec3) {
    let mut rng = SplitMix64::new(seed);
    let (mut sum, mut sum2) = (DVec3::ZERO, DVec3::ZERO);
    for _ in 0..samples {
        let u = Vec2::new(rng.next_f32(), rng.next_f32());
        if let Some(s) = light.sample_li(x, u) {
            let v = (s.li * (n.dot(s.wi).max(0.0) / s.pdf)).as_dvec3();
            sum += v;
            sum2 += v * v;
        }
    }
    let k = samples as f64;
    let mean = sum / k;
    let var = (sum2 / k - mean * mean).max(DVec3::ZERO);
    (mean, (var / k).map(f64::sqrt))
}

/// Solid angle of a triangle seen from `x` (Van Oosterom & Strackee 1983).
fn triangle_solid_angle(x: DVec3, p: &[Vec3; 3]) -> f64 {
    let [a, b, c] = p.map(|v| v.as_dvec3() - x);
    let (la, lb, lc) = (a.length(), b.length(), c.length());
    let num = a.dot(b.cross(c)).abs();
    let den = la * lb * lc + a.dot(b) * lc + a.dot(c) * lb + b.dot(c) * la;
    2.0 * num.atan2(den)
}

/// Irradiance at `x` (normal `n`) from a polygon of uniform radiance `l` lying entirely
/// above the horizon of `x`, by Lambert's formula: `E = l/2 |Σ θ_i (n · γ_i)|`, where `θ_i`
/// is the angle subtended by edge `i` and `γ_i` the unit normal of the plane through `x` and
/// the edge (the edge's contribution to the vector irradiance).
fn lambert_polygon_irradiance(x: DVec3, n: DVec3, verts: &[Vec3], l: f64) -> f64 {
    let r: Vec<DVec3> = verts
        .iter()
        .map(|v| (v.as_dvec3() - x).normalize())
        .collect();
    let mut sum = 0.0;
    for i in 0..r.len() {
        let (a, b) = (r[i], r[(i + 1) % r.len()]);
        let theta = a.dot(b).clamp(-1.0, 1.0).acos();
        sum += theta * n.dot(a.cross(b).normalize());
    }
    0.5 * l * sum.abs()
}

/// z-test of an estimate against the exact value per channel; returns the worst |z|.
fn z_score(mean: DVec3, se: DVec3, exact: DVec3) -> f64 {
    ((mean - exact) / se.max(DVec3::splat(1e-12)))
        .abs()
        .max_element()
}

#[test]
fn nee_triangle_irradiance_is_unbiased() {
    let rad = RADIANCE.as_dvec3();
    for (i, tp) in triangle_points().into_iter().enumerate() {
        let light = triangle(tp.two_sided);
        let exact = DVec3::new(
            lambert_polygon_irradiance(tp.p.as_dvec3(), tp.n.as_dvec3(), &light.p, rad.x),
            lambert_polygon_irradiance(tp.p.as_dvec3(), tp.n.as_dvec3(), &light.p, rad.y),
            lambert_polygon_irradiance(tp.p.as_dvec3(), tp.n.as_dvec3(), &light.p, rad.z),
        );
        let (mean, se) = irradiance_estimate(
            &Light::Triangle(light),
            tp.p,
            tp.n,
            200_000,
            0xe0 + i as u64,
        );
        let z = z_score(mean, se, exact);
        eprintln!(
            "triangle {}: E {:.6} +- {:.6}, exact {:.6}, z {z:.2}",
            tp.name, mean.x, se.x, exact.x
        );
        assert!(
            z < 3.0,
            "triangle {}: {mean:?} +- {se:?} vs {exact:?}",
            tp.name
        );
    }
    // Sanity of the closed form itself: a small triangle far away is a point source,
    // E ≈ L A cos θ_light cos θ_x / d².
    let far = [
        Vec3::new(0.0, 0.0, 100.0),
        Vec3::new(1.0, 0.0, 100.0),
        Vec3::new(0.0, 1.0, 100.0),
    ];
    let e = lambert_polygon_irradiance(DVec3::ZERO, DVec3::Z, &far, 1.0);
    assert!((e - 0.5 / 1e4).abs() < 1e-3 * 0.5 / 1e4, "{e}");
}

#[test]
fn nee_sphere_irradiance_is_unbiased() {
    // A uniformly emitting sphere entirely above the horizon irradiates like a point
    // source at its centre: E = π L sin²α cos β, sin α = r / d, β the angle between the
    // receiver's normal and the direction to the centre.
    let rad = RADIANCE.as_dvec3();
    let x = Vec3::new(0.3, -0.2, 0.1);
    for (i, (dist, tilt_deg)) in [(1.5f32, 0.0f32), (5.0, 0.0), (50.0, 0.0), (5.0, 40.0)]
        .into_iter()
        .enumerate()
    {
        let axis = Vec3::new(0.3, 0.5, 0.8).normalize();
        let light = sphere_at(x, axis, dist);
        // The receiver normal, tilted by `tilt_deg` away from the centre direction.
        let frame = Frame::from_normal(axis);
        let t = tilt_deg.to_radians();
        let n = frame.to_world(Vec3::new(t.sin(), 0.0, t.cos()));
        let sin2 = 1.0 / (dist as f64 * dist as f64);
        let exact = rad * (PI * sin2 * (t as f64).cos());
        let (mean, se) = irradiance_estimate(&Light::Sphere(light), x, n, 100_000, 0x5e + i as u64);
        let z = z_score(mean, se, exact);
        eprintln!(
            "sphere at {dist} radii, tilt {tilt_deg}: E {:.6e} +- {:.2e}, exact {:.6e}, z {z:.2}",
            mean.x, se.x, exact.x
        );
        // Under the centre the estimator has zero variance (cos θ / pdf is nearly constant
        // in a narrow cone): allow the f32 rounding then.
        assert!(
            z < 3.0 || ((mean - exact) / exact).abs().max_element() < 1e-4,
            "sphere at {dist}: {mean:?} +- {se:?} vs {exact:?}"
        );
    }
}

#[test]
fn nee_environment_irradiance_is_unbiased() {
    // A uniform environment L gives E = π L on any surface.
    let env = Light::Environment(Environment::uniform(RADIANCE, 10.0));
    let n = Vec3::new(0.3, -0.4, 0.5).normalize();
    let (mean, se) = irradiance_estimate(&env, Vec3::ZERO, n, 200_000, 0xe4);
    let exact = RADIANCE.as_dvec3() * PI;
    let z = z_score(mean, se, exact);
    eprintln!(
        "environment: E {:.5} +- {:.5}, exact {:.5}, z {z:.2}",
        mean.x, se.x, exact.x
    );
    assert!(z < 3.0, "{mean:?} +- {se:?} vs {exact:?}");
}

// ---------------------------------------------------------------------------------------
// Light selection
// ---------------------------------------------------------------------------------------

/// Lights of different power, with two dark ones (a black triangle and a black point).
fn light_set() -> (LightSet, Vec<f64>) {
    let tri = triangle(false);
    let lights = vec![
        Light::Triangle(tri),
        Light::Punctual(Punctual::Point {
            position: Vec3::new(0.0, 3.0, 0.0),
            intensity: Vec3::ZERO,
        }),
        Light::Sphere(SphereLight {
            center: Vec3::new(3.0, 0.0, 0.0),
            radius: 0.3,
            radiance: Vec3::new(1.0, 4.0, 2.0),
        }),
        Light::Punctual(Punctual::Point {
            position: Vec3::new(0.0, -3.0, 0.0),
            intensity: Vec3::new(5.0, 5.0, 5.0),
        }),
        Light::Triangle(TriangleLight::new(tri.p, Vec3::ZERO, true).expect("triangle")),
        Light::Environment(Environment::uniform(Vec3::splat(0.01), 4.0)),
    ];
    // Emitted power (luminance), from the radiometric definitions: a Lambertian emitter of
    // radiance L and area A emits π L A per side; a sphere π L 4π r²; an isotropic point
    // 4π I; the environment π L into the bounding sphere's area 4π R².
    let lum = |c: Vec3| luminance(c) as f64;
    let area = tri.area as f64;
    let expected = vec![
        PI * area * lum(RADIANCE),
        0.0,
        PI * 4.0 * PI * 0.09 * lum(Vec3::new(1.0, 4.0, 2.0)),
        4.0 * PI * 5.0,
        0.0,
        PI * 4.0 * PI * 16.0 * 0.01,
    ];
    (LightSet::new(lights), expected)
}

#[test]
fn light_power_matches_radiometry() {
    let (set, expected) = light_set();
    for (l, e) in set.lights.iter().zip(&expected) {
        let p = l.power() as f64;
        assert!((p - e).abs() <= 1e-5 * e.max(1e-30), "{l:?}: {p} vs {e}");
    }
    // A two-sided triangle emits from both faces.
    let two = Light::Triangle(triangle(true)).power();
    let one = Light::Triangle(triangle(false)).power();
    assert!((two - 2.0 * one).abs() <= 1e-6 * two);
}

#[test]
fn light_selection_is_proportional_to_power() {
    let (set, power) = light_set();
    let total: f64 = power.iter().sum();
    let pmf: Vec<f64> = power.iter().map(|p| p / total).collect();
    for (i, p) in pmf.iter().enumerate() {
        assert!((set.pmf(i) as f64 - p).abs() < 1e-6, "pmf({i})");
    }
    assert_eq!(set.pmf(99), 0.0);
    assert!(!set.is_empty());

    // Exhaustively on a grid of 2^16 values of u: each light is picked on an interval of
    // length pmf (to the grid resolution), the reported probability is pmf, and the dark
    // lights never.
    let m = 1usize << 16;
    let mut counts = vec![0usize; pmf.len()];
    for k in 0..m {
        let u = (k as f32 + 0.5) / m as f32;
        let (i, p) = set.select(u).expect("some light has power");
        assert_eq!(p, set.pmf(i));
        counts[i] += 1;
    }
    for (i, c) in counts.iter().enumerate() {
        let freq = *c as f64 / m as f64;
        assert!(
            (freq - pmf[i]).abs() <= 1.0 / m as f64 + 1e-6,
            "light {i}: {freq} vs {}",
            pmf[i]
        );
    }
    // The extremes of u, and u exactly on every cdf step (where a dark light's empty
    // interval sits).
    let mut edges = vec![0.0f32, 1.0 - f32::EPSILON / 2.0];
    let mut acc = 0.0;
    for p in &pmf {
        acc += p;
        for d in [-1e-7, 0.0, 1e-7] {
            edges.push(((acc + d) as f32).clamp(0.0, 1.0 - f32::EPSILON / 2.0));
        }
    }
    for u in edges {
        if let Some((i, p)) = set.select(u) {
            assert!(power[i] > 0.0, "dark light {i} picked at u = {u}");
            assert_eq!(p, set.pmf(i));
        }
    }

    // Random u: Pearson's chi-squared on the counts of the lit lights.
    let n = 200_000;
    let mut rng = SplitMix64::new(0x5e1ec7);
    let mut counts = vec![0u64; pmf.len()];
    for _ in 0..n {
        let (i, _) = set.select(rng.next_f32()).expect("some light has power");
        counts[i] += 1;
    }
    let mut stat = 0.0;
    let mut cells = 0;
    for (i, &c) in counts.iter().enumerate() {
        if pmf[i] == 0.0 {
            assert_eq!(c, 0, "dark light {i} picked");
            continue;
        }
        let e = pmf[i] * n as f64;
        stat += (c as f64 - e).powi(2) / e;
        cells += 1;
    }
    let p_value = chi2_survival(stat, cells - 1);
    eprintln!(
        "light selection: chi2 {stat:.2}, dof {}, p {p_value:.3}",
        cells - 1
    );
    assert!(p_value > 0.01, "selection counts {counts:?} vs pmf {pmf:?}");

    // No light with power: nothing to select.
    let dark = LightSet::new(vec![Light::Punctual(Punctual::Point {
        position: Vec3::ZERO,
        intensity: Vec3::ZERO,
    })]);
    assert!(dark.is_empty());
    assert!(dark.select(0.5).is_none());
    assert!(LightSet::new(Vec::new()).select(0.5).is_none());
}

// ---------------------------------------------------------------------------------------
// Punctual lights
// ---------------------------------------------------------------------------------------

#[test]
fn point_light_follows_the_inverse_square_law() {
    let intensity = Vec3::new(3.0, 2.0, 1.0);
    let position = Vec3::new(1.0, -2.0, 0.5);
    let l = Light::Punctual(Punctual::Point {
        position,
        intensity,
    });
    assert!(l.is_delta());
    for offset in [
        Vec3::new(0.0, 0.0, -1.0),
        Vec3::new(3.0, 4.0, 0.0),
        Vec3::new(-0.01, 0.02, 0.0),
    ] {
        let x = position + offset;
        let s = l.sample_li(x, Vec2::new(0.3, 0.7)).expect("point light");
        let d2 = offset.length_squared();
        assert!(
            (s.li - intensity / d2).abs().max_element() <= 1e-5 * (intensity / d2).max_element()
        );
        assert!((s.wi + offset.normalize()).length() < 1e-6);
        assert!((s.dist - d2.sqrt()).abs() < 1e-6 * s.dist);
        assert_eq!(s.p, position);
        assert!(s.delta);
        assert_eq!(s.pdf, 1.0);
        // No other technique can find a delta light.
        assert_eq!(l.pdf_li(x, s.wi, s.p, s.n), 0.0);
    }
    // A directional light: irradiance E along -direction, at infinity.
    let direction = Vec3::new(0.0, -0.6, -0.8);
    let d = Light::Punctual(Punctual::Directional {
        direction,
        irradiance: Vec3::splat(2.0),
        scene_radius: 5.0,
    });
    let s = d.sample_li(Vec3::ONE, Vec2::ZERO).expect("directional");
    assert_eq!(s.wi, -direction);
    assert_eq!(s.li, Vec3::splat(2.0));
    assert!(s.dist.is_infinite() && s.delta);
}

#[test]
fn spot_falloff_is_the_gltf_ramp() {
    let (inner, outer) = (20f32.to_radians().cos(), 35f32.to_radians().cos());
    // 1 inside the inner cone, 0 outside the outer one.
    for deg in [0.0f32, 10.0, 19.9] {
        assert_eq!(
            spot_falloff(deg.to_radians().cos(), inner, outer),
            1.0,
            "{deg}°"
        );
    }
    for deg in [35.1f32, 60.0, 90.0, 180.0] {
        assert_eq!(
            spot_falloff(deg.to_radians().cos(), inner, outer),
            0.0,
            "{deg}°"
        );
    }
    // Monotone (non-increasing in the angle) and continuous in between: the squared linear
    // ramp in cos θ of the KHR_lights_punctual reference.
    let mut prev = 1.0;
    for k in 0..=1000 {
        let deg = 19.0 + 17.0 * k as f32 / 1000.0;
        let c = deg.to_radians().cos();
        let s = spot_falloff(c, inner, outer);
        assert!(s <= prev + 1e-7, "not monotone at {deg}°");
        assert!(prev - s < 0.01, "jump at {deg}°");
        let t = ((c - outer) / (inner - outer)).clamp(0.0, 1.0);
        assert!((s - t * t).abs() < 1e-6);
        prev = s;
    }
    // Degenerate cone (inner == outer): a hard edge.
    assert_eq!(spot_falloff(0.95, 0.9, 0.9), 1.0);
    assert_eq!(spot_falloff(0.85, 0.9, 0.9), 0.0);

    // The spot light applies it to I / d², and gives no sample outside the outer cone.
    let intensity = Vec3::new(4.0, 2.0, 1.0);
    let spot = Light::Punctual(Punctual::Spot {
        position: Vec3::ZERO,
        axis: Vec3::new(0.0, 0.0, -1.0),
        intensity,
        cos_inner: inner,
        cos_outer: outer,
    });
    for deg in [0.0f32, 25.0, 30.0, 34.0, 40.0] {
        let t = deg.to_radians();
        let x = 2.0 * Vec3::new(t.sin(), 0.0, -t.cos());
        let s = spot.sample_li(x, Vec2::ZERO);
        let fall = spot_falloff(t.cos(), inner, outer);
        match s {
            Some(s) => {
                let expected = intensity * (fall / 4.0);
                assert!((s.li - expected).abs().max_element() < 1e-5, "{deg}°");
                assert!(s.delta && s.pdf == 1.0);
            }
            None => assert_eq!(fall, 0.0, "{deg}°"),
        }
    }
}

// ---------------------------------------------------------------------------------------
// Spherical triangle sampling (Arvo 1995)
// ---------------------------------------------------------------------------------------

/// Barycentric coordinates (b1, b2) of `x` in the triangle, in f64, and its distance to the
/// triangle's plane.
fn barycentric(x: DVec3, p: &[Vec3; 3]) -> (f64, f64, f64) {
    let [p0, p1, p2] = p.map(|v| v.as_dvec3());
    let (e1, e2) = (p1 - p0, p2 - p0);
    let n = e1.cross(e2);
    let d = x - p0;
    let plane = d.dot(n) / n.length();
    let b1 = d.cross(e2).dot(n) / n.length_squared();
    let b2 = e1.cross(d).dot(n) / n.length_squared();
    (b1, b2, plane)
}

#[test]
fn spherical_triangle_rule_is_shared_by_sample_and_pdf() {
    // Inside [MIN, MAX] = [2, 6.22] sr the density is 1 / Ω, Ω by the f64 solid angle of
    // the test; outside it is the area density. pdf_li must follow the same rule as
    // sample_li.
    let light = triangle(false);
    let l = Light::Triangle(light);
    let mut rng = SplitMix64::new(0x5a7);
    for (p, spherical) in [
        (Vec3::new(0.1, 0.0, 0.3), true),
        // 0.012 sr: far below the threshold (pbrt-v4's 3e-4 would sample it spherically).
        (Vec3::new(4.0, 0.5, 0.6), false),
        // About 0.2 sr: area sampling.
        (Vec3::new(0.1, 0.0, -2.2), false),
        (Vec3::new(0.1, 0.0, 0.85), true),
        (Vec3::new(0.1, 0.0, -88.0), false),
        // Almost on the triangle: more than 6.22 sr.
        (Vec3::new(0.1, 0.0, 0.999), false),
    ] {
        let omega = triangle_solid_angle(p.as_dvec3(), &light.p);
        assert_eq!(
            light.spherical_solid_angle(p).is_some(),
            spherical,
            "{p}: Ω {omega}"
        );
        for _ in 0..1000 {
            let u = Vec2::new(rng.next_f32(), rng.next_f32());
            let Some(s) = l.sample_li(p, u) else {
                continue;
            };
            let pdf = l.pdf_li(p, s.wi, s.p, s.n);
            assert!(s.pdf.is_finite() && s.pdf > 0.0);
            if spherical {
                // Exactly: the same rule and the same solid angle.
                assert_eq!(s.pdf, pdf, "{p}");
                assert!(
                    ((s.pdf as f64) * omega - 1.0).abs() < 1e-5,
                    "{p}: {}",
                    s.pdf
                );
            } else {
                let d = (s.p - p).as_dvec3();
                let cos = light.n.as_dvec3().dot(d.normalize()).abs();
                let area_pdf = d.length_squared() / (cos * light.area as f64);
                assert!(((s.pdf as f64) / area_pdf - 1.0).abs() < 1e-3, "{p}");
                // pdf_li recomputes d² / cos from the point: equal to rounding.
                assert!((s.pdf - pdf).abs() <= 1e-4 * pdf, "{p}: {} vs {pdf}", s.pdf);
            }
        }
    }
    // Degenerate configurations never give NaN: on the triangle's plane (Ω = 0), at a
    // vertex, at its centroid.
    let c = (light.p[0] + light.p[1] + light.p[2]) / 3.0;
    let in_plane = light.p[0] + 2.0 * (light.p[1] - light.p[0]);
    for p in [in_plane, light.p[0], c] {
        assert!(light.spherical_solid_angle(p).is_none(), "{p}");
        for k in 0..100 {
            let u = Vec2::new((k as f32 + 0.5) / 100.0, 0.37);
            if let Some(s) = l.sample_li(p, u) {
                assert!(s.pdf.is_finite() && s.wi.is_finite() && s.p.is_finite());
            }
        }
    }
}

#[test]
fn spherical_triangle_samples_lie_on_the_triangle() {
    let mut rng = SplitMix64::new(0x0a7e);
    for tp in triangle_points() {
        let light = triangle(tp.two_sided);
        if light.spherical_solid_angle(tp.p).is_none() {
            continue;
        }
        let l = Light::Triangle(light);
        let scale = tp.p.distance(light.p[0]) as f64;
        for _ in 0..20_000 {
            let u = Vec2::new(rng.next_f32(), rng.next_f32());
            let s = l.sample_li(tp.p, u).expect("the front is seen");
            let (b1, b2, plane) = barycentric(s.p.as_dvec3(), &light.p);
            assert!(
                plane.abs() < 1e-5 * scale.max(1.0),
                "{}: off the plane by {plane}",
                tp.name
            );
            assert!(
                b1 >= -1e-5 && b2 >= -1e-5 && b1 + b2 <= 1.0 + 1e-5,
                "{}: outside ({b1}, {b2})",
                tp.name
            );
            let along = (s.p - tp.p).normalize();
            assert!((along - s.wi).length() < 1e-5);
        }
        // The samples cover the triangle: all three corner regions are reached.
        let mut corners = [0usize; 3];
        for _ in 0..20_000 {
            let u = Vec2::new(rng.next_f32(), rng.next_f32());
            let s = l.sample_li(tp.p, u).expect("the front is seen");
            let (b1, b2, _) = barycentric(s.p.as_dvec3(), &light.p);
            let b = [1.0 - b1 - b2, b1, b2];
            for (k, &bk) in b.iter().enumerate() {
                if bk > 0.8 {
                    corners[k] += 1;
                }
            }
        }
        assert!(corners.iter().all(|&c| c > 0), "{}: {corners:?}", tp.name);
    }
}

#[test]
fn spherical_triangle_pdf_integrates_to_one() {
    // Midpoint quadrature of pdf_li over a cap about the direction to the centroid that
    // holds the triangle, in (cos θ, φ) cells of equal solid angle: ∫ pdf dω = 1.
    for tp in triangle_points() {
        let light = triangle(tp.two_sided);
        if light.spherical_solid_angle(tp.p).is_none() {
            continue;
        }
        let c = (light.p[0] + light.p[1] + light.p[2]) / 3.0;
        let axis = (c - tp.p).normalize();
        let frame = Frame::from_normal(axis);
        let min_cos = light
            .p
            .iter()
            .map(|v| axis.dot((*v - tp.p).normalize()) as f64)
            .fold(1.0, f64::min);
        // A cap a little wider than the vertices (a cap over 90° is the whole sphere).
        let z0 = if min_cos > 0.05 {
            1.0 - 1.2 * (1.0 - min_cos)
        } else {
            -1.0
        };
        let (nz, nphi) = (2000usize, 2000usize);
        let cell = (1.0 - z0) * 2.0 * PI / (nz * nphi) as f64;
        let mut integral = 0.0f64;
        for i in 0..nz {
            let z = z0 + (1.0 - z0) * (i as f64 + 0.5) / nz as f64;
            let r = (1.0 - z * z).sqrt();
            for j in 0..nphi {
                let phi = 2.0 * PI * (j as f64 + 0.5) / nphi as f64;
                let local = DVec3::new(r * phi.cos(), r * phi.sin(), z);
                let w = frame.to_world(local.as_vec3());
                integral += triangle_pdf(&light, tp.p, w) as f64 * cell;
            }
        }
        eprintln!("triangle {}: ∫ pdf_li dω = {integral:.5}", tp.name);
        assert!((integral - 1.0).abs() < 3e-3, "{}: {integral}", tp.name);
    }
}

// ---------------------------------------------------------------------------------------
// Light hierarchy
// ---------------------------------------------------------------------------------------

/// Many lights: 300 small triangles scattered in a 10 m box with random orientations
/// (a third two-sided, a few black), three spheres, a point and a spot light and an
/// environment. Returned with the reference points (position, normal) to test from.
fn many_lights() -> (Vec<Light>, Vec<(Vec3, Vec3)>) {
    let mut rng = SplitMix64::new(0x11a7_7ee5);
    let mut r = || rng.next_f32();
    let mut lights = Vec::new();
    for k in 0..300 {
        let c = Vec3::new(10.0 * r() - 5.0, 10.0 * r() - 5.0, 10.0 * r() - 5.0);
        let size = 0.05 + 0.4 * r();
        let p = [0, 1, 2].map(|_| c + size * Vec3::new(r() - 0.5, r() - 0.5, r() - 0.5));
        let radiance = if k % 37 == 5 {
            Vec3::ZERO
        } else {
            Vec3::new(r(), r(), r()) * 5.0
        };
        if let Some(t) = TriangleLight::new(p, radiance, k % 3 == 0) {
            lights.push(Light::Triangle(t));
        }
    }
    lights.push(Light::Sphere(SphereLight {
        center: Vec3::new(1.0, 2.0, 3.0),
        radius: 0.5,
        radiance: Vec3::splat(3.0),
    }));
    lights.push(Light::Sphere(SphereLight {
        center: Vec3::new(-4.0, 0.0, 1.0),
        radius: 0.1,
        radiance: Vec3::splat(40.0),
    }));
    lights.push(Light::Sphere(SphereLight {
        center: Vec3::new(0.0, -3.0, -3.0),
        radius: 1.0,
        radiance: Vec3::ZERO,
    }));
    lights.push(Light::Punctual(Punctual::Point {
        position: Vec3::new(2.0, -2.0, 0.0),
        intensity: Vec3::splat(2.0),
    }));
    lights.push(Light::Punctual(Punctual::Spot {
        position: Vec3::new(-2.0, 3.0, 0.0),
        axis: Vec3::new(0.0, -1.0, 0.0),
        intensity: Vec3::splat(5.0),
        cos_inner: 0.9,
        cos_outer: 0.8,
    }));
    lights.push(Light::Environment(Environment::uniform(
        Vec3::splat(0.02),
        9.0,
    )));
    let points = vec![
        (Vec3::ZERO, Vec3::Z),
        (
            Vec3::new(4.0, -4.0, 4.5),
            Vec3::new(-1.0, 1.0, -1.0).normalize(),
        ),
        // No normal (a transmissive surface): lights on both sides count.
        (Vec3::new(-1.0, 2.0, -0.5), Vec3::ZERO),
        // Far outside the lights.
        (Vec3::new(30.0, 0.0, 0.0), Vec3::X),
        // On a light's plane, inside the cloud.
        (Vec3::new(0.5, 0.5, 0.0), Vec3::new(0.0, 1.0, 0.0)),
    ];
    (lights, points)
}

#[test]
fn light_tree_pmf_matches_select_and_sums_to_one() {
    let (lights, points) = many_lights();
    let set = LightSet::new(lights.clone());
    // The tree is a pure function of the lights.
    let again = LightSet::new(lights);
    for &(p, n) in &points {
        let pmf: Vec<f32> = (0..set.lights.len()).map(|i| set.pmf_at(p, n, i)).collect();
        let again_pmf: Vec<f32> = (0..set.lights.len())
            .map(|i| again.pmf_at(p, n, i))
            .collect();
        assert_eq!(pmf, again_pmf);
        for (i, &q) in pmf.iter().enumerate() {
            assert!(q >= 0.0 && q.is_finite());
            if set.lights[i].power() <= 0.0 {
                assert_eq!(q, 0.0, "dark light {i}");
            }
        }
        // Every u on a grid: the reported probability is pmf_at's, bit for bit.
        let m = 1 << 14;
        let mut none = 0usize;
        for k in 0..m {
            let u = (k as f32 + 0.5) / m as f32;
            match set.select_at(u, p, n) {
                Some((i, q)) => {
                    assert_eq!(q, pmf[i], "{p}: light {i} at u = {u}");
                    assert!(q > 0.0);
                }
                None => none += 1,
            }
        }
        // The pmfs sum to one minus the probability of no sample: the traversal reaching
        // a node whose children both have zero importance (the node's merged cone is wider
        // than its children's). That loss must be small.
        let total: f64 = pmf.iter().map(|&q| q as f64).sum();
        let sampled = 1.0 - none as f64 / m as f64;
        assert!(
            (total - sampled).abs() <= 2.0 / m as f64 + 1e-5,
            "{p}: Σ pmf = {total}, sampled fraction {sampled}"
        );
        assert!(total > 0.99 && total <= 1.0 + 1e-5, "{p}: Σ pmf = {total}");
        eprintln!("light tree from {p}: Σ pmf = {total:.6}");
        for u in [0.0, 1.0 - f32::EPSILON / 2.0] {
            if let Some((i, q)) = set.select_at(u, p, n) {
                assert_eq!(q, pmf[i]);
            }
        }
    }
    // Infinite lights keep their global probability; out-of-range indices have none.
    let env = set.environment.expect("environment") as usize;
    assert_eq!(set.pmf_at(Vec3::ZERO, Vec3::Z, env), set.pmf(env));
    assert_eq!(set.pmf_at(Vec3::ZERO, Vec3::Z, 10_000), 0.0);
}

#[test]
fn light_tree_selection_matches_pmf_chi2() {
    // Pearson's chi-squared of selection counts against pmf_at per reference point, cells
    // with fewer than 5 expected pooled, Šidák-corrected over the points at 1%.
    let (lights, points) = many_lights();
    let set = LightSet::new(lights);
    let cfg = Chi2Config::new(points.len());
    let threshold = cfg.single_test_significance();
    let n = 400_000usize;
    for (k, &(p, nrm)) in points.iter().enumerate() {
        let mut rng = SplitMix64::new(0x7ee_c412 + k as u64);
        let mut counts = vec![0u64; set.lights.len()];
        for _ in 0..n {
            if let Some((i, _)) = set.select_at(rng.next_f32(), p, nrm) {
                counts[i] += 1;
            }
        }
        let (mut stat, mut cells) = (0.0, 0usize);
        let (mut pooled_e, mut pooled_o) = (0.0, 0.0);
        for (i, &c) in counts.iter().enumerate() {
            let e = set.pmf_at(p, nrm, i) as f64 * n as f64;
            if e == 0.0 {
                assert_eq!(c, 0, "light {i} of zero pmf picked from {p}");
            } else if e < 5.0 {
                pooled_e += e;
                pooled_o += c as f64;
            } else {
                stat += (c as f64 - e).powi(2) / e;
                cells += 1;
            }
        }
        if pooled_e > 0.0 {
            stat += (pooled_o - pooled_e).powi(2) / pooled_e;
            cells += 1;
        }
        let p_value = chi2_survival(stat, cells - 1);
        eprintln!(
            "light tree from {p}: chi2 {stat:.1}, dof {}, p {p_value:.3}",
            cells - 1
        );
        assert!(
            p_value > threshold,
            "from {p}: p = {p_value} (threshold {threshold})"
        );
    }
}

#[test]
fn light_tree_zero_pmf_only_for_lights_that_cannot_contribute() {
    // A light the tree never picks from (p, n) must give no light there: every sample of
    // it is invalid or arrives at grazing/back-facing angles of the receiver... or is from
    // a light that faces away. Checked by sampling each such light.
    let (lights, points) = many_lights();
    let set = LightSet::new(lights);
    let mut rng = SplitMix64::new(0x2e10);
    let mut zero = 0;
    for &(p, n) in &points {
        for (i, l) in set.lights.iter().enumerate() {
            if set.pmf_at(p, n, i) > 0.0 || l.power() <= 0.0 {
                continue;
            }
            zero += 1;
            for _ in 0..64 {
                let u = Vec2::new(rng.next_f32(), rng.next_f32());
                if let Some(s) = l.sample_li(p, u) {
                    let cos = if n == Vec3::ZERO {
                        1.0
                    } else {
                        n.dot(s.wi).abs()
                    };
                    assert!(
                        s.li == Vec3::ZERO || cos <= 1e-6,
                        "light {i} has pmf 0 at {p} but gives {:?}",
                        s.li
                    );
                }
            }
        }
    }
    assert!(zero > 0, "the scene must have back-facing lights");
    // Behind every one-sided light of a wall facing +z: no sample at all.
    let wall: Vec<Light> = (0..16)
        .map(|k| {
            let x = k as f32;
            Light::Triangle(
                TriangleLight::new(
                    [
                        Vec3::new(x, 0.0, 0.0),
                        Vec3::new(x + 1.0, 0.0, 0.0),
                        Vec3::new(x, 1.0, 0.0),
                    ],
                    RADIANCE,
                    false,
                )
                .expect("triangle"),
            )
        })
        .collect();
    let set = LightSet::new(wall);
    let behind = Vec3::new(8.0, 0.5, -2.0);
    assert!(set.select_at(0.3, behind, Vec3::Z).is_none());
    assert!((0..16).all(|i| set.pmf_at(behind, Vec3::Z, i) == 0.0));
    let front = Vec3::new(8.0, 0.5, 2.0);
    let total: f32 = (0..16).map(|i| set.pmf_at(front, Vec3::Z, i)).sum();
    assert!((total - 1.0).abs() < 1e-5);
}

#[test]
fn light_tree_quads_share_bounds_and_stay_consistent() {
    // Quad lights: the two triangles of each share their box and normal, so the tree
    // stores their split (by power: one triangle is twice as bright). select_at and pmf_at
    // must still agree bit for bit and sum to one where every quad faces the point.
    let mut lights = Vec::new();
    for k in 0..8 {
        let x = 2.0 * k as f32;
        let [a, b, c, d] = [
            Vec3::new(x, 0.0, 3.0),
            Vec3::new(x + 1.0, 0.0, 3.0),
            Vec3::new(x + 1.0, 1.0, 3.0),
            Vec3::new(x, 1.0, 3.0),
        ];
        // Clockwise seen from above: both emit downward.
        for (tri, scale) in [([a, c, b], 1.0), ([a, d, c], 2.0)] {
            let l = TriangleLight::new(tri, RADIANCE * scale, false).expect("triangle");
            lights.push(Light::Triangle(l));
        }
    }
    let set = LightSet::new(lights);
    for p in [Vec3::new(3.0, 0.5, 0.0), Vec3::new(-5.0, 2.0, 1.0)] {
        let pmf: Vec<f32> = (0..set.lights.len())
            .map(|i| set.pmf_at(p, Vec3::Z, i))
            .collect();
        let total: f64 = pmf.iter().map(|&q| q as f64).sum();
        assert!((total - 1.0).abs() < 1e-5, "{p}: Σ pmf = {total}");
        // The brighter triangle of each quad has twice the probability of the other.
        for q in pmf.chunks(2) {
            assert!((q[1] / q[0] - 2.0).abs() < 1e-5, "{q:?}");
        }
        let m = 1 << 12;
        for k in 0..m {
            let u = (k as f32 + 0.5) / m as f32;
            let (i, q) = set.select_at(u, p, Vec3::Z).expect("the quads face p");
            assert_eq!(q, pmf[i]);
        }
    }
}

// ---------------------------------------------------------------------------------------
// Image environment
// ---------------------------------------------------------------------------------------

/// A 24x12 image environment with varied texels (a smooth gradient times hashed noise,
/// one texel 200 times brighter, one black row) rotated by 35°.
fn image_environment() -> Environment {
    let (w, h) = (24u32, 12u32);
    let mut rng = SplitMix64::new(0xe4f1);
    let mut texels: Vec<Vec3> = (0..w * h)
        .map(|i| {
            let (x, y) = (i % w, i / w);
            let base = 0.2 + (x as f32 / w as f32) * (1.0 + y as f32 / h as f32);
            Vec3::new(
                base * rng.next_f32(),
                base * rng.next_f32(),
                base * rng.next_f32(),
            )
        })
        .collect();
    texels[5 * w as usize + 17] = Vec3::splat(200.0);
    for t in &mut texels[9 * w as usize..10 * w as usize] {
        *t = Vec3::ZERO;
    }
    let map = tessera_scene::EnvironmentMap::new("test", w, h, texels)
        .unwrap()
        .rotated(35.0);
    let mut env = Environment::uniform(RADIANCE, 10.0);
    env.image = Some(std::sync::Arc::new(super::environment::EnvImage::new(&map)));
    env
}

#[test]
fn image_environment_sampling_matches_pdf_chi2() {
    // Importance sampling by luminance × sin θ against its claimed solid-angle density, on
    // 40 x 80 bins (the pdf's texel edges are resolved by the adaptive cubature); and a
    // negative control: the same samples against the density without the sin θ Jacobian
    // (renormalised), which must be rejected.
    let env = Light::Environment(image_environment());
    let cfg = Chi2Config::new(2);
    let report = chi2_sphere(
        "image environment",
        &cfg,
        |u2, _| env.sample_li(Vec3::ZERO, u2).map(|s| s.wi),
        |w| env.pdf_li(Vec3::ZERO, w, Vec3::ZERO, Vec3::ZERO),
    )
    .unwrap_or_else(|e| panic!("{e}"));
    eprintln!(
        "image environment chi2: statistic {:.1}, dof {}, p = {:.4}",
        report.statistic, report.dof, report.p_value
    );
    let Light::Environment(e) = &env else {
        unreachable!()
    };
    let wrong = |w: Vec3| {
        // pdf_uv / (2π²) with sin θ dropped, scaled to integrate to about one: wrong
        // shape near the poles (sin θ from the horizontal part, never zero off the axis).
        let sin = (w.x * w.x + w.z * w.z).sqrt();
        e.pdf_li(w) * sin * 4.0 / PI as f32
    };
    let control = chi2_sphere(
        "image environment control",
        &cfg,
        |u2, _| env.sample_li(Vec3::ZERO, u2).map(|s| s.wi),
        wrong,
    );
    assert!(
        control.is_err(),
        "the control must be rejected: {control:?}"
    );
}

#[test]
fn image_environment_sample_pdf_equals_pdf_li_and_radiance_equals_le() {
    // Every sample reports the density pdf_li gives its direction and the radiance le
    // gives it (the same texel), up to rounding at texel edges (a rare neighbour).
    let e = image_environment();
    let light = Light::Environment(e.clone());
    let mut rng = SplitMix64::new(0x9df);
    let (mut n, mut mismatched) = (0usize, 0usize);
    let mut sum = DVec3::ZERO;
    for _ in 0..200_000 {
        let u = Vec2::new(rng.next_f32(), rng.next_f32());
        let Some(s) = light.sample_li(Vec3::ZERO, u) else {
            continue;
        };
        n += 1;
        let pdf = light.pdf_li(Vec3::ZERO, s.wi, Vec3::ZERO, Vec3::ZERO);
        let same = (pdf - s.pdf).abs() <= 1e-3 * s.pdf
            && (e.le(s.wi) - s.li).abs().max_element() <= 1e-5 * s.li.max_element();
        if !same {
            mismatched += 1;
        }
        assert!(s.pdf > 0.0 && s.li.max_element() > 0.0, "{s:?}");
        sum += (s.li / s.pdf).as_dvec3();
    }
    assert!(n > 199_000, "{n} valid samples of 200000");
    assert!(
        mismatched * 10_000 < n,
        "{mismatched} of {n} samples disagree with pdf_li/le"
    );
    // The estimate of ∫ L dω is the radiance factor times the image's integral.
    let want = (RADIANCE * e.image.as_ref().unwrap().integral).as_dvec3();
    let got = sum / n as f64;
    assert!(
        ((got - want) / want).abs().max_element() < 0.01,
        "∫ L dω: {got} vs {want}"
    );
}

#[test]
fn the_bounding_sphere_never_decides_against_the_exact_rule() {
    // The early out of the solid-angle rule skips the exact angle only where it is below
    // the threshold: over points from inside the bounding sphere to far outside it, around
    // triangles of several shapes (equilateral, long and thin, nearly degenerate), the
    // rule with the early out gives the same answer and the same angle as without. The
    // points concentrate where the bound is tight (a few radii from the centroid), and
    // some of them are sampled by solid angle.
    let shapes = [
        [Vec3::ZERO, Vec3::X, Vec3::new(0.5, 0.866, 0.0)],
        [
            Vec3::ZERO,
            Vec3::new(3.0, 0.0, 0.0),
            Vec3::new(1.5, 0.1, 0.0),
        ],
        [
            Vec3::ZERO,
            Vec3::new(1.0, 0.0, 0.0),
            Vec3::new(0.5, 1e-3, 0.0),
        ],
        [
            Vec3::new(1.0, 2.0, 3.0),
            Vec3::new(1.2, 2.0, 3.1),
            Vec3::new(1.0, 2.3, 2.9),
        ],
    ];
    let mut rng = SplitMix64::new(0xb0b);
    let (mut spherical, mut exact_calls) = (0u32, 0u32);
    for p in shapes {
        let light = TriangleLight::new(p, Vec3::ONE, true).unwrap();
        let c = (p[0] + p[1] + p[2]) / 3.0;
        let r = (p[0] - c)
            .length()
            .max((p[1] - c).length())
            .max((p[2] - c).length());
        for _ in 0..200_000 {
            let dir = Vec3::new(
                rng.next_f32() - 0.5,
                rng.next_f32() - 0.5,
                rng.next_f32() - 0.5,
            )
            .normalize_or(Vec3::Z);
            let q = c + dir * r * (0.05 + 3.0 * rng.next_f32());
            let exact = light.exact_spherical_solid_angle(q);
            assert_eq!(light.spherical_solid_angle(q), exact, "{q}");
            spherical += exact.is_some() as u32;
            exact_calls += 1;
        }
    }
    assert!(spherical > 1000, "{spherical} of {exact_calls}");
}
