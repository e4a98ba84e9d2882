//! The coordinator's job life cycle over the store and the scheduler: submission,
//! durable checkpoints as passes merge, resume after a restart, status, images, cancel.
//!
//! # Durability (ARCHITECTURE.md §6)
//! The store is the truth. A job is inserted before `POST /jobs` answers. A result is
//! merged in memory and its tile's checkpoint committed *before* the worker is told the
//! result was accepted, so an accepted pass survives `kill -9`. Checkpoint writes are
//! serialized by one async lock, and each snapshot is taken under that lock, so a newer
//! snapshot of a tile can never be overwritten by an older one. Lease ids are reserved in
//! blocks ([`LEASE_ID_BLOCK`]) whose end is committed before any lease of the block is
//! handed out, so fencing tokens never repeat after a restart.
//!
//! # Restart
//! [`Coordinator::open`] reloads every job that was not finished, rebuilds its
//! accumulators from the tile checkpoints (bit-exact Welford state) and puts the rest of
//! its units back in the queue. For a grace period no new lease is handed out, so workers
//! that were rendering when the coordinator died can reconnect and deliver their results;
//! those answer leases of the previous run and are adopted (validated, merged once).

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use tessera_api::{
    ApiError, ErrorCode, FrameQuery, History, HistoryPoint, ImageFormat, ImageQuery, JobList,
    JobListQuery, JobSettings, JobState, JobStatus, ResolvedJob, SceneRef, SceneUploaded, TileInfo,
    TileMap, ValidatedJob, WorkerInfo, WorkerList, WorkerState,
};
use tessera_farm::{
    FrameAccumulator, FrameImage, JobId, Submitted, TileAccumulator, UnitResult, WorkerId,
};
use tessera_scene::job::{load_job_scene, resolve_job};
use tessera_scene::Scene;

use crate::grpc::{now_ms, Farm, JobEntry, WorkerEntry};
use crate::store::{
    FaultEvent, FaultFilter, FaultKind, JobOrder, JobQuery, JobRecord, NewJob, SqliteStore, Store,
    StoreError, TileCheckpoint, UnitDigest,
};

/// Lease ids are reserved in blocks of this many (one store write per block).
pub const LEASE_ID_BLOCK: u64 = 4096;
/// Largest accepted scene upload.
pub const MAX_SCENE_BYTES: usize = 256 << 20;
/// Largest page of `GET /jobs`.
pub const MAX_PAGE: u32 = 200;
/// History points are recorded at most this often per job (plus the last one).
const HISTORY_INTERVAL_MS: u64 = 200;

/// How to run a coordinator.
#[derive(Clone, Debug)]
pub struct CoordinatorConfig {
    /// Directory of the SQLite store.
    pub data_dir: PathBuf,
    /// Bearer token required on the HTTP API, if any.
    pub api_token: Option<String>,
    /// Bearer token workers must present, if any.
    pub worker_token: Option<String>,
    /// How long a lease lasts without a heartbeat, ms.
    pub lease_ms: u64,
    /// How often workers heartbeat, ms.
    pub heartbeat_ms: u32,
    /// After a restart: how long to wait for workers to reconnect before leasing again, ms.
    pub grace_ms: u64,
    /// Passes per work unit.
    pub passes_per_unit: u32,
}

impl CoordinatorConfig {
    /// Defaults for a data directory: 10 s leases, 1 s heartbeats, 3 s restart grace, one
    /// pass per unit, no tokens.
    pub fn new(data_dir: impl Into<PathBuf>) -> Self {
        Self {
            data_dir: data_dir.into(),
            api_token: None,
            worker_token: None,
            lease_ms: 10_000,
            heartbeat_ms: 1_000,
            grace_ms: 3_000,
            passes_per_unit: 1,
        }
    }
}

/// What the coordinator keeps about a job besides the scheduler's state.
#[derive(Debug, Clone)]
pub struct JobRuntime {
    /// The settings as submitted (defaults filled in).
    pub settings: JobSettings,
    /// The validated settings.
    pub job: ValidatedJob,
    /// The job resolved against its scene.
    pub resolved: ResolvedJob,
    /// Life-cycle state.
    pub state: JobState,
    /// When it was accepted, Unix ms.
    pub created_unix_ms: u64,
    /// When it started running, Unix ms.
    pub started_unix_ms: Option<u64>,
    /// When it finished, Unix ms.
    pub finished_unix_ms: Option<u64>,
    /// Why it failed.
    pub error: Option<String>,
    /// Faulty-worker events on it.
    pub faults: u64,
    /// Per frame, per tile: (sum of squared relative errors, pixel count) of the tiles with
    /// at least two passes, kept incrementally so the image error costs O(tiles).
    tile_error: Vec<Vec<(f64, u64)>>,
    /// Per frame, per tile: the samples its renderers rejected as invalid.
    tile_rejected: Vec<Vec<TileRejected>>,
    last_history_ms: u64,
    /// Convergence history (also in the store).
    pub history: Vec<HistoryPoint>,
    /// Why a done job stopped, as `tessera render` says it ("finished", "time limit
    /// reached"); recorded in the EXR header of jobs that stop early.
    pub stopped: Option<&'static str>,
}

impl JobRuntime {
    fn error_estimate(&self) -> Option<f64> {
        let (mut sum, mut n) = (0.0, 0u64);
        let mut all = true;
        for frame in &self.tile_error {
            for &(s, c) in frame {
                if c == 0 {
                    all = false;
                }
                sum += s;
                n += c;
            }
        }
        (all && n > 0).then(|| (sum / n as f64).sqrt())
    }

    fn rejected_samples(&self) -> u64 {
        self.tile_rejected
            .iter()
            .flatten()
            .map(TileRejected::total)
            .sum()
    }

    fn elapsed_seconds(&self, now: u64) -> f64 {
        match self.started_unix_ms {
            Some(s) => (self.finished_unix_ms.unwrap_or(now).saturating_sub(s)) as f64 / 1e3,
            None => 0.0,
        }
    }
}

/// The samples a tile's renderers rejected as invalid (`UnitResult::rejected_samples`),
/// kept so that a restart neither loses nor double-counts them: the count of the merged
/// passes is checkpointed with the tile; units buffered ahead of a missing earlier pass
/// are lost on a restart and rendered again, so their counts wait apart until they merge.
#[derive(Debug, Clone, Default)]
struct TileRejected {
    /// In the merged passes (what the checkpoint stores).
    merged: u64,
    /// Of accepted units not merged yet: (first pass, count), non-zero counts only.
    buffered: Vec<(u32, u64)>,
}

