//! The farm as users run it: real `tessera` processes on loopback, real HTTP and gRPC, a
//! real SQLite file, `kill -9`. Every wait polls with a timeout; nothing sleeps a fixed
//! time to let something happen.
//!
//! The reference for every image is `tessera render` with the same settings: rendering is
//! a pure function of (scene, settings, seed, pixel, pass), so the farm's EXR must be
//! byte-identical to it however the work was distributed or interrupted (ARCHITECTURE.md §2).

use crate::common;
use tessera_testkit::{api_error, metric};

use common::farm::{
    cornell_job as job, local_render, local_render_adaptive, local_render_with, start_coordinator,
    start_worker, stored_passes, wait_done, TIMEOUT,
};
use common::{free_addresses, http_get, output, poll, read_exr, temp_dir, tessera, Proc};
use tessera_api::client::Client;
use tessera_api::JobSettings;

#[test]
fn one_and_three_workers_give_the_local_image_byte_for_byte() {
    let dir = temp_dir("e2e", "workers");
    let s = job(48, 40, 32);
    let reference = local_render(&dir, &s);
    let mut images = Vec::new();
    for workers in [1, 3] {
        let data = dir.join(format!("data{workers}"));
        let c = start_coordinator(&data, "127.0.0.1:0", "127.0.0.1:0", &[]);
        let _ws: Vec<Proc> = (0..workers)
            .map(|i| start_worker(&c.grpc, &format!("w{i}"), &[]))
            .collect();
        let client = Client::new(&c.http, None);
        let st = client.submit(&s, None).unwrap();
        let done = wait_done(&client, st.id);
        assert_eq!(done.passes_done, done.passes_planned);
        let exr = client.image(st.id, "exr").unwrap();
        images.push(exr);
        // Every worker took part when there are three (the plan has 2 x 2 tiles x 4 passes).
        let w = client.workers().unwrap();
        assert_eq!(w.workers.len(), workers);
    }
    assert!(
        images[0] == reference,
        "1 worker: EXR differs from tessera render"
    );
    assert!(
        images[1] == reference,
        "3 workers: EXR differs from tessera render"
    );
}

#[test]
fn adaptive_farm_jobs_are_identical_with_one_and_three_workers() {
    let dir = temp_dir("e2e", "adaptive");
    let mut images = Vec::new();
    for (mode, target) in [("sequential", 0.08), ("unbiased", 0.08)] {
        let mut per_mode = Vec::new();
        let mut local = job(48, 48, 256);
        local.adaptive = mode.into();
        local.target_error = Some(target);
        let reference = local_render_adaptive(&dir, &format!("local-{mode}.exr"), &local);
        for workers in [1, 3] {
            let data = dir.join(format!("data-{mode}-{workers}"));
            let c = start_coordinator(&data, "127.0.0.1:0", "127.0.0.1:0", &[]);
            let _ws: Vec<Proc> = (0..workers)
                .map(|i| start_worker(&c.grpc, &format!("w{i}"), &[]))
                .collect();
            let client = Client::new(&c.http, None);
            let mut s = job(48, 48, 256);
            s.adaptive = mode.into();
            s.target_error = Some(target);
            let st = client.submit(&s, None).unwrap();
            let done = wait_done(&client, st.id);
            // Adaptive stopping spent fewer samples than the budget somewhere.
            assert!(done.spp_so_far < 256.0, "{mode}: {} spp", done.spp_so_far);
            per_mode.push(client.image(st.id, "exr").unwrap());
        }
        assert!(
            per_mode[0] == per_mode[1],
            "{mode}: adaptive EXR differs between 1 and 3 workers"
        );
        // Leases name only the pixels still wanted and the image is still the
        // local render's, byte for byte.
        assert!(
            per_mode[0] == reference,
            "{mode}: adaptive farm EXR differs from tessera render"
        );
        images.push(per_mode.swap_remove(0));
    }
    assert!(images[0] != images[1], "the two modes gave the same image");
}

