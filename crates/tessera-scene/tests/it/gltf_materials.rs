//! glTF materials as tools write them: every texture slot, samplers, texture transforms,
//! texture-coordinate sets, alpha modes, tangents, the material extensions, instancing
//! and quantized attributes, and the required/optional extension rules.

use glam::{Vec2, Vec3, Vec4};
use serde_json::{json, Value};
use tessera_scene::gltf_import::load_slice;
use tessera_scene::{AlphaMode, Scene, SceneError, Wrap};
use tessera_testkit::gltf_gen::{png_rgb8, Gen};

fn load(bytes: &[u8]) -> Result<Scene, SceneError> {
    load_slice(bytes, "materials.glb", None, None)
}

/// A unit quad in the z = 0 plane facing +Z, with TEXCOORD_0 `(x, 1 - y)` (glTF's v runs
/// down the image, so the image's top is at y = 1) and TEXCOORD_1 `(2x, 2y)`.
fn quad(g: &mut Gen, material: usize) -> usize {
    let pos = g.positions(&[
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [1.0, 1.0, 0.0],
        [0.0, 1.0, 0.0],
    ]);
    let normal = g.vec3(&[[0.0, 0.0, 1.0]; 4]);
    let uv0 = g.vec2(&[[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]]);
    let uv1 = g.vec2(&[[0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [0.0, 2.0]]);
    let idx = g.indices_u16(&[0, 1, 2, 0, 2, 3]);
    g.push(
        "meshes",
        json!({"primitives": [{"attributes": {"POSITION": pos, "NORMAL": normal,
            "TEXCOORD_0": uv0, "TEXCOORD_1": uv1}, "indices": idx, "material": material}]}),
    )
}

/// A 2x2 PNG texture with the given sampler (or none); returns the texture index.
fn texture(g: &mut Gen, sampler: Option<Value>) -> usize {
    let png = png_rgb8(2, 2, &[255, 0, 0, 0, 255, 0, 0, 0, 255, 255, 255, 255]);
    let view = g.view(&png);
    let image = g.push(
        "images",
        json!({"bufferView": view, "mimeType": "image/png"}),
    );
    match sampler {
        Some(s) => {
            let si = g.push("samplers", s);
            g.push("textures", json!({"source": image, "sampler": si}))
        }
        None => g.push("textures", json!({"source": image})),
    }
}

#[test]
fn every_texture_slot_and_extension_is_read() {
    let mut g = Gen::new();
    for e in [
        "KHR_texture_transform",
        "KHR_materials_specular",
        "KHR_materials_transmission",
        "KHR_materials_volume",
        "KHR_materials_clearcoat",
        "KHR_materials_sheen",
        "KHR_materials_ior",
    ] {
        g.uses(e);
    }
    let t = texture(&mut g, None);
    let info = |set: u32| json!({"index": t, "texCoord": set});
    let material = g.push(
        "materials",
        json!({
            "pbrMetallicRoughness": {
                "baseColorFactor": [0.5, 0.5, 0.5, 0.25],
                "baseColorTexture": {"index": t, "extensions": {"KHR_texture_transform":
                    {"offset": [0.5, 0.0], "rotation": 0.0, "scale": [2.0, 2.0], "texCoord": 1}}},
                "metallicFactor": 0.25, "roughnessFactor": 0.75,
                "metallicRoughnessTexture": info(0)},
            "normalTexture": {"index": t, "scale": 0.5, "texCoord": 1},
            "occlusionTexture": {"index": t, "strength": 0.5},
            "emissiveTexture": info(0),
            "emissiveFactor": [1.0, 1.0, 1.0],
            "alphaMode": "MASK", "alphaCutoff": 0.3,
            "extensions": {
                "KHR_materials_specular": {"specularFactor": 0.5, "specularTexture": info(0),
                    "specularColorFactor": [1.0, 0.5, 0.25], "specularColorTexture": info(0)},
                "KHR_materials_transmission": {"transmissionFactor": 0.5, "transmissionTexture": info(0)},
                "KHR_materials_volume": {"thicknessFactor": 1.0, "attenuationDistance": 2.0,
                    "attenuationColor": [0.5, 1.0, 0.25]},
                "KHR_materials_clearcoat": {"clearcoatFactor": 0.75, "clearcoatTexture": info(0),
                    "clearcoatRoughnessFactor": 0.125, "clearcoatRoughnessTexture": info(0)},
                "KHR_materials_sheen": {"sheenColorFactor": [0.5, 0.25, 0.125],
                    "sheenColorTexture": info(0), "sheenRoughnessFactor": 0.5,
                    "sheenRoughnessTexture": info(0)},
                "KHR_materials_ior": {"ior": 1.4}
            }
        }),
    );
    let m = quad(&mut g, material);
    g.root(json!({"mesh": m}));
    let s = load(&g.glb()).unwrap();
    let m = s.materials[0].as_gltf().unwrap();
    assert_eq!((m.base_color, m.alpha), (Vec3::splat(0.5), 0.25));
    assert_eq!((m.metallic, m.roughness, m.ior), (0.25, 0.75, 1.4));
    assert_eq!(m.alpha_mode, AlphaMode::Mask { cutoff: 0.3 });
    // KHR_texture_transform's texCoord overrides the textureInfo's.
    let base = m.base_color_texture.unwrap();
    assert_eq!(base.uv_set, 1);
    let p = base.transform.unwrap().apply(Vec2::new(1.0, 1.0));
    assert!((p - Vec2::new(2.5, 2.0)).length() < 1e-6, "{p}");
    let normal = m.normal_map.unwrap();
    assert_eq!((normal.scale, normal.texture.uv_set), (0.5, 1));
    assert!(m.metallic_roughness_texture.is_some() && m.emissive_texture.is_some());
    assert_eq!(s.materials[0].emission, Vec3::ONE);
    assert_eq!(
        (m.specular, m.specular_color),
        (0.5, Vec3::new(1.0, 0.5, 0.25))
    );
    assert!(m.specular_texture.is_some() && m.specular_color_texture.is_some());
    assert_eq!(m.transmission, 0.5);
    assert!(m.transmission_texture.is_some());
    // Beer–Lambert: exp(-sigma 2) = colour.
    let sigma = m.volume.unwrap().sigma_a;
    let want = Vec3::new(0.5f32.ln(), 0.0, 0.25f32.ln()) / -2.0;
    assert!((sigma - want).length() < 1e-6, "{sigma} vs {want}");
    assert_eq!((m.clearcoat, m.clearcoat_roughness), (0.75, 0.125));
    assert!(m.clearcoat_texture.is_some() && m.clearcoat_roughness_texture.is_some());
    assert_eq!(m.sheen_color, Vec3::new(0.5, 0.25, 0.125));
    assert_eq!(m.sheen_roughness, 0.5);
    assert!(m.sheen_color_texture.is_some() && m.sheen_roughness_texture.is_some());
    // One image, one texture: every slot shares them.
    assert_eq!((s.images.len(), s.textures.len()), (1, 1));
    // Both coordinate sets are read because textures use both.
    let mesh = &s.meshes[0];
    assert_eq!(mesh.uvs.len(), 2);
    assert_eq!(mesh.uvs[1][2], Vec2::new(2.0, 2.0));
    // The normal map reads TEXCOORD_1 = (2x, 2y): MikkTSpace with v flipped gives +X
    // tangents whose bitangent cross(n, t) w runs along +Y... of the flipped v, which for
    // this set (v increasing with y) is -Y: w = -1.
    let t = mesh.tangents.as_ref().unwrap();
    for corner in t.iter().flatten() {
        assert!((corner.truncate() - Vec3::X).length() < 1e-5, "{corner}");
        assert_eq!(corner.w, -1.0);
    }
}

#[test]
fn generated_tangents_point_along_u_with_the_bitangent_up_the_image() {
    // The normal map reads TEXCOORD_0 = (x, 1 - y): +u along +X, the image's top at +Y.
    // The glTF normal map's green channel points up the image, so the bitangent
    // cross(n, t) w must be +Y: w = +1.
    let mut g = Gen::new();
    let t = texture(&mut g, None);
    let material = g.push("materials", json!({"normalTexture": {"index": t}}));
    let m = quad(&mut g, material);
    g.root(json!({"mesh": m}));
    let s = load(&g.glb()).unwrap();
    for corner in s.meshes[0].tangents.as_ref().unwrap().iter().flatten() {
        assert!(
            (*corner - Vec4::new(1.0, 0.0, 0.0, 1.0)).length() < 1e-5,
            "{corner}"
        );
    }
    // Given TANGENT attributes are used as they are (rotated with the node).
    let tangent = g.push(
        "accessors",
        json!({"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC4"}),
    );
    let bytes: Vec<u8> = [[0.0f32, 1.0, 0.0, -1.0]; 4]
        .iter()
        .flatten()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    let view = g.view(&bytes);
    g.doc["accessors"][tangent]["bufferView"] = json!(view);
    g.doc["meshes"][m]["primitives"][0]["attributes"]["TANGENT"] = json!(tangent);
    // Rotate the node by 90 degrees about Z: +Y tangents become -X.
    let h = std::f32::consts::FRAC_1_SQRT_2;
    g.doc["nodes"][0]["rotation"] = json!([0.0, 0.0, h, h]);
    let s = load(&g.glb()).unwrap();
    for corner in s.meshes[0].tangents.as_ref().unwrap().iter().flatten() {
        assert!(
            (*corner - Vec4::new(-1.0, 0.0, 0.0, -1.0)).length() < 1e-5,
            "{corner}"
        );
    }
    // A mirroring node flips the handedness.
    g.doc["nodes"][0]["rotation"] = json!([0.0, 0.0, 0.0, 1.0]);
    g.doc["nodes"][0]["scale"] = json!([-1.0, 1.0, 1.0]);
    let s = load(&g.glb()).unwrap();
    for corner in s.meshes[0].tangents.as_ref().unwrap().iter().flatten() {
        assert!(
            (*corner - Vec4::new(0.0, 1.0, 0.0, 1.0)).length() < 1e-5,
            "{corner}"
        );
    }
}

#[test]
fn sampler_wrap_modes_and_filters_are_kept_per_texture() {
    let mut g = Gen::new();
    let cases = [
        (
            json!({"wrapS": 10497, "wrapT": 33648}),
            Wrap::Repeat,
            Wrap::MirroredRepeat,
            false,
        ),
        (
            json!({"wrapS": 33071, "wrapT": 10497, "magFilter": 9728}),
            Wrap::ClampToEdge,
            Wrap::Repeat,
            true,
        ),
        (
            json!({"wrapS": 33648, "wrapT": 33071, "magFilter": 9729}),
            Wrap::MirroredRepeat,
            Wrap::ClampToEdge,
            false,
        ),
    ];
    for (sampler, ..) in &cases {
        let t = texture(&mut g, Some(sampler.clone()));
        let material = g.push(
            "materials",
            json!({"pbrMetallicRoughness": {"baseColorTexture": {"index": t}}}),
        );
        let m = quad(&mut g, material);
        g.root(json!({"mesh": m}));
    }
    let s = load(&g.glb()).unwrap();
    for (i, (_, s_wrap, t_wrap, nearest)) in cases.iter().enumerate() {
        let t = s.materials[i]
            .as_gltf()
            .unwrap()
            .base_color_texture
            .unwrap();
        let tex = &s.textures[t.texture as usize];
        assert_eq!(
            (tex.wrap_s, tex.wrap_t, tex.nearest),
            (*s_wrap, *t_wrap, *nearest)
        );
    }
}

#[test]
fn alpha_modes_are_read_with_the_default_cutoff() {
    let mut g = Gen::new();
    for mode in ["OPAQUE", "MASK", "BLEND"] {
        let material = g.push("materials", json!({"alphaMode": mode}));
        let m = quad(&mut g, material);
        g.root(json!({"mesh": m}));
    }
    let s = load(&g.glb()).unwrap();
    let modes: Vec<AlphaMode> = s
        .materials
        .iter()
        .map(|m| m.as_gltf().unwrap().alpha_mode)
        .collect();
    assert_eq!(
        modes,
        [
            AlphaMode::Opaque,
            AlphaMode::Mask { cutoff: 0.5 },
            AlphaMode::Blend
        ]
    );
    assert!(!s.materials[0].has_alpha() && s.materials[1].has_alpha());
}

#[test]
fn unlit_materials_emit_their_base_colour_and_scatter_nothing() {
    let mut g = Gen::new();
    g.uses("KHR_materials_unlit");
    let t = texture(&mut g, None);
    let material = g.push(
        "materials",
        json!({"pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.25, 1.0, 1.0],
            "baseColorTexture": {"index": t}}, "extensions": {"KHR_materials_unlit": {}}}),
    );
    let m = quad(&mut g, material);
    g.root(json!({"mesh": m}));
    let s = load(&g.glb()).unwrap();
    let mat = &s.materials[0];
    assert_eq!(mat.emission, Vec3::new(0.5, 0.25, 1.0));
    let g = mat.as_gltf().unwrap();
    assert!(g.unlit);
    assert_eq!(g.emissive_texture, g.base_color_texture);
}

