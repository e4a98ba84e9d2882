//! Tests of the adaptive policy: equivalence with the plain merge when off, determinism,
//! the decisions, and the bias of sequential stopping against the unbiased two-stage mode.

use super::*;
use crate::merge::TileAccumulator;
use crate::test_util::Rng;

fn unit(tile: u32, first_pass: u32, pass_count: u32) -> WorkUnit {
    WorkUnit {
        frame: 0,
        tile,
        first_pass,
        pass_count,
    }
}

/// A result whose pass means come from `f(pass, pixel)`.
fn result_from(rect: TileRect, u: WorkUnit, f: &dyn Fn(u32, usize) -> f32) -> UnitResult {
    let mut pass_means = Vec::new();
    for pass in u.first_pass..u.first_pass + u.pass_count {
        for i in 0..rect.pixel_count() {
            let v = f(pass, i);
            pass_means.push([v, v * 0.5, v * 0.25]);
        }
    }
    UnitResult {
        unit: u,
        width: rect.width,
        height: rect.height,
        pass_means,
        rejected_samples: 0,
        bias: None,
    }
}

/// An irregular, reproducible pass mean with occasional fireflies.
fn noisy(tile: u32, pass: u32, pixel: usize) -> f32 {
    let mut rng = Rng::new((u64::from(tile) << 40) ^ (u64::from(pass) << 20) ^ pixel as u64);
    let base = 0.2 + 0.8 * rng.uniform();
    let firefly = if rng.uniform() < 0.03 { 50.0 } else { 0.0 };
    (base + firefly) as f32
}

fn seq(target: f64) -> AdaptiveSettings {
    AdaptiveSettings {
        mode: AdaptiveMode::Sequential,
        target_error: target,
        ..Default::default()
    }
}

fn unb(target: f64) -> AdaptiveSettings {
    AdaptiveSettings {
        mode: AdaptiveMode::Unbiased,
        target_error: target,
        ..Default::default()
    }
}

#[test]
fn off_matches_the_plain_merge_bit_for_bit() {
    let plan = FramePlan::new(13, 9, 8, 2, 10).unwrap();
    let rect = plan.tile(1);
    let mut plain = TileAccumulator::new(rect);
    let mut off = AdaptiveTile::new(rect, AdaptiveSettings::default(), plan.passes);
    let mut units: Vec<WorkUnit> = (0..5).map(|c| unit(1, 2 * c, 2)).collect();
    Rng::new(3).shuffle(&mut units);
    for u in units {
        let r = result_from(rect, u, &|p, i| noisy(1, p, i));
        off.offer(&r);
        plain.offer(r).unwrap();
    }
    assert!(off.finished());
    assert_eq!(off.pixels(), plain.pixels());
    assert!(off.traced_passes().all(|t| t == 10));
}

/// An adaptive frame fed every unit of `plan` split `per` passes a unit, in plan order or
/// shuffled by `seed`, each unit's result made by `result`; checked finished.
fn split_frame(
    plan: FramePlan,
    settings: AdaptiveSettings,
    per: u32,
    seed: Option<u64>,
    result: impl Fn(TileRect, WorkUnit) -> UnitResult,
) -> AdaptiveFrame {
    let mut frame = AdaptiveFrame::new(plan, 0, settings).unwrap();
    let mut units = plan.units(0, per);
    if let Some(s) = seed {
        Rng::new(s).shuffle(&mut units);
    }
    for u in units {
        frame.offer(&result(plan.tile(u.tile), u)).unwrap();
    }
    assert!(frame.finished());
    frame
}

/// The adaptive state is a function of the pass data only: any unit split and arrival
/// order gives the same bits (ARCHITECTURE.md §2).
#[test]
fn decisions_do_not_depend_on_unit_split_or_order() {
    let plan = FramePlan::new(20, 12, 8, 1, 64).unwrap();
    for settings in [seq(0.15), unb(0.15)] {
        let run = |per: u32, seed: Option<u64>| {
            let frame = split_frame(plan, settings, per, seed, |rect, u| {
                result_from(rect, u, &|p, i| noisy(u.tile, p, i))
            });
            let img = frame.image();
            let mut bits: Vec<u32> = img.mean.iter().flatten().map(|v| v.to_bits()).collect();
            bits.extend(img.variance_of_mean.iter().flatten().map(|v| v.to_bits()));
            bits.extend(&img.passes);
            bits.extend(&img.samples);
            bits
        };
        let reference = run(1, None);
        for (per, seed) in [(4, Some(1)), (3, Some(2)), (64, None), (7, Some(9))] {
            assert!(run(per, seed) == reference, "{settings:?} per {per}");
        }
        // And adaptivity did something: not every pixel took every pass.
        let frame = {
            let mut f = AdaptiveFrame::new(plan, 0, settings).unwrap();
            for u in plan.units(0, 4) {
                let rect = plan.tile(u.tile);
                f.offer(&result_from(rect, u, &|p, i| noisy(u.tile, p, i)))
                    .unwrap();
            }
            f
        };
        let (_, lo, hi) = frame.samples_per_pixel();
        assert!(lo < hi && hi <= 64, "{settings:?}: {lo}..{hi}");
    }
}

