//! High availability on PostgreSQL (docs/store.md, "High availability"): two
//! real `tessera coordinator` processes on one fresh database (a schema of its own, see
//! `tessera_testkit::postgres`), one active and one standby, and workers that know both.
//! `kill -9` of the active one mid-job: the standby takes over, the job completes
//! byte-identical to `tessera render` and nothing is merged twice. A standby refuses
//! workers; a coordinator whose lock connection is lost stops granting; a frozen active
//! coordinator woken after the takeover writes nothing that lands (the deposed writer).
//!
//! Skipped without `TESSERA_TEST_POSTGRES` unless `TESSERA_REQUIRE_POSTGRES=1`.

use crate::common;

use std::time::{Duration, Instant};

use common::farm::{
    cornell_job, local_render, start_coordinator, start_worker_of, stored_passes, wait_done,
};
use common::farm::{Coord, TIMEOUT};
use common::{http_get, poll, temp_dir, wait_for};
use sqlx::Connection;
use tessera_api::client::Client;
use tessera_proto::v1;

/// The liveness bound of a takeover (the issue asks for "within a few seconds"; the
/// measured time is printed).
const TAKEOVER_BOUND: Duration = Duration::from_secs(15);

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap()
}

/// A fresh database URL, or `None` when PostgreSQL tests are skipped.
fn fresh_database(name: &str) -> Option<String> {
    runtime().block_on(tessera_testkit::postgres::fresh_database(name))
}

/// Starts a coordinator on the PostgreSQL `url` on port 0 listeners.
fn coordinator(dir: &std::path::Path, name: &str, url: &str) -> Coord {
    start_coordinator(
        &dir.join(name),
        "127.0.0.1:0",
        "127.0.0.1:0",
        &["--store", url],
    )
}

/// `/readyz` of `c`: (status, body).
fn readyz(c: &Coord) -> (u16, String) {
    http_get(&c.http, "/readyz")
}

/// Waits until `c` reports standby on `/readyz` (503 `standby: ...`) while `/healthz`
/// is 200 (alive).
fn wait_standby(c: &Coord, what: &str) {
    wait_for(what, Duration::from_secs(15), || match readyz(c) {
        (503, body) if body.starts_with("standby:") => Ok(()),
        (status, body) => Err(format!("{status} {body}")),
    });
    assert_eq!(http_get(&c.http, "/healthz").0, 200, "a standby is alive");
}

/// A worker's `Register` and `LeaseWork` on the gRPC port `grpc`: the status of the
/// first refusal, or `None` when both were answered.
fn worker_calls(grpc: &str) -> Option<tonic::Status> {
    runtime().block_on(async {
        let mut c = v1::worker_service_client::WorkerServiceClient::connect(grpc.to_string())
            .await
            .unwrap();
        let reg = c
            .register(v1::RegisterRequest {
                name: "probe".into(),
                threads: 1,
                version: "test".into(),
                capabilities: vec![],
            })
            .await;
        let (worker_id, session) = match reg {
            Ok(r) => {
                let r = r.into_inner();
                (r.worker_id, r.session)
            }
            Err(s) => return Some(s),
        };
        let mut lease = tonic::Request::new(v1::LeaseRequest {
            worker_id,
            max_units: 1,
            wait_ms: 0,
        });
        lease
            .metadata_mut()
            .insert(tessera_proto::SESSION_METADATA, session.parse().unwrap());
        c.lease_work(lease).await.err()
    })
}

