//! glTF import tests: documents are generated programmatically (see `gltf_gen`) as `.gltf`
//! with embedded base64 buffers, `.gltf` with external files, and `.glb`.

use glam::{Vec2, Vec3, Vec4};
use serde_json::json;
use std::f32::consts::{FRAC_1_SQRT_2, FRAC_PI_4};
use std::path::{Path, PathBuf};
use tessera_scene::gltf_import::{load_path, load_slice, photometric_to_radiometric};
use tessera_scene::{
    builtin, GltfMaterial, MaterialKind, PunctualLight, Scene, SceneError, Wrap, MAX_IMAGE_TEXELS,
    MAX_INPUT_BYTES,
};
use tessera_testkit::gltf_gen::{base64, png_grey16, png_rgb8, png_zeros, scratch_dir, Gen};

const TRI: [[f32; 3]; 3] = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];

fn load(bytes: &[u8]) -> Result<Scene, SceneError> {
    load_slice(bytes, "test.gltf", None, None)
}

/// Loads the document both as .gltf (embedded buffer) and as .glb; both must succeed.
fn load_both(g: &Gen) -> [Scene; 2] {
    let a = load(&g.gltf()).unwrap_or_else(|e| panic!(".gltf failed: {e}"));
    let b =
        load_slice(&g.glb(), "test.glb", None, None).unwrap_or_else(|e| panic!(".glb failed: {e}"));
    [a, b]
}

/// The error message of a load that must fail.
fn error_of(r: Result<Scene, SceneError>) -> String {
    match r {
        Ok(s) => panic!("expected an error, loaded {} triangles", s.triangle_count()),
        Err(e) => e.to_string(),
    }
}

/// Asserts that the message contains every fragment.
fn assert_mentions(message: &str, fragments: &[&str]) {
    for f in fragments {
        assert!(
            message.contains(f),
            "error {message:?} does not mention {f:?}"
        );
    }
}

fn close(a: Vec3, b: Vec3, tol: f32) -> bool {
    (a - b).abs().max_element() <= tol
}

