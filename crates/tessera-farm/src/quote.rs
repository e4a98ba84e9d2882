//! Quotes: what an accuracy costs, predicted from a short pilot render (ARCHITECTURE.md
//! §3, "Quotes and ETA").
//!
//! A pilot renders a few passes of a deterministic subset of a job's tiles with the job's
//! own settings and pass size, so a pilot pass costs and scatters like a pass of the job.
//! From it, [`quote`] predicts the image error the job reaches and the worker-seconds and
//! wall seconds it needs to reach given errors, with an interval for each.
//!
//! # The model
//!
//! Passes are independent replicates (ARCHITECTURE.md §3), so a pixel's variance of the
//! mean after `n` passes is `σ²/n`, and its relative error falls like `1/sqrt(n)`: the
//! image error (the RMS of the per-pixel relative errors over their robust scale,
//! `FrameImage::error_estimate`) after `n` passes is
//!
//! ```text
//! E(n) = sqrt(M · P / n),   M = mean over pilot pixels of rel², P = pilot passes
//! ```
//!
//! (`M` is the square of that estimate of the pilot, [`pilot_groups`]: a render stopping
//! at a target stops on it), and reaching a target `t` takes `n(t) = ceil(M · P / t²)` passes (at least 2, the fewest
//! with an error estimate). The cost of a pass is measured per pixel: `C` worker-seconds per
//! pixel-pass, the pilot's worker-seconds over its pixel-passes, so a frame of `W · H`
//! pixels costs `n · C · W · H` worker-seconds and the job `frames` times that.
//!
//! On the farm those are `U = frames · tiles · ceil(n / passes_per_unit)` units of equal
//! cost, and the spot checks render `K` of them twice (`K` ~ Binomial(`U`, fraction),
//! since which units are checked hashes the job's id, not known before it is submitted).
//! The worker-seconds count the copies; the wall seconds are the set-up plus the rounds
//! of units the workers take, `ceil((U + K) / workers)` units' time, expected over `K`.
//! With many small units that is the worker-seconds over the workers; with a few large
//! ones it is not: 8 whole-frame bdpt units on 2 workers take 4 rounds, or 5 when one
//! unit is spot-checked (a 2% fraction checks one of 8 units in 15% of jobs).
//!
//! # The interval
//!
//! `M` and `C` are means over a sample of the frame, and each carries a standard error:
//!
//! - `M` from the spread of the pilot's groups of pixels (its tiles, or bands of a
//!   whole-frame tile): a cluster-sample ratio estimate. The spread includes both the
//!   true variation over the frame and the noise of each group's variance estimate
//!   (with `K` replicates a variance estimate has relative standard error about
//!   `sqrt(2 / (K - 1))`, so an error estimate about `1 / sqrt(2 (K - 1))`; Owen 2001,
//!   section 6.7, on replicate-based error estimates). With a single group there is no
//!   spread, and the quote falls back on that per-replicate figure, which is conservative.
//! - `C` from the spread of the pilot's per-unit costs per pixel-pass, the same way.
//!
//! Worker-seconds are proportional to `M · C`, so their relative standard error is
//! `r = sqrt((se(M)/M)² + (se(C)/C)²)`, and the quote gives the 95% interval
//! `[s · exp(-1.96 r), s · exp(1.96 r)]` (log-normal, so it stays positive). An error's
//! interval uses `se(M)/(2M)` alike. The farm's figures take the spot checks' copies at
//! the 2.5% and 97.5% quantiles of `K` for the interval's two ends.
//!
//! Where the pilot's pass values are heavy-tailed (rare paths: fireflies), the interval
//! above understates the truth, because the law it extrapolates does not yet hold: the
//! pilot's tails ([`Tails`], the statistics in its module documentation) widen the
//! interval's high end, or make the quote "not predictable from the pilot"
//! ([`TailClass`], with the reason in [`Quote::tail_note`]); so does a heavy tail with
//! an `M` whose relative standard error exceeds [`REL_M_UNPREDICTABLE`].
//!
//! What the interval does not cover: paths so rare that no pilot pass found them (a
//! caustic the pilot missed makes every prediction optimistic; Jensen 2001, section 10.3,
//! on what a pilot can miss), a machine whose load changes between the pilot and the job,
//! and per-frame scene loading on workers beyond the measured `setup_seconds`. Adaptive
//! stopping is not modelled: the quote assumes every pixel takes every pass (adaptive
//! `off`); stopping converged pixels can only need fewer passes for the same image error.
//!
//! ```
//! use tessera_farm::quote::{quote, PilotGroup, PilotMeasurement, PilotUnit, QuoteJob};
//! // A pilot of 4 passes over two tiles of 1024 pixels, RMS relative error 0.2.
//! let pilot = PilotMeasurement {
//!     passes: 4,
//!     groups: vec![
//!         PilotGroup { pixels: 1024, sum_sq_rel: 1024.0 * 0.04 },
//!         PilotGroup { pixels: 1024, sum_sq_rel: 1024.0 * 0.04 },
//!     ],
//!     units: vec![PilotUnit { pixel_passes: 1024, worker_seconds: 0.01 }; 8],
//!     tails: None,
//! };
//! let job = QuoteJob {
//!     pixels_per_frame: 65536,
//!     frames: 1,
//!     planned_passes: 16,
//!     samples_per_pass: 16,
//!     workers: 2,
//!     setup_seconds: 0.0,
//!     tiles_per_frame: 64,
//!     passes_per_unit: 1,
//!     spot_check_fraction: 0.0,
//!     stop_interval: 0,
//! };
//! let q = quote(&pilot, &job, &[0.05]).unwrap();
//! // 0.2 after 4 passes: 0.1 after 16, 0.05 after 64.
//! assert!((q.planned.error.estimate - 0.1).abs() < 1e-12);
//! assert_eq!(q.targets[0].passes.estimate, 64.0);
//! assert!(!q.targets[0].within_plan);
//! ```

