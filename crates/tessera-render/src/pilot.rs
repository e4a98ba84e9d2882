//! The technique pilot: the cheapest of path tracing, bdpt and Metropolis light transport
//! for the same error, measured (ARCHITECTURE.md §4).
//!
//! The scene analysis picks bdpt for caustics lit by delta or tiny lights. With a delta
//! light (point, spot, directional) path tracing cannot find such a caustic at all, so
//! bdpt is the only correct choice. With a tiny *finite* light it can, when a
//! BSDF-sampled ray happens to hit the light, and which of the two then reaches an error
//! sooner depends on the scene: a small caustic in a large diffusely lit room is cheaper
//! to path trace, a caustic that fills the view is not (Veach & Guibas 1995, section 4.3,
//! compare the two at equal time). For those scenes the analysis leaves the choice to
//! this pilot ([`tessera_farm::job::RenderPlan::technique_pilot`]).
//!
//! # The measurement
//!
//! The techniques render the same small frame ([`PILOT_LONG_SIDE`] pixels on the long
//! side, the job's aspect ratio and camera) with [`PILOT_PASSES`] passes of
//! [`PILOT_SAMPLES_PER_PASS`] samples (mlt: as many mutations per pixel), the plan's depths
//! and the job's MIS and sampler, from a fixed seed. mlt samples every path bdpt does
//! (its chains run over bdpt's techniques), so where bdpt is correct it is too. Each is scored by its efficiency (Veach & Guibas 1995, section 2:
//! `1 / (variance x cost)`): its pilot image's mean squared relative error times its cost.
//!
//! Both techniques estimate the same image, and the pilot uses that twice. A pixel's
//! error is relative to its mean *in both pilots*: a path-traced caustic pixel where one
//! pass found the light has a relative error no larger than its neighbours' by its own
//! mean, while against the caustic's true brightness (which bdpt's pilot finds) it is the
//! firefly the eye sees. And path tracing's error is never taken below what the
//! difference of the two images shows (`on_one_scale`): where its passes missed a caustic
//! altogether its own variance shows nothing, the difference does.
//!
//! The cost is not wall time, which would make the choice, and so the image, depend on the
//! machine's load: it is the number of rays traced (closest hits and shadow rays,
//! [`crate::scene::rays_traced`]), bdpt's weighted by [`BDPT_RAY_COST`], its measured time
//! per ray relative to path tracing's (its rays also pay for MIS weights over every
//! connection and for splatting), mlt's by [`MLT_RAY_COST`]. Every input is
//! deterministic, so the choice is a pure function of the scene and the job: `tessera
//! render`, the coordinator at submission and at every restart all choose alike, and a farm
//! render stays byte-identical to a local one.
//!
//! # Path tracing against mnee
//!
//! Where the caustics are lit by small (not tiny) area lights through specular chains
//! within manifold next-event estimation's reach, the analysis chooses path tracing and
//! asks this pilot whether mnee (path tracing with MNEE, [`crate::integrator::mnee`]) is
//! the more efficient ([`tessera_farm::job::TechniquePilot::mnee`]). Both are unbiased,
//! so only efficiency is in question: [`run_mnee`] renders the two pilots, puts them on
//! one scale with mnee in bdpt's place (path tracing's error not taken below what the
//! difference of the images shows; errors relative to the image's mean luminance, the
//! image's mean squared error), costs mnee's rays at [`MNEE_RAY_COST`], and chooses
//! mnee when it is more than [`MNEE_MARGIN`] times as efficient ([`MneeVerdict`]).
//!
//! # Light through an opening
//!
//! The analysis also asks where the lights reach little of what the camera sees (Veach's
//! door ajar; `tessera_scene::analysis`, "Light through an opening"). There the image is a
//! few bright pixels (on the door-ajar room 1.6% of the pixels carry 57% of the light: the
//! floor and door lit through the gap) over a room lit only by rare paths, and at the
//! pilot's 32 samples per pixel most dark pixels are found by one pass of eight or by none,
//! in every technique: their relative errors measure the rarity of a hit, not the
//! technique (a pixel one bdpt pass found and no path-tracing pass did has a relative
//! variance of 4 against the pooled mean, whichever technique is better). Per-pixel
//! relative errors there ranked path tracing 5.0x bdpt's efficiency where the measured
//! efficiency `1 / (MSE x s)` is 0.71-0.78x (docs/benchmarks.md, "Metropolis light
//! transport"). So for such scenes each pixel's error is taken relative to the image's mean
//! luminance instead of its own ([`TechniqueVerdict::image_mean_error`]): the pilot scores
//! the image's mean squared error, the efficiency the benchmark measures, and ranks path
//! tracing at 1.09x bdpt and mlt at 0.51x (measured 0.71-0.78x and 0.62-0.76x). The
//! margin and spread rules are unchanged.
//!
//! # What it cannot see
//!
//! A pilot's error estimate is optimistic where paths are rare (the calibration suite's
//! finding:
//! caustic pixels whose passes never found the light show no error at all; Jensen 2001,
//! section 10.3, on what a pilot can miss). That bias favours path tracing, whose
//! caustics are the rare paths, so path tracing must win by [`PATH_MARGIN`], with its
//! error spread over the image rather than carried by a few pixels ([`MIN_PATH_SPREAD`]),
//! to be chosen. mlt's chains can miss light in every pass as path tracing's passes can,
//! so mlt is held to the same rules against the better of the other two, and its error is
//! not taken below what the difference of its image to bdpt's shows. Every choice is
//! unbiased: a wrong one costs time, never correctness.