/// A stopped pixel costs nothing on the farm. The workers report the
/// pixel-passes they traced (`tessera_worker_pixel_passes_total`): for an adaptive job
/// whose pixels mostly stop early it equals the pixel-passes `tessera render` used for
/// the same image (its `samples.Y` layer over the samples per pass), and is far below
/// whole tiles' worth, while the EXR stays byte-identical to the local one. Measured:
/// 42% and 32% of whole tiles on the Cornell box (unbiased, sequential), 43% and 35% on
/// the caustic (bdpt).
#[test]
fn adaptive_farm_traces_only_the_pixels_still_wanted() {
    let dir = temp_dir("e2e", "adaptive-traced");
    // The Cornell box (path: a stopped pixel traces nothing) and the caustic, whose plan is
    // bdpt (a stopped pixel traces its light subpaths only; the count is of camera
    // subpaths). Before bdpt skipped them, the caustic traced all 73,728 pixel-passes.
    for scene in ["builtin:cornell-box", "builtin:caustic"] {
        for mode in ["unbiased", "sequential"] {
            let mut s = job(48, 48, 512);
            s.scene = scene.into();
            s.adaptive = mode.into();
            s.target_error = Some(0.1);
            let name = format!("{}-{mode}", scene.trim_start_matches("builtin:"));
            let reference = local_render_adaptive(&dir, &format!("local-{name}.exr"), &s);
            let local = read_exr(dir.join(format!("local-{name}.exr")));
            // adaptive plan for 512 spp: 32 passes of 16 samples.
            let (samples_per_pass, passes) = (16.0, 32.0);
            let local_pixel_passes: f64 = local
                .get("samples.Y")
                .unwrap()
                .iter()
                .map(|&v| f64::from(v) / samples_per_pass)
                .sum();
            let full = 48.0 * 48.0 * passes;
            let c = start_coordinator(
                &dir.join(format!("data-{name}")),
                "127.0.0.1:0",
                "127.0.0.1:0",
                // Counted for merged units only, so a unit rendered twice counts once.
                &[],
            );
            let _w = start_worker(&c.grpc, "w0", &[]);
            let client = Client::new(&c.http, None);
            let st = client.submit(&s, None).unwrap();
            wait_done(&client, st.id);
            let exr = client.image(st.id, "exr").unwrap();
            assert!(
                exr == reference,
                "{name}: farm EXR differs from tessera render"
            );
            let (status, body) = http_get(&c.http, "/metrics");
            assert_eq!(status, 200, "{body}");
            let traced = metric(&body, "tessera_worker_pixel_passes_total").expect("the metric");
            println!(
                "{name}: pixel-passes traced on the farm {traced}, used by tessera render \
                 {local_pixel_passes}, whole tiles {full}"
            );
            assert_eq!(
                traced, local_pixel_passes,
                "{name}: the farm traced other pixels than the local render used"
            );
            assert!(
                traced < 0.6 * full,
                "{name}: {traced} of {full} pixel-passes traced: too few pixels stopped early"
            );
        }
    }
}

#[test]
fn a_killed_worker_loses_nothing() {
    let dir = temp_dir("e2e", "kill-worker");
    let s = job(64, 64, 128);
    let reference = local_render(&dir, &s);
    let c = start_coordinator(&dir.join("data"), "127.0.0.1:0", "127.0.0.1:0", &[]);
    let mut victim = start_worker(&c.grpc, "victim", &[]);
    let client = Client::new(&c.http, None);
    let st = client.submit(&s, None).unwrap();
    // Kill the only worker in the middle of the job, holding leases.
    poll("a third of the passes", TIMEOUT, || {
        let j = client.job(st.id).unwrap();
        j.passes_done * 3 >= j.passes_planned
    });
    victim.kill9();
    let mid = client.job(st.id).unwrap();
    assert!(
        mid.passes_done < mid.passes_planned,
        "the job finished before the kill"
    );
    // A new worker picks up the rest, including the dead worker's leases once they lapse.
    let _w = start_worker(&c.grpc, "rescuer", &[]);
    wait_done(&client, st.id);
    let exr = client.image(st.id, "exr").unwrap();
    assert!(exr == reference, "EXR after a worker was killed differs");
}

