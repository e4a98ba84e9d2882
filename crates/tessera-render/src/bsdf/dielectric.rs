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
//! # Multiple scattering
//! Single-scattering microfacet models lose the light that bounces more than once between
//! microfacets: 5% of a white furnace at alpha 0.09, 28% at alpha 0.49, more at grazing
//! angles. The lobe adds Kulla & Conty's compensation (2017, "Revisiting Physically Based
//! Shading at Imageworks", section on dielectric energy compensation), split between the
//! two sides. With `E_A(μ)` the single-scattering energy albedo seen from side `A`
//! ([`super::albedo::dielectric_albedo`], tabulated for `η` and `1/η`), `L_A = 1 - E_A` and
//! `Ē_A` its cosine-weighted average, the compensation is
//! `f_ms(wo, wi) = k_AB L_A(μo) L_B(μi) / π` for `wo` on side `A`, `wi` on side `B`
//! (tinted when `A ≠ B`). Writing `s` for the side with `η_s >= 1` (entering the denser
//! medium) and `t` for the other, the coefficients are
//!
//! - `k_ss = (1 - x) / (1 - Ē_s)`, `k_st = x / (η_s² (1 - Ē_t))`, `k_ts = η_s² k_st`,
//!   `k_tt = (1 - k_st (1 - Ē_s)) / (1 - Ē_t)`,
//!
//! which return exactly the lost energy from either side (`∫ f cos + η² ∫ f_t cos = 1`
//! for a white lobe, with the tables' `E`) and obey the generalised reciprocity above.
//! `x`, the share of the entering side's lost energy that is transmitted, is free: it is
//! the smooth interface's `1 - F_avg(η_s)` (Kulla & Conty's fit
//! `F_avg = (η - 1) / (4.08567 + 1.00071 η)`), at most `η_s² (1 - Ē_t) / (1 - Ē_s)`
//! so that `k_tt >= 0`.
//!
//! Sampling: with probability `L(μo)` the compensation (cosine-weighted, on the far side
//! with probability the share of its energy transmitted), otherwise a visible normal `h`
//! (Heitz 2018), then reflection with probability `F(wo·h)` (total internal reflection
//! gives `F = 1`) and refraction otherwise. The single-scattering densities are
//! `F D_wo(h) / (4 wo·h)` and `(1 - F) D_wo(h) |wi·h| / (wi·h + wo·h/η)²` (the Jacobian of
//! the refraction `h -> wi`, Walter et al. 2007, eq. 17); the weight is `eval / pdf` of
//! the mixture.

