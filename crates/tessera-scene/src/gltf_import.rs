//! glTF 2.0 import: `.gltf` (external files or `data:` URIs) and `.glb`, flattened into a
//! world-space [`Scene`].
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
//!   error. Skins, morph targets and animations are ignored (the rest pose is rendered).
//! - **Geometry** (spec "Meshes"): every primitive of mode `TRIANGLES` becomes one
//!   [`Mesh`] named `mesh M 'Name' primitive P`, with positions transformed to world space,
//!   normals transformed by the inverse transpose and renormalized, texture coordinates
//!   (`TEXCOORD_0`, or the set the base-colour texture names in `texCoord`) and indices
//!   (or the implicit `0..n`). When the node's world transform has a negative determinant
//!   the winding is flipped, so triangles stay counter-clockwise seen from the front (spec
//!   "Meshes > Overview": the determinant of the global transform defines the winding).
//!   Other primitive modes are an error. A primitive whose transformed normals degenerate
//!   (zero length, e.g. from a zero scale) keeps its positions and drops its normals.
//! - **Camera** (spec "Cameras"): the first node, in depth-first order, carrying a
//!   perspective camera, or the one whose camera name or node name equals the requested
//!   name. `world_from_camera` is the node's world transform with scale removed (glTF
//!   cameras look down their local -Z with +Y up). Without any camera one is synthesized
//!   that looks down -Z from the +Z side and frames the bounding sphere of the geometry with
//!   a 45° vertical field of view.
//! - **Materials** (spec "Materials", "Metallic-Roughness Material", "Default Material"):
//!   `pbrMetallicRoughness` becomes [`MaterialKind::MetallicRoughness`] with
//!   `KHR_materials_transmission` (default 0) and `KHR_materials_ior` (default 1.5).
//!   Emission is `emissiveFactor` x `KHR_materials_emissive_strength` (default 1),
//!   interpreted as linear-RGB radiance in W/(m² sr). Primitives without a material use the
//!   default material (base colour 1, metallic 1, roughness 1). Alpha modes, normal,
//!   occlusion, emissive and metallic-roughness textures are not used.
//! - **Textures** (spec "Textures", "Samplers", "Images"): base-colour textures are decoded
//!   (PNG or JPEG, 8 or 16 bits, grey or colour; alpha is dropped) and converted from sRGB to
//!   linear with the exact sRGB EOTF of IEC 61966-2-1. Row 0 is the top row of the image,
//!   which is where glTF puts texture coordinate v = 0. A sampler wrapping with `REPEAT` or
//!   `MIRRORED_REPEAT` in either direction (or no sampler, which defaults to repeat) gives
//!   a repeating texture; mirroring is approximated by repetition. Only clamping in both
//!   directions gives a clamped texture.
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
//! images) and the flattened output at four times that. Every error names the file and the
//! element (node, mesh, primitive, material, accessor, buffer view, buffer, image index)
//! that is wrong.

use crate::{
    Camera, Material, MaterialKind, Mesh, PunctualLight, Scene, SceneError, Texture, TextureRef,
    MAX_INPUT_BYTES,
};
use glam::{DMat3, DMat4, DQuat, DVec3, Vec2, Vec3};
use gltf::json;
use json::accessor::{ComponentType, GenericComponentType, IndexComponentType, Type};
use json::extensions::scene::khr_lights_punctual as khr_lights;
use json::validation::Checked;
use std::cell::Cell;
use std::collections::HashMap;
use std::io::Read;
use std::path::{Component, Path, PathBuf};
use std::rc::Rc;

/// Luminous efficacy used to convert `KHR_lights_punctual` photometric units to radiometric
/// ones: 683 lm/W, the efficacy of monochromatic light at 540 THz (~555 nm) that defines the
/// candela in the SI.
pub const LUMINOUS_EFFICACY: f32 = 683.0;

/// Image height of [`Scene::default_resolution`] for imported scenes, in pixels.
const DEFAULT_HEIGHT: u32 = 512;
/// Widest default image an extreme aspect ratio may ask for.
const MAX_DEFAULT_WIDTH: u32 = 16384;
/// Largest texture side accepted, in texels.
const MAX_TEXTURE_SIDE: u32 = 1 << 15;

/// Converts a `KHR_lights_punctual` light colour and photometric intensity to radiometric
/// units, per linear-RGB channel: `color * intensity / 683`.
///
/// For point and spot lights the glTF intensity is luminous intensity in candela (lm/sr)
/// and the result is radiant intensity in W/sr; for directional lights it is illuminance in
/// lux (lm/m²) and the result is irradiance in W/m² on a surface facing the light. 683 lm/W
/// ([`LUMINOUS_EFFICACY`]) is the luminous efficacy of 555 nm light, the definition of the
/// candela; applying it to every channel is the usual glTF convention.
pub fn photometric_to_radiometric(color: [f32; 3], intensity: f32) -> Vec3 {
    Vec3::from(color) * (intensity / LUMINOUS_EFFICACY)
}

/// Loads a `.gltf` or `.glb` file, choosing the camera named `camera` if given.
///
/// External buffers and images are resolved relative to the file's directory (parent
/// directories are allowed). Fails with [`SceneError::TooLarge`] when the file or its
/// buffers exceed [`MAX_INPUT_BYTES`].
pub fn load_path(path: &Path, camera: Option<&str>) -> Result<Scene, SceneError> {
    load_path_limited(path, camera, MAX_INPUT_BYTES)
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
    let base = base_dir.map(|dir| BaseDir {
        dir: dir.to_path_buf(),
        allow_parent: false,
    });
    load_bytes(bytes, name, base, camera, MAX_INPUT_BYTES)
}

/// Where external URIs are resolved.
struct BaseDir {
    dir: PathBuf,
    /// Whether `..` components may leave `dir`.
    allow_parent: bool,
}

fn load_path_limited(path: &Path, camera: Option<&str>, limit: u64) -> Result<Scene, SceneError> {
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
    load_bytes(&bytes, &file, Some(base), camera, limit)
}

enum ReadError {
    Io(std::io::Error),
    TooLarge(u64),
}

/// Reads a whole file, refusing (before reading) files larger than `limit` bytes.
fn read_capped(path: &Path, limit: u64) -> Result<Vec<u8>, ReadError> {
    let file = std::fs::File::open(path).map_err(ReadError::Io)?;
    let meta = file.metadata().map_err(ReadError::Io)?;
    if meta.is_dir() {
        return Err(ReadError::Io(std::io::Error::other("is a directory")));
    }
    if meta.len() > limit {
        return Err(ReadError::TooLarge(meta.len()));
    }
    let mut bytes = Vec::with_capacity(meta.len() as usize);
    // The file may grow between the metadata call and the read: read at most limit + 1.
    file.take(limit.saturating_add(1))
        .read_to_end(&mut bytes)
        .map_err(ReadError::Io)?;
    if bytes.len() as u64 > limit {
        return Err(ReadError::TooLarge(bytes.len() as u64));
    }
    Ok(bytes)
}

