use super::*;

/// SplitMix64, for test photons.
fn rng(state: &mut u64) -> f32 {
    *state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^= z >> 31;
    (z >> 40) as f32 / (1u64 << 24) as f32
}

/// The density estimate's known answer: `N` light paths each leave one photon uniform
/// over a unit square with power `Φ / N`, so the irradiance is `Φ` everywhere. The
/// merge estimate at a point, `sum_{|x_i - p| < r} β_i / (π r² N)` with `β_i = Φ`, has
/// mean `Φ` away from the edges. Query points at least `2 r` apart see disjoint photons
/// (independent estimates): a t-test of their mean against `Φ` at the 0.1% level, and
/// the grid's answer must equal a brute-force search's.
#[test]
fn density_estimate_is_the_irradiance() {
    let n = 200_000usize;
    let phi = 3.0f32;
    let r = 0.02f32;
    let mut s = 7u64;
    let photons: Vec<Photon> = (0..n)
        .map(|_| Photon {
            p: Vec3::new(rng(&mut s), rng(&mut s), 0.25),
            wo: Vec3::Z,
            n: Vec3::Z,
            beta: Vec3::splat(phi),
            depth: 1,
            d_vcm: 0.0,
            d_vm: 0.0,
        })
        .collect();
    let mut grid = HashGrid::default();
    grid.build(&photons, r);
    let norm = 1.0 / (PI * r * r * n as f32);
    let mut est = Vec::new();
    let steps = 20;
    for i in 0..steps {
        for j in 0..steps {
            let p = Vec3::new(
                0.05 + 0.9 * i as f32 / (steps - 1) as f32,
                0.05 + 0.9 * j as f32 / (steps - 1) as f32,
                0.25,
            );
            let mut e = 0.0f64;
            grid.query(&photons, p, |ph| e += ph.beta.x as f64);
            let brute: f64 = photons
                .iter()
                .filter(|ph| (ph.p - p).length_squared() <= r * r)
                .map(|ph| ph.beta.x as f64)
                .sum();
            assert_eq!(e, brute, "grid query at {p}");
            est.push(e * norm as f64);
        }
    }
    let m = est.len() as f64;
    let mean = est.iter().sum::<f64>() / m;
    let var = est.iter().map(|e| (e - mean).powi(2)).sum::<f64>() / (m - 1.0);
    let t = (mean - phi as f64) / (var / m).sqrt();
    assert!(t.abs() < 3.3, "mean {mean} vs {phi}: t = {t}");
    // And the estimate is not trivially right: each point saw about N π r² photons.
    assert!(var > 0.0);
}

#[test]
fn radius_follows_the_schedule() {
    let st = VcmSettings {
        mis: MisHeuristic::Power,
        max_depth: 8,
        rr_depth: 3,
        radius_1: 0.02,
        alpha: RADIUS_ALPHA,
        merge_only: false,
    };
    assert_eq!(st.radius(0), 0.02);
    let expect = st.radius(0) * 4f32.powf(-0.125);
    assert!((st.radius(3) - expect).abs() < 1e-7);
    assert!(st.radius(100) < st.radius(10));
}
