//! `POST /api/v1/jobs?dry_run=true`: a real `tessera coordinator` quotes a job
//! from a pilot it renders in a child process (`tessera pilot`), with the same maths and
//! the same pilot as `tessera estimate`, and queues nothing.

use crate::common;
use tessera_testkit::api_error;

use common::farm::{cornell_job, start_coordinator, start_worker};
use common::{output_ok, poll, temp_dir, tessera};
use serde_json::Value;
use std::time::Duration;
use tessera_api::client::Client;

/// `tessera estimate ... --json` on this machine with one thread.
fn estimate(scene: &str, extra: &[&str]) -> Value {
    let out = output_ok(
        tessera()
            .args(["estimate", scene, "--json", "--threads", "1"])
            .args(extra),
    );
    serde_json::from_str(&out).unwrap_or_else(|e| panic!("{e}: {out}"))
}

#[test]
fn a_dry_run_quotes_like_tessera_estimate_and_queues_nothing() {
    let dir = temp_dir("dry-run", "quote");
    let c = start_coordinator(&dir.join("store"), "127.0.0.1:0", "127.0.0.1:0", &[]);
    let client = Client::new(&c.http, None);

    // A built-in scene, for an asked fleet.
    let mut s = cornell_job(32, 32, 64);
    s.tile_size = 8;
    let q = client.quote(&s, Some(3)).expect("dry run");
    assert_eq!(q["dry_run"], true, "{q}");
    assert_eq!(q["workers"], 3, "{q}");
    assert_eq!(q["threads"], 1, "{q}");
    // The coordinator's own spot-check fraction (its default), which the seconds count.
    assert_eq!(q["spot_check_fraction"], 0.02, "{q}");
    assert!(
        q["fleet"]
            .as_str()
            .unwrap()
            .contains("3 worker(s) as asked"),
        "{q}"
    );
    let targets: Vec<f64> = q["quote"]["targets"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| t["target"].as_f64().unwrap())
        .collect();
    assert_eq!(targets, [0.10, 0.05, 0.02, 0.01]);
    // The pilot is a pure function of the job: the coordinator's and `tessera estimate`'s
    // merge to the same image, so their errors agree to the bit (timings do not).
    let e = estimate(
        "builtin:cornell-box",
        &[
            "--width",
            "32",
            "--height",
            "32",
            "--spp",
            "64",
            "--seed",
            "5",
            "--tile-size",
            "8",
        ],
    );
    for field in ["pilot_error", "pilot_pixels", "pilot_passes"] {
        assert_eq!(q["quote"][field], e["quote"][field], "{field}: {q} vs {e}");
    }
    assert_eq!(
        q["quote"]["targets"][2]["passes"], e["quote"]["targets"][2]["passes"],
        "the passes to 2% follow from the pilot's error alone"
    );
    // `tessera submit --dry-run` asks the same and prints it as `tessera estimate` does.
    let out = output_ok(tessera().args([
        "submit",
        "builtin:cornell-box",
        "--server",
        &c.http,
        "--dry-run",
        "--workers",
        "2",
        "--width",
        "32",
        "--height",
        "32",
        "--spp",
        "64",
    ]));
    assert!(
        out.contains("dry run on the coordinator; assumes 2 worker(s) as asked"),
        "{out}"
    );
    assert!(out.contains("to reach error 0.02"), "{out}");
    // Nothing was queued or stored.
    assert!(client.jobs(10, None).unwrap().jobs.is_empty());

    // An uploaded scene reaches the pilot as the workers load it, and quotes as the file
    // does from the command line.
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../scenes/indirect-room.gltf"
    );
    let up = client.upload_scene(&std::fs::read(path).unwrap()).unwrap();
    let mut u = tessera_api::JobSettings::new(up.hash.clone());
    u.width = Some(24);
    u.height = Some(24);
    u.spp = 32;
    u.target_error = Some(0.05);
    let q = client.quote(&u, None).expect("dry run of an upload");
    assert!(
        q["fleet"]
            .as_str()
            .unwrap()
            .contains("no worker is connected"),
        "{q}"
    );
    let e = estimate(
        path,
        &[
            "--width",
            "24",
            "--height",
            "24",
            "--spp",
            "32",
            "--target-error",
            "0.05",
        ],
    );
    assert_eq!(
        q["quote"]["pilot_error"], e["quote"]["pilot_error"],
        "{q} vs {e}"
    );
    assert_eq!(q["quote"]["targets"].as_array().unwrap().len(), 1);
    assert_eq!(q["quote"]["targets"][0]["target"], 0.05);

    // The fleet is the connected workers when none is asked for.
    let _w = start_worker(&c.grpc, "w1", &[]);
    poll("the worker to register", Duration::from_secs(30), || {
        client.workers().is_ok_and(|l| !l.workers.is_empty())
    });
    let q = client.quote(&s, None).expect("dry run with a worker");
    assert_eq!(q["workers"], 1, "{q}");
    assert_eq!(q["worker_threads"], 1, "{q}");
    assert!(q["fleet"].as_str().unwrap().contains("1 connected"), "{q}");

    // What a submission refuses, a dry run refuses, naming the field.
    let mut bad = s.clone();
    bad.spp = 0;
    let (status, err) = api_error(client.quote(&bad, None));
    assert_eq!(
        (status, err.field.as_deref()),
        (400, Some("spp")),
        "{err:?}"
    );
    let (status, err) = api_error(client.quote(&s, Some(0)));
    assert_eq!(
        (status, err.field.as_deref()),
        (400, Some("workers")),
        "{err:?}"
    );
    // A pilot too large to render on the coordinator's host: big tiles of many samples.
    let mut big = cornell_job(1024, 1024, 4096);
    big.tile_size = 256;
    let (status, err) = api_error(client.quote(&big, None));
    assert_eq!(status, 413, "{err:?}");
    assert!(err.message.contains("tessera estimate"), "{err:?}");
    // Still nothing queued, and no pilot scene file left behind.
    assert!(client.jobs(10, None).unwrap().jobs.is_empty());
    let pid = c.proc.pid().unwrap();
    let left: Vec<_> = std::fs::read_dir(std::env::temp_dir())
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| {
            e.file_name()
                .to_string_lossy()
                .starts_with(&format!("tessera-pilot-{pid}-"))
        })
        .collect();
    assert!(left.is_empty(), "pilot scene files left: {left:?}");
}
