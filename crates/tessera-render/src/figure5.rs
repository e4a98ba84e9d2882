//! Veach & Guibas 1995, figure 5, in numbers (Veach & Guibas 1995, section 4.1, figs. 4 and 5): the glossy
//! highlight of a spherical light on a plate of varying roughness, estimated from one
//! viewing ray by light (area) sampling, by BSDF (directional) sampling, and by both
//! combined with the balance, power (β = 2), cutoff (α = 0.1) and maximum heuristics.
//!
//! Setup (the paper's figure 4): the plate point is at the origin with normal +z; the
//! viewing ray arrives at 45°, and the mirror direction points at the centre of a sphere
//! light subtending 0.063 sr (radius 1.412 at distance 10, radiance 1). The plate is the
//! renderer's modified Phong (`kd = 0.05`, `ks = 0.75` as in `builtin:veach-mis`) with
//! exponent `n = 1/r - 1` for roughness `r` (the paper's parametrisation). Everything goes
//! through the renderer's own `Light::sample_li`/`pdf_li`, `Bsdf::sample`/`eval`/`pdf` and
//! `MisHeuristic::weight`.
//!
//! Statistic: for each technique, `sigma / mu` of one sample of the estimator (Veach's
//! "variance of a single sample"): for light or BSDF sampling alone one sample of that
//! technique; for a heuristic, the multi-sample estimator with one sample of each
//! technique (`n1 = n2 = 1`). Theorem 1 then bounds the balance heuristic's variance by
//! `min(sigma_light², sigma_bsdf²) + mu²/2` (weights that put everything on one technique
//! are one of the combinations it is compared with).

use crate::bsdf::phong::Phong;
use crate::bsdf::{Bsdf, Lobe};
use crate::integrator::MisHeuristic;
use crate::light::sphere::SphereLight;
use crate::light::Light;
use glam::{Vec2, Vec3};

/// The techniques, in CSV column order.
pub const TECHNIQUES: [&str; 6] = ["light", "bsdf", "balance", "power", "cutoff", "maximum"];
const HEURISTICS: [MisHeuristic; 4] = [
    MisHeuristic::Balance,
    MisHeuristic::Power,
    MisHeuristic::Cutoff(0.1),
    MisHeuristic::Maximum,
];

/// One roughness value: the mean and `sigma / mu` of every technique.
#[derive(Clone, Debug)]
pub struct Row {
    /// Surface roughness r.
    pub roughness: f64,
    /// Phong exponent `1/r - 1`.
    pub exponent: f64,
    /// Mean of each technique's estimator (all estimate the same highlight).
    pub mean: [f64; 6],
    /// `sigma / mu` of one sample, per technique.
    pub sigma_over_mu: [f64; 6],
}

/// splitmix64 → uniform f32 in [0, 1).
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> f32 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^= z >> 31;
        (z >> 40) as f32 * (1.0 / (1u64 << 24) as f32)
    }
}

/// Distance along unit `d` from the origin to the sphere, if it is hit in front.
fn hit_sphere(d: Vec3, c: Vec3, r: f32) -> Option<f32> {
    let b = d.dot(c);
    let disc = b * b - (c.length_squared() - r * r);
    if disc < 0.0 {
        return None;
    }
    let t = b - disc.sqrt();
    (t > 0.0).then_some(t)
}

/// Welford accumulator in f64.
#[derive(Default, Clone, Copy)]
struct Welford {
    n: f64,
    mean: f64,
    m2: f64,
}

impl Welford {
    fn push(&mut self, x: f64) {
        self.n += 1.0;
        let d = x - self.mean;
        self.mean += d / self.n;
        self.m2 += d * (x - self.mean);
    }
    fn sigma_over_mu(&self) -> f64 {
        (self.m2 / (self.n - 1.0)).sqrt() / self.mean
    }
}

