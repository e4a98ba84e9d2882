//! The renderable form of a scene: geometry with its BVH, per-hit shading data, lights and
//! the camera, built once from a [`tessera_scene::Scene`] and shared read-only by all
//! threads.

use crate::bsdf::{
    dielectric::RoughDielectric,
    diffuse::Diffuse,
    gltf::{gltf_bsdf_at, gltf_lobe, GltfBsdf, GltfParams},
    microfacet::{Conductor, MIN_ALPHA},
    phong::Phong,
    specular::{Glass, Mirror},
    Bsdf, Lobe,
};
use crate::camera::CameraModel;
use crate::geometry::{
    sphere_point, triangle_point, Geometry, Hit, InstanceRecord, Primitive, SphereRecord,
    SurfacePoint, TriangleAttributes, TriangleRecord, Triangles, NO_INSTANCE, NO_LIGHT, NO_MESH,
};
use crate::light::emission::{EmissionSample, WorldDisk};
use crate::light::LightSample;
use crate::light::{
    environment::{EnvImage, Environment},
    punctual::Punctual,
    sphere::SphereLight,
    triangle::TriangleLight,
    Light, LightSet,
};
use crate::math::gamma;
use crate::motion::{CameraKeys, MotionShading, MotionSplit};
use crate::sampling::warp::Frame;
use crate::sampling::{hash_combine, hash_u64};
use crate::texture;
mod build;

use glam::{Affine3A, DMat3, DVec3, Mat3A, Vec2, Vec3, Vec3A, Vec4};
use tessera_scene::{
    AlphaMode, GltfMaterial, Image, Material, MaterialKind, NormalMap, PunctualLight, Scene,
    Texture, TextureRef,
};

/// Errors building a render scene.
#[derive(Debug, thiserror::Error)]
pub enum BuildError {
    /// The image size is unusable.
    #[error("image size {0}x{1} is invalid")]
    ImageSize(u32, u32),
}

/// Per-mesh shading attributes (normals, texture coordinates and vertex colours by vertex,
/// tangents by triangle corner).
struct MeshShading {
    indices: Vec<[u32; 3]>,
    normals: Option<Vec<Vec3>>,
    uvs: Vec<Vec<Vec2>>,
    /// glTF `COLOR_0`, linear RGBA; only meshes that have it pay for it.
    colors: Option<Vec<Vec4>>,
    /// In world space, or in object space for an instance's prototype (carried to world
    /// space at each hit, [`SurfacePoint::tangent`]).
    tangents: Option<Vec<[Vec4; 3]>>,
    material: u32,
}

/// A scene ready to trace.
pub struct RenderScene {
    /// Geometry and acceleration structure.
    pub geometry: Geometry,
    meshes: Vec<MeshShading>,
    materials: Vec<Material>,
    textures: Vec<Texture>,
    images: Vec<Image>,
    /// Per material: some ray may pass through it (glTF alpha MASK or BLEND).
    alpha_tested: Vec<bool>,
    /// Whether any material is alpha-tested (else intersection skips the filter).
    any_alpha: bool,
    /// Per material: it shades in a tangent frame (a normal map, or KHR_materials_anisotropy
    /// of nonzero strength), so a hit on it interpolates the tangent
    /// ([`SurfacePoint::tangent`]); every other hit skips that work.
    uses_tangents: Vec<bool>,
    /// Per material: the lobe of a glTF material whose parameters are the same at every
    /// point ([`RenderScene::constant_gltf_lobe`]), built once instead of at every hit
    /// (where the mesh has no vertex colours); `None` for the others.
    constant_gltf: Vec<Option<GltfBsdf>>,
    /// Lights with their selection distribution.
    pub lights: LightSet,
    /// The camera for the image size.
    pub camera: CameraModel,
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// Shading of the moving triangles ([`Geometry::motion`]).
    motion_shading: Option<MotionShading>,
    /// The camera at the shutter's key times, when it moves.
    camera_keys: Option<CameraKeys>,
    /// What does not blur within the shutter (see [`crate::motion`]).
    pub motion_warnings: Vec<String>,
}

impl RenderScene {
    /// Whether anything moves within the shutter: camera samples then draw a time, and
    /// rays see the scene at it. False without a shutter, and when nothing moves.
    #[inline]
    pub fn has_motion(&self) -> bool {
        self.geometry.motion.is_some() || self.camera_keys.is_some()
    }

    /// Whether the camera moves within the shutter.
    pub fn camera_moves(&self) -> bool {
        self.camera_keys.is_some()
    }

    /// A line for the log: what moves within the shutter, and whether time is sampled.
    pub fn motion_summary(&self) -> String {
        if !self.has_motion() {
            return "nothing moves within it: no time sampled, the same samples as without a \
                    shutter"
                .into();
        }
        let segments = self.geometry.motion.as_ref().map_or(0, |m| m.segments());
        format!(
            "{} triangles move ({segments} linear segments), the camera {}; time sampled",
            self.moving_triangles(),
            if self.camera_moves() {
                "moves"
            } else {
                "is still"
            }
        )
    }

    /// Number of triangles that move within the shutter.
    pub fn moving_triangles(&self) -> usize {
        self.geometry.motion.as_ref().map_or(0, |m| m.records.len())
    }

    /// The camera at shutter fraction `time` (the frame's camera when it does not move).
    #[inline]
    pub fn camera_at(&self, time: f32) -> CameraModel {
        match &self.camera_keys {
            Some(k) => k.at(time),
            None => self.camera,
        }
    }

    /// The environment's light index and the radiance it sends along `-dir` to a ray
    /// leaving the scene in direction `dir`, if the scene has an environment.
    #[inline]
    pub fn environment(&self, dir: Vec3) -> Option<(usize, Vec3)> {
        let i = self.lights.environment? as usize;
        match &self.lights.lights[i] {
            Light::Environment(e) => Some((i, e.le(dir))),
            _ => None,
        }
    }

