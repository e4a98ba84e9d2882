//! Vertex connection and merging, and progressive photon mapping (its merge-only mode),
//! against a closed form, against path tracing, and against themselves across thread
//! counts.
//!
//! Statistics as in `bdpt.rs`: light tracing and the shared photon map make the pixels of
//! one pass correlated, so block means are formed per pass and their spread is taken
//! across passes (independent replicates, each with its own photon map).

use crate::common::{block_passes, block_stats, z_critical};
use glam::{Vec2, Vec3};
use tessera_farm::{
    AdaptiveFrame, AdaptiveMode, AdaptiveSettings, ErrorEstimator, FrameImage, FramePlan,
};
use tessera_render::adaptive::{render_adaptive, Limits};
use tessera_render::integrator::vcm::VcmSettings;
use tessera_render::integrator::Integrator;
use tessera_render::render::{render_frame, render_unit, RenderConfig};
use tessera_render::scene::RenderScene;
use tessera_scene::analysis::{analyse, EffectKind, PlannedIntegrator};
use tessera_scene::builtin::look_at_camera;
use tessera_scene::{Material, MaterialKind, Mesh, PunctualLight, Scene};

/// Index of refraction of the water.
const N: f64 = 1.33;
/// Intensity of the point light (W/sr).
const I: f64 = 10.0;
/// Height of the light above the water surface.
const H: f64 = 1.0;
/// Depth of the water (surface to floor).
const D: f64 = 0.5;
/// Horizontal offset of the light from the camera's axis (so that its mirror image in the
/// water is outside the view: `L S E` from a point light to a pinhole has no technique).
pub(crate) const X_LIGHT: f64 = 1.0;
/// Height of the camera above the water surface.
const H_CAM: f64 = 2.0;
/// Albedo of the floor.
const RHO: f64 = 0.8;

fn settings(integrator: Integrator, seed: u64, max_depth: u32) -> RenderConfig {
    RenderConfig {
        integrator,
        seed,
        max_depth,
        rr_depth: 8,
        ..RenderConfig::default()
    }
}

fn quad(name: &str, y: f32, half: f32, material: u32) -> Mesh {
    let v = Vec3::new;
    Mesh {
        name: name.into(),
        positions: vec![
            v(-half, y, -half),
            v(-half, y, half),
            v(half, y, half),
            v(half, y, -half),
        ],
        normals: None,
        uvs: vec![],
        tangents: None,
        indices: vec![[0, 1, 2], [0, 2, 3]],
        colors: None,
        material,
    }
}

/// The pool: a diffuse floor (albedo [`RHO`]) at y = 0 under a flat water surface
/// (smooth dielectric, index [`N`]) at y = [`D`], a point light [`H`] above the water and
/// [`X_LIGHT`] to the side, and a pinhole camera [`H_CAM`] above the water looking
/// straight down. Light reaches the camera only as `L S D S E` (and longer paths through
/// the water): no technique of path tracing or bdpt samples it.
pub fn pool() -> Scene {
    let v = Vec3::new;
    let materials = vec![
        Material::diffuse("floor", Vec3::splat(RHO as f32)),
        Material {
            name: "water".into(),
            kind: MaterialKind::Dielectric {
                ior: N as f32,
                roughness: 0.0,
                tint: Vec3::ONE,
            },
            emission: Vec3::ZERO,
            double_sided: false,
        },
    ];
    let y_cam = (D + H_CAM) as f32;
    Scene {
        name: "test:pool".into(),
        camera: look_at_camera(v(0.0, y_cam, 0.0), v(0.0, 0.0, 0.0), Vec3::Z, 20.0),
        meshes: vec![quad("floor", 0.0, 2.0, 0), quad("water", D as f32, 2.0, 1)],
        prototypes: Vec::new(),
        instances: Vec::new(),
        spheres: vec![],
        materials,
        textures: vec![],
        images: vec![],
        warnings: vec![],
        lights: vec![PunctualLight::Point {
            position: v(X_LIGHT as f32, (D + H) as f32, 0.0),
            intensity: Vec3::splat(I as f32),
        }],
        environment: None,
        environment_map: None,
        default_resolution: (24, 24),
        animated: false,
    }
}

/// Unpolarised Fresnel reflectance for light arriving from air at `cos_i` onto index `n`
/// (the same for the reverse direction inside, by reciprocity).
fn fresnel(cos_i: f64, n: f64) -> f64 {
    let sin_t = (1.0 - cos_i * cos_i).max(0.0).sqrt() / n;
    let cos_t = (1.0 - sin_t * sin_t).max(0.0).sqrt();
    let rs = (cos_i - n * cos_t) / (cos_i + n * cos_t);
    let rp = (n * cos_i - cos_t) / (n * cos_i + cos_t);
    0.5 * (rs * rs + rp * rp)
}

