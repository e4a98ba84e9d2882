//! Image output for Tessera: the merged statistics of a frame
//! ([`tessera_farm::FrameImage`]) as a multi-layer OpenEXR file or an sRGB PNG.
//!
//! Shared by the local renderer and the coordinator, which never links the renderer.
//!
//! EXR layout (one part, 32-bit float channels, ZIP compression, written single-threaded
//! so the bytes are a pure function of the image):
//!
//! | channels | meaning |
//! |---|---|
//! | `R`, `G`, `B` | the beauty: mean radiance per pixel, W/(m² sr), linear Rec. 709 |
//! | `variance.R`, `variance.G`, `variance.B` | estimated variance of the mean, from the spread of independent passes (0 with fewer than 2 passes) |
//! | `pooled_variance.R`, `.G`, `.B` | the variance of the mean for the pixel's confidence interval, such that `mean +- 2 sqrt(pooled_variance)` covers 95.45% ([`tessera_farm::INTERVAL_COVERAGE`]): the per-pass variance pooled over its 3x3 neighbourhood, widened by `(q / 2)^2` for Student's t quantile `q` of the pooled degrees of freedom, `sum (passes - 1)` over the neighbours with at least 2 passes (2.32 for 9, 2.10 for 27; [`tessera_farm::FrameImage::interval_variance`]); the unwidened pooled variance is `pooled_variance (2 / q)^2`. Covers 93-96% on the calibration suite, against 70% for `variance.*` at 2 passes and 86% at 4 |
//! | `relerr.Y` | estimated relative standard error of the pixel's luminance |
//! | `passes.Y` | number of passes merged |
//! | `samples.Y` | samples per pixel traced (for adaptive renders, including a discarded unbiased pilot: where the effort went) |
//! | `bias.Y`, `bias.variance.Y` | only in biased renders (vcm, ppm): the mean of the passes' estimates of the merging bias (signed luminance, [`tessera_farm::FrameImage::bias`]) and the variance of that mean; the pixel's error estimate is `sqrt(v + max(0, bias.Y² - bias.variance.Y))`, with `v` the luminance variance of its mean, and its relative error divides it by the bias-corrected mean ([`tessera_farm::bias_scale`]) |
//!
//! PNG: the beauty clamped to [0, 1] and encoded with the sRGB transfer function, 8 bits.
#![deny(missing_docs)]

mod heatmap;
pub mod rows;
pub use heatmap::{encode_heat_map_png, heat_colour};
pub use rows::{encode_exr_rows, exr_working_bytes, Exr, ExrStream, FrameRows, Pixel, UniformRows};

use exr::meta::attribute::{AttributeValue, Text};
use exr::prelude::{read, ReadChannels, ReadLayers};
use std::io::Cursor;
use tessera_farm::FrameImage;

/// Errors encoding or decoding images.
#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    /// EXR encoding or decoding failed.
    #[error("exr: {0}")]
    Exr(String),
    /// PNG encoding failed.
    #[error("png: {0}")]
    Png(String),
    /// The file name has no supported extension.
    #[error("unsupported output {0:?}: use a .exr or .png file name")]
    Format(String),
    /// Writing the file failed.
    #[error("cannot write {path}: {source}")]
    Io {
        /// Path.
        path: String,
        /// Cause.
        source: std::io::Error,
    },
    /// A layer is missing from a file being read.
    #[error("exr file has no channel {0}")]
    MissingChannel(String),
}

/// Name of the EXR header attribute holding Tessera's metadata (render settings and plan).
pub const METADATA_ATTRIBUTE: &str = "tessera";

/// Encodes the frame as a multi-layer EXR file. `metadata` (e.g. the render settings and
/// plan as JSON) is stored as one text attribute, [`METADATA_ATTRIBUTE`]: a single
/// attribute, because the EXR writer stores extra attributes in hash-map order and more
/// than one would make the bytes vary between runs. Encoded a block of rows at a time
/// ([`rows::encode_exr_rows`]): the frame's layers are not copied into channels.
pub fn encode_exr(img: &FrameImage, metadata: Option<&str>) -> Result<Vec<u8>, ImageError> {
    match rows::encode_exr_rows(img, metadata, usize::MAX)? {
        rows::Exr::Whole(bytes) => Ok(bytes),
        // Unreachable with no limit; written out rather than assumed.
        rows::Exr::Stream(s) => {
            let mut out = Vec::with_capacity(s.len() as usize);
            s.write_to(img, &mut out)?;
            Ok(out)
        }
    }
}

