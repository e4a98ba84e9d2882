//! Materials and textures: what a surface is made of, as the scene description states it
//! (factors and texture references); `tessera-render` evaluates the textures at each hit
//! and turns the result into a BSDF.

use glam::{Vec2, Vec3, Vec4};

/// How texture coordinates outside [0, 1] map into the image (glTF sampler `wrapS` and
/// `wrapT`, spec "Samplers").
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum Wrap {
    /// The image tiles: `u - floor(u)` (glTF `REPEAT`, 10497, the default).
    #[default]
    Repeat,
    /// The image tiles, every other copy mirrored (glTF `MIRRORED_REPEAT`, 33648).
    MirroredRepeat,
    /// Coordinates clamp so that filtering never reads past the edge texels (glTF
    /// `CLAMP_TO_EDGE`, 33071).
    ClampToEdge,
}

/// Texel storage of an [`Image`]: the values exactly as the file encodes them (not yet
/// linearised), so one decoded image serves both colour (sRGB) and data (linear) slots.
#[derive(Clone, Debug)]
pub enum Texels {
    /// 8 bits per channel, RGBA (grey and grey-alpha images are expanded).
    Rgba8(Vec<[u8; 4]>),
    /// Anything deeper (16-bit PNG), as encoded values in [0, 1].
    RgbaF32(Vec<[f32; 4]>),
}

impl Texels {
    /// Number of texels.
    pub fn len(&self) -> usize {
        match self {
            Texels::Rgba8(t) => t.len(),
            Texels::RgbaF32(t) => t.len(),
        }
    }

    /// True when there are no texels.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// A decoded image, row-major from the top row (glTF puts texture coordinate v = 0 at the
/// top of the image).
#[derive(Clone, Debug)]
pub struct Image {
    /// Width in texels.
    pub width: u32,
    /// Height in texels.
    pub height: u32,
    /// The encoded texels.
    pub texels: Texels,
}

impl Image {
    /// Texel `(x, y)` as encoded RGBA in [0, 1]; `srgb` decodes RGB with the sRGB EOTF
    /// (alpha is always linear, glTF spec "Metallic-Roughness Material").
    #[inline]
    pub fn texel(&self, x: u32, y: u32, srgb: bool) -> Vec4 {
        let i = (y * self.width + x) as usize;
        match &self.texels {
            Texels::Rgba8(t) => {
                let [r, g, b, a] = t[i];
                if srgb {
                    let lut = srgb8_lut();
                    Vec4::new(
                        lut[r as usize],
                        lut[g as usize],
                        lut[b as usize],
                        f32::from(a) / 255.0,
                    )
                } else {
                    Vec4::new(
                        f32::from(r) / 255.0,
                        f32::from(g) / 255.0,
                        f32::from(b) / 255.0,
                        f32::from(a) / 255.0,
                    )
                }
            }
            Texels::RgbaF32(t) => {
                let [r, g, b, a] = t[i];
                if srgb {
                    Vec4::new(
                        srgb_to_linear(r as f64) as f32,
                        srgb_to_linear(g as f64) as f32,
                        srgb_to_linear(b as f64) as f32,
                        a,
                    )
                } else {
                    Vec4::new(r, g, b, a)
                }
            }
        }
    }

    /// Mean texel (linearised when `srgb`), for statistics and light power estimates.
    pub fn mean(&self, srgb: bool) -> Vec4 {
        let n = self.texels.len();
        if n == 0 {
            return Vec4::ZERO;
        }
        let mut sum = glam::DVec4::ZERO;
        for y in 0..self.height {
            for x in 0..self.width {
                sum += self.texel(x, y, srgb).as_dvec4();
            }
        }
        (sum / n as f64).as_vec4()
    }
}

/// The exact sRGB EOTF (IEC 61966-2-1): encoded value in [0, 1] to linear.
pub fn srgb_to_linear(c: f64) -> f64 {
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

/// The sRGB EOTF of every 8-bit code, computed once.
fn srgb8_lut() -> &'static [f32; 256] {
    static LUT: std::sync::OnceLock<[f32; 256]> = std::sync::OnceLock::new();
    LUT.get_or_init(|| std::array::from_fn(|v| srgb_to_linear(v as f64 / 255.0) as f32))
}

/// An image with the sampler that reads it (glTF "Textures").
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Texture {
    /// Index into [`crate::Scene::images`].
    pub image: u32,
    /// Wrapping of the u coordinate.
    pub wrap_s: Wrap,
    /// Wrapping of the v coordinate.
    pub wrap_t: Wrap,
    /// Nearest-texel lookup (glTF `magFilter` NEAREST); otherwise bilinear.
    pub nearest: bool,
}

/// An affine map of texture coordinates, `uv' = m · (u, v, 1)` (KHR_texture_transform:
/// `T(offset) · R(rotation) · S(scale)`), stored as the two rows of a 2x3 matrix.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct UvTransform(pub [f32; 6]);

impl UvTransform {
    /// The KHR_texture_transform matrix `T · R · S`, where the rotation turns
    /// counter-clockwise in UV space as the extension defines it
    /// (`[cos, sin; -sin, cos]`).
    pub fn new(offset: Vec2, rotation: f32, scale: Vec2) -> Self {
        let (s, c) = rotation.sin_cos();
        Self([
            c * scale.x,
            s * scale.y,
            offset.x,
            -s * scale.x,
            c * scale.y,
            offset.y,
        ])
    }

