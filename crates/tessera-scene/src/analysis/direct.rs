//! Step 5: how much of what the camera sees the lights reach directly (the module
//! documentation's "Light through an opening" rule), by a shadow-ray survey at the
//! camera's first hits.
//!
//! A path tracer with next-event estimation connects every vertex to a light; where the
//! lights reach the surfaces the camera sees, the first connection already carries most of
//! the image. Where they reach almost none of them (Veach's door ajar: the lamp in the next
//! room, the seen room lit through a gap; Veach 1997, section 11.5, figure 11.4), the
//! image is carried by paths that must find the opening by BSDF sampling before a
//! connection succeeds, and bidirectional path tracing, whose light subpaths leave the lamp
//! through the opening, may be the cheaper technique for the same error (Veach & Guibas
//! 1995, section 4.3). The survey measures that fraction; the plan then leaves the choice
//! to the technique pilot.
//!
//! The survey is cheap: [`DIRECT_SURVEY_GRID`]² camera rays through the pixel centres of
//! a pinhole camera, and at each hit on a surface that scatters diffusely or glossily a
//! shadow ray to each light sample (point and spot lights; a few points on the emissive
//! triangles, on their emitting side; the nearest point of each emissive sphere; the
//! direction of each directional light; five directions about the normal for the
//! environment) until one is unoccluded. Every surface blocks a shadow ray (glass too, as
//! it blocks a path tracer's connections). The rays are traced in a small bounding volume
//! hierarchy (obvhs') over the scene's triangles and spheres.

use super::survey::Survey;
use super::{DIRECT_SURVEY_GRID, DIRECT_SURVEY_MAX_PRIMITIVES};
use crate::PunctualLight;
use glam::{Vec2, Vec3};
use obvhs::aabb::Aabb;
use obvhs::bvh2::Bvh2;
use obvhs::ploc::{PlocBuilder, SortPrecision};
use obvhs::ray::{Ray, RayHit};

/// What the survey found.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct DirectSurvey {
    /// Camera rays that hit a surface that scatters diffusely or glossily, or an emitter.
    pub(super) surfaces: usize,
    /// Those that see a light directly (an emitter counts as lit).
    pub(super) lit: usize,
}

impl DirectSurvey {
    /// `lit / surfaces` (1 without surfaces: nothing to say).
    pub(super) fn fraction(&self) -> f32 {
        if self.surfaces == 0 {
            1.0
        } else {
            self.lit as f32 / self.surfaces as f32
        }
    }
}

/// A primitive of the survey's hierarchy: a triangle (a vertex and two edges) or a sphere.
#[derive(Clone, Copy)]
enum Shape {
    Triangle { p0: Vec3, e1: Vec3, e2: Vec3 },
    Sphere { center: Vec3, radius: f32 },
}

#[derive(Clone, Copy)]
pub(super) struct Prim {
    shape: Shape,
    /// The primitive's material index.
    pub(super) material: usize,
    lo: Vec3,
    hi: Vec3,
}

impl Prim {
    /// Distance along `d` (unit) from `o` to the first hit in `(t_min, t_max)`.
    fn hit(&self, o: Vec3, d: Vec3, t_min: f32, t_max: f32) -> Option<f32> {
        match self.shape {
            Shape::Triangle { p0, e1, e2 } => {
                // Möller & Trumbore 1997, both faces.
                let p = d.cross(e2);
                let det = e1.dot(p);
                if det.abs() < 1e-12 {
                    return None;
                }
                let inv = 1.0 / det;
                let s = o - p0;
                let u = s.dot(p) * inv;
                if !(0.0..=1.0).contains(&u) {
                    return None;
                }
                let q = s.cross(e1);
                let v = d.dot(q) * inv;
                if v < 0.0 || u + v > 1.0 {
                    return None;
                }
                let t = e2.dot(q) * inv;
                (t > t_min && t < t_max).then_some(t)
            }
            Shape::Sphere { center, radius } => {
                let oc = o - center;
                let b = oc.dot(d);
                let c = oc.length_squared() - radius * radius;
                let disc = b * b - c;
                if disc < 0.0 {
                    return None;
                }
                let r = disc.sqrt();
                [-b - r, -b + r]
                    .into_iter()
                    .find(|&t| t > t_min && t < t_max)
            }
        }
    }

