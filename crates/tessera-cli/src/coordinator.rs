//! `tessera coordinator`: the HTTP API and dashboard, the workers' gRPC port and the store
//! (SQLite by default, or PostgreSQL with `--store`), served by [`tessera_coordinator::serve`] until Ctrl-C or SIGTERM.

use anyhow::{bail, Context, Result};
use clap::Args;
use std::io::Write;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;
use tessera_coordinator::service::{Coordinator, CoordinatorConfig};
use tessera_coordinator::store::{PostgresStore, StoreUrl};
use tessera_coordinator::{
    serve_coordinator, serve_ha, shutdown_signal, HttpLimits, Listeners, ServerTls, TlsFiles,
};

use crate::common::{init_tracing, runtime};

/// Options shared by `tessera coordinator` and `tessera serve`.
#[derive(Args, Clone, Debug)]
pub struct CoordinatorArgs {
    /// Address of the HTTP API and dashboard.
    #[arg(long, default_value = "127.0.0.1:8080")]
    pub http: SocketAddr,
    /// Address of the gRPC port for workers.
    #[arg(long, default_value = "127.0.0.1:50051")]
    pub grpc: SocketAddr,
    /// Directory of the SQLite store (created if missing), unless --store names another.
    #[arg(long, default_value = "tessera-data")]
    pub data: PathBuf,
    /// The store: `sqlite:DIR` or `postgres://USER@HOST:PORT/DB` (also `postgresql://`;
    /// docs/store.md). Default: the SQLite store in --data.
    #[arg(long, value_name = "URL", value_parser = parse_store_url)]
    pub store: Option<StoreUrl>,
    /// Bearer token required on the HTTP API.
    #[arg(long, env = "TESSERA_API_TOKEN")]
    pub api_token: Option<String>,
    /// Bearer token workers must present. A coordinator whose gRPC port listens beyond
    /// loopback without one (and without --tls-client-ca) generates one, keeps it in
    /// DATA/worker-token and requires it (docs/farm.md, "Worker credentials").
    #[arg(long, env = "TESSERA_WORKER_TOKEN")]
    pub worker_token: Option<String>,
    /// Lease duration without a heartbeat, milliseconds.
    #[arg(long, default_value_t = 10_000)]
    pub lease_ms: u64,
    /// Worker heartbeat interval, milliseconds.
    #[arg(long, default_value_t = 1_000)]
    pub heartbeat_ms: u32,
    /// After a restart, how long workers have to deliver what they were rendering before
    /// their units are leased again, milliseconds.
    #[arg(long, default_value_t = 3_000)]
    pub grace_ms: u64,
    /// HTTP: seconds a client has to send a request's head (from connecting, or from the
    /// request's first byte on a kept-alive connection).
    #[arg(long, default_value_t = 10, value_name = "SECS")]
    pub http_header_timeout: u64,
    /// HTTP: seconds a client has to send a request body, plus one second per
    /// --http-body-min-rate bytes received.
    #[arg(long, default_value_t = 30, value_name = "SECS")]
    pub http_body_timeout: u64,
    /// HTTP: bytes of request body that earn one more second of body timeout (0: none).
    #[arg(long, default_value_t = 65_536, value_name = "BYTES_PER_SEC")]
    pub http_body_min_rate: u64,
    /// HTTP: seconds a kept-alive connection may stay idle before it is closed.
    #[arg(long, default_value_t = 60, value_name = "SECS")]
    pub http_idle_timeout: u64,
    /// HTTP: most connections open at once; more are answered 503 and closed.
    #[arg(long, default_value_t = 1024, value_name = "N")]
    pub http_max_connections: usize,
    /// HTTP: most connections open at once from one IP address; more are answered 503
    /// and closed.
    #[arg(long, default_value_t = 64, value_name = "N")]
    pub http_max_connections_per_address: usize,
    /// Memory for the per-pixel merge state of all jobs (72 bytes per pixel of each frame
    /// in progress), e.g. `4GiB`, `512MiB` or a byte count. A job one frame of which
    /// needs more is refused; frames beyond it wait for others to complete.
    #[arg(long, default_value = "4GiB", value_parser = parse_bytes)]
    pub memory_budget: u64,
    /// The fraction (0 to 1) of units spot-checked: rendered a second time by a
    /// different worker and compared byte for byte; a worker whose copy differs from the
    /// one the others agree on is quarantined. Chosen by a hash of each unit, so a restart
    /// checks the same units. 0 disables (docs/ARCHITECTURE.md §6).
    #[arg(long, value_name = "FRACTION", default_value_t = tessera_farm::DEFAULT_SPOT_CHECK_FRACTION,
          value_parser = crate::worker::parse_fraction)]
    pub spot_check_fraction: f64,
    /// TLS on both ports: the server's certificate chain (PEM), reloaded on SIGHUP.
    #[arg(long, value_name = "FILE", requires = "tls_key")]
    pub tls_cert: Option<PathBuf>,
    /// The private key (PEM) of --tls-cert, reloaded on SIGHUP.
    #[arg(long, value_name = "FILE", requires = "tls_cert")]
    pub tls_key: Option<PathBuf>,
    /// Mutual TLS for workers: the gRPC port refuses workers without a certificate issued
    /// by this CA (PEM); the certificate's common name is the worker's identity.
    #[arg(long, value_name = "FILE", requires = "tls_cert")]
    pub tls_client_ca: Option<PathBuf>,
    /// Largest scene upload, e.g. `64MiB` (at most 256MiB); a larger one is refused
    /// with 413.
    #[arg(long, env = "TESSERA_MAX_SCENE_SIZE", default_value = "256MiB", value_parser = parse_bytes)]
    pub max_scene_size: u64,
    /// Bytes all stored scenes together may hold, e.g. `10GiB`; an upload beyond is
    /// refused with 507 naming the limit (docs/store.md, "Scene storage").
    #[arg(long, env = "TESSERA_SCENE_QUOTA", default_value = "10GiB", value_parser = parse_bytes)]
    pub scene_quota: u64,
    /// Bytes the scenes first uploaded with one API token may hold; an upload beyond is
    /// refused with 507 naming the limit.
    #[arg(long, env = "TESSERA_SCENE_QUOTA_PER_TOKEN", default_value = "10GiB", value_parser = parse_bytes)]
    pub scene_quota_per_token: u64,
    /// Delete stored scenes that no queued or running job needs once unused this long,
    /// e.g. `30d`, `12h`, `90m`; `off` keeps them until deleted with
    /// `DELETE /api/v1/scenes/{hash}`.
    // Spelled out so clap takes `None` ("off") as a parsed value, not a missing flag.
    #[arg(long, env = "TESSERA_SCENE_RETENTION", default_value = "off", value_parser = parse_retention)]
    pub scene_retention: ::std::option::Option<u64>,
    /// Dry runs (`POST /api/v1/jobs?dry_run=true`): seconds a quote's pilot may render on
    /// this host (one at a time, on one thread, in a child process) before it is killed.
    #[arg(long, default_value_t = 120, value_name = "SECS")]
    pub pilot_timeout: u64,
}

