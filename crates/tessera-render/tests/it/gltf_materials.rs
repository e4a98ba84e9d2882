//! glTF materials rendered, each against a known answer: texture slots, wrap modes,
//! texture transforms and coordinate sets read through an emissive texture seen directly
//! (the pixel is the texel), alpha MASK and BLEND (stochastic transparency, shadows
//! included), a normal map under a grazing directional light (Lambert's cosine with the
//! mapped normal), Beer–Lambert absorption through a slab, and a textured emitter lighting
//! a floor like the untextured emitter of its lit part (next-event estimation and light
//! tracing evaluate the texture where they sample).

use crate::common::{image_mean, render};
use serde_json::{json, Value};
use tessera_render::integrator::Integrator;
use tessera_render::render::RenderConfig;
use tessera_scene::gltf_import::load_slice;
use tessera_scene::Scene;
use tessera_testkit::gltf_gen::{png_rgb8, png_rgba8, Gen};

const SIDE: u32 = 12;

fn load(g: &Gen) -> Scene {
    load_slice(&g.glb(), "test.glb", None, None).unwrap()
}

fn config(integrator: Integrator) -> RenderConfig {
    RenderConfig {
        integrator,
        seed: 3,
        ..RenderConfig::default()
    }
}

/// A pinhole camera at height `d` above the centre of the unit square [0,1]² of the
/// z = 0 plane, looking down -Z (glTF cameras look down their -Z) so that the square
/// exactly fills a square image: pixel column k covers x in [k/12, (k+1)/12].
fn camera(g: &mut Gen, d: f32) {
    let yfov = 2.0 * (0.5 / d).atan();
    let c = g.push(
        "cameras",
        json!({"type": "perspective", "perspective": {"yfov": yfov, "znear": 0.01, "aspectRatio": 1.0}}),
    );
    g.root(json!({"camera": c, "translation": [0.5, 0.5, d]}));
}

/// A quad `[x0,x1] x [y0,y1]` at height `z` facing +Z, with TEXCOORD_0 from `uv(x, y)` and
/// TEXCOORD_1 = (x, 1 - y).
fn quad(
    g: &mut Gen,
    material: usize,
    (x0, x1, y0, y1, z): (f32, f32, f32, f32, f32),
    uv: impl Fn(f32, f32) -> [f32; 2],
) -> usize {
    let corners = [[x0, y0], [x1, y0], [x1, y1], [x0, y1]];
    let pos = g.positions(&corners.map(|[x, y]| [x, y, z]));
    let normal = g.vec3(&[[0.0, 0.0, 1.0]; 4]);
    let uv0 = g.vec2(&corners.map(|[x, y]| uv(x, y)));
    let uv1 = g.vec2(&corners.map(|[x, y]| [x, 1.0 - y]));
    let idx = g.indices_u16(&[0, 1, 2, 0, 2, 3]);
    let m = g.push(
        "meshes",
        json!({"primitives": [{"attributes": {"POSITION": pos, "NORMAL": normal,
            "TEXCOORD_0": uv0, "TEXCOORD_1": uv1}, "indices": idx, "material": material}]}),
    );
    g.root(json!({"mesh": m}))
}

/// A texture of an embedded PNG with a sampler.
fn texture(g: &mut Gen, png: &[u8], sampler: Value) -> usize {
    let view = g.view(png);
    let image = g.push(
        "images",
        json!({"bufferView": view, "mimeType": "image/png"}),
    );
    let s = g.push("samplers", sampler);
    g.push("textures", json!({"source": image, "sampler": s}))
}

/// A material that scatters nothing (black, no specular layer) and emits `emissive`
/// times the texture `info` (if any).
fn emitter(g: &mut Gen, emissive: [f32; 3], info: Option<Value>) -> usize {
    g.uses("KHR_materials_specular");
    let mut m = json!({"pbrMetallicRoughness": {"baseColorFactor": [0.0, 0.0, 0.0, 1.0],
        "metallicFactor": 0.0}, "emissiveFactor": emissive,
        "extensions": {"KHR_materials_specular": {"specularFactor": 0.0}}});
    if let Some(i) = info {
        m["emissiveTexture"] = i;
    }
    g.push("materials", m)
}