use serde::{Deserialize, Serialize};

mod eta;
mod tails;
pub use eta::{
    error_groups, job_eta, job_eta_seconds, pixel_work, AdaptiveEta, ErrorGroup, EtaSample,
    EtaTrend, JobEta, JobProgress, PixelWork, LAW_KURTOSIS, LAW_SD,
};
pub use tails::{TailClass, Tails};

/// The errors a quote is given when the job names none: 10%, 5%, 2% and 1%.
pub const DEFAULT_TARGETS: [f64; 4] = [0.10, 0.05, 0.02, 0.01];

/// Passes a pilot renders: the fewest that give each pixel a variance estimate with 3
/// degrees of freedom (an error estimate's relative standard error `1/sqrt(2·3)`, 41%, per
/// pixel; averaged over the pilot's pixels much less).
pub const PILOT_PASSES: u32 = 4;

/// At most this many pixels take part in a pilot (whole tiles, chosen evenly over the
/// frame), and at least [`PILOT_MIN_TILES`] tiles when the frame has them: a pilot of 4
/// passes over 8192 pixels costs a 64 spp job's passes over 1/32 of a 512 x 512 frame.
pub const PILOT_PIXELS: u64 = 8192;

/// The fewest tiles a pilot samples (all of them in a smaller frame), so the spread over
/// groups is measured.
pub const PILOT_MIN_TILES: u32 = 8;

/// The z value of a two-sided 95% interval.
const Z95: f64 = 1.96;

/// Above this relative standard error of the pilot's mean squared error `M` (over its
/// groups of pixels), a heavy-tailed pilot ([`TailClass::Heavy`]) is not predictable.
/// Where the pass values' tail index is below 4, their fourth moment, and so the spread of
/// `M` over groups, has no dependable estimate; when even the measured spread puts `M`
/// within a factor `exp(1.96 x 0.5)` = 2.7 either way, the extrapolated passes (a power
/// above 1 of `M`) span more than 10x and the pilot has not sized the error. Measured
/// (docs/benchmarks.md, "Quotes at 5% and 2% on the calibration suite"): the bdpt caustic
/// at 32x32, 0.55, was quoted [8, 96] passes for 5% and took 80 to 640; the glossy
/// highlight at 32x32, 0.35, and veach-mis at 64x64, 0.12, are covered at 5% and 2%.
pub const REL_M_UNPREDICTABLE: f64 = 0.5;

