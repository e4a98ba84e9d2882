use super::*;
use crate::plan::WorkUnit;
use crate::test_util::Rng;

/// A deterministic, irregular pass mean for (tile, pass, pixel): what a renderer would
/// return for that unit no matter how the passes are grouped.
fn pass_mean(tile: u32, pass: u32, pixel: usize) -> [f32; 3] {
    let mut rng =
        Rng::new((u64::from(tile) << 40) ^ (u64::from(pass) << 20) ^ pixel as u64 ^ 0xabcdef);
    // Occasional fireflies make the sums sensitive to order.
    let scale = if rng.uniform() < 0.05 { 1e3 } else { 1.0 };
    [0, 1, 2].map(|_| (scale * rng.uniform()) as f32)
}

fn render(plan: &FramePlan, unit: WorkUnit) -> UnitResult {
    let rect = plan.tile(unit.tile);
    let mut pass_means = Vec::with_capacity(unit.pass_count as usize * rect.pixel_count());
    for pass in unit.first_pass..unit.first_pass + unit.pass_count {
        pass_means.extend((0..rect.pixel_count()).map(|i| pass_mean(unit.tile, pass, i)));
    }
    UnitResult {
        unit,
        width: rect.width,
        height: rect.height,
        pass_means,
        rejected_samples: 0,
        bias: None,
    }
}

fn plan() -> FramePlan {
    FramePlan::new(37, 23, 8, 4, 12).unwrap()
}

/// Every bit of the merged state, for exact comparison.
fn snapshot(acc: &FrameAccumulator) -> Vec<u64> {
    let mut out = Vec::new();
    for t in acc.tiles() {
        out.push(u64::from(t.merged_passes()));
        out.push(t.buffered_units() as u64);
        for s in t.pixels() {
            out.push(u64::from(s.passes));
            out.extend(s.mean.iter().chain(&s.m2).map(|v| v.to_bits()));
            out.push(s.mean_lum.to_bits());
            out.push(s.m2_lum.to_bits());
        }
    }
    out
}

fn image_bits(img: &FrameImage) -> Vec<u32> {
    let mut out = vec![img.width, img.height];
    out.extend(img.mean.iter().flatten().map(|v| v.to_bits()));
    out.extend(img.variance_of_mean.iter().flatten().map(|v| v.to_bits()));
    out.extend(&img.passes);
    out.extend(&img.samples);
    out.extend(img.relative_error.iter().map(|v| v.to_bits()));
    out
}

fn merge_all(plan: &FramePlan, per: u32, seed: Option<u64>) -> FrameAccumulator {
    let mut units = plan.units(0, per);
    if let Some(seed) = seed {
        Rng::new(seed).shuffle(&mut units);
    }
    let mut acc = FrameAccumulator::new(*plan);
    let mut merged = 0u64;
    for u in units {
        match acc.offer(render(plan, u)).unwrap() {
            Offer::Merged { passes_merged } => merged += u64::from(passes_merged),
            Offer::Buffered => {}
            Offer::Duplicate { .. } => panic!("unexpected duplicate"),
        }
        assert_eq!(acc.merged_pass_count(), merged);
    }
    assert!(acc.complete());
    assert_eq!(
        acc.merged_pass_count(),
        u64::from(plan.tile_count()) * u64::from(plan.passes)
    );
    acc
}

/// A result with a bias channel: the pass mean's luminance minus 0.5, a signed value
/// that depends on (tile, pass, pixel) only.
fn render_biased(plan: &FramePlan, unit: WorkUnit) -> UnitResult {
    let mut r = render(plan, unit);
    r.bias = Some(
        r.pass_means
            .iter()
            .map(|m| (crate::luminance(m.map(f64::from)) - 0.5) as f32)
            .collect(),
    );
    r
}

