//! Leasing: order, fencing tokens, expiry, the tail rule, cancel; and submissions.

use super::{lcg_step, plan, result};
use crate::ids::JobId;
use crate::merge::FrameImage;
use crate::schedule::{tail_share, Lease, Scheduler, SubmitError, Submitted};
use std::collections::BTreeSet;

#[test]
fn priority_then_fifo_then_coarse_to_fine() {
    let p = plan();
    let mut s = Scheduler::new(1000, 0);
    s.add_job(1, 0, p, 0..=0, 2);
    s.add_job(2, 5, p, 0..=0, 2);
    s.add_job(3, 0, p, 0..=0, 2);
    let leases = s.lease(9, 0, 100);
    assert_eq!(leases.len(), 3 * 18);
    let jobs: Vec<JobId> = leases.iter().map(|l| l.job).collect();
    assert!(jobs[..18].iter().all(|&j| j == 2));
    assert!(jobs[18..36].iter().all(|&j| j == 1));
    assert!(jobs[36..].iter().all(|&j| j == 3));
    // Coarse to fine: every tile's first chunk before any second chunk.
    let firsts: Vec<u32> = leases[..18].iter().map(|l| l.unit.first_pass).collect();
    assert_eq!(firsts, [[0; 6], [2; 6], [4; 6]].concat());
    // Fencing tokens are unique and increasing.
    assert!(leases.windows(2).all(|w| w[0].lease_id < w[1].lease_id));
}

#[test]
fn expired_leases_are_released_in_canonical_order_and_merged_once() {
    let p = plan();
    let mut s = Scheduler::new(100, 0);
    s.add_job(1, 0, p, 0..=1, 3);
    let a = s.lease(1, 0, 3);
    // Heartbeat keeps lease a[0] alive; the others lapse.
    assert_eq!(s.extend(1, &[a[0].lease_id], 50).len(), 1);
    assert!(
        s.extend(2, &[a[1].lease_id], 50).is_empty(),
        "not the holder"
    );
    let expired = s.expire(120);
    assert_eq!(expired.len(), 2);
    // The next lease hands out the expired units first, in canonical order.
    let b = s.lease(2, 130, 2);
    assert_eq!(
        b.iter().map(|l| l.unit).collect::<Vec<_>>(),
        vec![a[1].unit, a[2].unit]
    );
    // Both the late worker and the new holder submit: merged once, compared once.
    assert_eq!(
        s.submit(a[1].lease_id, 1, result(&p, a[1].unit, 0.5)),
        Ok(Submitted::Accepted)
    );
    assert_eq!(
        s.submit(b[0].lease_id, 1, result(&p, b[0].unit, 0.5)),
        Ok(Submitted::Duplicate { identical: true })
    );
    // A copy that differs is flagged.
    assert_eq!(
        s.submit(b[1].lease_id, 1, result(&p, b[1].unit, 0.5)),
        Ok(Submitted::Accepted)
    );
    assert_eq!(
        s.submit(a[2].lease_id, 1, result(&p, a[2].unit, 0.25)),
        Ok(Submitted::Duplicate { identical: false })
    );
}

/// `expire` looks at the lease table only once the earliest deadline may have passed
/// (`next_expiry_ms`); every lease must still lapse at its own deadline, whatever was
/// leased, extended or expired before it.
#[test]
fn every_lease_lapses_at_its_deadline_after_extensions_and_earlier_expiries() {
    let p = plan();
    let mut s = Scheduler::new(100, 0);
    s.add_job(1, 0, p, 0..=1, 3);
    let a = s.lease(1, 0, 2); // deadlines 100
    assert!(s.expire(100).is_empty(), "a deadline is inclusive");
    // a[0] is extended to 150: the bound (100) is stale-low, a scan finds a[1] only.
    assert_eq!(s.extend(1, &[a[0].lease_id], 50).len(), 1);
    let e = s.expire(101);
    assert_eq!(
        e.iter().map(|l| l.lease_id).collect::<Vec<_>>(),
        [a[1].lease_id]
    );
    assert!(s.expire(150).is_empty());
    assert_eq!(s.expire(151).len(), 1, "the extended lease lapses at 150");
    // With no lease left the bound is open; a new lease must lower it again.
    assert!(s.expire(10_000).is_empty());
    let b = s.lease(2, 10_000, 1);
    assert_eq!(b.len(), 1);
    assert!(s.expire(10_100).is_empty());
    let e = s.expire(10_101);
    assert_eq!(
        e.iter().map(|l| l.lease_id).collect::<Vec<_>>(),
        [b[0].lease_id]
    );
    // A lease taken while an earlier one is held, then the earlier one delivered:
    // the later deadline is still found.
    let c = s.lease(3, 20_000, 1);
    let d = s.lease(3, 20_050, 1);
    assert_eq!(
        s.submit(c[0].lease_id, 1, result(&p, c[0].unit, 0.5)),
        Ok(Submitted::Accepted)
    );
    assert!(
        s.expire(20_101).is_empty(),
        "c was delivered, d lapses at 20,150"
    );
    let e = s.expire(20_151);
    assert_eq!(
        e.iter().map(|l| l.lease_id).collect::<Vec<_>>(),
        [d[0].lease_id]
    );
}

