//! The schema's migrations, and the rows that fail their checks: the checksums added by
//! a migration are filled for existing rows ([`migrate`]), damaged rows are listed for
//! `tessera store check` ([`damaged_rows`]) and a start drops the damaged checkpoints of
//! unfinished jobs so their units are rendered again (docs/store.md, "Checksums").

use super::*;

/// Creates `schema_version` if needed and applies the missing `migrations` in `tx`,
/// which the caller holds exclusively (SQLite: `BEGIN IMMEDIATE`; PostgreSQL: an
/// advisory lock), so two processes opening one new database cannot both migrate.
/// Applying version `checksum_schema` (the one that adds the `checksum` columns) also
/// fills them for every existing row, in the same transaction ([`backfill_checksums`]).
pub async fn migrate(
    tx: &mut Tx<'_>,
    migrations: &[(i64, &str)],
    checksum_schema: i64,
) -> StoreResult<()> {
    let supported = migrations.last().map_or(0, |m| m.0);
    let ddl = tx.dialect().schema_version_table();
    tx.conn().execute(stmt(ddl)).await?;
    let current = schema_version(&mut tx.conn()).await?;
    if current > supported {
        return Err(StoreError::SchemaTooNew {
            found: current,
            supported,
        });
    }
    for &(version, sql) in migrations.iter().filter(|m| m.0 > current) {
        tx.execute_script(sql).await?;
        tx.conn()
            .execute(
                stmt("INSERT INTO schema_version (version, applied_unix_ms) VALUES ($1, $2)")
                    .bind(version)
                    .bind(now_unix_ms()),
            )
            .await?;
        if version == checksum_schema {
            backfill_checksums(&mut tx.conn()).await?;
        }
    }
    Ok(())
}

/// Computes the checksum of every row of `jobs`, `tiles` and `scenes` that has none (the
/// rows of a store older than the checksums), one row at a time so that a large store
/// is never held in memory. A job row that cannot be decoded keeps no checksum: it is
/// reported as damaged whenever it is read, as it was before.
async fn backfill_checksums(conn: &mut Conn<'_>) -> StoreResult<()> {
    let jobs = conn
        .fetch_all(stmt(
            "SELECT id FROM jobs WHERE checksum IS NULL ORDER BY id",
        ))
        .await?;
    for id in jobs {
        let id: i64 = id.try_get("id")?;
        let row = conn
            .fetch_one(
                stmt(format!(
                    "SELECT {JOB_COLUMNS_BEFORE_ESTIMATOR} FROM jobs WHERE id = $1"
                ))
                .bind(id),
            )
            .await?;
        if let Ok(job) = decode_job(&row) {
            let sum = JobSum::from(&job).checksum();
            conn.execute(
                stmt("UPDATE jobs SET checksum = $2 WHERE id = $1")
                    .bind(id)
                    .bind(sum),
            )
            .await?;
        }
    }
    let tiles = conn
        .fetch_all(stmt(
            "SELECT job, frame, tile FROM tiles WHERE checksum IS NULL ORDER BY job, frame, tile",
        ))
        .await?;
    for key in tiles {
        let (job, frame, tile): (i64, i64, i64) = (
            key.try_get("job")?,
            key.try_get("frame")?,
            key.try_get("tile")?,
        );
        let row = conn
            .fetch_one(
                stmt(format!(
                    "SELECT {TILE_COLUMNS} FROM tiles WHERE job = $1 AND frame = $2 AND tile = $3"
                ))
                .bind(job)
                .bind(frame)
                .bind(tile),
            )
            .await?;
        let (stats, units, adaptive) = tile_blobs(&row)?;
        let sum = tile_sum(&row, &stats, &units, adaptive.as_deref())?.checksum();
        conn.execute(
            stmt("UPDATE tiles SET checksum = $4 WHERE job = $1 AND frame = $2 AND tile = $3")
                .bind(job)
                .bind(frame)
                .bind(tile)
                .bind(sum),
        )
        .await?;
    }
    let scenes = conn
        .fetch_all(stmt(
            "SELECT hash FROM scenes WHERE checksum IS NULL ORDER BY hash",
        ))
        .await?;
    for hash in scenes {
        let hash: String = hash.try_get("hash")?;
        let row = conn
            .fetch_one(stmt("SELECT data FROM scenes WHERE hash = $1").bind(&hash))
            .await?;
        let data: Vec<u8> = row.try_get("data")?;
        conn.execute(
            stmt("UPDATE scenes SET checksum = $2 WHERE hash = $1")
                .bind(&hash)
                .bind(scene_checksum(&hash, &data)),
        )
        .await?;
    }
    Ok(())
}

/// A row that fails its checks (its checksum, or the decoding and plan checks of a read),
/// found by [`damaged_rows`] or [`damaged_tiles`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DamagedRow {
    /// `jobs`, `tiles` or `scenes`.
    pub table: &'static str,
    /// The row's key for people: `job 3`, `job 3, frame 0, tile 5`, `scene HASH`.
    pub key: String,
    /// The job the row belongs to (`None` for a scene) and its state, if readable.
    pub job: Option<(JobId, Option<JobState>)>,
    /// What is wrong (the error a read of the row gives).
    pub reason: String,
}

