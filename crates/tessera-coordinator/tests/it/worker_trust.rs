//! A rogue worker against a real coordinator (ARCHITECTURE.md §6, "Untrusted workers"):
//! hand-written gRPC clients speaking `worker.proto`, on loopback, try what a probe found
//! the farm took on a worker's word — another worker's leases and id, a previous run's
//! fencing tokens, the whole queue, a job failed alone, absurd numbers and forged log
//! lines — and every attempt is refused without costing the honest workers anything.

use std::net::SocketAddr;
use std::time::Duration;

use tessera_api::JobSettings;
use tessera_coordinator::service::{Coordinator, CoordinatorConfig};
use tessera_coordinator::store::FaultFilter;
use tessera_coordinator::{serve_coordinator, Listeners};
use tessera_proto::v1;
use tessera_proto::v1::worker_service_client::WorkerServiceClient;
use tessera_proto::{WithSession, SESSION_METADATA};
use tessera_testkit::bounded;
use tonic::transport::Channel;
use tonic::Code;

type Client =
    WorkerServiceClient<tonic::service::interceptor::InterceptedService<Channel, WithSession>>;

/// A registered worker: its client (carrying its session), id, session and channel.
struct Worker {
    c: Client,
    id: u64,
    session: String,
    channel: Channel,
}

/// Serves `core` on loopback (until the test ends); returns the gRPC address.
async fn serving(core: &Coordinator) -> SocketAddr {
    let http = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let grpc = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = grpc.local_addr().unwrap();
    tokio::spawn(serve_coordinator(
        core.clone(),
        Listeners { http, grpc },
        std::future::pending(),
    ));
    addr
}

