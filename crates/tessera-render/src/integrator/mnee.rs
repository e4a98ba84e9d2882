//! Manifold next-event estimation (MNEE): light from a point or small area light reaching
//! a diffuse or rough vertex through a chain of up to [`MAX_CHAIN`] smooth specular
//! interfaces (a glass ball's two, a flat water surface's one), which ordinary next-event
//! estimation cannot see (the glass occludes its shadow ray) and BSDF sampling finds only
//! by chance (the fireflies of a caustic under a glass ball).
//!
//! # The estimator
//!
//! At the shading point `x` a light point `y` is sampled as for next-event estimation.
//! The straight segment `x -> y` gives the *seed chain*: the specular surfaces it crosses,
//! in order (Hanika, Droske & Fascione 2015, "Manifold Next Event Estimation", §3). A
//! Newton solver then moves the chain's vertices over their surfaces until every vertex
//! satisfies its specular constraint, with `x` and `y` held fixed. The constraint of a
//! vertex `p` with neighbours `a` (toward `x`) and `b` (toward `y`) is the generalized
//! half-vector of Jakob & Marschner 2012 ("Manifold Exploration", §4.1): with
//! `wa = (a - p)/|a - p|`, `wb = (b - p)/|b - p|` and `η_w` the index of the medium on
//! `w`'s side of the surface (1 outside, the material's `η` inside),
//! `h = normalize(η_wa wa + η_wb wb)` for a refraction, `normalize(wa + wb)` for a
//! reflection, and the constraint is `h`'s two components in the tangent plane of the
//! shading normal: zero exactly when Snell's law (or the law of reflection) holds about
//! the shading normal. Interpolated normals of a glTF sphere mesh are what is used, so
//! the solver finds the path the renderer's own BSDF sampling would follow; a flat
//! triangle's constant normal simply makes the constraint that of a plane.
//!
//! A vertex moves in the tangent plane of its shading normal (coordinates `(a, b)` along
//! the frame's `s`, `t`) and is projected back onto the geometry by tracing a ray from
//! its predecessor through the moved point (Zeltner, Georgiev & Jakob 2020, "Specular
//! Manifold Sampling", §4.2 and §5.2): the solver needs nothing of the geometry but the
//! renderer's ray casts and shading points, so it works on triangle meshes and spheres
//! alike. The constraint Jacobian is in closed form, in `f64`, with no ray cast (Jakob &
//! Marschner 2012, §4.1-4.2): each constraint depends on its vertex and the two
//! neighbours (a block-tridiagonal matrix); moving a vertex along its tangent turns `wa`,
//! `wb` and, through the derivative of the shading normal by position
//! ([`RenderScene::shading_normal_derivative`]: on a triangle with vertex normals the
//! interpolated normal is linear in the barycentrics, on a sphere `dn/dp = (I - n nᵀ)/r`),
//! the normal and the tangent frame the constraint is expressed in. Where the geometry
//! gives no such derivative (instances, moving triangles, normal maps) the Jacobian comes
//! from finite differences of the ray-cast parametrisation instead: forward differences
//! for Newton's steps, central ones for the geometry term. Ray casts are then needed only
//! to project each Newton step onto the geometry. A step that fails to project, or does
//! not reduce the constraint's norm, is halved.
//!
//! On convergence the contribution is, for an area light sampled with area density
//! `p_A(y)`,
//!
//! `f(x, ω_x) |cos θ_x| T Le(y, ω_y) |dω_x/dA_y| / p_A(y)`,
//!
//! where `T` is the product of the specular vertices' Fresnel transmittances and
//! reflectances with the radiance scaling `(η_i/η_t)²` of each refraction, taken from the
//! BSDF's own delta sample (so the estimate is the integral the path tracer's BSDF
//! sampling estimates), and `|dω_x/dA_y|` is the generalized geometry term: how much solid
//! angle at `x` one unit of light area covers through the chain. It comes from the
//! constraint Jacobian by the implicit function theorem (Jakob & Marschner 2012, §4.3):
//! with `C(X, y) = 0` at the solution, `dX/dy = -(∂C/∂X)⁻¹ ∂C/∂y`; the first vertex's
//! tangent coordinates `(a, b)` change by the top 2 x 2 block `D` of that, and since the
//! projection moves a point along the ray from `x`, the direction `ω_x` depends on
//! `(a, b)` as on a point of the tangent plane: `|dω_x/d(a,b)| = |ω_x · n_1| / r_1²`. So
//! `|dω_x/dA_y| = |ω_x · n_1| / r_1² · |det D|`. For a straight segment this is
//! `cos θ_y / r²`, the ordinary geometry term. A point light of intensity `I` is the
//! limit of a small area light seen edge-on to nothing: `I |dω_x/dA⊥_y|`, with `y` moved
//! perpendicular to the direction the light leaves by (`Le cos θ_y dA_y = I dω`).
//!
//! # Combination with BSDF sampling
//!
//! Every path MNEE finds can also be found by BSDF sampling through the glass. The two
//! are combined by partition, not by MIS (Hanika et al. 2015, §4.3, discuss the options;
//! the MNEE density of a BSDF-sampled path is not available in closed form): a path
//! `x, v_1..v_k, y` belongs to MNEE exactly when the solver, run from `x` and `y`, returns
//! that chain ([`claims`]); the path tracer then drops its BSDF-sampled emission, and
//! counts it otherwise. The solver is deterministic, so this partitions path space: no
//! path is counted twice, and the paths the solver misses (other roots with the same end
//! points, seeds blocked by an opaque surface, chains longer than [`MAX_CHAIN`], total
//! internal reflection, an area light's steep seeds below) stay with BSDF sampling, so no
//! energy is lost either. The price is one solve per BSDF-sampled path that reaches a
//! light through a specular chain, which is rare.
//!
//! # Hopeless seeds
//!
//! A curved dielectric focuses what it transmits: under a glass ball most of the ball's
//! shadow receives no refracted light from a small light above it, so from most shadow
//! points the solver has no solution to find (97% of the solves on bench/compare's glass
//! ball), and it fails in its first iteration, after the seed's three ray casts and a
//! step's two or four. Such seeds enter the ball near its rim: their straight segment
//! meets the surface steeply, while the seeds the solver converges from meet it within
//! 16.1 degrees of its normal there (17.7 with the light off to the side).
//! So for an area light a seed that enters its first vertex, a curved dielectric, more
//! than 25 degrees off the shading normal is not solved (`STEEP_SEED_COS`), and `seed`
//! stops at that vertex, one ray cast in. This is a choice of which paths MNEE samples,
//! not an approximation: [`claims`] runs the same [`connect`], so a path whose seed is
//! skipped is left to BSDF sampling, which samples it unbiased (a caustic seen from much
//! further behind a lens than its focus, where converging seeds do enter steeply, is
//! then noisier, not darker; the tests
//! `steep_seeds_are_the_hopeless_ones_under_a_ball_on_the_floor` and
//! `claims_leaves_the_skipped_solutions_to_bsdf_sampling`). A point light's seeds are
//! never skipped: no other technique samples its light.