    /// The unit geometric normal at `x` (a triangle's by its winding).
    pub(super) fn normal(&self, x: Vec3) -> Vec3 {
        match self.shape {
            Shape::Triangle { e1, e2, .. } => e1.cross(e2).normalize_or_zero(),
            Shape::Sphere { center, .. } => (x - center).normalize_or_zero(),
        }
    }
}

/// The survey's primitives in obvhs' binary BVH (built by PLOC, as the render scene's),
/// with its traversal: a survey ray needs no more than that.
pub(super) struct Bvh {
    /// The primitives, indexed as [`Bvh::trace`] returns them.
    pub(super) prims: Vec<Prim>,
    tree: Bvh2,
}

impl Bvh {
    pub(super) fn new(prims: Vec<Prim>) -> Self {
        let boxes: Vec<Aabb> = prims
            .iter()
            .map(|p| Aabb::new(p.lo.into(), p.hi.into()))
            .collect();
        let mut tree = Bvh2::default();
        if !boxes.is_empty() {
            let indices = (0..boxes.len() as u32).collect();
            PlocBuilder::new().build_ploc::<1, Aabb>(
                &mut tree,
                &boxes,
                indices,
                SortPrecision::U64,
                0,
            );
        }
        Self { prims, tree }
    }

    /// The first hit along `d` from `o` in `(t_min, t_max)`: distance and primitive.
    /// With `any`, the first hit found (a shadow ray needs no more).
    pub(super) fn trace(
        &self,
        o: Vec3,
        d: Vec3,
        t_min: f32,
        t_max: f32,
        any: bool,
    ) -> Option<(f32, usize)> {
        if self.tree.nodes.is_empty() {
            return None;
        }
        let ray = Ray::new(o.into(), d.into(), t_min, t_max);
        let prim = |id: usize| self.tree.primitive_indices[id] as usize;
        if any {
            let mut found = None;
            let missed = self.tree.ray_traverse_miss(ray, |ray, id| {
                let k = prim(id);
                match self.prims[k].hit(o, d, t_min, ray.tmax) {
                    Some(t) => {
                        found = Some((t, k));
                        t
                    }
                    None => f32::INFINITY,
                }
            });
            return if missed { None } else { found };
        }
        let mut best = None;
        let mut hit = RayHit::none();
        self.tree.ray_traverse(ray, &mut hit, |ray, id| {
            let k = prim(id);
            match self.prims[k].hit(o, d, t_min, ray.tmax) {
                Some(t) => {
                    best = Some((t, k));
                    t
                }
                None => f32::INFINITY,
            }
        });
        best
    }
}

/// Where a shadow ray goes.
enum Target {
    /// A point (a point light, a point on an emitter); with the emitter's normal when it
    /// emits on one side only, and for a spot its axis and the cosine of its outer angle.
    Point {
        at: Vec3,
        one_sided: Option<Vec3>,
        cone: Option<(Vec3, f32)>,
    },
    /// The nearest point of an emissive sphere.
    Sphere { center: Vec3, radius: f32 },
    /// Infinitely far in this direction (a directional light).
    Direction(Vec3),
    /// The environment: five directions about the surface normal.
    Environment,
}

/// Most points taken on the emissive triangles.
const MAX_AREA_POINTS: usize = 16;

