//! Jobs brought back after a coordinator restart (ARCHITECTURE.md §9, "Restart, resume and
//! the grace period"): each frame comes back from its checkpoints (merged passes, and for
//! adaptive jobs the policy state saved with them), the units those passes cover are
//! done, and the rest are leased again in canonical order, so the job ends with the image
//! of an uninterrupted run, bit for bit.

use super::job::{AdaptiveQueue, FrameSlot};
use super::memory::frame_state_bytes;
use super::Scheduler;
use crate::adaptive::{AdaptiveFrame, AdaptiveSettings, AdaptiveTileCheckpoint};
use crate::ids::JobId;
use crate::merge::FrameAccumulator;
use crate::plan::FramePlan;
use std::ops::RangeInclusive;

/// What a restart restored of a job for [`Scheduler::add_resumed_job`].
#[derive(Debug)]
pub struct Resumed {
    /// The frames the job renders (inclusive range).
    pub frames: std::ops::RangeInclusive<u32>,
    /// The accumulators of frames with checkpoints that are not complete, restored from
    /// them; frames neither here nor in `complete` have nothing merged.
    pub restored: Vec<FrameAccumulator>,
    /// Frames every tile of which has all its passes: not loaded, their images are in the
    /// store.
    pub complete: Vec<u32>,
}

/// What a restart restored of an adaptive job for [`Scheduler::add_resumed_adaptive_job`].
#[derive(Debug)]
pub struct ResumedAdaptive {
    /// The frames the job renders (inclusive range).
    pub frames: std::ops::RangeInclusive<u32>,
    /// The adaptive settings as submitted (rounded to the units again when added).
    pub settings: AdaptiveSettings,
    /// Each unfinished frame with checkpoints: its merged passes and, per tile in tile
    /// order, the policy state saved with them (`None`: nothing consumed).
    pub restored: Vec<(FrameAccumulator, Vec<Option<AdaptiveTileCheckpoint>>)>,
    /// Frames whose restored policy had finished every tile: not loaded, released at once
    /// (their images are restored from the store when asked for, as after a release in
    /// the running job).
    pub complete: Vec<u32>,
}

impl Scheduler {
    /// Adds a job resumed after a restart (see [`Resumed`]), cut into units of
    /// `passes_per_unit` passes as before the restart. Units whose passes
    /// every checkpoint already merged are done; everything else is leased again in
    /// canonical order.
    ///
    /// Checkpoints whose merged passes do not end on a unit boundary (impossible with the
    /// same `passes_per_unit`) are refused: their next unit would overlap merged passes.
    ///
    /// Memory: complete frames are released at once (their checkpoints are in the store),
    /// frames with no merged pass are left pending, the rest stay live and are charged to
    /// the budget even beyond it (what a run merged, the next keeps).
    pub fn add_resumed_job(
        &mut self,
        id: JobId,
        priority: i32,
        plan: FramePlan,
        resumed: Resumed,
        passes_per_unit: u32,
    ) -> Result<(), String> {
        let Resumed {
            frames,
            restored,
            complete,
        } = resumed;
        let passes_per_unit = passes_per_unit.max(1);
        if frames.is_empty() {
            return Err(format!("job {id}: no frames to resume"));
        }
        let first_frame = *frames.start();
        let mut slots: Vec<FrameSlot> = frames.clone().map(|_| FrameSlot::Pending).collect();
        for f in complete {
            match f
                .checked_sub(first_frame)
                .and_then(|k| slots.get_mut(k as usize))
            {
                Some(slot) => *slot = FrameSlot::Released,
                None => return Err(format!("job {id}: frame {f} is outside the job")),
            }
        }
        for f in &restored {
            if *f.plan() != plan {
                return Err(format!("job {id}: frame {} has another plan", f.frame()));
            }
            if !frames.contains(&f.frame()) {
                return Err(format!("job {id}: frame {} is outside the job", f.frame()));
            }
            for t in f.tiles() {
                let m = t.merged_passes();
                if m > plan.passes || (m % passes_per_unit != 0 && m != plan.passes) {
                    return Err(format!(
                        "job {id}: frame {} tile {} merged {m} passes, not a whole number of \
                         {passes_per_unit}-pass units",
                        f.frame(),
                        t.rect().index
                    ));
                }
            }
        }
        for f in restored {
            let k = (f.frame() - first_frame) as usize;
            slots[k] = FrameSlot::Live(Box::new(f));
        }
        let mut job = self.new_job(id, priority, plan, first_frame, passes_per_unit, slots);
        for i in 0..job.units_total() {
            let u = job.unit(i);
            let merged = match &job.frames[(u.frame - first_frame) as usize] {
                FrameSlot::Pending => continue,
                FrameSlot::Live(f) => f.tiles()[u.tile as usize].merged_passes(),
                FrameSlot::Released => plan.passes,
            };
            if u64::from(merged) >= u.end_pass() {
                job.done.insert(i);
            }
        }
        for slot in &mut job.frames {
            let state = slot.live().map(|f| (f.complete(), f.merged_pass_count()));
            *slot = match state {
                Some((true, _)) => FrameSlot::Released,
                Some((false, 0)) => FrameSlot::Pending,
                _ => std::mem::replace(slot, FrameSlot::Pending),
            };
        }
        self.memory.resident += job.resident_bytes();
        self.jobs.insert(id, job);
        Ok(())
    }

