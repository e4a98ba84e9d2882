//! Ray–scene intersection: triangles in a wide BVH of our own (`wide`, built from obvhs'
//! binary tree and traversed by the SIMD kernels of [`kernels`]), analytic spheres, and
//! instances of prototype meshes in two levels.
//!
//! **Two levels.** World-space triangles (meshes placed once) live in one BVH. A prototype
//! (a mesh placed at several places) has its own BVH over its object-space triangles, a
//! bottom-level structure built once; a top-level BVH over the instances' world bounds
//! points each leaf at one instance and so at its prototype (pbrt-v4, Pharr, Jakob &
//! Humphreys, 4th ed., section 7.1 "Object instancing"; the top level is "a BVH of
//! BVHs", section 7.3). At an instance leaf the ray is carried into object space by the
//! inverse affine transform, origin and direction, the direction *not* renormalised, so
//! the ray parameter `t` means the same point in both spaces and the nearest hit over
//! all instances is the one with the smallest `t`. The watertight test then runs
//! unchanged in object space. The instances' world bounds (the prototype's box
//! transformed corner by corner) are widened by the rounding bound of that transform
//! (pbrt 3rd ed. §3.9.3), so the top level prunes conservatively for the corners as
//! computed. A scene without instances skips the top level with one branch per ray.
//!
//! **One walk, every kernel.** Every BVH the renderer walks is ours: obvhs builds the
//! binary trees (see `build`) and `wide` collapses them into wide BVHs whose boxes the
//! SIMD kernels of [`kernels`] test; the walk is generic over what a leaf holds
//! (`wide::Leaves`): triangles, instances (the top level: at an instance the ray goes to
//! object space and the prototype's BVH is walked with the same kernel) or moving
//! triangles (one BVH per shutter segment, see `moving`). Our walk honours every distance
//! from 0 and picks slab planes by the direction's sign bit, so the defects of obvhs 0.4's
//! own CWBVH traversal, which the renderer once worked around, do not arise: it clamped
//! a child's entry distance at a hard-coded `1e-4` (a box within `1e-4` of the origin was
//! never entered: the renderer traversed with a ray shifted back by `1e-3`), and picked
//! the octant by `d < 0` while inverting `-0.0` to `-1/ε` (a ray exactly along `-Z`
//! tested the wrong slabs: the renderer added `+0.0`). Tests keep both cases, for
//! triangles, instances and moving triangles, on every kernel.
//!
//! **Which hit is nearest** is decided by a total order, not by the visit order, so that
//! every kernel gives the same hit bit for bit (ARCHITECTURE.md §2). The levels are
//! searched in turn, world-space triangles, instances, moving triangles, spheres, each
//! below the previous levels' nearest `t`, and a level's hit replaces theirs only when
//! strictly nearer (on an exact tie the earlier level's hit stays). Within a level the hit is the lexicographic minimum of `(t, key)` over every
//! hit the watertight test accepts (`wide::Nearest`), the key being [`triangle_key`]:
//! the triangle's number ([`Triangles::id`]: its place in obvhs' CWBVH leaf order, kept
//! beside the triangles stored in the wide BVH's own) among world-space triangles,
//! `(instance, number)` among instances (the instance first), the record index among
//! moving triangles. Spheres are
//! tested in index order, and one replaces the best only when strictly nearer.
//!
//! Triangles are tested with the watertight test of Woop, Benthin & Wald (JCGT 2013) in
//! pbrt's formulation (3rd ed. §3.6.2), with the fallback to double precision on exact
//! zero edge functions and pbrt's conservative bound that rejects hits whose `t` is not
//! provably positive (obvhs' Möller–Trumbore test could let rays slip through shared
//! edges).
//!
//! Every hit carries a floating-point error bound on its position (pbrt §3.9) so that rays
//! leaving it can be offset robustly by [`crate::math::offset_ray_origin`].
//!
//! The code is split by concern: `watertight` holds the ray–triangle and ray–sphere
//! tests, `traversal` the levels of triangles and of instances and the wide BVHs' build
//! from obvhs' trees, `wide` our wide BVH and its walk, [`kernels`] its box tests per
//! instruction set, `moving` the triangles that move within the shutter, and `build`
//! the construction of every binary tree (robust against coincident primitives, on a
//! thread with a stack of known size).

use crate::math::gamma;
use glam::{Affine3A, Mat3A, Vec2, Vec3, Vec3A, Vec4};

#[macro_use]
mod watertight;
mod build;
pub mod kernels;
mod moving;
mod traversal;
mod wide;

