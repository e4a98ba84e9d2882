//! Step 4b: which caustics of delta and tiny lights manifold next-event estimation (MNEE)
//! samples (the module documentation's "Manifold next-event estimation" rule), by a
//! survey of specular chains from the lights and from the camera.
//!
//! MNEE as the renderer builds it (`tessera_render::integrator::mnee`; Hanika, Droske &
//! Fascione 2015, §3) runs at every non-specular vertex `x` of the camera path and connects
//! it to a point, spot or emissive-triangle light through the specular surfaces that the
//! straight segment from `x` to the light crosses (its *seed chain*), at most
//! [`MNEE_MAX_CHAIN`] of them, each purely specular (a mirror or a smooth dielectric). So
//! it samples a delta light's caustic `L S{1,2} D` where
//!
//! - the light is a point, spot or (tiny) area light, not a directional or sphere light;
//! - the light reaches the receiver by crossing the specular surfaces, not by reflecting
//!   off them: a reflection's vertex is not on the straight segment, so no seed finds it
//!   (the Fresnel reflection of a glass ball onto the floor, a mirror's caustic);
//! - the chain has at most [`MNEE_MAX_CHAIN`] vertices, none of them a mixed material (a
//!   diffuse base under a specular coat is not a specular chain vertex);
//! - the camera sees the receiver at its first non-specular vertex, directly or through
//!   specular surfaces (`L S{1,2} D S* E`). This condition is the survey's, and
//!   conservative: MNEE also runs at the later vertices (so the same caustic's light after
//!   further bounces is sampled), but the survey does not follow camera paths through
//!   diffuse bounces, so a caustic seen only after one is not known to be within reach and
//!   keeps vertex merging.
//!
//! The survey checks these the way MNEE's seed sees the scene: from each point and spot
//! light (and the centre of each tiny area light) [`LIGHT_RAYS`] rays (a Fibonacci
//! lattice over the sphere, or over a spot's cone) are followed through the specular
//! surfaces they meet, straight on through a refracting one (as the seed segment crosses
//! it) and mirrored about the geometric normal off a reflecting one, up to
//! [`MNEE_MAX_CHAIN`] + 1 vertices; every branch that reaches a diffuse or glossy surface
//! after at least one specular vertex is a caustic, and must be of MNEE's shape. From the
//! camera, the direct-light survey's grid of rays is followed through specular surfaces
//! (both branches, up to [`CAMERA_CHAIN`] vertices) to the first non-specular surfaces;
//! the caustics' receivers must be among them. Materials, not points, are compared: the
//! survey errs toward "MNEE reaches it" only where a caustic's receiver material is seen
//! at all. A survey that finds no caustic at all (every ray missed the specular surfaces)
//! counts as not reaching: the plan then keeps vertex merging.

use super::direct::{camera_rays, emitting_point, primitives, Bvh};
use super::evidence::material_list;
use super::lights::{AreaLight, Lights};
use super::survey::Survey;
use super::{MNEE_MAX_CHAIN, SMALL_LIGHT_FRACTION, TINY_LIGHT_FRACTION};
use crate::PunctualLight;
use glam::Vec3;

/// Rays traced from each point, spot and tiny area light.
pub const LIGHT_RAYS: u32 = 1024;

/// Specular vertices followed along a camera ray before giving up on it.
pub const CAMERA_CHAIN: usize = 4;

/// What keeps MNEE from a caustic, each kind with the first example found.
#[derive(Default)]
struct Findings {
    /// Materials that receive a caustic MNEE samples (through purely refracting chains of
    /// at most [`MNEE_MAX_CHAIN`] vertices).
    receivers: Vec<usize>,
    /// A caustic through more specular vertices than MNEE's chains hold.
    longer: Option<String>,
    /// A caustic by a reflection, which no seed segment finds.
    reflection: Option<String>,
    /// A caustic through a mixed (diffuse or glossy and specular) material.
    mixed: Option<String>,
}