#[test]
fn required_extensions_are_checked_by_tessera_and_unknown_optional_ones_are_warnings() {
    let mut g = Gen::new();
    let material = g.push("materials", json!({}));
    let m = quad(&mut g, material);
    g.root(json!({"mesh": m}));
    // Extensions the gltf crate does not know but Tessera renders may be required.
    g.doc["extensionsRequired"] = json!([
        "KHR_materials_specular",
        "KHR_materials_clearcoat",
        "KHR_texture_transform",
        "KHR_mesh_quantization",
        "EXT_mesh_gpu_instancing"
    ]);
    g.doc["extensionsUsed"] = g.doc["extensionsRequired"].clone();
    let s = load(&g.glb()).unwrap();
    assert!(s.warnings.is_empty(), "{:?}", s.warnings);
    // An unknown required extension is an error naming it.
    g.doc["extensionsRequired"] = json!(["KHR_materials_specular", "EXT_meshopt_compression"]);
    let e = load(&g.glb()).unwrap_err().to_string();
    assert!(e.contains("EXT_meshopt_compression"), "{e}");
    assert!(
        !e.contains("requires the extensions KHR_materials_specular"),
        "{e}"
    );
    // An unknown optional one loads, with a warning the render plan repeats.
    g.doc["extensionsRequired"] = json!([]);
    g.doc["extensionsUsed"] = json!(["KHR_materials_iridescence"]);
    let s = load(&g.glb()).unwrap();
    assert_eq!(s.warnings.len(), 1);
    assert!(s.warnings[0].contains("KHR_materials_iridescence"));
    let plan = tessera_scene::analysis::analyse(&s);
    assert!(
        plan.summary().contains("KHR_materials_iridescence"),
        "{}",
        plan.summary()
    );
    assert!(plan.to_json().contains("\"warnings\":[\""));
}

