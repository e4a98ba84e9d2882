//! Directional albedo tables of the layers of [`super::gltf`], for albedo scaling (Kulla &
//! Conty 2017, "Revisiting Physically Based Shading at Imageworks", section on energy
//! compensation and layering).
//!
//! | table | meaning |
//! |---|---|
//! | [`ggx_albedo`] | `E(μ, α) = f0 A(μ, α) + f90 B(μ, α)`: the GGX reflection albedo with Schlick's Fresnel `f0 + (f90 - f0)(1 - wo·h)^5` (linear in `f0` and `f90`, so two tables serve every colour) |
//! | [`ggx_albedo_average`] | `E_avg(α) = 2 ∫ E(μ) μ dμ`, the cosine-weighted hemispherical average, as `(A_avg, B_avg)` |
//! | [`sheen_albedo`] | `E(μ, r)` of the Charlie sheen lobe of KHR_materials_sheen as published, sheen colour 1 |
//! | [`sheen_layer_albedo`] | `E'(μ, r)` of the sheen lobe Tessera renders (`sheen::Sheen::eval`, the published lobe divided by `max(1, E(μo), E(μi))`), sheen colour 1: what the sheen layer reflects, hence what it withholds from the base |
//! | [`anisotropic_ggx_albedo`] | `(A, B)` of [`ggx_albedo`] for the anisotropic GGX of KHR_materials_anisotropy, over `(μ, φ, r, t)`: `φ` the azimuth of `wo` from the anisotropy direction, `r` the perceptual roughness across it and `t = strength²` (`anisotropic_albedo.bin`), with its hemispherical average [`anisotropic_ggx_albedo_average`] |
//! | [`coat_loss`] | `D(μ, r_base, r_coat)`: what a white GGX base under a clearcoat loses to the coat's reciprocal `min` scaling (`coat_loss.bin`), with its average [`coat_loss_average`], for the compensation of [`super::gltf`] |
//! | [`coat_glass_loss`] | `G(μ, r, η, r_coat)`: of the power a white rough dielectric interface met from inside at `μ` sends out, the part a clearcoat (factor one) reflects back inside (`coat_glass_loss.bin`), with its average [`coat_glass_loss_average`], for the inside lobe of a coated rough glass in [`super::gltf`] |
//! | [`sheen_glass_loss`] | `(G_sh, H)(μ, r, η, r_sheen)`: [`coat_glass_loss`] with the sheen's layer albedo in place of the coat's, and the same times the largest coat albedo, bounding a coat and a sheen's overlap (`sheen_glass_loss.bin`), with their averages [`sheen_glass_loss_average`], for the inside lobe of a rough glass under a sheen in [`super::gltf`] |
//! | [`dielectric_albedo`] | `E(μ, α, η)`: the reflected plus transmitted power of the single-scattering rough dielectric, for `η` in `[1, 3]` and `1/η` (`dielectric_albedo.bin`), with its average [`dielectric_albedo_average`], for the multiple-scattering compensation of [`super::dielectric`] |
//!
//! The tables are computed by fixed quadrature and committed (`albedo_tables.bin`,
//! `dielectric_albedo.bin`, `anisotropic_albedo.bin`, `coat_loss.bin`,
//! `coat_glass_loss.bin` and `sheen_glass_loss.bin`, read
//! once per process): computing them at start-up took 0.6 s for the GGX tables and
//! 0.75 s for the sheen table at opt-level 3 on a busy two-core machine, paid by every
//! `tessera render`, worker and pilot process that met a glTF material (0.93 G of the
//! 3.8 G instructions of a small render of the Veach scene), and a committed table is
//! the same on every platform whatever its `sin` and `cos`. The test
//! `committed_tables_are_the_quadrature` (and `committed_dielectric_table_is_the_quadrature`)
//! recomputes them; `cargo test -p tessera-render
//! --lib write_albedo_tables -- --ignored` writes the file again after a change to the
//! quadrature or the node layout (both files); `write_coat_glass_table` writes
//! `coat_glass_loss.bin`, which integrates the GGX and dielectric tables (regenerate it
//! after them), and `write_sheen_glass_table` `sheen_glass_loss.bin` (after the sheen
//! table too). The dielectric table by the midpoint rule on
//! the visible-normal warp with both Fresnel branches of each microfacet
//! (`RoughDielectric::single_scattering_energy`), trilinear in `(sqrt(μ), r, sqrt(η - 1))`. The GGX
//! integrals by the midpoint rule on the square of the
//! visible-normal warp (`∫ F G2/G1 dD_wo`, Heitz 2018), the sheen integral by the midpoint
//! rule in `(sqrt(cos θi), φ)`. Lookups interpolate bilinearly in
//! `(sqrt(μ), r)` with `r = sqrt(α)` the perceptual roughness: the square root puts the
//! nodes close together at grazing angles, where shadowing and Fresnel change fastest. `E_avg` is integrated *from the
//! interpolated table*, piecewise exactly, so that `∫ (1 - E(μi)) 2 μi dμi = 1 - E_avg` holds
//! to rounding: the albedo-scaled Lambertian base then conserves energy exactly against the
//! table it is scaled by.

use super::microfacet::MIN_ALPHA;
use super::sheen;
#[cfg(test)]
use crate::sampling::warp::{ggx_g1, ggx_lambda, sample_ggx_vndf};
#[cfg(test)]
use glam::Vec2;
use glam::Vec3;
#[cfg(test)]
use rayon::prelude::*;
use std::sync::OnceLock;

mod glass_loss;
pub use glass_loss::{
    coat_glass_loss, coat_glass_loss_average, sheen_glass_loss, sheen_glass_loss_average,
};
#[cfg(test)]
pub(crate) use glass_loss::{coat_glass_loss_reference, sheen_glass_loss_reference};

/// Nodes along `sqrt(μ)`, `μ = cos θ` (uniform in [0, 1]).
const N_MU: usize = 64;
/// Nodes along the perceptual roughness `r` (uniform in [0, 1]).
const N_R: usize = 32;
/// Quadrature points per side of the unit square, per table entry.
#[cfg(test)]
const N_QUAD: usize = 48;
/// `μ` at which the grazing column is evaluated (the integrals are continuous there).
#[cfg(test)]
const MU_MIN: f32 = 1e-4;

