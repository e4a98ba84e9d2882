//! Our own wide BVH over triangles: obvhs' binary tree collapsed into nodes of
//! [`WIDTH`] children whose boxes are stored as structure-of-arrays, so one box test
//! covers every child with the ISA's widest vectors (the kernels are in `kernels`).
//!
//! **Collapse.** Greedy, by the surface area heuristic (a simple variant of the collapse
//! in Ylitie, Karras & Laine 2017, §3, without their dynamic programme): a wide node
//! starts with its binary node's two children and repeatedly opens an interior child into
//! its two children until it has [`WIDTH`] children or none is interior. A child whose
//! subtree holds at most [`LEAF_MAX`] triangles (or that is a binary leaf) becomes a
//! leaf; any other child becomes a wide node in turn. Children that would become wide
//! nodes are opened first: each one left in place costs a node of its own (256 bytes and
//! one more box test for every ray that enters it), while a slot costs the same used or
//! empty, so only when none is left are leaf-sized children split to fill the free slots
//! (smaller leaves: fewer triangle tests per entered leaf, in the SAH's terms, Wald,
//! Benthin & Boulos 2008, §3). Within each class the child of largest surface area (the
//! one a ray is likeliest to enter) goes first. Nodes are 64-byte aligned (one
//! [`WideNode`] of 8 children is exactly four cache lines: the six bound arrays, then the
//! child references).
//!
//! **Leaves** name the triangles' positions in the level's triangle array (obvhs' CWBVH
//! leaf order, which [`super::triangle_key`] hashes, so keys and images do not change);
//! the triangles themselves are tested by `watertight`'s scalar test, unchanged.
//!
//! **The hit is independent of the visit order.** A triangle hit replaces the best one
//! when its `t` is smaller, or equal with a smaller triangle index; boxes are pruned only
//! beyond the best `t` plus a relative margin ([`box_limit`]) far wider than the rounding
//! of the box and triangle tests, and the box test is conservative (Ize 2013, via pbrt
//! 3rd ed. §3.9.2: the far distance is scaled by `1 + 2 γ(3)`). So the nearest hit is the
//! lexicographic minimum of `(t, index)` over every hit the watertight test accepts,
//! whatever order the children are visited in and whatever kernel tests the boxes: every
//! kernel gives the same hit, bit for bit (ARCHITECTURE.md §2).

use super::{triangle_key, Hit, Primitive, TriangleRecord};
use crate::math::gamma;
use obvhs::bvh2::Bvh2;

/// Children per node.
pub(super) const WIDTH: usize = 8;

/// The most triangles a leaf made from a binary subtree holds. 4 rather than 3: on a
/// 200,000-triangle terrain the same instructions per ray (-0.3%) and 11% less geometry
/// (docs/benchmarks.md, "The wide BVH: an 8-lane AVX2 box test ...").
pub(super) const LEAF_MAX: u32 = 4;

/// Entries of the traversal stack kept on the machine stack; deeper trees (only the
/// pathological inputs of `build`'s known limit) use a heap stack.
const STACK_INLINE: usize = 96;

/// One node: the bounds of its children as structure-of-arrays (`lo[axis][child]`), and
/// what each child is. An unused slot has an empty box (`lo = +inf`, `hi = -inf`), which
/// no ray enters.
#[repr(C, align(64))]
#[derive(Clone, Copy, Debug)]
pub(super) struct WideNode {
    /// Lower bounds, per axis, per child.
    pub(super) lo: [[f32; WIDTH]; 3],
    /// Upper bounds, per axis, per child.
    pub(super) hi: [[f32; WIDTH]; 3],
    /// An interior child's node index, or a leaf's first entry in [`WideBvh::prims`].
    pub(super) child: [u32; WIDTH],
    /// 0 for an interior child (or an unused slot), else the leaf's triangle count.
    pub(super) count: [u32; WIDTH],
}

impl WideNode {
    /// A node with every slot unused.
    pub(super) const EMPTY: WideNode = WideNode {
        lo: [[f32::INFINITY; WIDTH]; 3],
        hi: [[f32::NEG_INFINITY; WIDTH]; 3],
        child: [0; WIDTH],
        count: [0; WIDTH],
    };
}

/// A wide BVH over one level's triangles (root at node 0; no nodes for no triangles).
#[derive(Default)]
pub(super) struct WideBvh {
    pub(super) nodes: Vec<WideNode>,
    /// Leaf contents: positions in the level's triangle array.
    pub(super) prims: Vec<u32>,
    /// The most traversal stack entries any ray can need.
    stack_need: usize,
}

