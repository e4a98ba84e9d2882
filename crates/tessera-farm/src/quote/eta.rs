//! The running ETA of a job (ARCHITECTURE.md §3, "Quotes and ETA"): when it will be
//! done, from its measured progress, and for a job that stops at a target error, as
//! honest as the quote: a 95% interval, or "not predictable from the passes so far" with
//! the reason.
//!
//! # Jobs that run their planned work
//!
//! Their work is known: the remaining passes at the rate so far, `t (planned - done) /
//! done` (passes of a job cost alike), or what is left of a time limit if less.
//!
//! # Adaptive jobs that stop at a target error
//!
//! What ends them is each pixel's own stopping (ARCHITECTURE.md §3, "Adaptive
//! stopping"), not the image estimate: a sequential job ends when every pixel's own `rel`
//! is under the target at a decision (with its 3x3 neighbourhood), an unbiased one when
//! every pixel has the fresh passes its pilot planned. Extrapolating the image estimate by
//! `1/sqrt(work)` (the ETA before 2026-12-07) predicted veach-mis 39-75% short and
//! glass-spot 17 times too long (docs/benchmarks.md, "Quotes and ETA"). So the ETA sums
//! the work left pixel by pixel ([`pixel_work`], [`PixelWork`]), in pixel-passes (a
//! stopped pixel is not traced):
//!
//! - **sequential**: an active pixel with `k` passes and relative error `r` reaches the
//!   target `E` after `n = k (r / E)²` passes under its own `1/sqrt(n)` law; it stops at
//!   the first decision boundary at or above the largest `n` of its neighbourhood (at most
//!   the plan's end);
//! - **unbiased**: after the tile's pilot, exactly the fresh passes it planned; before,
//!   unknown (counted at the plan's end; "not predictable yet" while more than a tenth of
//!   the active pixels are).
//!
//! The seconds are that work over the rate ([`AdaptiveEta`]): pixel-passes traced per
//! second over the later half of the job so far, less the time since the measurement. Its
//! 95% interval combines, on a log scale: the laws' own uncertainty (each neighbourhood's
//! law log-normal with the relative variance of a variance from `k` passes,
//! `2 / (k - 1) + kurtosis / k`, [`LAW_KURTOSIS`]; their sum fitted by a log-normal of
//! the same moments, Fenton 1960), the drift of the predicted total since half the job
//! (where the laws still move, the prediction is that uncertain), and [`LAW_SD`] for what
//! the laws leave out (first passage, dilation); and the spread of the rate between the
//! job's third and fourth quarters. The tail class is the merged passes' ([`EtaTrend`],
//! below): heavy widens the high end to each pixel's law with its per-pass error growing
//! like `n^gamma`; not predictable gives no point ETA and an interval up to the sample
//! budget at the slow end of the rate.
//!
//! # The tail class of a job that stops at a target error
//!
//! The image error falls like `1/sqrt(work)` where the pass values' variance is finite
//! and their per-pass error settled (the quote's law, module documentation of
//! [`crate::quote`]): from the current error `e` after `t` seconds, reaching the target `E`
//! takes `(e / E)²` times the work done, `t ((e / E)² - 1)` more seconds (the image law,
//! kept for a caller with no pixel statistics). The law rests on
//! the same two things a quote's does, and the job's merged passes measure both
//! ([`EtaTrend`]):
//!
//! - **the error's spread over the frame**: `M = e²` is a mean over the pixels, and its
//!   relative standard error over the frame's groups of pixels (tiles, or bands of 16
//!   rows of a whole-frame tile; [`error_groups`]), `rel_M`, gives the interval
//!   `[t ((e / E)² exp(-1.96 rel_M) - 1), t ((e / E)² exp(1.96 rel_M) - 1)]`, as the
//!   quote's interval on `M` does;
//! - **the per-pass error's growth** `g`: the pixels' mean per-pass relative variance
//!   (`rel² k` of a pixel with `k` passes, [`ErrorGroup::sum_per_pass`]) now over the same
//!   at about half the work so far. For a finite variance both estimate the same per-pass
//!   variance and `g` is about 1, whether or not some pixels stopped early (a pixel's
//!   per-pass figure does not depend on its pass count); where rare bright paths carry the
//!   error, each pass that catches one raises it, and `g` grows (the pilot's statistic of
//!   the same name, [`super::Tails`], between its halves and all of it).
//!
//! They are classed as the quote classes its pilot ([`super::TailClass`]), with the
//! quote's thresholds: `g >=` [`super::tails::GROWTH_UNPREDICTABLE`] is not predictable
//! (the error did not fall with the work); `g >` [`super::tails::GROWTH_HEAVY`] is heavy,
//! and the interval's high end extrapolates the per-pass error still growing like
//! `work^gamma`, `gamma = log2 g` (`n / n_now = (M_high / E²)^(1 / (1 - gamma))`, the
//! quote's heavy extrapolation); a heavy job whose groups disagree on its error, `rel_M`
//! above [`super::REL_M_UNPREDICTABLE`], is not predictable either. A job that is not
//! predictable has no point ETA: the interval's low end is the law's figure (a lower
//! bound, as the quote's), its high end the planned work at the rate so far (the job
//! cannot run past its sample budget).
//!
//! What the merged state does not keep, the pilot's other two statistics need: Hill's
//! tail index and the share of the brightest pass values are read off each pixel's
//! individual pass values, which a merge folds into running sums. Every figure is capped
//! by the planned work at the rate so far and by a time limit.

