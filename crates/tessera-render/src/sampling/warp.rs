//! Warps from the unit square to the domains a renderer samples, with their densities.
//!
//! Each warp maps a uniform point `u` of `[0, 1)^2` to a point of a 2-manifold (sphere,
//! hemisphere, cone, disk, triangle) or to a direction distributed like a lobe; the matching
//! `*_pdf` function is the density of the result with respect to the stated measure (solid
//! angle for directions, area for points). Most are derived with Arvo's recipe in Arvo 2001, section 4.2:
//! take a parametrization, compute its area element (Jacobian), integrate it to a marginal and
//! a conditional CDF and invert both (Arvo 2001, section 4.3). Being smooth, monotone maps of the
//! square, they carry the stratification of a QMC point set over to the target domain.
//!
//! Conventions: directions are in a local shading frame whose `+z` axis is the surface normal
//! (see [`Frame`]); `theta` is the polar angle from `+z` and `phi` the azimuth. All functions
//! are robust for `u` anywhere in `[0, 1)^2` (including exactly 0 and `1 - 2^-24`): no NaN,
//! unit-length directions within rounding.
//!
//! Trigonometric and transcendental functions come from the platform's `libm` (`sin`, `cos`,
//! `ln`, `exp_m1`, `powf`); they are deterministic for one build on one platform.

use std::f32::consts::{FRAC_1_PI, FRAC_PI_2, FRAC_PI_4, PI, TAU};

use glam::{Vec2, Vec3};

/// `1 / (4 pi)`.
const INV_4PI: f32 = 0.25 * FRAC_1_PI;
/// `1 / (2 pi)`.
const INV_2PI: f32 = 0.5 * FRAC_1_PI;

/// Unit vector with polar angle given by `(cos theta, sin theta)` and azimuth `2 pi v`.
#[inline]
fn spherical(cos_theta: f32, sin_theta: f32, v: f32) -> Vec3 {
    let (s, c) = (TAU * v).sin_cos();
    Vec3::new(sin_theta * c, sin_theta * s, cos_theta)
}

/// Uniform direction on the unit sphere (Archimedes: `z = cos theta` uniform in `[-1, 1]`,
/// `phi` uniform); see [`uniform_sphere_pdf`].
///
/// `sin theta = 2 sqrt(u (1 - u))` equals `sqrt(1 - z^2)` for `z = 1 - 2u` but has no
/// cancellation near the poles.
pub fn square_to_uniform_sphere(u: Vec2) -> Vec3 {
    let z = 1.0 - 2.0 * u.x;
    let sin_theta = 2.0 * (u.x * (1.0 - u.x)).max(0.0).sqrt();
    spherical(z, sin_theta, u.y)
}

/// Density of [`square_to_uniform_sphere`] with respect to solid angle: `1 / (4 pi)`.
pub fn uniform_sphere_pdf() -> f32 {
    INV_4PI
}

/// Uniform direction on the hemisphere `z >= 0` (Arvo 2001, section 4.3.3, eq. 4.26 with `z1 -> 1 - z1`:
/// `z = 1 - u.x`, `sin theta = sqrt(u.x (2 - u.x))`); see [`uniform_hemisphere_pdf`].
pub fn square_to_uniform_hemisphere(u: Vec2) -> Vec3 {
    let z = 1.0 - u.x;
    let sin_theta = (u.x * (2.0 - u.x)).max(0.0).sqrt();
    spherical(z, sin_theta, u.y)
}

/// Density of [`square_to_uniform_hemisphere`] with respect to solid angle: `1 / (2 pi)` on
/// the upper hemisphere (the caller checks `z >= 0`).
pub fn uniform_hemisphere_pdf() -> f32 {
    INV_2PI
}

/// Shirley–Chiu concentric map of the square onto the unit disk (Shirley & Chiu 1997, in
/// Shirley's later branch-reduced form): concentric squares go to concentric circles, so it
/// is area-preserving with far less distortion than the polar map `sqrt(u.x), 2 pi u.y` of
/// Arvo 2001, section 4.3.2 (eq. 4.23), which keeps strata compact. Density `1 / pi` with respect to
/// area on the unit disk.
#[inline]
pub fn square_to_concentric_disk(u: Vec2) -> Vec2 {
    let a = 2.0 * u.x - 1.0;
    let b = 2.0 * u.y - 1.0;
    if a == 0.0 && b == 0.0 {
        return Vec2::ZERO;
    }
    // On the square ring of half-width r, the angle advances linearly along each side.
    let (r, phi) = if a.abs() > b.abs() {
        (a, FRAC_PI_4 * (b / a))
    } else {
        (b, FRAC_PI_2 - FRAC_PI_4 * (a / b))
    };
    let (s, c) = phi.sin_cos();
    Vec2::new(r * c, r * s)
}

