//! The [`Store`] contract on a SQL database, once for both backends: every statement
//! through [`Conn`] and [`Write`], in PostgreSQL's spelling.

use super::integrity::drop_damaged_checkpoints;
use super::*;
use crate::store::{scene_quota, SceneDeletion};

/// The [`Store`] contract on a SQL database, once for both backends.
#[async_trait]
impl<B: SqlBackend> Store for B {
    async fn insert_job(&self, job: NewJob) -> StoreResult<(JobId, bool)> {
        let created = check_new_job(&job)?;
        let mut w = self.begin_write().await?;
        let inserted = w
            .fetch_optional(
                stmt(
                    "INSERT INTO jobs (idempotency_key, name, scene_ref, settings_json, \
                         plan_width, plan_height, plan_tile_size, plan_samples_per_pass, \
                         plan_passes, first_frame, last_frame, passes_per_unit, priority, state, \
                         created_unix_ms, render_plan_json, error_estimate_caveat) \
                     VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11, $12, $13, 'queued', \
                         $14, $15, $16) \
                     ON CONFLICT (idempotency_key) DO NOTHING \
                     RETURNING id",
                )
                .bind(job.idempotency_key.as_deref())
                .bind(job.name.as_deref())
                .bind(&job.scene_ref)
                .bind(&job.settings_json)
                .bind(i64::from(job.plan.width))
                .bind(i64::from(job.plan.height))
                .bind(i64::from(job.plan.tile_size))
                .bind(i64::from(job.plan.samples_per_pass))
                .bind(i64::from(job.plan.passes))
                .bind(i64::from(job.frames.start))
                .bind(i64::from(job.frames.end))
                .bind(i64::from(job.passes_per_unit))
                .bind(i64::from(job.priority))
                .bind(created)
                .bind(job.render_plan_json.as_deref())
                .bind(job.error_estimate_caveat.as_deref()),
            )
            .await?;
        let (id, created): (i64, bool) = match inserted {
            Some(row) => {
                let id: i64 = row.try_get("id")?;
                // The id is the database's, so the checksum that covers it is written
                // in a second statement of the same transaction.
                let sum = JobSum {
                    id,
                    idempotency_key: job.idempotency_key.as_deref(),
                    name: job.name.as_deref(),
                    scene_ref: &job.scene_ref,
                    settings_json: &job.settings_json,
                    plan: job.plan,
                    frames: job.frames,
                    passes_per_unit: job.passes_per_unit,
                    priority: job.priority,
                    created_unix_ms: created,
                    render_plan_json: job.render_plan_json.as_deref(),
                    error_estimate_caveat: job.error_estimate_caveat.as_deref(),
                };
                w.execute(
                    stmt("UPDATE jobs SET checksum = $2 WHERE id = $1")
                        .bind(id)
                        .bind(sum.checksum()),
                )
                .await?;
                (id, true)
            }
            None => {
                // Only a conflicting idempotency key makes the insert do nothing; under
                // PostgreSQL's READ COMMITTED this statement sees the conflicting row,
                // committed.
                let row = w
                    .conn()
                    .fetch_one(
                        stmt("SELECT id FROM jobs WHERE idempotency_key = $1")
                            .bind(job.idempotency_key.as_deref()),
                    )
                    .await?;
                (row.try_get("id")?, false)
            }
        };
        self.finish_write(w, created).await?;
        let id = JobId::try_from(id)
            .map_err(|_| StoreError::Corrupt(format!("jobs: negative id {id}")))?;
        Ok((id, created))
    }

    async fn get_job(&self, id: JobId) -> StoreResult<Option<JobRecord>> {
        let Ok(key) = i64::try_from(id) else {
            return Ok(None);
        };
        self.reader()
            .fetch_optional(stmt(format!("SELECT {JOB_COLUMNS} FROM jobs WHERE id = $1")).bind(key))
            .await?
            .as_ref()
            .map(job_from_row)
            .transpose()
    }

