//! A clearcoat or a sheen over rough glass, seen from inside: [`coat_glass_loss`] and
//! [`sheen_glass_loss`] of the table in [`super`]'s documentation, their committed tables
//! (`coat_glass_loss.bin`, `sheen_glass_loss.bin`), quadrature and look-ups.

use super::*;

/// Nodes of the coated-glass table along the inside cosine `μ`, uniform in the coordinate
/// of [`g_mu_coordinate`]; an odd count puts the critical cosine on a node.
const G_MU: usize = 33;
/// Nodes along the interface's perceptual roughness, uniform in `[sqrt(MIN_ALPHA), 1]`.
const G_R: usize = 12;
/// Nodes along the relative index, uniform in `sqrt((η - 1) / (DIELECTRIC_ETA_MAX - 1))`
/// as the dielectric table's; an odd count puts the glTF default `η = 1.5` on a node.
const G_ETA: usize = 13;
/// Nodes along the layer's perceptual roughness, uniform in `[r_min, 1]` (the coat's
/// `sqrt(MIN_ALPHA)`, the sheen's [`sheen::MIN_SHEEN_ROUGHNESS`]).
const G_RC: usize = 8;
/// Entries of the coated-glass table (and of each of the sheen's two).
const G_SIZE: usize = G_RC * G_ETA * G_R * G_MU;
/// Quadrature points per side of the unit square (visible normals), per entry.
#[cfg(test)]
const G_QUAD: usize = 32;
/// Midpoint nodes in `sqrt(μi)` of the compensation's transmitted part, per entry.
#[cfg(test)]
const G_MS: usize = 64;

/// The committed coated-glass table `G(μ, r, η, r_coat)`, `r_coat` slowest, then `η`,
/// `r`, and `μ` fastest, little-endian binary32 (written by `write_coat_glass_table`).
static COMMITTED_COAT_GLASS: &[u8; 4 * G_SIZE] = include_bytes!("../coat_glass_loss.bin");

/// The committed sheen-over-glass tables in the coated-glass table's layout, the sheen's
/// perceptual roughness in place of the coat's: `G_sh` then `H` of
/// [`sheen_glass_loss`] (written by `write_sheen_glass_table`).
static COMMITTED_SHEEN_GLASS: &[u8; 8 * G_SIZE] = include_bytes!("../sheen_glass_loss.bin");

/// A glass-loss table (the coat's `G`, the sheen's `G_sh` or `H`) with its
/// cosine-weighted averages per `(r_layer, η, r)`.
struct GlassLossTable {
    v: Vec<f32>,
    avg: Vec<f32>,
}

#[inline]
fn g_index(k: usize, e: usize, j: usize, i: usize) -> usize {
    ((k * G_ETA + e) * G_R + j) * G_MU + i
}

/// The critical cosine `sqrt(1 - 1/η²)` inside a medium of relative index `η`: below
/// it a smooth interface reflects everything.
#[inline]
fn critical_cosine(eta: f32) -> f32 {
    (1.0 - 1.0 / (eta * eta)).max(0.0).sqrt()
}

/// The coated-glass table's coordinate of the inside cosine `μ`: linear in `μ` from 0 to
/// 1/2 below the critical cosine `mu_c`, and from 1/2 to 1 above it. `G` rises sharply
/// past `mu_c` (light leaving at grazing angles, which the coat reflects most), for a
/// smooth interface within a few degrees: aligning that edge across the indices keeps the
/// interpolation in `η` from blending two edges apart (with nodes in `sqrt(μ)`, the table
/// was off by 0.1 beside the edge at `r` 0.16, `η` 1.2), and puts half the nodes on the
/// transmitting side.
#[inline]
fn g_mu_coordinate(mu: f32, mu_c: f32) -> f32 {
    let mu = mu.clamp(0.0, 1.0);
    if mu < mu_c {
        0.5 * mu / mu_c
    } else {
        0.5 + 0.5 * (mu - mu_c) / (1.0 - mu_c).max(1e-6)
    }
}

/// The inverse of [`g_mu_coordinate`]: `μ` at the coordinate `x`.
fn g_mu_at(x: f32, mu_c: f32) -> f32 {
    if x <= 0.5 {
        mu_c * 2.0 * x
    } else {
        mu_c + (1.0 - mu_c) * (2.0 * x - 1.0)
    }
}

