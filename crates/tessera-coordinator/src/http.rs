//! The HTTP API v1 (ARCHITECTURE.md §5) and the dashboard, on axum.
//!
//! Every `/api/v1` route answers JSON; every failure is an [`ApiError`] serialized as
//! `{"error": {"code", "message", "field"?}}` with its 4xx/5xx status, including malformed
//! query strings, bodies and unknown routes (no framework-default plain-text errors).
//! With an API token configured, `/api/v1` and `/metrics` (it names workers and jobs)
//! require `Authorization: Bearer TOKEN`, the scheme in any letter case ([`crate::auth`];
//! 401 otherwise); `/healthz` and the dashboard files are open, the dashboard asking its
//! user for the token.
//!
//! Job ids in paths are canonical decimal (`/jobs/7`; `/jobs/07`, `/jobs/+7` name no job,
//! 404), so one job has one URL. A request body that does not arrive within the body
//! timeout ([`crate::connections`]) is answered `408` and its connection closed.

use std::sync::Arc;

use axum::body::Bytes;
use axum::extract::rejection::BytesRejection;
use axum::extract::{DefaultBodyLimit, Path, RawQuery, Request, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::{delete, get, post};
use axum::{Extension, Json, Router};
use serde::de::DeserializeOwned;
use tessera_api::{
    ApiError, ErrorCode, FrameQuery, FromJson, ImageFormat, ImageQuery, JobListQuery, JobSettings,
    SubmitQuery, API_PREFIX, IDEMPOTENCY_KEY_HEADER,
};
use tracing::Instrument;

use crate::connections::ConnectionStats;
use crate::error::CoordError;
use crate::service::images::ImageBody;
use crate::service::Coordinator;

/// An [`ApiError`] as an HTTP response.
pub struct HttpError(pub ApiError);

impl From<ApiError> for HttpError {
    fn from(e: ApiError) -> Self {
        Self(e)
    }
}

impl From<CoordError> for HttpError {
    /// Through the one mapping of coordinator errors to HTTP ([`crate::error`]).
    fn from(e: CoordError) -> Self {
        Self(e.into())
    }
}

impl IntoResponse for HttpError {
    fn into_response(self) -> Response {
        let status =
            StatusCode::from_u16(self.0.status()).unwrap_or(StatusCode::INTERNAL_SERVER_ERROR);
        let mut resp = (status, Json(&self.0)).into_response();
        if status == StatusCode::REQUEST_TIMEOUT {
            // The rest of a trickled body is not worth reading.
            resp.headers_mut()
                .insert(header::CONNECTION, HeaderValue::from_static("close"));
        }
        if status == StatusCode::UNAUTHORIZED {
            resp.headers_mut().insert(
                header::WWW_AUTHENTICATE,
                HeaderValue::from_static("Bearer realm=\"tessera\""),
            );
        }
        // The request span logs server faults with their message (`trace_request`).
        if status.is_server_error() {
            resp.extensions_mut().insert(ServerFault(self.0.message));
        }
        resp
    }
}

/// The message of a 5xx answer, handed from the handler to [`trace_request`] in the
/// response's extensions so that the error is logged once, by the middleware.
#[derive(Clone)]
struct ServerFault(String);

/// The request span: method, path (never the query or headers: no tokens in logs) and
/// status, with a log line per request — `error` for 5xx answers (with the message),
/// `info` for refused requests, `debug` otherwise.
async fn trace_request(req: Request, next: Next) -> Response {
    let span = tracing::info_span!(
        "http",
        method = %req.method(),
        path = %req.uri().path(),
        status = tracing::field::Empty,
    );
    let started = std::time::Instant::now();
    let resp = next.run(req).instrument(span.clone()).await;
    let status = resp.status().as_u16();
    let ms = started.elapsed().as_millis() as u64;
    span.record("status", status);
    let _g = span.enter();
    if let Some(ServerFault(message)) = resp.extensions().get::<ServerFault>() {
        tracing::error!(status, ms, error = %message, "request failed");
    } else if resp.status().is_client_error() {
        tracing::info!(status, ms, "request refused");
    } else {
        tracing::debug!(status, ms, "request served");
    }
    resp
}

type HttpResult<T> = Result<T, HttpError>;

/// The content security policy of the dashboard: everything from this origin only.
pub const DASHBOARD_CSP: &str = "default-src 'self'; img-src 'self' blob: data:; style-src 'self'; script-src 'self'; connect-src 'self'";

/// The OpenAPI 3 description of the API, served at `/api/v1/openapi.json`.
pub const OPENAPI_JSON: &str = include_str!("openapi.json");

/// The router of the whole HTTP port.
pub fn router(core: Coordinator) -> Router {
    let api = Router::new()
        .route("/jobs", post(submit_job).get(list_jobs))
        .route("/jobs/{id}", get(get_job).delete(cancel_job))
        .route("/jobs/{id}/image", get(job_image))
        .route("/jobs/{id}/history", get(job_history))
        .route("/jobs/{id}/tiles", get(job_tiles))
        .route(
            "/scenes",
            post(upload_scene).layer(DefaultBodyLimit::max(core.config().max_scene_bytes)),
        )
        .route("/scenes/{hash}", delete(delete_scene))
        .route("/builtins", get(builtins))
        .route("/workers", get(workers))
        .route("/workers/{name}/quarantine", delete(lift_quarantine))
        .route("/openapi.json", get(openapi))
        .fallback(api_not_found)
        .layer(DefaultBodyLimit::max(1 << 20))
        .layer(middleware::from_fn_with_state(core.clone(), require_token));
    Router::new()
        .nest(API_PREFIX, api)
        .route("/healthz", get(healthz))
        .route("/readyz", get(readyz))
        .route(
            "/metrics",
            get(metrics).layer(middleware::from_fn_with_state(core.clone(), require_token)),
        )
        .route("/", get(dashboard_asset))
        .route("/index.html", get(dashboard_asset))
        .route("/assets/{*path}", get(dashboard_asset))
        .fallback(not_found)
        .layer(middleware::from_fn(trace_request))
        .with_state(core)
}

/// The router of a standby coordinator's HTTP port (`crate::ha`): `/healthz` 200 (the
/// process is alive and doing its job, waiting), `/readyz` 503 (route to the active
/// one), everything else 503 `unavailable`; each answer says `message`.
pub fn standby_router(message: &'static str) -> Router {
    Router::new()
        .route(
            "/healthz",
            get(move || async move { (StatusCode::OK, format!("{message}\n")) }),
        )
        .route(
            "/readyz",
            get(move || async move { (StatusCode::SERVICE_UNAVAILABLE, format!("{message}\n")) }),
        )
        // Not traced as the active router is: every answer is a 503 by design, and
        // logging each as a failed request would bury the log in probes.
        .fallback(move || async move { HttpError(ApiError::new(ErrorCode::Unavailable, message)) })
}

/// The API client a request was admitted as ([`crate::auth::client_name`]): whose quota
/// its scene uploads count in.
#[derive(Clone)]
struct ApiClient(String);

async fn require_token(State(core): State<Coordinator>, mut req: Request, next: Next) -> Response {
    let token = core.config().api_token.as_deref();
    req.extensions_mut()
        .insert(ApiClient(crate::auth::client_name(token)));
    if let Some(token) = token {
        let given = req
            .headers()
            .get(header::AUTHORIZATION)
            .and_then(|v| v.to_str().ok());
        if !crate::auth::bearer_matches(given, token) {
            return HttpError(ApiError::new(
                ErrorCode::Unauthorized,
                "this API requires a bearer token: send Authorization: Bearer TOKEN",
            ))
            .into_response();
        }
    }
    next.run(req).await
}

/// Parses a query string; a bad value is a 400 naming its parameter (`field`).
fn parse_query<T: DeserializeOwned + Default>(q: Option<String>) -> Result<T, ApiError> {
    let q = match q.as_deref() {
        None | Some("") => return Ok(T::default()),
        Some(q) => q,
    };
    serde_urlencoded::from_str(q).map_err(|e| {
        // Find the parameter to blame: the first that does not parse on its own (every
        // parameter of the API's queries is optional, so one alone must parse).
        let pairs: Vec<(String, String)> = serde_urlencoded::from_str(q).unwrap_or_default();
        let culprit = pairs.iter().find(|pair| {
            serde_urlencoded::to_string([pair])
                .map(|one| serde_urlencoded::from_str::<T>(&one).is_err())
                .unwrap_or(false)
        });
        match culprit {
            Some((key, _)) => {
                let key: String = key.chars().take(64).collect();
                ApiError::invalid_field(key, format!("invalid query parameter: {e}"))
            }
            None => ApiError::new(
                ErrorCode::InvalidRequest,
                format!("invalid query string: {e}"),
            ),
        }
    })
}

/// A job id from a path: canonical decimal only (no sign, no leading zero), so that
/// `/jobs/01` and `/jobs/+1` do not alias `/jobs/1`.
fn parse_id(id: &str) -> Result<u64, ApiError> {
    let canonical = !id.is_empty()
        && id.bytes().all(|b| b.is_ascii_digit())
        && (id == "0" || !id.starts_with('0'));
    match id.parse::<u64>() {
        Ok(n) if canonical => Ok(n),
        _ => Err(ApiError::new(
            ErrorCode::NotFound,
            format!("job {id:?} does not exist: job ids are positive integers in decimal"),
        )),
    }
}

async fn submit_job(
    State(core): State<Coordinator>,
    headers: HeaderMap,
    RawQuery(q): RawQuery,
    body: Result<Bytes, BytesRejection>,
) -> HttpResult<Response> {
    let body = body.map_err(body_error)?;
    let q: SubmitQuery = parse_query(q)?;
    if q.workers.is_some() && !q.dry_run {
        return Err(
            ApiError::invalid_field("workers", "only a dry run (dry_run=true) takes it").into(),
        );
    }
    if let Some(ct) = headers.get(header::CONTENT_TYPE) {
        let ct = ct.to_str().unwrap_or("");
        if !ct.starts_with("application/json") {
            return Err(ApiError::new(
                ErrorCode::InvalidRequest,
                format!("the job must be sent as application/json, not {ct:?}"),
            )
            .into());
        }
    }
    let key = match headers.get(IDEMPOTENCY_KEY_HEADER) {
        Some(v) => Some(
            v.to_str()
                .map_err(|_| ApiError::invalid_field("idempotency-key", "must be ASCII"))?
                .to_string(),
        ),
        None => None,
    };
    let settings = JobSettings::from_json(&body)?;
    if q.dry_run {
        // A quote creates nothing, so the idempotency key has nothing to guard.
        return Ok(Json(core.quote(settings, q.workers).await?).into_response());
    }
    let (status, created) = core.submit(settings, key).await?;
    let code = if created {
        StatusCode::CREATED
    } else {
        StatusCode::OK
    };
    let mut resp = (code, Json(status.clone())).into_response();
    if let Ok(v) = HeaderValue::from_str(&format!("{API_PREFIX}/jobs/{}", status.id)) {
        resp.headers_mut().insert(header::LOCATION, v);
    }
    Ok(resp)
}

async fn list_jobs(State(core): State<Coordinator>, RawQuery(q): RawQuery) -> HttpResult<Response> {
    let q: JobListQuery = parse_query(q)?;
    Ok(Json(core.list(q).await?).into_response())
}

async fn get_job(State(core): State<Coordinator>, Path(id): Path<String>) -> HttpResult<Response> {
    Ok(Json(core.status(parse_id(&id)?).await?).into_response())
}

async fn cancel_job(
    State(core): State<Coordinator>,
    Path(id): Path<String>,
) -> HttpResult<Response> {
    Ok(Json(core.cancel(parse_id(&id)?).await?).into_response())
}

async fn job_history(
    State(core): State<Coordinator>,
    Path(id): Path<String>,
) -> HttpResult<Response> {
    Ok(Json(core.history(parse_id(&id)?).await?).into_response())
}

async fn job_tiles(
    State(core): State<Coordinator>,
    Path(id): Path<String>,
    RawQuery(q): RawQuery,
) -> HttpResult<Response> {
    let q: FrameQuery = parse_query(q)?;
    Ok(Json(core.tiles(parse_id(&id)?, q).await?).into_response())
}

/// An encoded image shared with the coordinator's image cache, as a response body
/// without a copy.
struct SharedBytes(std::sync::Arc<Vec<u8>>);

impl AsRef<[u8]> for SharedBytes {
    fn as_ref(&self) -> &[u8] {
        &self.0
    }
}

async fn job_image(
    State(core): State<Coordinator>,
    Path(id): Path<String>,
    RawQuery(q): RawQuery,
) -> HttpResult<Response> {
    let q: ImageQuery = parse_query(q)?;
    let id = parse_id(&id)?;
    let body = match core.image(id, q).await {
        Ok(body) => body,
        // Refused for lack of memory (the budget is held by merge state and other
        // encodes): say when to come back.
        Err(e @ CoordError::Unavailable(_)) => {
            let mut resp = HttpError::from(e).into_response();
            resp.headers_mut().insert(
                header::RETRY_AFTER,
                HeaderValue::from(crate::service::images::RETRY_AFTER_SECONDS),
            );
            return Ok(resp);
        }
        Err(e) => return Err(e.into()),
    };
    let headers = [
        (header::CONTENT_TYPE, q.format.content_type()),
        (header::CACHE_CONTROL, "no-store"),
    ];
    let mut resp = match body {
        ImageBody::Whole(bytes) => {
            (headers, axum::body::Bytes::from_owner(SharedBytes(bytes))).into_response()
        }
        ImageBody::Stream { len, chunks } => {
            let body =
                axum::body::Body::from_stream(tokio_stream::wrappers::ReceiverStream::new(chunks));
            let mut resp = (headers, body).into_response();
            resp.headers_mut()
                .insert(header::CONTENT_LENGTH, HeaderValue::from(len));
            resp
        }
    };
    if q.format == ImageFormat::Exr {
        if let Ok(v) = HeaderValue::from_str(&format!("attachment; filename=\"job-{id}.exr\"")) {
            resp.headers_mut().insert(header::CONTENT_DISPOSITION, v);
        }
    }
    Ok(resp)
}

fn body_error(e: BytesRejection) -> ApiError {
    if crate::connections::is_body_timeout(&e) {
        ApiError::new(
            ErrorCode::RequestTimeout,
            "the request body did not arrive in time (the body timeout); the connection is closed",
        )
    } else if e.status() == StatusCode::PAYLOAD_TOO_LARGE {
        ApiError::new(
            ErrorCode::TooLarge,
            format!("the request body is too large: {}", e.body_text()),
        )
    } else {
        ApiError::new(
            ErrorCode::InvalidRequest,
            format!("cannot read the request body: {}", e.body_text()),
        )
    }
}

async fn upload_scene(
    State(core): State<Coordinator>,
    client: Option<Extension<ApiClient>>,
    body: Result<Bytes, BytesRejection>,
) -> HttpResult<Response> {
    let body = body.map_err(|e| {
        if e.status() == StatusCode::PAYLOAD_TOO_LARGE {
            ApiError::new(
                ErrorCode::TooLarge,
                format!(
                    "the scene is larger than the limit of {} bytes per upload (--max-scene-size)",
                    core.config().max_scene_bytes
                ),
            )
        } else {
            body_error(e)
        }
    })?;
    let client = client.map_or_else(|| crate::auth::client_name(None), |c| c.0 .0);
    let out = core.upload_scene_as(body.to_vec(), &client).await?;
    Ok((StatusCode::CREATED, Json(out)).into_response())
}

/// `DELETE /scenes/{hash}`: 204 when the scene was deleted, 404 when no scene has this
/// hash, 409 naming the queued or running jobs that need it.
async fn delete_scene(
    State(core): State<Coordinator>,
    Path(hash): Path<String>,
) -> HttpResult<Response> {
    core.delete_scene(&hash).await?;
    Ok(StatusCode::NO_CONTENT.into_response())
}

async fn builtins() -> Response {
    let list: Vec<serde_json::Value> = tessera_scene::builtin::NAMES
        .iter()
        .map(|n| {
            serde_json::json!({
                "name": n,
                "scene": format!("builtin:{n}"),
                "description": builtin_description(n),
            })
        })
        .collect();
    Json(serde_json::json!({ "builtins": list })).into_response()
}

fn builtin_description(name: &str) -> &'static str {
    match name {
        "cornell-box" => "the classic Cornell box",
        "veach-mis" => "Veach & Guibas 1995: four glossy plates, four spherical lights",
        "furnace" => "a closed emitting box: every pixel is exactly 2.5",
        "caustic" => "a glass sphere on a diffuse floor under a small light",
        _ => "",
    }
}

