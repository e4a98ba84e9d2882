//! `tessera submit`: uploads the scene if it is a file (and the `--environment` image if
//! it is one), submits the job built from
//! `tessera render`'s flags ([`JobArgs::settings`]), and with `--wait` follows it to the
//! end and downloads the image.

use anyhow::{bail, Context, Result};
use clap::Args;
use std::path::{Path, PathBuf};
use std::time::Duration;
use tessera_api::client::Client;
use tessera_api::{FrameRange, JobSettings, JobState, JobStatus};

use crate::common::client_error;
use crate::render::{JobArgs, StopArgs};
use crate::status::progress_line;

/// Job options of `tessera submit` (the same meaning as `tessera render`'s).
#[derive(Args, Clone, Debug)]
pub struct SubmitArgs {
    /// The job, with the same flags as `tessera render` (SCENE is builtin:NAME, or a
    /// .gltf/.glb file, uploaded first).
    #[command(flatten)]
    pub job: JobArgs,
    /// When the job stops before its budget, as with `tessera render`.
    #[command(flatten)]
    pub stop: StopArgs,
    /// The coordinator's HTTP URL.
    #[arg(long, default_value = "http://127.0.0.1:8080", env = "TESSERA_SERVER")]
    pub server: String,
    /// API bearer token.
    #[arg(long, env = "TESSERA_API_TOKEN")]
    pub token: Option<String>,
    /// CA certificate(s) (PEM) an `https://` server's certificate must be issued by.
    #[arg(long, value_name = "FILE")]
    pub tls_ca: Option<PathBuf>,
    /// First frame.
    #[arg(long, default_value_t = 0)]
    pub frame_start: u32,
    /// Last frame (inclusive; default the first).
    #[arg(long)]
    pub frame_end: Option<u32>,
    /// Higher runs first.
    #[arg(long, default_value_t = 0)]
    pub priority: i32,
    /// A name for the job.
    #[arg(long)]
    pub name: Option<String>,
    /// Idempotency key: a retried submission with the same key returns the same job.
    #[arg(long)]
    pub idempotency_key: Option<String>,
    /// Quote the job instead of submitting it (`POST /jobs?dry_run=true`): the coordinator
    /// renders a short pilot and predicts the time to reach 10%, 5%, 2% and 1% error (or
    /// --target-error) on its workers. Nothing is queued.
    #[arg(long, conflicts_with_all = ["wait", "output", "idempotency_key"])]
    pub dry_run: bool,
    /// With --dry-run: the workers the quote assumes (default: the connected ones).
    #[arg(long, requires = "dry_run")]
    pub workers: Option<u32>,
    /// With --dry-run: print the coordinator's answer as JSON.
    #[arg(long, requires = "dry_run")]
    pub json: bool,
    /// Wait until the job is done, showing progress.
    #[arg(long)]
    pub wait: bool,
    /// With --wait: write the final image here (.exr or .png). A job of several frames
    /// needs a run of `#` in the file name, replaced by each frame's number zero-padded
    /// to its length: `-o out_####.exr` writes out_0000.exr, out_0001.exr, ...
    #[arg(short, long)]
    pub output: Option<PathBuf>,
    /// With --wait: give up after this many seconds.
    #[arg(long, default_value_t = 86_400.0)]
    pub wait_timeout: f64,
}

/// `tessera submit`.
pub fn submit(args: SubmitArgs) -> Result<()> {
    let client =
        crate::common::api_client(&args.server, args.token.clone(), args.tls_ca.as_deref())?;
    let scene = scene_ref(&client, &args.job.scene)?;
    let mut s = args.job.settings(scene, &args.stop);
    upload_environment(&client, &mut s)?;
    s.frames = FrameRange {
        start: args.frame_start,
        end: args.frame_end.unwrap_or(args.frame_start),
    };
    s.priority = args.priority;
    s.name = args.name.clone();
    if let Some(out) = &args.output {
        if !args.wait {
            bail!("-o/--output needs --wait");
        }
        let ext = out.extension().and_then(|e| e.to_str()).unwrap_or("");
        if !matches!(ext, "exr" | "png") {
            bail!("output {} must end in .exr or .png", out.display());
        }
        if s.frames.count() > 1 && frame_pattern(out).is_none() {
            bail!(
                "a job of {} frames writes one file per frame: give -o a run of # for the \
                 frame number, e.g. out_####.exr",
                s.frames.count()
            );
        }
    }
    if args.dry_run {
        let v = client.quote(&s, args.workers).map_err(client_error)?;
        if args.json {
            println!("{}", serde_json::to_string_pretty(&v)?);
            return Ok(());
        }
        return crate::estimate::print_dry_run(v);
    }
    let job = client
        .submit(&s, args.idempotency_key.as_deref())
        .map_err(client_error)?;
    println!("job {} {}", job.id, job.state.as_str());
    if !args.wait {
        return Ok(());
    }
    let done = wait(&client, job.id, args.wait_timeout)?;
    if let Some(out) = &args.output {
        if frame_pattern(out).is_some() {
            for frame in s.frames.iter() {
                download(&client, done.id, Some(frame), &frame_path(out, frame))?;
            }
        } else {
            download(&client, done.id, None, out)?;
        }
    }
    Ok(())
}

