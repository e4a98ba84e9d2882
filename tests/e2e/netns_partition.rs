//! The farm on several hosts: the coordinator and two workers, each in its own network
//! namespace joined by veth pairs (tests/e2e/common/netns.rs), real `tessera` processes run
//! by `ip netns exec`. One worker's link is cut for longer than its lease and restored;
//! another run degrades a link (loss, delay). Either way the job must complete with the
//! EXR byte-identical to `tessera render` (ARCHITECTURE.md §2), and no unit may be merged
//! twice.
//!
//! Needs root (CAP_NET_ADMIN) and iproute2, and nftables where the kernel has no netem.
//! Without them the tests say why and pass, unless `CI` is set: there they fail, since CI
//! runs as root. Every wait polls with a timeout.

use crate::common;

use std::path::Path;

use common::farm::{
    cornell_job, local_render, spawn_coordinator, spawn_worker, wait_done, Coord, TIMEOUT,
};
use common::netns::Hosts;
use common::{poll, temp_dir, wait_for, Proc};
use tessera_api::client::Client;
use tessera_api::JobSettings;

/// The gRPC port inside the coordinator's namespace (its own, so nothing else uses it).
const GRPC_PORT: u16 = 50051;
/// The HTTP API, on the coordinator's loopback: only the test, from inside, talks to it.
const HTTP: &str = "127.0.0.1:8080";
/// The worker token: a coordinator listening beyond loopback requires one
/// (docs/farm.md, "Worker credentials").
const WORKER_TOKEN: &str = "netns-partition-worker-token";

/// The namespaces, or `None` (the test passes) when they cannot be made here and `CI` is
/// not set.
fn hosts(tag: &str) -> Option<Hosts> {
    if let Some(why) = common::netns::unavailable(tag) {
        assert!(
            std::env::var_os("CI").is_none(),
            "CI is set but network namespaces cannot be made: {why}"
        );
        eprintln!("skipped: network namespaces cannot be made here: {why}");
        return None;
    }
    Some(Hosts::new(tag, 2))
}

/// The farm: a coordinator in its namespace (stderr, with its result log, in
/// `dir/coordinator.log`) and one single-threaded worker in each worker namespace, each
/// dialling the coordinator's address on its own link.
fn farm(h: &Hosts, dir: &Path, lease: &[&str]) -> (Coord, Vec<Proc>) {
    let mut cmd = Hosts::exec(&h.coordinator, env!("CARGO_BIN_EXE_tessera"));
    // Results that arrive late, duplicates included, are logged at info.
    cmd.env(
        "RUST_LOG",
        "warn,tessera_coordinator::service::results=info",
    );
    let grpc = format!("0.0.0.0:{GRPC_PORT}");
    let log = dir.join("coordinator.log");
    let mut extra = vec!["--worker-token", WORKER_TOKEN];
    extra.extend_from_slice(lease);
    let c = spawn_coordinator(cmd, &dir.join("data"), HTTP, &grpc, &extra, Some(&log));
    let workers = h
        .workers
        .iter()
        .enumerate()
        .map(|(i, ns)| {
            let url = format!("http://{}:{GRPC_PORT}", Hosts::coordinator_addr(i));
            spawn_worker(
                Hosts::exec(ns, env!("CARGO_BIN_EXE_tessera")),
                &[&url],
                &format!("w{i}"),
                &["--token", WORKER_TOKEN],
                None,
            )
        })
        .collect();
    (c, workers)
}

/// A counter from the coordinator's `/metrics`.
fn metric(text: &str, name: &str) -> u64 {
    tessera_testkit::require_metric(text, name) as u64
}

/// What the coordinator said of results that came back after their lease: (duplicates
/// compared with the merged copy and found identical, copies of a complete frame).
fn late_results(log: &Path) -> (usize, usize) {
    let text = std::fs::read_to_string(log).unwrap_or_default();
    (
        text.matches("the unit was already merged (identical copy dropped)")
            .count(),
        text.matches("late result for a complete frame").count(),
    )
}

/// Waits for job `id`, checks its image against `tessera render` and that every unit
/// was merged exactly once; returns /metrics.
fn finish(c: &Coord, h: &Hosts, s: &JobSettings, id: u64, reference: &[u8]) -> String {
    let http = &c.http;
    Hosts::within(&h.coordinator, || {
        let client = Client::new(http, None);
        let done = wait_done(&client, id);
        assert_eq!(done.passes_done, done.passes_planned);
        assert_eq!(
            done.faults, 0,
            "a result was refused or a duplicate differed"
        );
        let exr = client.image(id, "exr").unwrap();
        assert!(
            exr == reference,
            "{}x{}: EXR differs from tessera render",
            s.width.unwrap(),
            s.height.unwrap()
        );
        let metrics = String::from_utf8(client.get_raw("/metrics").unwrap()).unwrap();
        // One pass per unit (the coordinator's default): a unit merged twice would count
        // twice here (and change the image).
        assert_eq!(
            metric(&metrics, "tessera_units_merged_total"),
            done.passes_planned,
            "units merged != units planned"
        );
        metrics
    })
}

