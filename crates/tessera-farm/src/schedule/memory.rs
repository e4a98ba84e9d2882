//! The memory budget for per-pixel merge state (ARCHITECTURE.md §6, "Memory: budgeted,
//! never assumed"): one budget for all jobs, charged a frame at a time when the frame's
//! first unit is leased ([`Job::make_live`]) and credited when the caller releases a
//! complete, checkpointed frame ([`Scheduler::release_frame`]), or when a finished
//! adaptive job gives its frames back under pressure. A frame that does not fit waits;
//! one frame is always allowed when nothing is resident, so no job waits forever.
//!
//! The same budget counts the transient memory of image encodes (the coordinator's
//! `/image` downloads, [`Scheduler::reserve_transient`]): an encode reserves what it will
//! hold before it holds it, and one that does not fit waits for another to finish. One
//! encode is always allowed when no other runs, so a budget full of merge state cannot
//! starve downloads: the coordinator then holds at most the budget plus one encode.

use super::job::{FrameSlot, Job};
use super::Scheduler;
use crate::adaptive::AdaptiveFrame;
use crate::ids::JobId;
use crate::merge::FrameAccumulator;
use crate::plan::FramePlan;

/// The memory budget for per-pixel merge state, shared by all jobs.
#[derive(Clone, Copy, Debug)]
pub(super) struct Memory {
    pub(super) budget: u64,
    pub(super) resident: u64,
    /// Reserved by running image encodes.
    pub(super) transient: u64,
    /// The largest `resident + transient` seen.
    pub(super) high_water: u64,
}

impl Memory {
    /// No budget, nothing held.
    pub(super) fn unbounded() -> Self {
        Self {
            budget: u64::MAX,
            resident: 0,
            transient: 0,
            high_water: 0,
        }
    }

    fn note_high_water(&mut self) {
        self.high_water = self
            .high_water
            .max(self.resident.saturating_add(self.transient));
    }
}

/// Bytes of merge state one frame of `plan` holds in memory: a [`crate::PixelStats`] per
/// pixel, and the adaptive policy's per-pixel state for adaptive jobs.
pub fn frame_state_bytes(plan: &FramePlan, adaptive: bool) -> u64 {
    let per_pixel = FrameAccumulator::BYTES_PER_PIXEL
        + if adaptive {
            AdaptiveFrame::BYTES_PER_PIXEL
        } else {
            0
        };
    u64::from(plan.width) * u64::from(plan.height) * per_pixel
}

/// Bytes of one pixel's merging-bias statistics ([`crate::BiasStats`]).
const BIAS_BYTES_PER_PIXEL: u64 = std::mem::size_of::<crate::BiasStats>() as u64;

/// [`frame_state_bytes`] of a job whose frames may also keep the merging-bias channel of
/// vcm and ppm (`biased`; [`crate::UnitResult::bias`]): a [`crate::BiasStats`] per pixel in
/// the accumulator ([`crate::TileAccumulator::bias`]) and, for adaptive jobs, another in
/// the policy's state over the passes each pixel keeps ([`crate::AdaptiveTile::bias`]).
pub fn frame_state_bytes_with_bias(plan: &FramePlan, adaptive: bool, biased: bool) -> u64 {
    let copies = if biased { 1 + u64::from(adaptive) } else { 0 };
    frame_state_bytes(plan, adaptive)
        + u64::from(plan.width) * u64::from(plan.height) * copies * BIAS_BYTES_PER_PIXEL
}

/// Where a frame's merge state is ([`Scheduler::residency`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Residency {
    /// No unit of the frame was leased yet: nothing merged, nothing allocated.
    Pending,
    /// In memory ([`Scheduler::frame`]).
    Live,
    /// Complete, checkpointed and dropped from memory: read it from the store.
    Released,
}

impl Job {
    /// Allocates frame `k`'s merge state if it is pending and fits the budget; whether
    /// it is live now.
    pub(super) fn make_live(&mut self, k: usize, mem: &mut Memory) -> bool {
        match self.frames.get(k) {
            Some(FrameSlot::Live(_)) => return true,
            Some(FrameSlot::Pending) => {}
            Some(FrameSlot::Released) | None => return false,
        }
        // Encodes in progress count too (they end soon); a frame still goes when no
        // merge state is resident, so no job waits forever.
        let held = mem.resident.saturating_add(mem.transient);
        if held.saturating_add(self.frame_bytes) > mem.budget && mem.resident > 0 {
            return false;
        }
        let frame = self.first_frame + k as u32;
        if let Some(a) = self.adaptive.as_mut() {
            // Validated when the job was added; cannot fail.
            match AdaptiveFrame::new(self.plan, frame, a.settings) {
                Ok(f) => a.frames[k] = Some(f),
                Err(_) => return false,
            }
        }
        self.frames[k] = FrameSlot::Live(Box::new(FrameAccumulator::for_frame(self.plan, frame)));
        mem.resident += self.frame_bytes;
        mem.note_high_water();
        true
    }

    /// Bytes of this job's live frames.
    pub(super) fn resident_bytes(&self) -> u64 {
        let live = self
            .frames
            .iter()
            .filter(|f| matches!(f, FrameSlot::Live(_)))
            .count() as u64;
        live * self.frame_bytes
    }
}

impl Scheduler {
    /// Sets the memory budget for per-pixel merge state of all jobs, in bytes (unbounded
    /// by default). Frames that do not fit wait for completed frames to be released; one
    /// frame is always allowed when nothing is resident, so no job waits forever.
    pub fn set_memory_budget(&mut self, bytes: u64) {
        self.memory.budget = bytes;
    }

