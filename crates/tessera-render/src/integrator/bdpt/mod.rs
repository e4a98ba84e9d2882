//! Bidirectional path tracing (Veach & Guibas 1995, section 4.3; the structure follows
//! pbrt 3rd ed. ch. 16).
//!
//! Every camera sample builds two subpaths: a *camera subpath* `z0 z1 ...` from the lens
//! (z0 is the camera vertex) and a *light subpath* `y0 y1 ...` from a light chosen in
//! proportion to its power, started by emission sampling ([`crate::light::emission`]). Each
//! prefix `y0..y(s-1)` of the light subpath joined to each prefix `z0..z(t-1)` of the camera
//! subpath is one sample of the path-space integrand from technique `(s, t)` (Veach & Guibas 1995, eq. 17
//! and fig. 8):
//!
//! - `s = 0`: the camera subpath hits an emitter (area light, or the environment when it
//!   escapes);
//! - `s = 1`: next-event estimation: a light point is sampled *from* `z(t-1)` with the
//!   light's own `sample_li` (cone sampling for spheres) and connected;
//! - `t = 1`: light tracing: the lens is sampled from `y(s-1)` and the contribution is
//!   *splatted* onto the film where the ray lands, weighted by the camera importance `We`
//!   (Hanrahan 2001, chapter 7: importance is the adjoint of radiance; [`crate::camera`]);
//! - otherwise: `y(s-1)` and `z(t-1)` are joined by a shadow ray with the geometry term `G`.
//!
//! `(1, 1)` (seeing a light point directly from a sampled lens point) is not used, `(0, 2)`
//! is the only technique for a directly visible emitter, and `t = 0` is impossible (the
//! lens is not in the scene). Every technique is weighted with the power heuristic (β = 2;
//! `MisHeuristic::Balance` selects β = 1) over all techniques that could have produced the
//! same path, computed from the per-vertex forward and reverse densities in area measure
//! with the ratio recurrence of Veach's thesis §10.2 (pbrt's `MISWeight`): delta vertices and
//! delta lights make the techniques that would connect at them impossible, and their
//! densities are remapped to 1 so the ratios stay defined. Russian roulette ends subpaths
//! after `rr_depth` bounces; it is left out of the MIS densities, which keeps the estimator
//! unbiased because the weights of all techniques still sum to one for every path.
//!
//! Light subpaths carry importance transport: their BSDF factors are the adjoint
//! `f*(wo, wi) = f(wi, wo)`, they do not take the `1/η²` radiance scaling of refraction,
//! and shading normals get Veach's correction `|wo·ns||wi·ng| / (|wo·ng||wi·ns|)`.
//!
//! # Splatting and determinism (ARCHITECTURE.md §2)
//! A light-tracing contribution lands on whichever pixel the connection hits, not on the
//! pixel whose sample produced it. Splats are kept deterministic this way:
//!
//! - the light subpath of sample `i` of pixel `p` in pass `k` is drawn from its own sampler
//!   stream, `PixelSampler(job seed ^ LIGHT_STREAM, frame, p, k)`, so it is a pure function of
//!   (scene, settings, seed, frame, pixel, pass, sample index), like the camera subpath;
//! - for `bdpt` the frame plan has **one tile covering the whole frame**
//!   (`FramePlan::whole_frame`), so every splat lands in the tile being rendered; work units
//!   are (frame, pass range) and still run in parallel, across passes, in `render_frame` and
//!   on farm workers;
//! - within a unit each pass is rendered single-threaded in a fixed order (pixels row-major,
//!   samples in index order) into one f64 accumulator per pixel, camera contributions and
//!   splats interleaved in that order: identical bytes for a unit rendered twice, and the
//!   same image for any thread count and any split into pass ranges.
//!
//! Each camera sample traces one light subpath, so a pass traces `W H S` light paths. With
//! `We` normalised over the whole image, the pass mean of a pixel is
//! `(sum of its S camera contributions + sum of the splats landing in it) / S`, an unbiased
//! estimate of the pixel (pbrt's `1/spp` splat scale), and passes stay independent
//! replicates (ARCHITECTURE.md §3).
//!
//! A plan with smaller tiles still renders correctly: a unit then traces the light subpaths
//! of *every* pixel of the frame for its passes and keeps the splats that land in its tile
//! (the subpath of a pixel outside the tile is traced alone), which costs `tile count` times
//! the light tracing. `tessera` always plans `bdpt` with the whole-frame tile.
//!
//! # Adaptive stopping
//! A pixel the adaptive policy has stopped traces no camera subpath: its camera
//! techniques (`t >= 2`, with their connections) are the bulk of a sample's cost. Its light
//! subpaths are still traced, because their splats belong to other pixels; skipping them
//! would change every pixel they land in. So a stopped pixel costs its light subpaths
//! only, and the wanted pixels get exactly the values of a render of every pixel.
//!
//! Limits: subpaths have at most [`MAX_BDPT_DEPTH`] bounces (fixed-size vertex arrays on the
//! stack: nothing is allocated per sample); deeper `max_depth` settings are clamped.