#[test]
fn the_standby_takes_over_after_kill9_and_the_job_completes_byte_identical() {
    let Some(url) = fresh_database("ha_failover") else {
        return;
    };
    let dir = temp_dir("ha", "failover");
    let s = cornell_job(48, 48, 96);
    let reference = local_render(&dir, &s);

    let mut a = coordinator(&dir, "a", &url);
    a.wait_active();
    let b = coordinator(&dir, "b", &url);
    wait_standby(&b, "the second coordinator to stand by");
    // A standby refuses workers with a status naming its state.
    let refused = worker_calls(&b.grpc).expect("the standby answered a worker");
    assert_eq!(refused.code(), tonic::Code::Unavailable, "{refused:?}");
    assert!(refused.message().contains("standby"), "{refused:?}");

    let grpc = [a.grpc.as_str(), b.grpc.as_str()];
    let logs = [dir.join("w1.log"), dir.join("w2.log")];
    let _w1 = start_worker_of(&grpc, "w1", &[], Some(&logs[0]));
    // The second worker lists the standby first: it must move on to the active one.
    let _w2 = start_worker_of(&[grpc[1], grpc[0]], "w2", &[], Some(&logs[1]));
    let client_a = Client::new(&a.http, None);
    let job = client_a.submit(&s, None).unwrap();
    poll("a quarter of the passes", TIMEOUT, || {
        let j = client_a.job(job.id).unwrap();
        j.passes_done * 4 >= j.passes_planned
    });
    // Killed once the store holds some of them (`stored_passes`).
    poll("passes committed to the store", TIMEOUT, || {
        stored_passes(&url, job.id) > 0
    });
    let before = client_a.job(job.id).unwrap().passes_done;

    let killed = Instant::now();
    a.proc.kill9();
    b.wait_active();
    let takeover = killed.elapsed();
    println!(
        "takeover: the standby was active {:.0} ms after kill -9 of the active coordinator",
        takeover.as_secs_f64() * 1000.0
    );
    assert!(
        takeover < TAKEOVER_BOUND,
        "takeover took {takeover:?} (bound {TAKEOVER_BOUND:?})"
    );

    let client_b = Client::new(&b.http, None);
    // The status counts passes merged in memory, also those whose checkpoint was not
    // committed yet (their workers were not told "accepted" and deliver them again), so
    // the new coordinator may start a little behind what the old one showed.
    let resumed = client_b.job(job.id).unwrap();
    println!(
        "passes merged: {before} shown by the killed coordinator, {} resumed by the new one",
        resumed.passes_done
    );
    assert!(
        resumed.passes_done > 0,
        "merged passes were lost in the takeover"
    );
    let done = wait_done(&client_b, job.id);
    println!(
        "job done {:.0} ms after the kill",
        killed.elapsed().as_secs_f64() * 1000.0
    );
    // Nothing merged twice: every tile has exactly its planned passes and the job's
    // samples per pixel are exactly the requested ones (a pass merged twice would add
    // to both, and change the image).
    assert_eq!(done.passes_done, done.passes_planned);
    assert_eq!(done.spp_so_far, f64::from(s.spp));
    let tiles = client_b.tiles(job.id).unwrap();
    for t in &tiles.tiles {
        assert_eq!(
            t.passes, tiles.passes_planned,
            "tile {} merged {} passes of {}",
            t.index, t.passes, tiles.passes_planned
        );
    }
    let exr = client_b.image(job.id, "exr").unwrap();
    assert!(
        exr == reference,
        "the EXR after a failover differs from tessera render"
    );
    for log in &logs {
        let text = std::fs::read_to_string(log).unwrap_or_default();
        let carried = text.contains("submitting results rendered before the reconnection");
        println!(
            "{}: {}",
            log.display(),
            if carried {
                "delivered results of the killed coordinator's leases to the new one"
            } else {
                "had no result in hand at the kill"
            }
        );
    }
}

#[test]
fn a_coordinator_that_loses_its_lock_connection_stops_granting() {
    let Some(url) = fresh_database("ha_lock_lost") else {
        return;
    };
    let dir = temp_dir("ha", "lock-lost");
    let a = coordinator(&dir, "a", &url);
    a.wait_active();
    let b = coordinator(&dir, "b", &url);
    wait_standby(&b, "the second coordinator to stand by");
    assert_eq!(worker_calls(&a.grpc).map(|s| s.code()), None);

    // End the active coordinator's lock session from the server side, as a failing
    // network or an operator's pg_terminate_backend would.
    let pid = a.proc.pid().unwrap();
    let lost = Instant::now();
    let ended: Vec<bool> = runtime().block_on(async {
        let mut conn = sqlx::PgConnection::connect(&url).await.unwrap();
        sqlx::query_scalar(
            "SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE application_name = $1",
        )
        .bind(format!("tessera-lock {pid}"))
        .fetch_all(&mut conn)
        .await
        .unwrap()
    });
    assert_eq!(ended, [true], "the lock session of coordinator {pid}");
    wait_standby(&a, "the coordinator that lost its lock to stand by");
    let stepped_down = lost.elapsed();
    let refused = worker_calls(&a.grpc).expect("a deposed coordinator answered a worker");
    assert_eq!(refused.code(), tonic::Code::Unavailable, "{refused:?}");
    b.wait_active();
    println!(
        "lock lost: stopped serving after {:.0} ms, the standby active after {:.0} ms",
        stepped_down.as_secs_f64() * 1000.0,
        lost.elapsed().as_secs_f64() * 1000.0
    );
    assert_eq!(worker_calls(&b.grpc).map(|s| s.code()), None);
    // The deposed one stays a standby while the other holds the lock.
    assert!(readyz(&a).1.starts_with("standby:"));
}

