//! The strategies of [`super`]: the MIS weight of a technique `(s, t)` (Veach 1997,
//! §10.2, computed from the vertices' forward and reverse densities as pbrt-v4 does), each
//! technique (emission, next-event estimation, connection, light tracing), the camera
//! estimate of one sample and the whole-frame unit that drives them.

use super::*;

#[inline]
fn remap0(f: f32) -> f32 {
    if f != 0.0 {
        f
    } else {
        1.0
    }
}

#[inline]
fn pow_beta(r: f32, beta: i32) -> f32 {
    if beta == 1 {
        r
    } else {
        r * r
    }
}

/// The MIS weight of technique `(s, t)` for the path `light[..s] + cam[..t]` (reversed),
/// with `sampled` replacing `light[0]` (s = 1) or `cam[0]` (t = 1). The arrays are edited in
/// place and restored (pbrt's scoped assignments): only the edited fields are saved, and
/// where `sampled` replaces an endpoint, every field of it but the BSDF ([`Endpoint`]: the
/// replaced vertex and `sampled` are both endpoints, whose BSDF nothing reads; a vertex
/// carries its BSDF, hundreds of bytes, and this runs once per technique).
fn mis_weight(
    ctx: &Ctx,
    st: &BdptSettings,
    light: &mut [Vertex; MAX_VERTICES],
    cam: &mut [Vertex; MAX_VERTICES],
    sampled: Option<&Vertex>,
    s: usize,
    t: usize,
) -> f32 {
    if s + t == 2 {
        return 1.0;
    }
    let exp = st.beta_exponent();
    // Save what is edited: the connection vertices' `delta` and `pdf_rev`, their
    // predecessors' `pdf_rev`, and a vertex `sampled` replaces.
    let saved_p = (cam[t - 1].delta, cam[t - 1].pdf_rev);
    let saved_q = if s > 0 {
        (light[s - 1].delta, light[s - 1].pdf_rev)
    } else {
        (false, 0.0)
    };
    let saved_qm = if s > 1 { light[s - 2].pdf_rev } else { 0.0 };
    let saved_pm = if t > 1 { cam[t - 2].pdf_rev } else { 0.0 };
    let (mut saved_l0, mut saved_c0) = (None, None);
    if let Some(v) = sampled {
        debug_assert!(v.kind != Kind::Surface, "only an endpoint is sampled");
        if s == 1 {
            debug_assert!(light[0].kind != Kind::Surface);
            saved_l0 = Some(light[0].endpoint());
            light[0].set_endpoint(v.endpoint());
        } else if t == 1 {
            debug_assert!(cam[0].kind != Kind::Surface);
            saved_c0 = Some(cam[0].endpoint());
            cam[0].set_endpoint(v.endpoint());
        }
    }
    // The connection vertices are connected, not scattered by a delta lobe.
    cam[t - 1].delta = false;
    if s > 0 {
        light[s - 1].delta = false;
    }
    // Reverse density of pt = cam[t-1].
    let v = if s > 0 {
        let prev = if s > 1 { Some(&light[s - 2]) } else { None };
        ctx.pdf(&light[s - 1], prev, &cam[t - 1])
    } else {
        ctx.pdf_light_origin(&cam[t - 1], &cam[t - 2])
    };
    cam[t - 1].pdf_rev = v;
    // Reverse density of cam[t-2].
    if t > 1 {
        let v = if s > 0 {
            ctx.pdf(&cam[t - 1], Some(&light[s - 1]), &cam[t - 2])
        } else {
            ctx.pdf_light(&cam[t - 1], &cam[t - 2])
        };
        cam[t - 2].pdf_rev = v;
    }
    // Reverse densities of qs = light[s-1] and light[s-2].
    if s > 0 {
        let prev = if t > 1 { Some(&cam[t - 2]) } else { None };
        let v = ctx.pdf(&cam[t - 1], prev, &light[s - 1]);
        light[s - 1].pdf_rev = v;
    }
    if s > 1 {
        let v = ctx.pdf(&light[s - 1], Some(&cam[t - 1]), &light[s - 2]);
        light[s - 2].pdf_rev = v;
    }

    // Techniques that would have connected further along the camera subpath...
    let mut sum = 0.0f32;
    let mut ri = 1.0f32;
    for i in (1..t).rev() {
        ri *= remap0(cam[i].pdf_rev) / remap0(cam[i].pdf_fwd);
        if !cam[i].delta && !cam[i - 1].delta {
            sum += pow_beta(ri, exp);
        }
    }
    // ... and further along the light subpath.
    let mut ri = 1.0f32;
    for i in (0..s).rev() {
        ri *= remap0(light[i].pdf_rev) / remap0(light[i].pdf_fwd);
        let delta_before = if i > 0 {
            light[i - 1].delta
        } else {
            light[0].delta_light
        };
        if !light[i].delta && !delta_before {
            sum += pow_beta(ri, exp);
        }
    }

    // Restore: the fields, then a replaced vertex whole.
    (cam[t - 1].delta, cam[t - 1].pdf_rev) = saved_p;
    if s > 0 {
        (light[s - 1].delta, light[s - 1].pdf_rev) = saved_q;
    }
    if s > 1 {
        light[s - 2].pdf_rev = saved_qm;
    }
    if t > 1 {
        cam[t - 2].pdf_rev = saved_pm;
    }
    if let Some(e) = saved_l0 {
        light[0].set_endpoint(e);
    }
    if let Some(e) = saved_c0 {
        cam[0].set_endpoint(e);
    }
    let w = 1.0 / (1.0 + sum);
    if w.is_finite() {
        w
    } else {
        0.0
    }
}