#[test]
fn a_killed_coordinator_resumes_and_loses_no_job() {
    let dir = temp_dir("e2e", "kill-coordinator");
    let data = dir.join("data");
    let s = job(64, 64, 128);
    let reference = local_render(&dir, &s);
    let (http, grpc) = free_addresses();
    let mut c = start_coordinator(&data, &http, &grpc, &[]);
    let _w1 = start_worker(&c.grpc, "w1", &[]);
    let _w2 = start_worker(&c.grpc, "w2", &[]);
    let client = Client::new(&c.http, None);
    let running = client.submit(&s, None).unwrap();
    // A second job that stays queued behind it (lower priority): it must survive too.
    let mut queued = job(16, 16, 8);
    queued.priority = -1;
    queued.name = Some("queued".into());
    let queued = client.submit(&queued, Some("key-1")).unwrap();
    poll("a quarter of the passes", TIMEOUT, || {
        let j = client.job(running.id).unwrap();
        j.passes_done * 4 >= j.passes_planned
    });
    // Killed once the store holds some of them (`stored_passes`: the status also counts
    // passes whose group commit is still on its way).
    let store = data.join("tessera.sqlite3");
    poll("passes committed to the store", TIMEOUT, || {
        stored_passes(store.to_str().unwrap(), running.id) > 0
    });
    c.proc.kill9();
    // Restart on the same data directory and addresses; the workers reconnect by themselves.
    let c2 = start_coordinator(&data, &http, &grpc, &[]);
    let client = Client::new(&c2.http, None);
    let after = client.job(running.id).unwrap();
    assert!(
        after.passes_done > 0,
        "merged passes were lost in the restart"
    );
    assert!(after.passes_done < after.passes_planned);
    let done = wait_done(&client, running.id);
    assert_eq!(done.passes_done, done.passes_planned);
    let exr = client.image(running.id, "exr").unwrap();
    assert!(exr == reference, "EXR after a coordinator restart differs");
    // The queued job was not lost, and its idempotency key still maps to it.
    let mut again = job(16, 16, 8);
    again.priority = -1;
    again.name = Some("queued".into());
    assert_eq!(client.submit(&again, Some("key-1")).unwrap().id, queued.id);
    wait_done(&client, queued.id);
    assert_eq!(client.jobs(10, None).unwrap().jobs.len(), 2);
}

/// The adaptive policy's state is checkpointed with its tiles. `kill -9` of
/// the coordinator in the middle of an adaptive job, for both modes: the restarted
/// coordinator resumes from the merged passes and the decisions taken on them (before,
/// an adaptive job started again from pass 0), redoing at most the units in flight, and
/// the job ends byte-identical to `tessera render`. A further restart once it is done
/// rebuilds the finished image from the store alone: the policy's image, not the
/// accumulator of every leased pass (which averages in a discarded pilot and the zeros of
/// stopped pixels).
#[test]
fn a_killed_coordinator_resumes_an_adaptive_job_where_its_policy_was() {
    let dir = temp_dir("e2e", "kill-adaptive");
    for (mode, target) in [("unbiased", 0.06), ("sequential", 0.06)] {
        let mut s = job(64, 64, 1024);
        s.adaptive = mode.into();
        s.target_error = Some(target);
        let reference = local_render_adaptive(&dir, &format!("local-{mode}.exr"), &s);
        let data = dir.join(format!("data-{mode}"));
        let (http, grpc) = free_addresses();
        let mut c = start_coordinator(&data, &http, &grpc, &[]);
        let _w1 = start_worker(&c.grpc, "w1", &[]);
        let _w2 = start_worker(&c.grpc, "w2", &[]);
        let client = Client::new(&c.http, None);
        let st = client.submit(&s, None).unwrap();
        // Past the unbiased pilot (8 of 64 passes) or the first sequential decisions.
        poll("the first decisions", TIMEOUT, || {
            let j = client.job(st.id).unwrap();
            j.passes_done * 6 >= j.passes_planned || j.state == tessera_api::JobState::Done
        });
        // ... and an eighth of them committed to the store (`stored_passes`).
        let planned = i64::try_from(client.job(st.id).unwrap().passes_planned).unwrap();
        let store = data.join("tessera.sqlite3");
        poll("passes committed to the store", TIMEOUT, || {
            stored_passes(store.to_str().unwrap(), st.id) * 8 >= planned
        });
        c.proc.kill9();
        let c2 = start_coordinator(&data, &http, &grpc, &[]);
        let client = Client::new(&c2.http, None);
        let after = client.job(st.id).unwrap();
        assert_ne!(
            after.state,
            tessera_api::JobState::Done,
            "{mode}: the job finished before the kill; make it longer"
        );
        assert!(
            after.passes_done * 8 >= after.passes_planned,
            "{mode}: {} of {} passes after the restart: the merged passes were not resumed",
            after.passes_done,
            after.passes_planned
        );
        let done = wait_done(&client, st.id);
        assert!(done.spp_so_far < 1024.0, "{mode}: {} spp", done.spp_so_far);
        let exr = client.image(st.id, "exr").unwrap();
        assert!(
            exr == reference,
            "{mode}: adaptive EXR after a coordinator restart differs from tessera render"
        );
        drop(client);
        drop(c2);
        // The finished job's image from the store alone.
        let c3 = start_coordinator(&data, &http, &grpc, &[]);
        let client = Client::new(&c3.http, None);
        let stored = client.image(st.id, "exr").unwrap();
        assert!(
            stored == reference,
            "{mode}: the stored image of the finished adaptive job differs from tessera render"
        );
    }
}

