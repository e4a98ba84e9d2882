//! The render plan of every built-in and glTF test scene is what a rendering engineer would
//! write down; synthetic scenes exercise each rule (black, direct-only, depth of field,
//! textures, tiny lights, rough glass, emitters that do not scatter).

use glam::Vec3;
use tessera_scene::analysis::{analyse, EffectKind, PlannedIntegrator, RenderPlan};
use tessera_scene::builtin::look_at_camera;
use tessera_scene::{
    GltfMaterial, Image, Material, MaterialKind, Mesh, PunctualLight, Scene, Sphere, Texels,
    Texture, TextureRef, Wrap,
};

use EffectKind::*;

fn scene_path(name: &str) -> String {
    format!("{}/../../scenes/{name}", env!("CARGO_MANIFEST_DIR"))
}

fn plan_of(arg: &str) -> RenderPlan {
    analyse(&tessera_scene::load(arg).unwrap())
}

/// Asserts that exactly `present` are found, that `absent` lists the rest, and that the
/// plan is internally consistent.
fn assert_effects(name: &str, plan: &RenderPlan, present: &[EffectKind]) {
    let mut found: Vec<EffectKind> = plan.effects.iter().map(|e| e.kind).collect();
    found.sort();
    let mut want = present.to_vec();
    want.sort();
    assert_eq!(found, want, "{name}: effects\n{}", plan.summary());
    for k in EffectKind::ALL {
        assert_eq!(
            plan.absent.contains(&k),
            !present.contains(&k),
            "{name}: absent list wrong for {k}"
        );
    }
    for e in &plan.effects {
        assert!(!e.evidence.is_empty(), "{name}: {} has no evidence", e.kind);
    }
    assert!(
        plan.reasons.iter().any(|r| r.contains("static scene")),
        "{name}: motion is not explained"
    );
    assert_eq!(plan.lens_sampling, plan.has(DepthOfField), "{name}");
    // The JSON is valid, ASCII, and agrees with the struct.
    let json = plan.to_json();
    assert!(json.is_ascii(), "{json}");
    assert!(json.starts_with("{\"integrator\":"), "{json}");
    let v: serde_json::Value = serde_json::from_str(&json).unwrap();
    assert_eq!(v["integrator"], plan.integrator.as_str());
    assert_eq!(v["max_depth"], plan.max_depth);
    assert_eq!(v["rr_depth"], plan.rr_depth);
    assert_eq!(v["effects"].as_array().unwrap().len(), plan.effects.len());
    assert_eq!(v["absent"].as_array().unwrap().len(), plan.absent.len());
    assert!(v["overridden"].is_null());
    // The summary names every effect and the integrator.
    let text = plan.summary();
    for e in &plan.effects {
        assert!(
            text.contains(&format!("{}: {}", e.kind, e.evidence)),
            "{text}"
        );
    }
    assert!(
        text.starts_with(&format!("render plan: {}", plan.integrator)),
        "{text}"
    );
}

fn evidence(plan: &RenderPlan, kind: EffectKind) -> &str {
    plan.evidence(kind)
        .unwrap_or_else(|| panic!("no {kind}:\n{}", plan.summary()))
}

#[test]
fn cornell_box_is_a_closed_bright_diffuse_room() {
    for arg in [
        "builtin:cornell-box".to_string(),
        scene_path("cornell-box.gltf"),
    ] {
        let plan = plan_of(&arg);
        assert_effects(&arg, &plan, &[DirectArea, IndirectDiffuse]);
        let area = evidence(&plan, DirectArea);
        assert!(
            area.contains("2 emissive triangles in material 3 'light'"),
            "{arg}: {area}"
        );
        assert!(evidence(&plan, IndirectDiffuse).contains("(closed)"));
        assert_eq!(plan.integrator, PlannedIntegrator::Path, "{arg}");
        assert_eq!((plan.max_depth, plan.rr_depth), (16, 5), "{arg}");
        assert!(!plan.lens_sampling);
        let text = plan.summary();
        for needle in [
            "pinhole camera: no lens sampling",
            "nothing transmits: no refraction paths",
            "no specular surfaces: no caustic technique",
        ] {
            assert!(text.contains(needle), "{arg}: {text}");
        }
    }
}