use super::{ratio_mean, TailClass, REL_M_UNPREDICTABLE, Z95};
use crate::quote::tails::{GROWTH_HEAVY, GROWTH_UNPREDICTABLE};
use crate::PixelStats;

mod work;
pub use work::{pixel_work, PixelWork, LAW_KURTOSIS};

/// A group of a frame's pixels whose errors are summed, for the spread of the image
/// error over the frame and its per-pass figure ([`error_groups`]).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ErrorGroup {
    /// Pixels in the group with an error estimate (at least 2 passes).
    pub pixels: u64,
    /// Sum over them of the squared relative error (`PixelStats::relative_error`).
    pub sum_sq_rel: f64,
    /// Sum over them of the squared relative error times the pixel's passes: the
    /// per-pass relative variance, which does not fall with the passes.
    pub sum_per_pass: f64,
}

/// The error groups of a frame's tiles, each given as its width and its pixels'
/// statistics (row-major): one group per tile, or bands of 16 rows of a frame of a single
/// tile (a whole-frame bdpt tile), whose one group would have no spread. Pixels with fewer
/// than 2 passes have no estimate and are left out.
pub fn error_groups<'a>(
    tiles: impl IntoIterator<Item = (u32, &'a [PixelStats])>,
) -> Vec<ErrorGroup> {
    let tiles: Vec<(u32, &[PixelStats])> = tiles.into_iter().collect();
    let single = tiles.len() == 1;
    let mut groups = Vec::new();
    for (width, pixels) in tiles {
        let band = if single {
            width.max(1) as usize * 16
        } else {
            pixels.len().max(1)
        };
        for chunk in pixels.chunks(band) {
            let mut g = ErrorGroup::default();
            for s in chunk.iter().filter(|s| s.passes >= 2) {
                let r2 = s.relative_error().powi(2);
                if r2.is_finite() {
                    g.pixels += 1;
                    g.sum_sq_rel += r2;
                    g.sum_per_pass += r2 * f64::from(s.passes);
                }
            }
            groups.push(g);
        }
    }
    groups
}

/// What a running job's merged passes say of its error's tail (module documentation): the
/// statistics a stopping job's ETA is classed by.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct EtaTrend {
    /// Relative standard error of the image's mean squared error over its groups of
    /// pixels; `None` with fewer than 2 groups with pixels.
    pub rel_m: Option<f64>,
    /// The mean per-pass relative variance now over the same at about half the work so
    /// far; `None` until there is such an earlier figure.
    pub growth: Option<f64>,
}

