//! TLS on both ports, optional mutual TLS for workers, and reloading the certificate on
//! SIGHUP (ARCHITECTURE.md §6, docs/tls.md).
//!
//! - [`TlsFiles`] names the PEM files: the server's certificate chain and private key,
//!   used on the HTTP and the gRPC port, and optionally a CA whose certificates workers
//!   must present on the gRPC port (mutual TLS). [`ServerTls::load`] reads and checks them
//!   all before anything is served: a missing, empty or malformed file, or a key that does
//!   not match the certificate, is a [`TlsError`] naming the file.
//! - Both ports run rustls with the *ring* provider, TLS 1.2 and 1.3. The HTTP port
//!   offers ALPN `http/1.1`, the gRPC port `h2`. The HTTP port asks for no client
//!   certificate (it has `--api-token`); with a client CA the gRPC port refuses every
//!   handshake without a certificate issued by that CA. The bearer tokens stay on top.
//! - With mutual TLS, the common name (CN) of a worker's certificate is its identity: it
//!   reaches the gRPC handlers as [`PeerInfo`] and is recorded in the worker's
//!   registration (`identity` in `GET /api/v1/workers`).
//! - [`ServerTls::reload`] reads the files again; connections accepted afterwards use
//!   the new certificate, connections already open keep theirs. A failed reload keeps the
//!   configuration in force and logs the error. [`ServerTls::reload_on_sighup`] does this
//!   on every SIGHUP (Unix).
//!
//! TLS handshakes run on the connection's own task, never in the accept loop, and are
//! bounded (the HTTP port's header timeout; [`GRPC_HANDSHAKE_TIMEOUT`] on the gRPC port),
//! so a client that opens a connection and sends nothing holds no one up.

use std::io;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::pin::Pin;
use std::sync::{Arc, RwLock};
use std::task::{Context, Poll};
use std::time::Duration;

use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer};
use rustls::server::WebPkiClientVerifier;
use rustls::{RootCertStore, ServerConfig};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::mpsc;
use tokio_rustls::server::TlsStream;
use tokio_rustls::TlsAcceptor;

/// How long a gRPC client has to complete its TLS handshake.
pub const GRPC_HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);

/// The PEM files of a coordinator's TLS configuration (flags `--tls-cert`, `--tls-key`,
/// `--tls-client-ca`).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TlsFiles {
    /// The server's certificate chain, leaf first.
    pub cert: PathBuf,
    /// The server's private key (PKCS#8, PKCS#1 or SEC1).
    pub key: PathBuf,
    /// With it, workers must present a certificate issued by one of these CAs.
    pub client_ca: Option<PathBuf>,
}

/// Why a TLS configuration could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum TlsError {
    /// A file could not be read.
    #[error("cannot read {}: {source}", path.display())]
    Read {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: io::Error,
    },
    /// A file is not what it should be: no PEM item of the expected kind, or a malformed
    /// one.
    #[error("{}: {reason}", path.display())]
    Invalid {
        /// The file.
        path: PathBuf,
        /// What is wrong with it.
        reason: String,
    },
}

impl TlsError {
    fn invalid(path: &Path, reason: impl Into<String>) -> Self {
        Self::Invalid {
            path: path.to_path_buf(),
            reason: reason.into(),
        }
    }
}

/// The rustls configurations of the two ports, as loaded from one reading of the files.
struct Configs {
    http: Arc<ServerConfig>,
    grpc: Arc<ServerConfig>,
}

/// A coordinator's server-side TLS: the configurations in force and the files they were
/// read from (module documentation).
pub struct ServerTls {
    files: TlsFiles,
    current: RwLock<Arc<Configs>>,
}

impl std::fmt::Debug for ServerTls {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ServerTls")
            .field("files", &self.files)
            .finish_non_exhaustive()
    }
}

impl ServerTls {
    /// Reads and checks the files.
    pub fn load(files: TlsFiles) -> Result<Self, TlsError> {
        let configs = build(&files)?;
        Ok(Self {
            files,
            current: RwLock::new(Arc::new(configs)),
        })
    }

    /// The files this configuration is read from.
    pub fn files(&self) -> &TlsFiles {
        &self.files
    }

    /// Whether the gRPC port requires client certificates.
    pub fn mutual(&self) -> bool {
        self.files.client_ca.is_some()
    }

