//! Instancing (a prototype stored once, placed by transforms, traced in two levels) against
//! the same scene flattened to world space: the same triangles are hit at the same `t`,
//! surface data agrees, spawned rays do not re-hit their own surface, and the two render
//! the same image within noise.

use crate::common::{image_mean, render, Rng};
use glam::{Affine3A, Quat, Vec3};
use tessera_render::geometry::{Primitive, NO_INSTANCE};
use tessera_render::integrator::{Integrator, MisHeuristic};
use tessera_render::math::offset_ray_origin;
use tessera_render::render::RenderConfig;
use tessera_render::sampling::SamplerKind;
use tessera_render::scene::RenderScene;
use tessera_scene::builtin::look_at_camera;
use tessera_scene::{Instance, Material, Mesh, PunctualLight, Scene};

/// A closed, convex box (12 triangles, counter-clockwise seen from outside), with smooth
/// normals so normal transformation is exercised; instances make it irregular.
pub(crate) fn lumpy_box() -> Mesh {
    let c = [
        [-0.5, -0.5, -0.5],
        [0.5, -0.5, -0.5],
        [0.5, 0.5, -0.5],
        [-0.5, 0.5, -0.5],
        [-0.5, -0.5, 0.5],
        [0.5, -0.5, 0.5],
        [0.5, 0.5, 0.5],
        [-0.5, 0.5, 0.5],
    ]
    .map(Vec3::from);
    let quads = [
        [0, 3, 2, 1],
        [4, 5, 6, 7],
        [0, 1, 5, 4],
        [2, 3, 7, 6],
        [1, 2, 6, 5],
        [0, 4, 7, 3],
    ];
    let mut indices = Vec::new();
    for q in quads {
        indices.push([q[0], q[1], q[2]]);
        indices.push([q[0], q[2], q[3]]);
    }
    Mesh {
        name: "box".into(),
        positions: c.to_vec(),
        normals: Some(c.iter().map(|p| p.normalize()).collect()),
        uvs: vec![],
        tangents: None,
        colors: None,
        indices,
        material: 1,
    }
}

/// Transforms with rotation, non-uniform scale and mirroring, on a 4 x 4 grid.
fn transforms() -> Vec<Affine3A> {
    let mut rng = Rng(0x5eed);
    (0..16)
        .map(|i| {
            let q = Quat::from_axis_angle(rng.dir(), std::f32::consts::TAU * rng.next());
            // At most 0.9 across, so no two boxes (nor a box and the floor) overlap.
            let mut s =
                Vec3::new(0.3, 0.3, 0.3) + 0.6 * Vec3::new(rng.next(), rng.next(), rng.next());
            if i % 3 == 1 {
                s.x = -s.x; // mirrored
            }
            let t = Vec3::new((i % 4) as f32 * 2.0 - 3.0, 1.0, (i / 4) as f32 * 2.0 - 3.0);
            Affine3A::from_scale_rotation_translation(s, q, t)
        })
        .collect()
}

/// A square floor of material 0 at `y = 0`, `half` on each side of the origin, facing up.
pub(crate) fn floor(half: f32) -> Mesh {
    Mesh {
        name: "floor".into(),
        positions: vec![
            Vec3::new(-half, 0.0, -half),
            Vec3::new(half, 0.0, -half),
            Vec3::new(half, 0.0, half),
            Vec3::new(-half, 0.0, half),
        ],
        normals: None,
        uvs: vec![],
        tangents: None,
        colors: None,
        indices: vec![[0, 2, 1], [0, 3, 2]],
        material: 0,
    }
}