use crate::bsdf::Bsdf;
use crate::geometry::SurfacePoint;
use crate::light::Light;
use crate::math::offset_ray_origin;
use crate::sampling::warp::Frame;
use crate::scene::RenderScene;
use glam::{DMat3, DVec3, Vec2, Vec3};

/// Most specular vertices between the shading point and the light (a sphere's two
/// interfaces, or one flat water surface).
pub const MAX_CHAIN: usize = 2;

/// Newton iterations before the solver gives up.
const MAX_ITERATIONS: u32 = 6;

/// Step halvings per Newton iteration before the solver gives up.
const MAX_HALVINGS: u32 = 2;

/// Converged when every constraint component (the tangential part of a unit half-vector,
/// about an angle in radians) is below this: well above what `f32` positions resolve
/// (about `1e-7 / |segment|`), well below a pixel's angle.
const TOLERANCE: f64 = 1e-5;

/// A specular vertex's outgoing direction from the BSDF's delta sample must agree with
/// the solved chain to this cosine (about 0.8 degrees).
const DIRECTION_AGREEMENT: f32 = 0.9999;

/// For an area light, a seed whose straight segment enters a curved dielectric at more
/// than 25 degrees from its shading normal (the cosine of the angle below this) is not
/// solved: [`seed`] stops at that first vertex (see "Hopeless seeds" in the module docs).
/// The seeds the solver converges from enter bench/compare's glass ball within 16.1
/// degrees of the normal, and `builtin:caustic`'s sphere (lit from off to the side)
/// within 17.7 (docs/benchmarks.md, "Hopeless MNEE seeds skipped").
const STEEP_SEED_COS: f32 = 0.906_307_8;

/// The shading point a chain starts at: what a ray leaving it needs.
#[derive(Clone, Copy, Debug)]
pub struct Anchor {
    /// Position.
    pub p: Vec3,
    /// Error bound of `p`.
    pub p_error: Vec3,
    /// Geometric normal.
    pub ng: Vec3,
}

impl Anchor {
    /// The anchor of a surface point.
    pub fn of(sp: &SurfacePoint) -> Self {
        Self {
            p: sp.p,
            p_error: sp.p_error,
            ng: sp.ng,
        }
    }

    /// The origin of a ray leaving toward `dir`, offset off the surface.
    fn origin(&self, dir: Vec3) -> Vec3 {
        offset_ray_origin(self.p, self.p_error, self.ng, dir)
    }
}

/// A specular vertex of a chain: its surface point, for a dielectric the relative index
/// `η` (inside over outside; `0` for a mirror), and the derivative of its shading normal
/// by position ([`RenderScene::shading_normal_derivative`]) where the geometry gives it.
#[derive(Clone, Copy, Debug)]
struct Vertex {
    sp: SurfacePoint,
    eta: f32,
    dn: Option<DMat3>,
}

/// The specular vertices between `x` and `y`, in order from `x`.
#[derive(Clone, Copy, Debug)]
pub struct Chain {
    v: [Vertex; MAX_CHAIN],
    len: usize,
}

impl Chain {
    /// Number of specular vertices.
    pub fn len(&self) -> usize {
        self.len
    }

    /// True if there are none (never for a chain the solver returns).
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The positions of the vertices, in order from `x`.
    pub fn positions(&self) -> impl Iterator<Item = Vec3> + '_ {
        self.v[..self.len].iter().map(|v| v.sp.p)
    }
}

/// The light end of a connection.
#[derive(Clone, Copy, Debug)]
pub enum LightEnd {
    /// A point on an emissive triangle of light `li`, with its normal.
    Area {
        /// Light index.
        li: usize,
        /// The point.
        p: Vec3,
        /// Its (unit) normal.
        n: Vec3,
    },
    /// A point or spot light, light `li`, at `p`.
    Point {
        /// Light index.
        li: usize,
        /// Its position.
        p: Vec3,
    },
}

