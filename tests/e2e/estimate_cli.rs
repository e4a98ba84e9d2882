//! `tessera estimate`: a quote from a short pilot. Its JSON names the job it is
//! for, honours the job's options (resolution, spp, integrator, frames, target), and its
//! prediction of the planned error covers what `tessera render` then reaches.

use crate::common;

use common::{output, output_ok, temp_dir, tessera};
use serde_json::Value;

/// `tessera estimate builtin:cornell-box --json` with a tiny frame and extra flags.
fn estimate(extra: &[&str]) -> Value {
    let out = output_ok(
        tessera()
            .args([
                "estimate",
                "builtin:cornell-box",
                "--json",
                "--threads",
                "2",
            ])
            .args(["--width", "32", "--height", "32", "--tile-size", "8"])
            .args(extra),
    );
    serde_json::from_str(&out).unwrap_or_else(|e| panic!("{e}: {out}"))
}

fn f(v: &Value) -> f64 {
    v.as_f64().unwrap_or_else(|| panic!("not a number: {v}"))
}

#[test]
fn json_names_the_job_and_quotes_every_default_target() {
    let v = estimate(&[
        "--spp",
        "64",
        "--workers",
        "2",
        "--frame-end",
        "2",
        "--spot-check-fraction",
        "0",
    ]);
    assert_eq!(v["spot_check_fraction"], 0.0);
    assert_eq!(v["width"], 32);
    assert_eq!(v["height"], 32);
    assert_eq!(v["frames"], 3);
    assert_eq!(v["spp"], 64);
    assert_eq!(v["workers"], 2);
    assert_eq!(v["integrator"], "path");
    assert_eq!(v["black"], false);
    assert_eq!(
        v["error_estimate_caveat"],
        Value::Null,
        "no caustics of a tiny light"
    );
    let q = &v["quote"];
    assert_eq!(q["pilot_passes"], 4);
    assert!(f(&q["pilot_error"]) > 0.0);
    let targets: Vec<f64> = q["targets"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| f(&t["target"]))
        .collect();
    assert_eq!(targets, [0.10, 0.05, 0.02, 0.01]);
    for cost in std::iter::once(&q["planned"])
        .chain(q["targets"].as_array().unwrap().iter().map(|t| &t["cost"]))
    {
        for field in [
            "passes",
            "spp",
            "error",
            "worker_seconds_per_frame",
            "worker_seconds",
            "seconds_per_frame",
            "seconds",
        ] {
            let i = &cost[field];
            assert!(
                f(&i["low"]) <= f(&i["estimate"]) && f(&i["estimate"]) <= f(&i["high"]),
                "{field}: {i}"
            );
        }
        // The whole job is three frames; without spot checks, and with the frame's 16
        // tiles shared evenly, wall time is worker-seconds over 2 workers.
        let per_frame = f(&cost["worker_seconds_per_frame"]["estimate"]);
        let whole = f(&cost["worker_seconds"]["estimate"]);
        assert!((whole - 3.0 * per_frame).abs() <= 1e-9 * whole.max(1.0));
        let wall = f(&cost["seconds"]["estimate"]) - f(&v["setup_seconds"]);
        assert!(
            (wall - whole / 2.0).abs() <= 1e-6 * whole.max(1.0),
            "{cost}"
        );
    }
    // Smaller errors cost more: 1/sqrt(work), so each halving of the error is 4x the passes.
    let t = q["targets"].as_array().unwrap();
    let passes = |i: usize| f(&t[i]["passes"]["estimate"]);
    assert!(passes(0) <= passes(1) && passes(1) < passes(2) && passes(2) < passes(3));
    assert!(passes(3) >= 3.0 * passes(2), "{} {}", passes(2), passes(3));
}