    /// Adds an adaptive job resumed after a restart: like
    /// [`Scheduler::add_adaptive_job`], with each frame in `restored` brought back from its
    /// checkpoints: the merged passes (the accumulator) and, per tile in tile order, the
    /// policy state saved with them (`None`: nothing consumed). Units whose passes a tile
    /// merged are done; the rest are gated by the restored decisions exactly as they
    /// would have been without the restart (leased, waiting for a decision, or skipped),
    /// so the job ends with the image an uninterrupted run makes, bit for bit.
    ///
    /// Refuses (naming the frame and tile) a policy state that the settings could not have
    /// produced ([`AdaptiveFrame::restore`]), one that consumed other passes than its tile
    /// merged (an unfinished tile consumes every merged pass; a finished one may have
    /// merged a unit past its end), a frame outside the job or of another plan, and merged
    /// passes that do not end on a unit boundary. Restored frames are live and charged to
    /// the memory budget even beyond it (the caller restores only the unfinished ones);
    /// `complete` frames are released, their units never leased again.
    pub fn add_resumed_adaptive_job(
        &mut self,
        id: JobId,
        priority: i32,
        plan: FramePlan,
        passes_per_unit: u32,
        resumed: ResumedAdaptive,
    ) -> Result<AdaptiveSettings, String> {
        let ResumedAdaptive {
            frames,
            settings: adaptive,
            restored,
            complete,
        } = resumed;
        let ppu = passes_per_unit.max(1);
        let settings = adaptive.for_units(ppu);
        AdaptiveFrame::new(plan, *frames.start(), settings)
            .map_err(|e| format!("job {id}: {e}"))?;
        let first_frame = *frames.start();
        let live = restore_adaptive_frames(id, plan, &frames, settings, ppu, restored)?;
        for &f in &complete {
            if !frames.contains(&f) {
                return Err(format!("job {id}: frame {f} is outside the job"));
            }
            if live.iter().any(|(acc, _)| acc.frame() == f) {
                return Err(format!(
                    "job {id}: frame {f} is both finished and in progress"
                ));
            }
        }
        let count = frames.clone().count();
        self.add_job(id, priority, plan, frames, ppu);
        let frame_bytes = frame_state_bytes(&plan, true);
        let Some(job) = self.jobs.get_mut(&id) else {
            return Err(format!("job {id}: not added"));
        };
        job.frame_bytes = frame_bytes;
        let mut queue = AdaptiveQueue::new(settings, count);
        for &f in &complete {
            job.frames[(f - first_frame) as usize] = FrameSlot::Released;
        }
        for (acc, policy) in live {
            let k = (acc.frame() - first_frame) as usize;
            job.frames[k] = FrameSlot::Live(Box::new(acc));
            queue.frames[k] = Some(policy);
            self.memory.resident += frame_bytes;
        }
        job.adaptive = Some(queue);
        for i in 0..job.units_total() {
            let u = job.unit(i);
            if let FrameSlot::Live(f) = &job.frames[(u.frame - first_frame) as usize] {
                if u64::from(f.tiles()[u.tile as usize].merged_passes()) >= u.end_pass() {
                    job.done.insert(i);
                }
            }
        }
        Ok(settings)
    }
}

/// The restored frames of adaptive job `id`, each with its policy state rebuilt from its
/// tiles' checkpoints and checked against the tiles' merged passes (see
/// [`Scheduler::add_resumed_adaptive_job`] for what is refused).
fn restore_adaptive_frames(
    id: JobId,
    plan: FramePlan,
    frames: &RangeInclusive<u32>,
    settings: AdaptiveSettings,
    ppu: u32,
    restored: Vec<(FrameAccumulator, Vec<Option<AdaptiveTileCheckpoint>>)>,
) -> Result<Vec<(FrameAccumulator, AdaptiveFrame)>, String> {
    let mut live = Vec::with_capacity(restored.len());
    for (acc, checkpoints) in restored {
        let f = acc.frame();
        if *acc.plan() != plan {
            return Err(format!("job {id}: frame {f} has another plan"));
        }
        if !frames.contains(&f) {
            return Err(format!("job {id}: frame {f} is outside the job"));
        }
        let policy = AdaptiveFrame::restore(plan, f, settings, &checkpoints)
            .map_err(|e| format!("job {id}: frame {f}: {e}"))?;
        for (t, a) in acc.tiles().iter().zip(policy.tiles()) {
            let (merged, consumed) = (t.merged_passes(), a.consumed_passes());
            let consistent = if a.finished() {
                consumed <= merged
            } else {
                consumed == merged
            };
            if !consistent || (merged % ppu != 0 && merged != plan.passes) {
                return Err(format!(
                    "job {id}: frame {f} tile {}: {merged} passes merged in units of \
                     {ppu}, {consumed} consumed by the adaptive policy{}",
                    t.rect().index,
                    if a.finished() { " (finished)" } else { "" }
                ));
            }
        }
        live.push((acc, policy));
    }
    Ok(live)
}
