//! The frame plan: how one frame is cut into tiles and passes, and into work units.

use serde::{Deserialize, Serialize};

/// Largest accepted image width or height, in pixels.
pub const MAX_DIMENSION: u32 = 16384;
/// Smallest accepted tile edge, in pixels.
pub const MIN_TILE_SIZE: u32 = 4;
/// Largest accepted tile edge, in pixels, except for a whole-frame tile (see
/// [`FramePlan::whole_frame`]).
pub const MAX_TILE_SIZE: u32 = 256;
/// Largest frame, in pixels, that may be planned as one whole-frame tile (2^20: a unit
/// result then holds at most 12 MiB of pass means per pass).
pub const MAX_WHOLE_FRAME_PIXELS: u64 = 1 << 20;
/// Largest accepted number of samples per pixel in one pass.
pub const MAX_SAMPLES_PER_PASS: u32 = 1024;
/// Largest accepted number of passes per pixel.
pub const MAX_PASSES: u32 = 65536;
/// Bound on the total work of a frame: `width * height * spp` must not exceed it (2^40).
pub const MAX_FRAME_SAMPLES: u64 = 1 << 40;
/// Cap on the samples per pass chosen by [`FramePlan::for_spp`].
///
/// A pass is one Owen-scrambled `(0, m, 2)`-net per pair of dimensions, and a net of 64
/// points stratifies far better than eight independent nets of 8 (Owen 2001, section 6.7:
/// the variance of a scrambled net falls faster than `1/n` within one net, only like `1/K`
/// across independent replicates); measured in `docs/benchmarks.md`, "Sampling
/// structure". The cap keeps one pass of a large frame short enough for progress and for
/// the farm's (tile, pass range) units.
pub const MAX_AUTO_SAMPLES_PER_PASS: u32 = 64;
/// Cap on the samples per pass of [`FramePlan::whole_frame`] (bdpt). A whole-frame plan's
/// unit is the whole frame, so its duration grows with the pass size: this cap keeps a
/// 1024 x 1024 bdpt unit at 16.8 M paths, within a worker's stop grace period
/// (`docs/deploy.md`): whole-frame units are no longer than before the larger
/// [`MAX_AUTO_SAMPLES_PER_PASS`].
pub const WHOLE_FRAME_MAX_SAMPLES_PER_PASS: u32 = 16;
/// Minimum number of passes [`FramePlan::for_spp`] aims for outside [`LOW_SPP`], and
/// [`FramePlan::whole_frame`] at every spp: 4 replicates, so 3 degrees of freedom for
/// each pixel's own variance (ARCHITECTURE.md §3).
pub const TARGET_MIN_PASSES: u32 = 4;
/// Minimum number of passes [`FramePlan::for_spp`] aims for at [`LOW_SPP`] samples per
/// pixel: 2, the fewest that estimate a variance, so that each pass keeps more of its
/// scrambled net (Owen 2001, section 6.7).
///
/// Measured (`docs/benchmarks.md`, "Sampling structure", 2026-12-06 and its evening): 2
/// passes of `N / 2` have 6-21% less variance than 4 of `N / 4` at 16-64 spp (bench/compare
/// at 64 spp: the Cornell box 0.90, veach-mis 0.81, the glass ball 0.92 of the 4-pass
/// variance; the 2M-triangle scene 0.86 at 16 spp); the pixels' intervals pool their
/// variance over 3x3 pixels (up to 9 degrees of freedom at `K = 2`) at Student's t
/// quantile ([`crate::FrameImage::interval_variance`]), and the image estimate stays
/// calibrated at 2 passes with the robust scale's level [`crate::neighbours_level`] (with
/// the 3x3 mean it was 0.79 of the measured error on veach-mis at 64 spp, below the
/// calibration suite's 0.8). Whole-frame techniques (bdpt, vcm, ppm, mlt) and adaptive
/// plans keep their rules: nothing was measured for them.
pub const LOW_SPP_MIN_PASSES: u32 = 2;
/// The samples per pixel at which [`FramePlan::for_spp`] aims for [`LOW_SPP_MIN_PASSES`]
/// passes: from 16, where the calibration suite was measured (below it, passes of a few
/// samples are skewed and 4 of them keep the estimate closer), to below 256, where a pass
/// of 128 would exceed [`MAX_AUTO_SAMPLES_PER_PASS`] and 4 passes of 64 are what the cap
/// gives anyway.
pub const LOW_SPP: std::ops::Range<u32> = 16..256;

