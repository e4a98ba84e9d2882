//! Owen-scrambled Sobol' points in two dimensions, in pure `u32` arithmetic.
//!
//! The construction follows Burley 2020, "Practical Hash-based Owen Scrambling" (JCGT 9(4)):
//!
//! 1. the sample index is itself Owen-scrambled ("shuffled"), which turns the first `S`
//!    indices into a random aligned block of `2^m >= S` consecutive indices of the sequence,
//!    visited in a random nested order;
//! 2. the Sobol' point of that index is computed from the generator matrices of
//!    dimensions 0 and 1;
//! 3. every coordinate is Owen-scrambled (nested uniform scrambling, Owen 2001, section 6.7) with a
//!    hash-based Laine–Karras permutation applied to the bit-reversed value.
//!
//! Only Sobol' dimensions 0 and 1 are ever used: higher dimensions of the integrand get
//! fresh, independently scrambled and shuffled copies of this 2D set (padding by Latin
//! supercube sampling, Owen 2001, section 6.8; see `super::PixelSampler`). Dimensions 0 and 1 of
//! Sobol' form a (0,2)-sequence in base 2, so every aligned block of `2^m` points is a
//! (0,m,2)-net, and Owen scrambling preserves the net property with probability one
//! (Owen 2001, section 6.7).

/// Generator matrix of Sobol' dimension 1 as 32 direction numbers `v_k = m_k / 2^k`, stored
/// as 0.32 fixed point; index bit `k` toggles `v_{k+1}`.
///
/// Dimension 1 uses the primitive polynomial `x + 1` (degree 1), whose recurrence for the
/// odd integers `m_k` is `m_k = 2 m_{k-1} XOR m_{k-1}` with `m_1 = 1` (Bratley & Fox 1988).
/// The result is Pascal's triangle modulo 2 (1, 3, 5, 15, 17, 51, ...), so it is generated
/// here rather than pasted as a table.
const SOBOL_DIM1: [u32; 32] = {
    let mut v = [0u32; 32];
    let mut m: u32 = 1;
    let mut k = 0;
    while k < 32 {
        // m_{k+1} has at most k + 1 significant bits; shifting by 31 - k left-aligns
        // m_{k+1} / 2^{k+1} in 0.32 fixed point.
        v[k] = m << (31 - k);
        m ^= m << 1;
        k += 1;
    }
    v
};

/// Sobol' dimension 0 of `index` in 0.32 fixed point: the van der Corput radical inverse in
/// base 2, i.e. the bit reversal of the index (its generator matrix is the identity).
/// (The hot path folds this reversal away; kept as the textbook reference for tests.)
#[cfg(test)]
#[inline]
pub(crate) fn sobol_dim0(index: u32) -> u32 {
    index.reverse_bits()
}

/// [`SOBOL_DIM1`] folded into four byte tables: entry `[b][v]` is the XOR of the direction
/// numbers selected by byte value `v` at byte position `b` of the index. The shuffled
/// indices carry seed-dependent high bits, so a bit loop would run ~16 times per point;
/// four lookups do the same GF(2) product.
const SOBOL_DIM1_BYTES: [[u32; 256]; 4] = {
    let mut t = [[0u32; 256]; 4];
    let mut b = 0;
    while b < 4 {
        let mut v = 0;
        while v < 256 {
            let mut x = 0u32;
            let mut k = 0;
            while k < 8 {
                if v & (1 << k) != 0 {
                    x ^= SOBOL_DIM1[b * 8 + k];
                }
                k += 1;
            }
            t[b][v] = x;
            v += 1;
        }
        b += 1;
    }
    t
};

/// Sobol' dimension 1 of `index` in 0.32 fixed point: the XOR of the direction numbers
/// selected by the set bits of the index (a matrix–vector product over GF(2)).
/// (The hot path uses [`sobol_dim1_reversed`]; this is the reference for tests.)
#[cfg(test)]
#[inline]
pub(crate) fn sobol_dim1(index: u32) -> u32 {
    let [b0, b1, b2, b3] = index.to_le_bytes();
    SOBOL_DIM1_BYTES[0][b0 as usize]
        ^ SOBOL_DIM1_BYTES[1][b1 as usize]
        ^ SOBOL_DIM1_BYTES[2][b2 as usize]
        ^ SOBOL_DIM1_BYTES[3][b3 as usize]
}

