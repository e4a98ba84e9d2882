//! The wide BVH's kernels against each other, against the scalar kernel and against
//! obvhs' CWBVH traversal that preceded them.

use super::build::{self, BvhBuildStats};
use super::traversal::{traversal_ray, traversal_t};
use super::*;
use obvhs::ray::RayHit;

fn lcg(state: &mut u64) -> f32 {
    *state = state
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    ((*state >> 40) as f32) / (1u64 << 24) as f32
}

/// A bumpy terrain of `2 n²` triangles over `[-1, 1]²` (y up), with a few hundred loose
/// triangles scattered above it, in a shuffled order.
fn terrain(n: usize, seed: u64) -> Vec<TriangleRecord> {
    let h = |x: f32, z: f32| 0.1 * (7.0 * x).sin() * (5.0 * z).cos() + 0.02 * (31.0 * x * z).sin();
    let v = |i: usize, j: usize| {
        let x = -1.0 + 2.0 * i as f32 / n as f32;
        let z = -1.0 + 2.0 * j as f32 / n as f32;
        Vec3::new(x, h(x, z), z)
    };
    let mut tris = Vec::with_capacity(2 * n * n + 500);
    for i in 0..n {
        for j in 0..n {
            let (a, b, c, d) = (v(i, j), v(i + 1, j), v(i + 1, j + 1), v(i, j + 1));
            tris.push([a, c, b]);
            tris.push([a, d, c]);
        }
    }
    let mut s = seed;
    for _ in 0..500 {
        let c = Vec3::new(
            2.0 * lcg(&mut s) - 1.0,
            0.2 + lcg(&mut s),
            2.0 * lcg(&mut s) - 1.0,
        );
        let mut e = || Vec3::new(lcg(&mut s), lcg(&mut s), lcg(&mut s)) * 0.1 - 0.05;
        tris.push([c + e(), c + e(), c + e()]);
    }
    for i in (1..tris.len()).rev() {
        let j = (lcg(&mut s) * (i + 1) as f32) as usize % (i + 1);
        tris.swap(i, j);
    }
    tris.into_iter()
        .enumerate()
        .map(|(i, p)| TriangleRecord {
            p,
            mesh: 0,
            index: i as u32,
            material: 0,
            light: NO_LIGHT,
        })
        .collect()
}

/// Random rays: origins around and inside the terrain's box, directions uniform, some
/// exactly along an axis (with `-0.0` components) and some grazing.
fn rays(count: usize, seed: u64) -> Vec<(Vec3, Vec3)> {
    let mut s = seed;
    (0..count)
        .map(|k| {
            let o = Vec3::new(
                3.0 * lcg(&mut s) - 1.5,
                1.5 * lcg(&mut s) - 0.3,
                3.0 * lcg(&mut s) - 1.5,
            );
            let d = match k % 8 {
                0 => Vec3::new(-0.0, -1.0, 0.0),
                1 => Vec3::new(0.0, -0.02, 1.0).normalize(),
                _ => {
                    let z = 2.0 * lcg(&mut s) - 1.0;
                    let phi = std::f32::consts::TAU * lcg(&mut s);
                    let r = (1.0 - z * z).max(0.0).sqrt();
                    Vec3::new(r * phi.cos(), z, r * phi.sin())
                }
            };
            (o, d)
        })
        .collect()
}

/// The nearest hit as obvhs' CWBVH traversal found it before the wide BVH (the code this
/// module's traversal replaced, kept here as the reference).
fn obvhs_nearest(
    bvh: &obvhs::cwbvh::CwBvh,
    tris: &[TriangleRecord],
    origin: Vec3,
    dir: Vec3,
) -> Option<(f32, u32)> {
    let mut best_t = f32::INFINITY;
    let mut best = None;
    let ray = traversal_ray(origin, dir, best_t);
    let mut hit = RayHit::none();
    with_watertight_ray!(origin, dir, |wt| bvh.ray_traverse(
        ray,
        &mut hit,
        |_, id| {
            match wt.intersect(&tris[id].p, best_t) {
                Some((t, ..)) => {
                    best_t = t;
                    best = Some((t, id as u32));
                    traversal_t(t)
                }
                None => f32::INFINITY,
            }
        }
    ));
    best
}

fn hit_bits(h: Option<Hit>) -> Option<(u32, u32, u32, u32)> {
    h.map(|h| match h.primitive {
        Primitive::Triangle { index, b1, b2, .. } => {
            (h.t.to_bits(), index, b1.to_bits(), b2.to_bits())
        }
        _ => panic!("only triangles here"),
    })
}

