//! Adaptive local rendering: the round-by-round driver of `tessera-farm`'s adaptive policy
//! (ARCHITECTURE.md §3).
//!
//! Each round renders, for every tile that is not finished, its next chunk of passes
//! ([`tessera_farm::AdaptiveTile::next_chunk`], never crossing a decision boundary) on a
//! thread pool, skipping the pixels the policy no longer wants
//! ([`crate::render::render_unit_where`]); the results are then offered in tile order and
//! the policy takes its decisions. Because every decision reads only a tile's own merged
//! state at fixed pass indices, the image is bit-identical for any thread count. A time
//! limit is the one exception: where it stops depends on the machine's speed (the stop is
//! still taken between rounds, so the image is a valid adaptive image of fewer passes).

use crate::render::{render_unit_where, RenderConfig};
use crate::scene::RenderScene;
use std::time::Instant;
use tessera_farm::{AdaptiveFrame, AdaptiveMode, ConvergencePoint, UnitResult};

/// Extra stopping rules of an adaptive render, besides the policy and the plan's passes.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Limits {
    /// Stop after the first round that ends at or beyond this many seconds.
    pub time_limit_seconds: Option<f64>,
    /// With [`AdaptiveMode::Off`]: stop the whole image after the first round whose image
    /// error estimate is at or below this (all pixels sampled alike). Ignored by the other
    /// modes, whose policy stops pixels at the target itself.
    pub target_error: Option<f64>,
}

/// Why an adaptive render stopped.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StopReason {
    /// Every tile finished: all pixels converged, got their planned fresh passes, or
    /// reached the plan's pass budget (`--spp`).
    Finished,
    /// The image error estimate reached the target ([`AdaptiveMode::Off`] only).
    TargetReached,
    /// The time limit was reached.
    TimeLimit,
}

impl StopReason {
    /// A short description for summaries.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Finished => "finished",
            Self::TargetReached => "target error reached",
            Self::TimeLimit => "time limit reached",
        }
    }
}

/// The outcome of [`render_adaptive`].
#[derive(Debug, Clone)]
pub struct AdaptiveRender {
    /// The merged adaptive state; [`AdaptiveFrame::image`] gives the layers.
    pub frame: AdaptiveFrame,
    /// Wall-clock seconds spent.
    pub seconds: f64,
    /// One point per round: elapsed seconds, mean spp traced, image error estimate.
    pub history: Vec<ConvergencePoint>,
    /// Why it stopped.
    pub stop: StopReason,
    /// Samples (camera paths) traced.
    pub paths: u64,
    /// Samples dropped as NaN, infinite or negative, summed over the units (see
    /// [`UnitResult::rejected_samples`]); 0 in a healthy render.
    pub rejected_samples: u64,
}

/// Renders `frame` (an empty [`AdaptiveFrame`]) round by round on `threads` threads
/// (0 = all cores), calling `progress(&frame)` after each round.
///
/// # Panics
/// If the thread pool cannot be built (the caller bounds `threads`).
pub fn render_adaptive(
    scene: &RenderScene,
    settings: &RenderConfig,
    mut frame: AdaptiveFrame,
    threads: usize,
    limits: Limits,
    mut progress: impl FnMut(&AdaptiveFrame),
) -> AdaptiveRender {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("thread pool");
    let plan = *frame.plan();
    let start = Instant::now();
    let mut history = Vec::new();
    let mut rejected_samples = 0u64;
    let stop = loop {
        let units = frame.next_round();
        if units.is_empty() {
            break StopReason::Finished;
        }
        let results: Vec<UnitResult> = {
            let f = &frame;
            pool.install(|| {
                use rayon::prelude::*;
                units
                    .par_iter()
                    .map(|&u| {
                        let tile = f.tile(u.tile).expect("round units name existing tiles");
                        render_unit_where(scene, settings, &plan, u, |i, pass| tile.wants(i, pass))
                    })
                    .collect()
            })
        };
        // Offered in tile order; each tile consumes its own passes in pass order anyway.
        for r in &results {
            rejected_samples += r.rejected_samples;
            frame
                .offer(r)
                .expect("locally rendered unit is valid for its plan");
        }
        let elapsed = start.elapsed().as_secs_f64();
        let error = frame.image_error();
        let estimated = frame.every_pixel_estimated();
        history.push(ConvergencePoint {
            elapsed_seconds: elapsed,
            spp: frame.samples_per_pixel().0,
            error_estimate: estimated.then_some(error),
        });
        progress(&frame);
        if frame.settings().mode == AdaptiveMode::Off {
            if let Some(t) = limits.target_error {
                if estimated && error <= t {
                    break StopReason::TargetReached;
                }
            }
        }
        if let Some(limit) = limits.time_limit_seconds {
            if elapsed >= limit {
                break StopReason::TimeLimit;
            }
        }
    };
    let paths = frame
        .tiles()
        .iter()
        .flat_map(|t| t.traced_passes())
        .map(|p| u64::from(p) * u64::from(plan.samples_per_pass))
        .sum();
    AdaptiveRender {
        frame,
        seconds: start.elapsed().as_secs_f64(),
        history,
        stop,
        paths,
        rejected_samples,
    }
}
