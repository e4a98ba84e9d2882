//! Building obvhs' binary BVHs, which `wide` collapses into the BVHs the renderer walks
//! (triangles, the top level over instances, the motion segments), and the CWBVH leaf
//! order that numbers triangles and instances: robust against coincident primitives, and
//! on a stack of known size.
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
//! **Memory.** A large scene's peak memory is its BVH build, so the triangle build holds
//! as little beside obvhs' own arrays as it can (figures for a 2M-triangle terrain in
//! docs/benchmarks.md, "Memory and scale"). The triangles are read from the scene by
//! index (`Geometry::build_instanced_of`), not gathered into an array of records first;
//! their boxes go straight into PLOC's leaf nodes, which PLOC then works on
//! ([`leaves_bvh2`]), instead of into an array of boxes that obvhs copies into leaves and
//! an array of obvhs triangles before it; the reinsertion's parent maps are freed once it
//! is done; the leaf order that numbers the triangles is computed without the CWBVH and
//! its cost table of 112 bytes per triangle ([`cwbvh_order`]); the records are made in
//! leaf order once the binary tree is gone. obvhs' binary nodes are its 32-byte ones
//! (the `small_bvh2_node` feature: the same trees, primitive count and index kept in the
//! boxes' padding); the tree's nodes become resident only as PLOC writes them and its
//! identity primitive indices are made after PLOC ([`ploc_from_leaves`]); while the tree
//! is collapsed, those indices hold the leaf order's positions (`traversal`). None of
//! this changes a tree or an image.
//!
//! **Large levels in chunks.** One PLOC build holds, at its end, its two node arrays and
//! its sort keys (80 bytes a primitive) beside the finished tree (64): with the scene's
//! meshes, 162 bytes a triangle, more than a renderer that keeps its geometry in 67
//! needs. A level of [`CHUNKED_FROM`] primitives or more is therefore built by PLOC in
//! chunks of at most [`CHUNK_MAX`], split at spatial medians, written into the final node array,
//! each optimised by the same reinsertion ([`chunked_bvh2`]): its tree, and so its
//! triangles' numbers, differ from the single build's; smaller levels keep theirs.
//!
//! **Stack.** All builds run on a thread of their own with a stack of
//! [`BUILD_STACK_BYTES`] ([`on_build_stack`]), so obvhs' recursions never depend on the
//! stack of the caller (workers build inside tokio's `spawn_blocking` threads, 2 MiB).

use obvhs::aabb::Aabb;
use obvhs::bvh2::node::Bvh2Node;
use obvhs::bvh2::reinsertion::ReinsertionOptimizer;
use obvhs::bvh2::Bvh2;
#[cfg(test)]
use obvhs::cwbvh::bvh2_to_cwbvh::bvh2_to_cwbvh;
use obvhs::ploc::PlocBuilder;
use obvhs::ploc::PlocSearchDistance;
#[cfg(test)]
use obvhs::triangle::Triangle;
use obvhs::BvhBuildParams;

/// A primitive's box as the builds below read it: a box itself, or a PLOC leaf holding
/// one (so the triangle build needs no array of boxes beside its leaves).
trait HasBox {
    fn bbox(&self) -> Aabb;
}

impl HasBox for Aabb {
    #[inline(always)]
    fn bbox(&self) -> Aabb {
        *self
    }
}

impl HasBox for Bvh2Node {
    #[inline(always)]
    fn bbox(&self) -> Aabb {
        *self.aabb()
    }
}

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
    /// Chunks built by separate PLOC builds in levels of [`CHUNKED_FROM`] primitives or
    /// more (0 for smaller scenes; see "Memory" in the module docs).
    pub chunks: u64,
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
        self.chunks += other.chunks;
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
/// so [`to_cwbvh`] of it is the CWBVH that call returns. (The renderer builds from
/// leaves, [`leaves_bvh2`]; the tests compare against obvhs through this.)
#[cfg(test)]
pub(super) fn triangles_bvh2(triangles: &[Triangle], stats: &mut BvhBuildStats) -> Bvh2 {
    leaves_bvh2(
        triangles
            .iter()
            .enumerate()
            .map(|(i, t)| Bvh2Node::new(t.aabb(), 1, i as u32))
            .collect(),
        stats,
    )
}

