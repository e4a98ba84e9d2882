//! Jobs: submission (ARCHITECTURE.md §9, steps 2 to 6), status, the job list, cancel and
//! the convergence history.
//!
//! A job in memory (queued, running, or finished in this run) is described from its
//! [`JobRuntime`] and the scheduler; a job that finished before this coordinator started
//! is described from the store alone.

use tessera_api::{
    History, JobList, JobListQuery, JobSettings, JobState, JobStatus, ResolvedJob, ValidatedJob,
};
use tessera_farm::job::StopVerdict;
use tessera_farm::quote::{job_eta, AdaptiveEta, JobEta, JobProgress, TailClass};
use tessera_farm::{frame_state_bytes_with_bias, FramePlan, JobId, Progress, WorkerId};

use super::{Coordinator, MAX_PAGE};
use crate::error::{CoordError, CoordResult};
use crate::state::{now_ms, Farm, JobEntry, JobRuntime, Stop};
use crate::store::{FaultFilter, JobOrder, JobQuery, JobRecord, NewJob, TileSummary};

impl Coordinator {
    /// Accepts a job: validates it, resolves it against its scene, stores it, queues it.
    /// With an idempotency key already used, returns the job created then if the
    /// settings are the same (after defaults are filled in), and refuses with
    /// [`CoordError::Conflict`] naming the key otherwise. The flag is whether the job is
    /// new.
    pub async fn submit(
        &self,
        mut settings: JobSettings,
        idempotency_key: Option<String>,
    ) -> CoordResult<(JobStatus, bool)> {
        self.accepting_work()?;
        if let Some(k) = &idempotency_key {
            if k.is_empty() || k.len() > 200 || k.chars().any(char::is_control) {
                return Err(CoordError::invalid_field(
                    "idempotency-key",
                    "must be 1 to 200 printable characters",
                ));
            }
        }
        let job = settings.validate()?;
        canonical_environment(&mut settings, &job);
        // Held until the job is stored: its scene and environment image cannot be deleted
        // meanwhile.
        let _scene_kept = self.inner.scene_lock.read().await;
        let (scene, environment) = self.lit_scene(&job).await?;
        // Resolution also checks the adaptive settings against the plan (field `adaptive`).
        let settings_json = serde_json::to_string(&settings).map_err(CoordError::internal)?;
        let bytes = super::resume::scene_bytes(&self.inner.farm, &job.scene.source);
        let resolved = self
            .inner
            .technique
            .resolve(&job, settings_json.as_bytes(), scene, bytes, environment)
            .await?;
        self.check_memory(&job, &resolved)?;
        let created = now_ms();
        let (id, new) = self
            .inner
            .store
            .insert_job(NewJob {
                settings_json: settings_json.clone(),
                plan: resolved.plan,
                frames: job.frames,
                passes_per_unit: self.inner.cfg.passes_per_unit,
                priority: job.priority,
                scene_ref: job.scene.source.to_string(),
                name: job.name.clone(),
                idempotency_key: idempotency_key.clone(),
                created_unix_ms: created,
                render_plan_json: Some(resolved.render_plan.to_json()),
                error_estimate_caveat: resolved.error_estimate_caveat(),
            })
            .await?;
        if !new {
            // The same key with other settings is a different request: refuse it rather
            // than answer with a job the client did not ask for.
            let same = self
                .inner
                .store
                .get_job(id)
                .await?
                .is_some_and(|rec| rec.settings_json == settings_json);
            if !same {
                let key = idempotency_key.as_deref().unwrap_or_default();
                return Err(CoordError::Conflict {
                    field: "idempotency-key".into(),
                    message: format!(
                        "the key {key:?} was used for job {id} with other settings; \
                         use a new key for a new job"
                    ),
                });
            }
            return Ok((self.status(id).await?, false));
        }
        let black = resolved.black;
        {
            let mut farm = self.lock()?;
            if !black {
                let ppu = self.inner.cfg.passes_per_unit;
                add_to_scheduler(&mut farm, id, job.priority, &resolved, ppu)?;
                farm.jobs.insert(id, JobEntry::of(&resolved));
            }
            let rt = JobRuntime::new(settings, resolved, JobState::Queued, created);
            farm.runtime.insert(id, rt);
        }
        tracing::info!(job = id, black, "job accepted");
        self.work_changed(true);
        if black {
            // Nothing to trace: the plan found no light (ARCHITECTURE.md §4).
            self.set_state(id, JobState::Running, None).await?;
            self.set_state(id, JobState::Done, None).await?;
        }
        Ok((self.status(id).await?, true))
    }