    /// Applies the map.
    #[inline]
    pub fn apply(&self, uv: Vec2) -> Vec2 {
        let m = &self.0;
        Vec2::new(
            m[0] * uv.x + m[1] * uv.y + m[2],
            m[3] * uv.x + m[4] * uv.y + m[5],
        )
    }
}

/// Reference to a texture: which texture, which texture-coordinate set, and how the
/// coordinates are transformed.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TextureRef {
    /// Index into [`crate::Scene::textures`].
    pub texture: u32,
    /// The `TEXCOORD_n` set (index into [`crate::Mesh::uvs`]).
    pub uv_set: u32,
    /// KHR_texture_transform, if any.
    pub transform: Option<UvTransform>,
}

impl TextureRef {
    /// Texture `texture` read through `TEXCOORD_0` without a transform.
    pub fn new(texture: u32) -> Self {
        Self {
            texture,
            uv_set: 0,
            transform: None,
        }
    }
}

/// How the alpha channel (base colour alpha times its texture's alpha) is interpreted
/// (glTF `alphaMode`).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub enum AlphaMode {
    /// Alpha is ignored: the surface is fully opaque.
    #[default]
    Opaque,
    /// Opaque where alpha >= `cutoff`, absent elsewhere (glTF `MASK`, `alphaCutoff`
    /// default 0.5).
    Mask {
        /// The threshold.
        cutoff: f32,
    },
    /// Partial coverage: a ray passes through with probability `1 - alpha` (stochastic
    /// transparency; glTF `BLEND`).
    Blend,
}

/// A tangent-space normal map (glTF `normalTexture`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NormalMap {
    /// The texture (linear RGB; `n = 2 rgb - 1` in the tangent frame).
    pub texture: TextureRef,
    /// Scale of the X and Y components (glTF `normalTexture.scale`, default 1).
    pub scale: f32,
}

/// KHR_materials_anisotropy: the GGX roughness of the metal and the specular layer
/// stretched along a direction of the tangent frame (the mesh's `TANGENT`, or MikkTSpace
/// tangents of the texture coordinates when it has none).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Anisotropy {
    /// `anisotropyStrength` in [0, 1]: the alpha along the direction is
    /// `mix(α, 1, strength²)`, across it `α`.
    pub strength: f32,
    /// `anisotropyRotation`: radians counter-clockwise from the tangent toward the
    /// bitangent.
    pub rotation: f32,
    /// `anisotropyTexture` (linear): the direction in RG (`2 rg - 1` in the tangent
    /// frame, then rotated by `rotation`), a factor on the strength in B.
    pub texture: Option<TextureRef>,
}

/// Beer–Lambert absorption inside a transmissive volume (KHR_materials_volume).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Volume {
    /// Absorption coefficient σ_a per scene unit, per channel:
    /// `-ln(attenuationColor) / attenuationDistance`; transmittance over a distance d
    /// inside is `exp(-σ_a d)`.
    pub sigma_a: Vec3,
}

