//! Vertex connection and merging (Georgiev, Křivánek, Davidovič & Slusallek 2012, "Light
//! transport simulation with vertex connection and merging", sections 4-5 and the technical
//! report's equations 31-55; Hachisuka, Pantaleoni & Jensen 2012 describe the same unified
//! estimator). SmallVCM (Davidovič & Georgiev) is the reference implementation this one was
//! checked against.
//!
//! Every pass is one iteration of the algorithm:
//!
//! 1. **Light subpaths.** Each camera sample of the frame traces one light subpath (as in
//!    [`super::bdpt`]: a light chosen by power, emission sampled, importance transport with
//!    the adjoint BSDF, no `1/η²` on refraction, Veach's shading-normal correction). Its
//!    non-specular vertices are the pass's *photons*: `N = W H S` light paths per pass
//!    (`S` samples per pixel per pass).
//! 2. **The photon map.** A hash grid of cell size `2 r` over the photons, built
//!    single-threaded in the order the light subpaths were traced (pixels row-major,
//!    samples in index order), so it is a pure function of (scene, settings, seed, frame,
//!    pass).
//! 3. **Camera subpaths.** Each camera vertex on a non-specular surface takes every
//!    technique: emission found by the camera subpath, next-event estimation, connection
//!    to every vertex of its own sample's light subpath (bidirectional path tracing's
//!    connections), and **merging** with every photon within `r` (density estimation with
//!    a constant kernel `1/(π r²)`, normalised by the `N` light paths). Light tracing
//!    (`t = 1`) splats onto the film as bdpt does.
//! 4. **Multiple importance sampling** over all of them, with the merging technique's
//!    pseudo-density `η = π r² N` times the light subpath's density at the merged vertex
//!    (the paper's eq. 10-12): the weights are computed from the three running quantities
//!    `dVCM`, `dVC`, `dVM` each subpath carries (technical report eqs. 31-36 at each vertex,
//!    37-47 for the techniques), the power heuristic (β = 2) unless `mis: balance`. Where
//!    bidirectional path tracing samples a path well its connection techniques keep most
//!    of the weight; merging takes over where connections cannot sample at all, e.g.
//!    specular-diffuse-specular paths from a point light (`L S D S E`).
//!
//! # Bias and the radius schedule
//!
//! Merging estimates the irradiance at a point by the photons in a disc of radius `r`
//! around it: the expected value is the irradiance *blurred over the disc*, so merging is
//! **biased** (by about `r²/8` times the Laplacian of the irradiance for a smooth field,
//! more at edges and across geometry). The radius shrinks over the passes so that the mean
//! of the passes is consistent (Knaus & Zwicker 2011, "Progressive photon mapping: a
//! probabilistic approach", section 4.3; Georgiev et al. 2012 section 5.1):
//!
//! `r_k = r_1 (k + 1)^((α - 1) / 2)` for pass `k` (numbered from 0), α = [`RADIUS_ALPHA`],
//!
//! and `r_1` = [`RADIUS_FOOTPRINTS`] *pixel footprints*: the width of a pixel's cone of
//! directions at the camera path's first merge vertex ([`pixel_footprint`]: the median
//! over a fixed grid of camera rays, following specular surfaces to the first
//! non-specular one), after Hachisuka & Jensen 2009, section 4, who start each pixel's
//! radius from its footprint. A disc of a fixed number of footprints holds the same number
//! of photons whatever the resolution (`N = W H S` grows as the footprint's area
//! shrinks), so a pass's noise per pixel does not depend on the image size; a fraction of
//! the scene (SmallVCM's and Georgiev et al.'s rule, Tessera's before 2026-12-06) gave 4.85
//! footprints on the pool floor, which the camera sees a fifth of the scene across, and
//! 0.97 on the Cornell box, which it sees whole, at any image size; 20 footprints meet the
//! pool's goal of 2% in 120 CPU-seconds at 256 x 256 with vcm and ppm
//! (docs/benchmarks.md, "The first radius from the camera's pixel footprint"). `r_1` is
//! at most [`RADIUS_MAX_SCENE`] of the scene's bounding radius (at small images 20
//! footprints are much of the view), and where no survey ray reaches a surface that
//! merges it is [`RADIUS_PIXELS`] scene radii over the image's long side. The survey is a
//! pure function of the scene, the camera and the image size, so every worker computes
//! the same radius. The schedule is indexed by the pass number, not by the unit, so every
//! split of the passes into units sees the same radii. Passes remain independent
//! replicates (each has its own photon map), but not identically distributed: their bias
//! shrinks with `k`, and the pass spread does not see the bias that the passes share. The
//! plan, the job status and the EXR header say so
//! (`tessera_farm::job::RenderPlan::error_estimate_caveat`). On a smooth field (the pool)
//! the spread alone is calibrated; where merging blurs a sharp caustic it is far from it
//! (0.03-0.07 of the measured error on the glass caustic at 32 x 32, the same document),
//! so every pass also estimates its bias (below).
//!
//! # The bias estimate
//!
//! Each sample estimates the bias of its merges, and the unit carries the pixels' pass
//! means of it as [`UnitResult::bias`] (signed luminance); the merged image's error
//! estimate is then `sqrt(variance from the pass spread + bias²)` (ARCHITECTURE.md §3).
//! After Hachisuka, Jarosz & Jensen 2010 ("A progressive error estimation framework for
//! photon density estimation", section 4: the bias of a kernel estimate is `r²/2 · k₂ ·
//! ΔL` to leading order, `k₂` the kernel's second moment per axis, the Laplacian `ΔL`
//! estimated from the same photons), derived here for the constant kernel merging uses.
//! Let `L(y)` be the density merging estimates (a photon's contribution per unit area)
//! on the surface around the camera vertex `x`, and `E_k = ∫_disc L(x + y) dy / (π r²)`
//! the expected merge of pass `k` (radius `r`). With `L(x + y) = L + ∇L·y + ½ yᵀ H y +
//! O(|y|³)` the odd terms vanish over the disc and `E[y_i y_j] = δ_ij r²/4`, so
//!
//! `bias_k = E_k - L(x) ≈ (r²/8) ΔL(x)`.
//!
//! Weighting each merged photon at distance `d` by `g(d) = 6 d²/r² - 3` instead of 1
//! estimates exactly that term: `u = d²/r²` is uniform over the disc, so the weight has
//! mean `6 · ½ - 3 = 0` (the constant term `L` drops out) and `∫ g |y|² dy / (π r²) =
//! r² (6/3 - 3/2) = r²/2`, so `∫ g y_i² dy / (π r²) = r²/4` per axis and the weighted
//! merge has expectation `½ Σ_i H_ii r²/4 = (r²/8) ΔL` (check: for `L = |y|²`, `ΔL = 4`, the blur's bias is the mean of `|y|²`
//! over the disc, `r²/2`, and the weighted merge gives `∫ (6|y|²/r² - 3)|y|² / (π r²) =
//! r²/2`). It is the least-variance weight of the form `a + b d²` with these two moments
//! (Lagrange), and costs one multiply-add per merged photon. It is a merge's own
//! contribution (MIS weight included) times `g`, so it follows merging's share of the
//! image (all of it in ppm, where connections fail in vcm). Where `L` has an edge the
//! Taylor series fails, but the weighted merge is still `∫ g L / (π r²)`: of the edge's
//! sign, zero with the edge through `x`, and up to 3 times the blur where the edge is near
//! the rim; the measured calibration is in docs/benchmarks.md ("The merging bias term").
//!
//! **Signed, not squared.** The per-pass estimate is noisy: on a smooth field its variance
//! is about `E[g²] = 3` times the merge's own. A squared value per pass would add that
//! noise as bias in every pass. Signed, the passes' estimates average (their mean
//! estimates the merged image's bias, the mean of the passes' biases), and their spread
//! gives the noise of that mean, which the estimate subtracts:
//! `bias² ≈ b̄² - Var(b̄)` (`tessera_farm::bias_squared`), summed over pixels before it is
//! clamped at 0 (`tessera_farm::image_relative_error_biased`). It is computed beside the radiance
//! sums, never inside them: the images are bit-identical to those without it, and it is
//! as deterministic as they are.
//!
//! # Light leaks
//!
//! The disc of radius `r` around a camera vertex is a disc in space, not on the surface:
//! photons of another surface within `r` are merged as if they had arrived at the vertex
//! (Jensen, the course notes' section 10.5.2: the estimate assumes the nearest photons
//! represent the illumination at `x`). Two cases make that far worse than a blur. A wall
//! of no thickness (a single quad, as interiors are often modelled) has the lit floor of
//! one room within `r` of the dark floor of the next: on Veach's door-ajar room
//! (`scenes/door-ajar.gltf`, 64 x 64, 128 spp) vcm's image mean was 3.8 times the
//! reference's. And a corner: a floor's photons counted on the wall beside it. So a
//! photon is merged only if its geometric normal is within [`MERGE_NORMAL_COS`] of the
//! camera vertex's (both on the side their light and the camera are) and a shadow ray
//! between the two points, lifted [`MERGE_LIFT`] radii off the camera vertex's surface
//! (the photon's end raised to the vertex's tangent plane where it is below it, as on a
//! convex surface), is clear (`MergeGuard`). Both tests refuse only pairs whose merged
//! path (the photon's last segment moved to the camera vertex) does not exist or belongs
//! to another surface, and both pass every pair as `r` shrinks on a smooth surface, so
//! merging stays consistent; the MIS weights are unchanged (merging estimates the same
//! paths, from the photons of the vertex's own surface). The cost is a short shadow ray
//! per merged photon (docs/benchmarks.md, "Light leaks in merging").
//!
//! # Determinism and the farm (ARCHITECTURE.md §2)
//!
//! As for bdpt: the plan is one whole-frame tile, a unit is (frame, pass range), and each
//! pass is rendered single-threaded in a fixed order, the photon map rebuilt per pass
//! inside the unit. A unit's bytes do not depend on the thread count or on which worker
//! renders it. The light subpath of a sample is traced twice, once for the photon map and
//! once beside its camera subpath for the connections and light tracing (from the same
//! sampler stream, so it is the same subpath): storing every light vertex with its BSDF
//! would cost hundreds of bytes per vertex for the whole pass.
//!
//! Motion blur: a sample's subpaths see the scene at the sample's time, but merging pairs a
//! camera vertex with photons of other samples' times.
//!
//! Russian roulette is left out of the MIS densities, as in bdpt: every path's weights
//! still sum to one, so the connection techniques stay unbiased.
//!
//! # Progressive photon mapping (`ppm`): the merge-only mode
//!
//! With [`VcmSettings::merge_only`] the same machinery is plain progressive photon
//! mapping (Hachisuka & Jensen 2009, stochastic PPM's estimator with Knaus & Zwicker
//! 2011's per-pass radius schedule above; Georgiev et al. 2012 section 5 and SmallVCM's
//! `kPpm` mode): the light subpaths and the photon map are vcm's, but the camera subpath
//! follows specular events only, counts the emission it finds on the way (weight one: no
//! other technique of this mode samples such a path), and at its first non-specular
//! vertex merges with every photon within `r` (weight one: merging is the only technique
//! for every path through that vertex) and stops. No next-event estimation, connections
//! or light tracing, so no splats: a pixel's value depends only on the pass's photon map
//! and its own camera samples. The density estimate then carries all indirect *and*
//! direct light, so its bias (the irradiance blurred over the disc) is in every pixel, not
//! only where connections fail. Its first radius is vcm's: on the pool, where merging is
//! the only technique either has, the same multiple of the footprint served both
//! (docs/benchmarks.md, "The first radius from the camera's pixel footprint").

