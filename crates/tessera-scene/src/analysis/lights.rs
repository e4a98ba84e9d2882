//! Step 3: the lights (the module documentation's "Lights" rule). A light counts only if
//! it has positive power; each kind found becomes a `Direct*` effect.

use super::evidence::{material_list, plural};
use super::survey::{triangle_area, Bounds, Survey};
use super::{push, Effect, EffectKind};
use crate::{PunctualLight, Scene, Sphere};
use glam::Vec3;

/// The emissive triangles of one material.
pub(super) struct AreaLight {
    /// Index of the emissive material.
    pub(super) material: usize,
    /// Number of its triangles with area > 0.
    pub(super) triangles: usize,
    /// Their total area.
    pub(super) area: f32,
    /// Their bounds.
    pub(super) bounds: Bounds,
}

/// The lights with positive power.
pub(super) struct Lights<'a> {
    /// Area lights, grouped by material.
    pub(super) area: Vec<AreaLight>,
    /// Spheres with an emissive material, with their index.
    pub(super) spheres: Vec<(usize, &'a Sphere)>,
    /// Point lights with positive intensity.
    pub(super) points: usize,
    /// Spot lights with positive intensity and an outer cone angle > 0.
    pub(super) spots: usize,
    /// Directional lights with positive irradiance.
    pub(super) directionals: usize,
    /// The environment radiance, if positive.
    pub(super) environment: Option<Vec3>,
    /// The environment image's name and size, if the environment is an image.
    pub(super) environment_image: Option<(String, u32, u32)>,
}

impl Lights<'_> {
    /// Whether a light the camera can see exists (area, sphere or environment).
    pub(super) fn visible(&self) -> bool {
        !self.area.is_empty() || !self.spheres.is_empty() || self.environment.is_some()
    }

    /// Number of point, spot and directional lights.
    pub(super) fn delta(&self) -> usize {
        self.points + self.spots + self.directionals
    }

    /// Whether there is any light.
    pub(super) fn any(&self) -> bool {
        self.visible() || self.delta() > 0
    }
}

/// Finds the lights of `scene`.
pub(super) fn find(scene: &Scene) -> Lights<'_> {
    let spheres: Vec<(usize, &Sphere)> = scene
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
    Lights {
        area: area_lights(scene),
        spheres,
        points,
        spots,
        directionals,
        environment: scene.environment.filter(|e| e.max_element() > 0.0),
        environment_image: scene
            .environment_map
            .as_ref()
            .map(|m| (m.name.clone(), m.width, m.height)),
    }
}

/// Emissive triangles with area > 0, grouped by material.
fn area_lights(scene: &Scene) -> Vec<AreaLight> {
    let mut area_lights = Vec::new();
    for (mi, m) in scene.materials.iter().enumerate() {
        if !m.is_emissive() {
            continue;
        }
        let (mut count, mut area, mut bounds) = (0usize, 0.0f32, Bounds::empty());
        for placed in scene
            .placed_meshes()
            .filter(|x| x.material() as usize == mi)
        {
            for p in placed.triangles() {
                let a = triangle_area(p);
                if a > 0.0 {
                    count += 1;
                    area += a;
                    p.iter().for_each(|&v| bounds.add(v));
                }
            }
        }
        if count > 0 {
            area_lights.push(AreaLight {
                material: mi,
                triangles: count,
                area,
                bounds,
            });
        }
    }
    area_lights
}

/// Records one `Direct*` effect per kind of light found, with its evidence.
pub(super) fn report(lights: &Lights, survey: &Survey, effects: &mut Vec<Effect>) {
    let Survey { scene, classes, .. } = survey;
    if !lights.area.is_empty() {
        let triangles: usize = lights.area.iter().map(|a| a.triangles).sum();
        let area: f32 = lights.area.iter().map(|a| a.area).sum();
        let mats: Vec<usize> = lights.area.iter().map(|a| a.material).collect();
        push(
            effects,
            EffectKind::DirectArea,
            format!(
                "{} in {} (total area {area:.4} m^2)",
                plural(triangles, "emissive triangle", "emissive triangles"),
                material_list(scene, &mats, classes, false)
            ),
        );
    }
    if !lights.spheres.is_empty() {
        let rmin = lights
            .spheres
            .iter()
            .map(|(_, s)| s.radius)
            .fold(f32::INFINITY, f32::min);
        let rmax = lights
            .spheres
            .iter()
            .map(|(_, s)| s.radius)
            .fold(0.0, f32::max);
        let radii = if rmin == rmax {
            format!("radius {rmin}")
        } else {
            format!("radii {rmin} to {rmax}")
        };
        push(
            effects,
            EffectKind::DirectSphere,
            format!(
                "{} ({radii})",
                plural(lights.spheres.len(), "emissive sphere", "emissive spheres")
            ),
        );
    }
    if lights.points > 0 {
        push(
            effects,
            EffectKind::DirectPoint,
            plural(lights.points, "point light", "point lights"),
        );
    }
    if lights.spots > 0 {
        push(
            effects,
            EffectKind::DirectSpot,
            plural(lights.spots, "spot light", "spot lights"),
        );
    }
    if lights.directionals > 0 {
        push(
            effects,
            EffectKind::DirectDirectional,
            plural(
                lights.directionals,
                "directional light",
                "directional lights",
            ),
        );
    }
    if let Some(e) = lights.environment {
        let what = match &lights.environment_image {
            Some((name, w, h)) => format!(
                "image environment {name} ({w}x{h}), strength ({}, {}, {})",
                e.x, e.y, e.z
            ),
            None => format!(
                "uniform environment, radiance ({}, {}, {}) W/(m^2 sr)",
                e.x, e.y, e.z
            ),
        };
        push(effects, EffectKind::DirectEnvironment, what);
    }
}