fn load_bytes(
    bytes: &[u8],
    file: &str,
    base: Option<BaseDir>,
    camera: Option<&str>,
    limit: u64,
) -> Result<Scene, SceneError> {
    if bytes.len() as u64 > limit {
        return Err(SceneError::TooLarge {
            path: file.to_string(),
            bytes: bytes.len() as u64,
            limit,
        });
    }
    let result = quietly(|| Importer::run(bytes, file, base, camera, limit));
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

/// Mesh data of one primitive in its mesh's local space, shared by every node instancing it.
struct LocalPrimitive {
    positions: Vec<Vec3>,
    normals: Option<Vec<Vec3>>,
    uvs: Option<Vec<Vec2>>,
    triangles: Vec<[u32; 3]>,
    material: u32,
}

/// A perspective camera found while walking the scene graph.
struct CameraCandidate {
    node: usize,
    camera: usize,
    world: DMat4,
}

struct Importer<'a> {
    file: &'a str,
    root: json::Root,
    base: Option<BaseDir>,
    limit: u64,
    /// Bytes of buffers and external images read so far.
    input_bytes: u64,
    /// Estimated bytes of flattened output so far.
    output_bytes: u64,
    buffers: Vec<Vec<u8>>,
    textures: Vec<Texture>,
    /// (image index, repeat) -> index into `textures`.
    texture_map: HashMap<(usize, bool), u32>,
    /// Texture-coordinate set each material's base-colour texture reads.
    material_uv_set: Vec<u32>,
    default_material_used: bool,
    primitives: HashMap<(usize, usize), Rc<LocalPrimitive>>,
}

type Res<T> = Result<T, SceneError>;

impl<'a> Importer<'a> {
    fn err<T>(&self, message: impl Into<String>) -> Res<T> {
        Err(SceneError::Gltf {
            file: self.file.to_string(),
            message: message.into(),
        })
    }

    fn run(
        bytes: &[u8],
        file: &'a str,
        base: Option<BaseDir>,
        camera: Option<&str>,
        limit: u64,
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
        let root = parse_json(json_bytes).map_err(gerr)?;
        let mut imp = Importer {
            file,
            root,
            base,
            limit,
            input_bytes: 0,
            output_bytes: 0,
            buffers: Vec::new(),
            textures: Vec::new(),
            texture_map: HashMap::new(),
            material_uv_set: Vec::new(),
            default_material_used: false,
            primitives: HashMap::new(),
        };
        imp.check_document()?;
        imp.load_buffers(bin)?;
        imp.build(camera)
    }

    /// Loads every buffer (GLB binary chunk, `data:` URI or external file) and checks its
    /// length against its `byteLength` (spec "Buffers and Buffer Views").
    fn load_buffers(&mut self, mut bin: Option<&[u8]>) -> Res<()> {
        let declared: u64 = self
            .root
            .buffers
            .iter()
            .fold(0u64, |sum, b| sum.saturating_add(b.byte_length.0));
        if declared > self.limit {
            return Err(SceneError::TooLarge {
                path: format!("{} (sum of buffer byteLengths)", self.file),
                bytes: declared,
                limit: self.limit,
            });
        }
        let mut buffers = Vec::with_capacity(self.root.buffers.len());
        for i in 0..self.root.buffers.len() {
            let what = format!("buffer {i}");
            let (uri, len) = (
                self.root.buffers[i].uri.clone(),
                self.root.buffers[i].byte_length.0,
            );
            let mut data = match &uri {
                None => match bin.take() {
                    // Spec "GLB File Format Specification > Binary buffer": the BIN chunk
                    // is the first buffer, the one without a uri.
                    Some(b) if i == 0 => b.to_vec(),
                    _ => {
                        return self.err(format!(
                            "{what} has no uri and there is no GLB binary chunk for it"
                        ))
                    }
                },
                Some(uri) => self.read_uri(uri, &what)?.1,
            };
            if (data.len() as u64) < len {
                return self.err(format!(
                    "{what} declares byteLength {len} but its data has only {} bytes",
                    data.len()
                ));
            }
            data.truncate(len as usize);
            buffers.push(data);
        }
        self.buffers = buffers;
        Ok(())
    }

    /// Reads the bytes a URI refers to: a base64 `data:` URI or a relative path. Returns the
    /// media type of a data URI (if it names one) and the bytes.
    fn read_uri(&mut self, uri: &str, what: &str) -> Res<(Option<String>, Vec<u8>)> {
        let shown = truncate_for_message(uri);
        if let Some(rest) = uri.strip_prefix("data:") {
            let Some((meta, payload)) = rest.split_once(',') else {
                return self.err(format!("{what}: data URI without ',': {shown:?}"));
            };
            let Some(mime) = meta.strip_suffix(";base64") else {
                return self.err(format!(
                    "{what}: only base64 data URIs are supported, got {shown:?}"
                ));
            };
            let data = decode_base64(payload)
                .or_else(|e| self.err(format!("{what}: bad base64 in data URI: {e}")))?;
            let mime = (!mime.is_empty()).then(|| mime.to_string());
            return Ok((mime, data));
        }
        if has_scheme(uri) {
            return self.err(format!(
                "{what}: URI {shown:?} is not supported (only data: URIs and relative paths)"
            ));
        }
        let relative = match percent_decode(uri) {
            Ok(p) => p,
            Err(e) => return self.err(format!("{what}: URI {shown:?}: {e}")),
        };
        let Some(base) = &self.base else {
            return self.err(format!(
                "{what} refers to the external file {shown:?}, but the document was given \
                 in memory without a base directory (embed it as a data: URI or use .glb)"
            ));
        };
        let rel = Path::new(&relative);
        for c in rel.components() {
            match c {
                Component::Normal(_) | Component::CurDir => {}
                Component::ParentDir if base.allow_parent => {}
                _ => {
                    return self.err(format!(
                        "{what}: URI {shown:?} must be a relative path inside the base directory"
                    ))
                }
            }
        }
        let path = base.dir.join(rel);
        let remaining = self.limit.saturating_sub(self.input_bytes);
        let data = match read_capped(&path, remaining) {
            Ok(d) => d,
            Err(ReadError::Io(e)) => {
                return self.err(format!(
                    "{what}: cannot read URI {shown:?} ({}): {e}",
                    path.display()
                ))
            }
            Err(ReadError::TooLarge(bytes)) => {
                return Err(SceneError::TooLarge {
                    path: format!("{} ({what}: {})", self.file, path.display()),
                    bytes: bytes.saturating_add(self.input_bytes),
                    limit: self.limit,
                })
            }
        };
        self.input_bytes += data.len() as u64;
        Ok((None, data))
    }

    /// The bytes of buffer view `vi`, checked against its buffer.
    fn view_bytes(&self, vi: usize, what: &str) -> Res<&[u8]> {
        let Some(view) = self.root.buffer_views.get(vi) else {
            return self.err(format!(
                "{what} refers to bufferView {vi}, but there are only {}",
                self.root.buffer_views.len()
            ));
        };
        let bi = view.buffer.value();
        let Some(buffer) = self.buffers.get(bi) else {
            return self.err(format!(
                "bufferView {vi} ({what}) refers to buffer {bi}, but there are only {}",
                self.buffers.len()
            ));
        };
        let offset = view.byte_offset.map_or(0, |o| o.0);
        let len = view.byte_length.0;
        match offset.checked_add(len) {
            Some(end) if end <= buffer.len() as u64 => Ok(&buffer[offset as usize..end as usize]),
            _ => self.err(format!(
                "bufferView {vi} ({what}): bytes {offset}..{} are past the end of buffer {bi} \
                 ({} bytes)",
                offset as u128 + len as u128,
                buffer.len()
            )),
        }
    }

