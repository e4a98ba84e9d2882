//! The walks through the wide BVHs (see `wide`) of one level of triangles and of the top
//! level over instances, and the construction of a wide BVH from obvhs' binary tree.

use super::build::{self, BvhBuildStats};
use super::kernels::{self, Isa};
use super::wide::{BoxTest, Leaves, Level, Nearest, WideBvh};
use super::{AttributeRuns, HitTriangle, InstanceRecord, Prototype, TriangleRecord, Triangles};
use glam::Vec3;
use obvhs::aabb::Aabb;
use obvhs::bvh2::node::Bvh2Node;

/// One BVH of triangles (the world-space one, or a prototype's in object space) with the
/// instance its hits report, and the kernel that tests its boxes.
pub(super) struct TriangleLevel<'g> {
    pub(super) bvh: &'g WideBvh,
    pub(super) triangles: &'g Triangles,
    pub(super) instance: u32,
    pub(super) isa: Isa,
}

impl TriangleLevel<'_> {
    /// Offers every kept hit of `origin + t dir` to `best` (see [`Nearest`]).
    #[inline(always)]
    pub(super) fn nearest(
        &self,
        origin: Vec3,
        dir: Vec3,
        best: &mut Nearest,
        keep: &impl Fn(HitTriangle<'_>, u64, f32, f32) -> bool,
    ) {
        with_watertight_ray!(origin, dir, |wt| {
            let level = Level {
                triangles: self.triangles,
                instance: self.instance,
                intersect: &|p: &[Vec3; 3], t_max: f32| wt.intersect(p, t_max),
                keep,
            };
            kernels::nearest(self.isa, self.bvh, origin, dir, &level, best)
        })
    }

    /// Whether any kept hit of `origin + t dir` has `t < t_max`.
    #[inline(always)]
    pub(super) fn any(
        &self,
        origin: Vec3,
        dir: Vec3,
        t_max: f32,
        keep: &impl Fn(HitTriangle<'_>, u64, f32, f32) -> bool,
    ) -> bool {
        with_watertight_ray!(origin, dir, |wt| {
            let level = Level {
                triangles: self.triangles,
                instance: self.instance,
                intersect: &|p: &[Vec3; 3], t_max: f32| wt.intersect(p, t_max),
                keep,
            };
            kernels::any(self.isa, self.bvh, origin, dir, &level, t_max)
        })
    }
}

/// The leaves of the top level: each entry is an instance (an index into
/// `Geometry::instances`). At a leaf the world ray is carried into the instance's object
/// space and the prototype's BVH is walked with the same box test, so the whole two-level
/// walk runs inside one kernel.
pub(super) struct InstanceLeaves<'g, F> {
    /// The top level's leaf contents.
    pub(super) prims: &'g [u32],
    pub(super) instances: &'g [InstanceRecord],
    pub(super) prototypes: &'g [Prototype],
    /// The world-space ray.
    pub(super) origin: Vec3,
    pub(super) dir: Vec3,
    pub(super) keep: &'g F,
}

impl<F> InstanceLeaves<'_, F> {
    /// Instance `id`'s prototype and the ray in its object space (the direction
    /// unnormalised, so `t` is shared with the world ray).
    #[inline(always)]
    fn object_ray(&self, id: u32) -> (&Prototype, Vec3, Vec3) {
        let inst = &self.instances[id as usize];
        let o = inst.object_from_world.transform_point3(self.origin);
        let d = inst.object_from_world.transform_vector3(self.dir);
        (&self.prototypes[inst.prototype as usize], o, d)
    }
}

