//! Measurement (ignored by default) behind "Packets of camera rays" in
//! docs/benchmarks.md: the camera rays of a render, generated as the camera loop does
//! (one pixel's sampler at a time) and in blocks of 8 pixels (8 samplers side by side,
//! sample by sample), traced one by one and as packets of 8
//! (`Geometry::intersect_packet`), every hit compared bit for bit.
//!
//! `TESSERA_BENCH_SCENE=terrain.glb cargo test --release -p tessera-render --test
//! packet_bench -- --ignored --nocapture`; `TESSERA_BENCH_SIZE` (pixels a side, default
//! 64), `TESSERA_BENCH_SPP` (default 16), `TESSERA_PACKET_BLOCK` (`4x2`, the default, or
//! `8x1`), `TESSERA_ISA`, `TESSERA_PACKET_REPS` (default 3) and `TESSERA_PACKET_MODE`:
//! `check` (the default: both orders of generation and both ways of tracing, in-process
//! times of interleaved repetitions, and the comparison), or one of `single`, `packet`,
//! `gen-pixel`, `gen-block`, `none` (generate once, then that alone, repeated: one
//! process per mode, for timing whole processes against each other and subtracting
//! `none`). Callgrind counts each part as the inclusive cost of its function
//! (`trace_single`, `trace_packets`, `generate_pixel_order`, `generate_block_order`).

use glam::{Vec2, Vec3};
use std::time::Instant;
use tessera_farm::FramePlan;
use tessera_render::geometry::{Geometry, Hit, Primitive, PACKET};
use tessera_render::render::RenderConfig;
use tessera_render::sampling::PixelSampler;
use tessera_render::scene::RenderScene;