mod photon_map;
mod radius;

use super::{render_whole_frame, MisHeuristic, SampleStream, WholeFrame};
use crate::bsdf::diffuse::Diffuse;
use crate::bsdf::{Bsdf, Lobe};
use crate::camera::CameraModel;
use crate::geometry::NO_LIGHT;
use crate::light::emission::WorldDisk;
use crate::math::offset_ray_origin;
use crate::sampling::warp::Frame;
use crate::sampling::{PixelSampler, SamplerKind};
use crate::scene::RenderScene;
use glam::{Vec2, Vec3};
use photon_map::{HashGrid, MergeGuard, Photon};
use radius::first_radius;
pub use radius::{
    pixel_footprint, RADIUS_ALPHA, RADIUS_FOOTPRINTS, RADIUS_MAX_SCENE, RADIUS_PIXELS,
};
use std::f32::consts::PI;
use tessera_farm::{FramePlan, UnitResult, WorkUnit};

/// Largest number of bounces of a path; `max_depth` is clamped to it.
pub const MAX_VCM_DEPTH: u32 = 32;
/// Light vertices a subpath can store (one per bounce).
const MAX_LIGHT_VERTICES: usize = MAX_VCM_DEPTH as usize + 1;
/// A photon is merged only where its geometric normal is within 60 degrees of the camera
/// vertex's: the radiance estimate assumes that the photons near `x` represent the
/// illumination at `x` (Jensen, the course notes' section 10.5.2), and a floor's photons
/// would otherwise count on the wall beside them as if they had arrived there (module
/// documentation, "Light leaks").
pub const MERGE_NORMAL_COS: f32 = 0.5;
/// ... and nothing is between the two points lifted this many radii off the camera
/// vertex's surface (at least four times its position's rounding error): a photon behind a
/// wall of no thickness is within the radius of the floor on the wall's other side. Small,
/// so that the shadow ray does not pass over a low obstacle or start inside a solid that
/// meets the surface (a ball on the floor).
pub const MERGE_LIFT: f32 = 1e-3;
/// Mixed into the job seed for the light subpaths' sampler stream.
const LIGHT_STREAM: u64 = 0x7663_6d5f_6c69_6768; // "vcm_ligh"

