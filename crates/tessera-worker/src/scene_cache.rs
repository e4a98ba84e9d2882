//! Scenes fetched by content hash, parsed and built once and kept for the next units
//! (a worker pays for a scene once however many units of it it renders), and the time a
//! lease's scene is loaded at.
//!
//! A lease's environment lights the scene as `tessera render --environment` lights it:
//! decoded from the image fetched by its hash (checked, like a scene) and applied to the
//! scene and to every shutter key before the build. Scenes are cached under their
//! environment too, since the same scene under another light is another render scene.

use crate::connect::Client;
use sha2::{Digest, Sha256};
use std::collections::{HashMap, VecDeque};
use std::sync::{Arc, Mutex};
use tessera_farm::job::SceneRef;
use tessera_farm::job::{EnvironmentSource, JobEnvironment};
use tessera_proto::v1;
use tessera_proto::LeasedUnit;
use tessera_render::scene::RenderScene;
use tessera_scene::environment::SceneEnvironment;
use tessera_scene::Scene;

/// Scenes and their built forms, by scene reference and camera (`SCENE#CAMERA`).
#[derive(Default)]
pub(crate) struct SceneCache {
    /// Static scenes, parsed.
    scenes: HashMap<String, Arc<Scene>>,
    /// Animated scenes: their bytes (none for built-ins), parsed at each frame's time.
    animated: HashMap<String, Option<Arc<Vec<u8>>>>,
    /// Built render scenes by (scene and camera, width, height); a handful at most.
    built: Vec<(String, u32, u32, Arc<RenderScene>)>,
    /// Keys of `scenes` and `animated`, oldest first: a worker that serves job after job
    /// keeps the last [`SCENE_CACHE`] of them, not every scene it ever saw.
    order: VecDeque<String>,
    /// Decoded environments by [`JobEnvironment::metadata_json`], newest last; a few at
    /// most (a decoded 8K image is hundreds of megabytes).
    environments: Vec<(String, Arc<SceneEnvironment>)>,
}

/// Decoded environments kept.
const ENVIRONMENT_CACHE: usize = 2;

/// Built render scenes kept (each holds a BVH: the largest thing a worker keeps).
const BUILT_CACHE: usize = 4;
/// Parsed static scenes and animated scenes' bytes kept, together.
const SCENE_CACHE: usize = 8;

impl SceneCache {
    /// Records that `key` was just added to `scenes` or `animated`, and forgets the
    /// oldest entries beyond [`SCENE_CACHE`] (a lease still rendering one keeps its own
    /// `Arc`; a later lease fetches it again).
    fn added(&mut self, key: &str) {
        self.order.retain(|k| k != key);
        self.order.push_back(key.to_string());
        while self.order.len() > SCENE_CACHE {
            if let Some(old) = self.order.pop_front() {
                self.scenes.remove(&old);
                self.animated.remove(&old);
            }
        }
    }
}

/// The built scene for a lease, from the cache or fetched and built now.
///
/// A static scene is parsed once and built once per image size, whatever the frame. An
/// animated one (glTF animations, [`Scene::animated`]) is parsed and built at each
/// frame's time ([`tessera_scene::job::frame_time`], the rule every renderer uses), from
/// its bytes kept in the cache, under [`tessera_farm::job::JobScene::frame_key`]; the
/// built scenes of the last few times are kept.
pub(crate) async fn scene_for(
    client: &mut Client,
    cache: &Arc<Mutex<SceneCache>>,
    l: &LeasedUnit,
) -> Result<Arc<RenderScene>, String> {
    let (js, plan, frame) = (&l.scene, &l.plan, l.unit.frame);
    // Under another environment the same scene is another scene.
    let lit = |k: String| match &l.environment {
        None => k,
        Some(e) => format!("{k}|environment:{}", e.metadata_json()),
    };
    let key = lit(js.parse_key());
    let time = tessera_scene::job::frame_time(js, frame);
    let timed_key = lit(js.frame_key(frame));
    let lock = || cache.lock().map_err(|_| "scene cache poisoned".to_string());
    let built_key = {
        let c = lock()?;
        let built_key = if c.animated.contains_key(&key) {
            timed_key.clone()
        } else {
            key.clone()
        };
        if let Some((_, _, _, rs)) = c
            .built
            .iter()
            .find(|(k, w, h, _)| *k == built_key && *w == plan.width && *h == plan.height)
        {
            return Ok(rs.clone());
        }
        built_key
    };
    let (cached, raw) = {
        let c = lock()?;
        (c.scenes.get(&key).cloned(), c.animated.get(&key).cloned())
    };
    let environment = match &l.environment {
        Some(e) => Some(environment_for(client, cache, e).await?),
        None => None,
    };
    let (parsed, built_key) = match cached {
        Some(s) => (s, built_key),
        None => {
            let bytes = match (&js.source, raw) {
                (SceneRef::Builtin(_), _) => None,
                (_, Some(b)) => b,
                (SceneRef::Hash(hash), None) => Some(Arc::new(fetch_scene(client, hash).await?)),
            };
            // The same loader as the coordinator's, so both see the same scene.
            let (js2, b2, t) = (js.clone(), bytes.clone(), time.clone());
            let env2 = environment.clone();
            let parsed = tokio::task::spawn_blocking(move || {
                load_lit(&js2, b2.as_deref().map(Vec::as_slice), &t, env2.as_deref())
            })
            .await
            .map_err(|e| e.to_string())?
            .map_err(|e| e.to_string())?;
            let parsed = Arc::new(parsed);
            let mut c = lock()?;
            if parsed.animated {
                // Parsed again for every time: keep the bytes, not the scene.
                c.animated.insert(key.clone(), bytes);
                c.added(&key);
                (parsed, timed_key)
            } else {
                c.scenes.insert(key.clone(), parsed.clone());
                c.added(&key);
                (parsed, key.clone())
            }
        }
    };
    let (w, h) = (plan.width, plan.height);
    // Motion blur: an animated scene with a shutter is also loaded at the shutter's key
    // times (from the bytes kept for it), as `tessera render` does.
    let raw = if parsed.animated && js.shutter.is_some() {
        lock()?.animated.get(&key).cloned().flatten()
    } else {
        None
    };
    let times = tessera_scene::job::shutter_times(js, frame);
    let js2 = js.clone();
    let built = tokio::task::spawn_blocking(move || {
        let keys = tessera_scene::job::shutter_scenes(&times, &parsed, |t| {
            load_lit(
                &js2,
                raw.as_deref().map(Vec::as_slice),
                t,
                environment.as_deref(),
            )
        })
        .map_err(|e| e.to_string())?;
        RenderScene::build_in_motion(&parsed, &keys, w, h).map_err(|e| e.to_string())
    })
    .await
    .map_err(|e| e.to_string())??;
    let built = Arc::new(built);
    let mut c = lock()?;
    c.built.push((built_key, w, h, built.clone()));
    if c.built.len() > BUILT_CACHE {
        c.built.remove(0);
    }
    Ok(built)
}

