//! Step 5, meshes (spec "Meshes"): each `TRIANGLES` primitive read once in its mesh's
//! local space, then placed: a mesh placed once is transformed to world space; a mesh
//! placed at two or more places (several nodes, or EXT_mesh_gpu_instancing) is stored
//! once in object space as a prototype with one instance per place (pbrt-v4, Pharr, Jakob
//! & Humphreys, 4th ed., section 7.1 "Object instancing"). Two exceptions are flattened
//! per place even when shared: emissive primitives (area lights are sampled by world-space
//! triangle) and placements whose transform cannot be inverted (a zero scale), which the
//! renderer could not carry a ray into.

use super::graph::Placement;
use super::{Importer, Res};
use crate::{Instance, Material, Mesh, PlacedMesh};
use glam::{Affine3A, DMat3, DMat4, Vec2, Vec3, Vec4};
use gltf::json;
use json::validation::Checked;
use std::collections::HashMap;
use std::rc::Rc;

/// Mesh data of one primitive in its mesh's local space, shared by every node instancing it
/// (a deformed copy per node for skins and morph targets, see the `deform` step).
#[derive(Clone)]
pub(super) struct LocalPrimitive {
    pub(super) positions: Vec<Vec3>,
    pub(super) normals: Option<Vec<Vec3>>,
    uvs: Vec<Vec<Vec2>>,
    /// `COLOR_0` as linear RGBA per vertex, when the primitive has it.
    pub(super) colors: Option<Vec<Vec4>>,
    /// Per triangle corner, when the material has a normal map.
    pub(super) tangents: Option<Vec<[Vec4; 3]>>,
    pub(super) triangles: Vec<[u32; 3]>,
    material: u32,
}

/// The placed geometry of a scene: world-space meshes, prototypes and their instances.
#[derive(Default)]
pub(super) struct Geometry {
    /// Meshes placed once (and flattened shared ones), in world space.
    pub(super) meshes: Vec<Mesh>,
    /// Shared primitives, in object space.
    pub(super) prototypes: Vec<Mesh>,
    /// Placements of the prototypes.
    pub(super) instances: Vec<Instance>,
}

impl Geometry {
    /// Every placed mesh (see [`crate::Scene::placed_meshes`]).
    pub(super) fn placed(&self) -> impl Iterator<Item = PlacedMesh<'_>> + '_ {
        crate::placed(&self.meshes, &self.prototypes, &self.instances)
    }

    /// World-space bounds of each world-space mesh and each instance, empty meshes left
    /// out. An instance's are its prototype's object bounds transformed corner by corner
    /// (conservative, and cheap for 10,000 instances).
    pub(super) fn bounds(&self) -> impl Iterator<Item = (Vec3, Vec3)> + '_ {
        let proto: Vec<Option<(Vec3, Vec3)>> =
            self.prototypes.iter().map(crate::mesh_bounds).collect();
        let flat = self.meshes.iter().filter_map(crate::mesh_bounds);
        let inst = self.instances.iter().filter_map(move |i| {
            let (lo, hi) = proto[i.prototype as usize]?;
            let mut wlo = Vec3::splat(f32::INFINITY);
            let mut whi = Vec3::splat(f32::NEG_INFINITY);
            for k in 0..8 {
                let c = Vec3::select(glam::BVec3::new(k & 1 != 0, k & 2 != 0, k & 4 != 0), hi, lo);
                let w = i.world_from_object.transform_point3(c);
                wlo = wlo.min(w);
                whi = whi.max(w);
            }
            Some((wlo, whi))
        });
        flat.chain(inst)
    }

    /// Triangles as rendered (instances counted once each).
    pub(super) fn triangle_count(&self) -> usize {
        self.placed().map(|m| m.mesh.indices.len()).sum()
    }
}