#[test]
fn veach_mis_has_four_sphere_lights_and_glossy_plates() {
    let plan = plan_of("builtin:veach-mis");
    assert_effects(
        "veach-mis",
        &plan,
        &[DirectSphere, IndirectDiffuse, GlossyReflection],
    );
    assert!(evidence(&plan, DirectSphere).starts_with("4 emissive spheres"));
    let glossy = evidence(&plan, GlossyReflection);
    for plate in ["plate0", "plate1", "plate2", "plate3"] {
        assert!(glossy.contains(plate), "{glossy}");
    }
    // The emitters have zero albedo: they are lights, not surfaces.
    assert!(!glossy.contains("light"), "{glossy}");
    assert_eq!(plan.integrator, PlannedIntegrator::Path);
    // Dark and open: no need for a deep path.
    assert_eq!((plan.max_depth, plan.rr_depth), (8, 3));
}

#[test]
fn furnace_is_a_closed_bright_emitting_box() {
    let plan = plan_of("builtin:furnace");
    assert_effects("furnace", &plan, &[DirectArea, IndirectDiffuse]);
    assert!(evidence(&plan, DirectArea).starts_with("12 emissive triangles"));
    assert_eq!(plan.integrator, PlannedIntegrator::Path);
    assert_eq!(plan.max_depth, 16);
}

#[test]
fn caustic_scene_needs_bdpt_for_its_tiny_light() {
    let plan = plan_of("builtin:caustic");
    assert_effects(
        "caustic",
        &plan,
        &[
            DirectSphere,
            DirectEnvironment,
            IndirectDiffuse,
            SpecularReflection,
            Refraction,
            TotalInternalReflection,
            Caustics,
            DeltaLitCaustics,
            TinyLightImages,
        ],
    );
    // Radius 0.05 against a scene radius of about 7.2: 0.7 %, below the 1 % threshold.
    let delta = evidence(&plan, DeltaLitCaustics);
    assert!(
        delta.contains("radius 0.05 (0.70% of the scene radius 7.19)"),
        "{delta}"
    );
    // The camera sees the glass ball, in and through which the tiny light shows: E S+ L.
    let images = evidence(&plan, TinyLightImages);
    assert!(
        images.contains("material 1 'glass'") && images.contains("radius 0.05"),
        "{images}"
    );
    assert!(evidence(&plan, Refraction).contains("material 1 'glass'"));
    assert_eq!(plan.integrator, PlannedIntegrator::Bdpt);
    assert_eq!((plan.max_depth, plan.rr_depth), (12, 5));
    assert!(plan
        .reasons
        .iter()
        .any(|r| r.contains("one whole-frame tile")));
}

#[test]
fn glass_spot_gltf_is_a_delta_lit_caustic_seen_through_glass() {
    let plan = plan_of(&scene_path("glass-spot.gltf"));
    assert_effects(
        "glass-spot",
        &plan,
        &[
            DirectSpot,
            IndirectDiffuse,
            SpecularReflection,
            Refraction,
            TotalInternalReflection,
            Caustics,
            DeltaLitCaustics,
            DeltaLitSds,
        ],
    );
    assert_eq!(evidence(&plan, DirectSpot), "1 spot light");
    assert!(evidence(&plan, DeltaLitCaustics).contains("1 spot light"));
    assert!(evidence(&plan, Refraction).contains("material 1 'glass'"));
    // The camera sees the ball, through which the caustic under it appears.
    assert!(evidence(&plan, DeltaLitSds).contains("1 delta light"));
    assert_eq!(plan.integrator, PlannedIntegrator::Vcm);
    assert_eq!(plan.max_depth, 12);
}

// ---- synthetic scenes ----

fn quad(material: u32, corners: [Vec3; 4]) -> Mesh {
    Mesh {
        name: "quad".into(),
        positions: corners.to_vec(),
        normals: None,
        uvs: vec![],
        tangents: None,
        colors: None,
        indices: vec![[0, 1, 2], [0, 2, 3]],
        material,
    }
}

/// A 10 m x 10 m floor at y = 0 facing up.
fn floor(material: u32) -> Mesh {
    let v = Vec3::new;
    quad(
        material,
        [
            v(-5.0, 0.0, -5.0),
            v(-5.0, 0.0, 5.0),
            v(5.0, 0.0, 5.0),
            v(5.0, 0.0, -5.0),
        ],
    )
}

