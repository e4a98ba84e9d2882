//! Environment images: an equirectangular (latitude–longitude) radiance map that lights a
//! scene from every direction rays leave it in, read from Radiance `.hdr` (RGBE) or
//! OpenEXR.
//!
//! # Mapping
//! The image's top row looks straight up (+Y, glTF's up axis), its bottom row straight
//! down; a column `u ∈ [0, 1)` is the azimuth `φ = 2π (u - 1/2)` measured from +X toward
//! +Z, so the image's centre looks along +X, its quarter columns along -Z (u = 1/4) and +Z
//! (u = 3/4). In Blender's Z-up world (glTF +X, -Z, +Y are Blender's +X, +Y, +Z) this is
//! the mapping of Cycles' environment texture, so an HDR lights a glTF scene here as it
//! lights the same scene imported into Blender. [`EnvironmentMap::rotation`] turns the
//! image about +Y (positive: counter-clockwise seen from above).
//!
//! # Limits
//! As glTF textures: at most [`crate::MAX_IMAGE_TEXELS`] texels, read from the header
//! before anything is decoded (a small compressed file can decode to gigabytes), and the
//! decoder's allocation capped at 1 GiB.

use crate::{SceneError, MAX_IMAGE_TEXELS};
use glam::Vec3;
use std::io::Cursor;
use std::path::Path;
use std::sync::Arc;

/// An equirectangular environment image of linear radiance (see the module docs for its
/// mapping). Scaled by [`crate::Scene::environment`] (strength and tint).
#[derive(Clone, PartialEq)]
pub struct EnvironmentMap {
    /// Where the image came from (file name or content hash), for messages.
    pub name: String,
    /// Width in texels (azimuth).
    pub width: u32,
    /// Height in texels (polar angle, top row up).
    pub height: u32,
    /// Linear RGB radiance, W/(m² sr) before scaling, row-major from the top row. Shared:
    /// cloning a scene (animation keys, flattening) does not copy the image.
    pub texels: Arc<[Vec3]>,
    /// Rotation about the up axis (+Y) in radians, counter-clockwise seen from above.
    pub rotation: f32,
}

impl std::fmt::Debug for EnvironmentMap {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        // Not the texels: a 4K map would print millions of numbers.
        f.debug_struct("EnvironmentMap")
            .field("name", &self.name)
            .field("width", &self.width)
            .field("height", &self.height)
            .field("rotation", &self.rotation)
            .finish_non_exhaustive()
    }
}

impl EnvironmentMap {
    /// A map of `width` x `height` texels (row-major from the top row), checked: the size
    /// matches, every texel is finite and non-negative.
    pub fn new(name: &str, width: u32, height: u32, texels: Vec<Vec3>) -> Result<Self, String> {
        if width == 0 || height == 0 || texels.len() as u64 != u64::from(width) * u64::from(height)
        {
            return Err(format!(
                "{name}: {width}x{height} does not match its {} texels",
                texels.len()
            ));
        }
        if let Some(i) = texels
            .iter()
            .position(|t| !t.is_finite() || t.min_element() < 0.0)
        {
            return Err(format!(
                "{name}: texel ({}, {}) is {} (radiance must be finite and non-negative)",
                i as u64 % u64::from(width),
                i as u64 / u64::from(width),
                texels[i]
            ));
        }
        Ok(Self {
            name: name.to_string(),
            width,
            height,
            texels: texels.into(),
            rotation: 0.0,
        })
    }

    /// The map with rotation `degrees` about the up axis.
    pub fn rotated(mut self, degrees: f32) -> Self {
        self.rotation = degrees.to_radians();
        self
    }
}

/// Reads an environment image from a file (see [`decode_environment`]).
pub fn load_environment(path: &Path) -> Result<EnvironmentMap, SceneError> {
    let name = path.display().to_string();
    let len = std::fs::metadata(path)
        .map_err(|source| SceneError::Io {
            path: name.clone(),
            source,
        })?
        .len();
    if len > crate::MAX_INPUT_BYTES {
        return Err(SceneError::TooLarge {
            path: name,
            bytes: len,
            limit: crate::MAX_INPUT_BYTES,
        });
    }
    let bytes = std::fs::read(path).map_err(|source| SceneError::Io {
        path: name.clone(),
        source,
    })?;
    decode_environment(&bytes, &name)
}

/// Decodes an environment image from the bytes of a Radiance `.hdr` or OpenEXR file (told
/// apart by their magic numbers, not the name), checking its size from the header before
/// decoding. `name` names it in errors.
pub fn decode_environment(bytes: &[u8], name: &str) -> Result<EnvironmentMap, SceneError> {
    let err = |message: String| SceneError::Invalid {
        scene: format!("environment {name}"),
        message,
    };
    let (width, height, texels) = if bytes.starts_with(b"#?") {
        decode_hdr(bytes).map_err(err)?
    } else if bytes.starts_with(&[0x76, 0x2f, 0x31, 0x01]) {
        decode_exr(bytes).map_err(err)?
    } else {
        return Err(err(
            "not a Radiance .hdr (#?RADIANCE) or OpenEXR file; an environment is an \
             equirectangular HDR image"
                .into(),
        ));
    };
    EnvironmentMap::new(name, width, height, texels).map_err(err)
}