/// The ray as the box test sees it: origin, reciprocal direction, and per axis whether
/// the direction is negative (its sign bit, so `-0.0` counts as negative and pairs with
/// its reciprocal `-inf`).
#[derive(Clone, Copy, Debug)]
pub(super) struct BoxRay {
    pub(super) origin: [f32; 3],
    pub(super) inv: [f32; 3],
    pub(super) neg: [bool; 3],
}

impl BoxRay {
    #[inline(always)]
    pub(super) fn new(origin: glam::Vec3, dir: glam::Vec3) -> Self {
        let d = dir.to_array();
        Self {
            origin: origin.to_array(),
            inv: d.map(|c| 1.0 / c),
            neg: d.map(f32::is_sign_negative),
        }
    }
}

impl BoxRay {
    /// Whether the origin is finite and the direction has no NaN (a zero component's
    /// infinite reciprocal is fine).
    #[inline(always)]
    fn is_finite(&self) -> bool {
        self.origin.iter().all(|c| c.is_finite()) && self.inv.iter().all(|c| !c.is_nan())
    }
}

/// Scale of the far distance that makes the box test conservative (pbrt 3rd ed. §3.9.2).
#[inline(always)]
pub(super) fn far_scale() -> f32 {
    1.0 + 2.0 * gamma(3)
}

/// How far along the ray boxes are still entered when the best hit so far is at `t`:
/// a relative margin of `1e-5`, far beyond the few ulps by which the triangle test's `t`
/// and the box test's entry distance can disagree, so ties are never pruned.
#[inline(always)]
pub(super) fn box_limit(t: f32) -> f32 {
    t * (1.0 + 1e-5)
}

/// How a box test is computed: the kernels (`kernels`) implement it.
pub(super) trait BoxTest {
    /// Entry distances of every child of `node` and the bit mask of those the ray enters
    /// at or before `limit`.
    fn test(node: &WideNode, ray: &BoxRay, limit: f32) -> ([f32; WIDTH], u32);
}

/// The near and far planes of `node` on `axis` for a ray whose direction on it is
/// negative when `neg`.
#[inline(always)]
pub(super) fn planes(node: &WideNode, axis: usize, neg: bool) -> (&[f32; WIDTH], &[f32; WIDTH]) {
    if neg {
        (&node.hi[axis], &node.lo[axis])
    } else {
        (&node.lo[axis], &node.hi[axis])
    }
}