impl EtaTrend {
    /// The spread of `groups`' error, and the mean per-pass figure they give (for a later
    /// [`EtaTrend::with_growth`]); `None` for the figure when no pixel has an estimate.
    pub fn of_groups(groups: &[ErrorGroup]) -> (Option<f64>, Option<f64>) {
        let with: Vec<&ErrorGroup> = groups.iter().filter(|g| g.pixels > 0).collect();
        let pixels: u64 = with.iter().map(|g| g.pixels).sum();
        if pixels == 0 {
            return (None, None);
        }
        let per_pass = with.iter().map(|g| g.sum_per_pass).sum::<f64>() / pixels as f64;
        let (m, se) = ratio_mean(with.iter().map(|g| (g.pixels as f64, g.sum_sq_rel)));
        let rel_m = se.filter(|_| m > 0.0).map(|se| se / m);
        (rel_m, Some(per_pass).filter(|q| q.is_finite()))
    }

    /// The growth of the per-pass figure `now` at `work` from `history`, the figures
    /// earlier in the job as `(work, per-pass figure)` in any order and unit of work: the
    /// latest one at or below half of `work` (none when there is none, or it is 0).
    pub fn with_growth(
        rel_m: Option<f64>,
        now: Option<f64>,
        work: f64,
        history: impl IntoIterator<Item = (f64, f64)>,
    ) -> Self {
        let earlier = history
            .into_iter()
            .filter(|&(w, q)| w > 0.0 && w <= 0.5 * work && q > 0.0 && q.is_finite())
            .max_by(|a, b| a.0.total_cmp(&b.0));
        let growth = match (now, earlier) {
            (Some(q), Some((_, q_half))) => Some(q / q_half).filter(|g| g.is_finite()),
            _ => None,
        };
        Self { rel_m, growth }
    }

    /// The class and, unless light, the reason in words with the figures (module
    /// documentation). Without a growth yet, light: the spread alone gives the interval.
    pub fn verdict(&self) -> (TailClass, Option<String>) {
        let Some(g) = self.growth else {
            return (TailClass::Light, None);
        };
        let figures = format!(
            "per-pass error x{g:.2} from half the work so far to all of it, relative \
             standard error {} of the mean squared error over the frame's tiles",
            self.rel_m.map_or("n/a".into(), |r| format!("{r:.2}"))
        );
        let not = |why: &str| {
            Some(format!(
                "not predictable from the passes so far: {why}, the mark of rare paths \
                 (fireflies) whose variance the passes have not sized; the interval runs \
                 from what the 1/sqrt(work) law says (a lower bound) to the sample budget \
                 ({figures})"
            ))
        };
        if g >= GROWTH_UNPREDICTABLE {
            return (
                TailClass::Unpredictable,
                not("the error estimate grew with the passes instead of falling"),
            );
        }
        if g > GROWTH_HEAVY {
            if let Some(r) = self.rel_m.filter(|&r| r > REL_M_UNPREDICTABLE) {
                return (
                    TailClass::Unpredictable,
                    not(&format!(
                        "the per-pass error is growing and the frame's tiles disagree on \
                         the error (relative standard error {r:.2}, above \
                         {REL_M_UNPREDICTABLE})"
                    )),
                );
            }
            return (
                TailClass::Heavy,
                Some(format!(
                    "heavy-tailed: the interval's high end extrapolates the per-pass error \
                     growing like work^{:.2} ({figures})",
                    g.log2()
                )),
            );
        }
        (TailClass::Light, None)
    }
}

/// A running job's progress, what [`job_eta`] predicts from.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct JobProgress {
    /// Seconds spent rendering so far (the rate's denominator; the coordinator counts
    /// from the job's first lease).
    pub elapsed_seconds: f64,
    /// Passes merged, over all tiles and frames; or any measure of the work done in the
    /// unit of `passes_planned` (only their ratio counts: the coordinator passes passes
    /// times units, to count the spot checks' copies without truncating).
    pub passes_done: u64,
    /// Passes planned, over all tiles and frames (or the work planned, as above).
    pub passes_planned: u64,
    /// The current image error estimate, if there is one.
    pub error: Option<f64>,
    /// The target error, if the job stops when its image reaches it (adaptive jobs). A
    /// job without adaptive stopping on the farm runs its planned passes whatever its
    /// target, so its target does not shorten its ETA.
    pub stopping_target: Option<f64>,
    /// Seconds left of the job's time limit, if it has one.
    pub time_limit_left_seconds: Option<f64>,
    /// What the merged passes say of the error's tail, for a job that stops at its
    /// target; `None` reads as light with no spread.
    pub trend: Option<EtaTrend>,
    /// An adaptive job that stops at its target: its pixels' work left and the measured
    /// rate. `None` before its first measurement; the ETA then falls back to the image
    /// law.
    pub adaptive: Option<AdaptiveEta>,
}

