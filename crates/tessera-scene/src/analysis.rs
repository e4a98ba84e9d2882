//! Scene analysis: which light-transport effects a scene contains, and the render plan
//! that simulates exactly those (DESIGN §4, "simulate only what the scene calls for").
//!
//! [`analyse`] looks at the lights, the materials that surfaces actually use, the shape of
//! the geometry and the camera, and returns a [`RenderPlan`]: the [`Effect`]s present, each
//! with its evidence, the [`EffectKind`]s that are absent, and the integrator with the path
//! depth and Russian-roulette settings chosen for exactly those effects, with the reasons.
//!
//! # The rules (this is the contract)
//!
//! **Lights.** A light counts only if it has positive power:
//! - area lights: emissive triangles (emission > 0, area > 0), grouped by material
//!   ([`EffectKind::DirectArea`]);
//! - sphere lights: spheres with an emissive material ([`EffectKind::DirectSphere`]);
//! - point, spot and directional lights: [`PunctualLight`]s with positive intensity or
//!   irradiance (a spot also needs an outer cone angle > 0) ([`EffectKind::DirectPoint`],
//!   [`EffectKind::DirectSpot`], [`EffectKind::DirectDirectional`]);
//! - the environment: [`Scene::environment`] with positive radiance
//!   ([`EffectKind::DirectEnvironment`]).
//!
//! With no light the plan is [`PlannedIntegrator::Black`], reason "no light: the image is
//! black", and the renderer skips tracing. The same holds when the only lights are point,
//! spot or directional lights (which the camera cannot see) and no surface scatters light.
//! A black plan is empty: it lists no effect besides the lights found.
//!
//! **Surfaces.** Only materials used by a mesh with triangles or by a sphere count. A
//! material *scatters* unless every layer below is absent (an emitter with zero albedo is
//! a light and nothing else). The classes of each material:
//! - `Diffuse`: diffuse (if the albedo is > 0);
//! - `Phong`: glossy if `ks > 0`, diffuse if `kd > 0`;
//! - `Conductor`: specular if roughness < [`SPECULAR_ROUGHNESS`], glossy otherwise;
//! - `Mirror`: specular (if the reflectance is > 0);
//! - `Dielectric`: refraction (if the tint is > 0; *smooth* refraction if roughness <
//!   [`SPECULAR_ROUGHNESS`]); with `ior != 1` also a Fresnel reflection (specular or
//!   glossy by roughness) and total internal reflection;
//! - `MetallicRoughness` (glTF), by layer weight:
//!   - the metal (`metallic > 0` and a base colour above 0) is a conductor as above;
//!   - the dielectric base (weight `(1 - metallic)(1 - transmission)` above 0) is diffuse
//!     if the base colour is above 0, under a Fresnel coat (if `ior > 1`) that counts as
//!     specular if roughness < [`SPECULAR_ROUGHNESS`], glossy if roughness <
//!     [`DIFFUSE_LIKE_ROUGHNESS`], and not at all above that (a roughness-1 dielectric
//!     coat is basically diffuse, so a plain glTF wall is "diffuse");
//!   - the transmissive part (weight `(1 - metallic) transmission` above 0) refracts
//!     (smoothly if roughness < [`SPECULAR_ROUGHNESS`]) under a Fresnel reflection (if
//!     `ior > 1`, specular or glossy by roughness), with total internal reflection if
//!     `ior > 1`.
//!
//! [`EffectKind::GlossyReflection`], [`EffectKind::SpecularReflection`],
//! [`EffectKind::Refraction`] and [`EffectKind::TotalInternalReflection`] are present when
//! some used, scattering material has that class.
//!
//! **Light bouncing between surfaces.** The scattering primitives are the spheres and the
//! triangles whose material scatters. Light can scatter more than once (a *multi-bounce*
//! scene) unless the scattering geometry is a single plane (all scattering triangles
//! coplanar and no scattering sphere) or a single sphere seen and lit only from outside.
//! A non-planar mesh counts as multi-bounce even if it is convex: the analysis errs on the
//! side of simulating more, never less.
//! - [`EffectKind::IndirectDiffuse`]: multi-bounce and some material is diffuse.
//! - [`EffectKind::Caustics`]: multi-bounce, some material is specular or refracts
//!   smoothly (a mirror, smooth glass, smooth metal: roughness < [`SPECULAR_ROUGHNESS`]),
//!   some material is diffuse, and there is a light.
//! - [`EffectKind::DeltaLitCaustics`]: caustics, and at least one point, spot or
//!   directional light, or a tiny sphere or area light (bounding radius below
//!   [`TINY_LIGHT_FRACTION`] of the scene's bounding radius): light a path tracer with
//!   next-event estimation reaches through a specular chain with zero (or almost zero)
//!   probability.
//!
//! **Camera, motion, textures.** [`EffectKind::DepthOfField`] iff the camera aperture
//! radius is > 0, and then `lens_sampling` is on; [`EffectKind::Motion`] is always absent
//! (the scene description has no animation data: a static scene);
//! [`EffectKind::Textures`] iff a used material has a base-colour texture.
//!
//! **Integrator.**
//! - [`PlannedIntegrator::Black`] if there is no light (see above);
//! - [`PlannedIntegrator::Direct`] if nothing can bounce light to the camera a second
//!   time: no indirect diffuse and nothing glossy, specular or refractive (e.g. a single
//!   plane under a light);
//! - [`PlannedIntegrator::Bdpt`] if there are delta-lit caustics;
//! - [`PlannedIntegrator::Path`] otherwise.
//!
//! **Depth.** `Direct`: `max_depth` 1. `Path`/`Bdpt`: [`CLOSED_ROOM_DEPTH`] for a *closed
//! bright room* — indirect diffuse, an area-weighted mean diffuse albedo above
//! [`BRIGHT_ALBEDO`] and scattering surfaces whose area is at least [`CLOSED_FRACTION`] of
//! the surface of the scene's bounding box — else [`DEFAULT_DEPTH`]; with refraction at
//! least [`REFRACTION_DEPTH`] (light needs several interfaces to pass through glass).
//! `rr_depth` is [`DEFAULT_RR_DEPTH`], or [`REFRACTION_RR_DEPTH`] with refraction. `Black`
//! has depth 0: nothing is traced.
//!
//! ```
//! use tessera_scene::analysis::{analyse, EffectKind, PlannedIntegrator};
//! let plan = analyse(&tessera_scene::load("builtin:cornell-box").unwrap());
//! assert!(plan.has(EffectKind::IndirectDiffuse));
//! assert_eq!(plan.integrator, PlannedIntegrator::Path);
//! ```