pub use build::{BvhBuildStats, BUILD_STACK_BYTES, CHUNKED_FROM, CLUSTER_MIN, TIE_MIN};
pub use kernels::Isa;
pub use moving::{shutter_segment, MotionTriangles};
use traversal::{leaf_order, triangle_bvh, triangle_bvh_of, InstanceLeaves, TriangleLevel};
pub use watertight::intersect_sphere;
use wide::{Nearest, WideBvh};

/// Sentinel for "not a light".
pub const NO_LIGHT: u32 = u32::MAX;

/// [`SurfacePoint::mesh`] of a point on a sphere.
pub const NO_MESH: u32 = u32::MAX;

/// [`Primitive::Triangle::instance`] of a triangle stored in world space.
pub const NO_INSTANCE: u32 = u32::MAX;

/// A triangle as stored for intersection, in BVH leaf order.
#[derive(Clone, Copy, Debug)]
pub struct TriangleRecord {
    /// Vertex positions in world space (in object space for a prototype's triangle).
    pub p: [Vec3; 3],
    /// Index of the mesh in the scene.
    pub mesh: u32,
    /// Index of the triangle within its mesh (for normals and texture coordinates).
    pub index: u32,
    /// Material index.
    pub material: u32,
    /// Index in the light list if the triangle emits, else [`NO_LIGHT`].
    pub light: u32,
}

impl TriangleRecord {
    /// What shading and the alpha filter read of the triangle (everything but `p`).
    #[inline(always)]
    pub fn attributes(&self) -> TriangleAttributes {
        TriangleAttributes {
            mesh: self.mesh,
            index: self.index,
            material: self.material,
            light: self.light,
        }
    }
}

/// What a stored triangle carries beside its positions: read after the walk (shading)
/// or when the watertight test accepts a hit (the alpha filter), never for a test.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TriangleAttributes {
    /// Index of the mesh in the scene.
    pub mesh: u32,
    /// Index of the triangle within its mesh (for normals and texture coordinates).
    pub index: u32,
    /// Material index.
    pub material: u32,
    /// Index in the light list if the triangle emits, else [`NO_LIGHT`].
    pub light: u32,
}

/// One level's triangles (the world-space ones, or a prototype's) stored in the leaf
/// order of the level's wide BVH, so that a leaf is a contiguous range of them, and split
/// by who reads what: the positions, all the watertight test reads (Woop, Benthin & Wald
/// 2013, §3), in one array, and two numbers per triangle read only at a hit. A leaf's
/// triangles are then adjacent 36-byte records instead of 52-byte ones reached through
/// an index array (docs/benchmarks.md, "Leaf-ordered triangles").
///
/// **Numbers.** Stored triangle `s` keeps the number it had when the triangles were
/// stored in obvhs' CWBVH leaf order ([`Triangles::id`]): ties between equal hit
/// distances go to the lower number and the alpha filter hashes it
/// ([`triangle_key`]), so hits and images are those of that order. [`Primitive::Triangle`]
/// names the stored position `s`.
///
/// **Attributes without an array of them.** The mesh, index, material and light of a
/// triangle are not stored per triangle (16 bytes each): the level keeps, per stored
/// triangle, its place in the order the level was built from (4 bytes: a scene's meshes
/// one after the other, each triangle in its mesh's order), and [`AttributeRun`]s that
/// give the attributes of every place: within a run the mesh and material are the same
/// and the index and light count up by one with the place. A mesh is one run (an
/// emissive mesh one more for each degenerate triangle, which is no light), so the runs
/// are a handful for a scene, and [`Triangles::attributes`] finds a place's run by a
/// table of blocks of places (usually one read, else a binary search over the runs of
/// one block), after the walk or when the alpha filter asks, never for a box or
/// triangle test
/// (docs/benchmarks.md, "Attributes from the triangle's place").
#[derive(Default)]
pub struct Triangles {
    /// The corners of triangle `s`, in leaf order.
    positions: Vec<[Vec3; 3]>,
    /// Its number for [`triangle_key`].
    ids: Vec<u32>,
    /// Its place in the level's build order, which [`Triangles::runs`] map to its
    /// attributes.
    places: Vec<u32>,
    /// The attributes of the places, run by run, in order of their first place.
    runs: Vec<AttributeRun>,
    /// Per block of `1 << block_shift` places, the run holding the block's first place,
    /// and one entry more (the last run): a place's run is among
    /// `runs[blocks[b]..=blocks[b + 1]]` of its block `b`, usually the first, so the
    /// look-up after a hit is a table read and not a binary search over every run.
    blocks: Vec<u32>,
    /// The places per block, as a power of two: about two blocks a run.
    block_shift: u32,
}

/// Consecutive places of a level's build order (see [`Triangles`]) whose attributes are
/// `first` at place `start` and follow from it by [`AttributeRun::at`] at the places after.
#[derive(Clone, Copy, Debug)]
struct AttributeRun {
    /// The first place of the run.
    start: u32,
    /// The attributes at `start`.
    first: TriangleAttributes,
}

