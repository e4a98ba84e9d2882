//! Step 5a, deformation (spec "Meshes > Morph Targets" and "Skins"): a primitive whose
//! mesh has morph targets, or whose node has a skin, is evaluated at the scene's time into
//! new vertex positions (and normals and tangents) once, when the scene is built, before
//! it is placed; the renderer then sees ordinary triangles and its BVH is built over them.
//! Such a primitive is always flattened (never instanced): its shape depends on its node.
//!
//! - **Morph targets** first (spec "Morph Targets": the morphed position is
//!   `POSITION + sum_k w_k * target_k.POSITION`, and the same for `NORMAL`). The weights
//!   are the node's animated `weights` at the scene's time, else the node's `weights`,
//!   else the mesh's `weights`, else zero; their count must equal the number of targets.
//!   `TANGENT` deltas are not applied (tangents are kept as read).
//! - **Skin** then (spec "Skins", linear blend skinning): with joint matrices
//!   `J_j = globalTransform(joint_j) * inverseBindMatrix_j`, a vertex with joints `j_i`
//!   and weights `w_i` (every `JOINTS_n`/`WEIGHTS_n` set, the weights normalized to sum
//!   to 1) moves to `sum_i w_i J_{j_i} p`. That is world space: the skinned mesh's own
//!   node transform does not place it (spec "Skins": only the joint transforms are
//!   applied; it is the brief's `inverse(meshGlobal) * jointGlobal * inverseBindMatrix`
//!   followed by the mesh node's global transform, which cancel). Normals move with the
//!   inverse transpose of the blended matrix, tangents with the blended matrix.
//!   A blended matrix with a negative determinant mirrors: as for a mirroring node
//!   transform (spec "Meshes > Overview"), a triangle most of whose vertices are
//!   mirrored is re-wound (its corners' tangents with it, their bitangent signs
//!   flipped), so triangles stay counter-clockwise seen from the front.
//!
//! Bad input is an error naming the node, mesh, primitive and field: a skin index or
//! joint node past the end or not in the scene, an inverse-bind-matrix accessor with fewer
//! elements than joints, JOINTS or WEIGHTS with another element count than POSITION, a
//! joint index past the skin's joints, a negative weight or a vertex whose weights sum to
//! zero, morph-target accessors of the wrong count, non-finite weights (accessors are
//! read with the importer's checks: counts bounded by the input size, values finite).

use super::meshes::{prim_name, LocalPrimitive};
use super::{Importer, Res};
use glam::{DMat3, DMat4, DVec3, Vec3};
use gltf::json;
use json::accessor::{ComponentType, GenericComponentType};
use json::validation::Checked;

