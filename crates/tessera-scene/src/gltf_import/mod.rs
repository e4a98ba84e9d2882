//! glTF 2.0 import: `.gltf` (external files or `data:` URIs) and `.glb`, into a world-space
//! [`Scene`] (meshes placed more than once kept as prototypes with instances).
//!
//! References are to the glTF 2.0 specification (Khronos, version 2.0.1) by section title,
//! and to the Khronos extension specifications.
//!
//! # What is imported
//!
//! - **Scene graph** (spec "Scenes", "Nodes and Hierarchy", "Transformations"): the default
//!   scene (`scene`), else scene 0, else every node that is nobody's child. Node transforms
//!   (`matrix`, or `translation * rotation * scale`) are accumulated from the roots down; the
//!   hierarchy must be a forest of strict trees, so a node reachable twice (or a cycle) is an
//!   error.
//! - **Time** (spec "Animations", "Skins", "Meshes > Morph Targets", Appendix C): the
//!   scene is evaluated at one [`SceneTime`] ([`load_path_at`], [`load_slice_at`];
//!   [`load_path`] and [`load_slice`] use t = 0). Every animation plays unless one is named;
//!   node translation, rotation and scale channels (`STEP`, `LINEAR` with quaternion slerp,
//!   `CUBICSPLINE`) replace the nodes' own values, so meshes, lights and the camera move;
//!   times outside the keyframes clamp. Morph targets (with animated `weights`) and skins
//!   (linear blend skinning) are evaluated into world-space vertices, once per scene
//!   build. The rules are in the `animation` and `deform` steps. A file without
//!   animations, skins or morph targets imports exactly as before.
//! - **Geometry** (spec "Meshes"): every primitive of mode `TRIANGLES` placed once becomes
//!   one world-space [`crate::Mesh`] named `mesh M 'Name' primitive P`, with positions transformed to world space,
//!   normals transformed by the inverse transpose and renormalized, texture coordinates
//!   (every `TEXCOORD_n` the material's textures read) and indices
//!   (or the implicit `0..n`). When the node's world transform has a negative determinant
//!   the winding is flipped, so triangles stay counter-clockwise seen from the front (spec
//!   "Meshes > Overview": the determinant of the global transform defines the winding).
//!   Other primitive modes are an error. A primitive whose transformed normals degenerate
//!   (zero length, e.g. from a zero scale) keeps its positions and drops its normals.
//!   A mesh placed at two or more places (several nodes, or EXT_mesh_gpu_instancing) is
//!   stored once per primitive in object space in [`Scene::prototypes`] with one
//!   [`crate::Instance`] per place, except for emissive primitives and non-invertible
//!   transforms, which are flattened as above (see the `meshes` step).
//! - **Camera** (spec "Cameras"): the first node, in depth-first order, carrying a
//!   perspective camera, or the one whose camera name or node name equals the requested
//!   name. `world_from_camera` is the node's world transform with scale removed (glTF
//!   cameras look down their local -Z with +Y up). Without any camera one is synthesized
//!   that looks down -Z from the +Z side and frames the bounding sphere of the geometry with
//!   a 45° vertical field of view.
//! - **Materials** (spec "Materials", "Metallic-Roughness Material", "Default Material"):
//!   every material becomes a [`GltfMaterial`] ([`MaterialKind::Gltf`]): base colour and
//!   alpha with `baseColorTexture` (sRGB RGB, linear alpha), `metallicFactor` and
//!   `roughnessFactor` with `metallicRoughnessTexture` (metalness in B, roughness in G),
//!   `normalTexture` with its `scale` (tangent space; tangents from `TANGENT`, else
//!   generated with MikkTSpace as the spec asks, see below), `emissiveTexture` (sRGB)
//!   multiplying `emissiveFactor` x `KHR_materials_emissive_strength` (emitted radiance
//!   in W/(m² sr)), and `alphaMode` (`OPAQUE`, `MASK` with `alphaCutoff`, default 0.5,
//!   or `BLEND`, rendered as stochastic transparency). `occlusionTexture` is read (a broken
//!   one is an error) and ignored: ambient occlusion approximates, for real-time
//!   renderers, the shadowing a path tracer computes. Extensions: `KHR_materials_ior`,
//!   `KHR_materials_specular` (factor, colour, both textures), `KHR_materials_transmission`
//!   (factor and texture), `KHR_materials_volume` (`attenuationColor` and
//!   `attenuationDistance` become a Beer–Lambert absorption coefficient
//!   `σ = -ln(colour) / distance`; `thicknessFactor` and its texture are a real-time
//!   stand-in for the geometry and are not used), `KHR_materials_clearcoat`,
//!   `KHR_materials_sheen` (factors and textures), `KHR_materials_anisotropy`
//!   (`anisotropyStrength`, `anisotropyRotation`, `anisotropyTexture` with the direction
//!   in RG and a strength factor in B), `KHR_materials_emissive_strength` and
//!   `KHR_materials_unlit` (the base colour, textured, becomes the emission, and the
//!   surface scatters nothing). Primitives without a material use the default material
//!   (base colour 1, metallic 1, roughness 1).
//! - **Textures** (spec "Textures", "Samplers", "Images"): each image is decoded once
//!   (PNG or JPEG, 8 or 16 bits, grey or colour, with alpha) and kept as the file encodes
//!   it (8-bit images at 4 bytes a texel); the renderer linearises colour slots with the
//!   exact sRGB EOTF of IEC 61966-2-1 and reads data slots as linear. Row 0 is the top row
//!   of the image, which is where glTF puts texture coordinate v = 0. Each texture keeps
//!   its sampler's `wrapS`/`wrapT` (`REPEAT`, `MIRRORED_REPEAT`, `CLAMP_TO_EDGE`, exactly)
//!   and `magFilter` (`NEAREST`, else bilinear). Each texture reference keeps its
//!   `texCoord` and `KHR_texture_transform` (offset, rotation, scale, and its `texCoord`
//!   override); every `TEXCOORD_n` a material's textures name is imported.
//! - **Tangents**: `TANGENT` when the primitive has it, else MikkTSpace (Mikkelsen 2008,
//!   the `bevy_mikktspace` crate, a safe port of the reference code) per triangle corner,
//!   fed with `(u, 1 - v)` so that, as in Blender, the bitangent `cross(n, t) w` points up
//!   the image (the normal map's +Y, green). Only primitives with a normal map or
//!   KHR_materials_anisotropy get them (the latter from `TEXCOORD_0` without a normal map).
//! - **Extensions** ([`SUPPORTED_EXTENSIONS`]): a file whose `extensionsRequired` names
//!   anything else is refused with the names; an unknown extension that is only used
//!   becomes a warning in [`Scene::warnings`], which the render plan repeats.
//!   `KHR_mesh_quantization` needs nothing more (integer and normalized attributes are
//!   read as the spec's accessor rules say); `EXT_mesh_gpu_instancing` places the mesh at
//!   every instance's `T * R * S` under the node.
//! - **Lights** (`KHR_lights_punctual`): point, spot and directional lights at their nodes'
//!   world positions, pointing along their nodes' world -Z. The extension gives photometric
//!   quantities: point and spot intensity in candela (lm/sr), directional illuminance in lux
//!   (lm/m²). They are converted to radiometric quantities by dividing by
//!   [`LUMINOUS_EFFICACY`] = 683 lm/W, the luminous efficacy of monochromatic 555 nm light
//!   that defines the candela (SI brochure, 9th edition, section 2.3.1). So
//!   `intensity [W/sr] = color * intensity [cd] / 683` and
//!   `irradiance [W/m²] = color * illuminance [lx] / 683`, per linear-RGB channel (see
//!   [`photometric_to_radiometric`]). This treats each RGB channel as if it had the
//!   efficacy of 555 nm light; the Blender glTF importer/exporter uses the same factor
//!   (`PBR_WATTS_TO_LUMENS = 683`).
//!   Spot cones default to inner 0 and outer π/4. The light `range` is ignored: lights fall
//!   off with the physical inverse square law only (the extension allows this; `range` is a
//!   hint for real-time culling).
//!
//! # Robustness
//!
//! No input makes the importer panic. The GLB container, buffers, buffer views, accessors,
//! index values, node transforms and images are checked before they are used, and the
//! whole import additionally runs under [`std::panic::catch_unwind`], so that a panic in a
//! dependency (the `gltf` crate panics on some malformed documents) becomes a
//! [`SceneError::Gltf`]. (This relies on the default `panic = "unwind"`.) While the import
//! runs, the default panic message is silenced for the importing thread only. Inputs are
//! capped at [`MAX_INPUT_BYTES`] (the file, and separately the sum of its buffers and
//! images), images at [`crate::MAX_IMAGE_TEXELS`] each and [`crate::MAX_SCENE_TEXELS`]
//! together (read from each image's header before it is decoded, so a decompression bomb
//! costs nothing), every top-level array of the document at [`crate::MAX_NODES`] elements
//! (counted before the JSON is parsed), stored triangles at [`crate::MAX_TRIANGLES`], and
//! the output at four times the input limit, where a prototype counts once and an
//! instance as its transform (so 10,000 instances of a large tree load). Every error names
//! the file and the element (node, mesh, primitive, material, accessor, buffer view,
//! buffer, image index) that is wrong.
//!
//! # Where each step lives
//!
//! An `Importer` holds the parsed document and what has been read so far; its steps are
//! in one file each: `container` (`.gltf`/`.glb` parsing, document checks, buffers, `data:`
//! URIs and external files), `accessors` (buffer views and accessors), `materials`
//! (materials and textures), `animation` (the pose at the scene's time), `graph` (the node
//! hierarchy and its transforms), `deform` (skins and morph targets), `meshes`, `lights` and
//! `camera`. This file holds the public entry points, the panic guard and the
//! order of the steps.

