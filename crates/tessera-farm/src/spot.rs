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
//! Besides that sample, two checks make catching a faulty worker a designed property
//! rather than luck (ARCHITECTURE.md §6, "Spot checks and quarantine"):
//!
//! - **A sequential test per worker** ([`worker_check_rate`]): every unit a worker
//!   delivers is checked until [`BURN_IN_CHECKS`] of its copies have matched another
//!   worker's, and the rate then falls as `BURN_IN_CHECKS / (verified + 1)`, never below
//!   the fraction. A worker that corrupts a fraction `p` of its units (independently of
//!   which are checked) passes `c` checks with probability at most `(1 - p)^c`
//!   ([`escape_bound`]): with `BURN_IN_CHECKS` = 32 and `p` = 0.1 that is 3.4% before it
//!   leaves the burn-in, and after `n` units it has passed about `sqrt(2 B n - B^2)`
//!   checks (`B` = 32: 800 after 10,000 units, a bound of 3e-4 at `p` = 0.01), at a cost
//!   of `B / checks` of its units rendered twice (4% at 10,000 units).
//! - **An outlier test of every delivered unit** ([`unit_is_outlier`]) against its tile's
//!   merged passes, which are independent replicates of each pixel: a unit whose passes
//!   deviate from the tile's running mean far more often than any distribution allows is
//!   re-rendered on another worker and compared byte for byte, like a sampled unit.
//!
//! A leaf: the selection and the events depend on no scheduler state. The scheduler's
//! side (held copies, agreement, quarantine) is `schedule/spot.rs`.

use crate::ids::{JobId, WorkerId};
use crate::plan::WorkUnit;
use crate::stats::PixelStats;

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

/// Matching checks a worker must pass before its units are sampled rather than all
/// checked ([`worker_check_rate`]).
pub const BURN_IN_CHECKS: u64 = 32;

/// Salt of the per-worker selection in [`worker_selects`], independent of the fraction's.
pub const WORKER_CHECK_SALT: u64 = 0x5772_6b43_6865_636b; // "WrkCheck"

/// The fraction of a worker's units checked after `verified` of its copies matched
/// another worker's: 1 during the burn-in (`verified < BURN_IN_CHECKS`), then
/// `BURN_IN_CHECKS / (verified + 1)`, never below `fraction` (the job-wide sample). With
/// `C` checks passed the next unit is checked with probability about `B / C` (`B` =
/// `BURN_IN_CHECKS`), so `dC/dn = B / C`: after `n >= B` units a clean worker has passed
/// about `sqrt(2 B n - B^2)` checks, until the rate reaches `fraction` at `C = B / fraction`.
///
/// ```
/// use tessera_farm::spot::{worker_check_rate, BURN_IN_CHECKS};
/// assert_eq!(worker_check_rate(0, 0.02), 1.0);
/// assert_eq!(worker_check_rate(BURN_IN_CHECKS - 1, 0.02), 1.0);
/// assert_eq!(worker_check_rate(4 * BURN_IN_CHECKS - 1, 0.02), 0.25);
/// assert_eq!(worker_check_rate(1 << 40, 0.02), 0.02);
/// ```
pub fn worker_check_rate(verified: u64, fraction: f64) -> f64 {
    if verified < BURN_IN_CHECKS {
        return 1.0;
    }
    (BURN_IN_CHECKS as f64 / (verified as f64 + 1.0)).max(fraction)
}

/// Whether a worker with `verified` matching checks has its copy of `unit` checked: a
/// hash of the unit against [`worker_check_rate`] (deterministic, like
/// [`is_spot_checked`], and independent of it).
pub fn worker_selects(verified: u64, fraction: f64, job: JobId, unit: &WorkUnit) -> bool {
    unit_selected(
        WORKER_CHECK_SALT,
        worker_check_rate(verified, fraction),
        job,
        unit,
    )
}

