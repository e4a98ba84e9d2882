//! The renderable form of a scene: geometry with its BVH, per-hit shading data, lights and
//! the camera, built once from a [`tessera_scene::Scene`] and shared read-only by all
//! threads.

use crate::bsdf::{
    diffuse::Diffuse,
    gltf::{gltf_bsdf, GltfParams},
    microfacet::{Conductor, MIN_ALPHA},
    phong::Phong,
    specular::{Glass, Mirror},
    Bsdf, Lobe,
};
use crate::camera::CameraModel;
use crate::geometry::{
    sphere_point, triangle_point, Geometry, Hit, Primitive, SphereRecord, SurfacePoint,
    TriangleRecord, NO_LIGHT,
};
use crate::light::{
    environment::Environment, punctual::Punctual, sphere::SphereLight, triangle::TriangleLight,
    Light, LightSet,
};
use glam::{Vec2, Vec3};
use tessera_scene::{Material, MaterialKind, PunctualLight, Scene, Texture};

/// Errors building a render scene.
#[derive(Debug, thiserror::Error)]
pub enum BuildError {
    /// The image size is unusable.
    #[error("image size {0}x{1} is invalid")]
    ImageSize(u32, u32),
}

/// Per-mesh shading attributes (normals and texture coordinates by vertex).
struct MeshShading {
    indices: Vec<[u32; 3]>,
    normals: Option<Vec<Vec3>>,
    uvs: Option<Vec<Vec2>>,
}

/// A scene ready to trace.
pub struct RenderScene {
    /// Geometry and acceleration structure.
    pub geometry: Geometry,
    meshes: Vec<MeshShading>,
    materials: Vec<Material>,
    textures: Vec<Texture>,
    /// Lights with their selection distribution.
    pub lights: LightSet,
    /// The camera for the image size.
    pub camera: CameraModel,
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
}

impl RenderScene {
    /// Builds the BVH, the light list and the camera for a `width` x `height` image.
    pub fn build(scene: &Scene, width: u32, height: u32) -> Result<Self, BuildError> {
        if width == 0 || height == 0 {
            return Err(BuildError::ImageSize(width, height));
        }
        let mut lights: Vec<Light> = Vec::new();
        let mut triangles = Vec::with_capacity(scene.triangle_count());
        for (mi, mesh) in scene.meshes.iter().enumerate() {
            let mat = &scene.materials[mesh.material as usize];
            for (ti, idx) in mesh.indices.iter().enumerate() {
                let p = idx.map(|i| mesh.positions[i as usize]);
                let mut light = NO_LIGHT;
                if mat.is_emissive() {
                    if let Some(l) = TriangleLight::new(p, mat.emission, mat.double_sided) {
                        light = lights.len() as u32;
                        lights.push(Light::Triangle(l));
                    }
                }
                triangles.push(TriangleRecord {
                    p,
                    mesh: mi as u32,
                    index: ti as u32,
                    material: mesh.material,
                    light,
                });
            }
        }
        let mut spheres = Vec::with_capacity(scene.spheres.len());
        for s in &scene.spheres {
            let mat = &scene.materials[s.material as usize];
            let mut light = NO_LIGHT;
            if mat.is_emissive() {
                light = lights.len() as u32;
                lights.push(Light::Sphere(SphereLight {
                    center: s.center,
                    radius: s.radius,
                    radiance: mat.emission,
                }));
            }
            spheres.push(SphereRecord {
                center: s.center,
                radius: s.radius,
                material: s.material,
                light,
            });
        }
        let geometry = Geometry::build(triangles, spheres);
        for l in &scene.lights {
            lights.push(Light::Punctual(match *l {
                PunctualLight::Point {
                    position,
                    intensity,
                } => Punctual::Point {
                    position,
                    intensity,
                },
                PunctualLight::Spot {
                    position,
                    direction,
                    intensity,
                    inner_angle,
                    outer_angle,
                } => Punctual::Spot {
                    position,
                    axis: direction,
                    intensity,
                    cos_inner: inner_angle.cos(),
                    cos_outer: outer_angle.cos(),
                },
                PunctualLight::Directional {
                    direction,
                    irradiance,
                } => Punctual::Directional {
                    direction,
                    irradiance,
                    scene_radius: geometry.bounds_radius,
                },
            }));
        }
        if let Some(radiance) = scene.environment {
            lights.push(Light::Environment(Environment {
                radiance,
                scene_radius: geometry.bounds_radius,
            }));
        }
        let meshes = scene
            .meshes
            .iter()
            .map(|m| MeshShading {
                indices: m.indices.clone(),
                normals: m.normals.clone(),
                uvs: m.uvs.clone(),
            })
            .collect();
        Ok(Self {
            geometry,
            meshes,
            materials: scene.materials.clone(),
            textures: scene.textures.clone(),
            lights: LightSet::new(lights),
            camera: CameraModel::new(&scene.camera, width, height),
            width,
            height,
        })
    }