/// A group of pilot pixels whose error is summed: a tile, or a band of a whole-frame tile.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PilotGroup {
    /// Pixels in the group, each with the pilot's passes.
    pub pixels: u64,
    /// Sum over the group's pixels of the squared relative error after the pilot's passes
    /// (as [`pilot_groups`] weighs it: the render's image estimate's).
    pub sum_sq_rel: f64,
}

/// The pilot's pixels in groups for the error and its spread: each pilot tile of `acc`, or
/// bands of 16 rows of a single whole-frame tile (bdpt), whose one group would have no
/// spread.
///
/// A render that stops at a target stops when its own image estimate
/// ([`crate::FrameAccumulator::image_error`]: each pixel's spread over a robust scale,
/// ARCHITECTURE.md §3) reaches it, so the groups' mean squared error is that estimate of
/// the pilot, squared; each group's share of it is its share of the pixels' squared
/// relative errors over their own means (`PixelStats::relative_error`), which the spread
/// over groups is measured with. The own-mean figure alone is lower after a pilot's few
/// passes wherever pass values are skewed (a pass that catches a bright path raises the
/// mean it is divided by), and the law then fell short: on the indirect room (24x24, 5%)
/// it quoted 84 passes [76, 92] and every render took 100 or 104, while the robust
/// estimate's per-pass error at 4 passes (0.252) was the renders' at their end (0.24-0.25).
pub fn pilot_groups(acc: &crate::FrameAccumulator, tiles: &[u32]) -> Vec<PilotGroup> {
    let mut groups = Vec::new();
    for &t in tiles {
        let Some(tile) = acc.tile(t) else { continue };
        let band = if tiles.len() == 1 {
            tile.rect().width.max(1) as usize * 16
        } else {
            tile.pixels().len().max(1)
        };
        for chunk in tile.pixels().chunks(band) {
            groups.push(PilotGroup {
                pixels: chunk.len() as u64,
                sum_sq_rel: chunk.iter().map(|s| s.relative_error().powi(2)).sum(),
            });
        }
    }
    let pixels: u64 = groups.iter().map(|g| g.pixels).sum();
    let own: f64 = groups.iter().map(|g| g.sum_sq_rel).sum();
    let render = acc.image_error();
    if pixels > 0 && own > 0.0 && render.is_finite() {
        let scale = render * render * pixels as f64 / own;
        for g in &mut groups {
            g.sum_sq_rel *= scale;
        }
    }
    groups
}

/// One rendered unit of the pilot and what it cost.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PilotUnit {
    /// Pixels times passes the unit rendered.
    pub pixel_passes: u64,
    /// Worker-seconds it took: seconds of one worker using all its threads (a unit's
    /// thread-seconds divided by the worker's threads).
    pub worker_seconds: f64,
}

/// What a pilot render measured.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PilotMeasurement {
    /// Passes every pilot pixel took (at least 2).
    pub passes: u32,
    /// The pilot's pixels in groups, for the error and its spread.
    pub groups: Vec<PilotGroup>,
    /// The pilot's units, for the cost per pixel-pass and its spread.
    pub units: Vec<PilotUnit>,
    /// The tails of the pilot's pass values ([`Tails::measure`]), when measured: whether
    /// the quote stands, is widened or cannot be given ([`Tails::verdict`]).
    #[serde(default)]
    pub tails: Option<Tails>,
}

/// The job a quote is for.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct QuoteJob {
    /// Pixels of one frame (`width * height`).
    pub pixels_per_frame: u64,
    /// Frames in the job.
    pub frames: u64,
    /// Passes the job plans per pixel.
    pub planned_passes: u32,
    /// Samples per pass (the pilot's and the job's).
    pub samples_per_pass: u32,
    /// Workers the work is spread over (at least 1).
    pub workers: u32,
    /// Seconds of set-up before the first unit (loading the scene, building its BVH),
    /// added once to the wall time.
    pub setup_seconds: f64,
    /// Tiles of a frame: a pass of a frame is this many units (1 for a whole-frame tile,
    /// as bdpt renders).
    pub tiles_per_frame: u32,
    /// Passes per work unit (the coordinator's `passes_per_unit`, 1 by default).
    pub passes_per_unit: u32,
    /// The fraction of units the farm renders a second time to compare the copies (spot
    /// checks, `tessera_farm::DEFAULT_SPOT_CHECK_FRACTION` by default; 0 for none).
    pub spot_check_fraction: f64,
    /// Passes between the checks of a job that stops at its target error (the adaptive
    /// policy's `interval`: a render stopping at a target checks its image after each round
    /// of that many passes, so it stops at a multiple of it). A target's passes are rounded
    /// up to it. 0 or 1: no rounding (a job that runs its planned passes).
    #[serde(default)]
    pub stop_interval: u32,
}