impl AttributeRun {
    /// The attributes `k` places after the run's start: the same mesh and material, the
    /// index and (if the first place is a light) the light `k` further on. Wrapping
    /// additions, so the run's extent is decided by comparing this with the input
    /// ([`AttributeRuns::push`]) and no input can make it differ from what was given.
    #[inline(always)]
    fn at(&self, k: u32) -> TriangleAttributes {
        let a = self.first;
        TriangleAttributes {
            mesh: a.mesh,
            index: a.index.wrapping_add(k),
            material: a.material,
            light: if a.light == NO_LIGHT {
                NO_LIGHT
            } else {
                a.light.wrapping_add(k)
            },
        }
    }
}

/// The runs of a level's build order, made place by place (in order) while the boxes
/// are read.
#[derive(Default)]
pub(super) struct AttributeRuns(Vec<AttributeRun>);

impl AttributeRuns {
    /// Adds place `place` (one after the last added) with attributes `a`: the last run
    /// goes on if it gives `a` there, else a run starts.
    #[inline]
    pub(super) fn push(&mut self, place: u32, a: TriangleAttributes) {
        if let Some(r) = self.0.last() {
            if r.at(place - r.start) == a {
                return;
            }
        }
        self.0.push(AttributeRun {
            start: place,
            first: a,
        });
    }
}

impl Triangles {
    /// The triangles at places `order[ids[s]]` of the level's build order, stored in the
    /// order of `ids` (the level's leaf order) and numbered `ids[s]`; `position(place)`
    /// gives a place's corners and `runs` every place's attributes.
    pub(super) fn gather(
        ids: Vec<u32>,
        order: &[u32],
        runs: AttributeRuns,
        position: impl Fn(usize) -> [Vec3; 3],
    ) -> Self {
        let places: Vec<u32> = ids.iter().map(|&id| order[id as usize]).collect();
        let positions = places.iter().map(|&i| position(i as usize)).collect();
        let mut runs = runs.0;
        runs.shrink_to_fit();
        // The fewest places per block that leave at most two blocks a run.
        let count = order.len() as u64;
        let mut block_shift = 0;
        while (count >> block_shift) + 1 > 2 * runs.len() as u64 {
            block_shift += 1;
        }
        let block_count = (count >> block_shift) as usize + 1;
        let mut blocks = Vec::with_capacity(block_count + 1);
        let mut r = 0;
        for b in 0..block_count {
            let first = (b as u64) << block_shift;
            while r + 1 < runs.len() && u64::from(runs[r + 1].start) <= first {
                r += 1;
            }
            blocks.push(r as u32);
        }
        blocks.push(runs.len().saturating_sub(1) as u32);
        Self {
            positions,
            ids,
            places,
            runs,
            blocks,
            block_shift,
        }
    }

    /// Number of triangles.
    #[inline(always)]
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    /// Whether there are none.
    #[inline(always)]
    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    /// The corners of stored triangle `s`.
    #[inline(always)]
    pub fn positions(&self, s: usize) -> [Vec3; 3] {
        self.positions[s]
    }

    /// The corners of the stored triangles `range`, what a leaf's walk reads.
    #[inline(always)]
    pub(super) fn positions_in(&self, range: std::ops::Range<usize>) -> &[[Vec3; 3]] {
        &self.positions[range]
    }

    /// The attributes of stored triangle `s`, from its place and the run that holds it
    /// (see the type's docs).
    #[inline(always)]
    pub fn attributes(&self, s: usize) -> TriangleAttributes {
        let place = self.places[s];
        let b = (place >> self.block_shift) as usize;
        let (lo, hi) = (self.blocks[b] as usize, self.blocks[b + 1] as usize);
        // The run holding `place` is the last one starting at or before it; the block's
        // first run starts at or before the block, so it is at least that one.
        let r = if lo == hi || self.runs[lo + 1].start > place {
            &self.runs[lo]
        } else {
            let within = &self.runs[lo + 1..=hi];
            &within[within.partition_point(|r| r.start <= place) - 1]
        };
        r.at(place - r.start)
    }

    /// The number of stored triangle `s` (see the type's docs).
    #[inline(always)]
    pub fn id(&self, s: usize) -> u32 {
        self.ids[s]
    }

    /// Stored triangle `s` as a record.
    pub fn record(&self, s: usize) -> TriangleRecord {
        let a = self.attributes(s);
        TriangleRecord {
            p: self.positions(s),
            mesh: a.mesh,
            index: a.index,
            material: a.material,
            light: a.light,
        }
    }

