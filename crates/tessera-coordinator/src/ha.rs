//! High availability on PostgreSQL: one active coordinator, the others standbys
//! (docs/store.md, "High availability"; ARCHITECTURE.md §9, "The coordinator's
//! lifecycle").
//!
//! Every coordinator on a PostgreSQL store runs [`serve_ha`], a loop of two phases:
//!
//! 1. **Standby.** Both ports are served by stand-ins: gRPC answers every worker request
//!    `UNAVAILABLE` with a message saying this is a standby (workers try the next
//!    coordinator they know), HTTP answers `/healthz` 200 (alive), `/readyz` 503
//!    `standby: ...` (a load balancer or readiness probe routes to the active one) and
//!    everything else 503 `unavailable`. Meanwhile it polls, every [`LOCK_POLL`], for a
//!    PostgreSQL session-level advisory lock ([`Leadership`]) on a dedicated connection.
//! 2. **Active.** Holding the lock, it raises the store's fencing epoch
//!    ([`PostgresStore::take_leadership`]), opens the [`Coordinator`] (the normal start:
//!    resume every unfinished job, count the crash-loop guard, the grace period for
//!    workers to deliver) and serves until shut down, or until the lock connection is
//!    lost ([`Leadership::lost`]). A loss deposes it at once ([`Coordinator::depose`]:
//!    no lease granted, no result taken from then on), its servers stop without draining
//!    and it becomes a standby again.
//!
//! Why a session-level advisory lock: PostgreSQL releases it when the session ends —
//! the coordinator's process died, was killed, or its connection broke — with nothing
//! to expire or clean up, and only one session holds it. The lock is keyed by the
//! store's schema (`current_schema()`), so farms in different schemas of one database
//! do not exclude each other. The lock session asks the server to end it when it falls
//! silent for [`IDLE_SESSION_TIMEOUT`] (`idle_session_timeout`, PostgreSQL 14+), so a
//! frozen or cut-off active coordinator loses the lock on the server's side too; on its
//! own side it checks the connection every [`LOCK_CHECK`] and gives up the leadership
//! when a check fails or takes longer than [`LOCK_CHECK_TIMEOUT`].
//!
//! Fencing: the lock decides who serves; the epoch decides whose writes land. A
//! coordinator that lost the lock but has not noticed yet may still try to write; its
//! writes fail once the new leader raised the epoch ([`StoreError::NotLeader`]), and the
//! new leader reads the store (jobs, checkpoints, the lease high-water mark) only after
//! the raise, so it reserves lease ids above every id the old one could have granted.
//! Results of the old leader's leases are then adopted as leases of a previous run
//! (validated, merged once or compared with the merged copy; ARCHITECTURE.md §9).
//!
//! The listeners are bound once; each phase serves a duplicate of their sockets
//! (`try_clone`), so connections arriving during a switch wait in the kernel's backlog
//! for the next phase instead of being refused.

use std::future::Future;
use std::str::FromStr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use sqlx::postgres::{PgConnectOptions, PgConnection};
use sqlx::{ConnectOptions, Connection};

use crate::server::{serve_phase, Ended, Listeners, ServeError, Sockets};
use crate::service::{Coordinator, CoordinatorConfig};
use crate::store::{PostgresStore, Store, StoreError};
use crate::tls::ServerTls;

/// How often a standby tries to take the leadership lock.
pub const LOCK_POLL: Duration = Duration::from_millis(500);
/// How often the active coordinator checks its lock connection.
pub const LOCK_CHECK: Duration = Duration::from_millis(500);
/// A check of the lock connection slower than this counts as a lost connection.
pub const LOCK_CHECK_TIMEOUT: Duration = Duration::from_secs(2);
/// The server ends the lock session after this long without a statement (the active
/// coordinator checks every [`LOCK_CHECK`]), releasing the lock of a coordinator that
/// froze or was cut off from the database.
pub const IDLE_SESSION_TIMEOUT: Duration = Duration::from_secs(5);
/// How long a coordinator that lost the leadership waits before it competes for it again,
/// so that another coordinator, which may well have a sound connection where this one's
/// failed, takes over first.
pub const REJOIN_DELAY: Duration = Duration::from_secs(2);