use crate::integrator::{render_unit, RenderConfig};
use crate::scene::{rays_traced, RenderScene};
use rayon::prelude::*;
use tessera_farm::job::{Integrator, PilotVerdict, PlannedIntegrator, RenderPlan, ValidatedJob};
use tessera_farm::{FrameAccumulator, FramePlan};
use tessera_scene::job::PilotQuestion;
use tessera_scene::Scene;

/// Pixels on the long side of the pilot frame.
pub const PILOT_LONG_SIDE: u32 = 64;
/// Passes of each technique: 8 replicates give each pixel a variance estimate with 7
/// degrees of freedom.
pub const PILOT_PASSES: u32 = 8;
/// Samples per pass.
pub const PILOT_SAMPLES_PER_PASS: u32 = 4;
/// The pilot's seed: fixed, so the choice does not depend on the job's seed.
pub const PILOT_SEED: u64 = 0x0070_696c_6f74;
/// Time per ray of bdpt relative to path tracing, measured with `tessera bench-plan`
/// (docs/benchmarks.md, "Technique pilot"): the cost of a bdpt ray in path-tracing rays.
pub const BDPT_RAY_COST: f64 = 1.45;
/// Time per ray of mlt relative to path tracing: on the door-ajar room mlt's ray took 1.19x
/// bdpt's (CPU seconds per ray, docs/benchmarks.md, "Metropolis light transport"), times
/// [`BDPT_RAY_COST`]. A mutation evaluates one bidirectional technique with its MIS weight
/// over all of them, and the bootstrap evaluates all of them.
pub const MLT_RAY_COST: f64 = 1.7;
/// Path tracing is chosen only when its measured efficiency is at least this many times
/// bdpt's, since the pilot's error estimate flatters it (module documentation).
pub const PATH_MARGIN: f64 = 1.5;
/// ... and only when its error is spread over at least this fraction of the pixels
/// ([`TechniqueMeasurement::spread`]): an error carried by a few pixels is the heavy tail
/// of rare paths, whose true variance a pilot of a few dozen samples per pixel cannot
/// measure. On `builtin:caustic` path tracing's pilot spreads its error over 0.7-9.4% of
/// the pixels and claims 1.5-2.9x bdpt's efficiency; the variance over 24 seeds says
/// 0.17x (docs/benchmarks.md, "Technique pilot").
pub const MIN_PATH_SPREAD: f64 = 0.1;
/// Time per ray of mnee relative to path tracing on bench/compare's glass ball (256 x 256,
/// 64 spp, 2 threads, whole-process CPU medians of 5 interleaved runs): 1.116x the CPU
/// seconds for 1.034x the rays (11,008,686 against 10,644,553), the Newton solver forming
/// and solving the constraint Jacobian beside its projection rays; 1.24x for 1.10x before
/// the steep seeds were skipped (docs/benchmarks.md, "Hopeless MNEE seeds skipped").
pub const MNEE_RAY_COST: f64 = 1.08;
/// Mnee is chosen over path tracing only when its measured efficiency is more than this
/// many times path tracing's (a tie goes to the simpler technique). No more margin is
/// needed: path tracing's pilot, whose caustic is the rare paths, is the one flattered.
pub const MNEE_MARGIN: f64 = 1.0;