#[test]
fn a_worker_cut_off_past_its_lease_is_re_leased_and_its_late_results_are_compared() {
    let Some(h) = hosts("cut") else { return };
    let dir = temp_dir("netns", "cut");
    // 16 tiles of 16 x 16 pixels, 8 passes of 64 samples: 128 small units (the tile size
    // does not change the image), so the job outlasts the cut and the lease.
    let mut s = cornell_job(64, 64, 512);
    s.tile_size = 16;
    let reference = local_render(&dir, &s);
    // Leases of 1.5 s, heartbeats every 250 ms (tests/e2e/common/farm.rs).
    let (c, _workers) = farm(&h, &dir, &[]);
    // The API as the coordinator's host sees it (a `Coord` holds a process: not `Sync`).
    let http = &c.http;
    let (id, before) = Hosts::within(&h.coordinator, || {
        let client = Client::new(http, None);
        let id = client.submit(&s, None).unwrap().id;
        // Both workers are at work and most of the job is left.
        poll("both workers to deliver", TIMEOUT, || {
            let w = client.workers().unwrap().workers;
            w.len() == 2 && w.iter().all(|w| w.units_done > 0)
        });
        let j = client.job(id).unwrap();
        assert!(
            j.passes_done * 2 < j.passes_planned,
            "too little left to cut: {j:?}"
        );
        (id, j.passes_done)
    });
    h.set_link(0, false);
    eprintln!("cut w0's link at {before} passes merged");
    // The coordinator gives w0's units to w1 once w0's leases lapse unheard: the link
    // stays down until it has, whatever the timing of the machine.
    let expired = Hosts::within(&h.coordinator, || {
        let client = Client::new(http, None);
        wait_for("w0's leases to expire", TIMEOUT, || {
            let m = String::from_utf8(client.get_raw("/metrics").unwrap()).unwrap();
            match metric(&m, "tessera_leases_expired_total") {
                0 => Err("none yet".to_string()),
                n => Ok(n),
            }
        })
    });
    // And w1 renders on meanwhile: some of the re-leased work is merged without w0.
    let during = Hosts::within(&h.coordinator, || {
        let client = Client::new(http, None);
        let at = client.job(id).unwrap().passes_done;
        poll("w1 to merge more while w0 is cut off", TIMEOUT, || {
            client.job(id).unwrap().passes_done > at
        });
        client.job(id).unwrap()
    });
    assert!(
        during.passes_done < during.passes_planned,
        "the job finished during the cut"
    );
    h.set_link(0, true);
    eprintln!(
        "restored w0's link: {expired} leases had expired, {} passes merged",
        during.passes_done
    );
    let metrics = finish(&c, &h, &s, id, &reference);
    let (compared, late) = late_results(&dir.join("coordinator.log"));
    let expired = metric(&metrics, "tessera_leases_expired_total");
    eprintln!(
        "leases expired (units re-leased): {expired}; late results compared identical: {compared}; late for a complete frame: {late}"
    );
    // w0 delivers what it rendered while cut off once the link is back: each such unit is
    // either merged (if w1 had not yet) and w1's copy compared, or compared itself.
    assert!(
        compared > 0,
        "no late result was compared (log in {})",
        dir.display()
    );
    // w0 is back and working: it registered again or carried on.
    Hosts::within(&h.coordinator, || {
        let w = Client::new(http, None).workers().unwrap().workers;
        assert!(
            w.iter().any(|w| w.name == "w0" && w.units_done > 0),
            "{w:?}"
        );
    });
}

#[test]
fn a_slow_lossy_link_still_gives_the_local_image() {
    let Some(h) = hosts("lossy") else { return };
    let dir = temp_dir("netns", "lossy");
    // 16 tiles x 16 passes of 64: 256 units, each crossing the bad link twice. 1024
    // samples per pixel keep the healthy worker busy for seconds, long enough for the
    // degraded one (whose every request may wait out a retransmission) to take some.
    let mut s = cornell_job(64, 64, 1024);
    s.tile_size = 16;
    let reference = local_render(&dir, &s);
    let how = h
        .degrade(0)
        .unwrap_or_else(|e| panic!("cannot degrade a link here: {e}"));
    eprintln!("w0's link degraded with {how:?}");
    let (c, _workers) = farm(&h, &dir, &[]);
    let http = &c.http;
    let id = Hosts::within(&h.coordinator, || {
        let client = Client::new(http, None);
        // The job is submitted once both workers have registered: w0 registers across the
        // bad link (a lost SYN waits a second to be sent again), and a job submitted
        // before could be rendered by w1 alone, which proves nothing about the link.
        poll("both workers to register", TIMEOUT, || {
            let w = client.workers().unwrap().workers;
            w.len() == 2
        });
        client.submit(&s, None).unwrap().id
    });
    let metrics = finish(&c, &h, &s, id, &reference);
    let stats = h.degradation_stats(0);
    eprintln!("{how:?} on w0's link:\n{stats}");
    eprintln!(
        "leases expired: {}; units merged: {}",
        metric(&metrics, "tessera_leases_expired_total"),
        metric(&metrics, "tessera_units_merged_total")
    );
    // The degraded worker took part: its traffic crossed the bad link.
    Hosts::within(&h.coordinator, || {
        let w = Client::new(http, None).workers().unwrap().workers;
        assert!(
            w.iter().any(|w| w.name == "w0" && w.units_done > 0),
            "{w:?}"
        );
    });
}
