//! Scene description for Tessera: what is in a scene, where it came from, and whether it
//! is valid.
//!
//! A [`Scene`] is a world-space description: triangle meshes with the node hierarchy's
//! transforms already applied, analytic spheres, materials, textures, punctual lights, an
//! optional uniform environment and one camera. A mesh placed at several places (several
//! glTF nodes, or EXT_mesh_gpu_instancing) is stored once instead, in object space, as a
//! [`Scene::prototypes`] entry with one [`Instance`] per place (object instancing, Pharr,
//! Jakob & Humphreys, pbrt-v4, 4th ed., section 7.1 "Object instancing"), so a forest of
//! identical trees costs the memory of one tree. [`Scene::placed_meshes`] walks both
//! kinds with their transforms, so a reader that needs world-space triangles does not
//! repeat the transform logic. It is produced by
//!
//! - [`gltf_import::load_path`] / [`gltf_import::load_slice`] from glTF 2.0 (`.gltf` with
//!   external or embedded buffers, or `.glb`), evaluated at a [`SceneTime`] with the
//!   `_at` variants (animations, skins and morph targets; t = 0 otherwise), and
//! - [`builtin::load`] for the built-in scenes addressed as `builtin:NAME`.
//!
//! Use [`load`] to resolve a scene argument as the command line gives it.
//!
//! Units: lengths are in scene units (metres for glTF), emitted radiance in W/(m² sr) per
//! linear-RGB channel, punctual intensities in W/sr, directional irradiance in W/m².
//! Every loader validates its output with [`Scene::validate`], so a renderer may assume
//! finite geometry, in-range indices and physically meaningful parameters.
//!
//! ```
//! let scene = tessera_scene::load("builtin:cornell-box").unwrap();
//! assert!(scene.triangle_count() > 0);
//! ```
#![deny(missing_docs)]

pub mod analysis;
pub mod builtin;
pub mod environment;
pub mod gltf_import;
pub mod job;
pub mod material;

pub use environment::EnvironmentMap;
pub use gltf_import::SceneTime;
pub use material::{
    AlphaMode, Anisotropy, GltfMaterial, Image, Material, MaterialKind, NormalMap, Texels, Texture,
    TextureRef, UvTransform, Volume, Wrap,
};

use glam::{Affine3A, Mat4, Vec2, Vec3, Vec4};
use std::path::Path;

/// Largest coordinate accepted, in scene units (|x|, |y|, |z| of every vertex in world
/// space, of sphere bounds and of the camera). The renderer works in f32: its error bounds
/// and distance computations square coordinates, which overflow near 1.8e19, and its BVH
/// builder fails on bounds it cannot subdivide. 1e12 m is seven times the Earth–Sun
/// distance, far beyond any scene, and leaves every product finite.
pub const MAX_COORDINATE: f32 = 1e12;

/// Largest scene file accepted, in bytes (glTF JSON, .glb, or the sum of its buffers).
pub const MAX_INPUT_BYTES: u64 = 1 << 30;

/// Largest image accepted, in decoded texels (width x height): 8192 x 8192 = 64 Mi, or
/// any other shape of that area. Checked from the image's header before anything is
/// decoded, so a small compressed file that would decode to gigabytes (a decompression
/// bomb: a 0.26 MB PNG of 16384 x 16384 zeros) is refused at once. An 8-bit image at the
/// limit takes 256 MiB as stored (RGBA8), a 16-bit one 1 GiB (RGBA f32).
pub const MAX_IMAGE_TEXELS: u64 = 8192 * 8192;

/// Most nodes a glTF document may have: 1 Mi (1,048,576), three times the 300,000
/// instancing nodes of the robustness issue's scene (which imports, analyses and builds
/// in about 2 s). The same bound applies to every other top-level array of the document
/// (meshes, accessors, materials, ...), counted before the document is parsed: a parsed
/// node takes a few hundred bytes, so a file of empty nodes would otherwise need a hundred
/// times its size.
pub const MAX_NODES: u64 = 1 << 20;

