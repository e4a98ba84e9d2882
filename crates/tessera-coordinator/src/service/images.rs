//! Images: a frame's merged state, from memory or rebuilt from the tile checkpoints of a
//! job that finished before this coordinator started (ARCHITECTURE.md §9, step 11), and
//! what is served from it: the image (PNG or EXR) and the per-tile progress map.

use tessera_api::{
    FrameQuery, FrameRange, ImageFormat, ImageQuery, JobState, ResolvedJob, TileInfo, TileMap,
};
use tessera_farm::{AdaptiveFrame, FrameAccumulator, FrameImage, JobId};

use super::resume::{resolve_stored, restore_frames};
use super::Coordinator;
use crate::error::{CoordError, CoordResult};
use crate::state::tile_error;

/// One frame of a job as far as it is merged.
struct FrameState {
    /// Why the job stopped, once it is done.
    stopped: Option<&'static str>,
    /// The merged tiles; `None` for a black job or an adaptive job in memory.
    acc: Option<FrameAccumulator>,
    /// The adaptive policy's state of an adaptive job in memory (its image is the job's).
    adaptive: Option<AdaptiveFrame>,
    resolved: ResolvedJob,
    frame: u32,
}

impl FrameState {
    /// The frame's image: the adaptive policy's, the merged tiles', or black.
    fn image(&self) -> FrameImage {
        match (&self.adaptive, &self.acc) {
            (Some(a), _) => a.image(),
            (None, Some(acc)) => acc.image(),
            (None, None) => FrameImage::black(&self.resolved.plan),
        }
    }
}

impl Coordinator {
    /// The merged state of one frame, from memory or rebuilt from the store.
    async fn frame_state(&self, id: JobId, frame: Option<u32>) -> CoordResult<FrameState> {
        if let Some(fs) = self.live_frame_state(id, frame)? {
            return Ok(fs);
        }
        // Not in memory: a job finished before this coordinator started.
        let store = &*self.inner.store;
        let rec = store
            .get_job(id)
            .await?
            .ok_or_else(|| CoordError::job_not_found(id))?;
        let f = frame.unwrap_or(rec.frames.start);
        if !rec.frames.iter().contains(&f) {
            return Err(frame_error(f, rec.frames));
        }
        let stored = resolve_stored(store, &self.inner.farm, &rec).await?;
        let stopped = (rec.state == JobState::Done).then_some("finished");
        let acc = if stored.resolved.black {
            None
        } else {
            let checkpoints = store.load_tiles(id, Some(f)).await?;
            let mut restored =
                restore_frames(rec.plan, [f], checkpoints).map_err(CoordError::Internal)?;
            restored.frames.pop()
        };
        Ok(FrameState {
            stopped,
            acc,
            adaptive: None,
            resolved: stored.resolved,
            frame: f,
        })
    }

    /// The merged state of one frame of a job in memory; `None` if the job is not (or
    /// its frame has no accumulator).
    fn live_frame_state(&self, id: JobId, frame: Option<u32>) -> CoordResult<Option<FrameState>> {
        let farm = self.lock()?;
        let Some(rt) = farm.runtime.get(&id) else {
            return Ok(None);
        };
        let f = frame.unwrap_or(rt.job().frames.start);
        if !rt.job().frames.iter().contains(&f) {
            return Err(frame_error(f, rt.job().frames));
        }
        let state = |acc, adaptive| FrameState {
            stopped: rt.stopped,
            acc,
            adaptive,
            resolved: rt.resolved.clone(),
            frame: f,
        };
        if rt.resolved.black {
            return Ok(Some(state(None, None)));
        }
        if let Some(a) = farm.scheduler.adaptive_frame(id, f) {
            return Ok(Some(state(None, Some(a.clone()))));
        }
        Ok(farm
            .scheduler
            .frame(id, f)
            .map(|acc| state(Some(acc.clone()), None)))
    }

    /// `GET /jobs/{id}/image`: the current merged image as PNG or EXR.
    pub async fn image(&self, id: JobId, q: ImageQuery) -> CoordResult<Vec<u8>> {
        let fs = self.frame_state(id, q.frame).await?;
        // Merging and encoding a large frame is CPU work: off the async runtime.
        tokio::task::spawn_blocking(move || {
            let image = fs.image();
            match q.format {
                ImageFormat::Png => tessera_image::encode_png(&image),
                ImageFormat::Exr => {
                    tessera_image::encode_exr(&image, Some(&fs.resolved.metadata_json(fs.stopped)))
                }
            }
        })
        .await
        .map_err(CoordError::internal)?
        .map_err(CoordError::internal)
    }

    /// The current merged image of a frame (the job's first frame by default), as the
    /// EXR of `GET /jobs/{id}/image` encodes it.
    pub async fn frame_image(&self, id: JobId, frame: Option<u32>) -> CoordResult<FrameImage> {
        let fs = self.frame_state(id, frame).await?;
        tokio::task::spawn_blocking(move || fs.image())
            .await
            .map_err(CoordError::internal)
    }

    /// `GET /jobs/{id}/tiles`: per-tile progress of a frame.
    pub async fn tiles(&self, id: JobId, q: FrameQuery) -> CoordResult<TileMap> {
        let fs = self.frame_state(id, q.frame).await?;
        let plan = fs.resolved.plan;
        let tiles = plan
            .tiles()
            .map(|rect| {
                let (passes, error) = tile_progress(&fs, rect.index as usize);
                TileInfo {
                    index: rect.index,
                    x: rect.x0,
                    y: rect.y0,
                    width: rect.width,
                    height: rect.height,
                    passes,
                    spp: f64::from(passes) * f64::from(plan.samples_per_pass),
                    error,
                    done: passes >= plan.passes,
                }
            })
            .collect();
        Ok(TileMap {
            frame: fs.frame,
            width: plan.width,
            height: plan.height,
            passes_planned: plan.passes,
            tiles,
        })
    }
}

/// A tile's (passes done, RMS relative error) in a frame state.
fn tile_progress(fs: &FrameState, index: usize) -> (u32, Option<f64>) {
    let plan = fs.resolved.plan;
    match (&fs.adaptive, &fs.acc) {
        (Some(a), _) => {
            let t = &a.tiles()[index];
            let (mut sum, mut n) = (0.0, 0u64);
            // Pixels with one pass have no variance estimate yet (ARCHITECTURE.md §3).
            for p in t.pixels() {
                if p.passes >= 2 {
                    let r = p.relative_error();
                    sum += r * r;
                    n += 1;
                }
            }
            let done = if t.finished() {
                plan.passes
            } else {
                t.consumed_passes()
            };
            (done, (n > 0).then(|| (sum / n as f64).sqrt()))
        }
        (None, Some(acc)) => {
            let t = &acc.tiles()[index];
            let (s, n) = tile_error(t);
            (t.merged_passes(), (n > 0).then(|| (s / n as f64).sqrt()))
        }
        (None, None) => (plan.passes, Some(0.0)),
    }
}

/// The answer to a frame outside the job's range.
fn frame_error(f: u32, frames: FrameRange) -> CoordError {
    CoordError::invalid_field(
        "frame",
        format!(
            "frame {f} is not rendered by this job (frames {}..={})",
            frames.start, frames.end
        ),
    )
}