    /// The elements of accessor `ai`, tightly packed (strides removed, sparse substitution
    /// applied), with their component type and component count (spec "Accessors").
    fn packed_accessor(&self, ai: usize, what: &str) -> Res<(Vec<u8>, ComponentType, usize)> {
        let Some(acc) = self.root.accessors.get(ai) else {
            return self.err(format!(
                "{what} refers to accessor {ai}, but there are only {}",
                self.root.accessors.len()
            ));
        };
        let what = format!("accessor {ai} ({what})");
        let Checked::Valid(GenericComponentType(ct)) = acc.component_type else {
            return self.err(format!("{what} has an invalid componentType"));
        };
        let Checked::Valid(ty) = acc.type_ else {
            return self.err(format!("{what} has an invalid type"));
        };
        let ncomp = match ty {
            Type::Scalar => 1,
            Type::Vec2 => 2,
            Type::Vec3 => 3,
            Type::Vec4 => 4,
            _ => return self.err(format!("{what}: matrix accessors are not supported here")),
        };
        let elem = ncomp * ct.size();
        let count = acc.count.0;
        let total = match count.checked_mul(elem as u64) {
            Some(t) if t <= self.limit => t as usize,
            _ => return self.err(format!("{what}: count {count} is too large")),
        };
        let count = count as usize;
        let mut out = vec![0u8; total];
        if let Some(vi) = acc.buffer_view {
            let vi = vi.value();
            let bytes = self.view_bytes(vi, &what)?;
            let stride = match self.root.buffer_views[vi].byte_stride {
                Some(s) if s.0 < elem => {
                    return self.err(format!(
                        "{what}: bufferView {vi} byteStride {} is smaller than an element \
                         ({elem} bytes)",
                        s.0
                    ))
                }
                Some(s) => s.0,
                None => elem,
            };
            let offset = acc.byte_offset.map_or(0, |o| o.0);
            if count > 0 {
                let need = (count as u128 - 1) * stride as u128 + elem as u128 + offset as u128;
                if need > bytes.len() as u128 {
                    return self.err(format!(
                        "{what}: {count} elements of {elem} bytes at offset {offset} with \
                         stride {stride} need {need} bytes, but bufferView {vi} has only {}",
                        bytes.len()
                    ));
                }
                let offset = offset as usize;
                for (i, dst) in out.chunks_exact_mut(elem).enumerate() {
                    let start = offset + i * stride;
                    dst.copy_from_slice(&bytes[start..start + elem]);
                }
            }
        }
        if let Some(sparse) = &acc.sparse {
            let n = sparse.count.0;
            if n > count as u64 {
                return self.err(format!(
                    "{what}: sparse count {n} exceeds the accessor count {count}"
                ));
            }
            let n = n as usize;
            let Checked::Valid(IndexComponentType(ict)) = sparse.indices.component_type else {
                return self.err(format!("{what}: invalid sparse index componentType"));
            };
            if !matches!(
                ict,
                ComponentType::U8 | ComponentType::U16 | ComponentType::U32
            ) {
                return self.err(format!("{what}: sparse indices must be unsigned integers"));
            }
            let isz = ict.size();
            let ivi = sparse.indices.buffer_view.value();
            let ibytes = self.view_bytes(ivi, &format!("{what} sparse indices"))?;
            let ioff = sparse.indices.byte_offset.0;
            let vvi = sparse.values.buffer_view.value();
            let vbytes = self.view_bytes(vvi, &format!("{what} sparse values"))?;
            let voff = sparse.values.byte_offset.0;
            if ioff as u128 + (n * isz) as u128 > ibytes.len() as u128
                || voff as u128 + (n * elem) as u128 > vbytes.len() as u128
            {
                return self.err(format!(
                    "{what}: sparse indices or values run past their bufferViews ({ivi}, {vvi})"
                ));
            }
            let (ioff, voff) = (ioff as usize, voff as usize);
            for k in 0..n {
                let idx = read_uint(ict, &ibytes[ioff + k * isz..]) as usize;
                if idx >= count {
                    return self.err(format!(
                        "{what}: sparse index {k} = {idx} is past the accessor count {count}"
                    ));
                }
                out[idx * elem..(idx + 1) * elem]
                    .copy_from_slice(&vbytes[voff + k * elem..voff + (k + 1) * elem]);
            }
        }
        Ok((out, ct, ncomp))
    }

    /// Reads a float (or normalized/integer) accessor with `n` components per element.
    fn read_floats<const N: usize>(&self, ai: usize, what: &str) -> Res<Vec<[f32; N]>> {
        let (bytes, ct, ncomp) = self.packed_accessor(ai, what)?;
        if ncomp != N {
            return self.err(format!(
                "accessor {ai} ({what}) has {ncomp} components per element, expected {N}"
            ));
        }
        let normalized = self.root.accessors[ai].normalized;
        let cs = ct.size();
        let out: Vec<[f32; N]> = bytes
            .chunks_exact(N * cs)
            .map(|e| std::array::from_fn(|j| read_float(ct, normalized, &e[j * cs..])))
            .collect();
        if let Some(i) = out.iter().position(|v| v.iter().any(|c| !c.is_finite())) {
            return self.err(format!(
                "accessor {ai} ({what}) element {i} is not finite: {:?}",
                out[i]
            ));
        }
        Ok(out)
    }

    /// Reads an index accessor (unsigned scalar integers, spec "Meshes > Overview").
    fn read_indices(&self, ai: usize, what: &str) -> Res<Vec<u32>> {
        let (bytes, ct, ncomp) = self.packed_accessor(ai, what)?;
        if ncomp != 1
            || !matches!(
                ct,
                ComponentType::U8 | ComponentType::U16 | ComponentType::U32
            )
        {
            return self.err(format!(
                "accessor {ai} ({what}) must be SCALAR unsigned byte/short/int indices"
            ));
        }
        let cs = ct.size();
        Ok(bytes.chunks_exact(cs).map(|b| read_uint(ct, b)).collect())
    }

