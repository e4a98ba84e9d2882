//! Running `tessera pilot` as a child process: the one way the coordinator renders a
//! user's scene (a dry run's quote, [`super::quote`], and the technique pilot,
//! [`super::technique`]). A scene that crashes or exhausts the renderer takes only the
//! child down, and a child that overruns its time is killed.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{ExitStatus, Stdio};
use std::sync::Arc;
use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};

use crate::state::now_ms;

/// The most a pilot may print: its answer is a few kilobytes.
const MAX_PILOT_OUTPUT: u64 = 1 << 20;

/// The most of a failed pilot's standard error that is read (its last line is reported).
const MAX_PILOT_STDERR: u64 = 64 << 10;

/// Why a child pilot gave no answer.
#[derive(Debug)]
pub(crate) enum ChildError {
    /// It could not be started, its pipes failed, or its scene file could not be written.
    Io(String),
    /// It ran past its time and was killed.
    Timeout(Duration),
    /// It exited unsuccessfully; the last line of its standard error says why.
    Failed {
        /// Its exit status.
        status: ExitStatus,
        /// The last non-empty line of its standard error, `error: ` removed.
        message: String,
    },
}

/// A scene file handed to a pilot, removed when dropped.
struct TempScene(PathBuf);

impl TempScene {
    /// Writes `bytes` to a new file in the system's temporary directory, its name ending
    /// in `suffix` (the pilot reads files by their contents, not their names).
    fn write(bytes: &[u8], suffix: &str) -> std::io::Result<Self> {
        static NEXT: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
        let n = NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let path = std::env::temp_dir().join(format!(
            "tessera-pilot-{}-{}-{n}{suffix}",
            std::process::id(),
            now_ms()
        ));
        let mut f = std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(&path)?;
        let t = Self(path);
        f.write_all(bytes)?;
        Ok(t)
    }
}

impl Drop for TempScene {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.0);
    }
}

/// Writes `bytes` (if any) to a temporary file for a pilot, off the async runtime's
/// threads (up to MAX_SCENE_BYTES of file I/O); `what` names it in errors.
async fn temp_file(
    bytes: Option<Arc<Vec<u8>>>,
    suffix: &'static str,
    what: &str,
) -> Result<Option<TempScene>, ChildError> {
    let Some(b) = bytes else {
        return Ok(None);
    };
    let f = tokio::task::spawn_blocking(move || TempScene::write(&b, suffix))
        .await
        .map_err(|e| ChildError::Io(e.to_string()))?
        .map_err(|e| ChildError::Io(format!("writing the pilot's {what}: {e}")))?;
    Ok(Some(f))
}

/// Runs `program pilot ARGS [--scene-file F] [--environment-file E]` with `body` (the
/// job's settings as JSON) on its standard input and returns its standard output; `scene`
/// is the uploaded scene's bytes (`None` for a built-in scene) and `environment` the
/// job's environment image's (`None` without one), each written to a temporary file for
/// it.
pub(crate) async fn run_pilot(
    program: &Path,
    args: &[String],
    scene: Option<Arc<Vec<u8>>>,
    environment: Option<Arc<Vec<u8>>>,
    body: Vec<u8>,
    timeout: Duration,
) -> Result<Vec<u8>, ChildError> {
    let scene_file = temp_file(scene, ".glb", "scene").await?;
    let environment_file = temp_file(environment, ".env", "environment image").await?;
    let mut cmd = tokio::process::Command::new(program);
    cmd.arg("pilot")
        .args(args)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .kill_on_drop(true);
    if let Some(f) = &scene_file {
        cmd.arg("--scene-file").arg(&f.0);
    }
    if let Some(f) = &environment_file {
        cmd.arg("--environment-file").arg(&f.0);
    }
    let run = async {
        let mut child = cmd.spawn().map_err(|e| {
            ChildError::Io(format!("starting the pilot {}: {e}", program.display()))
        })?;
        let (Some(mut stdin), Some(stdout), Some(stderr)) =
            (child.stdin.take(), child.stdout.take(), child.stderr.take())
        else {
            return Err(ChildError::Io("the pilot's pipes were not opened".into()));
        };
        let mut out = Vec::new();
        let mut err = Vec::new();
        let mut stdout = stdout.take(MAX_PILOT_OUTPUT);
        let mut stderr = stderr.take(MAX_PILOT_STDERR);
        let write = async {
            // A pilot that exits early closes its end: its exit status says why.
            let _ = stdin.write_all(&body).await;
            drop(stdin);
        };
        let (_, o, e, status) = tokio::join!(
            write,
            stdout.read_to_end(&mut out),
            stderr.read_to_end(&mut err),
            child.wait()
        );
        o.and(e)
            .map_err(|e| ChildError::Io(format!("reading the pilot: {e}")))?;
        let status = status.map_err(|e| ChildError::Io(format!("waiting for the pilot: {e}")))?;
        Ok((status, out, err))
    };
    let (status, out, err) = match tokio::time::timeout(timeout, run).await {
        Ok(r) => r?,
        // Dropping the future kills the child (kill_on_drop).
        Err(_) => return Err(ChildError::Timeout(timeout)),
    };
    if !status.success() {
        let text = String::from_utf8_lossy(&err);
        let message = text
            .lines()
            .rev()
            .find(|l| !l.trim().is_empty())
            .unwrap_or("no message")
            .trim()
            .trim_start_matches("error: ")
            .to_string();
        return Err(ChildError::Failed { status, message });
    }
    Ok(out)
}