fn base_scene(materials: Vec<Material>, meshes: Vec<Mesh>) -> Scene {
    Scene {
        name: "synthetic".into(),
        camera: look_at_camera(
            Vec3::new(0.0, 2.0, 6.0),
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::Y,
            40.0,
        ),
        meshes,
        prototypes: Vec::new(),
        instances: Vec::new(),
        spheres: vec![],
        materials,
        textures: vec![],
        images: vec![],
        warnings: vec![],
        lights: vec![],
        environment: None,
        environment_map: None,
        default_resolution: (64, 48),
        animated: false,
    }
}

/// Validates a synthetic scene (as every loader does) and analyses it.
fn analyse_valid(scene: &Scene) -> RenderPlan {
    scene.validate().unwrap();
    analyse(scene)
}

fn point_light() -> PunctualLight {
    PunctualLight::Point {
        position: Vec3::new(0.0, 3.0, 0.0),
        intensity: Vec3::splat(10.0),
    }
}

fn metallic_roughness(metallic: f32, roughness: f32, transmission: f32) -> MaterialKind {
    with_specular(metallic, roughness, transmission, 1.0)
}

/// A glTF material with a KHR_materials_specular factor.
fn with_specular(metallic: f32, roughness: f32, transmission: f32, specular: f32) -> MaterialKind {
    MaterialKind::Gltf(Box::new(GltfMaterial {
        base_color: Vec3::splat(0.8),
        metallic,
        roughness,
        transmission,
        specular,
        ..GltfMaterial::default()
    }))
}

#[test]
fn no_light_renders_black() {
    let mut scene = tessera_scene::builtin::cornell_box();
    for m in &mut scene.materials {
        m.emission = Vec3::ZERO;
    }
    let plan = analyse_valid(&scene);
    assert_effects("dark cornell", &plan, &[]);
    assert_eq!(plan.integrator, PlannedIntegrator::Black);
    assert_eq!(plan.max_depth, 0);
    assert!(plan
        .reasons
        .iter()
        .any(|r| r == "no light: the image is black"));

    // Lights with zero power are no lights either.
    let mut scene = base_scene(
        vec![Material::diffuse("floor", Vec3::splat(0.5))],
        vec![floor(0)],
    );
    scene.lights.push(PunctualLight::Point {
        position: Vec3::Y,
        intensity: Vec3::ZERO,
    });
    scene.environment = Some(Vec3::ZERO);
    assert_eq!(analyse_valid(&scene).integrator, PlannedIntegrator::Black);

    // A point light with nothing to shine on is invisible.
    let mut scene = base_scene(vec![], vec![]);
    scene.lights.push(point_light());
    let plan = analyse_valid(&scene);
    assert_eq!(plan.integrator, PlannedIntegrator::Black);
    assert!(plan.has(DirectPoint));
    assert!(
        plan.reasons[0].contains("the image is black"),
        "{:?}",
        plan.reasons
    );
}

#[test]
fn single_plane_under_a_point_light_is_direct_lighting_only() {
    let mut scene = base_scene(
        vec![Material::diffuse("floor", Vec3::splat(0.5))],
        vec![floor(0)],
    );
    scene.lights.push(point_light());
    let plan = analyse_valid(&scene);
    assert_effects("plane", &plan, &[DirectPoint]);
    assert_eq!(plan.integrator, PlannedIntegrator::Direct);
    assert_eq!(plan.max_depth, 1);

    // The same plane split into two meshes is still one plane.
    let mut split = scene.clone();
    let mut second = floor(0);
    for p in &mut second.positions {
        p.x += 10.0;
    }
    split.meshes.push(second);
    assert_eq!(analyse_valid(&split).integrator, PlannedIntegrator::Direct);

    // A second plane facing it: light bounces between them.
    let mut two = scene.clone();
    let v = Vec3::new;
    two.meshes.push(quad(
        0,
        [
            v(-5.0, 0.0, -5.0),
            v(5.0, 0.0, -5.0),
            v(5.0, 5.0, -5.0),
            v(-5.0, 5.0, -5.0),
        ],
    ));
    let plan = analyse_valid(&two);
    assert_effects("two planes", &plan, &[DirectPoint, IndirectDiffuse]);
    assert_eq!(plan.integrator, PlannedIntegrator::Path);
    assert_eq!(plan.max_depth, 8);

    // A glossy plane needs more than the direct integrator offers.
    let mut glossy = scene.clone();
    glossy.materials[0].kind = metallic_roughness(0.0, 0.5, 0.0);
    let plan = analyse_valid(&glossy);
    assert_effects("glossy plane", &plan, &[DirectPoint, GlossyReflection]);
    assert_eq!(plan.integrator, PlannedIntegrator::Path);
}

