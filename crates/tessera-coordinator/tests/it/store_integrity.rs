//! Store integrity on real SQLite files (docs/store.md, "Checksums" and "What is checked
//! at start"): a byte changed in a tile checkpoint or a job's settings is found on read,
//! by `store check` and at start, and never becomes a wrong image; a damaged index makes
//! the start refuse exactly as `store check` says; a store that lost its commit marker
//! and its `-wal` file is refused instead of issuing job ids again.

use std::path::Path;

use sqlx::Connection;
use tessera_api::{ImageFormat, ImageQuery, JobSettings, JobState};
use tessera_coordinator::service::{Coordinator, CoordinatorConfig};
use tessera_coordinator::store::{
    maintenance, marker, NewJob, SqliteStore, Store, StoreError, TileCheckpointRef, UnitDigest,
    DATABASE_FILE,
};
use tessera_farm::{FramePlan, JobId, PixelStats};

async fn open(dir: &Path) -> Coordinator {
    Coordinator::open(CoordinatorConfig::new(dir))
        .await
        .expect("the coordinator comes up")
}

fn small_job() -> JobSettings {
    let mut job = JobSettings::new("builtin:cornell-box");
    (job.width, job.height, job.spp) = (Some(16), Some(16), 4);
    job.seed = 3;
    job
}

async fn raw(dir: &Path) -> sqlx::SqliteConnection {
    sqlx::SqliteConnection::connect(&format!("sqlite://{}", dir.join(DATABASE_FILE).display()))
        .await
        .unwrap()
}

/// The value 0.2808 the probe saw change, as pixel 0's red mean of every checkpoint.
const RED: f64 = 0.2808;

/// Stores the checkpoint of tile 0 of a one-tile 16x16 `job` with its first `passes`
/// passes merged, as the coordinator would have, then closes the store (the WAL is
/// folded into the database file).
async fn checkpoint_passes(dir: &Path, job: JobId, passes: u32) {
    let store = SqliteStore::open(dir).await.unwrap();
    let pixel = PixelStats {
        passes,
        mean: [RED, 0.25, 0.125],
        m2: [0.0; 3],
        mean_lum: 0.25,
        m2_lum: 0.0,
    };
    let pixels = vec![pixel; 16 * 16];
    let units: Vec<UnitDigest> = (0..passes)
        .map(|p| UnitDigest {
            first_pass: p,
            pass_count: 1,
            digest: u64::from(p),
        })
        .collect();
    store
        .save_tile(TileCheckpointRef {
            job,
            frame: 0,
            tile: 0,
            merged_passes: passes,
            pixels: &pixels,
            units: &units,
            rejected_samples: 0,
            adaptive: None,
            bias: None,
        })
        .await
        .unwrap();
    store.close().await;
}

/// Flips the lowest bit of the byte of pixel 0's red mean that turns 0.2808 into another
/// finite value (the stored checksum is left as it was), behind the store.
async fn flip_checkpoint_byte(dir: &Path, job: JobId) {
    let mut c = raw(dir).await;
    let mut stats: Vec<u8> = sqlx::query_scalar("SELECT stats FROM tiles WHERE job = ?1")
        .bind(job as i64)
        .fetch_one(&mut c)
        .await
        .unwrap();
    // Header 5 bytes, passes 4 bytes, then mean[0]'s 8 bytes, little-endian.
    let at = 5 + 4 + 6;
    let before = f64::from_le_bytes(stats[9..17].try_into().unwrap());
    stats[at] ^= 0x01;
    let after = f64::from_le_bytes(stats[9..17].try_into().unwrap());
    assert!(before == RED && after.is_finite() && after != before);
    sqlx::query("UPDATE tiles SET stats = ?1 WHERE job = ?2")
        .bind(stats)
        .bind(job as i64)
        .execute(&mut c)
        .await
        .unwrap();
    c.close().await.unwrap();
}

/// A finished job's checkpoint with one byte changed: before, its EXR was served with the
/// pixel changed; now the read is refused naming the tile, `store check` lists the row
/// with what the coordinator does, and the coordinator still starts.
#[tokio::test]
async fn a_flipped_checkpoint_byte_of_a_finished_job_is_never_served() {
    let dir = tempfile::tempdir().unwrap();
    let core = open(dir.path()).await;
    let st = core.submit(small_job(), None).await.unwrap().0;
    let passes = u32::try_from(st.passes_planned).unwrap();
    drop(core);
    checkpoint_passes(dir.path(), st.id, passes).await;
    let exr = ImageQuery {
        format: ImageFormat::Exr,
        frame: None,
    };
    let core = open(dir.path()).await;
    assert_eq!(core.status(st.id).await.unwrap().state, JobState::Done);
    core.image(st.id, exr)
        .await
        .expect("the intact image is served");
    core.store().close().await;
    drop(core);

    flip_checkpoint_byte(dir.path(), st.id).await;
    let report = maintenance::check(dir.path()).await;
    assert!(report.healthy(), "{report}");
    assert!(!report.clean(), "{report}");
    let text = report.to_string();
    for needle in [
        format!("tiles job {}, frame 0, tile 0", st.id),
        "checksum".into(),
        "reads of this frame's image are refused".into(),
        "verdict: DAMAGED ROWS".into(),
    ] {
        assert!(text.contains(&needle), "{needle:?} missing from:\n{text}");
    }

    let core = open(dir.path()).await;
    let e = core
        .image(st.id, exr)
        .await
        .expect_err("no image from a damaged checkpoint");
    let msg = e.to_string();
    assert!(
        msg.contains(&format!("job {}, frame 0, tile 0", st.id)) && msg.contains("checksum"),
        "{msg}"
    );
    let direct = core.store().load_tiles(st.id, None).await.unwrap_err();
    assert!(
        matches!(direct, StoreError::CorruptTile { tile: 0, .. }),
        "{direct}"
    );
}

