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
//! requests restore or encode a frame at once.
//!
//! Image encodes are counted in the memory budget (`--memory-budget`,
//! [`tessera_farm::Scheduler::reserve_transient`]): before a request restores, snapshots
//! or encodes a frame it reserves what that will hold ([`encode_bytes`]); a request that
//! does not fit waits for another encode to end, and after [`BUDGET_WAIT`] is refused with
//! 503 and `Retry-After` naming the budget. Waiting rather than refusing at once: encodes
//! are short, and a download that waits a few seconds is better than one the client must
//! retry. The EXR is encoded a block of 16 rows at a time ([`tessera_image::rows`]) from
//! the frame's layers in place: a frame nothing was merged into costs a few rows, a frame
//! restored from the store its merge state, a live frame a 36 B/px snapshot taken under
//! the lock. An EXR larger than [`KEEP_WHOLE_BYTES`] is not kept: its header and offset
//! table are, and the response body is streamed from a second pass of the encoder, 64 KiB
//! at a time, so its bytes are never all in memory.

use std::collections::HashMap;
use std::io::Write;
use std::sync::Arc;
use std::time::Duration;

use axum::body::Bytes;
use tessera_farm::job::StopVerdict;
use tessera_farm::{AdaptiveMode, BiasStats, PixelStats};
use tessera_image::rows::{encode_exr_rows, exr_working_bytes, Exr, FrameRows, Pixel, UniformRows};

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

/// How long an image request waits for room in the memory budget before it is refused
/// (503, with [`RETRY_AFTER_SECONDS`]).
pub const BUDGET_WAIT: Duration = Duration::from_secs(30);
/// The `Retry-After` of an image request refused for lack of memory.
pub const RETRY_AFTER_SECONDS: u64 = 5;
/// The largest encoded EXR built whole in memory (and cached); larger ones are streamed.
pub const KEEP_WHOLE_BYTES: usize = IMAGE_CACHE_BYTES / 4;
/// A streamed body is sent in chunks of this many bytes ...
const STREAM_CHUNK: usize = 64 << 10;
/// ... with at most this many queued for a slow client.
const STREAM_QUEUE: usize = 4;

/// An image response body.
pub enum ImageBody {
    /// The whole file, shared with the image cache.
    Whole(Arc<Vec<u8>>),
    /// A file too large to keep, encoded while it is sent.
    Stream {
        /// Its length in bytes.
        len: u64,
        /// Its bytes in order; an error ends the body early (the encode failed or the
        /// frame changed under it, which a snapshot rules out).
        chunks: tokio::sync::mpsc::Receiver<std::io::Result<Bytes>>,
    },
}