/// Irradiance on the pool floor at horizontal distance `r` from the point below the light.
///
/// A ray leaving the light at angle θ₁ from the vertical meets the water at horizontal
/// distance `h tan θ₁`, refracts to θ₂ (`sin θ₁ = n sin θ₂`, Snell) and reaches the floor
/// at `r(θ₁) = h tan θ₁ + d tan θ₂`. The power in the solid angle `sin θ₁ dθ₁ dφ` is
/// `I sin θ₁ dθ₁ dφ`, of which the fraction `T(θ₁) = 1 - F(θ₁)` (Fresnel) crosses the
/// surface; power is conserved through the refraction (no `n²` for flux), and it lands on
/// the floor's annulus of area `r dr dφ`. So
///
/// `E(r) = I T(θ₁) sin θ₁ / (r dr/dθ₁)`, with
/// `dr/dθ₁ = h / cos² θ₁ + (d / cos² θ₂) cos θ₁ / (n cos θ₂)`
///
/// (the refraction's compression of the solid angle: `dθ₂/dθ₁ = cos θ₁ / (n cos θ₂)`), and
/// at `r = 0` the limit `I T(0) / (h + d/n)²` (the light's apparent distance).
pub(crate) fn floor_irradiance(r: f64) -> f64 {
    if r < 1e-9 {
        return I * (1.0 - fresnel(1.0, N)) / (H + D / N).powi(2);
    }
    let r_of = |t1: f64| {
        let t2 = (t1.sin() / N).asin();
        H * t1.tan() + D * t2.tan()
    };
    let (mut lo, mut hi) = (0.0f64, std::f64::consts::FRAC_PI_2 - 1e-9);
    for _ in 0..100 {
        let mid = 0.5 * (lo + hi);
        if r_of(mid) < r {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    let t1 = 0.5 * (lo + hi);
    let t2 = (t1.sin() / N).asin();
    let dr = H / t1.cos().powi(2) + D / t2.cos().powi(2) * t1.cos() / (N * t2.cos());
    I * (1.0 - fresnel(t1.cos(), N)) * t1.sin() / (r * dr)
}

/// [`floor_irradiance`] tabulated on `0..=R_TABLE` (linear interpolation between
/// `TABLE` + 1 points): the bisection is too slow to call per sample of the blur.
struct Table(Vec<f64>);

const R_TABLE: f64 = 4.0;
const TABLE: usize = 4000;

impl Table {
    fn new(f: impl Fn(f64) -> f64) -> Self {
        Self(
            (0..=TABLE)
                .map(|i| f(R_TABLE * i as f64 / TABLE as f64))
                .collect(),
        )
    }

    fn at(&self, r: f64) -> f64 {
        let x = (r / R_TABLE * TABLE as f64).clamp(0.0, TABLE as f64 - 1e-9);
        let i = x as usize;
        let t = x - i as f64;
        self.0[i] * (1.0 - t) + self.0[i + 1] * t
    }
}

/// The mean of the irradiance `e` over the disc of radius `radius` around the floor
/// point at distance `r` from the light's foot: the expected value of a merge with that
/// radius (a constant kernel), by a midpoint rule in `(ρ², φ)`.
fn blurred_irradiance(e: &Table, r: f64, radius: f64) -> f64 {
    let (nr, nphi) = (12, 24);
    let mut sum = 0.0;
    for i in 0..nr {
        let rho = radius * ((i as f64 + 0.5) / nr as f64).sqrt();
        for j in 0..nphi {
            let phi = std::f64::consts::TAU * (j as f64 + 0.5) / nphi as f64;
            let (x, z) = (r + rho * phi.cos(), rho * phi.sin());
            sum += e.at((x * x + z * z).sqrt());
        }
    }
    sum / (nr * nphi) as f64
}

/// The closed form of the radiance the camera receives along `dir` from `origin` (above
/// the water), with `irradiance(r)` the floor's irradiance at distance `r` from the
/// light's foot. The camera ray meets the water at angle θ_c, crosses it with `T(θ_c)`,
/// refracts to θ_t and reaches the floor; the Lambertian floor leaves radiance `ρ E / π`
/// in the water, and leaving the denser medium divides radiance by `n²` (radiance over
/// n² is invariant along a ray, Veach 1997 §5.2):
///
/// `L = T(θ_c) ρ E(r) / (π n²)`.
///
/// Only `L S D S E` is counted: the test renders with `max_depth` 3, which leaves out the
/// paths that bounce on the floor again after a reflection under the water surface.
fn pool_radiance(origin: Vec3, dir: Vec3, irradiance: impl Fn(f64) -> f64) -> f64 {
    let (o, d) = (origin.as_dvec3(), dir.as_dvec3().normalize());
    let t = (D - o.y) / d.y;
    let hit = o + d * t;
    let cos_c = -d.y;
    let horizontal = glam::DVec2::new(d.x, d.z);
    let sin_c = horizontal.length();
    let sin_t = sin_c / N;
    let tan_t = sin_t / (1.0 - sin_t * sin_t).sqrt();
    let u = if sin_c > 0.0 {
        horizontal / sin_c
    } else {
        glam::DVec2::ZERO
    };
    let floor = glam::DVec2::new(hit.x, hit.z) + u * (D * tan_t);
    let r = (floor - glam::DVec2::new(X_LIGHT, 0.0)).length();
    (1.0 - fresnel(cos_c, N)) * RHO * irradiance(r) / (std::f64::consts::PI * N * N)
}

/// The pool render's errors against the closed form `exact` (per pixel, luminance): the
/// measured relative RMS error, the image estimate a render reports (the pass spread,
/// `tessera_farm::image_relative_error`), and the image mean's relative offset. The pool
/// goal measurements of every technique share it.
pub(crate) fn pool_errors(
    plan: FramePlan,
    results: Vec<tessera_farm::UnitResult>,
    exact: &[f64],
) -> (f64, f64, f64) {
    let lum = |p: [f32; 3]| 0.2126 * p[0] as f64 + 0.7152 * p[1] as f64 + 0.0722 * p[2] as f64;
    let (w, h) = (plan.width as usize, plan.height as usize);
    let mut acc = tessera_farm::FrameAccumulator::new(plan);
    for r in results {
        acc.offer(r).unwrap();
    }
    let img = acc.image();
    let n = exact.len() as f64;
    let (mut rel2, mut sum, mut sum_exact) = (0.0, 0.0, 0.0);
    for (p, e) in img.mean.iter().zip(exact) {
        rel2 += ((lum(*p) - e) / e).powi(2);
        sum += lum(*p);
        sum_exact += e;
    }
    let estimate = tessera_farm::image_relative_error(w, h, |x, y| {
        let i = y * w + x;
        Some((lum(img.mean[i]), lum(img.variance_of_mean[i])))
    });
    ((rel2 / n).sqrt(), estimate, sum / sum_exact - 1.0)
}

/// The expected value of each `block x block` block: the closed form averaged over a
/// 4 x 4 grid of film points per pixel (the box filter), for `irradiance`.
pub(crate) fn expected_blocks(
    rs: &RenderScene,
    w: u32,
    h: u32,
    block: u32,
    irradiance: impl Fn(f64) -> f64 + Copy,
) -> Vec<f64> {
    let (bx, by) = (w.div_ceil(block), h.div_ceil(block));
    let mut sums = vec![0.0f64; (bx * by) as usize];
    let mut counts = vec![0u32; (bx * by) as usize];
    for y in 0..h {
        for x in 0..w {
            let mut l = 0.0;
            for sy in 0..4 {
                for sx in 0..4 {
                    let film = Vec2::new(
                        x as f32 + (sx as f32 + 0.5) / 4.0,
                        y as f32 + (sy as f32 + 0.5) / 4.0,
                    );
                    let (o, d) = rs.camera.generate_ray(film, Vec2::ZERO);
                    l += pool_radiance(o, d, irradiance);
                }
            }
            let b = ((y / block) * bx + x / block) as usize;
            sums[b] += l / 16.0;
            counts[b] += 1;
        }
    }
    sums.iter()
        .zip(&counts)
        .map(|(s, &c)| s / c as f64)
        .collect()
}

/// The merging settings `integrator` (vcm or ppm) renders with.
fn merge_settings(
    integrator: Integrator,
    s: &RenderConfig,
    rs: &RenderScene,
    w: u32,
    h: u32,
) -> VcmSettings {
    let new = match integrator {
        Integrator::Ppm => VcmSettings::ppm,
        _ => VcmSettings::new,
    };
    new(s.mis, s.max_depth, s.rr_depth, rs, w, h)
}

/// The first radius's footprint survey on the pool (`vcm::pixel_footprint`): the camera
/// looks straight down from [`H_CAM`] above the water, so a pixel's cone at the floor,
/// through the flat surface, is `ℓ sqrt(Ω)` with `ℓ` about `H_CAM + D` (the unfolded
/// length; the median ray is 8 degrees off the axis, 1% off the axis's value) and `Ω = A /
/// (W H)`, `A` the film's area at distance 1. The settings take 20 of them at 256 x 256;
/// at 24 x 24, 20 footprints would be most of the view and the scene cap holds instead.
#[test]
fn the_first_radius_is_pixel_footprints_on_the_pool() {
    use tessera_render::integrator::vcm::{pixel_footprint, RADIUS_FOOTPRINTS, RADIUS_MAX_SCENE};
    let (w, h) = (256, 256);
    let rs = RenderScene::build(&pool(), w, h).unwrap();
    let f = pixel_footprint(&rs, w, h, 3).unwrap() as f64;
    let tan = (10f64).to_radians().tan();
    let expect = (H_CAM + D) * (4.0 * tan * tan / (w * h) as f64).sqrt();
    eprintln!("pool footprint at 256 x 256: {f:.6} m, expected about {expect:.6} m");
    assert!((f / expect - 1.0).abs() < 0.03, "{f} vs {expect}");
    let s = settings(Integrator::Vcm, 1, 3);
    let st = merge_settings(Integrator::Vcm, &s, &rs, w, h);
    assert!((st.radius_1 as f64 / (RADIUS_FOOTPRINTS as f64 * f) - 1.0).abs() < 1e-5);
    let small = RenderScene::build(&pool(), 24, 24).unwrap();
    let st = merge_settings(Integrator::Ppm, &s, &small, 24, 24);
    let cap = RADIUS_MAX_SCENE * small.geometry.bounds_radius;
    assert_eq!(st.radius_1, cap);
    // Where the rule and the cap hold on scenes the camera sees whole (for the docs).
    for name in ["builtin:cornell-box", "builtin:caustic"] {
        let scene = tessera_scene::load(name).unwrap();
        for edge in [32, 256, 1024] {
            let rs = RenderScene::build(&scene, edge, edge).unwrap();
            let f = pixel_footprint(&rs, edge, edge, 8).unwrap();
            let big = rs.geometry.bounds_radius;
            eprintln!(
                "{name} at {edge} x {edge}: footprint {f:.5} = {:.5} of the scene radius; r_1 = \
                 {:.2} footprints (cap {:.1}, scene fraction rule {:.2})",
                f / big,
                (RADIUS_FOOTPRINTS * f).min(RADIUS_MAX_SCENE * big) / f,
                RADIUS_MAX_SCENE * big / f,
                1.5 * big / edge as f32 / f
            );
        }
    }
    // The survey needs a surface that merges: the camera looking away from everything
    // finds none (and the settings fall back to the scene-fraction rule).
    let mut away = pool();
    away.camera = look_at_camera(
        Vec3::new(0.0, 3.0, 0.0),
        Vec3::new(0.0, 10.0, 0.0),
        Vec3::Z,
        20.0,
    );
    let rs = RenderScene::build(&away, w, h).unwrap();
    assert_eq!(pixel_footprint(&rs, w, h, 3), None);
}

/// The SDS pool against its closed form. Each 6 x 6 block's mean over 48 passes must be
/// within `z σ + bias` of the closed form, where σ is the block's standard error from the
/// spread of the passes, z the Bonferroni-corrected 1% critical value, and `bias` the
/// documented bias of merging: the closed form blurred by each pass's merging disc
/// (`VcmSettings::radius`), averaged over the passes, minus the closed form. The blurred
/// form itself must pass the plain z-test: that the render converges to it is what says
/// the bias is only the kernel's.
#[test]
fn vcm_renders_the_pool_floor_to_its_closed_form() {
    pool_floor_to_its_closed_form(Integrator::Vcm, 5);
}

/// As [`vcm_renders_the_pool_floor_to_its_closed_form`] for progressive photon mapping,
/// where merging is the only technique.
#[test]
fn ppm_renders_the_pool_floor_to_its_closed_form() {
    pool_floor_to_its_closed_form(Integrator::Ppm, 6);
}

fn pool_floor_to_its_closed_form(integrator: Integrator, seed: u64) {
    let scene = pool();
    let (w, h, block) = (24, 24, 6);
    let rs = RenderScene::build(&scene, w, h).unwrap();
    let passes = 48;
    let plan = FramePlan::new(w, h, w, 8, passes).unwrap();
    let s = settings(integrator, seed, 3);
    let stats = block_stats(&block_passes(&rs, &s, &plan, block));
    let exact = expected_blocks(&rs, w, h, block, floor_irradiance);
    let st = merge_settings(integrator, &s, &rs, w, h);
    let radii: Vec<f64> = (0..passes).map(|k| st.radius(k) as f64).collect();
    // The blur of each pass's radius, averaged over the passes, tabulated in r.
    let e = Table::new(floor_irradiance);
    let blur = Table::new(|r| {
        radii
            .iter()
            .map(|&rk| blurred_irradiance(&e, r, rk))
            .sum::<f64>()
            / radii.len() as f64
    });
    let blurred = expected_blocks(&rs, w, h, block, |r| blur.at(r));
    let crit = z_critical(0.01, stats.len());
    let (mut worst_rel, mut worst_z) = (0.0f64, 0.0f64);
    for (b, &(mean, var)) in stats.iter().enumerate() {
        let se = var.sqrt();
        let bias = (blurred[b] - exact[b]).abs();
        let rel = (mean - exact[b]) / exact[b];
        eprintln!(
            "pool block {b}: {integrator} {mean:.5} ± {se:.5}, closed form {:.5} (blurred {:.5}, \
             bias bound {bias:.5}), relative error {rel:+.4}",
            exact[b], blurred[b]
        );
        assert!(
            (mean - exact[b]).abs() <= crit * se + bias,
            "block {b}: {mean} vs closed form {} (se {se}, bias bound {bias})",
            exact[b]
        );
        let z = (mean - blurred[b]) / se;
        assert!(
            z.abs() <= crit,
            "block {b}: z = {z} against the blurred form"
        );
        worst_rel = worst_rel.max(rel.abs());
        worst_z = worst_z.max(z.abs());
    }
    let mean: f64 = stats.iter().map(|s| s.0).sum::<f64>() / stats.len() as f64;
    let expect: f64 = exact.iter().sum::<f64>() / exact.len() as f64;
    eprintln!(
        "pool image: {integrator} {mean:.5}, closed form {expect:.5} ({:+.3}%); worst block {:.3}%, \
         worst |z| against the blurred form {worst_z:.2} (critical {crit:.2})",
        100.0 * (mean / expect - 1.0),
        100.0 * worst_rel
    );
    // Not vacuous: the floor is lit, and the image's mean is within 2% of the closed form.
    assert!(expect > 0.01, "{expect}");
    assert!((mean / expect - 1.0).abs() < 0.02, "{mean} vs {expect}");
}

/// The reported estimate against the measured error at the footprint rule's radius
/// (docs/benchmarks.md, "The SDS pool in one minute"): the pool at 128 x 128, where `r_1`
/// is [`tessera_render::integrator::vcm::RADIUS_FOOTPRINTS`] footprints (below about 100
/// pixels the scene cap holds), 32 passes of 1 sample, 4 seeds. The reported image
/// estimate (`FrameImage::error_estimate`: the pass spread plus the merging bias term,
/// which must stay small here) over the relative RMS
/// error measured against the closed form, root mean square over the seeds, must be
/// within 0.8-1.25 (measured: see the output), and each render's pixel intervals (2
/// estimated standard errors, Student's t with 31 degrees of freedom predicts 94.6%) must
/// cover 90-97% of the pixels: the bias merging leaves on the smooth pool floor is small
/// against the pass spread, so the spread alone is calibrated here.
#[test]
fn pool_estimate_covers_the_measured_error() {
    for integrator in [Integrator::Ppm, Integrator::Vcm] {
        pool_estimate_is_calibrated(integrator);
    }
}

fn pool_estimate_is_calibrated(integrator: Integrator) {
    let (w, h) = (128, 128);
    let rs = RenderScene::build(&pool(), w, h).unwrap();
    let table = Table::new(floor_irradiance);
    let exact = expected_blocks(&rs, w, h, 1, |r| table.at(r));
    let lum = |p: [f32; 3]| 0.2126 * p[0] as f64 + 0.7152 * p[1] as f64 + 0.0722 * p[2] as f64;
    let plan = FramePlan::new(w, h, w, 1, 32).unwrap();
    let (mut est2, mut meas2) = (0.0, 0.0);
    for seed in [31, 32, 33, 34] {
        let img = render_frame(&rs, &settings(integrator, seed, 3), &plan, 0, 0, |_, _| {}).image();
        let n = exact.len() as f64;
        let (mut rel2, mut inside) = (0.0, 0usize);
        for (i, e) in exact.iter().enumerate() {
            let m = lum(img.mean[i]);
            rel2 += ((m - e) / e).powi(2);
            inside += usize::from((m - e).abs() <= 2.0 * lum(img.variance_of_mean[i]).sqrt());
        }
        let measured = (rel2 / n).sqrt();
        let estimate = img
            .error_estimate(tessera_farm::ErrorEstimator::Robust)
            .unwrap();
        let spread = tessera_farm::image_relative_error(w as usize, h as usize, |x, y| {
            let i = y * w as usize + x;
            Some((lum(img.mean[i]), lum(img.variance_of_mean[i])))
        });
        let bias = img.bias.as_ref().expect("vcm and ppm carry bias layers");
        // The parts of the estimate (ARCHITECTURE.md §3): the spread over the
        // bias-corrected scale, and the squared bias term over it.
        let (mut sv, mut sb) = (0.0, 0.0);
        for (i, b) in bias.iter().enumerate() {
            let (m, v) = (lum(img.mean[i]), lum(img.variance_of_mean[i]));
            let (bm, bv) = (f64::from(b[0]), f64::from(b[1]));
            let s = tessera_farm::bias_scale(m, v, m, bm, bv);
            sv += v / (s * s);
            sb += tessera_farm::bias_squared(bm, bv) / (s * s);
        }
        let n_px = bias.len() as f64;
        eprintln!(
            "pool 128x128 {integrator} seed {seed}: spread over the corrected scale {:.4}, \
             bias term {:.4} (signed root of its mean square)",
            (sv / n_px).sqrt(),
            (sb / n_px).signum() * (sb / n_px).abs().sqrt()
        );
        let coverage = inside as f64 / n;
        eprintln!(
            "pool 128x128 {integrator} seed {seed}: estimate {estimate:.4} (spread alone \
             {spread:.4}) / measured {measured:.4} = {:.3}, 2-sigma coverage {:.2}%",
            estimate / measured,
            100.0 * coverage
        );
        assert!(
            (0.90..=0.97).contains(&coverage),
            "{integrator} seed {seed}: coverage {coverage}"
        );
        est2 += estimate * estimate;
        meas2 += measured * measured;
    }
    let ratio = (est2 / meas2).sqrt();
    eprintln!("pool 128x128 {integrator}: estimate / measured over the seeds {ratio:.3}");
    assert!((0.8..=1.25).contains(&ratio), "{integrator}: {ratio}");
}

/// Path tracing and bdpt leave the pool floor black: there is no technique for `L S D S E`
/// from a point light. The analysis finds the class and plans mnee (every caustic within
/// manifold next-event estimation's reach, unbiased); path and bdpt say they cannot sample
/// it, mnee says nothing is missing, vcm and ppm that they are biased.
#[test]
fn the_pool_is_invisible_to_path_and_bdpt_and_the_plan_picks_mnee() {
    let scene = pool();
    let (w, h) = (12, 12);
    let rs = RenderScene::build(&scene, w, h).unwrap();
    let plan = FramePlan::new(w, h, w, 4, 4).unwrap();
    for integrator in [Integrator::Path, Integrator::Bdpt] {
        let acc = render_frame(&rs, &settings(integrator, 1, 3), &plan, 0, 1, |_, _| {});
        let img = acc.image();
        let max = img
            .mean
            .iter()
            .map(|p| p[0].max(p[1]).max(p[2]))
            .fold(0.0f32, f32::max);
        assert_eq!(max, 0.0, "{integrator}: the floor is lit?");
    }
    let p = analyse(&scene);
    assert!(p.has(EffectKind::DeltaLitSds), "{}", p.summary());
    assert_eq!(p.integrator, PlannedIntegrator::Mnee, "{}", p.summary());
    assert_eq!(p.unsampled(Integrator::Mnee), None, "{}", p.summary());
    let caveat = p.error_estimate_caveat(Integrator::Bdpt).unwrap();
    assert!(caveat.starts_with("cannot sample"), "{caveat}");
    for integrator in [Integrator::Vcm, Integrator::Ppm] {
        let caveat = p.error_estimate_caveat(integrator).unwrap();
        assert!(caveat.starts_with("biased"), "{integrator}: {caveat}");
    }
}

/// Every technique weighted by MIS, merging's bias aside: vcm agrees with path tracing on
/// the Cornell box (area light, every connection and merge in play). The whole image's
/// mean over the passes must be within `z σ` of path tracing's plus 1% for the merging
/// bias at the corners.
#[test]
fn vcm_agrees_with_path_on_the_cornell_box() {
    agrees_with_path_on_the_cornell_box(Integrator::Vcm, 0.01);
}

/// Progressive photon mapping on the Cornell box: all of its light, direct included, is
/// merged, so the blur's loss at the box's edges and corners is in every pass: a 2%
/// allowance for the bias (measured: -0.46% ± 1.2% at 32 passes; the first radius is
/// the scene cap, a sixteenth of the scene's bounding radius, at 24 x 24).
#[test]
fn ppm_agrees_with_path_on_the_cornell_box() {
    agrees_with_path_on_the_cornell_box(Integrator::Ppm, 0.02);
}

fn agrees_with_path_on_the_cornell_box(integrator: Integrator, bias: f64) {
    let scene = tessera_scene::load("builtin:cornell-box").unwrap();
    let rs = RenderScene::build(&scene, 24, 24).unwrap();
    let path = whole_image_mean(&rs, Integrator::Path, 22);
    agrees(&rs, "cornell box", integrator, ("path", path), bias);
}

/// The glass sphere's caustic of a small light (`builtin:caustic`, the calibration suite's
/// caustic scene) against the suite's converged reference (bdpt, 262,144 samples per pixel,
/// `tests/fixtures/calibration/caustic.exr`): at 32 x 32 the first radius is the scene cap
/// (`RADIUS_MAX_SCENE`, the largest the footprint rule gives; 5 footprints here, 20 from
/// about 128 pixels). The whole image's mean must be within `z σ` of the reference's plus
/// 2% for the blur, which spreads the focused caustic over the sphere's shadow and loses
/// light at the floor's edges (measured: vcm -1.53% ± 1.05%, ppm -1.85% ± 1.07%, neither
/// significant against the spread alone). The per-pixel bias is another matter: see
/// docs/benchmarks.md, "The first radius from the camera's pixel footprint".
#[test]
fn vcm_agrees_with_bdpt_on_the_caustic() {
    agrees_with_the_caustic_reference(Integrator::Vcm, 0.02);
}

/// As [`vcm_agrees_with_bdpt_on_the_caustic`] for progressive photon mapping, where the
/// direct light is merged too.
#[test]
fn ppm_agrees_with_bdpt_on_the_caustic() {
    agrees_with_the_caustic_reference(Integrator::Ppm, 0.02);
}

fn agrees_with_the_caustic_reference(integrator: Integrator, bias: f64) {
    let scene = tessera_scene::load("builtin:caustic").unwrap();
    let rs = RenderScene::build(&scene, 32, 32).unwrap();
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../tests/fixtures/calibration/caustic.exr"
    );
    let exr = tessera_image::read_exr(&std::fs::read(path).unwrap()).unwrap();
    assert_eq!((exr.width, exr.height), (32, 32));
    let layer = |c: &str| exr.get(c).unwrap().to_vec();
    let weights = [0.2126f64, 0.7152, 0.0722];
    let n = 32 * 32;
    let (mut mean, mut sd) = (vec![0.0f64; n], vec![0.0f64; n]);
    for (i, c) in ["R", "G", "B"].into_iter().enumerate() {
        let (m, v) = (layer(c), layer(&format!("variance.{c}")));
        for p in 0..n {
            mean[p] += weights[i] * m[p] as f64;
            // The channels' covariances are not stored: bound the luminance's standard
            // error by that of perfectly correlated channels.
            sd[p] += weights[i] * (v[p] as f64).sqrt();
        }
    }
    let n = n as f64;
    let reference = (
        mean.iter().sum::<f64>() / n,
        sd.iter().map(|s| s * s).sum::<f64>() / (n * n),
    );
    agrees(
        &rs,
        "caustic",
        integrator,
        ("bdpt reference", reference),
        bias,
    );
}

/// The whole image's mean luminance of `integrator` over 32 passes of 4 samples (max depth
/// 8) and the variance of that mean from the spread of the passes.
fn whole_image_mean(rs: &RenderScene, integrator: Integrator, seed: u64) -> (f64, f64) {
    let (w, h) = (rs.width, rs.height);
    let plan = FramePlan::new(w, h, w, 4, 32).unwrap();
    let whole = block_passes(rs, &settings(integrator, seed, 8), &plan, 4)
        .iter()
        .map(|b| vec![b.iter().sum::<f64>() / b.len() as f64])
        .collect::<Vec<_>>();
    block_stats(&whole)[0]
}

/// `integrator`'s whole image mean (seed 21) within the two-sided 1% `z` of the combined
/// standard error plus `bias` of the reference's mean.
fn agrees(
    rs: &RenderScene,
    name: &str,
    integrator: Integrator,
    (label, reference): (&str, (f64, f64)),
    bias: f64,
) {
    let merged = whole_image_mean(rs, integrator, 21);
    let se = (merged.1 + reference.1).sqrt();
    eprintln!(
        "{name}: {integrator} {:.5} ± {:.5}, {label} {:.5} ± {:.5} ({:+.2}%)",
        merged.0,
        merged.1.sqrt(),
        reference.0,
        reference.1.sqrt(),
        100.0 * (merged.0 / reference.0 - 1.0)
    );
    assert!(
        (merged.0 - reference.0).abs() <= z_critical(0.01, 1) * se + bias * reference.0,
        "{integrator} {} vs {label} {}",
        merged.0,
        reference.0
    );
}

/// A wall of no thickness (one quad at x = 0) stands on a floor that runs under it, and a
/// point light lights the floor on the wall's left. The camera looks down at the floor on
/// its right, where no path from the light arrives (nothing above or around the wall
/// returns light): the exact image is black. Merging's disc reaches under the wall to the
/// lit floor (here `r_1` is the scene cap, 0.19, and the camera sees the floor from 0.15
/// beside the wall) unless a photon must be visible from the camera vertex (the module
/// documentation of `integrator::vcm`, "Light leaks"): before that test vcm's and ppm's
/// pixels beside the wall were lit. Every pixel of every pass must be exactly zero.
#[test]
fn no_light_leaks_under_a_wall_of_no_thickness() {
    let v = Vec3::new;
    let wall = Mesh {
        name: "wall".into(),
        positions: vec![
            v(0.0, 0.0, -2.0),
            v(0.0, 0.0, 2.0),
            v(0.0, 3.0, 2.0),
            v(0.0, 3.0, -2.0),
        ],
        normals: None,
        uvs: vec![],
        tangents: None,
        indices: vec![[0, 1, 2], [0, 2, 3]],
        colors: None,
        material: 0,
    };
    let scene = Scene {
        name: "test:wall".into(),
        camera: look_at_camera(v(0.5, 2.0, 0.0), v(0.5, 0.0, 0.0), Vec3::Z, 20.0),
        meshes: vec![quad("floor", 0.0, 2.0, 0), wall],
        prototypes: Vec::new(),
        instances: Vec::new(),
        spheres: vec![],
        materials: vec![Material::diffuse("white", Vec3::splat(0.8))],
        textures: vec![],
        images: vec![],
        warnings: vec![],
        lights: vec![PunctualLight::Point {
            position: v(-0.5, 1.0, 0.0),
            intensity: Vec3::splat(10.0),
        }],
        environment: None,
        environment_map: None,
        default_resolution: (24, 24),
        animated: false,
    };
    let rs = RenderScene::build(&scene, 24, 24).unwrap();
    let plan = FramePlan::new(24, 24, 24, 4, 4).unwrap();
    for integrator in [Integrator::Vcm, Integrator::Ppm] {
        let s = settings(integrator, 5, 8);
        let st = merge_settings(integrator, &s, &rs, 24, 24);
        assert!(
            st.radius_1 > 0.15,
            "the disc ({}) no longer reaches under the wall: the test shows nothing",
            st.radius_1
        );
        let img = render_frame(&rs, &s, &plan, 0, 2, |_, _| {});
        let lit = img
            .image()
            .mean
            .iter()
            .filter(|p| p.iter().any(|c| *c != 0.0))
            .count();
        assert_eq!(lit, 0, "{integrator}: {lit} pixels lit through the wall");
    }
}

/// The merging bias term makes the caustic's error estimate honest (ARCHITECTURE.md §3,
/// the module documentation of `integrator::vcm`, "The bias estimate"): on
/// `builtin:caustic` at 32 x 32, 4 passes of 16 samples (the default plan of 64 spp), 4
/// seeds, the image estimate over the error measured against the suite's converged bdpt
/// reference (its own variance subtracted), root mean square over the seeds, must be
/// within 0.5-2 for vcm and for ppm; the pass spread alone is below 0.1 there
/// (docs/benchmarks.md, "The merging bias term"), so the test fails without the term.
#[test]
fn caustic_estimate_with_the_bias_term_is_calibrated() {
    let scene = tessera_scene::load("builtin:caustic").unwrap();
    let rs = RenderScene::build(&scene, 32, 32).unwrap();
    let reference = caustic_reference();
    let plan = FramePlan::new(32, 32, 32, 16, 4).unwrap();
    for integrator in [Integrator::Vcm, Integrator::Ppm] {
        let (mut est2, mut spread2, mut meas2) = (0.0, 0.0, 0.0);
        for seed in [8, 9, 10, 11] {
            let img =
                render_frame(&rs, &settings(integrator, seed, 8), &plan, 0, 0, |_, _| {}).image();
            let estimate = img
                .error_estimate(tessera_farm::ErrorEstimator::Robust)
                .unwrap();
            let spread = spread_alone(&img, tessera_farm::ErrorEstimator::Robust);
            let measured = measured_against(&img, &reference);
            eprintln!(
                "caustic 32x32 {integrator} seed {seed}: estimate {estimate:.4} (spread alone \
                 {spread:.4}), measured {measured:.4}: {:.3}",
                estimate / measured
            );
            est2 += estimate * estimate;
            spread2 += spread * spread;
            meas2 += measured * measured;
        }
        let ratio = (est2 / meas2).sqrt();
        eprintln!(
            "caustic 32x32 {integrator}: estimate / measured {ratio:.3} (spread alone {:.3})",
            (spread2 / meas2).sqrt()
        );
        assert!((0.5..=2.0).contains(&ratio), "{integrator}: {ratio}");
    }
}

/// Adaptive renders of vcm and ppm keep the merging bias channel over the passes each
/// pixel keeps, and their estimate adds the bias term as the uniform one does
/// (ARCHITECTURE.md §3, "Biased techniques: the bias term"): on `builtin:caustic` at
/// 32 x 32, `tessera render --adaptive unbiased|sequential --target-error 0.1 --spp 4096
/// --max-depth 8` (its plan: passes of 16 samples), seeds 8-11, the estimate over the
/// error measured against the suite's converged reference, root mean square over the
/// seeds, must be within the 0.8-1.25 for both techniques and both modes
/// (measured 0.92-0.96). The pass spread alone was 0.02-0.08 there (docs/benchmarks.md,
/// "The merging bias term under adaptive stopping"), so the test fails without the term;
/// the frame's own estimate (status, summary) must be the written image's.
#[test]
fn adaptive_caustic_estimate_with_the_bias_term_is_calibrated() {
    for (integrator, mode, (ratio, spread)) in adaptive_caustic_ratios(&[8, 9, 10, 11]) {
        assert!(
            (0.8..=1.25).contains(&ratio),
            "{integrator} {mode}: estimate / measured {ratio} (spread alone {spread})"
        );
        assert!(spread < 0.2, "{integrator} {mode}: spread alone {spread}");
    }
}

/// Estimate over measured error, with the bias term and from the spread alone, root mean
/// square over `seeds`, of `tessera render`'s adaptive renders of the caustic at 32 x 32
/// (target 0.1, at most 4,096 spp, max depth 8) for vcm and ppm, unbiased and sequential.
fn adaptive_caustic_ratios(seeds: &[u64]) -> Vec<(Integrator, AdaptiveMode, (f64, f64))> {
    let scene = tessera_scene::load("builtin:caustic").unwrap();
    let rs = RenderScene::build(&scene, 32, 32).unwrap();
    let reference = caustic_reference();
    let plan = tessera_farm::adaptive_plan(32, 32, 4096, 32).unwrap();
    let mut out = Vec::new();
    for integrator in [Integrator::Vcm, Integrator::Ppm] {
        for mode in [AdaptiveMode::Unbiased, AdaptiveMode::Sequential] {
            let (mut est2, mut spread2, mut meas2) = (0.0, 0.0, 0.0);
            for &seed in seeds {
                let s = AdaptiveSettings {
                    mode,
                    target_error: 0.1,
                    ..AdaptiveSettings::default()
                };
                let frame = AdaptiveFrame::new(plan, 0, s).unwrap();
                let config = RenderConfig {
                    integrator,
                    seed,
                    max_depth: 8,
                    ..RenderConfig::default()
                };
                let out = render_adaptive(&rs, &config, frame, 0, Limits::default(), |_| {});
                let img = out.frame.image();
                assert!(img.bias.is_some(), "{integrator} {mode}: no bias layers");
                let estimator = ErrorEstimator::for_mode(mode);
                let estimate = img.error_estimate(estimator).unwrap();
                assert!(
                    (out.frame.image_error() - estimate).abs() <= 1e-4 * estimate,
                    "{integrator} {mode}: the frame says {}, its image {estimate}",
                    out.frame.image_error()
                );
                let spread = spread_alone(&img, estimator);
                let measured = measured_against(&img, &reference);
                let (mean_spp, _, _) = out.frame.samples_per_pixel();
                eprintln!(
                    "caustic 32x32 adaptive {mode} {integrator} seed {seed}: estimate \
                     {estimate:.4} (spread alone {spread:.4}), measured {measured:.4}: {:.3}, \
                     mean spp {mean_spp:.1}",
                    estimate / measured
                );
                est2 += estimate * estimate;
                spread2 += spread * spread;
                meas2 += measured * measured;
            }
            let ratio = ((est2 / meas2).sqrt(), (spread2 / meas2).sqrt());
            eprintln!(
                "caustic 32x32 adaptive {mode} {integrator}: estimate / measured {:.3} (spread \
                 alone {:.3})",
                ratio.0, ratio.1
            );
            out.push((integrator, mode, ratio));
        }
    }
    out
}

/// The measurement behind docs/benchmarks.md, "The merging bias term": on
/// `builtin:caustic` at 32 x 32 (against the suite's committed reference) and 64 x 64
/// (against a bdpt render of 16,384 samples per pixel made here, 64 passes of 256, seed
/// 1000, its variance subtracted like the committed one's), vcm and ppm at 64, 256 and
/// 1,024 spp (the default plan's 4 x 16, 4 x 64 and 16 x 64, whole-frame), 8 seeds each:
/// the estimate with the bias term and the pass spread's alone over the measured error,
/// root mean square over the seeds, with one render's range. Run with `--ignored
/// --nocapture`.
#[test]
#[ignore = "a measurement: prints the caustic's bias-term table (about 10 minutes)"]
fn caustic_bias_term_table() {
    let scene = tessera_scene::load("builtin:caustic").unwrap();
    eprintln!("| size | technique | spp (passes) | estimate / measured (one render: min-max) | spread alone / measured | measured error (min-max) |");
    eprintln!("|---|---|---|---|---|---|");
    for edge in [32u32, 64] {
        let rs = RenderScene::build(&scene, edge, edge).unwrap();
        let reference = if edge == 32 {
            caustic_reference()
        } else {
            let settings = RenderConfig {
                integrator: Integrator::Bdpt,
                seed: 1000,
                max_depth: 8,
                ..RenderConfig::default()
            };
            let plan = FramePlan::new(edge, edge, edge, 256, 64).unwrap();
            let img = render_frame(&rs, &settings, &plan, 0, 0, |_, _| {}).image();
            let w = tessera_farm::LUMINANCE_WEIGHTS;
            (0..img.mean.len())
                .map(|p| {
                    (
                        (0..3).map(|c| w[c] * f64::from(img.mean[p][c])).sum(),
                        (0..3)
                            .map(|c| w[c] * w[c] * f64::from(img.variance_of_mean[p][c]))
                            .sum(),
                    )
                })
                .collect()
        };
        for integrator in [Integrator::Vcm, Integrator::Ppm] {
            for (per_pass, passes) in [(16u32, 4u32), (64, 4), (64, 16)] {
                let plan = FramePlan::new(edge, edge, edge, per_pass, passes).unwrap();
                let mut rows = Vec::new();
                for seed in 8..16 {
                    let settings = RenderConfig {
                        integrator,
                        seed,
                        max_depth: 8,
                        ..RenderConfig::default()
                    };
                    let img = render_frame(&rs, &settings, &plan, 0, 0, |_, _| {}).image();
                    let estimate = img
                        .error_estimate(tessera_farm::ErrorEstimator::Robust)
                        .unwrap();
                    let spread = spread_alone(&img, tessera_farm::ErrorEstimator::Robust);
                    rows.push((estimate, spread, measured_against(&img, &reference)));
                }
                let rms = |f: fn(&(f64, f64, f64)) -> f64| {
                    (rows.iter().map(|r| f(r).powi(2)).sum::<f64>() / rows.len() as f64).sqrt()
                };
                let range = |f: &dyn Fn(&(f64, f64, f64)) -> f64| {
                    rows.iter()
                        .map(f)
                        .fold((f64::MAX, f64::MIN), |(a, b), x| (a.min(x), b.max(x)))
                };
                let m = rms(|r| r.2);
                let (lo, hi) = range(&|r| r.0 / r.2);
                let (mlo, mhi) = range(&|r| r.2);
                eprintln!(
                    "| {edge}x{edge} | {integrator} | {} ({passes}) | {:.3} ({lo:.3}-{hi:.3}) | {:.3} | {m:.4} ({mlo:.4}-{mhi:.4}) |",
                    per_pass * passes,
                    rms(|r| r.0) / m,
                    rms(|r| r.1) / m,
                );
            }
        }
    }
}

/// The calibration suite's caustic reference (bdpt, 262,144 samples per pixel, 32 x 32):
/// per pixel its mean luminance and the variance of that mean (channels taken as
/// independent, as the suite's measured error does).
fn caustic_reference() -> Vec<(f64, f64)> {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../tests/fixtures/calibration/caustic.exr"
    );
    let exr = tessera_image::read_exr(&std::fs::read(path).unwrap()).unwrap();
    assert_eq!((exr.width, exr.height), (32, 32));
    let w = tessera_farm::LUMINANCE_WEIGHTS;
    let layer = |c: &str| exr.get(c).unwrap().to_vec();
    let (m, v): (Vec<_>, Vec<_>) = ["R", "G", "B"]
        .iter()
        .map(|c| (layer(c), layer(&format!("variance.{c}"))))
        .unzip();
    (0..32 * 32)
        .map(|p| {
            (
                (0..3).map(|c| w[c] * f64::from(m[c][p])).sum(),
                (0..3).map(|c| w[c] * w[c] * f64::from(v[c][p])).sum(),
            )
        })
        .collect()
}