mod accessors;
mod animation;
mod camera;
mod container;
mod deform;
mod extensions;
mod graph;
mod lights;
mod materials;
mod meshes;

pub use animation::SceneTime;
pub use extensions::SUPPORTED_EXTENSIONS;
pub use lights::{photometric_to_radiometric, LUMINOUS_EFFICACY};

#[cfg(doc)]
use crate::{GltfMaterial, MaterialKind};
use crate::{Image, Scene, SceneError, Texture, MAX_INPUT_BYTES};
use animation::Pose;
use camera::default_resolution;
use container::{parse_json, read_capped, split_glb, BaseDir, ReadError};
use gltf::json;
use graph::Instances;
use materials::default_material;
use meshes::LocalPrimitive;
use std::cell::Cell;
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::rc::Rc;

/// Loads a `.gltf` or `.glb` file, choosing the camera named `camera` if given.
///
/// External buffers and images are resolved relative to the file's directory (parent
/// directories are allowed). Fails with [`SceneError::TooLarge`] when the file or its
/// buffers exceed [`MAX_INPUT_BYTES`].
pub fn load_path(path: &Path, camera: Option<&str>) -> Result<Scene, SceneError> {
    load_path_at(path, camera, &SceneTime::default())
}

/// [`load_path`] with the scene evaluated at `time` (animations, skins and morph targets;
/// see the `animation` and `deform` steps). [`load_path`] is this at t = 0.
pub fn load_path_at(
    path: &Path,
    camera: Option<&str>,
    time: &SceneTime,
) -> Result<Scene, SceneError> {
    load_path_limited(path, camera, time, Limits::DEFAULT)
}

