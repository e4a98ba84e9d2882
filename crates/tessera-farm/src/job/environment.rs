//! The `environment` job setting: what lights a scene from every direction rays leave it
//! in — a uniform colour, or an uploaded equirectangular HDR image (Radiance `.hdr` or
//! OpenEXR, stored by content hash like scenes) — with a strength and a rotation about
//! the up axis. Absent by default: a scene is lit only by its own lights.

use serde::{Deserialize, Serialize};

use super::settings::JobError;

/// Largest strength accepted (a factor on the radiance).
pub const MAX_ENVIRONMENT_STRENGTH: f64 = 1e6;

/// Largest radiance per channel of a uniform environment colour, W/(m² sr).
pub const MAX_ENVIRONMENT_RADIANCE: f64 = 1e6;

/// The `environment` field of [`super::JobSettings`], as submitted.
///
/// ```
/// let e: tessera_farm::job::EnvironmentSettings =
///     serde_json::from_str(r#"{"source": "0.5,0.5,0.5", "strength": 2}"#).unwrap();
/// let v = e.validate().unwrap();
/// assert_eq!(v.radiance(), [1.0, 1.0, 1.0]);
/// ```
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EnvironmentSettings {
    /// `"R,G,B"`: a uniform radiance in W/(m² sr) per linear channel; or the 64-hex-digit
    /// content hash of an uploaded equirectangular image (`POST /api/v1/scenes` stores
    /// `.hdr` and `.exr` files too).
    pub source: String,
    /// Factor on the radiance, in [0, 1e6]. Default 1.
    #[serde(default = "one", skip_serializing_if = "is_one")]
    pub strength: f64,
    /// Rotation of the image about the up axis (+Y), degrees, counter-clockwise seen from
    /// above; in [-360, 360]. Default 0.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub rotation_degrees: f64,
}

fn one() -> f64 {
    1.0
}
fn is_one(v: &f64) -> bool {
    *v == 1.0
}
fn is_zero(v: &f64) -> bool {
    *v == 0.0
}

/// Where a validated environment's radiance comes from.
#[derive(Debug, Clone, PartialEq)]
pub enum EnvironmentSource {
    /// A uniform radiance per channel.
    Colour([f32; 3]),
    /// An uploaded image, by the lower-case SHA-256 of its bytes.
    Image(String),
}

/// A validated `environment` setting.
#[derive(Debug, Clone, PartialEq)]
pub struct JobEnvironment {
    /// A colour or an image.
    pub source: EnvironmentSource,
    /// Factor on the radiance, in [0, 1e6].
    pub strength: f32,
    /// Rotation about +Y in degrees, in [-360, 360].
    pub rotation_degrees: f32,
}

impl JobEnvironment {
    /// The radiance factor: the colour times the strength, or (for an image) the strength
    /// on every channel.
    pub fn radiance(&self) -> [f32; 3] {
        match &self.source {
            EnvironmentSource::Colour(c) => c.map(|v| v * self.strength),
            EnvironmentSource::Image(_) => [self.strength; 3],
        }
    }

    /// The canonical raw form (validating it gives back an equal environment).
    pub fn to_settings(&self) -> EnvironmentSettings {
        let source = match &self.source {
            EnvironmentSource::Colour(c) => format!("{},{},{}", c[0], c[1], c[2]),
            EnvironmentSource::Image(h) => h.clone(),
        };
        EnvironmentSettings {
            source,
            strength: f64::from(self.strength),
            rotation_degrees: f64::from(self.rotation_degrees),
        }
    }

    /// The header's record of the environment (JSON object text).
    pub fn metadata_json(&self) -> String {
        let source = match &self.source {
            EnvironmentSource::Colour(c) => format!("[{},{},{}]", c[0], c[1], c[2]),
            EnvironmentSource::Image(h) => format!("\"{h}\""),
        };
        format!(
            "{{\"source\":{source},\"strength\":{},\"rotation_degrees\":{}}}",
            self.strength, self.rotation_degrees
        )
    }
}

impl EnvironmentSettings {
    /// Settings for `source` with strength 1 and no rotation.
    pub fn new(source: impl Into<String>) -> Self {
        Self {
            source: source.into(),
            strength: 1.0,
            rotation_degrees: 0.0,
        }
    }

    /// Checks the fields: errors name `environment.source`, `.strength` or
    /// `.rotation_degrees`.
    pub fn validate(&self) -> Result<JobEnvironment, JobError> {
        let s = self.source.trim();
        let source = if s.len() == 64 && s.bytes().all(|b| b.is_ascii_hexdigit()) {
            EnvironmentSource::Image(s.to_ascii_lowercase())
        } else {
            let parts: Vec<&str> = s.split(',').map(str::trim).collect();
            let values: Option<Vec<f64>> = (parts.len() == 3)
                .then(|| parts.iter().map(|p| p.parse::<f64>().ok()).collect())
                .flatten();
            match values {
                Some(v)
                    if v.iter()
                        .all(|c| c.is_finite() && (0.0..=MAX_ENVIRONMENT_RADIANCE).contains(c)) =>
                {
                    EnvironmentSource::Colour([v[0] as f32, v[1] as f32, v[2] as f32])
                }
                _ => {
                    return Err(JobError::new(
                        "environment.source",
                        format_args!(
                            "expected R,G,B (radiance per channel, 0 to \
                             {MAX_ENVIRONMENT_RADIANCE}) or the 64-hex-digit hash of an \
                             uploaded .hdr/.exr image, got {:?}",
                            self.source
                        ),
                    ))
                }
            }
        };
        if !(self.strength.is_finite() && (0.0..=MAX_ENVIRONMENT_STRENGTH).contains(&self.strength))
        {
            return Err(JobError::new(
                "environment.strength",
                format_args!(
                    "must be in [0, {MAX_ENVIRONMENT_STRENGTH}], got {}",
                    self.strength
                ),
            ));
        }
        if !(self.rotation_degrees.is_finite() && self.rotation_degrees.abs() <= 360.0) {
            return Err(JobError::new(
                "environment.rotation_degrees",
                format_args!("must be in [-360, 360], got {}", self.rotation_degrees),
            ));
        }
        Ok(JobEnvironment {
            source,
            strength: self.strength as f32,
            rotation_degrees: self.rotation_degrees as f32,
        })
    }
}