use super::{render_whole_frame, MisHeuristic, SampleSource, SampleStream, WholeFrame};
use crate::bsdf::diffuse::Diffuse;
use crate::bsdf::{Bsdf, Lobe};
use crate::camera::CameraModel;
use crate::geometry::NO_LIGHT;
use crate::light::emission::WorldDisk;
use crate::light::Light;
use crate::math::offset_ray_origin;
use crate::sampling::warp::Frame;
use crate::sampling::PixelSampler;
use crate::scene::RenderScene;
use glam::{Vec2, Vec3};
use tessera_farm::{FramePlan, UnitResult, WorkUnit};

mod strategies;
pub use strategies::render_unit;
pub(super) use strategies::{technique, Scratch};

/// Largest number of bounces of a bidirectional path; `max_depth` is clamped to it.
pub const MAX_BDPT_DEPTH: u32 = 32;
/// Vertices of a camera subpath: the camera, then up to `MAX_BDPT_DEPTH + 1` surfaces.
pub(super) const MAX_VERTICES: usize = MAX_BDPT_DEPTH as usize + 2;
/// Mixed into the job seed for the light subpaths' sampler stream.
const LIGHT_STREAM: u64 = 0x6c69_6768_745f_7061; // "light_pa"

/// Settings of the bidirectional integrator.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BdptSettings {
    /// Weighting heuristic: balance (β = 1), otherwise the power heuristic (β = 2).
    pub mis: MisHeuristic,
    /// Maximum number of bounces of a full path (clamped to [`MAX_BDPT_DEPTH`]).
    pub max_depth: u32,
    /// Russian roulette ends subpaths after this many bounces.
    pub rr_depth: u32,
}

impl BdptSettings {
    /// Settings with `max_depth` clamped to `1..=MAX_BDPT_DEPTH`.
    pub fn new(mis: MisHeuristic, max_depth: u32, rr_depth: u32) -> Self {
        Self {
            mis,
            max_depth: max_depth.clamp(1, MAX_BDPT_DEPTH),
            rr_depth,
        }
    }

