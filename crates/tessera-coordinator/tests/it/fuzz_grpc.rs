//! Worker results over gRPC, fuzzed (robustness issue: a fuzz target per input surface;
//! docs/fuzzing.md, "gRPC results"): a deterministic, bounded mutation harness on stable
//! Rust against a real `Coordinator` over a temporary store, through the real gRPC
//! service (`WorkerGrpc`, decode and all; no socket).
//!
//! For every leased unit the harness sends mutated copies of the correct result (fields
//! set to random or edge values, values made non-finite or negative, the list cut or
//! grown, the unit or lease moved, an unknown worker), then the correct one, unless a
//! mutation that touched only unvalidated diagnostics was accepted first. It checks:
//! nothing panics; every refusal of the registered worker's result is counted as one of
//! its faults (in the worker list and `/metrics`); no unknown worker appears in the
//! listing; and nothing accepted is lost: the job ends `done` with every planned pass,
//! and a coordinator reopened on the store sees the same.

use tessera_api::JobSettings;
use tessera_coordinator::grpc::WorkerGrpc;
use tessera_coordinator::service::{Coordinator, CoordinatorConfig};
use tessera_proto::v1;
use tessera_proto::v1::worker_service_server::WorkerService;
use tonic::Request;

/// The harness's seed: change it to explore, keep it fixed in CI.
const SEED: u64 = 0x7e55_e7a0_0016;
/// Mutated copies sent per unit before the correct one.
const MUTANTS_PER_UNIT: usize = 6;

use tessera_testkit::SplitMix64 as Rng;

/// The values this harness draws besides plain numbers.
trait Draw {
    /// A u32 that is often an edge case.
    fn edge_u32(&mut self) -> u32;
    /// A value a pass mean must not have.
    fn bad_f32(&mut self) -> f32;
}

impl Draw for Rng {
    fn edge_u32(&mut self) -> u32 {
        const EDGES: [u32; 6] = [0, 1, 2, 7, u32::MAX, u32::MAX - 1];
        if self.below(2) == 0 {
            EDGES[self.below(EDGES.len() as u64) as usize]
        } else {
            self.next() as u32
        }
    }
    fn bad_f32(&mut self) -> f32 {
        [
            f32::NAN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            -1.0,
            -1e-30,
            f32::MIN,
        ][self.below(6) as usize]
    }
}

/// Which mutation a copy got, and whether the coordinator may accept it (the mutation
/// touched only diagnostics it does not validate).
fn mutate(rng: &mut Rng, r: &mut v1::SubmitResultRequest) -> (&'static str, bool) {
    let (w0, h0) = (r.width, r.height);
    match rng.below(12) {
        0 => {
            // Every call is bound to the caller's session: a result under any other
            // worker id is refused before it is read, and the id is never listed.
            r.worker_id = r.worker_id.wrapping_add(1 + rng.below(1 << 40));
            ("unknown worker", false)
        }
        1 => {
            r.lease_id = match rng.below(3) {
                0 => 0,
                1 => r.lease_id.wrapping_add(1 + rng.below(1000)),
                _ => rng.next(),
            };
            ("other lease", false)
        }
        2 => {
            let u = r.unit.get_or_insert_with(Default::default);
            match rng.below(4) {
                0 => u.frame = rng.edge_u32().max(1),
                1 => u.tile = u.tile.wrapping_add(1 + rng.below(64) as u32),
                2 => u.first_pass = u.first_pass.wrapping_add(1 + rng.below(64) as u32),
                _ => u.pass_count = [0, 2, 3, u32::MAX][rng.below(4) as usize],
            }
            ("other unit", false)
        }
        3 => {
            r.unit = None;
            ("no unit", false)
        }
        4 => {
            if rng.below(2) == 0 {
                r.width = rng.edge_u32();
            } else {
                r.height = rng.edge_u32();
            }
            if (r.width, r.height) == (w0, h0) {
                r.width = w0 + 1;
            }
            ("other size", false)
        }
        5 => {
            let mut means = r.means();
            let i = rng.below(means.len() as u64) as usize;
            means[i] = rng.bad_f32();
            r.set_means(&means);
            ("bad value", false)
        }
        6 => {
            let bad = rng.bad_f32();
            let means = vec![bad; r.means().len()];
            r.set_means(&means);
            ("all values bad", false)
        }
        7 => {
            // Any number of bytes short: a partial float, or whole pixels missing.
            let keep = rng.below(r.pass_means.len() as u64) as usize;
            r.pass_means.truncate(keep);
            ("too few values", false)
        }
        8 => {
            let extra = 1 + rng.below(1200) as usize;
            r.pass_means.extend(std::iter::repeat_n(0x3f, extra));
            ("too many values", false)
        }
        9 => {
            r.render_seconds = [f64::NAN, f64::INFINITY, -1.0, 1e300][rng.below(4) as usize];
            ("odd render seconds", true)
        }
        10 => {
            r.rejected_samples = rng.next();
            ("odd rejected samples", true)
        }
        _ => {
            // The job hint is trusted only for leases of a previous run.
            r.job_id = rng.next();
            ("other job hint", true)
        }
    }
}