fn env_u32(name: &str, default: u32) -> u32 {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// A block of pixels' rays for one sample index: ray `i` is pixel `i` of the block.
type Packet = ([Vec3; PACKET], [Vec3; PACKET]);

/// The camera ray of pixel `(x, y)`'s current sample, as the camera loop draws it.
#[inline(always)]
fn camera_ray(scene: &RenderScene, sampler: &mut PixelSampler, x: u32, y: u32) -> (Vec3, Vec3) {
    let film = Vec2::new(x as f32, y as f32) + sampler.next_2d();
    let lens = if scene.camera.has_lens() {
        sampler.next_2d()
    } else {
        Vec2::ZERO
    };
    scene.camera.generate_ray(film, lens)
}

/// Every camera ray of the plan in the camera loop's order: pass, pixel (row-major),
/// sample.
#[inline(never)]
fn generate_pixel_order(
    scene: &RenderScene,
    plan: &FramePlan,
    cfg: &RenderConfig,
) -> Vec<(Vec3, Vec3)> {
    let mut rays = Vec::with_capacity(
        (plan.width * plan.height * plan.samples_per_pass * plan.passes) as usize,
    );
    for pass in 0..plan.passes {
        for y in 0..plan.height {
            for x in 0..plan.width {
                let pixel = y * plan.width + x;
                let mut sampler = PixelSampler::new(cfg.sampler, cfg.seed, 0, pixel, pass);
                for i in 0..plan.samples_per_pass {
                    sampler.start_sample(i);
                    rays.push(camera_ray(scene, &mut sampler, x, y));
                }
            }
        }
    }
    rays
}

/// The same rays by blocks of `bw x bh` pixels (`bw * bh = PACKET`): per pass and block,
/// the block's samplers side by side, and per sample index one packet of the block's rays.
#[inline(never)]
fn generate_block_order(
    scene: &RenderScene,
    plan: &FramePlan,
    cfg: &RenderConfig,
    (bw, bh): (u32, u32),
) -> Vec<Packet> {
    let mut packets = Vec::with_capacity(
        (plan.width * plan.height * plan.samples_per_pass * plan.passes) as usize / PACKET,
    );
    for pass in 0..plan.passes {
        for by in (0..plan.height).step_by(bh as usize) {
            for bx in (0..plan.width).step_by(bw as usize) {
                let at = |k: usize| (bx + k as u32 % bw, by + k as u32 / bw);
                let mut samplers: [PixelSampler; PACKET] = std::array::from_fn(|k| {
                    let (x, y) = at(k);
                    PixelSampler::new(cfg.sampler, cfg.seed, 0, y * plan.width + x, pass)
                });
                for i in 0..plan.samples_per_pass {
                    let mut o = [Vec3::ZERO; PACKET];
                    let mut d = [Vec3::ZERO; PACKET];
                    for (k, s) in samplers.iter_mut().enumerate() {
                        s.start_sample(i);
                        let (x, y) = at(k);
                        (o[k], d[k]) = camera_ray(scene, s, x, y);
                    }
                    packets.push((o, d));
                }
            }
        }
    }
    packets
}

/// The packets' rays traced one by one.
#[inline(never)]
fn trace_single(geometry: &Geometry, packets: &[Packet], hits: &mut Vec<Option<Hit>>) {
    hits.clear();
    for (o, d) in packets {
        for i in 0..PACKET {
            hits.push(geometry.intersect(o[i], d[i], f32::INFINITY));
        }
    }
}

/// The packets traced as packets.
#[inline(never)]
fn trace_packets(geometry: &Geometry, packets: &[Packet], hits: &mut Vec<Option<Hit>>) {
    hits.clear();
    for (o, d) in packets {
        hits.extend(geometry.intersect_packet(o, d, f32::INFINITY));
    }
}

fn hit_bits(h: &Option<Hit>) -> Option<(u32, u32, u32, u32)> {
    h.map(|h| match h.primitive {
        Primitive::Triangle { index, b1, b2, .. } => {
            (h.t.to_bits(), index, b1.to_bits(), b2.to_bits())
        }
        Primitive::Sphere { index } => (h.t.to_bits(), index, 0, 0),
        Primitive::Moving { index, b1, b2, .. } => {
            (h.t.to_bits(), index, b1.to_bits(), b2.to_bits())
        }
    })
}

/// FNV-1a over the hits' bits.
fn hash(hits: &[Option<Hit>]) -> u64 {
    let mut h = 0xcbf2_9ce4_8422_2325u64;
    for v in hits.iter().map(hit_bits) {
        let (a, b, c, d) = v.unwrap_or((u32::MAX, 0, 0, 0));
        for w in [a, b, c, d] {
            h = (h ^ u64::from(w)).wrapping_mul(0x100_0000_01b3);
        }
    }
    h
}

#[test]
#[ignore = "measurement: set TESSERA_BENCH_SCENE"]
fn packets_of_camera_rays() {
    let Ok(path) = std::env::var("TESSERA_BENCH_SCENE") else {
        println!("TESSERA_BENCH_SCENE is unset: nothing measured");
        return;
    };
    let (size, spp) = (
        env_u32("TESSERA_BENCH_SIZE", 64),
        env_u32("TESSERA_BENCH_SPP", 16),
    );
    let reps = env_u32("TESSERA_PACKET_REPS", 3);
    let block = match std::env::var("TESSERA_PACKET_BLOCK").as_deref() {
        Ok("8x1") => (8, 1),
        _ => (4, 2),
    };
    assert_eq!(size % 8, 0, "TESSERA_BENCH_SIZE must be a multiple of 8");
    let mode = std::env::var("TESSERA_PACKET_MODE").unwrap_or_else(|_| "check".into());
    let scene = tessera_scene::load(&path).unwrap();
    let rs = RenderScene::build(&scene, size, size).unwrap();
    drop(scene);
    let plan = FramePlan::for_spp(size, size, spp, 16).unwrap();
    let cfg = RenderConfig {
        seed: 1,
        ..RenderConfig::default()
    };
    let g = &rs.geometry;
    let packets = generate_block_order(&rs, &plan, &cfg, block);
    let mut hits = Vec::with_capacity(packets.len() * PACKET);
    let timed = |f: &mut dyn FnMut()| {
        let t = Instant::now();
        f();
        t.elapsed().as_secs_f64()
    };
    match mode.as_str() {
        "single" | "packet" | "gen-pixel" | "gen-block" | "none" => {
            let mut seconds = 0.0;
            for _ in 0..reps {
                seconds += timed(&mut || match mode.as_str() {
                    "single" => trace_single(g, &packets, &mut hits),
                    "packet" => trace_packets(g, &packets, &mut hits),
                    "gen-pixel" => drop(generate_pixel_order(&rs, &plan, &cfg)),
                    "gen-block" => drop(generate_block_order(&rs, &plan, &cfg, block)),
                    _ => {}
                });
            }
            println!(
                "{path}: {mode} x{reps}, kernel {}, {} rays, {seconds:.3} s, hits hash {:016x}",
                g.isa().name(),
                packets.len() * PACKET,
                hash(&hits)
            );
        }
        _ => {
            // The two orders of generation give the same rays.
            let by_pixel = generate_pixel_order(&rs, &plan, &cfg);
            let spp_pass = plan.samples_per_pass as usize;
            let (bw, bh) = block;
            let mut k = 0;
            for pass in 0..plan.passes {
                for by in (0..size).step_by(bh as usize) {
                    for bx in (0..size).step_by(bw as usize) {
                        for i in 0..spp_pass {
                            let (o, d) = &packets[k];
                            for j in 0..PACKET {
                                let (x, y) = (bx + j as u32 % bw, by + j as u32 / bw);
                                let at =
                                    ((pass * size * size + y * size + x) as usize) * spp_pass + i;
                                let (po, pd) = by_pixel[at];
                                assert!(
                                    po == o[j] && pd == d[j],
                                    "ray of pixel ({x}, {y}), sample {i}"
                                );
                            }
                            k += 1;
                        }
                    }
                }
            }
            let mut packet_hits = Vec::with_capacity(hits.capacity());
            let (mut ts, mut tp, mut tgp, mut tgb) =
                (Vec::new(), Vec::new(), Vec::new(), Vec::new());
            for r in 0..reps {
                // Alternate which goes first.
                if r % 2 == 0 {
                    ts.push(timed(&mut || trace_single(g, &packets, &mut hits)));
                    tp.push(timed(&mut || trace_packets(g, &packets, &mut packet_hits)));
                    tgp.push(timed(&mut || drop(generate_pixel_order(&rs, &plan, &cfg))));
                    tgb.push(timed(&mut || {
                        drop(generate_block_order(&rs, &plan, &cfg, block))
                    }));
                } else {
                    tp.push(timed(&mut || trace_packets(g, &packets, &mut packet_hits)));
                    ts.push(timed(&mut || trace_single(g, &packets, &mut hits)));
                    tgb.push(timed(&mut || {
                        drop(generate_block_order(&rs, &plan, &cfg, block))
                    }));
                    tgp.push(timed(&mut || drop(generate_pixel_order(&rs, &plan, &cfg))));
                }
            }
            let mismatches = hits
                .iter()
                .zip(&packet_hits)
                .filter(|(a, b)| hit_bits(a) != hit_bits(b))
                .count();
            let found = hits.iter().filter(|h| h.is_some()).count();
            let ratios = |a: &[f64], b: &[f64]| {
                let mut r: Vec<f64> = a.iter().zip(b).map(|(a, b)| a / b).collect();
                r.sort_by(f64::total_cmp);
                format!(
                    "median {:.3} (min {:.3}, max {:.3})",
                    r[r.len() / 2],
                    r[0],
                    r[r.len() - 1]
                )
            };
            println!(
                "{path}: kernel {}, block {bw}x{bh}, {size}x{size} {spp} spp: {} camera rays, {found} hits, {mismatches} differ; hits hash {:016x}",
                g.isa().name(),
                hits.len(),
                hash(&hits)
            );
            println!(
                "trace s: single {ts:.3?}, packets {tp:.3?}; packets / single {}",
                ratios(&tp, &ts)
            );
            println!(
                "generate s: pixel order {tgp:.3?}, blocks {tgb:.3?}; blocks / pixel {}",
                ratios(&tgb, &tgp)
            );
            assert_eq!(mismatches, 0, "packet hits differ from single-ray hits");
        }
    }
}
