//! SplitMix64 (Steele, Lea & Flood 2014), the fuzz harnesses' generator: small, seedable
//! and without a dependency, so a failing iteration is replayed from its seed alone.
//! Used by the coordinator's gRPC and HTTP fuzz tests and the scene crate's glTF fuzz
//! test.

/// The generator's state; `SplitMix64(seed)` starts it.
pub struct SplitMix64(pub u64);

impl SplitMix64 {
    /// The next 64 random bits.
    // Not `Iterator::next`: the stream never ends, and the harnesses want the bare call.
    #[allow(clippy::should_implement_trait)]
    pub fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// A number below `n` (0 for `n = 0`); the modulo bias is irrelevant for fuzzing.
    pub fn below(&mut self, n: u64) -> u64 {
        self.next() % n.max(1)
    }

    /// An index below `n` (0 for `n = 0`).
    pub fn index(&mut self, n: usize) -> usize {
        self.below(n as u64) as usize
    }

    /// One of `xs`, which must not be empty.
    pub fn pick<'a, T>(&mut self, xs: &'a [T]) -> &'a T {
        &xs[self.index(xs.len())]
    }
}
