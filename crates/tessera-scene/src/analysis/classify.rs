//! Step 1: how each material scatters light, as the classes of the module documentation's
//! "Surfaces" rule (diffuse, glossy, specular, refraction, total internal reflection).

use super::{DIFFUSE_LIKE_ROUGHNESS, SPECULAR_ROUGHNESS};
use crate::{GltfMaterial, Material, MaterialKind, Scene, TextureRef};
use glam::Vec3;

/// How one material scatters light (see the module documentation).
#[derive(Clone, Debug, Default)]
pub(super) struct Classes {
    pub(super) diffuse: bool,
    pub(super) glossy: bool,
    pub(super) specular: bool,
    pub(super) refraction: bool,
    pub(super) smooth_refraction: bool,
    pub(super) tir: bool,
    /// Mean diffuse albedo (over channels, textures averaged), weighted by the diffuse
    /// layer's weight.
    pub(super) diffuse_albedo: f32,
    /// Short description of the model, for evidence.
    pub(super) describe: String,
}

impl Classes {
    /// Whether any layer scatters light (an emitter with no layer is only a light).
    pub(super) fn scatters(&self) -> bool {
        self.diffuse || self.glossy || self.specular || self.refraction
    }

    /// Reflection layer with the given roughness: specular or glossy.
    fn reflect(&mut self, roughness: f32) {
        if roughness < SPECULAR_ROUGHNESS {
            self.specular = true;
        } else {
            self.glossy = true;
        }
    }
}

/// Mean over the three channels.
fn mean(v: Vec3) -> f32 {
    (v.x + v.y + v.z) / 3.0
}

/// Mean and smallest texel of a texture reference, per RGBA channel (linearised when
/// `srgb`); `(1, 1)` without a texture, so factors pass through unchanged.
fn texture_stats(scene: &Scene, t: Option<&TextureRef>, srgb: bool) -> (glam::Vec4, glam::Vec4) {
    let Some(image) = t
        .and_then(|t| scene.textures.get(t.texture as usize))
        .and_then(|t| scene.images.get(t.image as usize))
    else {
        return (glam::Vec4::ONE, glam::Vec4::ONE);
    };
    let mut lo = glam::Vec4::splat(f32::INFINITY);
    for y in 0..image.height {
        for x in 0..image.width {
            lo = lo.min(image.texel(x, y, srgb));
        }
    }
    (image.mean(srgb), lo)
}

/// The classes of material `m` of `scene` (whose textures give the means and minima of
/// texture-modulated parameters).
pub(super) fn classify(m: &Material, scene: &Scene) -> Classes {
    let mut c = Classes::default();
    match &m.kind {
        MaterialKind::Diffuse { albedo } => {
            c.describe = format!("diffuse, albedo {:.2}", mean(*albedo));
            if albedo.max_element() > 0.0 {
                c.diffuse = true;
                c.diffuse_albedo = mean(*albedo);
            }
        }
        MaterialKind::Phong { kd, ks, exponent } => {
            c.describe = format!(
                "Phong, kd {:.2}, ks {:.2}, exponent {exponent}",
                mean(*kd),
                mean(*ks)
            );
            if kd.max_element() > 0.0 {
                c.diffuse = true;
                c.diffuse_albedo = mean(*kd);
            }
            c.glossy = ks.max_element() > 0.0;
        }
        MaterialKind::Conductor { f0, roughness } => {
            c.describe = format!("conductor, f0 {:.2}, roughness {roughness}", mean(*f0));
            c.reflect(*roughness);
        }
        MaterialKind::Mirror { reflectance } => {
            c.describe = format!("mirror, reflectance {:.2}", mean(*reflectance));
            c.specular = reflectance.max_element() > 0.0;
        }
        MaterialKind::Dielectric {
            ior,
            roughness,
            tint,
        } => {
            c.describe = format!("dielectric, ior {ior}, roughness {roughness}");
            if tint.max_element() > 0.0 {
                c.refraction = true;
                c.smooth_refraction = *roughness < SPECULAR_ROUGHNESS;
            }
            if *ior != 1.0 {
                c.reflect(*roughness);
                c.tir = c.refraction;
            }
        }
        MaterialKind::Gltf(g) => classify_gltf(&mut c, g, scene),
    }
    c
}

/// The glTF arm of [`classify`]: layer weights from the factors times their textures'
/// means; whether a reflection is specular from the smallest roughness a texture gives.
fn classify_gltf(c: &mut Classes, g: &GltfMaterial, scene: &Scene) {
    let (metallic, roughness, transmission) = (g.metallic, g.roughness, g.transmission);
    let ior = g.ior;
    c.describe = format!(
        "metallic-roughness, metallic {metallic}, roughness {roughness}, \
         transmission {transmission}, ior {ior}"
    );
    if g.specular != 1.0 {
        c.describe += &format!(", specular {}", g.specular);
    }
    if g.clearcoat > 0.0 {
        c.describe += &format!(", clearcoat {}", g.clearcoat);
    }
    if g.sheen_color.max_element() > 0.0 {
        c.describe += &format!(", sheen {:.2}", mean(g.sheen_color));
    }
    if g.unlit {
        // KHR_materials_unlit scatters nothing: it is only an emitter.
        c.describe = "unlit (emits its base colour)".into();
        return;
    }
    let (color_mean, _) = texture_stats(scene, g.base_color_texture.as_ref(), true);
    let (mr_mean, mr_min) = texture_stats(scene, g.metallic_roughness_texture.as_ref(), false);
    let (tr_mean, _) = texture_stats(scene, g.transmission_texture.as_ref(), false);
    let (sp_mean, _) = texture_stats(scene, g.specular_texture.as_ref(), false);
    let color = g.base_color * color_mean.truncate();
    let metallic = metallic * mr_mean.z;
    let roughness = roughness * mr_min.y;
    let transmission = transmission * tr_mean.x;
    let specular = g.specular * sp_mean.w;
    let coloured = color.max_element() > 0.0;
    let (metal, base, trans) = (
        metallic,
        (1.0 - metallic) * (1.0 - transmission),
        (1.0 - metallic) * transmission,
    );
    if metal > 0.0 && coloured {
        c.reflect(roughness);
    }
    if base > 0.0 {
        if coloured {
            c.diffuse = true;
            c.diffuse_albedo = base * mean(color);
        }
        // KHR_materials_specular 0 removes the Fresnel coat altogether.
        if ior > 1.0 && specular > 0.0 && roughness < DIFFUSE_LIKE_ROUGHNESS {
            c.reflect(roughness);
        }
    }
    if trans > 0.0 {
        if ior > 1.0 {
            c.reflect(roughness);
        }
        if coloured {
            c.refraction = true;
            c.smooth_refraction = roughness < SPECULAR_ROUGHNESS;
            c.tir = ior > 1.0;
        }
    }
    if g.clearcoat > 0.0 {
        let (_, cr_min) = texture_stats(scene, g.clearcoat_roughness_texture.as_ref(), false);
        c.reflect(g.clearcoat_roughness * cr_min.y);
    }
    if g.sheen_color.max_element() > 0.0 {
        c.glossy = true;
    }
}
