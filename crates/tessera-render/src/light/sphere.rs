//! Spherical lights, sampled by the cone of directions they subtend (Shirley 2001,
//! chapter 3 "spherical luminaires"): from a point outside, the sphere covers a cone of half
//! angle θmax with `sin² θmax = r² / d²`; directions are drawn uniformly in that cone,
//! `pdf_ω = 1 / (2π (1 - cos θmax))`, so every sample hits the light. From a point inside,
//! the light is sampled uniformly by area.
//!
//! | parameter | meaning |
//! |---|---|
//! | `center`, `radius` | geometry |
//! | `radiance` | emitted radiance, W/(m² sr), outward |
//!
//! `1 - cos θmax` is computed as `sin² / (1 + cos)` so that tiny, distant spheres (Veach's
//! smallest light subtends ~1e-5 sr) keep their precision in f32.

use super::LightSample;
use crate::geometry::sphere_point;
use crate::sampling::warp::{square_to_uniform_sphere, Frame};
use glam::{Vec2, Vec3};
use std::f32::consts::{PI, TAU};

/// An emissive sphere.
#[derive(Clone, Copy, Debug)]
pub struct SphereLight {
    /// Centre.
    pub center: Vec3,
    /// Radius.
    pub radius: f32,
    /// Outward radiance.
    pub radiance: Vec3,
}

impl SphereLight {
    pub(crate) fn power(&self) -> Vec3 {
        // π L times the area 4π r².
        self.radiance * (4.0 * PI * PI * self.radius * self.radius)
    }

    /// `1 - cos θmax` of the subtended cone seen from distance² `d2`, or `None` inside.
    #[inline]
    fn one_minus_cos_max(&self, d2: f32) -> Option<f32> {
        let r2 = self.radius * self.radius;
        if d2 <= r2 * (1.0 + 1e-4) {
            return None;
        }
        let sin2 = r2 / d2;
        let cos = (1.0 - sin2).max(0.0).sqrt();
        Some(sin2 / (1.0 + cos))
    }

    pub(crate) fn sample_li(&self, p_ref: Vec3, u: Vec2) -> Option<LightSample> {
        let to_center = self.center - p_ref;
        let d2 = to_center.length_squared();
        let Some(omc) = self.one_minus_cos_max(d2) else {
            return self.sample_area(p_ref, u);
        };
        let d = d2.sqrt();
        // Uniform in the cone: 1 - cos θ = u0 (1 - cos θmax).
        let one_minus_cos = u.x * omc;
        let cos_theta = 1.0 - one_minus_cos;
        let sin2_theta = (one_minus_cos * (2.0 - one_minus_cos)).max(0.0);
        let sin_theta = sin2_theta.sqrt();
        let phi = TAU * u.y;
        let frame = Frame::from_normal(to_center / d);
        let wi = frame
            .to_world(Vec3::new(
                sin_theta * phi.cos(),
                sin_theta * phi.sin(),
                cos_theta,
            ))
            .normalize();
        // Distance to the near intersection along wi.
        let r2 = self.radius * self.radius;
        let ds = d * cos_theta - (r2 - d2 * sin2_theta).max(0.0).sqrt();
        let (p, p_error, n) = sphere_point(self.center, self.radius, p_ref + wi * ds);
        let pdf = 1.0 / (TAU * omc);
        Some(LightSample {
            wi,
            dist: (p - p_ref).length(),
            p,
            p_error,
            n,
            li: self.radiance,
            pdf,
            delta: false,
        })
    }

    fn sample_area(&self, p_ref: Vec3, u: Vec2) -> Option<LightSample> {
        let n = square_to_uniform_sphere(u);
        let (p, p_error, n) = sphere_point(self.center, self.radius, self.center + n * self.radius);
        let d = p - p_ref;
        let dist2 = d.length_squared();
        let dist = dist2.sqrt();
        let wi = d / dist;
        let cos_l = n.dot(-wi);
        // Outward emission only: from inside, the sphere is dark.
        if cos_l <= 0.0 {
            return None;
        }
        let area = 4.0 * PI * self.radius * self.radius;
        let pdf = dist2 / (cos_l * area);
        Some(LightSample {
            wi,
            dist,
            p,
            p_error,
            n,
            li: self.radiance,
            pdf,
            delta: false,
        })
    }

    pub(crate) fn pdf_li(&self, p_ref: Vec3, p_light: Vec3, n_light: Vec3) -> f32 {
        let d2 = (self.center - p_ref).length_squared();
        match self.one_minus_cos_max(d2) {
            Some(omc) => 1.0 / (TAU * omc),
            None => {
                let d = p_light - p_ref;
                let dist2 = d.length_squared();
                let cos_l = n_light.dot(-d) / dist2.sqrt();
                if cos_l <= 0.0 {
                    return 0.0;
                }
                dist2 / (cos_l * 4.0 * PI * self.radius * self.radius)
            }
        }
    }
}
