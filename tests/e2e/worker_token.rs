//! Safe defaults for workers (docs/farm.md, "Worker credentials"): a real
//! `tessera coordinator` whose gRPC port listens beyond loopback without a worker token
//! generates one, prints it once, keeps it in `DATA/worker-token` (mode 0600) and refuses
//! workers without it; a restart reuses it without printing it again.

use crate::common;

use std::process::Command;

use common::{temp_dir, Proc};
use tessera_proto::v1;

/// A worker's `Register` on `grpc` with `token` (if any): the refusal's code, `None` when
/// registered.
fn register(grpc: &str, token: Option<&str>) -> Option<tonic::Code> {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap()
        .block_on(async {
            let mut c = v1::worker_service_client::WorkerServiceClient::connect(grpc.to_string())
                .await
                .unwrap();
            let mut req = tonic::Request::new(v1::RegisterRequest {
                name: "probe".into(),
                threads: 1,
                version: "test".into(),
                capabilities: vec![],
            });
            if let Some(t) = token {
                req.metadata_mut()
                    .insert("authorization", format!("Bearer {t}").parse().unwrap());
            }
            c.register(req).await.err().map(|s| s.code())
        })
}

fn start(data: &std::path::Path, log: &std::path::Path) -> (Proc, String) {
    let mut proc = Proc::spawn(
        "coordinator",
        Command::new(env!("CARGO_BIN_EXE_tessera"))
            .args([
                "coordinator",
                "--http",
                "127.0.0.1:0",
                "--grpc",
                "0.0.0.0:0",
                "--data",
            ])
            .arg(data)
            .env_remove("TESSERA_API_TOKEN")
            .env_remove("TESSERA_WORKER_TOKEN")
            .env("RUST_LOG", "warn"),
        Some(log),
    );
    let grpc = proc.wait_line("grpc: ");
    // Listening on every interface: dial it on loopback.
    let port = grpc.rsplit(':').next().unwrap().to_string();
    (proc, format!("http://127.0.0.1:{port}"))
}

#[test]
fn a_coordinator_beyond_loopback_without_a_worker_token_generates_and_requires_one() {
    let dir = temp_dir("worker_token", "generated");
    let data = dir.join("data");
    let log = dir.join("coordinator.log");
    let (mut proc, grpc) = start(&data, &log);
    let file = data.join("worker-token");
    let token = std::fs::read_to_string(&file).unwrap().trim().to_string();
    assert_eq!(token.len(), 64, "{token:?}");
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        let mode = std::fs::metadata(&file).unwrap().permissions().mode() & 0o777;
        assert_eq!(mode, 0o600, "{mode:o}");
    }
    let printed = std::fs::read_to_string(&log).unwrap();
    assert!(
        printed.contains(&format!("TESSERA_WORKER_TOKEN={token}"))
            && printed.contains("--worker-token")
            && printed.contains(&file.display().to_string()),
        "{printed}"
    );
    assert_eq!(register(&grpc, None), Some(tonic::Code::Unauthenticated));
    assert_eq!(
        register(&grpc, Some("wrong")),
        Some(tonic::Code::Unauthenticated)
    );
    assert_eq!(register(&grpc, Some(&token)), None);
    proc.stop();
    // A restart keeps the token and does not print it again.
    let log2 = dir.join("coordinator2.log");
    let (mut proc, grpc) = start(&data, &log2);
    let printed = std::fs::read_to_string(&log2).unwrap();
    assert!(!printed.contains(&token), "{printed}");
    assert!(printed.contains(&file.display().to_string()), "{printed}");
    assert_eq!(register(&grpc, Some(&token)), None);
    assert_eq!(register(&grpc, None), Some(tonic::Code::Unauthenticated));
    proc.stop();
}