#[test]
fn gpu_instancing_places_the_mesh_at_every_instance() {
    let mut g = Gen::new();
    g.uses("EXT_mesh_gpu_instancing");
    let material = g.push("materials", json!({}));
    let m = quad(&mut g, material);
    let translations = g.vec3(&[[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 20.0, 0.0]]);
    g.root(json!({"mesh": m, "translation": [0.0, 0.0, 5.0],
        "extensions": {"EXT_mesh_gpu_instancing": {"attributes": {"TRANSLATION": translations}}}}));
    let s = load(&g.glb()).unwrap();
    // Stored once, placed three times.
    assert!(s.meshes.is_empty());
    assert_eq!(s.prototypes.len(), 1);
    assert_eq!(s.instances.len(), 3);
    assert_eq!(s.triangle_count(), 3 * s.stored_triangle_count());
    let origins: Vec<Vec3> = s.placed_meshes().map(|m| m.triangle(0)[0]).collect();
    assert_eq!(
        origins,
        [
            Vec3::new(0.0, 0.0, 5.0),
            Vec3::new(10.0, 0.0, 5.0),
            Vec3::new(0.0, 20.0, 5.0)
        ]
    );
    // Attributes of different lengths are an error naming the node.
    let one = g.vec3(&[[1.0, 1.0, 1.0]]);
    g.doc["nodes"][0]["extensions"]["EXT_mesh_gpu_instancing"]["attributes"]["SCALE"] = json!(one);
    let e = load(&g.glb()).unwrap_err().to_string();
    assert!(e.contains("node 0 EXT_mesh_gpu_instancing"), "{e}");
}

