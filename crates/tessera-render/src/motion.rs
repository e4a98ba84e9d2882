//! Motion blur: what moves while the shutter is open, and where it is at each time.
//!
//! A frame with a shutter is given as the scene at its own time (the *base*: everything
//! that does not move, every light and all shading data come from it) and the scene at
//! `K + 1` *key times* spread evenly over the shutter, `τ_i = i / K` of the way from its
//! opening to its closing. [`MotionSplit::new`] compares them:
//!
//! - a world-space mesh whose vertex positions differ at some key *moves*; so does an
//!   instance whose transform or prototype differs. Their triangles leave the static BVHs
//!   and become [`MotionTriangles`] (moving instances are flattened to world space per
//!   key), with their shading normals and tangents known at every key;
//! - a camera that differs at some key moves: [`CameraKeys`] interpolates it;
//! - when nothing moves, there is no motion: the frame renders exactly as without a
//!   shutter (no time is drawn, so every sample is the same);
//! - what cannot blur is said in [`MotionSplit::warnings`]: emitting meshes and punctual
//!   lights stay where they are at the frame's time (light sampling would otherwise need
//!   a time-dependent light list), and a scene whose structure changes within the shutter
//!   (a mesh appearing, a winding flipping under a mirroring scale) renders unblurred.
//!
//! Every camera sample then draws a time τ from its own sampler dimension
//! (`integrator::render_camera_samples`), and the whole path (camera, every ray, every
//! shadow ray) sees the scene at that τ: the estimate is the time average of the image
//! over the shutter, as a box shutter defines it (Cook, Porter & Carpenter 1984,
//! "Distributed Ray Tracing", section "Motion blur").

use crate::camera::CameraModel;
use crate::geometry::{shutter_segment, MotionTriangles, TriangleRecord, NO_LIGHT};
use glam::{Affine3A, Mat3A, Mat4, Quat, Vec3, Vec3A, Vec4};
use tessera_scene::{Camera, Scene};

/// The shading data of moving triangles at the key times, beside
/// [`MotionTriangles`]' positions.
pub struct MotionShading {
    /// `K + 1`: keys per record.
    keys: usize,
    /// Per record and key: unit world-space vertex normals (zero when the mesh has none).
    normals: Vec<[Vec3; 3]>,
    /// Per record: whether it has vertex normals.
    has_normals: Vec<bool>,
    /// Per record and key: world-space tangents with the bitangent sign (zero when none).
    tangents: Vec<[Vec4; 3]>,
    /// Per record: whether it has tangents.
    has_tangents: Vec<bool>,
    /// Per record: the geometric normal `(p1 - p0) x (p2 - p0)` points to the back (a
    /// flattened instance under a mirroring transform keeps its object-space winding).
    flip: Vec<bool>,
}

impl MotionShading {
    /// Record `r`'s vertex normals at segment `s`, fraction `u`, if it has normals.
    #[inline]
    pub fn normals_at(&self, r: usize, s: usize, u: f32) -> Option<[Vec3; 3]> {
        if !self.has_normals[r] {
            return None;
        }
        let (a, b) = (
            &self.normals[r * self.keys + s],
            &self.normals[r * self.keys + s + 1],
        );
        Some([0, 1, 2].map(|k| a[k].lerp(b[k], u)))
    }

    /// Record `r`'s corner tangents at segment `s`, fraction `u`, if it has tangents.
    #[inline]
    pub fn tangents_at(&self, r: usize, s: usize, u: f32) -> Option<[Vec4; 3]> {
        if !self.has_tangents[r] {
            return None;
        }
        let (a, b) = (
            &self.tangents[r * self.keys + s],
            &self.tangents[r * self.keys + s + 1],
        );
        Some([0, 1, 2].map(|k| a[k].lerp(b[k], u)))
    }

    /// Whether record `r`'s geometric normal must be negated.
    #[inline]
    pub fn flipped(&self, r: usize) -> bool {
        self.flip[r]
    }

    /// Bytes of the key data.
    pub fn bytes(&self) -> usize {
        std::mem::size_of_val(self.normals.as_slice())
            + std::mem::size_of_val(self.tangents.as_slice())
            + self.has_normals.len()
            + self.has_tangents.len()
            + self.flip.len()
    }
}

