//! The light hierarchy changes which light next-event estimation picks, not the expected
//! image: the path tracer with the tree ([`LightSet::new`]) against the same path tracer
//! selecting lights by power ([`LightSet::with_power_selection`]), independent seeds, a
//! two-sided z-test per 8 x 8 block and for the whole image, Bonferroni-corrected over the
//! blocks for a family-wise level of 1% (Marschner, CS 6630 notes, section 2; passes are
//! independent replicates, Owen 2001, section 6.7).

use crate::common::{assert_blocks_agree, block_passes, block_stats};
use tessera_farm::FramePlan;
use tessera_render::integrator::Integrator;
use tessera_render::light::LightSet;
use tessera_render::render::RenderConfig;
use tessera_render::scene::RenderScene;

fn settings(seed: u64) -> RenderConfig {
    RenderConfig {
        integrator: Integrator::Path,
        seed,
        max_depth: 8,
        rr_depth: 3,
        ..RenderConfig::default()
    }
}

fn tree_matches_power_selection(scene_name: &str, w: u32, h: u32) {
    let scene = tessera_scene::load(scene_name).unwrap();
    let tree = RenderScene::build(&scene, w, h).unwrap();
    let mut power = RenderScene::build(&scene, w, h).unwrap();
    power.lights = LightSet::with_power_selection(power.lights.lights.clone());
    // 32 passes of 4 samples: enough passes for the estimated standard errors to be close
    // to exact.
    let plan = FramePlan::new(w, h, w.max(h), 4, 32).unwrap();
    let a = block_passes(&tree, &settings(1), &plan, 8);
    let b = block_passes(&power, &settings(2), &plan, 8);
    let image = |p: &[Vec<f64>]| -> Vec<Vec<f64>> {
        p.iter()
            .map(|b| vec![b.iter().sum::<f64>() / b.len() as f64])
            .collect()
    };
    assert_blocks_agree(
        &format!("{scene_name} tree vs power, whole image"),
        &block_stats(&image(&a)),
        &block_stats(&image(&b)),
    );
    assert_blocks_agree(
        &format!("{scene_name} tree vs power"),
        &block_stats(&a),
        &block_stats(&b),
    );
}

#[test]
fn light_tree_nee_is_unbiased_on_veach_mis() {
    tree_matches_power_selection("builtin:veach-mis", 48, 48);
}

#[test]
fn light_tree_nee_is_unbiased_on_cornell_box() {
    tree_matches_power_selection("builtin:cornell-box", 32, 32);
}