#[test]
fn quantized_attributes_are_dequantized() {
    // KHR_mesh_quantization: positions as SHORT (not normalized) and texture coordinates
    // as normalized UNSIGNED_BYTE.
    let mut g = Gen::new();
    g.uses("KHR_mesh_quantization");
    g.doc["extensionsRequired"] = json!(["KHR_mesh_quantization"]);
    let pos: Vec<u8> = [[0i16, 0, 0, 0], [2, 0, 0, 0], [0, 3, 0, 0]]
        .iter()
        .flatten()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    let pv = g.view(&pos);
    let pa = g.push(
        "accessors",
        json!({"bufferView": pv, "componentType": 5122, "count": 3, "type": "VEC3",
            "byteOffset": 0, "min": [0, 0, 0], "max": [2, 3, 0]}),
    );
    g.doc["bufferViews"][pv]["byteStride"] = json!(8);
    let uv: Vec<u8> = vec![0, 0, 0, 0, 255, 0, 0, 0, 0, 255, 0, 0];
    let uvv = g.view(&uv);
    g.doc["bufferViews"][uvv]["byteStride"] = json!(4);
    let ua = g.push(
        "accessors",
        json!({"bufferView": uvv, "componentType": 5121, "normalized": true, "count": 3, "type": "VEC2"}),
    );
    let t = texture(&mut g, None);
    let material = g.push(
        "materials",
        json!({"pbrMetallicRoughness": {"baseColorTexture": {"index": t}}}),
    );
    let m = g.push(
        "meshes",
        json!({"primitives": [{"attributes": {"POSITION": pa, "TEXCOORD_0": ua}, "material": material}]}),
    );
    g.root(json!({"mesh": m}));
    let s = load(&g.glb()).unwrap();
    assert_eq!(s.meshes[0].positions[1], Vec3::new(2.0, 0.0, 0.0));
    assert_eq!(s.meshes[0].positions[2], Vec3::new(0.0, 3.0, 0.0));
    assert_eq!(s.meshes[0].uvs[0][1], Vec2::new(1.0, 0.0));
    assert_eq!(s.meshes[0].uvs[0][2], Vec2::new(0.0, 1.0));
}