    /// The nearest surface along `origin + t dir` (`0 < t < t_max`) that the ray does not
    /// pass through: alpha-tested triangles (glTF MASK and BLEND) let it through where
    /// their alpha says so (MASK by the cutoff, BLEND with probability `1 - alpha`).
    #[inline]
    pub fn intersect(&self, origin: Vec3, dir: Vec3, t_max: f32) -> Option<Hit> {
        self.intersect_at(origin, dir, t_max, 0.0)
    }

    /// [`RenderScene::intersect`] at shutter fraction `time` (motion blur).
    #[inline]
    pub fn intersect_at(&self, origin: Vec3, dir: Vec3, t_max: f32, time: f32) -> Option<Hit> {
        count_ray();
        if !self.any_alpha {
            return self
                .geometry
                .intersect_where(origin, dir, t_max, time, |_, _, _, _| true);
        }
        let key = ray_key(origin, dir);
        self.geometry
            .intersect_where(origin, dir, t_max, time, |tri, id, b1, b2| {
                let tri = tri.attributes();
                !self.alpha_tested[tri.material as usize]
                    || !self.transparent_at(&tri, id, b1, b2, key)
            })
    }

    /// True if an opaque (or, by alpha, not passed-through) surface blocks
    /// `origin + t dir` for `0 < t < t_max`: shadow rays see alpha like camera rays do.
    #[inline]
    pub fn occluded(&self, origin: Vec3, dir: Vec3, t_max: f32) -> bool {
        self.occluded_at(origin, dir, t_max, 0.0)
    }

    /// [`RenderScene::occluded`] at shutter fraction `time` (motion blur).
    #[inline]
    pub fn occluded_at(&self, origin: Vec3, dir: Vec3, t_max: f32, time: f32) -> bool {
        count_ray();
        if !self.any_alpha {
            return self
                .geometry
                .occluded_where(origin, dir, t_max, time, |_, _, _, _| true);
        }
        let key = ray_key(origin, dir);
        self.geometry
            .occluded_where(origin, dir, t_max, time, |tri, id, b1, b2| {
                let tri = tri.attributes();
                !self.alpha_tested[tri.material as usize]
                    || !self.transparent_at(&tri, id, b1, b2, key)
            })
    }

    /// Whether the ray with hash `key` passes through the alpha-tested triangle `tri`
    /// (identified by `id`, [`crate::geometry::triangle_key`]) at barycentrics `(b1, b2)`. MASK: where alpha is below the
    /// cutoff. BLEND: stochastically, with probability `1 - alpha` (stochastic
    /// transparency, Enderton et al. 2010), decided by a hash of the ray and the triangle
    /// rather than the sampler, as pbrt-v4 does for alpha (Pharr, Jakob & Humphreys,
    /// 4th ed., section 7.1.1): deterministic, and the same for every ray that is the same
    /// ray, so shadow rays and camera rays agree.
    fn transparent_at(
        &self,
        tri: &TriangleAttributes,
        id: u64,
        b1: f32,
        b2: f32,
        key: u64,
    ) -> bool {
        let Some(g) = self.materials[tri.material as usize].as_gltf() else {
            return false;
        };
        let alpha = self.alpha(g, tri.mesh, tri.index, Vec2::new(b1, b2));
        match g.alpha_mode {
            AlphaMode::Opaque => false,
            AlphaMode::Mask { cutoff } => alpha < cutoff,
            AlphaMode::Blend => {
                let u = (hash_combine(key, id) >> 40) as f32 * (1.0 / (1u64 << 24) as f32);
                u >= alpha
            }
        }
    }

    /// Base-colour alpha (factor times texture times vertex colour) at a point of a
    /// triangle.
    fn alpha(&self, g: &GltfMaterial, mesh: u32, tri: u32, bary: Vec2) -> f32 {
        let m = &self.meshes[mesh as usize];
        alpha_at(
            &self.textures,
            &self.images,
            g,
            (&m.uvs, m.colors.as_deref()),
            m.indices[tri as usize],
            bary,
        )
    }

    /// The vertex colour (glTF `COLOR_0`, RGBA) at `sp`, if its mesh has vertex colours.
    #[inline]
    fn vertex_color(&self, sp: &SurfacePoint) -> Option<Vec4> {
        if sp.mesh == NO_MESH {
            return None;
        }
        let m = &self.meshes[sp.mesh as usize];
        let c = m.colors.as_deref()?;
        Some(color_at(c, m.indices[sp.tri as usize], sp.bary))
    }

    /// Texture coordinates of set `set` at barycentrics `bary` of triangle `tri` of
    /// `mesh` ((0, 0) where the mesh lacks the set).
    #[inline]
    fn uv(&self, mesh: u32, tri: u32, bary: Vec2, set: u32) -> Vec2 {
        let m = &self.meshes[mesh as usize];
        uv_at(&m.uvs, m.indices[tri as usize], set, bary)
    }

    /// Texture coordinates a texture reference reads at `sp`.
    #[inline]
    fn uv_of(&self, sp: &SurfacePoint, t: &TextureRef) -> Vec2 {
        if t.uv_set == 0 || sp.mesh == NO_MESH {
            sp.uv
        } else {
            self.uv(sp.mesh, sp.tri, sp.bary, t.uv_set)
        }
    }

    /// The texture `t` at `uv` (before its KHR_texture_transform), RGBA, RGB linearised
    /// when `srgb` (colour slots; data slots are linear).
    #[inline]
    fn lookup(&self, t: &TextureRef, uv: Vec2, srgb: bool) -> Vec4 {
        lookup(&self.textures, &self.images, t, uv, srgb)
    }

    /// The texture `t` read at `sp`.
    #[inline]
    fn tex(&self, sp: &SurfacePoint, t: &Option<TextureRef>, srgb: bool) -> Vec4 {
        match t {
            Some(t) => self.lookup(t, self.uv_of(sp, t), srgb),
            None => Vec4::ONE,
        }
    }

