//! Storage integrity against the real `tessera` binary (docs/store.md): a
//! store that lost its WAL, has damaged pages or cannot be written is refused at start
//! with the recovery steps; a write failing while the coordinator runs makes it stop
//! accepting work (503) while reads keep working; `tessera store backup` of a running
//! store and `tessera store restore` bring the jobs back; job ids never repeat.

use crate::common;

use std::path::{Path, PathBuf};
use std::process::Command;

use common::farm::start_coordinator;
use common::{output, temp_dir, tessera, Proc};
use tessera_api::client::{Client, ClientError};
use tessera_api::JobSettings;

fn small_job(name: &str) -> JobSettings {
    let mut job = JobSettings::new("builtin:cornell-box");
    (job.width, job.height, job.spp) = (Some(16), Some(16), 4);
    job.name = Some(name.into());
    job
}

/// Starts a coordinator on `data` (port 0) and submits `n` jobs; returns it, its client
/// and the job ids.
fn coordinator_with_jobs(data: &Path, n: usize) -> (common::farm::Coord, Client, Vec<u64>) {
    let c = start_coordinator(data, "127.0.0.1:0", "127.0.0.1:0", &[]);
    let client = Client::new(&c.http, None);
    let ids = (0..n)
        .map(|i| {
            client
                .submit(&small_job(&format!("job {i}")), None)
                .unwrap()
                .id
        })
        .collect();
    (c, client, ids)
}

/// `tessera coordinator` on `data` must refuse to start: returns its stderr.
fn refused_start(data: &Path) -> String {
    let (ok, stdout, stderr) = output(
        tessera()
            .args([
                "coordinator",
                "--http",
                "127.0.0.1:0",
                "--grpc",
                "127.0.0.1:0",
            ])
            .arg("--data")
            .arg(data),
    );
    assert!(!ok, "the coordinator started: {stdout}\n{stderr}");
    assert!(!stdout.contains("http: "), "it served: {stdout}");
    stderr
}

/// `tessera store SUBCOMMAND --data DATA ARGS`: (success, stdout, stderr).
fn store(sub: &str, data: &Path, args: &[&Path]) -> (bool, String, String) {
    output(
        tessera()
            .args(["store", sub, "--data"])
            .arg(data)
            .args(args),
    )
}

fn db(data: &Path) -> PathBuf {
    data.join("tessera.sqlite3")
}

/// Copies the files of a data directory (no subdirectories).
fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        if e.file_type().unwrap().is_file() {
            std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
        }
    }
}

/// Overwrites `len` bytes of `file` at `offset` with a pattern that is no valid page.
fn scribble(file: &Path, offset: u64, len: usize) {
    use std::io::{Seek, SeekFrom, Write};
    let mut f = std::fs::OpenOptions::new().write(true).open(file).unwrap();
    f.seek(SeekFrom::Start(offset)).unwrap();
    let junk: Vec<u8> = (0..len).map(|i| (i * 151 + 7) as u8).collect();
    f.write_all(&junk).unwrap();
    f.sync_all().unwrap();
}

#[test]
fn a_deleted_or_damaged_wal_is_refused_and_job_ids_never_repeat() {
    let dir = temp_dir("store", "wal");
    let data = dir.join("data");
    let (mut c, _client, ids) = coordinator_with_jobs(&data, 3);
    // kill -9: no checkpoint, so the WAL holds every commit answered 201.
    c.proc.kill9();
    let wal = data.join("tessera.sqlite3-wal");
    assert!(wal.metadata().unwrap().len() > 0, "the WAL holds the jobs");
    let damaged = dir.join("damaged");
    copy_dir(&data, &damaged);
    std::fs::remove_file(&wal).unwrap();
    scribble(&damaged.join("tessera.sqlite3-wal"), 100, 2000);

    for d in [&data, &damaged] {
        let stderr = refused_start(d);
        for needle in [
            "behind its commit marker",
            "tessera.commit-marker",
            "job ids up to 3",
            "tessera store restore --data",
            "tessera store accept-loss --data",
        ] {
            assert!(stderr.contains(needle), "{needle:?} missing from: {stderr}");
        }
        let (ok, stdout, _) = store("check", d, &[]);
        assert!(!ok, "store check passed: {stdout}");
        assert!(stdout.contains("BEHIND"), "{stdout}");
    }

    // Accepting the loss: the coordinator starts, and the lost ids are not issued again.
    let (ok, stdout, stderr) = store("accept-loss", &data, &[]);
    assert!(ok, "{stdout}\n{stderr}");
    let (ok, stdout, _) = store("check", &data, &[]);
    assert!(ok, "{stdout}");
    let (_c, _client, after) = coordinator_with_jobs(&data, 1);
    assert!(
        after[0] > *ids.iter().max().unwrap(),
        "{after:?} after {ids:?}"
    );
}

