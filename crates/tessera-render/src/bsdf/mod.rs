//! Bidirectional scattering distribution functions.
//!
//! # The sampling contract
//! Everything here works in the local shading frame, `+z` along the shading normal.
//! `wo` points toward the viewer (the previous path vertex), `wi` toward the light (the
//! next vertex); both are unit vectors pointing away from the surface.
//!
//! - [`Bsdf::eval`] returns `f(wo, wi) |cos θi|`: **the cosine is included** (as Mitsuba does),
//!   so a path's throughput is multiplied by `eval / pdf` without another cosine.
//! - [`Bsdf::pdf`] is the solid-angle density with which [`Bsdf::sample`] produces `wi`
//!   through its non-delta lobes.
//! - [`Bsdf::sample`] returns the direction and the *weight* `f |cos θi| / pdf` (already
//!   divided by the pdf). `None` is an invalid sample (e.g. a lobe direction below the
//!   horizon): its contribution is zero, which keeps the estimator unbiased because `pdf`
//!   accounts for the lost mass.
//! - Delta lobes (mirror, smooth glass) are never returned by `eval`/`pdf`; a sample from
//!   one has `delta = true` and `pdf` set to the lobe-selection probability (not a density).
//!
//! A [`Bsdf`] is a weighted mixture of up to three [`Lobe`]s; the weights are both the
//! mixing weights and the lobe-selection probabilities (one-sample MIS over lobes: the
//! combined pdf is the weighted sum, Veach & Guibas 1995, section 3). Opaque lobes scatter on both sides of a
//! surface (the frame is mirrored when `wo` is below), glass distinguishes inside from
//! outside by the sign of `wo.z`.
//!
//! One file per lobe: [`diffuse`], [`phong`], [`microfacet`] (GGX conductor),
//! [`dielectric`] (rough glass), [`specular`] (mirror and smooth glass), [`sheen`], and
//! [`gltf`], the layered glTF material built from them, with its albedo tables in
//! [`albedo`].

pub mod albedo;
pub mod dielectric;
pub mod diffuse;
pub mod gltf;
pub mod microfacet;
pub mod phong;
pub mod sheen;
pub mod specular;

use glam::{Vec2, Vec3};

/// A sampled direction.
#[derive(Clone, Copy, Debug)]
pub struct BsdfSample {
    /// Incident direction (local frame).
    pub wi: Vec3,
    /// `f |cos θi| / pdf`.
    pub weight: Vec3,
    /// Solid-angle density of the non-delta mixture at `wi`, or the selection probability
    /// for a delta lobe.
    pub pdf: f32,
    /// The sample came from a delta lobe (no MIS possible).
    pub delta: bool,
}

/// One scattering lobe. The variants are the closed list of models the renderer has;
/// `match` below is the checklist for adding one.
#[derive(Clone, Copy, Debug)]
pub enum Lobe {
    /// Lambertian reflection.
    Diffuse(diffuse::Diffuse),
    /// Veach's energy-conserving modified Phong.
    Phong(phong::Phong),
    /// GGX rough conductor with Schlick's Fresnel.
    Conductor(microfacet::Conductor),
    /// GGX rough dielectric interface: reflection and refraction.
    RoughDielectric(dielectric::RoughDielectric),
    /// The layered glTF material (metal, specular over diffuse, transmission, clearcoat,
    /// sheen); may contain a delta transmission component.
    Gltf(gltf::GltfLobe),
    /// Ideal mirror.
    Mirror(specular::Mirror),
    /// Smooth dielectric interface with Fresnel and total internal reflection.
    Glass(specular::Glass),
}

impl Lobe {
    /// Lobes that only reflect scatter on both sides of a surface.
    #[inline]
    fn is_opaque(&self) -> bool {
        match self {
            Lobe::Glass(_) | Lobe::RoughDielectric(_) => false,
            Lobe::Gltf(g) => !g.transmits(),
            _ => true,
        }
    }

    /// True if the lobe is a Dirac delta distribution (a lobe with delta and non-delta
    /// components, [`Lobe::Gltf`], is not; its delta samples say so themselves).
    #[inline]
    pub fn is_delta(&self) -> bool {
        match self {
            Lobe::Mirror(_) | Lobe::Glass(_) => true,
            Lobe::Gltf(g) => g.is_pure_delta(),
            _ => false,
        }
    }

    #[inline]
    fn eval(&self, wo: Vec3, wi: Vec3) -> Vec3 {
        match self {
            Lobe::Diffuse(l) => l.eval(wo, wi),
            Lobe::Phong(l) => l.eval(wo, wi),
            Lobe::Conductor(l) => l.eval(wo, wi),
            Lobe::RoughDielectric(l) => l.eval(wo, wi),
            Lobe::Gltf(l) => l.eval(wo, wi),
            Lobe::Mirror(_) | Lobe::Glass(_) => Vec3::ZERO,
        }
    }

