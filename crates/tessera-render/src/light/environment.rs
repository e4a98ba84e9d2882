//! The environment: radiance arriving from every direction not blocked by the scene.
//!
//! Uniform (`L` from everywhere, sampled uniformly over the sphere, `pdf_ω = 1 / (4π)`), or
//! an equirectangular image ([`tessera_scene::environment`] gives its mapping) scaled by
//! `L`. The image is read texel by texel (nearest, no filtering), so its radiance is
//! piecewise constant in `(u, v)` and sampling can follow it exactly: pbrt-v4's image
//! infinite light (Pharr, Jakob & Humphreys, 4th ed., section 12.5.2) with the
//! piecewise-constant 2D distribution of section A.5.6 ("PiecewiseConstant2D": a marginal
//! over rows, a conditional over the columns of each row) built from luminance × `sin θ`
//! (the equirectangular map's area distortion), so that
//! `pdf_ω(ω) = pdf_uv(u, v) / (2π² sin θ)` (section 12.5.2, equation 12.26 with the
//! latitude–longitude Jacobian `2π² sin θ` of pbrt-v3's section 14.2.4).

use super::LightSample;
use crate::sampling::warp::{square_to_uniform_sphere, uniform_sphere_pdf};
use glam::{Mat3, Vec2, Vec3};
use std::f32::consts::PI;
use std::sync::Arc;
use tessera_scene::EnvironmentMap;

/// The environment light.
#[derive(Clone, Debug)]
pub struct Environment {
    /// Radiance of a uniform environment; with an image, the factor multiplying it.
    pub radiance: Vec3,
    /// Radius of the scene's bounding sphere (for the power estimate).
    pub scene_radius: f32,
    /// The image and its sampling distribution; `None` for a uniform environment.
    pub image: Option<Arc<EnvImage>>,
}

impl Environment {
    /// A uniform environment of radiance `radiance`.
    pub fn uniform(radiance: Vec3, scene_radius: f32) -> Self {
        Self {
            radiance,
            scene_radius,
            image: None,
        }
    }

    /// Radiance arriving from direction `wi` (unit, pointing from the scene toward the
    /// environment).
    #[inline]
    pub fn le(&self, wi: Vec3) -> Vec3 {
        match &self.image {
            None => self.radiance,
            Some(im) => self.radiance * im.lookup(wi),
        }
    }

    pub(crate) fn power(&self) -> Vec3 {
        match &self.image {
            // Power entering the bounding sphere: π L times its area.
            None => self.radiance * (4.0 * PI * PI * self.scene_radius * self.scene_radius),
            // The same for a direction-dependent L: the flux through the bounding disk,
            // π R² ∫ L dω.
            Some(im) => self.radiance * im.integral * (PI * self.scene_radius * self.scene_radius),
        }
    }

    pub(crate) fn sample_li(&self, u: Vec2) -> Option<LightSample> {
        let (wi, li, pdf) = match &self.image {
            None => (
                square_to_uniform_sphere(u),
                self.radiance,
                uniform_sphere_pdf(),
            ),
            Some(im) => {
                let (wi, texel, pdf) = im.sample(u)?;
                (wi, self.radiance * texel, pdf)
            }
        };
        Some(LightSample {
            wi,
            dist: f32::INFINITY,
            p: Vec3::ZERO,
            p_error: Vec3::ZERO,
            n: Vec3::ZERO,
            li,
            pdf,
            delta: false,
        })
    }

    pub(crate) fn pdf_li(&self, wi: Vec3) -> f32 {
        match &self.image {
            None => uniform_sphere_pdf(),
            Some(im) => im.pdf(wi),
        }
    }
}

/// A piecewise-constant density on [0, 1) (pbrt-v4's `PiecewiseConstant1D`, Pharr, Jakob &
/// Humphreys, 4th ed., section A.5.5): `n` equal steps of height `func[i]`.
#[derive(Clone, Debug)]
struct Piecewise1D {
    func: Vec<f32>,
    /// `cdf[i]` = ∫₀^{i/n} f / ∫ f, `n + 1` entries from 0 to 1.
    cdf: Vec<f32>,
    /// ∫₀¹ f.
    integral: f32,
}

impl Piecewise1D {
    fn new(func: Vec<f32>) -> Self {
        let n = func.len();
        let mut acc = vec![0.0f64; n + 1];
        for (i, &f) in func.iter().enumerate() {
            acc[i + 1] = acc[i] + f64::from(f) / n as f64;
        }
        let integral = acc[n];
        let cdf = if integral > 0.0 {
            acc.iter().map(|&c| (c / integral) as f32).collect()
        } else {
            // Nothing to follow: uniform steps (the density reports 0 everywhere).
            (0..=n).map(|i| i as f32 / n as f32).collect()
        };
        Self {
            func,
            cdf,
            integral: integral as f32,
        }
    }

    /// `(x, density at x, step index)` for `u` in [0, 1).
    #[inline]
    fn sample(&self, u: f32) -> (f32, f32, usize) {
        let n = self.func.len();
        let o = self
            .cdf
            .partition_point(|&c| c <= u)
            .saturating_sub(1)
            .min(n - 1);
        let width = self.cdf[o + 1] - self.cdf[o];
        let du = if width > 0.0 {
            ((u - self.cdf[o]) / width).clamp(0.0, 1.0)
        } else {
            0.0
        };
        let x = ((o as f32 + du) / n as f32).min(1.0 - f32::EPSILON / 2.0);
        let pdf = if self.integral > 0.0 {
            self.func[o] / self.integral
        } else {
            0.0
        };
        (x, pdf, o)
    }
}

