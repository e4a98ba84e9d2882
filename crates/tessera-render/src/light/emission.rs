//! Emission sampling: where light leaves a light source and in which direction, for the
//! light subpaths of bidirectional path tracing (Veach & Guibas 1995, section 4.3: "the
//! light subpath is constructed by choosing a random point on a light source (area
//! sampling), followed by casting a random ray (directional sampling)").
//!
//! # The sampling contract
//! [`Light::sample_le`] returns a ray leaving the light: its origin `p` (with its error
//! bound), the light's normal `n` at `p` (zero for point-like and distant lights), the unit
//! direction of travel `dir`, the emitted quantity `le`, and two densities:
//!
//! | light | `le` | `pdf_pos` | `pdf_dir` |
//! |---|---|---|---|
//! | triangle | radiance L | `1 / area` (area measure) | `cos θ / π` (cosine about `n`; `|cos θ| / 2π` two-sided) |
//! | sphere | radiance L | `1 / (4π r²)` | `cos θ / π` about the outward normal |
//! | point | intensity I | 1 (delta position) | `1 / (4π)` |
//! | spot | `I s(θ)` (glTF falloff) | 1 (delta position) | uniform in the outer cone, `1 / (2π (1 - cos θo))` |
//! | directional | irradiance E | `1 / (π R²)`: uniform on a disk of radius R facing the light | 1 (delta direction) |
//! | environment | radiance L | `1 / (π R²)` on the disk perpendicular to `dir` | `1 / (4π)` |
//!
//! The throughput of the first light vertex is `le |cos θ| / (pdf_pos pdf_dir)` (the cosine
//! only for area lights), whose expectation is the light's emitted power Φ; the tests
//! check it against the closed forms. For distant lights the disk of radius `R` is centred on
//! the scene's bounding sphere and placed `R` in front of it along `-dir` (pbrt 3rd ed.
//! §16.1.5), so every ray that can reach the scene starts from it. [`Light::pdf_le`] gives
//! both densities for a given ray, for the MIS weights of bidirectional path tracing.

use super::punctual::{spot_falloff, Punctual};
use super::Light;
use crate::geometry::{sphere_point, triangle_point};
use crate::math::luminance;
use crate::sampling::warp::{
    cosine_hemisphere_pdf, square_to_concentric_disk, square_to_cosine_hemisphere,
    square_to_uniform_cone, square_to_uniform_sphere, square_to_uniform_triangle, uniform_cone_pdf,
    uniform_sphere_pdf, Frame,
};
use glam::{Vec2, Vec3};
use std::f32::consts::{FRAC_1_PI, PI};

/// The disk from which distant lights (directional, environment) emit: the scene's bounding
/// sphere, slightly enlarged so that no surface lies exactly on the disk.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WorldDisk {
    /// Centre of the bounding sphere.
    pub center: Vec3,
    /// Radius of the disk (and distance of its plane from the centre).
    pub radius: f32,
}

impl WorldDisk {
    /// The disk of a bounding sphere `(center, radius)`.
    pub fn new(center: Vec3, radius: f32) -> Self {
        Self {
            center,
            radius: radius.max(1e-6) * 1.001,
        }
    }

    /// Area density of a point on the disk, `1 / (π R²)`.
    #[inline]
    pub fn pdf_pos(&self) -> f32 {
        1.0 / (PI * self.radius * self.radius)
    }

    /// A point on the disk facing the direction of travel `dir`, from `u`.
    #[inline]
    fn point(&self, dir: Vec3, u: Vec2) -> Vec3 {
        let f = Frame::from_normal(dir);
        let d = square_to_concentric_disk(u) * self.radius;
        self.center + f.s * d.x + f.t * d.y - dir * self.radius
    }
}

/// A ray of emitted light; see the [module documentation](self).
#[derive(Clone, Copy, Debug)]
pub struct EmissionSample {
    /// Origin of the ray.
    pub p: Vec3,
    /// Error bound of `p`.
    pub p_error: Vec3,
    /// Normal of the light surface at `p`; zero for point, spot and distant lights.
    pub n: Vec3,
    /// Unit direction of travel.
    pub dir: Vec3,
    /// Radiance (area lights, environment), intensity (point, spot) or irradiance
    /// (directional).
    pub le: Vec3,
    /// Density of `p` (area measure; 1 for a delta position).
    pub pdf_pos: f32,
    /// Density of `dir` (solid angle; 1 for a delta direction).
    pub pdf_dir: f32,
}

