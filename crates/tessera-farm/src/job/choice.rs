//! The choices a job makes, each one type with one string form: [`SceneRef`],
//! [`IntegratorChoice`] (what was asked for, possibly `auto`) and [`Integrator`] (what is
//! rendered, never `auto`), [`MisHeuristic`], [`SamplerKind`] and [`AdaptiveMode`].
//!
//! `Display` writes the canonical spelling and `FromStr` parses it (plus documented
//! aliases); serde uses the same strings, so the HTTP API, the command line, the store and
//! the EXR header all spell a choice the same way.

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Deserializer, Serialize, Serializer};

/// Longest accepted built-in scene name, in characters.
pub const MAX_BUILTIN_NAME_CHARS: usize = 64;
/// Threshold of the cutoff heuristic when `mis` is plain `"cutoff"`.
pub const DEFAULT_CUTOFF_ALPHA: f32 = 0.1;

/// Implements `Serialize`/`Deserialize` as the type's string form (`Display`/`FromStr`).
macro_rules! string_serde {
    ($t:ty) => {
        impl Serialize for $t {
            fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
                s.collect_str(self)
            }
        }
        impl<'de> Deserialize<'de> for $t {
            fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
                let s = String::deserialize(d)?;
                s.parse().map_err(serde::de::Error::custom)
            }
        }
    };
}

/// A reference to a scene: built into every worker, or uploaded and stored by content hash.
///
/// Its string form is `"builtin:NAME"` or the 64 lowercase hex digits of the SHA-256 of the
/// scene bytes (as returned by `POST /api/v1/scenes`). Parsing accepts upper-case hex and
/// normalizes it.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub enum SceneRef {
    /// A built-in scene, e.g. `Builtin("cornell-box")` for `"builtin:cornell-box"`.
    Builtin(String),
    /// An uploaded scene: lowercase hex SHA-256 of its bytes.
    Hash(String),
}

impl SceneRef {
    /// The string form, `"builtin:NAME"` or the hex hash.
    pub fn as_wire(&self) -> String {
        self.to_string()
    }

    /// The content hash of an uploaded scene; `None` for a built-in one.
    pub fn hash(&self) -> Option<&str> {
        match self {
            Self::Hash(h) => Some(h),
            Self::Builtin(_) => None,
        }
    }

    /// Whether `s` is 64 hex digits.
    fn is_sha256_hex(s: &str) -> bool {
        s.len() == 64 && s.bytes().all(|b| b.is_ascii_hexdigit())
    }
}

impl FromStr for SceneRef {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        if s.is_empty() {
            return Err("must not be empty".into());
        }
        if let Some(name) = s.strip_prefix("builtin:") {
            let ok = !name.is_empty()
                && name.chars().count() <= MAX_BUILTIN_NAME_CHARS
                && name
                    .bytes()
                    .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'-' | b'_' | b'.'));
            if !ok {
                return Err(format!(
                    "built-in scene name {name:?} is invalid: expected 1 to \
                     {MAX_BUILTIN_NAME_CHARS} letters, digits, '-', '_' or '.'"
                ));
            }
            return Ok(Self::Builtin(name.to_owned()));
        }
        if Self::is_sha256_hex(s) {
            return Ok(Self::Hash(s.to_ascii_lowercase()));
        }
        Err(format!(
            "expected \"builtin:NAME\" or the 64-hex-digit hash of an uploaded scene, got {s:?}"
        ))
    }
}

impl fmt::Display for SceneRef {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Builtin(name) => write!(f, "builtin:{name}"),
            Self::Hash(h) => f.write_str(h),
        }
    }
}

string_serde!(SceneRef);