/// `sobol_dim1(index).reverse_bits()`, from bit-reversed byte tables.
#[inline]
pub(crate) fn sobol_dim1_reversed(index: u32) -> u32 {
    let [b0, b1, b2, b3] = index.to_le_bytes();
    SOBOL_DIM1_REV_BYTES[0][b0 as usize]
        ^ SOBOL_DIM1_REV_BYTES[1][b1 as usize]
        ^ SOBOL_DIM1_REV_BYTES[2][b2 as usize]
        ^ SOBOL_DIM1_REV_BYTES[3][b3 as usize]
}

/// [`SOBOL_DIM1_BYTES`] with every entry bit-reversed (reversal distributes over XOR).
const SOBOL_DIM1_REV_BYTES: [[u32; 256]; 4] = {
    let mut t = SOBOL_DIM1_BYTES;
    let mut b = 0;
    while b < 4 {
        let mut v = 0;
        while v < 256 {
            t[b][v] = t[b][v].reverse_bits();
            v += 1;
        }
        b += 1;
    }
    t
};

/// The bit-loop form of [`sobol_dim1`], kept as the reference for its test.
#[cfg(test)]
fn sobol_dim1_reference(index: u32) -> u32 {
    let mut bits = index;
    let mut x = 0u32;
    while bits != 0 {
        let k = bits.trailing_zeros();
        x ^= SOBOL_DIM1[k as usize];
        bits &= bits - 1;
    }
    x
}

/// `REVERSED_BYTES[k][v]`: the byte value `v` bit-reversed and placed where byte `k` of a
/// `u32` lands when the word is bit-reversed (byte `3 - k`).
const REVERSED_BYTES: [[u32; 256]; 4] = {
    let mut t = [[0u32; 256]; 4];
    let mut k = 0;
    while k < 4 {
        let mut v = 0;
        while v < 256 {
            t[k][v] = ((v as u8).reverse_bits() as u32) << (24 - 8 * k);
            v += 1;
        }
        k += 1;
    }
    t
};

/// `x.reverse_bits()` from byte tables. x86-64 has no bit-reverse instruction: the
/// compiler's byte swap and three mask-and-shift rounds take about twenty instructions,
/// four table look-ups about a dozen, and a sample's values reverse two or three words
/// each (docs/benchmarks.md, "Raw speed", 2026-12-06 evening).
#[inline]
pub(crate) fn reverse_bits(x: u32) -> u32 {
    let [b0, b1, b2, b3] = x.to_le_bytes();
    REVERSED_BYTES[0][b0 as usize]
        | REVERSED_BYTES[1][b1 as usize]
        | REVERSED_BYTES[2][b2 as usize]
        | REVERSED_BYTES[3][b3 as usize]
}

/// `x.reverse_bits() >> 8`: the top 24 bits of the reversal, which are all a sample
/// value keeps (`super::unit_f32_of_top24`); three look-ups, byte 3 of `x` would land below them.
#[inline]
pub(crate) fn reverse_bits_top24(x: u32) -> u32 {
    let [b0, b1, b2, _] = x.to_le_bytes();
    (REVERSED_BYTES[0][b0 as usize]
        | REVERSED_BYTES[1][b1 as usize]
        | REVERSED_BYTES[2][b2 as usize])
        >> 8
}

/// Laine–Karras style hash permutation on a bit-reversed integer, with Vegdahl's improved
/// constants ("Building a better LK hash", 2021, as used by Blender Cycles).
///
/// Every step (XOR with a multiple by an even constant, adding the seed, multiplying by an
/// odd constant) changes bit `i` only as a function of bits `<= i`, and flips bit `i` by a
/// function of the bits strictly below it. On reversed bits "below" means "more significant
/// digits of the original value", which is exactly Owen's nested uniform scrambling: the
/// permutation applied to digit `k` depends on the preceding `k - 1` digits (Owen 2001, section 6.7).
#[inline]
pub(crate) fn laine_karras_permutation(mut x: u32, seed: u32) -> u32 {
    x ^= x.wrapping_mul(0x3d20_adea);
    x = x.wrapping_add(seed);
    x = x.wrapping_mul((seed >> 16) | 1);
    x ^= x.wrapping_mul(0x0552_6c56);
    x ^= x.wrapping_mul(0x53a2_2864);
    x
}

/// Base-2 Owen scrambling (nested uniform scrambling, Owen 2001, section 6.7) of a 0.32 fixed-point
/// value, or of an integer index (Burley 2020 §3: the same operation shuffles the index).
/// (The hot path folds its first reversal into the sampler; kept as the textbook
/// reference for tests.)
#[cfg(test)]
#[inline]
pub(crate) fn nested_uniform_scramble(x: u32, seed: u32) -> u32 {
    laine_karras_permutation(x.reverse_bits(), seed).reverse_bits()
}