impl EmissionSample {
    /// `le |cos θ| / (pdf_pos pdf_dir)`: the power carried by the ray (before light
    /// selection), whose expectation is the light's power.
    #[inline]
    pub fn weight(&self) -> Vec3 {
        let cos = if self.n == Vec3::ZERO {
            1.0
        } else {
            self.n.dot(self.dir).abs()
        };
        self.le * (cos / (self.pdf_pos * self.pdf_dir))
    }
}

impl Light {
    /// Samples a ray of emitted light from `u_pos` (position) and `u_dir` (direction);
    /// `None` when the sample carries nothing (e.g. a spot direction outside the falloff,
    /// which cannot happen for the uniform cone, or a zero density).
    pub fn sample_le(&self, u_pos: Vec2, u_dir: Vec2, world: &WorldDisk) -> Option<EmissionSample> {
        let s = match *self {
            Light::Triangle(l) => {
                let (b0, b1) = square_to_uniform_triangle(u_pos);
                let (p, p_error) = triangle_point(&l.p, b0, b1, 1.0 - b0 - b1);
                // Two-sided: pick the side with probability 1/2 and stretch u back.
                let (n_side, u, side_pdf) = if l.two_sided {
                    if u_dir.x < 0.5 {
                        (l.n, Vec2::new(u_dir.x * 2.0, u_dir.y), 0.5)
                    } else {
                        (-l.n, Vec2::new((u_dir.x - 0.5) * 2.0, u_dir.y), 0.5)
                    }
                } else {
                    (l.n, u_dir, 1.0)
                };
                let local = square_to_cosine_hemisphere(u);
                let dir = Frame::from_normal(n_side).to_world(local).normalize();
                EmissionSample {
                    p,
                    p_error,
                    n: l.n,
                    dir,
                    le: l.radiance,
                    pdf_pos: 1.0 / l.area,
                    pdf_dir: side_pdf * cosine_hemisphere_pdf(local.z),
                }
            }
            Light::Sphere(l) => {
                let on = square_to_uniform_sphere(u_pos);
                let (p, p_error, n) = sphere_point(l.center, l.radius, l.center + on * l.radius);
                let local = square_to_cosine_hemisphere(u_dir);
                let dir = Frame::from_normal(n).to_world(local).normalize();
                EmissionSample {
                    p,
                    p_error,
                    n,
                    dir,
                    le: l.radiance,
                    pdf_pos: 1.0 / (4.0 * PI * l.radius * l.radius),
                    pdf_dir: cosine_hemisphere_pdf(local.z),
                }
            }
            Light::Punctual(Punctual::Point {
                position,
                intensity,
            }) => EmissionSample {
                p: position,
                p_error: Vec3::ZERO,
                n: Vec3::ZERO,
                dir: square_to_uniform_sphere(u_dir),
                le: intensity,
                pdf_pos: 1.0,
                pdf_dir: uniform_sphere_pdf(),
            },
            Light::Punctual(Punctual::Spot {
                position,
                axis,
                intensity,
                cos_inner,
                cos_outer,
            }) => {
                let local = square_to_uniform_cone(u_dir, cos_outer);
                let dir = Frame::from_normal(axis).to_world(local).normalize();
                EmissionSample {
                    p: position,
                    p_error: Vec3::ZERO,
                    n: Vec3::ZERO,
                    dir,
                    le: intensity * spot_falloff(local.z, cos_inner, cos_outer),
                    pdf_pos: 1.0,
                    pdf_dir: uniform_cone_pdf(cos_outer),
                }
            }
            Light::Punctual(Punctual::Directional {
                direction,
                irradiance,
                ..
            }) => EmissionSample {
                p: world.point(direction, u_pos),
                p_error: Vec3::ZERO,
                n: Vec3::ZERO,
                dir: direction,
                le: irradiance,
                pdf_pos: world.pdf_pos(),
                pdf_dir: 1.0,
            },
            Light::Environment(ref e) => {
                // Light arrives from `-dir`: uniformly over the sphere, or as the image's
                // importance sampling draws it (the same density as next-event estimation).
                let (dir, le, pdf_dir) = match &e.image {
                    None => (
                        -square_to_uniform_sphere(u_dir),
                        e.radiance,
                        uniform_sphere_pdf(),
                    ),
                    Some(_) => {
                        let ls = e.sample_li(u_dir)?;
                        (-ls.wi, ls.li, ls.pdf)
                    }
                };
                EmissionSample {
                    p: world.point(dir, u_pos),
                    p_error: Vec3::ZERO,
                    n: Vec3::ZERO,
                    dir,
                    le,
                    pdf_pos: world.pdf_pos(),
                    pdf_dir,
                }
            }
        };
        let ok = s.pdf_pos > 0.0
            && s.pdf_dir > 0.0
            && s.pdf_pos.is_finite()
            && s.pdf_dir.is_finite()
            && s.dir.is_finite()
            && luminance(s.le) > 0.0;
        ok.then_some(s)
    }

