//! The HTTP API's smaller promises (robustness issue, item 8), over a real port: the
//! token guards `/metrics`, the `Bearer` scheme in any case, idempotency conflicts, the
//! `limit` range, canonical job ids, job counts after a restart, lost workers forgotten,
//! results from unknown workers not listed. Every wait is bounded by [`tessera_testkit::HANG`].

use std::net::SocketAddr;
use std::time::Duration;

use tessera_api::{JobSettings, JobState};
use tessera_coordinator::service::{Coordinator, CoordinatorConfig};
use tessera_coordinator::{serve_coordinator, Listeners};
use tessera_testkit::bounded;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::sync::oneshot;

async fn start(
    cfg: CoordinatorConfig,
) -> (SocketAddr, SocketAddr, Coordinator, oneshot::Sender<()>) {
    let core = Coordinator::open(cfg).await.unwrap();
    let http = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let grpc = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let (h, g) = (http.local_addr().unwrap(), grpc.local_addr().unwrap());
    let (tx, rx) = oneshot::channel::<()>();
    tokio::spawn(serve_coordinator(
        core.clone(),
        Listeners { http, grpc },
        async {
            let _ = rx.await;
        },
    ));
    (h, g, core, tx)
}

/// The answer to one request: status, lower-cased head, body.
struct Answer {
    status: u16,
    body: String,
}

impl Answer {
    fn json(&self) -> serde_json::Value {
        serde_json::from_str(&self.body).unwrap_or_else(|e| panic!("{e}: {}", self.body))
    }
}

/// One HTTP/1.1 request (`headers` are whole lines without CRLF).
async fn request(
    addr: SocketAddr,
    method: &str,
    path: &str,
    headers: &[&str],
    body: &str,
) -> Answer {
    bounded("an HTTP request", async {
        let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
        let mut req = format!(
            "{method} {path} HTTP/1.1\r\nHost: t\r\nConnection: close\r\nContent-Length: {}\r\n",
            body.len()
        );
        for h in headers {
            req.push_str(h);
            req.push_str("\r\n");
        }
        req.push_str("\r\n");
        req.push_str(body);
        s.write_all(req.as_bytes()).await.unwrap();
        let mut out = Vec::new();
        s.read_to_end(&mut out).await.unwrap();
        let text = String::from_utf8_lossy(&out).into_owned();
        let (head, body) = text.split_once("\r\n\r\n").unwrap_or((&text, ""));
        let status = head
            .split(' ')
            .nth(1)
            .and_then(|s| s.parse().ok())
            .unwrap_or_else(|| panic!("no status in {head:?}"));
        Answer {
            status,
            body: body.to_string(),
        }
    })
    .await
}

