//! What rendering a work unit returns, and its validation.

use serde::{Deserialize, Serialize};

use crate::plan::{FramePlan, TileRect, WorkUnit};

/// What rendering a work unit returns: for each pass of the unit (in pass order), for each
/// pixel of the tile (row-major), the pass mean RGB — the average of the pass's
/// `samples_per_pass` samples — as f32 linear radiance.
///
/// `pass_means[p * width * height + y * width + x]` is pass `unit.first_pass + p` of the
/// tile pixel `(x, y)`. Results may come from remote workers: check them with
/// [`UnitResult::validate`] (the accumulators do) before trusting any field.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct UnitResult {
    /// The unit that was rendered.
    pub unit: WorkUnit,
    /// Tile width in pixels.
    pub width: u32,
    /// Tile height in pixels.
    pub height: u32,
    /// Pass means, pass-major then row-major (`pass_count * width * height` values).
    pub pass_means: Vec<[f32; 3]>,
    /// Samples the renderer dropped as NaN, infinite or negative radiance (a renderer bug,
    /// not light; each counts as black in its pass mean). Diagnostic only: not validated,
    /// not merged and not part of [`UnitResult::digest`]. Missing in older serialized
    /// results, where it reads as 0.
    #[serde(default)]
    pub rejected_samples: u64,
    /// The renderer's per-pass estimate of its own bias, for techniques that are biased
    /// (vertex merging: vcm and ppm), `None` for every unbiased one: one signed luminance
    /// per pass and pixel, laid out as `pass_means`
    /// (`bias[p * width * height + y * width + x]`). Each is the leading term of the
    /// expected error of that pass mean
    /// (`E[pass mean] - true value`, Hachisuka, Jarosz & Jensen 2010, section 4), itself a
    /// noisy, unbiased estimate of it, so the merge keeps its spread beside its mean
    /// (ARCHITECTURE.md §3, "Biased techniques: the bias term"). Absent from the serialized form and from
    /// [`UnitResult::digest`] when `None`, so unbiased results keep their bytes and
    /// digests.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bias: Option<Vec<f32>>,
}