impl LightEnd {
    fn p(&self) -> Vec3 {
        match *self {
            LightEnd::Area { p, .. } | LightEnd::Point { p, .. } => p,
        }
    }
}

/// A solved and checked connection from `x` to a light through a specular chain.
#[derive(Clone, Copy, Debug)]
pub struct Connection {
    /// The specular vertices.
    pub chain: Chain,
    /// The direction from `x` to the first vertex.
    pub wi: Vec3,
    /// Product of the specular vertices' delta BSDF values (Fresnel and `1/η²` scaling)
    /// and the media's transmittance along the chain.
    pub throughput: Vec3,
    /// Emitted radiance toward the chain (area light) or intensity (point light).
    pub emission: Vec3,
    /// The generalized geometry term: `|dω_x/dA_y|` for an area light, `|dω_x/dA⊥_y|`
    /// for a point light.
    pub geometry: f32,
}

/// The specular vertex at a ray hit: `None` unless its BSDF is purely a delta
/// distribution (a mirror or smooth dielectric) with an index other than 1.
fn specular_vertex(
    scene: &RenderScene,
    origin: Vec3,
    dir: Vec3,
    time: f32,
    t_max: f32,
) -> Result<Option<Vertex>, ()> {
    let Some(hit) = scene.intersect_at(origin, dir, t_max, time) else {
        return Ok(None);
    };
    let sp = scene.surface(&hit, origin, dir);
    let bsdf = scene.bsdf(&sp, -dir);
    if bsdf.has_non_delta() {
        return Err(());
    }
    let eta = bsdf.glass_eta().unwrap_or(0.0);
    if eta == 1.0 {
        return Err(());
    }
    let dn = scene.shading_normal_derivative(&hit, &sp);
    Ok(Some(Vertex { sp, eta, dn }))
}

/// The seed chain: the specular surfaces the segment `x -> y` crosses. `None` if an
/// opaque non-specular surface blocks it, if there are more than `max_chain` of them, or
/// none (ordinary next-event estimation covers that path); with `skip_steep` (an area
/// light's end) also if the segment enters its first vertex, a curved dielectric, steeper
/// than [`STEEP_SEED_COS`] allows, before the rest of the chain is cast.
fn seed(
    scene: &RenderScene,
    x: &Anchor,
    y: Vec3,
    time: f32,
    max_chain: usize,
    skip_steep: bool,
) -> Option<Chain> {
    let d = y - x.p;
    let dist = d.length();
    if dist <= 0.0 || !dist.is_finite() {
        return None;
    }
    let dir = d / dist;
    let mut origin = x.origin(dir);
    let mut chain = Chain {
        v: [Vertex {
            sp: dummy_point(),
            eta: 0.0,
            dn: None,
        }; MAX_CHAIN],
        len: 0,
    };
    loop {
        let remaining = (y - origin).dot(dir) * (1.0 - 1e-4);
        if remaining <= 0.0 {
            break;
        }
        match specular_vertex(scene, origin, dir, time, remaining) {
            Err(()) => return None,
            Ok(None) => break,
            Ok(Some(v)) => {
                if chain.len == max_chain.min(MAX_CHAIN) {
                    return None;
                }
                if skip_steep && chain.len == 0 && steep_entry(&v, dir) {
                    return None;
                }
                origin = offset_ray_origin(v.sp.p, v.sp.p_error, v.sp.ng, dir);
                chain.v[chain.len] = v;
                chain.len += 1;
            }
        }
    }
    (chain.len > 0).then_some(chain)
}

/// Whether the straight segment along `dir` meets the vertex `v`, a curved dielectric
/// (its shading normal has a nonzero derivative by position), more than 25 degrees off
/// its shading normal (`STEEP_SEED_COS`). Flat interfaces, mirrors and surfaces whose
/// curvature the geometry does not give are never steep: through a flat interface the
/// solver converges from any seed.
fn steep_entry(v: &Vertex, dir: Vec3) -> bool {
    v.eta > 0.0 && v.dn.is_some_and(|w| w != DMat3::ZERO) && dir.dot(v.sp.ns).abs() < STEEP_SEED_COS
}

/// A placeholder for the unused slots of a chain.
fn dummy_point() -> SurfacePoint {
    SurfacePoint {
        p: Vec3::ZERO,
        p_error: Vec3::ZERO,
        ng: Vec3::Z,
        ns: Vec3::Z,
        uv: Vec2::ZERO,
        mesh: 0,
        tri: 0,
        bary: Vec2::ZERO,
        material: 0,
        light: crate::geometry::NO_LIGHT,
        tangent: glam::Vec4::ZERO,
    }
}

/// The vertex where the ray from `from` through `target` first meets a surface, if that
/// surface is specular.
fn project(scene: &RenderScene, from: &Anchor, target: Vec3, time: f32) -> Option<Vertex> {
    let d = target - from.p;
    let len = d.length();
    if len <= 0.0 || !len.is_finite() {
        return None;
    }
    let dir = d / len;
    specular_vertex(scene, from.origin(dir), dir, time, f32::INFINITY)
        .ok()
        .flatten()
}

