//! Resolving a validated job against its scene: the render plan turns `auto` into
//! concrete settings, and the frame plan follows from the scene's resolution.
//!
//! `tessera render` and the coordinator both call [`ValidatedJob::resolve`], so a job
//! gives the same settings, the same frame plan and the same EXR metadata
//! ([`ResolvedJob::metadata_json`]) however it is rendered: locally or through the farm
//! (ARCHITECTURE.md §2).

use super::choice::{Integrator, IntegratorChoice};
use super::plan::{json_string, PlannedIntegrator, RenderPlan};
use super::settings::{JobError, RenderConfig, ValidatedJob, DEFAULT_MAX_DEPTH, DEFAULT_RR_DEPTH};
use crate::merge::FrameImage;
use crate::plan::FramePlan;

/// What resolution needs to know of a scene, besides its render plan.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SceneFacts {
    /// The image size the scene asks for (from its camera), used for missing dimensions.
    pub default_resolution: (u32, u32),
}

/// A job resolved against its scene: what every worker renders.
#[derive(Debug, Clone, PartialEq)]
pub struct ResolvedJob {
    /// The validated job it came from.
    pub job: ValidatedJob,
    /// Concrete render settings.
    pub config: RenderConfig,
    /// The frame plan for the resolved resolution.
    pub plan: FramePlan,
    /// The scene analysis, with `overridden` set when the job forced other settings.
    pub render_plan: RenderPlan,
    /// The plan found no light: the image is black and nothing needs tracing.
    pub black: bool,
}

impl ValidatedJob {
    /// Resolves this job against its scene's facts and render plan
    /// (`tessera_scene::analysis::analyse`).
    ///
    /// With `integrator` auto the render plan decides: black (no light), direct lighting
    /// with one bounce, path, mnee, bdpt, vcm or mlt with the plan's depth and Russian roulette depth. An
    /// explicit integrator uses the general configuration (depth [`DEFAULT_MAX_DEPTH`],
    /// roulette from [`DEFAULT_RR_DEPTH`]) and is recorded as an override, as is a
    /// `max_depth` other than the one chosen. Adaptive settings are checked against the
    /// frame plan (an unbiased pilot needs room for fresh passes): errors of `adaptive`.
    pub fn resolve(
        &self,
        scene: SceneFacts,
        mut render_plan: RenderPlan,
    ) -> Result<ResolvedJob, JobError> {
        let (width, height) = self.resolution(scene.default_resolution);
        let mut forced = Vec::new();
        let mut black = false;
        let (integrator, plan_depth, rr_depth) = match self.render.integrator {
            IntegratorChoice::Auto => match render_plan.integrator {
                PlannedIntegrator::Black => {
                    black = true;
                    // Nothing is traced; these settings only fill the metadata.
                    (Integrator::Direct, 1, render_plan.rr_depth)
                }
                PlannedIntegrator::Direct => (Integrator::Direct, 1, render_plan.rr_depth),
                PlannedIntegrator::Path => (
                    Integrator::Path,
                    render_plan.max_depth,
                    render_plan.rr_depth,
                ),
                PlannedIntegrator::Bdpt => (
                    Integrator::Bdpt,
                    render_plan.max_depth,
                    render_plan.rr_depth,
                ),
                PlannedIntegrator::Vcm => {
                    (Integrator::Vcm, render_plan.max_depth, render_plan.rr_depth)
                }
                PlannedIntegrator::Mlt => {
                    (Integrator::Mlt, render_plan.max_depth, render_plan.rr_depth)
                }
                PlannedIntegrator::Mnee => (
                    Integrator::Mnee,
                    render_plan.max_depth,
                    render_plan.rr_depth,
                ),
            },
            IntegratorChoice::Fixed(i) => {
                forced.push(format!("--integrator {i}"));
                (i, DEFAULT_MAX_DEPTH, DEFAULT_RR_DEPTH)
            }
        };
        if let Some(d) = self.render.max_depth {
            if d != plan_depth {
                forced.push(format!("--max-depth {d}"));
            }
        }
        if !forced.is_empty() {
            render_plan.set_override(&forced.join(" "));
        }
        let config = RenderConfig {
            integrator,
            mis: self.render.mis,
            sampler: self.render.sampler,
            seed: self.render.seed,
            max_depth: self.render.max_depth.unwrap_or(plan_depth),
            rr_depth,
        };
        config.validate()?;
        // The frame plan follows the resolved integrator: bdpt, chosen by the plan or
        // asked for, gets one whole-frame tile.
        let plan = self.plan_for(integrator.into(), width, height)?;
        if let Some(a) = self.adaptive_settings() {
            a.validate(plan.passes)
                .map_err(|e| JobError::new("adaptive", e))?;
        }
        Ok(ResolvedJob {
            job: self.clone(),
            config,
            plan,
            render_plan,
            black,
        })
    }
}

