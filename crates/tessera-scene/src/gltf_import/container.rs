//! Step 1, the container: `.gltf` JSON or the `.glb` binary container (spec "GLB File
//! Format Specification"), the document-level checks, and the buffers with their `data:`
//! URIs and external files, under the size limits of the module documentation.

use super::meshes::prim_name;
use super::{Importer, Res};
use crate::SceneError;
use gltf::json;
use json::validation::Checked;
use std::io::Read;
use std::path::{Component, Path, PathBuf};

/// Where external URIs are resolved.
pub(super) struct BaseDir {
    /// The directory.
    pub(super) dir: PathBuf,
    /// Whether `..` components may leave `dir`.
    pub(super) allow_parent: bool,
}

/// Why [`read_capped`] failed.
pub(super) enum ReadError {
    /// Reading failed.
    Io(std::io::Error),
    /// The file has more bytes (the count given) than the limit.
    TooLarge(u64),
}

/// Reads a whole file, refusing (before reading) files larger than `limit` bytes.
pub(super) fn read_capped(path: &Path, limit: u64) -> Result<Vec<u8>, ReadError> {
    let file = std::fs::File::open(path).map_err(ReadError::Io)?;
    let meta = file.metadata().map_err(ReadError::Io)?;
    if meta.is_dir() {
        return Err(ReadError::Io(std::io::Error::other("is a directory")));
    }
    if meta.len() > limit {
        return Err(ReadError::TooLarge(meta.len()));
    }
    let mut bytes = Vec::with_capacity(meta.len() as usize);
    // The file may grow between the metadata call and the read: read at most limit + 1.
    file.take(limit.saturating_add(1))
        .read_to_end(&mut bytes)
        .map_err(ReadError::Io)?;
    if bytes.len() as u64 > limit {
        return Err(ReadError::TooLarge(bytes.len() as u64));
    }
    Ok(bytes)
}