    /// Walks the scene graph and assembles the scene.
    fn build(mut self, camera_name: Option<&str>) -> Res<Scene> {
        let materials = self.convert_materials()?;

        // Which nodes to start from (spec "Scenes").
        let roots: Vec<usize> = if let Some(s) = self.root.scene {
            let Some(scene) = self.root.scenes.get(s.value()) else {
                return self.err(format!(
                    "the default scene {} is past the end ({} scenes)",
                    s.value(),
                    self.root.scenes.len()
                ));
            };
            scene.nodes.iter().map(|n| n.value()).collect()
        } else if let Some(s) = self.root.scenes.first() {
            s.nodes.iter().map(|n| n.value()).collect()
        } else {
            let mut is_child = vec![false; self.root.nodes.len()];
            for node in &self.root.nodes {
                for c in node.children.iter().flatten() {
                    if let Some(flag) = is_child.get_mut(c.value()) {
                        *flag = true;
                    }
                }
            }
            (0..self.root.nodes.len())
                .filter(|&i| !is_child[i])
                .collect()
        };

        let mut meshes = Vec::new();
        let mut lights = Vec::new();
        let mut cameras = Vec::new();
        let mut visited = vec![false; self.root.nodes.len()];
        // Depth-first, pre-order, children in order (explicit stack: no recursion limit).
        let mut stack: Vec<(usize, DMat4)> =
            roots.iter().rev().map(|&n| (n, DMat4::IDENTITY)).collect();
        while let Some((ni, parent)) = stack.pop() {
            if ni >= self.root.nodes.len() {
                return self.err(format!(
                    "node index {ni} is past the end ({} nodes)",
                    self.root.nodes.len()
                ));
            }
            if std::mem::replace(&mut visited[ni], true) {
                return self.err(format!(
                    "node {ni} is reached twice: the node hierarchy must be a set of disjoint \
                     trees (spec \"Nodes and Hierarchy\")"
                ));
            }
            let world = parent * self.local_transform(ni)?;
            if !world.is_finite() {
                return self.err(format!("node {ni}: world transform is not finite"));
            }
            if let Some(m) = self.root.nodes[ni].mesh {
                self.instance_mesh(ni, m.value(), &world, &mut meshes)?;
            }
            let node = &self.root.nodes[ni];
            if let Some(c) = node.camera {
                let ci = c.value();
                let cam = self.root.cameras.get(ci);
                if cam.is_some_and(|c| c.type_ == Checked::Valid(json::camera::Type::Perspective)) {
                    cameras.push(CameraCandidate {
                        node: ni,
                        camera: ci,
                        world,
                    });
                }
            }
            if let Some(ext) = node
                .extensions
                .as_ref()
                .and_then(|e| e.khr_lights_punctual.as_ref())
            {
                lights.push(self.convert_light(ni, ext.light.value(), &world)?);
            }
            if let Some(children) = &node.children {
                for c in children.iter().rev() {
                    stack.push((c.value(), world));
                }
            }
        }

        let mut materials = materials;
        if self.default_material_used {
            // Spec "Default Material": base colour 1, metallic 1, roughness 1.
            materials.push(Material {
                name: "glTF default material".into(),
                kind: MaterialKind::MetallicRoughness {
                    base_color: Vec3::ONE,
                    base_color_texture: None,
                    metallic: 1.0,
                    roughness: 1.0,
                    transmission: 0.0,
                    ior: 1.5,
                },
                emission: Vec3::ZERO,
                double_sided: false,
            });
        }

        let triangles: usize = meshes.iter().map(|m: &Mesh| m.indices.len()).sum();
        if triangles == 0 && lights.is_empty() {
            return self.err("no geometry: the scene has no triangles and no lights");
        }

        let camera = self.choose_camera(camera_name, &cameras, &meshes, &lights)?;
        let default_resolution = match camera.aspect_ratio {
            Some(a) => {
                let w = (DEFAULT_HEIGHT as f32 * a).round();
                (
                    w.clamp(1.0, MAX_DEFAULT_WIDTH as f32) as u32,
                    DEFAULT_HEIGHT,
                )
            }
            None => (DEFAULT_HEIGHT, DEFAULT_HEIGHT),
        };
        let scene = Scene {
            name: self.file.to_string(),
            camera,
            meshes,
            spheres: Vec::new(),
            materials,
            textures: std::mem::take(&mut self.textures),
            lights,
            environment: None,
            default_resolution,
        };
        scene.validate()?;
        Ok(scene)
    }

    /// Checks the document as a whole: the asset version, then the `gltf` crate's
    /// validation of indices and required properties (run under the caller's panic guard,
    /// after the pre-checks below that would otherwise panic inside it).
    fn check_document(&mut self) -> Res<()> {
        let version = self.root.asset.version.clone();
        if version.split('.').next() != Some("2") {
            return self.err(format!(
                "asset.version is {version:?}; only glTF 2.x is supported"
            ));
        }
        let naccessors = self.root.accessors.len();
        let nmaterials = self.root.materials.len();
        for (mi, mesh) in self.root.meshes.iter().enumerate() {
            for (pi, prim) in mesh.primitives.iter().enumerate() {
                let what = prim_name(mi, mesh, pi);
                for (semantic, a) in &prim.attributes {
                    if a.value() >= naccessors {
                        return self.err(format!(
                            "{what}: attribute {} refers to accessor {}, but there are only \
                             {naccessors}",
                            semantic_name(semantic),
                            a.value()
                        ));
                    }
                }
                if let Some(a) = prim.indices.filter(|a| a.value() >= naccessors) {
                    return self.err(format!(
                        "{what}: indices refer to accessor {}, but there are only {naccessors}",
                        a.value()
                    ));
                }
                if let Some(m) = prim.material.filter(|m| m.value() >= nmaterials) {
                    return self.err(format!(
                        "{what}: material index {} is past the end ({nmaterials} materials)",
                        m.value()
                    ));
                }
            }
        }
        let root = std::mem::take(&mut self.root);
        match gltf::Document::from_json(root) {
            Ok(doc) => {
                self.root = doc.into_json();
                Ok(())
            }
            Err(gltf::Error::Validation(errors)) => {
                let mut message = String::from("invalid glTF:");
                for (path, error) in errors.iter().take(8) {
                    message.push_str(&format!(" {path}: {error};"));
                }
                if errors.len() > 8 {
                    message.push_str(&format!(" and {} more", errors.len() - 8));
                }
                self.err(message)
            }
            Err(e) => self.err(format!("invalid glTF: {e}")),
        }
    }

    /// The local transform of node `ni` (spec "Transformations": a column-major `matrix`,
    /// or `T * R * S`). Non-finite values are an error naming the node.
    fn local_transform(&self, ni: usize) -> Res<DMat4> {
        let node = &self.root.nodes[ni];
        if let Some(m) = node.matrix {
            if m.iter().any(|v| !v.is_finite()) {
                return self.err(format!("node {ni}: matrix contains NaN or infinity: {m:?}"));
            }
            return Ok(DMat4::from_cols_array(&m.map(f64::from)));
        }
        let t = node.translation.unwrap_or([0.0; 3]);
        let r = node.rotation.as_ref().map_or([0.0, 0.0, 0.0, 1.0], |q| q.0);
        let s = node.scale.unwrap_or([1.0; 3]);
        if t.iter().chain(&r).chain(&s).any(|v| !v.is_finite()) {
            return self.err(format!(
                "node {ni}: translation/rotation/scale contains NaN or infinity \
                 (t {t:?}, r {r:?}, s {s:?})"
            ));
        }
        let q = DQuat::from_xyzw(r[0].into(), r[1].into(), r[2].into(), r[3].into());
        let len = q.length();
        if !len.is_finite() || len <= 1e-6 {
            return self.err(format!(
                "node {ni}: rotation quaternion {r:?} has zero length"
            ));
        }
        Ok(DMat4::from_scale_rotation_translation(
            DVec3::from(s.map(f64::from)),
            q / len,
            DVec3::from(t.map(f64::from)),
        ))
    }