/// Where the survey's light rays start: a light's name for the evidence, its position and,
/// for a spot, its axis and the cosine of its outer angle.
struct Source {
    name: String,
    at: Vec3,
    cone: Option<(Vec3, f32)>,
}

/// A branch of a light's specular chain: how it got where it is.
#[derive(Clone, Copy)]
struct Branch {
    /// Specular vertices so far.
    vertices: usize,
    /// The first specular material met.
    first: usize,
    /// Whether some vertex reflected.
    reflected: Option<usize>,
    /// Whether some vertex was of a mixed material.
    mixed: Option<usize>,
}

/// Why MNEE cannot sample every caustic of the scene's delta and tiny lights, each reason
/// with its evidence; empty when it can. Run for scenes with delta-lit caustics.
pub(super) fn misses(survey: &Survey, lights: &Lights) -> Vec<String> {
    let scene = survey.scene;
    let mut out = Vec::new();
    let tiny = TINY_LIGHT_FRACTION * survey.scene_radius;
    let mut sources: Vec<Source> = Vec::new();
    for (i, l) in scene.lights.iter().enumerate() {
        if let Some((at, cone)) = emitting_point(l) {
            let kind = if cone.is_some() { "spot" } else { "point" };
            sources.push(Source {
                name: format!("{kind} light {i}"),
                at,
                cone,
            });
        } else if let PunctualLight::Directional { irradiance, .. } = *l {
            if irradiance.max_element() > 0.0 {
                out.push(format!(
                    "directional light {i}: MNEE connects to light points (point, spot and \
                     emissive-triangle lights), not to a direction"
                ));
            }
        }
    }
    for (i, s) in &lights.spheres {
        if s.radius < tiny {
            out.push(format!(
                "sphere light {i} (radius {}): MNEE connects to point, spot and \
                 emissive-triangle lights, not to spheres",
                s.radius
            ));
        }
    }
    for a in &lights.area {
        if a.bounds.radius() < tiny {
            sources.push(area_source(survey, a));
        }
    }
    let Some(prims) = primitives(survey) else {
        out.push(
            "the scene has too many primitives for the survey of specular chains, so \
             MNEE's reach is unknown"
                .into(),
        );
        return out;
    };
    let bvh = Bvh::new(prims);
    let eps = 1e-4 * survey.scene_radius;
    let found = survey_sources(survey, &bvh, &sources, eps);
    let list = |m: &[usize]| material_list(scene, m, &survey.classes, false);
    out.extend(found.longer);
    out.extend(found.reflection);
    out.extend(found.mixed);
    if found.receivers.is_empty() {
        if !sources.is_empty() {
            out.push(format!(
                "the survey of {LIGHT_RAYS} rays from each light found no caustic that MNEE's \
                 chains hold, so none is known to be within its reach"
            ));
        }
        return out;
    }
    let seen = first_seen(survey, &bvh, eps);
    if !found.receivers.iter().any(|m| seen.contains(m)) {
        out.push(format!(
            "the caustics on {} appear at no surface the camera sees first (directly or \
             through specular surfaces): their light reaches the camera only after a further \
             diffuse or glossy bounce, which the survey does not follow, so they are not known \
             to be within MNEE's reach",
            list(&found.receivers)
        ));
    }
    out
}

/// Follows [`LIGHT_RAYS`] rays from each source through the specular surfaces they meet
/// and collects what their chains found.
fn survey_sources(survey: &Survey, bvh: &Bvh, sources: &[Source], eps: f32) -> Findings {
    let mut found = Findings::default();
    for Source { name, at, cone } in sources {
        for d in directions(*cone) {
            let branch = Branch {
                vertices: 0,
                first: usize::MAX,
                reflected: None,
                mixed: None,
            };
            follow(survey, bvh, name, *at, d, eps, branch, &mut found);
        }
    }
    found
}

