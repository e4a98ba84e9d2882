//! Adaptive stopping: which pixels of a tile still need passes, and when a tile is done
//! (ARCHITECTURE.md §3). Pure: no I/O, no clock, no threads.
//!
//! # Why decisions are made at fixed pass indices
//!
//! An [`AdaptiveTile`] consumes a tile's passes strictly in pass order (buffering results
//! that arrive early, like [`crate::TileAccumulator`]) and takes its decisions only at
//! *decision boundaries*, pass indices fixed by the [`AdaptiveSettings`] alone. A decision
//! at boundary `b` reads nothing but the tile's own merged state over passes `0..b`, which
//! is a pure function of the job (ARCHITECTURE.md §2). Hence an adaptive render is bit-identical with
//! any number of threads or workers and any arrival order: the same pixels stop at the same
//! passes, and their statistics hold the same passes pushed in the same order.
//!
//! # Modes
//!
//! - [`AdaptiveMode::Off`]: every pixel takes every planned pass (the same statistics as
//!   [`crate::TileAccumulator`], bit for bit).
//! - [`AdaptiveMode::Sequential`]: at passes `min_passes`, `min_passes + interval`, ... a
//!   pixel whose relative error `sqrt(Var[mean]) / (lum(mean) + eps)` is below the target
//!   stops, unless a neighbour within one pixel (in the same tile) is still above it
//!   (dilation). Stopping on the estimate itself is biased (Kirk & Arvo 1991, Jensen 2001,
//!   section 10.3): a pixel whose first passes missed a rare bright path (a caustic, a small light
//!   in a glossy reflection) looks converged with too little energy. The minimum pass count
//!   and the dilation make that less likely; the bias test in this module measures what
//!   remains.
//! - [`AdaptiveMode::Unbiased`]: Kirk & Arvo's two-stage remedy (Jensen 2001, section 10.3: "to
//!   eliminate bias the pilot sample must be thrown away"). A pilot of `min_passes` passes
//!   estimates each pixel's per-pass relative deviation `d = s / (lum + eps)`; the pixel is
//!   given `n = ceil(max(λ d, d² / (2 target)²))` fresh passes, clamped to
//!   `[min_fresh_passes, plan passes - pilot]`, with `λ` chosen so that the tile's planned
//!   RMS relative error `sqrt(mean(d² / n))` is the target ([`neyman_scale`],
//!   [`fresh_passes_needed`]). That is the optimal (Neyman) allocation for the image's RMS
//!   error, `n ∝ d` (Owen 2001, section 6.2), with no pixel planned above twice the target
//!   ([`NEYMAN_ERROR_CAP`]); giving each pixel the target, `n = d² / target²` (the rule
//!   before 2026-12-05), costs as much as uniform sampling for the same RMS. The relative
//!   variance `d²` is the larger of the pixel's own and the mean over its 3x3 neighbourhood
//!   in the tile ([`pooled_pilot_variance`]), so that a dark pixel whose own pilot missed a
//!   rare bright path that its neighbours' pilots caught is not given the minimum. The
//!   pilot statistics are then discarded and only passes
//!   `pilot .. pilot + n` form the pixel's mean and error estimate. Because `n` depends only
//!   on the pilot, which is independent of the fresh passes (passes are independent
//!   replicates, Owen 2001, section 6.7), the fresh mean is unbiased whatever `n` turned out to be.
//!
//! # Rendering only what is wanted
//!
//! [`AdaptiveTile::wants`] tells whether a pixel will use a given pass. A local renderer
//! skips the pixels that do not (their values are ignored when merged). On the farm a lease
//! carries the same set, [`AdaptiveTile::wanted_pixels`] as a run-length list
//! ([`crate::PixelRuns`]), and the worker traces only those pixels and reports
//! the others as black; the policy reads only the passes it wants, so the image is the same
//! as the local one, and a worker that renders whole tiles (one that predates the field)
//! gives the same image too. [`AdaptiveTile::lease_horizon`] is the first pass that cannot
//! be rendered yet because a decision before it is still open; below it every decision
//! [`AdaptiveTile::wants`] reads is final, which makes the leased set a pure function of
//! the job.
//!
//! # The bias channel of biased techniques
//!
//! Vertex merging (vcm, ppm) sends each pass's estimate of its own bias beside the pass
//! means ([`UnitResult::bias`], ARCHITECTURE.md §3, "Biased techniques: the bias term").
//! A tile keeps it as [`crate::BiasStats`] per pixel over exactly the passes the pixel's
//! radiance statistics keep (pushed with them; discarded with the unbiased pilot), so
//! [`AdaptiveFrame::image`] has bias layers and [`AdaptiveFrame::image_error`] adds the
//! bias term as a uniform render does ([`crate::ErrorEstimator::image_error_biased`]).
//! As in [`crate::TileAccumulator`], the channel lasts only while every unit from pass 0 on
//! carries one. Decisions read the radiance statistics alone, as for every technique. The
//! tile's checkpoint carries the channel ([`AdaptiveTileCheckpoint::bias`]), so a frame
//! restored from the store (after a restart, or a finished frame's image) keeps it; one
//! restored from a checkpoint without it estimates from the pass spread alone.
//!
//! # Example
//!
//! ```
//! use tessera_farm::{AdaptiveFrame, AdaptiveMode, AdaptiveSettings, FramePlan, UnitResult};
//!
//! let plan = FramePlan::new(16, 16, 8, 1, 64)?;
//! let settings = AdaptiveSettings { mode: AdaptiveMode::Sequential, target_error: 0.05, ..Default::default() };
//! let mut frame = AdaptiveFrame::new(plan, 0, settings)?;
//! // A constant image converges at the first decision (8 passes).
//! loop {
//!     let units = frame.next_round();
//!     if units.is_empty() {
//!         break;
//!     }
//!     for unit in units {
//!         let rect = plan.tile(unit.tile);
//!         let pass_means = vec![[0.5f32; 3]; rect.pixel_count() * unit.pass_count as usize];
//!         let r = UnitResult { unit, width: rect.width, height: rect.height, pass_means, rejected_samples: 0, bias: None };
//!         frame.offer(&r)?;
//!     }
//! }
//! assert!(frame.finished());
//! assert_eq!(frame.image().samples[0], 8);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

