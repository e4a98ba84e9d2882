//! Building the `obvhs` CWBVHs: robust against coincident primitives, and on a stack of
//! known size.
//!
//! **Why coincident primitives are quadratic in obvhs 0.4.0.** Its PLOC builder sorts the
//! primitives by the Morton code of their box centres, then repeatedly pairs every node
//! with the neighbour (within 14 places in sort order) whose union box has the smallest
//! surface area, and merges the pairs that choose each other. Candidates are compared
//! with `<=`, so among equal costs the *last* one wins. When many boxes are identical
//! (the same triangle repeated, or instances of one mesh at one place) every cost ties:
//! node `i` chooses `i + 14`, which chooses `i + 28`, and only the last two nodes choose
//! each other. Each pass over all `n` nodes then merges one pair, so the build takes `n`
//! passes (`O(n²)`, 40 s for 40,000 triangles), and the tree it makes is a chain `n`
//! nodes deep. The CWBVH conversion (`Bvh2Converter::calculate_cost_impl` and
//! `convert_to_cwbvh_impl`) recurses once per level of that chain, which overflows any
//! ordinary thread stack. The same happens, more mildly, for any group of primitives
//! whose costs tie (identical or nested boxes around one centre).
//!
//! **What we do.** Before calling obvhs we group the primitives by the cell of their box
//! centre on a grid of `2^21` cells per axis over the bounds of all boxes (the resolution
//! of obvhs' own 64-bit Morton codes, so primitives in one cell are indistinguishable to
//! its sort). When no cell holds [`CLUSTER_MIN`] primitives or more, which is what
//! ordinary scenes look like, the BVH is built by exactly the obvhs call used before, so
//! their trees and images do not change. Otherwise each crowded cell becomes a *cluster*:
//! PLOC (with the same parameters, and obvhs' reinsertion optimiser) builds the top of the
//! tree over the clusters' union boxes and the remaining single primitives, and each
//! cluster leaf is then replaced by a balanced subtree over its members, built by median
//! splits along the widest axis of their centres (by index where the centres coincide).
//! A cluster of `g` primitives costs `O(g log g)` and adds `⌈log2 g⌉` levels, so the
//! whole build stays `O(n log n)` and shallow.
//!
//! **Ties without coincidence.** A long row of identical primitives at exactly even
//! spacing (a fence, an array of instances placed by a modifier) ties every neighbour cost
//! too, without any crowded cell: node `i` chooses `i + 1`, which chooses `i + 2`, and
//! obvhs builds a chain in `O(n²)` (measured before this was handled: 5,000 triangles
//! 0.28 s, 20,000 in 4.0 s). Such input is recognised by its boxes: when
//! [`TIE_MIN`] boxes or more have bit-identical extents, every box is widened by a tiny,
//! deterministic, index-dependent margin (at most `2^-10` of its own size, see
//! [`tie_break_pad`]) before PLOC sees it. The costs then differ, pairs choose each other
//! as in any ordinary input, and the build takes `O(log n)` passes and makes an
//! `O(log n)`-deep tree ([`BvhBuildStats::tie_broken`] counts the primitives). A widened
//! box still contains its primitive, so the tree stays conservative: hits are the exact
//! triangle tests' as always. Ordinary scenes (no such run of equal extents) take the
//! unchanged obvhs call, so their trees and images do not change. (A flat grid of
//! identical quads is not affected in the first place: its Morton order makes pairs
//! mutual; 524,288 such triangles build in 1 s either way.)
//!
//! **Stack.** All builds run on a thread of their own with a stack of
//! [`BUILD_STACK_BYTES`] ([`on_build_stack`]), so obvhs' recursions never depend on the
//! stack of the caller (workers build inside tokio's `spawn_blocking` threads, 2 MiB).

use obvhs::aabb::Aabb;
use obvhs::bvh2::node::Bvh2Node;
use obvhs::bvh2::reinsertion::ReinsertionOptimizer;
use obvhs::bvh2::Bvh2;
use obvhs::cwbvh::bvh2_to_cwbvh::bvh2_to_cwbvh;
use obvhs::cwbvh::CwBvh;
use obvhs::ploc::PlocBuilder;
use obvhs::triangle::Triangle;
use obvhs::BvhBuildParams;