/// One technique's pilot.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TechniqueMeasurement {
    /// The pilot image's RMS relative error, each pixel's against the mean of both
    /// pilots, or against the image's mean luminance where the scene is lit through an
    /// opening (module documentation).
    pub error: f64,
    /// Rays traced.
    pub rays: u64,
    /// Cost in path-tracing ray equivalents (`rays`, bdpt's times [`BDPT_RAY_COST`]).
    pub cost: f64,
    /// How evenly the pixels carry the error: Kish's effective number of pixels,
    /// `(sum v)² / sum v²` over the pixels' relative variances `v`, as a fraction of the
    /// pixels (1: every pixel alike; small: a handful carry it, the heavy tail of rare
    /// paths whose true size a pilot cannot measure).
    pub spread: f64,
}

impl TechniqueMeasurement {
    /// `1 / (error² x cost)`: higher is better; per million ray equivalents, so the
    /// numbers reported stay readable.
    pub fn efficiency(&self) -> f64 {
        1e6 / (self.error * self.error * self.cost)
    }
}

/// What the pilot measured and chose.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TechniqueVerdict {
    /// Path tracing's pilot.
    pub path: TechniqueMeasurement,
    /// Bdpt's pilot.
    pub bdpt: TechniqueMeasurement,
    /// Metropolis light transport's pilot (multiplexed over bdpt's techniques, so it
    /// samples every path bdpt does).
    pub mlt: TechniqueMeasurement,
    /// Pilot frame size.
    pub size: (u32, u32),
    /// Each pixel's error was taken relative to the image's mean luminance, not its own
    /// (the scene is lit through an opening; module documentation).
    pub image_mean_error: bool,
}

impl TechniqueVerdict {
    /// Whether path tracing beats bdpt: its efficiency is at least [`PATH_MARGIN`] times
    /// bdpt's and its error is spread over at least [`MIN_PATH_SPREAD`] of the pixels. A
    /// technique whose pilot shows no error (a black pilot) counts as free of error, so
    /// path tracing, the simpler, wins a tie of zeros.
    fn path_beats_bdpt(&self) -> bool {
        beats(&self.path, &self.bdpt, false)
    }

    /// The technique chosen: the better of path tracing and bdpt as above, unless mlt beats
    /// that one by the same rules ([`PATH_MARGIN`] and [`MIN_PATH_SPREAD`]: its pilot, whose
    /// chains may miss light in every pass, flatters it as path tracing's does), strictly,
    /// so that a tie goes to the simpler technique.
    pub fn choice(&self) -> PlannedIntegrator {
        let (base, base_m) = if self.path_beats_bdpt() {
            (PlannedIntegrator::Path, &self.path)
        } else {
            (PlannedIntegrator::Bdpt, &self.bdpt)
        };
        if beats(&self.mlt, base_m, true) {
            PlannedIntegrator::Mlt
        } else {
            base
        }
    }

    /// Whether path tracing is chosen ([`TechniqueVerdict::choice`]).
    pub fn path_wins(&self) -> bool {
        self.choice() == PlannedIntegrator::Path
    }

