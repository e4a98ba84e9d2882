use super::*;
use crate::test_util::Rng;

fn job(planned_passes: u32) -> QuoteJob {
    QuoteJob {
        pixels_per_frame: 256 * 256,
        frames: 3,
        planned_passes,
        samples_per_pass: 16,
        workers: 4,
        setup_seconds: 0.5,
        tiles_per_frame: 256,
        passes_per_unit: 1,
        spot_check_fraction: 0.0,
        stop_interval: 0,
    }
}

/// A synthetic pilot whose pixels have a known relative error `sigma / sqrt(passes)`:
/// each pixel's squared relative error is `sigma² / passes` times a chi-squared
/// variable with `passes - 1` degrees of freedom over `passes - 1` (what a variance
/// estimate from `passes` Gaussian replicates is), and each unit's cost per
/// pixel-pass is `cost` times a noisy factor.
fn synthetic(rng: &mut Rng, sigma: f64, cost: f64, passes: u32, tiles: u32) -> PilotMeasurement {
    let px = 256u64;
    let dof = passes - 1;
    let groups = (0..tiles)
        .map(|t| {
            // Tiles differ: some are twice as noisy as others.
            let tile_sigma = sigma * if t % 2 == 0 { 0.8 } else { 1.166 };
            let sum_sq_rel = (0..px)
                .map(|_| {
                    let chi2: f64 = (0..dof).map(|_| rng.normal().powi(2)).sum();
                    tile_sigma * tile_sigma / f64::from(passes) * chi2 / f64::from(dof)
                })
                .sum();
            PilotGroup {
                pixels: px,
                sum_sq_rel,
            }
        })
        .collect();
    let units = (0..tiles * passes)
        .map(|_| PilotUnit {
            pixel_passes: px,
            worker_seconds: cost * px as f64 * (1.0 + 0.2 * rng.normal()).max(0.1),
        })
        .collect();
    PilotMeasurement {
        passes,
        groups,
        units,
        tails: None,
    }
}

#[test]
fn error_follows_the_inverse_square_root_of_passes() {
    let pilot = PilotMeasurement {
        passes: 4,
        groups: vec![PilotGroup {
            pixels: 100,
            sum_sq_rel: 100.0 * 0.16,
        }],
        units: vec![PilotUnit {
            pixel_passes: 400,
            worker_seconds: 4.0,
        }],
        tails: None,
    };
    let q = quote(&pilot, &job(16), &[0.1, 0.4, 0.01]).unwrap();
    assert!((q.pilot_error - 0.4).abs() < 1e-12);
    // 0.4 after 4 passes -> 0.2 after 16.
    assert!((q.planned.error.estimate - 0.2).abs() < 1e-12);
    // 0.1 needs 64 passes, 16 times the pilot's; 0.4 the floor of 2 (4 by the law,
    // which is the pilot itself); 0.01 needs 6400.
    let t = &q.targets;
    assert_eq!(t[0].passes.estimate, 64.0);
    assert!(!t[0].within_plan);
    assert_eq!(t[1].passes.estimate, 4.0);
    assert!(t[1].within_plan);
    assert_eq!(t[2].passes.estimate, 6400.0);
    // 0.01 worker-seconds per pixel-pass: 64 passes of 65536 pixels, 3 frames.
    let c = &t[0].cost;
    assert!((c.worker_seconds_per_frame.estimate - 64.0 * 0.01 * 65536.0).abs() < 1e-6);
    assert!((c.worker_seconds.estimate - 3.0 * 64.0 * 0.01 * 65536.0).abs() < 1e-6);
    assert!(
        (c.seconds.estimate - (0.5 + c.worker_seconds.estimate / 4.0)).abs() < 1e-6,
        "wall = set-up + worker-seconds / workers"
    );
    assert_eq!(c.spp.estimate, 64.0 * 16.0);
    // One group: the interval falls back on 1/sqrt(2 (K - 1)) and is wide.
    assert!(t[0].passes.low < 64.0 && t[0].passes.high > 64.0);
}

