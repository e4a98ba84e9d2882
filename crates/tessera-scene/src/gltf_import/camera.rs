//! Step 7, the camera (spec "Cameras"): the perspective camera asked for by name, else
//! the first one found, else one synthesized to frame the geometry; and the default image
//! size it implies.

use super::meshes::Geometry;
use super::{Importer, Res};
use crate::{Camera, PunctualLight};
use glam::{DMat4, DVec3, Vec3};
use gltf::json;
use json::validation::Checked;

/// Image height of [`Scene::default_resolution`](crate::Scene::default_resolution) for imported scenes, in pixels.
const DEFAULT_HEIGHT: u32 = 512;
/// Widest default image an extreme aspect ratio may ask for.
const MAX_DEFAULT_WIDTH: u32 = 16384;

/// A perspective camera found while walking the scene graph.
pub(super) struct CameraCandidate {
    /// The node carrying the camera.
    pub(super) node: usize,
    /// The glTF camera index.
    pub(super) camera: usize,
    /// The node's world transform.
    pub(super) world: DMat4,
}

impl Importer<'_> {
    /// Picks the camera (by name, else the first perspective camera) or synthesizes one.
    pub(super) fn choose_camera(
        &self,
        wanted: Option<&str>,
        candidates: &[CameraCandidate],
        geometry: &Geometry,
        lights: &[PunctualLight],
    ) -> Res<Camera> {
        let chosen = match wanted {
            Some(name) => Some(self.camera_named(name, candidates)?),
            None => candidates.first(),
        };
        match chosen {
            Some(c) => self.convert_camera(c),
            None => Ok(synthesize_camera(geometry, lights)),
        }
    }

    /// The candidate whose camera name or node name is `name`; an error listing the
    /// available cameras if there is none.
    fn camera_named<'c>(
        &self,
        name: &str,
        candidates: &'c [CameraCandidate],
    ) -> Res<&'c CameraCandidate> {
        let node_name = |c: &CameraCandidate| self.root.nodes[c.node].name.as_deref();
        let camera_name = |c: &CameraCandidate| self.root.cameras[c.camera].name.as_deref();
        let found = candidates
            .iter()
            .find(|c| camera_name(c) == Some(name) || node_name(c) == Some(name));
        if let Some(c) = found {
            return Ok(c);
        }
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
        self.err(format!("no camera named {name:?}; {available}"))
    }

    /// The [`Camera`] of candidate `c`: its perspective parameters checked, its node
    /// transform without scale.
    fn convert_camera(&self, c: &CameraCandidate) -> Res<Camera> {
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
fn synthesize_camera(geometry: &Geometry, lights: &[PunctualLight]) -> Camera {
    let mut lo = Vec3::splat(f32::INFINITY);
    let mut hi = Vec3::splat(f32::NEG_INFINITY);
    for (lo_p, hi_p) in geometry.bounds() {
        lo = lo.min(lo_p);
        hi = hi.max(hi_p);
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

/// The default image size for `camera`: [`DEFAULT_HEIGHT`] high, and as wide as the
/// camera's aspect ratio asks (at most [`MAX_DEFAULT_WIDTH`]), else square.
pub(super) fn default_resolution(camera: &Camera) -> (u32, u32) {
    match camera.aspect_ratio {
        Some(a) => {
            let w = (DEFAULT_HEIGHT as f32 * a).round();
            (
                w.clamp(1.0, MAX_DEFAULT_WIDTH as f32) as u32,
                DEFAULT_HEIGHT,
            )
        }
        None => (DEFAULT_HEIGHT, DEFAULT_HEIGHT),
    }
}