/// A point or spot light that emits: where from and, for a spot, its cone (unit axis,
/// cosine of the outer angle); `None` for dark lights and lights of other kinds.
pub(super) fn emitting_point(l: &PunctualLight) -> Option<(Vec3, Option<(Vec3, f32)>)> {
    match *l {
        PunctualLight::Point {
            position,
            intensity,
        } if intensity.max_element() > 0.0 => Some((position, None)),
        PunctualLight::Spot {
            position,
            direction,
            intensity,
            outer_angle,
            ..
        } if intensity.max_element() > 0.0 && outer_angle > 0.0 => Some((
            position,
            Some((direction.normalize_or_zero(), outer_angle.cos())),
        )),
        _ => None,
    }
}

/// The light samples of the survey.
fn targets(survey: &Survey) -> Vec<Target> {
    let scene = survey.scene;
    let mut out = Vec::new();
    for l in &scene.lights {
        if let Some((at, cone)) = emitting_point(l) {
            out.push(Target::Point {
                at,
                one_sided: None,
                cone,
            });
        } else if let PunctualLight::Directional {
            direction,
            irradiance,
        } = *l
        {
            if irradiance.max_element() > 0.0 {
                out.push(Target::Direction(-direction.normalize_or_zero()));
            }
        }
    }
    // Emissive triangles: four points each (the centroid and three towards the corners)
    // when there are few of them, else the centroids of an even selection.
    let mut emitters: Vec<([Vec3; 3], bool)> = Vec::new();
    for placed in scene.placed_meshes() {
        let Some(m) = scene.materials.get(placed.material() as usize) else {
            continue;
        };
        if m.is_emissive() {
            emitters.extend(placed.triangles().map(|t| (t, m.double_sided)));
        }
    }
    let per = if emitters.len() * 4 <= MAX_AREA_POINTS {
        4
    } else {
        1
    };
    let stride = (emitters.len() * per).div_ceil(MAX_AREA_POINTS).max(1);
    for &(p, double_sided) in emitters.iter().step_by(stride) {
        let n = (p[1] - p[0]).cross(p[2] - p[0]).normalize_or_zero();
        let c = (p[0] + p[1] + p[2]) / 3.0;
        let one_sided = (!double_sided).then_some(n);
        out.push(Target::Point {
            at: c,
            one_sided,
            cone: None,
        });
        if per == 4 {
            for v in p {
                out.push(Target::Point {
                    at: 0.5 * (c + v),
                    one_sided,
                    cone: None,
                });
            }
        }
    }
    for s in &scene.spheres {
        if scene
            .materials
            .get(s.material as usize)
            .is_some_and(|m| m.is_emissive())
        {
            out.push(Target::Sphere {
                center: s.center,
                radius: s.radius,
            });
        }
    }
    if scene.environment.is_some_and(|e| e.max_element() > 0.0) {
        out.push(Target::Environment);
    }
    out
}

/// The scene's triangles and spheres, or `None` above [`DIRECT_SURVEY_MAX_PRIMITIVES`].
pub(super) fn primitives(survey: &Survey) -> Option<Vec<Prim>> {
    let scene = survey.scene;
    let mut prims = Vec::new();
    for placed in scene.placed_meshes() {
        if prims.len() + placed.mesh.indices.len() > DIRECT_SURVEY_MAX_PRIMITIVES {
            return None;
        }
        let material = placed.material() as usize;
        prims.extend(placed.triangles().map(|p| Prim {
            shape: Shape::Triangle {
                p0: p[0],
                e1: p[1] - p[0],
                e2: p[2] - p[0],
            },
            material,
            lo: p[0].min(p[1]).min(p[2]),
            hi: p[0].max(p[1]).max(p[2]),
        }));
    }
    if prims.len() + scene.spheres.len() > DIRECT_SURVEY_MAX_PRIMITIVES {
        return None;
    }
    prims.extend(scene.spheres.iter().map(|s| Prim {
        shape: Shape::Sphere {
            center: s.center,
            radius: s.radius,
        },
        material: s.material as usize,
        lo: s.center - Vec3::splat(s.radius),
        hi: s.center + Vec3::splat(s.radius),
    }));
    Some(prims)
}