async fn register(grpc: SocketAddr, name: &str, threads: u32) -> Worker {
    let channel = tonic::transport::Endpoint::from_shared(format!("http://{grpc}"))
        .unwrap()
        .connect()
        .await
        .unwrap();
    let reg = WorkerServiceClient::new(channel.clone())
        .register(v1::RegisterRequest {
            name: name.into(),
            threads,
            version: "test".into(),
            capabilities: vec!["path".into()],
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(reg.session.len(), 32, "a 128-bit session in hex");
    Worker {
        c: WorkerServiceClient::with_interceptor(
            channel.clone(),
            WithSession::new(&reg.session).unwrap(),
        ),
        id: reg.worker_id,
        session: reg.session,
        channel,
    }
}

/// A request under `session` (any worker id), as a rogue forges it.
fn as_session<T>(msg: T, session: &str) -> tonic::Request<T> {
    let mut r = tonic::Request::new(msg);
    r.metadata_mut()
        .insert(SESSION_METADATA, session.parse().unwrap());
    r
}

/// A request with `session` if any.
fn maybe<T>(msg: T, session: &Option<String>) -> tonic::Request<T> {
    match session {
        Some(s) => as_session(msg, s),
        None => tonic::Request::new(msg),
    }
}

async fn lease(w: &mut Worker, max_units: u32) -> Vec<v1::Lease> {
    w.c.lease_work(v1::LeaseRequest {
        worker_id: w.id,
        max_units,
        wait_ms: 0,
    })
    .await
    .unwrap()
    .into_inner()
    .leases
}

/// A well-formed result of `l`, every value `v`, sent by `worker` with `fence`.
fn result(worker: u64, l: &v1::Lease, v: f32, fence: Vec<u8>) -> v1::SubmitResultRequest {
    let plan = tessera_farm::FramePlan::try_from(l.plan.unwrap()).unwrap();
    let unit = l.unit.unwrap();
    let rect = plan.tile(unit.tile);
    let n = 3 * unit.pass_count as usize * rect.pixel_count();
    v1::SubmitResultRequest {
        worker_id: worker,
        lease_id: l.lease_id,
        unit: Some(unit),
        width: rect.width,
        height: rect.height,
        pass_means: tessera_proto::means_to_bytes(&vec![v; n]),
        render_seconds: 0.01,
        job_id: l.job_id,
        rejected_samples: 0,
        traced_pixel_passes: 0,
        fence,
        bias: Vec::new(),
    }
}

async fn submit(c: &mut Client, r: v1::SubmitResultRequest) -> v1::SubmitResultResponse {
    c.submit_result(r).await.unwrap().into_inner()
}

fn cornell(width: u32, height: u32, tile: u32, spp: u32) -> JobSettings {
    let mut job = JobSettings::new("builtin:cornell-box");
    (job.width, job.height, job.tile_size, job.spp) = (Some(width), Some(height), tile, spp);
    job
}

/// A coordinator on `dir`'s store without spot checks (a held copy would wait for a
/// second worker).
fn config(dir: &tempfile::TempDir) -> CoordinatorConfig {
    let mut cfg = CoordinatorConfig::new(dir.path());
    cfg.spot_check_fraction = 0.0;
    cfg
}

fn faults_of(core: &Coordinator, name: &str) -> u64 {
    core.workers()
        .unwrap()
        .workers
        .iter()
        .filter(|w| w.name == name)
        .map(|w| w.faults)
        .sum()
}

/// A: a rogue guessing a frozen worker's lease ids delivers nothing, and impersonating
/// its id (heartbeats, returns, results) is refused; the honest worker's own copies are
/// then all taken and nothing is counted against it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_rogue_cannot_answer_or_act_under_another_workers_lease_or_id() {
    let dir = tempfile::tempdir().unwrap();
    let core = Coordinator::open(config(&dir)).await.unwrap();
    let (job, _) = core.submit(cornell(32, 32, 8, 1), None).await.unwrap();
    let grpc = serving(&core).await;
    let mut victim = bounded("register", register(grpc, "victim", 1)).await;
    let leases = lease(&mut victim, 64).await;
    assert_eq!(leases.len(), 16, "the victim holds every unit");
    let mut rogue = register(grpc, "rogue", 1).await;

    // Guessing lease ids around the victim's, for any unit, with no fence or a made-up
    // one: nothing is taken.
    let (lo, hi) = (leases[0].lease_id, leases[15].lease_id);
    let (mut accepted, mut forged_count) = (0, 1u64);
    for id in lo.saturating_sub(4)..=hi + 4 {
        for l in &leases {
            let mut forged = result(
                rogue.id,
                l,
                9.0,
                if id % 2 == 0 { vec![] } else { vec![0; 32] },
            );
            forged.lease_id = id;
            accepted += u32::from(submit(&mut rogue.c, forged).await.accepted);
            forged_count += 1;
        }
    }
    assert_eq!(accepted, 0, "a guessed lease was taken");
    // The victim's own fence, replayed by the rogue under its own id: not its lease.
    let stolen = result(rogue.id, &leases[0], 9.0, leases[0].fence.clone());
    assert!(!submit(&mut rogue.c, stolen).await.accepted);

    // Acting under the victim's id: without a session, or with the rogue's own.
    let mut bare = WorkerServiceClient::new(rogue.channel.clone());
    let beat = v1::HeartbeatRequest {
        worker_id: victim.id,
        lease_ids: leases.iter().map(|l| l.lease_id).collect(),
        paths_per_second: 0.0,
    };
    let back = v1::ReturnLeasesRequest {
        worker_id: victim.id,
        lease_ids: leases.iter().map(|l| l.lease_id).collect(),
        unusable: "cannot load".into(),
    };
    let as_victim = result(victim.id, &leases[1], 9.0, leases[1].fence.clone());
    for session in [None, Some(rogue.session.clone())] {
        let s = bare
            .heartbeat(maybe(beat.clone(), &session))
            .await
            .unwrap_err();
        assert_eq!(s.code(), Code::PermissionDenied, "{s}");
        let s = bare
            .return_leases(maybe(back.clone(), &session))
            .await
            .unwrap_err();
        assert_eq!(s.code(), Code::PermissionDenied, "{s}");
        let s = bare
            .submit_result(maybe(as_victim.clone(), &session))
            .await
            .unwrap_err();
        assert_eq!(s.code(), Code::PermissionDenied, "{s}");
    }
    // Under its own id, the victim's leases are not the rogue's to return.
    let returned = rogue
        .c
        .return_leases(v1::ReturnLeasesRequest {
            worker_id: rogue.id,
            ..back.clone()
        })
        .await
        .unwrap()
        .into_inner()
        .returned;
    assert_eq!(returned, 0);

    // The victim delivers every unit: all taken, nothing counted against it.
    for l in &leases {
        let r = submit(&mut victim.c, result(victim.id, l, 0.5, l.fence.clone())).await;
        assert!(r.accepted, "{}", r.reason);
    }
    let status = core.status(job.id).await.unwrap();
    assert_eq!(status.state.as_str(), "done", "{status:?}");
    assert_eq!(faults_of(&core, "victim"), 0);
    assert!(faults_of(&core, "rogue") > 0);
    eprintln!(
        "worker_trust A: 0 of {} forged results taken; rogue faults {}",
        forged_count,
        faults_of(&core, "rogue")
    );
}

/// B: a previous run's fencing tokens are taken after a restart only during the grace
/// period, for exactly the unit they named and from a worker of the name they were issued
/// to; never for a job created after the restart.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn previous_run_fences_name_one_unit_for_one_worker_within_the_grace() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = config(&dir);
    (cfg.grace_ms, cfg.lease_ms) = (300, 1_000);
    let core = Coordinator::open(cfg.clone()).await.unwrap();
    let (job, _) = core.submit(cornell(32, 32, 8, 1), None).await.unwrap();
    let grpc = serving(&core).await;
    let mut honest = register(grpc, "honest", 1).await;
    let leases = lease(&mut honest, 64).await;
    assert_eq!(leases.len(), 16);
    // One unit delivered, so the job resumes with work merged (and the frame is live).
    let r = submit(
        &mut honest.c,
        result(honest.id, &leases[0], 0.5, leases[0].fence.clone()),
    )
    .await;
    assert!(r.accepted, "{}", r.reason);
    core.store().close().await;
    drop(core);

    // The restart (same store, same fence key).
    let core = Coordinator::open(cfg).await.unwrap();
    let grpc = serving(&core).await;
    let mut honest = register(grpc, "honest", 1).await;
    let mut rogue = register(grpc, "rogue", 1).await;
    // The rogue resends the previous run's lease 1 (and the others) for every unit:
    // without the fence, or with the honest worker's fence for another unit or as itself.
    let mut accepted = 0;
    for l in &leases[1..] {
        for (id, fence) in [
            (leases[0].lease_id, vec![]),
            (leases[0].lease_id, leases[0].fence.clone()),
            (l.lease_id, l.fence.clone()),
        ] {
            let mut forged = result(rogue.id, l, 9.0, fence);
            forged.lease_id = id;
            accepted += u32::from(submit(&mut rogue.c, forged).await.accepted);
        }
    }
    assert_eq!(
        accepted, 0,
        "a previous run's lease was taken from the rogue"
    );
    // The honest worker's lease, for another unit than the one it named: refused.
    let mut moved = result(honest.id, &leases[2], 0.5, leases[1].fence.clone());
    moved.lease_id = leases[1].lease_id;
    assert!(!submit(&mut honest.c, moved).await.accepted);
    // Its own lease for its own unit, within the grace: taken.
    let r = submit(
        &mut honest.c,
        result(honest.id, &leases[1], 0.5, leases[1].fence.clone()),
    )
    .await;
    assert!(r.accepted, "{}", r.reason);

    // A job created after the restart: no previous-run lease answers for it.
    let (late, _) = core.submit(cornell(32, 32, 8, 1), None).await.unwrap();
    let mut replay = result(honest.id, &leases[2], 0.5, leases[2].fence.clone());
    replay.job_id = late.id;
    assert!(!submit(&mut honest.c, replay).await.accepted);

    // Past the grace (300 ms) and the resumed leases' deadline (1 s after it): refused,
    // its unit leased again, and not counted as the honest worker's fault.
    tokio::time::sleep(Duration::from_millis(1_500)).await;
    let before = faults_of(&core, "honest");
    let r = submit(
        &mut honest.c,
        result(honest.id, &leases[3], 0.5, leases[3].fence.clone()),
    )
    .await;
    assert!(
        !r.accepted,
        "a previous run's lease was taken after the grace"
    );
    assert!(r.reason.contains("previous run"), "{}", r.reason);
    assert_eq!(faults_of(&core, "honest"), before);
    let status = core.status(job.id).await.unwrap();
    assert_eq!(status.passes_done, 2, "{status:?}");
}

