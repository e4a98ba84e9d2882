//! Workers and the coordinator's gRPC service talking real gRPC over loopback: a job
//! rendered by one worker and by three workers gives the same image, bit for bit, as the
//! local renderer (ARCHITECTURE.md §2); a worker without the token is refused; a worker
//! stopped mid-job delivers what it rendered and gives back the units it prefetched, and
//! heartbeats keep prefetched leases alive.
//!
//! The service is the production one: a real [`Coordinator`] over a temporary SQLite
//! store, the job submitted through it as `POST /jobs` would.

use std::time::{Duration, Instant};
use tessera_coordinator::grpc::WorkerGrpc;
use tessera_coordinator::service::{Coordinator, CoordinatorConfig};
use tessera_farm::job::JobSettings;
use tessera_farm::{FrameImage, FramePlan};
use tessera_render::render::render_frame;
use tessera_render::scene::RenderScene;
use tessera_worker::{run, WorkerConfig, WorkerError};

fn plan() -> FramePlan {
    FramePlan::for_spp(40, 32, 16, 16).unwrap()
}

/// The job: the plan above (40x32, 16 spp, 16-pixel tiles) with seed 11.
fn settings() -> JobSettings {
    let mut s = JobSettings::new("builtin:cornell-box");
    s.width = Some(40);
    s.height = Some(32);
    s.spp = 16;
    s.tile_size = 16;
    s.seed = 11;
    s
}

/// A coordinator over a fresh store in `dir` whose workers need `token`.
async fn coordinator(dir: &tempfile::TempDir, token: Option<&str>) -> Coordinator {
    coordinator_with(dir, token, 100, 2000).await
}

/// [`coordinator`] with the given heartbeat interval and lease length.
async fn coordinator_with(
    dir: &tempfile::TempDir,
    token: Option<&str>,
    heartbeat_ms: u32,
    lease_ms: u64,
) -> Coordinator {
    let mut cfg = CoordinatorConfig::new(dir.path());
    cfg.worker_token = token.map(str::to_string);
    cfg.heartbeat_ms = heartbeat_ms;
    cfg.lease_ms = lease_ms;
    Coordinator::open(cfg).await.unwrap()
}

/// Starts the coordinator's gRPC service on an ephemeral loopback port; returns its URL.
async fn start(core: Coordinator) -> String {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let svc = WorkerGrpc::for_coordinator(core).into_server();
    tokio::spawn(async move {
        tonic::transport::Server::builder()
            .add_service(svc)
            .serve_with_incoming(tokio_stream::wrappers::TcpListenerStream::new(listener))
            .await
            .unwrap();
    });
    format!("http://{addr}")
}