pub use crate::job::AdaptiveMode;
use crate::mask::PixelRuns;
use crate::merge::{FrameImage, MergeError};
use crate::plan::{FramePlan, PlanError, TileRect, WorkUnit};
use crate::result::UnitResult;
use crate::stats::{BiasStats, PixelStats, REL_EPS};

/// Parameters of the adaptive policy. The plan's pass count is the upper bound.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct AdaptiveSettings {
    /// The mode.
    pub mode: AdaptiveMode,
    /// Target relative error per pixel (and hence RMS over the image), e.g. 0.01.
    pub target_error: f64,
    /// Sequential: no pixel stops before this many passes (the first decision boundary).
    /// Unbiased: the length of the discarded pilot. At least 2 (a variance needs two
    /// replicates); 8 by default, since an estimate from fewer passes is too often lucky.
    pub min_passes: u32,
    /// Sequential: passes between decision boundaries after `min_passes`. Also the chunk
    /// a local render round takes per tile. At least 1; 4 by default.
    pub interval: u32,
    /// Unbiased: the fewest fresh passes a pixel is given (at least 2, so it has an error
    /// estimate); 4 by default.
    pub min_fresh_passes: u32,
}

impl Default for AdaptiveSettings {
    fn default() -> Self {
        Self {
            mode: AdaptiveMode::Off,
            target_error: 0.01,
            min_passes: 8,
            interval: 4,
            min_fresh_passes: 4,
        }
    }
}

/// Why adaptive settings cannot be used with a plan.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum AdaptiveError {
    /// The target error is not a positive finite number.
    #[error("target error {0} is invalid: must be a positive, finite relative error such as 0.01")]
    Target(f64),
    /// `min_passes < 2`.
    #[error("minimum pass count {0} is invalid: must be at least 2")]
    MinPasses(u32),
    /// `interval == 0`.
    #[error("decision interval 0 is invalid: must be at least 1 pass")]
    Interval,
    /// `min_fresh_passes < 2`.
    #[error("minimum fresh pass count {0} is invalid: must be at least 2")]
    MinFresh(u32),
    /// Unbiased mode needs room for the pilot and the fresh passes.
    #[error("unbiased adaptive sampling needs at least {needed} passes (a pilot of {pilot} plus {fresh} fresh), the plan has {passes}: raise the sample budget")]
    TooFewPasses {
        /// Passes in the plan.
        passes: u32,
        /// Pilot length.
        pilot: u32,
        /// Minimum fresh passes.
        fresh: u32,
        /// `pilot + fresh`.
        needed: u32,
    },
    /// The plan is invalid.
    #[error(transparent)]
    Plan(#[from] PlanError),
}

impl AdaptiveSettings {
    /// The settings a farm job cut into units of `passes_per_unit` passes runs with:
    /// decisions fall between units, so `min_passes` and `interval` are rounded up to
    /// multiples of it. [`crate::Scheduler::add_adaptive_job`] applies it, and so must
    /// whoever restores the job's policy state from a checkpoint.
    pub fn for_units(self, passes_per_unit: u32) -> Self {
        let ppu = passes_per_unit.max(1);
        let round_up = |v: u32| v.div_ceil(ppu).saturating_mul(ppu);
        Self {
            min_passes: round_up(self.min_passes),
            interval: round_up(self.interval.max(1)),
            ..self
        }
    }

    /// Checks the settings against a plan with `passes` passes.
    pub fn validate(&self, passes: u32) -> Result<(), AdaptiveError> {
        if self.mode == AdaptiveMode::Off {
            return Ok(());
        }
        if !(self.target_error.is_finite() && self.target_error > 0.0) {
            return Err(AdaptiveError::Target(self.target_error));
        }
        if self.min_passes < 2 {
            return Err(AdaptiveError::MinPasses(self.min_passes));
        }
        if self.interval == 0 {
            return Err(AdaptiveError::Interval);
        }
        if self.mode == AdaptiveMode::Unbiased {
            if self.min_fresh_passes < 2 {
                return Err(AdaptiveError::MinFresh(self.min_fresh_passes));
            }
            let needed = self.min_passes.saturating_add(self.min_fresh_passes);
            if passes < needed {
                return Err(AdaptiveError::TooFewPasses {
                    passes,
                    pilot: self.min_passes,
                    fresh: self.min_fresh_passes,
                    needed,
                });
            }
        }
        Ok(())
    }

    /// Whether a decision is taken once passes `0..passes` are merged.
    pub fn is_boundary(&self, passes: u32) -> bool {
        match self.mode {
            AdaptiveMode::Off => false,
            AdaptiveMode::Sequential => {
                passes >= self.min_passes
                    && (passes - self.min_passes).is_multiple_of(self.interval.max(1))
            }
            AdaptiveMode::Unbiased => passes == self.min_passes,
        }
    }

    /// The first decision boundary strictly after `passes`, if any.
    pub fn next_boundary(&self, passes: u32) -> Option<u32> {
        match self.mode {
            AdaptiveMode::Off => None,
            AdaptiveMode::Sequential => {
                if passes < self.min_passes {
                    return Some(self.min_passes);
                }
                let k = self.interval.max(1);
                let steps = (passes - self.min_passes) / k + 1;
                self.min_passes.checked_add(steps.checked_mul(k)?)
            }
            AdaptiveMode::Unbiased => (passes < self.min_passes).then_some(self.min_passes),
        }
    }
}

/// Cap on the samples per pass of [`adaptive_plan`]. Smaller than
/// [`MAX_AUTO_SAMPLES_PER_PASS`](crate::plan::MAX_AUTO_SAMPLES_PER_PASS): adaptive
/// decisions need many short passes more than each pass needs a large net (the trade-off
/// is in `docs/benchmarks.md`, "Sampling structure"; adaptive plans were not changed).
pub const ADAPTIVE_MAX_SAMPLES_PER_PASS: u32 = 16;

