//! The memory budget: frames wait for it, complete frames are released.

use super::{plan, result};
use crate::adaptive::AdaptiveFrame;
use crate::merge::FrameAccumulator;
use crate::plan::FramePlan;
use crate::schedule::{
    frame_state_bytes, frame_state_bytes_with_bias, Residency, Scheduler, Submitted,
};

#[test]
fn frames_wait_for_the_memory_budget_and_release_it_when_complete() {
    let p = plan();
    let frame = frame_state_bytes(&p, false);
    assert_eq!(frame, 40 * 30 * FrameAccumulator::BYTES_PER_PIXEL);
    let mut s = Scheduler::new(1000, 0);
    // Room for one frame and a half: three frames of job 1, then job 2, take turns.
    s.set_memory_budget(frame + frame / 2);
    s.add_job(1, 0, p, 0..=2, 2);
    s.add_job(2, 0, p, 0..=0, 2);
    assert_eq!(s.resident_bytes(), 0, "nothing is allocated before a lease");
    assert_eq!(s.residency(1, 1), Some(Residency::Pending));
    let mut order = Vec::new();
    loop {
        let ls = s.lease(1, 0, 100);
        if ls.is_empty() {
            break;
        }
        assert!(s.resident_bytes() <= frame + frame / 2);
        // Only one frame is ever live: every lease of a batch is of one frame.
        assert!(ls
            .iter()
            .all(|l| (l.job, l.unit.frame) == (ls[0].job, ls[0].unit.frame)));
        order.push((ls[0].job, ls[0].unit.frame));
        for l in &ls {
            assert_eq!(
                s.submit(l.lease_id, l.job, result(&p, l.unit, 0.5)),
                Ok(Submitted::Accepted)
            );
        }
        // The frame is complete; until its checkpoints are durable it stays.
        assert!(
            s.lease(1, 0, 100).is_empty(),
            "the next frame waits for memory"
        );
        assert!(s.release_frame(ls[0].job, ls[0].unit.frame));
        assert_eq!(s.resident_bytes(), 0);
    }
    assert_eq!(order, vec![(1, 0), (1, 1), (1, 2), (2, 0)]);
    assert!(s.is_complete(1) && s.is_complete(2));
    let pr = s.progress(1).unwrap();
    assert_eq!((pr.frames_done, pr.passes_done), (3, pr.passes_planned));
    assert_eq!(s.residency(1, 2), Some(Residency::Released));
    assert!(s.frame(1, 2).is_none());
}

/// A finished frame of a running adaptive job gives its memory back, so an
/// adaptive animation under a budget of one frame renders frame after frame (before,
/// adaptive frames stayed until the job ended and the second frame never fit).
#[test]
fn finished_adaptive_frames_are_released_and_the_next_frame_fits() {
    use crate::adaptive::{AdaptiveMode, AdaptiveSettings};
    let p = FramePlan::new(16, 8, 8, 1, 48).unwrap(); // 2 tiles, 48 passes
    for mode in [AdaptiveMode::Sequential, AdaptiveMode::Unbiased] {
        let settings = AdaptiveSettings {
            mode,
            target_error: 0.05,
            ..AdaptiveSettings::default()
        };
        let frame = frame_state_bytes(&p, true);
        let mut s = Scheduler::new(1000, 0);
        s.set_memory_budget(frame);
        s.add_adaptive_job(7, 0, p, 0..=2, 2, settings).unwrap();
        let mut order = Vec::new();
        for _ in 0..1000 {
            let ls = s.lease(1, 0, 100);
            if ls.is_empty() {
                break;
            }
            assert!(s.resident_bytes() <= frame, "{mode}: one frame at a time");
            for l in &ls {
                if order.last() != Some(&l.unit.frame) {
                    order.push(l.unit.frame);
                }
                assert_eq!(
                    s.submit(l.lease_id, 7, result(&p, l.unit, 0.5)),
                    Ok(Submitted::Accepted)
                );
            }
            let f = ls[0].unit.frame;
            if s.adaptive_frame(7, f).is_some_and(AdaptiveFrame::finished) {
                // Not before its checkpoints are durable: the caller says when.
                assert_eq!(s.residency(7, f), Some(Residency::Live));
                assert!(s.release_frame(7, f), "{mode}: frame {f}");
                assert_eq!(s.residency(7, f), Some(Residency::Released));
                assert!(s.adaptive_frame(7, f).is_none());
                assert_eq!(s.resident_bytes(), 0);
            }
        }
        assert_eq!(order, [0, 1, 2], "{mode}");
        assert!(s.is_complete(7), "{mode}");
        let pr = s.progress(7).unwrap();
        assert_eq!(pr.frames_done, 3, "{mode}");
    }
}

