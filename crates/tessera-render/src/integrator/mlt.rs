//! Metropolis light transport: multiplexed primary-sample-space MLT over the bidirectional
//! techniques (Hachisuka, Kaplanyan & Dachsbacher 2014, "Multiplexed Metropolis Light
//! Transport"; the mutations of Kelemen, Szirmay-Kalos, Antal & Csonka 2002; the
//! normalisation of Veach 1997, section 11.3).
//!
//! # What a sample is
//! A state of the chain is a vector of uniform numbers (the *primary samples*). It
//! drives, in three streams so that a change of the technique does not shift the other
//! numbers (Hachisuka et al. 2014, section 4.2): the path depth `d` (uniform in
//! `0..=max_depth`), one bidirectional technique `(s, t)` with `s + t = d + 2` (uniform
//! among the `d + 2`), the film position and the camera subpath of exactly `t` vertices
//! (camera stream, which reads the technique's number at depth 0 too, so that the numbers
//! after it sit at the same place at every depth), the light subpath of exactly `s`
//! vertices (light stream) and the
//! technique's own lens or light sample (connection stream; `bdpt::technique`). Its value
//! `f` is that technique's MIS-weighted contribution times `(max_depth + 1)(d + 2)`: summed
//! over depths and techniques, the MIS weights of [`bdpt`] make this an unbiased estimate
//! of the image, so `∫ f du` is the image's total (per unit film area) and a Metropolis
//! chain with the target `c(f) = luminance(f)` spends its time where the image is bright,
//! wherever the paths that carry that light are. The depth is a primary sample (pbrt-v4
//! fixes a chain's depth at its start instead): one pass has few chains, and a fixed depth
//! per chain would leave each depth's share of the pass to a handful of draws.
//! Subpaths take no Russian roulette (their lengths are fixed by the state).
//!
//! # Mutations (Kelemen et al. 2002, section 4)
//! Each step is a *large step* (probability [`LARGE_STEP_PROBABILITY`]: every number drawn
//! anew, uniform, an independence sampler) or a *small step* (every number moved by a
//! normal offset of deviation [`SIGMA`], wrapped onto `[0, 1)`). Both proposals are
//! symmetric, so the acceptance `min(1, c(f') / c(f))` satisfies detailed balance with
//! respect to `c`. Numbers are mutated lazily when the walk asks for them (the small steps
//! a number missed add up to one normal offset of deviation `SIGMA sqrt(n)`), which is the
//! same distribution as mutating every number every step. The chain records both the
//! proposal and the current state with their expected weights (Veach 1997, section
//! 11.5.1, "expected values"), which costs nothing and removes the variance of the
//! accept/reject coin.
//!
//! # Passes are independent replicates (ARCHITECTURE.md §3)
//! Pass `k` of frame `f` is a fresh, deterministic computation from `hash(seed, f, k)`:
//!
//! 1. **Bootstrap** (Veach 1997, section 11.3.1): `n_b = W H S / 32` independent uniform
//!    vectors, each evaluated at *every* depth and technique (`eval_all`: the subpaths
//!    traced once at full length, each technique reading the prefix of the numbers it
//!    would read alone, so each is exactly a state of the chain with the depth and technique
//!    numbers anywhere in their cells). The vector's candidates are the `(max_depth + 1)
//!    (d + 2)` cells of the depth and technique numbers, one uniform sample in each, a
//!    stratified bootstrap; a candidate's weight `c / q` is its MIS-weighted contribution's
//!    luminance, so `b = Σ / n_b` is the mean luminance of bdpt-like samples with all
//!    techniques and estimates `∫ c(f) du`. A vector that evaluates one technique sees a
//!    door-ajar room's light through the gap a few times per pass; this sees it in every
//!    technique that carries it (docs/benchmarks.md, "Metropolis light transport").
//! 2. **Chains**: `n_c` independent chains (one per 256 mutations, at least 8), each
//!    starting at a bootstrap candidate drawn with probability proportional to its weight
//!    (importance resampling, which removes start-up bias, Veach 1997, section 11.3.3: a
//!    vector in proportion to its total, then its depth and technique in proportion to their
//!    share, and the two numbers uniform in their cells) and running its share of the
//!    pass's `W H S` mutations (`S` the plan's samples per pass).
//! 3. The pass image is `b / S` times the recorded weights `f / c(f)` that landed in each
//!    pixel: the histogram of a chain with stationary density `c / b` times `b` is the image.
//!
//! No number is shared between passes, so the pass means of a pixel are independent and
//! identically distributed and their spread estimates the error of their mean, as for every
//! other technique. Within a pass the pixels are correlated (one bootstrap, chains crossing
//! pixels); that is the price of the method and does not bias the per-pixel error estimate.
//!
//! # Units and the farm
//! Like `bdpt` and `vcm`, `mlt` renders whole-frame units (`FramePlan::whole_frame`): a
//! pass's chains wander over the whole image. A unit is (frame, pass range) and costs, per
//! pass, `W H S` mutations (each one path and one of its techniques) plus the
//! bootstrap's `n_b` vectors (a 32nd of the mutations, each at every technique) and one
//! more evaluation of a vector per chain start. A unit's bytes
//! depend only on (scene, settings, seed, frame, passes): the same with any thread count and
//! on any worker. A plan with smaller tiles renders each tile's pixels from the whole
//! frame's chains (correct, `tile count` times the cost). The adaptive policy's `wanted`
//! mask is not consulted: a chain cannot skip a pixel, and every pixel gets the same value
//! whatever the mask.
//!
//! # Bias
//! None in expectation: the bootstrap-resampled start makes each pass an unbiased estimate
//! (Veach 1997, section 11.3.3), like `bdpt`'s. Variance is where MLT differs: within a
//! pass, light found by few chains is either found (bright) or not (black), so passes of
//! scenes with several separate bright regions spread widely; more samples per pass (longer
//! chains) shrink that.

