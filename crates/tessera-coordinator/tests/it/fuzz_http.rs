//! The HTTP API's inputs, fuzzed (robustness issue: a fuzz target per input surface;
//! docs/fuzzing.md, "HTTP bodies"): a deterministic, bounded mutation harness on stable
//! Rust that sends mutated job submissions (JSON values and raw bytes), headers
//! (content type, idempotency key, authorization), query strings and scene uploads to
//! the real router over a temporary store (no socket).
//!
//! It checks: nothing panics; no answer is a 5xx; every refusal is a JSON error body with
//! a known code and a 4xx status; every job answered 201 can be read back.
//!
//! Bodies that would ask for more than [`MAX_PIXELS`] pixels are not sent: memory
//! budgets at submission are another part of the robustness issue, and without them one
//! such job would take the test machine's memory.

use axum::body::Body;
use axum::http::{Request, Response};
use axum::Router;
use serde_json::{json, Value};
use tessera_api::{FromJson, JobSettings};
use tessera_coordinator::service::{Coordinator, CoordinatorConfig};

const SEED: u64 = 0x7e55_e7a0_0008;
const JOB_BODIES: usize = 4000;
const QUERIES: usize = 1000;
const SCENE_UPLOADS: usize = 200;
/// Largest frame area times frame count a sent job may ask for.
const MAX_PIXELS: u64 = 1 << 18;

use tessera_testkit::SplitMix64 as Rng;

const KEYS: &[&str] = &[
    "scene",
    "camera",
    "width",
    "height",
    "spp",
    "integrator",
    "mis",
    "sampler",
    "seed",
    "max_depth",
    "frames",
    "priority",
    "target_error",
    "adaptive",
    "min_passes",
    "time_limit_seconds",
    "tile_size",
    "name",
    "start",
    "end",
    "unknown_field",
    "",
];

fn odd_value(rng: &mut Rng) -> Value {
    match rng.below(20) {
        0 => Value::Null,
        1 => json!(true),
        2 => json!(-1),
        3 => json!(0),
        4 => json!(1),
        5 => json!(i64::MAX),
        6 => json!(u64::MAX),
        7 => json!(4_294_967_296u64),
        8 => json!(1e308),
        9 => json!(-0.0),
        10 => json!(0.5),
        11 => json!(""),
        12 => json!("builtin:"),
        13 => json!("x".repeat(10_000)),
        14 => json!("\u{202e}\u{0}é😀"),
        15 => json!("NaN"),
        16 => json!([]),
        17 => json!({}),
        18 => json!({"start": rng.below(5), "end": rng.below(5)}),
        _ => json!(rng.below(70_000)),
    }
}

fn seeds() -> Vec<Value> {
    vec![
        json!({"scene": "builtin:cornell-box", "width": 16, "height": 16, "spp": 4}),
        json!({"scene": "builtin:furnace", "width": 8, "height": 8, "spp": 2, "integrator": "path",
               "mis": "cutoff:0.1", "sampler": "independent", "seed": 7, "max_depth": 4,
               "frames": {"start": 0, "end": 1}, "priority": 3, "tile_size": 4, "name": "n"}),
        json!({"scene": "builtin:veach-mis", "width": 12, "height": 10, "spp": 16,
               "target_error": 0.1, "adaptive": "sequential", "min_passes": 2,
               "time_limit_seconds": 5.0}),
        json!({"scene": "builtin:caustic", "width": 8, "height": 8, "integrator": "bdpt"}),
    ]
}

fn mutate_value(rng: &mut Rng, v: &mut Value, depth: u32) {
    let Value::Object(map) = v else {
        *v = odd_value(rng);
        return;
    };
    match rng.below(5) {
        0 | 1 => {
            let key = rng.pick(KEYS).to_string();
            map.insert(key, odd_value(rng));
        }
        2 => {
            if let Some(k) = map
                .keys()
                .nth(rng.below(map.len() as u64) as usize)
                .cloned()
            {
                map.remove(&k);
            }
        }
        3 if depth < 3 => {
            if let Some(Value::Object(_)) = map.get("frames") {
                let f = map.get_mut("frames").unwrap();
                mutate_value(rng, f, depth + 1);
            } else {
                map.insert("frames".into(), odd_value(rng));
            }
        }
        _ => {
            let key = rng.pick(KEYS).to_string();
            let mut nested = json!(1);
            for _ in 0..rng.below(200) {
                nested = json!([nested]);
            }
            map.insert(key, nested);
        }
    }
}

