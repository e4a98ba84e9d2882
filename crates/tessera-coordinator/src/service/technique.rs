//! The technique pilot on the farm: where the scene analysis leaves the choice between
//! path tracing and bdpt to a measured pilot (`tessera_render::pilot`), the coordinator
//! runs it in a child process (`tessera pilot --technique`, [`super::child`]) before it
//! resolves the job, at submission, at a restart and wherever a stored job is resolved
//! again.
//!
//! The pilot is deterministic (a fixed seed, cost counted in rays), so the child's verdict
//! is the one `tessera render` reaches in process, and every resolution of the same job
//! reaches the same one: the frame plan, the integrator and the EXR header's plan agree
//! with a local render byte for byte. Verdicts are cached by what they depend on, so a
//! scene submitted many times, or a finished job's image served again, pilots once.
//!
//! A coordinator without a pilot program (one embedded in a test) cannot run it and keeps
//! the analysis's bdpt, saying so in the plan. A pilot that fails refuses the job, as it
//! does in `tessera render` (the resolve path's one failure policy, ARCHITECTURE.md §4).

use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use tessera_farm::job::{PilotVerdict, ResolvedJob, ValidatedJob};
use tessera_scene::job::{no_pilot, resolve_job, PilotQuestion, ResolveError};
use tessera_scene::Scene;

use super::child::{run_pilot, ChildError};

/// Verdicts kept; the cache is emptied when it is full (a verdict costs one pilot again).
const CACHE_ENTRIES: usize = 1024;

/// How the coordinator runs technique pilots: its program, their time limit, one at a
/// time, and the verdicts so far.
pub(crate) struct TechniquePilots {
    program: Option<PathBuf>,
    timeout: Duration,
    permit: tokio::sync::Semaphore,
    cache: Mutex<HashMap<String, PilotVerdict>>,
}

impl TechniquePilots {
    /// Pilots run by `program` (`None`: none run), each killed after `timeout`.
    pub(crate) fn new(program: Option<PathBuf>, timeout: Duration) -> Self {
        Self {
            program,
            timeout,
            permit: tokio::sync::Semaphore::new(1),
            cache: Mutex::new(HashMap::new()),
        }
    }

    /// Resolves `job` against `scene` on the one resolve path
    /// ([`tessera_scene::job::resolve_job`], as `tessera render` does in process), with a
    /// child process as the technique pilot where the plan asks for one (given
    /// `settings_json`, the uploaded scene's `scene_bytes` and the environment image's
    /// `environment_bytes`; `scene` is lit by the environment already). The analysis is CPU work
    /// on a scene of any size, so it runs on a blocking thread, which waits for the child
    /// on the runtime.
    pub(crate) async fn resolve(
        self: &Arc<Self>,
        job: &ValidatedJob,
        settings_json: &[u8],
        scene: Scene,
        scene_bytes: Option<Arc<Vec<u8>>>,
        environment_bytes: Option<Arc<Vec<u8>>>,
    ) -> Result<ResolvedJob, ResolveError> {
        let this = self.clone();
        let job = job.clone();
        let settings_json = settings_json.to_vec();
        let runtime = tokio::runtime::Handle::current();
        tokio::task::spawn_blocking(move || {
            resolve_job(&job, &scene, |q| {
                runtime.block_on(this.verdict(
                    q,
                    settings_json.clone(),
                    scene_bytes.clone(),
                    environment_bytes.clone(),
                ))
            })
        })
        .await
        .map_err(|e| ResolveError::Pilot(format!("the resolution panicked: {e}")))?
    }

    /// The pilot's verdict for `q`, from the cache or a child.
    async fn verdict(
        &self,
        q: &PilotQuestion<'_>,
        settings_json: Vec<u8>,
        scene_bytes: Option<Arc<Vec<u8>>>,
        environment_bytes: Option<Arc<Vec<u8>>>,
    ) -> Result<PilotVerdict, String> {
        let Some(program) = &self.program else {
            return no_pilot("this coordinator has no pilot program")(q);
        };
        // The question's key names the scene, not the light around it: the environment
        // (its image's hash, strength and rotation) changes what the pilot measures.
        let environment = q.job.environment.as_ref().map(|e| e.metadata_json());
        let key = format!("{}|{}", q.key(), environment.unwrap_or_default());
        if let Some(v) = self.cached(&key) {
            return Ok(v);
        }
        let _permit = self.permit.acquire().await.map_err(|e| e.to_string())?;
        // Another request may have piloted the same job while this one waited.
        if let Some(v) = self.cached(&key) {
            return Ok(v);
        }
        let args = ["--technique".to_string(), "--threads".into(), "1".into()];
        let out = run_pilot(
            program,
            &args,
            scene_bytes,
            environment_bytes,
            settings_json,
            self.timeout,
        )
        .await
        .map_err(|e| match e {
            ChildError::Io(e) => e,
            ChildError::Timeout(t) => {
                format!("it did not finish within {} s", t.as_secs_f64())
            }
            ChildError::Failed { status, message } => format!("{status}: {message}"),
        })?;
        let v: PilotVerdict = serde_json::from_slice(&out)
            .map_err(|e| format!("its answer is not a verdict: {e}"))?;
        tracing::info!(scene = %q.job.scene.source, path_wins = v.path_wins, "technique pilot");
        if let Ok(mut c) = self.cache.lock() {
            if c.len() >= CACHE_ENTRIES {
                c.clear();
            }
            c.insert(key, v.clone());
        }
        Ok(v)
    }

    fn cached(&self, key: &str) -> Option<PilotVerdict> {
        self.cache.lock().ok()?.get(key).cloned()
    }
}

impl From<ResolveError> for crate::error::CoordError {
    fn from(e: ResolveError) -> Self {
        match e {
            ResolveError::Job(e) => e.into(),
            e @ ResolveError::Pilot(_) => Self::InvalidScene(e.to_string()),
        }
    }
}
