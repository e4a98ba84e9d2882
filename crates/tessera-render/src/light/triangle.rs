//! Emissive triangles (area lights).
//!
//! | parameter | meaning |
//! |---|---|
//! | `p` | vertices; the front is counter-clockwise, `n = normalize((p1-p0) x (p2-p0))` |
//! | `radiance` | emitted radiance W/(m² sr), constant over the triangle |
//! | `two_sided` | emit on both sides; otherwise only along `n` (glTF `doubleSided`) |
//! | `power_scale`, `shading` | a textured emitter: its mean texture value (for selection) and the mesh triangle where [`crate::scene::RenderScene`] evaluates the texture |
//!
//! Sampled uniformly by area (Arvo 2001, chapter 4, triangle warp) and converted to solid angle:
//! `pdf_ω = d² / (|cos θ_l| A)` (Shirley 2001, chapter 3).

use super::LightSample;
use crate::geometry::triangle_point;
use crate::sampling::warp::square_to_uniform_triangle;
use glam::{Vec2, Vec3};
use std::f32::consts::PI;

/// An emissive triangle.
#[derive(Clone, Copy, Debug)]
pub struct TriangleLight {
    /// Vertices.
    pub p: [Vec3; 3],
    /// Unit geometric normal.
    pub n: Vec3,
    /// Area.
    pub area: f32,
    /// Emitted radiance.
    pub radiance: Vec3,
    /// Emits on both sides.
    pub two_sided: bool,
    /// Mean of the emission's variation over the triangle (emissive texture, alpha
    /// coverage), which scales the power used for light selection; 1 when constant.
    pub power_scale: Vec3,
    /// `(mesh, triangle)` when the emission varies over the triangle: the render scene
    /// then evaluates it where a point is sampled.
    pub shading: Option<(u32, u32)>,
}

impl TriangleLight {
    /// Builds the light; `None` for degenerate triangles.
    pub fn new(p: [Vec3; 3], radiance: Vec3, two_sided: bool) -> Option<Self> {
        let c = (p[1] - p[0]).cross(p[2] - p[0]);
        let len = c.length();
        if !(len > 0.0 && len.is_finite()) {
            return None;
        }
        Some(Self {
            p,
            n: c / len,
            area: 0.5 * len,
            radiance,
            two_sided,
            power_scale: Vec3::ONE,
            shading: None,
        })
    }

    /// Radiance leaving the light toward `w` (unit, pointing away from the light).
    #[inline]
    pub fn emitted(&self, w: Vec3) -> Vec3 {
        if self.two_sided || self.n.dot(w) > 0.0 {
            self.radiance
        } else {
            Vec3::ZERO
        }
    }

    pub(crate) fn power(&self) -> Vec3 {
        self.radiance * self.power_scale * (PI * self.area * if self.two_sided { 2.0 } else { 1.0 })
    }

    pub(crate) fn sample_li(&self, p_ref: Vec3, u: Vec2) -> Option<LightSample> {
        let (b0, b1) = square_to_uniform_triangle(u);
        let b2 = 1.0 - b0 - b1;
        let (p, p_error) = triangle_point(&self.p, b0, b1, b2);
        let d = p - p_ref;
        let dist2 = d.length_squared();
        if dist2 <= 0.0 {
            return None;
        }
        let dist = dist2.sqrt();
        let wi = d / dist;
        let cos_l = self.n.dot(-wi);
        let li = self.emitted(-wi);
        if cos_l == 0.0 || li == Vec3::ZERO {
            return None;
        }
        let pdf = dist2 / (cos_l.abs() * self.area);
        if !pdf.is_finite() {
            return None;
        }
        Some(LightSample {
            wi,
            dist,
            p,
            p_error,
            n: self.n,
            li,
            pdf,
            delta: false,
        })
    }

    pub(crate) fn pdf_li(&self, p_ref: Vec3, p_light: Vec3, n_light: Vec3) -> f32 {
        let d = p_light - p_ref;
        let dist2 = d.length_squared();
        let cos_l = n_light.dot(d) / dist2.sqrt();
        if cos_l == 0.0 {
            return 0.0;
        }
        dist2 / (cos_l.abs() * self.area)
    }
}