    /// The reason the plan records, with the measured efficiencies.
    pub fn reason(&self) -> String {
        let (p, b, m) = (&self.path, &self.bdpt, &self.mlt);
        let ratio = |x: &TechniqueMeasurement| {
            if x.efficiency().is_finite() && b.efficiency() > 0.0 {
                format!("{:.2}x", x.efficiency() / b.efficiency())
            } else {
                "n/a".into()
            }
        };
        let scale = if self.image_mean_error {
            "; errors relative to the image's mean luminance, the scene being lit through an \
             opening"
        } else {
            ""
        };
        format!(
            "technique pilot ({}x{}, {PILOT_PASSES} passes of {PILOT_SAMPLES_PER_PASS} \
             samples each{scale}): path error {:.4} for {} rays (spread {:.3}), bdpt error {:.4} for \
             {} rays (x{BDPT_RAY_COST} per ray, spread {:.3}), mlt error {:.4} for {} rays \
             (x{MLT_RAY_COST} per ray, spread {:.3}); efficiency 1/(error^2 x cost) path {:.4}, \
             bdpt {:.4}, mlt {:.4} (path/bdpt {}, mlt/bdpt {}; path or mlt needs \
             {PATH_MARGIN}x and a spread of {MIN_PATH_SPREAD}): {} chosen",
            self.size.0,
            self.size.1,
            p.error,
            p.rays,
            p.spread,
            b.error,
            b.rays,
            b.spread,
            m.error,
            m.rays,
            m.spread,
            p.efficiency(),
            b.efficiency(),
            m.efficiency(),
            ratio(p),
            ratio(m),
            self.choice()
        )
    }
}

/// Whether `a` beats `b` by the pilot's rules: `a`'s efficiency at least [`PATH_MARGIN`]
/// times `b`'s (more than, if `strict`) and its error spread over at least
/// [`MIN_PATH_SPREAD`] of the pixels. Compares error² x cost without dividing, so zero
/// errors compare too.
fn beats(a: &TechniqueMeasurement, b: &TechniqueMeasurement, strict: bool) -> bool {
    let (lhs, rhs) = (
        a.error * a.error * a.cost * PATH_MARGIN,
        b.error * b.error * b.cost,
    );
    (if strict { lhs < rhs } else { lhs <= rhs }) && a.spread >= MIN_PATH_SPREAD
}

/// The pilot frame for a `width x height` job: [`PILOT_LONG_SIDE`] on the long side, the
/// same aspect ratio, at least 1 pixel each way.
pub fn pilot_size(width: u32, height: u32) -> (u32, u32) {
    let long = width.max(height).max(1);
    let scale = |v: u32| {
        ((u64::from(v) * u64::from(PILOT_LONG_SIDE) + u64::from(long) / 2) / u64::from(long))
            .clamp(1, u64::from(PILOT_LONG_SIDE)) as u32
    };
    if long <= PILOT_LONG_SIDE {
        (width.max(1), height.max(1))
    } else {
        (scale(width), scale(height))
    }
}

/// One technique's pilot before the two are put on one scale: per pixel the mean and
/// the variance of the mean (luminance weights over the channels), and the rays traced.
#[derive(Clone)]
struct Raw {
    mean: Vec<f64>,
    variance: Vec<f64>,
    rays: u64,
}

/// Below this fraction of the image's mean luminance a pixel's scale is floored, so dark
/// pixels do not turn tiny absolute noise into large relative errors.
const DARK_FLOOR: f64 = 0.1;

/// Renders the pilot of one technique on `scene` (built at the pilot size).
fn measure(scene: &RenderScene, config: &RenderConfig, plan: &FramePlan) -> Raw {
    let units = plan.units(0, 1);
    // Each unit is rendered on one thread, so the thread's ray counter brackets it.
    let results: Vec<_> = units
        .into_par_iter()
        .map(|unit| {
            let before = rays_traced();
            let result = render_unit(scene, config, plan, unit);
            (result, rays_traced() - before)
        })
        .collect();
    let mut acc = FrameAccumulator::for_frame(*plan, 0);
    let mut rays = 0u64;
    for (result, r) in results {
        rays += r;
        // Our own results always fit the plan.
        acc.offer(result).expect("pilot unit fits its plan");
    }
    let image = acc.image();
    let lum = |c: &[f32; 3]| tessera_farm::luminance(c.map(f64::from));
    Raw {
        mean: image.mean.iter().map(lum).collect(),
        variance: image.variance_of_mean.iter().map(lum).collect(),
        rays,
    }
}