/// A predicted quantity and its 95% interval.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Interval {
    /// The prediction.
    pub estimate: f64,
    /// Lower end of the 95% interval.
    pub low: f64,
    /// Upper end of the 95% interval.
    pub high: f64,
}

impl Interval {
    /// `estimate` with the log-normal interval of relative standard error `rel_se`.
    fn lognormal(estimate: f64, rel_se: f64) -> Self {
        Self {
            estimate,
            low: estimate * (-Z95 * rel_se).exp(),
            high: estimate * (Z95 * rel_se).exp(),
        }
    }

    fn map(self, f: impl Fn(f64) -> f64) -> Self {
        Self {
            estimate: f(self.estimate),
            low: f(self.low),
            high: f(self.high),
        }
    }

    /// Whether `x` lies in `[low, high]`.
    pub fn contains(&self, x: f64) -> bool {
        self.low <= x && x <= self.high
    }
}

/// What a number of passes costs.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Cost {
    /// Passes per pixel (whole passes; the interval from the error's interval).
    pub passes: Interval,
    /// Samples per pixel, `passes * samples_per_pass`.
    pub spp: Interval,
    /// The image error predicted at those passes.
    pub error: Interval,
    /// Worker-seconds per frame.
    pub worker_seconds_per_frame: Interval,
    /// Worker-seconds for the whole job.
    pub worker_seconds: Interval,
    /// Wall seconds per frame with the job's workers: worker-seconds over workers.
    pub seconds_per_frame: Interval,
    /// Wall seconds for the whole job: set-up plus worker-seconds over workers.
    pub seconds: Interval,
}

/// The cost of reaching one target error.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TargetQuote {
    /// The target image error (RMS relative error).
    pub target: f64,
    /// Whether the job's planned passes suffice (by the estimate). When not, the job as
    /// planned stops at its sample budget above the target; ask for more spp.
    pub within_plan: bool,
    /// Passes per pixel needed (the interval from the pilot error's interval).
    pub passes: Interval,
    /// What they cost.
    pub cost: Cost,
}

/// A quote: the planned job's predicted error and cost, and the cost of each target.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Quote {
    /// The pilot's image error after its passes.
    pub pilot_error: f64,
    /// The pilot's passes.
    pub pilot_passes: u32,
    /// Pixels in the pilot.
    pub pilot_pixels: u64,
    /// Worker-seconds the pilot took.
    pub pilot_worker_seconds: f64,
    /// Measured worker-seconds per pixel-pass.
    pub worker_seconds_per_pixel_pass: f64,
    /// Relative standard error of the predicted seconds (from the error's and the cost's).
    pub relative_standard_error: f64,
    /// The job as planned: its error and cost.
    pub planned: Cost,
    /// One entry per target, in the order given.
    pub targets: Vec<TargetQuote>,
    /// What the prediction assumes, for people.
    pub assumes: String,
    /// The pilot's tail statistics, when measured.
    #[serde(default)]
    pub tails: Option<Tails>,
    /// Whether the figures are a prediction ([`TailClass::Light`]), one with intervals
    /// widened for a heavy tail, or not a prediction at all ([`TailClass::Unpredictable`]:
    /// "not predictable from the pilot", the figures a lower bound).
    #[serde(default)]
    pub tail_class: TailClass,
    /// Why, in words with the measured figures, unless [`TailClass::Light`].
    #[serde(default)]
    pub tail_note: Option<String>,
}

/// Why no quote can be made.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum QuoteError {
    /// The pilot is unusable (named problem).
    #[error("pilot: {0}")]
    Pilot(String),
    /// A field of the job or a target is out of range (field, problem).
    #[error("{0}: {1}")]
    Field(&'static str, String),
}