#[test]
fn an_emitter_without_albedo_is_only_a_light() {
    let v = Vec3::new;
    let light = |albedo: f32| Material {
        name: "panel".into(),
        kind: MaterialKind::Diffuse {
            albedo: Vec3::splat(albedo),
        },
        emission: Vec3::splat(5.0),
        double_sided: false,
    };
    let panel = quad(
        1,
        [
            v(-1.0, 3.0, -1.0),
            v(1.0, 3.0, -1.0),
            v(1.0, 3.0, 1.0),
            v(-1.0, 3.0, 1.0),
        ],
    );
    let black = base_scene(
        vec![Material::diffuse("floor", Vec3::splat(0.5)), light(0.0)],
        vec![floor(0), panel.clone()],
    );
    let plan = analyse_valid(&black);
    assert_effects("black panel", &plan, &[DirectArea]);
    assert_eq!(plan.integrator, PlannedIntegrator::Direct);
    // A panel that reflects sends floor light back down.
    let white = base_scene(
        vec![Material::diffuse("floor", Vec3::splat(0.5)), light(0.5)],
        vec![floor(0), panel],
    );
    let plan = analyse_valid(&white);
    assert_effects("white panel", &plan, &[DirectArea, IndirectDiffuse]);
    assert_eq!(plan.integrator, PlannedIntegrator::Path);
}

#[test]
fn aperture_means_depth_of_field_and_lens_sampling() {
    let mut scene = tessera_scene::builtin::cornell_box();
    scene.camera.aperture_radius = 0.01;
    scene.camera.focus_distance = 1.0;
    let plan = analyse_valid(&scene);
    assert_effects(
        "cornell dof",
        &plan,
        &[DirectArea, IndirectDiffuse, DepthOfField],
    );
    assert!(plan.lens_sampling);
    assert!(evidence(&plan, DepthOfField).contains("aperture radius 0.01"));
    assert!(plan.reasons.iter().any(|r| r.contains("lens sampling on")));
}

#[test]
fn used_textures_are_found_and_unused_ones_ignored() {
    let textured = Material {
        name: "checker".into(),
        kind: MaterialKind::Gltf(Box::new(GltfMaterial {
            base_color_texture: Some(TextureRef::new(0)),
            metallic: 0.0,
            ..GltfMaterial::default()
        })),
        emission: Vec3::ZERO,
        double_sided: false,
    };
    let mut scene = base_scene(
        vec![textured, Material::diffuse("plain", Vec3::splat(0.5))],
        vec![floor(0)],
    );
    scene.images.push(Image {
        width: 2,
        height: 1,
        texels: Texels::Rgba8(vec![[0, 0, 0, 255], [255, 255, 255, 255]]),
    });
    scene.textures.push(Texture {
        image: 0,
        wrap_s: Wrap::Repeat,
        wrap_t: Wrap::Repeat,
        nearest: false,
    });
    scene.lights.push(point_light());
    scene.validate().unwrap();
    let plan = analyse_valid(&scene);
    assert_effects("textured", &plan, &[DirectPoint, Textures]);
    assert!(evidence(&plan, Textures).contains("material 0 'checker'"));
    assert_eq!(plan.integrator, PlannedIntegrator::Direct);

    scene.meshes[0].material = 1;
    assert!(!analyse_valid(&scene).has(Textures));
}

