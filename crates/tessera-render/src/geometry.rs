//! Ray–scene intersection: triangles in an `obvhs` compressed wide BVH, analytic spheres,
//! and instances of prototype meshes in two levels.
//!
//! **Two levels.** World-space triangles (meshes placed once) live in one BVH. A prototype
//! (a mesh placed at several places) has its own BVH over its object-space triangles, a
//! bottom-level structure built once; a top-level BVH over the instances' world bounds
//! points each leaf at one instance and so at its prototype (pbrt-v4, Pharr, Jakob &
//! Humphreys, 4th ed., section 7.1 "Object instancing"; the top level is "a BVH of
//! BVHs", section 7.3). At an instance leaf the ray is carried into object space by the
//! inverse affine transform, origin and direction, the direction *not* renormalised, so
//! the ray parameter `t` means the same point in both spaces and the nearest hit over
//! all instances is the one with the smallest `t`. The watertight test and the shift
//! trick below then run unchanged in object space. A scene without instances skips the
//! top level with one branch per ray.
//!
//! Two defects of obvhs 0.4.0 are kept out of our images here:
//!
//! 1. **Near hits.** Its CWBVH node test clamps a child's entry distance at a hard-coded
//!    `1e-4` and ignores `Ray::tmin`, so a child box lying entirely within `1e-4` of the ray
//!    origin is never visited and nearby hits are lost (small-scale scenes break). We traverse
//!    with a *shifted* ray whose origin lies [`TRAVERSAL_SHIFT`] behind the real origin, so
//!    every real hit is at least that far along the traversal ray, beyond the clamp. The
//!    triangles themselves are intersected with the *unshifted* ray, so no precision is
//!    lost; only the pruning distance handed back to obvhs is expressed in the shifted
//!    parameterisation (rounded up, so pruning stays conservative).
//! 2. **Watertightness.** Its Möller–Trumbore test can let rays slip through shared edges.
//!    We use the watertight test of Woop, Benthin & Wald (JCGT 2013) in pbrt's formulation
//!    (3rd ed. §3.6.2), with the fallback to double precision on exact zero edge functions
//!    and pbrt's conservative bound that rejects hits whose `t` is not provably positive.
//!
//! Every hit carries a floating-point error bound on its position (pbrt §3.9) so that rays
//! leaving it can be offset robustly by [`crate::math::offset_ray_origin`].

use crate::math::gamma;
use glam::{Affine3A, Mat3A, Vec2, Vec3, Vec3A, Vec3Swizzles};
use obvhs::cwbvh::CwBvh;
use obvhs::ray::{Ray, RayHit};

/// How far behind the real origin the BVH traversal ray starts (see the module docs). It
/// must exceed obvhs' internal clamp of `1e-4` on node entry distances.
pub const TRAVERSAL_SHIFT: f32 = 1e-3;

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
    /// A triangle: index into [`Geometry::triangles`] (or, for an instance, into its
    /// prototype's [`Prototype::triangles`]) and barycentrics of vertices 1 and 2.
    Triangle {
        /// Index into the BVH-ordered triangle array.
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
    bvh: CwBvh,
    /// Object-space triangles in the order the BVH leaves refer to them.
    pub triangles: Vec<TriangleRecord>,
}