/// The image's error estimate from the pass spread alone: its bias layers dropped, so
/// what the bias term adds can be seen beside it.
fn spread_alone(img: &FrameImage, estimator: tessera_farm::ErrorEstimator) -> f64 {
    FrameImage {
        bias: None,
        ..img.clone()
    }
    .error_estimate(estimator)
    .unwrap()
}

/// The calibration suite's measured error: the RMS over pixels of the luminance error
/// over `lum(reference) + REL_EPS`, the reference's variance subtracted.
fn measured_against(img: &FrameImage, reference: &[(f64, f64)]) -> f64 {
    let lum = |p: [f32; 3]| tessera_farm::luminance(p.map(f64::from));
    let sum: f64 = reference
        .iter()
        .enumerate()
        .map(|(p, &(m, v))| {
            let d = lum(img.mean[p]) - m;
            (d * d - v) / (m + tessera_farm::REL_EPS).powi(2)
        })
        .sum();
    (sum / reference.len() as f64).max(0.0).sqrt()
}

/// ARCHITECTURE.md §2 for vcm: the photon map is built single-threaded per pass inside
/// the unit, so thread counts and unit splits change nothing.
#[test]
fn vcm_is_bit_identical_across_threads_and_unit_splits() {
    bit_identical_across_threads_and_unit_splits(Integrator::Vcm);
}

