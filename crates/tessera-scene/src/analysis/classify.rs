//! Step 1: how each material scatters light, as the classes of the module documentation's
//! "Surfaces" rule (diffuse, glossy, specular, refraction, total internal reflection).

use super::{DIFFUSE_LIKE_ROUGHNESS, SPECULAR_ROUGHNESS};
use crate::{Material, MaterialKind, Texture};
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

/// Mean texel of a texture (zero for an empty one).
fn texture_mean(t: &Texture) -> Vec3 {
    if t.texels.is_empty() {
        return Vec3::ZERO;
    }
    t.texels.iter().copied().sum::<Vec3>() / t.texels.len() as f32
}

/// The classes of material `m`; `textures` gives the mean of a base-colour texture.
pub(super) fn classify(m: &Material, textures: &[Texture]) -> Classes {
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
        MaterialKind::MetallicRoughness {
            base_color,
            base_color_texture,
            metallic,
            roughness,
            transmission,
            ior,
            specular,
        } => {
            c.describe = format!(
                "metallic-roughness, metallic {metallic}, roughness {roughness}, \
                 transmission {transmission}, ior {ior}"
            );
            if *specular != 1.0 {
                c.describe += &format!(", specular {specular}");
            }
            let texture = base_color_texture.and_then(|t| textures.get(t.texture as usize));
            let color = *base_color * texture.map_or(Vec3::ONE, texture_mean);
            let coloured = color.max_element() > 0.0;
            let (metal, base, trans) = (
                *metallic,
                (1.0 - metallic) * (1.0 - transmission),
                (1.0 - metallic) * transmission,
            );
            if metal > 0.0 && coloured {
                c.reflect(*roughness);
            }
            if base > 0.0 {
                if coloured {
                    c.diffuse = true;
                    c.diffuse_albedo = base * mean(color);
                }
                // KHR_materials_specular 0 removes the Fresnel coat altogether.
                if *ior > 1.0 && *specular > 0.0 && *roughness < DIFFUSE_LIKE_ROUGHNESS {
                    c.reflect(*roughness);
                }
            }
            if trans > 0.0 {
                if *ior > 1.0 {
                    c.reflect(*roughness);
                }
                if coloured {
                    c.refraction = true;
                    c.smooth_refraction = *roughness < SPECULAR_ROUGHNESS;
                    c.tir = *ior > 1.0;
                }
            }
        }
    }
    c
}
