//! The pixel work of adaptive frames on synthetic pass values (fixed seeds): stopped
//! pixels count nothing, a few slow pixels carry the work left, the predicted work holds
//! what the frame then takes, and what cannot be predicted says so.

use super::*;
use crate::quote::{job_eta, AdaptiveEta, EtaSample, EtaTrend, JobProgress, TailClass};
use crate::test_util::Rng;
use crate::{AdaptiveFrame, AdaptiveSettings, FramePlan, UnitResult};

/// A sequential frame of `w` x `h` pixels in tiles of 16, target `target`, at most
/// `passes` passes (decisions at 8, then every 4).
fn sequential(w: u32, h: u32, passes: u32, target: f64) -> AdaptiveFrame {
    let plan = FramePlan::new(w, h, 16, 1, passes).unwrap();
    let settings = AdaptiveSettings {
        mode: AdaptiveMode::Sequential,
        target_error: target,
        ..Default::default()
    };
    AdaptiveFrame::new(plan, 0, settings).unwrap()
}

/// Renders rounds of `frame` (each tile's next chunk of passes) until it is finished or
/// `stop` says so; pixel `(x, y)`'s pass value is `draw(rng, x, y)`.
fn render(
    frame: &mut AdaptiveFrame,
    rng: &mut Rng,
    draw: impl Fn(&mut Rng, u32, u32) -> f64,
    stop: impl Fn(&AdaptiveFrame) -> bool,
) {
    while !stop(frame) {
        let units = frame.next_round();
        if units.is_empty() {
            return;
        }
        for unit in units {
            let rect = frame.plan().tile(unit.tile);
            let mut pass_means = Vec::with_capacity(rect.pixel_count() * unit.pass_count as usize);
            for _ in 0..unit.pass_count {
                for y in 0..rect.height {
                    for x in 0..rect.width {
                        let v = draw(rng, rect.x0 + x, rect.y0 + y) as f32;
                        pass_means.push([v; 3]);
                    }
                }
            }
            let r = UnitResult {
                unit,
                width: rect.width,
                height: rect.height,
                pass_means,
                rejected_samples: 0,
                bias: None,
            };
            frame.offer(&r).unwrap();
        }
    }
}

fn consumed(frame: &AdaptiveFrame) -> u32 {
    frame
        .tiles()
        .iter()
        .map(|t| t.consumed_passes())
        .max()
        .unwrap_or(0)
}

fn traced(frame: &AdaptiveFrame) -> f64 {
    frame
        .tiles()
        .iter()
        .flat_map(|t| t.traced_passes())
        .map(f64::from)
        .sum()
}

/// A positive pass value of mean 1 and relative spread about `sd` (log-normal: renderers
/// refuse negative radiance).
fn positive(r: &mut Rng, sd: f64) -> f64 {
    let s = (1.0 + sd * sd).ln().sqrt();
    (s * r.normal() - 0.5 * s * s).exp()
}

/// The ETA of `work` at one pixel-pass per second, measured now.
fn eta_of(work: PixelWork, trend: EtaTrend) -> crate::quote::JobEta {
    let a = AdaptiveEta::measure(work, work.done, &[], 0.0);
    assert_eq!(a.rate, 1.0);
    a.eta(trend, None)
}

/// A tile of constant pixels stops at its first decision and adds nothing to the work
/// left; the noisy tile beside it carries all of it, each of its pixels up to the
/// boundary its own law names (per-pass relative error 0.6, target 0.05: 144 passes).
#[test]
fn pixels_that_stopped_count_nothing() {
    let mut frame = sequential(32, 16, 256, 0.05);
    let mut rng = Rng::new(0x5709);
    let draw = |r: &mut Rng, x: u32, _| 0.5 * if x < 16 { 1.0 } else { positive(r, 0.6) };
    render(&mut frame, &mut rng, draw, |f| consumed(f) >= 12);
    assert!(frame.tiles()[0].finished());
    let work = pixel_work(&frame, 0.0);
    assert_eq!(work.active, 256, "{work:?}");
    assert_eq!(work.unknown, 0);
    // Traced: the quiet tile's 8 passes and the noisy one's 12.
    assert_eq!(work.done, 256.0 * 8.0 + 256.0 * 12.0);
    assert_eq!(work.budget, 256.0 * (256.0 - 12.0));
    assert_eq!(work.left_heavy, work.left);
    // About 144 - 12 passes per pixel; the neighbourhood's largest law pushes it up.
    let per_pixel = work.left / 256.0;
    assert!((132.0..260.0).contains(&per_pixel), "{per_pixel}");
    // The quiet tile alone: nothing left.
    let mut quiet = sequential(16, 16, 256, 0.05);
    render(&mut quiet, &mut rng, |_, _, _| 0.5, |_| false);
    let w = pixel_work(&quiet, 0.0);
    assert_eq!((w.left, w.active, w.budget), (0.0, 0, 0.0));
    assert_eq!(eta_of(w, EtaTrend::default()).seconds, Some(0.0));
}

