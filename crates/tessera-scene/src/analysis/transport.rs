//! Step 4: light bouncing between surfaces (the module documentation's "Surfaces" and
//! "Light bouncing between surfaces" rules): which used materials scatter and how, whether
//! light can scatter more than once, indirect diffuse light, glossy and specular
//! reflection, refraction, total internal reflection and caustics.

use super::classify::Classes;
use super::evidence::{material_list, plural, verb};
use super::lights::Lights;
use super::survey::Survey;
use super::{push, Effect, EffectKind, CLOSED_FRACTION, SPECULAR_ROUGHNESS, TINY_LIGHT_FRACTION};
use crate::{PunctualLight, Sphere};
use glam::Vec3;

/// The used, scattering materials, by class (material indices in order).
pub(super) struct Surfaces {
    /// Every used material that scatters.
    pub(super) scattering: Vec<usize>,
    /// Those with a diffuse layer.
    pub(super) diffuse: Vec<usize>,
    /// Those with a glossy reflection.
    pub(super) glossy: Vec<usize>,
    /// Those with a specular reflection.
    pub(super) specular: Vec<usize>,
    /// Those that refract.
    pub(super) refraction: Vec<usize>,
    /// Those that reflect specularly or refract smoothly.
    pub(super) smooth_specular: Vec<usize>,
    /// Those with total internal reflection.
    pub(super) tir: Vec<usize>,
}

impl Surfaces {
    fn of(survey: &Survey) -> Self {
        let scattering: Vec<usize> = (0..survey.nmat()).filter(|&i| survey.scatters(i)).collect();
        let with = |f: fn(&Classes) -> bool| -> Vec<usize> {
            scattering
                .iter()
                .copied()
                .filter(|&i| f(&survey.classes[i]))
                .collect()
        };
        Self {
            diffuse: with(|c| c.diffuse),
            glossy: with(|c| c.glossy),
            specular: with(|c| c.specular),
            refraction: with(|c| c.refraction),
            smooth_specular: with(|c| c.specular || c.smooth_refraction),
            tir: with(|c| c.tir),
            scattering,
        }
    }
}

/// Whether light can scatter more than once, and the scattering primitives.
pub(super) struct Bouncing {
    /// Number of spheres whose material scatters.
    pub(super) spheres: usize,
    /// Number of triangles whose material scatters.
    pub(super) triangles: usize,
    /// Light can scatter more than once.
    pub(super) multi_bounce: bool,
    /// "N scattering surfaces" (meshes and spheres), for evidence and reasons.
    pub(super) surfaces: String,
}

/// What the transport step found, for the plan decision.
pub(super) struct Transport {
    /// The scattering materials by class.
    pub(super) surfaces: Surfaces,
    /// Whether light bounces between surfaces.
    pub(super) bouncing: Bouncing,
    /// Area-weighted mean diffuse albedo.
    pub(super) mean_albedo: f32,
    /// Scattering area over the bounding box's surface area.
    pub(super) enclosure: f32,
    /// [`EffectKind::IndirectDiffuse`] is present.
    pub(super) indirect_diffuse: bool,
    /// [`EffectKind::Caustics`] is present.
    pub(super) caustics: bool,
    /// [`EffectKind::DeltaLitCaustics`] is present.
    pub(super) delta_lit: bool,
    /// Only finite (tiny area or sphere) lights light the caustics, no point, spot or
    /// directional light: path tracing finds them too, by BSDF sampling, so it is a
    /// correct alternative to bdpt.
    pub(super) tiny_lit_only: bool,
    /// [`EffectKind::DeltaLitSds`] is present: a delta light's caustics may be seen through
    /// (or in) a specular surface the camera sees.
    pub(super) delta_sds: bool,
    /// What manifold next-event estimation cannot sample of the delta and tiny lights'
    /// caustics (`manifold::misses`), filled in by `analyse` after this step where
    /// [`Transport::delta_lit`]; empty otherwise.
    pub(super) beyond_mnee: Vec<String>,
    /// Where the caustics are lit by finite lights only, none of them tiny: the evidence
    /// that some are lit by small area lights through specular chains within manifold
    /// next-event estimation's reach (`manifold::small_light_caustics`), filled in by
    /// `analyse` after this step; `None` otherwise.
    pub(super) small_light_mnee: Option<String>,
}

