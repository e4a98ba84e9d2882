//! KHR_materials_anisotropy away from world-space meshes: the hit carries its shading
//! tangent ([`tessera_render::geometry::SurfacePoint::tangent`]), so an instanced
//! anisotropic mesh shades as its flattened copy does, and a moving one is anisotropic in
//! its frame at the ray's time.

use crate::common::{assert_blocks_agree, block_passes, block_stats, z_critical, Rng};
use crate::instancing::{floor, lumpy_box};
use glam::{Affine3A, Quat, Vec3};
use tessera_farm::FramePlan;
use tessera_render::geometry::{Hit, Primitive, SurfacePoint, NO_INSTANCE};
use tessera_render::integrator::Integrator;
use tessera_render::render::RenderConfig;
use tessera_render::sampling::warp::Frame;
use tessera_render::scene::RenderScene;
use tessera_scene::builtin::look_at_camera;
use tessera_scene::{Anisotropy, GltfMaterial, Instance, Material, Mesh, PunctualLight, Scene};

/// [`lumpy_box`] (smooth normals, so the shading normal varies over a face) with, per face,
/// one tangent along its first edge and a bitangent sign that alternates between faces:
/// the frame the anisotropy direction lives in.
fn brushed_box() -> Mesh {
    let mut mesh = lumpy_box();
    let tangents = mesh
        .indices
        .chunks(2)
        .enumerate()
        .flat_map(|(f, quad)| {
            // Equal corner tangents within a triangle: interpolating then transforming
            // (an instance) and transforming each corner then interpolating (a flattened
            // copy) give the same direction even under non-uniform scale.
            let [a, b, _] = quad[0].map(|i| mesh.positions[i as usize]);
            let t = (b - a)
                .normalize()
                .extend(if f % 2 == 0 { 1.0 } else { -1.0 });
            [[t; 3]; 2]
        })
        .collect();
    mesh.name = "brushed box".into();
    mesh.tangents = Some(tangents);
    mesh
}

/// Brushed metal: anisotropyStrength 0.8 turned by 0.4 rad from the tangent, roughness
/// 0.4 (alpha 0.16 across the direction, 0.70 along it); `strength` 0 is the same metal,
/// isotropic.
fn brushed_metal(strength: f32) -> Material {
    Material::gltf(
        "brushed",
        GltfMaterial {
            base_color: Vec3::new(0.95, 0.8, 0.6),
            metallic: 1.0,
            roughness: 0.4,
            anisotropy: Some(Anisotropy {
                strength,
                rotation: 0.4,
                texture: None,
            }),
            ..GltfMaterial::default()
        },
    )
}

/// Rotations, non-uniform scales and mirrors on a 3 x 3 grid.
fn transforms() -> Vec<Affine3A> {
    let mut rng = Rng(0xa150);
    (0..9)
        .map(|i| {
            let q = Quat::from_axis_angle(rng.dir(), std::f32::consts::TAU * rng.next());
            let mut s = Vec3::splat(0.4) + 0.6 * Vec3::new(rng.next(), rng.next(), rng.next());
            if i % 3 == 1 {
                s.y = -s.y; // mirrored
            }
            let t = Vec3::new((i % 3) as f32 * 1.6 - 1.6, 0.9, (i / 3) as f32 * 1.6 - 1.6);
            Affine3A::from_scale_rotation_translation(s, q, t)
        })
        .collect()
}

/// A grey floor and nine instances of [`brushed_box`] of anisotropy `strength`, lit by a
/// point light and a dim environment.
fn instanced(strength: f32) -> Scene {
    let floor = floor(4.0);
    Scene {
        name: "brushed boxes".into(),
        camera: look_at_camera(
            Vec3::new(0.0, 4.5, 5.5),
            Vec3::new(0.0, 0.6, 0.0),
            Vec3::Y,
            45.0,
        ),
        meshes: vec![floor],
        prototypes: vec![brushed_box()],
        instances: transforms()
            .into_iter()
            .map(|world_from_object| Instance {
                prototype: 0,
                world_from_object,
            })
            .collect(),
        spheres: vec![],
        materials: vec![
            Material::diffuse("floor", Vec3::splat(0.5)),
            brushed_metal(strength),
        ],
        textures: vec![],
        images: vec![],
        warnings: vec![],
        lights: vec![PunctualLight::Point {
            position: Vec3::new(1.5, 5.0, 2.5),
            intensity: Vec3::splat(40.0),
        }],
        environment: Some(Vec3::splat(0.1)),
        environment_map: None,
        default_resolution: (24, 24),
        animated: false,
    }
}

/// A ray from above the boxes toward them.
fn ray(rng: &mut Rng) -> (Vec3, Vec3) {
    let origin = Vec3::new(
        8.0 * rng.next() - 4.0,
        2.5 + 2.0 * rng.next(),
        8.0 * rng.next() - 4.0,
    );
    let target = Vec3::new(
        4.0 * rng.next() - 2.0,
        0.4 + rng.next(),
        4.0 * rng.next() - 2.0,
    );
    (origin, (target - origin).normalize())
}