impl TileRejected {
    /// Records an accepted unit starting at `first_pass` with `count` rejected samples,
    /// the tile having `merged_passes` merged passes after it.
    fn accept(&mut self, first_pass: u32, count: u64, merged_passes: u32) {
        if count > 0 {
            self.buffered.push((first_pass, count));
        }
        let merged = &mut self.merged;
        self.buffered.retain(|&(pass, n)| {
            let done = pass < merged_passes;
            if done {
                *merged += n;
            }
            !done
        });
    }

    fn total(&self) -> u64 {
        self.merged + self.buffered.iter().map(|b| b.1).sum::<u64>()
    }
}

fn tile_error(tile: &TileAccumulator) -> (f64, u64) {
    if tile.merged_passes() < 2 {
        return (0.0, 0);
    }
    let mut sum = 0.0;
    for p in tile.pixels() {
        let r = p.relative_error();
        sum += r * r;
    }
    (sum, tile.pixels().len() as u64)
}

/// The coordinator: shared by the HTTP routes, the gRPC service and the ticker.
#[derive(Clone)]
pub struct Coordinator {
    inner: Arc<Inner>,
}

struct Inner {
    farm: Arc<Mutex<Farm>>,
    store: Arc<dyn Store>,
    cfg: CoordinatorConfig,
    /// Serializes store writes of merged state (see the module docs).
    write: tokio::sync::Mutex<()>,
    /// Lease ids up to this are reserved in the store.
    lease_reserved: Mutex<u64>,
    /// No leases are handed out before this (Unix ms): the restart grace period.
    lease_blocked_until_ms: u64,
    /// Set when the coordinator started, for uptime.
    started: Instant,
}

/// Why a request failed, as the HTTP API reports it.
pub type ApiResult<T> = Result<T, ApiError>;

fn internal(e: impl std::fmt::Display) -> ApiError {
    ApiError::new(ErrorCode::Internal, format!("internal error: {e}"))
}

fn store_err(e: StoreError) -> ApiError {
    tracing::error!(error = %e, "store failure");
    internal(e)
}

impl Coordinator {
    /// Opens the store in `cfg.data_dir` and resumes every unfinished job in it.
    pub async fn open(cfg: CoordinatorConfig) -> Result<Self, StoreError> {
        let store: Arc<dyn Store> = Arc::new(SqliteStore::open(&cfg.data_dir).await?);
        Self::with_store(cfg, store).await
    }

    /// Like [`Coordinator::open`] over a given store.
    pub async fn with_store(
        cfg: CoordinatorConfig,
        store: Arc<dyn Store>,
    ) -> Result<Self, StoreError> {
        let high_water = store.max_lease_id().await?;
        let mut farm = Farm::with_first_lease(cfg.lease_ms, high_water);
        let resumable = store.jobs_to_resume().await?;
        let resumed = !resumable.is_empty();
        let mut failed = Vec::new();
        for rec in resumable {
            match Self::resume_job(&*store, &mut farm, &rec, cfg.passes_per_unit).await {
                Ok(()) => tracing::info!(job = rec.id, "resumed"),
                Err(e) => {
                    tracing::error!(job = rec.id, error = %e, "cannot resume job");
                    failed.push((rec.id, e));
                }
            }
        }
        for (id, e) in failed {
            store
                .set_job_state(id, JobState::Failed, Some(e), now_ms())
                .await?;
        }
        let blocked = if resumed { now_ms() + cfg.grace_ms } else { 0 };
        // Leases of the previous run may still be held by reconnecting workers.
        farm.scheduler.grace(blocked + cfg.lease_ms);
        Ok(Self {
            inner: Arc::new(Inner {
                farm: Arc::new(Mutex::new(farm)),
                store,
                cfg,
                write: tokio::sync::Mutex::new(()),
                lease_reserved: Mutex::new(high_water),
                lease_blocked_until_ms: blocked,
                started: Instant::now(),
            }),
        })
    }

    async fn resume_job(
        store: &dyn Store,
        farm: &mut Farm,
        rec: &JobRecord,
        _default_ppu: u32,
    ) -> Result<(), String> {
        let settings: JobSettings = serde_json::from_str(&rec.settings_json)
            .map_err(|e| format!("stored settings are unreadable: {e}"))?;
        let job = settings.validate().map_err(|e| e.to_string())?;
        let scene = load_scene(store, farm, &job.scene, job.camera.as_deref()).await?;
        let resolved = resolve_job(&job, &scene).map_err(|e| e.to_string())?;
        if resolved.plan != rec.plan {
            return Err("the stored frame plan differs from this build's plan".into());
        }
        let plan = rec.plan;
        let mut frames: Vec<FrameAccumulator> = rec
            .frames
            .iter()
            .map(|f| FrameAccumulator::for_frame(plan, f))
            .collect();
        let mut tile_rejected =
            vec![vec![TileRejected::default(); plan.tile_count() as usize]; frames.len()];
        for cp in store
            .load_tiles(rec.id, None)
            .await
            .map_err(|e| e.to_string())?
        {
            let Some(fi) = frames.iter().position(|f| f.frame() == cp.frame) else {
                return Err(format!("checkpoint of frame {} outside the job", cp.frame));
            };
            let acc = &mut frames[fi];
            if let Some(r) = tile_rejected[fi].get_mut(cp.tile as usize) {
                r.merged = cp.rejected_samples;
            }
            let rect = plan
                .get_tile(cp.tile)
                .ok_or_else(|| format!("checkpoint of unknown tile {}", cp.tile))?;
            let units: Vec<(u32, u32, u64)> = cp
                .units
                .iter()
                .map(|u| (u.first_pass, u.pass_count, u.digest))
                .collect();
            let tile = TileAccumulator::restore(rect, cp.merged_passes, cp.pixels, &units)?;
            acc.restore_tile(tile)?;
        }
        let tile_error = if job.adaptive_settings().is_some() {
            // The adaptive policy's per-pixel state is not checkpointed: an adaptive job
            // starts again from its first pass after a restart (its result is the same).
            add_to_scheduler(farm, rec.id, rec.priority, plan, &job, rec.passes_per_unit)
                .map_err(|e| e.message)?;
            tile_rejected
                .iter_mut()
                .flatten()
                .for_each(|r| *r = TileRejected::default());
            vec![vec![(0.0, 0); plan.tile_count() as usize]; rec.frames.count() as usize]
        } else {
            let te = frames
                .iter()
                .map(|f| f.tiles().iter().map(tile_error).collect())
                .collect();
            farm.scheduler.add_resumed_job(
                rec.id,
                rec.priority,
                plan,
                frames,
                rec.passes_per_unit,
            )?;
            te
        };
        farm.jobs.insert(
            rec.id,
            JobEntry {
                scene: job.scene.clone(),
                camera: job.camera.clone(),
                settings: resolved.config,
                plan,
            },
        );
        let history = store.list_history(rec.id).await.unwrap_or_default();
        let faults = store
            .count_faults(&FaultFilter {
                job: Some(rec.id),
                worker: None,
            })
            .await
            .unwrap_or(0);
        farm.runtime.insert(
            rec.id,
            JobRuntime {
                settings,
                job,
                resolved,
                state: rec.state,
                created_unix_ms: rec.created_unix_ms,
                started_unix_ms: rec.started_unix_ms,
                finished_unix_ms: None,
                error: None,
                faults,
                tile_error,
                tile_rejected,
                last_history_ms: 0,
                history,
                stopped: (rec.state == JobState::Done).then_some("finished"),
            },
        );
        Ok(())
    }