    /// Reads the files again and, if they are all good, puts them in force for the
    /// connections accepted from now on; otherwise keeps the configuration in force.
    pub fn reload(&self) -> Result<(), TlsError> {
        let configs = Arc::new(build(&self.files)?);
        match self.current.write() {
            Ok(mut cur) => *cur = configs,
            Err(poisoned) => *poisoned.into_inner() = configs,
        }
        Ok(())
    }

    fn configs(&self) -> Arc<Configs> {
        match self.current.read() {
            Ok(c) => c.clone(),
            Err(poisoned) => poisoned.into_inner().clone(),
        }
    }

    /// The acceptor of the HTTP port for a connection accepted now.
    pub fn http_acceptor(&self) -> TlsAcceptor {
        TlsAcceptor::from(self.configs().http.clone())
    }

    /// The acceptor of the gRPC port for a connection accepted now.
    pub fn grpc_acceptor(&self) -> TlsAcceptor {
        TlsAcceptor::from(self.configs().grpc.clone())
    }

    /// Reloads the files on every SIGHUP until the task is aborted, logging the outcome
    /// (on platforms without SIGHUP the task does nothing).
    pub fn reload_on_sighup(self: Arc<Self>) -> tokio::task::JoinHandle<()> {
        tokio::spawn(async move {
            #[cfg(unix)]
            {
                use tokio::signal::unix::{signal, SignalKind};
                let mut hup = match signal(SignalKind::hangup()) {
                    Ok(s) => s,
                    Err(e) => {
                        tracing::error!(error = %e, "cannot listen for SIGHUP; TLS files will not be reloaded");
                        return;
                    }
                };
                while hup.recv().await.is_some() {
                    match self.reload() {
                        Ok(()) => tracing::info!(
                            cert = %self.files.cert.display(),
                            "TLS certificate reloaded"
                        ),
                        Err(e) => tracing::error!(
                            error = %e,
                            "TLS reload failed; keeping the certificate in force"
                        ),
                    }
                }
            }
            #[cfg(not(unix))]
            {
                let _ = self;
            }
        })
    }
}

fn provider() -> Arc<rustls::crypto::CryptoProvider> {
    Arc::new(rustls::crypto::ring::default_provider())
}

/// Reads a PEM file's certificates (at least one).
pub fn read_certs(path: &Path) -> Result<Vec<CertificateDer<'static>>, TlsError> {
    let bytes = std::fs::read(path).map_err(|source| TlsError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    let certs = CertificateDer::pem_slice_iter(&bytes)
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| TlsError::invalid(path, format!("malformed PEM certificate: {e}")))?;
    if certs.is_empty() {
        return Err(TlsError::invalid(path, "no PEM certificate in the file"));
    }
    Ok(certs)
}

/// Reads a PEM file's private key (the first one).
pub fn read_key(path: &Path) -> Result<PrivateKeyDer<'static>, TlsError> {
    let bytes = std::fs::read(path).map_err(|source| TlsError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    PrivateKeyDer::from_pem_slice(&bytes).map_err(|e| match e {
        rustls::pki_types::pem::Error::NoItemsFound => {
            TlsError::invalid(path, "no PEM private key in the file")
        }
        e => TlsError::invalid(path, format!("malformed PEM private key: {e}")),
    })
}

fn build(files: &TlsFiles) -> Result<Configs, TlsError> {
    let certs = read_certs(&files.cert)?;
    let key = read_key(&files.key)?;
    let verifier = match &files.client_ca {
        None => None,
        Some(ca) => {
            let mut roots = RootCertStore::empty();
            for c in read_certs(ca)? {
                roots.add(c).map_err(|e| {
                    TlsError::invalid(ca, format!("not a usable CA certificate: {e}"))
                })?;
            }
            Some(
                WebPkiClientVerifier::builder_with_provider(Arc::new(roots), provider())
                    .build()
                    .map_err(|e| TlsError::invalid(ca, format!("not a usable client CA: {e}")))?,
            )
        }
    };
    let config = |alpn: &[u8], verifier| -> Result<Arc<ServerConfig>, TlsError> {
        let builder = ServerConfig::builder_with_provider(provider())
            .with_safe_default_protocol_versions()
            .map_err(|e| TlsError::invalid(&files.cert, e.to_string()))?;
        let builder = match verifier {
            Some(v) => builder.with_client_cert_verifier(v),
            None => builder.with_no_client_auth(),
        };
        let mut cfg = builder
            .with_single_cert(certs.clone(), key.clone_key())
            .map_err(|e| {
                TlsError::invalid(
                    &files.key,
                    format!(
                        "does not go with the certificate {}: {e}",
                        files.cert.display()
                    ),
                )
            })?;
        cfg.alpn_protocols = vec![alpn.to_vec()];
        Ok(Arc::new(cfg))
    };
    Ok(Configs {
        http: config(b"http/1.1", None)?,
        grpc: config(b"h2", verifier)?,
    })
}

