//! One job vocabulary, one resolution path: for a table of settings
//! — every integrator (auto, path, direct, bdpt, vcm, ppm, mlt; mnee on the pool) times every adaptive mode, on a
//! tiled glTF scene and on a glTF scene whose plan renders one whole-frame tile (a spot
//! light through glass, seen through the glass: vcm), each
//! rendered from a named camera — `tessera render` and a farm job give byte-identical
//! EXRs, headers included (ARCHITECTURE.md §2), vcm's and ppm's with their bias layers
//! under every adaptive mode. And every frame of an animated multi-frame
//! job is byte-identical to `tessera render --frame F`.

use crate::common;

use std::path::Path;

use common::farm::{spawn_worker, start_coordinator, start_worker, wait_done, Coord};
use common::{output, output_ok, poll, read_exr, run, temp_dir, tessera, Proc};
use tessera_api::client::Client;
use tessera_api::JobSettings;

/// `tessera render FILE` with the flags that give the settings `s` (whose scene is the
/// file's uploaded hash), plus `extra` flags.
fn local_render(file: &Path, s: &JobSettings, out: &Path, extra: &[&str]) -> Vec<u8> {
    let mut cmd = tessera();
    cmd.arg("render").arg(file).args(extra);
    if let Some(c) = s.camera.as_deref() {
        cmd.args(["--camera", c]);
    }
    cmd.args(["--width", &s.width.unwrap().to_string()])
        .args(["--height", &s.height.unwrap().to_string()])
        .args(["--spp", &s.spp.to_string()])
        .args(["--seed", &s.seed.to_string()])
        .args(["--tile-size", &s.tile_size.to_string()])
        .args(["--integrator", &s.integrator])
        .args(["--adaptive", &s.adaptive])
        .arg("-o")
        .arg(out);
    if let Some(t) = s.target_error {
        cmd.args(["--target-error", &t.to_string()]);
    }
    output_ok(&mut cmd);
    std::fs::read(out).unwrap()
}

/// A coordinator on loopback with its store under `dir` and two one-thread workers, and
/// a client of its HTTP API (keep the first two alive while the test runs).
fn two_worker_farm(dir: &Path) -> (Coord, Vec<Proc>, Client) {
    let c = start_coordinator(&dir.join("data"), "127.0.0.1:0", "127.0.0.1:0", &[]);
    let ws = (0..2)
        .map(|i| start_worker(&c.grpc, &format!("w{i}"), &[]))
        .collect();
    let client = Client::new(&c.http, None);
    (c, ws, client)
}