/// Why a unit result was rejected. Messages name the offending field and value.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ResultError {
    /// The tile index is not in the plan.
    #[error("tile {tile} does not exist (the plan has {tile_count} tiles)")]
    UnknownTile {
        /// Tile index of the result.
        tile: u32,
        /// Number of tiles in the plan.
        tile_count: u32,
    },
    /// The result is for a different tile than the accumulator it was offered to.
    #[error("result is for tile {tile}, offered to the accumulator of tile {expected}")]
    WrongTile {
        /// Tile index of the result.
        tile: u32,
        /// Tile of the accumulator.
        expected: u32,
    },
    /// `width` or `height` differs from the tile's.
    #[error("tile {tile}: {field} {value} != {expected}")]
    Dimension {
        /// Tile index.
        tile: u32,
        /// `"width"` or `"height"`.
        field: &'static str,
        /// Value in the result.
        value: u32,
        /// The tile's value.
        expected: u32,
    },
    /// `pass_count` is 0.
    #[error("tile {tile}: pass_count is 0")]
    NoPasses {
        /// Tile index.
        tile: u32,
    },
    /// The pass range extends beyond the plan's passes.
    #[error("tile {tile}: passes {first_pass}..{end_pass} are outside the plan's {passes} passes")]
    PassRange {
        /// Tile index.
        tile: u32,
        /// First pass of the result.
        first_pass: u32,
        /// One past the last pass of the result.
        end_pass: u64,
        /// Passes in the plan.
        passes: u32,
    },
    /// `pass_means` has the wrong length.
    #[error("tile {tile}: pass_means has {len} values, expected {expected} (pass_count {pass_count} x {pixels} pixels)")]
    Length {
        /// Tile index.
        tile: u32,
        /// Actual length.
        len: usize,
        /// `pass_count * pixels`.
        expected: u64,
        /// Passes in the unit.
        pass_count: u32,
        /// Pixels in the tile.
        pixels: usize,
    },
    /// A value is NaN or infinite.
    #[error("pass_means[{index}] is {value} (channel {channel} of pixel {pixel} in pass {pass})")]
    NonFinite {
        /// Index into `pass_means`.
        index: usize,
        /// Colour channel (0 = R, 1 = G, 2 = B).
        channel: usize,
        /// Pixel index within the tile (row-major).
        pixel: usize,
        /// Absolute pass index.
        pass: u64,
        /// The offending value.
        value: f32,
    },
    /// A value is negative (radiance cannot be).
    #[error("pass_means[{index}] is negative: {value} (channel {channel} of pixel {pixel} in pass {pass})")]
    Negative {
        /// Index into `pass_means`.
        index: usize,
        /// Colour channel (0 = R, 1 = G, 2 = B).
        channel: usize,
        /// Pixel index within the tile (row-major).
        pixel: usize,
        /// Absolute pass index.
        pass: u64,
        /// The offending value.
        value: f32,
    },
    /// A value is larger than [`MAX_PASS_MEAN`]: no render gives such a mean, and merged
    /// its square would overflow the variance sums to infinity.
    #[error("pass_means[{index}] is {value}, above the bound {MAX_PASS_MEAN:e} (channel {channel} of pixel {pixel} in pass {pass})")]
    TooLarge {
        /// Index into `pass_means`.
        index: usize,
        /// Colour channel (0 = R, 1 = G, 2 = B).
        channel: usize,
        /// Pixel index within the tile (row-major).
        pixel: usize,
        /// Absolute pass index.
        pass: u64,
        /// The offending value.
        value: f32,
    },
    /// The bias channel's length differs from `pass_means`'.
    #[error("tile {tile}: bias has {len} values, expected {expected} (one per pass mean)")]
    BiasLength {
        /// Tile index.
        tile: u32,
        /// Actual length.
        len: usize,
        /// The length of `pass_means`.
        expected: usize,
    },
    /// A bias value is NaN, infinite or larger in magnitude than [`MAX_PASS_MEAN`].
    #[error("bias[{index}] is {value}, not finite within +-{MAX_PASS_MEAN:e} (pixel {pixel} in pass {pass})")]
    BiasValue {
        /// Index into `bias`.
        index: usize,
        /// Pixel index within the tile (row-major).
        pixel: usize,
        /// Absolute pass index.
        pass: u64,
        /// The offending value.
        value: f32,
    },
}

/// The largest pass mean a result may carry. A pass mean is an average of radiance
/// samples; a worker reporting more is faulty or hostile. The bound keeps what the merge
/// and the images derive from pass means finite in `f32`: the square of a mean (1e32) times
/// the most passes a plan has (65,536) stays below `f32::MAX` (3.4e38), so a tile's sums of
/// squares and the EXR's variance layers cannot overflow to infinity.
pub const MAX_PASS_MEAN: f32 = 1.0e16;

impl UnitResult {
    /// Checks the result against a plan: the tile exists, `width`/`height` equal the tile's,
    /// `pass_count >= 1` and the passes lie within the plan, `pass_means` has
    /// `pass_count * pixels` values, and every value is finite, `>= 0` (`-0.0` is
    /// accepted) and at most [`MAX_PASS_MEAN`]. The frame number is not checked (a plan is the same for every frame).
    pub fn validate(&self, plan: &FramePlan) -> Result<(), ResultError> {
        let tile = self.unit.tile;
        let rect = plan.get_tile(tile).ok_or(ResultError::UnknownTile {
            tile,
            tile_count: plan.tile_count(),
        })?;
        self.validate_shape(&rect)?;
        if self.unit.end_pass() > u64::from(plan.passes) {
            return Err(ResultError::PassRange {
                tile,
                first_pass: self.unit.first_pass,
                end_pass: self.unit.end_pass(),
                passes: plan.passes,
            });
        }
        self.validate_values(&rect)
    }

