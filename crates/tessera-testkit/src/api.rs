//! The HTTP API's errors as the typed client (`tessera_api::client`) returns them.

use tessera_api::client::ClientError;
use tessera_api::ApiError;

/// The status and error body of a request that the API refused; fails the test if `r`
/// succeeded or failed otherwise (transport, decoding).
pub fn api_error<T: std::fmt::Debug>(r: Result<T, ClientError>) -> (u16, ApiError) {
    match r {
        Err(ClientError::Api { status, error }) => (status, error),
        other => panic!("expected an API error, got {other:?}"),
    }
}