    /// Surface data at a hit of the ray `origin + t dir`: position with its error bound,
    /// normals (interpolated, then perturbed by a glTF normal map and kept facing the view
    /// `-dir`, see `view_facing_normal`), texture coordinates.
    #[inline]
    pub fn surface(&self, hit: &Hit, origin: Vec3, dir: Vec3) -> SurfacePoint {
        let mut sp = self.surface_unbent(hit, origin, dir);
        if self.normal_map(sp.material).is_some() {
            sp.ns = view_facing_normal(sp.ng, -dir, sp.ns);
        }
        sp
    }

    /// The derivative of the unit shading normal `ns` of `sp` (the surface point of `hit`)
    /// by position: the linear map taking a displacement within the hit surface's tangent
    /// plane to the change of `ns`, the Weingarten map of the shading normal field. On a
    /// sphere it is `(I - n nᵀ) / r`; on a triangle with vertex normals the unnormalised
    /// interpolated normal `N` and the position are both linear in the barycentrics, so
    /// `dns = ±(I - ns nsᵀ) dN / |N|` with `dN` from the corners' normals and the
    /// barycentric change from the corners' positions; a flat triangle's is zero. `None`
    /// where the normal field is not stored in that form: instances, moving triangles and
    /// normal-mapped materials (a caller falls back to finite differences there). Used by
    /// manifold next-event estimation for its constraint Jacobian (Jakob & Marschner 2012,
    /// "Manifold Exploration", §4.1).
    pub fn shading_normal_derivative(&self, hit: &Hit, sp: &SurfacePoint) -> Option<DMat3> {
        if self.normal_map(sp.material).is_some() {
            return None;
        }
        match hit.primitive {
            Primitive::Sphere { index } => {
                let s = &self.geometry.spheres[index as usize];
                let n = sp.ns.as_dvec3();
                let r = s.radius.abs() as f64;
                (r > 0.0).then(|| (DMat3::IDENTITY - outer(n, n)) * (1.0 / r))
            }
            Primitive::Triangle {
                index, instance, ..
            } if instance == NO_INSTANCE => {
                let level = &self.geometry.triangles;
                let tri = level.attributes(index as usize);
                let mesh = &self.meshes[tri.mesh as usize];
                let Some(normals) = mesh.normals.as_ref() else {
                    return Some(DMat3::ZERO);
                };
                let [n0, n1, n2] =
                    mesh.indices[tri.index as usize].map(|i| normals[i as usize].as_dvec3());
                let [p0, p1, p2] = level.positions(index as usize).map(|p| p.as_dvec3());
                let (b1, b2) = (sp.bary.x as f64, sp.bary.y as f64);
                let big_n = n0 + b1 * (n1 - n0) + b2 * (n2 - n0);
                let len = big_n.length();
                if len <= 0.0 || !len.is_finite() {
                    // `ns` fell back to the geometric normal: constant over the triangle.
                    return Some(DMat3::ZERO);
                }
                let v = big_n / len;
                // `ns` is `v` turned onto the geometric normal's side.
                let side = if v.dot(sp.ng.as_dvec3()) < 0.0 {
                    -1.0
                } else {
                    1.0
                };
                // Barycentric change of an in-plane displacement `dq`: the least-squares
                // solution of `dq = e1 db1 + e2 db2`, `G⁻¹ [e1 e2]ᵀ dq` with the Gram matrix `G`.
                let (e1, e2) = (p1 - p0, p2 - p0);
                let (g11, g12, g22) = (e1.dot(e1), e1.dot(e2), e2.dot(e2));
                let det = g11 * g22 - g12 * g12;
                if det <= 1e-30 * g11 * g22 || !det.is_finite() {
                    return None;
                }
                // Rows of G⁻¹ [e1 e2]ᵀ: db1 = r1 · dq, db2 = r2 · dq.
                let r1 = (g22 * e1 - g12 * e2) / det;
                let r2 = (g11 * e2 - g12 * e1) / det;
                let project = (DMat3::IDENTITY - outer(v, v)) * (side / len);
                Some(project * (outer(n1 - n0, r1) + outer(n2 - n0, r2)))
            }
            _ => None,
        }
    }

    /// [`RenderScene::surface`] before a normal-mapped shading normal is bent for the view.
    #[inline(always)]
    fn surface_unbent(&self, hit: &Hit, origin: Vec3, dir: Vec3) -> SurfacePoint {
        match hit.primitive {
            Primitive::Triangle {
                index,
                instance,
                b1,
                b2,
            } => {
                if instance == NO_INSTANCE {
                    self.triangle_surface(&self.geometry.triangles, index, b1, b2, None)
                } else {
                    let inst = &self.geometry.instances[instance as usize];
                    let proto = &self.geometry.prototypes[inst.prototype as usize];
                    self.triangle_surface(&proto.triangles, index, b1, b2, Some(inst))
                }
            }
            Primitive::Moving {
                index,
                b1,
                b2,
                time,
            } => self.moving_surface(index as usize, b1, b2, time),
            Primitive::Sphere { index } => {
                let s = &self.geometry.spheres[index as usize];
                let (p, p_error, n) = sphere_point(s.center, s.radius, origin + dir * hit.t);
                let uv = Vec2::new(
                    0.5 + n.z.atan2(n.x) / std::f32::consts::TAU,
                    n.y.clamp(-1.0, 1.0).acos() / std::f32::consts::PI,
                );
                SurfacePoint {
                    p,
                    p_error,
                    ng: n,
                    ns: n,
                    uv,
                    mesh: NO_MESH,
                    tri: 0,
                    bary: Vec2::ZERO,
                    material: s.material,
                    light: s.light,
                    tangent: Vec4::ZERO,
                }
            }
        }
    }