/// Settings of the vertex connection and merging integrator.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VcmSettings {
    /// Weighting heuristic: balance (β = 1), otherwise the power heuristic (β = 2).
    pub mis: MisHeuristic,
    /// Maximum number of bounces of a full path (clamped to [`MAX_VCM_DEPTH`]).
    pub max_depth: u32,
    /// Russian roulette ends subpaths after this many bounces.
    pub rr_depth: u32,
    /// Merging radius of the first pass (world units).
    pub radius_1: f32,
    /// The radius schedule's α ([`RADIUS_ALPHA`]).
    pub alpha: f32,
    /// Progressive photon mapping: merging at the first non-specular camera vertex is the
    /// only technique (see the [module documentation](self)).
    pub merge_only: bool,
}

impl VcmSettings {
    /// Settings for a `width` x `height` image of `scene`: `r_1` =
    /// [`RADIUS_FOOTPRINTS`] pixel footprints ([`pixel_footprint`]), at most
    /// [`RADIUS_MAX_SCENE`] of the scene's bounding radius, α = [`RADIUS_ALPHA`],
    /// `max_depth` clamped to `1..=MAX_VCM_DEPTH`.
    pub fn new(
        mis: MisHeuristic,
        max_depth: u32,
        rr_depth: u32,
        scene: &RenderScene,
        width: u32,
        height: u32,
    ) -> Self {
        let max_depth = max_depth.clamp(1, MAX_VCM_DEPTH);
        let footprint = pixel_footprint(scene, width, height, max_depth);
        Self {
            mis,
            max_depth,
            rr_depth,
            radius_1: first_radius(
                footprint,
                RADIUS_FOOTPRINTS,
                scene.geometry.bounds_radius,
                width.max(height),
            ),
            alpha: RADIUS_ALPHA,
            merge_only: false,
        }
    }

    /// Progressive photon mapping's settings: [`VcmSettings::new`]'s (the same first
    /// radius) with [`VcmSettings::merge_only`].
    pub fn ppm(
        mis: MisHeuristic,
        max_depth: u32,
        rr_depth: u32,
        scene: &RenderScene,
        width: u32,
        height: u32,
    ) -> Self {
        Self {
            merge_only: true,
            ..Self::new(mis, max_depth, rr_depth, scene, width, height)
        }
    }

    /// The merging radius of pass `pass` (numbered from 0): `r_1 (pass + 1)^((α - 1)/2)`.
    pub fn radius(&self, pass: u32) -> f32 {
        (self.radius_1 * (pass as f32 + 1.0).powf(0.5 * (self.alpha - 1.0))).max(1e-7)
    }

    fn beta_exponent(&self) -> i32 {
        match self.mis {
            MisHeuristic::Balance => 1,
            _ => 2,
        }
    }
}

/// The constants of one pass: the MIS factors of merging against connecting and the
/// density estimate's normalisation.
#[derive(Clone, Copy, Debug)]
struct PassConst {
    /// MIS exponent.
    exp: i32,
    /// `mis(η)`, `η = π r² N` (technical report eq. 20 with one connection per camera
    /// sample and `N` light paths to merge with).
    vm: f32,
    /// `mis(1 / η)`.
    vc: f32,
    /// `1 / (π r² N)`: the constant kernel over the light paths.
    norm: f32,
}

