//! Deterministic per-pixel sample generation and the warps that turn samples into
//! directions and points.
//!
//! Determinism contract (ARCHITECTURE.md §2): every value returned by a [`PixelSampler`] is a pure
//! function of (job seed, frame, pixel, pass, sample index, dimension), computed with integer
//! hashing only, so it is bit-identical on every platform, thread count and work order.
//!
//! Statistics contract (ARCHITECTURE.md §3): pass `k` of pixel `p` draws its `S` samples from a
//! randomized QMC point set whose randomization is seeded by `hash(job seed, frame, p, k)`.
//! Each pass is then an independent, identically distributed, unbiased estimate of the pixel,
//! and the spread between passes estimates the error of their mean (Owen 2001, section 6.7).

mod sobol;
pub mod warp;

use glam::Vec2;

/// Which randomized point set a [`PixelSampler`] draws from: the job contract's
/// [`tessera_farm::job::SamplerKind`]. `Sobol` is Owen-scrambled Sobol'
/// (Burley 2020): each 2D request is a fresh, independently scrambled and shuffled
/// (0,m,2)-net, padded by Latin supercube sampling (Owen 2001, section 6.8);
/// `Independent` is independent uniform random numbers from a hash of (pass, sample
/// index, dimension): plain Monte Carlo, the reference for unbiasedness and variance
/// comparisons.
pub use tessera_farm::job::SamplerKind;

/// Number of dimension indices (2D or 1D requests) per sample served by scrambled Sobol'
/// sets; deeper requests (long paths) are padded with hashed independent random numbers
/// (Owen 2001, section 6.8: the QMC structure matters for the first, most important dimensions).
/// Those are the very numbers [`SamplerKind::Independent`] returns for the same dimension.
const SOBOL_DIMENSIONS: u32 = 64;

/// `2^-24`: the spacing of the 24-bit grid on which sample values lie.
const INV_2_POW_24: f32 = 1.0 / 16_777_216.0;

/// Maps the top 24 bits of a 0.32 fixed-point value to an `f32` in `[0, 1)`.
///
/// An `f32` has a 24-bit significand, so every multiple of `2^-24` below one is exactly
/// representable and the largest result is `1 - 2^-24 < 1`. (Converting all 32 bits could
/// round up to exactly `1.0`.)
#[cfg(test)]
#[inline]
fn to_unit_f32(bits: u32) -> f32 {
    unit_f32_of_top24(bits >> 8)
}

/// `top24 * 2^-24`: a sample value from the top 24 bits of its 0.32 fixed-point word,
/// already shifted down (the sampler reverses only those bits). Every multiple of `2^-24`
/// below one is an exact `f32`, so the largest value is `1 - 2^-24 < 1`.
#[inline]
fn unit_f32_of_top24(top24: u32) -> f32 {
    top24 as f32 * INV_2_POW_24
}

/// The 64-bit finalizer of SplitMix64 (Steele, Lea & Flood 2014; "variant 13" constants by
/// Stafford): a bijection of `u64` with full avalanche, i.e. every input bit flips each output
/// bit with probability close to 1/2.
///
/// Note that `hash_u64(0) == 0` (it is a bijection built from xor-shifts and multiplications);
/// [`hash_combine`] adds a constant so that zero inputs still produce well-mixed seeds.
#[inline]
pub fn hash_u64(mut x: u64) -> u64 {
    x ^= x >> 30;
    x = x.wrapping_mul(0xbf58_476d_1ce4_e5b9);
    x ^= x >> 27;
    x = x.wrapping_mul(0x94d0_49bb_1331_11eb);
    x ^= x >> 31;
    x
}

/// Mixes `v` into the running hash `seed`; used to build seeds from tuples such as
/// (job seed, frame, pixel, pass).
///
/// `v` is first hashed with the golden-ratio increment of SplitMix64 so that small, dense
/// inputs (pixel 0, 1, 2, ...) become unrelated 64-bit words; the rotation of `seed` makes the
/// combination order-dependent (`hash_combine(hash_combine(s, a), b)` differs from the
/// swapped order), and the final [`hash_u64`] avalanches the result.
#[inline]
pub fn hash_combine(seed: u64, v: u64) -> u64 {
    hash_u64(seed.rotate_left(27) ^ hash_u64(v.wrapping_add(0x9e37_79b9_7f4a_7c15)))
}

