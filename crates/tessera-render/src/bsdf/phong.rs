//! Veach's energy-conserving modified Phong (Lafortune & Willems 1994; used by Veach &
//! Guibas 1995 for the glossy plates of figure 2):
//!
//! `f(wo, wi) = kd / π + ks (n + 2) / (2π) cos^n α`, where α is the angle between `wi` and
//! the mirror direction of `wo`.
//!
//! | parameter | meaning |
//! |---|---|
//! | `kd` | diffuse reflectance |
//! | `ks` | specular reflectance; `kd + ks <= 1` conserves energy |
//! | `exponent` | Phong exponent n: larger is smoother |
//!
//! Sampling picks the diffuse part with probability `lum(kd) / (lum(kd) + lum(ks))` and
//! otherwise the Phong lobe `(n + 1)/(2π) cos^n α` around the mirror direction (Arvo 2001,
//! chapter 4, the Princeton COS 526 path tracing slides); samples below the horizon are invalid (the missing mass is exactly the
//! energy the model loses there).

use crate::math::luminance;
use crate::sampling::warp::{
    cosine_hemisphere_pdf, phong_lobe_pdf, square_to_cosine_hemisphere, square_to_phong_lobe, Frame,
};
use glam::{Vec2, Vec3};
use std::f32::consts::FRAC_1_PI;

/// Modified Phong lobe.
#[derive(Clone, Copy, Debug)]
pub struct Phong {
    /// Diffuse reflectance.
    pub kd: Vec3,
    /// Specular reflectance.
    pub ks: Vec3,
    /// Phong exponent.
    pub exponent: f32,
}

impl Phong {
    fn p_diffuse(&self) -> f32 {
        let d = luminance(self.kd);
        let s = luminance(self.ks);
        if d + s <= 0.0 {
            1.0
        } else {
            d / (d + s)
        }
    }

    fn mirror(wo: Vec3) -> Vec3 {
        Vec3::new(-wo.x, -wo.y, wo.z)
    }

    pub(crate) fn eval(&self, wo: Vec3, wi: Vec3) -> Vec3 {
        if wo.z <= 0.0 || wi.z <= 0.0 {
            return Vec3::ZERO;
        }
        let cos_alpha = Self::mirror(wo).dot(wi);
        let spec = if cos_alpha > 0.0 {
            (self.exponent + 2.0) * 0.5 * FRAC_1_PI * cos_alpha.powf(self.exponent)
        } else {
            0.0
        };
        (self.kd * FRAC_1_PI + self.ks * spec) * wi.z
    }

    pub(crate) fn pdf(&self, wo: Vec3, wi: Vec3) -> f32 {
        if wo.z <= 0.0 || wi.z <= 0.0 {
            return 0.0;
        }
        let pd = self.p_diffuse();
        let cos_alpha = Self::mirror(wo).dot(wi);
        let spec = if cos_alpha > 0.0 {
            phong_lobe_pdf(cos_alpha, self.exponent)
        } else {
            0.0
        };
        pd * cosine_hemisphere_pdf(wi.z) + (1.0 - pd) * spec
    }

    pub(crate) fn sample(&self, wo: Vec3, u1: f32, u2: Vec2) -> Option<(Vec3, Vec3, f32)> {
        if wo.z <= 0.0 {
            return None;
        }
        let wi = if u1 < self.p_diffuse() {
            square_to_cosine_hemisphere(u2)
        } else {
            let frame = Frame::from_normal(Self::mirror(wo));
            frame.to_world(square_to_phong_lobe(u2, self.exponent))
        };
        if wi.z <= 0.0 {
            return None;
        }
        let pdf = self.pdf(wo, wi);
        if pdf <= 0.0 {
            return None;
        }
        Some((wi, self.eval(wo, wi) / pdf, pdf))
    }
}
