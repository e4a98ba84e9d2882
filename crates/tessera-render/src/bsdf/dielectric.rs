//! Rough dielectric interface: GGX microfacet reflection and refraction (Walter et al.
//! 2007, sections 4-5), the rough counterpart of [`super::specular::Glass`].
//!
//! | parameter | meaning |
//! |---|---|
//! | `eta` | relative index of refraction, n_inside / n_outside (inside is `-z`) |
//! | `alpha` | GGX alpha (roughness²), at least [`super::microfacet::MIN_ALPHA`] |
//! | `tint` | factor on transmitted light (the glTF base colour) |
//!
//! Seen from `wo`'s side, `η = eta` when `wo.z > 0` and `1/eta` otherwise (the frame is then
//! mirrored, so the formulas below always have `cos θo > 0`). With `F` the exact dielectric
//! Fresnel reflectance of the microfacet `h` and the height-correlated `G2`:
//!
//! - reflection, `h = normalize(wo + wi)`: `f = F D G2 / (4 cos θo cos θi)`;
//! - refraction, `h = ±normalize(wo + η wi)` facing `wo` (Walter et al. 2007, eq. 16 and
//!   21): `f = tint (1 - F) D G2 |wi·h| |wo·h| / (|cos θo| |cos θi| (wo·h + η wi·h)²)`.
//!
//! The refraction term is the *radiance* BTDF (Walter's with the ray's own index on `wo`'s
//! side): it carries the `1/η²` that [`super::specular::Glass`] applies to radiance
//! crossing an interface, and satisfies the generalised reciprocity
//! `f(wo, wi) = f(wi, wo) / η²`, so the adjoint `f(wi, wo)` that BDPT's light subpaths
//! evaluate is the importance BTDF without any extra factor (pbrt 4th ed. section 9.5.2).
//!
//! Sampling: a visible normal `h` (Heitz 2018), then reflection with probability `F(wo·h)`
//! (total internal reflection gives `F = 1`) and refraction otherwise. The densities are
//! `F D_wo(h) / (4 wo·h)` and `(1 - F) D_wo(h) |wi·h| / (wi·h + wo·h/η)²` (the Jacobian of
//! the refraction `h -> wi`, Walter et al. 2007, eq. 17).

use super::flip_z;
use super::fresnel_dielectric;
use crate::sampling::warp::{ggx_d, ggx_g1, ggx_lambda, ggx_vndf_pdf, sample_ggx_vndf};
use glam::{Vec2, Vec3};

/// Rough dielectric interface.
#[derive(Clone, Copy, Debug)]
pub struct RoughDielectric {
    /// Relative index of refraction (inside over outside).
    pub eta: f32,
    /// GGX alpha (roughness²), at least [`super::microfacet::MIN_ALPHA`].
    pub alpha: f32,
    /// Transmission tint.
    pub tint: Vec3,
}

/// Refracts `wo` (with `wo·h > 0`) through the microfacet `h` into the medium of relative
/// index `eta`; `None` under total internal reflection.
#[inline]
fn refract(wo: Vec3, h: Vec3, eta: f32) -> Option<Vec3> {
    let cos_i = wo.dot(h);
    let sin2_t = (1.0 - cos_i * cos_i).max(0.0) / (eta * eta);
    if sin2_t >= 1.0 {
        return None;
    }
    let cos_t = (1.0 - sin2_t).sqrt();
    Some((-wo / eta + (cos_i / eta - cos_t) * h).normalize())
}

impl RoughDielectric {
    /// Mirrors the frame so that `wo.z > 0`; returns the flip and `η` seen from `wo`.
    #[inline]
    fn side(&self, wo: Vec3) -> (bool, f32) {
        if wo.z > 0.0 {
            (false, self.eta)
        } else {
            (true, 1.0 / self.eta)
        }
    }

    #[inline]
    fn g2(&self, wo: Vec3, wi: Vec3) -> f32 {
        1.0 / (1.0 + ggx_lambda(wo, self.alpha) + ggx_lambda(wi, self.alpha))
    }

    /// The generalised half vector of a refraction (`wo.z > 0 > wi.z`), facing `wo`, or
    /// `None` for directions no microfacet refracts into each other.
    #[inline]
    fn refraction_half(wo: Vec3, wi: Vec3, eta: f32) -> Option<Vec3> {
        let h = wo + eta * wi;
        let len2 = h.length_squared();
        if len2 <= 1e-12 {
            return None;
        }
        let h = h / len2.sqrt();
        let h = if h.z < 0.0 { -h } else { h };
        // The microfacet must face wo and have wi behind it.
        if wo.dot(h) <= 0.0 || wi.dot(h) >= 0.0 {
            return None;
        }
        Some(h)
    }