/// Stack size of the thread every BVH build runs on (see
/// [`super::Geometry::build_instanced`] and [`super::MotionTriangles::new`]). obvhs' CWBVH
/// conversion recurses once per level of the binary tree, a few hundred bytes a level.
/// Clustered trees are `O(log n)` deep; the margin is for the trees obvhs itself still
/// makes deep (the known limit in the module docs). It is address space reserved, not
/// memory used, until a deep recursion touches it.
pub const BUILD_STACK_BYTES: usize = 64 << 20;

/// The fewest primitives in one centre cell that are built as a cluster (see the module
/// docs). Smaller groups are left to PLOC: a group of `g` tied primitives costs it about
/// `g` extra passes, which below this stays within the passes an ordinary build needs.
pub const CLUSTER_MIN: usize = 32;

/// The fewest boxes with bit-identical extents for which ties are broken by widening
/// the boxes (see the module docs). A tied run of `g` primitives costs obvhs about `g`
/// passes over all `n`; below this it stays within a few milliseconds.
pub const TIE_MIN: usize = 1024;

/// Bits per axis of the centre cells: those of obvhs' 64-bit Morton codes.
const CELL_BITS: u32 = 21;

/// What building BVHs cost, summed over every BVH of a scene (the world-space triangles,
/// each prototype, the top level over instances, each motion segment): a count of the
/// work done by our own code, so tests can bound the build by `n log n` instead of
/// by wall-clock time.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct BvhBuildStats {
    /// BVHs built.
    pub bvhs: u64,
    /// Primitives (triangles or instance boxes) over all of them.
    pub primitives: u64,
    /// Primitives that were built into cluster subtrees (0 for ordinary scenes).
    pub clustered: u64,
    /// Clusters built.
    pub clusters: u64,
    /// Items handed to obvhs' PLOC builder: each single primitive, and one per cluster.
    /// No centre cell among them holds [`CLUSTER_MIN`] single primitives, so PLOC does
    /// not meet the ties that make it quadratic.
    pub ploc_inputs: u64,
    /// Steps of our own code: `n ⌈log2 n⌉ + n` per BVH for grouping (a bound on the
    /// comparisons of its sort), and, where clusters are built, one per node visited
    /// while grafting them and one per primitive per level of each cluster's median
    /// splits. At most `2 n ⌈log2 n⌉ + 6 n` per BVH.
    pub work: u64,
    /// Primitives whose boxes were widened to break PLOC's ties (0 for ordinary scenes).
    pub tie_broken: u64,
    /// Deepest binary tree built by our own code or measured by it (the grafted trees
    /// and the tie-broken ones; 0 when every BVH took the ordinary path, whose depth
    /// obvhs does not report).
    pub max_depth: u32,
}

impl BvhBuildStats {
    /// Adds `other`'s counts (the depth is the maximum of the two).
    pub fn add(&mut self, other: &BvhBuildStats) {
        self.bvhs += other.bvhs;
        self.primitives += other.primitives;
        self.clustered += other.clustered;
        self.clusters += other.clusters;
        self.ploc_inputs += other.ploc_inputs;
        self.work += other.work;
        self.tie_broken += other.tie_broken;
        self.max_depth = self.max_depth.max(other.max_depth);
    }
}

/// Runs `f` on a thread with a stack of [`BUILD_STACK_BYTES`] and returns its result (a
/// panic in `f` is resumed on the caller). Panics if the thread cannot be started.
pub(super) fn on_build_stack<R: Send>(f: impl FnOnce() -> R + Send) -> R {
    std::thread::scope(|scope| {
        let handle = std::thread::Builder::new()
            .name("tessera-bvh-build".into())
            .stack_size(BUILD_STACK_BYTES)
            .spawn_scoped(scope, f)
            .expect("cannot start the BVH build thread");
        match handle.join() {
            Ok(r) => r,
            Err(panic) => std::panic::resume_unwind(panic),
        }
    })
}

/// The build parameters of every BVH: obvhs' "medium" preset, as before clustering.
const fn params() -> BvhBuildParams {
    BvhBuildParams::medium_build()
}