/// C: one worker claiming every thread and asking for every unit holds a bounded share,
/// and the other worker still gets work; one worker returning units "unusable" cannot
/// fail a job alone while another worker is live.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_worker_cannot_hold_a_whole_job_nor_fail_it_alone() {
    let dir = tempfile::tempdir().unwrap();
    let core = Coordinator::open(config(&dir)).await.unwrap();
    // 32 x 33 tiles of 8 x 8: 1,056 units.
    let (job, _) = core.submit(cornell(256, 264, 8, 1), None).await.unwrap();
    let grpc = serving(&core).await;
    let mut rogue = register(grpc, "rogue", u32::MAX).await;
    let mut honest = register(grpc, "honest", 1).await;
    let mut held = Vec::new();
    for _ in 0..8 {
        held.extend(lease(&mut rogue, u32::MAX).await);
    }
    assert!(held.len() <= 768, "one worker holds {} units", held.len());
    let theirs = lease(&mut honest, 4).await;
    assert!(!theirs.is_empty(), "the honest worker got no unit");

    // Three "unusable" returns from the rogue alone: the job goes on.
    for chunk in held.chunks(10).take(3) {
        rogue
            .c
            .return_leases(v1::ReturnLeasesRequest {
                worker_id: rogue.id,
                lease_ids: chunk.iter().map(|l| l.lease_id).collect(),
                unusable: "cannot load".into(),
            })
            .await
            .unwrap();
    }
    let status = core.status(job.id).await.unwrap();
    assert!(!status.state.is_terminal(), "{status:?}");
    eprintln!(
        "worker_trust C: rogue held {} of 1056 units, honest got {}",
        held.len(),
        theirs.len()
    );
}