/// The first key of the advisory lock (the second is the hash of the store's schema).
const LOCK_CLASS: i32 = 0x7465_7373; // "tess"

/// The `application_name` of the lock session: `tessera-lock PID`, so an operator (or a
/// test) can find a coordinator's session in `pg_stat_activity`.
pub fn lock_application_name() -> String {
    format!("tessera-lock {}", std::process::id())
}

/// The message every request to a standby is answered with.
pub const STANDBY_MESSAGE: &str = "standby: this coordinator is not the active one; it waits \
     for the leadership of its PostgreSQL store (the active coordinator serves the farm)";

/// The leadership of a PostgreSQL store: a session-level advisory lock held on a
/// connection of its own, kept open. Dropping it closes the connection, which releases
/// the lock.
pub struct Leadership {
    conn: PgConnection,
}

impl std::fmt::Debug for Leadership {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Leadership").finish_non_exhaustive()
    }
}

impl Leadership {
    /// Opens a lock session on `url` (not taking the lock yet).
    async fn connect(url: &str) -> Result<PgConnection, sqlx::Error> {
        let options = PgConnectOptions::from_str(url)?
            .application_name(&lock_application_name())
            // The check every LOCK_CHECK would fill a debug log.
            .disable_statement_logging();
        let mut conn = options.connect().await?;
        // Best effort: `idle_session_timeout` exists from PostgreSQL 14 on; without it the
        // server notices a vanished coordinator only by its TCP keepalives.
        let timeout = format!(
            "SET idle_session_timeout = '{}ms'",
            IDLE_SESSION_TIMEOUT.as_millis()
        );
        if let Err(e) = sqlx::raw_sql(&timeout).execute(&mut conn).await {
            tracing::debug!(error = %e, "idle_session_timeout not set on the lock session");
        }
        Ok(conn)
    }

    /// One attempt on an open lock session: whether the lock was taken.
    async fn try_lock(conn: &mut PgConnection) -> Result<bool, sqlx::Error> {
        sqlx::query_scalar(
            "SELECT pg_try_advisory_lock($1, hashtext(COALESCE(current_schema(), '')))",
        )
        .bind(LOCK_CLASS)
        .fetch_one(conn)
        .await
    }

    /// One attempt: connects to `url` and tries the lock. `Ok(None)` when another
    /// session holds it.
    pub async fn try_acquire(url: &str) -> Result<Option<Self>, sqlx::Error> {
        let mut conn = Self::connect(url).await?;
        if Self::try_lock(&mut conn).await? {
            Ok(Some(Self { conn }))
        } else {
            let _ = conn.close().await;
            Ok(None)
        }
    }

    /// Polls for the lock every [`LOCK_POLL`] until it is taken, on one session kept
    /// open between attempts (its statements also keep it from the server's idle
    /// timeout). Connection failures are logged (at most once every 30 s while they
    /// last) and the session opened again.
    pub async fn acquire(url: &str) -> Self {
        let mut last_warning: Option<Instant> = None;
        let mut session: Option<PgConnection> = None;
        loop {
            let attempt = async {
                let conn = match session.as_mut() {
                    Some(c) => c,
                    None => session.insert(Self::connect(url).await?),
                };
                Self::try_lock(conn).await
            };
            match attempt.await {
                Ok(true) => {
                    if let Some(conn) = session.take() {
                        return Self { conn };
                    }
                }
                Ok(false) => {}
                Err(e) => {
                    session = None;
                    if last_warning.is_none_or(|t| t.elapsed() >= Duration::from_secs(30)) {
                        tracing::warn!(error = %e, "standby cannot reach the PostgreSQL store; retrying");
                        last_warning = Some(Instant::now());
                    }
                }
            }
            tokio::time::sleep(LOCK_POLL).await;
        }
    }