/// Most triangles a scene may store: 32 Mi (33,554,432), counting each world-space mesh
/// and each instanced prototype once (instances of a prototype add none; they are bounded
/// by [`MAX_NODES`] and the import's memory budget). The renderer needs about 150 bytes
/// a stored triangle with its BVH, so the limit is about 5 GB.
pub const MAX_TRIANGLES: u64 = 1 << 25;

/// Largest total of decoded texels over every image of a scene: 256 Mi, four images at
/// [`MAX_IMAGE_TEXELS`] (1 GiB as 8-bit RGBA). Checked from each header before decoding.
pub const MAX_SCENE_TEXELS: u64 = 4 * MAX_IMAGE_TEXELS;

/// An error while loading or validating a scene. The message names the file and the
/// element (node, mesh, material, accessor index) that is wrong.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    /// The scene argument names nothing we know (`builtin:NAME` with an unknown name, or
    /// an unsupported extension).
    #[error("unknown scene {0:?}: expected a .gltf/.glb path or builtin:NAME (one of {1})")]
    Unknown(String, String),
    /// Reading a file failed.
    #[error("cannot read {path}: {source}")]
    Io {
        /// The file that could not be read.
        path: String,
        /// The underlying error.
        source: std::io::Error,
    },
    /// The input is larger than [`MAX_INPUT_BYTES`].
    #[error("{path}: {bytes} bytes is larger than the limit of {limit} bytes")]
    TooLarge {
        /// The offending file.
        path: String,
        /// Its size.
        bytes: u64,
        /// The limit.
        limit: u64,
    },
    /// The glTF document is malformed or uses something we cannot render.
    #[error("{file}: {message}")]
    Gltf {
        /// The file (or `<memory>`).
        file: String,
        /// What is wrong, naming the element.
        message: String,
    },
    /// The scene failed validation.
    #[error("invalid scene {scene}: {message}")]
    Invalid {
        /// Scene name.
        scene: String,
        /// What is wrong.
        message: String,
    },
}

/// A pinhole or thin-lens perspective camera.
#[derive(Clone, Debug, PartialEq)]
pub struct Camera {
    /// Camera name (glTF camera or node name), if any.
    pub name: Option<String>,
    /// World-from-camera rigid transform. The camera looks down its local -Z axis with +Y
    /// up, as glTF defines it.
    pub world_from_camera: Mat4,
    /// Vertical field of view in radians.
    pub yfov: f32,
    /// Aspect ratio width/height from the scene, if it specifies one; the image size
    /// decides otherwise.
    pub aspect_ratio: Option<f32>,
    /// Radius of the thin-lens aperture in scene units; 0 is a pinhole.
    pub aperture_radius: f32,
    /// Distance to the plane in focus (only used when `aperture_radius > 0`).
    pub focus_distance: f32,
}

/// A triangle mesh, in world space in [`Scene::meshes`] and in object space in
/// [`Scene::prototypes`] (then every "world-space" below reads "object-space").
#[derive(Clone, Debug, Default)]
pub struct Mesh {
    /// Name of the glTF mesh/node, for error messages and statistics.
    pub name: String,
    /// World-space vertex positions.
    pub positions: Vec<Vec3>,
    /// World-space unit shading normals, one per vertex, if the source had them.
    pub normals: Option<Vec<Vec3>>,
    /// Texture-coordinate sets by index (`uvs[n]` is `TEXCOORD_n`), each one per vertex
    /// or empty when the source lacks that set (it then reads as (0, 0)).
    pub uvs: Vec<Vec<Vec2>>,
    /// Vertex colours (glTF `COLOR_0`) as linear RGBA, one per vertex, if the source had
    /// them: they multiply a glTF material's base colour and alpha. `None` costs nothing
    /// per vertex.
    pub colors: Option<Vec<Vec4>>,
    /// World-space unit tangents with the bitangent sign in `w`, per triangle corner
    /// (`tangents[t][k]` belongs to vertex `indices[t][k]`): glTF `TANGENT`, or generated
    /// with MikkTSpace, whose tangents are defined per corner. Present when a normal map
    /// needs them.
    pub tangents: Option<Vec<[Vec4; 3]>>,
    /// Triangles as vertex indices, counter-clockwise seen from the front.
    pub indices: Vec<[u32; 3]>,
    /// Index into [`Scene::materials`].
    pub material: u32,
}