/// Whether manifold next-event estimation reaches caustics of the scene's small area
/// lights (bounding radius below [`SMALL_LIGHT_FRACTION`] of the scene's; the module
/// documentation's "Caustics of small area lights" rule): [`LIGHT_RAYS`] rays from each
/// such light's centre are followed through the specular surfaces as for [`misses`], and
/// the caustics of MNEE's shape (at most [`MNEE_MAX_CHAIN`] refracting surfaces, none
/// mixed) that land on a material the camera sees first are the evidence. `None` where
/// there is no small area light, no such caustic, or the scene is too large to survey.
/// Unlike [`misses`] it does not ask that every caustic be within reach: with finite
/// lights BSDF sampling keeps the paths MNEE does not claim.
pub(super) fn small_light_caustics(survey: &Survey, lights: &Lights) -> Option<String> {
    let scene = survey.scene;
    let small = SMALL_LIGHT_FRACTION * survey.scene_radius;
    let sources: Vec<Source> = lights
        .area
        .iter()
        .filter(|a| a.bounds.radius() < small)
        .map(|a| area_source(survey, a))
        .collect();
    if sources.is_empty() {
        return None;
    }
    let bvh = Bvh::new(primitives(survey)?);
    let eps = 1e-4 * survey.scene_radius;
    let found = survey_sources(survey, &bvh, &sources, eps);
    let seen = first_seen(survey, &bvh, eps);
    let reached: Vec<usize> = found
        .receivers
        .into_iter()
        .filter(|m| seen.contains(m))
        .collect();
    if reached.is_empty() {
        return None;
    }
    let names: Vec<&str> = sources.iter().map(|s| s.name.as_str()).collect();
    Some(format!(
        "{} through at most {MNEE_MAX_CHAIN} refracting surfaces onto {}, which the camera \
         sees",
        names.join(", "),
        material_list(scene, &reached, &survey.classes, false)
    ))
}

/// The survey's source for area light `a`: its bounding box's centre.
fn area_source(survey: &Survey, a: &AreaLight) -> Source {
    Source {
        name: format!(
            "the area light of {}",
            material_list(survey.scene, &[a.material], &survey.classes, false)
        ),
        at: 0.5 * (a.bounds.lo + a.bounds.hi),
        cone: None,
    }
}

/// Where a survey ray meets a scattering surface: the point, the geometric normal and the
/// material.
struct Hit {
    x: Vec3,
    n: Vec3,
    m: usize,
}

/// The first hit along `d` from `o`, if its material scatters (an emitter that does not,
/// or nothing, ends the ray).
fn hit(survey: &Survey, bvh: &Bvh, o: Vec3, d: Vec3, eps: f32) -> Option<Hit> {
    let (t, k) = bvh.trace(o, d, eps, f32::INFINITY, false)?;
    let prim = &bvh.prims[k];
    let x = o + t * d;
    survey.scatters(prim.material).then(|| Hit {
        x,
        n: prim.normal(x),
        m: prim.material,
    })
}

