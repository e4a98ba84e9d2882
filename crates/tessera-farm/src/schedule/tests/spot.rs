//! Spot checks and quarantine.

use super::plan;
use crate::ids::WorkerId;
use crate::merge::FrameImage;
use crate::plan::{FramePlan, WorkUnit};
use crate::result::UnitResult;
use crate::schedule::{Lease, Scheduler, SubmitError, Submitted};
use crate::spot::{is_spot_checked, SpotEvent, SpotOutcome};
use std::collections::BTreeSet;

/// What an honest worker renders: a pure function of the unit.
fn honest(plan: &FramePlan, unit: WorkUnit) -> UnitResult {
    let rect = plan.tile(unit.tile);
    let n = rect.pixel_count() * unit.pass_count as usize;
    let base = 0.5 + unit.tile as f32 + unit.first_pass as f32 * 0.1;
    let pass_means = (0..n).map(|k| [base + (k % 7) as f32 * 0.01; 3]).collect();
    UnitResult {
        unit,
        width: rect.width,
        height: rect.height,
        pass_means,
        rejected_samples: 0,
    }
}

/// What a faulty worker renders: well-formed, one value off.
fn corrupt(plan: &FramePlan, unit: WorkUnit) -> UnitResult {
    let mut r = honest(plan, unit);
    r.pass_means[3][1] += 0.25;
    r
}

fn bits(img: &FrameImage) -> Vec<u32> {
    img.mean
        .iter()
        .chain(&img.variance_of_mean)
        .flat_map(|p| p.map(f32::to_bits))
        .chain(img.passes.iter().copied())
        .collect()
}

/// The image of the job rendered by honest workers without spot checks.
fn reference() -> Vec<u32> {
    let p = plan();
    let mut s = Scheduler::new(100, 0);
    s.add_job(1, 0, p, 0..=0, 1);
    while !s.is_complete(1) {
        for l in s.lease(1, 0, 100) {
            s.submit(l.lease_id, 1, honest(&p, l.unit)).unwrap();
        }
    }
    bits(&s.frame(1, 0).unwrap().image())
}

/// Drives `workers` (id, faulty) round-robin, each leasing up to 2 units as one of
/// `workers.len()` one-thread workers and delivering them the next round (so copies
/// of one unit are in flight at once), until the job completes or `rounds` pass.
/// Asserts that no worker is ever leased a spot-checked unit it already delivered a
/// copy of. Returns the events.
fn drive(s: &mut Scheduler, workers: &[(WorkerId, bool)], rounds: u32) -> Vec<SpotEvent> {
    let p = plan();
    let mut delivered: BTreeSet<(WorkUnit, WorkerId)> = BTreeSet::new();
    let mut held: Vec<Lease> = Vec::new();
    let mut events = Vec::new();
    let live = workers
        .iter()
        .filter(|(w, _)| !s.is_quarantined(*w))
        .count() as u64;
    for round in 0..rounds {
        if s.is_complete(1) {
            break;
        }
        for &(w, faulty) in workers {
            // Deliver what this worker leased last round.
            let mine: Vec<Lease> = held.iter().filter(|l| l.worker == w).copied().collect();
            held.retain(|l| l.worker != w);
            for l in mine {
                let r = if faulty {
                    corrupt(&p, l.unit)
                } else {
                    honest(&p, l.unit)
                };
                match s.submit_from(w, l.lease_id, 1, r) {
                    Ok(_) | Err(SubmitError::Quarantined(_)) => {}
                    Err(e) => panic!("worker {w}: {e}"),
                }
                delivered.insert((l.unit, w));
                events.extend(s.take_spot_events());
            }
            let got = s.lease_among(w, u64::from(round), 2, 1, live);
            for l in &got {
                if is_spot_checked(s.spot_check_fraction(), 1, &l.unit) {
                    assert!(
                        !delivered.contains(&(l.unit, w)) || live == 1,
                        "worker {w} leased a second copy of {:?}",
                        l.unit
                    );
                }
            }
            held.extend(got);
        }
    }
    events
}