    #[inline]
    fn pdf(&self, wo: Vec3, wi: Vec3) -> f32 {
        match self {
            Lobe::Diffuse(l) => l.pdf(wo, wi),
            Lobe::Phong(l) => l.pdf(wo, wi),
            Lobe::Conductor(l) => l.pdf(wo, wi),
            Lobe::RoughDielectric(l) => l.pdf(wo, wi),
            Lobe::Gltf(l) => l.pdf(wo, wi),
            Lobe::Mirror(_) | Lobe::Glass(_) => 0.0,
        }
    }

    /// Samples `wi`: the direction, weight `f|cos|/pdf`, pdf (a probability for a delta
    /// sample) and whether the sample is a delta one.
    #[inline]
    fn sample(&self, wo: Vec3, u1: f32, u2: Vec2) -> Option<BsdfSample> {
        let (wi, weight, pdf) = match self {
            Lobe::Diffuse(l) => l.sample(wo, u2),
            Lobe::Phong(l) => l.sample(wo, u1, u2),
            Lobe::Conductor(l) => l.sample(wo, u2),
            Lobe::RoughDielectric(l) => l.sample(wo, u1, u2),
            Lobe::Gltf(l) => return l.sample(wo, u1, u2),
            Lobe::Mirror(l) => l.sample(wo),
            Lobe::Glass(l) => l.sample(wo, u1),
        }?;
        Some(BsdfSample {
            wi,
            weight,
            pdf,
            delta: self.is_delta(),
        })
    }
}

/// Mirrors `v` to the upper hemisphere when `flip` is set (two-sided opaque lobes).
#[inline]
pub(crate) fn flip_z(v: Vec3, flip: bool) -> Vec3 {
    if flip {
        Vec3::new(v.x, v.y, -v.z)
    } else {
        v
    }
}

/// A weighted mixture of up to three lobes. Allocation-free; built per hit.
#[derive(Clone, Copy, Debug)]
pub struct Bsdf {
    lobes: [Lobe; 3],
    weights: [f32; 3],
    count: usize,
}

impl Bsdf {
    /// A BSDF with a single lobe.
    #[inline]
    pub fn single(lobe: Lobe) -> Self {
        // The unused slots hold the smallest variant: writing `[lobe; 3]` would copy the
        // largest lobe (the layered glTF one, about 240 bytes) three times per hit. Written
        // out rather than as a `const`: a constant of the enum is copied whole (a memset
        // of both slots and a copy of the whole array, about 180 instructions per hit),
        // while the expression writes only its tag and albedo.
        Self {
            lobes: [
                lobe,
                Lobe::Diffuse(diffuse::Diffuse { albedo: Vec3::ZERO }),
                Lobe::Diffuse(diffuse::Diffuse { albedo: Vec3::ZERO }),
            ],
            weights: [1.0, 0.0, 0.0],
            count: 1,
        }
    }

    /// A mixture; weights are normalised to sum to one and zero-weight lobes dropped.
    pub fn mixture(parts: &[(Lobe, f32)]) -> Self {
        let total: f32 = parts.iter().map(|p| p.1.max(0.0)).sum();
        let mut out = Self::single(Lobe::Diffuse(diffuse::Diffuse { albedo: Vec3::ZERO }));
        out.count = 0;
        if total <= 0.0 {
            out.count = 1;
            return out;
        }
        for &(lobe, w) in parts.iter().take(3) {
            if w > 0.0 {
                out.lobes[out.count] = lobe;
                out.weights[out.count] = w / total;
                out.count += 1;
            }
        }
        out
    }

    /// True if some lobe transmits light through the surface (it scatters into both
    /// hemispheres, so light selection must not favour one side).
    pub fn has_transmission(&self) -> bool {
        self.lobes[..self.count].iter().any(|l| !l.is_opaque())
    }

    /// True if some lobe is not a delta distribution (so light sampling can help).
    pub fn has_non_delta(&self) -> bool {
        self.lobes[..self.count].iter().any(|l| !l.is_delta())
    }

    /// The relative index of refraction (inside over outside) of the smooth dielectric lobe
    /// (or of a glTF lobe's transmission), if the mixture has one. Light tracing needs it
    /// for delta refraction samples: radiance crossing the interface is scaled by
    /// `(η_i/η_t)²` in [`Bsdf::sample`], importance (and power) is not (pbrt 3rd ed.
    /// §16.1.3, non-symmetric scattering due to refraction). Rough refraction needs nothing:
    /// its `eval` is the radiance BTDF, whose adjoint `f(wi, wo)` is the importance BTDF
    /// (see [`dielectric`]).
    pub fn glass_eta(&self) -> Option<f32> {
        self.lobes[..self.count].iter().find_map(|l| match l {
            Lobe::Glass(g) => Some(g.eta),
            Lobe::RoughDielectric(g) => Some(g.eta),
            Lobe::Gltf(g) => g.eta(),
            _ => None,
        })
    }