/// The half-vector constraint at a vertex `p` between `a` (toward `x`) and `b`, with what
/// its derivatives need (Jakob & Marschner 2012, §4.1): the unit directions `wa`, `wb` to
/// the neighbours and their distances, the indices `η_a`, `η_b` of the media they lie in,
/// the generalized half-vector `H = η_a wa + η_b wb` (`wa + wb` for a mirror) and its
/// normalisation `h`, and the shading frame the constraint is expressed in.
#[derive(Clone, Copy, Debug, Default)]
struct Local {
    wa: DVec3,
    la: f64,
    ea: f64,
    wb: DVec3,
    lb: f64,
    eb: f64,
    /// `|H|`.
    len: f64,
    h: DVec3,
    n: DVec3,
    s: DVec3,
    t: DVec3,
}

impl Local {
    fn of(a: DVec3, v: &Vertex, b: DVec3) -> Option<Self> {
        let p = v.sp.p.as_dvec3();
        let n = v.sp.ns.as_dvec3();
        let (da, db) = (a - p, b - p);
        let (la, lb) = (da.length(), db.length());
        if !(la > 0.0 && lb > 0.0 && la.is_finite() && lb.is_finite()) {
            return None;
        }
        let (wa, wb) = (da / la, db / lb);
        let (ea, eb) = if v.eta > 0.0 {
            let eta = v.eta as f64;
            let side = |w: DVec3| if w.dot(n) > 0.0 { 1.0 } else { eta };
            (side(wa), side(wb))
        } else {
            (1.0, 1.0)
        };
        let big_h = wa * ea + wb * eb;
        let len = big_h.length();
        if len < 1e-12 {
            return None;
        }
        let (s, t) = frame_tangents(n);
        Some(Self {
            wa,
            la,
            ea,
            wb,
            lb,
            eb,
            len,
            h: big_h / len,
            n,
            s,
            t,
        })
    }

    /// The two constraint components: `h`'s coordinates in the tangent plane.
    fn value(&self) -> [f64; 2] {
        [self.h.dot(self.s), self.h.dot(self.t)]
    }

    /// `∂H` when the neighbour toward `x` moves by `d`: `η_a (I - wa waᵀ) d / |a - p|`.
    fn dh_a(&self, d: DVec3) -> DVec3 {
        (d - self.wa * self.wa.dot(d)) * (self.ea / self.la)
    }

    /// `∂H` when the neighbour toward the light moves by `d`.
    fn dh_b(&self, d: DVec3) -> DVec3 {
        (d - self.wb * self.wb.dot(d)) * (self.eb / self.lb)
    }

    /// The constraint's change for a change `dh_big` of `H` and `(ds, dt)` of the frame:
    /// `dh = (I - h hᵀ) dH / |H|`, `d(h · s) = dh · s + h · ds`.
    fn d(&self, dh_big: DVec3, ds: DVec3, dt: DVec3) -> [f64; 2] {
        let dh = (dh_big - self.h * self.h.dot(dh_big)) / self.len;
        [
            dh.dot(self.s) + self.h.dot(ds),
            dh.dot(self.t) + self.h.dot(dt),
        ]
    }
}

/// The tangents `s`, `t` of [`Frame::from_normal`] (Duff et al. 2017, "Building an
/// Orthonormal Basis, Revisited") in `f64`.
fn frame_tangents(n: DVec3) -> (DVec3, DVec3) {
    let sign = 1.0f64.copysign(n.z);
    let a = -1.0 / (sign + n.z);
    let b = n.x * n.y * a;
    (
        DVec3::new(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x),
        DVec3::new(b, sign + n.y * n.y * a, -n.y),
    )
}

/// The change of [`frame_tangents`]`(n)` when `n` changes by `dn`: the formulas
/// differentiated (`da = a² dn_z`), so the constraint's derivative includes the frame's
/// turning with the normal as the finite differences do.
fn frame_tangents_derivative(n: DVec3, dn: DVec3) -> (DVec3, DVec3) {
    let sign = 1.0f64.copysign(n.z);
    let a = -1.0 / (sign + n.z);
    let da = a * a * dn.z;
    let db = (dn.x * n.y + n.x * dn.y) * a + n.x * n.y * da;
    (
        DVec3::new(
            sign * (2.0 * n.x * dn.x * a + n.x * n.x * da),
            sign * db,
            -sign * dn.x,
        ),
        DVec3::new(db, 2.0 * n.y * dn.y * a + n.y * n.y * da, -dn.y),
    )
}

/// The two constraint components of vertex `v` between `a` (toward `x`) and `b`.
fn constraint(a: DVec3, v: &Vertex, b: DVec3) -> Option<[f64; 2]> {
    Local::of(a, v, b).map(|l| l.value())
}

/// The chain's constraint vector (two components a vertex, from `x`).
fn constraints(x: Vec3, chain: &Chain, y: Vec3) -> Option<[f64; 2 * MAX_CHAIN]> {
    let mut c = [0.0; 2 * MAX_CHAIN];
    for i in 0..chain.len {
        let a = if i == 0 { x } else { chain.v[i - 1].sp.p };
        let b = if i + 1 == chain.len {
            y
        } else {
            chain.v[i + 1].sp.p
        };
        let ci = constraint(a.as_dvec3(), &chain.v[i], b.as_dvec3())?;
        c[2 * i] = ci[0];
        c[2 * i + 1] = ci[1];
    }
    Some(c)
}

fn norm(c: &[f64]) -> f64 {
    c.iter().map(|v| v * v).sum::<f64>().sqrt()
}