    /// Surface data at barycentrics `(b1, b2)` of stored triangle `index` of `level`, which
    /// is in world space, or in object space of the instance `inst`. For an instance the position and its error
    /// bound are carried to world space (see [`transform_point`]), normals by the inverse
    /// transpose and tangents by the linear part, the bitangent sign flipped when the
    /// instance mirrors, so the result equals that of a flattened copy up to rounding.
    #[inline(always)]
    fn triangle_surface(
        &self,
        level: &Triangles,
        index: u32,
        b1: f32,
        b2: f32,
        inst: Option<&InstanceRecord>,
    ) -> SurfacePoint {
        let b0 = 1.0 - b1 - b2;
        let corners = level.positions(index as usize);
        let tri = &level.attributes(index as usize);
        let (mut p, mut p_error) = triangle_point(&corners, b0, b1, b2);
        let mut ng = (corners[1] - corners[0])
            .cross(corners[2] - corners[0])
            .normalize_or(Vec3::Z);
        if let Some(inst) = inst {
            (p, p_error) = transform_point(inst, p, p_error);
            ng = (inst.normal_to_world * Vec3A::from(ng))
                .normalize_or(Vec3A::Z)
                .into();
        }
        let mesh = &self.meshes[tri.mesh as usize];
        let idx = mesh.indices[tri.index as usize];
        let normals = mesh.normals.as_ref().map(|n| {
            let corners = idx.map(|i| n[i as usize]);
            match inst {
                None => corners,
                // Each vertex normal to world space and renormalised before interpolating,
                // as the importer does for a flattened copy: under non-uniform scale the
                // lengths change unequally, and the interpolation must weigh the same
                // unit normals to give the same shading.
                Some(inst) => corners
                    .map(|v| Vec3::from(inst.normal_to_world * Vec3A::from(v)).normalize_or_zero()),
            }
        });
        let mut sp = self.shaded_point(tri, p, p_error, ng, normals, b1, b2);
        if let (true, Some(t)) = (self.uses_tangents[tri.material as usize], &mesh.tangents) {
            let c = t[tri.index as usize];
            let mut tangent = (c[0] * b0 + c[1] * b1 + c[2] * b2).truncate();
            let mut sign = if c[0].w < 0.0 { -1.0 } else { 1.0 };
            if let Some(inst) = inst {
                tangent = inst.world_from_object.transform_vector3(tangent);
                sign *= inst.handedness;
            }
            self.set_tangent(&mut sp, tangent, sign);
        }
        sp
    }