/// Finds the transport effects, records them with their evidence, and returns what the
/// plan decision needs.
pub(super) fn analyse(survey: &Survey, lights: &Lights, effects: &mut Vec<Effect>) -> Transport {
    let surfaces = Surfaces::of(survey);
    let bouncing = bouncing(survey, lights);
    let (mean_albedo, enclosure) = albedo_and_enclosure(survey, &surfaces);
    let indirect_diffuse = bouncing.multi_bounce && !surfaces.diffuse.is_empty();
    if indirect_diffuse {
        let closed = if enclosure >= CLOSED_FRACTION {
            "closed"
        } else {
            "open"
        };
        push(
            effects,
            EffectKind::IndirectDiffuse,
            format!(
                "diffuse {} among {} that can exchange light; area-weighted diffuse \
                 albedo {mean_albedo:.2}; scattering surfaces cover {:.0}% of the bounding box \
                 ({closed})",
                material_list(survey.scene, &surfaces.diffuse, &survey.classes, false),
                bouncing.surfaces,
                100.0 * enclosure
            ),
        );
    }
    report_reflection(survey, &surfaces, effects);
    let caustics = lights.any()
        && bouncing.multi_bounce
        && !surfaces.smooth_specular.is_empty()
        && !surfaces.diffuse.is_empty();
    if caustics {
        push(
            effects,
            EffectKind::Caustics,
            format!(
                "light can reach diffuse {} through specular {}",
                material_list(survey.scene, &surfaces.diffuse, &survey.classes, false),
                material_list(
                    survey.scene,
                    &surfaces.smooth_specular,
                    &survey.classes,
                    false
                )
            ),
        );
    }
    let (delta_lit, tiny_lit_only) = if caustics {
        report_delta_lit(survey, lights, effects)
    } else {
        (false, false)
    };
    let delta_sds = delta_lit && report_delta_sds(survey, lights, &surfaces, effects);
    report_tiny_light_images(survey, lights, &surfaces, effects);
    Transport {
        surfaces,
        bouncing,
        mean_albedo,
        enclosure,
        indirect_diffuse,
        caustics,
        delta_lit,
        tiny_lit_only,
        delta_sds,
        beyond_mnee: Vec::new(),
        small_light_mnee: None,
    }
}

/// The `L S+ D S+ E` class from delta lights ([`EffectKind::DeltaLitSds`]): the scene has
/// delta-lit caustics, a point, spot or directional light, and the camera sees a smooth
/// specular surface, through or in which a caustic may appear. Conservative: a specular
/// primitive counts as seen when its bounding sphere meets the camera's view cone (the
/// cone around the image's diagonal), whether or not a caustic shows through it.
fn report_delta_sds(
    survey: &Survey,
    lights: &Lights,
    surfaces: &Surfaces,
    effects: &mut Vec<Effect>,
) -> bool {
    if lights.delta() == 0 {
        return false;
    }
    let seen = specular_in_view(survey, &surfaces.smooth_specular);
    if seen.is_empty() {
        return false;
    }
    push(
        effects,
        EffectKind::DeltaLitSds,
        format!(
            "the camera sees specular {}, through or in which the caustics of {} can appear: \
             light paths L S+ D S+ E, which no connection technique samples",
            material_list(survey.scene, &seen, &survey.classes, false),
            plural(lights.delta(), "delta light", "delta lights")
        ),
    );
    true
}

/// The images of tiny lights in specular surfaces ([`EffectKind::TinyLightImages`]): a
/// tiny sphere or area light ([`tiny_finite_lights`]) and a smooth specular primitive the
/// camera may see ([`specular_in_view`]), in or through which the light may appear as
/// `E S+ L`. Conservative as [`report_delta_sds`] is: whether the light shows in the
/// surface is not checked. The error estimate's caveat says what it costs
/// (docs/benchmarks.md, "the bdpt caustic re-measured, and where its error is": most of a
/// render's error in one to three pixels holding a single sample of the light).
fn report_tiny_light_images(
    survey: &Survey,
    lights: &Lights,
    surfaces: &Surfaces,
    effects: &mut Vec<Effect>,
) {
    let tiny = tiny_finite_lights(survey, lights);
    if tiny.is_empty() {
        return;
    }
    let seen = specular_in_view(survey, &surfaces.smooth_specular);
    if seen.is_empty() {
        return;
    }
    push(
        effects,
        EffectKind::TinyLightImages,
        format!(
            "the camera sees specular {}, in or through which the images of {} can appear \
             (E S+ L)",
            material_list(survey.scene, &seen, &survey.classes, false),
            tiny.join(", ")
        ),
    );
}

