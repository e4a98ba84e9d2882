use super::*;

fn quad_tris(scale: f32) -> Vec<TriangleRecord> {
    // Two triangles sharing the diagonal of a square in the z = 0 plane.
    let s = scale;
    let a = Vec3::new(-s, -s, 0.0);
    let b = Vec3::new(s, -s, 0.0);
    let c = Vec3::new(s, s, 0.0);
    let d = Vec3::new(-s, s, 0.0);
    let rec = |p, i| TriangleRecord {
        p,
        mesh: 0,
        index: i,
        material: 0,
        light: NO_LIGHT,
    };
    vec![rec([a, b, c], 0), rec([a, c, d], 1)]
}

#[test]
fn shared_edges_are_watertight() {
    // Rays aimed exactly at the shared diagonal (and at the shared vertices) of a fan of
    // triangles must hit; a Möller–Trumbore test loses a fraction of these.
    let mut rng = 0x1234_5678_9abc_def0u64;
    let mut next = || {
        rng = rng
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((rng >> 40) as f32) / (1u64 << 24) as f32
    };
    // A fan of 64 triangles around the origin, slightly irregular.
    let n = 64;
    let mut tris = Vec::new();
    let pts: Vec<Vec3> = (0..n)
        .map(|i| {
            let a = i as f32 / n as f32 * std::f32::consts::TAU;
            Vec3::new(a.cos(), a.sin(), 0.1 * (3.0 * a).sin())
        })
        .collect();
    for i in 0..n {
        tris.push(TriangleRecord {
            p: [Vec3::new(0.0, 0.0, 0.05), pts[i], pts[(i + 1) % n]],
            mesh: 0,
            index: i as u32,
            material: 0,
            light: NO_LIGHT,
        });
    }
    let geo = Geometry::build(tris.clone(), vec![]);
    let mut misses = 0;
    let total = 20000;
    for k in 0..total {
        let e = k % n;
        let t = next();
        // A point exactly on edge (centre, pts[e]) computed in float.
        let target = Vec3::new(0.0, 0.0, 0.05) * (1.0 - t) + pts[e] * t;
        let origin = Vec3::new(next() - 0.5, next() - 0.5, 3.0 + next());
        let dir = (target - origin).normalize();
        if geo.intersect(origin, dir, f32::INFINITY).is_none() {
            misses += 1;
        }
    }
    assert_eq!(
        misses, 0,
        "{misses} of {total} rays slipped through shared edges"
    );
}

#[test]
fn a_moving_triangle_is_hit_where_it_stands_at_the_ray_time() {
    // A unit triangle in z = 0 sliding from x = -10 to x = +10 over the shutter,
    // given at 3 keys (2 segments): at time τ its vertices are 20 τ - 10 along x.
    let tri = |dx: f32| {
        [
            Vec3::new(dx - 0.5, -0.5, 0.0),
            Vec3::new(dx + 0.5, -0.5, 0.0),
            Vec3::new(dx, 0.5, 0.0),
        ]
    };
    let record = TriangleRecord {
        p: tri(-10.0),
        mesh: 0,
        index: 0,
        material: 0,
        light: NO_LIGHT,
    };
    let motion = MotionTriangles::new(vec![record], vec![tri(-10.0), tri(0.0), tri(10.0)], 2);
    let geo = Geometry::build(Vec::new(), Vec::new()).with_motion(motion);
    for time in [0.0f32, 0.1, 0.25, 0.5, 0.62, 0.9, 1.0] {
        let x = 20.0 * time - 10.0;
        let origin = Vec3::new(x, -0.2, 5.0);
        let hit = geo
            .intersect_where(origin, -Vec3::Z, f32::INFINITY, time, |_, _, _, _| true)
            .unwrap_or_else(|| panic!("missed the triangle at time {time}"));
        assert!((hit.t - 5.0).abs() < 1e-5, "t {} at time {time}", hit.t);
        assert!(matches!(hit.primitive, Primitive::Moving { index: 0, time: t, .. } if t == time));
        assert!(geo.occluded_where(origin, -Vec3::Z, 10.0, time, |_, _, _, _| true));
        // One unit beside it at that time: nothing; and where it was at other times.
        let beside = Vec3::new(x + 1.2, -0.2, 5.0);
        assert!(geo
            .intersect_where(beside, -Vec3::Z, f32::INFINITY, time, |_, _, _, _| true)
            .is_none());
        let later = (time + 0.3).min(1.0);
        if later - time > 0.1 {
            assert!(!geo.occluded_where(origin, -Vec3::Z, 10.0, later, |_, _, _, _| true));
        }
    }
    // The bounding sphere covers the whole sweep.
    assert!(geo.bounds_radius >= 10.0);
}

#[test]
fn near_hits_below_obvhs_clamp_are_found() {
    for scale in [1e-4f32, 1e-2, 1.0] {
        let geo = Geometry::build(quad_tris(scale), vec![]);
        for dist in [1e-7f32, 1e-6, 1e-5, 5e-5, 9e-5] {
            let d = dist * scale.max(1e-3);
            let origin = Vec3::new(0.1 * scale, 0.2 * scale, d);
            let hit = geo.intersect(origin, -Vec3::Z, f32::INFINITY);
            let hit = hit.unwrap_or_else(|| panic!("missed at distance {d} scale {scale}"));
            assert!((hit.t - d).abs() <= d * 1e-3, "t {} vs {d}", hit.t);
            assert!(geo.occluded(origin, -Vec3::Z, 1.0));
            // t_max just before the surface: no hit.
            assert!(geo.intersect(origin, -Vec3::Z, d * 0.5).is_none());
            assert!(!geo.occluded(origin, -Vec3::Z, d * 0.5));
        }
    }
}

#[test]
fn sphere_intersection_is_accurate_for_tiny_and_distant_spheres() {
    let t = intersect_sphere(
        Vec3::new(0.0, 0.0, -1e4),
        0.01,
        Vec3::ZERO,
        -Vec3::Z,
        f32::INFINITY,
    )
    .unwrap();
    assert!((t - (1e4 - 0.01)).abs() < 2e-3, "{t}");
    let t = intersect_sphere(Vec3::ZERO, 1.0, Vec3::ZERO, Vec3::X, f32::INFINITY).unwrap();
    assert!((t - 1.0).abs() < 1e-6);
    assert!(intersect_sphere(
        Vec3::ZERO,
        1.0,
        Vec3::new(0.0, 2.0, 0.0),
        Vec3::X,
        f32::INFINITY
    )
    .is_none());
}

/// A small pseudo-random generator for the builder tests.
fn lcg(state: &mut u64) -> f32 {
    *state = state
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    ((*state >> 40) as f32) / (1u64 << 24) as f32
}

fn record(p: [Vec3; 3], i: u32) -> TriangleRecord {
    TriangleRecord {
        p,
        mesh: 0,
        index: i,
        material: 0,
        light: NO_LIGHT,
    }
}

