//! glTF 2.0 import (to be written).
use crate::{Scene, SceneError};
use std::path::Path;

/// Loads a `.gltf` or `.glb` file, choosing the camera named `camera` if given.
pub fn load_path(path: &Path, camera: Option<&str>) -> Result<Scene, SceneError> {
    let _ = camera;
    Err(SceneError::Gltf { file: path.display().to_string(), message: "glTF import is not written yet".into() })
}

/// Loads a glTF document from memory; `base_dir` resolves external buffer/image URIs.
pub fn load_slice(bytes: &[u8], name: &str, base_dir: Option<&Path>, camera: Option<&str>) -> Result<Scene, SceneError> {
    let _ = (bytes, base_dir, camera);
    Err(SceneError::Gltf { file: name.to_string(), message: "glTF import is not written yet".into() })
}
