//! Images: a frame's merged state, from memory or rebuilt from the tile checkpoints (a
//! frame released after it completed, or a job that finished before this coordinator
//! started, ARCHITECTURE.md §9, step 11), and what is served from it: the image (PNG or
//! EXR) and the per-tile progress map.
//!
//! Memory and load (ARCHITECTURE.md §6): nothing here copies a frame's accumulators. The
//! PNG is made from the pixel means straight into 8-bit rows (3 bytes per pixel), the EXR
//! layers and the tile map are read under the farm lock; a frame in the store is
//! restored, used and dropped. Encoded images are cached per frame and merge count, so
//! pollers of an unchanged frame cost a map lookup, and at most [`HEAVY_REQUESTS`]
//! requests restore or encode a frame at once, which bounds what image requests hold
//! however many arrive.

use std::collections::HashMap;
use std::sync::Arc;

use tessera_api::{
    FrameQuery, FrameRange, ImageFormat, ImageQuery, ResolvedJob, TileInfo, TileMap,
};
use tessera_farm::{
    AdaptiveFrame, AdaptiveSettings, FrameAccumulator, FrameImage, FramePlan, JobId, Residency,
};

use super::resume::{resolve_stored, restore_frames};
use super::Coordinator;
use crate::error::{CoordError, CoordResult};
use crate::state::{tile_error, Stop};
use tessera_farm::job::StopVerdict;

/// Image requests that may restore a frame from the store or encode one at the same
/// time; the rest wait (and then usually find the image cached).
pub const HEAVY_REQUESTS: usize = 2;
/// Encoded images kept for pollers, in bytes over all jobs.
pub const IMAGE_CACHE_BYTES: usize = 64 << 20;
/// How old a cached PNG of a running job may be and still be served although results
/// merged since: the dashboard polls once a second, and re-encoding on every merge would
/// put one encode per poller on the render's cores. Final images (a stopped job, a
/// released frame) and EXR downloads are always current.
pub const PREVIEW_MAX_AGE: std::time::Duration = std::time::Duration::from_millis(1000);

/// The merged state of a frame as a request sees it.
enum Source<'a> {
    /// A job the render plan found nothing to trace in: exactly black, all passes done.
    Black,
    /// Nothing merged yet (its merge state is not allocated).
    Empty,
    /// The adaptive policy's state (the image of an adaptive job).
    Adaptive(&'a AdaptiveFrame),
    /// Merged tiles, with their (sum of squared relative errors, pixels) when the job
    /// keeps them up to date (a live frame), so a tile map does not walk every pixel.
    Merged(&'a FrameAccumulator, Option<&'a [(f64, u64)]>),
}

/// What a request needs to know of a job besides the frame's pixels.
#[derive(Clone)]
struct FrameMeta {
    resolved: ResolvedJob,
    stopped: Option<Stop>,
    frame: u32,
    /// Changes whenever the frame's image may have changed (cache key): twice the job's
    /// merge count while it runs, plus one once it stopped; `u64::MAX` for a frame that no
    /// longer changes (released, or of a job of an earlier run).
    version: u64,
    /// The adaptive settings the job ran with (rounded to its units), for an adaptive
    /// job: its image is the policy's, restored from the store's checkpoints.
    adaptive: Option<AdaptiveSettings>,
}

/// A frame rebuilt from the store.
enum StoredFrame {
    /// A job the render plan found nothing to trace in.
    Black,
    /// The merged passes.
    Merged(FrameAccumulator),
    /// The adaptive policy's state.
    Adaptive(AdaptiveFrame),
}

/// A frame found in memory, or where to read it from.
enum Located<T> {
    /// Computed under the farm lock.
    Done(T),
    /// Released after completing: restore it from the store's checkpoints.
    Store(Box<FrameMeta>),
}

/// One encoded image.
struct Cached {
    version: u64,
    bytes: Arc<Vec<u8>>,
    /// When it was encoded.
    at: std::time::Instant,
}

/// An image cache key: (job, frame, EXR rather than PNG).
type ImageKey = (JobId, u32, bool);

/// Encoded images by key: (version, bytes).
#[derive(Default)]
pub(crate) struct ImageCache {
    entries: HashMap<ImageKey, Cached>,
    bytes: usize,
}

impl ImageCache {
    /// The cached image of `key` if it is of `version`, or (a PNG of a running job,
    /// whose versions are even, see [`FrameMeta::version`]) younger than
    /// [`PREVIEW_MAX_AGE`].
    fn get(&self, key: ImageKey, version: u64) -> Option<Arc<Vec<u8>>> {
        let c = self.entries.get(&key)?;
        let running = version.is_multiple_of(2) && version != u64::MAX;
        let fresh_enough =
            !key.2 && running && c.version.is_multiple_of(2) && c.at.elapsed() < PREVIEW_MAX_AGE;
        (c.version == version || fresh_enough).then(|| c.bytes.clone())
    }