/// One triangle with a material, under a root node: the base of the malformed-input tests.
fn basic() -> Gen {
    let mut g = Gen::new();
    let mat = g.push(
        "materials",
        json!({"name": "grey", "pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.5, 0.5, 1.0]}}),
    );
    let m = g.triangle_mesh("tri", &TRI, Some(&[0, 1, 2]), Some(mat));
    g.root(json!({"name": "root", "mesh": m}));
    g
}

#[test]
fn basic_document_loads_in_every_container() {
    let g = basic();
    for s in load_both(&g) {
        assert_eq!(s.triangle_count(), 1);
        assert_eq!(s.meshes[0].name, "mesh 0 'tri' primitive 0");
        assert_eq!(s.meshes[0].material, 0);
        let g = s.materials[0].as_gltf().expect("a glTF material");
        assert_eq!(g.base_color, Vec3::splat(0.5));
        // glTF defaults (spec "Metallic-Roughness Material"), and KHR_materials_specular's
        // default factor.
        assert_eq!(
            (g.metallic, g.roughness, g.transmission, g.ior, g.specular),
            (1.0, 1.0, 0.0, 1.5, 1.0)
        );
        assert!(g.base_color_texture.is_none());
        assert_eq!(g.alpha_mode, tessera_scene::AlphaMode::Opaque);
    }
    // And from an external .bin next to the .gltf, including a percent-encoded file name.
    let dir = scratch_dir("external");
    let path = g.write_external(&dir, "scene.gltf", "my%20data.bin", Some("my data.bin"));
    let s = load_path(&path, None).unwrap();
    assert_eq!(s.triangle_count(), 1);
    // Through the crate's front door too.
    let s = tessera_scene::load(path.to_str().unwrap()).unwrap();
    assert_eq!(s.triangle_count(), 1);
    // Parent directories are fine for files on disk.
    std::fs::create_dir_all(dir.join("sub")).unwrap();
    let path = g.write_external(&dir.join("sub"), "up.gltf", "../my%20data.bin", None);
    assert_eq!(load_path(&path, None).unwrap().triangle_count(), 1);
}

#[test]
fn node_hierarchy_transforms_are_applied() {
    let s = FRAC_1_SQRT_2;
    for use_matrix in [false, true] {
        let mut g = Gen::new();
        let m = g.triangle_mesh("tri", &TRI, Some(&[0, 1, 2]), None);
        let normals = g.vec3(&[[1.0, 0.0, 0.0]; 3]);
        g.doc["meshes"][m]["primitives"][0]["attributes"]["NORMAL"] = json!(normals);
        let child = g.node(json!({"mesh": m, "scale": [2.0, 2.0, 2.0]}));
        if use_matrix {
            // T(1,2,3) * Rz(90°), column-major.
            g.root(json!({"matrix": [0.0, 1.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 1.0, 2.0, 3.0, 1.0],
                          "children": [child]}));
        } else {
            g.root(json!({"translation": [1.0, 2.0, 3.0], "rotation": [0.0, 0.0, s, s], "children": [child]}));
        }
        for scene in load_both(&g) {
            let mesh = &scene.meshes[0];
            // (1,0,0) -> scale 2 -> (2,0,0) -> Rz(90°) -> (0,2,0) -> +(1,2,3).
            assert!(
                close(mesh.positions[1], Vec3::new(1.0, 4.0, 3.0), 1e-5),
                "{:?}",
                mesh.positions
            );
            assert!(
                close(mesh.positions[2], Vec3::new(-1.0, 2.0, 3.0), 1e-5),
                "{:?}",
                mesh.positions
            );
            assert!(close(mesh.positions[0], Vec3::new(1.0, 2.0, 3.0), 1e-5));
            let n = mesh.normals.as_ref().unwrap();
            assert!(close(n[0], Vec3::Y, 1e-5), "{n:?}");
            assert_eq!(mesh.indices, vec![[0, 1, 2]]);
            // Primitives without a material get the glTF default material.
            let mat = &scene.materials[mesh.material as usize];
            assert!(mat
                .as_gltf()
                .is_some_and(|g| (g.metallic, g.roughness) == (1.0, 1.0)));
            assert_eq!(mat.kind, scene.materials.last().unwrap().kind);
        }
    }
}

#[test]
fn non_uniform_scale_transforms_normals_by_the_inverse_transpose() {
    let mut g = Gen::new();
    let m = g.triangle_mesh("tri", &TRI, None, None);
    let n = Vec3::new(1.0, 1.0, 0.0).normalize();
    let normals = g.vec3(&[n.to_array(); 3]);
    g.doc["meshes"][m]["primitives"][0]["attributes"]["NORMAL"] = json!(normals);
    g.root(json!({"mesh": m, "scale": [2.0, 1.0, 1.0]}));
    let [scene, _] = load_both(&g);
    let got = scene.meshes[0].normals.as_ref().unwrap()[0];
    // The surface x + y = c becomes x/2 + y = c: normal (1/2, 1, 0) normalized.
    assert!(
        close(got, Vec3::new(0.5, 1.0, 0.0).normalize(), 1e-5),
        "{got}"
    );
    // Implicit indices 0..n.
    assert_eq!(scene.meshes[0].indices, vec![[0, 1, 2]]);
}

#[test]
fn negative_scale_flips_winding() {
    let geometric_normal = |s: &Scene| {
        let m = &s.meshes[0];
        let [a, b, c] = m.indices[0].map(|i| m.positions[i as usize]);
        (b - a).cross(c - a).normalize()
    };
    for (scale, expect_flip) in [
        ([1.0, 1.0, 1.0], false),
        ([-1.0, 1.0, 1.0], true),
        ([-1.0, -1.0, 1.0], false),
    ] {
        let mut g = Gen::new();
        let m = g.triangle_mesh("tri", &TRI, Some(&[0, 1, 2]), None);
        g.root(json!({"mesh": m, "scale": scale}));
        for s in load_both(&g) {
            // The triangle is counter-clockwise seen from +Z and must stay so (a mirror in x
            // maps +Z to +Z, so the front still faces +Z).
            assert!(
                close(geometric_normal(&s), Vec3::Z, 1e-6),
                "scale {scale:?}: {:?}",
                s.meshes[0]
            );
            let flipped = s.meshes[0].indices[0] == [0, 2, 1];
            assert_eq!(flipped, expect_flip, "scale {scale:?}");
        }
    }
    // A mirroring parent with a mirroring child cancels out.
    let mut g = Gen::new();
    let m = g.triangle_mesh("tri", &TRI, Some(&[0, 1, 2]), None);
    let child = g.node(json!({"mesh": m, "scale": [1.0, 1.0, -1.0]}));
    g.root(json!({"scale": [-1.0, 1.0, 1.0], "children": [child]}));
    let [s, _] = load_both(&g);
    assert_eq!(s.meshes[0].indices[0], [0, 1, 2]);
    assert!(close(geometric_normal(&s), -Vec3::Z, 1e-6));
}

fn two_camera_doc() -> Gen {
    let mut g = basic();
    let c0 = g.push(
        "cameras",
        json!({"name": "first", "type": "perspective",
        "perspective": {"yfov": 0.5, "aspectRatio": 1.5, "znear": 0.1}}),
    );
    let c1 = g.push(
        "cameras",
        json!({"name": "second", "type": "perspective",
        "perspective": {"yfov": 0.8, "znear": 0.1, "zfar": 100.0}}),
    );
    g.push(
        "cameras",
        json!({"name": "ortho", "type": "orthographic",
        "orthographic": {"xmag": 1.0, "ymag": 1.0, "znear": 0.1, "zfar": 10.0}}),
    );
    g.root(json!({"name": "CamA", "camera": c0, "translation": [0.0, 0.0, 5.0]}));
    let s = FRAC_1_SQRT_2;
    // Rotated 90° about Y: looks down world -X.
    g.root(json!({"name": "CamB", "camera": c1, "translation": [1.0, 2.0, 3.0], "rotation": [0.0, s, 0.0, s], "scale": [3.0, 3.0, 3.0]}));
    g
}

#[test]
fn camera_is_selected_by_camera_or_node_name() {
    let g = two_camera_doc();
    let bytes = g.gltf();
    let first = load(&bytes).unwrap();
    assert_eq!(first.camera.name.as_deref(), Some("first"));
    assert_eq!(first.camera.yfov, 0.5);
    assert_eq!(first.camera.aspect_ratio, Some(1.5));
    assert_eq!(first.default_resolution, (768, 512));
    assert!(close(
        first.camera.world_from_camera.w_axis.truncate(),
        Vec3::new(0.0, 0.0, 5.0),
        1e-6
    ));

    for name in ["second", "CamB"] {
        let s = load_slice(&bytes, "test.gltf", None, Some(name)).unwrap();
        assert_eq!(s.camera.yfov, 0.8);
        assert_eq!(s.camera.aspect_ratio, None);
        assert_eq!(s.default_resolution, (512, 512));
        let m = s.camera.world_from_camera;
        assert!(close(m.w_axis.truncate(), Vec3::new(1.0, 2.0, 3.0), 1e-6));
        // Looks down -X (the camera's -Z), with +Y up, and the node's scale removed.
        assert!(close(-m.z_axis.truncate(), -Vec3::X, 1e-6), "{m}");
        assert!(close(m.y_axis.truncate(), Vec3::Y, 1e-6), "{m}");
        assert!((m.determinant() - 1.0).abs() < 1e-5);
    }

    let e = error_of(load_slice(&bytes, "test.gltf", None, Some("nope")));
    assert_mentions(
        &e,
        &["test.gltf", "nope", "first", "second", "CamA", "CamB"],
    );
    let e = error_of(load_slice(&bytes, "test.gltf", None, Some("ortho")));
    assert_mentions(&e, &["ortho", "orthographic"]);
    // Without cameras in the file, any name is unknown.
    let e = error_of(load_slice(
        &basic().gltf(),
        "test.gltf",
        None,
        Some("first"),
    ));
    assert_mentions(&e, &["first", "no perspective cameras"]);
}

#[test]
fn missing_camera_is_synthesized_to_frame_the_scene() {
    let mut g = Gen::new();
    let m = g.triangle_mesh("tri", &TRI, None, None);
    g.root(json!({"mesh": m, "translation": [10.0, 0.0, -4.0]}));
    let [s, _] = load_both(&g);
    let cam = &s.camera;
    assert!((cam.yfov - 45f32.to_radians()).abs() < 1e-6);
    let eye = cam.world_from_camera.w_axis.truncate();
    // Looking down -Z from the +Z side of the geometry, centred on it.
    assert_eq!(cam.world_from_camera.z_axis.truncate(), Vec3::Z);
    assert!(
        close(eye.truncate().extend(0.0), Vec3::new(10.5, 0.5, 0.0), 1e-5),
        "{eye}"
    );
    assert!(eye.z > -4.0 + 0.5);
    // Every vertex is inside the field of view.
    let inv = cam.world_from_camera.inverse();
    for p in &s.meshes[0].positions {
        let q = inv.transform_point3(*p);
        assert!(
            q.z < 0.0
                && (q.y / -q.z).abs() <= (cam.yfov / 2.0).tan()
                && (q.x / -q.z).abs() <= (cam.yfov / 2.0).tan()
        );
    }
    assert_eq!(s.default_resolution, (512, 512));
}

#[test]
fn emissive_strength_multiplies_emissive_factor() {
    let mut g = Gen::new();
    g.uses("KHR_materials_emissive_strength");
    let strong = g.push("materials", json!({"emissiveFactor": [1.0, 0.5, 0.25],
        "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 4.0}}, "doubleSided": true}));
    let plain = g.push("materials", json!({"emissiveFactor": [1.0, 0.5, 0.25]}));
    let m0 = g.triangle_mesh("a", &TRI, None, Some(strong));
    let m1 = g.triangle_mesh("b", &TRI, None, Some(plain));
    g.root(json!({"mesh": m0}));
    g.root(json!({"mesh": m1}));
    for s in load_both(&g) {
        assert_eq!(s.materials[0].emission, Vec3::new(4.0, 2.0, 1.0));
        assert!(s.materials[0].double_sided);
        assert_eq!(s.materials[1].emission, Vec3::new(1.0, 0.5, 0.25));
        assert!(!s.materials[1].double_sided);
        assert_eq!(s.meshes[1].material, 1);
    }
}

#[test]
fn transmission_and_ior_extensions_are_read() {
    let mut g = Gen::new();
    g.uses("KHR_materials_transmission");
    g.uses("KHR_materials_ior");
    let glass = g.push("materials", json!({"pbrMetallicRoughness": {"metallicFactor": 0.0, "roughnessFactor": 0.0},
        "extensions": {"KHR_materials_transmission": {"transmissionFactor": 1.0}, "KHR_materials_ior": {"ior": 1.33}}}));
    let m = g.triangle_mesh("a", &TRI, None, Some(glass));
    g.root(json!({"mesh": m}));
    let [s, _] = load_both(&g);
    assert_eq!(
        s.materials[0].kind,
        MaterialKind::Gltf(Box::new(GltfMaterial {
            metallic: 0.0,
            roughness: 0.0,
            transmission: 1.0,
            ior: 1.33,
            ..GltfMaterial::default()
        }))
    );
}

/// Blender writes `KHR_materials_specular` with `specularFactor: 0` for a Specular IOR
/// Level of 0 (a pure diffuse surface); the factor is read, 1 without the extension.
#[test]
fn specular_extension_factor_is_read() {
    let mut g = Gen::new();
    g.uses("KHR_materials_specular");
    let matte = g.push("materials", json!({"pbrMetallicRoughness": {"metallicFactor": 0.0, "roughnessFactor": 0.5},
        "extensions": {"KHR_materials_specular": {"specularFactor": 0.0, "specularColorFactor": [1.0, 1.0, 1.0]}}}));
    let half = g.push(
        "materials",
        json!({"pbrMetallicRoughness": {"metallicFactor": 0.0},
        "extensions": {"KHR_materials_specular": {"specularFactor": 0.5}}}),
    );
    let m0 = g.triangle_mesh("a", &TRI, None, Some(matte));
    let m1 = g.triangle_mesh("b", &TRI, None, Some(half));
    g.root(json!({"mesh": m0}));
    g.root(json!({"mesh": m1}));
    for s in load_both(&g) {
        for (i, want) in [(0, 0.0), (1, 0.5)] {
            assert_eq!(s.materials[i].as_gltf().unwrap().specular, want);
        }
    }
    // A factor outside [0, 1] is refused naming the material.
    g.push(
        "materials",
        json!({"extensions": {"KHR_materials_specular": {"specularFactor": 1.5}}}),
    );
    let e = error_of(load(&g.gltf()));
    assert!(e.contains("material 2"), "{e}");
}

#[test]
fn punctual_lights_are_converted_to_radiometric_units() {
    let mut g = Gen::new();
    let point = g.light(
        json!({"type": "point", "color": [1.0, 0.5, 0.0], "intensity": 1366.0, "range": 3.0}),
    );
    let sun = g.light(json!({"type": "directional", "intensity": 2049.0}));
    let spot = g.light(json!({"type": "spot", "intensity": 683.0, "spot": {}}));
    let narrow = g.light(json!({"type": "spot", "color": [0.0, 1.0, 0.0], "spot": {"innerConeAngle": 0.2, "outerConeAngle": 0.6}}));
    let s = FRAC_1_SQRT_2;
    g.root(json!({"translation": [1.0, 2.0, 3.0], "extensions": {"KHR_lights_punctual": {"light": point}}}));
    // Rotated -90° about X: local -Z points down.
    g.root(json!({"rotation": [-s, 0.0, 0.0, s], "extensions": {"KHR_lights_punctual": {"light": sun}}}));
    // A spot in a translated parent, rotated 90° about Y: local -Z points along world -X.
    let child = g.node(
        json!({"translation": [1.0, 0.0, 0.0], "rotation": [0.0, s, 0.0, s],
        "extensions": {"KHR_lights_punctual": {"light": spot}}}),
    );
    g.root(json!({"translation": [0.0, 5.0, 0.0], "children": [child]}));
    g.root(json!({"extensions": {"KHR_lights_punctual": {"light": narrow}}}));
    for scene in load_both(&g) {
        assert_eq!(scene.lights.len(), 4);
        // A scene with lights and no geometry is allowed.
        assert_eq!(scene.triangle_count(), 0);
        match scene.lights[0] {
            PunctualLight::Point {
                position,
                intensity,
            } => {
                assert!(close(position, Vec3::new(1.0, 2.0, 3.0), 1e-6));
                // 1366 cd / 683 lm/W = 2 W/sr, times the colour.
                assert!(
                    close(intensity, Vec3::new(2.0, 1.0, 0.0), 1e-6),
                    "{intensity}"
                );
            }
            l => panic!("{l:?}"),
        }
        match scene.lights[1] {
            PunctualLight::Directional {
                direction,
                irradiance,
            } => {
                assert!(close(direction, -Vec3::Y, 1e-6), "{direction}");
                assert!(close(irradiance, Vec3::splat(3.0), 1e-6), "{irradiance}");
            }
            l => panic!("{l:?}"),
        }
        match scene.lights[2] {
            PunctualLight::Spot {
                position,
                direction,
                intensity,
                inner_angle,
                outer_angle,
            } => {
                assert!(
                    close(position, Vec3::new(1.0, 5.0, 0.0), 1e-6),
                    "{position}"
                );
                assert!(close(direction, -Vec3::X, 1e-6), "{direction}");
                assert!(close(intensity, Vec3::ONE, 1e-6));
                assert_eq!((inner_angle, outer_angle), (0.0, FRAC_PI_4));
            }
            l => panic!("{l:?}"),
        }
        match scene.lights[3] {
            PunctualLight::Spot {
                direction,
                intensity,
                inner_angle,
                outer_angle,
                ..
            } => {
                assert_eq!(direction, -Vec3::Z);
                // Default intensity 1 cd.
                assert!(close(intensity, Vec3::new(0.0, 1.0 / 683.0, 0.0), 1e-9));
                assert_eq!((inner_angle, outer_angle), (0.2, 0.6));
            }
            l => panic!("{l:?}"),
        }
    }
    assert_eq!(
        photometric_to_radiometric([1.0, 1.0, 1.0], 683.0),
        Vec3::ONE
    );
}

fn srgb_eotf(v: f64) -> f32 {
    (if v <= 0.04045 {
        v / 12.92
    } else {
        ((v + 0.055) / 1.055).powf(2.4)
    }) as f32
}

#[test]
fn base_color_textures_are_decoded_from_srgb() {
    let rgb: [u8; 12] = [0, 0, 0, 128, 128, 128, 255, 255, 255, 10, 200, 50];
    let png = png_rgb8(2, 2, &rgb);
    let grey = png_grey16(1, 1, &[32768]);
    let mut g = Gen::new();
    let view = g.view(&png);
    let img_view = g.push(
        "images",
        json!({"bufferView": view, "mimeType": "image/png"}),
    );
    let img_uri = g.push(
        "images",
        json!({"uri": format!("data:image/png;base64,{}", base64(&png))}),
    );
    let img_grey = g.push(
        "images",
        json!({"uri": format!("data:image/png;base64,{}", base64(&grey))}),
    );
    let clamp = g.push("samplers", json!({"wrapS": 33071, "wrapT": 33071}));
    let t_clamp = g.push("textures", json!({"source": img_view, "sampler": clamp}));
    let t_repeat = g.push("textures", json!({"source": img_uri}));
    let t_grey = g.push("textures", json!({"source": img_grey}));
    let mut materials = Vec::new();
    for t in [t_clamp, t_repeat, t_grey] {
        materials.push(g.push(
            "materials",
            json!({"pbrMetallicRoughness": {"baseColorTexture": {"index": t}}}),
        ));
    }
    let uvs = [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]];
    for m in materials {
        let mesh = g.triangle_mesh("textured", &TRI, None, Some(m));
        let uv = g.vec2(&uvs);
        g.doc["meshes"][mesh]["primitives"][0]["attributes"]["TEXCOORD_0"] = json!(uv);
        g.root(json!({"mesh": mesh}));
    }
    let expected: Vec<Vec3> = rgb
        .chunks(3)
        .map(|p| {
            Vec3::from(
                <[u8; 3]>::try_from(p)
                    .unwrap()
                    .map(|c| srgb_eotf(c as f64 / 255.0)),
            )
        })
        .collect();
    assert_eq!(expected[0], Vec3::ZERO);
    assert!((expected[1].x - 0.215_861).abs() < 1e-5);
    for s in load_both(&g) {
        assert_eq!(s.textures.len(), 3);
        // The PNG is decoded once per image; the texture carries the sampler.
        assert_eq!(s.images.len(), 3);
        for (mi, (wrap, texels)) in [(Wrap::ClampToEdge, &expected), (Wrap::Repeat, &expected)]
            .into_iter()
            .enumerate()
        {
            let t = s.materials[mi]
                .as_gltf()
                .and_then(|g| g.base_color_texture)
                .unwrap_or_else(|| panic!("material {mi} has no texture"));
            let tex = &s.textures[t.texture as usize];
            assert_eq!((tex.wrap_s, tex.wrap_t), (wrap, wrap));
            let im = &s.images[tex.image as usize];
            assert_eq!((im.width, im.height), (2, 2));
            for (k, want) in texels.iter().enumerate() {
                let got = im.texel(k as u32 % 2, k as u32 / 2, true).truncate();
                assert!(close(got, *want, 1e-6), "{got} vs {want}");
            }
        }
        let t = s.materials[2]
            .as_gltf()
            .and_then(|g| g.base_color_texture)
            .expect("no grey texture");
        let im = &s.images[s.textures[t.texture as usize].image as usize];
        let got = im.texel(0, 0, true).truncate();
        assert!(
            close(got, Vec3::splat(srgb_eotf(32768.0 / 65535.0)), 1e-6),
            "{got}"
        );
        let uv: Vec<Vec2> = uvs.iter().map(|&u| Vec2::from(u)).collect();
        assert_eq!(s.meshes[0].uvs, vec![uv]);
    }
}

#[test]
fn non_triangle_primitives_are_rejected_with_their_names() {
    let mut g = basic();
    g.doc["meshes"][0]["primitives"][0]["mode"] = json!(3); // LINE_STRIP
    let e = error_of(load(&g.gltf()));
    assert_mentions(&e, &["test.gltf", "mesh 0 'tri' primitive 0", "LineStrip"]);
}

#[test]
fn empty_scene_is_an_error_unless_it_has_lights() {
    let g = Gen::new();
    let e = error_of(load(&g.gltf()));
    assert_mentions(&e, &["no geometry"]);
    let mut g = Gen::new();
    let l = g.light(json!({"type": "point"}));
    g.root(json!({"extensions": {"KHR_lights_punctual": {"light": l}}}));
    assert_eq!(load(&g.gltf()).unwrap().lights.len(), 1);
}

// ---------------------------------------------------------------------------------------
// Malformed input: always an error naming the element, never a panic.

#[test]
fn truncated_gltf_json_is_an_error() {
    let bytes = basic().gltf();
    for cut in [0, 1, bytes.len() / 4, bytes.len() / 2, bytes.len() - 2] {
        let e = error_of(load(&bytes[..cut]));
        assert_mentions(&e, &["test.gltf"]);
    }
}

#[test]
fn every_truncation_of_a_glb_is_an_error() {
    let bytes = basic().glb();
    assert!(load(&bytes).is_ok());
    for cut in 0..bytes.len() {
        let r = load_slice(&bytes[..cut], "cut.glb", None, None);
        assert!(r.is_err(), "prefix of {cut} bytes loaded");
    }
    let e = error_of(load_slice(
        &bytes[..bytes.len() - 10],
        "cut.glb",
        None,
        None,
    ));
    assert_mentions(&e, &["cut.glb", "truncated"]);
}

#[test]
fn corrupted_bytes_never_panic() {
    // Flip bits everywhere in a small .glb and a small .gltf: any outcome but a panic is fine.
    let mut g = basic();
    let c = g.push(
        "cameras",
        json!({"type": "perspective", "perspective": {"yfov": 0.5, "znear": 0.1}}),
    );
    g.root(json!({"camera": c}));
    let l = g.light(json!({"type": "spot", "spot": {}}));
    g.root(json!({"extensions": {"KHR_lights_punctual": {"light": l}}}));
    let png = png_rgb8(1, 1, &[1, 2, 3]);
    let v = g.view(&png);
    let i = g.push("images", json!({"bufferView": v, "mimeType": "image/png"}));
    let t = g.push("textures", json!({"source": i}));
    g.doc["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"] = json!({"index": t});
    for bytes in [
        g.glb(),
        serde_json::to_vec(&g.json_with_buffer(Some(format!("data:;base64,{}", base64(&g.bin)))))
            .unwrap(),
    ] {
        assert!(load(&bytes).is_ok());
        let mut caught_panics = 0;
        for i in 0..bytes.len() {
            for x in [0x01u8, 0x10, 0x80] {
                let mut b = bytes.clone();
                b[i] ^= x;
                if let Err(e) = load(&b) {
                    caught_panics += e.to_string().contains("made the reader fail") as usize;
                }
            }
        }
        println!("{caught_panics} corruptions were caught as panics");
    }
}

#[test]
fn accessor_past_its_buffer_is_an_error() {
    let mut g = basic();
    g.doc["accessors"][0]["count"] = json!(1000);
    let e = error_of(load(&g.gltf()));
    assert_mentions(
        &e,
        &[
            "accessor 0",
            "mesh 0 'tri' primitive 0 POSITION",
            "bufferView 0",
        ],
    );
    let mut g = basic();
    g.doc["accessors"][0]["byteOffset"] = json!(4096);
    assert_mentions(&error_of(load(&g.glb())), &["accessor 0"]);
    // A buffer view past the end of its buffer.
    let mut g = basic();
    g.doc["bufferViews"][1]["byteLength"] = json!(100000);
    assert_mentions(&error_of(load(&g.gltf())), &["bufferView 1", "buffer 0"]);
    // A huge count on a sparse accessor without a bufferView.
    let mut g = basic();
    g.doc["accessors"][0] = json!({"componentType": 5126, "count": 1u64 << 40, "type": "VEC3", "min": [0, 0, 0], "max": [1, 1, 1],
        "sparse": {"count": 1, "indices": {"bufferView": 1, "componentType": 5123}, "values": {"bufferView": 0}}});
    assert_mentions(&error_of(load(&g.gltf())), &["accessor 0", "too large"]);
}

#[test]
fn sparse_accessors_are_applied() {
    let mut g = basic();
    // Replace vertex 2 with (0, 5, 0) through a sparse substitution.
    let idx = g.view(&2u16.to_le_bytes());
    let val = g.view(
        &[0f32, 5.0, 0.0]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect::<Vec<u8>>(),
    );
    g.doc["accessors"][0]["sparse"] = json!({"count": 1, "indices": {"bufferView": idx, "componentType": 5123}, "values": {"bufferView": val}});
    let [s, _] = load_both(&g);
    assert_eq!(s.meshes[0].positions[2], Vec3::new(0.0, 5.0, 0.0));
    // A sparse index past the accessor count.
    let mut g2 = Gen::new();
    g2.doc = g.doc.clone();
    g2.bin = g.bin.clone();
    let bad = g2.view(&7u16.to_le_bytes());
    g2.doc["accessors"][0]["sparse"]["indices"]["bufferView"] = json!(bad);
    assert_mentions(&error_of(load(&g2.gltf())), &["accessor 0", "sparse index"]);
}

#[test]
fn index_past_vertex_count_is_an_error() {
    let mut g = Gen::new();
    let m = g.triangle_mesh("tri", &TRI, Some(&[0, 1, 7]), None);
    g.root(json!({"mesh": m}));
    let e = error_of(load(&g.gltf()));
    assert_mentions(&e, &["mesh 0 'tri' primitive 0", "= 7", "3 vertices"]);
    // Index count not a multiple of three.
    let mut g = Gen::new();
    let m = g.triangle_mesh("tri", &TRI, Some(&[0, 1, 2, 0]), None);
    g.root(json!({"mesh": m}));
    assert_mentions(&error_of(load(&g.gltf())), &["multiple of 3"]);
}

#[test]
fn non_finite_node_transforms_are_errors() {
    let mut g = basic();
    let mut matrix = vec![json!(0.0); 16];
    for d in [0, 5, 10, 15] {
        matrix[d] = json!(1.0);
    }
    matrix[12] = json!(1e39); // overflows f32: infinity
    g.doc["nodes"][0]["matrix"] = json!(matrix);
    let e = error_of(load(&g.gltf()));
    assert_mentions(&e, &["test.gltf", "node 0", "matrix"]);
    let mut g = basic();
    g.doc["nodes"][0]["translation"] = json!([0.0, -1e39, 0.0]);
    assert_mentions(&error_of(load(&g.glb())), &["node 0"]);
    // NaN itself is not JSON; it is still refused.
    let text = String::from_utf8(basic().gltf()).unwrap().replace(
        "\"name\": \"root\"",
        "\"name\": \"root\", \"scale\": [NaN, 1, 1]",
    );
    assert!(text.contains("NaN"));
    assert!(load(text.as_bytes()).is_err());
    // Overflow while composing transforms.
    let mut g = basic();
    g.doc["nodes"][0]["scale"] = json!([1e30, 1e30, 1e30]);
    let child = g.node(json!({"scale": [1e30, 1e30, 1e30], "mesh": 0}));
    g.doc["nodes"][0]["children"] = json!([child]);
    g.doc["nodes"][0].as_object_mut().unwrap().remove("mesh");
    assert_mentions(&error_of(load(&g.gltf())), &["node 1"]);
}

/// A finite but astronomically large scale (the robustness issue's poison scene:
/// `nodes[0].scale = [1e38, 1e38, 1e38]` made the BVH builder panic inside obvhs) is
/// refused at import, naming the node; the built-in bound also guards `Scene::validate`.
#[test]
fn coordinates_beyond_the_renderable_range_are_errors() {
    let mut g = basic();
    g.doc["nodes"][0]["scale"] = json!([1e38, 1e38, 1e38]);
    let e = error_of(load(&g.glb()));
    assert_mentions(&e, &["node 0", "beyond", "scale"]);
    // The same mesh used twice is an instanced prototype: its placements are checked too,
    // and the error names the node that places it.
    let mut g = basic();
    g.root(json!({"mesh": 0}));
    let s = load(&g.glb()).unwrap();
    assert_eq!((s.meshes.len(), s.instances.len()), (0, 2));
    g.doc["nodes"][1]["scale"] = json!([1e38, 1e38, 1e38]);
    let e = error_of(load(&g.glb()));
    assert_mentions(&e, &["node 1", "beyond", "scale"]);
    // Finite transforms whose product overflows f32 in world space name the node too.
    let mut g = basic();
    g.root(json!({"mesh": 0, "translation": [3e38, 0.0, 0.0], "scale": [1e3, 1.0, 1.0]}));
    assert_mentions(&error_of(load(&g.glb())), &["node 1"]);
    // EXT_mesh_gpu_instancing: the error names the node and the instance.
    let mut g = basic();
    g.uses("EXT_mesh_gpu_instancing");
    let t = g.vec3(&[[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 5e12, 0.0]]);
    g.doc["nodes"][0]["extensions"] =
        json!({"EXT_mesh_gpu_instancing": {"attributes": {"TRANSLATION": t}}});
    let e = error_of(load(&g.glb()));
    assert_mentions(&e, &["node 0 EXT_mesh_gpu_instancing instance 2", "beyond"]);
    // A NaN in a node matrix of an instancing node is refused before placement.
    let text = String::from_utf8(g.gltf()).unwrap().replace(
        "\"name\": \"root\"",
        "\"name\": \"root\", \"matrix\": [1,0,0,0, 0,1,0,0, 0,0,1,0, NaN,0,0,1]",
    );
    assert!(text.contains("NaN"));
    assert!(load(text.as_bytes()).is_err());
    let mut g = basic();
    g.root(
        json!({"mesh": 0, "matrix": [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0,
        1.0, 0.0, 0.0, 1e39, 0.0, 1.0]}),
    );
    assert_mentions(&error_of(load(&g.glb())), &["node 1", "matrix"]);
    // Large but sane scenes load.
    let mut g = basic();
    g.doc["nodes"][0]["scale"] = json!([1e9, 1e9, 1e9]);
    assert!(load(&g.glb()).is_ok());
}

#[test]
fn missing_external_buffer_names_the_uri() {
    let dir = scratch_dir("missing");
    let path = basic().write_external(&dir, "scene.gltf", "missing.bin", None);
    let e = error_of(load_path(&path, None));
    assert_mentions(&e, &["scene.gltf", "buffer 0", "missing.bin"]);
    // In memory without a base directory, external references are refused.
    let bytes = std::fs::read(&path).unwrap();
    assert_mentions(
        &error_of(load_slice(&bytes, "upload.gltf", None, None)),
        &["upload.gltf", "missing.bin", "base directory"],
    );
    // With a base directory, uploads may not escape it.
    let g = basic();
    std::fs::write(dir.join("data.bin"), &g.bin).unwrap();
    let escaping = serde_json::to_vec(&g.json_with_buffer(Some("../data.bin".into()))).unwrap();
    let sub = dir.join("sub");
    std::fs::create_dir_all(&sub).unwrap();
    assert_mentions(
        &error_of(load_slice(&escaping, "upload.gltf", Some(&sub), None)),
        &["inside the base directory"],
    );
    let inside = serde_json::to_vec(&g.json_with_buffer(Some("data.bin".into()))).unwrap();
    assert_eq!(
        load_slice(&inside, "upload.gltf", Some(&dir), None)
            .unwrap()
            .triangle_count(),
        1
    );
    // Other URI schemes are not fetched.
    let remote =
        serde_json::to_vec(&g.json_with_buffer(Some("https://example.com/data.bin".into())))
            .unwrap();
    assert_mentions(
        &error_of(load_slice(&remote, "upload.gltf", Some(&dir), None)),
        &["not supported"],
    );
}

#[test]
fn bad_percent_encoding_is_an_error() {
    let dir = scratch_dir("percent");
    for uri in ["bad%zz.bin", "bad%2", "%ff%fe.bin"] {
        let path = basic().write_external(&dir, "scene.gltf", uri, None);
        let e = error_of(load_path(&path, None));
        assert_mentions(&e, &["buffer 0", "percent"]);
    }
    // Bad base64 in a data URI.
    let g = basic();
    let bytes = serde_json::to_vec(
        &g.json_with_buffer(Some("data:application/octet-stream;base64,@@@@".into())),
    )
    .unwrap();
    assert_mentions(&error_of(load(&bytes)), &["buffer 0", "base64"]);
}

fn textured(image: serde_json::Value) -> Gen {
    let mut g = basic();
    let i = g.push("images", image);
    let t = g.push("textures", json!({"source": i}));
    g.doc["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"] = json!({"index": t});
    g
}

/// The robustness issue's decompression bombs: .glb files under 1 MB whose embedded PNG
/// decodes to 16384 x 16384 or 32768 x 8192 (256 Mi texels, 1 GiB as RGBA) are refused
/// from the PNG header, naming the image and the limit, before anything is decoded.
#[test]
fn decompression_bombs_are_refused_from_the_header() {
    for (w, h) in [(16384, 16384), (32768, 8192)] {
        let png = png_zeros(w, h);
        let mut g = basic();
        let v = g.view(&png);
        let mut g = {
            let i = g.push(
                "images",
                json!({"name": "bomb", "bufferView": v, "mimeType": "image/png"}),
            );
            let t = g.push("textures", json!({"source": i}));
            g.doc["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"] = json!({"index": t});
            g
        };
        let glb = g.glb();
        assert!(glb.len() < 1 << 20, "{w}x{h}: {} bytes", glb.len());
        let e = error_of(load(&glb));
        assert_mentions(
            &e,
            &[
                "image 0 'bomb'",
                &format!("{w}x{h}"),
                &format!("limit of {MAX_IMAGE_TEXELS} texels per image"),
            ],
        );
        // Without a name, the error names the index.
        g.doc["images"][0].as_object_mut().unwrap().remove("name");
        assert_mentions(&error_of(load(&g.glb())), &["image 0:"]);
    }
}

#[test]
fn image_with_buffer_view_but_no_mime_type_is_an_error() {
    let png = png_rgb8(1, 1, &[1, 2, 3]);
    let mut g = basic();
    let v = g.view(&png);
    let mut g = {
        let i = g.push("images", json!({"bufferView": v}));
        let t = g.push("textures", json!({"source": i}));
        g.doc["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"] = json!({"index": t});
        g
    };
    let e = error_of(load(&g.glb()));
    assert_mentions(&e, &["image 0", "mimeType"]);
    // With the media type it loads.
    g.doc["images"][0]["mimeType"] = json!("image/png");
    assert_eq!(load(&g.glb()).unwrap().textures.len(), 1);
}

#[test]
fn image_range_past_buffer_is_an_error() {
    let mut g = textured(json!({"bufferView": 0, "mimeType": "image/png"}));
    let v = g.push(
        "bufferViews",
        json!({"buffer": 0, "byteOffset": 64, "byteLength": 1 << 20}),
    );
    g.doc["images"][0]["bufferView"] = json!(v);
    let e = error_of(load(&g.glb()));
    assert_mentions(
        &e,
        &[
            "image 0",
            &format!("bufferView {v}"),
            "past the end of buffer 0",
        ],
    );
    // Bytes that are not an image.
    let g = textured(json!({"bufferView": 0, "mimeType": "image/png"}));
    assert_mentions(&error_of(load(&g.glb())), &["image 0", "not a PNG or JPEG"]);
    // A PNG whose data is cut short.
    let png = png_rgb8(4, 4, &[7; 48]);
    let g = textured(
        json!({"uri": format!("data:image/png;base64,{}", base64(&png[..png.len() - 20]))}),
    );
    assert_mentions(&error_of(load(&g.gltf())), &["image 0"]);
}

#[test]
fn oversize_input_is_refused() {
    // A sparse file one byte over the limit: refused from its size, before reading.
    let dir = scratch_dir("oversize");
    let path = dir.join("huge.glb");
    let f = std::fs::File::create(&path).unwrap();
    f.set_len(MAX_INPUT_BYTES + 1).unwrap();
    drop(f);
    match load_path(&path, None) {
        Err(SceneError::TooLarge { bytes, limit, .. }) => {
            assert_eq!((bytes, limit), (MAX_INPUT_BYTES + 1, MAX_INPUT_BYTES))
        }
        r => panic!("expected TooLarge, got {r:?}"),
    }
    std::fs::remove_file(&path).unwrap();
    // Buffers that claim more than the limit in total.
    let mut doc = basic().json_with_buffer(Some("data:;base64,AAAA".into()));
    doc["buffers"][0]["byteLength"] = json!(MAX_INPUT_BYTES);
    doc["buffers"]
        .as_array_mut()
        .unwrap()
        .push(json!({"byteLength": 8, "uri": "data:;base64,AAAA"}));
    match load(&serde_json::to_vec(&doc).unwrap()) {
        Err(SceneError::TooLarge { bytes, .. }) => assert_eq!(bytes, MAX_INPUT_BYTES + 8),
        r => panic!("expected TooLarge, got {r:?}"),
    }
    // A buffer shorter than its byteLength.
    let mut doc = basic().json_with_buffer(Some("data:;base64,AAAA".into()));
    doc["buffers"][0]["byteLength"] = json!(64);
    assert_mentions(
        &error_of(load(&serde_json::to_vec(&doc).unwrap())),
        &["buffer 0", "byteLength 64"],
    );
}

#[test]
fn dangling_indices_are_errors() {
    let mut g = basic();
    g.doc["meshes"][0]["primitives"][0]["material"] = json!(5);
    assert_mentions(
        &error_of(load(&g.gltf())),
        &["test.gltf", "mesh 0 'tri' primitive 0", "material index 5"],
    );
    let mut g = basic();
    g.doc["nodes"][0]["children"] = json!([9]);
    assert_mentions(&error_of(load(&g.gltf())), &["nodes[0].children[0]"]);
    let mut g = basic();
    g.doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"] = json!(42);
    assert_mentions(
        &error_of(load(&g.gltf())),
        &["mesh 0 'tri' primitive 0", "POSITION", "accessor 42"],
    );
    let mut g = basic();
    g.doc["nodes"][0]["mesh"] = json!(3);
    assert!(load(&g.gltf()).is_err());
    let mut g = basic();
    g.doc["scene"] = json!(2);
    assert!(load(&g.gltf()).is_err());
    let mut g = basic();
    g.doc["nodes"][0]["camera"] = json!(0);
    assert!(load(&g.gltf()).is_err());
    let mut g = basic();
    g.doc["nodes"][0]["extensions"] = json!({"KHR_lights_punctual": {"light": 0}});
    assert!(load(&g.gltf()).is_err());
    let mut g = basic();
    g.doc["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"] = json!({"index": 0});
    assert!(load(&g.gltf()).is_err());
}

#[test]
fn node_cycles_are_errors() {
    let mut g = basic();
    g.doc["nodes"][0]["children"] = json!([0]);
    assert_mentions(&error_of(load(&g.gltf())), &["node 0", "reached twice"]);
    let mut g = basic();
    let a = g.node(json!({}));
    g.doc["nodes"][0]["children"] = json!([a]);
    g.doc["scenes"][0]["nodes"] = json!([0, a]);
    assert_mentions(
        &error_of(load(&g.gltf())),
        &[&format!("node {a}"), "reached twice"],
    );
}

#[test]
fn mesh_without_positions_is_an_error() {
    let mut g = basic();
    let normals = g.vec3(&[[0.0, 0.0, 1.0]; 3]);
    g.doc["meshes"][0]["primitives"][0]["attributes"] = json!({"NORMAL": normals});
    let e = error_of(load(&g.gltf()));
    assert_mentions(&e, &["POSITION"]);
}

#[test]
fn odd_documents_are_errors_not_panics() {
    // type perspective without a perspective object (the gltf crate would panic).
    let mut g = basic();
    let c = g.push("cameras", json!({"type": "perspective", "orthographic": {"xmag": 1, "ymag": 1, "znear": 0.1, "zfar": 2}}));
    g.root(json!({"camera": c}));
    assert!(load(&g.gltf()).is_err());
    // Bad yfov.
    let mut g = basic();
    let c = g.push(
        "cameras",
        json!({"type": "perspective", "perspective": {"yfov": 4.0, "znear": 0.1}}),
    );
    g.root(json!({"camera": c}));
    assert_mentions(&error_of(load(&g.gltf())), &["camera 0", "yfov"]);
    // glTF 1.0.
    let mut g = basic();
    g.doc["asset"]["version"] = json!("1.0");
    assert_mentions(&error_of(load(&g.gltf())), &["version"]);
    // A required extension we do not implement.
    let mut g = basic();
    g.doc["extensionsRequired"] = json!(["KHR_draco_mesh_compression"]);
    assert!(load(&g.gltf()).is_err());
    // .glb with a bad version, or whose first chunk is not JSON.
    let mut glb = basic().glb();
    glb[4] = 1;
    assert_mentions(&error_of(load(&glb)), &["version"]);
    let mut glb = basic().glb();
    glb[16..20].copy_from_slice(b"BIN\0");
    assert!(load(&glb).is_err());
    // .glb header claiming less than its own size.
    let mut glb = basic().glb();
    glb[8..12].copy_from_slice(&3u32.to_le_bytes());
    assert!(load(&glb).is_err());
    // GLB chunk length past the end.
    let mut glb = basic().glb();
    glb[12..16].copy_from_slice(&u32::MAX.to_le_bytes());
    assert!(load(&glb).is_err());
    // A buffer with no uri in a .gltf.
    let doc = basic().json_with_buffer(None);
    assert_mentions(
        &error_of(load(&serde_json::to_vec(&doc).unwrap())),
        &["buffer 0", "no uri"],
    );
    // A directory where a file is expected.
    let dir = scratch_dir("dir.gltf");
    assert!(load_path(&dir, None).is_err());
    // Out-of-range material parameters are reported by validation.
    let mut g = basic();
    g.doc["materials"][0]["pbrMetallicRoughness"]["baseColorFactor"] = json!([2.0, 0.0, 0.0, 1.0]);
    assert!(load(&g.gltf()).is_err());
}

// ---------------------------------------------------------------------------------------
// Shipped scenes.

fn scenes_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenes")
}

/// Emissive triangles as (sorted vertex list, area), total emissive area, and emitted power
/// sum(area * radiance * pi) for one-sided Lambertian emitters.
fn emitters(s: &Scene) -> (Vec<[[f32; 3]; 3]>, f64, [f64; 3]) {
    let mut tris = Vec::new();
    let mut area = 0.0;
    let mut power = [0.0; 3];
    for m in &s.meshes {
        let mat = &s.materials[m.material as usize];
        if !mat.is_emissive() {
            continue;
        }
        for t in &m.indices {
            let [a, b, c] = t.map(|i| m.positions[i as usize]);
            let ta = 0.5 * (b - a).cross(c - a).length() as f64;
            area += ta;
            for (k, p) in power.iter_mut().enumerate() {
                *p += ta * mat.emission[k] as f64 * std::f64::consts::PI;
            }
            let mut v = [a.to_array(), b.to_array(), c.to_array()];
            v.sort_by(|x, y| x.partial_cmp(y).unwrap());
            tris.push(v);
        }
    }
    tris.sort_by(|x, y| x.partial_cmp(y).unwrap());
    (tris, area, power)
}

#[test]
fn shipped_cornell_box_matches_the_builtin() {
    let gltf = load_path(&scenes_dir().join("cornell-box.gltf"), None).unwrap();
    let builtin = builtin::load("cornell-box").unwrap();
    assert_eq!(gltf.triangle_count(), builtin.triangle_count());
    let rel = |a: f64, b: f64| ((a - b) / b).abs();
    let (gt, ga, gp) = emitters(&gltf);
    let (bt, ba, bp) = emitters(&builtin);
    assert_eq!(gt.len(), bt.len());
    for (x, y) in gt.iter().zip(&bt) {
        for (p, q) in x.iter().zip(y) {
            assert!(
                close(Vec3::from(*p), Vec3::from(*q), 1e-6),
                "{x:?} vs {y:?}"
            );
        }
    }
    assert!(rel(ga, ba) < 1e-4, "area {ga} vs {ba}");
    for k in 0..3 {
        assert!(rel(gp[k], bp[k]) < 1e-4, "power {gp:?} vs {bp:?}");
    }
    // Same emitted radiance (17, 12, 4) and the same facing (down).
    let light = gltf.materials.iter().find(|m| m.is_emissive()).unwrap();
    assert!(
        close(light.emission, Vec3::new(17.0, 12.0, 4.0), 1e-4),
        "{}",
        light.emission
    );
    // Same surfaces: every triangle of the builtin appears with the same orientation and albedo.
    let tri_set = |s: &Scene| {
        let mut v: Vec<([i64; 9], [i64; 3])> = Vec::new();
        for m in &s.meshes {
            let albedo = match &s.materials[m.material as usize].kind {
                MaterialKind::Diffuse { albedo } => *albedo,
                MaterialKind::Gltf(g) => {
                    assert_eq!((g.metallic, g.roughness), (0.0, 1.0));
                    g.base_color
                }
                k => panic!("{k:?}"),
            };
            for t in &m.indices {
                // Rotate the vertex list so the smallest vertex comes first (keeps the winding).
                let p = t.map(|i| {
                    m.positions[i as usize]
                        .to_array()
                        .map(|c| (c * 1e5).round() as i64)
                });
                let r = (0..3).min_by_key(|&k| p[k]).unwrap();
                let q = [p[r], p[(r + 1) % 3], p[(r + 2) % 3]];
                v.push((
                    q.concat().try_into().unwrap(),
                    albedo.to_array().map(|c| (c * 1e4).round() as i64),
                ));
            }
        }
        v.sort();
        v
    };
    assert_eq!(tri_set(&gltf), tri_set(&builtin));
    // Same camera.
    let (gc, bc) = (&gltf.camera, &builtin.camera);
    assert!(close(
        gc.world_from_camera.w_axis.truncate(),
        Vec3::new(0.278, 0.273, -0.8),
        1e-6
    ));
    let diff = gc.world_from_camera - bc.world_from_camera;
    assert!(
        diff.to_cols_array().iter().all(|d| d.abs() < 1e-6),
        "{} vs {}",
        gc.world_from_camera,
        bc.world_from_camera
    );
    assert!((gc.yfov - bc.yfov).abs() < 1e-6);
    assert_eq!(gc.aspect_ratio, Some(1.0));
    assert_eq!(gltf.default_resolution, builtin.default_resolution);
    assert_eq!(gltf.lights.len(), 0);
}

#[test]
fn shipped_glass_spot_scene_loads() {
    let s = load_path(&scenes_dir().join("glass-spot.gltf"), None).unwrap();
    let spots: Vec<_> = s
        .lights
        .iter()
        .filter(|l| matches!(l, PunctualLight::Spot { .. }))
        .collect();
    assert_eq!((spots.len(), s.lights.len()), (1, 1));
    if let PunctualLight::Spot {
        direction,
        position,
        ..
    } = spots[0]
    {
        assert!(close(*direction, -Vec3::Y, 1e-5), "{direction}");
        assert!(position.y > 1.0);
    }
    let glass = s
        .materials
        .iter()
        .filter(|m| {
            m.as_gltf().is_some_and(|g| {
                (g.transmission, g.ior, g.metallic, g.roughness) == (1.0, 1.5, 0.0, 0.0)
            })
        })
        .count();
    assert_eq!(glass, 1);
    assert!(s.triangle_count() > 500);
    assert!(s.meshes.iter().any(|m| m.normals.is_some()));
    assert_eq!(s.camera.name.as_deref(), Some("main"));
}

/// `COLOR_0` (spec "Meshes > Overview"): VEC3 or VEC4 of float, normalized unsigned byte
/// or normalized unsigned short, read as linear RGBA (alpha 1 for VEC3), carried to the
/// mesh; a primitive without it costs nothing; non-normalized integers are refused.
#[test]
fn vertex_colours_are_read_for_every_component_type() {
    let with_colors = |bytes: Vec<u8>, ct: u32, ty: &str, normalized: bool| {
        let mut g = basic();
        let view = g.view(&bytes);
        let acc = g.push(
            "accessors",
            json!({"bufferView": view, "componentType": ct, "count": 3, "type": ty,
                "normalized": normalized}),
        );
        g.doc["meshes"][0]["primitives"][0]["attributes"]["COLOR_0"] = json!(acc);
        g
    };
    let floats: Vec<u8> = [0.25f32, 0.5, 1.0, 0.0, 0.125, 0.75, 1.0, 1.0, 0.0]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    let bytes: Vec<u8> = vec![0, 51, 102, 255, 255, 0, 0, 128, 10, 20, 30, 40];
    let shorts: Vec<u8> = [0u16, 65535, 32768, 13107, 1, 2, 3, 4, 5, 6, 7, 8]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    let cases: [(Vec<u8>, u32, &str, Vec4); 3] = [
        (floats, 5126, "VEC3", Vec4::new(0.25, 0.5, 1.0, 1.0)),
        (
            bytes,
            5121,
            "VEC4",
            Vec4::new(0.0, 51.0 / 255.0, 102.0 / 255.0, 1.0),
        ),
        (
            shorts,
            5123,
            "VEC4",
            Vec4::new(0.0, 1.0, 32768.0 / 65535.0, 13107.0 / 65535.0),
        ),
    ];
    for (bytes, ct, ty, first) in cases {
        for s in load_both(&with_colors(bytes.clone(), ct, ty, ct != 5126)) {
            let c = s.meshes[0].colors.as_ref().expect("vertex colours");
            assert_eq!(c.len(), 3);
            assert!(
                (c[0] - first).abs().max_element() < 1e-6,
                "{ct} {ty}: {:?}",
                c[0]
            );
        }
    }
    assert!(load_both(&basic())[0].meshes[0].colors.is_none());
    let err = error_of(load(&with_colors(vec![1; 12], 5121, "VEC4", false).gltf()));
    assert_mentions(&err, &["COLOR_0", "normalized"]);
}
