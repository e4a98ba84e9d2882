//! The watertight ray–triangle test (Woop, Benthin & Wald, JCGT 2013, in pbrt's
//! formulation) and the ray–sphere test.

use crate::math::gamma;
use glam::{Vec3, Vec3A, Vec3Swizzles};

/// Per-ray constants of the watertight triangle test: the permutation that makes the ray
/// direction's largest component z (`KZ` is that component's axis, a type parameter so the
/// permutation compiles to a fixed shuffle instead of indexing through memory), and the
/// shear that aligns the ray with +z.
#[derive(Clone, Copy)]
pub(super) struct WatertightRay<const KZ: usize> {
    /// The ray origin, permuted.
    origin: Vec3A,
    sx: f32,
    sy: f32,
    sz: f32,
}

/// The axis of `dir`'s largest component (ties to the later axis), which becomes z in the
/// watertight test.
#[inline(always)]
pub(super) fn dominant_axis(dir: Vec3) -> usize {
    let a = dir.abs();
    if a.x > a.y {
        if a.x > a.z {
            0
        } else {
            2
        }
    } else if a.y > a.z {
        1
    } else {
        2
    }
}

/// Runs `$body` with `$wt` bound to the [`WatertightRay`] of `origin + t dir` for the
/// direction's dominant axis: one branch per ray, and the traversal in `$body` is
/// compiled once per axis.
macro_rules! with_watertight_ray {
    ($origin:expr, $dir:expr, |$wt:ident| $body:expr) => {{
        let (origin, dir) = ($origin, $dir);
        match $crate::geometry::watertight::dominant_axis(dir) {
            0 => {
                let $wt = $crate::geometry::watertight::WatertightRay::<0>::new(origin, dir);
                $body
            }
            1 => {
                let $wt = $crate::geometry::watertight::WatertightRay::<1>::new(origin, dir);
                $body
            }
            _ => {
                let $wt = $crate::geometry::watertight::WatertightRay::<2>::new(origin, dir);
                $body
            }
        }
    }};
}

impl<const KZ: usize> WatertightRay<KZ> {
    /// `(v[kx], v[ky], v[kz])` with `kx = (kz + 1) % 3`, `ky = (kx + 1) % 3`.
    #[inline(always)]
    fn permute(v: Vec3A) -> Vec3A {
        match KZ {
            0 => v.yzx(),
            1 => v.zxy(),
            _ => v,
        }
    }

    #[inline(always)]
    pub(super) fn new(origin: Vec3, dir: Vec3) -> Self {
        let d = Self::permute(Vec3A::from(dir));
        Self {
            origin: Self::permute(Vec3A::from(origin)),
            sx: -d.x / d.z,
            sy: -d.y / d.z,
            sz: 1.0 / d.z,
        }
    }

