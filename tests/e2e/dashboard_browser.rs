//! The dashboard in a real browser, end to end.
//!
//! Starts `tessera serve` (SQLite store in a temp dir, two local workers of one thread,
//! port-0 listeners, no demo job), opens the dashboard in headless Chromium driven over
//! the W3C WebDriver protocol (Debian's `chromium` and `chromium-driver`), submits
//! `builtin:cornell-box` through the form and waits until the job page shows it done.
//! Then it checks that the preview loaded (the right size and not one flat color), that
//! the convergence plot has points, that the tile heat map draws, that the jobs table
//! lists the job, that the workers table lists both local workers, and that the page
//! asked no host but the coordinator (resource timing entries, plus the
//! Content-Security-Policy the coordinator sends) and logged no error. Screenshots go to
//! `target/dashboard-artifacts/`.
//!
//! Without Chromium and chromedriver the test says so and passes, unless `CI` is set
//! (`.ci/run` installs them), where it fails.
//!
//! WebDriver is a few JSON requests over HTTP to a local chromedriver, spoken here
//! directly with `std::net` rather than through a client crate: the test needs eight
//! commands, and no TLS, async runtime or connection pool.

use crate::common;

use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use common::{free_port, tessera, OnDrop, Proc};
use serde_json::{json, Value};

const CHROMIUM: &str = "/usr/bin/chromium";
const CHROMEDRIVER: &str = "/usr/bin/chromedriver";
/// The W3C WebDriver key of an element reference.
const ELEMENT: &str = "element-6066-11e4-a52e-4f735466cecf";
/// Long enough for a slow CI machine; the waits return as soon as the page is ready.
const TIMEOUT: Duration = Duration::from_secs(180);

/// Polls `f` until it gives `Ok`, for at most [`TIMEOUT`] ([`common::wait_for`]).
fn wait_for<T>(what: &str, f: impl FnMut() -> Result<T, String>) -> T {
    common::wait_for(what, TIMEOUT, f)
}

// ---------------------------------------------------------------------------------------
// HTTP/1.1, just enough for chromedriver and the coordinator on loopback

struct Response {
    status: u16,
    headers: Vec<(String, String)>,
    body: Vec<u8>,
}

impl Response {
    fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(k, _)| k.eq_ignore_ascii_case(name))
            .map(|(_, v)| v.as_str())
    }
}

/// One request on a fresh connection (`Connection: close`). `addr` is `HOST:PORT`.
fn http(addr: &str, method: &str, path: &str, body: Option<&Value>) -> std::io::Result<Response> {
    let mut s = TcpStream::connect(addr)?;
    s.set_read_timeout(Some(Duration::from_secs(120)))?;
    let body = body.map(|b| b.to_string()).unwrap_or_default();
    let mut req = format!("{method} {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n");
    let sends_body = !body.is_empty() || !matches!(method, "GET" | "DELETE");
    if sends_body {
        req += &format!(
            "Content-Type: application/json; charset=utf-8\r\nContent-Length: {}\r\n",
            body.len()
        );
    }
    req += "\r\n";
    s.write_all(req.as_bytes())?;
    s.write_all(body.as_bytes())?;
    // Read the head, then exactly Content-Length bytes (chromedriver keeps the
    // connection open whatever `Connection: close` says), or chunks, or to the end.
    let mut raw = Vec::new();
    let mut buf = [0u8; 16384];
    let split = loop {
        if let Some(i) = raw.windows(4).position(|w| w == b"\r\n\r\n") {
            break i;
        }
        let n = s.read(&mut buf)?;
        if n == 0 {
            return Err(std::io::Error::other(
                "connection closed before the end of headers",
            ));
        }
        raw.extend_from_slice(&buf[..n]);
    };
    let head = String::from_utf8_lossy(&raw[..split]).to_string();
    let mut lines = head.split("\r\n");
    let status = lines
        .next()
        .and_then(|l| l.split(' ').nth(1))
        .and_then(|c| c.parse().ok())
        .ok_or_else(|| std::io::Error::other(format!("bad status line in {head:?}")))?;
    let headers: Vec<(String, String)> = lines
        .filter_map(|l| l.split_once(':'))
        .map(|(k, v)| (k.trim().to_string(), v.trim().to_string()))
        .collect();
    let find = |name: &str| {
        headers
            .iter()
            .find(|(k, _)| k.eq_ignore_ascii_case(name))
            .map(|(_, v)| v.clone())
    };
    let mut body = raw[split + 4..].to_vec();
    if method == "HEAD" || status == 204 || status == 304 {
        body.clear();
    } else if let Some(len) = find("content-length") {
        let len: usize = len
            .parse()
            .map_err(|_| std::io::Error::other(format!("bad Content-Length {len:?}")))?;
        while body.len() < len {
            let n = s.read(&mut buf)?;
            if n == 0 {
                return Err(std::io::Error::other("connection closed inside the body"));
            }
            body.extend_from_slice(&buf[..n]);
        }
        body.truncate(len);
    } else if find("transfer-encoding").is_some_and(|v| v.eq_ignore_ascii_case("chunked")) {
        loop {
            if let Some(b) = dechunk(&body)? {
                body = b;
                break;
            }
            let n = s.read(&mut buf)?;
            if n == 0 {
                return Err(std::io::Error::other("connection closed inside a chunk"));
            }
            body.extend_from_slice(&buf[..n]);
        }
    } else {
        s.read_to_end(&mut body)?;
    }
    Ok(Response {
        status,
        headers,
        body,
    })
}