/// Whether the tile map of frame `frame` of job `id` shows a tile with merged passes.
fn has_merged_passes(client: &Client, id: u64, frame: u32) -> bool {
    client
        .get_raw(&format!("/api/v1/jobs/{id}/tiles?frame={frame}"))
        .is_ok_and(|t| {
            let v: serde_json::Value = serde_json::from_slice(&t).unwrap();
            v["tiles"]
                .as_array()
                .is_some_and(|ts| ts.iter().any(|t| t["passes"].as_u64() > Some(0)))
        })
}

/// An adaptive animation comes back from `kill -9` holding only its frame in
/// progress. The store keeps a finished frame's checkpoints, so a restart finds every
/// frame the job finished; they were restored live until the job ended, beyond a budget of
/// one frame (and an adaptive job had to fit the budget with all its frames). Now the
/// restart releases them: under `--memory-budget` of one adaptive frame, `/metrics` shows
/// one frame resident after the restart, the job ends, and every frame's EXR (the
/// released one from the store) is byte-identical to `tessera render --frame F`.
///
/// The tile map shows a merge before its checkpoint is committed, so the kill can come
/// between the two (CI, 2026-12-05): the frame in progress then has nothing in the store
/// and the restart rightly holds nothing. The expected figure is therefore read after the
/// restart, from what came back: one frame if the frame after the finished ones has
/// merged passes, none otherwise; never the finished frames.
#[test]
fn a_restarted_adaptive_animation_holds_only_its_frame_in_progress() {
    let dir = temp_dir("e2e", "adaptive-frames-restart");
    let mut s = job(32, 32, 4096);
    s.adaptive = "sequential".into();
    s.target_error = Some(0.03);
    s.frames = tessera_api::FrameRange { start: 0, end: 2 };
    // One adaptive frame of 32 x 32 (ARCHITECTURE.md §6: 157 B per pixel).
    let frame_bytes = tessera_farm::frame_state_bytes(
        &tessera_farm::FramePlan::new(32, 32, 16, 1, 1).unwrap(),
        true,
    );
    let budget = frame_bytes.to_string();
    let extra = ["--memory-budget", budget.as_str()];
    let data = dir.join("data");
    let (http, grpc) = free_addresses();
    let mut c = start_coordinator(&data, &http, &grpc, &extra);
    let mut w = start_worker(&c.grpc, "w1", &[]);
    let client = Client::new(&c.http, None);
    let st = client.submit(&s, None).unwrap();
    let id = st.id;
    // Frame 0 finished and released, frame 1 with merged passes.
    poll("frame 0 done and frame 1 begun", TIMEOUT, || {
        let begun = has_merged_passes(&client, id, 1);
        let j = client.job(id).unwrap();
        (j.frames_done >= 1 && begun) || j.state == tessera_api::JobState::Done
    });
    // The worker first, so no more results arrive while the coordinator is killed.
    w.kill9();
    c.proc.kill9();
    let c2 = start_coordinator(&data, &http, &grpc, &extra);
    let client = Client::new(&c2.http, None);
    let after = client.job(id).unwrap();
    assert_ne!(
        after.state,
        tessera_api::JobState::Done,
        "the job finished before the kill; make it longer"
    );
    let metrics = String::from_utf8(client.get_raw("/metrics").unwrap()).unwrap();
    let resident: u64 = metrics
        .lines()
        .find_map(|l| l.strip_prefix("tessera_merge_state_bytes "))
        .and_then(|v| v.parse().ok())
        .expect("tessera_merge_state_bytes in /metrics");
    // Frames finish in order under a budget of one frame: the one in progress, if any,
    // is the first not done. Read after /metrics, so reading it cannot load it.
    let next = after.frames_done;
    let in_progress = has_merged_passes(&client, id, next);
    let expected = if in_progress { frame_bytes } else { 0 };
    assert_eq!(
        resident, expected,
        "after the restart ({} frame(s) done, frame {next} in progress: {in_progress}): \
         {resident} bytes of merge state, one frame is {frame_bytes}",
        after.frames_done
    );
    let _w2 = start_worker(&c2.grpc, "w2", &[]);
    wait_done(&client, id);
    for f in 0..=2u32 {
        let exr = client
            .get_raw(&format!("/api/v1/jobs/{id}/image?frame={f}&format=exr"))
            .unwrap();
        let frame = f.to_string();
        let reference = local_render_with(
            &dir,
            &format!("local-{f}.exr"),
            &s,
            &[
                "--adaptive",
                "sequential",
                "--target-error",
                "0.03",
                "--frame",
                &frame,
            ],
        );
        assert!(
            exr == reference,
            "frame {f}: EXR after the restart differs from tessera render --frame {f}"
        );
    }
}