#[test]
fn a_lapsed_lease_is_wanted_until_its_result_arrives_or_its_job_is_canceled() {
    let p = plan();
    let mut s = Scheduler::new(100, 0);
    s.add_job(1, 0, p, 0..=0, 3);
    s.add_job(2, 0, p, 0..=0, 3);
    let a = s.lease(1, 0, 2);
    let b: Vec<Lease> = s
        .lease(1, 0, 100)
        .into_iter()
        .filter(|l| l.job == 2)
        .take(1)
        .collect();
    // Live leases are not lapsed.
    assert!(!s.is_lapsed_and_wanted(a[0].lease_id));
    s.expire(200);
    assert!(s.is_lapsed_and_wanted(a[0].lease_id));
    assert!(s.is_lapsed_and_wanted(b[0].lease_id));
    // Delivered: nothing more is wanted for it.
    assert_eq!(
        s.submit(a[0].lease_id, 1, result(&p, a[0].unit, 0.5)),
        Ok(Submitted::Accepted)
    );
    assert!(!s.is_lapsed_and_wanted(a[0].lease_id));
    assert!(s.is_lapsed_and_wanted(a[1].lease_id));
    // A canceled job wants no result; an id never issued is not lapsed.
    s.cancel(2);
    assert!(!s.is_lapsed_and_wanted(b[0].lease_id));
    assert!(!s.is_lapsed_and_wanted(999_999));
}

#[test]
fn bad_submissions_are_refused_and_change_nothing() {
    let p = plan();
    let mut s = Scheduler::new(100, 0);
    s.add_job(1, 0, p, 0..=0, 6);
    let l = s.lease(1, 0, 2);
    // A lease id never issued.
    assert_eq!(
        s.submit(999, 1, result(&p, l[0].unit, 0.5)),
        Err(SubmitError::UnknownLease(999))
    );
    // A lease for another unit.
    assert!(s
        .submit(l[0].lease_id, 1, result(&p, l[1].unit, 0.5))
        .is_err());
    // Wrong size and NaN.
    let mut r = result(&p, l[0].unit, 0.5);
    r.width -= 1;
    assert!(matches!(
        s.submit(l[0].lease_id, 1, r),
        Err(SubmitError::Invalid(_))
    ));
    let mut r = result(&p, l[0].unit, 0.5);
    r.pass_means[3][1] = f32::NAN;
    assert!(matches!(
        s.submit(l[0].lease_id, 1, r),
        Err(SubmitError::Invalid(_))
    ));
    assert_eq!(s.progress(1).unwrap().units_done, 0);
    // The genuine result still goes in.
    assert_eq!(
        s.submit(l[0].lease_id, 1, result(&p, l[0].unit, 0.5)),
        Ok(Submitted::Accepted)
    );
    assert_eq!(s.progress(1).unwrap().units_done, 1);
}

#[test]
fn a_job_completes_bit_identically_whatever_the_worker_interleaving() {
    let p = plan();
    let run = |workers: u64, seed: u64| {
        let mut s = Scheduler::new(100, 0);
        s.add_job(7, 0, p, 0..=0, 2);
        let mut now = 0;
        let mut rng = seed;
        let mut held: Vec<Lease> = Vec::new();
        while !s.is_complete(7) {
            now += 10;
            for w in 0..workers {
                held.extend(s.lease(w, now, 1));
            }
            lcg_step(&mut rng);
            // Deliver a pseudo-random held lease; sometimes drop one (a dead worker).
            if held.is_empty() {
                s.expire(now + 1000);
                continue;
            }
            let k = (rng >> 33) as usize % held.len();
            let l = held.swap_remove(k);
            if rng.is_multiple_of(5) {
                continue;
            }
            let _ = s.submit(l.lease_id, 7, result(&p, l.unit, 0.5 + l.unit.tile as f32));
            if rng.is_multiple_of(3) {
                s.expire(now + 1000);
            }
        }
        s.frame(7, 0).unwrap().image()
    };
    let a = run(1, 1);
    for (w, seed) in [(3, 2), (5, 3)] {
        let b = run(w, seed);
        assert!(a
            .mean
            .iter()
            .zip(&b.mean)
            .all(|(x, y)| x.map(f32::to_bits) == y.map(f32::to_bits)));
        assert!(a
            .variance_of_mean
            .iter()
            .zip(&b.variance_of_mean)
            .all(|(x, y)| x.map(f32::to_bits) == y.map(f32::to_bits)));
    }
}

