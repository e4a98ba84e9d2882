//! TLS on both ports of the in-process coordinator (`serve_coordinator` with
//! `CoordinatorConfig::tls`), on loopback, with a CA and certificates made here by rcgen:
//! a plain-text client is refused on both TLS ports, a client trusting another CA is
//! refused, and under mutual TLS a worker without a certificate, or with one from another
//! CA, is refused while one with a certificate from the right CA registers under its
//! certificate's common name. Every wait is bounded by [`tessera_testkit::HANG`].

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, ServerName};
use tessera_coordinator::service::{Coordinator, CoordinatorConfig};
use tessera_coordinator::{serve_coordinator, Listeners, TlsFiles};
use tessera_proto::v1;
use tessera_proto::v1::worker_service_client::WorkerServiceClient;
use tessera_testkit::bounded;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tonic::transport::{Certificate, Channel, ClientTlsConfig, Endpoint, Identity};

use tessera_testkit::test_ca::TestCa as Ca;

fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p
}

struct Farm {
    http: SocketAddr,
    grpc: SocketAddr,
    core: Coordinator,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    served: tokio::task::JoinHandle<Result<(), tessera_coordinator::ServeError>>,
    _dir: tempfile::TempDir,
}

impl Farm {
    /// A coordinator with TLS from `ca` (and mutual TLS with `client_ca`).
    async fn start(ca: &Ca, client_ca: Option<&Ca>) -> Self {
        let dir = tempfile::tempdir().unwrap();
        let (cert, key) = ca.issue_pem("coordinator", true);
        let mut cfg = CoordinatorConfig::new(dir.path().join("data"));
        cfg.tls = Some(TlsFiles {
            cert: write(dir.path(), "cert.pem", &cert),
            key: write(dir.path(), "key.pem", &key),
            client_ca: client_ca.map(|c| write(dir.path(), "client-ca.pem", &c.pem())),
        });
        let core = Coordinator::open(cfg).await.unwrap();
        let http = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let grpc = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let (h, g) = (http.local_addr().unwrap(), grpc.local_addr().unwrap());
        let (tx, rx) = tokio::sync::oneshot::channel::<()>();
        let served = tokio::spawn(serve_coordinator(
            core.clone(),
            Listeners { http, grpc },
            async {
                let _ = rx.await;
            },
        ));
        Self {
            http: h,
            grpc: g,
            core,
            stop: Some(tx),
            served,
            _dir: dir,
        }
    }

    async fn stop(mut self) {
        let _ = self.stop.take().map(|s| s.send(()));
        bounded("shutdown", self.served).await.unwrap().unwrap();
    }
}

/// `GET path` over TLS trusting `ca_pem`; the response, or the TLS error.
async fn https_get(addr: SocketAddr, ca_pem: &str, path: &str) -> Result<String, String> {
    let mut roots = rustls::RootCertStore::empty();
    for c in CertificateDer::pem_slice_iter(ca_pem.as_bytes()) {
        roots.add(c.unwrap()).unwrap();
    }
    let config = rustls::ClientConfig::builder_with_provider(Arc::new(
        rustls::crypto::ring::default_provider(),
    ))
    .with_safe_default_protocol_versions()
    .unwrap()
    .with_root_certificates(roots)
    .with_no_client_auth();
    let tcp = tokio::net::TcpStream::connect(addr).await.unwrap();
    let mut s = tokio_rustls::TlsConnector::from(Arc::new(config))
        .connect(ServerName::try_from("127.0.0.1").unwrap(), tcp)
        .await
        .map_err(|e| e.to_string())?;
    let req = format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n");
    s.write_all(req.as_bytes())
        .await
        .map_err(|e| e.to_string())?;
    let mut out = Vec::new();
    // A peer that closes without close_notify after the response is fine here.
    let _ = s.read_to_end(&mut out).await;
    Ok(String::from_utf8_lossy(&out).into_owned())
}

/// A plain-text `GET /healthz`: what came back before the server closed the connection.
async fn plain_get(addr: SocketAddr) -> Vec<u8> {
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    let req = format!("GET /healthz HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n");
    s.write_all(req.as_bytes()).await.unwrap();
    let mut out = Vec::new();
    let _ = s.read_to_end(&mut out).await;
    out
}

fn register_request() -> v1::RegisterRequest {
    v1::RegisterRequest {
        name: "w".into(),
        threads: 1,
        version: "test".into(),
        capabilities: vec![],
    }
}