    async fn list_jobs(&self, query: JobQuery) -> StoreResult<Vec<JobRecord>> {
        if query.limit == 0 {
            return Ok(Vec::new());
        }
        let (cmp, dir, default_cursor) = match query.order {
            JobOrder::NewestFirst => ("<", "DESC", i64::MAX),
            JobOrder::OldestFirst => (">", "ASC", 0),
        };
        let cursor = match (query.cursor.map(i64::try_from), query.order) {
            (None, _) => default_cursor,
            (Some(Ok(c)), _) => c,
            // A cursor above every possible id: all ids come after it newest first, none
            // oldest first.
            (Some(Err(_)), JobOrder::NewestFirst) => i64::MAX,
            (Some(Err(_)), JobOrder::OldestFirst) => return Ok(Vec::new()),
        };
        // The casts give PostgreSQL the type of a parameter that may be NULL.
        let sql = format!(
            "SELECT {JOB_COLUMNS} FROM jobs WHERE id {cmp} $1 \
             AND (CAST($2 AS TEXT) IS NULL OR state = CAST($2 AS TEXT)) \
             ORDER BY id {dir} LIMIT $3"
        );
        let rows = self
            .reader()
            .fetch_all(
                stmt(sql)
                    .bind(cursor)
                    .bind(query.state.map(JobState::as_str))
                    .bind(i64::from(query.limit)),
            )
            .await?;
        rows.iter().map(job_from_row).collect()
    }

    async fn set_job_state(
        &self,
        id: JobId,
        state: JobState,
        error: Option<String>,
        now_unix_ms: u64,
    ) -> StoreResult<bool> {
        let key = i64::try_from(id).map_err(|_| StoreError::JobNotFound(id))?;
        let now = to_i64(now_unix_ms, "now_unix_ms")?;
        let mut w = self.begin_write().await?;
        let changed = w
            .execute(
                stmt(
                    "UPDATE jobs SET state = CAST($2 AS TEXT), error = $3, \
                         started_unix_ms = CASE WHEN CAST($2 AS TEXT) = 'running' \
                             AND started_unix_ms IS NULL THEN $4 ELSE started_unix_ms END, \
                         finished_unix_ms = CASE WHEN CAST($2 AS TEXT) \
                             IN ('done', 'failed', 'canceled') \
                             THEN $4 ELSE finished_unix_ms END \
                     WHERE id = $1 AND state IN ('queued', 'running')",
                )
                .bind(key)
                .bind(state.as_str())
                .bind(error.as_deref())
                .bind(now),
            )
            .await?
            > 0;
        let exists = changed
            || w.fetch_optional(stmt("SELECT 1 AS one FROM jobs WHERE id = $1").bind(key))
                .await?
                .is_some();
        self.finish_write(w, changed).await?;
        if exists {
            Ok(changed)
        } else {
            Err(StoreError::JobNotFound(id))
        }
    }

    async fn count_jobs_by_state(&self) -> StoreResult<Vec<(JobState, u64)>> {
        let rows = self
            .reader()
            .fetch_all(stmt("SELECT state, COUNT(*) AS n FROM jobs GROUP BY state"))
            .await?;
        rows.iter().map(state_count_from_row).collect()
    }

    async fn jobs_to_resume(&self) -> StoreResult<Vec<JobRecord>> {
        let rows = self
            .reader()
            .fetch_all(stmt(format!(
                "SELECT {JOB_COLUMNS} FROM jobs WHERE state IN ('queued', 'running') ORDER BY id"
            )))
            .await?;
        rows.iter().map(job_from_row).collect()
    }

    async fn put_scene(&self, hash: &str, bytes: &[u8]) -> StoreResult<bool> {
        if hash.is_empty() {
            return Err(StoreError::InvalidInput("scene hash is empty".into()));
        }
        let size = to_i64(bytes.len() as u64, "scene size")?;
        let mut w = self.begin_write().await?;
        let stored = w
            .execute(
                stmt(
                    "INSERT INTO scenes (hash, size, data, stored_unix_ms, checksum) \
                     VALUES ($1, $2, $3, $4, $5) ON CONFLICT (hash) DO NOTHING",
                )
                .bind(hash)
                .bind(size)
                .bind(bytes)
                .bind(now_unix_ms())
                .bind(scene_checksum(hash, bytes)),
            )
            .await?
            > 0;
        self.finish_write(w, stored).await?;
        Ok(stored)
    }

