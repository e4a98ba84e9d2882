//! Emissive triangles (area lights).
//!
//! | parameter | meaning |
//! |---|---|
//! | `p` | vertices; the front is counter-clockwise, `n = normalize((p1-p0) x (p2-p0))` |
//! | `radiance` | emitted radiance W/(m² sr), constant over the triangle |
//! | `two_sided` | emit on both sides; otherwise only along `n` (glTF `doubleSided`) |
//! | `power_scale`, `shading` | a textured emitter: its mean texture value (for selection) and the mesh triangle where [`crate::scene::RenderScene`] evaluates the texture |
//!
//! Two sampling techniques, chosen by a deterministic rule on the solid angle `Ω` the
//! triangle subtends from the reference point (as pbrt-v4's `TriangleLight`, Pharr, Jakob &
//! Humphreys 2023, section 6.5.4):
//!
//! - `MIN_SPHERICAL_SOLID_ANGLE <= Ω <= MAX_SPHERICAL_SOLID_ANGLE` (2 and 6.22 sr):
//!   uniformly by solid
//!   angle, with Arvo's area-preserving parametrization of the spherical triangle (Arvo
//!   1995, "Stratified Sampling of Spherical Triangles"; Arvo 2001, section 4.3.5, figure
//!   4.7): `pdf_ω = 1 / Ω`. Near a large emitter this removes the `d² / cos θ_l` factor of
//!   area sampling, whose variance grows without bound as the point approaches the light.
//! - otherwise uniformly by area (Arvo 2001, section 4.3.1, triangle warp), converted to
//!   solid angle: `pdf_ω = d² / (|cos θ_l| A)` (Shirley 2001, chapter 3). For small solid
//!   angles it is as good and cheaper (and the warp would lose precision: its angles sum
//!   to `π + Ω`); a triangle covering nearly a hemisphere (the point almost on it) makes the
//!   warp ill-conditioned.
//!
//! `TriangleLight::pdf_li` applies the same rule, so it returns exactly the density
//! `TriangleLight::sample_li` used. The spherical warp runs in f64: it is a handful of
//! operations per shadow ray, and keeps the warp's area `α + β + γ - π` consistent with the
//! solid angle `Ω` of the pdf (computed by Van Oosterom & Strackee's formula) for solid
//! angles down to `MIN_SPHERICAL_SOLID_ANGLE`.

use super::LightSample;
use crate::geometry::triangle_point;
use crate::sampling::warp::square_to_uniform_triangle;
use glam::{DVec3, Vec2, Vec3};
use std::f32::consts::PI;

/// Smallest solid angle (sr) sampled by the spherical-triangle warp. pbrt-v4 uses 3e-4,
/// where the warp's `α + β + γ - π` starts to cancel; here the warp (~150 ns in f64) is
/// kept for triangles that subtend enough for the `d² / cos θ_l` variation of area
/// sampling to matter. Measured on the Cornell box (a 0.02 sr light seen from most
/// points; docs/benchmarks.md): pbrt's threshold cut the noise variance by 3% for 40% more
/// CPU time; 0.1 sr by 0.8% for 6.5% more instructions; from 0.5 sr up the noise equals
/// area sampling's, and at 2 sr the warp costs 0.5% more instructions than none. So it is
/// left to the points very close to a large emitter, where area sampling's variance grows
/// without bound.
pub const MIN_SPHERICAL_SOLID_ANGLE: f64 = 2.0;
/// `r² / d²` below which a bounding sphere of radius `r` at distance `d` subtends less
/// than [`MIN_SPHERICAL_SOLID_ANGLE`]: `1 - (1 - 2 / 2π)² = 0.5336` lowered by 6% for
/// margin. (The bound `2π r² / d²` of the solid angle, halved for margin, skipped the
/// exact angle only below 0.159: on the Cornell box one light sample in ten then computed
/// it in f64, docs/benchmarks.md "Raw speed", 2026-12-06 evening.)
const SPHERE_BOUND_RATIO: f32 = 0.5;
const _: () = assert!(
    (SPHERE_BOUND_RATIO as f64)
        < 1.0
            - (1.0 - MIN_SPHERICAL_SOLID_ANGLE / std::f64::consts::TAU)
                * (1.0 - MIN_SPHERICAL_SOLID_ANGLE / std::f64::consts::TAU)
);