/// [`triangles_bvh2`] given PLOC's leaves: `leaves[i]` holds primitive `i`'s box, with
/// one primitive, `i`. The leaves become PLOC's working array, so the build holds no
/// other copy of the boxes (see "Memory" in the module docs); the tree is the one
/// `PlocBuilder::build` makes of the same boxes, node for node.
pub(super) fn leaves_bvh2(leaves: Vec<Bvh2Node>, stats: &mut BvhBuildStats) -> Bvh2 {
    let bbox = |i: usize| leaves[i].bbox();
    let mut bvh2 = match crowded_cells(leaves.len(), bbox, stats) {
        None if tied_extents(leaves.len(), bbox, stats) => tie_broken_bvh2(&leaves, stats),
        None => {
            let p = params();
            let mut bvh2 = ploc_from_leaves(leaves, &p);
            ReinsertionOptimizer::default().run(&mut bvh2, p.reinsertion_batch_ratio, None);
            bvh2
        }
        Some(cells) => clustered_bvh2(&leaves, &cells, stats),
    };
    // The reinsertion's maps (parents, primitives to nodes, 12 bytes a primitive) are
    // not read again: free them before the order and the collapse.
    bvh2.parents = Vec::new();
    bvh2.primitives_to_nodes = Vec::new();
    bvh2
}

/// Levels of at least this many primitives are built in chunks ([`chunked_bvh2`]);
/// smaller ones, every scene below about 4 million triangles in one level, keep the
/// single PLOC build and so their trees, triangle numbers and images.
pub const CHUNKED_FROM: usize = 1 << 22;

/// The most primitives in one chunk of [`chunked_bvh2`]: PLOC's working arrays of a
/// chunk and its tree (144 bytes a primitive) are then at most 144 MiB beside the tree
/// being filled.
pub(super) const CHUNK_MAX: usize = 1 << 20;

/// A binary BVH over the `n` boxes `bbox(0..n)` (leaf `i` holds primitive `i`, as from
/// [`leaves_bvh2`]) that never holds PLOC's working arrays for all of them at once: with
/// `n >= chunked_from` and neither crowded cells nor tied extents among the boxes (those
/// take [`leaves_bvh2`]'s robust builds, over every box at once), the primitives are
/// split top down at the median of their box centres along the widest axis into
/// `⌈n / chunk_max⌉` chunks of about equal size (the top of the tree: compact chunks
/// whose centres do not overlap, as a spatial-median build's upper levels), and each
/// chunk built as a level of its own is, by PLOC and obvhs' reinsertion with the usual
/// parameters, then copied into the final node array. PLOC merges each cluster with a
/// neighbour within its search radius in the Morton order (Meister & Bittner 2018, §3),
/// so within a chunk the merges are much like the single build's. The reinsertion runs
/// per chunk rather than once over the whole tree: obvhs takes its candidates from the
/// start of the node array, which a single PLOC build fills with the top of the tree but
/// which here holds the first chunk. Below `chunked_from`, or on the robust paths, it is
/// [`leaves_bvh2`] of the boxes.
///
/// Memory: one PLOC build of all `n` holds its two node arrays and sort keys beside the
/// tree (80 + 64 bytes a primitive) at its end; this holds
/// the primitives' order (4 bytes a primitive), the tree (64) and one chunk's PLOC arrays
/// (docs/benchmarks.md, "Large scene"). The tree is not the single build's, so the
/// triangles' numbers (their CWBVH leaf order) differ and images can differ where
/// two triangles are hit at exactly the same distance.
pub(super) fn chunked_bvh2(
    n: usize,
    bbox: impl Fn(usize) -> Aabb,
    chunked_from: usize,
    chunk_max: usize,
    stats: &mut BvhBuildStats,
) -> Bvh2 {
    let leaves = |bbox: &dyn Fn(usize) -> Aabb| -> Vec<Bvh2Node> {
        (0..n)
            .map(|i| Bvh2Node::new(bbox(i), 1, i as u32))
            .collect()
    };
    if n < chunked_from.max(2) {
        return leaves_bvh2(leaves(&bbox), stats);
    }
    // The robust builds' checks, on the boxes as read: if either finds its input, the
    // whole level takes [`leaves_bvh2`] (which counts its own checks).
    let mut probe = *stats;
    let crowded = crowded_cells(n, &bbox, &mut probe).is_some();
    if crowded || tied_extents(n, &bbox, &mut probe) {
        return leaves_bvh2(leaves(&bbox), stats);
    }
    *stats = probe;
    let count = n.div_ceil(chunk_max.max(1));
    let mut chunks = Chunks {
        order: (0..n as u32).collect(),
        bbox: &bbox,
        // Every node of the finished tree, reserved once: pages are resident only as
        // chunks are copied in.
        nodes: Vec::with_capacity(2 * n - 1),
        max_depth: 0,
        work: 0,
    };
    chunks.nodes.push(Bvh2Node::default());
    chunks.build(count, 0..n, 0, 0);
    debug_assert_eq!(chunks.nodes.len(), 2 * n - 1);
    stats.chunks += count as u64;
    stats.work += chunks.work;
    let Chunks {
        nodes, max_depth, ..
    } = chunks;
    Bvh2 {
        nodes,
        // Leaves name their primitive directly (`first_index`), through the identity.
        primitive_indices: (0..n as u32).collect(),
        max_depth: max_depth.max(obvhs::bvh2::DEFAULT_MAX_STACK_DEPTH),
        ..Bvh2::default()
    }
}

