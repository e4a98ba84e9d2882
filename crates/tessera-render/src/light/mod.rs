//! Light sources and light selection.
//!
//! # The sampling contract
//! [`Light::sample_li`] picks a point (or direction) on the light as seen from a reference
//! point and returns the radiance arriving along `wi` (for delta lights: intensity over
//! squared distance, or irradiance), the solid-angle pdf with respect to `wi` (1 for delta
//! lights, flagged `delta`), and the light point with its floating-point error bound for
//! a robust shadow ray. [`Light::pdf_li`] gives the same density for a direction found by
//! BSDF sampling, for multiple importance sampling (Veach & Guibas 1995).
//!
//! [`LightSet`] chooses one light per sample in two ways. [`LightSet::select`]: with
//! probability proportional to its emitted power (luminance), Shirley 2001, chapter 3
//! ("many lights"); bidirectional path tracing starts light subpaths with it, which have no
//! reference point. [`LightSet::select_at`]: by the light hierarchy of [`tree`], in
//! proportion to an estimate of each light's contribution to a reference point (Conty
//! Estevez & Kulla 2018); the path tracer's next-event estimation uses it, and weighs
//! emission found by BSDF sampling against [`LightSet::pmf_at`] of the previous vertex.
//!
//! Bidirectional path tracing's light-sampling connections (`s = 1`) draw their points with
//! [`Light::sample_li`], which for large triangles samples by solid angle, and divide by
//! that density; their MIS weights use the light-origin area density for every technique
//! alike, as pbrt-v4 does, so the weights still sum to one and the estimate stays unbiased
//! (`tests/it/bdpt.rs` compares bdpt with the path tracer).
//!
//! Variants, one file each: [`triangle`] (emissive triangles: area lights), [`sphere`]
//! (spherical lights, sampled by the cone they subtend), [`punctual`] (point, spot,
//! directional), [`environment`] (uniform or image environment). [`emission`] samples rays leaving
//! each light, for the light subpaths of bidirectional path tracing.

pub mod emission;
pub mod environment;
pub mod punctual;
pub mod sphere;
pub mod tree;
pub mod triangle;

use crate::math::luminance;
use glam::{Vec2, Vec3};

/// A sample of incident light at a reference point.
#[derive(Clone, Copy, Debug)]
pub struct LightSample {
    /// Unit direction from the reference point toward the light.
    pub wi: Vec3,
    /// Distance to the light point (infinite for distant lights).
    pub dist: f32,
    /// The point on the light (for shadow rays; unused when `dist` is infinite).
    pub p: Vec3,
    /// Error bound of `p`.
    pub p_error: Vec3,
    /// Surface normal at `p` (zero for punctual lights).
    pub n: Vec3,
    /// Incident radiance (or, for delta lights, irradiance-like `I / d²` or `E`).
    pub li: Vec3,
    /// Solid-angle density of `wi` (1 for delta lights).
    pub pdf: f32,
    /// A delta light: no other technique can find it.
    pub delta: bool,
}

/// A light source. The closed list of emitters.
#[derive(Clone, Debug)]
pub enum Light {
    /// An emissive triangle.
    Triangle(triangle::TriangleLight),
    /// An emissive sphere.
    Sphere(sphere::SphereLight),
    /// A point, spot or directional light.
    Punctual(punctual::Punctual),
    /// The environment: uniform or an image.
    Environment(environment::Environment),
}

impl Light {
    /// Samples incident light at `p_ref` from `u`.
    #[inline]
    pub fn sample_li(&self, p_ref: Vec3, u: Vec2) -> Option<LightSample> {
        match self {
            Light::Triangle(l) => l.sample_li(p_ref, u),
            Light::Sphere(l) => l.sample_li(p_ref, u),
            Light::Punctual(l) => l.sample_li(p_ref),
            Light::Environment(l) => l.sample_li(u),
        }
    }

    /// Solid-angle density with which [`Light::sample_li`] would produce the direction from
    /// `p_ref` to the light point `p_light` (normal `n_light`); for the environment, the
    /// direction `wi`.
    #[inline]
    pub fn pdf_li(&self, p_ref: Vec3, wi: Vec3, p_light: Vec3, n_light: Vec3) -> f32 {
        match self {
            Light::Triangle(l) => l.pdf_li(p_ref, p_light, n_light),
            Light::Sphere(l) => l.pdf_li(p_ref, p_light, n_light),
            Light::Punctual(_) => 0.0,
            Light::Environment(l) => l.pdf_li(wi),
        }
    }