/// Which end of an interval a figure is for.
#[derive(Clone, Copy)]
enum End {
    Low,
    Estimate,
    High,
}

/// The spot checks' second copies among `U` units: each unit is chosen with probability
/// `f` by a hash of its identity (`crate::is_spot_checked`), so the count `K` is, for a job
/// not yet numbered, Binomial(`U`, `f`).
struct Copies {
    /// `E[K] = U f`.
    mean: f64,
    /// The 2.5% quantile of `K`.
    low: f64,
    /// The 97.5% quantile of `K`.
    high: f64,
    /// `E[ceil((U + K) / W)]`: the expected rounds of units `W` workers take.
    mean_rounds: f64,
}

impl Copies {
    /// Exact for `U f <= 30` (the pmf by its recurrence from `(1 - f)^U`); above that, the
    /// normal approximation with `ceil` adding `(W - 1) / (2 W)` rounds on average.
    fn of(units: f64, f: f64, workers: f64) -> Self {
        let rounds = |k: f64| ((units + k) / workers).ceil();
        if f <= 0.0 || f >= 1.0 {
            let k = if f >= 1.0 { units } else { 0.0 };
            return Self {
                mean: k,
                low: k,
                high: k,
                mean_rounds: rounds(k),
            };
        }
        let mean = units * f;
        let p0 = (units * (-f).ln_1p()).exp();
        if mean <= 30.0 && p0 > 0.0 {
            let (mut p, mut cdf, mut mean_rounds) = (p0, 0.0, 0.0);
            let (mut low, mut high) = (None, None);
            let mut k = 0.0;
            loop {
                cdf += p;
                mean_rounds += p * rounds(k);
                if low.is_none() && cdf >= 0.025 {
                    low = Some(k);
                }
                if high.is_none() && cdf >= 0.975 {
                    high = Some(k);
                }
                if k >= units || (high.is_some() && 1.0 - cdf < 1e-12) {
                    break;
                }
                p *= (units - k) / (k + 1.0) * f / (1.0 - f);
                k += 1.0;
            }
            // What the loop left of the tail (under 1e-12) counts at its last round.
            mean_rounds += (1.0 - cdf).max(0.0) * rounds(k);
            return Self {
                mean,
                low: low.unwrap_or(0.0),
                high: high.unwrap_or(k),
                mean_rounds,
            };
        }
        let sd = (mean * (1.0 - f)).sqrt();
        Self {
            mean,
            low: (mean - Z95 * sd).round().max(0.0),
            high: (mean + Z95 * sd).round().min(units),
            mean_rounds: (units + mean) / workers + (workers - 1.0) / (2.0 * workers),
        }
    }
}

/// A pixel-weighted mean over clusters and its standard error (a ratio estimator:
/// `sum y / sum x`, with the cluster-sampling variance `T/(T-1) sum (w (y/x - R))²`,
/// `w = x / sum x`). `None` for the error when fewer than 2 clusters.
fn ratio_mean(pairs: impl Iterator<Item = (f64, f64)> + Clone) -> (f64, Option<f64>) {
    let (sx, sy, t) = pairs
        .clone()
        .fold((0.0, 0.0, 0usize), |(sx, sy, t), (x, y)| {
            (sx + x, sy + y, t + 1)
        });
    let r = sy / sx;
    if t < 2 {
        return (r, None);
    }
    let ss: f64 = pairs.map(|(x, y)| ((y - r * x) / sx).powi(2)).sum();
    (r, Some((ss * t as f64 / (t - 1) as f64).sqrt()))
}

