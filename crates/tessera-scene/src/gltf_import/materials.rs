//! Step 3, materials and textures (spec "Materials", "Metallic-Roughness Material",
//! "Default Material", "Textures", "Samplers", "Images").

use super::{Importer, Res};
use crate::{Material, MaterialKind, Texture, TextureRef};
use glam::Vec3;
use gltf::json;
use json::validation::Checked;

/// Largest texture side accepted, in texels.
const MAX_TEXTURE_SIDE: u32 = 1 << 15;

impl Importer<'_> {
    /// Converts every glTF material, in order (scene material i = glTF material i).
    pub(super) fn convert_materials(&mut self) -> Res<Vec<Material>> {
        let mut out = Vec::with_capacity(self.root.materials.len());
        for mi in 0..self.root.materials.len() {
            let m = &self.root.materials[mi];
            let name = match &m.name {
                Some(n) => format!("material {mi} '{n}'"),
                None => format!("material {mi}"),
            };
            let pbr = &m.pbr_metallic_roughness;
            let [r, g, b, _alpha] = pbr.base_color_factor.0;
            let texture_info = pbr
                .base_color_texture
                .as_ref()
                .map(|t| (t.index.value(), t.tex_coord));
            let ext = m.extensions.as_ref();
            let transmission = ext
                .and_then(|e| e.transmission.as_ref())
                .map_or(0.0, |t| t.transmission_factor.0);
            let ior = ext.and_then(|e| e.ior.as_ref()).map_or(1.5, |i| i.ior.0);
            // KHR_materials_specular: the factor scales the dielectric Fresnel layer. Its
            // colour factor and textures are not read yet (the factor alone is exact for a
            // white specular colour, which is what exporters write by default).
            let specular = ext
                .and_then(|e| e.specular.as_ref())
                .map_or(1.0, |s| s.specular_factor.0);
            let strength = ext
                .and_then(|e| e.emissive_strength.as_ref())
                .map_or(1.0, |s| s.emissive_strength.0);
            let emission = Vec3::from(m.emissive_factor.0) * strength;
            let (metallic, roughness) = (pbr.metallic_factor.0, pbr.roughness_factor.0);
            let double_sided = m.double_sided;
            let base_color_texture = match texture_info {
                Some((ti, _)) => Some(self.texture(ti, &name)?),
                None => None,
            };
            self.material_uv_set
                .push(texture_info.map_or(0, |(_, set)| set));
            out.push(Material {
                name,
                kind: MaterialKind::MetallicRoughness {
                    base_color: Vec3::new(r, g, b),
                    base_color_texture,
                    metallic,
                    roughness,
                    transmission,
                    ior,
                    specular,
                },
                emission,
                double_sided,
            });
        }
        Ok(out)
    }

    /// Decodes (once per image and wrap mode) the texture `ti` used by `what`.
    fn texture(&mut self, ti: usize, what: &str) -> Res<TextureRef> {
        let Some(tex) = self.root.textures.get(ti) else {
            return self.err(format!(
                "{what} refers to texture {ti}, but there are only {}",
                self.root.textures.len()
            ));
        };
        let ii = tex.source.value();
        // Spec "Samplers": without a sampler, repeat wrapping should be used.
        let repeat = match tex.sampler.map(|s| self.root.samplers.get(s.value())) {
            None => true,
            Some(None) => return self.err(format!("texture {ti} refers to a missing sampler")),
            Some(Some(s)) => {
                let clamp = Checked::Valid(json::texture::WrappingMode::ClampToEdge);
                !(s.wrap_s == clamp && s.wrap_t == clamp)
            }
        };
        if let Some(&t) = self.texture_map.get(&(ii, repeat)) {
            return Ok(TextureRef { texture: t });
        }
        let mut texture = self.decode_image(ii, &format!("texture {ti} of {what}"))?;
        texture.repeat = repeat;
        let index = self.textures.len() as u32;
        self.textures.push(texture);
        self.texture_map.insert((ii, repeat), index);
        Ok(TextureRef { texture: index })
    }

    /// Decodes image `ii` (PNG or JPEG) into a linear-RGB texture (spec "Images").
    fn decode_image(&mut self, ii: usize, what: &str) -> Res<Texture> {
        let Some(image) = self.root.images.get(ii) else {
            return self.err(format!(
                "{what} refers to image {ii}, but there are only {}",
                self.root.images.len()
            ));
        };
        let what = format!("image {ii} ({what})");
        let (declared, bytes) = if let Some(vi) = image.buffer_view {
            // Spec "Images": mimeType must be defined when bufferView is defined.
            let Some(mime) = &image.mime_type else {
                return self.err(format!(
                    "{what} has a bufferView but no mimeType (the spec requires one)"
                ));
            };
            let mime = mime.0.clone();
            (Some(mime), self.view_bytes(vi.value(), &what)?.to_vec())
        } else if let Some(uri) = image.uri.clone() {
            let declared = image.mime_type.as_ref().map(|m| m.0.clone());
            let (data_mime, bytes) = self.read_uri(&uri, &what)?;
            (data_mime.or(declared), bytes)
        } else {
            return self.err(format!("{what} has neither a uri nor a bufferView"));
        };
        let format = if bytes.starts_with(b"\x89PNG\r\n\x1a\n") {
            image::ImageFormat::Png
        } else if bytes.starts_with(&[0xff, 0xd8, 0xff]) {
            image::ImageFormat::Jpeg
        } else {
            return self.err(format!(
                "{what} is not a PNG or JPEG image (declared media type {declared:?})"
            ));
        };
        let mut reader = image::ImageReader::with_format(std::io::Cursor::new(&bytes), format);
        let mut limits = image::Limits::default();
        limits.max_image_width = Some(MAX_TEXTURE_SIDE);
        limits.max_image_height = Some(MAX_TEXTURE_SIDE);
        limits.max_alloc = Some(self.limit.min(1 << 30));
        reader.limits(limits);
        let decoded = match reader.decode() {
            Ok(d) => d,
            Err(e) => return self.err(format!("{what}: cannot decode {format:?}: {e}")),
        };
        let (width, height) = (decoded.width(), decoded.height());
        let texels = width as u64 * height as u64;
        self.add_output(texels * 12, &what)?;
        if texels == 0 {
            return self.err(format!("{what} is empty"));
        }
        let color = decoded.color();
        let depth = color.bits_per_pixel() / u16::from(color.channel_count());
        let texels: Vec<Vec3> = match depth {
            8 => {
                let lut: Vec<f32> = (0..256)
                    .map(|v| srgb_to_linear(v as f64 / 255.0) as f32)
                    .collect();
                decoded
                    .into_rgb8()
                    .pixels()
                    .map(|p| Vec3::new(lut[p[0] as usize], lut[p[1] as usize], lut[p[2] as usize]))
                    .collect()
            }
            16 => decoded
                .into_rgb16()
                .pixels()
                .map(|p| Vec3::from(p.0.map(|c| srgb_to_linear(c as f64 / 65535.0) as f32)))
                .collect(),
            _ => decoded
                .into_rgb32f()
                .pixels()
                .map(|p| Vec3::from(p.0.map(|c| srgb_to_linear(c as f64) as f32)))
                .collect(),
        };
        Ok(Texture {
            width,
            height,
            texels,
            repeat: true,
        })
    }
}

/// The glTF default material (spec "Default Material"), used by primitives without one.
pub(super) fn default_material() -> Material {
    // Spec "Default Material": base colour 1, metallic 1, roughness 1.
    Material {
        name: "glTF default material".into(),
        kind: MaterialKind::MetallicRoughness {
            base_color: Vec3::ONE,
            base_color_texture: None,
            metallic: 1.0,
            roughness: 1.0,
            transmission: 0.0,
            ior: 1.5,
            specular: 1.0,
        },
        emission: Vec3::ZERO,
        double_sided: false,
    }
}

/// The exact sRGB EOTF (IEC 61966-2-1): encoded value in [0, 1] to linear.
fn srgb_to_linear(c: f64) -> f64 {
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn srgb_eotf_matches_reference_points() {
        assert_eq!(srgb_to_linear(0.0), 0.0);
        assert!((srgb_to_linear(1.0) - 1.0).abs() < 1e-12);
        assert!((srgb_to_linear(0.5) - 0.214_041_140_482_232_5).abs() < 1e-9);
        assert!((srgb_to_linear(0.04) - 0.04 / 12.92).abs() < 1e-15);
    }
}
