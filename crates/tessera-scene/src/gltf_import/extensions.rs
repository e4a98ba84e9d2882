//! The glTF extensions Tessera reads: which ones a file may require, the untyped ones
//! (the `gltf` crate has no types for KHR_materials_clearcoat, KHR_materials_sheen,
//! KHR_materials_anisotropy and EXT_mesh_gpu_instancing; they arrive as JSON in its `others` maps), and the warnings for
//! optional extensions that are ignored.

use super::{Importer, Res};
use glam::{DMat4, DQuat, DVec3};
use gltf::json;
use serde::Deserialize;
use serde_json::{Map, Value};

/// Every extension whose meaning Tessera renders (or, for the ones marked, reads and
/// deliberately ignores because a path tracer computes what they approximate). A file may
/// list these in `extensionsRequired`.
pub const SUPPORTED_EXTENSIONS: &[&str] = &[
    "KHR_lights_punctual",
    "KHR_materials_anisotropy",
    "KHR_materials_clearcoat",
    "KHR_materials_emissive_strength",
    "KHR_materials_ior",
    "KHR_materials_sheen",
    "KHR_materials_specular",
    "KHR_materials_transmission",
    "KHR_materials_unlit",
    "KHR_materials_volume",
    "KHR_mesh_quantization",
    "KHR_texture_transform",
    "EXT_mesh_gpu_instancing",
];

/// KHR_materials_clearcoat (Khronos extension specification).
#[derive(Deserialize)]
#[serde(rename_all = "camelCase")]
pub(super) struct Clearcoat {
    #[serde(default)]
    pub(super) clearcoat_factor: f32,
    #[serde(default)]
    pub(super) clearcoat_texture: Option<json::texture::Info>,
    #[serde(default)]
    pub(super) clearcoat_roughness_factor: f32,
    #[serde(default)]
    pub(super) clearcoat_roughness_texture: Option<json::texture::Info>,
}

/// KHR_materials_sheen (Khronos extension specification).
#[derive(Deserialize)]
#[serde(rename_all = "camelCase")]
pub(super) struct Sheen {
    #[serde(default)]
    pub(super) sheen_color_factor: [f32; 3],
    #[serde(default)]
    pub(super) sheen_color_texture: Option<json::texture::Info>,
    #[serde(default)]
    pub(super) sheen_roughness_factor: f32,
    #[serde(default)]
    pub(super) sheen_roughness_texture: Option<json::texture::Info>,
}

/// KHR_materials_anisotropy (Khronos extension specification).
#[derive(Deserialize)]
#[serde(rename_all = "camelCase")]
pub(super) struct Anisotropy {
    #[serde(default)]
    pub(super) anisotropy_strength: f32,
    #[serde(default)]
    pub(super) anisotropy_rotation: f32,
    #[serde(default)]
    pub(super) anisotropy_texture: Option<json::texture::Info>,
}

/// EXT_mesh_gpu_instancing: accessors of per-instance TRS.
#[derive(Deserialize)]
struct GpuInstancing {
    attributes: Map<String, Value>,
}

/// Parses the extension object `name` of `others`, if present.
fn typed<T: for<'de> Deserialize<'de>>(
    others: &Map<String, Value>,
    name: &str,
) -> Result<Option<T>, String> {
    match others.get(name) {
        None => Ok(None),
        Some(v) => serde_json::from_value(v.clone())
            .map(Some)
            .map_err(|e| format!("{name} is malformed: {e}")),
    }
}

/// The material's KHR_materials_clearcoat, if present.
pub(super) fn clearcoat(others: &Map<String, Value>) -> Result<Option<Clearcoat>, String> {
    typed(others, "KHR_materials_clearcoat")
}

/// The material's KHR_materials_anisotropy, if present.
pub(super) fn anisotropy(others: &Map<String, Value>) -> Result<Option<Anisotropy>, String> {
    typed(others, "KHR_materials_anisotropy")
}

/// The material's KHR_materials_sheen, if present.
pub(super) fn sheen(others: &Map<String, Value>) -> Result<Option<Sheen>, String> {
    typed(others, "KHR_materials_sheen")
}

