//! Jobs resumed from their checkpoints after a restart, plain and adaptive.

use super::{deliver_random, noisy_result, plan, result};
use crate::adaptive::AdaptiveFrame;
use crate::ids::JobId;
use crate::merge::{FrameAccumulator, FrameImage, TileAccumulator};
use crate::plan::FramePlan;
use crate::schedule::{frame_state_bytes, Lease, Residency, Resumed, ResumedAdaptive, Scheduler};
use crate::stats::PixelStats;

/// Renders job 7 to completion, but "crashes" after `crash_after` submissions: the
/// merged tiles are checkpointed (as the coordinator's store does), a new scheduler is
/// built from them with the old high-water mark, and one late result of the earlier
/// run is delivered to it.
fn run_with_restart(crash_after: usize) -> (FrameImage, u64) {
    let p = plan();
    let mut s = Scheduler::new(100, 0);
    s.add_job(7, 0, p, 0..=0, 2);
    let mut submitted = 0;
    let mut late = None;
    while submitted < crash_after {
        let mut ls = s.lease(1, 0, 2);
        // Hold the last lease of the batch across the crash.
        if submitted + ls.len() > crash_after {
            late = ls.pop();
        }
        for l in ls {
            s.submit(l.lease_id, 7, result(&p, l.unit, 0.5 + l.unit.tile as f32))
                .unwrap();
            submitted += 1;
        }
        if late.is_some() {
            break;
        }
    }
    // Checkpoint what is merged, as the store would hold it.
    let mut restored = FrameAccumulator::new(p);
    for t in s.frame(7, 0).map_or(&[][..], FrameAccumulator::tiles) {
        let units: Vec<_> = t.merged_units().collect();
        let tile =
            TileAccumulator::restore(t.rect(), t.merged_passes(), t.pixels().to_vec(), &units)
                .unwrap();
        restored.restore_tile(tile).unwrap();
    }
    let high_water = s.max_issued_lease_id();
    let mut s2 = Scheduler::new(100, high_water);
    let resumed = Resumed {
        frames: 0..=0,
        restored: vec![restored],
        complete: Vec::new(),
    };
    s2.add_resumed_job(7, 0, p, resumed, 2).unwrap();
    let mut adopted = 0;
    if let Some(l) = late {
        assert!(s2.is_previous_run_lease(l.lease_id));
        s2.submit(l.lease_id, 7, result(&p, l.unit, 0.5 + l.unit.tile as f32))
            .unwrap();
        adopted += 1;
    }
    while !s2.is_complete(7) {
        let ls = s2.lease(2, 0, 3);
        assert!(!ls.is_empty(), "incomplete job with nothing to lease");
        for l in ls {
            assert!(
                l.lease_id > high_water,
                "fencing tokens repeat after a restart"
            );
            let _ = s2.submit(l.lease_id, 7, result(&p, l.unit, 0.5 + l.unit.tile as f32));
        }
    }
    (s2.frame(7, 0).unwrap().image(), adopted)
}

#[test]
fn a_resumed_job_completes_bit_identically() {
    let (reference, _) = run_with_restart(0);
    for crash_after in [1, 5, 9, 17] {
        let (image, adopted) = run_with_restart(crash_after);
        assert_eq!(adopted, 1, "crash after {crash_after}");
        assert_eq!(image, reference, "crash after {crash_after}");
    }
    // A checkpoint that does not end on a unit boundary is refused.
    let p = plan();
    let mut f = FrameAccumulator::new(p);
    let rect = p.tile(0);
    let units = [(0, 1, 0)];
    let mut px = vec![PixelStats::default(); rect.pixel_count()];
    px.iter_mut().for_each(|s| s.push([1.0; 3]));
    f.restore_tile(TileAccumulator::restore(rect, 1, px, &units).unwrap())
        .unwrap();
    let mut s = Scheduler::new(100, 0);
    let resumed = Resumed {
        frames: 0..=0,
        restored: vec![f],
        complete: Vec::new(),
    };
    assert!(s.add_resumed_job(1, 0, p, resumed, 2).is_err());
    // Units that do not tile the merged passes are refused.
    let px = vec![PixelStats::default(); rect.pixel_count()];
    assert!(TileAccumulator::restore(rect, 4, px.clone(), &[(0, 2, 0)]).is_err());
    assert!(TileAccumulator::restore(rect, 2, px, &[(1, 1, 0)]).is_err());
}

/// What a coordinator's store holds of an adaptive job at a crash: per live frame, the
/// tiles' merged state (as restored from their checkpoints) and the policy state saved
/// with it; a tile with nothing merged has no checkpoint.
fn adaptive_snapshot(
    s: &Scheduler,
    job: JobId,
    plan: FramePlan,
    frames: std::ops::RangeInclusive<u32>,
) -> Vec<(FrameAccumulator, Vec<Option<crate::AdaptiveTileCheckpoint>>)> {
    let mut out = Vec::new();
    for f in frames {
        let Some(acc) = s.frame(job, f) else {
            continue;
        };
        let policy = s.adaptive_frame(job, f).unwrap();
        let mut restored = FrameAccumulator::for_frame(plan, f);
        let mut cps = Vec::new();
        for (t, a) in acc.tiles().iter().zip(policy.tiles()) {
            let units: Vec<_> = t.merged_units().collect();
            let tile =
                TileAccumulator::restore(t.rect(), t.merged_passes(), t.pixels().to_vec(), &units)
                    .unwrap();
            restored.restore_tile(tile).unwrap();
            cps.push((t.merged_passes() > 0).then(|| a.checkpoint()));
        }
        out.push((restored, cps));
    }
    out
}

