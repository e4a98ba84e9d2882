//! Step 2: the geometry survey — which materials the surfaces use, the area each covers,
//! and the extent of the scene. Everything later steps look up is collected here.

use super::classify::{classify, Classes};
use crate::{PunctualLight, Scene};
use glam::Vec3;

/// Axis-aligned bounds, empty until a point is added.
#[derive(Clone, Copy)]
pub(super) struct Bounds {
    pub(super) lo: Vec3,
    pub(super) hi: Vec3,
}

impl Bounds {
    pub(super) fn empty() -> Self {
        Self {
            lo: Vec3::splat(f32::INFINITY),
            hi: Vec3::splat(f32::NEG_INFINITY),
        }
    }
    pub(super) fn add(&mut self, p: Vec3) {
        self.lo = self.lo.min(p);
        self.hi = self.hi.max(p);
    }
    pub(super) fn is_empty(&self) -> bool {
        self.lo.x > self.hi.x
    }
    pub(super) fn radius(&self) -> f32 {
        if self.is_empty() {
            0.0
        } else {
            0.5 * (self.hi - self.lo).length()
        }
    }
    pub(super) fn surface_area(&self) -> f32 {
        if self.is_empty() {
            return 0.0;
        }
        let d = self.hi - self.lo;
        2.0 * (d.x * d.y + d.y * d.z + d.z * d.x)
    }
}

/// Area of a triangle.
pub(super) fn triangle_area(p: [Vec3; 3]) -> f32 {
    0.5 * (p[1] - p[0]).cross(p[2] - p[0]).length()
}

/// The scene with each material's classes, which materials are used, their areas and the
/// extent of the geometry.
pub(super) struct Survey<'a> {
    /// The scene analysed.
    pub(super) scene: &'a Scene,
    /// The classes of each material, by material index.
    pub(super) classes: Vec<Classes>,
    /// Whether a mesh with triangles or a sphere uses each material.
    pub(super) used: Vec<bool>,
    /// Surface area covered by each material.
    pub(super) area_by_material: Vec<f32>,
    /// Bounds of the geometry (empty without geometry).
    pub(super) geometry: Bounds,
    /// Bounding radius of the geometry, or of the camera and the lights without geometry,
    /// and 1 if that is 0.
    pub(super) scene_radius: f32,
}

impl<'a> Survey<'a> {
    /// Classifies the materials and measures the geometry of `scene`.
    pub(super) fn new(scene: &'a Scene) -> Self {
        let classes: Vec<Classes> = scene.materials.iter().map(|m| classify(m, scene)).collect();
        let nmat = scene.materials.len();

        // Which materials are used, and the geometry's extent and areas.
        let mut used = vec![false; nmat];
        let mut area_by_material = vec![0.0f32; nmat];
        let mut geometry = Bounds::empty();
        for placed in scene.placed_meshes() {
            let mi = placed.material() as usize;
            if placed.mesh.indices.is_empty() || mi >= nmat {
                continue;
            }
            used[mi] = true;
            for p in placed.triangles() {
                area_by_material[mi] += triangle_area(p);
                for v in p {
                    geometry.add(v);
                }
            }
        }
        for s in &scene.spheres {
            let mi = s.material as usize;
            if mi >= nmat {
                continue;
            }
            used[mi] = true;
            area_by_material[mi] += 4.0 * std::f32::consts::PI * s.radius * s.radius;
            geometry.add(s.center - Vec3::splat(s.radius));
            geometry.add(s.center + Vec3::splat(s.radius));
        }
        let scene_radius = scene_radius(scene, geometry);
        Self {
            scene,
            classes,
            used,
            area_by_material,
            geometry,
            scene_radius,
        }
    }

    /// Number of materials.
    pub(super) fn nmat(&self) -> usize {
        self.scene.materials.len()
    }

    /// Whether material `mi` exists, is used and scatters light.
    pub(super) fn scatters(&self, mi: usize) -> bool {
        mi < self.nmat() && self.used[mi] && self.classes[mi].scatters()
    }
}

/// Bounding radius of `geometry`, or without geometry of the camera position and the
/// point and spot lights; 1 when that radius is 0.
fn scene_radius(scene: &Scene, geometry: Bounds) -> f32 {
    let mut b = geometry;
    if b.is_empty() {
        b.add(scene.camera.world_from_camera.w_axis.truncate());
        for l in &scene.lights {
            match l {
                PunctualLight::Point { position, .. } | PunctualLight::Spot { position, .. } => {
                    b.add(*position)
                }
                PunctualLight::Directional { .. } => {}
            }
        }
    }
    let r = b.radius();
    if r > 0.0 {
        r
    } else {
        1.0
    }
}
