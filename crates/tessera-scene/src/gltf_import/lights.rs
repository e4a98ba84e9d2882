//! Step 6, lights (`KHR_lights_punctual`): point, spot and directional lights at their
//! nodes, converted from photometric to radiometric units.

use super::{Importer, Res};
use crate::PunctualLight;
use glam::{DMat4, DVec3, Vec3};
use gltf::json;
use json::extensions::scene::khr_lights_punctual as khr_lights;
use json::validation::Checked;

/// Luminous efficacy used to convert `KHR_lights_punctual` photometric units to radiometric
/// ones: 683 lm/W, the efficacy of monochromatic light at 540 THz (~555 nm) that defines the
/// candela in the SI.
pub const LUMINOUS_EFFICACY: f32 = 683.0;

/// Converts a `KHR_lights_punctual` light colour and photometric intensity to radiometric
/// units, per linear-RGB channel: `color * intensity / 683`.
///
/// For point and spot lights the glTF intensity is luminous intensity in candela (lm/sr)
/// and the result is radiant intensity in W/sr; for directional lights it is illuminance in
/// lux (lm/m²) and the result is irradiance in W/m² on a surface facing the light. 683 lm/W
/// ([`LUMINOUS_EFFICACY`]) is the luminous efficacy of 555 nm light, the definition of the
/// candela; applying it to every channel is the usual glTF convention.
pub fn photometric_to_radiometric(color: [f32; 3], intensity: f32) -> Vec3 {
    Vec3::from(color) * (intensity / LUMINOUS_EFFICACY)
}

impl Importer<'_> {
    /// Converts the `KHR_lights_punctual` light `li` instanced at node `ni`.
    pub(super) fn convert_light(&self, ni: usize, li: usize, world: &DMat4) -> Res<PunctualLight> {
        let all = self
            .root
            .extensions
            .as_ref()
            .and_then(|e| e.khr_lights_punctual.as_ref())
            .map_or(&[][..], |l| &l.lights[..]);
        let Some(light) = all.get(li) else {
            return self.err(format!(
                "node {ni} refers to light {li}, but there are only {}",
                all.len()
            ));
        };
        let power = photometric_to_radiometric(light.color, light.intensity);
        let position = world.transform_point3(DVec3::ZERO).as_vec3();
        // The light shines along the node's local -Z.
        let direction = world
            .transform_vector3(DVec3::NEG_Z)
            .normalize_or_zero()
            .as_vec3();
        let kind = match light.type_ {
            Checked::Valid(t) => t,
            Checked::Invalid => return self.err(format!("light {li} has an invalid type")),
        };
        if kind != khr_lights::Type::Point && direction == Vec3::ZERO {
            return self.err(format!(
                "node {ni}: light {li} has no direction (its transform collapses -Z)"
            ));
        }
        Ok(match kind {
            khr_lights::Type::Point => PunctualLight::Point {
                position,
                intensity: power,
            },
            khr_lights::Type::Directional => PunctualLight::Directional {
                direction,
                irradiance: power,
            },
            khr_lights::Type::Spot => {
                // KHR_lights_punctual defaults: innerConeAngle 0, outerConeAngle pi/4.
                let (inner, outer) = light
                    .spot
                    .as_ref()
                    .map_or((0.0, std::f32::consts::FRAC_PI_4), |s| {
                        (s.inner_cone_angle, s.outer_cone_angle)
                    });
                PunctualLight::Spot {
                    position,
                    direction,
                    intensity: power,
                    inner_angle: inner,
                    outer_angle: outer,
                }
            }
        })
    }
}