    /// Every stored triangle as a record, in stored order.
    pub fn iter(&self) -> impl Iterator<Item = TriangleRecord> + '_ {
        (0..self.len()).map(|s| self.record(s))
    }

    /// Number of attribute runs (see the type's docs).
    pub fn runs(&self) -> usize {
        self.runs.len()
    }

    /// Bytes of the arrays, from their lengths.
    pub fn bytes(&self) -> usize {
        std::mem::size_of_val(self.positions.as_slice())
            + std::mem::size_of_val(self.ids.as_slice())
            + std::mem::size_of_val(self.places.as_slice())
            + std::mem::size_of_val(self.runs.as_slice())
            + std::mem::size_of_val(self.blocks.as_slice())
    }
}

/// A triangle the watertight test accepted, as the filter of
/// [`Geometry::intersect_where`] sees it: its attributes are worked out only if the
/// filter asks for them, so a filter that keeps every hit costs the walk no look-up.
#[derive(Clone, Copy)]
pub enum HitTriangle<'a> {
    /// Stored triangle `s` of a level.
    Stored(&'a Triangles, usize),
    /// A moving triangle's record.
    Record(&'a TriangleRecord),
}

impl HitTriangle<'_> {
    /// The triangle's mesh, index, material and light.
    #[inline(always)]
    pub fn attributes(self) -> TriangleAttributes {
        match self {
            HitTriangle::Stored(t, s) => t.attributes(s),
            HitTriangle::Record(r) => r.attributes(),
        }
    }
}

/// An analytic sphere.
#[derive(Clone, Copy, Debug)]
pub struct SphereRecord {
    /// Centre.
    pub center: Vec3,
    /// Radius.
    pub radius: f32,
    /// Material index.
    pub material: u32,
    /// Index in the light list if the sphere emits, else [`NO_LIGHT`].
    pub light: u32,
}

/// What a ray hit.
#[derive(Clone, Copy, Debug)]
pub enum Primitive {
    /// A triangle: its stored position in [`Geometry::triangles`] (or, for an instance,
    /// in its prototype's [`Prototype::triangles`]) and barycentrics of vertices 1 and 2.
    Triangle {
        /// Position in the level's leaf-ordered [`Triangles`] (not its number for
        /// [`triangle_key`], which is [`Triangles::id`] of it).
        index: u32,
        /// Index into [`Geometry::instances`], or [`NO_INSTANCE`] for a world-space
        /// triangle.
        instance: u32,
        /// Barycentric coordinate of vertex 1.
        b1: f32,
        /// Barycentric coordinate of vertex 2.
        b2: f32,
    },
    /// A sphere: index into [`Geometry::spheres`].
    Sphere {
        /// Index of the sphere.
        index: u32,
    },
    /// A triangle that moves within the shutter (motion blur): index into
    /// [`MotionTriangles::records`], barycentrics of vertices 1 and 2 of the triangle as it
    /// stood at `time`, and that time (shutter fraction), so shading sees the same
    /// triangle the ray hit.
    Moving {
        /// Index into [`MotionTriangles::records`].
        index: u32,
        /// Barycentric coordinate of vertex 1.
        b1: f32,
        /// Barycentric coordinate of vertex 2.
        b2: f32,
        /// Shutter fraction in `[0, 1]` of the ray.
        time: f32,
    },
}

/// The nearest intersection found along a ray.
#[derive(Clone, Copy, Debug)]
pub struct Hit {
    /// Ray parameter of the hit.
    pub t: f32,
    /// What was hit.
    pub primitive: Primitive,
}

/// A mesh stored once and placed by instances: its object-space triangles in their own
/// BVH (the bottom level).
pub struct Prototype {
    bvh: WideBvh,
    /// Bounds of the object-space triangles.
    bounds: obvhs::aabb::Aabb,
    /// Object-space triangles in the BVH's leaf order.
    pub triangles: Triangles,
}

impl Prototype {
    /// Bytes of the BVH nodes and triangles.
    pub fn bytes(&self) -> usize {
        self.bvh.bytes() + self.triangles.bytes()
    }
}

/// One placement of a [`Prototype`], with the transforms intersection and shading need.
#[derive(Clone, Copy, Debug)]
pub struct InstanceRecord {
    /// Position of the instance in the list given to [`Geometry::build_instanced`]
    /// (`tessera_scene::Scene::instances` order).
    pub index: u32,
    /// Index into [`Geometry::prototypes`].
    pub prototype: u32,
    /// World-from-object transform.
    pub world_from_object: Affine3A,
    /// Its inverse (computed in double precision), which carries rays into object space.
    pub object_from_world: Affine3A,
    /// The inverse transpose of the linear part: transforms normals to world space, and
    /// keeps the front side that a flattened copy, re-wound when mirrored, would have.
    pub normal_to_world: Mat3A,
    /// 1, or -1 when the transform mirrors (flips the bitangent sign of tangents).
    pub handedness: f32,
}