/// Both pilots on one scale: per pixel, squared errors over the square of the pixel's
/// mean in both pilots (both estimate the same image; bdpt's finds the caustic path
/// tracing's may have missed), floored at [`DARK_FLOOR`] of the image's mean, averaged
/// over the image. Relative, so a directly seen emitter's edge weighs no more than any
/// pixel. With `image_mean_error`, over the square of the image's mean instead, for every
/// pixel (a scene lit through an opening; module documentation).
///
/// Path tracing's mean squared error is the larger of its own variance estimate `S_path`
/// and what the difference of the two images says: `E[(m_path - m_bdpt)²] = V_path +
/// V_bdpt` for two independent unbiased estimates, so `D - S_bdpt` estimates `V_path`
/// without trusting `S_path`. Where path tracing's passes never found a caustic its
/// `S_path` shows nothing, but its image lacks the caustic bdpt's has, and `D` sees that.
/// Not the other way round: bdpt, built for these paths, is the one whose estimate is
/// trusted here, and `D - S_path` would charge path tracing's missed caustic to bdpt.
fn on_one_scale(
    path: Raw,
    bdpt: Raw,
    mlt: Raw,
    image_mean_error: bool,
) -> (
    TechniqueMeasurement,
    TechniqueMeasurement,
    TechniqueMeasurement,
) {
    let n = path.mean.len().min(bdpt.mean.len()).min(mlt.mean.len());
    let pooled: Vec<f64> = (0..n)
        .map(|i| 0.5 * (path.mean[i] + bdpt.mean[i]))
        .collect();
    let image_mean = pooled.iter().sum::<f64>() / n.max(1) as f64;
    let floor = DARK_FLOOR * image_mean;
    let (mut s_path, mut s_bdpt, mut s_mlt, mut d, mut d_mlt) = (0.0, 0.0, 0.0, 0.0, 0.0);
    let (mut q_path, mut q_bdpt, mut q_mlt) = (0.0, 0.0, 0.0);
    for (i, &mean) in pooled.iter().enumerate() {
        let scale = if image_mean_error {
            image_mean
        } else {
            mean.max(floor)
        };
        if scale > 0.0 {
            let s2 = scale * scale;
            let (vp, vb, vm) = (
                path.variance[i].max(0.0) / s2,
                bdpt.variance[i].max(0.0) / s2,
                mlt.variance[i].max(0.0) / s2,
            );
            (s_path, s_bdpt, s_mlt) = (s_path + vp, s_bdpt + vb, s_mlt + vm);
            (q_path, q_bdpt, q_mlt) = (q_path + vp * vp, q_bdpt + vb * vb, q_mlt + vm * vm);
            let diff = path.mean[i] - bdpt.mean[i];
            d += diff * diff / s2;
            let diff = mlt.mean[i] - bdpt.mean[i];
            d_mlt += diff * diff / s2;
        }
    }
    let spread = |s: f64, q: f64| {
        if q > 0.0 {
            s * s / q / n.max(1) as f64
        } else {
            1.0
        }
    };
    let of = |r: &Raw, own: f64, q: f64, floor: f64, ray_cost: f64| TechniqueMeasurement {
        error: (own.max(floor) / n.max(1) as f64).sqrt(),
        rays: r.rays,
        cost: r.rays as f64 * ray_cost,
        spread: spread(own, q),
    };
    // mlt's chains, like path tracing's passes, can miss light in every pass: its error is
    // not taken below what the difference to bdpt's image shows either.
    (
        of(&path, s_path, q_path, d - s_bdpt, 1.0),
        of(&bdpt, s_bdpt, q_bdpt, 0.0, BDPT_RAY_COST),
        of(&mlt, s_mlt, q_mlt, d_mlt - s_bdpt, MLT_RAY_COST),
    )
}

/// Measures path tracing and bdpt on `scene` for a job of `width x height` with the
/// plan's depths and the job's MIS and sampler.
pub fn run(
    scene: &Scene,
    job: &ValidatedJob,
    plan: &RenderPlan,
    (width, height): (u32, u32),
) -> Result<TechniqueVerdict, String> {
    let (size, rs, frame) = pilot_frame(scene, (width, height))?;
    let config = |integrator| pilot_config(job, plan, integrator);
    let image_mean_error = plan
        .technique_pilot
        .as_ref()
        .is_some_and(|t| t.lit_through_opening);
    let (path, bdpt, mlt) = on_one_scale(
        measure(&rs, &config(Integrator::Path), &frame),
        measure(&rs, &config(Integrator::Bdpt), &frame),
        measure(&rs, &config(Integrator::Mlt), &frame),
        image_mean_error,
    );
    Ok(TechniqueVerdict {
        path,
        bdpt,
        mlt,
        size,
        image_mean_error,
    })
}

