//! A light hierarchy: a bounding volume hierarchy over the emitters, for choosing the light
//! of next-event estimation by its estimated contribution to a reference point rather than
//! by its power alone (Conty Estevez & Kulla 2018, "Importance Sampling of Many Lights with
//! Adaptive Tree Splitting", sections 4 and 5; as pbrt-v4's `BVHLightSampler`, Pharr, Jakob
//! & Humphreys 2023, section 12.6.3). Shirley 2001, chapter 3, notes that with many lights
//! most shadow rays go to lights that contribute little; here a triangle facing away from
//! the point, or far from it, is rarely chosen.
//!
//! # What a node stores
//!
//! [`LightBounds`]: the total power `φ` of its lights (luminance), their spatial bounding
//! box, and an orientation cone: an axis `w` and angles `θ_o` (every emitter's normal is
//! within `θ_o` of `w`) and `θ_e` (each emits only within `θ_e` of its normal; `π/2` for a
//! Lambertian surface), with `two_sided` when some light emits on both sides.
//!
//! # Selection
//!
//! From the root, a child is chosen with probability proportional to its importance at the
//! reference point ([`LightBounds::importance`]); the probability of a light is the product
//! of the choices on its path. The path of every light is stored as a bit trail (bit `k`
//! is the choice at depth `k`, 1 for the second child), so [`LightTree::pmf`] walks only
//! that path, `O(depth)`, and recomputes the same importances in the same order: it returns
//! bit for bit the probability [`LightTree::select`] multiplied up. A child of zero
//! importance is never chosen (its lights cannot light the point: they lie behind it or
//! face away from it); when both children of a node have zero importance there is no
//! sample. Multiple importance sampling stays unbiased as long as this pmf is the one the
//! BSDF-sampled technique is weighted against (Veach & Guibas 1995).
//!
//! Infinite lights (environment, directional) have no position: they are chosen before the
//! tree, each with its probability in the global power-proportional distribution
//! ([`super::LightSet::pmf`]), and the tree shares the remaining probability. Lights with
//! no power are in neither and have probability 0.
//!
//! # Determinism
//!
//! The tree is a pure function of the light list: built sequentially, split by the binned
//! surface-area-orientation heuristic of Conty Estevez & Kulla 2018 (section 4.4) on the
//! light centroids with ties broken by the first axis and bucket, partitions stable, and a
//! median split by light order when no split helps or the tree gets deep.
//! Traversal allocates nothing.

use super::Light;
use glam::Vec3;
use std::f32::consts::PI;

/// Number of buckets per axis of the binned split.
const BUCKETS: usize = 12;
/// Depth beyond which splits are median splits by light order, so that every trail fits
/// in 64 bits (40 + log2(2^24 lights) < 64).
const MAX_HEURISTIC_DEPTH: u32 = 40;
/// A trail that marks a light outside the tree.
const NOT_IN_TREE: u64 = u64::MAX;
/// Slack (radians) added to merged orientation cones: rounding must never make a cone
/// exclude a child's normal, or a node could wrongly get zero importance.
const CONE_SLACK: f32 = 1e-4;

/// Bounds of a set of emitters: their power, where they are and which way they emit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LightBounds {
    /// Lower corner of the bounding box.
    pub min: Vec3,
    /// Upper corner of the bounding box.
    pub max: Vec3,
    /// Axis of the cone of emitter normals (unit).
    pub w: Vec3,
    /// Total emitted power (luminance).
    pub phi: f32,
    /// `cos θ_o`: every normal is within `θ_o` of `w`.
    pub cos_theta_o: f32,
    /// `cos θ_e`: every emitter emits within `θ_e` of its normal.
    pub cos_theta_e: f32,
    /// Some emitter emits on both sides of its surface.
    pub two_sided: bool,
}

/// `cos(max(0, a - b))` from the sines and cosines of two angles in `[0, π]`.
#[inline]
fn cos_sub_clamped(sin_a: f32, cos_a: f32, sin_b: f32, cos_b: f32) -> f32 {
    if cos_a > cos_b {
        1.0
    } else {
        cos_a * cos_b + sin_a * sin_b
    }
}

/// `sin(max(0, a - b))` from the sines and cosines of two angles in `[0, π]`.
#[inline]
fn sin_sub_clamped(sin_a: f32, cos_a: f32, sin_b: f32, cos_b: f32) -> f32 {
    if cos_a > cos_b {
        0.0
    } else {
        sin_a * cos_b - cos_a * sin_b
    }
}