/// Scene geometry with its acceleration structure.
pub struct Geometry {
    bvh: WideBvh,
    /// World-space triangles in the BVH's leaf order.
    pub triangles: Triangles,
    /// Meshes stored once, each with its bottom-level BVH.
    pub prototypes: Vec<Prototype>,
    /// The top level: a wide BVH over the instances' world bounds, its leaves naming
    /// positions in [`Geometry::instances`].
    tlas: WideBvh,
    /// Instances in the order the top-level leaves refer to them.
    pub instances: Vec<InstanceRecord>,
    /// Analytic spheres (tested linearly: scenes have few).
    pub spheres: Vec<SphereRecord>,
    /// Triangles that move within the shutter, when the scene has motion blur.
    pub motion: Option<MotionTriangles>,
    /// Centre and radius of a sphere bounding everything.
    pub bounds_center: Vec3,
    /// Radius of the bounding sphere.
    pub bounds_radius: f32,
    /// What building the BVHs cost.
    build_stats: BvhBuildStats,
    /// The kernel that tests the wide BVHs' boxes.
    isa: Isa,
}

impl Geometry {
    /// Builds the BVH over `triangles` (any order) and keeps `spheres`.
    pub fn build(triangles: Vec<TriangleRecord>, spheres: Vec<SphereRecord>) -> Self {
        Self::build_instanced(triangles, spheres, Vec::new(), &[])
    }

    /// [`Geometry::build`] with prototypes (object-space triangles, one BVH each) and
    /// `instances` as `(prototype, world_from_object)`; every transform must be finite and
    /// invertible (what `tessera_scene::Scene::validate` checks).
    ///
    /// The BVHs are built on a thread of their own with a stack of [`BUILD_STACK_BYTES`],
    /// whatever the caller's stack, and stay `O(n log n)` on coincident primitives (see
    /// [`Geometry::build_stats`]).
    pub fn build_instanced(
        triangles: Vec<TriangleRecord>,
        spheres: Vec<SphereRecord>,
        prototypes: Vec<Vec<TriangleRecord>>,
        instances: &[(u32, Affine3A)],
    ) -> Self {
        Self::build_instanced_of(
            triangles.len(),
            |i| triangles[i],
            spheres,
            prototypes,
            instances,
        )
    }

    /// [`Geometry::build_instanced`] with the world-space triangles given as `count`
    /// records `record(0..count)` (the order of a `Vec` the other builders take), which
    /// it reads twice instead of holding them all: once for the BVH's boxes and once, in
    /// leaf order, for the records it keeps. A scene of millions of triangles is then
    /// held once, as the geometry, not also as an array in scene order (see "Memory" in
    /// the `build` module docs). `record` must give the same record for an index each time.
    pub fn build_instanced_of(
        count: usize,
        record: impl Fn(usize) -> TriangleRecord + Sync,
        spheres: Vec<SphereRecord>,
        prototypes: Vec<Vec<TriangleRecord>>,
        instances: &[(u32, Affine3A)],
    ) -> Self {
        let record = &record;
        build::on_build_stack(move || {
            Self::build_on_this_thread(count, record, spheres, prototypes, instances)
        })
    }