/// Cosine-weighted direction on the hemisphere `z >= 0` by Malley's method: a uniform point
/// of the unit disk (here [`square_to_concentric_disk`]) projected up onto the hemisphere has
/// density `cos theta / pi` in solid angle, because projecting to the disk multiplies solid
/// angle by `cos theta` (Nusselt analog). See [`cosine_hemisphere_pdf`].
#[inline]
pub fn square_to_cosine_hemisphere(u: Vec2) -> Vec3 {
    let d = square_to_concentric_disk(u);
    let z = (1.0 - d.length_squared()).max(0.0).sqrt();
    Vec3::new(d.x, d.y, z)
}

/// Density of [`square_to_cosine_hemisphere`] with respect to solid angle:
/// `max(cos theta, 0) / pi`.
#[inline]
pub fn cosine_hemisphere_pdf(cos_theta: f32) -> f32 {
    cos_theta.max(0.0) * FRAC_1_PI
}

/// Uniform direction in the cone `cos theta >= cos_theta_max` around `+z`
/// (Shirley 2001, section 3, spherical luminaires: `cos theta` uniform in `[cos_theta_max, 1]`);
/// see [`uniform_cone_pdf`].
///
/// For very small cones (e.g. a distant spherical light) prefer
/// [`square_to_uniform_cone_one_minus_cos`] with `1 - cos_theta_max` computed stably (see
/// [`cone_one_minus_cos_from_sin2`]): `cos_theta_max` itself cannot resolve angles below
/// about `3.5e-4` rad in `f32`.
pub fn square_to_uniform_cone(u: Vec2, cos_theta_max: f32) -> Vec3 {
    // For cos_theta_max in [0.5, 1] this subtraction is exact (Sterbenz lemma).
    square_to_uniform_cone_one_minus_cos(u, 1.0 - cos_theta_max)
}

/// [`square_to_uniform_cone`] parametrized by `one_minus_cos_max = 1 - cos_theta_max`
/// in `[0, 2]`.
///
/// Works with `1 - cos theta = u.x (1 - cos_theta_max)` throughout and takes
/// `sin theta = sqrt((1 - cos)(1 + cos)) = sqrt(w (2 - w))` from it, so the direction keeps
/// full relative precision in its tangential components even when `cos theta` rounds to 1.
pub fn square_to_uniform_cone_one_minus_cos(u: Vec2, one_minus_cos_max: f32) -> Vec3 {
    let w = u.x * one_minus_cos_max;
    let sin_theta = (w * (2.0 - w)).max(0.0).sqrt();
    spherical(1.0 - w, sin_theta, u.y)
}

/// Density of [`square_to_uniform_cone`] with respect to solid angle, for directions inside
/// the cone (zero outside; the caller tests membership): one over the cone's solid angle
/// `2 pi (1 - cos_theta_max)`. A degenerate cone (`cos_theta_max == 1`) is a delta
/// distribution and gives `+inf`; treat it as a point light.
pub fn uniform_cone_pdf(cos_theta_max: f32) -> f32 {
    uniform_cone_pdf_one_minus_cos(1.0 - cos_theta_max)
}

/// [`uniform_cone_pdf`] parametrized by `one_minus_cos_max = 1 - cos_theta_max`.
pub fn uniform_cone_pdf_one_minus_cos(one_minus_cos_max: f32) -> f32 {
    INV_2PI / one_minus_cos_max
}

/// `1 - cos theta_max` from `sin^2 theta_max` without cancellation:
/// `1 - cos = sin^2 / (1 + cos)`. For a sphere of radius `r` seen from distance `d > r`,
/// `sin^2 theta_max = r^2 / d^2`. Values `>= 1` give 1 (a hemisphere).
pub fn cone_one_minus_cos_from_sin2(sin2_theta_max: f32) -> f32 {
    let s2 = sin2_theta_max.clamp(0.0, 1.0);
    s2 / (1.0 + (1.0 - s2).sqrt())
}