#[test]
fn gltf_material_layers_classify_by_roughness_and_weights() {
    let cases: [(MaterialKind, &[EffectKind]); 8] = [
        // A plain glTF wall: rough dielectric coat over diffuse is diffuse.
        (metallic_roughness(0.0, 1.0, 0.0), &[]),
        // KHR_materials_specular 0: a smooth dielectric without its Fresnel coat is diffuse.
        (with_specular(0.0, 0.01, 0.0, 0.0), &[]),
        (metallic_roughness(0.0, 0.5, 0.0), &[GlossyReflection]),
        (metallic_roughness(0.0, 0.01, 0.0), &[SpecularReflection]),
        (metallic_roughness(1.0, 0.6, 0.0), &[GlossyReflection]),
        (
            metallic_roughness(0.0, 0.3, 1.0),
            &[GlossyReflection, Refraction, TotalInternalReflection],
        ),
        (
            MaterialKind::Conductor {
                f0: Vec3::splat(0.9),
                roughness: 0.01,
            },
            &[SpecularReflection],
        ),
        (
            MaterialKind::Phong {
                kd: Vec3::ZERO,
                ks: Vec3::splat(0.5),
                exponent: 100.0,
            },
            &[GlossyReflection],
        ),
    ];
    for (kind, classes) in cases {
        // A lit white floor with a ball of the material on it.
        let mut scene = base_scene(
            vec![
                Material::diffuse("floor", Vec3::splat(0.8)),
                Material {
                    name: "ball".into(),
                    kind: kind.clone(),
                    emission: Vec3::ZERO,
                    double_sided: false,
                },
            ],
            vec![floor(0)],
        );
        scene.spheres.push(Sphere {
            center: Vec3::new(0.0, 0.5, 0.0),
            radius: 0.5,
            material: 1,
        });
        scene.environment = Some(Vec3::splat(1.0));
        scene.validate().unwrap();
        let plan = analyse_valid(&scene);
        let mut want = vec![DirectEnvironment, IndirectDiffuse];
        want.extend_from_slice(classes);
        if classes.contains(&SpecularReflection) {
            // A smooth reflector focuses the environment onto the floor, but the
            // environment is no delta light.
            want.push(Caustics);
        }
        assert_effects(&format!("{kind:?}"), &plan, &want);
        assert_eq!(plan.integrator, PlannedIntegrator::Path, "{kind:?}");
        let refracts = classes.contains(&Refraction);
        assert_eq!(plan.max_depth, if refracts { 12 } else { 8 }, "{kind:?}");
        assert_eq!(plan.rr_depth, if refracts { 5 } else { 3 }, "{kind:?}");
    }
}

#[test]
fn caustics_need_a_smooth_specular_surface_and_bdpt_needs_a_small_light() {
    // A large light: caustics, but a path tracer finds them by BSDF sampling.
    let mut scene = tessera_scene::builtin::caustic();
    scene.spheres[1].radius = 0.5;
    let plan = analyse_valid(&scene);
    assert!(plan.has(Caustics) && !plan.has(DeltaLitCaustics));
    assert!(!plan.has(TinyLightImages), "{}", plan.summary());
    assert_eq!(plan.integrator, PlannedIntegrator::Path);

    // Rough glass: refraction without caustics.
    let mut scene = tessera_scene::builtin::caustic();
    scene.materials[1].kind = MaterialKind::Dielectric {
        ior: 1.5,
        roughness: 0.3,
        tint: Vec3::ONE,
    };
    let plan = analyse_valid(&scene);
    assert!(plan.has(Refraction) && plan.has(GlossyReflection));
    assert!(!plan.has(Caustics) && !plan.has(SpecularReflection));
    assert_eq!(plan.integrator, PlannedIntegrator::Path);

    // A mirror ball under a point light: a delta-lit reflective caustic, no refraction.
    let mut scene = base_scene(
        vec![
            Material::diffuse("floor", Vec3::splat(0.8)),
            Material {
                name: "mirror".into(),
                kind: MaterialKind::Mirror {
                    reflectance: Vec3::splat(0.9),
                },
                emission: Vec3::ZERO,
                double_sided: false,
            },
        ],
        vec![floor(0)],
    );
    scene.spheres.push(Sphere {
        center: Vec3::new(0.0, 0.5, 0.0),
        radius: 0.5,
        material: 1,
    });
    scene.lights.push(point_light());
    let plan = analyse_valid(&scene);
    assert_effects(
        "mirror ball",
        &plan,
        &[
            DirectPoint,
            IndirectDiffuse,
            SpecularReflection,
            Caustics,
            DeltaLitCaustics,
            DeltaLitSds,
        ],
    );
    // The camera sees the ball, in which the floor's caustic appears: L S D S E.
    assert!(evidence(&plan, DeltaLitSds).contains("material 1 'mirror'"));
    assert_eq!(plan.integrator, PlannedIntegrator::Vcm);
    assert_eq!((plan.max_depth, plan.rr_depth), (8, 3));

    // The same ball behind the camera: the caustic is never seen through it, bdpt.
    scene.spheres[0].center = Vec3::new(0.0, 0.5, 9.0);
    let plan = analyse_valid(&scene);
    assert!(!plan.has(DeltaLitSds), "{}", plan.summary());
    assert_eq!(plan.integrator, PlannedIntegrator::Bdpt);
}

