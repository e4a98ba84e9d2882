//! Canonical merging of unit results into tile and frame statistics.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use crate::plan::{FramePlan, PlanError, TileRect};
use crate::result::{ResultError, UnitResult};
use crate::stats::{BiasStats, PixelStats};

/// What [`TileAccumulator::offer`] / [`FrameAccumulator::offer`] did with a result.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Offer {
    /// The result extended the contiguous prefix of merged passes and was folded in,
    /// together with any buffered results that became contiguous.
    Merged {
        /// Number of passes merged by this offer (this result's and any released buffered
        /// ones); the new total is [`TileAccumulator::merged_passes`].
        passes_merged: u32,
    },
    /// The result was accepted and buffered until the passes before it are merged.
    Buffered,
    /// The result covers exactly the passes of a unit already merged or buffered; nothing
    /// changed.
    Duplicate {
        /// Whether its digest equals the stored one. `false` means two renders of the same
        /// work differ: a faulty worker, or non-deterministic rendering.
        identical: bool,
    },
}

/// Why a result could not be merged. The accumulator is unchanged after any error.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MergeError {
    /// The result failed validation.
    #[error("invalid result: {0}")]
    Invalid(#[from] ResultError),
    /// The result belongs to another frame.
    #[error("result is for frame {frame}, the accumulator holds frame {expected}")]
    WrongFrame {
        /// Frame of the result.
        frame: u32,
        /// Frame of the accumulator.
        expected: u32,
    },
    /// The result's passes partly overlap an earlier unit without being exactly that unit.
    #[error("tile {tile}: passes {first_pass}..{end_pass} overlap the earlier unit with passes {other_first}..{other_end}")]
    Overlap {
        /// Tile index.
        tile: u32,
        /// First pass of the result.
        first_pass: u32,
        /// One past the last pass of the result.
        end_pass: u64,
        /// First pass of the earlier unit.
        other_first: u32,
        /// One past the last pass of the earlier unit.
        other_end: u64,
    },
}

/// A buffered unit's pass means and bias channel ([`UnitResult::bias`]).
type Pending = (Vec<[f32; 3]>, Option<Vec<f32>>);

/// Bookkeeping for one accepted unit of a tile.
#[derive(Debug, Clone)]
struct UnitRecord {
    pass_count: u32,
    digest: u64,
    /// The pass means and the bias channel while the unit waits for earlier passes;
    /// `None` once merged.
    pending: Option<Pending>,
}

/// The merged state of one tile: its pixels' statistics over passes `0..merged_passes`,
/// merged strictly in pass order.
///
/// Results may arrive in any order. A result is buffered until it extends the contiguous
/// prefix of merged passes, then folded pass by pass in pass order, so the statistics are
/// bit-identical however the passes were split into units and in whatever order they
/// arrived (ARCHITECTURE.md §2). Every accepted unit's pass range and digest are remembered for
/// duplicate detection.
#[derive(Debug, Clone)]
pub struct TileAccumulator {
    rect: TileRect,
    pixels: Vec<PixelStats>,
    merged_passes: u32,
    /// The statistics of the bias channel ([`UnitResult::bias`]), per pixel: `Some` only
    /// while every merged unit carried one (vcm and ppm), from the first pass on.
    bias: Option<Vec<BiasStats>>,
    /// Accepted units keyed by first pass; their ranges never overlap, and those below
    /// `merged_passes` tile `0..merged_passes` exactly.
    units: BTreeMap<u32, UnitRecord>,
}

impl TileAccumulator {
    /// An empty accumulator for one tile (allocates `rect.pixel_count()` statistics).
    pub fn new(rect: TileRect) -> Self {
        Self {
            rect,
            pixels: vec![PixelStats::default(); rect.pixel_count()],
            merged_passes: 0,
            bias: None,
            units: BTreeMap::new(),
        }
    }

    /// Offers a result for this tile.
    ///
    /// The result is checked with [`UnitResult::validate_for_tile`] (pass ranges are only
    /// bounded by `u32` here; [`FrameAccumulator::offer`] bounds them by the plan). Units
    /// may arrive in any order; each must either overlap no earlier unit or cover exactly
    /// the passes of one, in which case it is a duplicate: its digest is compared with the
    /// stored one and [`Offer::Duplicate`] is returned without merging. Partial overlap is
    /// [`MergeError::Overlap`]. On any error the accumulator is unchanged.
    pub fn offer(&mut self, result: UnitResult) -> Result<Offer, MergeError> {
        result.validate_for_tile(&self.rect)?;
        self.offer_validated(result)
    }

