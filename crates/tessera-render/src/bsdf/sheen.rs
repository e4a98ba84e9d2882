//! The sheen layer of KHR_materials_sheen: the "Charlie" distribution of Estevez & Kulla
//! 2017 ("Production Friendly Microfacet Sheen BRDF", section 2) with the extension's
//! visibility term (their fitted `Λ`, section 3), for cloth-like retro- and grazing
//! reflection.
//!
//! | parameter | meaning |
//! |---|---|
//! | `color` | sheen colour, linear RGB in [0, 1] |
//! | `r` | perceptual sheen roughness, `α = r²`, clamped to at least [`MIN_SHEEN_ROUGHNESS`] |
//!
//! `f = color D(h) V`, `D(h) = (2 + 1/α) sin^(1/α) θh / (2π)` (normalised:
//! `∫ D cos θh dω = 1`), `V = 1 / ((1 + Λ(wo) + Λ(wi)) 4 cos θo cos θi)`, with the
//! extension's `Λ(μ) = exp(L(μ))` for `μ < 1/2` and `exp(2 L(1/2) - L(1 - μ))` otherwise,
//! `L(x) = a / (1 + b x^c) + d x + e` and `(a, b, c, d, e)` interpolated in `(1 - α)²`
//! between the fits at `α = 0` and `α = 1`. Reciprocal. Divided by `max(1, E(μo), E(μi))`
//! (`E` the lobe's albedo), which only acts on smooth sheens at grazing angles, where the
//! published lobe's albedo exceeds one. [`super::gltf`] samples it from the
//! cosine-weighted hemisphere (the lobe is broad; the weight `π f` is bounded).

use super::albedo::sheen_albedo;
use glam::Vec3;
use std::f32::consts::PI;

/// Smallest perceptual sheen roughness used: below it `sin^(1/α)` is too narrow for the
/// f32 evaluation and the albedo table.
pub const MIN_SHEEN_ROUGHNESS: f32 = 0.07;

/// Charlie sheen lobe.
#[derive(Clone, Copy, Debug)]
pub struct Sheen {
    /// Sheen colour.
    pub color: Vec3,
    /// Charlie `α = r²`.
    pub alpha: f32,
}

/// The extension's fit `L(x)` of Estevez & Kulla 2017, section 3.
#[inline]
fn fit_l(x: f32, alpha: f32) -> f32 {
    let t = (1.0 - alpha) * (1.0 - alpha);
    let mix = |p: f32, q: f32| p + (q - p) * t;
    let a = mix(21.5473, 25.3245);
    let b = mix(3.82987, 3.32435);
    let c = mix(0.19823, 0.16801);
    let d = mix(-1.97760, -1.27393);
    let e = mix(-4.32054, -4.85967);
    a / (1.0 + b * x.powf(c)) + d * x + e
}

/// Charlie's `Λ(μ)`.
#[inline]
fn lambda(mu: f32, alpha: f32) -> f32 {
    let mu = mu.abs();
    if mu < 0.5 {
        fit_l(mu, alpha).exp()
    } else {
        (2.0 * fit_l(0.5, alpha) - fit_l(1.0 - mu, alpha)).exp()
    }
}

impl Sheen {
    /// A sheen of `color` and perceptual roughness `r`.
    pub fn new(color: Vec3, r: f32) -> Self {
        let r = r.clamp(MIN_SHEEN_ROUGHNESS, 1.0);
        Sheen {
            color,
            alpha: r * r,
        }
    }

    /// The Charlie distribution of normals at `cos θh`.
    #[inline]
    fn d(&self, cos_h: f32) -> f32 {
        let inv = 1.0 / self.alpha;
        let sin2 = (1.0 - cos_h * cos_h).max(0.0);
        (2.0 + inv) * sin2.powf(0.5 * inv) / (2.0 * PI)
    }

    /// `f cos θi` of the lobe as published: `color D / ((1 + Λo + Λi) 4 cos θo)`.
    pub(crate) fn eval_raw(&self, wo: Vec3, wi: Vec3) -> Vec3 {
        if wo.z <= 0.0 || wi.z <= 0.0 {
            return Vec3::ZERO;
        }
        let h = wo + wi;
        if h.length_squared() <= 1e-12 {
            return Vec3::ZERO;
        }
        let cos_h = h.normalize().z;
        let l = 1.0 + lambda(wo.z, self.alpha) + lambda(wi.z, self.alpha);
        self.color * (self.d(cos_h) / (4.0 * l * wo.z))
    }

    /// `f cos θi`: [`Sheen::eval_raw`] divided by `max(1, E(μo), E(μi))`, `E` its albedo.
    /// The published lobe reflects more than it receives at grazing angles when it is smooth
    /// (`E = 1.8` at 89° for roughness 0.1); the symmetric factor keeps it reciprocal and
    /// its albedo at most one.
    pub(crate) fn eval(&self, wo: Vec3, wi: Vec3) -> Vec3 {
        let r = self.alpha.sqrt();
        let norm = sheen_albedo(wo.z, r).max(sheen_albedo(wi.z, r)).max(1.0);
        self.eval_raw(wo, wi) / norm
    }
}
