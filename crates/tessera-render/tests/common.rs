//! Helpers shared by the rendering tests: render a scene through the real plan, unit
//! renderer and canonical merge, and summarise pixel statistics.
#![allow(dead_code)]

use tessera_farm::{FrameAccumulator, FramePlan};
use tessera_render::render::{render_frame, RenderSettings};
use tessera_render::scene::RenderScene;
use tessera_scene::Scene;

/// Renders `scene` at `w` x `h`, `spp` samples per pixel, on all cores.
pub fn render(
    scene: &Scene,
    w: u32,
    h: u32,
    spp: u32,
    settings: &RenderSettings,
) -> FrameAccumulator {
    let rs = RenderScene::build(scene, w, h).unwrap();
    let plan = FramePlan::for_spp(w, h, spp, 16).unwrap();
    render_frame(&rs, settings, &plan, 0, 0, |_, _| {})
}

/// Mean of one channel over all pixels, and its standard error from the per-pixel
/// variances of the mean (pixels are independent estimates).
pub fn image_mean(acc: &FrameAccumulator, channel: usize) -> (f64, f64) {
    let img = acc.image();
    let n = img.mean.len() as f64;
    let mean = img.mean.iter().map(|p| p[channel] as f64).sum::<f64>() / n;
    let var = img
        .variance_of_mean
        .iter()
        .map(|v| v[channel] as f64)
        .sum::<f64>()
        / (n * n);
    (mean, var.sqrt())
}