    /// The surface point at barycentrics `(b1, b2)` of `tri` at world position `p` (error
    /// bound `p_error`) with geometric normal `ng`: the shading normal interpolated from
    /// the world-space vertex `normals` (if any) onto `ng`'s side, texture coordinates
    /// from the mesh.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn shaded_point(
        &self,
        tri: &TriangleAttributes,
        p: Vec3,
        p_error: Vec3,
        ng: Vec3,
        normals: Option<[Vec3; 3]>,
        b1: f32,
        b2: f32,
    ) -> SurfacePoint {
        let b0 = 1.0 - b1 - b2;
        let mesh = &self.meshes[tri.mesh as usize];
        let idx = mesh.indices[tri.index as usize];
        let mut ns = ng;
        if let Some([n0, n1, n2]) = normals {
            if let Some(v) = (b0 * n0 + b1 * n1 + b2 * n2).try_normalize() {
                ns = if v.dot(ng) < 0.0 { -v } else { v };
            }
        }
        let bary = Vec2::new(b1, b2);
        SurfacePoint {
            p,
            p_error,
            ng,
            ns,
            uv: uv_at(&mesh.uvs, idx, 0, bary),
            mesh: tri.mesh,
            tri: tri.index,
            bary,
            material: tri.material,
            light: tri.light,
            tangent: Vec4::ZERO,
        }
    }

    /// The normal map of `material`, if it has one (tangents are interpolated only then).
    #[inline(always)]
    fn normal_map(&self, material: u32) -> Option<&NormalMap> {
        self.materials[material as usize]
            .as_gltf()
            .and_then(|g| g.normal_map.as_ref())
    }

    /// Gives `sp` its world-space `tangent` and bitangent `sign`, and perturbs its shading
    /// normal by the material's normal map (if any) in that frame: one frame for the normal
    /// map and the anisotropy's direction ([`RenderScene::anisotropy`]).
    #[inline(always)]
    fn set_tangent(&self, sp: &mut SurfacePoint, tangent: Vec3, sign: f32) {
        sp.tangent = tangent.extend(sign);
        if let Some(nm) = self.normal_map(sp.material) {
            self.apply_normal_map(sp, nm, tangent, sign);
        }
    }

    /// Perturbs `sp.ns` by the normal map `nm` in the tangent frame of `tangent` and
    /// bitangent sign `sign`.
    #[inline(always)]
    fn apply_normal_map(&self, sp: &mut SurfacePoint, nm: &NormalMap, tangent: Vec3, sign: f32) {
        let texel = self.lookup(&nm.texture, self.uv_of(sp, &nm.texture), false);
        sp.ns = normal_mapped(sp.ns, sp.ng, tangent, sign, texel, nm.scale);
    }

    /// Surface data at barycentrics `(b1, b2)` of moving triangle `r` as it stands at
    /// shutter fraction `time`: positions, normals and tangents interpolated between the
    /// key times exactly as the intersection interpolated the positions.
    fn moving_surface(&self, r: usize, b1: f32, b2: f32, time: f32) -> SurfacePoint {
        let motion = self
            .geometry
            .motion
            .as_ref()
            .expect("a moving hit comes from the motion triangles");
        let shading = self
            .motion_shading
            .as_ref()
            .expect("moving triangles have their shading");
        let tri = &motion.records[r].attributes();
        let p3 = motion.positions_at(r, time);
        let (s, u) = motion.segment_of(time);
        let b0 = 1.0 - b1 - b2;
        let (p, p_error) = triangle_point(&p3, b0, b1, b2);
        let mut ng = (p3[1] - p3[0]).cross(p3[2] - p3[0]).normalize_or(Vec3::Z);
        if shading.flipped(r) {
            ng = -ng;
        }
        let mut sp = self.shaded_point(tri, p, p_error, ng, shading.normals_at(r, s, u), b1, b2);
        if self.uses_tangents[tri.material as usize] {
            if let Some(c) = shading.tangents_at(r, s, u) {
                let tangent = (c[0] * b0 + c[1] * b1 + c[2] * b2).truncate();
                let sign = if c[0].w < 0.0 { -1.0 } else { 1.0 };
                self.set_tangent(&mut sp, tangent, sign);
            }
        }
        sp
    }

    /// Beer–Lambert transmittance `exp(-σ_a t)` of a ray segment of length `t` (unit `dir`)
    /// that ends at `sp` coming from the inside of a KHR_materials_volume material, i.e.
    /// arriving at the back of its (outward-facing) surface: the segment ran through the
    /// absorbing volume. 1 elsewhere. This assumes closed meshes with outward normals, as
    /// the extension does; a path tracer needs no `thicknessFactor`.
    #[inline]
    pub fn transmittance(&self, sp: &SurfacePoint, dir: Vec3, t: f32) -> Vec3 {
        match self.materials[sp.material as usize]
            .as_gltf()
            .and_then(|g| g.volume.as_ref())
        {
            Some(v) if dir.dot(sp.ng) > 0.0 => (-v.sigma_a * t).exp(),
            _ => Vec3::ONE,
        }
    }

    /// Radiance emitted by the surface at `sp` toward `w` (unit, pointing away from it),
    /// with the material's emissive texture applied.
    #[inline]
    pub fn emitted(&self, sp: &SurfacePoint, w: Vec3) -> Vec3 {
        if sp.light == NO_LIGHT {
            return Vec3::ZERO;
        }
        match &self.lights.lights[sp.light as usize] {
            Light::Triangle(l) => {
                let le = l.emitted(w);
                match self.materials[sp.material as usize].emissive_texture() {
                    Some(t) if le != Vec3::ZERO => le * self.tex(sp, &Some(*t), true).truncate(),
                    _ => le,
                }
            }
            Light::Sphere(l) => {
                if sp.ng.dot(w) > 0.0 {
                    l.radiance
                } else {
                    Vec3::ZERO
                }
            }
            _ => Vec3::ZERO,
        }
    }

    /// How much of a triangle light's factor is emitted at point `p` on it: the emissive
    /// texture there, times the alpha coverage (the probability that a ray would find the
    /// surface there, which is what a hit sees on average). 1 for untextured lights.
    fn emission_scale(&self, l: &TriangleLight, p: Vec3) -> Vec3 {
        let Some((mesh, tri)) = l.shading else {
            return Vec3::ONE;
        };
        let m = &self.meshes[mesh as usize];
        let material = &self.materials[m.material as usize];
        let idx = m.indices[tri as usize];
        let bary = barycentrics(&l.p, p);
        emission_variation(
            &self.textures,
            &self.images,
            material,
            (&m.uvs, m.colors.as_deref()),
            idx,
            bary,
        )
    }

    /// Samples light `li` as seen from `p_ref` (see [`Light::sample_li`]), with textured
    /// emission evaluated at the sampled point.
    #[inline]
    pub fn sample_li(&self, li: usize, p_ref: Vec3, u: Vec2) -> Option<LightSample> {
        let light = &self.lights.lights[li];
        let mut ls = light.sample_li(p_ref, u)?;
        if let Light::Triangle(l) = light {
            if l.shading.is_some() {
                ls.li *= self.emission_scale(l, ls.p);
                if ls.li == Vec3::ZERO {
                    return None;
                }
            }
        }
        Some(ls)
    }

    /// Samples a ray leaving light `li` (see [`Light::sample_le`]), with textured emission
    /// evaluated at its origin.
    #[inline]
    pub fn sample_le(
        &self,
        li: usize,
        u_pos: Vec2,
        u_dir: Vec2,
        world: &WorldDisk,
    ) -> Option<EmissionSample> {
        let light = &self.lights.lights[li];
        let mut es = light.sample_le(u_pos, u_dir, world)?;
        if let Light::Triangle(l) = light {
            if l.shading.is_some() {
                es.le *= self.emission_scale(l, es.p);
                if es.le == Vec3::ZERO {
                    return None;
                }
            }
        }
        Some(es)
    }

    /// The BSDF of the material at `sp`, for light leaving toward the world direction
    /// `wo` (a glTF lobe looks up what depends on `wo` alone once; any `wo` may be
    /// evaluated).
    #[inline]
    pub fn bsdf(&self, sp: &SurfacePoint, wo: Vec3) -> Bsdf {
        let m = &self.materials[sp.material as usize];
        match &m.kind {
            MaterialKind::Diffuse { albedo } => {
                Bsdf::single(Lobe::Diffuse(Diffuse { albedo: *albedo }))
            }
            MaterialKind::Phong { kd, ks, exponent } => Bsdf::single(Lobe::Phong(Phong {
                kd: *kd,
                ks: *ks,
                exponent: *exponent,
            })),
            MaterialKind::Conductor { f0, roughness } => Bsdf::single(Lobe::Conductor(Conductor {
                f0: *f0,
                alpha: (roughness * roughness).max(MIN_ALPHA),
            })),
            MaterialKind::Mirror { reflectance } => Bsdf::single(Lobe::Mirror(Mirror {
                reflectance: *reflectance,
            })),
            MaterialKind::Dielectric {
                ior,
                roughness,
                tint,
            } => {
                let alpha = roughness * roughness;
                if alpha < MIN_ALPHA {
                    Bsdf::single(Lobe::Glass(Glass {
                        eta: *ior,
                        tint: *tint,
                    }))
                } else {
                    Bsdf::single(Lobe::RoughDielectric(RoughDielectric {
                        eta: *ior,
                        alpha,
                        tint: *tint,
                    }))
                }
            }
            // `wo.dot(ns)` is `Frame::from_normal(ns).to_local(wo).z` to the bit.
            MaterialKind::Gltf(g) => match &self.constant_gltf[sp.material as usize] {
                // The lobe `gltf_params` would give here, built once: vertex colours are
                // the one input besides the material's that can still vary.
                Some(lobe) if self.vertex_color_free(sp) => lobe.prepared(wo.dot(sp.ns)),
                _ => gltf_bsdf_at(&self.gltf_params(g, sp), wo.dot(sp.ns)),
            },
        }
    }

    /// Whether the mesh of `sp` has no vertex colours (a sphere has none).
    #[inline]
    fn vertex_color_free(&self, sp: &SurfacePoint) -> bool {
        sp.mesh == NO_MESH || self.meshes[sp.mesh as usize].colors.is_none()
    }

    /// The lobe of the glTF material `g` if its [`RenderScene::gltf_params`] are the same
    /// at every point of a mesh without vertex colours: unlit, or with no texture at all
    /// ([`GltfMaterial::textures`], so a texture slot added there is never missed; the
    /// normal map sets the diffuse gain per point) and no anisotropy (whose direction
    /// follows the tangent). Those are computed once, here, by the very function a hit
    /// would call (a missing texture reads as one, `x * 1.0 == x`).
    fn constant_gltf_lobe(&self, g: &GltfMaterial) -> Option<GltfBsdf> {
        if !g.unlit && (g.textures().next().is_some() || g.anisotropy.is_some()) {
            return None;
        }
        let anywhere = SurfacePoint {
            p: Vec3::ZERO,
            p_error: Vec3::ZERO,
            ng: Vec3::Z,
            ns: Vec3::Z,
            uv: Vec2::ZERO,
            mesh: NO_MESH,
            tri: 0,
            bary: Vec2::ZERO,
            material: 0,
            light: NO_LIGHT,
            tangent: Vec4::ZERO,
        };
        Some(gltf_lobe(&self.gltf_params(g, &anywhere)))
    }

    /// The glTF material's parameters at `sp`: every factor times its texture (glTF 2.0
    /// spec "Metallic-Roughness Material" and the extension specifications for which
    /// channel each texture carries).
    fn gltf_params(&self, g: &GltfMaterial, sp: &SurfacePoint) -> GltfParams {
        if g.unlit {
            // KHR_materials_unlit: emission only (set up by the importer), no scattering.
            return GltfParams {
                base_color: Vec3::ZERO,
                metallic: 0.0,
                specular: 0.0,
                ..GltfParams::default()
            };
        }
        let mr = self.tex(sp, &g.metallic_roughness_texture, false);
        let mut base_color = g.base_color * self.tex(sp, &g.base_color_texture, true).truncate();
        let (anisotropy, anisotropy_direction) = self.anisotropy(g, sp);
        // glTF 2.0 "Metallic-Roughness Material": base colour = factor × texture × COLOR_0.
        if let Some(c) = self.vertex_color(sp) {
            base_color *= c.truncate();
        }
        GltfParams {
            base_color,
            metallic: g.metallic * mr.z,
            roughness: g.roughness * mr.y,
            ior: g.ior,
            specular: g.specular * self.tex(sp, &g.specular_texture, false).w,
            specular_color: g.specular_color
                * self.tex(sp, &g.specular_color_texture, true).truncate(),
            transmission: g.transmission * self.tex(sp, &g.transmission_texture, false).x,
            clearcoat: g.clearcoat * self.tex(sp, &g.clearcoat_texture, false).x,
            clearcoat_roughness: g.clearcoat_roughness
                * self.tex(sp, &g.clearcoat_roughness_texture, false).y,
            sheen_color: g.sheen_color * self.tex(sp, &g.sheen_color_texture, true).truncate(),
            sheen_roughness: g.sheen_roughness * self.tex(sp, &g.sheen_roughness_texture, false).w,
            diffuse_gain: if g.normal_map.is_some() {
                normal_map_diffuse_gain(sp.ns, sp.ng)
            } else {
                1.0
            },
            anisotropy,
            anisotropy_direction,
        }
    }

    /// KHR_materials_anisotropy at `sp`: the strength and the direction in the local
    /// shading frame (`Frame::from_normal(ns)`, the integrators' frame). The extension's
    /// direction is `(cos, sin)` of `anisotropyRotation`, or the texture's `2 rg - 1`
    /// rotated by it (its B channel scaling the strength), in the frame of the hit's
    /// tangent and bitangent `w cross(n, t)` ([`SurfacePoint::tangent`], the normal map's
    /// frame, on instances and moving meshes as on world-space ones), here made orthogonal
    /// to the shading normal. `(0, +x)`, isotropic, without the extension or a tangent.
    fn anisotropy(&self, g: &GltfMaterial, sp: &SurfacePoint) -> (f32, Vec2) {
        const ISOTROPIC: (f32, Vec2) = (0.0, Vec2::X);
        let Some(a) = &g.anisotropy else {
            return ISOTROPIC;
        };
        let tangent = sp.tangent.truncate();
        let sign = if sp.tangent.w < 0.0 { -1.0 } else { 1.0 };
        let n = sp.ns;
        let Some(t) = (tangent - n * n.dot(tangent)).try_normalize() else {
            return ISOTROPIC;
        };
        let b = n.cross(t) * sign;
        let (sin, cos) = a.rotation.sin_cos();
        let (mut strength, mut dir) = (a.strength, Vec2::new(cos, sin));
        if a.texture.is_some() {
            let texel = self.tex(sp, &a.texture, false);
            let d = Vec2::new(2.0 * texel.x - 1.0, 2.0 * texel.y - 1.0)
                .try_normalize()
                .unwrap_or(Vec2::X);
            dir = Vec2::new(cos * d.x - sin * d.y, sin * d.x + cos * d.y);
            strength *= texel.z;
        }
        let world = t * dir.x + b * dir.y;
        let frame = Frame::from_normal(n);
        (strength, Vec2::new(world.dot(frame.s), world.dot(frame.t)))
    }
}