use crate::{Material, MaterialKind, PunctualLight, Scene, Texture};
use glam::Vec3;
pub use tessera_farm::job::plan::{Effect, EffectKind, PlannedIntegrator, RenderPlan};

/// Roughness below which a reflection or refraction counts as specular (near-delta).
pub const SPECULAR_ROUGHNESS: f32 = 0.05;
/// Roughness from which the Fresnel coat of a glTF dielectric base counts as part of the
/// diffuse lobe rather than as glossy reflection.
pub const DIFFUSE_LIKE_ROUGHNESS: f32 = 0.9;
/// A sphere or area light whose bounding radius is below this fraction of the scene's
/// bounding radius is "tiny": for caustics it behaves like a point light.
pub const TINY_LIGHT_FRACTION: f32 = 0.01;
/// Area-weighted mean diffuse albedo above which a room is "bright".
pub const BRIGHT_ALBEDO: f32 = 0.5;
/// Fraction of the bounding box's surface that scattering surfaces must cover for the
/// scene to count as a closed room.
pub const CLOSED_FRACTION: f32 = 0.75;
/// Path depth of a closed bright room.
pub const CLOSED_ROOM_DEPTH: u32 = 16;
/// Path depth otherwise.
pub const DEFAULT_DEPTH: u32 = 8;
/// Minimum path depth when something refracts.
pub const REFRACTION_DEPTH: u32 = 12;
/// Russian roulette start depth by default.
pub const DEFAULT_RR_DEPTH: u32 = 3;
/// Russian roulette start depth when something refracts.
pub const REFRACTION_RR_DEPTH: u32 = 5;