    /// Returns (t, b0, b1, b2) for a hit with `t < t_max`, or `None`.
    #[inline(always)]
    pub(super) fn intersect(&self, p: &[Vec3; 3], t_max: f32) -> Option<(f32, f32, f32, f32)> {
        // Permuting before subtracting the (permuted) origin gives the same bits as
        // subtracting first: each lane is one subtraction either way.
        let tr = |v: Vec3| Self::permute(Vec3A::from(v)) - self.origin;
        let mut p0t = tr(p[0]);
        let mut p1t = tr(p[1]);
        let mut p2t = tr(p[2]);
        p0t.x += self.sx * p0t.z;
        p0t.y += self.sy * p0t.z;
        p1t.x += self.sx * p1t.z;
        p1t.y += self.sy * p1t.z;
        p2t.x += self.sx * p2t.z;
        p2t.y += self.sy * p2t.z;
        let mut e0 = p1t.x * p2t.y - p1t.y * p2t.x;
        let mut e1 = p2t.x * p0t.y - p2t.y * p0t.x;
        let mut e2 = p0t.x * p1t.y - p0t.y * p1t.x;
        // An edge function that is exactly zero may be a rounding artefact: decide it in
        // double precision so neighbouring triangles agree (watertightness).
        if e0 == 0.0 || e1 == 0.0 || e2 == 0.0 {
            let (a, b, c) = (p0t.as_dvec3(), p1t.as_dvec3(), p2t.as_dvec3());
            e0 = (b.x * c.y - b.y * c.x) as f32;
            e1 = (c.x * a.y - c.y * a.x) as f32;
            e2 = (a.x * b.y - a.y * b.x) as f32;
        }
        if (e0 < 0.0 || e1 < 0.0 || e2 < 0.0) && (e0 > 0.0 || e1 > 0.0 || e2 > 0.0) {
            return None;
        }
        let det = e0 + e1 + e2;
        if det == 0.0 {
            return None;
        }
        p0t.z *= self.sz;
        p1t.z *= self.sz;
        p2t.z *= self.sz;
        let t_scaled = e0 * p0t.z + e1 * p1t.z + e2 * p2t.z;
        if det < 0.0 && (t_scaled >= 0.0 || t_scaled < t_max * det) {
            return None;
        }
        if det > 0.0 && (t_scaled <= 0.0 || t_scaled > t_max * det) {
            return None;
        }
        let inv_det = 1.0 / det;
        let t = t_scaled * inv_det;
        // Reject hits whose t is not provably positive given the rounding in the
        // computation above (pbrt 3rd ed. §3.9.6).
        let max_zt = Vec3::new(p0t.z, p1t.z, p2t.z).abs().max_element();
        let delta_z = gamma(3) * max_zt;
        let max_xt = Vec3::new(p0t.x, p1t.x, p2t.x).abs().max_element();
        let max_yt = Vec3::new(p0t.y, p1t.y, p2t.y).abs().max_element();
        let delta_x = gamma(5) * (max_xt + max_zt);
        let delta_y = gamma(5) * (max_yt + max_zt);
        let delta_e = 2.0 * (gamma(2) * max_xt * max_yt + delta_y * max_xt + delta_x * max_yt);
        let max_e = Vec3::new(e0, e1, e2).abs().max_element();
        let delta_t =
            3.0 * (gamma(3) * max_e * max_zt + delta_e * max_zt + delta_z * max_e) * inv_det.abs();
        if t <= delta_t {
            return None;
        }
        Some((t, e0 * inv_det, e1 * inv_det, e2 * inv_det))
    }
}

/// Intersects a ray with a sphere; returns the nearest `t` in `(0, t_max)`.
///
/// Uses the numerically stable form of the quadratic from Haines et al., "Precision
/// Improvements for Ray/Sphere Intersection" (Ray Tracing Gems, ch. 7): the discriminant
/// is computed from the distance of the centre to the ray line, which does not cancel
/// catastrophically for small or distant spheres.
#[inline]
pub fn intersect_sphere(
    center: Vec3,
    radius: f32,
    origin: Vec3,
    dir: Vec3,
    t_max: f32,
) -> Option<f32> {
    let f = origin - center;
    let a = dir.length_squared();
    let b_half = -f.dot(dir);
    let perp = f + (b_half / a) * dir;
    let disc = a * (radius * radius - perp.length_squared());
    if disc < 0.0 {
        return None;
    }
    let c = f.length_squared() - radius * radius;
    let sq = disc.sqrt();
    let q = if b_half >= 0.0 {
        b_half + sq
    } else {
        b_half - sq
    };
    let (mut t0, mut t1) = (c / q, q / a);
    if t0 > t1 {
        std::mem::swap(&mut t0, &mut t1);
    }
    // Conservative positivity margin: the roots carry a small relative error.
    let eps = gamma(7) * t1.abs().max(t0.abs());
    if t0 > eps && t0 < t_max {
        Some(t0)
    } else if t1 > eps && t1 < t_max {
        Some(t1)
    } else {
        None
    }
}