#[inline]
fn safe_sqrt(x: f32) -> f32 {
    x.max(0.0).sqrt()
}

impl LightBounds {
    /// The bounds of one light, `None` for infinite lights and lights without power.
    pub fn of(light: &Light) -> Option<Self> {
        let phi = light.power();
        if !(phi > 0.0 && phi.is_finite()) {
            return None;
        }
        // Emitters that radiate in every direction: the whole sphere of normals.
        let omni = |min: Vec3, max: Vec3| LightBounds {
            min,
            max,
            w: Vec3::Z,
            phi,
            cos_theta_o: -1.0,
            cos_theta_e: 0.0,
            two_sided: false,
        };
        match light {
            Light::Triangle(t) => Some(LightBounds {
                min: t.p[0].min(t.p[1]).min(t.p[2]),
                max: t.p[0].max(t.p[1]).max(t.p[2]),
                w: t.n,
                phi,
                cos_theta_o: 1.0,
                // Lambertian: emits up to 90° from its normal.
                cos_theta_e: 0.0,
                two_sided: t.two_sided,
            }),
            Light::Sphere(s) => Some(omni(
                s.center - Vec3::splat(s.radius),
                s.center + Vec3::splat(s.radius),
            )),
            // A spot light is bounded as a point light: exact, if less selective.
            Light::Punctual(super::punctual::Punctual::Point { position, .. })
            | Light::Punctual(super::punctual::Punctual::Spot { position, .. }) => {
                Some(omni(*position, *position))
            }
            Light::Punctual(super::punctual::Punctual::Directional { .. })
            | Light::Environment(_) => None,
        }
    }

    /// The bounds of the union of two sets (Conty Estevez & Kulla 2018, section 4.1): the
    /// box union, the sum of powers, the smallest cone around both cones (slightly widened
    /// against rounding), the widest emission angle.
    pub fn union(&self, o: &LightBounds) -> LightBounds {
        Angled::of(*self).union(&Angled::of(*o)).bounds
    }

    /// [`LightBounds::union`] given the cone angles `θ_o` of both (the axis and `cos θ_o`
    /// of the union, and its `θ_o`).
    #[inline]
    fn union_with(&self, theta_a: f32, o: &LightBounds, theta_b: f32) -> (LightBounds, f32) {
        let (w, cos_theta_o, theta_o) = cone_union(
            self.w,
            self.cos_theta_o,
            theta_a,
            o.w,
            o.cos_theta_o,
            theta_b,
        );
        let bounds = LightBounds {
            min: self.min.min(o.min),
            max: self.max.max(o.max),
            w,
            phi: self.phi + o.phi,
            cos_theta_o,
            cos_theta_e: self.cos_theta_e.min(o.cos_theta_e),
            two_sided: self.two_sided || o.two_sided,
        };
        (bounds, theta_o)
    }

    fn centroid(&self) -> Vec3 {
        0.5 * (self.min + self.max)
    }

    /// A conservative estimate of the contribution of these lights to a point `p` with
    /// normal `n` (`Vec3::ZERO` for no normal: a transmissive surface or a medium), after
    /// Conty Estevez & Kulla 2018, section 5.1, in the form of pbrt-v4's
    /// `LightBounds::Importance`: `φ cos θ' / d²`, where `θ'` is the smallest angle any
    /// emitter normal in the cone can make with any direction from the box toward `p`
    /// (the angle to the box centre minus `θ_o` minus the half-angle `θ_b` the box's bounding
    /// sphere subtends from `p`), and zero when `θ' >= θ_e` (no emitter faces `p`). With a
    /// normal, it is multiplied by the bound `cos(max(0, θ_i - θ_b))` of the receiver's
    /// `|cos θ_i|`: two-sided, since opaque lobes reflect on both sides of a surface.
    /// `d²` is clamped below by half the box diagonal, as pbrt does, so that points inside
    /// a node do not get unbounded importance.
    #[inline]
    pub fn importance(&self, p: Vec3, n: Vec3) -> f32 {
        self.importance_with(&Shape::of(self), p, n)
    }