/// Loads a glTF document from memory; `base_dir` resolves external buffer/image URIs.
///
/// `bytes` is either glTF JSON or a `.glb`; `name` is used in error messages and as the
/// scene name. Without `base_dir` only embedded data (`data:` URIs, the GLB binary chunk)
/// is allowed. With it, external references must stay inside `base_dir` (no absolute
/// paths, no `..`), so uploads cannot read other files.
pub fn load_slice(
    bytes: &[u8],
    name: &str,
    base_dir: Option<&Path>,
    camera: Option<&str>,
) -> Result<Scene, SceneError> {
    load_slice_at(bytes, name, base_dir, camera, &SceneTime::default())
}

/// [`load_slice`] with the scene evaluated at `time`. [`load_slice`] is this at t = 0.
pub fn load_slice_at(
    bytes: &[u8],
    name: &str,
    base_dir: Option<&Path>,
    camera: Option<&str>,
    time: &SceneTime,
) -> Result<Scene, SceneError> {
    let base = base_dir.map(|dir| BaseDir {
        dir: dir.to_path_buf(),
        allow_parent: false,
    });
    load_bytes(bytes, name, base, camera, time, Limits::DEFAULT)
}

/// The caps an import runs under: the crate's constants, smaller ones in unit tests.
#[derive(Clone, Copy, Debug)]
struct Limits {
    /// [`MAX_INPUT_BYTES`]: the file, and the sum of its buffers and external images.
    bytes: u64,
    /// [`crate::MAX_IMAGE_TEXELS`].
    image_texels: u64,
    /// [`crate::MAX_SCENE_TEXELS`].
    scene_texels: u64,
    /// [`crate::MAX_NODES`], for every top-level array.
    elements: u64,
    /// [`crate::MAX_TRIANGLES`], stored.
    triangles: u64,
}