    /// Completes when the lock is lost: the lock connection failed, or a check of it took
    /// longer than [`LOCK_CHECK_TIMEOUT`]. Returns why.
    pub async fn lost(&mut self) -> String {
        let mut every = tokio::time::interval(LOCK_CHECK);
        every.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            every.tick().await;
            let check = sqlx::query_scalar::<_, i32>("SELECT 1").fetch_one(&mut self.conn);
            match tokio::time::timeout(LOCK_CHECK_TIMEOUT, check).await {
                Ok(Ok(_)) => {}
                Ok(Err(e)) => {
                    return format!("the connection holding the leadership lock failed: {e}")
                }
                Err(_) => {
                    return format!(
                        "the connection holding the leadership lock did not answer within {} ms",
                        LOCK_CHECK_TIMEOUT.as_millis()
                    )
                }
            }
        }
    }
}

/// Runs a coordinator on the PostgreSQL `store` (opened by the caller, so a bad URL or
/// an unreachable server stops the start) as a standby, then as the active coordinator
/// whenever it holds the leadership (see the [module documentation](self)), until
/// `shutdown` completes. `url` is the store's URL as given (with its password).
///
/// Returns an error when the coordinator cannot start as the active one for a reason
/// that a retry does not cure (a store that does not resume), or a server fails.
pub async fn serve_ha(
    config: CoordinatorConfig,
    store: PostgresStore,
    url: &str,
    listeners: Listeners,
    shutdown: impl Future<Output = ()>,
) -> Result<(), ServeError> {
    let tls = match &config.tls {
        Some(files) => Some(Arc::new(ServerTls::load(files.clone())?)),
        None => None,
    };
    let reloader = tls.clone().map(ServerTls::reload_on_sighup);
    let sockets = Sockets::new(listeners)?;
    tokio::pin!(shutdown);
    let mut rejoin_after = Duration::ZERO;
    let result = loop {
        // Standby.
        tracing::warn!("standby: waiting for the leadership of the PostgreSQL store");
        let standby = crate::server::spawn_standby(&config, sockets.listeners()?, tls.clone());
        let wait = std::mem::take(&mut rejoin_after);
        let taken = tokio::select! {
            l = async {
                tokio::time::sleep(wait).await;
                Leadership::acquire(url).await
            } => Some(l),
            _ = &mut shutdown => None,
        };
        standby.stop().await;
        let Some(mut leadership) = taken else {
            break Ok(());
        };
        // Active.
        let started = Instant::now();
        let core = match become_active(&config, &store).await {
            Ok(core) => core,
            Err(e) if matches!(e, StoreError::Unreachable { .. }) => {
                tracing::error!(error = %e, "cannot start as the active coordinator; standing by again");
                drop(leadership);
                tokio::time::sleep(LOCK_POLL).await;
                continue;
            }
            Err(e) => break Err(ServeError::Open(e)),
        };
        // Warnings, not information: a change of the active coordinator is what an
        // operator looks for in the log (the default filter shows warnings).
        tracing::warn!(
            ms = started.elapsed().as_millis() as u64,
            "active: this coordinator holds the leadership and serves the farm"
        );
        let end = async {
            tokio::select! {
                _ = &mut shutdown => Ended::Shutdown,
                reason = leadership.lost() => Ended::Deposed(reason),
            }
        };
        match serve_phase(core, sockets.listeners()?, tls.clone(), end).await {
            // Reopen is the SQLite coordinator's (`serve_coordinator`), never this one's.
            Ok(Ended::Shutdown | Ended::Reopen) => break Ok(()),
            Ok(Ended::Deposed(reason)) => {
                tracing::error!(reason = %reason, "lost the leadership: stopped serving; standing by");
                rejoin_after = REJOIN_DELAY;
            }
            Err(e) => break Err(e),
        }
        drop(leadership);
    };
    if let Some(r) = reloader {
        r.abort();
    }
    store.close().await;
    result
}

/// Takes the fencing epoch and opens the coordinator on the store: the normal start,
/// resuming every unfinished job.
async fn become_active(
    config: &CoordinatorConfig,
    store: &PostgresStore,
) -> Result<Coordinator, StoreError> {
    let epoch = store.take_leadership().await?;
    tracing::warn!(epoch, "took the leadership of the PostgreSQL store");
    let shared: Arc<dyn Store> = Arc::new(store.clone());
    Coordinator::with_store(config.clone(), shared).await
}
