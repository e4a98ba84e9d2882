//! No crash loop: the coordinator always comes up. A job that crashed the
//! coordinator at every start ends failed after a bounded number of restarts, with the
//! reason in its status; a job that cannot be resumed fails alone instead of stopping the
//! start. A crash is simulated by dropping the coordinator without the graceful end that
//! `serve` records (docs/store.md, "No crash loop").

use std::path::Path;

use sqlx::Connection;
use tessera_api::{JobSettings, JobState};
use tessera_coordinator::service::{Coordinator, CoordinatorConfig};
use tessera_coordinator::store::{
    TileCheckpointRef, UnitDigest, DATABASE_FILE, MAX_RESUMES_WITHOUT_PROGRESS,
};
use tessera_farm::{JobId, PixelStats};

async fn open(dir: &Path) -> Coordinator {
    Coordinator::open(CoordinatorConfig::new(dir))
        .await
        .expect("the coordinator comes up")
}

fn small_job(scene: &str) -> JobSettings {
    let mut job = JobSettings::new(scene);
    (job.width, job.height, job.spp) = (Some(16), Some(16), 4);
    job
}

async fn raw(dir: &Path) -> sqlx::SqliteConnection {
    sqlx::SqliteConnection::connect(&format!("sqlite://{}", dir.join(DATABASE_FILE).display()))
        .await
        .unwrap()
}

async fn sql(dir: &Path, statement: &str) {
    let mut c = raw(dir).await;
    sqlx::query(statement).execute(&mut c).await.unwrap();
    c.close().await.unwrap();
}

/// (state, error, resumes) of a job, read from the database itself.
async fn stored(dir: &Path, job: JobId) -> (String, Option<String>, i64) {
    let mut c = raw(dir).await;
    let row: (String, Option<String>, i64) =
        sqlx::query_as("SELECT state, error, resumes FROM jobs WHERE id = ?1")
            .bind(job as i64)
            .fetch_one(&mut c)
            .await
            .unwrap();
    c.close().await.unwrap();
    row
}

/// Stores the checkpoint of tile 0 of a one-tile 16x16 `job` with its first `passes`
/// passes merged, one unit per pass, as the coordinator would have before a crash.
async fn checkpoint_passes(dir: &Path, job: JobId, passes: u32) {
    let store = tessera_coordinator::store::SqliteStore::open(dir)
        .await
        .unwrap();
    let pixels = vec![PixelStats::default(); 16 * 16];
    let units: Vec<UnitDigest> = (0..passes)
        .map(|p| UnitDigest {
            first_pass: p,
            pass_count: 1,
            digest: u64::from(p),
        })
        .collect();
    tessera_coordinator::store::Store::save_tile(
        &store,
        TileCheckpointRef {
            job,
            frame: 0,
            tile: 0,
            merged_passes: passes,
            pixels: &pixels,
            units: &units,
            rejected_samples: 0,
            adaptive: None,
            bias: None,
        },
    )
    .await
    .unwrap();
    tessera_coordinator::store::Store::close(&store).await;
}