/// The farm's scene loader, then the environment applied (replacing any the scene had),
/// in the order `tessera render` applies it.
fn load_lit(
    js: &tessera_farm::job::JobScene,
    bytes: Option<&[u8]>,
    time: &tessera_scene::SceneTime,
    environment: Option<&SceneEnvironment>,
) -> Result<Scene, tessera_scene::SceneError> {
    let mut scene = tessera_scene::job::load_job_scene_at(js, bytes, time)?;
    if let Some(e) = environment {
        e.apply(&mut scene);
    }
    Ok(scene)
}

/// A lease's environment decoded, from the cache or now: an image is fetched by its hash
/// with FetchScene (the coordinator serves environment images as it serves scenes) and
/// checked against the hash before it is decoded.
async fn environment_for(
    client: &mut Client,
    cache: &Arc<Mutex<SceneCache>>,
    env: &JobEnvironment,
) -> Result<Arc<SceneEnvironment>, String> {
    let key = env.metadata_json();
    let lock = || cache.lock().map_err(|_| "scene cache poisoned".to_string());
    if let Some((_, e)) = lock()?.environments.iter().find(|(k, _)| *k == key) {
        return Ok(e.clone());
    }
    let bytes = match &env.source {
        EnvironmentSource::Colour(_) => None,
        EnvironmentSource::Image(hash) => Some(fetch_scene(client, hash).await?),
    };
    let env2 = env.clone();
    let decoded = tokio::task::spawn_blocking(move || {
        SceneEnvironment::from_job(&env2, bytes.as_deref()).map_err(|e| e.to_string())
    })
    .await
    .map_err(|e| e.to_string())??;
    let decoded = Arc::new(decoded);
    let mut c = lock()?;
    c.environments.retain(|(k, _)| *k != key);
    c.environments.push((key, decoded.clone()));
    if c.environments.len() > ENVIRONMENT_CACHE {
        c.environments.remove(0);
    }
    Ok(decoded)
}

/// Fetches a scene's bytes by content hash and checks them against it.
async fn fetch_scene(client: &mut Client, hash: &str) -> Result<Vec<u8>, String> {
    let mut stream = client
        .fetch_scene(v1::FetchSceneRequest {
            scene_hash: hash.to_string(),
        })
        .await
        .map_err(|s| format!("fetch scene {hash}: {}", s.message()))?
        .into_inner();
    let mut bytes = Vec::new();
    while let Some(chunk) = stream
        .message()
        .await
        .map_err(|s| format!("fetch scene {hash}: {}", s.message()))?
    {
        if chunk.offset != bytes.len() as u64 {
            return Err(format!(
                "scene {hash}: chunk at offset {} after {} bytes",
                chunk.offset,
                bytes.len()
            ));
        }
        if chunk.total_size > tessera_scene::MAX_INPUT_BYTES {
            return Err(format!(
                "scene {hash}: {} bytes is too large",
                chunk.total_size
            ));
        }
        bytes.extend_from_slice(&chunk.data);
    }
    let digest = Sha256::digest(&bytes);
    let hex: String = digest.iter().map(|b| format!("{b:02x}")).collect();
    if hex != hash {
        return Err(format!("scene {hash}: received bytes hash to {hex}"));
    }
    Ok(bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_scene_cache_keeps_the_newest_scenes() {
        let mut c = SceneCache::default();
        let scene = Arc::new(tessera_scene::load("builtin:furnace").unwrap());
        for i in 0..SCENE_CACHE + 3 {
            let key = format!("s{i}");
            if i % 2 == 0 {
                c.scenes.insert(key.clone(), scene.clone());
            } else {
                c.animated.insert(key.clone(), None);
            }
            c.added(&key);
        }
        assert_eq!(c.scenes.len() + c.animated.len(), SCENE_CACHE);
        // The oldest three are gone, the newest are kept.
        for i in 0..3 {
            let key = format!("s{i}");
            assert!(!c.scenes.contains_key(&key) && !c.animated.contains_key(&key));
        }
        let newest = format!("s{}", SCENE_CACHE + 2);
        assert!(c.scenes.contains_key(&newest) || c.animated.contains_key(&newest));
        // Adding a key again moves it to the back instead of counting it twice.
        c.added("s3");
        assert_eq!(c.order.len(), SCENE_CACHE);
        assert_eq!(c.order.back().map(String::as_str), Some("s3"));
    }
}