/// The size of tile `tile` of a `width` x `height` frame cut in `ts`-pixel tiles.
fn tile_size(width: u32, height: u32, ts: u32, tile: u32) -> (u32, u32) {
    let across = width.div_ceil(ts);
    let (x, y) = ((tile % across) * ts, (tile / across) * ts);
    ((width - x).min(ts), (height - y).min(ts))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn mutated_worker_results_are_refused_counted_and_lose_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let core = Coordinator::open(CoordinatorConfig::new(dir.path()))
        .await
        .unwrap();
    let mut job = JobSettings::new("builtin:cornell-box");
    (job.width, job.height, job.spp, job.tile_size) = (Some(60), Some(28), 8, 8);
    let (job, _) = core.submit(job, None).await.unwrap();
    let svc = WorkerGrpc::for_coordinator(core.clone());
    let reg = svc
        .register(Request::new(v1::RegisterRequest {
            name: "fuzzer".into(),
            threads: 1,
            version: "test".into(),
            capabilities: vec!["path".into()],
        }))
        .await
        .unwrap()
        .into_inner();
    let (worker_id, session) = (reg.worker_id, reg.session);
    // Every call after Register carries the worker's session secret.
    let sess = |msg| {
        let mut r = Request::new(msg);
        r.metadata_mut()
            .insert(tessera_proto::SESSION_METADATA, session.parse().unwrap());
        r
    };
    let mut rng = Rng(SEED);
    let (mut sent, mut refused_mine, mut units) = (0u64, 0u64, 0u64);
    loop {
        let leases = svc
            .lease_work({
                let mut r = Request::new(v1::LeaseRequest {
                    worker_id,
                    max_units: 4,
                    wait_ms: 0,
                });
                r.metadata_mut()
                    .insert(tessera_proto::SESSION_METADATA, session.parse().unwrap());
                r
            })
            .await
            .unwrap()
            .into_inner()
            .leases;
        if leases.is_empty() {
            break;
        }
        for lease in leases {
            let plan = lease.plan.unwrap();
            let unit = lease.unit.unwrap();
            let (w, h) = tile_size(plan.width, plan.height, plan.tile_size, unit.tile);
            let n = 3 * (unit.pass_count * w * h) as usize;
            let good = v1::SubmitResultRequest {
                worker_id,
                lease_id: lease.lease_id,
                unit: Some(unit),
                width: w,
                height: h,
                pass_means: tessera_proto::means_to_bytes(
                    &(0..n).map(|i| (i % 7) as f32 * 0.125).collect::<Vec<_>>(),
                ),
                render_seconds: 0.01,
                job_id: lease.job_id,
                rejected_samples: 0,
                traced_pixel_passes: 0,
                fence: lease.fence.clone(),
                bias: Vec::new(),
            };
            let mut delivered = false;
            for _ in 0..MUTANTS_PER_UNIT {
                let mut bad = good.clone();
                let (what, may_pass) = mutate(&mut rng, &mut bad);
                let mine = bad.worker_id == worker_id;
                let answer = svc.submit_result(sess(bad)).await;
                sent += 1;
                if !mine {
                    // Another worker's id without its session: refused before anything
                    // is read, as a gRPC error (NOT_FOUND for an id nobody has).
                    let s = answer.expect_err("a result under an unknown worker id was taken");
                    assert_eq!(s.code(), tonic::Code::NotFound, "{what}: {s}");
                    continue;
                }
                // A malformed result is answered "not accepted" with the reason (and
                // counted), never with a gRPC error.
                let accepted = answer
                    .unwrap_or_else(|s| panic!("{what}: {s}"))
                    .into_inner()
                    .accepted;
                assert!(
                    !accepted || may_pass,
                    "{what}: a malformed result was accepted"
                );
                if !accepted && mine {
                    refused_mine += 1;
                }
                if accepted {
                    // A harmless mutation delivered the unit. (Sending it again under
                    // the same lease would be refused as an unknown lease and counted
                    // as a fault: the scheduler forgets a lease once its unit merged.)
                    delivered = true;
                    break;
                }
            }
            if !delivered {
                let a = svc.submit_result(sess(good)).await.unwrap().into_inner();
                sent += 1;
                assert!(a.accepted, "the correct result was refused: {}", a.reason);
            }
            units += 1;
        }
    }
    let status = core.status(job.id).await.unwrap();
    assert_eq!(status.state.as_str(), "done", "{status:?}");
    assert_eq!(status.passes_done, status.passes_planned);
    let workers = core.workers().unwrap().workers;
    assert_eq!(
        workers.len(),
        1,
        "unknown worker ids were listed: {workers:?}"
    );
    // Every refusal of the worker's results is one fault.
    assert!(refused_mine > 0);
    assert_eq!(workers[0].faults, refused_mine);
    let metrics = core.metrics().await.unwrap();
    assert!(
        metrics.contains(&format!(
            "tessera_worker_faults_total {}",
            workers[0].faults
        )),
        "{metrics}"
    );
    eprintln!(
        "fuzz_grpc: {sent} results sent for {units} units, {refused_mine} of the worker's refused, {} faults",
        workers[0].faults
    );
    // Nothing accepted is lost: a coordinator reopened on the store has every pass.
    core.store().close().await;
    drop((svc, core));
    let again = Coordinator::open(CoordinatorConfig::new(dir.path()))
        .await
        .unwrap();
    let status = again.status(job.id).await.unwrap();
    assert_eq!(status.state.as_str(), "done");
    assert_eq!(status.passes_done, status.passes_planned);
}

