//! Waits in async tests that fail instead of hanging: a bound on how long a future may
//! take, used only to turn a hang into a failure (no test asserts a duration with it).

use std::future::Future;
use std::time::Duration;

/// How long [`bounded`] lets a future run before it fails the test. Generous, since it
/// only exists to fail a hung test; a loaded CI machine must not reach it.
pub const HANG: Duration = Duration::from_secs(60);

/// Awaits `f`, failing the test (naming `what`) if it takes longer than [`HANG`].
pub async fn bounded<T>(what: &str, f: impl Future<Output = T>) -> T {
    tokio::time::timeout(HANG, f)
        .await
        .unwrap_or_else(|_| panic!("{what}: nothing happened within {HANG:?}"))
}