/// The bias channel merges like the pass means: bit-identical across unit splits and
/// arrival orders, Welford over the passes in order, into the image's bias layers and
/// its estimate (which grows by the bias); a unit without the channel drops it.
#[test]
fn bias_channel_merges_in_pass_order_and_needs_every_unit() {
    let plan = plan();
    let merge = |per: u32, seed: Option<u64>, plain_unit: Option<usize>| {
        let mut units = plan.units(0, per);
        if let Some(seed) = seed {
            Rng::new(seed).shuffle(&mut units);
        }
        let mut acc = FrameAccumulator::new(plan);
        for (i, u) in units.into_iter().enumerate() {
            let r = if Some(i) == plain_unit {
                render(&plan, u)
            } else {
                render_biased(&plan, u)
            };
            acc.offer(r).unwrap();
        }
        acc
    };
    let reference = merge(1, None, None);
    let img = reference.image();
    let layer = img.bias.clone().expect("every unit carried bias");
    for (per, seed) in [(4, Some(1)), (5, Some(2)), (12, None)] {
        let acc = merge(per, seed, None);
        let other = acc.image().bias.unwrap();
        assert!(
            other
                .iter()
                .flatten()
                .zip(layer.iter().flatten())
                .all(|(a, b)| a.to_bits() == b.to_bits()),
            "per {per}"
        );
        assert_eq!(
            acc.image_error().to_bits(),
            reference.image_error().to_bits()
        );
    }
    // Tile 14's pixel 3 against a Welford run over its passes.
    let mut b = BiasStats::default();
    for pass in 0..plan.passes {
        b.push((crate::luminance(pass_mean(14, pass, 3).map(f64::from)) - 0.5) as f32);
    }
    assert_eq!(reference.tile(14).unwrap().bias().unwrap()[3], b);
    // The estimate adds the bias: the same passes without the channel estimate less.
    let plain = merge_all(&plan, 1, None);
    assert!(reference.image_error() > plain.image_error());
    assert_eq!(plain.image().bias, None);
    let plain_image = plain.image();
    let spread = plain_image
        .error_estimate(crate::ErrorEstimator::Robust)
        .unwrap();
    let with = img.error_estimate(crate::ErrorEstimator::Robust).unwrap();
    assert!(with > spread, "{with} vs {spread}");
    // One unit without the channel: no bias layers at all, the spread's estimate.
    let mixed = merge(1, Some(3), Some(7));
    assert_eq!(mixed.image().bias, None);
    assert_eq!(mixed.image_error().to_bits(), plain.image_error().to_bits());
}

#[test]
fn merge_is_bit_identical_across_splits_and_orders() {
    let plan = plan();
    let reference = merge_all(&plan, 1, None);
    let ref_state = snapshot(&reference);
    let ref_image = image_bits(&reference.image());
    let ref_error = reference.image_error().to_bits();
    for per in [1, 4, 5, 12, 100] {
        for seed in [None, Some(1), Some(2), Some(3)] {
            let acc = merge_all(&plan, per, seed);
            assert!(snapshot(&acc) == ref_state, "per {per} seed {seed:?}");
            assert!(
                image_bits(&acc.image()) == ref_image,
                "per {per} seed {seed:?}"
            );
            assert_eq!(acc.image_error().to_bits(), ref_error);
        }
    }
    // And the state really is the in-order fold of the pass means.
    let t = reference.tile(14).unwrap();
    let mut s = PixelStats::default();
    for pass in 0..plan.passes {
        s.push(pass_mean(14, pass, 3));
    }
    assert_eq!(t.pixels()[3], s);
    // A different order of pushes gives different bits (the test can detect it).
    let mut r = PixelStats::default();
    for pass in (0..plan.passes).rev() {
        r.push(pass_mean(14, pass, 3));
    }
    assert_ne!(
        (r.mean.map(f64::to_bits), r.m2.map(f64::to_bits)),
        (s.mean.map(f64::to_bits), s.m2.map(f64::to_bits))
    );
}

#[test]
fn buffering_and_merge_counts() {
    let plan = plan();
    let mut acc = TileAccumulator::new(plan.tile(4));
    let unit = |first_pass, pass_count| WorkUnit {
        frame: 0,
        tile: 4,
        first_pass,
        pass_count,
    };
    assert_eq!(acc.offer(render(&plan, unit(4, 4))), Ok(Offer::Buffered));
    assert_eq!(acc.offer(render(&plan, unit(2, 2))), Ok(Offer::Buffered));
    assert_eq!(acc.merged_passes(), 0);
    assert_eq!(acc.buffered_units(), 2);
    assert!(acc.pixels().iter().all(|s| s.passes == 0));
    assert_eq!(
        acc.offer(render(&plan, unit(0, 2))),
        Ok(Offer::Merged { passes_merged: 8 })
    );
    assert_eq!(acc.merged_passes(), 8);
    assert_eq!(acc.buffered_units(), 0);
    assert_eq!(
        acc.offer(render(&plan, unit(8, 4))),
        Ok(Offer::Merged { passes_merged: 4 })
    );
    assert!(acc.pixels().iter().all(|s| s.passes == 12));
    assert_eq!(acc.rect(), plan.tile(4));
}