/// The tiny finite lights, each described: sphere lights and groups of emissive triangles
/// (by material) whose bounding radius is below [`TINY_LIGHT_FRACTION`] of the scene's.
fn tiny_finite_lights(survey: &Survey, lights: &Lights) -> Vec<String> {
    let scene_radius = survey.scene_radius;
    let tiny = TINY_LIGHT_FRACTION * scene_radius;
    let mut out = Vec::new();
    for (i, s) in &lights.spheres {
        if s.radius < tiny {
            out.push(format!(
                "sphere light {i} of radius {} ({:.2}% of the scene radius {:.2})",
                s.radius,
                100.0 * s.radius / scene_radius,
                scene_radius
            ));
        }
    }
    for a in &lights.area {
        let r = a.bounds.radius();
        if r < tiny {
            out.push(format!(
                "area light of {} of radius {r} ({:.2}% of the scene radius {:.2})",
                material_list(survey.scene, &[a.material], &survey.classes, false),
                100.0 * r / scene_radius,
                scene_radius
            ));
        }
    }
    out
}

/// The materials among `specular` of a sphere or triangle whose bounding sphere meets the
/// camera's view cone, in material order.
fn specular_in_view(survey: &Survey, specular: &[usize]) -> Vec<usize> {
    let camera = &survey.scene.camera;
    let origin = camera.world_from_camera.transform_point3(Vec3::ZERO);
    let Some(forward) = camera
        .world_from_camera
        .transform_vector3(Vec3::NEG_Z)
        .try_normalize()
    else {
        return Vec::new();
    };
    // Half the angle of the image's diagonal; an image without an aspect ratio of its own
    // is taken as wide as 2:1 (erring on the side of seeing more).
    let aspect = camera.aspect_ratio.unwrap_or(2.0).max(1.0);
    let half = ((0.5 * camera.yfov).tan() * (1.0 + aspect * aspect).sqrt()).atan();
    let in_view = |center: Vec3, radius: f32| {
        let v = center - origin;
        let d = v.length();
        if d <= radius {
            return true;
        }
        let angle = (v.dot(forward) / d).clamp(-1.0, 1.0).acos();
        angle <= half + (radius / d).clamp(0.0, 1.0).asin()
    };
    let mut seen: Vec<usize> = Vec::new();
    for s in &survey.scene.spheres {
        let m = s.material as usize;
        if specular.contains(&m) && !seen.contains(&m) && in_view(s.center, s.radius) {
            seen.push(m);
        }
    }
    for placed in survey.scene.placed_meshes() {
        let m = placed.material() as usize;
        if !specular.contains(&m) || seen.contains(&m) {
            continue;
        }
        if placed.triangles().any(|t| {
            let c = (t[0] + t[1] + t[2]) / 3.0;
            let r = t.iter().map(|p| p.distance(c)).fold(0.0f32, f32::max);
            in_view(c, r)
        }) {
            seen.push(m);
        }
    }
    seen.sort_unstable();
    seen
}

/// Multi-bounce: is the scattering geometry more than one plane or one convex sphere?
fn bouncing(survey: &Survey, lights: &Lights) -> Bouncing {
    let scene = survey.scene;
    let scattering_spheres: Vec<&Sphere> = scene
        .spheres
        .iter()
        .filter(|s| survey.scatters(s.material as usize))
        .collect();
    let (scattering_triangles, coplanar) = scattering_triangles(survey);
    let scattering_meshes = scene
        .placed_meshes()
        .filter(|m| !m.mesh.indices.is_empty() && survey.scatters(m.material() as usize))
        .count();
    let multi_bounce = match (scattering_spheres.len(), scattering_triangles) {
        (0, _) => !coplanar,
        (1, 0) => sphere_contains_camera_or_light(survey, lights, scattering_spheres[0]),
        _ => true,
    };
    let surfaces = plural(
        scattering_meshes + scattering_spheres.len(),
        "scattering surface",
        "scattering surfaces",
    );
    Bouncing {
        spheres: scattering_spheres.len(),
        triangles: scattering_triangles,
        multi_bounce,
        surfaces,
    }
}

/// The number of triangles whose material scatters, and whether they are all coplanar.
fn scattering_triangles(survey: &Survey) -> (usize, bool) {
    let mut scattering_triangles = 0usize;
    let mut plane: Option<(Vec3, f32)> = None;
    let mut coplanar = true;
    let eps = 1e-4 * survey.scene_radius;
    for placed in survey
        .scene
        .placed_meshes()
        .filter(|m| survey.scatters(m.material() as usize))
    {
        for p in placed.triangles() {
            scattering_triangles += 1;
            if !coplanar {
                continue;
            }
            match plane {
                None => {
                    let n = (p[1] - p[0]).cross(p[2] - p[0]);
                    if n.length() > 0.0 {
                        let n = n.normalize();
                        plane = Some((n, n.dot(p[0])));
                    }
                }
                Some((n, d)) => {
                    if p.iter().any(|v| (n.dot(*v) - d).abs() > eps) {
                        coplanar = false;
                    }
                }
            }
        }
    }
    (scattering_triangles, coplanar)
}

