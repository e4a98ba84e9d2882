//! Integrators: estimators of the radiance arriving at the camera along a ray.
//!
//! | name | what it computes |
//! |---|---|
//! | `path` | unidirectional path tracing with next-event estimation, multiple importance sampling and Russian roulette ([`path`]) |
//! | `direct` | direct lighting only: emission seen by the camera and light arriving at the first surface, one bounce, both techniques combined by MIS |
//! | `bdpt` | bidirectional path tracing: camera and light subpaths joined by every connection technique, light tracing splatted onto the film, power-heuristic MIS ([`bdpt`]) |

pub mod bdpt;
pub mod path;

use std::fmt;
use std::str::FromStr;

/// Which integrator renders the image.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum IntegratorKind {
    /// Path tracing with NEE and MIS.
    Path,
    /// Direct lighting only.
    Direct,
    /// Bidirectional path tracing (caustics from small and delta lights).
    Bdpt,
}

impl FromStr for IntegratorKind {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "path" => Ok(Self::Path),
            "direct" => Ok(Self::Direct),
            "bdpt" => Ok(Self::Bdpt),
            _ => Err(format!(
                "unknown integrator {s:?}: expected path, direct or bdpt"
            )),
        }
    }
}

impl fmt::Display for IntegratorKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::Path => "path",
            Self::Direct => "direct",
            Self::Bdpt => "bdpt",
        })
    }
}

/// The weighting heuristic of multiple importance sampling (Veach & Guibas 1995, seed 002
/// §3). With one sample from each of two techniques with densities `p` (the one that
/// produced the sample) and `q`:
///
/// - balance: `p / (p + q)`, provably close to optimal;
/// - power (β = 2): `p² / (p² + q²)`, sharper where one technique is much better (default);
/// - cutoff (α): techniques with density below `α · max` get weight 0, the rest share
///   by balance;
/// - maximum: weight 1 for the technique with the larger density, 0 otherwise.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum MisHeuristic {
    /// Balance heuristic.
    Balance,
    /// Power heuristic with exponent 2.
    Power,
    /// Cutoff heuristic with threshold α in (0, 1].
    Cutoff(f32),
    /// Maximum heuristic.
    Maximum,
}

impl MisHeuristic {
    /// The weight of a sample drawn by the technique with density `p` when the other
    /// technique has density `q` at the same point.
    #[inline]
    pub fn weight(self, p: f32, q: f32) -> f32 {
        // NaN densities count as zero.
        if p.is_nan() || p <= 0.0 {
            return 0.0;
        }
        if q.is_nan() || q <= 0.0 {
            return 1.0;
        }
        match self {
            Self::Balance => p / (p + q),
            Self::Power => {
                // Divide through by the larger density to avoid overflow of p².
                let m = p.max(q);
                let (a, b) = (p / m, q / m);
                a * a / (a * a + b * b)
            }
            Self::Cutoff(alpha) => {
                let m = p.max(q);
                if p < alpha * m {
                    0.0
                } else if q < alpha * m {
                    1.0
                } else {
                    p / (p + q)
                }
            }
            // Ties split evenly so the two weights still sum to one.
            Self::Maximum => match p.partial_cmp(&q) {
                Some(std::cmp::Ordering::Greater) => 1.0,
                Some(std::cmp::Ordering::Less) => 0.0,
                _ => 0.5,
            },
        }
    }
}

impl FromStr for MisHeuristic {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "balance" => Ok(Self::Balance),
            "power" => Ok(Self::Power),
            "maximum" | "max" => Ok(Self::Maximum),
            "cutoff" => Ok(Self::Cutoff(0.1)),
            _ => {
                if let Some(a) = s.strip_prefix("cutoff:") {
                    let a: f32 = a
                        .parse()
                        .map_err(|_| format!("cutoff threshold {a:?} is not a number"))?;
                    if a > 0.0 && a <= 1.0 {
                        return Ok(Self::Cutoff(a));
                    }
                    return Err(format!("cutoff threshold {a} must be in (0, 1]"));
                }
                Err(format!("unknown MIS heuristic {s:?}: expected balance, power, cutoff[:ALPHA] or maximum"))
            }
        }
    }
}

impl fmt::Display for MisHeuristic {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Balance => f.write_str("balance"),
            Self::Power => f.write_str("power"),
            Self::Cutoff(a) => write!(f, "cutoff:{a}"),
            Self::Maximum => f.write_str("maximum"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn heuristics_partition_unity() {
        // For two techniques the weights of the same point must sum to one.
        for h in [
            MisHeuristic::Balance,
            MisHeuristic::Power,
            MisHeuristic::Cutoff(0.1),
            MisHeuristic::Maximum,
        ] {
            for (p, q) in [
                (1.0f32, 1.0f32),
                (1.0, 0.01),
                (3.0, 7.0),
                (1e-30, 1e30),
                (1e30, 1e-30),
            ] {
                let s = h.weight(p, q) + h.weight(q, p);
                assert!((s - 1.0).abs() < 1e-5, "{h}: {p} {q} -> {s}");
            }
        }
        assert_eq!(MisHeuristic::Power.weight(2.0, 1.0), 0.8);
        assert_eq!(MisHeuristic::Cutoff(0.5).weight(0.4, 1.0), 0.0);
    }
}
