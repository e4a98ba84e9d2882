//! Response bodies: jobs, workers, scenes, convergence history.

use serde::{Deserialize, Serialize};

use tessera_farm::job::JobSettings;

/// Life-cycle state of a job; serialized in lowercase.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum JobState {
    /// Accepted, no unit leased yet.
    Queued,
    /// Units are being rendered.
    Running,
    /// Every planned pass is merged, or a stopping criterion (target error, time limit,
    /// adaptive stopping) was met.
    Done,
    /// The job cannot complete (e.g. its scene failed to load); see [`JobStatus::error`].
    Failed,
    /// Canceled with `DELETE /api/v1/jobs/{id}`.
    Canceled,
}

impl JobState {
    /// Whether the job will not change any more (done, failed or canceled).
    pub fn is_terminal(self) -> bool {
        matches!(self, Self::Done | Self::Failed | Self::Canceled)
    }

    /// The string form, e.g. `"queued"`.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Queued => "queued",
            Self::Running => "running",
            Self::Done => "done",
            Self::Failed => "failed",
            Self::Canceled => "canceled",
        }
    }
}

/// `GET /api/v1/jobs/{id}` (and the body of a successful `POST /api/v1/jobs`): a job and
/// its progress.
///
/// Pass counts are summed over tiles and frames: a job of F frames of T tiles with P passes
/// each plans `F * T * P` passes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JobStatus {
    /// Job id.
    pub id: u64,
    /// The job's name, if it was given one.
    pub name: Option<String>,
    /// Life-cycle state.
    pub state: JobState,
    /// The scene reference (`"builtin:NAME"` or content hash).
    pub scene: String,
    /// The settings, in canonical form (every default filled in).
    pub settings: JobSettings,
    /// The resolved image width (known once the scene is loaded).
    #[serde(default)]
    pub width: Option<u32>,
    /// The resolved image height (known once the scene is loaded).
    #[serde(default)]
    pub height: Option<u32>,
    /// Number of frames.
    pub frames_total: u32,
    /// Number of frames with every planned pass merged.
    pub frames_done: u32,
    /// Tiles per frame times frames.
    pub tiles_total: u64,
    /// Passes planned, over all tiles and frames.
    pub passes_planned: u64,
    /// Passes merged, over all tiles and frames. A pass counts once it is merged, before
    /// its checkpoint's group commit, after which its worker hears "accepted"; so after a
    /// coordinator crash the count may start a little lower than it last read: those
    /// passes are delivered again (or rendered again), never lost.
    pub passes_done: u64,
    /// Samples per pixel merged so far, averaged over the pixels of all frames (not an
    /// integer under adaptive stopping).
    pub spp_so_far: f64,
    /// The current image error estimate (RMS relative error, ARCHITECTURE.md §3), the one
    /// `error_estimator` names, as of the job's last history point (at most 0.2 s old while
    /// results arrive); `None` until every pixel has at least two passes. (Before
    /// 2026-12-07 a job without adaptive stopping gave the RMS of each pixel's error over
    /// its own mean here, not the robust scale its `error_estimator` named.)
    pub error_estimate: Option<f64>,
    /// Which estimator `error_estimate` and the per-pixel intervals are
    /// (`tessera_farm::ERROR_ESTIMATOR`, also in the EXR header). For a job read back from
    /// the store, the name stored with its estimate (store schema version 9, PostgreSQL
    /// 8); absent when the estimate was stored by an older build, which did not say which
    /// estimator computed it, and from older servers.
    #[serde(default)]
    pub error_estimator: Option<String>,
    /// Why `error_estimate` may be optimistic for this job, when the render plan knows
    /// (path tracing a scene whose caustics are lit by tiny or delta lights, which only
    /// bdpt samples; adaptive stopping on a scene of rare bright paths;
    /// `tessera_farm::job::ResolvedJob::error_estimate_caveat`, also in the
    /// EXR header). Absent when there is none, from older servers, and for a job stored
    /// by one (before store schema version 6, PostgreSQL 5).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error_estimate_caveat: Option<String>,
    /// The requested target error, if any.
    pub target_error: Option<f64>,
    /// Once a job with a target error is done: whether its error estimate is at or below
    /// the target. `None` while it runs, and without a target. A job can finish without
    /// reaching its target (its pixels ran out of passes, or its time limit came first);
    /// [`JobStatus::stop_reason`] then says why.
    #[serde(default)]
    pub target_reached: Option<bool>,
    /// Once a job that may stop early (adaptive, a target error or a time limit) is done:
    /// why it stopped, and for a target whether and why not it was reached, e.g.
    /// "target error 0.03 not reached: the estimate is 0.0362 when the sample budget
    /// (4096 spp) ran out".
    #[serde(default)]
    pub stop_reason: Option<String>,
    /// Seconds since the job started running (0 while queued).
    pub elapsed_seconds: f64,
    /// Estimated seconds until done; `None` when not yet predictable, and for a job that
    /// stops at its target error whose error is not predictable from its passes so far
    /// (`eta_tail_class` `unpredictable`; `eta_note` says why).
    pub eta_seconds: Option<f64>,
    /// The low end of the 95% interval of the seconds until done, for a running job that
    /// stops at its target error (adaptive with a target; ARCHITECTURE.md §3, "Quotes and
    /// ETA"): where the law the ETA extrapolates is not predictable, a lower bound. Absent
    /// for other jobs and from older servers.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub eta_low_seconds: Option<f64>,
    /// The high end of that interval: where not predictable, the sample budget at the rate
    /// so far (the job cannot run longer). Absent as `eta_low_seconds` is.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub eta_high_seconds: Option<f64>,
    /// For a running job that stops at its target error: how far the ETA's law can be
    /// trusted, classed as a quote's pilot is (`tessera_farm::quote::TailClass`):
    /// `light` (the interval stands), `heavy` (its high end widened for a per-pass error
    /// still growing) or `unpredictable` (no `eta_seconds`). Absent for other jobs and
    /// from older servers.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub eta_tail_class: Option<String>,
    /// Why, unless `light`: the reason and the measured figures, e.g. "not predictable
    /// from the passes so far: the error estimate grew with the passes instead of
    /// falling, ...".
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub eta_note: Option<String>,
    /// When the job was accepted, Unix milliseconds.
    pub created_unix_ms: u64,
    /// When the job started running (its first lease), Unix milliseconds; `None` while
    /// queued. Absent from older servers.
    #[serde(default)]
    pub started_unix_ms: Option<u64>,
    /// When the job reached its final state (done, failed or canceled), Unix
    /// milliseconds, as the coordinator's clock read it; `None` until then. A client
    /// polling the status learns when a job ended to the millisecond without polling
    /// that often. Absent from older servers.
    #[serde(default)]
    pub finished_unix_ms: Option<u64>,
    /// Scheduling priority (higher first).
    pub priority: i32,
    /// Faulty-worker events on this job: refused results (wrong size, non-finite values)
    /// and duplicate results that differ from the merged copy.
    pub faults: u64,
    /// Samples the renderers dropped as NaN, infinite or negative radiance, summed over
    /// the job's accepted units (each counts as black in its pixel). 0 in a healthy
    /// render; anything else points at a renderer bug. Absent from older servers.
    #[serde(default)]
    pub rejected_samples: u64,
    /// Why the job failed, when `state` is `failed`.
    #[serde(default)]
    pub error: Option<String>,
    /// The render plan (ARCHITECTURE.md §4): the light-transport effects found in the scene with
    /// their evidence, the absent ones, and the integrator configuration chosen for them,
    /// as `tessera_farm::job::RenderPlan::to_json` writes it, kept with the job in the
    /// store. `None` for a job stored by an older build (before store schema version 6,
    /// PostgreSQL 5).
    #[serde(default)]
    pub plan: Option<serde_json::Value>,
    /// Adaptive stopping mode (`off`, `sequential`, `unbiased`).
    #[serde(default)]
    pub adaptive: String,
}