/// A table over `(μ, r)` with bilinear lookup; the `r` nodes are uniform in
/// `[r_min, 1]`, `r_min` the smallest roughness the lobe uses (so that it is a node).
struct Table {
    v: [[f32; N_R]; N_MU],
    r_min: f32,
}

impl Table {
    /// Cell and fractional position of `x` in [0, 1] on `n` uniform nodes.
    #[inline]
    fn locate(x: f32, n: usize) -> (usize, f32) {
        let t = x.clamp(0.0, 1.0) * (n - 1) as f32;
        let i = (t as usize).min(n - 2);
        (i, t - i as f32)
    }

    #[inline]
    fn lookup(&self, mu: f32, r: f32) -> f32 {
        let (i, s) = Self::locate(mu.max(0.0).sqrt(), N_MU);
        let (j, t) = Self::locate(self.r_coordinate(r), N_R);
        self.interpolate(i, s, j, t)
    }

    /// The bilinear interpolation in cell `(i, j)` at fractions `(s, t)` (from
    /// [`Table::locate`]), so tables on the same grid share one location.
    #[inline]
    fn interpolate(&self, i: usize, s: f32, j: usize, t: f32) -> f32 {
        let a = self.v[i][j] + (self.v[i + 1][j] - self.v[i][j]) * s;
        let b = self.v[i][j + 1] + (self.v[i + 1][j + 1] - self.v[i][j + 1]) * s;
        a + (b - a) * t
    }

    /// The lookup coordinate in [0, 1] of the roughness `r`.
    #[inline]
    fn r_coordinate(&self, r: f32) -> f32 {
        (r - self.r_min) / (1.0 - self.r_min)
    }

    /// `2 ∫ E(μ) μ dμ` of column `j`, exactly for its interpolation.
    fn column_average(&self, j: usize) -> f32 {
        let column: [f32; N_MU] = std::array::from_fn(|i| self.v[i][j]);
        sqrt_mu_average(&column)
    }
}

/// `2 ∫ E(μ) μ dμ` of values `E` on nodes uniform in `x = sqrt(μ)` over [0, 1], exactly for
/// their linear interpolation in `x`: `2 μ dμ = 4 x³ dx` and `E` is linear on each cell.
fn sqrt_mu_average(column: &[f32]) -> f32 {
    let h = 1.0 / (column.len() - 1) as f64;
    let mut sum = 0.0f64;
    for (i, pair) in column.windows(2).enumerate() {
        let (a, b) = (pair[0] as f64, pair[1] as f64);
        let (x0, x1) = (i as f64 * h, (i + 1) as f64 * h);
        // ∫ 4x³ (a + (b - a)(x - x0)/h) dx over [x0, x1].
        let p4 = x1.powi(4) - x0.powi(4);
        let p5 = x1.powi(5) - x0.powi(5);
        sum += a * p4 + (b - a) / h * (0.8 * p5 - x0 * p4);
    }
    sum as f32
}

/// Node `i` of `n` uniform in [0, 1].
fn node(i: usize, n: usize) -> f32 {
    i as f32 / (n - 1) as f32
}

/// `μ` of node `i` (the nodes are uniform in `sqrt(μ)`).
#[cfg(test)]
fn mu_node(i: usize) -> f32 {
    node(i, N_MU).powi(2)
}

/// The roughness of node `j` of a table whose `r` nodes are uniform in `[r_min, 1]`.
#[cfg(test)]
fn r_node(r_min: f32, j: usize) -> f32 {
    r_min + (1.0 - r_min) * node(j, N_R)
}

/// `(A, B)` at one `(μ, α)` by the midpoint rule on the visible-normal warp.
#[cfg(test)]
fn ggx_albedo_quadrature(mu: f32, alpha: f32) -> (f32, f32) {
    let mu = mu.max(MU_MIN);
    let wo = Vec3::new((1.0 - mu * mu).max(0.0).sqrt(), 0.0, mu);
    let g1 = ggx_g1(wo, alpha);
    let (mut a, mut b) = (0.0f64, 0.0f64);
    for i in 0..N_QUAD {
        for j in 0..N_QUAD {
            let u = Vec2::new(
                (i as f32 + 0.5) / N_QUAD as f32,
                (j as f32 + 0.5) / N_QUAD as f32,
            );
            let h = sample_ggx_vndf(wo, alpha, u);
            let wi = crate::math::reflect(wo, h);
            if wi.z <= 0.0 {
                continue;
            }
            let g2 = 1.0 / (1.0 + ggx_lambda(wo, alpha) + ggx_lambda(wi, alpha));
            let w = (g2 / g1) as f64;
            let m = (1.0 - wo.dot(h).clamp(0.0, 1.0)).powi(5) as f64;
            a += w * (1.0 - m);
            b += w * m;
        }
    }
    let n = (N_QUAD * N_QUAD) as f64;
    ((a / n) as f32, (b / n) as f32)
}

/// `E` of the sheen lobe (colour 1) at one `(μ, r)`: `∫ f cos dω` by the midpoint rule
/// in `(t, φ)` with `μi = t²` (`dω = 2t dt dφ`), dense at the horizon, where the smooth
/// Charlie lobe puts its energy; `φ` over half the circle (the lobe is symmetric about the
/// plane of incidence).
#[cfg(test)]
fn sheen_albedo_quadrature(mu: f32, r: f32) -> f32 {
    sheen_quadrature(mu, r, sheen::Sheen::eval_raw)
}

/// `E'` of the rendered sheen lobe ([`sheen::Sheen::eval`], normalised by the committed
/// `E` table) at one `(μ, r)`, by the quadrature of [`sheen_albedo_quadrature`].
#[cfg(test)]
fn sheen_layer_albedo_quadrature(mu: f32, r: f32) -> f32 {
    sheen_quadrature(mu, r, sheen::Sheen::eval)
}

/// `∫ f cos dω` of the sheen lobe `eval` (colour 1) at one `(μ, r)`.
#[cfg(test)]
fn sheen_quadrature(mu: f32, r: f32, eval: fn(&sheen::Sheen, Vec3, Vec3) -> Vec3) -> f32 {
    const N_T: usize = 96;
    const N_PHI: usize = 48;
    let mu = mu.max(MU_MIN);
    let wo = Vec3::new((1.0 - mu * mu).max(0.0).sqrt(), 0.0, mu);
    let lobe = sheen::Sheen::new(Vec3::ONE, r);
    let mut sum = 0.0f64;
    for i in 0..N_T {
        let t = (i as f32 + 0.5) / N_T as f32;
        let mu_i = t * t;
        let sin_i = (1.0 - mu_i * mu_i).max(0.0).sqrt();
        for j in 0..N_PHI {
            let phi = std::f32::consts::PI * (j as f32 + 0.5) / N_PHI as f32;
            let wi = Vec3::new(sin_i * phi.cos(), sin_i * phi.sin(), mu_i);
            sum += (eval(&lobe, wo, wi).x * 2.0 * t) as f64;
        }
    }
    // dt dφ = (1 / N_T)(π / N_PHI), times 2 for the other half of the circle.
    (sum * 2.0 * std::f64::consts::PI / (N_T * N_PHI) as f64) as f32
}

