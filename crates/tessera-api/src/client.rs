//! A typed blocking client of the HTTP API v1 (feature `client`), used by `tessera submit`,
//! `tessera status` and the end-to-end tests.

use std::time::Duration;

use crate::{
    ApiError, ErrorCode, History, JobList, JobSettings, JobStatus, SceneUploaded, TileMap,
    WorkerList, API_PREFIX, IDEMPOTENCY_KEY_HEADER,
};

/// Largest response body read (images of large frames are big).
const MAX_BODY: u64 = 4 << 30;

/// Why a call failed.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    /// The server answered with an API error.
    #[error("{status}: {error}")]
    Api {
        /// HTTP status.
        status: u16,
        /// The error it sent.
        error: ApiError,
    },
    /// The server could not be reached, or answered something that is not the API.
    #[error("{0}")]
    Transport(String),
}

/// The agent every client uses: API errors are answers, not transport errors.
fn agent(tls: ureq::tls::TlsConfig) -> ureq::Agent {
    ureq::Agent::config_builder()
        .http_status_as_error(false)
        .timeout_global(Some(Duration::from_secs(300)))
        .tls_config(tls)
        .build()
        .into()
}

/// A client of one coordinator.
#[derive(Clone)]
pub struct Client {
    base: String,
    token: Option<String>,
    agent: ureq::Agent,
}

impl Client {
    /// A client of the coordinator at `base` (e.g. `http://127.0.0.1:8080`), sending
    /// `token` as a bearer token if given.
    pub fn new(base: &str, token: Option<String>) -> Self {
        Self {
            base: base.trim_end_matches('/').to_string(),
            token,
            agent: agent(ureq::tls::TlsConfig::default()),
        }
    }

    /// The same client, trusting only the CA certificates in `ca_pem` (PEM) for an
    /// `https://` server (`--tls-ca`); without it, `https://` trusts the public web roots.
    pub fn with_tls_ca(mut self, ca_pem: &[u8]) -> Result<Self, ClientError> {
        let mut roots = Vec::new();
        for item in ureq::tls::parse_pem(ca_pem) {
            match item {
                Ok(ureq::tls::PemItem::Certificate(c)) => roots.push(c),
                Ok(_) => {}
                Err(e) => return Err(ClientError::Transport(format!("the CA file: {e}"))),
            }
        }
        if roots.is_empty() {
            return Err(ClientError::Transport(
                "the CA file holds no PEM certificate".into(),
            ));
        }
        let tls = ureq::tls::TlsConfig::builder()
            .root_certs(ureq::tls::RootCerts::from(roots))
            .build();
        self.agent = agent(tls);
        Ok(self)
    }

    fn url(&self, path: &str) -> String {
        format!("{}{API_PREFIX}{path}", self.base)
    }

    fn finish(
        &self,
        resp: Result<ureq::http::Response<ureq::Body>, ureq::Error>,
    ) -> Result<Vec<u8>, ClientError> {
        let mut resp = resp.map_err(|e| ClientError::Transport(format!("{}: {e}", self.base)))?;
        let status = resp.status().as_u16();
        let body = resp
            .body_mut()
            .with_config()
            .limit(MAX_BODY)
            .read_to_vec()
            .map_err(|e| ClientError::Transport(format!("reading the response: {e}")))?;
        if (200..300).contains(&status) {
            return Ok(body);
        }
        let error = serde_json::from_slice::<ApiError>(&body).unwrap_or_else(|_| {
            ApiError::new(
                ErrorCode::Unknown,
                format!("HTTP {status}: {}", String::from_utf8_lossy(&body)),
            )
        });
        Err(ClientError::Api { status, error })
    }

    fn get_bytes(&self, path: &str) -> Result<Vec<u8>, ClientError> {
        let mut req = self.agent.get(self.url(path));
        if let Some(t) = &self.token {
            req = req.header("authorization", format!("Bearer {t}"));
        }
        self.finish(req.call())
    }

    fn json<T: serde::de::DeserializeOwned>(bytes: &[u8]) -> Result<T, ClientError> {
        serde_json::from_slice(bytes)
            .map_err(|e| ClientError::Transport(format!("unexpected response: {e}")))
    }

    fn post(
        &self,
        path: &str,
        content_type: &str,
        body: &[u8],
        key: Option<&str>,
    ) -> Result<Vec<u8>, ClientError> {
        let mut req = self
            .agent
            .post(self.url(path))
            .header("content-type", content_type);
        if let Some(t) = &self.token {
            req = req.header("authorization", format!("Bearer {t}"));
        }
        if let Some(k) = key {
            req = req.header(IDEMPOTENCY_KEY_HEADER, k);
        }
        self.finish(req.send(body))
    }

