//! The Python clients against a real farm (a coordinator with an API token and one
//! worker): the Python client's tests (`clients/python/tests`, unittest) and the Blender
//! extension's in real Blender run headless (`clients/blender/tests`, the `bpy` module
//! 5.0.1 from PyPI in a cached virtualenv). docs/clients.md describes both clients.
//!
//! Where a machine cannot run them (no Python 3; for Blender, no Python 3.11 or no way to
//! install `bpy`), a test says so and passes; with `CI` set it fails instead. The
//! virtualenv is `$TESSERA_BPY_VENV`, else `~/.cache/tessera/bpy-5.0.1`, made once and
//! reused by later runs.

use crate::common;

use common::farm::{start_coordinator, start_worker, Coord};
use common::{temp_dir, Proc};
use std::path::{Path, PathBuf};
use std::process::Command;

/// The API token the farm of these tests requires.
const TOKEN: &str = "python-clients-token";
/// The `bpy` release the extension is tested with (Blender 5.0.1; it needs Python 3.11).
const BPY: &str = "bpy==5.0.1";

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// Passes with a message where the machine lacks what the test needs, fails under CI.
fn skip(what: &str) {
    if std::env::var_os("CI").is_some() {
        panic!("CI is set, so this test may not be skipped: {what}");
    }
    eprintln!("SKIPPED: {what}");
}

/// The output of `python -c CODE`, if that Python runs it.
fn python_says(python: &Path, code: &str) -> Option<String> {
    let o = Command::new(python).args(["-c", code]).output().ok()?;
    o.status
        .success()
        .then(|| String::from_utf8_lossy(&o.stdout).trim().to_string())
}

/// A Python 3 interpreter whose version `ok` accepts, from `PATH` or Debian's.
fn find_python(names: &[&str], ok: impl Fn(&str) -> bool) -> Option<PathBuf> {
    let mut candidates: Vec<PathBuf> = Vec::new();
    for name in names {
        if let Some(paths) = std::env::var_os("PATH") {
            candidates.extend(std::env::split_paths(&paths).map(|d| d.join(name)));
        }
        candidates.push(Path::new("/usr/bin").join(name));
    }
    candidates.into_iter().find(|p| {
        p.is_file()
            && python_says(p, "import sys; print('%d.%d' % sys.version_info[:2])")
                .is_some_and(|v| ok(&v))
    })
}

/// A farm with an API token: a coordinator and one worker of one thread.
fn farm(dir: &Path) -> (Coord, Proc) {
    let c = start_coordinator(
        &dir.join("store"),
        "127.0.0.1:0",
        "127.0.0.1:0",
        &["--api-token", TOKEN],
    );
    let w = start_worker(&c.grpc, "python-clients-worker", &[]);
    (c, w)
}