/// Against a known law with noise, the 95% intervals of the passes needed and of the
/// planned error cover the truth in most of 200 seeded pilots, and are not so wide as
/// to be useless.
#[test]
fn intervals_cover_a_known_law() {
    let mut rng = Rng::new(0x5eed_0015);
    let (sigma, cost) = (0.8, 2e-6);
    // The tiles' mean squared per-pass error: half at 0.8², half at 1.166².
    let true_m1 = (0.8f64.powi(2) + 1.166f64.powi(2)) / 2.0 * sigma * sigma;
    let target = 0.02;
    let true_passes = true_m1 / (target * target);
    let planned = 64;
    let true_planned_error = (true_m1 / f64::from(planned)).sqrt();
    let true_ws = true_passes * cost * 65536.0;
    let (mut cover_n, mut cover_e, mut cover_s, mut width) = (0, 0, 0, 0.0);
    let trials = 200;
    for _ in 0..trials {
        let pilot = synthetic(&mut rng, sigma, cost, 4, 16);
        let q = quote(&pilot, &job(planned), &[target]).unwrap();
        let t = &q.targets[0];
        // Whole passes round up: compare with the truth rounded up too.
        cover_n += usize::from(t.passes.contains(true_passes.ceil()));
        cover_e += usize::from(q.planned.error.contains(true_planned_error));
        let ws = &t.cost.worker_seconds_per_frame;
        cover_s += usize::from(ws.low <= true_ws * 1.001 && true_ws <= ws.high * 1.001);
        width += t.passes.high / t.passes.low;
    }
    let frac = |n: usize| n as f64 / f64::from(trials);
    assert!(frac(cover_n) >= 0.88, "passes covered {}", frac(cover_n));
    assert!(frac(cover_e) >= 0.88, "error covered {}", frac(cover_e));
    assert!(frac(cover_s) >= 0.88, "seconds covered {}", frac(cover_s));
    let width = width / f64::from(trials);
    assert!(width < 2.0, "mean high/low {width}");
}

/// A few large units (8 whole-frame passes, as bdpt renders them) on 2 workers take
/// whole rounds, and a spot check's copy of one of them costs a round more.
#[test]
fn a_few_large_units_take_whole_rounds_and_spot_checks_add_one() {
    let pilot = PilotMeasurement {
        passes: 4,
        groups: vec![
            PilotGroup {
                pixels: 1024,
                sum_sq_rel: 1024.0 * 0.04,
            };
            4
        ],
        // 2 worker-seconds a unit, without spread.
        units: vec![
            PilotUnit {
                pixel_passes: 1024,
                worker_seconds: 2.0,
            };
            4
        ],
        tails: None,
    };
    let job = QuoteJob {
        pixels_per_frame: 1024,
        frames: 1,
        planned_passes: 8,
        samples_per_pass: 16,
        workers: 2,
        setup_seconds: 0.0,
        tiles_per_frame: 1,
        passes_per_unit: 1,
        spot_check_fraction: 0.0,
        stop_interval: 0,
    };
    let close = |a: f64, b: f64| (a - b).abs() < 1e-9;
    let c = quote(&pilot, &job, &[]).unwrap().planned;
    assert!(close(c.worker_seconds.estimate, 16.0));
    assert!(close(c.seconds.estimate, 8.0) && close(c.seconds.high, 8.0));
    // 3 workers: ceil(8 / 3) = 3 rounds, not 16 / 3 worker-seconds.
    let three = quote(&pilot, &QuoteJob { workers: 3, ..job }, &[]).unwrap();
    assert!(close(three.planned.seconds.estimate, 6.0));

    // 2% spot-checked: K ~ Binomial(8, 0.02); 4 rounds when K = 0, 5 for K = 1 or 2,
    // ceil((8 + k) / 2) in general.
    let f = 0.02;
    let checked = QuoteJob {
        spot_check_fraction: f,
        ..job
    };
    let c = quote(&pilot, &checked, &[]).unwrap().planned;
    let (mut p, mut rounds) = ((1.0f64 - f).powi(8), 0.0);
    for k in 0..=8 {
        rounds += p * f64::from((8 + k + 1) / 2);
        p *= f64::from(8 - k) / f64::from(k + 1) * f / (1.0 - f);
    }
    assert!((rounds - 4.15).abs() < 0.01, "{rounds}");
    assert!(close(c.seconds.estimate, 2.0 * rounds), "{:?}", c.seconds);
    // P(K = 0) = 0.851, P(K <= 1) = 0.990: the 95% interval spans 4 to 5 rounds.
    assert!(close(c.seconds.low, 8.0) && close(c.seconds.high, 10.0));
    assert!(close(c.worker_seconds.estimate, 16.0 * 1.02));
    assert!(close(c.worker_seconds.high, 18.0));
    assert!(close(c.seconds_per_frame.estimate, c.seconds.estimate));
}