    /// [`TileAccumulator::offer`] for a result already validated against this tile.
    fn offer_validated(&mut self, result: UnitResult) -> Result<Offer, MergeError> {
        let first = result.unit.first_pass;
        let count = result.unit.pass_count;
        let end = result.unit.end_pass();

        // The unit starting at or before `first`, then the first one starting after it.
        if let Some((&f, rec)) = self.units.range(..=first).next_back() {
            if f == first && rec.pass_count == count {
                return Ok(Offer::Duplicate {
                    identical: rec.digest == result.digest(),
                });
            }
            let rec_end = u64::from(f) + u64::from(rec.pass_count);
            if rec_end > u64::from(first) {
                return Err(self.overlap(first, end, f, rec_end));
            }
        }
        if let Some((&f, rec)) = self.units.range(first.saturating_add(1)..).next() {
            if u64::from(f) < end {
                let rec_end = u64::from(f) + u64::from(rec.pass_count);
                return Err(self.overlap(first, end, f, rec_end));
            }
        }

        let digest = result.digest();
        if first != self.merged_passes {
            self.units.insert(
                first,
                UnitRecord {
                    pass_count: count,
                    digest,
                    pending: Some((result.pass_means, result.bias)),
                },
            );
            return Ok(Offer::Buffered);
        }
        self.units.insert(
            first,
            UnitRecord {
                pass_count: count,
                digest,
                pending: None,
            },
        );
        self.fold(&result.pass_means, result.bias.as_deref(), count);
        let mut passes_merged = count;
        // Release buffered units that are now contiguous.
        while let Some(rec) = self.units.get_mut(&self.merged_passes) {
            let Some((means, bias)) = rec.pending.take() else {
                break;
            };
            let n = rec.pass_count;
            self.fold(&means, bias.as_deref(), n);
            passes_merged = passes_merged.saturating_add(n);
        }
        Ok(Offer::Merged { passes_merged })
    }

    fn overlap(&self, first: u32, end: u64, other_first: u32, other_end: u64) -> MergeError {
        MergeError::Overlap {
            tile: self.rect.index,
            first_pass: first,
            end_pass: end,
            other_first,
            other_end,
        }
    }

    /// Folds `pass_count` passes of validated means (pass-major) into the statistics, pass
    /// by pass, and advances `merged_passes`. The bias channel is kept only while every
    /// unit from pass 0 on carries one: a unit without it (a technique or a worker that
    /// does not send it) drops the tile's bias statistics for good, and the estimate falls
    /// back to the pass spread alone rather than mixing passes with and without it.
    fn fold(&mut self, means: &[[f32; 3]], bias: Option<&[f32]>, pass_count: u32) {
        let n = self.pixels.len();
        if n > 0 {
            for pass in means.chunks_exact(n) {
                for (stats, &rgb) in self.pixels.iter_mut().zip(pass) {
                    stats.push(rgb);
                }
            }
        }
        match (bias, self.bias.as_mut()) {
            (Some(b), None) if self.merged_passes == 0 && n > 0 => {
                let mut stats = vec![BiasStats::default(); n];
                for pass in b.chunks_exact(n) {
                    for (s, &v) in stats.iter_mut().zip(pass) {
                        s.push(v);
                    }
                }
                self.bias = Some(stats);
            }
            (Some(b), Some(stats)) if n > 0 => {
                for pass in b.chunks_exact(n) {
                    for (s, &v) in stats.iter_mut().zip(pass) {
                        s.push(v);
                    }
                }
            }
            _ => self.bias = None,
        }
        self.merged_passes = self.merged_passes.saturating_add(pass_count);
    }

    /// Number of passes merged: every pixel's statistics cover passes `0..merged_passes()`.
    pub fn merged_passes(&self) -> u32 {
        self.merged_passes
    }

    /// Per-pixel statistics, row-major within the tile.
    pub fn pixels(&self) -> &[PixelStats] {
        &self.pixels
    }

    /// Per-pixel statistics of the bias channel ([`UnitResult::bias`]), row-major within
    /// the tile, when every merged unit carried one.
    pub fn bias(&self) -> Option<&[BiasStats]> {
        self.bias.as_deref()
    }