impl Limits {
    /// The documented limits.
    const DEFAULT: Limits = Limits {
        bytes: MAX_INPUT_BYTES,
        image_texels: crate::MAX_IMAGE_TEXELS,
        scene_texels: crate::MAX_SCENE_TEXELS,
        elements: crate::MAX_NODES,
        triangles: crate::MAX_TRIANGLES,
    };
}

/// [`load_path`] under `limits`.
fn load_path_limited(
    path: &Path,
    camera: Option<&str>,
    time: &SceneTime,
    limits: Limits,
) -> Result<Scene, SceneError> {
    let limit = limits.bytes;
    let file = path.display().to_string();
    let bytes = read_capped(path, limit).map_err(|e| match e {
        ReadError::Io(source) => SceneError::Io {
            path: file.clone(),
            source,
        },
        ReadError::TooLarge(bytes) => SceneError::TooLarge {
            path: file.clone(),
            bytes,
            limit,
        },
    })?;
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let base = BaseDir {
        dir,
        allow_parent: true,
    };
    load_bytes(&bytes, &file, Some(base), camera, time, limits)
}

/// Imports `bytes` (refused when over `limits.bytes`) under the panic guard.
fn load_bytes(
    bytes: &[u8],
    file: &str,
    base: Option<BaseDir>,
    camera: Option<&str>,
    time: &SceneTime,
    limits: Limits,
) -> Result<Scene, SceneError> {
    let limit = limits.bytes;
    if bytes.len() as u64 > limit {
        return Err(SceneError::TooLarge {
            path: file.to_string(),
            bytes: bytes.len() as u64,
            limit,
        });
    }
    let result = quietly(|| Importer::run(bytes, file, base, camera, time, limits));
    match result {
        Ok(r) => r,
        Err(panic) => Err(SceneError::Gltf {
            file: file.to_string(),
            message: format!("malformed glTF made the reader fail: {panic}"),
        }),
    }
}

thread_local! {
    /// Nonzero while this thread runs an import whose panics are caught.
    static QUIET: Cell<u32> = const { Cell::new(0) };
}

/// Runs `f`, turning a panic into `Err(message)`. The default panic message is not printed
/// for panics on this thread while `f` runs (a panic hook that defers to the previous hook
/// otherwise is installed once per process).
fn quietly<T>(f: impl FnOnce() -> T) -> Result<T, String> {
    static HOOK: std::sync::Once = std::sync::Once::new();
    HOOK.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if QUIET.try_with(|q| q.get()).unwrap_or(0) == 0 {
                previous(info);
            }
        }));
    });
    QUIET.with(|q| q.set(q.get() + 1));
    let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(f));
    QUIET.with(|q| q.set(q.get().saturating_sub(1)));
    result.map_err(|payload| {
        if let Some(s) = payload.downcast_ref::<&str>() {
            (*s).to_string()
        } else if let Some(s) = payload.downcast_ref::<String>() {
            s.clone()
        } else {
            "panic".to_string()
        }
    })
}

