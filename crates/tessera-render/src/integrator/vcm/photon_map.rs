//! The photon map of a pass: its photons, the hash grid that finds those within the
//! merging radius, and the leak test that keeps a merge on the camera vertex's own surface
//! (the module documentation of [`super`], "Light leaks").

use super::{PathVertex, MERGE_LIFT, MERGE_NORMAL_COS};
use glam::Vec3;

/// A light vertex in the photon map: what merging needs, without the BSDF.
#[derive(Clone, Copy, Debug)]
pub(super) struct Photon {
    pub(super) p: Vec3,
    /// Unit direction toward the previous light vertex (where the light came from).
    pub(super) wo: Vec3,
    /// The geometric normal on the side the light arrived from.
    pub(super) n: Vec3,
    pub(super) beta: Vec3,
    pub(super) depth: u32,
    pub(super) d_vcm: f32,
    pub(super) d_vm: f32,
}

/// The leak test of one camera vertex's merges ([`super`]'s documentation, "Light
/// leaks"), its per-vertex parts computed once before the photon query.
pub(super) struct MergeGuard {
    /// The vertex's geometric normal on the camera's side.
    pub(super) n: Vec3,
    /// How far both ends of the shadow ray are lifted off the surface: [`MERGE_LIFT`]
    /// radii, at least four times the vertex position's rounding error.
    pub(super) eps: f32,
}

impl MergeGuard {
    pub(super) fn new(v: &PathVertex, r2: f32) -> Self {
        let n = v.facing_ng();
        let eps = (MERGE_LIFT * r2.sqrt()).max(4.0 * n.abs().dot(v.p_error));
        Self { n, eps }
    }

    /// The cheap half of the test, before the BSDF: the photon's normal within
    /// [`MERGE_NORMAL_COS`] of the vertex's, both on the side their light and the camera
    /// are.
    #[inline]
    pub(super) fn same_side(&self, ph: &Photon) -> bool {
        self.n.dot(ph.n) >= MERGE_NORMAL_COS
    }
}

/// A hash grid over the photons of a pass (Georgiev et al. 2012, section 6; SmallVCM's
/// `HashGrid`): cells of side `2 r`, hashed into as many buckets as there are photons, the
/// photon indices sorted by bucket in the order they were stored (a counting sort: no
/// dependence on anything but the photons' order). A query visits the 2 x 2 x 2 cells the
/// disc of radius `r` can touch, each bucket once.
#[derive(Default)]
pub(super) struct HashGrid {
    inv_cell: f32,
    pub(super) r2: f32,
    /// `starts[b]..starts[b + 1]`: the range of `indices` in bucket `b`.
    starts: Vec<u32>,
    indices: Vec<u32>,
}

impl HashGrid {
    fn bucket(&self, c: [i32; 3]) -> usize {
        let h = (c[0] as u32).wrapping_mul(73_856_093)
            ^ (c[1] as u32).wrapping_mul(19_349_663)
            ^ (c[2] as u32).wrapping_mul(83_492_791);
        h as usize % (self.starts.len() - 1)
    }

    fn cell(&self, p: Vec3) -> [i32; 3] {
        let q = (p * self.inv_cell).floor();
        [q.x as i32, q.y as i32, q.z as i32]
    }

    /// Rebuilds the grid over `photons` for radius `r`, reusing the buffers.
    pub(super) fn build(&mut self, photons: &[Photon], r: f32) {
        self.inv_cell = 1.0 / (2.0 * r);
        self.r2 = r * r;
        let buckets = photons.len().max(1);
        self.starts.clear();
        self.starts.resize(buckets + 1, 0);
        for ph in photons {
            let b = self.bucket(self.cell(ph.p));
            self.starts[b + 1] += 1;
        }
        for b in 0..buckets {
            self.starts[b + 1] += self.starts[b];
        }
        self.indices.clear();
        self.indices.resize(photons.len(), 0);
        // Fill each bucket in photon order: `starts[b]` is its next free slot meanwhile.
        for (i, ph) in photons.iter().enumerate() {
            let b = self.bucket(self.cell(ph.p));
            let at = self.starts[b] as usize;
            self.starts[b] += 1;
            self.indices[at] = i as u32;
        }
        // The fill advanced every start to its bucket's end: shift back by one bucket.
        for b in (1..=buckets).rev() {
            self.starts[b] = self.starts[b - 1];
        }
        self.starts[0] = 0;
    }

    /// Calls `f` on every photon within `r` of `p`, in a fixed order.
    pub(super) fn query(&self, photons: &[Photon], p: Vec3, mut f: impl FnMut(&Photon)) {
        if photons.is_empty() {
            return;
        }
        let q = p * self.inv_cell;
        let base = q.floor();
        let frac = q - base;
        let c = [base.x as i32, base.y as i32, base.z as i32];
        let o = [
            if frac.x < 0.5 { -1 } else { 1 },
            if frac.y < 0.5 { -1 } else { 1 },
            if frac.z < 0.5 { -1 } else { 1 },
        ];
        let mut seen = [usize::MAX; 8];
        let mut n_seen = 0;
        for k in 0..8u32 {
            let cell = [
                c[0].wrapping_add(if k & 1 != 0 { o[0] } else { 0 }),
                c[1].wrapping_add(if k & 2 != 0 { o[1] } else { 0 }),
                c[2].wrapping_add(if k & 4 != 0 { o[2] } else { 0 }),
            ];
            let b = self.bucket(cell);
            // Two cells hashed into one bucket: visit it once, or its photons count twice.
            if seen[..n_seen].contains(&b) {
                continue;
            }
            seen[n_seen] = b;
            n_seen += 1;
            for &i in &self.indices[self.starts[b] as usize..self.starts[b + 1] as usize] {
                let ph = &photons[i as usize];
                if (ph.p - p).length_squared() <= self.r2 {
                    f(ph);
                }
            }
        }
    }
}