impl Importer<'_> {
    /// Refuses a file that requires an extension Tessera does not know (naming them), and
    /// records the unknown optional ones as warnings. The `gltf` crate's own required-
    /// extension check knows fewer extensions than Tessera reads, so the list is cleared
    /// for it once it has been checked here.
    pub(super) fn check_extensions(&mut self) -> Res<()> {
        let unknown: Vec<&String> = self
            .root
            .extensions_required
            .iter()
            .filter(|e| !SUPPORTED_EXTENSIONS.contains(&e.as_str()))
            .collect();
        if !unknown.is_empty() {
            let names: Vec<&str> = unknown.iter().map(|s| s.as_str()).collect();
            return self.err(format!(
                "the file requires {} {}, which Tessera does not support (supported: {})",
                if names.len() == 1 {
                    "the extension"
                } else {
                    "the extensions"
                },
                names.join(", "),
                SUPPORTED_EXTENSIONS.join(", ")
            ));
        }
        for e in &self.root.extensions_used {
            if !SUPPORTED_EXTENSIONS.contains(&e.as_str()) {
                self.warnings.push(format!(
                    "glTF extension {e} is not supported and is ignored"
                ));
            }
        }
        self.root.extensions_required.clear();
        Ok(())
    }

    /// The per-instance transforms of node `ni`'s EXT_mesh_gpu_instancing (each
    /// `T * R * S`, spec of the extension), or `None` without the extension.
    pub(super) fn gpu_instances(&self, ni: usize) -> Res<Option<Vec<DMat4>>> {
        let node = &self.root.nodes[ni];
        let Some(ext) = node.extensions.as_ref() else {
            return Ok(None);
        };
        let inst: Option<GpuInstancing> = typed(&ext.others, "EXT_mesh_gpu_instancing")
            .map_err(|e| self.gerr(format!("node {ni}: {e}")))?;
        let Some(inst) = inst else {
            return Ok(None);
        };
        let what = format!("node {ni} EXT_mesh_gpu_instancing");
        let accessor = |key: &str| -> Res<Option<usize>> {
            match inst.attributes.get(key) {
                None => Ok(None),
                Some(v) => match v.as_u64() {
                    Some(a) if (a as usize) < self.root.accessors.len() => Ok(Some(a as usize)),
                    _ => self.err(format!("{what}: {key} is not a valid accessor index: {v}")),
                },
            }
        };
        let t = match accessor("TRANSLATION")? {
            Some(a) => Some(self.read_floats::<3>(a, &format!("{what} TRANSLATION"))?),
            None => None,
        };
        let r = match accessor("ROTATION")? {
            Some(a) => Some(self.read_floats::<4>(a, &format!("{what} ROTATION"))?),
            None => None,
        };
        let s = match accessor("SCALE")? {
            Some(a) => Some(self.read_floats::<3>(a, &format!("{what} SCALE"))?),
            None => None,
        };
        let counts: Vec<usize> = [
            t.as_ref().map(Vec::len),
            r.as_ref().map(Vec::len),
            s.as_ref().map(Vec::len),
        ]
        .into_iter()
        .flatten()
        .collect();
        let Some(&n) = counts.first() else {
            return self.err(format!("{what} has no TRANSLATION, ROTATION or SCALE"));
        };
        if counts.iter().any(|&c| c != n) {
            return self.err(format!(
                "{what}: the attributes have different counts {counts:?}"
            ));
        }
        let mut out = Vec::with_capacity(n);
        for i in 0..n {
            let tt = t.as_ref().map_or([0.0; 3], |v| v[i]);
            let rr = r.as_ref().map_or([0.0, 0.0, 0.0, 1.0], |v| v[i]);
            let ss = s.as_ref().map_or([1.0; 3], |v| v[i]);
            let q = DQuat::from_xyzw(rr[0].into(), rr[1].into(), rr[2].into(), rr[3].into());
            let len = q.length();
            if !(len.is_finite() && len > 1e-6) || tt.iter().chain(&ss).any(|v| !v.is_finite()) {
                return self.err(format!("{what}: instance {i} has an invalid transform"));
            }
            out.push(DMat4::from_scale_rotation_translation(
                DVec3::from(ss.map(f64::from)),
                q / len,
                DVec3::from(tt.map(f64::from)),
            ));
        }
        Ok(Some(out))
    }
}
