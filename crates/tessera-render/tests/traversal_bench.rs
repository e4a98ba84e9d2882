//! Measurement (ignored by default) behind the "wide BVH" sections of docs/benchmarks.md:
//! one render of a glTF scene with one kernel, for callgrind (instruction counts do not
//! move with the machine's load) and `perf stat`, printing the geometry's bytes per
//! triangle, the rays traced and a hash of the image's bits (equal hashes before and
//! after a traversal change: the image did not change).
//!
//! `TESSERA_BENCH_SCENE=terrain.glb cargo test -p tessera-render --test
//! traversal_bench -- --ignored --nocapture` (the `test` profile is optimised);
//! `TESSERA_BENCH_SIZE=64` (pixels a side, default 64), `TESSERA_BENCH_SPP` (default 16)
//! and `TESSERA_ISA` choose the render and the kernel. One render thread.

use std::time::Instant;
use tessera_farm::FramePlan;
use tessera_render::render::{render_frame_counted, RenderConfig};
use tessera_render::scene::RenderScene;

fn env_u32(name: &str, default: u32) -> u32 {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

#[test]
#[ignore = "measurement: set TESSERA_BENCH_SCENE"]
fn traversal_render() {
    let Ok(path) = std::env::var("TESSERA_BENCH_SCENE") else {
        println!("TESSERA_BENCH_SCENE is unset: nothing measured");
        return;
    };
    let (size, spp) = (
        env_u32("TESSERA_BENCH_SIZE", 64),
        env_u32("TESSERA_BENCH_SPP", 16),
    );
    let scene = tessera_scene::load(&path).unwrap();
    let t = Instant::now();
    let rs = RenderScene::build(&scene, size, size).unwrap();
    let build = t.elapsed().as_secs_f64();
    drop(scene);
    let triangles = rs.geometry.triangles.len().max(1);
    let plan = FramePlan::for_spp(size, size, spp, 16).unwrap();
    let cfg = RenderConfig {
        seed: 1,
        ..RenderConfig::default()
    };
    let t = Instant::now();
    let frame = render_frame_counted(&rs, &cfg, &plan, 0, 1, |_, _| {});
    let seconds = t.elapsed().as_secs_f64();
    let (rays, image) = (frame.rays, frame.accumulator.image());
    // FNV-1a over the bits of the mean and its variance.
    let mut hash = 0xcbf2_9ce4_8422_2325u64;
    for v in image
        .mean
        .iter()
        .chain(&image.variance_of_mean)
        .flat_map(|m| m.map(f32::to_bits))
    {
        hash = (hash ^ u64::from(v)).wrapping_mul(0x100_0000_01b3);
    }
    println!(
        "{path}: kernel {}, {triangles} triangles, build {build:.2} s, geometry {:.1} bytes per triangle; {size}x{size} {spp} spp: {rays} rays in {seconds:.2} s; image hash {hash:016x}",
        rs.geometry.isa().name(),
        rs.geometry.bytes() as f64 / triangles as f64,
    );
}
