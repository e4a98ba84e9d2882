//! The OpenAPI description served at `/api/v1/openapi.json` documents every field of the
//! job settings the server accepts, and nothing else (a field added to the job contract
//! without its documentation fails here).

use std::collections::BTreeSet;

use tessera_api::{FrameRange, JobSettings, Shutter};
use tessera_coordinator::http::OPENAPI_JSON;

#[test]
fn openapi_documents_exactly_the_job_settings_fields() {
    let api: serde_json::Value = serde_json::from_str(OPENAPI_JSON).expect("valid JSON");
    let documented: BTreeSet<String> = api["components"]["schemas"]["JobSettings"]["properties"]
        .as_object()
        .expect("JobSettings properties")
        .keys()
        .cloned()
        .collect();
    // Every optional field set, so that serialization writes every key.
    let mut s = JobSettings::new("builtin:cornell-box");
    s.camera = Some("main".into());
    s.width = Some(64);
    s.height = Some(48);
    s.max_depth = Some(8);
    s.frames = FrameRange { start: 1, end: 2 };
    s.fps = 30.0;
    s.animation = Some("walk".into());
    s.shutter = Some(Shutter {
        open: -0.25,
        close: 0.25,
    });
    s.target_error = Some(0.05);
    s.adaptive = "sequential".into();
    s.min_passes = 12;
    s.time_limit_seconds = Some(60.0);
    s.name = Some("n".into());
    s.environment = Some(tessera_api::EnvironmentSettings {
        source: "1,1,1".into(),
        strength: 2.0,
        rotation_degrees: 90.0,
    });
    let sent: BTreeSet<String> = serde_json::to_value(&s)
        .unwrap()
        .as_object()
        .unwrap()
        .keys()
        .cloned()
        .collect();
    assert_eq!(documented, sent);
    // And the example validates.
    s.validate().unwrap();
}