impl std::fmt::Debug for ImageBody {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ImageBody::Whole(bytes) => write!(f, "ImageBody::Whole({} bytes)", bytes.len()),
            ImageBody::Stream { len, .. } => write!(f, "ImageBody::Stream({len} bytes)"),
        }
    }
}

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
    /// Woken when an encode gives its memory back.
    room: Arc<tokio::sync::Notify>,
    /// [`KEEP_WHOLE_BYTES`] unless a test sets another limit.
    keep_whole: Option<usize>,
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
        let adaptive = stored.resolved.adaptive_settings();
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
    /// while the frame is unchanged; the encode's memory is reserved in the budget first.
    pub async fn image(&self, id: JobId, q: ImageQuery) -> CoordResult<ImageBody> {
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
                return Ok(ImageBody::Whole(hit));
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
                return Ok(ImageBody::Whole(hit));
            }
        }
        if exr {
            return self.exr(id, q.frame).await;
        }
        let (kind, plan, adaptive) = self.frame_kind(id, q.frame).await?;
        // A frame restored from the store is the dearest case; reserve for it unless the
        // frame is in memory now (it can only move from memory to the store, not back).
        let _reservation = self
            .reserve(encode_bytes(&plan, false, kind, adaptive))
            .await?;
        let (meta, rgb) = self
            .with_frame(id, q.frame, true, move |src, m| {
                (m.clone(), preview_rgb8(&src, &m.resolved.plan))
            })
            .await?;
        let plan = meta.resolved.plan;
        let bytes = tokio::task::spawn_blocking(move || {
            tessera_image::encode_png_rgb8(plan.width, plan.height, &rgb)
        })
        .await
        .map_err(CoordError::internal)?
        .map_err(CoordError::internal)?;
        let bytes = Arc::new(bytes);
        if let Ok(mut c) = self.inner.images.lock() {
            c.put(key(&meta), meta.version, bytes.clone());
        }
        Ok(ImageBody::Whole(bytes))
    }

    /// The EXR of a frame: whole (and cached) up to [`KEEP_WHOLE_BYTES`], else streamed.
    async fn exr(&self, id: JobId, frame: Option<u32>) -> CoordResult<ImageBody> {
        // The frame can move between the kind the reservation was made for and the
        // encode (a pending frame becomes live, a live one is released to the store):
        // the encode then reserves again for what it finds.
        let mut tries = 0;
        let (reservation, meta, rows) = loop {
            let (kind, plan, adaptive) = self.frame_kind(id, frame).await?;
            let reservation = self
                .reserve(encode_bytes(&plan, true, kind, adaptive))
                .await?;
            if let Some((meta, rows)) = self.exr_rows(id, frame, kind).await? {
                break (reservation, meta, rows);
            }
            tries += 1;
            if tries >= 4 {
                let which =
                    frame.map_or_else(|| "the first frame".into(), |f| format!("frame {f}"));
                return Err(CoordError::Unavailable(format!(
                    "{which} of job {id} keeps moving between memory and the store; retry \
                     in {RETRY_AFTER_SECONDS} s"
                )));
            }
        };
        let key = (id, meta.frame, true);
        let version = meta.version;
        let keep = self
            .inner
            .images
            .lock()
            .ok()
            .and_then(|c| c.keep_whole)
            .unwrap_or(KEEP_WHOLE_BYTES);
        let encoded = tokio::task::spawn_blocking(move || {
            // The verdict of this frame's own image, as `tessera render` writes it.
            let verdict = meta
                .stopped
                .map(|s| verdict(&meta.resolved, &rows, s == Stop::TimeLimit));
            let metadata = meta.resolved.metadata_json(verdict.as_ref());
            encode_exr_rows(&rows, Some(&metadata), keep).map(|e| (e, rows))
        })
        .await
        .map_err(CoordError::internal)?
        .map_err(CoordError::internal)?;
        match encoded {
            (Exr::Whole(bytes), _) => {
                let bytes = Arc::new(bytes);
                if let Ok(mut c) = self.inner.images.lock() {
                    c.put(key, version, bytes.clone());
                }
                Ok(ImageBody::Whole(bytes))
            }
            (Exr::Stream(stream), rows) => {
                let (tx, chunks) = tokio::sync::mpsc::channel(STREAM_QUEUE);
                let len = stream.len();
                // The second pass runs while the body is sent, holding the reservation
                // (not the permit: a slow client must not hold up other downloads, and
                // the memory is what the permit was protecting).
                tokio::task::spawn_blocking(move || {
                    let mut out = ChannelWriter {
                        tx,
                        buf: Vec::with_capacity(STREAM_CHUNK),
                    };
                    let written = stream.write_to(&rows, &mut out);
                    // The memory is given back before the body ends (the sender goes
                    // last), so a client that read the whole body finds it free.
                    drop(rows);
                    drop(reservation);
                    if let Err(e) = written {
                        tracing::warn!("streaming the EXR of job {id} failed: {e}");
                        let _ = out
                            .tx
                            .blocking_send(Err(std::io::Error::other(e.to_string())));
                    }
                });
                Ok(ImageBody::Stream { len, chunks })
            }
        }
    }

    /// Where a frame is, for its reservation: the frame's plan and whether its job is
    /// adaptive.
    async fn frame_kind(
        &self,
        id: JobId,
        frame: Option<u32>,
    ) -> CoordResult<(Kind, FramePlan, bool)> {
        let located = self.locate(id, frame, |src, m| {
            let kind = match src {
                Source::Black | Source::Empty => Kind::Uniform,
                Source::Adaptive(_) | Source::Merged(..) => Kind::Live,
            };
            (kind, m.resolved.plan, m.adaptive.is_some())
        })?;
        Ok(match located {
            Some(Located::Done(v)) => v,
            Some(Located::Store(m)) => (Kind::Store, m.resolved.plan, m.adaptive.is_some()),
            None => {
                let m = self.stored_meta(id, frame).await?;
                (Kind::Store, m.resolved.plan, m.adaptive.is_some())
            }
        })
    }

    /// A frame's layers to encode, if reading them costs no more than `reserved` allows
    /// (`None`: the frame moved; reserve again).
    async fn exr_rows(
        &self,
        id: JobId,
        frame: Option<u32>,
        reserved: Kind,
    ) -> CoordResult<Option<(FrameMeta, Rows)>> {
        let located = self.locate(id, frame, move |src, m| {
            let plan = &m.resolved.plan;
            let rows = match src {
                Source::Black => Rows::Uniform(uniform(plan, true)),
                Source::Empty => Rows::Uniform(uniform(plan, false)),
                // A snapshot, taken under the lock: the merges go on meanwhile.
                _ if reserved < Kind::Live => return None,
                Source::Adaptive(a) => Rows::Image(a.image()),
                Source::Merged(acc, _) => Rows::Image(acc.image()),
            };
            Some((m.clone(), rows))
        })?;
        let meta = match located {
            Some(Located::Done(v)) => return Ok(v),
            _ if reserved < Kind::Store => return Ok(None),
            Some(Located::Store(meta)) => *meta,
            None => self.stored_meta(id, frame).await?,
        };
        let plan = meta.resolved.plan;
        let rows = match self.restore_frame(id, &meta).await? {
            StoredFrame::Black => Rows::Uniform(uniform(&plan, true)),
            StoredFrame::Merged(acc) => {
                let biased = acc.tiles().iter().all(|t| t.bias().is_some());
                Rows::Merged(plan, acc, biased)
            }
            StoredFrame::Adaptive(a) => Rows::adaptive(plan, a),
        };
        Ok(Some((meta, rows)))
    }

    /// Reserves `bytes` of the memory budget for an encode, waiting up to [`BUDGET_WAIT`]
    /// for other encodes to give theirs back.
    async fn reserve(&self, bytes: u64) -> CoordResult<Reservation> {
        let room = self
            .inner
            .images
            .lock()
            .map_err(|_| CoordError::poisoned())?
            .room
            .clone();
        let deadline = tokio::time::Instant::now() + BUDGET_WAIT;
        loop {
            // Registered before the check, so a release between the two is not missed.
            let notified = room.notified();
            tokio::pin!(notified);
            notified.as_mut().enable();
            if self.lock()?.scheduler.reserve_transient(bytes) {
                return Ok(Reservation {
                    core: self.clone(),
                    bytes,
                });
            }
            if tokio::time::timeout_at(deadline, notified).await.is_err() {
                return Err(CoordError::Unavailable(format!(
                    "encoding this image needs {} MiB and the memory budget \
                     (--memory-budget) is held by merge state and other image encodes; \
                     retry in {RETRY_AFTER_SECONDS} s",
                    bytes.div_ceil(1 << 20)
                )));
            }
        }
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

/// Where a frame is, cheapest to encode first.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
enum Kind {
    /// Black or nothing merged: every pixel the same, read from no memory.
    Uniform,
    /// In memory: snapshotted under the lock.
    Live,
    /// Restored from the store's checkpoints.
    Store,
}

/// Bytes an image encode of a frame of `plan` holds at most, reserved in the memory
/// budget before it starts. EXR: the row encoder's working set
/// ([`exr_working_bytes`]) and the file while it is kept whole (at most
/// [`KEEP_WHOLE_BYTES`]; 48 B per pixel bounds it, ZIP never grows a block). PNG: the 8-bit
/// rows (3 B/px), the encoder's filtered copy and its compressed output (at most as much
/// again each). Plus the frame itself: a live frame's 36 B/px snapshot (EXR; the PNG reads
/// the means in place), a stored frame's restored merge state and the checkpoints it is
/// read from (twice [`tessera_farm::frame_state_bytes`]), and an adaptive frame's traced
/// passes (4 B/px).
fn encode_bytes(plan: &FramePlan, exr: bool, kind: Kind, adaptive: bool) -> u64 {
    let n = u64::from(plan.width) * u64::from(plan.height);
    let slack = 64 << 10;
    let encode = if exr {
        exr_working_bytes(plan.width) + (n * 48 + slack).min(KEEP_WHOLE_BYTES as u64)
    } else {
        n * 9 + slack
    };
    encode
        + match kind {
            Kind::Uniform => 0,
            Kind::Live if exr => n * 36,
            Kind::Live => 0,
            Kind::Store => {
                2 * tessera_farm::frame_state_bytes(plan, adaptive)
                    + if adaptive { n * 4 } else { 0 }
            }
        }
}

/// A share of the memory budget held by one encode, given back when dropped.
struct Reservation {
    core: Coordinator,
    bytes: u64,
}

impl Drop for Reservation {
    fn drop(&mut self) {
        if let Ok(mut farm) = self.core.lock() {
            farm.scheduler.release_transient(self.bytes);
        }
        if let Ok(c) = self.core.inner.images.lock() {
            c.room.notify_waiters();
        }
    }
}

/// A blocking writer into a streamed response body, [`STREAM_CHUNK`] bytes a message; it
/// fails once the client is gone, which ends the encode.
struct ChannelWriter {
    tx: tokio::sync::mpsc::Sender<std::io::Result<Bytes>>,
    buf: Vec<u8>,
}

impl ChannelWriter {
    fn send(&mut self) -> std::io::Result<()> {
        if self.buf.is_empty() {
            return Ok(());
        }
        let chunk = std::mem::replace(&mut self.buf, Vec::with_capacity(STREAM_CHUNK));
        self.tx
            .blocking_send(Ok(Bytes::from(chunk)))
            .map_err(|_| std::io::Error::other("the client went away"))
    }
}

impl Write for ChannelWriter {
    fn write(&mut self, data: &[u8]) -> std::io::Result<usize> {
        self.buf.extend_from_slice(data);
        if self.buf.len() >= STREAM_CHUNK {
            self.send()?;
        }
        Ok(data.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.send()
    }
}

/// A frame's layers as the EXR encoder reads them.
enum Rows {
    /// Black or empty.
    Uniform(UniformRows),
    /// A snapshot of a live frame.
    Image(FrameImage),
    /// Merged passes restored from the store, read in place, and whether every tile kept
    /// its bias statistics (the frame then has bias layers, as `FrameAccumulator::image`).
    Merged(FramePlan, FrameAccumulator, bool),
    /// An adaptive frame restored from the store, with each tile's traced passes, and
    /// whether every tile kept its bias statistics (the frame then has bias layers, as
    /// `AdaptiveFrame::image`).
    Adaptive(FramePlan, AdaptiveFrame, Vec<Vec<u32>>, bool),
}

/// Every pixel of a black frame (all passes of zeros) or of one nothing was merged into.
fn uniform(plan: &FramePlan, black: bool) -> UniformRows {
    UniformRows {
        width: plan.width,
        height: plan.height,
        pixel: if black {
            Pixel {
                passes: plan.passes,
                samples: plan.spp(),
                ..Pixel::default()
            }
        } else {
            Pixel::default()
        },
    }
}

/// The bias layers of the last `bias.len()` pixels of `out` (the tile's row just added).
fn set_bias(out: &mut [Pixel], bias: &[BiasStats]) {
    let n = out.len();
    for (p, b) in out[n - bias.len()..].iter_mut().zip(bias) {
        p.bias = b.layers();
    }
}

/// A pixel's layers from its statistics, as `FrameAccumulator::image` writes them.
fn pixel_of(s: &PixelStats, samples: u32) -> Pixel {
    let estimated = s.passes >= 2;
    Pixel {
        mean: s.mean.map(|m| m as f32),
        variance_of_mean: if estimated {
            s.variance_of_mean().map(|v| v as f32)
        } else {
            [0.0; 3]
        },
        passes: s.passes,
        samples,
        relative_error: if estimated {
            s.relative_error() as f32
        } else {
            0.0
        },
        bias: [0.0; 2],
    }
}

impl Rows {
    /// The rows of an adaptive frame restored from the store.
    fn adaptive(plan: FramePlan, a: AdaptiveFrame) -> Self {
        let traced = a
            .tiles()
            .iter()
            .map(|t| t.traced_passes().collect())
            .collect();
        let biased = a.tiles().iter().all(|t| t.bias().is_some());
        Rows::Adaptive(plan, a, traced, biased)
    }

    /// The tile holding (`x`, `y`) and the pixel's index in it.
    fn tile_of(plan: &FramePlan, x: u32, y: u32) -> (usize, u32, u32) {
        // Tile 0 is a full tile in each direction the frame is at least a tile long;
        // a frame shorter than a tile both ways is one tile.
        let edge = plan.get_tile(0).map_or(1, |r| r.width.max(r.height).max(1));
        let t = (y / edge) * plan.tiles_x() + x / edge;
        (t as usize, x % edge, y % edge)
    }

    /// Pixel (`x`, `y`) of a frame restored from the store.
    fn stored_pixel(&self, x: u32, y: u32) -> Pixel {
        match self {
            Rows::Merged(plan, acc, biased) => {
                let (t, lx, ly) = Self::tile_of(plan, x, y);
                let tile = &acc.tiles()[t];
                let rw = tile.rect().width.max(1);
                let samples = tile.merged_passes().saturating_mul(plan.samples_per_pass);
                let i = (ly * rw + lx) as usize;
                let mut p = pixel_of(&tile.pixels()[i], samples);
                if *biased {
                    p.bias = tile.bias().map_or([0.0; 2], |b| b[i].layers());
                }
                p
            }
            Rows::Adaptive(plan, a, traced, biased) => {
                let (t, lx, ly) = Self::tile_of(plan, x, y);
                let tile = &a.tiles()[t];
                let i = (ly * tile.rect().width.max(1) + lx) as usize;
                let samples = traced[t][i].saturating_mul(plan.samples_per_pass);
                let mut p = pixel_of(&tile.pixels()[i], samples);
                if *biased {
                    p.bias = tile.bias().map_or([0.0; 2], |b| b[i].layers());
                }
                p
            }
            Rows::Uniform(u) => u.pixel,
            Rows::Image(img) => img.pixel(x, y),
        }
    }
}

impl FrameRows for Rows {
    fn width(&self) -> u32 {
        match self {
            Rows::Uniform(u) => u.width,
            Rows::Image(img) => img.width,
            Rows::Merged(plan, ..) | Rows::Adaptive(plan, ..) => plan.width,
        }
    }
    fn height(&self) -> u32 {
        match self {
            Rows::Uniform(u) => u.height,
            Rows::Image(img) => img.height,
            Rows::Merged(plan, ..) | Rows::Adaptive(plan, ..) => plan.height,
        }
    }
    fn pixel(&self, x: u32, y: u32) -> Pixel {
        self.stored_pixel(x, y)
    }
    fn has_bias(&self) -> bool {
        match self {
            Rows::Image(img) => img.has_bias(),
            // Only where every tile kept its bias statistics, as `FrameAccumulator::image`
            // and `AdaptiveFrame::image`.
            Rows::Merged(_, _, biased) | Rows::Adaptive(_, _, _, biased) => *biased,
            Rows::Uniform(_) => false,
        }
    }
    fn row(&self, y: u32, out: &mut Vec<Pixel>) {
        out.clear();
        match self {
            Rows::Uniform(u) => out.resize(u.width as usize, u.pixel),
            Rows::Image(img) => {
                let w = img.width as usize;
                out.extend((0..w).map(|x| img.pixel(x as u32, y)));
            }
            // Tile by tile along the row: each tile's row is contiguous.
            Rows::Merged(plan, acc, biased) => {
                let mut x = 0;
                while x < plan.width {
                    let (t, _, ly) = Self::tile_of(plan, x, y);
                    let tile = &acc.tiles()[t];
                    let width = tile.rect().width.max(1);
                    let samples = tile.merged_passes().saturating_mul(plan.samples_per_pass);
                    let start = (ly * width) as usize;
                    let row = &tile.pixels()[start..start + width as usize];
                    out.extend(row.iter().map(|s| pixel_of(s, samples)));
                    if let (true, Some(bias)) = (*biased, tile.bias()) {
                        set_bias(out, &bias[start..start + width as usize]);
                    }
                    x += width;
                }
            }
            Rows::Adaptive(plan, a, traced, biased) => {
                let mut x = 0;
                while x < plan.width {
                    let (t, _, ly) = Self::tile_of(plan, x, y);
                    let tile = &a.tiles()[t];
                    let width = tile.rect().width.max(1);
                    let start = (ly * width) as usize;
                    let row = &tile.pixels()[start..start + width as usize];
                    let passes = &traced[t][start..start + width as usize];
                    out.extend(
                        row.iter()
                            .zip(passes)
                            .map(|(s, &p)| pixel_of(s, p.saturating_mul(plan.samples_per_pass))),
                    );
                    if let (true, Some(bias)) = (*biased, tile.bias()) {
                        set_bias(out, &bias[start..start + width as usize]);
                    }
                    x += width;
                }
            }
        }
    }
}

/// The stop verdict a stopped job's EXR header states: [`StopVerdict::of_image`] of the
/// frame's image, with the estimate read from the rows rather than a built image.
fn verdict(resolved: &ResolvedJob, rows: &Rows, time_limit: bool) -> StopVerdict {
    if let Rows::Image(img) = rows {
        return StopVerdict::of_image(resolved, img, time_limit);
    }
    StopVerdict {
        time_limit,
        target: resolved.job.target_error,
        estimate: tessera_image::rows::error_estimate(rows, resolved.error_estimator()),
        spp: resolved.plan.spp(),
        unbiased: resolved.job.adaptive == AdaptiveMode::Unbiased,
        unsampled: StopVerdict::unsampled_of(resolved),
    }
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
    use crate::service::CoordinatorConfig;
    use tessera_api::JobSettings;

    /// The bytes of an image response.
    async fn body(b: ImageBody) -> Vec<u8> {
        match b {
            ImageBody::Whole(b) => b.to_vec(),
            ImageBody::Stream { len, mut chunks } => {
                let mut out = Vec::new();
                while let Some(c) = chunks.recv().await {
                    out.extend_from_slice(&c.unwrap());
                }
                assert_eq!(out.len() as u64, len);
                out
            }
        }
    }

    /// Several concurrent EXR downloads of a large frame nothing was merged into (the
    /// case that held 2.37 GB for one 8700x5800 EXR: the frame's layers, its channels
    /// and the file were built whole) are encoded a block of rows at a time and streamed,
    /// each reserving its working set in the memory budget: the budget's accounting never
    /// exceeds it, requests that do not fit wait instead, and every download is the
    /// whole-file encoding byte for byte.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn concurrent_exr_downloads_stay_inside_the_memory_budget() {
        let dir = tempfile::tempdir().unwrap();
        let cfg = CoordinatorConfig::new(dir.path());
        let core = Coordinator::open(cfg).await.unwrap();
        let mut job = JobSettings::new("builtin:cornell-box");
        (job.width, job.height, job.spp) = (Some(1600), Some(1200), 4);
        let (status, _) = core.submit(job, None).await.unwrap();
        let id = status.id;
        let q = ImageQuery {
            format: ImageFormat::Exr,
            frame: None,
        };
        let whole = body(core.image(id, q).await.unwrap()).await;
        // From now on nothing is kept whole (or cached): every request streams.
        {
            let mut c = core.inner.images.lock().unwrap();
            c.keep_whole = Some(0);
            c.entries.clear();
            c.bytes = 0;
        }
        let plan = {
            let farm = core.lock().unwrap();
            farm.runtime[&id].resolved.plan
        };
        let one = encode_bytes(&plan, true, Kind::Uniform, false);
        // Room for two encodes at a time: six more requests must wait for room.
        let budget = 2 * one + one / 2;
        core.lock().unwrap().scheduler.set_memory_budget(budget);
        let before = core.lock().unwrap().scheduler.memory_high_water();
        let downloads: Vec<_> = (0..8)
            .map(|_| {
                let core = core.clone();
                tokio::spawn(async move { body(core.image(id, q).await.unwrap()).await })
            })
            .collect();
        for d in downloads {
            assert!(
                d.await.unwrap() == whole,
                "a streamed EXR differs from the whole one"
            );
        }
        let farm = core.lock().unwrap();
        assert_eq!(farm.scheduler.transient_bytes(), 0, "a reservation leaked");
        let high = farm.scheduler.memory_high_water().max(before);
        assert!(high <= budget, "{high} > {budget}");
        // The whole file of the old encoder held about 130 B per pixel at once, so the
        // bound above is a real one: the frame's layers alone would not fit it.
        let n = u64::from(plan.width) * u64::from(plan.height);
        assert!(budget < n * 36, "{budget} vs {}", n * 36);
    }

    /// An adaptive frame of a biased technique (vcm, ppm) rebuilt from its tiles'
    /// checkpoints, as a finished frame's image is served from the store, encodes the
    /// EXR its live image does, bias layers included, and states the same estimate (the
    /// bias term added: above the pass spread alone), in both adaptive modes.
    #[test]
    fn a_stored_adaptive_frame_keeps_its_bias_layers_and_estimate() {
        use tessera_farm::{ErrorEstimator, UnitResult};
        // A reproducible value in [0, 1) for (pass, pixel, salt) (splitmix64).
        let value = |pass: u32, i: usize, salt: u64| {
            let mut x = ((u64::from(pass) << 32) ^ (i as u64) ^ (salt << 56))
                .wrapping_add(0x9e37_79b9_7f4a_7c15);
            x = (x ^ (x >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            x = (x ^ (x >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            ((x ^ (x >> 31)) >> 11) as f32 / (1u64 << 53) as f32
        };
        let plan = FramePlan::new(12, 10, 8, 1, 24).unwrap();
        for mode in [AdaptiveMode::Sequential, AdaptiveMode::Unbiased] {
            let settings = AdaptiveSettings {
                mode,
                target_error: 0.05,
                ..Default::default()
            };
            let mut live = AdaptiveFrame::new(plan, 0, settings).unwrap();
            for u in plan.units(0, 4) {
                let rect = plan.get_tile(u.tile).unwrap();
                let n = rect.pixel_count();
                let (mut pass_means, mut bias) = (Vec::new(), Vec::new());
                for pass in u.first_pass..u.first_pass + u.pass_count {
                    for i in 0..n {
                        let v = 0.2 + value(pass, i, u64::from(u.tile));
                        pass_means.push([v, 0.5 * v, 0.25 * v]);
                        bias.push(0.3 * value(pass, i, 100 + u64::from(u.tile)) - 0.05);
                    }
                }
                let r = UnitResult {
                    unit: u,
                    width: rect.width,
                    height: rect.height,
                    pass_means,
                    rejected_samples: 0,
                    bias: Some(bias),
                };
                live.offer(&r).unwrap();
            }
            let cps: Vec<_> = live.tiles().iter().map(|t| Some(t.checkpoint())).collect();
            let stored = AdaptiveFrame::restore(plan, 0, settings, &cps).unwrap();
            let rows = Rows::adaptive(plan, stored);
            let image = live.image();
            assert!(image.has_bias() && rows.has_bias(), "{mode:?}");
            let exr = |r: &dyn FrameRows| match encode_exr_rows(r, None, usize::MAX).unwrap() {
                Exr::Whole(b) => b,
                Exr::Stream(_) => unreachable!("no limit"),
            };
            assert!(
                exr(&rows) == exr(&image),
                "{mode:?}: the stored frame's EXR differs from the live one's"
            );
            let estimator = ErrorEstimator::for_mode(mode);
            let estimate = tessera_image::rows::error_estimate(&rows, estimator);
            assert!(estimate.is_some(), "{mode:?}");
            assert_eq!(estimate, image.error_estimate(estimator), "{mode:?}");
            let spread = FrameImage {
                bias: None,
                ..image.clone()
            }
            .error_estimate(estimator);
            assert!(estimate > spread, "{mode:?}: {estimate:?} vs {spread:?}");
        }
    }

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