impl<F> Leaves for InstanceLeaves<'_, F>
where
    F: Fn(HitTriangle<'_>, u64, f32, f32) -> bool,
{
    #[inline(always)]
    fn nearest<K: BoxTest>(&self, first: u32, count: u32, best: &mut Nearest) {
        let first = first as usize;
        for &id in &self.prims[first..first + count as usize] {
            let (proto, o, d) = self.object_ray(id);
            let ray = super::wide::BoxRay::new(o, d);
            with_watertight_ray!(o, d, |wt| {
                let level = Level {
                    triangles: &proto.triangles,
                    instance: id,
                    intersect: &|p: &[Vec3; 3], t_max: f32| wt.intersect(p, t_max),
                    keep: self.keep,
                };
                super::wide::nearest::<K, _>(&proto.bvh, &ray, &level, best)
            })
        }
    }

    /// The top level's own stack: each instance's prototype is walked, with the
    /// triangles' stack, inside this walk.
    #[inline(always)]
    fn stack() -> &'static std::thread::LocalKey<std::cell::Cell<Vec<(u32, f32)>>> {
        &super::wide::TOP_STACK
    }

    #[inline(always)]
    fn any<K: BoxTest>(&self, first: u32, count: u32, t_max: f32) -> bool {
        let first = first as usize;
        // A loop rather than `Iterator::any`, which LLVM left uninlined, outside the
        // kernel's `#[target_feature]` function (callgrind: 9% of an instanced render).
        for &id in &self.prims[first..first + count as usize] {
            let (proto, o, d) = self.object_ray(id);
            let ray = super::wide::BoxRay::new(o, d);
            let hit = with_watertight_ray!(o, d, |wt| {
                let level = Level {
                    triangles: &proto.triangles,
                    instance: id,
                    intersect: &|p: &[Vec3; 3], t_max: f32| wt.intersect(p, t_max),
                    keep: self.keep,
                };
                super::wide::any::<K, _>(&proto.bvh, &ray, &level, t_max)
            });
            if hit {
                return true;
            }
        }
        false
    }
}

/// The wide BVH over `triangles`, the triangles stored in its leaf order and numbered
/// by obvhs' CWBVH leaf order (the order [`super::triangle_key`] has always numbered
/// them by, so keys and images do not change; see [`Triangles`]), and their bounds. The
/// binary tree is built once; of obvhs' CWBVH only its order is computed
/// ([`build::cwbvh_order`]).
pub(super) fn triangle_bvh(
    triangles: &[TriangleRecord],
    stats: &mut BvhBuildStats,
) -> (WideBvh, Triangles, Aabb) {
    triangle_bvh_of(triangles.len(), &|i| triangles[i], stats)
}

/// [`triangle_bvh`] over the `count` triangles `record(0..count)`, read several times
/// (for the boxes, once in leaf order for the triangles kept) instead of from a slice:
/// the caller needs no array of every triangle beside the stored ones, and those are
/// made only once the binary tree's temporaries are freed. Levels of
/// [`build::CHUNKED_FROM`] triangles or more are built in chunks
/// ([`build::chunked_bvh2`]).
pub(super) fn triangle_bvh_of(
    count: usize,
    record: &impl Fn(usize) -> TriangleRecord,
    stats: &mut BvhBuildStats,
) -> (WideBvh, Triangles, Aabb) {
    triangle_bvh_chunked(count, record, build::CHUNKED_FROM, build::CHUNK_MAX, stats)
}