/// `n` small triangles scattered in the unit cube.
fn scattered(n: usize, seed: u64) -> Vec<TriangleRecord> {
    let mut s = seed;
    (0..n)
        .map(|i| {
            let c = Vec3::new(lcg(&mut s), lcg(&mut s), lcg(&mut s));
            let d = |s: &mut u64| Vec3::new(lcg(s) - 0.5, lcg(s) - 0.5, lcg(s) - 0.5) * 0.05;
            record([c + d(&mut s), c + d(&mut s), c + d(&mut s)], i as u32)
        })
        .collect()
}

/// Every stored triangle's attributes, worked out from its place and the level's runs,
/// are those of the record it was built from, whatever the records say: meshes of
/// consecutive triangles (one run each), emissive meshes with a triangle that is no light
/// in the middle, attributes that jump from triangle to triangle, and indices and lights
/// next to `u32::MAX`, where the run's additions wrap.
#[test]
fn stored_attributes_are_the_records_given() {
    let mut tris = scattered(4000, 23);
    let mut s = 5u64;
    let mut light = 0u32;
    for (i, r) in tris.iter_mut().enumerate() {
        let (block, k) = (i / 500, (i % 500) as u32);
        (r.mesh, r.index, r.material, r.light) = match block {
            // Plain meshes, one run each.
            0 | 1 => (block as u32, k, 3, NO_LIGHT),
            // An emissive mesh whose triangle 200 is no light (degenerate): the lights
            // after it are numbered on without a gap.
            2 => (2, k, 4, if k == 200 { NO_LIGHT } else { light }),
            // Everything drawn at random.
            3 => (
                (lcg(&mut s) * 7.0) as u32,
                (lcg(&mut s) * 1e6) as u32,
                (lcg(&mut s) * 5.0) as u32,
                if lcg(&mut s) < 0.5 {
                    NO_LIGHT
                } else {
                    (lcg(&mut s) * 1e6) as u32
                },
            ),
            // Counting up past `u32::MAX - 1`; the light reaches `NO_LIGHT`'s bits.
            4 => (9, (u32::MAX - 250).wrapping_add(k), 1, NO_LIGHT),
            5 => (10, k, 1, (u32::MAX - 499).wrapping_add(k)),
            // One triangle per mesh.
            _ => (100 + i as u32, 0, i as u32 % 3, NO_LIGHT),
        };
        if block == 2 && k != 200 {
            light += 1;
        }
    }
    let by_position: std::collections::HashMap<[u32; 9], TriangleRecord> =
        tris.iter().map(|r| (bits(&r.p), *r)).collect();
    assert_eq!(
        by_position.len(),
        tris.len(),
        "positions identify the records"
    );
    let g = Geometry::build(tris.clone(), vec![]);
    assert_eq!(g.triangles.len(), tris.len());
    let mut seen = std::collections::HashSet::new();
    for got in g.triangles.iter() {
        let want = by_position[&bits(&got.p)];
        assert_eq!(got.attributes(), want.attributes(), "{:?}", got.p);
        assert!(seen.insert(bits(&got.p)));
    }
    // The plain and wrapping meshes are a run each, the emissive one three (before, at
    // and after its dark triangle), the random block and the one-triangle meshes a run a
    // triangle: 2 + 3 + 500 + 2 + 1000.
    assert_eq!(g.triangles.runs(), 1507);
    let uniform = Geometry::build(scattered(4000, 23), vec![]);
    assert_eq!(uniform.triangles.runs(), 1);
    // Per triangle: 36 bytes of corners, the number and the place; the one run is noise.
    assert!(uniform.triangles.bytes() - 4000 * 44 < 64);
}

fn bits(p: &[Vec3; 3]) -> [u32; 9] {
    let f = p.map(|v| v.to_array()).concat();
    std::array::from_fn(|i| f[i].to_bits())
}

#[test]
fn ordinary_geometry_takes_the_unclustered_path() {
    let geo = Geometry::build(scattered(5000, 7), vec![]);
    let stats = geo.build_stats();
    assert_eq!(stats.clustered, 0, "{stats:?}");
    assert_eq!(stats.ploc_inputs, 5000);
    assert_eq!(stats.max_depth, 0);
}

/// The nearest hit by testing every triangle (the reference for the BVH).
fn brute_force(tris: &[TriangleRecord], origin: Vec3, dir: Vec3) -> Option<f32> {
    let mut best = f32::INFINITY;
    with_watertight_ray!(origin, dir, |wt| {
        for t in tris {
            if let Some((h, ..)) = wt.intersect(&t.p, best) {
                best = h;
            }
        }
    });
    best.is_finite().then_some(best)
}

#[test]
fn clustered_trees_find_the_same_nearest_hits_as_brute_force() {
    // Scattered triangles, plus two crowds of coincident copies (one inside the scatter,
    // one beside it): the top of the tree is PLOC's, the crowds are grafted subtrees.
    let mut tris = scattered(3000, 11);
    let crowd = [
        Vec3::new(0.4, 0.4, 0.5),
        Vec3::new(0.6, 0.4, 0.5),
        Vec3::new(0.5, 0.6, 0.5),
    ];
    for _ in 0..500 {
        tris.push(record(crowd, tris.len() as u32));
    }
    let far = crowd.map(|p| p + Vec3::new(3.0, 0.0, 0.0));
    for _ in 0..CLUSTER_MIN {
        tris.push(record(far, tris.len() as u32));
    }
    let geo = Geometry::build(tris.clone(), vec![]);
    let stats = geo.build_stats();
    assert_eq!(stats.clusters, 2, "{stats:?}");
    assert_eq!(stats.clustered, 500 + CLUSTER_MIN as u64);
    assert_eq!(
        geo.triangles.len(),
        tris.len(),
        "every triangle is in a leaf"
    );
    let mut s = 99u64;
    let mut hits = 0;
    for k in 0..600 {
        let target = if k % 3 == 0 {
            Vec3::new(0.5, 0.45, 0.5) + (k % 2) as f32 * Vec3::new(3.0, 0.0, 0.0)
        } else {
            Vec3::new(lcg(&mut s), lcg(&mut s), lcg(&mut s))
        };
        let origin = Vec3::new(lcg(&mut s) * 4.0 - 1.0, lcg(&mut s) * 2.0 - 0.5, 3.0);
        let dir = (target - origin).normalize();
        let want = brute_force(&tris, origin, dir);
        let got = geo.intersect(origin, dir, f32::INFINITY).map(|h| h.t);
        assert_eq!(got, want, "ray {k}");
        hits += usize::from(got.is_some());
    }
    assert!(hits > 300, "{hits} hits");
}