    /// Refuses a job whose merge state cannot fit the memory budget: one frame, since
    /// frames are released as they complete (an adaptive frame once its policy has
    /// finished every tile, also at a restart: `resume::restore_adaptive`), and the frames
    /// that do not fit wait for that.
    pub(crate) fn check_memory(
        &self,
        job: &ValidatedJob,
        resolved: &ResolvedJob,
    ) -> CoordResult<()> {
        if resolved.black {
            return Ok(());
        }
        let adaptive = job.adaptive_settings().is_some();
        let per_frame =
            frame_state_bytes_with_bias(&resolved.plan, adaptive, resolved.estimates_bias());
        let needed = per_frame;
        let budget = self.inner.cfg.memory_budget;
        if needed <= budget {
            return Ok(());
        }
        let plan = &resolved.plan;
        let what = format!(
            "a {}x{}{} frame",
            plan.width,
            plan.height,
            if adaptive { " adaptive" } else { "" }
        );
        Err(CoordError::TooLarge(format!(
            "{what} needs {} of merge state in the coordinator, above its memory budget of {} \
             (--memory-budget); render fewer or smaller frames, or raise the budget",
            bytes(needed),
            bytes(budget)
        )))
    }

    /// The status of a job.
    pub async fn status(&self, id: JobId) -> CoordResult<JobStatus> {
        if let Some(s) = self.live_status(id)? {
            return Ok(s);
        }
        let rec = self
            .inner
            .store
            .get_job(id)
            .await?
            .ok_or_else(|| CoordError::job_not_found(id))?;
        self.stored_status(&rec).await
    }

    fn live_status(&self, id: JobId) -> CoordResult<Option<JobStatus>> {
        let farm = self.lock()?;
        Ok(farm.runtime.get(&id).map(|rt| status_of(&farm, id, rt)))
    }