#[test]
fn boundaries() {
    let s = seq(0.1);
    let b: Vec<u32> = (0..30).filter(|&p| s.is_boundary(p)).collect();
    assert_eq!(b, [8, 12, 16, 20, 24, 28]);
    assert_eq!(s.next_boundary(0), Some(8));
    assert_eq!(s.next_boundary(8), Some(12));
    assert_eq!(s.next_boundary(9), Some(12));
    assert_eq!(s.next_boundary(u32::MAX - 1), None);
    let u = unb(0.1);
    assert_eq!((0..100).filter(|&p| u.is_boundary(p)).count(), 1);
    assert_eq!(u.next_boundary(3), Some(8));
    assert_eq!(u.next_boundary(8), None);
    assert_eq!(AdaptiveSettings::default().next_boundary(0), None);
}

#[test]
fn validation_names_the_problem() {
    assert_eq!(seq(0.0).validate(64), Err(AdaptiveError::Target(0.0)));
    assert!(seq(f64::NAN).validate(64).is_err());
    let mut s = seq(0.1);
    s.min_passes = 1;
    assert_eq!(s.validate(64), Err(AdaptiveError::MinPasses(1)));
    let mut s = seq(0.1);
    s.interval = 0;
    assert_eq!(s.validate(64), Err(AdaptiveError::Interval));
    let e = unb(0.1).validate(10).unwrap_err();
    assert!(e.to_string().contains("at least 12 passes"), "{e}");
    assert!(unb(0.1).validate(12).is_ok());
    // Off ignores the rest.
    let s = AdaptiveSettings {
        target_error: -1.0,
        ..Default::default()
    };
    assert!(s.validate(1).is_ok());
    let plan = FramePlan::new(8, 8, 8, 1, 4).unwrap();
    assert!(AdaptiveFrame::new(plan, 0, unb(0.1)).is_err());
}

#[test]
fn adaptive_plan_has_many_passes() {
    for (spp, s, k) in [
        (1, 1, 1),
        (64, 2, 32),
        (256, 8, 32),
        (1024, 16, 64),
        (100, 2, 50),
    ] {
        let p = adaptive_plan(8, 8, spp, 8).unwrap();
        assert_eq!((p.samples_per_pass, p.passes), (s, k), "spp {spp}");
    }
    assert!(adaptive_plan(8, 8, 0, 8).is_err());
}

/// Sequential: a constant pixel stops at the first boundary; a noisy pixel keeps its
/// 3x3 neighbourhood going (dilation) but not pixels two away.
#[test]
fn sequential_stops_converged_pixels_with_dilation() {
    let plan = FramePlan::new(6, 1, 8, 1, 40).unwrap();
    let rect = plan.tile(0);
    let mut t = AdaptiveTile::new(rect, seq(0.05), plan.passes);
    // Pixel 0 alternates 0 / 2 (relative error ~ 1/sqrt(n)); the others are constant.
    let f = |p: u32, i: usize| {
        if i == 0 {
            (p % 2 * 2) as f32
        } else {
            1.0
        }
    };
    t.offer(&result_from(rect, unit(0, 0, 7), &f));
    assert_eq!(t.lease_horizon(), 8);
    assert_eq!(t.next_chunk(), Some((7, 1)));
    t.offer(&result_from(rect, unit(0, 7, 1), &f));
    // At pass 8: pixels 0 and 1 active (1 by dilation), 2..6 stopped.
    let active: Vec<bool> = (0..6).map(|i| t.wants(i, 8)).collect();
    assert_eq!(active, [true, true, false, false, false, false]);
    assert_eq!(t.active_pixels(), 2);
    assert_eq!(t.lease_horizon(), 12);
    // Run to the end: pixel 0 never reaches 5% with 40 passes (rel = 1/sqrt(n) ~ 0.16).
    t.offer(&result_from(rect, unit(0, 8, 32), &f));
    assert!(t.finished());
    let traced: Vec<u32> = t.traced_passes().collect();
    assert_eq!(traced, [40, 40, 8, 8, 8, 8]);
    assert_eq!(t.pixels()[0].passes, 40);
    assert_eq!(t.pixels()[0].mean[0], 1.0);
    // Stopped pixels keep exactly their first 8 passes.
    assert_eq!(t.pixels()[3].passes, 8);
}