/// An environment image prepared for lookup and importance sampling.
#[derive(Clone)]
pub struct EnvImage {
    width: usize,
    height: usize,
    texels: Arc<[Vec3]>,
    world_from_env: Mat3,
    env_from_world: Mat3,
    /// Over rows (`v`): each row's integral of its conditional.
    marginal: Piecewise1D,
    /// Per row, over columns (`u`): luminance × `sin θ` of the row's centre.
    conditional: Vec<Piecewise1D>,
    /// ∫ L dω over the sphere, per channel (unscaled).
    pub integral: Vec3,
}

impl std::fmt::Debug for EnvImage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("EnvImage")
            .field("width", &self.width)
            .field("height", &self.height)
            .field("integral", &self.integral)
            .finish_non_exhaustive()
    }
}

impl EnvImage {
    /// Builds the sampling distribution of `map` (`O(texels)` time and 8 bytes of
    /// distribution per texel besides the 12 of the texel).
    pub fn new(map: &EnvironmentMap) -> Self {
        let (w, h) = (map.width as usize, map.height as usize);
        let mut conditional = Vec::with_capacity(h);
        let mut integral = [0.0f64; 3];
        for row in 0..h {
            let (t0, t1) = (PI * row as f32 / h as f32, PI * (row + 1) as f32 / h as f32);
            let sin_theta = (PI * (row as f32 + 0.5) / h as f32).sin();
            // Solid angle of one texel of this row: (2π / w)(cos θ0 - cos θ1).
            let omega = (2.0 * std::f64::consts::PI / w as f64)
                * (f64::from(t0).cos() - f64::from(t1).cos());
            let texels = &map.texels[row * w..(row + 1) * w];
            for t in texels {
                for (k, acc) in integral.iter_mut().enumerate() {
                    *acc += f64::from(t[k]) * omega;
                }
            }
            conditional.push(Piecewise1D::new(
                texels
                    .iter()
                    .map(|&t| crate::math::luminance(t).max(0.0) * sin_theta)
                    .collect(),
            ));
        }
        let marginal = Piecewise1D::new(conditional.iter().map(|c| c.integral).collect());
        let world_from_env = Mat3::from_rotation_y(map.rotation);
        Self {
            width: w,
            height: h,
            texels: map.texels.clone(),
            world_from_env,
            env_from_world: world_from_env.transpose(),
            marginal,
            conditional,
            integral: Vec3::new(integral[0] as f32, integral[1] as f32, integral[2] as f32),
        }
    }

    /// Image coordinates `(u, v)` in [0, 1]² of the world direction `w`, and `sin θ`.
    #[inline]
    fn uv(&self, w: Vec3) -> (Vec2, f32) {
        let d = self.env_from_world * w;
        let cos_theta = d.y.clamp(-1.0, 1.0);
        let phi = d.z.atan2(d.x);
        let u = 0.5 + phi / (2.0 * PI);
        let v = cos_theta.acos() / PI;
        // From the horizontal part: accurate near the poles, where 1 - cos² cancels.
        let sin_theta = (d.x * d.x + d.z * d.z).sqrt().min(1.0);
        (Vec2::new(u, v), sin_theta)
    }

    /// Texel (column, row) containing `uv`.
    #[inline]
    fn texel_of(&self, uv: Vec2) -> (usize, usize) {
        let col = ((uv.x * self.width as f32) as usize).min(self.width - 1);
        let row = ((uv.y * self.height as f32) as usize).min(self.height - 1);
        (col, row)
    }

    /// The image's radiance toward world direction `w` (nearest texel).
    #[inline]
    pub fn lookup(&self, w: Vec3) -> Vec3 {
        let (col, row) = self.texel_of(self.uv(w).0);
        self.texels[row * self.width + col]
    }

    /// Solid-angle density of [`EnvImage::sample`] producing `w`.
    #[inline]
    pub fn pdf(&self, w: Vec3) -> f32 {
        let (uv, sin_theta) = self.uv(w);
        if sin_theta <= 0.0 || self.marginal.integral <= 0.0 {
            return 0.0;
        }
        let (col, row) = self.texel_of(uv);
        let pdf_uv = self.conditional[row].func[col] / self.marginal.integral;
        pdf_uv / (2.0 * PI * PI * sin_theta)
    }

    /// A direction drawn in proportion to luminance: `(w, texel radiance, solid-angle pdf)`.
    #[inline]
    pub fn sample(&self, u: Vec2) -> Option<(Vec3, Vec3, f32)> {
        let (v, pdf_v, row) = self.marginal.sample(u.y);
        let (uu, pdf_u, col) = self.conditional[row].sample(u.x);
        let pdf_uv = pdf_v * pdf_u;
        let theta = PI * v;
        let phi = 2.0 * PI * (uu - 0.5);
        let (sin_theta, cos_theta) = theta.sin_cos();
        if pdf_uv <= 0.0 || sin_theta <= 0.0 {
            return None;
        }
        let d = Vec3::new(sin_theta * phi.cos(), cos_theta, sin_theta * phi.sin());
        let w = (self.world_from_env * d).normalize();
        let pdf = pdf_uv / (2.0 * PI * PI * sin_theta);
        Some((w, self.texels[row * self.width + col], pdf))
    }
}