/// Measures one roughness with `samples` samples per technique.
pub fn measure(roughness: f64, samples: u32, seed: u64) -> Row {
    let s = std::f32::consts::FRAC_1_SQRT_2;
    let wo = Vec3::new(-s, 0.0, s);
    let dist = 10.0f32;
    let center = Vec3::new(s, 0.0, s) * dist;
    // 2π (1 - cos θmax) = 0.063 sr.
    let one_minus_cos = 0.063f32 / std::f32::consts::TAU;
    let sin2 = one_minus_cos * (2.0 - one_minus_cos);
    let radius = dist * sin2.sqrt();
    let light = Light::Sphere(SphereLight {
        center,
        radius,
        radiance: Vec3::ONE,
    });
    let exponent = (1.0 / roughness - 1.0) as f32;
    let bsdf = Bsdf::single(Lobe::Phong(Phong {
        kd: Vec3::splat(0.05),
        ks: Vec3::splat(0.75),
        exponent,
    }));
    let mut rng = Rng(seed ^ roughness.to_bits());
    let mut acc = [Welford::default(); 6];
    for _ in 0..samples {
        // Light (area) sampling: contribution, and the BSDF's density of the same direction.
        let (c_l, pl_l, pb_l) = match light.sample_li(Vec3::ZERO, Vec2::new(rng.next(), rng.next()))
        {
            Some(ls) if ls.pdf > 0.0 => {
                let f = bsdf.eval(wo, ls.wi).x;
                (f * ls.li.x / ls.pdf, ls.pdf, bsdf.pdf(wo, ls.wi))
            }
            _ => (0.0, 0.0, 0.0),
        };
        // BSDF (directional) sampling: does the ray hit the light?
        let (u1, u2) = (rng.next(), Vec2::new(rng.next(), rng.next()));
        let (c_b, pb_b, pl_b) = match bsdf.sample(wo, u1, u2) {
            Some(bs) if !bs.delta && bs.pdf > 0.0 => match hit_sphere(bs.wi, center, radius) {
                Some(t) => {
                    let p = bs.wi * t;
                    let n = (p - center).normalize();
                    (bs.weight.x, bs.pdf, light.pdf_li(Vec3::ZERO, bs.wi, p, n))
                }
                None => (0.0, bs.pdf, 0.0),
            },
            _ => (0.0, 0.0, 0.0),
        };
        acc[0].push(f64::from(c_l));
        acc[1].push(f64::from(c_b));
        for (k, h) in HEURISTICS.iter().enumerate() {
            let f = h.weight(pl_l, pb_l) * c_l + h.weight(pb_b, pl_b) * c_b;
            acc[2 + k].push(f64::from(f));
        }
    }
    Row {
        roughness,
        exponent: f64::from(exponent),
        mean: acc.map(|a| a.mean),
        sigma_over_mu: acc.map(|a| a.sigma_over_mu()),
    }
}

/// The roughness ladder: 13 values, log-spaced from 1e-4 to 0.5 (Phong exponents from
/// 9999 down to 1).
pub fn roughness_ladder() -> Vec<f64> {
    (0..13)
        .map(|i| 10f64.powf(-4.0 + f64::from(i) * (0.5f64.log10() + 4.0) / 12.0))
        .collect()
}

/// Measures the whole ladder.
pub fn run(samples: u32, seed: u64) -> Vec<Row> {
    roughness_ladder()
        .into_iter()
        .map(|r| measure(r, samples, seed))
        .collect()
}

/// The CSV: roughness, exponent, then sigma/mu and mean of each technique.
pub fn csv(rows: &[Row]) -> String {
    let mut out = String::from("roughness,exponent");
    for t in TECHNIQUES {
        out.push_str(&format!(",{t}_sigma_over_mu"));
    }
    for t in TECHNIQUES {
        out.push_str(&format!(",{t}_mean"));
    }
    out.push('\n');
    for r in rows {
        out.push_str(&format!("{:.6},{:.3}", r.roughness, r.exponent));
        for v in r.sigma_over_mu {
            out.push_str(&format!(",{v:.6}"));
        }
        for v in r.mean {
            out.push_str(&format!(",{v:.6}"));
        }
        out.push('\n');
    }
    out
}

/// What the paper claims, checked on our numbers.
#[derive(Debug, Clone)]
pub struct Claims {
    /// Largest `sigma_h² - (min(sigma_light², sigma_bsdf²) + mu²/2)` over heuristics and
    /// roughness, in units of mu²: Theorem 1's bound holds for the balance heuristic if
    /// this is <= 0 for it; reported for all four.
    pub worst_excess_over_bound: [f64; 4],
    /// Largest ratio `(sigma/mu)_h / min((sigma/mu)_light, (sigma/mu)_bsdf)` per heuristic.
    pub worst_ratio_to_best: [f64; 4],
    /// `(sigma/mu)` of power and balance at the smoothest and the roughest plate.
    pub extremes: [(f64, f64); 2],
}