/// A floor and 16 instances of [`lumpy_box`], lit by a point light and an environment.
fn instanced() -> Scene {
    let floor = floor(5.0);
    Scene {
        name: "instanced boxes".into(),
        camera: look_at_camera(Vec3::new(0.0, 6.0, 9.0), Vec3::ZERO, Vec3::Y, 45.0),
        meshes: vec![floor],
        prototypes: vec![lumpy_box()],
        instances: transforms()
            .into_iter()
            .map(|world_from_object| Instance {
                prototype: 0,
                world_from_object,
            })
            .collect(),
        spheres: vec![],
        materials: vec![
            Material::diffuse("floor", Vec3::splat(0.6)),
            Material::diffuse("box", Vec3::new(0.7, 0.5, 0.3)),
        ],
        textures: vec![],
        images: vec![],
        warnings: vec![],
        lights: vec![PunctualLight::Point {
            position: Vec3::new(1.0, 6.0, 2.0),
            intensity: Vec3::splat(30.0),
        }],
        environment: Some(Vec3::splat(0.2)),
        environment_map: None,
        default_resolution: (32, 32),
        animated: false,
    }
}

#[test]
fn instanced_rays_hit_the_triangles_a_flattened_copy_does() {
    let inst = instanced();
    let flat = inst.flattened();
    inst.validate().unwrap();
    flat.validate().unwrap();
    let ri = RenderScene::build(&inst, 8, 8).unwrap();
    let rf = RenderScene::build(&flat, 8, 8).unwrap();
    assert_eq!(ri.geometry.instances.len(), 16);
    let mut rng = Rng(0xfeed);
    let (total, mut hits, mut mismatched) = (20000, 0, 0);
    for _ in 0..total {
        let origin = Vec3::new(
            10.0 * rng.next() - 5.0,
            4.0 * rng.next(),
            10.0 * rng.next() - 5.0,
        );
        let target = Vec3::new(
            8.0 * rng.next() - 4.0,
            1.6 * rng.next(),
            8.0 * rng.next() - 4.0,
        );
        let d = (target - origin).normalize();
        let hi = ri.geometry.intersect(origin, d, f32::INFINITY);
        let hf = rf.geometry.intersect(origin, d, f32::INFINITY);
        assert_eq!(ri.geometry.occluded(origin, d, f32::INFINITY), hi.is_some());
        let (Some(hi), Some(hf)) = (hi, hf) else {
            if hi.is_some() != hf.is_some() {
                mismatched += 1;
            }
            continue;
        };
        hits += 1;
        let (si, sf) = (ri.surface(&hi, origin, d), rf.surface(&hf, origin, d));
        // Which triangle: instance k's triangle j is flattened mesh 1 + k, triangle j.
        let same = match (hi.primitive, hf.primitive) {
            (Primitive::Triangle { instance, .. }, Primitive::Triangle { .. })
                if instance != NO_INSTANCE =>
            {
                let k = ri.geometry.instances[instance as usize].index;
                sf.mesh == 1 + k && sf.tri == si.tri
            }
            _ => si.mesh == 0 && sf.mesh == 0 && si.tri == sf.tri,
        };
        if !same {
            mismatched += 1;
            continue;
        }
        // Relative, plus a few ulps of the coordinates for hits right at the origin.
        assert!(
            (hi.t - hf.t).abs() <= 1e-4 * hf.t + 1e-5,
            "t {} vs {}",
            hi.t,
            hf.t
        );
        assert!((si.p - sf.p).length() <= 1e-4, "p {} vs {}", si.p, sf.p);
        assert!(si.ng.dot(sf.ng) > 0.9999, "ng {} vs {}", si.ng, sf.ng);
        assert!(si.ns.dot(sf.ns) > 0.999, "ns {} vs {}", si.ns, sf.ns);
        // The error bound covers the actual error: the exact (double-precision) world
        // point of the same barycentrics on the object-space triangle.
        if let Primitive::Triangle {
            index,
            instance,
            b1,
            b2,
        } = hi.primitive
        {
            if instance != NO_INSTANCE {
                let rec = &ri.geometry.instances[instance as usize];
                let tri = ri.geometry.prototypes[rec.prototype as usize]
                    .triangles
                    .record(index as usize);
                let (b1, b2) = (f64::from(b1), f64::from(b2));
                let b0 = 1.0 - b1 - b2;
                let p = tri.p.map(|v| v.as_dvec3());
                let exact = rec
                    .world_from_object
                    .as_daffine3()
                    .transform_point3(b0 * p[0] + b1 * p[1] + b2 * p[2]);
                let gap = (si.p.as_dvec3() - exact).abs();
                assert!(
                    gap.cmple(si.p_error.as_dvec3()).all(),
                    "error {gap} exceeds the bound {}",
                    si.p_error
                );
            }
        }
    }
    eprintln!("{hits} hits of {total} rays, {mismatched} differ (edge rays)");
    assert!(hits > total / 2);
    assert!(
        mismatched * 1000 <= total,
        "{mismatched} of {total} rays hit different triangles"
    );
}