/// How two scenes' BSDFs compare at the hits of the same rays on the boxes.
#[derive(Debug, Default)]
struct Agreement {
    /// Hits on the same triangle of a box in both scenes.
    hits: usize,
    /// Hits whose tangents differ in direction or bitangent sign.
    tangents_differ: usize,
    /// Evaluations compared (a few directions per hit).
    evals: usize,
    /// Evaluations that differ by more than 0.2% (plus a tiny absolute slack).
    differ: usize,
}

/// Which mesh and triangle a hit is on: its shading mesh's (for an instance, that is its
/// prototype's, stored after the meshes).
fn shading_triangle(_: &RenderScene, _: &Hit, sp: &SurfacePoint) -> (u32, u32) {
    (sp.mesh, sp.tri)
}

/// Which mesh and triangle a hit would be on in `Scene::flattened()`'s copy: instance k's
/// triangles are on mesh `1 + k` (after the floor).
fn flattened_triangle(rs: &RenderScene, hit: &Hit, sp: &SurfacePoint) -> (u32, u32) {
    match hit.primitive {
        Primitive::Triangle { instance, .. } if instance != NO_INSTANCE => {
            (1 + rs.geometry.instances[instance as usize].index, sp.tri)
        }
        _ => (sp.mesh, sp.tri),
    }
}

/// A hit's triangle as [`shading_triangle`] or [`flattened_triangle`] name it.
type TriangleOf = fn(&RenderScene, &Hit, &SurfacePoint) -> (u32, u32);

/// Compares, ray by ray, `a`'s BSDF at its hit on a box (at shutter fraction `time_a`)
/// with `b`'s (at `time_b`) for random incident directions, and the hits' tangents. Hits
/// must be on the same triangle, `a`'s named by `triangle_a`, `b`'s by its shading mesh
/// (rays that hit different ones, at edges, are skipped; so is the floor).
fn compare_bsdfs(
    a: &RenderScene,
    time_a: f32,
    triangle_a: TriangleOf,
    b: &RenderScene,
    time_b: f32,
) -> Agreement {
    let mut rng = Rng(0x7a9e);
    let mut out = Agreement::default();
    for _ in 0..6000 {
        let (origin, d) = ray(&mut rng);
        let (Some(ha), Some(hb)) = (
            a.intersect_at(origin, d, f32::INFINITY, time_a),
            b.intersect_at(origin, d, f32::INFINITY, time_b),
        ) else {
            continue;
        };
        let (sa, sb) = (a.surface(&ha, origin, d), b.surface(&hb, origin, d));
        if triangle_a(a, &ha, &sa) != (sb.mesh, sb.tri) || sa.material != 1 {
            continue;
        }
        out.hits += 1;
        let (ta, tb) = (sa.tangent.truncate(), sb.tangent.truncate());
        let unit = |t: Vec3| t.try_normalize().unwrap_or(Vec3::ZERO);
        if unit(ta).dot(unit(tb)) < 0.9999 || sa.tangent.w != sb.tangent.w {
            out.tangents_differ += 1;
        }
        let (fa, fb) = (Frame::from_normal(sa.ns), Frame::from_normal(sb.ns));
        let (ba, bb) = (a.bsdf(&sa, -d), b.bsdf(&sb, -d));
        for _ in 0..4 {
            let mut wi = rng.dir();
            if wi.dot(sa.ns) < 0.0 {
                wi = -wi;
            }
            let ea = ba.eval(fa.to_local(-d), fa.to_local(wi));
            let eb = bb.eval(fb.to_local(-d), fb.to_local(wi));
            out.evals += 1;
            if (ea - eb).abs().max_element() > 2e-3 * ea.max(eb).max_element() + 1e-5 {
                out.differ += 1;
            }
        }
    }
    eprintln!("{out:?}");
    out
}

#[test]
fn anisotropic_instances_shade_as_their_flattened_copy() {
    let inst = instanced(0.8);
    inst.validate().unwrap();
    let ri = RenderScene::build(&inst, 8, 8).unwrap();
    let rf = RenderScene::build(&inst.flattened(), 8, 8).unwrap();
    assert!(ri.motion_warnings.is_empty(), "{:?}", ri.motion_warnings);
    let same = compare_bsdfs(&ri, 0.0, flattened_triangle, &rf, 0.0);
    assert!(same.hits > 1000, "{same:?}");
    assert_eq!(same.tangents_differ, 0, "{same:?}");
    // Points within a rounding error of where a sharp lobe turns may differ; no more.
    assert!(same.differ * 1000 <= same.evals, "{same:?}");
    // The comparison can fail: the same boxes isotropic differ at most points.
    let iso = RenderScene::build(&instanced(0.0), 8, 8).unwrap();
    let other = compare_bsdfs(&ri, 0.0, shading_triangle, &iso, 0.0);
    assert!(other.differ * 2 >= other.evals, "{other:?}");
}