/// The light transport algorithm that renders a job: the resolved form of
/// [`IntegratorChoice`], so it cannot be `auto`.
///
/// | name | what it computes |
/// |---|---|
/// | `path` | unidirectional path tracing with next-event estimation, MIS and Russian roulette |
/// | `direct` | direct lighting only: emission seen by the camera and light arriving at the first surface |
/// | `bdpt` | bidirectional path tracing (Veach & Guibas 1995): caustics from small and delta lights |
/// | `vcm` | vertex connection and merging (Georgiev et al. 2012): bdpt plus photon density estimation, for caustics seen through specular surfaces (biased, consistent) |
/// | `ppm` | progressive photon mapping (Hachisuka & Jensen 2009; Knaus & Zwicker 2011): vcm's merging alone, at the first non-specular camera vertex (biased, consistent) |
/// | `mlt` | Metropolis light transport (multiplexed over bdpt's techniques, Hachisuka et al. 2014): for light that reaches what the camera sees through narrow openings |
/// | `mnee` | path tracing with manifold next-event estimation (Hanika, Droske & Fascione 2015) at every non-specular camera vertex: caustics of point, spot and small area lights through up to two specular interfaces, seen directly or through specular surfaces (unbiased) |
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum Integrator {
    /// Path tracing with next-event estimation and MIS. The default.
    #[default]
    Path,
    /// Direct lighting only.
    Direct,
    /// Bidirectional path tracing.
    Bdpt,
    /// Vertex connection and merging: bidirectional path tracing combined with photon
    /// density estimation by MIS. Biased (merging blurs light over a radius that shrinks
    /// with the passes), consistent.
    Vcm,
    /// Progressive photon mapping: vcm's photon map and radius schedule with merging as
    /// the only technique, at the first non-specular vertex of the camera subpath. Biased
    /// like vcm, consistent.
    Ppm,
    /// Metropolis light transport: Markov chains in primary sample space over the
    /// bidirectional techniques, each pass with its own chains and normalisation.
    Mlt,
    /// Path tracing with manifold next-event estimation: at the camera path's first
    /// non-specular vertex, a Newton solver connects to a point, spot or small area light
    /// through a chain of up to two smooth specular interfaces (Hanika, Droske & Fascione
    /// 2015), which samples `L S D S* E` caustics that plain path tracing cannot. Unbiased;
    /// estimates each pixel on its own, so it tiles like path tracing.
    Mnee,
}

impl Integrator {
    /// The string form: `"path"`, `"direct"`, `"bdpt"`, `"vcm"`, `"ppm"`, `"mlt"` or
    /// `"mnee"`.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Path => "path",
            Self::Direct => "direct",
            Self::Bdpt => "bdpt",
            Self::Vcm => "vcm",
            Self::Ppm => "ppm",
            Self::Mlt => "mlt",
            Self::Mnee => "mnee",
        }
    }

    /// Whether the integrator's estimate is biased (its expected value is not the pixel's
    /// true value at any finite number of passes): vertex merging blurs light over its
    /// radius. The pass spread does not see such a bias.
    pub fn is_biased(self) -> bool {
        self.merges()
    }

    /// Whether the integrator renders whole-frame units (one tile per pass): light tracing
    /// splats onto any pixel (bdpt, vcm, mlt), merging reads the whole pass's photon map
    /// (vcm, ppm), and mlt's Markov chains wander over the whole frame.
    pub fn whole_frame(self) -> bool {
        matches!(self, Self::Bdpt | Self::Vcm | Self::Ppm | Self::Mlt)
    }

    /// Whether the integrator merges with a per-pass photon map (vcm, ppm): it renders
    /// whole-frame units and holds the pass's photons in memory.
    pub fn merges(self) -> bool {
        matches!(self, Self::Vcm | Self::Ppm)
    }
}

impl FromStr for Integrator {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "path" => Ok(Self::Path),
            "direct" => Ok(Self::Direct),
            "bdpt" => Ok(Self::Bdpt),
            "vcm" => Ok(Self::Vcm),
            "ppm" => Ok(Self::Ppm),
            "mlt" => Ok(Self::Mlt),
            "mnee" => Ok(Self::Mnee),
            _ => Err(format!(
                "expected one of \"path\", \"direct\", \"bdpt\", \"vcm\", \"ppm\", \"mlt\", \"mnee\", got {s:?}"
            )),
        }
    }
}

impl fmt::Display for Integrator {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

string_serde!(Integrator);

/// The light transport algorithm requested for a job: an [`Integrator`], or `auto` for
/// the one the scene's render plan chooses (ARCHITECTURE.md §4).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum IntegratorChoice {
    /// Chosen from the scene's effect analysis. The default.
    #[default]
    Auto,
    /// This integrator, with the general configuration.
    Fixed(Integrator),
}