/// `2 ∫ G(μ) μ dμ` of values `G` at the nodes `μ` (increasing), exactly for their linear
/// interpolation in `μ`.
fn mu_linear_average(mu: &[f32], g: &[f32]) -> f32 {
    let mut sum = 0.0f64;
    for (m, v) in mu.windows(2).zip(g.windows(2)) {
        let (m0, dm) = (m[0] as f64, (m[1] - m[0]) as f64);
        let (g0, dg) = (v[0] as f64, (v[1] - v[0]) as f64);
        // ∫ 2 (m0 + dm t)(g0 + dg t) dm dt over t in [0, 1].
        sum += 2.0 * dm * (m0 * g0 + (m0 * dg + dm * g0) / 2.0 + dm * dg / 3.0);
    }
    sum as f32
}

/// `G(μ)` at one `(μ, α, η, α_coat)`: [`glass_loss_quadrature`] with the coat's albedo.
#[cfg(test)]
fn coat_glass_loss_quadrature(mu: f32, alpha: f32, eta: f32, alpha_cc: f32) -> f32 {
    glass_loss_quadrature(mu, alpha, eta, |mu_t| coat_albedo(mu_t, alpha_cc))
}

/// The power the interface of `(α, η)` seen from inside at `μ` sends out (single
/// scattering by the midpoint rule on the visible-normal warp, as the dielectric table;
/// the compensation's transmitted part, which depends on `μi` alone, by the midpoint
/// rule in `sqrt(μi)`), each direction weighted by a layer's albedo `layer(μi)` at its
/// outside cosine: what that layer reflects back inside.
#[cfg(test)]
fn glass_loss_quadrature(mu: f32, alpha: f32, eta: f32, layer: impl Fn(f32) -> f32) -> f32 {
    let mu = mu.max(MU_MIN);
    // The interface seen from inside: the frame mirrored so that the inside is `+z`.
    let inside = crate::bsdf::dielectric::RoughDielectric {
        eta: 1.0 / eta,
        alpha,
        tint: Vec3::ONE,
    };
    let wo = Vec3::new((1.0 - mu * mu).max(0.0).sqrt(), 0.0, mu);
    let coat = |wi: Vec3| layer(wi.z.abs());
    let mut single = 0.0f64;
    for i in 0..G_QUAD {
        for j in 0..G_QUAD {
            let u = Vec2::new(
                (i as f32 + 0.5) / G_QUAD as f32,
                (j as f32 + 0.5) / G_QUAD as f32,
            );
            single += inside.single_scattering_energy_with(wo, u, |_| 0.0, coat) as f64;
        }
    }
    // `∫ f_ms E_cc dωi = 2π ∫ f_ms(μi) E_cc(μi) dμi`, `dμi = 2x dx` with `x = sqrt(μi)`.
    let mut multiple = 0.0f64;
    for k in 0..G_MS {
        let x = (k as f64 + 0.5) / G_MS as f64;
        let mu_i = (x * x) as f32;
        let wi = Vec3::new((1.0 - mu_i * mu_i).max(0.0).sqrt(), 0.0, -mu_i);
        if let Some(f) = inside.eval_multiple(wo, wi) {
            multiple += (f.x * layer(mu_i)) as f64 * 2.0 * x / G_MS as f64;
        }
    }
    // Power, not radiance: the radiance BTDF's `1/η²` (`η = 1/eta` seen from inside) undone.
    let power = 2.0 * std::f64::consts::PI * multiple / (eta as f64 * eta as f64);
    (single / (G_QUAD * G_QUAD) as f64 + power) as f32
}

/// The coated-glass table by quadrature, in the committed file's order.
#[cfg(test)]
fn coat_glass_loss_quadrature_table() -> Vec<f32> {
    glass_loss_quadrature_table(MIN_ALPHA.sqrt(), |mu_t, rc| {
        coat_albedo(mu_t, (rc * rc).max(MIN_ALPHA))
    })
}

/// The sheen-over-glass tables by quadrature, in the committed file's order: `G_sh`
/// (the sheen's layer albedo as [`crate::bsdf::gltf`] scales by it, capped at one) then `H`
/// (times the envelope of the coat's albedo, [`coat_albedo_envelope`]).
#[cfg(test)]
fn sheen_glass_loss_quadrature_tables() -> Vec<f32> {
    let r_min = sheen::MIN_SHEEN_ROUGHNESS;
    let e_sh = |mu_t: f32, r: f32| sheen_layer_albedo(mu_t, r).min(1.0);
    let mut v = glass_loss_quadrature_table(r_min, e_sh);
    v.extend(glass_loss_quadrature_table(r_min, |mu_t, r| {
        e_sh(mu_t, r) * coat_albedo_envelope(mu_t)
    }));
    v
}

