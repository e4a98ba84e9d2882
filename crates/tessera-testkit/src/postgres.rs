//! A fresh PostgreSQL database for a test (docs/store.md, "Testing against PostgreSQL").
//!
//! `TESSERA_TEST_POSTGRES` is the URL of an empty database the tests may create schemas
//! in (`.ci/postgres start` makes one). Each test gets its own schema, named after it and
//! this process, and the URL it returns puts that schema first on the `search_path`, so
//! tests run in parallel without seeing each other's tables. Without the variable a test
//! is skipped (it says so and passes), unless `TESSERA_REQUIRE_POSTGRES=1`, when it fails:
//! CI sets both, so a PostgreSQL test cannot silently not run there.
//!
//! Used by the coordinator's store suite (crates/tessera-coordinator/tests/it/store.rs)
//! and the end-to-end suites (tests/e2e/).

use sqlx::Connection;

/// The variable naming the test database.
pub const TEST_POSTGRES: &str = "TESSERA_TEST_POSTGRES";
/// Set to `1` to make a missing [`TEST_POSTGRES`] a failure instead of a skip.
pub const REQUIRE_POSTGRES: &str = "TESSERA_REQUIRE_POSTGRES";

/// The URL of a new, empty schema for the test `name` in the test database, or `None`
/// (after printing that the test is skipped) when [`TEST_POSTGRES`] is not set.
pub async fn fresh_database(name: &str) -> Option<String> {
    let Some(base) = std::env::var(TEST_POSTGRES).ok().filter(|v| !v.is_empty()) else {
        if std::env::var(REQUIRE_POSTGRES).as_deref() == Ok("1") {
            panic!(
                "{REQUIRE_POSTGRES}=1 but {TEST_POSTGRES} is not set: set it to the URL of \
                 an empty PostgreSQL database (`.ci/postgres start DIR` starts a server and \
                 prints one)"
            );
        }
        eprintln!("skipped: {name} needs PostgreSQL; set {TEST_POSTGRES} to run it");
        return None;
    };
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.subsec_nanos());
    let safe: String = name
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() {
                c.to_ascii_lowercase()
            } else {
                '_'
            }
        })
        .take(40)
        .collect();
    let schema = format!("t_{safe}_{}_{nanos}", std::process::id());
    let mut conn = sqlx::PgConnection::connect(&base)
        .await
        .unwrap_or_else(|e| panic!("cannot connect to {TEST_POSTGRES}={base}: {e}"));
    sqlx::raw_sql(&format!("CREATE SCHEMA {schema}"))
        .execute(&mut conn)
        .await
        .unwrap_or_else(|e| panic!("cannot create schema {schema} in {base}: {e}"));
    let _ = conn.close().await;
    let sep = if base.contains('?') { '&' } else { '?' };
    Some(format!("{base}{sep}options=-c%20search_path%3D{schema}"))
}
