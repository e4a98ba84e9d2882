//! Scenes: uploads (ARCHITECTURE.md §9, step 1) and loading a job's scene for submission,
//! resume and images (step 4), lit by the job's environment.
//!
//! Environment images (Radiance `.hdr`, OpenEXR) are uploaded, stored, counted against the
//! quotas and deleted exactly as scenes are: one content-addressed store, told apart by
//! the files' magic numbers. An image is decoded at upload (its texel count checked from
//! the header first, as textures are), so a broken or oversized one is refused then, not
//! when a job names it.
//!
//! Uploaded bytes are kept in the farm's cache by content hash, because workers fetch
//! them from there (`FetchScene`); a scene missing from the cache is read from the store.
//! Parsing runs on a blocking thread, never on the async runtime.
//!
//! Storage is bounded (docs/store.md, "Scene storage"): an upload larger than
//! [`CoordinatorConfig::max_scene_bytes`](super::CoordinatorConfig::max_scene_bytes) is
//! refused with 413, one that would take the stored scenes beyond their total quota or
//! its API client's quota with 507, each naming the limit and the numbers. A scene no
//! queued or running job needs can be deleted (`DELETE /api/v1/scenes/{hash}`), and is
//! deleted by the maintenance once unused for the retention period, if one is set.

use std::sync::{Arc, Mutex};

use sha2::{Digest, Sha256};
use tessera_api::{SceneRef, SceneUploaded};
use tessera_farm::job::{EnvironmentSource, JobEnvironment, JobScene, ValidatedJob};
use tessera_scene::environment::{decode_environment, SceneEnvironment};
use tessera_scene::job::{load_job_scene_at, resolution_time};
use tessera_scene::Scene;

use super::Coordinator;
use crate::error::{CoordError, CoordResult};
use crate::state::Farm;
use crate::store::{SceneDeletion, Store, StoreError};

/// Scenes deleted by one run of the retention, at most (the next run takes the rest).
const RETENTION_BATCH: u32 = 64;
/// How often the retention runs, ms.
const RETENTION_EVERY_MS: u64 = 60_000;