    /// Checks the result against one tile alone: everything [`UnitResult::validate`] checks
    /// except the upper bound of the pass range, which needs the plan (the range must still
    /// end within `u32`).
    pub fn validate_for_tile(&self, rect: &TileRect) -> Result<(), ResultError> {
        if self.unit.tile != rect.index {
            return Err(ResultError::WrongTile {
                tile: self.unit.tile,
                expected: rect.index,
            });
        }
        self.validate_shape(rect)?;
        if self.unit.end_pass() > u64::from(u32::MAX) {
            return Err(ResultError::PassRange {
                tile: rect.index,
                first_pass: self.unit.first_pass,
                end_pass: self.unit.end_pass(),
                passes: u32::MAX,
            });
        }
        self.validate_values(rect)
    }

    fn validate_shape(&self, rect: &TileRect) -> Result<(), ResultError> {
        let tile = rect.index;
        for (field, value, expected) in [
            ("width", self.width, rect.width),
            ("height", self.height, rect.height),
        ] {
            if value != expected {
                return Err(ResultError::Dimension {
                    tile,
                    field,
                    value,
                    expected,
                });
            }
        }
        if self.unit.pass_count == 0 {
            return Err(ResultError::NoPasses { tile });
        }
        let pixels = rect.pixel_count();
        let expected = u64::from(self.unit.pass_count).saturating_mul(pixels as u64);
        if self.pass_means.len() as u64 != expected {
            return Err(ResultError::Length {
                tile,
                len: self.pass_means.len(),
                expected,
                pass_count: self.unit.pass_count,
                pixels,
            });
        }
        Ok(())
    }

    fn validate_values(&self, rect: &TileRect) -> Result<(), ResultError> {
        let pixels = rect.pixel_count().max(1);
        if let Some(bias) = &self.bias {
            if bias.len() != self.pass_means.len() {
                return Err(ResultError::BiasLength {
                    tile: rect.index,
                    len: bias.len(),
                    expected: self.pass_means.len(),
                });
            }
            // Signed (a blur lowers peaks and raises valleys), but bounded like the pass
            // means, so that its square stays finite in the merged statistics.
            if let Some((index, &value)) = bias
                .iter()
                .enumerate()
                .find(|(_, v)| !(v.is_finite() && v.abs() <= MAX_PASS_MEAN))
            {
                return Err(ResultError::BiasValue {
                    index,
                    pixel: index % pixels,
                    pass: u64::from(self.unit.first_pass) + (index / pixels) as u64,
                    value,
                });
            }
        }
        for (index, rgb) in self.pass_means.iter().enumerate() {
            for (channel, &value) in rgb.iter().enumerate() {
                // `!(value >= 0.0)` also catches NaN; finiteness is reported first.
                if (0.0..=MAX_PASS_MEAN).contains(&value) {
                    continue;
                }
                let pixel = index % pixels;
                let pass = u64::from(self.unit.first_pass) + (index / pixels) as u64;
                return Err(if value > MAX_PASS_MEAN && value.is_finite() {
                    ResultError::TooLarge {
                        index,
                        channel,
                        pixel,
                        pass,
                        value,
                    }
                } else if value.is_finite() {
                    ResultError::Negative {
                        index,
                        channel,
                        pixel,
                        pass,
                        value,
                    }
                } else {
                    ResultError::NonFinite {
                        index,
                        channel,
                        pixel,
                        pass,
                        value,
                    }
                });
            }
        }
        Ok(())
    }

    /// A deterministic 64-bit digest of the whole result, for comparing duplicates.
    ///
    /// FNV-1a (64-bit) over the little-endian bytes of `frame, tile, first_pass,
    /// pass_count, width, height` (u32 each), the length of `pass_means` (u64), then the
    /// exact bits of every value (`f32::to_bits`, channel by channel); with a bias channel
    /// ([`UnitResult::bias`]), then its length (u64) and the bits of its values. Stable
    /// across platforms and versions; `0.0` and `-0.0` differ. A result without a bias
    /// channel has the digest it had before the channel existed.
    pub fn digest(&self) -> u64 {
        let mut h = Fnv1a::new();
        for v in [
            self.unit.frame,
            self.unit.tile,
            self.unit.first_pass,
            self.unit.pass_count,
            self.width,
            self.height,
        ] {
            h.write(&v.to_le_bytes());
        }
        h.write(&(self.pass_means.len() as u64).to_le_bytes());
        for rgb in &self.pass_means {
            for v in rgb {
                h.write(&v.to_bits().to_le_bytes());
            }
        }
        if let Some(bias) = &self.bias {
            h.write(&(bias.len() as u64).to_le_bytes());
            for v in bias {
                h.write(&v.to_bits().to_le_bytes());
            }
        }
        h.finish()
    }
}