    /// Restores the bias statistics of a tile rebuilt by [`TileAccumulator::restore`]
    /// from a checkpoint that holds them; refuses statistics of another pixel count or
    /// of other passes than the tile's.
    pub fn restore_bias(&mut self, bias: Vec<BiasStats>) -> Result<(), String> {
        if bias.len() != self.pixels.len()
            || bias
                .iter()
                .zip(&self.pixels)
                .any(|(b, p)| b.passes != p.passes)
        {
            return Err(format!(
                "tile {}: the checkpoint's bias statistics do not match its pixels",
                self.rect.index
            ));
        }
        self.bias = Some(bias);
        Ok(())
    }

    /// The tile.
    pub fn rect(&self) -> TileRect {
        self.rect
    }

    /// Number of accepted units still waiting for earlier passes.
    pub fn buffered_units(&self) -> usize {
        self.units.values().filter(|r| r.pending.is_some()).count()
    }

    /// The merged units `(first_pass, pass_count, digest)` in pass order: they tile
    /// `0..merged_passes()` exactly. Buffered units are not included (a checkpoint holds
    /// only merged state; buffered work is simply rendered again after a restart).
    pub fn merged_units(&self) -> impl Iterator<Item = (u32, u32, u64)> + '_ {
        self.units
            .range(..self.merged_passes)
            .filter(|(_, r)| r.pending.is_none())
            .map(|(&f, r)| (f, r.pass_count, r.digest))
    }

    /// Rebuilds a tile from a checkpoint: per-pixel statistics over passes
    /// `0..merged_passes` and the merged units `(first_pass, pass_count, digest)`.
    ///
    /// The restored accumulator continues bit-identically: merging the remaining passes
    /// gives the same statistics as an uninterrupted merge, because the Welford state is
    /// restored exactly (ARCHITECTURE.md §2, §6). Refuses a checkpoint whose pixel count does not
    /// match the tile, whose units do not tile `0..merged_passes` contiguously, or whose
    /// pixels claim more passes than were merged.
    pub fn restore(
        rect: TileRect,
        merged_passes: u32,
        pixels: Vec<PixelStats>,
        units: &[(u32, u32, u64)],
    ) -> Result<Self, String> {
        if pixels.len() != rect.pixel_count() {
            return Err(format!(
                "tile {} has {} pixels, the checkpoint {}",
                rect.index,
                rect.pixel_count(),
                pixels.len()
            ));
        }
        if let Some(p) = pixels.iter().find(|p| p.passes > merged_passes) {
            return Err(format!(
                "tile {}: a pixel has {} passes, more than the {merged_passes} merged",
                rect.index, p.passes
            ));
        }
        let mut map = BTreeMap::new();
        let mut next = 0u32;
        for &(first, count, digest) in units {
            if first != next || count == 0 {
                return Err(format!(
                    "tile {}: merged units are not contiguous at pass {next}",
                    rect.index
                ));
            }
            next = first.checked_add(count).ok_or("pass range overflows")?;
            map.insert(
                first,
                UnitRecord {
                    pass_count: count,
                    digest,
                    pending: None,
                },
            );
        }
        if next != merged_passes {
            return Err(format!(
                "tile {}: units cover passes 0..{next}, the checkpoint says {merged_passes}",
                rect.index
            ));
        }
        Ok(Self {
            rect,
            pixels,
            merged_passes,
            bias: None,
            units: map,
        })
    }
}

/// A whole frame being merged: one [`TileAccumulator`] per tile of the plan, plus
/// image-level views.
#[derive(Debug, Clone)]
pub struct FrameAccumulator {
    plan: FramePlan,
    frame: u32,
    tiles: Vec<TileAccumulator>,
}

impl FrameAccumulator {
    /// Bytes of merge state per pixel (one [`PixelStats`]); what the coordinator's memory
    /// budget counts.
    pub const BYTES_PER_PIXEL: u64 = std::mem::size_of::<PixelStats>() as u64;

    /// An empty accumulator for frame 0 of a plan; see [`FrameAccumulator::for_frame`].
    ///
    /// # Panics
    /// If the plan is invalid ([`FramePlan::validate`] fails), which cannot happen for
    /// plans from [`FramePlan::new`], [`FramePlan::for_spp`] or deserialization. Use
    /// [`FrameAccumulator::try_new`] for plans assembled by hand.
    pub fn new(plan: FramePlan) -> Self {
        Self::for_frame(plan, 0)
    }