/// Pixel means (RGB) of a render, row-major from the top row.
fn pixels(scene: &Scene, spp: u32, integrator: Integrator) -> Vec<[f32; 3]> {
    let acc = render(scene, SIDE, SIDE, spp, &config(integrator));
    acc.image().mean.clone()
}

const RED: [f32; 3] = [1.0, 0.0, 0.0];
const GREEN: [f32; 3] = [0.0, 1.0, 0.0];

/// The colour of every pixel column, checked to be the same down each column.
fn columns(px: &[[f32; 3]]) -> Vec<[f32; 3]> {
    (0..SIDE as usize)
        .map(|x| {
            let c = px[x];
            for y in 0..SIDE as usize {
                let p = px[y * SIDE as usize + x];
                assert!(
                    (0..3).all(|k| (p[k] - c[k]).abs() < 1e-5),
                    "column {x} row {y}: {p:?} vs {c:?}"
                );
            }
            c
        })
        .collect()
}

/// Two pixels per texel column: the expected texel of each of the six columns.
fn expect(pattern: [[f32; 3]; 6]) -> Vec<[f32; 3]> {
    pattern.iter().flat_map(|c| [*c, *c]).collect()
}

fn assert_columns(got: &[[f32; 3]], want: &[[f32; 3]], what: &str) {
    for (x, (g, w)) in got.iter().zip(want).enumerate() {
        assert!(
            (0..3).all(|k| (g[k] - w[k]).abs() < 1e-5),
            "{what}: column {x} is {g:?}, expected {w:?}\n got {got:?}"
        );
    }
}

/// A 2x1 red|green texture, nearest filtering, seen through an emissive quad whose u runs
/// from -1 to 2 across the image (six texel columns of two pixels each). The expected
/// patterns are the OpenGL wrap definitions written out by hand for texel indices
/// -2..=3: repeat `i mod 2`, mirrored repeat (period 4: 1 0 0 1 1 0), clamp to edge
/// (0 0 0 1 1 1).
#[test]
fn wrap_modes_texture_transform_and_coordinate_sets() {
    let png = png_rgb8(2, 1, &[255, 0, 0, 0, 255, 0]);
    let cases: [(u32, [[f32; 3]; 6]); 3] = [
        (10497, [RED, GREEN, RED, GREEN, RED, GREEN]),
        (33648, [GREEN, RED, RED, GREEN, GREEN, RED]),
        (33071, [RED, RED, RED, GREEN, GREEN, GREEN]),
    ];
    for (mode, pattern) in cases {
        let mut g = Gen::new();
        let t = texture(
            &mut g,
            &png,
            json!({"wrapS": mode, "wrapT": mode, "magFilter": 9728}),
        );
        let m = emitter(&mut g, [1.0; 3], Some(json!({"index": t})));
        quad(&mut g, m, (0.0, 1.0, 0.0, 1.0, 0.0), |x, _| {
            [-1.0 + 3.0 * x, 0.5]
        });
        camera(&mut g, 2.0);
        let got = columns(&pixels(&load(&g), 4, Integrator::Path));
        assert_columns(&got, &expect(pattern), &format!("wrap mode {mode}"));
    }
    // KHR_texture_transform: u in [0, 1] mapped by offset -1 and scale 3 is the same
    // image as u in [-1, 2]; read through TEXCOORD_1 (x, 1 - y) while TEXCOORD_0 is 0.
    let mut g = Gen::new();
    g.uses("KHR_texture_transform");
    let t = texture(&mut g, &png, json!({"wrapS": 10497, "magFilter": 9728}));
    let info = json!({"index": t, "texCoord": 1, "extensions": {"KHR_texture_transform":
        {"offset": [-1.0, 0.0], "scale": [3.0, 1.0]}}});
    let m = emitter(&mut g, [1.0; 3], Some(info));
    quad(&mut g, m, (0.0, 1.0, 0.0, 1.0, 0.0), |_, _| [0.0, 0.0]);
    camera(&mut g, 2.0);
    let got = columns(&pixels(&load(&g), 4, Integrator::Path));
    assert_columns(
        &got,
        &expect([RED, GREEN, RED, GREEN, RED, GREEN]),
        "KHR_texture_transform on TEXCOORD_1",
    );
    // The emissive texture is sRGB: code 188 is linear 0.5029, times the factor.
    let mut g = Gen::new();
    let grey = png_rgb8(1, 1, &[188, 188, 188]);
    let t = texture(&mut g, &grey, json!({}));
    let m = emitter(&mut g, [2.0, 1.0, 0.5], Some(json!({"index": t})));
    quad(&mut g, m, (0.0, 1.0, 0.0, 1.0, 0.0), |x, y| [x, y]);
    camera(&mut g, 2.0);
    let px = pixels(&load(&g), 4, Integrator::Path);
    let lin = ((188.0 / 255.0 + 0.055) / 1.055f64).powf(2.4) as f32;
    for p in px {
        for (k, f) in [2.0, 1.0, 0.5].iter().enumerate() {
            assert!((p[k] - f * lin).abs() < 1e-5, "{p:?} vs {}", f * lin);
        }
    }
}