/// A plan for an adaptive render with at most `spp` samples per pixel: like
/// [`FramePlan::for_spp`] but aiming for at least 32 passes (samples per pass the largest
/// power of two not above `max(1, spp / 32)`, capped at [`ADAPTIVE_MAX_SAMPLES_PER_PASS`]),
/// because adaptive decisions are taken between passes and the unbiased pilot alone takes
/// 8 of them.
pub fn adaptive_plan(
    width: u32,
    height: u32,
    spp: u32,
    tile_size: u32,
) -> Result<FramePlan, PlanError> {
    let max = ADAPTIVE_MAX_SAMPLES_PER_PASS * crate::plan::MAX_PASSES;
    if spp == 0 || spp > max {
        return Err(PlanError::Spp { spp, max });
    }
    let target = (spp / 32).max(1);
    let pow2 = 1u32 << (31 - target.leading_zeros());
    let s = pow2.min(ADAPTIVE_MAX_SAMPLES_PER_PASS);
    FramePlan::new(width, height, tile_size, s, spp.div_ceil(s))
}

/// Per-pixel bookkeeping of the policy.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
struct PixelState {
    /// Sequential: the decision boundary at which the pixel stopped (it takes the passes
    /// below it and none from it on); `None` while it samples. Unused otherwise. The pass,
    /// not a flag, so that [`AdaptiveTile::wants`] answers for a past pass as it did then:
    /// a copy of an old unit leased again gets the pixel set the first copy got.
    stopped_at: Option<std::num::NonZeroU32>,
    /// Unbiased: fresh passes fixed by the pilot (0 while the pilot runs).
    needed: u32,
    /// Passes the pixel used (including a discarded pilot): its rendering effort.
    traced: u32,
}

/// The adaptive state of one tile: per-pixel statistics of the passes each pixel keeps,
/// and the policy's decisions. Feed it every unit result of the tile (in any order); it
/// consumes passes in pass order.
///
/// Serializable, so a coordinator can checkpoint it with the tile's merged statistics
/// (the policy state is not recoverable from [`crate::PixelStats`] alone).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct AdaptiveTile {
    rect: TileRect,
    settings: AdaptiveSettings,
    max_passes: u32,
    /// Passes `0..next_pass` are consumed.
    next_pass: u32,
    stats: Vec<PixelStats>,
    state: Vec<PixelState>,
    /// Results that arrived before their turn: first pass -> (pass count, pass means,
    /// bias channel).
    pending: BTreeMap<u32, PendingUnit>,
    /// Scratch for decisions (converged flags), kept to avoid reallocating.
    scratch: Vec<bool>,
    /// Unbiased: one past the last pass any pixel needs, once the pilot has decided.
    end: Option<u32>,
    /// Statistics of the bias channel ([`UnitResult::bias`], vcm and ppm) over the same
    /// passes as `stats`, pixel by pixel: `Some` only while every consumed unit from pass
    /// 0 on carried one (as [`crate::TileAccumulator`] keeps it), and discarded with the
    /// unbiased pilot like the pixels' own statistics.
    #[serde(default)]
    bias: Option<Vec<BiasStats>>,
}

/// A unit buffered until its passes' turn: (pass count, pass means, bias channel).
type PendingUnit = (u32, Vec<[f32; 3]>, Option<Vec<f32>>);

impl AdaptiveTile {
    /// The state of tile `rect` for a plan with `max_passes` passes. The settings must have
    /// passed [`AdaptiveSettings::validate`] (as [`AdaptiveFrame::new`] checks).
    pub fn new(rect: TileRect, settings: AdaptiveSettings, max_passes: u32) -> Self {
        let n = rect.pixel_count();
        Self {
            rect,
            settings,
            max_passes,
            next_pass: 0,
            stats: vec![PixelStats::default(); n],
            state: vec![PixelState::default(); n],
            pending: BTreeMap::new(),
            scratch: vec![false; n],
            end: None,
            bias: None,
        }
    }

    /// The tile.
    pub fn rect(&self) -> TileRect {
        self.rect
    }

    /// Passes consumed so far (every decision up to this pass index has been made).
    pub fn consumed_passes(&self) -> u32 {
        self.next_pass
    }

    /// One past the last pass this tile can still use: the plan's pass count, or for
    /// unbiased after the pilot the largest `pilot + n` over its pixels.
    pub fn end_pass(&self) -> u32 {
        self.end.unwrap_or(self.max_passes).min(self.max_passes)
    }

    /// Whether the tile needs no more passes.
    pub fn finished(&self) -> bool {
        self.next_pass >= self.end_pass() || self.all_stopped()
    }

    fn all_stopped(&self) -> bool {
        self.settings.mode == AdaptiveMode::Sequential
            && self.state.iter().all(|s| s.stopped_at.is_some())
    }

    /// Passes below this index may be rendered now; later ones wait for a decision (or are
    /// never needed). Equal to [`AdaptiveTile::consumed_passes`] once the tile is finished.
    pub fn lease_horizon(&self) -> u32 {
        if self.finished() {
            return self.next_pass;
        }
        let end = self.end_pass();
        match self.settings.next_boundary(self.next_pass) {
            Some(b) => b.min(end),
            None => end,
        }
    }

    /// The next chunk of passes a local render round should render for this tile:
    /// `[consumed, min(consumed + interval, lease_horizon))`, or `None` if finished.
    pub fn next_chunk(&self) -> Option<(u32, u32)> {
        let h = self.lease_horizon();
        if h <= self.next_pass {
            return None;
        }
        let end = h.min(self.next_pass.saturating_add(self.settings.interval.max(1)));
        Some((self.next_pass, end - self.next_pass))
    }

    /// Whether tile pixel `i` (row-major) will use pass `pass`, as far as the decisions
    /// made so far tell. Passes not consumed yet and beyond the lease horizon may still be
    /// dropped by a later decision; for a pass below the horizon the answer is final: it
    /// reads only the decisions at boundaries up to `pass`, which later decisions do not
    /// change. It never turns from false back to true as `pass` grows.
    #[inline]
    pub fn wants(&self, i: usize, pass: u32) -> bool {
        let Some(s) = self.state.get(i) else {
            return false;
        };
        if pass >= self.max_passes {
            return false;
        }
        match self.settings.mode {
            AdaptiveMode::Off => true,
            AdaptiveMode::Sequential => s.stopped_at.is_none_or(|b| pass < b.get()),
            AdaptiveMode::Unbiased => {
                pass < self.settings.min_passes
                    || s.needed == 0
                    || pass < self.settings.min_passes.saturating_add(s.needed)
            }
        }
    }