    /// The configuration.
    pub fn config(&self) -> &CoordinatorConfig {
        &self.inner.cfg
    }

    /// The farm state shared with the gRPC service.
    pub fn farm(&self) -> Arc<Mutex<Farm>> {
        self.inner.farm.clone()
    }

    /// The store.
    pub fn store(&self) -> Arc<dyn Store> {
        self.inner.store.clone()
    }

    fn lock(&self) -> ApiResult<MutexGuard<'_, Farm>> {
        self.inner
            .farm
            .lock()
            .map_err(|_| internal("farm state poisoned"))
    }

    /// Seconds since this coordinator started.
    pub fn uptime_seconds(&self) -> f64 {
        self.inner.started.elapsed().as_secs_f64()
    }

    // ------------------------------------------------------------------------------------
    // Scenes

    /// Stores an uploaded scene (a .glb or a self-contained .gltf) after checking that it
    /// loads; returns its content hash and statistics.
    pub async fn upload_scene(&self, bytes: Vec<u8>) -> ApiResult<SceneUploaded> {
        use sha2::{Digest, Sha256};
        if bytes.is_empty() {
            return Err(ApiError::new(
                ErrorCode::InvalidRequest,
                "the scene upload is empty: send the bytes of a .glb or .gltf file",
            ));
        }
        if bytes.len() > MAX_SCENE_BYTES {
            return Err(ApiError::new(
                ErrorCode::TooLarge,
                format!(
                    "the scene is {} bytes, more than the limit of {MAX_SCENE_BYTES}",
                    bytes.len()
                ),
            ));
        }
        let hash = hex(&Sha256::digest(&bytes));
        let bytes = Arc::new(bytes);
        let b2 = bytes.clone();
        let name = format!("scene {hash}");
        let scene = tokio::task::spawn_blocking(move || {
            tessera_scene::gltf_import::load_slice(&b2, &name, None, None)
        })
        .await
        .map_err(internal)?
        .map_err(|e| ApiError::new(ErrorCode::InvalidScene, format!("invalid scene: {e}")))?;
        self.inner
            .store
            .put_scene(&hash, &bytes)
            .await
            .map_err(store_err)?;
        let out = SceneUploaded {
            hash: hash.clone(),
            bytes: bytes.len() as u64,
            triangles: scene.triangle_count() as u64,
            meshes: scene.meshes.len() as u32,
            materials: scene.materials.len() as u32,
            lights: (scene.lights.len()
                + scene
                    .meshes
                    .iter()
                    .filter(|m| {
                        scene
                            .materials
                            .get(m.material as usize)
                            .is_some_and(|mat| mat.emission.max_element() > 0.0)
                    })
                    .count()) as u32,
        };
        self.lock()?.scenes.insert(hash, bytes);
        Ok(out)
    }

    /// Builds a job's scene: a built-in one, or an uploaded one from the farm's cache or
    /// the store (then cached for the workers' FetchScene). Errors name the `scene` field.
    async fn scene(&self, scene_ref: &SceneRef, camera: Option<&str>) -> ApiResult<Scene> {
        let bytes = match scene_ref {
            SceneRef::Hash(h) => {
                let cached = self.lock()?.scenes.get(h).cloned();
                let b = match cached {
                    Some(b) => b,
                    None => {
                        let stored = self.inner.store.get_scene(h).await.map_err(store_err)?;
                        let missing = || {
                            ApiError::invalid_field(
                                "scene",
                                format!("no uploaded scene has hash {h}: POST it to /api/v1/scenes first"),
                            )
                        };
                        Arc::new(stored.ok_or_else(missing)?)
                    }
                };
                self.lock()?.scenes.insert(h.clone(), b.clone());
                Some(b)
            }
            SceneRef::Builtin(_) => None,
        };
        let (scene_ref, camera) = (scene_ref.clone(), camera.map(str::to_owned));
        tokio::task::spawn_blocking(move || {
            load_job_scene(
                &scene_ref,
                bytes.as_deref().map(|b| b.as_slice()),
                camera.as_deref(),
            )
        })
        .await
        .map_err(internal)?
        .map_err(|e| ApiError::invalid_field("scene", e))
    }

    // ------------------------------------------------------------------------------------
    // Jobs

    /// Accepts a job: validates it, resolves it against its scene, stores it, queues it.
    /// With an idempotency key already used, returns the job created then.
    pub async fn submit(
        &self,
        settings: JobSettings,
        idempotency_key: Option<String>,
    ) -> ApiResult<(JobStatus, bool)> {
        if let Some(k) = &idempotency_key {
            if k.is_empty() || k.len() > 200 || k.chars().any(char::is_control) {
                return Err(ApiError::invalid_field(
                    "idempotency-key",
                    "must be 1 to 200 printable characters",
                ));
            }
        }
        let job = settings.validate()?;
        let scene = self.scene(&job.scene, job.camera.as_deref()).await?;
        let resolved = resolve_job(&job, &scene)?;
        let adaptive = job.adaptive_settings();
        if let Some(a) = &adaptive {
            a.validate(resolved.plan.passes)
                .map_err(|e| ApiError::invalid_field("adaptive", e))?;
        }
        let settings_json = serde_json::to_string(&settings).map_err(internal)?;
        let created = now_ms();
        let (id, new) = self
            .inner
            .store
            .insert_job(NewJob {
                settings_json,
                plan: resolved.plan,
                frames: job.frames,
                passes_per_unit: self.inner.cfg.passes_per_unit,
                priority: job.priority,
                scene_ref: job.scene.to_string(),
                name: job.name.clone(),
                idempotency_key,
                created_unix_ms: created,
            })
            .await
            .map_err(store_err)?;
        if !new {
            return Ok((self.status(id).await?, false));
        }
        let black = resolved.black;
        {
            let mut farm = self.lock()?;
            let frames = job.frames;
            if !black {
                add_to_scheduler(
                    &mut farm,
                    id,
                    job.priority,
                    resolved.plan,
                    &job,
                    self.inner.cfg.passes_per_unit,
                )?;
                farm.jobs.insert(
                    id,
                    JobEntry {
                        scene: job.scene.clone(),
                        camera: job.camera.clone(),
                        settings: resolved.config,
                        plan: resolved.plan,
                    },
                );
            }
            let tiles = resolved.plan.tile_count() as usize;
            farm.runtime.insert(
                id,
                JobRuntime {
                    settings,
                    job,
                    tile_error: vec![vec![(0.0, 0); tiles]; frames.count() as usize],
                    tile_rejected: vec![
                        vec![TileRejected::default(); tiles];
                        frames.count() as usize
                    ],
                    resolved,
                    state: JobState::Queued,
                    created_unix_ms: created,
                    started_unix_ms: None,
                    finished_unix_ms: None,
                    error: None,
                    faults: 0,
                    last_history_ms: 0,
                    history: Vec::new(),
                    stopped: None,
                },
            );
        }
        if black {
            // Nothing to trace: the plan found no light (ARCHITECTURE.md §4).
            self.set_state(id, JobState::Running, None).await?;
            self.set_state(id, JobState::Done, None).await?;
        }
        Ok((self.status(id).await?, true))
    }

    async fn set_state(&self, id: JobId, state: JobState, error: Option<String>) -> ApiResult<()> {
        let now = now_ms();
        self.inner
            .store
            .set_job_state(id, state, error.clone(), now)
            .await
            .map_err(store_err)?;
        let mut farm = self.lock()?;
        if let Some(rt) = farm.runtime.get_mut(&id) {
            rt.state = state;
            if state == JobState::Running && rt.started_unix_ms.is_none() {
                rt.started_unix_ms = Some(now);
            }
            if state == JobState::Done && rt.stopped.is_none() {
                rt.stopped = Some("finished");
            }
            if state.is_terminal() {
                rt.finished_unix_ms = Some(now);
                if rt.started_unix_ms.is_none() {
                    rt.started_unix_ms = Some(now);
                }
            }
            rt.error = error;
        }
        Ok(())
    }

    /// The status of a job.
    pub async fn status(&self, id: JobId) -> ApiResult<JobStatus> {
        if let Some(s) = self.live_status(id)? {
            return Ok(s);
        }
        let rec = self
            .inner
            .store
            .get_job(id)
            .await
            .map_err(store_err)?
            .ok_or_else(|| not_found(id))?;
        self.stored_status(&rec).await
    }

    fn live_status(&self, id: JobId) -> ApiResult<Option<JobStatus>> {
        let farm = self.lock()?;
        let Some(rt) = farm.runtime.get(&id) else {
            return Ok(None);
        };
        Ok(Some(status_of(&farm, id, rt)))
    }

    /// Status of a job that is no longer in memory (finished before a restart): built from
    /// the store.
    async fn stored_status(&self, rec: &JobRecord) -> ApiResult<JobStatus> {
        let settings: JobSettings = serde_json::from_str(&rec.settings_json)
            .unwrap_or_else(|_| JobSettings::new(rec.scene_ref.clone()));
        let tiles = self
            .inner
            .store
            .load_tiles(rec.id, None)
            .await
            .map_err(store_err)?;
        let plan = rec.plan;
        let passes_done: u64 = tiles.iter().map(|t| u64::from(t.merged_passes)).sum();
        let rejected_samples: u64 = tiles.iter().map(|t| t.rejected_samples).sum();
        let frames_total = rec.frames.count() as u32;
        let tiles_total = u64::from(plan.tile_count()) * u64::from(frames_total);
        let passes_planned = tiles_total * u64::from(plan.passes);
        let history = self
            .inner
            .store
            .list_history(rec.id)
            .await
            .map_err(store_err)?;
        let faults = self
            .inner
            .store
            .count_faults(&FaultFilter {
                job: Some(rec.id),
                worker: None,
            })
            .await
            .map_err(store_err)?;
        let pixels = f64::from(plan.width) * f64::from(plan.height) * f64::from(frames_total);
        let samples: f64 = tiles
            .iter()
            .map(|t| t.pixels.len() as f64 * f64::from(t.merged_passes))
            .sum::<f64>()
            * f64::from(plan.samples_per_pass);
        let elapsed = match (rec.started_unix_ms, rec.finished_unix_ms) {
            (Some(s), Some(f)) => f.saturating_sub(s) as f64 / 1e3,
            (Some(s), None) => now_ms().saturating_sub(s) as f64 / 1e3,
            _ => 0.0,
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
            frames_done: if rec.state == JobState::Done {
                frames_total
            } else {
                0
            },
            tiles_total,
            passes_planned,
            passes_done,
            spp_so_far: if pixels > 0.0 { samples / pixels } else { 0.0 },
            error_estimate: history.last().and_then(|h| h.error_estimate),
            elapsed_seconds: elapsed,
            eta_seconds: None,
            created_unix_ms: rec.created_unix_ms,
            priority: rec.priority,
            faults,
            rejected_samples,
            error: rec.error.clone(),
            plan: None,
        })
    }

    /// `GET /jobs`: a page of jobs, newest first.
    pub async fn list(&self, q: JobListQuery) -> ApiResult<JobList> {
        let cursor = match q.cursor.as_deref() {
            None | Some("") => None,
            Some(c) => Some(c.parse::<u64>().map_err(|_| {
                ApiError::invalid_field("cursor", format!("expected a job id, got {c:?}"))
            })?),
        };
        let limit = q.limit.unwrap_or(50).clamp(1, MAX_PAGE);
        let recs = self
            .inner
            .store
            .list_jobs(JobQuery {
                cursor,
                limit: limit + 1,
                state: q.state,
                order: JobOrder::NewestFirst,
            })
            .await
            .map_err(store_err)?;
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
    pub async fn cancel(&self, id: JobId) -> ApiResult<JobStatus> {
        let status = self.status(id).await?;
        if status.state.is_terminal() {
            return Ok(status);
        }
        {
            let mut farm = self.lock()?;
            farm.scheduler.cancel(id);
        }
        self.set_state(id, JobState::Canceled, None).await?;
        self.status(id).await
    }

    /// The convergence history of a job.
    pub async fn history(&self, id: JobId) -> ApiResult<History> {
        if let Some(points) = self.lock()?.runtime.get(&id).map(|rt| rt.history.clone()) {
            return Ok(History { points });
        }
        self.inner
            .store
            .get_job(id)
            .await
            .map_err(store_err)?
            .ok_or_else(|| not_found(id))?;
        let points = self.inner.store.list_history(id).await.map_err(store_err)?;
        Ok(History { points })
    }

    /// The merged state of one frame, from memory or rebuilt from the store.
    async fn frame_state(&self, id: JobId, frame: Option<u32>) -> ApiResult<FrameState> {
        {
            let farm = self.lock()?;
            if let Some(rt) = farm.runtime.get(&id) {
                let f = frame.unwrap_or(rt.job.frames.start);
                if !rt.job.frames.iter().contains(&f) {
                    return Err(frame_error(f, &rt.job));
                }
                let resolved = rt.resolved.clone();
                let stopped = rt.stopped;
                if rt.resolved.black {
                    return Ok(FrameState {
                        stopped,
                        acc: None,
                        adaptive: None,
                        resolved,
                        frame: f,
                    });
                }
                if let Some(a) = farm.scheduler.adaptive_frame(id, f) {
                    return Ok(FrameState {
                        stopped,
                        acc: None,
                        adaptive: Some(a.clone()),
                        resolved,
                        frame: f,
                    });
                }
                if let Some(acc) = farm.scheduler.frame(id, f) {
                    return Ok(FrameState {
                        stopped,
                        acc: Some(acc.clone()),
                        adaptive: None,
                        resolved,
                        frame: f,
                    });
                }
            }
        }
        // Not in memory: a job finished before this coordinator started.
        let rec = self
            .inner
            .store
            .get_job(id)
            .await
            .map_err(store_err)?
            .ok_or_else(|| not_found(id))?;
        let settings: JobSettings = serde_json::from_str(&rec.settings_json)
            .map_err(|e| internal(format!("stored settings of job {id}: {e}")))?;
        let job = settings.validate()?;
        let stopped = (rec.state == JobState::Done).then_some("finished");
        let f = frame.unwrap_or(rec.frames.start);
        if !rec.frames.iter().contains(&f) {
            return Err(frame_error(f, &job));
        }
        let scene = self.scene(&job.scene, job.camera.as_deref()).await?;
        let resolved = resolve_job(&job, &scene)?;
        if resolved.black {
            return Ok(FrameState {
                stopped,
                acc: None,
                adaptive: None,
                resolved,
                frame: f,
            });
        }
        let mut acc = FrameAccumulator::for_frame(rec.plan, f);
        for cp in self
            .inner
            .store
            .load_tiles(id, Some(f))
            .await
            .map_err(store_err)?
        {
            let rect = rec
                .plan
                .get_tile(cp.tile)
                .ok_or_else(|| internal("checkpoint of an unknown tile"))?;
            let units: Vec<_> = cp
                .units
                .iter()
                .map(|u| (u.first_pass, u.pass_count, u.digest))
                .collect();
            let tile = TileAccumulator::restore(rect, cp.merged_passes, cp.pixels, &units)
                .map_err(internal)?;
            acc.restore_tile(tile).map_err(internal)?;
        }
        Ok(FrameState {
            stopped,
            acc: Some(acc),
            adaptive: None,
            resolved,
            frame: f,
        })
    }

    /// `GET /jobs/{id}/image`: the current merged image as PNG or EXR.
    pub async fn image(&self, id: JobId, q: ImageQuery) -> ApiResult<Vec<u8>> {
        let fs = self.frame_state(id, q.frame).await?;
        tokio::task::spawn_blocking(move || {
            let image = match (&fs.adaptive, &fs.acc) {
                (Some(a), _) => a.image(),
                (None, Some(acc)) => acc.image(),
                (None, None) => FrameImage::black(&fs.resolved.plan),
            };
            match q.format {
                ImageFormat::Png => tessera_image::encode_png(&image),
                ImageFormat::Exr => {
                    tessera_image::encode_exr(&image, Some(&fs.resolved.metadata_json(fs.stopped)))
                }
            }
        })
        .await
        .map_err(internal)?
        .map_err(internal)
    }

    /// `GET /jobs/{id}/tiles`: per-tile progress of a frame.
    pub async fn tiles(&self, id: JobId, q: FrameQuery) -> ApiResult<TileMap> {
        let fs = self.frame_state(id, q.frame).await?;
        let plan = fs.resolved.plan;
        let tiles = plan
            .tiles()
            .map(|rect| {
                let (passes, error) = match (&fs.adaptive, &fs.acc) {
                    (Some(a), _) => {
                        let t = &a.tiles()[rect.index as usize];
                        let (mut sum, mut n) = (0.0, 0u64);
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
                        let t = &acc.tiles()[rect.index as usize];
                        let (s, n) = tile_error(t);
                        (t.merged_passes(), (n > 0).then(|| (s / n as f64).sqrt()))
                    }
                    (None, None) => (plan.passes, Some(0.0)),
                };
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

    // ------------------------------------------------------------------------------------
    // Workers

    /// `GET /workers`.
    pub fn workers(&self) -> ApiResult<WorkerList> {
        let farm = self.lock()?;
        let now = now_ms();
        let lost_after = u64::from(self.inner.cfg.heartbeat_ms) * 5 + 2_000;
        let workers = farm
            .workers
            .iter()
            .map(|(&id, w)| {
                let leases = farm.scheduler.leases().filter(|l| l.worker == id).count();
                let state = if now.saturating_sub(w.last_seen_ms) > lost_after {
                    WorkerState::Lost
                } else if w.draining {
                    WorkerState::Draining
                } else if leases > 0 {
                    WorkerState::Busy
                } else {
                    WorkerState::Idle
                };
                WorkerInfo {
                    id,
                    name: w.name.clone(),
                    threads: w.threads,
                    state,
                    last_heartbeat_unix_ms: w.last_seen_ms,
                    units_done: w.units_done,
                    paths_per_second: w.paths_per_second,
                    faults: w.faults,
                    version: w.version.clone(),
                }
            })
            .collect();
        Ok(WorkerList { workers })
    }

    // ------------------------------------------------------------------------------------
    // The gRPC side

    /// Called by the gRPC service after leasing: commits the reservation of lease ids
    /// before any of them reaches a worker, and marks jobs that started running.
    pub(crate) async fn after_lease(&self, jobs: Vec<JobId>) -> Result<(), String> {
        let max = self
            .inner
            .farm
            .lock()
            .map_err(|_| "farm state poisoned")?
            .scheduler
            .max_issued_lease_id();
        let need = {
            let r = self.inner.lease_reserved.lock().map_err(|_| "poisoned")?;
            (max > *r).then_some(max + LEASE_ID_BLOCK)
        };
        if let Some(upto) = need {
            let _w = self.inner.write.lock().await;
            self.inner
                .store
                .record_lease_high_water(upto)
                .await
                .map_err(|e| e.to_string())?;
            let mut r = self.inner.lease_reserved.lock().map_err(|_| "poisoned")?;
            *r = (*r).max(upto);
        }
        for id in jobs {
            let queued = self
                .inner
                .farm
                .lock()
                .map_err(|_| "farm state poisoned")?
                .runtime
                .get(&id)
                .is_some_and(|rt| rt.state == JobState::Queued);
            if queued {
                self.set_state(id, JobState::Running, None)
                    .await
                    .map_err(|e| e.message)?;
            }
        }
        Ok(())
    }

    /// Whether leasing is paused (the restart grace period).
    pub(crate) fn leasing_paused(&self) -> bool {
        now_ms() < self.inner.lease_blocked_until_ms
    }

    /// Validates, merges and durably checkpoints a worker's result; returns whether it
    /// was accepted and why not.
    pub(crate) async fn accept_result(
        &self,
        worker_id: WorkerId,
        lease_id: u64,
        job_hint: u64,
        result: Result<UnitResult, String>,
        render_seconds: f64,
    ) -> (bool, String) {
        let _w = self.inner.write.lock().await;
        let now = now_ms();
        let mut fault: Option<FaultEvent> = None;
        let mut checkpoint = None;
        let mut history = None;
        let mut finished = None;
        let (accepted, reason) = {
            let Ok(mut guard) = self.inner.farm.lock() else {
                return (false, "farm state poisoned".into());
            };
            let farm = &mut *guard;
            let job = farm.scheduler.lease_job(lease_id).or_else(|| {
                (farm.scheduler.is_previous_run_lease(lease_id) && job_hint != 0)
                    .then_some(job_hint)
            });
            let worker_name = farm
                .workers
                .get(&worker_id)
                .map(|w| w.name.clone())
                .unwrap_or_else(|| format!("worker {worker_id}"));
            let rejected_samples = result.as_ref().map_or(0, |r| r.rejected_samples);
            let outcome = match (result, job) {
                (Err(e), _) => Err((FaultKind::InvalidResult, e)),
                (Ok(result), Some(job)) => {
                    let unit = result.unit;
                    let before = farm
                        .scheduler
                        .frame(job, unit.frame)
                        .and_then(|f| f.tile(unit.tile))
                        .map_or(0, |t| t.merged_passes());
                    match farm.scheduler.submit(lease_id, job, result) {
                        Ok(s) => Ok((job, unit, before, s)),
                        Err(tessera_farm::SubmitError::Invalid(e)) => {
                            Err((FaultKind::InvalidResult, e.to_string()))
                        }
                        Err(tessera_farm::SubmitError::Canceled(j)) => {
                            // Not the worker's fault: the job went away.
                            return (false, format!("job {j} was canceled"));
                        }
                        Err(e) => Err((FaultKind::LeaseViolation, e.to_string())),
                    }
                }
                (Ok(_), None) => Err((
                    FaultKind::LeaseViolation,
                    format!("lease {lease_id} is unknown"),
                )),
            };
            let w = farm
                .workers
                .entry(worker_id)
                .or_insert_with(WorkerEntry::default);
            w.last_seen_ms = now;
            match outcome {
                Ok((job, unit, before, Submitted::Accepted)) => {
                    w.units_done += 1;
                    if render_seconds.is_finite() && render_seconds > 0.0 {
                        w.render_seconds += render_seconds;
                    }
                    let frame = farm.scheduler.frame(job, unit.frame);
                    if let (Some(acc), Some(rt)) = (frame, farm.runtime.get_mut(&job)) {
                        let tile = &acc.tiles()[unit.tile as usize];
                        let fi = (unit.frame - rt.job.frames.start) as usize;
                        let rejected = rt
                            .tile_rejected
                            .get_mut(fi)
                            .and_then(|f| f.get_mut(unit.tile as usize))
                            .map(|r| {
                                r.accept(unit.first_pass, rejected_samples, tile.merged_passes());
                                r.merged
                            })
                            .unwrap_or(0);
                        if tile.merged_passes() != before {
                            if let Some(slot) = rt
                                .tile_error
                                .get_mut(fi)
                                .and_then(|f| f.get_mut(unit.tile as usize))
                            {
                                *slot = tile_error(tile);
                            }
                            checkpoint = Some(TileCheckpoint {
                                job,
                                frame: unit.frame,
                                tile: unit.tile,
                                merged_passes: tile.merged_passes(),
                                pixels: tile.pixels().to_vec(),
                                units: tile
                                    .merged_units()
                                    .map(|(first_pass, pass_count, digest)| UnitDigest {
                                        first_pass,
                                        pass_count,
                                        digest,
                                    })
                                    .collect(),
                                rejected_samples: rejected,
                            });
                        }
                    }
                    let complete = farm.scheduler.is_complete(job);
                    let progress = farm.scheduler.progress(job);
                    if let (Some(rt), Some(p)) = (farm.runtime.get_mut(&job), progress) {
                        if complete || now >= rt.last_history_ms + HISTORY_INTERVAL_MS {
                            rt.last_history_ms = now;
                            let (spp, error_estimate) = match farm
                                .scheduler
                                .adaptive_frame(job, rt.job.frames.start)
                            {
                                Some(a) => (
                                    a.samples_per_pixel().0,
                                    a.every_pixel_estimated().then(|| a.image_error()),
                                ),
                                None => (
                                    spp_so_far(&rt.resolved, p.passes_done, rt.job.frames.count()),
                                    rt.error_estimate(),
                                ),
                            };
                            let point = HistoryPoint {
                                elapsed_seconds: rt.elapsed_seconds(now),
                                spp,
                                error_estimate,
                            };
                            rt.history.push(point);
                            history = Some((job, point));
                        }
                    }
                    if complete {
                        finished = Some(job);
                    }
                    (true, String::new())
                }
                Ok((_, _, _, Submitted::Duplicate { identical: true })) => {
                    (true, "duplicate (identical)".into())
                }
                Ok((job, _, _, Submitted::Duplicate { identical: false })) => {
                    w.faults += 1;
                    if let Some(rt) = farm.runtime.get_mut(&job) {
                        rt.faults += 1;
                    }
                    let msg = "duplicate differs from the merged copy: faulty worker".to_string();
                    tracing::warn!(worker_id, lease_id, "{msg}");
                    fault = Some(FaultEvent {
                        worker: worker_name,
                        job: Some(job),
                        kind: FaultKind::DuplicateMismatch,
                        message: msg.clone(),
                        unix_ms: now,
                    });
                    (false, msg)
                }
                Err((kind, msg)) => {
                    w.faults += 1;
                    if let Some(rt) = job.and_then(|j| farm.runtime.get_mut(&j)) {
                        rt.faults += 1;
                    }
                    tracing::warn!(worker_id, lease_id, error = %msg, "result rejected");
                    fault = Some(FaultEvent {
                        worker: worker_name,
                        job,
                        kind,
                        message: msg.clone(),
                        unix_ms: now,
                    });
                    (false, msg)
                }
            }
        };
        let store = &self.inner.store;
        if let Some(cp) = &checkpoint {
            if let Err(e) = store.save_tile(cp.as_ref()).await {
                let (job, frame, tile) = (cp.job, cp.frame, cp.tile);
                tracing::error!(job, frame, tile, error = %e, "checkpoint failed");
                return (
                    false,
                    format!("the coordinator could not store the result: {e}"),
                );
            }
        }
        if let Some((job, point)) = history {
            if let Err(e) = store.append_history(job, point).await {
                tracing::warn!(job, error = %e, "history point not stored");
            }
        }
        if let Some(f) = &fault {
            if let Err(e) = store.record_fault(f).await {
                tracing::warn!(error = %e, "fault event not stored");
            }
        }
        drop(_w);
        if let Some(job) = finished {
            if let Err(e) = self.set_state(job, JobState::Done, None).await {
                tracing::error!(job, error = %e.message, "cannot mark job done");
            }
        }
        (accepted, reason)
    }

    /// Periodic housekeeping: expire lapsed leases, stop jobs past their time limit.
    pub async fn tick(&self) {
        let now = now_ms();
        let mut over_time = Vec::new();
        if let Ok(mut farm) = self.inner.farm.lock() {
            if !self.leasing_paused() {
                farm.scheduler.expire(now);
            }
            for (&id, rt) in &farm.runtime {
                if let (Some(limit), JobState::Running) = (rt.job.time_limit_seconds, rt.state) {
                    if rt.elapsed_seconds(now) >= limit {
                        over_time.push(id);
                    }
                }
            }
            for id in &over_time {
                farm.scheduler.cancel(*id);
                if let Some(rt) = farm.runtime.get_mut(id) {
                    rt.stopped = Some("time limit reached");
                }
            }
        }
        for id in over_time {
            tracing::info!(job = id, "time limit reached");
            let _ = self.set_state(id, JobState::Done, None).await;
        }
    }

    /// Runs [`Coordinator::tick`] every 200 ms until the returned handle is dropped.
    pub fn spawn_ticker(&self) -> tokio::task::JoinHandle<()> {
        let me = self.clone();
        tokio::spawn(async move {
            let mut iv = tokio::time::interval(Duration::from_millis(200));
            loop {
                iv.tick().await;
                me.tick().await;
            }
        })
    }

    /// Prometheus text exposition of the farm's counters and gauges.
    pub fn metrics(&self) -> ApiResult<String> {
        use std::fmt::Write;
        let farm = self.lock()?;
        let mut by_state: BTreeMap<&str, u64> = BTreeMap::new();
        for rt in farm.runtime.values() {
            *by_state.entry(rt.state.as_str()).or_default() += 1;
        }
        let mut s = String::new();
        let _ = writeln!(
            s,
            "# HELP tessera_jobs Jobs known to this coordinator run, by state.\n# TYPE tessera_jobs gauge"
        );
        for st in ["queued", "running", "done", "failed", "canceled"] {
            let _ = writeln!(
                s,
                "tessera_jobs{{state=\"{st}\"}} {}",
                by_state.get(st).unwrap_or(&0)
            );
        }
        let _ = writeln!(s, "# HELP tessera_workers Registered workers.\n# TYPE tessera_workers gauge\ntessera_workers {}", farm.workers.len());
        let units: u64 = farm.workers.values().map(|w| w.units_done).sum();
        let faults: u64 = farm.workers.values().map(|w| w.faults).sum();
        let _ = writeln!(s, "# HELP tessera_units_merged_total Units accepted from workers.\n# TYPE tessera_units_merged_total counter\ntessera_units_merged_total {units}");
        let _ = writeln!(s, "# HELP tessera_worker_faults_total Refused results and mismatching duplicates.\n# TYPE tessera_worker_faults_total counter\ntessera_worker_faults_total {faults}");
        let _ = writeln!(s, "# HELP tessera_leases_outstanding Leases currently held by workers.\n# TYPE tessera_leases_outstanding gauge\ntessera_leases_outstanding {}", farm.scheduler.leases().count());
        let _ = writeln!(s, "# HELP tessera_worker_paths_per_second Last reported throughput per worker.\n# TYPE tessera_worker_paths_per_second gauge");
        for w in farm.workers.values() {
            let _ = writeln!(
                s,
                "tessera_worker_paths_per_second{{worker={:?}}} {}",
                w.name, w.paths_per_second
            );
        }
        let _ = writeln!(s, "# HELP tessera_uptime_seconds Seconds since the coordinator started.\n# TYPE tessera_uptime_seconds gauge\ntessera_uptime_seconds {:.3}", self.uptime_seconds());
        Ok(s)
    }
}

struct FrameState {
    /// Why the job stopped, once it is done.
    stopped: Option<&'static str>,
    acc: Option<FrameAccumulator>,
    /// The adaptive policy's state of an adaptive job in memory (its image is the job's).
    adaptive: Option<tessera_farm::AdaptiveFrame>,
    resolved: ResolvedJob,
    frame: u32,
}

fn add_to_scheduler(
    farm: &mut Farm,
    id: JobId,
    priority: i32,
    plan: tessera_farm::FramePlan,
    job: &ValidatedJob,
    passes_per_unit: u32,
) -> ApiResult<()> {
    match job.adaptive_settings() {
        Some(a) => {
            farm.scheduler
                .add_adaptive_job(id, priority, plan, job.frames.iter(), passes_per_unit, a)
                .map_err(|e| ApiError::invalid_field("adaptive", e))?;
        }
        None => farm
            .scheduler
            .add_job(id, priority, plan, job.frames.iter(), passes_per_unit),
    }
    Ok(())
}

fn frame_error(f: u32, job: &ValidatedJob) -> ApiError {
    ApiError::invalid_field(
        "frame",
        format!(
            "frame {f} is not rendered by this job (frames {}..={})",
            job.frames.start, job.frames.end
        ),
    )
}

fn not_found(id: JobId) -> ApiError {
    ApiError::new(ErrorCode::NotFound, format!("job {id} does not exist"))
}

fn spp_so_far(r: &ResolvedJob, passes_done: u64, frames: u64) -> f64 {
    // Tile passes weighted by tile area: with equal passes per pixel this is exact; the
    // status is informative, so a uniform-tile approximation is enough for partial frames.
    let tiles = u64::from(r.plan.tile_count()) * frames.max(1);
    if tiles == 0 {
        return 0.0;
    }
    passes_done as f64 / tiles as f64 * f64::from(r.plan.samples_per_pass)
}

fn status_of(farm: &Farm, id: JobId, rt: &JobRuntime) -> JobStatus {
    let now = now_ms();
    let plan = rt.resolved.plan;
    let frames_total = rt.job.frames.count() as u32;
    let tiles_total = u64::from(plan.tile_count()) * u64::from(frames_total);
    let passes_planned = tiles_total * u64::from(plan.passes);
    let progress = farm.scheduler.progress(id);
    let (passes_done, frames_done) = match (progress, rt.resolved.black) {
        (_, true) => (passes_planned, frames_total),
        (Some(p), false) => (p.passes_done, p.frames_done),
        (None, false) => (0, 0),
    };
    let elapsed = rt.elapsed_seconds(now);
    let adaptive_frame = farm.scheduler.adaptive_frame(id, rt.job.frames.start);
    let error = if rt.resolved.black {
        Some(0.0)
    } else if let Some(a) = adaptive_frame {
        a.every_pixel_estimated().then(|| a.image_error())
    } else {
        rt.error_estimate()
    };
    let eta = if rt.state.is_terminal() {
        Some(0.0)
    } else {
        eta_seconds(
            elapsed,
            passes_done,
            passes_planned,
            error,
            rt.job.target_error,
        )
    };
    JobStatus {
        id,
        name: rt.job.name.clone(),
        state: rt.state,
        scene: rt.job.scene.to_string(),
        settings: rt.settings.clone(),
        width: Some(plan.width),
        height: Some(plan.height),
        frames_total,
        frames_done,
        tiles_total,
        passes_planned,
        passes_done,
        spp_so_far: match adaptive_frame {
            Some(a) => a.samples_per_pixel().0,
            None => spp_so_far(&rt.resolved, passes_done, rt.job.frames.count()),
        },
        error_estimate: error,
        target_error: rt.job.target_error,
        elapsed_seconds: elapsed,
        eta_seconds: eta,
        created_unix_ms: rt.created_unix_ms,
        priority: rt.job.priority,
        faults: rt.faults,
        rejected_samples: rt.rejected_samples(),
        error: rt.error.clone(),
        plan: serde_json::from_str(&rt.resolved.render_plan.to_json()).ok(),
        adaptive: rt.job.adaptive.to_string(),
    }
}

/// Estimated seconds until a job is done, from the time spent so far.
///
/// Monte Carlo error falls like `1 / sqrt(work)` (ARCHITECTURE.md §3), so reaching `target` from
/// the current `error` needs `(error / target)^2` times the work done so far; the job also
/// stops when all planned passes are merged, so the estimate is the smaller of that and
/// the time for the remaining passes at the current rate. `None` before anything merged.
pub fn eta_seconds(
    elapsed: f64,
    passes_done: u64,
    passes_planned: u64,
    error: Option<f64>,
    target: Option<f64>,
) -> Option<f64> {
    if passes_done == 0 || elapsed <= 0.0 {
        return None;
    }
    let remaining_passes =
        elapsed * (passes_planned.saturating_sub(passes_done)) as f64 / passes_done as f64;
    let by_error = match (error, target) {
        (Some(e), Some(t)) if t > 0.0 && e.is_finite() => {
            Some((elapsed * ((e / t).powi(2) - 1.0)).max(0.0))
        }
        _ => None,
    };
    Some(match by_error {
        Some(b) => b.min(remaining_passes),
        None => remaining_passes,
    })
}

/// Loads a job's scene (from the farm's cache or the store, caching uploaded bytes for the
/// workers' FetchScene).
async fn load_scene(
    store: &dyn Store,
    farm: &mut Farm,
    scene: &SceneRef,
    camera: Option<&str>,
) -> Result<Scene, String> {
    let bytes = match scene {
        SceneRef::Hash(h) => match farm.scenes.get(h) {
            Some(b) => Some(b.clone()),
            None => {
                let b = store
                    .get_scene(h)
                    .await
                    .map_err(|e| e.to_string())?
                    .ok_or_else(|| format!("scene {h} is missing from the store"))?;
                let b = Arc::new(b);
                farm.scenes.insert(h.clone(), b.clone());
                Some(b)
            }
        },
        SceneRef::Builtin(_) => None,
    };
    load_job_scene(scene, bytes.as_deref().map(|b| b.as_slice()), camera).map_err(|e| e.to_string())
}

fn hex(bytes: &[u8]) -> String {
    use std::fmt::Write;
    bytes.iter().fold(String::with_capacity(64), |mut s, b| {
        let _ = write!(s, "{b:02x}");
        s
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rejected_samples_of_buffered_units_wait_until_they_merge() {
        let mut r = TileRejected::default();
        // Passes 2..4 arrive first and are buffered (0 passes merged).
        r.accept(2, 5, 0);
        assert_eq!((r.merged, r.total()), (0, 5));
        // Passes 0..2 merge, and with them the buffered unit: 4 passes merged.
        r.accept(0, 1, 4);
        assert_eq!((r.merged, r.total()), (6, 6));
        assert!(r.buffered.is_empty());
        r.accept(4, 0, 6);
        assert_eq!((r.merged, r.total()), (6, 6));
    }

    #[test]
    fn eta_follows_inverse_square_root_of_work() {
        // Error 0.04 after 10 s, target 0.02: four times the work, 30 s more.
        let eta = eta_seconds(10.0, 100, 10_000, Some(0.04), Some(0.02)).unwrap();
        assert!((eta - 30.0).abs() < 1e-9);
        // Bounded by the remaining planned passes: 100 of 200 done in 10 s.
        let eta = eta_seconds(10.0, 100, 200, Some(0.04), Some(0.001)).unwrap();
        assert!((eta - 10.0).abs() < 1e-9);
        // Already below target.
        assert_eq!(
            eta_seconds(10.0, 100, 200, Some(0.01), Some(0.02)),
            Some(0.0)
        );
        assert_eq!(eta_seconds(0.0, 0, 200, None, None), None);
    }
}