/// `GET /api/v1/jobs`: one page of jobs, newest first.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JobList {
    /// The jobs of this page.
    pub jobs: Vec<JobStatus>,
    /// Pass as `?cursor=` to get the next page; `None` on the last page.
    pub next_cursor: Option<String>,
}

/// Query string of `GET /api/v1/jobs`.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JobListQuery {
    /// `next_cursor` of the previous page.
    #[serde(default)]
    pub cursor: Option<String>,
    /// Page size (the server caps it).
    #[serde(default)]
    pub limit: Option<u32>,
    /// Only jobs in this state.
    #[serde(default)]
    pub state: Option<JobState>,
}

/// Query string of `POST /api/v1/jobs`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SubmitQuery {
    /// Quote the job instead of queueing it: a short pilot predicts the seconds and
    /// worker-seconds to reach 10%, 5%, 2% and 1% error (or the job's `target_error`).
    #[serde(default)]
    pub dry_run: bool,
    /// With `dry_run`: workers the quote assumes (default: the connected workers).
    #[serde(default)]
    pub workers: Option<u32>,
}

/// Image file format of `GET /api/v1/jobs/{id}/image`; serialized in lowercase.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ImageFormat {
    /// 8-bit sRGB PNG of the mean. The default.
    #[default]
    Png,
    /// Multi-layer float OpenEXR (mean, variance of the mean, passes, ...).
    Exr,
}