impl Importer<'_> {
    /// Checks the document as a whole: the asset version, then the `gltf` crate's
    /// validation of indices and required properties (run under the caller's panic guard,
    /// after the pre-checks below that would otherwise panic inside it).
    pub(super) fn check_document(&mut self) -> Res<()> {
        let version = self.root.asset.version.clone();
        if version.split('.').next() != Some("2") {
            return self.err(format!(
                "asset.version is {version:?}; only glTF 2.x is supported"
            ));
        }
        let naccessors = self.root.accessors.len();
        let nmaterials = self.root.materials.len();
        for (mi, mesh) in self.root.meshes.iter().enumerate() {
            for (pi, prim) in mesh.primitives.iter().enumerate() {
                let what = prim_name(mi, mesh, pi);
                for (semantic, a) in &prim.attributes {
                    if a.value() >= naccessors {
                        return self.err(format!(
                            "{what}: attribute {} refers to accessor {}, but there are only \
                             {naccessors}",
                            semantic_name(semantic),
                            a.value()
                        ));
                    }
                }
                if let Some(a) = prim.indices.filter(|a| a.value() >= naccessors) {
                    return self.err(format!(
                        "{what}: indices refer to accessor {}, but there are only {naccessors}",
                        a.value()
                    ));
                }
                if let Some(m) = prim.material.filter(|m| m.value() >= nmaterials) {
                    return self.err(format!(
                        "{what}: material index {} is past the end ({nmaterials} materials)",
                        m.value()
                    ));
                }
            }
        }
        let root = std::mem::take(&mut self.root);
        match gltf::Document::from_json(root) {
            Ok(doc) => {
                self.root = doc.into_json();
                Ok(())
            }
            Err(gltf::Error::Validation(errors)) => {
                let mut message = String::from("invalid glTF:");
                for (path, error) in errors.iter().take(8) {
                    message.push_str(&format!(" {path}: {error};"));
                }
                if errors.len() > 8 {
                    message.push_str(&format!(" and {} more", errors.len() - 8));
                }
                self.err(message)
            }
            Err(e) => self.err(format!("invalid glTF: {e}")),
        }
    }

    /// Loads every buffer (GLB binary chunk, `data:` URI or external file) and checks its
    /// length against its `byteLength` (spec "Buffers and Buffer Views").
    pub(super) fn load_buffers(&mut self, mut bin: Option<&[u8]>) -> Res<()> {
        let declared: u64 = self
            .root
            .buffers
            .iter()
            .fold(0u64, |sum, b| sum.saturating_add(b.byte_length.0));
        if declared > self.limit {
            return Err(SceneError::TooLarge {
                path: format!("{} (sum of buffer byteLengths)", self.file),
                bytes: declared,
                limit: self.limit,
            });
        }
        let mut buffers = Vec::with_capacity(self.root.buffers.len());
        for i in 0..self.root.buffers.len() {
            let what = format!("buffer {i}");
            let (uri, len) = (
                self.root.buffers[i].uri.clone(),
                self.root.buffers[i].byte_length.0,
            );
            let mut data = match &uri {
                None => match bin.take() {
                    // Spec "GLB File Format Specification > Binary buffer": the BIN chunk
                    // is the first buffer, the one without a uri.
                    Some(b) if i == 0 => b.to_vec(),
                    _ => {
                        return self.err(format!(
                            "{what} has no uri and there is no GLB binary chunk for it"
                        ))
                    }
                },
                Some(uri) => self.read_uri(uri, &what)?.1,
            };
            if (data.len() as u64) < len {
                return self.err(format!(
                    "{what} declares byteLength {len} but its data has only {} bytes",
                    data.len()
                ));
            }
            data.truncate(len as usize);
            buffers.push(data);
        }
        self.buffers = buffers;
        Ok(())
    }

    /// Reads the bytes a URI refers to: a base64 `data:` URI or a relative path. Returns the
    /// media type of a data URI (if it names one) and the bytes.
    pub(super) fn read_uri(&mut self, uri: &str, what: &str) -> Res<(Option<String>, Vec<u8>)> {
        let shown = truncate_for_message(uri);
        if let Some(rest) = uri.strip_prefix("data:") {
            let Some((meta, payload)) = rest.split_once(',') else {
                return self.err(format!("{what}: data URI without ',': {shown:?}"));
            };
            let Some(mime) = meta.strip_suffix(";base64") else {
                return self.err(format!(
                    "{what}: only base64 data URIs are supported, got {shown:?}"
                ));
            };
            let data = decode_base64(payload)
                .or_else(|e| self.err(format!("{what}: bad base64 in data URI: {e}")))?;
            let mime = (!mime.is_empty()).then(|| mime.to_string());
            return Ok((mime, data));
        }
        if has_scheme(uri) {
            return self.err(format!(
                "{what}: URI {shown:?} is not supported (only data: URIs and relative paths)"
            ));
        }
        let relative = match percent_decode(uri) {
            Ok(p) => p,
            Err(e) => return self.err(format!("{what}: URI {shown:?}: {e}")),
        };
        let Some(base) = &self.base else {
            return self.err(format!(
                "{what} refers to the external file {shown:?}, but the document was given \
                 in memory without a base directory (embed it as a data: URI or use .glb)"
            ));
        };
        let rel = Path::new(&relative);
        for c in rel.components() {
            match c {
                Component::Normal(_) | Component::CurDir => {}
                Component::ParentDir if base.allow_parent => {}
                _ => {
                    return self.err(format!(
                        "{what}: URI {shown:?} must be a relative path inside the base directory"
                    ))
                }
            }
        }
        let path = base.dir.join(rel);
        let remaining = self.limit.saturating_sub(self.input_bytes);
        let data = match read_capped(&path, remaining) {
            Ok(d) => d,
            Err(ReadError::Io(e)) => {
                return self.err(format!(
                    "{what}: cannot read URI {shown:?} ({}): {e}",
                    path.display()
                ))
            }
            Err(ReadError::TooLarge(bytes)) => {
                return Err(SceneError::TooLarge {
                    path: format!("{} ({what}: {})", self.file, path.display()),
                    bytes: bytes.saturating_add(self.input_bytes),
                    limit: self.limit,
                })
            }
        };
        self.input_bytes += data.len() as u64;
        Ok((None, data))
    }
}

/// The name of an attribute semantic, for messages.
fn semantic_name(s: &Checked<json::mesh::Semantic>) -> String {
    match s {
        Checked::Valid(s) => s.to_string(),
        Checked::Invalid => "(invalid)".into(),
    }
}

