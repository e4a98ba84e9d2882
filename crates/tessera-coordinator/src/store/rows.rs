//! Reading stored rows back into records, and checking inputs before they are written:
//! the rules both store implementations ([`SqliteStore`](super::SqliteStore) and
//! [`PostgresStore`](super::PostgresStore)) share, so they cannot drift apart.
//!
//! Both schemas store every integer as a 64-bit signed column and every string as text,
//! so a [`Row`] of either database decodes the same Rust types.

use tessera_api::{FrameRange, JobState};
use tessera_farm::{FramePlan, JobId};

use super::checksum::{verify, JobSum, TileSum};
use super::sql::Row;
use super::{FaultEvent, FaultKind, JobRecord, NewJob, QuarantineRecord, StoreError, StoreResult};

/// Columns of `jobs` read by [`job_from_row`], in its order (the same in both schemas).
pub(super) const JOB_COLUMNS: &str = "id, idempotency_key, name, scene_ref, settings_json, \
     plan_width, plan_height, plan_tile_size, plan_samples_per_pass, plan_passes, \
     first_frame, last_frame, passes_per_unit, priority, state, error, \
     created_unix_ms, started_unix_ms, finished_unix_ms, render_plan_json, \
     error_estimate_caveat, error_estimator, checksum";

/// [`JOB_COLUMNS`] as they were before schema version 9 (PostgreSQL 8) added
/// `error_estimator`: what a migration run before that one (the checksums' backfill) can
/// select.
pub(super) const JOB_COLUMNS_BEFORE_ESTIMATOR: &str = "id, idempotency_key, name, scene_ref, \
     settings_json, plan_width, plan_height, plan_tile_size, plan_samples_per_pass, \
     plan_passes, first_frame, last_frame, passes_per_unit, priority, state, error, \
     created_unix_ms, started_unix_ms, finished_unix_ms, render_plan_json, \
     error_estimate_caveat, checksum";

/// Columns of `jobs` read by [`plan_from_row`].
pub(super) const PLAN_COLUMNS: &str = "plan_width, plan_height, plan_tile_size, \
     plan_samples_per_pass, plan_passes, first_frame, last_frame";

/// Unix milliseconds now, as stored.
pub(super) fn now_unix_ms() -> i64 {
    use std::time::{SystemTime, UNIX_EPOCH};
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| i64::try_from(d.as_millis()).unwrap_or(i64::MAX))
}

/// A u64 to bind as a 64-bit integer, refused above `i64::MAX`.
pub(super) fn to_i64(v: u64, what: &str) -> StoreResult<i64> {
    i64::try_from(v).map_err(|_| StoreError::InvalidInput(format!("{what} {v} exceeds 2^63 - 1")))
}

/// Reads an integer column and converts it, reporting a stored value out of range as
/// corrupt (`place` names the row).
pub(super) fn int_col<T: TryFrom<i64>>(
    row: &Row,
    col: &str,
    place: &dyn Fn() -> String,
) -> StoreResult<T> {
    let v = row.try_get::<i64>(col)?;
    T::try_from(v)
        .map_err(|_| StoreError::Corrupt(format!("{}: {col} = {v} is out of range", place())))
}

/// [`int_col`] of a nullable column.
pub(super) fn opt_int_col<T: TryFrom<i64>>(
    row: &Row,
    col: &str,
    place: &dyn Fn() -> String,
) -> StoreResult<Option<T>> {
    row.try_get::<Option<i64>>(col)?
        .map(|v| {
            T::try_from(v).map_err(|_| {
                StoreError::Corrupt(format!("{}: {col} = {v} is out of range", place()))
            })
        })
        .transpose()
}