/// The sRGB transfer function (IEC 61966-2-1) of a linear value in [0, 1].
pub fn srgb_encode(linear: f32) -> f32 {
    let c = linear.clamp(0.0, 1.0);
    if c <= 0.0031308 {
        12.92 * c
    } else {
        1.055 * c.powf(1.0 / 2.4) - 0.055
    }
}

/// Encodes 8-bit RGB pixels (row-major) as PNG.
pub fn encode_png_rgb8(width: u32, height: u32, rgb: &[u8]) -> Result<Vec<u8>, ImageError> {
    let mut out = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut out, width, height);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        enc.set_source_srgb(png::SrgbRenderingIntent::Perceptual);
        let mut w = enc
            .write_header()
            .map_err(|e| ImageError::Png(e.to_string()))?;
        w.write_image_data(rgb)
            .map_err(|e| ImageError::Png(e.to_string()))?;
    }
    Ok(out)
}

/// Encodes the beauty as an sRGB PNG (clamped, 8 bits).
pub fn encode_png(img: &FrameImage) -> Result<Vec<u8>, ImageError> {
    let rgb: Vec<u8> = img
        .mean
        .iter()
        .flat_map(|p| p.map(|c| (srgb_encode(c) * 255.0 + 0.5) as u8))
        .collect();
    encode_png_rgb8(img.width, img.height, &rgb)
}

/// Writes the frame to `path`, choosing EXR or PNG by the extension; `metadata` goes into
/// the EXR header (PNG files do not carry it).
pub fn write_image(
    path: &std::path::Path,
    img: &FrameImage,
    metadata: Option<&str>,
) -> Result<(), ImageError> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(|e| e.to_ascii_lowercase());
    let bytes = match ext.as_deref() {
        Some("exr") => encode_exr(img, metadata)?,
        Some("png") => encode_png(img)?,
        _ => return Err(ImageError::Format(path.display().to_string())),
    };
    std::fs::write(path, bytes).map_err(|source| ImageError::Io {
        path: path.display().to_string(),
        source,
    })
}

/// A decoded EXR: width, height, the named float channels and Tessera's metadata.
pub struct ExrChannels {
    /// The [`METADATA_ATTRIBUTE`] text, if present.
    pub metadata: Option<String>,
    /// Width.
    pub width: usize,
    /// Height.
    pub height: usize,
    /// Channels by name, each row-major.
    pub channels: Vec<(String, Vec<f32>)>,
}

impl ExrChannels {
    /// The channel called `name`.
    pub fn get(&self, name: &str) -> Result<&[f32], ImageError> {
        self.channels
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, v)| v.as_slice())
            .ok_or_else(|| ImageError::MissingChannel(name.to_string()))
    }
}

/// Reads every channel of the first layer of an EXR file (used for references and tests).
pub fn read_exr(bytes: &[u8]) -> Result<ExrChannels, ImageError> {
    let image = read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .from_buffered(Cursor::new(bytes))
        .map_err(|e| ImageError::Exr(e.to_string()))?;
    let size = image.layer_data.size;
    let channels = image
        .layer_data
        .channel_data
        .list
        .iter()
        .map(|c| (c.name.to_string(), c.sample_data.values_as_f32().collect()))
        .collect();
    let metadata = image
        .layer_data
        .attributes
        .other
        .get(&Text::from(METADATA_ATTRIBUTE))
        .and_then(|v| match v {
            AttributeValue::Text(t) => Some(t.to_string()),
            _ => None,
        });
    Ok(ExrChannels {
        metadata,
        width: size.0,
        height: size.1,
        channels,
    })
}