impl Claims {
    /// Checks the rows (the first and last are the extremes).
    pub fn check(rows: &[Row]) -> Claims {
        let mut excess = [f64::NEG_INFINITY; 4];
        let mut ratio = [0.0f64; 4];
        for r in rows {
            let best = r.sigma_over_mu[0].min(r.sigma_over_mu[1]);
            for k in 0..4 {
                let h = r.sigma_over_mu[2 + k];
                excess[k] = excess[k].max(h * h - (best * best + 0.5));
                ratio[k] = ratio[k].max(h / best);
            }
        }
        let ext = |r: &Row| (r.sigma_over_mu[3], r.sigma_over_mu[2]);
        Claims {
            worst_excess_over_bound: excess,
            worst_ratio_to_best: ratio,
            extremes: [
                rows.first().map_or((0.0, 0.0), ext),
                rows.last().map_or((0.0, 0.0), ext),
            ],
        }
    }

    /// Whether both claims hold: every heuristic within Theorem 1's `mu²/2` of the better
    /// technique, and power below balance at both extremes.
    pub fn hold(&self) -> bool {
        self.worst_excess_over_bound.iter().all(|&e| e <= 0.0)
            && self.extremes.iter().all(|&(p, b)| p < b)
    }

    /// A human-readable summary.
    pub fn summary(&self) -> String {
        let mut s = String::new();
        for (k, name) in TECHNIQUES[2..].iter().enumerate() {
            s.push_str(&format!(
                "  {name}: worst sigma/mu ratio to the better single technique {:.3}; worst sigma² - (best² + mu²/2) = {:+.4} mu²\n",
                self.worst_ratio_to_best[k], self.worst_excess_over_bound[k]
            ));
        }
        s.push_str(&format!(
            "  smoothest plate: power {:.4} vs balance {:.4}; roughest plate: power {:.4} vs balance {:.4}\n",
            self.extremes[0].0, self.extremes[0].1, self.extremes[1].0, self.extremes[1].1
        ));
        s.push_str(if self.hold() {
            "  the paper's claims hold\n"
        } else {
            "  the paper's claims do NOT all hold\n"
        });
        s
    }
}

/// The curves of the plot: one series of (roughness, sigma/mu) per technique.
pub fn series(rows: &[Row]) -> Vec<(String, Vec<(f64, f64)>)> {
    TECHNIQUES
        .iter()
        .enumerate()
        .map(|(k, t)| {
            (
                t.to_string(),
                rows.iter()
                    .map(|r| (r.roughness, r.sigma_over_mu[k]))
                    .collect(),
            )
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every technique estimates the same highlight, and the paper's claims hold on a
    /// reduced run (20k samples per point instead of 100k; fixed seed).
    #[test]
    fn figure5_claims_hold() {
        let rows = run(20_000, 5);
        eprint!("{}", csv(&rows));
        eprint!("{}", Claims::check(&rows).summary());
        for r in &rows {
            let m = r.mean;
            // Unbiased techniques agree within a few standard errors of the worst one.
            let se = r
                .sigma_over_mu
                .iter()
                .zip(&m)
                .map(|(s, m)| s * m / (20_000f64).sqrt())
                .fold(0.0, f64::max);
            for v in &m[1..] {
                assert!(
                    (v - m[0]).abs() <= 5.0 * se,
                    "r {}: means {m:?}",
                    r.roughness
                );
            }
        }
        let c = Claims::check(&rows);
        assert!(c.hold(), "{}", c.summary());
        // And the single techniques cross over: light sampling wins on rough plates, BSDF
        // sampling on smooth ones.
        let (first, last) = (&rows[0], &rows[rows.len() - 1]);
        assert!(first.sigma_over_mu[1] < first.sigma_over_mu[0]);
        assert!(last.sigma_over_mu[0] < last.sigma_over_mu[1]);
    }
}
