//! One job vocabulary, one resolution path (the redesign issue): for a table of settings
//! — every integrator (auto, path, direct, bdpt) times every adaptive mode, on a tiled
//! glTF scene and on a glTF scene whose plan is bdpt (a spot light through glass), each
//! rendered from a named camera — `tessera render` and a farm job give byte-identical
//! EXRs, headers included (ARCHITECTURE.md §2).

mod common;

use std::path::Path;

use common::farm::{start_coordinator, start_worker, wait_done};
use common::{output_ok, temp_dir, tessera, Proc};
use tessera_api::client::Client;
use tessera_api::JobSettings;

/// `tessera render FILE` with the flags that give the settings `s` (whose scene is the
/// file's uploaded hash).
fn local_render(file: &Path, s: &JobSettings, out: &Path) -> Vec<u8> {
    let mut cmd = tessera();
    cmd.arg("render")
        .arg(file)
        .args(["--camera", s.camera.as_deref().unwrap()])
        .args(["--width", &s.width.unwrap().to_string()])
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

#[test]
fn tessera_render_and_the_farm_write_the_same_exr_for_every_setting() {
    let dir = temp_dir("e2e", "local-and-farm");
    let c = start_coordinator(&dir.join("data"), "127.0.0.1:0", "127.0.0.1:0", &[]);
    let _ws: Vec<Proc> = (0..2)
        .map(|i| start_worker(&c.grpc, &format!("w{i}"), &[]))
        .collect();
    let client = Client::new(&c.http, None);
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenes");
    // (file, camera, whether the render plan chooses bdpt)
    let scenes = [
        ("cornell-box.gltf", "camera", false),
        ("glass-spot.gltf", "main", true),
    ];
    let mut compared = 0;
    for (file, camera, plan_is_bdpt) in scenes {
        let path = root.join(file);
        let uploaded = client.upload_scene(&std::fs::read(&path).unwrap()).unwrap();
        for integrator in ["auto", "path", "direct", "bdpt"] {
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
                // bdpt, chosen by the plan or asked for, renders one whole-frame tile.
                let bdpt = integrator == "bdpt" || (integrator == "auto" && plan_is_bdpt);
                assert_eq!(done.tiles_total == 1, bdpt, "{case}: tiles");
                // Issue 15: a done job with a target says whether it reached it.
                assert_eq!(
                    done.target_reached.is_some(),
                    s.target_error.is_some(),
                    "{case}: {done:?}"
                );
                assert_eq!(done.stop_reason.is_some(), adaptive != "off", "{case}");
                let farm = client.image(st.id, "exr").unwrap();
                let out = dir.join(format!("{compared}.exr"));
                let local = local_render(&path, &s, &out);
                assert!(
                    farm == local,
                    "{case}: the farm's EXR differs from tessera render's"
                );
                compared += 1;
            }
        }
    }
    assert_eq!(compared, 24);
    let _ = std::fs::remove_dir_all(&dir);
}