/// Runs the survey; `None` when the scene has more than [`DIRECT_SURVEY_MAX_PRIMITIVES`]
/// triangles and spheres (the survey would no longer be cheap; the plan then stays
/// path tracing, as before the survey existed).
pub(super) fn survey(survey: &Survey) -> Option<DirectSurvey> {
    let scene = survey.scene;
    let bvh = Bvh::new(primitives(survey)?);
    let targets = targets(survey);
    let eps = 1e-4 * survey.scene_radius;
    let (origin, rays) = camera_rays(scene);
    let mut result = DirectSurvey {
        surfaces: 0,
        lit: 0,
    };
    for d in rays {
        let Some((t, k)) = bvh.trace(origin, d, 0.0, f32::INFINITY, false) else {
            continue;
        };
        let prim = &bvh.prims[k];
        let Some(material) = scene.materials.get(prim.material) else {
            continue;
        };
        if material.is_emissive() {
            result.surfaces += 1;
            result.lit += 1;
            continue;
        }
        // Only where next-event estimation applies: a diffuse or glossy layer.
        let classes = &survey.classes[prim.material];
        if !(classes.diffuse || classes.glossy) {
            continue;
        }
        result.surfaces += 1;
        let x = origin + t * d;
        let mut n = prim.normal(x);
        if n.dot(d) > 0.0 {
            n = -n;
        }
        let from = x + eps * n;
        if targets
            .iter()
            .any(|target| sees(&bvh, from, n, target, eps))
        {
            result.lit += 1;
        }
    }
    Some(result)
}

/// The pinhole camera's position and the unit directions of the survey's
/// [`DIRECT_SURVEY_GRID`]² rays through pixel centres, row by row (the scene's aspect
/// ratio).
pub(super) fn camera_rays(scene: &crate::Scene) -> (Vec3, impl Iterator<Item = Vec3> + '_) {
    let camera = &scene.camera;
    let (w, h) = scene.default_resolution;
    let aspect = camera
        .aspect_ratio
        .unwrap_or(w.max(1) as f32 / h.max(1) as f32);
    let tan = (0.5 * camera.yfov).tan();
    let origin = camera.world_from_camera.transform_point3(Vec3::ZERO);
    let g = DIRECT_SURVEY_GRID;
    let rays = (0..g).flat_map(move |j| {
        (0..g).map(move |i| {
            let uv = (Vec2::new(i as f32, j as f32) + 0.5) / g as f32;
            let local = Vec3::new(
                (2.0 * uv.x - 1.0) * tan * aspect,
                (1.0 - 2.0 * uv.y) * tan,
                -1.0,
            );
            camera
                .world_from_camera
                .transform_vector3(local)
                .normalize_or_zero()
        })
    });
    (origin, rays)
}