/// Predicts the planned job's error and cost, and what each target costs (see the module
/// documentation for the model and the interval).
pub fn quote(
    pilot: &PilotMeasurement,
    job: &QuoteJob,
    targets: &[f64],
) -> Result<Quote, QuoteError> {
    check_inputs(pilot, job, targets)?;
    let fit = Fit::of(pilot);
    let pricing = Pricing::new(&fit, job);
    let (mut tail_class, mut tail_note) = pilot
        .tails
        .map_or((TailClass::Light, None), |t| t.verdict());
    if let (TailClass::Heavy, Some(t)) = (tail_class, pilot.tails) {
        // A heavy tail and a pilot error that its groups barely agree on (module
        // documentation, "The interval"): the widened interval would rest on a spread
        // the tail makes unreliable.
        if fit.rel_m > REL_M_UNPREDICTABLE {
            tail_class = TailClass::Unpredictable;
            tail_note = Some(t.unpredictable_note(&format!(
                "the pass values are heavy-tailed and the pilot's groups of pixels disagree \
                 on its error (relative standard error {:.2} of the mean squared error, \
                 above {REL_M_UNPREDICTABLE}), so neither the error nor its spread can be \
                 extrapolated",
                fit.rel_m
            )));
        }
    }
    // A heavy tail's extrapolation: the per-pass error growing like passes^gamma.
    let gamma = match (tail_class, pilot.tails) {
        (TailClass::Heavy, Some(t)) => Some(t.gamma()),
        _ => None,
    };
    let planned_n = f64::from(job.planned_passes);
    let mut planned_error = Interval::lognormal(fit.error_after(planned_n), fit.rel_m / 2.0);
    if let Some(g) = gamma {
        let m_high = fit.m * (Z95 * fit.rel_m).exp();
        planned_error.high = planned_error
            .high
            .max((m_high * (planned_n / fit.p).powf(g - 1.0)).sqrt());
    }
    let planned = pricing.cost(
        Interval {
            estimate: planned_n,
            low: planned_n,
            high: planned_n,
        },
        planned_error,
    );
    let targets = targets
        .iter()
        .map(|&t| {
            let m_interval = Interval::lognormal(fit.m, fit.rel_m);
            // A render stopping at its target checks after rounds of `stop_interval`
            // passes: it stops at the first multiple past the passes needed.
            let step = f64::from(job.stop_interval.max(1));
            let whole = |n: f64| ((n.ceil().max(2.0)) / step).ceil() * step;
            let mut passes = m_interval.map(|m| whole(m * fit.p / (t * t)));
            if let Some(g) = gamma {
                // E(n)² = M (n / P)^(gamma - 1) = t²  =>  n = P (M / t²)^(1 / (1 - gamma));
                // gamma < 1 for a heavy (not unpredictable) tail.
                let n = fit.p * (m_interval.high / (t * t)).powf(1.0 / (1.0 - g));
                passes.high = passes.high.max(whole(n));
            }
            let error = Interval::lognormal(fit.error_after(passes.estimate), fit.rel_m / 2.0);
            TargetQuote {
                target: t,
                within_plan: passes.estimate <= planned_n,
                passes,
                cost: pricing.cost(passes, error),
            }
        })
        .collect();
    Ok(Quote {
        pilot_error: fit.m.sqrt(),
        pilot_passes: pilot.passes,
        pilot_pixels: pilot.groups.iter().map(|g| g.pixels).sum(),
        pilot_worker_seconds: pilot.units.iter().map(|u| u.worker_seconds).sum(),
        worker_seconds_per_pixel_pass: fit.c,
        relative_standard_error: fit.rel_m.hypot(fit.rel_c),
        planned,
        targets,
        assumes: "every pixel takes every pass (adaptive off; adaptive stopping is expected \
                  to need no more for the same image error); frames cost like the pilot's \
                  frame; the error falls like 1/sqrt(passes); workers as fast as the pilot's, \
                  sharing out units of equal cost, the spot-checked ones twice"
            .into(),
        tails: pilot.tails,
        tail_class,
        tail_note,
    })
}