#[test]
fn instanced_and_flattened_brushed_boxes_render_the_same_image() {
    let (w, h, block) = (24, 24, 4);
    let plan = FramePlan::new(w, h, w, 4, 32).unwrap();
    let settings = RenderConfig {
        integrator: Integrator::Path,
        seed: 5,
        max_depth: 8,
        rr_depth: 3,
        ..RenderConfig::default()
    };
    let blocks = |scene: &Scene| {
        let rs = RenderScene::build(scene, w, h).unwrap();
        block_stats(&block_passes(&rs, &settings, &plan, block))
    };
    let inst = blocks(&instanced(0.8));
    let flat = blocks(&instanced(0.8).flattened());
    assert_blocks_agree("brushed boxes, instanced vs flattened", &inst, &flat);
    // The test has the power to see the anisotropy: the isotropic boxes fail it.
    let iso = blocks(&instanced(0.0));
    let crit = z_critical(0.01, inst.len());
    let worst = inst
        .iter()
        .zip(&iso)
        .filter(|(a, b)| a.1 + b.1 > 0.0)
        .map(|(a, b)| ((a.0 - b.0) / (a.1 + b.1).sqrt()).abs())
        .fold(0.0, f64::max);
    eprintln!("isotropic boxes: max |z| = {worst:.2} (critical {crit:.2})");
    assert!(worst > crit, "{worst}");
}

/// One brushed box as a world-space mesh and one as an instance, and the same scene with
/// both turned and moved: the keys of a shutter over which they move.
fn moving_keys() -> (Scene, Scene) {
    let mut still = instanced(0.8);
    let mut world = brushed_box();
    let place = Affine3A::from_scale_rotation_translation(
        Vec3::new(0.8, 1.1, 0.7),
        Quat::from_rotation_y(0.5),
        Vec3::new(-1.0, 0.9, 0.0),
    );
    world.positions = world
        .positions
        .iter()
        .map(|&p| place.transform_point3(p))
        .collect();
    world.normals = None;
    world.tangents = world.tangents.map(|ts| {
        ts.iter()
            .map(|c| {
                c.map(|t| {
                    place
                        .transform_vector3(t.truncate())
                        .normalize()
                        .extend(t.w)
                })
            })
            .collect()
    });
    still.meshes.push(world);
    still.instances.truncate(2);
    still.instances.remove(0); // keeps a mirrored one
    still.instances[0].world_from_object =
        Affine3A::from_translation(Vec3::new(1.0, 0.0, 0.0)) * still.instances[0].world_from_object;
    let turn =
        Affine3A::from_rotation_translation(Quat::from_rotation_y(0.7), Vec3::new(0.3, 0.1, -0.2));
    let mut moved = still.clone();
    for m in &mut moved.meshes[1..] {
        m.positions = m
            .positions
            .iter()
            .map(|&p| turn.transform_point3(p))
            .collect();
        m.tangents = m.tangents.take().map(|ts| {
            ts.iter()
                .map(|c| c.map(|t| turn.transform_vector3(t.truncate()).extend(t.w)))
                .collect()
        });
    }
    for i in &mut moved.instances {
        i.world_from_object = turn * i.world_from_object;
    }
    (still, moved)
}

#[test]
fn moving_anisotropic_meshes_are_anisotropic_at_the_rays_time() {
    let (still, moved) = moving_keys();
    still.validate().unwrap();
    moved.validate().unwrap();
    assert!(still.instances[0].world_from_object.matrix3.determinant() < 0.0);
    let keys = [still.clone(), moved.clone()];
    let moving = RenderScene::build_in_motion(&still, &keys, 8, 8).unwrap();
    assert_eq!(moving.moving_triangles(), 24);
    assert!(
        moving.motion_warnings.is_empty(),
        "{:?}",
        moving.motion_warnings
    );
    // At the shutter's opening the moving boxes shade as the still ones.
    let at_open = RenderScene::build(&still, 8, 8).unwrap();
    let same = compare_bsdfs(&moving, 0.0, shading_triangle, &at_open, 0.0);
    assert!(same.hits > 500, "{same:?}");
    assert_eq!(same.tangents_differ, 0, "{same:?}");
    assert!(same.differ * 1000 <= same.evals, "{same:?}");
    // At its closing, as the turned ones: the tangent turned with them.
    let at_close = RenderScene::build(&moved, 8, 8).unwrap();
    let same = compare_bsdfs(&moving, 1.0, shading_triangle, &at_close, 0.0);
    assert!(same.hits > 500, "{same:?}");
    assert_eq!(same.tangents_differ, 0, "{same:?}");
    assert!(same.differ * 1000 <= same.evals, "{same:?}");
    // Which a tangent that did not turn would not (the world-space box's, here; the
    // instance's turns with its transform).
    let mut unturned = moved.clone();
    for (m, s) in unturned.meshes.iter_mut().zip(&still.meshes) {
        m.tangents = s.tangents.clone();
    }
    let wrong = RenderScene::build(&unturned, 8, 8).unwrap();
    let other = compare_bsdfs(&moving, 1.0, shading_triangle, &wrong, 0.0);
    assert!(other.tangents_differ * 4 >= other.hits, "{other:?}");
    assert!(other.differ * 5 >= other.evals, "{other:?}");
}