#[test]
fn coincident_triangles_build_a_shallow_tree_in_n_log_n_work() {
    let p = [Vec3::ZERO, Vec3::X, Vec3::Y];
    for n in [1000usize, 20_000] {
        let geo = Geometry::build((0..n as u32).map(|i| record(p, i)).collect(), vec![]);
        let stats = geo.build_stats();
        let log = u64::from(usize::BITS - (n - 1).leading_zeros());
        assert_eq!(stats.clustered, n as u64, "{stats:?}");
        assert!(stats.work <= 2 * n as u64 * log + 6 * n as u64, "{stats:?}");
        assert!(u64::from(stats.max_depth) <= log + 1, "{stats:?}");
        let hit = geo.intersect(Vec3::new(0.2, 0.2, 1.0), -Vec3::Z, f32::INFINITY);
        assert!((hit.expect("the triangle is hit").t - 1.0).abs() < 1e-6);
    }
}

/// A row of `n` identical triangles at exactly even spacing (powers of two, so every
/// neighbour's union box has the same surface area): the input whose ties made obvhs'
/// PLOC quadratic without any crowded cell.
fn even_row(n: usize) -> Vec<TriangleRecord> {
    (0..n as u32)
        .map(|i| {
            let x = i as f32 * 0.015625;
            let p = [
                Vec3::new(x, 0.0, 0.0),
                Vec3::new(x + 0.0078125, 0.0, 0.0),
                Vec3::new(x, 0.0078125, 0.0),
            ];
            record(p, i)
        })
        .collect()
}

#[test]
fn an_evenly_spaced_row_of_identical_triangles_builds_a_shallow_tree() {
    for n in [TIE_MIN, 20_000] {
        let tris = even_row(n);
        let geo = Geometry::build(tris.clone(), vec![]);
        let stats = geo.build_stats();
        let log = u64::from(usize::BITS - (n - 1).leading_zeros());
        assert_eq!(stats.clustered, 0, "{stats:?}");
        assert_eq!(stats.tie_broken, n as u64, "{stats:?}");
        // A chain (the quadratic build) would be n deep; PLOC's ordinary trees are
        // within a small multiple of log2 n.
        assert!(u64::from(stats.max_depth) <= 3 * log, "{stats:?}");
        assert!(stats.work <= 2 * n as u64 * log + 6 * n as u64, "{stats:?}");
        // The widened boxes keep every triangle reachable: rays straight down onto
        // triangles along the row (and between them) agree with brute force.
        let mut s = 5u64;
        for k in 0..400 {
            let x = lcg(&mut s) * n as f32 * 0.015625;
            let y = lcg(&mut s) * 0.01;
            let origin = Vec3::new(x, y, 1.0 + k as f32 * 1e-3);
            let want = brute_force(&tris, origin, -Vec3::Z);
            let got = geo.intersect(origin, -Vec3::Z, f32::INFINITY).map(|h| h.t);
            assert_eq!(got, want, "ray {k} at x {x}");
        }
    }
}

#[test]
fn tie_break_margins_are_small_positive_and_deterministic() {
    let b = obvhs::aabb::Aabb::new(glam::Vec3A::ZERO, glam::Vec3A::new(2.0, 1.0, 0.0));
    let mut distinct = std::collections::BTreeSet::new();
    for i in 0..4096u32 {
        let d = build::tie_break_pad(&b, i);
        assert!(
            d >= 2.0 / (1u32 << 18) as f32 && d <= 2.0 / (1u32 << 10) as f32,
            "{d}"
        );
        assert_eq!(d, build::tie_break_pad(&b, i));
        distinct.insert(d.to_bits());
    }
    // 256 levels, nearly all used: neighbours rarely tie.
    assert!(distinct.len() > 250, "{}", distinct.len());
    let point = obvhs::aabb::Aabb::new(glam::Vec3A::splat(-8.0), glam::Vec3A::splat(-8.0));
    assert!(build::tie_break_pad(&point, 0) > 0.0);
}

/// The triangle build hands PLOC its leaves directly (no array of boxes beside them, see
/// "Memory" in `build`): the tree must be the one obvhs' own `PlocBuilder::build` and
/// reinsertion make of the same boxes, node for node, or the leaf order, the keys and so
/// the images would change.
#[test]
fn ploc_on_leaves_makes_obvhs_own_tree_node_for_node() {
    use obvhs::bvh2::reinsertion::ReinsertionOptimizer;
    use obvhs::ploc::PlocBuilder;
    for (n, seed) in [(1usize, 1u64), (2, 2), (37, 3), (4096, 4), (60_000, 5)] {
        let tris: Vec<obvhs::triangle::Triangle> = scattered(n, seed)
            .iter()
            .map(|t| obvhs::triangle::Triangle {
                v0: t.p[0].into(),
                v1: t.p[1].into(),
                v2: t.p[2].into(),
            })
            .collect();
        let ours = build::triangles_bvh2(&tris, &mut BvhBuildStats::default());
        let p = obvhs::BvhBuildParams::medium_build();
        let mut theirs = PlocBuilder::with_capacity(n).build(
            p.ploc_search_distance,
            &tris,
            (0..n as u32).collect(),
            p.sort_precision,
            p.search_depth_threshold,
        );
        ReinsertionOptimizer::default().run(&mut theirs, p.reinsertion_batch_ratio, None);
        let bits = |b: &obvhs::bvh2::Bvh2| -> Vec<[u32; 8]> {
            b.nodes
                .iter()
                .map(|node| {
                    let (lo, hi) = (node.aabb().min, node.aabb().max);
                    [
                        lo.x.to_bits(),
                        lo.y.to_bits(),
                        lo.z.to_bits(),
                        hi.x.to_bits(),
                        hi.y.to_bits(),
                        hi.z.to_bits(),
                        node.prim_count,
                        node.first_index,
                    ]
                })
                .collect()
        };
        assert_eq!(bits(&ours), bits(&theirs), "{n} triangles: nodes");
        assert_eq!(
            ours.primitive_indices, theirs.primitive_indices,
            "{n} triangles: leaf indices"
        );
    }
}

/// [`Geometry::build_instanced_of`] reads the triangles through a function instead of a
/// `Vec`: the same records in the same leaf order as [`Geometry::build`], the same
/// bounds, the same hits.
#[test]
fn triangles_read_through_a_function_build_the_same_geometry() {
    let tris = scattered(3000, 11);
    let spheres = vec![SphereRecord {
        center: Vec3::new(2.0, 0.5, 0.5),
        radius: 0.25,
        material: 0,
        light: NO_LIGHT,
    }];
    let a = Geometry::build(tris.clone(), spheres.clone());
    let reads = std::sync::atomic::AtomicUsize::new(0);
    let b = Geometry::build_instanced_of(
        tris.len(),
        |i| {
            reads.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            tris[i]
        },
        spheres,
        Vec::new(),
        &[],
    );
    // Each record is read a bounded number of times (bounds, boxes, leaf order).
    assert_eq!(reads.into_inner(), 3 * tris.len());
    assert_eq!(a.triangles.len(), b.triangles.len());
    for s in 0..a.triangles.len() {
        let (x, y) = (a.triangles.record(s), b.triangles.record(s));
        assert_eq!((x.p, x.index), (y.p, y.index));
        assert_eq!(a.triangles.id(s), b.triangles.id(s));
    }
    assert_eq!(a.bounds_center, b.bounds_center);
    assert_eq!(a.bounds_radius.to_bits(), b.bounds_radius.to_bits());
    assert_eq!(a.bytes(), b.bytes());
    let mut s = 99u64;
    for _ in 0..2000 {
        let o = Vec3::new(lcg(&mut s), lcg(&mut s), -1.0);
        let d = (Vec3::new(lcg(&mut s), lcg(&mut s), 1.0) - o).normalize();
        let (ha, hb) = (
            a.intersect(o, d, f32::INFINITY),
            b.intersect(o, d, f32::INFINITY),
        );
        assert_eq!(
            ha.map(|h| h.t.to_bits()),
            hb.map(|h| h.t.to_bits()),
            "{o} {d}"
        );
    }
}

