//! A packet walk: the nearest hits of [`PACKET`] coherent rays (the camera rays of a
//! block of pixels) through one level's wide BVH with one shared stack and a per-ray
//! active mask, as a measurement of whether packets pay (docs/benchmarks.md, "Packets of
//! camera rays"). As in packet tracing since Wald, Slusallek, Benthin & Wagner 2001
//! ("Interactive rendering with coherent ray tracing"), Embree's hybrid traversal
//! (`kernels/bvh/bvh_intersector_hybrid.cpp`) and tinybvh's `BVH::Intersect256Rays`,
//! the packet walks a node once and tests each ray only while it is still active; here each ray's box test is
//! the single-ray kernel's ([`BoxTest`], the same IEEE operations in the same order)
//! with the ray's own pruning limit, and each ray's triangle tests are the watertight
//! test of the single-ray walk.
//!
//! **Every ray's hit is its single-ray hit, bit for bit.** A level's nearest hit is the
//! lexicographic minimum of `(t, key)` over every hit the watertight test accepts,
//! whatever the visit order, as long as pruning is conservative (`wide` module docs): the
//! packet visits nodes in an order of its own (nearest first by the least entry distance
//! of the rays entering a child) and prunes each ray by its own best `t` exactly as the
//! single-ray walk does ([`box_limit`]), so it offers each ray the same candidate hits
//! that can be nearest and [`Nearest`] decides them the same way.

use super::watertight::WatertightRay;
use super::wide::{box_limit, BoxRay, BoxTest, Nearest, WideBvh, WIDTH};
use super::{triangle_key, Hit, HitTriangle, Primitive, Triangles};
use std::cell::Cell;

/// Rays per packet: one bit each in a `u32` mask, and a 4x2 or 8x1 block of pixels.
pub const PACKET: usize = 8;

/// A stack entry: a node, the rays that entered it (bit `i` for ray `i`) and each one's
/// entry distance.
#[derive(Clone, Copy)]
struct Entry {
    node: u32,
    rays: u32,
    entry: [f32; PACKET],
}

thread_local! {
    /// The packet walk's stack, reused from packet to packet (grown once per thread, so
    /// the walk allocates nothing once warm).
    static PACKET_STACK: Cell<Vec<Entry>> = const { Cell::new(Vec::new()) };
}

/// Offers every kept hit of ray `i` (for each bit `i` of `active`) in `bvh`'s leaves,
/// the stored `triangles` of one level of world-space triangles, to `best[i]`: `rays[i]`
/// is the ray as the box test sees it, `wt[i]` as the watertight test does (every ray of
/// the packet with the same dominant axis `KZ`), `keep` the filter of
/// `Geometry::intersect_where`. Each ray must be finite ([`BoxRay`]'s check is the
/// caller's).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
pub(super) fn nearest<K: BoxTest, const KZ: usize, F>(
    bvh: &WideBvh,
    triangles: &Triangles,
    instance: u32,
    rays: &[BoxRay; PACKET],
    wt: &[WatertightRay<KZ>; PACKET],
    keep: &F,
    best: &mut [Nearest; PACKET],
    active: u32,
) where
    F: Fn(HitTriangle<'_>, u64, f32, f32) -> bool,
{
    if bvh.nodes.is_empty() || active == 0 {
        return;
    }
    let mut stack = PACKET_STACK.take();
    stack.clear();
    stack.push(Entry {
        node: 0,
        rays: active,
        entry: [0.0; PACKET],
    });
    while let Some(e) = stack.pop() {
        // Rays whose best hit is now nearer than their entry into this node leave it
        // (the single-ray walk's test at its pop).
        let mut m = e.rays;
        let mut bits = e.rays;
        while bits != 0 {
            let i = bits.trailing_zeros() as usize;
            bits &= bits - 1;
            if e.entry[i] > box_limit(best[i].t) {
                m &= !(1 << i);
            }
        }
        if m == 0 {
            continue;
        }
        let node = &bvh.nodes[e.node as usize];
        // Each active ray's box test of every child; `enter[c]` the rays entering child
        // `c`, `key[c]` the least entry distance among them (the visit order).
        let mut dist = [[0.0f32; WIDTH]; PACKET];
        let mut enter = [0u32; WIDTH];
        let mut key = [f32::INFINITY; WIDTH];
        let mut bits = m;
        while bits != 0 {
            let i = bits.trailing_zeros() as usize;
            bits &= bits - 1;
            let (d, mut mask) = K::test(node, &rays[i], box_limit(best[i].t));
            dist[i] = d;
            while mask != 0 {
                let c = mask.trailing_zeros() as usize;
                mask &= mask - 1;
                enter[c] |= 1 << i;
                key[c] = if d[c] < key[c] { d[c] } else { key[c] };
            }
        }
        // Children entered by any ray, nearest first (insertion sort: few are entered).
        let mut order = [0u8; WIDTH];
        let mut n = 0;
        for c in 0..WIDTH {
            if enter[c] == 0 {
                continue;
            }
            let mut j = n;
            while j > 0 && key[order[j - 1] as usize] > key[c] {
                order[j] = order[j - 1];
                j -= 1;
            }
            order[j] = c as u8;
            n += 1;
        }
        // Leaves now, nearest first, each triangle against every ray entering the leaf
        // (its corners loaded once).
        for &c in &order[..n] {
            let c = c as usize;
            let count = node.count[c];
            if count == 0 {
                continue;
            }
            let first = node.child[c] as usize;
            let leaf = triangles.positions_in(first..first + count as usize);
            for (s, p) in (first..).zip(leaf) {
                let mut bits = enter[c];
                while bits != 0 {
                    let i = bits.trailing_zeros() as usize;
                    bits &= bits - 1;
                    let b = &mut best[i];
                    let Some((t, _, b1, b2)) = wt[i].intersect(p, b.bound()) else {
                        continue;
                    };
                    let id = triangle_key(instance, triangles.id(s));
                    if !b.beats(t, id) || !keep(HitTriangle::Stored(triangles, s), id, b1, b2) {
                        continue;
                    }
                    b.set(
                        Hit {
                            t,
                            primitive: Primitive::Triangle {
                                index: s as u32,
                                instance,
                                b1,
                                b2,
                            },
                        },
                        id,
                    );
                }
            }
        }
        // Interior children pushed farthest first, so the nearest is walked next.
        for &c in order[..n].iter().rev() {
            let c = c as usize;
            if node.count[c] != 0 {
                continue;
            }
            stack.push(Entry {
                node: node.child[c],
                rays: enter[c],
                entry: std::array::from_fn(|i| dist[i][c]),
            });
        }
    }
    PACKET_STACK.set(stack);
}