struct GgxTables {
    a: Table,
    b: Table,
    a_avg: [f32; N_R],
    b_avg: [f32; N_R],
}

/// The committed tables: `A`, `B`, the sheen `E` and the rendered sheen's `E'`, each
/// `N_MU` rows of `N_R` values, little-endian binary32 (written by `write_albedo_tables`).
static COMMITTED: &[u8; N_TABLES * TABLE_BYTES] = include_bytes!("albedo_tables.bin");

/// Tables in `albedo_tables.bin`.
const N_TABLES: usize = 4;

/// Bytes of one table in `albedo_tables.bin`.
const TABLE_BYTES: usize = 4 * N_MU * N_R;

/// The values of a table, row by row.
type Values = [[f32; N_R]; N_MU];

/// Table `k` (0: A, 1: B, 2: sheen `E`, 3: sheen `E'`) of the committed file.
fn committed(k: usize) -> Values {
    let bytes = &COMMITTED[k * TABLE_BYTES..(k + 1) * TABLE_BYTES];
    let mut v = [[0.0; N_R]; N_MU];
    for (x, b) in v.as_flattened_mut().iter_mut().zip(bytes.chunks_exact(4)) {
        *x = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
    }
    v
}

/// The GGX tables `(A, B)` by quadrature, rows in parallel (the order of the results is
/// fixed, so the tables are the same on any number of threads).
#[cfg(test)]
fn ggx_quadrature_tables() -> (Values, Values) {
    let r_min = MIN_ALPHA.sqrt();
    let rows: Vec<[(f32, f32); N_R]> = (0..N_MU)
        .into_par_iter()
        .map(|i| {
            std::array::from_fn(|j| {
                let r = r_node(r_min, j);
                ggx_albedo_quadrature(mu_node(i), (r * r).max(MIN_ALPHA))
            })
        })
        .collect();
    let (mut a, mut b) = ([[0.0; N_R]; N_MU], [[0.0; N_R]; N_MU]);
    for (i, row) in rows.iter().enumerate() {
        for (j, &(ea, eb)) in row.iter().enumerate() {
            a[i][j] = ea;
            b[i][j] = eb;
        }
    }
    (a, b)
}

/// The sheen table of `albedo` (a quadrature at one `(μ, r)`), rows in parallel.
#[cfg(test)]
fn sheen_quadrature_table(albedo: fn(f32, f32) -> f32) -> Values {
    let r_min = sheen::MIN_SHEEN_ROUGHNESS;
    let rows: Vec<[f32; N_R]> = (0..N_MU)
        .into_par_iter()
        .map(|i| std::array::from_fn(|j| albedo(mu_node(i), r_node(r_min, j))))
        .collect();
    let mut v = [[0.0; N_R]; N_MU];
    for (i, row) in rows.into_iter().enumerate() {
        v[i] = row;
    }
    v
}

fn ggx_tables() -> &'static GgxTables {
    static TABLES: OnceLock<GgxTables> = OnceLock::new();
    TABLES.get_or_init(|| {
        let r_min = MIN_ALPHA.sqrt();
        let a = Table {
            v: committed(0),
            r_min,
        };
        let b = Table {
            v: committed(1),
            r_min,
        };
        let a_avg = std::array::from_fn(|j| a.column_average(j));
        let b_avg = std::array::from_fn(|j| b.column_average(j));
        GgxTables { a, b, a_avg, b_avg }
    })
}

fn sheen_table() -> &'static Table {
    static TABLE: OnceLock<Table> = OnceLock::new();
    TABLE.get_or_init(|| Table {
        v: committed(2),
        r_min: sheen::MIN_SHEEN_ROUGHNESS,
    })
}

fn sheen_layer_table() -> &'static Table {
    static TABLE: OnceLock<Table> = OnceLock::new();
    TABLE.get_or_init(|| Table {
        v: committed(3),
        r_min: sheen::MIN_SHEEN_ROUGHNESS,
    })
}

/// `(A, B)` with `E = f0 A + f90 B` the albedo of GGX reflection with Schlick's Fresnel at
/// `μ = cos θo` and GGX `alpha`.
#[inline]
pub fn ggx_albedo(mu: f32, alpha: f32) -> (f32, f32) {
    let t = ggx_tables();
    let r = alpha.max(0.0).sqrt();
    // A and B share their grid (and `r_min`): locate once.
    let (i, s) = Table::locate(mu.max(0.0).sqrt(), N_MU);
    let (j, u) = Table::locate(t.a.r_coordinate(r), N_R);
    (t.a.interpolate(i, s, j, u), t.b.interpolate(i, s, j, u))
}

/// `(A_avg, B_avg)`: the cosine-weighted averages `2 ∫ A(μ) μ dμ` and `2 ∫ B(μ) μ dμ` of
/// the interpolated [`ggx_albedo`] at `alpha`.
#[inline]
pub fn ggx_albedo_average(alpha: f32) -> (f32, f32) {
    let t = ggx_tables();
    let (j, s) = Table::locate(t.a.r_coordinate(alpha.max(0.0).sqrt()), N_R);
    let lerp = |v: &[f32; N_R]| v[j] + (v[j + 1] - v[j]) * s;
    (lerp(&t.a_avg), lerp(&t.b_avg))
}

/// The albedo of the published (unnormalised) sheen lobe of colour 1 and perceptual
/// roughness `r` at `μ = cos θo`; it exceeds one at grazing angles for smooth sheens.
#[inline]
pub fn sheen_albedo(mu: f32, r: f32) -> f32 {
    sheen_table().lookup(mu, r)
}