/// Unbiased: the pilot fixes n = ceil(s² / (target (lum + eps))²) and is discarded.
#[test]
fn unbiased_discards_the_pilot_and_takes_the_planned_fresh_passes() {
    let plan = FramePlan::new(2, 1, 8, 1, 100).unwrap();
    let rect = plan.tile(0);
    let target = 0.1;
    let mut t = AdaptiveTile::new(rect, unb(target), plan.passes);
    // Pixel 0: pilot alternates 0.5 / 1.5 (lum mean 1, per-pass variance 8/7 * 0.25 in
    // luminance units of the (v, v/2, v/4) colour), then a constant 7.0 in fresh passes.
    // Pixel 1: constant 1.0; alone it would need the minimum, 4, but it pools its
    // neighbour's variance: half of pixel 0's (the mean over the 2x1 tile).
    let f = |p: u32, i: usize| match (i, p < 8) {
        (0, true) => 0.5 + (p % 2) as f32,
        (0, false) => 7.0,
        _ => 1.0,
    };
    t.offer(&result_from(rect, unit(0, 0, 8), &f));
    let lum = |v: f64| crate::stats::luminance([v, v * 0.5, v * 0.25]);
    let s2 = lum(0.5).powi(2) * 8.0 / 7.0;
    // Relative deviations: pixel 0 its own, pixel 1 the pooled half of its variance; each
    // is given d · mean(d) / target² (the optimal allocation in the tile).
    let d = [s2.sqrt(), (0.5 * s2).sqrt()].map(|x| x / (lum(1.0) + REL_EPS));
    let mean = (d[0] + d[1]) / 2.0;
    let [expected, pooled] = d.map(|d| (d * mean / (target * target)).ceil() as u32);
    assert!(pooled > 4 && pooled < expected, "{pooled}");
    // The tile's RMS error by the pilot is then at most the target.
    let rms =
        ((d[0].powi(2) / f64::from(expected) + d[1].powi(2) / f64::from(pooled)) / 2.0).sqrt();
    assert!(rms <= target && rms > 0.9 * target, "{rms}");
    let needed: Vec<u32> = t.fresh_passes_needed().collect();
    assert_eq!(needed, [expected, pooled]);
    assert!(t.pixels().iter().all(|s| s.passes == 0), "pilot discarded");
    assert_eq!(t.end_pass(), 8 + expected);
    assert_eq!(t.lease_horizon(), 8 + expected);
    assert!(t.wants(0, 8 + expected - 1) && !t.wants(0, 8 + expected));
    assert!(t.wants(1, 8 + pooled - 1) && !t.wants(1, 8 + pooled));
    t.offer(&result_from(rect, unit(0, 8, 92), &f));
    assert!(t.finished());
    // Only fresh passes: pixel 0's mean is exactly 7 (no trace of the pilot).
    assert_eq!(t.pixels()[0].mean[0], 7.0);
    assert_eq!(t.pixels()[0].passes, expected);
    assert_eq!(t.pixels()[1].passes, pooled);
    let traced: Vec<u32> = t.traced_passes().collect();
    assert_eq!(traced, [8 + expected, 8 + pooled]);
}

