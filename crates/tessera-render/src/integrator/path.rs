//! Unidirectional path tracing with next-event estimation (NEE), multiple importance
//! sampling and Russian roulette.
//!
//! The estimator follows the path formulation of the rendering equation (Hanrahan 2001 and Dutré 2001, chapters 7–8,
//! the Princeton COS 526 path tracing slides). At every non-specular vertex two techniques estimate direct light: sampling
//! a light (NEE: one light chosen by the light hierarchy in proportion to its estimated
//! contribution, Conty Estevez & Kulla 2018; Shirley 2001, chapter 3) and sampling the
//! BSDF and hitting an emitter. Their contributions are combined with the selected MIS
//! heuristic (Veach & Guibas 1995, section 3), so glossy highlights of small lights and
//! large lights are both rendered with low variance. After `rr_depth` bounces a path
//! survives with probability `min(0.95, max throughput x eta scale)` and is reweighted by
//! its inverse: Russian roulette keeps the estimator unbiased (Dutré 2001, chapter 8). The
//! survival follows the throughput, so dim paths (which carry little) end early, and is
//! capped below one so that bright paths in closed rooms still end; the eta scale undoes
//! the `1/η²` that radiance picks up entering glass (pbrt-v4, Pharr, Jakob & Humphreys,
//! 4th ed., section 13.1.6: the throughput seen by roulette should not depend on which
//! medium the path is in), as Mitsuba 3's path tracer does.
//!
//! Steps, as labelled below: 1 intersect, 2 emission (MIS with NEE of the previous
//! vertex), 3 direct light by NEE, 4 BSDF sample, 5 Russian roulette.
//!
//! [`radiance_mnee`] adds manifold next-event estimation at step 3 ([`super::mnee`]:
//! light through chains of smooth specular surfaces) and at step 2 drops the emission of
//! BSDF-sampled paths that MNEE would have found. It is a separate monomorphisation of the
//! same loop, so [`radiance`]'s code and images are those of the path tracer without it.

use super::{mnee, MisHeuristic};
use crate::math::offset_ray_origin;
use crate::sampling::warp::Frame;
use crate::sampling::PixelSampler;
use crate::scene::RenderScene;
use glam::Vec3;

/// Largest survival probability of Russian roulette: even a path that carries all of its
/// energy ends with probability 5% per bounce once roulette has started (Mitsuba 3's
/// path tracer uses the same cap).
pub const RR_MAX_SURVIVAL: f32 = 0.95;

/// Settings of the path integrator. The `direct` integrator is this one with
/// `max_depth = 1`; the path tracer knows no other integrator.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PathSettings {
    /// MIS weighting.
    pub mis: MisHeuristic,
    /// Maximum number of scattering events (1 = direct lighting: emission seen directly
    /// and light arriving at the first surface).
    pub max_depth: u32,
    /// Russian roulette starts after this many bounces.
    pub rr_depth: u32,
}

/// Radiance along the ray `(origin, dir)` at shutter fraction `time` (which only moving
/// geometry reads; see [`crate::motion`]). Consumes dimensions from `sampler` in a fixed
/// order so that the result is a pure function of the sampler state.
pub fn radiance(
    scene: &RenderScene,
    s: &PathSettings,
    origin: Vec3,
    dir: Vec3,
    time: f32,
    sampler: &mut PixelSampler,
) -> Vec3 {
    radiance_with::<false>(scene, s, origin, dir, time, sampler)
}

/// [`radiance`] with manifold next-event estimation ([`super::mnee`]) at every
/// non-specular vertex: light from point and emissive-triangle lights through chains of
/// up to [`mnee::MAX_CHAIN`] specular vertices, and BSDF-sampled paths that MNEE would
/// have found left to it. The same sampler dimensions as [`radiance`] (MNEE reuses the
/// next-event estimation's light sample), so the two differ only by the caustics.
pub fn radiance_mnee(
    scene: &RenderScene,
    s: &PathSettings,
    origin: Vec3,
    dir: Vec3,
    time: f32,
    sampler: &mut PixelSampler,
) -> Vec3 {
    radiance_with::<true>(scene, s, origin, dir, time, sampler)
}

/// Where MNEE could have started the path being traced: the last non-specular vertex, its
/// light selection normal and longest chain, and the specular vertices since.
#[derive(Clone, Copy)]
struct MneeOrigin {
    x: mnee::Anchor,
    n_select: Vec3,
    max_chain: usize,
    chain: [Vec3; mnee::MAX_CHAIN],
    len: usize,
}

