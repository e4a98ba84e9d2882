//! The perspective camera: pinhole, or thin lens when the aperture is open.
//!
//! Film coordinates: pixel (x, y) with y down; the camera looks down its local -Z with +Y
//! up (glTF). A thin lens samples the aperture with the concentric disk map (Arvo 2001,
//! chapter 4) and focuses on the plane `z = -focus_distance`.
//!
//! # Importance (for light tracing)
//! Bidirectional path tracing connects light-subpath vertices to the camera, so the camera
//! is also an emitter of *importance* `We` (the adjoint of radiance, Hanrahan 2001, chapter 7 "Adjoint
//! equations and importance sampling"). With the image plane at distance 1 of area
//! `A = 4 tan(fov_x/2) tan(fov_y/2)` and a lens of area `A_lens` (1 for a pinhole, whose
//! position is a delta), pbrt 3rd ed. §16.1.1:
//!
//! - `We(p_lens, ω) = 1 / (A A_lens cos⁴ θ)` for ω inside the image, θ from the optical axis;
//! - the camera samples ray directions with `pdf_dir = 1 / (A cos³ θ)` and lens points with
//!   `pdf_pos = 1 / A_lens`;
//! - [`CameraModel::sample_wi`] picks a lens point seen from a scene point, with density
//!   `d² / (|cos θ| A_lens)` in solid angle at that point.
//!
//! `We` is normalised over the whole image: one light path's splat `We ...` estimates the
//! image sum, and the splats of `N` light paths per pixel, divided by `N`, estimate each
//! pixel's mean (see `integrator::bdpt`).

use crate::sampling::warp::square_to_concentric_disk;
use glam::{Mat4, Vec2, Vec3};
use tessera_scene::Camera;

/// A camera prepared for a given image size.
#[derive(Clone, Copy, Debug)]
pub struct CameraModel {
    world_from_camera: Mat4,
    camera_from_world: Mat4,
    /// Unit optical axis in world space (the camera's local -Z).
    forward: Vec3,
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
            camera_from_world: camera.world_from_camera.inverse(),
            forward: camera
                .world_from_camera
                .transform_vector3(Vec3::NEG_Z)
                .normalize_or(Vec3::NEG_Z),
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

    /// Area of the image on the plane at distance 1, `A = 4 tan(fov_x/2) tan(fov_y/2)`.
    #[inline]
    pub fn film_area(&self) -> f32 {
        4.0 * self.tan_half_x * self.tan_half_y
    }

    /// Lens area, 1 for a pinhole (a delta position, measured with density 1).
    #[inline]
    pub fn lens_area(&self) -> f32 {
        if self.lens_radius > 0.0 {
            std::f32::consts::PI * self.lens_radius * self.lens_radius
        } else {
            1.0
        }
    }

    /// Unit optical axis in world space.
    #[inline]
    pub fn forward(&self) -> Vec3 {
        self.forward
    }

    /// Film position (pixels, y down) of the ray leaving the lens point `p_lens` (world) in
    /// direction `w` (unit, world), with `cos θ` to the optical axis; `None` if the ray points
    /// backwards or lands outside the image. The inverse of [`CameraModel::generate_ray`].
    #[inline]
    pub fn raster(&self, p_lens: Vec3, w: Vec3) -> Option<(Vec2, f32)> {
        let cos = w.dot(self.forward);
        if cos <= 0.0 {
            return None;
        }
        let d = self.camera_from_world.transform_vector3(w);
        if d.z >= 0.0 {
            return None;
        }
        // Direction through the film on the plane z = -1 (pinhole), or through the point
        // where the ray meets the focus plane (thin lens).
        let q = if self.lens_radius > 0.0 {
            let pl = self.camera_from_world.transform_point3(p_lens);
            let t = self.focus_distance / -d.z;
            (pl + d * t) / self.focus_distance
        } else {
            d / -d.z
        };
        let film = Vec2::new(
            (q.x / self.tan_half_x + 1.0) * 0.5 * self.width,
            (1.0 - q.y / self.tan_half_y) * 0.5 * self.height,
        );
        let inside = film.x >= 0.0 && film.x < self.width && film.y >= 0.0 && film.y < self.height;
        (inside && film.is_finite()).then_some((film, cos))
    }

    /// Solid-angle density with which [`CameraModel::generate_ray`] (film position uniform
    /// over the image) produces direction `w` from lens point `p_lens`: `1 / (A cos³ θ)`, zero
    /// outside the image.
    #[inline]
    pub fn pdf_dir(&self, p_lens: Vec3, w: Vec3) -> f32 {
        match self.raster(p_lens, w) {
            Some((_, cos)) => 1.0 / (self.film_area() * cos * cos * cos),
            None => 0.0,
        }
    }

    /// Samples the lens as seen from the scene point `p_ref` (for light tracing): the
    /// importance arriving at `p_ref` from the camera and where it lands on the film.
    #[inline]
    pub fn sample_wi(&self, p_ref: Vec3, u: Vec2) -> Option<CameraSample> {
        let p_lens = if self.lens_radius > 0.0 {
            let l = square_to_concentric_disk(u) * self.lens_radius;
            self.world_from_camera
                .transform_point3(Vec3::new(l.x, l.y, 0.0))
        } else {
            self.origin
        };
        let d = p_lens - p_ref;
        let dist2 = d.length_squared();
        if dist2.is_nan() || dist2 <= 0.0 {
            return None;
        }
        let dist = dist2.sqrt();
        let wi = d / dist;
        let (raster, cos) = self.raster(p_lens, -wi)?;
        let lens_area = self.lens_area();
        let cos2 = cos * cos;
        let we = 1.0 / (self.film_area() * lens_area * cos2 * cos2);
        let pdf = dist2 / (cos * lens_area);
        (we.is_finite() && pdf.is_finite()).then_some(CameraSample {
            p_lens,
            wi,
            dist,
            we,
            pdf,
            raster,
        })
    }
}

/// A lens point sampled from a scene point by [`CameraModel::sample_wi`].
#[derive(Clone, Copy, Debug)]
pub struct CameraSample {
    /// The point on the lens (the pinhole for a pinhole camera).
    pub p_lens: Vec3,
    /// Unit direction from the scene point toward `p_lens`.
    pub wi: Vec3,
    /// Distance from the scene point to `p_lens`.
    pub dist: f32,
    /// Importance `We` of the ray from `p_lens` toward the scene point.
    pub we: f32,
    /// Solid-angle density of `wi` at the scene point.
    pub pdf: f32,
    /// Film position (pixels, y down) where the ray lands.
    pub raster: Vec2,
}