/// The body of a complete chunked message, or `None` while more bytes are needed.
fn dechunk(mut b: &[u8]) -> std::io::Result<Option<Vec<u8>>> {
    let bad = || std::io::Error::other("bad chunked body");
    let mut out = Vec::new();
    loop {
        let Some(eol) = b.windows(2).position(|w| w == b"\r\n") else {
            return Ok(None);
        };
        let size = std::str::from_utf8(&b[..eol]).map_err(|_| bad())?;
        let size = usize::from_str_radix(size.split(';').next().unwrap_or("").trim(), 16)
            .map_err(|_| bad())?;
        b = &b[eol + 2..];
        if size == 0 {
            return Ok(Some(out));
        }
        let Some(chunk) = b.get(..size) else {
            return Ok(None);
        };
        out.extend_from_slice(chunk);
        let Some(rest) = b.get(size + 2..) else {
            return Ok(None);
        };
        b = rest;
    }
}

/// `http://HOST:PORT/...` -> (`HOST:PORT`, origin).
fn split_url(url: &str) -> (String, String) {
    let rest = url
        .strip_prefix("http://")
        .unwrap_or_else(|| panic!("not an http URL: {url}"));
    let host = rest.split('/').next().unwrap().to_string();
    (host.clone(), format!("http://{host}"))
}

// ---------------------------------------------------------------------------------------
// W3C WebDriver

struct Browser {
    driver: String,
    session: String,
}

impl Browser {
    fn start(driver: String, profile: &Path) -> Self {
        let caps = json!({"capabilities": {"alwaysMatch": {
            "browserName": "chrome",
            "goog:chromeOptions": {
                "binary": CHROMIUM,
                "args": [
                    "--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                    "--window-size=1360,1500", "--force-device-scale-factor=1",
                    "--no-first-run", "--disable-extensions", "--disable-background-networking",
                    "--disable-component-update", "--disable-sync", "--disable-default-apps",
                    "--force-prefers-reduced-motion",
                    format!("--user-data-dir={}", profile.display()),
                ],
            },
            "goog:loggingPrefs": {"browser": "ALL"},
        }}});
        let r = http(&driver, "POST", "/session", Some(&caps)).expect("chromedriver /session");
        let v: Value = serde_json::from_slice(&r.body).expect("session JSON");
        let session = v["value"]["sessionId"]
            .as_str()
            .unwrap_or_else(|| panic!("no session: {v}"))
            .to_string();
        Self { driver, session }
    }