/// The pilot's frame for a job of `width x height`: its size, the scene built at it and
/// one whole-frame tile of [`PILOT_PASSES`] passes of [`PILOT_SAMPLES_PER_PASS`].
fn pilot_frame(
    scene: &Scene,
    (width, height): (u32, u32),
) -> Result<((u32, u32), RenderScene, FramePlan), String> {
    let size = pilot_size(width, height);
    let rs = RenderScene::build(scene, size.0, size.1).map_err(|e| e.to_string())?;
    let frame = FramePlan::new(
        size.0,
        size.1,
        size.0.max(size.1),
        PILOT_SAMPLES_PER_PASS,
        PILOT_PASSES,
    )
    .map_err(|e| e.to_string())?;
    Ok((size, rs, frame))
}

/// A technique's pilot settings: the plan's depths, the job's MIS and sampler, the
/// pilot's seed.
fn pilot_config(job: &ValidatedJob, plan: &RenderPlan, integrator: Integrator) -> RenderConfig {
    RenderConfig {
        integrator,
        mis: job.render.mis,
        sampler: job.render.sampler,
        seed: PILOT_SEED,
        max_depth: job.render.max_depth.unwrap_or(plan.max_depth),
        rr_depth: plan.rr_depth,
    }
}

/// What the pilot measured where the question is path tracing against mnee
/// ([`tessera_farm::job::TechniquePilot::mnee`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MneeVerdict {
    /// Path tracing's pilot, its error not taken below what the difference to mnee's image
    /// shows.
    pub path: TechniqueMeasurement,
    /// Mnee's pilot, its cost its rays times [`MNEE_RAY_COST`].
    pub mnee: TechniqueMeasurement,
    /// Pilot frame size.
    pub size: (u32, u32),
}

impl MneeVerdict {
    /// Whether mnee is chosen: its efficiency more than [`MNEE_MARGIN`] times path
    /// tracing's (error² x cost compared without dividing, so zero errors compare too).
    pub fn mnee_wins(&self) -> bool {
        let (m, p) = (&self.mnee, &self.path);
        m.error * m.error * m.cost * MNEE_MARGIN < p.error * p.error * p.cost
    }

    /// The reason the plan records, with the measured efficiencies.
    pub fn reason(&self) -> String {
        let (p, m) = (&self.path, &self.mnee);
        let ratio = if p.efficiency() > 0.0 && m.efficiency().is_finite() {
            format!("{:.2}x", m.efficiency() / p.efficiency())
        } else {
            "n/a".into()
        };
        format!(
            "technique pilot ({}x{}, {PILOT_PASSES} passes of {PILOT_SAMPLES_PER_PASS} samples \
             each): path error {:.4} for {} rays, mnee error {:.4} for {} rays \
             (x{MNEE_RAY_COST} per ray); efficiency 1/(error^2 x cost) path {:.4}, mnee {:.4} \
             (mnee/path {ratio}; mnee needs more than {MNEE_MARGIN}x): {} chosen",
            self.size.0,
            self.size.1,
            p.error,
            p.rays,
            m.error,
            m.rays,
            p.efficiency(),
            m.efficiency(),
            if self.mnee_wins() { "mnee" } else { "path" }
        )
    }
}