/// A point of instance `inst` and its absolute error bound carried from object to world
/// space (pbrt 3rd ed., Pharr, Jakob & Humphreys, section 3.9.4 "Bounding Intersection
/// Point Error", "Effect of Transformations": the input error through `|M|` grown by
/// `1 + gamma(3)`, plus `gamma(3) (|M| |p| + |t|)` for the transform's own rounding).
/// One more such term is added for the spawned ray's origin, which is carried back into
/// object space by `object_from_world` and rounded again there: the offset along the
/// normal must cover that too, or a ray could restart behind its own surface.
#[inline(always)]
fn transform_point(inst: &InstanceRecord, p: Vec3, err: Vec3) -> (Vec3, Vec3) {
    let m = &inst.world_from_object;
    let abs_m = Mat3A::from_cols(
        m.matrix3.x_axis.abs(),
        m.matrix3.y_axis.abs(),
        m.matrix3.z_axis.abs(),
    );
    let pw = m.transform_point3(p);
    let forward = (1.0 + gamma(3)) * (abs_m * Vec3A::from(err))
        + gamma(3) * (abs_m * Vec3A::from(p.abs()) + m.translation.abs());
    // The inverse transform's rounding of the world point, expressed in world space.
    let inv = &inst.object_from_world;
    let abs_inv = Mat3A::from_cols(
        inv.matrix3.x_axis.abs(),
        inv.matrix3.y_axis.abs(),
        inv.matrix3.z_axis.abs(),
    );
    let back = gamma(3) * (abs_m * (abs_inv * Vec3A::from(pw.abs()) + inv.translation.abs()));
    (pw, (forward + back).into())
}