/// The probability that a worker corrupting each of its units with probability at least
/// `p`, independently of the check selection, passes `checks` checks: `(1 - p)^checks`.
/// The sequential test's false-negative bound (each check compares the whole unit byte
/// for byte, so a checked corrupt unit is always caught).
///
/// ```
/// use tessera_farm::spot::{escape_bound, BURN_IN_CHECKS};
/// // A worker flipping a bit in 10% of its units leaves the burn-in unnoticed 3.4% of
/// // the time.
/// assert!((escape_bound(0.1, BURN_IN_CHECKS) - 0.0343).abs() < 1e-4);
/// ```
pub fn escape_bound(p: f64, checks: u64) -> f64 {
    (1.0 - p.clamp(0.0, 1.0)).powf(checks as f64)
}

/// The outlier test's threshold in standard deviations: a delivered pass of a pixel
/// counts as an outlier when it is at least `k` standard deviations of the `n + 1` passes
/// (the merged ones and it) from their mean.
pub const OUTLIER_K: f64 = 3.0;

/// Pixels need at least this many merged passes to be tested: among `n + 1` values none
/// can lie more than `sqrt(n)` standard deviations from their mean (Samuelson 1968), so
/// with fewer than `OUTLIER_K^2` passes no pass can be an outlier.
pub const OUTLIER_MIN_PASSES: u32 = 9;

/// The false-alarm probability of [`unit_is_outlier`] per unit on honest data, at most
/// (a false alarm costs one re-render of the unit: the byte comparison decides).
pub const OUTLIER_FALSE_ALARM: f64 = 1e-6;

/// Tested pixels and outliers among them of one delivered pass (`pass`, the tile's pixels
/// row-major) against the tile's merged pixels `merged`, on luminance.
///
/// Why the bound holds for any radiance distribution: at a pixel the `n` merged passes
/// and the new one are independent draws of one distribution (passes are independent
/// replicates, ARCHITECTURE.md §3), so they are exchangeable. Of any `n + 1` numbers at
/// most a fraction `1 / k^2` lie `k` or more of their standard deviations from their mean
/// (Chebyshev's inequality applied to their empirical distribution), and by exchangeability
/// the new pass is each of them with equal probability: it is an outlier with probability
/// at most `1 / k^2`, however heavy the tails. Nothing is estimated: the mean and
/// standard deviation are those of the `n + 1` values themselves.
pub fn pass_outliers(merged: &[PixelStats], pass: &[[f32; 3]]) -> (u64, u64) {
    let (mut tested, mut outliers) = (0u64, 0u64);
    for (s, x) in merged.iter().zip(pass) {
        if s.passes < OUTLIER_MIN_PASSES {
            continue;
        }
        let n = f64::from(s.passes);
        let x = crate::stats::luminance(x.map(f64::from));
        // Mean and sum of squared deviations of the n + 1 values.
        let mean = (n * s.mean_lum + x) / (n + 1.0);
        let ss = s.m2_lum + n * (s.mean_lum - mean).powi(2) + (x - mean).powi(2);
        let var = ss / (n + 1.0);
        if !(var.is_finite() && x.is_finite()) {
            continue;
        }
        tested += 1;
        if var > 0.0 && (x - mean).powi(2) >= OUTLIER_K * OUTLIER_K * var {
            outliers += 1;
        }
    }
    (outliers, tested)
}

/// An upper bound on `P(X >= c)` for `X` binomial(`n`, `q`), `c > n q`: the Chernoff
/// bound `exp(-n D(c/n || q))` with `D` the Kullback-Leibler divergence of Bernoulli
/// distributions (Hoeffding 1963, eq. 2.1); 1 for `c <= n q`. It holds as well for a sum of
/// independent Bernoulli variables each with probability at most `q`.
pub fn binomial_tail_bound(n: u64, c: u64, q: f64) -> f64 {
    if n == 0 || c as f64 <= n as f64 * q {
        return 1.0;
    }
    let a = c as f64 / n as f64;
    let term = |x: f64, y: f64| if x <= 0.0 { 0.0 } else { x * (x / y).ln() };
    let d = term(a, q) + term(1.0 - a, 1.0 - q);
    (-(n as f64) * d).exp()
}