/// One placement of a prototype mesh ([`Scene::prototypes`]) in the world.
///
/// The prototype keeps its object-space winding; a transform with a negative determinant
/// (a mirror) makes it clockwise in world space, and readers account for that: normals
/// transform by the inverse transpose (which yields the front side the flattened,
/// re-wound mesh would have), tangents by the linear part with their bitangent sign
/// multiplied by the sign of the determinant.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Instance {
    /// Index into [`Scene::prototypes`].
    pub prototype: u32,
    /// World-from-object affine transform (invertible, finite).
    pub world_from_object: Affine3A,
}

impl Instance {
    /// Bytes an instance costs in a scene (for import budgets and memory figures).
    pub const BYTES: u64 = std::mem::size_of::<Instance>() as u64;

    /// Whether `m` can place a prototype: finite, with a finite single-precision inverse
    /// (the renderer carries rays into object space by it). What [`Scene::validate`]
    /// checks and the importer decides flattening by.
    pub fn transform_is_invertible(m: &Affine3A) -> bool {
        m.is_finite() && m.matrix3.determinant() != 0.0 && m.inverse().is_finite()
    }

    /// Whether the transform mirrors (negative determinant).
    pub fn mirrors(&self) -> bool {
        self.world_from_object.matrix3.determinant() < 0.0
    }
}

/// The object-space bounds (min, max) of the vertices `mesh`'s triangles use, `None` for
/// a mesh without triangles.
pub(crate) fn mesh_bounds(mesh: &Mesh) -> Option<(Vec3, Vec3)> {
    let mut lo = Vec3::splat(f32::INFINITY);
    let mut hi = Vec3::splat(f32::NEG_INFINITY);
    for &v in mesh.indices.iter().flatten() {
        let p = *mesh.positions.get(v as usize)?;
        lo = lo.min(p);
        hi = hi.max(p);
    }
    (lo.x <= hi.x).then_some((lo, hi))
}

/// A vertex of `mesh` that `world_from_object` places at a non-finite point or beyond
/// [`MAX_COORDINATE`], with where it lands; `bounds` are the mesh's [`mesh_bounds`]. The
/// eight corners of the bounds are checked first, so a placement well inside the range
/// (every placement of a sane scene) costs eight transforms however large the mesh; only
/// when a corner is out are the vertices themselves checked, so the answer is exact.
pub(crate) fn far_vertex(
    mesh: &Mesh,
    bounds: Option<(Vec3, Vec3)>,
    world_from_object: &Affine3A,
) -> Option<(usize, Vec3)> {
    let out = |p: Vec3| !p.is_finite() || p.abs().max_element() > MAX_COORDINATE;
    let (lo, hi) = bounds?;
    let corner_out = (0..8).any(|k| {
        let c = Vec3::select(glam::BVec3::new(k & 1 != 0, k & 2 != 0, k & 4 != 0), hi, lo);
        out(world_from_object.transform_point3(c))
    });
    if !corner_out {
        return None;
    }
    mesh.positions
        .iter()
        .map(|&p| world_from_object.transform_point3(p))
        .enumerate()
        .find(|&(_, w)| out(w))
}

/// A mesh as placed in the world: a world-space mesh of [`Scene::meshes`] (no transform),
/// or a prototype with an instance's transform. See [`Scene::placed_meshes`].
#[derive(Clone, Copy, Debug)]
pub struct PlacedMesh<'a> {
    /// The mesh's data (world space, or object space with `world_from_object`).
    pub mesh: &'a Mesh,
    /// The instance transform, `None` for a world-space mesh.
    pub world_from_object: Option<Affine3A>,
}

impl PlacedMesh<'_> {
    /// World-space positions of triangle `t`, in the mesh's vertex order (clockwise seen
    /// from the front when the instance mirrors; areas and bounds do not care).
    #[inline]
    pub fn triangle(&self, t: usize) -> [Vec3; 3] {
        let p = self.mesh.indices[t].map(|i| self.mesh.positions[i as usize]);
        match &self.world_from_object {
            None => p,
            Some(m) => p.map(|v| m.transform_point3(v)),
        }
    }

    /// World-space positions of every triangle (see [`PlacedMesh::triangle`]).
    pub fn triangles(&self) -> impl Iterator<Item = [Vec3; 3]> + '_ {
        (0..self.mesh.indices.len()).map(|t| self.triangle(t))
    }

    /// The mesh's material.
    pub fn material(&self) -> u32 {
        self.mesh.material
    }
}

