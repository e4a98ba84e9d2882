//! Adaptive jobs: no unit leased beyond an open decision, the pixel sets leases name.

use super::{deliver_random, lcg_step, noisy_result};
use crate::adaptive::AdaptiveFrame;
use crate::plan::{FramePlan, WorkUnit};
use crate::schedule::{Lease, Scheduler, Submitted};
use std::collections::{BTreeMap, BTreeSet};

/// An adaptive job's units waiting for a decision are not queued work: with one
/// whole-frame tile (bdpt) the first worker to ask used to get every unit before the
/// next decision, and the other waited (the tail rule counted the whole plan).
#[test]
fn adaptive_windows_are_shared_between_workers() {
    use crate::adaptive::{AdaptiveMode, AdaptiveSettings};
    // One 16-pixel tile covering the frame: the plan of a bdpt job.
    let p = FramePlan::new(16, 16, 16, 4, 64).unwrap();
    assert_eq!(p.tile_count(), 1);
    let settings = AdaptiveSettings {
        mode: AdaptiveMode::Sequential,
        target_error: 0.05,
        ..AdaptiveSettings::default()
    };
    let mut s = Scheduler::new(100, 0);
    s.add_adaptive_job(3, 0, p, 0..=0, 1, settings).unwrap();
    // Before the first decision (min_passes 8): 8 units of one pass open. Two
    // one-thread workers asking for 8 each get 2 each (half their share of 8).
    let a = s.lease_among(0, 0, 8, 1, 2);
    let b = s.lease_among(1, 0, 8, 1, 2);
    assert_eq!(
        (a.len(), b.len()),
        (2, 2),
        "the first worker took the window"
    );
    // The window is all there is: the rest of it is shared out, then nothing is left.
    let mut leased: Vec<_> = a.into_iter().chain(b).collect();
    for w in (0..2).cycle().take(8) {
        leased.extend(s.lease_among(w, 0, 8, 1, 2));
    }
    assert_eq!(leased.len(), 8);
    assert!(leased.iter().all(|l| l.unit.first_pass < 8));
}

/// Adaptive farm jobs. Whatever the number of workers and the interleaving
/// (with lost leases re-leased after expiry), no unit is leased beyond an open decision,
/// finished tiles stop being leased, and the image equals the local adaptive render of
/// the same passes bit for bit.
#[test]
fn adaptive_jobs_stop_tiles_and_stay_bit_identical() {
    use crate::adaptive::{AdaptiveMode, AdaptiveSettings};
    let p = FramePlan::new(24, 16, 8, 1, 48).unwrap(); // 6 tiles
    for mode in [AdaptiveMode::Sequential, AdaptiveMode::Unbiased] {
        let settings = AdaptiveSettings {
            mode,
            target_error: 0.05,
            min_passes: 7, // rounded up to 8 (units of 2 passes)
            interval: 3,   // rounded up to 4
            ..AdaptiveSettings::default()
        };
        // The local render of the same job: the policy fed every planned pass.
        let used_local = {
            let mut s = settings;
            s.min_passes = 8;
            s.interval = 4;
            s
        };
        let mut local = AdaptiveFrame::new(p, 0, used_local).unwrap();
        for u in p.units(0, 2) {
            local.offer(&noisy_result(&p, u)).unwrap();
        }
        let reference = local.image();
        for (workers, seed) in [(1u64, 1u64), (3, 2), (5, 3)] {
            let mut s = Scheduler::new(100, 0);
            let used = s.add_adaptive_job(7, 0, p, 0..=0, 2, settings).unwrap();
            assert_eq!((used.min_passes, used.interval), (8, 4));
            let (mut now, mut rng) = (0u64, seed);
            let mut held: Vec<Lease> = Vec::new();
            let mut leased_units = BTreeSet::new();
            while !s.is_complete(7) {
                now += 10;
                assert!(now < 1_000_000, "{mode}: the job stalls");
                for w in 0..workers {
                    let new = s.lease(w, now, 1);
                    let f = s.adaptive_frame(7, 0).unwrap();
                    for l in &new {
                        let t = f.tile(l.unit.tile).unwrap();
                        assert!(
                            l.unit.first_pass < t.lease_horizon(),
                            "{mode}: unit {:?} leased beyond the open decision at {}",
                            l.unit,
                            t.lease_horizon()
                        );
                    }
                    leased_units.extend(new.iter().map(|l| l.unit));
                    held.extend(new);
                }
                deliver_random(&mut s, 7, &p, &mut held, &mut rng, now, (5, 3));
            }
            let image = s.adaptive_frame(7, 0).unwrap().image();
            assert_eq!(image, reference, "{mode} with {workers} workers");
            // Tile 0 (constant) stopped at the first decision (sequential: 4 of its 24
            // units) or after the pilot and the minimum 4 fresh passes (unbiased: 6).
            let f = s.adaptive_frame(7, 0).unwrap();
            assert!(f.tile(0).unwrap().finished());
            let end0 = if mode == AdaptiveMode::Sequential {
                8
            } else {
                12
            };
            assert!(leased_units
                .iter()
                .all(|u| u.tile != 0 || u.first_pass < end0));
            let total = p.unit_count(2) as usize;
            assert!(
                leased_units.len() < total,
                "{mode}: adaptivity saved nothing"
            );
            assert!(
                s.lease(1, now, 10).is_empty(),
                "{mode}: work after completion"
            );
        }
    }
    // Settings that do not fit the plan are refused.
    let mut s = Scheduler::new(100, 0);
    let bad = AdaptiveSettings {
        mode: AdaptiveMode::Unbiased,
        target_error: 0.05,
        min_passes: 48,
        ..AdaptiveSettings::default()
    };
    assert!(s.add_adaptive_job(1, 0, p, 0..=0, 2, bad).is_err());
    assert!(s.lease(1, 0, 1).is_empty());
}