/// Deterministic sample generator for one pass of one pixel.
///
/// Usage: for each sample index `i` of the pass call [`start_sample`](Self::start_sample),
/// then draw the dimensions of that sample in a fixed order with [`next_1d`](Self::next_1d) and
/// [`next_2d`](Self::next_2d). Each call consumes one *dimension index* (a 2D request is one
/// dimension index); the value depends only on (pass seed, sample index, dimension index), so
/// samples may be generated in any order and on any thread.
///
/// With [`SamplerKind::Sobol`], dimension index `d < 64` of samples `0..S` is the point set
/// `d` of the pass: a 2D Sobol' (0,m,2)-net (dimensions 0 and 1 of the sequence; a 1D request
/// uses dimension 0) with its own Owen scramble and its own Owen-scrambled index shuffle, all
/// seeded from (pass seed, `d`). Shuffling each set's run order independently is Latin
/// supercube sampling (Owen 2001, section 6.8): it decorrelates the sets, which would otherwise be
/// copies of one sequence, while each 2D set keeps its stratification. For `S` a power of two
/// every set is exactly stratified; for other `S` the first `S` points of a `2^m` set are used,
/// which stays unbiased because each point is uniformly distributed (Owen 2001, section 6.7).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PixelSampler {
    kind: SamplerKind,
    /// The seeds of point sets `0..64` of this pass, filled on first use: they depend on
    /// (pass seed, dimension) only, so the S samples of a pass share them (a cache, not
    /// state: values never depend on whether a seed was cached).
    scrambles: [sobol::Scramble; SOBOL_DIMENSIONS as usize],
    /// Bit `d` set when `scrambles[d]` is filled.
    filled: u64,
    /// `hash(job seed, frame, pixel, pass)`: the seed of every randomization in this pass.
    pass_seed: u64,
    /// `hash(pass seed, index)`, cached for the independent generator.
    sample_seed: u64,
    index: u32,
    /// `index.reverse_bits()`, cached: every Sobol' request of the sample shuffles the
    /// index, which starts from its bit reversal (x86 has no bit-reverse instruction).
    index_reversed: u32,
    dimension: u32,
}

impl PixelSampler {
    /// Creates the sampler of pass `pass` of pixel `pixel` (a linear pixel index) of frame
    /// `frame` of a job. Sample index and dimension start at 0.
    pub fn new(kind: SamplerKind, job_seed: u64, frame: u32, pixel: u32, pass: u32) -> Self {
        let pass_seed = hash_combine(
            hash_combine(hash_combine(hash_u64(job_seed), frame as u64), pixel as u64),
            pass as u64,
        );
        let mut sampler = PixelSampler {
            kind,
            scrambles: [sobol::Scramble {
                shuffle: 0,
                x: 0,
                y: 0,
            }; SOBOL_DIMENSIONS as usize],
            filled: 0,
            pass_seed,
            sample_seed: 0,
            index: 0,
            index_reversed: 0,
            dimension: 0,
        };
        sampler.start_sample(0);
        sampler
    }

    /// Starts sample `index` (within the pass) and resets the dimension index to 0.
    pub fn start_sample(&mut self, index: u32) {
        self.index = index;
        self.index_reversed = index.reverse_bits();
        self.dimension = 0;
        self.sample_seed = hash_combine(self.pass_seed, index as u64);
    }

    /// Next 1D value of the current sample, in `[0, 1)` (at most `1 - 2^-24`).
    pub fn next_1d(&mut self) -> f32 {
        let d = self.take_dimension();
        let top24 = match self.kind {
            SamplerKind::Sobol if d < SOBOL_DIMENSIONS => {
                let s = self.cached_scramble(d);
                // `to_unit_f32` of the reversed word keeps its top 24 bits: reverse just those.
                sobol::reverse_bits_top24(sobol::scrambled_sobol_1d_unreversed(
                    self.index_reversed,
                    s.shuffle,
                    s.x,
                ))
            }
            _ => ((self.random_bits(d) >> 32) as u32) >> 8,
        };
        unit_f32_of_top24(top24)
    }

    /// Next 2D value of the current sample, each component in `[0, 1)`.
    pub fn next_2d(&mut self) -> Vec2 {
        let d = self.take_dimension();
        let (x, y) = match self.kind {
            SamplerKind::Sobol if d < SOBOL_DIMENSIONS => {
                let (x, y) = sobol::scrambled_sobol_2d_unreversed(
                    self.index_reversed,
                    self.cached_scramble(d),
                );
                (sobol::reverse_bits_top24(x), sobol::reverse_bits_top24(y))
            }
            _ => {
                let h = self.random_bits(d);
                (((h >> 32) as u32) >> 8, (h as u32) >> 8)
            }
        };
        Vec2::new(unit_f32_of_top24(x), unit_f32_of_top24(y))
    }