/// The path tracer; `MNEE` adds manifold next-event estimation (a separate
/// monomorphisation, so the plain path tracer's code and images do not change).
#[inline(always)]
fn radiance_with<const MNEE: bool>(
    scene: &RenderScene,
    s: &PathSettings,
    mut origin: Vec3,
    mut dir: Vec3,
    time: f32,
    sampler: &mut PixelSampler,
) -> Vec3 {
    // MNEE's claim on the path so far (`None`: no MNEE connection can produce it).
    let mut mnee_origin: Option<MneeOrigin> = None;
    let max_depth = s.max_depth;
    let mut l = Vec3::ZERO;
    let mut beta = Vec3::ONE;
    // State of the previous scattering vertex for MIS of emission found by BSDF sampling.
    let mut prev_delta = true;
    let mut prev_pdf = 0.0f32;
    let mut prev_p = origin;
    // The normal light selection used at the previous vertex (zero: none).
    let mut prev_n = Vec3::ZERO;
    let mut depth = 0u32;
    // Product of η² over the refractions so far (radiance is scaled by 1/η² entering a
    // denser medium): roulette decides on `beta * eta_scale`.
    let mut eta_scale = 1.0f32;
    loop {
        // 1. Intersect.
        let Some(hit) = scene.intersect_at(origin, dir, f32::INFINITY, time) else {
            if let Some((env_index, le)) = scene.environment(dir) {
                let w = if prev_delta {
                    1.0
                } else {
                    let pl = scene.lights.pmf_at(prev_p, prev_n, env_index)
                        * scene.lights.lights[env_index].pdf_li(
                            prev_p,
                            dir,
                            Vec3::ZERO,
                            Vec3::ZERO,
                        );
                    s.mis.weight(prev_pdf, pl)
                };
                l += beta * le * w;
            }
            break;
        };
        let sp = scene.surface(&hit, origin, dir);
        let wo_world = -dir;
        // Absorption inside a KHR_materials_volume medium along the segment just traced.
        beta *= scene.transmittance(&sp, dir, hit.t);

        // 2. Emission at the hit, weighted against NEE from the previous vertex.
        if sp.light != crate::geometry::NO_LIGHT {
            let le = scene.emitted(&sp, wo_world);
            if le != Vec3::ZERO {
                let claimed = MNEE
                    && prev_delta
                    && mnee_origin.is_some_and(|m| {
                        m.len > 0
                            && mnee::claims(
                                scene,
                                &m.x,
                                m.n_select,
                                m.max_chain,
                                &m.chain[..m.len],
                                &sp,
                                time,
                            )
                    });
                let w = if claimed {
                    0.0
                } else if prev_delta {
                    1.0
                } else {
                    let li = sp.light as usize;
                    let pl = scene.lights.pmf_at(prev_p, prev_n, li)
                        * scene.lights.lights[li].pdf_li(prev_p, dir, sp.p, sp.ng);
                    s.mis.weight(prev_pdf, pl)
                };
                l += beta * le * w;
            }
        }
        if depth >= max_depth {
            break;
        }

        let bsdf = scene.bsdf(&sp, wo_world);
        let frame = Frame::from_normal(sp.ns);
        let wo = frame.to_local(wo_world);
        // MNEE at this vertex: a non-specular one with room for a chain of one. At every
        // such vertex, not only the first: at the later ones BSDF sampling cannot stand in
        // for it where the light is a point or spot light (a BSDF-sampled ray never hits a
        // delta light), so a caustic's light after a further diffuse bounce (on the pool,
        // the floor's light returned to it by the water's underside, 15% of the image at
        // depth 16) would be lost, not merely noisy (docs/benchmarks.md, "MNEE at every
        // non-specular vertex").
        let mnee_here = MNEE && bsdf.has_non_delta() && depth + 2 <= max_depth;

        // 3. Next-event estimation: a light chosen by the light hierarchy for this point.
        // Transmissive surfaces pass no normal, so that lights behind them count.
        let n_select = if bsdf.has_transmission() {
            Vec3::ZERO
        } else {
            sp.ns
        };
        // The light sample's two dimensions are consumed at every vertex, drawn only where
        // they are used (a purely specular vertex skips them): the same later samples.
        if !bsdf.has_non_delta() {
            sampler.skip(2);
        } else {
            let u_light = sampler.next_1d();
            let u_light2 = sampler.next_2d();
            if let Some((li, pmf)) = scene.lights.select_at(u_light, sp.p, n_select) {
                // Whether the shadow ray found the light unblocked: then the straight
                // segment crosses no specular surface and MNEE has no seed chain.
                let mut nee_visible = false;
                if let Some(ls) = scene.sample_li(li, sp.p, u_light2) {
                    let wi = frame.to_local(ls.wi);
                    // Reject light arriving through the geometric surface (shading-normal leak).
                    let geometric_ok = ls.wi.dot(sp.ng).signum() == wi.z.signum();
                    let f = bsdf.eval(wo, wi);
                    if geometric_ok && f != Vec3::ZERO {
                        let o = offset_ray_origin(sp.p, sp.p_error, sp.ng, ls.wi);
                        let visible = if ls.dist.is_finite() {
                            let target = offset_ray_origin(ls.p, ls.p_error, ls.n, -ls.wi);
                            let d = target - o;
                            let dist = d.length();
                            dist > 0.0 && !scene.occluded_at(o, d / dist, dist * (1.0 - 1e-4), time)
                        } else {
                            !scene.occluded_at(o, ls.wi, f32::INFINITY, time)
                        };
                        nee_visible = visible;
                        if visible {
                            let p_light = pmf * ls.pdf;
                            let w = if ls.delta {
                                1.0
                            } else {
                                s.mis.weight(p_light, bsdf.pdf(wo, wi))
                            };
                            l += beta * f * ls.li * (w / p_light);
                        }
                    }
                }
                // Light through specular chains, from the same light sample dimensions.
                if mnee_here && !nee_visible {
                    let max_chain = ((max_depth - depth - 1) as usize).min(mnee::MAX_CHAIN);
                    l += beta
                        * mnee::estimate(
                            scene, &sp, &bsdf, &frame, wo, li, pmf, u_light2, time, max_chain,
                        );
                }
            }
        }

        // 4. Sample the BSDF for the next direction.
        let u_bsdf = sampler.next_1d();
        let u_bsdf2 = sampler.next_2d();
        let Some(bs) = bsdf.sample(wo, u_bsdf, u_bsdf2) else {
            break;
        };
        let wi_world = frame.to_world(bs.wi);
        if wi_world.dot(sp.ng).signum() != bs.wi.z.signum() {
            break; // crosses the geometric surface on the wrong side
        }
        beta *= bs.weight;
        if !beta.is_finite() || beta == Vec3::ZERO {
            break;
        }
        if MNEE {
            mnee_origin = if !bs.delta {
                // A new origin: MNEE at this vertex covers chains of up to `max_chain`.
                mnee_here.then(|| MneeOrigin {
                    x: mnee::Anchor::of(&sp),
                    n_select,
                    max_chain: ((max_depth - depth - 1) as usize).min(mnee::MAX_CHAIN),
                    chain: [Vec3::ZERO; mnee::MAX_CHAIN],
                    len: 0,
                })
            } else if bsdf.has_non_delta() {
                // A delta sample of a mixed material: MNEE chains hold only purely
                // specular vertices.
                None
            } else {
                mnee_origin.and_then(|mut m| {
                    (m.len < m.max_chain).then(|| {
                        m.chain[m.len] = sp.p;
                        m.len += 1;
                        m
                    })
                })
            };
        }
        if bs.wi.z * wo.z < 0.0 {
            if let Some(eta) = bsdf.glass_eta() {
                // Entering (wo outside, +z) radiance was scaled by 1/η², leaving by η².
                eta_scale *= if wo.z > 0.0 {
                    eta * eta
                } else {
                    1.0 / (eta * eta)
                };
            }
        }
        prev_delta = bs.delta;
        prev_pdf = bs.pdf;
        prev_p = sp.p;
        prev_n = n_select;
        origin = offset_ray_origin(sp.p, sp.p_error, sp.ng, wi_world);
        dir = wi_world;
        depth += 1;

        // 5. Russian roulette. Its dimension is consumed at every vertex, drawn only once
        // roulette has started.
        if depth < s.rr_depth {
            sampler.skip(1);
        } else {
            let u_rr = sampler.next_1d();
            let survive = (beta.max_element() * eta_scale).min(RR_MAX_SURVIVAL);
            if u_rr >= survive {
                break;
            }
            beta /= survive;
        }
    }
    l
}
