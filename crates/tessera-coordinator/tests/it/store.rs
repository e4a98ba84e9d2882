//! The store suite: every test body is a function of a [`Fixture`] (a fresh, empty store
//! and the means to reopen it and to reach its tables directly), run once against SQLite
//! files in temporary directories and once against a real PostgreSQL server
//! (`TESSERA_TEST_POSTGRES`, a fresh schema per test; skipped when unset unless
//! `TESSERA_REQUIRE_POSTGRES=1`, see `tessera_testkit::postgres`). The tests
//! `store::NAME::sqlite` and `store::NAME::postgres` run the body `NAME`.

use std::path::Path;
use std::sync::Arc;

use sqlx::Connection;
use tessera_api::{FrameRange, HistoryPoint, JobState};
use tessera_coordinator::store::{
    self, FaultEvent, FaultFilter, FaultKind, JobOrder, JobQuery, NewJob, PostgresStore,
    QuarantineRecord, SqliteStore, Store, StoreError, StoreUrl, TileCheckpoint, UnitDigest,
    DATABASE_FILE,
};
use tessera_farm::{
    AdaptivePixel, AdaptiveTileCheckpoint, BiasStats, FramePlan, JobId, PixelStats,
};

use tessera_testkit::postgres;

/// A fresh, empty store of one backend.
enum Fixture {
    /// A data directory.
    Sqlite(tempfile::TempDir),
    /// The URL of a fresh schema.
    Postgres(String),
}

impl Fixture {
    async fn sqlite() -> Self {
        Self::Sqlite(tempfile::tempdir().unwrap())
    }

    /// `None` when PostgreSQL tests are skipped.
    async fn postgres(test: &str) -> Option<Self> {
        postgres::fresh_database(test).await.map(Self::Postgres)
    }

    fn url(&self) -> StoreUrl {
        match self {
            Self::Sqlite(dir) => StoreUrl::Sqlite(dir.path().to_path_buf()),
            Self::Postgres(url) => StoreUrl::Postgres(url.clone()),
        }
    }

    /// Opens (or reopens) the store.
    async fn open(&self) -> Arc<dyn Store> {
        store::open(&self.url()).await.unwrap()
    }

    async fn try_open(&self) -> Result<Arc<dyn Store>, StoreError> {
        store::open(&self.url()).await
    }

    /// The newest schema version this build migrates the backend to.
    /// The schema version that added row checksums.
    fn checksum_schema(&self) -> i64 {
        match self {
            Self::Sqlite(_) => 7,
            Self::Postgres(_) => 6,
        }
    }

    fn supported_schema(&self) -> i64 {
        match self {
            Self::Sqlite(_) => SqliteStore::SUPPORTED_SCHEMA,
            Self::Postgres(_) => PostgresStore::SUPPORTED_SCHEMA,
        }
    }

    /// Runs SQL statements (no parameters) on a connection of its own, behind the store.
    async fn exec(&self, sql: &str) {
        match self {
            Self::Sqlite(dir) => {
                let mut c = sqlite_conn(dir.path()).await;
                sqlx::raw_sql(sql).execute(&mut c).await.unwrap();
            }
            Self::Postgres(url) => {
                let mut c = sqlx::PgConnection::connect(url).await.unwrap();
                sqlx::raw_sql(sql).execute(&mut c).await.unwrap();
            }
        }
    }

    /// The single value of `SELECT {col} FROM {table}` as bytes (a blob column).
    async fn blob(&self, table: &str, col: &str) -> Vec<u8> {
        let sql = format!("SELECT {col} FROM {table}");
        match self {
            Self::Sqlite(dir) => {
                let mut c = sqlite_conn(dir.path()).await;
                sqlx::query_scalar(&sql).fetch_one(&mut c).await.unwrap()
            }
            Self::Postgres(url) => {
                let mut c = sqlx::PgConnection::connect(url).await.unwrap();
                sqlx::query_scalar(&sql).fetch_one(&mut c).await.unwrap()
            }
        }
    }

    /// `UPDATE {table} SET {col} = blob` (every row).
    async fn set_blob(&self, table: &str, col: &str, blob: Vec<u8>) {
        match self {
            Self::Sqlite(dir) => {
                let mut c = sqlite_conn(dir.path()).await;
                sqlx::query(&format!("UPDATE {table} SET {col} = ?1"))
                    .bind(blob)
                    .execute(&mut c)
                    .await
                    .unwrap();
            }
            Self::Postgres(url) => {
                let mut c = sqlx::PgConnection::connect(url).await.unwrap();
                sqlx::query(&format!("UPDATE {table} SET {col} = $1"))
                    .bind(blob)
                    .execute(&mut c)
                    .await
                    .unwrap();
            }
        }
    }

    /// The schema version recorded in the database.
    async fn schema_version(&self) -> i64 {
        let sql = "SELECT MAX(version) FROM schema_version";
        let v: Option<i64> = match self {
            Self::Sqlite(dir) => {
                let mut c = sqlite_conn(dir.path()).await;
                sqlx::query_scalar(sql).fetch_one(&mut c).await.unwrap()
            }
            Self::Postgres(url) => {
                let mut c = sqlx::PgConnection::connect(url).await.unwrap();
                sqlx::query_scalar(sql).fetch_one(&mut c).await.unwrap()
            }
        };
        v.unwrap_or(0)
    }

    /// SQLite's full integrity check of the file; PostgreSQL checks its own pages.
    async fn integrity_check(&self) {
        if let Self::Sqlite(dir) = self {
            let mut c = sqlite_conn(dir.path()).await;
            let r: Vec<String> = sqlx::query_scalar("PRAGMA integrity_check")
                .fetch_all(&mut c)
                .await
                .unwrap();
            assert_eq!(r, ["ok"]);
        }
    }
}

/// Runs each named test body `NAME(&Fixture)` as the tests `NAME::sqlite` and
/// `NAME::postgres`.
macro_rules! both_backends {
    ($($name:ident),* $(,)?) => {
        $(
            mod $name {
                #[tokio::test]
                async fn sqlite() {
                    super::$name(&super::Fixture::sqlite().await).await;
                }

                #[tokio::test]
                async fn postgres() {
                    if let Some(f) = super::Fixture::postgres(stringify!($name)).await {
                        super::$name(&f).await;
                    }
                }
            }
        )*
    };
}

both_backends!(
    jobs_round_trip,
    invalid_jobs_are_refused,
    idempotency_key_returns_the_existing_job,
    concurrent_idempotent_inserts,
    pagination,
    job_states_and_resume,
    scenes_by_content_hash,
    tile_checkpoints_round_trip_and_upsert,
    adaptive_policy_state_round_trips,
    invalid_checkpoints_are_refused_atomically,
    corrupt_blobs_are_errors_naming_the_tile,
    changed_rows_fail_their_checksums,
    stores_without_checksums_get_them_when_migrated,
    lease_high_water_history_and_faults,
    quarantines_round_trip,
    runs_and_resume_counts,
    reopened_store_sees_everything,
    newer_schema_is_refused,
);

/// 40x30 pixels in 16-pixel tiles: 3 x 2 tiles (16x16, 16x16, 8x16, 16x14, 16x14, 8x14),
/// 8 passes of 4 samples.
fn plan() -> FramePlan {
    FramePlan::new(40, 30, 16, 4, 8).unwrap()
}