/// The state of [`chunked_bvh2`]'s build: the primitives (`order`, split in place into
/// chunks), and the tree's nodes so far.
struct Chunks<'a, F> {
    order: Vec<u32>,
    bbox: &'a F,
    nodes: Vec<Bvh2Node>,
    max_depth: usize,
    /// One step per primitive per level of the splits above the chunks.
    work: u64,
}

impl<F: Fn(usize) -> Aabb> Chunks<'_, F> {
    /// Builds the primitives `order[range]` as `count` chunks into the subtree rooted at
    /// `slot` (`depth` below the root): split at the median of their box centres along
    /// the widest axis (the share of `count / 2` chunks of them on one side), down to
    /// single chunks; returns the subtree's box.
    fn build(
        &mut self,
        count: usize,
        range: std::ops::Range<usize>,
        slot: usize,
        depth: usize,
    ) -> Aabb {
        if count <= 1 {
            return self.chunk(range, slot, depth);
        }
        let members = &mut self.order[range.clone()];
        let centre = |i: u32| (self.bbox)(i as usize).center();
        let mut centres = Aabb::empty();
        for &i in members.iter() {
            centres.extend(centre(i));
        }
        let spread = centres.diagonal();
        let axis = if spread.x >= spread.y && spread.x >= spread.z {
            0
        } else if spread.y >= spread.z {
            1
        } else {
            2
        };
        let left_count = count / 2;
        let mid = members.len() * left_count / count;
        // Keys of 8 bytes for the selection, so the boxes are read once a level.
        let mut keys: Vec<(f32, u32)> = members.iter().map(|&i| (centre(i)[axis], i)).collect();
        keys.select_nth_unstable_by(mid, |a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        for (m, &(_, i)) in members.iter_mut().zip(&keys) {
            *m = i;
        }
        drop(keys);
        self.work += members.len() as u64;
        let first = self.nodes.len();
        self.nodes.push(Bvh2Node::default());
        self.nodes.push(Bvh2Node::default());
        let split = range.start + mid;
        let left = self.build(left_count, range.start..split, first, depth + 1);
        let right = self.build(count - left_count, split..range.end, first + 1, depth + 1);
        let bounds = left.union(&right);
        self.nodes[slot] = Bvh2Node::new(bounds, 0, first as u32);
        bounds
    }

    /// PLOC over the chunk `order[range]` (in index order, so the chunk's tree does not
    /// depend on how the splits arranged it), its root written at `slot` and its other
    /// nodes appended, renumbered: interior children by where they land, leaves by the
    /// primitive they hold.
    fn chunk(&mut self, range: std::ops::Range<usize>, slot: usize, depth: usize) -> Aabb {
        let members = &mut self.order[range];
        members.sort_unstable();
        let members = &*members;
        let leaves: Vec<Bvh2Node> = members
            .iter()
            .enumerate()
            .map(|(j, &i)| Bvh2Node::new((self.bbox)(i as usize), 1, j as u32))
            .collect();
        let p = params();
        let mut tree = ploc_from_leaves(leaves, &p);
        ReinsertionOptimizer::default().run(&mut tree, p.reinsertion_batch_ratio, None);
        self.max_depth = self.max_depth.max(depth + tree.max_depth);
        // Chunk node `j >= 1` lands at `base + j - 1`.
        let base = self.nodes.len();
        let renumber = |node: &Bvh2Node| {
            let first = if node.is_leaf() {
                members[node.first_index as usize]
            } else {
                (base + node.first_index as usize - 1) as u32
            };
            Bvh2Node::new(*node.aabb(), node.prim_count, first)
        };
        let root = renumber(&tree.nodes[0]);
        self.nodes.extend(tree.nodes[1..].iter().map(renumber));
        self.nodes[slot] = root;
        *root.aabb()
    }
}

