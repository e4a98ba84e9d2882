//! Adaptive stopping end to end: `tessera render` with --target-error/--adaptive/--time-limit/
//! --spp-map, as a user runs it.

use crate::common;

use common::{read_exr, run, temp_dir};

/// Adaptive renders are bit-identical with 1 and 2 threads (ARCHITECTURE.md §2), the samples layer
/// holds the per-pixel effort, and the heat map is written.
#[test]
fn adaptive_render_is_deterministic_and_reports_its_effort() {
    let dir = temp_dir("adaptive", "det");
    for mode in ["sequential", "unbiased"] {
        let mut files = Vec::new();
        for threads in ["1", "2"] {
            let out = dir.join(format!("{mode}-{threads}.exr"));
            let map = dir.join(format!("{mode}-{threads}.png"));
            let (ok, stdout, stderr) = run(&[
                "render",
                "builtin:veach-mis",
                "--width",
                "32",
                "--height",
                "24",
                "--spp",
                "512",
                "--max-depth",
                "2",
                "--target-error",
                "0.1",
                "--adaptive",
                mode,
                "--threads",
                threads,
                "-o",
                out.to_str().unwrap(),
                "--spp-map",
                map.to_str().unwrap(),
            ]);
            assert!(ok, "{stdout}\n{stderr}");
            for needle in [
                "samples per pixel: mean",
                "min ",
                "max ",
                "seconds:",
                "estimated relative error:",
                "paths per second:",
            ] {
                assert!(stdout.contains(needle), "{needle:?} missing:\n{stdout}");
            }
            assert_eq!(&std::fs::read(&map).unwrap()[1..4], b"PNG");
            files.push(std::fs::read(&out).unwrap());
        }
        assert!(
            files[0] == files[1],
            "{mode}: EXR differs between 1 and 2 threads"
        );
        let exr = tessera_image::read_exr(&files[0]).unwrap();
        let samples = exr.get("samples.Y").unwrap();
        let passes = exr.get("passes.Y").unwrap();
        let (lo, hi) = samples
            .iter()
            .fold((f32::MAX, 0f32), |(a, b), &s| (a.min(s), b.max(s)));
        assert!(lo < hi && hi <= 512.0, "{mode}: samples {lo}..{hi}");
        // Effort is whole passes of the adaptive plan (512 spp = 32 passes of 16).
        assert!(samples.iter().all(|s| s % 16.0 == 0.0));
        if mode == "unbiased" {
            // The discarded pilot (8 passes) is effort but not part of the estimate.
            assert!(samples
                .iter()
                .zip(passes)
                .all(|(&s, &p)| s == 16.0 * (p + 8.0)));
        } else {
            assert!(samples.iter().zip(passes).all(|(&s, &p)| s == 16.0 * p));
        }
        let meta = exr.metadata.unwrap_or_default();
        assert!(meta.contains(&format!("\"adaptive\":\"{mode}\"")), "{meta}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn adaptive_flags_are_checked() {
    for (extra, needle) in [
        (vec!["--adaptive", "sequential"], "--target-error"),
        (vec!["--adaptive", "sometimes"], "sometimes"),
        (vec!["--target-error", "0"], "--target-error"),
        (vec!["--target-error", "nan"], "--target-error"),
        (vec!["--time-limit", "0"], "--time-limit"),
        (vec!["--spp-map", "map.jpg"], "--spp-map"),
        (
            vec![
                "--adaptive",
                "unbiased",
                "--target-error",
                "0.1",
                "--spp",
                "4",
            ],
            "--spp",
        ),
    ] {
        let mut args = vec!["render", "builtin:cornell-box", "-o", "x.exr"];
        args.extend(extra.iter().copied());
        let (ok, _, stderr) = run(&args);
        assert!(!ok, "{args:?} succeeded");
        assert!(!stderr.contains("panicked"), "{args:?}: {stderr}");
        assert!(
            stderr.contains(needle),
            "{args:?}: {stderr} lacks {needle:?}"
        );
    }
}

/// --time-limit and --target-error with --adaptive off stop the whole image between
/// rounds; the summary says why.
#[test]
fn off_mode_stops_at_a_target_or_time_limit() {
    let dir = temp_dir("adaptive", "off");
    let out = dir.join("t.exr");
    let (ok, stdout, stderr) = run(&[
        "render",
        "builtin:cornell-box",
        "--width",
        "16",
        "--height",
        "16",
        "--spp",
        "4096",
        "--max-depth",
        "2",
        "--target-error",
        "0.2",
        "-o",
        out.to_str().unwrap(),
    ]);
    assert!(ok, "{stdout}\n{stderr}");
    assert!(stdout.contains("stopped: target error reached"), "{stdout}");
    let exr = read_exr(&out);
    let s = exr.get("samples.Y").unwrap();
    assert!(s.iter().all(|&v| v == s[0]) && s[0] < 4096.0, "{}", s[0]);
    let (ok, stdout, stderr) = run(&[
        "render",
        "builtin:cornell-box",
        "--width",
        "16",
        "--height",
        "16",
        "--spp",
        "1048576",
        "--time-limit",
        "0.2",
        "-o",
        out.to_str().unwrap(),
    ]);
    assert!(ok, "{stdout}\n{stderr}");
    assert!(stdout.contains("stopped: time limit reached"), "{stdout}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// An adaptive render whose pixels run out of passes above the target says it
/// finished without reaching the target, in its summary and in its EXR header, instead of
/// "finished (target error 0.001)".
#[test]
fn a_target_the_budget_does_not_reach_is_not_claimed() {
    let dir = temp_dir("adaptive", "unreached");
    let out = dir.join("u.exr");
    let (ok, stdout, stderr) = run(&[
        "render",
        "builtin:cornell-box",
        "--width",
        "16",
        "--height",
        "16",
        "--spp",
        "64",
        "--adaptive",
        "unbiased",
        "--target-error",
        "0.001",
        "-o",
        out.to_str().unwrap(),
    ]);
    assert!(ok, "{stdout}\n{stderr}");
    assert!(stdout.contains("stopped: finished\n"), "{stdout}");
    assert!(
        stdout.contains("target: target error 0.001 not reached: the estimate is 0.")
            && stdout.contains(
                "when the passes its pilot planned (within the sample budget of 64 spp) were done"
            ),
        "{stdout}"
    );
    let meta = read_exr(&out).metadata.expect("EXR metadata");
    assert!(
        meta.contains(r#""stopped":"finished","target_reached":false,"error_reached":0."#),
        "{meta}"
    );
    // The same job with a target it reaches says so.
    let (ok, stdout, stderr) = run(&[
        "render",
        "builtin:cornell-box",
        "--width",
        "16",
        "--height",
        "16",
        "--spp",
        "4096",
        "--max-depth",
        "2",
        "--target-error",
        "0.2",
        "-o",
        out.to_str().unwrap(),
    ]);
    assert!(ok, "{stdout}\n{stderr}");
    assert!(
        stdout.contains("target: target error 0.2 reached (the estimate is 0."),
        "{stdout}"
    );
    let meta = read_exr(&out).metadata.expect("EXR metadata");
    assert!(
        meta.contains(r#""stopped":"target error reached","target_reached":true,"#),
        "{meta}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