    /// [`LightBounds::importance`] with the point-independent part precomputed.
    #[inline]
    fn importance_with(&self, shape: &Shape, p: Vec3, n: Vec3) -> f32 {
        let pc = shape.centroid;
        let d2_center = p.distance_squared(pc);
        let d2 = d2_center.max(shape.half_diagonal).max(f32::MIN_POSITIVE);
        let wi = (p - pc).normalize_or_zero();
        let mut cos_w = self.w.dot(wi);
        if self.two_sided {
            cos_w = cos_w.abs();
        }
        let sin_w = safe_sqrt(1.0 - cos_w * cos_w);
        // θ_b: the cone of directions the box's bounding sphere subtends from p.
        let r2 = shape.r2;
        let cos_b = if d2_center <= r2 {
            -1.0
        } else {
            safe_sqrt(1.0 - r2 / d2_center)
        };
        let sin_b = safe_sqrt(1.0 - cos_b * cos_b);
        // θ' = max(0, θ_w - θ_o - θ_b).
        let sin_o = shape.sin_o;
        let cos_x = cos_sub_clamped(sin_w, cos_w, sin_o, self.cos_theta_o);
        let sin_x = sin_sub_clamped(sin_w, cos_w, sin_o, self.cos_theta_o);
        let cos_p = cos_sub_clamped(sin_x, cos_x, sin_b, cos_b);
        if cos_p <= self.cos_theta_e {
            return 0.0;
        }
        let mut importance = self.phi * cos_p / d2;
        if n != Vec3::ZERO {
            let cos_i = wi.dot(n).abs();
            let sin_i = safe_sqrt(1.0 - cos_i * cos_i);
            importance *= cos_sub_clamped(sin_i, cos_i, sin_b, cos_b);
        }
        if importance.is_nan() {
            0.0
        } else {
            importance.clamp(0.0, f32::MAX)
        }
    }

    /// The surface-area-orientation cost of a set of lights (Conty Estevez & Kulla 2018,
    /// section 4.4): power times the orientation measure `M_Ω` times the surface area of
    /// the box, times `kr`, which favours splitting a long parent box across its length.
    fn cost(&self, theta_o: f32, theta_e: f32, kr: f32) -> f32 {
        let theta_w = (theta_o + theta_e).min(PI);
        let sin_o = theta_o.sin();
        let m_omega = 2.0 * PI * (1.0 - self.cos_theta_o)
            + PI / 2.0
                * (2.0 * theta_w * sin_o - (theta_o - 2.0 * theta_w).cos() - 2.0 * theta_o * sin_o
                    + self.cos_theta_o);
        let d = self.max - self.min;
        let area = 2.0 * (d.x * d.y + d.y * d.z + d.z * d.x);
        // Points and flat boxes have no area: keep their cost comparable by power.
        self.phi * m_omega * kr * area.max(1e-12)
    }
}

/// The parts of [`LightBounds::importance`] that depend on the bounds only, computed once
/// per tree node rather than at every visit of every shading point.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Shape {
    /// Centre of the box.
    centroid: Vec3,
    /// Half the box diagonal's length: the floor of the squared distance.
    half_diagonal: f32,
    /// Squared radius of the box's bounding sphere.
    r2: f32,
    /// `sin θ_o`.
    sin_o: f32,
}

impl Shape {
    #[inline]
    fn of(b: &LightBounds) -> Self {
        let diag = b.max - b.min;
        Shape {
            centroid: b.centroid(),
            half_diagonal: 0.5 * diag.length(),
            r2: 0.25 * diag.length_squared(),
            sin_o: safe_sqrt(1.0 - b.cos_theta_o * b.cos_theta_o),
        }
    }
}

/// The angle between two unit vectors.
#[inline]
fn angle_between(a: Vec3, b: Vec3) -> f32 {
    a.cross(b).length().atan2(a.dot(b))
}

/// `θ` of `cos θ`, clamped against rounding.
#[inline]
fn angle_of(cos: f32) -> f32 {
    cos.clamp(-1.0, 1.0).acos()
}