/// PLOC over `leaves` (leaf `i` holding primitive `i`) with the parameters `p`: what
/// `PlocBuilder::build` does with the leaves' boxes and the identity as indices (it sets
/// the tree's primitive indices, makes one leaf node per box and sums the boxes into the
/// scene's box in index order, then merges), without the slice of boxes it would read.
///
/// Memory: the tree's nodes are allocated zeroed (`Bvh2::zeroed`), so their pages become
/// resident only as PLOC writes them, from the last pair to the root, and the identity
/// primitive indices (PLOC does not read them: a leaf names its primitive) are made once
/// PLOC's working arrays are freed. What is resident at the end of PLOC, its peak, is
/// then its two node arrays and sort keys (80 bytes a primitive) and the tree's nodes
/// (64); see docs/benchmarks.md, "Large scene".
fn ploc_from_leaves(leaves: Vec<Bvh2Node>, p: &BvhBuildParams) -> Bvh2 {
    let n = leaves.len();
    let mut bvh2 = Bvh2::zeroed(n);
    bvh2.primitive_indices = Vec::new();
    if n == 0 {
        return bvh2;
    }
    let mut total = Aabb::empty();
    for leaf in &leaves {
        let b = leaf.aabb();
        total.extend(b.min);
        total.extend(b.max);
    }
    let mut builder = PlocBuilder::new();
    builder.current_nodes = leaves;
    let (precision, depth) = (p.sort_precision, p.search_depth_threshold);
    match p.ploc_search_distance {
        PlocSearchDistance::Minimum => {
            builder.build_ploc_from_leaves::<1, false>(&mut bvh2, total, precision, depth)
        }
        PlocSearchDistance::VeryLow => {
            builder.build_ploc_from_leaves::<2, false>(&mut bvh2, total, precision, depth)
        }
        PlocSearchDistance::Low => {
            builder.build_ploc_from_leaves::<6, false>(&mut bvh2, total, precision, depth)
        }
        PlocSearchDistance::Medium => {
            builder.build_ploc_from_leaves::<14, false>(&mut bvh2, total, precision, depth)
        }
        PlocSearchDistance::High => {
            builder.build_ploc_from_leaves::<24, false>(&mut bvh2, total, precision, depth)
        }
        PlocSearchDistance::VeryHigh => {
            builder.build_ploc_from_leaves::<32, false>(&mut bvh2, total, precision, depth)
        }
    }
    drop(builder);
    bvh2.primitive_indices = (0..n as u32).collect();
    bvh2
}