/// [`triangle_bvh_of`] with levels of `chunked_from` triangles or more built in chunks of
/// at most `chunk_max` (the tests build small levels in chunks).
///
/// Memory (docs/benchmarks.md, "Large scene"): the binary tree's primitive indices are
/// the identity, so while the tree is collapsed they hold the triangles' leaf-order
/// positions instead (the entries the wide leaves take), and the leaf order itself, the
/// inverse, is made from them once the tree is freed: one array of 4 bytes a triangle
/// beside the tree at the collapse instead of three.
pub(super) fn triangle_bvh_chunked(
    count: usize,
    record: &impl Fn(usize) -> TriangleRecord,
    chunked_from: usize,
    chunk_max: usize,
    stats: &mut BvhBuildStats,
) -> (WideBvh, Triangles, Aabb) {
    if count == 0 {
        return (WideBvh::default(), Triangles::default(), Aabb::empty());
    }
    // The boxes obvhs' triangle builder would compute (`Triangle::aabb`), and the
    // attributes of every place, as runs (see `Triangles`).
    let triangle_box = |p: [Vec3; 3]| {
        obvhs::triangle::Triangle {
            v0: p[0].into(),
            v1: p[1].into(),
            v2: p[2].into(),
        }
        .aabb()
    };
    let mut runs = AttributeRuns::default();
    let mut bvh2 = if count >= chunked_from {
        for i in 0..count {
            runs.push(i as u32, record(i).attributes());
        }
        let bbox = |i: usize| triangle_box(record(i).p);
        build::chunked_bvh2(count, bbox, chunked_from, chunk_max, stats)
    } else {
        // The boxes as PLOC leaves, read once with the runs.
        let leaves: Vec<Bvh2Node> = (0..count)
            .map(|i| {
                let r = record(i);
                runs.push(i as u32, r.attributes());
                Bvh2Node::new(triangle_box(r.p), 1, i as u32)
            })
            .collect();
        build::leaves_bvh2(leaves, stats)
    };
    let bounds = *bvh2.nodes[0].aabb();
    debug_assert!(
        bvh2.primitive_indices
            .iter()
            .enumerate()
            .all(|(i, &p)| p as usize == i),
        "the builds' primitive indices are the identity"
    );
    let (order, position) = leaf_order(&bvh2);
    drop(order);
    bvh2.primitive_indices = position;
    let mut wide = WideBvh::collapse_entries(&bvh2);
    let position = std::mem::take(&mut bvh2.primitive_indices);
    drop(bvh2);
    // Shrinking copies the nodes: done with the binary tree gone, not beside it.
    wide.nodes.shrink_to_fit();
    let mut order = vec![0u32; count];
    for (i, &k) in position.iter().enumerate() {
        order[k as usize] = i as u32;
    }
    drop(position);
    // The leaves' entries, CWBVH positions leaf after leaf, become the stored order and
    // the triangles' numbers; the leaves' ranges then index the stored triangles.
    let ids = std::mem::take(&mut wide.prims);
    let triangles = Triangles::gather(ids, &order, runs, |i| record(i).p);
    (wide, triangles, bounds)
}

/// obvhs' CWBVH leaf order of `bvh2`'s primitives, the order a level stores them in
/// (`order[k]` is the primitive stored at `k`), and its inverse (`position[i]` is where
/// primitive `i` is stored, what the wide leaves name).
pub(super) fn leaf_order(bvh2: &obvhs::bvh2::Bvh2) -> (Vec<u32>, Vec<u32>) {
    let order = build::cwbvh_order(bvh2);
    let mut position = vec![0u32; order.len()];
    for (k, &i) in order.iter().enumerate() {
        position[i as usize] = k as u32;
    }
    (order, position)
}

/// The ray obvhs' CWBVH traversal was handed for `origin + t dir`, `t < t_max`, when it
/// still traversed the renderer's BVHs: shifted back by [`TRAVERSAL_SHIFT`] past its
/// hard-coded `1e-4` clamp on node entry distances, its end rounded up so pruning is
/// conservative. Only the tests that compare our traversal with obvhs' still use it.
#[cfg(test)]
#[inline(always)]
pub(super) fn traversal_ray(origin: Vec3, dir: Vec3, t_max: f32) -> obvhs::ray::Ray {
    let shifted_origin = glam::Vec3A::from(origin - dir * TRAVERSAL_SHIFT);
    let traversal_max = if t_max.is_finite() {
        traversal_t(t_max)
    } else {
        t_max
    };
    // `+ 0.0` turns `-0.0` into `+0.0`: obvhs 0.4 picks the ray octant by `d < 0` but
    // inverts `-0.0` to `-1/ε`, so a negative-zero component tests the wrong slabs.
    obvhs::ray::Ray::new(
        shifted_origin,
        glam::Vec3A::from(dir + Vec3::ZERO),
        0.0,
        traversal_max,
    )
}

/// How far behind the real origin [`traversal_ray`] starts: beyond obvhs' clamp of `1e-4`.
#[cfg(test)]
pub(super) const TRAVERSAL_SHIFT: f32 = 1e-3;

/// The parameter along [`traversal_ray`] of the real ray's `t`, rounded up.
#[cfg(test)]
#[inline(always)]
pub(super) fn traversal_t(t: f32) -> f32 {
    (t + TRAVERSAL_SHIFT) * (1.0 + 1e-5)
}