/// A mesh's per-vertex texture coordinates and vertex colours (if any).
type VertexData<'a> = (&'a [Vec<Vec2>], Option<&'a [Vec4]>);

/// Base-colour alpha (factor times texture times vertex colour alpha) at barycentrics
/// `bary` of the triangle `idx` of a mesh with texture coordinates and vertex colours
/// `(uvs, colors)`.
#[inline]
fn alpha_at(
    textures: &[Texture],
    images: &[Image],
    g: &GltfMaterial,
    (uvs, colors): VertexData<'_>,
    idx: [u32; 3],
    bary: Vec2,
) -> f32 {
    let alpha = match &g.base_color_texture {
        Some(t) => {
            let uv = uv_at(uvs, idx, t.uv_set, bary);
            g.alpha * lookup(textures, images, t, uv, true).w
        }
        None => g.alpha,
    };
    match colors {
        Some(c) => alpha * color_at(c, idx, bary).w,
        None => alpha,
    }
}

/// The vertex colour at barycentrics `bary` of the triangle `idx`.
#[inline]
fn color_at(colors: &[Vec4], idx: [u32; 3], bary: Vec2) -> Vec4 {
    (1.0 - bary.x - bary.y) * colors[idx[0] as usize]
        + bary.x * colors[idx[1] as usize]
        + bary.y * colors[idx[2] as usize]
}

/// How much of a material's emission factor leaves a point of a triangle: its emissive
/// texture there times its alpha coverage (1 without either).
fn emission_variation(
    textures: &[Texture],
    images: &[Image],
    material: &Material,
    (uvs, colors): VertexData<'_>,
    idx: [u32; 3],
    bary: Vec2,
) -> Vec3 {
    let mut scale = Vec3::ONE;
    if let Some(t) = material.emissive_texture() {
        let uv = uv_at(uvs, idx, t.uv_set, bary);
        scale *= lookup(textures, images, t, uv, true).truncate();
    }
    if let Some(g) = material.as_gltf() {
        scale *= coverage(
            g.alpha_mode,
            alpha_at(textures, images, g, (uvs, colors), idx, bary),
        );
    }
    scale
}

/// The probability that a ray finds a surface of alpha `alpha` there: 1 when opaque, 0 or
/// 1 by the cutoff for MASK, `alpha` for BLEND (stochastic transparency's expectation).
#[inline]
fn coverage(mode: AlphaMode, alpha: f32) -> f32 {
    match mode {
        AlphaMode::Opaque => 1.0,
        AlphaMode::Mask { cutoff } => f32::from(u8::from(alpha >= cutoff)),
        AlphaMode::Blend => alpha.clamp(0.0, 1.0),
    }
}

/// A hash of a ray, for decisions that must be the same for the same ray (alpha).
#[inline]
fn ray_key(origin: Vec3, dir: Vec3) -> u64 {
    let a = (u64::from(origin.x.to_bits()) << 32) | u64::from(origin.y.to_bits());
    let b = (u64::from(origin.z.to_bits()) << 32) | u64::from(dir.x.to_bits());
    let c = (u64::from(dir.y.to_bits()) << 32) | u64::from(dir.z.to_bits());
    hash_combine(hash_combine(hash_u64(a), b), c)
}

/// Texture coordinates of set `set` at barycentrics `bary` of the triangle `idx`.
#[inline]
fn uv_at(uvs: &[Vec<Vec2>], idx: [u32; 3], set: u32, bary: Vec2) -> Vec2 {
    match uvs.get(set as usize) {
        Some(uv) if !uv.is_empty() => {
            (1.0 - bary.x - bary.y) * uv[idx[0] as usize]
                + bary.x * uv[idx[1] as usize]
                + bary.y * uv[idx[2] as usize]
        }
        // No coordinates: set 0 falls back to the barycentrics (as before textures had
        // sets), other sets read (0, 0).
        _ if set == 0 => bary,
        _ => Vec2::ZERO,
    }
}

/// Texture reference `t` at `uv`, after its KHR_texture_transform.
#[inline]
fn lookup(textures: &[Texture], images: &[Image], t: &TextureRef, uv: Vec2, srgb: bool) -> Vec4 {
    let tex = &textures[t.texture as usize];
    let uv = match &t.transform {
        Some(m) => m.apply(uv),
        None => uv,
    };
    texture::sample(&images[tex.image as usize], tex, uv, srgb)
}