/// [`build::cwbvh_order`] lists the primitives in the order of obvhs' CWBVH of the same
/// binary tree (`to_cwbvh(..).primitive_indices`), which numbers the triangles: on
/// ordinary trees of several sizes, a clustered one (coincident triangles beside
/// scattered ones) and a tie-broken one (an evenly spaced row).
#[test]
fn the_compact_leaf_order_is_obvhs_cwbvh_order() {
    let coincident = {
        let mut t = scattered(3000, 21);
        let p = [Vec3::ZERO, Vec3::X, Vec3::Y];
        t.extend((0..500u32).map(|i| record(p, 3000 + i)));
        t
    };
    let inputs = [
        ("one", scattered(1, 1)),
        ("two", scattered(2, 2)),
        ("three", scattered(3, 3)),
        ("a hundred", scattered(100, 4)),
        ("scattered", scattered(20_000, 5)),
        ("coincident", coincident),
        ("an even row", even_row(TIE_MIN + 7)),
    ];
    for (name, tris) in inputs {
        let tris: Vec<obvhs::triangle::Triangle> = tris
            .iter()
            .map(|t| obvhs::triangle::Triangle {
                v0: t.p[0].into(),
                v1: t.p[1].into(),
                v2: t.p[2].into(),
            })
            .collect();
        let mut stats = BvhBuildStats::default();
        let bvh2 = build::triangles_bvh2(&tris, &mut stats);
        let ours = build::cwbvh_order(&bvh2);
        let theirs = build::to_cwbvh(&bvh2).primitive_indices;
        assert_eq!(ours.len(), tris.len(), "{name}");
        assert_eq!(ours, theirs, "{name}: {stats:?}");
    }
}

/// Every kernel this CPU runs.
fn available_kernels() -> Vec<Isa> {
    Isa::ALL.into_iter().filter(|i| i.available()).collect()
}

/// A hit as bits: `t`, what was hit (kind, index, instance), barycentrics.
fn bits_of(h: Option<Hit>) -> Option<(u32, u32, u32, u32, u32, u32)> {
    h.map(|h| {
        let (kind, index, instance, b1, b2) = match h.primitive {
            Primitive::Triangle {
                index,
                instance,
                b1,
                b2,
            } => (0, index, instance, b1, b2),
            Primitive::Moving { index, b1, b2, .. } => (1, index, 0, b1, b2),
            Primitive::Sphere { index } => (2, index, 0, 0.0, 0.0),
        };
        (
            h.t.to_bits(),
            kind,
            index,
            instance,
            b1.to_bits(),
            b2.to_bits(),
        )
    })
}

/// A random rotation, non-uniform scale (mirrored when `mirror`) and translation.
fn random_transform(s: &mut u64, mirror: bool) -> Affine3A {
    let axis = Vec3::new(lcg(s) - 0.5, lcg(s) - 0.5, lcg(s) - 0.5).normalize_or(Vec3::Y);
    let rotation = glam::Quat::from_axis_angle(axis, 6.0 * lcg(s));
    let mut scale = Vec3::new(0.5 + lcg(s), 0.5 + lcg(s), 0.5 + lcg(s));
    if mirror {
        scale.x = -scale.x;
    }
    let t = Vec3::new(8.0 * lcg(s) - 4.0, 8.0 * lcg(s) - 4.0, 8.0 * lcg(s) - 4.0);
    Affine3A::from_scale_rotation_translation(scale, rotation, t)
}

/// The nearest hit over every instance by testing every triangle of each, with the
/// object-space ray the geometry computes: the lexicographic minimum of
/// `(t, instance, triangle number)` (the rule in the module docs), as `(t, instance,
/// stored position)`.
fn instances_brute_force(g: &Geometry, origin: Vec3, dir: Vec3) -> Option<(f32, u32, u32)> {
    let mut best: Option<(f32, u32, u32, u32)> = None;
    for (id, inst) in g.instances.iter().enumerate() {
        let o = inst.object_from_world.transform_point3(origin);
        let d = inst.object_from_world.transform_vector3(dir);
        let tris = &g.prototypes[inst.prototype as usize].triangles;
        with_watertight_ray!(o, d, |wt| {
            for (i, tri) in tris.iter().enumerate() {
                if let Some((t, ..)) = wt.intersect(&tri.p, f32::INFINITY) {
                    let cand = (t, id as u32, tris.id(i), i as u32);
                    if best.is_none_or(|b| (cand.0, cand.1, cand.2) < (b.0, b.1, b.2)) {
                        best = Some(cand);
                    }
                }
            }
        });
    }
    best.map(|(t, instance, _, i)| (t, instance, i))
}

