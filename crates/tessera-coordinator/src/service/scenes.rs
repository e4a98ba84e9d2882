//! Scenes: uploads (ARCHITECTURE.md §9, step 1) and loading a job's scene for submission,
//! resume and images (step 4).
//!
//! Uploaded bytes are kept in the farm's cache by content hash, because workers fetch
//! them from there (`FetchScene`); a scene missing from the cache is read from the store.
//! Parsing runs on a blocking thread, never on the async runtime.

use std::sync::{Arc, Mutex};

use sha2::{Digest, Sha256};
use tessera_api::{SceneRef, SceneUploaded};
use tessera_farm::job::JobScene;
use tessera_scene::job::{load_job_scene_at, resolution_time};
use tessera_scene::Scene;

use super::{Coordinator, MAX_SCENE_BYTES};
use crate::error::{CoordError, CoordResult};
use crate::state::Farm;
use crate::store::{Store, StoreError};

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
        }
    }
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
    let poisoned = || SceneLoadError::Internal("farm state poisoned".into());
    let bytes = match &scene.source {
        SceneRef::Hash(h) => {
            let cached = farm.lock().map_err(|_| poisoned())?.scenes.get(h).cloned();
            let b = match cached {
                Some(b) => b,
                None => Arc::new(
                    store
                        .get_scene(h)
                        .await?
                        .ok_or_else(|| SceneLoadError::Missing(h.clone()))?,
                ),
            };
            farm.lock()
                .map_err(|_| poisoned())?
                .scenes
                .insert(h.clone(), b.clone());
            Some(b)
        }
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
    /// Stores an uploaded scene (a .glb or a self-contained .gltf) after checking that it
    /// loads; returns its content hash and statistics.
    pub async fn upload_scene(&self, bytes: Vec<u8>) -> CoordResult<SceneUploaded> {
        self.accepting_work()?;
        if bytes.is_empty() {
            return Err(CoordError::InvalidRequest(
                "the scene upload is empty: send the bytes of a .glb or .gltf file".into(),
            ));
        }
        if bytes.len() > MAX_SCENE_BYTES {
            return Err(CoordError::TooLarge(format!(
                "the scene is {} bytes, more than the limit of {MAX_SCENE_BYTES}",
                bytes.len()
            )));
        }
        let hash = hex(&Sha256::digest(&bytes));
        let bytes = Arc::new(bytes);
        let b2 = bytes.clone();
        let name = format!("scene {hash}");
        let scene = tokio::task::spawn_blocking(move || {
            tessera_scene::gltf_import::load_slice(&b2, &name, None, None)
        })
        .await
        .map_err(CoordError::internal)?
        .map_err(|e| CoordError::InvalidScene(e.to_string()))?;
        self.inner.store.put_scene(&hash, &bytes).await?;
        let out = SceneUploaded {
            hash: hash.clone(),
            bytes: bytes.len() as u64,
            triangles: scene.triangle_count() as u64,
            // Meshes as placed: world-space meshes plus instances of stored prototypes.
            meshes: (scene.meshes.len() + scene.instances.len()) as u32,
            materials: scene.materials.len() as u32,
            lights: light_count(&scene),
        };
        tracing::info!(scene = %hash, bytes = bytes.len(), "scene uploaded");
        self.lock()?.scenes.insert(hash, bytes);
        Ok(out)
    }

    /// A job's scene, loaded by [`load_scene`]; errors name the `scene` field.
    pub(crate) async fn scene(&self, scene: &JobScene) -> CoordResult<Scene> {
        Ok(load_scene(&*self.inner.store, &self.inner.farm, scene).await?)
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
