//! The glTF 2.0 metallic-roughness material with KHR_materials_ior, _specular,
//! _transmission, _clearcoat, _sheen and _anisotropy, as one layered, energy-conserving
//! lobe.
//!
//! The caller (the scene) applies textures and fills a [`GltfParams`] per hit;
//! [`gltf_bsdf`] turns it into a [`Bsdf`]. The structure is the glTF 2.0 spec's appendix B
//! (`mix(dielectric, metal, metallic)`) with the extensions' layers on top:
//!
//! ```text
//! coat   = clearcoat · f_cc  +  g_cc · sheen_layer                 (KHR_materials_clearcoat)
//! sheen_layer = f_sheen  +  g_sh · base                            (KHR_materials_sheen)
//! base   = metallic · metal + (1 - metallic) · dielectric
//! dielectric = (1 - transmission) · (f_spec + f_diffuse) + transmission · f_glass
//! ```
//!
//! | part | model |
//! |---|---|
//! | `metal` | GGX conductor, Schlick `f0 = base_color` ([`super::microfacet::Conductor`]), plus Kulla & Conty 2017's multiple-scattering lobe `F_ms (1 - E1(μo))(1 - E1(μi)) / (π (1 - E1_avg))` with `F_ms = F_avg² E1_avg / (1 - F_avg (1 - E1_avg))` and Schlick's `F_avg = f0 + (1 - f0)/21`, so that rough metals keep the energy single-scattering GGX loses (as Cycles' multiscatter GGX does; a white metal has albedo 1) |
//! | `f_spec` | GGX reflection with Schlick's Fresnel, `f0 = min(((ior-1)/(ior+1))² specular_color, 1) specular`, `f90 = specular` (KHR_materials_specular; `f90 = 0` for `ior = 1`: no interface) |
//! | `f_diffuse` | Lambertian `base_color/π`, albedo-scaled by the specular layer in Kulla & Conty 2017's reciprocal form `(1 - E(μo))(1 - E(μi)) / (1 - E_avg)` per channel |
//! | `f_glass` | the dielectric interface of KHR_materials_transmission (solid, refracting, exact Fresnel, tinted by the base colour): [`super::dielectric::RoughDielectric`], or the delta [`super::specular::Glass`] when `roughness² < MIN_ALPHA` or `ior = 1` |
//! | `f_sheen` | Charlie sheen ([`super::sheen::Sheen`]), `g_sh = min(1 - max(sheen_color) E_sh(μo), same at μi)` |
//! | `f_cc` | GGX reflection, `f0 = 0.04` (ior 1.5), `f90 = 1`, own roughness, `g_cc = min(1 - clearcoat E_cc(μo), same at μi)` |
//!
//! KHR_materials_anisotropy stretches the GGX of `metal` and `f_spec` (the extension's
//! specular BRDF; the transmission and the clearcoat stay isotropic): `α_t = mix(α, 1,
//! strength²)` along [`GltfParams::anisotropy_direction`], `α` across it
//! ([`super::microfacet::AnisoGgx`], sampled from its visible normals, Heitz 2018). Its
//! albedos, for the metal's multiple scattering and the diffuse base's scaling, come from
//! the anisotropic tables at each direction's azimuth from the anisotropy direction
//! ([`super::albedo::anisotropic_ggx_albedo`]), so both keep their energy (white furnaces
//! in `bsdf::tests`); strength 0 is the isotropic lobe to the bit.
//!
//! `E` are the layers' directional albedos ([`super::albedo`]); the sheen's is that of the
//! lobe as rendered ([`super::albedo::sheen_layer_albedo`]), which the normalisation of
//! `sheen::Sheen::eval` puts below the published lobe's, so that the base gets
//! what the sheen does not reflect.
//!
//! # Energy and reciprocity
//! The Lambertian base under the specular layer gets exactly the energy the layer does
//! not reflect (single scattering included): a white dielectric has albedo 1 at every angle
//! up to table interpolation (`bsdf::tests::gltf_white_furnace`). The spec's `fresnel_mix`
//! (base weighted by `1 - F(wo·h)`) is not used: it gains energy at grazing angles.
//!
//! Clearcoat and sheen scale *everything* below them, whose lobes may be sharp (a metal), so
//! the exact Lambertian form cannot be used there: `(1 - E(μo))(1 - E(μi)) / (1 - E_avg)`
//! exceeds `1 - E(μo)` for a mirror base at normal incidence. The extensions' `1 - E(μo)`
//! conserves energy but is not reciprocal, which BDPT's light subpaths (evaluating the
//! adjoint `f(wi, wo)`) would notice. `min(1 - E(μo), 1 - E(μi))` is both reciprocal and
//! bounded by `1 - E(μo)` for any base, hence never creates energy; it is the largest such
//! symmetric factor, and is what the sharp parts of the base (metal, specular layer,
//! transmission) get. On the Lambertian part it would lose 2-4% of a white furnace (it
//! did, before this form): that part instead gets the layers' scaling in Kulla & Conty's
//! reciprocal form, together with the specular layer's,
//! `(1 - E_s(μo)) T(μo) (1 - E_s(μi)) T(μi) / (2 ∫ (1 - E_s) T μ dμ)` with
//! `T = (1 - clearcoat E_cc)(1 - max(sheen_color) E_sh)`, which returns exactly the energy
//! that the layers and the specular layer do not reflect (`bsdf::tests` has a white
//! furnace per layer). For transmission, only the outside direction meets
//! the layers: the factor is `1 - E(μ_outside)` (reciprocal in the generalised sense).
//! Light leaving a smooth interface from inside is reflected back inside by the layers in
//! the part they do not let out (`GltfLobe::sample_smooth_exit`), so that a coated glass
//! keeps its energy; over a rough interface, what the clearcoat reflects back of the
//! light leaving it is tabulated per inside angle, interface and coat roughness and index
//! ([`super::albedo::coat_glass_loss`]) and returned inside as a reciprocal Kulla–Conty
//! lobe (`GltfLobe::coat_the_glass`); a sheen's part likewise
//! ([`super::albedo::sheen_glass_loss`]), and a coat and a sheen together return no more
//! than the two layers reflect.
//!
//! # Sides
//! Without transmission the material is opaque and two-sided (the mixture mirrors the
//! frame). With transmission `+z` is the outside: coat and sheen are there only; from the
//! inside the interface is seen with `1/η` (total internal reflection included) and the
//! opaque parts (metal, specular, diffuse) are two-sided as before.

