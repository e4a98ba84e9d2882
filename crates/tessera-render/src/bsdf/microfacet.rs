//! GGX (Trowbridge–Reitz) microfacet lobes: a rough conductor and the glTF 2.0 dielectric
//! base.
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
//! | [`GltfDielectric`] | `base` colour, `alpha`, `f0` from the IOR, `specular` (KHR_materials_specular factor, scaling the Fresnel term): glTF 2.0 spec appendix B's dielectric, a GGX specular layer `F(wo·h) D G2 / (4 cos θo cos θi)` over a Lambertian base weighted by `1 - F(wo·h)` (the spec's `fresnel_mix`; it gains a little energy at grazing angles for bright bases), with Schlick's `F = f0 + (1 - f0)(1 - cos)^5` |

use super::fresnel_schlick;
use crate::math::luminance;
use crate::sampling::warp::{
    cosine_hemisphere_pdf, ggx_d, ggx_g1, ggx_lambda, ggx_vndf_pdf, sample_ggx_vndf,
    square_to_cosine_hemisphere,
};
use glam::{Vec2, Vec3};
use std::f32::consts::FRAC_1_PI;

/// Smallest GGX alpha used: smoother surfaces are numerically treated as this rough (the
/// highlight is then narrower than a pixel in practice).
pub const MIN_ALPHA: f32 = 2e-3;

#[inline]
fn g2(wo: Vec3, wi: Vec3, alpha: f32) -> f32 {
    1.0 / (1.0 + ggx_lambda(wo, alpha) + ggx_lambda(wi, alpha))
}

/// Density of sampling `wi` by reflecting `wo` about a visible normal.
#[inline]
fn vndf_reflection_pdf(wo: Vec3, h: Vec3, alpha: f32) -> f32 {
    let dot = wo.dot(h);
    if dot <= 0.0 || wo.z <= 0.0 {
        return 0.0;
    }
    // Jacobian of the reflection h -> wi: 1 / (4 wo·h); the VNDF pdf is the grazing-safe form.
    ggx_vndf_pdf(wo, h, alpha) / (4.0 * dot)
}

#[inline]
fn half_vector(wo: Vec3, wi: Vec3) -> Option<Vec3> {
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

/// The glTF dielectric base: Lambertian diffuse under a GGX specular layer, mixed by
/// Schlick's Fresnel of the half vector.
#[derive(Clone, Copy, Debug)]
pub struct GltfDielectric {
    /// Base colour (diffuse reflectance).
    pub base: Vec3,
    /// GGX alpha (roughness²), at least [`MIN_ALPHA`].
    pub alpha: f32,
    /// Fresnel reflectance at normal incidence, `((ior - 1)/(ior + 1))²`.
    pub f0: f32,
    /// KHR_materials_specular's `specularFactor` in [0, 1]: the Fresnel term is
    /// `specular · F_Schlick(f0, cos)` (the extension's `f0 · specular` and
    /// `f90 = specular`), so 0 leaves the Lambertian base alone and 1 is the core model.
    pub specular: f32,
}

impl GltfDielectric {
    /// The layer's Fresnel reflectance for the cosine `cos` (of the half vector, or of
    /// `wo` for the lobe choice).
    fn fresnel(&self, cos: f32) -> f32 {
        self.specular * fresnel_schlick(Vec3::splat(self.f0), cos).x
    }

    fn p_specular(&self, wo: Vec3) -> f32 {
        if self.specular <= 0.0 {
            // No specular layer: never sample it.
            return 0.0;
        }
        let f = self.fresnel(wo.z);
        let d = (1.0 - f) * luminance(self.base);
        (f / (f + d)).clamp(0.05, 1.0)
    }

    pub(crate) fn eval(&self, wo: Vec3, wi: Vec3) -> Vec3 {
        if wo.z <= 0.0 || wi.z <= 0.0 {
            return Vec3::ZERO;
        }
        let Some(h) = half_vector(wo, wi) else {
            return Vec3::ZERO;
        };
        let f = self.fresnel(wo.dot(h));
        let spec = f * ggx_d(h, self.alpha) * g2(wo, wi, self.alpha) / (4.0 * wo.z);
        // glTF 2.0 appendix B fresnel_mix: the base gets 1 - F(wo·h). This is the spec's
        // model, kept so glTF scenes match other glTF renderers; it is not exactly energy
        // conserving at grazing angles for bright bases (albedo up to 1.09 for base 0.9 at
        // 75°, see bsdf::tests::gltf_dielectric_energy), a known property of the spec model.
        let t = 1.0 - f;
        self.base * (t * FRAC_1_PI * wi.z) + Vec3::splat(spec)
    }

    pub(crate) fn pdf(&self, wo: Vec3, wi: Vec3) -> f32 {
        if wo.z <= 0.0 || wi.z <= 0.0 {
            return 0.0;
        }
        let ps = self.p_specular(wo);
        let spec = half_vector(wo, wi).map_or(0.0, |h| vndf_reflection_pdf(wo, h, self.alpha));
        ps * spec + (1.0 - ps) * cosine_hemisphere_pdf(wi.z)
    }

    pub(crate) fn sample(&self, wo: Vec3, u1: f32, u2: Vec2) -> Option<(Vec3, Vec3, f32)> {
        if wo.z <= 0.0 {
            return None;
        }
        let wi = if u1 < self.p_specular(wo) {
            crate::math::reflect(wo, sample_ggx_vndf(wo, self.alpha, u2))
        } else {
            square_to_cosine_hemisphere(u2)
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