impl IntegratorChoice {
    /// Path tracing.
    pub const PATH: Self = Self::Fixed(Integrator::Path);
    /// Direct lighting.
    pub const DIRECT: Self = Self::Fixed(Integrator::Direct);
    /// Bidirectional path tracing.
    pub const BDPT: Self = Self::Fixed(Integrator::Bdpt);
    /// Vertex connection and merging.
    pub const VCM: Self = Self::Fixed(Integrator::Vcm);
    /// Progressive photon mapping.
    pub const PPM: Self = Self::Fixed(Integrator::Ppm);
    /// Metropolis light transport.
    pub const MLT: Self = Self::Fixed(Integrator::Mlt);
    /// Path tracing with manifold next-event estimation.
    pub const MNEE: Self = Self::Fixed(Integrator::Mnee);

    /// The string form: `"auto"`, `"path"`, `"direct"`, `"bdpt"`, `"vcm"`, `"ppm"`, `"mlt"`
    /// or `"mnee"`.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Auto => "auto",
            Self::Fixed(i) => i.as_str(),
        }
    }
}

impl From<Integrator> for IntegratorChoice {
    fn from(i: Integrator) -> Self {
        Self::Fixed(i)
    }
}

impl FromStr for IntegratorChoice {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "auto" => Ok(Self::Auto),
            _ => s.parse().map(Self::Fixed).map_err(|_| {
                format!(
                    "expected one of \"auto\", \"path\", \"direct\", \"bdpt\", \"vcm\", \"ppm\", \"mlt\", \"mnee\", got {s:?}"
                )
            }),
        }
    }
}

impl fmt::Display for IntegratorChoice {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

string_serde!(IntegratorChoice);

/// The weighting heuristic of multiple importance sampling (Veach & Guibas 1995, section
/// 3). With one sample from each of two techniques with densities `p` (the one that
/// produced the sample) and `q`:
///
/// - balance: `p / (p + q)`, provably close to optimal;
/// - power (β = 2): `p² / (p² + q²)`, sharper where one technique is much better (default);
/// - cutoff (α): techniques with density below `α · max` get weight 0, the rest share
///   by balance;
/// - maximum: weight 1 for the technique with the larger density, 0 otherwise.
///
/// String forms: `"balance"`, `"power"`, `"cutoff"` ([`DEFAULT_CUTOFF_ALPHA`]),
/// `"cutoff:ALPHA"` with α in (0, 1], `"maximum"` (`"max"` is accepted as an alias).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum MisHeuristic {
    /// Balance heuristic.
    Balance,
    /// Power heuristic with exponent 2. The default.
    #[default]
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
            "cutoff" => Ok(Self::Cutoff(DEFAULT_CUTOFF_ALPHA)),
            _ => {
                if let Some(a) = s.strip_prefix("cutoff:") {
                    let alpha: f32 = a
                        .parse()
                        .map_err(|_| format!("cutoff threshold {a:?} is not a number"))?;
                    if alpha > 0.0 && alpha <= 1.0 {
                        return Ok(Self::Cutoff(alpha));
                    }
                    return Err(format!("cutoff threshold must be in (0, 1], got {a}"));
                }
                Err(format!(
                    "expected one of \"balance\", \"power\", \"cutoff\", \"cutoff:ALPHA\", \
                     \"maximum\", got {s:?}"
                ))
            }
        }
    }
}

impl fmt::Display for MisHeuristic {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Balance => f.write_str("balance"),
            Self::Power => f.write_str("power"),
            // `{}` of an f32 prints the shortest string that parses back to the same value.
            Self::Cutoff(a) => write!(f, "cutoff:{a}"),
            Self::Maximum => f.write_str("maximum"),
        }
    }
}

string_serde!(MisHeuristic);