#[test]
fn duplicates_are_detected_and_change_nothing() {
    let plan = plan();
    let mut acc = FrameAccumulator::new(plan);
    let u = |tile, first_pass, pass_count| WorkUnit {
        frame: 0,
        tile,
        first_pass,
        pass_count,
    };
    acc.offer(render(&plan, u(3, 0, 4))).unwrap(); // merged
    acc.offer(render(&plan, u(3, 8, 4))).unwrap(); // buffered
    let before = snapshot(&acc);

    // Equal copies, of a merged and of a buffered unit.
    for unit in [u(3, 0, 4), u(3, 8, 4)] {
        assert_eq!(
            acc.offer(render(&plan, unit)),
            Ok(Offer::Duplicate { identical: true })
        );
        assert!(snapshot(&acc) == before);
    }
    // Modified copies: one bit of one value.
    for unit in [u(3, 0, 4), u(3, 8, 4)] {
        let mut r = render(&plan, unit);
        r.pass_means[17][2] = f32::from_bits(r.pass_means[17][2].to_bits() ^ 1);
        assert_eq!(acc.offer(r), Ok(Offer::Duplicate { identical: false }));
        assert!(snapshot(&acc) == before);
    }
    // Partial overlaps are errors and change nothing either.
    for (first, count) in [(0, 1), (2, 4), (3, 2), (6, 3), (9, 1), (0, 12)] {
        let err = acc.offer(render(&plan, u(3, first, count))).unwrap_err();
        assert!(matches!(err, MergeError::Overlap { tile: 3, .. }), "{err}");
        assert!(snapshot(&acc) == before);
    }
    assert_eq!(
        acc.offer(render(&plan, u(3, 2, 4)))
            .unwrap_err()
            .to_string(),
        "tile 3: passes 2..6 overlap the earlier unit with passes 0..4"
    );
    // The gap still merges, releasing the buffered unit.
    assert_eq!(
        acc.offer(render(&plan, u(3, 4, 4))),
        Ok(Offer::Merged { passes_merged: 8 })
    );
    assert_eq!(
        acc.offer(render(&plan, u(3, 4, 4))),
        Ok(Offer::Duplicate { identical: true })
    );
}