/// The standard deviation of the logarithm allowed for the pixels' laws themselves in
/// the work left ([`AdaptiveEta::eta`]): a pixel stops at the first decision its noisy estimate
/// falls under the target (a first passage, earlier than the law's mean crossing) and only
/// with its 3x3 neighbourhood (later); on synthetic frames with normal-tailed passes the
/// two left the predicted work within 5% of what the frames then took
/// (`the_work_left_holds_what_the_frame_then_takes`), and 10% is allowed for frames whose
/// pixels are fewer or whose passes are less regular.
pub const LAW_SD: f64 = 0.1;

/// One measurement of an adaptive job's pixel work ([`PixelWork`]), kept over the job so
/// that the rate and the drift of the prediction can be read off later ones.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct EtaSample {
    /// Seconds since the job's first lease.
    pub elapsed_seconds: f64,
    /// Pixel-passes traced by then ([`PixelWork::done`]).
    pub done: f64,
    /// The total pixel-passes then predicted ([`PixelWork::total`]).
    pub total: f64,
}

/// An adaptive job's work left and the rate it is done at: what the ETA of a job that
/// stops at its target extrapolates (module documentation, "Adaptive jobs").
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct AdaptiveEta {
    /// The job's pixel work, summed over its frames, as of the measurement.
    pub work: PixelWork,
    /// Pixel-passes traced per second, over the later half of the job so far (the
    /// first lease, the scene's transfer and the workers' set-up left out), or over all
    /// of it before there is an earlier measurement.
    pub rate: f64,
    /// The rate's spread, a standard deviation of its logarithm: `|ln(r3 / r4)|` of the
    /// rates over the third and the fourth quarter of the job so far; 0 until measured.
    pub rate_spread: f64,
    /// How far the predicted total moved since about half the job so far, in
    /// pixel-passes: where the laws' predictions still move, the prediction is that
    /// uncertain.
    pub drift: f64,
    /// Seconds since the measurement (the status is asked between them).
    pub age_seconds: f64,
}

impl AdaptiveEta {
    /// The measurement `work` at `elapsed_seconds`, with the rate, its spread and the
    /// drift read against `earlier` measurements of the same job (in any order);
    /// `age_seconds` since it was taken.
    pub fn measure(
        work: PixelWork,
        elapsed_seconds: f64,
        earlier: &[EtaSample],
        age_seconds: f64,
    ) -> Self {
        let t = elapsed_seconds;
        // The latest measurement at or before `at`.
        let at = |at: f64| {
            earlier
                .iter()
                .filter(|s| s.elapsed_seconds > 0.0 && s.elapsed_seconds <= at)
                .max_by(|a, b| a.elapsed_seconds.total_cmp(&b.elapsed_seconds))
                .copied()
        };
        let rate_between = |a: EtaSample, b: EtaSample| {
            let dt = b.elapsed_seconds - a.elapsed_seconds;
            Some((b.done - a.done) / dt).filter(|r| dt > 0.0 && r.is_finite() && *r > 0.0)
        };
        let now = EtaSample {
            elapsed_seconds: t,
            done: work.done,
            total: work.total(),
        };
        let half = at(0.5 * t);
        let rate = half
            .and_then(|h| rate_between(h, now))
            .unwrap_or(if t > 0.0 { work.done / t } else { 0.0 });
        let rate_spread = match (half, at(0.75 * t)) {
            (Some(h), Some(q)) => match (rate_between(h, q), rate_between(q, now)) {
                (Some(r3), Some(r4)) => (r3 / r4).ln().abs(),
                _ => 0.0,
            },
            _ => 0.0,
        };
        Self {
            work,
            rate,
            rate_spread,
            drift: half.map_or(0.0, |h| (now.total - h.total).abs()),
            age_seconds: age_seconds.max(0.0),
        }
    }