use super::bdpt::{self, BdptSettings, Ctx, Scratch, MAX_BDPT_DEPTH};
use super::{accumulate, MisHeuristic, SampleSource, SampleStream};
use crate::math::luminance;
use crate::sampling::{hash_combine, hash_u64};
use crate::scene::RenderScene;
use glam::{Vec2, Vec3};
use tessera_farm::{FramePlan, UnitResult, WorkUnit};

/// Probability of a large step (an independent proposal); pbrt-v4's default. On the
/// door-ajar room 0.1 and 0.5 measured no better, with either bootstrap (docs/benchmarks.md,
/// "Metropolis light transport").
pub const LARGE_STEP_PROBABILITY: f64 = 0.3;
/// Standard deviation of a small step's offset of each primary sample (Kelemen et al. use
/// an exponential of similar width; pbrt-v4's default normal). 0.03 measured the same on
/// the door-ajar room, 0.003 worse.
pub const SIGMA: f64 = 0.01;
/// Mutations per chain the pass aims at (`W H S / MUTATIONS_PER_CHAIN` chains, clamped to
/// `MIN_CHAINS..=MAX_CHAINS`): long enough for small steps to explore, many enough that the
/// depths and regions of the image are visited in proportion within one pass. On the
/// door-ajar room 256 measured best of 64, 128, 256, 1024 and 4096 (docs/benchmarks.md):
/// a pass's image is a sum of the chains' neighbourhoods, so more, shorter chains cover it
/// more evenly, until each start's bootstrap path costs more than its chain explores.
const MUTATIONS_PER_CHAIN: u64 = 256;
/// Fewest chains per pass.
const MIN_CHAINS: u64 = 8;
/// Most chains per pass (a start costs one bootstrap evaluation, like a bdpt sample).
const MAX_CHAINS: u64 = 1 << 16;
/// Bootstrap vectors per mutation, as a divisor: `W H S / 32` vectors, each evaluated at
/// every depth and technique (about a bdpt sample's cost). 16 measured no better, 64 worse.
const BOOTSTRAP_DIVISOR: u64 = 32;
/// Mixed into the job seed for the chains' random numbers.
const MLT_STREAM: u64 = 0x6d6c_745f_6368_6169; // "mlt_chai"
/// Tags the bootstrap and chain seeds of a pass apart.
const BOOTSTRAP_TAG: u64 = 0x626f_6f74;
const CHAIN_TAG: u64 = 0x6368_6169;

/// The primary sample streams: which numbers drive which part of the path.
const CAMERA_STREAM: usize = 0;
const LIGHT_STREAM: usize = 1;
const CONNECTION_STREAM: usize = 2;
const STREAMS: usize = 3;

/// Settings of the Metropolis integrator.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MltSettings {
    /// The bidirectional techniques the chains sample (no Russian roulette).
    bdpt: BdptSettings,
}

impl MltSettings {
    /// Settings with `max_depth` clamped to `1..=MAX_BDPT_DEPTH`; `mis` weighs the
    /// techniques as for `bdpt`.
    pub fn new(mis: MisHeuristic, max_depth: u32) -> Self {
        Self {
            // Subpath lengths are part of the state: no roulette.
            bdpt: BdptSettings::new(mis, max_depth.clamp(1, MAX_BDPT_DEPTH), u32::MAX),
        }
    }