impl ImageFormat {
    /// The MIME type of the response.
    pub fn content_type(self) -> &'static str {
        match self {
            Self::Png => "image/png",
            Self::Exr => "image/x-exr",
        }
    }
}

/// Query string of `GET /api/v1/jobs/{id}/image`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImageQuery {
    /// File format; default PNG.
    #[serde(default)]
    pub format: ImageFormat,
    /// Frame number; default the job's first frame.
    #[serde(default)]
    pub frame: Option<u32>,
}

/// State of a worker; serialized in lowercase.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum WorkerState {
    /// Connected, holding no lease.
    Idle,
    /// Connected, rendering leased units.
    Busy,
    /// Shutting down: finishing or returning its leases.
    Draining,
    /// Missed its heartbeats; its leases were (or will be) returned to the queue.
    Lost,
}

/// One worker in `GET /api/v1/workers`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct WorkerInfo {
    /// Worker id (assigned at registration).
    pub id: u64,
    /// The name the worker registered with.
    pub name: String,
    /// Render threads.
    pub threads: u32,
    /// Current state.
    pub state: WorkerState,
    /// Last heartbeat, Unix milliseconds.
    pub last_heartbeat_unix_ms: u64,
    /// Units whose results were accepted.
    pub units_done: u64,
    /// Recent throughput in camera paths per second.
    pub paths_per_second: f64,
    /// Faulty-worker events: refused results and mismatching duplicates.
    pub faults: u64,
    /// The worker's Tessera version.
    #[serde(default)]
    pub version: String,
    /// Under mutual TLS, the common name of the certificate the worker connected with
    /// (its identity); absent otherwise.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub identity: Option<String>,
    /// Whether a spot check found the worker faulty: it gets no leases and its results
    /// are refused (ARCHITECTURE.md §6, "Spot checks and quarantine").
    #[serde(default)]
    pub quarantined: bool,
    /// Why it is quarantined; absent if it is not.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub quarantine_reason: Option<String>,
}

/// `GET /api/v1/workers`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct WorkerList {
    /// The workers, by id.
    pub workers: Vec<WorkerInfo>,
    /// The quarantine list: every name and identity under which a worker is quarantined
    /// when it registers, whether or not such a worker is connected now (after a restart
    /// of the coordinator it may not have registered yet).
    #[serde(default)]
    pub quarantines: Vec<QuarantineInfo>,
}

/// One entry of the quarantine list in `GET /api/v1/workers` (ARCHITECTURE.md §6, "Spot
/// checks and quarantine"): kept in the coordinator's store until
/// `DELETE /api/v1/workers/{name}/quarantine` lifts it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct QuarantineInfo {
    /// The name the worker registered with.
    pub name: String,
    /// The common name of its TLS client certificate under mutual TLS; absent otherwise.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub identity: Option<String>,
    /// Why it was quarantined.
    pub reason: String,
    /// When it was first quarantined, Unix milliseconds.
    pub since_unix_ms: u64,
}

/// `POST /api/v1/scenes`: the stored scene's content hash and statistics.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct SceneUploaded {
    /// Lowercase hex SHA-256 of the uploaded bytes: the `scene` of a job.
    pub hash: String,
    /// Size of the upload in bytes.
    pub bytes: u64,
    /// Triangles in the scene.
    pub triangles: u64,
    /// Meshes as placed (glTF mesh primitives, instances counted once per place).
    pub meshes: u32,
    /// Materials.
    pub materials: u32,
    /// Lights (punctual lights and emissive meshes).
    pub lights: u32,
}