fn mutate_bytes(rng: &mut Rng, b: &mut Vec<u8>) {
    match rng.below(5) {
        0 => b.truncate(rng.below(b.len() as u64 + 1) as usize),
        1 if !b.is_empty() => {
            let i = rng.below(b.len() as u64) as usize;
            b[i] = rng.next() as u8;
        }
        2 => {
            let i = rng.below(b.len() as u64 + 1) as usize;
            let junk: Vec<u8> = (0..rng.below(8)).map(|_| rng.next() as u8).collect();
            b.splice(i..i, junk);
        }
        3 => {
            // A key given twice.
            if b.last() == Some(&b'}') {
                b.pop();
                b.extend_from_slice(br#","spp":5}"#);
            }
        }
        _ => {
            b.insert(0, b'[');
            b.push(b']');
        }
    }
}

/// Whether a body, if valid, would ask for a frame area the coordinator cannot yet
/// refuse by budget.
fn too_big(body: &[u8]) -> bool {
    let Ok(s) = JobSettings::from_json(body) else {
        return false;
    };
    let (w, h) = (s.width.unwrap_or(1024), s.height.unwrap_or(1024));
    let side = u64::from(w.max(h));
    let frames = s.frames.count();
    side * side * frames > MAX_PIXELS || s.spp > 4096
}

async fn call(router: &mut Router, req: Request<Body>) -> Response<Body> {
    tower_service::Service::call(router, req).await.unwrap()
}

/// Checks an answer; returns its status and body.
async fn check(resp: Response<Body>, what: &str) -> (u16, Value) {
    let status = resp.status().as_u16();
    let bytes = axum::body::to_bytes(resp.into_body(), 64 << 20)
        .await
        .unwrap();
    assert!(
        status < 500,
        "{what}: answered {status}: {}",
        String::from_utf8_lossy(&bytes)
    );
    if status >= 400 {
        let v: Value = serde_json::from_slice(&bytes)
            .unwrap_or_else(|e| panic!("{what}: {status} with a non-JSON body ({e})"));
        let code = v["error"]["code"].as_str().unwrap_or("");
        assert!(
            [
                "invalid_field",
                "invalid_request",
                "invalid_scene",
                "unauthorized",
                "not_found",
                "conflict",
                "too_large",
                "request_timeout"
            ]
            .contains(&code),
            "{what}: {status} with {v}"
        );
        assert!(v["error"]["message"].is_string(), "{what}: {v}");
        return (status, v);
    }
    (
        status,
        serde_json::from_slice(&bytes).unwrap_or(Value::Null),
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fuzzed_requests_get_4xx_json_errors_and_never_a_server_fault() {
    let dir = tempfile::tempdir().unwrap();
    let core = Coordinator::open(CoordinatorConfig::new(dir.path()))
        .await
        .unwrap();
    let mut router = tessera_coordinator::http::router(core.clone());
    let mut rng = Rng(SEED);
    let seeds = seeds();
    let (mut sent, mut skipped, mut created) = (0u32, 0u32, Vec::new());
    let mut statuses = std::collections::BTreeMap::<u16, u32>::new();

    // Job submissions: mutated JSON values, then mutated bytes, with odd headers.
    for i in 0..JOB_BODIES {
        let mut v = rng.pick(&seeds).clone();
        for _ in 0..1 + rng.below(3) {
            mutate_value(&mut rng, &mut v, 0);
        }
        let mut body = serde_json::to_vec(&v).unwrap();
        if i % 3 == 0 {
            mutate_bytes(&mut rng, &mut body);
        }
        if too_big(&body) {
            skipped += 1;
            continue;
        }
        let mut req = Request::post("/api/v1/jobs");
        req = match rng.below(8) {
            0 => req.header(
                "content-type",
                *rng.pick(&["text/plain", "", "application/jsonx", "multipart/form-data"]),
            ),
            1 => req,
            _ => req.header("content-type", "application/json"),
        };
        if rng.below(4) == 0 {
            let key: Vec<u8> = match rng.below(4) {
                0 => b"k".repeat(1 + rng.below(300) as usize),
                1 => vec![b'a', 0x7f, b'\t', b'b'],
                2 => vec![0xc3, 0xa9, 0xff],
                _ => format!("key-{}", rng.below(4)).into_bytes(),
            };
            req = req.header("idempotency-key", key);
        }
        if rng.below(10) == 0 {
            req = req.header(
                "authorization",
                *rng.pick(&["Bearer x", "bearer", "", "Basic Zm9v"]),
            );
        }
        let what = format!(
            "POST /jobs {}",
            String::from_utf8_lossy(&body[..body.len().min(300)])
        );
        // A header value the HTTP library refuses cannot be sent at all.
        let Ok(req) = req.body(Body::from(body)) else {
            continue;
        };
        let resp = call(&mut router, req).await;
        let (status, v) = check(resp, &what).await;
        *statuses.entry(status).or_default() += 1;
        sent += 1;
        if status == 201 {
            created.push(
                v["id"]
                    .as_u64()
                    .unwrap_or_else(|| panic!("{what}: 201 without an id: {v}")),
            );
        }
    }

    // Query strings and paths.
    let paths = [
        "/api/v1/jobs",
        "/api/v1/jobs/1/image",
        "/api/v1/jobs/1/tiles",
        "/api/v1/jobs/1/history",
        "/api/v1/workers",
    ];
    let qkeys = [
        "limit", "cursor", "state", "format", "frame", "x", "", "limit[]",
    ];
    let qvals = [
        "0",
        "1",
        "200",
        "201",
        "-1",
        "abc",
        "png",
        "exr",
        "done",
        "99999999999",
        "%00",
        "%ZZ",
        "",
        "1e3",
        "+1",
    ];
    for _ in 0..QUERIES {
        let mut q = String::new();
        for j in 0..rng.below(4) {
            if j > 0 {
                q.push('&');
            }
            let k: &&str = rng.pick(&qkeys);
            q.push_str(k);
            if rng.below(6) != 0 {
                q.push('=');
                let v: &&str = rng.pick(&qvals);
                q.push_str(v);
            }
        }
        let path = rng.pick(&paths);
        let uri = format!("{path}?{q}");
        let Ok(req) = Request::get(uri.as_str()).body(Body::empty()) else {
            continue;
        };
        let resp = call(&mut router, req).await;
        let (status, _) = check(resp, &format!("GET {uri}")).await;
        *statuses.entry(status).or_default() += 1;
        sent += 1;
    }

    // Scene uploads: random bytes, truncated glTF JSON, odd content types.
    for _ in 0..SCENE_UPLOADS {
        let mut body: Vec<u8> = match rng.below(3) {
            0 => (0..rng.below(2000)).map(|_| rng.next() as u8).collect(),
            1 => br#"{"asset":{"version":"2.0"},"scenes":[{"nodes":[0]}],"nodes":[{"mesh":0}]}"#
                .to_vec(),
            _ => b"glTF\x02\x00\x00\x00".to_vec(),
        };
        mutate_bytes(&mut rng, &mut body);
        let req = Request::post("/api/v1/scenes")
            .header(
                "content-type",
                *rng.pick(&[
                    "application/octet-stream",
                    "model/gltf-binary",
                    "text/plain",
                ]),
            )
            .body(Body::from(body))
            .unwrap();
        let resp = call(&mut router, req).await;
        let (status, _) = check(resp, "POST /scenes").await;
        *statuses.entry(status).or_default() += 1;
        sent += 1;
    }

    // Nothing answered 201 is lost.
    for id in &created {
        let req = Request::get(format!("/api/v1/jobs/{id}"))
            .body(Body::empty())
            .unwrap();
        let (status, v) = check(call(&mut router, req).await, "GET a created job").await;
        assert_eq!(status, 200, "job {id} was created and is gone: {v}");
    }
    eprintln!("fuzz_http: {sent} requests sent ({skipped} oversized jobs not sent), {} jobs created; statuses {statuses:?}", created.len());
    assert!(
        statuses.contains_key(&400) && !created.is_empty(),
        "{statuses:?}"
    );
}