/// A black, half-transparent plane at z = 0 in front of an emissive wall of radiance 1
/// at z = -1 (the camera above sees only the plane's square).
fn alpha_scene(alpha_mode: &str, base: Value, texture_png: Option<Vec<u8>>) -> Scene {
    let mut g = Gen::new();
    let wall = emitter(&mut g, [1.0; 3], None);
    quad(&mut g, wall, (-5.0, 6.0, -5.0, 6.0, -1.0), |x, y| [x, y]);
    g.uses("KHR_materials_specular");
    let mut m = json!({"pbrMetallicRoughness": {"baseColorFactor": base, "metallicFactor": 0.0},
        "alphaMode": alpha_mode, "doubleSided": true,
        "extensions": {"KHR_materials_specular": {"specularFactor": 0.0}}});
    if let Some(png) = texture_png {
        let t = texture(&mut g, &png, json!({"magFilter": 9728, "wrapS": 33071}));
        m["pbrMetallicRoughness"]["baseColorTexture"] = json!({"index": t});
    }
    let plane = g.push("materials", m);
    quad(&mut g, plane, (0.0, 1.0, 0.0, 1.0, 0.0), |x, _| [x, 0.5]);
    camera(&mut g, 2.0);
    load(&g)
}

#[test]
fn alpha_mask_cuts_out_and_blend_lets_light_through_in_proportion() {
    // MASK with a texture whose left texel has alpha 0.2 and right 0.8, cutoff 0.5: the
    // left half of the image shows the wall (1), the right half the black plane (0).
    let png = png_rgba8(2, 1, &[0, 0, 0, 51, 0, 0, 0, 204]);
    let s = alpha_scene("MASK", json!([1.0, 1.0, 1.0, 1.0]), Some(png.clone()));
    let got = columns(&pixels(&s, 4, Integrator::Path));
    let (white, black) = ([1.0; 3], [0.0; 3]);
    assert_columns(
        &got,
        &expect([white, white, white, black, black, black]),
        "MASK",
    );
    // OPAQUE ignores alpha: all black.
    let s = alpha_scene("OPAQUE", json!([1.0, 1.0, 1.0, 1.0]), Some(png));
    assert!(pixels(&s, 4, Integrator::Path)
        .iter()
        .all(|p| p == &[0.0; 3]));
    // BLEND with alpha 0.3: a camera ray passes with probability 0.7. 144 pixels x 256
    // rays; z-test of the image mean against 0.7 with the estimated standard error.
    for integrator in [Integrator::Path, Integrator::Bdpt] {
        let s = alpha_scene("BLEND", json!([0.0, 0.0, 0.0, 0.3]), None);
        let acc = render(&s, SIDE, SIDE, 256, &config(integrator));
        let (mean, se) = image_mean(&acc, 0);
        let z = (mean - 0.7) / se;
        eprintln!("BLEND {integrator:?}: {mean:.4} ± {se:.4} (z = {z:.2})");
        assert!(z.abs() < 4.0, "{integrator:?}: {mean} ± {se}, expected 0.7");
        assert!(se > 0.0 && se < 0.01);
    }
}