    /// The environment radiance, if the scene has one.
    #[inline]
    pub fn environment(&self) -> Option<(usize, Vec3)> {
        let i = self.lights.environment? as usize;
        match &self.lights.lights[i] {
            Light::Environment(e) => Some((i, e.radiance)),
            _ => None,
        }
    }

    /// Surface data at a hit of the ray `origin + t dir`.
    #[inline]
    pub fn surface(&self, hit: &Hit, origin: Vec3, dir: Vec3) -> SurfacePoint {
        match hit.primitive {
            Primitive::Triangle { index, b1, b2 } => {
                let tri = &self.geometry.triangles[index as usize];
                let b0 = 1.0 - b1 - b2;
                let (p, p_error) = triangle_point(&tri.p, b0, b1, b2);
                let ng = (tri.p[1] - tri.p[0])
                    .cross(tri.p[2] - tri.p[0])
                    .normalize_or(Vec3::Z);
                let mesh = &self.meshes[tri.mesh as usize];
                let idx = mesh.indices[tri.index as usize];
                let mut ns = ng;
                if let Some(n) = &mesh.normals {
                    let interp =
                        b0 * n[idx[0] as usize] + b1 * n[idx[1] as usize] + b2 * n[idx[2] as usize];
                    if let Some(v) = interp.try_normalize() {
                        ns = if v.dot(ng) < 0.0 { -v } else { v };
                    }
                }
                let uv = match &mesh.uvs {
                    Some(uv) => {
                        b0 * uv[idx[0] as usize]
                            + b1 * uv[idx[1] as usize]
                            + b2 * uv[idx[2] as usize]
                    }
                    None => Vec2::new(b1, b2),
                };
                SurfacePoint {
                    p,
                    p_error,
                    ng,
                    ns,
                    uv,
                    material: tri.material,
                    light: tri.light,
                }
            }
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
                    material: s.material,
                    light: s.light,
                }
            }
        }
    }

    /// Radiance emitted by the surface at `sp` toward `w` (unit, pointing away from it).
    #[inline]
    pub fn emitted(&self, sp: &SurfacePoint, w: Vec3) -> Vec3 {
        if sp.light == NO_LIGHT {
            return Vec3::ZERO;
        }
        match &self.lights.lights[sp.light as usize] {
            Light::Triangle(l) => l.emitted(w),
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

    fn texture(&self, index: u32, uv: Vec2) -> Vec3 {
        let t = &self.textures[index as usize];
        let wrap = |v: f32, n: u32| -> u32 {
            let v = if t.repeat {
                v - v.floor()
            } else {
                v.clamp(0.0, 1.0)
            };
            ((v * n as f32) as u32).min(n - 1)
        };
        let x = wrap(uv.x, t.width);
        let y = wrap(uv.y, t.height);
        t.texels[(y * t.width + x) as usize]
    }

    /// The BSDF of the material at `sp`.
    #[inline]
    pub fn bsdf(&self, sp: &SurfacePoint) -> Bsdf {
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
            MaterialKind::Dielectric { ior, tint, .. } => Bsdf::single(Lobe::Glass(Glass {
                eta: *ior,
                tint: *tint,
            })),
            MaterialKind::MetallicRoughness {
                base_color,
                base_color_texture,
                metallic,
                roughness,
                transmission,
                ior,
                specular,
            } => {
                let mut base = *base_color;
                if let Some(t) = base_color_texture {
                    base *= self.texture(t.texture, sp.uv);
                }
                gltf_bsdf(&GltfParams {
                    base_color: base,
                    metallic: *metallic,
                    roughness: *roughness,
                    transmission: *transmission,
                    ior: *ior,
                    specular: *specular,
                    ..GltfParams::default()
                })
            }
        }
    }
}