/// Light tracing, `t = 1`: connects every vertex `light[s-1]` (s >= 2) to a point sampled on
/// the lens and splats the weighted contribution at its film position. Consumes one 2D
/// value of the light sampler per vertex. Every non-zero contribution is passed to `splat`,
/// invalid ones (NaN, infinite, negative) included: the caller drops and counts those that
/// land in its tile.
fn splat_light_paths(
    ctx: &Ctx,
    st: &BdptSettings,
    light: &mut [Vertex; MAX_VERTICES],
    cam: &mut [Vertex; MAX_VERTICES],
    n_light: usize,
    sampler: &mut PixelSampler,
    splat: &mut impl FnMut(Vec2, Vec3),
) {
    for s in 2..=n_light {
        let u = sampler.next_2d();
        if s - 1 > st.max_depth as usize {
            continue;
        }
        if let Some((raster, l)) = light_tracing(ctx, st, light, cam, s, u) {
            splat(raster, l);
        }
    }
}

/// Technique `(s, 1)`, `s >= 2`: `light[s-1]` connected to the lens point `u` samples; the
/// MIS-weighted contribution and the film position it lands on, or `None` when it is zero.
fn light_tracing(
    ctx: &Ctx,
    st: &BdptSettings,
    light: &mut [Vertex; MAX_VERTICES],
    cam: &mut [Vertex; MAX_VERTICES],
    s: usize,
    u: Vec2,
) -> Option<(Vec2, Vec3)> {
    let qs = light[s - 1];
    if !qs.connectible() {
        return None;
    }
    let cs = ctx.camera.sample_wi(qs.p, u)?;
    let f = ctx.f(&qs, cs.wi, true);
    let mut l = qs.beta * f * (cs.we / cs.pdf) * qs.ns.dot(cs.wi).abs();
    if l == Vec3::ZERO || !ctx.visible(qs.p, qs.p_error, qs.ng, cs.p_lens, Vec3::ZERO, Vec3::ZERO) {
        return None;
    }
    let mut c = Vertex::empty();
    c.kind = Kind::Camera;
    c.p = cs.p_lens;
    c.beta = Vec3::splat(cs.we / cs.pdf);
    l *= mis_weight(ctx, st, light, cam, Some(&c), s, 1);
    (l != Vec3::ZERO).then_some((cs.raster, l))
}

/// Technique `(0, t)`, `t >= 2`: the camera subpath's own emission at `cam[t-1]`, MIS-weighted.
fn emission(
    ctx: &Ctx,
    st: &BdptSettings,
    light: &mut [Vertex; MAX_VERTICES],
    cam: &mut [Vertex; MAX_VERTICES],
    t: usize,
) -> Vec3 {
    let pt = &cam[t - 1];
    if pt.is_light() && pt.le != Vec3::ZERO {
        let l = pt.le * pt.beta;
        let w = mis_weight(ctx, st, light, cam, None, 0, t);
        l * w
    } else {
        Vec3::ZERO
    }
}