    /// Converts every glTF material, in order (scene material i = glTF material i).
    fn convert_materials(&mut self) -> Res<Vec<Material>> {
        let mut out = Vec::with_capacity(self.root.materials.len());
        for mi in 0..self.root.materials.len() {
            let m = &self.root.materials[mi];
            let name = match &m.name {
                Some(n) => format!("material {mi} '{n}'"),
                None => format!("material {mi}"),
            };
            let pbr = &m.pbr_metallic_roughness;
            let [r, g, b, _alpha] = pbr.base_color_factor.0;
            let texture_info = pbr
                .base_color_texture
                .as_ref()
                .map(|t| (t.index.value(), t.tex_coord));
            let ext = m.extensions.as_ref();
            let transmission = ext
                .and_then(|e| e.transmission.as_ref())
                .map_or(0.0, |t| t.transmission_factor.0);
            let ior = ext.and_then(|e| e.ior.as_ref()).map_or(1.5, |i| i.ior.0);
            let strength = ext
                .and_then(|e| e.emissive_strength.as_ref())
                .map_or(1.0, |s| s.emissive_strength.0);
            let emission = Vec3::from(m.emissive_factor.0) * strength;
            let (metallic, roughness) = (pbr.metallic_factor.0, pbr.roughness_factor.0);
            let double_sided = m.double_sided;
            let base_color_texture = match texture_info {
                Some((ti, _)) => Some(self.texture(ti, &name)?),
                None => None,
            };
            self.material_uv_set
                .push(texture_info.map_or(0, |(_, set)| set));
            out.push(Material {
                name,
                kind: MaterialKind::MetallicRoughness {
                    base_color: Vec3::new(r, g, b),
                    base_color_texture,
                    metallic,
                    roughness,
                    transmission,
                    ior,
                },
                emission,
                double_sided,
            });
        }
        Ok(out)
    }

    /// Decodes (once per image and wrap mode) the texture `ti` used by `what`.
    fn texture(&mut self, ti: usize, what: &str) -> Res<TextureRef> {
        let Some(tex) = self.root.textures.get(ti) else {
            return self.err(format!(
                "{what} refers to texture {ti}, but there are only {}",
                self.root.textures.len()
            ));
        };
        let ii = tex.source.value();
        // Spec "Samplers": without a sampler, repeat wrapping should be used.
        let repeat = match tex.sampler.map(|s| self.root.samplers.get(s.value())) {
            None => true,
            Some(None) => return self.err(format!("texture {ti} refers to a missing sampler")),
            Some(Some(s)) => {
                let clamp = Checked::Valid(json::texture::WrappingMode::ClampToEdge);
                !(s.wrap_s == clamp && s.wrap_t == clamp)
            }
        };
        if let Some(&t) = self.texture_map.get(&(ii, repeat)) {
            return Ok(TextureRef { texture: t });
        }
        let mut texture = self.decode_image(ii, &format!("texture {ti} of {what}"))?;
        texture.repeat = repeat;
        let index = self.textures.len() as u32;
        self.textures.push(texture);
        self.texture_map.insert((ii, repeat), index);
        Ok(TextureRef { texture: index })
    }

    /// Decodes image `ii` (PNG or JPEG) into a linear-RGB texture (spec "Images").
    fn decode_image(&mut self, ii: usize, what: &str) -> Res<Texture> {
        let Some(image) = self.root.images.get(ii) else {
            return self.err(format!(
                "{what} refers to image {ii}, but there are only {}",
                self.root.images.len()
            ));
        };
        let what = format!("image {ii} ({what})");
        let (declared, bytes) = if let Some(vi) = image.buffer_view {
            // Spec "Images": mimeType must be defined when bufferView is defined.
            let Some(mime) = &image.mime_type else {
                return self.err(format!(
                    "{what} has a bufferView but no mimeType (the spec requires one)"
                ));
            };
            let mime = mime.0.clone();
            (Some(mime), self.view_bytes(vi.value(), &what)?.to_vec())
        } else if let Some(uri) = image.uri.clone() {
            let declared = image.mime_type.as_ref().map(|m| m.0.clone());
            let (data_mime, bytes) = self.read_uri(&uri, &what)?;
            (data_mime.or(declared), bytes)
        } else {
            return self.err(format!("{what} has neither a uri nor a bufferView"));
        };
        let format = if bytes.starts_with(b"\x89PNG\r\n\x1a\n") {
            image::ImageFormat::Png
        } else if bytes.starts_with(&[0xff, 0xd8, 0xff]) {
            image::ImageFormat::Jpeg
        } else {
            return self.err(format!(
                "{what} is not a PNG or JPEG image (declared media type {declared:?})"
            ));
        };
        let mut reader = image::ImageReader::with_format(std::io::Cursor::new(&bytes), format);
        let mut limits = image::Limits::default();
        limits.max_image_width = Some(MAX_TEXTURE_SIDE);
        limits.max_image_height = Some(MAX_TEXTURE_SIDE);
        limits.max_alloc = Some(self.limit.min(1 << 30));
        reader.limits(limits);
        let decoded = match reader.decode() {
            Ok(d) => d,
            Err(e) => return self.err(format!("{what}: cannot decode {format:?}: {e}")),
        };
        let (width, height) = (decoded.width(), decoded.height());
        let texels = width as u64 * height as u64;
        self.add_output(texels * 12, &what)?;
        if texels == 0 {
            return self.err(format!("{what} is empty"));
        }
        let color = decoded.color();
        let depth = color.bits_per_pixel() / u16::from(color.channel_count());
        let texels: Vec<Vec3> = match depth {
            8 => {
                let lut: Vec<f32> = (0..256)
                    .map(|v| srgb_to_linear(v as f64 / 255.0) as f32)
                    .collect();
                decoded
                    .into_rgb8()
                    .pixels()
                    .map(|p| Vec3::new(lut[p[0] as usize], lut[p[1] as usize], lut[p[2] as usize]))
                    .collect()
            }
            16 => decoded
                .into_rgb16()
                .pixels()
                .map(|p| Vec3::from(p.0.map(|c| srgb_to_linear(c as f64 / 65535.0) as f32)))
                .collect(),
            _ => decoded
                .into_rgb32f()
                .pixels()
                .map(|p| Vec3::from(p.0.map(|c| srgb_to_linear(c as f64) as f32)))
                .collect(),
        };
        Ok(Texture {
            width,
            height,
            texels,
            repeat: true,
        })
    }

    /// Counts `bytes` of flattened output against the output budget.
    fn add_output(&mut self, bytes: u64, what: &str) -> Res<()> {
        self.output_bytes = self.output_bytes.saturating_add(bytes);
        let budget = self.limit.saturating_mul(4);
        if self.output_bytes > budget {
            return self.err(format!(
                "{what}: the flattened scene would need more than {budget} bytes \
                 (too many instances or texels)"
            ));
        }
        Ok(())
    }