const JOB: &str = r#"{"scene":"builtin:cornell-box","width":16,"height":16,"spp":4}"#;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_api_token_guards_metrics_and_any_case_of_bearer_is_accepted() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = CoordinatorConfig::new(dir.path());
    cfg.api_token = Some("s3cret".into());
    let (http, _, _core, _stop) = start(cfg).await;
    assert_eq!(request(http, "GET", "/metrics", &[], "").await.status, 401);
    let wrong = ["Authorization: Bearer nope"];
    assert_eq!(
        request(http, "GET", "/metrics", &wrong, "").await.status,
        401
    );
    assert_eq!(request(http, "GET", "/healthz", &[], "").await.status, 200);
    for scheme in ["Bearer", "bearer", "BEARER"] {
        let auth = format!("Authorization: {scheme} s3cret");
        let m = request(http, "GET", "/metrics", &[&auth], "").await;
        assert_eq!(m.status, 200, "{scheme}: {}", m.body);
        assert!(
            m.body.contains("tessera_jobs{state=\"queued\"}"),
            "{}",
            m.body
        );
        assert!(
            m.body.contains("tessera_http_connections_open"),
            "{}",
            m.body
        );
        let jobs = request(http, "GET", "/api/v1/jobs", &[&auth], "").await;
        assert_eq!(jobs.status, 200, "{scheme}: {}", jobs.body);
    }
    assert_eq!(
        request(http, "GET", "/api/v1/jobs", &[], "").await.status,
        401
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_idempotency_key_reused_with_other_settings_is_a_conflict() {
    let dir = tempfile::tempdir().unwrap();
    let (http, _, _core, _stop) = start(CoordinatorConfig::new(dir.path())).await;
    let key = [
        "Content-Type: application/json",
        "idempotency-key: render-42",
    ];
    let first = request(http, "POST", "/api/v1/jobs", &key, JOB).await;
    assert_eq!(first.status, 201, "{}", first.body);
    let id = first.json()["id"].as_u64().unwrap();
    // The same settings (even written differently) are the same request.
    let same = r#"{"spp":4,"height":16,"width":16,"scene":"builtin:cornell-box"}"#;
    let again = request(http, "POST", "/api/v1/jobs", &key, same).await;
    assert_eq!(again.status, 200, "{}", again.body);
    assert_eq!(again.json()["id"].as_u64(), Some(id));
    let other = r#"{"scene":"builtin:cornell-box","width":16,"height":16,"spp":8}"#;
    let conflict = request(http, "POST", "/api/v1/jobs", &key, other).await;
    assert_eq!(conflict.status, 409, "{}", conflict.body);
    let e = conflict.json();
    assert_eq!(e["error"]["code"], "conflict");
    assert_eq!(e["error"]["field"], "idempotency-key");
    assert!(
        e["error"]["message"]
            .as_str()
            .unwrap()
            .contains("render-42"),
        "{e}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn limit_outside_its_range_and_non_canonical_ids_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let (http, _, _core, _stop) = start(CoordinatorConfig::new(dir.path())).await;
    let json = ["Content-Type: application/json"];
    assert_eq!(
        request(http, "POST", "/api/v1/jobs", &json, JOB)
            .await
            .status,
        201
    );
    for bad in ["0", "201", "-1", "abc", "99999999999"] {
        let a = request(http, "GET", &format!("/api/v1/jobs?limit={bad}"), &[], "").await;
        assert_eq!(a.status, 400, "limit={bad}: {}", a.body);
        assert_eq!(
            a.json()["error"]["field"],
            "limit",
            "limit={bad}: {}",
            a.body
        );
    }
    for good in ["1", "200"] {
        let a = request(http, "GET", &format!("/api/v1/jobs?limit={good}"), &[], "").await;
        assert_eq!(a.status, 200, "limit={good}: {}", a.body);
    }
    let unknown = request(http, "GET", "/api/v1/jobs?colour=red", &[], "").await;
    assert_eq!(unknown.status, 400);
    assert_eq!(unknown.json()["error"]["field"], "colour");
    assert_eq!(
        request(http, "GET", "/api/v1/jobs/1", &[], "").await.status,
        200
    );
    for alias in ["+1", "01", "1.0", "%2B1", " 1"] {
        let path = format!("/api/v1/jobs/{}", alias.replace(' ', "%20"));
        for p in [
            path.clone(),
            format!("{path}/history"),
            format!("{path}/tiles"),
        ] {
            let a = request(http, "GET", &p, &[], "").await;
            assert_eq!(a.status, 404, "{p}: {}", a.body);
        }
        let a = request(http, "DELETE", &path, &[], "").await;
        assert_eq!(a.status, 404, "DELETE {path}: {}", a.body);
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn job_counts_in_metrics_survive_a_restart() {
    let dir = tempfile::tempdir().unwrap();
    let core = Coordinator::open(CoordinatorConfig::new(dir.path()))
        .await
        .unwrap();
    let mut job = JobSettings::new("builtin:cornell-box");
    (job.width, job.height, job.spp) = (Some(16), Some(16), 4);
    let (a, _) = core.submit(job.clone(), None).await.unwrap();
    let _ = core.submit(job, None).await.unwrap();
    core.cancel(a.id).await.unwrap();
    let before = core.metrics().await.unwrap();
    core.store().close().await;
    drop(core);
    let core = Coordinator::open(CoordinatorConfig::new(dir.path()))
        .await
        .unwrap();
    let after = core.metrics().await.unwrap();
    for line in [
        "tessera_jobs{state=\"queued\"} 1",
        "tessera_jobs{state=\"canceled\"} 1",
    ] {
        assert!(before.contains(line), "{before}");
        assert!(after.contains(line), "{after}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn lost_workers_are_forgotten_and_counted() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = CoordinatorConfig::new(dir.path());
    (cfg.heartbeat_ms, cfg.forget_lost_ms) = (10, 100);
    let core = Coordinator::open(cfg).await.unwrap();
    let stays = core.register_worker("stays".into(), 1, "t").unwrap();
    let _lost = core.register_worker("goes".into(), 1, "t").unwrap();
    bounded("the lost worker forgotten", async {
        loop {
            core.heartbeat(stays, 0.0, &[]).unwrap();
            core.tick().await;
            let names: Vec<String> = core
                .workers()
                .unwrap()
                .workers
                .into_iter()
                .map(|w| w.name)
                .collect();
            if names == ["stays"] {
                break;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    })
    .await;
    let m = core.metrics().await.unwrap();
    assert!(m.contains("tessera_workers_forgotten_total 1"), "{m}");
    assert!(m.contains("tessera_workers 1\n"), "{m}");
}

/// A heartbeat never tells a worker to drop a lapsed lease of a job that goes on
/// (worker.proto: the worker may finish it; its result is merged once or compared), so a
/// worker cut off past its lease still delivers (tests/netns_partition.rs). It cancels
/// leases of a canceled job and unknown ones. Lapsed leases are counted in /metrics.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn heartbeats_keep_lapsed_leases_deliverable_and_cancel_only_canceled_or_unknown_ones() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = CoordinatorConfig::new(dir.path());
    (cfg.lease_ms, cfg.heartbeat_ms) = (200, 50);
    let core = Coordinator::open(cfg).await.unwrap();
    let mut job = JobSettings::new("builtin:cornell-box");
    (job.width, job.height, job.spp) = (Some(64), Some(64), 4);
    let (status, _) = core.submit(job, None).await.unwrap();
    let w = core.register_worker("w".into(), 1, "t").unwrap();
    let held: Vec<u64> = core
        .lease(w, 2)
        .await
        .unwrap()
        .units
        .iter()
        .map(|u| u.lease_id)
        .collect();
    assert_eq!(held.len(), 2);
    // No heartbeat: past the deadline the housekeeping tick returns both units.
    bounded("the leases to lapse", async {
        loop {
            core.tick().await;
            let m = core.metrics().await.unwrap();
            if gauge(&m, "tessera_leases_expired_total") == 2 {
                break;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await;
    let hb = core.heartbeat(w, 0.0, &held).unwrap();
    assert!(hb.extended.is_empty(), "a lapsed lease was extended");
    assert!(
        hb.cancel.is_empty(),
        "lapsed leases of a live job were cancelled: {:?}",
        hb.cancel
    );
    assert_eq!(
        core.heartbeat(w, 0.0, &[987_654]).unwrap().cancel,
        [987_654]
    );
    core.cancel(status.id).await.unwrap();
    assert_eq!(core.heartbeat(w, 0.0, &held).unwrap().cancel, held);
}

/// The value of an unlabelled gauge in a `/metrics` text.
fn gauge(metrics: &str, name: &str) -> u64 {
    metrics
        .lines()
        .find_map(|l| l.strip_prefix(name)?.strip_prefix(' ')?.parse().ok())
        .unwrap_or_else(|| panic!("no {name} in {metrics}"))
}

/// The queue depth the worker autoscaler reads (docs/deploy.md): units waiting to be
/// leased and units leased, against a job's own units; a canceled job counts nothing.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn queued_and_leased_units_in_metrics_follow_the_jobs_units() {
    let dir = tempfile::tempdir().unwrap();
    let core = Coordinator::open(CoordinatorConfig::new(dir.path()))
        .await
        .unwrap();
    let m = core.metrics().await.unwrap();
    assert_eq!(
        (
            gauge(&m, "tessera_units_queued"),
            gauge(&m, "tessera_units_leased")
        ),
        (0, 0)
    );
    // 64 x 64 in 32-pixel tiles: 4 tiles; a unit is one tile and one pass (the default).
    let mut job = JobSettings::new("builtin:cornell-box");
    (job.width, job.height, job.spp) = (Some(64), Some(64), 4);
    let (status, _) = core.submit(job.clone(), None).await.unwrap();
    assert_eq!(status.tiles_total, 4);
    let units = status.passes_planned;
    assert!(units >= 4, "{status:?}");
    let m = core.metrics().await.unwrap();
    assert_eq!(gauge(&m, "tessera_units_queued"), units, "{m}");
    assert_eq!(gauge(&m, "tessera_units_leased"), 0, "{m}");

    let worker = core.register_worker("w".into(), 1, "t").unwrap();
    let grant = core.lease(worker, 3).await.unwrap();
    assert_eq!(grant.units.len(), 3);
    let m = core.metrics().await.unwrap();
    assert_eq!(gauge(&m, "tessera_units_queued"), units - 3, "{m}");
    assert_eq!(gauge(&m, "tessera_units_leased"), 3, "{m}");

    // A second job adds its units; canceling it takes them away again.
    let (other, _) = core.submit(job, None).await.unwrap();
    let m = core.metrics().await.unwrap();
    assert_eq!(gauge(&m, "tessera_units_queued"), 2 * units - 3, "{m}");
    core.cancel(other.id).await.unwrap();
    let m = core.metrics().await.unwrap();
    assert_eq!(gauge(&m, "tessera_units_queued"), units - 3, "{m}");
    assert_eq!(gauge(&m, "tessera_leases_outstanding"), 3, "{m}");
}

/// A worker's result for a lease: a flat grey image, with one value off if `corrupt`
/// (well-formed, so only a spot check's comparison catches it).
fn delivery(
    worker: tessera_farm::WorkerId,
    l: &tessera_proto::LeasedUnit,
    corrupt: bool,
) -> tessera_coordinator::service::Delivery {
    let rect = l.plan.tile(l.unit.tile);
    let mut pass_means = vec![[0.5f32; 3]; rect.pixel_count() * l.unit.pass_count as usize];
    if corrupt {
        pass_means[0][0] = 0.75;
    }
    tessera_coordinator::service::Delivery {
        worker,
        lease_id: l.lease_id,
        fence: l.fence.clone(),
        job_hint: l.job_id,
        result: Ok(tessera_farm::UnitResult {
            unit: l.unit,
            width: rect.width,
            height: rect.height,
            pass_means,
            rejected_samples: 0,
            bias: None,
        }),
        render_seconds: 0.01,
        traced_pixel_passes: 0,
    }
}

/// A spot check through the coordinator. A worker's corrupt copy is held, not
/// merged; the honest copies of two other workers outvote it; the faulty worker is then
/// quarantined: listed so over HTTP, leased nothing, told to drop its leases, and still
/// quarantined when it registers again under its name.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_spot_check_mismatch_quarantines_the_worker() {
    use tessera_coordinator::service::{Accepted, Rejected};
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = CoordinatorConfig::new(dir.path());
    cfg.spot_check_fraction = 1.0;
    let (http, _, core, _stop) = start(cfg).await;
    let mut job = JobSettings::new("builtin:cornell-box");
    (job.width, job.height, job.spp) = (Some(64), Some(64), 4);
    let (status, _) = core.submit(job, None).await.unwrap();
    let [bad, b, c] = ["bad", "b", "c"].map(|n| core.register_worker(n.into(), 1, "t").unwrap());
    let first = core.lease(bad, 1).await.unwrap().units.remove(0);
    let got = core
        .accept_result(delivery(bad, &first, true))
        .await
        .unwrap();
    assert_eq!(got, Accepted::Held);
    // The held unit goes to another worker, never back to the one with a copy.
    let again = core.lease(bad, 1).await.unwrap().units.remove(0);
    assert_ne!(again.unit, first.unit);
    let second = core.lease(b, 1).await.unwrap().units.remove(0);
    assert_eq!(second.unit, first.unit);
    let got = core
        .accept_result(delivery(b, &second, false))
        .await
        .unwrap();
    assert_eq!(got, Accepted::Held, "disputed: waits for a third worker");
    assert_eq!(core.status(status.id).await.unwrap().passes_done, 0);
    let third = core.lease(c, 1).await.unwrap().units.remove(0);
    assert_eq!(third.unit, first.unit);
    let got = core
        .accept_result(delivery(c, &third, false))
        .await
        .unwrap();
    assert_eq!(got, Accepted::Merged);
    assert_eq!(core.status(status.id).await.unwrap().passes_done, 1);

    let list = request(http, "GET", "/api/v1/workers", &[], "")
        .await
        .json();
    for w in list["workers"].as_array().unwrap() {
        let faulty = w["name"] == "bad";
        assert_eq!(w["quarantined"], faulty, "{w}");
        assert_eq!(w["quarantine_reason"].is_string(), faulty, "{w}");
    }
    // No more work, its lease revoked and to be dropped, its results refused.
    let grant = core.lease(bad, 4).await.unwrap();
    assert!(grant.units.is_empty() && grant.retry_after_ms >= 1000);
    let hb = core.heartbeat(bad, 0.0, &[again.lease_id]).unwrap();
    assert_eq!(hb.cancel, vec![again.lease_id]);
    let refused = core.accept_result(delivery(bad, &again, false)).await;
    assert!(
        matches!(refused, Err(Rejected::Quarantined(_))),
        "{refused:?}"
    );
    // Registering again does not launder it.
    let back = core.register_worker("bad".into(), 1, "t").unwrap();
    assert!(core.lease(back, 4).await.unwrap().units.is_empty());
    let m = core.metrics().await.unwrap();
    assert_eq!(
        gauge(&m, "tessera_spot_checks_total{outcome=\"mismatch\"}"),
        1,
        "{m}"
    );
    assert_eq!(gauge(&m, "tessera_workers_quarantined_total"), 1, "{m}");
    assert!(gauge(&m, "tessera_workers_quarantined") >= 1, "{m}");
}

/// The quarantine list is in the store and an operator can lift it. A worker
/// quarantined by a spot check is quarantined again at once when it registers with a
/// coordinator restarted on the same store (under the same name and identity only), and
/// is in the quarantine list of `GET /api/v1/workers` before it registers;
/// `DELETE /api/v1/workers/{name}/quarantine` (token required) lifts it (204): it is no
/// longer listed as quarantined, is leased units again, the lift is counted and stored
/// (a further restart does not bring the quarantine back), and a second lift is a 404
/// naming the worker.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_quarantine_outlives_a_restart_until_an_operator_lifts_it() {
    use tessera_coordinator::service::Accepted;
    let dir = tempfile::tempdir().unwrap();
    let config = || {
        let mut cfg = CoordinatorConfig::new(dir.path());
        cfg.spot_check_fraction = 1.0;
        cfg.grace_ms = 0;
        cfg.api_token = Some("tok".into());
        cfg
    };
    let core = Coordinator::open(config()).await.unwrap();
    let mut job = JobSettings::new("builtin:cornell-box");
    (job.width, job.height, job.spp) = (Some(64), Some(64), 4);
    core.submit(job, None).await.unwrap();
    let [bad, b, c] = ["bad", "b", "c"].map(|n| core.register_worker(n.into(), 1, "t").unwrap());
    // Two honest copies outvote the corrupt one.
    let l = core.lease(bad, 1).await.unwrap().units.remove(0);
    let got = core.accept_result(delivery(bad, &l, true)).await.unwrap();
    assert_eq!(got, Accepted::Held);
    for w in [b, c] {
        let l = core.lease(w, 1).await.unwrap().units.remove(0);
        core.accept_result(delivery(w, &l, false)).await.unwrap();
    }
    let quarantined = |list: &tessera_api::WorkerList, id| {
        let w = list.workers.iter().find(|w| w.id == id).unwrap();
        (w.quarantined, w.quarantine_reason.clone())
    };
    let (q, reason) = quarantined(&core.workers().unwrap(), bad);
    assert!(q, "the spot check quarantined it");
    let stored = core.store().list_quarantines().await.unwrap();
    assert_eq!(stored.len(), 1, "{stored:?}");
    assert_eq!(
        (stored[0].worker.as_str(), stored[0].identity.as_deref()),
        ("bad", None)
    );
    assert_eq!(Some(&stored[0].reason), reason.as_ref());
    core.store().close().await;
    drop(core);

    // Restarted on the same store: no worker is known, yet the name is distrusted, and
    // listed so.
    let (http, _, core, stop) = start(config()).await;
    let auth = ["Authorization: Bearer tok"];
    let list = request(http, "GET", "/api/v1/workers", &auth, "")
        .await
        .json();
    assert_eq!(list["workers"], serde_json::json!([]), "{list}");
    let listed = &list["quarantines"];
    assert_eq!(listed.as_array().map(Vec::len), Some(1), "{list}");
    assert_eq!(listed[0]["name"], "bad", "{list}");
    assert!(listed[0].get("identity").is_none(), "{list}");
    assert_eq!(listed[0]["reason"].as_str(), reason.as_deref(), "{list}");
    let again = core.register_worker("bad".into(), 1, "t").unwrap();
    let other_identity = core
        .register_worker_as("bad".into(), 1, "t", Some("cn-bad".into()))
        .unwrap();
    let honest = core.register_worker("b".into(), 1, "t").unwrap();
    let list = core.workers().unwrap();
    assert_eq!(quarantined(&list, again), (true, reason.clone()));
    assert_eq!(quarantined(&list, other_identity), (false, None));
    assert_eq!(quarantined(&list, honest), (false, None));
    let grant = core.lease(again, 1).await.unwrap();
    assert!(grant.units.is_empty() && grant.retry_after_ms >= 1000);
    assert!(!core.lease(honest, 1).await.unwrap().units.is_empty());

    let path = "/api/v1/workers/bad/quarantine";
    assert_eq!(request(http, "DELETE", path, &[], "").await.status, 401);
    let lifted = request(http, "DELETE", path, &auth, "").await;
    assert_eq!(lifted.status, 204, "{}", lifted.body);
    let list = request(http, "GET", "/api/v1/workers", &auth, "")
        .await
        .json();
    for w in list["workers"].as_array().unwrap() {
        assert_eq!(w["quarantined"], false, "{w}");
        assert!(w["quarantine_reason"].is_null(), "{w}");
    }
    assert_eq!(list["quarantines"], serde_json::json!([]), "{list}");
    assert!(!core.lease(again, 1).await.unwrap().units.is_empty());
    assert!(core.store().list_quarantines().await.unwrap().is_empty());
    let twice = request(http, "DELETE", path, &auth, "").await;
    assert_eq!(twice.status, 404, "{}", twice.body);
    let e = twice.json();
    assert_eq!(e["error"]["code"], "not_found", "{e}");
    assert!(
        e["error"]["message"].as_str().unwrap().contains("\"bad\""),
        "{e}"
    );
    let m = core.metrics().await.unwrap();
    assert_eq!(gauge(&m, "tessera_quarantines_lifted_total"), 1, "{m}");
    assert_eq!(gauge(&m, "tessera_workers_quarantined"), 0, "{m}");
    let _ = stop.send(());
    core.store().close().await;
    drop(core);

    // The lift was stored: after another restart the name is trusted.
    let core = Coordinator::open(config()).await.unwrap();
    let back = core.register_worker("bad".into(), 1, "t").unwrap();
    assert_eq!(quarantined(&core.workers().unwrap(), back), (false, None));
}

/// A spot-checked result opens a copy of its unit to the *other* workers only,
/// so it must wake their waiting lease requests, even when a request of the worker that
/// delivered it waits first. A single wake-up went to the oldest waiting request; when
/// that was the deliverer's own (a worker prefetching its next batch), it found nothing it
/// may take and waited on, and the other worker found the copy only at its deadline: a job
/// whose last unit was spot-checked ended a long poll late (bench-farm at 16 spp: 2.1 s
/// instead of 1.1 s in 1 round of 7 to 12). Counted, not timed: the other request's wait
/// must end woken, not at its deadline.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_held_spot_check_copy_wakes_the_other_workers_request() {
    use tessera_coordinator::service::Accepted;
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = CoordinatorConfig::new(dir.path());
    cfg.spot_check_fraction = 1.0;
    let core = Coordinator::open(cfg).await.unwrap();
    let mut job = JobSettings::new("builtin:cornell-box");
    (job.width, job.height, job.spp) = (Some(16), Some(16), 4);
    core.submit(job, None).await.unwrap();
    let [a, b] = ["a", "b"].map(|n| core.register_worker(n.into(), 1, "t").unwrap());
    // A holds every unit of the job: all that B can be given is a spot check's copy.
    let mut units = Vec::new();
    loop {
        let grant = core.lease(a, 256).await.unwrap();
        if grant.units.is_empty() {
            break;
        }
        units.extend(grant.units);
    }
    assert!(!units.is_empty());
    // A's request for more waits first, then B's (the longest wait there is, so that only
    // a wake-up ends it early).
    let waiting = |w| {
        let core = core.clone();
        tokio::spawn(async move {
            core.lease_waiting(w, 4, Duration::from_secs(2))
                .await
                .unwrap()
        })
    };
    let waits = |n| {
        let core = core.clone();
        async move {
            while core.lease_wait_counts().0 != n {
                tokio::time::sleep(Duration::from_millis(2)).await;
            }
        }
    };
    let _a_waits = waiting(a);
    bounded("A's request waiting", waits(1)).await;
    let b_waits = waiting(b);
    bounded("B's request waiting", waits(2)).await;
    let got = core
        .accept_result(delivery(a, &units[0], false))
        .await
        .unwrap();
    assert_eq!(got, Accepted::Held);
    let grant = bounded("B's request", b_waits).await.unwrap();
    assert_eq!(grant.units.len(), 1, "B was given no copy");
    assert_eq!(grant.units[0].unit, units[0].unit);
    let (_, _, at_deadline) = core.lease_wait_counts();
    assert_eq!(
        at_deadline, 0,
        "B found the copy only at its wait's deadline"
    );
}

/// A coordinator with spot-check fraction `spot` and one queued job of one 16x16 tile and 4
/// passes of one unit each (the Cornell box at 8 spp, 4 passes of 2: from 16 spp the plan
/// gives 2 passes), for the ETA tests.
async fn one_tile_job(spot: f64) -> (tempfile::TempDir, Coordinator, tessera_api::JobStatus) {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = CoordinatorConfig::new(dir.path());
    (cfg.spot_check_fraction, cfg.passes_per_unit) = (spot, 1);
    let core = Coordinator::open(cfg).await.unwrap();
    let mut job = JobSettings::new("builtin:cornell-box");
    (job.width, job.height, job.spp) = (Some(16), Some(16), 8);
    let (status, _) = core.submit(job, None).await.unwrap();
    assert_eq!((status.tiles_total, status.passes_planned), (1, 4));
    (dir, core, status)
}

/// Reads the job's status and checks that its ETA is `times` its elapsed time (and
/// positive): the rate so far applied to the work left.
async fn assert_eta(core: &Coordinator, id: u64, times: f64) -> tessera_api::JobStatus {
    let s = core.status(id).await.unwrap();
    let eta = s.eta_seconds.expect("an ETA");
    assert!(
        eta > 0.0 && (eta - s.elapsed_seconds * times).abs() < 1e-9,
        "eta {eta} s after {} s, want {times} times that",
        s.elapsed_seconds
    );
    s
}

/// The ETA counts the passes rendered and buffered for the canonical merge
/// order, not only the merged ones. A one-tile job of 4 passes, one unit each: passes 1,
/// 2 and 3 delivered before pass 0 wait in the tile's buffer (nothing is merged), yet
/// three quarters of the work is done, so the ETA is a third of the time spent (it was
/// `None`, as if nothing had been rendered); once pass 0 arrives the job is done.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_eta_counts_passes_buffered_for_the_merge_order() {
    use tessera_coordinator::service::Accepted;
    let (_dir, core, status) = one_tile_job(0.0).await;
    let w = core.register_worker("w".into(), 1, "t").unwrap();
    let mut units = core.lease(w, 4).await.unwrap().units;
    assert_eq!(units.len(), 4);
    units.sort_by_key(|l| l.unit.first_pass);
    // Some rendering time, so that the rate is measurable (milliseconds).
    tokio::time::sleep(Duration::from_millis(30)).await;
    for l in &units[1..] {
        let got = core
            .accept_result(slow(delivery(w, l, false)))
            .await
            .unwrap();
        assert_eq!(got, Accepted::Merged, "buffered counts as merged");
    }
    // Three of four passes took the job's elapsed time (since the first lease; the status
    // reads one clock for both): one more takes a third.
    let s = assert_eta(&core, status.id, 1.0 / 3.0).await;
    assert_eq!(s.passes_done, 0, "passes 1 to 3 wait for pass 0");
    core.accept_result(delivery(w, &units[0], false))
        .await
        .unwrap();
    let s = core.status(status.id).await.unwrap();
    assert_eq!((s.passes_done, s.state.as_str()), (4, "done"));
}

/// A delivery whose unit took a very long time to render, so that the ETA credits the
/// units still in flight with nothing (their age is nothing beside it).
fn slow(mut d: tessera_coordinator::service::Delivery) -> tessera_coordinator::service::Delivery {
    d.render_seconds = 1e6;
    d
}

/// Units in flight count as far as their age says: a batch of 4 leased together, one
/// delivered with a unit time of 1 ms, and 30 ms later the other 3 (rendering since that
/// result) count 90% (2.7 units): 1 + 2.7 of 4 units is done. Without the credit the ETA
/// would be 3 times the elapsed time.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_eta_credits_units_in_flight_by_their_age() {
    let (_dir, core, status) = one_tile_job(0.0).await;
    let w = core.register_worker("w".into(), 1, "t").unwrap();
    let mut units = core.lease(w, 4).await.unwrap().units;
    assert_eq!(units.len(), 4);
    units.sort_by_key(|l| l.unit.first_pass);
    tokio::time::sleep(Duration::from_millis(30)).await;
    let mut d = delivery(w, &units[0], false);
    d.render_seconds = 1e-3;
    core.accept_result(d).await.unwrap();
    // The worker renders the rest from its last result on: let 30 unit times pass.
    tokio::time::sleep(Duration::from_millis(30)).await;
    let s = assert_eta(&core, status.id, (4.0 - 3.7) / 3.7).await;
    assert_eq!(s.passes_done, 1);
}

/// The spot checks' second copies are work the ETA counts: with every unit checked, a job
/// of 4 units renders 8, and after the first 4 copies (held, nothing merged) half of the
/// work is done.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_eta_counts_the_spot_checks_copies() {
    use tessera_coordinator::service::Accepted;
    let (_dir, core, status) = one_tile_job(1.0).await;
    let first = core.register_worker("first".into(), 1, "t").unwrap();
    let units = core.lease(first, 4).await.unwrap().units;
    assert_eq!(units.len(), 4);
    tokio::time::sleep(Duration::from_millis(30)).await;
    for l in &units[..3] {
        let got = core
            .accept_result(slow(delivery(first, l, false)))
            .await
            .unwrap();
        assert_eq!(got, Accepted::Held, "the first copy waits for a second");
    }
    // 3 of 8 units' work: 5/3 of the elapsed time again (not truncated to whole passes,
    // 1.5 of the 4 planned, which would say 3 times).
    assert_eta(&core, status.id, 5.0 / 3.0).await;
    core.accept_result(delivery(first, &units[3], false))
        .await
        .unwrap();
    // 4 of 8 units' work in the elapsed time: as long again.
    let s = assert_eta(&core, status.id, 1.0).await;
    assert_eq!(s.passes_done, 0, "every unit waits for its second copy");
    let second = core.register_worker("second".into(), 1, "t").unwrap();
    let mut copies = 0;
    while copies < 4 {
        // Near the end of the work leases shrink (the tail share): as many rounds as it takes.
        let leased = core.lease(second, 4).await.unwrap().units;
        assert!(
            !leased.is_empty(),
            "the second copies are leased to the other worker"
        );
        for l in &leased {
            core.accept_result(delivery(second, l, false))
                .await
                .unwrap();
        }
        copies += leased.len();
    }
    let s = core.status(status.id).await.unwrap();
    assert_eq!((s.passes_done, s.state.as_str()), (4, "done"));
}

/// A job that path-traces caustics of a tiny light (`builtin:caustic`, where the
/// plan chooses bdpt) is told in its status that its error estimate may be optimistic, and
/// why; the same scene with bdpt only for the light's images in the glass (`E S+ L`, which
/// bdpt samples as path tracing does), and a scene without such light not at all.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_status_says_when_the_error_estimate_may_be_optimistic() {
    let dir = tempfile::tempdir().unwrap();
    let core = Coordinator::open(CoordinatorConfig::new(dir.path()))
        .await
        .unwrap();
    let submit = |scene: &str, integrator: &str| {
        let mut job = JobSettings::new(scene);
        (job.width, job.height, job.spp) = (Some(16), Some(16), 4);
        job.integrator = integrator.into();
        let core = core.clone();
        async move { core.submit(job, None).await.unwrap().0 }
    };
    let path = submit("builtin:caustic", "path").await;
    let caveat = path
        .error_estimate_caveat
        .expect("path tracing the caustic of a tiny light: a caveat");
    assert!(
        caveat.contains("may be optimistic") && caveat.contains("sphere light"),
        "{caveat}"
    );
    let bdpt = submit("builtin:caustic", "bdpt").await;
    let bdpt_caveat = bdpt
        .error_estimate_caveat
        .clone()
        .expect("the tiny light's images in the glass: a caveat");
    assert!(
        bdpt_caveat.contains("E S+ L") && !bdpt_caveat.contains("BSDF-sampled ray"),
        "{bdpt_caveat}"
    );
    let cornell = submit("builtin:cornell-box", "path").await;
    assert_eq!(cornell.error_estimate_caveat, None);

    // A job no longer held in memory (finished before a restart) is read back from the
    // store with its plan and its caveat as accepted.
    for id in [path.id, bdpt.id] {
        core.cancel(id).await.unwrap();
    }
    core.store().close().await;
    drop(core);
    let core = Coordinator::open(CoordinatorConfig::new(dir.path()))
        .await
        .unwrap();
    let stored = core.status(path.id).await.unwrap();
    assert_eq!(stored.state, JobState::Canceled);
    assert_eq!(
        stored.error_estimate_caveat.as_deref(),
        Some(caveat.as_str())
    );
    assert!(path.plan.is_some());
    assert_eq!(stored.plan, path.plan);
    let stored = core.status(bdpt.id).await.unwrap();
    assert_eq!(stored.error_estimate_caveat, Some(bdpt_caveat));
    assert_eq!(stored.plan, bdpt.plan);
}

/// A finished job read back from the store names its error estimate as the build that
/// stored it did, not as the reading build would: the robust scale's level changed on
/// 2026-12-06, and with it the estimates and the estimator's name, so a job stored before
/// showed its old-level estimate under the new name. Read back as stored; without a
/// stored name (a build before store schema 9) no name at all; with the old name, the old
/// name.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stored_job_names_the_estimator_its_estimate_was_stored_with() {
    use sqlx::Connection;
    let (dir, core, status) = one_tile_job(0.0).await;
    let w = core.register_worker("w".into(), 1, "t").unwrap();
    let units = core.lease(w, 4).await.unwrap().units;
    assert_eq!(units.len(), 4);
    for l in &units {
        core.accept_result(delivery(w, l, false)).await.unwrap();
    }
    let live = core.status(status.id).await.unwrap();
    assert_eq!(live.state, JobState::Done);
    let name = live.error_estimator.clone().expect("a name");
    assert!(live.error_estimate.is_some());
    let reopen = |core: Coordinator| {
        let path = dir.path().to_path_buf();
        async move {
            core.store().close().await;
            drop(core);
            Coordinator::open(CoordinatorConfig::new(&path))
                .await
                .unwrap()
        }
    };
    let set_name = |name: Option<&'static str>| {
        let db = dir.path().join(tessera_coordinator::store::DATABASE_FILE);
        async move {
            let mut c = sqlx::SqliteConnection::connect(&format!("sqlite://{}", db.display()))
                .await
                .unwrap();
            sqlx::query("UPDATE jobs SET error_estimator = ?")
                .bind(name)
                .execute(&mut c)
                .await
                .unwrap();
            c.close().await.unwrap();
        }
    };
    let core = reopen(core).await;
    let stored = core.status(status.id).await.unwrap();
    assert_eq!(stored.error_estimator.as_deref(), Some(name.as_str()));
    assert_eq!(stored.error_estimate, live.error_estimate);
    // As a build before schema 9 left it: the estimate, and no name for it.
    let core = reopen(core).await;
    set_name(None).await;
    let stored = core.status(status.id).await.unwrap();
    assert_eq!(stored.error_estimator, None);
    assert_eq!(stored.error_estimate, live.error_estimate);
    // Stored under the name of the level before 2026-12-06: that name.
    let old = "pass-spread, robust scale; pixel intervals pooled 3x3";
    set_name(Some(old)).await;
    let stored = core.status(status.id).await.unwrap();
    assert_eq!(stored.error_estimator.as_deref(), Some(old));
    assert_ne!(old, name);
}

/// A running job that stops at its target error (adaptive, with a target) shows the ETA's
/// interval and tail class over HTTP, as the OpenAPI document describes them; a job that
/// runs its planned passes shows neither.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_running_target_job_shows_its_eta_interval_over_http() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = CoordinatorConfig::new(dir.path());
    (cfg.spot_check_fraction, cfg.passes_per_unit) = (0.0, 1);
    let (http, _, core, _stop) = start(cfg).await;
    let mut job = JobSettings::new("builtin:cornell-box");
    (job.width, job.height, job.spp) = (Some(16), Some(16), 256);
    job.adaptive = "sequential".into();
    job.target_error = Some(0.001);
    let (status, _) = core.submit(job, None).await.unwrap();
    let w = core.register_worker("w".into(), 1, "t").unwrap();
    // Two passes, each a history point apart, with values that differ between passes so
    // that the image has an error above its target.
    for pass in 0..2u32 {
        let units = core.lease(w, 1).await.unwrap().units;
        assert_eq!(units.len(), 1);
        let mut d = delivery(w, &units[0], false);
        if let Ok(r) = &mut d.result {
            for (i, p) in r.pass_means.iter_mut().enumerate() {
                let v = 0.5 + 0.2 * ((i as u32 * 7 + pass * 3) % 5) as f32 / 5.0;
                *p = [v; 3];
            }
        }
        core.accept_result(d).await.unwrap();
        tokio::time::sleep(Duration::from_millis(250)).await;
    }
    let a = request(http, "GET", &format!("/api/v1/jobs/{}", status.id), &[], "").await;
    assert_eq!(a.status, 200, "{}", a.body);
    let v = a.json();
    assert_eq!(v["state"], "running", "{v}");
    assert!(v["error_estimate"].as_f64().unwrap() > 0.001, "{v}");
    let (eta, low, high) = (
        v["eta_seconds"].as_f64().expect("an ETA"),
        v["eta_low_seconds"].as_f64().expect("an interval"),
        v["eta_high_seconds"].as_f64().expect("an interval"),
    );
    assert!(low <= eta && eta <= high, "{v}");
    assert_eq!(v["eta_tail_class"], "light", "{v}");
    // A job that runs its planned passes: the ETA alone, as before.
    let mut plain = JobSettings::new("builtin:cornell-box");
    (plain.width, plain.height, plain.spp) = (Some(16), Some(16), 8);
    let (plain, _) = core.submit(plain, None).await.unwrap();
    let v = request(http, "GET", &format!("/api/v1/jobs/{}", plain.id), &[], "")
        .await
        .json();
    for absent in [
        "eta_low_seconds",
        "eta_high_seconds",
        "eta_tail_class",
        "eta_note",
    ] {
        assert!(v.get(absent).is_none(), "{absent}: {v}");
    }
}

