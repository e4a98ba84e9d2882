//! Tessera HTTP API v1: the request and response bodies of the coordinator's JSON API
//! (ARCHITECTURE.md §5), shared by the coordinator, `tessera submit` / `tessera status` and tests.
//!
//! This crate only describes data: it has no HTTP framework dependency and does not link
//! the renderer (the coordinator never does).
//!
//! - Submission is two-stage, with the job contract of [`tessera_farm::job`] (re-exported
//!   here): [`JobSettings`] is the body of `POST /api/v1/jobs` as sent (strings, optional
//!   fields, defaults, unknown fields rejected), parsed by [`FromJson::from_json`];
//!   [`JobSettings::validate`] checks every field and yields a [`ValidatedJob`] or a
//!   [`JobError`], which converts into an [`ApiError`] naming the offending field.
//! - Every failure is an [`ApiError`], serialized as
//!   `{"error": {"code": "...", "message": "...", "field": "..."}}` with
//!   [`ApiError::status`] giving the HTTP status.
//! - Responses: [`JobStatus`], [`JobList`], [`WorkerInfo`], [`WorkerList`] (with its
//!   [`QuarantineInfo`] list), [`SceneUploaded`], [`HistoryPoint`].
//!
//! ```
//! use tessera_api::{ApiError, FromJson, JobSettings};
//!
//! let err = JobSettings::from_json(br#"{"scene": "builtin:cornell-box", "spp": 0}"#)
//!     .and_then(|s| s.validate().map_err(ApiError::from))
//!     .unwrap_err();
//! assert_eq!(err.status(), 400);
//! assert_eq!(err.field.as_deref(), Some("spp"));
//! assert_eq!(err.message, "spp: must be between 1 and 1048576, got 0");
//! ```
#![deny(missing_docs)]

#[cfg(feature = "client")]
pub mod client;
mod error;
mod settings;
mod status;

pub use error::{ApiError, ErrorCode};
pub use settings::FromJson;
pub use status::{
    FrameQuery, History, HistoryPoint, ImageFormat, ImageQuery, JobList, JobListQuery, JobState,
    JobStatus, QuarantineInfo, SceneUploaded, SubmitQuery, TileInfo, TileMap, WorkerInfo,
    WorkerList, WorkerState,
};
pub use tessera_farm::job::{
    resolve_resolution, AdaptiveMode, EnvironmentSettings, FrameRange, Integrator,
    IntegratorChoice, JobError, JobSettings, MisHeuristic, RenderConfig, RenderRequest,
    ResolvedJob, SamplerKind, SceneRef, Shutter, ValidatedJob, DEFAULT_CUTOFF_ALPHA,
    DEFAULT_MAX_DEPTH, DEFAULT_MIN_PASSES, DEFAULT_RR_DEPTH, DEFAULT_SPP, DEFAULT_TILE_SIZE,
    MAX_BUILTIN_NAME_CHARS, MAX_DEPTH_LIMIT, MAX_FRAMES, MAX_NAME_CHARS, MAX_SPP,
};

/// Path prefix of every API v1 route.
pub const API_PREFIX: &str = "/api/v1";

/// Request header carrying the idempotency key of `POST /api/v1/jobs`: a retried
/// submission with the same key returns the job created by the first one.
pub const IDEMPOTENCY_KEY_HEADER: &str = "idempotency-key";
