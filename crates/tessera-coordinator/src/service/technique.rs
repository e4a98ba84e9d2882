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
//! the analysis's bdpt, saying so in the plan.

use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use serde::Deserialize;
use tessera_farm::job::{JobError, ResolvedJob, SceneFacts, ValidatedJob};
use tessera_scene::Scene;

use super::child::{run_pilot, ChildError};

/// Verdicts kept; the cache is emptied when it is full (a verdict costs one pilot again).
const CACHE_ENTRIES: usize = 1024;

/// The child's answer.
#[derive(Clone, Debug, Deserialize)]
struct Verdict {
    path_wins: bool,
    reason: String,
}

/// How the coordinator runs technique pilots: its program, their time limit, one at a
/// time, and the verdicts so far.
pub(crate) struct TechniquePilots {
    program: Option<PathBuf>,
    timeout: Duration,
    permit: tokio::sync::Semaphore,
    cache: Mutex<HashMap<String, Verdict>>,
}

/// Why a job did not resolve.
#[derive(Debug, thiserror::Error)]
pub(crate) enum ResolveError {
    /// The settings do not resolve against the scene.
    #[error("{0}")]
    Job(#[from] JobError),
    /// The technique pilot failed: the scene does not render.
    #[error("the technique pilot failed: {0}")]
    Pilot(String),
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

    /// Resolves `job` against `scene` as `tessera_render::pilot::resolve_job` does in
    /// process: the analysis, the technique pilot where the plan asks for one (in a child,
    /// given `settings_json` and the uploaded scene's `scene_bytes`), then resolution.
    pub(crate) async fn resolve(
        &self,
        job: &ValidatedJob,
        settings_json: &[u8],
        scene: &Scene,
        scene_bytes: Option<Arc<Vec<u8>>>,
    ) -> Result<ResolvedJob, ResolveError> {
        let mut plan = tessera_scene::analysis::analyse(scene);
        if plan.awaits_technique_pilot(job.render.integrator) {
            let verdict = self.verdict(job, settings_json, scene, scene_bytes).await?;
            plan.settle_technique(verdict.path_wins, verdict.reason);
        }
        Ok(job.resolve(
            SceneFacts {
                default_resolution: scene.default_resolution,
            },
            plan,
        )?)
    }

    /// The pilot's verdict for `job`, from the cache or a child.
    async fn verdict(
        &self,
        job: &ValidatedJob,
        settings_json: &[u8],
        scene: &Scene,
        scene_bytes: Option<Arc<Vec<u8>>>,
    ) -> Result<Verdict, ResolveError> {
        let Some(program) = &self.program else {
            return Ok(Verdict {
                path_wins: false,
                reason: "technique pilot not run (this coordinator has no pilot program): \
                         bdpt, the analysis's choice"
                    .into(),
            });
        };
        // What the verdict depends on (tessera_render::pilot::run): the scene, its camera
        // and animation, the resolution's aspect, the depth, MIS and sampler.
        let (w, h) = job.resolution(scene.default_resolution);
        let key = format!(
            "{}|{:?}|{:?}|{w}x{h}|{:?}|{}|{}",
            job.scene,
            job.camera,
            job.animation,
            job.render.max_depth,
            job.render.mis,
            job.render.sampler
        );
        if let Some(v) = self.cached(&key) {
            return Ok(v);
        }
        let _permit = self
            .permit
            .acquire()
            .await
            .map_err(|e| ResolveError::Pilot(e.to_string()))?;
        // Another request may have piloted the same job while this one waited.
        if let Some(v) = self.cached(&key) {
            return Ok(v);
        }
        let args = ["--technique".to_string(), "--threads".into(), "1".into()];
        let out = run_pilot(
            program,
            &args,
            scene_bytes,
            settings_json.to_vec(),
            self.timeout,
        )
        .await
        .map_err(|e| {
            ResolveError::Pilot(match e {
                ChildError::Io(e) => e,
                ChildError::Timeout(t) => {
                    format!("it did not finish within {} s", t.as_secs_f64())
                }
                ChildError::Failed { status, message } => format!("{status}: {message}"),
            })
        })?;
        let v: Verdict = serde_json::from_slice(&out)
            .map_err(|e| ResolveError::Pilot(format!("its answer is not a verdict: {e}")))?;
        tracing::info!(scene = %job.scene, path_wins = v.path_wins, "technique pilot");
        if let Ok(mut c) = self.cache.lock() {
            if c.len() >= CACHE_ENTRIES {
                c.clear();
            }
            c.insert(key, v.clone());
        }
        Ok(v)
    }

    fn cached(&self, key: &str) -> Option<Verdict> {
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
