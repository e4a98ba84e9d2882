//! Tests of the job contract: validation names the field, the canonical form round-trips.

use super::*;

const HASH: &str = "9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08";

fn base() -> JobSettings {
    JobSettings::new("builtin:cornell-box")
}

/// `f` makes a setting bad: it must be rejected, naming `field`, with a message
/// starting with the field name.
fn rejects(field: &str, f: impl FnOnce(&mut JobSettings)) -> JobError {
    let mut s = base();
    f(&mut s);
    let e = s.validate().expect_err(field);
    assert_eq!(e.field, field, "{e}");
    assert!(e.to_string().starts_with(&format!("{field}: ")), "{e}");
    e
}

fn accepts(f: impl FnOnce(&mut JobSettings)) -> ValidatedJob {
    let mut s = base();
    f(&mut s);
    match s.validate() {
        Ok(j) => j,
        Err(e) => panic!("rejected: {e}"),
    }
}

#[test]
fn defaults() {
    let s: JobSettings = serde_json::from_str(r#"{"scene":"builtin:cornell-box"}"#).unwrap();
    assert_eq!(s, base());
    let j = s.validate().unwrap();
    assert_eq!(j.scene.source, SceneRef::Builtin("cornell-box".into()));
    assert_eq!((j.width, j.height), (None, None));
    assert_eq!(j.spp, 64);
    assert_eq!(j.render, RenderRequest::default());
    // The depth is left to the render plan (or the general configuration's 16) until the
    // job is resolved against its scene.
    assert_eq!(j.render.max_depth, None);
    assert_eq!(j.frames, FrameRange { start: 0, end: 0 });
    assert_eq!(j.priority, 0);
    assert_eq!(j.adaptive, AdaptiveMode::Off);
    assert_eq!(j.tile_size, 32);
    assert_eq!((j.target_error, j.time_limit_seconds), (None, None));
    assert_eq!(j.name, None);
}

#[test]
fn full_json_round_trip() {
    let json = serde_json::json!({
        "scene": HASH, "width": 640, "height": 480, "spp": 256,
        "integrator": "bdpt", "mis": "cutoff:0.25", "sampler": "independent",
        "seed": u64::MAX, "max_depth": 32, "frames": {"start": 2, "end": 9},
        "priority": -5, "target_error": 0.02, "adaptive": "unbiased",
        "time_limit_seconds": 12.5, "tile_size": 64, "name": "turntable"
    });
    let s: JobSettings = serde_json::from_value(json.clone()).unwrap();
    assert_eq!(serde_json::to_value(&s).unwrap(), json);
    let j = s.validate().unwrap();
    assert_eq!(j.scene.source, SceneRef::Hash(HASH.into()));
    assert_eq!(j.render.integrator, IntegratorChoice::BDPT);
    assert_eq!(j.render.mis, MisHeuristic::Cutoff(0.25));
    assert_eq!(j.render.sampler, SamplerKind::Independent);
    assert_eq!(j.render.seed, u64::MAX);
    assert_eq!(j.render.max_depth, Some(32));
    assert_eq!(j.frames.count(), 8);
    assert_eq!(j.adaptive, AdaptiveMode::Unbiased);
    // The canonical form validates to the same job and is stable.
    let canon = j.to_settings();
    assert_eq!(canon, s);
    assert_eq!(canon.validate().unwrap(), j);
}

#[test]
fn canonical_form_normalizes_spellings() {
    let j = accepts(|s| {
        s.scene = HASH.to_ascii_uppercase();
        s.mis = "max".into();
    });
    let c = j.to_settings();
    assert_eq!(c.scene, HASH);
    assert_eq!(c.mis, "maximum");
    // The canonical form keeps a depth left to the plan unset.
    assert_eq!(c.max_depth, None);
    assert_eq!(c.validate().unwrap(), j);
    let j = accepts(|s| s.mis = "cutoff".into());
    assert_eq!(j.render.mis, MisHeuristic::Cutoff(0.1));
    assert_eq!(j.to_settings().mis, "cutoff:0.1");
    assert_eq!(j.to_settings().validate().unwrap(), j);
}

#[test]
fn scene() {
    rejects("scene", |s| s.scene = String::new());
    rejects("scene", |s| s.scene = "builtin:".into());
    rejects("scene", |s| s.scene = "builtin:../etc/passwd".into());
    rejects("scene", |s| s.scene = "builtin:a b".into());
    rejects("scene", |s| s.scene = format!("builtin:{}", "x".repeat(65)));
    rejects("scene", |s| s.scene = HASH[..63].into());
    rejects("scene", |s| s.scene = format!("{HASH}0"));
    rejects("scene", |s| s.scene = format!("{}g", &HASH[..63]));
    rejects("scene", |s| s.scene = "scenes/room.gltf".into());
    accepts(|s| s.scene = "builtin:veach-mis".into());
    accepts(|s| s.scene = format!("builtin:{}", "x".repeat(64)));
    assert_eq!(
        accepts(|s| s.scene = HASH.into()).scene.source.hash(),
        Some(HASH)
    );
}

#[test]
fn width_and_height() {
    for field in ["width", "height"] {
        let set = |s: &mut JobSettings, v| {
            if field == "width" {
                s.width = Some(v)
            } else {
                s.height = Some(v)
            }
        };
        let e = rejects(field, |s| set(s, 0));
        assert_eq!(
            e.to_string(),
            format!("{field}: must be between 1 and 16384, got 0")
        );
        rejects(field, |s| set(s, 16385));
        rejects(field, |s| set(s, u32::MAX));
        accepts(|s| set(s, 1));
        accepts(|s| set(s, 16384));
    }
}

#[test]
fn spp() {
    let e = rejects("spp", |s| s.spp = 0);
    assert_eq!(e.to_string(), "spp: must be between 1 and 1048576, got 0");
    rejects("spp", |s| s.spp = 1_048_577);
    accepts(|s| s.spp = 1);
    accepts(|s| s.spp = 1_048_576);
    // Absurd total work with a known size is refused up front, naming spp.
    let e = rejects("spp", |s| {
        s.width = Some(16384);
        s.height = Some(16384);
        s.spp = 1_048_576;
    });
    assert!(e.to_string().contains("more than the limit"), "{e}");
    accepts(|s| {
        s.width = Some(16384);
        s.height = Some(16384);
        s.spp = 4096;
    });
}

#[test]
fn enumerations() {
    for (field, good, bad) in [
        (
            "integrator",
            &[
                "auto", "path", "direct", "bdpt", "vcm", "ppm", "mlt", "mnee",
            ][..],
            &["", "Path", "pt", "photon", "MNEE", "manifold"][..],
        ),
        (
            "mis",
            &[
                "balance",
                "power",
                "cutoff",
                "cutoff:0.5",
                "cutoff:1",
                "maximum",
                "max",
            ][..],
            &[
                "",
                "cutoff:0",
                "cutoff:1.5",
                "cutoff:-0.1",
                "cutoff:x",
                "cutoff:NaN",
                "heuristic",
            ][..],
        ),
        (
            "sampler",
            &["sobol", "independent"][..],
            &["", "halton", "Sobol"][..],
        ),
        (
            "adaptive",
            &["off", "sequential", "unbiased"][..],
            &["", "on", "true"][..],
        ),
    ] {
        let set = |s: &mut JobSettings, v: &str| match field {
            "integrator" => s.integrator = v.into(),
            "mis" => s.mis = v.into(),
            "sampler" => s.sampler = v.into(),
            _ => {
                s.adaptive = v.into();
                s.target_error = Some(0.05);
            }
        };
        for v in good {
            accepts(|s| set(s, v));
        }
        for v in bad {
            let e = rejects(field, |s| set(s, v));
            assert!(
                e.to_string().contains("expected") || e.to_string().contains("cutoff"),
                "{e}"
            );
        }
    }
}

#[test]
fn max_depth() {
    rejects("max_depth", |s| s.max_depth = Some(0));
    rejects("max_depth", |s| s.max_depth = Some(1025));
    assert_eq!(accepts(|s| s.max_depth = Some(1)).render.max_depth, Some(1));
    assert_eq!(
        accepts(|s| s.max_depth = Some(1024)).render.max_depth,
        Some(1024)
    );
}

#[test]
fn frames() {
    let e = rejects("frames.end", |s| s.frames = FrameRange { start: 5, end: 4 });
    assert_eq!(
        e.to_string(),
        "frames.end: must not be less than frames.start (5), got 4"
    );
    rejects("frames", |s| {
        s.frames = FrameRange {
            start: 0,
            end: 100_000,
        }
    });
    rejects("frames", |s| {
        s.frames = FrameRange {
            start: 0,
            end: u32::MAX,
        }
    });
    let j = accepts(|s| {
        s.frames = FrameRange {
            start: 0,
            end: 99_999,
        }
    });
    assert_eq!(j.frames.count(), 100_000);
    let j = accepts(|s| {
        s.frames = FrameRange {
            start: u32::MAX,
            end: u32::MAX,
        }
    });
    assert_eq!(j.frames.iter().collect::<Vec<_>>(), vec![u32::MAX]);
}

#[test]
fn target_error() {
    for bad in [0.0, -0.1, 1.0001, f64::NAN, f64::INFINITY] {
        rejects("target_error", |s| s.target_error = Some(bad));
    }
    for good in [1e-6, 0.01, 1.0] {
        accepts(|s| s.target_error = Some(good));
    }
}

#[test]
fn shutter() {
    for (open, close) in [
        (0.25, 0.25),
        (0.5, -0.5),
        (-1.5, 0.0),
        (0.0, 1.01),
        (f64::NAN, 0.5),
        (0.0, f64::INFINITY),
    ] {
        rejects("shutter", |s| s.shutter = Some(Shutter { open, close }));
    }
    let j = accepts(|s| {
        s.shutter = Some(Shutter {
            open: -0.25,
            close: 0.25,
        })
    });
    // The key times: SHUTTER_SEGMENTS + 1, evenly from the opening to the closing.
    let keys = j.scene.shutter.unwrap().key_frames(12);
    assert_eq!(keys.len(), SHUTTER_SEGMENTS as usize + 1);
    assert_eq!((keys[0], *keys.last().unwrap()), (11.75, 12.25));
    // The JSON form is a pair.
    let raw: JobSettings =
        serde_json::from_str(r#"{"scene": "builtin:cornell-box", "shutter": [-1, 1]}"#).unwrap();
    assert_eq!(
        raw.shutter,
        Some(Shutter {
            open: -1.0,
            close: 1.0
        })
    );
    assert!(serde_json::from_str::<JobSettings>(
        r#"{"scene": "builtin:cornell-box", "shutter": [0.5]}"#
    )
    .is_err());
}

#[test]
fn time_limit() {
    for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
        rejects("time_limit_seconds", |s| s.time_limit_seconds = Some(bad));
    }
    accepts(|s| s.time_limit_seconds = Some(0.001));
    accepts(|s| s.time_limit_seconds = Some(86_400.0));
}

#[test]
fn tile_size() {
    rejects("tile_size", |s| s.tile_size = 3);
    rejects("tile_size", |s| s.tile_size = 257);
    rejects("tile_size", |s| s.tile_size = 0);
    accepts(|s| s.tile_size = 4);
    accepts(|s| s.tile_size = 256);
}

#[test]
fn name() {
    rejects("name", |s| s.name = Some("x".repeat(201)));
    rejects("name", |s| s.name = Some("line\nbreak".into()));
    accepts(|s| s.name = Some("x".repeat(200)));
    // Characters, not bytes.
    accepts(|s| s.name = Some("é".repeat(200)));
    accepts(|s| s.name = Some(String::new()));
}

#[test]
fn priority_and_seed_take_any_value() {
    for p in [i32::MIN, -1, 0, i32::MAX] {
        assert_eq!(accepts(|s| s.priority = p).priority, p);
    }
    assert_eq!(accepts(|s| s.seed = u64::MAX).render.seed, u64::MAX);
}

#[test]
fn render_config_validate() {
    assert!(RenderConfig::default().validate().is_ok());
    let bad = |f: fn(&mut RenderConfig), field: &str| {
        let mut c = RenderConfig::default();
        f(&mut c);
        assert_eq!(c.validate().unwrap_err().field, field);
    };
    bad(|c| c.max_depth = 0, "max_depth");
    bad(|c| c.rr_depth = 1025, "rr_depth");
    bad(|c| c.mis = MisHeuristic::Cutoff(0.0), "mis");
    bad(|c| c.mis = MisHeuristic::Cutoff(f32::NAN), "mis");
}

#[test]
fn plan_errors_name_fields() {
    let j = base().validate().unwrap();
    let p = j.plan_for(j.render.integrator, 640, 480).unwrap();
    assert_eq!(
        (p.width, p.height, p.tile_size, p.spp()),
        (640, 480, 32, 64)
    );
    assert_eq!(
        j.plan_for(j.render.integrator, 0, 480).unwrap_err().field,
        "width"
    );
    // bdpt plans one whole-frame tile, and refuses frames too large for it by name.
    let mut b = j.clone();
    b.render.integrator = IntegratorChoice::BDPT;
    let p = b.plan_for(b.render.integrator, 640, 480).unwrap();
    assert_eq!((p.tile_count(), p.tile_size), (1, 640));
    assert_eq!(
        p.spp(),
        j.plan_for(j.render.integrator, 640, 480).unwrap().spp()
    );
    let e = b.plan_for(b.render.integrator, 2048, 2048).unwrap_err();
    assert_eq!(e.field, "width");
    assert!(e.to_string().contains("whole-frame tile"), "{e}");
    assert_eq!(
        j.plan_for(j.render.integrator, 640, 0).unwrap_err().field,
        "height"
    );
    let mut big = j.clone();
    big.spp = MAX_SPP;
    assert_eq!(
        big.plan_for(big.render.integrator, 16384, 16384)
            .unwrap_err()
            .field,
        "spp"
    );
}

#[test]
fn resolution_follows_the_scene_aspect() {
    assert_eq!(resolve_resolution(None, None, (400, 300)), (400, 300));
    assert_eq!(resolve_resolution(Some(800), None, (400, 300)), (800, 600));
    assert_eq!(resolve_resolution(None, Some(150), (400, 300)), (200, 150));
    assert_eq!(resolve_resolution(Some(1), None, (400, 300)), (1, 1));
    assert_eq!(resolve_resolution(Some(7), Some(9), (400, 300)), (7, 9));
    let j = accepts(|s| s.width = Some(100));
    assert_eq!(j.resolution((512, 256)), (100, 50));
}

#[test]
fn choices_parse_their_display() {
    for m in [
        MisHeuristic::Balance,
        MisHeuristic::Power,
        MisHeuristic::Cutoff(0.1),
        MisHeuristic::Cutoff(0.3333333),
        MisHeuristic::Maximum,
    ] {
        assert_eq!(m.to_string().parse::<MisHeuristic>().unwrap(), m);
        let json = serde_json::to_string(&m).unwrap();
        assert_eq!(serde_json::from_str::<MisHeuristic>(&json).unwrap(), m);
    }
    for i in [
        IntegratorChoice::Auto,
        IntegratorChoice::PATH,
        IntegratorChoice::DIRECT,
        IntegratorChoice::BDPT,
    ] {
        assert_eq!(i.as_str().parse::<IntegratorChoice>().unwrap(), i);
    }
    let c = RenderConfig::default();
    let json = serde_json::to_string(&c).unwrap();
    assert_eq!(
        json,
        r#"{"integrator":"path","mis":"power","sampler":"sobol","seed":0,"max_depth":16,"rr_depth":5}"#
    );
    assert_eq!(serde_json::from_str::<RenderConfig>(&json).unwrap(), c);
    assert!(serde_json::from_str::<SceneRef>(r#""builtin:""#).is_err());
}

/// Regression (redesign issue): `tessera render` refused adaptive stopping without a
/// target error while the API accepted it and stopped at 100%; both refuse it now.
#[test]
fn adaptive_stopping_needs_a_target() {
    let e = rejects("target_error", |s| s.adaptive = "sequential".into());
    assert!(e.to_string().contains("needs a target error"), "{e}");
    accepts(|s| {
        s.adaptive = "unbiased".into();
        s.target_error = Some(0.02);
    });
    // Off needs none.
    accepts(|s| s.adaptive = "off".into());
}

#[test]
fn camera_and_min_passes() {
    rejects("camera", |s| s.camera = Some(String::new()));
    rejects("camera", |s| s.camera = Some("a\tb".into()));
    assert_eq!(
        accepts(|s| s.camera = Some("dolly".into()))
            .scene
            .camera
            .as_deref(),
        Some("dolly")
    );
    rejects("min_passes", |s| s.min_passes = 1);
    rejects("min_passes", |s| s.min_passes = 1025);
    assert_eq!(accepts(|s| s.min_passes = 2).min_passes, 2);
    // Defaults are left out of the canonical JSON, so older clients' bodies round-trip.
    let json = serde_json::to_value(base()).unwrap();
    assert!(json.get("camera").is_none() && json.get("min_passes").is_none());
}

#[test]
fn environment_is_a_colour_or_an_image_hash_with_strength_and_rotation() {
    assert!(base().validate().unwrap().environment.is_none());
    let j = accepts(|s| {
        s.environment = Some(EnvironmentSettings {
            source: "0.5, 1, 2".into(),
            strength: 2.0,
            rotation_degrees: -90.0,
        })
    });
    // The canonical form validates back to the same job.
    assert_eq!(j.to_settings().validate().unwrap(), j);
    let e = j.environment.unwrap();
    assert_eq!(e.source, EnvironmentSource::Colour([0.5, 1.0, 2.0]));
    assert_eq!(e.radiance(), [1.0, 2.0, 4.0]);
    let j = accepts(|s| s.environment = Some(EnvironmentSettings::new(HASH.to_uppercase())));
    let e = j.environment.unwrap();
    assert_eq!(e.source, EnvironmentSource::Image(HASH.into()));
    assert_eq!(e.radiance(), [1.0; 3]);
    for bad in ["1,1", "a,b,c", "1,1,-1", "1,1,inf", "sky.hdr", ""] {
        rejects("environment.source", |s| {
            s.environment = Some(EnvironmentSettings::new(bad))
        });
    }
    rejects("environment.strength", |s| {
        s.environment = Some(EnvironmentSettings {
            strength: -1.0,
            ..EnvironmentSettings::new("1,1,1")
        })
    });
    rejects("environment.rotation_degrees", |s| {
        s.environment = Some(EnvironmentSettings {
            rotation_degrees: 400.0,
            ..EnvironmentSettings::new("1,1,1")
        })
    });
    // Absent, it is not serialized (stored jobs keep their bytes); defaults are omitted.
    assert!(!serde_json::to_string(&base())
        .unwrap()
        .contains("environment"));
    let mut s = base();
    s.environment = Some(EnvironmentSettings::new("1,1,1"));
    let json = serde_json::to_string(&s).unwrap();
    assert!(
        json.ends_with(r#""environment":{"source":"1,1,1"}}"#),
        "{json}"
    );
    assert_eq!(serde_json::from_str::<JobSettings>(&json).unwrap(), s);
}

/// The render plan of a scene with a light path class no connection technique samples
/// (the pool: `L S D S E` from a point light), as the analysis reports it.
fn pool_plan() -> RenderPlan {
    RenderPlan {
        effects: vec![Effect {
            kind: EffectKind::DeltaLitSds,
            evidence: "1 delta light seen through material 1 'water'".into(),
        }],
        absent: vec![],
        integrator: PlannedIntegrator::Vcm,
        max_depth: 8,
        rr_depth: 5,
        lens_sampling: false,
        reasons: vec!["vcm: L S+ D S+ E".into()],
        overridden: None,
        warnings: vec![],
        technique_pilot: None,
        beyond_mnee: vec![],
    }
}

/// Runs the adaptive policy `settings` of `plan` over passes whose every pixel is black
/// (what bdpt renders of the pool's floor) and returns the fewest passes a pixel got.
fn fewest_passes_of_black_passes(plan: crate::FramePlan, settings: crate::AdaptiveSettings) -> u32 {
    let mut frame = crate::AdaptiveFrame::new(plan, 0, settings).unwrap();
    while !frame.finished() {
        let round = frame.next_round();
        assert!(!round.is_empty(), "an unfinished policy with nothing to do");
        for unit in round {
            let rect = plan.tile(unit.tile);
            let result = crate::UnitResult {
                unit,
                width: rect.width,
                height: rect.height,
                pass_means: vec![[0.0; 3]; rect.pixel_count() * unit.pass_count as usize],
                rejected_samples: 0,
                bias: None,
            };
            frame.offer(&result).unwrap();
        }
    }
    frame.samples_per_pixel().1 / plan.samples_per_pass
}

/// No pixel stops as converged while the integrator cannot sample a light path class of
/// the scene (`StopVerdict::unsampled`): the floor bdpt renders black has an estimate of
/// zero, and the job's own adaptive settings stop it at the first decision (the test can
/// fail), while the resolved job's run every pass, in both adaptive modes. vcm and ppm,
/// which sample the class, keep the job's settings.
#[test]
fn no_pixel_stops_converged_while_a_class_is_unsampled() {
    let facts = SceneFacts {
        default_resolution: (16, 16),
    };
    for mode in ["sequential", "unbiased"] {
        let mut s = base();
        s.integrator = "bdpt".into();
        s.adaptive = mode.into();
        s.target_error = Some(0.05);
        // 32 whole-frame passes of 16: room for the decisions and the unbiased pilot.
        s.spp = 512;
        let job = s.validate().unwrap();
        let r = job.resolve(facts, pool_plan()).unwrap();
        assert!(StopVerdict::unsampled_of(&r), "{mode}");
        let all = r.plan.passes;
        let raw = fewest_passes_of_black_passes(r.plan, job.adaptive_settings().unwrap());
        assert!(
            raw < all,
            "{mode}: the job's settings stop black pixels ({raw} of {all})"
        );
        let held = fewest_passes_of_black_passes(r.plan, r.adaptive_settings().unwrap());
        assert_eq!(
            held, all,
            "{mode}: a pixel stopped while a class is unsampled"
        );
        for integrator in ["vcm", "ppm"] {
            s.integrator = integrator.into();
            let job = s.validate().unwrap();
            let r = job.resolve(facts, pool_plan()).unwrap();
            assert!(!StopVerdict::unsampled_of(&r), "{integrator}");
            assert_eq!(
                r.adaptive_settings(),
                job.adaptive_settings(),
                "{integrator}"
            );
        }
    }
}

#[test]
fn adaptive_whole_frame_plans_have_room_for_the_unbiased_pilot() {
    // bdpt (and vcm, ppm, mlt) render one whole-frame tile; under adaptive stopping they
    // take the adaptive plan's short passes, so unbiased stopping's pilot of 8 passes and
    // its fresh passes fit a budget of 64 spp (4 passes of 16 would be refused).
    let mut s = base();
    s.integrator = "bdpt".into();
    s.adaptive = "unbiased".into();
    s.target_error = Some(0.1);
    let j = s.validate().unwrap();
    let p = j.plan_for(j.render.integrator, 640, 480).unwrap();
    assert_eq!((p.tile_count(), p.tile_size), (1, 640));
    assert_eq!((p.samples_per_pass, p.passes), (2, 32));
    j.adaptive_settings()
        .unwrap()
        .validate(p.passes)
        .expect("the unbiased pilot fits");
    // Without adaptive stopping the whole-frame plan keeps its few large passes.
    let mut u = j.clone();
    u.adaptive = AdaptiveMode::Off;
    let p = u.plan_for(u.render.integrator, 640, 480).unwrap();
    assert_eq!((p.samples_per_pass, p.passes), (16, 4));
}

/// A plan that chooses mnee resolves to it at the plan's depth, tiled like path tracing;
/// on the pool (every caustic within MNEE's reach: `beyond_mnee` empty) nothing is
/// unsampled, while where MNEE cannot reach a caveat says what it misses and the render
/// holds every pixel to its passes, as for bdpt.
#[test]
fn mnee_resolves_in_tiles_and_is_unsampled_only_beyond_its_reach() {
    let facts = SceneFacts {
        default_resolution: (64, 64),
    };
    let mut plan = pool_plan();
    plan.integrator = PlannedIntegrator::Mnee;
    plan.max_depth = 12;
    let mut s = base();
    s.tile_size = 16;
    let job = s.validate().unwrap();
    let r = job.resolve(facts, plan.clone()).unwrap();
    assert_eq!(r.config.integrator, Integrator::Mnee);
    assert_eq!((r.config.max_depth, r.config.rr_depth), (12, 5));
    assert_eq!(r.plan.tile_count(), 16);
    assert!(r.render_plan.overridden.is_none());
    assert!(!StopVerdict::unsampled_of(&r));
    // Asked for explicitly: the same integrator, tiles, and nothing unsampled.
    s.integrator = "mnee".into();
    let r = s.validate().unwrap().resolve(facts, plan.clone()).unwrap();
    assert_eq!(r.config.integrator, Integrator::Mnee);
    assert_eq!(r.plan.tile_count(), 16);
    assert!(!StopVerdict::unsampled_of(&r));
    // Beyond MNEE's reach (a vcm plan that says why): forcing mnee leaves the class
    // unsampled, and the caveat names what MNEE misses.
    let mut beyond = pool_plan();
    beyond.beyond_mnee = vec!["light of point light 0 reflects off specular material 1".into()];
    let r = s.validate().unwrap().resolve(facts, beyond).unwrap();
    assert!(StopVerdict::unsampled_of(&r));
    let caveat = r.error_estimate_caveat().unwrap();
    assert!(caveat.starts_with("cannot sample"), "{caveat}");
    assert!(
        caveat.contains("reflects off specular material 1"),
        "{caveat}"
    );
}