/// Refuses images over [`MAX_IMAGE_TEXELS`].
fn check_size(w: u64, h: u64) -> Result<(), String> {
    let texels = w.saturating_mul(h);
    if texels > MAX_IMAGE_TEXELS {
        return Err(format!(
            "{w}x{h} is {texels} texels, more than the limit of {MAX_IMAGE_TEXELS} texels per \
             image (MAX_IMAGE_TEXELS, 8192x8192)"
        ));
    }
    if texels == 0 {
        return Err("the image is empty".into());
    }
    Ok(())
}

/// Radiance RGBE through the `image` crate, size checked from the header first.
fn decode_hdr(bytes: &[u8]) -> Result<(u32, u32, Vec<Vec3>), String> {
    let format = image::ImageFormat::Hdr;
    let (w, h) = image::ImageReader::with_format(Cursor::new(bytes), format)
        .into_dimensions()
        .map_err(|e| format!("cannot read the Radiance header: {e}"))?;
    check_size(u64::from(w), u64::from(h))?;
    let mut reader = image::ImageReader::with_format(Cursor::new(bytes), format);
    let mut limits = image::Limits::default();
    limits.max_alloc = Some(1 << 30);
    reader.limits(limits);
    let decoded = reader
        .decode()
        .map_err(|e| format!("cannot decode the Radiance image: {e}"))?
        .into_rgb32f();
    let texels = decoded.pixels().map(|p| Vec3::from(p.0)).collect();
    Ok((w, h, texels))
}

/// OpenEXR (first layer, largest resolution level, channels R, G and B; Y alone is read as
/// grey), size checked from the header first.
fn decode_exr(bytes: &[u8]) -> Result<(u32, u32, Vec<Vec3>), String> {
    use exr::prelude::{read, ReadChannels, ReadLayers};
    let meta = exr::meta::MetaData::read_from_buffered(Cursor::new(bytes), false)
        .map_err(|e| format!("cannot read the OpenEXR header: {e}"))?;
    let header = meta
        .headers
        .first()
        .ok_or_else(|| "the OpenEXR file has no layer".to_string())?;
    let size = header.layer_size;
    check_size(size.0 as u64, size.1 as u64)?;
    let image = read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .from_buffered(Cursor::new(bytes))
        .map_err(|e| format!("cannot decode the OpenEXR image: {e}"))?;
    let (w, h) = image.layer_data.size.into();
    check_size(w as u64, h as u64)?;
    let list = &image.layer_data.channel_data.list;
    let channel = |name: &str| -> Option<Vec<f32>> {
        list.iter()
            .find(|c| c.name == *name)
            .map(|c| c.sample_data.values_as_f32().collect())
    };
    let (r, g, b) = match (channel("R"), channel("G"), channel("B"), channel("Y")) {
        (Some(r), Some(g), Some(b), _) => (r, g, b),
        (_, _, _, Some(y)) => (y.clone(), y.clone(), y),
        _ => return Err("the OpenEXR image has no R, G, B (or Y) channels".into()),
    };
    let n = w * h;
    if r.len() != n || g.len() != n || b.len() != n {
        return Err("the OpenEXR channels are subsampled, which is not supported".into());
    }
    let texels = (0..n).map(|i| Vec3::new(r[i], g[i], b[i])).collect();
    Ok((w as u32, h as u32, texels))
}

/// A job's environment made ready for its scenes: the radiance factor and, for an image,
/// the decoded map (shared by every scene it is applied to: animation frames and shutter
/// keys decode it once).
#[derive(Clone, Debug)]
pub struct SceneEnvironment {
    /// Uniform radiance, or the factor on the image.
    pub radiance: Vec3,
    /// The image, rotated as the job asks.
    pub map: Option<EnvironmentMap>,
}

impl SceneEnvironment {
    /// The environment a validated `environment` setting describes; `image` holds the
    /// bytes of its uploaded image (needed only for an image source).
    pub fn from_job(
        env: &tessera_farm::job::JobEnvironment,
        image: Option<&[u8]>,
    ) -> Result<Self, SceneError> {
        use tessera_farm::job::EnvironmentSource;
        let map = match (&env.source, image) {
            (EnvironmentSource::Colour(_), _) => None,
            (EnvironmentSource::Image(hash), Some(bytes)) => Some(
                decode_environment(bytes, &format!("environment {hash}"))?
                    .rotated(env.rotation_degrees),
            ),
            (EnvironmentSource::Image(hash), None) => {
                return Err(SceneError::Invalid {
                    scene: format!("environment {hash}"),
                    message: "its bytes are not stored".into(),
                })
            }
        };
        Ok(Self {
            radiance: Vec3::from(env.radiance()),
            map,
        })
    }

    /// Sets `scene`'s environment to this one (replacing any the scene had).
    pub fn apply(&self, scene: &mut crate::Scene) {
        scene.environment = Some(self.radiance);
        scene.environment_map = self.map.clone();
    }
}