/// The tiles of `job` that a read refuses (checksum, decoding, the job's plan), one frame
/// at a time: (frame, tile, the error). When the job's plan cannot be read, the
/// checksums alone are checked.
async fn damaged_tiles(
    conn: &mut Conn<'_>,
    job: JobId,
) -> StoreResult<Vec<(i64, i64, StoreError)>> {
    let key = to_i64(job, "job id")?;
    let plan = job_plan(conn, job).await.ok();
    let frames = conn
        .fetch_all(stmt("SELECT DISTINCT frame FROM tiles WHERE job = $1 ORDER BY frame").bind(key))
        .await?;
    let mut damaged = Vec::new();
    for f in frames {
        let frame: i64 = f.try_get("frame")?;
        let rows = conn
            .fetch_all(
                stmt(format!(
                    "SELECT {TILE_COLUMNS} FROM tiles WHERE job = $1 AND frame = $2 ORDER BY tile"
                ))
                .bind(key)
                .bind(frame),
            )
            .await?;
        for row in rows {
            let tile: i64 = row.try_get("tile")?;
            let (stats, units, adaptive) = tile_blobs(&row)?;
            let problem = match plan {
                Some((plan, frames)) => tile_from_parts(
                    &plan,
                    frames,
                    job,
                    &row,
                    &stats,
                    &units,
                    adaptive.as_deref(),
                )
                .err(),
                None => {
                    let sum = tile_sum(&row, &stats, &units, adaptive.as_deref())?.checksum();
                    let stored: Option<Vec<u8>> = row.try_get("checksum")?;
                    verify(stored.as_deref(), &sum)
                        .err()
                        .map(|reason| StoreError::CorruptTile {
                            job,
                            frame: u32::try_from(frame).unwrap_or(u32::MAX),
                            tile: u32::try_from(tile).unwrap_or(u32::MAX),
                            reason,
                        })
                }
            };
            if let Some(e) = problem {
                damaged.push((frame, tile, e));
            }
        }
    }
    Ok(damaged)
}

/// Every row of `jobs`, `tiles` and `scenes` that a read refuses: the checks of
/// `tessera store check` (read-only; one job's or scene's rows in memory at a time).
pub async fn damaged_rows(conn: &mut Conn<'_>) -> StoreResult<Vec<DamagedRow>> {
    let mut out = Vec::new();
    let jobs = conn
        .fetch_all(stmt("SELECT id, state FROM jobs ORDER BY id"))
        .await?;
    for j in jobs {
        let id: i64 = j.try_get("id")?;
        let Ok(job) = JobId::try_from(id) else {
            out.push(DamagedRow {
                table: "jobs",
                key: format!("job {id}"),
                job: None,
                reason: format!("negative id {id}"),
            });
            continue;
        };
        let state = parse_state(&j.try_get::<String>("state")?);
        let row = conn
            .fetch_one(stmt(format!("SELECT {JOB_COLUMNS} FROM jobs WHERE id = $1")).bind(id))
            .await?;
        if let Err(e) = job_from_row(&row) {
            out.push(DamagedRow {
                table: "jobs",
                key: format!("job {job}"),
                job: Some((job, state)),
                reason: e.to_string(),
            });
        }
        for (frame, tile, e) in damaged_tiles(conn, job).await? {
            out.push(DamagedRow {
                table: "tiles",
                key: format!("job {job}, frame {frame}, tile {tile}"),
                job: Some((job, state)),
                reason: e.to_string(),
            });
        }
    }
    let scenes = conn
        .fetch_all(stmt("SELECT hash FROM scenes ORDER BY hash"))
        .await?;
    for s in scenes {
        let hash: String = s.try_get("hash")?;
        if let Err(e) = read_scene(conn, &hash).await {
            out.push(DamagedRow {
                table: "scenes",
                key: format!("scene {hash}"),
                job: None,
                reason: e.to_string(),
            });
        }
    }
    Ok(out)
}

/// Deletes the tile checkpoints of every queued or running job that a read would refuse
/// (a checksum that does not match, a blob that does not decode or fit the plan), each
/// logged as an error naming the row: the job's resume then finds the tile without a
/// checkpoint and renders its units again, instead of failing the job or merging into
/// damaged statistics (docs/store.md, "Checksums"). Called by [`Store::begin_run`], so a
/// start drops exactly what `tessera store check` reports for such jobs. Checkpoints of
/// finished jobs are kept: their image is refused with the error naming the tile.
pub(super) async fn drop_damaged_checkpoints<B: SqlBackend>(store: &B) -> StoreResult<()> {
    let jobs = store
        .reader()
        .fetch_all(stmt(
            "SELECT id FROM jobs WHERE state IN ('queued', 'running') ORDER BY id",
        ))
        .await?;
    for j in jobs {
        let id: i64 = j.try_get("id")?;
        let Ok(job) = JobId::try_from(id) else {
            continue;
        };
        let damaged = damaged_tiles(&mut store.reader(), job).await?;
        if damaged.is_empty() {
            continue;
        }
        let mut w = store.begin_write().await?;
        for (frame, tile, e) in &damaged {
            tracing::error!(
                table = "tiles",
                job,
                frame,
                tile,
                error = %e,
                "damaged tile checkpoint dropped; its units are rendered again"
            );
            w.execute(
                stmt("DELETE FROM tiles WHERE job = $1 AND frame = $2 AND tile = $3")
                    .bind(id)
                    .bind(*frame)
                    .bind(*tile),
            )
            .await?;
        }
        store.finish_write(w, false).await?;
    }
    Ok(())
}