/// Unbiased: a pixel's pilot variance is pooled over its 3x3 neighbourhood within the
/// tile, so a quiet pixel next to a noisy one is not given the minimum, and pixels two
/// away, or across a tile border, are not affected.
#[test]
fn unbiased_pools_the_pilot_over_the_neighbourhood_in_the_tile() {
    // Two 4x1 tiles; pixel 1 of tile 0 is noisy in the pilot, every other pixel constant.
    let plan = FramePlan::new(8, 1, 4, 1, 100).unwrap();
    let target = 0.1;
    let f = |p: u32, i: usize| if i == 1 { 0.5 + (p % 2) as f32 } else { 1.0 };
    let mut t0 = AdaptiveTile::new(plan.tile(0), unb(target), plan.passes);
    t0.offer(&result_from(plan.tile(0), unit(0, 0, 8), &f));
    let needed: Vec<u32> = t0.fresh_passes_needed().collect();
    // Pixel 1 pools over pixels 0..=2 (its own variance is the largest: kept); pixels 0
    // and 2 pool over 2 and 3 pixels holding pixel 1; pixel 3 is two away.
    let lum = |v: f64| crate::stats::luminance([v, v * 0.5, v * 0.25]);
    let s2 = lum(0.5).powi(2) * 8.0 / 7.0;
    let d = [s2 / 2.0, s2, s2 / 3.0, 0.0].map(|v| v.sqrt() / (lum(1.0) + REL_EPS));
    let mean = d.iter().sum::<f64>() / 4.0;
    let n = |d: f64| ((d * mean / (target * target)).ceil() as u32).max(4);
    assert_eq!(needed, [n(d[0]), n(d[1]), n(d[2]), 4]);
    assert!(needed[1] > needed[0] && needed[0] > needed[2] && needed[2] > 4);
    // The same pixels in tile 1 are all constant: tile 0's pilot does not reach it.
    let mut t1 = AdaptiveTile::new(plan.tile(1), unb(target), plan.passes);
    t1.offer(&result_from(plan.tile(1), unit(1, 0, 8), &|_, _| 1.0));
    assert!(t1.fresh_passes_needed().all(|n| n == 4));
    assert_eq!(pooled_pilot_variance(&[], 0, 0, 0, 0), 0.0);
}

#[test]
fn fresh_passes_are_clamped() {
    // max(λ d, (d / cap)²): 50 · 0.2 = 10 against (0.2 / 0.2)² = 1.
    assert_eq!(fresh_passes_needed(0.2, 50.0, 0.2, 4, 50), 10);
    // The cap decides: (1 / 0.1)² = 100 against 10 · 1 = 10.
    assert_eq!(fresh_passes_needed(1.0, 10.0, 0.1, 4, 500), 100);
    assert_eq!(fresh_passes_needed(0.0, 50.0, 0.2, 4, 50), 4);
    assert_eq!(fresh_passes_needed(5.0, 50.0, 0.2, 4, 50), 50);
    assert_eq!(fresh_passes_needed(5.0, 50.0, 0.2, 4, 2), 4);
    assert_eq!(fresh_passes_needed(f64::NAN, 50.0, 0.2, 4, 50), 50);
    assert_eq!(fresh_passes_needed(0.5, f64::INFINITY, 0.2, 4, 50), 50);
}

/// The capped optimal allocation: the planned RMS error is the target, no pixel is planned
/// above `cap · target`, and without a binding cap it is Neyman's `n ∝ d` (Owen 2001,
/// section 6.2).
#[test]
fn neyman_scale_meets_the_target_and_the_cap() {
    let (t, cap) = (0.05, 2.0);
    // No pixel near the cap: λ = mean(d) / t².
    let d = [0.1, 0.2, 0.3, 0.2];
    assert!((neyman_scale(&d, t, cap) - 0.2 / (t * t)).abs() < 1e-9);
    let mut rng = Rng::new(11);
    for case in 0..200 {
        // Heavy-tailed deviations: most pixels quiet, a few very noisy.
        let d: Vec<f64> = (0..64)
            .map(|_| {
                let u = rng.uniform();
                if u < 0.05 {
                    20.0 * rng.uniform()
                } else {
                    0.05 + 0.3 * u
                }
            })
            .collect();
        let lambda = neyman_scale(&d, t, cap);
        let n: Vec<f64> = d
            .iter()
            .map(|d| (lambda * d).max((d / (cap * t)).powi(2)))
            .collect();
        let ms = d.iter().zip(&n).map(|(d, n)| d * d / n).sum::<f64>() / d.len() as f64;
        assert!(
            (ms.sqrt() / t - 1.0).abs() < 1e-9,
            "case {case}: rms {}",
            ms.sqrt()
        );
        for (d, n) in d.iter().zip(&n) {
            assert!(
                d / n.sqrt() <= cap * t * (1.0 + 1e-9),
                "case {case}: {d} {n}"
            );
        }
        // Cheaper than each pixel to the target (n = d² / t²), never dearer.
        let each: f64 = d.iter().map(|d| d * d / (t * t)).sum();
        assert!(n.iter().sum::<f64>() <= each * (1.0 + 1e-9));
    }
    assert!(neyman_scale(&[], t, cap).is_nan());
    assert_eq!(neyman_scale(&[0.0, 0.0], t, cap), 0.0);
}