/// The finite-difference step for moving vertex `i`: a thousandth of its shorter segment,
/// no less than what `f32` coordinates resolve well.
fn step_of(x: Vec3, chain: &Chain, i: usize, y: Vec3) -> f32 {
    let p = chain.v[i].sp.p;
    let a = if i == 0 { x } else { chain.v[i - 1].sp.p };
    let b = if i + 1 == chain.len {
        y
    } else {
        chain.v[i + 1].sp.p
    };
    let seg = (a - p).length().min((b - p).length());
    (1e-3 * seg).max(2e-5 * (1.0 + p.abs().max_element()))
}

/// A chain's constraint Jacobian `∂C/∂X` (rows: the constraints from `x`; columns: the
/// vertices' tangent coordinates).
type Matrix = [[f64; 2 * MAX_CHAIN]; 2 * MAX_CHAIN];

/// `∂C/∂X`: column `2i + j` is the derivative by vertex `i`'s tangent coordinate `j` (a
/// move of the vertex along its shading frame's `s` or `t`, projected onto the surface
/// along the ray from its predecessor). In closed form ([`jacobian_analytic`]) where every
/// vertex carries its normal's derivative, else by finite differences
/// ([`jacobian_by_differences`]).
fn jacobian(
    scene: &RenderScene,
    x: &Anchor,
    chain: &Chain,
    y: Vec3,
    time: f32,
    c: Option<&[f64; 2 * MAX_CHAIN]>,
) -> Option<Matrix> {
    if chain.v[..chain.len].iter().all(|v| v.dn.is_some()) {
        jacobian_analytic(x.p, chain, y)
    } else {
        jacobian_by_differences(scene, x, chain, y, time, c)
    }
}

/// The neighbours of vertex `i`: toward `x` and toward the light.
fn neighbours(x: Vec3, chain: &Chain, i: usize, y: Vec3) -> (DVec3, DVec3) {
    let a = if i == 0 { x } else { chain.v[i - 1].sp.p };
    let b = if i + 1 == chain.len {
        y
    } else {
        chain.v[i + 1].sp.p
    };
    (a.as_dvec3(), b.as_dvec3())
}

/// `∂C/∂X` in closed form, no ray cast (Jakob & Marschner 2012, §4.1-4.2: each vertex's
/// constraint depends on itself and its two neighbours, so the matrix is block
/// tridiagonal). A vertex's tangent move `e` (its frame's `s` or `t`) projected along the
/// ray `d` from its predecessor lands, to first order, at `e' = e - d (e · n_g)/(d · n_g)`
/// on the surface's plane; that moves `wa` and `wb` (`∂H = -(∂H/∂a + ∂H/∂b) e'`), the
/// shading normal by [`RenderScene::shading_normal_derivative`]'s `dn = W e'`, and the
/// frame with it. A neighbour's move changes only `wa` or `wb`. `None` if a vertex lacks
/// its normal's derivative or the ray grazes a surface.
fn jacobian_analytic(x: Vec3, chain: &Chain, y: Vec3) -> Option<Matrix> {
    let len = chain.len;
    let mut local = [Local::default(); MAX_CHAIN];
    // Each vertex's tangent moves projected onto its surface.
    let mut moves = [[DVec3::ZERO; 2]; MAX_CHAIN];
    for i in 0..len {
        let v = &chain.v[i];
        let (a, b) = neighbours(x, chain, i, y);
        local[i] = Local::of(a, v, b)?;
        let d = (v.sp.p.as_dvec3() - a).normalize_or_zero();
        let ng = v.sp.ng.as_dvec3();
        let cos = d.dot(ng);
        if cos.abs() < 1e-6 {
            return None;
        }
        for (j, e) in [local[i].s, local[i].t].into_iter().enumerate() {
            moves[i][j] = e - d * (e.dot(ng) / cos);
        }
    }
    let mut m = [[0.0; 2 * MAX_CHAIN]; 2 * MAX_CHAIN];
    for i in 0..len {
        let l = &local[i];
        let w = chain.v[i].dn?;
        for j in 0..2 {
            let e = moves[i][j];
            // The vertex itself: both directions and the normal's frame move.
            let (ds, dt) = frame_tangents_derivative(l.n, w * e);
            let d = l.d(-(l.dh_a(e) + l.dh_b(e)), ds, dt);
            m[2 * i][2 * i + j] = d[0];
            m[2 * i + 1][2 * i + j] = d[1];
            if i > 0 {
                let d = l.d(l.dh_a(moves[i - 1][j]), DVec3::ZERO, DVec3::ZERO);
                m[2 * i][2 * (i - 1) + j] = d[0];
                m[2 * i + 1][2 * (i - 1) + j] = d[1];
            }
            if i + 1 < len {
                let d = l.d(l.dh_b(moves[i + 1][j]), DVec3::ZERO, DVec3::ZERO);
                m[2 * i][2 * (i + 1) + j] = d[0];
                m[2 * i + 1][2 * (i + 1) + j] = d[1];
            }
        }
    }
    Some(m)
}