    /// The pixels a unit of this tile with passes `first_pass .. first_pass + pass_count`
    /// must trace: those the policy wants for any of its passes ([`AdaptiveTile::wants`]).
    /// `None` when that is every pixel (the lease then names no set).
    ///
    /// Call it only for a unit below the [`AdaptiveTile::lease_horizon`] (or one already
    /// consumed): then every decision it reads is taken and final, so the set is a pure
    /// function of the job, the same whenever it is asked and for every copy of the unit
    /// (ARCHITECTURE.md §2).
    pub fn wanted_pixels(&self, first_pass: u32, pass_count: u32) -> Option<PixelRuns> {
        let end = first_pass.saturating_add(pass_count.max(1));
        let runs = PixelRuns::from_fn(self.state.len(), |i| {
            (first_pass..end).any(|p| self.wants(i, p))
        });
        // An empty set cannot be said on the wire (empty means every pixel) and is never
        // leased (the tile would be finished); tracing everything is then merely wasteful.
        (!runs.covers(self.state.len()) && !runs.is_empty()).then_some(runs)
    }

    /// Offers a result for this tile, already validated and accepted by the tile's
    /// [`crate::TileAccumulator`] (so it is neither malformed nor a duplicate). Passes at or
    /// beyond the plan's end, or already consumed, are ignored.
    pub fn offer(&mut self, result: &UnitResult) {
        let n = self.stats.len();
        if n == 0 || result.pass_means.len() != n * result.unit.pass_count as usize {
            return;
        }
        let first = result.unit.first_pass;
        // A bias channel of the wrong length (a result that skipped validation) counts as
        // none.
        let bias = result
            .bias
            .as_ref()
            .filter(|b| b.len() == result.pass_means.len());
        if first > self.next_pass {
            self.pending.insert(
                first,
                (
                    result.unit.pass_count,
                    result.pass_means.clone(),
                    bias.cloned(),
                ),
            );
            return;
        }
        self.consume(first, &result.pass_means, bias.map(Vec::as_slice));
        while let Some((count, means, bias)) = self.pending.remove(&self.next_pass) {
            debug_assert_eq!(means.len(), n * count as usize);
            let first = self.next_pass;
            self.consume(first, &means, bias.as_deref());
        }
    }

    /// Consumes passes `first..` (pass-major means and, where the unit carries one, its
    /// bias channel of the same layout), skipping any already consumed.
    fn consume(&mut self, first: u32, means: &[[f32; 3]], bias: Option<&[f32]>) {
        let n = self.stats.len();
        for (k, pass_means) in means.chunks_exact(n).enumerate() {
            let pass = first.saturating_add(k as u32);
            if pass < self.next_pass {
                continue;
            }
            if self.finished() {
                break;
            }
            // The bias channel starts with pass 0 and ends for good at the first pass
            // without one: the estimate then falls back to the pass spread alone rather
            // than mixing passes with and without it (as `TileAccumulator` does).
            let pass_bias = bias.and_then(|b| b.get(k * n..(k + 1) * n));
            match pass_bias {
                Some(_) if pass == 0 => self.bias = Some(vec![BiasStats::default(); n]),
                None => self.bias = None,
                Some(_) => {}
            }
            for (i, &rgb) in pass_means.iter().enumerate() {
                if self.wants(i, pass) {
                    self.stats[i].push(rgb);
                    self.state[i].traced += 1;
                    // Over the passes the pixel keeps, exactly as its radiance statistics.
                    if let (Some(stats), Some(b)) = (self.bias.as_mut(), pass_bias) {
                        stats[i].push(b[i]);
                    }
                }
            }
            self.next_pass = pass + 1;
            if self.settings.is_boundary(self.next_pass) {
                self.decide();
            }
        }
    }

    /// The decision at boundary `next_pass`, from this tile's state alone.
    fn decide(&mut self) {
        let target = self.settings.target_error;
        match self.settings.mode {
            AdaptiveMode::Off => {}
            AdaptiveMode::Sequential => {
                // converged: stopped before, or relative error below the target now.
                for (c, (s, st)) in self
                    .scratch
                    .iter_mut()
                    .zip(self.stats.iter().zip(&self.state))
                {
                    *c = st.stopped_at.is_some() || s.relative_error() < target;
                }
                // Dilation: stop only if the whole 3x3 neighbourhood (within the tile) has
                // converged, so one lucky pixel next to a noisy one keeps sampling.
                let (w, h) = (self.rect.width as usize, self.rect.height as usize);
                for y in 0..h {
                    for x in 0..w {
                        let i = y * w + x;
                        if self.state[i].stopped_at.is_some() || !self.scratch[i] {
                            continue;
                        }
                        let mut all = true;
                        for yy in y.saturating_sub(1)..(y + 2).min(h) {
                            for xx in x.saturating_sub(1)..(x + 2).min(w) {
                                all &= self.scratch[yy * w + xx];
                            }
                        }
                        if all {
                            // Boundaries are at least `min_passes >= 2`, never 0.
                            self.state[i].stopped_at = std::num::NonZeroU32::new(self.next_pass);
                        }
                    }
                }
            }
            AdaptiveMode::Unbiased => {
                let pilot = self.settings.min_passes;
                let max_fresh = self.max_passes.saturating_sub(pilot);
                let lo = self.settings.min_fresh_passes.min(max_fresh).max(1);
                let (w, h) = (self.rect.width as usize, self.rect.height as usize);
                // Decide every pixel first (the pooled variance reads the neighbours'
                // pilots, the scale λ every pixel's deviation), then discard the pilots.
                // Once per tile, not per pass: the two vectors are not in a hot loop.
                let deviations: Vec<Option<f64>> = (0..h)
                    .flat_map(|y| (0..w).map(move |x| (x, y)))
                    .map(|(x, y)| {
                        let pooled = pooled_pilot_variance(&self.stats, w, h, x, y);
                        pilot_relative_variance(&self.stats[y * w + x])
                            .map(|own| own.max(pooled).sqrt())
                    })
                    .collect();
                let known: Vec<f64> = deviations.iter().flatten().copied().collect();
                let cap = NEYMAN_ERROR_CAP;
                let lambda = neyman_scale(&known, target, cap);
                let mut end = pilot;
                for (st, d) in self.state.iter_mut().zip(&deviations) {
                    let needed = match d {
                        Some(d) => fresh_passes_needed(*d, lambda, cap * target, lo, max_fresh),
                        None => max_fresh.max(lo),
                    };
                    st.needed = needed;
                    end = end.max(pilot.saturating_add(needed));
                }
                // Kirk & Arvo: the pilot is thrown away; only fresh passes count, for the
                // bias channel as for the radiance.
                self.stats.fill(PixelStats::default());
                if let Some(bias) = self.bias.as_mut() {
                    bias.fill(BiasStats::default());
                }
                self.end = Some(end);
            }
        }
    }