    async fn get_scene(&self, hash: &str) -> StoreResult<Option<Vec<u8>>> {
        read_scene(&mut self.reader(), hash).await
    }

    async fn scene_exists(&self, hash: &str) -> StoreResult<bool> {
        // The key alone: the scene's bytes are not read.
        Ok(self
            .reader()
            .fetch_optional(stmt("SELECT 1 AS one FROM scenes WHERE hash = $1").bind(hash))
            .await?
            .is_some())
    }

    async fn scene_bytes(&self, owner: Option<&str>) -> StoreResult<u64> {
        scene_quota::scene_bytes(self, owner).await
    }

    async fn record_scene_upload(&self, hash: &str, owner: &str) -> StoreResult<()> {
        scene_quota::record_scene_upload(self, hash, owner).await
    }

    async fn delete_scene(&self, hash: &str) -> StoreResult<SceneDeletion> {
        scene_quota::delete_scene(self, hash).await
    }

    async fn unused_scenes(&self, cutoff_unix_ms: u64, limit: u32) -> StoreResult<Vec<String>> {
        scene_quota::unused_scenes(self, cutoff_unix_ms, limit).await
    }

    async fn save_tiles(&self, tiles: &[TileCheckpointRef<'_>]) -> StoreResult<()> {
        if tiles.is_empty() {
            return Ok(());
        }
        let mut w = self.begin_write().await?;
        let mut plans: Vec<(JobId, FramePlan, FrameRange)> = Vec::new();
        for t in tiles {
            let (plan, frames) = match plans.iter().find(|p| p.0 == t.job) {
                Some(&(_, plan, frames)) => (plan, frames),
                None => {
                    let (plan, frames) = job_plan(&mut w.conn(), t.job).await?;
                    plans.push((t.job, plan, frames));
                    (plan, frames)
                }
            };
            check_tile_to_save(&plan, frames, t)?;
            let (stats, units) = (encode_stats(t.pixels, t.bias), encode_units(t.units));
            let adaptive = t.adaptive.map(encode_adaptive);
            let sum = TileSum {
                job: to_i64(t.job, "job id")?,
                frame: i64::from(t.frame),
                tile: i64::from(t.tile),
                merged_passes: i64::from(t.merged_passes),
                rejected_samples: to_i64(t.rejected_samples, "rejected_samples")?,
                stats: &stats,
                units: &units,
                adaptive: adaptive.as_deref(),
            };
            let checksum = sum.checksum();
            w.execute(
                stmt(
                    "INSERT INTO tiles (job, frame, tile, merged_passes, stats, units, \
                         rejected_samples, adaptive, checksum) \
                     VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9) \
                     ON CONFLICT (job, frame, tile) DO UPDATE SET \
                         merged_passes = excluded.merged_passes, \
                         stats = excluded.stats, \
                         units = excluded.units, \
                         rejected_samples = excluded.rejected_samples, \
                         adaptive = excluded.adaptive, \
                         checksum = excluded.checksum",
                )
                .bind(sum.job)
                .bind(sum.frame)
                .bind(sum.tile)
                .bind(sum.merged_passes)
                .bind(&stats[..])
                .bind(&units[..])
                .bind(sum.rejected_samples)
                .bind(adaptive.as_deref())
                .bind(checksum),
            )
            .await?;
        }
        self.finish_write(w, false).await
    }

    async fn load_tiles(&self, job: JobId, frame: Option<u32>) -> StoreResult<Vec<TileCheckpoint>> {
        let key = i64::try_from(job).map_err(|_| StoreError::JobNotFound(job))?;
        let (plan, frames) = job_plan(&mut self.reader(), job).await?;
        let rows = self
            .reader()
            .fetch_all(
                stmt(format!(
                    "SELECT {TILE_COLUMNS} FROM tiles WHERE job = $1 \
                     AND (CAST($2 AS BIGINT) IS NULL OR frame = CAST($2 AS BIGINT)) \
                     ORDER BY frame, tile"
                ))
                .bind(key)
                .bind(frame.map(i64::from)),
            )
            .await?;
        rows.iter()
            .map(|row| {
                let stats: Vec<u8> = row.try_get("stats")?;
                let units: Vec<u8> = row.try_get("units")?;
                let adaptive: Option<Vec<u8>> = row.try_get("adaptive")?;
                tile_from_parts(&plan, frames, job, row, &stats, &units, adaptive.as_deref())
            })
            .collect()
    }

    async fn tile_summaries(&self, job: JobId) -> StoreResult<Vec<TileSummary>> {
        let key = i64::try_from(job).map_err(|_| StoreError::JobNotFound(job))?;
        let rows = self
            .reader()
            .fetch_all(
                stmt(
                    "SELECT frame, tile, merged_passes, rejected_samples FROM tiles \
                     WHERE job = $1 ORDER BY frame, tile",
                )
                .bind(key),
            )
            .await?;
        rows.iter().map(|row| summary_from_row(row, job)).collect()
    }

    async fn max_lease_id(&self) -> StoreResult<u64> {
        let row = self
            .reader()
            .fetch_optional(stmt(
                "SELECT value FROM counters WHERE name = 'lease_high_water'",
            ))
            .await?;
        let v: i64 = row
            .ok_or_else(|| {
                StoreError::Corrupt("counters: the lease_high_water row is missing".into())
            })?
            .try_get("value")?;
        u64::try_from(v)
            .map_err(|_| StoreError::Corrupt(format!("counters: lease_high_water = {v}")))
    }

    async fn record_lease_high_water(&self, lease_id: u64) -> StoreResult<()> {
        let v = to_i64(lease_id, "lease id")?;
        // Fenced like every write: a deposed PostgreSQL coordinator reserves no more
        // lease ids, so the new one's ids start above everything this one could grant.
        let mut w = self.begin_write().await?;
        // One statement: the row lock makes concurrent raises keep the largest value.
        let sql = format!(
            "UPDATE counters SET value = {}(value, $1) WHERE name = 'lease_high_water'",
            B::DIALECT.greatest()
        );
        if w.execute(stmt(sql).bind(v)).await? != 1 {
            return Err(StoreError::Corrupt(
                "counters: the lease_high_water row is missing".into(),
            ));
        }
        // Recorded in the commit marker too (SQLite): a reservation lost with a `-wal`
        // file would let fencing tokens repeat. Reservations come in blocks, so this is
        // one marker write per block.
        self.finish_write(w, true).await
    }

    async fn fence_key(&self, fresh: [u8; 32]) -> StoreResult<[u8; 32]> {
        // Kept if absent, in one write: concurrent coordinators agree on one key (the
        // primary key makes a later insert do nothing), and every later call returns it.
        let mut w = self.begin_write().await?;
        let mut key = [0u8; 32];
        for (i, (word, out)) in fresh
            .chunks_exact(8)
            .zip(key.chunks_exact_mut(8))
            .enumerate()
        {
            let name = format!("fence_key_{i}");
            let v = i64::from_le_bytes(word.try_into().expect("8 bytes"));
            w.execute(
                stmt("INSERT INTO counters (name, value) VALUES ($1, $2) ON CONFLICT (name) DO NOTHING")
                    .bind(&name)
                    .bind(v),
            )
            .await?;
            let kept: i64 = w
                .fetch_optional(stmt("SELECT value FROM counters WHERE name = $1").bind(&name))
                .await?
                .ok_or_else(|| StoreError::Corrupt(format!("counters: the {name} row is missing")))?
                .try_get("value")?;
            out.copy_from_slice(&kept.to_le_bytes());
        }
        self.finish_write(w, false).await?;
        Ok(key)
    }

    async fn append_history(
        &self,
        job: JobId,
        point: HistoryPoint,
        estimator: Option<&str>,
    ) -> StoreResult<()> {
        let key = i64::try_from(job).map_err(|_| StoreError::JobNotFound(job))?;
        let elapsed = check_finite(point.elapsed_seconds, "history elapsed_seconds")?;
        let spp = check_finite(point.spp, "history spp")?;
        let error = point
            .error_estimate
            .map(|e| check_finite(e, "history error_estimate"))
            .transpose()?;
        let mut w = self.begin_write().await?;
        let n = w
            .execute(
                stmt(
                    "INSERT INTO history (job, elapsed_seconds, spp, error_estimate) \
                     SELECT $1, $2, $3, $4 WHERE EXISTS (SELECT 1 FROM jobs WHERE id = $1)",
                )
                .bind(key)
                .bind(elapsed)
                .bind(spp)
                .bind(error),
            )
            .await?;
        if n == 0 {
            return Err(StoreError::JobNotFound(job));
        }
        if let Some(name) = estimator {
            // In the same transaction: the job's name is the one of its last point.
            w.execute(
                stmt("UPDATE jobs SET error_estimator = $2 WHERE id = $1")
                    .bind(key)
                    .bind(name),
            )
            .await?;
        }
        self.finish_write(w, false).await
    }

    async fn list_history(&self, job: JobId) -> StoreResult<Vec<HistoryPoint>> {
        let Ok(key) = i64::try_from(job) else {
            return Ok(Vec::new());
        };
        let rows = self
            .reader()
            .fetch_all(
                stmt(
                    "SELECT elapsed_seconds, spp, error_estimate FROM history \
                     WHERE job = $1 ORDER BY seq",
                )
                .bind(key),
            )
            .await?;
        rows.iter()
            .map(|r| {
                Ok(HistoryPoint {
                    elapsed_seconds: r.try_get("elapsed_seconds")?,
                    spp: r.try_get("spp")?,
                    error_estimate: r.try_get("error_estimate")?,
                })
            })
            .collect()
    }

    async fn record_fault(&self, fault: &FaultEvent) -> StoreResult<()> {
        let job = fault.job.map(|j| to_i64(j, "fault job")).transpose()?;
        let unix_ms = to_i64(fault.unix_ms, "fault unix_ms")?;
        let mut w = self.begin_write().await?;
        w.execute(
            stmt(
                "INSERT INTO faults (worker, job, kind, message, unix_ms) \
                 VALUES ($1, $2, $3, $4, $5)",
            )
            .bind(&fault.worker)
            .bind(job)
            .bind(fault.kind.as_str())
            .bind(&fault.message)
            .bind(unix_ms),
        )
        .await?;
        self.finish_write(w, false).await
    }

    async fn count_faults(&self, filter: &FaultFilter) -> StoreResult<u64> {
        let s = faults_stmt("COUNT(*) AS n", filter, "")?;
        let row = self.reader().fetch_one(s).await?;
        int_col(&row, "n", &|| "faults".to_string())
    }

    async fn list_faults(&self, filter: &FaultFilter, limit: u32) -> StoreResult<Vec<FaultEvent>> {
        let tail = format!(" ORDER BY id DESC LIMIT {limit}");
        let s = faults_stmt("worker, job, kind, message, unix_ms", filter, &tail)?;
        let rows = self.reader().fetch_all(s).await?;
        rows.iter().map(fault_from_row).collect()
    }

    async fn record_quarantine(&self, q: &QuarantineRecord) -> StoreResult<bool> {
        let unix_ms = to_i64(q.unix_ms, "quarantine unix_ms")?;
        let mut w = self.begin_write().await?;
        let n = w
            .execute(
                stmt(
                    "INSERT INTO quarantines (worker, identity, reason, unix_ms) \
                     VALUES ($1, $2, $3, $4) ON CONFLICT (worker, identity) DO NOTHING",
                )
                .bind(&q.worker)
                .bind(identity_col(q.identity.as_deref()))
                .bind(&q.reason)
                .bind(unix_ms),
            )
            .await?;
        self.finish_write(w, false).await?;
        Ok(n == 1)
    }

    async fn list_quarantines(&self) -> StoreResult<Vec<QuarantineRecord>> {
        let c = B::DIALECT.byte_order();
        let sql =
            format!("SELECT {QUARANTINE_COLUMNS} FROM quarantines ORDER BY worker{c}, identity{c}");
        let rows = self.reader().fetch_all(stmt(sql)).await?;
        rows.iter().map(quarantine_from_row).collect()
    }

    async fn delete_quarantines(&self, worker: &str) -> StoreResult<u64> {
        let mut w = self.begin_write().await?;
        let n = w
            .execute(stmt("DELETE FROM quarantines WHERE worker = $1").bind(worker))
            .await?;
        self.finish_write(w, false).await?;
        Ok(n)
    }

    async fn job_ids_to_resume(&self) -> StoreResult<Vec<JobId>> {
        let rows = self
            .reader()
            .fetch_all(stmt(
                "SELECT id FROM jobs WHERE state IN ('queued', 'running') ORDER BY id",
            ))
            .await?;
        rows.iter()
            .map(|row| {
                let id: i64 = row.try_get("id")?;
                JobId::try_from(id).map_err(|_| StoreError::Corrupt(format!("jobs: id {id}")))
            })
            .collect()
    }

    async fn begin_run(&self) -> StoreResult<PreviousRun> {
        let mut w = self.begin_write().await?;
        let clean = counter(&mut w, "clean_shutdown").await? != 0;
        let resuming = counter(&mut w, "resuming_job").await?;
        set_counter(&mut w, "clean_shutdown", 0).await?;
        self.finish_write(w, false).await?;
        drop_damaged_checkpoints(self).await?;
        Ok(PreviousRun {
            clean,
            resuming: u64::try_from(resuming).ok().filter(|&j| j > 0),
        })
    }

    async fn end_run(&self) -> StoreResult<()> {
        let mut w = self.begin_write().await?;
        set_counter(&mut w, "clean_shutdown", 1).await?;
        set_counter(&mut w, "resuming_job", 0).await?;
        self.finish_write(w, false).await
    }

    async fn record_resume(&self, job: JobId, count: bool) -> StoreResult<u32> {
        let key = i64::try_from(job).map_err(|_| StoreError::JobNotFound(job))?;
        let mut w = self.begin_write().await?;
        // The cast: PostgreSQL sums BIGINTs as NUMERIC.
        let sql = format!(
            "SELECT resumes, resume_passes, \
                 (SELECT CAST(COALESCE(SUM(merged_passes), 0) AS BIGINT) FROM tiles \
                     WHERE job = $1) AS merged \
             FROM jobs WHERE id = $1{}",
            B::DIALECT.for_update()
        );
        let row = w
            .fetch_optional(stmt(sql).bind(key))
            .await?
            .ok_or(StoreError::JobNotFound(job))?;
        let place = || format!("jobs row {job}");
        let resumes: u32 = int_col(&row, "resumes", &place)?;
        let before: i64 = row.try_get("resume_passes")?;
        let merged: i64 = row.try_get("merged")?;
        // Any change of the merged passes is progress (an adaptive job starts again from
        // its first pass after a restart, so its total can also go down).
        let resumes = if merged != before { 0 } else { resumes };
        let resumes = resumes.saturating_add(u32::from(count));
        w.execute(
            stmt("UPDATE jobs SET resumes = $2, resume_passes = $3 WHERE id = $1")
                .bind(key)
                .bind(i64::from(resumes))
                .bind(merged),
        )
        .await?;
        set_counter(&mut w, "resuming_job", key).await?;
        self.finish_write(w, false).await?;
        Ok(resumes)
    }

    async fn resumes_done(&self) -> StoreResult<()> {
        let mut w = self.begin_write().await?;
        set_counter(&mut w, "resuming_job", 0).await?;
        self.finish_write(w, false).await
    }

    async fn ping(&self) -> StoreResult<()> {
        self.reader().execute(stmt("SELECT 1")).await?;
        Ok(())
    }

    async fn close(&self) {
        self.close_pools().await;
    }
}