/// `∂C/∂X` by finite differences of the ray-cast projection, for vertices whose normal's
/// derivative the geometry does not give: `c` is the chain's own constraints for forward
/// differences (enough for Newton's direction); without it central differences (for the
/// geometry term, error `O(h²)`).
fn jacobian_by_differences(
    scene: &RenderScene,
    x: &Anchor,
    chain: &Chain,
    y: Vec3,
    time: f32,
    c: Option<&[f64; 2 * MAX_CHAIN]>,
) -> Option<Matrix> {
    let n = 2 * chain.len;
    let mut a = [[0.0; 2 * MAX_CHAIN]; 2 * MAX_CHAIN];
    for i in 0..chain.len {
        let from = if i == 0 {
            *x
        } else {
            Anchor::of(&chain.v[i - 1].sp)
        };
        let frame = Frame::from_normal(chain.v[i].sp.ns);
        let h = step_of(x.p, chain, i, y);
        for (j, e) in [frame.s, frame.t].into_iter().enumerate() {
            let mut moved = *chain;
            moved.v[i] = project(scene, &from, chain.v[i].sp.p + h * e, time)?;
            let plus = constraints(x.p, &moved, y)?;
            let (minus, span) = match c {
                Some(c) => (*c, h as f64),
                None => {
                    moved.v[i] = project(scene, &from, chain.v[i].sp.p - h * e, time)?;
                    (constraints(x.p, &moved, y)?, 2.0 * h as f64)
                }
            };
            for r in 0..n {
                a[r][2 * i + j] = (plus[r] - minus[r]) / span;
            }
        }
    }
    Some(a)
}

/// Solves `a m = b` for the `cols` right-hand sides of `b` (Gaussian elimination with
/// partial pivoting on the leading `n x n` block). `None` if `a` is singular. Index loops:
/// the rows and columns of two arrays move together, as in the textbook elimination.
#[allow(clippy::needless_range_loop)]
fn solve<const C: usize>(
    mut a: Matrix,
    mut b: [[f64; C]; 2 * MAX_CHAIN],
    n: usize,
) -> Option<[[f64; C]; 2 * MAX_CHAIN]> {
    let scale = a[..n]
        .iter()
        .flat_map(|r| r[..n].iter())
        .fold(0.0f64, |m, v| m.max(v.abs()));
    if scale.is_nan() || scale <= 0.0 || scale.is_infinite() {
        return None;
    }
    for col in 0..n {
        let pivot = (col..n).max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs()))?;
        if a[pivot][col].abs() < 1e-12 * scale {
            return None;
        }
        a.swap(col, pivot);
        b.swap(col, pivot);
        for r in col + 1..n {
            let f = a[r][col] / a[col][col];
            for k in col..n {
                a[r][k] -= f * a[col][k];
            }
            for k in 0..C {
                b[r][k] -= f * b[col][k];
            }
        }
    }
    for col in (0..n).rev() {
        for k in 0..C {
            let mut s = b[col][k];
            for j in col + 1..n {
                s -= a[col][j] * b[j][k];
            }
            b[col][k] = s / a[col][col];
        }
    }
    Some(b)
}

/// Newton's method on the chain's constraints with `x` and `y` fixed. The converged chain,
/// or `None`.
fn newton(scene: &RenderScene, x: &Anchor, mut chain: Chain, y: Vec3, time: f32) -> Option<Chain> {
    let n = 2 * chain.len;
    let mut c = constraints(x.p, &chain, y)?;
    let mut err = norm(&c[..n]);
    for _ in 0..MAX_ITERATIONS {
        if c[..n].iter().all(|v| v.abs() < TOLERANCE) {
            return Some(chain);
        }
        let a = jacobian(scene, x, &chain, y, time, Some(&c))?;
        let mut rhs = [[0.0; 1]; 2 * MAX_CHAIN];
        for r in 0..n {
            rhs[r][0] = -c[r];
        }
        let delta = solve(a, rhs, n)?;
        let mut beta = 1.0f32;
        let mut accepted = None;
        for _ in 0..MAX_HALVINGS {
            if let Some((moved, mc)) = step(scene, x, &chain, y, &delta, beta, time) {
                let e = norm(&mc[..n]);
                if e < err {
                    accepted = Some((moved, mc, e));
                    break;
                }
            }
            beta *= 0.5;
        }
        let (moved, mc, e) = accepted?;
        chain = moved;
        c = mc;
        err = e;
    }
    c[..n].iter().all(|v| v.abs() < TOLERANCE).then_some(chain)
}

/// The chain moved by `beta` times the Newton step `delta`, each vertex projected from
/// its (moved) predecessor, with its constraints.
fn step(
    scene: &RenderScene,
    x: &Anchor,
    chain: &Chain,
    y: Vec3,
    delta: &[[f64; 1]; 2 * MAX_CHAIN],
    beta: f32,
    time: f32,
) -> Option<(Chain, [f64; 2 * MAX_CHAIN])> {
    let mut moved = *chain;
    let mut from = *x;
    for i in 0..chain.len {
        let v = &chain.v[i];
        let (s, t) = frame_tangents(v.sp.ns.as_dvec3());
        let target = (v.sp.p.as_dvec3()
            + beta as f64 * (delta[2 * i][0] * s + delta[2 * i + 1][0] * t))
            .as_vec3();
        moved.v[i] = project(scene, &from, target, time)?;
        from = Anchor::of(&moved.v[i].sp);
    }
    let c = constraints(x.p, &moved, y)?;
    Some((moved, c))
}