    /// `POST /jobs`.
    pub fn submit(
        &self,
        settings: &JobSettings,
        idempotency_key: Option<&str>,
    ) -> Result<JobStatus, ClientError> {
        let body = serde_json::to_vec(settings)
            .map_err(|e| ClientError::Transport(format!("encoding the job: {e}")))?;
        Self::json(&self.post("/jobs", "application/json", &body, idempotency_key)?)
    }

    /// `POST /jobs?dry_run=true`: the job's quote (the JSON object of `tessera estimate
    /// --json`, with `dry_run` and `fleet`), for `workers` workers or the connected ones.
    /// Nothing is queued.
    pub fn quote(
        &self,
        settings: &JobSettings,
        workers: Option<u32>,
    ) -> Result<serde_json::Value, ClientError> {
        let body = serde_json::to_vec(settings)
            .map_err(|e| ClientError::Transport(format!("encoding the job: {e}")))?;
        let path = match workers {
            Some(n) => format!("/jobs?dry_run=true&workers={n}"),
            None => "/jobs?dry_run=true".to_string(),
        };
        Self::json(&self.post(&path, "application/json", &body, None)?)
    }

    /// `POST /jobs` with a raw body (for tests of malformed input).
    pub fn submit_raw(&self, body: &[u8]) -> Result<JobStatus, ClientError> {
        Self::json(&self.post("/jobs", "application/json", body, None)?)
    }

    /// `POST /scenes`.
    pub fn upload_scene(&self, bytes: &[u8]) -> Result<SceneUploaded, ClientError> {
        Self::json(&self.post("/scenes", "application/octet-stream", bytes, None)?)
    }

    /// `GET /jobs/{id}`.
    pub fn job(&self, id: u64) -> Result<JobStatus, ClientError> {
        Self::json(&self.get_bytes(&format!("/jobs/{id}"))?)
    }

    /// `GET /jobs?limit=&cursor=`.
    pub fn jobs(&self, limit: u32, cursor: Option<&str>) -> Result<JobList, ClientError> {
        let mut path = format!("/jobs?limit={limit}");
        if let Some(c) = cursor {
            path.push_str(&format!("&cursor={c}"));
        }
        Self::json(&self.get_bytes(&path)?)
    }

    /// `GET /jobs/{id}/history`.
    pub fn history(&self, id: u64) -> Result<History, ClientError> {
        Self::json(&self.get_bytes(&format!("/jobs/{id}/history"))?)
    }

    /// `GET /jobs/{id}/tiles`.
    pub fn tiles(&self, id: u64) -> Result<TileMap, ClientError> {
        Self::json(&self.get_bytes(&format!("/jobs/{id}/tiles"))?)
    }

    /// `GET /jobs/{id}/image?format=...`: `"png"` or `"exr"`.
    pub fn image(&self, id: u64, format: &str) -> Result<Vec<u8>, ClientError> {
        self.get_bytes(&format!("/jobs/{id}/image?format={format}"))
    }

    /// `GET /jobs/{id}/image?format=FORMAT&frame=FRAME`: one frame of a job of several.
    pub fn frame_image(&self, id: u64, format: &str, frame: u32) -> Result<Vec<u8>, ClientError> {
        self.get_bytes(&format!("/jobs/{id}/image?format={format}&frame={frame}"))
    }

    /// `DELETE /jobs/{id}`.
    pub fn cancel(&self, id: u64) -> Result<JobStatus, ClientError> {
        let mut req = self.agent.delete(self.url(&format!("/jobs/{id}")));
        if let Some(t) = &self.token {
            req = req.header("authorization", format!("Bearer {t}"));
        }
        Self::json(&self.finish(req.call())?)
    }

    /// `GET PATH` outside the API prefix, e.g. `/metrics` or `/healthz`.
    pub fn get_raw(&self, path: &str) -> Result<Vec<u8>, ClientError> {
        let mut req = self.agent.get(format!("{}{path}", self.base));
        if let Some(t) = &self.token {
            req = req.header("authorization", format!("Bearer {t}"));
        }
        self.finish(req.call())
    }

    /// `GET /workers`.
    pub fn workers(&self) -> Result<WorkerList, ClientError> {
        Self::json(&self.get_bytes("/workers")?)
    }

    /// Polls `GET /jobs/{id}` every `every` until the job is in a terminal state or
    /// `timeout` passes (then the last status is returned as an error message).
    pub fn wait(
        &self,
        id: u64,
        every: Duration,
        timeout: Duration,
        mut on_status: impl FnMut(&JobStatus),
    ) -> Result<JobStatus, ClientError> {
        let start = std::time::Instant::now();
        loop {
            let s = self.job(id)?;
            on_status(&s);
            if s.state.is_terminal() {
                return Ok(s);
            }
            if start.elapsed() > timeout {
                return Err(ClientError::Transport(format!(
                    "job {id} is still {} after {:.0} s",
                    s.state.as_str(),
                    timeout.as_secs_f64()
                )));
            }
            std::thread::sleep(every);
        }
    }
}