/// The largest clearcoat albedo at `μ` over all coat roughnesses: the maximum over the
/// GGX table's roughness nodes, which bounds [`coat_albedo`] everywhere, as its lookup is
/// linear in the roughness between nodes.
#[cfg(test)]
fn coat_albedo_envelope(mu: f32) -> f32 {
    let r_min = MIN_ALPHA.sqrt();
    (0..N_R)
        .map(|j| {
            let r = r_min + (1.0 - r_min) * node(j, N_R);
            coat_albedo(mu, r * r)
        })
        .fold(0.0, f32::max)
}

/// A glass-loss table by quadrature in the coated-glass layout, rows in parallel:
/// [`glass_loss_quadrature`] with the layer albedo `layer(μt, r_layer)`, `r_layer` on
/// [`G_RC`] nodes uniform in `[r_min, 1]`.
#[cfg(test)]
fn glass_loss_quadrature_table(r_min: f32, layer: impl Fn(f32, f32) -> f32 + Sync) -> Vec<f32> {
    (0..G_RC * G_ETA * G_R)
        .into_par_iter()
        .flat_map_iter(|row| {
            let (k, e, j) = (row / (G_ETA * G_R), (row / G_R) % G_ETA, row % G_R);
            let eta = eta_node_of(e, G_ETA);
            let r = r_node_of(j, G_R);
            let r_layer = r_min + (1.0 - r_min) * node(k, G_RC);
            let alpha = (r * r).max(MIN_ALPHA);
            let mu_c = critical_cosine(eta);
            let layer = &layer;
            (0..G_MU).map(move |i| {
                let mu = g_mu_at(node(i, G_MU), mu_c);
                glass_loss_quadrature(mu, alpha, eta, |mu_t| layer(mu_t, r_layer))
            })
        })
        .collect()
}

fn coat_glass_table() -> &'static GlassLossTable {
    static TABLE: OnceLock<GlassLossTable> = OnceLock::new();
    TABLE.get_or_init(|| GlassLossTable::read(COMMITTED_COAT_GLASS))
}

/// The sheen-over-glass tables `G_sh` and `H` of [`sheen_glass_loss`].
fn sheen_glass_tables() -> &'static [GlassLossTable; 2] {
    static TABLES: OnceLock<[GlassLossTable; 2]> = OnceLock::new();
    TABLES.get_or_init(|| {
        let (g, h) = COMMITTED_SHEEN_GLASS.split_at(4 * G_SIZE);
        [GlassLossTable::read(g), GlassLossTable::read(h)]
    })
}

impl GlassLossTable {
    /// The table from its committed little-endian bytes, with its averages.
    fn read(bytes: &[u8]) -> GlassLossTable {
        let v: Vec<f32> = bytes
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        let mut avg = Vec::with_capacity(G_RC * G_ETA * G_R);
        for k in 0..G_RC {
            for e in 0..G_ETA {
                let mu_c = critical_cosine(eta_node_of(e, G_ETA));
                let mu: [f32; G_MU] = std::array::from_fn(|i| g_mu_at(node(i, G_MU), mu_c));
                for j in 0..G_R {
                    let column: [f32; G_MU] = std::array::from_fn(|i| v[g_index(k, e, j, i)]);
                    avg.push(mu_linear_average(&mu, &column));
                }
            }
        }
        GlassLossTable { v, avg }
    }

    /// The interpolation at `μ` in the cell of [`g_locate`].
    #[inline]
    fn lookup(&self, mu: f32, eta: f32, cell: [(usize, f32); 3]) -> f32 {
        let mu_c = critical_cosine(eta.clamp(1.0, DIELECTRIC_ETA_MAX));
        let (i, s) = Table::locate(g_mu_coordinate(mu, mu_c), G_MU);
        let at = |k: usize, e: usize, j: usize| {
            let a = self.v[g_index(k, e, j, i)];
            a + (self.v[g_index(k, e, j, i + 1)] - a) * s
        };
        g_trilinear(at, cell)
    }

    /// The interpolation of the nodes' averages in the cell of [`g_locate`].
    #[inline]
    fn average(&self, cell: [(usize, f32); 3]) -> f32 {
        g_trilinear(|k, e, j| self.avg[(k * G_ETA + e) * G_R + j], cell)
    }
}

