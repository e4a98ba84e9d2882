//! Job submission over HTTP: the job contract ([`tessera_farm::job`]) with request-body
//! parsing ([`FromJson`]) and its errors as [`ApiError`]s.

use tessera_farm::job::{JobError, JobSettings};

use crate::error::ApiError;

impl From<JobError> for ApiError {
    /// An `invalid_field` error naming the field: the message stays `"{field}: {problem}"`.
    fn from(e: JobError) -> Self {
        ApiError::invalid_field(e.field, e.problem)
    }
}

/// Parsing a request body into a type, with failures as [`ApiError`]s that name the field.
pub trait FromJson: Sized {
    /// Parses a request body. Errors are [`ApiError`]s ready to send: `invalid_request`
    /// for malformed JSON, `invalid_field` naming the field for a wrong type, an unknown
    /// or a missing field.
    fn from_json(body: &[u8]) -> Result<Self, ApiError>;
}

impl FromJson for JobSettings {
    fn from_json(body: &[u8]) -> Result<Self, ApiError> {
        parse_json(body)
    }
}

/// Parses JSON into `T`, mapping failures to [`ApiError`]s that name the field.
pub(crate) fn parse_json<T: serde::de::DeserializeOwned>(body: &[u8]) -> Result<T, ApiError> {
    // Structs would also deserialize from JSON arrays (positionally); only objects are
    // meant.
    if body.iter().find(|b| !b.is_ascii_whitespace()) != Some(&b'{') {
        return Err(ApiError::invalid_request(
            "request body must be a JSON object",
        ));
    }
    let mut de = serde_json::Deserializer::from_slice(body);
    let result: Result<T, _> = serde_path_to_error::deserialize(&mut de);
    let err = match result {
        Ok(v) => {
            // Trailing garbage after the value.
            return match de.end() {
                Ok(()) => Ok(v),
                Err(e) => Err(ApiError::invalid_request(format!(
                    "request body is not valid JSON: {e}"
                ))),
            };
        }
        Err(err) => err,
    };
    let path = err.path().to_string();
    let inner = err.into_inner();
    if !inner.is_data() {
        return Err(ApiError::invalid_request(format!(
            "request body is not valid JSON: {inner}"
        )));
    }
    let text = inner.to_string();
    // Unknown and missing fields are reported at the enclosing object; name the field.
    let named = ["unknown field `", "missing field `"]
        .iter()
        .find_map(|prefix| text.strip_prefix(prefix))
        .and_then(|rest| rest.split('`').next());
    // serde_path_to_error already includes an unknown field in the path, not a missing one.
    let field = match (named, path.as_str()) {
        (Some(name), "." | "") => name.to_owned(),
        (Some(name), p) if p == name || p.ends_with(&format!(".{name}")) => p.to_owned(),
        (Some(name), parent) => format!("{parent}.{name}"),
        (None, "." | "") => {
            return Err(ApiError::invalid_request(format!(
                "request body is not valid: {inner}"
            )))
        }
        (None, p) => p.to_owned(),
    };
    // Drop serde_json's " at line L column C" suffix: the field name says where.
    let message = match text.rfind(" at line ") {
        Some(i) => &text[..i],
        None => &text,
    };
    Err(ApiError::invalid_field(field, message))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error::ErrorCode;

    #[test]
    fn job_errors_are_invalid_field_errors() {
        let mut s = JobSettings::new("builtin:cornell-box");
        s.spp = 0;
        let e = ApiError::from(s.validate().unwrap_err());
        assert_eq!(e.code, ErrorCode::InvalidField);
        assert_eq!(e.status(), 400);
        assert_eq!(e.message, "spp: must be between 1 and 1048576, got 0");
        assert_eq!(
            serde_json::to_value(&e).unwrap(),
            serde_json::json!({"error": {
                "code": "invalid_field",
                "message": "spp: must be between 1 and 1048576, got 0",
                "field": "spp"
            }})
        );
    }

    #[test]
    fn json_unknown_missing_and_mistyped_fields_name_the_field() {
        let e = JobSettings::from_json(br#"{"scene":"builtin:x","spx":5}"#).unwrap_err();
        assert_eq!(e.code, ErrorCode::InvalidField);
        assert_eq!(e.field.as_deref(), Some("spx"), "{e}");
        assert!(e.message.starts_with("spx: unknown field `spx`"), "{e}");
        // Also with serde_json directly (what an axum Json extractor does).
        assert!(serde_json::from_str::<JobSettings>(r#"{"scene":"builtin:x","spx":5}"#).is_err());

        let e = JobSettings::from_json(br#"{"scene":"builtin:x","frames":{"start":0,"stop":1}}"#)
            .unwrap_err();
        assert_eq!(e.field.as_deref(), Some("frames.stop"), "{e}");

        let e = JobSettings::from_json(br#"{"spp":5}"#).unwrap_err();
        assert_eq!(e.field.as_deref(), Some("scene"), "{e}");
        assert_eq!(e.message, "scene: missing field `scene`");

        let e = JobSettings::from_json(br#"{"scene":"builtin:x","spp":-1}"#).unwrap_err();
        assert_eq!(e.field.as_deref(), Some("spp"), "{e}");
        assert!(!e.message.contains("line"), "{e}");

        let e = JobSettings::from_json(br#"{"scene":"builtin:x","width":"wide"}"#).unwrap_err();
        assert_eq!(e.field.as_deref(), Some("width"), "{e}");

        let e =
            JobSettings::from_json(br#"{"scene":"builtin:x","frames":{"start":1}}"#).unwrap_err();
        assert_eq!(e.field.as_deref(), Some("frames.end"), "{e}");

        for bad in [
            &b"{"[..],
            b"",
            b"not json",
            br#"{"scene":"builtin:x"} trailing"#,
        ] {
            let e = JobSettings::from_json(bad).unwrap_err();
            assert_eq!(e.code, ErrorCode::InvalidRequest, "{e}");
            assert_eq!(e.field, None);
        }
        let e = JobSettings::from_json(b"[1, 2]").unwrap_err();
        assert_eq!(e.code, ErrorCode::InvalidRequest, "{e}");

        let ok = JobSettings::from_json(br#" {"scene":"builtin:x","spp":5} "#).unwrap();
        assert_eq!(ok.spp, 5);
    }
}