    /// `f(wo, wi) |cos θi|` of the non-delta lobes.
    pub fn eval(&self, wo: Vec3, wi: Vec3) -> Vec3 {
        let mut f = Vec3::ZERO;
        for i in 0..self.count {
            let lobe = &self.lobes[i];
            if lobe.is_delta() {
                continue;
            }
            let flip = lobe.is_opaque() && wo.z < 0.0;
            f += self.weights[i] * lobe.eval(flip_z(wo, flip), flip_z(wi, flip));
        }
        f
    }

    /// Solid-angle density of sampling `wi` through the non-delta lobes.
    pub fn pdf(&self, wo: Vec3, wi: Vec3) -> f32 {
        let mut p = 0.0;
        for i in 0..self.count {
            let lobe = &self.lobes[i];
            if lobe.is_delta() {
                continue;
            }
            let flip = lobe.is_opaque() && wo.z < 0.0;
            p += self.weights[i] * lobe.pdf(flip_z(wo, flip), flip_z(wi, flip));
        }
        p
    }

    /// Samples an incident direction: `u1` picks the lobe (and is re-used, rescaled, by the
    /// lobe), `u2` drives the lobe's warp.
    pub fn sample(&self, wo: Vec3, u1: f32, u2: Vec2) -> Option<BsdfSample> {
        if wo.z == 0.0 || self.count == 0 {
            return None;
        }
        // Choose the lobe by its weight and stretch u1 back to [0, 1).
        let mut idx = self.count - 1;
        let mut lo = 0.0;
        for i in 0..self.count {
            if u1 < lo + self.weights[i] || i == self.count - 1 {
                idx = i;
                break;
            }
            lo += self.weights[i];
        }
        let w = self.weights[idx];
        let u1 = ((u1 - lo) / w).clamp(0.0, 1.0 - f32::EPSILON);
        let lobe = &self.lobes[idx];
        let flip = lobe.is_opaque() && wo.z < 0.0;
        let BsdfSample {
            wi,
            weight,
            pdf,
            delta,
        } = lobe.sample(flip_z(wo, flip), u1, u2)?;
        let wi = flip_z(wi, flip);
        if delta {
            // f_mix / p_mix = (w f) / (w p): the mixture weight cancels.
            return Some(BsdfSample {
                wi,
                weight,
                pdf: w * pdf,
                delta: true,
            });
        }
        if self.count == 1 {
            return Some(BsdfSample {
                wi,
                weight,
                pdf,
                delta: false,
            });
        }
        // The direction could have come from any non-delta lobe: weight by the mixture.
        let f = self.eval(wo, wi);
        let p = self.pdf(wo, wi);
        if p <= 0.0 {
            return None;
        }
        Some(BsdfSample {
            wi,
            weight: f / p,
            pdf: p,
            delta: false,
        })
    }
}

/// Unpolarised Fresnel reflectance of a dielectric interface (exact, not Schlick).
/// `cos_i` is the cosine on the incident side (may be negative: then the ray is inside and
/// the relative index is inverted); `eta` is n_inside / n_outside. Returns 1 under total
/// internal reflection.
#[inline]
pub fn fresnel_dielectric(cos_i: f32, eta: f32) -> f32 {
    let (cos_i, eta) = if cos_i < 0.0 {
        (-cos_i, 1.0 / eta)
    } else {
        (cos_i, eta)
    };
    let sin2_t = (1.0 - cos_i * cos_i).max(0.0) / (eta * eta);
    if sin2_t >= 1.0 {
        return 1.0;
    }
    let cos_t = (1.0 - sin2_t).max(0.0).sqrt();
    let r_parl = (eta * cos_i - cos_t) / (eta * cos_i + cos_t);
    let r_perp = (cos_i - eta * cos_t) / (cos_i + eta * cos_t);
    0.5 * (r_parl * r_parl + r_perp * r_perp)
}

/// Schlick's approximation of Fresnel reflectance from the normal-incidence value `f0`.
#[inline]
pub fn fresnel_schlick(f0: Vec3, cos: f32) -> Vec3 {
    let m = (1.0 - cos.clamp(0.0, 1.0)).powi(5);
    f0 + (Vec3::ONE - f0) * m
}

#[cfg(test)]
mod tests;