    /// Deepest path (bounces).
    pub fn max_depth(&self) -> u32 {
        self.bdpt.max_depth
    }
}

/// SplitMix64 (Steele, Lea & Flood 2014): the chains' random numbers, one `u64` of state.
#[derive(Clone, Debug)]
struct Rng(u64);

impl Rng {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        hash_u64(self.0)
    }

    /// Uniform in `[0, 1)` with 53 bits.
    fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / 9_007_199_254_740_992.0)
    }

    /// A standard normal number (Box & Muller 1958).
    fn normal(&mut self) -> f64 {
        let u1 = 1.0 - self.uniform(); // (0, 1]
        let u2 = self.uniform();
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }
}

/// One primary sample with its value before the current step (for rejection).
#[derive(Clone, Copy, Debug)]
struct PrimarySample {
    value: f64,
    /// Iteration of the last change.
    modified: u64,
    backup: f64,
    modified_backup: u64,
}

/// Kelemen's primary sample vector with lazy mutation (pbrt-v4's `MLTSampler` is the same
/// design): the state of a chain. Numbers are created and mutated when the walk first asks
/// for them in an iteration; a rejected step restores those it changed.
#[derive(Clone, Debug)]
pub(crate) struct PrimarySamples {
    x: Vec<PrimarySample>,
    rng: Rng,
    iteration: u64,
    large_step: bool,
    last_large_step: u64,
    stream: usize,
    index: usize,
    sigma: f64,
    p_large: f64,
}

/// Largest `f32` below one: the numbers handed to the walks stay in `[0, 1)`.
const ONE_MINUS_EPSILON: f32 = 1.0 - f32::EPSILON / 2.0;

impl PrimarySamples {
    /// An empty vector with room for `capacity` numbers (no allocation later for walks
    /// that ask fewer) and mutation parameters `sigma`, `p_large`.
    pub(crate) fn new(capacity: usize, sigma: f64, p_large: f64) -> Self {
        Self {
            x: Vec::with_capacity(capacity),
            rng: Rng(0),
            iteration: 0,
            large_step: true,
            last_large_step: 0,
            stream: 0,
            index: 0,
            sigma,
            p_large,
        }
    }

    /// Starts a new state from `seed`: every number uniform and independent (iteration 0 is
    /// a large step).
    pub(crate) fn reset(&mut self, seed: u64) {
        self.x.clear();
        self.rng = Rng(seed);
        self.iteration = 0;
        self.large_step = true;
        self.last_large_step = 0;
        self.stream = 0;
        self.index = 0;
    }

    /// Continues the current state with the random numbers of `seed` (a chain started from
    /// a bootstrap sample takes its own numbers from there on).
    pub(crate) fn reseed(&mut self, seed: u64) {
        self.rng = Rng(seed);
    }

    /// Sets number `index` of stream `stream` (which must exist) to `value`, as part of
    /// the current state.
    pub(crate) fn set(&mut self, stream: usize, index: usize, value: f64) {
        let xi = &mut self.x[stream + STREAMS * index];
        xi.value = value;
        xi.backup = value;
    }

    /// A uniform number from the chain's generator (the acceptance coin).
    pub(crate) fn uniform(&mut self) -> f64 {
        self.rng.uniform()
    }

    /// Starts the next proposal: a large step with probability `p_large`.
    pub(crate) fn start_iteration(&mut self) {
        self.iteration += 1;
        self.large_step = self.rng.uniform() < self.p_large;
    }

    /// Restarts the walk's reading at stream `stream`.
    pub(crate) fn start_stream(&mut self, stream: usize) {
        self.stream = stream;
        self.index = 0;
    }

    /// Keeps the proposal.
    pub(crate) fn accept(&mut self) {
        if self.large_step {
            self.last_large_step = self.iteration;
        }
    }

    /// Restores the numbers the proposal changed.
    pub(crate) fn reject(&mut self) {
        let it = self.iteration;
        for xi in &mut self.x {
            if xi.modified == it {
                xi.value = xi.backup;
                xi.modified = xi.modified_backup;
            }
        }
        self.iteration -= 1;
    }