use super::albedo::{
    anisotropic_alphas, anisotropic_ggx_albedo, anisotropic_ggx_albedo_average,
    anisotropic_ggx_albedo_azimuthal, coat_glass_loss, coat_glass_loss_average, coat_loss,
    coat_loss_average, ggx_albedo, ggx_albedo_average, sheen_glass_loss, sheen_glass_loss_average,
    sheen_layer_albedo, COAT_F0,
};
use super::dielectric::RoughDielectric;
use super::diffuse::Diffuse;
use super::microfacet::{g2, half_vector, vndf_reflection_pdf, AnisoGgx, Conductor, MIN_ALPHA};
use super::sheen::Sheen;
use super::specular::Glass;
use super::{flip_z, fresnel_schlick, Bsdf, BsdfSample, Lobe};
use crate::sampling::warp::{
    cosine_hemisphere_pdf, ggx_d, sample_ggx_vndf, square_to_cosine_hemisphere,
};
use glam::{Vec2, Vec3};
use std::f32::consts::FRAC_1_PI;

/// glTF material parameters at one surface point (factors times texture values).
#[derive(Clone, Copy, Debug)]
pub struct GltfParams {
    /// Linear RGB base colour, in [0, 1].
    pub base_color: Vec3,
    /// Metalness, in [0, 1].
    pub metallic: f32,
    /// Perceptual roughness in [0, 1]; the GGX `alpha = roughness²`.
    pub roughness: f32,
    /// KHR_materials_ior, default 1.5 (1.0: no specular reflection).
    pub ior: f32,
    /// KHR_materials_specular `specularFactor` times the texture's alpha, default 1.
    pub specular: f32,
    /// KHR_materials_specular `specularColorFactor` times the texture's rgb, default 1.
    pub specular_color: Vec3,
    /// KHR_materials_transmission factor, default 0.
    pub transmission: f32,
    /// KHR_materials_clearcoat factor, default 0.
    pub clearcoat: f32,
    /// Perceptual clearcoat roughness, default 0.
    pub clearcoat_roughness: f32,
    /// KHR_materials_sheen colour, default 0 (no sheen).
    pub sheen_color: Vec3,
    /// Perceptual sheen roughness, default 0.
    pub sheen_roughness: f32,
    /// Gain of the Lambertian base, default 1: `2 / (1 + ns·ng)` under a normal map, which
    /// returns the part of its cosine lobe about the shading normal that falls below the
    /// geometric surface (docs/rendering.md, "Normal maps and energy").
    pub diffuse_gain: f32,
    /// KHR_materials_anisotropy strength in [0, 1], default 0 (isotropic): the GGX alpha
    /// along [`GltfParams::anisotropy_direction`] is `mix(α, 1, strength²)`, across it `α`.
    pub anisotropy: f32,
    /// The anisotropy direction in the local shading frame (`x`, `y` of a unit tangent
    /// vector; `+z` is the shading normal), default `+x`.
    pub anisotropy_direction: Vec2,
}

impl Default for GltfParams {
    /// The glTF defaults: the spec's default material (white, metallic 1, roughness 1) and
    /// every extension at its default.
    fn default() -> Self {
        GltfParams {
            base_color: Vec3::ONE,
            metallic: 1.0,
            roughness: 1.0,
            ior: 1.5,
            specular: 1.0,
            specular_color: Vec3::ONE,
            transmission: 0.0,
            clearcoat: 0.0,
            clearcoat_roughness: 0.0,
            sheen_color: Vec3::ZERO,
            sheen_roughness: 0.0,
            diffuse_gain: 1.0,
            anisotropy: 0.0,
            anisotropy_direction: Vec2::X,
        }
    }
}

/// The BSDF of the glTF material `p` (see the module documentation). Materials that reduce
/// to one built-in lobe get exactly that lobe: a Lambertian base (`specular = 0`, no metal,
/// transmission, coat or sheen) or plain smooth glass. (A metal is the layered lobe: it
/// carries the multiple-scattering term the built-in conductor does not.)
pub fn gltf_bsdf(p: &GltfParams) -> Bsdf {
    gltf_bsdf_at(p, f32::NAN)
}

/// [`gltf_bsdf`] prepared for the outgoing direction of local `z` coordinate `wo_z` (its
/// cosine with the shading normal): the layered lobe then looks up its albedo tables at
/// `wo` once rather than at every `eval`, `pdf` and `sample` (`GltfLobe::prepare`; the
/// results are bit-identical, and calls with another `wo` stay correct). NaN prepares
/// nothing.
pub fn gltf_bsdf_at(p: &GltfParams, wo_z: f32) -> Bsdf {
    gltf_lobe(p).prepared(wo_z)
}

/// The lobe [`gltf_bsdf`] is made of, not yet prepared for an outgoing direction: a
/// material whose parameters do not vary over its surface has one lobe everywhere, which
/// the render scene builds once ([`GltfBsdf::prepared`] then gives what
/// [`gltf_bsdf_at`] would, bit for bit).
pub fn gltf_lobe(p: &GltfParams) -> GltfBsdf {
    let g = GltfLobe::new(p);
    let layered = g.clearcoat > 0.0 || g.sheen_max > 0.0;
    if !layered {
        let no_spec = g.f0 == Vec3::ZERO && g.f90 == 0.0;
        if g.metal == 0.0 && g.transmit == 0.0 && no_spec {
            return GltfBsdf(Lobe::Diffuse(Diffuse {
                albedo: g.base * g.diffuse_gain,
            }));
        }
        if g.transmit == 1.0 && g.smooth {
            return GltfBsdf(Lobe::Glass(g.glass()));
        }
    }
    GltfBsdf(Lobe::Gltf(g))
}

/// A glTF material's lobe at a point ([`gltf_lobe`]): a Lambertian or smooth-glass lobe
/// where the material reduces to one, else the layered lobe, unprepared.
#[derive(Clone, Copy, Debug)]
pub struct GltfBsdf(Lobe);

impl GltfBsdf {
    /// The BSDF for the outgoing direction of local `z` coordinate `wo_z` (NaN prepares
    /// nothing): the layered lobe looks up its albedo tables at `wo` once
    /// (`GltfLobe::prepare`).
    #[inline]
    pub fn prepared(&self, wo_z: f32) -> Bsdf {
        match &self.0 {
            Lobe::Gltf(g) => {
                let mut g = *g;
                // `Bsdf` hands an opaque lobe `wo` mirrored to the upper hemisphere
                // (`flip_z`).
                let flip = !g.transmits() && wo_z < 0.0;
                g.prepare(if flip { -wo_z } else { wo_z });
                Bsdf::single(Lobe::Gltf(g))
            }
            // The small variant by name, so that only its fields are copied, not the
            // whole enum (about 240 bytes).
            Lobe::Diffuse(d) => Bsdf::single(Lobe::Diffuse(*d)),
            lobe => Bsdf::single(*lobe),
        }
    }
}

/// Indices of the components in [`GltfLobe::select`].
const COAT: usize = 0;
const SHEEN: usize = 1;
const METAL: usize = 2;
const SPEC: usize = 3;
const DIFFUSE: usize = 4;
const GLASS: usize = 5;

