//! The pixels of a tile a leased unit must trace: a run-length list over the
//! tile's row-major pixel indices.
//!
//! An adaptive job's lease names the pixels the policy still wants for the unit's passes
//! ([`crate::Scheduler::wanted_pixels`]); a worker traces only those and reports the
//! others as black, so a pixel that stopped costs nothing. The set is computed from
//! decisions already taken at the unit's first pass, which the lease horizon guarantees
//! are final (`crate::adaptive`), so it is a pure function of the job: every copy of a
//! unit carries the same set and renders the same bytes, and duplicates still compare
//! byte-identical.
//!
//! Runs are the canonical form: sorted, disjoint, non-adjacent `(start, len)` pairs with
//! `len >= 1`. Stopped pixels come in blobs (dilation stops whole neighbourhoods, and
//! converged regions are large), so a handful of runs per tile row is typical; the worst
//! case (alternate pixels) is one run per two pixels, no larger than a bitmask of 32-bit
//! words. On the wire (`tessera.v1.PixelRuns`) the pairs are flattened; an absent or
//! empty list means every pixel, so jobs without adaptive stopping and coordinators that
//! predate the field lease whole tiles as before.
//!
//! ```
//! use tessera_farm::PixelRuns;
//!
//! let wanted = [false, true, true, false, true, true, true, false];
//! let runs = PixelRuns::from_fn(wanted.len(), |i| wanted[i]);
//! assert_eq!(runs.flat(), vec![1, 2, 4, 3]);
//! assert_eq!(runs.count(), 5);
//! assert!(runs.contains(5) && !runs.contains(7));
//! assert_eq!(PixelRuns::from_flat(&runs.flat(), wanted.len())?, runs);
//! assert!(PixelRuns::from_flat(&[4, 2, 1, 1], 8).is_err()); // not sorted
//! # Ok::<(), tessera_farm::MaskError>(())
//! ```

/// Why a run-length pixel list is malformed (the worker refuses the lease with it).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum MaskError {
    /// An odd number of values: they are (start, length) pairs.
    #[error("has {0} values, not (start, length) pairs")]
    Odd(usize),
    /// More runs than a tile of this size can have.
    #[error("has {runs} runs, more than a tile of {pixels} pixels can have")]
    TooMany {
        /// Runs given.
        runs: usize,
        /// Pixels in the tile.
        pixels: usize,
    },
    /// A run of length 0.
    #[error("run {0} has length 0")]
    Empty(usize),
    /// A run that starts before the previous one ended (or touches it: runs are merged).
    #[error("run {index} starts at pixel {start}, not after the end of the previous run ({previous_end}) with a gap")]
    Order {
        /// The run's index.
        index: usize,
        /// Its start.
        start: u32,
        /// One past the previous run's last pixel.
        previous_end: u64,
    },
    /// A run past the tile's last pixel.
    #[error("run {index} ends at pixel {end}, past the tile's {pixels} pixels")]
    OutOfTile {
        /// The run's index.
        index: usize,
        /// One past its last pixel.
        end: u64,
        /// Pixels in the tile.
        pixels: usize,
    },
}

/// A set of pixels of one tile (row-major indices), as sorted, disjoint, non-adjacent
/// runs. See the module documentation.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct PixelRuns {
    /// `(start, len)`, canonical.
    runs: Vec<(u32, u32)>,
}

impl PixelRuns {
    /// The pixels `i < pixel_count` for which `wanted(i)` holds, in canonical runs.
    pub fn from_fn(pixel_count: usize, wanted: impl Fn(usize) -> bool) -> Self {
        let mut runs: Vec<(u32, u32)> = Vec::new();
        let mut open: Option<(u32, u32)> = None;
        for i in 0..pixel_count {
            // Tile pixel counts are bounded by the plan (at most 2^20 for a whole frame).
            let Ok(p) = u32::try_from(i) else { break };
            match (wanted(i), open.as_mut()) {
                (true, Some((_, len))) => *len += 1,
                (true, None) => open = Some((p, 1)),
                (false, Some(_)) => runs.extend(open.take()),
                (false, None) => {}
            }
        }
        runs.extend(open);
        Self { runs }
    }

    /// Decodes the wire form, `start, len` pairs flattened, checking it against a tile of
    /// `pixel_count` pixels: pairs, every run non-empty, in order with gaps between, and
    /// inside the tile.
    pub fn from_flat(values: &[u32], pixel_count: usize) -> Result<Self, MaskError> {
        if !values.len().is_multiple_of(2) {
            return Err(MaskError::Odd(values.len()));
        }
        let n = values.len() / 2;
        // Canonical runs have gaps between them, so a tile holds at most ceil(p / 2).
        if n > pixel_count.div_ceil(2) {
            return Err(MaskError::TooMany {
                runs: n,
                pixels: pixel_count,
            });
        }
        let mut runs = Vec::with_capacity(n);
        let mut previous_end: Option<u64> = None;
        for (index, pair) in values.chunks_exact(2).enumerate() {
            let (start, len) = (pair[0], pair[1]);
            if len == 0 {
                return Err(MaskError::Empty(index));
            }
            if let Some(prev) = previous_end {
                if u64::from(start) <= prev {
                    return Err(MaskError::Order {
                        index,
                        start,
                        previous_end: prev,
                    });
                }
            }
            let end = u64::from(start) + u64::from(len);
            if end > pixel_count as u64 {
                return Err(MaskError::OutOfTile {
                    index,
                    end,
                    pixels: pixel_count,
                });
            }
            previous_end = Some(end);
            runs.push((start, len));
        }
        Ok(Self { runs })
    }