/// 64-bit FNV-1a.
struct Fnv1a(u64);

impl Fnv1a {
    const OFFSET: u64 = 0xcbf2_9ce4_8422_2325;
    const PRIME: u64 = 0x0000_0100_0000_01b3;

    fn new() -> Self {
        Self(Self::OFFSET)
    }

    #[inline]
    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 ^= u64::from(b);
            self.0 = self.0.wrapping_mul(Self::PRIME);
        }
    }

    fn finish(&self) -> u64 {
        self.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn plan() -> FramePlan {
        FramePlan::new(37, 23, 8, 4, 10).unwrap()
    }

    fn result(plan: &FramePlan, tile: u32, first_pass: u32, pass_count: u32) -> UnitResult {
        let rect = plan.tile(tile);
        let n = pass_count as usize * rect.pixel_count();
        UnitResult {
            unit: WorkUnit {
                frame: 0,
                tile,
                first_pass,
                pass_count,
            },
            width: rect.width,
            height: rect.height,
            pass_means: (0..n).map(|i| [i as f32, 0.5, 0.25]).collect(),
            rejected_samples: 0,
            bias: None,
        }
    }

    #[test]
    fn fnv1a_reference_values() {
        // Published FNV-1a 64 test vectors.
        let hash = |s: &[u8]| {
            let mut h = Fnv1a::new();
            h.write(s);
            h.finish()
        };
        assert_eq!(hash(b""), 0xcbf29ce484222325);
        assert_eq!(hash(b"a"), 0xaf63dc4c8601ec8c);
        assert_eq!(hash(b"foobar"), 0x85944171f73967e8);
    }

    #[test]
    fn valid_results_pass() {
        let p = plan();
        // Edge tile 14 is 5x7; unit covering the last passes.
        result(&p, 14, 7, 3).validate(&p).unwrap();
        result(&p, 0, 0, 10).validate(&p).unwrap();
        let mut r = result(&p, 3, 0, 1);
        r.pass_means[0] = [-0.0, 0.0, MAX_PASS_MEAN];
        r.validate(&p).unwrap();
        r.validate_for_tile(&p.tile(3)).unwrap();
        // Beyond the bound: its square would overflow the merged statistics.
        r.pass_means[0] = [-0.0, 0.0, f32::MAX];
        assert!(matches!(
            r.validate(&p),
            Err(ResultError::TooLarge { channel: 2, .. })
        ));
    }

    #[test]
    fn errors_name_the_problem() {
        let p = plan();
        let msg = |r: &UnitResult| r.validate(&p).unwrap_err().to_string();

        let mut r = result(&p, 7, 0, 1);
        r.width = 31;
        assert_eq!(msg(&r), "tile 7: width 31 != 8");
        let mut r = result(&p, 14, 0, 1);
        r.height = 8;
        assert_eq!(msg(&r), "tile 14: height 8 != 7");

        let mut r = result(&p, 2, 0, 1);
        r.unit.tile = 15;
        assert_eq!(msg(&r), "tile 15 does not exist (the plan has 15 tiles)");

        let r = result(&p, 2, 8, 3);
        assert_eq!(
            msg(&r),
            "tile 2: passes 8..11 are outside the plan's 10 passes"
        );
        let mut r = result(&p, 2, 0, 1);
        r.unit.first_pass = u32::MAX;
        assert!(matches!(r.validate(&p), Err(ResultError::PassRange { .. })));

        let mut r = result(&p, 2, 0, 1);
        r.unit.pass_count = 0;
        r.pass_means.clear();
        assert_eq!(msg(&r), "tile 2: pass_count is 0");

        let mut r = result(&p, 2, 0, 2);
        r.pass_means.pop();
        assert_eq!(
            msg(&r),
            "tile 2: pass_means has 127 values, expected 128 (pass_count 2 x 64 pixels)"
        );
        let mut r = result(&p, 2, 0, 2);
        r.unit.pass_count = u32::MAX;
        r.unit.first_pass = 0;
        assert!(matches!(r.validate(&p), Err(ResultError::Length { .. })));

        let mut r = result(&p, 2, 3, 2);
        r.pass_means[70][1] = f32::NAN;
        assert_eq!(
            msg(&r),
            "pass_means[70] is NaN (channel 1 of pixel 6 in pass 4)"
        );
        let mut r = result(&p, 2, 0, 1);
        r.pass_means[12][2] = f32::INFINITY;
        assert_eq!(
            msg(&r),
            "pass_means[12] is inf (channel 2 of pixel 12 in pass 0)"
        );
        let mut r = result(&p, 2, 0, 1);
        r.pass_means[5][0] = -0.5;
        assert_eq!(
            msg(&r),
            "pass_means[5] is negative: -0.5 (channel 0 of pixel 5 in pass 0)"
        );

        let r = result(&p, 2, 0, 1);
        assert_eq!(
            r.validate_for_tile(&p.tile(3)).unwrap_err().to_string(),
            "result is for tile 2, offered to the accumulator of tile 3"
        );
    }

    #[test]
    fn digest_is_deterministic_and_sensitive() {
        let p = plan();
        let r = result(&p, 4, 2, 3);
        assert_eq!(r.digest(), r.clone().digest());
        let mut m = r.clone();
        m.pass_means[17][1] = f32::from_bits(m.pass_means[17][1].to_bits() ^ 1);
        assert_ne!(r.digest(), m.digest());
        let mut m = r.clone();
        m.unit.frame = 1;
        assert_ne!(r.digest(), m.digest());
        let mut z = result(&p, 4, 2, 1);
        let zd = z.digest();
        z.pass_means[0][0] = -0.0;
        assert_ne!(zd, z.digest());
    }

    #[test]
    fn rejected_samples_are_outside_the_digest_and_validation() {
        // Stored digests of merged units must keep matching re-rendered duplicates, and the
        // count is a diagnostic the merge does not judge.
        let p = plan();
        let r = result(&p, 4, 2, 3);
        let mut m = r.clone();
        m.rejected_samples = 12;
        assert_eq!(r.digest(), m.digest());
        m.validate(&p).unwrap();
    }

    /// The bias channel: checked for length and finiteness (negative values are valid),
    /// part of the digest only when present.
    #[test]
    fn bias_channel_is_validated_and_digested() {
        let p = plan();
        let r = result(&p, 4, 2, 3);
        let plain = r.digest();
        let mut b = r.clone();
        b.bias = Some(vec![-0.25; r.pass_means.len()]);
        b.validate(&p).unwrap();
        assert_ne!(b.digest(), plain);
        let mut c = b.clone();
        c.bias.as_mut().unwrap()[3] = -0.5;
        assert_ne!(c.digest(), b.digest());
        c.bias.as_mut().unwrap()[3] = f32::NAN;
        assert!(matches!(
            c.validate(&p),
            Err(ResultError::BiasValue { index: 3, .. })
        ));
        c.bias.as_mut().unwrap()[3] = -2.0 * MAX_PASS_MEAN;
        assert!(c.validate(&p).is_err());
        c.bias.as_mut().unwrap().pop();
        assert!(matches!(
            c.validate(&p),
            Err(ResultError::BiasLength { .. })
        ));
        // Absent: the serialized form has no field, and old serialized results read.
        let json = serde_json::to_string(&r).unwrap();
        assert!(!json.contains("bias"), "{json}");
        let back: UnitResult = serde_json::from_str(&json).unwrap();
        assert_eq!(back, r);
        assert_eq!(back.digest(), plain);
    }
}