/// Connects to the gRPC port over TLS and registers; the worker id or the error.
async fn register_tls(
    grpc: SocketAddr,
    ca_pem: &str,
    identity: Option<&(String, String)>,
) -> Result<u64, String> {
    let mut tls = ClientTlsConfig::new().ca_certificate(Certificate::from_pem(ca_pem));
    if let Some((cert, key)) = identity {
        tls = tls.identity(Identity::from_pem(cert, key));
    }
    let channel: Channel = Endpoint::from_shared(format!("https://{grpc}"))
        .unwrap()
        .tls_config(tls)
        .unwrap()
        .connect()
        .await
        .map_err(|e| format!("{e:?}"))?;
    let mut client = WorkerServiceClient::new(channel);
    client
        .register(register_request())
        .await
        .map(|r| r.into_inner().worker_id)
        .map_err(|e| format!("{e:?}"))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn both_ports_speak_tls_only_and_only_to_clients_trusting_their_ca() {
    let (ca, other) = (Ca::new("tessera test CA"), Ca::new("another CA"));
    let farm = Farm::start(&ca, None).await;

    let ok = bounded("https GET", https_get(farm.http, &ca.pem(), "/healthz"))
        .await
        .unwrap();
    assert!(ok.starts_with("HTTP/1.1 200"), "{ok}");

    // Plain text on the HTTP port: no HTTP answer, only the TLS layer's refusal.
    let plain = bounded("plain GET", plain_get(farm.http)).await;
    assert!(
        !String::from_utf8_lossy(&plain).contains("HTTP/1.1"),
        "{plain:?}"
    );

    // A client trusting another CA refuses the server's certificate.
    let e = bounded(
        "https GET, wrong CA",
        https_get(farm.http, &other.pem(), "/healthz"),
    )
    .await
    .unwrap_err();
    assert!(
        e.contains("UnknownIssuer") || e.contains("certificate"),
        "{e}"
    );

    // gRPC: TLS with the right CA works; plain text and the wrong CA do not.
    let id = bounded(
        "register over TLS",
        register_tls(farm.grpc, &ca.pem(), None),
    )
    .await
    .unwrap();
    assert!(id > 0);
    let plain = bounded("plain-text register", async {
        match WorkerServiceClient::connect(format!("http://{}", farm.grpc)).await {
            Err(e) => Err(format!("{e:?}")),
            Ok(mut c) => c
                .register(register_request())
                .await
                .map(|_| ())
                .map_err(|e| format!("{e:?}")),
        }
    })
    .await;
    assert!(plain.is_err(), "a plain-text worker registered");
    let e = bounded(
        "register, wrong CA",
        register_tls(farm.grpc, &other.pem(), None),
    )
    .await
    .unwrap_err();
    assert!(
        e.contains("UnknownIssuer") || e.contains("ertificate"),
        "{e}"
    );

    farm.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn mutual_tls_refuses_workers_without_a_certificate_from_the_client_ca() {
    let (ca, workers, rogue) = (
        Ca::new("server CA"),
        Ca::new("worker CA"),
        Ca::new("rogue CA"),
    );
    let farm = Farm::start(&ca, Some(&workers)).await;

    let e = bounded(
        "register without a certificate",
        register_tls(farm.grpc, &ca.pem(), None),
    )
    .await
    .unwrap_err();
    assert!(!e.is_empty());
    let rogue_id = rogue.issue_pem("intruder", false);
    let e = bounded(
        "register with a certificate of another CA",
        register_tls(farm.grpc, &ca.pem(), Some(&rogue_id)),
    )
    .await
    .unwrap_err();
    assert!(!e.is_empty());

    let good = workers.issue_pem("render-node-7", false);
    let id = bounded(
        "register with a good certificate",
        register_tls(farm.grpc, &ca.pem(), Some(&good)),
    )
    .await
    .unwrap();
    let list = farm.core.workers().unwrap();
    assert_eq!(list.workers.len(), 1, "only the good worker registered");
    assert_eq!(list.workers[0].id, id);
    assert_eq!(list.workers[0].identity.as_deref(), Some("render-node-7"));

    // The HTTP port asks for no client certificate (it has its own token).
    let ok = bounded(
        "https GET",
        https_get(farm.http, &ca.pem(), "/api/v1/workers"),
    )
    .await
    .unwrap();
    assert!(
        ok.starts_with("HTTP/1.1 200") && ok.contains("render-node-7"),
        "{ok}"
    );

    farm.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bad_tls_file_stops_serve_before_it_serves() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = CoordinatorConfig::new(dir.path().join("data"));
    cfg.tls = Some(TlsFiles {
        cert: write(
            dir.path(),
            "cert.pem",
            "-----BEGIN CERTIFICATE-----\nAAAA\n",
        ),
        key: write(dir.path(), "key.pem", ""),
        client_ca: None,
    });
    let core = Coordinator::open(cfg).await.unwrap();
    let http = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let grpc = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let e = bounded(
        "serve with a bad certificate",
        serve_coordinator(core, Listeners { http, grpc }, std::future::pending()),
    )
    .await
    .unwrap_err()
    .to_string();
    assert!(e.contains("cert.pem"), "{e}");
}
