//! Our own wide BVH over triangles: obvhs' binary tree collapsed into nodes of
//! [`WIDTH`] children whose boxes are stored as structure-of-arrays, so one box test
//! covers every child with the ISA's widest vectors (the kernels are in `kernels`).
//!
//! **Collapse.** By the surface area heuristic, with the dynamic programme of Ylitie,
//! Karras & Laine 2017, §3 (the SAH for wide nodes: Wald, Benthin & Boulos 2008, §3):
//! bottom up over obvhs' binary tree, every binary node gets the cheapest way to stand
//! for its subtree within a budget of 1 to [`WIDTH`] children of its parent: as one child
//! (a leaf of up to [`SahCost::leaf_max`] triangles, or a wide node of its own), or
//! distributed into its two subtrees' children. A wide node costs its box's half area
//! (each ray entering it tests all its children's boxes), a leaf its half area times its
//! triangle count times [`SahCost::prim`]; then the wide nodes are made top down by the
//! decisions ([`plan`]). Unlike the greedy collapse it replaced (open the child of
//! largest area until the node is full, as tinybvh's `MBVH::ConvertFrom` does; leaves of
//! at most 4 triangles), it makes a small subtree a leaf instead of an under-full node
//! where that is cheaper, and shares a node's slots out by what they save
//! (docs/benchmarks.md, "The SAH collapse"). Nodes are 64-byte aligned (one
//! [`WideNode`] of 8 children is exactly four cache lines: the six bound arrays, then the
//! child references).
//!
//! **Leaves** are ranges `(first, count)` of [`WideBvh::prims`], the leaf contents in the
//! order the collapse emits them. For instances and moving triangles the entries name
//! instances and records; a level of triangles takes them over as its triangles' numbers
//! and stores the triangles in that order ([`Triangles`]), so a leaf is the range of
//! stored triangles itself and no index array is walked. The numbers are the triangles'
//! positions in obvhs' CWBVH leaf order, which [`super::triangle_key`] hashes, so keys
//! and images do not change; the triangles are tested by `watertight`'s scalar test,
//! unchanged.
//!
//! **The hit is independent of the visit order.** A triangle hit replaces the best one
//! when its `t` is smaller, or equal with a smaller key (the triangle number in a level of
//! world-space triangles; see [`Nearest`] and the `geometry` module docs for instances
//! and moving triangles, whose leaves the same walk serves); boxes are pruned only
//! beyond the best `t` plus a relative margin ([`box_limit`]) far wider than the rounding
//! of the box and triangle tests, and the box test is conservative (Ize 2013, via pbrt
//! 3rd ed. §3.9.2: the far distance is scaled by `1 + 2 γ(3)`). So the nearest hit is the
//! lexicographic minimum of `(t, key)` over every hit the watertight test accepts,
//! whatever order the children are visited in and whatever kernel tests the boxes: every
//! kernel gives the same hit, bit for bit (ARCHITECTURE.md §2).

use super::{triangle_key, Hit, HitTriangle, Primitive, Triangles};
use crate::math::gamma;
use obvhs::bvh2::Bvh2;
use std::cell::Cell;
use std::thread::LocalKey;

/// Children per node.
pub(super) const WIDTH: usize = 8;

thread_local! {
    /// The traversal stack of this thread's walks over triangles (world-space,
    /// prototypes' and moving ones), reused from ray to ray: a stack made for each ray
    /// has to be written whole before use (`unsafe_code` is denied, so no
    /// `MaybeUninit`), and zeroing 96 entries cost 63 instructions a ray, 3.3% of a
    /// Cornell box path (docs/benchmarks.md, "Where a path's instructions go").
    /// [`Leaves::stack`] says which stack a walk takes.
    static LEVEL_STACK: Cell<Vec<(u32, f32)>> = const { Cell::new(Vec::new()) };
    /// The top level's stack: a walk over instances walks each prototype's BVH inside
    /// its own, with [`LEVEL_STACK`].
    pub(super) static TOP_STACK: Cell<Vec<(u32, f32)>> = const { Cell::new(Vec::new()) };
}

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
    /// An interior child's node index, or a leaf's first entry in [`WideBvh::prims`] (of
    /// a level of triangles: its first stored triangle, see [`Triangles`]).
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
    /// Leaf contents, leaf after leaf: instances, moving triangles' records, or the
    /// numbers of a level's triangles (empty once [`Triangles`] has taken them over).
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