impl WideBvh {
    /// The wide BVH of `bvh2` (non-empty), whose primitive `i` is at `position[i]` in the
    /// level's triangle array.
    #[allow(clippy::needless_range_loop)] // axes index the node's arrays and the box's
    pub(super) fn collapse(bvh2: &Bvh2, position: &[u32]) -> Self {
        let bn = &bvh2.nodes;
        // Triangles under every binary node, children before parents by an explicit
        // post-order walk (obvhs does not promise children after parents).
        let mut under = vec![0u32; bn.len()];
        let mut stack: Vec<(usize, bool)> = vec![(0, false)];
        while let Some((i, done)) = stack.pop() {
            let n = &bn[i];
            if n.is_leaf() {
                under[i] = n.prim_count;
            } else if done {
                let c = n.first_index as usize;
                under[i] = under[c] + under[c + 1];
            } else {
                stack.push((i, true));
                stack.push((n.first_index as usize, false));
                stack.push((n.first_index as usize + 1, false));
            }
        }
        // Every wide node but the root stands for a distinct binary interior node with more
        // than a leaf's triangles under it, so their count bounds the nodes. Reserving it
        // up front keeps the array from doubling (two copies at once at the build's memory
        // peak); pages never written are never resident, and the shrink at the end returns
        // the rest.
        let bound = 1
            + (0..bn.len())
                .filter(|&i| !bn[i].is_leaf() && under[i] > LEAF_MAX)
                .count();
        let mut nodes = Vec::with_capacity(bound);
        nodes.push(WideNode::EMPTY);
        let mut out = WideBvh {
            nodes,
            prims: Vec::with_capacity(position.len()),
            stack_need: 0,
        };
        // (binary node, wide node it fills)
        let mut work: Vec<(usize, usize)> = vec![(0, 0)];
        let mut children: Vec<usize> = Vec::with_capacity(WIDTH);
        let mut leaf_walk: Vec<usize> = Vec::new();
        while let Some((b, w)) = work.pop() {
            children.clear();
            if bn[b].is_leaf() {
                children.push(b);
            } else {
                let c = bn[b].first_index as usize;
                children.extend([c, c + 1]);
            }
            while children.len() < WIDTH {
                // The child to open: one that would become a wide node of its own if
                // any, else one that would become a leaf; within each class the one of
                // largest surface area (the first on ties). See the module docs.
                let mut open: Option<(usize, bool, f32)> = None;
                for (k, &c) in children.iter().enumerate() {
                    if !bn[c].is_leaf() {
                        let big = under[c] > LEAF_MAX;
                        let area = bn[c].aabb().half_area();
                        if open.is_none_or(|(_, b, a)| (big, area) > (b, a)) {
                            open = Some((k, big, area));
                        }
                    }
                }
                let Some((k, _, _)) = open else { break };
                let c = bn[children[k]].first_index as usize;
                children[k] = c;
                children.insert(k + 1, c + 1);
            }
            for (slot, &c) in children.iter().enumerate() {
                let bb = bn[c].aabb();
                for axis in 0..3 {
                    out.nodes[w].lo[axis][slot] = bb.min[axis];
                    out.nodes[w].hi[axis][slot] = bb.max[axis];
                }
                if bn[c].is_leaf() || under[c] <= LEAF_MAX {
                    let first = out.prims.len() as u32;
                    leaf_walk.clear();
                    leaf_walk.push(c);
                    while let Some(i) = leaf_walk.pop() {
                        let n = &bn[i];
                        if n.is_leaf() {
                            let s = n.first_index as usize;
                            for &p in &bvh2.primitive_indices[s..s + n.prim_count as usize] {
                                out.prims.push(position[p as usize]);
                            }
                        } else {
                            leaf_walk.push(n.first_index as usize + 1);
                            leaf_walk.push(n.first_index as usize);
                        }
                    }
                    out.nodes[w].child[slot] = first;
                    out.nodes[w].count[slot] = out.prims.len() as u32 - first;
                } else {
                    let node = out.nodes.len();
                    out.nodes.push(WideNode::EMPTY);
                    out.nodes[w].child[slot] = node as u32;
                    work.push((c, node));
                }
            }
        }
        // Stack entries a ray can need below each node: it pushes its interior children,
        // then works below one of them with the others waiting. Children come after
        // their parents, so one backward pass sees every child first.
        let mut need = vec![0usize; out.nodes.len()];
        for i in (0..out.nodes.len()).rev() {
            let node = &out.nodes[i];
            let inner: Vec<usize> = (0..WIDTH)
                .filter(|&k| node.count[k] == 0 && node.lo[0][k] <= node.hi[0][k])
                .map(|k| node.child[k] as usize)
                .collect();
            let below = inner.iter().map(|&c| need[c]).max().unwrap_or(0);
            need[i] = inner.len().max(inner.len().saturating_sub(1) + below);
        }
        out.stack_need = need[0] + 1;
        out.nodes.shrink_to_fit();
        out
    }

    /// Bytes of the nodes and leaf contents.
    pub(super) fn bytes(&self) -> usize {
        std::mem::size_of_val(self.nodes.as_slice()) + std::mem::size_of_val(self.prims.as_slice())
    }
}

/// A traversal stack large enough for `bvh`: `inline` for every ordinary tree, `heap`
/// (grown here) for the pathological deep ones. A slice rather than a closure, so the
/// walk is inlined into each kernel's `#[target_feature]` function.
#[inline(always)]
fn stack_for<'s>(
    bvh: &WideBvh,
    inline: &'s mut [(u32, f32); STACK_INLINE],
    heap: &'s mut Vec<(u32, f32)>,
) -> &'s mut [(u32, f32)] {
    if bvh.stack_need <= STACK_INLINE {
        inline
    } else {
        heap.resize(bvh.stack_need, (0, 0.0));
        heap
    }
}

/// The entries of the children in `mask` sorted nearest first by `dist` (insertion
/// sort: a ray enters few children), and how many there are.
#[inline(always)]
fn nearest_first(mut mask: u32, dist: &[f32; WIDTH]) -> ([u8; WIDTH], usize) {
    let mut order = [0u8; WIDTH];
    let mut n = 0;
    while mask != 0 {
        let c = mask.trailing_zeros() as u8;
        mask &= mask - 1;
        let mut j = n;
        while j > 0 && dist[order[j - 1] as usize] > dist[c as usize] {
            order[j] = order[j - 1];
            j -= 1;
        }
        order[j] = c;
        n += 1;
    }
    (order, n)
}

/// The triangles of one level with the test each needs.
pub(super) struct Level<'g> {
    pub(super) bvh: &'g WideBvh,
    pub(super) triangles: &'g [TriangleRecord],
    pub(super) instance: u32,
}

