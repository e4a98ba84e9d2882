//! The scene crate's integration tests, one binary (linking the crate once, not once per
//! file): each file below is a module, so a test is named `FILE::TEST`, e.g.
//! `cargo test -p tessera-scene --test it gltf::` runs the glTF import tests. Shared
//! helpers (the glTF builder, the fuzz generator) are in the `tessera-testkit` crate.

mod analysis;
mod animation;
mod environment;
mod fuzz_gltf;
mod gltf;
mod gltf_materials;
mod khronos;