/// Largest solid angle (sr) sampled by the spherical-triangle warp (pbrt-v4's threshold,
/// just under 2π): beyond it the point is almost on the triangle and the warp is
/// ill-conditioned.
pub const MAX_SPHERICAL_SOLID_ANGLE: f64 = 6.22;

/// An emissive triangle.
#[derive(Clone, Copy, Debug)]
pub struct TriangleLight {
    /// Vertices.
    pub p: [Vec3; 3],
    /// Unit geometric normal.
    pub n: Vec3,
    /// Area.
    pub area: f32,
    /// Emitted radiance.
    pub radiance: Vec3,
    /// Emits on both sides.
    pub two_sided: bool,
    /// Mean of the emission's variation over the triangle (emissive texture, alpha
    /// coverage), which scales the power used for light selection; 1 when constant.
    pub power_scale: Vec3,
    /// `(mesh, triangle)` when the emission varies over the triangle: the render scene
    /// then evaluates it where a point is sampled.
    pub shading: Option<(u32, u32)>,
    /// Centroid of `p`, for the cheap bound of [`TriangleLight::spherical`].
    centroid: Vec3,
    /// Squared distance from the centroid to the farthest vertex.
    bound_r2: f32,
}

impl TriangleLight {
    /// Builds the light; `None` for degenerate triangles.
    pub fn new(p: [Vec3; 3], radiance: Vec3, two_sided: bool) -> Option<Self> {
        let c = (p[1] - p[0]).cross(p[2] - p[0]);
        let len = c.length();
        if !(len > 0.0 && len.is_finite()) {
            return None;
        }
        // The bounding sphere of `spherical`'s early out, computed once per light rather
        // than once per shading point.
        let centroid = (p[0] + p[1] + p[2]) / 3.0;
        let bound_r2 = (p[0] - centroid)
            .length_squared()
            .max((p[1] - centroid).length_squared())
            .max((p[2] - centroid).length_squared());
        Some(Self {
            p,
            n: c / len,
            area: 0.5 * len,
            radiance,
            two_sided,
            power_scale: Vec3::ONE,
            shading: None,
            centroid,
            bound_r2,
        })
    }

    /// Radiance leaving the light toward `w` (unit, pointing away from the light).
    #[inline]
    pub fn emitted(&self, w: Vec3) -> Vec3 {
        if self.two_sided || self.n.dot(w) > 0.0 {
            self.radiance
        } else {
            Vec3::ZERO
        }
    }

    pub(crate) fn power(&self) -> Vec3 {
        self.radiance * self.power_scale * (PI * self.area * if self.two_sided { 2.0 } else { 1.0 })
    }

    /// The solid angle the triangle subtends from `p_ref` if it is sampled by solid angle
    /// there (the rule of the module documentation), else `None`. Van Oosterom & Strackee
    /// (1983): `tan(Ω / 2) = |a · (b × c)| / (1 + a·b + b·c + c·a)` for the unit vertex
    /// directions `a, b, c`; `atan2` keeps the quadrant for `Ω > π`.
    #[inline]
    pub fn spherical_solid_angle(&self, p_ref: Vec3) -> Option<f64> {
        self.spherical(p_ref).map(|(omega, _)| omega)
    }

    /// [`TriangleLight::spherical_solid_angle`] with the unit vertex directions.
    #[inline]
    fn spherical(&self, p_ref: Vec3) -> Option<(f64, [DVec3; 3])> {
        // A cheap upper bound first: the triangle lies in the sphere about its centroid
        // through its farthest vertex, which subtends `2π (1 - cos θ)` with
        // `cos θ = sqrt(1 - r² / d²)`; it is below the threshold `Ω_min` exactly when
        // `r² / d² < 1 - (1 - Ω_min / 2π)²` (0.534 for 2 sr). The exact angle is skipped
        // only below `SPHERE_BOUND_RATIO`, a margin far wider than the rounding of either
        // side, so the rule is the exact one.
        let r2 = self.bound_r2;
        let d2 = (self.centroid - p_ref).length_squared();
        if d2 > r2 && r2 < SPHERE_BOUND_RATIO * d2 {
            return None;
        }
        self.spherical_exact(p_ref)
    }