/// The layered glTF lobe (see the module documentation); build it with [`gltf_bsdf`].
#[derive(Clone, Copy, Debug)]
pub struct GltfLobe {
    base: Vec3,
    /// [`GltfParams::diffuse_gain`] (one without a normal map).
    diffuse_gain: f32,
    /// GGX alpha of the metal, specular and transmission, at least [`MIN_ALPHA`] (across
    /// the anisotropy direction, for an anisotropic lobe).
    alpha: f32,
    /// `t = strength²` of KHR_materials_anisotropy, zero for an isotropic lobe: the metal's
    /// and the specular layer's GGX has `α_t = α + (1 - α) t` along [`GltfLobe::aniso_dir`]
    /// (the transmission stays isotropic).
    aniso_t: f32,
    /// The anisotropy direction `(cos φ, sin φ)` in the local frame.
    aniso_dir: Vec2,
    /// Weights of the metal, the opaque dielectric and the transmissive dielectric.
    metal: f32,
    opaque: f32,
    transmit: f32,
    /// The specular layer's Schlick `f0` (per channel) and `f90`.
    f0: Vec3,
    f90: f32,
    /// `1 - E_avg` of the specular layer, per channel.
    one_minus_e_avg: Vec3,
    /// `2 ∫ (1 - E(μ)) T(μ) μ dμ` per channel, `E` the specular layer's albedo and `T` the
    /// product of the clearcoat's and the sheen's [`GltfLobe::layers_scale`]: the
    /// normalisation of the diffuse base under those layers (one when there are none).
    layered_avg: Vec3,
    /// Kulla–Conty multiple scattering of the metal: `F_ms / (π (1 - E1_avg))` per
    /// channel (zero without metal).
    ms_scale: Vec3,
    /// Under a clearcoat, the metal's multiple scattering in the layers' reciprocal form
    /// `F_ms (1 - E1(μo)) T(μo) (1 - E1(μi)) T(μi) / (π 2 ∫ (1 - E1) T μ dμ)`: this is the
    /// `F_ms / (π ...)` factor (zero without a coated metal).
    ms_coated: Vec3,
    /// Under a clearcoat, what the metal's single scattering loses to the coat's `min`
    /// factor, returned as `coat_metal D(μo) D(μi) cos θi` with `D` = [`coat_loss`]: this
    /// is `metal clearcoat F_avg / (π D_avg)` (zero without a coated metal).
    coat_metal: Vec3,
    /// The GGX alpha the coat-loss table is looked up at (the metal's; the root mean
    /// square of the two for an anisotropic one).
    alpha_loss: f32,
    /// Under a clearcoat or a sheen, rough transmission met from inside: what the layers
    /// reflect back of the light the interface sends out, `R(μ) = glass_gain ℓ(μ)`
    /// ([`GltfLobe::glass_loss`] is `ℓ`), returned inside as the lobe
    /// `coat_glass ℓ(μo) ℓ(μi) cos θi`; this is `transmit glass_gain / (π ℓ_avg)` (zero
    /// without a layered rough transmission).
    coat_glass: f32,
    /// `R / ℓ`: the clearcoat factor under a clearcoat alone (`ℓ` = [`coat_glass_loss`]),
    /// one with a sheen (`ℓ = R`, see [`GltfLobe::coat_the_glass`]).
    glass_gain: f32,
    /// Relative index of refraction of the transmissive part.
    eta: f32,
    /// Transmission through a smooth interface (a delta component).
    smooth: bool,
    clearcoat: f32,
    alpha_cc: f32,
    sheen: Sheen,
    sheen_r: f32,
    /// `max(sheen_color)`, the weight of the sheen's albedo scaling.
    sheen_max: f32,
    /// The terms that depend on `wo` alone, for the `wo` of [`GltfLobe::prepare`].
    at_wo: WoTerms,
}

/// The albedo tables of a [`GltfLobe`] at the outgoing direction: the specular layer's and
/// the metal's at `μo`. A path vertex evaluates its BSDF several times with one `wo` (the
/// light sample's `eval` and `pdf`, the BSDF sample's `select`, `pdf` and `eval`), each of
/// which would look them up again; [`GltfLobe::prepare`] looks them up once, with the same
/// functions, so a prepared lobe gives bit-identical results. Kept small: the lobe is
/// copied with every path vertex.
#[derive(Clone, Copy, Debug)]
struct WoTerms {
    /// The `wo.z` these terms are for; NaN (equal to nothing) until prepared.
    z: f32,
    /// [`GltfLobe::spec_albedo`] at `|wo.z|` (zero without an opaque dielectric).
    spec_albedo: Vec3,
    /// [`GltfLobe::ms_loss`] at `|wo.z|` (zero without metal).
    ms_loss: f32,
}

impl WoTerms {
    const UNPREPARED: WoTerms = WoTerms {
        z: f32::NAN,
        spec_albedo: Vec3::ZERO,
        ms_loss: 0.0,
    };
}

/// GGX reflection with Schlick's Fresnel `f0 + (f90 - f0)(1 - wo·h)^5`, times `cos θi`.
#[inline]
fn ggx_reflection(wo: Vec3, wi: Vec3, alpha: f32, f0: Vec3, f90: f32) -> Vec3 {
    if wo.z <= 0.0 || wi.z <= 0.0 {
        return Vec3::ZERO;
    }
    let Some(h) = half_vector(wo, wi) else {
        return Vec3::ZERO;
    };
    let m = (1.0 - wo.dot(h).clamp(0.0, 1.0)).powi(5);
    let f = f0 + (Vec3::splat(f90) - f0) * m;
    f * (ggx_d(h, alpha) * g2(wo, wi, alpha) / (4.0 * wo.z))
}

#[inline]
fn ggx_pdf(wo: Vec3, wi: Vec3, alpha: f32) -> f32 {
    if wo.z <= 0.0 || wi.z <= 0.0 {
        return 0.0;
    }
    half_vector(wo, wi).map_or(0.0, |h| vndf_reflection_pdf(wo, h, alpha))
}