/// The same for progressive photon mapping.
#[test]
fn ppm_is_bit_identical_across_threads_and_unit_splits() {
    bit_identical_across_threads_and_unit_splits(Integrator::Ppm);
}

fn bit_identical_across_threads_and_unit_splits(integrator: Integrator) {
    let scene = pool();
    let (w, h) = (16, 12);
    let rs = RenderScene::build(&scene, w, h).unwrap();
    let plan = FramePlan::new(w, h, w.max(h), 2, 4).unwrap();
    assert_eq!(plan.tile_count(), 1);
    let s = settings(integrator, 9, 8);
    let bits = super::common::frame_bits;
    let one = render_frame(&rs, &s, &plan, 0, 1, |_, _| {});
    let two = render_frame(&rs, &s, &plan, 0, 2, |_, _| {});
    assert!(bits(&one) == bits(&two), "2 threads differ from 1");
    let mut acc = tessera_farm::FrameAccumulator::new(plan);
    let mut units = plan.units(0, 1);
    units.reverse();
    for u in units {
        acc.offer(render_unit(&rs, &s, &plan, u)).unwrap();
    }
    assert!(bits(&acc) == bits(&one), "units in reverse order differ");
    assert!(one.image().mean.iter().any(|p| p[0] > 0.0), "a black image");
}