    /// Bytes of per-pixel merge state in memory, over all jobs.
    pub fn resident_bytes(&self) -> u64 {
        self.memory.resident
    }

    /// Counts the merging-bias channel of a biased technique (vcm, ppm) in the memory of
    /// every frame of job `job_id` ([`frame_state_bytes_with_bias`]): for the caller to
    /// call once it added the job, since the scheduler does not know the technique. Frames
    /// already live (a resumed job's) are charged the difference; calling it again changes
    /// nothing.
    pub fn count_bias_channel(&mut self, job_id: JobId) {
        let Some(job) = self.jobs.get_mut(&job_id) else {
            return;
        };
        let bytes = frame_state_bytes_with_bias(&job.plan, job.adaptive.is_some(), true);
        let before = job.resident_bytes();
        job.frame_bytes = bytes;
        let after = job.resident_bytes();
        let m = &mut self.memory;
        m.resident = m.resident.saturating_sub(before).saturating_add(after);
        m.note_high_water();
    }

    /// Reserves `bytes` of the budget for a transient image encode, if they fit beside the
    /// merge state and the other encodes, or if no other encode holds a reservation (one
    /// always proceeds); whether it was reserved. Give it back with
    /// [`Scheduler::release_transient`].
    pub fn reserve_transient(&mut self, bytes: u64) -> bool {
        let m = &mut self.memory;
        let held = m.resident.saturating_add(m.transient);
        if m.transient > 0 && held.saturating_add(bytes) > m.budget {
            return false;
        }
        m.transient = m.transient.saturating_add(bytes);
        m.note_high_water();
        true
    }

    /// Gives back a reservation of [`Scheduler::reserve_transient`].
    pub fn release_transient(&mut self, bytes: u64) {
        self.memory.transient = self.memory.transient.saturating_sub(bytes);
    }

    /// Bytes reserved by running image encodes.
    pub fn transient_bytes(&self) -> u64 {
        self.memory.transient
    }

    /// The most memory the budget has accounted for at once since the start: merge state
    /// plus image encodes.
    pub fn memory_high_water(&self) -> u64 {
        self.memory.high_water
    }

    /// Drops a complete frame's merge state from memory, once the caller has made its
    /// checkpoints durable; later results for it are
    /// [`Submitted::Late`](super::Submitted::Late) and its image comes from the store. A frame of an adaptive job is complete when its policy has
    /// finished every tile: the policy state is checkpointed with each tile, so
    /// the frame's image is restored from the store like any other, and the frames of an
    /// animation no longer hold memory until the whole job ends (with a budget of one
    /// frame, the next frame waited for that forever). Returns whether the frame was
    /// released now.
    pub fn release_frame(&mut self, job_id: JobId, frame: u32) -> bool {
        let Some(job) = self.jobs.get_mut(&job_id) else {
            return false;
        };
        let Some(k) = frame.checked_sub(job.first_frame).map(|k| k as usize) else {
            return false;
        };
        let Some(acc) = job.frames.get(k).and_then(FrameSlot::live) else {
            return false;
        };
        let complete = match &job.adaptive {
            Some(a) => a
                .frames
                .get(k)
                .and_then(Option::as_ref)
                .is_some_and(AdaptiveFrame::finished),
            None => acc.complete(),
        };
        if !complete {
            return false;
        }
        job.frames[k] = FrameSlot::Released;
        if let Some(a) = job.adaptive.as_mut() {
            a.frames[k] = None;
        }
        self.memory.resident = self.memory.resident.saturating_sub(job.frame_bytes);
        true
    }

    /// Where one frame's merge state is; `None` for an unknown job or frame.
    pub fn residency(&self, job_id: JobId, frame: u32) -> Option<Residency> {
        let job = self.jobs.get(&job_id)?;
        Some(
            match job
                .frames
                .get(frame.checked_sub(job.first_frame)? as usize)?
            {
                FrameSlot::Pending => Residency::Pending,
                FrameSlot::Live(_) => Residency::Live,
                FrameSlot::Released => Residency::Released,
            },
        )
    }

    /// The merged state of one frame of a job, while it is live (see [`Residency`]).
    pub fn frame(&self, job_id: JobId, frame: u32) -> Option<&FrameAccumulator> {
        let job = self.jobs.get(&job_id)?;
        job.frames
            .get(frame.checked_sub(job.first_frame)? as usize)?
            .live()
    }

    /// Under memory pressure (more than half the budget resident while a job has work),
    /// drops the state of finished adaptive jobs, oldest first (see [`Scheduler::lease`]).
    pub(super) fn evict_finished_adaptive(&mut self) {
        let pressure = |m: &Memory| m.resident > m.budget / 2;
        if !pressure(&self.memory) || !self.jobs.values().any(Job::has_work) {
            return;
        }
        let mut finished: Vec<(u64, JobId)> = self
            .jobs
            .iter()
            .filter(|(_, j)| j.adaptive.is_some() && !j.evicted && j.is_complete())
            .map(|(&id, j)| (j.seq, id))
            .collect();
        finished.sort_unstable();
        for (_, id) in finished {
            if !pressure(&self.memory) {
                break;
            }
            let Some(job) = self.jobs.get_mut(&id) else {
                continue;
            };
            self.memory.resident = self.memory.resident.saturating_sub(job.resident_bytes());
            job.frames.iter_mut().for_each(|f| *f = FrameSlot::Released);
            if let Some(a) = job.adaptive.as_mut() {
                a.frames.iter_mut().for_each(|f| *f = None);
            }
            job.evicted = true;
        }
    }
}