    /// Densities `(pdf_pos, pdf_dir)` with which [`Light::sample_le`] produces a ray leaving
    /// the light in direction `w` from a point with light normal `n` (ignored by point-like
    /// and distant lights). Delta components report 1, like `sample_le`.
    pub fn pdf_le(&self, n: Vec3, w: Vec3, world: &WorldDisk) -> (f32, f32) {
        match *self {
            Light::Triangle(l) => {
                let cos = n.dot(w);
                let pdf_dir = if l.two_sided {
                    0.5 * cos.abs() * FRAC_1_PI
                } else {
                    cos.max(0.0) * FRAC_1_PI
                };
                (1.0 / l.area, pdf_dir)
            }
            Light::Sphere(l) => (
                1.0 / (4.0 * PI * l.radius * l.radius),
                n.dot(w).max(0.0) * FRAC_1_PI,
            ),
            Light::Punctual(Punctual::Point { .. }) => (1.0, uniform_sphere_pdf()),
            Light::Punctual(Punctual::Spot {
                axis, cos_outer, ..
            }) => {
                let pdf = if w.dot(axis) >= cos_outer {
                    uniform_cone_pdf(cos_outer)
                } else {
                    0.0
                };
                (1.0, pdf)
            }
            Light::Punctual(Punctual::Directional { .. }) => (world.pdf_pos(), 1.0),
            Light::Environment(ref e) => (world.pdf_pos(), e.pdf_li(-w)),
        }
    }

    /// True for lights at infinity (directional and environment): their "position" is a
    /// direction and their rays start on the [`WorldDisk`].
    pub fn is_infinite(&self) -> bool {
        matches!(
            self,
            Light::Environment(_) | Light::Punctual(Punctual::Directional { .. })
        )
    }
}

#[cfg(test)]
mod tests {
    //! Emission sampling against its contract: a chi-squared test of every light's
    //! direction (and, for distant lights, disk position) distribution against the claimed
    //! density (Marschner, CS 6630 notes, section 2), `pdf_le` agreeing with `sample_le`, and the mean ray weight
    //! equal to the light's emitted power in closed form (a z-test at 3 standard errors).
    use super::*;
    use crate::chi2::{chi2_plane, chi2_sphere, chi2_sphere_cap, Chi2Config, SplitMix64};
    use crate::light::environment::Environment;
    use crate::light::sphere::SphereLight;
    use crate::light::triangle::TriangleLight;

    const RADIANCE: Vec3 = Vec3::new(2.0, 1.0, 0.5);
    const WORLD: WorldDisk = WorldDisk {
        center: Vec3::new(0.5, -0.25, 1.0),
        radius: 3.0,
    };

    fn triangle(two_sided: bool) -> Light {
        Light::Triangle(
            TriangleLight::new(
                [
                    Vec3::new(-1.0, -0.5, 1.0),
                    Vec3::new(0.3, 1.2, 1.1),
                    Vec3::new(1.2, -0.8, 0.9),
                ],
                RADIANCE,
                two_sided,
            )
            .unwrap(),
        )
    }

    fn sphere() -> Light {
        Light::Sphere(SphereLight {
            center: Vec3::new(0.2, 0.1, -0.3),
            radius: 0.7,
            radiance: RADIANCE,
        })
    }

    fn point() -> Light {
        Light::Punctual(Punctual::Point {
            position: Vec3::new(0.1, 2.0, -1.0),
            intensity: RADIANCE,
        })
    }