/// Which randomized point set a pixel's samples come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum SamplerKind {
    /// Owen-scrambled Sobol' (Burley 2020): each 2D request is a fresh, independently
    /// scrambled and shuffled (0,m,2)-net, padded by Latin supercube sampling (Owen 2001,
    /// section 6.8). The default.
    #[default]
    Sobol,
    /// Independent uniform random numbers from a hash of (pass, sample index, dimension):
    /// plain Monte Carlo, the reference for unbiasedness and variance comparisons.
    Independent,
}

impl SamplerKind {
    /// The string form: `"sobol"` or `"independent"`.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Sobol => "sobol",
            Self::Independent => "independent",
        }
    }
}

impl FromStr for SamplerKind {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "sobol" => Ok(Self::Sobol),
            "independent" => Ok(Self::Independent),
            _ => Err(format!(
                "expected one of \"sobol\", \"independent\", got {s:?}"
            )),
        }
    }
}

impl fmt::Display for SamplerKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

string_serde!(SamplerKind);

/// Adaptive stopping (ARCHITECTURE.md §3; Jensen 2001, section 10.3).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum AdaptiveMode {
    /// Every pixel gets every planned pass. The default.
    #[default]
    Off,
    /// Stop pixels at fixed pass boundaries once their own estimate is below the target
    /// (fast, slightly biased: Kirk & Arvo 1991).
    Sequential,
    /// Kirk & Arvo two-stage sampling: a discarded pilot fixes each pixel's pass count;
    /// only fresh passes form the image.
    Unbiased,
}

impl AdaptiveMode {
    /// The string form: `"off"`, `"sequential"` or `"unbiased"`.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Off => "off",
            Self::Sequential => "sequential",
            Self::Unbiased => "unbiased",
        }
    }
}

impl FromStr for AdaptiveMode {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "off" => Ok(Self::Off),
            "sequential" => Ok(Self::Sequential),
            "unbiased" => Ok(Self::Unbiased),
            _ => Err(format!(
                "expected one of \"off\", \"sequential\", \"unbiased\", got {s:?}"
            )),
        }
    }
}

impl fmt::Display for AdaptiveMode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

string_serde!(AdaptiveMode);

#[cfg(test)]
mod tests {
    use super::*;

    /// Every choice parses its own string form back (the one FromStr/Display pair).
    #[test]
    fn choices_parse_their_display() {
        for i in [
            Integrator::Path,
            Integrator::Direct,
            Integrator::Bdpt,
            Integrator::Vcm,
            Integrator::Ppm,
            Integrator::Mlt,
            Integrator::Mnee,
        ] {
            assert_eq!(i.to_string().parse::<Integrator>(), Ok(i));
            let c = IntegratorChoice::from(i);
            assert_eq!(c.to_string().parse::<IntegratorChoice>(), Ok(c));
            let json = serde_json::to_string(&c).unwrap();
            assert_eq!(json, format!("\"{i}\""));
            assert_eq!(serde_json::from_str::<IntegratorChoice>(&json).unwrap(), c);
        }
        assert_eq!(Integrator::Mnee.as_str(), "mnee");
        assert!(!Integrator::Mnee.whole_frame() && !Integrator::Mnee.is_biased());
        let e = "manifold".parse::<IntegratorChoice>().unwrap_err();
        assert!(e.contains("\"mnee\""), "{e}");
        assert_eq!(
            "auto".parse::<IntegratorChoice>(),
            Ok(IntegratorChoice::Auto)
        );
        assert!("auto".parse::<Integrator>().is_err());
        for m in [
            MisHeuristic::Balance,
            MisHeuristic::Power,
            MisHeuristic::Cutoff(0.25),
            MisHeuristic::Maximum,
        ] {
            assert_eq!(m.to_string().parse::<MisHeuristic>(), Ok(m));
        }
        for s in [SamplerKind::Sobol, SamplerKind::Independent] {
            assert_eq!(s.to_string().parse::<SamplerKind>(), Ok(s));
        }
        for a in [
            AdaptiveMode::Off,
            AdaptiveMode::Sequential,
            AdaptiveMode::Unbiased,
        ] {
            assert_eq!(a.to_string().parse::<AdaptiveMode>(), Ok(a));
            let json = serde_json::to_string(&a).unwrap();
            assert_eq!(json, format!("\"{a}\""));
        }
    }

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