/// The glTF 2.0 metallic-roughness material with the extensions Tessera reads. Every field
/// has the glTF default in [`Default`] (the spec's default material: base colour 1,
/// metallic 1, roughness 1). Texture values multiply their factors.
#[derive(Clone, Debug, PartialEq)]
pub struct GltfMaterial {
    /// `baseColorFactor` RGB (linear).
    pub base_color: Vec3,
    /// `baseColorFactor` alpha.
    pub alpha: f32,
    /// `baseColorTexture` (sRGB RGB, linear alpha).
    pub base_color_texture: Option<TextureRef>,
    /// `metallicFactor`.
    pub metallic: f32,
    /// `roughnessFactor` (perceptual; GGX alpha = roughness²).
    pub roughness: f32,
    /// `metallicRoughnessTexture`: metalness in B, roughness in G (linear).
    pub metallic_roughness_texture: Option<TextureRef>,
    /// `normalTexture`.
    pub normal_map: Option<NormalMap>,
    /// `emissiveTexture` (sRGB), multiplying [`crate::Material::emission`].
    pub emissive_texture: Option<TextureRef>,
    /// `alphaMode` with `alphaCutoff`.
    pub alpha_mode: AlphaMode,
    /// KHR_materials_ior (default 1.5).
    pub ior: f32,
    /// KHR_materials_specular `specularFactor` (default 1).
    pub specular: f32,
    /// KHR_materials_specular `specularTexture` (its alpha channel scales the factor).
    pub specular_texture: Option<TextureRef>,
    /// KHR_materials_specular `specularColorFactor` (default 1).
    pub specular_color: Vec3,
    /// KHR_materials_specular `specularColorTexture` (sRGB).
    pub specular_color_texture: Option<TextureRef>,
    /// KHR_materials_transmission `transmissionFactor` (default 0).
    pub transmission: f32,
    /// KHR_materials_transmission `transmissionTexture` (R channel).
    pub transmission_texture: Option<TextureRef>,
    /// KHR_materials_volume (absorption inside; `thicknessFactor` is a real-time
    /// approximation of the geometry a path tracer has, and is not used).
    pub volume: Option<Volume>,
    /// KHR_materials_clearcoat `clearcoatFactor` (default 0).
    pub clearcoat: f32,
    /// KHR_materials_clearcoat `clearcoatTexture` (R channel).
    pub clearcoat_texture: Option<TextureRef>,
    /// KHR_materials_clearcoat `clearcoatRoughnessFactor` (default 0).
    pub clearcoat_roughness: f32,
    /// KHR_materials_clearcoat `clearcoatRoughnessTexture` (G channel).
    pub clearcoat_roughness_texture: Option<TextureRef>,
    /// KHR_materials_sheen `sheenColorFactor` (default 0: no sheen).
    pub sheen_color: Vec3,
    /// KHR_materials_sheen `sheenColorTexture` (sRGB).
    pub sheen_color_texture: Option<TextureRef>,
    /// KHR_materials_sheen `sheenRoughnessFactor` (default 0).
    pub sheen_roughness: f32,
    /// KHR_materials_sheen `sheenRoughnessTexture` (alpha channel).
    pub sheen_roughness_texture: Option<TextureRef>,
    /// KHR_materials_unlit: the surface does not scatter; it emits its base colour
    /// (the importer moves the base colour into the emission).
    pub unlit: bool,
    /// KHR_materials_anisotropy, if the material has it.
    pub anisotropy: Option<Anisotropy>,
}

impl Default for GltfMaterial {
    fn default() -> Self {
        Self {
            base_color: Vec3::ONE,
            alpha: 1.0,
            base_color_texture: None,
            metallic: 1.0,
            roughness: 1.0,
            metallic_roughness_texture: None,
            normal_map: None,
            emissive_texture: None,
            alpha_mode: AlphaMode::Opaque,
            ior: 1.5,
            specular: 1.0,
            specular_texture: None,
            specular_color: Vec3::ONE,
            specular_color_texture: None,
            transmission: 0.0,
            transmission_texture: None,
            volume: None,
            clearcoat: 0.0,
            clearcoat_texture: None,
            clearcoat_roughness: 0.0,
            clearcoat_roughness_texture: None,
            sheen_color: Vec3::ZERO,
            sheen_color_texture: None,
            sheen_roughness: 0.0,
            sheen_roughness_texture: None,
            unlit: false,
            anisotropy: None,
        }
    }
}

impl GltfMaterial {
    /// Every texture reference of the material, for validation and statistics.
    pub fn textures(&self) -> impl Iterator<Item = &TextureRef> {
        [
            self.base_color_texture.as_ref(),
            self.metallic_roughness_texture.as_ref(),
            self.normal_map.as_ref().map(|n| &n.texture),
            self.emissive_texture.as_ref(),
            self.specular_texture.as_ref(),
            self.specular_color_texture.as_ref(),
            self.transmission_texture.as_ref(),
            self.clearcoat_texture.as_ref(),
            self.clearcoat_roughness_texture.as_ref(),
            self.sheen_color_texture.as_ref(),
            self.sheen_roughness_texture.as_ref(),
            self.anisotropy.as_ref().and_then(|a| a.texture.as_ref()),
        ]
        .into_iter()
        .flatten()
    }

    /// True when some ray may pass through the surface (MASK or BLEND).
    pub fn has_alpha(&self) -> bool {
        self.alpha_mode != AlphaMode::Opaque
    }
}