#[tokio::test]
async fn a_job_that_crashes_every_start_ends_failed_and_the_coordinator_comes_up() {
    let dir = tempfile::tempdir().unwrap();
    let core = open(dir.path()).await;
    let (a, _) = core
        .submit(small_job("builtin:cornell-box"), None)
        .await
        .unwrap();
    let (b, _) = core
        .submit(small_job("builtin:furnace"), None)
        .await
        .unwrap();
    let (a, b) = (a.id, b.id);
    drop(core); // crash

    // Every start dies while resuming job a (the store says so: resuming_job = a). Only a
    // is counted; b, resumed before it or after it, is not blamed.
    let limit = i64::from(MAX_RESUMES_WITHOUT_PROGRESS);
    for start in 1..=limit {
        sql(
            dir.path(),
            &format!("UPDATE counters SET value = {a} WHERE name = 'resuming_job'"),
        )
        .await;
        let core = open(dir.path()).await;
        assert_eq!(core.status(a).await.unwrap().state, JobState::Queued);
        drop(core);
        assert_eq!(stored(dir.path(), a).await.2, start);
        assert_eq!(stored(dir.path(), b).await.2, 0);
    }
    sql(
        dir.path(),
        &format!("UPDATE counters SET value = {a} WHERE name = 'resuming_job'"),
    )
    .await;
    let core = open(dir.path()).await;
    let s = core.status(a).await.unwrap();
    assert_eq!(s.state, JobState::Failed);
    let reason = s.error.unwrap_or_default();
    assert!(
        reason.contains(&format!("restarted {} times", limit + 1)) && reason.contains("progress"),
        "{reason}"
    );
    assert_eq!(core.status(b).await.unwrap().state, JobState::Queued);

    // A graceful end counts nothing.
    core.store().end_run().await.unwrap();
    drop(core);
    let core = open(dir.path()).await;
    drop(core); // a crash after the start: every unfinished job is counted once
    assert_eq!(stored(dir.path(), b).await.2, 0);
    let core = open(dir.path()).await;
    drop(core);
    assert_eq!(stored(dir.path(), b).await.2, 1);

    // Progress (a merged pass since the previous resume) starts the count again.
    checkpoint_passes(dir.path(), b, 1).await;
    let core = open(dir.path()).await;
    drop(core);
    assert_eq!(
        stored(dir.path(), b).await.2,
        1,
        "progress resets the count"
    );
    let (state, _, _) = stored(dir.path(), b).await;
    assert_eq!(state, "queued");
}

#[tokio::test]
async fn jobs_that_cannot_be_resumed_fail_alone_and_the_coordinator_starts() {
    let dir = tempfile::tempdir().unwrap();
    let core = open(dir.path()).await;
    let gltf = std::fs::read(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../scenes/cornell-box.gltf"
    ))
    .unwrap();
    let scene = core.upload_scene(gltf).await.unwrap();
    let mut ids = Vec::new();
    for s in [
        "builtin:cornell-box",
        &scene.hash,
        "builtin:cornell-box",
        "builtin:furnace",
    ] {
        ids.push(core.submit(small_job(s), None).await.unwrap().0.id);
    }
    core.store().end_run().await.unwrap();
    drop(core);
    let [bad_plan, missing_scene, unreadable, good] = ids[..] else {
        unreachable!()
    };
    sql(
        dir.path(),
        &format!("UPDATE jobs SET plan_tile_size = 0 WHERE id = {bad_plan}"),
    )
    .await;
    sql(dir.path(), "DELETE FROM scenes").await;
    sql(
        dir.path(),
        &format!("UPDATE jobs SET settings_json = '{{' WHERE id = {unreadable}"),
    )
    .await;

    let core = open(dir.path()).await;
    for (job, needle) in [
        (bad_plan, "invalid plan"),
        (missing_scene, "missing from the store"),
        // Caught by the row's checksum before the settings are parsed.
        (unreadable, "does not match its checksum"),
    ] {
        let (state, error, _) = stored(dir.path(), job).await;
        let error = error.unwrap_or_default();
        assert_eq!(state, "failed", "job {job}: {error}");
        assert!(error.contains(needle), "job {job}: {error}");
    }
    assert_eq!(core.status(good).await.unwrap().state, JobState::Queued);
}

/// A crash between a job's last checkpoint and its `done` state leaves a job whose every
/// pass is merged and stored but whose state says `running`: no result will ever come to
/// finish it, so the next start marks it done (`Coordinator::finish_complete_jobs`).
#[tokio::test]
async fn a_job_complete_in_the_store_is_done_after_a_restart() {
    let dir = tempfile::tempdir().unwrap();
    let core = open(dir.path()).await;
    let st = core
        .submit(small_job("builtin:cornell-box"), None)
        .await
        .unwrap()
        .0;
    assert_eq!(st.tiles_total, 1, "a 16x16 job is one tile");
    let passes = u32::try_from(st.passes_planned).unwrap();
    drop(core); // crash

    checkpoint_passes(dir.path(), st.id, passes).await;
    sql(
        dir.path(),
        &format!("UPDATE jobs SET state = 'running' WHERE id = {}", st.id),
    )
    .await;

    let core = open(dir.path()).await;
    let s = core.status(st.id).await.unwrap();
    assert_eq!(s.state, JobState::Done, "{:?}", s.error);
    assert_eq!(s.passes_done, s.passes_planned);
    assert_eq!(stored(dir.path(), st.id).await.0, "done");
}
