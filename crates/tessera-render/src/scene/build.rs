//! Building a [`RenderScene`]: the BVH over the scene's triangles and instances (and
//! what moves within the shutter), the lights with their selection powers, the per-mesh
//! shading data and the camera.

use super::*;

impl RenderScene {
    /// Builds the BVH, the light list and the camera for a `width` x `height` image.
    pub fn build(scene: &Scene, width: u32, height: u32) -> Result<Self, BuildError> {
        Self::build_in_motion(scene, &[], width, height)
    }

    /// [`RenderScene::build`] with motion blur: `scene` at the frame's time, and `keys`,
    /// the scene at `K + 1` times spread evenly over the shutter (empty for no shutter).
    /// What moves between the keys is traced at each ray's time ([`crate::motion`]);
    /// when nothing moves the result is the same as [`RenderScene::build`]'s.
    pub fn build_in_motion(
        scene: &Scene,
        keys: &[Scene],
        width: u32,
        height: u32,
    ) -> Result<Self, BuildError> {
        if width == 0 || height == 0 {
            return Err(BuildError::ImageSize(width, height));
        }
        let split = MotionSplit::new(scene, keys, width, height);
        let mut lights: Vec<Light> = Vec::new();
        // The world-space triangles are not gathered into an array here: the geometry
        // reads each one from the scene by its index in mesh order (twice: for the BVH's
        // boxes, then in leaf order for the records it keeps), so a large scene is held
        // once as its meshes and once as the geometry, never also as an array of records
        // in scene order (see "Memory" in `geometry::build`). What a record needs beyond
        // the mesh is its light, numbered here in the same order as always.
        let mut starts: Vec<(usize, u32)> = Vec::new();
        let mut count = 0usize;
        let mut mesh_lights: Vec<Option<Vec<u32>>> = vec![None; scene.meshes.len()];
        for (mi, mesh) in scene.meshes.iter().enumerate() {
            if split.moving_meshes[mi] || mesh.indices.is_empty() {
                continue;
            }
            starts.push((count, mi as u32));
            count += mesh.indices.len();
            let mat = &scene.materials[mesh.material as usize];
            if !mat.is_emissive() {
                continue;
            }
            let varies = mat.emissive_texture().is_some() || mat.has_alpha();
            let mut per_triangle = Vec::with_capacity(mesh.indices.len());
            for (ti, idx) in mesh.indices.iter().enumerate() {
                let p = idx.map(|i| mesh.positions[i as usize]);
                let mut light = NO_LIGHT;
                if let Some(mut l) = TriangleLight::new(p, mat.emission, mat.double_sided) {
                    if varies {
                        // Light selection by power: the texture's mean over the
                        // triangle (selection only shapes variance; the emitted
                        // radiance is evaluated exactly where a point is sampled).
                        l.power_scale = mean_emission_scale(scene, mat, mesh, idx);
                        l.shading = Some((mi as u32, ti as u32));
                    }
                    light = lights.len() as u32;
                    lights.push(Light::Triangle(l));
                }
                per_triangle.push(light);
            }
            mesh_lights[mi] = Some(per_triangle);
        }
        let record = |i: usize| {
            let (start, mi) = starts[starts.partition_point(|&(s, _)| s <= i) - 1];
            let mesh = &scene.meshes[mi as usize];
            let ti = i - start;
            TriangleRecord {
                p: mesh.indices[ti].map(|v| mesh.positions[v as usize]),
                mesh: mi,
                index: ti as u32,
                material: mesh.material,
                light: mesh_lights[mi as usize]
                    .as_ref()
                    .map_or(NO_LIGHT, |l| l[ti]),
            }
        };
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
        // Prototypes: object-space triangles, their shading stored after the meshes'.
        // They are never emissive (`Scene::validate`), so they carry no lights.
        let first_prototype = scene.meshes.len() as u32;
        let prototypes: Vec<Vec<TriangleRecord>> = scene
            .prototypes
            .iter()
            .enumerate()
            .map(|(pi, mesh)| {
                (0..mesh.indices.len())
                    .map(|ti| TriangleRecord {
                        p: mesh.indices[ti].map(|i| mesh.positions[i as usize]),
                        mesh: first_prototype + pi as u32,
                        index: ti as u32,
                        material: mesh.material,
                        light: NO_LIGHT,
                    })
                    .collect()
            })
            .collect();
        let instances: Vec<(u32, Affine3A)> = scene
            .instances
            .iter()
            .zip(&split.moving_instances)
            .filter(|(_, &moving)| !moving)
            .map(|(i, _)| (i.prototype, i.world_from_object))
            .collect();
        let mut geometry =
            Geometry::build_instanced_of(count, record, spheres, prototypes, &instances);
        let MotionSplit {
            triangles: moving,
            camera: camera_keys,
            warnings: motion_warnings,
            ..
        } = split;
        let motion_shading = match moving {
            Some((tris, shading)) => {
                geometry = geometry.with_motion(tris);
                Some(shading)
            }
            None => None,
        };
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
            let mut env = Environment::uniform(radiance, geometry.bounds_radius);
            env.image = scene
                .environment_map
                .as_ref()
                .map(|m| std::sync::Arc::new(EnvImage::new(m)));
            lights.push(Light::Environment(env));
        }
        let meshes = scene
            .meshes
            .iter()
            .chain(&scene.prototypes)
            .map(|m| MeshShading {
                indices: m.indices.clone(),
                normals: m.normals.clone(),
                uvs: m.uvs.clone(),
                colors: m.colors.clone(),
                tangents: m.tangents.clone(),
                material: m.material,
            })
            .collect();
        let alpha_tested: Vec<bool> = scene.materials.iter().map(Material::has_alpha).collect();
        let uses_tangents = scene
            .materials
            .iter()
            .map(|m| {
                m.as_gltf().is_some_and(|g| {
                    g.normal_map.is_some() || g.anisotropy.is_some_and(|a| a.strength > 0.0)
                })
            })
            .collect();
        let mut render = Self {
            geometry,
            meshes,
            materials: scene.materials.clone(),
            textures: scene.textures.clone(),
            images: scene.images.clone(),
            any_alpha: alpha_tested.iter().any(|&a| a),
            alpha_tested,
            uses_tangents,
            constant_gltf: Vec::new(),
            lights: LightSet::new(lights),
            camera: CameraModel::new(&scene.camera, width, height),
            width,
            height,
            motion_shading,
            camera_keys,
            motion_warnings,
        };
        render.constant_gltf = render
            .materials
            .iter()
            .map(|m| m.as_gltf().and_then(|g| render.constant_gltf_lobe(g)))
            .collect();
        Ok(render)
    }
}

/// The mean of a varying triangle light's [`RenderScene::emission_scale`] over the
/// triangle, from a fixed 8 x 8 stratified set of points (for light selection by power).
fn mean_emission_scale(
    scene: &Scene,
    mat: &Material,
    mesh: &tessera_scene::Mesh,
    idx: &[u32; 3],
) -> Vec3 {
    let mut sum = Vec3::ZERO;
    const N: u32 = 8;
    for i in 0..N {
        for j in 0..N {
            let u = Vec2::new((i as f32 + 0.5) / N as f32, (j as f32 + 0.5) / N as f32);
            let (b0, b1) = crate::sampling::warp::square_to_uniform_triangle(u);
            let bary = Vec2::new(b1, 1.0 - b0 - b1);
            let vertex = (mesh.uvs.as_slice(), mesh.colors.as_deref());
            sum += emission_variation(&scene.textures, &scene.images, mat, vertex, *idx, bary);
        }
    }
    sum / (N * N) as f32
}
