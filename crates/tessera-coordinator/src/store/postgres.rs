//! The PostgreSQL implementation of [`Store`](super::Store) (docs/store.md, "PostgreSQL").
//!
//! The same tables, semantics, statements ([`sql`](super::sql)) and row decoding
//! ([`rows`](super::rows)) as the SQLite store, in PostgreSQL's types. What differs, and
//! why:
//!
//! - durability is PostgreSQL's (its WAL, fsynced at commit with the server's default
//!   `synchronous_commit = on`); there is no `quick_check`, commit marker or write probe,
//!   which guard against damage to a local file that the server guards against itself;
//! - writes are not serialized in-process: each write is one transaction and the rows it
//!   must not race on are locked in it (`ON CONFLICT`, `SELECT ... FOR UPDATE`,
//!   `GREATEST` in one `UPDATE`), so several connections, and several coordinators, may
//!   write at once;
//! - a lost or refused connection is [`StoreError::Unreachable`], which is transient
//!   (not [`StoreError::is_write_failure`]): the pool reconnects and the next request
//!   may succeed, where a failing SQLite file stays failed.

use std::str::FromStr;
use std::sync::atomic::{AtomicI64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use async_trait::async_trait;
use sqlx::postgres::{PgConnectOptions, PgPool, PgPoolOptions};

use super::sql::{self, stmt, store_error, unreachable, Conn, Dialect, SqlBackend, Tx, Write};
use super::{StoreError, StoreResult};

/// Schema migrations of the PostgreSQL store: (version, SQL), applied in order in one
/// transaction. Its versions are its own (version 1 has the tables of SQLite's version 3).
/// Never edit a released migration; append a new one.
const MIGRATIONS: &[(i64, &str)] = &[
    (1, include_str!("migrations/postgres/0001_initial.sql")),
    (2, include_str!("migrations/postgres/0002_leader_epoch.sql")),
    (
        3,
        include_str!("migrations/postgres/0003_adaptive_policy.sql"),
    ),
    (4, include_str!("migrations/postgres/0004_quarantine.sql")),
    (5, include_str!("migrations/postgres/0005_render_plan.sql")),
    (
        CHECKSUM_SCHEMA,
        include_str!("migrations/postgres/0006_checksums.sql"),
    ),
    (
        7,
        include_str!("migrations/postgres/0007_scene_uploads.sql"),
    ),
    (
        8,
        include_str!("migrations/postgres/0008_error_estimator.sql"),
    ),
];

/// The schema version that added row checksums (filled for existing rows as it is
/// applied).
const CHECKSUM_SCHEMA: i64 = 6;

/// Connections in the pool: the coordinator's concurrent requests, merges and the ticker.
const MAX_CONNECTIONS: u32 = 8;

/// How long getting a connection (connecting, or waiting for a free one) may take before
/// the operation fails with [`StoreError::Unreachable`].
const ACQUIRE_TIMEOUT: Duration = Duration::from_secs(10);

/// Key of the transaction-level advisory lock taken while migrating, so that two
/// coordinators opening one new database do not both create the tables.
const MIGRATION_LOCK: i64 = 0x7465_7373_6572_6131; // "tessera1"

/// The farm's state in a PostgreSQL database (`postgres://user@host:port/db`).
///
/// Cloning is cheap and shares the pool and the fencing epoch.
#[derive(Debug, Clone)]
pub struct PostgresStore {
    pool: PgPool,
    /// The URL without its password, for messages.
    url: String,
    /// The fencing epoch this store's coordinator took as the active one
    /// ([`PostgresStore::take_leadership`]); 0 before, when writes are not fenced.
    epoch: Arc<AtomicI64>,
}

impl PostgresStore {
    /// The newest schema version this build knows (and migrates every database to).
    pub const SUPPORTED_SCHEMA: i64 = MIGRATIONS[MIGRATIONS.len() - 1].0;

    /// Connects to the database at `url` (`postgres://` or `postgresql://`, with the
    /// usual libpq URL parameters sqlx understands, e.g. `?options=-c search_path=s`) and
    /// brings its schema up to date.
    ///
    /// [`StoreError::BadUrl`] for a URL that cannot be parsed, [`StoreError::Unreachable`]
    /// when the server cannot be reached or refuses the login, [`StoreError::SchemaTooNew`]
    /// if a newer build migrated the database.
    pub async fn open(url: &str) -> StoreResult<Self> {
        let shown = redact(url);
        let options = PgConnectOptions::from_str(url).map_err(|e| StoreError::BadUrl {
            url: shown.clone(),
            reason: e.to_string(),
        })?;
        // A coordinator frozen inside a write transaction (a suspended VM, SIGSTOP) would
        // hold its row locks, and so block a standby's takeover, until TCP gave up: the
        // server ends such a session after 5 s, as the lock session's idle timeout does.
        let options = options
            .application_name("tessera-coordinator")
            .options([("idle_in_transaction_session_timeout", "5000")]);
        let pool = PgPoolOptions::new()
            .max_connections(MAX_CONNECTIONS)
            .acquire_timeout(ACQUIRE_TIMEOUT)
            .connect_with(options)
            .await
            .map_err(|e| unreachable(&shown, e))?;
        let store = Self {
            pool,
            url: shown,
            epoch: Arc::new(AtomicI64::new(0)),
        };
        store.migrate().await?;
        Ok(store)
    }

    /// Makes this store's coordinator the writer of the database: raises the store's
    /// fencing epoch by one and returns it. From then on every state-changing write of
    /// this store (and its clones) first checks, in its own transaction, that the epoch
    /// is still this one, and fails with [`StoreError::NotLeader`] once another
    /// coordinator took the leadership after it (docs/store.md, "High availability").
    ///
    /// The check reads the epoch `FOR SHARE` and this `UPDATE` locks it, so the raise
    /// waits for every write of the previous leader that passed its check to commit:
    /// when this returns, nothing the previous leader writes can land any more, and the
    /// new leader reads its state after everything the old one committed.
    ///
    /// Call it while holding the leadership lock (`crate::ha`), before reading the
    /// state to resume.
    pub async fn take_leadership(&self) -> StoreResult<i64> {
        let row = self
            .reader()
            .fetch_optional(stmt(
                "UPDATE counters SET value = value + 1 WHERE name = 'leader_epoch' \
                 RETURNING value",
            ))
            .await?;
        let epoch: i64 = row
            .ok_or_else(|| StoreError::Corrupt("counters: the leader_epoch row is missing".into()))?
            .try_get("value")?;
        self.epoch.store(epoch, Ordering::SeqCst);
        Ok(epoch)
    }

    /// The fencing check of a write transaction: fails with [`StoreError::NotLeader`]
    /// when another coordinator took the leadership after this one
    /// ([`PostgresStore::take_leadership`]); nothing to check before this store took it.
    async fn fence(&self, tx: &mut Tx<'_>) -> StoreResult<()> {
        let ours = self.epoch.load(Ordering::SeqCst);
        if ours == 0 {
            return Ok(());
        }
        let row = tx
            .conn()
            .fetch_optional(stmt(
                "SELECT value FROM counters WHERE name = 'leader_epoch' FOR SHARE",
            ))
            .await?;
        let current: Option<i64> = row.map(|r| r.try_get("value")).transpose()?;
        match current {
            Some(current) if current == ours => Ok(()),
            Some(current) => Err(StoreError::NotLeader { ours, current }),
            None => Err(StoreError::Corrupt(
                "counters: the leader_epoch row is missing".into(),
            )),
        }
    }

    /// The URL of the database, without its password.
    pub fn url(&self) -> &str {
        &self.url
    }

    /// The schema version of the database (the newest applied migration).
    pub async fn schema_version(&self) -> StoreResult<i64> {
        sql::schema_version(&mut self.reader()).await
    }

    /// Creates `schema_version` if needed and applies the missing migrations, all in one
    /// transaction under an advisory lock.
    async fn migrate(&self) -> StoreResult<()> {
        let mut tx = self.begin().await?;
        tx.conn()
            .execute(stmt("SELECT pg_advisory_xact_lock($1)").bind(MIGRATION_LOCK))
            .await?;
        sql::migrate(&mut tx, MIGRATIONS, CHECKSUM_SCHEMA).await?;
        tx.commit().await
    }

    /// Begins a transaction.
    async fn begin(&self) -> StoreResult<Tx<'_>> {
        let tx = self
            .pool
            .begin()
            .await
            .map_err(|e| store_error(Some(&self.url), e))?;
        Ok(Tx::Postgres(tx, &self.url))
    }
}

