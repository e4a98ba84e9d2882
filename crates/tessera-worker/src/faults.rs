//! Test hooks, compiled in only with the cargo feature `fault-injection` (off by default;
//! the crate doc says who turns it on).
//!
//! - `--inject-faults FRACTION` ([`crate::WorkerConfig::inject_faults`]): the worker
//!   corrupts the results of the units [`injects_fault`] selects, so that the
//!   coordinator's spot checks and quarantine can be tested end to end
//!   (docs/ARCHITECTURE.md §6, "Spot checks and quarantine").
//! - [`TEST_PANIC_SEED_VAR`]: rendering every unit of a job with that seed panics, so
//!   that the containment of a renderer's panic can be tested (no input is known to make
//!   the renderer panic).
//!
//! The rest of the crate calls them through [`Hooks`], which does nothing in a build
//! without the feature: a shipped worker reads no variable per unit.

use crate::WorkerError;
use tessera_proto::LeasedUnit;

/// Salt of the `--inject-faults` selection, independent of the spot-check selection.
#[cfg(feature = "fault-injection")]
pub const INJECT_FAULTS_SALT: u64 = 0x496e_6a46_6175_6c74; // "InjFault"

/// Whether a worker started with `--inject-faults fraction` corrupts `unit` of job `job`:
/// a hash of the unit's identity against the fraction ([`tessera_farm::unit_selected`]),
/// so the same units on every run and every worker, and a test can compute which.
#[cfg(feature = "fault-injection")]
pub fn injects_fault(fraction: f64, job: u64, unit: &tessera_farm::WorkUnit) -> bool {
    tessera_farm::unit_selected(INJECT_FAULTS_SALT, fraction, job, unit)
}

/// Set to a job seed, makes rendering every unit of jobs with that seed panic. For tests
/// of the panic containment only (no input is known to make the renderer panic); never set
/// it in production.
#[cfg(feature = "fault-injection")]
pub const TEST_PANIC_SEED_VAR: &str = "TESSERA_WORKER_TEST_PANIC_SEED";

/// Corrupts a result the way `--inject-faults` does: the lowest bit of the first traced value
/// flipped (of its absolute value, so it stays finite and non-negative): well-formed, so
/// validation accepts it, and a different digest, so a comparison does not.
#[cfg(feature = "fault-injection")]
fn corrupt(result: &mut tessera_farm::UnitResult) {
    // A traced pixel (nonzero): an untraced one of an adaptive lease is zeroed by the
    // coordinator before copies are compared, which would hide the fault.
    let first_traced = result
        .pass_means
        .iter()
        .position(|v| v[0] != 0.0)
        .unwrap_or(0);
    if let Some(v) = result.pass_means.get_mut(first_traced) {
        v[0] = f32::from_bits(v[0].abs().to_bits() ^ 1);
    }
}

/// The test hooks a worker runs with: nothing at all in a build without the feature.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Hooks {
    /// [`crate::WorkerConfig::inject_faults`], checked.
    #[cfg(feature = "fault-injection")]
    inject_faults: f64,
}

#[cfg(feature = "fault-injection")]
impl Hooks {
    /// The hooks for [`crate::WorkerConfig::inject_faults`], a fraction from 0 to 1.
    pub(crate) fn new(inject_faults: f64) -> Result<Self, WorkerError> {
        if !(0.0..=1.0).contains(&inject_faults) {
            return Err(WorkerError::Config(format!(
                "inject_faults {inject_faults} must be between 0 and 1"
            )));
        }
        Ok(Self { inject_faults })
    }

    /// Warns, once at start, that this worker corrupts results.
    pub(crate) fn announce(&self) {
        if self.inject_faults > 0.0 {
            tracing::warn!(
                fraction = self.inject_faults,
                "--inject-faults: this worker corrupts a fraction of its results (a testing aid)"
            );
        }
    }

    /// Called on the render thread, inside the panic containment, before `l` renders:
    /// panics if [`TEST_PANIC_SEED_VAR`] names the job's seed.
    pub(crate) fn before_render(&self, l: &LeasedUnit) {
        if std::env::var(TEST_PANIC_SEED_VAR).is_ok_and(|v| v == l.settings.seed.to_string()) {
            panic!("{TEST_PANIC_SEED_VAR} is {}", l.settings.seed);
        }
    }

    /// Called with the result of `l` once it rendered: corrupts it if `l` is one of the
    /// units [`injects_fault`] selects.
    pub(crate) fn after_render(&self, l: &LeasedUnit, result: &mut tessera_farm::UnitResult) {
        if injects_fault(self.inject_faults, l.job_id, &l.unit) {
            corrupt(result);
        }
    }
}

/// Without the feature: no hook, and nothing is read or changed.
#[cfg(not(feature = "fault-injection"))]
impl Hooks {
    /// No hooks: only 0 is accepted (the flag that sets another value does not exist in
    /// this build).
    pub(crate) fn new(inject_faults: f64) -> Result<Self, WorkerError> {
        if inject_faults != 0.0 {
            return Err(WorkerError::Config(format!(
                "inject_faults {inject_faults}: this build has no fault injection \
                 (tessera-worker's cargo feature `fault-injection`)"
            )));
        }
        Ok(Self {})
    }

    /// Nothing to announce.
    pub(crate) fn announce(&self) {}

    /// Nothing before rendering.
    pub(crate) fn before_render(&self, _: &LeasedUnit) {}

    /// Nothing after rendering.
    pub(crate) fn after_render(&self, _: &LeasedUnit, _: &mut tessera_farm::UnitResult) {}
}

#[cfg(all(test, feature = "fault-injection"))]
mod tests {
    use super::*;

    #[test]
    fn the_fraction_is_checked() {
        assert!(Hooks::new(0.0).is_ok());
        assert!(Hooks::new(1.0).is_ok());
        for bad in [-0.1, 1.5, f64::NAN] {
            assert!(
                matches!(Hooks::new(bad), Err(WorkerError::Config(_))),
                "{bad}"
            );
        }
    }

    #[test]
    fn a_corrupt_result_differs_in_one_bit_of_its_first_traced_value() {
        let unit = tessera_farm::WorkUnit {
            frame: 0,
            tile: 0,
            first_pass: 0,
            pass_count: 1,
        };
        let mut r = tessera_farm::UnitResult {
            unit,
            width: 3,
            height: 1,
            pass_means: vec![[0.0; 3], [0.5, 0.25, 0.125], [1.0; 3]],
            rejected_samples: 0,
            bias: None,
        };
        let before = r.clone();
        corrupt(&mut r);
        assert_eq!(r.pass_means[0], before.pass_means[0]);
        assert_eq!(r.pass_means[2], before.pass_means[2]);
        assert_eq!(r.pass_means[1][1..], before.pass_means[1][1..]);
        let (a, b) = (r.pass_means[1][0], before.pass_means[1][0]);
        assert_eq!((a.to_bits() ^ b.to_bits()), 1);
        assert!(a.is_finite() && a > 0.0);
        // Every unit at fraction 1, none at 0.
        assert!(injects_fault(1.0, 7, &unit));
        assert!(!injects_fault(0.0, 7, &unit));
    }
}