    /// A spot along +z (so the chi-squared cap is about the pole), 20° inner, 35° outer.
    fn spot() -> Light {
        Light::Punctual(Punctual::Spot {
            position: Vec3::new(0.0, 1.0, 0.0),
            axis: Vec3::Z,
            intensity: RADIANCE,
            cos_inner: 20f32.to_radians().cos(),
            cos_outer: 35f32.to_radians().cos(),
        })
    }

    fn directional() -> Light {
        Light::Punctual(Punctual::Directional {
            direction: Vec3::new(0.3, -1.0, 0.2).normalize(),
            irradiance: RADIANCE,
            scene_radius: 3.0,
        })
    }

    fn environment() -> Light {
        Light::Environment(Environment::uniform(RADIANCE, 3.0))
    }

    fn config(tests: usize) -> Chi2Config {
        Chi2Config {
            theta_bins: 16,
            phi_bins: 32,
            samples: 200_000,
            ..Chi2Config::new(tests)
        }
    }

    /// The direction density given a fixed position sample `u_pos`.
    fn chi2_dir(name: &str, cfg: &Chi2Config, light: Light, u_pos: Vec2) -> Result<f64, String> {
        let sample = |u: Vec2, _: f32| light.sample_le(u_pos, u, &WORLD).map(|s| s.dir);
        let n = light
            .sample_le(u_pos, Vec2::new(0.25, 0.5), &WORLD)
            .map_or(Vec3::ZERO, |s| s.n);
        let pdf = |w: Vec3| light.pdf_le(n, w, &WORLD).1;
        let r = match light {
            Light::Punctual(Punctual::Spot { cos_outer, .. }) => {
                chi2_sphere_cap(name, cfg, (cos_outer - 0.05) as f64, sample, pdf)?
            }
            _ => chi2_sphere(name, cfg, sample, pdf)?,
        };
        Ok(r.p_value)
    }

    /// The disk position of a distant light, in disk coordinates scaled to the unit disk.
    fn chi2_disk(name: &str, cfg: &Chi2Config, light: Light, u_dir: Vec2) -> Result<f64, String> {
        let dir = light
            .sample_le(Vec2::splat(0.5), u_dir, &WORLD)
            .unwrap()
            .dir;
        let f = Frame::from_normal(dir);
        let r = chi2_plane(
            name,
            cfg,
            (Vec2::splat(-1.0), Vec2::splat(1.0)),
            |u, _| {
                let s = light.sample_le(u, u_dir, &WORLD)?;
                let q = (s.p - (WORLD.center - dir * WORLD.radius)) / WORLD.radius;
                Some(Vec2::new(q.dot(f.s), q.dot(f.t)).clamp(Vec2::splat(-1.0), Vec2::splat(1.0)))
            },
            // pdf_pos is per m² of the disk; in unit-disk coordinates that is pdf R².
            |q| {
                if q.length_squared() <= 1.0 {
                    light.pdf_le(Vec3::ZERO, dir, &WORLD).0 * WORLD.radius * WORLD.radius
                } else {
                    0.0
                }
            },
        )?;
        Ok(r.p_value)
    }

    #[test]
    fn emission_sampling_matches_pdf_chi2() {
        let u = Vec2::new(0.3, 0.7);
        type Case = Box<dyn Fn(&str, &Chi2Config) -> Result<f64, String>>;
        let cases: Vec<(&str, Case)> = vec![
            (
                "triangle direction",
                Box::new(move |n, c| chi2_dir(n, c, triangle(false), u)),
            ),
            (
                "two-sided triangle direction",
                Box::new(move |n, c| chi2_dir(n, c, triangle(true), u)),
            ),
            (
                "sphere direction",
                Box::new(move |n, c| chi2_dir(n, c, sphere(), u)),
            ),
            (
                "point direction",
                Box::new(move |n, c| chi2_dir(n, c, point(), u)),
            ),
            (
                "spot direction",
                Box::new(move |n, c| chi2_dir(n, c, spot(), u)),
            ),
            (
                "environment direction",
                Box::new(move |n, c| chi2_dir(n, c, environment(), u)),
            ),
            (
                "directional disk",
                Box::new(move |n, c| chi2_disk(n, c, directional(), u)),
            ),
            (
                "environment disk",
                Box::new(move |n, c| chi2_disk(n, c, environment(), u)),
            ),
        ];
        let cfg = config(cases.len());
        let mut failures = Vec::new();
        for (name, f) in &cases {
            match f(name, &cfg) {
                Ok(p) => eprintln!("emission chi2 {name}: p = {p:.4}"),
                Err(e) => failures.push(e),
            }
        }
        assert!(failures.is_empty(), "{}", failures.join("\n"));
    }