    /// Status of a job that is no longer in memory (finished before a restart): built from
    /// the store.
    async fn stored_status(&self, rec: &JobRecord) -> CoordResult<JobStatus> {
        let store = &self.inner.store;
        let settings: JobSettings = serde_json::from_str(&rec.settings_json)
            .unwrap_or_else(|_| JobSettings::new(rec.scene_ref.clone()));
        let tiles = store.tile_summaries(rec.id).await?;
        let plan = rec.plan;
        let passes_done: u64 = tiles.iter().map(|t| u64::from(t.merged_passes)).sum();
        let rejected_samples: u64 = tiles.iter().map(|t| t.rejected_samples).sum();
        let frames_total = rec.frames.count() as u32;
        let tiles_total = u64::from(plan.tile_count()) * u64::from(frames_total);
        let passes_planned = tiles_total * u64::from(plan.passes);
        let history = store.list_history(rec.id).await?;
        let faults = store
            .count_faults(&FaultFilter {
                job: Some(rec.id),
                worker: None,
            })
            .await?;
        let pixels = f64::from(plan.width) * f64::from(plan.height) * f64::from(frames_total);
        let pixels_of = |t: &TileSummary| plan.get_tile(t.tile).map_or(0, |r| r.pixel_count());
        let samples: f64 = tiles
            .iter()
            .map(|t| pixels_of(t) as f64 * f64::from(t.merged_passes))
            .sum::<f64>()
            * f64::from(plan.samples_per_pass);
        let elapsed = match (rec.started_unix_ms, rec.finished_unix_ms) {
            (Some(s), Some(f)) => f.saturating_sub(s) as f64 / 1e3,
            (Some(s), None) => now_ms().saturating_sub(s) as f64 / 1e3,
            _ => 0.0,
        };
        let stops_early = settings.adaptive != "off"
            || settings.target_error.is_some()
            || settings.time_limit_seconds.is_some();
        // Stored settings were validated when accepted; an unknown spelling reads as off.
        let mode: tessera_farm::AdaptiveMode = settings.adaptive.parse().unwrap_or_default();
        let stop = Stop::of_stored(rec.state, rec.error.as_deref());
        let verdict = stop.filter(|_| stops_early).map(|stop| StopVerdict {
            time_limit: stop == Stop::TimeLimit,
            target: settings.target_error,
            estimate: history.last().and_then(|h| h.error_estimate),
            spp: plan.spp(),
            unbiased: mode == tessera_farm::AdaptiveMode::Unbiased,
            unsampled: StopVerdict::caveat_says_unsampled(rec.error_estimate_caveat.as_deref()),
        });
        let render_plan: Option<serde_json::Value> = rec
            .render_plan_json
            .as_deref()
            .and_then(|j| serde_json::from_str(j).ok());
        // The name the live status gave (`ResolvedJob::error_estimator_name`): a merging
        // integrator's render adds its bias term, uniform or adaptive.
        let biased = match settings
            .integrator
            .parse::<tessera_farm::job::IntegratorChoice>()
        {
            Ok(tessera_farm::job::IntegratorChoice::Fixed(i)) => i.is_biased(),
            _ => render_plan.as_ref().is_some_and(|p| {
                p.get("integrator").and_then(|i| i.as_str())
                    == Some(tessera_farm::job::PlannedIntegrator::Vcm.as_str())
            }),
        };
        let black = render_plan.as_ref().is_some_and(|p| {
            p.get("integrator").and_then(|i| i.as_str())
                == Some(tessera_farm::job::PlannedIntegrator::Black.as_str())
        });
        let current = tessera_farm::ErrorEstimator::for_mode(mode).name();
        let current = if biased && !black {
            format!("{current}; {}", tessera_farm::BIAS_TERM)
        } else {
            current.to_string()
        };
        // The estimate shown is the last stored history point's, computed by the build
        // that stored it: named as that build stored it (schema version 9), not as this
        // build would compute it. The robust scale's level changed on 2026-12-06, and the
        // estimates and the estimator's name with it, so an adaptive job finished before
        // showed its old-level estimate under the new name. A point stored by an older
        // build does not say which estimator computed it, and its name is not guessed.
        let estimate = history.last().and_then(|h| h.error_estimate);
        let estimator = match (&rec.error_estimator, estimate) {
            (Some(stored), _) => Some(stored.clone()),
            (None, Some(_)) => None,
            (None, None) => Some(current),
        };
        Ok(JobStatus {
            id: rec.id,
            name: rec.name.clone(),
            state: rec.state,
            scene: rec.scene_ref.clone(),
            target_error: settings.target_error,
            adaptive: settings.adaptive.clone(),
            settings,
            width: Some(plan.width),
            height: Some(plan.height),
            frames_total,
            // A job stopped by its time limit finished only the frames every tile of which
            // merged its planned passes; one that finished, every frame.
            frames_done: match stop {
                Some(Stop::TimeLimit) => complete_frames(&tiles, plan),
                Some(_) => frames_total,
                None => 0,
            },
            tiles_total,
            passes_planned,
            passes_done,
            spp_so_far: if pixels > 0.0 { samples / pixels } else { 0.0 },
            error_estimate: estimate,
            error_estimator: estimator,
            // Both as accepted (store schema 6); absent for jobs stored by older builds.
            error_estimate_caveat: rec.error_estimate_caveat.clone(),
            target_reached: verdict.and_then(|v| v.target_reached()),
            stop_reason: verdict.map(|v| v.summary()),
            elapsed_seconds: elapsed,
            eta_seconds: None,
            eta_low_seconds: None,
            eta_high_seconds: None,
            eta_tail_class: None,
            eta_note: None,
            created_unix_ms: rec.created_unix_ms,
            started_unix_ms: rec.started_unix_ms,
            finished_unix_ms: rec.finished_unix_ms,
            priority: rec.priority,
            faults,
            rejected_samples,
            // A done job's message is why it stopped (above), not an error.
            error: rec.error.clone().filter(|_| stop.is_none()),
            plan: render_plan,
        })
    }

