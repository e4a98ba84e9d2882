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
                        let v = if b.passes >= 2 {
                            b.variance_of_mean() as f32
                        } else {
                            0.0
                        };
                        layer[start + i] = [b.mean as f32, v];
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
    /// ([`FrameImage::bias`]) it is [`crate::image_relative_error_biased`] whatever the
    /// estimator.
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
            Some(bias) => crate::image_relative_error_biased(w, h, |x, y| {
                let (m, v, _) = pixel(x, y)?;
                let [b, vb] = *bias.get(y * w + x)?;
                Some((m, v, f64::from(b), f64::from(vb)))
            }),
            None => estimator.image_error(w, h, pixel),
        };
        e.is_finite().then_some(e)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::plan::WorkUnit;
    use crate::test_util::Rng;

    /// A deterministic, irregular pass mean for (tile, pass, pixel): what a renderer would
    /// return for that unit no matter how the passes are grouped.
    fn pass_mean(tile: u32, pass: u32, pixel: usize) -> [f32; 3] {
        let mut rng =
            Rng::new((u64::from(tile) << 40) ^ (u64::from(pass) << 20) ^ pixel as u64 ^ 0xabcdef);
        // Occasional fireflies make the sums sensitive to order.
        let scale = if rng.uniform() < 0.05 { 1e3 } else { 1.0 };
        [0, 1, 2].map(|_| (scale * rng.uniform()) as f32)
    }

    fn render(plan: &FramePlan, unit: WorkUnit) -> UnitResult {
        let rect = plan.tile(unit.tile);
        let mut pass_means = Vec::with_capacity(unit.pass_count as usize * rect.pixel_count());
        for pass in unit.first_pass..unit.first_pass + unit.pass_count {
            pass_means.extend((0..rect.pixel_count()).map(|i| pass_mean(unit.tile, pass, i)));
        }
        UnitResult {
            unit,
            width: rect.width,
            height: rect.height,
            pass_means,
            rejected_samples: 0,
            bias: None,
        }
    }

    fn plan() -> FramePlan {
        FramePlan::new(37, 23, 8, 4, 12).unwrap()
    }

    /// Every bit of the merged state, for exact comparison.
    fn snapshot(acc: &FrameAccumulator) -> Vec<u64> {
        let mut out = Vec::new();
        for t in acc.tiles() {
            out.push(u64::from(t.merged_passes()));
            out.push(t.buffered_units() as u64);
            for s in t.pixels() {
                out.push(u64::from(s.passes));
                out.extend(s.mean.iter().chain(&s.m2).map(|v| v.to_bits()));
                out.push(s.mean_lum.to_bits());
                out.push(s.m2_lum.to_bits());
            }
        }
        out
    }

    fn image_bits(img: &FrameImage) -> Vec<u32> {
        let mut out = vec![img.width, img.height];
        out.extend(img.mean.iter().flatten().map(|v| v.to_bits()));
        out.extend(img.variance_of_mean.iter().flatten().map(|v| v.to_bits()));
        out.extend(&img.passes);
        out.extend(&img.samples);
        out.extend(img.relative_error.iter().map(|v| v.to_bits()));
        out
    }

    fn merge_all(plan: &FramePlan, per: u32, seed: Option<u64>) -> FrameAccumulator {
        let mut units = plan.units(0, per);
        if let Some(seed) = seed {
            Rng::new(seed).shuffle(&mut units);
        }
        let mut acc = FrameAccumulator::new(*plan);
        let mut merged = 0u64;
        for u in units {
            match acc.offer(render(plan, u)).unwrap() {
                Offer::Merged { passes_merged } => merged += u64::from(passes_merged),
                Offer::Buffered => {}
                Offer::Duplicate { .. } => panic!("unexpected duplicate"),
            }
            assert_eq!(acc.merged_pass_count(), merged);
        }
        assert!(acc.complete());
        assert_eq!(
            acc.merged_pass_count(),
            u64::from(plan.tile_count()) * u64::from(plan.passes)
        );
        acc
    }

    /// A result with a bias channel: the pass mean's luminance minus 0.5, a signed value
    /// that depends on (tile, pass, pixel) only.
    fn render_biased(plan: &FramePlan, unit: WorkUnit) -> UnitResult {
        let mut r = render(plan, unit);
        r.bias = Some(
            r.pass_means
                .iter()
                .map(|m| (crate::luminance(m.map(f64::from)) - 0.5) as f32)
                .collect(),
        );
        r
    }

    /// The bias channel merges like the pass means: bit-identical across unit splits and
    /// arrival orders, Welford over the passes in order, into the image's bias layers and
    /// its estimate (which grows by the bias); a unit without the channel drops it.
    #[test]
    fn bias_channel_merges_in_pass_order_and_needs_every_unit() {
        let plan = plan();
        let merge = |per: u32, seed: Option<u64>, plain_unit: Option<usize>| {
            let mut units = plan.units(0, per);
            if let Some(seed) = seed {
                Rng::new(seed).shuffle(&mut units);
            }
            let mut acc = FrameAccumulator::new(plan);
            for (i, u) in units.into_iter().enumerate() {
                let r = if Some(i) == plain_unit {
                    render(&plan, u)
                } else {
                    render_biased(&plan, u)
                };
                acc.offer(r).unwrap();
            }
            acc
        };
        let reference = merge(1, None, None);
        let img = reference.image();
        let layer = img.bias.clone().expect("every unit carried bias");
        for (per, seed) in [(4, Some(1)), (5, Some(2)), (12, None)] {
            let acc = merge(per, seed, None);
            let other = acc.image().bias.unwrap();
            assert!(
                other
                    .iter()
                    .flatten()
                    .zip(layer.iter().flatten())
                    .all(|(a, b)| a.to_bits() == b.to_bits()),
                "per {per}"
            );
            assert_eq!(
                acc.image_error().to_bits(),
                reference.image_error().to_bits()
            );
        }
        // Tile 14's pixel 3 against a Welford run over its passes.
        let mut b = BiasStats::default();
        for pass in 0..plan.passes {
            b.push((crate::luminance(pass_mean(14, pass, 3).map(f64::from)) - 0.5) as f32);
        }
        assert_eq!(reference.tile(14).unwrap().bias().unwrap()[3], b);
        // The estimate adds the bias: the same passes without the channel estimate less.
        let plain = merge_all(&plan, 1, None);
        assert!(reference.image_error() > plain.image_error());
        assert_eq!(plain.image().bias, None);
        let plain_image = plain.image();
        let spread = plain_image
            .error_estimate(crate::ErrorEstimator::Robust)
            .unwrap();
        let with = img.error_estimate(crate::ErrorEstimator::Robust).unwrap();
        assert!(with > spread, "{with} vs {spread}");
        // One unit without the channel: no bias layers at all, the spread's estimate.
        let mixed = merge(1, Some(3), Some(7));
        assert_eq!(mixed.image().bias, None);
        assert_eq!(mixed.image_error().to_bits(), plain.image_error().to_bits());
    }

    #[test]
    fn merge_is_bit_identical_across_splits_and_orders() {
        let plan = plan();
        let reference = merge_all(&plan, 1, None);
        let ref_state = snapshot(&reference);
        let ref_image = image_bits(&reference.image());
        let ref_error = reference.image_error().to_bits();
        for per in [1, 4, 5, 12, 100] {
            for seed in [None, Some(1), Some(2), Some(3)] {
                let acc = merge_all(&plan, per, seed);
                assert!(snapshot(&acc) == ref_state, "per {per} seed {seed:?}");
                assert!(
                    image_bits(&acc.image()) == ref_image,
                    "per {per} seed {seed:?}"
                );
                assert_eq!(acc.image_error().to_bits(), ref_error);
            }
        }
        // And the state really is the in-order fold of the pass means.
        let t = reference.tile(14).unwrap();
        let mut s = PixelStats::default();
        for pass in 0..plan.passes {
            s.push(pass_mean(14, pass, 3));
        }
        assert_eq!(t.pixels()[3], s);
        // A different order of pushes gives different bits (the test can detect it).
        let mut r = PixelStats::default();
        for pass in (0..plan.passes).rev() {
            r.push(pass_mean(14, pass, 3));
        }
        assert_ne!(
            (r.mean.map(f64::to_bits), r.m2.map(f64::to_bits)),
            (s.mean.map(f64::to_bits), s.m2.map(f64::to_bits))
        );
    }

    #[test]
    fn buffering_and_merge_counts() {
        let plan = plan();
        let mut acc = TileAccumulator::new(plan.tile(4));
        let unit = |first_pass, pass_count| WorkUnit {
            frame: 0,
            tile: 4,
            first_pass,
            pass_count,
        };
        assert_eq!(acc.offer(render(&plan, unit(4, 4))), Ok(Offer::Buffered));
        assert_eq!(acc.offer(render(&plan, unit(2, 2))), Ok(Offer::Buffered));
        assert_eq!(acc.merged_passes(), 0);
        assert_eq!(acc.buffered_units(), 2);
        assert!(acc.pixels().iter().all(|s| s.passes == 0));
        assert_eq!(
            acc.offer(render(&plan, unit(0, 2))),
            Ok(Offer::Merged { passes_merged: 8 })
        );
        assert_eq!(acc.merged_passes(), 8);
        assert_eq!(acc.buffered_units(), 0);
        assert_eq!(
            acc.offer(render(&plan, unit(8, 4))),
            Ok(Offer::Merged { passes_merged: 4 })
        );
        assert!(acc.pixels().iter().all(|s| s.passes == 12));
        assert_eq!(acc.rect(), plan.tile(4));
    }

    #[test]
    fn duplicates_are_detected_and_change_nothing() {
        let plan = plan();
        let mut acc = FrameAccumulator::new(plan);
        let u = |tile, first_pass, pass_count| WorkUnit {
            frame: 0,
            tile,
            first_pass,
            pass_count,
        };
        acc.offer(render(&plan, u(3, 0, 4))).unwrap(); // merged
        acc.offer(render(&plan, u(3, 8, 4))).unwrap(); // buffered
        let before = snapshot(&acc);

        // Equal copies, of a merged and of a buffered unit.
        for unit in [u(3, 0, 4), u(3, 8, 4)] {
            assert_eq!(
                acc.offer(render(&plan, unit)),
                Ok(Offer::Duplicate { identical: true })
            );
            assert!(snapshot(&acc) == before);
        }
        // Modified copies: one bit of one value.
        for unit in [u(3, 0, 4), u(3, 8, 4)] {
            let mut r = render(&plan, unit);
            r.pass_means[17][2] = f32::from_bits(r.pass_means[17][2].to_bits() ^ 1);
            assert_eq!(acc.offer(r), Ok(Offer::Duplicate { identical: false }));
            assert!(snapshot(&acc) == before);
        }
        // Partial overlaps are errors and change nothing either.
        for (first, count) in [(0, 1), (2, 4), (3, 2), (6, 3), (9, 1), (0, 12)] {
            let err = acc.offer(render(&plan, u(3, first, count))).unwrap_err();
            assert!(matches!(err, MergeError::Overlap { tile: 3, .. }), "{err}");
            assert!(snapshot(&acc) == before);
        }
        assert_eq!(
            acc.offer(render(&plan, u(3, 2, 4)))
                .unwrap_err()
                .to_string(),
            "tile 3: passes 2..6 overlap the earlier unit with passes 0..4"
        );
        // The gap still merges, releasing the buffered unit.
        assert_eq!(
            acc.offer(render(&plan, u(3, 4, 4))),
            Ok(Offer::Merged { passes_merged: 8 })
        );
        assert_eq!(
            acc.offer(render(&plan, u(3, 4, 4))),
            Ok(Offer::Duplicate { identical: true })
        );
    }

    #[test]
    fn invalid_results_are_rejected_and_change_nothing() {
        let plan = plan();
        let mut acc = FrameAccumulator::new(plan);
        acc.offer(render(
            &plan,
            WorkUnit {
                frame: 0,
                tile: 14,
                first_pass: 0,
                pass_count: 2,
            },
        ))
        .unwrap();
        let before = snapshot(&acc);
        let good = || {
            render(
                &plan,
                WorkUnit {
                    frame: 0,
                    tile: 14,
                    first_pass: 2,
                    pass_count: 3,
                },
            )
        };
        let mut bad: Vec<UnitResult> = Vec::new();
        let mut r = good();
        r.width += 1;
        bad.push(r);
        let mut r = good();
        r.height = 8;
        bad.push(r);
        let mut r = good();
        r.pass_means.pop();
        bad.push(r);
        let mut r = good();
        r.pass_means.push([0.0; 3]);
        bad.push(r);
        let mut r = good();
        r.pass_means[40][1] = f32::NAN;
        bad.push(r);
        let mut r = good();
        r.pass_means[0][0] = f32::NEG_INFINITY;
        bad.push(r);
        let mut r = good();
        r.pass_means[104][2] = -1e-30;
        bad.push(r);
        let mut r = good();
        r.unit.tile = 15;
        bad.push(r);
        let mut r = good();
        r.unit.tile = u32::MAX;
        bad.push(r);
        let mut r = good();
        r.unit.first_pass = 10; // passes 10..13 of 12
        bad.push(r);
        let mut r = good();
        r.unit.first_pass = u32::MAX;
        bad.push(r);
        let mut r = good();
        r.unit.pass_count = 0;
        r.pass_means.clear();
        bad.push(r);
        for r in bad {
            let err = acc.offer(r.clone()).unwrap_err();
            assert!(matches!(err, MergeError::Invalid(_)), "{err}");
            assert!(snapshot(&acc) == before, "{err}");
            // The tile accumulator alone rejects it too (except the plan's pass bound).
            if r.unit.tile == 14 && r.unit.first_pass != 10 {
                let mut t = acc.tile(14).unwrap().clone();
                assert!(t.offer(r).is_err());
            }
        }
        let mut r = good();
        r.unit.frame = 1;
        assert_eq!(
            acc.offer(r),
            Err(MergeError::WrongFrame {
                frame: 1,
                expected: 0
            })
        );
        assert!(snapshot(&acc) == before);
        // A tile accumulator refuses other tiles' results.
        let mut t = TileAccumulator::new(plan.tile(13));
        assert!(matches!(
            t.offer(good()),
            Err(MergeError::Invalid(ResultError::WrongTile { .. }))
        ));
        // Frame accumulators for other frames.
        let mut acc1 = FrameAccumulator::for_frame(plan, 1);
        let mut r = good();
        r.unit.frame = 1;
        r.unit.first_pass = 0;
        assert_eq!(acc1.frame(), 1);
        assert_eq!(acc1.offer(r), Ok(Offer::Merged { passes_merged: 3 }));
    }

    #[test]
    fn try_new_rejects_invalid_plans() {
        let mut p = plan();
        p.tile_size = 0;
        assert_eq!(
            FrameAccumulator::try_new(p, 0).unwrap_err(),
            PlanError::TileSize(0)
        );
        assert_eq!(
            FrameAccumulator::try_new(plan(), 0).unwrap().plan(),
            &plan()
        );
    }

    fn constant(plan: &FramePlan, unit: WorkUnit, rgb: [f32; 3]) -> UnitResult {
        let rect = plan.tile(unit.tile);
        UnitResult {
            unit,
            width: rect.width,
            height: rect.height,
            pass_means: vec![rgb; unit.pass_count as usize * rect.pixel_count()],
            rejected_samples: 0,
            bias: None,
        }
    }

    #[test]
    fn image_error_of_constant_image_is_zero() {
        let plan = FramePlan::new(20, 9, 8, 2, 5).unwrap();
        let mut acc = FrameAccumulator::new(plan);
        assert_eq!(acc.image_error(), 0.0);
        for u in plan.units(0, 2) {
            acc.offer(constant(&plan, u, [0.3, 0.7, 0.1])).unwrap();
        }
        assert!(acc.complete());
        assert_eq!(acc.image_error(), 0.0);
        let img = acc.image();
        assert!(img.mean.iter().all(|&m| m == [0.3, 0.7, 0.1]));
        assert!(img.variance_of_mean.iter().all(|&v| v == [0.0; 3]));
        assert!(img.passes.iter().all(|&p| p == 5));
        assert!(img.samples.iter().all(|&s| s == 10));
        assert!(img.relative_error.iter().all(|&r| r == 0.0));
    }

    /// A hand-computed case. 8x1 image, 4-pixel tiles, S = 3:
    /// - tile 0 gets 2 passes: pixel 0 sees (1,0,0) then (0,0,0), so its luminance goes
    ///   0.2126 then 0; mean 0.1063, m2 = 2 * 0.1063^2, variance of the mean
    ///   m2 / (2 * 1) = 0.1063^2 and rel = 0.1063 / (0.1063 + 0.01). Pixel 1 sees (2,2,2)
    ///   then (4,4,4): lum 2 and 4, mean 3, m2 = 2, var = 1, rel = 1 / 3.01. Pixels 2 and 3
    ///   see zeros: rel = 0.
    /// - tile 1 gets 1 pass: excluded.
    ///
    /// The interval variance pools the per-pass variance `n v` of the 3x3 neighbours with
    /// at least 2 passes, weighted by `n - 1`, divides by the pixel's own `n` and widens
    /// by `(q / 2)^2` for the t quantile of the pooled degrees of freedom. A 3 x 2
    /// image (row-major): pixel 0 has 2 passes and v = 1 (per-pass variance 2), pixel 1 has
    /// 5 passes and v = 0.2 (per-pass 1), pixel 2 has 4 passes and v = 0.5 (per-pass 2),
    /// pixel 3 has 1 pass, pixels 4 and 5 have 3 passes and v = 0.
    #[test]
    fn interval_variance_hand_computed() {
        let img = FrameImage {
            width: 3,
            height: 2,
            mean: vec![[1.0; 3]; 6],
            variance_of_mean: [1.0, 0.2, 0.5, 7.0, 0.0, 0.0].map(|v| [v; 3]).to_vec(),
            passes: vec![2, 5, 4, 1, 3, 3],
            samples: vec![0; 6],
            relative_error: vec![0.0; 6],
            bias: None,
        };
        let iv = img.interval_variance();
        let close = |a: f32, b: f64| (f64::from(a) - b).abs() <= 1e-6 * b.max(1e-30);
        // Widened by (q / 2)^2 for Student's t quantile q of the pooled degrees of freedom
        // (2.4288 for 7, 2.2549 for 11, 2.2313 for 12).
        let widen = |dof: u64| (crate::interval_quantile(dof) / 2.0).powi(2);
        // Pixel 0 pools 0, 1, 4 (3 has 1 pass): dof 1 + 4 + 2, sum 1*2 + 4*1 + 2*0.
        assert!(close(iv[0][0], (6.0 / 7.0) / 2.0 * widen(7)), "{:?}", iv[0]);
        assert!((widen(7) - (2.4288051304035685f64 / 2.0).powi(2)).abs() < 1e-15);
        // Pixel 1 pools all but 3: dof 1 + 4 + 3 + 2 + 2, sum 2 + 4 + 3*2 + 0 + 0.
        assert!(
            close(iv[1][2], (12.0 / 12.0) / 5.0 * widen(12)),
            "{:?}",
            iv[1]
        );
        // Pixel 3 has no estimate of its own.
        assert_eq!(iv[3], [0.0; 3]);
        // Pixel 5 pools 1, 2, 4, 5: dof 4 + 3 + 2 + 2, sum 4 + 6.
        assert!(
            close(iv[5][1], (10.0 / 11.0) / 3.0 * widen(11)),
            "{:?}",
            iv[5]
        );
        // A constant per-pass variance pools to itself, widened for the neighbourhood's
        // degrees of freedom: 4 pixels of 3 in the corners (12), 6 in the middle column (18).
        let flat = FrameImage {
            variance_of_mean: vec![[0.25; 3]; 6],
            passes: vec![4; 6],
            ..img
        };
        for (p, v) in flat.interval_variance().iter().enumerate() {
            let dof = if p % 3 == 1 { 18 } else { 12 };
            assert!(close(v[0], 0.25 * widen(dof)), "pixel {p}: {v:?}");
            assert!(v[0] == v[1] && v[1] == v[2]);
        }
    }

    /// image error = sqrt((rel0^2 + rel1^2) / 4).
    #[test]
    fn image_error_hand_computed() {
        let plan = FramePlan::new(8, 1, 4, 3, 4).unwrap();
        let mut acc = FrameAccumulator::new(plan);
        let unit = |tile, first_pass| WorkUnit {
            frame: 0,
            tile,
            first_pass,
            pass_count: 1,
        };
        let result = |u: WorkUnit, px: [[f32; 3]; 4]| UnitResult {
            unit: u,
            width: 4,
            height: 1,
            pass_means: px.to_vec(),
            rejected_samples: 0,
            bias: None,
        };
        let z = [0.0; 3];
        acc.offer(result(unit(0, 0), [[1.0, 0.0, 0.0], [2.0; 3], z, z]))
            .unwrap();
        // Only one pass so far: nothing to estimate.
        assert_eq!(acc.image_error(), 0.0);
        acc.offer(result(unit(0, 1), [z, [4.0; 3], z, z])).unwrap();
        acc.offer(result(unit(1, 0), [[9.0, 0.0, 0.0], [1.0; 3], z, [5.0; 3]]))
            .unwrap();

        // Pixel 0: passes of luminance 0.2126 and 0, mean l0 = 0.1063, standard error l0;
        // it is darker than its neighbourhood, so its scale is its own mean.
        let l0 = 0.2126f64 / 2.0;
        let rel0 = l0 / (l0 + 0.01);
        // Pixel 1: passes 2 and 4, mean 3, standard error 1; its neighbourhood (pixels 0-2)
        // has mean (l0 + 3) / 3 < 3, so the robust scale falls to the floor 3 - 1 = 2.
        let rel1 = 1.0 / 2.01;
        let expected = ((rel0 * rel0 + rel1 * rel1) / 4.0).sqrt();
        let got = acc.image_error();
        assert!(
            (got - expected).abs() <= 1e-12 * expected,
            "{got} vs {expected}"
        );

        let img = acc.image();
        assert_eq!(img.passes, vec![2, 2, 2, 2, 1, 1, 1, 1]);
        assert_eq!(img.samples, vec![6, 6, 6, 6, 3, 3, 3, 3]);
        assert_eq!(img.mean[0], [0.5, 0.0, 0.0]);
        assert_eq!(img.mean[1], [3.0; 3]);
        assert_eq!(img.mean[4], [9.0, 0.0, 0.0]);
        assert_eq!(img.variance_of_mean[0], [0.25, 0.0, 0.0]);
        assert_eq!(img.variance_of_mean[1], [1.0; 3]);
        // One pass: no estimate, stored as 0.
        assert_eq!(img.variance_of_mean[7], [0.0; 3]);
        assert_eq!(img.relative_error[7], 0.0);
        assert!((f64::from(img.relative_error[0]) - rel0).abs() < 1e-6);
        // The layer keeps the pixel's own rel, standard error over its own mean.
        assert!((f64::from(img.relative_error[1]) - 1.0 / 3.01).abs() < 1e-6);
        assert!(!acc.complete());
        assert_eq!(acc.merged_pass_count(), 3);
    }

    /// The image is assembled at the right place: tile-local pixel (x, y) of tile t lands at
    /// (x0 + x, y0 + y).
    #[test]
    fn image_layout() {
        let plan = FramePlan::new(37, 23, 8, 1, 1).unwrap();
        let mut acc = FrameAccumulator::new(plan);
        for u in plan.units(0, 1) {
            let rect = plan.tile(u.tile);
            let mut pass_means = Vec::new();
            for y in 0..rect.height {
                for x in 0..rect.width {
                    pass_means.push([(rect.x0 + x) as f32, (rect.y0 + y) as f32, 0.0]);
                }
            }
            let r = UnitResult {
                unit: u,
                width: rect.width,
                height: rect.height,
                pass_means,
                rejected_samples: 0,
                bias: None,
            };
            assert_eq!(acc.offer(r), Ok(Offer::Merged { passes_merged: 1 }));
        }
        let img = acc.image();
        for y in 0..23u32 {
            for x in 0..37u32 {
                assert_eq!(img.mean[(y * 37 + x) as usize], [x as f32, y as f32, 0.0]);
            }
        }
    }

    /// The image error reads each pixel from its tile (no frame-sized copy): on a plan
    /// whose last tile column and row are narrower, it equals the estimate over the same
    /// statistics laid out row-major over the frame.
    #[test]
    fn image_error_reads_pixels_where_their_tiles_are() {
        let plan = FramePlan::new(37, 23, 8, 1, 3).unwrap();
        let mut acc = FrameAccumulator::new(plan);
        for u in plan.units(0, 3) {
            acc.offer(render(&plan, u)).unwrap();
        }
        let mut frame = vec![None; 37 * 23];
        for tile in &acc.tiles {
            let r = tile.rect();
            for (i, s) in tile.pixels().iter().enumerate() {
                let (x, y) = (
                    r.x0 as usize + i % r.width as usize,
                    r.y0 as usize + i / r.width as usize,
                );
                frame[y * 37 + x] = Some((s.mean_lum, s.lum_variance_of_mean()));
            }
        }
        let expected = crate::image_relative_error(37, 23, |x, y| frame[y * 37 + x]);
        assert!(expected > 0.0);
        assert_eq!(acc.image_error().to_bits(), expected.to_bits());
    }
}