/// One byte-level mutation of an encoded message: a bit flipped, a byte replaced, the
/// message cut short, random bytes inserted or appended (often a well-formed field of an
/// unknown or known number), or a slice repeated (a field sent twice).
fn mutate_bytes(rng: &mut Rng, bytes: &mut Vec<u8>) {
    let at = |rng: &mut Rng, len: usize| rng.below(len as u64 + 1) as usize;
    match rng.below(6) {
        0 if !bytes.is_empty() => {
            let i = rng.below(bytes.len() as u64) as usize;
            bytes[i] ^= 1 << rng.below(8);
        }
        1 if !bytes.is_empty() => {
            let i = rng.below(bytes.len() as u64) as usize;
            bytes[i] = rng.next() as u8;
        }
        2 => {
            let keep = at(rng, bytes.len());
            bytes.truncate(keep);
        }
        3 => {
            let i = at(rng, bytes.len());
            let extra: Vec<u8> = (0..1 + rng.below(12)).map(|_| rng.next() as u8).collect();
            bytes.splice(i..i, extra);
        }
        4 => {
            // A varint field: a small field number (known or not), then an edge value.
            let field = 1 + rng.below(20);
            let mut v = match rng.below(3) {
                0 => u64::MAX,
                1 => u64::from(rng.edge_u32()),
                _ => rng.next(),
            };
            bytes.push((field << 3) as u8);
            while v >= 0x80 {
                bytes.push((v as u8) | 0x80);
                v >>= 7;
            }
            bytes.push(v as u8);
        }
        _ if bytes.len() >= 2 => {
            let a = rng.below(bytes.len() as u64) as usize;
            let b = a + 1 + rng.below((bytes.len() - a) as u64) as usize;
            let slice = bytes[a..b.min(bytes.len())].to_vec();
            bytes.extend_from_slice(&slice);
        }
        _ => bytes.push(rng.next() as u8),
    }
}

