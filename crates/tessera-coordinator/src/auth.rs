//! Bearer tokens, for the HTTP API and for workers (ARCHITECTURE.md §5, §6).
//!
//! One rule for both ports: the `Authorization` value is `<scheme> <token>` with the
//! scheme `Bearer` in any letter case (RFC 9110 §11.1: the scheme is case-insensitive),
//! and the token is compared in constant time: both sides are hashed with SHA-256 and the
//! digests compared without an early exit, so neither the token's bytes nor its length
//! leak through timing. Tokens are never logged (the request log has the path only).

use sha2::{Digest, Sha256};

/// Whether the `Authorization` header value `given` carries the bearer token `token`.
pub fn bearer_matches(given: Option<&str>, token: &str) -> bool {
    let Some(given) = given else {
        return false;
    };
    let given = given.trim_start();
    let Some((scheme, presented)) = given.split_once(' ') else {
        return false;
    };
    scheme.eq_ignore_ascii_case("bearer") && constant_time_eq(presented.trim(), token)
}

/// The name scene quotas count an API client's uploads under (docs/store.md, "Scene
/// storage"): `token:` and the first 16 hex digits of the SHA-256 of the bearer token it
/// was admitted with, so the name is stable across restarts and never reveals the token;
/// `anonymous` on a coordinator without an API token.
pub fn client_name(token: Option<&str>) -> String {
    match token {
        None => "anonymous".into(),
        Some(t) => {
            let digest = Sha256::digest(t.as_bytes());
            let hex: String = digest[..8].iter().map(|b| format!("{b:02x}")).collect();
            format!("token:{hex}")
        }
    }
}

/// Compares two secrets in time independent of their contents and lengths.
fn constant_time_eq(a: &str, b: &str) -> bool {
    let (da, db) = (Sha256::digest(a.as_bytes()), Sha256::digest(b.as_bytes()));
    da.iter()
        .zip(db.iter())
        .fold(0u8, |acc, (x, y)| acc | (x ^ y))
        == 0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_scheme_is_case_insensitive_and_the_token_exact() {
        for h in [
            "Bearer s3cret",
            "bearer s3cret",
            "BEARER s3cret",
            "bEaReR  s3cret",
        ] {
            assert!(bearer_matches(Some(h), "s3cret"), "{h}");
        }
        for h in [
            "Bearer s3cre",
            "Bearer s3cret2",
            "Bearer S3CRET",
            "Basic s3cret",
            "Bearers3cret",
            "s3cret",
            "Bearer ",
            "",
        ] {
            assert!(!bearer_matches(Some(h), "s3cret"), "{h}");
        }
        assert!(!bearer_matches(None, "s3cret"));
    }
}