#[test]
fn every_kernel_finds_the_scalar_kernels_hits_and_obvhs_hits() {
    let tris = terrain(250, 7);
    assert!(tris.len() > 125_000);
    let mut geometry = Geometry::build(tris.clone(), Vec::new());
    // obvhs' CWBVH of the same binary tree, over the same (leaf-ordered) triangles.
    let obvhs_tris: Vec<obvhs::triangle::Triangle> = tris
        .iter()
        .map(|t| obvhs::triangle::Triangle {
            v0: t.p[0].into(),
            v1: t.p[1].into(),
            v2: t.p[2].into(),
        })
        .collect();
    let cw = build::to_cwbvh(&build::triangles_bvh2(
        &obvhs_tris,
        &mut BvhBuildStats::default(),
    ));
    let cw_tris: Vec<TriangleRecord> = cw
        .primitive_indices
        .iter()
        .map(|&i| tris[i as usize])
        .collect();
    // Stored in the wide BVH's leaf order, each numbered by its place in obvhs' order.
    assert_eq!(geometry.triangles.len(), cw_tris.len());
    assert!((0..cw_tris.len())
        .all(|s| cw_tris[geometry.triangles.id(s) as usize].p == geometry.triangles.positions(s)));

    let rays = rays(40_000, 11);
    geometry.set_isa(Isa::Scalar).unwrap();
    let scalar: Vec<_> = rays
        .iter()
        .map(|&(o, d)| hit_bits(geometry.intersect(o, d, f32::INFINITY)))
        .collect();
    // Shadow rays ending just before the nearest hit and just after it.
    let occlusion = |g: &Geometry, o: Vec3, d: Vec3, h: Option<(u32, u32, u32, u32)>| {
        let t = h.map_or(10.0, |h| f32::from_bits(h.0));
        u8::from(g.occluded(o, d, t * 0.999)) + 2 * u8::from(g.occluded(o, d, t * 1.001))
    };
    let scalar_occluded: Vec<u8> = rays
        .iter()
        .zip(&scalar)
        .map(|(&(o, d), &h)| occlusion(&geometry, o, d, h))
        .collect();
    let hits = scalar.iter().filter(|h| h.is_some()).count();
    assert!(
        hits > rays.len() / 10 && hits < rays.len(),
        "{hits} hits of {}",
        rays.len()
    );
    // Against obvhs: the same t and the same triangle for every ray.
    for (k, &(o, d)) in rays.iter().enumerate() {
        let old = obvhs_nearest(&cw, &cw_tris, o, d);
        let new = scalar[k].map(|h| (f32::from_bits(h.0), geometry.triangles.id(h.1 as usize)));
        assert_eq!(
            old.map(|(t, i)| (t.to_bits(), i)),
            new.map(|(t, i)| (t.to_bits(), i)),
            "ray {k} ({o}, {d}): obvhs {old:?}, wide {new:?}"
        );
    }
    // Every other kernel the CPU has: bit for bit the scalar kernel's answers.
    for isa in Isa::ALL.into_iter().filter(|i| i.available()) {
        geometry.set_isa(isa).unwrap();
        for (k, &(o, d)) in rays.iter().enumerate() {
            assert_eq!(
                hit_bits(geometry.intersect(o, d, f32::INFINITY)),
                scalar[k],
                "{} differs from scalar on ray {k}",
                isa.name()
            );
            let occ = occlusion(&geometry, o, d, scalar[k]);
            assert_eq!(
                occ,
                scalar_occluded[k],
                "{} occlusion on ray {k}",
                isa.name()
            );
            if scalar[k].is_some() {
                assert_eq!(
                    occ,
                    2,
                    "{}: shadow ray {k} before/after its hit",
                    isa.name()
                );
            }
        }
    }
}