/// A uniform job's status gives the estimate its `error_estimator` names (the robust
/// scale at the neighbours' level, as its EXR header's), not the RMS of each pixel's error
/// over its own mean, which it gave before: on an image whose pixels differ from their
/// neighbours the two differ, and the status is the named one to rounding.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_uniform_jobs_status_gives_the_estimate_its_estimator_names() {
    let (_dir, core, status) = one_tile_job(0.0).await;
    let w = core.register_worker("w".into(), 1, "t").unwrap();
    let units = core.lease(w, 4).await.unwrap().units;
    assert_eq!(units.len(), 4);
    // Pixel i's pass p: a checkerboard of levels 0.2 and 0.8, each pixel's passes spread
    // by a pattern of its own.
    let value = |i: usize, p: u32| {
        let level = if (i % 16 + i / 16).is_multiple_of(2) {
            0.2
        } else {
            0.8
        };
        let wobble = ((i as u32 * 7 + p * 5) % 4) as f32 / 3.0 - 0.5;
        level * (1.0 + 0.4 * wobble)
    };
    let mut stats = vec![tessera_farm::PixelStats::default(); 256];
    for l in &units {
        let mut d = delivery(w, l, false);
        if let Ok(r) = &mut d.result {
            for (i, px) in r.pass_means.iter_mut().enumerate() {
                *px = [value(i, l.unit.first_pass); 3];
                stats[i].push(*px);
            }
        }
        core.accept_result(d).await.unwrap();
    }
    let s = core.status(status.id).await.unwrap();
    assert_eq!(s.state, JobState::Done);
    assert_eq!(
        s.error_estimator.as_deref(),
        Some(tessera_farm::ERROR_ESTIMATOR)
    );
    let named = tessera_farm::image_relative_error(16, 16, |x, y| {
        let p = &stats[y * 16 + x];
        Some((p.mean_lum, p.lum_variance_of_mean()))
    });
    let own = (stats
        .iter()
        .map(|p| p.relative_error().powi(2))
        .sum::<f64>()
        / 256.0)
        .sqrt();
    assert!(named > 1.03 * own, "robust {named}, own means {own}");
    let e = s.error_estimate.expect("an estimate");
    assert!(
        (e / named - 1.0).abs() < 1e-9,
        "status {e}, named {named}, own {own}"
    );
}