#[test]
fn a_faulty_worker_is_quarantined_and_the_image_stays_identical() {
    let p = plan();
    let expected = reference();
    for fraction in [0.3, 1.0] {
        let mut s = Scheduler::new(100, 0);
        s.set_spot_check_fraction(fraction);
        s.add_job(1, 0, p, 0..=0, 1);
        let events = drive(&mut s, &[(3, true), (1, false), (2, false)], 500);
        assert!(s.is_complete(1), "fraction {fraction}: the job stalled");
        assert_eq!(
            bits(&s.frame(1, 0).unwrap().image()),
            expected,
            "fraction {fraction}: the image differs from the honest render"
        );
        assert!(s.is_quarantined(3));
        assert!(!s.is_quarantined(1) && !s.is_quarantined(2));
        assert!(
            s.lease(3, 1000, 10).is_empty(),
            "a quarantined worker leases"
        );
        let mismatches = events
            .iter()
            .filter(|e| {
                matches!(
                    e,
                    SpotEvent::Checked {
                        outcome: SpotOutcome::Mismatch,
                        ..
                    }
                )
            })
            .count();
        assert!(mismatches >= 1, "fraction {fraction}: {events:?}");
        let q: Vec<_> = events
            .iter()
            .filter(|e| matches!(e, SpotEvent::Quarantined { worker: 3, .. }))
            .collect();
        assert_eq!(q.len(), 1, "quarantined once");
        // The faulty worker delivered first (it leads the round), so at 0.3 some of
        // its corrupt units were merged unchecked: their tiles were dropped and every
        // re-rendered copy of its units differs from its own.
        if fraction < 1.0 {
            let SpotEvent::Quarantined { reset_tiles, .. } = q[0] else {
                unreachable!()
            };
            assert!(!reset_tiles.is_empty());
            let reverified: Vec<bool> = events
                .iter()
                .filter_map(|e| match e {
                    SpotEvent::Reverified { identical, .. } => Some(*identical),
                    _ => None,
                })
                .collect();
            assert!(!reverified.is_empty() && reverified.iter().all(|i| !i));
        }
        assert_eq!(s.spot_checks_waiting(), (0, 0));
    }
}

#[test]
fn a_worker_alone_checks_itself_and_finishes() {
    let p = plan();
    let mut s = Scheduler::new(100, 0);
    s.set_spot_check_fraction(0.3);
    s.add_job(1, 0, p, 0..=0, 1);
    let events = drive(&mut s, &[(1, false)], 500);
    assert!(s.is_complete(1));
    assert_eq!(bits(&s.frame(1, 0).unwrap().image()), reference());
    let checked = (0..36u64)
        .filter(|&i| {
            let u = WorkUnit {
                frame: 0,
                tile: (i % 6) as u32,
                first_pass: (i / 6) as u32,
                pass_count: 1,
            };
            is_spot_checked(0.3, 1, &u)
        })
        .count();
    assert!(checked > 0);
    let alone = events
        .iter()
        .filter(|e| {
            matches!(
                e,
                SpotEvent::Checked {
                    outcome: SpotOutcome::Alone,
                    ..
                }
            )
        })
        .count();
    assert_eq!(alone, checked);
    // The copies are counted as work: one more per checked unit, all rendered.
    let progress = s.progress(1).unwrap();
    assert_eq!(progress.copies_total, checked as u64);
    assert_eq!(
        (progress.units_done, progress.copies_done),
        (36, checked as u64)
    );
    // The plain lease (no knowledge of the others) never gives a worker its own
    // spot-checked unit again.
    let mut s = Scheduler::new(100, 0);
    s.set_spot_check_fraction(1.0);
    s.add_job(1, 0, p, 0..=0, 1);
    let first = s.lease(1, 0, 100);
    assert_eq!(first.len(), 36);
    for l in &first {
        assert_eq!(
            s.submit_from(1, l.lease_id, 1, honest(&p, l.unit)),
            Ok(Submitted::Held)
        );
    }
    assert!(s.lease(1, 0, 100).is_empty());
    let progress = s.progress(1).unwrap();
    assert_eq!(
        (
            progress.units_done,
            progress.copies_total,
            progress.copies_done
        ),
        (0, 36, 36),
        "36 first copies held: half the work"
    );
    let second = s.lease(2, 0, 100);
    assert_eq!(second.len(), 36);
    for l in &second {
        assert_eq!(
            s.submit_from(2, l.lease_id, 1, honest(&p, l.unit)),
            Ok(Submitted::Accepted)
        );
    }
    assert!(s.is_complete(1));
    let progress = s.progress(1).unwrap();
    assert_eq!((progress.units_done, progress.copies_done), (36, 36));
}