/// Refuses a pilot that measured nothing usable, and job fields or targets out of range.
fn check_inputs(
    pilot: &PilotMeasurement,
    job: &QuoteJob,
    targets: &[f64],
) -> Result<(), QuoteError> {
    if pilot.passes < 2 {
        return Err(QuoteError::Pilot(format!(
            "{} passes give no error estimate; at least 2 are needed",
            pilot.passes
        )));
    }
    let pixels: u64 = pilot.groups.iter().map(|g| g.pixels).sum();
    let pixel_passes: u64 = pilot.units.iter().map(|u| u.pixel_passes).sum();
    if pixels == 0 || pixel_passes == 0 {
        return Err(QuoteError::Pilot("no pixel was rendered".into()));
    }
    let bad = |x: f64| !x.is_finite() || x < 0.0;
    if pilot.groups.iter().any(|g| bad(g.sum_sq_rel)) {
        return Err(QuoteError::Pilot(
            "an error sum is negative or not finite".into(),
        ));
    }
    if pilot.units.iter().any(|u| bad(u.worker_seconds)) {
        return Err(QuoteError::Pilot(
            "a unit's seconds are negative or not finite".into(),
        ));
    }
    if job.pixels_per_frame == 0 || job.frames == 0 || job.planned_passes == 0 {
        return Err(QuoteError::Field(
            "job",
            "no pixel, frame or pass to render".into(),
        ));
    }
    if job.workers == 0 {
        return Err(QuoteError::Field("workers", "must be at least 1".into()));
    }
    if job.tiles_per_frame == 0 || job.passes_per_unit == 0 {
        return Err(QuoteError::Field(
            "job",
            "tiles_per_frame and passes_per_unit must be at least 1".into(),
        ));
    }
    if !(0.0..=1.0).contains(&job.spot_check_fraction) {
        return Err(QuoteError::Field(
            "spot_check_fraction",
            format!("must be 0 to 1, got {}", job.spot_check_fraction),
        ));
    }
    if bad(job.setup_seconds) {
        return Err(QuoteError::Field(
            "setup_seconds",
            "must be finite and >= 0".into(),
        ));
    }
    if let Some(t) = targets.iter().find(|t| !(t.is_finite() && **t > 0.0)) {
        return Err(QuoteError::Field(
            "target_error",
            format!("must be > 0, got {t}"),
        ));
    }
    Ok(())
}

/// The model's two figures from a pilot, each with its relative standard error (see the
/// module documentation): `M`, the mean squared relative error of a pilot pixel after
/// the pilot's `P` passes, and `C`, the worker-seconds per pixel-pass.
struct Fit {
    m: f64,
    rel_m: f64,
    c: f64,
    rel_c: f64,
    /// `P`, the pilot's passes.
    p: f64,
}

impl Fit {
    fn of(pilot: &PilotMeasurement) -> Self {
        let (m, se_m) = ratio_mean(pilot.groups.iter().map(|g| (g.pixels as f64, g.sum_sq_rel)));
        let (c, se_c) = ratio_mean(
            pilot
                .units
                .iter()
                .map(|u| (u.pixel_passes as f64, u.worker_seconds)),
        );
        // Without a spread over groups, the per-pixel figure for K replicates (Owen 2001,
        // section 6.7): the error estimate's relative s.e. 1/sqrt(2 (K - 1)), that of M twice it.
        let rel_m = match se_m {
            Some(se) if m > 0.0 => se / m,
            _ => 2.0 / (2.0 * f64::from(pilot.passes - 1)).sqrt(),
        };
        let rel_c = match se_c {
            Some(se) if c > 0.0 => se / c,
            _ => 0.0,
        };
        Self {
            m,
            rel_m,
            c,
            rel_c,
            p: f64::from(pilot.passes),
        }
    }

    /// `E(n)`: the image error after `n` passes.
    fn error_after(&self, n: f64) -> f64 {
        (self.m * self.p / n).sqrt()
    }
}

/// What passes cost on the job's farm: the fit's cost per pixel-pass and the job's
/// figures, as the model uses them.
struct Pricing {
    c: f64,
    rel_c: f64,
    frame_px: f64,
    frames: f64,
    workers: f64,
    units_per_pass: f64,
    ppu: f64,
    fraction: f64,
    samples_per_pass: f64,
    setup_seconds: f64,
}

impl Pricing {
    fn new(fit: &Fit, job: &QuoteJob) -> Self {
        Self {
            c: fit.c,
            rel_c: fit.rel_c,
            frame_px: job.pixels_per_frame as f64,
            frames: job.frames as f64,
            workers: f64::from(job.workers),
            units_per_pass: f64::from(job.tiles_per_frame),
            ppu: f64::from(job.passes_per_unit),
            fraction: job.spot_check_fraction,
            samples_per_pass: f64::from(job.samples_per_pass),
            setup_seconds: job.setup_seconds,
        }
    }