    /// `f(wo, wi) |cos θi|`.
    pub(crate) fn eval(&self, wo: Vec3, wi: Vec3) -> Vec3 {
        if wo.z == 0.0 || wi.z == 0.0 {
            return Vec3::ZERO;
        }
        let (flip, eta) = self.side(wo);
        let (wo, wi) = (flip_z(wo, flip), flip_z(wi, flip));
        if wi.z > 0.0 {
            let h = wo + wi;
            if h.length_squared() <= 1e-12 {
                return Vec3::ZERO;
            }
            let h = h.normalize();
            let f = fresnel_dielectric(wo.dot(h), eta);
            return Vec3::splat(f * ggx_d(h, self.alpha) * self.g2(wo, wi) / (4.0 * wo.z));
        }
        let Some(h) = Self::refraction_half(wo, wi, eta) else {
            return Vec3::ZERO;
        };
        let (oh, ih) = (wo.dot(h), wi.dot(h));
        let t = 1.0 - fresnel_dielectric(oh, eta);
        let denom = oh + eta * ih;
        self.tint
            * (t * ggx_d(h, self.alpha) * self.g2(wo, wi) * (ih.abs() * oh)
                / (wo.z * denom * denom))
    }

    /// Solid-angle density of [`RoughDielectric::sample`].
    pub(crate) fn pdf(&self, wo: Vec3, wi: Vec3) -> f32 {
        if wo.z == 0.0 || wi.z == 0.0 {
            return 0.0;
        }
        let (flip, eta) = self.side(wo);
        let (wo, wi) = (flip_z(wo, flip), flip_z(wi, flip));
        if wi.z > 0.0 {
            let h = wo + wi;
            if h.length_squared() <= 1e-12 {
                return 0.0;
            }
            let h = h.normalize();
            let oh = wo.dot(h);
            if oh <= 0.0 {
                return 0.0;
            }
            let f = fresnel_dielectric(oh, eta);
            return f * ggx_vndf_pdf(wo, h, self.alpha) / (4.0 * oh);
        }
        let Some(h) = Self::refraction_half(wo, wi, eta) else {
            return 0.0;
        };
        let (oh, ih) = (wo.dot(h), wi.dot(h));
        let t = 1.0 - fresnel_dielectric(oh, eta);
        let denom = ih + oh / eta;
        t * ggx_vndf_pdf(wo, h, self.alpha) * ih.abs() / (denom * denom)
    }

    /// Samples `wi`; returns (wi, weight f|cos θi|/pdf, pdf).
    pub(crate) fn sample(&self, wo: Vec3, u1: f32, u2: Vec2) -> Option<(Vec3, Vec3, f32)> {
        if wo.z == 0.0 {
            return None;
        }
        let (flip, eta) = self.side(wo);
        let wo_up = flip_z(wo, flip);
        let h = sample_ggx_vndf(wo_up, self.alpha, u2);
        let oh = wo_up.dot(h);
        if oh <= 0.0 {
            return None;
        }
        let f = fresnel_dielectric(oh, eta);
        // Both weights are D G2 (...) / (D_wo (...)) = G2 / G1(wo), times the tint and the
        // radiance scaling 1/η² for refraction (the Fresnel factor cancels its probability).
        let g1 = ggx_g1(wo_up, self.alpha);
        let wi = if u1 < f {
            let wi = crate::math::reflect(wo_up, h);
            if wi.z <= 0.0 {
                return None;
            }
            wi
        } else {
            let wi = refract(wo_up, h, eta)?;
            if wi.z >= 0.0 {
                return None;
            }
            wi
        };
        // The density in the caller's frame (`pdf` mirrors it again and picks η by side).
        let pdf = self.pdf(wo, flip_z(wi, flip));
        if pdf <= 0.0 || !pdf.is_finite() || g1 <= 0.0 {
            return None;
        }
        let ratio = self.g2(wo_up, wi) / g1;
        let weight = if wi.z > 0.0 {
            Vec3::splat(ratio)
        } else {
            self.tint * (ratio / (eta * eta))
        };
        Some((flip_z(wi, flip), weight, pdf))
    }
}