fn new_job(n: u32, key: Option<&str>) -> NewJob {
    NewJob {
        settings_json: format!(r#"{{"scene":"builtin:cornell-box","spp":{}}}"#, 32 + n),
        plan: plan(),
        frames: FrameRange { start: 2, end: 4 },
        passes_per_unit: 2,
        priority: n as i32 - 3,
        scene_ref: "builtin:cornell-box".into(),
        name: Some(format!("job {n}")),
        idempotency_key: key.map(str::to_string),
        created_unix_ms: 1_700_000_000_000 + u64::from(n),
        render_plan_json: Some(format!(r#"{{"effects":[],"job":{n}}}"#)),
        error_estimate_caveat: (n % 2 == 1).then(|| format!("caveat of job {n}")),
    }
}

/// Statistics of a tile after `passes` passes, with some awkward bit patterns mixed in
/// so the round trip must be bit-exact, not approximately equal.
fn tile_stats(tile: u32, passes: u32) -> Vec<PixelStats> {
    let rect = plan().tile(tile);
    (0..rect.pixel_count())
        .map(|i| {
            let mut s = PixelStats::default();
            for p in 0..passes {
                let v = 0.1 + (i as f32 * 0.37 + p as f32 * 1.3 + tile as f32).sin().abs();
                s.push([v, v * 0.5, v / 3.0]);
            }
            if i % 7 == 3 {
                s.mean[0] = f64::from_bits(s.mean[0].to_bits() ^ 1);
                s.m2_lum = f64::MIN_POSITIVE / 8.0; // subnormal
            }
            s
        })
        .collect()
}

fn units(passes: &[u32]) -> Vec<UnitDigest> {
    let mut first = 0;
    passes
        .iter()
        .enumerate()
        .map(|(i, &n)| {
            let u = UnitDigest {
                first_pass: first,
                pass_count: n,
                digest: 0xfeed_f00d_dead_beef ^ (i as u64) << 60,
            };
            first += n;
            u
        })
        .collect()
}

fn checkpoint(job: JobId, frame: u32, tile: u32, unit_passes: &[u32]) -> TileCheckpoint {
    let merged: u32 = unit_passes.iter().sum();
    TileCheckpoint {
        job,
        frame,
        tile,
        merged_passes: merged,
        pixels: tile_stats(tile, merged),
        units: units(unit_passes),
        // Any count round-trips; a distinct one per tile catches mixed-up rows.
        rejected_samples: u64::from(tile) * 1000 + u64::from(merged),
        adaptive: None,
        bias: None,
    }
}

fn bits(pixels: &[PixelStats]) -> Vec<u64> {
    pixels
        .iter()
        .flat_map(|s| {
            let mut v = vec![u64::from(s.passes)];
            v.extend(s.mean.map(f64::to_bits));
            v.extend(s.m2.map(f64::to_bits));
            v.extend([s.mean_lum.to_bits(), s.m2_lum.to_bits()]);
            v
        })
        .collect()
}

fn assert_same_checkpoint(a: &TileCheckpoint, b: &TileCheckpoint) {
    assert_eq!(
        (a.job, a.frame, a.tile, a.merged_passes),
        (b.job, b.frame, b.tile, b.merged_passes)
    );
    assert_eq!(a.units, b.units);
    assert_eq!(a.rejected_samples, b.rejected_samples);
    assert_eq!(
        bits(&a.pixels),
        bits(&b.pixels),
        "statistics differ bitwise"
    );
    let policy_bits = |c: &TileCheckpoint| {
        c.adaptive.as_ref().map(|a| {
            let stats: Vec<PixelStats> = a.pixels.iter().map(|p| p.stats).collect();
            let rest: Vec<[u32; 3]> = a
                .pixels
                .iter()
                .map(|p| [p.stopped_at, p.needed, p.traced])
                .collect();
            (a.consumed_passes, bits(&stats), rest)
        })
    };
    assert_eq!(
        policy_bits(a),
        policy_bits(b),
        "adaptive policy states differ"
    );
}

/// A policy state for `c`'s tile: every pixel's statistics, stops at pass 2 for some.
fn with_policy(mut c: TileCheckpoint) -> TileCheckpoint {
    c.adaptive = Some(AdaptiveTileCheckpoint {
        consumed_passes: c.merged_passes,
        pixels: c
            .pixels
            .iter()
            .enumerate()
            .map(|(i, &stats)| AdaptivePixel {
                stats,
                stopped_at: if i % 3 == 0 { 2 } else { 0 },
                needed: i as u32 % 5,
                traced: c.merged_passes,
            })
            .collect(),
        bias: None,
    });
    c
}

/// An adaptive job's tile keeps its policy state beside its merged passes,
/// bit-exact, with the bias records of vcm and ppm when it has them; a checkpoint without
/// one reads back without one (and clears it on upsert); a state of the wrong size is
/// refused when saved and a damaged one when loaded.
async fn adaptive_policy_state_round_trips(f: &Fixture) {
    let store = f.open().await;
    let (job, _) = store.insert_job(new_job(1, None)).await.unwrap();
    let t = with_policy(checkpoint(job, 3, 4, &[2, 1]));
    store.save_tile(t.as_ref()).await.unwrap();
    let loaded = store.load_tiles(job, Some(3)).await.unwrap();
    assert!(loaded[0].adaptive.is_some());
    assert_same_checkpoint(&loaded[0], &t);
    let plain = checkpoint(job, 3, 4, &[2, 1]);
    store.save_tile(plain.as_ref()).await.unwrap();
    assert!(store.load_tiles(job, Some(3)).await.unwrap()[0]
        .adaptive
        .is_none());

    let mut biased = t.clone();
    if let Some(a) = biased.adaptive.as_mut() {
        let bias = a.pixels.iter().enumerate().map(|(i, p)| BiasStats {
            passes: p.stats.passes,
            mean: 0.01 * i as f64 - 0.02,
            m2: 0.5 + i as f64,
        });
        a.bias = Some(bias.collect());
    }
    store.save_tile(biased.as_ref()).await.unwrap();
    let loaded = store.load_tiles(job, Some(3)).await.unwrap();
    assert!(loaded[0]
        .adaptive
        .as_ref()
        .is_some_and(|a| a.bias.is_some()));
    assert_eq!(loaded[0].adaptive, biased.adaptive);
    let mut wrong = biased.clone();
    if let Some(b) = wrong.adaptive.as_mut().and_then(|a| a.bias.as_mut()) {
        b[0].passes += 1;
    }
    let e = store.save_tile(wrong.as_ref()).await.unwrap_err();
    assert!(e.to_string().contains("pixel 0's bias record"), "{e}");
    store.save_tile(plain.as_ref()).await.unwrap();

    let mut short = t.clone();
    if let Some(a) = short.adaptive.as_mut() {
        a.pixels.pop();
    }
    let e = store.save_tile(short.as_ref()).await.unwrap_err();
    assert!(e.to_string().contains("adaptive policy state has"), "{e}");
    // The refused write changed nothing.
    assert!(store.load_tiles(job, Some(3)).await.unwrap()[0]
        .adaptive
        .is_none());

    store.save_tile(t.as_ref()).await.unwrap();
    let mut blob = f.blob("tiles", "adaptive").await;
    blob.truncate(blob.len() - 1);
    f.set_blob("tiles", "adaptive", blob).await;
    expect_corrupt_tile(&*store, job, "adaptive policy blob holds").await;
}

/// A raw connection to the SQLite database in `dir`, behind the store.
async fn sqlite_conn(dir: &Path) -> sqlx::SqliteConnection {
    sqlx::SqliteConnection::connect(&format!("sqlite://{}", dir.join(DATABASE_FILE).display()))
        .await
        .unwrap()
}

#[tokio::test]
async fn sqlite_store_creates_its_data_dir() {
    let dir = tempfile::tempdir().unwrap();
    let store = SqliteStore::open(&dir.path().join("nested/data"))
        .await
        .unwrap();
    assert!(store.path().ends_with(DATABASE_FILE));
    assert_eq!(
        store.schema_version().await.unwrap(),
        SqliteStore::SUPPORTED_SCHEMA
    );
}

async fn jobs_round_trip(f: &Fixture) {
    let store = f.open().await;
    assert_eq!(f.schema_version().await, f.supported_schema());

    let (a, created) = store.insert_job(new_job(1, None)).await.unwrap();
    assert!(created);
    let (b, _) = store.insert_job(new_job(2, Some("k"))).await.unwrap();
    assert!(b > a);
    let rec = store.get_job(a).await.unwrap().unwrap();
    let want = new_job(1, None);
    assert_eq!(rec.id, a);
    assert_eq!(rec.settings_json, want.settings_json);
    assert_eq!(rec.plan, want.plan);
    assert_eq!(rec.frames, want.frames);
    assert_eq!(rec.passes_per_unit, 2);
    assert_eq!(rec.priority, -2);
    assert_eq!(rec.scene_ref, want.scene_ref);
    assert_eq!(rec.name.as_deref(), Some("job 1"));
    assert_eq!(rec.idempotency_key, None);
    assert_eq!(rec.state, JobState::Queued);
    assert_eq!(rec.error, None);
    assert_eq!(rec.created_unix_ms, 1_700_000_000_001);
    assert_eq!((rec.started_unix_ms, rec.finished_unix_ms), (None, None));
    assert_eq!(rec.render_plan_json, want.render_plan_json);
    assert_eq!(
        rec.error_estimate_caveat.as_deref(),
        Some("caveat of job 1")
    );
    let rec_b = store.get_job(b).await.unwrap().unwrap();
    assert_eq!(rec_b.idempotency_key.as_deref(), Some("k"));
    assert_eq!(rec_b.error_estimate_caveat, None);
    assert_eq!(store.get_job(b + 100).await.unwrap(), None);
    assert_eq!(store.get_job(u64::MAX).await.unwrap(), None);

    // Unnamed job, no key.
    let mut anon = new_job(3, None);
    anon.name = None;
    anon.render_plan_json = None;
    let (c, _) = store.insert_job(anon).await.unwrap();
    let rec_c = store.get_job(c).await.unwrap().unwrap();
    assert_eq!(rec_c.name, None);
    assert_eq!(rec_c.render_plan_json, None);
}

async fn invalid_jobs_are_refused(f: &Fixture) {
    let store = f.open().await;
    let mut j = new_job(1, None);
    j.plan.tile_size = 1;
    let e = store.insert_job(j).await.unwrap_err();
    assert!(matches!(e, StoreError::InvalidInput(_)), "{e}");
    assert!(e.to_string().contains("tile size 1"), "{e}");
    let mut j = new_job(1, None);
    j.frames = FrameRange { start: 5, end: 4 };
    assert!(matches!(
        store.insert_job(j).await,
        Err(StoreError::InvalidInput(_))
    ));
    let mut j = new_job(1, None);
    j.passes_per_unit = 0;
    assert!(matches!(
        store.insert_job(j).await,
        Err(StoreError::InvalidInput(_))
    ));
    let mut j = new_job(1, None);
    j.created_unix_ms = u64::MAX;
    assert!(matches!(
        store.insert_job(j).await,
        Err(StoreError::InvalidInput(_))
    ));
    // Nothing was written.
    assert!(store
        .list_jobs(JobQuery::first(10))
        .await
        .unwrap()
        .is_empty());
}

async fn idempotency_key_returns_the_existing_job(f: &Fixture) {
    let store = f.open().await;
    let (a, created) = store.insert_job(new_job(1, Some("retry-1"))).await.unwrap();
    assert!(created);
    // A retry, even with other fields, returns the first job and writes nothing.
    let (again, created) = store.insert_job(new_job(9, Some("retry-1"))).await.unwrap();
    assert_eq!((again, created), (a, false));
    assert_eq!(
        store.get_job(a).await.unwrap().unwrap().name.as_deref(),
        Some("job 1")
    );
    let (other, created) = store.insert_job(new_job(2, Some("retry-2"))).await.unwrap();
    assert!(created && other != a);
    // Without a key every insert is a new job.
    let (x, _) = store.insert_job(new_job(3, None)).await.unwrap();
    let (y, _) = store.insert_job(new_job(3, None)).await.unwrap();
    assert_ne!(x, y);
    assert_eq!(
        store.list_jobs(JobQuery::first(100)).await.unwrap().len(),
        4
    );
}

/// Many concurrent submissions with one key through `Arc<dyn Store>`: exactly one creates
/// the job, all get its id.
async fn concurrent_idempotent_inserts(f: &Fixture) {
    let store = f.open().await;
    let tasks: Vec<_> = (0..16)
        .map(|i| {
            let store = Arc::clone(&store);
            tokio::spawn(async move {
                let key = if i % 2 == 0 { Some("same") } else { None };
                (i, store.insert_job(new_job(i, key)).await.unwrap())
            })
        })
        .collect();
    let mut keyed = Vec::new();
    let mut ids = std::collections::BTreeSet::new();
    for t in tasks {
        let (i, (id, created)) = t.await.unwrap();
        ids.insert(id);
        if i % 2 == 0 {
            keyed.push((id, created));
        } else {
            assert!(created);
        }
    }
    assert_eq!(keyed.iter().filter(|k| k.1).count(), 1);
    assert!(keyed.iter().all(|k| k.0 == keyed[0].0));
    assert_eq!(ids.len(), 9);
}

async fn pagination(f: &Fixture) {
    let store = f.open().await;
    let mut ids = Vec::new();
    for n in 0..7 {
        ids.push(store.insert_job(new_job(n, None)).await.unwrap().0);
    }
    store
        .set_job_state(ids[2], JobState::Running, None, 5)
        .await
        .unwrap();
    store
        .set_job_state(ids[5], JobState::Running, None, 5)
        .await
        .unwrap();

    let page_ids = |v: Vec<tessera_coordinator::store::JobRecord>| -> Vec<JobId> {
        v.into_iter().map(|j| j.id).collect()
    };
    // Newest first, pages of 3.
    let mut q = JobQuery::first(3);
    let mut seen: Vec<JobId> = Vec::new();
    loop {
        let page = page_ids(store.list_jobs(q).await.unwrap());
        seen.extend(&page);
        if page.len() < 3 {
            break;
        }
        q.cursor = page.last().copied();
    }
    let mut newest_first = ids.clone();
    newest_first.reverse();
    assert_eq!(seen, newest_first);

    // Oldest first.
    let q = JobQuery {
        cursor: Some(ids[1]),
        limit: 2,
        state: None,
        order: JobOrder::OldestFirst,
    };
    assert_eq!(page_ids(store.list_jobs(q).await.unwrap()), &ids[2..4]);

    // State filter with a cursor.
    let running = JobQuery {
        state: Some(JobState::Running),
        ..JobQuery::first(10)
    };
    assert_eq!(
        page_ids(store.list_jobs(running).await.unwrap()),
        [ids[5], ids[2]]
    );
    let after = JobQuery {
        cursor: Some(ids[5]),
        ..running
    };
    assert_eq!(page_ids(store.list_jobs(after).await.unwrap()), [ids[2]]);
    assert!(store
        .list_jobs(JobQuery::first(0))
        .await
        .unwrap()
        .is_empty());
    let huge = JobQuery {
        cursor: Some(u64::MAX),
        ..JobQuery::first(2)
    };
    assert_eq!(
        page_ids(store.list_jobs(huge).await.unwrap()),
        [ids[6], ids[5]]
    );
}

async fn job_states_and_resume(f: &Fixture) {
    let store = f.open().await;
    let mut ids = Vec::new();
    for n in 0..5 {
        ids.push(store.insert_job(new_job(n, None)).await.unwrap().0);
    }
    assert!(store
        .set_job_state(ids[0], JobState::Running, None, 100)
        .await
        .unwrap());
    // A second "running" keeps the first start time.
    assert!(store
        .set_job_state(ids[0], JobState::Running, None, 150)
        .await
        .unwrap());
    assert!(store
        .set_job_state(ids[0], JobState::Done, None, 200)
        .await
        .unwrap());
    let j = store.get_job(ids[0]).await.unwrap().unwrap();
    assert_eq!(j.state, JobState::Done);
    assert_eq!(
        (j.started_unix_ms, j.finished_unix_ms),
        (Some(100), Some(200))
    );
    // Terminal is final.
    assert!(!store
        .set_job_state(ids[0], JobState::Canceled, None, 300)
        .await
        .unwrap());
    assert_eq!(
        store.get_job(ids[0]).await.unwrap().unwrap().state,
        JobState::Done
    );

    store
        .set_job_state(
            ids[1],
            JobState::Failed,
            Some("scene failed to load".into()),
            7,
        )
        .await
        .unwrap();
    let j = store.get_job(ids[1]).await.unwrap().unwrap();
    assert_eq!(j.error.as_deref(), Some("scene failed to load"));
    assert_eq!((j.started_unix_ms, j.finished_unix_ms), (None, Some(7)));
    store
        .set_job_state(ids[2], JobState::Canceled, None, 8)
        .await
        .unwrap();
    store
        .set_job_state(ids[4], JobState::Running, None, 9)
        .await
        .unwrap();

    let resume: Vec<_> = store
        .jobs_to_resume()
        .await
        .unwrap()
        .into_iter()
        .map(|j| (j.id, j.state))
        .collect();
    assert_eq!(
        resume,
        [(ids[3], JobState::Queued), (ids[4], JobState::Running)]
    );
    assert!(matches!(
        store.set_job_state(999, JobState::Done, None, 1).await,
        Err(StoreError::JobNotFound(999))
    ));
}

async fn scenes_by_content_hash(f: &Fixture) {
    let store = f.open().await;
    let bytes: Vec<u8> = (0..100_000u32).map(|i| (i * 31 % 251) as u8).collect();
    let hash = "ab".repeat(32);
    assert!(!store.scene_exists(&hash).await.unwrap());
    assert_eq!(store.get_scene(&hash).await.unwrap(), None);
    assert!(store.put_scene(&hash, &bytes).await.unwrap());
    assert!(!store.put_scene(&hash, &bytes).await.unwrap());
    assert!(store.scene_exists(&hash).await.unwrap());
    assert_eq!(store.get_scene(&hash).await.unwrap().unwrap(), bytes);
    assert!(store.put_scene("cd", b"").await.unwrap());
    assert_eq!(store.get_scene("cd").await.unwrap().unwrap(), b"");
    assert!(matches!(
        store.put_scene("", b"x").await,
        Err(StoreError::InvalidInput(_))
    ));
}

async fn tile_checkpoints_round_trip_and_upsert(f: &Fixture) {
    let store = f.open().await;
    let (job, _) = store.insert_job(new_job(1, None)).await.unwrap();
    let (other, _) = store.insert_job(new_job(2, None)).await.unwrap();
    assert!(store.load_tiles(job, None).await.unwrap().is_empty());

    let t0 = checkpoint(job, 2, 0, &[2]);
    let t5 = checkpoint(job, 3, 5, &[2, 2, 1]); // edge tile 8x14
    let o1 = checkpoint(other, 4, 1, &[2]);
    store
        .save_tiles(&[t5.as_ref(), t0.as_ref(), o1.as_ref()])
        .await
        .unwrap();
    let loaded = store.load_tiles(job, None).await.unwrap();
    assert_eq!(loaded.len(), 2);
    assert_same_checkpoint(&loaded[0], &t0); // ordered by frame, tile
    assert_same_checkpoint(&loaded[1], &t5);
    let frame3 = store.load_tiles(job, Some(3)).await.unwrap();
    assert_eq!(frame3.len(), 1);
    assert_same_checkpoint(&frame3[0], &t5);
    assert!(store.load_tiles(job, Some(4)).await.unwrap().is_empty());

    // Upsert: more passes replace the row.
    let t0b = checkpoint(job, 2, 0, &[2, 2, 2, 2]);
    store.save_tile(t0b.as_ref()).await.unwrap();
    let loaded = store.load_tiles(job, Some(2)).await.unwrap();
    assert_eq!(loaded.len(), 1);
    assert_same_checkpoint(&loaded[0], &t0b);

    // A tile with nothing merged yet.
    let empty = TileCheckpoint {
        job,
        frame: 4,
        tile: 2,
        merged_passes: 0,
        pixels: vec![PixelStats::default(); 8 * 16],
        units: vec![],
        rejected_samples: 0,
        adaptive: None,
        bias: None,
    };
    store.save_tile(empty.as_ref()).await.unwrap();
    let loaded = store.load_tiles(job, Some(4)).await.unwrap();
    assert_same_checkpoint(&loaded[0], &empty);

    let o = store.load_tiles(other, None).await.unwrap();
    assert_eq!(o.len(), 1);
    assert_same_checkpoint(&o[0], &o1);
    assert!(matches!(
        store.load_tiles(12345, None).await,
        Err(StoreError::JobNotFound(12345))
    ));
}

async fn invalid_checkpoints_are_refused_atomically(f: &Fixture) {
    let store = f.open().await;
    let (job, _) = store.insert_job(new_job(1, None)).await.unwrap();
    let good = checkpoint(job, 2, 1, &[2]);

    let bad_cases: Vec<(TileCheckpoint, &str)> = vec![
        (checkpoint(job, 5, 1, &[2]), "frame 5"),
        (
            TileCheckpoint {
                tile: 6,
                ..checkpoint(job, 2, 1, &[2])
            },
            "tile 6",
        ),
        (
            TileCheckpoint {
                tile: 2, // 8x16, but 16x16 statistics
                ..checkpoint(job, 2, 1, &[2])
            },
            "256 pixel statistics",
        ),
        (
            TileCheckpoint {
                merged_passes: 3,
                ..checkpoint(job, 2, 1, &[2])
            },
            "units cover passes 0..2",
        ),
        (
            TileCheckpoint {
                units: units(&[1, 1, 0]),
                ..checkpoint(job, 2, 1, &[2])
            },
            "unit 2",
        ),
        (checkpoint(job, 2, 1, &[4, 4, 1]), "exceeds the plan's 8"),
        (
            {
                let mut c = checkpoint(job, 2, 1, &[2]);
                c.pixels[9].mean[1] = f64::INFINITY;
                c
            },
            "pixel 9",
        ),
    ];
    for (bad, needle) in &bad_cases {
        // The good checkpoint first, in the same batch: nothing may be saved.
        let e = store
            .save_tiles(&[good.as_ref(), bad.as_ref()])
            .await
            .unwrap_err();
        assert!(matches!(e, StoreError::InvalidInput(_)), "{e}");
        let msg = e.to_string();
        assert!(msg.contains(needle), "{msg} should mention {needle}");
        assert!(msg.contains(&format!("job {job}")), "{msg}");
    }
    assert!(store.load_tiles(job, None).await.unwrap().is_empty());
    let missing = checkpoint(777, 2, 1, &[2]);
    assert!(matches!(
        store.save_tile(missing.as_ref()).await,
        Err(StoreError::JobNotFound(777))
    ));
    store.save_tile(good.as_ref()).await.unwrap();
    assert_eq!(store.load_tiles(job, None).await.unwrap().len(), 1);
}

async fn expect_corrupt_tile(store: &dyn Store, job: JobId, needle: &str) {
    let e = store.load_tiles(job, None).await.unwrap_err();
    match &e {
        StoreError::CorruptTile {
            job: j,
            frame,
            tile,
            reason,
        } => {
            assert_eq!((*j, *frame, *tile), (job, 3, 4));
            assert!(reason.contains(needle), "{reason} should mention {needle}");
        }
        other => panic!("expected CorruptTile, got {other}"),
    }
    let msg = e.to_string();
    assert!(
        msg.contains(&format!("job {job}, frame 3, tile 4")),
        "{msg}"
    );
}

async fn corrupt_blobs_are_errors_naming_the_tile(f: &Fixture) {
    let store = f.open().await;
    let (job, _) = store.insert_job(new_job(1, None)).await.unwrap();
    let t = checkpoint(job, 3, 4, &[2, 1]);
    store.save_tile(t.as_ref()).await.unwrap();

    type Damage = Box<dyn Fn(&mut Vec<u8>)>;
    let corruptions: Vec<(&str, Damage, &str)> = vec![
        // Truncated in the middle of a pixel record.
        ("stats", Box::new(|b| b.truncate(100)), "announces"),
        // Exactly one pixel record short: the header's count disagrees.
        ("stats", Box::new(|b| b.truncate(b.len() - 68)), "announces"),
        // Unknown format version.
        ("stats", Box::new(|b| b[0] = 7), "format version 7"),
        // Header cut.
        ("stats", Box::new(|b| b.truncate(3)), "truncated"),
        ("stats", Box::new(|b| b.clear()), "empty"),
        // A NaN where pixel 0's first mean was.
        (
            "stats",
            Box::new(|b| b[9..17].copy_from_slice(&f64::NAN.to_bits().to_le_bytes())),
            "non-finite",
        ),
        ("units", Box::new(|b| b.truncate(12)), "unit digest"),
        // One unit less: the units no longer cover the merged passes.
        (
            "units",
            Box::new(|b| {
                b.truncate(b.len() - 16);
                b[1] = 1;
            }),
            "units cover passes 0..2",
        ),
    ];
    for (col, damage, needle) in &corruptions {
        // Restore the good row, then damage it.
        store.save_tile(t.as_ref()).await.unwrap();
        let mut blob = f.blob("tiles", col).await;
        damage(&mut blob);
        f.set_blob("tiles", col, blob).await;
        expect_corrupt_tile(&*store, job, needle).await;
    }
    store.save_tile(t.as_ref()).await.unwrap();
    f.exec("UPDATE tiles SET merged_passes = 2").await;
    expect_corrupt_tile(&*store, job, "more than the tile's merged_passes 2").await;

    // A job row with a broken plan is reported, not a panic.
    f.exec("UPDATE jobs SET plan_tile_size = 0").await;
    assert!(matches!(
        store.get_job(job).await,
        Err(StoreError::Corrupt(_))
    ));
}

/// Bytes changed behind the store in values that still decode (a tile's statistics, a
/// job's settings, a scene's bytes) fail the row's checksum on read, naming the row; a
/// start ([`Store::begin_run`]) drops the damaged checkpoints of an unfinished job so its
/// tiles are rendered again.
async fn changed_rows_fail_their_checksums(f: &Fixture) {
    let store = f.open().await;
    let (job, _) = store.insert_job(new_job(1, None)).await.unwrap();
    let t = checkpoint(job, 3, 4, &[2, 1]);
    store.save_tile(t.as_ref()).await.unwrap();
    let mut stats = f.blob("tiles", "stats").await;
    // A low mantissa byte of pixel 0's first mean: still finite, still decodes.
    stats[10] ^= 0x01;
    f.set_blob("tiles", "stats", stats).await;
    expect_corrupt_tile(&*store, job, "checksum").await;
    // The summaries (no pixels) still read; the start drops the checkpoint of the
    // queued job, and the job's tiles then load empty.
    assert_eq!(store.tile_summaries(job).await.unwrap().len(), 1);
    store.begin_run().await.unwrap();
    assert!(store.load_tiles(job, None).await.unwrap().is_empty());
    assert!(store.tile_summaries(job).await.unwrap().is_empty());
    // Saved again, it reads back.
    store.save_tile(t.as_ref()).await.unwrap();
    assert_eq!(store.load_tiles(job, None).await.unwrap().len(), 1);
    // A checkpoint of a finished job is kept (its image is refused instead).
    store
        .set_job_state(job, JobState::Done, None, 5)
        .await
        .unwrap();
    let mut units = f.blob("tiles", "units").await;
    units[15] ^= 0x80; // a byte of unit 0's digest (after the 5-byte header, 8 bytes of passes)
    f.set_blob("tiles", "units", units).await;
    store.begin_run().await.unwrap();
    expect_corrupt_tile(&*store, job, "checksum").await;
    f.exec("UPDATE tiles SET checksum = NULL").await;
    expect_corrupt_tile(&*store, job, "no checksum").await;

    // The job's settings: one digit changed.
    f.exec("UPDATE jobs SET settings_json = replace(settings_json, '33', '37')")
        .await;
    let e = store.get_job(job).await.unwrap_err();
    assert!(
        matches!(&e, StoreError::Corrupt(m) if m.contains(&format!("jobs row {job}")) && m.contains("checksum")),
        "{e}"
    );
    assert!(store.list_jobs(JobQuery::first(10)).await.is_err());

    // A scene's bytes.
    store.put_scene("h1", b"scene bytes").await.unwrap();
    assert_eq!(
        store.get_scene("h1").await.unwrap().unwrap(),
        b"scene bytes"
    );
    f.set_blob("scenes", "data", b"scene bytez".to_vec()).await;
    let e = store.get_scene("h1").await.unwrap_err();
    assert!(
        matches!(&e, StoreError::Corrupt(m) if m.contains("scenes row h1") && m.contains("checksum")),
        "{e}"
    );
    store.close().await;
}

/// A store written before the checksums opens, and the migration computes them for
/// every existing row (simulated by removing the columns and the migration's record).
async fn stores_without_checksums_get_them_when_migrated(f: &Fixture) {
    let store = f.open().await;
    let (job, _) = store.insert_job(new_job(1, None)).await.unwrap();
    let t = checkpoint(job, 3, 4, &[2, 1]);
    store.save_tile(t.as_ref()).await.unwrap();
    store.put_scene("h1", b"scene bytes").await.unwrap();
    let before = store.get_job(job).await.unwrap().unwrap();
    store.close().await;
    // The store as it was before the checksums' version: later migrations undone too.
    let checksums = f.checksum_schema();
    f.exec(&format!(
        "DELETE FROM schema_version WHERE version >= {checksums}; \
         DROP TABLE scene_uploads; \
         ALTER TABLE jobs DROP COLUMN error_estimator; \
         ALTER TABLE jobs DROP COLUMN checksum; \
         ALTER TABLE tiles DROP COLUMN checksum; \
         ALTER TABLE scenes DROP COLUMN checksum;"
    ))
    .await;
    let store = f.open().await;
    assert_eq!(f.schema_version().await, f.supported_schema());
    assert_eq!(store.get_job(job).await.unwrap().unwrap(), before);
    assert_same_checkpoint(&store.load_tiles(job, None).await.unwrap()[0], &t);
    assert_eq!(
        store.get_scene("h1").await.unwrap().unwrap(),
        b"scene bytes"
    );
    store.close().await;
}

/// The quarantine list. One row per (worker, identity), the first kept; listed
/// in order of name then identity (none first); a lift removes every identity of a name
/// and nothing else, and a second lift removes nothing; the rows outlive the store's
/// reopening.
async fn quarantines_round_trip(f: &Fixture) {
    let q = |worker: &str, identity: Option<&str>, t: u64| QuarantineRecord {
        worker: worker.into(),
        identity: identity.map(str::to_string),
        reason: format!("spot check at {t}"),
        unix_ms: t,
    };
    {
        let store = f.open().await;
        assert!(store.list_quarantines().await.unwrap().is_empty());
        assert!(store
            .record_quarantine(&q("bad", Some("cn-b"), 20))
            .await
            .unwrap());
        assert!(store.record_quarantine(&q("bad", None, 10)).await.unwrap());
        assert!(store
            .record_quarantine(&q("other", None, 30))
            .await
            .unwrap());
        // The same worker and identity again: the first reason and time are kept.
        assert!(!store.record_quarantine(&q("bad", None, 40)).await.unwrap());
        // An empty identity is none.
        assert!(!store
            .record_quarantine(&q("bad", Some(""), 50))
            .await
            .unwrap());
        assert!(matches!(
            store.record_quarantine(&q("bad", None, u64::MAX)).await,
            Err(StoreError::InvalidInput(_))
        ));
        store.close().await;
    }
    let store = f.open().await;
    let expected = [
        q("bad", None, 10),
        q("bad", Some("cn-b"), 20),
        q("other", None, 30),
    ];
    assert_eq!(store.list_quarantines().await.unwrap(), expected);
    assert_eq!(store.delete_quarantines("nobody").await.unwrap(), 0);
    assert_eq!(store.delete_quarantines("bad").await.unwrap(), 2);
    assert_eq!(store.delete_quarantines("bad").await.unwrap(), 0);
    assert_eq!(
        store.list_quarantines().await.unwrap(),
        [q("other", None, 30)]
    );
    // Quarantined again after the lift: a new row, with the new reason.
    assert!(store.record_quarantine(&q("bad", None, 60)).await.unwrap());
    assert_eq!(
        store.list_quarantines().await.unwrap(),
        [q("bad", None, 60), q("other", None, 30)]
    );
}

async fn lease_high_water_history_and_faults(f: &Fixture) {
    let store = f.open().await;
    assert_eq!(store.max_lease_id().await.unwrap(), 0);
    store.record_lease_high_water(1000).await.unwrap();
    store.record_lease_high_water(400).await.unwrap();
    assert_eq!(store.max_lease_id().await.unwrap(), 1000);
    assert!(matches!(
        store.record_lease_high_water(u64::MAX).await,
        Err(StoreError::InvalidInput(_))
    ));

    let (job, _) = store.insert_job(new_job(1, None)).await.unwrap();
    let (job2, _) = store.insert_job(new_job(2, None)).await.unwrap();
    let points = [
        HistoryPoint {
            elapsed_seconds: 0.5,
            spp: 4.0,
            error_estimate: None,
        },
        HistoryPoint {
            elapsed_seconds: 1.25,
            spp: 8.0,
            error_estimate: Some(0.125),
        },
        HistoryPoint {
            elapsed_seconds: 2.0,
            spp: 10.5,
            error_estimate: Some(0.1 + 0.2),
        },
    ];
    // The first point names no estimator (as a build before schema 9 stored none), the
    // others do: the job's is its last point's.
    let rec = |id| {
        let store = store.clone();
        async move { store.get_job(id).await.unwrap().unwrap() }
    };
    store.append_history(job, points[0], None).await.unwrap();
    assert_eq!(rec(job).await.error_estimator, None);
    store
        .append_history(job, points[1], Some("old"))
        .await
        .unwrap();
    store
        .append_history(job, points[2], Some("new"))
        .await
        .unwrap();
    assert_eq!(rec(job).await.error_estimator.as_deref(), Some("new"));
    store.append_history(job2, points[0], None).await.unwrap();
    assert_eq!(rec(job2).await.error_estimator, None);
    assert_eq!(store.list_history(job).await.unwrap(), points);
    assert_eq!(store.list_history(job2).await.unwrap(), &points[..1]);
    assert!(store.list_history(999).await.unwrap().is_empty());
    let nan = HistoryPoint {
        error_estimate: Some(f64::NAN),
        ..points[0]
    };
    assert!(matches!(
        store.append_history(job, nan, Some("x")).await,
        Err(StoreError::InvalidInput(_))
    ));
    assert!(matches!(
        store.append_history(999, points[0], None).await,
        Err(StoreError::JobNotFound(999))
    ));

    let fault = |worker: &str, job: Option<JobId>, kind, t| FaultEvent {
        worker: worker.into(),
        job,
        kind,
        message: format!("fault at {t}"),
        unix_ms: t,
    };
    let events = [
        fault("w1", Some(job), FaultKind::InvalidResult, 1),
        fault("w2", Some(job), FaultKind::DuplicateMismatch, 2),
        fault("w1", Some(job2), FaultKind::InvalidResult, 3),
        fault("w1", None, FaultKind::LeaseViolation, 4),
    ];
    for e in &events {
        store.record_fault(e).await.unwrap();
    }
    let count = |job, worker: Option<&str>| {
        let f = FaultFilter {
            job,
            worker: worker.map(str::to_string),
        };
        let store = store.clone();
        async move { store.count_faults(&f).await.unwrap() }
    };
    assert_eq!(count(None, None).await, 4);
    assert_eq!(count(Some(job), None).await, 2);
    assert_eq!(count(None, Some("w1")).await, 3);
    assert_eq!(count(Some(job), Some("w1")).await, 1);
    assert_eq!(count(Some(999), None).await, 0);
    let listed = store
        .list_faults(
            &FaultFilter {
                worker: Some("w1".into()),
                ..Default::default()
            },
            2,
        )
        .await
        .unwrap();
    assert_eq!(listed, [events[3].clone(), events[2].clone()]);
    store.ping().await.unwrap();
}

/// The run bookkeeping of the crash-loop guard: clean and unclean previous runs, the job
/// being resumed, and resume counts that restart when a job made progress.
async fn runs_and_resume_counts(f: &Fixture) {
    let store = f.open().await;
    // A new store counts as shut down cleanly.
    assert_eq!(
        store.begin_run().await.unwrap(),
        store::PreviousRun {
            clean: true,
            resuming: None
        }
    );
    let (job, _) = store.insert_job(new_job(1, None)).await.unwrap();
    assert_eq!(store.record_resume(job, false).await.unwrap(), 0);
    // The run "crashed" while resuming the job: the next start sees both.
    drop(store);
    let store = f.open().await;
    assert_eq!(
        store.begin_run().await.unwrap(),
        store::PreviousRun {
            clean: false,
            resuming: Some(job)
        }
    );
    assert_eq!(store.record_resume(job, true).await.unwrap(), 1);
    assert_eq!(store.record_resume(job, true).await.unwrap(), 2);
    // Progress (a merged pass) restarts the count.
    store
        .save_tile(checkpoint(job, 2, 0, &[2]).as_ref())
        .await
        .unwrap();
    assert_eq!(store.record_resume(job, true).await.unwrap(), 1);
    store.resumes_done().await.unwrap();
    store.end_run().await.unwrap();
    assert_eq!(
        store.begin_run().await.unwrap(),
        store::PreviousRun {
            clean: true,
            resuming: None
        }
    );
    assert!(matches!(
        store.record_resume(4242, true).await,
        Err(StoreError::JobNotFound(4242))
    ));
}

/// Everything written is there after the store is closed (or just dropped) and reopened.
async fn reopened_store_sees_everything(f: &Fixture) {
    let t;
    let (a, b);
    {
        let store = f.open().await;
        a = store.insert_job(new_job(1, Some("key"))).await.unwrap().0;
        b = store.insert_job(new_job(2, None)).await.unwrap().0;
        store
            .set_job_state(b, JobState::Running, None, 10)
            .await
            .unwrap();
        store.put_scene("hash", b"glTF bytes").await.unwrap();
        t = checkpoint(b, 3, 2, &[2, 2]);
        store.save_tile(t.as_ref()).await.unwrap();
        store.record_lease_high_water(4096).await.unwrap();
        store
            .append_history(
                b,
                HistoryPoint {
                    elapsed_seconds: 1.0,
                    spp: 8.0,
                    error_estimate: Some(0.5),
                },
                None,
            )
            .await
            .unwrap();
        store
            .record_fault(&FaultEvent {
                worker: "w".into(),
                job: Some(b),
                kind: FaultKind::InvalidResult,
                message: "NaN".into(),
                unix_ms: 5,
            })
            .await
            .unwrap();
        store.close().await;
    }
    let check = |store: Arc<dyn Store>| async move {
        f.integrity_check().await;
        assert_eq!(f.schema_version().await, f.supported_schema());
        let jobs = store.list_jobs(JobQuery::first(10)).await.unwrap();
        assert_eq!(jobs.iter().map(|j| j.id).collect::<Vec<_>>(), [b, a]);
        assert_eq!(
            store.insert_job(new_job(5, Some("key"))).await.unwrap(),
            (a, false)
        );
        assert_eq!(store.jobs_to_resume().await.unwrap().len(), 2);
        assert_eq!(
            store.get_job(b).await.unwrap().unwrap().state,
            JobState::Running
        );
        assert_eq!(
            store.get_scene("hash").await.unwrap().unwrap(),
            b"glTF bytes"
        );
        let tiles = store.load_tiles(b, None).await.unwrap();
        assert_eq!(tiles.len(), 1);
        assert_same_checkpoint(&tiles[0], &t);
        assert_eq!(store.max_lease_id().await.unwrap(), 4096);
        assert_eq!(store.list_history(b).await.unwrap().len(), 1);
        assert_eq!(
            store
                .count_faults(&FaultFilter {
                    job: Some(b),
                    ..Default::default()
                })
                .await
                .unwrap(),
            1
        );
        // Ids are never reused.
        let (c, _) = store.insert_job(new_job(3, None)).await.unwrap();
        assert!(c > b);
        store
    };
    let store = check(f.open().await).await;
    // Dropped without close: still all there (plus job c).
    drop(store);
    let store = f.open().await;
    assert_eq!(store.list_jobs(JobQuery::first(10)).await.unwrap().len(), 3);
}

async fn newer_schema_is_refused(f: &Fixture) {
    f.open().await.close().await;
    f.exec("INSERT INTO schema_version (version, applied_unix_ms) VALUES (99, 0)")
        .await;
    let e = f.try_open().await.err().expect("a newer schema is refused");
    let supported = f.supported_schema();
    assert!(
        matches!(e, StoreError::SchemaTooNew { found: 99, supported: s } if s == supported),
        "{e}"
    );
}

#[tokio::test]
async fn unusable_data_dir_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("file");
    std::fs::write(&file, b"not a directory").unwrap();
    let e = SqliteStore::open(&file.join("data")).await.unwrap_err();
    assert!(matches!(e, StoreError::DataDir { .. }), "{e}");
}

// ---- kill -9 durability ---------------------------------------------------------------

/// The URL as the child parses it again (with the password, unlike `Display`).
fn store_url_arg(url: &StoreUrl) -> String {
    match url {
        StoreUrl::Sqlite(dir) => format!("sqlite:{}", dir.display()),
        StoreUrl::Postgres(url) => url.clone(),
    }
}

/// Environment variable that turns [`kill9_child_entry`] into the writer process: the
/// store URL (`sqlite:DIR` or `postgres://...`) it writes to.
const CHILD_ENV: &str = "TESSERA_STORE_TEST_CHILD_DIR";

/// The child side of [`committed_writes_survive_sigkill`]: does nothing in a normal test
/// run. With `CHILD_ENV` set it writes a job, a tile checkpoint and a lease high-water
/// mark, reports `COMMITTED <job>`, then appends history points forever, reporting
/// `HISTORY <i>` after each commit, until it is killed (or 30 s pass).
#[test]
fn kill9_child_entry() {
    let Ok(url) = std::env::var(CHILD_ENV) else {
        return;
    };
    let url = StoreUrl::parse(&url).unwrap();
    use std::io::Write;
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    rt.block_on(async {
        let store = store::open(&url).await.unwrap();
        let (job, _) = store.insert_job(new_job(1, Some("child"))).await.unwrap();
        store
            .set_job_state(job, JobState::Running, None, 42)
            .await
            .unwrap();
        let t = checkpoint(job, 2, 3, &[2, 2, 2]);
        store.save_tile(t.as_ref()).await.unwrap();
        store.record_lease_high_water(777).await.unwrap();
        let mut out = std::io::stdout().lock();
        writeln!(out, "COMMITTED {job}").unwrap();
        out.flush().unwrap();
        let start = std::time::Instant::now();
        for i in 0u32.. {
            if start.elapsed().as_secs() > 30 {
                break;
            }
            let p = HistoryPoint {
                elapsed_seconds: f64::from(i),
                spp: f64::from(i) * 4.0,
                error_estimate: Some(1.0 / f64::from(i + 1)),
            };
            store.append_history(job, p, None).await.unwrap();
            // Keep a tile being rewritten too, so the kill may land mid-transaction.
            let t = checkpoint(job, 3, 0, &[1 + i % 8]);
            store.save_tile(t.as_ref()).await.unwrap();
            writeln!(out, "HISTORY {i}").unwrap();
            out.flush().unwrap();
        }
    });
}

#[cfg(unix)]
mod committed_writes_survive_sigkill {
    #[test]
    fn sqlite() {
        let f = super::Fixture::Sqlite(tempfile::tempdir().unwrap());
        super::committed_writes_survive_sigkill(&f);
    }

    #[test]
    fn postgres() {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        let name = "committed_writes_survive_sigkill";
        if let Some(f) = rt.block_on(super::Fixture::postgres(name)) {
            super::committed_writes_survive_sigkill(&f);
        }
    }
}

/// A child process writes to the store and is killed with SIGKILL mid-write: everything
/// it reported committed is there, intact, when the store is reopened.
#[cfg(unix)]
fn committed_writes_survive_sigkill(f: &Fixture) {
    use std::io::{BufRead, BufReader};
    use std::os::unix::process::ExitStatusExt;
    use std::process::{Command, Stdio};
    use std::time::{Duration, Instant};

    let mut child = Command::new(std::env::current_exe().unwrap())
        .args([
            "store::kill9_child_entry",
            "--exact",
            "--nocapture",
            "--test-threads=1",
        ])
        .env(CHILD_ENV, store_url_arg(&f.url()))
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .unwrap();
    let stdout = child.stdout.take().unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines() {
            let Ok(line) = line else { break };
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    let deadline = Instant::now() + Duration::from_secs(60);
    let mut job: Option<JobId> = None;
    let mut last_history: Option<u32> = None;
    while last_history.is_none_or(|h| h < 20) {
        let wait = deadline.saturating_duration_since(Instant::now());
        let line = match rx.recv_timeout(wait) {
            Ok(line) => line,
            Err(e) => {
                let _ = child.kill();
                let _ = child.wait();
                panic!("the child stopped reporting ({e:?}) after job {job:?}, history {last_history:?}");
            }
        };
        if let Some(i) = line.find("COMMITTED ") {
            job = Some(line[i + 10..].trim().parse().unwrap());
        } else if let Some(i) = line.find("HISTORY ") {
            last_history = Some(line[i + 8..].trim().parse().unwrap());
        }
    }
    child.kill().unwrap(); // SIGKILL
    let status = child.wait().unwrap();
    assert_eq!(status.signal(), Some(9), "{status:?}");
    let job = job.expect("the child reported its job");
    let reported = last_history.unwrap();

    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    rt.block_on(async {
        let store = f.open().await;
        f.integrity_check().await;
        let j = store.get_job(job).await.unwrap().expect("the job survived");
        assert_eq!(j.state, JobState::Running);
        assert_eq!(j.idempotency_key.as_deref(), Some("child"));
        assert_eq!(store.jobs_to_resume().await.unwrap().len(), 1);
        let tiles = store.load_tiles(job, Some(2)).await.unwrap();
        assert_eq!(tiles.len(), 1);
        assert_same_checkpoint(&tiles[0], &checkpoint(job, 2, 3, &[2, 2, 2]));
        // The tile rewritten in the loop is one of its committed versions, intact.
        let t = store.load_tiles(job, Some(3)).await.unwrap();
        assert_eq!(t.len(), 1);
        assert_same_checkpoint(&t[0], &checkpoint(job, 3, 0, &[t[0].merged_passes]));
        assert_eq!(store.max_lease_id().await.unwrap(), 777);
        let history = store.list_history(job).await.unwrap();
        assert!(
            history.len() as u32 > reported,
            "{} history points, the child reported {reported} committed",
            history.len()
        );
        for (i, p) in history.iter().enumerate() {
            assert_eq!(p.elapsed_seconds, i as f64);
        }
    });
}

// ---- PostgreSQL: bad URLs and servers that do not answer ------------------------------

#[test]
fn bad_store_urls_are_refused_naming_them() {
    for (url, needle) in [
        ("mysql://h/db", "expected sqlite:PATH"),
        ("tessera-data", "expected sqlite:PATH"),
        ("sqlite:", "needs a data directory"),
        ("postgres://u@h:notaport/db", "postgres://u@h:notaport/db"),
    ] {
        let e = StoreUrl::parse(url).unwrap_err();
        let msg = e.to_string();
        assert!(matches!(e, StoreError::BadUrl { .. }), "{msg}");
        assert!(msg.contains(needle), "{msg} should mention {needle}");
    }
    let e = StoreUrl::parse("postgres://u:hunter2@h:x/db").unwrap_err();
    assert!(!e.to_string().contains("hunter2"), "{e}");
    assert_eq!(
        StoreUrl::parse("sqlite:some/dir").unwrap(),
        StoreUrl::Sqlite("some/dir".into())
    );
    for url in ["postgres://u@h:5432/db", "postgresql://u@h/db"] {
        assert_eq!(
            StoreUrl::parse(url).unwrap(),
            StoreUrl::Postgres(url.into())
        );
    }
}

/// Nothing listens on port 1 of loopback: the open fails (after the pool's 10 s of
/// connection retries) with an error that
/// names the server (without the password), no panic, no hang.
#[tokio::test]
async fn an_unreachable_postgres_server_is_an_error_naming_it() {
    let e = PostgresStore::open("postgres://tessera:hunter2@127.0.0.1:1/tessera")
        .await
        .unwrap_err();
    let msg = e.to_string();
    assert!(matches!(e, StoreError::Unreachable { .. }), "{msg}");
    assert!(msg.contains("127.0.0.1:1"), "{msg}");
    assert!(!msg.contains("hunter2"), "{msg}");
    assert!(!e.is_write_failure());
}

/// A database that does not exist on a real server: an error naming the server.
#[tokio::test]
async fn a_missing_postgres_database_is_an_error_naming_it() {
    let Some(url) = postgres::fresh_database("missing_database").await else {
        return;
    };
    // The same server and user, another database name.
    let (base, _) = url.split_once('?').unwrap();
    let (server, _) = base.rsplit_once('/').unwrap();
    let missing = format!("{server}/no_such_tessera_db");
    let e = PostgresStore::open(&missing).await.unwrap_err();
    let msg = e.to_string();
    assert!(matches!(e, StoreError::Unreachable { .. }), "{msg}");
    assert!(msg.contains("no_such_tessera_db"), "{msg}");
}

/// High availability (docs/store.md, "High availability"): once a second coordinator
/// took the leadership of the store, every state-changing write of the first one is
/// refused as [`StoreError::NotLeader`] (a write failure), and the lease high-water mark
/// the new leader reads is above every id the old one reserved.
#[tokio::test]
async fn a_deposed_leaders_writes_are_fenced() {
    let Some(url) = postgres::fresh_database("fencing").await else {
        return;
    };
    let old = PostgresStore::open(&url).await.unwrap();
    let new = PostgresStore::open(&url).await.unwrap();
    let e1 = old.take_leadership().await.unwrap();
    let (job, _) = old.insert_job(new_job(1, None)).await.unwrap();
    old.record_lease_high_water(4096).await.unwrap();
    let e2 = new.take_leadership().await.unwrap();
    assert!(e2 > e1, "epochs {e1} then {e2}");
    assert_eq!(new.max_lease_id().await.unwrap(), 4096);

    let refused = |r: Result<(), StoreError>, what: &str| {
        let e = r.expect_err(what);
        assert!(
            matches!(e, StoreError::NotLeader { ours, current } if ours == e1 && current == e2),
            "{what}: {e}"
        );
        assert!(e.is_write_failure(), "{what}: {e}");
        assert!(e.to_string().contains("no longer the active one"), "{e}");
    };
    refused(
        old.record_lease_high_water(8192).await,
        "a lease reservation",
    );
    refused(
        old.insert_job(new_job(2, None)).await.map(|_| ()),
        "a job insert",
    );
    refused(
        old.set_job_state(job, JobState::Running, None, 1)
            .await
            .map(|_| ()),
        "a state change",
    );
    refused(
        old.save_tiles(&[checkpoint(job, 2, 0, &[2]).as_ref()])
            .await,
        "a checkpoint",
    );
    refused(old.end_run().await, "the clean end");
    refused(
        old.append_history(
            job,
            HistoryPoint {
                elapsed_seconds: 1.0,
                spp: 2.0,
                error_estimate: None,
            },
            None,
        )
        .await,
        "a history point",
    );
    refused(
        old.record_fault(&FaultEvent {
            worker: "w".into(),
            job: Some(job),
            kind: FaultKind::InvalidResult,
            message: "m".into(),
            unix_ms: 1,
        })
        .await,
        "a fault event",
    );
    refused(
        old.put_scene("ab", b"scene").await.map(|_| ()),
        "a scene upload",
    );
    assert!(new.list_history(job).await.unwrap().is_empty());
    assert_eq!(new.max_lease_id().await.unwrap(), 4096);
    // The new leader writes.
    new.record_lease_high_water(8192).await.unwrap();
    new.save_tiles(&[checkpoint(job, 2, 0, &[2]).as_ref()])
        .await
        .unwrap();
    assert_eq!(new.max_lease_id().await.unwrap(), 8192);
}
