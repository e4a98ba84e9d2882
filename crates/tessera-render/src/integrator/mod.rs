//! Integrators: estimators of the radiance arriving at the camera along a ray, and the one
//! place that decides which of them renders a work unit.
//!
//! | name | what it computes |
//! |---|---|
//! | `path` | unidirectional path tracing with next-event estimation, multiple importance sampling and Russian roulette ([`path`]) |
//! | `direct` | direct lighting only: emission seen by the camera and light arriving at the first surface, one bounce, both techniques combined by MIS ([`path`] with a bounce limit of 1) |
//! | `bdpt` | bidirectional path tracing: camera and light subpaths joined by every connection technique, light tracing splatted onto the film, power-heuristic MIS ([`bdpt`]) |
//! | `vcm` | vertex connection and merging: bdpt's techniques plus merging with a per-pass photon map, all weighted by MIS; biased, consistent ([`vcm`]) |
//! | `ppm` | progressive photon mapping: vcm's merging alone, at the first non-specular camera vertex; biased, consistent ([`vcm`]'s merge-only mode) |
//! | `mlt` | Metropolis light transport: Markov chains in primary sample space over bdpt's techniques, each pass with its own bootstrap normalisation and chains ([`mlt`]) |
//! | `mnee` | path tracing with manifold next-event estimation at every non-specular camera vertex: caustics of point, spot and small area lights through up to [`mnee::MAX_CHAIN`] specular interfaces; unbiased ([`path::radiance_mnee`], [`mnee`]) |
//!
//! # The interface
//!
//! [`RenderConfig`] is everything besides the scene and the frame plan that decides the
//! value of a sample. [`render_unit_where`] holds the one exhaustive `match` over
//! [`Integrator`]: each arm turns the render settings into that integrator's own
//! settings ([`path::PathSettings`], [`bdpt::BdptSettings`]) and renders the unit with it, so
//! an integrator never sees the others' variants or options. Dispatch is a `match` on a
//! `Copy` enum, decided once per unit; the per-sample loops inside are monomorphic and do
//! not allocate.
//!
//! Every integrator keeps the same contract, on which the farm's split and merge rely:
//!
//! - **Deterministic.** A unit's result is a pure function of (scene, settings, plan,
//!   unit): every sample draws from `PixelSampler::new(sampler, seed, frame, pixel, pass)`
//!   (or another stream derived from the seed, as bdpt's light subpaths do) and the samples
//!   of a pass are summed in a fixed order into one `f64` accumulator per pixel, the pass
//!   mean being that sum divided by `samples_per_pass` (the indexed sampler of pbrt-v4,
//!   `Sampler::StartPixelSample`; Pharr, Jakob & Humphreys 2023, section 8.3).
//! - **Invalid samples are dropped and counted.** A contribution that is NaN, infinite or
//!   negative is a bug, not light: it would poison the pixel's mean and the pass variance
//!   the error estimate reads. It is left out of the sum (the pass mean still divides by
//!   `samples_per_pass`: a dropped sample counts as black) and counted in
//!   [`UnitResult::rejected_samples`], which the coordinator sums per job.
//!   `accumulate` does both; use it for every contribution.
//! - **Pixels outside `wanted` may be skipped** (left black, or holding partial values
//!   the adaptive policy never reads): `path` and `direct` skip them entirely; bdpt skips
//!   their camera subpaths but still traces their light subpaths, whose splats land on
//!   other pixels.
//!
//! # Adding an integrator
//!
//! Photon mapping, say, as `pm`:
//!
//! 1. A variant `Integrator::PhotonMap` in the job contract
//!    (`tessera-farm/src/job/choice.rs`: its name in `as_str` and `FromStr`, which the
//!    command line, the HTTP API and the store all parse with), a row in the table above,
//!    and its value in the gRPC `Integrator` enum (`proto/tessera/v1/worker.proto` and the
//!    two `match`es in `tessera-proto/src/convert.rs`, which the compiler points at).
//! 2. One new file, `integrator/pm.rs`: a `//!` block saying what it estimates (cite the
//!    paper by author, year and section), its own `PmSettings` built from
//!    [`RenderConfig`] only in the `match` arm, and a
//!    `render_unit(scene, &PmSettings, SampleStream, plan, unit) -> UnitResult` that keeps
//!    the contract above. An integrator that estimates each pixel independently can call
//!    the shared camera-sample loop instead, as `path` and `direct` do.
//! 3. The arm in [`render_unit_where`]: the compiler's exhaustive-match error points at it.
//! 4. Tests beside the file (`#[cfg(test)] mod tests`) and an agreement test against
//!    `path` in `tests/it/` (as `tests/it/bdpt.rs` does); determinism across thread counts and
//!    unit splits comes from the contract and is checked by `tests/it/determinism.rs`.