/// Why a job stopped survives a restart. A job stopped by its time limit says so
/// in its status and EXR header before and after its coordinator restarts (the store keeps
/// the stop with the `done` state), and the reason is not reported as an error; its
/// unfinished frame is not counted as done.
#[test]
fn a_time_limit_stop_is_still_named_after_a_restart() {
    let dir = temp_dir("e2e", "time-limit-restart");
    let data = dir.join("data");
    // Ports chosen by the system at each start: the restarted coordinator needs the same
    // store, not the same addresses, and a port picked in advance could be taken by a test
    // running beside this one in the moment between the stop and the restart.
    let mut c = start_coordinator(&data, "127.0.0.1:0", "127.0.0.1:0", &[]);
    let _w = start_worker(&c.grpc, "w1", &[]);
    let client = Client::new(&c.http, None);
    let mut s = job(16, 16, 1 << 20);
    s.time_limit_seconds = Some(1.0);
    s.target_error = Some(1e-6);
    let id = client.submit(&s, None).unwrap().id;
    let done = wait_done(&client, id);
    let reason = |st: &tessera_api::JobStatus| st.stop_reason.clone().unwrap_or_default();
    assert!(reason(&done).contains("time limit"), "{done:?}");
    assert_eq!(done.target_reached, Some(false));
    assert_eq!(done.error, None);
    let header = |exr: &[u8]| String::from_utf8_lossy(exr).contains("time limit");
    assert!(
        header(&client.image(id, "exr").unwrap()),
        "EXR header before the restart"
    );
    c.proc.stop();
    let c2 = start_coordinator(&data, "127.0.0.1:0", "127.0.0.1:0", &[]);
    let client = Client::new(&c2.http, None);
    let after = client.job(id).unwrap();
    assert_eq!(after.state, tessera_api::JobState::Done);
    assert_eq!(reason(&after), reason(&done), "{after:?}");
    assert_eq!(after.target_reached, Some(false));
    assert_eq!(after.error, None);
    // The frame was stopped, not finished, before and after (the stored status counted
    // every frame of a `done` job as finished).
    assert_eq!((done.frames_done, after.frames_done), (0, 0), "{after:?}");
    assert!(
        header(&client.image(id, "exr").unwrap()),
        "EXR header after the restart"
    );
}