/// A floor (albedo 0.8, z = 0) lit by a directional light travelling along
/// (-1, 0, -1)/√2, and a vertical black BLEND plane with alpha 0.4 at x = 1.5 across every
/// light ray to the floor the camera sees (x in [0, 1]); camera rays never meet it. Shadow rays pass with
/// probability 0.6, so the floor's radiance is 0.6 of the unshadowed
/// `0.8/π · E cos 45°`.
#[test]
fn shadow_rays_pass_blended_surfaces_with_probability_one_minus_alpha() {
    let mut g = Gen::new();
    g.uses("KHR_materials_specular");
    g.uses("KHR_lights_punctual");
    let floor = g.push(
        "materials",
        json!({"pbrMetallicRoughness": {"baseColorFactor": [0.8, 0.8, 0.8, 1.0], "metallicFactor": 0.0},
            "extensions": {"KHR_materials_specular": {"specularFactor": 0.0}}}),
    );
    quad(&mut g, floor, (-1.0, 2.0, -1.0, 2.0, 0.0), |x, y| [x, y]);
    let blind = g.push(
        "materials",
        json!({"pbrMetallicRoughness": {"baseColorFactor": [0.0, 0.0, 0.0, 0.4], "metallicFactor": 0.0},
            "alphaMode": "BLEND", "doubleSided": true,
            "extensions": {"KHR_materials_specular": {"specularFactor": 0.0}}}),
    );
    // The blind: a quad in the x = 1.5 plane, y in [-2, 3], z in [0.3, 1.7] (shadow rays
    // from the floor's x in [0, 1] cross x = 1.5 at z = 1.5 - x).
    let pos = g.positions(&[
        [1.5, -2.0, 0.3],
        [1.5, 3.0, 0.3],
        [1.5, 3.0, 1.7],
        [1.5, -2.0, 1.7],
    ]);
    let idx = g.indices_u16(&[0, 1, 2, 0, 2, 3]);
    let mesh = g.push(
        "meshes",
        json!({"primitives": [{"attributes": {"POSITION": pos}, "indices": idx, "material": blind}]}),
    );
    g.root(json!({"mesh": mesh}));
    // 683 lux = 1 W/m² (Tessera and Blender divide by 683 lm/W).
    let light = g.light(json!({"type": "directional", "intensity": 683.0}));
    // Node -Z rotated to travel along (-1, 0, -1)/√2: rotate +45° about Y... the light's
    // -Z axis turned toward -X by a rotation of +45° about +Y (x' = -sin 45, z' = -cos 45).
    let (s, c) = (
        std::f32::consts::FRAC_PI_8.sin(),
        std::f32::consts::FRAC_PI_8.cos(),
    );
    g.root(json!({"rotation": [0.0, s, 0.0, c],
        "extensions": {"KHR_lights_punctual": {"light": light}}}));
    camera(&mut g, 0.5);
    g.doc["extensionsUsed"] = json!(["KHR_materials_specular", "KHR_lights_punctual"]);
    let scene = load(&g);
    let expected = 0.8 / std::f64::consts::PI * std::f64::consts::FRAC_1_SQRT_2 * 0.6;
    for integrator in [Integrator::Path, Integrator::Direct] {
        let acc = render(&scene, SIDE, SIDE, 128, &config(integrator));
        let (mean, se) = image_mean(&acc, 0);
        let z = (mean - expected) / se;
        eprintln!("shadow through BLEND {integrator:?}: {mean:.5} ± {se:.5}, expected {expected:.5} (z = {z:.2})");
        assert!(z.abs() < 4.0, "{integrator:?}: {mean} ± {se} vs {expected}");
    }
}

