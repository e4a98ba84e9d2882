//! Tessera's deterministic CPU rendering core.
//!
//! Architecture, bottom up:
//!
//! - [`sampling`]: the per-pixel randomized quasi-Monte Carlo sampler and the warps;
//! - [`geometry`]: triangles in an `obvhs` CWBVH (watertight, near-hit safe; built in
//!   `O(n log n)` even on coincident primitives, on a stack of known size) and spheres;
//! - [`bsdf`] and [`light`]: closed enums of scattering models and emitters, each
//!   variant in its own file with its documentation;
//! - [`integrator`]: path tracing with NEE and MIS, direct lighting and bdpt;
//! - [`pilot`]: the measured choice between path tracing and bdpt where both are correct;
//! - [`scene::RenderScene`]: a [`tessera_scene::Scene`] prepared for tracing;
//! - [`render::render_unit`]: renders one `tessera-farm` work unit (tile x pass range), the
//!   only entry point the farm's workers and the local renderer use;
//! - [`adaptive::render_adaptive`]: round-by-round adaptive rendering with
//!   `tessera-farm`'s adaptive policy (pixels that stopped are skipped).
//!
//! No async and no network code lives here.
//!
//! ```no_run
//! use tessera_render::{render::{render_frame, RenderConfig}, scene::RenderScene};
//! let scene = tessera_scene::load("builtin:cornell-box").unwrap();
//! let rs = RenderScene::build(&scene, 64, 64).unwrap();
//! let plan = tessera_farm::FramePlan::for_spp(64, 64, 16, 32).unwrap();
//! let acc = render_frame(&rs, &RenderConfig::default(), &plan, 0, 0, |_, _| {});
//! println!("relative error {}", acc.image_error());
//! ```
#![deny(missing_docs)]

pub mod adaptive;
pub mod bsdf;
pub mod camera;
pub mod figure5;
pub mod geometry;
pub mod integrator;
pub mod light;
pub mod math;
pub mod motion;
pub mod pilot;
pub mod render;
pub mod sampling;
pub mod scene;
pub mod texture;

#[cfg(test)]
mod chi2;