async fn farm_render(workers: usize) -> FrameImage {
    let dir = tempfile::tempdir().unwrap();
    let core = coordinator(&dir, Some("s3cret")).await;
    let (job, _) = core.submit(settings(), None).await.unwrap();
    assert_eq!((job.width, job.height), (Some(40), Some(32)));
    let url = start(core.clone()).await;
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    let mut handles = Vec::new();
    for i in 0..workers {
        let cfg = WorkerConfig {
            coordinators: vec![url.clone()],
            threads: 1,
            name: format!("w{i}"),
            token: Some("s3cret".into()),
            tls: None,
            inject_faults: 0.0,
        };
        let mut rx = stop_rx.clone();
        handles.push(tokio::spawn(run(cfg, async move {
            let _ = rx.changed().await;
        })));
    }
    // Wait by polling, with a deadline.
    let deadline = Instant::now() + Duration::from_secs(120);
    while !core.status(job.id).await.unwrap().state.is_terminal() {
        assert!(Instant::now() < deadline, "farm did not finish");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert_eq!(core.status(job.id).await.unwrap().state.as_str(), "done");
    stop_tx.send(true).unwrap();
    for h in handles {
        h.await.unwrap().unwrap();
    }
    let list = core.workers().unwrap().workers;
    assert_eq!(list.len(), workers);
    assert!(list.iter().all(|w| w.faults == 0));
    core.frame_image(job.id, Some(0)).await.unwrap()
}

fn bits(img: &FrameImage) -> Vec<u32> {
    img.mean
        .iter()
        .chain(&img.variance_of_mean)
        .flat_map(|p| p.map(f32::to_bits))
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_and_three_workers_match_the_local_render() {
    // The local render resolves the job as `tessera render` does (ARCHITECTURE.md §1).
    let scene = tessera_scene::load("builtin:cornell-box").unwrap();
    let job = settings().validate().unwrap();
    let resolved =
        tessera_scene::job::resolve_job(&job, &scene, tessera_render::pilot::verdict).unwrap();
    assert_eq!(resolved.plan, plan());
    assert_eq!(resolved.config.seed, 11);
    let rs = RenderScene::build(&scene, 40, 32).unwrap();
    let local = render_frame(&rs, &resolved.config, &plan(), 0, 2, |_, _| {}).image();
    let one = farm_render(1).await;
    let three = farm_render(3).await;
    assert!(
        bits(&one) == bits(&local),
        "1 worker differs from tessera render"
    );
    assert!(
        bits(&three) == bits(&local),
        "3 workers differ from tessera render"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_worker_without_the_token_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let url = start(coordinator(&dir, Some("s3cret")).await).await;
    for token in [None, Some("wrong".to_string())] {
        let cfg = WorkerConfig {
            coordinators: vec![url.clone()],
            threads: 1,
            name: "intruder".into(),
            token,
            tls: None,
            inject_faults: 0.0,
        };
        let r = tokio::time::timeout(Duration::from_secs(30), run(cfg, std::future::pending()))
            .await
            .unwrap();
        assert!(matches!(r, Err(WorkerError::Unauthenticated(_))), "{r:?}");
    }
}

/// A longer job than [`settings`]: 128x128 at 64 spp (2 passes of 32) in 16-pixel tiles,
/// 128 units.
fn long_settings() -> JobSettings {
    let mut s = settings();
    s.width = Some(128);
    s.height = Some(128);
    s.spp = 64;
    s
}

/// `tessera render`'s image of `s` (resolved as the coordinator resolves it).
fn local_image(s: &JobSettings) -> FrameImage {
    let scene = tessera_scene::load("builtin:cornell-box").unwrap();
    let resolved = tessera_scene::job::resolve_job(
        &s.clone().validate().unwrap(),
        &scene,
        tessera_render::pilot::verdict,
    )
    .unwrap();
    let rs = RenderScene::build(&scene, resolved.plan.width, resolved.plan.height).unwrap();
    render_frame(&rs, &resolved.config, &resolved.plan, 0, 2, |_, _| {}).image()
}

/// A running worker of `url` with `threads` threads, stopped by sending on the returned
/// channel.
fn spawn_worker(
    url: &str,
    name: &str,
    threads: usize,
) -> (
    tokio::sync::watch::Sender<bool>,
    tokio::task::JoinHandle<Result<(), WorkerError>>,
) {
    let (tx, mut rx) = tokio::sync::watch::channel(false);
    let cfg = WorkerConfig {
        coordinators: vec![url.to_string()],
        threads,
        name: name.into(),
        token: None,
        tls: None,
        inject_faults: 0.0,
    };
    let h = tokio::spawn(run(cfg, async move {
        let _ = rx.changed().await;
    }));
    (tx, h)
}

/// The value of the unlabelled sample `name` in the coordinator's `/metrics`.
async fn metric(core: &Coordinator, name: &str) -> f64 {
    tessera_testkit::require_metric(&core.metrics().await.unwrap(), name)
}

async fn wait_done(core: &Coordinator, job: u64) {
    let deadline = Instant::now() + Duration::from_secs(120);
    while !core.status(job).await.unwrap().state.is_terminal() {
        assert!(Instant::now() < deadline, "farm did not finish");
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    assert_eq!(core.status(job).await.unwrap().state.as_str(), "done");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stopped_worker_delivers_its_results_and_gives_back_its_prefetched_units() {
    let dir = tempfile::tempdir().unwrap();
    // No ticker runs here and leases last a minute: only the worker can clear its leases,
    // by delivering their results or giving them back.
    let core = coordinator_with(&dir, None, 100, 60_000).await;
    let (job, _) = core.submit(long_settings(), None).await.unwrap();
    let url = start(core.clone()).await;
    let (stop, first) = spawn_worker(&url, "first", 1);
    // Stop it once a batch is merged: it is then rendering one batch and holds the next.
    let deadline = Instant::now() + Duration::from_secs(60);
    while core.status(job.id).await.unwrap().passes_done == 0 {
        assert!(Instant::now() < deadline, "no unit was merged");
        tokio::time::sleep(Duration::from_millis(2)).await;
    }
    stop.send(true).unwrap();
    first.await.unwrap().unwrap();
    let status = core.status(job.id).await.unwrap();
    assert_eq!(
        status.state.as_str(),
        "running",
        "the job ended with the first worker"
    );
    assert_eq!(
        metric(&core, "tessera_leases_outstanding").await,
        0.0,
        "the stopped worker kept leases"
    );
    // Every unit it leased is merged or back in the queue: a second worker finishes the
    // job, with nothing lapsed and nothing merged twice.
    let (stop2, second) = spawn_worker(&url, "second", 2);
    wait_done(&core, job.id).await;
    stop2.send(true).unwrap();
    second.await.unwrap().unwrap();
    assert_eq!(metric(&core, "tessera_leases_expired_total").await, 0.0);
    assert_eq!(metric(&core, "tessera_worker_faults_total").await, 0.0);
    let image = core.frame_image(job.id, Some(0)).await.unwrap();
    assert!(
        bits(&image) == bits(&local_image(&long_settings())),
        "the farm image differs from tessera render"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn heartbeats_keep_prefetched_leases_alive() {
    let dir = tempfile::tempdir().unwrap();
    // Leases shorter than a batch takes to render: a prefetched batch waits about that
    // long before it starts, so only heartbeats can keep it.
    let core = coordinator_with(&dir, None, 50, 250).await;
    let (job, _) = core.submit(long_settings(), None).await.unwrap();
    let url = start(core.clone()).await;
    let workers: Vec<_> = (0..2)
        .map(|i| spawn_worker(&url, &format!("w{i}"), 1))
        .collect();
    wait_done(&core, job.id).await;
    for (stop, h) in workers {
        stop.send(true).unwrap();
        h.await.unwrap().unwrap();
    }
    assert_eq!(metric(&core, "tessera_leases_expired_total").await, 0.0);
    let image = core.frame_image(job.id, Some(0)).await.unwrap();
    assert!(bits(&image) == bits(&local_image(&long_settings())));
}