/// A Lambertian plane (albedo 0.8) with a constant tangent-space normal map under a
/// directional light grazing from +Y at 75° from the normal. The pixel is
/// `0.8/π · E · max(0, n'·l) · 2/(1 + n'·n)` with the mapped normal n' exactly (one delta
/// light, nothing to bounce off; the last factor is the normal map's energy compensation,
/// `scene::normal_map_diffuse_gain`). Green up the image tilts n' toward +Y (the image's top is +Y here, as
/// TEXCOORD_0 = (x, 1 - y) puts it), brightening the plane; green down darkens it. This
/// pins the MikkTSpace handedness that Blender and Cycles use.
#[test]
fn normal_map_tilts_the_shading_normal_with_the_right_handedness() {
    let theta = 75f64.to_radians();
    let l = [0.0, theta.sin(), theta.cos()];
    let mut results = Vec::new();
    for (green, scale) in [(191u8, 1.0f32), (64, 1.0), (191, 0.5), (128, 1.0)] {
        let mut g = Gen::new();
        g.uses("KHR_materials_specular");
        g.uses("KHR_lights_punctual");
        let png = png_rgb8(1, 1, &[128, green, 230]);
        let t = texture(&mut g, &png, json!({}));
        let m = g.push(
            "materials",
            json!({"pbrMetallicRoughness": {"baseColorFactor": [0.8, 0.8, 0.8, 1.0], "metallicFactor": 0.0},
                "normalTexture": {"index": t, "scale": scale},
                "extensions": {"KHR_materials_specular": {"specularFactor": 0.0}}}),
        );
        quad(&mut g, m, (-1.0, 2.0, -1.0, 2.0, 0.0), |x, y| [x, 1.0 - y]);
        let light = g.light(json!({"type": "directional", "intensity": 683.0}));
        // The light's -Z must travel along -l: rotate -Z by -(90° - 75°)... by an angle φ
        // about +X with -Z -> (0, -sin φ, -cos φ) = -l, φ = θ: rotation about X by -θ.
        let (s, c) = ((-theta / 2.0).sin(), (-theta / 2.0).cos());
        g.root(json!({"rotation": [s, 0.0, 0.0, c],
            "extensions": {"KHR_lights_punctual": {"light": light}}}));
        camera(&mut g, 2.0);
        let px = pixels(&load(&g), 2, Integrator::Path);
        // The mapped normal from the 8-bit texel (tangent +X, bitangent +Y, normal +Z).
        let dec = |v: u8| 2.0 * v as f64 / 255.0 - 1.0;
        let n = [dec(128) * scale as f64, dec(green) * scale as f64, dec(230)];
        let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
        let cos = (n[1] * l[1] + n[2] * l[2]) / len + n[0] * l[0] / len;
        let gain = 2.0 / (1.0 + n[2] / len);
        let expected = 0.8 / std::f64::consts::PI * cos.max(0.0) * gain;
        for p in &px {
            assert!(
                ((p[0] as f64) - expected).abs() < 1e-4 * expected.max(1e-3),
                "green {green} scale {scale}: pixel {} vs {expected}",
                p[0]
            );
        }
        results.push(px[0][0]);
    }
    // Green up is brighter than flat (128), which is brighter than green down.
    assert!(
        results[0] > results[3] && results[3] > results[1],
        "{results:?}"
    );
}