/// How a render that may stop early ended: why it stopped and whether it reached its
/// target error. A summary, status or EXR header never claims a target the image did not
/// reach: the verdict is read from the image's own error estimate, not from the fact that
/// the adaptive policy finished (its pixels may have run out of passes first).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StopVerdict {
    /// The job's time limit stopped it.
    pub time_limit: bool,
    /// The job's target error, if it has one.
    pub target: Option<f64>,
    /// The image's error estimate when it stopped ([`FrameImage::error_estimate`]; for a
    /// job of several frames, over all of them); `None` while a pixel has fewer than 2
    /// passes.
    pub estimate: Option<f64>,
    /// The job's sample budget per pixel (`spp`), named when it ran out first.
    pub spp: u32,
    /// The job used the unbiased adaptive mode: its fresh passes were planned from a pilot
    /// and it adds none after the plan (`crate::AdaptiveMode::Unbiased`), so a render that
    /// ends above its target ended because its plan was done, not only because of the
    /// budget.
    pub unbiased: bool,
    /// The integrator cannot sample a light path class of the scene
    /// ([`crate::job::RenderPlan::unsampled`]): the estimate does not see the missing
    /// light, so the target never counts as reached.
    pub unsampled: bool,
}

impl StopVerdict {
    /// The verdict on `image` of `job`, stopped by its time limit or not.
    pub fn of_image(job: &ResolvedJob, image: &FrameImage, time_limit: bool) -> Self {
        Self {
            time_limit,
            target: job.job.target_error,
            estimate: image.error_estimate(job.error_estimator()),
            spp: job.plan.spp(),
            unbiased: job.job.adaptive == crate::AdaptiveMode::Unbiased,
            unsampled: Self::unsampled_of(job),
        }
    }

    /// Whether `job`'s integrator cannot sample a light path class its scene has (the
    /// [`StopVerdict::unsampled`] of any verdict on it).
    pub fn unsampled_of(job: &ResolvedJob) -> bool {
        !job.black && job.render_plan.unsampled(job.config.integrator).is_some()
    }

    /// Whether a stored error estimate caveat marks a job whose integrator cannot sample a
    /// light path class of its scene (it starts with
    /// [`crate::job::plan::UNSAMPLED_CAVEAT`]): for [`StopVerdict::unsampled`] where only
    /// the stored caveat is at hand.
    pub fn caveat_says_unsampled(caveat: Option<&str>) -> bool {
        caveat.is_some_and(|c| c.starts_with(super::plan::UNSAMPLED_CAVEAT))
    }

    /// Whether the estimate is at or below the target; `None` without a target. Never
    /// `Some(true)` when the integrator cannot sample every light path class of the scene
    /// ([`StopVerdict::unsampled`]): an estimate blind to missing light is no evidence.
    pub fn target_reached(&self) -> Option<bool> {
        self.target
            .map(|t| !self.unsampled && self.estimate.is_some_and(|e| e <= t))
    }