/// Why a frame plan was rejected.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PlanError {
    /// Width or height is zero or larger than [`MAX_DIMENSION`].
    #[error(
        "image size {width}x{height} is invalid: width and height must be in 1..={MAX_DIMENSION}"
    )]
    Size {
        /// Requested width.
        width: u32,
        /// Requested height.
        height: u32,
    },
    /// Tile size outside [`MIN_TILE_SIZE`]..=[`MAX_TILE_SIZE`] (and not a whole-frame tile).
    #[error("tile size {0} is invalid: must be in {MIN_TILE_SIZE}..={MAX_TILE_SIZE}, or the larger image side for one whole-frame tile")]
    TileSize(u32),
    /// A whole-frame tile was asked for a frame larger than [`MAX_WHOLE_FRAME_PIXELS`].
    #[error("a {width}x{height} frame ({pixels} pixels) cannot be one whole-frame tile (bdpt): at most {MAX_WHOLE_FRAME_PIXELS} pixels (e.g. 1024x1024)")]
    WholeFrameTooLarge {
        /// Image width.
        width: u32,
        /// Image height.
        height: u32,
        /// `width * height`.
        pixels: u64,
    },
    /// Samples per pass outside 1..=[`MAX_SAMPLES_PER_PASS`].
    #[error("samples per pass {0} is invalid: must be in 1..={MAX_SAMPLES_PER_PASS}")]
    SamplesPerPass(u32),
    /// Pass count outside 1..=[`MAX_PASSES`].
    #[error("pass count {0} is invalid: must be in 1..={MAX_PASSES}")]
    Passes(u32),
    /// A requested samples-per-pixel count that cannot be planned.
    #[error("{spp} samples per pixel is invalid: must be in 1..={max}")]
    Spp {
        /// Requested samples per pixel.
        spp: u32,
        /// Largest plannable samples per pixel.
        max: u32,
    },
    /// `width * height * spp` exceeds [`MAX_FRAME_SAMPLES`].
    #[error("{width}x{height} pixels at {spp} samples per pixel is {total} samples, more than the limit of {MAX_FRAME_SAMPLES}")]
    TooMuchWork {
        /// Image width.
        width: u32,
        /// Image height.
        height: u32,
        /// Samples per pixel (`samples_per_pass * passes`).
        spp: u32,
        /// `width * height * spp`.
        total: u64,
    },
}

/// How one frame is rendered: the image is cut into square tiles (edge tiles smaller), and
/// every pixel receives `passes` independent passes of `samples_per_pass` samples each.
///
/// A pass is the unit of statistics (ARCHITECTURE.md §3): the mean of its samples is one replicate of
/// the pixel's value. Build plans with [`FramePlan::new`] or [`FramePlan::for_spp`], which
/// validate; deserialization validates too. Methods never panic on a plan built by hand with
/// out-of-range fields (a zero tile size is treated as 1), but such a plan is not supported.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(try_from = "FramePlanFields")]
pub struct FramePlan {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Tile edge in pixels.
    pub tile_size: u32,
    /// Samples per pixel in one pass (`S`).
    pub samples_per_pass: u32,
    /// Passes per pixel (`K`).
    pub passes: u32,
}

/// The unvalidated wire form of a [`FramePlan`]; deserialization goes through
/// [`FramePlan::new`].
#[derive(Deserialize)]
struct FramePlanFields {
    width: u32,
    height: u32,
    tile_size: u32,
    samples_per_pass: u32,
    passes: u32,
}

impl TryFrom<FramePlanFields> for FramePlan {
    type Error = PlanError;
    fn try_from(f: FramePlanFields) -> Result<Self, PlanError> {
        FramePlan::new(f.width, f.height, f.tile_size, f.samples_per_pass, f.passes)
    }
}