/// Caustics of a small area light within MNEE's reach (bench/compare's glass ball: a 0.2 m
/// square light over a glass ball on a floor): path tracing, with the choice against mnee
/// left to the technique pilot. A large square light (2 m) or rough glass (no caustic):
/// plain path tracing, no pilot.
#[test]
fn caustics_of_a_small_area_light_leave_mnee_to_the_pilot() {
    let square = |h: f32| {
        let mut scene = tessera_scene::builtin::caustic();
        scene.spheres.truncate(1);
        scene.environment = None;
        scene.materials.push(Material {
            name: "square light".into(),
            kind: MaterialKind::Diffuse { albedo: Vec3::ZERO },
            emission: Vec3::splat(250.0),
            double_sided: false,
        });
        let y = 2.5;
        scene.meshes.push(quad(
            2,
            [
                Vec3::new(-h, y, -h),
                Vec3::new(h, y, -h),
                Vec3::new(h, y, h),
                Vec3::new(-h, y, h),
            ],
        ));
        scene
    };
    let plan = analyse_valid(&square(0.1));
    assert!(
        plan.has(Caustics) && !plan.has(DeltaLitCaustics),
        "{}",
        plan.summary()
    );
    assert_eq!(plan.integrator, PlannedIntegrator::Path);
    let pilot = plan.technique_pilot.as_ref().expect("the mnee question");
    assert!(pilot.mnee && !pilot.lit_through_opening, "{pilot:?}");
    assert!(
        plan.reasons
            .iter()
            .any(|r| r.contains("measures mnee against path tracing")
                && r.contains("material 0 'floor'")),
        "{:?}",
        plan.reasons
    );
    let plan = analyse_valid(&square(1.0));
    assert_eq!(plan.integrator, PlannedIntegrator::Path);
    assert!(plan.technique_pilot.is_none(), "{}", plan.summary());
    let mut rough = square(0.1);
    rough.materials[1].kind = MaterialKind::Dielectric {
        ior: 1.5,
        roughness: 0.3,
        tint: Vec3::ONE,
    };
    let plan = analyse_valid(&rough);
    assert_eq!(plan.integrator, PlannedIntegrator::Path);
    assert!(plan.technique_pilot.is_none(), "{}", plan.summary());
}

#[test]
fn override_is_recorded_in_summary_and_json() {
    let mut plan = plan_of("builtin:caustic");
    plan.set_override("--integrator path");
    let o = plan.overridden.clone().unwrap();
    assert!(
        o.contains("--integrator path") && o.contains("chose bdpt"),
        "{o}"
    );
    assert!(plan.summary().contains(&format!("overridden: {o}")));
    let v: serde_json::Value = serde_json::from_str(&plan.to_json()).unwrap();
    assert_eq!(v["overridden"], o.as_str());
}

#[test]
fn json_escapes_names() {
    let mut scene = tessera_scene::builtin::cornell_box();
    scene.materials[3].name = "l\"ight\\ \u{e9}\u{1F4A1}\n".into();
    let plan = analyse_valid(&scene);
    let json = plan.to_json();
    assert!(json.is_ascii(), "{json}");
    let v: serde_json::Value = serde_json::from_str(&json).unwrap();
    let area = v["effects"][0]["evidence"].as_str().unwrap();
    assert!(area.contains("l\"ight\\ \u{e9}\u{1F4A1}\n"), "{area}");
}