    /// The wire form: `start, len` pairs flattened.
    pub fn flat(&self) -> Vec<u32> {
        self.runs.iter().flat_map(|&(s, l)| [s, l]).collect()
    }

    /// The runs, `(start, len)`, in order.
    pub fn runs(&self) -> &[(u32, u32)] {
        &self.runs
    }

    /// Whether no pixel is in the set.
    pub fn is_empty(&self) -> bool {
        self.runs.is_empty()
    }

    /// Number of pixels in the set.
    pub fn count(&self) -> u64 {
        self.runs.iter().map(|&(_, l)| u64::from(l)).sum()
    }

    /// Whether every one of `pixel_count` pixels is in the set.
    pub fn covers(&self, pixel_count: usize) -> bool {
        self.count() == pixel_count as u64
    }

    /// Whether pixel `i` is in the set: a binary search over the runs, no allocation
    /// (the worker calls it once per pixel and pass).
    #[inline]
    pub fn contains(&self, i: usize) -> bool {
        let Ok(i) = u32::try_from(i) else {
            return false;
        };
        // The first run that ends after `i`; `i` is in the set if that run starts at or
        // before it.
        let k = self
            .runs
            .partition_point(|&(s, l)| u64::from(s) + u64::from(l) <= u64::from(i));
        self.runs.get(k).is_some_and(|&(s, _)| s <= i)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_util::Rng;

    #[test]
    fn random_sets_round_trip_through_the_wire_form() {
        let mut rng = Rng::new(15);
        for case in 0..500 {
            let n = 1 + (rng.next_u64() % 300) as usize;
            // From dense to sparse, and blobs (runs of equal decisions).
            let p = rng.uniform();
            let blob = 1 + (rng.next_u64() % 8) as usize;
            let bits: Vec<bool> = (0..n.div_ceil(blob))
                .flat_map(|_| std::iter::repeat_n(rng.uniform() < p, blob))
                .take(n)
                .collect();
            let runs = PixelRuns::from_fn(n, |i| bits[i]);
            for (i, &b) in bits.iter().enumerate() {
                assert_eq!(runs.contains(i), b, "case {case} pixel {i}");
            }
            assert!(!runs.contains(n) && !runs.contains(usize::MAX));
            assert_eq!(runs.count(), bits.iter().filter(|&&b| b).count() as u64);
            assert_eq!(runs.covers(n), bits.iter().all(|&b| b));
            let back = PixelRuns::from_flat(&runs.flat(), n).unwrap();
            assert_eq!(back, runs, "case {case}");
            // Canonical: gaps between runs, none empty.
            for w in runs.runs().windows(2) {
                assert!(w[0].0 + w[0].1 < w[1].0);
            }
        }
    }

    #[test]
    fn extremes() {
        let all = PixelRuns::from_fn(1024, |_| true);
        assert_eq!(all.flat(), vec![0, 1024]);
        assert!(all.covers(1024));
        let none = PixelRuns::from_fn(1024, |_| false);
        assert!(none.is_empty() && none.flat().is_empty() && !none.contains(0));
        let alternate = PixelRuns::from_fn(9, |i| i % 2 == 0);
        assert_eq!(alternate.runs().len(), 5);
        assert_eq!(
            PixelRuns::from_flat(&alternate.flat(), 9).unwrap(),
            alternate
        );
    }

    #[test]
    fn malformed_lists_are_refused_with_the_reason() {
        let cases: [(&[u32], MaskError); 6] = [
            (&[1, 2, 3], MaskError::Odd(3)),
            (&[0, 0], MaskError::Empty(0)),
            (
                &[4, 2, 1, 1],
                MaskError::Order {
                    index: 1,
                    start: 1,
                    previous_end: 6,
                },
            ),
            (
                // Adjacent runs are one run in the canonical form.
                &[0, 2, 2, 1],
                MaskError::Order {
                    index: 1,
                    start: 2,
                    previous_end: 2,
                },
            ),
            (
                &[6, 3],
                MaskError::OutOfTile {
                    index: 0,
                    end: 9,
                    pixels: 8,
                },
            ),
            (
                &[0, 1, 2, 1, 4, 1, 6, 1, 8, 1],
                MaskError::TooMany { runs: 5, pixels: 8 },
            ),
        ];
        for (values, want) in cases {
            let got = PixelRuns::from_flat(values, 8).unwrap_err();
            assert_eq!(got, want, "{values:?}");
            assert!(!got.to_string().is_empty());
        }
        // u32 overflow of start + len is caught as out of the tile, not wrapped.
        assert!(matches!(
            PixelRuns::from_flat(&[u32::MAX, u32::MAX], 8),
            Err(MaskError::OutOfTile { .. })
        ));
    }
}