#[test]
fn the_tail_share_halves_the_even_share_and_never_exceeds_the_request() {
    // Early: what was asked; then half the worker's share, at least one unit.
    assert_eq!(tail_share(10_000, 1, 2, 64), 64);
    assert_eq!(tail_share(100, 1, 2, 64), 25);
    assert_eq!(tail_share(7, 1, 2, 64), 2);
    assert_eq!(tail_share(1, 1, 2, 64), 1);
    // A worker's share grows with its threads (2 of 6 threads: a third, halved).
    assert_eq!(tail_share(60, 2, 6, 64), 10);
    // A worker alone gets what it asks for, also with inconsistent counts (a worker
    // not counted among the sharing ones).
    assert_eq!(tail_share(3, 2, 2, 64), 64);
    assert_eq!(tail_share(60, 4, 2, 64), 64);
    // No overflow at the extremes: half of everything.
    let half = (u64::MAX / 2) as usize;
    assert_eq!(
        tail_share(u64::MAX, u64::MAX - 1, u64::MAX, usize::MAX),
        half
    );
    // Non-increasing as the queue drains.
    let mut last = usize::MAX;
    for q in (0..500).rev() {
        let n = tail_share(q, 1, 3, 16);
        assert!(n <= last && (1..=16).contains(&n));
        last = n;
    }
}

#[test]
fn leases_shrink_to_single_units_at_the_end_of_the_queue() {
    let p = plan(); // 6 tiles x 6 passes: 36 units
    let mut s = Scheduler::new(1000, 0);
    s.add_job(1, 0, p, 0..=0, 1);
    let mut sizes = Vec::new();
    let mut leased = BTreeSet::new();
    // Two one-thread workers take turns asking for 8 units each.
    for w in (0..2).cycle() {
        let got = s.lease_among(w, 0, 8, 1, 2);
        if got.is_empty() {
            break;
        }
        sizes.push(got.len());
        for l in got {
            assert!(
                leased.insert((l.unit.tile, l.unit.first_pass)),
                "leased twice"
            );
        }
    }
    assert_eq!(leased.len(), 36);
    // 36 waiting: ceil(36 / 4) = 9, capped to the 8 asked for; then 28 -> 7, ...
    assert_eq!(sizes, [8, 7, 6, 4, 3, 2, 2, 1, 1, 1, 1]);
    // Units returned to the queue count as waiting; merged ones do not.
    let mut s = Scheduler::new(100, 0);
    s.add_job(1, 0, p, 0..=0, 1);
    let all = s.lease(5, 0, 100);
    for l in &all[..20] {
        s.submit(l.lease_id, 1, result(&p, l.unit, 0.5)).unwrap();
    }
    s.expire(1000);
    // 16 returned, shared by 2 one-thread workers: 4 each.
    assert_eq!(s.lease_among(5, 1000, 64, 1, 2).len(), 4);
}

#[test]
fn batches_cut_by_the_tail_rule_give_the_same_image() {
    let p = plan();
    let run = |batch: usize, workers: u64| {
        let mut s = Scheduler::new(100, 0);
        s.add_job(7, 0, p, 0..=0, 1);
        let mut held: Vec<Lease> = Vec::new();
        let mut round = 0u64;
        while !s.is_complete(7) {
            round += 1;
            for w in 0..workers {
                held.extend(s.lease_among(w, round, batch, 1, workers));
            }
            // The newest leases are delivered first: an order unlike the canonical one.
            while let Some(l) = held.pop() {
                let r = result(&p, l.unit, 0.5 + l.unit.tile as f32);
                s.submit(l.lease_id, 7, r).unwrap();
            }
        }
        s.frame(7, 0).unwrap().image()
    };
    let a = run(1, 1);
    for (batch, workers) in [(4, 2), (16, 3), (64, 2)] {
        let b = run(batch, workers);
        let bits = |img: &FrameImage| {
            img.mean
                .iter()
                .chain(&img.variance_of_mean)
                .flat_map(|p| p.map(f32::to_bits))
                .collect::<Vec<u32>>()
        };
        assert_eq!(bits(&a), bits(&b), "batch {batch}, {workers} workers");
    }
}

#[test]
fn cancel_stops_leasing_and_returns_outstanding_leases() {
    let p = plan();
    let mut s = Scheduler::new(100, 0);
    s.add_job(1, 0, p, 0..=0, 1);
    let l = s.lease(1, 0, 4);
    let dropped = s.cancel(1);
    assert_eq!(dropped.len(), 4);
    assert!(s.lease(1, 10, 4).is_empty());
    assert_eq!(
        s.submit(l[0].lease_id, 1, result(&p, l[0].unit, 0.5)),
        Err(SubmitError::Canceled(1))
    );
}