    /// Per-pixel statistics of the passes each pixel keeps (row-major).
    pub fn pixels(&self) -> &[PixelStats] {
        &self.stats
    }

    /// Per-pixel statistics of the bias channel ([`UnitResult::bias`]: vcm and ppm) over
    /// the same passes as [`AdaptiveTile::pixels`] (row-major), when every consumed unit
    /// carried one.
    pub fn bias(&self) -> Option<&[BiasStats]> {
        self.bias.as_deref()
    }

    /// Passes each pixel used, including a discarded pilot (row-major), as an iterator.
    pub fn traced_passes(&self) -> impl Iterator<Item = u32> + '_ {
        self.state.iter().map(|s| s.traced)
    }

    /// Unbiased: the fresh passes each pixel was given (0 before the pilot decided).
    pub fn fresh_passes_needed(&self) -> impl Iterator<Item = u32> + '_ {
        self.state.iter().map(|s| s.needed)
    }

    /// Number of pixels still sampling.
    pub fn active_pixels(&self) -> usize {
        if self.finished() {
            return 0;
        }
        (0..self.state.len())
            .filter(|&i| self.wants(i, self.next_pass))
            .count()
    }
}

/// One pixel of an [`AdaptiveTileCheckpoint`].
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct AdaptivePixel {
    /// Statistics of the passes the pixel keeps (for unbiased after the pilot: the fresh
    /// ones only).
    pub stats: PixelStats,
    /// Sequential: the boundary at which the pixel stopped, 0 while it samples.
    pub stopped_at: u32,
    /// Unbiased: fresh passes fixed by the pilot, 0 while the pilot runs.
    pub needed: u32,
    /// Passes the pixel used, a discarded pilot included.
    pub traced: u32,
}

/// The policy state of one tile as plain data, to be stored with the tile's merged passes
/// (a coordinator restart resumes an adaptive job from its merged
/// passes). Results buffered ahead of their turn are not part of it (they are not part of
/// the tile's merge checkpoint either: their units are leased again).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AdaptiveTileCheckpoint {
    /// Passes consumed: every decision up to this pass index is taken.
    pub consumed_passes: u32,
    /// Per pixel, row-major within the tile.
    pub pixels: Vec<AdaptivePixel>,
    /// Biased techniques (vcm, ppm): the bias channel's statistics per pixel over the same
    /// passes as each pixel's kept statistics ([`AdaptiveTile::bias`]); `None` for every
    /// other technique, for a tile whose channel ended, and for checkpoints stored before
    /// the channel existed (the restored tile then estimates from the pass spread alone).
    #[serde(default)]
    pub bias: Option<Vec<BiasStats>>,
}

/// Why an [`AdaptiveTileCheckpoint`] cannot be restored (a damaged or foreign store row).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("adaptive checkpoint of tile {tile}: {reason}")]
pub struct AdaptiveRestoreError {
    /// The tile index.
    pub tile: u32,
    /// What is inconsistent.
    pub reason: String,
}

impl AdaptiveTile {
    /// The policy state to checkpoint with the tile (see [`AdaptiveTileCheckpoint`]).
    pub fn checkpoint(&self) -> AdaptiveTileCheckpoint {
        AdaptiveTileCheckpoint {
            consumed_passes: self.next_pass,
            pixels: self
                .stats
                .iter()
                .zip(&self.state)
                .map(|(s, st)| AdaptivePixel {
                    stats: *s,
                    stopped_at: st.stopped_at.map_or(0, std::num::NonZeroU32::get),
                    needed: st.needed,
                    traced: st.traced,
                })
                .collect(),
            bias: self.bias.clone(),
        }
    }

