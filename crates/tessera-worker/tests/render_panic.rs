//! A panic while rendering a unit does not end the worker: the unit's lease is returned as
//! unusable ("rendering panicked: ..."), the coordinator counts it against the job's
//! scene, not the worker, and fails the job after `MAX_UNUSABLE_RETURNS` such returns;
//! the same worker then renders the next job.
//!
//! No input is known to make the renderer panic, so the panic is provoked with the
//! worker's test-only variable [`TEST_PANIC_SEED_VAR`]. This file is its own test binary
//! with one test, so the variable is set before any other thread exists.

use std::time::{Duration, Instant};
use tessera_coordinator::grpc::WorkerGrpc;
use tessera_coordinator::service::{Coordinator, CoordinatorConfig};
use tessera_farm::job::JobSettings;
use tessera_worker::{run, WorkerConfig, TEST_PANIC_SEED_VAR};

/// The seed that makes the worker panic (no other test uses the variable).
const POISON_SEED: u64 = 4_242_424;

fn settings(seed: u64) -> JobSettings {
    let mut s = JobSettings::new("builtin:cornell-box");
    s.width = Some(16);
    s.height = Some(16);
    s.spp = 4;
    s.tile_size = 8;
    s.seed = seed;
    s
}

/// Polls until job `id` reaches a terminal state (bounded); its state and error.
async fn finished(core: &Coordinator, id: u64) -> (String, Option<String>) {
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        let s = core.status(id).await.unwrap();
        if s.state.is_terminal() {
            return (s.state.as_str().to_string(), s.error);
        }
        assert!(Instant::now() < deadline, "job {id} did not finish: {s:?}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

#[test]
fn a_unit_whose_rendering_panics_fails_its_job_and_the_worker_lives_on() {
    // Before the runtime starts: no other thread reads the environment yet.
    std::env::set_var(TEST_PANIC_SEED_VAR, POISON_SEED.to_string());
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap()
        .block_on(scenario());
}

async fn scenario() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = CoordinatorConfig::new(dir.path());
    cfg.heartbeat_ms = 100;
    cfg.lease_ms = 2000;
    let core = Coordinator::open(cfg).await.unwrap();
    let (poisoned, _) = core.submit(settings(POISON_SEED), None).await.unwrap();

    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    let svc = WorkerGrpc::for_coordinator(core.clone()).into_server();
    tokio::spawn(async move {
        tonic::transport::Server::builder()
            .add_service(svc)
            .serve_with_incoming(tokio_stream::wrappers::TcpListenerStream::new(listener))
            .await
            .unwrap();
    });
    let (stop_tx, mut stop_rx) = tokio::sync::watch::channel(false);
    let worker = tokio::spawn(run(
        WorkerConfig {
            coordinators: vec![url],
            threads: 1,
            name: "w".into(),
            token: None,
            tls: None,
            inject_faults: 0.0,
        },
        async move {
            let _ = stop_rx.changed().await;
        },
    ));

    let (state, error) = finished(&core, poisoned.id).await;
    assert_eq!(state, "failed", "{error:?}");
    let error = error.unwrap_or_default();
    assert!(error.contains("rendering panicked"), "{error}");
    assert!(error.contains(TEST_PANIC_SEED_VAR), "{error}");

    // The same worker session goes on to render a healthy job, and was never blamed.
    let (healthy, _) = core.submit(settings(7), None).await.unwrap();
    let (state, error) = finished(&core, healthy.id).await;
    assert_eq!(state, "done", "{error:?}");
    let workers = core.workers().unwrap().workers;
    assert_eq!(workers.len(), 1, "the worker registered again: {workers:?}");
    assert_eq!(workers[0].faults, 0);
    assert!(!worker.is_finished(), "the worker ended");
    stop_tx.send(true).unwrap();
    worker.await.unwrap().unwrap();
}