/// How one material scatters light (see the module documentation).
#[derive(Clone, Debug, Default)]
struct Classes {
    diffuse: bool,
    glossy: bool,
    specular: bool,
    refraction: bool,
    smooth_refraction: bool,
    tir: bool,
    /// Mean diffuse albedo (over channels, textures averaged), weighted by the diffuse
    /// layer's weight.
    diffuse_albedo: f32,
    /// Short description of the model, for evidence.
    describe: String,
}

impl Classes {
    fn scatters(&self) -> bool {
        self.diffuse || self.glossy || self.specular || self.refraction
    }

    /// Reflection layer with the given roughness: specular or glossy.
    fn reflect(&mut self, roughness: f32) {
        if roughness < SPECULAR_ROUGHNESS {
            self.specular = true;
        } else {
            self.glossy = true;
        }
    }
}

fn mean(v: Vec3) -> f32 {
    (v.x + v.y + v.z) / 3.0
}

fn texture_mean(t: &Texture) -> Vec3 {
    if t.texels.is_empty() {
        return Vec3::ZERO;
    }
    t.texels.iter().copied().sum::<Vec3>() / t.texels.len() as f32
}

fn classify(m: &Material, textures: &[Texture]) -> Classes {
    let mut c = Classes::default();
    match &m.kind {
        MaterialKind::Diffuse { albedo } => {
            c.describe = format!("diffuse, albedo {:.2}", mean(*albedo));
            if albedo.max_element() > 0.0 {
                c.diffuse = true;
                c.diffuse_albedo = mean(*albedo);
            }
        }
        MaterialKind::Phong { kd, ks, exponent } => {
            c.describe = format!(
                "Phong, kd {:.2}, ks {:.2}, exponent {exponent}",
                mean(*kd),
                mean(*ks)
            );
            if kd.max_element() > 0.0 {
                c.diffuse = true;
                c.diffuse_albedo = mean(*kd);
            }
            c.glossy = ks.max_element() > 0.0;
        }
        MaterialKind::Conductor { f0, roughness } => {
            c.describe = format!("conductor, f0 {:.2}, roughness {roughness}", mean(*f0));
            c.reflect(*roughness);
        }
        MaterialKind::Mirror { reflectance } => {
            c.describe = format!("mirror, reflectance {:.2}", mean(*reflectance));
            c.specular = reflectance.max_element() > 0.0;
        }
        MaterialKind::Dielectric {
            ior,
            roughness,
            tint,
        } => {
            c.describe = format!("dielectric, ior {ior}, roughness {roughness}");
            if tint.max_element() > 0.0 {
                c.refraction = true;
                c.smooth_refraction = *roughness < SPECULAR_ROUGHNESS;
            }
            if *ior != 1.0 {
                c.reflect(*roughness);
                c.tir = c.refraction;
            }
        }
        MaterialKind::MetallicRoughness {
            base_color,
            base_color_texture,
            metallic,
            roughness,
            transmission,
            ior,
        } => {
            c.describe = format!(
                "metallic-roughness, metallic {metallic}, roughness {roughness}, \
                 transmission {transmission}, ior {ior}"
            );
            let texture = base_color_texture.and_then(|t| textures.get(t.texture as usize));
            let color = *base_color * texture.map_or(Vec3::ONE, texture_mean);
            let coloured = color.max_element() > 0.0;
            let (metal, base, trans) = (
                *metallic,
                (1.0 - metallic) * (1.0 - transmission),
                (1.0 - metallic) * transmission,
            );
            if metal > 0.0 && coloured {
                c.reflect(*roughness);
            }
            if base > 0.0 {
                if coloured {
                    c.diffuse = true;
                    c.diffuse_albedo = base * mean(color);
                }
                if *ior > 1.0 && *roughness < DIFFUSE_LIKE_ROUGHNESS {
                    c.reflect(*roughness);
                }
            }
            if trans > 0.0 {
                if *ior > 1.0 {
                    c.reflect(*roughness);
                }
                if coloured {
                    c.refraction = true;
                    c.smooth_refraction = *roughness < SPECULAR_ROUGHNESS;
                    c.tir = *ior > 1.0;
                }
            }
        }
    }
    c
}

/// Axis-aligned bounds, empty until a point is added.
#[derive(Clone, Copy)]
struct Bounds {
    lo: Vec3,
    hi: Vec3,
}