/// Uniform point in a triangle as barycentric coordinates `(b0, b1)` (the third is
/// `1 - b0 - b1`), i.e. the point `b0 v0 + b1 v1 + (1 - b0 - b1) v2`; uniform in area, so the
/// density is `1 / area` for any triangle.
///
/// Heitz 2019, "A Low-Distortion Map Between Triangle and Square": the square is split by
/// its diagonal and each half is sheared onto the triangle `b0, b1 >= 0, b0 + b1 <= 1` by a
/// linear map of determinant 1/2. Unlike the square-root fold of Arvo 2001, section 4.3.1
/// (eq. 4.20) it is piecewise linear, so it distorts strata far less.
pub fn square_to_uniform_triangle(u: Vec2) -> (f32, f32) {
    if u.y > u.x {
        let b0 = 0.5 * u.x;
        (b0, u.y - b0)
    } else {
        let b1 = 0.5 * u.y;
        (u.x - b1, b1)
    }
}

/// Direction distributed like a normalized Phong lobe `(n + 1) / (2 pi) cos^n alpha` around
/// `+z` (Arvo 2001, section 4.3.4, eq. 4.28: `cos alpha = u.x^(1 / (n + 1))`); see [`phong_lobe_pdf`].
///
/// `1 - cos alpha = -expm1(ln(u.x) / (n + 1))` is computed directly so that `sin alpha`
/// stays accurate for large exponents, where `cos alpha` is within a few ulps of 1.
pub fn square_to_phong_lobe(u: Vec2, exponent: f32) -> Vec3 {
    // ln(0) = -inf gives w = 1 (the horizon), not NaN.
    let w = -(u.x.ln() / (exponent + 1.0)).exp_m1();
    let sin_alpha = (w * (2.0 - w)).max(0.0).sqrt();
    spherical(1.0 - w, sin_alpha, u.y)
}

/// Density of [`square_to_phong_lobe`] with respect to solid angle:
/// `(n + 1) / (2 pi) cos^n alpha` for `cos alpha > 0`, else 0. The normalization follows
/// from `int_0^{pi/2} cos^n(a) sin(a) da = 1 / (n + 1)`.
pub fn phong_lobe_pdf(cos_alpha: f32, exponent: f32) -> f32 {
    if cos_alpha <= 0.0 {
        return 0.0;
    }
    (exponent + 1.0) * INV_2PI * cos_alpha.powf(exponent)
}

/// GGX (Trowbridge–Reitz) normal distribution `D(m)` of an isotropic microsurface with width
/// `alpha` (= roughness^2), as a density of microfacet area per unit macro-surface area and
/// per solid angle of normals: `D(m) = alpha^2 / (pi cos^4 theta (alpha^2 + tan^2 theta)^2)`,
/// zero for `m.z <= 0`. It satisfies `int D(m) cos theta_m d omega_m = 1`.
///
/// For a unit `m`, `cos^2 theta (alpha^2 + tan^2 theta) = m.x^2 + m.y^2 + alpha^2 m.z^2`,
/// which is evaluated instead: no tangent, no cancellation, exact at the peak.
pub fn ggx_d(m: Vec3, alpha: f32) -> f32 {
    if m.z <= 0.0 {
        return 0.0;
    }
    let a2 = alpha * alpha;
    let k = m.x * m.x + m.y * m.y + a2 * m.z * m.z;
    a2 / (PI * k * k)
}

/// Smith's auxiliary function for GGX, `Lambda(w) = (sqrt(1 + alpha^2 tan^2 theta) - 1) / 2`
/// (Heitz 2014, "Understanding the Masking-Shadowing Function"). Depends on `tan^2 theta`
/// only, so it is even in `w.z` (useful for transmission); `+inf` at grazing `w.z == 0`.
///
/// Evaluated as `t / (2 (1 + sqrt(1 + t)))` with `t = alpha^2 tan^2 theta`, which avoids the
/// cancellation of `sqrt(1 + t) - 1` for small `t`.
pub fn ggx_lambda(w: Vec3, alpha: f32) -> f32 {
    let s2 = w.x * w.x + w.y * w.y;
    if s2 == 0.0 {
        return 0.0;
    }
    let z2 = w.z * w.z;
    let t = alpha * alpha * s2 / z2;
    if !t.is_finite() {
        return f32::INFINITY;
    }
    t / (2.0 * (1.0 + (1.0 + t).sqrt()))
}