/// The albedo of the sheen lobe as rendered (`sheen::Sheen::eval`, colour 1,
/// perceptual roughness `r`) at `μ = cos θo`, at most one. Below [`sheen_albedo`] wherever
/// the normalisation acts (smooth sheens, toward grazing `μo` or `μi`): the layering must
/// scale the base by what this lobe withholds, not by what the published one would (at
/// roughness 0.1 that lost 7% of a white furnace).
#[inline]
pub fn sheen_layer_albedo(mu: f32, r: f32) -> f32 {
    sheen_layer_table().lookup(mu, r)
}

// ---------------------------------------------------------------------------------------
// Rough dielectric energy tables
// ---------------------------------------------------------------------------------------

/// Nodes of the rough dielectric table along `sqrt(μ)`.
const D_MU: usize = 32;
/// Nodes along the perceptual roughness, uniform in `[sqrt(MIN_ALPHA), 1]`.
const D_R: usize = 16;
/// Nodes along the relative index, uniform in `sqrt((η - 1) / (DIELECTRIC_ETA_MAX - 1))`:
/// close together near one, where the leaving side's total internal reflection sets in
/// and its albedo changes fastest.
const D_ETA: usize = 16;
/// Largest relative index the dielectric table covers (diamond is 2.42); larger ones are
/// looked up at this one (their compensation is then approximate).
pub const DIELECTRIC_ETA_MAX: f32 = 3.0;
/// Entries of one side (`η >= 1`, entering; `η < 1`, leaving) of the dielectric table.
const D_SIDE: usize = D_ETA * D_MU * D_R;
/// Quadrature points per side of the unit square, per dielectric table entry.
#[cfg(test)]
const D_QUAD: usize = 32;

/// The committed rough dielectric table: `E(μ, r, η)` for the relative index `η` then
/// `1/η` (two sides of `D_ETA × D_MU × D_R` values, `η` slowest, `r` fastest),
/// little-endian binary32 (written by `write_albedo_tables`).
static COMMITTED_DIELECTRIC: &[u8; 8 * D_SIDE] = include_bytes!("dielectric_albedo.bin");

/// The rough dielectric table with its cosine-weighted averages per `(side, η, r)`.
struct DielectricTable {
    v: Vec<f32>,
    avg: Vec<f32>,
}

#[inline]
fn d_index(side: usize, k: usize, i: usize, j: usize) -> usize {
    ((side * D_ETA + k) * D_MU + i) * D_R + j
}

/// `(side, η_table)` of a relative index seen from the outgoing direction: entering
/// (`η >= 1`) is side 0, leaving is side 1 at `1/η`.
#[inline]
fn d_side(eta: f32) -> (usize, f32) {
    if eta >= 1.0 {
        (0, eta)
    } else {
        (1, 1.0 / eta)
    }
}

/// The roughness of the dielectric table's node `j`.
#[cfg(test)]
fn d_r_node(j: usize) -> f32 {
    r_node_of(j, D_R)
}

/// The relative index of the dielectric table's node `k` (before the side's inversion).
#[cfg(test)]
fn d_eta_node(k: usize) -> f32 {
    eta_node_of(k, D_ETA)
}

/// The relative index of node `k` of `n` uniform in `sqrt((η - 1) / (DIELECTRIC_ETA_MAX - 1))`.
fn eta_node_of(k: usize, n: usize) -> f32 {
    1.0 + (DIELECTRIC_ETA_MAX - 1.0) * node(k, n).powi(2)
}

/// The energy albedo of the single-scattering rough dielectric at one `(μ, α, η)` by the
/// midpoint rule on the visible-normal warp, with both branches of every microfacet taken
/// at their Fresnel weights (what `RoughDielectric::sample` returns on average).
#[cfg(test)]
fn dielectric_albedo_quadrature(mu: f32, alpha: f32, eta: f32) -> f32 {
    let mu = mu.max(MU_MIN);
    let wo = Vec3::new((1.0 - mu * mu).max(0.0).sqrt(), 0.0, mu);
    let lobe = super::dielectric::RoughDielectric {
        eta,
        alpha,
        tint: Vec3::ONE,
    };
    let mut sum = 0.0f64;
    for i in 0..D_QUAD {
        for j in 0..D_QUAD {
            let u = Vec2::new(
                (i as f32 + 0.5) / D_QUAD as f32,
                (j as f32 + 0.5) / D_QUAD as f32,
            );
            sum += lobe.single_scattering_energy(wo, u) as f64;
        }
    }
    (sum / (D_QUAD * D_QUAD) as f64) as f32
}

/// The dielectric table by quadrature, in the committed file's order, rows in parallel.
#[cfg(test)]
fn dielectric_quadrature_table() -> Vec<f32> {
    (0..2 * D_ETA * D_MU)
        .into_par_iter()
        .flat_map_iter(|row| {
            let (side, k, i) = (row / (D_ETA * D_MU), (row / D_MU) % D_ETA, row % D_MU);
            let eta = d_eta_node(k);
            let eta = if side == 0 { eta } else { 1.0 / eta };
            (0..D_R).map(move |j| {
                let r = d_r_node(j);
                dielectric_albedo_quadrature(mu_node_of(i, D_MU), (r * r).max(MIN_ALPHA), eta)
            })
        })
        .collect()
}

/// `μ` of node `i` of `n` uniform in `sqrt(μ)`.
#[cfg(test)]
fn mu_node_of(i: usize, n: usize) -> f32 {
    node(i, n).powi(2)
}

fn dielectric_table() -> &'static DielectricTable {
    static TABLE: OnceLock<DielectricTable> = OnceLock::new();
    TABLE.get_or_init(|| {
        let v: Vec<f32> = COMMITTED_DIELECTRIC
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        let mut avg = Vec::with_capacity(2 * D_ETA * D_R);
        for side in 0..2 {
            for k in 0..D_ETA {
                for j in 0..D_R {
                    let column: [f32; D_MU] = std::array::from_fn(|i| v[d_index(side, k, i, j)]);
                    avg.push(sqrt_mu_average(&column));
                }
            }
        }
        DielectricTable { v, avg }
    })
}

/// Cells and fractions of `(α, η)` in the dielectric table.
#[inline]
fn d_locate(alpha: f32, eta_table: f32) -> ((usize, f32), (usize, f32)) {
    let r_min = MIN_ALPHA.sqrt();
    let r = alpha.max(0.0).sqrt();
    let rj = Table::locate((r - r_min) / (1.0 - r_min), D_R);
    let t = ((eta_table - 1.0) / (DIELECTRIC_ETA_MAX - 1.0))
        .max(0.0)
        .sqrt();
    let ek = Table::locate(t, D_ETA);
    (rj, ek)
}