/// An unfinished job's checkpoint with one byte changed: `store check` says the start
/// drops it, and the start does, so the tile is rendered again instead of merging into
/// damaged statistics (or failing the job).
#[tokio::test]
async fn a_flipped_checkpoint_byte_of_a_running_job_is_dropped_and_rendered_again() {
    let dir = tempfile::tempdir().unwrap();
    let core = open(dir.path()).await;
    let st = core.submit(small_job(), None).await.unwrap().0;
    drop(core);
    checkpoint_passes(dir.path(), st.id, 2).await;
    flip_checkpoint_byte(dir.path(), st.id).await;

    let report = maintenance::check(dir.path()).await;
    let text = report.to_string();
    assert!(report.healthy() && !report.clean(), "{text}");
    assert!(
        text.contains("drops this checkpoint at its next start"),
        "{text}"
    );

    let core = open(dir.path()).await;
    let s = core.status(st.id).await.unwrap();
    assert_eq!(s.state, JobState::Queued, "{:?}", s.error);
    assert_eq!(s.passes_done, 0, "the damaged passes are not merged");
    assert!(core
        .store()
        .load_tiles(st.id, None)
        .await
        .unwrap()
        .is_empty());
    core.store().close().await;
    drop(core);
    let report = maintenance::check(dir.path()).await;
    assert!(report.clean(), "{report}");
}

/// A job's settings changed behind the store (seed 3 to 7): found by the row's checksum
/// on read, by `store check`, and the start fails that job alone with the reason.
#[tokio::test]
async fn flipped_settings_are_found() {
    let dir = tempfile::tempdir().unwrap();
    let core = open(dir.path()).await;
    let bad = core.submit(small_job(), None).await.unwrap().0.id;
    let good = core.submit(small_job(), None).await.unwrap().0.id;
    core.store().close().await;
    drop(core);
    let mut c = raw(dir.path()).await;
    let n = sqlx::query(
        "UPDATE jobs SET settings_json = replace(settings_json, '\"seed\":3', '\"seed\":7') \
         WHERE id = ?1",
    )
    .bind(bad as i64)
    .execute(&mut c)
    .await
    .unwrap()
    .rows_affected();
    assert_eq!(n, 1);
    let settings: String = sqlx::query_scalar("SELECT settings_json FROM jobs WHERE id = ?1")
        .bind(bad as i64)
        .fetch_one(&mut c)
        .await
        .unwrap();
    assert!(settings.contains("\"seed\":7"), "{settings}");
    c.close().await.unwrap();

    let store = SqliteStore::open(dir.path()).await.unwrap();
    let e = store.get_job(bad).await.unwrap_err();
    assert!(
        matches!(&e, StoreError::Corrupt(m) if m.contains(&format!("jobs row {bad}")) && m.contains("checksum")),
        "{e}"
    );
    assert!(store.get_job(good).await.unwrap().is_some());
    store.close().await;

    let report = maintenance::check(dir.path()).await;
    let text = report.to_string();
    assert!(report.healthy() && !report.clean(), "{text}");
    assert!(
        text.contains(&format!("jobs job {bad}:")) && text.contains("fails this job"),
        "{text}"
    );

    let core = open(dir.path()).await;
    let mut c = raw(dir.path()).await;
    let (state, error): (String, Option<String>) =
        sqlx::query_as("SELECT state, error FROM jobs WHERE id = ?1")
            .bind(bad as i64)
            .fetch_one(&mut c)
            .await
            .unwrap();
    assert_eq!(state, "failed");
    assert!(error.unwrap_or_default().contains("checksum"));
    assert_eq!(core.status(good).await.unwrap().state, JobState::Queued);
}