    /// [`Geometry::build_instanced_of`] on the calling thread.
    fn build_on_this_thread(
        count: usize,
        record: &impl Fn(usize) -> TriangleRecord,
        spheres: Vec<SphereRecord>,
        prototypes: Vec<Vec<TriangleRecord>>,
        instances: &[(u32, Affine3A)],
    ) -> Self {
        let mut build_stats = BvhBuildStats::default();
        let mut lo = Vec3::splat(f32::INFINITY);
        let mut hi = Vec3::splat(f32::NEG_INFINITY);
        for i in 0..count {
            for p in record(i).p {
                lo = lo.min(p);
                hi = hi.max(p);
            }
        }
        let (bvh, triangles, _) = triangle_bvh_of(count, record, &mut build_stats);
        let prototypes: Vec<Prototype> = prototypes
            .iter()
            .map(|tris| {
                let (bvh, triangles, bounds) = triangle_bvh(tris, &mut build_stats);
                Prototype {
                    bvh,
                    bounds,
                    triangles,
                }
            })
            .collect();
        // Instances of empty prototypes can never be hit (and an empty box has no centre
        // for the builder): leave them out.
        let instances: Vec<(u32, u32, Affine3A)> = instances
            .iter()
            .enumerate()
            .filter(|&(_, &(p, _))| !prototypes[p as usize].triangles.is_empty())
            .map(|(i, &(p, m))| (i as u32, p, m))
            .collect();
        // The top level: each instance's world bounds are its prototype's object bounds
        // transformed corner by corner (conservative for any affine map).
        let world_bounds: Vec<obvhs::aabb::Aabb> = instances
            .iter()
            .map(|&(_, proto, m)| {
                let b = prototypes[proto as usize].bounds;
                let mut wb = obvhs::aabb::Aabb::empty();
                for k in 0..8 {
                    let c = Vec3A::new(
                        if k & 1 == 0 { b.min.x } else { b.max.x },
                        if k & 2 == 0 { b.min.y } else { b.max.y },
                        if k & 4 == 0 { b.min.z } else { b.max.z },
                    );
                    wb.extend(m.transform_point3a(c));
                }
                lo = lo.min(wb.min.into());
                hi = hi.max(wb.max.into());
                wb
            })
            .collect();
        let (tlas, instances) = if instances.is_empty() {
            (WideBvh::default(), Vec::new())
        } else {
            // The tree over the boxes as computed (the one obvhs built before, so the
            // instances keep their numbers, which keys and images depend on), then each
            // box widened by its transform's rounding bound.
            let mut bvh2 = build::boxes_bvh2(&world_bounds, &mut build_stats);
            let (order, position) = leaf_order(&bvh2);
            build::widen_boxes(&mut bvh2, |i, b| {
                let (_, proto, m) = instances[i as usize];
                let pad = Vec3A::from(transform_error(&m, &prototypes[proto as usize].bounds));
                obvhs::aabb::Aabb::new(b.min - pad, b.max + pad)
            });
            let tlas = WideBvh::collapse(&bvh2, &position);
            let records = order
                .iter()
                .map(|&i| {
                    let (index, prototype, m) = instances[i as usize];
                    let inverse = m.as_daffine3().inverse();
                    InstanceRecord {
                        index,
                        prototype,
                        world_from_object: m,
                        object_from_world: inverse.as_affine3a(),
                        normal_to_world: Mat3A::from(inverse.matrix3.transpose().as_mat3()),
                        handedness: if m.matrix3.determinant() < 0.0 {
                            -1.0
                        } else {
                            1.0
                        },
                    }
                })
                .collect();
            (tlas, records)
        };
        for s in &spheres {
            lo = lo.min(s.center - s.radius);
            hi = hi.max(s.center + s.radius);
        }
        let (bounds_center, bounds_radius) = if lo.x <= hi.x {
            ((lo + hi) * 0.5, ((hi - lo) * 0.5).length().max(1e-6))
        } else {
            (Vec3::ZERO, 1.0)
        };
        Self {
            bvh,
            triangles,
            prototypes,
            tlas,
            instances,
            spheres,
            motion: None,
            bounds_center,
            bounds_radius,
            build_stats,
            isa: kernels::active(),
        }
    }

    /// The kernel that tests the wide BVHs' boxes ([`kernels::active`] unless
    /// `Geometry::with_isa` chose another).
    pub fn isa(&self) -> Isa {
        self.isa
    }

    /// Traverses this geometry with kernel `isa` from now on, or says why this CPU cannot
    /// run it. Every kernel finds the same hits, bit for bit (see [`kernels`]).
    pub fn set_isa(&mut self, isa: Isa) -> Result<(), String> {
        if !isa.available() {
            return Err(format!("this CPU lacks {}", isa.name()));
        }
        self.isa = isa;
        Ok(())
    }

    /// What building the BVHs cost (including the moving triangles' once added): a
    /// count of our own work, bounded by a constant times `n log n` (see
    /// [`BvhBuildStats::work`]).
    pub fn build_stats(&self) -> BvhBuildStats {
        self.build_stats
    }

    /// Adds the triangles that move within the shutter (see [`MotionTriangles`]) and
    /// widens the bounding sphere to cover them at every key time.
    pub fn with_motion(mut self, motion: MotionTriangles) -> Self {
        if motion.records.is_empty() {
            return self;
        }
        let (mut lo, mut hi) = (
            self.bounds_center - Vec3::splat(self.bounds_radius),
            self.bounds_center + Vec3::splat(self.bounds_radius),
        );
        if self.triangles.is_empty() && self.instances.is_empty() && self.spheres.is_empty() {
            lo = Vec3::splat(f32::INFINITY);
            hi = Vec3::splat(f32::NEG_INFINITY);
        }
        for p in motion.keys.iter().flatten() {
            lo = lo.min(*p);
            hi = hi.max(*p);
        }
        self.bounds_center = (lo + hi) * 0.5;
        self.bounds_radius = ((hi - lo) * 0.5).length().max(1e-6);
        self.build_stats.add(&motion.build_stats);
        self.motion = Some(motion);
        self
    }

