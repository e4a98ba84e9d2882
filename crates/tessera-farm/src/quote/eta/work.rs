//! The work an adaptive frame still needs, pixel by pixel (module documentation of
//! [`super`], "Adaptive jobs"): what actually ends an adaptive job is each pixel's own
//! stopping, so the work left is summed from each still-active pixel's own law, not
//! extrapolated from the image estimate.

use crate::adaptive::{AdaptiveFrame, AdaptiveMode, AdaptiveSettings, AdaptiveTile};

/// What an adaptive frame's pixels have traced and are predicted still to trace, in
/// pixel-passes (one pixel for one pass: what a worker traces for a wanted pixel,
/// ARCHITECTURE.md §3 "On the farm a stopped pixel costs nothing"). Summed over frames
/// with [`PixelWork::plus`].
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct PixelWork {
    /// Pixel-passes traced so far, a discarded unbiased pilot included.
    pub done: f64,
    /// Predicted pixel-passes left: each active pixel up to the decision boundary at which
    /// its own `1/sqrt(n)` law and its neighbours' (the dilation) put it under the target,
    /// capped by the plan's end; for an unbiased tile whose pilot decided, the fresh
    /// passes it planned (exact).
    pub left: f64,
    /// Mean of `left` where each pixel's law is uncertain ([`LAW_KURTOSIS`]): each group of
    /// pixels that stops with one pixel's law (its neighbourhood, by the dilation) taken as
    /// log-normal about its law, median the law, of log-variance
    /// `ln(1 + 2 / (k - 1) + kurtosis / k)` (the relative variance of a variance estimated
    /// from `k` passes); the groups are independent, and their sum is fitted by the
    /// log-normal of the same mean and variance (Fenton 1960).
    pub left_mean: f64,
    /// Variance of `left` under the same model.
    pub left_var: f64,
    /// The same pixels' work left where each pixel's per-pass error still grows like
    /// `n^gamma` (the heavy tail's extrapolation, [`pixel_work`]'s `gamma`): at least
    /// `left`.
    pub left_heavy: f64,
    /// Pixel-passes left if every active pixel ran to the plan's end: the sample budget.
    pub budget: f64,
    /// Pixel-passes left if the pixels without a prediction (`unknown`) stopped as soon
    /// as they can (the next decision; an unbiased pilot's end and its fewest fresh
    /// passes): the low end's floor while they are counted at the plan's end in `left`.
    pub left_floor: f64,
    /// Pixels still sampling.
    pub active: u64,
    /// Active pixels whose stop cannot be predicted yet (fewer than 2 passes, or an
    /// unbiased tile whose pilot has not decided), counted in `left` at the plan's end.
    pub unknown: u64,
}

impl PixelWork {
    /// The sum of two frames' work.
    pub fn plus(self, o: PixelWork) -> PixelWork {
        PixelWork {
            done: self.done + o.done,
            left: self.left + o.left,
            left_mean: self.left_mean + o.left_mean,
            left_var: self.left_var + o.left_var,
            left_heavy: self.left_heavy + o.left_heavy,
            budget: self.budget + o.budget,
            left_floor: self.left_floor + o.left_floor,
            active: self.active + o.active,
            unknown: self.unknown + o.unknown,
        }
    }

    /// The predicted total, done and left.
    pub fn total(&self) -> f64 {
        self.done + self.left
    }

    /// The log-normal fitted to the work left (`left_mean`, `left_var`): the median and
    /// the standard deviation of the logarithm; `None` with nothing left.
    pub fn left_lognormal(&self) -> Option<(f64, f64)> {
        if !(self.left_mean > 0.0 && self.left_var.is_finite()) {
            return None;
        }
        let s2 = (1.0 + self.left_var.max(0.0) / (self.left_mean * self.left_mean)).ln();
        Some((self.left_mean * (-0.5 * s2).exp(), s2.sqrt()))
    }
}

/// The excess kurtosis of a pixel's pass values allowed in the uncertainty of its law
/// ([`PixelWork::left_mean`]): the passes keep no fourth moment, and a variance estimated
/// from `k` passes has a relative variance of `2 / (k - 1) + kurtosis / k`. 6: a
/// log-normal pass value of relative spread 0.5 has 5; with normal pass values
/// (kurtosis 0) three slow pixels at 12 passes were predicted 1,080 pixel-passes where
/// they took 2,160 (`a_few_slow_pixels_carry_the_work_left`, log-normal passes of spread
/// 0.5). Heavier tails are the tail class's (`EtaTrend`).
pub const LAW_KURTOSIS: f64 = 6.0;

/// One pixel's part in [`sequential_tile`]'s walk.
#[derive(Debug, Clone, Copy, Default)]
struct Law {
    /// The pass it stops at by its own law, by the heavy law, and at the earliest (the
    /// next decision) when it has no law yet.
    stop: [u32; 3],
    /// The log-variance of its law; 0 where it is capped or unknown.
    log_var: f64,
    /// Pixels whose stop this pixel's law sets (itself included).
    group: u32,
}