/// How a surface scatters light. The variants name the physics; `tessera-render` turns
/// each into a BSDF.
#[derive(Clone, Debug, PartialEq)]
pub enum MaterialKind {
    /// Lambertian diffuse reflection with the given albedo.
    Diffuse {
        /// Reflectance in [0, 1] per channel.
        albedo: Vec3,
    },
    /// Veach's energy-conserving modified Phong (Lafortune & Willems 1994): a diffuse
    /// part `kd / pi` plus `ks (n + 2) / (2 pi) cos^n(alpha)` around the mirror direction.
    /// `kd + ks <= 1` per channel keeps it energy conserving.
    Phong {
        /// Diffuse reflectance.
        kd: Vec3,
        /// Specular reflectance.
        ks: Vec3,
        /// Phong exponent n >= 0.
        exponent: f32,
    },
    /// A rough conductor with a GGX (Trowbridge–Reitz) microfacet distribution and
    /// Schlick's Fresnel from the normal-incidence reflectance `f0`.
    Conductor {
        /// Reflectance at normal incidence.
        f0: Vec3,
        /// Perceptual roughness in [0, 1] (alpha = roughness²).
        roughness: f32,
    },
    /// glTF 2.0 metallic-roughness with its extensions (see [`GltfMaterial`]).
    Gltf(Box<GltfMaterial>),
    /// An ideal mirror.
    Mirror {
        /// Reflectance per channel.
        reflectance: Vec3,
    },
    /// A smooth (roughness 0) or rough (GGX) dielectric interface: glass.
    Dielectric {
        /// Index of refraction of the inside relative to the outside.
        ior: f32,
        /// Perceptual roughness; 0 is a smooth interface with Fresnel and total internal
        /// reflection.
        roughness: f32,
        /// Transmission tint per channel.
        tint: Vec3,
    },
}

/// A material: the scattering model plus emission.
#[derive(Clone, Debug, PartialEq)]
pub struct Material {
    /// Name, for messages.
    pub name: String,
    /// Scattering.
    pub kind: MaterialKind,
    /// Emitted radiance in W/(m² sr), linear RGB (glTF: emissiveFactor x
    /// KHR_materials_emissive_strength, times the emissive texture where there is one).
    pub emission: Vec3,
    /// Emission (and, for thin surfaces, scattering) on both sides; otherwise only along
    /// the geometric normal.
    pub double_sided: bool,
}

impl Material {
    /// A Lambertian material that does not emit.
    pub fn diffuse(name: &str, albedo: Vec3) -> Self {
        Self {
            name: name.to_string(),
            kind: MaterialKind::Diffuse { albedo },
            emission: Vec3::ZERO,
            double_sided: false,
        }
    }

    /// A glTF material.
    pub fn gltf(name: &str, m: GltfMaterial) -> Self {
        Self {
            name: name.to_string(),
            kind: MaterialKind::Gltf(Box::new(m)),
            emission: Vec3::ZERO,
            double_sided: false,
        }
    }

    /// True when the material emits light.
    pub fn is_emissive(&self) -> bool {
        self.emission.max_element() > 0.0
    }

    /// The glTF parameters, if this is a glTF material.
    pub fn as_gltf(&self) -> Option<&GltfMaterial> {
        match &self.kind {
            MaterialKind::Gltf(g) => Some(g),
            _ => None,
        }
    }

    /// The texture that multiplies the emission, if any.
    pub fn emissive_texture(&self) -> Option<&TextureRef> {
        self.as_gltf().and_then(|g| g.emissive_texture.as_ref())
    }

    /// True when some ray may pass through the surface (glTF alpha MASK or BLEND).
    pub fn has_alpha(&self) -> bool {
        self.as_gltf().is_some_and(GltfMaterial::has_alpha)
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

    #[test]
    fn texture_transform_matches_the_extension_matrix() {
        // KHR_texture_transform's example: offset (0.5, 0), rotation pi/2, scale (2, 2).
        let t = UvTransform::new(
            Vec2::new(0.5, 0.0),
            std::f32::consts::FRAC_PI_2,
            Vec2::splat(2.0),
        );
        // rotation [cos sin; -sin cos] = [0 1; -1 0]; (1, 0) scaled to (2, 0) -> (0, -2) + offset.
        let p = t.apply(Vec2::new(1.0, 0.0));
        assert!((p - Vec2::new(0.5, -2.0)).length() < 1e-6, "{p}");
        let q = t.apply(Vec2::new(0.0, 1.0));
        assert!((q - Vec2::new(2.5, 0.0)).length() < 1e-6, "{q}");
    }
}