/// The smallest cone containing two cones given by axis, `cos θ` and `θ` (the
/// direction-cone union of Conty Estevez & Kulla 2018, section 4.1, algorithm 1): its
/// axis, `cos θ` and `θ`. The angles come with the cones, `θ = angle_of(cos θ)`, so that
/// building a tree computes each once rather than at every union and cost.
fn cone_union(
    wa: Vec3,
    cos_a: f32,
    theta_a: f32,
    wb: Vec3,
    cos_b: f32,
    theta_b: f32,
) -> (Vec3, f32, f32) {
    let theta_d = angle_between(wa, wb);
    if (theta_d + theta_b).min(PI) <= theta_a {
        return (wa, cos_a, theta_a);
    }
    if (theta_d + theta_a).min(PI) <= theta_b {
        return (wb, cos_b, theta_b);
    }
    let theta_o = 0.5 * (theta_a + theta_d + theta_b) + CONE_SLACK;
    if theta_o >= PI {
        return (wa, -1.0, angle_of(-1.0));
    }
    let axis = wa.cross(wb);
    if axis.length_squared() == 0.0 {
        return (wa, -1.0, angle_of(-1.0));
    }
    // Rotate wa toward wb by θ_o - θ_a about their common normal (Rodrigues; the axis is
    // orthogonal to wa).
    let k = axis.normalize();
    let (s, c) = (theta_o - theta_a).sin_cos();
    let w = (wa * c + k.cross(wa) * s).normalize();
    // The stored cosine is what the tree keeps; its angle is taken from it (not θ_o
    // itself), as every later use of the cone would.
    let cos_o = theta_o.cos();
    (w, cos_o, angle_of(cos_o))
}

/// [`LightBounds`] with the angles of its cones, `θ_o` and `θ_e`, as the build needs
/// them at every union and cost.
#[derive(Clone, Copy, Debug)]
struct Angled {
    bounds: LightBounds,
    theta_o: f32,
    theta_e: f32,
}

impl Angled {
    fn of(bounds: LightBounds) -> Self {
        Angled {
            bounds,
            theta_o: angle_of(bounds.cos_theta_o),
            theta_e: angle_of(bounds.cos_theta_e),
        }
    }

    #[inline]
    fn union(&self, o: &Angled) -> Angled {
        let (bounds, theta_o) = self.bounds.union_with(self.theta_o, &o.bounds, o.theta_o);
        // `cos θ_e` of the union is the smaller cosine: the angle of the same cone.
        let theta_e = if self.bounds.cos_theta_e <= o.bounds.cos_theta_e {
            self.theta_e
        } else {
            o.theta_e
        };
        Angled {
            bounds,
            theta_o,
            theta_e,
        }
    }

    fn cost(&self, kr: f32) -> f32 {
        self.bounds.cost(self.theta_o, self.theta_e, kr)
    }
}

/// One node, in depth-first order: an interior node's first child follows it.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Node {
    bounds: LightBounds,
    /// `Shape::of(&bounds)`.
    shape: Shape,
    /// Interior: the index of the second child. Leaf: the light's index.
    index: u32,
    leaf: bool,
    /// Interior nodes whose children have the same bounds but for their power (the two
    /// triangles of a quad share a box and a normal): the probability of the first
    /// child, `φ0 / (φ0 + φ1)` at every point, so that no importance is evaluated there.
    /// (Where both would be zero, a light that cannot contribute is chosen instead of
    /// none: a wasted shadow ray, not a bias, since the pmf is the same.)
    fixed_p0: Option<f64>,
}

impl Node {
    fn new(bounds: LightBounds, index: u32, leaf: bool, fixed_p0: Option<f64>) -> Self {
        Node {
            bounds,
            shape: Shape::of(&bounds),
            index,
            leaf,
            fixed_p0,
        }
    }

    /// [`LightBounds::importance`] of the node's bounds.
    #[inline]
    fn importance(&self, p: Vec3, n: Vec3) -> f32 {
        self.bounds.importance_with(&self.shape, p, n)
    }
}

/// The light hierarchy over the finite lights of a [`super::LightSet`], and the infinite
/// lights chosen before it.
#[derive(Clone, Debug, Default)]
pub struct LightTree {
    nodes: Vec<Node>,
    /// Per light of the set: its bit trail, or `NOT_IN_TREE`.
    trails: Vec<u64>,
    /// Infinite lights with positive power: (index, probability).
    infinite: Vec<(u32, f32)>,
    /// Probability that the tree is used (1 minus the infinite lights' probabilities).
    p_tree: f64,
}

/// A light during the build.
#[derive(Clone, Copy)]
struct Item {
    light: u32,
    bounds: Angled,
    centroid: Vec3,
}