    fn put(&mut self, key: ImageKey, version: u64, bytes: Arc<Vec<u8>>) {
        if bytes.len() > IMAGE_CACHE_BYTES / 4 {
            return;
        }
        if let Some(old) = self.entries.remove(&key) {
            self.bytes -= old.bytes.len();
        }
        // Evict arbitrary entries until it fits: pollers refill what they use.
        while self.bytes + bytes.len() > IMAGE_CACHE_BYTES {
            let Some(&k) = self.entries.keys().next() else {
                break;
            };
            if let Some(old) = self.entries.remove(&k) {
                self.bytes -= old.bytes.len();
            }
        }
        self.bytes += bytes.len();
        let at = std::time::Instant::now();
        self.entries.insert(key, Cached { version, bytes, at });
    }
}

impl Coordinator {
    /// Finds frame `frame` (the job's first by default) of a job in memory and applies
    /// `f` to it under the lock; `None` if the job is not in memory.
    fn locate<T>(
        &self,
        id: JobId,
        frame: Option<u32>,
        f: impl FnOnce(Source<'_>, &FrameMeta) -> T,
    ) -> CoordResult<Option<Located<T>>> {
        let farm = self.lock()?;
        let Some(rt) = farm.runtime.get(&id) else {
            return Ok(None);
        };
        let fr = frame.unwrap_or(rt.job().frames.start);
        if !rt.job().frames.iter().contains(&fr) {
            return Err(frame_error(fr, rt.job().frames));
        }
        let meta = FrameMeta {
            resolved: rt.resolved.clone(),
            stopped: rt.stopped,
            frame: fr,
            version: rt.merges.wrapping_mul(2) + u64::from(rt.stopped.is_some()),
            adaptive: farm.scheduler.adaptive_settings(id),
        };
        if rt.resolved.black {
            return Ok(Some(Located::Done(f(Source::Black, &meta))));
        }
        if let Some(a) = farm.scheduler.adaptive_frame(id, fr) {
            return Ok(Some(Located::Done(f(Source::Adaptive(a), &meta))));
        }
        Ok(Some(match farm.scheduler.residency(id, fr) {
            Some(Residency::Live) => match farm.scheduler.frame(id, fr) {
                Some(acc) => {
                    let errors = rt
                        .tile_error
                        .get((fr - rt.job().frames.start) as usize)
                        .map(Vec::as_slice);
                    Located::Done(f(Source::Merged(acc, errors), &meta))
                }
                None => Located::Done(f(Source::Empty, &meta)),
            },
            Some(Residency::Released) => Located::Store(Box::new(FrameMeta {
                // A released frame no longer changes.
                version: u64::MAX,
                ..meta
            })),
            Some(Residency::Pending) | None => Located::Done(f(Source::Empty, &meta)),
        }))
    }

    /// Applies `f` to a frame, from memory or restored from the store (a released frame,
    /// or a job that finished before this coordinator started). Restoring takes one of
    /// the [`HEAVY_REQUESTS`] permits unless the caller `holds` one already.
    async fn with_frame<T: Send + 'static>(
        &self,
        id: JobId,
        frame: Option<u32>,
        holds: bool,
        f: impl Fn(Source<'_>, &FrameMeta) -> T + Send + Sync + 'static,
    ) -> CoordResult<T> {
        let f = Arc::new(f);
        let g = f.clone();
        let meta = match self.locate(id, frame, move |s, m| g(s, m))? {
            Some(Located::Done(v)) => return Ok(v),
            Some(Located::Store(meta)) => *meta,
            None => self.stored_meta(id, frame).await?,
        };
        let _permit = if holds {
            None
        } else {
            Some(
                self.inner
                    .heavy
                    .acquire()
                    .await
                    .map_err(CoordError::internal)?,
            )
        };
        let stored = self.restore_frame(id, &meta).await?;
        tokio::task::spawn_blocking(move || match &stored {
            StoredFrame::Merged(acc) => f(Source::Merged(acc, None), &meta),
            StoredFrame::Adaptive(a) => f(Source::Adaptive(a), &meta),
            StoredFrame::Black => f(Source::Black, &meta),
        })
        .await
        .map_err(CoordError::internal)
    }

    /// The meta of a frame of a job that is not in memory (finished before this
    /// coordinator started).
    async fn stored_meta(&self, id: JobId, frame: Option<u32>) -> CoordResult<FrameMeta> {
        let store = &*self.inner.store;
        let rec = store
            .get_job(id)
            .await?
            .ok_or_else(|| CoordError::job_not_found(id))?;
        let f = frame.unwrap_or(rec.frames.start);
        if !rec.frames.iter().contains(&f) {
            return Err(frame_error(f, rec.frames));
        }
        let stored = resolve_stored(store, &self.inner.farm, &self.inner.technique, &rec).await?;
        let adaptive = stored.resolved.job.adaptive_settings();
        Ok(FrameMeta {
            adaptive: adaptive.map(|a| a.for_units(rec.passes_per_unit)),
            resolved: stored.resolved,
            stopped: Stop::of_stored(rec.state, rec.error.as_deref()),
            frame: f,
            // Jobs of an earlier run no longer change.
            version: u64::MAX,
        })
    }

    /// A frame rebuilt from its checkpoints: an adaptive job's from the policy state saved
    /// with them, any other's from the merged passes.
    async fn restore_frame(&self, id: JobId, meta: &FrameMeta) -> CoordResult<StoredFrame> {
        if meta.resolved.black {
            return Ok(StoredFrame::Black);
        }
        let plan = meta.resolved.plan;
        let checkpoints = self.inner.store.load_tiles(id, Some(meta.frame)).await?;
        let mut restored =
            restore_frames(plan, [meta.frame], checkpoints).map_err(CoordError::Internal)?;
        if let (Some(settings), false, Some(policy)) = (
            meta.adaptive,
            restored.without_policy,
            restored.policy.pop(),
        ) {
            let frame = AdaptiveFrame::restore(plan, meta.frame, settings, &policy)
                .map_err(|e| CoordError::Internal(format!("job {id}: {e}")))?;
            return Ok(StoredFrame::Adaptive(frame));
        }
        // An adaptive job checkpointed by a build that did not save its policy's state
        // shows its merged passes, as that build did.
        match restored.frames.pop() {
            Some(acc) => Ok(StoredFrame::Merged(acc)),
            None => Err(CoordError::Internal(format!(
                "job {id}: frame {} was not restored",
                meta.frame
            ))),
        }
    }

    /// `GET /jobs/{id}/image`: the current merged image as PNG or EXR, from the cache
    /// while the frame is unchanged.
    pub async fn image(&self, id: JobId, q: ImageQuery) -> CoordResult<Arc<Vec<u8>>> {
        let exr = q.format == ImageFormat::Exr;
        let key = |m: &FrameMeta| (id, m.frame, exr);
        // The cheap question first: which version is current, and is it cached?
        let version = self.locate(id, q.frame, |_, m| (m.frame, m.version))?;
        let probe = match &version {
            Some(Located::Done((frame, v))) => Some((*frame, *v)),
            Some(Located::Store(m)) => Some((m.frame, m.version)),
            None => None,
        };
        if let Some((frame, v)) = probe {
            if let Some(hit) = self.cached(id, frame, exr, v) {
                return Ok(hit);
            }
        }
        // A bounded number of encodes at a time; a request that waited for one of them
        // usually finds its image cached.
        let _permit = self
            .inner
            .heavy
            .acquire()
            .await
            .map_err(CoordError::internal)?;
        if let Some((frame, v)) = probe {
            if let Some(hit) = self.cached(id, frame, exr, v) {
                return Ok(hit);
            }
        }
        let (meta, raw) = self
            .with_frame(id, q.frame, true, move |src, m| {
                let raw = if exr {
                    Raw::Exr(frame_image(&src, &m.resolved.plan))
                } else {
                    Raw::Png(preview_rgb8(&src, &m.resolved.plan))
                };
                (m.clone(), raw)
            })
            .await?;
        let plan = meta.resolved.plan;
        let (stopped, resolved) = (meta.stopped, meta.resolved.clone());
        let bytes = tokio::task::spawn_blocking(move || match raw {
            Raw::Png(rgb) => tessera_image::encode_png_rgb8(plan.width, plan.height, &rgb),
            Raw::Exr(img) => {
                // The verdict of this frame's own image, as `tessera render` writes it.
                let verdict =
                    stopped.map(|s| StopVerdict::of_image(&resolved, &img, s == Stop::TimeLimit));
                let metadata = resolved.metadata_json(verdict.as_ref());
                tessera_image::encode_exr(&img, Some(&metadata))
            }
        })
        .await
        .map_err(CoordError::internal)?
        .map_err(CoordError::internal)?;
        let bytes = Arc::new(bytes);
        if let Ok(mut c) = self.inner.images.lock() {
            c.put(key(&meta), meta.version, bytes.clone());
        }
        Ok(bytes)
    }

    fn cached(&self, id: JobId, frame: u32, exr: bool, version: u64) -> Option<Arc<Vec<u8>>> {
        self.inner
            .images
            .lock()
            .ok()
            .and_then(|c| c.get((id, frame, exr), version))
    }

    /// The current merged image of a frame (the job's first frame by default), as the
    /// EXR of `GET /jobs/{id}/image` encodes it.
    pub async fn frame_image(&self, id: JobId, frame: Option<u32>) -> CoordResult<FrameImage> {
        self.with_frame(id, frame, false, |src, m| {
            frame_image(&src, &m.resolved.plan)
        })
        .await
    }

    /// `GET /jobs/{id}/tiles`: per-tile progress of a frame.
    pub async fn tiles(&self, id: JobId, q: FrameQuery) -> CoordResult<TileMap> {
        self.with_frame(id, q.frame, false, |src, m| tile_map(&src, m))
            .await
    }
}

/// What an image request takes out of the lock to encode.
enum Raw {
    Png(Vec<u8>),
    Exr(FrameImage),
}

/// The frame's image layers.
fn frame_image(src: &Source<'_>, plan: &FramePlan) -> FrameImage {
    match src {
        Source::Adaptive(a) => a.image(),
        Source::Merged(acc, _) => acc.image(),
        Source::Black => FrameImage::black(plan),
        Source::Empty => FrameImage {
            passes: vec![0; plan.width as usize * plan.height as usize],
            samples: vec![0; plan.width as usize * plan.height as usize],
            ..FrameImage::black(plan)
        },
    }
}

/// The beauty as 8-bit sRGB rows, straight from the pixel statistics: the bytes
/// `tessera_image::encode_png` makes of [`frame_image`]'s mean, without the other layers.
fn preview_rgb8(src: &Source<'_>, plan: &FramePlan) -> Vec<u8> {
    let w = plan.width as usize;
    let mut rgb = vec![0u8; w * plan.height as usize * 3];
    let mut put = |x0: u32, y0: u32, width: u32, i: usize, mean: [f64; 3]| {
        let rw = width.max(1) as usize;
        let p = ((y0 as usize + i / rw) * w + x0 as usize + i % rw) * 3;
        for (c, m) in mean.iter().enumerate() {
            rgb[p + c] = (tessera_image::srgb_encode(*m as f32) * 255.0 + 0.5) as u8;
        }
    };
    match src {
        Source::Adaptive(a) => {
            for t in a.tiles() {
                let r = t.rect();
                for (i, s) in t.pixels().iter().enumerate() {
                    put(r.x0, r.y0, r.width, i, s.mean);
                }
            }
        }
        Source::Merged(acc, _) => {
            for t in acc.tiles() {
                let r = t.rect();
                for (i, s) in t.pixels().iter().enumerate() {
                    put(r.x0, r.y0, r.width, i, s.mean);
                }
            }
        }
        Source::Black | Source::Empty => {}
    }
    rgb
}

/// The tile map of a frame.
fn tile_map(src: &Source<'_>, m: &FrameMeta) -> TileMap {
    let plan = m.resolved.plan;
    let tiles = plan
        .tiles()
        .map(|rect| {
            let (passes, error) = tile_progress(src, &plan, rect.index as usize);
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
    TileMap {
        frame: m.frame,
        width: plan.width,
        height: plan.height,
        passes_planned: plan.passes,
        tiles,
    }
}

/// A tile's (passes done, RMS relative error).
fn tile_progress(src: &Source<'_>, plan: &FramePlan, index: usize) -> (u32, Option<f64>) {
    match src {
        Source::Adaptive(a) => {
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
        Source::Merged(acc, errors) => {
            let t = &acc.tiles()[index];
            let (s, n) = match errors.and_then(|e| e.get(index)) {
                Some(&cached) => cached,
                None => tile_error(t),
            };
            (t.merged_passes(), (n > 0).then(|| (s / n as f64).sqrt()))
        }
        Source::Black => (plan.passes, Some(0.0)),
        Source::Empty => (0, None),
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn running_previews_may_be_a_second_old_final_images_never() {
        let mut c = ImageCache::default();
        let png = (1, 0, false);
        let exr = (1, 0, true);
        c.put(png, 10, Arc::new(vec![1]));
        c.put(exr, 10, Arc::new(vec![2]));
        // Newer merges: the fresh PNG is served, the EXR is not.
        assert_eq!(c.get(png, 12).as_deref(), Some(&vec![1]));
        assert!(c.get(exr, 12).is_none());
        // The job stopped (odd version) or the frame was released: only an exact match.
        assert!(c.get(png, 13).is_none());
        assert!(c.get(png, u64::MAX).is_none());
        // Too old for a running job.
        if let Some(e) = c.entries.get_mut(&png) {
            e.at = e.at.checked_sub(PREVIEW_MAX_AGE).unwrap_or(e.at);
        }
        assert!(c.get(png, 12).is_none());
        assert_eq!(c.get(png, 10).as_deref(), Some(&vec![1]));
    }
}