impl Importer<'_> {
    /// Turns the walk's placements into geometry: meshes placed once are flattened to world
    /// space, meshes placed more often become prototypes with instances (see the module
    /// docs for the exceptions). `materials` are the converted materials (the default
    /// material, past their end, is not emissive). The output budget counts a prototype
    /// once and an instance as [`Instance::BYTES`], so a forest of 10,000 instances of one
    /// tree costs about one tree.
    pub(super) fn place_meshes(
        &mut self,
        placements: &[Placement],
        materials: &[Material],
    ) -> Res<Geometry> {
        let mut uses: HashMap<usize, usize> = HashMap::new();
        for pl in placements {
            *uses.entry(pl.mesh).or_default() += 1;
        }
        let mut geometry = Geometry::default();
        // (mesh, primitive) -> index into `geometry.prototypes`.
        let mut prototype_of: HashMap<(usize, usize), u32> = HashMap::new();
        // Per prototype: its object-space bounds, for the world-space range check.
        let mut prototype_bounds: Vec<Option<(Vec3, Vec3)>> = Vec::new();
        for pl in placements {
            let (ni, mi) = (pl.node, pl.mesh);
            let shared = uses[&mi] >= 2;
            let world_from_object = Affine3A::from_mat4(pl.world.as_mat4());
            let invertible = Instance::transform_is_invertible(&world_from_object);
            for pi in 0..self.root.meshes[mi].primitives.len() {
                let local = self.local_primitive(mi, pi)?;
                let emissive = materials
                    .get(local.material as usize)
                    .is_some_and(Material::is_emissive);
                if self.deforms(ni, mi, pi) {
                    // Skins and morph targets: evaluated for this node, then flattened.
                    let (deformed, world) = self.deform(ni, mi, pi, &local, &pl.world)?;
                    self.flatten_primitive(ni, mi, pi, &world, &deformed, &mut geometry.meshes)?;
                    continue;
                }
                if !shared || emissive || !invertible {
                    self.flatten_primitive(ni, mi, pi, &pl.world, &local, &mut geometry.meshes)?;
                    continue;
                }
                let prototype = match prototype_of.get(&(mi, pi)) {
                    Some(&p) => p,
                    None => {
                        let name = prim_name(mi, &self.root.meshes[mi], pi);
                        self.add_output(primitive_bytes(&local), &name)?;
                        self.add_triangles(local.triangles.len(), &name)?;
                        let p = geometry.prototypes.len() as u32;
                        let mesh = object_space_mesh(&local, name);
                        prototype_bounds.push(crate::mesh_bounds(&mesh));
                        geometry.prototypes.push(mesh);
                        prototype_of.insert((mi, pi), p);
                        p
                    }
                };
                // The same rule as a flattened placement's, naming the node: an instance
                // may not put a vertex where the renderer's f32 arithmetic breaks down.
                let proto = &geometry.prototypes[prototype as usize];
                let bounds = prototype_bounds[prototype as usize];
                if let Some((v, at)) = crate::far_vertex(proto, bounds, &world_from_object) {
                    return self.err(format!(
                        "node {ni}{} {}: vertex {v} is at {at} in world space, beyond \
                         ±{:e} scene units (check the node's scale and translation)",
                        pl.gpu_instance
                            .map(|k| format!(" EXT_mesh_gpu_instancing instance {k}"))
                            .unwrap_or_default(),
                        proto.name,
                        crate::MAX_COORDINATE
                    ));
                }
                self.add_output(Instance::BYTES, &format!("node {ni} mesh {mi}"))?;
                geometry.instances.push(Instance {
                    prototype,
                    world_from_object,
                });
            }
        }
        Ok(geometry)
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
        let mut uv_sets = prim
            .material
            .and_then(|m| self.material_uv_sets.get(m.value()).copied())
            .unwrap_or(0);
        let json_material = prim
            .material
            .and_then(|m| self.root.materials.get(m.value()));
        // KHR_materials_anisotropy: the direction lives in the tangent frame (spec of the
        // extension: TANGENT, or tangents computed as for a normal map, from TEXCOORD_0
        // when there is no normal map).
        let anisotropic = json_material
            .and_then(|m| m.extensions.as_ref())
            .is_some_and(|e| e.others.contains_key("KHR_materials_anisotropy"));
        let tangent_acc = attribute(json::mesh::Semantic::Tangents);
        let normal_map = json_material
            .and_then(|m| m.normal_texture.as_ref())
            .map(|n| n.tex_coord)
            .or(anisotropic.then_some(0));
        if anisotropic && tangent_acc.is_none() {
            uv_sets = uv_sets.max(normal_map.unwrap_or(0) + 1);
        }
        let normal_acc = attribute(json::mesh::Semantic::Normals);
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
        // Spec "Meshes > Overview": TEXCOORD_n for every set a texture of the material
        // reads; a missing set reads as (0, 0).
        let mut uvs = Vec::with_capacity(uv_sets as usize);
        for set in 0..uv_sets {
            let v = match attribute(json::mesh::Semantic::TexCoords(set)) {
                Some(a) => {
                    let v = self.read_floats::<2>(a.value(), &format!("{what} TEXCOORD_{set}"))?;
                    if v.len() != n {
                        return self.err(format!(
                            "{what}: TEXCOORD_{set} has {} elements but POSITION has {n}",
                            v.len()
                        ));
                    }
                    v.into_iter().map(Vec2::from).collect()
                }
                None => Vec::new(),
            };
            uvs.push(v);
        }
        // Spec "Meshes > Overview" and "Metallic-Roughness Material": COLOR_0 multiplies
        // the base colour and its alpha.
        let colors = match attribute(json::mesh::Semantic::Colors(0)) {
            Some(a) => {
                let v = self.read_colors(a.value(), &format!("{what} COLOR_0"))?;
                if v.len() != n {
                    return self.err(format!(
                        "{what}: COLOR_0 has {} elements but POSITION has {n}",
                        v.len()
                    ));
                }
                Some(v)
            }
            None => None,
        };
        let triangles = self.read_triangles(index_acc, n, &what)?;
        let tangents = match (normal_map, tangent_acc) {
            (None, _) => None,
            (Some(_), Some(a)) => {
                let v = self.read_floats::<4>(a.value(), &format!("{what} TANGENT"))?;
                if v.len() != n {
                    return self.err(format!(
                        "{what}: TANGENT has {} elements but POSITION has {n}",
                        v.len()
                    ));
                }
                Some(
                    triangles
                        .iter()
                        .map(|t| t.map(|i| Vec4::from(v[i as usize])))
                        .collect(),
                )
            }
            (Some(set), None) => {
                let uv = uvs.get(set as usize).filter(|u| !u.is_empty());
                if uv.is_none() && anisotropic {
                    self.warnings.push(format!(
                        "{what}: KHR_materials_anisotropy without TANGENT or TEXCOORD_{set} \
                         has no tangent frame; it is rendered isotropic"
                    ));
                }
                uv.map(|uv| mikktspace(&positions, normals.as_deref(), uv, &triangles))
            }
        };
        let p = Rc::new(LocalPrimitive {
            positions,
            normals,
            uvs,
            colors,
            tangents,
            triangles,
            material,
        });
        self.primitives.insert((mi, pi), p.clone());
        Ok(p)
    }

    /// The triangles of a primitive with `n` vertices: its index accessor, or `0..n`
    /// without one (spec "Meshes > Overview"), checked against the vertex count.
    fn read_triangles(
        &self,
        index_acc: Option<json::Index<json::Accessor>>,
        n: usize,
        what: &str,
    ) -> Res<Vec<[u32; 3]>> {
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
        Ok(indices
            .chunks_exact(3)
            .map(|t| [t[0], t[1], t[2]])
            .collect())
    }

    /// Appends `local`, primitive `pi` of mesh `mi`, placed at node `ni` by `world`, as a
    /// world-space [`Mesh`].
    fn flatten_primitive(
        &mut self,
        ni: usize,
        mi: usize,
        pi: usize,
        world: &DMat4,
        local: &LocalPrimitive,
        out: &mut Vec<Mesh>,
    ) -> Res<()> {
        let linear = DMat3::from_mat4(*world);
        let det = linear.determinant();
        let normal_matrix = linear.inverse().transpose();
        let name = prim_name(mi, &self.root.meshes[mi], pi);
        self.add_output(primitive_bytes(local), &format!("node {ni} {name}"))?;
        self.add_triangles(local.triangles.len(), &format!("node {ni} {name}"))?;
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
        if let Some(v) = positions
            .iter()
            .position(|p| p.abs().max_element() > crate::MAX_COORDINATE)
        {
            return self.err(format!(
                "node {ni} {name}: vertex {v} is at {} in world space, beyond ±{:e} scene \
                 units (check the node's scale and translation)",
                positions[v],
                crate::MAX_COORDINATE
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
        // Tangents are surface directions: they transform with the linear part. A
        // mirroring transform flips the handedness of (t, b, n), hence the sign of w.
        let sign = if det < 0.0 { -1.0 } else { 1.0 };
        let tangents = local.tangents.as_ref().map(|ts| {
            ts.iter()
                .map(|c| {
                    let c = if det < 0.0 { [c[0], c[2], c[1]] } else { *c };
                    c.map(|t| {
                        let w = (linear * t.truncate().as_dvec3())
                            .normalize_or_zero()
                            .as_vec3();
                        let w = if w.is_finite() { w } else { Vec3::ZERO };
                        w.extend(if t.w < 0.0 { -sign } else { sign })
                    })
                })
                .collect()
        });
        out.push(Mesh {
            name,
            positions,
            normals,
            uvs: local.uvs.clone(),
            colors: local.colors.clone(),
            tangents,
            indices: triangles,
            material: local.material,
        });
        Ok(())
    }
}

/// Estimated output bytes of one copy of a primitive (positions, normals, one uv set,
/// vertex colours and indices), for the import budget.
fn primitive_bytes(local: &LocalPrimitive) -> u64 {
    let colors = local.colors.as_ref().map_or(0, |c| c.len() as u64 * 16);
    local.positions.len() as u64 * 32 + local.triangles.len() as u64 * 12 + colors
}

/// The object-space prototype of a primitive placed at several places. Normals are
/// renormalised as the flattened path does; if one degenerates, the mesh drops its
/// normals (as a flattened one does).
fn object_space_mesh(local: &LocalPrimitive, name: String) -> Mesh {
    let normals = local.normals.as_ref().and_then(|ns| {
        ns.iter()
            .map(|n| n.try_normalize())
            .collect::<Option<Vec<Vec3>>>()
    });
    Mesh {
        name,
        positions: local.positions.clone(),
        normals,
        uvs: local.uvs.clone(),
        colors: local.colors.clone(),
        tangents: local.tangents.clone(),
        indices: local.triangles.clone(),
        material: local.material,
    }
}

/// `mesh M 'Name' primitive P` (or `mesh M primitive P` when the mesh is unnamed).
pub(super) fn prim_name(mi: usize, mesh: &json::Mesh, pi: usize) -> String {
    match &mesh.name {
        Some(n) => format!("mesh {mi} '{n}' primitive {pi}"),
        None => format!("mesh {mi} primitive {pi}"),
    }
}

/// MikkTSpace tangents per triangle corner (Mikkelsen 2008), as the glTF spec asks for
/// when a normal-mapped primitive has no TANGENT attribute. The texture coordinates are
/// given to MikkTSpace with v flipped (`1 - v`): glTF's v runs down the image while the
/// normal map's +Y (green) points up it, the convention MikkTSpace and Blender use, so the
/// bitangent `cross(n, t) w` points toward the texture's +Y. Without normals the face
/// normal is used, as the spec prescribes flat shading then.
fn mikktspace(
    positions: &[Vec3],
    normals: Option<&[Vec3]>,
    uvs: &[Vec2],
    triangles: &[[u32; 3]],
) -> Vec<[Vec4; 3]> {
    struct Geometry<'g> {
        positions: &'g [Vec3],
        normals: Option<&'g [Vec3]>,
        uvs: &'g [Vec2],
        triangles: &'g [[u32; 3]],
        out: Vec<[Vec4; 3]>,
    }
    impl Geometry<'_> {
        fn vertex(&self, face: usize, vert: usize) -> usize {
            self.triangles[face][vert] as usize
        }
    }
    impl bevy_mikktspace::Geometry for Geometry<'_> {
        fn num_faces(&self) -> usize {
            self.triangles.len()
        }
        fn num_vertices_of_face(&self, _face: usize) -> usize {
            3
        }
        fn position(&self, face: usize, vert: usize) -> [f32; 3] {
            self.positions[self.vertex(face, vert)].to_array()
        }
        fn normal(&self, face: usize, vert: usize) -> [f32; 3] {
            match self.normals {
                Some(n) => n[self.vertex(face, vert)].to_array(),
                None => {
                    let p = self.triangles[face].map(|i| self.positions[i as usize]);
                    (p[1] - p[0])
                        .cross(p[2] - p[0])
                        .normalize_or_zero()
                        .to_array()
                }
            }
        }
        fn tex_coord(&self, face: usize, vert: usize) -> [f32; 2] {
            let uv = self.uvs[self.vertex(face, vert)];
            [uv.x, 1.0 - uv.y]
        }
        fn set_tangent(
            &mut self,
            tangent_space: Option<bevy_mikktspace::TangentSpace>,
            face: usize,
            vert: usize,
        ) {
            if let Some(ts) = tangent_space {
                self.out[face][vert] = Vec4::from(ts.tangent_encoded());
            }
        }
    }
    let mut g = Geometry {
        positions,
        normals,
        uvs,
        triangles,
        // Corners MikkTSpace leaves unset (degenerate faces) keep a zero tangent, which
        // the renderer treats as "no normal map here".
        out: vec![[Vec4::ZERO; 3]; triangles.len()],
    };
    if bevy_mikktspace::generate_tangents(&mut g).is_err() {
        return vec![[Vec4::ZERO; 3]; triangles.len()];
    }
    g.out
}