/// Why a job's scene could not be loaded. The text is the reason a resumed job fails
/// with (`JobStatus.error`); requests see it as a [`CoordError`] on the `scene` field.
#[derive(Debug, thiserror::Error)]
pub enum SceneLoadError {
    /// No uploaded scene has this hash.
    #[error("scene {0} is missing from the store")]
    Missing(String),
    /// The scene's bytes do not load (or its camera does not exist).
    #[error("{0}")]
    Invalid(String),
    /// The store failed.
    #[error("{0}")]
    Store(#[from] StoreError),
    /// The coordinator failed (a poisoned lock, a panicked parser).
    #[error("{0}")]
    Internal(String),
    /// No uploaded file has the hash the job's `environment.source` names.
    #[error("environment image {0} is missing from the store")]
    EnvironmentMissing(String),
    /// The environment image does not decode.
    #[error("{0}")]
    EnvironmentInvalid(String),
}

impl From<SceneLoadError> for CoordError {
    fn from(e: SceneLoadError) -> Self {
        match e {
            SceneLoadError::Missing(h) => CoordError::invalid_field(
                "scene",
                format!("no uploaded scene has hash {h}: POST it to /api/v1/scenes first"),
            ),
            SceneLoadError::Invalid(e) => CoordError::invalid_field("scene", e),
            SceneLoadError::Store(e) => CoordError::Store(e),
            SceneLoadError::Internal(e) => CoordError::Internal(e),
            SceneLoadError::EnvironmentMissing(h) => CoordError::invalid_field(
                "environment.source",
                format!(
                    "no uploaded environment image has hash {h}: POST the .hdr or .exr file \
                     to /api/v1/scenes first"
                ),
            ),
            SceneLoadError::EnvironmentInvalid(e) => {
                CoordError::invalid_field("environment.source", e)
            }
        }
    }
}

/// Whether `bytes` begin like an environment image: Radiance RGBE (`#?`) or OpenEXR (its
/// magic number), the two formats [`decode_environment`] reads. A glTF file begins with
/// `glTF` or `{`.
pub(crate) fn is_environment_image(bytes: &[u8]) -> bool {
    bytes.starts_with(b"#?") || bytes.starts_with(&[0x76, 0x2f, 0x31, 0x01])
}

/// The bytes of the uploaded file `hash`: from the farm's cache, else from the store
/// (then cached, since workers fetch them from there with FetchScene). `None` when no
/// upload has this hash.
async fn uploaded_bytes(
    store: &dyn Store,
    farm: &Mutex<Farm>,
    hash: &str,
) -> Result<Option<Arc<Vec<u8>>>, SceneLoadError> {
    let poisoned = || SceneLoadError::Internal("farm state poisoned".into());
    let cached = farm
        .lock()
        .map_err(|_| poisoned())?
        .scenes
        .get(hash)
        .cloned();
    let b = match cached {
        Some(b) => b,
        None => match store.get_scene(hash).await? {
            Some(b) => Arc::new(b),
            None => return Ok(None),
        },
    };
    farm.lock()
        .map_err(|_| poisoned())?
        .scenes
        .insert(hash.to_string(), b.clone());
    Ok(Some(b))
}

/// A job's environment, decoded as `tessera render --environment` decodes it
/// ([`SceneEnvironment::from_job`]), with the bytes of its image (`None` for a colour),
/// which stay in the farm's cache for the workers. Decoding runs on a blocking thread.
pub(crate) async fn load_environment(
    store: &dyn Store,
    farm: &Mutex<Farm>,
    env: &JobEnvironment,
) -> Result<(SceneEnvironment, Option<Arc<Vec<u8>>>), SceneLoadError> {
    let bytes = match &env.source {
        EnvironmentSource::Colour(_) => None,
        EnvironmentSource::Image(h) => Some(
            uploaded_bytes(store, farm, h)
                .await?
                .ok_or_else(|| SceneLoadError::EnvironmentMissing(h.clone()))?,
        ),
    };
    let (env, b) = (env.clone(), bytes.clone());
    let decoded = tokio::task::spawn_blocking(move || {
        SceneEnvironment::from_job(&env, b.as_deref().map(Vec::as_slice))
    })
    .await
    .map_err(|e| SceneLoadError::Internal(e.to_string()))?
    .map_err(|e| SceneLoadError::EnvironmentInvalid(e.to_string()))?;
    Ok((decoded, bytes))
}

/// A job's scene as it is resolved: [`load_scene`], lit by the job's environment if it
/// has one (as `tessera render` lights it before resolving, so the plan, the technique
/// pilot and a black-image verdict agree with a local render); also the environment
/// image's bytes, for a pilot child.
pub(crate) async fn load_lit_scene(
    store: &dyn Store,
    farm: &Mutex<Farm>,
    job: &ValidatedJob,
) -> Result<(Scene, Option<Arc<Vec<u8>>>), SceneLoadError> {
    let mut scene = load_scene(store, farm, &job.scene).await?;
    let Some(env) = &job.environment else {
        return Ok((scene, None));
    };
    let (decoded, bytes) = load_environment(store, farm, env).await?;
    decoded.apply(&mut scene);
    Ok((scene, bytes))
}

/// Builds a job's scene: a built-in one, or an uploaded one from the farm's cache or the
/// store (then cached for the workers' FetchScene). The one scene loader of the
/// coordinator: submission, resume and images all call it. The scene is loaded at t = 0
/// with the job's `animation` (an unknown one is an error of the scene): jobs are
/// resolved against their scene at t = 0, as `tessera render` resolves them; workers
/// evaluate each frame at its own time.
pub(crate) async fn load_scene(
    store: &dyn Store,
    farm: &Mutex<Farm>,
    scene: &JobScene,
) -> Result<Scene, SceneLoadError> {
    let bytes = match &scene.source {
        SceneRef::Hash(h) => Some(
            uploaded_bytes(store, farm, h)
                .await?
                .ok_or_else(|| SceneLoadError::Missing(h.clone()))?,
        ),
        SceneRef::Builtin(_) => None,
    };
    let scene = scene.clone();
    tokio::task::spawn_blocking(move || {
        load_job_scene_at(
            &scene,
            bytes.as_deref().map(|b| b.as_slice()),
            &resolution_time(&scene),
        )
    })
    .await
    .map_err(|e| SceneLoadError::Internal(e.to_string()))?
    .map_err(|e| SceneLoadError::Invalid(e.to_string()))
}

impl Coordinator {
    /// Stores an uploaded scene (a .glb or a self-contained .gltf) or environment image (a
    /// Radiance .hdr or an OpenEXR file, by its magic number) after checking that it loads;
    /// returns its content hash and statistics (an image has no triangles, meshes,
    /// materials or lights). The upload counts as the anonymous client's
    /// ([`Coordinator::upload_scene_as`]).
    pub async fn upload_scene(&self, bytes: Vec<u8>) -> CoordResult<SceneUploaded> {
        self.upload_scene_as(bytes, &crate::auth::client_name(None))
            .await
    }