impl Bounds {
    fn empty() -> Self {
        Self {
            lo: Vec3::splat(f32::INFINITY),
            hi: Vec3::splat(f32::NEG_INFINITY),
        }
    }
    fn add(&mut self, p: Vec3) {
        self.lo = self.lo.min(p);
        self.hi = self.hi.max(p);
    }
    fn is_empty(&self) -> bool {
        self.lo.x > self.hi.x
    }
    fn radius(&self) -> f32 {
        if self.is_empty() {
            0.0
        } else {
            0.5 * (self.hi - self.lo).length()
        }
    }
    fn surface_area(&self) -> f32 {
        if self.is_empty() {
            return 0.0;
        }
        let d = self.hi - self.lo;
        2.0 * (d.x * d.y + d.y * d.z + d.z * d.x)
    }
}

/// "material 1 'glass'" or "materials 4 'plate0', 5 'plate1' and 2 more", optionally with
/// each material's description in parentheses.
fn material_list(scene: &Scene, indices: &[usize], classes: &[Classes], detail: bool) -> String {
    const SHOWN: usize = 6;
    let item = |&i: &usize| {
        let name = &scene.materials[i].name;
        // The glTF importer already names materials "material 3 'light'".
        let label = match name.strip_prefix(&format!("material {i}")) {
            Some(rest) if rest.is_empty() || rest.starts_with(' ') => format!("{i}{rest}"),
            _ => format!("{i} '{name}'"),
        };
        if detail {
            format!("{label} ({})", classes[i].describe)
        } else {
            label
        }
    };
    let mut s = String::from(if indices.len() == 1 {
        "material "
    } else {
        "materials "
    });
    s += &indices
        .iter()
        .take(SHOWN)
        .map(item)
        .collect::<Vec<_>>()
        .join(", ");
    if indices.len() > SHOWN {
        s += &format!(" and {} more", indices.len() - SHOWN);
    }
    s
}

fn plural(n: usize, one: &str, many: &str) -> String {
    format!("{n} {}", if n == 1 { one } else { many })
}

/// Subject-verb agreement: `verb("reflect", 1)` is "reflects", otherwise "reflect".
fn verb(v: &str, n: usize) -> String {
    if n == 1 {
        format!("{v}s")
    } else {
        v.to_string()
    }
}

fn triangle_area(p: [Vec3; 3]) -> f32 {
    0.5 * (p[1] - p[0]).cross(p[2] - p[0]).length()
}