/// Whether a delivered unit is a statistical outlier against its tile's merged pixels
/// `merged`: for some pass of the unit (`pass_means`, pass-major, each pass the tile's
/// pixels row-major), the number of outlier pixels ([`pass_outliers`]) is one that honest
/// passes reach with probability below [`OUTLIER_FALSE_ALARM`] over the unit's passes
/// ([`binomial_tail_bound`] with `q = 1 / OUTLIER_K^2`, at level `OUTLIER_FALSE_ALARM /
/// passes` per pass). Assumes the pixels of a pass independent of each other, as with
/// per-pixel sample streams; a technique whose passes correlate pixels (light paths
/// splatted onto several) can alarm more often, which costs re-renders, never a wrong
/// quarantine. Catches gross corruption (a scaled, shifted, black or garbage pass) once
/// its tile has [`OUTLIER_MIN_PASSES`] merged; not a flipped low bit, which only a
/// comparison of copies finds.
pub fn unit_is_outlier(merged: &[PixelStats], pass_means: &[[f32; 3]]) -> bool {
    let n = merged.len();
    if n == 0 || !pass_means.len().is_multiple_of(n) {
        return false;
    }
    let passes = pass_means.len() / n;
    let level = OUTLIER_FALSE_ALARM / passes.max(1) as f64;
    let q = 1.0 / (OUTLIER_K * OUTLIER_K);
    pass_means.chunks_exact(n).any(|pass| {
        let (outliers, tested) = pass_outliers(merged, pass);
        binomial_tail_bound(tested, outliers, q) < level
    })
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

    /// splitmix64 with a fixed seed.
    struct Rng(u64);
    impl Rng {
        fn next(&mut self) -> u64 {
            self.0 = mix(self.0);
            self.0
        }
        /// Uniform in (0, 1].
        fn uniform(&mut self) -> f64 {
            ((self.next() >> 11) as f64 + 1.0) / (1u64 << 53) as f64
        }
    }

    /// A heavy-tailed radiance: a Pareto variable of index 1.5 (infinite variance) with
    /// probability 0.02 (fireflies), else an exponential around 0.3, per pixel scaled by
    /// `scale`: far from normal, so a test assuming normality would alarm.
    fn radiance(r: &mut Rng, scale: f64) -> f32 {
        let v = if r.uniform() < 0.02 {
            r.uniform().powf(-1.0 / 1.5)
        } else {
            -0.3 * r.uniform().ln()
        };
        (v * scale) as f32
    }

    /// A tile of `w * h` pixels with `passes` merged passes of honest radiance.
    fn merged_tile(r: &mut Rng, pixels: usize, passes: u32) -> (Vec<PixelStats>, Vec<f64>) {
        let scale: Vec<f64> = (0..pixels).map(|_| 0.1 + 2.0 * r.uniform()).collect();
        let mut stats = vec![PixelStats::default(); pixels];
        for _ in 0..passes {
            for (s, &k) in stats.iter_mut().zip(&scale) {
                let v = radiance(r, k);
                s.push([v, v * 0.9, v * 1.1]);
            }
        }
        (stats, scale)
    }

    /// On honest data the per-pixel outlier rate is at most `1 / k^2` (the exchangeability
    /// bound; heavy tails included), and no unit alarms. Fixed seed; the assertions'
    /// false-failure probabilities are stated.
    #[test]
    fn the_outlier_test_rarely_alarms_on_honest_heavy_tailed_passes() {
        let mut r = Rng(0x0123_4567_89ab_cdef);
        let (mut outliers, mut tested, mut alarms) = (0u64, 0u64, 0u32);
        let units = 300;
        for u in 0..units {
            let passes = OUTLIER_MIN_PASSES + (u % 24);
            let (stats, scale) = merged_tile(&mut r, 256, passes);
            // A unit of two fresh passes.
            let fresh: Vec<[f32; 3]> = (0..2)
                .flat_map(|_| scale.clone())
                .map(|k| {
                    let v = radiance(&mut r, k);
                    [v, v * 0.9, v * 1.1]
                })
                .collect();
            for pass in fresh.chunks_exact(256) {
                let (o, t) = pass_outliers(&stats, pass);
                outliers += o;
                tested += t;
            }
            alarms += u32::from(unit_is_outlier(&stats, &fresh));
        }
        assert_eq!(tested, units as u64 * 2 * 256);
        // The count is a sum of Bernoulli variables with probability <= 1/9 each: it
        // exceeds 1/9 + 0.01 of 153,600 with probability below binomial_tail_bound
        // (< 1e-9), if the bound is right.
        let q = 1.0 / (OUTLIER_K * OUTLIER_K);
        let limit = ((q + 0.01) * tested as f64) as u64;
        assert!(binomial_tail_bound(tested, limit, q) < 1e-9);
        assert!(outliers < limit, "{outliers} of {tested} pixels alarmed");
        // Every unit alarms with probability <= 1e-6: any alarm in 300 has probability
        // <= 3e-4.
        assert_eq!(alarms, 0);
    }

    /// Gross corruption is caught once the tile has enough passes: a black pass, a pass
    /// scaled by 4, and one pass of a two-pass unit replaced by noise; a one-bit flip is not.
    #[test]
    fn the_outlier_test_catches_gross_corruption_not_a_flipped_bit() {
        let mut r = Rng(42);
        // Low-noise pixels (a diffuse wall): every pass close to the mean.
        let pixels = 256;
        let mut stats = vec![PixelStats::default(); pixels];
        for _ in 0..16 {
            for s in &mut stats {
                let v = (0.5 + 0.01 * r.uniform()) as f32;
                s.push([v; 3]);
            }
        }
        let honest: Vec<[f32; 3]> = (0..pixels)
            .map(|_| [(0.5 + 0.01 * r.uniform()) as f32; 3])
            .collect();
        assert!(!unit_is_outlier(&stats, &honest));
        let black = vec![[0.0f32; 3]; pixels];
        assert!(unit_is_outlier(&stats, &black));
        let scaled: Vec<[f32; 3]> = honest.iter().map(|p| p.map(|c| c * 4.0)).collect();
        assert!(unit_is_outlier(&stats, &scaled));
        let mut two = honest.clone();
        two.extend((0..pixels).map(|_| [(r.uniform() * 50.0) as f32; 3]));
        assert!(unit_is_outlier(&stats, &two));
        let mut flipped = honest.clone();
        flipped[3][0] = f32::from_bits(flipped[3][0].to_bits() ^ 1);
        assert!(!unit_is_outlier(&stats, &flipped));
        // Too few passes merged: nothing is tested, nothing alarms.
        let mut young = vec![PixelStats::default(); pixels];
        young.iter_mut().for_each(|s| s.push([0.5; 3]));
        assert_eq!(pass_outliers(&young, &black), (0, 0));
        assert!(!unit_is_outlier(&young, &black));
    }

    /// The schedule: all units in the burn-in, then falling with the record, never below
    /// the fraction; the checks passed after `n` units grow like `sqrt(2 B n - B^2)`, and
    /// the false-negative bound is `(1 - p)^checks`.
    #[test]
    fn the_worker_schedule_checks_new_workers_fully_and_then_less() {
        let f = 0.02;
        for v in 0..BURN_IN_CHECKS {
            assert_eq!(worker_check_rate(v, f), 1.0);
        }
        let mut last = 1.0;
        for v in BURN_IN_CHECKS..100_000 {
            let r = worker_check_rate(v, f);
            assert!(r <= last && r >= f, "{v}: {r}");
            last = r;
        }
        // Simulate a clean worker's record: the expected number of checks after n units.
        let mut checks = 0.0f64;
        for _ in 0..10_000 {
            checks += worker_check_rate(checks as u64, f);
        }
        let b = BURN_IN_CHECKS as f64;
        let predicted = (2.0 * b * 10_000.0 - b * b).sqrt();
        assert!(
            (checks - predicted).abs() < 0.1 * predicted,
            "{checks} checks, predicted {predicted}"
        );
        assert!(escape_bound(0.1, checks as u64) < 1e-9);
        // The selection follows the rate: all units at first, about 1/4 at 4B.
        let units: Vec<WorkUnit> = (0..4000u32)
            .map(|i| WorkUnit {
                frame: 0,
                tile: i % 100,
                first_pass: i / 100,
                pass_count: 1,
            })
            .collect();
        assert!(units.iter().all(|u| worker_selects(0, f, 5, u)));
        let hits = units
            .iter()
            .filter(|u| worker_selects(4 * BURN_IN_CHECKS - 1, f, 5, u))
            .count() as f64;
        // Binomial(4000, 0.25): sd 27.4; 4.5 sd bounds a false failure below 1e-5.
        assert!((hits - 1000.0).abs() < 4.5 * 27.4, "{hits}");
    }
}