    /// The farm's work for `n` passes of `frames` frames: worker-seconds with the spot
    /// checks' copies, and wall seconds, the rounds of equal units the workers take
    /// (`ceil((U + K) / W)` for `U` units and `K` copies: a few large units, as a
    /// whole-frame bdpt tile makes, do not share out evenly). `ws` is the worker-seconds
    /// of the `U` units alone, `end` which end of the interval (copies at its quantile).
    fn farm(&self, n: f64, ws: f64, frames: f64, end: End) -> (f64, f64) {
        let workers = self.workers;
        let units = frames * self.units_per_pass * (n / self.ppu).ceil();
        let per_unit = ws / units;
        let k = Copies::of(units, self.fraction, workers);
        let (copies, rounds) = match end {
            End::Low => (k.low, ((units + k.low) / workers).ceil()),
            End::Estimate => (k.mean, k.mean_rounds),
            End::High => (k.high, ((units + k.high) / workers).ceil()),
        };
        (ws + copies * per_unit, rounds * per_unit)
    }

    /// Worker-seconds and wall seconds of `frames` frames, each end of `passes` at the
    /// same end of the per-frame worker-seconds `per_frame`.
    fn on_farm(&self, passes: Interval, per_frame: Interval, frames: f64) -> (Interval, Interval) {
        let at = |n: f64, ws: f64, end| self.farm(n, ws * frames, frames, end);
        let (lo, est, hi) = (
            at(passes.low, per_frame.low, End::Low),
            at(passes.estimate, per_frame.estimate, End::Estimate),
            at(passes.high, per_frame.high, End::High),
        );
        let pick = |f: fn((f64, f64)) -> f64| Interval {
            estimate: f(est),
            low: f(lo),
            high: f(hi),
        };
        (pick(|x| x.0), pick(|x| x.1))
    }

    /// The cost of `passes` (an interval of whole passes), the cost's own spread added.
    fn cost(&self, passes: Interval, error: Interval) -> Cost {
        let per_frame = Interval::lognormal(passes.estimate * self.c * self.frame_px, self.rel_c);
        let per_frame = Interval {
            low: per_frame.low * passes.low / passes.estimate,
            high: per_frame.high * passes.high / passes.estimate,
            ..per_frame
        };
        let (ws_frame, wall_frame) = self.on_farm(passes, per_frame, 1.0);
        let (ws_whole, wall_whole) = self.on_farm(passes, per_frame, self.frames);
        Cost {
            passes,
            spp: passes.map(|n| n * self.samples_per_pass),
            error,
            worker_seconds_per_frame: ws_frame,
            worker_seconds: ws_whole,
            seconds_per_frame: wall_frame,
            seconds: wall_whole.map(|s| self.setup_seconds + s),
        }
    }
}

/// The tiles a pilot renders: about [`PILOT_PIXELS`] pixels of whole tiles, at least
/// [`PILOT_MIN_TILES`] (or every tile), in increasing index order. Deterministic.
///
/// Tile `i` of the pilot is `i · g mod T` for `g` the integer nearest `0.618 T` coprime with
/// `T` (a rank-1 lattice, the golden-ratio rule): the tiles are distinct and spread over
/// both rows and columns of the frame, where evenly spaced indices (`i · T / n`) would
/// fall in the same column whenever `n` divides the tiles per row.
pub fn pilot_tiles(tile_count: u32, pixels_per_tile: u64) -> Vec<u32> {
    if tile_count == 0 {
        return Vec::new();
    }
    let t = u64::from(tile_count);
    let by_pixels = (PILOT_PIXELS / pixels_per_tile.max(1)).max(1);
    let n = by_pixels.max(u64::from(PILOT_MIN_TILES)).min(t);
    let gcd = |mut a: u64, mut b: u64| {
        while b != 0 {
            (a, b) = (b, a % b);
        }
        a
    };
    let mut g = ((t as f64 * 0.618_033_988_7).round() as u64).max(1);
    while gcd(g, t) != 1 {
        g += 1;
    }
    let mut tiles: Vec<u32> = (0..n).map(|i| (i * g % t) as u32).collect();
    tiles.sort_unstable();
    tiles
}

#[cfg(test)]
mod tests;