/// One import in progress: the document, where external files are resolved, the limits,
/// and what has been read and converted so far. Its steps are `impl` blocks in this
/// module's files.
struct Importer<'a> {
    file: &'a str,
    root: json::Root,
    base: Option<BaseDir>,
    /// `limits.bytes`, the input limit most steps check against.
    limit: u64,
    limits: Limits,
    /// Bytes of buffers and external images read so far.
    input_bytes: u64,
    /// Triangles stored so far (world-space meshes and prototypes), against
    /// [`crate::MAX_TRIANGLES`].
    stored_triangles: u64,
    /// Decoded texels of the images so far, against [`crate::MAX_SCENE_TEXELS`].
    texels: u64,
    /// Estimated bytes of output so far (a prototype counts once, an instance as its
    /// transform).
    output_bytes: u64,
    buffers: Vec<Vec<u8>>,
    textures: Vec<Texture>,
    images: Vec<Image>,
    /// glTF texture index -> index into `textures`.
    texture_map: HashMap<usize, u32>,
    /// glTF image index -> index into `images`.
    image_map: HashMap<usize, u32>,
    /// Per material: how many `TEXCOORD_n` sets its textures read (largest n + 1).
    material_uv_sets: Vec<u32>,
    /// Unknown optional extensions and other things the render plan should mention.
    warnings: Vec<String>,
    default_material_used: bool,
    primitives: HashMap<(usize, usize), Rc<LocalPrimitive>>,
    /// The animated node properties at the scene's time (empty without animations).
    pose: Pose,
    /// Per node: its world transform, once the walk has reached it (skins read their
    /// joints' from here).
    node_world: Vec<Option<glam::DMat4>>,
}

/// The result of an import step.
type Res<T> = Result<T, SceneError>;

impl<'a> Importer<'a> {
    /// An error about this file with `message`.
    fn err<T>(&self, message: impl Into<String>) -> Res<T> {
        Err(self.gerr(message))
    }

    /// The error value of [`Importer::err`].
    fn gerr(&self, message: impl Into<String>) -> SceneError {
        SceneError::Gltf {
            file: self.file.to_string(),
            message: message.into(),
        }
    }

    /// Splits the container, parses the JSON, checks the document, loads the buffers, then
    /// builds the scene.
    fn run(
        bytes: &[u8],
        file: &'a str,
        base: Option<BaseDir>,
        camera: Option<&str>,
        time: &SceneTime,
        limits: Limits,
    ) -> Res<Scene> {
        let gerr = |message: String| SceneError::Gltf {
            file: file.to_string(),
            message,
        };
        let (json_bytes, bin) = if bytes.starts_with(b"glTF") {
            split_glb(bytes).map_err(gerr)?
        } else {
            (bytes, None)
        };
        let root = parse_json(json_bytes, limits.elements).map_err(gerr)?;
        let mut imp = Importer {
            file,
            root,
            base,
            limit: limits.bytes,
            limits,
            input_bytes: 0,
            texels: 0,
            stored_triangles: 0,
            output_bytes: 0,
            buffers: Vec::new(),
            textures: Vec::new(),
            images: Vec::new(),
            texture_map: HashMap::new(),
            image_map: HashMap::new(),
            material_uv_sets: Vec::new(),
            warnings: Vec::new(),
            default_material_used: false,
            primitives: HashMap::new(),
            pose: Pose::default(),
            node_world: Vec::new(),
        };
        imp.check_extensions()?;
        imp.check_document()?;
        imp.load_buffers(bin)?;
        imp.pose = imp.evaluate_animations(time)?;
        imp.build(camera)
    }