/// The work `frame` still needs (module documentation): per active pixel of each
/// unfinished tile,
///
/// - **sequential**: with `k` passes and relative error `r` (the one the policy stops on,
///   `PixelStats::relative_error`), `n = k (r / E)²` passes reach the target `E` under the
///   pixel's own `1/sqrt(n)` law; the pixel stops at the first decision boundary at or
///   above the largest `n` of its 3x3 neighbourhood in the tile (a pixel stops only with
///   its neighbours, the dilation; a stopped neighbour counts as converged), at most the
///   plan's end. With `gamma > 0` the heavy figure `left_heavy` takes
///   `n = k (r / E)^(2 / (1 - gamma))`, the law with the per-pass error growing like
///   `n^gamma` (the quote's heavy extrapolation, `gamma` below 1);
/// - **unbiased**: once the tile's pilot decided, `pilot + fresh - traced` (exact); before,
///   unknown.
///
/// Walks every pixel once and allocates one scratch vector for the frame (not per pixel);
/// for the coordinator's history points, not a hot loop.
pub fn pixel_work(frame: &AdaptiveFrame, gamma: f64) -> PixelWork {
    let settings = *frame.settings();
    let target = settings.target_error;
    let gamma = if gamma.is_finite() {
        gamma.clamp(0.0, 0.9)
    } else {
        0.0
    };
    let mut work = PixelWork::default();
    let mut scratch: Vec<Law> = Vec::new();
    for tile in frame.tiles() {
        work.done += tile.traced_passes().map(f64::from).sum::<f64>();
        if tile.finished() {
            continue;
        }
        match settings.mode {
            AdaptiveMode::Off => {}
            AdaptiveMode::Sequential => {
                sequential_tile(tile, &settings, target, gamma, &mut scratch, &mut work)
            }
            AdaptiveMode::Unbiased => unbiased_tile(tile, &settings, &mut work),
        }
    }
    work
}

/// The first decision boundary at or above `n` passes and after `consumed`, at most `end`.
fn stop_pass(settings: &AdaptiveSettings, consumed: u32, n: f64, end: u32) -> u32 {
    if !(n.is_finite() && n < f64::from(end)) {
        return end;
    }
    let from = (n.ceil() as u32).saturating_sub(1).max(consumed);
    settings.next_boundary(from).map_or(end, |b| b.min(end))
}

fn sequential_tile(
    tile: &AdaptiveTile,
    settings: &AdaptiveSettings,
    target: f64,
    gamma: f64,
    scratch: &mut Vec<Law>,
    work: &mut PixelWork,
) {
    let consumed = tile.consumed_passes();
    let end = tile.end_pass();
    let (w, h) = (tile.rect().width as usize, tile.rect().height as usize);
    let pixels = tile.pixels();
    scratch.clear();
    scratch.resize(pixels.len(), Law::default());
    // Each active pixel's own predicted stop (the point law and the heavy one); a stopped
    // pixel's is 0, converged whatever its neighbours do.
    for (i, s) in pixels.iter().enumerate() {
        if !tile.wants(i, consumed) {
            continue;
        }
        work.active += 1;
        let k = f64::from(s.passes);
        let r = s.relative_error();
        if s.passes < 2 || !r.is_finite() {
            work.unknown += 1;
            let soonest = settings.next_boundary(consumed).map_or(end, |b| b.min(end));
            scratch[i].stop = [end, end, soonest];
            continue;
        }
        let ratio = (r / target).powi(2);
        let n = k * ratio;
        let n_heavy = k * ratio.max(1.0).powf(1.0 / (1.0 - gamma));
        let stop = stop_pass(settings, consumed, n, end);
        scratch[i].stop = [stop, stop_pass(settings, consumed, n_heavy, end), stop];
        if n < f64::from(end) {
            scratch[i].log_var = (1.0 + 2.0 / (k - 1.0) + LAW_KURTOSIS / k).ln();
        }
    }
    // The dilation: a pixel stops with the latest of its 3x3 neighbourhood, whose law
    // then sets its stop (the group of that law).
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            if !tile.wants(i, consumed) {
                continue;
            }
            let (mut by, mut heavy, mut floor) = (i, 0u32, 0u32);
            for yy in y.saturating_sub(1)..(y + 2).min(h) {
                for xx in x.saturating_sub(1)..(x + 2).min(w) {
                    let j = yy * w + xx;
                    if scratch[j].stop[0] > scratch[by].stop[0] {
                        by = j;
                    }
                    heavy = heavy.max(scratch[j].stop[1]);
                    floor = floor.max(scratch[j].stop[2]);
                }
            }
            scratch[by].group += 1;
            let stop = scratch[by].stop[0];
            work.left += f64::from(stop.saturating_sub(consumed));
            work.left_heavy += f64::from(heavy.max(stop).saturating_sub(consumed));
            work.budget += f64::from(end.saturating_sub(consumed));
            work.left_floor += f64::from(floor.min(stop).saturating_sub(consumed));
        }
    }
    // Each group's work left, log-normal about its law (the moments of `left_mean`).
    for law in scratch.iter().filter(|l| l.group > 0) {
        let l = f64::from(law.group) * f64::from(law.stop[0].saturating_sub(consumed));
        let v = law.log_var;
        work.left_mean += l * (0.5 * v).exp();
        work.left_var += l * l * v.exp() * v.exp_m1();
    }
}

fn unbiased_tile(tile: &AdaptiveTile, settings: &AdaptiveSettings, work: &mut PixelWork) {
    let consumed = tile.consumed_passes();
    let end = tile.end_pass();
    let pilot = settings.min_passes;
    let decided = consumed >= pilot;
    for (i, (traced, needed)) in tile
        .traced_passes()
        .zip(tile.fresh_passes_needed())
        .enumerate()
    {
        if !tile.wants(i, consumed) {
            continue;
        }
        work.active += 1;
        let budget = f64::from(end.saturating_sub(consumed));
        work.budget += budget;
        if decided {
            let left = f64::from(pilot.saturating_add(needed).saturating_sub(traced));
            work.left += left;
            work.left_mean += left;
            work.left_heavy += left;
            work.left_floor += left;
        } else {
            work.unknown += 1;
            let fresh = settings.min_fresh_passes.min(end.saturating_sub(pilot));
            work.left_floor += f64::from((pilot + fresh).saturating_sub(consumed).min(end));
            work.left += budget;
            work.left_mean += budget;
            work.left_heavy += budget;
        }
    }
}

#[cfg(test)]
mod tests;