/// Whether a shadow ray from `from` (on a surface of normal `n`, facing the camera)
/// reaches `target` unoccluded, on the side the camera sees.
fn sees(bvh: &Bvh, from: Vec3, n: Vec3, target: &Target, eps: f32) -> bool {
    let to_point = |at: Vec3| {
        let v = at - from;
        let dist = v.length();
        if dist <= eps {
            return true;
        }
        let d = v / dist;
        n.dot(d) > 0.0 && bvh.trace(from, d, 0.0, dist - eps, true).is_none()
    };
    let to_infinity =
        |d: Vec3| n.dot(d) > 0.0 && bvh.trace(from, d, 0.0, f32::INFINITY, true).is_none();
    match *target {
        Target::Point {
            at,
            one_sided,
            cone,
        } => {
            if one_sided.is_some_and(|ln| ln.dot(from - at) <= 0.0) {
                return false;
            }
            if let Some((axis, cos_outer)) = cone {
                if axis.dot((from - at).normalize_or_zero()) < cos_outer {
                    return false;
                }
            }
            to_point(at)
        }
        Target::Sphere { center, radius } => {
            let out = (from - center).normalize_or_zero();
            to_point(center + (radius + eps) * out)
        }
        Target::Direction(d) => to_infinity(d),
        Target::Environment => {
            // The normal and four directions 60 degrees from it.
            let (b1, b2) = n.any_orthonormal_pair();
            let (s, c) = (60f32.to_radians().sin(), 60f32.to_radians().cos());
            std::iter::once(n)
                .chain([b1, -b1, b2, -b2].map(|b| c * n + s * b))
                .any(to_infinity)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fraction(scene: &crate::Scene) -> f32 {
        let s = Survey::new(scene);
        survey(&s).expect("a small scene").fraction()
    }

    /// The Cornell box's walls see its ceiling light almost everywhere; Veach's door-ajar
    /// room, lit only through the gap, almost nowhere.
    #[test]
    fn the_survey_tells_a_lit_room_from_one_lit_through_a_gap() {
        let cornell = crate::load("builtin:cornell-box").unwrap();
        let f = fraction(&cornell);
        assert!(f > 0.5, "cornell box {f}");
        let door = crate::load(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../scenes/door-ajar.gltf"
        ))
        .unwrap();
        let f = fraction(&door);
        assert!(f < 0.05, "door ajar {f}");
    }

    /// Over the repository's scenes the survey's rule changes one plan, the door-ajar
    /// room's: every other scene is lit directly over most of what its camera sees, or is
    /// not path traced (the survey is made only for a path-traced plan).
    #[test]
    fn among_the_repositorys_scenes_only_the_door_ajar_room_is_lit_through_an_opening() {
        let root = concat!(env!("CARGO_MANIFEST_DIR"), "/../../");
        let mut names: Vec<String> = ["cornell-box", "veach-mis", "furnace", "caustic"]
            .iter()
            .map(|n| format!("builtin:{n}"))
            .collect();
        for dir in ["scenes", "tests/fixtures/blender"] {
            let mut files: Vec<String> = std::fs::read_dir(format!("{root}{dir}"))
                .unwrap()
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| p.extension().is_some_and(|x| x == "gltf" || x == "glb"))
                .map(|p| p.to_string_lossy().into_owned())
                .collect();
            files.sort();
            names.extend(files);
        }
        assert!(names.len() > 20, "{names:?}");
        for name in names {
            let scene = crate::load(&name).unwrap();
            let s = Survey::new(&scene);
            let f = survey(&s).map(|d| d.fraction());
            let plan = crate::analysis::analyse(&scene);
            let opening = plan.reasons[0].contains("lit through an opening");
            eprintln!(
                "{name}: lit fraction {f:?}, {}, opening {opening}",
                plan.integrator
            );
            assert_eq!(opening, name.ends_with("door-ajar.gltf"), "{name}: {f:?}");
        }
    }

    /// The hierarchy finds the same first hits as testing every primitive.
    #[test]
    fn the_hierarchy_agrees_with_brute_force() {
        let scene = crate::load("builtin:veach-mis").unwrap();
        let s = Survey::new(&scene);
        let prims = primitives(&s).unwrap();
        let bvh = Bvh::new(prims.clone());
        let mut state = 12345u64;
        let mut next = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 40) as f32 / (1u64 << 24) as f32
        };
        let mut hits = 0;
        for _ in 0..2000 {
            let o = Vec3::new(next(), next(), next()) * 8.0 - 4.0;
            let d = (Vec3::new(next(), next(), next()) * 2.0 - 1.0).normalize_or_zero();
            let brute = prims
                .iter()
                .filter_map(|p| p.hit(o, d, 0.0, f32::INFINITY))
                .fold(f32::INFINITY, f32::min);
            let got = bvh.trace(o, d, 0.0, f32::INFINITY, false).map(|h| h.0);
            match got {
                Some(t) => {
                    hits += 1;
                    assert!((t - brute).abs() <= 1e-4 * brute.max(1.0), "{t} vs {brute}");
                }
                None => assert!(brute.is_infinite(), "missed a hit at {brute}"),
            }
        }
        assert!(hits > 200, "{hits} hits");
    }
}
