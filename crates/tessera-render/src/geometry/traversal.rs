//! The walk through one BVH of triangles, and the ray handed to obvhs for it (see the
//! module docs of `geometry` for the shift and the defects it works around).

use super::build::{self, BvhBuildStats};
use super::{triangle_key, Hit, Primitive, TriangleRecord, TRAVERSAL_SHIFT};
use glam::{Vec3, Vec3A};
use obvhs::cwbvh::CwBvh;
use obvhs::ray::{Ray, RayHit};

/// One BVH of triangles (the world-space one, or a prototype's in object space) with the
/// instance its hits report.
pub(super) struct TriangleLevel<'g> {
    pub(super) bvh: &'g CwBvh,
    pub(super) triangles: &'g [TriangleRecord],
    pub(super) instance: u32,
}

impl TriangleLevel<'_> {
    /// The nearest kept hit of `origin + t dir` with `t < *best_t`; lowers `*best_t` to it.
    #[inline(always)]
    pub(super) fn nearest(
        &self,
        origin: Vec3,
        dir: Vec3,
        best_t: &mut f32,
        keep: &impl Fn(&TriangleRecord, u64, f32, f32) -> bool,
    ) -> Option<Hit> {
        let ray = traversal_ray(origin, dir, *best_t);
        let mut hit = RayHit::none();
        let mut best = None;
        let tris = self.triangles;
        let instance = self.instance;
        with_watertight_ray!(origin, dir, |wt| self.bvh.ray_traverse(
            ray,
            &mut hit,
            |_, id| {
                let tri = &tris[id];
                match wt.intersect(&tri.p, *best_t) {
                    Some((t, _b0, b1, b2))
                        if keep(tri, triangle_key(instance, id as u32), b1, b2) =>
                    {
                        *best_t = t;
                        best = Some(Hit {
                            t,
                            primitive: Primitive::Triangle {
                                index: id as u32,
                                instance,
                                b1,
                                b2,
                            },
                        });
                        traversal_t(t)
                    }
                    _ => f32::INFINITY,
                }
            }
        ));
        best
    }

    /// Whether any kept hit of `origin + t dir` has `t < t_max`.
    #[inline(always)]
    pub(super) fn any(
        &self,
        origin: Vec3,
        dir: Vec3,
        t_max: f32,
        keep: &impl Fn(&TriangleRecord, u64, f32, f32) -> bool,
    ) -> bool {
        let ray = traversal_ray(origin, dir, t_max);
        let tris = self.triangles;
        let instance = self.instance;
        !with_watertight_ray!(origin, dir, |wt| self.bvh.ray_traverse_miss(
            ray,
            |_, id| {
                let tri = &tris[id];
                match wt.intersect(&tri.p, t_max) {
                    Some((_, _, b1, b2))
                        if keep(tri, triangle_key(instance, id as u32), b1, b2) =>
                    {
                        0.0
                    }
                    _ => f32::INFINITY,
                }
            }
        ))
    }
}

/// The ray handed to obvhs for `origin + t dir`, `t < t_max`: shifted back by
/// [`TRAVERSAL_SHIFT`] (see the module docs), its end rounded up so pruning is
/// conservative.
#[inline(always)]
pub(super) fn traversal_ray(origin: Vec3, dir: Vec3, t_max: f32) -> Ray {
    let shifted_origin = Vec3A::from(origin - dir * TRAVERSAL_SHIFT);
    let traversal_max = if t_max.is_finite() {
        traversal_t(t_max)
    } else {
        t_max
    };
    Ray::new(shifted_origin, traversal_dir(dir), 0.0, traversal_max)
}

/// The traversal ray's parameter of the real ray's `t`, rounded up so pruning is
/// conservative.
#[inline(always)]
pub(super) fn traversal_t(t: f32) -> f32 {
    (t + TRAVERSAL_SHIFT) * (1.0 + 1e-5)
}

/// A BVH over `triangles` and the triangles in its leaf order (so the hot loop indexes
/// them directly).
pub(super) fn triangle_bvh(
    triangles: &[TriangleRecord],
    stats: &mut BvhBuildStats,
) -> (CwBvh, Vec<TriangleRecord>) {
    if triangles.is_empty() {
        return (CwBvh::default(), Vec::new());
    }
    let tris: Vec<obvhs::triangle::Triangle> = triangles
        .iter()
        .map(|t| obvhs::triangle::Triangle {
            v0: t.p[0].into(),
            v1: t.p[1].into(),
            v2: t.p[2].into(),
        })
        .collect();
    let bvh = build::triangles_cwbvh(&tris, stats);
    let ordered = bvh
        .primitive_indices
        .iter()
        .map(|&i| triangles[i as usize])
        .collect();
    (bvh, ordered)
}

/// Bytes of a BVH's nodes and leaf index array.
pub(super) fn bvh_bytes(bvh: &CwBvh) -> usize {
    std::mem::size_of_val(bvh.nodes.as_slice())
        + std::mem::size_of_val(bvh.primitive_indices.as_slice())
}

/// The direction handed to obvhs. A third defect of obvhs 0.4.0: `safe_inverse(-0.0)` is
/// `-1/ε` while the CWBVH picks the ray octant by `d < 0` (false for `-0.0`), so a ray with
/// a negative-zero component (e.g. exactly along `-Z`) tests the wrong slab planes and
/// misses. Adding `+0.0` turns `-0.0` into `+0.0` and leaves every other value unchanged.
#[inline]
pub(super) fn traversal_dir(dir: Vec3) -> Vec3A {
    Vec3A::from(dir + Vec3::ZERO)
}