/// The energy albedo `E(μ)` of the single-scattering rough dielectric
/// ([`super::dielectric::RoughDielectric`] without its compensation) with GGX `alpha` and
/// relative index `eta` seen from the outgoing direction at `μ = |cos θo|`: the reflected
/// plus the transmitted power, `∫ f_r cos + η² ∫ f_t cos` (the radiance BTDF's `1/η²`
/// undone). Trilinear in `(sqrt(μ), sqrt(α), sqrt(η - 1))`.
#[inline]
pub fn dielectric_albedo(mu: f32, alpha: f32, eta: f32) -> f32 {
    let t = dielectric_table();
    let (side, eta_t) = d_side(eta);
    let (i, s) = Table::locate(mu.max(0.0).sqrt(), D_MU);
    let ((j, u), (k, w)) = d_locate(alpha, eta_t);
    let bilinear = |k: usize| {
        let at = |i, j| t.v[d_index(side, k, i, j)];
        let a = at(i, j) + (at(i + 1, j) - at(i, j)) * s;
        let b = at(i, j + 1) + (at(i + 1, j + 1) - at(i, j + 1)) * s;
        a + (b - a) * u
    };
    let (lo, hi) = (bilinear(k), bilinear(k + 1));
    lo + (hi - lo) * w
}

/// `E_avg = 2 ∫ E(μ) μ dμ` of the interpolated [`dielectric_albedo`] (exactly: the
/// average is linear, so it is the bilinear interpolation of the nodes' averages).
#[inline]
pub fn dielectric_albedo_average(alpha: f32, eta: f32) -> f32 {
    let t = dielectric_table();
    let (side, eta_t) = d_side(eta);
    let ((j, u), (k, w)) = d_locate(alpha, eta_t);
    let at = |k: usize, j: usize| t.avg[(side * D_ETA + k) * D_R + j];
    let lo = at(k, j) + (at(k, j + 1) - at(k, j)) * u;
    let hi = at(k + 1, j) + (at(k + 1, j + 1) - at(k + 1, j)) * u;
    lo + (hi - lo) * w
}

// ---------------------------------------------------------------------------------------
// Anisotropic GGX tables (KHR_materials_anisotropy)
// ---------------------------------------------------------------------------------------

/// Nodes of the anisotropic GGX tables along `sqrt(μ)`.
const A_MU: usize = 24;
/// Nodes along the azimuth of `wo` from the anisotropy direction, uniform in `[0, π/2]`
/// (the albedo is even in `φ` and in `π - φ`).
const A_PHI: usize = 9;
/// Nodes along the perceptual roughness `r` of the bitangent direction, uniform in
/// `[sqrt(MIN_ALPHA), 1]`.
const A_R: usize = 12;
/// Nodes along `t = strength²`, uniform in `[0, 1]`: the tangent's alpha is
/// `α_t = α + (1 - α) t` (the extension's `mix(α, 1, strength²)`).
const A_T: usize = 8;
/// Entries of one anisotropic table.
const A_SIZE: usize = A_T * A_R * A_PHI * A_MU;
/// Quadrature points per side of the unit square, per anisotropic table entry.
#[cfg(test)]
const A_QUAD: usize = 32;

/// The committed anisotropic GGX tables `A` then `B` (as [`ggx_albedo`]'s, for the
/// anisotropic distribution), each `A_T × A_R × A_PHI × A_MU` values, `t` slowest and `μ`
/// fastest, little-endian binary32 (written by `write_albedo_tables`).
static COMMITTED_ANISOTROPIC: &[u8; 8 * A_SIZE] = include_bytes!("anisotropic_albedo.bin");

/// The anisotropic tables with their cosine-weighted hemispherical averages per `(t, r)`.
struct AnisotropicTables {
    a: Vec<f32>,
    b: Vec<f32>,
    /// `(A_avg, B_avg)` per `(t, r)`, `t` slowest.
    avg: Vec<(f32, f32)>,
}

#[inline]
fn a_index(k: usize, j: usize, p: usize, i: usize) -> usize {
    ((k * A_R + j) * A_PHI + p) * A_MU + i
}

/// The anisotropic GGX of table coordinates `(α, t)`: `(α_t, α_b)`.
#[inline]
pub fn anisotropic_alphas(alpha: f32, t: f32) -> (f32, f32) {
    (alpha + (1.0 - alpha) * t, alpha)
}

/// `(A, B)` at one `(μ, φ, α, t)` by the midpoint rule on the anisotropic visible-normal
/// warp (as [`ggx_albedo_quadrature`]).
#[cfg(test)]
fn anisotropic_albedo_quadrature(mu: f32, phi: f32, alpha: f32, t: f32) -> (f32, f32) {
    let mu = mu.max(MU_MIN);
    let s = (1.0 - mu * mu).max(0.0).sqrt();
    let wo = Vec3::new(s * phi.cos(), s * phi.sin(), mu);
    let (ax, ay) = anisotropic_alphas(alpha, t);
    let ggx = super::microfacet::AnisoGgx { ax, ay };
    let g1 = 1.0 / (1.0 + ggx.lambda(wo));
    let (mut a, mut b) = (0.0f64, 0.0f64);
    for i in 0..A_QUAD {
        for j in 0..A_QUAD {
            let u = Vec2::new(
                (i as f32 + 0.5) / A_QUAD as f32,
                (j as f32 + 0.5) / A_QUAD as f32,
            );
            let h = ggx.sample_vndf(wo, u);
            let wi = crate::math::reflect(wo, h);
            if wi.z <= 0.0 {
                continue;
            }
            let w = (ggx.g2(wo, wi) / g1) as f64;
            let m = (1.0 - wo.dot(h).clamp(0.0, 1.0)).powi(5) as f64;
            a += w * (1.0 - m);
            b += w * m;
        }
    }
    let n = (A_QUAD * A_QUAD) as f64;
    ((a / n) as f32, (b / n) as f32)
}

/// The azimuth of node `p`.
#[cfg(test)]
fn a_phi_node(p: usize) -> f32 {
    std::f32::consts::FRAC_PI_2 * node(p, A_PHI)
}