impl LightTree {
    /// Builds the tree over `lights`; `pmf` is the set's global power-proportional
    /// distribution, which gives the infinite lights their probabilities.
    pub fn build(lights: &[Light], pmf: &[f32]) -> Self {
        Self::build_with(lights, pmf, PARALLEL_BUILD_LIGHTS)
    }

    /// [`LightTree::build`], building subtrees of at least `parallel_lights` lights on two
    /// threads.
    fn build_with(lights: &[Light], pmf: &[f32], parallel_lights: usize) -> Self {
        let mut items = Vec::new();
        let mut infinite = Vec::new();
        let mut p_infinite = 0.0f64;
        for (i, l) in lights.iter().enumerate() {
            if let Some(bounds) = LightBounds::of(l) {
                items.push(Item {
                    light: i as u32,
                    bounds: Angled::of(bounds),
                    centroid: bounds.centroid(),
                });
            } else if l.is_infinite() && pmf[i] > 0.0 {
                infinite.push((i as u32, pmf[i]));
                p_infinite += pmf[i] as f64;
            }
        }
        let mut tree = LightTree {
            nodes: Vec::with_capacity(2 * items.len()),
            trails: vec![NOT_IN_TREE; lights.len()],
            infinite,
            p_tree: if items.is_empty() {
                0.0
            } else {
                (1.0 - p_infinite).max(0.0)
            },
        };
        if !items.is_empty() {
            let mut trails = Vec::with_capacity(items.len());
            let at = Placement {
                depth: 0,
                trail: 0,
                base: 0,
                parallel_lights,
            };
            build_subtree(&mut items, at, &mut tree.nodes, &mut trails);
            for (light, trail) in trails {
                tree.trails[light as usize] = trail;
            }
        }
        tree
    }

    /// Number of nodes (0 without finite lights).
    pub fn node_count(&self) -> usize {
        self.nodes.len()
    }

    /// The probabilities of an interior node's children at `(p, n)`, or `None` when
    /// neither can light the point.
    #[inline]
    fn child_probability(&self, node: usize, p: Vec3, n: Vec3) -> Option<f64> {
        if let Some(p0) = self.nodes[node].fixed_p0 {
            return Some(p0);
        }
        let i0 = self.nodes[node + 1].importance(p, n) as f64;
        let i1 = self.nodes[self.nodes[node].index as usize].importance(p, n) as f64;
        if i0 == 0.0 && i1 == 0.0 {
            return None;
        }
        Some(i0 / (i0 + i1))
    }

    /// Chooses a light for the point `p` with normal `n` (zero for none) from `u` in
    /// `[0, 1)`: (light index, probability), `None` if no light can contribute.
    #[inline]
    pub fn select(&self, u: f32, p: Vec3, n: Vec3) -> Option<(usize, f32)> {
        let mut u = u as f64;
        // Infinite lights first, by their global probabilities.
        let mut acc = 0.0f64;
        for &(i, q) in &self.infinite {
            acc += q as f64;
            if u < acc {
                return Some((i as usize, q));
            }
        }
        if self.nodes.is_empty() || self.p_tree <= 0.0 {
            // Only rounding of the cumulative sum leads here.
            return self.infinite.last().map(|&(i, q)| (i as usize, q));
        }
        u = ((u - acc) / self.p_tree).clamp(0.0, 1.0 - f64::EPSILON);
        let mut pmf = self.p_tree;
        let mut node = 0usize;
        if self.nodes[0].leaf && self.nodes[0].importance(p, n) <= 0.0 {
            return None;
        }
        while !self.nodes[node].leaf {
            let p0 = self.child_probability(node, p, n)?;
            if u < p0 {
                u = (u / p0).min(1.0 - f64::EPSILON);
                pmf *= p0;
                node += 1;
            } else {
                u = ((u - p0) / (1.0 - p0)).clamp(0.0, 1.0 - f64::EPSILON);
                pmf *= 1.0 - p0;
                node = self.nodes[node].index as usize;
            }
        }
        Some((self.nodes[node].index as usize, pmf as f32))
    }