    /// [`TriangleLight::spherical`] without its early out: the rule itself.
    #[inline]
    fn spherical_exact(&self, p_ref: Vec3) -> Option<(f64, [DVec3; 3])> {
        let o = p_ref.as_dvec3();
        let [a, b, c] = self.p.map(|v| (v.as_dvec3() - o).normalize_or_zero());
        let num = a.dot(b.cross(c)).abs();
        let den = 1.0 + a.dot(b) + b.dot(c) + c.dot(a);
        let omega = 2.0 * num.atan2(den);
        (omega.is_finite()
            && (MIN_SPHERICAL_SOLID_ANGLE..=MAX_SPHERICAL_SOLID_ANGLE).contains(&omega))
        .then_some((omega, [a, b, c]))
    }

    /// The rule's solid angle from `p_ref` computed without the bounding sphere's early
    /// out, for the test that the early out never changes the rule.
    #[cfg(test)]
    pub(crate) fn exact_spherical_solid_angle(&self, p_ref: Vec3) -> Option<f64> {
        self.spherical_exact(p_ref).map(|(omega, _)| omega)
    }

    pub(crate) fn sample_li(&self, p_ref: Vec3, u: Vec2) -> Option<LightSample> {
        match self.spherical(p_ref) {
            Some((omega, dirs)) => self.sample_spherical(p_ref, u, omega, dirs),
            None => self.sample_area(p_ref, u),
        }
    }

    /// Area sampling, converted to solid angle.
    fn sample_area(&self, p_ref: Vec3, u: Vec2) -> Option<LightSample> {
        let (b0, b1) = square_to_uniform_triangle(u);
        let b2 = 1.0 - b0 - b1;
        let (p, p_error) = triangle_point(&self.p, b0, b1, b2);
        let d = p - p_ref;
        let dist2 = d.length_squared();
        if dist2 <= 0.0 {
            return None;
        }
        let dist = dist2.sqrt();
        let wi = d / dist;
        let cos_l = self.n.dot(-wi);
        let li = self.emitted(-wi);
        if cos_l == 0.0 || li == Vec3::ZERO {
            return None;
        }
        let pdf = dist2 / (cos_l.abs() * self.area);
        if !pdf.is_finite() {
            return None;
        }
        Some(LightSample {
            wi,
            dist,
            p,
            p_error,
            n: self.n,
            li,
            pdf,
            delta: false,
        })
    }