/// The adaptive settings of the resume tests.
fn resume_settings(mode: crate::adaptive::AdaptiveMode) -> crate::adaptive::AdaptiveSettings {
    crate::adaptive::AdaptiveSettings {
        mode,
        target_error: 0.05,
        min_passes: 8,
        interval: 4,
        ..crate::adaptive::AdaptiveSettings::default()
    }
}

/// Each frame of `frames` rendered by one uninterrupted adaptive frame, units of 2
/// passes: what a resumed job must end with.
fn local_adaptive_images(
    p: &FramePlan,
    frames: std::ops::RangeInclusive<u32>,
    settings: crate::adaptive::AdaptiveSettings,
) -> Vec<FrameImage> {
    frames
        .map(|f| {
            let mut local = AdaptiveFrame::new(*p, f, settings).unwrap();
            for u in p.units(f, 2) {
                local.offer(&noisy_result(p, u)).unwrap();
            }
            local.image()
        })
        .collect()
}

/// An adaptive job survives a coordinator crash at any point. The store's
/// view at the crash (merged passes and the policy state checkpointed with them;
/// buffered results and outstanding leases are lost) is resumed by a new scheduler,
/// which redoes only the lost units and ends with the image of an uninterrupted run
/// bit for bit, for both modes and crashes early, mid-decision and late, in a
/// two-frame job with one frame possibly not started.
#[test]
fn adaptive_jobs_resume_from_checkpoints_bit_identically() {
    use crate::adaptive::AdaptiveMode;
    let p = FramePlan::new(24, 16, 8, 1, 48).unwrap(); // 6 tiles
    let frames = 3..=4u32;
    for mode in [AdaptiveMode::Sequential, AdaptiveMode::Unbiased] {
        let settings = resume_settings(mode);
        let references = local_adaptive_images(&p, frames.clone(), settings);
        for (crash_at, seed) in [(5usize, 11u64), (40, 12), (90, 13), (150, 14)] {
            let mut s = Scheduler::new(100, 0);
            s.add_adaptive_job(7, 0, p, frames.clone(), 2, settings)
                .unwrap();
            let (mut now, mut rng, mut submitted) = (0u64, seed, 0usize);
            let mut held: Vec<Lease> = Vec::new();
            let mut crashed = false;
            let mut merged_before = 0u64;
            while !s.is_complete(7) {
                now += 10;
                assert!(now < 1_000_000, "{mode}: the job stalls");
                if submitted == crash_at && !crashed {
                    crashed = true;
                    merged_before = s.progress(7).unwrap().passes_done;
                    let snapshot = adaptive_snapshot(&s, 7, p, frames.clone());
                    s = Scheduler::new(100, 1_000);
                    s.add_resumed_adaptive_job(
                        7,
                        0,
                        p,
                        2,
                        ResumedAdaptive {
                            frames: frames.clone(),
                            settings,
                            restored: snapshot,
                            complete: Vec::new(),
                        },
                    )
                    .unwrap();
                    held.clear();
                    // Merged passes are restored, not rendered again.
                    assert_eq!(s.progress(7).unwrap().passes_done, merged_before);
                }
                for w in 0..3 {
                    held.extend(s.lease(w, now, 2));
                }
                if deliver_random(&mut s, 7, &p, &mut held, &mut rng, now, (7, 4)) {
                    submitted += 1;
                }
            }
            assert!(
                crashed,
                "{mode}: the job ended before the crash at {crash_at}"
            );
            assert!(
                crash_at < 10 || merged_before > 0,
                "{mode}: nothing merged before the crash at {crash_at}"
            );
            for (f, reference) in frames.clone().zip(&references) {
                let image = s.adaptive_frame(7, f).unwrap().image();
                assert_eq!(
                    &image, reference,
                    "{mode}, crash after {crash_at} results: frame {f}"
                );
            }
        }
    }
}