/// The anisotropic tables `(A, B)` by quadrature, in the committed file's order.
#[cfg(test)]
fn anisotropic_quadrature_tables() -> (Vec<f32>, Vec<f32>) {
    let r_min = MIN_ALPHA.sqrt();
    let entries: Vec<(f32, f32)> = (0..A_T * A_R * A_PHI)
        .into_par_iter()
        .flat_map_iter(|row| {
            let (k, j, p) = (row / (A_R * A_PHI), (row / A_PHI) % A_R, row % A_PHI);
            let r = r_min + (1.0 - r_min) * node(j, A_R);
            let alpha = (r * r).max(MIN_ALPHA);
            (0..A_MU).map(move |i| {
                anisotropic_albedo_quadrature(
                    mu_node_of(i, A_MU),
                    a_phi_node(p),
                    alpha,
                    node(k, A_T),
                )
            })
        })
        .collect();
    entries.into_iter().unzip()
}

fn anisotropic_tables() -> &'static AnisotropicTables {
    static TABLES: OnceLock<AnisotropicTables> = OnceLock::new();
    TABLES.get_or_init(|| {
        let read = |bytes: &[u8]| -> Vec<f32> {
            bytes
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect()
        };
        let a = read(&COMMITTED_ANISOTROPIC[..4 * A_SIZE]);
        let b = read(&COMMITTED_ANISOTROPIC[4 * A_SIZE..]);
        // The average over the hemisphere of the interpolated table: exact in `μ` per
        // azimuth node (`sqrt_mu_average`), then the trapezoid rule in `φ`, exact for the
        // linear interpolation between the azimuth nodes.
        let average = |v: &[f32], k: usize, j: usize| {
            let mut sum = 0.0;
            for p in 0..A_PHI {
                let column: [f32; A_MU] = std::array::from_fn(|i| v[a_index(k, j, p, i)]);
                let w = if p == 0 || p == A_PHI - 1 { 0.5 } else { 1.0 };
                sum += w * sqrt_mu_average(&column);
            }
            sum / (A_PHI - 1) as f32
        };
        let mut avg = Vec::with_capacity(A_T * A_R);
        for k in 0..A_T {
            for j in 0..A_R {
                avg.push((average(&a, k, j), average(&b, k, j)));
            }
        }
        AnisotropicTables { a, b, avg }
    })
}

/// Cells and fractions of `(α, t)` in the anisotropic tables.
#[inline]
fn a_locate(alpha: f32, t: f32) -> ((usize, f32), (usize, f32)) {
    let r_min = MIN_ALPHA.sqrt();
    let r = alpha.max(0.0).sqrt();
    (
        Table::locate((r - r_min) / (1.0 - r_min), A_R),
        Table::locate(t, A_T),
    )
}

/// `(A, B)` with `E = f0 A + f90 B` the albedo of anisotropic GGX reflection (Schlick's
/// Fresnel) seen from `w`, given in the frame whose `+x` is the anisotropy direction:
/// `α_t = α + (1 - α) t` along `+x`, `α` along `+y` ([`anisotropic_alphas`]).
/// Quadrilinear in `(sqrt(μ), φ, r, t)`, `φ` the azimuth folded into `[0, π/2]`.
#[inline]
pub fn anisotropic_ggx_albedo(w: Vec3, alpha: f32, t: f32) -> (f32, f32) {
    let tables = anisotropic_tables();
    let (i, s) = Table::locate(w.z.abs().sqrt(), A_MU);
    let phi = w.y.abs().atan2(w.x.abs());
    let (p, v) = Table::locate(phi * std::f32::consts::FRAC_2_PI, A_PHI);
    let ((j, u), (k, x)) = a_locate(alpha, t);
    let interpolate = |tab: &[f32]| {
        let mut out = 0.0;
        for (dk, wk) in [(0, 1.0 - x), (1, x)] {
            for (dj, wj) in [(0, 1.0 - u), (1, u)] {
                for (dp, wp) in [(0, 1.0 - v), (1, v)] {
                    let lo = tab[a_index(k + dk, j + dj, p + dp, i)];
                    let hi = tab[a_index(k + dk, j + dj, p + dp, i + 1)];
                    out += wk * wj * wp * (lo + (hi - lo) * s);
                }
            }
        }
        out
    };
    (interpolate(&tables.a), interpolate(&tables.b))
}

/// `(A_avg, B_avg)`: the cosine-weighted hemispherical averages (over `μ` and the azimuth)
/// of the interpolated [`anisotropic_ggx_albedo`] at `(α, t)`.
#[inline]
pub fn anisotropic_ggx_albedo_average(alpha: f32, t: f32) -> (f32, f32) {
    let tables = anisotropic_tables();
    let ((j, u), (k, x)) = a_locate(alpha, t);
    let at = |k: usize, j: usize| tables.avg[k * A_R + j];
    let lerp =
        |a: (f32, f32), b: (f32, f32), f: f32| (a.0 + (b.0 - a.0) * f, a.1 + (b.1 - a.1) * f);
    let lo = lerp(at(k, j), at(k, j + 1), u);
    let hi = lerp(at(k + 1, j), at(k + 1, j + 1), u);
    lerp(lo, hi, x)
}

/// `(A, B)` of [`anisotropic_ggx_albedo`] at `μ` averaged over the azimuth (the trapezoid
/// rule on the azimuth nodes, exact for the interpolation).
pub fn anisotropic_ggx_albedo_azimuthal(mu: f32, alpha: f32, t: f32) -> (f32, f32) {
    let (mut a, mut b) = (0.0, 0.0);
    let s = (1.0 - mu * mu).max(0.0).sqrt();
    for p in 0..A_PHI {
        let phi = std::f32::consts::FRAC_PI_2 * p as f32 / (A_PHI - 1) as f32;
        let (ea, eb) =
            anisotropic_ggx_albedo(Vec3::new(s * phi.cos(), s * phi.sin(), mu), alpha, t);
        let w = if p == 0 || p == A_PHI - 1 { 0.5 } else { 1.0 };
        a += w * ea;
        b += w * eb;
    }
    let n = (A_PHI - 1) as f32;
    (a / n, b / n)
}

#[cfg(test)]
pub(crate) fn anisotropic_albedo_reference(w: Vec3, alpha: f32, t: f32) -> (f32, f32) {
    let phi = w.y.abs().atan2(w.x.abs());
    anisotropic_albedo_quadrature(w.z.abs(), phi, alpha, t)
}

// ---------------------------------------------------------------------------------------
// A rough base under a clearcoat
// ---------------------------------------------------------------------------------------