/// Technique `(1, t)`, `t >= 2`: next-event estimation from `cam[t-1]` (a light chosen by
/// `u_light`, a point on it by `u2`), MIS-weighted. The caller checks the depth and that
/// `cam[t-1]` is a surface.
fn next_event(
    ctx: &Ctx,
    st: &BdptSettings,
    light: &mut [Vertex; MAX_VERTICES],
    cam: &mut [Vertex; MAX_VERTICES],
    t: usize,
    u_light: f32,
    u2: Vec2,
) -> Vec3 {
    let scene = ctx.scene;
    let pt = &cam[t - 1];
    if !pt.connectible() {
        return Vec3::ZERO;
    }
    let Some((li, pmf)) = scene.lights.select(u_light) else {
        return Vec3::ZERO;
    };
    let lt = &scene.lights.lights[li];
    let Some(ls) = scene.sample_li(li, pt.p, u2) else {
        return Vec3::ZERO;
    };
    let f = ctx.f(pt, ls.wi, false);
    let l = pt.beta * f * ls.li * (pt.ns.dot(ls.wi).abs() / (ls.pdf * pmf));
    let visible = l != Vec3::ZERO
        && if ls.dist.is_finite() {
            ctx.visible(pt.p, pt.p_error, pt.ng, ls.p, ls.p_error, ls.n)
        } else {
            let o = offset_ray_origin(pt.p, pt.p_error, pt.ng, ls.wi);
            !scene.occluded_at(o, ls.wi, f32::INFINITY, ctx.time)
        };
    if !visible {
        return Vec3::ZERO;
    }
    let mut v = Vertex::empty();
    v.kind = Kind::Light;
    v.p = ls.p;
    v.p_error = ls.p_error;
    v.ng = ls.n;
    v.ns = ls.n;
    v.light = li as u32;
    v.infinite = !ls.dist.is_finite();
    v.wo = -ls.wi;
    v.delta_light = lt.is_delta();
    v.beta = ls.li / (ls.pdf * pmf);
    v.pdf_fwd = ctx.pdf_light_origin(&v, pt);
    let w = mis_weight(ctx, st, light, cam, Some(&v), 1, t);
    l * w
}

/// Technique `(s, t)`, `s, t >= 2`: `light[s-1]` joined to `cam[t-1]` by a shadow ray,
/// MIS-weighted. The caller checks the depth.
fn connection(
    ctx: &Ctx,
    st: &BdptSettings,
    light: &mut [Vertex; MAX_VERTICES],
    cam: &mut [Vertex; MAX_VERTICES],
    s: usize,
    t: usize,
) -> Vec3 {
    let (qs, pt) = (&light[s - 1], &cam[t - 1]);
    if !qs.connectible() || !pt.connectible() {
        return Vec3::ZERO;
    }
    let Some(d) = pt.dir_to(qs) else {
        return Vec3::ZERO;
    };
    let l = qs.beta * ctx.f(qs, -d, true) * ctx.f(pt, d, false) * pt.beta;
    if l == Vec3::ZERO {
        return Vec3::ZERO;
    }
    let g = ctx.g(qs, pt);
    if g == 0.0 {
        return Vec3::ZERO;
    }
    let w = mis_weight(ctx, st, light, cam, None, s, t);
    l * (g * w)
}

/// Techniques with `t >= 2`: the camera subpath's own emission (`s = 0`), next-event
/// estimation (`s = 1`) and connections (`s >= 2`). Returns the radiance for the pixel.
fn camera_techniques(
    ctx: &Ctx,
    st: &BdptSettings,
    light: &mut [Vertex; MAX_VERTICES],
    cam: &mut [Vertex; MAX_VERTICES],
    n_light: usize,
    n_cam: usize,
    sampler: &mut PixelSampler,
) -> Vec3 {
    let max_depth = st.max_depth as usize;
    let mut total = Vec3::ZERO;
    for t in 2..=n_cam {
        // The techniques borrow the subpaths afresh around each `mis_weight` (which edits
        // them in place and restores them): a vertex is too large to copy per technique.
        // s = 0: the camera subpath found an emitter.
        if cam[t - 1].is_light() && cam[t - 1].le != Vec3::ZERO {
            total += emission(ctx, st, light, cam, t);
        }
        if cam[t - 1].kind == Kind::Light {
            continue; // an escaped ray connects to nothing
        }
        // s = 1: sample a light from pt (next-event estimation).
        let u_light = sampler.next_1d();
        let u2 = sampler.next_2d();
        if t - 1 <= max_depth && cam[t - 1].connectible() {
            let l = next_event(ctx, st, light, cam, t, u_light, u2);
            if l != Vec3::ZERO {
                total += l;
            }
        }
        // s >= 2: connect light[s-1] and cam[t-1].
        if !cam[t - 1].connectible() {
            continue;
        }
        for s in 2..=n_light {
            if s + t - 2 > max_depth {
                break;
            }
            let l = connection(ctx, st, light, cam, s, t);
            if l != Vec3::ZERO {
                total += l;
            }
        }
    }
    total
}

/// Per-unit scratch: the two subpaths (reused for every sample, never reallocated).
pub(in crate::integrator) struct Scratch {
    pub(in crate::integrator) light: [Vertex; MAX_VERTICES],
    pub(in crate::integrator) cam: [Vertex; MAX_VERTICES],
}

impl Scratch {
    /// Two empty subpaths, on the heap (they are large).
    pub(in crate::integrator) fn boxed() -> Box<Self> {
        let empty = Vertex::empty();
        Box::new(Scratch {
            light: [empty; MAX_VERTICES],
            cam: [empty; MAX_VERTICES],
        })
    }
}