impl FramePlan {
    /// Validates and builds a plan.
    ///
    /// Requires `1 <= width, height <= 16384`, `4 <= tile_size <= 256`,
    /// `1 <= samples_per_pass <= 1024`, `1 <= passes <= 65536` and
    /// `width * height * samples_per_pass * passes <= 2^40`.
    pub fn new(
        width: u32,
        height: u32,
        tile_size: u32,
        samples_per_pass: u32,
        passes: u32,
    ) -> Result<Self, PlanError> {
        if !(1..=MAX_DIMENSION).contains(&width) || !(1..=MAX_DIMENSION).contains(&height) {
            return Err(PlanError::Size { width, height });
        }
        if !(MIN_TILE_SIZE..=MAX_TILE_SIZE).contains(&tile_size) {
            // The one exception: a single tile covering the whole frame (bdpt, whose light
            // tracing splats anywhere on the film), of bounded size.
            if tile_size < MIN_TILE_SIZE || tile_size != width.max(height) {
                return Err(PlanError::TileSize(tile_size));
            }
            let pixels = u64::from(width) * u64::from(height);
            if pixels > MAX_WHOLE_FRAME_PIXELS {
                return Err(PlanError::WholeFrameTooLarge {
                    width,
                    height,
                    pixels,
                });
            }
        }
        if !(1..=MAX_SAMPLES_PER_PASS).contains(&samples_per_pass) {
            return Err(PlanError::SamplesPerPass(samples_per_pass));
        }
        if !(1..=MAX_PASSES).contains(&passes) {
            return Err(PlanError::Passes(passes));
        }
        // Both factors are at most 2^10 and 2^16, so the product fits a u32.
        let spp = samples_per_pass * passes;
        let total = u64::from(width) * u64::from(height) * u64::from(spp);
        if total > MAX_FRAME_SAMPLES {
            return Err(PlanError::TooMuchWork {
                width,
                height,
                spp,
                total,
            });
        }
        Ok(Self {
            width,
            height,
            tile_size,
            samples_per_pass,
            passes,
        })
    }

    /// Plans a frame for a requested number of samples per pixel `N`.
    ///
    /// With `m` = [`LOW_SPP_MIN_PASSES`] (2) from 16 to 255 spp ([`LOW_SPP`]) and
    /// [`TARGET_MIN_PASSES`] (4) otherwise, the samples per pass `S` is the largest power of
    /// two not above `max(1, N / m)` (integer division), capped at 64, and halved while the
    /// planned spp `S * ceil(N / S)` would exceed `N` by `N / 4` or more; the pass count is
    /// `K = ceil(N / S)`. So:
    /// - for `N >= m` there are at least `m` passes (exactly 2 for a power of two from 16
    ///   to 128, 4 below 16 and at 256, more beyond the cap): the variance of the mean is
    ///   estimated from the spread between passes and needs at least 2 of them;
    /// - for `N < 4` every pass is a single sample (`S = 1`, `K = N`);
    /// - few, large passes keep the stratification of the scrambled nets: at 64 spp, 2
    ///   passes of 32 have 10-20% less variance than 4 of 16, and at 1024 spp 16 passes of
    ///   64 far less than 64 of 16 (Owen 2001, section 6.7; measured in
    ///   `docs/benchmarks.md`, "Sampling structure"). The price is fewer degrees of freedom
    ///   per pixel: a pixel's `mean +- 2 sqrt(variance)` covers its true value with
    ///   Student's t probability for `K - 1` degrees of freedom (70% at `K = 2`, 86% at
    ///   `K = 4`), so its interval pools the variance of its 3x3 neighbourhood and uses t's
    ///   quantile for the pooled degrees of freedom
    ///   ([`crate::FrameImage::interval_variance`]); the image error estimate, an average
    ///   over pixels, stays calibrated (ARCHITECTURE.md §3);
    /// - `S <= 64` keeps one pass of a large frame short, so progress and the farm's units
    ///   stay fine-grained.
    ///
    /// The planned spp `S * K` exceeds `N` by less than `S` and less than `N / 4` (e.g.
    /// `N = 100` gives `S = 16`, `K = 7`, 112 spp: 4 passes of 32 would be 128). `N` may be
    /// at most `64 * 65536`.
    ///
    /// | N    | S  | K  | spp  |
    /// |------|----|----|------|
    /// | 1    | 1  | 1  | 1    |
    /// | 4    | 1  | 4  | 4    |
    /// | 8    | 2  | 4  | 8    |
    /// | 16   | 8  | 2  | 16   |
    /// | 64   | 32 | 2  | 64   |
    /// | 100  | 16 | 7  | 112  |
    /// | 128  | 64 | 2  | 128  |
    /// | 192  | 64 | 3  | 192  |
    /// | 256  | 64 | 4  | 256  |
    /// | 1000 | 64 | 16 | 1024 |
    pub fn for_spp(width: u32, height: u32, spp: u32, tile_size: u32) -> Result<Self, PlanError> {
        let min_passes = if LOW_SPP.contains(&spp) {
            LOW_SPP_MIN_PASSES
        } else {
            TARGET_MIN_PASSES
        };
        let (samples_per_pass, passes) =
            Self::split_spp(spp, MAX_AUTO_SAMPLES_PER_PASS, min_passes)?;
        Self::new(width, height, tile_size, samples_per_pass, passes)
    }

