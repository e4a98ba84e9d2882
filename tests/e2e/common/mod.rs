//! Helpers shared by the end-to-end suites in `tests/e2e/`: running the real `tessera`
//! binary, temporary directories, child processes that are cleaned up when a test fails,
//! waiting for a line of output or a condition by polling, and reading EXR files back.
//!
//! The suites are modules of one test target of the `tessera-cli` package (`[[test]]`
//! `e2e` in `crates/tessera-cli/Cargo.toml`), so `CARGO_BIN_EXE_tessera` names the binary
//! under test; each uses this module with `use crate::common;`. Not every suite uses every
//! helper. Helpers that do not need the binary (test CA, PostgreSQL schemas, metrics,
//! API errors) are in the `tessera-testkit` crate.

#![allow(dead_code)]

pub mod farm;
pub mod netns;

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

/// How long [`Proc::wait_line`] waits for a line before it fails the test.
pub const LINE_TIMEOUT: Duration = Duration::from_secs(120);

/// The `tessera` binary built for this test run.
pub fn tessera() -> Command {
    Command::new(env!("CARGO_BIN_EXE_tessera"))
}

/// A fresh, empty directory `tessera-SUITE-NAME-PID` in the system temp directory.
pub fn temp_dir(suite: &str, name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("tessera-{suite}-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Runs `cmd` to completion: (success, stdout, stderr).
pub fn output(cmd: &mut Command) -> (bool, String, String) {
    let o = cmd.output().unwrap();
    (
        o.status.success(),
        String::from_utf8_lossy(&o.stdout).to_string(),
        String::from_utf8_lossy(&o.stderr).to_string(),
    )
}

/// Runs `tessera ARGS` to completion: (success, stdout, stderr).
pub fn run(args: &[&str]) -> (bool, String, String) {
    output(tessera().args(args))
}

/// Runs `cmd` to completion, fails the test with both streams unless it succeeded, and
/// returns its stdout.
pub fn output_ok(cmd: &mut Command) -> String {
    let what = format!("{cmd:?}");
    let (ok, stdout, stderr) = output(cmd);
    assert!(ok, "{what} failed: {stdout}\n{stderr}");
    stdout
}

/// Reads the EXR file at `path` (all channels and Tessera's metadata).
pub fn read_exr(path: impl AsRef<Path>) -> tessera_image::ExrChannels {
    let path = path.as_ref();
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    tessera_image::read_exr(&bytes).unwrap()
}

/// A free loopback port (bound and released; used where a restarted coordinator must
/// come back on the same address its workers reconnect to).
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// Two free loopback addresses `(http, grpc)` for a coordinator that must come back on
/// the same ones after a restart ([`free_port`]).
pub fn free_addresses() -> (String, String) {
    (
        format!("127.0.0.1:{}", free_port()),
        format!("127.0.0.1:{}", free_port()),
    )
}

/// `GET path` on the HTTP server at `base` (`http://HOST:PORT`, an `/api/v1` suffix is
/// ignored) without a client library: (status, body); (0, error) when it cannot connect.
pub fn http_get(base: &str, path: &str) -> (u16, String) {
    use std::io::{Read, Write};
    let addr = base
        .trim_start_matches("http://")
        .trim_end_matches("/api/v1")
        .trim_end_matches('/');
    let mut s = match std::net::TcpStream::connect(addr) {
        Ok(s) => s,
        Err(e) => return (0, e.to_string()),
    };
    let _ = s.set_read_timeout(Some(Duration::from_secs(10)));
    if let Err(e) = write!(
        s,
        "GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"
    ) {
        return (0, e.to_string());
    }
    let mut out = String::new();
    if let Err(e) = s.read_to_string(&mut out) {
        return (0, e.to_string());
    }
    let status = out
        .split(' ')
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    let body = out.split_once("\r\n\r\n").map_or("", |(_, b)| b);
    (status, body.to_string())
}

/// Polls `f` every 50 ms until it gives `Ok`; fails the test with `what` and the last
/// observation after `timeout`.
pub fn wait_for<T>(what: &str, timeout: Duration, mut f: impl FnMut() -> Result<T, String>) -> T {
    let deadline = Instant::now() + timeout;
    loop {
        let last = match f() {
            Ok(v) => return v,
            Err(e) => e,
        };
        assert!(
            Instant::now() < deadline,
            "timed out waiting for {what}; last: {last}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// Polls until `f` holds; fails the test with `what` after `timeout`.
pub fn poll(what: &str, timeout: Duration, mut f: impl FnMut() -> bool) {
    wait_for(what, timeout, || {
        if f() {
            Ok(())
        } else {
            Err("not yet".to_string())
        }
    })
}

/// What dropping a [`Proc`] does to a process that is still running.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum OnDrop {
    /// SIGKILL at once.
    Kill,
    /// [`Proc::stop`]: SIGTERM, SIGKILL if it has not exited within 15 s.
    Stop,
}

/// A child process that is ended when dropped, test failure included, so a failing test
/// leaves nothing behind. Its stdout is read on a thread (so the pipe never fills up),
/// echoed as `[NAME] line` into the test's captured output and queued for
/// [`Proc::wait_line`].
pub struct Proc {
    name: String,
    child: Option<Child>,
    lines: mpsc::Receiver<String>,
    /// Shown when the process fails to print what a test waits for.
    log: Option<PathBuf>,
    on_drop: OnDrop,
}

impl Proc {
    /// Spawns `cmd` with stdin closed, stdout piped and stderr written to `stderr_log`
    /// (inherited when `None`). Dropping the result kills the process ([`OnDrop::Kill`]).
    pub fn spawn(name: &str, cmd: &mut Command, stderr_log: Option<&Path>) -> Self {
        cmd.stdin(Stdio::null()).stdout(Stdio::piped());
        if let Some(log) = stderr_log {
            cmd.stderr(Stdio::from(std::fs::File::create(log).unwrap()));
        }
        let mut child = cmd
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start {name}: {e}"));
        let stdout = child.stdout.take().unwrap();
        let (tx, lines) = mpsc::channel();
        let tag = name.to_string();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                println!("[{tag}] {line}");
                // Once nobody listens, keep draining the pipe.
                let _ = tx.send(line);
            }
        });
        Self {
            name: name.to_string(),
            child: Some(child),
            lines,
            log: stderr_log.map(Path::to_path_buf),
            on_drop: OnDrop::Kill,
        }
    }

    /// The process id, while it runs.
    pub fn pid(&self) -> Option<u32> {
        self.child.as_ref().map(Child::id)
    }

    /// Sets what dropping does.
    pub fn on_drop(mut self, on_drop: OnDrop) -> Self {
        self.on_drop = on_drop;
        self
    }

    /// Shows `path` (rather than the stderr log) when the process fails to print a line a
    /// test waits for.
    pub fn diagnostics(mut self, path: &Path) -> Self {
        self.log = Some(path.to_path_buf());
        self
    }

    fn log_text(&self) -> String {
        self.log
            .as_ref()
            .map(|p| std::fs::read_to_string(p).unwrap_or_default())
            .unwrap_or_else(|| "(not captured)".to_string())
    }

    /// Waits for a stdout line containing `marker`; returns the trimmed text after it.
    pub fn wait_line(&mut self, marker: &str) -> String {
        self.wait_lines(&[marker]).pop().unwrap()
    }

    /// Waits until, for each marker, a stdout line containing it was printed, in any
    /// order; returns the trimmed text after each marker, in the order of `markers`.
    /// Fails the test if the process exits first or [`LINE_TIMEOUT`] passes.
    pub fn wait_lines(&mut self, markers: &[&str]) -> Vec<String> {
        self.try_wait_lines(markers)
            .unwrap_or_else(|e| panic!("{e}"))
    }

    /// [`Proc::wait_lines`], but a process that exits first is an `Err` saying so (with its
    /// stderr), for a caller that can start it again; running out of time still fails.
    pub fn try_wait_lines(&mut self, markers: &[&str]) -> Result<Vec<String>, String> {
        let deadline = Instant::now() + LINE_TIMEOUT;
        let mut found: Vec<Option<String>> = vec![None; markers.len()];
        while found.iter().any(Option::is_none) {
            match self.lines.recv_timeout(Duration::from_millis(200)) {
                Ok(line) => {
                    for (slot, marker) in found.iter_mut().zip(markers) {
                        if let Some(i) = line.find(marker) {
                            *slot = Some(line[i + marker.len()..].trim().to_string());
                        }
                    }
                    continue;
                }
                Err(mpsc::RecvTimeoutError::Timeout) => {}
                Err(mpsc::RecvTimeoutError::Disconnected) => {
                    let status = self.child.as_mut().and_then(|c| c.wait().ok());
                    return Err(format!(
                        "{} exited ({status:?}) before printing {markers:?}; stderr:\n{}",
                        self.name,
                        self.log_text()
                    ));
                }
            }
            if let Some(Ok(Some(status))) = self.child.as_mut().map(Child::try_wait) {
                return Err(format!(
                    "{} exited ({status}) before printing {markers:?}; stderr:\n{}",
                    self.name,
                    self.log_text()
                ));
            }
            assert!(
                Instant::now() < deadline,
                "{} printed no {markers:?} line in time; stderr:\n{}",
                self.name,
                self.log_text()
            );
        }
        Ok(found.into_iter().map(Option::unwrap).collect())
    }

    /// SIGKILL, and waits for the process to be gone.
    pub fn kill9(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }

    /// SIGTERM (so `tessera serve` stops its local workers), SIGKILL if the process has
    /// not exited within 15 s; returns how it exited.
    pub fn stop(&mut self) -> Option<ExitStatus> {
        let mut child = self.child.take()?;
        if let Ok(Some(status)) = child.try_wait() {
            return Some(status);
        }
        let _ = Command::new("kill")
            .args(["-TERM", &child.id().to_string()])
            .status();
        let deadline = Instant::now() + Duration::from_secs(15);
        while Instant::now() < deadline {
            if let Ok(Some(status)) = child.try_wait() {
                return Some(status);
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        eprintln!(
            "{} did not stop on SIGTERM within 15 s: killing it",
            self.name
        );
        let _ = child.kill();
        child.wait().ok()
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        match self.on_drop {
            OnDrop::Kill => self.kill9(),
            OnDrop::Stop => {
                self.stop();
            }
        }
    }
}