/// The copies' figures are continuous where [`Copies::of`] changes from the exact
/// binomial to the normal approximation, and every unit is copied at fraction 1.
#[test]
fn spot_check_copies_are_continuous_between_exact_and_normal() {
    let exact = Copies::of(1500.0, 0.02, 7.0);
    let normal = Copies::of(1501.0, 0.02, 7.0);
    assert!((exact.mean_rounds - normal.mean_rounds).abs() < 0.3);
    assert!(
        (exact.high - normal.high).abs() <= 1.0,
        "{} {}",
        exact.high,
        normal.high
    );
    assert!(
        (exact.low - normal.low).abs() <= 1.0,
        "{} {}",
        exact.low,
        normal.low
    );
    let all = Copies::of(10.0, 1.0, 4.0);
    assert_eq!(
        (all.low, all.mean, all.high, all.mean_rounds),
        (10.0, 10.0, 10.0, 5.0)
    );
    let none = Copies::of(10.0, 0.0, 4.0);
    assert_eq!((none.high, none.mean_rounds), (0.0, 3.0));
}

/// A target-stopped render checks after rounds of `stop_interval` passes: the passes
/// a target needs round up to them. A heavy-tailed pilot widens the high end only; a
/// pilot too heavy to extrapolate says so and keeps the law's figures.
#[test]
fn stop_rounds_and_tails_shape_the_target_passes() {
    let mut rng = Rng::new(0x0e57_1a7e);
    let pilot = synthetic(&mut rng, 0.5, 1e-6, 4, 16);
    let plain = quote(&pilot, &job(1 << 20), &[0.02]).unwrap();
    let rounded = quote(
        &pilot,
        &QuoteJob {
            stop_interval: 4,
            ..job(1 << 20)
        },
        &[0.02],
    )
    .unwrap();
    let (p, r) = (plain.targets[0].passes, rounded.targets[0].passes);
    for (a, b) in [(p.low, r.low), (p.estimate, r.estimate), (p.high, r.high)] {
        assert!(b % 4.0 == 0.0 && b >= a && b < a + 4.0, "{p:?} {r:?}");
    }
    assert_eq!(plain.tail_class, TailClass::Light);

    let tails = |tail_index, variance_growth| Tails {
        values: 32768,
        tail_index: Some(tail_index),
        hill_k: 181,
        top_share: 0.3,
        variance_growth: Some(variance_growth),
    };
    let with = |t| PilotMeasurement {
        tails: Some(t),
        ..pilot.clone()
    };
    let heavy = quote(&with(tails(3.0, 1.5)), &job(1 << 20), &[0.02]).unwrap();
    assert_eq!(heavy.tail_class, TailClass::Heavy);
    let h = heavy.targets[0].passes;
    assert_eq!((h.low, h.estimate), (p.low, p.estimate));
    // gamma = log2 1.5 = 0.585: n = P (M_high / t²)^(1 / 0.415), far above the law's.
    assert!(h.high > 4.0 * p.high, "{h:?} {p:?}");
    assert!(heavy.planned.error.high > plain.planned.error.high);
    assert!(heavy.targets[0].cost.seconds.high > plain.targets[0].cost.seconds.high);

    let wild = quote(&with(tails(1.4, 1.1)), &job(1 << 20), &[0.02]).unwrap();
    assert_eq!(wild.tail_class, TailClass::Unpredictable);
    assert!(wild
        .tail_note
        .as_deref()
        .unwrap()
        .starts_with("not predictable from the pilot"));
    assert_eq!(wild.targets[0].passes, p);
}

