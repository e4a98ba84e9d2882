//! The dashboard's static files, embedded in the binary (no front-end build step).

/// An embedded file.
pub struct Asset {
    /// Its MIME type.
    pub content_type: &'static str,
    /// Its bytes.
    pub bytes: &'static [u8],
}

/// The embedded file served at `path` ("/", "/index.html" or "/assets/NAME").
pub fn asset(path: &str) -> Option<Asset> {
    match path {
        "/" | "/index.html" => Some(Asset {
            content_type: "text/html; charset=utf-8",
            bytes: b"<!doctype html><title>Tessera</title><p>Tessera coordinator. The API is at /api/v1.</p>",
        }),
        _ => None,
    }
}