/// Leases of adaptive jobs name the pixels still wanted. Workers that trace
/// only those (the rest black) give the local image bit for bit; the set of every unit
/// is the same whatever the workers and the interleaving (expiry, re-leases, copies
/// compared), and the same when asked again after the job finished, so it is a pure
/// function of the merged state; and the pixel-passes traced are those the local
/// render used (one pass per unit), far fewer than whole tiles.
#[test]
fn leased_pixel_sets_are_deterministic_and_save_the_stopped_pixels() {
    use crate::adaptive::{AdaptiveMode, AdaptiveSettings};
    let p = FramePlan::new(24, 16, 8, 1, 48).unwrap(); // 6 tiles of 64 pixels
    let masked = |unit: WorkUnit, wanted: &Option<crate::PixelRuns>| {
        let mut r = noisy_result(&p, unit);
        let n = p.tile(unit.tile).pixel_count();
        for (k, m) in r.pass_means.iter_mut().enumerate() {
            if wanted.as_ref().is_some_and(|w| !w.contains(k % n)) {
                *m = [0.0; 3];
            }
        }
        r
    };
    for (mode, ppu) in [
        (AdaptiveMode::Sequential, 1),
        (AdaptiveMode::Unbiased, 1),
        (AdaptiveMode::Sequential, 2),
        (AdaptiveMode::Unbiased, 2),
    ] {
        let settings = AdaptiveSettings {
            mode,
            // The unbiased mode's optimal allocation gives a tile's quiet pixels
            // passes in proportion to the tile's mean deviation, which the fireflies
            // raise: at 0.05 every pixel of a noisy tile would take all 40 fresh
            // passes and no lease would name a set.
            target_error: if mode == AdaptiveMode::Unbiased {
                0.2
            } else {
                0.05
            },
            min_passes: 8,
            interval: 4,
            ..AdaptiveSettings::default()
        };
        let mut local = AdaptiveFrame::new(p, 0, settings).unwrap();
        for u in p.units(0, ppu) {
            local.offer(&noisy_result(&p, u)).unwrap();
        }
        let reference = local.image();
        let local_traced: u64 = local
            .tiles()
            .iter()
            .flat_map(|t| t.traced_passes())
            .map(u64::from)
            .sum();
        let mut sets: Option<BTreeMap<WorkUnit, Option<crate::PixelRuns>>> = None;
        for (workers, seed) in [(1u64, 1u64), (3, 2), (4, 9)] {
            let mut s = Scheduler::new(100, 0);
            s.add_adaptive_job(7, 0, p, 0..=0, ppu, settings).unwrap();
            let (mut now, mut rng) = (0u64, seed);
            let mut held: Vec<(Lease, Option<crate::PixelRuns>)> = Vec::new();
            let mut seen: BTreeMap<WorkUnit, Option<crate::PixelRuns>> = BTreeMap::new();
            let mut traced = 0u64;
            while !s.is_complete(7) {
                now += 10;
                assert!(now < 1_000_000, "{mode}: the job stalls");
                for w in 0..workers {
                    for l in s.lease(w, now, 1) {
                        let set = s.wanted_pixels(7, &l.unit);
                        // Every copy of a unit gets the same set.
                        let first = seen.entry(l.unit).or_insert_with(|| set.clone());
                        assert_eq!(*first, set, "{mode}: unit {:?} changed its set", l.unit);
                        held.push((l, set));
                    }
                }
                lcg_step(&mut rng);
                if held.is_empty() {
                    s.expire(now + 1000);
                    continue;
                }
                let k = (rng >> 33) as usize % held.len();
                let (l, set) = held.swap_remove(k);
                if rng.is_multiple_of(5) {
                    continue; // a lost result: re-leased after expiry
                }
                let n = p.tile(l.unit.tile).pixel_count() as u64;
                // Some copies come from workers that trace whole tiles (older ones)
                // or carry values outside the set (bdpt splats): the same unit.
                let r = if rng.is_multiple_of(7) {
                    noisy_result(&p, l.unit)
                } else {
                    masked(l.unit, &set)
                };
                let outcome = s.submit(l.lease_id, 7, r).unwrap();
                match outcome {
                    Submitted::Accepted => {
                        traced += set.as_ref().map_or(n, crate::PixelRuns::count)
                            * u64::from(l.unit.pass_count);
                    }
                    // Masked pixels are deterministic zeros: copies agree.
                    other => assert_eq!(other, Submitted::Duplicate { identical: true }),
                }
                if rng.is_multiple_of(3) {
                    s.expire(now + 1000);
                }
            }
            let f = s.adaptive_frame(7, 0).unwrap();
            assert_eq!(f.image(), reference, "{mode}/{ppu} with {workers} workers");
            // Asked again now that every decision is taken, each set is unchanged.
            for (u, set) in &seen {
                assert_eq!(s.wanted_pixels(7, u), *set, "{mode}: {u:?} after the end");
            }
            match &sets {
                None => sets = Some(seen),
                Some(first) => assert_eq!(*first, seen, "{mode}: sets differ by workers"),
            }
            let full = u64::from(p.width * p.height * p.passes);
            if ppu == 1 {
                assert_eq!(traced, local_traced, "{mode}: traced vs the local render");
            } else {
                // A pixel wanted for one pass of a unit is traced for both.
                assert!(traced >= local_traced, "{mode}/{ppu}");
            }
            // Tile 0 (constant) stops at the first decision; the noisy ones later.
            assert!(traced < full, "{mode}/{ppu}: traced {traced} of {full}");
        }
        let sets = sets.unwrap();
        assert!(
            sets.values().any(Option::is_some),
            "{mode}: no lease named a pixel set"
        );
    }
}