    /// The tile `rect` restored from `cp` for a plan of `max_passes` passes with
    /// `settings` (those the job ran with). Everything is checked against the settings, so
    /// a checkpoint that no run of the policy could have produced is refused rather than
    /// trusted: the pixel count, the consumed passes, every stop at a decision boundary
    /// already passed, the unbiased fresh counts present exactly once the pilot is over
    /// and within the plan, traced counts within the consumed passes, finite statistics,
    /// and bias statistics (if any) finite and over the same passes as each pixel's.
    pub fn restore(
        rect: TileRect,
        settings: AdaptiveSettings,
        max_passes: u32,
        cp: &AdaptiveTileCheckpoint,
    ) -> Result<Self, AdaptiveRestoreError> {
        let err = |reason: String| AdaptiveRestoreError {
            tile: rect.index,
            reason,
        };
        let mut tile = Self::new(rect, settings, max_passes);
        if cp.pixels.len() != tile.state.len() {
            return Err(err(format!(
                "{} pixels, the tile has {}",
                cp.pixels.len(),
                tile.state.len()
            )));
        }
        let consumed = cp.consumed_passes;
        if consumed > max_passes {
            return Err(err(format!(
                "consumed {consumed} passes of a plan of {max_passes}"
            )));
        }
        let pilot = settings.min_passes;
        let decided = settings.mode == AdaptiveMode::Unbiased && consumed >= pilot;
        let max_fresh = max_passes.saturating_sub(pilot);
        let mut end = pilot;
        for (i, p) in cp.pixels.iter().enumerate() {
            let s = &p.stats;
            let finite = s.mean.iter().chain(&s.m2).all(|v| v.is_finite())
                && s.mean_lum.is_finite()
                && s.m2_lum.is_finite();
            if !finite || s.passes > p.traced || p.traced > consumed {
                return Err(err(format!(
                    "pixel {i}: {} passes kept, {} traced, {consumed} consumed, finite: {finite}",
                    s.passes, p.traced
                )));
            }
            let stop_ok = p.stopped_at == 0
                || (settings.mode == AdaptiveMode::Sequential
                    && p.stopped_at <= consumed
                    && settings.is_boundary(p.stopped_at));
            if !stop_ok {
                return Err(err(format!(
                    "pixel {i} stopped at pass {}, not a decision boundary up to {consumed}",
                    p.stopped_at
                )));
            }
            if (p.needed > 0) != decided || p.needed > max_fresh {
                return Err(err(format!(
                    "pixel {i} has {} fresh passes with {consumed} passes consumed",
                    p.needed
                )));
            }
            end = end.max(pilot.saturating_add(p.needed));
            tile.stats[i] = *s;
            tile.state[i] = PixelState {
                stopped_at: std::num::NonZeroU32::new(p.stopped_at),
                needed: p.needed,
                traced: p.traced,
            };
        }
        if let Some(bias) = &cp.bias {
            let finite = bias.iter().all(|b| b.mean.is_finite() && b.m2.is_finite());
            let same_passes = bias.len() == tile.stats.len()
                && bias
                    .iter()
                    .zip(&tile.stats)
                    .all(|(b, s)| b.passes == s.passes);
            if !(finite && same_passes) {
                return Err(err(format!(
                    "{} bias records for {} pixels, over the pixels' kept passes: \
                     {same_passes}, finite: {finite}",
                    bias.len(),
                    tile.stats.len()
                )));
            }
            tile.bias = Some(bias.clone());
        }
        tile.next_pass = consumed;
        tile.end = decided.then_some(end);
        Ok(tile)
    }
}

/// Fresh passes for a pixel after its pilot (Kirk & Arvo two-stage, Jensen 2001, section
/// 10.3), by the capped optimal (Neyman) allocation within its tile:
/// `ceil(max(λ d, (d / pixel_cap)²))`, clamped to `[lo, hi]`, for `d` the pixel's per-pass
/// relative standard deviation (the square root of the larger of its own pilot's
/// [`pilot_relative_variance`] and its neighbourhood's [`pooled_pilot_variance`]), `λ` the
/// tile's scale from [`neyman_scale`] and `pixel_cap` the largest error planned for one
/// pixel ([`NEYMAN_ERROR_CAP`] times the target). `hi` when the result is not finite.
///
/// Why not `ceil(d² / target²)`, each pixel to the target (the rule before 2026-12-05): the
/// target is the image's error, the RMS over pixels of `d / sqrt(n)`, and for a fixed sum
/// of passes that RMS is least with `n ∝ d` (Owen 2001, section 6.2: optimal allocations
/// take `n_h ∝ σ_h`), where `n ∝ d²` costs as much as giving every pixel the same passes.
/// Noisy pixels end noisier than quiet ones, which is what minimizes the image's error; the
/// cap keeps any one of them within twice the target. `n` still depends on the pilot
/// alone, so the fresh mean stays unbiased.
pub fn fresh_passes_needed(d: f64, lambda: f64, pixel_cap: f64, lo: u32, hi: u32) -> u32 {
    let hi = hi.max(lo);
    let n = (lambda * d).max((d / pixel_cap).powi(2)).ceil();
    if !n.is_finite() {
        return hi;
    }
    (n.clamp(0.0, f64::from(hi)) as u32).clamp(lo, hi)
}

/// No pixel's error is planned above this multiple of the target (see [`neyman_scale`]).
/// Measured on veach-mis (docs/benchmarks.md, 2026-12-05): 2 keeps most of the plain
/// optimal allocation's saving, 1.41 none of it; without a cap the noisiest pixels' few
/// fresh passes miss the rare paths their pilot found.
pub const NEYMAN_ERROR_CAP: f64 = 2.0;

/// The scale `λ` of the capped optimal allocation `n_i = max(λ d_i, d_i² / (c t)²)` that
/// makes the tile's planned RMS error `sqrt(mean(d_i² / n_i))` the target `t`:
/// `Σ min(d_i / λ, c² t²) = N t²`. Pixels whose optimal share would leave them above `c t`
/// are given `d² / (c t)²` and the rest share what remains (`λ = S / ((N - k c²) t²)` for
/// the `k` capped pixels and the sum `S` of the others' deviations). NaN when `deviations`
/// is empty; 0 when every deviation is 0.
pub fn neyman_scale(deviations: &[f64], target: f64, cap: f64) -> f64 {
    let n = deviations.len();
    if n == 0 {
        return f64::NAN;
    }
    let mut sorted = deviations.to_vec();
    sorted.sort_by(|a, b| b.total_cmp(a));
    let t2 = target * target;
    let c2 = cap * cap;
    let mut rest: f64 = sorted.iter().sum();
    for (k, &largest) in sorted.iter().enumerate() {
        // k pixels capped: the others share what is left.
        let room = (n as f64 - k as f64 * c2) * t2;
        if room <= 0.0 {
            break;
        }
        let lambda = rest / room;
        if largest <= lambda * c2 * t2 {
            return lambda;
        }
        rest -= largest;
    }
    // Only with c <= 1: every pixel at its cap is at most the target.
    0.0
}

/// A pilot pixel's per-pass *relative* variance of the luminance, `s² / (lum + eps)²` with
/// `s² = m2_lum / (K - 1)`: the squared relative error of one pass (`None` with fewer than
/// 2 passes, which have no variance estimate).
pub fn pilot_relative_variance(pilot: &PixelStats) -> Option<f64> {
    if pilot.passes < 2 {
        return None;
    }
    let per_pass_var = pilot.m2_lum.max(0.0) / f64::from(pilot.passes - 1);
    let scale = pilot.mean_lum.max(0.0) + REL_EPS;
    Some(per_pass_var / (scale * scale))
}