#[test]
fn eta_follows_inverse_square_root() {
    assert_eq!(eta_seconds(0.02, 0.01, 10.0), Some(30.0));
    assert_eq!(eta_seconds(0.01, 0.02, 10.0), Some(0.0));
    assert_eq!(eta_seconds(0.02, 0.0, 10.0), None);
    assert_eq!(eta_seconds(f64::NAN, 0.1, 10.0), None);
    assert_eq!(eta_seconds(0.2, 0.1, 0.0), None);
}

/// A heavy-tailed pixel: each sample is `V` with probability `P`, else 0 (a caustic or a
/// small light seen through a glossy reflection). True mean `P V = 1`.
const P: f64 = 0.01;
const V: f64 = 100.0;

/// Renders one tile of the heavy-tailed integrand through the real policy, unit by unit
/// as the local renderer does (only wanted pixels are sampled; the others' values are
/// ignored), and returns the tile's mean estimate (average over pixels) and mean spp.
fn heavy_tailed_tile(settings: AdaptiveSettings, rng: &mut Rng, plan: &FramePlan) -> (f64, f64) {
    let rect = plan.tile(0);
    let s = plan.samples_per_pass;
    let mut t = AdaptiveTile::new(rect, settings, plan.passes);
    let mut means = vec![[0.0f32; 3]; rect.pixel_count() * settings.interval as usize];
    while let Some((first, count)) = t.next_chunk() {
        let n = rect.pixel_count();
        means.resize(n * count as usize, [0.0; 3]);
        for k in 0..count {
            for i in 0..n {
                let mut sum = 0.0;
                if t.wants(i, first + k) {
                    for _ in 0..s {
                        if rng.uniform() < P {
                            sum += V;
                        }
                    }
                }
                let m = (sum / f64::from(s)) as f32;
                means[k as usize * n + i] = [m; 3];
            }
        }
        let r = UnitResult {
            unit: unit(0, first, count),
            width: rect.width,
            height: rect.height,
            pass_means: std::mem::take(&mut means),
            rejected_samples: 0,
            bias: None,
        };
        t.offer(&r);
        means = r.pass_means;
    }
    let px = t.pixels();
    let mean = px.iter().map(|p| p.mean[0]).sum::<f64>() / px.len() as f64;
    let spp = t.traced_passes().map(f64::from).sum::<f64>() * f64::from(s) / px.len() as f64;
    (mean, spp)
}

/// Bias test (Jensen 2001, section 10.3): over many independent trials of an 8x8 tile of
/// heavy-tailed pixels, the sequential policy's mean is measurably off the true mean,
/// while the unbiased two-stage policy matches it within 3 standard errors.
///
/// Statistics: each trial gives one tile average (pixels within a trial are coupled by
/// dilation, trials are independent), so the standard error of the grand mean is the
/// sample standard deviation of the trial averages over sqrt(trials), and
/// `z = (grand mean - 1) / se`. Sequential must show `z < -4` (a loss of energy: pixels
/// whose first passes missed every bright sample look converged); unbiased `|z| < 3`.
/// Fixed seeds; both assertions can fail (an unbiased policy that kept the pilot, or a
/// sequential one with a huge minimum pass count, would fail one of them).
#[test]
fn sequential_is_biased_and_unbiased_is_not() {
    let plan = FramePlan::new(8, 8, 8, 4, 256).unwrap();
    let trials = 400;
    let target = 0.2;
    let mut report = Vec::new();
    for (settings, seed) in [(seq(target), 11u64), (unb(target), 12u64)] {
        let mut rng = Rng::new(seed);
        let (mut sum, mut sum2, mut spp) = (0.0, 0.0, 0.0);
        for _ in 0..trials {
            let (m, s) = heavy_tailed_tile(settings, &mut rng, &plan);
            sum += m;
            sum2 += m * m;
            spp += s;
        }
        let n = f64::from(trials);
        let mean = sum / n;
        let var = (sum2 - n * mean * mean) / (n - 1.0);
        let se = (var / n).sqrt();
        let z = (mean - P * V) / se;
        eprintln!(
            "bias test {}: mean {mean:.4} (true 1), relative bias {:+.2}% +- {:.2}% (1 se), z = {z:.2}, mean spp {:.1}",
            settings.mode,
            100.0 * (mean - 1.0),
            100.0 * se,
            spp / n
        );
        report.push((settings.mode, z));
    }
    let z_seq = report[0].1;
    let z_unb = report[1].1;
    assert!(
        z_seq < -4.0,
        "sequential shows no significant bias: z = {z_seq}"
    );
    assert!(z_unb.abs() < 3.0, "unbiased mode is biased: z = {z_unb}");
}

