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
    for (x, y) in a.triangles.iter().zip(&b.triangles) {
        assert_eq!((x.p, x.index), (y.p, y.index));
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