    /// The steps after the container: materials and textures, the scene graph with its
    /// meshes, lights and cameras, then the camera; the result is validated.
    fn build(mut self, camera_name: Option<&str>) -> Res<Scene> {
        let mut materials = self.convert_materials()?;
        let roots = self.root_nodes()?;
        let Instances {
            placements,
            lights,
            cameras,
        } = self.walk(&roots)?;
        let geometry = self.place_meshes(&placements, &materials)?;
        drop(placements);
        if self.default_material_used {
            materials.push(default_material());
        }

        if geometry.triangle_count() == 0 && lights.is_empty() {
            return self.err("no geometry: the scene has no triangles and no lights");
        }

        let camera = self.choose_camera(camera_name, &cameras, &geometry, &lights)?;
        let default_resolution = default_resolution(&camera);
        let scene = Scene {
            name: self.file.to_string(),
            camera,
            meshes: geometry.meshes,
            prototypes: geometry.prototypes,
            instances: geometry.instances,
            spheres: Vec::new(),
            materials,
            textures: std::mem::take(&mut self.textures),
            images: std::mem::take(&mut self.images),
            warnings: std::mem::take(&mut self.warnings),
            lights,
            environment: None,
            environment_map: None,
            default_resolution,
            animated: !(self.pose.trs.is_empty() && self.pose.weights.is_empty()),
        };
        scene.validate()?;
        Ok(scene)
    }

    /// Counts `n` more stored triangles (for `what`) against [`crate::MAX_TRIANGLES`].
    fn add_triangles(&mut self, n: usize, what: &str) -> Res<()> {
        self.stored_triangles = self.stored_triangles.saturating_add(n as u64);
        let limit = self.limits.triangles;
        if self.stored_triangles > limit {
            return self.err(format!(
                "{what}: the scene would store more than {limit} triangles (MAX_TRIANGLES; \
                 a mesh placed at several nodes is stored once)"
            ));
        }
        Ok(())
    }