/// Splits a GLB into its JSON chunk and optional BIN chunk (spec "GLB File Format
/// Specification"), checking every length against the data actually present.
pub(super) fn split_glb(bytes: &[u8]) -> Result<(&[u8], Option<&[u8]>), String> {
    let u32_at = |at: usize| {
        bytes
            .get(at..at + 4)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    };
    let (Some(version), Some(length)) = (u32_at(4), u32_at(8)) else {
        return Err(format!(
            "truncated .glb: {} bytes, the header alone is 12",
            bytes.len()
        ));
    };
    if version != 2 {
        return Err(format!("unsupported .glb container version {version}"));
    }
    let length = length as usize;
    if length > bytes.len() {
        return Err(format!(
            "truncated .glb: the header declares {length} bytes but there are only {}",
            bytes.len()
        ));
    }
    if length < 12 {
        return Err(format!(
            "invalid .glb: declared length {length} is shorter than the header"
        ));
    }
    let data = &bytes[..length];
    let mut at = 12;
    let mut json = None;
    let mut bin = None;
    let mut chunk = 0;
    while at + 8 <= data.len() {
        let len = u32::from_le_bytes([data[at], data[at + 1], data[at + 2], data[at + 3]]) as usize;
        let kind = &data[at + 4..at + 8];
        let start = at + 8;
        let end = start
            .checked_add(len)
            .filter(|&e| e <= data.len())
            .ok_or_else(|| {
                format!(
                    "truncated .glb: chunk {chunk} declares {len} bytes but only {} remain",
                    data.len() - start
                )
            })?;
        match (chunk, kind) {
            (0, b"JSON") => json = Some(&data[start..end]),
            (0, _) => return Err("invalid .glb: the first chunk is not JSON".into()),
            (1, b"BIN\0") => bin = Some(&data[start..end]),
            _ => {} // Unknown chunks must be ignored.
        }
        chunk += 1;
        at = end;
    }
    match json {
        Some(j) => Ok((j, bin)),
        None => Err("invalid .glb: no JSON chunk".into()),
    }
}

/// Parses glTF JSON, tolerating a UTF-8 byte-order mark and trailing NUL padding. Every
/// top-level array (`nodes`, `meshes`, `accessors`, ...) is first counted without being
/// built, and one longer than `max_elements` is refused: a parsed element takes up to a
/// few hundred bytes, so `[{},{},...]` would otherwise amplify a file a hundredfold.
pub(super) fn parse_json(bytes: &[u8], max_elements: u64) -> Result<json::Root, String> {
    let bytes = bytes.strip_prefix(b"\xef\xbb\xbf").unwrap_or(bytes);
    let end = bytes
        .iter()
        .rposition(|&b| b != 0 && !b.is_ascii_whitespace())
        .map_or(0, |p| p + 1);
    let bytes = &bytes[..end];
    let mut de = serde_json::Deserializer::from_slice(bytes);
    if let Err(e) = serde::Deserializer::deserialize_any(&mut de, TopLevel(max_elements)) {
        // Malformed JSON is reported by the real parse below, with its own message.
        let message = e.to_string();
        if message.starts_with(TOO_MANY) {
            return Err(message.split(" at line").next().unwrap_or("").to_string());
        }
    }
    json::deserialize::from_slice(bytes).map_err(|e| format!("invalid glTF JSON: {e}"))
}

/// The start of the counting pass's error for an overlong array.
const TOO_MANY: &str = "the document's";

/// Counts the elements of every top-level array of a glTF document, building nothing.
struct TopLevel(u64);

impl<'de> serde::de::Visitor<'de> for TopLevel {
    type Value = ();
    fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        f.write_str("a glTF JSON object")
    }
    fn visit_map<A: serde::de::MapAccess<'de>>(self, mut map: A) -> Result<(), A::Error> {
        while let Some(key) = map.next_key::<std::borrow::Cow<'de, str>>()? {
            map.next_value_seed(Counted {
                key: &key,
                max: self.0,
            })?;
        }
        Ok(())
    }
}

/// One top-level value: an array is counted element by element (each skipped), anything
/// else skipped.
struct Counted<'k> {
    key: &'k str,
    max: u64,
}

impl<'de> serde::de::DeserializeSeed<'de> for Counted<'_> {
    type Value = ();
    fn deserialize<D: serde::Deserializer<'de>>(self, d: D) -> Result<(), D::Error> {
        d.deserialize_any(self)
    }
}

