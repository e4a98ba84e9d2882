//! `tessera_coordinator::serve` on port-0 listeners: it answers HTTP and gRPC, tells busy
//! workers to stop once shut down, keeps the gRPC port open while they hold leases, and
//! returns. Every wait is bounded by [`tessera_testkit::HANG`], used only to fail instead
//! of hanging.

use std::net::SocketAddr;
use std::time::Duration;

use tessera_api::JobSettings;
use tessera_coordinator::service::{Coordinator, CoordinatorConfig};
use tessera_coordinator::{serve, serve_coordinator, Listeners, ServeError};
use tessera_proto::v1;
use tessera_proto::v1::worker_service_client::WorkerServiceClient;
use tessera_testkit::bounded;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::sync::oneshot;

async fn listeners() -> (Listeners, SocketAddr, SocketAddr) {
    let http = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let grpc = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let (h, g) = (http.local_addr().unwrap(), grpc.local_addr().unwrap());
    (Listeners { http, grpc }, h, g)
}

/// A plain HTTP/1.1 GET; returns the whole response.
async fn get(addr: SocketAddr, path: &str) -> String {
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    let req = format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n");
    s.write_all(req.as_bytes()).await.unwrap();
    let mut out = String::new();
    s.read_to_string(&mut out).await.unwrap();
    out
}

type Client = WorkerServiceClient<
    tonic::service::interceptor::InterceptedService<
        tonic::transport::Channel,
        tessera_proto::WithSession,
    >,
>;

/// Registers a worker; its client carries the session from then on.
async fn register(grpc: SocketAddr) -> (Client, u64) {
    let channel = tonic::transport::Endpoint::from_shared(format!("http://{grpc}"))
        .unwrap()
        .connect()
        .await
        .unwrap();
    let reg = WorkerServiceClient::new(channel.clone())
        .register(v1::RegisterRequest {
            name: "test".into(),
            threads: 1,
            version: "test".into(),
            capabilities: vec!["path".into()],
        })
        .await
        .unwrap()
        .into_inner();
    let session = tessera_proto::WithSession::new(&reg.session).unwrap();
    (
        WorkerServiceClient::with_interceptor(channel, session),
        reg.worker_id,
    )
}

type Served = tokio::task::JoinHandle<Result<(), ServeError>>;

