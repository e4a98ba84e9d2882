//! Scene analysis: which light-transport effects a scene contains, and the render plan
//! that simulates exactly those (ARCHITECTURE.md §4, "simulate only what the scene calls for").
//!
//! [`analyse`] looks at the lights, the materials that surfaces actually use, the shape of
//! the geometry and the camera, and returns a [`RenderPlan`]: the [`Effect`]s present, each
//! with its evidence, the [`EffectKind`]s that are absent, and the integrator with the path
//! depth and Russian-roulette settings chosen for exactly those effects, with the reasons.
//!
//! # The rules (this is the contract)
//!
//! **Lights.** A light counts only if it has positive power:
//! - area lights: emissive triangles (emission > 0, area > 0), grouped by material
//!   ([`EffectKind::DirectArea`]);
//! - sphere lights: spheres with an emissive material ([`EffectKind::DirectSphere`]);
//! - point, spot and directional lights: [`PunctualLight`]s with positive intensity or
//!   irradiance (a spot also needs an outer cone angle > 0) ([`EffectKind::DirectPoint`],
//!   [`EffectKind::DirectSpot`], [`EffectKind::DirectDirectional`]);
//! - the environment: [`Scene::environment`] with positive radiance
//!   ([`EffectKind::DirectEnvironment`]).
//!
//! With no light the plan is [`PlannedIntegrator::Black`], reason "no light: the image is
//! black", and the renderer skips tracing. The same holds when the only lights are point,
//! spot or directional lights (which the camera cannot see) and no surface scatters light.
//! A black plan is empty: it lists no effect besides the lights found.
//!
//! **Surfaces.** Only materials used by a mesh with triangles or by a sphere count. A
//! material *scatters* unless every layer below is absent (an emitter with zero albedo is
//! a light and nothing else). The classes of each material:
//! - `Diffuse`: diffuse (if the albedo is > 0);
//! - `Phong`: glossy if `ks > 0`, diffuse if `kd > 0`;
//! - `Conductor`: specular if roughness < [`SPECULAR_ROUGHNESS`], glossy otherwise;
//! - `Mirror`: specular (if the reflectance is > 0);
//! - `Dielectric`: refraction (if the tint is > 0; *smooth* refraction if roughness <
//!   [`SPECULAR_ROUGHNESS`]); with `ior != 1` also a Fresnel reflection (specular or
//!   glossy by roughness) and total internal reflection;
//! - `Gltf` (metallic-roughness), by layer weight (factors times their textures' means;
//!   roughness from the smallest texel, clearcoat reflects by its roughness, sheen is
//!   glossy, KHR_materials_unlit scatters nothing):
//!   - the metal (`metallic > 0` and a base colour above 0) is a conductor as above;
//!   - the dielectric base (weight `(1 - metallic)(1 - transmission)` above 0) is diffuse
//!     if the base colour is above 0, under a Fresnel coat (if `ior > 1`) that counts as
//!     specular if roughness < [`SPECULAR_ROUGHNESS`], glossy if roughness <
//!     [`DIFFUSE_LIKE_ROUGHNESS`], and not at all above that (a roughness-1 dielectric
//!     coat is basically diffuse, so a plain glTF wall is "diffuse");
//!   - the transmissive part (weight `(1 - metallic) transmission` above 0) refracts
//!     (smoothly if roughness < [`SPECULAR_ROUGHNESS`]) under a Fresnel reflection (if
//!     `ior > 1`, specular or glossy by roughness), with total internal reflection if
//!     `ior > 1`.
//!
//! [`EffectKind::GlossyReflection`], [`EffectKind::SpecularReflection`],
//! [`EffectKind::Refraction`] and [`EffectKind::TotalInternalReflection`] are present when
//! some used, scattering material has that class.
//!
//! **Light bouncing between surfaces.** The scattering primitives are the spheres and the
//! triangles whose material scatters. Light can scatter more than once (a *multi-bounce*
//! scene) unless the scattering geometry is a single plane (all scattering triangles
//! coplanar and no scattering sphere) or a single sphere seen and lit only from outside.
//! A non-planar mesh counts as multi-bounce even if it is convex: the analysis errs on the
//! side of simulating more, never less.
//! - [`EffectKind::IndirectDiffuse`]: multi-bounce and some material is diffuse.
//! - [`EffectKind::Caustics`]: multi-bounce, some material is specular or refracts
//!   smoothly (a mirror, smooth glass, smooth metal: roughness < [`SPECULAR_ROUGHNESS`]),
//!   some material is diffuse, and there is a light.
//! - [`EffectKind::DeltaLitCaustics`]: caustics, and at least one point, spot or
//!   directional light, or a tiny sphere or area light (bounding radius below
//!   [`TINY_LIGHT_FRACTION`] of the scene's bounding radius): light a path tracer with
//!   next-event estimation reaches through a specular chain with zero (or almost zero)
//!   probability.
//!
//! - [`EffectKind::DeltaLitSds`]: delta-lit caustics, at least one point, spot or
//!   directional light, and a smooth specular primitive (sphere or triangle) whose bounding
//!   sphere meets the camera's view cone: a caustic of a delta light may be seen through or
//!   in it, as `L S+ D S+ E` (Heckbert 1990), which neither path tracing nor bdpt can
//!   sample.
//!
//! - [`EffectKind::TinyLightImages`]: a tiny sphere or area light (as above) and a smooth
//!   specular primitive whose bounding sphere meets the camera's view cone: the light's
//!   images may be seen in or through it, as `E S+ L`, which every integrator samples only
//!   as path tracing does (a camera path whose specular chain happens to end on the light),
//!   so the error estimate's caveat says the estimate may be optimistic there. Not a
//!   choice between techniques: none of them has another way to that light.
//!
//! **Camera, motion, textures.** [`EffectKind::DepthOfField`] iff the camera aperture
//! radius is > 0, and then `lens_sampling` is on; [`EffectKind::Motion`] is always absent
//! (there is no motion blur: each frame of an animated scene is the scene at one time,
//! and the plan's reasons say whether the scene is animated);
//! [`EffectKind::Textures`] iff a used material has a base-colour texture.
//!
//! **Integrator.**
//! - [`PlannedIntegrator::Black`] if there is no light (see above);
//! - [`PlannedIntegrator::Direct`] if nothing can bounce light to the camera a second
//!   time: no indirect diffuse and nothing glossy, specular or refractive (e.g. a single
//!   plane under a light);
//! - [`PlannedIntegrator::Mnee`] if there are delta-lit caustics seen through specular
//!   surfaces ([`EffectKind::DeltaLitSds`]) and manifold next-event estimation samples
//!   every caustic of the scene's delta and tiny lights (below): path tracing with MNEE is
//!   unbiased;
//! - [`PlannedIntegrator::Vcm`] if there are delta-lit caustics seen through specular
//!   surfaces that MNEE does not reach: vertex merging is the only technique for them;
//! - [`PlannedIntegrator::Bdpt`] if there are (other) delta-lit caustics;
//! - [`PlannedIntegrator::Bdpt`], left to the technique pilot, where the rules so far give
//!   path tracing but the scene is lit through an opening (below);
//! - [`PlannedIntegrator::Path`] otherwise; left to the technique pilot, against mnee,
//!   where caustics of small area lights are within MNEE's reach (below).
//!
//! Where the caustics' only lights are tiny finite ones, or the scene is lit through an
//! opening, path tracing is as correct as bdpt and the plan leaves the choice between them
//! (and mlt) to the technique pilot ([`RenderPlan::technique_pilot`]).
//!
//! **Manifold next-event estimation.** For a scene with delta-lit caustics, a survey of
//! specular chains (`manifold`) lists what MNEE (`tessera_render::integrator::mnee`:
//! Hanika, Droske & Fascione 2015) cannot sample ([`RenderPlan::beyond_mnee`]). MNEE
//! connects the camera path's first non-specular vertex to a point, spot or
//! emissive-triangle light through the specular surfaces the straight segment between
//! them crosses, at most [`MNEE_MAX_CHAIN`], each purely specular. So a caustic is within
//! its reach when its light is a point, spot or tiny area light (not a directional or
//! sphere light), it crosses (never reflects off) at most [`MNEE_MAX_CHAIN`] purely
//! specular surfaces, and the camera sees its receiver at the first non-specular vertex,
//! directly or through specular surfaces. The survey follows [`MNEE_LIGHT_RAYS`] rays
//! from each point and spot light (over a spot's cone) and from each tiny area light's
//! centre through the specular surfaces they meet (straight through refracting ones, as
//! MNEE's seed segment; mirrored off reflecting ones, up to [`MNEE_MAX_CHAIN`] + 1
//! vertices), and the direct-light survey's camera rays through specular surfaces (up to
//! [`MNEE_CAMERA_CHAIN`] vertices) to the first non-specular materials; it compares
//! materials. Finding no caustic at all counts as not reaching. What MNEE never samples,
//! even within that reach: the caustic's light after a further diffuse or glossy bounce
//! (`L S+ D .. D S* E`; the plan says so in its reasons and the error estimate caveat).
//!
//! **Caustics of small area lights.** Where the caustics are lit only by finite lights,
//! none tiny (no [`EffectKind::DeltaLitCaustics`]), path tracing finds them by BSDF
//! sampling, noisily when the light is small. For the area lights whose bounding radius
//! is below [`SMALL_LIGHT_FRACTION`] of the scene's, the survey of specular chains above
//! follows [`MNEE_LIGHT_RAYS`] rays from each light's centre; if some caustic of MNEE's
//! shape (at most [`MNEE_MAX_CHAIN`] refracting surfaces) lands on a material the camera
//! sees first, a path-traced plan leaves the choice between path tracing and mnee to the
//! technique pilot ([`RenderPlan::technique_pilot`], `mnee`). Both are unbiased: mnee is
//! path tracing with manifold next-event estimation, which leaves every path it does not
//! claim to BSDF sampling. A plan lit through an opening asks the bdpt question instead.
//!
//! **Light through an opening.** A path-traced plan is surveyed for how much of what the
//! camera sees the lights reach directly: [`DIRECT_SURVEY_GRID`]² pinhole camera rays
//! through pixel centres (the scene's aspect ratio); at each first hit on an emitter (lit)
//! or on a surface with a diffuse or glossy layer (where next-event estimation applies;
//! other hits are not counted), shadow rays to the lights' samples (point and spot lights,
//! inside the cone; up to 16 points on the emissive triangles, on their emitting side; the
//! nearest point of each emissive sphere; each directional light's direction; five
//! directions about the normal for the environment), every surface opaque. If fewer than
//! [`DIRECT_LIT_FRACTION`] of the counted hits see a light, the image is carried by paths
//! that a path tracer completes only after finding the opening by BSDF sampling (Veach's
//! door ajar, Veach 1997, section 11.5), and the plan is bdpt left to the pilot. Scenes
//! of more than [`DIRECT_SURVEY_MAX_PRIMITIVES`] triangles and spheres are not surveyed.
//! On the repository's scenes the fraction is 0.4% for `scenes/door-ajar.gltf` (one ray
//! sees through the gap), 18% for `scenes/indirect-room.gltf` (its light faces the
//! ceiling), 61% for `builtin:veach-mis`, 72% for the Cornell box and above 88% for the
//! rest.
//!
//! **Depth.** `Direct`: `max_depth` 1. `Path`/`Bdpt`/`Vcm`: [`CLOSED_ROOM_DEPTH`] for a *closed
//! bright room* — indirect diffuse, an area-weighted mean diffuse albedo above
//! [`BRIGHT_ALBEDO`] and scattering surfaces whose area is at least [`CLOSED_FRACTION`] of
//! the surface of the scene's bounding box — else [`DEFAULT_DEPTH`]; with refraction at
//! least [`REFRACTION_DEPTH`] (light needs several interfaces to pass through glass).
//! `rr_depth` is [`DEFAULT_RR_DEPTH`] for a closed bright room or with refraction (light
//! keeps bouncing, or needs several interfaces), else [`OPEN_SCENE_RR_DEPTH`]; survival
//! follows the throughput either way. `Black`
//! has depth 0: nothing is traced.
//!
//! ```
//! use tessera_scene::analysis::{analyse, EffectKind, PlannedIntegrator};
//! let plan = analyse(&tessera_scene::load("builtin:cornell-box").unwrap());
//! assert!(plan.has(EffectKind::IndirectDiffuse));
//! assert_eq!(plan.integrator, PlannedIntegrator::Path);
//! ```
//!
//! # Where each rule lives
//!
//! [`analyse`] runs the steps in order, each in its own module: `classify` (the classes of
//! each material), `survey` (used materials, their areas, the scene's extent), `lights`
//! (the "Lights" rule), `transport` (the "Surfaces" and "Light bouncing between surfaces"
//! rules), `appearance` (depth of field and textures) and `decide` (the "Integrator" and
//! "Depth" rules). The result types are the job contract's ([`tessera_farm::job::plan`]),
//! which depends on none of them.