    /// The ETA (module documentation, "Adaptive jobs"): the work left over the rate, its
    /// 95% interval from the pixels' laws' variance and the prediction's drift (in
    /// pixel-passes) and the rate's spread, classed by `trend` as the quote classes its
    /// pilot, all less the measurement's age and capped by the sample budget at the
    /// slow end of the rate and by `time_limit_left_seconds`.
    pub fn eta(&self, trend: EtaTrend, time_limit_left_seconds: Option<f64>) -> JobEta {
        let w = &self.work;
        let spread = if self.rate_spread.is_finite() {
            self.rate_spread
        } else {
            0.0
        };
        let f = (Z95 * spread).exp();
        let seconds = |pixel_passes: f64, rate: f64| pixel_passes / rate - self.age_seconds;
        let mut cap = if self.rate > 0.0 {
            seconds(w.budget, self.rate / f)
        } else {
            f64::INFINITY
        };
        if let Some(limit) = time_limit_left_seconds {
            cap = cap.min(limit);
        }
        let cap = cap.max(0.0);
        let clamp = |s: f64| if s.is_nan() { cap } else { s.clamp(0.0, cap) };
        let (mut class, mut note) = trend.verdict();
        // Too many pixels without a law: nothing bounds the work from below (measured: a
        // low end from their soonest stops at the early rate lay above the actual finish
        // at all 4 such marks, docs/benchmarks.md "The ETA of adaptive jobs from each
        // pixel's own law"), so the interval starts at 0.
        let mut no_floor = false;
        if self.rate.is_nan() || self.rate <= 0.0 {
            class = TailClass::Unpredictable;
            note = Some("not predictable yet: no rate measured".into());
            no_floor = true;
        } else if w.unknown * 10 > w.active {
            class = TailClass::Unpredictable;
            note = Some(format!(
                "not predictable yet: {} of the {} pixels still sampling have no prediction \
                 (fewer than 2 passes, or their tile's unbiased pilot has not decided); the \
                 interval runs from 0 to the sample budget",
                w.unknown, w.active
            ));
            no_floor = true;
        }
        // The work left's interval in pixel-passes, on a log scale: the pixels' laws
        // (their log-normal sum), the prediction's drift and the laws' own error
        // ([`LAW_SD`]) combined.
        let (median, log_sd) = w.left_lognormal().unwrap_or((w.left, 0.0));
        let rel_drift = if w.left > 0.0 {
            self.drift / w.left
        } else {
            0.0
        };
        let log_sd = (log_sd * log_sd + rel_drift * rel_drift + LAW_SD * LAW_SD).sqrt();
        let spread_work = (Z95 * log_sd).exp();
        // Pixels without a law yet count at their soonest stop at the low end.
        let floor = if w.unknown > 0 { w.left_floor } else { w.left };
        let low = seconds(w.left.min(median).min(floor) / spread_work, self.rate * f);
        let mut high = seconds(w.left.max(median) * spread_work, self.rate / f);
        if class == TailClass::Heavy {
            high = high.max(seconds(w.left_heavy * spread_work, self.rate / f));
        }
        let low = if no_floor { 0.0 } else { low };
        let point = seconds(w.left, self.rate);
        let (point, high) = match class {
            TailClass::Unpredictable => (None, cap),
            _ => (Some(point), high),
        };
        JobEta {
            seconds: point.map(clamp),
            interval: Some((clamp(low), clamp(high))),
            tail_class: Some(class),
            note,
        }
    }
}

/// A running job's ETA ([`job_eta`]).
#[derive(Debug, Clone, PartialEq)]
pub struct JobEta {
    /// Estimated seconds until done; `None` when not predictable.
    pub seconds: Option<f64>,
    /// The 95% interval `(low, high)` of the seconds left, for a job that stops at its
    /// target (its low end a lower bound when not predictable).
    pub interval: Option<(f64, f64)>,
    /// For a job that stops at its target: how far the law can be trusted.
    pub tail_class: Option<TailClass>,
    /// Why, unless light: the reason and the figures.
    pub note: Option<String>,
}