    /// Number `i` brought up to date with the current iteration.
    fn ensure_ready(&mut self, i: usize) -> f64 {
        while self.x.len() <= i {
            // A number the walk never asked for is, under the stationary distribution,
            // uniform and independent of the rest: create it so, as of the last large step.
            let value = self.rng.uniform();
            self.x.push(PrimarySample {
                value,
                modified: self.last_large_step,
                backup: value,
                modified_backup: self.last_large_step,
            });
        }
        let (large, it, last_large, sigma) = (
            self.large_step,
            self.iteration,
            self.last_large_step,
            self.sigma,
        );
        let xi = &mut self.x[i];
        if xi.modified == it {
            return xi.value;
        }
        // Missed a large step since its last change: it was redrawn then.
        if xi.modified < last_large {
            xi.value = self.rng.uniform();
            xi.modified = last_large;
        }
        xi.backup = xi.value;
        xi.modified_backup = xi.modified;
        if large {
            xi.value = self.rng.uniform();
        } else {
            // The small steps it missed since its last change, added up: the sum of `n`
            // independent normal offsets is one of deviation `sigma sqrt(n)`.
            let n = (it - xi.modified) as f64;
            let v = xi.value + self.rng.normal() * sigma * n.sqrt();
            xi.value = v - v.floor();
        }
        xi.modified = it;
        xi.value
    }
}

impl SampleSource for PrimarySamples {
    #[inline]
    fn next_1d(&mut self) -> f32 {
        let i = self.stream + STREAMS * self.index;
        self.index += 1;
        (self.ensure_ready(i) as f32).min(ONE_MINUS_EPSILON)
    }

    #[inline]
    fn next_2d(&mut self) -> Vec2 {
        let x = self.next_1d();
        Vec2::new(x, self.next_1d())
    }
}

/// A chain's state: the contribution `f`, where it lands, and its target value `c(f)`.
#[derive(Clone, Copy, Debug)]
pub(crate) struct State<T> {
    pub(crate) value: T,
    pub(crate) c: f64,
}

/// Runs `mutations` Metropolis steps from `current` (whose numbers `samples` holds):
/// `eval` evaluates the proposal the mutated numbers give, and `record(value, weight)`
/// receives each step's proposal and current state with their expected-value weights
/// `a / c'` and `(1 - a) / c` (a the acceptance). A proposal with `c` not finite and
/// positive is never accepted. Returns the final state.
pub(crate) fn run_chain<T: Copy>(
    samples: &mut PrimarySamples,
    mutations: u64,
    mut current: State<T>,
    mut eval: impl FnMut(&mut PrimarySamples) -> State<T>,
    mut record: impl FnMut(T, f64),
) -> State<T> {
    for _ in 0..mutations {
        samples.start_iteration();
        let proposal = eval(samples);
        let accept = if proposal.c.is_finite() && proposal.c > 0.0 {
            (proposal.c / current.c).min(1.0)
        } else {
            0.0
        };
        if accept > 0.0 {
            record(proposal.value, accept / proposal.c);
        }
        if accept < 1.0 {
            record(current.value, (1.0 - accept) / current.c);
        }
        if samples.uniform() < accept {
            current = proposal;
            samples.accept();
        } else {
            samples.reject();
        }
    }
    current
}

/// The target value of a contribution: its luminance if it is valid radiance, else zero
/// (an invalid contribution is counted in `rejected`, never sampled).
fn target(l: Vec3, rejected: &mut u64) -> f64 {
    if l.is_finite() && l.min_element() >= 0.0 {
        luminance(l) as f64
    } else {
        *rejected += 1;
        0.0
    }
}

/// One unit's Metropolis renderer: scene, settings and the reused buffers.
struct Mlt<'a> {
    ctx: Ctx<'a>,
    st: BdptSettings,
    motion: bool,
    lens: bool,
    film: Vec2,
    /// Path depths sampled: `0..=max_depth`.
    depths: usize,
    scratch: Box<Scratch>,
}