    /// An empty accumulator for the given frame of a plan; results of other frames are
    /// rejected with [`MergeError::WrongFrame`].
    ///
    /// # Panics
    /// If the plan is invalid, as for [`FrameAccumulator::new`].
    pub fn for_frame(plan: FramePlan, frame: u32) -> Self {
        match Self::try_new(plan, frame) {
            Ok(acc) => acc,
            Err(e) => panic!("FrameAccumulator needs a valid plan: {e}"),
        }
    }

    /// An empty accumulator for the given frame, or the reason the plan is invalid.
    pub fn try_new(plan: FramePlan, frame: u32) -> Result<Self, PlanError> {
        plan.validate()?;
        Ok(Self {
            plan,
            frame,
            tiles: plan.tiles().map(TileAccumulator::new).collect(),
        })
    }

    /// The plan.
    pub fn plan(&self) -> &FramePlan {
        &self.plan
    }

    /// The frame number this accumulator accepts.
    pub fn frame(&self) -> u32 {
        self.frame
    }

    /// Offers a result: checks the frame, validates it against the plan
    /// ([`UnitResult::validate`]), then offers it to its tile (see
    /// [`TileAccumulator::offer`]). On any error nothing changes.
    pub fn offer(&mut self, result: UnitResult) -> Result<Offer, MergeError> {
        if result.unit.frame != self.frame {
            return Err(MergeError::WrongFrame {
                frame: result.unit.frame,
                expected: self.frame,
            });
        }
        result.validate(&self.plan)?;
        match self.tiles.get_mut(result.unit.tile as usize) {
            Some(tile) => tile.offer_validated(result),
            // Unreachable after validation; kept panic-free.
            None => Err(MergeError::Invalid(ResultError::UnknownTile {
                tile: result.unit.tile,
                tile_count: self.plan.tile_count(),
            })),
        }
    }

    /// The accumulator of one tile, if the index exists.
    pub fn tile(&self, index: u32) -> Option<&TileAccumulator> {
        self.tiles.get(index as usize)
    }

    /// All tile accumulators in tile order.
    pub fn tiles(&self) -> &[TileAccumulator] {
        &self.tiles
    }

    /// Replaces a tile's state with a restored one (see [`TileAccumulator::restore`]);
    /// refuses a tile whose rectangle is not the plan's tile of that index.
    pub fn restore_tile(&mut self, tile: TileAccumulator) -> Result<(), String> {
        let index = tile.rect().index;
        match self.tiles.get_mut(index as usize) {
            Some(slot) if slot.rect() == tile.rect() => {
                *slot = tile;
                Ok(())
            }
            _ => Err(format!("tile {index} does not belong to this frame's plan")),
        }
    }

    /// Drops everything merged and buffered in one tile, leaving it empty (spot-check
    /// repair, ARCHITECTURE.md §6): a tile's statistics are a running accumulation in
    /// pass order, so a corrupt pass cannot be taken out again; the tile is merged anew
    /// from re-rendered units. Returns whether the tile exists.
    pub fn reset_tile(&mut self, index: u32) -> bool {
        match self.tiles.get_mut(index as usize) {
            Some(t) => {
                *t = TileAccumulator::new(t.rect());
                true
            }
            None => false,
        }
    }

    /// Whether every tile has merged all of the plan's passes.
    pub fn complete(&self) -> bool {
        self.tiles
            .iter()
            .all(|t| t.merged_passes() >= self.plan.passes)
    }

    /// Sum over tiles of their merged passes.
    pub fn merged_pass_count(&self) -> u64 {
        self.tiles
            .iter()
            .map(|t| u64::from(t.merged_passes()))
            .sum()
    }