/// `url` with its password replaced by `***`, for messages and logs.
pub(super) fn redact(url: &str) -> String {
    // postgres://user:password@host/...: the password sits between the first ':' after
    // the scheme and the last '@' before the path.
    let Some(scheme_end) = url.find("://").map(|i| i + 3) else {
        return url.to_string();
    };
    let rest = &url[scheme_end..];
    let authority_end = rest.find('/').unwrap_or(rest.len());
    let authority = &rest[..authority_end];
    match (authority.rfind('@'), authority.find(':')) {
        (Some(at), Some(colon)) if colon < at => format!(
            "{}{}:***{}",
            &url[..scheme_end],
            &authority[..colon],
            &rest[at..]
        ),
        _ => url.to_string(),
    }
}

/// PostgreSQL's side of the shared SQL layer ([`sql`]): concurrent writers, each write
/// fenced against a deposed coordinator; durability is the server's.
#[async_trait]
impl SqlBackend for PostgresStore {
    const DIALECT: Dialect = Dialect::Postgres;

    fn reader(&self) -> Conn<'_> {
        Conn::PgPool(&self.pool, &self.url)
    }

    async fn begin_write(&self) -> StoreResult<Write<'_>> {
        let mut tx = self.begin().await?;
        self.fence(&mut tx).await?;
        Ok(Write { tx, turn: None })
    }

    async fn finish_write(&self, write: Write<'_>, _recorded: bool) -> StoreResult<()> {
        // No commit marker: the server's WAL guards what SQLite's marker guards.
        write.tx.commit().await
    }

    async fn close_pools(&self) {
        self.pool.close().await;
    }
}

#[cfg(test)]
mod tests {
    use super::redact;

    #[test]
    fn passwords_are_not_shown() {
        assert_eq!(
            redact("postgres://u:secret@h:5432/db"),
            "postgres://u:***@h:5432/db"
        );
        assert_eq!(redact("postgres://u@h/db"), "postgres://u@h/db");
        assert_eq!(redact("postgresql://h/db"), "postgresql://h/db");
        assert_eq!(
            redact("postgres://u:p@ss@h/db?x=a:b"),
            "postgres://u:***@h/db?x=a:b"
        );
    }
}
