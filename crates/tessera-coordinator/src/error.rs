//! The coordinator's one error type, and its two presentations: an HTTP error body
//! ([`ApiError`], status + code + field, ARCHITECTURE.md §5) for the HTTP API and a
//! [`tonic::Status`] for the workers' gRPC service.
//!
//! The service layer returns [`CoordError`]; it knows nothing of HTTP or gRPC. The
//! conversions below are the only places that choose a status, and they do not log: the
//! HTTP request span logs server faults (`http::trace_request`), the gRPC service logs
//! them where it answers.

use tessera_api::{ApiError, ErrorCode};
use tessera_farm::job::JobError;
use tonic::Status;

use crate::store::StoreError;

/// Why a coordinator operation failed. The text (`Display`) is what clients read.
#[derive(Debug, thiserror::Error)]
pub enum CoordError {
    /// The job, worker or scene does not exist; the text says which.
    #[error("{0}")]
    NotFound(String),
    /// One field of the request is wrong; the text is `"{field}: {message}"`.
    #[error("{field}: {message}")]
    InvalidField {
        /// The field, e.g. `"spp"`, `"scene"`, `"frame"`.
        field: String,
        /// What is wrong with it.
        message: String,
    },
    /// The request is malformed as a whole (e.g. an empty scene upload).
    #[error("{0}")]
    InvalidRequest(String),
    /// An uploaded scene does not load.
    #[error("invalid scene: {0}")]
    InvalidScene(String),
    /// The request is larger than the coordinator accepts.
    #[error("{0}")]
    TooLarge(String),
    /// Storing this would exceed a storage quota; the text names the limit and the
    /// numbers.
    #[error("{0}")]
    InsufficientStorage(String),
    /// The request conflicts with what exists, e.g. an idempotency key reused with other
    /// settings; `field` names the input (the key's header).
    #[error("{field}: {message}")]
    Conflict {
        /// The input in conflict, e.g. `"idempotency-key"`.
        field: String,
        /// What it conflicts with.
        message: String,
    },
    /// The durable store failed; the request may be retried. A write failure
    /// ([`StoreError::is_write_failure`]) says that the coordinator stopped accepting work.
    #[error("{}", store_message(.0))]
    Store(#[from] StoreError),
    /// This coordinator is not the active one (a standby, or one that lost the
    /// leadership; `crate::ha`): workers and clients go to the active one. The text
    /// names the state.
    #[error("{0}")]
    NotActive(String),
    /// The coordinator cannot do this now or here (e.g. another dry run's pilot is
    /// rendering, or dry runs are not set up); the text says why and what to do instead.
    #[error("{0}")]
    Unavailable(String),
    /// Anything else that is the coordinator's fault.
    #[error("internal error: {0}")]
    Internal(String),
}

/// The text of [`CoordError::Store`].
fn store_message(e: &StoreError) -> String {
    match e {
        // Already says that no new work is accepted.
        StoreError::Failing(_) | StoreError::DiskFull(_) => e.to_string(),
        e if e.is_disk_full() => format!(
            "the disk of the store is full ({e}); this coordinator serves reads and \
             accepts no new work until space is freed, then resumes by itself (docs/store.md)"
        ),
        e if e.is_write_failure() => format!(
            "the store failed to write ({e}); this coordinator accepts no new work until it \
             is restarted (docs/store.md)"
        ),
        e => format!("internal error: {e}"),
    }
}

/// A coordinator operation's result.
pub type CoordResult<T> = Result<T, CoordError>;

impl CoordError {
    /// [`CoordError::InvalidField`] of `field`.
    pub fn invalid_field(field: impl Into<String>, message: impl std::fmt::Display) -> Self {
        Self::InvalidField {
            field: field.into(),
            message: message.to_string(),
        }
    }

    /// [`CoordError::Internal`].
    pub fn internal(e: impl std::fmt::Display) -> Self {
        Self::Internal(e.to_string())
    }

    /// The answer to a request for job `id`, which does not exist.
    pub fn job_not_found(id: u64) -> Self {
        Self::NotFound(format!("job {id} does not exist"))
    }

    /// The answer to a worker the coordinator does not know (it restarted, or the
    /// worker never registered): the worker registers again (ARCHITECTURE.md §9).
    pub fn unknown_worker() -> Self {
        Self::NotFound("unknown worker: register again".into())
    }

    /// The mutex around the farm state was poisoned by a panic.
    pub(crate) fn poisoned() -> Self {
        Self::Internal("farm state poisoned".into())
    }

