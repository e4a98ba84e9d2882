//! GGX (Trowbridge–Reitz) microfacet reflection: the rough conductor, and the helpers the
//! other GGX lobes share ([`super::dielectric`], [`super::gltf`]).
//!
//! Microfacet reflection (Walter et al. 2007): `f = D(h) G2(wo, wi) F(wo·h) / (4 |cos θo|
//! |cos θi|)` with the height-correlated Smith masking-shadowing `G2 = 1 / (1 + Λ(wo) +
//! Λ(wi))`. Directions are sampled from the distribution of *visible* normals (Heitz 2018),
//! which gives the pdf `G1(wo) D(h) / (4 cos θo)` and the low-variance weight
//! `F G2 / G1(wo)`.
//!
//! | lobe | parameters |
//! |---|---|
//! | [`Conductor`] | `f0` (reflectance at normal incidence, Schlick's Fresnel), `alpha` = roughness² |

use super::fresnel_schlick;
use crate::sampling::warp::{ggx_d, ggx_g1, ggx_lambda, ggx_vndf_pdf, sample_ggx_vndf};
use glam::{Vec2, Vec3};

/// Smallest GGX alpha used: smoother surfaces are numerically treated as this rough (the
/// highlight is then narrower than a pixel in practice).
pub const MIN_ALPHA: f32 = 2e-3;

/// Height-correlated Smith masking-shadowing `G2 = 1 / (1 + Λ(wo) + Λ(wi))`.
#[inline]
pub(crate) fn g2(wo: Vec3, wi: Vec3, alpha: f32) -> f32 {
    1.0 / (1.0 + ggx_lambda(wo, alpha) + ggx_lambda(wi, alpha))
}

/// Density of sampling `wi` by reflecting `wo` about a visible normal.
#[inline]
pub(crate) fn vndf_reflection_pdf(wo: Vec3, h: Vec3, alpha: f32) -> f32 {
    let dot = wo.dot(h);
    if dot <= 0.0 || wo.z <= 0.0 {
        return 0.0;
    }
    // Jacobian of the reflection h -> wi: 1 / (4 wo·h); the VNDF pdf is the grazing-safe form.
    ggx_vndf_pdf(wo, h, alpha) / (4.0 * dot)
}

/// `normalize(wo + wi)`, `None` when the two cancel.
#[inline]
pub(crate) fn half_vector(wo: Vec3, wi: Vec3) -> Option<Vec3> {
    let h = wo + wi;
    let len2 = h.length_squared();
    if len2 <= 1e-12 {
        return None;
    }
    Some(h / len2.sqrt())
}

/// Rough conductor.
#[derive(Clone, Copy, Debug)]
pub struct Conductor {
    /// Reflectance at normal incidence.
    pub f0: Vec3,
    /// GGX alpha (roughness²), at least [`MIN_ALPHA`].
    pub alpha: f32,
}

impl Conductor {
    pub(crate) fn eval(&self, wo: Vec3, wi: Vec3) -> Vec3 {
        if wo.z <= 0.0 || wi.z <= 0.0 {
            return Vec3::ZERO;
        }
        let Some(h) = half_vector(wo, wi) else {
            return Vec3::ZERO;
        };
        let f = fresnel_schlick(self.f0, wi.dot(h));
        f * (ggx_d(h, self.alpha) * g2(wo, wi, self.alpha) / (4.0 * wo.z))
    }

    pub(crate) fn pdf(&self, wo: Vec3, wi: Vec3) -> f32 {
        if wo.z <= 0.0 || wi.z <= 0.0 {
            return 0.0;
        }
        half_vector(wo, wi).map_or(0.0, |h| vndf_reflection_pdf(wo, h, self.alpha))
    }

    pub(crate) fn sample(&self, wo: Vec3, u: Vec2) -> Option<(Vec3, Vec3, f32)> {
        if wo.z <= 0.0 {
            return None;
        }
        let h = sample_ggx_vndf(wo, self.alpha, u);
        let wi = crate::math::reflect(wo, h);
        if wi.z <= 0.0 {
            return None;
        }
        let pdf = vndf_reflection_pdf(wo, h, self.alpha);
        if pdf <= 0.0 {
            return None;
        }
        let f = fresnel_schlick(self.f0, wi.dot(h));
        let weight = f * (g2(wo, wi, self.alpha) / ggx_g1(wo, self.alpha));
        Some((wi, weight, pdf))
    }
}