    fn beta_exponent(&self) -> i32 {
        match self.mis {
            MisHeuristic::Balance => 1,
            _ => 2,
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kind {
    Camera,
    Light,
    Surface,
}

/// One vertex of a subpath. `Copy` and fixed-size: subpaths are arrays on the stack.
#[derive(Clone, Copy, Debug)]
pub(super) struct Vertex {
    kind: Kind,
    /// Position (for a light at infinity: unused).
    p: Vec3,
    p_error: Vec3,
    /// Geometric normal; zero for the camera and point-like or distant lights.
    ng: Vec3,
    /// Shading normal (surfaces).
    ns: Vec3,
    /// Surfaces: unit direction toward the previous vertex of the subpath. Lights at
    /// infinity: the direction light travels in.
    wo: Vec3,
    frame: Frame,
    bsdf: Bsdf,
    /// Throughput of the subpath up to this vertex (radiance or importance weight).
    beta: Vec3,
    /// Radiance emitted toward the previous vertex (camera subpath on an emitter).
    le: Vec3,
    /// Light index: the emitter of a light vertex, or of an emissive surface.
    light: u32,
    /// A light at infinity (environment, directional).
    infinite: bool,
    /// The subpath scattered here by a delta lobe.
    delta: bool,
    /// A delta light (point, spot, directional).
    delta_light: bool,
    /// Area density of this vertex as generated by its own subpath.
    pdf_fwd: f32,
    /// Area density of this vertex if generated by the other subpath.
    pdf_rev: f32,
}

/// A vertex without its BSDF: all an endpoint (a camera or light vertex, whose BSDF is
/// never evaluated) holds. `mis_weight` swaps a sampled endpoint in and out through it
/// rather than copying whole vertices (hundreds of bytes each) once per technique, and
/// `random_walk` writes a surface vertex through it and its BSDF separately, in place.
#[derive(Clone, Copy)]
struct Endpoint {
    kind: Kind,
    p: Vec3,
    p_error: Vec3,
    ng: Vec3,
    ns: Vec3,
    wo: Vec3,
    frame: Frame,
    beta: Vec3,
    le: Vec3,
    light: u32,
    infinite: bool,
    delta: bool,
    delta_light: bool,
    pdf_fwd: f32,
    pdf_rev: f32,
}

impl Vertex {
    /// Every field but the BSDF (the patterns name every field, so a new one is not
    /// forgotten).
    #[inline]
    fn endpoint(&self) -> Endpoint {
        let Vertex {
            kind,
            p,
            p_error,
            ng,
            ns,
            wo,
            frame,
            bsdf: _,
            beta,
            le,
            light,
            infinite,
            delta,
            delta_light,
            pdf_fwd,
            pdf_rev,
        } = *self;
        Endpoint {
            kind,
            p,
            p_error,
            ng,
            ns,
            wo,
            frame,
            beta,
            le,
            light,
            infinite,
            delta,
            delta_light,
            pdf_fwd,
            pdf_rev,
        }
    }

    /// Sets every field but the BSDF from `e`.
    #[inline]
    fn set_endpoint(&mut self, e: Endpoint) {
        let Vertex {
            kind,
            p,
            p_error,
            ng,
            ns,
            wo,
            frame,
            bsdf: _,
            beta,
            le,
            light,
            infinite,
            delta,
            delta_light,
            pdf_fwd,
            pdf_rev,
        } = self;
        *kind = e.kind;
        *p = e.p;
        *p_error = e.p_error;
        *ng = e.ng;
        *ns = e.ns;
        *wo = e.wo;
        *frame = e.frame;
        *beta = e.beta;
        *le = e.le;
        *light = e.light;
        *infinite = e.infinite;
        *delta = e.delta;
        *delta_light = e.delta_light;
        *pdf_fwd = e.pdf_fwd;
        *pdf_rev = e.pdf_rev;
    }

    fn empty() -> Self {
        Self {
            kind: Kind::Camera,
            p: Vec3::ZERO,
            p_error: Vec3::ZERO,
            ng: Vec3::ZERO,
            ns: Vec3::ZERO,
            wo: Vec3::ZERO,
            frame: Frame::from_normal(Vec3::Z),
            bsdf: Bsdf::single(Lobe::Diffuse(Diffuse { albedo: Vec3::ZERO })),
            beta: Vec3::ZERO,
            le: Vec3::ZERO,
            light: NO_LIGHT,
            infinite: false,
            delta: false,
            delta_light: false,
            pdf_fwd: 0.0,
            pdf_rev: 0.0,
        }
    }

    #[inline]
    fn on_surface(&self) -> bool {
        self.ng != Vec3::ZERO
    }

    #[inline]
    fn is_light(&self) -> bool {
        self.kind == Kind::Light || (self.kind == Kind::Surface && self.light != NO_LIGHT)
    }

    #[inline]
    fn connectible(&self) -> bool {
        match self.kind {
            Kind::Surface => self.bsdf.has_non_delta(),
            Kind::Camera => true,
            Kind::Light => !(self.infinite && self.delta_light),
        }
    }

    /// Unit direction from this vertex toward `next`, or `None` if they coincide.
    #[inline]
    fn dir_to(&self, next: &Vertex) -> Option<Vec3> {
        if next.infinite {
            return Some(-next.wo);
        }
        (next.p - self.p).try_normalize()
    }
}

/// Scene data the vertex densities need.
pub(super) struct Ctx<'a> {
    pub(super) scene: &'a RenderScene,
    pub(super) world: WorldDisk,
    /// The sample's shutter fraction (motion blur): both subpaths and every connection
    /// see the scene at this one time.
    pub(super) time: f32,
    /// The camera at `time`.
    pub(super) camera: CameraModel,
}

impl<'a> Ctx<'a> {
    /// The context of `scene` at shutter time 0.
    pub(super) fn new(scene: &'a RenderScene) -> Self {
        Ctx {
            scene,
            world: WorldDisk::new(scene.geometry.bounds_center, scene.geometry.bounds_radius),
            time: 0.0,
            camera: scene.camera,
        }
    }

    /// Moves the context to shutter fraction `time` (motion blur).
    pub(super) fn set_time(&mut self, time: f32) {
        self.time = time;
        self.camera = self.scene.camera_at(time);
    }
}

impl Ctx<'_> {
    /// Converts a solid-angle density at `from` toward `next` into area density at `next`
    /// (Veach & Guibas 1995, section 4.3: "vertices chosen using a directional distribution can be converted to
    /// the area measure", `p_A = p_ω |cos θ_next| / d²`).
    #[inline]
    fn convert_density(&self, from: &Vertex, pdf: f32, next: &Vertex) -> f32 {
        if next.infinite {
            return pdf;
        }
        let w = next.p - from.p;
        let d2 = w.length_squared();
        if d2 == 0.0 {
            return 0.0;
        }
        let inv = 1.0 / d2;
        let mut pdf = pdf * inv;
        if next.on_surface() {
            pdf *= next.ng.dot(w * inv.sqrt()).abs();
        }
        pdf
    }

    /// Area density at `next` of the vertex after `v` when `v` was reached from `prev`.
    fn pdf(&self, v: &Vertex, prev: Option<&Vertex>, next: &Vertex) -> f32 {
        match v.kind {
            Kind::Light => self.pdf_light(v, next),
            Kind::Camera => {
                let Some(wn) = v.dir_to(next) else {
                    return 0.0;
                };
                let pdf = self.camera.pdf_dir(v.p, wn);
                self.convert_density(v, pdf, next)
            }
            Kind::Surface => {
                let (Some(wn), Some(prev)) = (v.dir_to(next), prev) else {
                    return 0.0;
                };
                let Some(wp) = v.dir_to(prev) else {
                    return 0.0;
                };
                let pdf = v.bsdf.pdf(v.frame.to_local(wp), v.frame.to_local(wn));
                self.convert_density(v, pdf, next)
            }
        }
    }

    /// Area density at `next` of the first bounce of a light subpath leaving the light
    /// vertex (or emissive surface) `v` toward it.
    fn pdf_light(&self, v: &Vertex, next: &Vertex) -> f32 {
        if v.infinite {
            // Distant lights emit from the world disk: the density of `next` is the disk's
            // area density projected onto `next`'s surface.
            let mut pdf = self.world.pdf_pos();
            if next.on_surface() {
                pdf *= next.ng.dot(v.wo).abs();
            }
            return pdf;
        }
        let w = next.p - v.p;
        let d2 = w.length_squared();
        if d2 == 0.0 || v.light == NO_LIGHT {
            return 0.0;
        }
        let w = w / d2.sqrt();
        let light = &self.scene.lights.lights[v.light as usize];
        let (_, pdf_dir) = light.pdf_le(v.ng, w, &self.world);
        let mut pdf = pdf_dir / d2;
        if next.on_surface() {
            pdf *= next.ng.dot(w).abs();
        }
        pdf
    }

    /// Density of the light vertex `v` itself as the start of a light subpath (light
    /// selection times position density; for the environment the direction density).
    fn pdf_light_origin(&self, v: &Vertex, next: &Vertex) -> f32 {
        if v.light == NO_LIGHT {
            return 0.0;
        }
        let li = v.light as usize;
        let pmf = self.scene.lights.pmf(li);
        let light = &self.scene.lights.lights[li];
        if v.infinite {
            return match light {
                // Direction density of `-w`, toward the environment.
                Light::Environment(_) => pmf * light.pdf_le(Vec3::ZERO, v.wo, &self.world).1,
                _ => pmf,
            };
        }
        let Some(w) = v.dir_to(next) else {
            return 0.0;
        };
        pmf * light.pdf_le(v.ng, w, &self.world).0
    }

    /// The BSDF factor at surface vertex `v` for light arriving from / leaving toward the
    /// unit direction `wn` (the other end of a connection). Camera subpath (radiance):
    /// `f(wo = toward camera, wi = wn)`. Light subpath (importance): the adjoint
    /// `f(wo = wn, wi = toward light)`, times Veach's shading-normal correction.
    #[inline]
    fn f(&self, v: &Vertex, wn: Vec3, importance: bool) -> Vec3 {
        let a = v.frame.to_local(v.wo);
        let b = v.frame.to_local(wn);
        // Light leaking through the geometric surface (shading normals) carries nothing.
        if a.z * v.wo.dot(v.ng) <= 0.0 || b.z * wn.dot(v.ng) <= 0.0 {
            return Vec3::ZERO;
        }
        if importance {
            // eval includes |cos| of its second argument; divide it out.
            let f = v.bsdf.eval(b, a) / a.z.abs();
            let num = v.wo.dot(v.ns).abs() * wn.dot(v.ng).abs();
            let den = v.wo.dot(v.ng).abs() * wn.dot(v.ns).abs();
            if den == 0.0 {
                return Vec3::ZERO;
            }
            f * (num / den)
        } else {
            v.bsdf.eval(a, b) / b.z.abs()
        }
    }

    /// Unoccluded between two points (robust shadow ray with offset end points).
    fn visible(&self, a: Vec3, a_err: Vec3, a_n: Vec3, b: Vec3, b_err: Vec3, b_n: Vec3) -> bool {
        let d = b - a;
        let o = offset_ray_origin(a, a_err, a_n, d);
        let t = offset_ray_origin(b, b_err, b_n, -d);
        let d = t - o;
        let dist = d.length();
        dist > 0.0
            && !self
                .scene
                .occluded_at(o, d / dist, dist * (1.0 - 1e-4), self.time)
    }

    /// `G(a ↔ b)` with shading-normal cosines (pbrt's convention), times visibility.
    fn g(&self, a: &Vertex, b: &Vertex) -> f32 {
        let d = a.p - b.p;
        let d2 = d.length_squared();
        if d2 == 0.0 {
            return 0.0;
        }
        let w = d / d2.sqrt();
        let mut g = 1.0 / d2;
        if a.on_surface() {
            g *= a.ns.dot(w).abs();
        }
        if b.on_surface() {
            g *= b.ns.dot(w).abs();
        }
        if g == 0.0 || !self.visible(a.p, a.p_error, a.ng, b.p, b.p_error, b.ng) {
            return 0.0;
        }
        g
    }
}

/// Extends a subpath from `path[start - 1]` along `(origin, dir)` until it has
/// `max_vertices` vertices, leaves the scene, is absorbed or stopped by Russian roulette.
/// Returns the number of vertices. `pdf_dir` is the solid-angle density of `dir`.
#[allow(clippy::too_many_arguments)]
fn random_walk<S: SampleSource>(
    ctx: &Ctx,
    s: &BdptSettings,
    path: &mut [Vertex; MAX_VERTICES],
    start: usize,
    max_vertices: usize,
    mut origin: Vec3,
    mut dir: Vec3,
    mut beta: Vec3,
    pdf_dir: f32,
    sampler: &mut S,
    importance: bool,
) -> usize {
    let scene = ctx.scene;
    let beta0 = beta.max_element();
    let mut pdf_fwd = pdf_dir;
    let mut n = start;
    let mut bounces = 0u32;
    while n < max_vertices {
        // 1. Intersect; a camera ray that escapes sees the environment (a light vertex).
        let Some(hit) = scene.intersect_at(origin, dir, f32::INFINITY, ctx.time) else {
            if !importance {
                if let Some((env, le)) = scene.environment(dir) {
                    let mut v = Vertex::empty();
                    v.kind = Kind::Light;
                    v.infinite = true;
                    v.wo = -dir;
                    v.light = env as u32;
                    v.beta = beta;
                    v.le = le;
                    v.pdf_fwd = pdf_fwd; // solid angle: the vertex is a direction
                    path[n] = v;
                    n += 1;
                }
            }
            break;
        };
        let sp = scene.surface(&hit, origin, dir);
        // Absorption inside a KHR_materials_volume medium along the segment just traced
        // (connections between two vertices inside a medium are not attenuated).
        beta *= scene.transmittance(&sp, dir, hit.t);
        // Written in place, the BSDF straight into its slot: a vertex (with its BSDF) is
        // large, and one built on the stack is copied whole into the array.
        let (before, here) = path.split_at_mut(n);
        let v = &mut here[0];
        v.set_endpoint(Endpoint {
            kind: Kind::Surface,
            p: sp.p,
            p_error: sp.p_error,
            ng: sp.ng,
            ns: sp.ns,
            wo: -dir,
            frame: Frame::from_normal(sp.ns),
            beta,
            le: if !importance && sp.light != NO_LIGHT {
                scene.emitted(&sp, -dir)
            } else {
                Vec3::ZERO
            },
            light: sp.light,
            infinite: false,
            delta: false,
            delta_light: false,
            pdf_fwd: 0.0,
            pdf_rev: 0.0,
        });
        v.bsdf = scene.bsdf(&sp, -dir);
        v.pdf_fwd = ctx.convert_density(&before[n - 1], pdf_fwd, v);
        n += 1;
        if n >= max_vertices {
            break;
        }

        // 2. Sample the BSDF (fixed dimension order: lobe, direction, roulette).
        let u1 = sampler.next_1d();
        let u2 = sampler.next_2d();
        let u_rr = sampler.next_1d();
        let wo = v.frame.to_local(-dir);
        let Some(bs) = v.bsdf.sample(wo, u1, u2) else {
            break;
        };
        let wi = v.frame.to_world(bs.wi);
        if wi.dot(sp.ng) * bs.wi.z <= 0.0 {
            break; // crosses the geometric surface on the wrong side
        }
        let weight = if !importance {
            bs.weight
        } else if bs.delta {
            // Power is not scaled by 1/η² on refraction: undo the radiance scaling.
            match v.bsdf.glass_eta() {
                Some(eta) if bs.wi.z * wo.z < 0.0 => {
                    let e = if wo.z > 0.0 { eta } else { 1.0 / eta };
                    bs.weight * (e * e)
                }
                _ => bs.weight,
            }
        } else if wo.z == 0.0 {
            Vec3::ZERO
        } else {
            // Adjoint BSDF f*(wo, wi) = f(wi, wo), times |cos θi| / pdf.
            v.bsdf.eval(bs.wi, wo) * (bs.wi.z.abs() / (wo.z.abs() * bs.pdf))
        };
        let weight = if importance {
            let num = wo.z.abs() * wi.dot(sp.ng).abs();
            let den = (-dir).dot(sp.ng).abs() * bs.wi.z.abs();
            if den == 0.0 {
                Vec3::ZERO
            } else {
                weight * (num / den)
            }
        } else {
            weight
        };
        beta *= weight;
        let (fwd, rev) = if bs.delta {
            (0.0, 0.0)
        } else {
            (bs.pdf, v.bsdf.pdf(bs.wi, wo))
        };
        path[n - 1].delta = bs.delta;
        let rev_area = ctx.convert_density(&path[n - 1], rev, &path[n - 2]);
        path[n - 2].pdf_rev = rev_area;
        pdf_fwd = fwd;
        if !beta.is_finite() || beta == Vec3::ZERO {
            break;
        }

        // 3. Russian roulette on the throughput relative to the subpath's start.
        bounces += 1;
        if bounces >= s.rr_depth {
            let survive = (beta.max_element() / beta0).clamp(0.05, 1.0);
            if u_rr >= survive {
                break;
            }
            beta /= survive;
        }
        origin = offset_ray_origin(sp.p, sp.p_error, sp.ng, wi);
        dir = wi;
    }
    n
}

/// Builds the camera subpath through film position `film`, of at most `max` vertices (bdpt:
/// `max_depth + 2`); returns its vertex count.
pub(super) fn camera_subpath<S: SampleSource>(
    ctx: &Ctx,
    s: &BdptSettings,
    film: Vec2,
    lens_u: Vec2,
    path: &mut [Vertex; MAX_VERTICES],
    max: usize,
    sampler: &mut S,
) -> usize {
    let camera = &ctx.camera;
    let (o, d) = camera.generate_ray(film, lens_u);
    let mut v = Vertex::empty();
    v.kind = Kind::Camera;
    v.p = o;
    v.beta = Vec3::ONE;
    path[0] = v;
    let pdf_dir = camera.pdf_dir(o, d);
    if pdf_dir.is_nan() || pdf_dir <= 0.0 || max <= 1 {
        return 1;
    }
    random_walk(
        ctx,
        s,
        path,
        1,
        max,
        o,
        d,
        Vec3::ONE,
        pdf_dir,
        sampler,
        false,
    )
}

/// Builds the light subpath of at most `max` vertices (bdpt: `max_depth + 1`); returns its
/// vertex count (0 without lights).
pub(super) fn light_subpath<S: SampleSource>(
    ctx: &Ctx,
    s: &BdptSettings,
    path: &mut [Vertex; MAX_VERTICES],
    max: usize,
    sampler: &mut S,
) -> usize {
    let scene = ctx.scene;
    let u_light = sampler.next_1d();
    let u_pos = sampler.next_2d();
    let u_dir = sampler.next_2d();
    let Some((li, pmf)) = scene.lights.select(u_light) else {
        return 0;
    };
    let light = &scene.lights.lights[li];
    let Some(es) = scene.sample_le(li, u_pos, u_dir, &ctx.world) else {
        return 0;
    };
    let infinite = light.is_infinite();
    let mut v = Vertex::empty();
    v.kind = Kind::Light;
    v.p = es.p;
    v.p_error = es.p_error;
    v.ng = es.n;
    v.ns = es.n;
    v.light = li as u32;
    v.infinite = infinite;
    v.delta_light = light.is_delta();
    v.beta = es.le;
    if infinite {
        v.wo = es.dir;
        v.pdf_fwd = match light {
            Light::Environment(_) => pmf * es.pdf_dir,
            _ => pmf,
        };
    } else {
        v.pdf_fwd = pmf * es.pdf_pos;
    }
    path[0] = v;
    let beta = es.weight() / pmf;
    let origin = if es.n == Vec3::ZERO {
        es.p
    } else {
        offset_ray_origin(es.p, es.p_error, es.n, es.dir)
    };
    if max <= 1 {
        return 1;
    }
    let n = random_walk(
        ctx, s, path, 1, max, origin, es.dir, beta, es.pdf_dir, sampler, true,
    );
    if infinite && n > 1 {
        // The first surface of a distant light's subpath is found by a point on the world
        // disk, not by a direction from a point: its density is the disk's, projected.
        let mut pdf = es.pdf_pos;
        if path[1].on_surface() {
            pdf *= path[1].ng.dot(es.dir).abs();
        }
        path[1].pdf_fwd = pdf;
    }
    n
}