    /// Plans a frame as **one tile covering the whole frame**, with the passes of
    /// [`FramePlan::for_spp`] but at most [`WHOLE_FRAME_MAX_SAMPLES_PER_PASS`] samples per
    /// pass (64 spp: 4 passes of 16; 1024 spp: 64 of 16), because a unit is then the whole
    /// frame. Bidirectional path tracing needs it: its light tracing
    /// splats onto any pixel, and with one tile every splat lands in the unit being
    /// rendered, so units are (frame, pass range) and the merge stays canonical. The tile
    /// edge is `max(width, height)` (at least [`MIN_TILE_SIZE`]); frames above
    /// [`MAX_WHOLE_FRAME_PIXELS`] are refused with [`PlanError::WholeFrameTooLarge`].
    pub fn whole_frame(width: u32, height: u32, spp: u32) -> Result<Self, PlanError> {
        let (samples_per_pass, passes) =
            Self::split_spp(spp, WHOLE_FRAME_MAX_SAMPLES_PER_PASS, TARGET_MIN_PASSES)?;
        let tile = width.max(height).max(MIN_TILE_SIZE);
        Self::new(width, height, tile, samples_per_pass, passes)
    }

    /// True if one tile covers the whole frame.
    pub fn is_whole_frame(&self) -> bool {
        self.tile_size >= self.width && self.tile_size >= self.height
    }

    /// `(samples_per_pass, passes)` for a requested spp with at most `cap` (a power of
    /// two) samples per pass and at least `min_passes` passes where the spp allows; see
    /// [`FramePlan::for_spp`].
    fn split_spp(spp: u32, cap: u32, min_passes: u32) -> Result<(u32, u32), PlanError> {
        let max = cap * MAX_PASSES;
        if spp == 0 || spp > max {
            return Err(PlanError::Spp { spp, max });
        }
        let target = (spp / min_passes.max(1)).max(1);
        // Largest power of two <= target (target >= 1).
        let mut samples_per_pass = (1u32 << (31 - target.leading_zeros())).min(cap);
        // Passes of spp / 2 may overshoot a spp that is not a power of two by almost half
        // (130 as 3 x 64); never more than a quarter (at 4 passes it cannot happen: the
        // overshoot is below S <= spp / 4). Ends at S = 1, whose overshoot is 0.
        while 4 * (spp.div_ceil(samples_per_pass) * samples_per_pass - spp) >= spp
            && samples_per_pass > 1
        {
            samples_per_pass /= 2;
        }
        let passes = spp.div_ceil(samples_per_pass);
        Ok((samples_per_pass, passes))
    }

    /// Checks that the fields satisfy the rules of [`FramePlan::new`].
    pub fn validate(&self) -> Result<(), PlanError> {
        Self::new(
            self.width,
            self.height,
            self.tile_size,
            self.samples_per_pass,
            self.passes,
        )
        .map(|_| ())
    }

    /// Samples per pixel of the whole plan, `samples_per_pass * passes` (saturating).
    pub fn spp(&self) -> u32 {
        self.samples_per_pass.saturating_mul(self.passes)
    }

    fn edge(&self) -> u32 {
        self.tile_size.max(1)
    }

    /// Number of tile columns.
    pub fn tiles_x(&self) -> u32 {
        self.width.div_ceil(self.edge())
    }

    /// Number of tile rows.
    pub fn tiles_y(&self) -> u32 {
        self.height.div_ceil(self.edge())
    }

    /// Number of tiles, `tiles_x * tiles_y`.
    pub fn tile_count(&self) -> u32 {
        self.tiles_x().saturating_mul(self.tiles_y())
    }