#[test]
fn damaged_pages_are_refused_and_an_empty_start_keeps_ids_unique() {
    let dir = temp_dir("store", "pages");
    let data = dir.join("data");
    let (mut c, _client, ids) = coordinator_with_jobs(&data, 20);
    // A graceful stop checkpoints the WAL into the database file.
    assert!(c.proc.stop().is_some_and(|s| s.success()));
    let len = db(&data).metadata().unwrap().len();
    assert!(len >= 5 * 4096, "{len} bytes");
    scribble(&db(&data), 4096, 3 * 4096); // pages 2 to 4: table b-tree pages
    let stderr = refused_start(&data);
    for needle in [
        "is damaged",
        "tessera.sqlite3",
        "tessera store restore --data",
    ] {
        assert!(stderr.contains(needle), "{needle:?} missing from: {stderr}");
    }
    let (ok, stdout, _) = store("check", &data, &[]);
    assert!(!ok && stdout.contains("DAMAGED"), "{stdout}");

    // The documented way to start empty: move the database away, accept.
    let aside = dir.join("aside");
    std::fs::create_dir_all(&aside).unwrap();
    std::fs::rename(db(&data), aside.join("tessera.sqlite3")).unwrap();
    let (ok, stdout, stderr) = store("accept-loss", &data, &[]);
    assert!(ok, "{stdout}\n{stderr}");
    let (_c, client, after) = coordinator_with_jobs(&data, 1);
    assert!(
        after[0] > *ids.iter().max().unwrap(),
        "{after:?} after {ids:?}"
    );
    assert_eq!(client.jobs(50, None).unwrap().jobs.len(), 1);
}

/// Makes `path` immutable (`chattr +i`, which binds root too) until dropped; `None` where
/// the filesystem or the user cannot.
struct Immutable(PathBuf);

impl Immutable {
    fn set(path: &Path) -> Option<Self> {
        let ok = Command::new("chattr")
            .arg("+i")
            .arg(path)
            .status()
            .is_ok_and(|s| s.success());
        ok.then(|| Self(path.to_path_buf()))
    }
}

impl Drop for Immutable {
    fn drop(&mut self) {
        let _ = Command::new("chattr").arg("-i").arg(&self.0).status();
    }
}

#[test]
fn a_read_only_store_is_refused_at_start() {
    // In the target directory, not the system temp directory: that may be a tmpfs,
    // which has no immutable flag.
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR"))
        .join(format!("store-read-only-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let data = dir.join("data");
    let (mut c, _client, _) = coordinator_with_jobs(&data, 1);
    assert!(c.proc.stop().is_some_and(|s| s.success()));
    for target in [db(&data), data.clone()] {
        let Some(_guard) = Immutable::set(&target) else {
            // chattr needs root (CAP_LINUX_IMMUTABLE) and a filesystem with the flag.
            eprintln!(
                "SKIPPED: `chattr +i {}` failed (root: {}); the read-only start is not checked here",
                target.display(),
                is_root()
            );
            return;
        };
        let stderr = refused_start(&data);
        assert!(
            stderr.contains("is not writable") && stderr.contains(&*data.to_string_lossy()),
            "{}: {stderr}",
            target.display()
        );
    }
    // Writable again: it starts.
    let _c = start_coordinator(&data, "127.0.0.1:0", "127.0.0.1:0", &[]);
}

/// The status code of `GET PATH` on the coordinator whose API is at `api`.
fn http_status(api: &str, path: &str) -> u16 {
    use std::io::{Read, Write};
    let addr = api
        .trim_start_matches("http://")
        .trim_end_matches("/api/v1");
    let mut s = std::net::TcpStream::connect(addr).unwrap();
    write!(
        s,
        "GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut out = String::new();
    s.read_to_string(&mut out).unwrap();
    out.split(' ')
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0)
}

fn is_root() -> bool {
    output(Command::new("id").arg("-u")).1.trim() == "0"
}

/// A self-contained glTF of about `pad` bytes, different for each `i` (a distinct hash).
fn padded_scene(i: usize, pad: usize) -> Vec<u8> {
    let text = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../scenes/cornell-box.gltf"
    ))
    .unwrap();
    let generator = format!("padding {i} {}", "x".repeat(pad));
    text.replacen("scenes/make_cornell_gltf.py", &generator, 1)
        .into_bytes()
}