/// What the collapse's surface area heuristic charges (Ylitie, Karras & Laine 2017, §3;
/// the SAH for wide nodes as in Wald, Benthin & Boulos 2008, §3): a wide node costs its
/// box's half area times 1 (one box test of every child for each ray that enters it), a
/// leaf its half area times its primitive count times [`SahCost::prim`] (one test of each
/// primitive for each ray that enters it).
#[derive(Clone, Copy, Debug)]
pub(super) struct SahCost {
    /// The most primitives a leaf made from a binary subtree holds (a binary leaf of more
    /// stays one leaf: obvhs' and our builds make leaves of one primitive).
    pub(super) leaf_max: u32,
    /// The cost of one primitive's test relative to one node's box test.
    pub(super) prim: f32,
}

impl SahCost {
    /// Triangles (and moving triangles): the scalar watertight test of one triangle
    /// against the box test of a node's eight children.
    pub(super) const TRIANGLES: SahCost = SahCost {
        leaf_max: 8,
        prim: 0.3,
    };
}

/// The collapse's decisions for one binary node: nibble `i - 1` for a budget of `i`
/// children (`1..=WIDTH`). Budget 1: 0 makes the node a leaf, `k` a wide node whose
/// children are its left subtree's with a budget of `k` and its right subtree's with
/// `WIDTH - k`. Budget `i >= 2`: 0 leaves the node one child (as decided for budget 1),
/// `k` distributes it into its left subtree's children with a budget of `k` and its right
/// subtree's with `i - k`. Four bytes per binary node, what the greedy collapse held
/// (each node's triangle count).
type Plan = u32;
const _: () = assert!(
    WIDTH <= 8,
    "a plan holds budgets of at most 8 in 4-bit fields"
);

/// The nibble of `plan` for a budget of `budget` children.
#[inline(always)]
fn decision(plan: Plan, budget: usize) -> usize {
    ((plan >> (4 * (budget - 1))) & 15) as usize
}

