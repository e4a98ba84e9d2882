//! The first merging radius of [`super::VcmSettings`], from the camera's pixel footprint,
//! and the schedule's constants (the module docs of [`super`], "Bias and the radius
//! schedule", say why).

use crate::math::offset_ray_origin;
use crate::sampling::warp::Frame;
use crate::scene::RenderScene;
use glam::Vec2;

/// The radius schedule's α (Knaus & Zwicker 2011): the radius of pass `k` is
/// `r_1 (k + 1)^((α - 1) / 2)`. 0.75 is SmallVCM's default and Knaus & Zwicker's choice
/// between variance (α → 1) and bias (α → 0) reduction.
pub const RADIUS_ALPHA: f32 = 0.75;
/// `r_1` in pixel footprints ([`pixel_footprint`]), of vertex connection and merging and
/// of progressive photon mapping alike: the smallest round multiple that meets the pool's
/// goal with both (docs/benchmarks.md, "The first radius from the camera's pixel
/// footprint").
pub const RADIUS_FOOTPRINTS: f32 = 20.0;
/// The largest `r_1`, as a fraction of the scene's bounding radius: the footprint rule's
/// disc must not blur a small image's scene away (at 24 x 24 pixels 20 footprints are
/// most of the view).
pub const RADIUS_MAX_SCENE: f32 = 1.0 / 16.0;
/// `r_1` in units of the scene's bounding radius per pixel of the image's long side, where
/// no camera ray of the footprint survey reaches a surface that merges (SmallVCM's rule).
pub const RADIUS_PIXELS: f32 = 1.5;
/// Camera rays of the footprint survey per image side ([`pixel_footprint`]).
const FOOTPRINT_GRID: u32 = 16;

/// The median pixel footprint of the camera paths' first merge vertices, in world units:
/// the width `ℓ sqrt(Ω)` of a pixel's cone of directions (solid angle `Ω`, from
/// [`crate::camera::CameraModel::pdf_dir`]) at the unfolded length `ℓ` of the camera path to its first
/// non-specular vertex. The survey traces 16 x 16 rays (`FOOTPRINT_GRID`) through pixel
/// centres spread evenly over the `width` x `height` image, at time 0 and through the
/// lens's centre, and follows specular events by their most likely branch (the lobe and
/// direction chosen with every random number at 0.5), for at most `max_depth` bounces:
/// a pure function of the scene and the camera, so every worker computes the same radius.
/// The cone's width ignores how curved specular surfaces widen or narrow it (a flat
/// interface of index `n` narrows the part of the path beyond it by up to `n`): a survey
/// of the merge scale, not a ray differential. Hachisuka & Jensen 2009, section 4, start
/// each hit point's radius from its pixel's footprint; here one radius serves the whole
/// pass (the hash grid's cell and the MIS pseudo-density `η = π r² N` are per pass), so
/// the median stands for the image. `None` when no survey ray reaches a non-specular
/// surface.
pub fn pixel_footprint(
    scene: &RenderScene,
    width: u32,
    height: u32,
    max_depth: u32,
) -> Option<f32> {
    let camera = &scene.camera;
    let (w, h) = (width.max(1) as f32, height.max(1) as f32);
    let mut found = Vec::with_capacity((FOOTPRINT_GRID * FOOTPRINT_GRID) as usize);
    for j in 0..FOOTPRINT_GRID {
        for i in 0..FOOTPRINT_GRID {
            let film = Vec2::new(
                (i as f32 + 0.5) / FOOTPRINT_GRID as f32 * w,
                (j as f32 + 0.5) / FOOTPRINT_GRID as f32 * h,
            );
            let (mut origin, mut dir) = camera.generate_ray(film, Vec2::splat(0.5));
            // `pdf_dir` is the density of directions over the whole image: one pixel's
            // solid angle is `1 / (pdf_dir W H)`.
            let pdf = camera.pdf_dir(origin, dir);
            if !(pdf > 0.0 && pdf.is_finite()) {
                continue;
            }
            let cone = (1.0 / (pdf * w * h)).sqrt();
            let mut length = 0.0f32;
            for _ in 0..max_depth.max(1) {
                let Some(hit) = scene.intersect_at(origin, dir, f32::INFINITY, 0.0) else {
                    break;
                };
                let sp = scene.surface(&hit, origin, dir);
                length += hit.t;
                let bsdf = scene.bsdf(&sp, -dir);
                if bsdf.has_non_delta() {
                    let f = length * cone;
                    if f.is_finite() && f > 0.0 {
                        found.push(f);
                    }
                    break;
                }
                let frame = Frame::from_normal(sp.ns);
                let Some(bs) = bsdf.sample(frame.to_local(-dir), 0.5, Vec2::splat(0.5)) else {
                    break;
                };
                let wi = frame.to_world(bs.wi);
                origin = offset_ray_origin(sp.p, sp.p_error, sp.ng, wi);
                dir = wi;
            }
        }
    }
    if found.is_empty() {
        return None;
    }
    found.sort_by(f32::total_cmp);
    Some(found[found.len() / 2])
}

/// The first pass's merging radius: `footprints` pixel footprints ([`pixel_footprint`]),
/// at most [`RADIUS_MAX_SCENE`] of the scene's bounding radius; [`RADIUS_PIXELS`] scene
/// radii over the image's long side where the survey finds no merge vertex.
pub(super) fn first_radius(
    footprint: Option<f32>,
    footprints: f32,
    scene_radius: f32,
    long: u32,
) -> f32 {
    let r = match footprint {
        Some(f) => (footprints * f).min(RADIUS_MAX_SCENE * scene_radius),
        None => RADIUS_PIXELS * scene_radius / long.max(1) as f32,
    };
    if r.is_finite() {
        r.max(1e-7)
    } else {
        1e-7
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The first radius: the footprints where the survey found one, capped at
    /// [`RADIUS_MAX_SCENE`] of the scene; the scene-fraction rule where it found none.
    #[test]
    fn first_radius_is_footprints_capped_by_the_scene() {
        assert!((first_radius(Some(0.001), 16.0, 10.0, 256) - 0.016).abs() < 1e-7);
        assert!((first_radius(Some(0.1), 16.0, 10.0, 256) - 10.0 / 16.0).abs() < 1e-6);
        assert!((first_radius(None, 16.0, 2.0, 256) - 1.5 * 2.0 / 256.0).abs() < 1e-7);
        assert_eq!(
            first_radius(Some(f32::INFINITY), 16.0, f32::INFINITY, 1),
            1e-7
        );
    }
}
