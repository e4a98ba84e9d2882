//! The renderer's integration tests, one binary (linking the crate once, not once per
//! file): each file below is a module, so a test is named `FILE::TEST`, e.g.
//! `cargo test -p tessera-render --test it bdpt::` runs the BDPT tests. `common` holds
//! the helpers they share; the glTF builder is in the `tessera-testkit` crate. The light
//! sampling measurement stays its own binary (`--test light_bench`): it times the process's
//! CPU seconds, which tests running beside it in one process would inflate.

mod analytic;
mod anisotropy;
mod bdpt;
mod blender_references;
mod calibration;
mod common;
mod determinism;
mod environment;
mod gltf_materials;
mod gltf_units;
mod instancing;
mod khronos_environment;
mod light_tree;
mod many_nodes;
mod mlt;
mod mnee;
mod mnee_plan;
mod motion_blur;
mod pilot;
mod plan_equivalence;
mod robustness;
mod vcm;