/// Smith masking function `G1(w) = 1 / (1 + Lambda(w))`: the fraction of the microsurface
/// visible from `w` among the microfacets facing it. Even in `w.z` like [`ggx_lambda`]; the
/// caller applies the hemisphere checks (`w . m > 0`, same side as the geometric normal).
pub fn ggx_g1(w: Vec3, alpha: f32) -> f32 {
    1.0 / (1.0 + ggx_lambda(w, alpha))
}

/// Samples a microfacet normal `m` from the GGX distribution of normals visible from `wo`,
/// `D_wo(m) = G1(wo) max(0, wo . m) D(m) / wo.z` (Heitz 2018, "Sampling the GGX Distribution
/// of Visible Normals", JCGT 7(4)); `wo` must be a unit vector with `wo.z >= 0`.
///
/// The method stretches the view into the configuration where the microsurface is a
/// hemisphere (`alpha = 1`), samples the projected area of that hemisphere as seen from the
/// stretched view (a disk whose half facing away is compressed by `(1 + v.z) / 2`), lifts the
/// point back onto the hemisphere and unstretches the normal. See [`ggx_vndf_pdf`].
pub fn sample_ggx_vndf(wo: Vec3, alpha: f32, u: Vec2) -> Vec3 {
    // Stretched view direction.
    let vh = Vec3::new(alpha * wo.x, alpha * wo.y, wo.z.max(0.0)).normalize_or(Vec3::Z);
    // Orthonormal basis around vh (t1 horizontal; arbitrary when vh is the pole).
    let len2 = vh.x * vh.x + vh.y * vh.y;
    let t1 = if len2 > 0.0 {
        Vec3::new(-vh.y, vh.x, 0.0) / len2.sqrt()
    } else {
        Vec3::X
    };
    let t2 = vh.cross(t1);
    // Uniform point on the unit disk, with its lower half squeezed to the projected
    // hemisphere's visible outline.
    let r = u.x.sqrt();
    let (sp, cp) = (TAU * u.y).sin_cos();
    let p1 = r * cp;
    let s = 0.5 * (1.0 + vh.z);
    let p2 = (1.0 - s) * (1.0 - p1 * p1).max(0.0).sqrt() + s * (r * sp);
    // Reproject onto the hemisphere and unstretch. A tiny positive floor keeps m strictly in
    // the upper hemisphere (where D > 0) when rounding lands the point on the horizon.
    let nh = p1 * t1 + p2 * t2 + (1.0 - p1 * p1 - p2 * p2).max(0.0).sqrt() * vh;
    Vec3::new(alpha * nh.x, alpha * nh.y, nh.z.max(f32::MIN_POSITIVE)).normalize_or(Vec3::Z)
}

/// Density of [`sample_ggx_vndf`] with respect to solid angle of `m`:
/// `D_wo(m) = G1(wo) max(0, wo . m) D(m) / wo.z`, zero for `wo.z <= 0`.
///
/// `G1(wo) / wo.z` is evaluated as `2 / (wo.z + sqrt(wo.z^2 + alpha^2 (wo.x^2 + wo.y^2)))`,
/// which stays finite and accurate at grazing angles where both factors go to zero.
pub fn ggx_vndf_pdf(wo: Vec3, m: Vec3, alpha: f32) -> f32 {
    let wo_m = wo.dot(m);
    if wo.z <= 0.0 || wo_m <= 0.0 {
        return 0.0;
    }
    let g1_over_cos =
        2.0 / (wo.z + (wo.z * wo.z + alpha * alpha * (wo.x * wo.x + wo.y * wo.y)).sqrt());
    g1_over_cos * wo_m * ggx_d(m, alpha)
}

/// Right-handed orthonormal basis `(s, t, n)` with `n` the given unit normal; local
/// coordinates put `n` on `+z`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Frame {
    /// First tangent (local `+x`).
    pub s: Vec3,
    /// Second tangent (local `+y`), `n x s`.
    pub t: Vec3,
    /// Normal (local `+z`).
    pub n: Vec3,
}