pub mod bdpt;
pub mod mlt;
pub mod mnee;
pub mod path;
pub mod vcm;

use crate::sampling::{PixelSampler, SamplerKind};
use crate::scene::RenderScene;
use glam::{Vec2, Vec3};
use tessera_farm::{FramePlan, UnitResult, WorkUnit};

/// Everything that decides the value of a sample, besides the scene and the plan: the job
/// contract's resolved [`tessera_farm::job::RenderConfig`] (for bdpt, `mis`
/// balance selects β = 1, any other the power heuristic).
pub use tessera_farm::job::RenderConfig;

/// The integrators, MIS heuristics and their string forms are the job contract's
/// ([`tessera_farm::job`]): one type each, re-exported where the renderer dispatches on them.
pub use tessera_farm::job::{Integrator, MisHeuristic};

/// Which sample sequence a unit draws from: the point set and the job seed. The same for
/// every integrator; an integrator needing a second stream derives it from the seed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SampleStream {
    /// Sample generator.
    pub sampler: SamplerKind,
    /// Job seed.
    pub seed: u64,
}

impl SampleStream {
    /// The sample sequence `settings` select.
    pub fn of(settings: &RenderConfig) -> Self {
        Self {
            sampler: settings.sampler,
            seed: settings.seed,
        }
    }
}

/// Renders one work unit. The caller guarantees that `unit` belongs to `plan` and that
/// `scene` was built for the plan's image size.
pub fn render_unit(
    scene: &RenderScene,
    settings: &RenderConfig,
    plan: &FramePlan,
    unit: WorkUnit,
) -> UnitResult {
    render_unit_where(scene, settings, plan, unit, |_, _| true)
}

