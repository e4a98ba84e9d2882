//! Measurement (ignored by default) behind the "Light hierarchy" section of
//! docs/benchmarks.md: noise variance and time of the path tracer at equal samples per
//! pixel on `builtin:veach-mis` and `builtin:cornell-box`.
//!
//! Noise variance: the scene is rendered twice with seeds 1 and 2; per pixel and channel,
//! `Var = (a - b)^2 / 2` estimates the variance of one render's pixel value. It is averaged
//! over the pixels and channels, leaving out pixels that see an emitter directly (their
//! variance is that of emission, not of light sampling). Efficiency is `1 / (Var x seconds)`
//! with the process CPU seconds of the render (one render thread), which other processes
//! on a shared machine disturb less than the wall clock.
//!
//! Run with `cargo test -p tessera-render --test light_bench -- --ignored --nocapture`.

use std::time::Instant;
use tessera_farm::FramePlan;
use tessera_render::geometry::NO_LIGHT;
use tessera_render::render::{render_frame, RenderConfig};
use tessera_render::scene::RenderScene;

const W: u32 = 256;
const H: u32 = 256;
const SPP: u32 = 64;
const THREADS: usize = 1;

/// CPU seconds (user + system) this process has used, from `/proc/self/stat` (Linux; in
/// clock ticks of 1/100 s).
fn cpu_seconds() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").expect("/proc/self/stat");
    // Fields after the parenthesised command name; utime and stime are fields 14 and 15.
    let rest = &stat[stat.rfind(')').expect("comm") + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks: f64 = f[11].parse::<f64>().unwrap() + f[12].parse::<f64>().unwrap();
    ticks / 100.0
}

/// Pixels whose primary rays (centre and four inner points) hit an emitter.
fn emitter_pixels(rs: &RenderScene) -> Vec<bool> {
    let mut mask = vec![false; (W * H) as usize];
    for y in 0..H {
        for x in 0..W {
            for (dx, dy) in [(0.5, 0.5), (0.1, 0.1), (0.9, 0.1), (0.1, 0.9), (0.9, 0.9)] {
                let film = glam::Vec2::new(x as f32 + dx, y as f32 + dy);
                let (o, d) = rs.camera.generate_ray(film, glam::Vec2::splat(0.5));
                if let Some(hit) = rs.intersect(o, d, f32::INFINITY) {
                    if rs.surface(&hit, o, d).light != NO_LIGHT {
                        mask[(y * W + x) as usize] = true;
                    }
                }
            }
        }
    }
    mask
}

#[test]
#[ignore = "measurement: minutes of rendering"]
fn light_sampling_efficiency() {
    for name in ["builtin:veach-mis", "builtin:cornell-box"] {
        let scene = tessera_scene::load(name).unwrap();
        let rs = RenderScene::build(&scene, W, H).unwrap();
        let mask = emitter_pixels(&rs);
        let plan = FramePlan::for_spp(W, H, SPP, 16).unwrap();
        let mut images = Vec::new();
        let mut seconds = 0.0;
        let mut cpu = 0.0;
        for seed in [1u64, 2] {
            let cfg = RenderConfig {
                seed,
                ..RenderConfig::default()
            };
            let t = Instant::now();
            let c = cpu_seconds();
            let acc = render_frame(&rs, &cfg, &plan, 0, THREADS, |_, _| {});
            seconds += t.elapsed().as_secs_f64();
            cpu += cpu_seconds() - c;
            images.push(acc.image().mean);
        }
        let (mut sum, mut n) = (0.0f64, 0usize);
        for (i, (a, b)) in images[0].iter().zip(&images[1]).enumerate() {
            if mask[i] {
                continue;
            }
            for c in 0..3 {
                let d = a[c] as f64 - b[c] as f64;
                sum += d * d / 2.0;
                n += 1;
            }
        }
        let var = sum / n as f64;
        let (wall, cpu) = (seconds / 2.0, cpu / 2.0);
        println!(
            "{name}: {W}x{H} {SPP} spp, {THREADS} thread(s): variance {var:.6e} over {} pixels, {cpu:.2} CPU s ({wall:.2} s wall) per render, efficiency 1/(var CPU s) {:.4e}",
            n / 3,
            1.0 / (var * cpu)
        );
    }
}