    /// Whether the coordinator (not the client) is at fault: worth an error log.
    pub fn is_server_fault(&self) -> bool {
        matches!(self, Self::Store(_) | Self::Internal(_))
    }
}

impl From<JobError> for CoordError {
    /// A job setting that failed validation or resolution names its field.
    fn from(e: JobError) -> Self {
        Self::InvalidField {
            field: e.field,
            message: e.problem,
        }
    }
}

impl From<CoordError> for ApiError {
    /// The one mapping to HTTP: each variant has one [`ErrorCode`] (hence one status).
    fn from(e: CoordError) -> Self {
        let code = match &e {
            CoordError::NotFound(_) => ErrorCode::NotFound,
            CoordError::InvalidField { field, message } => {
                return ApiError::invalid_field(field.clone(), message);
            }
            CoordError::InvalidRequest(_) => ErrorCode::InvalidRequest,
            CoordError::InvalidScene(_) => ErrorCode::InvalidScene,
            CoordError::TooLarge(_) => ErrorCode::TooLarge,
            CoordError::InsufficientStorage(_) => ErrorCode::InsufficientStorage,
            // A full disk: 507, until space is freed (docs/store.md).
            CoordError::Store(s) if s.is_disk_full() => ErrorCode::InsufficientStorage,
            // The store takes no writes (full disk, I/O error, read-only file): the
            // coordinator stops accepting work until restarted (docs/store.md).
            CoordError::Store(s) if s.is_write_failure() => ErrorCode::Unavailable,
            CoordError::NotActive(_) | CoordError::Unavailable(_) => ErrorCode::Unavailable,
            CoordError::Conflict { field, .. } => {
                return ApiError {
                    code: ErrorCode::Conflict,
                    message: e.to_string(),
                    field: Some(field.clone()),
                };
            }
            CoordError::Store(_) | CoordError::Internal(_) => ErrorCode::Internal,
        };
        ApiError::new(code, e.to_string())
    }
}

impl From<CoordError> for Status {
    /// The one mapping to gRPC. A store failure is `UNAVAILABLE`: the worker retries, and
    /// what it was told nothing about (a lease, a result) is simply issued again
    /// (ARCHITECTURE.md §9, steps 7 and 10).
    fn from(e: CoordError) -> Self {
        match e {
            CoordError::NotFound(m) => Status::not_found(m),
            e @ CoordError::InvalidField { .. } => Status::invalid_argument(e.to_string()),
            CoordError::InvalidRequest(m) => Status::invalid_argument(m),
            e @ CoordError::InvalidScene(_) => Status::invalid_argument(e.to_string()),
            CoordError::TooLarge(m) | CoordError::InsufficientStorage(m) => {
                Status::resource_exhausted(m)
            }
            e @ CoordError::Conflict { .. } => Status::already_exists(e.to_string()),
            CoordError::Store(e) => Status::unavailable(format!("coordinator store: {e}")),
            // UNAVAILABLE: the worker tries the next coordinator it knows.
            CoordError::NotActive(m) | CoordError::Unavailable(m) => Status::unavailable(m),
            CoordError::Internal(m) => Status::internal(m),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn http_and_grpc_mappings_keep_the_texts_clients_see() {
        let e: ApiError = CoordError::invalid_field("scene", "no such scene").into();
        assert_eq!((e.status(), e.field.as_deref()), (400, Some("scene")));
        assert_eq!(e.message, "scene: no such scene");
        let e: ApiError = CoordError::job_not_found(7).into();
        assert_eq!(
            (e.status(), e.message.as_str()),
            (404, "job 7 does not exist")
        );
        let e: ApiError = CoordError::internal("boom").into();
        assert_eq!(
            (e.status(), e.message.as_str()),
            (500, "internal error: boom")
        );
        let e: ApiError =
            CoordError::Store(StoreError::Failing("storing a job: disk full".into())).into();
        assert_eq!(e.status(), 503);
        assert!(
            e.message.contains("storing a job: disk full"),
            "{}",
            e.message
        );
        assert!(e.message.contains("accepts no new work"), "{}", e.message);
        let s: Status = CoordError::unknown_worker().into();
        assert_eq!(s.code(), tonic::Code::NotFound);
        assert_eq!(s.message(), "unknown worker: register again");
        let s: Status = CoordError::invalid_field("name", "at most 200 characters").into();
        assert_eq!(s.code(), tonic::Code::InvalidArgument);
        assert_eq!(s.message(), "name: at most 200 characters");
    }
}