/// The plan and frame range of a job row ([`PLAN_COLUMNS`]), checked.
pub(super) fn plan_from_row(row: &Row, job: JobId) -> StoreResult<(FramePlan, FrameRange)> {
    let place = || format!("jobs row {job}");
    let plan = FramePlan::new(
        int_col(row, "plan_width", &place)?,
        int_col(row, "plan_height", &place)?,
        int_col(row, "plan_tile_size", &place)?,
        int_col(row, "plan_samples_per_pass", &place)?,
        int_col(row, "plan_passes", &place)?,
    )
    .map_err(|e| StoreError::Corrupt(format!("{}: invalid plan: {e}", place())))?;
    let frames = FrameRange {
        start: int_col(row, "first_frame", &place)?,
        end: int_col(row, "last_frame", &place)?,
    };
    if frames.start > frames.end {
        return Err(StoreError::Corrupt(format!(
            "{}: first_frame {} > last_frame {}",
            place(),
            frames.start,
            frames.end
        )));
    }
    Ok((plan, frames))
}

/// Parses a stored job state.
pub(super) fn parse_state(s: &str) -> Option<JobState> {
    [
        JobState::Queued,
        JobState::Running,
        JobState::Done,
        JobState::Failed,
        JobState::Canceled,
    ]
    .into_iter()
    .find(|st| st.as_str() == s)
}

/// One row of `SELECT state, COUNT(*) AS n FROM jobs GROUP BY state`.
pub(super) fn state_count_from_row(row: &Row) -> StoreResult<(JobState, u64)> {
    let state = row.try_get::<String>("state")?;
    let n = row.try_get::<i64>("n")?;
    let state = parse_state(&state)
        .ok_or_else(|| StoreError::Corrupt(format!("jobs: unknown state {state:?}")))?;
    Ok((state, n.max(0) as u64))
}

/// A job row ([`JOB_COLUMNS`]), checked: decoded, then compared with its checksum
/// ([`StoreError::Corrupt`] naming the row if it differs).
pub(super) fn job_from_row(row: &Row) -> StoreResult<JobRecord> {
    let job = decode_job(row)?;
    let stored: Option<Vec<u8>> = row.try_get("checksum")?;
    verify(stored.as_deref(), &JobSum::from(&job).checksum())
        .map_err(|reason| StoreError::Corrupt(format!("jobs row {}: {reason}", job.id)))?;
    Ok(job)
}

/// A job row ([`JOB_COLUMNS`]) decoded and checked, without its checksum (to compute it).
pub(super) fn decode_job(row: &Row) -> StoreResult<JobRecord> {
    let id: JobId = int_col(row, "id", &|| "jobs row".to_string())?;
    let place = || format!("jobs row {id}");
    let (plan, frames) = plan_from_row(row, id)?;
    let state = row.try_get::<String>("state")?;
    let state = parse_state(&state)
        .ok_or_else(|| StoreError::Corrupt(format!("{}: unknown state {state:?}", place())))?;
    let passes_per_unit: u32 = int_col(row, "passes_per_unit", &place)?;
    if passes_per_unit == 0 {
        return Err(StoreError::Corrupt(format!(
            "{}: passes_per_unit is 0",
            place()
        )));
    }
    Ok(JobRecord {
        id,
        settings_json: row.try_get("settings_json")?,
        plan,
        frames,
        passes_per_unit,
        priority: int_col(row, "priority", &place)?,
        scene_ref: row.try_get("scene_ref")?,
        name: row.try_get("name")?,
        idempotency_key: row.try_get("idempotency_key")?,
        state,
        error: row.try_get("error")?,
        created_unix_ms: int_col(row, "created_unix_ms", &place)?,
        started_unix_ms: opt_int_col(row, "started_unix_ms", &place)?,
        finished_unix_ms: opt_int_col(row, "finished_unix_ms", &place)?,
        render_plan_json: row.try_get("render_plan_json")?,
        error_estimate_caveat: row.try_get("error_estimate_caveat")?,
        // Not selected by the checksums' backfill (`JOB_COLUMNS_BEFORE_ESTIMATOR`), which
        // runs before schema version 9 (PostgreSQL 8) adds the column.
        error_estimator: match row.try_get::<Option<String>>("error_estimator") {
            Err(sqlx::Error::ColumnNotFound(_)) => None,
            other => other?,
        },
    })
}