/// Seeds of one Owen-scrambled, shuffled 2D Sobol' point set.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Scramble {
    /// Seed of the index shuffle (the Latin supercube permutation of Owen 2001, section 6.8).
    pub(crate) shuffle: u32,
    /// Seed of the Owen scramble of coordinate 0.
    pub(crate) x: u32,
    /// Seed of the Owen scramble of coordinate 1.
    pub(crate) y: u32,
}

/// Point `index` of a shuffled, Owen-scrambled 2D Sobol' set, in 0.32 fixed point, given
/// `index_reversed = index.reverse_bits()` (the sampler reverses each sample's index once).
///
/// For `index < 2^m` the shuffled indices are a permutation of one aligned block of `2^m`
/// consecutive sequence indices: the Owen scramble of the index permutes its low `m` bits
/// among themselves and maps the (all-zero) high bits to a seed-dependent constant. Such a
/// block of a (0,2)-sequence is a (0,m,2)-net.
#[cfg(test)]
#[inline]
pub(crate) fn shuffled_scrambled_sobol_2d(index_reversed: u32, s: Scramble) -> (u32, u32) {
    let (x, y) = scrambled_sobol_2d_unreversed(index_reversed, s);
    (reverse_bits(x), reverse_bits(y))
}

/// [`shuffled_scrambled_sobol_2d`] before its two final bit reversals, which the sampler
/// takes by [`reverse_bits_top24`] (the bits a sample value keeps).
#[inline]
pub(crate) fn scrambled_sobol_2d_unreversed(index_reversed: u32, s: Scramble) -> (u32, u32) {
    // nested_uniform_scramble(index, shuffle), its first reversal done by the caller.
    let i = reverse_bits(laine_karras_permutation(index_reversed, s.shuffle));
    // nested_uniform_scramble(v, seed) = rev(LK(rev(v), seed)); with dimension 0 being
    // rev(i) and dimension 1 read from bit-reversed tables, the inner reversals cancel
    // (x86 has no bit-reverse instruction, so this saves three of seven).
    (
        laine_karras_permutation(i, s.x),
        laine_karras_permutation(sobol_dim1_reversed(i), s.y),
    )
}

/// Point `index` of a shuffled, Owen-scrambled 1D Sobol' (van der Corput) set, in 0.32
/// fixed point, given `index_reversed = index.reverse_bits()`; any `2^m` consecutive
/// shuffled indices starting at 0 are stratified into `2^m` equal intervals.
#[cfg(test)]
#[inline]
pub(crate) fn shuffled_scrambled_sobol_1d(index_reversed: u32, shuffle: u32, seed: u32) -> u32 {
    reverse_bits(scrambled_sobol_1d_unreversed(index_reversed, shuffle, seed))
}

