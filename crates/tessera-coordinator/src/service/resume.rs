//! Restart: jobs in the store brought back into memory (ARCHITECTURE.md §9, "Restart,
//! resume and the grace period").
//!
//! Two rules are written once here and used by both the restart and the images of jobs
//! that finished before it: `resolve_stored` turns a stored job into a resolved one
//! (parse the stored settings, validate, load the scene, resolve), and
//! `restore_frames` rebuilds frame accumulators from tile checkpoints, bit-exact.

use std::sync::{Arc, Mutex};

use tessera_api::{JobSettings, JobState, ResolvedJob};
use tessera_farm::job::JobError;
use tessera_farm::job::SceneRef;
use tessera_farm::{
    AdaptiveFrame, AdaptiveSettings, AdaptiveTileCheckpoint, FrameAccumulator, FramePlan, JobId,
    Resumed,
};

use super::jobs::add_to_scheduler;
use super::scenes::{load_lit_scene, SceneLoadError};
use super::technique::TechniquePilots;
use crate::error::CoordError;
use crate::state::{now_ms, tile_error, Farm, JobEntry, JobRuntime, Stop, TileRejected};
use crate::store::{
    FaultFilter, JobRecord, Store, StoreError, TileCheckpoint, MAX_RESUMES_WITHOUT_PROGRESS,
};
use tessera_scene::job::ResolveError;

/// A stored job as this build understands it.
pub(crate) struct StoredJob {
    /// The settings as submitted.
    pub settings: JobSettings,
    /// The job validated and resolved again against its scene.
    pub resolved: ResolvedJob,
}