impl Prototype {
    /// Bytes of the BVH nodes and triangle records.
    pub fn bytes(&self) -> usize {
        bvh_bytes(&self.bvh) + std::mem::size_of_val(self.triangles.as_slice())
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
    bvh: CwBvh,
    /// Triangles in the order the BVH leaves refer to them.
    pub triangles: Vec<TriangleRecord>,
    /// Meshes stored once, each with its bottom-level BVH.
    pub prototypes: Vec<Prototype>,
    /// The top level: a BVH over the instances' world bounds.
    tlas: CwBvh,
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
}

/// Per-ray constants of the watertight triangle test: the permutation that makes the ray
/// direction's largest component z (`KZ` is that component's axis, a type parameter so the
/// permutation compiles to a fixed shuffle instead of indexing through memory), and the
/// shear that aligns the ray with +z.
#[derive(Clone, Copy)]
struct WatertightRay<const KZ: usize> {
    /// The ray origin, permuted.
    origin: Vec3A,
    sx: f32,
    sy: f32,
    sz: f32,
}

/// The axis of `dir`'s largest component (ties to the later axis), which becomes z in the
/// watertight test.
#[inline(always)]
fn dominant_axis(dir: Vec3) -> usize {
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
        match dominant_axis(dir) {
            0 => {
                let $wt = WatertightRay::<0>::new(origin, dir);
                $body
            }
            1 => {
                let $wt = WatertightRay::<1>::new(origin, dir);
                $body
            }
            _ => {
                let $wt = WatertightRay::<2>::new(origin, dir);
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
    fn new(origin: Vec3, dir: Vec3) -> Self {
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
    fn intersect(&self, p: &[Vec3; 3], t_max: f32) -> Option<(f32, f32, f32, f32)> {
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

impl Geometry {
    /// Builds the BVH over `triangles` (any order) and keeps `spheres`.
    pub fn build(triangles: Vec<TriangleRecord>, spheres: Vec<SphereRecord>) -> Self {
        Self::build_instanced(triangles, spheres, Vec::new(), &[])
    }

    /// [`Geometry::build`] with prototypes (object-space triangles, one BVH each) and
    /// `instances` as `(prototype, world_from_object)`; every transform must be finite and
    /// invertible (what `tessera_scene::Scene::validate` checks).
    pub fn build_instanced(
        triangles: Vec<TriangleRecord>,
        spheres: Vec<SphereRecord>,
        prototypes: Vec<Vec<TriangleRecord>>,
        instances: &[(u32, Affine3A)],
    ) -> Self {
        let mut lo = Vec3::splat(f32::INFINITY);
        let mut hi = Vec3::splat(f32::NEG_INFINITY);
        for t in &triangles {
            for p in t.p {
                lo = lo.min(p);
                hi = hi.max(p);
            }
        }
        let (bvh, ordered) = triangle_bvh(&triangles);
        let prototypes: Vec<Prototype> = prototypes
            .iter()
            .map(|tris| {
                let (bvh, triangles) = triangle_bvh(tris);
                Prototype { bvh, triangles }
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
                let b = prototypes[proto as usize].bvh.total_aabb;
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
            (CwBvh::default(), Vec::new())
        } else {
            let mut build_time = std::time::Duration::ZERO;
            let tlas = obvhs::cwbvh::builder::build_cwbvh(
                &world_bounds,
                obvhs::BvhBuildParams::medium_build(),
                &mut build_time,
            );
            let records = tlas
                .primitive_indices
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
            triangles: ordered,
            prototypes,
            tlas,
            instances,
            spheres,
            motion: None,
            bounds_center,
            bounds_radius,
        }
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
        self.motion = Some(motion);
        self
    }

    /// Bytes of the acceleration structures and triangle records (BVH nodes, leaf index
    /// arrays, triangles, instances), from their lengths: what the geometry costs in
    /// memory, for comparing instancing with flattening.
    pub fn bytes(&self) -> usize {
        bvh_bytes(&self.bvh)
            + std::mem::size_of_val(self.triangles.as_slice())
            + self.prototypes.iter().map(Prototype::bytes).sum::<usize>()
            + bvh_bytes(&self.tlas)
            + std::mem::size_of_val(self.instances.as_slice())
            + self.motion.as_ref().map_or(0, MotionTriangles::bytes)
    }

    /// The nearest hit along `origin + t dir` with `0 < t < t_max`. `dir` need not be
    /// normalised, but the shift trick assumes it has unit length within a few percent.
    #[inline]
    pub fn intersect(&self, origin: Vec3, dir: Vec3, t_max: f32) -> Option<Hit> {
        self.intersect_where(origin, dir, t_max, 0.0, |_, _, _, _| true)
    }

    /// [`Geometry::intersect`] counting only the triangle hits `keep(record, key, b1, b2)`
    /// accepts (alpha-tested surfaces pass rays through where `keep` says so); `key`
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
        keep: impl Fn(&TriangleRecord, u64, f32, f32) -> bool,
    ) -> Option<Hit> {
        let mut best: Option<Hit> = None;
        let mut best_t = t_max;
        if !self.triangles.is_empty() {
            if let Some(h) = self.world_level().nearest(origin, dir, &mut best_t, &keep) {
                best = Some(h);
            }
        }
        if !self.instances.is_empty() {
            let ray = traversal_ray(origin, dir, best_t);
            let mut hit = RayHit::none();
            self.tlas.ray_traverse(ray, &mut hit, |_, id| {
                let (level, o, d) = self.instance_level(id, origin, dir);
                match level.nearest(o, d, &mut best_t, &keep) {
                    Some(h) => {
                        best = Some(h);
                        traversal_t(h.t)
                    }
                    None => f32::INFINITY,
                }
            });
        }
        if let Some(m) = &self.motion {
            if let Some(h) = m.nearest(origin, dir, &mut best_t, time, &keep) {
                best = Some(h);
            }
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
        keep: impl Fn(&TriangleRecord, u64, f32, f32) -> bool,
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
            if m.any(origin, dir, t_max, time, &keep) {
                return true;
            }
        }
        if self.instances.is_empty() {
            return false;
        }
        let ray = traversal_ray(origin, dir, t_max);
        !self.tlas.ray_traverse_miss(ray, |_, id| {
            let (level, o, d) = self.instance_level(id, origin, dir);
            if level.any(o, d, t_max, &keep) {
                0.0
            } else {
                f32::INFINITY
            }
        })
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
        }
    }

    /// Instance `id`'s prototype as a traversal level, with the ray in its object space
    /// (the direction unnormalised, so `t` is shared with the world ray).
    #[inline(always)]
    fn instance_level(
        &self,
        id: usize,
        origin: Vec3,
        dir: Vec3,
    ) -> (TriangleLevel<'_>, Vec3, Vec3) {
        let inst = &self.instances[id];
        let proto = &self.prototypes[inst.prototype as usize];
        let level = TriangleLevel {
            bvh: &proto.bvh,
            triangles: &proto.triangles,
            instance: id as u32,
        };
        let o = inst.object_from_world.transform_point3(origin);
        let d = inst.object_from_world.transform_vector3(dir);
        (level, o, d)
    }
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

/// One BVH of triangles (the world-space one, or a prototype's in object space) with the
/// instance its hits report.
struct TriangleLevel<'g> {
    bvh: &'g CwBvh,
    triangles: &'g [TriangleRecord],
    instance: u32,
}

impl TriangleLevel<'_> {
    /// The nearest kept hit of `origin + t dir` with `t < *best_t`; lowers `*best_t` to it.
    #[inline(always)]
    fn nearest(
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
    fn any(
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
fn traversal_ray(origin: Vec3, dir: Vec3, t_max: f32) -> Ray {
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
fn traversal_t(t: f32) -> f32 {
    (t + TRAVERSAL_SHIFT) * (1.0 + 1e-5)
}

/// A BVH over `triangles` and the triangles in its leaf order (so the hot loop indexes
/// them directly).
fn triangle_bvh(triangles: &[TriangleRecord]) -> (CwBvh, Vec<TriangleRecord>) {
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
    let mut build_time = std::time::Duration::ZERO;
    let bvh = obvhs::cwbvh::builder::build_cwbvh_from_tris(
        &tris,
        obvhs::BvhBuildParams::medium_build(),
        &mut build_time,
    );
    let ordered = bvh
        .primitive_indices
        .iter()
        .map(|&i| triangles[i as usize])
        .collect();
    (bvh, ordered)
}

/// Key for [`triangle_key`] of moving triangles: an instance number no instance has.
const MOTION_KEY_INSTANCE: u32 = NO_INSTANCE - 1;

/// Triangles that move within the shutter, for motion blur.
///
/// Each triangle is known at `K + 1` key times `τ_i = i / K` spread evenly over the
/// shutter (τ is the shutter fraction: 0 at the opening, 1 at the closing) and moves
/// linearly between neighbouring keys, vertex by vertex: the "motion steps" of Cycles and
/// the multi-segment linear motion of Embree (Woop et al. 2017, "STBVH: A Spatial-Temporal
/// BVH for Efficient Multi-Segment Motion Blur", section 3). Rigid rotation is followed by
/// its chords: a point at distance `r` from the axis turning by `θ` within one segment is
/// at most `r (1 - cos(θ/2)) ≈ r θ² / 8` off its arc.
///
/// Each of the `K` segments has its own BVH over the union of every triangle's bounds at
/// the segment's two keys. Linear interpolation keeps each vertex inside the segment of
/// its two key positions, so the union box bounds the triangle at every time of the
/// segment: the BVH prunes conservatively and no hit is lost. A ray at time τ traverses
/// segment `⌊τ K⌋` and intersects each leaf triangle at its interpolated position with the
/// same watertight test as static ones.
pub struct MotionTriangles {
    segments: u32,
    /// One BVH per segment.
    bvhs: Vec<CwBvh>,
    /// Per segment: the record index of each BVH leaf primitive.
    orders: Vec<Vec<u32>>,
    /// Mesh, triangle, material and light of each moving triangle; `p` holds its
    /// positions at τ = 0.
    pub records: Vec<TriangleRecord>,
    /// Positions at the key times: `keys[r * (K + 1) + i]` is record `r` at `τ_i`.
    keys: Vec<[Vec3; 3]>,
}

impl MotionTriangles {
    /// Moving triangles from `records` and their positions at `segments + 1` key times,
    /// `keys[r * (segments + 1) + i]` for record `r` at key `i`. Panics when the lengths
    /// disagree (a caller bug, not input).
    pub fn new(records: Vec<TriangleRecord>, keys: Vec<[Vec3; 3]>, segments: u32) -> Self {
        assert!(segments >= 1, "motion needs at least one segment");
        let n = segments as usize + 1;
        assert_eq!(
            keys.len(),
            records.len() * n,
            "one position per record and key"
        );
        let mut bvhs = Vec::with_capacity(segments as usize);
        let mut orders = Vec::with_capacity(segments as usize);
        for s in 0..segments as usize {
            if records.is_empty() {
                bvhs.push(CwBvh::default());
                orders.push(Vec::new());
                continue;
            }
            let bounds: Vec<obvhs::aabb::Aabb> = (0..records.len())
                .map(|r| {
                    let mut b = obvhs::aabb::Aabb::empty();
                    for p in keys[r * n + s].iter().chain(&keys[r * n + s + 1]) {
                        b.extend(Vec3A::from(*p));
                    }
                    b
                })
                .collect();
            let mut build_time = std::time::Duration::ZERO;
            let bvh = obvhs::cwbvh::builder::build_cwbvh(
                &bounds,
                obvhs::BvhBuildParams::medium_build(),
                &mut build_time,
            );
            orders.push(bvh.primitive_indices.clone());
            bvhs.push(bvh);
        }
        Self {
            segments,
            bvhs,
            orders,
            records,
            keys,
        }
    }

    /// Number of segments `K` between the `K + 1` key times.
    pub fn segments(&self) -> u32 {
        self.segments
    }

    /// The segment holding shutter fraction `time` and the fraction within it.
    #[inline(always)]
    pub fn segment_of(&self, time: f32) -> (usize, f32) {
        shutter_segment(time, self.segments)
    }

    /// Record `r`'s vertex positions at shutter fraction `time`: the same arithmetic for
    /// intersection and shading, so shading sees exactly the triangle that was hit.
    #[inline(always)]
    pub fn positions_at(&self, r: usize, time: f32) -> [Vec3; 3] {
        let (s, u) = self.segment_of(time);
        self.positions_in(r, s, u)
    }

    /// Record `r`'s vertex positions at fraction `u` of segment `s`.
    #[inline(always)]
    fn positions_in(&self, r: usize, s: usize, u: f32) -> [Vec3; 3] {
        let n = self.segments as usize + 1;
        lerp_corners(&self.keys[r * n + s], &self.keys[r * n + s + 1], u)
    }

    /// Whether `keep` accepts the hit at barycentrics `(b1, b2)` of record `r`.
    #[inline(always)]
    fn kept(
        &self,
        keep: &impl Fn(&TriangleRecord, u64, f32, f32) -> bool,
        r: usize,
        b1: f32,
        b2: f32,
    ) -> bool {
        keep(
            &self.records[r],
            triangle_key(MOTION_KEY_INSTANCE, r as u32),
            b1,
            b2,
        )
    }

    /// Bytes of the BVHs, leaf orders, records and key positions.
    pub fn bytes(&self) -> usize {
        self.bvhs.iter().map(bvh_bytes).sum::<usize>()
            + self.orders.iter().map(|o| o.len() * 4).sum::<usize>()
            + std::mem::size_of_val(self.records.as_slice())
            + std::mem::size_of_val(self.keys.as_slice())
    }

    /// The nearest kept hit at `time` with `t < *best_t`; lowers `*best_t` to it.
    #[inline]
    fn nearest(
        &self,
        origin: Vec3,
        dir: Vec3,
        best_t: &mut f32,
        time: f32,
        keep: &impl Fn(&TriangleRecord, u64, f32, f32) -> bool,
    ) -> Option<Hit> {
        let (s, u) = self.segment_of(time);
        let ray = traversal_ray(origin, dir, *best_t);
        let mut hit = RayHit::none();
        let mut best = None;
        let order = &self.orders[s];
        with_watertight_ray!(origin, dir, |wt| self.bvhs[s].ray_traverse(
            ray,
            &mut hit,
            |_, id| {
                let r = order[id] as usize;
                let p = self.positions_in(r, s, u);
                match wt.intersect(&p, *best_t) {
                    Some((t, _b0, b1, b2)) if self.kept(keep, r, b1, b2) => {
                        *best_t = t;
                        best = Some(Hit {
                            t,
                            primitive: Primitive::Moving {
                                index: r as u32,
                                b1,
                                b2,
                                time,
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

    /// Whether any kept hit at `time` has `t < t_max`.
    #[inline]
    fn any(
        &self,
        origin: Vec3,
        dir: Vec3,
        t_max: f32,
        time: f32,
        keep: &impl Fn(&TriangleRecord, u64, f32, f32) -> bool,
    ) -> bool {
        let (s, u) = self.segment_of(time);
        let ray = traversal_ray(origin, dir, t_max);
        let order = &self.orders[s];
        !with_watertight_ray!(origin, dir, |wt| self.bvhs[s].ray_traverse_miss(
            ray,
            |_, id| {
                let r = order[id] as usize;
                let p = self.positions_in(r, s, u);
                match wt.intersect(&p, t_max) {
                    Some((_, _, b1, b2)) if self.kept(keep, r, b1, b2) => 0.0,
                    _ => f32::INFINITY,
                }
            }
        ))
    }
}

/// Which of `segments` equal segments of the shutter holds shutter fraction `time`
/// (clamped to `[0, 1]`; 1 falls in the last), and the fraction within it.
#[inline(always)]
pub fn shutter_segment(time: f32, segments: u32) -> (usize, f32) {
    let x = time.clamp(0.0, 1.0) * segments as f32;
    let s = (x as u32).min(segments - 1);
    (s as usize, x - s as f32)
}

/// The corners `a + (b - a) u`, vertex by vertex.
#[inline(always)]
fn lerp_corners(a: &[Vec3; 3], b: &[Vec3; 3], u: f32) -> [Vec3; 3] {
    [
        a[0] + (b[0] - a[0]) * u,
        a[1] + (b[1] - a[1]) * u,
        a[2] + (b[2] - a[2]) * u,
    ]
}

/// Bytes of a BVH's nodes and leaf index array.
fn bvh_bytes(bvh: &CwBvh) -> usize {
    std::mem::size_of_val(bvh.nodes.as_slice())
        + std::mem::size_of_val(bvh.primitive_indices.as_slice())
}

/// The direction handed to obvhs. A third defect of obvhs 0.4.0: `safe_inverse(-0.0)` is
/// `-1/ε` while the CWBVH picks the ray octant by `d < 0` (false for `-0.0`), so a ray with
/// a negative-zero component (e.g. exactly along `-Z`) tests the wrong slab planes and
/// misses. Adding `+0.0` turns `-0.0` into `+0.0` and leaves every other value unchanged.
#[inline]
fn traversal_dir(dir: Vec3) -> Vec3A {
    Vec3A::from(dir + Vec3::ZERO)
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
mod tests {
    use super::*;

    fn quad_tris(scale: f32) -> Vec<TriangleRecord> {
        // Two triangles sharing the diagonal of a square in the z = 0 plane.
        let s = scale;
        let a = Vec3::new(-s, -s, 0.0);
        let b = Vec3::new(s, -s, 0.0);
        let c = Vec3::new(s, s, 0.0);
        let d = Vec3::new(-s, s, 0.0);
        let rec = |p, i| TriangleRecord {
            p,
            mesh: 0,
            index: i,
            material: 0,
            light: NO_LIGHT,
        };
        vec![rec([a, b, c], 0), rec([a, c, d], 1)]
    }

    #[test]
    fn shared_edges_are_watertight() {
        // Rays aimed exactly at the shared diagonal (and at the shared vertices) of a fan of
        // triangles must hit; a Möller–Trumbore test loses a fraction of these.
        let mut rng = 0x1234_5678_9abc_def0u64;
        let mut next = || {
            rng = rng
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((rng >> 40) as f32) / (1u64 << 24) as f32
        };
        // A fan of 64 triangles around the origin, slightly irregular.
        let n = 64;
        let mut tris = Vec::new();
        let pts: Vec<Vec3> = (0..n)
            .map(|i| {
                let a = i as f32 / n as f32 * std::f32::consts::TAU;
                Vec3::new(a.cos(), a.sin(), 0.1 * (3.0 * a).sin())
            })
            .collect();
        for i in 0..n {
            tris.push(TriangleRecord {
                p: [Vec3::new(0.0, 0.0, 0.05), pts[i], pts[(i + 1) % n]],
                mesh: 0,
                index: i as u32,
                material: 0,
                light: NO_LIGHT,
            });
        }
        let geo = Geometry::build(tris.clone(), vec![]);
        let mut misses = 0;
        let total = 20000;
        for k in 0..total {
            let e = k % n;
            let t = next();
            // A point exactly on edge (centre, pts[e]) computed in float.
            let target = Vec3::new(0.0, 0.0, 0.05) * (1.0 - t) + pts[e] * t;
            let origin = Vec3::new(next() - 0.5, next() - 0.5, 3.0 + next());
            let dir = (target - origin).normalize();
            if geo.intersect(origin, dir, f32::INFINITY).is_none() {
                misses += 1;
            }
        }
        assert_eq!(
            misses, 0,
            "{misses} of {total} rays slipped through shared edges"
        );
    }

    #[test]
    fn a_moving_triangle_is_hit_where_it_stands_at_the_ray_time() {
        // A unit triangle in z = 0 sliding from x = -10 to x = +10 over the shutter,
        // given at 3 keys (2 segments): at time τ its vertices are 20 τ - 10 along x.
        let tri = |dx: f32| {
            [
                Vec3::new(dx - 0.5, -0.5, 0.0),
                Vec3::new(dx + 0.5, -0.5, 0.0),
                Vec3::new(dx, 0.5, 0.0),
            ]
        };
        let record = TriangleRecord {
            p: tri(-10.0),
            mesh: 0,
            index: 0,
            material: 0,
            light: NO_LIGHT,
        };
        let motion = MotionTriangles::new(vec![record], vec![tri(-10.0), tri(0.0), tri(10.0)], 2);
        let geo = Geometry::build(Vec::new(), Vec::new()).with_motion(motion);
        for time in [0.0f32, 0.1, 0.25, 0.5, 0.62, 0.9, 1.0] {
            let x = 20.0 * time - 10.0;
            let origin = Vec3::new(x, -0.2, 5.0);
            let hit = geo
                .intersect_where(origin, -Vec3::Z, f32::INFINITY, time, |_, _, _, _| true)
                .unwrap_or_else(|| panic!("missed the triangle at time {time}"));
            assert!((hit.t - 5.0).abs() < 1e-5, "t {} at time {time}", hit.t);
            assert!(
                matches!(hit.primitive, Primitive::Moving { index: 0, time: t, .. } if t == time)
            );
            assert!(geo.occluded_where(origin, -Vec3::Z, 10.0, time, |_, _, _, _| true));
            // One unit beside it at that time: nothing; and where it was at other times.
            let beside = Vec3::new(x + 1.2, -0.2, 5.0);
            assert!(geo
                .intersect_where(beside, -Vec3::Z, f32::INFINITY, time, |_, _, _, _| true)
                .is_none());
            let later = (time + 0.3).min(1.0);
            if later - time > 0.1 {
                assert!(!geo.occluded_where(origin, -Vec3::Z, 10.0, later, |_, _, _, _| true));
            }
        }
        // The bounding sphere covers the whole sweep.
        assert!(geo.bounds_radius >= 10.0);
    }

    #[test]
    fn near_hits_below_obvhs_clamp_are_found() {
        for scale in [1e-4f32, 1e-2, 1.0] {
            let geo = Geometry::build(quad_tris(scale), vec![]);
            for dist in [1e-7f32, 1e-6, 1e-5, 5e-5, 9e-5] {
                let d = dist * scale.max(1e-3);
                let origin = Vec3::new(0.1 * scale, 0.2 * scale, d);
                let hit = geo.intersect(origin, -Vec3::Z, f32::INFINITY);
                let hit = hit.unwrap_or_else(|| panic!("missed at distance {d} scale {scale}"));
                assert!((hit.t - d).abs() <= d * 1e-3, "t {} vs {d}", hit.t);
                assert!(geo.occluded(origin, -Vec3::Z, 1.0));
                // t_max just before the surface: no hit.
                assert!(geo.intersect(origin, -Vec3::Z, d * 0.5).is_none());
                assert!(!geo.occluded(origin, -Vec3::Z, d * 0.5));
            }
        }
    }

    #[test]
    fn sphere_intersection_is_accurate_for_tiny_and_distant_spheres() {
        let t = intersect_sphere(
            Vec3::new(0.0, 0.0, -1e4),
            0.01,
            Vec3::ZERO,
            -Vec3::Z,
            f32::INFINITY,
        )
        .unwrap();
        assert!((t - (1e4 - 0.01)).abs() < 2e-3, "{t}");
        let t = intersect_sphere(Vec3::ZERO, 1.0, Vec3::ZERO, Vec3::X, f32::INFINITY).unwrap();
        assert!((t - 1.0).abs() < 1e-6);
        assert!(intersect_sphere(
            Vec3::ZERO,
            1.0,
            Vec3::new(0.0, 2.0, 0.0),
            Vec3::X,
            f32::INFINITY
        )
        .is_none());
    }
}