#[test]
fn instances_give_the_brute_force_nearest_hit_on_every_kernel() {
    // 300 placements of two prototypes (rotated, scaled, some mirrored), eight of them
    // at one place (their hits tie: the lowest instance must win), no world triangles.
    let mut s = 41u64;
    let small: Vec<TriangleRecord> = scattered(60, 3)
        .into_iter()
        .map(|mut t| {
            t.p = t.p.map(|p| p - Vec3::splat(0.5));
            t
        })
        .collect();
    let prototypes = vec![small, quad_tris(0.4)];
    let mut instances: Vec<(u32, Affine3A)> = (0..292)
        .map(|k| (k % 2, random_transform(&mut s, k % 5 == 0)))
        .collect();
    let twin = random_transform(&mut s, false);
    instances.extend((0..8).map(|_| (1, twin)));
    let mut g = Geometry::build_instanced(Vec::new(), Vec::new(), prototypes, &instances);
    assert_eq!(g.instances.len(), 300);
    let rays: Vec<(Vec3, Vec3)> = (0..3000)
        .map(|k| {
            let o = Vec3::new(14.0 * lcg(&mut s) - 7.0, 14.0 * lcg(&mut s) - 7.0, 9.0);
            // A third aimed at the coincident copies, the others anywhere below.
            let target = if k % 3 == 0 {
                twin.transform_point3(Vec3::new(
                    0.7 * lcg(&mut s) - 0.35,
                    0.7 * lcg(&mut s) - 0.35,
                    0.0,
                ))
            } else {
                Vec3::new(10.0 * lcg(&mut s) - 5.0, 10.0 * lcg(&mut s) - 5.0, -5.0)
            };
            (o, (target - o).normalize())
        })
        .collect();
    let mut reference = Vec::new();
    let (mut hits, mut twins) = (0, 0);
    for (k, &(o, d)) in rays.iter().enumerate() {
        let want = instances_brute_force(&g, o, d);
        let got = g.intersect(o, d, f32::INFINITY);
        let got_key = got.map(|h| match h.primitive {
            Primitive::Triangle {
                index, instance, ..
            } => (h.t, instance, index),
            _ => panic!("only instances here"),
        });
        assert_eq!(
            got_key.map(|(t, i, j)| (t.to_bits(), i, j)),
            want.map(|(t, i, j)| (t.to_bits(), i, j)),
            "ray {k}"
        );
        hits += usize::from(want.is_some());
        twins += usize::from(
            want.is_some_and(|(_, i, _)| g.instances[i as usize].world_from_object == twin),
        );
        let t = got.map_or(30.0, |h| h.t);
        reference.push((
            bits_of(got),
            g.occluded(o, d, t * 0.999),
            g.occluded(o, d, t * 1.001),
        ));
    }
    assert!(
        hits > 1000 && twins > 300,
        "{hits} hits, {twins} on the copies"
    );
    for isa in available_kernels() {
        g.set_isa(isa).unwrap();
        for (k, &(o, d)) in rays.iter().enumerate() {
            let got = g.intersect(o, d, f32::INFINITY);
            let t = got.map_or(30.0, |h| h.t);
            let answer = (
                bits_of(got),
                g.occluded(o, d, t * 0.999),
                g.occluded(o, d, t * 1.001),
            );
            assert_eq!(answer, reference[k], "{}: ray {k}", isa.name());
            assert!(!answer.1, "{}: ray {k} occluded before its hit", isa.name());
            assert_eq!(answer.2, got.is_some(), "{}: ray {k}", isa.name());
        }
    }
}

#[test]
fn moving_triangles_give_the_brute_force_nearest_hit_on_every_kernel() {
    // 400 triangles moving along random paths over 3 segments, four of them identical
    // (their hits tie: the lowest record must win).
    let mut s = 17u64;
    let segments = 3u32;
    let mut records = Vec::new();
    let mut keys = Vec::new();
    for (i, r) in scattered(400, 23).into_iter().enumerate() {
        let twin = i % 100 == 7;
        let mut p = if twin {
            [Vec3::ZERO, Vec3::X, Vec3::Y]
        } else {
            r.p
        };
        records.push(record(p, i as u32));
        for _ in 0..=segments {
            keys.push(p);
            if !twin {
                let step = Vec3::new(lcg(&mut s) - 0.5, lcg(&mut s) - 0.5, lcg(&mut s) - 0.5);
                p = p.map(|v| v + 0.3 * step);
            }
        }
    }
    let motion = MotionTriangles::new(records, keys, segments);
    let mut g = Geometry::build(Vec::new(), Vec::new()).with_motion(motion);
    let m = g.motion.as_ref().unwrap();
    let rays: Vec<(Vec3, Vec3, f32)> = (0..3000)
        .map(|k| {
            let o = Vec3::new(3.0 * lcg(&mut s) - 1.0, 3.0 * lcg(&mut s) - 1.0, 4.0);
            let target = if k % 4 == 0 {
                Vec3::new(0.3 * lcg(&mut s), 0.3 * lcg(&mut s), 0.0)
            } else {
                Vec3::new(2.0 * lcg(&mut s) - 0.5, 2.0 * lcg(&mut s) - 0.5, 0.5)
            };
            // Key times (segment ends) among the random ones.
            let time = if k % 10 == 0 {
                (k % 4) as f32 / 3.0
            } else {
                lcg(&mut s)
            };
            (o, (target - o).normalize(), time)
        })
        .collect();
    let brute = |o: Vec3, d: Vec3, time: f32| {
        let mut best: Option<(f32, u32)> = None;
        with_watertight_ray!(o, d, |wt| {
            for r in 0..m.records.len() {
                if let Some((t, ..)) = wt.intersect(&m.positions_at(r, time), f32::INFINITY) {
                    if best.is_none_or(|b| (t, r as u32) < b) {
                        best = Some((t, r as u32));
                    }
                }
            }
        });
        best
    };
    let mut reference = Vec::new();
    let (mut hits, mut twins) = (0, 0);
    for (k, &(o, d, time)) in rays.iter().enumerate() {
        let want = brute(o, d, time);
        let got = g.intersect_where(o, d, f32::INFINITY, time, |_, _, _, _| true);
        let got_key = got.map(|h| match h.primitive {
            Primitive::Moving { index, .. } => (h.t.to_bits(), index),
            _ => panic!("only moving triangles here"),
        });
        assert_eq!(got_key, want.map(|(t, r)| (t.to_bits(), r)), "ray {k}");
        hits += usize::from(want.is_some());
        twins += usize::from(want.is_some_and(|(_, r)| r % 100 == 7));
        let t = got.map_or(30.0, |h| h.t);
        let occ = |t_max: f32| g.occluded_where(o, d, t_max, time, |_, _, _, _| true);
        reference.push((bits_of(got), occ(t * 0.999), occ(t * 1.001)));
    }
    assert!(
        hits > 500 && twins > 100,
        "{hits} hits, {twins} on the copies"
    );
    for isa in available_kernels() {
        g.set_isa(isa).unwrap();
        for (k, &(o, d, time)) in rays.iter().enumerate() {
            let got = g.intersect_where(o, d, f32::INFINITY, time, |_, _, _, _| true);
            let t = got.map_or(30.0, |h| h.t);
            let occ = |t_max: f32| g.occluded_where(o, d, t_max, time, |_, _, _, _| true);
            let answer = (bits_of(got), occ(t * 0.999), occ(t * 1.001));
            assert_eq!(answer, reference[k], "{}: ray {k}", isa.name());
            assert!(!answer.1, "{}: ray {k} occluded before its hit", isa.name());
            assert_eq!(answer.2, got.is_some(), "{}: ray {k}", isa.name());
        }
    }
}