    /// `GET /jobs`: a page of jobs, newest first.
    pub async fn list(&self, q: JobListQuery) -> CoordResult<JobList> {
        let cursor = match q.cursor.as_deref() {
            None | Some("") => None,
            Some(c) => Some(c.parse::<u64>().map_err(|_| {
                CoordError::invalid_field("cursor", format!("expected a job id, got {c:?}"))
            })?),
        };
        let limit = q.limit.unwrap_or(50);
        if !(1..=MAX_PAGE).contains(&limit) {
            return Err(CoordError::invalid_field(
                "limit",
                format!("must be between 1 and {MAX_PAGE}, got {limit}"),
            ));
        }
        let recs = self
            .inner
            .store
            .list_jobs(JobQuery {
                cursor,
                limit: limit + 1,
                state: q.state,
                order: JobOrder::NewestFirst,
            })
            .await?;
        let more = recs.len() > limit as usize;
        let mut jobs = Vec::with_capacity(limit as usize);
        for rec in recs.iter().take(limit as usize) {
            match self.live_status(rec.id)? {
                Some(s) => jobs.push(s),
                None => jobs.push(self.stored_status(rec).await?),
            }
        }
        let next_cursor = if more {
            jobs.last().map(|j| j.id.to_string())
        } else {
            None
        };
        Ok(JobList { jobs, next_cursor })
    }

    /// `DELETE /jobs/{id}`: stops leasing the job's units and tells workers to drop them.
    pub async fn cancel(&self, id: JobId) -> CoordResult<JobStatus> {
        let status = self.status(id).await?;
        if status.state.is_terminal() {
            return Ok(status);
        }
        self.lock()?.scheduler.cancel(id);
        self.set_state(id, JobState::Canceled, None).await?;
        tracing::info!(job = id, "job canceled");
        self.status(id).await
    }

    /// The convergence history of a job.
    pub async fn history(&self, id: JobId) -> CoordResult<History> {
        if let Some(points) = self.lock()?.runtime.get(&id).map(|rt| rt.history.clone()) {
            return Ok(History { points });
        }
        self.inner
            .store
            .get_job(id)
            .await?
            .ok_or_else(|| CoordError::job_not_found(id))?;
        let points = self.inner.store.list_history(id).await?;
        Ok(History { points })
    }
}

/// Puts a job's units in the scheduler's queue, adaptive or not.
pub(crate) fn add_to_scheduler(
    farm: &mut Farm,
    id: JobId,
    priority: i32,
    resolved: &ResolvedJob,
    passes_per_unit: u32,
) -> CoordResult<()> {
    let (plan, job) = (resolved.plan, &resolved.job);
    // The resolved job's settings: no pixel stops early where a light path class is
    // unsampled.
    match resolved.adaptive_settings() {
        Some(a) => {
            farm.scheduler
                .add_adaptive_job(id, priority, plan, job.frames.iter(), passes_per_unit, a)
                .map_err(|e| CoordError::invalid_field("adaptive", e))?;
        }
        None => farm
            .scheduler
            .add_job(id, priority, plan, job.frames.iter(), passes_per_unit),
    }
    // vcm and ppm keep the merging-bias channel beside the pixels' statistics.
    if resolved.estimates_bias() {
        farm.scheduler.count_bias_channel(id);
    }
    Ok(())
}