    /// Reads primitive `pi` of mesh `mi` in local space (cached across instances).
    fn local_primitive(&mut self, mi: usize, pi: usize) -> Res<Rc<LocalPrimitive>> {
        if let Some(p) = self.primitives.get(&(mi, pi)) {
            return Ok(p.clone());
        }
        let mesh = &self.root.meshes[mi];
        let prim = &mesh.primitives[pi];
        let what = prim_name(mi, mesh, pi);
        match prim.mode {
            Checked::Valid(json::mesh::Mode::Triangles) => {}
            Checked::Valid(mode) => {
                return self.err(format!(
                    "{what}: primitive mode {mode:?} is not supported (only TRIANGLES)"
                ))
            }
            Checked::Invalid => return self.err(format!("{what}: invalid primitive mode")),
        }
        let attribute = |s: json::mesh::Semantic| prim.attributes.get(&Checked::Valid(s)).copied();
        let Some(pos) = attribute(json::mesh::Semantic::Positions) else {
            return self.err(format!("{what} has no POSITION attribute"));
        };
        let material = match prim.material {
            Some(m) => m.value() as u32,
            None => {
                self.default_material_used = true;
                self.root.materials.len() as u32
            }
        };
        let uv_set = prim
            .material
            .and_then(|m| self.material_uv_set.get(m.value()).copied())
            .unwrap_or(0);
        let normal_acc = attribute(json::mesh::Semantic::Normals);
        let uv_acc = attribute(json::mesh::Semantic::TexCoords(uv_set));
        let index_acc = prim.indices;

        let positions: Vec<Vec3> = self
            .read_floats::<3>(pos.value(), &format!("{what} POSITION"))?
            .into_iter()
            .map(Vec3::from)
            .collect();
        let n = positions.len();
        let normals = match normal_acc {
            Some(a) => {
                let v = self.read_floats::<3>(a.value(), &format!("{what} NORMAL"))?;
                if v.len() != n {
                    return self.err(format!(
                        "{what}: NORMAL has {} elements but POSITION has {n}",
                        v.len()
                    ));
                }
                Some(v.into_iter().map(Vec3::from).collect())
            }
            None => None,
        };
        let uvs = match uv_acc {
            Some(a) => {
                let v = self.read_floats::<2>(a.value(), &format!("{what} TEXCOORD_{uv_set}"))?;
                if v.len() != n {
                    return self.err(format!(
                        "{what}: TEXCOORD_{uv_set} has {} elements but POSITION has {n}",
                        v.len()
                    ));
                }
                Some(v.into_iter().map(Vec2::from).collect())
            }
            None => None,
        };
        let indices: Vec<u32> = match index_acc {
            Some(a) => {
                let ai = a.value();
                let idx = self.read_indices(ai, &format!("{what} indices"))?;
                if let Some(k) = idx.iter().position(|&i| i as usize >= n) {
                    return self.err(format!(
                        "{what}: index accessor {ai} element {k} = {} is past the {n} vertices",
                        idx[k]
                    ));
                }
                idx
            }
            None => {
                if n > u32::MAX as usize {
                    return self.err(format!("{what}: too many vertices"));
                }
                (0..n as u32).collect()
            }
        };
        if !indices.len().is_multiple_of(3) {
            return self.err(format!(
                "{what}: {} indices is not a multiple of 3 (mode TRIANGLES)",
                indices.len()
            ));
        }
        let triangles = indices
            .chunks_exact(3)
            .map(|t| [t[0], t[1], t[2]])
            .collect();
        let p = Rc::new(LocalPrimitive {
            positions,
            normals,
            uvs,
            triangles,
            material,
        });
        self.primitives.insert((mi, pi), p.clone());
        Ok(p)
    }

    /// Appends one world-space [`Mesh`] per primitive of mesh `mi` placed at node `ni`.
    fn instance_mesh(
        &mut self,
        ni: usize,
        mi: usize,
        world: &DMat4,
        out: &mut Vec<Mesh>,
    ) -> Res<()> {
        let Some(mesh) = self.root.meshes.get(mi) else {
            return self.err(format!(
                "node {ni} refers to mesh {mi}, but there are only {}",
                self.root.meshes.len()
            ));
        };
        let linear = DMat3::from_mat4(*world);
        let det = linear.determinant();
        let normal_matrix = linear.inverse().transpose();
        for pi in 0..mesh.primitives.len() {
            let name = prim_name(mi, &self.root.meshes[mi], pi);
            let local = self.local_primitive(mi, pi)?;
            let bytes = local.positions.len() as u64 * 32 + local.triangles.len() as u64 * 12;
            self.add_output(bytes, &format!("node {ni} {name}"))?;
            let positions: Vec<Vec3> = local
                .positions
                .iter()
                .map(|p| world.transform_point3(p.as_dvec3()).as_vec3())
                .collect();
            if let Some(v) = positions.iter().position(|p| !p.is_finite()) {
                return self.err(format!(
                    "node {ni} {name}: vertex {v} is not finite in world space"
                ));
            }
            let normals = local.normals.as_ref().and_then(|ns| {
                ns.iter()
                    .map(|n| {
                        let w = (normal_matrix * n.as_dvec3()).normalize_or_zero().as_vec3();
                        (w.is_finite() && w != Vec3::ZERO).then_some(w)
                    })
                    .collect::<Option<Vec<Vec3>>>()
            });
            // Spec "Meshes > Overview": a negative determinant makes the winding clockwise.
            let triangles = if det < 0.0 {
                local.triangles.iter().map(|&[a, b, c]| [a, c, b]).collect()
            } else {
                local.triangles.clone()
            };
            out.push(Mesh {
                name,
                positions,
                normals,
                uvs: local.uvs.clone(),
                indices: triangles,
                material: local.material,
            });
        }
        Ok(())
    }

    /// Converts the `KHR_lights_punctual` light `li` instanced at node `ni`.
    fn convert_light(&self, ni: usize, li: usize, world: &DMat4) -> Res<PunctualLight> {
        let all = self
            .root
            .extensions
            .as_ref()
            .and_then(|e| e.khr_lights_punctual.as_ref())
            .map_or(&[][..], |l| &l.lights[..]);
        let Some(light) = all.get(li) else {
            return self.err(format!(
                "node {ni} refers to light {li}, but there are only {}",
                all.len()
            ));
        };
        let power = photometric_to_radiometric(light.color, light.intensity);
        let position = world.transform_point3(DVec3::ZERO).as_vec3();
        // The light shines along the node's local -Z.
        let direction = world
            .transform_vector3(DVec3::NEG_Z)
            .normalize_or_zero()
            .as_vec3();
        let kind = match light.type_ {
            Checked::Valid(t) => t,
            Checked::Invalid => return self.err(format!("light {li} has an invalid type")),
        };
        if kind != khr_lights::Type::Point && direction == Vec3::ZERO {
            return self.err(format!(
                "node {ni}: light {li} has no direction (its transform collapses -Z)"
            ));
        }
        Ok(match kind {
            khr_lights::Type::Point => PunctualLight::Point {
                position,
                intensity: power,
            },
            khr_lights::Type::Directional => PunctualLight::Directional {
                direction,
                irradiance: power,
            },
            khr_lights::Type::Spot => {
                // KHR_lights_punctual defaults: innerConeAngle 0, outerConeAngle pi/4.
                let (inner, outer) = light
                    .spot
                    .as_ref()
                    .map_or((0.0, std::f32::consts::FRAC_PI_4), |s| {
                        (s.inner_cone_angle, s.outer_cone_angle)
                    });
                PunctualLight::Spot {
                    position,
                    direction,
                    intensity: power,
                    inner_angle: inner,
                    outer_angle: outer,
                }
            }
        })
    }