/// A byte count with an optional binary or decimal unit: `4GiB`, `512MiB`, `2GB`, `1024`.
fn parse_bytes(s: &str) -> std::result::Result<u64, String> {
    let t = s.trim();
    let split = t.find(|c: char| !c.is_ascii_digit()).unwrap_or(t.len());
    let (num, unit) = t.split_at(split);
    let n: u64 = num
        .parse()
        .map_err(|_| format!("{s:?} is not a byte count such as 4GiB or 1073741824"))?;
    let scale: u64 = match unit.trim().to_ascii_lowercase().as_str() {
        "" | "b" => 1,
        "k" | "kb" => 1_000,
        "kib" => 1 << 10,
        "m" | "mb" => 1_000_000,
        "mib" => 1 << 20,
        "g" | "gb" => 1_000_000_000,
        "gib" => 1 << 30,
        "t" | "tb" => 1_000_000_000_000,
        "tib" => 1 << 40,
        other => {
            return Err(format!(
                "unknown unit {other:?} in {s:?} (use B, KiB, MiB, GiB, TiB)"
            ))
        }
    };
    n.checked_mul(scale)
        .filter(|&b| b > 0)
        .ok_or_else(|| format!("{s:?} must be between 1 byte and 16 EiB"))
}

/// `--scene-retention`: `off`, or a duration with a unit (`s`, `m`, `h`, `d`), as
/// milliseconds.
fn parse_retention(s: &str) -> std::result::Result<Option<u64>, String> {
    let t = s.trim();
    if t.eq_ignore_ascii_case("off") {
        return Ok(None);
    }
    let split = t.find(|c: char| !c.is_ascii_digit()).unwrap_or(t.len());
    let (num, unit) = t.split_at(split);
    let bad = || format!("{s:?} is not a duration such as 30d, 12h, 90m or 3600s, or off");
    let n: u64 = num.parse().map_err(|_| bad())?;
    let ms: u64 = match unit.trim() {
        "s" => 1_000,
        "m" => 60_000,
        "h" => 3_600_000,
        "d" => 86_400_000,
        _ => return Err(bad()),
    };
    n.checked_mul(ms)
        .filter(|&v| v > 0 && v <= i64::MAX as u64)
        .map(Some)
        .ok_or_else(|| format!("{s:?} must be at least 1s and less than 290 million years"))
}