/// Frames whose every tile merged the plan's passes, from the stored tile summaries.
fn complete_frames(tiles: &[TileSummary], plan: FramePlan) -> u32 {
    let mut per_frame: std::collections::BTreeMap<u32, u32> = Default::default();
    for t in tiles.iter().filter(|t| t.merged_passes >= plan.passes) {
        *per_frame.entry(t.frame).or_default() += 1;
    }
    per_frame
        .values()
        .filter(|&&n| n >= plan.tile_count())
        .count() as u32
}

/// Samples per pixel merged so far.
pub(crate) fn spp_so_far(r: &ResolvedJob, passes_done: u64, frames: u64) -> f64 {
    // Tile passes weighted by tile area: with equal passes per pixel this is exact; the
    // status is informative, so a uniform-tile approximation is enough for partial frames.
    let tiles = u64::from(r.plan.tile_count()) * frames.max(1);
    if tiles == 0 {
        return 0.0;
    }
    passes_done as f64 / tiles as f64 * f64::from(r.plan.samples_per_pass)
}

/// The work the ETA counts as done: the merged passes, or if more, the planned passes in
/// the proportion of units rendered, buffered ones included.
///
/// Results merge in a fixed order (ARCHITECTURE.md §2), so a later pass rendered before
/// an earlier one waits in the tile's buffer: with whole-frame units (bdpt) one worker
/// renders passes 0, 1, ... while another renders 4, 5, ..., and the merged count lags
/// the work done by half. An ETA from merged passes alone then predicted two to four
/// times the job's actual length at 10% and 25% of it (docs/benchmarks.md, "The job status
/// ETA"). Units of a job hold equal numbers of passes (the last of a tile may hold
/// fewer), so their proportion is the work's.
///
/// The spot checks' second copies are work too: the work is the job's units plus its
/// copies, and the passes the ETA counts as done are the planned passes in the proportion
/// of that work rendered. A bdpt job of 8 whole-frame units one of which is spot-checked
/// renders 9 units; counted as 8 its ETA was 18-22% short (docs/benchmarks.md).
///
/// Units in flight count too, `in_flight_milli` thousandths of a unit
/// ([`in_flight_credit`]): a worker delivers a batch of units at once, so right after one
/// worker's batch arrives the others' (as far along) count nothing, and with a few large
/// units the rate then halves (a bdpt job's ETA said +64% to +78% at its first merge).
///
/// Returns (done, planned) in a common unit of work, `passes_planned x milli-units`, so
/// that no proportion is truncated (2 of 9 units of an 8-pass job are not 1 pass).
fn eta_work(
    progress: Option<Progress>,
    passes_done: u64,
    passes_planned: u64,
    in_flight_milli: u64,
) -> (u64, u64) {
    match progress {
        Some(p) if p.units_total > 0 => {
            let total = (u128::from(p.units_total) + u128::from(p.copies_total)) * 1000;
            let units = u128::from(p.units_done.min(p.units_total)) + u128::from(p.copies_done);
            let work = (units * 1000 + u128::from(in_flight_milli)).min(total);
            let rendered = u128::from(passes_planned) * work;
            // Merged passes exclude the copies: in the same proportion of the work.
            let merged = u128::from(passes_done) * u128::from(p.units_total) * 1000;
            let (mut done, mut planned) =
                (rendered.max(merged), u128::from(passes_planned) * total);
            // Both fit in 64 bits for any real job; halve both (keeping the ratio) if not.
            while planned > u128::from(u64::MAX) {
                (done, planned) = (done / 2, planned / 2);
            }
            (done as u64, planned as u64)
        }
        _ => (passes_done, passes_planned),
    }
}