    /// Picks the camera (by name, else the first perspective camera) or synthesizes one.
    fn choose_camera(
        &self,
        wanted: Option<&str>,
        candidates: &[CameraCandidate],
        meshes: &[Mesh],
        lights: &[PunctualLight],
    ) -> Res<Camera> {
        let node_name = |c: &CameraCandidate| self.root.nodes[c.node].name.as_deref();
        let camera_name = |c: &CameraCandidate| self.root.cameras[c.camera].name.as_deref();
        let chosen = match wanted {
            Some(name) => {
                let found = candidates
                    .iter()
                    .find(|c| camera_name(c) == Some(name) || node_name(c) == Some(name));
                match found {
                    Some(c) => Some(c),
                    None => {
                        let orthographic = self.root.cameras.iter().any(|c| {
                            c.name.as_deref() == Some(name)
                                && c.type_ == Checked::Valid(json::camera::Type::Orthographic)
                        });
                        if orthographic {
                            return self.err(format!(
                                "camera {name:?} is orthographic; only perspective cameras \
                                 are supported"
                            ));
                        }
                        let available: Vec<String> = candidates
                            .iter()
                            .map(|c| {
                                format!(
                                    "camera {} {:?} at node {} {:?}",
                                    c.camera,
                                    camera_name(c).unwrap_or(""),
                                    c.node,
                                    node_name(c).unwrap_or("")
                                )
                            })
                            .collect();
                        let available = if available.is_empty() {
                            "the scene has no perspective cameras".to_string()
                        } else {
                            format!("available: {}", available.join(", "))
                        };
                        return self.err(format!("no camera named {name:?}; {available}"));
                    }
                }
            }
            None => candidates.first(),
        };
        let Some(c) = chosen else {
            return Ok(synthesize_camera(meshes, lights));
        };
        let json_camera = &self.root.cameras[c.camera];
        let what = format!("camera {} at node {}", c.camera, c.node);
        let Some(p) = &json_camera.perspective else {
            return self.err(format!(
                "{what} is of type perspective but has no perspective"
            ));
        };
        if !(p.yfov > 0.0 && p.yfov < std::f32::consts::PI) {
            return self.err(format!("{what}: yfov {} is outside (0, pi)", p.yfov));
        }
        if let Some(a) = p.aspect_ratio {
            if !(a > 0.0 && a.is_finite()) {
                return self.err(format!("{what}: aspectRatio {a} is not positive"));
            }
        }
        // Remove scale (and any reflection) from the node transform, keeping the viewing
        // direction (-Z) and the up vector (+Y).
        let back = c.world.z_axis.truncate().normalize_or_zero();
        let right = c.world.y_axis.truncate().cross(back).normalize_or_zero();
        let up = back.cross(right);
        if back == DVec3::ZERO || right == DVec3::ZERO {
            return self.err(format!("{what}: the node transform is degenerate"));
        }
        let world = DMat4::from_cols(
            right.extend(0.0),
            up.extend(0.0),
            back.extend(0.0),
            c.world.w_axis.truncate().extend(1.0),
        );
        Ok(Camera {
            name: json_camera
                .name
                .clone()
                .or_else(|| self.root.nodes[c.node].name.clone()),
            world_from_camera: world.as_mat4(),
            yfov: p.yfov,
            aspect_ratio: p.aspect_ratio,
            aperture_radius: 0.0,
            focus_distance: 1.0,
        })
    }
}

/// A camera looking down -Z from the +Z side at the bounding sphere of the geometry (or of
/// the lights' positions, or of the unit cube), framed by a 45° vertical field of view.
fn synthesize_camera(meshes: &[Mesh], lights: &[PunctualLight]) -> Camera {
    let mut lo = Vec3::splat(f32::INFINITY);
    let mut hi = Vec3::splat(f32::NEG_INFINITY);
    for m in meshes {
        for t in &m.indices {
            for &v in t {
                let p = m.positions[v as usize];
                lo = lo.min(p);
                hi = hi.max(p);
            }
        }
    }
    if lo.x > hi.x {
        for l in lights {
            if let PunctualLight::Point { position, .. } | PunctualLight::Spot { position, .. } = l
            {
                lo = lo.min(*position);
                hi = hi.max(*position);
            }
        }
    }
    if lo.x > hi.x {
        lo = Vec3::splat(-0.5);
        hi = Vec3::splat(0.5);
    }
    let yfov = 45f32.to_radians();
    let center = (lo + hi) * 0.5;
    let radius = ((hi - lo).length() * 0.5).max(1e-3);
    let distance = radius / (yfov * 0.5).sin();
    let eye = center + Vec3::new(0.0, 0.0, distance);
    Camera {
        name: None,
        world_from_camera: glam::Mat4::from_translation(eye),
        yfov,
        aspect_ratio: None,
        aperture_radius: 0.0,
        focus_distance: distance,
    }
}

/// `mesh M 'Name' primitive P` (or `mesh M primitive P` when the mesh is unnamed).
fn prim_name(mi: usize, mesh: &json::Mesh, pi: usize) -> String {
    match &mesh.name {
        Some(n) => format!("mesh {mi} '{n}' primitive {pi}"),
        None => format!("mesh {mi} primitive {pi}"),
    }
}

fn semantic_name(s: &Checked<json::mesh::Semantic>) -> String {
    match s {
        Checked::Valid(s) => s.to_string(),
        Checked::Invalid => "(invalid)".into(),
    }
}

/// Splits a GLB into its JSON chunk and optional BIN chunk (spec "GLB File Format
/// Specification"), checking every length against the data actually present.
fn split_glb(bytes: &[u8]) -> Result<(&[u8], Option<&[u8]>), String> {
    let u32_at = |at: usize| {
        bytes
            .get(at..at + 4)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    };
    let (Some(version), Some(length)) = (u32_at(4), u32_at(8)) else {
        return Err(format!(
            "truncated .glb: {} bytes, the header alone is 12",
            bytes.len()
        ));
    };
    if version != 2 {
        return Err(format!("unsupported .glb container version {version}"));
    }
    let length = length as usize;
    if length > bytes.len() {
        return Err(format!(
            "truncated .glb: the header declares {length} bytes but there are only {}",
            bytes.len()
        ));
    }
    if length < 12 {
        return Err(format!(
            "invalid .glb: declared length {length} is shorter than the header"
        ));
    }
    let data = &bytes[..length];
    let mut at = 12;
    let mut json = None;
    let mut bin = None;
    let mut chunk = 0;
    while at + 8 <= data.len() {
        let len = u32::from_le_bytes([data[at], data[at + 1], data[at + 2], data[at + 3]]) as usize;
        let kind = &data[at + 4..at + 8];
        let start = at + 8;
        let end = start
            .checked_add(len)
            .filter(|&e| e <= data.len())
            .ok_or_else(|| {
                format!(
                    "truncated .glb: chunk {chunk} declares {len} bytes but only {} remain",
                    data.len() - start
                )
            })?;
        match (chunk, kind) {
            (0, b"JSON") => json = Some(&data[start..end]),
            (0, _) => return Err("invalid .glb: the first chunk is not JSON".into()),
            (1, b"BIN\0") => bin = Some(&data[start..end]),
            _ => {} // Unknown chunks must be ignored.
        }
        chunk += 1;
        at = end;
    }
    match json {
        Some(j) => Ok((j, bin)),
        None => Err("invalid .glb: no JSON chunk".into()),
    }
}