/// KHR_materials_volume: a slab of thickness 0.5 of a non-refracting (ior 1) transmissive
/// material with attenuationColor c at attenuationDistance 0.25, in front of an emissive
/// wall of radiance 1: the image is exp(-σ 0.5) = c² per channel exactly (Beer–Lambert).
#[test]
fn volume_absorption_follows_beer_lambert_through_a_slab() {
    let c = [0.8f32, 0.5, 0.2];
    let mut g = Gen::new();
    for e in [
        "KHR_materials_transmission",
        "KHR_materials_volume",
        "KHR_materials_ior",
    ] {
        g.uses(e);
    }
    let wall = emitter(&mut g, [1.0; 3], None);
    quad(&mut g, wall, (-5.0, 6.0, -5.0, 6.0, -2.0), |x, y| [x, y]);
    let glass = g.push(
        "materials",
        json!({"pbrMetallicRoughness": {"baseColorFactor": [1.0, 1.0, 1.0, 1.0],
            "metallicFactor": 0.0, "roughnessFactor": 0.0},
            "extensions": {"KHR_materials_transmission": {"transmissionFactor": 1.0},
                "KHR_materials_ior": {"ior": 1.0},
                "KHR_materials_volume": {"thicknessFactor": 0.5, "attenuationDistance": 0.25,
                    "attenuationColor": c}}}),
    );
    // Front face at z = 0 (normal +Z) and back face at z = -0.5 (normal -Z): a slab whose
    // outward normals point away from its inside. The camera is far away, so every ray
    // crosses the slab within 0.01° of the normal (path length 0.5 to 1e-8).
    quad(&mut g, glass, (-5.0, 6.0, -5.0, 6.0, 0.0), |x, y| [x, y]);
    let pos = g.positions(&[
        [-5.0, -5.0, -0.5],
        [-5.0, 6.0, -0.5],
        [6.0, 6.0, -0.5],
        [6.0, -5.0, -0.5],
    ]);
    let normal = g.vec3(&[[0.0, 0.0, -1.0]; 4]);
    let idx = g.indices_u16(&[0, 1, 2, 0, 2, 3]);
    let back = g.push(
        "meshes",
        json!({"primitives": [{"attributes": {"POSITION": pos, "NORMAL": normal}, "indices": idx, "material": glass}]}),
    );
    g.root(json!({"mesh": back}));
    camera(&mut g, 3000.0);
    let scene = load(&g);
    for integrator in [Integrator::Path, Integrator::Bdpt] {
        let px = pixels(&scene, 4, integrator);
        for p in &px {
            for k in 0..3 {
                let want = c[k] * c[k];
                assert!(
                    (p[k] - want).abs() < 1e-4,
                    "{integrator:?} channel {k}: {} vs {want}",
                    p[k]
                );
            }
        }
    }
}