/// The collapse's dynamic programme (Ylitie, Karras & Laine 2017, §3, their cost
/// function with [`SahCost`]): for every binary node and every budget `i` of children
/// it may take in its parent, the cheapest way to cover its subtree, bottom up. With
/// `C(n, i)` the cost of node `n` within a budget of `i`,
/// `C(n, 1) = min(leaf, A(n) + D(n, WIDTH))` (a leaf only up to `leaf_max` primitives),
/// `C(n, i) = min(C(n, 1), D(n, i))` for `i >= 2`, and `D(n, i)` the cheapest split
/// `C(left, k) + C(right, i - k)`. Returns the plans, and how many binary nodes would
/// become wide nodes if reached (a bound on the wide nodes besides the root). The costs
/// live on a stack as deep as the tree (a node's are read only by its parent); the plans
/// take four bytes per binary node.
fn plan(bvh2: &Bvh2, cost: SahCost) -> (Vec<Plan>, usize) {
    let bn = &bvh2.nodes;
    let mut plans: Vec<Plan> = vec![0; bn.len()];
    let mut internal = 0;
    // Each visited subtree's costs for budgets 1..=WIDTH and its primitive count.
    let mut values: Vec<([f32; WIDTH], u32)> = Vec::new();
    let mut stack: Vec<(usize, bool)> = vec![(0, false)];
    while let Some((i, done)) = stack.pop() {
        let n = &bn[i];
        let area = n.aabb().half_area();
        if n.is_leaf() {
            let leaf = area * n.prim_count as f32 * cost.prim;
            values.push(([leaf; WIDTH], n.prim_count));
            continue;
        }
        let first = n.first_index as usize;
        if !done {
            // Left first, so its values lie below the right's.
            stack.extend([(i, true), (first + 1, false), (first, false)]);
            continue;
        }
        let (right, count_right) = values.pop().expect("right subtree visited");
        let (left, count_left) = values.pop().expect("left subtree visited");
        let count = count_left.saturating_add(count_right);
        // The cheapest split of a budget of `i` (at least 2) between the subtrees; the
        // first on ties, and `k = 1` when every sum is NaN, so a split always exists.
        let split = |i: usize| {
            let mut best = (left[0] + right[i - 2], 1);
            for k in 2..i {
                let c = left[k - 1] + right[i - k - 1];
                if c < best.0 {
                    best = (c, k);
                }
            }
            best
        };
        let mut costs = [0f32; WIDTH];
        let mut p: Plan = 0;
        let (distribute, k) = split(WIDTH);
        let inner = area + distribute;
        let leaf = area * count as f32 * cost.prim;
        // The root is always a wide node (the walk starts at one), so its plan for a
        // budget of 1 is always the wide node's split.
        if i != 0 && count <= cost.leaf_max && leaf <= inner {
            costs[0] = leaf;
        } else {
            costs[0] = inner;
            p |= k as Plan;
            internal += 1;
        }
        for budget in 2..=WIDTH {
            let (c, k) = split(budget);
            if c < costs[0] {
                costs[budget - 1] = c;
                p |= (k as Plan) << (4 * (budget - 1));
            } else {
                costs[budget - 1] = costs[0];
            }
        }
        plans[i] = p;
        values.push((costs, count));
    }
    (plans, internal)
}

impl WideBvh {
    /// The wide BVH of `bvh2` (non-empty), whose primitive `i` is at `position[i]` in the
    /// level's triangle array, collapsed by the SAH with [`SahCost::TRIANGLES`] (every
    /// level: triangles, moving triangles and the top level over instances).
    pub(super) fn collapse(bvh2: &Bvh2, position: &[u32]) -> Self {
        Self::collapse_with(bvh2, position, SahCost::TRIANGLES)
    }

    /// [`WideBvh::collapse`] with the costs `cost` (see the module docs).
    pub(super) fn collapse_with(bvh2: &Bvh2, position: &[u32], cost: SahCost) -> Self {
        let mut out = Self::collapse_by(bvh2, |p| position[p as usize], cost);
        out.nodes.shrink_to_fit();
        out
    }

    /// [`WideBvh::collapse`] of a tree whose primitive indices are already the leaf
    /// entries (a level of triangles puts their positions there, see
    /// `traversal::triangle_bvh_chunked`), with the node array not yet shrunk to its
    /// length: its unused reserve was never written, so it is not resident, and shrinking
    /// copies the array (its 64-byte alignment rules out an in-place `realloc`), which
    /// the caller does once the binary tree is freed.
    pub(super) fn collapse_entries(bvh2: &Bvh2) -> Self {
        Self::collapse_by(bvh2, |p| p, SahCost::TRIANGLES)
    }

