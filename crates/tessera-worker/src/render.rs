//! Rendering a batch of leased units on the worker's thread pool, each unit on one
//! thread, with a renderer's panic contained to its unit.

use crate::faults::Hooks;
use crate::pipeline::Leases;
use rayon::prelude::*;
use std::sync::Arc;
use std::time::Instant;
use tessera_proto::LeasedUnit;
use tessera_render::render::{render_unit, render_unit_where};
use tessera_render::scene::RenderScene;

/// Leased units whose scenes are loaded and built, ready to render.
#[derive(Default)]
pub(crate) struct Batch {
    /// Each lease with its built scene.
    pub(crate) units: Vec<(LeasedUnit, Arc<RenderScene>)>,
}

impl Batch {
    /// The batch's lease ids, in order.
    pub(crate) fn lease_ids(&self) -> impl Iterator<Item = u64> + '_ {
        self.units.iter().map(|(l, _)| l.lease_id)
    }
}

impl Leases for Batch {
    fn lease_ids(&self) -> Vec<u64> {
        Batch::lease_ids(self).collect()
    }

    fn retain_leases(&mut self, mut keep: impl FnMut(u64) -> bool) {
        self.units.retain(|(l, _)| keep(l.lease_id));
    }

    fn is_empty(&self) -> bool {
        self.units.is_empty()
    }
}

/// One unit's outcome on the pool.
pub(crate) struct Outcome {
    /// The unit's lease.
    pub(crate) lease_id: u64,
    /// The unit's job.
    pub(crate) job_id: u64,
    /// The lease's seal.
    pub(crate) fence: Vec<u8>,
    /// The result, or the message of the renderer's panic.
    pub(crate) result: Result<tessera_farm::UnitResult, String>,
    /// Seconds it took on its thread.
    pub(crate) seconds: f64,
    /// Camera paths traced (0 if it panicked).
    pub(crate) paths: f64,
    /// Pixel-passes traced (0 if it panicked).
    pub(crate) pixel_passes: u64,
}

/// A batch rendering on the pool.
pub(crate) struct Rendering {
    /// The blocking task rendering it: the outcomes in the batch's order.
    pub(crate) task: tokio::task::JoinHandle<Vec<Outcome>>,
    /// When it started (the batch's wall time gives the worker's paths per second).
    pub(crate) started: Instant,
}

impl Rendering {
    /// Renders every unit of `batch` on the pool, on a blocking thread (never on the
    /// async runtime), with the test `hooks` around each unit.
    pub(crate) fn start(pool: &Arc<rayon::ThreadPool>, batch: Batch, hooks: Hooks) -> Self {
        let pool = pool.clone();
        let task = tokio::task::spawn_blocking(move || {
            pool.install(|| {
                batch
                    .units
                    .par_iter()
                    .map(|(l, rs)| {
                        let t = Instant::now();
                        let (mut result, pixel_passes) = match render_contained(rs, l, hooks) {
                            Ok((r, n)) => (Ok(r), n),
                            Err(e) => (Err(e), 0),
                        };
                        if let Ok(r) = &mut result {
                            hooks.after_render(l, r);
                        }
                        Outcome {
                            lease_id: l.lease_id,
                            job_id: l.job_id,
                            fence: l.fence.clone(),
                            result,
                            seconds: t.elapsed().as_secs_f64(),
                            // Only the pixels traced count towards the throughput.
                            paths: pixel_passes as f64 * f64::from(l.plan.samples_per_pass),
                            pixel_passes,
                        }
                    })
                    .collect()
            })
        });
        Self {
            task,
            started: Instant::now(),
        }
    }
}

/// Renders one leased unit, turning a panic of the renderer into `Err(message)`, so one
/// unit cannot end the worker's session (a panic would otherwise unwind through the rayon
/// pool into the blocking task and break the connection, and the unit would be leased
/// again forever). Also returns the pixel-passes traced.
///
/// Only the lease's wanted pixels are traced (an adaptive job's lease names them); the
/// others are left black, which keeps the result's size, and the coordinator's adaptive
/// policy never reads them. The set was validated against the tile when the lease was
/// decoded.
fn render_contained(
    rs: &RenderScene,
    l: &LeasedUnit,
    hooks: Hooks,
) -> Result<(tessera_farm::UnitResult, u64), String> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        hooks.before_render(l);
        let pixels = l.plan.tile(l.unit.tile).pixel_count() as u64;
        let all = pixels * u64::from(l.unit.pass_count);
        let Some(wanted) = &l.wanted else {
            return (render_unit(rs, &l.settings, &l.plan, l.unit), all);
        };
        // Counted where the renderer asks, so the figure is what was traced. The per-pixel
        // test is a binary search over the runs: nothing is allocated per pixel.
        let traced = std::cell::Cell::new(0u64);
        let result = render_unit_where(rs, &l.settings, &l.plan, l.unit, |i, _| {
            let yes = wanted.contains(i);
            traced.set(traced.get() + u64::from(yes));
            yes
        });
        // bdpt asks too: it traces camera subpaths for the wanted pixels only (the light
        // subpaths of every pixel still run, since their splats land anywhere).
        (result, traced.get())
    }))
    .map_err(|payload| panic_message(payload.as_ref()))
}

/// The message of a panic payload (`panic!` with a literal or a formatted string).
fn panic_message(payload: &(dyn std::any::Any + Send)) -> String {
    if let Some(s) = payload.downcast_ref::<&str>() {
        (*s).to_string()
    } else if let Some(s) = payload.downcast_ref::<String>() {
        s.clone()
    } else {
        "a panic without a message".to_string()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_panic_message_is_kept_whatever_its_payload() {
        let caught = |f: fn()| std::panic::catch_unwind(f).unwrap_err();
        // The panics print their messages: the panic hook is the process's, not this
        // test's, to change.
        let literal = caught(|| panic!("a literal"));
        let formatted = caught(|| panic!("formatted {}", 42));
        let other = caught(|| std::panic::panic_any(7u8));
        assert_eq!(panic_message(literal.as_ref()), "a literal");
        assert_eq!(panic_message(formatted.as_ref()), "formatted 42");
        assert_eq!(panic_message(other.as_ref()), "a panic without a message");
    }
}