/// The camera at the key times, interpolated in between: position and scale linearly,
/// orientation by quaternion slerp, field of view and lens linearly.
pub struct CameraKeys {
    keys: Vec<Camera>,
    /// Each key's `world_from_camera` as (scale, rotation, translation), decomposed once.
    poses: Vec<(Vec3, Quat, Vec3)>,
    width: u32,
    height: u32,
}

impl CameraKeys {
    /// The cameras `keys` (at least 2) of a `width` x `height` image.
    fn new(keys: Vec<Camera>, width: u32, height: u32) -> Self {
        let poses = keys
            .iter()
            .map(|k| k.world_from_camera.to_scale_rotation_translation())
            .collect();
        Self {
            keys,
            poses,
            width,
            height,
        }
    }

    /// The camera model at shutter fraction `time`.
    pub fn at(&self, time: f32) -> CameraModel {
        let (s, u) = shutter_segment(time, self.keys.len() as u32 - 1);
        let (a, b) = (&self.keys[s], &self.keys[s + 1]);
        let ((sa, ra, ta), (sb, rb, tb)) = (self.poses[s], self.poses[s + 1]);
        let lerp = |x: f32, y: f32| x + (y - x) * u;
        let cam = Camera {
            name: None,
            world_from_camera: Mat4::from_scale_rotation_translation(
                sa.lerp(sb, u),
                slerp_short(ra, rb, u),
                ta.lerp(tb, u),
            ),
            yfov: lerp(a.yfov, b.yfov),
            aspect_ratio: a.aspect_ratio,
            aperture_radius: lerp(a.aperture_radius, b.aperture_radius),
            focus_distance: lerp(a.focus_distance, b.focus_distance),
        };
        CameraModel::new(&cam, self.width, self.height)
    }
}

/// Slerp along the shorter arc (q and -q are the same rotation).
fn slerp_short(a: Quat, b: Quat, u: f32) -> Quat {
    let b = if a.dot(b) < 0.0 { -b } else { b };
    a.slerp(b, u).normalize()
}

/// What moves within the shutter, split off the base scene (see the module docs).
pub struct MotionSplit {
    /// Per base mesh: its triangles move.
    pub moving_meshes: Vec<bool>,
    /// Per base instance: it moves (and is flattened into the moving triangles).
    pub moving_instances: Vec<bool>,
    /// The moving triangles, when any.
    pub triangles: Option<(MotionTriangles, MotionShading)>,
    /// The camera's keys, when it moves.
    pub camera: Option<CameraKeys>,
    /// What does not blur, for the render plan and the log.
    pub warnings: Vec<String>,
}

impl MotionSplit {
    /// No motion: everything renders from the base scene.
    fn none(base: &Scene, warnings: Vec<String>) -> Self {
        Self {
            moving_meshes: vec![false; base.meshes.len()],
            moving_instances: vec![false; base.instances.len()],
            triangles: None,
            camera: None,
            warnings,
        }
    }

    /// Whether anything moves, so that camera samples draw a time.
    pub fn has_motion(&self) -> bool {
        self.triangles.is_some() || self.camera.is_some()
    }