    /// Assembles the image layers (row-major over the whole frame).
    pub fn image(&self) -> FrameImage {
        let (w, h) = (self.plan.width as usize, self.plan.height as usize);
        let n = w * h;
        let mut img = FrameImage {
            width: self.plan.width,
            height: self.plan.height,
            mean: vec![[0.0; 3]; n],
            variance_of_mean: vec![[0.0; 3]; n],
            passes: vec![0; n],
            samples: vec![0; n],
            relative_error: vec![0.0; n],
            bias: self
                .tiles
                .iter()
                .all(|t| t.bias().is_some())
                .then(|| vec![[0.0; 2]; n]),
        };
        for tile in &self.tiles {
            let r = tile.rect();
            let samples = tile
                .merged_passes()
                .saturating_mul(self.plan.samples_per_pass);
            for (row, stats) in tile
                .pixels()
                .chunks_exact(r.width.max(1) as usize)
                .enumerate()
            {
                let start = (r.y0 as usize + row) * w + r.x0 as usize;
                for (i, s) in stats.iter().enumerate() {
                    let p = start + i;
                    img.mean[p] = s.mean.map(|m| m as f32);
                    if s.passes >= 2 {
                        img.variance_of_mean[p] = s.variance_of_mean().map(|v| v as f32);
                        img.relative_error[p] = s.relative_error() as f32;
                    }
                    img.passes[p] = s.passes;
                    img.samples[p] = samples;
                }
            }
            if let (Some(layer), Some(bias)) = (img.bias.as_mut(), tile.bias()) {
                for (row, stats) in bias.chunks_exact(r.width.max(1) as usize).enumerate() {
                    let start = (r.y0 as usize + row) * w + r.x0 as usize;
                    for (i, b) in stats.iter().enumerate() {
                        layer[start + i] = b.layers();
                    }
                }
            }
        }
        img
    }

    /// Image relative error estimate ([`crate::image_relative_error`],
    /// ARCHITECTURE.md §3) over the pixels of the tiles with at least 2 merged passes;
    /// pixels with fewer have no error estimate and are excluded. 0 if no pixel has 2
    /// passes. Never NaN.
    pub fn image_error(&self) -> f64 {
        crate::stats::image_error_of_tiles_with_bias(
            &self.plan,
            crate::ErrorEstimator::Robust,
            |t| self.tiles.get(t).map(TileAccumulator::pixels),
            |t| self.tiles.get(t).and_then(TileAccumulator::bias),
        )
    }
}

/// The image layers of a frame, each row-major with `width * height` entries.
///
/// Pixels with fewer than 2 merged passes have no error estimate: their
/// `variance_of_mean` and `relative_error` are stored as 0 (image formats and viewers
/// handle infinities badly); look at `passes` to tell them apart.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrameImage {
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// Mean radiance (mean of the pass means).
    pub mean: Vec<[f32; 3]>,
    /// Estimated variance of the mean per channel (0 with fewer than 2 passes).
    pub variance_of_mean: Vec<[f32; 3]>,
    /// Merged passes per pixel.
    pub passes: Vec<u32>,
    /// Merged samples per pixel, `passes * samples_per_pass`.
    pub samples: Vec<u32>,
    /// Relative error per pixel, see [`PixelStats::relative_error`] (0 with fewer than 2
    /// passes): the pass spread's alone.
    pub relative_error: Vec<f32>,
    /// The bias layers of a biased render (vcm, ppm; `None` for every other technique):
    /// per pixel, the mean of its passes' bias estimates (signed luminance,
    /// [`UnitResult::bias`]) and the estimated variance of that mean (0 with fewer than
    /// 2 passes). A pixel's error estimate is `sqrt(v + max(0, b² - v_b))`, with `v` the
    /// luminance variance of its mean ([`crate::bias_squared`]), over
    /// [`crate::bias_scale`] for the relative error; the EXR's `bias.Y` and
    /// `bias.variance.Y`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bias: Option<Vec<[f32; 2]>>,
}

impl FrameImage {
    /// The image of a frame with no light: zero mean and variance with the plan's pass and
    /// sample counts, exactly what merging all-zero passes gives, without tracing a ray
    /// (the render plan's black shortcut, ARCHITECTURE.md §4; local and farm renders share it).
    pub fn black(plan: &FramePlan) -> Self {
        let n = plan.width as usize * plan.height as usize;
        Self {
            width: plan.width,
            height: plan.height,
            mean: vec![[0.0; 3]; n],
            variance_of_mean: vec![[0.0; 3]; n],
            passes: vec![plan.passes; n],
            samples: vec![plan.spp(); n],
            relative_error: vec![0.0; n],
            bias: None,
        }
    }