    /// The tile with this index, or `None` if `index >= tile_count()`.
    ///
    /// Tiles are numbered row-major from the top-left; tiles in the last column and row are
    /// narrower or shorter when the image size is not a multiple of the tile size.
    pub fn get_tile(&self, index: u32) -> Option<TileRect> {
        if index >= self.tile_count() {
            return None;
        }
        let edge = self.edge();
        let tiles_x = self.tiles_x();
        // index < tiles_x * tiles_y, so both coordinates are inside the image.
        let x0 = (index % tiles_x) * edge;
        let y0 = (index / tiles_x) * edge;
        Some(TileRect {
            index,
            x0,
            y0,
            width: edge.min(self.width - x0),
            height: edge.min(self.height - y0),
        })
    }

    /// The tile with this index (see [`FramePlan::get_tile`]).
    ///
    /// # Panics
    /// If `index >= tile_count()`. Use [`FramePlan::get_tile`] for untrusted indices.
    pub fn tile(&self, index: u32) -> TileRect {
        match self.get_tile(index) {
            Some(rect) => rect,
            None => panic!(
                "tile index {index} out of range (plan has {} tiles)",
                self.tile_count()
            ),
        }
    }

    /// All tiles in index order.
    pub fn tiles(&self) -> impl Iterator<Item = TileRect> + '_ {
        (0..self.tile_count()).filter_map(move |i| self.get_tile(i))
    }

    /// Number of pass chunks per tile when units hold `passes_per_unit` passes
    /// (a value of 0 is treated as 1).
    pub fn chunks_per_tile(&self, passes_per_unit: u32) -> u32 {
        self.passes.div_ceil(passes_per_unit.max(1))
    }

    /// Number of work units per frame, i.e. the length of [`FramePlan::units`].
    pub fn unit_count(&self, passes_per_unit: u32) -> u64 {
        u64::from(self.tile_count()) * u64::from(self.chunks_per_tile(passes_per_unit))
    }

    /// All work units of one frame in canonical scheduling order, coarse to fine: pass
    /// chunk 0 of every tile (in tile order), then chunk 1 of every tile, and so on, so a
    /// preview covers the whole frame early.
    ///
    /// Chunk `c` holds passes `c * passes_per_unit ..` of its tile; the last chunk holds
    /// the remainder and may be shorter. `passes_per_unit` of 0 is treated as 1; a value
    /// above `passes` gives one unit per tile. See [`FramePlan::unit_iter`] for a lazy
    /// version.
    pub fn units(&self, frame: u32, passes_per_unit: u32) -> Vec<WorkUnit> {
        self.unit_iter(frame, passes_per_unit).collect()
    }

    /// The units of [`FramePlan::units`] as a lazy iterator (no allocation).
    pub fn unit_iter(
        &self,
        frame: u32,
        passes_per_unit: u32,
    ) -> impl Iterator<Item = WorkUnit> + '_ {
        let per = passes_per_unit.max(1);
        let tiles = self.tile_count();
        let chunks = if tiles == 0 {
            0
        } else {
            self.chunks_per_tile(per)
        };
        (0..chunks).flat_map(move |chunk| {
            // chunk < ceil(passes / per), so chunk * per < passes: no overflow.
            let first_pass = chunk * per;
            let pass_count = per.min(self.passes - first_pass);
            (0..tiles).map(move |tile| WorkUnit {
                frame,
                tile,
                first_pass,
                pass_count,
            })
        })
    }
}

/// A rectangle of pixels rendered and merged as one piece.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct TileRect {
    /// Row-major tile index in its plan.
    pub index: u32,
    /// Left pixel column (inclusive).
    pub x0: u32,
    /// Top pixel row (inclusive).
    pub y0: u32,
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
}

impl TileRect {
    /// Number of pixels, `width * height`.
    pub fn pixel_count(&self) -> usize {
        (self.width as usize).saturating_mul(self.height as usize)
    }
}

/// One schedulable piece of work: a contiguous range of passes of one tile of one frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct WorkUnit {
    /// Frame number.
    pub frame: u32,
    /// Tile index in the frame's plan.
    pub tile: u32,
    /// First pass index of the unit.
    pub first_pass: u32,
    /// Number of consecutive passes.
    pub pass_count: u32,
}

