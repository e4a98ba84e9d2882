//! ARCHITECTURE.md §2: a frame's statistics are a pure function of the scene, the settings and the
//! seed — independent of thread count, of how passes are cut into work units and of the
//! order units arrive in.

use tessera_farm::{FrameAccumulator, FramePlan};
use tessera_render::render::{render_frame, render_unit, RenderConfig};
use tessera_render::scene::RenderScene;

use super::common::frame_bits as bits;

#[test]
fn thread_count_and_unit_split_do_not_change_a_bit() {
    let scene = tessera_scene::load("builtin:cornell-box").unwrap();
    let (w, h) = (48, 40);
    let rs = RenderScene::build(&scene, w, h).unwrap();
    let plan = FramePlan::for_spp(w, h, 32, 16).unwrap();
    // At least 2 passes, so the halves below are units of their own.
    assert!(plan.passes >= 2);
    let settings = RenderConfig {
        seed: 42,
        ..RenderConfig::default()
    };
    let reference = render_frame(&rs, &settings, &plan, 0, 1, |_, _| {});
    for threads in [2, 8] {
        let acc = render_frame(&rs, &settings, &plan, 0, threads, |_, _| {});
        assert!(
            bits(&acc) == bits(&reference),
            "{threads} threads differ from 1"
        );
    }
    // Two halves of the passes, as two sets of units offered in reverse order, merge to
    // the same statistics as a single run.
    let half = plan.passes / 2;
    let mut units = plan.units(0, half);
    units.reverse();
    let mut acc = FrameAccumulator::new(plan);
    for u in units {
        acc.offer(render_unit(&rs, &settings, &plan, u)).unwrap();
    }
    assert!(acc.complete());
    assert!(
        bits(&acc) == bits(&reference),
        "halves differ from a single run"
    );
    // A unit rendered twice is identical (so a duplicate can be compared).
    let u = plan.units(0, 1)[5];
    let a = render_unit(&rs, &settings, &plan, u);
    let b = render_unit(&rs, &settings, &plan, u);
    assert_eq!(a.digest(), b.digest());
    // A different seed gives a different image.
    let other = render_frame(
        &rs,
        &RenderConfig {
            seed: 43,
            ..settings
        },
        &plan,
        0,
        2,
        |_, _| {},
    );
    assert!(bits(&other) != bits(&reference));
}