/// The generalized geometry term of a solved chain: `|dω_x/dA_y|` with `y` moved in the
/// plane normal to `n_y` (see the module docs).
fn geometry_term(
    scene: &RenderScene,
    x: &Anchor,
    chain: &Chain,
    y: Vec3,
    n_y: Vec3,
    time: f32,
) -> Option<f32> {
    let n = 2 * chain.len;
    let a = jacobian(scene, x, chain, y, time, None)?;
    // `∂C/∂y`: only the last vertex's constraint sees `y`, through its `wb`.
    let frame = Frame::from_normal(n_y);
    let (prev, _) = neighbours(x.p, chain, chain.len - 1, y);
    let last = Local::of(prev, &chain.v[chain.len - 1], y.as_dvec3())?;
    let mut b = [[0.0; 2]; 2 * MAX_CHAIN];
    for (j, e) in [frame.s, frame.t].into_iter().enumerate() {
        let d = last.d(last.dh_b(e.as_dvec3()), DVec3::ZERO, DVec3::ZERO);
        b[n - 2][j] = d[0];
        b[n - 1][j] = d[1];
    }
    let m = solve(a, b, n)?;
    let det = m[0][0] * m[1][1] - m[0][1] * m[1][0];
    let first = &chain.v[0].sp;
    let d = (first.p - x.p).as_dvec3();
    let r2 = d.length_squared();
    let cos = (d / r2.sqrt()).dot(first.ns.as_dvec3()).abs();
    let g = (cos / r2 * det.abs()) as f32;
    (g.is_finite() && g > 0.0).then_some(g)
}

/// Seeds, solves and checks the connection from `x` to the light point `end`: `None` if
/// the seed is empty or blocked, the solver does not converge, a vertex's BSDF does not
/// send light along the solved chain, or the last segment is blocked.
pub fn connect(
    scene: &RenderScene,
    x: &Anchor,
    end: &LightEnd,
    time: f32,
    max_chain: usize,
) -> Option<Connection> {
    let y = end.p();
    // Only an area light's seeds may be skipped: what MNEE leaves of its light, BSDF
    // sampling finds. A point light's would be lost.
    let skip_steep = matches!(end, LightEnd::Area { .. });
    let chain = seed(scene, x, y, time, max_chain, skip_steep)?;
    let chain = newton(scene, x, chain, y, time)?;
    // The specular vertices' delta BSDF values along the solved directions, and the
    // media between them.
    let mut throughput = Vec3::ONE;
    let mut prev = x.p;
    for i in 0..chain.len {
        let v = &chain.v[i];
        let next = if i + 1 == chain.len {
            y
        } else {
            chain.v[i + 1].sp.p
        };
        let to_prev = (prev - v.sp.p).normalize_or_zero();
        let to_next = (next - v.sp.p).normalize_or_zero();
        let bsdf: Bsdf = scene.bsdf(&v.sp, to_prev);
        let frame = Frame::from_normal(v.sp.ns);
        let wo = frame.to_local(to_prev);
        // Refraction is the sample above the Fresnel reflectance, reflection below it.
        let u1 = if v.eta > 0.0 { 1.0 - f32::EPSILON } else { 0.0 };
        let bs = bsdf.sample(wo, u1, Vec2::ZERO)?;
        let wi = frame.to_world(bs.wi);
        if !bs.delta || wi.dot(to_next) < DIRECTION_AGREEMENT {
            return None;
        }
        // As the path tracer: a sample crossing the geometric surface on the wrong side
        // is no path.
        if wi.dot(v.sp.ng).signum() != bs.wi.z.signum()
            || to_prev.dot(v.sp.ng).signum() != wo.z.signum()
        {
            return None;
        }
        throughput *= bs.weight * bs.pdf;
        throughput *= scene.transmittance(&v.sp, -to_prev, (v.sp.p - prev).length());
        prev = v.sp.p;
    }
    let last = &chain.v[chain.len - 1].sp;
    let d = y - last.p;
    let dist = d.length();
    if dist <= 0.0 {
        return None;
    }
    let dir = d / dist;
    let origin = offset_ray_origin(last.p, last.p_error, last.ng, dir);
    let (emission, geometry) = match *end {
        LightEnd::Area { li, n, .. } => {
            // The last segment must reach the sampled light there.
            let hit = scene.intersect_at(origin, dir, dist * 1.01, time)?;
            let sp = scene.surface(&hit, origin, dir);
            if sp.light as usize != li || (sp.p - y).length() > 1e-3 * (1.0 + dist) {
                return None;
            }
            throughput *= scene.transmittance(&sp, dir, hit.t);
            let le = scene.emitted(&sp, -dir);
            (le, geometry_term(scene, x, &chain, y, n, time)?)
        }
        LightEnd::Point { li, .. } => {
            if scene.occluded_at(origin, dir, dist * (1.0 - 1e-4), time) {
                return None;
            }
            let Light::Punctual(p) = &scene.lights.lights[li] else {
                return None;
            };
            let (_, intensity) = p.intensity_toward(-dir)?;
            // Moved perpendicular to the direction it leaves by: `|dω_x/dA⊥_y|`.
            (intensity, geometry_term(scene, x, &chain, y, dir, time)?)
        }
    };
    if emission == Vec3::ZERO || throughput == Vec3::ZERO {
        return None;
    }
    let wi = (chain.v[0].sp.p - x.p).normalize_or_zero();
    Some(Connection {
        chain,
        wi,
        throughput,
        emission,
        geometry,
    })
}

