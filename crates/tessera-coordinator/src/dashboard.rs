//! The browser dashboard's static files, embedded in the binary.
//!
//! Plain HTML, CSS and JavaScript modules from `assets/`, with no build step: the page
//! talks only to the public HTTP API v1 and polls it about once a second. The router
//! serves [`asset`] for `GET /` and `GET /assets/NAME` with a strict
//! `Content-Security-Policy` (no inline script or style, no other host), so the files
//! keep to that: scripts are modules loaded by URL, styles live in `style.css`, and
//! images are fetched with the API token and shown from `blob:` URLs.

/// One embedded file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Asset {
    /// The `Content-Type` to send, e.g. `"text/javascript; charset=utf-8"`.
    pub content_type: &'static str,
    /// The file's bytes.
    pub bytes: &'static [u8],
}

const HTML: &str = "text/html; charset=utf-8";
const JS: &str = "text/javascript; charset=utf-8";
const CSS: &str = "text/css; charset=utf-8";
const SVG: &str = "image/svg+xml";

/// The files under `/assets/`, by name.
const FILES: &[(&str, &str, &[u8])] = &[
    ("index.html", HTML, include_bytes!("../assets/index.html")),
    ("app.js", JS, include_bytes!("../assets/app.js")),
    ("api.js", JS, include_bytes!("../assets/api.js")),
    ("util.js", JS, include_bytes!("../assets/util.js")),
    ("jobs.js", JS, include_bytes!("../assets/jobs.js")),
    ("job.js", JS, include_bytes!("../assets/job.js")),
    ("plot.js", JS, include_bytes!("../assets/plot.js")),
    ("heatmap.js", JS, include_bytes!("../assets/heatmap.js")),
    ("submit.js", JS, include_bytes!("../assets/submit.js")),
    ("workers.js", JS, include_bytes!("../assets/workers.js")),
    ("style.css", CSS, include_bytes!("../assets/style.css")),
    ("favicon.svg", SVG, include_bytes!("../assets/favicon.svg")),
];

/// The file for a request path: `"/"` and `"/index.html"` give the page, `"/assets/NAME"`
/// one of its files; anything else (including any other nesting) is `None`.
pub fn asset(path: &str) -> Option<Asset> {
    let name = match path {
        "/" | "/index.html" => "index.html",
        _ => path.strip_prefix("/assets/")?,
    };
    FILES
        .iter()
        .find(|(n, _, _)| *n == name)
        .map(|&(_, content_type, bytes)| Asset {
            content_type,
            bytes,
        })
}

/// The names of the embedded files (for listing and tests).
pub fn names() -> impl Iterator<Item = &'static str> {
    FILES.iter().map(|(n, _, _)| *n)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn text(name: &str) -> &'static str {
        std::str::from_utf8(asset(&format!("/assets/{name}")).unwrap().bytes).unwrap()
    }

    #[test]
    fn paths() {
        let index = asset("/").unwrap();
        assert_eq!(index, asset("/index.html").unwrap());
        assert_eq!(index, asset("/assets/index.html").unwrap());
        assert!(index.content_type.starts_with("text/html"));
        assert_eq!(asset("/assets/app.js").unwrap().content_type, JS);
        assert_eq!(asset("/assets/style.css").unwrap().content_type, CSS);
        for bad in [
            "",
            "/assets/",
            "/assets",
            "/app.js",
            "/assets/nope.js",
            "/assets/../Cargo.toml",
            "/assets//app.js",
            "/assets/sub/app.js",
            "/api/v1/jobs",
            "/index.html/",
        ] {
            assert!(asset(bad).is_none(), "{bad:?}");
        }
    }

    /// Every `/assets/...` URL and every module import names an embedded file, and every
    /// embedded file is used: the page cannot 404 on itself.
    #[test]
    fn references_resolve() {
        let mut used = vec!["index.html"];
        for name in names() {
            let t = text(name);
            for part in t.split("/assets/").skip(1) {
                let r: String = part
                    .chars()
                    .take_while(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '-' | '_'))
                    .collect();
                assert!(asset(&format!("/assets/{r}")).is_some(), "{name} names {r}");
                used.push(names().find(|n| *n == r).unwrap());
            }
            for part in t.split("from \"./").skip(1) {
                let r = &part[..part.find('"').unwrap()];
                assert!(
                    asset(&format!("/assets/{r}")).is_some(),
                    "{name} imports {r}"
                );
                used.push(names().find(|n| *n == r).unwrap());
            }
        }
        for name in names() {
            assert!(used.contains(&name), "{name} is embedded but never used");
        }
    }

    /// What the Content-Security-Policy forbids is not in the files: inline scripts,
    /// inline styles, event-handler attributes, and any other host.
    #[test]
    fn csp_clean() {
        let html = text("index.html");
        for script in html.split("<script").skip(1) {
            let tag = &script[..script.find('>').unwrap()];
            assert!(tag.contains("src=\"/assets/"), "inline script: {tag}");
            assert!(script[script.find('>').unwrap() + 1..].starts_with("</script>"));
        }
        assert!(!html.contains("<style"), "inline <style> block");
        assert!(!html.contains("style="), "inline style attribute");
        for (i, _) in html.match_indices(" on") {
            let attr: String = html[i + 1..]
                .chars()
                .take_while(|c| c.is_ascii_lowercase())
                .collect();
            assert!(
                !html[i + 1 + attr.len()..].starts_with('='),
                "inline event handler {attr}"
            );
        }
        for name in names() {
            let t = text(name);
            for scheme in ["http://", "https://", "//cdn", "@import", "url("] {
                for (i, _) in t.match_indices(scheme) {
                    // The SVG namespace is a name, not a request.
                    let rest = &t[i..];
                    assert!(
                        rest.starts_with("http://www.w3.org/2000/svg"),
                        "{name} refers to {:?}",
                        &rest[..rest.len().min(60)]
                    );
                }
            }
            assert!(!t.contains("innerHTML"), "{name} uses innerHTML");
            assert!(!t.contains("eval("), "{name} uses eval");
        }
    }
}