async fn workers(State(core): State<Coordinator>) -> HttpResult<Response> {
    Ok(Json(core.workers()?).into_response())
}

/// `DELETE /workers/{name}/quarantine`: 204 when a quarantine of that name was lifted,
/// 404 naming the worker when there was none.
async fn lift_quarantine(
    State(core): State<Coordinator>,
    Path(name): Path<String>,
) -> HttpResult<Response> {
    core.lift_quarantine(&name).await?;
    Ok(StatusCode::NO_CONTENT.into_response())
}

async fn openapi() -> Response {
    ([(header::CONTENT_TYPE, "application/json")], OPENAPI_JSON).into_response()
}

async fn api_not_found(req: Request) -> HttpError {
    HttpError(ApiError::new(
        ErrorCode::NotFound,
        format!("no API route {} {}", req.method(), req.uri().path()),
    ))
}

async fn not_found(req: Request) -> HttpError {
    HttpError(ApiError::new(
        ErrorCode::NotFound,
        format!("nothing at {}", req.uri().path()),
    ))
}

/// Liveness and the container health check: 200 while the store answers and takes
/// writes; 503 otherwise, and once this coordinator lost the leadership (`crate::ha`).
async fn healthz(State(core): State<Coordinator>) -> Response {
    if let Err(e) = core.active() {
        return (StatusCode::SERVICE_UNAVAILABLE, format!("{e}\n")).into_response();
    }
    match core.store().ping().await {
        Ok(()) => (StatusCode::OK, "ok\n").into_response(),
        Err(e) => (
            StatusCode::SERVICE_UNAVAILABLE,
            format!("store unavailable: {e}\n"),
        )
            .into_response(),
    }
}