/// A binary BVH over `triangles`: obvhs' triangle builder (PLOC, then reinsertion) for
/// ordinary input, the clustered build when centres crowd (see the module docs). It is
/// the tree `obvhs::cwbvh::builder::build_cwbvh_from_tris` converts (without pre-splits),
/// so [`to_cwbvh`] of it is the CWBVH that call returns.
pub(super) fn triangles_bvh2(triangles: &[Triangle], stats: &mut BvhBuildStats) -> Bvh2 {
    let boxes: Vec<Aabb> = triangles.iter().map(Triangle::aabb).collect();
    match crowded_cells(&boxes, stats) {
        None if tied_extents(&boxes, stats) => tie_broken_bvh2(&boxes, stats),
        None => {
            let p = params();
            let mut bvh2 = PlocBuilder::with_capacity(triangles.len()).build(
                p.ploc_search_distance,
                triangles,
                (0..triangles.len() as u32).collect::<Vec<_>>(),
                p.sort_precision,
                p.search_depth_threshold,
            );
            ReinsertionOptimizer::default().run(&mut bvh2, p.reinsertion_batch_ratio, None);
            bvh2
        }
        Some(cells) => clustered_bvh2(&boxes, &cells, stats),
    }
}

/// A CWBVH over `boxes` (instances' world bounds, moving triangles' swept bounds): obvhs'
/// builder for ordinary input, the clustered build when centres crowd.
pub(super) fn boxes_cwbvh(boxes: &[Aabb], stats: &mut BvhBuildStats) -> CwBvh {
    match crowded_cells(boxes, stats) {
        None if tied_extents(boxes, stats) => to_cwbvh(&tie_broken_bvh2(boxes, stats)),
        None => {
            let mut build_time = std::time::Duration::ZERO;
            obvhs::cwbvh::builder::build_cwbvh(boxes, params(), &mut build_time)
        }
        Some(cells) => to_cwbvh(&clustered_bvh2(boxes, &cells, stats)),
    }
}

/// obvhs' CWBVH of a binary BVH, with the leaf size its builders use.
pub(super) fn to_cwbvh(bvh2: &Bvh2) -> CwBvh {
    bvh2_to_cwbvh(bvh2, params().max_prims_per_leaf.clamp(1, 3), true, false)
}

/// `⌈log2 n⌉` (0 for `n <= 1`).
fn ceil_log2(n: usize) -> u64 {
    u64::from(usize::BITS - n.saturating_sub(1).leading_zeros())
}

/// The centre cell of every box, as `(cell, index)` sorted, when some cell holds
/// [`CLUSTER_MIN`] boxes or more; `None` otherwise (the ordinary path). Counts the
/// primitives and the grouping work in `stats`.
fn crowded_cells(boxes: &[Aabb], stats: &mut BvhBuildStats) -> Option<Vec<(u64, u32)>> {
    let n = boxes.len();
    stats.bvhs += 1;
    stats.primitives += n as u64;
    stats.work += n as u64 * ceil_log2(n) + n as u64;
    if n < CLUSTER_MIN {
        stats.ploc_inputs += n as u64;
        return None;
    }
    let mut total = Aabb::empty();
    for b in boxes {
        total.extend(b.min);
        total.extend(b.max);
    }
    let lo = total.min.as_dvec3();
    let extent = (total.max - total.min).as_dvec3();
    let cells = f64::from((1u32 << CELL_BITS) - 1);
    let quantise = |c: f64, lo: f64, extent: f64| -> u64 {
        if extent > 0.0 {
            // NaN and out-of-range values saturate in the cast: any cell will do.
            (((c - lo) / extent) * cells) as u64
        } else {
            0
        }
    };
    let mut keys: Vec<(u64, u32)> = boxes
        .iter()
        .enumerate()
        .map(|(i, b)| {
            let c = b.center().as_dvec3();
            let key = (quantise(c.x, lo.x, extent.x) << (2 * CELL_BITS))
                | (quantise(c.y, lo.y, extent.y) << CELL_BITS)
                | quantise(c.z, lo.z, extent.z);
            (key, i as u32)
        })
        .collect();
    keys.sort_unstable();
    let crowded = keys
        .chunk_by(|a, b| a.0 == b.0)
        .any(|run| run.len() >= CLUSTER_MIN);
    if crowded {
        Some(keys)
    } else {
        stats.ploc_inputs += n as u64;
        None
    }
}