/// The units of a job in flight, in thousandths, as far as their age says they are. A
/// worker renders one batch while it leases the next (the worker's pipeline), so per
/// worker: its oldest batch here (the leases issued with its oldest), rendering since that
/// lease or its last result, whichever is later, for `a` seconds, of `k` units of mean
/// time `u` (`JobRuntime::unit_seconds`), counts `min(a / u, 0.9 k)` units (one overdue
/// is not done until it arrives, hence at most 90%); a prefetched batch counts nothing.
/// Nothing before any unit's time is known. Conservative for workers that render a
/// batch's units in parallel.
fn in_flight_credit(farm: &Farm, job: JobId, unit_seconds: (f64, u64), now: u64) -> u64 {
    let (sum, n) = unit_seconds;
    if n == 0 || sum.is_nan() || sum <= 0.0 {
        return 0;
    }
    let mean = sum / n as f64;
    // Per worker: its oldest lease time and how many units it holds from then.
    let mut oldest: std::collections::BTreeMap<WorkerId, (u64, u64)> = Default::default();
    for (w, at) in farm.scheduler.in_flight(job) {
        let e = oldest.entry(w).or_insert((at, 0));
        if at < e.0 {
            *e = (at, 0);
        }
        if at == e.0 {
            e.1 += 1;
        }
    }
    oldest
        .iter()
        .map(|(w, &(at, k))| {
            let since = farm.workers.get(w).map_or(at, |e| at.max(e.last_result_ms));
            let age = now.saturating_sub(since) as f64 / 1e3;
            ((age / mean).min(0.9 * k as f64) * 1000.0) as u64
        })
        .sum()
}

/// The status of a job in memory.
fn status_of(farm: &Farm, id: JobId, rt: &JobRuntime) -> JobStatus {
    let now = now_ms();
    let plan = rt.resolved.plan;
    let frames_total = rt.job().frames.count() as u32;
    let tiles_total = u64::from(plan.tile_count()) * u64::from(frames_total);
    let passes_planned = tiles_total * u64::from(plan.passes);
    let progress = farm.scheduler.progress(id);
    let (passes_done, frames_done) = match (progress, rt.resolved.black) {
        (_, true) => (passes_planned, frames_total),
        (Some(p), false) => (p.passes_done, p.frames_done),
        (None, false) => (0, 0),
    };
    let elapsed = rt.elapsed_seconds(now);
    // An adaptive job's figures as of its last history point (a walk over every pixel),
    // kept when a finished job's state is evicted from memory.
    let adaptive = rt
        .job()
        .adaptive_settings()
        .map(|_| rt.adaptive_summary)
        .filter(|_| !rt.resolved.black);
    let error = if rt.resolved.black {
        Some(0.0)
    } else if let Some((_, e)) = adaptive {
        e
    } else {
        rt.error_estimate()
    };
    let eta = if rt.state.is_terminal() {
        Some(JobEta {
            seconds: Some(0.0),
            interval: None,
            tail_class: None,
            note: None,
        })
    } else {
        let credit = in_flight_credit(farm, id, rt.unit_seconds, now);
        let (eta_done, eta_planned) = eta_work(progress, passes_done, passes_planned, credit);
        job_eta(&JobProgress {
            // Since the first lease. Not from when the first merged unit began rendering
            // (its merge time less its render seconds, as before): a worker submits a
            // batch's results together, so that start was the batch's last unit's and the
            // rate too fast early on (-30% to -39% at 10% of veach-mis and a bdpt job,
            // docs/benchmarks.md); the workers' set-up it left out is small by comparison.
            elapsed_seconds: rt.elapsed_seconds(now),
            passes_done: eta_done,
            passes_planned: eta_planned,
            error,
            // On the farm only adaptive jobs stop at their target (ARCHITECTURE.md §3).
            stopping_target: adaptive.and(rt.job().target_error),
            time_limit_left_seconds: rt.job().time_limit_seconds.map(|l| l - elapsed),
            // The tail class of the passes merged so far, as the quote classes its pilot.
            trend: rt.eta_trend,
            // What ends an adaptive job: each pixel's own stop, as of the last history
            // point (ARCHITECTURE.md §3, "The ETA").
            adaptive: adaptive.and(rt.eta_adaptive).map(|(a, at)| AdaptiveEta {
                age_seconds: now.saturating_sub(at) as f64 / 1e3,
                ..a
            }),
        })
    };
    let eta_interval = eta.as_ref().and_then(|e| e.interval);
    let verdict = match rt.stopped {
        Some(stop) if rt.state == JobState::Done && rt.job().stops_early() => Some(StopVerdict {
            time_limit: stop == Stop::TimeLimit,
            target: rt.job().target_error,
            estimate: error,
            spp: plan.spp(),
            unbiased: rt.job().adaptive == tessera_farm::AdaptiveMode::Unbiased,
            unsampled: StopVerdict::unsampled_of(&rt.resolved),
        }),
        _ => None,
    };
    JobStatus {
        id,
        name: rt.job().name.clone(),
        state: rt.state,
        scene: rt.job().scene.source.to_string(),
        settings: rt.settings.clone(),
        width: Some(plan.width),
        height: Some(plan.height),
        frames_total,
        frames_done,
        tiles_total,
        passes_planned,
        passes_done,
        spp_so_far: match adaptive {
            Some((spp, _)) => spp,
            None => spp_so_far(&rt.resolved, passes_done, rt.job().frames.count()),
        },
        error_estimate: error,
        error_estimator: Some(rt.resolved.error_estimator_name()),
        error_estimate_caveat: rt.resolved.error_estimate_caveat(),
        target_error: rt.job().target_error,
        target_reached: verdict.and_then(|v| v.target_reached()),
        stop_reason: verdict.map(|v| v.summary()),
        elapsed_seconds: elapsed,
        eta_seconds: eta.as_ref().and_then(|e| e.seconds),
        eta_low_seconds: eta_interval.map(|i| i.0),
        eta_high_seconds: eta_interval.map(|i| i.1),
        eta_tail_class: eta
            .as_ref()
            .and_then(|e| e.tail_class)
            .map(|c| tail_class_name(c).to_string()),
        eta_note: eta.and_then(|e| e.note),
        created_unix_ms: rt.created_unix_ms,
        started_unix_ms: rt.started_unix_ms,
        finished_unix_ms: rt.finished_unix_ms,
        priority: rt.job().priority,
        faults: rt.faults,
        rejected_samples: rt.rejected_samples(),
        error: rt.error.clone(),
        plan: rt.plan_json.clone(),
        adaptive: rt.job().adaptive.to_string(),
    }
}