/// Efficiency `1 / (MSE x seconds)` of vcm, ppm, bdpt and path on the pool (against the closed
/// form, per pixel) and on `scenes/glass-spot.gltf` (against a vcm render with 4x the
/// passes, its own variance subtracted). Prints a table; run with `--ignored --nocapture`.
/// Wall time, so not an assertion.
#[test]
#[ignore = "a measurement: prints the efficiency table"]
fn vcm_efficiency_table() {
    use std::time::Instant;
    let time = |rs: &RenderScene, s: &RenderConfig, plan: &FramePlan| {
        let t = Instant::now();
        let acc = render_frame(rs, s, plan, 0, 2, |_, _| {});
        (acc.image(), t.elapsed().as_secs_f64())
    };
    let lum = |p: [f32; 3]| 0.2126 * p[0] as f64 + 0.7152 * p[1] as f64 + 0.0722 * p[2] as f64;
    // The pool, max depth 3 (the closed form's paths).
    let (w, h) = (64, 64);
    let rs = RenderScene::build(&pool(), w, h).unwrap();
    let exact = expected_blocks(&rs, w, h, 1, floor_irradiance);
    let plan = FramePlan::new(w, h, w, 4, 16).unwrap();
    for integrator in [
        Integrator::Vcm,
        Integrator::Ppm,
        Integrator::Bdpt,
        Integrator::Path,
    ] {
        let (img, secs) = time(&rs, &settings(integrator, 3, 3), &plan);
        let mse = img
            .mean
            .iter()
            .zip(&exact)
            .map(|(p, e)| (lum(*p) - e).powi(2))
            .sum::<f64>()
            / exact.len() as f64;
        let mean = img.mean.iter().map(|p| lum(*p)).sum::<f64>() / exact.len() as f64;
        let truth = exact.iter().sum::<f64>() / exact.len() as f64;
        eprintln!(
            "pool 64x64, 64 spp, {integrator}: {secs:.2} s, mean {mean:.4} (closed form \
             {truth:.4}), rel. RMSE {:.4}, 1/(MSE s) {:.4e}",
            mse.sqrt() / truth,
            1.0 / (mse * secs)
        );
    }
    // glass-spot: a spot light through a glass ball, seen through the ball.
    let scene = tessera_scene::load(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../scenes/glass-spot.gltf"
    ))
    .unwrap();
    let (w, h) = (48, 36);
    let rs = RenderScene::build(&scene, w, h).unwrap();
    let (reference, _) = time(
        &rs,
        &settings(Integrator::Vcm, 99, 12),
        &FramePlan::new(w, h, w, 8, 64).unwrap(),
    );
    let ref_var: f64 = reference
        .variance_of_mean
        .iter()
        .map(|v| lum(*v))
        .sum::<f64>()
        / reference.mean.len() as f64;
    let plan = FramePlan::new(w, h, w, 4, 16).unwrap();
    for integrator in [
        Integrator::Vcm,
        Integrator::Ppm,
        Integrator::Bdpt,
        Integrator::Path,
    ] {
        let (img, secs) = time(&rs, &settings(integrator, 4, 12), &plan);
        let n = img.mean.len() as f64;
        let mse = img
            .mean
            .iter()
            .zip(&reference.mean)
            .map(|(p, r)| (lum(*p) - lum(*r)).powi(2))
            .sum::<f64>()
            / n
            - ref_var;
        let truth = reference.mean.iter().map(|p| lum(*p)).sum::<f64>() / n;
        eprintln!(
            "glass-spot 48x36, 64 spp, {integrator}: {secs:.2} s, rel. RMSE {:.4} (vs vcm \
             256 spp), 1/(MSE s) {:.4e}",
            mse.max(0.0).sqrt() / truth,
            1.0 / (mse.max(1e-30) * secs)
        );
    }
}