/// Clearcoat's Fresnel reflectance at normal incidence (ior 1.5), `f0` of its albedo
/// `E_cc = COAT_F0 A + B`.
pub const COAT_F0: f32 = 0.04;

/// Nodes of the coat-loss table along `sqrt(μ)`.
const C_MU: usize = 32;
/// Nodes along the base's and the coat's perceptual roughness, each uniform in
/// `[sqrt(MIN_ALPHA), 1]`.
const C_R: usize = 16;
/// Entries of the coat-loss table.
const C_SIZE: usize = C_R * C_R * C_MU;
/// Quadrature points per side of the unit square, per coat-loss entry.
#[cfg(test)]
const C_QUAD: usize = 32;

/// The committed coat-loss table `D(μ, r_base, r_coat)`, `r_coat` slowest and `μ`
/// fastest, little-endian binary32 (written by `write_coat_loss_table`).
static COMMITTED_COAT_LOSS: &[u8; 4 * C_SIZE] = include_bytes!("coat_loss.bin");

/// The coat-loss table with its cosine-weighted averages per `(r_coat, r_base)`.
struct CoatLossTable {
    v: Vec<f32>,
    avg: Vec<f32>,
}

#[inline]
fn c_index(k: usize, j: usize, i: usize) -> usize {
    (k * C_R + j) * C_MU + i
}

/// The clearcoat's albedo `E_cc(μ) = COAT_F0 A + B` at GGX `alpha_cc`.
#[inline]
pub fn coat_albedo(mu: f32, alpha_cc: f32) -> f32 {
    let (a, b) = ggx_albedo(mu, alpha_cc);
    COAT_F0 * a + b
}

/// `D(μ)` at one `(μ, α_base, α_coat)` by the midpoint rule on the base's visible-normal
/// warp (white, `F = 1`).
#[cfg(test)]
fn coat_loss_quadrature(mu: f32, alpha: f32, alpha_cc: f32) -> f32 {
    let mu = mu.max(MU_MIN);
    let wo = Vec3::new((1.0 - mu * mu).max(0.0).sqrt(), 0.0, mu);
    let g1 = ggx_g1(wo, alpha);
    let e_o = coat_albedo(mu, alpha_cc);
    let mut sum = 0.0f64;
    for i in 0..C_QUAD {
        for j in 0..C_QUAD {
            let u = Vec2::new(
                (i as f32 + 0.5) / C_QUAD as f32,
                (j as f32 + 0.5) / C_QUAD as f32,
            );
            let h = sample_ggx_vndf(wo, alpha, u);
            let wi = crate::math::reflect(wo, h);
            if wi.z <= 0.0 {
                continue;
            }
            let g2 = 1.0 / (1.0 + ggx_lambda(wo, alpha) + ggx_lambda(wi, alpha));
            let gap = (coat_albedo(wi.z, alpha_cc) - e_o).max(0.0);
            sum += (g2 / g1 * gap) as f64;
        }
    }
    (sum / (C_QUAD * C_QUAD) as f64) as f32
}

/// The coat-loss table by quadrature, in the committed file's order.
#[cfg(test)]
fn coat_loss_quadrature_table() -> Vec<f32> {
    let r_min = MIN_ALPHA.sqrt();
    let r = move |j: usize| r_min + (1.0 - r_min) * node(j, C_R);
    (0..C_R * C_R)
        .into_par_iter()
        .flat_map_iter(|row| {
            let (k, j) = (row / C_R, row % C_R);
            let (alpha, alpha_cc) = ((r(j) * r(j)).max(MIN_ALPHA), (r(k) * r(k)).max(MIN_ALPHA));
            (0..C_MU).map(move |i| coat_loss_quadrature(mu_node_of(i, C_MU), alpha, alpha_cc))
        })
        .collect()
}

fn coat_loss_table() -> &'static CoatLossTable {
    static TABLE: OnceLock<CoatLossTable> = OnceLock::new();
    TABLE.get_or_init(|| {
        let v: Vec<f32> = COMMITTED_COAT_LOSS
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        let mut avg = Vec::with_capacity(C_R * C_R);
        for k in 0..C_R {
            for j in 0..C_R {
                let column: [f32; C_MU] = std::array::from_fn(|i| v[c_index(k, j, i)]);
                avg.push(sqrt_mu_average(&column));
            }
        }
        CoatLossTable { v, avg }
    })
}

/// Cells and fractions of `(α_base, α_coat)` in the coat-loss table.
#[inline]
fn c_locate(alpha: f32, alpha_cc: f32) -> ((usize, f32), (usize, f32)) {
    let r_min = MIN_ALPHA.sqrt();
    let at = |a: f32| Table::locate((a.max(0.0).sqrt() - r_min) / (1.0 - r_min), C_R);
    (at(alpha), at(alpha_cc))
}

/// `D(μ) = ∫ max(0, E_cc(μi) - E_cc(μ)) f(wo, wi) cos θi dωi`: what a white GGX base of
/// `alpha` under a clearcoat of `alpha_cc` (factor one) loses at `μ = cos θo` when the
/// coat scales it by the reciprocal `min(1 - E_cc(μo), 1 - E_cc(μi))` rather than by
/// `1 - E_cc(μo)` (the gap is linear in the clearcoat factor). Trilinear in
/// `(sqrt(μ), r_base, r_coat)`.
#[inline]
pub fn coat_loss(mu: f32, alpha: f32, alpha_cc: f32) -> f32 {
    let t = coat_loss_table();
    let (i, s) = Table::locate(mu.max(0.0).sqrt(), C_MU);
    let ((j, u), (k, w)) = c_locate(alpha, alpha_cc);
    let bilinear = |k: usize| {
        let at = |j: usize, i: usize| t.v[c_index(k, j, i)];
        let a = at(j, i) + (at(j, i + 1) - at(j, i)) * s;
        let b = at(j + 1, i) + (at(j + 1, i + 1) - at(j + 1, i)) * s;
        a + (b - a) * u
    };
    let (lo, hi) = (bilinear(k), bilinear(k + 1));
    lo + (hi - lo) * w
}

/// `2 ∫ D(μ) μ dμ` of the interpolated [`coat_loss`].
#[inline]
pub fn coat_loss_average(alpha: f32, alpha_cc: f32) -> f32 {
    let t = coat_loss_table();
    let ((j, u), (k, w)) = c_locate(alpha, alpha_cc);
    let at = |k: usize, j: usize| t.avg[k * C_R + j];
    let lo = at(k, j) + (at(k, j + 1) - at(k, j)) * u;
    let hi = at(k + 1, j) + (at(k + 1, j + 1) - at(k + 1, j)) * u;
    lo + (hi - lo) * w
}