    fn cmd(&self, method: &str, path: &str, body: Option<Value>) -> Result<Value, String> {
        let url = format!("/session/{}{path}", self.session);
        let body = body.or_else(|| (method == "POST").then(|| json!({})));
        let r = http(&self.driver, method, &url, body.as_ref()).map_err(|e| e.to_string())?;
        let v: Value = serde_json::from_slice(&r.body).map_err(|e| e.to_string())?;
        if r.status != 200 || v["value"].get("error").is_some() {
            return Err(format!("{method} {path}: {} {}", r.status, v["value"]));
        }
        Ok(v["value"].clone())
    }

    fn goto(&self, url: &str) {
        self.cmd("POST", "/url", Some(json!({"url": url}))).unwrap();
    }

    /// Runs `body` as a synchronous script (`arguments` available) and returns its value.
    fn exec(&self, body: &str, args: Value) -> Result<Value, String> {
        self.cmd(
            "POST",
            "/execute/sync",
            Some(json!({"script": body, "args": args})),
        )
    }

    fn find(&self, css: &str) -> Result<String, String> {
        let v = self.cmd(
            "POST",
            "/element",
            Some(json!({"using": "css selector", "value": css})),
        )?;
        v[ELEMENT]
            .as_str()
            .map(str::to_string)
            .ok_or_else(|| format!("no element id in {v}"))
    }

    fn click(&self, css: &str) {
        let el = wait_for(&format!("{css} to exist"), || self.find(css));
        self.cmd("POST", &format!("/element/{el}/click"), None)
            .unwrap_or_else(|e| panic!("click {css}: {e}"));
    }

    /// Clears the input and types `text`, as a user would.
    fn type_into(&self, css: &str, text: &str) {
        let el = wait_for(&format!("{css} to exist"), || self.find(css));
        self.cmd("POST", &format!("/element/{el}/clear"), None)
            .unwrap_or_else(|e| panic!("clear {css}: {e}"));
        self.cmd(
            "POST",
            &format!("/element/{el}/value"),
            Some(json!({"text": text})),
        )
        .unwrap_or_else(|e| panic!("type into {css}: {e}"));
    }

    fn screenshot(&self, path: &Path) {
        let v = self.cmd("GET", "/screenshot", None).expect("screenshot");
        let png = base64_decode(v.as_str().expect("screenshot is base64"));
        assert!(png.starts_with(b"\x89PNG"), "screenshot is not a PNG");
        std::fs::write(path, png).unwrap();
        println!("dashboard screenshot: {}", path.display());
    }

    /// The browser console since the last call (chromedriver's log endpoint).
    fn console(&self) -> Vec<Value> {
        match self.cmd("POST", "/se/log", Some(json!({"type": "browser"}))) {
            Ok(Value::Array(v)) => v,
            other => panic!("cannot read the browser console: {other:?}"),
        }
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let _ = self.cmd("DELETE", "", None);
    }
}

fn base64_decode(s: &str) -> Vec<u8> {
    let val = |c: u8| match c {
        b'A'..=b'Z' => c - b'A',
        b'a'..=b'z' => c - b'a' + 26,
        b'0'..=b'9' => c - b'0' + 52,
        b'+' => 62,
        b'/' => 63,
        _ => panic!("bad base64 byte {c}"),
    };
    let bytes: Vec<u8> = s
        .bytes()
        .filter(|c| !c.is_ascii_whitespace() && *c != b'=')
        .collect();
    let mut out = Vec::with_capacity(bytes.len() * 3 / 4);
    for chunk in bytes.chunks(4) {
        let mut n = 0u32;
        for (i, &c) in chunk.iter().enumerate() {
            n |= (val(c) as u32) << (18 - 6 * i);
        }
        out.extend_from_slice(&n.to_be_bytes()[1..chunk.len()]);
    }
    out
}

// ---------------------------------------------------------------------------------------
// The test