#[test]
fn rays_spawned_on_instances_do_not_hit_their_own_surface() {
    let s = instanced();
    let rs = RenderScene::build(&s, 8, 8).unwrap();
    let rf = RenderScene::build(&s.flattened(), 8, 8).unwrap();
    let mut rng = Rng(0xabcdef);
    let (mut tested, mut outward_self, mut inward_lost, mut flat_lost_too) = (0, 0, 0, 0);
    for _ in 0..20000 {
        let origin = Vec3::new(
            10.0 * rng.next() - 5.0,
            3.0 + rng.next(),
            10.0 * rng.next() - 5.0,
        );
        let target = Vec3::new(8.0 * rng.next() - 4.0, 1.0, 8.0 * rng.next() - 4.0);
        let d = (target - origin).normalize();
        let Some(hit) = rs.geometry.intersect(origin, d, f32::INFINITY) else {
            continue;
        };
        let Primitive::Triangle { instance, .. } = hit.primitive else {
            continue;
        };
        if instance == NO_INSTANCE {
            continue;
        }
        let sp = rs.surface(&hit, origin, d);
        tested += 1;
        // Out of the convex box, grazing as often as not: never the same instance again.
        let mut w = rng.dir();
        if w.dot(sp.ng) < 0.0 {
            w = -w;
        }
        if rng.next() < 0.5 {
            w = (w - sp.ng * w.dot(sp.ng) * (1.0 - 1e-3)).normalize();
        }
        let o = offset_ray_origin(sp.p, sp.p_error, sp.ng, w);
        if let Some(h2) = rs.geometry.intersect(o, w, f32::INFINITY) {
            if matches!(h2.primitive, Primitive::Triangle { instance: i2, .. } if i2 == instance) {
                outward_self += 1;
            }
        }
        // Into it: the same instance's other side (a closed mesh), wherever the flattened
        // copy finds it too (a point within its error bound of an edge may offset out of
        // the box through the neighbouring face, in either representation).
        let w = -w;
        let o = offset_ray_origin(sp.p, sp.p_error, sp.ng, w);
        match rs.geometry.intersect(o, w, f32::INFINITY) {
            Some(h2) if matches!(h2.primitive, Primitive::Triangle { instance: i2, .. } if i2 == instance) =>
                {}
            _ if rf.geometry.intersect(o, w, f32::INFINITY).is_none() => flat_lost_too += 1,
            other => {
                eprintln!("lost: p {} ng {} w {w} -> {other:?}", sp.p, sp.ng);
                inward_lost += 1
            }
        }
    }
    eprintln!(
        "{tested} points on instances: {outward_self} outward self-hits, {inward_lost} \
         inward rays lost ({flat_lost_too} lost by the flattened copy as well)"
    );
    assert!(tested > 2000);
    assert_eq!(outward_self, 0);
    assert_eq!(inward_lost, 0);
}