/// A frame released while the cursor is still inside it (one unit per lease: the
/// cursor stops at each leasable unit, so the passes past the tiles' ends are not
/// visited yet when the policy finishes) does not hold the cursor: the later frames
/// are rendered. Before the fix the job stalled after frame 0's first units.
#[test]
fn a_frame_released_ahead_of_the_cursor_does_not_stall_the_job() {
    use crate::adaptive::{AdaptiveMode, AdaptiveSettings};
    let p = FramePlan::new(16, 8, 8, 1, 48).unwrap();
    for mode in [AdaptiveMode::Sequential, AdaptiveMode::Unbiased] {
        let settings = AdaptiveSettings {
            mode,
            target_error: 0.05,
            ..AdaptiveSettings::default()
        };
        let mut s = Scheduler::new(1000, 0);
        s.set_memory_budget(frame_state_bytes(&p, true));
        s.add_adaptive_job(7, 0, p, 0..=2, 2, settings).unwrap();
        let mut order = Vec::new();
        for _ in 0..10_000 {
            let Some(l) = s.lease(1, 0, 1).pop() else {
                break;
            };
            if order.last() != Some(&l.unit.frame) {
                order.push(l.unit.frame);
            }
            assert_eq!(
                s.submit(l.lease_id, 7, result(&p, l.unit, 0.5)),
                Ok(Submitted::Accepted)
            );
            let f = l.unit.frame;
            if s.adaptive_frame(7, f).is_some_and(AdaptiveFrame::finished) {
                assert!(s.release_frame(7, f));
            }
        }
        assert_eq!(order, [0, 1, 2], "{mode}");
        assert!(s.is_complete(7), "{mode}");
    }
}

/// An unfinished adaptive frame is not released.
#[test]
fn an_unfinished_adaptive_frame_is_not_released() {
    use crate::adaptive::{AdaptiveMode, AdaptiveSettings};
    let p = FramePlan::new(16, 8, 8, 1, 48).unwrap();
    let settings = AdaptiveSettings {
        mode: AdaptiveMode::Sequential,
        target_error: 0.05,
        ..AdaptiveSettings::default()
    };
    let mut s = Scheduler::new(1000, 0);
    s.add_adaptive_job(7, 0, p, 0..=0, 2, settings).unwrap();
    let ls = s.lease(1, 0, 1);
    s.submit(ls[0].lease_id, 7, result(&p, ls[0].unit, 0.5))
        .unwrap();
    assert!(!s.release_frame(7, 0));
    assert!(!s.release_frame(7, 5), "no such frame");
    assert!(s.adaptive_frame(7, 0).is_some());
}

#[test]
fn a_late_result_for_a_released_frame_is_late_not_a_fault() {
    let p = plan();
    let mut s = Scheduler::new(10, 0);
    s.add_job(1, 0, p, 0..=0, 6);
    let first = s.lease(1, 0, 100);
    // Every lease lapses and the units go to a second worker, which completes them.
    s.expire(100);
    let second = s.lease(2, 100, 100);
    assert_eq!(first.len(), second.len());
    for l in &second {
        s.submit(l.lease_id, 1, result(&p, l.unit, 0.5)).unwrap();
    }
    assert!(s.release_frame(1, 0));
    assert!(!s.release_frame(1, 0), "released once");
    for l in &first {
        assert_eq!(
            s.submit(l.lease_id, 1, result(&p, l.unit, 0.5)),
            Ok(Submitted::Late)
        );
    }
}

#[test]
fn an_incomplete_frame_is_not_released() {
    let p = plan();
    let mut s = Scheduler::new(1000, 0);
    s.add_job(1, 0, p, 0..=0, 2);
    let ls = s.lease(1, 0, 1);
    s.submit(ls[0].lease_id, 1, result(&p, ls[0].unit, 0.5))
        .unwrap();
    assert!(!s.release_frame(1, 0));
    assert_eq!(s.residency(1, 0), Some(Residency::Live));
    assert_eq!(s.resident_bytes(), frame_state_bytes(&p, false));
    s.remove_job(1);
    assert_eq!(s.resident_bytes(), 0);
}