impl WorkUnit {
    /// One past the last pass index, widened so it cannot overflow.
    pub fn end_pass(&self) -> u64 {
        u64::from(self.first_pass) + u64::from(self.pass_count)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn new_validates() {
        assert!(FramePlan::new(64, 48, 16, 8, 8).is_ok());
        assert_eq!(
            FramePlan::new(0, 48, 16, 8, 8),
            Err(PlanError::Size {
                width: 0,
                height: 48
            })
        );
        assert!(matches!(
            FramePlan::new(16385, 1, 16, 1, 1),
            Err(PlanError::Size { .. })
        ));
        assert!(matches!(
            FramePlan::new(1, 16385, 16, 1, 1),
            Err(PlanError::Size { .. })
        ));
        assert_eq!(FramePlan::new(8, 8, 3, 1, 1), Err(PlanError::TileSize(3)));
        assert_eq!(
            FramePlan::new(8, 8, 257, 1, 1),
            Err(PlanError::TileSize(257))
        );
        assert!(FramePlan::new(8, 8, 4, 1, 1).is_ok());
        assert!(FramePlan::new(8, 8, 256, 1, 1).is_ok());
        assert_eq!(
            FramePlan::new(8, 8, 8, 0, 1),
            Err(PlanError::SamplesPerPass(0))
        );
        assert_eq!(
            FramePlan::new(8, 8, 8, 1025, 1),
            Err(PlanError::SamplesPerPass(1025))
        );
        assert_eq!(FramePlan::new(8, 8, 8, 1, 0), Err(PlanError::Passes(0)));
        assert_eq!(
            FramePlan::new(8, 8, 8, 1, 65537),
            Err(PlanError::Passes(65537))
        );
        // 16384^2 * 4096 = 2^40 exactly: allowed; one more sample is not.
        assert!(FramePlan::new(16384, 16384, 64, 1024, 4).is_ok());
        assert!(matches!(
            FramePlan::new(16384, 16384, 64, 1, 4097),
            Err(PlanError::TooMuchWork { .. })
        ));
        assert!(matches!(
            FramePlan::new(16384, 16384, 64, 1024, 65536),
            Err(PlanError::TooMuchWork { .. })
        ));
    }

    #[test]
    fn for_spp_choices() {
        let cases = [
            (1, 1, 1),
            (3, 1, 3),
            (4, 1, 4),
            (7, 1, 7),
            (8, 2, 4),
            (15, 2, 8),
            (16, 8, 2),
            (17, 4, 5),
            (25, 4, 7),
            (64, 32, 2),
            (100, 16, 7),
            (128, 64, 2),
            (130, 32, 5),
            (192, 64, 3),
            (200, 32, 7),
            (255, 64, 4),
            (256, 64, 4),
            (1000, 64, 16),
            (1024, 64, 16),
            (4096, 64, 64),
        ];
        for (n, s, k) in cases {
            let p = FramePlan::for_spp(32, 32, n, 16).unwrap();
            assert_eq!((p.samples_per_pass, p.passes), (s, k), "N = {n}");
        }
        // The rule's bounds for every N up to well past the cap: S a power of two, at most
        // 64; at least 2 passes from 16 to 255 spp (exactly 2 for a power of two), at least
        // 4 otherwise, at most 8 until S reaches the cap; overshoot below one pass and
        // below a quarter of N.
        for n in 1..=5000 {
            let p = FramePlan::for_spp(32, 32, n, 16).unwrap();
            let (s, k) = (p.samples_per_pass, p.passes);
            assert!(
                s.is_power_of_two() && s <= MAX_AUTO_SAMPLES_PER_PASS,
                "N = {n}"
            );
            assert!(p.spp() >= n && p.spp() - n < s, "N = {n}");
            assert!(4 * (p.spp() - n) < n, "N = {n}: {s} x {k}");
            let m = if LOW_SPP.contains(&n) {
                LOW_SPP_MIN_PASSES
            } else {
                TARGET_MIN_PASSES
            };
            if n >= m {
                assert!(k >= m, "N = {n}");
            } else {
                assert_eq!((s, k), (1, n), "N = {n}");
            }
            if LOW_SPP.contains(&n) && n.is_power_of_two() {
                assert_eq!(k, 2, "N = {n}");
            }
            if s < MAX_AUTO_SAMPLES_PER_PASS {
                assert!(k <= 2 * TARGET_MIN_PASSES, "N = {n}: {k} passes");
            }
        }
        assert!(matches!(
            FramePlan::for_spp(32, 32, 0, 16),
            Err(PlanError::Spp { .. })
        ));
        assert!(FramePlan::for_spp(1, 1, 64 * 65536, 4).is_ok());
        assert!(matches!(
            FramePlan::for_spp(32, 32, 64 * 65536 + 1, 16),
            Err(PlanError::Spp { .. })
        ));
        assert!(matches!(
            FramePlan::for_spp(32, 32, 64, 2),
            Err(PlanError::TileSize(2))
        ));
    }

    /// Every pixel is covered by exactly one tile, and tiles have the expected shapes.
    fn check_cover(plan: &FramePlan) {
        let (w, h) = (plan.width as usize, plan.height as usize);
        let mut owner = vec![u32::MAX; w * h];
        let mut total = 0usize;
        let mut count = 0u32;
        for (i, t) in plan.tiles().enumerate() {
            assert_eq!(t.index as usize, i);
            assert_eq!(t, plan.tile(t.index));
            assert!(t.width >= 1 && t.width <= plan.tile_size);
            assert!(t.height >= 1 && t.height <= plan.tile_size);
            assert!(t.x0 + t.width <= plan.width && t.y0 + t.height <= plan.height);
            total += t.pixel_count();
            count += 1;
            for y in t.y0..t.y0 + t.height {
                for x in t.x0..t.x0 + t.width {
                    let o = &mut owner[y as usize * w + x as usize];
                    assert_eq!(*o, u32::MAX, "pixel ({x}, {y}) covered twice");
                    *o = t.index;
                }
            }
        }
        assert_eq!(count, plan.tile_count());
        assert_eq!(total, w * h);
        assert!(owner.iter().all(|&o| o != u32::MAX));
        assert_eq!(plan.get_tile(plan.tile_count()), None);
    }

    #[test]
    fn tiles_cover_image_exactly_once() {
        for (w, h, ts) in [
            (64, 48, 16),
            (37, 23, 8),
            (1, 1, 4),
            (3, 100, 4),
            (300, 7, 256),
            (17, 17, 16),
        ] {
            check_cover(&FramePlan::new(w, h, ts, 1, 1).unwrap());
        }
    }

    #[test]
    fn edge_tiles_are_smaller() {
        let p = FramePlan::new(37, 23, 8, 1, 1).unwrap();
        assert_eq!((p.tiles_x(), p.tiles_y(), p.tile_count()), (5, 3, 15));
        assert_eq!(
            p.tile(0),
            TileRect {
                index: 0,
                x0: 0,
                y0: 0,
                width: 8,
                height: 8
            }
        );
        assert_eq!(
            p.tile(4),
            TileRect {
                index: 4,
                x0: 32,
                y0: 0,
                width: 5,
                height: 8
            }
        );
        assert_eq!(
            p.tile(10),
            TileRect {
                index: 10,
                x0: 0,
                y0: 16,
                width: 8,
                height: 7
            }
        );
        assert_eq!(
            p.tile(14),
            TileRect {
                index: 14,
                x0: 32,
                y0: 16,
                width: 5,
                height: 7
            }
        );
    }

    #[test]
    fn units_are_coarse_to_fine_and_cover_every_pass_once() {
        let plan = FramePlan::new(37, 23, 8, 4, 10).unwrap();
        for per in [0, 1, 3, 4, 10, 11, 1000] {
            let units = plan.units(7, per);
            assert_eq!(units.len() as u64, plan.unit_count(per), "per = {per}");
            let mut seen = vec![0u8; (plan.tile_count() * plan.passes) as usize];
            let mut last_first = 0;
            for (i, u) in units.iter().enumerate() {
                assert_eq!(u.frame, 7);
                // Coarse to fine: first_pass never decreases, and within one chunk the
                // tiles appear in order.
                assert!(u.first_pass >= last_first, "per = {per}");
                last_first = u.first_pass;
                assert_eq!(u.tile, i as u32 % plan.tile_count());
                assert!(u.pass_count >= 1 && u.pass_count <= per.max(1));
                assert!(u.end_pass() <= u64::from(plan.passes));
                for p in u.first_pass..u.first_pass + u.pass_count {
                    seen[(u.tile * plan.passes + p) as usize] += 1;
                }
            }
            assert!(seen.iter().all(|&s| s == 1), "per = {per}");
        }
        // Shapes: 3 passes per unit over 10 passes is 3 + 3 + 3 + 1.
        let units = plan.units(0, 3);
        let n = plan.tile_count() as usize;
        assert_eq!(units.len(), 4 * n);
        assert_eq!((units[0].first_pass, units[0].pass_count), (0, 3));
        assert_eq!((units[n].first_pass, units[n].pass_count), (3, 3));
        assert_eq!((units[3 * n].first_pass, units[3 * n].pass_count), (9, 1));
        // More passes per unit than passes: one whole unit per tile.
        let units = plan.units(0, 11);
        assert_eq!(units.len(), n);
        assert!(units
            .iter()
            .all(|u| u.first_pass == 0 && u.pass_count == 10));
    }

    #[test]
    fn deserialization_validates() {
        use serde::de::value::{Error, MapDeserializer};
        let de = |tile_size: u32| {
            let fields = [
                ("width", 64u32),
                ("height", 48),
                ("tile_size", tile_size),
                ("samples_per_pass", 8),
                ("passes", 8),
            ];
            FramePlan::deserialize(MapDeserializer::<_, Error>::new(fields.into_iter()))
        };
        assert_eq!(de(16).unwrap(), FramePlan::new(64, 48, 16, 8, 8).unwrap());
        let err = de(1).unwrap_err().to_string();
        assert!(err.contains("tile size 1 is invalid"), "{err}");
    }

    #[test]
    fn whole_frame_tiles() {
        // Above the tile cap: one tile of edge max(width, height).
        let p = FramePlan::whole_frame(640, 480, 64).unwrap();
        assert_eq!((p.tile_size, p.tile_count()), (640, 1));
        assert_eq!((p.samples_per_pass, p.passes), (16, 4));
        assert!(p.is_whole_frame());
        // The pass size is capped lower than for tiled plans: a unit is the whole frame.
        let p = FramePlan::whole_frame(640, 480, 1024).unwrap();
        assert_eq!((p.samples_per_pass, p.passes), (16, 64));
        assert!(FramePlan::whole_frame(4, 4, 16 * 65536).is_ok());
        assert!(matches!(
            FramePlan::whole_frame(4, 4, 16 * 65536 + 1),
            Err(PlanError::Spp { .. })
        ));
        assert_eq!(
            p.tile(0),
            TileRect {
                index: 0,
                x0: 0,
                y0: 0,
                width: 640,
                height: 480
            }
        );
        check_cover(&p);
        // Small frames: an ordinary plan with one tile (at least the minimum edge).
        let p = FramePlan::whole_frame(3, 2, 4).unwrap();
        assert_eq!((p.tile_size, p.tile_count()), (4, 1));
        assert!(!FramePlan::new(64, 48, 16, 8, 8).unwrap().is_whole_frame());
        // 1024 x 1024 is the largest square whole frame; a pixel more is refused by name.
        assert!(FramePlan::whole_frame(1024, 1024, 1).is_ok());
        assert!(FramePlan::whole_frame(16384, 64, 1).is_ok());
        let err = FramePlan::whole_frame(1025, 1024, 1).unwrap_err();
        assert_eq!(
            err,
            PlanError::WholeFrameTooLarge {
                width: 1025,
                height: 1024,
                pixels: 1025 * 1024
            }
        );
        assert!(err.to_string().contains("at most 1048576 pixels"), "{err}");
        // Large tiles other than the whole frame stay invalid.
        assert_eq!(
            FramePlan::new(640, 480, 480, 1, 1),
            Err(PlanError::TileSize(480))
        );
        assert_eq!(
            FramePlan::new(640, 480, 641, 1, 1),
            Err(PlanError::TileSize(641))
        );
        // Deserialization accepts a whole-frame plan (validation is the same).
        use serde::de::value::{Error, MapDeserializer};
        let fields = [
            ("width", 640u32),
            ("height", 480),
            ("tile_size", 640),
            ("samples_per_pass", 16),
            ("passes", 4),
        ];
        let de = FramePlan::deserialize(MapDeserializer::<_, Error>::new(fields.into_iter()));
        assert_eq!(de.unwrap(), FramePlan::whole_frame(640, 480, 64).unwrap());
    }

    #[test]
    fn hand_built_invalid_plans_do_not_panic() {
        let p = FramePlan {
            width: 10,
            height: 0,
            tile_size: 0,
            samples_per_pass: u32::MAX,
            passes: u32::MAX,
        };
        assert_eq!(p.tile_count(), 0);
        assert_eq!(p.spp(), u32::MAX);
        assert!(p.validate().is_err());
        assert_eq!(p.get_tile(0), None);
        assert_eq!(p.unit_iter(0, 0).count(), 0);
    }
}