/// The cases obvhs 0.4's own traversal got wrong, now through our kernels for instances
/// and moving triangles too: a hit (so a box) within its `1e-4` clamp of the origin, and
/// directions with `-0.0` components (`-Vec3::Z` is `(-0.0, -0.0, -1.0)`).
#[test]
fn near_hits_and_negative_zero_directions_through_instances_and_motion() {
    for scale in [1e-4f32, 1e-2, 1.0] {
        // The quad placed twice (so the top level has a node to prune), and once more
        // as a triangle pair that slides a little along x over the shutter.
        // Moved in x and y only, so the surface stays at z = 0 and the origin's z is
        // the distance exactly (as in the test above).
        let place = Vec3::new(3.0, -2.0, 0.0) * scale;
        let far = Affine3A::from_translation(Vec3::new(50.0, 0.0, 0.0) * scale);
        let instanced = Geometry::build_instanced(
            Vec::new(),
            Vec::new(),
            vec![quad_tris(scale)],
            &[(0, Affine3A::from_translation(place)), (0, far)],
        );
        let quad = quad_tris(scale);
        let keys: Vec<[Vec3; 3]> = quad
            .iter()
            .flat_map(|t| {
                [0.0, 0.1].map(|dx| t.p.map(|p| p + place + Vec3::new(dx * scale, 0.0, 0.0)))
            })
            .collect();
        let moving = Geometry::build(Vec::new(), Vec::new())
            .with_motion(MotionTriangles::new(quad, keys, 1));
        for (name, mut g) in [("instance", instanced), ("moving", moving)] {
            for isa in available_kernels() {
                g.set_isa(isa).unwrap();
                for dist in [1e-7f32, 1e-6, 1e-5, 5e-5, 9e-5] {
                    let d = dist * scale.max(1e-3);
                    let origin = place + Vec3::new(0.1 * scale, 0.2 * scale, d);
                    for dir in [-Vec3::Z, Vec3::new(0.0, 0.0, -1.0)] {
                        let at = |t_max: f32| {
                            g.intersect_where(origin, dir, t_max, 0.5, |_, _, _, _| true)
                        };
                        let what = format!("{name}, {}, distance {d} scale {scale}", isa.name());
                        let hit = at(f32::INFINITY).unwrap_or_else(|| panic!("missed: {what}"));
                        assert!((hit.t - d).abs() <= d * 1e-3, "t {} vs {d}: {what}", hit.t);
                        assert!(g.occluded_where(origin, dir, 1.0, 0.5, |_, _, _, _| true));
                        // t_max just before the surface: no hit.
                        assert!(at(d * 0.5).is_none(), "{what}");
                        assert!(!g.occluded_where(origin, dir, d * 0.5, 0.5, |_, _, _, _| true));
                    }
                }
            }
        }
    }
}

#[test]
fn on_equal_t_the_earlier_level_wins_and_the_filter_sees_past_it() {
    // One quad as a world-space pair, as two instances of a prototype at the identity
    // (their rays are the world ray bit for bit) and as moving triangles that stand
    // still: every hit ties. World first, then the lower instance, then the moving one.
    let quad = quad_tris(1.0);
    let keys: Vec<[Vec3; 3]> = quad.iter().flat_map(|t| [t.p, t.p]).collect();
    let mut g = Geometry::build_instanced(
        quad.clone(),
        Vec::new(),
        vec![quad.clone()],
        &[(0, Affine3A::IDENTITY), (0, Affine3A::IDENTITY)],
    )
    .with_motion(MotionTriangles::new(quad, keys, 1));
    let (o, d) = (Vec3::new(0.3, -0.2, 2.0), -Vec3::Z);
    for isa in available_kernels() {
        g.set_isa(isa).unwrap();
        let mut rejected: Vec<u64> = Vec::new();
        let mut seen = Vec::new();
        loop {
            let hit = g.intersect_where(o, d, f32::INFINITY, 0.3, |_, key, _, _| {
                !rejected.contains(&key)
            });
            let Some(hit) = hit else { break };
            assert!((hit.t - 2.0).abs() < 1e-6, "{}", isa.name());
            let key = match hit.primitive {
                Primitive::Triangle {
                    index, instance, ..
                } => triangle_key(instance, index),
                Primitive::Moving { index, .. } => triangle_key(NO_INSTANCE - 1, index),
                Primitive::Sphere { .. } => unreachable!(),
            };
            seen.push(match hit.primitive {
                Primitive::Triangle { instance, .. } => instance,
                _ => u32::MAX - 1,
            });
            rejected.push(key);
        }
        // The ray meets one triangle of each copy: world, instance 0, instance 1, moving.
        assert_eq!(
            seen,
            vec![NO_INSTANCE, 0, 1, u32::MAX - 1],
            "{}: the order hits were taken in",
            isa.name()
        );
    }
}

/// The binary tree obvhs builds over `tris` (as the renderer's build does).
fn bvh2_of(tris: &[TriangleRecord]) -> obvhs::bvh2::Bvh2 {
    let tris: Vec<obvhs::triangle::Triangle> = tris
        .iter()
        .map(|t| obvhs::triangle::Triangle {
            v0: t.p[0].into(),
            v1: t.p[1].into(),
            v2: t.p[2].into(),
        })
        .collect();
    build::triangles_bvh2(&tris, &mut BvhBuildStats::default())
}

/// Half the surface area of the box `lo..hi`, in `f64`.
fn half_area64(lo: [f32; 3], hi: [f32; 3]) -> f64 {
    let d = [0, 1, 2].map(|a| f64::from(hi[a]) - f64::from(lo[a]));
    d[0] * d[1] + d[1] * d[2] + d[2] * d[0]
}

/// The SAH cost of a wide BVH as `wide::SahCost` charges it, read from its nodes: each
/// node the half area of its children's union, each leaf its half area times its count
/// times `cost.prim`.
fn wide_cost(bvh: &wide::WideBvh, cost: wide::SahCost) -> f64 {
    let mut total = 0.0;
    for node in &bvh.nodes {
        let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
        for k in 0..wide::WIDTH {
            if node.lo[0][k] > node.hi[0][k] {
                continue;
            }
            let (l, h) = (
                [0, 1, 2].map(|a| node.lo[a][k]),
                [0, 1, 2].map(|a| node.hi[a][k]),
            );
            for a in 0..3 {
                lo[a] = lo[a].min(l[a]);
                hi[a] = hi[a].max(h[a]);
            }
            if node.count[k] != 0 {
                total += half_area64(l, h) * f64::from(node.count[k]) * f64::from(cost.prim);
            }
        }
        total += half_area64(lo, hi);
    }
    total
}

/// Every way to cover the subtree of binary node `c` by at most `max` subtrees (`c`
/// itself, or a cover of its left subtree beside one of its right).
fn covers(bn: &[obvhs::bvh2::node::Bvh2Node], c: usize, max: usize) -> Vec<Vec<usize>> {
    let mut out = vec![vec![c]];
    if !bn[c].is_leaf() && max >= 2 {
        let first = bn[c].first_index as usize;
        for a in covers(bn, first, max - 1) {
            for b in covers(bn, first + 1, max - a.len()) {
                out.push([a.clone(), b].concat());
            }
        }
    }
    out
}