    /// Uniform solid-angle sampling by Arvo's warp (Arvo 2001, section 4.3.5, figure 4.7).
    /// `u.x` picks the area `Â = u.x 𝒜` of the sub-triangle `A B Ĉ` (which fixes `Ĉ` on the
    /// arc `AC`), `u.y` a point on the arc `B Ĉ` with `1 - cos` uniform. The direction is
    /// then intersected with the triangle's plane for the light point.
    fn sample_spherical(
        &self,
        p_ref: Vec3,
        u: Vec2,
        omega: f64,
        [a, b, c]: [DVec3; 3],
    ) -> Option<LightSample> {
        let o = p_ref.as_dvec3();
        // Normals of the great circles through the edges; the internal angle at a vertex is
        // the dihedral angle between the planes of its two edges.
        let n_ab = a.cross(b).normalize_or_zero();
        let n_ac = a.cross(c).normalize_or_zero();
        let n_bc = b.cross(c).normalize_or_zero();
        // Rounding may degenerate a triangle inside the solid-angle range only at its
        // edges (a vertex direction repeated): no sample then, rather than one of the other
        // technique with a density `pdf_li` would not report.
        if n_ab == DVec3::ZERO || n_ac == DVec3::ZERO || n_bc == DVec3::ZERO {
            return None;
        }
        let alpha = angle_between(n_ab, n_ac);
        let beta = angle_between(-n_ab, n_bc);
        let gamma = angle_between(n_ac, n_bc);
        // Girard's formula (Arvo 2001, eq. 4.36).
        let area = alpha + beta + gamma - std::f64::consts::PI;
        if area.is_nan() || area <= 0.0 {
            return None;
        }
        let area_s = u.x as f64 * area;
        let (s, t) = (area_s - alpha).sin_cos();
        let (sin_alpha, cos_alpha) = alpha.sin_cos();
        let cos_c = a.dot(b);
        let uu = t - cos_alpha;
        let vv = s + sin_alpha * cos_c;
        let cos_bs = (((vv * t - uu * s) * cos_alpha - vv) / ((vv * s + uu * t) * sin_alpha))
            .clamp(-1.0, 1.0);
        let c_s = slerp_cos(a, c, cos_bs);
        let z = 1.0 - u.y as f64 * (1.0 - c_s.dot(b));
        let w = slerp_cos(b, c_s, z.clamp(-1.0, 1.0));
        // The light point: where `o + t w` meets the triangle (Möller & Trumbore), clamped
        // onto it against rounding.
        let [p0, p1, p2] = self.p.map(|v| v.as_dvec3());
        let (e1, e2) = (p1 - p0, p2 - p0);
        let q = w.cross(e2);
        let det = e1.dot(q);
        if det == 0.0 || !det.is_finite() {
            return None;
        }
        let sv = o - p0;
        let mut b1 = (sv.dot(q) / det).clamp(0.0, 1.0);
        let mut b2 = (w.dot(sv.cross(e1)) / det).clamp(0.0, 1.0);
        if b1 + b2 > 1.0 {
            let sum = b1 + b2;
            b1 /= sum;
            b2 /= sum;
        }
        let b0 = (1.0 - b1 - b2).max(0.0);
        let (p, p_error) = triangle_point(&self.p, b0 as f32, b1 as f32, b2 as f32);
        let d = p - p_ref;
        let dist = d.length();
        if dist.is_nan() || dist <= 0.0 {
            return None;
        }
        let wi = d / dist;
        let li = self.emitted(-wi);
        if li == Vec3::ZERO {
            return None;
        }
        Some(LightSample {
            wi,
            dist,
            p,
            p_error,
            n: self.n,
            li,
            pdf: (1.0 / omega) as f32,
            delta: false,
        })
    }

    pub(crate) fn pdf_li(&self, p_ref: Vec3, p_light: Vec3, n_light: Vec3) -> f32 {
        if let Some(omega) = self.spherical_solid_angle(p_ref) {
            return (1.0 / omega) as f32;
        }
        let d = p_light - p_ref;
        let dist2 = d.length_squared();
        let cos_l = n_light.dot(d) / dist2.sqrt();
        if cos_l == 0.0 {
            return 0.0;
        }
        dist2 / (cos_l.abs() * self.area)
    }
}

/// The angle between two unit vectors, accurate near 0 and π (unlike `acos` of the dot).
#[inline]
fn angle_between(x: DVec3, y: DVec3) -> f64 {
    x.cross(y).length().atan2(x.dot(y))
}

/// The point on the great arc from the unit vector `x` toward `y` at angle `θ` from `x`,
/// given `cos θ`: `x cos θ + [y|x] sin θ` with `[y|x]` the normalized part of `y`
/// orthogonal to `x` (Arvo 2001, eqs. 4.30 and 4.31). `x` when `y` is parallel to it.
#[inline]
fn slerp_cos(x: DVec3, y: DVec3, cos_theta: f64) -> DVec3 {
    let perp = (y - x * x.dot(y)).normalize_or_zero();
    let sin_theta = (1.0 - cos_theta * cos_theta).max(0.0).sqrt();
    x * cos_theta + perp * sin_theta
}