/// [`render_unit`] for only the (tile pixel, pass) pairs where `wanted(i, pass)` holds
/// (`i` row-major within the tile); the others are left black without tracing a ray.
/// Adaptive rendering (`tessera_farm::AdaptiveTile::wants`) uses it to skip pixels that
/// stopped: a wanted pixel's value is the same as with [`render_unit`], and the policy
/// ignores the others, so the image is the same as when whole tiles are rendered.
///
/// Bidirectional path tracing skips the camera subpaths of unwanted pixels but traces
/// every pixel's light subpaths (their splats land anywhere in the whole-frame tile), so
/// an unwanted pixel may hold the splats that landed in it: the policy ignores it, and the
/// farm zeroes it (`Scheduler`'s canonical masked result).
pub fn render_unit_where(
    scene: &RenderScene,
    settings: &RenderConfig,
    plan: &FramePlan,
    unit: WorkUnit,
    wanted: impl Fn(usize, u32) -> bool,
) -> UnitResult {
    let stream = SampleStream::of(settings);
    match settings.integrator {
        Integrator::Path | Integrator::Direct => {
            let path = path::PathSettings {
                mis: settings.mis,
                // Direct lighting is the path tracer stopped after its first scattering
                // event: emission seen directly, plus NEE and BSDF sampling at one vertex.
                max_depth: match settings.integrator {
                    Integrator::Direct => 1,
                    _ => settings.max_depth,
                },
                rr_depth: settings.rr_depth,
            };
            render_camera_samples(scene, stream, plan, unit, wanted, |o, d, time, sampler| {
                path::radiance(scene, &path, o, d, time, sampler)
            })
        }
        // Path tracing with MNEE estimates each pixel on its own, as path tracing does: the
        // same camera-sample loop, tiles and unit splits; its own monomorphisation of the
        // path loop, so plain path tracing's code and images are untouched.
        Integrator::Mnee => {
            let path = path::PathSettings {
                mis: settings.mis,
                max_depth: settings.max_depth,
                rr_depth: settings.rr_depth,
            };
            render_camera_samples(scene, stream, plan, unit, wanted, |o, d, time, sampler| {
                path::radiance_mnee(scene, &path, o, d, time, sampler)
            })
        }
        // Light tracing splats across pixels: see `bdpt` for how a unit stays deterministic
        // (and why bdpt plans use one whole-frame tile).
        Integrator::Bdpt => {
            let bdpt = bdpt::BdptSettings::new(settings.mis, settings.max_depth, settings.rr_depth);
            bdpt::render_unit(scene, &bdpt, stream, plan, unit, wanted)
        }
        // Light tracing splats and merging reads the whole pass's photon map: whole-frame
        // units as for bdpt, the photon map rebuilt per pass inside the unit.
        // ppm is vcm's merge-only mode: the same units and photon maps.
        Integrator::Vcm | Integrator::Ppm => {
            let new = if settings.integrator == Integrator::Ppm {
                vcm::VcmSettings::ppm
            } else {
                vcm::VcmSettings::new
            };
            let vcm = new(
                settings.mis,
                settings.max_depth,
                settings.rr_depth,
                scene,
                plan.width,
                plan.height,
            );
            vcm::render_unit(scene, &vcm, stream, plan, unit, wanted)
        }
        // Markov chains wander over the whole frame: whole-frame units as for bdpt, each
        // pass with its own bootstrap and chains.
        Integrator::Mlt => {
            let mlt = mlt::MltSettings::new(settings.mis, settings.max_depth);
            mlt::render_unit(scene, &mlt, stream, plan, unit, wanted)
        }
    }
}

/// Renders one work unit with path tracing plus manifold next-event estimation
/// ([`Integrator::Mnee`]) whatever `settings.integrator` says: `settings` as for
/// [`Integrator::Path`], so a test can render the same configuration with and without
/// MNEE.
pub fn render_unit_path_mnee(
    scene: &RenderScene,
    settings: &RenderConfig,
    plan: &FramePlan,
    unit: WorkUnit,
) -> UnitResult {
    let settings = RenderConfig {
        integrator: Integrator::Mnee,
        ..*settings
    };
    render_unit(scene, &settings, plan, unit)
}

/// Adds the sample `l` to a pixel's sum if it is valid radiance (finite, every channel
/// `>= 0`, `-0.0` included), otherwise counts it in `rejected` and leaves the sum alone.
/// Returns whether it was added. The sum is in `f64`, channel by channel, in the order of
/// the calls: that order is part of the determinism contract.
#[inline]
pub(crate) fn accumulate(sum: &mut [f64; 3], l: Vec3, rejected: &mut u64) -> bool {
    // A non-finite sample would poison the pixel: it is a bug, not light.
    if l.is_finite() && l.min_element() >= 0.0 {
        sum[0] += l.x as f64;
        sum[1] += l.y as f64;
        sum[2] += l.z as f64;
        true
    } else {
        *rejected += 1;
        false
    }
}