/// A panel at z = 1 facing down over a floor, emitting through a 2x1 texture whose left
/// texel is white and right texel black (nearest), against a panel of the left half's
/// size without a texture: the floor sees the same light, whichever way the integrator
/// finds it (path tracing with next-event estimation, BDPT with light tracing). z-test
/// of the two image means.
#[test]
fn a_textured_emitter_lights_like_the_untextured_emitter_of_its_lit_part() {
    let build = |textured: bool| {
        let mut g = Gen::new();
        g.uses("KHR_materials_specular");
        let floor = g.push(
            "materials",
            json!({"pbrMetallicRoughness": {"baseColorFactor": [0.8, 0.8, 0.8, 1.0], "metallicFactor": 0.0},
                "extensions": {"KHR_materials_specular": {"specularFactor": 0.0}}}),
        );
        quad(&mut g, floor, (-1.0, 2.0, -1.0, 2.0, 0.0), |x, y| [x, y]);
        let (x1, light) = if textured {
            let png = png_rgb8(2, 1, &[255, 255, 255, 0, 0, 0]);
            let t = texture(&mut g, &png, json!({"magFilter": 9728, "wrapS": 33071}));
            (1.0, emitter(&mut g, [4.0; 3], Some(json!({"index": t}))))
        } else {
            (0.5, emitter(&mut g, [4.0; 3], None))
        };
        // Facing down (-Z): the quad's corners in clockwise order seen from above.
        let corners = [[0.0, 0.0], [0.0, 1.0], [x1, 1.0], [x1, 0.0]];
        let pos = g.positions(&corners.map(|[x, y]| [x, y, 1.0]));
        let uv = g.vec2(&corners.map(|[x, _]| [x, 0.5]));
        let idx = g.indices_u16(&[0, 1, 2, 0, 2, 3]);
        let mesh = g.push(
            "meshes",
            json!({"primitives": [{"attributes": {"POSITION": pos, "TEXCOORD_0": uv}, "indices": idx, "material": light}]}),
        );
        g.root(json!({"mesh": mesh}));
        camera(&mut g, 0.9);
        load(&g)
    };
    let (textured, plain) = (build(true), build(false));
    for integrator in [Integrator::Path, Integrator::Bdpt] {
        let a = render(&textured, SIDE, SIDE, 64, &config(integrator));
        let b = render(&plain, SIDE, SIDE, 64, &config(integrator));
        for c in 0..3 {
            let ((ma, sa), (mb, sb)) = (image_mean(&a, c), image_mean(&b, c));
            let z = (ma - mb) / (sa * sa + sb * sb).sqrt();
            eprintln!("{integrator:?} channel {c}: textured {ma:.4} ± {sa:.4}, half panel {mb:.4} ± {sb:.4} (z = {z:.2})");
            assert!(z.abs() < 4.0, "{integrator:?}: {ma} ± {sa} vs {mb} ± {sb}");
            assert!(ma > 0.01);
        }
    }
}

/// A `COLOR_0` accessor with the same colour at each of 4 vertices, as `component_type`
/// (5126 float, 5121 unsigned byte, 5123 unsigned short; the integers normalized).
fn vertex_colors(g: &mut Gen, rgba: [f32; 4], vec4: bool, component_type: u32) -> usize {
    let n = if vec4 { 4 } else { 3 };
    let mut bytes = Vec::new();
    for _ in 0..4 {
        for &c in &rgba[..n] {
            match component_type {
                5126 => bytes.extend_from_slice(&c.to_le_bytes()),
                5121 => bytes.push((c * 255.0).round() as u8),
                _ => bytes.extend_from_slice(&((c * 65535.0).round() as u16).to_le_bytes()),
            }
        }
    }
    let view = g.view(&bytes);
    g.push(
        "accessors",
        json!({"bufferView": view, "componentType": component_type, "count": 4,
            "type": if vec4 { "VEC4" } else { "VEC3" }, "normalized": component_type != 5126}),
    )
}