/// The meshes of `meshes`, then each instance of `instances` with its prototype from
/// `prototypes` (the one implementation behind [`Scene::placed_meshes`], also used by the
/// importer before its [`Scene`] exists).
pub(crate) fn placed<'a>(
    meshes: &'a [Mesh],
    prototypes: &'a [Mesh],
    instances: &'a [Instance],
) -> impl Iterator<Item = PlacedMesh<'a>> + 'a {
    let flat = meshes.iter().map(|mesh| PlacedMesh {
        mesh,
        world_from_object: None,
    });
    let inst = instances.iter().map(move |i| PlacedMesh {
        mesh: &prototypes[i.prototype as usize],
        world_from_object: Some(i.world_from_object),
    });
    flat.chain(inst)
}

/// An analytic sphere (built-in scenes use these for spherical lights and glass balls).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sphere {
    /// Centre in world space.
    pub center: Vec3,
    /// Radius (> 0).
    pub radius: f32,
    /// Index into [`Scene::materials`].
    pub material: u32,
}

/// A punctual or distant light (KHR_lights_punctual), in radiometric units.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum PunctualLight {
    /// Isotropic point light.
    Point {
        /// Position in world space.
        position: Vec3,
        /// Radiant intensity in W/sr per channel.
        intensity: Vec3,
    },
    /// Spot light with a smooth falloff between the inner and outer cone angles.
    Spot {
        /// Position in world space.
        position: Vec3,
        /// Unit direction the spot points to.
        direction: Vec3,
        /// Radiant intensity on the axis in W/sr per channel.
        intensity: Vec3,
        /// Inner cone half-angle in radians (full intensity inside).
        inner_angle: f32,
        /// Outer cone half-angle in radians (zero outside).
        outer_angle: f32,
    },
    /// Directional (distant) light.
    Directional {
        /// Unit direction the light travels in.
        direction: Vec3,
        /// Irradiance on a surface facing the light, W/m² per channel.
        irradiance: Vec3,
    },
}

/// A scene ready to be built into a renderable form.
#[derive(Clone, Debug)]
pub struct Scene {
    /// Scene name (file name or `builtin:NAME`).
    pub name: String,
    /// The camera to render from.
    pub camera: Camera,
    /// World-space triangle meshes, each placed once.
    pub meshes: Vec<Mesh>,
    /// Object-space meshes placed by [`Scene::instances`] (stored once however often they
    /// are placed). Not emissive: area lights need world-space triangles, so the importer
    /// flattens emissive meshes into [`Scene::meshes`] instead.
    pub prototypes: Vec<Mesh>,
    /// Placements of [`Scene::prototypes`].
    pub instances: Vec<Instance>,
    /// Analytic spheres.
    pub spheres: Vec<Sphere>,
    /// Materials referenced by meshes and spheres.
    pub materials: Vec<Material>,
    /// Textures (an image with its sampler) referenced by materials.
    pub textures: Vec<Texture>,
    /// Images referenced by textures.
    pub images: Vec<Image>,
    /// What the loader ignored that a user may want to know (e.g. unsupported optional
    /// glTF extensions); the render plan repeats them.
    pub warnings: Vec<String>,
    /// Punctual and directional lights.
    pub lights: Vec<PunctualLight>,
    /// Environment radiance seen by rays that leave the scene, W/(m² sr): uniform, or,
    /// with [`Scene::environment_map`], the factor (strength and tint) that multiplies
    /// the image. `None`: no environment (the image is ignored).
    pub environment: Option<Vec3>,
    /// An equirectangular image the environment radiance comes from (see
    /// [`environment`]); `None` for a uniform environment.
    pub environment_map: Option<EnvironmentMap>,
    /// Default image size for this scene (width, height).
    pub default_resolution: (u32, u32),
    /// Whether the scene changes with time: it was loaded from a glTF file whose playing
    /// animations have channels, so another time may give another scene (see
    /// [`gltf_import`], "Time"). Built-in scenes are static.
    pub animated: bool,
}