/// The mean per-pass relative variance ([`pilot_relative_variance`]) of the pilots in the
/// `(2 POOL_RADIUS + 1)²` neighbourhood of pixel `(x, y)` of a `w x h` tile, clipped to the
/// tile (0 when none has a variance).
///
/// Why the unbiased mode pools: a pixel's own 8-pass pilot cannot see a path
/// rarer than about one in its hundred-odd samples, so a dark pixel lit mostly by rare
/// bright paths (light reflected off a small emitter, a caustic) has a pilot variance near
/// 0 and was given the minimum of fresh passes whatever the target; one of them catching
/// the bright path then made its error the image's (measured: one pixel held 97% of the
/// error of `bench accuracy`'s unbiased run, which was stuck at 7.2%). The per-sample
/// distribution changes slowly over an image (the argument of the pooled interval
/// variance, ARCHITECTURE.md §3), and nine pilots see nine times the samples. Taking the
/// larger of the pixel's own and the pooled figure keeps the decision a function of the
/// pilot alone, which is all Kirk & Arvo's unbiasedness needs: the fresh passes stay
/// independent of `n`. Pooling stays within the tile, so that a tile's decisions depend
/// on its own merged passes only (module documentation).
///
/// Relative, not absolute, variances are pooled: the neighbours' absolute variance over
/// the pixel's own brightness gives every dark pixel beside an emitter's edge or a glossy
/// firefly the bright pixel's work, which measured 4 to 10 times the CPU time of uniform
/// sampling for the same error on veach-mis (docs/bench-accuracy/README.md). What pooling
/// does not catch: a pixel holding a sliver of an emitter that neither its own pilot nor
/// its neighbours' relative variances show.
pub fn pooled_pilot_variance(stats: &[PixelStats], w: usize, h: usize, x: usize, y: usize) -> f64 {
    let (mut sum, mut count) = (0.0, 0u32);
    for yy in y.saturating_sub(POOL_RADIUS)..(y + POOL_RADIUS + 1).min(h) {
        for xx in x.saturating_sub(POOL_RADIUS)..(x + POOL_RADIUS + 1).min(w) {
            if let Some(v) = stats.get(yy * w + xx).and_then(pilot_relative_variance) {
                sum += v;
                count += 1;
            }
        }
    }
    if count == 0 {
        0.0
    } else {
        sum / f64::from(count)
    }
}

/// Radius of the neighbourhood [`pooled_pilot_variance`] pools: 1, a 3x3 block.
pub const POOL_RADIUS: usize = 1;

/// The adaptive state of a whole frame: one [`AdaptiveTile`] per tile.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct AdaptiveFrame {
    plan: FramePlan,
    frame: u32,
    settings: AdaptiveSettings,
    tiles: Vec<AdaptiveTile>,
}

impl AdaptiveFrame {
    /// Bytes of policy state per pixel beside the frame's accumulator (statistics, state
    /// and decision scratch), for the coordinator's memory budget.
    pub const BYTES_PER_PIXEL: u64 = (std::mem::size_of::<PixelStats>()
        + std::mem::size_of::<PixelState>()
        + std::mem::size_of::<bool>()) as u64;

    /// An empty adaptive state for `frame` of `plan`; fails on invalid plans or settings.
    pub fn new(
        plan: FramePlan,
        frame: u32,
        settings: AdaptiveSettings,
    ) -> Result<Self, AdaptiveError> {
        plan.validate()?;
        settings.validate(plan.passes)?;
        Ok(Self {
            plan,
            frame,
            settings,
            tiles: plan
                .tiles()
                .map(|r| AdaptiveTile::new(r, settings, plan.passes))
                .collect(),
        })
    }

    /// A frame restored from its tiles' checkpoints, one per tile in tile order (`None`:
    /// nothing consumed yet); fails on invalid settings, a wrong tile count or a
    /// checkpoint [`AdaptiveTile::restore`] refuses.
    pub fn restore(
        plan: FramePlan,
        frame: u32,
        settings: AdaptiveSettings,
        checkpoints: &[Option<AdaptiveTileCheckpoint>],
    ) -> Result<Self, AdaptiveRestoreError> {
        let mut f = Self::new(plan, frame, settings).map_err(|e| AdaptiveRestoreError {
            tile: 0,
            reason: e.to_string(),
        })?;
        if checkpoints.len() != f.tiles.len() {
            return Err(AdaptiveRestoreError {
                tile: 0,
                reason: format!(
                    "{} tile checkpoints for a plan of {} tiles",
                    checkpoints.len(),
                    f.tiles.len()
                ),
            });
        }
        for (t, cp) in f.tiles.iter_mut().zip(checkpoints) {
            if let Some(cp) = cp {
                *t = AdaptiveTile::restore(t.rect(), settings, plan.passes, cp)?;
            }
        }
        Ok(f)
    }

    /// The plan.
    pub fn plan(&self) -> &FramePlan {
        &self.plan
    }

    /// The settings.
    pub fn settings(&self) -> &AdaptiveSettings {
        &self.settings
    }

    /// The frame number.
    pub fn frame(&self) -> u32 {
        self.frame
    }

    /// The state of one tile.
    pub fn tile(&self, index: u32) -> Option<&AdaptiveTile> {
        self.tiles.get(index as usize)
    }

    /// All tiles in order.
    pub fn tiles(&self) -> &[AdaptiveTile] {
        &self.tiles
    }

    /// Offers a result. It is validated against the plan here too, so a caller without a
    /// [`crate::FrameAccumulator`] cannot feed garbage; duplicates of consumed passes are
    /// ignored (pass them to a `FrameAccumulator` first to have them compared).
    pub fn offer(&mut self, result: &UnitResult) -> Result<(), MergeError> {
        if result.unit.frame != self.frame {
            return Err(MergeError::WrongFrame {
                frame: result.unit.frame,
                expected: self.frame,
            });
        }
        result.validate(&self.plan)?;
        if let Some(t) = self.tiles.get_mut(result.unit.tile as usize) {
            t.offer(result);
        }
        Ok(())
    }

