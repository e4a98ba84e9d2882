//! Triangles that move within the shutter (motion blur): one BVH per shutter segment.

use super::build::{self, BvhBuildStats};
use super::traversal::{bvh_bytes, traversal_ray, traversal_t};
use super::{triangle_key, Hit, Primitive, TriangleRecord, NO_INSTANCE};
use glam::{Vec3, Vec3A};
use obvhs::cwbvh::CwBvh;
use obvhs::ray::RayHit;

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
    pub(super) keys: Vec<[Vec3; 3]>,
    /// What building the segments' BVHs cost.
    pub(super) build_stats: BvhBuildStats,
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
        let mut build_stats = BvhBuildStats::default();
        let (bvhs, orders) = build::on_build_stack(|| {
            (0..segments as usize)
                .map(|s| {
                    if records.is_empty() {
                        return (CwBvh::default(), Vec::new());
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
                    let bvh = build::boxes_cwbvh(&bounds, &mut build_stats);
                    let order = bvh.primitive_indices.clone();
                    (bvh, order)
                })
                .unzip()
        });
        Self {
            segments,
            bvhs,
            orders,
            records,
            keys,
            build_stats,
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
    pub(super) fn nearest(
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
    pub(super) fn any(
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