impl Mlt<'_> {
    /// The contribution of the state `samples` holds: the technique's MIS-weighted
    /// estimate times the number of depths and of techniques, and the film position it
    /// belongs to.
    fn eval(&mut self, samples: &mut PrimarySamples) -> (Vec3, Vec2) {
        samples.start_stream(CAMERA_STREAM);
        // The depth is a primary sample too (module documentation).
        let depth = ((samples.next_1d() * self.depths as f32) as usize).min(self.depths - 1);
        // The technique's number is read at every depth, so that the numbers after it
        // sit at the same place whatever the depth (the bootstrap evaluates every depth
        // and technique of one vector, `eval_all`).
        let u_technique = samples.next_1d();
        let (s, t, n) = if depth == 0 {
            // Only (0, 2) sees an emitter directly: (1, 1) is not a bdpt technique.
            (0, 2, 1)
        } else {
            let n = depth + 2;
            let s = ((u_technique * n as f32) as usize).min(n - 1);
            (s, n - s, n)
        };
        if self.motion {
            self.ctx.set_time(samples.next_1d());
        }
        let film = samples.next_2d() * self.film;
        let lens_u = if self.lens {
            samples.next_2d()
        } else {
            Vec2::ZERO
        };
        let (ctx, st) = (&self.ctx, &self.st);
        let n_cam = bdpt::camera_subpath(ctx, st, film, lens_u, &mut self.scratch.cam, t, samples);
        if n_cam != t {
            return (Vec3::ZERO, film);
        }
        samples.start_stream(LIGHT_STREAM);
        // s = 1 samples its light point from the camera vertex (next-event estimation).
        if s >= 2 && bdpt::light_subpath(ctx, st, &mut self.scratch.light, s, samples) != s {
            return (Vec3::ZERO, film);
        }
        samples.start_stream(CONNECTION_STREAM);
        let (l, raster) = bdpt::technique(ctx, st, &mut self.scratch, s, t, samples);
        (l * (n * self.depths) as f32, raster.unwrap_or(film))
    }
}

impl Mlt<'_> {
    /// Every depth's and technique's MIS-weighted contribution of the numbers `samples`
    /// holds, as `(depth, s, luminance)` for those with a positive luminance, into `out`;
    /// returns their sum. The subpaths are traced once, at full length, and each technique
    /// reads a prefix of them: the same numbers `eval` reads for that depth and technique.
    fn eval_all(
        &mut self,
        samples: &mut PrimarySamples,
        out: &mut Vec<(usize, usize, f64)>,
    ) -> f64 {
        out.clear();
        samples.start_stream(CAMERA_STREAM);
        samples.next_1d(); // depth
        samples.next_1d(); // technique
        if self.motion {
            self.ctx.set_time(samples.next_1d());
        }
        let film = samples.next_2d() * self.film;
        let lens_u = if self.lens {
            samples.next_2d()
        } else {
            Vec2::ZERO
        };
        let max_depth = self.depths - 1;
        let (ctx, st) = (&self.ctx, &self.st);
        let n_cam = bdpt::camera_subpath(
            ctx,
            st,
            film,
            lens_u,
            &mut self.scratch.cam,
            max_depth + 2,
            samples,
        );
        samples.start_stream(LIGHT_STREAM);
        let n_light = if max_depth + 1 >= 2 {
            bdpt::light_subpath(ctx, st, &mut self.scratch.light, max_depth + 1, samples)
        } else {
            0
        };
        let mut total = 0.0;
        for depth in 0..=max_depth {
            let n = depth + 2;
            let techniques = if depth == 0 { 0..1 } else { 0..n };
            for s in techniques {
                let t = n - s;
                if t > n_cam || (s >= 2 && s > n_light) {
                    continue;
                }
                samples.start_stream(CONNECTION_STREAM);
                let (l, _) = bdpt::technique(ctx, st, &mut self.scratch, s, t, samples);
                let c = target(l, &mut 0);
                if c > 0.0 && c.is_finite() {
                    total += c;
                    out.push((depth, s, c));
                }
            }
        }
        total
    }
}

/// A number in `[0, 1)` that `eval` maps to cell `k` of `n` (as `(u as f32 * n as f32)
/// as usize`), uniform over the numbers that do: drawn in the cell and redrawn when the
/// rounding to `f32` puts it in a neighbour.
fn uniform_in_cell(rng: &mut Rng, k: usize, n: usize) -> f64 {
    loop {
        let v = (k as f64 + rng.uniform()) / n as f64;
        let f = (v as f32).min(ONE_MINUS_EPSILON);
        if ((f * n as f32) as usize).min(n - 1) == k {
            return v;
        }
    }
}

/// The per-pass seed of the chains and the bootstrap.
fn pass_seed(seed: u64, frame: u32, pass: u32) -> u64 {
    hash_combine(
        hash_combine(hash_u64(seed ^ MLT_STREAM), frame as u64),
        pass as u64,
    )
}

/// Chains and bootstrap samples of a pass of `mutations` mutations.
fn pass_sizes(mutations: u64) -> (u64, u64) {
    let chains = (mutations / MUTATIONS_PER_CHAIN)
        .clamp(MIN_CHAINS, MAX_CHAINS)
        .min(mutations.max(1));
    let bootstrap = (mutations / BOOTSTRAP_DIVISOR).max(chains);
    (chains, bootstrap)
}