    /// Drops one tile's policy state and consumed passes, as if nothing had been offered
    /// to it (spot-check repair, with [`crate::FrameAccumulator::reset_tile`]): its
    /// decisions are then taken again from the passes merged anew. Returns whether the
    /// tile exists.
    pub fn reset_tile(&mut self, index: u32) -> bool {
        let (settings, passes) = (self.settings, self.plan.passes);
        match self.tiles.get_mut(index as usize) {
            Some(t) => {
                *t = AdaptiveTile::new(t.rect(), settings, passes);
                true
            }
            None => false,
        }
    }

    /// Whether every tile is finished.
    pub fn finished(&self) -> bool {
        self.tiles.iter().all(AdaptiveTile::finished)
    }

    /// The units of the next local render round: for every unfinished tile (in tile
    /// order), its [`AdaptiveTile::next_chunk`]. Empty once the frame is finished.
    pub fn next_round(&self) -> Vec<WorkUnit> {
        self.tiles
            .iter()
            .filter_map(|t| {
                t.next_chunk().map(|(first_pass, pass_count)| WorkUnit {
                    frame: self.frame,
                    tile: t.rect().index,
                    first_pass,
                    pass_count,
                })
            })
            .collect()
    }

    /// The image layers. `passes` counts the passes forming each pixel's estimate;
    /// `samples` counts the samples traced for it (`samples_per_pass` times the passes it
    /// used, including a discarded unbiased pilot), so the samples layer shows where the
    /// effort went. The bias layers ([`FrameImage::bias`]; vcm and ppm) are over the same
    /// passes as the mean, where every tile kept its bias channel
    /// ([`AdaptiveTile::bias`]).
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
        let spp = self.plan.samples_per_pass;
        for tile in &self.tiles {
            let r = tile.rect();
            let rw = r.width.max(1) as usize;
            for (i, (s, traced)) in tile.pixels().iter().zip(tile.traced_passes()).enumerate() {
                let p = (r.y0 as usize + i / rw) * w + r.x0 as usize + i % rw;
                img.mean[p] = s.mean.map(|m| m as f32);
                if s.passes >= 2 {
                    img.variance_of_mean[p] = s.variance_of_mean().map(|v| v as f32);
                    img.relative_error[p] = s.relative_error() as f32;
                }
                img.passes[p] = s.passes;
                img.samples[p] = traced.saturating_mul(spp);
            }
            if let (Some(layer), Some(bias)) = (img.bias.as_mut(), tile.bias()) {
                for (i, b) in bias.iter().enumerate() {
                    let p = (r.y0 as usize + i / rw) * w + r.x0 as usize + i % rw;
                    layer[p] = b.layers();
                }
            }
        }
        img
    }

    /// Image relative error estimate (ARCHITECTURE.md §3; the mode's
    /// [`crate::ErrorEstimator`]: [`crate::image_relative_error_pooled`] for unbiased,
    /// [`crate::image_relative_error`] otherwise) over the pixels with at least 2 passes in
    /// their estimate; 0 if there are none. Where every tile kept a bias channel (vcm,
    /// ppm) the merging bias term is added
    /// ([`crate::ErrorEstimator::image_error_biased`]), as for a uniform render.
    pub fn image_error(&self) -> f64 {
        let estimator = crate::ErrorEstimator::for_mode(self.settings.mode);
        crate::stats::image_error_of_tiles_with_bias(
            &self.plan,
            estimator,
            |t| self.tiles.get(t).map(AdaptiveTile::pixels),
            |t| self.tiles.get(t).and_then(AdaptiveTile::bias),
        )
    }

    /// Whether every pixel has at least 2 passes in its estimate, i.e. an error estimate.
    pub fn every_pixel_estimated(&self) -> bool {
        self.tiles
            .iter()
            .flat_map(|t| t.pixels())
            .all(|s| s.passes >= 2)
    }

    /// Samples traced per pixel: (mean, min, max) over the frame.
    pub fn samples_per_pixel(&self) -> (f64, u32, u32) {
        let spp = self.plan.samples_per_pass;
        let mut sum = 0u64;
        let (mut lo, mut hi, mut n) = (u32::MAX, 0u32, 0u64);
        for t in self.tiles.iter().flat_map(|t| t.traced_passes()) {
            let s = t.saturating_mul(spp);
            sum += u64::from(s);
            lo = lo.min(s);
            hi = hi.max(s);
            n += 1;
        }
        if n == 0 {
            return (0.0, 0, 0);
        }
        (sum as f64 / n as f64, lo, hi)
    }
}

/// One point of a convergence history: what `tessera-api`'s `HistoryPoint` carries.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ConvergencePoint {
    /// Seconds since the render started.
    pub elapsed_seconds: f64,
    /// Samples per pixel traced so far, averaged over pixels.
    pub spp: f64,
    /// Image error estimate; `None` before every pixel had two passes.
    pub error_estimate: Option<f64>,
}

/// Estimated seconds still needed to reach `target_error`, from the current error
/// estimate and the time spent so far.
///
/// Monte Carlo error falls like one over the square root of the work (the variance of a
/// mean of `n` independent replicates is `σ²/n`, ARCHITECTURE.md §3), so reaching `target` from
/// `current` after `t` seconds needs `t · (current / target)²` seconds in total:
/// `remaining = t · ((current / target)² - 1)`. Returns `Some(0.0)` when the target is
/// met, and `None` when nothing can be predicted (no time spent, a non-finite or
/// non-positive error or target). For adaptive renders it is an upper bound: converged
/// pixels stop, so the remaining work shrinks faster than this model assumes.
pub fn eta_seconds(current_error: f64, target_error: f64, elapsed_seconds: f64) -> Option<f64> {
    if !(current_error.is_finite()
        && target_error.is_finite()
        && elapsed_seconds.is_finite()
        && target_error > 0.0
        && current_error >= 0.0
        && elapsed_seconds > 0.0)
    {
        return None;
    }
    if current_error <= target_error {
        return Some(0.0);
    }
    let ratio = current_error / target_error;
    Some(elapsed_seconds * (ratio * ratio - 1.0))
}

#[cfg(test)]
mod tests;
