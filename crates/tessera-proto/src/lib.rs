//! The Tessera coordinator <-> worker gRPC protocol: `proto/tessera/v1/worker.proto`,
//! compiled at build time with [protox](https://docs.rs/protox) (no system `protoc`) into
//! prost messages and tonic client and server code ([`v1`]), plus checked conversions
//! between the wire messages and the domain types of `tessera-farm` (its job contract, [`tessera_farm::job`], included).
//!
//! Everything arriving over the wire is untrusted: the `TryFrom` conversions validate
//! every field and return a [`ProtoError`] naming the offending one (which converts into
//! a `tonic::Status` with code `INVALID_ARGUMENT`). The `From` conversions in the other
//! direction cannot fail.
//!
//! | wire message | domain type |
//! |---|---|
//! | [`v1::FramePlan`] | [`tessera_farm::FramePlan`] |
//! | [`v1::WorkUnit`] | [`tessera_farm::WorkUnit`] |
//! | [`v1::SubmitResultRequest`] | [`tessera_farm::UnitResult`] (+ worker, lease, seconds) |
//! | [`v1::RenderSettings`] | [`tessera_farm::job::RenderConfig`] |
//! | [`v1::Lease`] | [`LeasedUnit`] |
//!
//! Features: `transport` generates `WorkerServiceClient::connect` and enables tonic's
//! client transport. A server needs no feature of this crate (the coordinator enables
//! tonic's `server`/`router` itself).
//!
//! ```
//! use tessera_farm::{FramePlan, UnitResult};
//! use tessera_proto::v1;
//!
//! let plan = FramePlan::for_spp(64, 48, 64, 32)?;
//! let wire = v1::FramePlan::from(&plan);
//! assert_eq!(FramePlan::try_from(wire)?, plan);
//!
//! let unit = plan.units(0, 1)[0];
//! let result = UnitResult { unit, width: 32, height: 32, pass_means: vec![[0.5; 3]; 32 * 32], rejected_samples: 0, bias: None };
//! let request = v1::SubmitResultRequest::from_result(7, 99, &result, 0.25);
//! assert_eq!(request.means().len(), 3 * 32 * 32);
//! assert_eq!(UnitResult::try_from(request)?, result);
//!
//! let bad = v1::FramePlan { width: 0, ..v1::FramePlan::from(&plan) };
//! let err = FramePlan::try_from(bad).unwrap_err();
//! assert_eq!(err.field, "width");
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```
#![deny(missing_docs)]

/// The generated `tessera.v1` package: messages, enums, `worker_service_client` and
/// `worker_service_server`. Field documentation is the `.proto` file's.
#[allow(missing_docs, clippy::all, clippy::pedantic)]
pub mod v1 {
    tonic::include_proto!("tessera.v1");
}

mod convert;

pub use convert::{
    means_from_bytes, means_to_bytes, LeasedUnit, ProtoError, MAX_FENCE_BYTES, MAX_TILE_INDEX,
};

/// The gRPC metadata key carrying a worker's session secret (`RegisterResponse.session`)
/// on every call after Register that names its worker id (worker.proto, "Sessions").
pub const SESSION_METADATA: &str = "x-tessera-session";

/// A client interceptor adding a worker's session secret ([`SESSION_METADATA`]) to every
/// call: `WorkerServiceClient::with_interceptor(channel, WithSession::new(&session)?)`
/// after Register.
#[derive(Clone, Debug)]
pub struct WithSession(tonic::metadata::MetadataValue<tonic::metadata::Ascii>);

impl WithSession {
    /// The interceptor of `session` (`RegisterResponse.session`); an error if it is not
    /// a valid metadata value (printable ASCII).
    pub fn new(session: &str) -> Result<Self, tonic::metadata::errors::InvalidMetadataValue> {
        Ok(Self(session.parse()?))
    }
}

impl tonic::service::Interceptor for WithSession {
    fn call(&mut self, mut req: tonic::Request<()>) -> Result<tonic::Request<()>, tonic::Status> {
        req.metadata_mut().insert(SESSION_METADATA, self.0.clone());
        Ok(req)
    }
}
pub use v1::worker_service_client::WorkerServiceClient;
pub use v1::worker_service_server::{WorkerService, WorkerServiceServer};

/// Fully qualified name of the gRPC service, as it appears in request paths.
pub const SERVICE_NAME: &str = "tessera.v1.WorkerService";