/// The cheapest SAH cost of binary node `c` as one child (a leaf when allowed, else a
/// wide node over the best cover of its two subtrees), by trying every cover.
fn exhaustive_cost(bvh2: &obvhs::bvh2::Bvh2, c: usize, cost: wide::SahCost) -> f64 {
    let bn = &bvh2.nodes;
    let n = &bn[c];
    let b = n.aabb();
    let area = half_area64(b.min.to_array(), b.max.to_array());
    let count = {
        let (mut count, mut stack) = (0, vec![c]);
        while let Some(i) = stack.pop() {
            if bn[i].is_leaf() {
                count += bn[i].prim_count;
            } else {
                stack.extend([bn[i].first_index as usize, bn[i].first_index as usize + 1]);
            }
        }
        count
    };
    let leaf = area * f64::from(count) * f64::from(cost.prim);
    if n.is_leaf() {
        return leaf;
    }
    let first = n.first_index as usize;
    let mut best = f64::INFINITY;
    for a in covers(bn, first, wide::WIDTH - 1) {
        for b in covers(bn, first + 1, wide::WIDTH - a.len()) {
            let sum: f64 = a
                .iter()
                .chain(&b)
                .map(|&m| exhaustive_cost(bvh2, m, cost))
                .sum();
            best = best.min(sum);
        }
    }
    let inner = area + best;
    // The root is always a wide node.
    if c != 0 && count <= cost.leaf_max {
        inner.min(leaf)
    } else {
        inner
    }
}

/// The SAH collapse (Ylitie, Karras & Laine 2017, §3) finds the cheapest wide tree: on
/// small trees its cost equals the minimum over every way of collapsing them, tried
/// exhaustively, for leaf limits and primitive costs that favour leaves, nodes or both.
#[test]
fn the_sah_collapse_is_the_cheapest_collapse() {
    let costs = [
        wide::SahCost::TRIANGLES,
        wide::SahCost {
            leaf_max: 2,
            prim: 0.3,
        },
        wide::SahCost {
            leaf_max: 4,
            prim: 3.0,
        },
        wide::SahCost {
            leaf_max: 16,
            prim: 0.05,
        },
    ];
    let mut checked = 0;
    for seed in 0..6u64 {
        for n in [2, 3, 6, 10, 13] {
            let tris = scattered(n, 100 + seed);
            let bvh2 = bvh2_of(&tris);
            let identity: Vec<u32> = (0..n as u32).collect();
            for cost in costs {
                let wide = wide::WideBvh::collapse_with(&bvh2, &identity, cost);
                let ours = wide_cost(&wide, cost);
                let best = exhaustive_cost(&bvh2, 0, cost);
                assert!(
                    (ours - best).abs() <= 1e-5 * best,
                    "seed {seed}, {n} triangles, {cost:?}: collapse {ours}, cheapest {best}"
                );
                checked += 1;
            }
        }
    }
    assert_eq!(checked, 6 * 5 * 4);
}

/// The SAH collapse of a larger tree is a well-formed wide BVH: every triangle in exactly
/// one leaf, leaves within the limit, every node reached once, and at least as cheap as
/// wide nodes made greedily by opening the largest child (tinybvh's and our earlier
/// collapse), which it must be as the optimum.
#[test]
fn the_sah_collapse_covers_every_triangle_once_within_the_limits() {
    let n = 4000;
    let tris = scattered(n, 77);
    let bvh2 = bvh2_of(&tris);
    let identity: Vec<u32> = (0..n as u32).collect();
    for cost in [
        wide::SahCost::TRIANGLES,
        wide::SahCost {
            leaf_max: 3,
            prim: 1.0,
        },
    ] {
        let wide = wide::WideBvh::collapse_with(&bvh2, &identity, cost);
        let mut prims = wide.prims.clone();
        prims.sort_unstable();
        assert_eq!(prims, identity, "{cost:?}");
        let mut reached = vec![0u32; wide.nodes.len()];
        reached[0] = 1;
        let mut leaf_total = 0;
        for node in &wide.nodes {
            for k in 0..wide::WIDTH {
                if node.lo[0][k] > node.hi[0][k] {
                    continue;
                }
                if node.count[k] == 0 {
                    reached[node.child[k] as usize] += 1;
                } else {
                    assert!(node.count[k] <= cost.leaf_max, "{cost:?}");
                    leaf_total += node.count[k];
                }
            }
        }
        assert_eq!(leaf_total as usize, n);
        assert!(reached.iter().all(|&r| r == 1), "{cost:?}");
        // A greedy collapse of the same tree with the same leaf limit.
        let greedy = greedy_cost(&bvh2, cost);
        let ours = wide_cost(&wide, cost);
        assert!(
            ours <= greedy * (1.0 + 1e-6),
            "{cost:?}: {ours} against {greedy}"
        );
    }
}

/// The SAH cost of the greedy collapse: each wide node opens its child of largest area
/// (interior children whose subtree exceeds the leaf limit first) until it has
/// `wide::WIDTH` children; a child within the limit is a leaf.
fn greedy_cost(bvh2: &obvhs::bvh2::Bvh2, cost: wide::SahCost) -> f64 {
    let bn = &bvh2.nodes;
    // Triangles under each node, children first (obvhs does not promise children after
    // their parents).
    let mut under = vec![0u32; bn.len()];
    let mut stack = vec![(0usize, false)];
    while let Some((i, done)) = stack.pop() {
        let c = bn[i].first_index as usize;
        if bn[i].is_leaf() {
            under[i] = bn[i].prim_count;
        } else if done {
            under[i] = under[c] + under[c + 1];
        } else {
            stack.extend([(i, true), (c, false), (c + 1, false)]);
        }
    }
    let area = |i: usize| {
        let b = bn[i].aabb();
        half_area64(b.min.to_array(), b.max.to_array())
    };
    let mut total = 0.0;
    let mut work = vec![0usize];
    while let Some(b) = work.pop() {
        total += area(b);
        let first = bn[b].first_index as usize;
        let mut children = vec![first, first + 1];
        while children.len() < wide::WIDTH {
            let open = (0..children.len())
                .filter(|&k| !bn[children[k]].is_leaf())
                .max_by(|&x, &y| {
                    let key = |k: usize| (under[children[k]] > cost.leaf_max, area(children[k]));
                    key(x).partial_cmp(&key(y)).unwrap()
                });
            let Some(k) = open else { break };
            let c = bn[children[k]].first_index as usize;
            children[k] = c;
            children.insert(k + 1, c + 1);
        }
        for c in children {
            if bn[c].is_leaf() || under[c] <= cost.leaf_max {
                total += area(c) * f64::from(under[c]) * f64::from(cost.prim);
            } else {
                work.push(c);
            }
        }
    }
    total
}

/// The binary SAH cost of `bvh2` relative to its root's box (each interior node its
/// half area, each leaf its half area times its primitive count), in `f64`.
fn bvh2_sah(bvh2: &obvhs::bvh2::Bvh2) -> f64 {
    let area = |n: &obvhs::bvh2::node::Bvh2Node| {
        half_area64(n.aabb().min.to_array(), n.aabb().max.to_array())
    };
    let total: f64 = bvh2
        .nodes
        .iter()
        .map(|n| area(n) * f64::from(n.prim_count.max(1)))
        .sum();
    total / area(&bvh2.nodes[0])
}

