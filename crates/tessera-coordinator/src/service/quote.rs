//! Dry runs: `POST /api/v1/jobs?dry_run=true` quotes a job instead of queueing it
//!. The job is validated and resolved exactly as a submission is, so a quote is
//! refused for what a submission would be refused for; then a short pilot renders a
//! deterministic subset of the job's tiles and the quote is
//! [`tessera_farm::quote::quote`]'s, the same maths as `tessera estimate`.
//!
//! # Where the pilot runs, and why
//! The pilot renders on the coordinator's host in a child process (`tessera pilot`, the
//! coordinator's own binary, [`CoordinatorConfig::pilot_program`]) and not in the
//! coordinator: rendering a user's scene in the coordinator's address space would let a
//! scene that crashes or exhausts the renderer take the farm down, while a child takes
//! only itself down (and is killed at [`CoordinatorConfig::pilot_timeout_ms`]). One pilot
//! runs at a time, on one thread, so dry runs cost the coordinator at most one core;
//! another dry run meanwhile is answered 503 and may be retried.
//!
//! Its thread-seconds become worker-seconds by the fleet's threads: the quote assumes the
//! connected workers (or `?workers=N` of them) each have the mean thread count of the
//! connected ones, every thread as fast as one of the coordinator's host. With no worker
//! connected, one worker with the host's cores. The response says which (`fleet`).
//!
//! [`CoordinatorConfig::pilot_program`]: super::CoordinatorConfig::pilot_program
//! [`CoordinatorConfig::pilot_timeout_ms`]: super::CoordinatorConfig::pilot_timeout_ms

use std::time::Duration;

use super::child::{run_pilot, ChildError};
use super::Coordinator;
use crate::error::{CoordError, CoordResult};
use crate::state::now_ms;
use tessera_farm::job::{JobSettings, SceneRef};
use tessera_farm::quote::{pilot_tiles, PILOT_PASSES};

/// Default of [`super::CoordinatorConfig::pilot_timeout_ms`]: two minutes.
pub const PILOT_TIMEOUT_MS: u64 = 120_000;

/// The most camera paths a dry run's pilot may trace on the coordinator's host: about ten
/// seconds of one thread on the built-in scenes. A larger pilot (big tiles, or one
/// whole-frame bdpt tile of a large frame) is refused with the advice to run
/// `tessera estimate` on a worker.
pub const MAX_PILOT_PATHS: u64 = 1 << 23;

/// The largest fleet a quote may assume.
pub const MAX_QUOTE_WORKERS: u32 = 100_000;

/// The fleet a quote assumes: workers, threads per worker, and how they were chosen.
fn fleet(connected: &[u32], asked: Option<u32>, host_threads: u32) -> (u32, u32, String) {
    let threads = if connected.is_empty() {
        host_threads.max(1)
    } else {
        let sum: u64 = connected.iter().map(|&t| u64::from(t.max(1))).sum();
        (sum as f64 / connected.len() as f64).round().max(1.0) as u32
    };
    let basis = match (asked, connected.len()) {
        (Some(n), 0) => format!(
            "{n} worker(s) as asked, each with this coordinator host's {threads} threads (no \
             worker is connected)"
        ),
        (Some(n), _) => format!(
            "{n} worker(s) as asked, each with the connected workers' mean of {threads} threads"
        ),
        (None, 0) => format!(
            "no worker is connected: one worker with this coordinator host's {threads} threads"
        ),
        (None, c) => format!("the {c} connected worker(s), {threads} threads each on average"),
    };
    let workers = asked.unwrap_or(connected.len().max(1) as u32);
    (workers, threads, basis)
}

