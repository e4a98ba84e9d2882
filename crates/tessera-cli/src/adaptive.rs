//! `tessera render` with error targets, adaptive stopping and time limits:
//! `--target-error`, `--adaptive off|sequential|unbiased`, `--time-limit`, `--spp-map`.
//!
//! The render runs `tessera-farm`'s adaptive policy round by round through
//! [`tessera_render::adaptive::render_adaptive`]; `--spp` is the upper bound.

use crate::render::{Prepared, RenderArgs};
use anyhow::{bail, Context, Result};
use std::io::IsTerminal;
use std::path::Path;
use tessera_farm::job::StopVerdict;
use tessera_farm::{AdaptiveFrame, AdaptiveMode, AdaptiveSettings, FrameImage};
use tessera_render::adaptive::{render_adaptive, Limits, StopReason};

/// Checks that `path`, given to `flag`, names a PNG file.
pub fn check_png(flag: &str, path: &Path) -> Result<()> {
    let ok = path
        .extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case("png"));
    if !ok {
        bail!("{flag} {} must end in .png", path.display());
    }
    Ok(())
}

/// Writes the samples-per-pixel heat map of an image.
pub fn write_spp_map(path: &Path, img: &FrameImage) -> Result<()> {
    let png = tessera_image::encode_heat_map_png(img.width, img.height, &img.samples)?;
    std::fs::write(path, png).with_context(|| format!("writing --spp-map {}", path.display()))
}

/// Renders with the adaptive round loop and prints the summary.
pub fn render(p: &Prepared, args: &RenderArgs) -> Result<()> {
    let job = &p.resolved.job;
    let plan = p.resolved.plan;
    // Without an adaptive mode the policy only measures the whole image's error between
    // rounds, for --target-error and --time-limit.
    // The resolved job's settings: no pixel stops early where a light path class is
    // unsampled.
    let settings = p.resolved.adaptive_settings().unwrap_or(AdaptiveSettings {
        mode: AdaptiveMode::Off,
        target_error: job.target_error.unwrap_or(1.0),
        min_passes: job.min_passes,
        ..AdaptiveSettings::default()
    });
    // Resolution checked the settings against the plan; this cannot fail.
    let frame = AdaptiveFrame::new(plan, p.frame, settings).with_context(|| {
        format!(
            "--adaptive {} with --spp {} ({} passes of {})",
            job.adaptive, job.spp, plan.passes, plan.samples_per_pass
        )
    })?;
    let Some(render_scene) = p.render_scene.as_ref() else {
        bail!("internal: no render scene for a non-black render");
    };
    let bar = std::io::stderr().is_terminal().then(|| {
        let bar = indicatif::ProgressBar::new_spinner();
        bar.set_style(
            indicatif::ProgressStyle::with_template("{elapsed_precise} {spinner} {msg}")
                .expect("static template"),
        );
        bar
    });
    let limits = Limits {
        time_limit_seconds: job.time_limit_seconds,
        target_error: job.target_error,
    };
    let out = render_adaptive(
        render_scene,
        &p.resolved.config,
        frame,
        args.threads,
        limits,
        |f| {
            if let Some(b) = &bar {
                let (mean, _, _) = f.samples_per_pixel();
                let active: usize = f.tiles().iter().map(|t| t.active_pixels()).sum();
                b.set_message(format!(
                    "{mean:.1} spp, estimated error {:.4}, {active} pixels active",
                    f.image_error()
                ));
                b.tick();
            }
        },
    );
    if let Some(b) = bar {
        b.finish_and_clear();
    }
    let image = out.frame.image();
    let verdict = StopVerdict::of_image(&p.resolved, &image, out.stop == StopReason::TimeLimit);
    let meta = p.resolved.metadata_json(Some(&verdict));
    tessera_image::write_image(&args.output, &image, Some(&meta))?;
    if let Some(path) = &args.spp_map {
        write_spp_map(path, &image)?;
    }
    let (mean, lo, hi) = out.frame.samples_per_pixel();
    println!(
        "rendered {} ({}x{}, {} integrator, {} sampler, {} MIS, adaptive {}) to {}",
        p.scene.name,
        plan.width,
        plan.height,
        p.resolved.config.integrator,
        p.resolved.config.sampler,
        p.resolved.config.mis,
        job.adaptive,
        args.output.display()
    );
    println!(
        "samples per pixel: mean {mean:.1}, min {lo}, max {hi} (budget {} = {} passes of {})",
        plan.spp(),
        plan.passes,
        plan.samples_per_pass
    );
    // From the written image's own estimate: never a target it did not reach.
    println!("stopped: {}", verdict.stopped());
    if let Some(target) = verdict.describe() {
        println!("target: {target}");
    }
    println!("seconds: {:.3}", out.seconds);
    println!(
        "estimated relative error: {:.4} (estimator: {})",
        out.frame.image_error(),
        p.resolved.error_estimator_name()
    );
    crate::render::print_caveat(&p.resolved);
    println!(
        "paths per second: {:.0}",
        out.paths as f64 / out.seconds.max(1e-9)
    );
    crate::render::print_rejected_samples(out.rejected_samples);
    Ok(())
}