#[test]
fn a_target_option_and_the_job_options_are_honoured() {
    let v = estimate(&[
        "--spp",
        "256",
        "--target-error",
        "0.03",
        "--integrator",
        "direct",
    ]);
    assert_eq!(v["integrator"], "direct");
    assert_eq!(v["spp"], 256);
    // The quote counts the default farm's spot checks unless told otherwise.
    assert_eq!(v["spot_check_fraction"], 0.02);
    assert_eq!(v["frames"], 1);
    let t = v["quote"]["targets"].as_array().unwrap();
    assert_eq!(t.len(), 1);
    assert_eq!(f(&t[0]["target"]), 0.03);
    // spp is whole passes of the job's pass size (256 spp: 4 passes of 64).
    assert_eq!(v["samples_per_pass"], 64);
    let spp = f(&t[0]["cost"]["spp"]["estimate"]);
    assert_eq!(spp % 64.0, 0.0);
    assert_eq!(t[0]["within_plan"], spp <= 256.0);
    // The human form says the same.
    let text = output_ok(tessera().args([
        "estimate",
        "builtin:cornell-box",
        "--width",
        "32",
        "--height",
        "32",
        "--tile-size",
        "8",
        "--target-error",
        "0.03",
    ]));
    for needle in [
        "quote for builtin:cornell-box: 32x32, 1 frame",
        "pilot: ",
        "to reach error 0.03",
        "whole job: ",
        "2% of units spot-checked",
    ] {
        assert!(text.contains(needle), "lacks {needle:?}:\n{text}");
    }
}

/// With fixed seeds, the pilot's 4 passes predict the error of 16 passes (1024 spp):
/// `tessera render` of the same job lands within the quote's 95% interval.
#[test]
fn the_planned_error_is_predicted() {
    let v = estimate(&["--spp", "1024"]);
    assert_eq!(v["passes"], 16);
    let e = &v["quote"]["planned"]["error"];
    let dir = temp_dir("estimate", "planned");
    let out = dir.join("c.exr");
    let stdout = output_ok(
        tessera()
            .args([
                "render",
                "builtin:cornell-box",
                "--width",
                "32",
                "--height",
                "32",
            ])
            .args(["--tile-size", "8", "--spp", "1024", "-o"])
            .arg(&out),
    );
    let actual: f64 = stdout
        .lines()
        .find_map(|l| l.strip_prefix("estimated relative error: "))
        .and_then(|s| s.split_whitespace().next()?.parse().ok())
        .unwrap_or_else(|| panic!("no error line:\n{stdout}"));
    assert!(
        f(&e["low"]) <= actual && actual <= f(&e["high"]),
        "actual {actual}, predicted {e}"
    );
}

#[test]
fn bad_options_are_named() {
    for (args, needle) in [
        (vec!["--workers", "0"], "--workers"),
        (vec!["--spot-check-fraction", "2"], "--spot-check-fraction"),
        (vec!["--target-error=-1"], "target"),
        (
            vec!["--frame-start", "3", "--frame-end", "1"],
            "--frame-end",
        ),
        (vec!["--spp", "0"], "spp"),
    ] {
        let (ok, _, stderr) = output(
            tessera()
                .args([
                    "estimate",
                    "builtin:cornell-box",
                    "--width",
                    "16",
                    "--height",
                    "16",
                ])
                .args(&args),
        );
        assert!(!ok, "{args:?} accepted");
        assert!(stderr.contains(needle), "{args:?}: {stderr}");
    }
}

/// Path tracing the caustic of a tiny light: the quote says its errors may be optimistic,
/// and why (the plan's `delta-lit-caustics`); with bdpt only for the light's images in the
/// glass (`tiny-light-images`).
#[test]
fn the_quote_says_when_its_errors_may_be_optimistic() {
    let quote = |integrator: &str| {
        let out = output_ok(tessera().args([
            "estimate",
            "builtin:caustic",
            "--json",
            "--width",
            "16",
            "--height",
            "16",
            "--spp",
            "8",
            "--integrator",
            integrator,
        ]));
        serde_json::from_str::<Value>(&out).unwrap_or_else(|e| panic!("{e}: {out}"))
    };
    let path = quote("path");
    let caveat = path["error_estimate_caveat"].as_str().expect("a caveat");
    assert!(caveat.contains("sphere light"), "{caveat}");
    // bdpt finds the caustic by light tracing; what no integrator samples but from the
    // camera, the light's images in the glass (E S+ L), stays in its caveat.
    let bdpt = quote("bdpt");
    let caveat = bdpt["error_estimate_caveat"].as_str().expect("a caveat");
    assert!(caveat.contains("E S+ L"), "{caveat}");
    assert!(!caveat.contains("BSDF-sampled ray"), "{caveat}");
}