impl Scene {
    /// Number of triangles as rendered: over all meshes, with each instance's prototype
    /// counted once per instance.
    pub fn triangle_count(&self) -> usize {
        self.placed_meshes().map(|m| m.mesh.indices.len()).sum()
    }

    /// Number of triangles as stored: over all meshes and prototypes, each once.
    pub fn stored_triangle_count(&self) -> usize {
        self.meshes
            .iter()
            .chain(&self.prototypes)
            .map(|m| m.indices.len())
            .sum()
    }

    /// This scene with every instance copied to world space, as the glTF importer
    /// flattens a mesh placed once: positions transformed, normals by the inverse
    /// transpose and renormalised, tangents by the linear part, and for a mirroring
    /// transform the winding (and tangent corners) reversed and the bitangent sign
    /// flipped. For comparing instancing with flattening (tests, benchmarks); the flattened
    /// meshes follow [`Scene::meshes`] in instance order.
    pub fn flattened(&self) -> Scene {
        let mut flat = self.clone();
        flat.prototypes.clear();
        flat.instances.clear();
        flat.meshes.reserve(self.instances.len());
        for inst in &self.instances {
            let proto = &self.prototypes[inst.prototype as usize];
            let m = inst.world_from_object;
            let linear = glam::Mat3::from(m.matrix3);
            let normal = linear.inverse().transpose();
            let mirror = inst.mirrors();
            let sign = if mirror { -1.0 } else { 1.0 };
            let normals = proto.normals.as_ref().and_then(|n| {
                n.iter()
                    .map(|&v| (normal * v).try_normalize())
                    .collect::<Option<Vec<Vec3>>>()
            });
            let tangents = proto.tangents.as_ref().map(|ts| {
                ts.iter()
                    .map(|c| {
                        let c = if mirror { [c[0], c[2], c[1]] } else { *c };
                        c.map(|t| {
                            let w = (linear * t.truncate()).normalize_or_zero();
                            w.extend(if t.w < 0.0 { -sign } else { sign })
                        })
                    })
                    .collect()
            });
            flat.meshes.push(Mesh {
                name: proto.name.clone(),
                positions: proto
                    .positions
                    .iter()
                    .map(|&p| m.transform_point3(p))
                    .collect(),
                normals,
                uvs: proto.uvs.clone(),
                colors: proto.colors.clone(),
                tangents,
                indices: proto
                    .indices
                    .iter()
                    .map(|&[a, b, c]| if mirror { [a, c, b] } else { [a, b, c] })
                    .collect(),
                material: proto.material,
            });
        }
        flat
    }

    /// Every mesh as placed in the world: [`Scene::meshes`], then every instance with
    /// its prototype and transform.
    pub fn placed_meshes(&self) -> impl Iterator<Item = PlacedMesh<'_>> + '_ {
        placed(&self.meshes, &self.prototypes, &self.instances)
    }

    /// Checks every invariant the renderer relies on: finite numbers, in-range indices,
    /// positive radii, parameters within their physical ranges. The first problem found is
    /// the error, checked part by part: camera, meshes, instances, spheres, materials,
    /// textures and images, lights and the environment.
    pub fn validate(&self) -> Result<(), SceneError> {
        self.check_camera()
            .and_then(|()| self.check_meshes())
            .and_then(|()| self.check_instances())
            .and_then(|()| self.check_spheres())
            .and_then(|()| self.check_materials())
            .and_then(|()| self.check_images())
            .and_then(|()| self.check_lights())
            .map_err(|message| SceneError::Invalid {
                scene: self.name.clone(),
                message,
            })
    }