/// Whether [`TIE_MIN`] or more of `boxes` have bit-identical extents (the input that
/// ties PLOC's costs without crowding a cell; see the module docs). Counts its sort in
/// `stats.work`.
fn tied_extents(boxes: &[Aabb], stats: &mut BvhBuildStats) -> bool {
    let n = boxes.len();
    if n < TIE_MIN {
        return false;
    }
    stats.work += n as u64 * ceil_log2(n) + n as u64;
    let mut extents: Vec<[u32; 3]> = boxes
        .iter()
        .map(|b| (b.max - b.min).to_array().map(f32::to_bits))
        .collect();
    extents.sort_unstable();
    extents
        .chunk_by(|a, b| a == b)
        .any(|run| run.len() >= TIE_MIN)
}

/// The margin box `i` is widened by on every side to break ties: a fraction between
/// `2^-18` and `2^-10` of its largest extent, chosen by a hash of `i` (so every build of
/// the same input agrees), or, for a box without extent, the same fraction of its largest
/// coordinate (or of 1 at the origin). Large enough to change the surface areas PLOC
/// compares in `f32`, small enough not to change which boxes a ray meets in practice.
pub(super) fn tie_break_pad(b: &Aabb, i: u32) -> f32 {
    let size = (b.max - b.min).max_element();
    let scale = if size > 0.0 {
        size
    } else {
        b.min.abs().max(b.max.abs()).max_element().max(1.0)
    };
    // SplitMix64's finaliser: the low 8 bits of a well-mixed hash of the index.
    let mut z = u64::from(i).wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^= z >> 31;
    let k = (z & 0xff) as f32 + 1.0;
    scale * k * (1.0 / (1u32 << 18) as f32)
}

/// PLOC over `boxes` each widened by [`tie_break_pad`], then obvhs' reinsertion, as in
/// its own builder (see the module docs).
fn tie_broken_bvh2(boxes: &[Aabb], stats: &mut BvhBuildStats) -> Bvh2 {
    let padded: Vec<Aabb> = boxes
        .iter()
        .enumerate()
        .map(|(i, b)| {
            let d = glam::Vec3A::splat(tie_break_pad(b, i as u32));
            Aabb::new(b.min - d, b.max + d)
        })
        .collect();
    stats.tie_broken += boxes.len() as u64;
    stats.ploc_inputs += boxes.len() as u64;
    let p = params();
    let mut bvh2 = PlocBuilder::with_capacity(padded.len()).build(
        p.ploc_search_distance,
        &padded,
        (0..padded.len() as u32).collect(),
        p.sort_precision,
        p.search_depth_threshold,
    );
    ReinsertionOptimizer::default().run(&mut bvh2, p.reinsertion_batch_ratio, None);
    // The tree's depth, without recursion: what the tests bound by `log n`.
    let mut depth = 0u32;
    let mut stack: Vec<(usize, u32)> = vec![(0, 0)];
    while let Some((node, d)) = stack.pop() {
        stats.work += 1;
        depth = depth.max(d);
        let node = &bvh2.nodes[node];
        if !node.is_leaf() {
            let child = node.first_index as usize;
            stack.push((child, d + 1));
            stack.push((child + 1, d + 1));
        }
    }
    stats.max_depth = stats.max_depth.max(depth);
    bvh2
}