/// The policy state checkpointed at any point and
/// restored continues exactly as the uninterrupted state, bit for bit, with the same
/// leased pixel sets; a checkpoint no run could have produced is refused.
#[test]
fn checkpointed_policy_state_resumes_bit_identically() {
    let plan = FramePlan::new(20, 12, 8, 1, 64).unwrap();
    for settings in [seq(0.15), unb(0.15)] {
        let units = plan.units(0, 1);
        let feed = |f: &mut AdaptiveFrame, us: &[WorkUnit]| {
            for &u in us {
                let rect = plan.tile(u.tile);
                f.offer(&result_from(rect, u, &|p, i| noisy(u.tile, p, i)))
                    .unwrap();
            }
        };
        let mut whole = AdaptiveFrame::new(plan, 0, settings).unwrap();
        feed(&mut whole, &units);
        let reference = whole.image();
        for cut in [0, 1, units.len() / 5, units.len() / 2, units.len() - 1] {
            let mut first = AdaptiveFrame::new(plan, 0, settings).unwrap();
            feed(&mut first, &units[..cut]);
            let cps: Vec<Option<AdaptiveTileCheckpoint>> =
                first.tiles().iter().map(|t| Some(t.checkpoint())).collect();
            let mut resumed = AdaptiveFrame::restore(plan, 0, settings, &cps).unwrap();
            for (a, b) in first.tiles().iter().zip(resumed.tiles()) {
                assert_eq!(a.consumed_passes(), b.consumed_passes());
                assert_eq!(a.lease_horizon(), b.lease_horizon());
                let (p, n) = (a.consumed_passes(), 1);
                assert_eq!(a.wanted_pixels(p, n), b.wanted_pixels(p, n), "{settings:?}");
            }
            feed(&mut resumed, &units[cut..]);
            assert!(resumed.finished());
            assert_eq!(resumed.image(), reference, "{settings:?} cut at {cut}");
        }
        // Damaged checkpoints are refused with the tile named, never trusted.
        let cp = whole.tile(1).unwrap().checkpoint();
        let rect = plan.tile(1);
        let mut bad = cp.clone();
        bad.pixels.pop();
        assert!(AdaptiveTile::restore(rect, settings, plan.passes, &bad).is_err());
        let mut bad = cp.clone();
        bad.consumed_passes = plan.passes + 1;
        assert!(AdaptiveTile::restore(rect, settings, plan.passes, &bad).is_err());
        let mut bad = cp.clone();
        bad.pixels[0].stats.mean[1] = f64::NAN;
        assert!(AdaptiveTile::restore(rect, settings, plan.passes, &bad).is_err());
        let mut bad = cp.clone();
        bad.pixels[0].traced = cp.consumed_passes + 1;
        assert!(AdaptiveTile::restore(rect, settings, plan.passes, &bad).is_err());
        let mut bad = cp.clone();
        if settings.mode == AdaptiveMode::Sequential {
            bad.pixels[0].stopped_at = settings.min_passes + 1; // not a boundary
        } else {
            bad.pixels[0].needed = 0; // the pilot decided for every pixel
        }
        let e = AdaptiveTile::restore(rect, settings, plan.passes, &bad).unwrap_err();
        assert_eq!(e.tile, 1);
        assert!(AdaptiveFrame::restore(plan, 0, settings, &[None]).is_err());
    }
}

/// [`result_from`] with a bias channel: pixel `i`'s bias estimate in pass `p` is
/// `g(p, i)`.
fn biased_result_from(
    rect: TileRect,
    u: WorkUnit,
    f: &dyn Fn(u32, usize) -> f32,
    g: &dyn Fn(u32, usize) -> f32,
) -> UnitResult {
    let mut r = result_from(rect, u, f);
    let mut bias = Vec::new();
    for pass in u.first_pass..u.first_pass + u.pass_count {
        bias.extend((0..rect.pixel_count()).map(|i| g(pass, i)));
    }
    r.bias = Some(bias);
    r
}

/// A signed, reproducible bias estimate, different for every (pass, pixel).
fn bias_of(tile: u32, pass: u32, pixel: usize) -> f32 {
    let mut rng =
        Rng::new(0xb1a5 ^ (u64::from(tile) << 40) ^ (u64::from(pass) << 20) ^ pixel as u64);
    (rng.uniform() - 0.3) as f32
}