/// The coat's GGX `α` as the coordinate in [0, 1] of its perceptual roughness.
#[inline]
fn alpha_coordinate(alpha: f32) -> f32 {
    let r_min = MIN_ALPHA.sqrt();
    (alpha.max(0.0).sqrt() - r_min) / (1.0 - r_min)
}

/// Cells and fractions of `(α, η)` and of the layer's roughness coordinate `x_layer` in
/// [0, 1] in a glass-loss table (`η` beyond [`DIELECTRIC_ETA_MAX`] is looked up there).
#[inline]
fn g_locate(alpha: f32, eta: f32, x_layer: f32) -> [(usize, f32); 3] {
    let t = ((eta.min(DIELECTRIC_ETA_MAX) - 1.0) / (DIELECTRIC_ETA_MAX - 1.0))
        .max(0.0)
        .sqrt();
    [
        Table::locate(alpha_coordinate(alpha), G_R),
        Table::locate(t, G_ETA),
        Table::locate(x_layer, G_RC),
    ]
}

/// Trilinear interpolation of `at(k, e, j)` in the cell `[(j, u), (e, v), (k, w)]` of
/// [`g_locate`].
#[inline]
fn g_trilinear(at: impl Fn(usize, usize, usize) -> f32, cell: [(usize, f32); 3]) -> f32 {
    let [(j, u), (e, v), (k, w)] = cell;
    let lerp = |a: f32, b: f32, t: f32| a + (b - a) * t;
    let plane = |k: usize| {
        let lo = lerp(at(k, e, j), at(k, e, j + 1), u);
        let hi = lerp(at(k, e + 1, j), at(k, e + 1, j + 1), u);
        lerp(lo, hi, v)
    };
    lerp(plane(k), plane(k + 1), w)
}

/// `G(μ) = ∫_outside E_cc(μi) dP(wi)`: of the power that a white rough dielectric
/// interface of `alpha` and relative index `eta >= 1` (inside over outside) sends out
/// when met from inside at `μ = |cos θo|` (single scattering and the multiple-scattering
/// compensation of [`crate::bsdf::dielectric::RoughDielectric`]), the part a clearcoat of
/// `alpha_cc` (factor one) reflects back inside, `E_cc` at each direction's outside
/// cosine. [`crate::bsdf::gltf`] returns it inside as a lobe (it is linear in the clearcoat
/// factor). Quadrilinear in `(x, r, sqrt(η - 1), r_coat)`, `x` linear in `μ` from 0 to
/// 1/2 below the critical cosine `sqrt(1 - 1/η²)` and from 1/2 to 1 above it.
#[inline]
pub fn coat_glass_loss(mu: f32, alpha: f32, eta: f32, alpha_cc: f32) -> f32 {
    let cell = g_locate(alpha, eta, alpha_coordinate(alpha_cc));
    coat_glass_table().lookup(mu, eta, cell)
}

/// `2 ∫ G(μ) μ dμ` of [`coat_glass_loss`]: the trilinear interpolation of the nodes'
/// averages, exact at the index nodes (between them, the `μ` coordinate of the lookup
/// differs from the nodes', a difference of order the interpolation's own).
#[inline]
pub fn coat_glass_loss_average(alpha: f32, eta: f32, alpha_cc: f32) -> f32 {
    coat_glass_table().average(g_locate(alpha, eta, alpha_coordinate(alpha_cc)))
}

/// The cell of a sheen of perceptual roughness `sheen_r` in the sheen-over-glass tables.
#[inline]
fn sheen_glass_cell(alpha: f32, eta: f32, sheen_r: f32) -> [(usize, f32); 3] {
    let r_min = sheen::MIN_SHEEN_ROUGHNESS;
    g_locate(alpha, eta, (sheen_r - r_min) / (1.0 - r_min))
}

/// `(G_sh(μ), H(μ))` for a sheen of perceptual roughness `sheen_r` over the white rough
/// dielectric interface of [`coat_glass_loss`], met from inside at `μ`:
/// `G_sh = ∫_outside E_sh(μi) dP(wi)` is the part of the power the interface sends out
/// that the sheen (colour one) reflects back inside, `E_sh` = [`sheen_layer_albedo`]
/// (at most one) at each direction's outside cosine, as [`coat_glass_loss`] with the
/// sheen's layer albedo in place of the coat's. `H = ∫_outside E_sh(μi) Ê_cc(μi) dP(wi)`,
/// `Ê_cc` the largest clearcoat albedo over all coat roughnesses, bounds the overlap
/// `∫ E_sh E_cc dP` of a sheen under a clearcoat of any roughness, for [`crate::bsdf::gltf`]'s
/// return of a coat and a sheen together. Quadrilinear as [`coat_glass_loss`], with the
/// sheen's roughness uniform in `[MIN_SHEEN_ROUGHNESS, 1]` (`sheen_glass_loss.bin`).
#[inline]
pub fn sheen_glass_loss(mu: f32, alpha: f32, eta: f32, sheen_r: f32) -> (f32, f32) {
    let cell = sheen_glass_cell(alpha, eta, sheen_r);
    let [g, h] = sheen_glass_tables();
    (g.lookup(mu, eta, cell), h.lookup(mu, eta, cell))
}