/// A binary BVH over `boxes` (instances' world bounds, moving triangles' swept
/// bounds): the tree obvhs' `build_cwbvh` of the same boxes converts (PLOC, then
/// reinsertion) for ordinary input, the clustered or tie-broken build otherwise, as for
/// triangles ([`leaves_bvh2`]).
pub(super) fn boxes_bvh2(boxes: &[Aabb], stats: &mut BvhBuildStats) -> Bvh2 {
    leaves_bvh2(
        boxes
            .iter()
            .enumerate()
            .map(|(i, b)| Bvh2Node::new(*b, 1, i as u32))
            .collect(),
        stats,
    )
}

/// Replaces the box of every leaf of `bvh2` by `widen(primitive, box)` for each of its
/// primitives (unioned), and every interior box by the union of its children's, bottom
/// up: the tree stays nested (each box contains its children's) whatever `widen` does,
/// and its shape, so the order that numbers the primitives, does not change.
pub(super) fn widen_boxes(bvh2: &mut Bvh2, widen: impl Fn(u32, Aabb) -> Aabb) {
    if bvh2.nodes.is_empty() {
        return;
    }
    let mut stack: Vec<(usize, bool)> = vec![(0, false)];
    while let Some((i, done)) = stack.pop() {
        let node = bvh2.nodes[i];
        let first = node.first_index as usize;
        let bounds = if node.is_leaf() {
            let mut b = Aabb::empty();
            for &p in &bvh2.primitive_indices[first..first + node.prim_count as usize] {
                b = b.union(&widen(p, *node.aabb()));
            }
            b
        } else if done {
            bvh2.nodes[first].aabb().union(bvh2.nodes[first + 1].aabb())
        } else {
            stack.push((i, true));
            stack.push((first, false));
            stack.push((first + 1, false));
            continue;
        };
        bvh2.nodes[i] = Bvh2Node::new(bounds, node.prim_count, node.first_index);
    }
}

/// obvhs' CWBVH of a binary BVH, with the leaf size its builders use (the reference the
/// tests compare the leaf order with).
#[cfg(test)]
pub(super) fn to_cwbvh(bvh2: &Bvh2) -> obvhs::cwbvh::CwBvh {
    bvh2_to_cwbvh(bvh2, params().max_prims_per_leaf.clamp(1, 3), true, false)
}

/// `⌈log2 n⌉` (0 for `n <= 1`).
fn ceil_log2(n: usize) -> u64 {
    u64::from(usize::BITS - n.saturating_sub(1).leading_zeros())
}

