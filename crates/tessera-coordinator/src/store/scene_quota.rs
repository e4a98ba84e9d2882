//! Scene storage accounting and removal (docs/store.md, "Scene storage"): how many bytes
//! the stored scenes hold (in all, and per uploader), who uploaded a scene and when, which
//! jobs still need a scene, and deleting one. Kept apart from the scene rows' own
//! statements (`sql/`): these read the `size` column and the `scene_uploads` table
//! (schema 7; PostgreSQL 6), never a scene's bytes.

use tessera_farm::JobId;

use super::rows::{now_unix_ms, to_i64};
use super::sql::{stmt, SqlBackend};
use super::{SceneDeletion, StoreError, StoreResult};

/// The states of a job that still needs its scene (`queued`, `running`), as SQL.
const UNFINISHED: &str = "('queued', 'running')";

/// Bytes of the stored scenes: all of them (`owner` `None`), or those `owner` uploaded
/// first.
pub(super) async fn scene_bytes<B: SqlBackend>(b: &B, owner: Option<&str>) -> StoreResult<u64> {
    // CAST: PostgreSQL's SUM of a BIGINT is a NUMERIC.
    let row = match owner {
        None => {
            b.reader()
                .fetch_one(stmt(
                    "SELECT CAST(COALESCE(SUM(size), 0) AS BIGINT) AS n FROM scenes",
                ))
                .await?
        }
        Some(owner) => {
            b.reader()
                .fetch_one(
                    stmt(
                        "SELECT CAST(COALESCE(SUM(s.size), 0) AS BIGINT) AS n FROM scenes s \
                         JOIN scene_uploads u ON u.hash = s.hash WHERE u.owner = $1",
                    )
                    .bind(owner),
                )
                .await?
        }
    };
    let n: i64 = row.try_get("n")?;
    u64::try_from(n).map_err(|_| StoreError::Corrupt(format!("scenes: total size {n}")))
}

/// Records an upload of the stored scene `hash` by `owner`: the first uploader stays its
/// owner, the time becomes now (retention counts from the newest upload).
pub(super) async fn record_scene_upload<B: SqlBackend>(
    b: &B,
    hash: &str,
    owner: &str,
) -> StoreResult<()> {
    let mut w = b.begin_write().await?;
    w.conn()
        .execute(
            stmt(
                "INSERT INTO scene_uploads (hash, owner, uploaded_unix_ms) VALUES ($1, $2, $3) \
                 ON CONFLICT (hash) DO UPDATE SET uploaded_unix_ms = excluded.uploaded_unix_ms",
            )
            .bind(hash)
            .bind(owner)
            .bind(now_unix_ms()),
        )
        .await?;
    b.finish_write(w, false).await
}

/// The SQL condition that a row of `jobs` (as `table`) names the stored file `hash` (an
/// SQL expression) as its environment image: the coordinator stores an image source as
/// its lower-case hash (`service::jobs::canonical_environment`), so the settings' JSON
/// holds it verbatim. A hash is hex, without `LIKE`'s wildcards.
fn names_environment(table: &str, hash: &str) -> String {
    format!("{table}settings_json LIKE '%\"environment\":{{\"source\":\"' || {hash} || '\"%'")
}

/// Deletes the scene or environment image `hash` unless an unfinished job needs it as its
/// scene or its environment (checked in the same transaction, so a job cannot be stored
/// against it meanwhile).
pub(super) async fn delete_scene<B: SqlBackend>(b: &B, hash: &str) -> StoreResult<SceneDeletion> {
    let mut w = b.begin_write().await?;
    let rows = w
        .conn()
        .fetch_all(
            stmt(format!(
                "SELECT id FROM jobs WHERE (scene_ref = $1 OR {}) \
                 AND state IN {UNFINISHED} ORDER BY id",
                names_environment("", "$1")
            ))
            .bind(hash),
        )
        .await?;
    if !rows.is_empty() {
        let jobs = rows
            .iter()
            .map(|r| {
                let id: i64 = r.try_get("id")?;
                JobId::try_from(id).map_err(|_| StoreError::Corrupt(format!("jobs: id {id}")))
            })
            .collect::<StoreResult<Vec<JobId>>>()?;
        // Dropped: rolls back (nothing was written).
        return Ok(SceneDeletion::Needed(jobs));
    }
    let deleted = w
        .conn()
        .execute(stmt("DELETE FROM scenes WHERE hash = $1").bind(hash))
        .await?;
    w.conn()
        .execute(stmt("DELETE FROM scene_uploads WHERE hash = $1").bind(hash))
        .await?;
    // Recorded in the commit marker, as storing a scene is.
    b.finish_write(w, deleted > 0).await?;
    Ok(if deleted > 0 {
        SceneDeletion::Deleted
    } else {
        SceneDeletion::Missing
    })
}

/// Hashes of the stored scenes no unfinished job needs and nothing used since
/// `cutoff_unix_ms`: neither stored nor uploaded again since, and no job that refers to
/// them created or finished since. At most `limit`, oldest first.
pub(super) async fn unused_scenes<B: SqlBackend>(
    b: &B,
    cutoff_unix_ms: u64,
    limit: u32,
) -> StoreResult<Vec<String>> {
    let cutoff = to_i64(cutoff_unix_ms, "retention cutoff")?;
    let rows = b
        .reader()
        .fetch_all(
            stmt(format!(
                "SELECT s.hash AS hash FROM scenes s \
                 LEFT JOIN scene_uploads u ON u.hash = s.hash \
                 WHERE s.stored_unix_ms < $1 AND COALESCE(u.uploaded_unix_ms, 0) < $1 \
                 AND NOT EXISTS (SELECT 1 FROM jobs j WHERE (j.scene_ref = s.hash OR {}) \
                     AND (j.state IN {UNFINISHED} \
                          OR COALESCE(j.finished_unix_ms, j.created_unix_ms) >= $1)) \
                 ORDER BY s.stored_unix_ms, s.hash LIMIT $2",
                names_environment("j.", "s.hash")
            ))
            .bind(cutoff)
            .bind(i64::from(limit)),
        )
        .await?;
    rows.iter()
        .map(|r| r.try_get::<String>("hash").map_err(StoreError::from))
        .collect()
}