#[test]
fn a_dispute_waits_for_a_third_worker() {
    let p = plan();
    let mut s = Scheduler::new(100, 0);
    s.set_spot_check_fraction(1.0);
    s.add_job(1, 0, p, 0..=0, 1);
    // Two workers, one faulty: every unit is disputed and nobody can decide.
    drive(&mut s, &[(1, false), (2, true)], 100);
    assert!(!s.is_complete(1));
    assert!(!s.is_quarantined(1) && !s.is_quarantined(2));
    let (waiting, disputed) = s.spot_checks_waiting();
    assert!(waiting > 0 && disputed > 0, "{waiting} {disputed}");
    assert_eq!(
        s.progress(1).unwrap().passes_done,
        0,
        "nothing disputed is merged"
    );
    // A third worker decides by majority.
    drive(&mut s, &[(1, false), (2, true), (3, false)], 500);
    assert!(s.is_complete(1));
    assert!(s.is_quarantined(2) && !s.is_quarantined(1) && !s.is_quarantined(3));
    assert_eq!(bits(&s.frame(1, 0).unwrap().image()), reference());
    // The quarantined worker's late results are refused.
    let l = s.leases().next().copied();
    assert!(l.is_none(), "its leases were revoked");
}

#[test]
fn quarantine_drops_the_tiles_of_unverified_units_and_revokes_leases() {
    let p = plan();
    let mut s = Scheduler::new(100, 0);
    s.add_job(1, 0, p, 0..=0, 1);
    // Worker 9 merges the first pass of every tile (unchecked: no spot checks), and
    // holds a lease.
    for l in s.lease(9, 0, 6) {
        s.submit_from(9, l.lease_id, 1, corrupt(&p, l.unit))
            .unwrap();
    }
    let out = s.lease(9, 0, 1);
    assert_eq!(s.progress(1).unwrap().passes_done, 6);
    assert!(s.quarantine(9, "test"));
    assert!(!s.quarantine(9, "again"));
    assert_eq!(s.progress(1).unwrap().passes_done, 0);
    assert_eq!(s.progress(1).unwrap().units_leased, 0);
    assert_eq!(
        s.submit_from(9, out[0].lease_id, 1, honest(&p, out[0].unit)),
        Err(SubmitError::Quarantined(9))
    );
    let ev = s.take_spot_events();
    assert!(
        matches!(&ev[..], [SpotEvent::Quarantined { reset_tiles, unrepaired_units: 0, .. }] if reset_tiles.len() == 6)
    );
    while !s.is_complete(1) {
        for l in s.lease(1, 0, 100) {
            s.submit_from(1, l.lease_id, 1, honest(&p, l.unit)).unwrap();
        }
    }
    assert_eq!(bits(&s.frame(1, 0).unwrap().image()), reference());
    let again = s.take_spot_events();
    assert_eq!(again.len(), 6);
    assert!(again.iter().all(|e| matches!(
        e,
        SpotEvent::Reverified {
            worker: 9,
            identical: false,
            ..
        }
    )));
}

#[test]
fn a_lifted_quarantine_leases_again_and_takes_results() {
    let p = plan();
    let mut s = Scheduler::new(100, 0);
    s.add_job(1, 0, p, 0..=0, 1);
    assert!(!s.lift_quarantine(9), "not quarantined");
    let held = s.lease(9, 0, 1);
    assert!(s.quarantine(9, "test"));
    s.take_spot_events();
    assert!(s.lease(9, 0, 1).is_empty());
    assert_eq!(
        s.submit_from(9, held[0].lease_id, 1, honest(&p, held[0].unit)),
        Err(SubmitError::Quarantined(9))
    );
    assert!(s.lift_quarantine(9));
    assert!(!s.is_quarantined(9));
    assert!(!s.lift_quarantine(9), "lifted once");
    // Leased again, and its result merged.
    let again = s.lease(9, 0, 1);
    assert_eq!(again.len(), 1);
    assert_eq!(
        s.submit_from(9, again[0].lease_id, 1, honest(&p, again[0].unit)),
        Ok(Submitted::Accepted)
    );
    assert_eq!(s.progress(1).unwrap().passes_done, 1);
    // Quarantined again: the unit it merged since is dropped and repaired as before.
    assert!(s.quarantine(9, "again"));
    assert!(matches!(
        &s.take_spot_events()[..],
        [SpotEvent::Quarantined { reset_tiles, unrepaired_units: 0, .. }] if reset_tiles.len() == 1
    ));
    assert_eq!(s.progress(1).unwrap().passes_done, 0);
}