    /// Why the render ended, in the words `tessera render` prints after `stopped:`:
    /// `"time limit reached"`, `"target error reached"` or `"finished"` (every pass done,
    /// or every pixel converged or out of passes, without the image reaching a target).
    pub fn stopped(&self) -> &'static str {
        if self.time_limit {
            "time limit reached"
        } else if self.target_reached() == Some(true) {
            "target error reached"
        } else {
            "finished"
        }
    }

    /// Why it stopped and, with a target, whether it was reached: [`StopVerdict::describe`]
    /// when there is a target, [`StopVerdict::stopped`] otherwise.
    pub fn summary(&self) -> String {
        self.describe()
            .unwrap_or_else(|| self.stopped().to_string())
    }

    /// One line on the target for summaries and statuses, e.g. "target error 0.03 not
    /// reached: the estimate is 0.0362 when the sample budget (4096 spp) ran out" (an
    /// unbiased adaptive render: "... when the passes its pilot planned (within the sample
    /// budget of 4096 spp) were done", since the two-stage scheme adds no passes after its
    /// plan, whatever its estimate says); `None` without a target.
    pub fn describe(&self) -> Option<String> {
        let t = self.target?;
        let estimate = self.estimate.map_or("no estimate yet".to_string(), |e| {
            format!("the estimate is {e:.4}")
        });
        Some(match self.target_reached() {
            Some(true) => format!("target error {t} reached ({estimate})"),
            _ if self.unsampled => format!(
                "target error {t} not reached: {estimate}, but the integrator cannot sample \
                 every light path of the scene (see the error estimate caveat)"
            ),
            _ if self.time_limit => {
                format!("target error {t} not reached: {estimate} when the time limit ran out")
            }
            _ if self.unbiased => format!(
                "target error {t} not reached: {estimate} when the passes its pilot planned \
                 (within the sample budget of {} spp) were done",
                self.spp
            ),
            _ => format!(
                "target error {t} not reached: {estimate} when the sample budget ({} spp) ran out",
                self.spp
            ),
        })
    }
}

impl ResolvedJob {
    /// The adaptive policy's settings for this job ([`ValidatedJob::adaptive_settings`]),
    /// except where its integrator cannot sample a light path class of the scene
    /// ([`StopVerdict::unsampled_of`]): there the pixels that no pass lit (light the
    /// technique cannot find) have an estimate of zero and would stop as converged at the
    /// first decision, so no pixel may stop early: sequential decisions start after the
    /// last pass (`min_passes` past the plan), and unbiased gives every pixel every fresh
    /// pass (`min_fresh_passes` the plan's remainder). The job runs its whole budget (or
    /// until its time limit), and its verdict says the target was not reached. Every
    /// runner of the policy (`tessera render`, the scheduler, restores from checkpoints,
    /// image encodes) must take the settings from here, so that they decide alike.
    pub fn adaptive_settings(&self) -> Option<crate::adaptive::AdaptiveSettings> {
        let a = self.job.adaptive_settings()?;
        if !StopVerdict::unsampled_of(self) {
            return Some(a);
        }
        let passes = self.plan.passes;
        Some(match a.mode {
            crate::AdaptiveMode::Sequential => crate::adaptive::AdaptiveSettings {
                min_passes: passes.saturating_add(1).max(a.min_passes),
                ..a
            },
            crate::AdaptiveMode::Unbiased => crate::adaptive::AdaptiveSettings {
                min_fresh_passes: passes.saturating_sub(a.min_passes).max(a.min_fresh_passes),
                ..a
            },
            crate::AdaptiveMode::Off => a,
        })
    }