impl GltfLobe {
    /// The lobe of `p`, with the parameters clamped to their ranges.
    pub fn new(p: &GltfParams) -> Self {
        let c01 = |x: f32| x.clamp(0.0, 1.0);
        let base = p.base_color.clamp(Vec3::ZERO, Vec3::ONE);
        let metal = c01(p.metallic);
        let transmission = c01(p.transmission);
        let alpha_raw = c01(p.roughness).powi(2);
        let alpha = alpha_raw.max(MIN_ALPHA);
        let ior = p.ior.max(1.0);
        let specular = c01(p.specular);
        let r0 = ((ior - 1.0) / (ior + 1.0)).powi(2);
        let f0 = (r0 * p.specular_color.max(Vec3::ZERO)).min(Vec3::ONE) * specular;
        let f90 = if ior > 1.0 { specular } else { 0.0 };
        let opaque = (1.0 - metal) * (1.0 - transmission);
        // Anisotropy only where it changes the lobe: a strength of zero, or a roughness of
        // one (`mix(1, 1, t) = 1`), is the isotropic lobe to the bit.
        let strength = c01(p.anisotropy);
        let aniso_dir = p.anisotropy_direction.try_normalize();
        let aniso_t = match aniso_dir {
            Some(_) if alpha < 1.0 && (metal > 0.0 || opaque > 0.0) => strength * strength,
            _ => 0.0,
        };
        let aniso_dir = aniso_dir.unwrap_or(Vec2::X);
        let albedo_average = |alpha: f32| {
            if aniso_t > 0.0 {
                anisotropic_ggx_albedo_average(alpha, aniso_t)
            } else {
                ggx_albedo_average(alpha)
            }
        };
        // The tables are only touched when a specular layer lies over a diffuse base.
        let one_minus_e_avg = if opaque > 0.0 && (f0 != Vec3::ZERO || f90 > 0.0) {
            let (a_avg, b_avg) = albedo_average(alpha);
            (Vec3::ONE - (f0 * a_avg + Vec3::splat(f90 * b_avg))).max(Vec3::ZERO)
        } else {
            Vec3::ONE
        };
        // Kulla & Conty 2017: the energy single-scattering GGX loses, E1 being the albedo
        // with F = 1, returned as a lobe shaped like (1 - E1(μo))(1 - E1(μi)) and coloured
        // by the average Fresnel's geometric series F_ms.
        let ms_scale = if metal > 0.0 {
            let (a_avg, b_avg) = albedo_average(alpha);
            let e_avg = (a_avg + b_avg).clamp(0.0, 1.0 - 1e-4);
            let f_avg = base + (Vec3::ONE - base) / 21.0;
            let f_ms = f_avg * f_avg * e_avg / (Vec3::ONE - f_avg * (1.0 - e_avg));
            f_ms * (FRAC_1_PI / (1.0 - e_avg))
        } else {
            Vec3::ZERO
        };
        let sheen_color = p.sheen_color.clamp(Vec3::ZERO, Vec3::ONE);
        let sheen = Sheen::new(sheen_color, p.sheen_roughness);
        // The albedo table is looked up at the roughness the lobe uses.
        let sheen_r = sheen.alpha.sqrt();
        let mut lobe = GltfLobe {
            base,
            diffuse_gain: p.diffuse_gain.max(0.0),
            alpha,
            aniso_t,
            aniso_dir,
            metal,
            opaque,
            transmit: (1.0 - metal) * transmission,
            f0,
            f90,
            one_minus_e_avg,
            layered_avg: Vec3::ONE,
            ms_scale,
            ms_coated: Vec3::ZERO,
            coat_metal: Vec3::ZERO,
            alpha_loss: alpha,
            coat_glass: 0.0,
            glass_gain: 0.0,
            eta: ior,
            smooth: alpha_raw < MIN_ALPHA || ior - 1.0 < 1e-3,
            clearcoat: c01(p.clearcoat),
            alpha_cc: c01(p.clearcoat_roughness).powi(2).max(MIN_ALPHA),
            sheen,
            sheen_r,
            sheen_max: sheen_color.max_element(),
            at_wo: WoTerms::UNPREPARED,
        };
        if lobe.layered() && lobe.opaque > 0.0 {
            lobe.layered_avg = lobe.layered_average();
        }
        if lobe.clearcoat > 0.0 && metal > 0.0 {
            lobe.coat_the_metal();
        }
        if lobe.layered() && lobe.transmit > 0.0 && !lobe.smooth {
            lobe.coat_the_glass();
        }
        lobe
    }

    /// The clearcoat over rough transmission, seen from inside: light the interface sends
    /// out crosses the coat with `T(μt) = 1 - clearcoat E_cc(μt)` (as light entering
    /// does, so that the transmission stays reciprocal), and the rest, `clearcoat G(μo)`
    /// at the inside cosine `μo` ([`coat_glass_loss`]), is what the coat reflects back.
    /// It returns inside as Kulla & Conty 2017's reciprocal lobe for lost energy,
    /// `clearcoat G(μo) G(μi) / (π G_avg)` per unit transmission, whose albedo is
    /// `clearcoat G(μo)`: a white coated rough glass then keeps its energy from inside,
    /// as [`GltfLobe::sample_smooth_exit`] does for a smooth interface. Both directions
    /// are inside, so the lobe is symmetric (no `η²`: it never crosses the interface) and
    /// untinted, as the smooth exit's reflection.
    ///
    /// A sheen (weight `s = max(sheen_color)`) crosses with `1 - s E_sh(μt)` and
    /// reflects back `s G_sh(μo)` ([`sheen_glass_loss`]), returned the same way. Under
    /// both, the light crosses with `(1 - c E_cc)(1 - s E_sh)`, so the layers reflect back
    /// `c E_cc + s E_sh - c s E_cc E_sh` of each exit direction: the two returns
    /// `c G + s G_sh` count the product term's share `c s ∫ E_cc E_sh dP` twice. It
    /// depends on both roughnesses and is not tabulated; `H(μo)` of [`sheen_glass_loss`]
    /// bounds it from above (the sheen weighted by the largest coat albedo at each
    /// angle), so the lobe returns `R = c G + s G_sh - c s H`, never more than the
    /// layers reflect (white glass stays at or below one) and at least `c G` (as
    /// `H <= G_sh`). The lobe is linear in `R`'s average, so `R_avg` is the same
    /// combination of the tables' averages.
    fn coat_the_glass(&mut self) {
        if self.sheen_max == 0.0 {
            // A clearcoat alone: `ℓ = G`, `R = c G`.
            let g_avg = coat_glass_loss_average(self.alpha, self.eta, self.alpha_cc);
            if g_avg > 1e-6 {
                self.glass_gain = self.clearcoat;
                self.coat_glass = self.transmit * self.clearcoat * FRAC_1_PI / g_avg;
            }
            return;
        }
        let (c, s) = (self.clearcoat, self.sheen_max);
        let (sh_avg, h_avg) = sheen_glass_loss_average(self.alpha, self.eta, self.sheen_r);
        let mut r_avg = s * sh_avg;
        if c > 0.0 {
            r_avg +=
                c * coat_glass_loss_average(self.alpha, self.eta, self.alpha_cc) - c * s * h_avg;
        }
        if r_avg > 1e-6 {
            self.glass_gain = 1.0;
            self.coat_glass = self.transmit * FRAC_1_PI / r_avg;
        }
    }