    /// The probability that [`LightTree::select`] returns light `index` from `(p, n)`:
    /// the same products along the light's stored trail.
    #[inline]
    pub fn pmf(&self, p: Vec3, n: Vec3, index: usize) -> f32 {
        let Some(&trail) = self.trails.get(index) else {
            return 0.0;
        };
        if trail == NOT_IN_TREE {
            return self
                .infinite
                .iter()
                .find(|&&(i, _)| i as usize == index)
                .map_or(0.0, |&(_, q)| q);
        }
        if self.p_tree <= 0.0 {
            return 0.0;
        }
        if self.nodes[0].leaf && self.nodes[0].importance(p, n) <= 0.0 {
            return 0.0;
        }
        let mut pmf = self.p_tree;
        let mut node = 0usize;
        let mut trail = trail;
        while !self.nodes[node].leaf {
            let Some(p0) = self.child_probability(node, p, n) else {
                return 0.0;
            };
            if trail & 1 == 0 {
                pmf *= p0;
                node += 1;
            } else {
                pmf *= 1.0 - p0;
                node = self.nodes[node].index as usize;
            }
            trail >>= 1;
        }
        debug_assert_eq!(self.nodes[node].index as usize, index);
        pmf as f32
    }
}

/// Subtrees of at least this many lights build their two halves on two threads.
const PARALLEL_BUILD_LIGHTS: usize = 2048;

/// Builds the subtree of `items` (at `depth`, reached by `trail`) by appending its nodes,
/// in depth-first order, to `nodes`, whose first element has index `base` in the whole
/// tree, and its lights' trails to `trails`; returns its bounds.
///
/// Every split makes two non-empty groups and every leaf holds one light, so a subtree of
/// `n` lights has exactly `2n - 1` nodes: where the right half's nodes will start is known
/// before the left half is built, and large halves are built in parallel (`rayon::join`)
/// into vectors of their own, then appended. The tree is the same as built on one thread.
fn build_subtree(
    items: &mut [Item],
    place: Placement,
    nodes: &mut Vec<Node>,
    trails: &mut Vec<(u32, u64)>,
) -> LightBounds {
    let Placement {
        depth,
        trail,
        base,
        parallel_lights,
    } = place;
    let at = nodes.len();
    if items.len() == 1 {
        let it = items[0];
        nodes.push(Node::new(it.bounds.bounds, it.light, true, None));
        trails.push((it.light, trail));
        return it.bounds.bounds;
    }
    let mid = split(items, depth);
    // Placeholder, filled in once the children are built.
    nodes.push(Node::new(items[0].bounds.bounds, 0, false, None));
    let (left, right) = items.split_at_mut(mid);
    let right_trail = trail | (1u64 << depth);
    let left_base = base + nodes.len() as u32;
    let second = left_base + (2 * mid as u32 - 1);
    let child = |trail: u64, base: u32| Placement {
        depth: depth + 1,
        trail,
        base,
        parallel_lights,
    };
    let (b0, b1) =
        if mid.min(right.len()) >= parallel_lights / 2 && mid + right.len() >= parallel_lights {
            let half = |items: &mut [Item], trail: u64, base: u32| {
                let mut n = Vec::with_capacity(2 * items.len() - 1);
                let mut t = Vec::with_capacity(items.len());
                let b = build_subtree(items, child(trail, base), &mut n, &mut t);
                (b, n, t)
            };
            let ((b0, n0, t0), (b1, n1, t1)) = rayon::join(
                || half(left, trail, left_base),
                || half(right, right_trail, second),
            );
            nodes.extend(n0);
            nodes.extend(n1);
            trails.extend(t0);
            trails.extend(t1);
            (b0, b1)
        } else {
            let b0 = build_subtree(left, child(trail, base), nodes, trails);
            debug_assert_eq!(base + nodes.len() as u32, second);
            let b1 = build_subtree(right, child(right_trail, base), nodes, trails);
            (b0, b1)
        };
    let bounds = b0.union(&b1);
    let same = LightBounds { phi: b1.phi, ..b0 } == b1;
    nodes[at] = Node::new(
        bounds,
        second,
        false,
        same.then(|| b0.phi as f64 / (b0.phi as f64 + b1.phi as f64)),
    );
    bounds
}

/// Where a subtree goes: its depth and trail (the branch bits from the root), the index
/// its first node has in the whole tree, and from how many lights halves are built on
/// two threads.
#[derive(Clone, Copy)]
struct Placement {
    depth: u32,
    trail: u64,
    base: u32,
    parallel_lights: usize,
}