/// The file in the data directory that keeps a generated worker token.
pub const WORKER_TOKEN_FILE: &str = "worker-token";

impl CoordinatorArgs {
    /// Safe defaults for workers (docs/farm.md, "Worker credentials"): a gRPC port that
    /// listens beyond loopback with neither a worker token nor mutual TLS would take
    /// anonymous workers. Then the token kept in `DATA/worker-token` is used, or one is
    /// generated, kept there (mode 0600) and printed once, on standard error, with where
    /// workers take it. Loopback-only coordinators are left as they are.
    pub fn require_worker_credentials(&mut self) -> Result<()> {
        if self.worker_token.as_deref().is_some_and(|t| !t.is_empty())
            || self.tls_client_ca.is_some()
            || self.grpc.ip().is_loopback()
        {
            return Ok(());
        }
        let file = self.data.join(WORKER_TOKEN_FILE);
        match std::fs::read_to_string(&file) {
            Ok(t) if !t.trim().is_empty() => {
                self.worker_token = Some(t.trim().to_string());
                eprintln!(
                    "tessera: the gRPC port {} listens beyond loopback: workers must present \
                     the worker token kept in {} (TESSERA_WORKER_TOKEN)",
                    self.grpc,
                    file.display()
                );
                return Ok(());
            }
            Ok(_) => {}
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => {
                return Err(e)
                    .with_context(|| format!("reading the worker token {}", file.display()))
            }
        }
        let bytes: [u8; 32] = tessera_coordinator::trust::random_bytes();
        let token: String = bytes.iter().map(|b| format!("{b:02x}")).collect();
        std::fs::create_dir_all(&self.data)
            .with_context(|| format!("creating the data directory {}", self.data.display()))?;
        write_secret(&file, &token)
            .with_context(|| format!("keeping the worker token in {}", file.display()))?;
        eprintln!(
            "tessera: the gRPC port {grpc} listens beyond loopback and no worker token was \
             given (--worker-token / TESSERA_WORKER_TOKEN, or --tls-client-ca): generated one \
             and kept it in {file}; workers must present it:\n\n    \
             TESSERA_WORKER_TOKEN={token} tessera worker --coordinator http://HOST:{port}\n\n\
             It is printed this once; later starts read it from {file}.",
            grpc = self.grpc,
            file = file.display(),
            port = self.grpc.port(),
        );
        self.worker_token = Some(token);
        Ok(())
    }