/// The perceptual roughness of node `j` of `n` uniform in `[sqrt(MIN_ALPHA), 1]`.
#[cfg(test)]
fn r_node_of(j: usize, n: usize) -> f32 {
    let r_min = MIN_ALPHA.sqrt();
    r_min + (1.0 - r_min) * node(j, n)
}

#[cfg(test)]
pub(crate) fn coat_loss_reference(mu: f32, alpha: f32, alpha_cc: f32) -> f32 {
    coat_loss_quadrature(mu, alpha, alpha_cc)
}

#[cfg(test)]
pub(crate) fn dielectric_albedo_reference(mu: f32, alpha: f32, eta: f32) -> f32 {
    dielectric_albedo_quadrature(mu, alpha, eta)
}

#[cfg(test)]
pub(crate) fn ggx_albedo_reference(mu: f32, alpha: f32) -> (f32, f32) {
    ggx_albedo_quadrature(mu, alpha)
}

#[cfg(test)]
pub(crate) fn sheen_albedo_reference(mu: f32, r: f32) -> f32 {
    sheen_albedo_quadrature(mu, r)
}

#[cfg(test)]
pub(crate) fn sheen_layer_albedo_reference(mu: f32, r: f32) -> f32 {
    sheen_layer_albedo_quadrature(mu, r)
}

#[cfg(test)]
mod committed_tests {
    use super::*;

    /// The tables by quadrature, in the committed file's order (`E'` is normalised by the
    /// committed `E`, as the renderer's sheen lobe is).
    fn computed() -> [Values; N_TABLES] {
        let (a, b) = ggx_quadrature_tables();
        [
            a,
            b,
            sheen_quadrature_table(sheen_albedo_quadrature),
            sheen_quadrature_table(sheen_layer_albedo_quadrature),
        ]
    }

    /// The committed rough dielectric table is what the quadrature gives, within rounding.
    #[test]
    fn committed_dielectric_table_is_the_quadrature() {
        let table = dielectric_quadrature_table();
        let stored = &dielectric_table().v;
        assert_eq!(table.len(), stored.len());
        for (n, (c, s)) in table.iter().zip(stored).enumerate() {
            assert!(
                (c - s).abs() <= 1e-5,
                "dielectric entry {n}: quadrature {c}, committed {s}; regenerate with \
                 `cargo test -p tessera-render --lib write_anisotropic_table -- --ignored`"
            );
        }
    }

    /// The committed tables are what the quadrature gives, within rounding: the same bits
    /// on the machine that wrote them, and within 1e-5 wherever `sin`, `cos` and `sqrt`
    /// round differently (they are albedos, of order one).
    #[test]
    fn committed_tables_are_the_quadrature() {
        for (k, table) in computed().iter().enumerate() {
            let stored = committed(k);
            for i in 0..N_MU {
                for j in 0..N_R {
                    let (c, s) = (table[i][j], stored[i][j]);
                    assert!(
                        (c - s).abs() <= 1e-5,
                        "table {k} node ({i}, {j}): quadrature {c}, committed {s}; \
                         regenerate with `cargo test -p tessera-render --lib \
                         write_albedo_tables -- --ignored`"
                    );
                }
            }
        }
    }

    /// Writes `albedo_tables.bin` and `dielectric_albedo.bin` from the quadrature (run by
    /// hand, see the module docs).
    #[test]
    #[ignore = "writes src/bsdf/*.bin; run by hand after changing the quadrature"]
    fn write_albedo_tables() {
        let mut bytes = Vec::with_capacity(N_TABLES * TABLE_BYTES);
        for table in computed() {
            for v in table.as_flattened() {
                bytes.extend_from_slice(&v.to_le_bytes());
            }
        }
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("src/bsdf");
        std::fs::write(dir.join("albedo_tables.bin"), bytes).unwrap();
        let bytes: Vec<u8> = dielectric_quadrature_table()
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        std::fs::write(dir.join("dielectric_albedo.bin"), bytes).unwrap();
    }

    /// Writes `anisotropic_albedo.bin` from the quadrature (run by hand; separate from
    /// `write_albedo_tables` so that the other tables keep the bits they were written with).
    #[test]
    #[ignore = "writes src/bsdf/anisotropic_albedo.bin; run by hand after changing the quadrature"]
    fn write_anisotropic_table() {
        let (a, b) = anisotropic_quadrature_tables();
        let bytes: Vec<u8> = a.iter().chain(&b).flat_map(|v| v.to_le_bytes()).collect();
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("src/bsdf");
        std::fs::write(dir.join("anisotropic_albedo.bin"), bytes).unwrap();
    }

    /// Writes `coat_loss.bin` from the quadrature (run by hand).
    #[test]
    #[ignore = "writes src/bsdf/coat_loss.bin; run by hand after changing the quadrature"]
    fn write_coat_loss_table() {
        let bytes: Vec<u8> = coat_loss_quadrature_table()
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("src/bsdf");
        std::fs::write(dir.join("coat_loss.bin"), bytes).unwrap();
    }

    /// The committed coat-loss table is what the quadrature gives, within rounding.
    #[test]
    fn committed_coat_loss_table_is_the_quadrature() {
        let table = coat_loss_quadrature_table();
        for (n, (c, s)) in table.iter().zip(&coat_loss_table().v).enumerate() {
            assert!(
                (c - s).abs() <= 1e-5,
                "coat-loss entry {n}: quadrature {c}, committed {s}; regenerate with \
                 `cargo test -p tessera-render --lib write_coat_loss_table -- --ignored`"
            );
        }
    }

    /// The committed anisotropic GGX tables are what the quadrature gives, within rounding.
    #[test]
    fn committed_anisotropic_tables_are_the_quadrature() {
        let (a, b) = anisotropic_quadrature_tables();
        let t = anisotropic_tables();
        for (n, (c, s)) in a.iter().chain(&b).zip(t.a.iter().chain(&t.b)).enumerate() {
            assert!(
                (c - s).abs() <= 1e-5,
                "anisotropic entry {n}: quadrature {c}, committed {s}; regenerate with \
                 `cargo test -p tessera-render --lib write_anisotropic_table -- --ignored`"
            );
        }
    }
}