/// The byte range of the last run of `#` in the file name of `out`, if any.
fn frame_pattern(out: &Path) -> Option<std::ops::Range<usize>> {
    let name = out.file_name()?.to_str()?;
    let end = name.rfind('#')? + 1;
    let start = name[..end].trim_end_matches('#').len();
    Some(start..end)
}

/// `out` with its run of `#` replaced by `frame`, zero-padded to the run's length
/// (`out_####.exr`, frame 7: `out_0007.exr`; longer numbers are not cut).
fn frame_path(out: &Path, frame: u32) -> PathBuf {
    let Some(r) = frame_pattern(out) else {
        return out.to_path_buf();
    };
    let name = out.file_name().and_then(|n| n.to_str()).unwrap_or_default();
    let width = r.len();
    let file = format!("{}{frame:0width$}{}", &name[..r.start], &name[r.end..]);
    out.with_file_name(file)
}

/// The job's scene: a built-in as named, a file uploaded first and named by its hash.
fn scene_ref(client: &Client, scene: &str) -> Result<String> {
    if scene.starts_with("builtin:") {
        return Ok(scene.to_string());
    }
    let path = PathBuf::from(scene);
    let bytes = std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?;
    let up = client.upload_scene(&bytes).map_err(client_error)?;
    println!(
        "uploaded {} ({} bytes, {} triangles): {}",
        path.display(),
        up.bytes,
        up.triangles,
        up.hash
    );
    Ok(up.hash)
}

/// Uploads `--environment`'s image, if it names a file, and puts its hash in `s` (the
/// file's SHA-256, which is the upload's content address); a colour stays as it is.
fn upload_environment(client: &Client, s: &mut JobSettings) -> Result<()> {
    let file = s.environment.as_ref().map(|e| e.source.clone());
    let Some(bytes) = crate::render::environment_source(s)? else {
        return Ok(());
    };
    let up = client.upload_scene(&bytes).map_err(client_error)?;
    println!(
        "uploaded environment {} ({} bytes): {}",
        file.unwrap_or_default(),
        up.bytes,
        up.hash
    );
    if let Some(e) = &mut s.environment {
        e.source = up.hash;
    }
    Ok(())
}

/// Follows the job to its end, printing each new progress line to standard error and the
/// last one to standard output; an end other than `done` is an error.
fn wait(client: &Client, id: u64, timeout_seconds: f64) -> Result<JobStatus> {
    let mut last = String::new();
    let mut last_class = None;
    let done = client
        .wait(
            id,
            Duration::from_millis(500),
            Duration::from_secs_f64(timeout_seconds.max(1.0)),
            |st| {
                let line = progress_line(st);
                if line != last {
                    eprintln!("{line}");
                    last = line;
                }
                // Why the ETA is widened or not predictable, when its class changes (the
                // note's figures change with every merge).
                if st.eta_tail_class != last_class {
                    if let Some(n) = &st.eta_note {
                        eprintln!("eta: {n}");
                    }
                    last_class.clone_from(&st.eta_tail_class);
                }
            },
        )
        .map_err(client_error)?;
    println!("{}", progress_line(&done));
    if let Some(r) = &done.stop_reason {
        println!("stopped: {r}");
    }
    if done.state != JobState::Done {
        bail!(
            "job {} ended {}{}",
            done.id,
            done.state.as_str(),
            done.error
                .as_deref()
                .map(|e| format!(": {e}"))
                .unwrap_or_default()
        );
    }
    Ok(done)
}

/// Writes the finished job's image (of `frame`, for a job of several) to `out`, EXR or
/// PNG by its extension.
fn download(client: &Client, id: u64, frame: Option<u32>, out: &Path) -> Result<()> {
    let format = if out.extension().and_then(|e| e.to_str()) == Some("exr") {
        "exr"
    } else {
        "png"
    };
    let bytes = match frame {
        Some(f) => client.frame_image(id, format, f),
        None => client.image(id, format),
    }
    .map_err(client_error)?;
    std::fs::write(out, &bytes).with_context(|| format!("writing {}", out.display()))?;
    println!("wrote {}", out.display());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_patterns_are_replaced_by_zero_padded_frame_numbers() {
        let p = Path::new("/tmp/shots/out_####.exr");
        assert_eq!(frame_path(p, 7), Path::new("/tmp/shots/out_0007.exr"));
        assert_eq!(
            frame_path(p, 123_456),
            Path::new("/tmp/shots/out_123456.exr")
        );
        // The last run of the file name only; a directory's # is not a pattern.
        let p = Path::new("/tmp/a#b/v#1_##.png");
        assert_eq!(frame_path(p, 3), Path::new("/tmp/a#b/v#1_03.png"));
        assert_eq!(frame_pattern(Path::new("/tmp/a#b/plain.exr")), None);
    }
}