    /// The collapse, primitive `p` of `bvh2` becoming the leaf entry `entry(p)`.
    #[allow(clippy::needless_range_loop)] // axes index the node's arrays and the box's
    fn collapse_by(bvh2: &Bvh2, entry: impl Fn(u32) -> u32, cost: SahCost) -> Self {
        let bn = &bvh2.nodes;
        let (plans, internal) = plan(bvh2, cost);
        // Every wide node but the root stands for a distinct binary node planned as one,
        // so their count bounds the nodes. Reserving it up front keeps the array from
        // doubling (two copies at once at the build's memory peak); pages never written
        // are never resident, and the callers shrink the array to return the rest.
        let mut nodes = Vec::with_capacity(1 + internal);
        nodes.push(WideNode::EMPTY);
        let mut out = WideBvh {
            nodes,
            prims: Vec::with_capacity(bvh2.primitive_indices.len()),
            stack_need: 0,
        };
        // A child is a leaf when its plan for a budget of 1 is (binary leaves included).
        let is_leaf = |c: usize| decision(plans[c], 1) == 0;
        // (binary node, wide node it fills); a root that is a binary leaf is the root
        // node's only child.
        let mut work: Vec<(usize, usize)> = vec![(0, 0)];
        let mut children: Vec<usize> = Vec::with_capacity(WIDTH);
        let mut gather: Vec<(usize, usize)> = Vec::with_capacity(2 * WIDTH);
        let mut leaf_walk: Vec<usize> = Vec::new();
        while let Some((b, w)) = work.pop() {
            children.clear();
            if is_leaf(b) {
                children.push(b);
            } else {
                // The plan's children, left to right: each (subtree, budget) stays one
                // child or is distributed between its subtrees.
                let k = decision(plans[b], 1);
                let first = bn[b].first_index as usize;
                gather.clear();
                gather.extend([(first + 1, WIDTH - k), (first, k)]);
                while let Some((c, budget)) = gather.pop() {
                    let k = if budget >= 2 && !bn[c].is_leaf() {
                        decision(plans[c], budget)
                    } else {
                        0
                    };
                    if k == 0 {
                        children.push(c);
                    } else {
                        let first = bn[c].first_index as usize;
                        gather.extend([(first + 1, budget - k), (first, k)]);
                    }
                }
            }
            debug_assert!(children.len() <= WIDTH);
            for (slot, &c) in children.iter().enumerate() {
                let bb = bn[c].aabb();
                for axis in 0..3 {
                    out.nodes[w].lo[axis][slot] = bb.min[axis];
                    out.nodes[w].hi[axis][slot] = bb.max[axis];
                }
                if is_leaf(c) {
                    let first = out.prims.len() as u32;
                    leaf_walk.clear();
                    leaf_walk.push(c);
                    while let Some(i) = leaf_walk.pop() {
                        let n = &bn[i];
                        if n.is_leaf() {
                            let s = n.first_index as usize;
                            for &p in &bvh2.primitive_indices[s..s + n.prim_count as usize] {
                                out.prims.push(entry(p));
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
        out
    }

    /// Bytes of the nodes and leaf contents.
    pub(super) fn bytes(&self) -> usize {
        std::mem::size_of_val(self.nodes.as_slice()) + std::mem::size_of_val(self.prims.as_slice())
    }
}

/// This thread's stack `key` taken out of it, at least as long as `bvh` can need
/// (grown once per thread to the deepest tree walked): the walk indexes a slice of it,
/// inlined into each kernel's `#[target_feature]` function (`LocalKey::with` would put
/// it in a closure), and gives it back with `key.set`. Taken rather than borrowed, so a
/// walk that did not give it back (a panic) leaves an empty stack, not a locked one.
#[inline(always)]
fn take_stack(key: &'static LocalKey<Cell<Vec<(u32, f32)>>>, bvh: &WideBvh) -> Vec<(u32, f32)> {
    let mut stack = key.take();
    if stack.len() < bvh.stack_need {
        stack.resize(bvh.stack_need, (0, 0.0));
    }
    stack
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

/// The nearest hit found so far in one level of the scene (the world-space triangles, the
/// instances, the moving triangles), and the rule that replaces it: a hit replaces the
/// best one when its `t` is smaller, or equal with a smaller key ([`super::triangle_key`]
/// of the triangle, which orders instances before their triangles). So the level's
/// nearest hit is the lexicographic minimum of `(t, key)` over every hit the triangle
/// test accepts, whatever the visit order (see the module docs).
pub(super) struct Nearest {
    /// The level's exclusive bound on `t` (the ray's end, or an earlier level's hit).
    t_max: f32,
    /// The best hit's `t`, or `t_max` while there is none: what the walk prunes by.
    pub(super) t: f32,
    /// The best hit's key.
    key: u64,
    /// The best hit.
    pub(super) hit: Option<Hit>,
}

impl Nearest {
    /// No hit yet, below `t_max`.
    #[inline(always)]
    pub(super) fn new(t_max: f32) -> Self {
        Self {
            t_max,
            t: t_max,
            key: u64::MAX,
            hit: None,
        }
    }

    /// The bound to hand the triangle test: the level's own while there is no hit, else
    /// the best `t` widened by [`box_limit`] so that ties reach [`Nearest::offer`], which
    /// decides them exactly.
    #[inline(always)]
    pub(super) fn bound(&self) -> f32 {
        if self.hit.is_some() {
            box_limit(self.t).min(self.t_max)
        } else {
            self.t_max
        }
    }

    /// Whether a hit at `t` with key `key` would replace the best one.
    #[inline(always)]
    pub(super) fn beats(&self, t: f32, key: u64) -> bool {
        self.hit.is_none() || t < self.t || (t == self.t && key < self.key)
    }

    /// Makes `hit` (which [`Nearest::beats`] the best) the best.
    #[inline(always)]
    pub(super) fn set(&mut self, hit: Hit, key: u64) {
        self.t = hit.t;
        self.key = key;
        self.hit = Some(hit);
    }
}

/// What the leaves of a wide BVH hold and how a ray meets them. The walks below are
/// generic over it, so one walk, compiled into every kernel, serves triangles, instances
/// (whose leaves walk a prototype's BVH in turn, with the same box test `K`) and moving
/// triangles.
pub(super) trait Leaves {
    /// Offers every hit in the leaf `(first, count)` of a node (its `child` and `count`)
    /// to `best`.
    fn nearest<K: BoxTest>(&self, first: u32, count: u32, best: &mut Nearest);

    /// Whether the leaf `(first, count)` holds a kept hit with `t < t_max`.
    fn any<K: BoxTest>(&self, first: u32, count: u32, t_max: f32) -> bool;

    /// The thread's traversal stack for a walk over these leaves (see [`LEVEL_STACK`]):
    /// leaves that walk other BVHs inside the walk take another.
    #[inline(always)]
    fn stack() -> &'static LocalKey<Cell<Vec<(u32, f32)>>> {
        &LEVEL_STACK
    }
}

/// The triangles of one level with the test each needs: `intersect(p, t_max)` is the
/// watertight test of the ray, `keep` the filter of `Geometry::intersect_where`. A leaf
/// `(first, count)` is the stored triangles `first..first + count` (see [`Triangles`]):
/// the walk reads their positions, adjacent in one array, and a hit's number and
/// attributes only once the test accepts it.
pub(super) struct Level<'g, I, F> {
    pub(super) triangles: &'g Triangles,
    pub(super) instance: u32,
    pub(super) intersect: &'g I,
    pub(super) keep: &'g F,
}

impl<I, F> Leaves for Level<'_, I, F>
where
    I: Fn(&[glam::Vec3; 3], f32) -> Option<(f32, f32, f32, f32)>,
    F: Fn(HitTriangle<'_>, u64, f32, f32) -> bool,
{
    #[inline(always)]
    fn nearest<K: BoxTest>(&self, first: u32, count: u32, best: &mut Nearest) {
        let first = first as usize;
        let leaf = self.triangles.positions_in(first..first + count as usize);
        for (s, p) in (first..).zip(leaf) {
            let Some((t, _, b1, b2)) = (self.intersect)(p, best.bound()) else {
                continue;
            };
            let key = triangle_key(self.instance, self.triangles.id(s));
            if !best.beats(t, key)
                || !(self.keep)(HitTriangle::Stored(self.triangles, s), key, b1, b2)
            {
                continue;
            }
            best.set(
                Hit {
                    t,
                    primitive: Primitive::Triangle {
                        index: s as u32,
                        instance: self.instance,
                        b1,
                        b2,
                    },
                },
                key,
            );
        }
    }

    #[inline(always)]
    fn any<K: BoxTest>(&self, first: u32, count: u32, t_max: f32) -> bool {
        // A loop rather than `Iterator::any`, which LLVM may leave uninlined, outside
        // the kernel's `#[target_feature]` function.
        let first = first as usize;
        let leaf = self.triangles.positions_in(first..first + count as usize);
        for (s, p) in (first..).zip(leaf) {
            if let Some((_, _, b1, b2)) = (self.intersect)(p, t_max) {
                let key = triangle_key(self.instance, self.triangles.id(s));
                if (self.keep)(HitTriangle::Stored(self.triangles, s), key, b1, b2) {
                    return true;
                }
            }
        }
        false
    }
}

/// Offers every hit of the ray in `bvh`'s leaves to `best` (the lexicographic minimum of
/// `(t, key)`, see [`Nearest`]), visiting children nearest first and pruning boxes
/// beyond [`box_limit`] of the best `t`.
#[inline(always)]
pub(super) fn nearest<K: BoxTest, L: Leaves>(
    bvh: &WideBvh,
    ray: &BoxRay,
    leaves: &L,
    best: &mut Nearest,
) {
    // A ray with a NaN or infinite coordinate hits nothing (and would enter unused slots).
    if bvh.nodes.is_empty() || !ray.is_finite() {
        return;
    }
    let mut stack = take_stack(L::stack(), bvh);
    stack[0] = (0, 0.0);
    let mut sp = 1;
    while sp > 0 {
        sp -= 1;
        let (ni, entry) = stack[sp];
        if entry > box_limit(best.t) {
            continue;
        }
        let node = &bvh.nodes[ni as usize];
        let (dist, mask) = K::test(node, ray, box_limit(best.t));
        let (order, n) = nearest_first(mask, &dist);
        for &c in &order[..n] {
            let c = c as usize;
            if node.count[c] != 0 {
                leaves.nearest::<K>(node.child[c], node.count[c], best);
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
    L::stack().set(stack);
}

/// Whether any kept hit of the ray in `bvh`'s leaves has `t < t_max` (shadow rays: the
/// first one found ends the walk).
#[inline(always)]
pub(super) fn any<K: BoxTest, L: Leaves>(
    bvh: &WideBvh,
    ray: &BoxRay,
    leaves: &L,
    t_max: f32,
) -> bool {
    if bvh.nodes.is_empty() || !ray.is_finite() {
        return false;
    }
    let limit = box_limit(t_max);
    let mut stack = take_stack(L::stack(), bvh);
    let hit = any_below::<K, L>(bvh, ray, leaves, t_max, limit, &mut stack);
    L::stack().set(stack);
    hit
}

/// The walk of [`any`] with `stack` (at least `bvh`'s `stack_need` entries long).
#[inline(always)]
fn any_below<K: BoxTest, L: Leaves>(
    bvh: &WideBvh,
    ray: &BoxRay,
    leaves: &L,
    t_max: f32,
    limit: f32,
    stack: &mut [(u32, f32)],
) -> bool {
    stack[0] = (0, 0.0);
    let mut sp = 1;
    while sp > 0 {
        sp -= 1;
        let node = &bvh.nodes[stack[sp].0 as usize];
        let (_, mut mask) = K::test(node, ray, limit);
        while mask != 0 {
            let c = mask.trailing_zeros() as usize;
            mask &= mask - 1;
            if node.count[c] == 0 {
                stack[sp] = (node.child[c], 0.0);
                sp += 1;
            } else if leaves.any::<K>(node.child[c], node.count[c], t_max) {
                return true;
            }
        }
    }
    false
}