/// Analyses `scene` into a render plan, following the rules in the module documentation.
pub fn analyse(scene: &Scene) -> RenderPlan {
    let classes: Vec<Classes> = scene
        .materials
        .iter()
        .map(|m| classify(m, &scene.textures))
        .collect();
    let nmat = scene.materials.len();

    // Which materials are used, and the geometry's extent and areas.
    let mut used = vec![false; nmat];
    let mut area_by_material = vec![0.0f32; nmat];
    let mut geometry = Bounds::empty();
    for mesh in &scene.meshes {
        let mi = mesh.material as usize;
        if mesh.indices.is_empty() || mi >= nmat {
            continue;
        }
        used[mi] = true;
        for t in &mesh.indices {
            let p = t.map(|i| mesh.positions[i as usize]);
            area_by_material[mi] += triangle_area(p);
            for v in p {
                geometry.add(v);
            }
        }
    }
    for s in &scene.spheres {
        let mi = s.material as usize;
        if mi >= nmat {
            continue;
        }
        used[mi] = true;
        area_by_material[mi] += 4.0 * std::f32::consts::PI * s.radius * s.radius;
        geometry.add(s.center - Vec3::splat(s.radius));
        geometry.add(s.center + Vec3::splat(s.radius));
    }
    let scene_radius = {
        let mut b = geometry;
        if b.is_empty() {
            b.add(scene.camera.world_from_camera.w_axis.truncate());
            for l in &scene.lights {
                match l {
                    PunctualLight::Point { position, .. }
                    | PunctualLight::Spot { position, .. } => b.add(*position),
                    PunctualLight::Directional { .. } => {}
                }
            }
        }
        let r = b.radius();
        if r > 0.0 {
            r
        } else {
            1.0
        }
    };
    let scatters = |mi: usize| mi < nmat && used[mi] && classes[mi].scatters();

    let mut effects: Vec<Effect> = Vec::new();
    let mut reasons: Vec<String> = Vec::new();
    let mut push = |kind, evidence: String| effects.push(Effect { kind, evidence });

    // ---- Lights ----
    // Area lights, grouped by material: (triangles, area, bounds).
    let mut area_lights: Vec<(usize, usize, f32, Bounds)> = Vec::new();
    for (mi, m) in scene.materials.iter().enumerate() {
        if !m.is_emissive() {
            continue;
        }
        let (mut count, mut area, mut bounds) = (0usize, 0.0f32, Bounds::empty());
        for mesh in scene.meshes.iter().filter(|x| x.material as usize == mi) {
            for t in &mesh.indices {
                let p = t.map(|i| mesh.positions[i as usize]);
                let a = triangle_area(p);
                if a > 0.0 {
                    count += 1;
                    area += a;
                    p.iter().for_each(|&v| bounds.add(v));
                }
            }
        }
        if count > 0 {
            area_lights.push((mi, count, area, bounds));
        }
    }
    let sphere_lights: Vec<(usize, &crate::Sphere)> = scene
        .spheres
        .iter()
        .enumerate()
        .filter(|(_, s)| {
            scene
                .materials
                .get(s.material as usize)
                .is_some_and(|m| m.is_emissive())
        })
        .collect();
    let mut points = 0usize;
    let mut spots = 0usize;
    let mut directionals = 0usize;
    for l in &scene.lights {
        match l {
            PunctualLight::Point { intensity, .. } if intensity.max_element() > 0.0 => points += 1,
            PunctualLight::Spot {
                intensity,
                outer_angle,
                ..
            } if intensity.max_element() > 0.0 && *outer_angle > 0.0 => spots += 1,
            PunctualLight::Directional { irradiance, .. } if irradiance.max_element() > 0.0 => {
                directionals += 1
            }
            _ => {}
        }
    }
    let environment = scene.environment.filter(|e| e.max_element() > 0.0);

    if !area_lights.is_empty() {
        let triangles: usize = area_lights.iter().map(|a| a.1).sum();
        let area: f32 = area_lights.iter().map(|a| a.2).sum();
        let mats: Vec<usize> = area_lights.iter().map(|a| a.0).collect();
        push(
            EffectKind::DirectArea,
            format!(
                "{} in {} (total area {area:.4} m^2)",
                plural(triangles, "emissive triangle", "emissive triangles"),
                material_list(scene, &mats, &classes, false)
            ),
        );
    }
    if !sphere_lights.is_empty() {
        let rmin = sphere_lights
            .iter()
            .map(|(_, s)| s.radius)
            .fold(f32::INFINITY, f32::min);
        let rmax = sphere_lights
            .iter()
            .map(|(_, s)| s.radius)
            .fold(0.0, f32::max);
        let radii = if rmin == rmax {
            format!("radius {rmin}")
        } else {
            format!("radii {rmin} to {rmax}")
        };
        push(
            EffectKind::DirectSphere,
            format!(
                "{} ({radii})",
                plural(sphere_lights.len(), "emissive sphere", "emissive spheres")
            ),
        );
    }
    if points > 0 {
        push(
            EffectKind::DirectPoint,
            plural(points, "point light", "point lights"),
        );
    }
    if spots > 0 {
        push(
            EffectKind::DirectSpot,
            plural(spots, "spot light", "spot lights"),
        );
    }
    if directionals > 0 {
        push(
            EffectKind::DirectDirectional,
            plural(directionals, "directional light", "directional lights"),
        );
    }
    if let Some(e) = environment {
        push(
            EffectKind::DirectEnvironment,
            format!(
                "uniform environment, radiance ({}, {}, {}) W/(m^2 sr)",
                e.x, e.y, e.z
            ),
        );
    }
    let visible_lights =
        !area_lights.is_empty() || !sphere_lights.is_empty() || environment.is_some();
    let delta_lights = points + spots + directionals;
    let any_light = visible_lights || delta_lights > 0;

    // ---- Surfaces ----
    let scattering: Vec<usize> = (0..nmat).filter(|&i| scatters(i)).collect();
    let with = |f: fn(&Classes) -> bool| -> Vec<usize> {
        scattering
            .iter()
            .copied()
            .filter(|&i| f(&classes[i]))
            .collect()
    };
    let diffuse = with(|c| c.diffuse);
    let glossy = with(|c| c.glossy);
    let specular = with(|c| c.specular);
    let refraction = with(|c| c.refraction);
    let smooth_specular = with(|c| c.specular || c.smooth_refraction);
    let tir = with(|c| c.tir);

    // Multi-bounce: is the scattering geometry more than one plane or one convex sphere?
    let camera_pos = scene.camera.world_from_camera.w_axis.truncate();
    let scattering_spheres: Vec<&crate::Sphere> = scene
        .spheres
        .iter()
        .filter(|s| scatters(s.material as usize))
        .collect();
    let mut scattering_triangles = 0usize;
    let mut plane: Option<(Vec3, f32)> = None;
    let mut coplanar = true;
    let eps = 1e-4 * scene_radius;
    for mesh in scene
        .meshes
        .iter()
        .filter(|m| scatters(m.material as usize))
    {
        for t in &mesh.indices {
            let p = t.map(|i| mesh.positions[i as usize]);
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
    let scattering_meshes = scene
        .meshes
        .iter()
        .filter(|m| !m.indices.is_empty() && scatters(m.material as usize))
        .count();
    let multi_bounce = match (scattering_spheres.len(), scattering_triangles) {
        (0, _) => !coplanar,
        (1, 0) => {
            // A sphere is convex: light scatters off it once unless the camera or a light
            // is inside it.
            let s = scattering_spheres[0];
            let inside = |p: Vec3| (p - s.center).length() < s.radius;
            inside(camera_pos)
                || scene.lights.iter().any(|l| match l {
                    PunctualLight::Point { position, .. }
                    | PunctualLight::Spot { position, .. } => inside(*position),
                    PunctualLight::Directional { .. } => false,
                })
                || sphere_lights.iter().any(|(_, l)| inside(l.center))
                || area_lights.iter().any(|a| inside(0.5 * (a.3.lo + a.3.hi)))
        }
        _ => true,
    };
    let surfaces = plural(
        scattering_meshes + scattering_spheres.len(),
        "scattering surface",
        "scattering surfaces",
    );

    // Area-weighted diffuse albedo and enclosure.
    let (mut albedo_sum, mut diffuse_area) = (0.0f32, 0.0f32);
    for &i in &diffuse {
        albedo_sum += classes[i].diffuse_albedo * area_by_material[i];
        diffuse_area += area_by_material[i];
    }
    let mean_albedo = if diffuse_area > 0.0 {
        albedo_sum / diffuse_area
    } else {
        0.0
    };
    let scattering_area: f32 = scattering.iter().map(|&i| area_by_material[i]).sum();
    let box_area = geometry.surface_area();
    let enclosure = if box_area > 0.0 {
        scattering_area / box_area
    } else {
        0.0
    };

    let indirect_diffuse = multi_bounce && !diffuse.is_empty();
    if indirect_diffuse {
        let closed = if enclosure >= CLOSED_FRACTION {
            "closed"
        } else {
            "open"
        };
        push(
            EffectKind::IndirectDiffuse,
            format!(
                "diffuse {} among {surfaces} that can exchange light; area-weighted diffuse \
                 albedo {mean_albedo:.2}; scattering surfaces cover {:.0}% of the bounding box \
                 ({closed})",
                material_list(scene, &diffuse, &classes, false),
                100.0 * enclosure
            ),
        );
    }
    if !glossy.is_empty() {
        push(
            EffectKind::GlossyReflection,
            format!(
                "{} {} glossily",
                material_list(scene, &glossy, &classes, true),
                verb("reflect", glossy.len())
            ),
        );
    }
    if !specular.is_empty() {
        push(
            EffectKind::SpecularReflection,
            format!(
                "{} {} specularly (roughness < {SPECULAR_ROUGHNESS})",
                material_list(scene, &specular, &classes, true),
                verb("reflect", specular.len())
            ),
        );
    }
    if !refraction.is_empty() {
        push(
            EffectKind::Refraction,
            format!(
                "{} {}",
                material_list(scene, &refraction, &classes, true),
                verb("transmit", refraction.len())
            ),
        );
    }
    if !tir.is_empty() {
        push(
            EffectKind::TotalInternalReflection,
            format!(
                "{} can trap light by total internal reflection (ior != 1)",
                material_list(scene, &tir, &classes, false)
            ),
        );
    }
    let caustics = any_light && multi_bounce && !smooth_specular.is_empty() && !diffuse.is_empty();
    if caustics {
        push(
            EffectKind::Caustics,
            format!(
                "light can reach diffuse {} through specular {}",
                material_list(scene, &diffuse, &classes, false),
                material_list(scene, &smooth_specular, &classes, false)
            ),
        );
    }
    // Delta or tiny lights for caustics.
    let mut delta_evidence: Vec<String> = Vec::new();
    if caustics {
        if points > 0 {
            delta_evidence.push(plural(points, "point light", "point lights"));
        }
        if spots > 0 {
            delta_evidence.push(plural(spots, "spot light", "spot lights"));
        }
        if directionals > 0 {
            delta_evidence.push(plural(
                directionals,
                "directional light",
                "directional lights",
            ));
        }
        let tiny = TINY_LIGHT_FRACTION * scene_radius;
        for (i, s) in &sphere_lights {
            if s.radius < tiny {
                delta_evidence.push(format!(
                    "sphere light {i} of radius {} ({:.2}% of the scene radius {:.2})",
                    s.radius,
                    100.0 * s.radius / scene_radius,
                    scene_radius
                ));
            }
        }
        for (mi, _, _, b) in &area_lights {
            let r = b.radius();
            if r < tiny {
                delta_evidence.push(format!(
                    "area light of {} of radius {r} ({:.2}% of the scene radius {:.2})",
                    material_list(scene, &[*mi], &classes, false),
                    100.0 * r / scene_radius,
                    scene_radius
                ));
            }
        }
    }
    let delta_lit = !delta_evidence.is_empty();
    if delta_lit {
        push(
            EffectKind::DeltaLitCaustics,
            format!(
                "the caustics are lit by {}: next-event estimation cannot connect through a \
                 specular chain to them",
                delta_evidence.join(", ")
            ),
        );
    }
    let cam = &scene.camera;
    let lens_sampling = cam.aperture_radius > 0.0;
    if lens_sampling {
        push(
            EffectKind::DepthOfField,
            format!(
                "camera aperture radius {}, focused at {}",
                cam.aperture_radius, cam.focus_distance
            ),
        );
    }
    let textured: Vec<usize> = (0..nmat)
        .filter(|&i| {
            used[i]
                && matches!(
                    scene.materials[i].kind,
                    MaterialKind::MetallicRoughness {
                        base_color_texture: Some(_),
                        ..
                    }
                )
        })
        .collect();
    if !textured.is_empty() {
        push(
            EffectKind::Textures,
            format!(
                "{} {} a base-colour texture",
                material_list(scene, &textured, &classes, false),
                verb("use", textured.len())
            ),
        );
    }

    // ---- Integrator and its configuration ----
    let more_than_direct =
        indirect_diffuse || !glossy.is_empty() || !specular.is_empty() || !refraction.is_empty();
    let integrator = if !any_light {
        reasons.push("no light: the image is black".into());
        PlannedIntegrator::Black
    } else if !visible_lights && scattering.is_empty() {
        reasons.push(
            "no light reaches the camera: point, spot and directional lights are invisible and \
             no surface scatters their light; the image is black"
                .into(),
        );
        PlannedIntegrator::Black
    } else if !more_than_direct {
        reasons.push(format!(
            "direct lighting only: {} ({}) and nothing glossy, specular or transmissive, so no \
             light reaches the camera after a second bounce",
            surfaces,
            if scattering_triangles + scattering_spheres.len() == 0 {
                "nothing to bounce off"
            } else {
                "no two of them exchange light"
            }
        ));
        PlannedIntegrator::Direct
    } else if delta_lit {
        reasons.push(
            "bdpt: caustics lit by delta or tiny lights, which a path tracer with next-event \
             estimation samples with zero or vanishing probability"
                .into(),
        );
        reasons.push(
            "bdpt light-traces onto the film: one whole-frame tile, units split by passes".into(),
        );
        PlannedIntegrator::Bdpt
    } else {
        let mut why: Vec<&str> = Vec::new();
        if indirect_diffuse {
            why.push("indirect diffuse");
        }
        if !glossy.is_empty() {
            why.push("glossy reflection");
        }
        if !specular.is_empty() {
            why.push("specular reflection");
        }
        if !refraction.is_empty() {
            why.push("refraction");
        }
        reasons.push(format!(
            "path tracing with next-event estimation and MIS: more than one bounce for {}",
            why.join(", ")
        ));
        if caustics {
            reasons.push(
                "the caustics are lit only by finite lights: path tracing finds them by BSDF \
                 sampling, no bidirectional technique needed"
                    .into(),
            );
        }
        PlannedIntegrator::Path
    };

    let (max_depth, rr_depth) = match integrator {
        PlannedIntegrator::Black => (0, 0),
        PlannedIntegrator::Direct => {
            reasons.push("max depth 1: one scattering event".into());
            (1, DEFAULT_RR_DEPTH)
        }
        PlannedIntegrator::Path | PlannedIntegrator::Bdpt => {
            let closed_bright =
                indirect_diffuse && mean_albedo > BRIGHT_ALBEDO && enclosure >= CLOSED_FRACTION;
            let mut depth = if closed_bright {
                reasons.push(format!(
                    "max depth {CLOSED_ROOM_DEPTH}: a closed bright room (diffuse albedo \
                     {mean_albedo:.2} > {BRIGHT_ALBEDO}, surfaces cover {:.0}% >= {:.0}% of the \
                     bounding box) keeps light bouncing",
                    100.0 * enclosure,
                    100.0 * CLOSED_FRACTION
                ));
                CLOSED_ROOM_DEPTH
            } else {
                reasons.push(format!(
                    "max depth {DEFAULT_DEPTH}: not a closed bright room (diffuse albedo \
                     {mean_albedo:.2}, surfaces cover {:.0}% of the bounding box)",
                    100.0 * enclosure
                ));
                DEFAULT_DEPTH
            };
            let mut rr = DEFAULT_RR_DEPTH;
            if !refraction.is_empty() {
                if depth < REFRACTION_DEPTH {
                    reasons.push(format!(
                        "max depth raised to {REFRACTION_DEPTH}: light needs several \
                         interfaces to pass through glass"
                    ));
                    depth = REFRACTION_DEPTH;
                }
                rr = REFRACTION_RR_DEPTH;
                reasons.push(format!(
                    "Russian roulette from depth {rr}: paths through glass need their first \
                     bounces"
                ));
            } else {
                reasons.push(format!("Russian roulette from depth {rr}"));
            }
            (depth, rr)
        }
    };

    if integrator != PlannedIntegrator::Black {
        reasons.push(if lens_sampling {
            format!(
                "thin-lens camera (aperture radius {}): lens sampling on",
                cam.aperture_radius
            )
        } else {
            "pinhole camera: no lens sampling".into()
        });
        if refraction.is_empty() {
            reasons.push("nothing transmits: no refraction paths".into());
        }
        if !caustics {
            reasons.push(if smooth_specular.is_empty() {
                "no specular surfaces: no caustic technique".into()
            } else {
                "no caustics (no diffuse receiver, or nothing for light to bounce between): no \
                 caustic technique"
                    .into()
            });
        }
    }
    reasons.push("motion: static scene (the scene description has no animation)".into());
    if integrator == PlannedIntegrator::Black {
        // An empty plan: no light is transported, so no transport effect, lens or texture
        // shows. Only the (invisible, unlit-upon) lights found stay as evidence.
        effects.retain(|e| e.kind <= EffectKind::DirectEnvironment);
    }

    let present: Vec<EffectKind> = effects.iter().map(|e| e.kind).collect();
    let absent = EffectKind::ALL
        .into_iter()
        .filter(|k| !present.contains(k))
        .collect();
    RenderPlan {
        effects,
        absent,
        integrator,
        max_depth,
        rr_depth,
        lens_sampling,
        reasons,
        overridden: None,
    }
}