/// A heavy-tailed pilot whose groups disagree on its error is not predictable: the
/// bdpt caustic at 32x32 (tail index 2.83, 40% of the squared error in the brightest
/// 1%, growth 1.23, the error's relative standard error 0.55 over its two bands) was
/// classed heavy and quoted [8, 96] passes for 5%, and its renders took 80 and 640.
/// The same tails with groups that agree (0.34, the glossy highlight's at 32x32,
/// covered) stay heavy, and light tails are not judged by the spread at all.
#[test]
fn heavy_tails_with_an_unsettled_error_are_not_predictable() {
    let caustic = Tails {
        values: 4096,
        tail_index: Some(2.83),
        hill_k: 64,
        top_share: 0.40,
        variance_growth: Some(1.23),
    };
    assert_eq!(caustic.verdict().0, TailClass::Heavy);
    // Two groups of 512 pixels with per-pixel squared errors a and b: the ratio
    // estimate's relative standard error is |a - b| / (a + b).
    let pilot = |rel: f64, tails| PilotMeasurement {
        passes: 4,
        groups: [1.0 + rel, 1.0 - rel]
            .map(|f| PilotGroup {
                pixels: 512,
                sum_sq_rel: 512.0 * 0.0078 * f,
            })
            .to_vec(),
        units: vec![
            PilotUnit {
                pixel_passes: 1024,
                worker_seconds: 0.01,
            };
            4
        ],
        tails,
    };
    let job = QuoteJob {
        pixels_per_frame: 1024,
        frames: 1,
        planned_passes: 1 << 16,
        samples_per_pass: 16,
        workers: 1,
        setup_seconds: 0.0,
        tiles_per_frame: 1,
        passes_per_unit: 1,
        spot_check_fraction: 0.0,
        stop_interval: 4,
    };
    let unsettled = quote(&pilot(0.55, Some(caustic)), &job, &[0.05]).unwrap();
    assert!((unsettled.relative_standard_error - 0.55).abs() < 1e-9);
    assert_eq!(unsettled.tail_class, TailClass::Unpredictable);
    let note = unsettled.tail_note.as_deref().unwrap();
    assert!(
        note.starts_with("not predictable from the pilot") && note.contains("groups"),
        "{note}"
    );
    // Its figures are the law's, a lower bound: not widened by the tail.
    let law = quote(&pilot(0.55, None), &job, &[0.05]).unwrap();
    assert_eq!(unsettled.targets[0].passes, law.targets[0].passes);

    let settled = quote(&pilot(0.34, Some(caustic)), &job, &[0.05]).unwrap();
    assert_eq!(settled.tail_class, TailClass::Heavy);
    let light = Tails {
        tail_index: Some(8.0),
        top_share: 0.1,
        variance_growth: Some(1.0),
        ..caustic
    };
    let light = quote(&pilot(0.55, Some(light)), &job, &[0.05]).unwrap();
    assert_eq!(light.tail_class, TailClass::Light);
}

/// The pilot's error is the render's own image estimate of it, not the pixels' errors
/// over their own means: with skewed pass values (a pass in twelve four times
/// brighter) the two differ, and a quote from the latter stops short of where the
/// render's estimate reaches the target. The groups keep their shares.
#[test]
fn the_pilot_error_is_the_render_estimate_of_the_pilot() {
    let plan = crate::FramePlan::new(32, 32, 16, 16, 4).unwrap();
    let mut acc = crate::FrameAccumulator::new(plan);
    let mut rng = Rng::new(0x0b5e_55ed);
    for tile in 0..plan.tile_count() {
        for pass in 0..4 {
            let rect = plan.tile(tile);
            let pass_means = (0..rect.pixel_count())
                .map(|i| {
                    let level = 0.5 + (i % 7) as f32 * 0.1;
                    let bright = if rng.uniform() < 1.0 / 12.0 { 4.0 } else { 1.0 };
                    [level * bright * (0.8 + 0.4 * rng.uniform() as f32); 3]
                })
                .collect();
            let unit = crate::WorkUnit {
                frame: 0,
                tile,
                first_pass: pass,
                pass_count: 1,
            };
            let result = crate::UnitResult {
                unit,
                width: rect.width,
                height: rect.height,
                pass_means,
                rejected_samples: 0,
                bias: None,
            };
            acc.offer(result).unwrap();
        }
    }
    let tiles: Vec<u32> = (0..plan.tile_count()).collect();
    let groups = pilot_groups(&acc, &tiles);
    assert_eq!(groups.len(), 4);
    let pixels: u64 = groups.iter().map(|g| g.pixels).sum();
    let m = groups.iter().map(|g| g.sum_sq_rel).sum::<f64>() / pixels as f64;
    let render = acc.image_error();
    assert!((m.sqrt() / render - 1.0).abs() < 1e-12, "{m} {render}");
    // Over their own means (the rule before) the pixels' errors are lower.
    let own: Vec<f64> = tiles
        .iter()
        .map(|&t| {
            let px = acc.tile(t).unwrap().pixels();
            px.iter().map(|s| s.relative_error().powi(2)).sum()
        })
        .collect();
    let own_m = own.iter().sum::<f64>() / pixels as f64;
    assert!(m > 1.05 * own_m, "robust {m} own {own_m}");
    for (g, o) in groups.iter().zip(&own) {
        assert!((g.sum_sq_rel / m - o / own_m).abs() < 1e-9);
    }
    // A quote from them reports that error.
    let pilot = PilotMeasurement {
        passes: 4,
        groups,
        units: vec![
            PilotUnit {
                pixel_passes: 256,
                worker_seconds: 0.01,
            };
            16
        ],
        tails: None,
    };
    let q = quote(&pilot, &job(16), &[0.05]).unwrap();
    assert!((q.pilot_error / render - 1.0).abs() < 1e-12);
}

