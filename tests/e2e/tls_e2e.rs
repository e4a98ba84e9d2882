//! TLS end to end with real processes on loopback (docs/tls.md): a CA and certificates
//! made here by rcgen; `tessera coordinator --tls-cert --tls-key --tls-client-ca`, a
//! `tessera worker` with `--tls-ca` and its client certificate, `tessera submit` and
//! `tessera status` with `--tls-ca` on `https://`. The farm's EXR must be byte-identical
//! to `tessera render` (ARCHITECTURE.md §2), and SIGHUP must put new certificate files in
//! force for new connections, keeping the old ones when the new ones are bad. Every wait
//! polls with a timeout.

use crate::common;

use std::path::Path;
use std::time::Duration;

use common::farm::{start_coordinator, start_worker};
use common::{output, output_ok, poll, temp_dir, tessera, Proc};
use tessera_testkit::test_ca::TestCa as Ca;

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// A worker named `w1` connecting over TLS to `grpc`, trusting `ca`, presenting the client
/// certificate `cert` with its key `key`.
fn tls_worker(grpc: &str, ca: &Path, cert: &Path, key: &Path) -> Proc {
    start_worker(
        grpc,
        "w1",
        &[
            "--tls-ca",
            s(ca),
            "--tls-cert",
            s(cert),
            "--tls-key",
            s(key),
        ],
    )
}

/// An API client of the coordinator at `http` (https://) that trusts `ca`.
fn tls_client(http: &str, ca: &Path) -> tessera_api::client::Client {
    tessera_api::client::Client::new(http, None)
        .with_tls_ca(&std::fs::read(ca).unwrap())
        .unwrap()
}

/// `tessera status --server SERVER --tls-ca CA --json`: whether it succeeded, and its
/// stderr.
fn status(server: &str, ca: &Path) -> (bool, String) {
    let (ok, _, err) =
        output(tessera().args(["status", "--server", server, "--tls-ca", s(ca), "--json"]));
    (ok, err)
}

#[test]
fn a_mutual_tls_farm_renders_the_local_image_byte_for_byte() {
    let dir = temp_dir("tls", "farm");
    let (ca, worker_ca, other) = (
        Ca::new("farm CA"),
        Ca::new("worker CA"),
        Ca::new("other CA"),
    );
    let ca_pem = ca.write(&dir, "ca.pem");
    let worker_ca_pem = worker_ca.write(&dir, "worker-ca.pem");
    let other_pem = other.write(&dir, "other.pem");
    let (cert, key) = ca.issue(&dir, "server", "coordinator", true);
    let (wcert, wkey) = worker_ca.issue(&dir, "worker", "render-node-1", false);

    let local = dir.join("local.exr");
    output_ok(tessera().args([
        "render",
        "builtin:cornell-box",
        "--width",
        "16",
        "--height",
        "16",
        "--spp",
        "4",
        "--seed",
        "5",
        "-o",
        s(&local),
    ]));

    let c = start_coordinator(
        &dir.join("data"),
        "127.0.0.1:0",
        "127.0.0.1:0",
        &[
            "--tls-cert",
            s(&cert),
            "--tls-key",
            s(&key),
            "--tls-client-ca",
            s(&worker_ca_pem),
        ],
    );
    assert!(c.http.starts_with("https://"), "{}", c.http);
    assert!(c.grpc.starts_with("https://"), "{}", c.grpc);

    // The HTTP clients: the right CA answers; another CA and plain text do not.
    assert!(status(&c.http, &ca_pem).0);
    let (ok, err) = status(&c.http, &other_pem);
    assert!(!ok && err.to_lowercase().contains("certificate"), "{err}");
    let plain = c.http.replacen("https://", "http://", 1);
    let (ok, _, _) = output(tessera().args(["status", "--server", &plain]));
    assert!(!ok, "plain text was answered on the TLS port");

    let _w = tls_worker(&c.grpc, &ca_pem, &wcert, &wkey);
    let farm = dir.join("farm.exr");
    output_ok(tessera().args([
        "submit",
        "builtin:cornell-box",
        "--width",
        "16",
        "--height",
        "16",
        "--spp",
        "4",
        "--seed",
        "5",
        "--server",
        &c.http,
        "--tls-ca",
        s(&ca_pem),
        "--wait",
        "--wait-timeout",
        "120",
        "-o",
        s(&farm),
    ]));
    assert!(
        std::fs::read(&farm).unwrap() == std::fs::read(&local).unwrap(),
        "the farm's EXR over mutual TLS differs from tessera render"
    );

    // The worker registered under its certificate's common name.
    let workers = tls_client(&c.http, &ca_pem).workers().unwrap().workers;
    assert_eq!(workers.len(), 1);
    assert_eq!(workers[0].identity.as_deref(), Some("render-node-1"));
}