/// Reorders `items` into two non-empty groups and returns where the second starts: the
/// cheapest binned surface-area-orientation split over the three axes, or a median split
/// by light order when the centroids coincide, no split is finite, or the tree is deep.
fn split(items: &mut [Item], depth: u32) -> usize {
    let median = items.len() / 2;
    if depth >= MAX_HEURISTIC_DEPTH {
        return median;
    }
    let mut cmin = Vec3::splat(f32::INFINITY);
    let mut cmax = Vec3::splat(f32::NEG_INFINITY);
    // Only the box of the whole set is needed here: its cone union would cost three
    // inverse trigonometric functions per light and level.
    let (mut bmin, mut bmax) = (items[0].bounds.bounds.min, items[0].bounds.bounds.max);
    for it in items.iter() {
        cmin = cmin.min(it.centroid);
        cmax = cmax.max(it.centroid);
        bmin = bmin.min(it.bounds.bounds.min);
        bmax = bmax.max(it.bounds.bounds.max);
    }
    let diag = bmax - bmin;
    let extent = cmax - cmin;
    let bucket_of = |c: Vec3, dim: usize| -> usize {
        let t = (c[dim] - cmin[dim]) / extent[dim];
        ((BUCKETS as f32 * t) as usize).min(BUCKETS - 1)
    };
    let mut best: Option<(f32, usize, usize)> = None;
    for dim in 0..3 {
        if extent[dim].is_nan() || extent[dim] <= 0.0 || diag[dim].is_nan() || diag[dim] <= 0.0 {
            continue;
        }
        let mut buckets: [Option<Angled>; BUCKETS] = [None; BUCKETS];
        for it in items.iter() {
            let b = &mut buckets[bucket_of(it.centroid, dim)];
            *b = Some(match b {
                Some(x) => x.union(&it.bounds),
                None => it.bounds,
            });
        }
        let kr = diag.max_element() / diag[dim];
        for cut in 0..BUCKETS - 1 {
            let side = |r: std::ops::Range<usize>| {
                buckets[r]
                    .iter()
                    .flatten()
                    .fold(None, |acc: Option<Angled>, b| {
                        Some(acc.map_or(*b, |a| a.union(b)))
                    })
            };
            let (Some(lo), Some(hi)) = (side(0..cut + 1), side(cut + 1..BUCKETS)) else {
                continue;
            };
            let cost = lo.cost(kr) + hi.cost(kr);
            if cost.is_finite() && best.is_none_or(|(c, _, _)| cost < c) {
                best = Some((cost, dim, cut));
            }
        }
    }
    let Some((_, dim, cut)) = best else {
        return median;
    };
    // A stable partition keeps the order, and so the tree, a function of the light list.
    let (mut lo, mut hi): (Vec<Item>, Vec<Item>) = items
        .iter()
        .copied()
        .partition(|it| bucket_of(it.centroid, dim) <= cut);
    let mid = lo.len();
    if mid == 0 || mid == items.len() {
        return median;
    }
    lo.append(&mut hi);
    items.copy_from_slice(&lo);
    mid
}

#[cfg(test)]
mod build_tests {
    use super::*;
    use crate::light::triangle::TriangleLight;

    /// A tree built with its large halves on two threads is the tree built on one: the
    /// same nodes in the same order (so the same pmfs and the same images) and the same
    /// trails. 5,000 small triangles facing every way, so the build splits on both the
    /// box and the cone and several levels go parallel.
    #[test]
    fn parallel_build_is_the_sequential_build() {
        let mut lights = Vec::new();
        let mut x = 0x2545_f491u32;
        let mut next = || {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            x as f32 / u32::MAX as f32
        };
        while lights.len() < 5000 {
            let c = Vec3::new(next(), next(), next()) * 10.0;
            let p = [
                c,
                c + Vec3::new(next(), next(), next()) * 0.2,
                c + Vec3::new(next(), next(), next()) * 0.2,
            ];
            if let Some(t) = TriangleLight::new(p, Vec3::splat(1.0 + next()), false) {
                lights.push(Light::Triangle(t));
            }
        }
        let pmf = vec![1.0 / lights.len() as f32; lights.len()];
        let one = LightTree::build_with(&lights, &pmf, usize::MAX);
        let two = LightTree::build_with(&lights, &pmf, 256);
        assert_eq!(one.nodes.len(), 2 * lights.len() - 1);
        assert!(
            one.nodes == two.nodes,
            "the parallel build made another tree"
        );
        assert_eq!(one.trails, two.trails);
        assert!(one.trails.iter().all(|&t| t != NOT_IN_TREE));
    }
}