    /// Passes over the next `n` dimension indices of the current sample without computing
    /// their values, as if they were drawn and discarded: the values drawn after it are
    /// the same (each depends on its dimension index alone), and the draws it saves cost
    /// about a hundred instructions each. For a technique that consumes a fixed set of
    /// dimensions per path vertex but does not need all of them at every vertex.
    #[inline]
    pub fn skip(&mut self, n: u32) {
        self.dimension = self.dimension.wrapping_add(n);
    }

    #[inline]
    fn take_dimension(&mut self) -> u32 {
        let d = self.dimension;
        self.dimension = d.wrapping_add(1);
        d
    }

    /// [`Self::scramble`] through the per-pass cache (`d < 64`).
    #[inline]
    fn cached_scramble(&mut self, d: u32) -> sobol::Scramble {
        let bit = 1u64 << d;
        if self.filled & bit == 0 {
            self.scrambles[d as usize] = self.scramble(d);
            self.filled |= bit;
        }
        self.scrambles[d as usize]
    }

    /// The three 32-bit seeds of point set `d` of this pass (index shuffle and the two
    /// coordinate scrambles), taken from two independent 64-bit hashes.
    #[inline]
    fn scramble(&self, d: u32) -> sobol::Scramble {
        let h = hash_combine(self.pass_seed, d as u64);
        let g = hash_u64(h);
        sobol::Scramble {
            shuffle: h as u32,
            x: (h >> 32) as u32,
            y: g as u32,
        }
    }