/// The pool (`scenes/pool.gltf`): a point light above flat water over a diffuse floor, the
/// camera above the water. Light reaches the camera only as `L S D S E`: the plan finds
/// the class, and since its one caustic crosses one refracting surface from a point light
/// and the camera sees the floor through the water, chooses path tracing with manifold
/// next-event estimation (unbiased), saying what MNEE covers and what it does not; nothing
/// is left unsampled, and the error estimate caveat names the caustic's light after a
/// further bounce.
#[test]
fn pool_gltf_is_a_delta_lit_sds_scene_for_mnee() {
    let plan = plan_of(&scene_path("pool.gltf"));
    eprintln!("{}", plan.summary());
    assert!(plan.has(DeltaLitCaustics) && plan.has(DeltaLitSds));
    assert!(evidence(&plan, DeltaLitSds).contains("material 1 'water'"));
    assert_eq!(
        plan.integrator,
        PlannedIntegrator::Mnee,
        "{:?}",
        plan.beyond_mnee
    );
    assert!(plan.beyond_mnee.is_empty(), "{:?}", plan.beyond_mnee);
    assert!(plan.reasons[0].starts_with("mnee: "), "{}", plan.reasons[0]);
    assert!(plan.reasons[1].contains("after a further diffuse or glossy bounce"));
    assert!(!plan.reasons.iter().any(|r| r.contains("biased: ")));
    // The floor and the water cover 80% of their bounding box: a closed bright room.
    assert_eq!((plan.max_depth, plan.rr_depth), (16, 5));
    assert!(plan.technique_pilot.is_none());
    let mnee = tessera_farm::job::Integrator::Mnee;
    assert_eq!(plan.unsampled(mnee), None);
    let caveat = plan.error_estimate_caveat(mnee).unwrap();
    assert!(caveat.starts_with("may be optimistic: mnee"), "{caveat}");
    assert!(
        !caveat.contains("cannot sample") && !caveat.contains("biased"),
        "{caveat}"
    );
    // Path tracing and bdpt still cannot sample it, and say so as before.
    for used in [
        tessera_farm::job::Integrator::Path,
        tessera_farm::job::Integrator::Bdpt,
    ] {
        let caveat = plan.error_estimate_caveat(used).unwrap();
        assert!(caveat.starts_with("cannot sample"), "{caveat}");
    }
}

/// A synthetic pool: a 4 m x 4 m diffuse floor at y = 0 under flat water (index 1.33) at
/// y = 0.5 (more water layers above it at `extra` heights), a point light at (1, 1.5, 0),
/// and the camera above the water looking down at the floor through it.
fn pool(extra: &[f32]) -> Scene {
    let v = Vec3::new;
    let water = Material {
        name: "water".into(),
        kind: MaterialKind::Dielectric {
            ior: 1.33,
            roughness: 0.0,
            tint: Vec3::ONE,
        },
        emission: Vec3::ZERO,
        double_sided: false,
    };
    let sheet = |y: f32, m: u32| {
        quad(
            m,
            [
                v(-2.0, y, -2.0),
                v(-2.0, y, 2.0),
                v(2.0, y, 2.0),
                v(2.0, y, -2.0),
            ],
        )
    };
    let mut meshes = vec![sheet(0.0, 0), sheet(0.5, 1)];
    meshes.extend(extra.iter().map(|&y| sheet(y, 1)));
    let mut scene = base_scene(
        vec![Material::diffuse("floor", Vec3::splat(0.8)), water],
        meshes,
    );
    scene.camera = look_at_camera(v(0.0, 2.5, 0.05), Vec3::ZERO, Vec3::Y, 20.0);
    scene.lights.push(PunctualLight::Point {
        position: v(1.0, 1.5, 0.0),
        intensity: Vec3::splat(10.0),
    });
    scene
}

