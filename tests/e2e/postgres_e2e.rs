//! The farm on a PostgreSQL store: real `tessera` processes on loopback against a real
//! PostgreSQL server (`TESSERA_TEST_POSTGRES`, a fresh schema per test; see
//! `tessera_testkit::postgres`), `kill -9` of the coordinator and a restart on the same
//! database. The reference image is `tessera render` of the same job, byte for byte
//! (ARCHITECTURE.md §2).

use crate::common;

use common::farm::TIMEOUT;
use common::farm::{
    cornell_job, local_render, start_coordinator, start_worker, stored_passes, wait_done,
};
use common::{free_addresses, output, poll, temp_dir};
use tessera_api::client::Client;

/// A fresh database URL, or `None` when PostgreSQL tests are skipped.
fn fresh_database(name: &str) -> Option<String> {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap()
        .block_on(tessera_testkit::postgres::fresh_database(name))
}

#[test]
fn a_farm_on_postgres_renders_the_local_image_and_resumes_after_kill9() {
    let Some(url) = fresh_database("e2e_kill_coordinator") else {
        return;
    };
    let dir = temp_dir("pg-e2e", "kill-coordinator");
    // Not used by a PostgreSQL store; a separate directory shows nothing is written there.
    let data = dir.join("unused-data");
    let s = cornell_job(64, 64, 128);
    let reference = local_render(&dir, &s);
    let (http, grpc) = free_addresses();
    let store = ["--store", url.as_str()];
    let mut c = start_coordinator(&data, &http, &grpc, &store);
    c.wait_active();
    let _w1 = start_worker(&c.grpc, "w1", &[]);
    let _w2 = start_worker(&c.grpc, "w2", &[]);
    let client = Client::new(&c.http, None);
    let running = client.submit(&s, None).unwrap();
    let mut queued = cornell_job(16, 16, 8);
    queued.priority = -1;
    let queued = client.submit(&queued, Some("key-1")).unwrap();
    poll("a quarter of the passes", TIMEOUT, || {
        let j = client.job(running.id).unwrap();
        j.passes_done * 4 >= j.passes_planned
    });
    // Killed once the store holds some of them: under load the first group commit (a
    // fresh connection) can still be on its way when the status shows a quarter merged.
    poll("passes committed to the store", TIMEOUT, || {
        stored_passes(&url, running.id) > 0
    });
    c.proc.kill9();

    // Restart on the same database and addresses; the workers reconnect by themselves.
    let c2 = start_coordinator(&data, &http, &grpc, &store);
    // A standby until the killed coordinator's lock session is gone (docs/store.md).
    c2.wait_active();
    let client = Client::new(&c2.http, None);
    let after = client.job(running.id).unwrap();
    assert!(
        after.passes_done > 0,
        "merged passes were lost in the restart"
    );
    assert!(after.passes_done < after.passes_planned);
    let done = wait_done(&client, running.id);
    assert_eq!(done.passes_done, done.passes_planned);
    let exr = client.image(running.id, "exr").unwrap();
    assert!(
        exr == reference,
        "EXR rendered on PostgreSQL after a coordinator kill differs from tessera render"
    );
    // The queued job survived, and its idempotency key still maps to it.
    let mut again = cornell_job(16, 16, 8);
    again.priority = -1;
    assert_eq!(client.submit(&again, Some("key-1")).unwrap().id, queued.id);
    wait_done(&client, queued.id);
    assert!(
        !data.join("tessera.sqlite3").exists(),
        "a SQLite file was created although --store names PostgreSQL"
    );
}

/// `tessera serve --store postgres://...`: the whole farm in one command on PostgreSQL.
#[test]
fn serve_on_postgres_renders_the_local_image() {
    let Some(url) = fresh_database("e2e_serve") else {
        return;
    };
    let dir = temp_dir("pg-e2e", "serve");
    let s = cornell_job(32, 24, 16);
    let reference = local_render(&dir, &s);
    let mut serve = common::Proc::spawn(
        "serve",
        common::tessera()
            .args([
                "serve",
                "--http",
                "127.0.0.1:0",
                "--grpc",
                "127.0.0.1:0",
                "--workers",
                "2",
                "--store",
                &url,
            ])
            .env_remove("TESSERA_API_TOKEN")
            .env_remove("TESSERA_WORKER_TOKEN"),
        None,
    );
    let http = serve.wait_line("http: ");
    let http = http.trim_end_matches("/api/v1");
    poll("tessera serve to be active", TIMEOUT, || {
        common::http_get(http, "/readyz").0 == 200
    });
    let client = Client::new(http, None);
    let st = client.submit(&s, None).unwrap();
    wait_done(&client, st.id);
    assert!(client.image(st.id, "exr").unwrap() == reference);
}

/// Bad `--store` values and a server that does not answer: a clear error naming the URL,
/// exit status 1 or 2, no panic. Needs no PostgreSQL server.
#[test]
fn bad_store_urls_and_unreachable_servers_are_clear_errors() {
    let dir = temp_dir("pg-e2e", "bad-urls");
    for (url, needle) in [
        ("mysql://h/db", "invalid store URL \"mysql://h/db\""),
        (
            "postgres://tessera:hunter2@127.0.0.1:1/tessera",
            "cannot reach the PostgreSQL store postgres://tessera:***@127.0.0.1:1/tessera",
        ),
    ] {
        let (ok, _, stderr) = output(
            common::tessera()
                .args([
                    "coordinator",
                    "--http",
                    "127.0.0.1:0",
                    "--grpc",
                    "127.0.0.1:0",
                ])
                .arg("--data")
                .arg(&dir)
                .args(["--store", url]),
        );
        assert!(!ok, "the coordinator started on {url}");
        assert!(stderr.contains(needle), "{stderr} should contain {needle}");
        assert!(!stderr.contains("hunter2"), "{stderr}");
        assert!(!stderr.contains("panicked"), "{stderr}");
    }
    // `tessera store` is for the SQLite store: with a PostgreSQL URL it names the tools.
    let (ok, _, stderr) = output(common::tessera().args([
        "store",
        "backup",
        "--store",
        "postgres://tessera@127.0.0.1:1/tessera",
        "out.dump",
    ]));
    assert!(!ok);
    assert!(stderr.contains("pg_dump"), "{stderr}");
    assert!(stderr.contains("pg_restore"), "{stderr}");
}
