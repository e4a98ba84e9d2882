//! Workers and the coordinator's gRPC service talking real gRPC over loopback: a job
//! rendered by one worker and by three workers gives the same image, bit for bit, as the
//! local renderer (ARCHITECTURE.md §2); a worker without the token is refused.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tessera_coordinator::grpc::{Farm, JobEntry, WorkerGrpc};
use tessera_farm::job::{RenderConfig, SceneRef};
use tessera_farm::{FrameImage, FramePlan};
use tessera_render::render::render_frame;
use tessera_render::scene::RenderScene;
use tessera_worker::{run, WorkerConfig, WorkerError};

fn plan() -> FramePlan {
    FramePlan::for_spp(40, 32, 16, 16).unwrap()
}

fn settings() -> RenderConfig {
    RenderConfig {
        seed: 11,
        ..RenderConfig::default()
    }
}

/// Starts the service on an ephemeral loopback port; returns its URL.
async fn start(farm: Arc<Mutex<Farm>>, token: Option<&str>) -> String {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let svc = WorkerGrpc::new(farm, token.map(str::to_string), 100, 2000).into_server();
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
    let mut farm = Farm::new(2000);
    farm.scheduler.add_job(1, 0, plan(), 0..=0, 1);
    farm.jobs.insert(
        1,
        JobEntry {
            scene: SceneRef::Builtin("cornell-box".into()),
            camera: None,
            settings: settings(),
            plan: plan(),
        },
    );
    let farm = Arc::new(Mutex::new(farm));
    let url = start(farm.clone(), Some("s3cret")).await;
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    let mut handles = Vec::new();
    for i in 0..workers {
        let cfg = WorkerConfig {
            coordinator: url.clone(),
            threads: 1,
            name: format!("w{i}"),
            token: Some("s3cret".into()),
        };
        let mut rx = stop_rx.clone();
        handles.push(tokio::spawn(run(cfg, async move {
            let _ = rx.changed().await;
        })));
    }
    // Wait by polling, with a deadline.
    let deadline = Instant::now() + Duration::from_secs(120);
    while !farm.lock().unwrap().scheduler.is_complete(1) {
        assert!(Instant::now() < deadline, "farm did not finish");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    stop_tx.send(true).unwrap();
    for h in handles {
        h.await.unwrap().unwrap();
    }
    let f = farm.lock().unwrap();
    assert_eq!(f.workers.len(), workers);
    assert!(f.workers.values().all(|w| w.faults == 0));
    f.scheduler.frame(1, 0).unwrap().image()
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
    let scene = tessera_scene::load("builtin:cornell-box").unwrap();
    let rs = RenderScene::build(&scene, 40, 32).unwrap();
    let local = render_frame(&rs, &settings(), &plan(), 0, 2, |_, _| {}).image();
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
    let farm = Arc::new(Mutex::new(Farm::new(2000)));
    let url = start(farm, Some("s3cret")).await;
    for token in [None, Some("wrong".to_string())] {
        let cfg = WorkerConfig {
            coordinator: url.clone(),
            threads: 1,
            name: "intruder".into(),
            token,
        };
        let r = tokio::time::timeout(Duration::from_secs(30), run(cfg, std::future::pending()))
            .await
            .unwrap();
        assert!(matches!(r, Err(WorkerError::Unauthenticated(_))), "{r:?}");
    }
}