/// D: pass means beyond the bound are refused, reported render seconds are bounded by
/// the lease's age, an "unusable" reason cannot forge a log line or job error, names are
/// counted in characters, duplicate names give one metric series, and a flood of bogus
/// results costs a bounded number of fault rows.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn worker_numbers_and_strings_are_bounded() {
    let dir = tempfile::tempdir().unwrap();
    let core = Coordinator::open(config(&dir)).await.unwrap();
    let (job, _) = core.submit(cornell(32, 32, 8, 1), None).await.unwrap();
    let grpc = serving(&core).await;
    let mut w = register(grpc, "dup", 1).await;
    let leases = lease(&mut w, 64).await;
    assert_eq!(leases.len(), 16);
    let _twin = register(grpc, "dup", 1).await;

    // f32::MAX, and just above the bound: refused; the bound itself: taken.
    for v in [f32::MAX, tessera_farm::MAX_PASS_MEAN * 1.01] {
        let r = submit(
            &mut w.c,
            result(w.id, &leases[0], v, leases[0].fence.clone()),
        )
        .await;
        assert!(!r.accepted, "{v} was taken");
        assert!(r.reason.contains("above the bound"), "{}", r.reason);
    }
    let mut big = result(
        w.id,
        &leases[0],
        tessera_farm::MAX_PASS_MEAN,
        leases[0].fence.clone(),
    );
    big.render_seconds = 1e308;
    let r = submit(&mut w.c, big).await;
    assert!(r.accepted, "{}", r.reason);
    let metrics = core.metrics().await.unwrap();
    let seconds: f64 = metrics
        .lines()
        .find_map(|l| l.strip_prefix("tessera_worker_render_seconds_total "))
        .unwrap()
        .parse()
        .unwrap();
    assert!(seconds.is_finite() && seconds < 120.0, "{seconds}");
    let series = metrics
        .lines()
        .filter(|l| l.starts_with("tessera_worker_paths_per_second{worker=\"dup\"}"))
        .count();
    assert_eq!(series, 1, "{metrics}");

    // Names: 200 characters of two bytes each are 200 characters; 201 are too many.
    let mut plain = WorkerServiceClient::new(w.channel.clone());
    let reg = |name: String| v1::RegisterRequest {
        name,
        threads: 1,
        version: "test".into(),
        capabilities: vec![],
    };
    assert!(plain.register(reg("é".repeat(200))).await.is_ok());
    let s = plain.register(reg("é".repeat(201))).await.unwrap_err();
    assert_eq!(s.code(), Code::InvalidArgument, "{s}");

    // 3,000 bogus results in a burst: every one counted, a bounded number stored.
    for i in 0..3_000u64 {
        let mut bogus = result(w.id, &leases[1], 0.5, vec![]);
        bogus.lease_id = 1_000_000 + i;
        assert!(!submit(&mut w.c, bogus).await.accepted);
    }
    assert_eq!(
        core.workers()
            .unwrap()
            .workers
            .iter()
            .find(|x| x.id == w.id)
            .unwrap()
            .faults,
        3_002,
        "the two means above the bound and the 3,000 bogus results"
    );
    let rows = core
        .store()
        .count_faults(&FaultFilter {
            job: None,
            worker: Some("dup".into()),
        })
        .await
        .unwrap();
    assert!(rows <= 60, "{rows} fault rows for a burst of 3,000");

    // A reason with a newline (and an escape sequence), returned by the only live
    // workers: the job fails, its error on one line.
    for l in leases[2..5].iter() {
        w.c.return_leases(v1::ReturnLeasesRequest {
            worker_id: w.id,
            lease_ids: vec![l.lease_id],
            unusable: "oops\nERROR forged line \u{1b}[31m".into(),
        })
        .await
        .unwrap();
    }
    let status = core.status(job.id).await.unwrap();
    // The twin and the "é" workers are live too: one name ("dup") of three is not
    // enough to fail the job.
    assert!(!status.state.is_terminal(), "{status:?}");
    eprintln!("worker_trust D: {rows} fault rows stored for 3,000 bogus results");
}