    /// Emitted power (luminance of W per channel), for light selection.
    pub fn power(&self) -> f32 {
        match self {
            Light::Triangle(l) => luminance(l.power()),
            Light::Sphere(l) => luminance(l.power()),
            Light::Punctual(l) => luminance(l.power()),
            Light::Environment(l) => luminance(l.power()),
        }
    }

    /// True for point, spot and directional lights.
    pub fn is_delta(&self) -> bool {
        matches!(self, Light::Punctual(_))
    }
}

/// All lights of a scene with a power-proportional selection distribution and a light
/// hierarchy for selection from a reference point.
#[derive(Clone, Debug, Default)]
pub struct LightSet {
    /// The lights.
    pub lights: Vec<Light>,
    cdf: Vec<f32>,
    pmf: Vec<f32>,
    /// Index of the environment light, if any.
    pub environment: Option<u32>,
    /// The light hierarchy; `None` selects by power from every reference point.
    tree: Option<tree::LightTree>,
}

impl LightSet {
    /// Builds the selection distributions: by power, and the light hierarchy. Lights with
    /// zero power are never selected.
    pub fn new(lights: Vec<Light>) -> Self {
        let mut set = Self::with_power_selection(lights);
        set.tree = Some(tree::LightTree::build(&set.lights, &set.pmf));
        set
    }

    /// A set without the light hierarchy: [`LightSet::select_at`] and
    /// [`LightSet::pmf_at`] are [`LightSet::select`] and [`LightSet::pmf`] at every
    /// reference point. For comparisons (the tree must not change the expected image).
    pub fn with_power_selection(lights: Vec<Light>) -> Self {
        let powers: Vec<f64> = lights.iter().map(|l| l.power().max(0.0) as f64).collect();
        let total: f64 = powers.iter().sum();
        let mut cdf = Vec::with_capacity(lights.len());
        let mut pmf = Vec::with_capacity(lights.len());
        let mut acc = 0.0f64;
        for p in &powers {
            let q = if total > 0.0 { p / total } else { 0.0 };
            acc += q;
            pmf.push(q as f32);
            cdf.push(acc as f32);
        }
        if let Some(last) = cdf.last_mut() {
            *last = 1.0;
        }
        let environment = lights
            .iter()
            .position(|l| matches!(l, Light::Environment(_)))
            .map(|i| i as u32);
        Self {
            lights,
            cdf,
            pmf,
            environment,
            tree: None,
        }
    }

    /// True if no light has positive power.
    pub fn is_empty(&self) -> bool {
        self.pmf.iter().all(|&p| p <= 0.0)
    }

    /// Picks a light with probability proportional to power: (index, probability).
    #[inline]
    pub fn select(&self, u: f32) -> Option<(usize, f32)> {
        if self.lights.is_empty() {
            return None;
        }
        let i = self
            .cdf
            .partition_point(|&c| c <= u)
            .min(self.lights.len() - 1);
        let p = self.pmf[i];
        if p <= 0.0 {
            return None;
        }
        Some((i, p))
    }

    /// Probability of selecting light `index`.
    #[inline]
    pub fn pmf(&self, index: usize) -> f32 {
        self.pmf.get(index).copied().unwrap_or(0.0)
    }

    /// Picks a light for the reference point `p` with normal `n` (`Vec3::ZERO` when the
    /// surface transmits, so that lights on both sides count): (index, probability), by the
    /// light hierarchy. `None` when no light can contribute there.
    #[inline]
    pub fn select_at(&self, u: f32, p: Vec3, n: Vec3) -> Option<(usize, f32)> {
        match &self.tree {
            Some(t) => t.select(u, p, n),
            None => self.select(u),
        }
    }

    /// The probability with which [`LightSet::select_at`] picks light `index` from `(p, n)`:
    /// exactly the probability it reports, `O(depth)`.
    #[inline]
    pub fn pmf_at(&self, p: Vec3, n: Vec3, index: usize) -> f32 {
        match &self.tree {
            Some(t) => t.pmf(p, n, index),
            None => self.pmf(index),
        }
    }
}

#[cfg(test)]
mod tests;