/// MNEE's reach decides between mnee and vcm: the pool is within it; three water layers
/// make a chain longer than MNEE's two vertices; a directional light is not a point MNEE
/// connects to; a caustic that the camera sees only after a diffuse bounce (the pool's
/// floor lighting a screen beside it, the water in view but nothing seen through it) is
/// never at the first non-specular vertex where MNEE runs. Each keeps vcm and says why,
/// and a job that forces mnee there is told it cannot sample the class.
#[test]
fn mnee_is_planned_where_every_caustic_is_within_its_reach() {
    let plan = analyse_valid(&pool(&[]));
    assert!(plan.has(DeltaLitSds));
    assert_eq!(
        plan.integrator,
        PlannedIntegrator::Mnee,
        "{}",
        plan.summary()
    );

    let mnee = tessera_farm::job::Integrator::Mnee;
    let expect_vcm = |name: &str, scene: &Scene, why: &str| {
        let plan = analyse_valid(scene);
        assert!(plan.has(DeltaLitSds), "{name}: {}", plan.summary());
        assert_eq!(
            plan.integrator,
            PlannedIntegrator::Vcm,
            "{name}: {}",
            plan.summary()
        );
        assert!(
            plan.beyond_mnee.iter().any(|r| r.contains(why)),
            "{name}: {:?}",
            plan.beyond_mnee
        );
        let not_mnee = plan.reasons.iter().find(|r| r.starts_with("not mnee: "));
        assert!(
            not_mnee.is_some_and(|r| r.contains(why)),
            "{name}: {:?}",
            plan.reasons
        );
        let caveat = plan.unsampled(mnee).unwrap();
        assert!(
            caveat.starts_with("cannot sample") && caveat.contains(why),
            "{caveat}"
        );
    };

    // Three refracting layers: the straight segment to the light crosses three.
    expect_vcm(
        "three layers",
        &pool(&[0.6, 0.7]),
        "3 or more specular surfaces",
    );

    let mut scene = pool(&[]);
    scene.lights[0] = PunctualLight::Directional {
        direction: Vec3::new(-0.3, -1.0, 0.0).normalize(),
        irradiance: Vec3::splat(3.0),
    };
    expect_vcm("directional", &scene, "directional light 0");

    // The screen: diffuse, beside the pool at z = 3 below the water's height (so the
    // water's reflection, which goes up, never reaches it), facing the camera at z = 10,
    // whose narrow view holds only the screen, though the water is in its view cone.
    let mut scene = pool(&[]);
    let v = Vec3::new;
    scene
        .materials
        .push(Material::diffuse("screen", Vec3::splat(0.8)));
    scene.meshes.push(quad(
        2,
        [
            v(-3.0, 0.1, 3.0),
            v(3.0, 0.1, 3.0),
            v(3.0, 0.45, 3.0),
            v(-3.0, 0.45, 3.0),
        ],
    ));
    scene.camera = look_at_camera(v(0.0, 0.275, 10.0), v(0.0, 0.275, 0.0), Vec3::Y, 2.0);
    scene.default_resolution = (32, 32);
    expect_vcm(
        "seen after a bounce",
        &scene,
        "appear at no surface the camera sees first",
    );
}

/// The glass ball under a spot light: the light it reflects off the ball's outside onto
/// the floor (Fresnel) is a caustic no MNEE seed finds, so the plan keeps vcm and says so.
#[test]
fn a_reflected_caustic_keeps_vcm() {
    let plan = plan_of(&scene_path("glass-spot.gltf"));
    assert_eq!(plan.integrator, PlannedIntegrator::Vcm);
    assert!(
        plan.beyond_mnee
            .iter()
            .any(|r| r.contains("reflects off specular")),
        "{:?}",
        plan.beyond_mnee
    );
}

/// `scenes/mirror-caustic.gltf`: a point light's caustic under a glass ball, seen only in a
/// mirror. The analysis finds `L S+ D S+ E` from a delta light through the mirror and
/// plans vcm; bdpt would leave the caustic's reflection out and say so.
#[test]
fn mirror_caustic_gltf_is_a_delta_lit_sds_scene_for_vcm() {
    let plan = plan_of(&scene_path("mirror-caustic.gltf"));
    eprintln!("{}", plan.summary());
    assert!(plan.has(DeltaLitCaustics) && plan.has(DeltaLitSds));
    assert!(evidence(&plan, DeltaLitSds).contains("'mirror'"));
    assert_eq!(plan.integrator, PlannedIntegrator::Vcm);
    let caveat = plan
        .error_estimate_caveat(tessera_farm::job::Integrator::Bdpt)
        .unwrap();
    assert!(caveat.starts_with("cannot sample"), "{caveat}");
}