/// [`shuffled_scrambled_sobol_1d`] before its final bit reversal (see
/// [`scrambled_sobol_2d_unreversed`]).
#[inline]
pub(crate) fn scrambled_sobol_1d_unreversed(index_reversed: u32, shuffle: u32, seed: u32) -> u32 {
    let i = reverse_bits(laine_karras_permutation(index_reversed, shuffle));
    // As in the 2D case: rev(LK(rev(rev(i)))) = rev(LK(i)).
    laine_karras_permutation(i, seed)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cancelled_reversals_give_the_textbook_composition() {
        let mut x = 0x9e37_79b9u32;
        for index in 0..4096u32 {
            x = x.wrapping_mul(747_796_405).wrapping_add(2_891_336_453);
            let s = Scramble {
                shuffle: x,
                x: x.rotate_left(11) ^ 0x5bd1_e995,
                y: x.rotate_left(23),
            };
            let j = nested_uniform_scramble(index, s.shuffle);
            let textbook = (
                nested_uniform_scramble(sobol_dim0(j), s.x),
                nested_uniform_scramble(sobol_dim1(j), s.y),
            );
            let reversed = index.reverse_bits();
            assert_eq!(shuffled_scrambled_sobol_2d(reversed, s), textbook);
            assert_eq!(
                shuffled_scrambled_sobol_1d(reversed, s.shuffle, s.x),
                textbook.0
            );
        }
    }

    #[test]
    fn table_reversal_is_the_bit_reversal() {
        let mut x = 0x0bad_cafeu32;
        for i in 0..100_000u32 {
            x = x.wrapping_mul(747_796_405).wrapping_add(2_891_336_453);
            for v in [i, x, !i, i << 16] {
                assert_eq!(reverse_bits(v), v.reverse_bits(), "{v:#x}");
                assert_eq!(reverse_bits_top24(v), v.reverse_bits() >> 8, "{v:#x}");
            }
        }
        for v in [0, 1, u32::MAX, 0x8000_0000] {
            assert_eq!(reverse_bits(v), v.reverse_bits());
        }
    }

    #[test]
    fn byte_tables_equal_the_bit_loop() {
        let mut x = 0x1234_5678u32;
        for i in 0..100_000u32 {
            x = x.wrapping_mul(747_796_405).wrapping_add(2_891_336_453);
            assert_eq!(sobol_dim1(i), sobol_dim1_reference(i));
            assert_eq!(sobol_dim1(x), sobol_dim1_reference(x));
            assert_eq!(
                sobol_dim1_reversed(x),
                sobol_dim1_reference(x).reverse_bits()
            );
        }
    }

    #[test]
    fn sobol_dim1_matches_known_prefix() {
        // Sobol' dimension 2 in the usual 1-based numbering (Joe–Kuo table line 1), points
        // 0..8 in natural (not Gray-code) order: v_1 = 1/2, v_2 = 3/4, v_3 = 5/8 and XORs.
        let expected = [0.0, 0.5, 0.75, 0.25, 0.625, 0.125, 0.375, 0.875];
        for (i, e) in expected.iter().enumerate() {
            let x = sobol_dim1(i as u32) as f64 / 4294967296.0;
            assert_eq!(x, *e, "index {i}");
        }
        // m_k for x + 1 is Pascal's triangle mod 2: 1, 3, 5, 15, 17, 51.
        let m: Vec<u32> = (0..6).map(|k| SOBOL_DIM1[k] >> (31 - k)).collect();
        assert_eq!(m, vec![1, 3, 5, 15, 17, 51]);
    }

    #[test]
    fn unscrambled_blocks_are_0_m_2_nets() {
        // Every aligned block of 2^m points of dims (0,1) is a (0,m,2)-net: one point in
        // each elementary interval of area 2^-m.
        for m in 1..=8u32 {
            for block in [0u32, 1, 7, 1000] {
                let pts: Vec<(u32, u32)> = (0..(1u32 << m))
                    .map(|i| {
                        let idx = (block << m) | i;
                        (sobol_dim0(idx), sobol_dim1(idx))
                    })
                    .collect();
                assert!(is_net(&pts, m), "m = {m}, block = {block}");
            }
        }
    }

    #[test]
    fn scrambled_shuffled_sets_stay_nets() {
        for m in 1..=8u32 {
            for seed in 0..20u32 {
                let s = Scramble {
                    shuffle: seed.wrapping_mul(0x9e37_79b9),
                    x: seed.wrapping_mul(0x85eb_ca6b) ^ 0x1234,
                    y: seed.wrapping_mul(0xc2b2_ae35) ^ 0x5678,
                };
                let pts: Vec<(u32, u32)> = (0..(1u32 << m))
                    .map(|i| shuffled_scrambled_sobol_2d(i.reverse_bits(), s))
                    .collect();
                assert!(is_net(&pts, m), "m = {m}, seed = {seed}");
            }
        }
    }

    #[test]
    fn owen_scramble_is_a_bijection_on_prefixes() {
        // Nested scrambling maps each dyadic interval of length 2^-k onto one of the same
        // length: the top k bits of the output depend only on the top k bits of the input.
        for seed in [0u32, 1, 0xdead_beef, 0x1357_9bdf] {
            let mut seen = [false; 256];
            for top in 0..256u32 {
                let a = nested_uniform_scramble(top << 24, seed) >> 24;
                let b = nested_uniform_scramble((top << 24) | 0x00ab_cdef, seed) >> 24;
                assert_eq!(a, b);
                assert!(!seen[a as usize]);
                seen[a as usize] = true;
            }
        }
    }

    /// True when the 2^m points have exactly one point in every elementary interval
    /// [a 2^-k, (a+1) 2^-k) x [b 2^-(m-k), (b+1) 2^-(m-k)), k = 0..=m.
    fn is_net(pts: &[(u32, u32)], m: u32) -> bool {
        (0..=m).all(|k| {
            let mut hit = vec![false; 1 << m];
            pts.iter().all(|&(x, y)| {
                let cx = if k == 0 { 0 } else { x >> (32 - k) };
                let cy = if k == m { 0 } else { y >> (32 - (m - k)) };
                let cell = ((cx << (m - k)) | cy) as usize;
                !std::mem::replace(&mut hit[cell], true)
            })
        })
    }
}