    /// `ℓ(μ)` of [`GltfLobe::coat_the_glass`] at this lobe's roughness, index and layers:
    /// `G(μ)` under a clearcoat alone, `R(μ) = c G + s G_sh - c s H` with a sheen.
    #[inline]
    fn glass_loss(&self, mu: f32) -> f32 {
        let coat = |mu| coat_glass_loss(mu, self.alpha, self.eta, self.alpha_cc);
        if self.sheen_max == 0.0 {
            return coat(mu);
        }
        let (c, s) = (self.clearcoat, self.sheen_max);
        let (g_sh, h) = sheen_glass_loss(mu, self.alpha, self.eta, self.sheen_r);
        let mut r = s * g_sh;
        if c > 0.0 {
            r += c * coat(mu) - c * s * h;
        }
        r.max(0.0)
    }

    /// The clearcoat's scaling of a metal: its multiple scattering in the layers'
    /// reciprocal form (a cosine-like lobe: the `min` factor lost 2-4% of it, as it did
    /// of a Lambertian base), and the compensation of what the `min` factor takes from its
    /// single scattering, which is sharp: `D(μ)` per unit clearcoat factor, tabulated
    /// ([`coat_loss`]), returned as the reciprocal lobe `D(μo) D(μi) / (π D_avg)` (Kulla &
    /// Conty 2017's form for lost energy). A white metal under a coat then reflects
    /// `E_cc(μo) + (1 - E_cc(μo))` up to the tables.
    fn coat_the_metal(&mut self) {
        // F_ms / π(1 - E1_avg) is ms_scale; F_ms / (π L) with L = 2 ∫ (1 - E1) T μ dμ.
        let e_avg_loss = {
            let (a, b) = if self.anisotropic() {
                anisotropic_ggx_albedo_average(self.alpha, self.aniso_t)
            } else {
                ggx_albedo_average(self.alpha)
            };
            (1.0 - (a + b).clamp(0.0, 1.0 - 1e-4)).max(1e-4)
        };
        const N: usize = 32;
        let mut l = 0.0;
        for k in 0..N {
            let x = (k as f32 + 0.5) / N as f32;
            let mu = x * x;
            l += self.ms_loss_azimuthal(mu) * self.layers_scale(mu) * (4.0 * x * x * x / N as f32);
        }
        self.ms_coated = self.ms_scale * (e_avg_loss / l.max(1e-6));
        let (ax, ay) = anisotropic_alphas(self.alpha, self.aniso_t);
        self.alpha_loss = ((ax * ax + ay * ay) / 2.0).sqrt();
        let d_avg = coat_loss_average(self.alpha_loss, self.alpha_cc);
        if d_avg > 1e-6 {
            let f_avg = self.base + (Vec3::ONE - self.base) / 21.0;
            self.coat_metal = f_avg * (self.metal * self.clearcoat * FRAC_1_PI / d_avg);
        }
    }

    /// `1 - E1(μ)` of [`GltfLobe::ms_loss`] averaged over the azimuth.
    fn ms_loss_azimuthal(&self, mu: f32) -> f32 {
        let (a, b) = if self.anisotropic() {
            anisotropic_ggx_albedo_azimuthal(mu, self.alpha, self.aniso_t)
        } else {
            ggx_albedo(mu, self.alpha)
        };
        (1.0 - a - b).max(0.0)
    }

    /// True if a clearcoat or a sheen lies over the base.
    #[inline]
    fn layered(&self) -> bool {
        self.clearcoat > 0.0 || self.sheen_max > 0.0
    }

    /// `1 - E` of the layers over the base at `μ`: the product of the clearcoat's and the
    /// sheen's albedo scaling.
    #[inline]
    fn layers_scale(&self, mu: f32) -> f32 {
        self.coat_scale(mu) * self.sheen_scale(mu)
    }

    /// [`GltfLobe::layered_avg`] by the midpoint rule in `x = sqrt(μ)` (`2 μ dμ = 4 x³ dx`;
    /// the tables are linear in `x`, so 32 points leave an error far below their own).
    fn layered_average(&self) -> Vec3 {
        const N: usize = 32;
        let mut sum = Vec3::ZERO;
        for k in 0..N {
            let x = (k as f32 + 0.5) / N as f32;
            let mu = x * x;
            let t = (Vec3::ONE - self.spec_albedo_azimuthal(mu)) * self.layers_scale(mu);
            sum += t * (4.0 * x * x * x / N as f32);
        }
        sum
    }

    /// Computes the terms that depend on `wo` alone once, for every later call with a
    /// `wo` of the same `z` (see [`WoTerms`]); calls with another `wo` compute their own.
    #[inline]
    pub(crate) fn prepare(&mut self, wo_z: f32) {
        // An anisotropic lobe's albedos depend on the azimuth of `wo` too: not prepared.
        if wo_z.is_nan() || self.anisotropic() {
            return;
        }
        let (spec_albedo, ms_loss) = self.albedos(Vec3::new(0.0, 0.0, wo_z.abs()));
        self.at_wo = WoTerms {
            z: wo_z,
            spec_albedo,
            ms_loss,
        };
    }

    /// [`GltfLobe::spec_albedo`] at `wo.z >= 0`, prepared or looked up.
    #[inline]
    fn spec_albedo_wo(&self, wo: Vec3) -> Vec3 {
        if wo.z == self.at_wo.z {
            self.at_wo.spec_albedo
        } else {
            self.spec_albedo(wo)
        }
    }

    /// [`GltfLobe::ms_loss`] at `wo.z >= 0`, prepared or looked up.
    #[inline]
    fn ms_loss_wo(&self, wo: Vec3) -> f32 {
        if wo.z == self.at_wo.z {
            self.at_wo.ms_loss
        } else {
            self.ms_loss(wo)
        }
    }

    /// True if part of the light is transmitted (the lobe is then not two-sided).
    #[inline]
    pub(crate) fn transmits(&self) -> bool {
        self.transmit > 0.0
    }

    /// True if every component is a delta distribution.
    #[inline]
    pub(crate) fn is_pure_delta(&self) -> bool {
        self.smooth && self.transmit == 1.0 && self.clearcoat == 0.0 && self.sheen_max == 0.0
    }

    /// The relative index of refraction of the transmissive part, if any.
    #[inline]
    pub(crate) fn eta(&self) -> Option<f32> {
        self.transmits().then_some(self.eta)
    }

    fn conductor(&self) -> Conductor {
        Conductor {
            f0: self.base,
            alpha: self.alpha,
        }
    }

    fn glass(&self) -> Glass {
        Glass {
            eta: self.eta,
            tint: self.base,
        }
    }

    fn rough_glass(&self) -> RoughDielectric {
        RoughDielectric {
            eta: self.eta,
            alpha: self.alpha,
            tint: self.base,
        }
    }

    /// True if the metal's and the specular layer's GGX is anisotropic.
    #[inline]
    fn anisotropic(&self) -> bool {
        self.aniso_t > 0.0
    }

    /// `w` in the frame whose `+x` is the anisotropy direction (a rotation about `z`).
    #[inline]
    fn aligned(&self, w: Vec3) -> Vec3 {
        let (c, s) = (self.aniso_dir.x, self.aniso_dir.y);
        Vec3::new(c * w.x + s * w.y, c * w.y - s * w.x, w.z)
    }

