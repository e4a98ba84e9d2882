//! Lambertian diffuse reflection: `f = albedo / π`.
//!
//! | parameter | meaning |
//! |---|---|
//! | `albedo` | hemispherical reflectance per channel, in [0, 1] |
//!
//! Sampled with the cosine-weighted hemisphere (Malley's method via the concentric disk,
//! Arvo 2001, chapter 4 and the Princeton COS 526 path tracing slides), so `weight = albedo` exactly.

use crate::sampling::warp::{cosine_hemisphere_pdf, square_to_cosine_hemisphere};
use glam::{Vec2, Vec3};
use std::f32::consts::FRAC_1_PI;

/// Lambertian lobe.
#[derive(Clone, Copy, Debug)]
pub struct Diffuse {
    /// Reflectance.
    pub albedo: Vec3,
}

impl Diffuse {
    pub(crate) fn eval(&self, wo: Vec3, wi: Vec3) -> Vec3 {
        if wo.z <= 0.0 || wi.z <= 0.0 {
            return Vec3::ZERO;
        }
        self.albedo * (FRAC_1_PI * wi.z)
    }

    pub(crate) fn pdf(&self, wo: Vec3, wi: Vec3) -> f32 {
        if wo.z <= 0.0 || wi.z <= 0.0 {
            return 0.0;
        }
        cosine_hemisphere_pdf(wi.z)
    }

    pub(crate) fn sample(&self, wo: Vec3, u: Vec2) -> Option<(Vec3, Vec3, f32)> {
        if wo.z <= 0.0 {
            return None;
        }
        let wi = square_to_cosine_hemisphere(u);
        if wi.z <= 0.0 {
            return None;
        }
        Some((wi, self.albedo, cosine_hemisphere_pdf(wi.z)))
    }
}