impl Importer<'_> {
    /// Whether primitive `pi` of mesh `mi` placed at node `ni` deforms: the node has a
    /// skin, or the primitive has morph targets.
    pub(super) fn deforms(&self, ni: usize, mi: usize, pi: usize) -> bool {
        self.root.nodes[ni].skin.is_some()
            || self.root.meshes[mi].primitives[pi]
                .targets
                .as_ref()
                .is_some_and(|t| !t.is_empty())
    }

    /// Primitive `pi` of mesh `mi` at node `ni` (placed by `world`), morphed and skinned
    /// at the scene's time, with the transform that places the result: `world` for a
    /// mesh with morph targets alone, the identity for a skinned one (already in world
    /// space).
    pub(super) fn deform(
        &self,
        ni: usize,
        mi: usize,
        pi: usize,
        local: &LocalPrimitive,
        world: &DMat4,
    ) -> Res<(LocalPrimitive, DMat4)> {
        let mesh = &self.root.meshes[mi];
        let what = format!("node {ni} {}", prim_name(mi, mesh, pi));
        let mut out = local.clone();
        self.morph(ni, mi, pi, &what, &mut out)?;
        match self.root.nodes[ni].skin {
            Some(si) => {
                self.skin(si.value(), mi, pi, &what, &mut out)?;
                Ok((out, DMat4::IDENTITY))
            }
            None => Ok((out, *world)),
        }
    }

    /// Applies the morph targets of the primitive with the node's weights.
    fn morph(
        &self,
        ni: usize,
        mi: usize,
        pi: usize,
        what: &str,
        out: &mut LocalPrimitive,
    ) -> Res<()> {
        let mesh = &self.root.meshes[mi];
        let Some(targets) = mesh.primitives[pi]
            .targets
            .as_ref()
            .filter(|t| !t.is_empty())
        else {
            return Ok(());
        };
        let node = &self.root.nodes[ni];
        let (weights, source): (Vec<f32>, &str) = if let Some(w) = self.pose.weights.get(&ni) {
            (w.clone(), "the animated weights")
        } else if let Some(w) = &node.weights {
            (w.clone(), "node weights")
        } else if let Some(w) = &mesh.weights {
            (w.clone(), "mesh weights")
        } else {
            (vec![0.0; targets.len()], "")
        };
        if weights.len() != targets.len() {
            return self.err(format!(
                "{what}: {source} has {} values but the primitive has {} morph targets",
                weights.len(),
                targets.len()
            ));
        }
        if let Some(k) = weights.iter().position(|w| !w.is_finite()) {
            return self.err(format!(
                "{what}: {source} value {k} is not finite: {}",
                weights[k]
            ));
        }
        let n = out.positions.len();
        for (k, (target, &w)) in targets.iter().zip(&weights).enumerate() {
            if w == 0.0 {
                continue;
            }
            if let Some(a) = target.positions {
                let d = self.read_floats::<3>(a.value(), &format!("{what} target {k} POSITION"))?;
                self.check_count(d.len(), n, &format!("{what}: target {k} POSITION"))?;
                for (p, d) in out.positions.iter_mut().zip(&d) {
                    *p += w * Vec3::from(*d);
                }
            }
            if let (Some(a), Some(normals)) = (target.normals, out.normals.as_mut()) {
                let d = self.read_floats::<3>(a.value(), &format!("{what} target {k} NORMAL"))?;
                if d.len() != n {
                    return self.err(format!(
                        "{what}: target {k} NORMAL has {} elements but POSITION has {n}",
                        d.len()
                    ));
                }
                for (p, d) in normals.iter_mut().zip(&d) {
                    *p += w * Vec3::from(*d);
                }
            }
        }
        Ok(())
    }

    /// An error unless an attribute has the `n` elements of POSITION.
    fn check_count(&self, got: usize, n: usize, what: &str) -> Res<()> {
        if got != n {
            return self.err(format!("{what} has {got} elements but POSITION has {n}"));
        }
        Ok(())
    }

    /// Skins the primitive with skin `si` (linear blend skinning into world space): the
    /// joints' matrices, every vertex's influences, then the blend.
    fn skin(
        &self,
        si: usize,
        mi: usize,
        pi: usize,
        what: &str,
        out: &mut LocalPrimitive,
    ) -> Res<()> {
        let joints = self.skin_joints(si, what)?;
        let n = out.positions.len();
        let influences = self.skin_influences(si, mi, pi, what, n, joints.len())?;
        self.blend_skin(&joints, &influences, what, out)
    }

    /// The skinning matrices of skin `si`'s joints: each joint's world transform times its
    /// inverse bind matrix (identity when the skin has none).
    fn skin_joints(&self, si: usize, what: &str) -> Res<Vec<DMat4>> {
        let Some(skin) = self.root.skins.get(si) else {
            return self.err(format!(
                "{what}: skin {si} is past the end ({} skins)",
                self.root.skins.len()
            ));
        };
        let swhat = format!("skin {si}");
        if skin.joints.is_empty() {
            return self.err(format!("{swhat} has no joints"));
        }
        let ibm: Option<Vec<[f32; 16]>> = match skin.inverse_bind_matrices {
            Some(a) => {
                let m =
                    self.read_floats::<16>(a.value(), &format!("{swhat} inverseBindMatrices"))?;
                if m.len() < skin.joints.len() {
                    return self.err(format!(
                        "{swhat}: inverseBindMatrices has {} elements for {} joints",
                        m.len(),
                        skin.joints.len()
                    ));
                }
                Some(m)
            }
            None => None,
        };
        let mut joints = Vec::with_capacity(skin.joints.len());
        for (k, j) in skin.joints.iter().enumerate() {
            let jn = j.value();
            let Some(Some(global)) = self.node_world.get(jn) else {
                return self.err(format!(
                    "{swhat} joint {k}: node {jn} is not in the scene (joints must be nodes \
                     of the rendered scene)"
                ));
            };
            let inverse_bind = ibm.as_ref().map_or(DMat4::IDENTITY, |m| {
                DMat4::from_cols_array(&m[k].map(f64::from))
            });
            joints.push(*global * inverse_bind);
        }
        Ok(joints)
    }

    /// Every JOINTS_n / WEIGHTS_n set of primitive `pi` of mesh `mi`, as (joints, weights)
    /// per set and vertex (set-major: `n` vertices per set), checked against the skin's
    /// `joint_count` joints.
    fn skin_influences(
        &self,
        si: usize,
        mi: usize,
        pi: usize,
        what: &str,
        n: usize,
        joint_count: usize,
    ) -> Res<Vec<([u32; 4], [f32; 4])>> {
        let prim = &self.root.meshes[mi].primitives[pi];
        let attribute = |s: json::mesh::Semantic| prim.attributes.get(&Checked::Valid(s)).copied();
        let mut influences: Vec<([u32; 4], [f32; 4])> = Vec::new();
        for set in 0.. {
            let (j, w) = (
                attribute(json::mesh::Semantic::Joints(set)),
                attribute(json::mesh::Semantic::Weights(set)),
            );
            let (j, w) = match (j, w) {
                (None, None) => break,
                (Some(j), Some(w)) => (j.value(), w.value()),
                _ => {
                    return self.err(format!(
                        "{what}: JOINTS_{set} and WEIGHTS_{set} must come together"
                    ))
                }
            };
            let integer = matches!(
                self.root.accessors.get(j).map(|a| a.component_type),
                Some(Checked::Valid(GenericComponentType(
                    ComponentType::U8 | ComponentType::U16
                )))
            ) && !self.root.accessors[j].normalized;
            if !integer {
                return self.err(format!(
                    "{what}: JOINTS_{set} (accessor {j}) must be unsigned byte or short integers"
                ));
            }
            let jv = self.read_floats::<4>(j, &format!("{what} JOINTS_{set}"))?;
            let wv = self.read_floats::<4>(w, &format!("{what} WEIGHTS_{set}"))?;
            self.check_count(jv.len(), n, &format!("{what}: JOINTS_{set}"))?;
            self.check_count(wv.len(), n, &format!("{what}: WEIGHTS_{set}"))?;
            for (v, (jj, ww)) in jv.iter().zip(&wv).enumerate() {
                for c in 0..4 {
                    if ww[c] < 0.0 {
                        return self.err(format!(
                            "{what}: WEIGHTS_{set} vertex {v} has a negative weight {}",
                            ww[c]
                        ));
                    }
                    if ww[c] > 0.0 && jj[c] as usize >= joint_count {
                        return self.err(format!(
                            "{what}: JOINTS_{set} vertex {v} names joint {} of skin {si}, \
                             which has {} joints",
                            jj[c], joint_count
                        ));
                    }
                }
                influences.push((jj.map(|x| x as u32), *ww));
            }
        }
        if influences.is_empty() {
            return self.err(format!("{what}: has a skin but no JOINTS_0/WEIGHTS_0"));
        }
        Ok(influences)
    }

    /// Blends every vertex of `out` by its `influences` over the `joints` (weights
    /// normalised to sum to one), transforms normals by the inverse transpose and tangents
    /// by the linear part, and re-winds triangles a mirroring blend turns inside out.
    fn blend_skin(
        &self,
        joints: &[DMat4],
        influences: &[([u32; 4], [f32; 4])],
        what: &str,
        out: &mut LocalPrimitive,
    ) -> Res<()> {
        let n = out.positions.len();
        let sets = influences.len() / n.max(1);
        // Per vertex: the blended matrix, applied to the position, its inverse transpose
        // to the normal; its linear part kept for the per-corner tangents.
        let mut linear: Vec<DMat3> = Vec::with_capacity(n);
        for v in 0..n {
            let mut m = DMat4::ZERO;
            let mut total = 0.0f64;
            for s in 0..sets {
                let (jj, ww) = &influences[s * n + v];
                for c in 0..4 {
                    if ww[c] > 0.0 {
                        let w = f64::from(ww[c]);
                        m += joints[jj[c] as usize] * w;
                        total += w;
                    }
                }
            }
            if !(total > 0.0 && total.is_finite()) {
                return self.err(format!(
                    "{what}: vertex {v}: its skin weights sum to {total}, not a positive number"
                ));
            }
            // Normalized weights (spec "Skins": the weights of a vertex sum to one; an
            // exporter's rounding is corrected here).
            let m = m * (1.0 / total);
            let p = m.transform_point3(out.positions[v].as_dvec3());
            out.positions[v] = p.as_vec3();
            let l = DMat3::from_mat4(m);
            if let Some(normals) = out.normals.as_mut() {
                let nm = l.inverse().transpose();
                let w = nm * normals[v].as_dvec3();
                normals[v] = if w.is_finite() {
                    w.as_vec3()
                } else {
                    DVec3::ZERO.as_vec3()
                };
            }
            linear.push(l);
        }
        if let Some(tangents) = out.tangents.as_mut() {
            for (corners, tri) in tangents.iter_mut().zip(&out.triangles) {
                for (t, &v) in corners.iter_mut().zip(tri) {
                    let d = (linear[v as usize] * t.truncate().as_dvec3()).normalize_or_zero();
                    *t = d.as_vec3().extend(t.w);
                }
            }
        }
        // Mirrored triangles: re-wound, with their tangent corners (whose handedness the
        // mirror flips).
        for (ti, tri) in out.triangles.iter_mut().enumerate() {
            let mirrored = tri
                .iter()
                .filter(|&&v| linear[v as usize].determinant() < 0.0)
                .count();
            if mirrored >= 2 {
                *tri = [tri[0], tri[2], tri[1]];
                if let Some(tangents) = out.tangents.as_mut() {
                    let c = tangents[ti];
                    tangents[ti] = [c[0], c[2], c[1]].map(|t| t.truncate().extend(-t.w));
                }
            }
        }
        Ok(())
    }
}