#[test]
fn a_mesh_under_several_nodes_is_stored_once() {
    // One mesh under four nodes (one mirrored, one scaled to nothing) and an emissive mesh
    // under two: the shared mesh becomes one prototype with an instance per invertible
    // placement; the degenerate placement and the emitter are flattened.
    let mut g = Gen::new();
    let grey = g.push("materials", json!({}));
    let glow = g.push("materials", json!({"emissiveFactor": [1.0, 1.0, 1.0]}));
    let m = quad(&mut g, grey);
    let lamp = quad(&mut g, glow);
    g.root(json!({"mesh": m, "translation": [0.0, 0.0, 1.0]}));
    let h = std::f32::consts::FRAC_1_SQRT_2;
    g.root(json!({"mesh": m, "translation": [3.0, 0.0, 0.0], "rotation": [0.0, 0.0, h, h]}));
    g.root(json!({"mesh": m, "scale": [-1.0, 2.0, 1.0]}));
    g.root(json!({"mesh": m, "scale": [0.0, 1.0, 1.0]}));
    g.root(json!({"mesh": lamp, "translation": [0.0, 5.0, 0.0]}));
    g.root(json!({"mesh": lamp, "translation": [0.0, 6.0, 0.0]}));
    let s = load(&g.glb()).unwrap();
    assert_eq!(s.prototypes.len(), 1);
    assert_eq!(s.instances.len(), 3);
    assert_eq!(s.meshes.len(), 3, "degenerate placement and two emitters");
    assert!(s.instances.iter().all(|i| i.prototype == 0));
    assert_eq!(
        s.instances.iter().map(|i| i.mirrors()).collect::<Vec<_>>(),
        [false, false, true]
    );
    assert_eq!(s.triangle_count(), 6 * 2);
    assert_eq!(s.stored_triangle_count(), 4 * 2);
    // The second instance: rotated 90 degrees about z, then moved to x = 3.
    let corner = s.placed_meshes().nth(4).unwrap().triangle(0)[1];
    assert!(
        (corner - Vec3::new(3.0, 1.0, 0.0)).length() < 1e-6,
        "{corner}"
    );
    // The analysis sees every placement: the shared quad's area counts four times (the
    // degenerate copy has none).
    let plan = tessera_scene::analysis::analyse(&s);
    assert!(!plan.summary().is_empty());
}