fn artifacts_dir() -> PathBuf {
    // CARGO_BIN_EXE_tessera is target/<profile>/tessera.
    let exe = Path::new(env!("CARGO_BIN_EXE_tessera"));
    let dir = exe
        .parent()
        .and_then(Path::parent)
        .unwrap_or(Path::new("."))
        .join("dashboard-artifacts");
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Whether the browser is installed; without it, fails under CI and skips elsewhere.
fn browser_available() -> bool {
    let missing: Vec<&str> = [CHROMIUM, CHROMEDRIVER]
        .into_iter()
        .filter(|p| !Path::new(p).exists())
        .collect();
    if missing.is_empty() {
        return true;
    }
    let msg = format!(
        "dashboard browser test needs {} (Debian: apt-get install chromium chromium-driver)",
        missing.join(" and ")
    );
    if std::env::var_os("CI").is_some() {
        panic!("{msg}; CI is set, so this is a failure (.ci/run installs them)");
    }
    eprintln!("SKIPPED: {msg}");
    false
}

/// The pixel statistics of the preview `<img>`, drawn to a canvas, or why not yet.
const PREVIEW_STATS: &str = r#"
const img = document.querySelector('#preview-img');
if (!img || img.hidden || !img.complete || img.naturalWidth === 0) return null;
const c = document.createElement('canvas');
c.width = img.naturalWidth; c.height = img.naturalHeight;
const ctx = c.getContext('2d');
ctx.drawImage(img, 0, 0);
const d = ctx.getImageData(0, 0, c.width, c.height).data;
let n = 0, sum = 0, sum2 = 0, min = 255, max = 0;
for (let i = 0; i < d.length; i += 4) {
  const l = 0.2126 * d[i] + 0.7152 * d[i + 1] + 0.0722 * d[i + 2];
  n++; sum += l; sum2 += l * l; min = Math.min(min, l); max = Math.max(max, l);
}
const mean = sum / n;
return {width: img.naturalWidth, height: img.naturalHeight, src: img.src, mean,
        variance: sum2 / n - mean * mean, min, max,
        caption: document.querySelector('#preview-caption').textContent};
"#;

/// `tessera serve` with a SQLite store in `tmp`, `workers` local workers of one thread,
/// port-0 listeners, no demo job (the test's job would queue behind it), and `extra`
/// arguments. Returns the guard and the dashboard URL it printed.
fn serve(tag: &str, tmp: &Path, workers: usize, extra: &[&str]) -> (Proc, String) {
    let log = artifacts_dir().join(format!("{tag}-serve.stderr.log"));
    let mut serve = Proc::spawn(
        &format!("{tag} serve"),
        tessera()
            .args(["serve", "--workers", &workers.to_string()])
            .args(["--threads-per-worker", "1", "--http", "127.0.0.1:0"])
            .args(["--grpc", "127.0.0.1:0", "--demo", "none", "--data"])
            .arg(tmp.join("data"))
            .args(extra),
        Some(&log),
    )
    .on_drop(OnDrop::Stop);
    let url = serve.wait_line("dashboard:");
    println!("dashboard at {url}");
    (serve, url)
}

/// A browser session and its chromedriver. Fields drop in order: the session is closed
/// before the driver stops.
struct Chrome {
    browser: Browser,
    _driver: Proc,
}

/// The browser tests run one at a time: two Chromiums at once are more than a 2-core CI
/// machine should carry.
static ONE_BROWSER: std::sync::Mutex<()> = std::sync::Mutex::new(());

fn chrome(tag: &str, tmp: &Path) -> Chrome {
    let artifacts = artifacts_dir();
    let driver_log = artifacts.join(format!("{tag}-chromedriver.log"));
    // A port the system gave out a moment ago: chromedriver's own `--port=0` picks a random
    // port without asking the system, and exits ("IPv4 port not available") when a test
    // beside this one holds it. Another test can still take this one before chromedriver
    // binds it, so a driver that exits before it starts is started again on a new port.
    let mut attempts = Vec::new();
    let (driver, port) = loop {
        let port = free_port();
        let mut driver = Proc::spawn(
            &format!("{tag} chromedriver"),
            Command::new(CHROMEDRIVER).args([
                format!("--port={port}"),
                format!("--log-path={}", driver_log.display()),
            ]),
            Some(&artifacts.join(format!("{tag}-chromedriver.stderr.log"))),
        )
        .on_drop(OnDrop::Stop)
        .diagnostics(&driver_log);
        match driver.try_wait_lines(&["was started successfully on port"]) {
            Ok(_) => break (driver, port),
            Err(e) if attempts.len() < 4 => attempts.push(e),
            Err(e) => panic!("chromedriver did not start in 5 attempts: {attempts:#?}\n{e}"),
        }
    };
    let browser = Browser::start(format!("127.0.0.1:{port}"), &tmp.join("chrome"));
    Chrome {
        browser,
        _driver: driver,
    }
}

#[test]
fn dashboard_in_headless_chromium() {
    if !browser_available() {
        return;
    }
    let _one = ONE_BROWSER.lock().unwrap_or_else(|e| e.into_inner());
    let artifacts = artifacts_dir();
    let tmp = tempfile::tempdir().unwrap();

    let (mut serve, url) = serve("job", tmp.path(), 2, &[]);
    let (addr, origin) = split_url(&url);

    // The coordinator sends the page with a policy that forbids other hosts and inline code.
    let page = http(&addr, "GET", "/", None).expect("GET /");
    assert_eq!(page.status, 200);
    assert!(page
        .header("content-type")
        .unwrap_or("")
        .starts_with("text/html"));
    let csp = page
        .header("content-security-policy")
        .expect("the dashboard is served with a Content-Security-Policy");
    for directive in [
        "default-src 'self'",
        "script-src 'self'",
        "style-src 'self'",
        "connect-src 'self'",
    ] {
        assert!(csp.contains(directive), "CSP {csp:?} lacks {directive:?}");
    }
    assert!(
        !csp.contains("unsafe-inline") && !csp.contains('*'),
        "{csp}"
    );

    let chrome = chrome("job", tmp.path());
    let browser = &chrome.browser;

    // Submit builtin:cornell-box through the form.
    browser.goto(&format!("{url}#/submit"));
    // Record every request of the page, however long it polls (the default buffer is 250).
    browser
        .exec(
            "performance.setResourceTimingBufferSize(1000000);",
            json!([]),
        )
        .unwrap();
    wait_for("the built-in scenes in the form", || {
        browser
            .exec(
                "return [...document.querySelectorAll('#f-scene option')].map(o => o.value);",
                json!([]),
            )
            .and_then(|v| {
                if v.as_array()
                    .is_some_and(|a| a.iter().any(|o| o == "builtin:cornell-box"))
                {
                    Ok(())
                } else {
                    Err(v.to_string())
                }
            })
    });
    browser.click("#f-scene option[value='builtin:cornell-box']");
    browser.type_into("#f-width", "64");
    browser.type_into("#f-height", "64");
    browser.type_into("#f-spp", "16");
    browser.type_into("#f-name", "browser test");
    // A dim uniform environment around the box: the form's lighting fields reach the
    // quote and the job.
    browser.type_into("#f-env-colour", "0.05,0.05,0.05");
    // The quote before submitting (a dry run): a table with the planned row and one row
    // per default target, each with a wall time; no job is created by it.
    browser.click("#f-quote");
    let rows = wait_for("the quote table", || {
        let v = browser.exec(
            "return [[...document.querySelectorAll('#quote tbody tr')].map(r => r.textContent), \
             document.querySelector('#submit-status')?.textContent ?? ''];",
            json!([]),
        )?;
        let status = v[1].as_str().unwrap_or("");
        assert!(
            !status.contains("No quote"),
            "the quote was refused: {status}"
        );
        match v[0].as_array() {
            Some(r) if r.len() == 5 => Ok(r.clone()),
            _ => Err(v.to_string()),
        }
    });
    println!("quote rows: {rows:?}");
    browser.screenshot(&artifacts_dir().join("submit-quote.png"));
    assert!(
        rows[0].as_str().unwrap().starts_with("as planned"),
        "{rows:?}"
    );
    for (row, target) in rows[1..].iter().zip(["10 %", "5 %", "2 %", "1 %"]) {
        let row = row.as_str().unwrap();
        assert!(row.starts_with(&format!("{target} error")), "{row}");
        assert!(row.contains(" s (") || row.contains(" min ("), "{row}");
    }
    browser.click("#f-submit");

    // The form navigates to the new job's page.
    let job_id: u64 = wait_for("the job page after submitting", || {
        let v = browser.exec(
            "return [location.hash, document.querySelector('#submit-status')?.textContent ?? ''];",
            json!([]),
        )?;
        let hash = v[0].as_str().unwrap_or("");
        if let Some(id) = hash.strip_prefix("#/jobs/") {
            return id.parse().map_err(|e| format!("{hash}: {e}"));
        }
        let status = v[1].as_str().unwrap_or("");
        assert!(
            !status.contains("not accepted"),
            "the form was refused: {status}"
        );
        Err(format!("still at {hash}, status {status:?}"))
    });
    println!("submitted job {job_id}");

    // Wait until the page shows it done.
    wait_for("the job to be shown as done", || {
        let state = browser.exec(
            "return document.querySelector('#job-state')?.textContent ?? '';",
            json!([]),
        )?;
        let state = state.as_str().unwrap_or("").to_string();
        assert!(
            !["failed", "canceled"].contains(&state.as_str()),
            "job {job_id} ended {state}: {}",
            browser
                .exec(
                    "return document.querySelector('main').innerText;",
                    json!([])
                )
                .unwrap_or_default()
        );
        if state == "done" {
            Ok(())
        } else {
            Err(state)
        }
    });

    // The final preview: loaded, 64 x 64, not one flat color.
    let stats = wait_for("the final preview image", || {
        let v = browser.exec(PREVIEW_STATS, json!([]))?;
        if v["caption"].as_str().unwrap_or("").contains("final") {
            Ok(v)
        } else {
            Err(v.to_string())
        }
    });
    println!("preview: {stats}");
    assert_eq!(
        (stats["width"].as_u64(), stats["height"].as_u64()),
        (Some(64), Some(64))
    );
    assert!(
        stats["src"].as_str().unwrap().starts_with("blob:"),
        "{stats}"
    );
    assert!(
        stats["variance"].as_f64().unwrap() > 1.0
            && stats["max"].as_f64().unwrap() - stats["min"].as_f64().unwrap() > 10.0,
        "the preview is (nearly) one flat color: {stats}"
    );

    // The convergence plot has points; the render plan is shown.
    let plot = wait_for("points in the convergence plot", || {
        let v = browser.exec(
            "return {points: document.querySelectorAll('#plot circle.pt').length, \
                     label: document.querySelector('#plot')?.getAttribute('aria-label'), \
                     integrator: document.querySelector('#plan-integrator')?.textContent};",
            json!([]),
        )?;
        if v["points"].as_u64().unwrap_or(0) > 0 && v["integrator"].is_string() {
            Ok(v)
        } else {
            Err(v.to_string())
        }
    });
    println!("plot: {plot}");
    let settings = browser
        .exec(
            "return document.querySelector('.settings')?.textContent ?? '';",
            json!([]),
        )
        .unwrap();
    assert!(
        settings.as_str().unwrap_or("").contains("0.05,0.05,0.05"),
        "the job's settings do not name the environment: {settings}"
    );

    // The heat map overlay draws from /tiles.
    browser.click("input[name^='overlay-'][value='error']");
    wait_for("the tile error heat map", || {
        let v = browser.exec(
            "const c = document.querySelector('#heatmap'); \
             return c && !c.hidden ? [c.width, c.height] : null;",
            json!([]),
        )?;
        if v == json!([64, 64]) {
            Ok(())
        } else {
            Err(v.to_string())
        }
    });
    let shot = artifacts.join("job.png");
    browser.screenshot(&shot);

    // The jobs table lists the job as done.
    browser.click("a[data-nav='jobs']");
    wait_for("the job in the jobs table", || {
        let v = browser.exec(
            "const r = document.querySelector(`#jobs-table tr[data-job='${arguments[0]}']`); \
             return r ? r.innerText : null;",
            json!([job_id]),
        )?;
        let text = v.as_str().unwrap_or("");
        if text.contains("done") && text.contains("browser test") {
            Ok(())
        } else {
            Err(v.to_string())
        }
    });
    browser.screenshot(&artifacts.join("jobs.png"));

    // The workers table lists the two local workers.
    browser.click("a[data-nav='workers']");
    let workers = wait_for("two workers in the workers table", || {
        let v = browser.exec(
            "return [...document.querySelectorAll('#workers-table tbody tr')].map(r => r.innerText);",
            json!([]),
        )?;
        if v.as_array().map_or(0, Vec::len) == 2 {
            Ok(v)
        } else {
            Err(v.to_string())
        }
    });
    println!("workers: {workers}");
    browser.screenshot(&artifacts.join("workers.png"));

    // No request went anywhere but the coordinator (blob: URLs are the page's own images).
    let requests = browser
        .exec(
            "return [location.href, ...performance.getEntriesByType('resource').map(e => e.name)];",
            json!([]),
        )
        .unwrap();
    let requests: Vec<&str> = requests
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_str().unwrap())
        .collect();
    let blob = format!("blob:{origin}/");
    let foreign: Vec<&&str> = requests
        .iter()
        .filter(|u| !(u.starts_with(&format!("{origin}/")) || u.starts_with(&blob)))
        .collect();
    assert!(foreign.is_empty(), "requests to other hosts: {foreign:?}");
    for needed in [
        "/assets/app.js",
        "/assets/style.css",
        "/api/v1/jobs",
        "/api/v1/workers",
    ] {
        assert!(
            requests.iter().any(|u| u.contains(needed)),
            "no request for {needed} in {requests:?}"
        );
    }
    println!(
        "{} requests, all to {origin} (first: {:?})",
        requests.len(),
        &requests[..requests.len().min(6)]
    );

    // Nothing went wrong in the page: no error banner, no console errors (a CSP violation,
    // a failed request or a script error is logged as SEVERE).
    let banner = browser
        .exec(
            "return document.querySelector('#banner').hidden;",
            json!([]),
        )
        .unwrap();
    assert_eq!(banner, json!(true), "the error banner is showing");
    let severe: Vec<Value> = browser
        .console()
        .into_iter()
        .filter(|e| e["level"] == "SEVERE")
        .collect();
    assert!(severe.is_empty(), "console errors: {severe:#?}");

    drop(chrome);
    let status = serve.stop();
    println!("tessera serve stopped: {status:?}");
    println!("artifacts: {}", artifacts.display());
}

