//! The perspective camera: pinhole, or thin lens when the aperture is open.
//!
//! Film coordinates: pixel (x, y) with y down; the camera looks down its local -Z with +Y
//! up (glTF). A thin lens samples the aperture with the concentric disk map (seed 000
//! ch. 4) and focuses on the plane `z = -focus_distance`.

use crate::sampling::warp::square_to_concentric_disk;
use glam::{Mat4, Vec2, Vec3};
use tessera_scene::Camera;

/// A camera prepared for a given image size.
#[derive(Clone, Copy, Debug)]
pub struct CameraModel {
    world_from_camera: Mat4,
    origin: Vec3,
    tan_half_y: f32,
    tan_half_x: f32,
    width: f32,
    height: f32,
    lens_radius: f32,
    focus_distance: f32,
}

impl CameraModel {
    /// Prepares `camera` for a `width` x `height` image (the image's aspect ratio wins over
    /// the scene's).
    pub fn new(camera: &Camera, width: u32, height: u32) -> Self {
        let tan_half_y = (camera.yfov * 0.5).tan();
        let aspect = width as f32 / height as f32;
        Self {
            world_from_camera: camera.world_from_camera,
            origin: camera.world_from_camera.transform_point3(Vec3::ZERO),
            tan_half_y,
            tan_half_x: tan_half_y * aspect,
            width: width as f32,
            height: height as f32,
            lens_radius: camera.aperture_radius,
            focus_distance: camera.focus_distance,
        }
    }

    /// True when the lens has an aperture (depth of field needs a lens sample).
    pub fn has_lens(&self) -> bool {
        self.lens_radius > 0.0
    }

    /// Primary ray through film position `film` (in pixels) and lens sample `lens`:
    /// (origin, unit direction).
    #[inline]
    pub fn generate_ray(&self, film: Vec2, lens: Vec2) -> (Vec3, Vec3) {
        let ndc_x = 2.0 * film.x / self.width - 1.0;
        let ndc_y = 1.0 - 2.0 * film.y / self.height;
        let dir_cam = Vec3::new(ndc_x * self.tan_half_x, ndc_y * self.tan_half_y, -1.0);
        if self.lens_radius > 0.0 {
            let l = square_to_concentric_disk(lens) * self.lens_radius;
            let p_lens = Vec3::new(l.x, l.y, 0.0);
            let p_focus = dir_cam * self.focus_distance;
            let o = self.world_from_camera.transform_point3(p_lens);
            let d = self
                .world_from_camera
                .transform_vector3(p_focus - p_lens)
                .normalize();
            (o, d)
        } else {
            (
                self.origin,
                self.world_from_camera
                    .transform_vector3(dir_cam)
                    .normalize(),
            )
        }
    }
}