    /// The variance of each pixel's mean for its confidence interval, such that
    /// `mean +- 2 sqrt(interval_variance)` covers [`crate::INTERVAL_COVERAGE`] (95.45%):
    /// the per-pass variance pooled over the pixel's 3x3 neighbourhood (the neighbours
    /// inside the image with at least 2 passes, each weighted by its degrees of freedom
    /// `n_q - 1`), divided by the pixel's own pass count, and widened by `(q / 2)^2` for
    /// Student's t quantile `q` of the pooled degrees of freedom `sum (n_q - 1)`
    /// ([`crate::interval_quantile`]: 2.32 for 9, 2.10 for 27; see
    /// [`crate::pooled_interval_variance`]). 0 where the pixel has fewer than 2
    /// passes.
    ///
    /// Why pooled: a pixel's own variance estimate has only `K - 1` degrees of freedom, so
    /// `mean +- 2 sqrt(variance_of_mean)` covers its true value with Student's t
    /// probability, 86% at `K = 4` and 70% at `K = 2` (ARCHITECTURE.md §3). The per-sample
    /// variance changes slowly across the image, and the passes of different pixels are
    /// independent, so pooling 9 pixels gives up to `9 (K - 1)` degrees of freedom, at the
    /// price of a bias at sharp changes of the variance (an emitter's silhouette), where
    /// pixels on the quiet side get a wider interval and pixels on the noisy side a
    /// narrower one. Why widened: even 9 (K - 1) degrees of freedom leave the 2-sigma
    /// interval short of 95.45% (92.3% at `K = 2`, 94.4% at `K = 4`); at t's quantile it
    /// covers 93-96% on the calibration suite at 2 passes as at 4
    /// (`crates/tessera-render/tests/it/calibration.rs`, `docs/benchmarks.md` "Calibration
    /// suite", "Sampling structure"). The image error estimate keeps the pixels' own
    /// estimates: pooling would spread an emitter edge's variance over its dark
    /// neighbours, whose relative error it would inflate.
    pub fn interval_variance(&self) -> Vec<[f32; 3]> {
        let (w, h) = (self.width as usize, self.height as usize);
        let mut out = vec![[0.0f32; 3]; self.mean.len()];
        for y in 0..h {
            for x in 0..w {
                let p = y * w + x;
                if self.passes[p] < 2 {
                    continue;
                }
                let (mut sum, mut dof) = ([0.0f64; 3], 0.0f64);
                for qy in y.saturating_sub(1)..(y + 2).min(h) {
                    for qx in x.saturating_sub(1)..(x + 2).min(w) {
                        let q = qy * w + qx;
                        let n = f64::from(self.passes[q]);
                        if n < 2.0 {
                            continue;
                        }
                        // Per-pass variance n v_q, weighted by n - 1 degrees of freedom.
                        for (c, s) in sum.iter_mut().enumerate() {
                            *s += (n - 1.0) * n * f64::from(self.variance_of_mean[q][c]);
                        }
                        dof += n - 1.0;
                    }
                }
                let own = f64::from(self.passes[p]);
                out[p] = crate::pooled_interval_variance(sum, dof, own);
            }
        }
        out
    }

    /// The image's relative error estimate `estimator` from its own layers
    /// (ARCHITECTURE.md §3: [`crate::image_relative_error`] or
    /// [`crate::image_relative_error_pooled`], from each pixel's standard error
    /// `relative_error * (lum(mean) + REL_EPS)` and its passes), or `None` while a pixel
    /// has fewer than 2 passes (it has no estimate, so no claim about the image can be
    /// made). Computed from the written layers, so every renderer of the same image (local
    /// or farm, live or restored from checkpoints) gets the same number. With bias layers
    /// ([`FrameImage::bias`]) it is the estimator's
    /// [`crate::ErrorEstimator::image_error_biased`]: [`crate::image_relative_error_biased`]
    /// for the robust one, [`crate::image_relative_error_pooled_biased`] for the pooled one
    /// (unbiased adaptive renders of vcm and ppm).
    pub fn error_estimate(&self, estimator: crate::ErrorEstimator) -> Option<f64> {
        if self.passes.is_empty() || self.passes.iter().any(|&p| p < 2) {
            return None;
        }
        let (w, h) = (self.width as usize, self.height as usize);
        let pixel = |x: usize, y: usize| {
            let p = y * w + x;
            let m = crate::luminance(self.mean.get(p)?.map(f64::from));
            let se = f64::from(*self.relative_error.get(p)?) * (m.max(0.0) + crate::REL_EPS);
            Some((m, se * se, *self.passes.get(p)?))
        };
        let e = match &self.bias {
            Some(bias) => estimator.image_error_biased(w, h, |x, y| {
                let (m, v, k) = pixel(x, y)?;
                let [b, vb] = *bias.get(y * w + x)?;
                Some((m, v, k, f64::from(b), f64::from(vb)))
            }),
            None => estimator.image_error(w, h, pixel),
        };
        e.is_finite().then_some(e)
    }
}

#[cfg(test)]
mod tests;