#[test]
fn bad_input_gets_json_errors_and_the_coordinator_keeps_serving() {
    let dir = temp_dir("e2e", "bad-input");
    let c = start_coordinator(&dir.join("data"), "127.0.0.1:0", "127.0.0.1:0", &[]);
    let client = Client::new(&c.http, None);
    for (body, field) in [
        (r#"{"scene": "builtin:cornell-box", "spp": 0}"#, Some("spp")),
        (
            r#"{"scene": "builtin:cornell-box", "width": 100000}"#,
            Some("width"),
        ),
        (r#"{"scene": "builtin:nope"}"#, Some("scene")),
        (r#"{"scene": "builtin:cornell-box", "colour": 1}"#, None),
        (
            r#"{"scene": "builtin:cornell-box", "mis": "magic"}"#,
            Some("mis"),
        ),
        (
            r#"{"scene": "builtin:cornell-box", "target_error": -1}"#,
            Some("target_error"),
        ),
        ("not json", None),
    ] {
        let (status, e) = api_error(client.submit_raw(body.as_bytes()));
        assert_eq!(status, 400, "{body}: {e}");
        if let Some(f) = field {
            assert_eq!(e.field.as_deref(), Some(f), "{body}: {e}");
        }
        assert!(!e.message.is_empty());
    }
    for upload in [
        &b""[..],
        b"garbage",
        b"glTF\x02\x00\x00\x00\xff\xff\xff\xff",
        br#"{"asset": {"version": "2.0"}, "buffers": [{"byteLength": 10, "uri": "/etc/passwd"}]}"#,
    ] {
        let (status, e) = api_error(client.upload_scene(upload));
        assert!((400..500).contains(&status), "{status}: {e}");
    }
    // A job naming a scene hash that was never uploaded.
    let (status, e) = api_error(client.submit(&JobSettings::new("ab".repeat(32)), None));
    assert_eq!((status, e.field.as_deref()), (400, Some("scene")));
    let (status, _) = api_error(client.job(12345));
    assert_eq!(status, 404);
    let (status, _) = api_error(client.image(12345, "png"));
    assert_eq!(status, 404);
    // Still serving: a real upload and a job over it render.
    let gltf = std::fs::read(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../scenes/cornell-box.gltf"
    ))
    .unwrap();
    let up = client.upload_scene(&gltf).unwrap();
    assert!(up.triangles > 0);
    let _w = start_worker(&c.grpc, "w", &[]);
    let mut s = JobSettings::new(up.hash);
    (s.width, s.height, s.spp) = (Some(16), Some(16), 4);
    let st = client.submit(&s, None).unwrap();
    wait_done(&client, st.id);
    let png = client.image(st.id, "png").unwrap();
    assert_eq!(&png[1..4], b"PNG");
}

#[test]
fn tokens_are_required_when_configured() {
    let dir = temp_dir("e2e", "tokens");
    let c = start_coordinator(
        &dir.join("data"),
        "127.0.0.1:0",
        "127.0.0.1:0",
        &[
            "--api-token",
            "api-s3cret",
            "--worker-token",
            "worker-s3cret",
        ],
    );
    // HTTP: no token, wrong token, right token.
    for token in [None, Some("wrong".to_string())] {
        let (status, e) = api_error(Client::new(&c.http, token).jobs(5, None));
        assert_eq!(status, 401, "{e}");
    }
    let client = Client::new(&c.http, Some("api-s3cret".into()));
    let st = client.submit(&job(16, 16, 4), None).unwrap();
    // gRPC: a worker without the token is refused and exits with an error; a worker with a
    // wrong token too; the right one renders the job.
    for extra in [&[][..], &["--token", "nope"][..]] {
        let (ok, _, err) = output(
            tessera()
                .args(["worker", "--coordinator", &c.grpc, "--threads", "1"])
                .args(extra)
                .env_remove("TESSERA_WORKER_TOKEN"),
        );
        assert!(!ok);
        assert!(err.contains("token"), "{err}");
    }
    assert_eq!(client.job(st.id).unwrap().passes_done, 0);
    let _w = start_worker(&c.grpc, "w", &["--token", "worker-s3cret"]);
    wait_done(&client, st.id);
}

#[test]
fn faulty_results_are_rejected_and_the_image_is_unaffected() {
    use tessera_proto::v1;
    let dir = temp_dir("e2e", "faulty");
    // One tile of 4 passes of 2 (8 spp): 4 units, of which the faulty worker leases 3.
    let s = job(32, 32, 8);
    let reference = local_render(&dir, &s);
    let c = start_coordinator(&dir.join("data"), "127.0.0.1:0", "127.0.0.1:0", &[]);
    let client = Client::new(&c.http, None);
    let st = client.submit(&s, None).unwrap();
    // A faulty worker, speaking real gRPC from this test: it leases units and returns a
    // result of the wrong size, then one with a NaN, then a negative value.
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let faults = rt.block_on(async {
        let channel = tonic::transport::Endpoint::from_shared(c.grpc.clone())
            .unwrap()
            .connect()
            .await
            .unwrap();
        let reg = tessera_proto::WorkerServiceClient::new(channel.clone())
            .register(v1::RegisterRequest {
                name: "faulty".into(),
                threads: 1,
                version: "test".into(),
                capabilities: vec![],
            })
            .await
            .unwrap()
            .into_inner();
        // Every call after Register carries the session (worker.proto, "Sessions").
        let mut g = tessera_proto::WorkerServiceClient::with_interceptor(
            channel,
            tessera_proto::WithSession::new(&reg.session).unwrap(),
        );
        let leases = g
            .lease_work(v1::LeaseRequest {
                worker_id: reg.worker_id,
                max_units: 3,
                wait_ms: 0,
            })
            .await
            .unwrap()
            .into_inner()
            .leases;
        assert_eq!(leases.len(), 3);
        let mut rejected = 0;
        for (k, l) in leases.into_iter().enumerate() {
            let l = tessera_proto::LeasedUnit::try_from(l).unwrap();
            let rect = l.plan.tile(l.unit.tile);
            let n = rect.pixel_count() * l.unit.pass_count as usize * 3;
            let mut pass_means = vec![0.5f32; n];
            match k {
                0 => {
                    pass_means.pop();
                }
                1 => pass_means[7] = f32::NAN,
                _ => pass_means[3] = -1.0,
            }
            let (width, height) = (rect.width, rect.height);
            let unit = v1::WorkUnit::from(l.unit);
            let r = g
                .submit_result(v1::SubmitResultRequest {
                    worker_id: reg.worker_id,
                    lease_id: l.lease_id,
                    unit: Some(unit),
                    width,
                    height,
                    pass_means: tessera_proto::means_to_bytes(&pass_means),
                    render_seconds: 0.1,
                    job_id: l.job_id,
                    rejected_samples: 0,
                    traced_pixel_passes: 0,
                    fence: l.fence.clone(),
                    bias: Vec::new(),
                })
                .await
                .unwrap()
                .into_inner();
            assert!(!r.accepted, "a bad result was accepted");
            assert!(!r.reason.is_empty());
            rejected += 1;
        }
        rejected
    });
    assert_eq!(faults, 3);
    let j = client.job(st.id).unwrap();
    assert_eq!(j.passes_done, 0, "a rejected result was merged");
    assert_eq!(j.faults, 3);
    let w = client.workers().unwrap();
    let faulty = w.workers.iter().find(|w| w.name == "faulty").unwrap();
    assert_eq!(faulty.faults, 3);
    // Honest workers finish the job (the faulty worker's leases lapse and are re-leased).
    let _w = start_worker(&c.grpc, "honest", &[]);
    wait_done(&client, st.id);
    assert!(client.image(st.id, "exr").unwrap() == reference);
    let metrics = String::from_utf8(client.get_raw("/metrics").unwrap()).unwrap();
    assert!(
        metrics.contains("tessera_worker_faults_total 3"),
        "{metrics}"
    );
}

/// Workers you can trust (ARCHITECTURE.md §6, "Spot checks and quarantine"): a worker started with `--inject-faults` corrupts
/// its results in a way validation cannot see; spot checks catch it, quarantine it and
/// repair what it had merged, and the job still ends byte-identical to `tessera render`.
///
/// Why this must fail if spot checks or quarantine do not work, whatever the timing:
/// - `--inject-faults 1` corrupts every unit the faulty worker renders and
///   `--spot-check-fraction 1` checks every unit, so every copy it delivers is compared
///   with another worker's (the test does not depend on which units it happens to get;
///   at the issue's 0.01 that would be a matter of luck on a small job).
/// - It starts alone and renders the first units by itself: alone, it re-renders its own
///   spot-checked copies, which agree with each other (its faults are deterministic), so
///   corrupt units are merged unverified (`alone` in /metrics). Only if quarantine drops
///   and re-renders the tiles those went into can the EXR equal the local render.
/// - Then two honest workers join while most of the job is left. The faulty worker's next
///   copy differs from an honest one (disputed), the second honest worker decides by
///   majority, and the faulty worker must be quarantined for the job to finish right.
#[test]
fn spot_checks_quarantine_a_worker_injecting_faults_and_repair_the_image() {
    let dir = temp_dir("e2e", "spot-checks");
    // 2 x 2 tiles of 32 x 32, 8 passes of 64 samples: 32 units.
    let s = job(64, 64, 512);
    let reference = local_render(&dir, &s);
    let c = start_coordinator(
        &dir.join("data"),
        "127.0.0.1:0",
        "127.0.0.1:0",
        &["--spot-check-fraction", "1"],
    );
    let client = Client::new(&c.http, None);
    let _faulty = start_worker(&c.grpc, "faulty", &["--inject-faults", "1"]);
    poll("the faulty worker to register", TIMEOUT, || {
        client.workers().unwrap().workers.len() == 1
    });
    let st = client.submit(&s, None).unwrap();
    // Alone, it merges a few units of its own (corrupt, verified by nobody else).
    poll("units merged by the faulty worker alone", TIMEOUT, || {
        client.job(st.id).unwrap().passes_done >= 2
    });
    let mid = client.job(st.id).unwrap();
    assert!(
        mid.passes_done * 2 < mid.passes_planned,
        "the faulty worker did half the job alone ({} of {} passes): too fast to test",
        mid.passes_done,
        mid.passes_planned
    );
    let _h1 = start_worker(&c.grpc, "honest-1", &[]);
    let _h2 = start_worker(&c.grpc, "honest-2", &[]);
    wait_done(&client, st.id);
    let exr = client.image(st.id, "exr").unwrap();
    assert!(
        exr == reference,
        "the EXR differs from tessera render: a corrupt unit stayed merged"
    );
    let workers = client.workers().unwrap().workers;
    assert_eq!(workers.len(), 3);
    for w in &workers {
        let faulty = w.name == "faulty";
        assert_eq!(w.quarantined, faulty, "{}: {w:?}", w.name);
        assert_eq!(w.quarantine_reason.is_some(), faulty, "{}: {w:?}", w.name);
    }
    let metrics = String::from_utf8(client.get_raw("/metrics").unwrap()).unwrap();
    let value = |name: &str| -> u64 {
        metrics
            .lines()
            .find_map(|l| l.strip_prefix(name)?.trim().parse().ok())
            .unwrap_or_else(|| panic!("{name} not in /metrics:\n{metrics}"))
    };
    assert_eq!(value("tessera_workers_quarantined "), 1);
    assert!(value("tessera_spot_checks_total{outcome=\"mismatch\"} ") >= 1);
    assert!(value("tessera_spot_checks_total{outcome=\"match\"} ") >= 1);
    assert!(value("tessera_spot_checks_total{outcome=\"alone\"} ") >= 1);
    // What it merged alone was dropped, rendered again and found corrupt.
    assert!(value("tessera_tiles_reset_total ") >= 1);
    assert!(value("tessera_units_reverified_total{outcome=\"differed\"} ") >= 1);
    assert_eq!(value("tessera_units_unrepaired_total "), 0);
}