    /// The render settings, the stopping settings and the render plan as one JSON object
    /// for the EXR header, with a stable key order, so that a farm render and a local
    /// render of the same job write byte-identical files. A black render (no light) has
    /// integrator `"black"`. Jobs that stop early ([`ValidatedJob::stops_early`]) start
    /// with `adaptive`, `target_error`, `min_passes`, `interval`, `time_limit`, `stopped`
    /// (why the render ended, [`StopVerdict::stopped`]), `target_reached` (whether the
    /// image's estimate is at or below `target_error`; `null` without a target) and
    /// `error_reached` (the image's estimate, [`FrameImage::error_estimate`]); the last
    /// three are `null` while it runs. Every header names the error estimator of its
    /// variance layers and estimate (`error_estimator`, [`ResolvedJob::error_estimator`]); a job
    /// whose estimate may be optimistic ends with `error_estimate_caveat` saying why
    /// ([`ResolvedJob::error_estimate_caveat`]). The text is ASCII.
    pub fn metadata_json(&self, stopped: Option<&StopVerdict>) -> String {
        let job = &self.job;
        let c = &self.config;
        let integrator = if self.black {
            "black"
        } else {
            c.integrator.as_str()
        };
        let mut out = String::from("{");
        if job.stops_early() {
            let interval = crate::adaptive::AdaptiveSettings::default().interval;
            out += &format!(
                "\"adaptive\":\"{}\",\"target_error\":{},\"min_passes\":{},\"interval\":{interval},\"time_limit\":{},\"stopped\":{},\"target_reached\":{},\"error_reached\":{},",
                job.adaptive,
                job.target_error.map_or("null".to_string(), |e| e.to_string()),
                job.min_passes,
                job.time_limit_seconds.map_or("null".to_string(), |t| t.to_string()),
                stopped.map_or("null".to_string(), |v| json_string(v.stopped())),
                stopped
                    .and_then(StopVerdict::target_reached)
                    .map_or("null".to_string(), |r| r.to_string()),
                stopped
                    .and_then(|v| v.estimate)
                    .map_or("null".to_string(), |e| e.to_string()),
            );
        }
        let p = &self.plan;
        // Only a named camera is recorded: the default camera adds nothing.
        let camera = job
            .scene
            .camera
            .as_deref()
            .map_or(String::new(), |c| format!(",\"camera\":{}", json_string(c)));
        // Time settings only when they differ from the default (every animation at 24
        // frames per second), so static jobs keep the header they always had.
        let mut camera = camera;
        if job.scene.fps != super::settings::DEFAULT_FPS {
            camera += &format!(",\"fps\":{}", job.scene.fps);
        }
        if let Some(a) = &job.scene.animation {
            camera += &format!(",\"animation\":{}", json_string(a));
        }
        if let Some(s) = &job.scene.shutter {
            camera += &format!(",\"shutter\":[{},{}]", s.open, s.close);
        }
        // Only when set, so jobs without one keep the header they always had.
        if let Some(e) = &job.environment {
            camera += &format!(",\"environment\":{}", e.metadata_json());
        }
        // Only where it applies, so other jobs keep the header they always had.
        let caveat = self.error_estimate_caveat().map_or(String::new(), |c| {
            format!(",\"error_estimate_caveat\":{}", json_string(&c))
        });
        out += &format!(
            "\"scene\":{}{camera},\"width\":{},\"height\":{},\"spp\":{},\"samples_per_pass\":{},\"passes\":{},\"integrator\":\"{integrator}\",\"mis\":\"{}\",\"sampler\":\"{}\",\"seed\":{},\"max_depth\":{},\"rr_depth\":{},\"error_estimator\":{},\"plan\":{}{caveat}}}",
            json_string(&job.scene.source.to_string()),
            p.width,
            p.height,
            p.spp(),
            p.samples_per_pass,
            p.passes,
            c.mis,
            c.sampler,
            c.seed,
            c.max_depth,
            c.rr_depth,
            json_string(&self.error_estimator_name()),
            self.render_plan.to_json()
        );
        out
    }

    /// The image error estimate this job reports ([`crate::ErrorEstimator::for_mode`] of
    /// its adaptive mode).
    pub fn error_estimator(&self) -> crate::ErrorEstimator {
        crate::ErrorEstimator::for_mode(self.job.adaptive)
    }

    /// Whether this job's image carries bias layers and its estimate the bias term
    /// ([`crate::UnitResult::bias`], [`crate::ErrorEstimator::image_error_biased`]): a
    /// biased integrator (vcm, ppm), with or without adaptive stopping (the adaptive
    /// policy keeps each pixel's bias statistics over the passes it keeps,
    /// [`crate::AdaptiveTile::bias`]).
    pub fn estimates_bias(&self) -> bool {
        !self.black && self.config.integrator.is_biased()
    }

    /// The name of this job's error estimate, as the EXR header (`error_estimator`), the
    /// job status and `tessera render` give it: [`crate::ErrorEstimator::name`], followed
    /// by "; " and [`crate::BIAS_TERM`] when [`ResolvedJob::estimates_bias`].
    pub fn error_estimator_name(&self) -> String {
        let name = self.error_estimator().name();
        if self.estimates_bias() {
            format!("{name}; {}", crate::BIAS_TERM)
        } else {
            name.to_string()
        }
    }

    /// Why this job's error estimate may be optimistic, or `None`: for the integrator it
    /// renders with ([`crate::job::RenderPlan::error_estimate_caveat`]) and, for an
    /// adaptive job, for its stopping
    /// ([`crate::job::RenderPlan::adaptive_error_estimate_caveat`]), joined by "; ".
    pub fn error_estimate_caveat(&self) -> Option<String> {
        if self.black {
            return None;
        }
        let integrator = self
            .render_plan
            .error_estimate_caveat(self.config.integrator);
        let adaptive = (self.job.adaptive != super::choice::AdaptiveMode::Off)
            .then(|| self.render_plan.adaptive_error_estimate_caveat())
            .flatten();
        match (integrator, adaptive) {
            (Some(a), Some(b)) => Some(format!("{a}; {b}")),
            (a, b) => a.or(b),
        }
    }
}