    /// The inverse of [`GltfLobe::aligned`].
    #[inline]
    fn unaligned(&self, w: Vec3) -> Vec3 {
        let (c, s) = (self.aniso_dir.x, self.aniso_dir.y);
        Vec3::new(c * w.x - s * w.y, s * w.x + c * w.y, w.z)
    }

    /// The anisotropic GGX of the metal and the specular layer, in the aligned frame.
    #[inline]
    fn aniso_ggx(&self) -> AnisoGgx {
        let (ax, ay) = anisotropic_alphas(self.alpha, self.aniso_t);
        AnisoGgx { ax, ay }
    }

    /// GGX reflection at the base roughness (the metal's and the specular layer's), with
    /// Schlick's Fresnel from `f0` to `f90`, times `cos θi`.
    #[inline]
    fn base_reflection(&self, wo: Vec3, wi: Vec3, f0: Vec3, f90: f32) -> Vec3 {
        if self.anisotropic() {
            self.aniso_ggx()
                .reflection(self.aligned(wo), self.aligned(wi), f0, f90)
        } else {
            ggx_reflection(wo, wi, self.alpha, f0, f90)
        }
    }

    /// Single-scattering GGX of the metal (Schlick's Fresnel from the base colour).
    #[inline]
    fn metal_single(&self, wo: Vec3, wi: Vec3) -> Vec3 {
        if self.anisotropic() {
            self.base_reflection(wo, wi, self.base, 1.0)
        } else {
            self.conductor().eval(wo, wi)
        }
    }

    /// Density of sampling `wi` by reflecting `wo` about a visible normal of the base GGX.
    #[inline]
    fn base_pdf(&self, wo: Vec3, wi: Vec3) -> f32 {
        if self.anisotropic() {
            self.aniso_ggx()
                .reflection_pdf(self.aligned(wo), self.aligned(wi))
        } else {
            ggx_pdf(wo, wi, self.alpha)
        }
    }

    /// Reflects `wo` (upper hemisphere) about a visible normal of the base GGX drawn by `u`.
    #[inline]
    fn base_sample(&self, wo: Vec3, u: Vec2) -> Vec3 {
        let h = if self.anisotropic() {
            self.unaligned(self.aniso_ggx().sample_vndf(self.aligned(wo), u))
        } else {
            sample_ggx_vndf(wo, self.alpha, u)
        };
        crate::math::reflect(wo, h)
    }

    /// `(A, B)` of the base GGX seen from `w` ([`ggx_albedo`], or
    /// [`anisotropic_ggx_albedo`] at `w`'s azimuth from the anisotropy direction).
    #[inline]
    fn ggx_table(&self, w: Vec3) -> (f32, f32) {
        if self.anisotropic() {
            anisotropic_ggx_albedo(self.aligned(w), self.alpha, self.aniso_t)
        } else {
            ggx_albedo(w.z.abs(), self.alpha)
        }
    }

    /// The specular layer's albedo `E(w)` per channel (a function of `μ = |w.z|` alone
    /// for an isotropic lobe).
    #[inline]
    fn spec_albedo(&self, w: Vec3) -> Vec3 {
        if self.f90 == 0.0 && self.f0 == Vec3::ZERO {
            return Vec3::ZERO;
        }
        let (a, b) = self.ggx_table(w);
        self.f0 * a + Vec3::splat(self.f90 * b)
    }

    /// [`GltfLobe::spec_albedo`] at `μ` averaged over the azimuth.
    #[inline]
    fn spec_albedo_azimuthal(&self, mu: f32) -> Vec3 {
        if !self.anisotropic() {
            return self.spec_albedo(Vec3::new(0.0, 0.0, mu));
        }
        if self.f90 == 0.0 && self.f0 == Vec3::ZERO {
            return Vec3::ZERO;
        }
        let (a, b) = anisotropic_ggx_albedo_azimuthal(mu, self.alpha, self.aniso_t);
        self.f0 * a + Vec3::splat(self.f90 * b)
    }

    /// `1 - E1(w)`: what single-scattering GGX at the metal's roughness loses seen from `w`.
    #[inline]
    fn ms_loss(&self, w: Vec3) -> f32 {
        let (a, b) = self.ggx_table(w);
        (1.0 - a - b).max(0.0)
    }

    /// `1 - clearcoat E_cc(μ)`.
    #[inline]
    fn coat_scale(&self, mu: f32) -> f32 {
        if self.clearcoat == 0.0 {
            return 1.0;
        }
        let (a, b) = ggx_albedo(mu, self.alpha_cc);
        (1.0 - self.clearcoat * (COAT_F0 * a + b)).max(0.0)
    }

    /// `1 - max(sheen_color) E_sheen(μ)`, `E_sheen` the albedo of the sheen lobe as rendered
    /// (normalised, [`sheen_layer_albedo`]).
    #[inline]
    fn sheen_scale(&self, mu: f32) -> f32 {
        if self.sheen_max == 0.0 {
            return 1.0;
        }
        (1.0 - self.sheen_max * sheen_layer_albedo(mu, self.sheen_r).min(1.0)).max(0.0)
    }

    /// Metal, specular layer and diffuse base, `wo` and `wi` in the upper hemisphere.
    fn opaque_eval(&self, wo: Vec3, wi: Vec3) -> Vec3 {
        let mut f = Vec3::ZERO;
        if self.metal > 0.0 {
            let ms = self.ms_scale * (self.ms_loss_wo(wo) * self.ms_loss(wi) * wi.z);
            f += self.metal * (self.metal_single(wo, wi) + ms);
        }
        if self.opaque > 0.0 {
            let spec = self.base_reflection(wo, wi, self.f0, self.f90);
            // Kulla & Conty 2017: the base receives what the layer does not reflect, in
            // the reciprocal form (1 - E(μo))(1 - E(μi)) / (1 - E_avg).
            let eo = Vec3::ONE - self.spec_albedo_wo(wo);
            let ei = Vec3::ONE - self.spec_albedo(wi);
            let scale = (eo * ei / self.one_minus_e_avg.max(Vec3::splat(1e-6))).max(Vec3::ZERO);
            let diffuse = self.base * scale * (self.diffuse_gain * FRAC_1_PI * wi.z);
            f += self.opaque * (spec + diffuse);
        }
        f
    }

