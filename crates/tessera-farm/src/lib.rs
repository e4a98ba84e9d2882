//! Pure job logic of Tessera: how a frame is cut into work, and how the results are merged
//! into an image with a running error estimate. No I/O, no async, no threads.
//!
//! This crate is the single code path for planning and merging. The local renderer
//! (`tessera render`) drives it in-process; the farm coordinator drives it with results
//! from remote workers. Both therefore produce bit-identical images for the same job.
//!
//! # Architecture
//!
//! - [`FramePlan`] cuts a frame into square **tiles** (row-major, edge tiles smaller) and
//!   every pixel's samples into **passes** of `samples_per_pass` samples. A pass is an
//!   independent replicate of the pixel (ARCHITECTURE.md §3), which is what makes the error
//!   estimable. [`FramePlan::for_spp`] picks the pass size for a requested spp.
//! - A [`WorkUnit`] is a contiguous range of passes of one tile. [`FramePlan::units`] lists
//!   a frame's units coarse to fine: the first passes of every tile before later ones.
//! - Rendering a unit yields a [`UnitResult`]: the mean of each pass for each pixel.
//!   [`UnitResult::validate`] rejects anything malformed (results may come from remote
//!   workers); [`UnitResult::digest`] fingerprints it for duplicate comparison.
//! - A [`TileAccumulator`] keeps one [`PixelStats`] (Welford running mean and variance in
//!   f64) per pixel. Results arriving out of order are buffered and folded strictly in pass
//!   order, so the statistics are bit-identical regardless of worker count, unit split or
//!   arrival order (ARCHITECTURE.md §2). Duplicates are detected and compared, never merged twice.
//! - A [`FrameAccumulator`] holds one tile accumulator per tile and assembles a
//!   [`FrameImage`] (mean, variance of the mean, passes, samples and relative error layers)
//!   and the image error estimate, the RMS of per-pixel relative errors over a robust
//!   scale ([`robust_scale`], ARCHITECTURE.md §3).
//!
//! Nothing here panics on untrusted input: results are validated and every failure is a
//! typed error ([`PlanError`], [`ResultError`], [`MergeError`]). The only documented panics
//! concern programmer errors (an out-of-range [`FramePlan::tile`] index, a hand-built
//! invalid plan given to [`FrameAccumulator::new`]), each with a non-panicking variant.
//!
//! # Example
//!
//! ```
//! use tessera_farm::{FrameAccumulator, FramePlan, Offer, UnitResult};
//!
//! // 40x30 pixels, 16-pixel tiles, 64 spp: 2 passes of 32 samples.
//! let plan = FramePlan::for_spp(40, 30, 64, 16)?;
//! assert_eq!((plan.samples_per_pass, plan.passes, plan.tile_count()), (32, 2, 6));
//!
//! let mut frame = FrameAccumulator::new(plan);
//! // Two passes per unit (one unit per tile here); results may arrive in any order.
//! let mut units = plan.units(0, 2);
//! units.reverse();
//! for unit in units {
//!     let rect = plan.tile(unit.tile);
//!     // A stand-in for the renderer: pass p of every pixel has mean 0.5 + p / 100.
//!     let mut pass_means = Vec::new();
//!     for p in unit.first_pass..unit.first_pass + unit.pass_count {
//!         let v = 0.5 + p as f32 / 100.0;
//!         pass_means.extend(std::iter::repeat([v, v, v]).take(rect.pixel_count()));
//!     }
//!     let result =
//!         UnitResult { unit, width: rect.width, height: rect.height, pass_means, rejected_samples: 0, bias: None };
//!     let again = result.clone();
//!     frame.offer(result)?;
//!     // A second copy of the same work is recognised and not merged.
//!     assert_eq!(frame.offer(again)?, Offer::Duplicate { identical: true });
//! }
//! assert!(frame.complete());
//! let image = frame.image();
//! assert_eq!(image.samples[0], 64);
//! // The mean of passes 0..2: 0.5 + (0 + 1) / 200.
//! assert!((image.mean[0][0] - 0.505).abs() < 1e-6);
//! assert!(frame.image_error() > 0.0);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```
#![deny(missing_docs)]

mod adaptive;
mod ids;
pub mod job;
mod mask;
mod merge;
mod plan;
pub mod quote;
mod result;
mod schedule;
pub mod spot;
mod stats;

pub use adaptive::{
    adaptive_plan, eta_seconds, fresh_passes_needed, neyman_scale, pilot_relative_variance,
    pooled_pilot_variance, AdaptiveError, AdaptiveFrame, AdaptiveMode, AdaptivePixel,
    AdaptiveRestoreError, AdaptiveSettings, AdaptiveTile, AdaptiveTileCheckpoint, ConvergencePoint,
    ADAPTIVE_MAX_SAMPLES_PER_PASS, NEYMAN_ERROR_CAP, POOL_RADIUS,
};
pub use ids::{JobId, WorkerId};
pub use mask::{MaskError, PixelRuns};
pub use merge::{FrameAccumulator, FrameImage, MergeError, Offer, TileAccumulator};
pub use plan::{
    FramePlan, PlanError, TileRect, WorkUnit, LOW_SPP, LOW_SPP_MIN_PASSES,
    MAX_AUTO_SAMPLES_PER_PASS, MAX_DIMENSION, MAX_FRAME_SAMPLES, MAX_PASSES, MAX_SAMPLES_PER_PASS,
    MAX_TILE_SIZE, MAX_WHOLE_FRAME_PIXELS, MIN_TILE_SIZE, TARGET_MIN_PASSES,
    WHOLE_FRAME_MAX_SAMPLES_PER_PASS,
};
pub use result::{ResultError, UnitResult, MAX_PASS_MEAN};
pub use schedule::{
    frame_state_bytes, frame_state_bytes_with_bias, tail_share, Lease, Progress, Residency,
    Resumed, ResumedAdaptive, Scheduler, SubmitError, Submitted, EXACT_SPOT_COUNT,
};
pub use spot::{
    is_spot_checked, unit_selected, SpotEvent, SpotOutcome, DEFAULT_SPOT_CHECK_FRACTION,
};
pub use stats::{
    bias_scale, bias_squared, image_relative_error, image_relative_error_biased,
    image_relative_error_pooled, image_relative_error_pooled_biased, interval_quantile, luminance,
    neighbours_level, pooled_interval_variance, robust_scale, BiasStats, ErrorEstimator,
    PixelStats, BIAS_TERM, ERROR_ESTIMATOR, ERROR_ESTIMATOR_POOLED, INTERVAL_COVERAGE,
    LUMINANCE_WEIGHTS, REL_EPS,
};

#[cfg(test)]
mod test_util {
    /// splitmix64: a small, fixed-seed PRNG for tests.
    pub struct Rng(u64);

    impl Rng {
        pub fn new(seed: u64) -> Self {
            Self(seed)
        }

        pub fn next_u64(&mut self) -> u64 {
            self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            z ^ (z >> 31)
        }

        /// Uniform in [0, 1).
        pub fn uniform(&mut self) -> f64 {
            (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
        }

        /// Standard normal (Box–Muller, one output per call).
        pub fn normal(&mut self) -> f64 {
            let u1 = 1.0 - self.uniform(); // (0, 1]
            let u2 = self.uniform();
            (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
        }

        /// Fisher–Yates shuffle.
        pub fn shuffle<T>(&mut self, v: &mut [T]) {
            for i in (1..v.len()).rev() {
                let j = (self.next_u64() % (i as u64 + 1)) as usize;
                v.swap(i, j);
            }
        }
    }
}