#[test]
fn tessera_render_and_the_farm_write_the_same_exr_for_every_setting() {
    let dir = temp_dir("e2e", "local-and-farm");
    let (_c, _ws, client) = two_worker_farm(&dir);
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenes");
    // (file, camera, whether the render plan chooses a whole-frame integrator)
    let scenes = [
        ("cornell-box.gltf", "camera", false),
        ("glass-spot.gltf", "main", true),
    ];
    let mut compared = 0;
    for (file, camera, plan_is_bdpt) in scenes {
        let path = root.join(file);
        let uploaded = client.upload_scene(&std::fs::read(&path).unwrap()).unwrap();
        for integrator in ["auto", "path", "direct", "bdpt", "vcm", "ppm", "mlt"] {
            for adaptive in ["off", "sequential", "unbiased"] {
                let mut s = JobSettings::new(uploaded.hash.clone());
                s.camera = Some(camera.into());
                s.width = Some(20);
                s.height = Some(16);
                s.spp = 256;
                s.seed = 3;
                s.tile_size = 8;
                s.integrator = integrator.into();
                s.adaptive = adaptive.into();
                if adaptive != "off" {
                    s.target_error = Some(0.1);
                }
                let case = format!("{file} --integrator {integrator} --adaptive {adaptive}");
                let st = client.submit(&s, None).unwrap();
                let done = wait_done(&client, st.id);
                // bdpt, vcm, ppm and mlt, chosen by the plan or asked for, render
                // one whole-frame tile.
                let bdpt = ["bdpt", "vcm", "ppm", "mlt"].contains(&integrator)
                    || (integrator == "auto" && plan_is_bdpt);
                assert_eq!(done.tiles_total == 1, bdpt, "{case}: tiles");
                // A done job with a target says whether it reached it.
                assert_eq!(
                    done.target_reached.is_some(),
                    s.target_error.is_some(),
                    "{case}: {done:?}"
                );
                assert_eq!(done.stop_reason.is_some(), adaptive != "off", "{case}");
                let farm = client.image(st.id, "exr").unwrap();
                let out = dir.join(format!("{compared}.exr"));
                let local = local_render(&path, &s, &out, &[]);
                assert!(
                    farm == local,
                    "{case}: the farm's EXR differs from tessera render's"
                );
                // Vertex merging carries its bias layers in every adaptive mode (the
                // adaptive policy keeps each pixel's bias statistics), so the comparison
                // covers them.
                if ["vcm", "ppm"].contains(&integrator) {
                    let exr = tessera_image::read_exr(&local).unwrap();
                    assert!(exr.get("bias.Y").is_ok(), "{case}: no bias layers");
                }
                compared += 1;
            }
        }
    }
    assert_eq!(compared, 42);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Path tracing with manifold next-event estimation, asked for (`--integrator mnee`) and
/// chosen by the plan (`auto` on the pool: a point light's caustic seen through flat
/// water), renders in tiles like path tracing, and the farm's EXR is byte-identical to
/// `tessera render`'s, headers included; the job's status names no class it cannot
/// sample.
#[test]
fn tessera_render_and_the_farm_write_the_same_exr_with_mnee() {
    let dir = temp_dir("e2e", "local-and-farm-mnee");
    let (_c, _ws, client) = two_worker_farm(&dir);
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenes/pool.gltf");
    let uploaded = client.upload_scene(&std::fs::read(&path).unwrap()).unwrap();
    for (i, integrator) in ["mnee", "auto"].into_iter().enumerate() {
        let mut s = JobSettings::new(uploaded.hash.clone());
        s.width = Some(20);
        s.height = Some(16);
        s.spp = 8;
        s.seed = 4;
        s.tile_size = 8;
        s.integrator = integrator.into();
        let case = format!("pool.gltf --integrator {integrator}");
        let st = client.submit(&s, None).unwrap();
        let done = wait_done(&client, st.id);
        assert!(done.tiles_total > 1, "{case}: mnee tiles like path");
        let caveat = done.error_estimate_caveat.clone().unwrap_or_default();
        assert!(!caveat.contains("cannot sample"), "{case}: {caveat}");
        let farm = client.image(st.id, "exr").unwrap();
        let local = local_render(&path, &s, &dir.join(format!("mnee{i}.exr")), &[]);
        assert!(
            farm == local,
            "{case}: the farm's EXR differs from tessera render's"
        );
        let exr = tessera_image::read_exr(&local).unwrap();
        assert!(exr.get("bias.Y").is_err(), "{case}: mnee is unbiased");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// A multi-frame job of an animated scene (Blender's keyframed cubes) on two
/// workers, at 2.4 frames per second so that frames 0, 1 and 2 are the scene at t = 0,
/// 5/12 and 5/6 s: each frame's EXR is byte-identical to `tessera render --frame F
/// --fps 2.4`, and the frames differ, since the cubes move.
#[test]
fn every_frame_of_an_animated_farm_job_equals_tessera_render_frame() {
    let dir = temp_dir("e2e", "animated-frames");
    let (c, _ws, client) = two_worker_farm(&dir);
    let path =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/fixtures/animation/anim_cube.glb");
    let uploaded = client.upload_scene(&std::fs::read(&path).unwrap()).unwrap();
    let mut s = JobSettings::new(uploaded.hash.clone());
    s.width = Some(24);
    s.height = Some(16);
    s.spp = 16;
    s.seed = 5;
    s.tile_size = 8;
    s.fps = 2.4;
    s.frames = tessera_api::FrameRange { start: 0, end: 2 };
    let st = client.submit(&s, None).unwrap();
    wait_done(&client, st.id);
    let mut frames = Vec::new();
    for f in 0..=2u32 {
        let farm = client
            .get_raw(&format!(
                "/api/v1/jobs/{}/image?format=exr&frame={f}",
                st.id
            ))
            .unwrap();
        let out = dir.join(format!("frame{f}.exr"));
        let frame = f.to_string();
        let local = local_render(&path, &s, &out, &["--frame", &frame, "--fps", "2.4"]);
        assert!(
            farm == local,
            "frame {f}: the farm's EXR differs from tessera render --frame {f}"
        );
        frames.push(out);
    }
    // `tessera submit --wait -o seq_##.exr` writes the sequence, one file per frame,
    // the same bytes.
    let pattern = dir.join("seq_##.exr");
    output_ok(tessera().args([
        "submit",
        path.to_str().unwrap(),
        "--server",
        &c.http,
        "--width",
        "24",
        "--height",
        "16",
        "--spp",
        "16",
        "--seed",
        "5",
        "--tile-size",
        "8",
        "--fps",
        "2.4",
        "--frame-end",
        "2",
        "--wait",
        "-o",
        pattern.to_str().unwrap(),
    ]));
    for (f, local) in frames.iter().enumerate() {
        let seq = dir.join(format!("seq_{f:02}.exr"));
        assert!(
            std::fs::read(&seq).unwrap() == std::fs::read(local).unwrap(),
            "{}: differs from tessera render --frame {f}",
            seq.display()
        );
    }
    // The frames differ because the cubes move, not only because each frame has its own
    // seeds: frame 2 at t = 5/6 s against frame 2 of the same job at 1e6 fps (t = 2e-6 s,
    // clamped to the first keyframe, which is the pose of frame 0).
    let still = dir.join("still.exr");
    local_render(&path, &s, &still, &["--frame", "2", "--fps", "1000000"]);
    let (moving, still) = (read_exr(&frames[2]), read_exr(&still));
    assert_ne!(
        moving.get("R").unwrap(),
        still.get("R").unwrap(),
        "the cubes did not move"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// Motion blur: Blender's moving sphere and turning cube with a shutter of one
/// frame on two workers, all 24 frames with the path tracer and frames 11 and 12 with
/// bdpt: each frame's EXR is byte-identical to `tessera render --frame F
/// --shutter=-0.5,0.5`, frames differ where the scene moves, and the blurred frame
/// differs from the same frame without a shutter.
#[test]
fn a_motion_blurred_farm_job_equals_tessera_render_with_the_shutter() {
    let dir = temp_dir("e2e", "motion-blur");
    let (_c, _ws, client) = two_worker_farm(&dir);
    let path =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/fixtures/motion/motion_ball.glb");
    let uploaded = client.upload_scene(&std::fs::read(&path).unwrap()).unwrap();
    for (integrator, first, last) in [("auto", 1, 24), ("bdpt", 11, 12)] {
        let mut s = JobSettings::new(uploaded.hash.clone());
        s.width = Some(24);
        s.height = Some(16);
        s.spp = 8;
        s.seed = 3;
        s.tile_size = 8;
        s.integrator = integrator.into();
        s.shutter = Some(tessera_api::Shutter {
            open: -0.5,
            close: 0.5,
        });
        s.frames = tessera_api::FrameRange {
            start: first,
            end: last,
        };
        let st = client.submit(&s, None).unwrap();
        wait_done(&client, st.id);
        for f in first..=last {
            let farm = client
                .get_raw(&format!(
                    "/api/v1/jobs/{}/image?format=exr&frame={f}",
                    st.id
                ))
                .unwrap();
            let out = dir.join(format!("{integrator}-{f}.exr"));
            let frame = f.to_string();
            let local = local_render(&path, &s, &out, &["--frame", &frame, "--shutter=-0.5,0.5"]);
            assert!(
                farm == local,
                "{integrator} frame {f}: the farm's EXR differs from tessera render --frame {f} \
                 --shutter=-0.5,0.5"
            );
        }
        // The white sphere moves from left to right over frames 1..24: the left half's
        // share of the light falls from the first frame to the last (not only noise: each
        // frame has its own seeds, so a plain inequality would prove nothing).
        let left_share = |f: u32| {
            let img = read_exr(dir.join(format!("{integrator}-{f}.exr")));
            let (w, r) = (img.width, img.get("R").unwrap());
            let left: f32 = r
                .iter()
                .enumerate()
                .filter(|(i, _)| i % w < w / 2)
                .map(|(_, v)| v)
                .sum();
            left / r.iter().sum::<f32>()
        };
        let (a, b) = (left_share(first), left_share(last));
        assert!(
            integrator == "bdpt" || a > b + 0.02,
            "{integrator}: the left half's share of the light is {a:.3} at frame {first} and \
             {b:.3} at frame {last}: the sphere did not move"
        );
        let sharp = dir.join(format!("{integrator}-sharp.exr"));
        local_render(&path, &s, &sharp, &["--frame", "12"]);
        let blurred = read_exr(dir.join(format!("{integrator}-12.exr")));
        assert_ne!(
            blurred.get("R").unwrap(),
            read_exr(&sharp).get("R").unwrap(),
            "{integrator}: the shutter changed nothing"
        );
    }
    // What `tessera render` says about the shutter.
    let said = output_ok(tessera().args([
        "render",
        path.to_str().unwrap(),
        "--frame",
        "12",
        "--shutter=-0.5,0.5",
        "--width",
        "8",
        "--height",
        "8",
        "--spp",
        "1",
        "-o",
        dir.join("said.exr").to_str().unwrap(),
    ]));
    assert!(
        said.contains("motion blur: shutter [-0.5, 0.5] frames: 2220 triangles move (8 linear segments), the camera is still; time sampled"),
        "{said}"
    );
    let (ok, _, err) = run(&[
        "render",
        path.to_str().unwrap(),
        "--shutter=0.5,-0.5",
        "-o",
        dir.join("bad.exr").to_str().unwrap(),
    ]);
    assert!(
        !ok && err.contains("invalid --shutter: must open before it closes"),
        "{err}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// Environment lighting on the farm: Khronos' BoxVertexColors, which has no light of its
/// own (black without an environment), lit by a uniform colour and by an uploaded HDR
/// image (strength and rotation set), with path tracing and bdpt: each farm EXR is
/// byte-identical to `tessera render --environment` with the same settings, and its
/// header and the job's plan name the environment. The image case with path tracing goes
/// through `tessera submit --environment FILE`, which uploads the file.
#[test]
fn a_farm_job_lit_by_an_environment_equals_tessera_render_with_it() {
    let dir = temp_dir("e2e", "environment-farm");
    let (c, _ws, client) = two_worker_farm(&dir);
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../tests/fixtures/khronos/BoxVertexColors.gltf");
    let uploaded = client.upload_scene(&std::fs::read(&path).unwrap()).unwrap();
    // A sky: bluish above, brown below, a bright patch low in the east.
    let sky = tessera_testkit::gltf_gen::radiance_hdr(32, 16, |x, y| {
        if (20..24).contains(&x) && (5..7).contains(&y) {
            [40.0, 36.0, 30.0]
        } else if y < 8 {
            [0.4, 0.6, 1.0]
        } else {
            [0.3, 0.2, 0.15]
        }
    });
    let sky_file = dir.join("sky.hdr");
    std::fs::write(&sky_file, &sky).unwrap();
    let sky_hash = client.upload_scene(&sky).unwrap().hash;
    let sky_name = sky_file.to_str().unwrap();
    let cases = [
        ("0.6,0.7,0.9", "path"),
        ("0.6,0.7,0.9", "bdpt"),
        (sky_name, "path"),
        (sky_name, "bdpt"),
    ];
    for (i, (env, integrator)) in cases.into_iter().enumerate() {
        let image = env == sky_name;
        let mut s = JobSettings::new(uploaded.hash.clone());
        s.width = Some(20);
        s.height = Some(16);
        s.spp = 16;
        s.seed = 11;
        s.tile_size = 8;
        s.integrator = integrator.into();
        let (strength, rotation) = ("1.5", if image { "30" } else { "0" });
        let mut e = tessera_api::EnvironmentSettings::new(if image { &sky_hash } else { env });
        e.strength = 1.5;
        e.rotation_degrees = if image { 30.0 } else { 0.0 };
        s.environment = Some(e);
        let case = format!("--environment {env} --integrator {integrator}");
        let farm = if image && integrator == "path" {
            let out = dir.join(format!("submit{i}.exr"));
            output_ok(tessera().args([
                "submit",
                path.to_str().unwrap(),
                "--server",
                &c.http,
                "--width",
                "20",
                "--height",
                "16",
                "--spp",
                "16",
                "--seed",
                "11",
                "--tile-size",
                "8",
                "--integrator",
                integrator,
                "--environment",
                env,
                "--environment-strength",
                strength,
                "--environment-rotation",
                rotation,
                "--wait",
                "-o",
                out.to_str().unwrap(),
            ]));
            std::fs::read(&out).unwrap()
        } else {
            let st = client.submit(&s, None).unwrap();
            let done = wait_done(&client, st.id);
            let plan = done
                .plan
                .as_ref()
                .map(|p| p.to_string())
                .unwrap_or_default();
            assert!(plan.contains("environment"), "{case}: the plan {plan}");
            client.image(st.id, "exr").unwrap()
        };
        let out = dir.join(format!("env{i}.exr"));
        let local = local_render(
            &path,
            &s,
            &out,
            &[
                "--environment",
                env,
                "--environment-strength",
                strength,
                "--environment-rotation",
                rotation,
            ],
        );
        assert!(
            farm == local,
            "{case}: the farm's EXR differs from tessera render's"
        );
        let named = if image {
            sky_hash.as_str()
        } else {
            "[0.6,0.7,0.9]"
        };
        let header = b"\"environment\":{\"source\":";
        assert!(
            contains(&farm, header) && contains(&farm, named.as_bytes()),
            "{case}: the EXR header does not name the environment"
        );
        // Lit: the scene has no light of its own, so an environment that did not reach
        // the workers would leave it black.
        let exr = read_exr(&out);
        let red = exr.get("R").unwrap();
        assert!(red.iter().any(|&v| v > 0.0), "{case}: the image is black");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// Whether `needle` occurs in `hay`.
fn contains(hay: &[u8], needle: &[u8]) -> bool {
    hay.windows(needle.len()).any(|w| w == needle)
}

/// The determinism contract across traversal kernels (ARCHITECTURE.md §2): two workers
/// forced to different kernels (`TESSERA_ISA=scalar` and the widest this CPU has) share
/// every job, and the farm's EXR equals `tessera render`'s (default kernel) byte for
/// byte, on the Cornell box and on a glTF scene of a few thousand triangles, with and
/// without adaptive stopping. On a CPU with only the scalar kernel both workers run it,
/// which the test says.
#[test]
fn workers_on_different_kernels_write_tessera_renders_exr() {
    use tessera_render::geometry::Isa;
    let dir = temp_dir("e2e", "kernels");
    // A kernel the CPU lacks (or no kernel at all) is refused at start, so the workers
    // below really run the kernels they name.
    let (ok, _, err) = output(tessera().env("TESSERA_ISA", "avx1024").args([
        "worker",
        "--coordinator",
        "http://127.0.0.1:9",
    ]));
    assert!(!ok && err.contains("TESSERA_ISA=avx1024: unknown"), "{err}");
    let wide = Isa::best();
    if wide == Isa::Scalar {
        eprintln!("this CPU has only the scalar kernel: both workers run it");
    }
    let c = start_coordinator(&dir.join("data"), "127.0.0.1:0", "127.0.0.1:0", &[]);
    let _ws: Vec<Proc> = [Isa::Scalar, wide]
        .into_iter()
        .enumerate()
        .map(|(i, isa)| {
            let mut cmd = tessera();
            cmd.env("TESSERA_ISA", isa.name());
            spawn_worker(cmd, &[&c.grpc], &format!("w{i}-{}", isa.name()), &[], None)
        })
        .collect();
    let client = Client::new(&c.http, None);
    poll(
        "both workers registered",
        std::time::Duration::from_secs(60),
        || client.workers().is_ok_and(|w| w.workers.len() == 2),
    );
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenes");
    let file = root.join("indirect-room.gltf");
    let uploaded = client.upload_scene(&std::fs::read(&file).unwrap()).unwrap();
    let mut compared = 0;
    for (scene, path) in [
        ("builtin:cornell-box".to_string(), None),
        (uploaded.hash.clone(), Some(file.as_path())),
    ] {
        for adaptive in ["off", "sequential"] {
            let mut s = JobSettings::new(scene.clone());
            s.width = Some(32);
            s.height = Some(24);
            s.spp = 64;
            s.seed = 7;
            s.tile_size = 8;
            s.adaptive = adaptive.into();
            if adaptive != "off" {
                s.target_error = Some(0.2);
            }
            let st = client.submit(&s, None).unwrap();
            wait_done(&client, st.id);
            let farm = client.image(st.id, "exr").unwrap();
            let out = dir.join(format!("{compared}.exr"));
            let local = match path {
                Some(path) => local_render(path, &s, &out, &[]),
                None => {
                    let mut cmd = tessera();
                    cmd.args(["render", &s.scene, "--width", "32", "--height", "24"])
                        .args(["--spp", "64", "--seed", "7", "--tile-size", "8"])
                        .args(["--adaptive", adaptive]);
                    if adaptive != "off" {
                        cmd.args(["--target-error", "0.2"]);
                    }
                    output_ok(cmd.arg("-o").arg(&out));
                    std::fs::read(&out).unwrap()
                }
            };
            assert!(
                farm == local,
                "{scene} --adaptive {adaptive}: the farm's EXR (workers on scalar and {}) \
                 differs from tessera render's",
                wide.name()
            );
            compared += 1;
        }
    }
    assert_eq!(compared, 4);
    // Both kernels took part: 4 jobs of 12 tiles (and their passes) over two workers
    // that each take one unit at a time.
    let w = client.workers().unwrap().workers;
    assert!(
        w.iter().all(|w| w.units_done > 0),
        "a worker rendered nothing, so the kernels were not mixed: {w:?}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