#[test]
fn a_failing_write_stops_accepting_work_and_reads_keep_working() {
    let dir = temp_dir("store", "full");
    let data = dir.join("data");
    let log = dir.join("coordinator.log");
    // A file size limit (it binds root too) makes the store's writes fail with EFBIG
    // once its WAL reaches 4 MiB, as a full disk would; SIGXFSZ is ignored so the write
    // fails instead of killing the process.
    let script = format!(
        "trap '' XFSZ; ulimit -f 8192; exec '{}' coordinator --http 127.0.0.1:0 --grpc 127.0.0.1:0 --data '{}'",
        env!("CARGO_BIN_EXE_tessera"),
        data.display()
    );
    let mut proc = Proc::spawn(
        "coordinator",
        Command::new("sh")
            .args(["-c", &script])
            .env("RUST_LOG", "warn"),
        Some(&log),
    );
    let http = proc.wait_line("http: ");
    let client = Client::new(http.trim_end_matches("/api/v1"), None);
    let job = client.submit(&small_job("before"), None).unwrap();
    let mut refused = None;
    for i in 0..40 {
        match client.upload_scene(&padded_scene(i, 512 << 10)) {
            Ok(_) => {}
            Err(ClientError::Api { status, error }) => {
                refused = Some((i, status, error));
                break;
            }
            Err(e) => panic!("upload {i}: {e}"),
        }
    }
    let (i, status, error) = refused.expect("an upload beyond the file size limit failed");
    assert!(i > 0, "the first upload already failed");
    assert_eq!(status, 503, "{error:?}");
    assert!(
        error.message.contains("the store failed to write")
            && error.message.contains("accepts no new work"),
        "{}",
        error.message
    );
    // From now on: no new work, with the reason.
    match client.submit(&small_job("after"), None) {
        Err(ClientError::Api { status: 503, error }) => {
            assert_eq!(error.code.as_str(), "unavailable");
            assert!(
                error.message.contains("accepts no new work"),
                "{}",
                error.message
            );
        }
        other => panic!("expected 503, got {other:?}"),
    }
    assert_eq!(http_status(&http, "/healthz"), 503);
    // Reads keep working.
    assert_eq!(client.job(job.id).unwrap().id, job.id);
    assert!(!client.jobs(10, None).unwrap().jobs.is_empty());
    proc.kill9();
    let log = std::fs::read_to_string(&log).unwrap();
    assert!(
        log.contains("ERROR") && log.contains("store write failed"),
        "{log}"
    );
}

#[test]
fn backup_of_a_running_store_restores_with_its_jobs() {
    let dir = temp_dir("store", "backup");
    let data = dir.join("data");
    let backup = dir.join("backup.sqlite3");
    let (mut c, client, ids) = coordinator_with_jobs(&data, 3);
    let (ok, stdout, stderr) = store("backup", &data, &[&backup]);
    assert!(ok, "{stdout}\n{stderr}");
    assert!(stdout.contains("3 queued"), "{stdout}");
    // A job after the backup: lost by the restore, but its id is never issued again.
    let late = client.submit(&small_job("late"), None).unwrap().id;
    // Restoring needs the coordinator stopped.
    assert!(c.proc.stop().is_some_and(|s| s.success()));
    let (ok, stdout, stderr) = store("restore", &data, &[&backup]);
    assert!(ok, "{stdout}\n{stderr}");
    assert!(stdout.contains("replaced files moved to"), "{stdout}");
    let (ok, stdout, _) = store("check", &data, &[]);
    assert!(ok, "{stdout}");
    let (_c, client, after) = coordinator_with_jobs(&data, 1);
    let listed: Vec<u64> = client
        .jobs(50, None)
        .unwrap()
        .jobs
        .iter()
        .map(|j| j.id)
        .collect();
    for id in &ids {
        assert!(listed.contains(id), "job {id} missing from {listed:?}");
    }
    assert!(!listed.contains(&late));
    assert!(after[0] > late, "{after:?} reissues {late}");
    // A damaged backup is refused and changes nothing.
    let bad = dir.join("bad.sqlite3");
    std::fs::write(&bad, b"not a database").unwrap();
    let (ok, _, stderr) = store("restore", &data, &[&bad]);
    assert!(!ok && stderr.contains("not usable"), "{stderr}");
}
