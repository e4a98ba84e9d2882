//! Step 3, materials and textures (spec "Materials", "Metallic-Roughness Material",
//! "Default Material", "Textures", "Samplers", "Images", and the material extensions).

use super::extensions::{anisotropy, clearcoat, sheen};
use super::{Importer, Res};
use crate::material::{
    AlphaMode, Anisotropy, GltfMaterial, Image, Material, MaterialKind, NormalMap, Texels, Texture,
    TextureRef, UvTransform, Volume, Wrap,
};
use crate::{MAX_IMAGE_TEXELS, MAX_SCENE_TEXELS};
use glam::{Vec2, Vec3};
use gltf::json;
use json::validation::Checked;

/// Largest texture side accepted, in texels.
const MAX_TEXTURE_SIDE: u32 = 1 << 15;

/// Where a texture reference sits (material and slot), for error messages.
struct Slot<'s> {
    material: &'s str,
    name: &'s str,
}

impl Importer<'_> {
    /// Converts every glTF material, in order (scene material i = glTF material i).
    pub(super) fn convert_materials(&mut self) -> Res<Vec<Material>> {
        let mut out = Vec::with_capacity(self.root.materials.len());
        for mi in 0..self.root.materials.len() {
            let m = self.root.materials[mi].clone();
            let name = match &m.name {
                Some(n) => format!("material {mi} '{n}'"),
                None => format!("material {mi}"),
            };
            let (material, uv_sets) = self.convert_material(&m, &name)?;
            self.material_uv_sets.push(uv_sets);
            out.push(material);
        }
        Ok(out)
    }

    /// One material, and the largest `TEXCOORD_n` set its textures read (+1; 0 for none).
    fn convert_material(&mut self, m: &json::Material, name: &str) -> Res<(Material, u32)> {
        let slot = |s| Slot {
            material: name,
            name: s,
        };
        let pbr = &m.pbr_metallic_roughness;
        let [r, g, b, alpha] = pbr.base_color_factor.0;
        let mut g_mat = GltfMaterial {
            base_color: Vec3::new(r, g, b),
            alpha,
            metallic: pbr.metallic_factor.0,
            roughness: pbr.roughness_factor.0,
            ..GltfMaterial::default()
        };
        g_mat.base_color_texture = self.info(&pbr.base_color_texture, &slot("baseColorTexture"))?;
        g_mat.metallic_roughness_texture = self.info(
            &pbr.metallic_roughness_texture,
            &slot("metallicRoughnessTexture"),
        )?;
        if let Some(n) = &m.normal_texture {
            let transform = n
                .extensions
                .as_ref()
                .and_then(|e| e.others.get("KHR_texture_transform"));
            let texture = self.texture_ref(
                n.index.value(),
                n.tex_coord,
                transform_from_value(transform),
                &slot("normalTexture"),
            )?;
            g_mat.normal_map = Some(NormalMap {
                texture,
                scale: n.scale,
            });
        }
        // Spec "Materials > Occlusion": ambient occlusion is a real-time approximation of
        // the shadowing a path tracer computes; the texture is read (so a broken one is
        // still an error) and ignored.
        if let Some(o) = &m.occlusion_texture {
            self.texture_ref(
                o.index.value(),
                o.tex_coord,
                None,
                &slot("occlusionTexture"),
            )?;
        }
        g_mat.emissive_texture = self.info(&m.emissive_texture, &slot("emissiveTexture"))?;
        g_mat.alpha_mode = match m.alpha_mode {
            Checked::Valid(json::material::AlphaMode::Opaque) => AlphaMode::Opaque,
            Checked::Valid(json::material::AlphaMode::Mask) => AlphaMode::Mask {
                cutoff: m.alpha_cutoff.map_or(0.5, |c| c.0),
            },
            Checked::Valid(json::material::AlphaMode::Blend) => AlphaMode::Blend,
            Checked::Invalid => return self.err(format!("{name} has an invalid alphaMode")),
        };
        let mut strength = 1.0;
        if let Some(ext) = &m.extensions {
            if let Some(t) = &ext.transmission {
                g_mat.transmission = t.transmission_factor.0;
                g_mat.transmission_texture =
                    self.info(&t.transmission_texture, &slot("transmissionTexture"))?;
            }
            if let Some(i) = &ext.ior {
                g_mat.ior = i.ior.0;
            }
            if let Some(s) = &ext.specular {
                g_mat.specular = s.specular_factor.0;
                g_mat.specular_texture =
                    self.info(&s.specular_texture, &slot("specularTexture"))?;
                g_mat.specular_color = Vec3::from(s.specular_color_factor.0);
                g_mat.specular_color_texture =
                    self.info(&s.specular_color_texture, &slot("specularColorTexture"))?;
            }
            if let Some(v) = &ext.volume {
                g_mat.volume = volume(v.attenuation_color.0, v.attenuation_distance.0);
            }
            if let Some(s) = &ext.emissive_strength {
                strength = s.emissive_strength.0;
            }
            g_mat.unlit = ext.unlit.is_some();
            if let Some(c) =
                clearcoat(&ext.others).map_err(|e| self.gerr(format!("{name}: {e}")))?
            {
                g_mat.clearcoat = c.clearcoat_factor;
                g_mat.clearcoat_roughness = c.clearcoat_roughness_factor;
                g_mat.clearcoat_texture =
                    self.info(&c.clearcoat_texture, &slot("clearcoatTexture"))?;
                g_mat.clearcoat_roughness_texture = self.info(
                    &c.clearcoat_roughness_texture,
                    &slot("clearcoatRoughnessTexture"),
                )?;
            }
            if let Some(a) =
                anisotropy(&ext.others).map_err(|e| self.gerr(format!("{name}: {e}")))?
            {
                let (strength, rotation) = (a.anisotropy_strength, a.anisotropy_rotation);
                if !(0.0..=1.0).contains(&strength) || !rotation.is_finite() {
                    return self.err(format!(
                        "{name}: KHR_materials_anisotropy needs anisotropyStrength in [0, 1] \
                         and a finite anisotropyRotation (got {strength}, {rotation})"
                    ));
                }
                g_mat.anisotropy = Some(Anisotropy {
                    strength,
                    rotation,
                    texture: self.info(&a.anisotropy_texture, &slot("anisotropyTexture"))?,
                });
            }
            if let Some(s) = sheen(&ext.others).map_err(|e| self.gerr(format!("{name}: {e}")))? {
                g_mat.sheen_color = Vec3::from(s.sheen_color_factor);
                g_mat.sheen_roughness = s.sheen_roughness_factor;
                g_mat.sheen_color_texture =
                    self.info(&s.sheen_color_texture, &slot("sheenColorTexture"))?;
                g_mat.sheen_roughness_texture =
                    self.info(&s.sheen_roughness_texture, &slot("sheenRoughnessTexture"))?;
            }
        }
        let mut emission = Vec3::from(m.emissive_factor.0) * strength;
        if g_mat.unlit {
            // KHR_materials_unlit: the surface shows its base colour whatever the lighting.
            // As radiance that is an emitter of the base colour that scatters nothing.
            emission = g_mat.base_color;
            g_mat.emissive_texture = g_mat.base_color_texture;
        }
        let uv_sets = g_mat.textures().map(|t| t.uv_set + 1).max().unwrap_or(0);
        let material = Material {
            name: name.to_string(),
            kind: MaterialKind::Gltf(Box::new(g_mat)),
            emission,
            double_sided: m.double_sided,
        };
        Ok((material, uv_sets))
    }

    /// A `textureInfo` (with its KHR_texture_transform), if present.
    fn info(&mut self, info: &Option<json::texture::Info>, slot: &Slot) -> Res<Option<TextureRef>> {
        let Some(info) = info else {
            return Ok(None);
        };
        let ext = info.extensions.as_ref();
        let transform = ext.and_then(|e| e.texture_transform.as_ref());
        // KHR_texture_transform: its texCoord, when present, overrides the textureInfo's.
        let tex_coord = transform
            .and_then(|t| t.tex_coord)
            .unwrap_or(info.tex_coord);
        let transform = transform
            .map(|t| UvTransform::new(Vec2::from(t.offset.0), t.rotation.0, Vec2::from(t.scale.0)));
        self.texture_ref(info.index.value(), tex_coord, transform, slot)
            .map(Some)
    }

    /// The scene texture for glTF texture `ti`, read through `TEXCOORD_{tex_coord}`.
    fn texture_ref(
        &mut self,
        ti: usize,
        tex_coord: u32,
        transform: Option<UvTransform>,
        slot: &Slot,
    ) -> Res<TextureRef> {
        let what = format!("{} of {}", slot.name, slot.material);
        if tex_coord > 7 {
            return self.err(format!(
                "{what} reads TEXCOORD_{tex_coord}; at most TEXCOORD_7 is supported"
            ));
        }
        let texture = self.texture(ti, &what)?;
        Ok(TextureRef {
            texture,
            uv_set: tex_coord,
            transform,
        })
    }

    /// Converts (once) glTF texture `ti`: its image and its sampler.
    fn texture(&mut self, ti: usize, what: &str) -> Res<u32> {
        if let Some(&t) = self.texture_map.get(&ti) {
            return Ok(t);
        }
        let Some(tex) = self.root.textures.get(ti) else {
            return self.err(format!(
                "{what} refers to texture {ti}, but there are only {}",
                self.root.textures.len()
            ));
        };
        let ii = tex.source.value();
        // Spec "Samplers": without a sampler, repeat wrapping and auto filtering are used.
        let (wrap_s, wrap_t, nearest) = match tex.sampler.map(|s| self.root.samplers.get(s.value()))
        {
            None => (Wrap::Repeat, Wrap::Repeat, false),
            Some(None) => return self.err(format!("texture {ti} refers to a missing sampler")),
            Some(Some(s)) => (
                wrap(s.wrap_s),
                wrap(s.wrap_t),
                s.mag_filter == Some(Checked::Valid(json::texture::MagFilter::Nearest)),
            ),
        };
        let image = match self.image_map.get(&ii) {
            Some(&i) => i,
            None => {
                let decoded = self.decode_image(ii, &format!("texture {ti} of {what}"))?;
                let i = self.images.len() as u32;
                self.images.push(decoded);
                self.image_map.insert(ii, i);
                i
            }
        };
        let index = self.textures.len() as u32;
        self.textures.push(Texture {
            image,
            wrap_s,
            wrap_t,
            nearest,
        });
        self.texture_map.insert(ti, index);
        Ok(index)
    }

    /// Decodes image `ii` (PNG or JPEG) into encoded RGBA texels (spec "Images").
    fn decode_image(&mut self, ii: usize, what: &str) -> Res<Image> {
        let Some(image) = self.root.images.get(ii) else {
            return self.err(format!(
                "{what} refers to image {ii}, but there are only {}",
                self.root.images.len()
            ));
        };
        let named = match &image.name {
            Some(n) => format!("image {ii} '{}'", truncate(n)),
            None => format!("image {ii}"),
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
        // The size from the header, before anything is decoded: a compressed image can
        // decode to a thousand times its bytes.
        let (w, h) = image::ImageReader::with_format(std::io::Cursor::new(&bytes), format)
            .into_dimensions()
            .or_else(|e| self.err(format!("{what}: cannot read the {format:?} header: {e}")))?;
        let texels = u64::from(w) * u64::from(h);
        let (per_image, per_scene) = (self.limits.image_texels, self.limits.scene_texels);
        if texels > per_image {
            return self.err(format!(
                "{named}: {w}x{h} is {texels} texels, more than the limit of {per_image} \
                 texels per image (MAX_IMAGE_TEXELS; {MAX_IMAGE_TEXELS} is 8192x8192)"
            ));
        }
        let total = self.texels.saturating_add(texels);
        if total > per_scene {
            return self.err(format!(
                "{named}: {w}x{h} brings the scene's images to {total} texels, more than the \
                 limit of {per_scene} texels per scene (MAX_SCENE_TEXELS; {MAX_SCENE_TEXELS} \
                 is four 8192x8192 images)"
            ));
        }
        self.texels = total;
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
        let count = width as u64 * height as u64;
        if (width, height) != (w, h) {
            return self.err(format!(
                "{what}: decoded to {width}x{height}, but its header says {w}x{h}"
            ));
        }
        if count == 0 {
            return self.err(format!("{what} is empty"));
        }
        let color = decoded.color();
        let depth = color.bits_per_pixel() / u16::from(color.channel_count());
        let texels = if depth == 8 {
            self.add_output(count * 4, &what)?;
            Texels::Rgba8(decoded.into_rgba8().pixels().map(|p| p.0).collect())
        } else {
            self.add_output(count * 16, &what)?;
            Texels::RgbaF32(decoded.into_rgba32f().pixels().map(|p| p.0).collect())
        };
        Ok(Image {
            width,
            height,
            texels,
        })
    }
}