impl PassConst {
    fn new(st: &VcmSettings, pass: u32, light_paths: u64) -> Self {
        let r = st.radius(pass);
        let eta = PI * r * r * light_paths.max(1) as f32;
        let exp = st.beta_exponent();
        let mis = |x: f32| if exp == 1 { x } else { x * x };
        Self {
            exp,
            vm: mis(eta),
            vc: mis(1.0 / eta),
            norm: 1.0 / eta,
        }
    }

    #[inline]
    fn mis(&self, x: f32) -> f32 {
        if self.exp == 1 {
            x
        } else {
            x * x
        }
    }
}

/// A vertex of a subpath on a surface, with the MIS quantities of the subpath that reached
/// it. `Copy`: subpaths are fixed arrays in per-unit scratch.
#[derive(Clone, Copy)]
struct PathVertex {
    p: Vec3,
    p_error: Vec3,
    ng: Vec3,
    ns: Vec3,
    /// Unit direction toward the previous vertex.
    wo: Vec3,
    frame: Frame,
    bsdf: Bsdf,
    /// Throughput up to this vertex (radiance or importance weight).
    beta: Vec3,
    /// Radiance emitted toward the previous vertex (camera subpaths on an emitter).
    le: Vec3,
    /// The emitter of an emissive surface, or `NO_LIGHT`.
    light: u32,
    /// Segments from the subpath's origin (1 for the first surface).
    depth: u32,
    d_vcm: f32,
    d_vc: f32,
    d_vm: f32,
}

impl PathVertex {
    /// The geometric normal on the side `wo` points to: the camera's side for a camera
    /// vertex, the side the light arrived from for a light vertex.
    #[inline]
    fn facing_ng(&self) -> Vec3 {
        if self.wo.dot(self.ng) >= 0.0 {
            self.ng
        } else {
            -self.ng
        }
    }

    fn empty() -> Self {
        Self {
            p: Vec3::ZERO,
            p_error: Vec3::ZERO,
            ng: Vec3::Z,
            ns: Vec3::Z,
            wo: Vec3::Z,
            frame: Frame::from_normal(Vec3::Z),
            bsdf: Bsdf::single(Lobe::Diffuse(Diffuse { albedo: Vec3::ZERO })),
            beta: Vec3::ZERO,
            le: Vec3::ZERO,
            light: NO_LIGHT,
            depth: 0,
            d_vcm: 0.0,
            d_vc: 0.0,
            d_vm: 0.0,
        }
    }
}

/// The state of a random walk between vertices.
#[derive(Clone, Copy)]
struct Walk {
    origin: Vec3,
    /// The previous vertex (for the segment length in the MIS update).
    prev: Vec3,
    dir: Vec3,
    beta: Vec3,
    beta0: f32,
    depth: u32,
    /// The subpath starts at a light at infinity: its first segment has no length.
    infinite_origin: bool,
    d_vcm: f32,
    d_vc: f32,
    d_vm: f32,
}

/// Scene data every technique needs.
struct Ctx<'a> {
    scene: &'a RenderScene,
    world: WorldDisk,
    time: f32,
    camera: CameraModel,
}

enum Step {
    Surface,
    Escaped,
    Stop,
}