#[test]
fn instanced_and_flattened_scenes_render_the_same_image() {
    let inst = instanced();
    let flat = inst.flattened();
    let settings = RenderConfig {
        integrator: Integrator::Path,
        mis: MisHeuristic::Power,
        sampler: SamplerKind::Sobol,
        seed: 3,
        max_depth: 8,
        rr_depth: 3,
    };
    let (w, h, spp) = (32, 32, 64);
    let ai = render(&inst, w, h, spp, &settings);
    let af = render(&flat, w, h, spp, &settings);
    let (ii, fi) = (ai.image(), af.image());
    let mut max_diff = 0.0f32;
    let mut identical = 0;
    for (a, b) in ii.mean.iter().zip(&fi.mean) {
        let d = (0..3).map(|c| (a[c] - b[c]).abs()).fold(0.0, f32::max);
        max_diff = max_diff.max(d);
        identical += usize::from(d == 0.0);
    }
    for c in 0..3 {
        let (mi, si) = image_mean(&ai, c);
        let (mf, sf) = image_mean(&af, c);
        let z = (mi - mf) / (si * si + sf * sf).sqrt();
        eprintln!(
            "channel {c}: instanced {mi:.5} ± {si:.5}, flattened {mf:.5} ± {sf:.5}, z = {z:.2}"
        );
        assert!(z.abs() < 4.0, "channel {c}: {mi} vs {mf}, z = {z}");
        assert!((mi - mf).abs() < 0.02 * mf, "channel {c}: {mi} vs {mf}");
    }
    eprintln!(
        "{identical} of {} pixels bit-identical, largest pixel difference {max_diff}",
        ii.mean.len()
    );
}

#[test]
fn the_triangle_filter_sees_which_instance_was_hit() {
    // Alpha testing calls the filter with a key naming instance and triangle: rejecting
    // the nearest instance's triangles lets the ray through to the next one, for camera
    // and shadow rays alike.
    let s = instanced();
    let rs = RenderScene::build(&s, 8, 8).unwrap();
    let (o, d) = (Vec3::new(-3.0, 1.0, -8.0), Vec3::Z);
    let near = rs.geometry.intersect(o, d, f32::INFINITY).unwrap();
    let Primitive::Triangle { instance, .. } = near.primitive else {
        panic!("expected a triangle")
    };
    assert_ne!(instance, NO_INSTANCE);
    let mine = tessera_render::geometry::triangle_key(instance, 0) >> 32;
    let next = rs
        .geometry
        .intersect_where(o, d, f32::INFINITY, 0.0, |_, key, _, _| key >> 32 != mine)
        .unwrap();
    let Primitive::Triangle { instance: i2, .. } = next.primitive else {
        panic!("expected a triangle")
    };
    assert!(i2 != instance && next.t > near.t, "{next:?} after {near:?}");
    assert!(rs
        .geometry
        .occluded_where(o, d, next.t * 1.01, 0.0, |_, key, _, _| key >> 32 != mine));
    assert!(!rs
        .geometry
        .occluded_where(o, d, next.t * 0.99, 0.0, |_, key, _, _| key >> 32 != mine));
    assert!(!rs
        .geometry
        .occluded_where(o, d, f32::INFINITY, 0.0, |_, key, _, _| key >> 32 == 0));
}

/// The determinism contract across traversal kernels (ARCHITECTURE.md §2) for the two
/// levels: the instanced scene (top level and prototype walked inside one kernel)
/// renders to the same bits with every kernel this CPU has.
#[test]
fn every_kernel_renders_the_instanced_scene_bit_identically() {
    use tessera_farm::FramePlan;
    use tessera_render::geometry::Isa;
    use tessera_render::render::render_frame;
    let (w, h) = (32, 24);
    let mut rs = RenderScene::build(&instanced(), w, h).unwrap();
    assert_eq!(rs.geometry.instances.len(), transforms().len());
    let plan = FramePlan::for_spp(w, h, 16, 16).unwrap();
    let settings = RenderConfig {
        seed: 9,
        ..RenderConfig::default()
    };
    let mut reference = None;
    for isa in Isa::ALL.into_iter().filter(|i| i.available()) {
        rs.geometry.set_isa(isa).unwrap();
        let bits = crate::common::frame_bits(&render_frame(&rs, &settings, &plan, 0, 0, |_, _| {}));
        match &reference {
            None => reference = Some(bits),
            Some(r) => assert!(*r == bits, "{} differs from scalar", isa.name()),
        }
    }
}