#[test]
fn bad_input_names_the_problem() {
    let pilot = synthetic(&mut Rng::new(1), 0.5, 1e-6, 4, 4);
    let e = quote(&pilot, &job(16), &[0.0]).unwrap_err();
    assert!(e.to_string().starts_with("target_error"), "{e}");
    let e = quote(
        &pilot,
        &QuoteJob {
            workers: 0,
            ..job(16)
        },
        &[0.1],
    )
    .unwrap_err();
    assert!(e.to_string().starts_with("workers"), "{e}");
    let e = quote(
        &pilot,
        &QuoteJob {
            spot_check_fraction: 1.5,
            ..job(16)
        },
        &[0.1],
    )
    .unwrap_err();
    assert!(e.to_string().starts_with("spot_check_fraction"), "{e}");
    let one = PilotMeasurement {
        passes: 1,
        ..pilot.clone()
    };
    assert!(quote(&one, &job(16), &[0.1]).is_err());
    let empty = PilotMeasurement {
        groups: vec![],
        ..pilot
    };
    assert!(quote(&empty, &job(16), &[0.1]).is_err());
}

#[test]
fn eta_follows_progress_and_the_inverse_square_root_of_work() {
    let p = JobProgress {
        elapsed_seconds: 10.0,
        passes_done: 100,
        passes_planned: 10_000,
        error: Some(0.04),
        stopping_target: Some(0.02),
        time_limit_left_seconds: None,
        trend: None,
        adaptive: None,
    };
    // Error 0.04 after 10 s, target 0.02: four times the work, 30 s more.
    assert_eq!(job_eta_seconds(&p), Some(30.0));
    // A job that does not stop at its target runs its passes: 99 times the work done.
    let no_stop = JobProgress {
        stopping_target: None,
        ..p
    };
    assert_eq!(job_eta_seconds(&no_stop), Some(990.0));
    // Bounded by the remaining planned passes: 100 of 200 done in 10 s.
    let near = JobProgress {
        passes_planned: 200,
        stopping_target: Some(0.001),
        ..p
    };
    assert_eq!(job_eta_seconds(&near), Some(10.0));
    // And by a time limit; and never negative.
    let limited = JobProgress {
        time_limit_left_seconds: Some(2.0),
        ..no_stop
    };
    assert_eq!(job_eta_seconds(&limited), Some(2.0));
    let reached = JobProgress {
        error: Some(0.01),
        ..p
    };
    assert_eq!(job_eta_seconds(&reached), Some(0.0));
    let nothing = JobProgress {
        passes_done: 0,
        ..p
    };
    assert_eq!(job_eta_seconds(&nothing), None);
    // Stopping at a target with no estimate yet: no point, between now and the plan's end
    // at the pass rate so far (9,900 passes at 10 per second).
    let unknown = job_eta(&JobProgress { error: None, ..p }).unwrap();
    assert_eq!(unknown.seconds, None);
    assert_eq!(unknown.interval, Some((0.0, 990.0)));
    assert_eq!(unknown.tail_class, Some(TailClass::Unpredictable));
    assert!(unknown.note.unwrap().starts_with("not predictable yet"));
    // A job that runs its passes needs no estimate.
    let planned = job_eta(&JobProgress {
        error: None,
        ..no_stop
    })
    .unwrap();
    assert_eq!(planned.seconds, Some(990.0));
}

#[test]
fn pilot_tiles_are_spread_and_bounded() {
    // 256 tiles (16 x 16) of 1024 pixels: 8 distinct tiles in 8 rows and 8 columns.
    let t = pilot_tiles(256, 1024);
    assert_eq!(t.len(), 8);
    let rows: std::collections::BTreeSet<u32> = t.iter().map(|i| i / 16).collect();
    let cols: std::collections::BTreeSet<u32> = t.iter().map(|i| i % 16).collect();
    assert_eq!((rows.len(), cols.len()), (8, 8), "{t:?}");
    // A small frame: every tile.
    assert_eq!(pilot_tiles(4, 1024), vec![0, 1, 2, 3]);
    // Tiles larger than the budget: still the minimum count.
    assert_eq!(pilot_tiles(100, 65536).len(), 8);
    assert!(pilot_tiles(0, 1).is_empty());
}