#[test]
fn finished_adaptive_jobs_make_room_for_waiting_ones() {
    use crate::adaptive::AdaptiveSettings;
    let p = plan();
    let adaptive = AdaptiveSettings {
        target_error: 1.0,
        ..AdaptiveSettings::default()
    };
    let mut s = Scheduler::new(1000, 0);
    s.set_memory_budget(frame_state_bytes(&p, true));
    s.add_adaptive_job(1, 0, p, 0..=0, 1, adaptive).unwrap();
    while !s.is_complete(1) {
        let ls = s.lease(1, 0, 100);
        assert!(!ls.is_empty(), "the adaptive job stalled");
        for l in ls {
            s.submit(l.lease_id, 1, result(&p, l.unit, 0.5)).unwrap();
        }
    }
    assert!(
        s.adaptive_frame(1, 0).is_some(),
        "kept while nobody needs room"
    );
    s.add_job(2, 0, p, 0..=0, 2);
    let ls = s.lease(1, 0, 100);
    assert!(!ls.is_empty(), "job 2 waits forever");
    assert!(ls.iter().all(|l| l.job == 2));
    assert!(s.is_complete(1));
    assert_eq!(s.residency(1, 0), Some(Residency::Released));
    assert!(s.adaptive_frame(1, 0).is_none());
}

/// Image encodes share the budget with merge state: a reservation that does not fit
/// beside the resident frames and the other encodes is refused (the caller waits), one
/// encode always proceeds when no other runs, a live frame waits for room that encodes
/// hold, and the high-water mark counts both.
#[test]
fn image_encodes_are_counted_in_the_memory_budget() {
    let p = plan();
    let frame = frame_state_bytes(&p, false);
    let mut s = Scheduler::new(1000, 0);
    s.set_memory_budget(2 * frame);
    s.add_job(1, 0, p, 0..=1, 2);
    assert!(!s.lease(1, 0, 1).is_empty());
    assert_eq!(s.resident_bytes(), frame);
    // Half a frame fits beside it, twice; a third does not.
    assert!(s.reserve_transient(frame / 2));
    assert!(s.reserve_transient(frame / 2));
    assert!(!s.reserve_transient(frame / 2));
    assert_eq!(s.transient_bytes(), frame);
    assert_eq!(s.memory_high_water(), 2 * frame);
    s.release_transient(frame / 2);
    s.release_transient(frame / 2);
    assert_eq!(s.transient_bytes(), 0);
    // Alone, an encode larger than what is left still proceeds.
    assert!(s.reserve_transient(3 * frame));
    assert!(!s.reserve_transient(1));
    s.release_transient(3 * frame);
    // While encodes hold the room, the job's second frame waits for it.
    assert!(s.reserve_transient(frame));
    let leased: Vec<_> = s.lease(1, 0, 100);
    assert!(
        leased.iter().all(|l| l.unit.frame == 0),
        "frame 1 went live"
    );
    s.release_transient(frame);
}

/// The frames of a vcm or ppm job also hold the merging-bias channel, 24 B per pixel in
/// the accumulator and as much again in an adaptive policy's state: counted once the
/// caller says so, for frames made live later and for one already live, and given back
/// in full when the frame is released.
#[test]
fn the_bias_channel_of_a_biased_technique_is_counted() {
    use crate::adaptive::AdaptiveSettings;
    let p = plan();
    let n = 40 * 30;
    for adaptive in [false, true] {
        let plain = frame_state_bytes(&p, adaptive);
        assert_eq!(frame_state_bytes_with_bias(&p, adaptive, false), plain);
        let biased = frame_state_bytes_with_bias(&p, adaptive, true);
        assert_eq!(biased, plain + n * if adaptive { 48 } else { 24 });
        let add = |s: &mut Scheduler, id| {
            if adaptive {
                s.add_adaptive_job(id, 0, p, 0..=0, 2, AdaptiveSettings::default())
                    .unwrap();
            } else {
                s.add_job(id, 0, p, 0..=0, 2);
            }
        };
        let mut s = Scheduler::new(1000, 0);
        // Counted before its frame is live.
        add(&mut s, 1);
        s.count_bias_channel(1);
        let mut leases = s.lease(1, 0, 100);
        assert!(!leases.is_empty());
        assert_eq!(s.resident_bytes(), biased, "adaptive {adaptive}");
        // Counted after (a resumed job's live frames): the difference is charged once.
        add(&mut s, 2);
        let more = s.lease(1, 0, 100);
        assert!(more.iter().any(|l| l.job == 2));
        leases.extend(more);
        assert_eq!(s.resident_bytes(), biased + plain);
        s.count_bias_channel(2);
        s.count_bias_channel(2);
        assert_eq!(s.resident_bytes(), 2 * biased, "adaptive {adaptive}");
        // Released in full.
        for _ in 0..100 {
            if leases.is_empty() {
                break;
            }
            for l in &leases {
                assert_eq!(
                    s.submit(l.lease_id, l.job, result(&p, l.unit, 0.5)),
                    Ok(Submitted::Accepted)
                );
            }
            leases = s.lease(1, 0, 100);
        }
        for id in [1, 2] {
            assert!(s.release_frame(id, 0), "adaptive {adaptive}: job {id}");
        }
        assert_eq!(s.resident_bytes(), 0, "adaptive {adaptive}");
    }
}