#[test]
fn invalid_results_are_rejected_and_change_nothing() {
    let plan = plan();
    let mut acc = FrameAccumulator::new(plan);
    acc.offer(render(
        &plan,
        WorkUnit {
            frame: 0,
            tile: 14,
            first_pass: 0,
            pass_count: 2,
        },
    ))
    .unwrap();
    let before = snapshot(&acc);
    let good = || {
        render(
            &plan,
            WorkUnit {
                frame: 0,
                tile: 14,
                first_pass: 2,
                pass_count: 3,
            },
        )
    };
    let mut bad: Vec<UnitResult> = Vec::new();
    let mut r = good();
    r.width += 1;
    bad.push(r);
    let mut r = good();
    r.height = 8;
    bad.push(r);
    let mut r = good();
    r.pass_means.pop();
    bad.push(r);
    let mut r = good();
    r.pass_means.push([0.0; 3]);
    bad.push(r);
    let mut r = good();
    r.pass_means[40][1] = f32::NAN;
    bad.push(r);
    let mut r = good();
    r.pass_means[0][0] = f32::NEG_INFINITY;
    bad.push(r);
    let mut r = good();
    r.pass_means[104][2] = -1e-30;
    bad.push(r);
    let mut r = good();
    r.unit.tile = 15;
    bad.push(r);
    let mut r = good();
    r.unit.tile = u32::MAX;
    bad.push(r);
    let mut r = good();
    r.unit.first_pass = 10; // passes 10..13 of 12
    bad.push(r);
    let mut r = good();
    r.unit.first_pass = u32::MAX;
    bad.push(r);
    let mut r = good();
    r.unit.pass_count = 0;
    r.pass_means.clear();
    bad.push(r);
    for r in bad {
        let err = acc.offer(r.clone()).unwrap_err();
        assert!(matches!(err, MergeError::Invalid(_)), "{err}");
        assert!(snapshot(&acc) == before, "{err}");
        // The tile accumulator alone rejects it too (except the plan's pass bound).
        if r.unit.tile == 14 && r.unit.first_pass != 10 {
            let mut t = acc.tile(14).unwrap().clone();
            assert!(t.offer(r).is_err());
        }
    }
    let mut r = good();
    r.unit.frame = 1;
    assert_eq!(
        acc.offer(r),
        Err(MergeError::WrongFrame {
            frame: 1,
            expected: 0
        })
    );
    assert!(snapshot(&acc) == before);
    // A tile accumulator refuses other tiles' results.
    let mut t = TileAccumulator::new(plan.tile(13));
    assert!(matches!(
        t.offer(good()),
        Err(MergeError::Invalid(ResultError::WrongTile { .. }))
    ));
    // Frame accumulators for other frames.
    let mut acc1 = FrameAccumulator::for_frame(plan, 1);
    let mut r = good();
    r.unit.frame = 1;
    r.unit.first_pass = 0;
    assert_eq!(acc1.frame(), 1);
    assert_eq!(acc1.offer(r), Ok(Offer::Merged { passes_merged: 3 }));
}

#[test]
fn try_new_rejects_invalid_plans() {
    let mut p = plan();
    p.tile_size = 0;
    assert_eq!(
        FrameAccumulator::try_new(p, 0).unwrap_err(),
        PlanError::TileSize(0)
    );
    assert_eq!(
        FrameAccumulator::try_new(plan(), 0).unwrap().plan(),
        &plan()
    );
}

fn constant(plan: &FramePlan, unit: WorkUnit, rgb: [f32; 3]) -> UnitResult {
    let rect = plan.tile(unit.tile);
    UnitResult {
        unit,
        width: rect.width,
        height: rect.height,
        pass_means: vec![rgb; unit.pass_count as usize * rect.pixel_count()],
        rejected_samples: 0,
        bias: None,
    }
}

#[test]
fn image_error_of_constant_image_is_zero() {
    let plan = FramePlan::new(20, 9, 8, 2, 5).unwrap();
    let mut acc = FrameAccumulator::new(plan);
    assert_eq!(acc.image_error(), 0.0);
    for u in plan.units(0, 2) {
        acc.offer(constant(&plan, u, [0.3, 0.7, 0.1])).unwrap();
    }
    assert!(acc.complete());
    assert_eq!(acc.image_error(), 0.0);
    let img = acc.image();
    assert!(img.mean.iter().all(|&m| m == [0.3, 0.7, 0.1]));
    assert!(img.variance_of_mean.iter().all(|&v| v == [0.0; 3]));
    assert!(img.passes.iter().all(|&p| p == 5));
    assert!(img.samples.iter().all(|&s| s == 10));
    assert!(img.relative_error.iter().all(|&r| r == 0.0));
}