    /// A wrong pdf must be caught: the spot sampled uniformly in its cone tested against a
    /// cone of the inner angle.
    #[test]
    fn emission_chi2_rejects_a_wrong_pdf() {
        let light = spot();
        let cfg = config(1);
        let r = chi2_sphere_cap(
            "spot against the inner cone",
            &cfg,
            0.7,
            |u, _| light.sample_le(Vec2::ZERO, u, &WORLD).map(|s| s.dir),
            |w| {
                let ci = 20f32.to_radians().cos();
                if w.z >= ci {
                    uniform_cone_pdf(ci)
                } else {
                    0.0
                }
            },
        );
        assert!(r.is_err(), "{r:?}");
    }

    #[test]
    fn pdf_le_agrees_with_sample_le() {
        let mut rng = SplitMix64::new(3);
        for light in [
            triangle(false),
            triangle(true),
            sphere(),
            point(),
            spot(),
            directional(),
            environment(),
        ] {
            for _ in 0..1000 {
                let u1 = Vec2::new(rng.next_f32(), rng.next_f32());
                let u2 = Vec2::new(rng.next_f32(), rng.next_f32());
                let Some(s) = light.sample_le(u1, u2, &WORLD) else {
                    continue;
                };
                let (pp, pd) = light.pdf_le(s.n, s.dir, &WORLD);
                assert!(
                    (pp - s.pdf_pos).abs() <= 1e-4 * s.pdf_pos,
                    "{light:?}: {pp} vs {}",
                    s.pdf_pos
                );
                assert!(
                    (pd - s.pdf_dir).abs() <= 1e-3 * s.pdf_dir,
                    "{light:?}: {pd} vs {}",
                    s.pdf_dir
                );
            }
        }
    }

    /// `E[le |cos| / (pdf_pos pdf_dir)] = Φ`, the emitted power, per channel.
    #[test]
    fn emitted_power_matches_closed_form() {
        let r2 = WORLD.radius * WORLD.radius;
        let (ci, co) = (20f32.to_radians().cos(), 35f32.to_radians().cos());
        let tri_area = match triangle(false) {
            Light::Triangle(t) => t.area,
            _ => unreachable!(),
        };
        let cases = [
            ("triangle", triangle(false), PI * tri_area),
            ("two-sided triangle", triangle(true), 2.0 * PI * tri_area),
            ("sphere", sphere(), 4.0 * PI * PI * 0.49),
            ("point", point(), 4.0 * PI),
            // glTF falloff s = t² between the cones: 2π ((1 - cos_i) + (cos_i - cos_o) / 3).
            ("spot", spot(), 2.0 * PI * ((1.0 - ci) + (ci - co) / 3.0)),
            ("directional", directional(), PI * r2),
            ("environment", environment(), 4.0 * PI * PI * r2),
        ];
        let mut rng = SplitMix64::new(11);
        let n = 200_000;
        for (name, light, factor) in cases {
            let (mut sum, mut sum2) = (0.0f64, 0.0f64);
            for _ in 0..n {
                let u1 = Vec2::new(rng.next_f32(), rng.next_f32());
                let u2 = Vec2::new(rng.next_f32(), rng.next_f32());
                // Channel 0 carries RADIANCE.x = 2.
                let w = light
                    .sample_le(u1, u2, &WORLD)
                    .map_or(0.0, |s| s.weight().x as f64);
                sum += w;
                sum2 += w * w;
            }
            let mean = sum / n as f64;
            let se = ((sum2 / n as f64 - mean * mean).max(0.0) / n as f64).sqrt();
            let exact = (factor * RADIANCE.x) as f64;
            // Most of these estimators are constant (importance sampling proportional to the
            // emission): their standard error is rounding only, hence the relative slack.
            eprintln!(
                "emitted power {name}: {mean:.5} ± {se:.5}, closed form {exact:.5}, relative difference {:.2e}",
                (mean - exact) / exact
            );
            assert!(
                (mean - exact).abs() <= 3.0 * se + 1e-4 * exact,
                "{name}: {mean} vs {exact}"
            );
        }
    }
}