/// A sphere is convex: light scatters off it once unless the camera or a light is inside
/// it.
fn sphere_contains_camera_or_light(survey: &Survey, lights: &Lights, s: &Sphere) -> bool {
    let scene = survey.scene;
    let camera_pos = scene.camera.world_from_camera.w_axis.truncate();
    let inside = |p: Vec3| (p - s.center).length() < s.radius;
    inside(camera_pos)
        || scene.lights.iter().any(|l| match l {
            PunctualLight::Point { position, .. } | PunctualLight::Spot { position, .. } => {
                inside(*position)
            }
            PunctualLight::Directional { .. } => false,
        })
        || lights.spheres.iter().any(|(_, l)| inside(l.center))
        || lights
            .area
            .iter()
            .any(|a| inside(0.5 * (a.bounds.lo + a.bounds.hi)))
}

/// Area-weighted diffuse albedo, and the enclosure: the scattering area over the surface
/// area of the geometry's bounding box.
fn albedo_and_enclosure(survey: &Survey, surfaces: &Surfaces) -> (f32, f32) {
    let area_by_material = &survey.area_by_material;
    let (mut albedo_sum, mut diffuse_area) = (0.0f32, 0.0f32);
    for &i in &surfaces.diffuse {
        albedo_sum += survey.classes[i].diffuse_albedo * area_by_material[i];
        diffuse_area += area_by_material[i];
    }
    let mean_albedo = if diffuse_area > 0.0 {
        albedo_sum / diffuse_area
    } else {
        0.0
    };
    let scattering_area: f32 = surfaces
        .scattering
        .iter()
        .map(|&i| area_by_material[i])
        .sum();
    let box_area = survey.geometry.surface_area();
    let enclosure = if box_area > 0.0 {
        scattering_area / box_area
    } else {
        0.0
    };
    (mean_albedo, enclosure)
}

/// Records glossy and specular reflection, refraction and total internal reflection.
fn report_reflection(survey: &Survey, surfaces: &Surfaces, effects: &mut Vec<Effect>) {
    let list =
        |indices: &[usize], detail| material_list(survey.scene, indices, &survey.classes, detail);
    let Surfaces {
        glossy,
        specular,
        refraction,
        tir,
        ..
    } = surfaces;
    if !glossy.is_empty() {
        push(
            effects,
            EffectKind::GlossyReflection,
            format!(
                "{} {} glossily",
                list(glossy, true),
                verb("reflect", glossy.len())
            ),
        );
    }
    if !specular.is_empty() {
        push(
            effects,
            EffectKind::SpecularReflection,
            format!(
                "{} {} specularly (roughness < {SPECULAR_ROUGHNESS})",
                list(specular, true),
                verb("reflect", specular.len())
            ),
        );
    }
    if !refraction.is_empty() {
        push(
            effects,
            EffectKind::Refraction,
            format!(
                "{} {}",
                list(refraction, true),
                verb("transmit", refraction.len())
            ),
        );
    }
    if !tir.is_empty() {
        push(
            effects,
            EffectKind::TotalInternalReflection,
            format!(
                "{} can trap light by total internal reflection (ior != 1)",
                list(tir, false)
            ),
        );
    }
}

/// For a scene with caustics: records [`EffectKind::DeltaLitCaustics`] if delta or tiny
/// lights light them, and returns whether it did and whether only tiny finite lights did.
fn report_delta_lit(survey: &Survey, lights: &Lights, effects: &mut Vec<Effect>) -> (bool, bool) {
    let mut delta_evidence: Vec<String> = Vec::new();
    if lights.points > 0 {
        delta_evidence.push(plural(lights.points, "point light", "point lights"));
    }
    if lights.spots > 0 {
        delta_evidence.push(plural(lights.spots, "spot light", "spot lights"));
    }
    if lights.directionals > 0 {
        delta_evidence.push(plural(
            lights.directionals,
            "directional light",
            "directional lights",
        ));
    }
    let delta_lights = !delta_evidence.is_empty();
    delta_evidence.extend(tiny_finite_lights(survey, lights));
    let delta_lit = !delta_evidence.is_empty();
    if delta_lit {
        push(
            effects,
            EffectKind::DeltaLitCaustics,
            format!(
                "the caustics are lit by {}: next-event estimation cannot connect through a \
                 specular chain to them",
                delta_evidence.join(", ")
            ),
        );
    }
    (delta_lit, delta_lit && !delta_lights)
}