/// Three noisy pixels in a quiet tile (per-pass relative error 0.5 against 0.01): at
/// pass 12 the quiet pixels away from them have stopped, and the work left is the three
/// 3x3 neighbourhoods' (27 pixels) up to about 100 passes; rendered on, the frame takes
/// work within the 95% interval.
#[test]
fn a_few_slow_pixels_carry_the_work_left() {
    let slow = [(3, 3), (12, 4), (8, 12)];
    let mut frame = sequential(16, 16, 1024, 0.05);
    let mut rng = Rng::new(0x510e);
    let draw = |r: &mut Rng, x: u32, y: u32| {
        let sd = if slow.contains(&(x, y)) { 0.5 } else { 0.01 };
        positive(r, sd)
    };
    render(&mut frame, &mut rng, draw, |f| consumed(f) >= 12);
    let work = pixel_work(&frame, 0.0);
    assert_eq!(work.active, 27, "{work:?}");
    let per_pixel = work.left / 27.0;
    assert!((40.0..200.0).contains(&per_pixel), "{per_pixel}");
    let eta = eta_of(work, EtaTrend::default());
    assert_eq!(eta.tail_class, Some(TailClass::Light));
    let (low, high) = eta.interval.unwrap();
    let before = traced(&frame);
    render(&mut frame, &mut rng, draw, |_| false);
    let took = traced(&frame) - before;
    assert!(
        low <= took && took <= high,
        "{took} pixel-passes against [{low:.0}, {high:.0}], predicted {:.0}",
        eta.seconds.unwrap()
    );
}

/// A frame of pixels whose noise varies (per-pass relative error 0.05 to 0.2, log-normal
/// over the pixels) at target 0.01: at pass 16 the work left predicted pixel by pixel
/// holds what the frame then takes, within its interval and 25%. The image law (the image
/// estimate extrapolated by 1/sqrt(work), what the ETA was) says much less: the image's RMS
/// reaches the target long before its noisiest pixels do.
#[test]
fn the_work_left_holds_what_the_frame_then_takes() {
    let mut frame = sequential(64, 64, 1024, 0.01);
    let mut rng = Rng::new(0xf1_9a15);
    let level: Vec<f64> = (0..64 * 64)
        .map(|_| 0.05 * (0.6 * rng.normal()).exp().clamp(1.0, 4.0))
        .collect();
    let draw = |r: &mut Rng, x: u32, y: u32| positive(r, level[(y * 64 + x) as usize]);
    render(&mut frame, &mut rng, draw, |f| consumed(f) >= 16);
    let work = pixel_work(&frame, 0.0);
    let eta = eta_of(work, EtaTrend::default());
    let (low, high) = eta.interval.unwrap();
    let point = eta.seconds.unwrap();
    // The image law: the image error after `done` pixel-passes.
    let image = frame.image_error();
    let image_law = work.done * ((image / 0.01).powi(2) - 1.0);
    let before = traced(&frame);
    render(&mut frame, &mut rng, draw, |_| false);
    let took = traced(&frame) - before;
    assert!(
        low <= took && took <= high,
        "{took} against [{low:.0}, {high:.0}]"
    );
    assert!(
        (point / took - 1.0).abs() < 0.25,
        "{point:.0} against {took}"
    );
    assert!(
        image_law < 0.75 * took,
        "image law {image_law:.0}, took {took}"
    );
}