/// Without adaptive stopping every pixel keeps every pass, so the bias channel's
/// statistics are those of the plain merge, bit for bit.
#[test]
fn off_keeps_the_plain_merges_bias_channel() {
    let plan = FramePlan::new(13, 9, 8, 2, 10).unwrap();
    let rect = plan.tile(1);
    let mut plain = TileAccumulator::new(rect);
    let mut off = AdaptiveTile::new(rect, AdaptiveSettings::default(), plan.passes);
    let mut units: Vec<WorkUnit> = (0..5).map(|c| unit(1, 2 * c, 2)).collect();
    Rng::new(4).shuffle(&mut units);
    for u in units {
        let r = biased_result_from(rect, u, &|p, i| noisy(1, p, i), &|p, i| bias_of(1, p, i));
        off.offer(&r);
        plain.offer(r).unwrap();
    }
    assert!(off.finished());
    assert_eq!(off.bias(), plain.bias());
    assert!(off.bias().is_some());
}

/// Each pixel's bias statistics are over exactly the passes its radiance statistics keep:
/// for unbiased, the fresh passes after the discarded pilot; for sequential, the passes
/// before it stopped. Checked against the mean of those passes' bias values computed
/// here, and bit-identical for any unit split and arrival order.
#[test]
fn the_bias_channel_follows_the_passes_each_pixel_keeps() {
    let plan = FramePlan::new(20, 12, 8, 1, 64).unwrap();
    for settings in [seq(0.15), unb(0.15)] {
        let run = |per: u32, seed: Option<u64>| {
            split_frame(plan, settings, per, seed, |rect, u| {
                biased_result_from(rect, u, &|p, i| noisy(u.tile, p, i), &|p, i| {
                    bias_of(u.tile, p, i)
                })
            })
        };
        let frame = run(1, None);
        let mut kept_fewer = false;
        for tile in frame.tiles() {
            let t = tile.rect().index;
            let bias = tile.bias().expect("every unit carried a bias channel");
            let fresh: Vec<u32> = tile.fresh_passes_needed().collect();
            for (i, (b, s)) in bias.iter().zip(tile.pixels()).enumerate() {
                assert_eq!(b.passes, s.passes, "{settings:?} tile {t} pixel {i}");
                // The passes the pixel keeps: unbiased from the pilot's end, sequential
                // from pass 0.
                let first = match settings.mode {
                    AdaptiveMode::Unbiased => {
                        assert_eq!(s.passes, fresh[i]);
                        settings.min_passes
                    }
                    _ => 0,
                };
                let want: f64 = (first..first + s.passes)
                    .map(|p| f64::from(bias_of(t, p, i)))
                    .sum::<f64>()
                    / f64::from(s.passes);
                assert!((b.mean - want).abs() < 1e-12, "{b:?} {want}");
                kept_fewer |= s.passes < plan.passes;
            }
        }
        assert!(kept_fewer, "{settings:?}: the policy stopped nothing");
        let img = frame.image();
        let layer = img.bias.as_ref().expect("bias layers");
        let reference = run(1, None).image();
        for (per, seed) in [(4, Some(1)), (3, Some(2)), (64, None)] {
            let other = run(per, seed);
            let o = other.image();
            let bits = |l: &[[f32; 2]]| l.iter().flatten().map(|v| v.to_bits()).collect::<Vec<_>>();
            assert!(
                bits(o.bias.as_ref().unwrap()) == bits(layer),
                "{settings:?} per {per}"
            );
            assert_eq!(other.image_error().to_bits(), frame.image_error().to_bits());
        }
        assert_eq!(reference, img);
        // The estimate adds the bias term: above the same frame's spread alone, and the
        // image's own estimate from its layers agrees to f32 rounding.
        let estimator = crate::ErrorEstimator::for_mode(settings.mode);
        let spread = FrameImage {
            bias: None,
            ..img.clone()
        }
        .error_estimate(estimator)
        .unwrap();
        let with = img.error_estimate(estimator).unwrap();
        assert!(with > 1.2 * spread, "{settings:?}: {with} vs {spread}");
        assert!(
            (frame.image_error() / with - 1.0).abs() < 1e-4,
            "{settings:?}: {} vs {with}",
            frame.image_error()
        );
    }
}