/// A `faults` row (`worker, job, kind, message, unix_ms`), checked.
pub(super) fn fault_from_row(row: &Row) -> StoreResult<FaultEvent> {
    let place = || "faults row".to_string();
    let kind = row.try_get::<String>("kind")?;
    Ok(FaultEvent {
        worker: row.try_get("worker")?,
        job: opt_int_col(row, "job", &place)?,
        kind: FaultKind::parse(&kind)
            .ok_or_else(|| StoreError::Corrupt(format!("faults row: unknown kind {kind:?}")))?,
        message: row.try_get("message")?,
        unix_ms: int_col(row, "unix_ms", &place)?,
    })
}

/// Columns of `quarantines` read by [`quarantine_from_row`], in its order.
pub(super) const QUARANTINE_COLUMNS: &str = "worker, identity, reason, unix_ms";

/// A stored quarantine's identity column: `''` stands for none, since a primary key
/// column cannot hold `NULL` in both schemas.
pub(super) fn identity_col(identity: Option<&str>) -> &str {
    identity.unwrap_or("")
}

/// A row of `quarantines` ([`QUARANTINE_COLUMNS`]) as a record.
pub(super) fn quarantine_from_row(row: &Row) -> StoreResult<QuarantineRecord> {
    let worker = row.try_get::<String>("worker")?;
    let place = || format!("quarantines row of worker {worker:?}");
    let identity = row.try_get::<String>("identity")?;
    Ok(QuarantineRecord {
        identity: (!identity.is_empty()).then_some(identity),
        reason: row.try_get("reason")?,
        unix_ms: int_col(row, "unix_ms", &place)?,
        worker,
    })
}

/// Refuses a finite-only value that is not finite.
pub(super) fn check_finite(v: f64, what: &str) -> StoreResult<f64> {
    if v.is_finite() {
        Ok(v)
    } else {
        Err(StoreError::InvalidInput(format!(
            "{what} must be finite, got {v}"
        )))
    }
}

/// Checks a job before it is inserted ([`Store::insert_job`](super::Store::insert_job)):
/// a valid plan, `frames.start <= frames.end`, at least one pass per unit. Returns the
/// creation time as stored.
pub(super) fn check_new_job(job: &NewJob) -> StoreResult<i64> {
    job.plan
        .validate()
        .map_err(|e| StoreError::InvalidInput(format!("job plan: {e}")))?;
    if job.frames.start > job.frames.end {
        return Err(StoreError::InvalidInput(format!(
            "job frames: start {} > end {}",
            job.frames.start, job.frames.end
        )));
    }
    if job.passes_per_unit == 0 {
        return Err(StoreError::InvalidInput(
            "job passes_per_unit must be at least 1".into(),
        ));
    }
    to_i64(job.created_unix_ms, "created_unix_ms")
}

/// The `WHERE` clause of a fault filter, with the placeholders `$1`, `$2`, ..., and the
/// values to bind in order: the job id (if filtered), then the worker name (if filtered).
pub(super) fn fault_where(filter: &super::FaultFilter) -> StoreResult<(String, Option<i64>)> {
    let p = |i: usize| format!("${i}");
    let mut clauses = Vec::new();
    let job = filter.job.map(|j| to_i64(j, "job id")).transpose()?;
    if job.is_some() {
        clauses.push(format!("job = {}", p(clauses.len() + 1)));
    }
    if filter.worker.is_some() {
        clauses.push(format!("worker = {}", p(clauses.len() + 1)));
    }
    let sql = if clauses.is_empty() {
        String::new()
    } else {
        format!("WHERE {}", clauses.join(" AND "))
    };
    Ok((sql, job))
}