/// Estimated seconds until a running job is done, with its interval and tail class (module
/// documentation): the smallest of the remaining passes at the rate so far, for an
/// adaptive job that stops at a target its pixels' work left ([`AdaptiveEta`]) at the
/// measured rate, classed by [`EtaTrend::verdict`], and what is left of a time limit.
/// `None` before any pass is merged. Never negative.
pub fn job_eta(p: &JobProgress) -> Option<JobEta> {
    if p.passes_done == 0 || p.elapsed_seconds.is_nan() || p.elapsed_seconds <= 0.0 {
        return None;
    }
    let t = p.elapsed_seconds;
    let left = p.passes_planned.saturating_sub(p.passes_done) as f64;
    let mut cap = t * left / p.passes_done as f64;
    if let Some(limit) = p.time_limit_left_seconds {
        cap = cap.min(limit);
    }
    let cap = cap.max(0.0);
    let planned = Some(JobEta {
        seconds: Some(cap),
        interval: None,
        tail_class: None,
        note: None,
    });
    let Some(target) = p.stopping_target.filter(|t| t.is_finite() && *t > 0.0) else {
        return planned;
    };
    if let Some(a) = p.adaptive {
        let mut eta = a.eta(p.trend.unwrap_or_default(), p.time_limit_left_seconds);
        // No rate of pixel work yet: the planned passes at the job's pass rate bound it
        // (an interval with no upper end reads as "unbounded" to every client).
        if let Some((low, _)) = eta.interval.filter(|i| !i.1.is_finite()) {
            eta.interval = Some((low.min(cap), cap));
        }
        return Some(eta);
    }
    let Some(e) = p.error.filter(|e| e.is_finite() && *e >= 0.0) else {
        // A job that stops at its target with no error estimate yet (the coordinator
        // measures its pixels at its first history point): the passes it may take are
        // the plan's, its stop unknown; a point here would be the plan's end, measured
        // at +217% at 10% of a Cornell box job (docs/benchmarks.md).
        return Some(JobEta {
            seconds: None,
            interval: Some((0.0, cap)),
            tail_class: Some(TailClass::Unpredictable),
            note: Some(
                "not predictable yet: no error estimate merged; the interval runs from 0 \
                 to the planned passes"
                    .into(),
            ),
        });
    };
    // No pixel statistics (a caller that keeps none): the image law.
    let clamp = |s: f64| if s.is_nan() { cap } else { s.clamp(0.0, cap) };
    let trend = p.trend.unwrap_or_default();
    let (class, note) = trend.verdict();
    let rel = trend.rel_m.unwrap_or(0.0);
    // The work needed over the work done, at the estimate and the ends of `M`'s interval.
    let ratio = (e / target).powi(2);
    let (r_low, r_high) = (ratio * (-Z95 * rel).exp(), ratio * (Z95 * rel).exp());
    let law = |r: f64| t * (r - 1.0);
    let (seconds, low, high) = match class {
        TailClass::Light => (Some(law(ratio)), law(r_low), law(r_high)),
        TailClass::Heavy => {
            // gamma < 1 below the unpredictable growth: E(n)² = M (n / n_now)^(gamma - 1).
            let gamma = trend.growth.map_or(0.0, |g| g.max(1.0).log2());
            let high = law(r_high).max(law(r_high.max(1.0).powf(1.0 / (1.0 - gamma))));
            (Some(law(ratio)), law(r_low), high)
        }
        TailClass::Unpredictable => (None, law(ratio), cap),
    };
    Some(JobEta {
        seconds: seconds.map(clamp),
        interval: Some((clamp(low), clamp(high))),
        tail_class: Some(class),
        note,
    })
}

/// Estimated seconds until a running job is done ([`job_eta`]'s point figure): `None`
/// before any pass is merged, and for a job that stops at a target whose error is not
/// predictable from its passes so far.
pub fn job_eta_seconds(p: &JobProgress) -> Option<f64> {
    job_eta(p).and_then(|e| e.seconds)
}

#[cfg(test)]
mod tests;