/// An index that lost an entry (a byte flipped in an index page): `quick_check` passes,
/// so the coordinator used to start and answer 500s while `store check` said it would
/// refuse. Now both run the same checks: the start refuses with the message the check
/// prints, and `tessera store reindex` repairs it.
#[tokio::test]
async fn a_damaged_index_is_refused_by_start_and_check_alike() {
    let dir = tempfile::tempdir().unwrap();
    let core = open(dir.path()).await;
    for _ in 0..3 {
        core.submit(small_job(), None).await.unwrap();
    }
    core.store().close().await;
    drop(core);

    // The index jobs_by_state (state, id) is one leaf page: change `queued` in its first
    // entry found; the table keeps its own copy of the state.
    let mut c = raw(dir.path()).await;
    let (root, page_size): (i64, i64) = (
        sqlx::query_scalar("SELECT rootpage FROM sqlite_master WHERE name = 'jobs_by_state'")
            .fetch_one(&mut c)
            .await
            .unwrap(),
        sqlx::query_scalar("PRAGMA page_size")
            .fetch_one(&mut c)
            .await
            .unwrap(),
    );
    c.close().await.unwrap();
    let file = dir.path().join(DATABASE_FILE);
    let mut bytes = std::fs::read(&file).unwrap();
    let page = usize::try_from((root - 1) * page_size).unwrap()
        ..usize::try_from(root * page_size).unwrap();
    let at = bytes[page.clone()]
        .windows(6)
        .position(|w| w == b"queued")
        .expect("the index page holds the state")
        + page.start;
    bytes[at + 2] = b'x';
    std::fs::write(&file, &bytes).unwrap();

    let report = maintenance::check(dir.path()).await;
    let refused = SqliteStore::open(dir.path())
        .await
        .expect_err("the start refuses a damaged index");
    assert!(matches!(refused, StoreError::Damaged { .. }), "{refused}");
    assert_eq!(
        report.refusal.as_deref(),
        Some(&*refused.to_string()),
        "{report}"
    );
    let msg = refused.to_string();
    assert!(
        msg.contains("jobs_by_state") && msg.contains("tessera store reindex"),
        "{msg}"
    );
    assert!(Coordinator::open(CoordinatorConfig::new(dir.path()))
        .await
        .is_err());

    let report = maintenance::reindex(dir.path()).await.unwrap();
    assert!(report.clean(), "{report}");
    let core = open(dir.path()).await;
    assert_eq!(core.store().count_jobs_by_state().await.unwrap().len(), 1);
}

fn new_job() -> NewJob {
    NewJob {
        settings_json: "{}".into(),
        plan: FramePlan::new(16, 16, 16, 1, 4).unwrap(),
        frames: tessera_api::FrameRange { start: 0, end: 0 },
        passes_per_unit: 1,
        priority: 0,
        scene_ref: "builtin:cornell-box".into(),
        name: None,
        idempotency_key: None,
        created_unix_ms: 1,
        render_plan_json: None,
        error_estimate_caveat: None,
    }
}

/// The commit marker and the `-wal` file deleted together: the database file alone used
/// to open as an older store and issue job id 1 again. The database file itself now
/// carries a commit generation, so a missing marker is refused, by the start and by
/// `store check` with the same message; and lease reservations are in the marker too.
#[tokio::test]
async fn a_deleted_marker_and_wal_are_refused_and_ids_never_repeat() {
    let dir = tempfile::tempdir().unwrap();
    let store = SqliteStore::open(dir.path()).await.unwrap();
    let mut ids = Vec::new();
    for _ in 0..3 {
        ids.push(store.insert_job(new_job()).await.unwrap().0);
    }
    store.record_lease_high_water(4096).await.unwrap();
    let m = marker::read_marker(dir.path()).unwrap().unwrap();
    assert_eq!((m.max_job_id, m.lease_high_water), (3, 4096));

    // What is left when the marker and the WAL are deleted while the store is open (the
    // coordinator killed): the database file alone.
    let lost = tempfile::tempdir().unwrap();
    std::fs::copy(
        dir.path().join(DATABASE_FILE),
        lost.path().join(DATABASE_FILE),
    )
    .unwrap();
    // And the WAL alone deleted: behind the marker, as before; the lease ids too.
    let wal_only = tempfile::tempdir().unwrap();
    for f in [DATABASE_FILE, marker::MARKER_FILE] {
        std::fs::copy(dir.path().join(f), wal_only.path().join(f)).unwrap();
    }
    store.close().await;

    let refused = SqliteStore::open(lost.path())
        .await
        .expect_err("a store without its marker is refused");
    assert!(
        matches!(refused, StoreError::MarkerMissing { .. }),
        "{refused}"
    );
    let msg = refused.to_string();
    assert!(
        msg.contains("tessera.commit-marker") && msg.contains("is missing"),
        "{msg}"
    );
    let report = maintenance::check(lost.path()).await;
    assert_eq!(report.refusal.as_deref(), Some(&*msg), "{report}");
    assert!(!report.healthy());

    let refused = SqliteStore::open(wal_only.path()).await.err().unwrap();
    match &refused {
        StoreError::BehindMarker {
            database, marker, ..
        } => {
            assert_eq!(marker.lease_high_water, 4096);
            assert!(database.max_job_id < 3, "{refused}");
        }
        other => panic!("expected BehindMarker, got {other}"),
    }

    // Accepting the loss keeps ids above what the marker recorded: no job id repeats.
    maintenance::accept_loss(wal_only.path()).await.unwrap();
    let store = SqliteStore::open(wal_only.path()).await.unwrap();
    let (id, _) = store.insert_job(new_job()).await.unwrap();
    assert!(id > 3, "job id {id} issued again");
    assert!(store.max_lease_id().await.unwrap() >= 4096);
    store.close().await;
}