/// The checks of [`check_checkpoint`](super::codec::check_checkpoint) on a tile to save,
/// as [`StoreError::InvalidInput`] naming the tile.
pub(super) fn check_tile_to_save(
    plan: &FramePlan,
    frames: FrameRange,
    t: &super::TileCheckpointRef<'_>,
) -> StoreResult<()> {
    super::codec::check_checkpoint(
        plan,
        frames,
        t.frame,
        t.tile,
        t.merged_passes,
        t.pixels,
        t.units,
    )
    .and_then(|()| match t.adaptive {
        Some(a) => super::codec::check_adaptive(plan, t.tile, a),
        None => Ok(()),
    })
    .map_err(|reason| {
        StoreError::InvalidInput(format!(
            "checkpoint of job {}, frame {}, tile {}: {reason}",
            t.job, t.frame, t.tile
        ))
    })
}

/// Decodes and checks a stored tile checkpoint's columns against its job's plan, then
/// against the row's checksum ([`StoreError::CorruptTile`] naming the tile). `row` has
/// the columns `job, frame, tile, merged_passes, rejected_samples, checksum`.
pub(super) fn tile_from_parts(
    plan: &FramePlan,
    frames: FrameRange,
    job: JobId,
    row: &Row,
    stats: &[u8],
    units: &[u8],
    adaptive: Option<&[u8]>,
) -> StoreResult<super::TileCheckpoint> {
    use super::codec::{
        check_adaptive, check_bias, check_checkpoint, decode_adaptive, decode_stats, decode_units,
    };
    let place = || format!("tiles of job {job}");
    let frame: u32 = int_col(row, "frame", &place)?;
    let tile: u32 = int_col(row, "tile", &place)?;
    let corrupt = |reason: String| StoreError::CorruptTile {
        job,
        frame,
        tile,
        reason,
    };
    let merged_passes: u32 = int_col(row, "merged_passes", &place)?;
    let rejected_samples: u64 = int_col(row, "rejected_samples", &place)?;
    let (pixels, bias) = decode_stats(stats).map_err(corrupt)?;
    if let Some(b) = &bias {
        check_bias(&pixels, b).map_err(corrupt)?;
    }
    let unit_blob = units;
    let units = decode_units(units).map_err(corrupt)?;
    check_checkpoint(plan, frames, frame, tile, merged_passes, &pixels, &units).map_err(corrupt)?;
    let blob = adaptive;
    let adaptive = adaptive
        .map(|blob| {
            let a = decode_adaptive(blob)?;
            check_adaptive(plan, tile, &a)?;
            Ok(a)
        })
        .transpose()
        .map_err(corrupt)?;
    let sum = TileSum {
        job: row.try_get("job")?,
        frame: i64::from(frame),
        tile: i64::from(tile),
        merged_passes: i64::from(merged_passes),
        rejected_samples: row.try_get("rejected_samples")?,
        stats,
        units: unit_blob,
        adaptive: blob,
    };
    let stored: Option<Vec<u8>> = row.try_get("checksum")?;
    verify(stored.as_deref(), &sum.checksum()).map_err(corrupt)?;
    Ok(super::TileCheckpoint {
        job,
        frame,
        tile,
        merged_passes,
        pixels,
        units,
        rejected_samples,
        adaptive,
        bias,
    })
}

/// A `tiles` summary row (`frame, tile, merged_passes, rejected_samples`).
pub(super) fn summary_from_row(row: &Row, job: JobId) -> StoreResult<super::TileSummary> {
    let place = || format!("tiles of job {job}");
    Ok(super::TileSummary {
        frame: int_col(row, "frame", &place)?,
        tile: int_col(row, "tile", &place)?,
        merged_passes: int_col(row, "merged_passes", &place)?,
        rejected_samples: int_col(row, "rejected_samples", &place)?,
    })
}
