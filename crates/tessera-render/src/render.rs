//! Rendering work units: the one code path for "render a tile".
//!
//! [`render_unit`] renders passes `first_pass .. first_pass + pass_count` of one tile and
//! returns each pass's per-pixel mean. Every sample is a pure function of (scene, settings,
//! job seed, frame, pixel, pass, sample index) — DESIGN §2 — so a unit rendered twice, on
//! any machine or thread, gives identical bytes. [`render_frame`] runs all units of a frame
//! on a thread pool and merges them with `tessera-farm`'s canonical merge, exactly as the
//! farm does.

use crate::integrator::path::{radiance, PathSettings};
use crate::integrator::IntegratorKind;
use crate::sampling::PixelSampler;
use crate::scene::RenderScene;
use glam::Vec2;
use tessera_farm::{FrameAccumulator, FramePlan, UnitResult, WorkUnit};

/// Everything that decides the value of a sample, besides the scene and the plan: the job
/// contract's resolved [`RenderConfig`](tessera_farm::job::RenderConfig).
pub use tessera_farm::job::RenderConfig as RenderSettings;

/// Renders one work unit. The caller guarantees that `unit` belongs to `plan` and that
/// `scene` was built for the plan's image size.
pub fn render_unit(
    scene: &RenderScene,
    settings: &RenderSettings,
    plan: &FramePlan,
    unit: WorkUnit,
) -> UnitResult {
    render_unit_where(scene, settings, plan, unit, |_, _| true)
}

/// [`render_unit`] for only the (tile pixel, pass) pairs where `wanted(i, pass)` holds
/// (`i` row-major within the tile); the others are left black without tracing a ray.
/// Adaptive rendering (`tessera_farm::AdaptiveTile::wants`) uses it to skip pixels that
/// stopped: a wanted pixel's value is the same as with [`render_unit`], and the policy
/// ignores the others, so the image is the same as when whole tiles are rendered.
///
/// Bidirectional path tracing renders every pixel: its light-tracing splats land
/// anywhere in the (whole-frame) tile, so skipping pixels would not save their cost.
pub fn render_unit_where(
    scene: &RenderScene,
    settings: &RenderSettings,
    plan: &FramePlan,
    unit: WorkUnit,
    wanted: impl Fn(usize, u32) -> bool,
) -> UnitResult {
    if settings.integrator == IntegratorKind::Bdpt {
        // Light tracing splats across pixels: see `integrator::bdpt` for how a unit stays
        // deterministic (and why bdpt plans use one whole-frame tile).
        return crate::integrator::bdpt::render_unit(scene, settings, plan, unit);
    }
    let rect = plan.tile(unit.tile);
    let pixels = (rect.width * rect.height) as usize;
    let spp = plan.samples_per_pass;
    let path = PathSettings {
        kind: settings.integrator,
        mis: settings.mis,
        max_depth: settings.max_depth,
        rr_depth: settings.rr_depth,
    };
    let lens = scene.camera.has_lens();
    let mut pass_means = Vec::with_capacity(pixels * unit.pass_count as usize);
    for pass in unit.first_pass..unit.first_pass + unit.pass_count {
        for y in rect.y0..rect.y0 + rect.height {
            for x in rect.x0..rect.x0 + rect.width {
                let pixel = y * plan.width + x;
                if !wanted(((y - rect.y0) * rect.width + (x - rect.x0)) as usize, pass) {
                    pass_means.push([0.0; 3]);
                    continue;
                }
                let mut sampler =
                    PixelSampler::new(settings.sampler, settings.seed, unit.frame, pixel, pass);
                let mut sum = [0.0f64; 3];
                for i in 0..spp {
                    sampler.start_sample(i);
                    // Box reconstruction: the sample stays inside its pixel, so tiles are
                    // independent.
                    let film = Vec2::new(x as f32, y as f32) + sampler.next_2d();
                    let lens_u = if lens { sampler.next_2d() } else { Vec2::ZERO };
                    let (o, d) = scene.camera.generate_ray(film, lens_u);
                    let l = radiance(scene, &path, o, d, &mut sampler);
                    // A non-finite sample would poison the pixel: it is a bug, not light.
                    if l.is_finite() && l.min_element() >= 0.0 {
                        sum[0] += l.x as f64;
                        sum[1] += l.y as f64;
                        sum[2] += l.z as f64;
                    }
                }
                let inv = 1.0 / spp as f64;
                pass_means.push([
                    (sum[0] * inv) as f32,
                    (sum[1] * inv) as f32,
                    (sum[2] * inv) as f32,
                ]);
            }
        }
    }
    UnitResult {
        unit,
        width: rect.width,
        height: rect.height,
        pass_means,
    }
}

/// Renders a whole frame on `threads` threads (0 = all cores), calling `progress(done,
/// total)` after each merged unit. Units are rendered in parallel and merged as they
/// arrive: the canonical merge makes the statistics independent of arrival order.
pub fn render_frame(
    scene: &RenderScene,
    settings: &RenderSettings,
    plan: &FramePlan,
    frame: u32,
    threads: usize,
    mut progress: impl FnMut(usize, usize),
) -> FrameAccumulator {
    let units = plan.units(frame, 1);
    let total = units.len();
    let mut acc = FrameAccumulator::new(*plan);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("thread pool");
    let (tx, rx) = std::sync::mpsc::channel();
    pool.in_place_scope(|scope| {
        scope.spawn(move |_| {
            use rayon::prelude::*;
            units.into_par_iter().for_each_with(tx, |tx, unit| {
                let _ = tx.send(render_unit(scene, settings, plan, unit));
            });
        });
        for (done, result) in rx.iter().enumerate() {
            // Our own results always fit the plan; a failure here is a bug worth a panic.
            acc.offer(result).expect("locally rendered unit is valid");
            progress(done + 1, total);
        }
    });
    acc
}
