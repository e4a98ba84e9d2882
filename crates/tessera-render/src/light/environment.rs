//! A uniform environment: radiance `L` arriving from every direction not blocked by the
//! scene. Sampled uniformly over the sphere of directions, `pdf_ω = 1 / (4π)`.

use super::LightSample;
use crate::sampling::warp::{square_to_uniform_sphere, uniform_sphere_pdf};
use glam::{Vec2, Vec3};
use std::f32::consts::PI;

/// Uniform environment light.
#[derive(Clone, Copy, Debug)]
pub struct Environment {
    /// Radiance.
    pub radiance: Vec3,
    /// Radius of the scene's bounding sphere (for the power estimate).
    pub scene_radius: f32,
}

impl Environment {
    pub(crate) fn power(&self) -> Vec3 {
        // Power entering the bounding sphere: π L times its area.
        self.radiance * (4.0 * PI * PI * self.scene_radius * self.scene_radius)
    }

    pub(crate) fn sample_li(&self, u: Vec2) -> Option<LightSample> {
        let wi = square_to_uniform_sphere(u);
        Some(LightSample {
            wi,
            dist: f32::INFINITY,
            p: Vec3::ZERO,
            p_error: Vec3::ZERO,
            n: Vec3::ZERO,
            li: self.radiance,
            pdf: uniform_sphere_pdf(),
            delta: false,
        })
    }

    pub(crate) fn pdf_li(&self, _wi: Vec3) -> f32 {
        uniform_sphere_pdf()
    }
}