use super::albedo::{dielectric_albedo, dielectric_albedo_average};
use super::flip_z;
use super::fresnel_dielectric;
use crate::sampling::warp::{
    cosine_hemisphere_pdf, ggx_d, ggx_lambda, ggx_vndf_pdf, sample_ggx_vndf,
    square_to_cosine_hemisphere,
};
use glam::{Vec2, Vec3};
use std::f32::consts::FRAC_1_PI;

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

    /// `f(wo, wi) |cos θi|` of single scattering.
    fn eval_single(&self, wo: Vec3, wi: Vec3) -> Vec3 {
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

    /// Solid-angle density of [`RoughDielectric::sample_single`].
    fn pdf_single(&self, wo: Vec3, wi: Vec3) -> f32 {
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

    /// Samples `wi` from single scattering (a visible normal, then reflection or refraction
    /// by Fresnel); `wo.z > 0` after mirroring, with `eta` seen from `wo`.
    fn sample_single(wo_up: Vec3, alpha: f32, eta: f32, u1: f32, u2: Vec2) -> Option<Vec3> {
        let h = sample_ggx_vndf(wo_up, alpha, u2);
        if wo_up.dot(h) <= 0.0 {
            return None;
        }
        Self::scatter(wo_up, h, eta, u1 < fresnel_dielectric(wo_up.dot(h), eta))
    }

    /// Reflects (`reflect`) or refracts `wo_up` about the microfacet `h`; `None` when the
    /// direction ends on the wrong side (or under total internal reflection).
    #[inline]
    fn scatter(wo_up: Vec3, h: Vec3, eta: f32, reflect: bool) -> Option<Vec3> {
        if reflect {
            let wi = crate::math::reflect(wo_up, h);
            (wi.z > 0.0).then_some(wi)
        } else {
            refract(wo_up, h, eta).filter(|wi| wi.z < 0.0)
        }
    }

    /// The power single scattering returns for the visible normal of `u`, averaged over the
    /// Fresnel choice: `F G2/G1` for the reflection plus `(1 - F) G2/G1` for the
    /// refraction (whose radiance weight carries `1/η²`, undone here), each where the
    /// direction is valid. Its mean over `u` is the energy albedo the compensation's tables
    /// hold ([`super::albedo`]).
    #[cfg(test)]
    pub(crate) fn single_scattering_energy(&self, wo_up: Vec3, u: Vec2) -> f32 {
        self.single_scattering_energy_with(wo_up, u, |_| 1.0, |_| 1.0)
    }

    /// [`RoughDielectric::single_scattering_energy`] with the reflected and the refracted
    /// power weighted by `reflected(wi)` and `refracted(wi)` (for the clearcoat's loss over
    /// rough glass, [`super::albedo::coat_glass_loss`], which weights the light leaving
    /// the interface by what the coat reflects back).
    #[cfg(test)]
    pub(crate) fn single_scattering_energy_with(
        &self,
        wo_up: Vec3,
        u: Vec2,
        reflected: impl Fn(Vec3) -> f32,
        refracted: impl Fn(Vec3) -> f32,
    ) -> f32 {
        let h = sample_ggx_vndf(wo_up, self.alpha, u);
        let oh = wo_up.dot(h);
        let g1 = crate::sampling::warp::ggx_g1(wo_up, self.alpha);
        if oh <= 0.0 || g1 <= 0.0 {
            return 0.0;
        }
        let f = fresnel_dielectric(oh, self.eta);
        let part = |reflect: bool, p: f32| {
            if p <= 0.0 {
                return 0.0;
            }
            Self::scatter(wo_up, h, self.eta, reflect).map_or(0.0, |wi| {
                let weight = if reflect {
                    reflected(wi)
                } else {
                    refracted(wi)
                };
                p * self.g2(wo_up, wi) / g1 * weight
            })
        };
        part(true, f) + part(false, 1.0 - f)
    }

    /// The compensation at `wo` (`wo.z > 0` after mirroring, `eta` seen from it).
    #[inline]
    fn compensation(&self, mu_o: f32, eta: f32) -> Compensation {
        let loss_o = (1.0 - dielectric_albedo(mu_o, self.alpha, eta)).clamp(0.0, 1.0);
        // The entering side s (η_s >= 1) and the other, t.
        let entering = eta >= 1.0;
        let eta_s = if entering { eta } else { 1.0 / eta };
        let floor = 1e-6;
        let ls = (1.0 - dielectric_albedo_average(self.alpha, eta_s)).max(floor);
        let lt = (1.0 - dielectric_albedo_average(self.alpha, 1.0 / eta_s)).max(floor);
        let f_avg = (eta_s - 1.0) / (4.08567 + 1.00071 * eta_s);
        let e2 = eta_s * eta_s;
        let x = (1.0 - f_avg).clamp(0.0, 1.0).min(e2 * lt / ls);
        let k_st = x / (e2 * lt);
        let (same, cross, share) = if entering {
            ((1.0 - x) / ls, k_st, x)
        } else {
            let share = (k_st * ls).min(1.0);
            ((1.0 - share) / lt, e2 * k_st, share)
        };
        Compensation {
            loss_o,
            same: same * FRAC_1_PI,
            cross: cross * FRAC_1_PI,
            share,
        }
    }

    /// `(1 - E(μo), share transmitted)`: the probability of sampling the compensation at
    /// `wo` and its probability of the far side (for the tests' reference density).
    #[cfg(test)]
    pub(crate) fn compensation_sampling(&self, wo: Vec3) -> (f32, f32) {
        let c = self.compensation(wo.z.abs(), self.side(wo).1);
        (c.loss_o, c.share)
    }

    /// `f(wo, wi) |cos θi|`: single scattering plus the multiple-scattering compensation.
    pub(crate) fn eval(&self, wo: Vec3, wi: Vec3) -> Vec3 {
        let single = self.eval_single(wo, wi);
        match self.eval_multiple(wo, wi) {
            Some(ms) => single + ms,
            None => single,
        }
    }

    /// `f_ms(wo, wi) |cos θi|`, the multiple-scattering compensation alone; `None` where it
    /// is zero (a direction in the plane, or nothing lost at `wo`).
    pub(crate) fn eval_multiple(&self, wo: Vec3, wi: Vec3) -> Option<Vec3> {
        if wo.z == 0.0 || wi.z == 0.0 {
            return None;
        }
        let (_, eta) = self.side(wo);
        let c = self.compensation(wo.z.abs(), eta);
        if c.loss_o == 0.0 {
            return None;
        }
        let (mu_i, same) = (wi.z.abs(), wo.z * wi.z > 0.0);
        let eta_i = if same { eta } else { 1.0 / eta };
        let loss_i = (1.0 - dielectric_albedo(mu_i, self.alpha, eta_i)).max(0.0);
        let ms = c.loss_o * loss_i * mu_i;
        Some(if same {
            Vec3::splat(c.same * ms)
        } else {
            self.tint * (c.cross * ms)
        })
    }

    /// Solid-angle density of [`RoughDielectric::sample`].
    pub(crate) fn pdf(&self, wo: Vec3, wi: Vec3) -> f32 {
        let single = self.pdf_single(wo, wi);
        if wo.z == 0.0 || wi.z == 0.0 {
            return single;
        }
        let (_, eta) = self.side(wo);
        let c = self.compensation(wo.z.abs(), eta);
        let side = if wo.z * wi.z > 0.0 {
            1.0 - c.share
        } else {
            c.share
        };
        (1.0 - c.loss_o) * single + c.loss_o * side * cosine_hemisphere_pdf(wi.z.abs())
    }

    /// Samples `wi`; returns (wi, weight f|cos θi|/pdf, pdf).
    pub(crate) fn sample(&self, wo: Vec3, u1: f32, u2: Vec2) -> Option<(Vec3, Vec3, f32)> {
        if wo.z == 0.0 {
            return None;
        }
        let (flip, eta) = self.side(wo);
        let wo_up = flip_z(wo, flip);
        let c = self.compensation(wo_up.z, eta);
        let wi = if u1 < c.loss_o {
            // The compensation: cosine-weighted, on the far side with its share.
            let u = u1 / c.loss_o;
            let wi = square_to_cosine_hemisphere(u2);
            if u < c.share {
                -wi
            } else {
                wi
            }
        } else {
            let u = ((u1 - c.loss_o) / (1.0 - c.loss_o)).clamp(0.0, 1.0 - f32::EPSILON);
            Self::sample_single(wo_up, self.alpha, eta, u, u2)?
        };
        let wi = flip_z(wi, flip);
        if wi.z == 0.0 {
            return None;
        }
        let pdf = self.pdf(wo, wi);
        if pdf <= 0.0 || !pdf.is_finite() {
            return None;
        }
        Some((wi, self.eval(wo, wi) / pdf, pdf))
    }
}

/// The multiple-scattering compensation of a [`RoughDielectric`] at one `wo` (see the
/// module documentation).
#[derive(Clone, Copy, Debug)]
struct Compensation {
    /// `1 - E(μo)`: the energy single scattering loses, and the probability of sampling
    /// the compensation.
    loss_o: f32,
    /// `k / π` towards `wo`'s side and towards the other.
    same: f32,
    cross: f32,
    /// The share of the compensation's energy that is transmitted (its sampling
    /// probability).
    share: f32,
}
