//! Point, spot and directional lights (KHR_lights_punctual, converted to radiometric units
//! by `tessera-scene`). Delta distributions: only light sampling can find them.
//!
//! | light | parameters | incident light at distance d |
//! |---|---|---|
//! | point | `intensity` I (W/sr) | `I / d²` |
//! | spot | I, axis, inner/outer cone angles | `I s(θ) / d²` with the glTF falloff `s = t²`, `t = clamp((cos θ - cos θo)/(cos θi - cos θo))` |
//! | directional | irradiance E (W/m²), travel direction | `E` |

use super::LightSample;
use glam::Vec3;
use std::f32::consts::PI;

/// A delta light.
#[derive(Clone, Copy, Debug)]
pub enum Punctual {
    /// Isotropic point light.
    Point {
        /// Position.
        position: Vec3,
        /// Radiant intensity, W/sr.
        intensity: Vec3,
    },
    /// Spot light.
    Spot {
        /// Position.
        position: Vec3,
        /// Unit axis direction.
        axis: Vec3,
        /// On-axis intensity, W/sr.
        intensity: Vec3,
        /// Cosine of the inner cone angle.
        cos_inner: f32,
        /// Cosine of the outer cone angle.
        cos_outer: f32,
    },
    /// Distant light.
    Directional {
        /// Unit direction the light travels in.
        direction: Vec3,
        /// Irradiance on a surface facing the light.
        irradiance: Vec3,
        /// Radius of the scene's bounding sphere (for the power estimate).
        scene_radius: f32,
    },
}

/// The glTF spot falloff between the outer and inner cone (KHR_lights_punctual reference
/// implementation: a squared linear ramp in cos θ).
#[inline]
pub fn spot_falloff(cos_theta: f32, cos_inner: f32, cos_outer: f32) -> f32 {
    if cos_inner <= cos_outer {
        return if cos_theta >= cos_outer { 1.0 } else { 0.0 };
    }
    let t = ((cos_theta - cos_outer) / (cos_inner - cos_outer)).clamp(0.0, 1.0);
    t * t
}

/// Light from an isotropic point of intensity `intensity` at `position`: `I / d²`.
#[inline]
fn point_sample(p_ref: Vec3, position: Vec3, intensity: Vec3) -> Option<LightSample> {
    let d = position - p_ref;
    let d2 = d.length_squared();
    if d2 <= 0.0 {
        return None;
    }
    let dist = d2.sqrt();
    Some(LightSample {
        wi: d / dist,
        dist,
        p: position,
        p_error: Vec3::ZERO,
        n: Vec3::ZERO,
        li: intensity / d2,
        pdf: 1.0,
        delta: true,
    })
}

impl Punctual {
    pub(crate) fn power(&self) -> Vec3 {
        match *self {
            Punctual::Point { intensity, .. } => 4.0 * PI * intensity,
            // Integral of the falloff over the sphere, approximated by the cone between the
            // inner and outer angles (used only to choose lights, never for radiance).
            Punctual::Spot {
                intensity,
                cos_inner,
                cos_outer,
                ..
            } => 2.0 * PI * intensity * (1.0 - 0.5 * (cos_inner + cos_outer)),
            Punctual::Directional {
                irradiance,
                scene_radius,
                ..
            } => PI * scene_radius * scene_radius * irradiance,
        }
    }

    /// The position of a point or spot light and its radiant intensity (W/sr) in the unit
    /// direction `w` leaving it; `None` for a directional light, which has no position.
    /// Manifold next-event estimation needs the intensity along the direction the light
    /// leaves by through a refracting chain, which is not the straight line to the
    /// shading point that [`Punctual::sample_li`] assumes.
    pub fn intensity_toward(&self, w: Vec3) -> Option<(Vec3, Vec3)> {
        match *self {
            Punctual::Point {
                position,
                intensity,
            } => Some((position, intensity)),
            Punctual::Spot {
                position,
                axis,
                intensity,
                cos_inner,
                cos_outer,
            } => Some((
                position,
                intensity * spot_falloff(w.dot(axis), cos_inner, cos_outer),
            )),
            Punctual::Directional { .. } => None,
        }
    }

    pub(crate) fn sample_li(&self, p_ref: Vec3) -> Option<LightSample> {
        match *self {
            Punctual::Point {
                position,
                intensity,
            } => point_sample(p_ref, position, intensity),
            Punctual::Spot {
                position,
                axis,
                intensity,
                cos_inner,
                cos_outer,
            } => {
                // A point light whose intensity falls off with the angle from the axis.
                let mut ls = point_sample(p_ref, position, intensity)?;
                let s = spot_falloff((-ls.wi).dot(axis), cos_inner, cos_outer);
                if s <= 0.0 {
                    return None;
                }
                ls.li *= s;
                Some(ls)
            }
            Punctual::Directional {
                direction,
                irradiance,
                ..
            } => Some(LightSample {
                wi: -direction,
                dist: f32::INFINITY,
                p: Vec3::ZERO,
                p_error: Vec3::ZERO,
                n: Vec3::ZERO,
                li: irradiance,
                pdf: 1.0,
                delta: true,
            }),
        }
    }
}