/// D: the "unusable" reason that fails a job is escaped: no newline or escape character
/// reaches the job's error (a farm of one worker, which fails the job alone).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_unusable_reason_cannot_forge_a_line() {
    let dir = tempfile::tempdir().unwrap();
    let core = Coordinator::open(config(&dir)).await.unwrap();
    let (job, _) = core.submit(cornell(32, 32, 8, 1), None).await.unwrap();
    let grpc = serving(&core).await;
    let mut w = register(grpc, "alone", 1).await;
    for _ in 0..3 {
        let l = lease(&mut w, 1).await;
        w.c.return_leases(v1::ReturnLeasesRequest {
            worker_id: w.id,
            lease_ids: vec![l[0].lease_id],
            unusable: format!("oops\nERROR forged line \u{1b}[31m{}", "x".repeat(2_000)),
        })
        .await
        .unwrap();
    }
    let status = core.status(job.id).await.unwrap();
    assert_eq!(status.state.as_str(), "failed", "{status:?}");
    let error = status.error.unwrap();
    assert!(
        !error.contains('\n') && !error.contains('\u{1b}'),
        "{error:?}"
    );
    assert!(
        error.contains("oops\\nERROR forged line \\u{1b}[31m"),
        "{error:?}"
    );
    assert!(error.chars().count() < 700, "{}", error.len());
}
