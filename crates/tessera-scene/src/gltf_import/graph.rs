//! Step 4, the scene graph (spec "Scenes", "Nodes and Hierarchy", "Transformations"):
//! the root nodes, and the depth-first walk that accumulates world transforms and
//! records where meshes, cameras and lights are placed.

use super::camera::CameraCandidate;
use super::{Importer, Res};
use crate::PunctualLight;
use glam::{DMat4, DQuat, DVec3};
use gltf::json;
use json::validation::Checked;

/// A glTF mesh placed at a node (once per EXT_mesh_gpu_instancing instance).
pub(super) struct Placement {
    /// The node placing it.
    pub(super) node: usize,
    /// Which EXT_mesh_gpu_instancing instance of the node this is, if any (for messages).
    pub(super) gpu_instance: Option<usize>,
    /// The glTF mesh index (checked to exist).
    pub(super) mesh: usize,
    /// World-from-mesh transform.
    pub(super) world: DMat4,
}

/// What the walk over the scene graph found, in depth-first order.
#[derive(Default)]
pub(super) struct Instances {
    /// Every placement of a mesh; [`Importer::place_meshes`] decides which are
    /// flattened and which become instances of a stored-once prototype.
    pub(super) placements: Vec<Placement>,
    /// Lights at their nodes.
    pub(super) lights: Vec<PunctualLight>,
    /// Nodes carrying a perspective camera.
    pub(super) cameras: Vec<CameraCandidate>,
}

impl Importer<'_> {
    /// Which nodes to start from (spec "Scenes"): the default scene's, else scene 0's, else
    /// every node that is nobody's child.
    pub(super) fn root_nodes(&self) -> Res<Vec<usize>> {
        Ok(if let Some(s) = self.root.scene {
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
        })
    }

    /// Walks the trees below `roots` and instances what their nodes carry. Every node may
    /// be reached once only.
    pub(super) fn walk(&mut self, roots: &[usize]) -> Res<Instances> {
        let mut found = Instances::default();
        let mut visited = vec![false; self.root.nodes.len()];
        self.node_world = vec![None; self.root.nodes.len()];
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
            self.node_world[ni] = Some(world);
            self.visit_node(ni, &world, &mut found)?;
            if let Some(children) = &self.root.nodes[ni].children {
                for c in children.iter().rev() {
                    stack.push((c.value(), world));
                }
            }
        }
        Ok(found)
    }

    /// Records the mesh placements, perspective camera and light of node `ni` at `world`.
    fn visit_node(&mut self, ni: usize, world: &DMat4, found: &mut Instances) -> Res<()> {
        if let Some(m) = self.root.nodes[ni].mesh {
            let mi = m.value();
            if mi >= self.root.meshes.len() {
                return self.err(format!(
                    "node {ni} refers to mesh {mi}, but there are only {}",
                    self.root.meshes.len()
                ));
            }
            let mut place = |imp: &mut Self, world: DMat4, gpu_instance| -> Res<()> {
                // A placement costs a transform until it is known to be flattened.
                imp.add_output(
                    std::mem::size_of::<Placement>() as u64,
                    &format!("node {ni}"),
                )?;
                found.placements.push(Placement {
                    node: ni,
                    gpu_instance,
                    mesh: mi,
                    world,
                });
                Ok(())
            };
            match self.gpu_instances(ni)? {
                // EXT_mesh_gpu_instancing: the mesh at every instance transform, each
                // applied before the node's own (the extension's `world * instance`).
                Some(instances) => {
                    for (k, inst) in instances.into_iter().enumerate() {
                        let at = *world * inst;
                        if !at.is_finite() {
                            return self.err(format!(
                                "node {ni}: EXT_mesh_gpu_instancing instance {k}: its world \
                                 transform is not finite"
                            ));
                        }
                        place(self, at, Some(k))?;
                    }
                }
                None => place(self, *world, None)?,
            }
        }
        let node = &self.root.nodes[ni];
        if let Some(c) = node.camera {
            let ci = c.value();
            let cam = self.root.cameras.get(ci);
            if cam.is_some_and(|c| c.type_ == Checked::Valid(json::camera::Type::Perspective)) {
                found.cameras.push(CameraCandidate {
                    node: ni,
                    camera: ci,
                    world: *world,
                });
            }
        }
        if let Some(ext) = node
            .extensions
            .as_ref()
            .and_then(|e| e.khr_lights_punctual.as_ref())
        {
            found
                .lights
                .push(self.convert_light(ni, ext.light.value(), world)?);
        }
        Ok(())
    }

    /// The local transform of node `ni` (spec "Transformations": a column-major `matrix`,
    /// or `T * R * S`), with the animated parts of the pose at the scene's time in place
    /// of the node's own (spec "Animations"; the `animation` step refused a matrix on an
    /// animated node). Non-finite values are an error naming the node.
    fn local_transform(&self, ni: usize) -> Res<DMat4> {
        let node = &self.root.nodes[ni];
        let animated = self.pose.trs.get(&ni).copied().unwrap_or_default();
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
        let (s, q, t) = (
            animated.scale.unwrap_or(DVec3::from(s.map(f64::from))),
            animated.rotation.unwrap_or(q / len),
            animated
                .translation
                .unwrap_or(DVec3::from(t.map(f64::from))),
        );
        Ok(DMat4::from_scale_rotation_translation(s, q, t))
    }
}
