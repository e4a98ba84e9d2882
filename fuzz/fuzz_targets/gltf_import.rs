//! glTF/GLB import under libFuzzer (docs/fuzzing.md, "glTF/GLB import"): any bytes, as
//! `.glb` or `.gltf` JSON, must import to `Ok` (a scene that validates) or `Err`, never
//! panic. A panic the importer's own guard contained (it turns a panic in a dependency
//! into an error) is reported as a crash here too, so that it can be fixed at its source.
//! Seed it with `tests/fuzz/corpus/gltf/`.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    match tessera_scene::gltf_import::load_slice(data, "fuzz.glb", None, None) {
        Ok(scene) => scene.validate().expect("an imported scene validates"),
        Err(e) => assert!(
            !e.to_string().contains("made the reader fail"),
            "a panic inside the importer: {e}"
        ),
    }
});