    /// Compares `base` with the scene at the key times `keys` (empty, or at least 2) and
    /// splits off what moves. `first_prototype` is the shading index of the base's first
    /// prototype (its meshes come first).
    pub fn new(base: &Scene, keys: &[Scene], width: u32, height: u32) -> Self {
        if keys.len() < 2 {
            return Self::none(base, Vec::new());
        }
        if let Some(why) = keys.iter().find_map(|k| structure_differs(base, k)) {
            return Self::none(
                base,
                vec![format!(
                    "motion blur: the scene's structure changes within the shutter ({why}); \
                     the frame renders without blur at its own time"
                )],
            );
        }
        let mut warnings = Vec::new();
        let moving_meshes: Vec<bool> = (0..base.meshes.len())
            .map(|m| {
                keys.iter()
                    .any(|k| k.meshes[m].positions != base.meshes[m].positions)
            })
            .collect();
        let emissive_moving: Vec<bool> = moving_meshes
            .iter()
            .enumerate()
            .map(|(m, &mv)| mv && base.materials[base.meshes[m].material as usize].is_emissive())
            .collect();
        let moving_meshes: Vec<bool> = moving_meshes
            .iter()
            .zip(&emissive_moving)
            .map(|(&m, &e)| m && !e)
            .collect();
        if let Some(m) = emissive_moving.iter().position(|&e| e) {
            warnings.push(format!(
                "motion blur: emitting mesh '{}' moves within the shutter but is rendered \
                 where it is at the frame's time (moving lights do not blur)",
                base.meshes[m].name
            ));
        }
        if keys.iter().any(|k| k.lights != base.lights) {
            warnings.push(
                "motion blur: punctual lights move within the shutter but are rendered \
                 where they are at the frame's time (moving lights do not blur)"
                    .into(),
            );
        }
        let moving_prototypes: Vec<bool> = (0..base.prototypes.len())
            .map(|p| {
                keys.iter()
                    .any(|k| k.prototypes[p].positions != base.prototypes[p].positions)
            })
            .collect();
        let moving_instances: Vec<bool> = (0..base.instances.len())
            .map(|i| {
                let inst = &base.instances[i];
                moving_prototypes[inst.prototype as usize]
                    || keys.iter().any(|k| k.instances[i] != *inst)
            })
            .collect();
        let camera_moves = keys.iter().any(|k| k.camera != base.camera);
        let triangles = moving_triangles(base, keys, &moving_meshes, &moving_instances);
        Self {
            moving_meshes,
            moving_instances,
            triangles,
            camera: camera_moves.then(|| {
                CameraKeys::new(
                    keys.iter().map(|k| k.camera.clone()).collect(),
                    width,
                    height,
                )
            }),
            warnings,
        }
    }
}

/// Why `key` cannot be matched triangle for triangle with `base`, if it cannot.
fn structure_differs(base: &Scene, key: &Scene) -> Option<String> {
    if key.meshes.len() != base.meshes.len()
        || key.prototypes.len() != base.prototypes.len()
        || key.instances.len() != base.instances.len()
    {
        return Some("the number of meshes or instances differs".into());
    }
    let same = |a: &tessera_scene::Mesh, b: &tessera_scene::Mesh| {
        a.indices == b.indices
            && a.positions.len() == b.positions.len()
            && a.material == b.material
            && a.normals.is_some() == b.normals.is_some()
            && a.tangents.is_some() == b.tangents.is_some()
    };
    for (a, b) in base.meshes.iter().zip(&key.meshes) {
        if !same(a, b) {
            return Some(format!("mesh '{}' changes its triangles", a.name));
        }
    }
    for (a, b) in base.prototypes.iter().zip(&key.prototypes) {
        if !same(a, b) {
            return Some(format!("mesh '{}' changes its triangles", a.name));
        }
    }
    for (a, b) in base.instances.iter().zip(&key.instances) {
        if a.prototype != b.prototype
            || (a.world_from_object.matrix3.determinant() < 0.0)
                != (b.world_from_object.matrix3.determinant() < 0.0)
        {
            return Some("an instance changes its mesh or its handedness".into());
        }
    }
    None
}