/// One point of a job's convergence history, for the dashboard's error-versus-time plot.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct HistoryPoint {
    /// Seconds since the job started running.
    pub elapsed_seconds: f64,
    /// Samples per pixel merged at that time (averaged over pixels).
    pub spp: f64,
    /// Image error estimate at that time; `None` before every pixel had two passes.
    pub error_estimate: Option<f64>,
}

/// `GET /api/v1/jobs/{id}/history`: the convergence history, oldest first.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct History {
    /// One point per merge step (thinned to at most a few thousand points).
    pub points: Vec<HistoryPoint>,
}

/// One tile in `GET /api/v1/jobs/{id}/tiles`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TileInfo {
    /// Tile index, row-major.
    pub index: u32,
    /// Left pixel column.
    pub x: u32,
    /// Top pixel row.
    pub y: u32,
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Passes merged into this tile.
    pub passes: u32,
    /// Mean samples per pixel merged into this tile.
    pub spp: f64,
    /// RMS relative error of the tile's pixels; `None` before two passes.
    pub error: Option<f64>,
    /// Whether the tile has stopped (all passes merged, or stopped adaptively).
    pub done: bool,
}

/// `GET /api/v1/jobs/{id}/tiles?frame=F`: per-tile progress of one frame, for heat maps.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TileMap {
    /// The frame.
    pub frame: u32,
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// Passes planned per tile.
    pub passes_planned: u32,
    /// The tiles, by index.
    pub tiles: Vec<TileInfo>,
}