/// A unit without a bias channel (a technique or a worker that does not send one) ends
/// the tile's channel for good, as in the plain merge; results without one leave the
/// image as it always was.
#[test]
fn a_unit_without_a_bias_channel_ends_it() {
    let plan = FramePlan::new(8, 8, 8, 1, 32).unwrap();
    let rect = plan.tile(0);
    let mut frame = AdaptiveFrame::new(plan, 0, unb(0.1)).unwrap();
    let mut plain = AdaptiveFrame::new(plan, 0, unb(0.1)).unwrap();
    for u in plan.units(0, 4) {
        let f = |p, i| noisy(0, p, i);
        let r = if u.first_pass == 4 {
            result_from(rect, u, &f)
        } else {
            biased_result_from(rect, u, &f, &|p, i| bias_of(0, p, i))
        };
        frame.offer(&r).unwrap();
        plain.offer(&result_from(rect, u, &f)).unwrap();
        assert_eq!(frame.tile(0).unwrap().bias().is_some(), u.first_pass < 4);
    }
    assert!(frame.image().bias.is_none());
    assert_eq!(frame.image(), plain.image());
    assert_eq!(frame.image_error().to_bits(), plain.image_error().to_bits());
}

/// A frame restored from its tiles' checkpoints, which carry the bias statistics,
/// continues bit for bit; a checkpoint without them (stored before the channel existed)
/// restores a frame that estimates from the pass spread alone; statistics of other passes
/// are refused.
#[test]
fn restored_bias_statistics_continue_bit_identically() {
    let plan = FramePlan::new(16, 8, 8, 1, 40).unwrap();
    for settings in [unb(0.1), seq(0.1)] {
        let offer = |frame: &mut AdaptiveFrame, units: &[WorkUnit]| {
            for &u in units {
                let rect = plan.tile(u.tile);
                let r = biased_result_from(rect, u, &|p, i| noisy(u.tile, p, i), &|p, i| {
                    bias_of(u.tile, p, i)
                });
                frame.offer(&r).unwrap();
            }
        };
        let units = plan.units(0, 4);
        let (before, after) = units.split_at(units.len() / 2);
        let mut whole = AdaptiveFrame::new(plan, 0, settings).unwrap();
        offer(&mut whole, &units);
        let mut half = AdaptiveFrame::new(plan, 0, settings).unwrap();
        offer(&mut half, before);
        let cps: Vec<_> = half.tiles().iter().map(|t| Some(t.checkpoint())).collect();
        assert!(cps.iter().flatten().all(|c| c.bias.is_some()));
        let mut restored = AdaptiveFrame::restore(plan, 0, settings, &cps).unwrap();
        offer(&mut restored, after);
        assert_eq!(restored.image(), whole.image(), "{settings:?}");
        assert!(whole.image().bias.is_some());
        assert_eq!(
            restored.image_error().to_bits(),
            whole.image_error().to_bits()
        );
        // The checkpoint of the finished frame restores its image, bias layers included.
        let done: Vec<_> = whole.tiles().iter().map(|t| Some(t.checkpoint())).collect();
        let rebuilt = AdaptiveFrame::restore(plan, 0, settings, &done).unwrap();
        assert_eq!(rebuilt.image(), whole.image(), "{settings:?}");
        // Without the bias statistics: the same radiance, no bias layers, the spread-only
        // estimate.
        let old: Vec<_> = done
            .iter()
            .map(|c| {
                c.clone()
                    .map(|c| AdaptiveTileCheckpoint { bias: None, ..c })
            })
            .collect();
        let spread_only = AdaptiveFrame::restore(plan, 0, settings, &old).unwrap();
        let img = spread_only.image();
        assert!(img.bias.is_none());
        assert_eq!(img.mean, whole.image().mean);
        assert!(spread_only.image_error() < whole.image_error());
        // Bias statistics of other passes than the pixels', of another pixel count, or
        // not finite, are refused.
        let bad = |edit: &dyn Fn(&mut Vec<crate::BiasStats>)| {
            let mut cps = cps.clone();
            if let Some(Some(c)) = cps.first_mut() {
                edit(c.bias.as_mut().unwrap());
            }
            AdaptiveFrame::restore(plan, 0, settings, &cps).unwrap_err()
        };
        let e = bad(&|b| b[3].passes += 1);
        assert!(e.reason.contains("bias records"), "{e}");
        let e = bad(&|b| {
            b.pop();
        });
        assert!(e.reason.contains("bias records"), "{e}");
        let e = bad(&|b| b[0].m2 = f64::NAN);
        assert!(e.reason.contains("finite: false"), "{e}");
    }
}