/// Sends `signal` (`STOP`, `CONT`) to the process `pid`.
fn signal(pid: u32, signal: &str) {
    let ok = std::process::Command::new("kill")
        .arg(format!("-{signal}"))
        .arg(pid.to_string())
        .status()
        .is_ok_and(|s| s.success());
    assert!(ok, "kill -{signal} {pid}");
}

/// The deposed writer: the active coordinator is frozen (`SIGSTOP`, as a long
/// GC-like pause or a suspended VM would), the standby takes over once the frozen one's
/// lock session times out, and the frozen one is then woken (`SIGCONT`) with leases,
/// merged passes and possibly a group commit of its own in hand. Whatever it still tries
/// to write is fenced: a job submitted to it is refused and lands nowhere, it stands by,
/// and the job completes on the new coordinator byte-identical to `tessera render` with
/// every tile at exactly its planned passes.
#[test]
fn a_frozen_then_woken_coordinator_writes_nothing_that_lands() {
    let Some(url) = fresh_database("ha_deposed_writer") else {
        return;
    };
    let dir = temp_dir("ha", "deposed-writer");
    let s = cornell_job(48, 48, 96);
    let reference = local_render(&dir, &s);

    let a = coordinator(&dir, "a", &url);
    a.wait_active();
    let b = coordinator(&dir, "b", &url);
    wait_standby(&b, "the second coordinator to stand by");
    let grpc = [a.grpc.as_str(), b.grpc.as_str()];
    let _w1 = start_worker_of(&grpc, "w1", &[], Some(&dir.join("w1.log")));
    let _w2 = start_worker_of(&grpc, "w2", &[], Some(&dir.join("w2.log")));
    let client_a = Client::new(&a.http, None);
    let job = client_a.submit(&s, None).unwrap();
    poll("a quarter of the passes", TIMEOUT, || {
        let j = client_a.job(job.id).unwrap();
        j.passes_done * 4 >= j.passes_planned
    });

    let pid = a.proc.pid().unwrap();
    let frozen = Instant::now();
    signal(pid, "STOP");
    b.wait_active();
    println!(
        "takeover: the standby was active {:.0} ms after the active one froze",
        frozen.elapsed().as_secs_f64() * 1000.0
    );
    signal(pid, "CONT");
    // Woken, it may not have noticed yet that it lost the lock: either way its write
    // must not land (a fenced insert or a refusal as not active, both 503). If the request
    // arrives while it hands its sockets from the active server to the standby one, the
    // active server's graceful shutdown closes the connection before reading it (CI,
    // 2026-12-05: "Peer disconnected"): refused too. Whether anything landed is checked on
    // the new coordinator's job list at the end.
    let refused = client_a.submit(&cornell_job(16, 16, 4), None);
    match refused {
        Err(tessera_api::client::ClientError::Api { status: 503, .. }) => {}
        Err(tessera_api::client::ClientError::Transport(e)) => {
            println!("the submission to the woken coordinator was cut off: {e}");
        }
        other => panic!("the woken, deposed coordinator accepted a job: {other:?}"),
    }
    wait_standby(&a, "the woken coordinator to stand by");

    let client_b = Client::new(&b.http, None);
    let done = wait_done(&client_b, job.id);
    assert_eq!(done.passes_done, done.passes_planned);
    assert_eq!(done.spp_so_far, f64::from(s.spp));
    let tiles = client_b.tiles(job.id).unwrap();
    for t in &tiles.tiles {
        assert_eq!(
            t.passes, tiles.passes_planned,
            "tile {} merged {} passes of {}",
            t.index, t.passes, tiles.passes_planned
        );
    }
    assert!(
        client_b.image(job.id, "exr").unwrap() == reference,
        "the EXR after the frozen coordinator woke differs from tessera render"
    );
    let jobs = client_b.jobs(10, None).unwrap().jobs;
    assert_eq!(
        jobs.iter().map(|j| j.id).collect::<Vec<_>>(),
        [job.id],
        "a job submitted to the deposed coordinator landed"
    );
}
