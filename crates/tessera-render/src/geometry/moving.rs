//! Triangles that move within the shutter (motion blur): one BVH per shutter segment.

use super::build::{self, BvhBuildStats};
use super::kernels::{self, Isa};
use super::wide::{BoxTest, Leaves, Nearest, WideBvh};
use super::{triangle_key, Hit, HitTriangle, Primitive, TriangleRecord, NO_INSTANCE};
use crate::math::gamma;
use glam::{Vec3, Vec3A};
use obvhs::aabb::Aabb;

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
/// segment: the BVH prunes conservatively and no hit is lost (each box is widened by the
/// rounding bound of the interpolation, `lerp_error`, so that holds for the positions
/// as computed too). A ray at time τ walks segment `⌊τ K⌋`'s wide BVH with the kernel's
/// box test, like static triangles (see `wide`), and intersects each leaf triangle at
/// its interpolated position with the same watertight test. The nearest hit is the
/// lexicographic minimum of `(t, record index)`, whatever the visit order or kernel.
pub struct MotionTriangles {
    segments: u32,
    /// One wide BVH per segment; its leaves name record indices.
    bvhs: Vec<WideBvh>,
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
        let bvhs = build::on_build_stack(|| {
            (0..segments as usize)
                .map(|s| {
                    if records.is_empty() {
                        return WideBvh::default();
                    }
                    let boxes: Vec<Aabb> = (0..records.len())
                        .map(|r| {
                            let mut b = Aabb::empty();
                            for p in keys[r * n + s].iter().chain(&keys[r * n + s + 1]) {
                                b.extend(Vec3A::from(*p));
                            }
                            b
                        })
                        .collect();
                    // The tree is built over the exact boxes (so ties among them are
                    // recognised as such, see `build`), then widened.
                    let mut bvh2 = build::boxes_bvh2(&boxes, &mut build_stats);
                    build::widen_boxes(&mut bvh2, |_, b| {
                        let pad = Vec3A::from(lerp_error(b.min.into(), b.max.into()));
                        Aabb::new(b.min - pad, b.max + pad)
                    });
                    let identity: Vec<u32> = (0..records.len() as u32).collect();
                    WideBvh::collapse(&bvh2, &identity)
                })
                .collect()
        });
        Self {
            segments,
            bvhs,
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

    /// Bytes of the BVHs, records and key positions.
    pub fn bytes(&self) -> usize {
        self.bvhs.iter().map(WideBvh::bytes).sum::<usize>()
            + std::mem::size_of_val(self.records.as_slice())
            + std::mem::size_of_val(self.keys.as_slice())
    }

    /// Offers every kept hit at `time` to `best` (see [`Nearest`]), with kernel `isa`.
    #[inline]
    pub(super) fn nearest(
        &self,
        isa: Isa,
        origin: Vec3,
        dir: Vec3,
        best: &mut Nearest,
        time: f32,
        keep: &impl Fn(HitTriangle<'_>, u64, f32, f32) -> bool,
    ) {
        let (s, u) = self.segment_of(time);
        with_watertight_ray!(origin, dir, |wt| {
            let leaves = MovingLeaves {
                motion: self,
                segment: s,
                u,
                time,
                intersect: &|p: &[Vec3; 3], t_max: f32| wt.intersect(p, t_max),
                keep,
            };
            kernels::nearest(isa, &self.bvhs[s], origin, dir, &leaves, best)
        })
    }

    /// Whether any kept hit at `time` has `t < t_max`, with kernel `isa`.
    #[inline]
    pub(super) fn any(
        &self,
        isa: Isa,
        origin: Vec3,
        dir: Vec3,
        t_max: f32,
        time: f32,
        keep: &impl Fn(HitTriangle<'_>, u64, f32, f32) -> bool,
    ) -> bool {
        let (s, u) = self.segment_of(time);
        with_watertight_ray!(origin, dir, |wt| {
            let leaves = MovingLeaves {
                motion: self,
                segment: s,
                u,
                time,
                intersect: &|p: &[Vec3; 3], t_max: f32| wt.intersect(p, t_max),
                keep,
            };
            kernels::any(isa, &self.bvhs[s], origin, dir, &leaves, t_max)
        })
    }
}

/// The leaves of one segment's BVH for a ray at `time` (fraction `u` of the segment):
/// each entry is a record, tested where it stands then.
struct MovingLeaves<'g, I, F> {
    motion: &'g MotionTriangles,
    segment: usize,
    u: f32,
    time: f32,
    intersect: &'g I,
    keep: &'g F,
}

impl<I, F> Leaves for MovingLeaves<'_, I, F>
where
    I: Fn(&[Vec3; 3], f32) -> Option<(f32, f32, f32, f32)>,
    F: Fn(HitTriangle<'_>, u64, f32, f32) -> bool,
{
    #[inline(always)]
    fn nearest<K: BoxTest>(&self, first: u32, count: u32, best: &mut Nearest) {
        let first = first as usize;
        for &r in &self.motion.bvhs[self.segment].prims[first..first + count as usize] {
            let p = self.motion.positions_in(r as usize, self.segment, self.u);
            let Some((t, _, b1, b2)) = (self.intersect)(&p, best.bound()) else {
                continue;
            };
            let key = triangle_key(MOTION_KEY_INSTANCE, r);
            if !best.beats(t, key)
                || !(self.keep)(
                    HitTriangle::Record(&self.motion.records[r as usize]),
                    key,
                    b1,
                    b2,
                )
            {
                continue;
            }
            best.set(
                Hit {
                    t,
                    primitive: Primitive::Moving {
                        index: r,
                        b1,
                        b2,
                        time: self.time,
                    },
                },
                key,
            );
        }
    }

    #[inline(always)]
    fn any<K: BoxTest>(&self, first: u32, count: u32, t_max: f32) -> bool {
        let first = first as usize;
        // A loop rather than `Iterator::any`, which LLVM may leave uninlined, outside
        // the kernel's `#[target_feature]` function.
        for &r in &self.motion.bvhs[self.segment].prims[first..first + count as usize] {
            let p = self.motion.positions_in(r as usize, self.segment, self.u);
            if let Some((_, _, b1, b2)) = (self.intersect)(&p, t_max) {
                let key = triangle_key(MOTION_KEY_INSTANCE, r);
                if (self.keep)(
                    HitTriangle::Record(&self.motion.records[r as usize]),
                    key,
                    b1,
                    b2,
                ) {
                    return true;
                }
            }
        }
        false
    }
}

/// A bound on the rounding error of [`lerp_corners`] for a coordinate between `lo` and
/// `hi`, per axis: `a + (b - a) u` is three roundings, so it lies within
/// `γ(3) (|a| + |b|)` of the exact value (pbrt 3rd ed. §3.9.1-3.9.2), and `|a|, |b| <=
/// max(|lo|, |hi|)`.
#[inline]
fn lerp_error(lo: Vec3, hi: Vec3) -> Vec3 {
    lo.abs().max(hi.abs()) * (2.0 * gamma(3))
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