/// At most 60 characters of a name from the file, for messages.
fn truncate(name: &str) -> String {
    match name.char_indices().nth(60) {
        Some((i, _)) => format!("{}...", &name[..i]),
        None => name.to_string(),
    }
}

/// A glTF sampler wrap mode (spec "Samplers").
fn wrap(mode: Checked<json::texture::WrappingMode>) -> Wrap {
    use json::texture::WrappingMode;
    match mode {
        Checked::Valid(WrappingMode::ClampToEdge) => Wrap::ClampToEdge,
        Checked::Valid(WrappingMode::MirroredRepeat) => Wrap::MirroredRepeat,
        // The document check refused invalid values already; REPEAT is the default.
        Checked::Valid(WrappingMode::Repeat) | Checked::Invalid => Wrap::Repeat,
    }
}

/// KHR_texture_transform from an untyped extension object (normal and occlusion textures
/// carry their extensions untyped in the `gltf` crate).
fn transform_from_value(v: Option<&serde_json::Value>) -> Option<UvTransform> {
    let v = v?;
    let pair = |key: &str, default: [f32; 2]| -> Vec2 {
        v.get(key)
            .and_then(|a| serde_json::from_value::<[f32; 2]>(a.clone()).ok())
            .map_or(Vec2::from(default), Vec2::from)
    };
    let rotation = v.get("rotation").and_then(|r| r.as_f64()).unwrap_or(0.0) as f32;
    Some(UvTransform::new(
        pair("offset", [0.0, 0.0]),
        rotation,
        pair("scale", [1.0, 1.0]),
    ))
}

/// KHR_materials_volume: `attenuationColor` is the colour white light turns into after
/// travelling `attenuationDistance` inside, so Beer–Lambert's `exp(-σ d) = c` gives
/// `σ = -ln(c) / d`. An infinite distance (the default) is no absorption.
fn volume(color: [f32; 3], distance: f32) -> Option<Volume> {
    if !(distance.is_finite() && distance > 0.0) {
        return None;
    }
    let sigma = Vec3::from(color.map(|c| -c.clamp(1e-6, 1.0).ln() / distance));
    (sigma.max_element() > 0.0).then_some(Volume { sigma_a: sigma })
}

/// The glTF default material (spec "Default Material"), used by primitives without one.
pub(super) fn default_material() -> Material {
    Material::gltf("glTF default material", GltfMaterial::default())
}