/// The one technique `(s, t)` on a light subpath of `s` and a camera subpath of `t >= 1`
/// vertices (multiplexed MLT evaluates one technique per sample; Hachisuka, Kaplanyan &
/// Dachsbacher 2014, section 4): its MIS-weighted contribution and, for light tracing
/// (`t = 1`), the film position it lands on. Draws from `sampler` a 2D lens sample
/// (`t = 1`) or a light choice and a 2D light sample (`s = 1`), nothing otherwise.
pub(in crate::integrator) fn technique<S: SampleSource>(
    ctx: &Ctx,
    st: &BdptSettings,
    scratch: &mut Scratch,
    s: usize,
    t: usize,
    sampler: &mut S,
) -> (Vec3, Option<Vec2>) {
    let Scratch { light, cam } = scratch;
    if t == 1 {
        let u = sampler.next_2d();
        return match light_tracing(ctx, st, light, cam, s, u) {
            Some((raster, l)) => (l, Some(raster)),
            None => (Vec3::ZERO, None),
        };
    }
    if s == 0 {
        return (emission(ctx, st, light, cam, t), None);
    }
    if cam[t - 1].kind == Kind::Light {
        return (Vec3::ZERO, None); // an escaped ray connects to nothing
    }
    if s == 1 {
        let u_light = sampler.next_1d();
        let u2 = sampler.next_2d();
        return (next_event(ctx, st, light, cam, t, u_light, u2), None);
    }
    (connection(ctx, st, light, cam, s, t), None)
}

/// Renders one work unit with bidirectional path tracing; see the [module
/// documentation](super) for the splatting and determinism design.
///
/// Invalid contributions (NaN, infinite, negative) are dropped and counted in
/// `rejected_samples`: a camera sample's estimate of a tile pixel, and each light-tracing
/// splat landing in the tile.
///
/// Only tile pixels where `wanted(i, pass)` holds (`i` row-major in the tile) trace camera
/// subpaths; every pixel of the frame still traces its light subpaths, so a wanted pixel
/// gets the same value as when every pixel is wanted, splats included. An unwanted pixel's
/// pass mean holds only the splats that landed in it: a partial estimate, which the
/// adaptive policy never reads and the farm zeroes.
pub fn render_unit(
    scene: &RenderScene,
    st: &BdptSettings,
    stream: SampleStream,
    plan: &FramePlan,
    unit: WorkUnit,
    wanted: impl Fn(usize, u32) -> bool,
) -> UnitResult {
    let mut technique = Bdpt {
        ctx: Ctx::new(scene),
        st,
        motion: scene.has_motion(),
        lens: scene.camera.has_lens(),
        scratch: Scratch::boxed(),
    };
    let light_seed = stream.seed ^ LIGHT_STREAM;
    render_whole_frame(&mut technique, light_seed, stream, plan, unit, wanted)
}

/// One unit's bidirectional path tracer: the scene data, the settings and the scratch
/// subpaths, for [`render_whole_frame`].
struct Bdpt<'a> {
    ctx: Ctx<'a>,
    st: &'a BdptSettings,
    motion: bool,
    lens: bool,
    scratch: Box<Scratch>,
}

impl WholeFrame for Bdpt<'_> {
    fn begin_pass(&mut self, _pass: u32) {}

    fn sample(
        &mut self,
        x: u32,
        y: u32,
        ls: &mut PixelSampler,
        cs: Option<&mut PixelSampler>,
        splat: &mut impl FnMut(Vec2, Vec3),
    ) -> Vec3 {
        let (ctx, st) = (&mut self.ctx, self.st);
        let Scratch { light, cam } = &mut *self.scratch;
        if self.motion {
            // The sample's time, from the light stream's first dimension: every pixel
            // draws it, inside the tile or not, so the splats agree.
            ctx.set_time(ls.next_1d());
        }
        let n_light = light_subpath(ctx, st, light, st.max_depth as usize + 1, ls);
        let mut camera_l = Vec3::ZERO;
        if let Some(cs) = cs {
            let film = Vec2::new(x as f32, y as f32) + cs.next_2d();
            let lens_u = if self.lens { cs.next_2d() } else { Vec2::ZERO };
            let n_cam = camera_subpath(ctx, st, film, lens_u, cam, st.max_depth as usize + 2, cs);
            camera_l = camera_techniques(ctx, st, light, cam, n_light, n_cam, cs);
        }
        // Splats first, then the pixel's own estimate: a fixed order.
        splat_light_paths(ctx, st, light, cam, n_light, ls, splat);
        camera_l
    }
}