/// Follows a light's ray from `o` along `d` through specular surfaces, recording the
/// caustics it makes in `found`.
#[allow(clippy::too_many_arguments)]
fn follow(
    survey: &Survey,
    bvh: &Bvh,
    light: &str,
    o: Vec3,
    d: Vec3,
    eps: f32,
    branch: Branch,
    found: &mut Findings,
) {
    let Some(Hit { x, n, m }) = hit(survey, bvh, o, d, eps) else {
        return;
    };
    let c = &survey.classes[m];
    let list = |m: &[usize]| material_list(survey.scene, m, &survey.classes, false);
    if branch.vertices > 0 && (c.diffuse || c.glossy) {
        // A caustic: light reaching a diffuse or glossy surface through specular ones.
        if branch.vertices > MNEE_MAX_CHAIN {
            found.longer.get_or_insert_with(|| {
                format!(
                    "light of {light} crosses {} or more specular surfaces (the first of {}) \
                     before reaching {}: MNEE's chains hold at most {MNEE_MAX_CHAIN}",
                    branch.vertices,
                    list(&[branch.first]),
                    list(&[m])
                )
            });
        } else if let Some(r) = branch.reflected {
            found.reflection.get_or_insert_with(|| {
                format!(
                    "light of {light} reflects off specular {} onto {}: a reflection's vertex \
                     is not on the straight segment to the light, so MNEE's seed never finds it",
                    list(&[r]),
                    list(&[m])
                )
            });
        } else if let Some(x) = branch.mixed {
            found.mixed.get_or_insert_with(|| {
                format!(
                    "light of {light} reaches {} through {}, which is diffuse or glossy as \
                     well as specular: MNEE's chains hold only purely specular surfaces",
                    list(&[m]),
                    list(&[x])
                )
            });
        } else if !found.receivers.contains(&m) {
            found.receivers.push(m);
        }
    }
    let reflects = c.specular;
    let refracts = c.smooth_refraction;
    if !(reflects || refracts) || branch.vertices > MNEE_MAX_CHAIN {
        return;
    }
    let mixed = (c.diffuse || c.glossy).then_some(m).or(branch.mixed);
    let first = if branch.vertices == 0 {
        m
    } else {
        branch.first
    };
    if refracts {
        // Straight on, as MNEE's seed segment crosses the interface.
        let next = Branch {
            vertices: branch.vertices + 1,
            first,
            mixed,
            ..branch
        };
        follow(survey, bvh, light, x, d, eps, next, found);
    }
    if reflects {
        let r = d - 2.0 * d.dot(n) * n;
        let next = Branch {
            vertices: branch.vertices + 1,
            first,
            reflected: branch.reflected.or(Some(m)),
            mixed,
        };
        follow(survey, bvh, light, x, r, eps, next, found);
    }
}

/// The materials of the first non-specular surfaces the camera sees, directly or through
/// specular surfaces (both branches of each, up to [`CAMERA_CHAIN`] vertices).
fn first_seen(survey: &Survey, bvh: &Bvh, eps: f32) -> Vec<usize> {
    fn walk(
        survey: &Survey,
        bvh: &Bvh,
        o: Vec3,
        d: Vec3,
        eps: f32,
        depth: usize,
        seen: &mut Vec<usize>,
    ) {
        let Some(Hit { x, n, m }) = hit(survey, bvh, o, d, eps) else {
            return;
        };
        let c = &survey.classes[m];
        if c.diffuse || c.glossy {
            if !seen.contains(&m) {
                seen.push(m);
            }
            return;
        }
        if depth == CAMERA_CHAIN {
            return;
        }
        if c.smooth_refraction {
            walk(survey, bvh, x, d, eps, depth + 1, seen);
        }
        if c.specular {
            walk(survey, bvh, x, d - 2.0 * d.dot(n) * n, eps, depth + 1, seen);
        }
    }
    let (origin, rays) = camera_rays(survey.scene);
    let mut seen = Vec::new();
    for d in rays {
        walk(survey, bvh, origin, d, eps, 0, &mut seen);
    }
    seen
}

/// [`LIGHT_RAYS`] unit directions of a spherical Fibonacci lattice (González 2010), over
/// the whole sphere or, for a spot `(axis, cos outer)`, over its cone.
fn directions(cone: Option<(Vec3, f32)>) -> impl Iterator<Item = Vec3> {
    let (axis, cos_outer) = cone.unwrap_or((Vec3::Z, -1.0));
    let (b1, b2) = axis.any_orthonormal_pair();
    let golden = std::f32::consts::PI * (3.0 - 5f32.sqrt());
    (0..LIGHT_RAYS).map(move |i| {
        let cos = 1.0 - (1.0 - cos_outer) * (i as f32 + 0.5) / LIGHT_RAYS as f32;
        let sin = (1.0 - cos * cos).max(0.0).sqrt();
        let phi = golden * i as f32;
        cos * axis + sin * (phi.cos() * b1 + phi.sin() * b2)
    })
}