/// Measures path tracing and mnee on `scene` for a job of `width x height`, as [`run`]
/// does path tracing and bdpt. Mnee stands where bdpt does in [`on_one_scale`]: the
/// technique built for the caustics, whose own variance is trusted, while path tracing's
/// error is not taken below what the difference of the two images shows (its passes may
/// have missed a caustic mnee's found). Errors are relative to the image's mean
/// luminance, so each technique is scored by its image's mean squared error, the
/// efficiency `1 / (MSE x cost)` bench/compare measures: per pixel, relative to each
/// pixel's own mean, the caustic (where the two differ) weighs no more than any dark
/// pixel, and on bench/compare's glass ball the pilot ranked mnee at 0.76x path tracing
/// where its measured efficiency is above path tracing's (docs/benchmarks.md, "MNEE
/// retuned and chosen by the pilot").
pub fn run_mnee(
    scene: &Scene,
    job: &ValidatedJob,
    plan: &RenderPlan,
    (width, height): (u32, u32),
) -> Result<MneeVerdict, String> {
    let (size, rs, frame) = pilot_frame(scene, (width, height))?;
    let path = measure(&rs, &pilot_config(job, plan, Integrator::Path), &frame);
    let mnee = measure(&rs, &pilot_config(job, plan, Integrator::Mnee), &frame);
    let (path, mut mnee, _) = on_one_scale(path, mnee.clone(), mnee, true);
    mnee.cost = mnee.rays as f64 * MNEE_RAY_COST;
    Ok(MneeVerdict { path, mnee, size })
}

