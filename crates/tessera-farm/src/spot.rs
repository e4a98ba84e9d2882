//! Spot checks (ARCHITECTURE.md §6, "Spot checks and quarantine"): which units are
//! rendered twice on purpose, and what the scheduler reports when their copies are
//! compared.
//!
//! Rendering is deterministic (ARCHITECTURE.md §2), so two workers' copies of one unit are
//! bit-identical and any difference is a fault. A fraction of the units is chosen by
//! [`is_spot_checked`], a hash of the unit's identity (job, frame, tile, first pass)
//! compared with the fraction: no random state, so a restarted coordinator checks the same
//! units, and the choice is independent of who renders what.
//!
//! The scheduler holds a spot-checked unit's first copy unmerged and leases the unit again
//! to a different worker; the copies are compared by digest and the unit merged only once
//! two copies agree (the merged bytes are then the ones every honest worker renders, so the
//! image stays byte-identical to a local render even when a faulty copy came first).
//! Workers whose copy differs from the agreed one are quarantined (see
//! [`crate::Scheduler::quarantine`] and ARCHITECTURE.md §6, "Spot checks and quarantine").
//!
//! A leaf: the selection and the events depend on no scheduler state. The scheduler's
//! side (held copies, agreement, quarantine) is `schedule/spot.rs`.

use crate::ids::{JobId, WorkerId};
use crate::plan::WorkUnit;

/// The default fraction of units spot-checked by a coordinator: 2%.
pub const DEFAULT_SPOT_CHECK_FRACTION: f64 = 0.02;

/// Salt of the spot-check selection in [`unit_selected`].
pub const SPOT_CHECK_SALT: u64 = 0x5370_6f74_4368_6b31; // "SpotChk1"

/// Whether `unit` of job `job` is spot-checked at `fraction` (0 disables, 1 checks every
/// unit; NaN checks none).
///
/// ```
/// use tessera_farm::{is_spot_checked, WorkUnit};
/// let u = WorkUnit { frame: 0, tile: 3, first_pass: 1, pass_count: 1 };
/// assert!(!is_spot_checked(0.0, 7, &u));
/// assert!(is_spot_checked(1.0, 7, &u));
/// // A pure function of the unit: the same answer every time.
/// assert_eq!(is_spot_checked(0.5, 7, &u), is_spot_checked(0.5, 7, &u));
/// ```
pub fn is_spot_checked(fraction: f64, job: JobId, unit: &WorkUnit) -> bool {
    unit_selected(SPOT_CHECK_SALT, fraction, job, unit)
}

/// Whether the hash of (`salt`, `job`, the unit's frame, tile and first pass) falls below
/// `fraction` of the 64-bit range: a deterministic selection of about `fraction` of all
/// units, independent between salts. The pass count is left out so that one pass range
/// is chosen the same way however the job was cut (units are fixed per job anyway).
///
/// Shared by the coordinator's spot checks and the worker's `--inject-faults` testing aid
/// (with its own salt), so a test can compute both selections for a fixed job.
pub fn unit_selected(salt: u64, fraction: f64, job: JobId, unit: &WorkUnit) -> bool {
    // NaN compares false everywhere: selects nothing.
    if fraction.is_nan() || fraction <= 0.0 {
        return false;
    }
    if fraction >= 1.0 {
        return true;
    }
    let mut h = mix(salt ^ job);
    for v in [unit.frame, unit.tile, unit.first_pass] {
        h = mix(h ^ u64::from(v));
    }
    // The top 53 bits as a uniform number in [0, 1).
    let u = (h >> 11) as f64 * (1.0 / (1u64 << 53) as f64);
    u < fraction
}

/// The SplitMix64 finalizer (Steele, Lea & Flood 2014): a bijective 64-bit mix.
fn mix(x: u64) -> u64 {
    let mut z = x.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// How a spot check ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SpotOutcome {
    /// Two different workers' copies agreed, and no copy differed.
    Match,
    /// Copies differed; the unit was merged once two different workers agreed, and the
    /// workers whose copy differed were quarantined.
    Mismatch,
    /// The only worker able to render the unit rendered it twice and its copies agreed:
    /// merged, but not verified by another worker (a farm of one worker; this catches only
    /// faults that do not repeat).
    Alone,
}

impl SpotOutcome {
    /// The label in `/metrics` (`tessera_spot_checks_total{outcome=...}`).
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Match => "match",
            Self::Mismatch => "mismatch",
            Self::Alone => "alone",
        }
    }
}

