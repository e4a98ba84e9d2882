//! Uploads of the robustness issue's poison scenes (the minimized crashers committed in
//! `tests/fuzz/corpus/gltf/`) are refused by `POST /scenes` with a 400 naming the problem,
//! at once: a decompression bomb from its PNG header (nothing is decoded), the 1e38 scale
//! from the node's world-space vertices. Nothing is stored.

use std::path::PathBuf;
use tessera_api::ApiError;
use tessera_coordinator::service::{Coordinator, CoordinatorConfig};

fn crasher(name: &str) -> Vec<u8> {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../tests/fuzz/corpus/gltf")
        .join(name);
    std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn poison_scene_uploads_are_refused_naming_the_limit() {
    let dir = tempfile::tempdir().unwrap();
    let core = Coordinator::open(CoordinatorConfig::new(dir.path()))
        .await
        .unwrap();
    let cases = [
        (
            "crasher-bomb-16384x16384.glb",
            &["image 0 'bomb'", "16384x16384", "MAX_IMAGE_TEXELS"][..],
        ),
        (
            "crasher-bomb-32768x8192.glb",
            &["image 0 'bomb'", "32768x8192", "MAX_IMAGE_TEXELS"][..],
        ),
        ("crasher-scale-1e38.glb", &["node 0", "beyond"][..]),
    ];
    for (name, fragments) in cases {
        let e = ApiError::from(core.upload_scene(crasher(name)).await.unwrap_err());
        assert_eq!(e.status(), 400, "{name}: {e:?}");
        for f in fragments {
            assert!(e.message.contains(f), "{name}: {:?} lacks {f:?}", e.message);
        }
    }
}
