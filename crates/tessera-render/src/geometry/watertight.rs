//! The watertight ray–triangle test (Woop, Benthin & Wald, JCGT 2013, in pbrt's
//! formulation), for one triangle and for a pack of a leaf's triangles at once, and the
//! ray–sphere test.

use super::wide::{PackHits, TrianglePack, TriangleTest, PACK};
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

/// `[f(0), .., f(PACK - 1)]`: one operation on every lane (the lanes LLVM vectorises).
/// Written out: `std::array::from_fn` and `array::map` were left as calls in the
/// kernels (callgrind, docs/benchmarks.md "Leaves as packs").
#[inline(always)]
fn each<T>(mut f: impl FnMut(usize) -> T) -> [T; PACK] {
    [f(0), f(1), f(2), f(3)]
}

/// `[f(0), f(1), f(2)]`, per vertex or axis (written out, see [`each`]).
#[inline(always)]
pub(super) fn three<T>(mut f: impl FnMut(usize) -> T) -> [T; 3] {
    [f(0), f(1), f(2)]
}

/// `if a > b { a } else { b }`: glam's `max_element` of a `Vec3` is
/// `max(x, max(y, z))` with this `max`.
#[inline(always)]
fn max(a: f32, b: f32) -> f32 {
    if a > b {
        a
    } else {
        b
    }
}

impl<const KZ: usize> WatertightRay<KZ> {
    /// [`WatertightRay::intersect`] of the first `lanes` triangles of `pack`, every lane
    /// at once: per lane the same IEEE operations in the same order as the scalar test
    /// (each line below is the scalar line it mirrors; no fused multiply-add, no
    /// approximate reciprocal), so a lane's hit is the scalar test's, bit for bit. The
    /// scalar test's early returns become a mask: its conditions are pure functions of
    /// values computed the same way, so testing all of them gives its verdict. A lane
    /// with an edge function exactly zero needs the scalar test's double-precision
    /// fallback, and is redone by the scalar test (rare: a ray through an edge or vertex
    /// in single precision).
    #[inline(always)]
    pub(super) fn intersect_pack(&self, pack: &TrianglePack, lanes: usize, t_max: f32) -> PackHits {
        // The permutation of `permute`: x <- kx, y <- ky, z <- KZ.
        let (kx, ky) = ((KZ + 1) % 3, (KZ + 2) % 3);
        let (o, p) = (self.origin, &pack.p);
        // tr(p[v]), then `p.x += sx * p.z`, `p.y += sy * p.z`.
        let z: [[f32; PACK]; 3] = three(|v| each(|l| p[v][KZ][l] - o.z));
        let x: [[f32; PACK]; 3] = three(|v| each(|l| (p[v][kx][l] - o.x) + self.sx * z[v][l]));
        let y: [[f32; PACK]; 3] = three(|v| each(|l| (p[v][ky][l] - o.y) + self.sy * z[v][l]));
        let e0 = each(|l| x[1][l] * y[2][l] - y[1][l] * x[2][l]);
        let e1 = each(|l| x[2][l] * y[0][l] - y[2][l] * x[0][l]);
        let e2 = each(|l| x[0][l] * y[1][l] - y[0][l] * x[1][l]);
        let det = each(|l| e0[l] + e1[l] + e2[l]);
        // `p.z *= sz`.
        let z: [[f32; PACK]; 3] = three(|v| each(|l| z[v][l] * self.sz));
        let t_scaled = each(|l| e0[l] * z[0][l] + e1[l] * z[1][l] + e2[l] * z[2][l]);
        let inv_det = each(|l| 1.0 / det[l]);
        let t = each(|l| t_scaled[l] * inv_det[l]);
        let max_zt = each(|l| max(z[0][l].abs(), max(z[1][l].abs(), z[2][l].abs())));
        let delta_z = each(|l| gamma(3) * max_zt[l]);
        let max_xt = each(|l| max(x[0][l].abs(), max(x[1][l].abs(), x[2][l].abs())));
        let max_yt = each(|l| max(y[0][l].abs(), max(y[1][l].abs(), y[2][l].abs())));
        let delta_x = each(|l| gamma(5) * (max_xt[l] + max_zt[l]));
        let delta_y = each(|l| gamma(5) * (max_yt[l] + max_zt[l]));
        let delta_e = each(|l| {
            2.0 * (gamma(2) * max_xt[l] * max_yt[l]
                + delta_y[l] * max_xt[l]
                + delta_x[l] * max_yt[l])
        });
        let max_e = each(|l| max(e0[l].abs(), max(e1[l].abs(), e2[l].abs())));
        let delta_t = each(|l| {
            3.0 * (gamma(3) * max_e[l] * max_zt[l] + delta_e[l] * max_zt[l] + delta_z[l] * max_e[l])
                * inv_det[l].abs()
        });
        let mut hits = PackHits {
            mask: 0,
            t,
            b1: each(|l| e1[l] * inv_det[l]),
            b2: each(|l| e2[l] * inv_det[l]),
        };
        let mut fallback = 0u32;
        for l in 0..PACK {
            let (e0, e1, e2, det, ts) = (e0[l], e1[l], e2[l], det[l], t_scaled[l]);
            let zero = e0 == 0.0 || e1 == 0.0 || e2 == 0.0;
            let miss = ((e0 < 0.0 || e1 < 0.0 || e2 < 0.0) && (e0 > 0.0 || e1 > 0.0 || e2 > 0.0))
                || det == 0.0
                || (det < 0.0 && (ts >= 0.0 || ts < t_max * det))
                || (det > 0.0 && (ts <= 0.0 || ts > t_max * det))
                || t[l] <= delta_t[l];
            fallback |= u32::from(zero) << l;
            hits.mask |= u32::from(!zero && !miss) << l;
        }
        let valid = (1u32 << lanes) - 1;
        hits.mask &= valid;
        let mut fallback = fallback & valid;
        while fallback != 0 {
            let l = fallback.trailing_zeros() as usize;
            fallback &= fallback - 1;
            if let Some((t, _, b1, b2)) = self.intersect(&pack.triangle(l), t_max) {
                hits.mask |= 1 << l;
                hits.t[l] = t;
                hits.b1[l] = b1;
                hits.b2[l] = b2;
            }
        }
        hits
    }
}

impl<const KZ: usize> TriangleTest for WatertightRay<KZ> {
    #[inline(always)]
    fn triangle(&self, p: &[Vec3; 3], t_max: f32) -> Option<(f32, f32, f32, f32)> {
        self.intersect(p, t_max)
    }

    #[inline(always)]
    fn pack(&self, pack: &TrianglePack, lanes: usize, t_max: f32) -> PackHits {
        self.intersect_pack(pack, lanes, t_max)
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