/// The moving triangles with their key positions and shading: moving world-space meshes
/// as they are, moving instances flattened to world space at every key.
fn moving_triangles(
    base: &Scene,
    keys: &[Scene],
    moving_meshes: &[bool],
    moving_instances: &[bool],
) -> Option<(MotionTriangles, MotionShading)> {
    let n = keys.len();
    let mut records = Vec::new();
    let mut positions: Vec<[Vec3; 3]> = Vec::new();
    let mut shading = MotionShading {
        keys: n,
        normals: Vec::new(),
        has_normals: Vec::new(),
        tangents: Vec::new(),
        has_tangents: Vec::new(),
        flip: Vec::new(),
    };
    for (mi, mesh) in base.meshes.iter().enumerate() {
        if !moving_meshes[mi] {
            continue;
        }
        for (ti, idx) in mesh.indices.iter().enumerate() {
            records.push(TriangleRecord {
                p: idx.map(|i| keys[0].meshes[mi].positions[i as usize]),
                mesh: mi as u32,
                index: ti as u32,
                material: mesh.material,
                light: NO_LIGHT,
            });
            for k in keys {
                let m = &k.meshes[mi];
                positions.push(idx.map(|i| m.positions[i as usize]));
                shading.normals.push(match &m.normals {
                    Some(nr) => idx.map(|i| nr[i as usize]),
                    None => [Vec3::ZERO; 3],
                });
                shading.tangents.push(match &m.tangents {
                    Some(t) => t[ti],
                    None => [Vec4::ZERO; 3],
                });
            }
            shading.has_normals.push(mesh.normals.is_some());
            shading.has_tangents.push(mesh.tangents.is_some());
            shading.flip.push(false);
        }
    }
    let first_prototype = base.meshes.len() as u32;
    for (ii, inst) in base.instances.iter().enumerate() {
        if !moving_instances[ii] {
            continue;
        }
        let pi = inst.prototype as usize;
        let proto = &base.prototypes[pi];
        let mirrored = inst.world_from_object.matrix3.determinant() < 0.0;
        // Per key: the instance's normal transform, inverted once, not once per triangle.
        let normal_to_world: Vec<Mat3A> = keys
            .iter()
            .map(|k| normal_matrix(&k.instances[ii].world_from_object))
            .collect();
        for (ti, idx) in proto.indices.iter().enumerate() {
            records.push(TriangleRecord {
                p: [Vec3::ZERO; 3],
                mesh: first_prototype + pi as u32,
                index: ti as u32,
                material: proto.material,
                light: NO_LIGHT,
            });
            for (k, normal_to_world) in keys.iter().zip(&normal_to_world) {
                let m = k.instances[ii].world_from_object;
                let p = &k.prototypes[pi];
                positions.push(idx.map(|i| m.transform_point3(p.positions[i as usize])));
                shading.normals.push(match &p.normals {
                    Some(nr) => idx.map(|i| {
                        Vec3::from(*normal_to_world * Vec3A::from(nr[i as usize]))
                            .normalize_or_zero()
                    }),
                    None => [Vec3::ZERO; 3],
                });
                let sign = if mirrored { -1.0 } else { 1.0 };
                shading.tangents.push(match &p.tangents {
                    Some(t) => t[ti].map(|c| {
                        m.transform_vector3(c.truncate()).extend(if c.w < 0.0 {
                            -sign
                        } else {
                            sign
                        })
                    }),
                    None => [Vec4::ZERO; 3],
                });
            }
            let r = records.len() - 1;
            records[r].p = positions[r * n];
            shading.has_normals.push(proto.normals.is_some());
            shading.has_tangents.push(proto.tangents.is_some());
            shading.flip.push(mirrored);
        }
    }
    if records.is_empty() {
        return None;
    }
    Some((
        MotionTriangles::new(records, positions, n as u32 - 1),
        shading,
    ))
}

/// The inverse transpose of `m`'s linear part (normals to world space), in double
/// precision as the static instances compute it.
fn normal_matrix(m: &Affine3A) -> Mat3A {
    let inverse = m.as_daffine3().inverse();
    Mat3A::from(inverse.matrix3.transpose().as_mat3())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_moving_camera_is_interpolated_between_its_keys() {
        // Three keys: at the origin looking down -Z, then 2 units along +X turned 90°
        // about +Y, then 4 units along +X turned 180°.
        let key = |x: f32, turn: f32| Camera {
            name: None,
            world_from_camera: Mat4::from_rotation_translation(
                Quat::from_rotation_y(turn),
                Vec3::new(x, 0.0, 0.0),
            ),
            yfov: 0.8,
            aspect_ratio: None,
            aperture_radius: 0.0,
            focus_distance: 1.0,
        };
        let keys = CameraKeys::new(
            vec![
                key(0.0, 0.0),
                key(2.0, std::f32::consts::FRAC_PI_2),
                key(4.0, std::f32::consts::PI),
            ],
            8,
            8,
        );
        // The ray through the image centre: from the interpolated position, along the
        // slerped optical axis (-Z turned by the interpolated angle about +Y).
        for (time, x, turn) in [
            (0.0f32, 0.0f32, 0.0f32),
            (0.25, 1.0, std::f32::consts::FRAC_PI_4),
            (0.5, 2.0, std::f32::consts::FRAC_PI_2),
            (1.0, 4.0, std::f32::consts::PI),
        ] {
            let (o, d) = keys
                .at(time)
                .generate_ray(glam::Vec2::new(4.0, 4.0), glam::Vec2::ZERO);
            let want = Quat::from_rotation_y(turn) * Vec3::NEG_Z;
            assert!(
                (o - Vec3::new(x, 0.0, 0.0)).length() < 1e-5,
                "origin {o} at {time}"
            );
            assert!(
                (d - want).length() < 1e-5,
                "direction {d} at {time}, want {want}"
            );
        }
    }
}