/// `2 ∫ G_sh(μ) μ dμ` and `2 ∫ H(μ) μ dμ` of [`sheen_glass_loss`], as
/// [`coat_glass_loss_average`].
#[inline]
pub fn sheen_glass_loss_average(alpha: f32, eta: f32, sheen_r: f32) -> (f32, f32) {
    let cell = sheen_glass_cell(alpha, eta, sheen_r);
    let [g, h] = sheen_glass_tables();
    (g.average(cell), h.average(cell))
}

#[cfg(test)]
pub(crate) fn sheen_glass_loss_reference(mu: f32, alpha: f32, eta: f32, sheen_r: f32) -> f32 {
    glass_loss_quadrature(mu, alpha, eta, |mu_t| {
        sheen_layer_albedo(mu_t, sheen_r).min(1.0)
    })
}

#[cfg(test)]
pub(crate) fn coat_glass_loss_reference(mu: f32, alpha: f32, eta: f32, alpha_cc: f32) -> f32 {
    coat_glass_loss_quadrature(mu, alpha, eta, alpha_cc)
}

#[cfg(test)]
mod committed_tests {
    use super::*;

    /// Writes a glass-loss table file of `src/bsdf` from its quadrature.
    fn write_glass_table(file: &str, table: &[f32]) {
        let bytes: Vec<u8> = table.iter().flat_map(|v| v.to_le_bytes()).collect();
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("src/bsdf");
        std::fs::write(dir.join(file), bytes).unwrap();
    }

    /// The committed glass-loss `tables` are what the quadrature gives, within rounding.
    fn assert_glass_tables_are(file: &str, writer: &str, quadrature: &[f32], tables: &[&[f32]]) {
        let committed: Vec<f32> = tables.concat();
        assert_eq!(quadrature.len(), committed.len());
        for (n, (c, s)) in quadrature.iter().zip(&committed).enumerate() {
            assert!(
                (c - s).abs() <= 1e-5,
                "{file} entry {n}: quadrature {c}, committed {s}; regenerate with \
                 `cargo test -p tessera-render --lib {writer} -- --ignored`"
            );
        }
    }

    /// Writes `coat_glass_loss.bin` from the quadrature (run by hand; it depends on the
    /// GGX and dielectric tables, so it is written after them).
    #[test]
    #[ignore = "writes src/bsdf/coat_glass_loss.bin; run by hand after changing the quadrature"]
    fn write_coat_glass_table() {
        write_glass_table("coat_glass_loss.bin", &coat_glass_loss_quadrature_table());
    }

    /// Writes `sheen_glass_loss.bin` from the quadrature (run by hand; it depends on the
    /// GGX, sheen and dielectric tables, so it is written after them).
    #[test]
    #[ignore = "writes src/bsdf/sheen_glass_loss.bin; run by hand after changing the quadrature"]
    fn write_sheen_glass_table() {
        write_glass_table(
            "sheen_glass_loss.bin",
            &sheen_glass_loss_quadrature_tables(),
        );
    }

    /// The committed coated-glass table is what the quadrature gives, within rounding.
    #[test]
    fn committed_coat_glass_table_is_the_quadrature() {
        let v = &coat_glass_table().v;
        let quadrature = coat_glass_loss_quadrature_table();
        assert_glass_tables_are(
            "coat_glass_loss.bin",
            "write_coat_glass_table",
            &quadrature,
            &[v],
        );
    }

    /// The committed sheen-over-glass tables are what the quadrature gives, within rounding.
    #[test]
    fn committed_sheen_glass_tables_are_the_quadrature() {
        let [g, h] = sheen_glass_tables();
        let quadrature = sheen_glass_loss_quadrature_tables();
        let (file, writer) = ("sheen_glass_loss.bin", "write_sheen_glass_table");
        assert_glass_tables_are(file, writer, &quadrature, &[&g.v, &h.v]);
    }
}