#[test]
fn ten_thousand_gpu_instances_load_within_the_budget() {
    // A 33,282-triangle grid mesh placed 10,000 times by EXT_mesh_gpu_instancing:
    // flattened, that is 333 M triangles (about 9.4 GB by the importer's estimate, past its
    // 4 GiB output budget); stored once it loads.
    let mut g = Gen::new();
    g.uses("EXT_mesh_gpu_instancing");
    let material = g.push("materials", json!({}));
    let n = 130u32;
    let mut pos = Vec::new();
    for y in 0..n {
        for x in 0..n {
            pos.push([x as f32 / 129.0, y as f32 / 129.0, 0.0]);
        }
    }
    let mut idx = Vec::new();
    for y in 0..n - 1 {
        for x in 0..n - 1 {
            let v = y * n + x;
            idx.extend([v, v + 1, v + n + 1, v, v + n + 1, v + n]);
        }
    }
    let pos = g.positions(&pos);
    let idx = g.indices_u32(&idx);
    let m = g.push(
        "meshes",
        json!({"primitives": [{"attributes": {"POSITION": pos}, "indices": idx, "material": material}]}),
    );
    let t: Vec<[f32; 3]> = (0..10_000)
        .map(|i| [(i % 100) as f32 * 2.0, 0.0, (i / 100) as f32 * 2.0])
        .collect();
    let t = g.vec3(&t);
    g.root(json!({"mesh": m,
        "extensions": {"EXT_mesh_gpu_instancing": {"attributes": {"TRANSLATION": t}}}}));
    let s = tessera_scene::gltf_import::load_slice(&g.glb(), "forest.glb", None, None).unwrap();
    assert_eq!(s.prototypes.len(), 1);
    assert_eq!(s.instances.len(), 10_000);
    assert_eq!(s.stored_triangle_count(), 33_282);
    assert_eq!(s.triangle_count(), 33_282 * 10_000);
}