/// Parses glTF JSON, tolerating a UTF-8 byte-order mark and trailing NUL padding.
fn parse_json(bytes: &[u8]) -> Result<json::Root, String> {
    let bytes = bytes.strip_prefix(b"\xef\xbb\xbf").unwrap_or(bytes);
    let end = bytes
        .iter()
        .rposition(|&b| b != 0 && !b.is_ascii_whitespace())
        .map_or(0, |p| p + 1);
    json::deserialize::from_slice(&bytes[..end]).map_err(|e| format!("invalid glTF JSON: {e}"))
}

/// True when a URI starts with a scheme (`scheme:`, RFC 3986 section 3.1).
fn has_scheme(uri: &str) -> bool {
    match uri.split_once(':') {
        Some((scheme, _)) => {
            let mut chars = scheme.chars();
            chars.next().is_some_and(|c| c.is_ascii_alphabetic())
                && chars.all(|c| c.is_ascii_alphanumeric() || "+-.".contains(c))
        }
        None => false,
    }
}

/// Decodes `%XX` escapes (RFC 3986 section 2.1); the result must be UTF-8.
fn percent_decode(s: &str) -> Result<String, String> {
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'%' {
            let hex = |c: u8| (c as char).to_digit(16);
            match (
                b.get(i + 1).and_then(|&c| hex(c)),
                b.get(i + 2).and_then(|&c| hex(c)),
            ) {
                (Some(h), Some(l)) => out.push((h * 16 + l) as u8),
                _ => return Err(format!("bad percent-encoding at byte {i}")),
            }
            i += 3;
        } else {
            out.push(b[i]);
            i += 1;
        }
    }
    String::from_utf8(out).map_err(|_| "percent-decoded URI is not UTF-8".to_string())
}

/// Decodes standard (or URL-safe) base64, with optional padding and ignoring whitespace.
fn decode_base64(s: &str) -> Result<Vec<u8>, String> {
    let mut out = Vec::with_capacity(s.len() / 4 * 3 + 3);
    let (mut acc, mut bits, mut padding) = (0u32, 0u32, false);
    for (i, c) in s.bytes().enumerate() {
        let v = match c {
            b'A'..=b'Z' => c - b'A',
            b'a'..=b'z' => c - b'a' + 26,
            b'0'..=b'9' => c - b'0' + 52,
            b'+' | b'-' => 62,
            b'/' | b'_' => 63,
            b'=' => {
                padding = true;
                continue;
            }
            b' ' | b'\t' | b'\r' | b'\n' => continue,
            _ => return Err(format!("invalid character {:?} at offset {i}", c as char)),
        };
        if padding {
            return Err(format!("data after '=' padding at offset {i}"));
        }
        acc = (acc << 6) | u32::from(v);
        bits += 6;
        if bits >= 8 {
            bits -= 8;
            out.push((acc >> bits) as u8);
            acc &= (1 << bits) - 1;
        }
    }
    if bits >= 6 {
        return Err("truncated base64 (length is 1 mod 4)".into());
    }
    Ok(out)
}

/// Shortens long URIs (data URIs) for error messages.
fn truncate_for_message(s: &str) -> String {
    match s.char_indices().nth(60) {
        Some((i, _)) => format!("{}...", &s[..i]),
        None => s.to_string(),
    }
}

/// The exact sRGB EOTF (IEC 61966-2-1): encoded value in [0, 1] to linear.
fn srgb_to_linear(c: f64) -> f64 {
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

/// Reads an unsigned integer component (little endian, as all glTF binary data).
fn read_uint(ct: ComponentType, b: &[u8]) -> u32 {
    match ct {
        ComponentType::U8 | ComponentType::I8 => u32::from(b[0]),
        ComponentType::U16 | ComponentType::I16 => u32::from(u16::from_le_bytes([b[0], b[1]])),
        ComponentType::U32 | ComponentType::F32 => u32::from_le_bytes([b[0], b[1], b[2], b[3]]),
    }
}

/// Reads one component as f32; normalized integers map to [0, 1] or [-1, 1] as the spec's
/// "Accessors" section prescribes (e.g. `max(c / 127, -1)` for signed bytes).
fn read_float(ct: ComponentType, normalized: bool, b: &[u8]) -> f32 {
    match ct {
        ComponentType::F32 => f32::from_le_bytes([b[0], b[1], b[2], b[3]]),
        ComponentType::I8 => {
            let v = f32::from(b[0] as i8);
            if normalized {
                (v / 127.0).max(-1.0)
            } else {
                v
            }
        }
        ComponentType::U8 => {
            let v = f32::from(b[0]);
            if normalized {
                v / 255.0
            } else {
                v
            }
        }
        ComponentType::I16 => {
            let v = f32::from(i16::from_le_bytes([b[0], b[1]]));
            if normalized {
                (v / 32767.0).max(-1.0)
            } else {
                v
            }
        }
        ComponentType::U16 => {
            let v = f32::from(u16::from_le_bytes([b[0], b[1]]));
            if normalized {
                v / 65535.0
            } else {
                v
            }
        }
        ComponentType::U32 => {
            let v = u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64;
            (if normalized { v / u32::MAX as f64 } else { v }) as f32
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base64_round_trips_known_vectors() {
        assert_eq!(decode_base64("").unwrap(), b"");
        assert_eq!(decode_base64("Zg==").unwrap(), b"f");
        assert_eq!(decode_base64("Zm8=").unwrap(), b"fo");
        assert_eq!(decode_base64("Zm9v").unwrap(), b"foo");
        assert_eq!(decode_base64("Zm9vYg").unwrap(), b"foob");
        assert!(decode_base64("Z").is_err());
        assert!(decode_base64("Zm9v!").is_err());
        assert!(decode_base64("Zg==Zg").is_err());
    }

    #[test]
    fn percent_decoding_rejects_bad_escapes() {
        assert_eq!(percent_decode("a%20b.bin").unwrap(), "a b.bin");
        assert!(percent_decode("a%2").is_err());
        assert!(percent_decode("a%zzb").is_err());
        assert!(percent_decode("%ff").is_err());
    }

    #[test]
    fn srgb_eotf_matches_reference_points() {
        assert_eq!(srgb_to_linear(0.0), 0.0);
        assert!((srgb_to_linear(1.0) - 1.0).abs() < 1e-12);
        assert!((srgb_to_linear(0.5) - 0.214_041_140_482_232_5).abs() < 1e-9);
        assert!((srgb_to_linear(0.04) - 0.04 / 12.92).abs() < 1e-15);
    }

    #[test]
    fn inputs_over_the_limit_are_too_large() {
        let json = br#"{"asset":{"version":"2.0"}}"#;
        let r = load_bytes(json, "small", None, None, 10);
        assert!(
            matches!(r, Err(SceneError::TooLarge { bytes, limit: 10, .. }) if bytes == json.len() as u64)
        );
        // A buffer whose declared length exceeds the limit is refused before decoding.
        let doc = br#"{"asset":{"version":"2.0"},"buffers":[{"byteLength":5000,"uri":"data:application/octet-stream;base64,AAAA"}]}"#;
        let r = load_bytes(doc, "buffers", None, None, 1000);
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

    #[test]
    fn panics_become_errors() {
        let r: Result<(), String> = quietly(|| panic!("boom"));
        assert_eq!(r.unwrap_err(), "boom");
    }
}
