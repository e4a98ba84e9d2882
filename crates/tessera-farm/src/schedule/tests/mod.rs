//! The scheduler's tests, one file per concern of `schedule/`, with the helpers they share.

mod adaptive;
mod lease;
mod memory;
mod resume;
mod spot;

use super::{Lease, Scheduler};
use crate::ids::JobId;
use crate::plan::{FramePlan, WorkUnit};
use crate::result::UnitResult;

/// One step of Knuth's MMIX linear congruential generator: the fixed pseudo-random
/// delivery order of the scheduler's property tests.
fn lcg_step(rng: &mut u64) {
    *rng = rng
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
}

fn result(plan: &FramePlan, unit: WorkUnit, value: f32) -> UnitResult {
    let rect = plan.tile(unit.tile);
    let n = rect.pixel_count() * unit.pass_count as usize;
    let pass_means = (0..n).map(|k| [value + (k % 7) as f32 * 0.01; 3]).collect();
    UnitResult {
        unit,
        width: rect.width,
        height: rect.height,
        pass_means,
        rejected_samples: 0,
        bias: None,
    }
}

fn plan() -> FramePlan {
    FramePlan::new(40, 30, 16, 4, 6).unwrap() // 6 tiles, 6 passes
}

/// A reproducible noisy pass mean: tile 0 is constant (converges at once), the others
/// noisy with occasional fireflies (some pixels converge, some never do).
fn noisy_result(plan: &FramePlan, unit: WorkUnit) -> UnitResult {
    let rect = plan.tile(unit.tile);
    let mut pass_means = Vec::new();
    for pass in unit.first_pass..unit.first_pass + unit.pass_count {
        for i in 0..rect.pixel_count() {
            let mut rng = crate::test_util::Rng::new(
                (u64::from(unit.tile) << 40) ^ (u64::from(pass) << 20) ^ i as u64,
            );
            let v = if unit.tile == 0 {
                0.5
            } else {
                let firefly = if rng.uniform() < 0.02 * (i % 4) as f64 {
                    40.0
                } else {
                    0.0
                };
                0.3 + 0.5 * rng.uniform() + firefly
            };
            pass_means.push([v as f32; 3]);
        }
    }
    UnitResult {
        unit,
        width: rect.width,
        height: rect.height,
        pass_means,
        rejected_samples: 0,
        bias: None,
    }
}

/// One delivery of a randomly interleaved farm: a lease of `held` chosen by `rng`
/// delivers its [`noisy_result`], except one in `odds.0` whose result is lost (its
/// unit is leased again after expiry); after one delivery in `odds.1`, and whenever
/// nothing is held, the outstanding leases lapse. Returns whether a result was
/// submitted.
fn deliver_random(
    s: &mut Scheduler,
    job: JobId,
    plan: &FramePlan,
    held: &mut Vec<Lease>,
    rng: &mut u64,
    now: u64,
    odds: (u64, u64),
) -> bool {
    lcg_step(rng);
    if held.is_empty() {
        s.expire(now + 1000);
        return false;
    }
    let k = (*rng >> 33) as usize % held.len();
    let l = held.swap_remove(k);
    if rng.is_multiple_of(odds.0) {
        return false;
    }
    let _ = s.submit(l.lease_id, job, noisy_result(plan, l.unit));
    if rng.is_multiple_of(odds.1) {
        s.expire(now + 1000);
    }
    true
}
