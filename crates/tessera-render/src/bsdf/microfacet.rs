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

// ---------------------------------------------------------------------------------------
// Anisotropic GGX (KHR_materials_anisotropy)
// ---------------------------------------------------------------------------------------

/// Anisotropic GGX roughness in a frame whose `+x` is the direction of `ax` (the
/// anisotropy direction) and `+y` that of `ay`, `+z` the normal. The distribution is
/// isotropic GGX stretched by `(ax, ay)` (Heitz 2014, "Understanding the Masking-Shadowing
/// Function", section 5.3): `D(m) = 1 / (π ax ay (mx²/ax² + my²/ay² + mz²)²)` and
/// `Λ(w) = (sqrt(1 + (ax² wx² + ay² wy²) / wz²) - 1) / 2`. With `ax = ay = α` these are
/// the isotropic functions of `crate::sampling::warp`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AnisoGgx {
    /// GGX alpha along local `+x`.
    pub ax: f32,
    /// GGX alpha along local `+y`.
    pub ay: f32,
}

impl AnisoGgx {
    /// The distribution of normals `D(m)`.
    #[inline]
    pub fn d(&self, m: Vec3) -> f32 {
        if m.z <= 0.0 {
            return 0.0;
        }
        let (x, y) = (m.x / self.ax, m.y / self.ay);
        let k = x * x + y * y + m.z * m.z;
        1.0 / (std::f32::consts::PI * self.ax * self.ay * k * k)
    }

    /// Smith's `Λ(w)`, even in `w.z`, `+inf` at grazing `w.z == 0` (in the cancellation-free
    /// form of `ggx_lambda`).
    #[inline]
    pub fn lambda(&self, w: Vec3) -> f32 {
        let s2 = self.ax * self.ax * w.x * w.x + self.ay * self.ay * w.y * w.y;
        if s2 == 0.0 {
            return 0.0;
        }
        let t = s2 / (w.z * w.z);
        if !t.is_finite() {
            return f32::INFINITY;
        }
        t / (2.0 * (1.0 + (1.0 + t).sqrt()))
    }

    /// Height-correlated `G2 = 1 / (1 + Λ(wo) + Λ(wi))`.
    #[inline]
    pub fn g2(&self, wo: Vec3, wi: Vec3) -> f32 {
        1.0 / (1.0 + self.lambda(wo) + self.lambda(wi))
    }

    /// Samples a visible normal from `wo` (`wo.z >= 0`): Heitz 2018, "Sampling the GGX
    /// Distribution of Visible Normals" (JCGT 7(4)), whose stretch by `(ax, ay)` is the
    /// anisotropic case (as `sample_ggx_vndf` with one alpha).
    #[inline]
    pub fn sample_vndf(&self, wo: Vec3, u: Vec2) -> Vec3 {
        let vh = Vec3::new(self.ax * wo.x, self.ay * wo.y, wo.z.max(0.0)).normalize_or(Vec3::Z);
        let len2 = vh.x * vh.x + vh.y * vh.y;
        let t1 = if len2 > 0.0 {
            Vec3::new(-vh.y, vh.x, 0.0) / len2.sqrt()
        } else {
            Vec3::X
        };
        let t2 = vh.cross(t1);
        let r = u.x.sqrt();
        let (sp, cp) = (std::f32::consts::TAU * u.y).sin_cos();
        let p1 = r * cp;
        let s = 0.5 * (1.0 + vh.z);
        let p2 = (1.0 - s) * (1.0 - p1 * p1).max(0.0).sqrt() + s * (r * sp);
        let nh = p1 * t1 + p2 * t2 + (1.0 - p1 * p1 - p2 * p2).max(0.0).sqrt() * vh;
        Vec3::new(self.ax * nh.x, self.ay * nh.y, nh.z.max(f32::MIN_POSITIVE)).normalize_or(Vec3::Z)
    }

    /// Density of [`AnisoGgx::sample_vndf`]: `G1(wo) max(0, wo·m) D(m) / wo.z`, with
    /// `G1 / wo.z` in the form that stays finite at grazing `wo`.
    #[inline]
    pub fn vndf_pdf(&self, wo: Vec3, m: Vec3) -> f32 {
        let wo_m = wo.dot(m);
        if wo.z <= 0.0 || wo_m <= 0.0 {
            return 0.0;
        }
        let s2 = self.ax * self.ax * wo.x * wo.x + self.ay * self.ay * wo.y * wo.y;
        let g1_over_cos = 2.0 / (wo.z + (wo.z * wo.z + s2).sqrt());
        g1_over_cos * wo_m * self.d(m)
    }

    /// GGX reflection with Schlick's Fresnel `f0 + (f90 - f0)(1 - wo·h)^5`, times
    /// `cos θi` (both directions above the surface, in this frame).
    #[inline]
    pub fn reflection(&self, wo: Vec3, wi: Vec3, f0: Vec3, f90: f32) -> Vec3 {
        if wo.z <= 0.0 || wi.z <= 0.0 {
            return Vec3::ZERO;
        }
        let Some(h) = half_vector(wo, wi) else {
            return Vec3::ZERO;
        };
        let m = (1.0 - wo.dot(h).clamp(0.0, 1.0)).powi(5);
        let f = f0 + (Vec3::splat(f90) - f0) * m;
        f * (self.d(h) * self.g2(wo, wi) / (4.0 * wo.z))
    }

    /// Density of reflecting `wo` about a visible normal into `wi`.
    #[inline]
    pub fn reflection_pdf(&self, wo: Vec3, wi: Vec3) -> f32 {
        if wo.z <= 0.0 || wi.z <= 0.0 {
            return 0.0;
        }
        let Some(h) = half_vector(wo, wi) else {
            return 0.0;
        };
        let dot = wo.dot(h);
        if dot <= 0.0 {
            return 0.0;
        }
        self.vndf_pdf(wo, h) / (4.0 * dot)
    }
}