impl<'de> serde::de::Visitor<'de> for Counted<'_> {
    type Value = ();
    fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        f.write_str("any JSON value")
    }
    fn visit_seq<A: serde::de::SeqAccess<'de>>(self, mut seq: A) -> Result<(), A::Error> {
        let mut n = 0u64;
        while seq.next_element::<serde::de::IgnoredAny>()?.is_some() {
            n += 1;
            if n > self.max {
                return Err(serde::de::Error::custom(format!(
                    "{TOO_MANY} {:?} array has more than {} elements (MAX_NODES)",
                    self.key, self.max
                )));
            }
        }
        Ok(())
    }
    fn visit_map<A: serde::de::MapAccess<'de>>(self, mut map: A) -> Result<(), A::Error> {
        while map
            .next_entry::<serde::de::IgnoredAny, serde::de::IgnoredAny>()?
            .is_some()
        {}
        Ok(())
    }
    fn visit_bool<E>(self, _: bool) -> Result<(), E> {
        Ok(())
    }
    fn visit_i64<E>(self, _: i64) -> Result<(), E> {
        Ok(())
    }
    fn visit_u64<E>(self, _: u64) -> Result<(), E> {
        Ok(())
    }
    fn visit_f64<E>(self, _: f64) -> Result<(), E> {
        Ok(())
    }
    fn visit_str<E>(self, _: &str) -> Result<(), E> {
        Ok(())
    }
    fn visit_unit<E>(self) -> Result<(), E> {
        Ok(())
    }
}

/// True when a URI starts with a scheme (`scheme:`, RFC 3986 section 3.1).
fn has_scheme(uri: &str) -> bool {
    match uri.split_once(':') {
        Some((scheme, _)) => {
            let mut chars = scheme.chars();
            chars.next().is_some_and(|c| c.is_ascii_alphabetic())
                && chars.all(|c| c.is_ascii_alphanumeric() || "+-.".contains(c))
        }
        None => false,
    }
}

/// Decodes `%XX` escapes (RFC 3986 section 2.1); the result must be UTF-8.
fn percent_decode(s: &str) -> Result<String, String> {
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'%' {
            let hex = |c: u8| (c as char).to_digit(16);
            match (
                b.get(i + 1).and_then(|&c| hex(c)),
                b.get(i + 2).and_then(|&c| hex(c)),
            ) {
                (Some(h), Some(l)) => out.push((h * 16 + l) as u8),
                _ => return Err(format!("bad percent-encoding at byte {i}")),
            }
            i += 3;
        } else {
            out.push(b[i]);
            i += 1;
        }
    }
    String::from_utf8(out).map_err(|_| "percent-decoded URI is not UTF-8".to_string())
}

/// Decodes standard (or URL-safe) base64, with optional padding and ignoring whitespace.
fn decode_base64(s: &str) -> Result<Vec<u8>, String> {
    let mut out = Vec::with_capacity(s.len() / 4 * 3 + 3);
    let (mut acc, mut bits, mut padding) = (0u32, 0u32, false);
    for (i, c) in s.bytes().enumerate() {
        let v = match c {
            b'A'..=b'Z' => c - b'A',
            b'a'..=b'z' => c - b'a' + 26,
            b'0'..=b'9' => c - b'0' + 52,
            b'+' | b'-' => 62,
            b'/' | b'_' => 63,
            b'=' => {
                padding = true;
                continue;
            }
            b' ' | b'\t' | b'\r' | b'\n' => continue,
            _ => return Err(format!("invalid character {:?} at offset {i}", c as char)),
        };
        if padding {
            return Err(format!("data after '=' padding at offset {i}"));
        }
        acc = (acc << 6) | u32::from(v);
        bits += 6;
        if bits >= 8 {
            bits -= 8;
            out.push((acc >> bits) as u8);
            acc &= (1 << bits) - 1;
        }
    }
    if bits >= 6 {
        return Err("truncated base64 (length is 1 mod 4)".into());
    }
    Ok(out)
}

/// Shortens long URIs (data URIs) for error messages.
fn truncate_for_message(s: &str) -> String {
    match s.char_indices().nth(60) {
        Some((i, _)) => format!("{}...", &s[..i]),
        None => s.to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base64_round_trips_known_vectors() {
        assert_eq!(decode_base64("").unwrap(), b"");
        assert_eq!(decode_base64("Zg==").unwrap(), b"f");
        assert_eq!(decode_base64("Zm8=").unwrap(), b"fo");
        assert_eq!(decode_base64("Zm9v").unwrap(), b"foo");
        assert_eq!(decode_base64("Zm9vYg").unwrap(), b"foob");
        assert!(decode_base64("Z").is_err());
        assert!(decode_base64("Zm9v!").is_err());
        assert!(decode_base64("Zg==Zg").is_err());
    }

    #[test]
    fn percent_decoding_rejects_bad_escapes() {
        assert_eq!(percent_decode("a%20b.bin").unwrap(), "a b.bin");
        assert!(percent_decode("a%2").is_err());
        assert!(percent_decode("a%zzb").is_err());
        assert!(percent_decode("%ff").is_err());
    }
}