/// The clustered build (see the module docs) over `boxes`, given every box's centre cell
/// as `(cell, index)` sorted by cell.
fn clustered_bvh2(boxes: &[Aabb], cells: &[(u64, u32)], stats: &mut BvhBuildStats) -> Bvh2 {
    // Items for PLOC: every crowded cell as one (its members a range of `members`), every
    // other primitive on its own.
    let mut members: Vec<u32> = Vec::with_capacity(boxes.len());
    let mut items: Vec<(u32, u32)> = Vec::new();
    let mut item_boxes: Vec<Aabb> = Vec::new();
    for run in cells.chunk_by(|a, b| a.0 == b.0) {
        if run.len() >= CLUSTER_MIN {
            let start = members.len() as u32;
            let mut bounds = Aabb::empty();
            for &(_, i) in run {
                members.push(i);
                bounds = bounds.union(&boxes[i as usize]);
            }
            items.push((start, members.len() as u32));
            item_boxes.push(bounds);
            stats.clusters += 1;
            stats.clustered += run.len() as u64;
        } else {
            for &(_, i) in run {
                items.push((members.len() as u32, members.len() as u32 + 1));
                members.push(i);
                item_boxes.push(boxes[i as usize]);
            }
        }
    }
    stats.ploc_inputs += items.len() as u64;
    let p = params();
    let mut top = PlocBuilder::with_capacity(item_boxes.len()).build(
        p.ploc_search_distance,
        &item_boxes,
        (0..item_boxes.len() as u32).collect(),
        p.sort_precision,
        p.search_depth_threshold,
    );
    ReinsertionOptimizer::default().run(&mut top, p.reinsertion_batch_ratio, None);

    // Graft: copy the top tree, replacing each leaf by a subtree over its items' members.
    let n = boxes.len();
    let mut nodes: Vec<Bvh2Node> = Vec::with_capacity(2 * n - 1);
    nodes.push(Bvh2Node::default());
    let mut max_depth = 0u32;
    let mut work = 0u64;
    let mut stack: Vec<(usize, usize, u32)> = vec![(0, 0, 0)];
    let mut leaf_members: Vec<u32> = Vec::new();
    while let Some((old, slot, depth)) = stack.pop() {
        work += 1;
        let node = top.nodes[old];
        if node.is_leaf() {
            leaf_members.clear();
            let first = node.first_index as usize;
            for &item in &top.primitive_indices[first..first + node.prim_count as usize] {
                let (s, e) = items[item as usize];
                leaf_members.extend_from_slice(&members[s as usize..e as usize]);
            }
            let d = median_subtree(&mut leaf_members, boxes, &mut nodes, slot, &mut work);
            max_depth = max_depth.max(depth + d);
        } else {
            let first = nodes.len();
            nodes.push(Bvh2Node::default());
            nodes.push(Bvh2Node::default());
            nodes[slot] = Bvh2Node::new(*node.aabb(), 0, first as u32);
            let child = node.first_index as usize;
            stack.push((child, first, depth + 1));
            stack.push((child + 1, first + 1, depth + 1));
        }
    }
    debug_assert_eq!(nodes.len(), 2 * n - 1);
    stats.work += work;
    stats.max_depth = stats.max_depth.max(max_depth);
    Bvh2 {
        nodes,
        // Leaves name their primitive directly (`first_index`), through the identity.
        primitive_indices: (0..n as u32).collect(),
        max_depth: (max_depth as usize + 1).max(obvhs::bvh2::DEFAULT_MAX_STACK_DEPTH),
        ..Bvh2::default()
    }
}

/// Writes a balanced binary tree over `members` (primitive indices into `boxes`, at
/// least one) into `nodes`, its root at `slot` and every other node appended: median
/// splits along the widest axis of the members' centres, or, where the centres coincide,
/// in the order given. Leaves hold one primitive each. Returns the tree's depth (0 for a
/// single leaf) and adds one to `work` per member per level.
fn median_subtree(
    members: &mut [u32],
    boxes: &[Aabb],
    nodes: &mut Vec<Bvh2Node>,
    slot: usize,
    work: &mut u64,
) -> u32 {
    let centre = |i: u32| boxes[i as usize].center();
    let mut max_depth = 0;
    let mut stack: Vec<(usize, usize, usize, u32)> = vec![(0, members.len(), slot, 0)];
    while let Some((start, end, slot, depth)) = stack.pop() {
        max_depth = max_depth.max(depth);
        let range = &mut members[start..end];
        *work += range.len() as u64;
        if let [only] = range {
            nodes[slot] = Bvh2Node::new(boxes[*only as usize], 1, *only);
            continue;
        }
        let mut bounds = Aabb::empty();
        let mut centres = Aabb::empty();
        for &m in range.iter() {
            bounds = bounds.union(&boxes[m as usize]);
            centres.extend(centre(m));
        }
        let spread = centres.max - centres.min;
        let axis = if spread.x >= spread.y && spread.x >= spread.z {
            0
        } else if spread.y >= spread.z {
            1
        } else {
            2
        };
        let mid = range.len() / 2;
        if spread[axis] > 0.0 {
            range.select_nth_unstable_by(mid, |&a, &b| {
                centre(a)[axis].total_cmp(&centre(b)[axis]).then(a.cmp(&b))
            });
        }
        let first = nodes.len();
        nodes.push(Bvh2Node::default());
        nodes.push(Bvh2Node::default());
        nodes[slot] = Bvh2Node::new(bounds, 0, first as u32);
        stack.push((start, start + mid, first, depth + 1));
        stack.push((start + mid, end, first + 1, depth + 1));
    }
    max_depth
}