/// glTF `COLOR_0` multiplies the base colour and its alpha (spec "Metallic-Roughness
/// Material"): a Lambertian plane of base colour 0.8 with one vertex colour `c` at every
/// vertex, lit head-on by a directional light of irradiance 1, has radiance exactly
/// `0.8 c / π` (one delta light, nothing to bounce off), for float, normalized byte and
/// normalized short colours, VEC3 and VEC4; under alpha MASK a vertex alpha below the
/// cutoff cuts the plane out (black), above it keeps it.
#[test]
fn vertex_colours_multiply_base_colour_and_alpha() {
    let scene = |rgba: [f32; 4], vec4: bool, ct: u32, mask: bool| {
        let mut g = Gen::new();
        g.uses("KHR_materials_specular");
        g.uses("KHR_lights_punctual");
        let mut m = json!({"pbrMetallicRoughness": {"baseColorFactor": [0.8, 0.8, 0.8, 1.0],
                "metallicFactor": 0.0},
            "extensions": {"KHR_materials_specular": {"specularFactor": 0.0}}});
        if mask {
            m["alphaMode"] = json!("MASK");
        }
        let mat = g.push("materials", m);
        let corners = [[-1.0, -1.0], [2.0, -1.0], [2.0, 2.0], [-1.0, 2.0]];
        let pos = g.positions(&corners.map(|[x, y]| [x, y, 0.0]));
        let normal = g.vec3(&[[0.0, 0.0, 1.0]; 4]);
        let color = vertex_colors(&mut g, rgba, vec4, ct);
        let idx = g.indices_u16(&[0, 1, 2, 0, 2, 3]);
        let mesh = g.push(
            "meshes",
            json!({"primitives": [{"attributes": {"POSITION": pos, "NORMAL": normal,
                "COLOR_0": color}, "indices": idx, "material": mat}]}),
        );
        g.root(json!({"mesh": mesh}));
        // 683 lux = 1 W/m²; the light's -Z travels straight down onto the plane.
        let light = g.light(json!({"type": "directional", "intensity": 683.0}));
        g.root(json!({"extensions": {"KHR_lights_punctual": {"light": light}}}));
        camera(&mut g, 2.0);
        load(&g)
    };
    let rgba = [0.2, 0.6, 1.0, 1.0];
    for (ct, vec4) in [(5126, false), (5126, true), (5121, true), (5123, false)] {
        let px = pixels(&scene(rgba, vec4, ct, false), 2, Integrator::Path);
        // What the file holds after quantisation to the component type.
        let q = |c: f32| match ct {
            5121 => (c * 255.0).round() / 255.0,
            5123 => (c * 65535.0).round() / 65535.0,
            _ => c,
        };
        for p in &px {
            for k in 0..3 {
                let want = 0.8 * q(rgba[k]) / std::f32::consts::PI;
                assert!(
                    (p[k] - want).abs() < 1e-4 * want,
                    "component type {ct} VEC{}: channel {k} {} vs {want}",
                    if vec4 { 4 } else { 3 },
                    p[k]
                );
            }
        }
    }
    // MASK (cutoff 0.5): vertex alpha 0.2 lets every ray through, 0.8 keeps the plane.
    for (alpha, visible) in [(0.2, false), (0.8, true)] {
        let px = pixels(
            &scene([1.0, 1.0, 1.0, alpha], true, 5121, true),
            2,
            Integrator::Path,
        );
        assert!(
            px.iter().all(|p| (p[0] > 0.2) == visible),
            "vertex alpha {alpha}: {:?}",
            px[0]
        );
    }
}

/// Khronos' BoxVertexColors (tests/fixtures/khronos, CC0): `COLOR_0` is each vertex's
/// position, so the cube is black at the origin's corner and white at (1, 1, 1). Under a
/// white uniform environment its faces show those colours (the default material is a
/// rough metal of base colour × vertex colour), not the plain grey it rendered as when
/// vertex colours were ignored.
#[test]
fn khronos_box_vertex_colors_shows_its_colours() {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../tests/fixtures/khronos/BoxVertexColors.gltf"
    );
    let mut scene = tessera_scene::load(path).unwrap();
    let mesh = &scene.meshes[0];
    let colors = mesh.colors.as_ref().expect("COLOR_0 is read");
    for (c, p) in colors.iter().zip(&mesh.positions) {
        assert!(
            (c.truncate() - p.abs()).abs().max_element() < 1e-6 && c.w == 1.0,
            "{c} at {p}"
        );
    }
    scene.environment = Some(glam::Vec3::ONE);
    let px = pixels(&scene, 16, Integrator::Path);
    // Some pixel is strongly coloured: one channel well above another.
    let chroma = px
        .iter()
        .map(|p| {
            let (lo, hi) = (p[0].min(p[1]).min(p[2]), p[0].max(p[1]).max(p[2]));
            hi - lo
        })
        .fold(0.0f32, f32::max);
    assert!(
        chroma > 0.3,
        "the cube renders grey: largest channel spread {chroma}"
    );
}