/// Readiness, for a load balancer or a Kubernetes readiness probe: 200 `active` on the
/// coordinator that serves the farm, 503 otherwise. A standby answers 503 `standby: ...`
/// from its own router (`crate::ha`), where `/healthz` is 200.
async fn readyz(State(core): State<Coordinator>) -> Response {
    match healthz(State(core)).await {
        r if r.status() == StatusCode::OK => (StatusCode::OK, "active\n").into_response(),
        r => r,
    }
}

async fn metrics(
    State(core): State<Coordinator>,
    connections: Option<Extension<Arc<ConnectionStats>>>,
) -> HttpResult<Response> {
    let mut text = core.metrics().await?;
    // The connection counters exist when the router runs under `serve`'s accept loop.
    if let Some(Extension(c)) = connections {
        text.push_str(&c.prometheus());
    }
    Ok(([(header::CONTENT_TYPE, "text/plain; version=0.0.4")], text).into_response())
}

async fn dashboard_asset(req: Request) -> Response {
    match crate::dashboard::asset(req.uri().path()) {
        Some(a) => (
            [
                (header::CONTENT_TYPE, a.content_type),
                (header::CONTENT_SECURITY_POLICY, DASHBOARD_CSP),
                (header::CACHE_CONTROL, "no-cache"),
            ],
            a.bytes,
        )
            .into_response(),
        None => HttpError(ApiError::new(
            ErrorCode::NotFound,
            format!("no dashboard file {}", req.uri().path()),
        ))
        .into_response(),
    }
}