impl Frame {
    /// Builds the basis of a unit normal with the branchless construction of Duff et al.
    /// 2017, "Building an Orthonormal Basis, Revisited" (JCGT 6(1)), which is continuous
    /// except across `n.z = 0` sign changes and accurate even for `n` close to `-z`
    /// (unlike Frisvad's original).
    pub fn from_normal(n: Vec3) -> Self {
        let sign = 1.0f32.copysign(n.z);
        let a = -1.0 / (sign + n.z);
        let b = n.x * n.y * a;
        Frame {
            s: Vec3::new(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x),
            t: Vec3::new(b, sign + n.y * n.y * a, -n.y),
            n,
        }
    }

    /// Coordinates of world vector `v` in this frame (`n` becomes `+z`).
    pub fn to_local(&self, v: Vec3) -> Vec3 {
        Vec3::new(v.dot(self.s), v.dot(self.t), v.dot(self.n))
    }

    /// World vector of local coordinates `v`.
    pub fn to_world(&self, v: Vec3) -> Vec3 {
        self.s * v.x + self.t * v.y + self.n * v.z
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::chi2::{chi2_plane, chi2_sphere, chi2_sphere_cap, Chi2Config, Chi2Report};

    /// u values on and near the boundary of the square, where warps divide by zero or take
    /// square roots of rounding noise.
    const EDGE: [f32; 7] = [
        0.0,
        1e-30,
        1e-7,
        0.25,
        0.5,
        1.0 - 1e-7,
        1.0 - 1.0 / 16_777_216.0,
    ];

    fn edge_points() -> impl Iterator<Item = Vec2> {
        EDGE.iter()
            .flat_map(|&x| EDGE.iter().map(move |&y| Vec2::new(x, y)))
    }

    fn assert_unit(v: Vec3, what: &str) {
        assert!(v.is_finite(), "{what}: {v:?}");
        assert!(
            (v.length() - 1.0).abs() < 1e-5,
            "{what}: |{v:?}| = {}",
            v.length()
        );
    }

    #[test]
    fn warps_are_robust_on_the_boundary() {
        for u in edge_points() {
            assert_unit(square_to_uniform_sphere(u), "sphere");
            let h = square_to_uniform_hemisphere(u);
            assert_unit(h, "hemisphere");
            assert!(h.z >= 0.0);
            let c = square_to_cosine_hemisphere(u);
            assert_unit(c, "cosine");
            assert!(c.z >= 0.0 && cosine_hemisphere_pdf(c.z).is_finite());
            let d = square_to_concentric_disk(u);
            assert!(d.is_finite() && d.length() <= 1.0 + 1e-6, "disk {d:?}");
            let (b0, b1) = square_to_uniform_triangle(u);
            assert!(
                b0 >= 0.0 && b1 >= 0.0 && b0 + b1 <= 1.0,
                "triangle {b0} {b1}"
            );
            for cmax in [-1.0, 0.0, 0.5, 0.999, 1.0 - 1e-7, 1.0] {
                let w = square_to_uniform_cone(u, cmax);
                assert_unit(w, "cone");
                assert!(w.z >= cmax - 1e-6, "cone {w:?} {cmax}");
            }
            for n in [0.0, 1.0, 10.0, 1000.0, 1e6] {
                let w = square_to_phong_lobe(u, n);
                assert_unit(w, "phong");
                assert!(w.z >= 0.0 && phong_lobe_pdf(w.z, n).is_finite());
            }
        }
    }

    #[test]
    fn ggx_is_robust() {
        for alpha in [1e-4, 1e-3, 0.05, 0.5, 1.0] {
            for theta_deg in [0.0f32, 45.0, 80.0, 89.9, 89.999, 90.0] {
                let t = theta_deg.to_radians();
                let wo = Vec3::new(t.sin(), 0.0, t.cos().max(0.0));
                let lambda = ggx_lambda(wo, alpha);
                assert!(!lambda.is_nan() && lambda >= 0.0);
                let g1 = ggx_g1(wo, alpha);
                assert!((0.0..=1.0).contains(&g1), "G1 {g1}");
                for u in edge_points() {
                    let m = sample_ggx_vndf(wo, alpha, u);
                    assert_unit(m, "vndf");
                    assert!(m.z > 0.0, "m {m:?}");
                    let d = ggx_d(m, alpha);
                    assert!(d.is_finite() && d > 0.0, "D({m:?}) = {d}");
                    let p = ggx_vndf_pdf(wo, m, alpha);
                    assert!(p.is_finite() && p >= 0.0, "pdf {p}");
                }
            }
        }
        // Tiny wo.z: G1 / wo.z stays finite and equals the limit 2 / (alpha sin theta).
        let wo = Vec3::new(1.0, 0.0, 1e-30);
        assert!(ggx_vndf_pdf(wo, Vec3::Z, 0.5).is_finite());
        let m = Vec3::new(0.6, 0.0, 0.8);
        let expected = 2.0 / 0.5 * 0.6 * ggx_d(m, 0.5);
        assert!((ggx_vndf_pdf(wo, m, 0.5) / expected - 1.0).abs() < 1e-5);
    }

    #[test]
    fn ggx_closed_forms() {
        // D at the peak is 1 / (pi alpha^2); Lambda(0) = 0, G1 at 45 deg for alpha = 1 is
        // 2 / (1 + sqrt 2); the stable vndf pdf equals the textbook product.
        for alpha in [1e-4f32, 0.05, 0.3, 1.0] {
            let d = ggx_d(Vec3::Z, alpha);
            assert!(
                (d * PI * alpha * alpha - 1.0).abs() < 1e-5,
                "alpha {alpha}: D {d}"
            );
        }
        assert_eq!(ggx_lambda(Vec3::Z, 0.3), 0.0);
        let w45 = Vec3::new(1.0, 0.0, 1.0).normalize();
        assert!((ggx_g1(w45, 1.0) - 2.0 / (1.0 + 2f32.sqrt())).abs() < 1e-6);
        let wo = Vec3::new(0.3, -0.4, 0.5).normalize();
        let m = Vec3::new(0.1, 0.2, 0.9).normalize();
        for alpha in [0.05f32, 0.3, 0.8] {
            let textbook = ggx_g1(wo, alpha) * wo.dot(m) * ggx_d(m, alpha) / wo.z;
            let stable = ggx_vndf_pdf(wo, m, alpha);
            assert!((stable / textbook - 1.0).abs() < 1e-5);
        }
    }

    #[test]
    fn tiny_cones_keep_their_angle() {
        // A cone of half-angle 1e-5 rad: 1 - cos = 5e-11 is far below the f32 spacing at 1.
        let half_angle = 1e-5f32;
        let omc = cone_one_minus_cos_from_sin2(half_angle * half_angle);
        assert!((omc / (0.5 * half_angle * half_angle) - 1.0).abs() < 1e-5);
        let w = square_to_uniform_cone_one_minus_cos(Vec2::new(0.999_999_9, 0.3), omc);
        let sin_theta = w.truncate().length();
        assert!((sin_theta / half_angle - 1.0).abs() < 1e-4, "{sin_theta}");
        // pdf times solid angle is one.
        let pdf = uniform_cone_pdf_one_minus_cos(omc);
        assert!((pdf * TAU * omc - 1.0).abs() < 1e-6);
        assert!((cone_one_minus_cos_from_sin2(1.0) - 1.0).abs() < 1e-7);
        assert!(uniform_cone_pdf(1.0).is_infinite());
    }

    #[test]
    fn frames_are_orthonormal() {
        let mut normals = vec![Vec3::Z, -Vec3::Z, Vec3::X, Vec3::new(-0.0, 0.0, -1.0)];
        normals.push(Vec3::new(1e-4, 2e-4, -1.0).normalize());
        for i in 0..200 {
            normals.push(square_to_uniform_sphere(Vec2::new(
                (i as f32 + 0.5) / 200.0,
                (i as f32 * 0.618_034).fract(),
            )));
        }
        for n in normals {
            let f = Frame::from_normal(n);
            for (a, b) in [(f.s, f.t), (f.t, f.n), (f.s, f.n)] {
                assert!(a.dot(b).abs() < 1e-5, "n {n:?}");
            }
            assert_unit(f.s, "s");
            assert_unit(f.t, "t");
            assert!((f.s.cross(f.t) - n).length() < 1e-5, "handedness {n:?}");
            let v = Vec3::new(0.3, -0.5, 0.8);
            assert!((f.to_local(f.to_world(v)) - v).length() < 1e-5);
            assert!((f.to_local(n) - Vec3::Z).length() < 1e-5);
        }
    }

    /// One member of the chi-squared family: a name and a test run with the family's config.
    type Case = (
        String,
        Box<dyn Fn(&Chi2Config) -> Result<Chi2Report, String> + Sync>,
    );

    fn case(
        name: String,
        f: impl Fn(&str, &Chi2Config) -> Result<Chi2Report, String> + Sync + 'static,
    ) -> Case {
        let n = name.clone();
        (name, Box::new(move |cfg| f(&n, cfg)))
    }

    /// `cos theta` of the cap holding all but a fraction `1e-3` of a lobe's mass, or -1 for
    /// wide lobes, so that narrow lobes are resolved by the bins.
    fn cap(cos_min: f32) -> f64 {
        if cos_min < 0.5 {
            -1.0
        } else {
            cos_min as f64
        }
    }

    /// The family of chi-squared tests of every warp, corrected together (Šidák).
    fn family() -> Vec<Case> {
        let mut cases: Vec<Case> = vec![
            case("uniform sphere".into(), |name, cfg| {
                chi2_sphere(
                    name,
                    cfg,
                    |u, _| Some(square_to_uniform_sphere(u)),
                    |_| uniform_sphere_pdf(),
                )
            }),
            case("uniform hemisphere".into(), |name, cfg| {
                chi2_sphere(
                    name,
                    cfg,
                    |u, _| Some(square_to_uniform_hemisphere(u)),
                    |w| {
                        if w.z >= 0.0 {
                            uniform_hemisphere_pdf()
                        } else {
                            0.0
                        }
                    },
                )
            }),
            case("cosine hemisphere".into(), |name, cfg| {
                chi2_sphere(
                    name,
                    cfg,
                    |u, _| Some(square_to_cosine_hemisphere(u)),
                    |w| cosine_hemisphere_pdf(w.z),
                )
            }),
            case("concentric disk".into(), |name, cfg| {
                let cfg = Chi2Config {
                    phi_bins: cfg.theta_bins,
                    ..cfg.clone()
                };
                chi2_plane(
                    name,
                    &cfg,
                    (Vec2::splat(-1.0), Vec2::splat(1.0)),
                    |u, _| Some(square_to_concentric_disk(u)),
                    |p| {
                        if p.length_squared() <= 1.0 {
                            FRAC_1_PI
                        } else {
                            0.0
                        }
                    },
                )
            }),
            case("uniform triangle".into(), |name, cfg| {
                let cfg = Chi2Config {
                    phi_bins: cfg.theta_bins,
                    ..cfg.clone()
                };
                chi2_plane(
                    name,
                    &cfg,
                    (Vec2::ZERO, Vec2::ONE),
                    |u, _| {
                        let (b0, b1) = square_to_uniform_triangle(u);
                        Some(Vec2::new(b0, b1))
                    },
                    // Barycentric (b0, b1) space: the triangle has area 1/2.
                    |b| {
                        if b.x >= 0.0 && b.y >= 0.0 && b.x + b.y <= 1.0 {
                            2.0
                        } else {
                            0.0
                        }
                    },
                )
            }),
        ];
        for cos_max in [0.5f32, 0.999] {
            cases.push(case(format!("cone cos_max {cos_max}"), move |name, cfg| {
                // The narrow cone is binned on a cap twice its size: half the cap must
                // stay empty.
                let lo = if cos_max > 0.9 {
                    1.0 - 2.0 * (1.0 - cos_max as f64)
                } else {
                    -1.0
                };
                chi2_sphere_cap(
                    name,
                    cfg,
                    lo,
                    |u, _| Some(square_to_uniform_cone(u, cos_max)),
                    |w| {
                        if w.z >= cos_max {
                            uniform_cone_pdf(cos_max)
                        } else {
                            0.0
                        }
                    },
                )
            }));
        }
        for n in [1.0f32, 10.0, 100.0, 1000.0] {
            cases.push(case(format!("phong n {n}"), move |name, cfg| {
                // P(cos > c) = 1 - c^(n + 1).
                let lo = cap(1e-3f32.powf(1.0 / (n + 1.0)));
                chi2_sphere_cap(
                    name,
                    cfg,
                    lo,
                    |u, _| Some(square_to_phong_lobe(u, n)),
                    |w| phong_lobe_pdf(w.z, n),
                )
            }));
        }
        for alpha in [0.05f32, 0.3, 0.8] {
            for theta_deg in [0.0f32, 45.0, 80.0] {
                cases.push(case(
                    format!("ggx vndf alpha {alpha} theta_o {theta_deg}"),
                    move |name, cfg| {
                        let t = theta_deg.to_radians();
                        // Off-axis azimuth, so that the test does not rely on symmetry.
                        let wo = Vec3::new(t.sin() * 0.6, t.sin() * 0.8, t.cos());
                        // Narrow lobes are binned on a cap: D cos theta puts mass
                        // alpha^2 / (alpha^2 + T^2) beyond tan theta = T, so T = 3 alpha keeps
                        // ~90% of the normals on the cap, with the core spread over ~4
                        // bins per scale length alpha^2 / 2 of 1 - cos theta. The wide lobes
                        // test the tails at full resolution.
                        let lo = if alpha < 0.1 {
                            1.0 / (1.0 + 9.0 * alpha as f64 * alpha as f64).sqrt()
                        } else {
                            -1.0
                        };
                        chi2_sphere_cap(
                            name,
                            cfg,
                            lo,
                            |u, _| Some(sample_ggx_vndf(wo, alpha, u)),
                            |m| ggx_vndf_pdf(wo, m, alpha),
                        )
                    },
                ));
            }
        }
        cases
    }

    /// Runs the cases on two threads (the test machine has two cores) and returns the
    /// failure messages.
    fn run_family(cases: &[Case], cfg: &Chi2Config) -> Vec<String> {
        let (even, odd): (Vec<_>, Vec<_>) = cases
            .iter()
            .enumerate()
            .partition(|(i, _)| i.is_multiple_of(2));
        let run = |part: Vec<(usize, &Case)>| -> Vec<String> {
            part.into_iter()
                .filter_map(|(_, (name, f))| match f(cfg) {
                    Ok(report) => {
                        assert!(report.dof > 0 && report.statistic >= 0.0, "{name}");
                        assert!(report.p_value >= cfg.single_test_significance());
                        None
                    }
                    Err(msg) => Some(msg),
                })
                .collect()
        };
        std::thread::scope(|s| {
            let h = s.spawn(|| run(odd));
            let mut failures = run(even);
            failures.extend(h.join().expect("chi2 thread panicked"));
            failures
        })
    }

    #[test]
    fn warps_match_their_pdfs_chi2() {
        let cases = family();
        let cfg = Chi2Config::new(cases.len());
        let failures = run_family(&cases, &cfg);
        assert!(
            failures.is_empty(),
            "chi2 failures:\n{}",
            failures.join("\n")
        );
    }

    #[test]
    fn chi2_rejects_wrong_pdfs() {
        // Negative controls at the family's threshold: the tests above can fail.
        let cfg = Chi2Config::new(family().len());
        let controls: Vec<Result<Chi2Report, String>> = vec![
            // Cosine samples against the uniform hemisphere pdf.
            chi2_sphere(
                "control cosine vs uniform",
                &cfg,
                |u, _| Some(square_to_cosine_hemisphere(u)),
                |w| {
                    if w.z >= 0.0 {
                        uniform_hemisphere_pdf()
                    } else {
                        0.0
                    }
                },
            ),
            // A subtly wrong exponent: Phong 10 samples against the n = 11 pdf.
            chi2_sphere(
                "control phong 10 vs 11",
                &cfg,
                |u, _| Some(square_to_phong_lobe(u, 10.0)),
                |w| phong_lobe_pdf(w.z, 11.0),
            ),
            // The plain NDF D(m) cos(theta) instead of the visible normals at 80 degrees.
            chi2_sphere_cap(
                "control vndf vs D cos",
                &cfg,
                -1.0,
                |u, _| {
                    let t = 80f32.to_radians();
                    Some(sample_ggx_vndf(Vec3::new(t.sin(), 0.0, t.cos()), 0.3, u))
                },
                |m| ggx_d(m, 0.3) * m.z,
            ),
            // Polar-map disk samples (Arvo 2001, eq. 4.23) with the radius not square-rooted.
            chi2_plane(
                "control disk without sqrt",
                &Chi2Config {
                    phi_bins: cfg.theta_bins,
                    ..cfg.clone()
                },
                (Vec2::splat(-1.0), Vec2::splat(1.0)),
                |u, _| Some(u.x * Vec2::from_angle(TAU * u.y)),
                |p| {
                    if p.length_squared() <= 1.0 {
                        FRAC_1_PI
                    } else {
                        0.0
                    }
                },
            ),
        ];
        for c in controls {
            let err = c.expect_err("a wrong pdf must be rejected");
            assert!(err.contains("rejected"), "{err}");
        }
    }
}