/// The nearest kept hit of the ray with `t < *best_t` (the lexicographic minimum of
/// `(t, index)`, see the module docs); lowers `*best_t` to it. `intersect(p, t_max)` is
/// the watertight test of the ray.
#[inline(always)]
pub(super) fn nearest<K: BoxTest>(
    level: &Level<'_>,
    ray: &BoxRay,
    best_t: &mut f32,
    intersect: &impl Fn(&[glam::Vec3; 3], f32) -> Option<(f32, f32, f32, f32)>,
    keep: &impl Fn(&TriangleRecord, u64, f32, f32) -> bool,
) -> Option<Hit> {
    let bvh = level.bvh;
    // A ray with a NaN or infinite coordinate hits nothing (and would enter unused slots).
    if bvh.nodes.is_empty() || !ray.is_finite() {
        return None;
    }
    let t_max = *best_t;
    let mut best: Option<Hit> = None;
    let mut best_index = u32::MAX;
    let (mut inline, mut heap) = ([(0u32, 0f32); STACK_INLINE], Vec::new());
    let stack = stack_for(bvh, &mut inline, &mut heap);
    stack[0] = (0, 0.0);
    let mut sp = 1;
    while sp > 0 {
        sp -= 1;
        let (ni, entry) = stack[sp];
        if entry > box_limit(*best_t) {
            continue;
        }
        let node = &bvh.nodes[ni as usize];
        let (dist, mask) = K::test(node, ray, box_limit(*best_t));
        let (order, n) = nearest_first(mask, &dist);
        for &c in &order[..n] {
            let c = c as usize;
            let count = node.count[c];
            if count == 0 {
                continue;
            }
            let first = node.child[c] as usize;
            for &id in &bvh.prims[first..first + count as usize] {
                let tri = &level.triangles[id as usize];
                // The test's own bound admits ties with the best hit (see
                // `box_limit`); the comparison below decides them exactly.
                let bound = if best.is_some() {
                    box_limit(*best_t).min(t_max)
                } else {
                    t_max
                };
                let Some((t, _, b1, b2)) = intersect(&tri.p, bound) else {
                    continue;
                };
                if best.is_some() && !(t < *best_t || (t == *best_t && id < best_index)) {
                    continue;
                }
                if !keep(tri, triangle_key(level.instance, id), b1, b2) {
                    continue;
                }
                *best_t = t;
                best_index = id;
                best = Some(Hit {
                    t,
                    primitive: Primitive::Triangle {
                        index: id,
                        instance: level.instance,
                        b1,
                        b2,
                    },
                });
            }
        }
        for &c in order[..n].iter().rev() {
            let c = c as usize;
            if node.count[c] == 0 {
                stack[sp] = (node.child[c], dist[c]);
                sp += 1;
            }
        }
    }
    best
}

/// Whether any kept hit of the ray has `t < t_max` (shadow rays: the first one found
/// ends the walk).
#[inline(always)]
pub(super) fn any<K: BoxTest>(
    level: &Level<'_>,
    ray: &BoxRay,
    t_max: f32,
    intersect: &impl Fn(&[glam::Vec3; 3], f32) -> Option<(f32, f32, f32, f32)>,
    keep: &impl Fn(&TriangleRecord, u64, f32, f32) -> bool,
) -> bool {
    let bvh = level.bvh;
    if bvh.nodes.is_empty() || !ray.is_finite() {
        return false;
    }
    let limit = box_limit(t_max);
    let (mut inline, mut heap) = ([(0u32, 0f32); STACK_INLINE], Vec::new());
    let stack = stack_for(bvh, &mut inline, &mut heap);
    stack[0] = (0, 0.0);
    let mut sp = 1;
    while sp > 0 {
        sp -= 1;
        let node = &bvh.nodes[stack[sp].0 as usize];
        let (_, mut mask) = K::test(node, ray, limit);
        while mask != 0 {
            let c = mask.trailing_zeros() as usize;
            mask &= mask - 1;
            let count = node.count[c];
            if count == 0 {
                stack[sp] = (node.child[c], 0.0);
                sp += 1;
                continue;
            }
            let first = node.child[c] as usize;
            for &id in &bvh.prims[first..first + count as usize] {
                let tri = &level.triangles[id as usize];
                if let Some((_, _, b1, b2)) = intersect(&tri.p, t_max) {
                    if keep(tri, triangle_key(level.instance, id), b1, b2) {
                        return true;
                    }
                }
            }
        }
    }
    false
}