/// A coordinator over a fresh store in `dir` with one small job (16x16, 4 spp) queued.
async fn coordinator_with_a_job(dir: &tempfile::TempDir) -> (Coordinator, tessera_api::JobStatus) {
    let core = Coordinator::open(CoordinatorConfig::new(dir.path()))
        .await
        .unwrap();
    let mut job = JobSettings::new("builtin:cornell-box");
    (job.width, job.height, job.spp) = (Some(16), Some(16), 4);
    let (job, _) = core.submit(job, None).await.unwrap();
    (core, job)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn serve_answers_http_and_grpc_and_returns_on_shutdown() {
    let dir = tempfile::tempdir().unwrap();
    let (ls, http, grpc) = listeners().await;
    let (tx, rx) = oneshot::channel::<()>();
    // `serve`'s future is not `Send` (see its documentation): run it beside the client
    // rather than spawning it.
    let server = serve(CoordinatorConfig::new(dir.path()), ls, async {
        let _ = rx.await;
    });
    let client = async {
        let health = get(http, "/healthz").await;
        assert!(health.starts_with("HTTP/1.1 200"), "{health}");
        let (_client, id) = register(grpc).await;
        assert!(id > 0);
        tx.send(()).unwrap();
    };
    let (served, ()) = bounded("serve, a request, shutdown", async {
        tokio::join!(server, client)
    })
    .await;
    served.unwrap();
    // Both ports are closed now.
    assert!(tokio::net::TcpStream::connect(http).await.is_err());
    assert!(tokio::net::TcpStream::connect(grpc).await.is_err());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_busy_worker_is_told_to_stop_and_can_still_return_its_leases() {
    let dir = tempfile::tempdir().unwrap();
    let (core, _job) = coordinator_with_a_job(&dir).await;
    let (ls, _http, grpc) = listeners().await;
    let (tx, rx) = oneshot::channel::<()>();
    let served: Served = tokio::spawn(serve_coordinator(core, ls, async {
        let _ = rx.await;
    }));
    let (mut client, worker_id) = bounded("Register", register(grpc)).await;
    let leases = bounded(
        "LeaseWork",
        client.lease_work(v1::LeaseRequest {
            worker_id,
            max_units: 1,
            wait_ms: 0,
        }),
    )
    .await
    .unwrap()
    .into_inner()
    .leases;
    let lease_ids: Vec<u64> = leases.iter().map(|l| l.lease_id).collect();
    assert_eq!(lease_ids.len(), 1);
    let beat = v1::HeartbeatRequest {
        worker_id,
        lease_ids: lease_ids.clone(),
        paths_per_second: 0.0,
    };
    let hb = client.heartbeat(beat.clone()).await.unwrap().into_inner();
    assert!(
        !hb.shutdown,
        "shutdown before the coordinator was asked to stop"
    );

    tx.send(()).unwrap();
    bounded("a heartbeat answering shutdown", async {
        loop {
            let hb = client.heartbeat(beat.clone()).await.unwrap().into_inner();
            if hb.shutdown {
                assert_eq!(
                    hb.extended.len(),
                    1,
                    "the lease is still extended while draining"
                );
                break;
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    })
    .await;
    // The worker holds a lease, so the gRPC port is still open: it gives the lease back.
    let back = client
        .return_leases(v1::ReturnLeasesRequest {
            worker_id,
            lease_ids,
            unusable: String::new(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(back.returned, 1);
    bounded("serve returning after the worker drained", served)
        .await
        .unwrap()
        .unwrap();
}

/// A worker that cannot load a job's scene returns its leases saying why; after
/// `MAX_UNUSABLE_RETURNS` such returns the job fails with the reason instead of being
/// leased again forever (the robustness issue's poison-scene hot loop), while a plain
/// return (a draining worker) counts nothing.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_scene_no_worker_can_use_fails_its_job() {
    use tessera_coordinator::service::MAX_UNUSABLE_RETURNS;
    let dir = tempfile::tempdir().unwrap();
    let (core, job) = coordinator_with_a_job(&dir).await;
    // Queued: neither started nor finished.
    assert_eq!((job.started_unix_ms, job.finished_unix_ms), (None, None));
    let (ls, _http, grpc) = listeners().await;
    let (_tx, rx) = oneshot::channel::<()>();
    let _served: Served = tokio::spawn(serve_coordinator(core.clone(), ls, async {
        let _ = rx.await;
    }));
    let (mut client, worker_id) = bounded("Register", register(grpc)).await;
    let lease = |client: &mut Client| {
        let mut c = client.clone();
        async move {
            loop {
                let leases = c
                    .lease_work(v1::LeaseRequest {
                        worker_id,
                        max_units: 1,
                        wait_ms: 0,
                    })
                    .await
                    .unwrap()
                    .into_inner()
                    .leases;
                if !leases.is_empty() {
                    return leases.iter().map(|l| l.lease_id).collect::<Vec<u64>>();
                }
                tokio::time::sleep(Duration::from_millis(10)).await;
            }
        }
    };
    // A plain return does not count.
    let ids = bounded("a lease", lease(&mut client)).await;
    let back = client
        .return_leases(v1::ReturnLeasesRequest {
            worker_id,
            lease_ids: ids,
            unusable: String::new(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(back.returned, 1);
    // Running since its first lease, not finished.
    let running = core.status(job.id).await.unwrap();
    let started = running.started_unix_ms.expect("started at the first lease");
    assert!(started >= job.created_unix_ms);
    assert_eq!(running.finished_unix_ms, None);
    for i in 0..MAX_UNUSABLE_RETURNS {
        assert!(!core.status(job.id).await.unwrap().state.is_terminal());
        let ids = bounded("a lease", lease(&mut client)).await;
        let back = client
            .return_leases(v1::ReturnLeasesRequest {
                worker_id,
                lease_ids: ids,
                unusable: format!("scene builtin:cornell-box: out of memory (try {i})"),
            })
            .await
            .unwrap()
            .into_inner();
        assert_eq!(back.returned, 1);
    }
    let status = core.status(job.id).await.unwrap();
    assert_eq!(status.state.as_str(), "failed");
    // A final state records when it was reached; the start stays the first lease's.
    assert_eq!(status.started_unix_ms, Some(started));
    let finished = status.finished_unix_ms.expect("a failed job has finished");
    assert!(finished >= started);
    let error = status.error.unwrap_or_default();
    assert!(error.contains("could not use the scene"), "{error}");
    assert!(error.contains("out of memory"), "{error}");
    // And nothing is leased any more.
    let leases = client
        .lease_work(v1::LeaseRequest {
            worker_id,
            max_units: 4,
            wait_ms: 0,
        })
        .await
        .unwrap()
        .into_inner()
        .leases;
    assert!(leases.is_empty());
}

/// A lease request with `wait_ms` is a long poll. With nothing queued it
/// waits; a job queued meanwhile wakes it, and it answers with units (the wait counted
/// `woken`, not `deadline`: without the wake-up it would find them only at its deadline).
/// With nothing arriving it ends at its deadline, empty.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_waiting_lease_request_is_woken_by_a_job_queued() {
    let dir = tempfile::tempdir().unwrap();
    let core = Coordinator::open(CoordinatorConfig::new(dir.path()))
        .await
        .unwrap();
    let worker = core.register_worker("w".into(), 1, "test").unwrap();
    // Nothing comes: the wait ends at its deadline, with no unit.
    let grant = core
        .lease_waiting(worker, 1, Duration::from_millis(20))
        .await
        .unwrap();
    assert!(grant.units.is_empty());
    assert_eq!(core.lease_wait_counts(), (0, 0, 1));
    // The longest wait there is, so that only a wake-up ends it early.
    let waiting = tokio::spawn({
        let core = core.clone();
        async move {
            core.lease_waiting(worker, 4, Duration::from_secs(2))
                .await
                .unwrap()
        }
    });
    bounded("the request waiting", async {
        while core.lease_wait_counts().0 != 1 {
            tokio::time::sleep(Duration::from_millis(2)).await;
        }
    })
    .await;
    let mut job = JobSettings::new("builtin:cornell-box");
    (job.width, job.height, job.spp) = (Some(16), Some(16), 4);
    core.submit(job, None).await.unwrap();
    let grant = bounded("the woken request", waiting).await.unwrap();
    assert!(!grant.units.is_empty(), "the woken request found no unit");
    let (now, woken, deadline) = core.lease_wait_counts();
    assert_eq!((now, woken), (0, 1), "the wait was not woken by the job");
    assert_eq!(deadline, 1, "only the first wait ended at its deadline");
    let metrics = core.metrics().await.unwrap();
    assert!(
        metrics.contains("tessera_lease_waits_total{ended=\"woken\"} 1"),
        "{metrics}"
    );
    assert!(
        metrics.contains("tessera_lease_requests_waiting 0"),
        "{metrics}"
    );
}

/// A worker stopping says so with a plain ReturnLeases (empty when it holds nothing
/// unstarted) while it finishes the unit it renders: /workers shows it draining until it
/// asks for work again. An unusable return is not a drain.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_worker_returning_its_leases_is_draining_until_it_leases_again() {
    use tessera_api::WorkerState;
    let dir = tempfile::tempdir().unwrap();
    let (core, _job) = coordinator_with_a_job(&dir).await;
    let (ls, _http, grpc) = listeners().await;
    let (_tx, rx) = oneshot::channel::<()>();
    let _served: Served = tokio::spawn(serve_coordinator(core.clone(), ls, async {
        let _ = rx.await;
    }));
    let (mut client, worker_id) = bounded("Register", register(grpc)).await;
    let state = || {
        let list = core.workers().unwrap();
        let w = list.workers.iter().find(|w| w.id == worker_id).unwrap();
        w.state
    };
    let lease = v1::LeaseRequest {
        worker_id,
        max_units: 1,
        wait_ms: 0,
    };
    let held = client.lease_work(lease).await.unwrap().into_inner().leases;
    assert_eq!(held.len(), 1);
    assert_eq!(state(), WorkerState::Busy);
    let give_back = |unusable: &str| v1::ReturnLeasesRequest {
        worker_id,
        lease_ids: Vec::new(),
        unusable: unusable.into(),
    };
    let back = client.return_leases(give_back("")).await.unwrap();
    assert_eq!(back.into_inner().returned, 0, "nothing was given back");
    assert_eq!(state(), WorkerState::Draining, "while it finishes its unit");
    let more = client.lease_work(lease).await.unwrap().into_inner().leases;
    assert_eq!(more.len(), 1);
    assert_eq!(state(), WorkerState::Busy, "asking for work ends a drain");
    client
        .return_leases(give_back("scene: cannot load"))
        .await
        .unwrap();
    assert_eq!(
        state(),
        WorkerState::Busy,
        "an unusable return is not a drain"
    );
}