mod appearance;
mod classify;
mod decide;
mod direct;
mod evidence;
mod lights;
mod manifold;
mod survey;
mod transport;

pub use tessera_farm::job::plan::{
    Effect, EffectKind, PlannedIntegrator, RenderPlan, TechniquePilot,
};

#[cfg(doc)]
use crate::PunctualLight;
use crate::Scene;

/// Roughness below which a reflection or refraction counts as specular (near-delta).
pub const SPECULAR_ROUGHNESS: f32 = 0.05;
/// Roughness from which the Fresnel coat of a glTF dielectric base counts as part of the
/// diffuse lobe rather than as glossy reflection.
pub const DIFFUSE_LIKE_ROUGHNESS: f32 = 0.9;
/// A sphere or area light whose bounding radius is below this fraction of the scene's
/// bounding radius is "tiny": for caustics it behaves like a point light.
pub const TINY_LIGHT_FRACTION: f32 = 0.01;
/// Bounding radius, as a fraction of the scene's bounding radius, below which an area
/// light is *small* for the "Caustics of small area lights" rule: BSDF sampling finds its
/// caustics rarely enough that manifold next-event estimation may pay (bench/compare's
/// glass ball: a 0.2 m square light, 0.02 of the scene's radius).
pub const SMALL_LIGHT_FRACTION: f32 = 0.05;
/// Area-weighted mean diffuse albedo above which a room is "bright".
pub const BRIGHT_ALBEDO: f32 = 0.5;
/// Fraction of the bounding box's surface that scattering surfaces must cover for the
/// scene to count as a closed room.
pub const CLOSED_FRACTION: f32 = 0.75;
/// Path depth of a closed bright room.
pub const CLOSED_ROOM_DEPTH: u32 = 16;
/// Path depth otherwise.
pub const DEFAULT_DEPTH: u32 = 8;
/// Minimum path depth when something refracts.
pub const REFRACTION_DEPTH: u32 = 12;
/// Camera rays of the direct-light survey: a grid of this many squared (module
/// documentation, "Light through an opening").
pub const DIRECT_SURVEY_GRID: u32 = 16;
/// Largest number of triangles and spheres the direct-light survey traces (its hierarchy
/// is built for the analysis alone, so it must stay cheap); above it the survey is not
/// made and the rule does not apply.
pub const DIRECT_SURVEY_MAX_PRIMITIVES: usize = 1 << 18;
/// Below this fraction of the surveyed camera hits lit directly, a path-traced plan is
/// left to the technique pilot (module documentation, "Light through an opening").
pub const DIRECT_LIT_FRACTION: f32 = 0.1;
/// Russian roulette start depth of a plan for a closed bright room or a scene with
/// refraction: the job contract's [`tessera_farm::job::DEFAULT_RR_DEPTH`] (5, Mitsuba 3's).
pub const DEFAULT_RR_DEPTH: u32 = tessera_farm::job::DEFAULT_RR_DEPTH;
/// Russian roulette start depth of an open scene without refraction: its paths carry
/// little after a few bounces, so roulette may cut them early. Measured (docs/benchmarks.md,
/// "Russian roulette"): starting at 5 instead of 3 costs the Veach scene 12% more
/// instructions for the same noise, and buys the closed Cornell box 24% less noise for 27%
/// more instructions.
pub const OPEN_SCENE_RR_DEPTH: u32 = 3;
/// Most specular vertices manifold next-event estimation connects through: the
/// renderer's `tessera_render::integrator::mnee::MAX_CHAIN` (a test there checks that the
/// two agree), which the plan's "Manifold next-event estimation" rule reads.
pub const MNEE_MAX_CHAIN: usize = 2;
pub use manifold::{CAMERA_CHAIN as MNEE_CAMERA_CHAIN, LIGHT_RAYS as MNEE_LIGHT_RAYS};

/// Analyses `scene` into a render plan, following the rules in the module documentation.
pub fn analyse(scene: &Scene) -> RenderPlan {
    let survey = survey::Survey::new(scene);
    let mut effects: Vec<Effect> = Vec::new();
    let lights = lights::find(scene);
    lights::report(&lights, &survey, &mut effects);
    let mut transport = transport::analyse(&survey, &lights, &mut effects);
    let lens_sampling = appearance::report(&survey, &mut effects);
    // What MNEE cannot sample matters only where delta or tiny lights make caustics.
    if transport.delta_lit {
        transport.beyond_mnee = manifold::misses(&survey, &lights);
    } else if transport.caustics {
        transport.small_light_mnee = manifold::small_light_caustics(&survey, &lights);
    }
    let mut plan = decide::plan(
        &scene.camera,
        scene.animated,
        &lights,
        &transport,
        lens_sampling,
        effects,
        || direct::survey(&survey),
    );
    plan.warnings = scene.warnings.clone();
    plan
}

/// Records an effect with its evidence.
fn push(effects: &mut Vec<Effect>, kind: EffectKind, evidence: String) {
    effects.push(Effect { kind, evidence });
}