#[test]
fn every_box_kernel_computes_the_scalar_kernels_bits_lane_by_lane() {
    use super::kernels::box_test;
    use super::wide::{BoxRay, WideNode, WIDTH};
    let mut s = 19u64;
    let mut entered = 0u32;
    for k in 0..20_000usize {
        let mut node = WideNode::EMPTY;
        for c in 0..WIDTH {
            // Some unused slots, some boxes flat on an axis.
            if k % 5 == 0 && c % 3 == 1 {
                continue;
            }
            for axis in 0..3 {
                let a = 4.0 * lcg(&mut s) - 2.0;
                let w = if (k + c + axis) % 7 == 0 {
                    0.0
                } else {
                    lcg(&mut s)
                };
                node.lo[axis][c] = a;
                node.hi[axis][c] = a + w;
            }
            node.count[c] = 1;
        }
        let axis = k % 3;
        let mut o = [0.0f32; 3].map(|_| 3.0 * lcg(&mut s) - 1.5);
        // Aimed near the centre of child 0 (always used), so that boxes are entered.
        let mut d = [0.0f32; 3];
        for (a, d) in d.iter_mut().enumerate() {
            let centre = 0.5 * (node.lo[a][0] + node.hi[a][0]);
            *d = centre + 0.6 * lcg(&mut s) - 0.3 - o[a];
        }
        // Directions with a zero (or negative zero) component, origins in a box face:
        // infinite reciprocals and `0 * inf = NaN` slabs.
        if k % 3 == 0 {
            d[axis] = if k % 2 == 0 { 0.0 } else { -0.0 };
        }
        if k % 2 == 0 {
            o[axis] = node.lo[axis][0];
        }
        let ray = BoxRay::new(Vec3::from(o), Vec3::from(d));
        let limit = if k % 4 < 2 {
            f32::INFINITY
        } else {
            3.0 * lcg(&mut s)
        };
        let (dist, mask) = box_test(Isa::Scalar, &node, &ray, limit);
        entered += mask.count_ones();
        for isa in Isa::ALL.into_iter().filter(|i| i.available()) {
            let (d2, m2) = box_test(isa, &node, &ray, limit);
            assert_eq!(m2, mask, "{}: node {k}, mask", isa.name());
            for c in (0..WIDTH).filter(|c| mask >> c & 1 == 1) {
                assert_eq!(
                    d2[c].to_bits(),
                    dist[c].to_bits(),
                    "{}: node {k}, child {c}",
                    isa.name()
                );
            }
        }
    }
    // The rays enter a fair share of the boxes (the comparison is not vacuous; about
    // 7,000 with this seed).
    assert!(entered > 5_000, "{entered} boxes entered");
}

#[test]
fn equal_hit_distances_go_to_the_lower_triangle_index() {
    // Eight copies of one triangle: every ray that hits hits all of them at the same t,
    // and the first in the level's order wins, whatever the kernel.
    let p = [
        Vec3::new(-1.0, -1.0, 0.0),
        Vec3::new(1.0, -1.0, 0.0),
        Vec3::new(0.0, 1.0, 0.0),
    ];
    let mut tris: Vec<TriangleRecord> = (0..8)
        .map(|i| TriangleRecord {
            p,
            mesh: 0,
            index: i,
            material: 0,
            light: NO_LIGHT,
        })
        .collect();
    // And a far-away field of others, so the tree has interior nodes.
    tris.extend(terrain(20, 3).into_iter().map(|mut t| {
        for v in &mut t.p {
            *v += Vec3::new(0.0, 0.0, 10.0);
        }
        t
    }));
    let mut g = Geometry::build(tris, Vec::new());
    // Their stored positions, by their numbers (what ties are decided by).
    let mut copies: Vec<u32> = (0..g.triangles.len() as u32)
        .filter(|&i| g.triangles.positions(i as usize) == p)
        .collect();
    copies.sort_by_key(|&i| g.triangles.id(i as usize));
    let first_key = u64::from(g.triangles.id(copies[0] as usize));
    assert_eq!(copies.len(), 8);
    for isa in Isa::ALL.into_iter().filter(|i| i.available()) {
        g.set_isa(isa).unwrap();
        let hit = g
            .intersect(Vec3::new(0.1, 0.0, -1.0), Vec3::Z, f32::INFINITY)
            .unwrap();
        let Primitive::Triangle { index, .. } = hit.primitive else {
            panic!()
        };
        assert_eq!(index, copies[0], "{}", isa.name());
        // With the filter rejecting the first copy, the next one is found.
        let hit = g
            .intersect_where(
                Vec3::new(0.1, 0.0, -1.0),
                Vec3::Z,
                f32::INFINITY,
                0.0,
                |_, key, _, _| key != first_key,
            )
            .unwrap();
        let Primitive::Triangle { index, .. } = hit.primitive else {
            panic!()
        };
        assert_eq!(index, copies[1], "{}", isa.name());
    }
}