    /// The validated coordinator configuration.
    fn config(&self) -> Result<CoordinatorConfig> {
        if self.lease_ms < 100 || u64::from(self.heartbeat_ms) * 2 > self.lease_ms {
            bail!(
                "--lease-ms {} must be at least 100 and at least twice --heartbeat-ms {}",
                self.lease_ms,
                self.heartbeat_ms
            );
        }
        for (flag, secs) in [
            ("--http-header-timeout", self.http_header_timeout),
            ("--http-body-timeout", self.http_body_timeout),
            ("--http-idle-timeout", self.http_idle_timeout),
        ] {
            if !(1..=86_400).contains(&secs) {
                bail!("{flag} {secs} must be between 1 and 86400 seconds");
            }
        }
        if self.http_max_connections == 0 || self.http_max_connections_per_address == 0 {
            bail!(
                "--http-max-connections and --http-max-connections-per-address must be at least 1"
            );
        }
        let mut cfg = CoordinatorConfig::new(self.data.clone());
        cfg.store = self.store.clone();
        cfg.api_token = self.api_token.clone().filter(|t| !t.is_empty());
        cfg.worker_token = self.worker_token.clone().filter(|t| !t.is_empty());
        cfg.lease_ms = self.lease_ms;
        cfg.heartbeat_ms = self.heartbeat_ms;
        cfg.grace_ms = self.grace_ms;
        cfg.memory_budget = self.memory_budget;
        if !(1..=3600).contains(&self.pilot_timeout) {
            bail!(
                "--pilot-timeout {} must be between 1 and 3600 seconds",
                self.pilot_timeout
            );
        }
        cfg.pilot_timeout_ms = self.pilot_timeout * 1000;
        // The pilot is this binary's hidden `tessera pilot`.
        cfg.pilot_program = std::env::current_exe().ok();
        cfg.spot_check_fraction = self.spot_check_fraction;
        let max_scene = tessera_coordinator::service::MAX_SCENE_BYTES;
        if self.max_scene_size > max_scene as u64 {
            bail!(
                "--max-scene-size {} must be at most {max_scene} bytes (256MiB)",
                self.max_scene_size
            );
        }
        cfg.max_scene_bytes = self.max_scene_size as usize;
        cfg.scene_quota_bytes = self.scene_quota;
        cfg.scene_quota_per_token = self.scene_quota_per_token;
        cfg.scene_retention_ms = self.scene_retention;
        cfg.http_limits = HttpLimits {
            header_timeout: Duration::from_secs(self.http_header_timeout),
            body_timeout: Duration::from_secs(self.http_body_timeout),
            body_min_rate: self.http_body_min_rate,
            idle_timeout: Duration::from_secs(self.http_idle_timeout),
            max_connections: self.http_max_connections,
            max_connections_per_address: self.http_max_connections_per_address,
        };
        if let (Some(cert), Some(key)) = (&self.tls_cert, &self.tls_key) {
            let files = TlsFiles {
                cert: cert.clone(),
                key: key.clone(),
                client_ca: self.tls_client_ca.clone(),
            };
            // Checked now, so that a bad file stops the start before anything is bound.
            ServerTls::load(files.clone()).context("loading the TLS files")?;
            cfg.tls = Some(files);
        }
        Ok(cfg)
    }

    /// The URL scheme of both ports: `https` with TLS.
    pub fn scheme(&self) -> &'static str {
        if self.tls_cert.is_some() {
            "https"
        } else {
            "http"
        }
    }

    /// Opens the store, then binds both ports (so their real addresses are known before
    /// anything is printed). On a PostgreSQL store the coordinator is not opened yet: it
    /// runs as a standby until it holds the store's leadership ([`Opened::Standby`],
    /// docs/store.md "High availability").
    pub async fn open(&self) -> Result<(Opened, Listeners)> {
        let cfg = self.config()?;
        let url = cfg.store_url();
        let opened = match &url {
            StoreUrl::Postgres(raw) => {
                // Opened (connected, migrated) now, so that a bad URL or an unreachable
                // server stops the start as on SQLite.
                let store = PostgresStore::open(raw)
                    .await
                    .with_context(|| format!("opening the store {url}"))?;
                Opened::Standby {
                    config: Box::new(cfg),
                    store,
                    url: raw.clone(),
                }
            }
            StoreUrl::Sqlite(_) => Opened::Single(
                Coordinator::open(cfg)
                    .await
                    .with_context(|| format!("opening the store {url}"))?,
            ),
        };
        Ok((opened, self.bind().await?))
    }

    /// Binds both ports.
    async fn bind(&self) -> Result<Listeners> {
        let http = tokio::net::TcpListener::bind(self.http)
            .await
            .with_context(|| format!("binding the HTTP port {}", self.http))?;
        let grpc = tokio::net::TcpListener::bind(self.grpc)
            .await
            .with_context(|| format!("binding the gRPC port {}", self.grpc))?;
        Ok(Listeners { http, grpc })
    }
}