impl Coordinator {
    /// Quotes `settings` without queueing it (`POST /api/v1/jobs?dry_run=true`): the JSON
    /// object of `tessera estimate --json` for the job (its `quote` is `null` for a black
    /// image), with `dry_run: true` and `fleet` saying which workers it assumes. `workers`
    /// overrides the connected workers' count. See the [module docs](self).
    pub async fn quote(
        &self,
        settings: JobSettings,
        workers: Option<u32>,
    ) -> CoordResult<serde_json::Value> {
        self.accepting_work()?;
        if let Some(n) = workers {
            if n == 0 || n > MAX_QUOTE_WORKERS {
                return Err(CoordError::invalid_field(
                    "workers",
                    format!("must be 1 to {MAX_QUOTE_WORKERS}"),
                ));
            }
        }
        let mut settings = settings;
        let job = settings.validate()?;
        super::jobs::canonical_environment(&mut settings, &job);
        let (scene, environment) = self.lit_scene(&job).await?;
        let body = serde_json::to_vec(&settings).map_err(CoordError::internal)?;
        let bytes = super::resume::scene_bytes(&self.inner.farm, &job.scene.source);
        let resolved = self
            .inner
            .technique
            .resolve(&job, &body, scene, bytes, environment.clone())
            .await?;
        // A quote for a job the coordinator would refuse would mislead.
        self.check_memory(&job, &resolved)?;
        let plan = resolved.plan;
        let pilot_paths: u64 = pilot_tiles(plan.tile_count(), plan.tile(0).pixel_count() as u64)
            .iter()
            .map(|&t| plan.tile(t).pixel_count() as u64)
            .sum::<u64>()
            * u64::from(PILOT_PASSES)
            * u64::from(plan.samples_per_pass);
        if !resolved.black && pilot_paths > MAX_PILOT_PATHS {
            return Err(CoordError::TooLarge(format!(
                "the pilot of this job would trace {pilot_paths} paths ({PILOT_PASSES} passes of \
                 {} samples over its pilot tiles), more than a dry run renders on the \
                 coordinator ({MAX_PILOT_PATHS}); quote it with `tessera estimate` on a worker",
                plan.samples_per_pass
            )));
        }
        let Some(program) = self.inner.cfg.pilot_program.clone() else {
            return Err(CoordError::Unavailable(
                "this coordinator renders no pilots (it was started without a pilot \
                 program): run `tessera estimate` instead"
                    .into(),
            ));
        };
        let (connected, bytes) = {
            let farm = self.lock()?;
            let now = now_ms();
            let lost_after = self.lost_after_ms();
            let connected: Vec<u32> = farm
                .workers
                .values()
                .filter(|w| !w.draining && now.saturating_sub(w.last_seen_ms) <= lost_after)
                .map(|w| w.threads)
                .collect();
            let bytes = match &job.scene.source {
                SceneRef::Builtin(_) => None,
                SceneRef::Hash(h) => farm.scenes.get(h).cloned(),
            };
            (connected, bytes)
        };
        let host = std::thread::available_parallelism().map_or(1, |n| n.get() as u32);
        let (workers, worker_threads, basis) = fleet(&connected, workers, host);
        // One pilot at a time: a second dry run is told to come back, not queued, so dry
        // runs cannot pile up work on the coordinator's host.
        let _permit = self.inner.pilots.try_acquire().map_err(|_| {
            CoordError::Unavailable(
                "another dry run's pilot is rendering; retry in a few seconds".into(),
            )
        })?;
        let scene_bytes = match (&job.scene.source, bytes) {
            (SceneRef::Builtin(_), _) => None,
            (SceneRef::Hash(_), Some(b)) => Some(b),
            (SceneRef::Hash(h), None) => {
                return Err(CoordError::internal(format!(
                    "scene {h} loaded but its bytes are not in memory"
                )))
            }
        };
        let args = [
            "--workers".to_string(),
            workers.to_string(),
            "--worker-threads".to_string(),
            worker_threads.to_string(),
            "--threads".to_string(),
            "1".to_string(),
            "--spot-check-fraction".to_string(),
            self.inner.cfg.spot_check_fraction.to_string(),
            "--passes-per-unit".to_string(),
            self.inner.cfg.passes_per_unit.max(1).to_string(),
        ];
        let timeout = Duration::from_millis(self.inner.cfg.pilot_timeout_ms.max(1));
        let started = std::time::Instant::now();
        let out = match run_pilot(&program, &args, scene_bytes, environment, body, timeout).await {
            Ok(out) => out,
            Err(ChildError::Io(e)) => return Err(CoordError::internal(e)),
            Err(ChildError::Timeout(t)) => {
                return Err(CoordError::Unavailable(format!(
                    "the pilot did not finish within {} s (--pilot-timeout); quote a smaller \
                     job, or run `tessera estimate` on a worker",
                    t.as_secs_f64()
                )))
            }
            Err(ChildError::Failed { status, message }) => {
                tracing::warn!(%status, message, "dry-run pilot failed");
                return Err(CoordError::InvalidScene(format!(
                    "the pilot render failed ({status}): {message}"
                )));
            }
        };
        let mut value: serde_json::Value = serde_json::from_slice(&out)
            .map_err(|e| CoordError::internal(format!("the pilot's answer is not JSON: {e}")))?;
        let Some(obj) = value.as_object_mut() else {
            return Err(CoordError::internal(
                "the pilot's answer is not a JSON object",
            ));
        };
        obj.insert("dry_run".into(), true.into());
        obj.insert("fleet".into(), basis.into());
        obj.insert(
            "quote_seconds".into(),
            started.elapsed().as_secs_f64().into(),
        );
        tracing::info!(
            scene = %job.scene.source,
            workers,
            worker_threads,
            seconds = started.elapsed().as_secs_f64(),
            "dry run quoted"
        );
        Ok(value)
    }
}

#[cfg(test)]
mod tests {
    use super::fleet;

    #[test]
    fn the_fleet_is_the_connected_workers_unless_asked() {
        let (w, t, basis) = fleet(&[4, 8], None, 2);
        assert_eq!((w, t), (2, 6));
        assert!(basis.contains("2 connected"), "{basis}");
        let (w, t, _) = fleet(&[4, 8], Some(10), 2);
        assert_eq!((w, t), (10, 6));
        let (w, t, basis) = fleet(&[], None, 3);
        assert_eq!((w, t), (1, 3));
        assert!(basis.contains("no worker is connected"), "{basis}");
        let (w, t, _) = fleet(&[], Some(5), 3);
        assert_eq!((w, t), (5, 3));
    }
}