/// A restart releases the frames its restored policy had finished. The
/// store keeps a released frame's checkpoints, so a restart finds every frame the job
/// finished; restored live, they held the memory budget until the job ended (under a
/// budget of one frame the frame in progress came back beyond it, and an adaptive job
/// had to fit the budget with all its frames). Here frame 0 comes back released,
/// frame 1 live, and the job ends with the images of an uninterrupted run, one frame
/// in memory at a time, never leasing frame 0 again.
#[test]
fn a_resumed_adaptive_job_releases_its_finished_frames() {
    use crate::adaptive::AdaptiveMode;
    let p = FramePlan::new(24, 16, 8, 1, 48).unwrap(); // 6 tiles
    let frames = 0..=2u32;
    let budget = frame_state_bytes(&p, true);
    for mode in [AdaptiveMode::Sequential, AdaptiveMode::Unbiased] {
        let settings = resume_settings(mode);
        let references = local_adaptive_images(&p, frames.clone(), settings);
        // One unit at a time until frame 0 is released and frame 1 has merged passes.
        let mut s = Scheduler::new(100, 0);
        s.set_memory_budget(budget);
        s.add_adaptive_job(7, 0, p, frames.clone(), 2, settings)
            .unwrap();
        while s.residency(7, 0) != Some(Residency::Released)
            || s.frame(7, 1).is_none_or(|f| f.merged_pass_count() == 0)
        {
            let l = s.lease(1, 0, 1).pop().expect("the job has work");
            s.submit(l.lease_id, 7, noisy_result(&p, l.unit)).unwrap();
            if s.adaptive_frame(7, 0).is_some_and(AdaptiveFrame::finished) {
                assert!(s.release_frame(7, 0));
            }
        }
        let restored = adaptive_snapshot(&s, 7, p, frames.clone());
        assert_eq!(restored.len(), 1, "{mode}: frame 1 only");
        let resumed = |complete: Vec<u32>| ResumedAdaptive {
            frames: frames.clone(),
            settings,
            restored: restored.clone(),
            complete,
        };
        let err = Scheduler::new(100, 0)
            .add_resumed_adaptive_job(7, 0, p, 2, resumed(vec![0, 1]))
            .unwrap_err();
        assert!(
            err.contains("frame 1 is both finished and in progress"),
            "{err}"
        );
        let err = Scheduler::new(100, 0)
            .add_resumed_adaptive_job(7, 0, p, 2, resumed(vec![3]))
            .unwrap_err();
        assert!(err.contains("frame 3 is outside the job"), "{err}");

        let mut s = Scheduler::new(100, 0);
        s.set_memory_budget(budget);
        s.add_resumed_adaptive_job(7, 0, p, 2, resumed(vec![0]))
            .unwrap();
        assert_eq!(s.residency(7, 0), Some(Residency::Released), "{mode}");
        assert!(s.adaptive_frame(7, 0).is_none(), "{mode}");
        assert_eq!(s.resident_bytes(), budget, "{mode}: frame 1 alone");
        let mut order = Vec::new();
        for _ in 0..10_000 {
            let Some(l) = s.lease(1, 0, 1).pop() else {
                break;
            };
            let f = l.unit.frame;
            if order.last() != Some(&f) {
                order.push(f);
            }
            s.submit(l.lease_id, 7, noisy_result(&p, l.unit)).unwrap();
            assert!(s.resident_bytes() <= budget, "{mode}: one frame at a time");
            if let Some(a) = s.adaptive_frame(7, f).filter(|a| a.finished()) {
                assert_eq!(a.image(), references[f as usize], "{mode}: frame {f}");
                assert!(s.release_frame(7, f));
            }
        }
        assert_eq!(order, [1, 2], "{mode}");
        assert!(s.is_complete(7), "{mode}");
        assert_eq!(s.progress(7).unwrap().frames_done, 3, "{mode}");
    }
}

/// A restored policy state that its tile's merged passes contradict is refused.
#[test]
fn a_policy_state_out_of_step_with_its_tile_is_refused() {
    use crate::adaptive::{AdaptiveMode, AdaptiveSettings};
    let p = FramePlan::new(16, 8, 8, 1, 48).unwrap(); // 2 tiles
    let settings = AdaptiveSettings {
        mode: AdaptiveMode::Sequential,
        target_error: 0.05,
        ..AdaptiveSettings::default()
    };
    let mut s = Scheduler::new(100, 0);
    s.add_adaptive_job(7, 0, p, 0..=0, 2, settings).unwrap();
    // Tile 1 (noisy) takes its first 4 passes.
    for _ in 0..8 {
        for l in s.lease(0, 0, 4) {
            let _ = s.submit(l.lease_id, 7, noisy_result(&p, l.unit));
        }
    }
    let good = adaptive_snapshot(&s, 7, p, 0..=0);
    assert!(Scheduler::new(100, 0)
        .add_resumed_adaptive_job(
            7,
            0,
            p,
            2,
            ResumedAdaptive {
                frames: 0..=0,
                settings,
                restored: good.clone(),
                complete: Vec::new(),
            }
        )
        .is_ok());
    // The policy state of an older checkpoint beside newer merged passes.
    let mut stale = good;
    let mut fresh = AdaptiveFrame::new(p, 0, settings).unwrap();
    for u in p
        .units(0, 2)
        .into_iter()
        .filter(|u| u.tile == 1 && u.first_pass < 2)
    {
        fresh.offer(&noisy_result(&p, u)).unwrap();
    }
    stale[0].1[1] = Some(fresh.tile(1).unwrap().checkpoint());
    let err = Scheduler::new(100, 0)
        .add_resumed_adaptive_job(
            7,
            0,
            p,
            2,
            ResumedAdaptive {
                frames: 0..=0,
                settings,
                restored: stale,
                complete: Vec::new(),
            },
        )
        .unwrap_err();
    assert!(err.contains("frame 0 tile 1"), "{err}");
}