    /// [`GltfLobe::opaque_eval`] under a clearcoat or a sheen, as its sharp parts (metal
    /// and specular layer, which the caller scales by the layers' `min` factors) and the
    /// diffuse base, which gets the layers' albedo scaling in Kulla & Conty's reciprocal
    /// form with the specular layer's: `(1 - E(μo)) T(μo) (1 - E(μi)) T(μi) /
    /// layered_avg`, so that it returns exactly what the specular layer, the coat and the
    /// sheen do not reflect (`T` is [`GltfLobe::layers_scale`]).
    fn layered_opaque_eval(&self, wo: Vec3, wi: Vec3) -> (Vec3, Vec3) {
        let mut sharp = Vec3::ZERO;
        let mut diffuse = Vec3::ZERO;
        if self.metal > 0.0 {
            sharp += self.metal * self.metal_single(wo, wi);
            let loss = self.ms_loss_wo(wo) * self.ms_loss(wi) * wi.z;
            if self.ms_coated == Vec3::ZERO {
                sharp += self.metal * self.ms_scale * loss;
            } else {
                let t = self.layers_scale(wo.z) * self.layers_scale(wi.z);
                diffuse += self.metal * self.ms_coated * (loss * t);
            }
        }
        if self.opaque > 0.0 {
            sharp += self.opaque * self.base_reflection(wo, wi, self.f0, self.f90);
            let eo = (Vec3::ONE - self.spec_albedo_wo(wo)) * self.layers_scale(wo.z);
            let ei = (Vec3::ONE - self.spec_albedo(wi)) * self.layers_scale(wi.z);
            let scale = (eo * ei / self.layered_avg.max(Vec3::splat(1e-6))).max(Vec3::ZERO);
            diffuse += self.opaque * self.base * scale * (self.diffuse_gain * FRAC_1_PI * wi.z);
        }
        (sharp, diffuse)
    }

    /// The coated metal's compensation `coat_metal D(μo) D(μi) μi` (see
    /// [`GltfLobe::coat_the_metal`]), both directions outside.
    #[inline]
    fn coat_compensation(&self, mo: f32, mi: f32) -> Vec3 {
        if self.coat_metal == Vec3::ZERO {
            return Vec3::ZERO;
        }
        let d = |mu| coat_loss(mu, self.alpha_loss, self.alpha_cc);
        self.coat_metal * (d(mo) * d(mi) * mi)
    }

    /// Component selection probabilities at `wo` (estimates of their albedos), in the
    /// order [`COAT`], [`SHEEN`], [`METAL`], [`SPEC`], [`DIFFUSE`], [`GLASS`].
    #[inline]
    fn select(&self, wo: Vec3) -> [f32; 6] {
        if wo.z == self.at_wo.z {
            self.select_with(wo, self.at_wo.spec_albedo, self.at_wo.ms_loss)
        } else {
            let (e, ms) = self.albedos(wo);
            self.select_with(wo, e, ms)
        }
    }

    /// The specular layer's albedo and the metal's loss seen from `w`, where the lobe has
    /// them.
    #[inline]
    fn albedos(&self, w: Vec3) -> (Vec3, f32) {
        let e = if self.opaque > 0.0 {
            self.spec_albedo(w)
        } else {
            Vec3::ZERO
        };
        let ms = if self.metal > 0.0 {
            self.ms_loss(w)
        } else {
            0.0
        };
        (e, ms)
    }

    /// [`GltfLobe::select`] from the [`GltfLobe::albedos`] at `|wo.z|`.
    fn select_with(&self, wo: Vec3, spec_albedo: Vec3, ms_loss: f32) -> [f32; 6] {
        let outside = wo.z > 0.0;
        let mu = wo.z.abs();
        let mut w = [0.0f32; 6];
        let mut under = 1.0;
        if outside {
            if self.clearcoat > 0.0 {
                w[COAT] = 1.0 - self.coat_scale(mu);
                under = self.coat_scale(mu);
            }
            if self.sheen_max > 0.0 {
                w[SHEEN] = under * self.sheen_max * sheen_layer_albedo(mu, self.sheen_r).min(1.0);
                under *= self.sheen_scale(mu);
            }
        }
        if self.metal > 0.0 {
            let f = fresnel_schlick(self.base, mu).max_element();
            w[METAL] = under * self.metal * f.max(0.05);
            if outside && self.coat_metal != Vec3::ZERO {
                // The coat compensation is cosine-like too; its albedo is
                // coat_metal π D_avg D(μo).
                let d_avg = coat_loss_average(self.alpha_loss, self.alpha_cc);
                let d = coat_loss(mu, self.alpha_loss, self.alpha_cc);
                w[DIFFUSE] += self.coat_metal.max_element() * std::f32::consts::PI * d_avg * d;
            }
            // The multiple-scattering lobe is cosine-like: sampled with the diffuse one.
            // Its albedo is ms_scale π (1 - E1(μo)) (1 - E1_avg) <= F_ms (1 - E1(μo)).
            let ms = self.ms_scale.max_element() * std::f32::consts::PI * ms_loss;
            w[DIFFUSE] += under * self.metal * ms;
        }
        if self.opaque > 0.0 {
            let e = spec_albedo;
            w[SPEC] = under * self.opaque * e.max_element();
            w[DIFFUSE] += under
                * self.opaque
                * (self.base * (Vec3::ONE - e)).max_element()
                * self.diffuse_gain;
        }
        if !outside && self.coat_glass > 0.0 {
            // The layers' return inside is cosine-like; its albedo is transmit R(μo).
            w[DIFFUSE] += self.transmit * self.glass_gain * self.glass_loss(mu);
        }
        w[GLASS] = under * self.transmit;
        let total: f32 = w.iter().sum();
        if total > 0.0 {
            for x in &mut w {
                *x /= total;
            }
        }
        w
    }

    /// `f(wo, wi) |cos θi|` of the non-delta components.
    pub(crate) fn eval(&self, wo: Vec3, wi: Vec3) -> Vec3 {
        if wo.z == 0.0 || wi.z == 0.0 {
            return Vec3::ZERO;
        }
        let glass = |wo, wi| {
            if self.transmit > 0.0 && !self.smooth {
                self.transmit * self.rough_glass().eval(wo, wi)
            } else {
                Vec3::ZERO
            }
        };
        match (wo.z > 0.0, wi.z > 0.0) {
            (true, true) => {
                if !self.layered() {
                    return self.opaque_eval(wo, wi) + glass(wo, wi);
                }
                let (mo, mi) = (wo.z, wi.z);
                let (sharp, diffuse) = self.layered_opaque_eval(wo, wi);
                let mut f = sharp + glass(wo, wi);
                if self.sheen_max > 0.0 {
                    let g_sh = self.sheen_scale(mo).min(self.sheen_scale(mi));
                    f = self.sheen.eval(wo, wi) + g_sh * f;
                }
                if self.clearcoat > 0.0 {
                    let g_cc = self.coat_scale(mo).min(self.coat_scale(mi));
                    let coat = ggx_reflection(wo, wi, self.alpha_cc, Vec3::splat(COAT_F0), 1.0);
                    f = self.clearcoat * coat + g_cc * f;
                }
                f + diffuse + self.coat_compensation(mo, mi)
            }
            // Inside a transmissive material: the opaque parts are two-sided.
            (false, false) => {
                if !self.transmits() {
                    return Vec3::ZERO;
                }
                let f = self.opaque_eval(flip_z(wo, true), flip_z(wi, true)) + glass(wo, wi);
                if self.coat_glass == 0.0 {
                    return f;
                }
                let (mo, mi) = (-wo.z, -wi.z);
                let back = self.glass_loss(mo) * self.glass_loss(mi) * mi;
                f + Vec3::splat(self.coat_glass * back)
            }
            (o, _) => {
                let out = if o { wo.z } else { wi.z };
                self.coat_scale(out) * self.sheen_scale(out) * glass(wo, wi)
            }
        }
    }

