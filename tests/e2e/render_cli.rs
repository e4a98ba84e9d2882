//! End-to-end tests of `tessera render` as a user runs it: real process, real files.

use crate::common;

use std::path::Path;

use common::{output, output_ok, temp_dir, tessera};

fn render(out: &Path, extra: &[&str]) -> String {
    output_ok(
        tessera()
            .args([
                "render",
                "builtin:cornell-box",
                "--width",
                "64",
                "--height",
                "48",
                "--spp",
                "16",
                "-o",
            ])
            .arg(out)
            .args(extra),
    )
}

#[test]
fn exr_is_bit_identical_for_any_thread_count_and_across_runs() {
    let dir = temp_dir("cli", "determinism");
    let mut files = Vec::new();
    for (i, threads) in ["1", "2", "8", "2"].iter().enumerate() {
        let out = dir.join(format!("run{i}.exr"));
        render(&out, &["--threads", threads, "--seed", "3"]);
        files.push(std::fs::read(&out).unwrap());
    }
    for f in &files[1..] {
        assert!(f == &files[0], "EXR bytes differ between runs");
    }
    // The layers are there and the beauty is plausible.
    let exr = tessera_image::read_exr(&files[0]).unwrap();
    assert_eq!((exr.width, exr.height), (64, 48));
    for name in [
        "R",
        "G",
        "B",
        "variance.R",
        "variance.G",
        "variance.B",
        "pooled_variance.R",
        "pooled_variance.G",
        "pooled_variance.B",
        "relerr.Y",
        "passes.Y",
        "samples.Y",
    ] {
        let c = exr.get(name).unwrap();
        assert!(c.iter().all(|v| v.is_finite() && *v >= 0.0), "{name}");
    }
    assert!(exr.get("samples.Y").unwrap().iter().all(|&s| s == 16.0));
    // The settings travel in the header.
    let meta = exr.metadata.clone().unwrap_or_default();
    assert!(
        meta.contains("\"seed\":3") && meta.contains("\"integrator\":\"path\""),
        "{meta}"
    );
    let mean_r: f32 = exr.get("R").unwrap().iter().sum::<f32>() / (64.0 * 48.0);
    assert!(mean_r > 0.05 && mean_r < 2.0, "mean red {mean_r}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn png_output_and_summary() {
    let dir = temp_dir("cli", "png");
    let out = dir.join("cornell.png");
    let stdout = render(&out, &[]);
    let bytes = std::fs::read(&out).unwrap();
    assert_eq!(&bytes[1..4], b"PNG");
    for needle in [
        "samples per pixel: 16",
        "seconds:",
        "estimated relative error:",
        "paths per second:",
    ] {
        assert!(
            stdout.contains(needle),
            "summary lacks {needle:?}:\n{stdout}"
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn bad_arguments_are_reported_not_panicked() {
    let dir = temp_dir("cli", "bad");
    for (args, needle) in [
        (
            vec!["render", "builtin:nope", "-o", "x.exr"],
            "unknown scene",
        ),
        (
            vec!["render", "builtin:cornell-box", "-o", "x.tiff"],
            ".exr or .png",
        ),
        (
            vec!["render", "builtin:cornell-box", "-o", "x.exr", "--spp", "0"],
            "--spp",
        ),
        (
            vec![
                "render",
                "builtin:cornell-box",
                "-o",
                "x.exr",
                "--width",
                "0",
                "--height",
                "5",
            ],
            "invalid",
        ),
        (
            vec!["render", "missing.gltf", "-o", "x.exr"],
            "missing.gltf",
        ),
        (
            vec![
                "render",
                "builtin:cornell-box",
                "-o",
                "x.exr",
                "--mis",
                "nope",
            ],
            "MIS",
        ),
    ] {
        let (ok, _, stderr) = output(tessera().current_dir(&dir).args(&args));
        assert!(!ok, "{args:?} succeeded");
        assert!(!stderr.contains("panicked"), "{args:?} panicked: {stderr}");
        assert!(
            stderr.contains(needle),
            "{args:?}: {stderr} lacks {needle:?}"
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_traversal_kernel_the_cpu_lacks_or_an_unknown_one_is_refused() {
    let dir = temp_dir("cli", "isa");
    let out = dir.join("x.exr");
    let (ok, _, err) = output(
        tessera()
            .env("TESSERA_ISA", "avx1024")
            .args(["render", "builtin:cornell-box", "--spp", "1", "-o"])
            .arg(&out),
    );
    assert!(!ok);
    assert!(err.contains("TESSERA_ISA=avx1024: unknown"), "{err}");
    assert!(!out.exists());
    // The scalar kernel exists on every CPU, and gives the same image as the default.
    let (a, b) = (dir.join("a.exr"), dir.join("b.exr"));
    render(&a, &[]);
    output_ok(
        tessera()
            .env("TESSERA_ISA", "scalar")
            .args([
                "render",
                "builtin:cornell-box",
                "--width",
                "64",
                "--height",
                "48",
                "--spp",
                "16",
                "-o",
            ])
            .arg(&b),
    );
    assert_eq!(std::fs::read(&a).unwrap(), std::fs::read(&b).unwrap());
}