/// The centre cell of every box `bbox(0..n)`, as `(cell, index)` sorted, when some cell holds
/// [`CLUSTER_MIN`] boxes or more; `None` otherwise (the ordinary path). Counts the
/// primitives and the grouping work in `stats`.
fn crowded_cells(
    n: usize,
    bbox: impl Fn(usize) -> Aabb,
    stats: &mut BvhBuildStats,
) -> Option<Vec<(u64, u32)>> {
    stats.bvhs += 1;
    stats.primitives += n as u64;
    stats.work += n as u64 * ceil_log2(n) + n as u64;
    if n < CLUSTER_MIN {
        stats.ploc_inputs += n as u64;
        return None;
    }
    let mut total = Aabb::empty();
    for i in 0..n {
        let b = bbox(i);
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
    let mut keys: Vec<(u64, u32)> = (0..n)
        .map(|i| {
            let c = bbox(i).center().as_dvec3();
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

/// Whether [`TIE_MIN`] or more of the boxes `bbox(0..n)` have bit-identical extents (the input that
/// ties PLOC's costs without crowding a cell; see the module docs). Counts its sort in
/// `stats.work`.
fn tied_extents(n: usize, bbox: impl Fn(usize) -> Aabb, stats: &mut BvhBuildStats) -> bool {
    if n < TIE_MIN {
        return false;
    }
    stats.work += n as u64 * ceil_log2(n) + n as u64;
    let mut extents: Vec<[u32; 3]> = (0..n)
        .map(|i| {
            let b = bbox(i);
            (b.max - b.min).to_array().map(f32::to_bits)
        })
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
fn tie_broken_bvh2<B: HasBox>(boxes: &[B], stats: &mut BvhBuildStats) -> Bvh2 {
    let padded: Vec<Aabb> = boxes
        .iter()
        .enumerate()
        .map(|(i, b)| {
            let b = &b.bbox();
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
fn clustered_bvh2<B: HasBox>(boxes: &[B], cells: &[(u64, u32)], stats: &mut BvhBuildStats) -> Bvh2 {
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
                bounds = bounds.union(&boxes[i as usize].bbox());
            }
            items.push((start, members.len() as u32));
            item_boxes.push(bounds);
            stats.clusters += 1;
            stats.clustered += run.len() as u64;
        } else {
            for &(_, i) in run {
                items.push((members.len() as u32, members.len() as u32 + 1));
                members.push(i);
                item_boxes.push(boxes[i as usize].bbox());
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
fn median_subtree<B: HasBox>(
    members: &mut [u32],
    boxes: &[B],
    nodes: &mut Vec<Bvh2Node>,
    slot: usize,
    work: &mut u64,
) -> u32 {
    let centre = |i: u32| boxes[i as usize].bbox().center();
    let mut max_depth = 0;
    let mut stack: Vec<(usize, usize, usize, u32)> = vec![(0, members.len(), slot, 0)];
    while let Some((start, end, slot, depth)) = stack.pop() {
        max_depth = max_depth.max(depth);
        let range = &mut members[start..end];
        *work += range.len() as u64;
        if let [only] = range {
            nodes[slot] = Bvh2Node::new(boxes[*only as usize].bbox(), 1, *only);
            continue;
        }
        let mut bounds = Aabb::empty();
        let mut centres = Aabb::empty();
        for &m in range.iter() {
            bounds = bounds.union(&boxes[m as usize].bbox());
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

/// The order in which [`to_cwbvh`] of `bvh2` lists the primitives (its
/// `primitive_indices`), computed without the CWBVH: what the triangle build keeps of the
/// conversion (the leaf order that numbers triangles, see `triangle_bvh`).
///
/// obvhs' conversion (`Bvh2Converter`, after Ylitie, Karras & Laine 2017, §4, "cost
/// table" and "child ordering") fills a table of 7 decisions of 8 bytes for every binary
/// node (112 bytes per primitive) and builds the 80-byte CWBVH nodes; this is the same
/// dynamic programme with the same floating-point operations in the same order, but its
/// costs live on the recursion's stack (a node's costs are only read by its parent) and
/// each decision is one byte (kind, and which split of the child budget goes left and
/// right), 7 bytes per internal node; a leaf's decisions are all "leaf" and are not
/// stored. The walk that lists the primitives is the conversion's own: each node's
/// children gathered by the decisions, ordered by the greedy octant assignment, leaves
/// listed in slot order as they are met and internal children visited afterwards.
/// The tests check the order against obvhs' on ordinary, clustered and tie-broken trees.
pub(super) fn cwbvh_order(bvh2: &Bvh2) -> Vec<u32> {
    if bvh2.nodes.is_empty() {
        return Vec::new();
    }
    let max_prims_per_leaf = params().max_prims_per_leaf.clamp(1, 3);
    let mut order = CwbvhOrder {
        bvh2,
        decisions: vec![[0u8; 7]; bvh2.nodes.len()],
        primitives: Vec::with_capacity(bvh2.primitive_indices.len()),
    };
    order.cost(0, max_prims_per_leaf);
    order.convert(0);
    order.primitives
}

/// A decision's kind, as obvhs' `DecisionKind`.
const KIND_LEAF: u8 = 0;
const KIND_INTERNAL: u8 = 1;
const KIND_DISTRIBUTE: u8 = 2;
/// obvhs' "no split" marker (`u8::MAX`), stored in 3 bits as 7.
const SPLIT_NONE: u8 = 7;
/// obvhs' `PRIM_COST`: the SAH cost of a primitive relative to a node.
const PRIM_COST: f32 = 0.3;

/// The state of [`cwbvh_order`]: per binary node 7 decisions of one byte each
/// (kind in bits 6-7, left split in bits 3-5, right split in bits 0-2).
struct CwbvhOrder<'a> {
    bvh2: &'a Bvh2,
    decisions: Vec<[u8; 7]>,
    primitives: Vec<u32>,
}

/// One decision: kind, and the child budgets of its left and right subtrees.
#[derive(Clone, Copy)]
struct Decision {
    cost: f32,
    kind: u8,
    left: u8,
    right: u8,
}

impl CwbvhOrder<'_> {
    /// obvhs' `calculate_cost_impl`: fills `node`'s decisions and returns its 7 costs
    /// and its primitive count.
    fn cost(&mut self, node_index: usize, max_prims_per_leaf: u32) -> ([f32; 7], u32) {
        let node = &self.bvh2.nodes[node_index];
        let half_area = node.aabb().half_area();
        let first_index = node.first_index as usize;
        let prim_count = node.prim_count;
        if prim_count != 0 {
            // Leaves hold one primitive (PLOC's and our grafted trees' alike).
            assert!(prim_count == 1, "leaves must hold one primitive");
            let cost_leaf = half_area * (prim_count as f32) * PRIM_COST;
            return ([cost_leaf; 7], prim_count);
        }
        let (left, n_left) = self.cost(first_index, max_prims_per_leaf);
        let (right, n_right) = self.cost(first_index + 1, max_prims_per_leaf);
        let num_primitives = n_left + n_right;
        let mut d = [Decision {
            cost: 0.0,
            kind: KIND_DISTRIBUTE,
            left: 0,
            right: 0,
        }; 7];
        {
            let cost_leaf = if num_primitives <= max_prims_per_leaf {
                (num_primitives as f32) * half_area * PRIM_COST
            } else {
                f32::INFINITY
            };
            let mut cost_distribute = f32::INFINITY;
            let (mut dl, mut dr) = (u8::MAX, u8::MAX);
            for k in 0..7 {
                let c = left[k] + right[6 - k];
                if c < cost_distribute {
                    cost_distribute = c;
                    dl = k as u8;
                    dr = 6 - k as u8;
                }
            }
            let cost_internal = cost_distribute + half_area;
            if cost_leaf < cost_internal {
                d[0].kind = KIND_LEAF;
                d[0].cost = cost_leaf;
            } else {
                d[0].kind = KIND_INTERNAL;
                d[0].cost = cost_internal;
            }
            d[0].left = dl;
            d[0].right = dr;
        }
        for i in 1..7 {
            let mut cost_distribute = d[i - 1].cost;
            let (mut dl, mut dr) = (u8::MAX, u8::MAX);
            for k in 0..i {
                let c = left[k] + right[i - k - 1];
                if c < cost_distribute {
                    cost_distribute = c;
                    dl = k as u8;
                    dr = i as u8 - k as u8 - 1;
                }
            }
            d[i].cost = cost_distribute;
            if dl != u8::MAX {
                d[i].kind = KIND_DISTRIBUTE;
                d[i].left = dl;
                d[i].right = dr;
            } else {
                d[i] = d[i - 1];
            }
        }
        let pack = |s: u8| if s == u8::MAX { SPLIT_NONE } else { s };
        self.decisions[node_index] = d.map(|d| (d.kind << 6) | (pack(d.left) << 3) | pack(d.right));
        (d.map(|d| d.cost), num_primitives)
    }

    /// Decision `flat` of obvhs' table (`node * 7 + i`): kind, left split, right split.
    fn decision(&self, flat: usize) -> (u8, usize, usize) {
        let (node, i) = (flat / 7, flat % 7);
        if self.bvh2.nodes[node].is_leaf() {
            return (KIND_LEAF, 0, 0);
        }
        let b = self.decisions[node][i];
        let unpack = |s: u8| {
            if s == SPLIT_NONE {
                u8::MAX as usize
            } else {
                s as usize
            }
        };
        (b >> 6, unpack((b >> 3) & 7), unpack(b & 7))
    }

    /// obvhs' `get_children`.
    fn children(&self, node_index: usize, children: &mut [u32; 8], count: &mut usize, i: usize) {
        let node = &self.bvh2.nodes[node_index];
        if node.is_leaf() {
            children[*count] = node_index as u32;
            *count += 1;
            return;
        }
        let (_, left, right) = self.decision(node_index * 7 + i);
        let first = node.first_index as usize;
        for (child, split) in [(first, left), (first + 1, right)] {
            if self.decision(child * 7 + split).0 == KIND_DISTRIBUTE {
                self.children(child, children, count, split);
            } else {
                children[*count] = child as u32;
                *count += 1;
            }
        }
    }

    /// obvhs' `order_children`: the children's greedy assignment to the 8 octant slots.
    fn order_children(&self, node_index: usize, children: &mut [u32; 8], count: usize) {
        let p = self.bvh2.nodes[node_index].aabb().center();
        let mut cost = [[f32::MAX; 8]; 8];
        for (s, d) in (0..8usize).map(|s| {
            (
                s,
                glam::Vec3A::new(
                    if s & 0b100 != 0 { -1.0 } else { 1.0 },
                    if s & 0b010 != 0 { -1.0 } else { 1.0 },
                    if s & 0b001 != 0 { -1.0 } else { 1.0 },
                ),
            )
        }) {
            for c in 0..count {
                let v = self.bvh2.nodes[children[c] as usize].aabb().center() - p;
                cost[c][s] = d.dot(v);
            }
        }
        let mut assignment = [usize::MAX; 8];
        let mut slot_filled = [false; 8];
        loop {
            let mut min_cost = f32::MAX;
            let (mut min_slot, mut min_index) = (usize::MAX, usize::MAX);
            for c in 0..count {
                if assignment[c] == usize::MAX {
                    for (s, &filled) in slot_filled.iter().enumerate() {
                        if !filled && cost[c][s] < min_cost {
                            min_cost = cost[c][s];
                            min_slot = s;
                            min_index = c;
                        }
                    }
                }
            }
            if min_slot == usize::MAX {
                break;
            }
            slot_filled[min_slot] = true;
            assignment[min_index] = min_slot;
        }
        let original = std::mem::replace(children, [u32::MAX; 8]);
        for i in 0..count {
            children[assignment[i]] = original[i];
        }
    }

    /// obvhs' `convert_to_cwbvh_impl`, keeping only the primitive order.
    fn convert(&mut self, node_index: usize) {
        let mut children = [u32::MAX; 8];
        let mut count = 0;
        self.children(node_index, &mut children, &mut count, 0);
        self.order_children(node_index, &mut children, count);
        let mut internal = [false; 8];
        for (slot, &child) in children.iter().enumerate() {
            if child == u32::MAX {
                continue;
            }
            match self.decision(child as usize * 7).0 {
                KIND_LEAF => self.list_primitives(child as usize),
                _ => internal[slot] = true,
            }
        }
        for (slot, &child) in children.iter().enumerate() {
            if child != u32::MAX && internal[slot] {
                self.convert(child as usize);
            }
        }
    }

    /// obvhs' `count_primitives`: the primitives under `node_index`, left before right.
    fn list_primitives(&mut self, node_index: usize) {
        let node = self.bvh2.nodes[node_index];
        if node.is_leaf() {
            self.primitives
                .push(self.bvh2.primitive_indices[node.first_index as usize]);
            return;
        }
        self.list_primitives(node.first_index as usize);
        self.list_primitives(node.first_index as usize + 1);
    }
}