/// A hand-computed case. 8x1 image, 4-pixel tiles, S = 3:
/// - tile 0 gets 2 passes: pixel 0 sees (1,0,0) then (0,0,0), so its luminance goes
///   0.2126 then 0; mean 0.1063, m2 = 2 * 0.1063^2, variance of the mean
///   m2 / (2 * 1) = 0.1063^2 and rel = 0.1063 / (0.1063 + 0.01). Pixel 1 sees (2,2,2)
///   then (4,4,4): lum 2 and 4, mean 3, m2 = 2, var = 1, rel = 1 / 3.01. Pixels 2 and 3
///   see zeros: rel = 0.
/// - tile 1 gets 1 pass: excluded.
///
/// The interval variance pools the per-pass variance `n v` of the 3x3 neighbours with
/// at least 2 passes, weighted by `n - 1`, divides by the pixel's own `n` and widens
/// by `(q / 2)^2` for the t quantile of the pooled degrees of freedom. A 3 x 2
/// image (row-major): pixel 0 has 2 passes and v = 1 (per-pass variance 2), pixel 1 has
/// 5 passes and v = 0.2 (per-pass 1), pixel 2 has 4 passes and v = 0.5 (per-pass 2),
/// pixel 3 has 1 pass, pixels 4 and 5 have 3 passes and v = 0.
#[test]
fn interval_variance_hand_computed() {
    let img = FrameImage {
        width: 3,
        height: 2,
        mean: vec![[1.0; 3]; 6],
        variance_of_mean: [1.0, 0.2, 0.5, 7.0, 0.0, 0.0].map(|v| [v; 3]).to_vec(),
        passes: vec![2, 5, 4, 1, 3, 3],
        samples: vec![0; 6],
        relative_error: vec![0.0; 6],
        bias: None,
    };
    let iv = img.interval_variance();
    let close = |a: f32, b: f64| (f64::from(a) - b).abs() <= 1e-6 * b.max(1e-30);
    // Widened by (q / 2)^2 for Student's t quantile q of the pooled degrees of freedom
    // (2.4288 for 7, 2.2549 for 11, 2.2313 for 12).
    let widen = |dof: u64| (crate::interval_quantile(dof) / 2.0).powi(2);
    // Pixel 0 pools 0, 1, 4 (3 has 1 pass): dof 1 + 4 + 2, sum 1*2 + 4*1 + 2*0.
    assert!(close(iv[0][0], (6.0 / 7.0) / 2.0 * widen(7)), "{:?}", iv[0]);
    assert!((widen(7) - (2.4288051304035685f64 / 2.0).powi(2)).abs() < 1e-15);
    // Pixel 1 pools all but 3: dof 1 + 4 + 3 + 2 + 2, sum 2 + 4 + 3*2 + 0 + 0.
    assert!(
        close(iv[1][2], (12.0 / 12.0) / 5.0 * widen(12)),
        "{:?}",
        iv[1]
    );
    // Pixel 3 has no estimate of its own.
    assert_eq!(iv[3], [0.0; 3]);
    // Pixel 5 pools 1, 2, 4, 5: dof 4 + 3 + 2 + 2, sum 4 + 6.
    assert!(
        close(iv[5][1], (10.0 / 11.0) / 3.0 * widen(11)),
        "{:?}",
        iv[5]
    );
    // A constant per-pass variance pools to itself, widened for the neighbourhood's
    // degrees of freedom: 4 pixels of 3 in the corners (12), 6 in the middle column (18).
    let flat = FrameImage {
        variance_of_mean: vec![[0.25; 3]; 6],
        passes: vec![4; 6],
        ..img
    };
    for (p, v) in flat.interval_variance().iter().enumerate() {
        let dof = if p % 3 == 1 { 18 } else { 12 };
        assert!(close(v[0], 0.25 * widen(dof)), "pixel {p}: {v:?}");
        assert!(v[0] == v[1] && v[1] == v[2]);
    }
}

