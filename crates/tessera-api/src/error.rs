//! The JSON error body of every failed request (ARCHITECTURE.md §5).

use std::fmt;

use serde::{Deserialize, Serialize};

/// Machine-readable kind of an [`ApiError`]; serialized in `snake_case`
/// (`"invalid_field"`, `"not_found"`, ...). Each maps to one HTTP status
/// ([`ErrorCode::status`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ErrorCode {
    /// A field of the request has an invalid value; [`ApiError::field`] names it. 400.
    InvalidField,
    /// The request is malformed as a whole (not JSON, wrong content type, bad query
    /// string). 400.
    InvalidRequest,
    /// An uploaded scene could not be parsed or failed validation. 400.
    InvalidScene,
    /// A bearer token is required and was missing or wrong. 401.
    Unauthorized,
    /// The job, scene, worker or route does not exist. 404.
    NotFound,
    /// The request conflicts with the resource's state (e.g. an idempotency key reused
    /// with different settings). 409.
    Conflict,
    /// The request body is larger than the server accepts. 413.
    TooLarge,
    /// The request body did not arrive within the server's body timeout; the connection
    /// is closed. 408.
    RequestTimeout,
    /// The server failed; the request may be retried. 500.
    Internal,
    /// The server cannot take this request now (its store takes no writes: a full disk,
    /// an I/O error, a read-only file); reads still work. 503.
    Unavailable,
    /// The server has no room to store this: the stored scenes would exceed a quota (the
    /// message names the limit and the numbers), or the server's disk is full (reads still
    /// work; writes resume once space is freed). 507.
    InsufficientStorage,
    /// A code this version does not know (sent by a newer server). Deserialization only;
    /// treated as 500.
    #[serde(other)]
    Unknown,
}

impl ErrorCode {
    /// The HTTP status code for this kind of error.
    pub fn status(self) -> u16 {
        match self {
            Self::InvalidField | Self::InvalidRequest | Self::InvalidScene => 400,
            Self::Unauthorized => 401,
            Self::NotFound => 404,
            Self::Conflict => 409,
            Self::TooLarge => 413,
            Self::RequestTimeout => 408,
            Self::Internal | Self::Unknown => 500,
            Self::Unavailable => 503,
            Self::InsufficientStorage => 507,
        }
    }

    /// The code as it appears in JSON, e.g. `"invalid_field"`.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::InvalidField => "invalid_field",
            Self::InvalidRequest => "invalid_request",
            Self::InvalidScene => "invalid_scene",
            Self::Unauthorized => "unauthorized",
            Self::NotFound => "not_found",
            Self::Conflict => "conflict",
            Self::TooLarge => "too_large",
            Self::RequestTimeout => "request_timeout",
            Self::Internal => "internal",
            Self::Unavailable => "unavailable",
            Self::InsufficientStorage => "insufficient_storage",
            Self::Unknown => "unknown",
        }
    }
}

impl fmt::Display for ErrorCode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// An API error: what every non-2xx response carries.
///
/// Serializes as ARCHITECTURE.md §5 requires, wrapped in an `"error"` object, with `field` present
/// only when one field is to blame:
///
/// ```
/// use tessera_api::ApiError;
///
/// let e = ApiError::invalid_field("spp", "must be between 1 and 1048576, got 0");
/// assert_eq!(e.status(), 400);
/// assert_eq!(
///     serde_json::to_string(&e).unwrap(),
///     r#"{"error":{"code":"invalid_field","message":"spp: must be between 1 and 1048576, got 0","field":"spp"}}"#
/// );
/// ```
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(into = "ErrorEnvelope", from = "ErrorEnvelope")]
pub struct ApiError {
    /// What kind of error.
    pub code: ErrorCode,
    /// A human-readable explanation. For [`ErrorCode::InvalidField`] it starts with the
    /// field name, e.g. `"spp: must be between 1 and 1048576, got 0"`.
    pub message: String,
    /// The offending field of the request (a dotted path such as `"frames.end"`), when
    /// one field is to blame.
    pub field: Option<String>,
}

/// The wire form of [`ApiError`]: `{"error": {...}}`.
#[derive(Serialize, Deserialize)]
struct ErrorEnvelope {
    error: ErrorBody,
}

#[derive(Serialize, Deserialize)]
struct ErrorBody {
    code: ErrorCode,
    message: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    field: Option<String>,
}

impl From<ApiError> for ErrorEnvelope {
    fn from(e: ApiError) -> Self {
        Self {
            error: ErrorBody {
                code: e.code,
                message: e.message,
                field: e.field,
            },
        }
    }
}