    /// 64 independent uniform bits for (pass, sample index, dimension `d`).
    #[inline]
    fn random_bits(&self, d: u32) -> u64 {
        // Keyed by the per-sample seed, so unlike the `scramble` seeds (keyed by the pass
        // seed alone) these differ for every sample index.
        hash_combine(self.sample_seed, d as u64)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const KINDS: [SamplerKind; 2] = [SamplerKind::Sobol, SamplerKind::Independent];

    #[test]
    fn parse_and_display() {
        assert_eq!("sobol".parse::<SamplerKind>(), Ok(SamplerKind::Sobol));
        assert_eq!(
            "independent".parse::<SamplerKind>(),
            Ok(SamplerKind::Independent)
        );
        let err = "halton".parse::<SamplerKind>().unwrap_err().to_string();
        assert!(err.contains("sobol") && err.contains("independent") && err.contains("halton"));
        for k in KINDS {
            assert_eq!(k.to_string().parse::<SamplerKind>(), Ok(k));
        }
    }

    #[test]
    fn hash_values_are_pinned() {
        // Bit-reproducibility across platforms: pin a few outputs. SplitMix64 of seed 0
        // produces 0xe220a8397b1dcdaf as its first output (= finalizer of the golden ratio).
        assert_eq!(hash_u64(0x9e37_79b9_7f4a_7c15), 0xe220_a839_7b1d_cdaf);
        assert_ne!(hash_combine(1, 2), hash_combine(2, 1));
        assert_ne!(hash_combine(0, 0), 0);
    }

    #[test]
    fn deterministic_and_pass_dependent() {
        for kind in KINDS {
            let draw = |pass: u32, pixel: u32| {
                let mut s = PixelSampler::new(kind, 42, 7, pixel, pass);
                let mut v = Vec::new();
                for i in [0u32, 1, 5, 3] {
                    s.start_sample(i);
                    for _ in 0..70 {
                        v.push(s.next_1d());
                        let p = s.next_2d();
                        v.extend([p.x, p.y]);
                    }
                }
                v
            };
            let a = draw(0, 10);
            assert_eq!(a, draw(0, 10), "{kind}: same inputs must give same values");
            assert_ne!(a, draw(1, 10), "{kind}: different pass");
            assert_ne!(a, draw(0, 11), "{kind}: different pixel");
            // Order independence: sample 5 drawn alone equals sample 5 drawn after others.
            let mut s = PixelSampler::new(kind, 42, 7, 10, 0);
            s.start_sample(5);
            assert_eq!(s.next_1d(), a[2 * 70 * 3]);
            // Different job seeds and frames give different values.
            let mut t = PixelSampler::new(kind, 43, 7, 10, 0);
            assert_ne!(t.next_2d(), PixelSampler::new(kind, 42, 7, 10, 0).next_2d());
            t = PixelSampler::new(kind, 42, 8, 10, 0);
            assert_ne!(t.next_2d(), PixelSampler::new(kind, 42, 7, 10, 0).next_2d());
        }
    }

    #[test]
    fn values_in_unit_interval() {
        for kind in KINDS {
            for pass in 0..64 {
                let mut s = PixelSampler::new(kind, 9, 0, pass * 31, pass);
                for i in 0..64 {
                    s.start_sample(i);
                    for _ in 0..80 {
                        let a = s.next_1d();
                        let p = s.next_2d();
                        for v in [a, p.x, p.y] {
                            assert!((0.0..1.0).contains(&v), "{kind}: {v}");
                        }
                    }
                }
            }
        }
        assert!(to_unit_f32(u32::MAX) < 1.0);
        assert_eq!(to_unit_f32(u32::MAX), 1.0 - INV_2_POW_24);
    }

    #[test]
    fn sobol_pass_is_a_0_4_2_net() {
        // 16 samples of one pass: exactly one point in every elementary interval of area
        // 1/16 (16x1, 8x2, 4x4, 2x8, 1x16 grids), for several dimension indices, pixels and
        // passes; Owen scrambling and the index shuffle preserve the (0,4,2)-net.
        for pixel in 0..8 {
            for pass in 0..8 {
                let mut s = PixelSampler::new(SamplerKind::Sobol, 1234, 0, pixel, pass);
                let mut sets = vec![Vec::new(); 6];
                let mut ones = vec![Vec::new(); 3];
                for i in 0..16 {
                    s.start_sample(i);
                    for set in sets.iter_mut() {
                        set.push(s.next_2d());
                    }
                    for one in ones.iter_mut() {
                        one.push(s.next_1d());
                    }
                }
                for (d, pts) in sets.iter().enumerate() {
                    for (nx, ny) in [(4, 4), (16, 1), (1, 16), (8, 2), (2, 8)] {
                        let mut hit = vec![0u32; 16];
                        for p in pts {
                            let cx = (p.x * nx as f32) as usize;
                            let cy = (p.y * ny as f32) as usize;
                            hit[cx * ny + cy] += 1;
                        }
                        assert!(
                            hit.iter().all(|&h| h == 1),
                            "pixel {pixel} pass {pass} dim {d} grid {nx}x{ny}: {hit:?}"
                        );
                    }
                }
                for one in &ones {
                    let mut hit = [0u32; 16];
                    for v in one {
                        hit[(v * 16.0) as usize] += 1;
                    }
                    assert!(hit.iter().all(|&h| h == 1), "1D: {hit:?}");
                }
            }
        }
    }

    #[test]
    fn sobol_sets_differ_between_dimensions() {
        // Padding must not reuse one scramble for every dimension (Owen 2001, section 6.8: k copies of
        // the same randomization would be perfectly correlated).
        let mut s = PixelSampler::new(SamplerKind::Sobol, 5, 0, 0, 0);
        let a = s.next_2d();
        let b = s.next_2d();
        assert_ne!(a, b);
    }

    /// Per-pass estimates of the integral of x*y over samples 0..n of passes 0..k, each pass
    /// using dimension index `dim` (the earlier indices are drawn and discarded).
    fn pass_estimates(kind: SamplerKind, n: u32, k: u32, dim: u32) -> Vec<f64> {
        (0..k)
            .map(|pass| {
                let mut s = PixelSampler::new(kind, 0xfeed, 1, 77, pass);
                let mut sum = 0.0f64;
                for i in 0..n {
                    s.start_sample(i);
                    for _ in 0..dim {
                        s.next_2d();
                    }
                    let p = s.next_2d();
                    sum += p.x as f64 * p.y as f64;
                }
                sum / n as f64
            })
            .collect()
    }

    /// Mean and sample variance (unbiased, 1/(K-1)) of the pass estimates.
    fn mean_var(v: &[f64]) -> (f64, f64) {
        let k = v.len() as f64;
        let mean = v.iter().sum::<f64>() / k;
        let var = v.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / (k - 1.0);
        (mean, var)
    }

    #[test]
    fn passes_are_unbiased_replicates() {
        // z-test of Owen 2001, section 6.7: the mean of K independent replicates has standard error
        // sqrt(var / K), estimated from the pass-to-pass variance. Exact integral: 1/4.
        // Dimension indices 0 (first set), 5 (a padded set) and 70 (hashed padding).
        for kind in KINDS {
            for dim in [0u32, 5, 70] {
                let est = pass_estimates(kind, 16, 4000, dim);
                let (mean, var) = mean_var(&est);
                let se = (var / est.len() as f64).sqrt();
                let z = (mean - 0.25) / se;
                eprintln!("{kind} dim {dim}: mean {mean:.8} se {se:.3e} z {z:+.2}");
                assert!(z.abs() < 3.0, "{kind} dim {dim}: z = {z}");
            }
        }
    }

    #[test]
    fn sobol_pass_variance_beats_independent() {
        // For a smooth integrand scrambled nets have variance o(1/n) (Owen 2001, section 6.7), far
        // below the Monte Carlo sigma^2/n; at S = 64 the ratio must be < 0.2.
        let (_, v_sobol) = mean_var(&pass_estimates(SamplerKind::Sobol, 64, 2000, 0));
        let (_, v_indep) = mean_var(&pass_estimates(SamplerKind::Independent, 64, 2000, 0));
        let ratio = v_sobol / v_indep;
        eprintln!(
            "S=64 pass variance: sobol {v_sobol:.3e} independent {v_indep:.3e} ratio {ratio:.4}"
        );
        // Independent: Var(xy)/64 = (1/9 - 1/16)/64.
        let mc = (1.0 / 9.0 - 1.0 / 16.0) / 64.0;
        assert!(
            (v_indep / mc - 1.0).abs() < 0.15,
            "independent variance {v_indep} vs {mc}"
        );
        assert!(ratio < 0.2, "ratio {ratio}");
    }

    #[test]
    fn independent_dimensions_are_uncorrelated() {
        // Cheap sanity check of the hash: the two components and consecutive dimensions of
        // the independent sampler have correlation ~0 (|r| < 4 / sqrt(n)).
        let n = 20_000u32;
        let mut s = PixelSampler::new(SamplerKind::Independent, 1, 0, 0, 0);
        let (mut sxy, mut sxz) = (0.0f64, 0.0f64);
        for i in 0..n {
            s.start_sample(i);
            let p = s.next_2d();
            let z = s.next_1d();
            sxy += (p.x as f64 - 0.5) * (p.y as f64 - 0.5);
            sxz += (p.x as f64 - 0.5) * (z as f64 - 0.5);
        }
        let r = |s: f64| s / n as f64 * 12.0;
        let bound = 4.0 / (n as f64).sqrt();
        assert!(r(sxy).abs() < bound && r(sxz).abs() < bound);
    }

    #[test]
    fn pixel_sampler_fits_on_the_stack_without_heap() {
        // 64 cached scramble seeds plus counters: stack-only, no allocation per pixel.
        assert!(std::mem::size_of::<PixelSampler>() <= 1024);
    }

    #[test]
    fn skipped_dimensions_leave_the_later_values_alone() {
        // Drawing and discarding 1D and 2D values is the same as skipping them: the values
        // after agree bit for bit, in the Sobol' sets and in the hashed padding.
        for kind in KINDS {
            let mut drawn = PixelSampler::new(kind, 3, 1, 40, 2);
            let mut skipped = drawn.clone();
            for i in 0..4 {
                drawn.start_sample(i);
                skipped.start_sample(i);
                for k in 0..40 {
                    if k % 3 == 0 {
                        drawn.next_1d();
                        drawn.next_2d();
                        skipped.skip(2);
                    }
                    assert_eq!(drawn.next_2d(), skipped.next_2d(), "{kind} {i} {k}");
                    assert_eq!(drawn.next_1d(), skipped.next_1d(), "{kind} {i} {k}");
                }
            }
        }
    }

    #[test]
    fn cached_scrambles_do_not_change_values() {
        // Drawing samples in a different order (so the cache fills differently) gives the
        // same values: the cache is invisible.
        let mut a = PixelSampler::new(SamplerKind::Sobol, 5, 0, 17, 3);
        let mut forward = Vec::new();
        for i in 0..8 {
            a.start_sample(i);
            forward.push((a.next_2d(), a.next_1d(), a.next_2d()));
        }
        for i in (0..8).rev() {
            let mut b = PixelSampler::new(SamplerKind::Sobol, 5, 0, 17, 3);
            b.start_sample(i);
            assert_eq!(forward[i as usize], (b.next_2d(), b.next_1d(), b.next_2d()));
        }
    }
}