/// image error = sqrt((rel0^2 + rel1^2) / 4).
#[test]
fn image_error_hand_computed() {
    let plan = FramePlan::new(8, 1, 4, 3, 4).unwrap();
    let mut acc = FrameAccumulator::new(plan);
    let unit = |tile, first_pass| WorkUnit {
        frame: 0,
        tile,
        first_pass,
        pass_count: 1,
    };
    let result = |u: WorkUnit, px: [[f32; 3]; 4]| UnitResult {
        unit: u,
        width: 4,
        height: 1,
        pass_means: px.to_vec(),
        rejected_samples: 0,
        bias: None,
    };
    let z = [0.0; 3];
    acc.offer(result(unit(0, 0), [[1.0, 0.0, 0.0], [2.0; 3], z, z]))
        .unwrap();
    // Only one pass so far: nothing to estimate.
    assert_eq!(acc.image_error(), 0.0);
    acc.offer(result(unit(0, 1), [z, [4.0; 3], z, z])).unwrap();
    acc.offer(result(unit(1, 0), [[9.0, 0.0, 0.0], [1.0; 3], z, [5.0; 3]]))
        .unwrap();

    // Pixel 0: passes of luminance 0.2126 and 0, mean l0 = 0.1063, standard error l0;
    // it is darker than its neighbourhood, so its scale is its own mean.
    let l0 = 0.2126f64 / 2.0;
    let rel0 = l0 / (l0 + 0.01);
    // Pixel 1: passes 2 and 4, mean 3, standard error 1; its level (`neighbours_level`:
    // pixels 0 and 2 have mean l0 / 2, floored at 3 / 9) is below 3, so the robust scale
    // falls to the floor 3 - 1 = 2.
    let rel1 = 1.0 / 2.01;
    let expected = ((rel0 * rel0 + rel1 * rel1) / 4.0).sqrt();
    let got = acc.image_error();
    assert!(
        (got - expected).abs() <= 1e-12 * expected,
        "{got} vs {expected}"
    );

    let img = acc.image();
    assert_eq!(img.passes, vec![2, 2, 2, 2, 1, 1, 1, 1]);
    assert_eq!(img.samples, vec![6, 6, 6, 6, 3, 3, 3, 3]);
    assert_eq!(img.mean[0], [0.5, 0.0, 0.0]);
    assert_eq!(img.mean[1], [3.0; 3]);
    assert_eq!(img.mean[4], [9.0, 0.0, 0.0]);
    assert_eq!(img.variance_of_mean[0], [0.25, 0.0, 0.0]);
    assert_eq!(img.variance_of_mean[1], [1.0; 3]);
    // One pass: no estimate, stored as 0.
    assert_eq!(img.variance_of_mean[7], [0.0; 3]);
    assert_eq!(img.relative_error[7], 0.0);
    assert!((f64::from(img.relative_error[0]) - rel0).abs() < 1e-6);
    // The layer keeps the pixel's own rel, standard error over its own mean.
    assert!((f64::from(img.relative_error[1]) - 1.0 / 3.01).abs() < 1e-6);
    assert!(!acc.complete());
    assert_eq!(acc.merged_pass_count(), 3);
}

/// The image is assembled at the right place: tile-local pixel (x, y) of tile t lands at
/// (x0 + x, y0 + y).
#[test]
fn image_layout() {
    let plan = FramePlan::new(37, 23, 8, 1, 1).unwrap();
    let mut acc = FrameAccumulator::new(plan);
    for u in plan.units(0, 1) {
        let rect = plan.tile(u.tile);
        let mut pass_means = Vec::new();
        for y in 0..rect.height {
            for x in 0..rect.width {
                pass_means.push([(rect.x0 + x) as f32, (rect.y0 + y) as f32, 0.0]);
            }
        }
        let r = UnitResult {
            unit: u,
            width: rect.width,
            height: rect.height,
            pass_means,
            rejected_samples: 0,
            bias: None,
        };
        assert_eq!(acc.offer(r), Ok(Offer::Merged { passes_merged: 1 }));
    }
    let img = acc.image();
    for y in 0..23u32 {
        for x in 0..37u32 {
            assert_eq!(img.mean[(y * 37 + x) as usize], [x as f32, y as f32, 0.0]);
        }
    }
}

/// The image error reads each pixel from its tile (no frame-sized copy): on a plan
/// whose last tile column and row are narrower, it equals the estimate over the same
/// statistics laid out row-major over the frame.
#[test]
fn image_error_reads_pixels_where_their_tiles_are() {
    let plan = FramePlan::new(37, 23, 8, 1, 3).unwrap();
    let mut acc = FrameAccumulator::new(plan);
    for u in plan.units(0, 3) {
        acc.offer(render(&plan, u)).unwrap();
    }
    let mut frame = vec![None; 37 * 23];
    for tile in &acc.tiles {
        let r = tile.rect();
        for (i, s) in tile.pixels().iter().enumerate() {
            let (x, y) = (
                r.x0 as usize + i % r.width as usize,
                r.y0 as usize + i / r.width as usize,
            );
            frame[y * 37 + x] = Some((s.mean_lum, s.lum_variance_of_mean()));
        }
    }
    let expected = crate::image_relative_error(37, 23, |x, y| frame[y * 37 + x]);
    assert!(expected > 0.0);
    assert_eq!(acc.image_error().to_bits(), expected.to_bits());
}