impl From<ErrorEnvelope> for ApiError {
    fn from(e: ErrorEnvelope) -> Self {
        Self {
            code: e.error.code,
            message: e.error.message,
            field: e.error.field,
        }
    }
}

impl ApiError {
    /// An error of the given kind without a field.
    pub fn new(code: ErrorCode, message: impl Into<String>) -> Self {
        Self {
            code,
            message: message.into(),
            field: None,
        }
    }

    /// [`ErrorCode::InvalidField`]: the message becomes `"{field}: {problem}"`.
    pub fn invalid_field(field: impl Into<String>, problem: impl fmt::Display) -> Self {
        let field = field.into();
        Self {
            code: ErrorCode::InvalidField,
            message: format!("{field}: {problem}"),
            field: Some(field),
        }
    }

    /// [`ErrorCode::InvalidRequest`].
    pub fn invalid_request(message: impl Into<String>) -> Self {
        Self::new(ErrorCode::InvalidRequest, message)
    }

    /// [`ErrorCode::InvalidScene`].
    pub fn invalid_scene(message: impl Into<String>) -> Self {
        Self::new(ErrorCode::InvalidScene, message)
    }

    /// [`ErrorCode::Unauthorized`] with a standard message.
    pub fn unauthorized() -> Self {
        Self::new(
            ErrorCode::Unauthorized,
            "a valid bearer token is required (Authorization: Bearer TOKEN)",
        )
    }

    /// [`ErrorCode::NotFound`]: `what` is e.g. `"job 42"`.
    pub fn not_found(what: impl fmt::Display) -> Self {
        Self::new(ErrorCode::NotFound, format!("{what} not found"))
    }

    /// [`ErrorCode::Conflict`].
    pub fn conflict(message: impl Into<String>) -> Self {
        Self::new(ErrorCode::Conflict, message)
    }

    /// [`ErrorCode::TooLarge`]: the body exceeded `limit` bytes.
    pub fn too_large(limit: u64) -> Self {
        Self::new(
            ErrorCode::TooLarge,
            format!("request body is larger than the limit of {limit} bytes"),
        )
    }

    /// [`ErrorCode::Internal`].
    pub fn internal(message: impl Into<String>) -> Self {
        Self::new(ErrorCode::Internal, message)
    }

    /// The HTTP status code to answer with (400, 401, 404, 409, 413 or 500).
    pub fn status(&self) -> u16 {
        self.code.status()
    }
}

impl fmt::Display for ApiError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} ({})", self.message, self.code)
    }
}

impl std::error::Error for ApiError {}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn json_shape_is_the_design_contract() {
        let e = ApiError::not_found("job 7");
        assert_eq!(
            serde_json::to_value(&e).unwrap(),
            json!({"error": {"code": "not_found", "message": "job 7 not found"}})
        );
        let e = ApiError::invalid_field("frames.end", "must be >= frames.start (3), got 1");
        assert_eq!(
            serde_json::to_value(&e).unwrap(),
            json!({"error": {
                "code": "invalid_field",
                "message": "frames.end: must be >= frames.start (3), got 1",
                "field": "frames.end"
            }})
        );
    }

    #[test]
    fn round_trip_and_unknown_codes() {
        for e in [
            ApiError::invalid_field("spp", "bad"),
            ApiError::invalid_request("not JSON"),
            ApiError::unauthorized(),
            ApiError::too_large(10),
            ApiError::internal("disk full"),
        ] {
            let s = serde_json::to_string(&e).unwrap();
            assert_eq!(serde_json::from_str::<ApiError>(&s).unwrap(), e);
        }
        let e: ApiError =
            serde_json::from_str(r#"{"error":{"code":"teapot","message":"short and stout"}}"#)
                .unwrap();
        assert_eq!(e.code, ErrorCode::Unknown);
        assert_eq!(e.status(), 500);
        assert_eq!(e.field, None);
    }

    #[test]
    fn statuses() {
        let cases = [
            (ErrorCode::InvalidField, 400),
            (ErrorCode::InvalidRequest, 400),
            (ErrorCode::InvalidScene, 400),
            (ErrorCode::Unauthorized, 401),
            (ErrorCode::NotFound, 404),
            (ErrorCode::Conflict, 409),
            (ErrorCode::TooLarge, 413),
            (ErrorCode::Internal, 500),
            (ErrorCode::Unavailable, 503),
            (ErrorCode::InsufficientStorage, 507),
        ];
        for (code, status) in cases {
            assert_eq!(ApiError::new(code, "x").status(), status, "{code}");
            // as_str agrees with serde.
            assert_eq!(
                serde_json::to_value(code).unwrap(),
                serde_json::Value::String(code.as_str().into())
            );
        }
    }
}