impl Ctx<'_> {
    /// Traces the walk's next segment and writes the surface it finds into `v`, with the
    /// MIS quantities completed for the hit (technical report eqs. 31-36: the segment's
    /// squared length and the cosine at the hit, in area measure by the geometric normal).
    fn trace(&self, w: &mut Walk, v: &mut PathVertex, c: &PassConst, importance: bool) -> Step {
        let scene = self.scene;
        let Some(hit) = scene.intersect_at(w.origin, w.dir, f32::INFINITY, self.time) else {
            return Step::Escaped;
        };
        let sp = scene.surface(&hit, w.origin, w.dir);
        w.beta *= scene.transmittance(&sp, w.dir, hit.t);
        w.depth += 1;
        let cos = sp.ng.dot(w.dir).abs();
        if cos == 0.0 {
            return Step::Stop;
        }
        if w.depth > 1 || !w.infinite_origin {
            w.d_vcm *= c.mis((sp.p - w.prev).length_squared());
        }
        let inv = 1.0 / c.mis(cos);
        w.d_vcm *= inv;
        w.d_vc *= inv;
        w.d_vm *= inv;
        v.p = sp.p;
        v.p_error = sp.p_error;
        v.ng = sp.ng;
        v.ns = sp.ns;
        v.wo = -w.dir;
        v.frame = Frame::from_normal(sp.ns);
        v.bsdf = scene.bsdf(&sp, -w.dir);
        v.beta = w.beta;
        v.le = if !importance && sp.light != NO_LIGHT {
            scene.emitted(&sp, -w.dir)
        } else {
            Vec3::ZERO
        };
        v.light = sp.light;
        v.depth = w.depth;
        v.d_vcm = w.d_vcm;
        v.d_vc = w.d_vc;
        v.d_vm = w.d_vm;
        Step::Surface
    }

    /// Samples the BSDF at `v` and continues the walk (the dimension order of bdpt's
    /// walk: lobe, direction, roulette), updating the MIS quantities for the new direction
    /// (technical report eqs. 34-36; 53-55 for a specular event). False when the walk ends.
    fn scatter(
        &self,
        st: &VcmSettings,
        c: &PassConst,
        v: &PathVertex,
        w: &mut Walk,
        sampler: &mut PixelSampler,
        importance: bool,
    ) -> bool {
        let u1 = sampler.next_1d();
        let u2 = sampler.next_2d();
        let u_rr = sampler.next_1d();
        let wo = v.frame.to_local(v.wo);
        let Some(bs) = v.bsdf.sample(wo, u1, u2) else {
            return false;
        };
        let wi = v.frame.to_world(bs.wi);
        if wi.dot(v.ng) * bs.wi.z <= 0.0 {
            return false;
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
            v.bsdf.eval(bs.wi, wo) * (bs.wi.z.abs() / (wo.z.abs() * bs.pdf))
        };
        let weight = if importance {
            let num = wo.z.abs() * wi.dot(v.ng).abs();
            let den = v.wo.dot(v.ng).abs() * bs.wi.z.abs();
            if den == 0.0 {
                Vec3::ZERO
            } else {
                weight * (num / den)
            }
        } else {
            weight
        };
        w.beta *= weight;
        if !w.beta.is_finite() || w.beta == Vec3::ZERO {
            return false;
        }
        let cos_out = wi.dot(v.ng).abs();
        if bs.delta {
            // The forward and reverse densities of a specular event cancel.
            w.d_vcm = 0.0;
            w.d_vc *= c.mis(cos_out);
            w.d_vm *= c.mis(cos_out);
        } else {
            if bs.pdf <= 0.0 {
                return false;
            }
            let rev = v.bsdf.pdf(bs.wi, wo);
            let f = c.mis(cos_out / bs.pdf);
            w.d_vc = f * (w.d_vc * c.mis(rev) + w.d_vcm + c.vm);
            w.d_vm = f * (w.d_vm * c.mis(rev) + w.d_vcm * c.vc + 1.0);
            w.d_vcm = c.mis(1.0 / bs.pdf);
        }
        if w.depth >= st.rr_depth {
            let survive = (w.beta.max_element() / w.beta0).clamp(0.05, 1.0);
            if u_rr >= survive {
                return false;
            }
            w.beta /= survive;
        }
        w.origin = offset_ray_origin(v.p, v.p_error, v.ng, wi);
        w.prev = v.p;
        w.dir = wi;
        true
    }

    /// The BSDF factor (no cosine) at `v` toward `wn`: radiance (`f(wo = v.wo, wi = wn)`)
    /// or importance (the adjoint, with Veach's shading-normal correction). Zero for light
    /// leaking through the geometric surface.
    #[inline]
    fn f(&self, v: &PathVertex, wn: Vec3, importance: bool) -> Vec3 {
        let a = v.frame.to_local(v.wo);
        let b = v.frame.to_local(wn);
        if a.z * v.wo.dot(v.ng) <= 0.0 || b.z * wn.dot(v.ng) <= 0.0 {
            return Vec3::ZERO;
        }
        if importance {
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

    /// Solid-angle densities `(forward, reverse)` at `v` of scattering toward `wn` and of
    /// the reverse event (arriving from `wn`, leaving toward `v.wo`).
    #[inline]
    fn pdfs(&self, v: &PathVertex, wn: Vec3) -> (f32, f32) {
        let a = v.frame.to_local(v.wo);
        let b = v.frame.to_local(wn);
        (v.bsdf.pdf(a, b), v.bsdf.pdf(b, a))
    }

    /// Whether nothing lies between the camera vertex `v` and the photon `ph`, both just
    /// off `v`'s surface (`guard`, made for `v`): the costly half of the leak test, after
    /// the BSDF. The photon's end is raised to `v`'s tangent plane where it lies below it,
    /// so that the chord of a convex surface does not pass through its own solid.
    fn photon_visible(&self, v: &PathVertex, guard: &MergeGuard, ph: &Photon) -> bool {
        let n = guard.n;
        let a = v.p + n * guard.eps;
        let below = (v.p - ph.p).dot(n).max(0.0);
        let d = ph.p + n * (below + guard.eps) - a;
        let dist = d.length();
        dist == 0.0 || !self.scene.occluded_at(a, d / dist, dist, self.time)
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
}

/// Traces the light subpath of one sample and stores its non-specular surface vertices
/// (at most `max_depth`, the deepest a connection or a merge can use) in `out`; returns
/// how many. Consumes the light sampler's dimensions in a fixed order, so tracing it
/// again from the same sampler state gives the same vertices.
fn light_subpath(
    ctx: &Ctx,
    st: &VcmSettings,
    c: &PassConst,
    out: &mut [PathVertex; MAX_LIGHT_VERTICES],
    slot: &mut PathVertex,
    sampler: &mut PixelSampler,
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
    // Technical report eqs. 31-33 and 48-50 (delta lights): the emission's densities.
    let emission_pdf = pmf * es.pdf_pos * es.pdf_dir;
    let direct_pdf = pmf * if infinite { es.pdf_dir } else { es.pdf_pos };
    let d_vc = if light.is_delta() {
        0.0
    } else {
        let cos = if infinite || es.n == Vec3::ZERO {
            1.0
        } else {
            es.n.dot(es.dir).abs()
        };
        c.mis(cos / emission_pdf)
    };
    let beta = es.weight() / pmf;
    let origin = if es.n == Vec3::ZERO {
        es.p
    } else {
        offset_ray_origin(es.p, es.p_error, es.n, es.dir)
    };
    let mut w = Walk {
        origin,
        prev: es.p,
        dir: es.dir,
        beta,
        beta0: beta.max_element(),
        depth: 0,
        infinite_origin: infinite,
        d_vcm: c.mis(direct_pdf / emission_pdf),
        d_vc,
        d_vm: d_vc * c.vc,
    };
    let mut n = 0;
    while w.depth < st.max_depth {
        match ctx.trace(&mut w, slot, c, true) {
            Step::Surface => {}
            Step::Escaped | Step::Stop => break,
        }
        if slot.bsdf.has_non_delta() {
            out[n] = *slot;
            n += 1;
        }
        if w.depth >= st.max_depth || !ctx.scatter(st, c, slot, &mut w, sampler, true) {
            break;
        }
    }
    n
}

/// Per-unit scratch, reused for every sample and pass.
struct Scratch {
    light: [PathVertex; MAX_LIGHT_VERTICES],
    slot: PathVertex,
    cam: PathVertex,
    photons: Vec<Photon>,
    grid: HashGrid,
}

/// Light tracing (`t = 1`): connects every stored light vertex to a point sampled on the
/// lens and splats the weighted contribution (technical report eqs. 46-47). One 2D value
/// of the light sampler per vertex.
fn splat_light_vertices(
    ctx: &Ctx,
    c: &PassConst,
    light: &[PathVertex],
    sampler: &mut PixelSampler,
    splat: &mut impl FnMut(Vec2, Vec3),
) {
    for lv in light {
        let u = sampler.next_2d();
        let Some(cs) = ctx.camera.sample_wi(lv.p, u) else {
            continue;
        };
        let f = ctx.f(lv, cs.wi, true);
        let l = lv.beta * f * (cs.we / cs.pdf) * lv.ns.dot(cs.wi).abs();
        if l == Vec3::ZERO
            || !ctx.visible(lv.p, lv.p_error, lv.ng, cs.p_lens, Vec3::ZERO, Vec3::ZERO)
        {
            continue;
        }
        let camera_pdf_a =
            ctx.camera.pdf_dir(cs.p_lens, -cs.wi) * lv.ng.dot(cs.wi).abs() / (cs.dist * cs.dist);
        let (_, rev) = ctx.pdfs(lv, cs.wi);
        let w_light = c.mis(camera_pdf_a) * (c.vm + lv.d_vcm + lv.d_vc * c.mis(rev));
        let l = l / (1.0 + w_light);
        if l != Vec3::ZERO {
            splat(cs.raster, l);
        }
    }
}

/// The camera subpath of one sample with every technique at its vertices: emission,
/// next-event estimation, connections to `light` (the sample's own light subpath) and
/// merging with the pass's photons. Returns the sample's radiance estimate, and adds the
/// bias estimate of its merges to `bias` (the module documentation, "The bias estimate").
#[allow(clippy::too_many_arguments)]
fn camera_subpath(
    ctx: &Ctx,
    st: &VcmSettings,
    c: &PassConst,
    film: Vec2,
    lens_u: Vec2,
    light: &[PathVertex],
    photons: &[Photon],
    grid: &HashGrid,
    v: &mut PathVertex,
    sampler: &mut PixelSampler,
    bias: &mut Vec3,
) -> Vec3 {
    let scene = ctx.scene;
    let max_depth = st.max_depth;
    // The bias weight of a merge at squared distance d² is `6 d²/r² - 3` (the module
    // documentation, "The bias estimate").
    let inv_r2 = 1.0 / grid.r2;
    let weight = |d2: f32| 6.0 * d2 * inv_r2 - 3.0;
    let (o, d) = ctx.camera.generate_ray(film, lens_u);
    let pdf_dir = ctx.camera.pdf_dir(o, d);
    if pdf_dir.is_nan() || pdf_dir <= 0.0 {
        return Vec3::ZERO;
    }
    let mut w = Walk {
        origin: o,
        prev: o,
        dir: d,
        beta: Vec3::ONE,
        beta0: 1.0,
        depth: 0,
        infinite_origin: false,
        d_vcm: c.mis(1.0 / pdf_dir),
        d_vc: 0.0,
        d_vm: 0.0,
    };
    let mut total = Vec3::ZERO;
    loop {
        match ctx.trace(&mut w, v, c, false) {
            Step::Surface => {}
            Step::Stop => break,
            Step::Escaped => {
                // The environment, as an emitter found by the camera subpath (no MIS
                // update for a vertex at infinity).
                if let Some((env, le)) = scene.environment(w.dir) {
                    let weight = if w.depth == 0 || st.merge_only {
                        1.0
                    } else {
                        let pmf = scene.lights.pmf(env);
                        let (pdf_pos, pdf_dir) =
                            scene.lights.lights[env].pdf_le(Vec3::ZERO, -w.dir, &ctx.world);
                        let direct = pmf * pdf_dir;
                        let emission = pmf * pdf_pos * pdf_dir;
                        1.0 / (1.0 + c.mis(direct) * w.d_vcm + c.mis(emission) * w.d_vc)
                    };
                    total += w.beta * le * weight;
                }
                break;
            }
        }
        let t = v.depth;
        // Emission found by the camera subpath (technical report eqs. 42-43). In ppm every
        // vertex before this one was specular, and only this technique samples the path.
        if v.le != Vec3::ZERO && t - 1 <= max_depth {
            let weight = if t == 1 || st.merge_only {
                1.0
            } else {
                let li = v.light as usize;
                let pmf = scene.lights.pmf(li);
                let (pdf_pos, pdf_dir) = scene.lights.lights[li].pdf_le(v.ng, v.wo, &ctx.world);
                let direct = pmf * pdf_pos;
                let emission = pmf * pdf_pos * pdf_dir;
                1.0 / (1.0 + c.mis(direct) * v.d_vcm + c.mis(emission) * v.d_vc)
            };
            total += v.beta * v.le * weight;
        }
        if t > max_depth {
            break;
        }
        if st.merge_only {
            if v.bsdf.has_non_delta() {
                // Progressive photon mapping: the density estimate at the first
                // non-specular vertex is the only technique for every path through it.
                let mut sum = Vec3::ZERO;
                let mut bsum = Vec3::ZERO;
                let guard = MergeGuard::new(v, grid.r2);
                grid.query(photons, v.p, |ph| {
                    if ph.depth + t - 1 <= max_depth && guard.same_side(ph) {
                        let f = ctx.f(v, ph.wo, false);
                        if f != Vec3::ZERO && ctx.photon_visible(v, &guard, ph) {
                            let m = f * ph.beta;
                            sum += m;
                            bsum += m * weight((ph.p - v.p).length_squared());
                        }
                    }
                });
                total += v.beta * sum * c.norm;
                *bias += v.beta * bsum * c.norm;
                break;
            }
            if !ctx.scatter(st, c, v, &mut w, sampler, false) {
                break;
            }
            continue;
        }
        let u_light = sampler.next_1d();
        let u2 = sampler.next_2d();
        if v.bsdf.has_non_delta() {
            total += next_event(ctx, c, v, u_light, u2);
            // Connections to the sample's light subpath (eqs. 40-41).
            for lv in light {
                if lv.depth + t > max_depth {
                    break;
                }
                total += connect(ctx, c, v, lv);
            }
            // Merging with the pass's photons (eqs. 38-39).
            let mut sum = Vec3::ZERO;
            let mut bsum = Vec3::ZERO;
            let guard = MergeGuard::new(v, grid.r2);
            grid.query(photons, v.p, |ph| {
                if ph.depth + t - 1 > max_depth || !guard.same_side(ph) {
                    return;
                }
                let fc = ctx.f(v, ph.wo, false);
                if fc == Vec3::ZERO || !ctx.photon_visible(v, &guard, ph) {
                    return;
                }
                let (dir_pdf, rev_pdf) = ctx.pdfs(v, ph.wo);
                let w_light = ph.d_vcm * c.vc + ph.d_vm * c.mis(dir_pdf);
                let w_camera = v.d_vcm * c.vc + v.d_vm * c.mis(rev_pdf);
                let m = fc * ph.beta / (w_light + 1.0 + w_camera);
                sum += m;
                bsum += m * weight((ph.p - v.p).length_squared());
            });
            total += v.beta * sum * c.norm;
            *bias += v.beta * bsum * c.norm;
        }
        if !ctx.scatter(st, c, v, &mut w, sampler, false) {
            break;
        }
    }
    total
}

/// Next-event estimation at camera vertex `v` (technical report eqs. 44-45). The light's
/// densities in the weights are its emission densities ([`crate::light::Light::pdf_le`]),
/// in the technique that finds an emitter and in this one alike, so the weights of a path
/// sum to one.
fn next_event(ctx: &Ctx, c: &PassConst, v: &PathVertex, u_light: f32, u2: Vec2) -> Vec3 {
    let scene = ctx.scene;
    let Some((li, pmf)) = scene.lights.select(u_light) else {
        return Vec3::ZERO;
    };
    let lt = &scene.lights.lights[li];
    let Some(ls) = scene.sample_li(li, v.p, u2) else {
        return Vec3::ZERO;
    };
    let f = ctx.f(v, ls.wi, false);
    let l = v.beta * f * ls.li * (v.ns.dot(ls.wi).abs() / (ls.pdf * pmf));
    if l == Vec3::ZERO {
        return Vec3::ZERO;
    }
    let infinite = !ls.dist.is_finite();
    let (bsdf_pdf, rev_pdf) = ctx.pdfs(v, ls.wi);
    let (pdf_pos, pdf_dir) = lt.pdf_le(ls.n, -ls.wi, &ctx.world);
    let cos_here = v.ng.dot(ls.wi).abs();
    let (w_light, ratio) = if infinite {
        let w = if lt.is_delta() || pdf_dir <= 0.0 {
            0.0
        } else {
            c.mis(bsdf_pdf / (pmf * pdf_dir))
        };
        (w, pdf_pos * cos_here)
    } else {
        let d2 = ls.dist * ls.dist;
        let w = if lt.is_delta() || pdf_pos <= 0.0 {
            0.0
        } else {
            let cos_light = ls.n.dot(ls.wi).abs();
            c.mis(bsdf_pdf * cos_light / (d2 * pmf * pdf_pos))
        };
        (w, pdf_dir * cos_here / d2)
    };
    let w_camera = c.mis(ratio) * (c.vm + v.d_vcm + v.d_vc * c.mis(rev_pdf));
    let visible = if infinite {
        let o = offset_ray_origin(v.p, v.p_error, v.ng, ls.wi);
        !scene.occluded_at(o, ls.wi, f32::INFINITY, ctx.time)
    } else {
        ctx.visible(v.p, v.p_error, v.ng, ls.p, ls.p_error, ls.n)
    };
    if !visible {
        return Vec3::ZERO;
    }
    l / (w_light + 1.0 + w_camera)
}

/// Connects camera vertex `v` to light vertex `lv` (technical report eqs. 40-41).
fn connect(ctx: &Ctx, c: &PassConst, v: &PathVertex, lv: &PathVertex) -> Vec3 {
    let d = lv.p - v.p;
    let d2 = d.length_squared();
    if d2 == 0.0 || !d2.is_finite() {
        return Vec3::ZERO;
    }
    let dir = d / d2.sqrt();
    let fc = ctx.f(v, dir, false);
    if fc == Vec3::ZERO {
        return Vec3::ZERO;
    }
    let fl = ctx.f(lv, -dir, true);
    if fl == Vec3::ZERO {
        return Vec3::ZERO;
    }
    let g = v.ns.dot(dir).abs() * lv.ns.dot(dir).abs() / d2;
    let (c_dir, c_rev) = ctx.pdfs(v, dir);
    let (l_dir, l_rev) = ctx.pdfs(lv, -dir);
    let camera_pdf_a = c_dir * lv.ng.dot(dir).abs() / d2;
    let light_pdf_a = l_dir * v.ng.dot(dir).abs() / d2;
    let w_light = c.mis(camera_pdf_a) * (c.vm + lv.d_vcm + lv.d_vc * c.mis(l_rev));
    let w_camera = c.mis(light_pdf_a) * (c.vm + v.d_vcm + v.d_vc * c.mis(c_rev));
    let l = v.beta * lv.beta * fc * fl * (g / (w_light + 1.0 + w_camera));
    if l == Vec3::ZERO || !ctx.visible(v.p, v.p_error, v.ng, lv.p, lv.p_error, lv.ng) {
        return Vec3::ZERO;
    }
    l
}

/// Renders one work unit with vertex connection and merging; see the [module
/// documentation](self). The unit contract is bdpt's ([`super::bdpt::render_unit`]):
/// every pixel of the frame traces its light subpaths (for the photon map and for light
/// tracing), only wanted tile pixels trace camera subpaths, and invalid contributions are
/// dropped and counted.
pub fn render_unit(
    scene: &RenderScene,
    st: &VcmSettings,
    stream: SampleStream,
    plan: &FramePlan,
    unit: WorkUnit,
    wanted: impl Fn(usize, u32) -> bool,
) -> UnitResult {
    let light_paths = plan.width as u64 * plan.height as u64 * plan.samples_per_pass as u64;
    let empty = PathVertex::empty();
    let mut technique = Vcm {
        ctx: Ctx {
            scene,
            world: WorldDisk::new(scene.geometry.bounds_center, scene.geometry.bounds_radius),
            time: 0.0,
            camera: scene.camera,
        },
        st,
        c: PassConst::new(st, unit.first_pass, light_paths),
        light_paths,
        light_seed: stream.seed ^ LIGHT_STREAM,
        frame: unit.frame,
        pixels: plan.width * plan.height,
        spp: plan.samples_per_pass,
        kind: stream.sampler,
        motion: scene.has_motion(),
        lens: scene.camera.has_lens(),
        last_bias: 0.0,
        scratch: Box::new(Scratch {
            light: [empty; MAX_LIGHT_VERTICES],
            slot: empty,
            cam: empty,
            photons: Vec::new(),
            grid: HashGrid::default(),
        }),
    };
    let light_seed = technique.light_seed;
    render_whole_frame(&mut technique, light_seed, stream, plan, unit, wanted)
}

/// One unit's vertex connection and merging: the scene data, the settings, the pass's
/// constants and photon map, and the scratch subpaths, for [`render_whole_frame`].
struct Vcm<'a> {
    ctx: Ctx<'a>,
    st: &'a VcmSettings,
    /// The current pass's constants (its radius and MIS factors).
    c: PassConst,
    /// Light subpaths per pass: one per sample of every pixel of the frame.
    light_paths: u64,
    light_seed: u64,
    frame: u32,
    /// Pixels of the frame.
    pixels: u32,
    spp: u32,
    kind: SamplerKind,
    motion: bool,
    lens: bool,
    scratch: Box<Scratch>,
    /// The bias estimate (luminance) of the last sample's camera estimate.
    last_bias: f64,
}

impl Vcm<'_> {
    /// The sample's time (motion blur), from the light stream's first dimension, as bdpt
    /// draws it.
    fn draw_time(&mut self, ls: &mut PixelSampler) {
        if self.motion {
            self.ctx.time = ls.next_1d();
            self.ctx.camera = self.ctx.scene.camera_at(self.ctx.time);
        }
    }
}