    /// [`Coordinator::upload_scene`] by the API client named `client`
    /// ([`crate::auth::client_name`]), whose quota it counts in.
    pub async fn upload_scene_as(
        &self,
        bytes: Vec<u8>,
        client: &str,
    ) -> CoordResult<SceneUploaded> {
        self.accepting_work()?;
        if bytes.is_empty() {
            return Err(CoordError::InvalidRequest(
                "the scene upload is empty: send the bytes of a .glb or .gltf file".into(),
            ));
        }
        let max = self.inner.cfg.max_scene_bytes;
        if bytes.len() > max {
            return Err(CoordError::TooLarge(format!(
                "the scene is {} bytes, more than the limit of {max} bytes per upload \
                 (--max-scene-size)",
                bytes.len()
            )));
        }
        let hash = hex(&Sha256::digest(&bytes));
        let bytes = Arc::new(bytes);
        let b2 = bytes.clone();
        let name = format!("scene {hash}");
        let environment = is_environment_image(&bytes);
        let image_name = format!("image {hash}");
        // Decoded in full, as a job would decode it: the texel limit is checked from the
        // header before anything is allocated, and a truncated or corrupt file fails here.
        let scene = tokio::task::spawn_blocking(move || {
            if environment {
                decode_environment(&b2, &image_name).map(|_| None)
            } else {
                tessera_scene::gltf_import::load_slice(&b2, &name, None, None).map(Some)
            }
        })
        .await
        .map_err(CoordError::internal)?
        .map_err(|e| CoordError::InvalidScene(e.to_string()))?;
        {
            let _shared = self.inner.scene_lock.read().await;
            let _turn = self.inner.uploads.lock().await;
            let store = &self.inner.store;
            // A scene stored already takes no more room: no quota applies to it again.
            if !store.scene_exists(&hash).await? {
                self.check_scene_quota(bytes.len() as u64, client).await?;
            }
            store.put_scene(&hash, &bytes).await?;
            store.record_scene_upload(&hash, client).await?;
        }
        let out = SceneUploaded {
            hash: hash.clone(),
            bytes: bytes.len() as u64,
            triangles: scene.as_ref().map_or(0, |s| s.triangle_count() as u64),
            // Meshes as placed: world-space meshes plus instances of stored prototypes.
            meshes: scene
                .as_ref()
                .map_or(0, |s| (s.meshes.len() + s.instances.len()) as u32),
            materials: scene.as_ref().map_or(0, |s| s.materials.len() as u32),
            lights: scene.as_ref().map_or(0, light_count),
        };
        tracing::info!(
            scene = %hash,
            bytes = bytes.len(),
            client,
            environment,
            "scene uploaded"
        );
        self.lock()?.scenes.insert(hash, bytes);
        Ok(out)
    }

    /// Refuses (507) a new scene of `size` bytes that would take the stored scenes beyond
    /// the total quota or `client`'s quota; the error names the limit and the numbers.
    async fn check_scene_quota(&self, size: u64, client: &str) -> CoordResult<()> {
        let cfg = &self.inner.cfg;
        let store = &self.inner.store;
        let total = store.scene_bytes(None).await?;
        if total.saturating_add(size) > cfg.scene_quota_bytes {
            return Err(CoordError::InsufficientStorage(format!(
                "the stored scenes would exceed their total quota (--scene-quota) of {} \
                 bytes: they hold {total} bytes and this scene is {size}; delete scenes no \
                 job needs (DELETE /api/v1/scenes/{{hash}}) or raise the quota",
                cfg.scene_quota_bytes
            )));
        }
        let own = store.scene_bytes(Some(client)).await?;
        if own.saturating_add(size) > cfg.scene_quota_per_token {
            return Err(CoordError::InsufficientStorage(format!(
                "the scenes uploaded with this API token would exceed its quota \
                 (--scene-quota-per-token) of {} bytes: they hold {own} bytes and this \
                 scene is {size}; delete scenes no job needs (DELETE /api/v1/scenes/{{hash}}) \
                 or raise the quota",
                cfg.scene_quota_per_token
            )));
        }
        Ok(())
    }