    /// Counts `bytes` of output against the output budget.
    fn add_output(&mut self, bytes: u64, what: &str) -> Res<()> {
        self.output_bytes = self.output_bytes.saturating_add(bytes);
        let budget = self.limit.saturating_mul(4);
        if self.output_bytes > budget {
            return self.err(format!(
                "{what}: the scene would need more than {budget} bytes \
                 (too many instances or texels)"
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The default limits with `n` input bytes.
    fn bytes(n: u64) -> Limits {
        Limits {
            bytes: n,
            ..Limits::DEFAULT
        }
    }

    #[test]
    fn inputs_over_the_limit_are_too_large() {
        let json = br#"{"asset":{"version":"2.0"}}"#;
        let r = load_bytes(json, "small", None, None, &SceneTime::default(), bytes(10));
        assert!(
            matches!(r, Err(SceneError::TooLarge { bytes, limit: 10, .. }) if bytes == json.len() as u64)
        );
        // A buffer whose declared length exceeds the limit is refused before decoding.
        let doc = br#"{"asset":{"version":"2.0"},"buffers":[{"byteLength":5000,"uri":"data:application/octet-stream;base64,AAAA"}]}"#;
        let r = load_bytes(
            doc,
            "buffers",
            None,
            None,
            &SceneTime::default(),
            bytes(1000),
        );
        assert!(
            matches!(
                r,
                Err(SceneError::TooLarge {
                    bytes: 5000,
                    limit: 1000,
                    ..
                })
            ),
            "{r:?}"
        );
    }

    /// A .glb with one triangle and one material per image, each a `w` x `h` PNG.
    fn glb_with_images(sizes: &[(u32, u32)]) -> Vec<u8> {
        let mut bin: Vec<u8> = [0.0f32, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let mut views = vec![serde_json::json!({"buffer": 0, "byteLength": 36})];
        let (mut images, mut textures, mut materials) = (vec![], vec![], vec![]);
        for (i, &(w, h)) in sizes.iter().enumerate() {
            let mut png = Vec::new();
            image::DynamicImage::new_luma8(w, h)
                .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
                .unwrap();
            while !bin.len().is_multiple_of(4) {
                bin.push(0);
            }
            views.push(
                serde_json::json!({"buffer": 0, "byteOffset": bin.len(), "byteLength": png.len()}),
            );
            bin.extend_from_slice(&png);
            images.push(serde_json::json!({"bufferView": i + 1, "mimeType": "image/png"}));
            textures.push(serde_json::json!({"source": i}));
            materials.push(
                serde_json::json!({"pbrMetallicRoughness": {"baseColorTexture": {"index": i}}}),
            );
        }
        let doc = serde_json::json!({
            "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
            "nodes": [{"mesh": 0}],
            "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
            "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                "min": [0, 0, 0], "max": [1, 1, 0]}],
            "bufferViews": views, "images": images, "textures": textures, "materials": materials,
            "buffers": [{"byteLength": bin.len()}],
        });
        let mut json = serde_json::to_vec(&doc).unwrap();
        while !json.len().is_multiple_of(4) {
            json.push(b' ');
        }
        while !bin.len().is_multiple_of(4) {
            bin.push(0);
        }
        let total = 12 + 8 + json.len() + 8 + bin.len();
        let mut out = b"glTF".to_vec();
        for v in [2, total as u32, json.len() as u32] {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out.extend_from_slice(b"JSON");
        out.extend_from_slice(&json);
        out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
        out.extend_from_slice(b"BIN\0");
        out.extend_from_slice(&bin);
        out
    }

    /// The texel budgets, per image and per scene, with small limits: each image is
    /// checked from its header, and the error names the image and the limit.
    #[test]
    fn images_over_the_texel_budgets_are_refused() {
        let limits = Limits {
            image_texels: 64,
            scene_texels: 100,
            ..Limits::DEFAULT
        };
        let load = |sizes: &[(u32, u32)]| {
            load_bytes(
                &glb_with_images(sizes),
                "t.glb",
                None,
                None,
                &SceneTime::default(),
                limits,
            )
        };
        let s = load(&[(8, 8), (6, 6)]).unwrap();
        assert_eq!(s.images.len(), 2);
        let e = load(&[(8, 8), (16, 5)]).unwrap_err().to_string();
        assert!(e.contains("image 1") && e.contains("16x5"), "{e}");
        assert!(e.contains("limit of 64 texels per image"), "{e}");
        let e = load(&[(8, 8), (6, 6), (1, 1)]).unwrap_err().to_string();
        assert!(e.contains("image 2") && e.contains("101 texels"), "{e}");
        assert!(e.contains("limit of 100 texels per scene"), "{e}");
    }

    /// Node and triangle caps, with small limits: an overlong top-level array is refused
    /// before the document is parsed, naming the array and the limit; stored triangles
    /// are counted as meshes are placed, naming the node and primitive.
    #[test]
    fn documents_over_the_node_and_triangle_caps_are_refused() {
        let glb = glb_with_images(&[]);
        let t0 = SceneTime::default();
        let with = |elements, triangles| Limits {
            elements,
            triangles,
            ..Limits::DEFAULT
        };
        assert!(load_bytes(&glb, "t.glb", None, None, &t0, with(1, 1)).is_ok());
        let e = load_bytes(&glb, "t.glb", None, None, &t0, with(1, 0))
            .unwrap_err()
            .to_string();
        assert!(e.contains("node 0 mesh 0 primitive 0"), "{e}");
        assert!(e.contains("more than 0 triangles (MAX_TRIANGLES"), "{e}");
        let nodes = br#"{"asset":{"version":"2.0"},"nodes":[{},{},{},{}]}"#;
        let e = load_bytes(nodes, "n.gltf", None, None, &t0, with(3, 1))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("\"nodes\" array has more than 3 elements (MAX_NODES)"),
            "{e}"
        );
        // Malformed JSON still gets the parser's own message.
        let e = load_bytes(b"{\"nodes\":[", "m.gltf", None, None, &t0, with(3, 1))
            .unwrap_err()
            .to_string();
        assert!(e.contains("invalid glTF JSON"), "{e}");
    }

    #[test]
    fn panics_become_errors() {
        let r: Result<(), String> = quietly(|| panic!("boom"));
        assert_eq!(r.unwrap_err(), "boom");
    }
}