/// `msg` as a request carrying the worker session `session`.
fn signed<M>(msg: M, session: &str) -> Request<M> {
    let mut r = Request::new(msg);
    r.metadata_mut()
        .insert(tessera_proto::SESSION_METADATA, session.parse().unwrap());
    r
}

/// `msg` encoded, mutated once or twice, and decoded again as `M`: `None` when the
/// bytes no longer decode (prost refuses them before the service sees anything).
fn mutated<M: prost::Message + Default>(rng: &mut Rng, msg: &M) -> Option<M> {
    let mut bytes = msg.encode_to_vec();
    // Mostly one mutation: most bytes mutated twice no longer decode at all.
    for _ in 0..if rng.below(4) == 0 { 2 } else { 1 } {
        mutate_bytes(rng, &mut bytes);
    }
    M::decode(bytes.as_slice()).ok()
}

/// Every worker message, mutated at the byte level and sent by a registered worker with
/// its valid session (the strongest position a rogue worker has), for every lease it
/// holds: Register, Heartbeat, LeaseWork, SubmitResult, FetchScene and ReturnLeases. No
/// call panics or hangs; an honest worker then finishes the job; every planned pass is
/// merged once, and a reopened coordinator sees the same.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn byte_mutated_worker_messages_never_panic_and_the_job_completes() {
    let dir = tempfile::tempdir().unwrap();
    let core = Coordinator::open(CoordinatorConfig::new(dir.path()))
        .await
        .unwrap();
    let mut job = JobSettings::new("builtin:cornell-box");
    (job.width, job.height, job.spp, job.tile_size) = (Some(40), Some(24), 8, 8);
    let (job, _) = core.submit(job, None).await.unwrap();
    let svc = WorkerGrpc::for_coordinator(core.clone());
    let register = |name: &str| v1::RegisterRequest {
        name: name.into(),
        threads: 1,
        version: "test".into(),
        capabilities: vec!["path".into()],
    };
    let reg = svc
        .register(Request::new(register("rogue")))
        .await
        .unwrap()
        .into_inner();
    let (rogue, session) = (reg.worker_id, reg.session);
    let mut rng = Rng(SEED ^ 0xb17e);
    let (mut calls, mut undecodable, mut accepted_results) = (0u64, 0u64, 0u64);
    let (mut leased, mut results_sent) = (0u64, 0u64);
    for round in 0..24 {
        // Mutated registrations (no session needed), lease requests and heartbeats.
        for _ in 0..4 {
            match mutated(&mut rng, &register("rogue")) {
                Some(m) => {
                    let _ = svc.register(Request::new(m)).await;
                    calls += 1;
                }
                None => undecodable += 1,
            }
        }
        let lease_req = v1::LeaseRequest {
            worker_id: rogue,
            max_units: 2,
            wait_ms: 0,
        };
        let mut leases = Vec::new();
        for _ in 0..3 {
            match mutated(&mut rng, &lease_req) {
                // A long poll is bounded by the coordinator (2 s); keep the harness fast.
                Some(mut m) if m.wait_ms == 0 || round % 8 == 0 => {
                    m.wait_ms = m.wait_ms.min(50);
                    if let Ok(r) = svc.lease_work(signed(m, &session)).await {
                        leases.extend(r.into_inner().leases);
                    }
                    calls += 1;
                }
                Some(_) => {}
                None => undecodable += 1,
            }
        }
        leased += leases.len() as u64;
        let ids: Vec<u64> = leases.iter().map(|l| l.lease_id).collect();
        let beat = v1::HeartbeatRequest {
            worker_id: rogue,
            lease_ids: ids.clone(),
            paths_per_second: 1e6,
        };
        for _ in 0..3 {
            match mutated(&mut rng, &beat) {
                Some(m) => {
                    let _ = svc.heartbeat(signed(m, &session)).await;
                    calls += 1;
                }
                None => undecodable += 1,
            }
        }
        for lease in &leases {
            let (Some(plan), Some(unit)) = (lease.plan.as_ref(), lease.unit) else {
                continue;
            };
            let (w, h) = tile_size(plan.width, plan.height, plan.tile_size, unit.tile);
            let n = 3 * (unit.pass_count * w * h) as usize;
            let good = v1::SubmitResultRequest {
                worker_id: rogue,
                lease_id: lease.lease_id,
                unit: Some(unit),
                width: w,
                height: h,
                pass_means: tessera_proto::means_to_bytes(&vec![0.25; n]),
                render_seconds: 0.01,
                job_id: lease.job_id,
                rejected_samples: 0,
                traced_pixel_passes: 0,
                fence: lease.fence.clone(),
                bias: Vec::new(),
            };
            for _ in 0..4 {
                match mutated(&mut rng, &good) {
                    Some(m) => {
                        if let Ok(r) = svc.submit_result(signed(m, &session)).await {
                            accepted_results += u64::from(r.into_inner().accepted);
                        }
                        calls += 1;
                        results_sent += 1;
                    }
                    None => undecodable += 1,
                }
            }
            let fetch = v1::FetchSceneRequest {
                scene_hash: lease.scene_hash.clone(),
            };
            if let Some(m) = mutated(&mut rng, &fetch) {
                if let Ok(stream) = svc.fetch_scene(signed(m, &session)).await {
                    use tokio_stream::StreamExt;
                    let mut s = stream.into_inner();
                    while s.next().await.is_some() {}
                }
                calls += 1;
            }
        }
        // Give the leases back (mutated first, then as they are, with no reason), so the
        // honest worker below can take every unit the rogue did not deliver.
        let give_back = v1::ReturnLeasesRequest {
            worker_id: rogue,
            lease_ids: ids,
            unusable: String::new(),
        };
        if let Some(m) = mutated(&mut rng, &give_back) {
            let _ = svc.return_leases(signed(m, &session)).await;
            calls += 1;
        }
        let _ = svc.return_leases(signed(give_back, &session)).await;
    }
    eprintln!(
        "fuzz_grpc bytes: {calls} mutated calls, {undecodable} undecodable, {leased} units \
         leased, {results_sent} mutated results sent, {accepted_results} accepted"
    );
    // The harness reached every call (the rogue's faults may end its leasing early).
    assert!(calls >= 80 && leased > 0 && results_sent > 0);
    // Two honest workers finish whatever is left (two, so that every spot-checked unit
    // finds a second worker for its copy).
    let mut honest = Vec::new();
    for name in ["honest-a", "honest-b"] {
        let r = svc
            .register(Request::new(register(name)))
            .await
            .unwrap()
            .into_inner();
        honest.push((r.worker_id, r.session));
    }
    for _ in 0..10_000 {
        let mut any = false;
        for (id, session) in &honest {
            let leases = svc
                .lease_work(signed(
                    v1::LeaseRequest {
                        worker_id: *id,
                        max_units: 8,
                        wait_ms: 0,
                    },
                    session,
                ))
                .await
                .unwrap()
                .into_inner()
                .leases;
            for lease in leases {
                any = true;
                let plan = lease.plan.unwrap();
                let unit = lease.unit.unwrap();
                let (w, h) = tile_size(plan.width, plan.height, plan.tile_size, unit.tile);
                let n = 3 * (unit.pass_count * w * h) as usize;
                let result = v1::SubmitResultRequest {
                    worker_id: *id,
                    lease_id: lease.lease_id,
                    unit: Some(unit),
                    width: w,
                    height: h,
                    pass_means: tessera_proto::means_to_bytes(&vec![0.5; n]),
                    render_seconds: 0.01,
                    job_id: lease.job_id,
                    rejected_samples: 0,
                    traced_pixel_passes: 0,
                    fence: lease.fence.clone(),
                    bias: Vec::new(),
                };
                let a = svc
                    .submit_result(signed(result, session))
                    .await
                    .unwrap()
                    .into_inner();
                assert!(a.accepted, "an honest result was refused: {}", a.reason);
            }
        }
        if !any {
            break;
        }
    }
    let status = core.status(job.id).await.unwrap();
    assert_eq!(status.state.as_str(), "done", "{status:?}");
    assert_eq!(status.passes_done, status.passes_planned);
    core.store().close().await;
    drop((svc, core));
    let again = Coordinator::open(CoordinatorConfig::new(dir.path()))
        .await
        .unwrap();
    let status = again.status(job.id).await.unwrap();
    assert_eq!(status.state.as_str(), "done");
    assert_eq!(status.passes_done, status.passes_planned);
}