/// The boxes of `tris` as the triangle build reads them.
fn tri_box(tris: &[TriangleRecord]) -> impl Fn(usize) -> obvhs::aabb::Aabb + '_ {
    |i| {
        let p = tris[i].p;
        obvhs::triangle::Triangle {
            v0: p[0].into(),
            v1: p[1].into(),
            v2: p[2].into(),
        }
        .aabb()
    }
}

/// A level built in chunks ([`build::chunked_bvh2`], here 10 chunks of 2,000 scattered
/// triangles) is a valid tree: every node's box holds its children's, every primitive is
/// in exactly one leaf, the primitive indices are the identity; the same input builds the
/// same tree bit for bit; and its SAH cost is within 3% of the single PLOC build's.
#[test]
fn a_level_built_in_chunks_is_a_whole_tree_as_good_as_one_build() {
    let tris = scattered(20_000, 31);
    let n = tris.len();
    let mut stats = BvhBuildStats::default();
    let chunked = build::chunked_bvh2(n, tri_box(&tris), 1000, 2000, &mut stats);
    assert_eq!(stats.chunks, 10, "{stats:?}");
    assert_eq!(
        (stats.bvhs, stats.primitives, stats.clustered),
        (1, n as u64, 0)
    );
    let nodes = &chunked.nodes;
    assert_eq!(nodes.len(), 2 * n - 1);
    assert!(chunked
        .primitive_indices
        .iter()
        .enumerate()
        .all(|(i, &p)| p as usize == i));
    let mut seen = vec![0u32; n];
    let mut stack = vec![0usize];
    let mut visited = 0;
    while let Some(i) = stack.pop() {
        visited += 1;
        let node = &nodes[i];
        let first = node.first_index as usize;
        if node.is_leaf() {
            assert_eq!(node.prim_count, 1);
            seen[chunked.primitive_indices[first] as usize] += 1;
            let b = tri_box(&tris)(chunked.primitive_indices[first] as usize);
            assert!(node.aabb().min.cmple(b.min).all() && node.aabb().max.cmpge(b.max).all());
            continue;
        }
        for c in [first, first + 1] {
            let cb = nodes[c].aabb();
            assert!(
                node.aabb().min.cmple(cb.min).all() && node.aabb().max.cmpge(cb.max).all(),
                "node {i} does not hold child {c}"
            );
            stack.push(c);
        }
    }
    assert_eq!(visited, nodes.len(), "every node is reached once");
    assert!(seen.iter().all(|&k| k == 1), "every primitive in one leaf");

    let again = build::chunked_bvh2(n, tri_box(&tris), 1000, 2000, &mut BvhBuildStats::default());
    let bits = |t: &obvhs::bvh2::Bvh2| -> Vec<[u32; 8]> {
        t.nodes
            .iter()
            .map(|n| {
                let (lo, hi) = (n.aabb().min.to_array(), n.aabb().max.to_array());
                [lo[0], lo[1], lo[2], hi[0], hi[1], hi[2]]
                    .map(f32::to_bits)
                    .iter()
                    .copied()
                    .chain([n.prim_count, n.first_index])
                    .collect::<Vec<_>>()
                    .try_into()
                    .expect("8 words")
            })
            .collect()
    };
    assert_eq!(bits(&chunked), bits(&again), "deterministic");

    let single = bvh2_of(&tris);
    let (c, s) = (bvh2_sah(&chunked), bvh2_sah(&single));
    eprintln!("chunked SAH {c} against one build's {s}");
    assert!(c <= 1.03 * s, "chunked SAH {c} against one build's {s}");
}

/// Below the chunk threshold a level is the single build's, tree for tree; and input the
/// robust builds must take (coincident triangles) takes them whatever its size.
#[test]
fn small_and_crowded_levels_are_not_built_in_chunks() {
    let tris = scattered(3000, 41);
    let mut stats = BvhBuildStats::default();
    let below = build::chunked_bvh2(tris.len(), tri_box(&tris), 3001, 500, &mut stats);
    assert_eq!(stats.chunks, 0);
    let single = bvh2_of(&tris);
    assert_eq!(below.nodes.len(), single.nodes.len());
    for (a, b) in below.nodes.iter().zip(&single.nodes) {
        assert_eq!(
            (a.aabb().min, a.aabb().max, a.prim_count, a.first_index),
            (b.aabb().min, b.aabb().max, b.prim_count, b.first_index)
        );
    }
    let p = [Vec3::ZERO, Vec3::X, Vec3::Y];
    let mut crowded = scattered(3000, 43);
    crowded.extend((0..500u32).map(|i| record(p, 3000 + i)));
    let mut stats = BvhBuildStats::default();
    build::chunked_bvh2(crowded.len(), tri_box(&crowded), 1000, 500, &mut stats);
    assert_eq!(
        (stats.chunks, stats.clustered, stats.bvhs),
        (0, 500, 1),
        "{stats:?}"
    );
}

/// A level of triangles built in chunks (through `triangle_bvh_chunked`, 8 chunks) finds
/// the nearest hit by testing every triangle on 3,000 rays, and stores every triangle
/// once with its own attributes.
#[test]
fn a_level_built_in_chunks_finds_the_brute_force_hits() {
    let tris = scattered(16_000, 47);
    let mut stats = BvhBuildStats::default();
    let (bvh, triangles, _) =
        traversal::triangle_bvh_chunked(tris.len(), &|i| tris[i], 1000, 2000, &mut stats);
    assert_eq!(stats.chunks, 8);
    assert_eq!(triangles.len(), tris.len());
    let mut indices: Vec<u32> = (0..triangles.len())
        .map(|s| {
            let r = triangles.record(s);
            assert_eq!(bits(&r.p), bits(&tris[r.index as usize].p));
            r.index
        })
        .collect();
    indices.sort_unstable();
    assert!(indices.iter().enumerate().all(|(i, &k)| k as usize == i));
    let level = traversal::TriangleLevel {
        bvh: &bvh,
        triangles: &triangles,
        instance: NO_INSTANCE,
        isa: kernels::active(),
    };
    let mut s = 53u64;
    let mut hits = 0;
    for k in 0..3000 {
        let o = Vec3::new(lcg(&mut s), lcg(&mut s), -1.0);
        let d = (Vec3::new(lcg(&mut s), lcg(&mut s), lcg(&mut s)) - o).normalize();
        let mut best = Nearest::new(f32::INFINITY);
        level.nearest(o, d, &mut best, &|_, _, _, _| true);
        let got = best.hit.map(|h| h.t);
        assert_eq!(got, brute_force(&tris, o, d), "ray {k}");
        hits += usize::from(got.is_some());
    }
    assert!(hits > 1000, "{hits} hits");
}