impl WholeFrame for Vcm<'_> {
    /// The pass's photon map, from every sample's light subpath in a fixed order.
    fn begin_pass(&mut self, pass: u32) {
        let st = self.st;
        self.c = PassConst::new(st, pass, self.light_paths);
        self.scratch.photons.clear();
        for pixel in 0..self.pixels {
            let mut ls = PixelSampler::new(self.kind, self.light_seed, self.frame, pixel, pass);
            for i in 0..self.spp {
                ls.start_sample(i);
                self.draw_time(&mut ls);
                let Scratch {
                    light,
                    slot,
                    photons,
                    ..
                } = &mut *self.scratch;
                let n = light_subpath(&self.ctx, st, &self.c, light, slot, &mut ls);
                photons.extend(light[..n].iter().map(|v| Photon {
                    p: v.p,
                    wo: v.wo,
                    n: v.facing_ng(),
                    beta: v.beta,
                    depth: v.depth,
                    d_vcm: v.d_vcm,
                    d_vm: v.d_vm,
                }));
            }
        }
        let Scratch { photons, grid, .. } = &mut *self.scratch;
        grid.build(photons, st.radius(pass));
    }

    /// Camera subpaths, connections to their own light subpath (traced again from the
    /// same stream), merges, and light tracing.
    fn sample(
        &mut self,
        x: u32,
        y: u32,
        ls: &mut PixelSampler,
        cs: Option<&mut PixelSampler>,
        splat: &mut impl FnMut(Vec2, Vec3),
    ) -> Vec3 {
        self.draw_time(ls);
        let (ctx, st, c) = (&self.ctx, self.st, &self.c);
        let Scratch {
            light,
            slot,
            cam,
            photons,
            grid,
        } = &mut *self.scratch;
        // Progressive photon mapping neither connects nor light-traces: the sample's own
        // light subpath is not needed again.
        let n_light = if st.merge_only {
            0
        } else {
            light_subpath(ctx, st, c, light, slot, ls)
        };
        let mut camera_l = Vec3::ZERO;
        let mut bias = Vec3::ZERO;
        if let Some(cs) = cs {
            let film = Vec2::new(x as f32, y as f32) + cs.next_2d();
            let lens_u = if self.lens { cs.next_2d() } else { Vec2::ZERO };
            camera_l = camera_subpath(
                ctx,
                st,
                c,
                film,
                lens_u,
                &light[..n_light],
                photons,
                grid,
                cam,
                cs,
                &mut bias,
            );
        }
        self.last_bias = tessera_farm::luminance(bias.to_array().map(f64::from));
        // Splats first, then the pixel's own estimate: a fixed order.
        splat_light_vertices(ctx, c, &light[..n_light], ls, splat);
        camera_l
    }

    /// Merging is biased: every sample estimates its merges' bias.
    fn estimates_bias(&self) -> bool {
        true
    }

    fn sample_bias(&self) -> f64 {
        self.last_bias
    }
}

#[cfg(test)]
mod tests;