/// Renders one work unit with multiplexed MLT; see the [module documentation](self) for
/// the passes, the units and the determinism. `wanted` is accepted for the common
/// interface and not consulted: every pixel of the tile gets its value.
pub fn render_unit(
    scene: &RenderScene,
    settings: &MltSettings,
    stream: SampleStream,
    plan: &FramePlan,
    unit: WorkUnit,
    _wanted: impl Fn(usize, u32) -> bool,
) -> UnitResult {
    let rect = plan.tile(unit.tile);
    let (w, h) = (plan.width, plan.height);
    let spp = plan.samples_per_pass;
    let depths = settings.max_depth() as usize + 1;
    let mutations = w as u64 * h as u64 * spp as u64;
    let (n_chains, n_bootstrap) = pass_sizes(mutations);
    let mut mlt = Mlt {
        ctx: Ctx::new(scene),
        st: settings.bdpt,
        motion: scene.has_motion(),
        lens: scene.camera.has_lens(),
        film: Vec2::new(w as f32, h as f32),
        depths,
        scratch: Scratch::boxed(),
    };
    // Room for every number a walk of the deepest path asks (6 for the technique, time,
    // film and lens, 4 per bounce, 3 for the connection), in every stream: no allocation
    // per mutation.
    let per_stream = 8 + 4 * (settings.max_depth() as usize + 2);
    let mut samples = PrimarySamples::new(STREAMS * per_stream, SIGMA, LARGE_STEP_PROBABILITY);
    let mut cdf = vec![0.0f64; n_bootstrap as usize];
    let mut found = Vec::new();
    let mut sum = vec![[0.0f64; 3]; (w * h) as usize];
    let pixels = rect.pixel_count();
    let mut pass_means = Vec::with_capacity(pixels * unit.pass_count as usize);
    let mut rejected_samples = 0u64;
    for pass in unit.first_pass..unit.first_pass + unit.pass_count {
        let seed = pass_seed(stream.seed, unit.frame, pass);
        let boot_seed = |i: usize| hash_combine(seed ^ BOOTSTRAP_TAG, i as u64);
        sum.fill([0.0; 3]);
        // 1. Bootstrap: the normalisation from this pass's own samples.
        let mut total = 0.0f64;
        for (i, entry) in cdf.iter_mut().enumerate() {
            samples.reset(boot_seed(i));
            total += mlt.eval_all(&mut samples, &mut found);
            *entry = total;
        }
        let b = total / n_bootstrap as f64;
        // 2. Chains, started from bootstrap samples drawn in proportion to their value.
        if b > 0.0 && b.is_finite() {
            for chain in 0..n_chains {
                let mut rng = Rng(hash_combine(seed ^ CHAIN_TAG, chain));
                let u = rng.uniform() * total;
                // The first entry whose running sum exceeds u: its own value is positive.
                let i = cdf.partition_point(|&c| c <= u).min(cdf.len() - 1);
                samples.reset(boot_seed(i));
                // Its depth and technique in proportion to their contribution, with
                // numbers in their cells that select them (module documentation).
                let all = mlt.eval_all(&mut samples, &mut found);
                let mut u = rng.uniform() * all;
                let mut pick = found[found.len() - 1];
                for &e in &found {
                    if u < e.2 {
                        pick = e;
                        break;
                    }
                    u -= e.2;
                }
                let (d, s_pick, _) = pick;
                samples.set(CAMERA_STREAM, 0, uniform_in_cell(&mut rng, d, depths));
                let n = if d == 0 { 1 } else { d + 2 };
                samples.set(CAMERA_STREAM, 1, uniform_in_cell(&mut rng, s_pick, n));
                let (l, p) = mlt.eval(&mut samples);
                let start = State {
                    value: (l, p),
                    c: target(l, &mut 0),
                };
                samples.reseed(rng.next_u64());
                let share = mutations / n_chains + u64::from(chain < mutations % n_chains);
                run_chain(
                    &mut samples,
                    share,
                    start,
                    |samples| {
                        let (l, p) = mlt.eval(samples);
                        State {
                            value: (l, p),
                            c: target(l, &mut rejected_samples),
                        }
                    },
                    |(l, p), weight| {
                        let px = (p.x as u32).min(w - 1);
                        let py = (p.y as u32).min(h - 1);
                        let l = l * weight as f32;
                        accumulate(&mut sum[(py * w + px) as usize], l, &mut 0);
                    },
                );
            }
        }
        // 3. The pass image: b / S times the recorded weights of each tile pixel.
        let scale = if b.is_finite() { b / spp as f64 } else { 0.0 };
        for y in rect.y0..rect.y0 + rect.height {
            for x in rect.x0..rect.x0 + rect.width {
                let s = sum[(y * w + x) as usize];
                pass_means.push([
                    (s[0] * scale) as f32,
                    (s[1] * scale) as f32,
                    (s[2] * scale) as f32,
                ]);
            }
        }
    }
    UnitResult {
        unit,
        width: rect.width,
        height: rect.height,
        pass_means,
        rejected_samples,
        bias: None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::chi2::chi2_survival;

    /// A target on the unit square with a peak, a step and a ridge across the wrap-around
    /// edge: what a chain's states must be distributed as.
    fn target_2d(u: Vec2) -> f64 {
        let (x, y) = (u.x as f64, u.y as f64);
        let peak = (-((x - 0.3).powi(2) + (y - 0.7).powi(2)) / 0.01).exp() * 4.0;
        let step = if x < 0.1 { 2.0 } else { 0.0 };
        let ridge = if !(0.05..=0.95).contains(&y) {
            1.5
        } else {
            0.0
        };
        0.2 + peak + step + ridge
    }

    const BINS: usize = 10;

    /// Probability of bin (i, j) under `target_2d`, by a fine midpoint rule.
    fn bin_probabilities() -> Vec<f64> {
        let sub = 40;
        let mut p = vec![0.0; BINS * BINS];
        for i in 0..BINS * sub {
            for j in 0..BINS * sub {
                let u = Vec2::new(
                    ((i as f64 + 0.5) / (BINS * sub) as f64) as f32,
                    ((j as f64 + 0.5) / (BINS * sub) as f64) as f32,
                );
                p[(i / sub) * BINS + j / sub] += target_2d(u);
            }
        }
        let total: f64 = p.iter().sum();
        p.iter().map(|v| v / total).collect()
    }

    fn eval_2d(samples: &mut PrimarySamples) -> State<Vec2> {
        samples.start_stream(CAMERA_STREAM);
        // A few numbers are asked for only in part of the domain, as a walk's later
        // bounces are: the lazy mutation of numbers that were skipped is exercised too.
        let u = samples.next_2d();
        if u.x > 0.5 {
            samples.start_stream(LIGHT_STREAM);
            samples.next_2d();
        }
        State {
            value: u,
            c: target_2d(u),
        }
    }

    /// Detailed balance: chains started *in* the stationary distribution (by rejection
    /// sampling the target) must still be in it after any number of steps. The end states
    /// of independent chains are independent draws, so a chi-squared test on them is
    /// valid; two tests (large steps mixed in, and small steps only) at a family-wise
    /// level of 0.001 (Šidák).
    #[test]
    fn mutations_keep_the_target_distribution() {
        let probabilities = bin_probabilities();
        let fmax = 0.2 + 4.0 + 2.0 + 1.5;
        let alpha = 1.0 - (1.0 - 0.001f64).powf(0.5);
        for (p_large, sigma) in [(LARGE_STEP_PROBABILITY, 0.1), (0.0, 0.05)] {
            let chains = 20_000;
            let mut counts = vec![0u64; BINS * BINS];
            let mut samples = PrimarySamples::new(16, sigma, p_large);
            let mut seeds = Rng(0x5eed_1234);
            for _ in 0..chains {
                // Rejection sampling of the start.
                let start = loop {
                    samples.reset(seeds.next_u64());
                    let s = eval_2d(&mut samples);
                    if samples.uniform() * fmax < s.c {
                        break s;
                    }
                };
                let end = run_chain(&mut samples, 40, start, eval_2d, |_, _| {});
                let i = ((end.value.x * BINS as f32) as usize).min(BINS - 1);
                let j = ((end.value.y * BINS as f32) as usize).min(BINS - 1);
                counts[i * BINS + j] += 1;
            }
            let stat: f64 = counts
                .iter()
                .zip(&probabilities)
                .map(|(&o, &p)| {
                    let e = p * chains as f64;
                    (o as f64 - e).powi(2) / e
                })
                .sum();
            let p_value = chi2_survival(stat, BINS * BINS - 1);
            assert!(
                p_value > alpha,
                "p_large {p_large}: chi2 {stat:.1}, p = {p_value:.2e}"
            );
        }
    }

    /// The same test must fail for a chain whose acceptance is wrong (here: always
    /// accepting), or it could not catch a broken one.
    #[test]
    fn a_wrong_acceptance_fails_the_test() {
        let probabilities = bin_probabilities();
        let fmax = 0.2 + 4.0 + 2.0 + 1.5;
        let chains = 20_000;
        let mut counts = vec![0u64; BINS * BINS];
        let mut samples = PrimarySamples::new(16, 0.1, LARGE_STEP_PROBABILITY);
        let mut seeds = Rng(0x5eed_1234);
        for _ in 0..chains {
            let start = loop {
                samples.reset(seeds.next_u64());
                let s = eval_2d(&mut samples);
                if samples.uniform() * fmax < s.c {
                    break s;
                }
            };
            // Every proposal looks equally good: a random walk, uniform in the limit.
            let end = run_chain(
                &mut samples,
                40,
                start,
                |s| State {
                    c: 1.0,
                    ..eval_2d(s)
                },
                |_, _| {},
            );
            let i = ((end.value.x * BINS as f32) as usize).min(BINS - 1);
            let j = ((end.value.y * BINS as f32) as usize).min(BINS - 1);
            counts[i * BINS + j] += 1;
        }
        let stat: f64 = counts
            .iter()
            .zip(&probabilities)
            .map(|(&o, &p)| (o as f64 - p * chains as f64).powi(2) / (p * chains as f64))
            .sum();
        assert!(chi2_survival(stat, BINS * BINS - 1) < 1e-6, "chi2 {stat}");
    }

    #[test]
    fn a_rejected_step_restores_the_numbers() {
        let mut s = PrimarySamples::new(8, 0.1, 0.0);
        s.reset(7);
        s.start_stream(CAMERA_STREAM);
        let a = s.next_2d();
        s.start_iteration();
        s.start_stream(CAMERA_STREAM);
        let b = s.next_2d();
        assert_ne!(a, b);
        s.reject();
        assert_eq!(s.iteration, 0);
        assert_eq!(Vec2::new(s.x[0].value as f32, s.x[3].value as f32), a);
    }

    #[test]
    fn pass_sizes_cover_every_mutation() {
        for m in [1u64, 15, 1000, 65_536, 10_000_000] {
            let (c, b) = pass_sizes(m);
            assert!(c >= 1 && c <= m.max(1) && b >= c, "{m}: {c} {b}");
        }
    }

    /// The bootstrap's `eval_all` gives, for every depth and technique, exactly what
    /// `eval` gives for the state with the depth and technique numbers in that cell (the
    /// prefix reading of the subpaths), and nothing for the cells it leaves out: on the
    /// Cornell box (an area light, so every technique carries light), over many vectors.
    #[test]
    fn eval_all_gives_each_technique_as_eval_does() {
        let scene = tessera_scene::load("builtin:cornell-box").unwrap();
        let (w, h) = (16u32, 16u32);
        let rs = RenderScene::build(&scene, w, h).unwrap();
        let settings = MltSettings::new(MisHeuristic::Power, 5);
        let depths = settings.max_depth() as usize + 1;
        let mut mlt = Mlt {
            ctx: Ctx::new(&rs),
            st: settings.bdpt,
            motion: rs.has_motion(),
            lens: rs.camera.has_lens(),
            film: Vec2::new(w as f32, h as f32),
            depths,
            scratch: Scratch::boxed(),
        };
        let mut samples = PrimarySamples::new(64, SIGMA, LARGE_STEP_PROBABILITY);
        let mut found = Vec::new();
        let mut rng = Rng(17);
        let (mut checked, mut nonzero) = (0, 0);
        for seed in 0..300u64 {
            samples.reset(seed);
            let total = mlt.eval_all(&mut samples, &mut found);
            let sum: f64 = found.iter().map(|e| e.2).sum();
            assert!((total - sum).abs() <= 1e-12 * total.max(1.0));
            let all = found.clone();
            for d in 0..depths {
                let n = if d == 0 { 1 } else { d + 2 };
                for s in 0..n {
                    samples.set(CAMERA_STREAM, 0, uniform_in_cell(&mut rng, d, depths));
                    samples.set(CAMERA_STREAM, 1, uniform_in_cell(&mut rng, s, n));
                    let (l, _) = mlt.eval(&mut samples);
                    let c = target(l, &mut 0) / (n * depths) as f64;
                    let want = all
                        .iter()
                        .find(|e| e.0 == d && e.1 == s)
                        .map_or(0.0, |e| e.2);
                    assert!(
                        (c - want).abs() <= 1e-5 * want.max(1e-12),
                        "seed {seed}, depth {d}, s {s}: eval {c}, eval_all {want}"
                    );
                    checked += 1;
                    nonzero += usize::from(want > 0.0);
                }
            }
        }
        assert!(nonzero > checked / 20, "{nonzero} of {checked} carry light");
    }
}