    /// Deletes the uploaded scene `hash` from the store and the farm's cache: 404 when no
    /// scene has this hash, 409 naming the jobs while a queued or running job needs it.
    pub async fn delete_scene(&self, hash: &str) -> CoordResult<()> {
        self.accepting_work()?;
        let not_found = || CoordError::NotFound(format!("no scene {hash}"));
        if hash.len() != 64 || !hash.bytes().all(|b| matches!(b, b'0'..=b'9' | b'a'..=b'f')) {
            return Err(not_found());
        }
        let _exclusive = self.inner.scene_lock.write().await;
        match self.inner.store.delete_scene(hash).await? {
            SceneDeletion::Deleted => {
                self.lock()?.scenes.remove(hash);
                tracing::info!(scene = %hash, "scene deleted");
                Ok(())
            }
            SceneDeletion::Missing => {
                // Not in the store: nothing to keep in memory either.
                self.lock()?.scenes.remove(hash);
                Err(not_found())
            }
            SceneDeletion::Needed(jobs) => {
                let list: Vec<String> = jobs.iter().map(u64::to_string).collect();
                Err(CoordError::Conflict {
                    field: "hash".into(),
                    message: format!(
                        "scene {hash} is needed by unfinished jobs {}: cancel them or let \
                         them finish first",
                        list.join(", ")
                    ),
                })
            }
        }
    }

    /// The scene retention of the periodic maintenance ([`Coordinator::tick`]): once a
    /// minute, deletes scenes unused for
    /// [`CoordinatorConfig::scene_retention_ms`](super::CoordinatorConfig::scene_retention_ms)
    /// that no queued or running job needs. Failures are logged; the next run tries again.
    pub(crate) async fn scene_retention(&self, now: u64) {
        use std::sync::atomic::Ordering;
        let Some(keep) = self.inner.cfg.scene_retention_ms else {
            return;
        };
        let last = self.inner.retention_ran_ms.load(Ordering::SeqCst);
        if now < last.saturating_add(RETENTION_EVERY_MS) || self.accepting_work().is_err() {
            return;
        }
        self.inner.retention_ran_ms.store(now, Ordering::SeqCst);
        match self.retain_scenes(now.saturating_sub(keep)).await {
            Ok(0) => {}
            Ok(n) => tracing::info!(scenes = n, "unused scenes past their retention deleted"),
            Err(e) => tracing::warn!(error = %e, "scene retention failed"),
        }
    }

    /// Deletes up to a batch of stored scenes that no queued or running job needs and
    /// nothing used since `cutoff_unix_ms`; returns how many were deleted.
    pub async fn retain_scenes(&self, cutoff_unix_ms: u64) -> CoordResult<usize> {
        let unused = self
            .inner
            .store
            .unused_scenes(cutoff_unix_ms, RETENTION_BATCH)
            .await?;
        let mut deleted = 0;
        for hash in unused {
            let _exclusive = self.inner.scene_lock.write().await;
            // Checked again in the deletion's transaction: a job submitted meanwhile keeps it.
            if self.inner.store.delete_scene(&hash).await? == SceneDeletion::Deleted {
                self.lock()?.scenes.remove(&hash);
                tracing::info!(scene = %hash, "unused scene deleted (retention)");
                deleted += 1;
            }
        }
        Ok(deleted)
    }

    /// A job's scene lit by its environment, and the environment image's bytes
    /// ([`load_lit_scene`]); errors name `scene` or `environment.source`.
    pub(crate) async fn lit_scene(
        &self,
        job: &ValidatedJob,
    ) -> CoordResult<(Scene, Option<Arc<Vec<u8>>>)> {
        Ok(load_lit_scene(&*self.inner.store, &self.inner.farm, job).await?)
    }

    /// The bytes of an uploaded scene, for a worker's FetchScene.
    pub fn scene_bytes(&self, hash: &str) -> CoordResult<Arc<Vec<u8>>> {
        self.lock()?
            .scenes
            .get(hash)
            .cloned()
            .ok_or_else(|| CoordError::NotFound(format!("no scene {hash}")))
    }
}

/// Light sources: explicit lights plus meshes with an emissive material.
fn light_count(scene: &Scene) -> u32 {
    let emissive = scene
        .meshes
        .iter()
        .filter(|m| {
            scene
                .materials
                .get(m.material as usize)
                .is_some_and(|mat| mat.emission.max_element() > 0.0)
        })
        .count();
    (scene.lights.len() + emissive) as u32
}

fn hex(bytes: &[u8]) -> String {
    use std::fmt::Write;
    bytes.iter().fold(String::with_capacity(64), |mut s, b| {
        let _ = write!(s, "{b:02x}");
        s
    })
}