    /// Bytes of the acceleration structures and triangles (BVH nodes, leaf index arrays,
    /// triangles, instances), from their lengths: what the geometry costs in
    /// memory, for comparing instancing with flattening.
    pub fn bytes(&self) -> usize {
        self.bvh.bytes()
            + self.triangles.bytes()
            + self.prototypes.iter().map(Prototype::bytes).sum::<usize>()
            + self.tlas.bytes()
            + std::mem::size_of_val(self.instances.as_slice())
            + self.motion.as_ref().map_or(0, MotionTriangles::bytes)
    }

    /// The nearest hit along `origin + t dir` with `0 < t < t_max` (`dir` need not be
    /// normalised; on ties see the module docs).
    #[inline]
    pub fn intersect(&self, origin: Vec3, dir: Vec3, t_max: f32) -> Option<Hit> {
        self.intersect_where(origin, dir, t_max, 0.0, |_, _, _, _| true)
    }

    /// [`Geometry::intersect`] counting only the triangle hits `keep(triangle, key, b1,
    /// b2)` accepts (alpha-tested surfaces pass rays through where `keep` says so); `key`
    /// identifies the triangle (see [`triangle_key`]). Rejected hits do not shorten the
    /// ray, so the traversal goes on past them. `time` is the ray's shutter fraction in
    /// `[0, 1]`: moving triangles ([`Geometry::motion`]) are intersected where they stand
    /// then; everything else ignores it.
    pub fn intersect_where(
        &self,
        origin: Vec3,
        dir: Vec3,
        t_max: f32,
        time: f32,
        keep: impl Fn(HitTriangle<'_>, u64, f32, f32) -> bool,
    ) -> Option<Hit> {
        let mut best: Option<Hit> = None;
        let mut best_t = t_max;
        // Each level searches below the nearest `t` of the levels before it, and its hit
        // replaces theirs only when strictly nearer (the triangle test compares `t` with
        // its bound in a scaled form, which may admit an equal `t`): on equal `t` the
        // earlier level's hit stays (see the module docs).
        let take = |n: Nearest, best: &mut Option<Hit>, best_t: &mut f32| {
            if let Some(h) = n.hit {
                if best.is_none() || h.t < *best_t {
                    *best_t = h.t;
                    *best = Some(h);
                }
            }
        };
        if !self.triangles.is_empty() {
            let mut n = Nearest::new(best_t);
            self.world_level().nearest(origin, dir, &mut n, &keep);
            take(n, &mut best, &mut best_t);
        }
        if !self.instances.is_empty() {
            let mut n = Nearest::new(best_t);
            let leaves = self.instance_leaves(origin, dir, &keep);
            kernels::nearest(self.isa, &self.tlas, origin, dir, &leaves, &mut n);
            take(n, &mut best, &mut best_t);
        }
        if let Some(m) = &self.motion {
            let mut n = Nearest::new(best_t);
            m.nearest(self.isa, origin, dir, &mut n, time, &keep);
            take(n, &mut best, &mut best_t);
        }
        for (i, s) in self.spheres.iter().enumerate() {
            if let Some(t) = intersect_sphere(s.center, s.radius, origin, dir, best_t) {
                best_t = t;
                best = Some(Hit {
                    t,
                    primitive: Primitive::Sphere { index: i as u32 },
                });
            }
        }
        best
    }

    /// True if anything blocks `origin + t dir` for `0 < t < t_max`.
    #[inline]
    pub fn occluded(&self, origin: Vec3, dir: Vec3, t_max: f32) -> bool {
        self.occluded_where(origin, dir, t_max, 0.0, |_, _, _, _| true)
    }

    /// [`Geometry::occluded`] at shutter fraction `time`, with the triangle filter of
    /// [`Geometry::intersect_where`].
    pub fn occluded_where(
        &self,
        origin: Vec3,
        dir: Vec3,
        t_max: f32,
        time: f32,
        keep: impl Fn(HitTriangle<'_>, u64, f32, f32) -> bool,
    ) -> bool {
        for s in &self.spheres {
            if intersect_sphere(s.center, s.radius, origin, dir, t_max).is_some() {
                return true;
            }
        }
        if !self.triangles.is_empty() && self.world_level().any(origin, dir, t_max, &keep) {
            return true;
        }
        if let Some(m) = &self.motion {
            if m.any(self.isa, origin, dir, t_max, time, &keep) {
                return true;
            }
        }
        !self.instances.is_empty() && {
            let leaves = self.instance_leaves(origin, dir, &keep);
            kernels::any(self.isa, &self.tlas, origin, dir, &leaves, t_max)
        }
    }
}

impl Geometry {
    /// The world-space triangles as a traversal level.
    #[inline(always)]
    fn world_level(&self) -> TriangleLevel<'_> {
        TriangleLevel {
            bvh: &self.bvh,
            triangles: &self.triangles,
            instance: NO_INSTANCE,
            isa: self.isa,
        }
    }

    /// The top level's leaves for the world ray `origin + t dir`.
    #[inline(always)]
    fn instance_leaves<'g, F>(
        &'g self,
        origin: Vec3,
        dir: Vec3,
        keep: &'g F,
    ) -> InstanceLeaves<'g, F> {
        InstanceLeaves {
            prims: &self.tlas.prims,
            instances: &self.instances,
            prototypes: &self.prototypes,
            origin,
            dir,
            keep,
        }
    }
}