/// The technique pilot's verdict for `question` ([`tessera_scene::job::resolve_job`]
/// calls it where the plan leaves the choice to a measurement): [`run`] at the job's
/// resolution with the analysis's depths. Fails only when the pilot's scene or frame plan
/// cannot be built; the job is then refused (the resolve path's one failure policy).
pub fn verdict(question: &PilotQuestion<'_>) -> Result<PilotVerdict, String> {
    if question
        .plan
        .technique_pilot
        .as_ref()
        .is_some_and(|t| t.mnee)
    {
        let v = run_mnee(
            question.scene,
            question.job,
            question.plan,
            question.resolution(),
        )?;
        return Ok(PilotVerdict {
            path_wins: !v.mnee_wins(),
            mlt_wins: false,
            mnee_wins: v.mnee_wins(),
            reason: v.reason(),
        });
    }
    let v = run(
        question.scene,
        question.job,
        question.plan,
        question.resolution(),
    )?;
    let choice = v.choice();
    Ok(PilotVerdict {
        path_wins: choice == PlannedIntegrator::Path,
        mlt_wins: choice == PlannedIntegrator::Mlt,
        mnee_wins: false,
        reason: v.reason(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn raw(mean: &[f64], variance: &[f64], rays: u64) -> Raw {
        Raw {
            mean: mean.to_vec(),
            variance: variance.to_vec(),
            rays,
        }
    }

    /// Path tracing's passes missed a caustic bdpt found: its own variance shows nothing
    /// there, the difference of the images does, and its error is not taken below it.
    #[test]
    fn a_missed_caustic_counts_against_path_tracing() {
        let path = raw(&[1.0, 1.0, 0.0, 1.0], &[0.01, 0.01, 0.0, 0.01], 100);
        let bdpt = raw(&[1.0, 1.0, 4.0, 1.0], &[0.01, 0.01, 0.04, 0.01], 100);
        let mlt = raw(&[1.0, 1.0, 4.0, 1.0], &[0.01, 0.01, 0.04, 0.01], 100);
        let (p, b, m) = on_one_scale(path, bdpt, mlt, false);
        // mlt's image is bdpt's: its own variance is its error; its rays cost mlt's.
        assert_eq!(m.error, b.error);
        assert_eq!(m.cost, 100.0 * MLT_RAY_COST);
        // Pooled means 1, 1, 2, 1: the difference 4² / 2² = 4 dominates path's 0.03.
        let d = 4.0;
        let s_b = 0.01 * 3.0 + 0.04 / 4.0;
        assert!(
            (p.error - ((d - s_b) / 4.0f64).sqrt()).abs() < 1e-12,
            "{p:?}"
        );
        assert!(p.error > b.error, "{p:?} {b:?}");
        assert_eq!(b.cost, 100.0 * BDPT_RAY_COST);
        let v = TechniqueVerdict {
            path: p,
            bdpt: b,
            mlt: m,
            size: (2, 2),
            image_mean_error: false,
        };
        assert!(!v.path_wins(), "{}", v.reason());
        // A tie with bdpt goes to bdpt.
        assert_eq!(v.choice(), PlannedIntegrator::Bdpt, "{}", v.reason());
    }

    /// A bright pixel over dark ones: per pixel, path tracing's quiet dark pixels make it
    /// the better; against the image's mean (a scene lit through an opening), bdpt's quiet
    /// bright pixel does, and each error is the image's mean squared error over its mean².
    #[test]
    fn lit_through_an_opening_errors_are_against_the_image_mean() {
        let means = [3.0, 0.1, 0.1, 0.0];
        let path = || raw(&means, &[0.09, 0.0001, 0.0001, 0.0], 100);
        let bdpt = || raw(&means, &[0.0009, 0.0009, 0.0009, 0.0], 100);
        let mlt = || raw(&means, &[0.0009, 0.0009, 0.0009, 0.0], 100);
        let (p, b, _) = on_one_scale(path(), bdpt(), mlt(), false);
        assert!(p.error < b.error, "{p:?} {b:?}");
        let (p, b, _) = on_one_scale(path(), bdpt(), mlt(), true);
        assert!(p.error > b.error, "{p:?} {b:?}");
        // Image mean 0.8: path's squared errors 0.0902 over 0.64, over 4 pixels.
        assert!(
            (p.error - (0.0902f64 / 0.64 / 4.0).sqrt()).abs() < 1e-12,
            "{p:?}"
        );
        assert!(
            (b.error - (0.0027f64 / 0.64 / 4.0).sqrt()).abs() < 1e-12,
            "{b:?}"
        );
    }

    /// Path tracing cheaper and its error spread evenly: chosen. The same figures with the
    /// error carried by one pixel in sixteen: not.
    #[test]
    fn path_tracing_needs_the_margin_and_the_spread() {
        let even = TechniqueMeasurement {
            error: 0.1,
            rays: 100,
            cost: 100.0,
            spread: 0.9,
        };
        let bdpt = TechniqueMeasurement {
            error: 0.1,
            rays: 100,
            cost: 100.0 * PATH_MARGIN * 1.01,
            spread: 0.9,
        };
        let v = |path| TechniqueVerdict {
            path,
            bdpt,
            mlt: TechniqueMeasurement { error: 1.0, ..bdpt },
            size: (4, 4),
            image_mean_error: false,
        };
        assert!(v(even).path_wins());
        assert!(!v(TechniqueMeasurement {
            spread: 1.0 / 16.0,
            ..even
        })
        .path_wins());
        assert!(!v(TechniqueMeasurement {
            cost: 102.0,
            ..even
        })
        .path_wins());
    }

    /// mlt is chosen when it beats the better of path tracing and bdpt by the margin with
    /// its error spread; not on a tie, and not with its error in a few pixels.
    #[test]
    fn mlt_needs_the_margin_and_the_spread_over_the_better_of_the_others() {
        let m = |error: f64, cost: f64, spread: f64| TechniqueMeasurement {
            error,
            rays: cost as u64,
            cost,
            spread,
        };
        let v = |path, bdpt, mlt| TechniqueVerdict {
            path,
            bdpt,
            mlt,
            size: (4, 4),
            image_mean_error: false,
        };
        let (path, bdpt) = (m(0.2, 100.0, 0.9), m(0.1, 200.0, 0.9));
        // bdpt is the better of the two (2x path); mlt at 1.6x bdpt wins.
        let mlt = m(0.1, 200.0 / 1.6, 0.9);
        assert_eq!(v(path, bdpt, mlt).choice(), PlannedIntegrator::Mlt);
        assert!(v(path, bdpt, mlt).reason().ends_with("mlt chosen"));
        // Exactly the margin: a tie goes to the simpler technique.
        let tie = m(0.1, 200.0 / PATH_MARGIN, 0.9);
        assert_eq!(v(path, bdpt, tie).choice(), PlannedIntegrator::Bdpt);
        // The error carried by a few pixels: not.
        let few = m(0.1, 200.0 / 1.6, 0.05);
        assert_eq!(v(path, bdpt, few).choice(), PlannedIntegrator::Bdpt);
        // Against path tracing when path wins: mlt must beat path, not bdpt.
        let (path, bdpt) = (m(0.1, 100.0, 0.9), m(0.1, 200.0, 0.9));
        assert_eq!(v(path, bdpt, mlt).choice(), PlannedIntegrator::Path);
        let fast = m(0.1, 100.0 / 1.6, 0.9);
        assert_eq!(v(path, bdpt, fast).choice(), PlannedIntegrator::Mlt);
    }
}