/// CPU seconds (user + system) this process has used so far, from `/proc/self/stat`
/// (clock ticks of 1/100 s): the pool goal is stated in CPU time, which the shared
/// machine's load does not inflate as it does wall time.
pub(crate) fn cpu_seconds() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    // Fields after the command name (which is in parentheses): utime and stime are the
    // 12th and 13th of them.
    let rest = stat.rsplit_once(')').map(|r| r.1).unwrap_or("");
    let f: Vec<&str> = rest.split_whitespace().collect();
    let tick = |i: usize| f.get(i).and_then(|s| s.parse::<f64>().ok()).unwrap_or(0.0);
    (tick(11) + tick(12)) / 100.0
}

/// The pool goal (docs/benchmarks.md, "The SDS pool in one minute"): the pool at 256 x 256,
/// max depth 3 (the closed form's `L S D S E`), rendered by ppm and vcm on 2 threads for
/// `TESSERA_POOL_PASSES` passes (default 16) of `TESSERA_POOL_SPP` samples (default 1),
/// the first radius scaled by `TESSERA_POOL_RADIUS` (default 1) and the schedule's α
/// `TESSERA_POOL_ALPHA` (default [`tessera_render::integrator::vcm::RADIUS_ALPHA`]):
/// CPU seconds, the measured relative RMS error per pixel against the closed form (box
/// filtered), the image mean against the closed form's, and the reported estimate
/// (`tessera_farm::image_relative_error`, the pass spread) over the measured error.
/// A measurement, not an assertion; run with `--ignored --nocapture`.
#[test]
#[ignore = "a measurement: the pool goal's figures"]
fn pool_goal_measurement() {
    let env = |k: &str, d: u32| {
        std::env::var(k)
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(d)
    };
    let envf = |k: &str, d: f32| {
        std::env::var(k)
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(d)
    };
    let passes = env("TESSERA_POOL_PASSES", 16);
    let radius_scale = envf("TESSERA_POOL_RADIUS", 1.0);
    let alpha = envf(
        "TESSERA_POOL_ALPHA",
        tessera_render::integrator::vcm::RADIUS_ALPHA,
    );
    let spp = env("TESSERA_POOL_SPP", 1);
    let (w, h) = (256, 256);
    let rs = RenderScene::build(&pool(), w, h).unwrap();
    let table = Table::new(floor_irradiance);
    let exact = expected_blocks(&rs, w, h, 1, |r| table.at(r));
    let plan = FramePlan::new(w, h, w, spp, passes).unwrap();
    let footprint = tessera_render::integrator::vcm::pixel_footprint(&rs, w, h, 3).unwrap();
    let which = std::env::var("TESSERA_POOL_INTEGRATORS").unwrap_or("ppm,vcm".into());
    for name in which.split(',') {
        let integrator: Integrator = name.parse().unwrap();
        let s = settings(integrator, 11, 3);
        let mut st = merge_settings(integrator, &s, &rs, w, h);
        st.radius_1 *= radius_scale;
        st.alpha = alpha;
        let stream = tessera_render::integrator::SampleStream::of(&s);
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(2)
            .build()
            .unwrap();
        let c0 = cpu_seconds();
        let results: Vec<_> = pool.install(|| {
            use rayon::prelude::*;
            plan.units(0, 1)
                .par_iter()
                .map(|u| {
                    tessera_render::integrator::vcm::render_unit(
                        &rs,
                        &st,
                        stream,
                        &plan,
                        *u,
                        |_, _| true,
                    )
                })
                .collect()
        });
        let cpu = cpu_seconds() - c0;
        let (measured, estimate, offset) = pool_errors(plan, results, &exact);
        eprintln!(
            "pool 256x256 {integrator} (r_1 {:.4} = {:.1} footprints, alpha {}): {passes} passes x \
             {spp} spp, {cpu:.1} CPU s; measured \
             rel. RMS error {measured:.4}, estimate {estimate:.4} (ratio {:.2}); image mean \
             {:+.2}% off the closed form",
            st.radius_1,
            st.radius_1 / footprint,
            st.alpha,
            estimate / measured,
            100.0 * offset
        );
    }
}
