//! `tessera bench-plan`: what the render plan buys, measured side by side in one run
//! (ARCHITECTURE.md §4).
//!
//! For each pair of configurations the same scene is rendered at the same size and sample
//! count; the time to reach a target relative error (default 5%) is predicted from the
//! measured time and the estimated image error, since error falls like `1/sqrt(work)`
//! (ARCHITECTURE.md §3, ETA): `t_target = t (error / target)²`. The pairs are
//!
//! - `builtin:caustic` with `path` and with `bdpt` (the plan's choice: a caustic lit by a
//!   small light);
//! - every built-in scene with the general configuration (`--integrator path`, max depth
//!   16) and with the plan's (`--integrator auto`).
//!
//! Ratios are printed, never asserted (tests do not assert wall time).

use crate::render::{prepare, JobArgs, StopArgs};
use anyhow::Result;
use clap::Args;
use std::time::Instant;
use tessera_render::render::render_frame;

/// Options of `tessera bench-plan`.
#[derive(Args)]
pub struct BenchPlanArgs {
    /// Image width.
    #[arg(long, default_value_t = 128)]
    width: u32,
    /// Image height.
    #[arg(long, default_value_t = 96)]
    height: u32,
    /// Samples per pixel of each measurement.
    #[arg(long, default_value_t = 64)]
    spp: u32,
    /// Target relative image error.
    #[arg(long, default_value_t = 0.05)]
    target_error: f64,
    /// Worker threads (0 = all cores).
    #[arg(long, default_value_t = 0)]
    threads: usize,
}

/// One measured configuration.
struct Measured {
    label: String,
    seconds: f64,
    error: f64,
    /// Predicted seconds to reach the target error.
    to_target: f64,
    /// The image (for region errors).
    image: Option<tessera_farm::FrameImage>,
}

/// RMS relative error over the pixels of `mask`.
fn region_error(image: &tessera_farm::FrameImage, mask: &[bool]) -> f64 {
    let (mut sum, mut n) = (0.0f64, 0usize);
    for (i, &m) in mask.iter().enumerate() {
        if m {
            let r = image.relative_error[i] as f64;
            sum += r * r;
            n += 1;
        }
    }
    (sum / n.max(1) as f64).sqrt()
}

fn lum(p: [f32; 3]) -> f32 {
    0.2126 * p[0] + 0.7152 * p[1] + 0.0722 * p[2]
}

fn measure(
    args: &BenchPlanArgs,
    scene: &str,
    integrator: &str,
    depth: Option<u32>,
) -> Result<Measured> {
    let job = JobArgs {
        spp: args.spp,
        width: Some(args.width),
        height: Some(args.height),
        integrator: integrator.into(),
        max_depth: depth,
        ..JobArgs::new(scene)
    };
    let p = prepare(&job, &StopArgs::default(), 0)?;
    let label = format!(
        "{scene} {} (max depth {}{})",
        p.resolved.config.integrator,
        p.resolved.config.max_depth,
        if integrator == "auto" {
            ", plan"
        } else {
            ", general"
        }
    );
    let Some(rs) = p.render_scene.as_ref() else {
        return Ok(Measured {
            label,
            seconds: 0.0,
            error: 0.0,
            to_target: 0.0,
            image: None,
        });
    };
    let start = Instant::now();
    let acc = render_frame(
        rs,
        &p.resolved.config,
        &p.resolved.plan,
        0,
        args.threads,
        |_, _| {},
    );
    let seconds = start.elapsed().as_secs_f64();
    let error = acc.image_error();
    let to_target = seconds * (error / args.target_error).powi(2);
    Ok(Measured {
        label,
        seconds,
        error,
        to_target,
        image: Some(acc.image()),
    })
}

fn report(a: &Measured, b: &Measured, target: f64) {
    for m in [a, b] {
        println!(
            "  {:<55} {:>8.3} s  error {:.4}  -> {:>9.3} s to {:.0}%",
            m.label,
            m.seconds,
            m.error,
            m.to_target,
            100.0 * target
        );
    }
    if b.to_target > 0.0 {
        println!(
            "  ratio (first / second) of time to {:.0}% error: {:.2}; time per sample: {:.2}",
            100.0 * target,
            a.to_target / b.to_target,
            a.seconds / b.seconds.max(1e-12)
        );
    }
}

/// Runs the comparisons and prints them.
pub fn bench_plan(args: BenchPlanArgs) -> Result<()> {
    println!(
        "bench-plan: {}x{}, {} spp per measurement, target error {}",
        args.width, args.height, args.spp, args.target_error
    );
    println!("builtin:caustic, path vs bdpt:");
    let path = measure(&args, "builtin:caustic", "path", Some(12))?;
    let bdpt = measure(&args, "builtin:caustic", "bdpt", Some(12))?;
    report(&path, &bdpt, args.target_error);
    // The caustic itself, approximated as the brightest 3% of the lower half of the bdpt
    // image (the floor, where the focused light is far brighter than direct light).
    if let (Some(a), Some(b)) = (&path.image, &bdpt.image) {
        let (w, h) = (b.width as usize, b.height as usize);
        let mut lower: Vec<f32> = (h / 2 * w..h * w).map(|i| lum(b.mean[i])).collect();
        lower.sort_by(f32::total_cmp);
        let cut = lower[lower.len() * 97 / 100];
        let mask: Vec<bool> = (0..w * h)
            .map(|i| i >= h / 2 * w && lum(b.mean[i]) >= cut)
            .collect();
        let (ea, eb) = (region_error(a, &mask), region_error(b, &mask));
        let (ta, tb) = (
            path.seconds * (ea / args.target_error).powi(2),
            bdpt.seconds * (eb / args.target_error).powi(2),
        );
        println!(
            "  caustic region ({} brightest floor pixels of the bdpt image): path error {ea:.4} -> {ta:.3} s, bdpt error {eb:.4} -> {tb:.3} s to {:.0}%; ratio {:.2}",
            mask.iter().filter(|&&m| m).count(),
            100.0 * args.target_error,
            ta / tb.max(1e-12)
        );
    }
    for scene in tessera_scene::builtin::NAMES {
        let scene = format!("builtin:{scene}");
        println!("{scene}, general configuration vs the render plan:");
        let general = measure(&args, &scene, "path", Some(16))?;
        let planned = measure(&args, &scene, "auto", None)?;
        report(&general, &planned, args.target_error);
    }
    Ok(())
}