    /// A finite camera inside the coordinate bound, with a field of view and lens in range.
    fn check_camera(&self) -> Result<(), String> {
        let cam = &self.camera;
        if !cam.world_from_camera.is_finite() {
            return Err("camera transform is not finite".into());
        }
        let eye = cam.world_from_camera.w_axis.truncate();
        if eye.abs().max_element() > MAX_COORDINATE {
            return Err(format!(
                "camera position {eye} is beyond ±{MAX_COORDINATE:e} scene units"
            ));
        }
        if !(cam.yfov > 0.0 && cam.yfov < std::f32::consts::PI) {
            return Err(format!("camera yfov {} is outside (0, pi)", cam.yfov));
        }
        if !(cam.aperture_radius >= 0.0 && cam.aperture_radius.is_finite()) {
            return Err(format!(
                "camera aperture {} is invalid",
                cam.aperture_radius
            ));
        }
        if cam.aperture_radius > 0.0
            && !(cam.focus_distance > 0.0 && cam.focus_distance.is_finite())
        {
            return Err(format!(
                "camera focus distance {} is invalid",
                cam.focus_distance
            ));
        }
        Ok(())
    }

    /// Meshes and prototypes: existing materials, finite vertices inside the coordinate
    /// bound, indices within the vertices, consistent normals, texture coordinates and
    /// tangents.
    fn check_meshes(&self) -> Result<(), String> {
        let nmat = self.materials.len() as u32;
        let meshes = self.meshes.iter().enumerate().map(|(i, m)| ("mesh", i, m));
        let prototypes = self.prototypes.iter().enumerate();
        for (kind, i, m) in meshes.chain(prototypes.map(|(i, m)| ("prototype", i, m))) {
            if m.material >= nmat {
                return Err(format!(
                    "{kind} {i} ({}) uses material {} of {nmat}",
                    m.name, m.material
                ));
            }
            if let Some(p) = m.positions.iter().position(|p| !p.is_finite()) {
                return Err(format!("{kind} {i} ({}) vertex {p} is not finite", m.name));
            }
            if let Some(p) = m
                .positions
                .iter()
                .position(|p| p.abs().max_element() > MAX_COORDINATE)
            {
                return Err(format!(
                    "{kind} {i} ({}) vertex {p} at {} is beyond ±{MAX_COORDINATE:e} scene units",
                    m.name, m.positions[p]
                ));
            }
            let nv = m.positions.len() as u32;
            if let Some(t) = m.indices.iter().position(|t| t.iter().any(|&v| v >= nv)) {
                return Err(format!(
                    "{kind} {i} ({}) triangle {t} indexes past its {nv} vertices",
                    m.name
                ));
            }
            if let Some(n) = &m.normals {
                if n.len() != m.positions.len() || n.iter().any(|v| !v.is_finite()) {
                    return Err(format!("{kind} {i} ({}) has invalid normals", m.name));
                }
            }
            for (set, uv) in m.uvs.iter().enumerate() {
                if (!uv.is_empty() && uv.len() != m.positions.len())
                    || uv.iter().any(|v| !v.is_finite())
                {
                    return Err(format!(
                        "{kind} {i} ({}) has invalid texture coordinates TEXCOORD_{set}",
                        m.name
                    ));
                }
            }
            if let Some(c) = &m.colors {
                if c.len() != m.positions.len() || c.iter().any(|v| !v.is_finite()) {
                    return Err(format!(
                        "{kind} {i} ({}) has invalid vertex colours",
                        m.name
                    ));
                }
            }
            if let Some(t) = &m.tangents {
                if t.len() != m.indices.len() || t.iter().flatten().any(|v| !v.is_finite()) {
                    return Err(format!("{kind} {i} ({}) has invalid tangents", m.name));
                }
            }
        }
        Ok(())
    }

