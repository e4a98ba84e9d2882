//! Delta lobes: the ideal mirror and the smooth dielectric interface (glass).
//!
//! | lobe | parameters |
//! |---|---|
//! | [`Mirror`] | `reflectance` per channel |
//! | [`Glass`] | `eta` = n_inside / n_outside, `tint` of transmitted light |
//!
//! Glass reflects with the exact unpolarised Fresnel reflectance `F` and refracts (Snell's
//! law) otherwise, choosing between the two with probability `F`; under total internal
//! reflection `F = 1`. Radiance crossing an interface is scaled by `(η_i/η_t)²` (radiance
//! divided by η² is invariant; the camera path carries radiance), pbrt 3rd ed. §8.2.

use super::fresnel_dielectric;
use glam::Vec3;

/// Ideal mirror.
#[derive(Clone, Copy, Debug)]
pub struct Mirror {
    /// Reflectance.
    pub reflectance: Vec3,
}

impl Mirror {
    pub(crate) fn sample(&self, wo: Vec3) -> Option<(Vec3, Vec3, f32)> {
        if wo.z <= 0.0 {
            return None;
        }
        Some((Vec3::new(-wo.x, -wo.y, wo.z), self.reflectance, 1.0))
    }
}

/// Smooth dielectric.
#[derive(Clone, Copy, Debug)]
pub struct Glass {
    /// Relative index of refraction (inside over outside).
    pub eta: f32,
    /// Transmission tint.
    pub tint: Vec3,
}

impl Glass {
    pub(crate) fn sample(&self, wo: Vec3, u: f32) -> Option<(Vec3, Vec3, f32)> {
        let cos_o = wo.z;
        if cos_o == 0.0 {
            return None;
        }
        let f = fresnel_dielectric(cos_o, self.eta);
        if u < f {
            return Some((Vec3::new(-wo.x, -wo.y, wo.z), Vec3::ONE, f));
        }
        // Relative index across the interface as seen from wo's side.
        let eta = if cos_o > 0.0 {
            self.eta
        } else {
            1.0 / self.eta
        };
        let sin2_t = (1.0 - cos_o * cos_o).max(0.0) / (eta * eta);
        if sin2_t >= 1.0 {
            return None; // unreachable: F = 1 under total internal reflection
        }
        let cos_t = (1.0 - sin2_t).sqrt();
        let wi = Vec3::new(-wo.x / eta, -wo.y / eta, -cos_t * cos_o.signum());
        Some((wi, self.tint / (eta * eta), 1.0 - f))
    }
}
