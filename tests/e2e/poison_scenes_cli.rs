//! `tessera render` on the robustness issue's poison scenes (the minimized crashers of
//! `tests/fuzz/corpus/gltf/`): each exits with code 1 and an error naming the problem,
//! never with a panic (code 101), and writes no image.

use crate::common;

use common::{temp_dir, tessera};
use std::path::PathBuf;

#[test]
fn poison_scenes_are_errors_not_panics() {
    let corpus = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../tests/fuzz/corpus/gltf");
    let dir = temp_dir("poison", "render");
    let cases = [
        ("crasher-scale-1e38.glb", "node 0"),
        ("crasher-bomb-16384x16384.glb", "MAX_IMAGE_TEXELS"),
        ("crasher-bomb-32768x8192.glb", "MAX_IMAGE_TEXELS"),
    ];
    for (file, names) in cases {
        let out = dir.join(format!("{file}.png"));
        let o = tessera()
            .arg("render")
            .arg(corpus.join(file))
            .args(["--spp", "1", "--width", "8", "--height", "8", "-o"])
            .arg(&out)
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{file}: {stderr}");
        assert!(
            stderr.starts_with("error: loading scene"),
            "{file}: {stderr}"
        );
        assert!(stderr.contains(names), "{file}: {stderr}");
        assert!(!stderr.contains("panicked"), "{file}: {stderr}");
        assert!(!out.exists(), "{file}: an image was written");
    }
    let _ = std::fs::remove_dir_all(&dir);
}