/// Per-pod worker certificates rotate under a running worker (cert-manager's
/// csi-driver renews them in place, docs/deploy.md). The worker reads its files again
/// before every connection, so after its coordinator restarts it registers under the new
/// certificate's name, without a restart of its own.
#[test]
fn a_worker_presents_its_rotated_client_certificate_on_the_next_connection() {
    let dir = temp_dir("tls", "rotate");
    let (ca, worker_ca) = (Ca::new("farm CA"), Ca::new("worker CA"));
    let ca_pem = ca.write(&dir, "ca.pem");
    let worker_ca_pem = worker_ca.write(&dir, "worker-ca.pem");
    let (cert, key) = ca.issue(&dir, "server", "coordinator", true);
    let (wcert, wkey) = worker_ca.issue(&dir, "worker", "pod-a", false);
    let tls = [
        "--tls-cert",
        s(&cert),
        "--tls-key",
        s(&key),
        "--tls-client-ca",
        s(&worker_ca_pem),
    ];
    let data = dir.join("data");
    let mut c = start_coordinator(&data, "127.0.0.1:0", "127.0.0.1:0", &tls);
    let _w = tls_worker(&c.grpc, &ca_pem, &wcert, &wkey);
    let identities = |http: &str| -> Vec<String> {
        tls_client(http, &ca_pem)
            .workers()
            .map(|w| w.workers.into_iter().filter_map(|w| w.identity).collect())
            .unwrap_or_default()
    };
    poll(
        "the worker registered as pod-a",
        Duration::from_secs(30),
        || identities(&c.http) == ["pod-a"],
    );
    // The certificate is renewed in place (written whole, then renamed), and the
    // coordinator restarts on the same addresses: the worker reconnects with the new one.
    worker_ca.issue(&dir, "worker", "pod-b", false);
    let (http, grpc) = (
        c.http.trim_start_matches("https://").to_string(),
        c.grpc.trim_start_matches("https://").to_string(),
    );
    c.proc.kill9();
    let c2 = start_coordinator(&data, &http, &grpc, &tls);
    poll(
        "the worker registered again as pod-b",
        Duration::from_secs(30),
        || identities(&c2.http).contains(&"pod-b".to_string()),
    );
    assert!(
        !identities(&c2.http).contains(&"pod-a".to_string()),
        "the old certificate was presented again"
    );
}

#[test]
fn sighup_puts_new_certificate_files_in_force_and_keeps_the_old_ones_if_bad() {
    let dir = temp_dir("tls", "sighup");
    let (old_ca, new_ca) = (Ca::new("old CA"), Ca::new("new CA"));
    let (old_pem, new_pem) = (old_ca.write(&dir, "old.pem"), new_ca.write(&dir, "new.pem"));
    let (cert, key) = old_ca.issue(&dir, "server", "coordinator", true);
    let log = dir.join("coordinator.log");
    let mut proc = Proc::spawn(
        "coordinator",
        tessera()
            .args([
                "coordinator",
                "--http",
                "127.0.0.1:0",
                "--grpc",
                "127.0.0.1:0",
            ])
            .arg("--data")
            .arg(dir.join("data"))
            .args(["--tls-cert", s(&cert), "--tls-key", s(&key)])
            .env("RUST_LOG", "info")
            .env_remove("TESSERA_API_TOKEN"),
        Some(&log),
    );
    let http = proc
        .wait_line("http: ")
        .trim_end_matches("/api/v1")
        .to_string();
    let pid = proc.pid().unwrap().to_string();
    assert!(status(&http, &old_pem).0);
    assert!(!status(&http, &new_pem).0);

    // New files, SIGHUP: new connections see the new certificate.
    new_ca.issue(&dir, "server", "coordinator", true);
    output_ok(std::process::Command::new("kill").args(["-HUP", &pid]));
    poll(
        "the new certificate in force",
        Duration::from_secs(20),
        || status(&http, &new_pem).0,
    );
    assert!(
        !status(&http, &old_pem).0,
        "the old certificate is still served"
    );

    // A bad key, SIGHUP: an error is logged and the certificate in force stays.
    std::fs::write(&key, "not a key\n").unwrap();
    output_ok(std::process::Command::new("kill").args(["-HUP", &pid]));
    poll("the failed reload logged", Duration::from_secs(20), || {
        std::fs::read_to_string(&log)
            .unwrap_or_default()
            .contains("TLS reload failed")
    });
    let text = std::fs::read_to_string(&log).unwrap();
    assert!(
        text.contains("server.key"),
        "the error names the file: {text}"
    );
    assert!(
        status(&http, &new_pem).0,
        "a failed reload dropped the certificate"
    );
    proc.stop();
}

#[test]
fn bad_tls_flags_are_clear_errors_at_start() {
    let dir = temp_dir("tls", "flags");
    let missing = dir.join("missing.pem");
    let (ok, _, err) = output(tessera().args([
        "coordinator",
        "--http",
        "127.0.0.1:0",
        "--grpc",
        "127.0.0.1:0",
        "--data",
        s(&dir.join("data")),
        "--tls-cert",
        s(&missing),
        "--tls-key",
        s(&missing),
    ]));
    assert!(!ok && err.contains("missing.pem"), "{err}");
    let (ok, _, err) = output(tessera().args([
        "worker",
        "--coordinator",
        "https://127.0.0.1:1",
        "--tls-ca",
        s(&missing),
    ]));
    assert!(!ok && err.contains("missing.pem"), "{err}");
    let (ok, _, err) = output(tessera().args(["worker", "--coordinator", "https://127.0.0.1:1"]));
    assert!(!ok && err.contains("--tls-ca"), "{err}");
}