    /// Instances: an existing prototype, an invertible transform that keeps every vertex
    /// inside the coordinate bound, and no emissive prototype (area lights are world-space
    /// meshes).
    fn check_instances(&self) -> Result<(), String> {
        let proto_bounds: Vec<Option<(Vec3, Vec3)>> =
            self.prototypes.iter().map(mesh_bounds).collect();
        for (i, inst) in self.instances.iter().enumerate() {
            let Some(proto) = self.prototypes.get(inst.prototype as usize) else {
                return Err(format!(
                    "instance {i} places prototype {} of {}",
                    inst.prototype,
                    self.prototypes.len()
                ));
            };
            if !Instance::transform_is_invertible(&inst.world_from_object) {
                return Err(format!(
                    "instance {i} of prototype {} has a transform that is not finite and \
                     invertible",
                    inst.prototype
                ));
            }
            let bounds = proto_bounds[inst.prototype as usize];
            if let Some((v, at)) = far_vertex(proto, bounds, &inst.world_from_object) {
                return Err(format!(
                    "instance {i} of prototype {} ({}) places vertex {v} at {at}, beyond \
                     ±{MAX_COORDINATE:e} scene units",
                    inst.prototype, proto.name,
                ));
            }
            if self
                .materials
                .get(proto.material as usize)
                .is_some_and(Material::is_emissive)
            {
                return Err(format!(
                    "instance {i}: prototype {} ({}) is emissive; area lights must be \
                     world-space meshes",
                    inst.prototype, proto.name
                ));
            }
        }
        Ok(())
    }

    /// Spheres: a finite centre and positive radius inside the bound, an existing material.
    fn check_spheres(&self) -> Result<(), String> {
        let nmat = self.materials.len() as u32;
        for (i, s) in self.spheres.iter().enumerate() {
            if !(s.center.is_finite()
                && s.radius > 0.0
                && s.radius.is_finite()
                && (s.center.abs() + s.radius).max_element() <= MAX_COORDINATE)
            {
                return Err(format!("sphere {i} has an invalid centre or radius"));
            }
            if s.material >= nmat {
                return Err(format!("sphere {i} uses material {} of {nmat}", s.material));
            }
        }
        Ok(())
    }

    /// Materials: emission and every parameter within its physical range, existing
    /// textures.
    fn check_materials(&self) -> Result<(), String> {
        let ntex = self.textures.len() as u32;
        for (i, m) in self.materials.iter().enumerate() {
            let unit = |v: Vec3| v.is_finite() && v.min_element() >= 0.0;
            if !unit(m.emission) {
                return Err(format!("material {i} ({}) has invalid emission", m.name));
            }
            let ok = match &m.kind {
                MaterialKind::Diffuse { albedo } => unit(*albedo) && albedo.max_element() <= 1.0,
                MaterialKind::Phong { kd, ks, exponent } => {
                    unit(*kd)
                        && unit(*ks)
                        && (*kd + *ks).max_element() <= 1.0 + 1e-6
                        && *exponent >= 0.0
                        && exponent.is_finite()
                }
                MaterialKind::Conductor { f0, roughness } => {
                    unit(*f0) && f0.max_element() <= 1.0 && (0.0..=1.0).contains(roughness)
                }
                MaterialKind::Gltf(g) => gltf_in_range(g, ntex),
                MaterialKind::Mirror { reflectance } => {
                    unit(*reflectance) && reflectance.max_element() <= 1.0
                }
                MaterialKind::Dielectric {
                    ior,
                    roughness,
                    tint,
                } => {
                    *ior > 0.0
                        && ior.is_finite()
                        && (0.0..=1.0).contains(roughness)
                        && unit(*tint)
                        && tint.max_element() <= 1.0
                }
            };
            if !ok {
                return Err(format!(
                    "material {i} ({}) has parameters out of range: {:?}",
                    m.name, m.kind
                ));
            }
        }
        Ok(())
    }

    /// Textures name existing images, and images have the size their texels say.
    fn check_images(&self) -> Result<(), String> {
        let nimg = self.images.len() as u32;
        for (i, t) in self.textures.iter().enumerate() {
            if t.image >= nimg {
                return Err(format!("texture {i} uses image {} of {nimg}", t.image));
            }
        }
        for (i, im) in self.images.iter().enumerate() {
            if im.width == 0
                || im.height == 0
                || im.texels.len() != (im.width as usize) * (im.height as usize)
            {
                return Err(format!("image {i} has inconsistent size"));
            }
        }
        Ok(())
    }