/// The light end MNEE samples for light `li` from `x` with `u` (the next-event
/// estimation sample's dimensions), with its density per unit light area times `pmf`
/// (the light selection's probability; per point for a point light). `None` for lights
/// MNEE does not sample (spheres, the environment, directional lights).
pub fn sample_end(
    scene: &RenderScene,
    x: Vec3,
    li: usize,
    pmf: f32,
    u: Vec2,
) -> Option<(LightEnd, f32)> {
    match &scene.lights.lights[li] {
        Light::Triangle(_) => {
            let ls = scene.sample_li(li, x, u)?;
            let cos = ls.n.dot(ls.wi).abs();
            let pdf = pmf * ls.pdf * cos / (ls.dist * ls.dist);
            (pdf > 0.0 && pdf.is_finite()).then_some((
                LightEnd::Area {
                    li,
                    p: ls.p,
                    n: ls.n,
                },
                pdf,
            ))
        }
        Light::Punctual(p) => {
            let (position, _) = p.intensity_toward(Vec3::Z)?;
            Some((LightEnd::Point { li, p: position }, pmf))
        }
        _ => None,
    }
}

/// The MNEE estimate at the shading point `sp` (BSDF `bsdf` in the shading frame
/// `frame`, outgoing direction `wo` in that frame) for light `li` chosen with
/// probability `pmf`, from the light sample's dimensions `u`; zero where there is no
/// specular connection. Multiply by the path throughput.
#[allow(clippy::too_many_arguments)]
pub fn estimate(
    scene: &RenderScene,
    sp: &SurfacePoint,
    bsdf: &Bsdf,
    frame: &Frame,
    wo: Vec3,
    li: usize,
    pmf: f32,
    u: Vec2,
    time: f32,
    max_chain: usize,
) -> Vec3 {
    let Some((end, pdf)) = sample_end(scene, sp.p, li, pmf, u) else {
        return Vec3::ZERO;
    };
    let x = Anchor::of(sp);
    let Some(c) = connect(scene, &x, &end, time, max_chain) else {
        return Vec3::ZERO;
    };
    let wi = frame.to_local(c.wi);
    // Light arriving through the geometric surface (a shading-normal leak) is rejected,
    // as by next-event estimation.
    if c.wi.dot(sp.ng).signum() != wi.z.signum() {
        return Vec3::ZERO;
    }
    let f = bsdf.eval(wo, wi);
    f * c.throughput * c.emission * (c.geometry / pdf)
}

/// Whether next-event estimation's shadow ray from `x` to the light point `y` (position
/// error `y_error`, normal `n_y`) is unoccluded: the ray the path tracer casts, from `x`
/// offset toward `y` to `y` offset back toward `x`. Where it is, the straight segment
/// crosses no specular surface, so MNEE's seed chain is empty and the path tracer does not
/// run MNEE for that light sample; [`claims`] asks the same question first, so that a
/// path MNEE never generates is never claimed (the partition below).
pub fn shadow_ray_clear(
    scene: &RenderScene,
    x: &Anchor,
    y: Vec3,
    y_error: Vec3,
    n_y: Vec3,
    time: f32,
) -> bool {
    let wi = (y - x.p).normalize_or_zero();
    let o = x.origin(wi);
    let target = offset_ray_origin(y, y_error, n_y, -wi);
    let d = target - o;
    let dist = d.length();
    dist > 0.0 && !scene.occluded_at(o, d / dist, dist * (1.0 - 1e-4), time)
}

/// Whether MNEE from `x` (selection normal `n_select`, chains up to `max_chain`) would
/// have produced the BSDF-sampled path that left `x`, crossed the specular vertices
/// `path` and hit the emitter at `light` (see "Combination with BSDF sampling" in the
/// module docs): then the path tracer leaves that path's emission to MNEE.
pub fn claims(
    scene: &RenderScene,
    x: &Anchor,
    n_select: Vec3,
    max_chain: usize,
    path: &[Vec3],
    light: &SurfacePoint,
    time: f32,
) -> bool {
    let li = light.light as usize;
    if path.is_empty() || !matches!(scene.lights.lights.get(li), Some(Light::Triangle(_))) {
        return false;
    }
    // MNEE samples this light point only if next-event estimation's light sample can
    // land on it: the light selected with positive probability, a positive density, and
    // emission toward `x` along the straight line (else `sample_li` returns nothing).
    let d = light.p - x.p;
    let dist = d.length();
    if dist <= 0.0 {
        return false;
    }
    let pmf = scene.lights.pmf_at(x.p, n_select, li);
    let pdf = scene.lights.lights[li].pdf_li(x.p, d / dist, light.p, light.ng);
    if !(pmf > 0.0 && pdf > 0.0) || scene.emitted(light, -d / dist) == Vec3::ZERO {
        return false;
    }
    // The path tracer runs MNEE only where next-event estimation's shadow ray to the light
    // point was blocked: ask the same question, with the same ray, so that the two sides
    // of the partition agree even where a seed ray and the shadow ray, whose ends are
    // offset differently, would disagree at a silhouette's edge.
    if shadow_ray_clear(scene, x, light.p, light.p_error, light.ng, time) {
        return false;
    }
    let end = LightEnd::Area {
        li,
        p: light.p,
        n: light.ng,
    };
    let Some(c) = connect(scene, x, &end, time, max_chain) else {
        return false;
    };
    let tol = 1e-3 * (1.0 + dist);
    c.chain.len() == path.len()
        && c.chain
            .positions()
            .zip(path)
            .all(|(a, b)| (a - *b).length() <= tol)
}

#[cfg(test)]
mod tests;