/// Runs `python -m unittest discover -v` on the test directory `tests` against the farm,
/// fails the test unless every test ran and passed, and returns its output.
fn unittest(python: &Path, tests: &Path, c: &Coord, dir: &Path) -> String {
    let scratch = dir.join("scratch");
    std::fs::create_dir_all(&scratch).unwrap();
    let o = Command::new(python)
        .args(["-m", "unittest", "discover", "-v", "-s"])
        .arg(tests)
        .current_dir(tests)
        .env("TESSERA_SERVER", &c.http)
        .env("TESSERA_API_TOKEN", TOKEN)
        .env("TESSERA_BIN", env!("CARGO_BIN_EXE_tessera"))
        .env("TESSERA_TEST_DIR", &scratch)
        // Blender's user files (the extension installed from its zip) stay in the test's
        // directory, not the home directory's.
        .env("BLENDER_USER_RESOURCES", dir.join("blender-user"))
        .env_remove("PYTHONPATH")
        .output()
        .unwrap_or_else(|e| panic!("{}: {e}", python.display()));
    let out = format!(
        "{}\n{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    // The scripts' measurements (round trip, quote) for the test log.
    for line in out.lines().filter(|l| !l.contains("| INFO")) {
        println!("[python] {line}");
    }
    assert!(o.status.success(), "python tests failed:\n{out}");
    assert!(
        !out.contains("(skipped="),
        "a Python test was skipped against a running farm:\n{out}"
    );
    out
}

#[test]
fn the_python_client_against_a_real_farm() {
    let Some(python) = find_python(&["python3"], |v| {
        v.split_once('.')
            .and_then(|(a, b)| Some((a.parse::<u32>().ok()?, b.parse::<u32>().ok()?)))
            .is_some_and(|(a, b)| a == 3 && b >= 9)
    }) else {
        return skip("the Python client's tests need Python 3.9 or newer (python3)");
    };
    let dir = temp_dir("python-clients", "client");
    let (c, _w) = farm(&dir);
    let out = unittest(&python, &repo().join("clients/python/tests"), &c, &dir);
    // unittest -v prints `NAME (MODULE.CLASS.NAME) ... ok` for each test that passed.
    assert!(
        out.lines().any(|l| l
            .starts_with("test_content_addressed_submit_wait_and_frames_equal_tessera_render ")
            && l.ends_with("... ok")),
        "{out}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// The virtualenv's Python with `bpy` installed: made (and `bpy` installed from PyPI)
/// on first use, reused afterwards. Errors say what is missing.
fn bpy_python() -> Result<PathBuf, String> {
    let venv = match std::env::var_os("TESSERA_BPY_VENV") {
        Some(v) => PathBuf::from(v),
        None => {
            let home = std::env::var_os("HOME").ok_or("HOME is not set")?;
            PathBuf::from(home).join(".cache/tessera/bpy-5.0.1")
        }
    };
    let python = venv.join("bin/python");
    let has_bpy = |p: &Path| python_says(p, "import bpy; print(bpy.app.version_string)");
    if let Some(v) = has_bpy(&python) {
        println!("bpy {v} in {}", venv.display());
        return Ok(python);
    }
    let base = find_python(&["python3.11", "python3"], |v| v == "3.11")
        .ok_or("bpy 5.0.1 needs Python 3.11 (python3.11 or a python3 of that version)")?;
    // Built beside the final place and renamed into it, so that an interrupted install
    // is never taken for a finished one.
    let partial = venv.with_extension(format!("partial-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&partial);
    std::fs::create_dir_all(partial.parent().unwrap()).map_err(|e| e.to_string())?;
    let run = |cmd: &mut Command, what: &str| -> Result<(), String> {
        let o = cmd.output().map_err(|e| format!("{what}: {e}"))?;
        if o.status.success() {
            Ok(())
        } else {
            Err(format!(
                "{what} failed: {}{}",
                String::from_utf8_lossy(&o.stdout),
                String::from_utf8_lossy(&o.stderr)
            ))
        }
    };
    run(
        Command::new(&base).args(["-m", "venv"]).arg(&partial),
        "python3.11 -m venv (Debian: apt-get install python3-venv)",
    )?;
    println!("installing {BPY} into {} (once)", venv.display());
    // `timeout` bounds a stalled download; the wheel is about 350 MB.
    let installed = run(
        Command::new("timeout")
            .arg("900")
            .arg(partial.join("bin/python"))
            .args([
                "-m",
                "pip",
                "install",
                "--quiet",
                "--disable-pip-version-check",
                BPY,
            ]),
        &format!("pip install {BPY}"),
    );
    if let Err(e) = installed {
        let _ = std::fs::remove_dir_all(&partial);
        return Err(e);
    }
    // A concurrent run may have finished first: then its virtualenv is used.
    if std::fs::rename(&partial, &venv).is_err() {
        let _ = std::fs::remove_dir_all(&partial);
    }
    has_bpy(&python)
        .map(|_| python.clone())
        .ok_or_else(|| format!("{} cannot import bpy after installing it", python.display()))
}

#[test]
fn the_blender_extension_in_headless_blender_against_a_real_farm() {
    let python = match bpy_python() {
        Ok(p) => p,
        Err(e) => return skip(&format!("the Blender extension's tests need bpy: {e}")),
    };
    let dir = temp_dir("python-clients", "blender");
    let (c, _w) = farm(&dir);
    let out = unittest(&python, &repo().join("clients/blender/tests"), &c, &dir);
    // Three frames from the operator, each byte-identical to `tessera render` of the
    // exported glTF; the zip validated by Blender's validator.
    for needle in [
        "test_three_frames_round_trip_byte_identical_to_tessera_render",
        "ROUNDTRIP frame 3",
        "test_quote_fills_the_panel_and_queues_nothing",
        "test_wrong_token_and_unreachable_server_are_messages_not_tracebacks",
        "VALIDATE ",
    ] {
        assert!(out.contains(needle), "no {needle:?} in:\n{out}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}
