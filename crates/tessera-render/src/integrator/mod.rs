//! Integrators: estimators of the radiance arriving at the camera along a ray.
//!
//! | name | what it computes |
//! |---|---|
//! | `path` | unidirectional path tracing with next-event estimation, multiple importance sampling and Russian roulette ([`path`]) |
//! | `direct` | direct lighting only: emission seen by the camera and light arriving at the first surface, one bounce, both techniques combined by MIS |
//! | `bdpt` | bidirectional path tracing: camera and light subpaths joined by every connection technique, light tracing splatted onto the film, power-heuristic MIS ([`bdpt`]) |

pub mod bdpt;
pub mod path;

/// The integrators, MIS heuristics and their string forms are the job contract's
/// ([`tessera_farm::job`]): one type each, here under the renderer's names.
pub use tessera_farm::job::{Integrator as IntegratorKind, MisHeuristic};