/// The camera-sample loop of integrators that estimate every pixel on its own: for each
/// pass, each wanted tile pixel (row-major) and each sample index, starts the pixel's
/// sampler, draws a film point inside the pixel, (with a lens) a lens point and (when the
/// scene moves within the shutter) a time, and accumulates
/// `radiance(origin, dir, time, sampler)`. A scene without motion draws no time, so its
/// samples are those it has without a shutter.
///
/// Box reconstruction: the sample stays inside its pixel, so tiles are independent.
fn render_camera_samples(
    scene: &RenderScene,
    stream: SampleStream,
    plan: &FramePlan,
    unit: WorkUnit,
    wanted: impl Fn(usize, u32) -> bool,
    mut radiance: impl FnMut(Vec3, Vec3, f32, &mut PixelSampler) -> Vec3,
) -> UnitResult {
    let rect = plan.tile(unit.tile);
    let pixels = (rect.width * rect.height) as usize;
    let spp = plan.samples_per_pass;
    let lens = scene.camera.has_lens();
    let motion = scene.has_motion();
    let mut rejected_samples = 0u64;
    let mut pass_means = Vec::with_capacity(pixels * unit.pass_count as usize);
    for pass in unit.first_pass..unit.first_pass + unit.pass_count {
        for y in rect.y0..rect.y0 + rect.height {
            for x in rect.x0..rect.x0 + rect.width {
                let pixel = y * plan.width + x;
                if !wanted(((y - rect.y0) * rect.width + (x - rect.x0)) as usize, pass) {
                    pass_means.push([0.0; 3]);
                    continue;
                }
                let mut sampler =
                    PixelSampler::new(stream.sampler, stream.seed, unit.frame, pixel, pass);
                let mut sum = [0.0f64; 3];
                for i in 0..spp {
                    sampler.start_sample(i);
                    let film = Vec2::new(x as f32, y as f32) + sampler.next_2d();
                    let lens_u = if lens { sampler.next_2d() } else { Vec2::ZERO };
                    let (o, d, time) = if motion {
                        // The shutter is a box: the time is uniform over it.
                        let time = sampler.next_1d();
                        let (o, d) = scene.camera_at(time).generate_ray(film, lens_u);
                        (o, d, time)
                    } else {
                        let (o, d) = scene.camera.generate_ray(film, lens_u);
                        (o, d, 0.0)
                    };
                    let l = radiance(o, d, time, &mut sampler);
                    accumulate(&mut sum, l, &mut rejected_samples);
                }
                let inv = 1.0 / spp as f64;
                pass_means.push([
                    (sum[0] * inv) as f32,
                    (sum[1] * inv) as f32,
                    (sum[2] * inv) as f32,
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

/// Where a technique's random walks draw their numbers: a [`PixelSampler`] (the
/// per-pixel randomized point sets) or a Markov chain's primary sample vector
/// ([`mlt`]). Walks generic over it are monomorphic, so a `PixelSampler` caller's
/// values are exactly those of a walk that took `&mut PixelSampler`.
pub(crate) trait SampleSource {
    /// The next 1D value of the sample, in `[0, 1)`.
    fn next_1d(&mut self) -> f32;
    /// The next 2D value of the sample, each component in `[0, 1)`.
    fn next_2d(&mut self) -> Vec2;
}

impl SampleSource for PixelSampler {
    #[inline]
    fn next_1d(&mut self) -> f32 {
        PixelSampler::next_1d(self)
    }
    #[inline]
    fn next_2d(&mut self) -> Vec2 {
        PixelSampler::next_2d(self)
    }
}

/// A technique whose light subpaths splat onto any pixel of the frame (bdpt, vcm) or whose
/// estimate reads the whole pass's photon map (vcm, ppm): it
/// renders whole-frame units through [`render_whole_frame`], which owns the pixel and
/// sample loops and the order of the sums.
pub(crate) trait WholeFrame {
    /// Prepares pass `pass` before its first pixel (vcm builds the pass's photon map).
    fn begin_pass(&mut self, pass: u32);

    /// One sample of pixel `(x, y)`: the light subpath from `ls` and, where the pixel is
    /// traced, the camera subpath from `cs` (both samplers already started at the sample).
    /// Light-tracing contributions go to `splat(raster position, radiance)` in the order
    /// they are made; returns the camera subpath's estimate (zero without `cs`).
    fn sample(
        &mut self,
        x: u32,
        y: u32,
        ls: &mut PixelSampler,
        cs: Option<&mut PixelSampler>,
        splat: &mut impl FnMut(Vec2, Vec3),
    ) -> Vec3;

    /// Whether the technique is biased and estimates its bias per sample (vertex merging,
    /// [`vcm`]): the unit then carries [`UnitResult::bias`]. False by default.
    fn estimates_bias(&self) -> bool {
        false
    }

    /// The bias estimate (luminance, signed) of the camera estimate the last
    /// [`WholeFrame::sample`] returned; 0 by default.
    fn sample_bias(&self) -> f64 {
        0.0
    }
}

/// The sample loop of whole-frame techniques (docs in [`bdpt`]'s module): for each pass,
/// every pixel of the frame row-major traces `spp` light subpaths from the stream
/// `light_seed`; tile pixels where `wanted(i, pass)` holds also trace camera subpaths.
/// A sample's splats that land in the tile are summed first, then its camera estimate, in
/// `f64`: that order is part of the determinism contract. Invalid contributions are
/// dropped and counted in `rejected_samples`. An unwanted pixel's pass mean holds only the
/// splats that landed in it.
pub(crate) fn render_whole_frame(
    technique: &mut impl WholeFrame,
    light_seed: u64,
    stream: SampleStream,
    plan: &FramePlan,
    unit: WorkUnit,
    wanted: impl Fn(usize, u32) -> bool,
) -> UnitResult {
    let rect = plan.tile(unit.tile);
    let (tw, th) = (rect.width, rect.height);
    let pixels = rect.pixel_count();
    let spp = plan.samples_per_pass;
    let kind = stream.sampler;
    let mut sum = vec![[0.0f64; 3]; pixels];
    let mut pass_means = Vec::with_capacity(pixels * unit.pass_count as usize);
    let mut rejected_samples = 0u64;
    // The bias channel: per tile pixel, the sum of its camera samples' bias estimates,
    // beside (never inside) the radiance sums, so the pass means keep their bits.
    let biased = technique.estimates_bias();
    let mut bias_sum = vec![0.0f64; if biased { pixels } else { 0 }];
    let mut bias = biased.then(|| Vec::with_capacity(pixels * unit.pass_count as usize));
    // Index within the tile of pixel (x, y), if it is in the tile.
    let in_tile = |x: u32, y: u32| {
        (x >= rect.x0 && x < rect.x0 + tw && y >= rect.y0 && y < rect.y0 + th)
            .then(|| ((y - rect.y0) * tw + (x - rect.x0)) as usize)
    };
    for pass in unit.first_pass..unit.first_pass + unit.pass_count {
        technique.begin_pass(pass);
        sum.fill([0.0; 3]);
        bias_sum.fill(0.0);
        for y in 0..plan.height {
            for x in 0..plan.width {
                let pixel = y * plan.width + x;
                let mut ls = PixelSampler::new(kind, light_seed, unit.frame, pixel, pass);
                // A pixel the adaptive policy no longer wants traces no camera subpath (nor
                // its connections, the bulk of the cost), but its light subpath still runs:
                // its splats land on other pixels, which must get the same values as in a
                // render of every pixel.
                let traced = in_tile(x, y).filter(|&j| wanted(j, pass));
                let mut cs =
                    traced.map(|_| PixelSampler::new(kind, stream.seed, unit.frame, pixel, pass));
                for i in 0..spp {
                    ls.start_sample(i);
                    if let Some(cs) = cs.as_mut() {
                        cs.start_sample(i);
                    }
                    let camera_l = technique.sample(x, y, &mut ls, cs.as_mut(), &mut |r, l| {
                        let px = (r.x as u32).min(plan.width - 1);
                        let py = (r.y as u32).min(plan.height - 1);
                        if let Some(j) = in_tile(px, py) {
                            accumulate(&mut sum[j], l, &mut rejected_samples);
                        }
                    });
                    if let Some(j) = traced {
                        // A rejected sample counts as black: its bias estimate is dropped
                        // with it.
                        if accumulate(&mut sum[j], camera_l, &mut rejected_samples) && biased {
                            let b = technique.sample_bias();
                            if b.is_finite() {
                                bias_sum[j] += b;
                            }
                        }
                    }
                }
            }
        }
        let inv = 1.0 / spp as f64;
        pass_means.extend(sum.iter().map(|s| {
            [
                (s[0] * inv) as f32,
                (s[1] * inv) as f32,
                (s[2] * inv) as f32,
            ]
        }));
        if let Some(bias) = bias.as_mut() {
            let bound = f64::from(tessera_farm::MAX_PASS_MEAN);
            bias.extend(
                bias_sum
                    .iter()
                    .map(|b| (b * inv).clamp(-bound, bound) as f32),
            );
        }
    }
    UnitResult {
        unit,
        width: tw,
        height: th,
        pass_means,
        rejected_samples,
        bias,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn accumulate_adds_valid_radiance_and_counts_the_rest() {
        let mut sum = [0.0f64; 3];
        let mut rejected = 0;
        assert!(accumulate(
            &mut sum,
            Vec3::new(1.0, 2.0, 0.5),
            &mut rejected
        ));
        // -0.0 is valid (it compares equal to 0).
        assert!(accumulate(
            &mut sum,
            Vec3::new(-0.0, 0.0, 0.0),
            &mut rejected
        ));
        for bad in [
            Vec3::new(f32::NAN, 0.0, 0.0),
            Vec3::new(0.0, f32::INFINITY, 0.0),
            Vec3::new(0.0, 0.0, f32::NEG_INFINITY),
            Vec3::new(1.0, -1e-9, 1.0),
        ] {
            assert!(!accumulate(&mut sum, bad, &mut rejected), "{bad}");
        }
        assert_eq!(sum, [1.0, 2.0, 0.5]);
        assert_eq!(rejected, 4);
    }

    fn cornell(w: u32, h: u32) -> RenderScene {
        let scene = tessera_scene::load("builtin:cornell-box").unwrap();
        RenderScene::build(&scene, w, h).unwrap()
    }

    #[test]
    fn a_unit_reports_its_non_finite_samples() {
        // The camera-sample loop of `path` and `direct`, with an estimator that returns NaN
        // for every third sample it is asked for.
        let rs = cornell(8, 8);
        let plan = FramePlan::new(8, 8, 4, 4, 2).unwrap();
        let unit = plan.units(0, 2)[1];
        assert_eq!(unit.pass_count, 2);
        let mut calls = 0u64;
        let r = render_camera_samples(
            &rs,
            SampleStream::of(&RenderConfig::default()),
            &plan,
            unit,
            |i, _| i != 0, // tile pixel 0 is skipped: no samples, no rejects
            |_, _, _, _| {
                calls += 1;
                if calls.is_multiple_of(3) {
                    Vec3::NAN
                } else {
                    Vec3::ONE
                }
            },
        );
        // 15 wanted pixels x 2 passes x 4 samples.
        assert_eq!(calls, 120);
        assert_eq!(r.rejected_samples, 40);
        // A rejected sample counts as black: the means add up to the valid samples.
        let pixels = 16;
        let mut valid = 0.0;
        for (k, m) in r.pass_means.iter().enumerate() {
            if k % pixels == 0 {
                assert_eq!(*m, [0.0; 3]);
            } else {
                assert!(m[0] == 0.5 || m[0] == 0.75, "{m:?}");
                assert_eq!(m[0], m[1]);
                assert_eq!(m[0], m[2]);
            }
            valid += m[0] * 4.0;
        }
        assert_eq!(valid, 80.0);
        r.validate(&plan).unwrap();
    }

    #[test]
    fn healthy_renders_reject_nothing() {
        let rs = cornell(8, 8);
        for integrator in [Integrator::Path, Integrator::Direct, Integrator::Bdpt] {
            let s = RenderConfig {
                integrator,
                ..RenderConfig::default()
            };
            let plan = FramePlan::whole_frame(8, 8, 8).unwrap();
            for unit in plan.units(0, 1) {
                let r = render_unit(&rs, &s, &plan, unit);
                assert_eq!(r.rejected_samples, 0, "{integrator}");
            }
        }
    }
}