    /// Lights and the environment: finite, non-negative, directions normalised, spot
    /// cones within a hemisphere; and a non-zero default resolution.
    fn check_lights(&self) -> Result<(), String> {
        for (i, l) in self.lights.iter().enumerate() {
            let ok = match l {
                PunctualLight::Point {
                    position,
                    intensity,
                } => {
                    position.is_finite() && intensity.is_finite() && intensity.min_element() >= 0.0
                }
                PunctualLight::Spot {
                    position,
                    direction,
                    intensity,
                    inner_angle,
                    outer_angle,
                } => {
                    position.is_finite()
                        && direction.is_normalized()
                        && intensity.is_finite()
                        && intensity.min_element() >= 0.0
                        && *inner_angle >= 0.0
                        && inner_angle <= outer_angle
                        && *outer_angle <= std::f32::consts::FRAC_PI_2
                }
                PunctualLight::Directional {
                    direction,
                    irradiance,
                } => {
                    direction.is_normalized()
                        && irradiance.is_finite()
                        && irradiance.min_element() >= 0.0
                }
            };
            if !ok {
                return Err(format!("light {i} has invalid parameters: {l:?}"));
            }
        }
        if let Some(e) = self.environment {
            if !(e.is_finite() && e.min_element() >= 0.0) {
                return Err("environment radiance is invalid".into());
            }
        }
        if let Some(m) = &self.environment_map {
            let n = u64::from(m.width) * u64::from(m.height);
            if n == 0
                || m.texels.len() as u64 != n
                || !m.rotation.is_finite()
                || m.texels
                    .iter()
                    .any(|t| !t.is_finite() || t.min_element() < 0.0)
            {
                return Err(format!("environment image {} is invalid", m.name));
            }
        }
        let (w, h) = self.default_resolution;
        if w == 0 || h == 0 {
            return Err("default resolution is zero".into());
        }
        Ok(())
    }
}

/// Whether the parameters of a glTF material are in their physical ranges and its texture
/// references exist.
fn gltf_in_range(g: &GltfMaterial, ntex: u32) -> bool {
    let unit = |v: Vec3| v.is_finite() && v.min_element() >= 0.0 && v.max_element() <= 1.0;
    let frac = |v: f32| (0.0..=1.0).contains(&v);
    unit(g.base_color)
        && frac(g.alpha)
        && frac(g.metallic)
        && frac(g.roughness)
        && frac(g.transmission)
        && g.ior >= 1.0
        && g.ior.is_finite()
        && frac(g.specular)
        && g.specular_color.is_finite()
        && g.specular_color.min_element() >= 0.0
        && frac(g.clearcoat)
        && frac(g.clearcoat_roughness)
        && unit(g.sheen_color)
        && frac(g.sheen_roughness)
        && g.normal_map.is_none_or(|n| n.scale.is_finite())
        && g.volume
            .is_none_or(|v| v.sigma_a.is_finite() && v.sigma_a.min_element() >= 0.0)
        && match g.alpha_mode {
            AlphaMode::Mask { cutoff } => cutoff.is_finite(),
            _ => true,
        }
        && g.textures().all(|t| {
            t.texture < ntex
                && t.transform
                    .is_none_or(|m| m.0.iter().all(|v| v.is_finite()))
        })
}

/// Resolves a scene argument: `builtin:NAME` or a path to a `.gltf`/`.glb` file.
pub fn load(arg: &str) -> Result<Scene, SceneError> {
    load_with_camera(arg, None)
}

/// Like [`load`], choosing the glTF camera with the given name (glTF files only).
pub fn load_with_camera(arg: &str, camera: Option<&str>) -> Result<Scene, SceneError> {
    load_at(arg, camera, &SceneTime::default())
}

/// Like [`load_with_camera`], with a glTF scene evaluated at `time` (built-in scenes are
/// static).
pub fn load_at(arg: &str, camera: Option<&str>, time: &SceneTime) -> Result<Scene, SceneError> {
    if let Some(name) = arg.strip_prefix("builtin:") {
        return builtin::load(name);
    }
    let path = Path::new(arg);
    match path
        .extension()
        .and_then(|e| e.to_str())
        .map(|e| e.to_ascii_lowercase())
    {
        Some(ext) if ext == "gltf" || ext == "glb" => gltf_import::load_path_at(path, camera, time),
        _ => Err(SceneError::Unknown(
            arg.to_string(),
            builtin::NAMES.join(", "),
        )),
    }
}