/// KHR_materials_anisotropy (which Blender 4.2+ writes for an anisotropic Principled
/// BSDF): strength, rotation and texture are read, the extension is no longer warned about,
/// and a primitive without a normal map gets MikkTSpace tangents from TEXCOORD_0, whose
/// frame the direction lives in.
#[test]
fn anisotropy_is_read_with_a_tangent_frame() {
    let mut g = Gen::new();
    g.uses("KHR_materials_anisotropy");
    let t = texture(&mut g, None);
    let material = g.push(
        "materials",
        json!({"pbrMetallicRoughness": {"roughnessFactor": 0.3},
            "extensions": {"KHR_materials_anisotropy": {"anisotropyStrength": 0.6,
                "anisotropyRotation": 1.5, "anisotropyTexture": {"index": t}}}}),
    );
    let m = quad(&mut g, material);
    g.root(json!({"mesh": m}));
    let s = load(&g.glb()).unwrap();
    assert!(
        !s.warnings.iter().any(|w| w.contains("anisotropy")),
        "{:?}",
        s.warnings
    );
    let a = s.materials[0].as_gltf().unwrap().anisotropy.unwrap();
    assert_eq!((a.strength, a.rotation), (0.6, 1.5));
    assert_eq!(a.texture.map(|t| t.uv_set), Some(0));
    // The quad's TEXCOORD_0 is (x, 1 - y): MikkTSpace's tangent runs along +x.
    let tangents = s.meshes[0]
        .tangents
        .as_ref()
        .expect("tangents for anisotropy");
    for corner in tangents.iter().flatten() {
        assert!((corner.truncate() - Vec3::X).length() < 1e-4, "{corner}");
    }

    // Defaults: strength 0, rotation 0, no texture; a bad strength is refused by name.
    for (ext, ok) in [
        (json!({}), true),
        (json!({"anisotropyStrength": 1.5}), false),
    ] {
        let mut g = Gen::new();
        g.uses("KHR_materials_anisotropy");
        let material = g.push(
            "materials",
            json!({"extensions": {"KHR_materials_anisotropy": ext}}),
        );
        let m = quad(&mut g, material);
        g.root(json!({"mesh": m}));
        match load(&g.glb()) {
            Ok(s) => {
                assert!(ok);
                let a = s.materials[0].as_gltf().unwrap().anisotropy.unwrap();
                assert_eq!((a.strength, a.rotation, a.texture), (0.0, 0.0, None));
            }
            Err(e) => {
                assert!(!ok);
                assert!(e.to_string().contains("anisotropyStrength"), "{e}");
            }
        }
    }
}

/// An anisotropic mesh placed twice is stored once, as any mesh is: the renderer carries
/// the object-space tangents to each hit through the instance's transform.
#[test]
fn an_anisotropic_mesh_placed_twice_is_instanced() {
    let mut g = Gen::new();
    g.uses("KHR_materials_anisotropy");
    let material = g.push(
        "materials",
        json!({"extensions": {"KHR_materials_anisotropy": {"anisotropyStrength": 0.7}}}),
    );
    let m = quad(&mut g, material);
    g.root(json!({"mesh": m}));
    let h = std::f32::consts::FRAC_1_SQRT_2;
    g.root(json!({"mesh": m, "translation": [3.0, 0.0, 0.0], "rotation": [0.0, 0.0, h, h]}));
    let s = load(&g.glb()).unwrap();
    assert!(s.meshes.is_empty());
    assert_eq!((s.prototypes.len(), s.instances.len()), (1, 2));
    let tangents = s.prototypes[0].tangents.as_ref().expect("tangents");
    for corner in tangents.iter().flatten() {
        assert!((corner.truncate() - Vec3::X).length() < 1e-4, "{corner}");
    }
}

/// Blender's anisotropic metal (tests/fixtures/blender/anisotropy.glb, made by
/// make_fixtures.py): the extension as Blender writes it, without TANGENT, on a UV sphere.
#[test]
fn blender_anisotropy_fixture_imports() {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../tests/fixtures/blender/anisotropy.glb"
    );
    let s = tessera_scene::load(path).unwrap();
    assert!(
        !s.warnings.iter().any(|w| w.contains("anisotropy")),
        "{:?}",
        s.warnings
    );
    let sphere = s
        .meshes
        .iter()
        .find(|m| {
            s.materials[m.material as usize]
                .as_gltf()
                .is_some_and(|g| g.anisotropy.is_some())
        })
        .expect("the brushed sphere");
    let a = s.materials[sphere.material as usize]
        .as_gltf()
        .unwrap()
        .anisotropy
        .unwrap();
    assert!((a.strength - 0.8).abs() < 1e-6, "{a:?}");
    let tangents = sphere.tangents.as_ref().expect("generated tangents");
    assert_eq!(tangents.len(), sphere.indices.len());
    // Tangents are unit and orthogonal to the vertex normals (MikkTSpace's frame).
    let normals = sphere.normals.as_ref().unwrap();
    for (tri, corners) in sphere.indices.iter().zip(tangents) {
        for (v, t) in tri.iter().zip(corners) {
            let n = normals[*v as usize];
            assert!((t.truncate().length() - 1.0).abs() < 1e-3);
            assert!(n.dot(t.truncate()).abs() < 1e-2, "{n} {t}");
        }
    }
}