/// Who is on the other end of a gRPC connection: its address and, under mutual TLS, the
/// common name of its certificate. tonic puts it in every request's extensions.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct PeerInfo {
    /// The peer's socket address.
    pub remote_addr: Option<SocketAddr>,
    /// The CN of the client certificate's subject, if it presented one with a CN.
    pub identity: Option<String>,
}

/// A TLS connection on the gRPC port, as tonic serves it.
pub struct GrpcTlsStream {
    inner: TlsStream<TcpStream>,
    info: PeerInfo,
}

impl tonic::transport::server::Connected for GrpcTlsStream {
    type ConnectInfo = PeerInfo;

    fn connect_info(&self) -> PeerInfo {
        self.info.clone()
    }
}

impl AsyncRead for GrpcTlsStream {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_read(cx, buf)
    }
}

impl AsyncWrite for GrpcTlsStream {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.inner).poll_write(cx, buf)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.inner).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.inner.is_write_vectored()
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }
}

/// The gRPC port's connections after their TLS handshake, for tonic's
/// `serve_with_incoming_shutdown`. Accepting stops when the stream is dropped.
pub fn grpc_incoming(
    listener: TcpListener,
    tls: Arc<ServerTls>,
) -> tokio_stream::wrappers::ReceiverStream<io::Result<GrpcTlsStream>> {
    let (tx, rx) = mpsc::channel::<io::Result<GrpcTlsStream>>(64);
    tokio::spawn(async move {
        loop {
            let (stream, peer) = tokio::select! {
                _ = tx.closed() => return,
                accepted = listener.accept() => match accepted {
                    Ok(a) => a,
                    Err(e) => {
                        tracing::warn!(error = %e, "cannot accept a gRPC connection");
                        tokio::time::sleep(Duration::from_millis(100)).await;
                        continue;
                    }
                },
            };
            // TCP_NODELAY: see `server::spawn_grpc`.
            let _ = stream.set_nodelay(true);
            let acceptor = tls.grpc_acceptor();
            let tx = tx.clone();
            tokio::spawn(async move {
                match tokio::time::timeout(GRPC_HANDSHAKE_TIMEOUT, acceptor.accept(stream)).await {
                    Ok(Ok(s)) => {
                        let identity = s
                            .get_ref()
                            .1
                            .peer_certificates()
                            .and_then(|c| c.first())
                            .and_then(|c| subject_common_name(c.as_ref()));
                        let info = PeerInfo {
                            remote_addr: Some(peer),
                            identity,
                        };
                        let _ = tx.send(Ok(GrpcTlsStream { inner: s, info })).await;
                    }
                    Ok(Err(e)) => {
                        tracing::info!(peer = %peer, error = %e, "gRPC TLS handshake refused")
                    }
                    Err(_) => tracing::info!(peer = %peer, "gRPC TLS handshake timed out"),
                }
            });
        }
    });
    tokio_stream::wrappers::ReceiverStream::new(rx)
}

/// One DER element: its tag, its contents and what follows it.
fn der(input: &[u8]) -> Option<(u8, &[u8], &[u8])> {
    let (&tag, rest) = input.split_first()?;
    let (&first, rest) = rest.split_first()?;
    let (len, rest) = if first < 0x80 {
        (usize::from(first), rest)
    } else {
        let n = usize::from(first & 0x7f);
        if n == 0 || n > 4 || rest.len() < n {
            return None;
        }
        let len = rest[..n]
            .iter()
            .fold(0usize, |acc, &b| (acc << 8) | usize::from(b));
        (len, &rest[n..])
    };
    if rest.len() < len {
        return None;
    }
    Some((tag, &rest[..len], &rest[len..]))
}