/// A growing per-pass error (growth 2.2 from half the work) is not predictable: no point
/// ETA, the reason, an interval from the pixels' laws to the sample budget; an unbiased
/// frame whose pilot has not decided is not predictable yet, and says why.
#[test]
fn what_cannot_be_predicted_says_so() {
    let mut frame = sequential(16, 16, 256, 0.05);
    let mut rng = Rng::new(0x4ea7);
    render(
        &mut frame,
        &mut rng,
        |r, _, _| positive(r, 0.3),
        |f| consumed(f) >= 12,
    );
    let work = pixel_work(&frame, 0.0);
    let grew = EtaTrend {
        rel_m: Some(0.1),
        growth: Some(2.2),
    };
    let eta = eta_of(work, grew);
    assert_eq!(eta.tail_class, Some(TailClass::Unpredictable));
    assert_eq!(eta.seconds, None);
    assert!(eta
        .note
        .unwrap()
        .starts_with("not predictable from the passes so far"));
    let (low, high) = eta.interval.unwrap();
    assert_eq!(high, work.budget);
    assert!(low <= work.left && low > 0.0, "{low} {work:?}");
    // Heavy (growth 1.5): the point stays the laws', the high end grows.
    let heavy = EtaTrend {
        rel_m: Some(0.1),
        growth: Some(1.5),
    };
    let light = eta_of(work, EtaTrend::default());
    let w_heavy = pixel_work(&frame, 1.5f64.log2());
    assert!(w_heavy.left_heavy > 1.5 * w_heavy.left, "{w_heavy:?}");
    let eta = eta_of(w_heavy, heavy);
    assert_eq!(eta.tail_class, Some(TailClass::Heavy));
    assert_eq!(eta.seconds, light.seconds);
    assert!(eta.interval.unwrap().1 > light.interval.unwrap().1);
    // Unbiased, mid-pilot (4 of its 8 passes): every pixel unknown.
    let plan = FramePlan::new(16, 16, 16, 1, 64).unwrap();
    let settings = AdaptiveSettings {
        mode: AdaptiveMode::Unbiased,
        target_error: 0.05,
        ..Default::default()
    };
    let mut pilot = AdaptiveFrame::new(plan, 0, settings).unwrap();
    render(
        &mut pilot,
        &mut rng,
        |r, _, _| positive(r, 0.3),
        |f| consumed(f) >= 4,
    );
    let w = pixel_work(&pilot, 0.0);
    assert_eq!((w.unknown, w.active), (256, 256));
    let eta = eta_of(w, EtaTrend::default());
    assert_eq!(eta.seconds, None);
    assert!(eta.note.unwrap().starts_with("not predictable yet"));
    // The low end counts them at their soonest stop (the pilot's 8 passes and 4 fresh:
    // 8 more each), not at the plan's end (60 more).
    assert_eq!(w.left_floor, 256.0 * 8.0);
    // The interval: nothing known bounds it from below.
    assert_eq!(eta.interval, Some((0.0, w.budget)));
    // After the pilot: exact, the fresh passes the pilot planned.
    render(
        &mut pilot,
        &mut rng,
        |r, _, _| positive(r, 0.3),
        |f| consumed(f) >= 8,
    );
    let w = pixel_work(&pilot, 0.0);
    assert_eq!(w.unknown, 0);
    let planned: f64 = pilot.tiles()[0]
        .fresh_passes_needed()
        .map(|n| f64::from(8 + n))
        .sum();
    assert_eq!(w.left, planned - w.done);
    assert_eq!(w.left_var, 0.0);
}

/// The rate is read over the later half of the job so far (the start-up before the first
/// result left out), its spread from the third and fourth quarters, the drift from the
/// total predicted at half the time.
#[test]
fn the_rate_is_measured_over_the_later_half() {
    let samples: Vec<EtaSample> = [
        (1.0, 0.0, 900.0),
        (2.0, 100.0, 1000.0),
        (3.0, 200.0, 1000.0),
    ]
    .iter()
    .map(|&(t, done, total)| EtaSample {
        elapsed_seconds: t,
        done,
        total,
    })
    .collect();
    let work = PixelWork {
        done: 400.0,
        left: 800.0,
        left_mean: 800.0,
        budget: 4000.0,
        active: 10,
        ..Default::default()
    };
    let a = AdaptiveEta::measure(work, 4.0, &samples, 0.5);
    // From t = 2 (100 done) to t = 4 (400): 150 per second, not 400 / 4 = 100.
    assert_eq!(a.rate, 150.0);
    // Third quarter (2 to 3): 100 per second; fourth (3 to 4): 200.
    assert!((a.rate_spread - 2f64.ln()).abs() < 1e-12);
    assert_eq!(a.drift, 200.0);
    let eta = a.eta(EtaTrend::default(), None);
    // 800 / 150 less the half second since.
    assert!((eta.seconds.unwrap() - (800.0 / 150.0 - 0.5)).abs() < 1e-9);
    let (low, high) = eta.interval.unwrap();
    assert!(low < eta.seconds.unwrap() && eta.seconds.unwrap() < high);
    // A time limit caps every figure.
    let limited = a.eta(EtaTrend::default(), Some(2.0));
    assert_eq!(limited.seconds, Some(2.0));
    assert_eq!(limited.interval.unwrap().1, 2.0);
}

/// Before any pixel-pass is counted the rate is zero: not predictable, and the interval
/// ends at the plan's passes at the job's pass rate rather than at infinity (which the
/// status would send as `null`, an interval without an upper end).
#[test]
fn no_rate_yet_ends_the_interval_at_the_plan() {
    let work = PixelWork {
        left: 800.0,
        left_mean: 800.0,
        budget: 4000.0,
        active: 10,
        unknown: 10,
        ..Default::default()
    };
    let a = AdaptiveEta::measure(work, 2.0, &[], 0.0);
    assert_eq!(a.rate, 0.0);
    let p = JobProgress {
        elapsed_seconds: 2.0,
        passes_done: 4,
        passes_planned: 64,
        error: None,
        stopping_target: Some(0.05),
        time_limit_left_seconds: None,
        trend: None,
        adaptive: Some(a),
    };
    let eta = job_eta(&p).unwrap();
    assert_eq!(eta.seconds, None);
    assert_eq!(eta.tail_class, Some(TailClass::Unpredictable));
    // 60 passes left at 2 per second.
    assert_eq!(eta.interval, Some((0.0, 30.0)));
    assert!(eta.note.unwrap().contains("no rate measured"));
}