/// What the scheduler learned from spot checks, taken by the caller with
/// [`crate::Scheduler::take_spot_events`] after each submission.
#[derive(Clone, Debug, PartialEq)]
pub enum SpotEvent {
    /// A spot check ended and its unit was merged.
    Checked {
        /// The job.
        job: JobId,
        /// The unit.
        unit: WorkUnit,
        /// How it ended.
        outcome: SpotOutcome,
    },
    /// Two workers' copies of a spot-checked unit differ; the unit is leased to a third
    /// worker to decide (it waits while no third worker is available).
    Disputed {
        /// The job.
        job: JobId,
        /// The unit.
        unit: WorkUnit,
        /// The workers with a copy so far.
        workers: Vec<WorkerId>,
    },
    /// A worker was quarantined: it gets no new leases, its leases were revoked, its
    /// results are refused, and the tiles it merged unverified units into were dropped
    /// and are rendered again by other workers.
    Quarantined {
        /// The worker.
        worker: WorkerId,
        /// Why.
        reason: String,
        /// The tiles dropped to be merged again from scratch: (job, frame, tile).
        reset_tiles: Vec<(JobId, u32, u32)>,
        /// Unverified units of the worker that could not be rendered again: in frames
        /// already complete and released from memory, or in jobs already complete.
        unrepaired_units: u64,
    },
    /// A unit the quarantined `worker` had merged unverified was rendered again by
    /// another worker after its tile was dropped, and compared with the old copy.
    Reverified {
        /// The job.
        job: JobId,
        /// The unit.
        unit: WorkUnit,
        /// The quarantined worker whose copy it was.
        worker: WorkerId,
        /// Whether the new copy equals the quarantined worker's (false: that copy was
        /// corrupt, and dropping the tile repaired the image).
        identical: bool,
    },
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The selection hits about `fraction` of the units: over `n` units the count is
    /// binomial(n, f), so it must lie within 4.5 standard deviations of `n f` (a false
    /// failure has probability below 1e-5 per case), and selections for different salts
    /// and jobs are different sets.
    #[test]
    fn selection_is_deterministic_and_hits_the_fraction() {
        let units: Vec<WorkUnit> = (0..4u32)
            .flat_map(|frame| {
                (0..50u32).flat_map(move |tile| {
                    (0..50u32).map(move |first_pass| WorkUnit {
                        frame,
                        tile,
                        first_pass,
                        pass_count: 1,
                    })
                })
            })
            .collect();
        let n = units.len() as f64; // 10,000
        for f in [0.005, 0.02, 0.1, 0.5, 0.9] {
            for job in [1u64, 2, 1 << 40] {
                let hits = units.iter().filter(|u| is_spot_checked(f, job, u)).count();
                let sd = (n * f * (1.0 - f)).sqrt();
                let z = (hits as f64 - n * f) / sd;
                assert!(
                    z.abs() < 4.5,
                    "fraction {f}, job {job}: {hits} of {n} (z = {z:.2})"
                );
                // Deterministic: the same units again.
                let again = units.iter().filter(|u| is_spot_checked(f, job, u)).count();
                assert_eq!(hits, again);
            }
        }
        // The pass count does not matter; the job and the salt do.
        let u = units[123];
        let wide = WorkUnit { pass_count: 4, ..u };
        assert_eq!(is_spot_checked(0.3, 9, &u), is_spot_checked(0.3, 9, &wide));
        let a: Vec<bool> = units.iter().map(|u| is_spot_checked(0.5, 1, u)).collect();
        let b: Vec<bool> = units.iter().map(|u| is_spot_checked(0.5, 2, u)).collect();
        let c: Vec<bool> = units.iter().map(|u| unit_selected(1, 0.5, 1, u)).collect();
        assert_ne!(a, b);
        assert_ne!(a, c);
        // Two independent selections at 0.5 overlap on about a quarter of the units.
        let both = a.iter().zip(&c).filter(|(x, y)| **x && **y).count() as f64;
        let sd = (n * 0.25 * 0.75).sqrt();
        assert!(((both - n * 0.25) / sd).abs() < 4.5, "overlap {both}");
        // Edge fractions.
        assert!(units.iter().all(|u| !is_spot_checked(0.0, 1, u)));
        assert!(units.iter().all(|u| !is_spot_checked(-1.0, 1, u)));
        assert!(units.iter().all(|u| !is_spot_checked(f64::NAN, 1, u)));
        assert!(units.iter().all(|u| is_spot_checked(1.0, 1, u)));
    }
}