/// The common name (OID 2.5.4.3) of a DER certificate's subject, if it has one that is a
/// string. The certificate has already been verified; anything unexpected yields `None`.
pub fn subject_common_name(cert: &[u8]) -> Option<String> {
    const SEQUENCE: u8 = 0x30;
    const CN: &[u8] = &[0x55, 0x04, 0x03];
    let (tag, cert, _) = der(cert)?;
    if tag != SEQUENCE {
        return None;
    }
    let (tag, tbs, _) = der(cert)?;
    if tag != SEQUENCE {
        return None;
    }
    let mut rest = tbs;
    // [0] version (optional), serial, signature algorithm, issuer, validity, subject.
    let (tag, _, r) = der(rest)?;
    if tag == 0xa0 {
        rest = r;
    }
    for _ in 0..4 {
        rest = der(rest)?.2;
    }
    let (tag, mut subject, _) = der(rest)?;
    if tag != SEQUENCE {
        return None;
    }
    while !subject.is_empty() {
        let (_, mut set, r) = der(subject)?;
        subject = r;
        while !set.is_empty() {
            let (_, attr, r) = der(set)?;
            set = r;
            let (tag, oid, value) = der(attr)?;
            if tag == 0x06 && oid == CN {
                let (_, v, _) = der(value)?;
                return std::str::from_utf8(v).ok().map(str::to_string);
            }
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
        let p = dir.join(name);
        std::fs::write(&p, text).unwrap();
        p
    }

    fn self_signed(cn: &str) -> (String, String) {
        let key = rcgen::KeyPair::generate().unwrap();
        let mut params = rcgen::CertificateParams::new(vec!["localhost".into()]).unwrap();
        params
            .distinguished_name
            .push(rcgen::DnType::CommonName, cn);
        params
            .distinguished_name
            .push(rcgen::DnType::OrganizationName, "tessera tests");
        let cert = params.self_signed(&key).unwrap();
        (cert.pem(), key.serialize_pem())
    }

    #[test]
    fn the_common_name_is_read_from_the_subject() {
        let key = rcgen::KeyPair::generate().unwrap();
        let mut params = rcgen::CertificateParams::new(vec!["w".into()]).unwrap();
        params
            .distinguished_name
            .push(rcgen::DnType::OrganizationName, "farm");
        params
            .distinguished_name
            .push(rcgen::DnType::CommonName, "worker-7");
        let cert = params.self_signed(&key).unwrap();
        assert_eq!(subject_common_name(cert.der()).as_deref(), Some("worker-7"));
        let mut params = rcgen::CertificateParams::new(vec!["w".into()]).unwrap();
        params.distinguished_name = rcgen::DistinguishedName::new();
        let cert = params.self_signed(&key).unwrap();
        assert_eq!(subject_common_name(cert.der()), None);
        for bad in [
            &b""[..],
            b"\x30",
            b"\x30\x84\xff\xff\xff\xff",
            b"\x02\x01\x00",
        ] {
            assert_eq!(subject_common_name(bad), None);
        }
    }

    #[test]
    fn bad_files_are_named_and_a_failed_reload_keeps_the_old_configuration() {
        let dir = tempfile::tempdir().unwrap();
        let (cert, key) = self_signed("one");
        let files = TlsFiles {
            cert: write(dir.path(), "cert.pem", &cert),
            key: write(dir.path(), "key.pem", &key),
            client_ca: None,
        };
        let tls = ServerTls::load(files.clone()).unwrap();

        let missing = TlsFiles {
            cert: dir.path().join("nope.pem"),
            ..files.clone()
        };
        let e = ServerTls::load(missing).unwrap_err().to_string();
        assert!(e.contains("nope.pem"), "{e}");

        let garbage = write(dir.path(), "garbage.pem", "not a certificate\n");
        let e = ServerTls::load(TlsFiles {
            key: garbage.clone(),
            ..files.clone()
        })
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("garbage.pem") && e.contains("private key"),
            "{e}"
        );
        let e = ServerTls::load(TlsFiles {
            client_ca: Some(garbage),
            ..files.clone()
        })
        .unwrap_err()
        .to_string();
        assert!(e.contains("garbage.pem"), "{e}");

        let (_, other_key) = self_signed("two");
        write(dir.path(), "key.pem", &other_key);
        let before = Arc::as_ptr(&tls.configs());
        let e = tls.reload().unwrap_err().to_string();
        assert!(e.contains("key.pem"), "{e}");
        assert_eq!(
            Arc::as_ptr(&tls.configs()),
            before,
            "the old configuration stays"
        );

        write(dir.path(), "key.pem", &key);
        tls.reload().unwrap();
        assert_ne!(Arc::as_ptr(&tls.configs()), before);
    }
}