/// The status's spelling of a tail class (`eta_tail_class`), as a quote's JSON spells it.
fn tail_class_name(c: TailClass) -> &'static str {
    match c {
        TailClass::Light => "light",
        TailClass::Heavy => "heavy",
        TailClass::Unpredictable => "unpredictable",
    }
}

/// A byte count for people, in binary units: "64.0 MiB", "18.0 GiB".
pub(crate) fn bytes(n: u64) -> String {
    const UNITS: [&str; 5] = ["B", "KiB", "MiB", "GiB", "TiB"];
    let mut v = n as f64;
    let mut u = 0;
    while v >= 1024.0 && u + 1 < UNITS.len() {
        v /= 1024.0;
        u += 1;
    }
    if u == 0 {
        format!("{n} B")
    } else {
        format!("{v:.1} {}", UNITS[u])
    }
}

/// Writes an environment image's hash in the settings as validation reads it (lower case,
/// trimmed), so the stored settings name the stored file exactly: the store finds the
/// unfinished jobs that need an image by that text (`store::scene_quota`).
pub(crate) fn canonical_environment(settings: &mut JobSettings, job: &ValidatedJob) {
    use tessera_farm::job::EnvironmentSource;
    if let (Some(e), Some(raw)) = (&job.environment, settings.environment.as_mut()) {
        if let EnvironmentSource::Image(h) = &e.source {
            raw.source = h.clone();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn byte_counts_read_in_binary_units() {
        assert_eq!(bytes(512), "512 B");
        assert_eq!(bytes(64 << 20), "64.0 MiB");
        assert_eq!(bytes(16384 * 16384 * 72), "18.0 GiB");
    }
}
