//! The worker's TLS settings: PEM files checked when read, and read again before each
//! connection so that a rotated certificate is presented without a restart.

use crate::WorkerError;
use tonic::transport::{Certificate, ClientTlsConfig, Identity};

/// A worker's TLS settings, read from PEM files by [`WorkerTls::from_files`].
///
/// Read from files, they are read again before every connection to a coordinator
/// ([`WorkerTls::reread`]): a certificate that rotates under a running worker (a
/// per-pod certificate that cert-manager's csi-driver renews before it expires,
/// docs/deploy.md) is presented on the next connection, without a restart.
#[derive(Clone)]
pub struct WorkerTls {
    /// The CA certificates (PEM) the coordinator's certificate must be issued by.
    pub ca_pem: Vec<u8>,
    /// The worker's certificate chain and private key (PEM), for mutual TLS.
    pub identity: Option<(Vec<u8>, Vec<u8>)>,
    /// The files they were read from, if they were: the CA, then the certificate and key.
    pub files: Option<TlsFiles>,
}

/// The PEM files of a [`WorkerTls`].
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TlsFiles {
    /// The CA certificates.
    pub ca: std::path::PathBuf,
    /// For mutual TLS: the worker's certificate chain and its private key.
    pub cert_and_key: Option<(std::path::PathBuf, std::path::PathBuf)>,
}

impl std::fmt::Debug for WorkerTls {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("WorkerTls")
            .field("ca_pem_bytes", &self.ca_pem.len())
            .field("client_certificate", &self.identity.is_some())
            .finish()
    }
}

impl WorkerTls {
    /// Reads the CA file and, for mutual TLS, the certificate and key files, checking
    /// that each holds what it should (errors name the file).
    pub fn from_files(
        ca: &std::path::Path,
        cert_and_key: Option<(&std::path::Path, &std::path::Path)>,
    ) -> Result<Self, WorkerError> {
        use rustls::pki_types::pem::PemObject;
        use rustls::pki_types::{CertificateDer, PrivateKeyDer};
        let read = |p: &std::path::Path| {
            std::fs::read(p)
                .map_err(|e| WorkerError::Config(format!("cannot read {}: {e}", p.display())))
        };
        let certs = |p: &std::path::Path, bytes: &[u8]| {
            let n = CertificateDer::pem_slice_iter(bytes)
                .collect::<Result<Vec<_>, _>>()
                .map_err(|e| {
                    WorkerError::Config(format!("{}: malformed PEM certificate: {e}", p.display()))
                })?
                .len();
            if n == 0 {
                return Err(WorkerError::Config(format!(
                    "{}: no PEM certificate in the file",
                    p.display()
                )));
            }
            Ok(())
        };
        let ca_pem = read(ca)?;
        certs(ca, &ca_pem)?;
        let identity = match cert_and_key {
            None => None,
            Some((cert, key)) => {
                let cert_pem = read(cert)?;
                certs(cert, &cert_pem)?;
                let key_pem = read(key)?;
                PrivateKeyDer::from_pem_slice(&key_pem).map_err(|e| {
                    WorkerError::Config(format!(
                        "{}: no usable PEM private key: {e}",
                        key.display()
                    ))
                })?;
                Some((cert_pem, key_pem))
            }
        };
        let files = Some(TlsFiles {
            ca: ca.to_path_buf(),
            cert_and_key: cert_and_key.map(|(c, k)| (c.to_path_buf(), k.to_path_buf())),
        });
        Ok(Self {
            ca_pem,
            identity,
            files,
        })
    }

    /// The settings read again from the files they came from, if the files now hold
    /// something else; `None` when they did not come from files or are unchanged. An
    /// error (a file missing or half written during a rotation) names the file; the
    /// caller keeps the settings it has.
    pub fn reread(&self) -> Option<Result<Self, WorkerError>> {
        let files = self.files.as_ref()?;
        let cert_and_key = files
            .cert_and_key
            .as_ref()
            .map(|(c, k)| (c.as_path(), k.as_path()));
        match Self::from_files(&files.ca, cert_and_key) {
            Ok(fresh) if fresh.ca_pem == self.ca_pem && fresh.identity == self.identity => None,
            other => Some(other),
        }
    }

    /// The client side of the handshake: the CA to trust and, for mutual TLS, the
    /// identity to present.
    pub(crate) fn client_config(&self) -> ClientTlsConfig {
        let mut cfg = ClientTlsConfig::new().ca_certificate(Certificate::from_pem(&self.ca_pem));
        if let Some((cert, key)) = &self.identity {
            cfg = cfg.identity(Identity::from_pem(cert, key));
        }
        cfg
    }
}