/// Why a stored job cannot be resolved again. The text is what a job that cannot be
/// resumed fails with (`JobStatus.error`, stored); requests see a [`CoordError`].
#[derive(Debug, thiserror::Error)]
pub(crate) enum StoredJobError {
    /// The stored settings are not JSON this build reads.
    #[error("stored settings are unreadable: {error}")]
    Unreadable {
        /// The job.
        job: JobId,
        /// The parser's complaint.
        error: serde_json::Error,
    },
    /// The settings no longer validate, or no longer resolve against the scene.
    #[error("{0}")]
    Invalid(#[from] JobError),
    /// The scene is gone or no longer loads.
    #[error(transparent)]
    Scene(#[from] SceneLoadError),
    /// The technique pilot failed ([`super::technique`]).
    #[error("{0}")]
    Pilot(String),
}

impl From<ResolveError> for StoredJobError {
    fn from(e: ResolveError) -> Self {
        match e {
            ResolveError::Job(e) => Self::Invalid(e),
            e @ ResolveError::Pilot(_) => Self::Pilot(e.to_string()),
        }
    }
}

impl From<StoredJobError> for CoordError {
    fn from(e: StoredJobError) -> Self {
        match e {
            StoredJobError::Unreadable { job, error } => {
                CoordError::Internal(format!("stored settings of job {job}: {error}"))
            }
            StoredJobError::Invalid(e) => e.into(),
            StoredJobError::Scene(e) => e.into(),
            StoredJobError::Pilot(e) => CoordError::InvalidScene(e),
        }
    }
}

/// The stored job -> resolved job chain: parse the stored settings, validate them, load
/// the scene (lit by the job's environment), resolve (the same resolution as `POST /jobs` and `tessera render`,
/// ARCHITECTURE.md §1).
pub(crate) async fn resolve_stored(
    store: &dyn Store,
    farm: &Mutex<Farm>,
    pilots: &Arc<TechniquePilots>,
    rec: &JobRecord,
) -> Result<StoredJob, StoredJobError> {
    let settings: JobSettings = serde_json::from_str(&rec.settings_json)
        .map_err(|error| StoredJobError::Unreadable { job: rec.id, error })?;
    let job = settings.validate()?;
    let (scene, environment) = load_lit_scene(store, farm, &job).await?;
    let bytes = scene_bytes(farm, &job.scene.source);
    let resolved = pilots
        .resolve(
            &job,
            rec.settings_json.as_bytes(),
            scene,
            bytes,
            environment,
        )
        .await?;
    Ok(StoredJob { settings, resolved })
}

/// The bytes of an uploaded scene in memory (`load_scene` keeps them); `None` for a
/// built-in scene.
pub(crate) fn scene_bytes(farm: &Mutex<Farm>, scene: &SceneRef) -> Option<Arc<Vec<u8>>> {
    match scene {
        SceneRef::Builtin(_) => None,
        SceneRef::Hash(h) => farm.lock().ok()?.scenes.get(h).cloned(),
    }
}

/// Frames rebuilt from tile checkpoints.
pub(crate) struct Restored {
    /// One accumulator per frame, in the order asked for.
    pub frames: Vec<FrameAccumulator>,
    /// Per frame (number, per tile): the rejected samples of the merged passes.
    pub rejected: Vec<(u32, Vec<u64>)>,
    /// Per frame, per tile: the adaptive policy's state saved with the tile (adaptive
    /// jobs; `None` where the tile has no checkpoint or its checkpoint none).
    pub policy: Vec<Vec<Option<AdaptiveTileCheckpoint>>>,
    /// Whether some checkpoint has merged passes but no policy state: an adaptive job's
    /// checkpoint written before schema version 4, whose policy cannot be restored.
    pub without_policy: bool,
}

/// What a restart keeps of a complete frame: per tile, its rejected samples and its
/// (sum of squared relative errors, pixel count) for the job's error estimate.
struct CompleteFrame {
    frame: u32,
    rejected: Vec<u64>,
    errors: Vec<(f64, u64)>,
    /// Its image error estimate (`FrameAccumulator::image_error`, the status's).
    estimate: Option<f64>,
}

/// A job's frames that have checkpoints but are not complete, restored, and the
/// complete ones summarized; one frame at a time, so a restart holds the merge state of
/// the frames in progress only, whatever the job's length (ARCHITECTURE.md §6, memory).
async fn restore_incomplete(
    store: &dyn Store,
    rec: &JobRecord,
) -> Result<(Restored, Vec<CompleteFrame>), String> {
    let plan = rec.plan;
    let summaries = store
        .tile_summaries(rec.id)
        .await
        .map_err(|e| e.to_string())?;
    let tiles = plan.tile_count() as usize;
    // frame -> per tile (merged passes, rejected samples)
    let mut frames: std::collections::BTreeMap<u32, Vec<(u32, u64)>> = Default::default();
    for s in &summaries {
        let slots = frames.entry(s.frame).or_insert_with(|| vec![(0, 0); tiles]);
        if let Some(slot) = slots.get_mut(s.tile as usize) {
            *slot = (s.merged_passes, s.rejected_samples);
        }
    }
    let mut restored = Restored {
        frames: Vec::new(),
        rejected: Vec::new(),
        policy: Vec::new(),
        without_policy: false,
    };
    let mut complete = Vec::new();
    for (f, slots) in frames {
        let checkpoints = store
            .load_tiles(rec.id, Some(f))
            .await
            .map_err(|e| e.to_string())?;
        let mut one = restore_frames(plan, [f], checkpoints)?;
        if slots.iter().all(|&(m, _)| m >= plan.passes) {
            // Summarized and dropped: its image is read from the store when asked for.
            let (frame, rejected) = one.rejected.pop().unwrap_or((f, Vec::new()));
            let errors = one
                .frames
                .iter()
                .flat_map(|a| a.tiles().iter().map(tile_error))
                .collect();
            let estimate = one.frames.first().map(|a| a.image_error());
            complete.push(CompleteFrame {
                frame,
                rejected,
                errors,
                estimate,
            });
            continue;
        }
        restored.frames.append(&mut one.frames);
        restored.rejected.append(&mut one.rejected);
    }
    Ok((restored, complete))
}

/// An adaptive job's frames with checkpoints, one at a time: the unfinished
/// ones restored with their policy state, those whose policy had finished every tile
/// summarized and dropped (their images are restored from the store when asked for), so
/// a restart holds the frames in progress only, as a running job does after releasing
/// its finished frames. `None` when a checkpoint predates the policy state (the job then
/// starts over).
async fn restore_adaptive(
    store: &dyn Store,
    rec: &JobRecord,
    settings: AdaptiveSettings,
) -> Result<Option<(Restored, Vec<FinishedAdaptive>)>, String> {
    let summaries = store
        .tile_summaries(rec.id)
        .await
        .map_err(|e| e.to_string())?;
    let frames: std::collections::BTreeSet<u32> = summaries.iter().map(|s| s.frame).collect();
    let settings = settings.for_units(rec.passes_per_unit);
    let mut restored = Restored {
        frames: Vec::new(),
        rejected: Vec::new(),
        policy: Vec::new(),
        without_policy: false,
    };
    let mut finished = Vec::new();
    for f in frames {
        let checkpoints = store
            .load_tiles(rec.id, Some(f))
            .await
            .map_err(|e| e.to_string())?;
        let mut one = restore_frames(rec.plan, [f], checkpoints)?;
        if one.without_policy {
            return Ok(None);
        }
        let policy = one.policy.first().map(Vec::as_slice).unwrap_or_default();
        let state = AdaptiveFrame::restore(rec.plan, f, settings, policy)
            .map_err(|e| format!("frame {f}: {e}"))?;
        if state.finished() {
            finished.push(FinishedAdaptive {
                frame: f,
                rejected: one.rejected.pop().map(|(_, r)| r).unwrap_or_default(),
                // The job's status and history read the first frame's final figures.
                summary: (f == rec.frames.start).then(|| super::results::adaptive_summary(&state)),
            });
            continue;
        }
        restored.frames.append(&mut one.frames);
        restored.rejected.append(&mut one.rejected);
        restored.policy.append(&mut one.policy);
    }
    Ok(Some((restored, finished)))
}

/// What a restart keeps of an adaptive frame whose policy had finished: its rejected
/// samples per tile and, for the job's first frame, its summary.
struct FinishedAdaptive {
    frame: u32,
    rejected: Vec<u64>,
    summary: Option<(f64, Option<f64>)>,
}

/// The checkpoint-restore loop: accumulators of `frames` under `plan` with every
/// checkpointed tile restored (bit-exact Welford state, ARCHITECTURE.md §6). Refuses a
/// checkpoint of another frame, of an unknown tile, or one that does not restore.
pub(crate) fn restore_frames(
    plan: FramePlan,
    frames: impl IntoIterator<Item = u32>,
    checkpoints: Vec<TileCheckpoint>,
) -> Result<Restored, String> {
    let mut accs: Vec<FrameAccumulator> = frames
        .into_iter()
        .map(|f| FrameAccumulator::for_frame(plan, f))
        .collect();
    let mut rejected: Vec<(u32, Vec<u64>)> = accs
        .iter()
        .map(|a| (a.frame(), vec![0; plan.tile_count() as usize]))
        .collect();
    let mut policy: Vec<Vec<Option<AdaptiveTileCheckpoint>>> = accs
        .iter()
        .map(|_| vec![None; plan.tile_count() as usize])
        .collect();
    let mut without_policy = false;
    for mut cp in checkpoints {
        let Some(fi) = accs.iter().position(|f| f.frame() == cp.frame) else {
            return Err(format!("checkpoint of frame {} outside the job", cp.frame));
        };
        if let Some(r) = rejected[fi].1.get_mut(cp.tile as usize) {
            *r = cp.rejected_samples;
        }
        without_policy |= cp.adaptive.is_none() && cp.merged_passes > 0;
        if let Some(slot) = policy[fi].get_mut(cp.tile as usize) {
            *slot = cp.adaptive.take();
        }
        let rect = plan
            .get_tile(cp.tile)
            .ok_or_else(|| format!("checkpoint of unknown tile {}", cp.tile))?;
        let units: Vec<(u32, u32, u64)> = cp
            .units
            .iter()
            .map(|u| (u.first_pass, u.pass_count, u.digest))
            .collect();
        let mut tile =
            tessera_farm::TileAccumulator::restore(rect, cp.merged_passes, cp.pixels, &units)?;
        if let Some(bias) = cp.bias {
            tile.restore_bias(bias)?;
        }
        accs[fi].restore_tile(tile)?;
    }
    Ok(Restored {
        frames: accs,
        rejected,
        policy,
        without_policy,
    })
}

/// Resumes every unfinished job of the store into `farm`; jobs that cannot be resumed
/// are marked failed with the reason, and so is a job in a crash loop (below). Returns
/// whether any job was resumed (then leasing waits for the grace period). Only a store
/// that cannot be written stops the start.
///
/// # No crash loop (docs/store.md)
/// A job that crashes the coordinator while it handles it (at submission, at resume or
/// while running) would crash every restart. So every start after a crash counts, per
/// job and durably before the job is touched, the restarts that found it without a new
/// merged pass ([`Store::record_resume`]); a job past [`MAX_RESUMES_WITHOUT_PROGRESS`] is
/// failed instead of resumed. A crash during a start is blamed on the job that start was
/// resuming alone; a crash after it on every job then unfinished (a job that made
/// progress starts counting again). A graceful shutdown counts nothing.
pub(crate) async fn resume_all(
    store: &dyn Store,
    farm: &Mutex<Farm>,
    pilots: &Arc<TechniquePilots>,
) -> Result<bool, StoreError> {
    let previous = store.begin_run().await?;
    let mut resumed = false;
    for id in store.job_ids_to_resume().await? {
        let count = !previous.clean && previous.resuming.is_none_or(|j| j == id);
        let outcome = match store.record_resume(id, count).await {
            Ok(n) if n > MAX_RESUMES_WITHOUT_PROGRESS => Err(format!(
                "the coordinator restarted {n} times after a crash while running this job \
                 without progress (no new merged pass; the limit is \
                 {MAX_RESUMES_WITHOUT_PROGRESS}): failed to end a crash loop, see the \
                 coordinator's log of those runs"
            )),
            Ok(_) => match store.get_job(id).await {
                Ok(Some(rec)) => resume_job(store, farm, pilots, &rec).await,
                Ok(None) => continue,
                Err(e) if e.is_write_failure() => return Err(e),
                Err(e) => Err(format!("the stored job cannot be read: {e}")),
            },
            Err(e) if e.is_write_failure() => return Err(e),
            Err(e) => Err(format!("the stored job cannot be read: {e}")),
        };
        match outcome {
            Ok(()) => {
                resumed = true;
                tracing::info!(job = id, "job resumed");
            }
            Err(e) => {
                tracing::error!(job = id, error = %e, "cannot resume job; it is failed");
                store
                    .set_job_state(id, JobState::Failed, Some(e), now_ms())
                    .await?;
            }
        }
    }
    store.resumes_done().await?;
    Ok(resumed)
}

/// Brings one stored job back: resolved again, its plan checked, its tiles restored, its
/// remaining units queued.
async fn resume_job(
    store: &dyn Store,
    farm: &Mutex<Farm>,
    pilots: &Arc<TechniquePilots>,
    rec: &JobRecord,
) -> Result<(), String> {
    let StoredJob { settings, resolved } = resolve_stored(store, farm, pilots, rec)
        .await
        .map_err(|e| e.to_string())?;
    if resolved.plan != rec.plan {
        return Err("the stored frame plan differs from this build's plan".into());
    }
    let adaptive = resolved.adaptive_settings();
    let restored = match adaptive {
        Some(a) => match restore_adaptive(store, rec, a).await? {
            Some((r, finished)) => Restart::Adaptive(a, r, finished),
            None => Restart::Over,
        },
        None => {
            let (r, c) = restore_incomplete(store, rec).await?;
            Restart::Plain(r, c)
        }
    };
    let history = store.list_history(rec.id).await.unwrap_or_default();
    let faults = store
        .count_faults(&FaultFilter {
            job: Some(rec.id),
            worker: None,
        })
        .await
        .unwrap_or(0);
    let mut farm = farm.lock().map_err(|_| "farm state poisoned".to_string())?;
    let mut rt = JobRuntime::new(settings, resolved, rec.state, rec.created_unix_ms);
    let (plan, first, ppu) = (rec.plan, rec.frames.start, rec.passes_per_unit);
    match restored {
        Restart::Over => {
            // Checkpoints of a build that did not save the policy's state: the job starts
            // again from its first pass (its result is the same), so its rejected counts
            // start from zero too.
            tracing::warn!(
                job = rec.id,
                "adaptive job checkpointed without its policy state (an older build): \
                 rendering it again from the first pass"
            );
            add_to_scheduler(&mut farm, rec.id, rec.priority, &rt.resolved, ppu)
                .map_err(|e| e.to_string())?;
        }
        Restart::Adaptive(settings, restored, finished) => {
            // The policy resumes where it was; only units in flight are redone.
            let finished_counts = finished.iter().map(|f| (f.frame, &f.rejected));
            let restored_counts = restored.rejected.iter().map(|(f, r)| (*f, r));
            restore_rejected(&mut rt, first, finished_counts.chain(restored_counts));
            let resumed = tessera_farm::ResumedAdaptive {
                frames: rec.frames.start..=rec.frames.end,
                settings,
                restored: restored.frames.into_iter().zip(restored.policy).collect(),
                complete: finished.iter().map(|f| f.frame).collect(),
            };
            farm.scheduler
                .add_resumed_adaptive_job(rec.id, rec.priority, plan, ppu, resumed)?;
            let summary = finished.iter().find_map(|f| f.summary);
            match farm.scheduler.adaptive_frame(rec.id, first) {
                Some(a) => rt.adaptive_summary = super::results::adaptive_summary(a),
                None => rt.adaptive_summary = summary.unwrap_or(rt.adaptive_summary),
            }
        }
        Restart::Plain(restored, complete) => {
            for f in &restored.frames {
                let k = (f.frame() - first) as usize;
                if let Some(slot) = rt.tile_error.get_mut(k) {
                    *slot = f.tiles().iter().map(tile_error).collect();
                }
                if let Some(slot) = rt.frame_error.get_mut(k) {
                    *slot = Some(f.image_error()).filter(|e| e.is_finite());
                }
            }
            for c in &complete {
                let k = (c.frame - first) as usize;
                if let Some(slot) = rt.tile_error.get_mut(k) {
                    slot.clone_from(&c.errors);
                }
                if let Some(slot) = rt.frame_error.get_mut(k) {
                    *slot = c.estimate.filter(|e| e.is_finite());
                }
            }
            let counts = complete.iter().map(|c| (c.frame, &c.rejected));
            let restored_counts = restored.rejected.iter().map(|(f, r)| (*f, r));
            restore_rejected(&mut rt, first, counts.chain(restored_counts));
            let resumed = Resumed {
                frames: rec.frames.start..=rec.frames.end,
                restored: restored.frames,
                complete: complete.iter().map(|c| c.frame).collect(),
            };
            farm.scheduler
                .add_resumed_job(rec.id, rec.priority, plan, resumed, ppu)?;
        }
    }
    // vcm and ppm keep the merging-bias channel beside the pixels' statistics (the
    // restored frames are charged for it; a job started over was counted already).
    if rt.resolved.estimates_bias() {
        farm.scheduler.count_bias_channel(rec.id);
    }
    farm.jobs.insert(rec.id, JobEntry::of(&rt.resolved));
    rt.started_unix_ms = rec.started_unix_ms;
    rt.faults = faults;
    rt.history = history;
    rt.stopped = Stop::of_stored(rec.state, rec.error.as_deref());
    farm.runtime.insert(rec.id, rt);
    Ok(())
}

/// How a stored job comes back.
enum Restart {
    /// Without adaptive stopping: its incomplete frames restored, its complete ones
    /// summarized.
    Plain(Restored, Vec<CompleteFrame>),
    /// Adaptive, with the policy's state: its unfinished frames restored, its finished
    /// ones summarized.
    Adaptive(AdaptiveSettings, Restored, Vec<FinishedAdaptive>),
    /// Adaptive, checkpointed without the policy's state: from its first pass.
    Over,
}

/// Per frame (number, per tile), the rejected samples of the merged passes, into the
/// job's counts.
fn restore_rejected<'a>(
    rt: &mut JobRuntime,
    first: u32,
    counts: impl Iterator<Item = (u32, &'a Vec<u64>)>,
) {
    for (f, counts) in counts {
        if let Some(slots) = rt.tile_rejected.get_mut((f - first) as usize) {
            for (slot, &merged) in slots.iter_mut().zip(counts) {
                *slot = TileRejected::with_merged(merged);
            }
        }
    }
}