/// Barycentric coordinates `(b1, b2)` of a point `p` in (or numerically near) triangle
/// `t`, from the sub-triangle areas.
fn barycentrics(t: &[Vec3; 3], p: Vec3) -> Vec2 {
    let n = (t[1] - t[0]).cross(t[2] - t[0]);
    let len2 = n.length_squared();
    if len2 <= 0.0 {
        return Vec2::ZERO;
    }
    let b1 = (t[2] - t[0]).cross(p - t[0]).dot(n) / -len2;
    let b2 = (t[1] - t[0]).cross(p - t[0]).dot(n) / len2;
    Vec2::new(b1.clamp(0.0, 1.0), b2.clamp(0.0, 1.0))
}

/// The shading normal after a tangent-space normal map (glTF 2.0 spec "Materials >
/// Normal texture"): `n' = normalize(t x + b y + n z)` with `(x, y, z) = (2 rgb - 1)`,
/// `x` and `y` scaled by `scale`, `t` made orthogonal to `n` (Gram–Schmidt) and
/// `b = cross(n, t) w`. A degenerate tangent or a result on the wrong side of the
/// geometric normal leaves `n` unchanged, so no shading normal ever points into the
/// surface.
fn normal_mapped(n: Vec3, ng: Vec3, tangent: Vec3, sign: f32, texel: Vec4, scale: f32) -> Vec3 {
    let t = tangent - n * n.dot(tangent);
    let Some(t) = t.try_normalize() else {
        return n;
    };
    let b = n.cross(t) * sign;
    let x = (2.0 * texel.x - 1.0) * scale;
    let y = (2.0 * texel.y - 1.0) * scale;
    let z = 2.0 * texel.z - 1.0;
    match (t * x + b * y + n * z).try_normalize() {
        Some(m) if m.dot(ng) > 0.0 => m,
        _ => n,
    }
}

/// The gain `2 / (1 + |ns·ng|)` of a Lambertian lobe about the shading normal `ns` of a
/// normal-mapped surface of geometric normal `ng` (both unit): the integrators reject the
/// directions below the geometric surface (light does not leak through it), which take
/// `(1 - cos θ) / 2` of a cosine lobe tilted by `θ` from `ng` (the sky view factor of a
/// tilted plane is `(1 + cos θ) / 2`), whatever the view. The gain returns exactly that,
/// so a white normal-mapped Lambertian surface keeps all the light in a white furnace (it
/// kept 95.5% with a strong map); it depends on the shading point alone, so the lobe stays
/// reciprocal (docs/rendering.md, "Normal maps and energy", has the measurements).
#[inline]
pub(crate) fn normal_map_diffuse_gain(ns: Vec3, ng: Vec3) -> f32 {
    2.0 / (1.0 + ns.dot(ng).abs().min(1.0))
}

/// The shading normal `n` turned toward the geometric normal `ng`, in their common plane,
/// just enough that the view direction `v` (unit, pointing away from the surface) is above
/// the shading hemisphere by `min(0.9 v·ng, 0.01)`; `n` itself when it already is. A
/// normal-mapped shading normal can face away from a grazing view that the surface faces:
/// the opaque BSDFs then see `wo` below the shading hemisphere, mirror their frame and
/// scatter into the lower shading hemisphere, nearly all of it below the geometric
/// surface, which the integrators reject (light does not leak through surfaces): black
/// holes on normal-mapped floors seen along their length. Cycles keeps such views
/// shading (its diffuse closures ignore which side of `N` the view is on, its glossy ones
/// bend `N` with `ensure_valid_specular_reflection`); the smallest turn that puts the view
/// above the shading hemisphere does the same for every lobe while leaving every other
/// shading point as it was (docs/rendering.md, "Normal maps at grazing angles", has the
/// measurements). Seen from behind, `ng` and `n` are mirrored first.
pub(crate) fn view_facing_normal(ng: Vec3, v: Vec3, n: Vec3) -> Vec3 {
    let back = v.dot(ng) < 0.0;
    let (ng, n) = if back { (-ng, -n) } else { (ng, n) };
    let vz = v.dot(ng);
    let threshold = (0.9 * vz).min(0.01);
    if n.dot(v) >= threshold {
        return if back { -n } else { n };
    }
    // With x the unit tangential part of n, n(ψ) = cos ψ x + sin ψ ng and
    // v·n(ψ) = ρ cos(ψ - ψ0), ρ = |(v·x, v·ng)|, ψ0 = atan2(v·ng, v·x); it rises from below
    // the threshold at n to v·ng above it at ng, crossing it at ψ0 - acos(threshold / ρ).
    let x = (n - n.dot(ng) * ng).try_normalize().unwrap_or(n);
    let vx = v.dot(x);
    let rho = (vx * vx + vz * vz).sqrt();
    let bent = if rho <= 0.0 {
        ng
    } else {
        let psi = vz.atan2(vx) - (threshold / rho).clamp(-1.0, 1.0).acos();
        let (s, c) = psi.sin_cos();
        (c * x + s * ng).normalize_or(ng)
    };
    if back {
        -bent
    } else {
        bent
    }
}

thread_local! {
    /// Rays traced on this thread ([`rays_traced`]).
    static RAYS: std::cell::Cell<u64> = const { std::cell::Cell::new(0) };
}

/// Counts one ray query: a thread-local add, a few instructions beside the traversal's
/// thousands, so every render counts without a branch or a shared cache line.
#[inline(always)]
fn count_ray() {
    RAYS.with(|r| r.set(r.get().wrapping_add(1)));
}

/// Ray queries ([`RenderScene::intersect_at`] and [`RenderScene::occluded_at`], closest
/// hits and shadow rays alike) made on the calling thread since it started. The difference
/// across a call that renders on this thread is that call's ray count: deterministic, as
/// the render is, so it can stand for cost where wall time cannot (the technique pilot,
/// [`crate::pilot`]) and give rays per second beside paths per second.
pub fn rays_traced() -> u64 {
    RAYS.with(std::cell::Cell::get)
}

/// The outer product `a bᵀ`.
fn outer(a: DVec3, b: DVec3) -> DMat3 {
    DMat3::from_cols(a * b.x, a * b.y, a * b.z)
}

#[cfg(test)]
mod tests;