/// Per axis, a bound on the rounding error of `m` applied to any corner of `b`:
/// `|m_i0 x| + |m_i1 y| + |m_i2 z| + |t_i|` times `γ(3)` (pbrt 3rd ed. §3.9.3, the error
/// of transforming a point), with each coordinate at its largest magnitude over the box;
/// `γ(4)` rather than `γ(3)` because the sum is rounded too.
fn transform_error(m: &Affine3A, b: &obvhs::aabb::Aabb) -> Vec3 {
    let c = b.min.abs().max(b.max.abs());
    let a = Mat3A::from_cols(
        m.matrix3.x_axis.abs(),
        m.matrix3.y_axis.abs(),
        m.matrix3.z_axis.abs(),
    );
    Vec3::from(a * c + m.translation.abs()) * gamma(4)
}

/// Identifies a triangle for the filter of [`Geometry::intersect_where`] (and for hashing
/// decisions per triangle, such as stochastic alpha): its index for a world-space
/// triangle, its index and instance otherwise.
#[inline]
pub fn triangle_key(instance: u32, index: u32) -> u64 {
    if instance == NO_INSTANCE {
        u64::from(index)
    } else {
        ((u64::from(instance) + 1) << 32) | u64::from(index)
    }
}

/// Surface data at a hit, in world space.
#[derive(Clone, Copy, Debug)]
pub struct SurfacePoint {
    /// Position.
    pub p: Vec3,
    /// Conservative absolute error bound of each coordinate of `p`.
    pub p_error: Vec3,
    /// Unit geometric normal (for triangles: `(p1 - p0) x (p2 - p0)` normalised, i.e. the
    /// front side is counter-clockwise; for spheres: outward).
    pub ng: Vec3,
    /// Unit shading normal, on the same side as `ng` (interpolated, then normal-mapped).
    pub ns: Vec3,
    /// Texture coordinates of set 0 (`TEXCOORD_0`; spherical coordinates on spheres).
    pub uv: Vec2,
    /// Mesh of the hit triangle, or [`NO_MESH`] on a sphere.
    pub mesh: u32,
    /// Triangle index within its mesh.
    pub tri: u32,
    /// Barycentric coordinates `(b1, b2)` of the hit in its triangle.
    pub bary: Vec2,
    /// Material index.
    pub material: u32,
    /// Light index or [`NO_LIGHT`].
    pub light: u32,
    /// The shading tangent in world space (`xyz`: the mesh's corner tangents interpolated
    /// at `bary`, carried by the instance's transform or taken at the ray's time for a
    /// moving mesh; neither unit nor orthogonal to `ns`) and the bitangent sign (`w`,
    /// ±1, flipped by a mirroring instance): the frame of the normal map and of
    /// KHR_materials_anisotropy. Filled only where the material uses a tangent frame and
    /// the mesh has tangents, zero elsewhere, so other materials pay one store for it.
    pub tangent: Vec4,
}

/// Position on a triangle from barycentrics, with pbrt's error bound (§3.9.4).
#[inline]
pub fn triangle_point(p: &[Vec3; 3], b0: f32, b1: f32, b2: f32) -> (Vec3, Vec3) {
    let pos = b0 * p[0] + b1 * p[1] + b2 * p[2];
    let err = gamma(7) * ((b0 * p[0]).abs() + (b1 * p[1]).abs() + (b2 * p[2]).abs());
    (pos, err)
}

/// Position on a sphere re-projected onto its surface, with pbrt's error bound (§3.9.4).
#[inline]
pub fn sphere_point(center: Vec3, radius: f32, p: Vec3) -> (Vec3, Vec3, Vec3) {
    let local = p - center;
    let len = local.length();
    let n = if len > 0.0 { local / len } else { Vec3::Y };
    let local = n * radius;
    let pos = center + local;
    let err = gamma(5) * local.abs() + gamma(1) * center.abs() + gamma(1) * pos.abs();
    (pos, err, n)
}

#[cfg(test)]
mod kernel_tests;
#[cfg(test)]
mod tests;
