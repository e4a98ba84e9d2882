//! Rendering work units and frames: the one code path for "render a tile".
//!
//! [`render_unit`] renders passes `first_pass .. first_pass + pass_count` of one tile and
//! returns each pass's per-pixel mean, with the integrator the settings select (the
//! dispatch and the integrators' shared contract are in [`crate::integrator`]). Every
//! sample is a pure function of (scene, settings, job seed, frame, pixel, pass, sample
//! index), so a unit rendered twice, on any machine or thread, gives identical bytes.
//! [`render_frame`] runs all units of a frame on a thread pool and merges them with
//! `tessera-farm`'s canonical merge, exactly as the farm does.

use crate::scene::RenderScene;
use tessera_farm::{FrameAccumulator, FramePlan};

// The settings and the per-unit dispatch over the integrators live in `integrator`; they
// are re-exported here, where the farm's workers and the local renderer have always
// found them.
pub use crate::integrator::{render_unit, render_unit_where, RenderConfig};

/// What [`render_frame_counted`] returns.
#[derive(Debug)]
pub struct RenderedFrame {
    /// The merged frame, as [`render_frame`] returns it.
    pub accumulator: FrameAccumulator,
    /// Samples dropped as NaN, infinite or negative, summed over the frame's units (see
    /// [`tessera_farm::UnitResult::rejected_samples`]); 0 in a healthy render.
    pub rejected_samples: u64,
    /// Rays traced, closest hits and shadow rays ([`crate::scene::rays_traced`]): paths
    /// per second depends on path length, rays per second less so.
    pub rays: u64,
}

/// Renders a whole frame on `threads` threads (0 = all cores), calling `progress(done,
/// total)` after each merged unit. Units are rendered in parallel and merged as they
/// arrive: the canonical merge makes the statistics independent of arrival order.
pub fn render_frame(
    scene: &RenderScene,
    settings: &RenderConfig,
    plan: &FramePlan,
    frame: u32,
    threads: usize,
    progress: impl FnMut(usize, usize),
) -> FrameAccumulator {
    render_frame_counted(scene, settings, plan, frame, threads, progress).accumulator
}

/// [`render_frame`], also reporting how many samples the integrator rejected.
pub fn render_frame_counted(
    scene: &RenderScene,
    settings: &RenderConfig,
    plan: &FramePlan,
    frame: u32,
    threads: usize,
    mut progress: impl FnMut(usize, usize),
) -> RenderedFrame {
    let units = plan.units(frame, 1);
    let total = units.len();
    let mut acc = FrameAccumulator::for_frame(*plan, frame);
    let mut rejected_samples = 0u64;
    let mut rays = 0u64;
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("thread pool");
    let (tx, rx) = std::sync::mpsc::channel();
    pool.in_place_scope(|scope| {
        scope.spawn(move |_| {
            use rayon::prelude::*;
            units.into_par_iter().for_each_with(tx, |tx, unit| {
                // A unit renders on one thread: its counter brackets the unit's rays.
                let before = crate::scene::rays_traced();
                let result = render_unit(scene, settings, plan, unit);
                let _ = tx.send((result, crate::scene::rays_traced() - before));
            });
        });
        for (done, (result, unit_rays)) in rx.iter().enumerate() {
            rejected_samples += result.rejected_samples;
            rays += unit_rays;
            // Our own results always fit the plan; a failure here is a bug worth a panic.
            acc.offer(result).expect("locally rendered unit is valid");
            progress(done + 1, total);
        }
    });
    RenderedFrame {
        accumulator: acc,
        rejected_samples,
        rays,
    }
}