    /// Solid-angle density of [`GltfLobe::sample`]'s non-delta components.
    pub(crate) fn pdf(&self, wo: Vec3, wi: Vec3) -> f32 {
        if wo.z == 0.0 || wi.z == 0.0 {
            return 0.0;
        }
        self.pdf_with(&self.select(wo), wo, wi)
    }

    /// [`GltfLobe::pdf`] with the selection weights `w = select(wo)` already at hand.
    fn pdf_with(&self, w: &[f32; 6], wo: Vec3, wi: Vec3) -> f32 {
        let glass = if self.smooth || w[GLASS] == 0.0 {
            0.0
        } else {
            w[GLASS] * self.rough_glass().pdf(wo, wi)
        };
        if wo.z * wi.z < 0.0 {
            return glass;
        }
        let flip = wo.z < 0.0;
        let (wo, wi) = (flip_z(wo, flip), flip_z(wi, flip));
        let cos = cosine_hemisphere_pdf(wi.z);
        let ggx = self.base_pdf(wo, wi);
        let mut p = glass + (w[METAL] + w[SPEC]) * ggx + (w[DIFFUSE] + w[SHEEN]) * cos;
        if w[COAT] > 0.0 {
            p += w[COAT] * ggx_pdf(wo, wi, self.alpha_cc);
        }
        p
    }

    /// The smooth interface under a clearcoat or a sheen, met from inside (`wo.z < 0`),
    /// chosen with probability `w_glass`. Light refracted outward crosses the layers with
    /// `T(μt) = coat_scale(μt) sheen_scale(μt)` (`μt` the outside cosine), as light entering
    /// does, so that the transmission stays reciprocal; the rest, `(1 - F)(1 - T)`, is what
    /// the layers reflect back, and returns inside along the interface's mirror direction
    /// (a smooth coat over a smooth interface reflects specularly; a rough one's spread is
    /// neglected). Without it a coated glass sphere lost `1 - T` at every exit: 18% of a
    /// white furnace. Reflection `F + (1 - F)(1 - T)`, refraction `(1 - F) T`: one in all.
    fn sample_smooth_exit(&self, wo: Vec3, u1: f32, w_glass: f32) -> Option<BsdfSample> {
        let glass = self.glass();
        let f = super::fresnel_dielectric(wo.z, glass.eta);
        let mirror = Vec3::new(-wo.x, -wo.y, wo.z);
        // The refracted direction's outside cosine (none under total internal reflection).
        let inv = glass.eta;
        let sin2_t = (1.0 - wo.z * wo.z).max(0.0) * inv * inv;
        let (p_reflect, refracted) = if f >= 1.0 || sin2_t >= 1.0 {
            (1.0, None)
        } else {
            let cos_t = (1.0 - sin2_t).sqrt();
            let t = self.coat_scale(cos_t) * self.sheen_scale(cos_t);
            let wi = Vec3::new(-wo.x * inv, -wo.y * inv, cos_t);
            (1.0 - (1.0 - f) * t, Some(wi))
        };
        let scale = self.transmit / w_glass;
        match refracted {
            Some(wi) if u1 >= p_reflect => Some(BsdfSample {
                // Radiance leaving the denser side: `(η_i/η_t)² = η²`, as `Glass::sample`.
                wi,
                weight: glass.tint * (inv * inv) * scale,
                pdf: w_glass * (1.0 - p_reflect),
                delta: true,
            }),
            _ => Some(BsdfSample {
                wi: mirror,
                weight: Vec3::splat(scale),
                pdf: w_glass * p_reflect,
                delta: true,
            }),
        }
    }

    /// Samples a component by `u1` (rescaled and reused by the component), then its
    /// direction by `u2`.
    #[inline]
    pub(crate) fn sample(&self, wo: Vec3, u1: f32, u2: Vec2) -> Option<BsdfSample> {
        if wo.z == 0.0 {
            return None;
        }
        let w = self.select(wo);
        // The last component with a weight takes the rounding remainder of the sum.
        let last = w.iter().rposition(|&x| x > 0.0)?;
        let (mut k, mut lo) = (last, 0.0);
        for (i, &wi) in w.iter().enumerate() {
            if wi > 0.0 && (u1 < lo + wi || i == last) {
                k = i;
                break;
            }
            lo += wi;
        }
        let u1 = ((u1 - lo) / w[k]).clamp(0.0, 1.0 - f32::EPSILON);
        let flip = wo.z < 0.0;
        let wo_up = flip_z(wo, flip);
        let wi = match k {
            GLASS if self.smooth && wo.z < 0.0 && self.layered() => {
                return self.sample_smooth_exit(wo, u1, w[GLASS]);
            }
            GLASS if self.smooth => {
                let (wi, weight, p) = self.glass().sample(wo, u1)?;
                // The layers on the outside scale the interface: reflection at wo's
                // angle from outside (the mirror direction has the same cosine), and the
                // outside direction of a refraction.
                let out = if wo.z > 0.0 {
                    Some(wo.z)
                } else if wi.z > 0.0 {
                    Some(wi.z)
                } else {
                    None
                };
                let layers = out.map_or(1.0, |mu| self.coat_scale(mu) * self.sheen_scale(mu));
                return Some(BsdfSample {
                    wi,
                    weight: weight * (self.transmit * layers / w[GLASS]),
                    pdf: w[GLASS] * p,
                    delta: true,
                });
            }
            GLASS => self.rough_glass().sample(wo, u1, u2)?.0,
            COAT => crate::math::reflect(wo_up, sample_ggx_vndf(wo_up, self.alpha_cc, u2)),
            METAL | SPEC => self.base_sample(wo_up, u2),
            _ => square_to_cosine_hemisphere(u2),
        };
        let wi = if k == GLASS { wi } else { flip_z(wi, flip) };
        if wi.z == 0.0 || (k != GLASS && wi.z * wo.z <= 0.0) {
            return None;
        }
        // `pdf` would select again: the weights are those of this `wo`.
        let pdf = self.pdf_with(&w, wo, wi);
        if pdf <= 0.0 || !pdf.is_finite() {
            return None;
        }
        Some(BsdfSample {
            wi,
            weight: self.eval(wo, wi) / pdf,
            pdf,
            delta: false,
        })
    }
}