/// A coordinator ready to serve ([`CoordinatorArgs::open`]).
pub enum Opened {
    /// On SQLite: the one coordinator of its store, open and resumed.
    Single(Coordinator),
    /// On PostgreSQL: a standby, until it takes the leadership ([`serve_ha`]).
    Standby {
        /// The validated configuration.
        config: Box<CoordinatorConfig>,
        /// The store, open.
        store: PostgresStore,
        /// The store's URL as given.
        url: String,
    },
}

impl Opened {
    /// Serves until `shutdown` completes: [`serve_coordinator`] or [`serve_ha`].
    pub async fn serve(
        self,
        listeners: Listeners,
        shutdown: impl std::future::Future<Output = ()>,
    ) -> Result<()> {
        match self {
            Self::Single(core) => serve_coordinator(core, listeners, shutdown).await?,
            Self::Standby { config, store, url } => {
                serve_ha(*config, store, &url, listeners, shutdown).await?
            }
        }
        Ok(())
    }
}

/// `--store`'s parser: [`StoreUrl::parse`], its error naming the URL.
pub(crate) fn parse_store_url(s: &str) -> Result<StoreUrl, String> {
    StoreUrl::parse(s).map_err(|e| e.to_string())
}

/// Prints the addresses scripts and tests read: `http: `, `grpc: ` and `dashboard: `.
pub fn print_addresses(listeners: &Listeners, scheme: &str) -> Result<()> {
    let (http, grpc) = (listeners.http.local_addr()?, listeners.grpc.local_addr()?);
    println!("http: {scheme}://{http}/api/v1");
    println!("grpc: {scheme}://{grpc}");
    println!("dashboard: {scheme}://{http}/");
    let _ = std::io::stdout().flush();
    Ok(())
}

/// Writes `secret` to a new file `path` readable by its owner only.
fn write_secret(path: &std::path::Path, secret: &str) -> std::io::Result<()> {
    let mut options = std::fs::OpenOptions::new();
    options.write(true).create_new(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        options.mode(0o600);
    }
    let mut f = options.open(path)?;
    writeln!(f, "{secret}")?;
    f.sync_all()
}

/// `tessera coordinator`.
pub fn coordinator(mut args: CoordinatorArgs) -> Result<()> {
    init_tracing();
    args.require_worker_credentials()?;
    runtime()?.block_on(async {
        let (opened, listeners) = args.open().await?;
        print_addresses(&listeners, args.scheme())?;
        opened.serve(listeners, shutdown_signal()).await
    })
}

#[cfg(test)]
mod tests {
    use super::{parse_bytes, parse_retention};

    #[test]
    fn retention_parses_units_and_off() {
        assert_eq!(parse_retention("off"), Ok(None));
        assert_eq!(parse_retention("OFF"), Ok(None));
        assert_eq!(parse_retention("30d"), Ok(Some(30 * 86_400_000)));
        assert_eq!(parse_retention("12h"), Ok(Some(12 * 3_600_000)));
        assert_eq!(parse_retention("90m"), Ok(Some(90 * 60_000)));
        assert_eq!(parse_retention("3600s"), Ok(Some(3_600_000)));
        for bad in ["", "30", "0d", "1w", "d", "-1h", "99999999999999999d"] {
            assert!(parse_retention(bad).is_err(), "{bad:?}");
        }
    }

    #[test]
    fn byte_counts_parse_with_units() {
        assert_eq!(parse_bytes("4GiB"), Ok(4 << 30));
        assert_eq!(parse_bytes("512 MiB"), Ok(512 << 20));
        assert_eq!(parse_bytes("2gb"), Ok(2_000_000_000));
        assert_eq!(parse_bytes("1073741824"), Ok(1 << 30));
        for bad in ["", "GiB", "4 parsecs", "0", "99999999999TiB", "-1"] {
            assert!(parse_bytes(bad).is_err(), "{bad:?}");
        }
    }
}