/// With `--api-token`, the page asks for the token on the first 401, keeps it in the tab
/// and sends it on every request (the workers table fills only with it).
#[test]
fn dashboard_asks_for_the_api_token() {
    if !browser_available() {
        return;
    }
    let _one = ONE_BROWSER.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let token = "dashboard-test-token";
    let (_serve, url) = serve("token", tmp.path(), 1, &["--api-token", token]);
    let (addr, _) = split_url(&url);
    let r = http(&addr, "GET", "/api/v1/workers", None).unwrap();
    assert_eq!(r.status, 401, "the API is open without the token");

    let chrome = chrome("token", tmp.path());
    let browser = &chrome.browser;
    browser.goto(&format!("{url}#/workers"));
    wait_for("the token dialog", || {
        let v = browser.exec(
            "return [document.querySelector('#token-dialog').open, \
                     document.querySelector('#token-reason').textContent];",
            json!([]),
        )?;
        if v[0] == json!(true) {
            Ok(())
        } else {
            Err(v.to_string())
        }
    });
    browser.type_into("#token-input", token);
    browser.click("#token-dialog button[value='ok']");
    let rows = wait_for("the workers table with the token", || {
        let v = browser.exec(
            "return document.querySelectorAll('#workers-table tbody tr').length;",
            json!([]),
        )?;
        match v.as_u64() {
            Some(n) if n >= 1 => Ok(n),
            _ => Err(v.to_string()),
        }
    });
    assert_eq!(rows, 1);
    let kept = browser
        .exec(
            "return sessionStorage.getItem('tessera.api-token');",
            json!([]),
        )
        .unwrap();
    assert_eq!(kept, json!(token));
    let banner = browser
        .exec(
            "return document.querySelector('#banner').hidden;",
            json!([]),
        )
        .unwrap();
    assert_eq!(banner, json!(true), "the error banner is showing");
}
