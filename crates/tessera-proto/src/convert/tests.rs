//! Round trips and refusals of every wire conversion.

use super::*;
use prost::Message;

/// A way to break a message, and the field the error must name.
type Case<M> = (&'static str, fn(&mut M));
type BoxedCase<M> = (&'static str, Box<dyn Fn(&mut M)>);

const HASH: &str = "9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08";

fn plan() -> FramePlan {
    FramePlan::for_spp(70, 50, 64, 32).unwrap()
}

/// A result for `unit` of `plan()` whose values encode (pass, pixel, channel).
fn result(unit: WorkUnit) -> UnitResult {
    let rect = plan().tile(unit.tile);
    let mut pass_means = Vec::new();
    for p in 0..unit.pass_count {
        for px in 0..rect.pixel_count() {
            let v = p as f32 + px as f32 / 1000.0;
            pass_means.push([v, v + 0.25, v + 0.5]);
        }
    }
    UnitResult {
        unit,
        width: rect.width,
        height: rect.height,
        pass_means,
        rejected_samples: u64::from(unit.first_pass) * 1000 + 7,
        bias: None,
    }
}

/// Encodes and decodes through the protobuf wire format.
fn wire<M: Message + Default>(m: &M) -> M {
    M::decode(m.encode_to_vec().as_slice()).unwrap()
}

#[test]
fn frame_plan_round_trip() {
    for p in [
        plan(),
        FramePlan::new(1, 1, 4, 1, 1).unwrap(),
        FramePlan::new(16384, 16384, 256, 1024, 4).unwrap(),
    ] {
        let w = wire(&v1::FramePlan::from(&p));
        assert_eq!(FramePlan::try_from(w).unwrap(), p);
    }
}

#[test]
fn frame_plan_rejections_name_the_field() {
    let good = v1::FramePlan::from(plan());
    let cases: [Case<v1::FramePlan>; 9] = [
        ("width", |p| p.width = 0),
        ("width", |p| p.width = 1_000_000),
        ("height", |p| p.height = 0),
        ("height", |p| p.height = u32::MAX),
        ("tile_size", |p| p.tile_size = 2),
        ("tile_size", |p| p.tile_size = 1 << 30),
        ("samples_per_pass", |p| p.samples_per_pass = 0),
        ("passes", |p| p.passes = 0),
        ("passes", |p| {
            // Every field in range, but far too much work in total.
            p.width = 16384;
            p.height = 16384;
            p.samples_per_pass = 1024;
            p.passes = 65536;
        }),
    ];
    for (field, f) in cases {
        let mut p = good;
        f(&mut p);
        let e = FramePlan::try_from(p).unwrap_err();
        assert_eq!(e.field, field, "{e}");
        assert!(e.to_string().starts_with(&format!("{field}: ")));
    }
    // An all-default (empty) message is invalid, not a 0x0 image.
    assert_eq!(
        FramePlan::try_from(v1::FramePlan::default())
            .unwrap_err()
            .field,
        "width"
    );
}

#[test]
fn work_unit_round_trip_and_rejections() {
    for u in plan().units(3, 3) {
        assert_eq!(WorkUnit::try_from(wire(&v1::WorkUnit::from(u))).unwrap(), u);
    }
    let u = v1::WorkUnit {
        frame: 0,
        tile: 0,
        first_pass: 0,
        pass_count: 0,
    };
    assert_eq!(WorkUnit::try_from(u).unwrap_err().field, "pass_count");
    let u = v1::WorkUnit {
        first_pass: 65535,
        pass_count: 2,
        ..u
    };
    assert_eq!(WorkUnit::try_from(u).unwrap_err().field, "pass_count");
    let u = v1::WorkUnit {
        first_pass: u32::MAX,
        pass_count: u32::MAX,
        ..u
    };
    assert_eq!(WorkUnit::try_from(u).unwrap_err().field, "pass_count");
    let u = v1::WorkUnit {
        tile: MAX_TILE_INDEX + 1,
        first_pass: 0,
        pass_count: 1,
        ..u
    };
    assert_eq!(WorkUnit::try_from(u).unwrap_err().field, "tile");
    let u = v1::WorkUnit {
        tile: MAX_TILE_INDEX,
        first_pass: 65535,
        pass_count: 1,
        ..u
    };
    assert!(WorkUnit::try_from(u).is_ok());
    // MAX_TILE_INDEX is the last tile of the finest possible plan.
    let finest = FramePlan::new(16384, 16384, 4, 1, 1).unwrap();
    assert_eq!(finest.tile_count() - 1, MAX_TILE_INDEX);
}

#[test]
fn unit_result_round_trip() {
    let p = plan();
    for unit in p.units(2, 3) {
        let r = result(unit);
        let req = v1::SubmitResultRequest::from_result(5, 77, &r, 1.5);
        assert_eq!(
            req.means().len(),
            3 * unit.pass_count as usize * p.tile(unit.tile).pixel_count()
        );
        // Interleaved r, g, b.
        assert_eq!(&req.means()[..3], &r.pass_means[0][..]);
        let req = wire(&req);
        assert_eq!((req.worker_id, req.lease_id), (5, 77));
        assert_eq!(req.render_seconds, 1.5);
        assert_eq!(req.rejected_samples, r.rejected_samples);
        let back = UnitResult::try_from(&req).unwrap();
        // Bit-exact, and still valid for the plan.
        assert_eq!(back.digest(), r.digest());
        assert_eq!(back, r);
        back.validate(&p).unwrap();
        assert_eq!(UnitResult::try_from(req).unwrap(), r);
    }
}

#[test]
fn pass_means_are_packed_on_the_wire() {
    let unit = WorkUnit {
        frame: 0,
        tile: 0,
        first_pass: 0,
        pass_count: 1,
    };
    let r = UnitResult {
        unit,
        width: 4,
        height: 4,
        pass_means: vec![[1.0, 2.0, 3.0]; 16],
        rejected_samples: 0,
        bias: None,
    };
    let bytes = v1::SubmitResultRequest::from_result(1, 1, &r, 0.0).encode_to_vec();
    // 48 floats of 4 bytes plus a few bytes of tags and lengths (unpacked would add a
    // tag byte per float).
    assert!(bytes.len() < 48 * 4 + 32, "{} bytes", bytes.len());
}

/// The message as a worker from before `pass_means` became `bytes` encoded it: the
/// same fields, the means as `repeated float [packed = true]`.
#[derive(Clone, PartialEq, prost::Message)]
struct PackedFloatsRequest {
    #[prost(uint64, tag = "1")]
    worker_id: u64,
    #[prost(uint64, tag = "2")]
    lease_id: u64,
    #[prost(message, optional, tag = "3")]
    unit: Option<v1::WorkUnit>,
    #[prost(uint32, tag = "4")]
    width: u32,
    #[prost(uint32, tag = "5")]
    height: u32,
    #[prost(float, repeated, packed = "true", tag = "6")]
    pass_means: Vec<f32>,
    #[prost(double, tag = "7")]
    render_seconds: f64,
}

#[test]
fn pass_means_bytes_are_the_packed_floats_of_older_workers() {
    // (`rejected_samples` came later than these fields; the old message has none.)
    let r = UnitResult {
        rejected_samples: 0,
        bias: None,
        ..result(plan().units(1, 2)[1])
    };
    let old = PackedFloatsRequest {
        worker_id: 3,
        lease_id: 9,
        unit: Some(r.unit.into()),
        width: r.width,
        height: r.height,
        pass_means: r.pass_means.as_flattened().to_vec(),
        render_seconds: 0.25,
    };
    // An old worker's message, read by this coordinator: the same result, bit for bit.
    let now = v1::SubmitResultRequest::decode(old.encode_to_vec().as_slice()).unwrap();
    assert_eq!(UnitResult::try_from(&now).unwrap(), r);
    // This worker's message, read by an old coordinator: the same floats.
    let new = v1::SubmitResultRequest::from_result(3, 9, &r, 0.25);
    let back = PackedFloatsRequest::decode(new.encode_to_vec().as_slice()).unwrap();
    assert_eq!(back, old);
    // And the two encodings are the same bytes.
    assert_eq!(new.encode_to_vec(), old.encode_to_vec());
}

#[test]
fn unit_result_rejections_name_the_field() {
    let r = result(plan().units(0, 2)[0]);
    let good = v1::SubmitResultRequest::from_result(1, 2, &r, 0.5);
    assert_eq!(good.rejected_samples, r.rejected_samples);
    // A worker that predates `rejected_samples` sends none (the proto3 default): 0.
    let old = v1::SubmitResultRequest {
        rejected_samples: 0,
        ..good.clone()
    };
    let back = UnitResult::try_from(wire(&old)).unwrap();
    assert_eq!(back.rejected_samples, 0);
    // Up to every pixel-pass of the unit may be reported traced.
    let all = 2 * u64::from(good.width) * u64::from(good.height);
    let counted = v1::SubmitResultRequest {
        traced_pixel_passes: all,
        ..good.clone()
    };
    assert!(UnitResult::try_from(wire(&counted)).is_ok());
    let cases: [Case<v1::SubmitResultRequest>; 13] = [
        ("unit", |q| q.unit = None),
        ("unit.pass_count", |q| {
            q.unit.as_mut().unwrap().pass_count = 0
        }),
        ("width", |q| q.width = 0),
        ("height", |q| q.height = 0),
        ("width", |q| q.width = 100_000),
        ("height", |q| q.height = u32::MAX),
        ("pass_means", |q| {
            q.pass_means.pop();
        }),
        ("pass_means", |q| q.pass_means.extend(1.0f32.to_le_bytes())),
        ("pass_means", |q| {
            q.pass_means.truncate(q.pass_means.len() - 12)
        }),
        ("pass_means", |q| q.pass_means.extend([0u8; 12])),
        ("render_seconds", |q| q.render_seconds = f64::NAN),
        ("render_seconds", |q| q.render_seconds = -1.0),
        ("traced_pixel_passes", |q| {
            q.traced_pixel_passes = 2 * u64::from(q.width) * u64::from(q.height) + 1
        }),
    ];
    for (field, f) in cases {
        let mut q = good.clone();
        f(&mut q);
        let e = UnitResult::try_from(&q).unwrap_err();
        assert_eq!(e.field, field, "{e}");
    }
    let mut q = good.clone();
    q.pass_means.pop();
    let e = UnitResult::try_from(&q).unwrap_err();
    assert!(e.reason.contains("not a multiple of 12"), "{e}");
    let status = tonic::Status::from(e);
    assert_eq!(status.code(), tonic::Code::InvalidArgument);
    assert!(status.message().starts_with("pass_means: "));
    // Right shape, but the wrong tile size for the plan: caught by the farm's validate.
    let mut q = good.clone();
    q.width -= 1;
    q.pass_means
        .truncate(12 * 2 * q.width as usize * q.height as usize);
    let back = UnitResult::try_from(&q).unwrap();
    assert!(back.validate(&plan()).is_err());
    // Non-finite values pass the shape check and are refused by the farm's validate.
    let mut q = good;
    let mut means = q.means();
    means[4] = f32::NAN;
    q.set_means(&means);
    let back = UnitResult::try_from(&q).unwrap();
    assert!(back.validate(&plan()).is_err());
}

fn configs() -> Vec<RenderConfig> {
    let mut out = Vec::new();
    for integrator in [
        Integrator::Path,
        Integrator::Direct,
        Integrator::Bdpt,
        Integrator::Vcm,
        Integrator::Ppm,
        Integrator::Mlt,
        Integrator::Mnee,
    ] {
        for mis in [
            MisHeuristic::Balance,
            MisHeuristic::Power,
            MisHeuristic::Cutoff(0.1),
            MisHeuristic::Cutoff(1.0),
            MisHeuristic::Maximum,
        ] {
            for sampler in [SamplerKind::Sobol, SamplerKind::Independent] {
                out.push(RenderConfig {
                    integrator,
                    mis,
                    sampler,
                    seed: 0xdead_beef_0123_4567,
                    max_depth: 7,
                    rr_depth: 3,
                });
            }
        }
    }
    out
}

#[test]
fn render_settings_round_trip() {
    for c in configs() {
        let w = wire(&v1::RenderSettings::from(&c));
        assert_eq!(RenderConfig::try_from(w).unwrap(), c);
    }
    let c = RenderConfig {
        max_depth: 1024,
        rr_depth: 1024,
        seed: u64::MAX,
        ..RenderConfig::default()
    };
    assert_eq!(
        RenderConfig::try_from(v1::RenderSettings::from(c)).unwrap(),
        c
    );
}

#[test]
fn render_settings_rejections_name_the_field() {
    let good = v1::RenderSettings::from(RenderConfig::default());
    let cases: [Case<v1::RenderSettings>; 11] = [
        ("integrator", |s| s.integrator = 0),
        ("integrator", |s| s.integrator = 99),
        ("mis", |s| s.mis = 0),
        ("mis", |s| s.mis = -1),
        ("sampler", |s| s.sampler = 0),
        ("sampler", |s| s.sampler = 3),
        ("mis_cutoff_alpha", |s| {
            s.mis = v1::MisHeuristic::Cutoff.into();
            s.mis_cutoff_alpha = 0.0;
        }),
        ("mis_cutoff_alpha", |s| {
            s.mis = v1::MisHeuristic::Cutoff.into();
            s.mis_cutoff_alpha = f32::NAN;
        }),
        ("max_depth", |s| s.max_depth = 0),
        ("max_depth", |s| s.max_depth = 1025),
        ("rr_depth", |s| s.rr_depth = u32::MAX),
    ];
    for (field, f) in cases {
        let mut s = good;
        f(&mut s);
        let e = RenderConfig::try_from(s).unwrap_err();
        assert_eq!(e.field, field, "{e}");
        assert!(!e.reason.starts_with(field), "{e}");
    }
    // The empty message is rejected rather than read as some default.
    assert!(RenderConfig::try_from(v1::RenderSettings::default()).is_err());
    // mnee has its own number (8, after mlt's 7: never renumbered), and a value beyond the
    // newest this build knows is refused as coming from a newer peer, never guessed.
    assert_eq!(v1::Integrator::Mnee as i32, 8);
    assert_eq!(v1::Integrator::Mlt as i32, 7);
    let mut s = good;
    s.integrator = 9;
    let e = RenderConfig::try_from(s).unwrap_err();
    assert_eq!(e.field, "integrator");
    assert!(e.reason.contains("unknown value 9"), "{e}");
    // The cutoff threshold is ignored by the other heuristics.
    let mut s = good;
    s.mis_cutoff_alpha = 7.0;
    assert!(RenderConfig::try_from(s).is_ok());
}

fn leased() -> LeasedUnit {
    let p = plan();
    let unit = *p.units(4, 2).last().unwrap();
    let n = p.tile(unit.tile).pixel_count();
    LeasedUnit {
        lease_id: 12,
        deadline_unix_ms: 1_700_000_000_000,
        job_id: 3,
        scene: JobScene {
            source: SceneRef::Hash(HASH.into()),
            camera: Some("dolly".into()),
            fps: 30.0,
            animation: Some("walk".into()),
            shutter: Some(Shutter {
                open: -0.25,
                close: 0.5,
            }),
        },
        settings: configs()[7],
        plan: p,
        unit,
        // Pixels in blobs: the set an adaptive lease carries.
        wanted: Some(PixelRuns::from_fn(n, |i| (i / 7) % 3 != 1)),
        fence: vec![7; 32],
        environment: Some(JobEnvironment {
            source: EnvironmentSource::Image(HASH.into()),
            strength: 2.5,
            rotation_degrees: -90.0,
        }),
    }
}

#[test]
fn lease_round_trip() {
    let l = leased();
    let w = wire(&v1::Lease::from(&l));
    assert_eq!(w.scene_hash, HASH);
    assert_eq!(LeasedUnit::try_from(w).unwrap(), l);
    let l = LeasedUnit {
        scene: JobScene {
            source: SceneRef::Builtin("cornell-box".into()),
            camera: None,
            ..leased().scene
        },
        wanted: None,
        // Not every float is a short decimal: the wire carries them exactly.
        environment: Some(JobEnvironment {
            source: EnvironmentSource::Colour([0.1, 1.0 / 3.0, 0.0]),
            strength: 0.7,
            rotation_degrees: 12.345,
        }),
        ..leased()
    };
    let w = v1::Lease::from(l.clone());
    assert_eq!(w.scene_hash, "builtin:cornell-box");
    assert_eq!(LeasedUnit::try_from(w).unwrap(), l);
    // A whole LeaseResponse survives the wire.
    let resp = v1::LeaseResponse {
        leases: vec![v1::Lease::from(leased()), v1::Lease::from(l)],
        retry_after_ms: 0,
    };
    assert_eq!(wire(&resp), resp);
    // A present but empty pixel list means every pixel, like an absent one.
    let mut w = v1::Lease::from(&leased());
    w.wanted = Some(v1::PixelRuns { runs: Vec::new() });
    assert_eq!(LeasedUnit::try_from(wire(&w)).unwrap().wanted, None);
    // The runs survive the wire exactly.
    let l = leased();
    let back = LeasedUnit::try_from(wire(&v1::Lease::from(&l))).unwrap();
    assert_eq!(back.wanted, l.wanted);
    assert!(back.wanted.as_ref().unwrap().runs().len() > 3);
}

#[test]
fn lease_rejections_name_the_field() {
    let good = v1::Lease::from(leased());
    let tiles = plan().tile_count();
    let passes = plan().passes;
    let cases: Vec<BoxedCase<v1::Lease>> = vec![
        ("scene_hash", Box::new(|l| l.scene_hash.clear())),
        (
            "scene_hash",
            Box::new(|l| l.scene_hash = "../../etc/passwd".into()),
        ),
        (
            "shutter",
            Box::new(|l| {
                l.shutter = Some(v1::Shutter {
                    open: 0.5,
                    close: 0.5,
                })
            }),
        ),
        (
            "shutter",
            Box::new(|l| {
                l.shutter = Some(v1::Shutter {
                    open: f64::NAN,
                    close: 0.5,
                })
            }),
        ),
        ("settings", Box::new(|l| l.settings = None)),
        (
            "settings.sampler",
            Box::new(|l| l.settings.as_mut().unwrap().sampler = 0),
        ),
        ("plan", Box::new(|l| l.plan = None)),
        (
            "plan.tile_size",
            Box::new(|l| l.plan.as_mut().unwrap().tile_size = 0),
        ),
        ("unit", Box::new(|l| l.unit = None)),
        (
            "unit.pass_count",
            Box::new(|l| l.unit.as_mut().unwrap().pass_count = 0),
        ),
        (
            "unit.tile",
            Box::new(move |l| l.unit.as_mut().unwrap().tile = tiles),
        ),
        (
            "unit.pass_count",
            Box::new(move |l| {
                let u = l.unit.as_mut().unwrap();
                u.first_pass = passes - 1;
                u.pass_count = 2;
            }),
        ),
        // Malformed pixel sets: refused naming the field, never a panic.
        (
            "wanted.runs",
            Box::new(|l| l.wanted.as_mut().unwrap().runs.push(3)),
        ),
        (
            "wanted.runs",
            Box::new(|l| l.wanted = Some(v1::PixelRuns { runs: vec![5, 0] })),
        ),
        (
            "wanted.runs",
            Box::new(|l| {
                l.wanted = Some(v1::PixelRuns {
                    runs: vec![9, 2, 3, 1],
                })
            }),
        ),
        (
            "wanted.runs",
            // The edge tile has 6 x 18 = 108 pixels.
            Box::new(|l| l.wanted = Some(v1::PixelRuns { runs: vec![100, 9] })),
        ),
        (
            "wanted.runs",
            Box::new(|l| {
                l.wanted = Some(v1::PixelRuns {
                    runs: vec![u32::MAX, u32::MAX],
                })
            }),
        ),
    ];
    for (field, f) in cases {
        let mut l = good.clone();
        f(&mut l);
        let e = LeasedUnit::try_from(l).unwrap_err();
        assert_eq!(e.field, field, "{e}");
    }
}

#[test]
fn generated_service_metadata() {
    use tonic::server::NamedService;
    struct Nop;
    #[tonic::async_trait]
    impl crate::WorkerService for Nop {
        async fn register(
            &self,
            _: tonic::Request<v1::RegisterRequest>,
        ) -> Result<tonic::Response<v1::RegisterResponse>, tonic::Status> {
            Err(tonic::Status::unimplemented("register"))
        }
        async fn heartbeat(
            &self,
            _: tonic::Request<v1::HeartbeatRequest>,
        ) -> Result<tonic::Response<v1::HeartbeatResponse>, tonic::Status> {
            Err(tonic::Status::unimplemented("heartbeat"))
        }
        async fn lease_work(
            &self,
            _: tonic::Request<v1::LeaseRequest>,
        ) -> Result<tonic::Response<v1::LeaseResponse>, tonic::Status> {
            Err(tonic::Status::unimplemented("lease_work"))
        }
        async fn submit_result(
            &self,
            _: tonic::Request<v1::SubmitResultRequest>,
        ) -> Result<tonic::Response<v1::SubmitResultResponse>, tonic::Status> {
            Err(tonic::Status::unimplemented("submit_result"))
        }
        type FetchSceneStream = std::pin::Pin<
            Box<
                dyn tonic::codegen::tokio_stream::Stream<
                        Item = Result<v1::SceneChunk, tonic::Status>,
                    > + Send,
            >,
        >;
        async fn fetch_scene(
            &self,
            _: tonic::Request<v1::FetchSceneRequest>,
        ) -> Result<tonic::Response<Self::FetchSceneStream>, tonic::Status> {
            Err(tonic::Status::unimplemented("fetch_scene"))
        }
        async fn return_leases(
            &self,
            _: tonic::Request<v1::ReturnLeasesRequest>,
        ) -> Result<tonic::Response<v1::ReturnLeasesResponse>, tonic::Status> {
            Err(tonic::Status::unimplemented("return_leases"))
        }
    }
    let _server = crate::WorkerServiceServer::new(Nop);
    assert_eq!(
        <crate::WorkerServiceServer<Nop> as NamedService>::NAME,
        crate::SERVICE_NAME
    );
}

#[test]
fn a_lease_without_an_environment_has_none_and_a_bad_one_is_refused_by_field() {
    let l = LeasedUnit {
        environment: None,
        ..leased()
    };
    let w = wire(&v1::Lease::from(&l));
    assert!(w.environment.is_none());
    assert_eq!(LeasedUnit::try_from(w).unwrap(), l);
    let bad = |f: fn(&mut v1::Environment), field: &str| {
        let mut w = v1::Lease::from(leased());
        f(w.environment.as_mut().unwrap());
        let e = LeasedUnit::try_from(w).unwrap_err();
        assert_eq!(e.field, field, "{e}");
    };
    bad(|e| e.image_hash = "ABC".into(), "environment.image_hash");
    bad(
        |e| e.image_hash = HASH.to_uppercase(),
        "environment.image_hash",
    );
    bad(|e| e.colour = vec![1.0; 3], "environment.colour");
    bad(
        |e| {
            e.image_hash.clear();
            e.colour = vec![1.0, 1.0];
        },
        "environment.colour",
    );
    bad(
        |e| {
            e.image_hash.clear();
            e.colour = vec![1.0, f32::NAN, 1.0];
        },
        "environment.colour",
    );
    bad(|e| e.strength = -1.0, "environment.strength");
    bad(|e| e.strength = f32::INFINITY, "environment.strength");
    bad(
        |e| e.rotation_degrees = 361.0,
        "environment.rotation_degrees",
    );
}

/// The bias channel: a biased result round-trips bit for bit; an unbiased one sends no
/// bias bytes (its message is what it was before the field existed) and a message without
/// them decodes to no channel; a channel of the wrong length is refused, naming `bias`.
#[test]
fn bias_channel_round_trips_and_is_absent_when_empty() {
    let plain = result(plan().units(0, 2)[0]);
    let m = v1::SubmitResultRequest::from_result(1, 2, &plain, 0.5);
    assert!(m.bias.is_empty());
    assert_eq!(UnitResult::try_from(wire(&m)).unwrap(), plain);
    let n = plain.pass_means.len();
    let biased = UnitResult {
        bias: Some((0..n).map(|i| i as f32 * -0.125 + 0.5).collect()),
        ..plain.clone()
    };
    let m = v1::SubmitResultRequest::from_result(1, 2, &biased, 0.5);
    assert_eq!(m.bias.len(), 4 * n);
    let back = UnitResult::try_from(wire(&m)).unwrap();
    assert_eq!(back, biased);
    assert_eq!(back.digest(), biased.digest());
    let mut short = m.clone();
    short.bias.truncate(4 * n - 4);
    assert_eq!(UnitResult::try_from(&short).unwrap_err().field, "bias");
}