/// Query string of `GET /api/v1/jobs/{id}/tiles`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FrameQuery {
    /// Frame number; default the job's first frame.
    #[serde(default)]
    pub frame: Option<u32>,
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn status() -> JobStatus {
        JobStatus {
            id: 42,
            name: Some("turntable".into()),
            state: JobState::Running,
            scene: "builtin:cornell-box".into(),
            settings: JobSettings::new("builtin:cornell-box"),
            width: Some(256),
            height: Some(256),
            frames_total: 1,
            frames_done: 0,
            tiles_total: 64,
            passes_planned: 512,
            passes_done: 100,
            spp_so_far: 12.5,
            error_estimate: Some(0.031),
            error_estimator: Some("pass-spread".into()),
            error_estimate_caveat: None,
            target_error: None,
            target_reached: None,
            stop_reason: None,
            elapsed_seconds: 3.25,
            eta_seconds: Some(10.0),
            eta_low_seconds: None,
            eta_high_seconds: None,
            eta_tail_class: None,
            eta_note: None,
            created_unix_ms: 1_700_000_000_000,
            started_unix_ms: Some(1_700_000_000_250),
            finished_unix_ms: None,
            priority: 0,
            faults: 1,
            rejected_samples: 3,
            error: None,
            plan: None,
            adaptive: "off".into(),
        }
    }

    fn round_trip<T>(v: &T) -> serde_json::Value
    where
        T: Serialize + serde::de::DeserializeOwned + PartialEq + std::fmt::Debug,
    {
        let s = serde_json::to_string(v).unwrap();
        assert_eq!(&serde_json::from_str::<T>(&s).unwrap(), v);
        serde_json::from_str(&s).unwrap()
    }

    #[test]
    fn job_status_json() {
        let v = round_trip(&status());
        assert_eq!(v["state"], "running");
        assert_eq!(v["settings"]["spp"], 64);
        assert_eq!(v["settings"]["mis"], "power");
        assert_eq!(v["target_error"], serde_json::Value::Null);
        assert_eq!(v["eta_seconds"], 10.0);
        // The ETA's interval and class are for jobs that stop at a target: absent here, so
        // a client of an older server reads the same JSON.
        for absent in [
            "eta_low_seconds",
            "eta_high_seconds",
            "eta_tail_class",
            "eta_note",
        ] {
            assert!(v.get(absent).is_none(), "{absent}: {v}");
        }
        let not_predictable = JobStatus {
            eta_seconds: None,
            eta_low_seconds: Some(2.0),
            eta_high_seconds: Some(90.0),
            eta_tail_class: Some("unpredictable".into()),
            eta_note: Some("not predictable from the passes so far: ...".into()),
            ..status()
        };
        let v = round_trip(&not_predictable);
        assert_eq!(v["eta_seconds"], serde_json::Value::Null);
        assert_eq!(v["eta_high_seconds"], 90.0);
        assert_eq!(v["eta_tail_class"], "unpredictable");
        assert_eq!(v["rejected_samples"], 3);
        let list = JobList {
            jobs: vec![status(), status()],
            next_cursor: Some("41".into()),
        };
        let v = round_trip(&list);
        assert_eq!(v["jobs"].as_array().unwrap().len(), 2);
        assert_eq!(v["next_cursor"], "41");
        // Optional additions may be absent (an older server).
        let mut v = serde_json::to_value(status()).unwrap();
        let obj = v.as_object_mut().unwrap();
        obj.remove("width");
        obj.remove("height");
        obj.remove("error");
        obj.remove("rejected_samples");
        let s: JobStatus = serde_json::from_value(v).unwrap();
        assert_eq!((s.width, s.error), (None, None));
        assert_eq!(s.rejected_samples, 0);
    }

    #[test]
    fn states() {
        for (s, name, terminal) in [
            (JobState::Queued, "queued", false),
            (JobState::Running, "running", false),
            (JobState::Done, "done", true),
            (JobState::Failed, "failed", true),
            (JobState::Canceled, "canceled", true),
        ] {
            assert_eq!(serde_json::to_value(s).unwrap(), json!(name));
            assert_eq!(s.as_str(), name);
            assert_eq!(s.is_terminal(), terminal);
        }
        assert!(serde_json::from_value::<JobState>(json!("cancelled")).is_err());
    }

    #[test]
    fn workers_scenes_history() {
        let w = WorkerInfo {
            id: 3,
            name: "render-3".into(),
            threads: 8,
            state: WorkerState::Busy,
            last_heartbeat_unix_ms: 1_700_000_000_123,
            units_done: 77,
            paths_per_second: 1.5e6,
            faults: 0,
            version: "0.1.0".into(),
            identity: Some("render-3.farm".into()),
            quarantined: true,
            quarantine_reason: Some("spot check".into()),
        };
        let v = round_trip(&WorkerList {
            workers: vec![w.clone()],
            quarantines: vec![QuarantineInfo {
                name: "render-3".into(),
                identity: None,
                reason: "spot check".into(),
                since_unix_ms: 1_700_000_000_000,
            }],
        });
        assert_eq!(v["workers"][0]["state"], "busy");
        assert_eq!(v["workers"][0]["paths_per_second"], 1.5e6);
        assert_eq!(
            v["quarantines"],
            json!([{"name": "render-3", "reason": "spot check", "since_unix_ms": 1_700_000_000_000u64}])
        );
        // A list from a coordinator without the quarantine list still reads.
        let old: WorkerList = serde_json::from_value(json!({"workers": []})).unwrap();
        assert!(old.quarantines.is_empty());

        let sc = SceneUploaded {
            hash: "ab".repeat(32),
            bytes: 1234,
            triangles: 36,
            meshes: 3,
            materials: 2,
            lights: 1,
        };
        assert_eq!(
            round_trip(&sc),
            json!({"hash": "ab".repeat(32), "bytes": 1234, "triangles": 36,
                   "meshes": 3, "materials": 2, "lights": 1})
        );
        let h = HistoryPoint {
            elapsed_seconds: 1.0,
            spp: 8.0,
            error_estimate: None,
        };
        assert_eq!(
            round_trip(&h),
            json!({"elapsed_seconds": 1.0, "spp": 8.0, "error_estimate": null})
        );
    }

    #[test]
    fn queries() {
        let q: ImageQuery = serde_json::from_value(json!({})).unwrap();
        assert_eq!(q, ImageQuery::default());
        assert_eq!(q.format.content_type(), "image/png");
        let q: ImageQuery = serde_json::from_value(json!({"format": "exr", "frame": 3})).unwrap();
        assert_eq!((q.format, q.frame), (ImageFormat::Exr, Some(3)));
        assert!(serde_json::from_value::<ImageQuery>(json!({"format": "tiff"})).is_err());
        assert!(serde_json::from_value::<ImageQuery>(json!({"fromat": "exr"})).is_err());
        let q: JobListQuery =
            serde_json::from_value(json!({"state": "done", "limit": 10})).unwrap();
        assert_eq!(q.state, Some(JobState::Done));
        round_trip(&q);
    }
}
