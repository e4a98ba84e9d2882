//! The walk through one BVH of triangles (our wide BVH, see `wide`), and the ray handed
//! to obvhs for the BVHs it still traverses, the top level over instances and the motion
//! segments (see the module docs of `geometry` for the shift and the defects it works
//! around).

use super::build::{self, BvhBuildStats};
use super::kernels::{self, Isa};
use super::wide::{Level, WideBvh};
use super::{Hit, TriangleRecord, TRAVERSAL_SHIFT};
use glam::{Vec3, Vec3A};
use obvhs::aabb::Aabb;
use obvhs::bvh2::node::Bvh2Node;
use obvhs::cwbvh::CwBvh;
use obvhs::ray::Ray;

/// One BVH of triangles (the world-space one, or a prototype's in object space) with the
/// instance its hits report, and the kernel that tests its boxes.
pub(super) struct TriangleLevel<'g> {
    pub(super) bvh: &'g WideBvh,
    pub(super) triangles: &'g [TriangleRecord],
    pub(super) instance: u32,
    pub(super) isa: Isa,
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
        let level = Level {
            bvh: self.bvh,
            triangles: self.triangles,
            instance: self.instance,
        };
        with_watertight_ray!(origin, dir, |wt| kernels::nearest(
            self.isa,
            &level,
            origin,
            dir,
            best_t,
            &|p: &[Vec3; 3], t_max: f32| wt.intersect(p, t_max),
            keep
        ))
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
        let level = Level {
            bvh: self.bvh,
            triangles: self.triangles,
            instance: self.instance,
        };
        with_watertight_ray!(origin, dir, |wt| kernels::any(
            self.isa,
            &level,
            origin,
            dir,
            t_max,
            &|p: &[Vec3; 3], t_max: f32| wt.intersect(p, t_max),
            keep
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

/// The wide BVH over `triangles`, the triangles in obvhs' CWBVH leaf order (the order
/// [`super::triangle_key`] has always numbered them by, so keys and images do not
/// change), and their bounds. The binary tree is built once; of obvhs' CWBVH only its
/// order is computed ([`build::cwbvh_order`]).
pub(super) fn triangle_bvh(
    triangles: &[TriangleRecord],
    stats: &mut BvhBuildStats,
) -> (WideBvh, Vec<TriangleRecord>, Aabb) {
    triangle_bvh_of(triangles.len(), &|i| triangles[i], stats)
}

/// [`triangle_bvh`] over the `count` triangles `record(0..count)`, read twice (once for
/// the boxes, once in leaf order for the records kept) instead of from a slice: the
/// caller needs no array of every triangle beside the one in leaf order, and the records
/// are made only once the binary tree's temporaries are freed.
pub(super) fn triangle_bvh_of(
    count: usize,
    record: &impl Fn(usize) -> TriangleRecord,
    stats: &mut BvhBuildStats,
) -> (WideBvh, Vec<TriangleRecord>, Aabb) {
    if count == 0 {
        return (WideBvh::default(), Vec::new(), Aabb::empty());
    }
    // The boxes obvhs' triangle builder would compute (`Triangle::aabb`), as PLOC leaves.
    let leaves: Vec<Bvh2Node> = (0..count)
        .map(|i| {
            let p = record(i).p;
            let t = obvhs::triangle::Triangle {
                v0: p[0].into(),
                v1: p[1].into(),
                v2: p[2].into(),
            };
            Bvh2Node::new(t.aabb(), 1, i as u32)
        })
        .collect();
    let bvh2 = build::leaves_bvh2(leaves, stats);
    let order = build::cwbvh_order(&bvh2);
    let mut position = vec![0u32; count];
    for (k, &i) in order.iter().enumerate() {
        position[i as usize] = k as u32;
    }
    let bounds = *bvh2.nodes[0].aabb();
    let wide = WideBvh::collapse(&bvh2, &position);
    drop((bvh2, position));
    let ordered = order.iter().map(|&i| record(i as usize)).collect();
    (wide, ordered, bounds)
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