#[test]
fn a_kernel_the_cpu_lacks_is_refused_with_its_name() {
    assert!(Isa::parse("scalar").is_ok());
    assert!(Isa::parse("SSE2").is_ok());
    let err = Isa::parse("neon9").unwrap_err();
    assert!(err.contains("unknown"), "{err}");
    for isa in Isa::ALL {
        let r = Isa::parse(isa.name());
        assert_eq!(r.is_ok(), isa.available(), "{r:?}");
        if let Err(e) = r {
            assert!(e.contains("lacks") && e.contains(isa.name()), "{e}");
        }
    }
}

#[test]
fn every_kernel_renders_the_builtin_scenes_and_a_large_one_bit_identically() {
    use crate::render::{render_frame, RenderConfig};
    use crate::scene::RenderScene;
    use tessera_farm::FramePlan;

    let mut scenes: Vec<(String, tessera_scene::Scene)> = tessera_scene::builtin::NAMES
        .iter()
        .map(|n| {
            let name = format!("builtin:{n}");
            let s = tessera_scene::load(&name).unwrap();
            (name, s)
        })
        .collect();
    // The Cornell box with a terrain of 180,000 triangles across it, and a prototype
    // placed three times.
    let mut big = tessera_scene::load("builtin:cornell-box").unwrap();
    let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
    for p in big.meshes.iter().flat_map(|m| &m.positions) {
        lo = lo.min(*p);
        hi = hi.max(*p);
    }
    let ext = hi - lo;
    let n = 300u32;
    let mut positions = Vec::new();
    for i in 0..=n {
        for j in 0..=n {
            let (u, v) = (i as f32 / n as f32, j as f32 / n as f32);
            let bump = 0.04 * ((23.0 * u).sin() * (17.0 * v).cos());
            positions.push(Vec3::new(
                lo.x + ext.x * u,
                lo.y + ext.y * (0.25 + bump),
                lo.z + ext.z * v,
            ));
        }
    }
    let mut indices = Vec::new();
    for i in 0..n {
        for j in 0..n {
            let a = i * (n + 1) + j;
            indices.push([a, a + 1, a + n + 2]);
            indices.push([a, a + n + 2, a + n + 1]);
        }
    }
    let mut terrain_mesh = big.meshes[0].clone();
    terrain_mesh.name = "terrain".into();
    terrain_mesh.positions = positions;
    terrain_mesh.normals = None;
    terrain_mesh.uvs = Vec::new();
    terrain_mesh.tangents = None;
    terrain_mesh.indices = indices;
    big.meshes.push(terrain_mesh);
    let mut proto = big.meshes[0].clone();
    let c = (lo + hi) * 0.5;
    for p in &mut proto.positions {
        *p = (*p - c) * 0.15;
    }
    big.prototypes.push(proto);
    for k in 0..3 {
        big.instances.push(tessera_scene::Instance {
            prototype: big.prototypes.len() as u32 - 1,
            world_from_object: glam::Affine3A::from_rotation_translation(
                glam::Quat::from_rotation_y(0.7 * k as f32),
                c + Vec3::new(ext.x * (0.25 * k as f32 - 0.25), 0.0, 0.0),
            ),
        });
    }
    scenes.push(("cornell-box with a terrain".into(), big));

    for isa in Isa::ALL.into_iter().filter(|i| !i.available()) {
        eprintln!("skipping the {} kernel: this CPU lacks it", isa.name());
    }
    let (w, h) = (40, 30);
    let plan = FramePlan::for_spp(w, h, 8, 16).unwrap();
    let settings = RenderConfig {
        seed: 5,
        ..RenderConfig::default()
    };
    for (name, scene) in &scenes {
        let mut rs = RenderScene::build(scene, w, h).unwrap();
        let mut reference = None;
        for isa in Isa::ALL.into_iter().filter(|i| i.available()) {
            rs.geometry.set_isa(isa).unwrap();
            let img = render_frame(&rs, &settings, &plan, 0, 2, |_, _| {}).image();
            let bits: Vec<u32> = img
                .mean
                .iter()
                .flat_map(|m| m.map(f32::to_bits))
                .chain(
                    img.variance_of_mean
                        .iter()
                        .flat_map(|v| v.map(f32::to_bits)),
                )
                .collect();
            match &reference {
                None => reference = Some(bits),
                Some(r) => assert!(*r == bits, "{name}: {} differs from scalar", isa.name()),
            }
        }
    }
}
