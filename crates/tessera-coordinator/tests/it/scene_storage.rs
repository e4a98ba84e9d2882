//! Scene storage cannot fill the disk and keep the farm down (docs/store.md, "Scene
//! storage" and "When the disk is full"): uploads beyond their size (413) or beyond the
//! total or one client's quota (507) are refused naming the limit and the numbers;
//! `DELETE /api/v1/scenes/{hash}` is refused while a job needs the scene, then works,
//! then answers 404; retention deletes unused scenes only; a coordinator started on a
//! full disk (a real tmpfs, as root) serves reads, answers writes 507 and takes writes
//! again by itself once space is freed. Every wait is bounded by
//! [`tessera_testkit::HANG`].

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

use tessera_api::{JobSettings, JobState};
use tessera_coordinator::service::{Coordinator, CoordinatorConfig};
use tessera_coordinator::{serve_coordinator, Listeners};
use tessera_testkit::bounded;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::sync::oneshot;

/// A self-contained glTF (the Cornell box) padded to about `pad` more bytes, distinct for
/// each `i` (a distinct hash).
fn scene(i: usize, pad: usize) -> Vec<u8> {
    let text = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../scenes/cornell-box.gltf"
    ))
    .unwrap();
    let generator = format!("padding {i} {}", "x".repeat(pad));
    let out = text.replacen("scenes/make_cornell_gltf.py", &generator, 1);
    assert_ne!(out, text, "the scene's generator string moved");
    out.into_bytes()
}

fn small_job(scene: &str) -> JobSettings {
    let mut job = JobSettings::new(scene);
    (job.width, job.height, job.spp) = (Some(16), Some(16), 4);
    job
}

async fn start(cfg: CoordinatorConfig) -> (SocketAddr, Coordinator, oneshot::Sender<()>) {
    let core = Coordinator::open(cfg).await.unwrap();
    let (addr, tx) = serve(core.clone()).await;
    (addr, core, tx)
}

async fn serve(core: Coordinator) -> (SocketAddr, oneshot::Sender<()>) {
    let http = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let grpc = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = http.local_addr().unwrap();
    let (tx, rx) = oneshot::channel::<()>();
    tokio::spawn(serve_coordinator(core, Listeners { http, grpc }, async {
        let _ = rx.await;
    }));
    (addr, tx)
}

/// One answer: status and body.
struct Answer {
    status: u16,
    body: String,
}

impl Answer {
    fn json(&self) -> serde_json::Value {
        serde_json::from_str(&self.body).unwrap_or_else(|e| panic!("{e}: {}", self.body))
    }

    /// The error's code and message.
    fn error(&self) -> (String, String) {
        let j = self.json();
        (
            j["error"]["code"].as_str().unwrap_or_default().to_string(),
            j["error"]["message"]
                .as_str()
                .unwrap_or_default()
                .to_string(),
        )
    }
}

/// One HTTP/1.1 request with a byte body.
async fn request(
    addr: SocketAddr,
    method: &str,
    path: &str,
    token: Option<&str>,
    body: &[u8],
) -> Answer {
    bounded("an HTTP request", async {
        let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
        let mut head = format!(
            "{method} {path} HTTP/1.1\r\nHost: t\r\nConnection: close\r\nContent-Length: {}\r\n",
            body.len()
        );
        if let Some(t) = token {
            head.push_str(&format!("Authorization: Bearer {t}\r\n"));
        }
        head.push_str("\r\n");
        s.write_all(head.as_bytes()).await.unwrap();
        // A refused upload may be answered before its body is read: not an error here.
        let _ = s.write_all(body).await;
        let mut out = Vec::new();
        let _ = s.read_to_end(&mut out).await;
        let text = String::from_utf8_lossy(&out).into_owned();
        let (head, body) = text.split_once("\r\n\r\n").unwrap_or((&text, ""));
        let status = head
            .split(' ')
            .nth(1)
            .and_then(|s| s.parse().ok())
            .unwrap_or_else(|| panic!("no status in {head:?}"));
        Answer {
            status,
            body: body.to_string(),
        }
    })
    .await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn uploads_beyond_their_size_or_a_quota_are_refused_naming_the_limit() {
    let dir = tempfile::tempdir().unwrap();
    let size = scene(0, 4096).len() as u64;
    let mut cfg = CoordinatorConfig::new(dir.path());
    cfg.api_token = Some("t0ken".into());
    cfg.max_scene_bytes = (size + 100) as usize;
    cfg.scene_quota_bytes = 10 * size;
    cfg.scene_quota_per_token = 2 * size + size / 2;
    let (addr, core, stop) = start(cfg).await;
    let tok = Some("t0ken");
    // One upload over the size: 413, naming the limit and the size.
    let a = request(addr, "POST", "/api/v1/scenes", tok, &scene(9, 8192)).await;
    assert_eq!(a.status, 413, "{}", a.body);
    let (code, msg) = a.error();
    assert_eq!(code, "too_large");
    assert!(
        msg.contains("--max-scene-size") && msg.contains(&(size + 100).to_string()),
        "{msg}"
    );
    // The token's quota: two fit, the third does not.
    for i in 0..2 {
        let a = request(addr, "POST", "/api/v1/scenes", tok, &scene(i, 4096)).await;
        assert_eq!(a.status, 201, "{}", a.body);
    }
    let a = request(addr, "POST", "/api/v1/scenes", tok, &scene(2, 4096)).await;
    assert_eq!(a.status, 507, "{}", a.body);
    let (code, msg) = a.error();
    assert_eq!(code, "insufficient_storage");
    assert!(
        msg.contains("--scene-quota-per-token")
            && msg.contains(&(2 * size + size / 2).to_string())
            && msg.contains(&(2 * size).to_string())
            && msg.contains(&size.to_string()),
        "{msg}"
    );
    // A scene stored already takes no room: uploading it again is no refusal.
    let a = request(addr, "POST", "/api/v1/scenes", tok, &scene(1, 4096)).await;
    assert_eq!(a.status, 201, "{}", a.body);
    // Quotas are per client: another one has its own.
    core.upload_scene_as(scene(3, 4096), "other").await.unwrap();
    core.upload_scene_as(scene(4, 4096), "other").await.unwrap();
    let e = core
        .upload_scene_as(scene(5, 4096), "other")
        .await
        .unwrap_err();
    assert_eq!(tessera_api::ApiError::from(e).status(), 507);
    let _ = stop.send(());

    // The total quota, over all clients.
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = CoordinatorConfig::new(dir.path());
    cfg.scene_quota_bytes = 3 * size;
    let (addr, core, stop) = start(cfg).await;
    core.upload_scene_as(scene(0, 4096), "a").await.unwrap();
    core.upload_scene_as(scene(1, 4096), "b").await.unwrap();
    core.upload_scene_as(scene(2, 4096), "c").await.unwrap();
    let a = request(addr, "POST", "/api/v1/scenes", None, &scene(3, 4096)).await;
    assert_eq!(a.status, 507, "{}", a.body);
    let (code, msg) = a.error();
    assert_eq!(code, "insufficient_storage");
    assert!(
        msg.contains("total quota (--scene-quota)")
            && msg.contains(&(3 * size).to_string())
            && msg.contains(&format!("hold {} bytes", 3 * size)),
        "{msg}"
    );
    let _ = stop.send(());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_scene_is_deleted_only_once_no_unfinished_job_needs_it() {
    let dir = tempfile::tempdir().unwrap();
    let (addr, core, stop) = start(CoordinatorConfig::new(dir.path())).await;
    let up = request(addr, "POST", "/api/v1/scenes", None, &scene(0, 0)).await;
    assert_eq!(up.status, 201, "{}", up.body);
    let hash = up.json()["hash"].as_str().unwrap().to_string();
    let (job, _) = core.submit(small_job(&hash), None).await.unwrap();
    let path = format!("/api/v1/scenes/{hash}");
    // A queued job needs it: 409 naming the job.
    let a = request(addr, "DELETE", &path, None, b"").await;
    assert_eq!(a.status, 409, "{}", a.body);
    let (code, msg) = a.error();
    assert_eq!(code, "conflict");
    assert!(msg.contains(&format!("jobs {}", job.id)), "{msg}");
    assert!(core.store().scene_exists(&hash).await.unwrap());
    // Canceled, it needs it no more.
    let c = request(
        addr,
        "DELETE",
        &format!("/api/v1/jobs/{}", job.id),
        None,
        b"",
    )
    .await;
    assert!(c.status < 300, "{}", c.body);
    assert_eq!(core.status(job.id).await.unwrap().state, JobState::Canceled);
    let a = request(addr, "DELETE", &path, None, b"").await;
    assert_eq!(a.status, 204, "{}", a.body);
    // Gone everywhere: the store, the workers' cache, the quota's count.
    assert!(!core.store().scene_exists(&hash).await.unwrap());
    assert!(core.scene_bytes(&hash).is_err());
    assert_eq!(core.store().scene_bytes(None).await.unwrap(), 0);
    let a = request(addr, "DELETE", &path, None, b"").await;
    assert_eq!(a.status, 404, "{}", a.body);
    assert_eq!(a.error().0, "not_found");
    // Not a hash: 404 too, the store untouched.
    let a = request(addr, "DELETE", "/api/v1/scenes/..%2Fetc", None, b"").await;
    assert_eq!(a.status, 404, "{}", a.body);
    // A job of a deleted scene is refused, naming the scene.
    let e = core.submit(small_job(&hash), None).await.unwrap_err();
    assert!(e.to_string().contains("no uploaded scene"), "{e}");
    let _ = stop.send(());
}

/// A small equirectangular Radiance image, distinct for each `i`.
fn environment_image(i: u32) -> Vec<u8> {
    tessera_testkit::gltf_gen::radiance_hdr(8, 4, |x, y| {
        [1.0 + (x + i) as f32, 0.5 + y as f32, 0.75]
    })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn environment_images_are_checked_at_upload_and_kept_while_a_job_needs_them() {
    let dir = tempfile::tempdir().unwrap();
    let (addr, core, stop) = start(CoordinatorConfig::new(dir.path())).await;
    // An image is stored like a scene, with no triangles.
    let up = request(addr, "POST", "/api/v1/scenes", None, &environment_image(0)).await;
    assert_eq!(up.status, 201, "{}", up.body);
    assert_eq!(up.json()["triangles"], 0);
    let hash = up.json()["hash"].as_str().unwrap().to_string();
    // A header promising more texels than a texture may have, a truncated image and an
    // OpenEXR magic number with nothing after it: refused at upload (400 invalid_scene),
    // saying what is wrong.
    let huge = b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 10000 +X 10000\n\0\0\0\0".to_vec();
    let a = request(addr, "POST", "/api/v1/scenes", None, &huge).await;
    assert_eq!(a.status, 400, "{}", a.body);
    let (code, msg) = a.error();
    assert_eq!(code, "invalid_scene");
    assert!(
        msg.contains("100000000 texels") && msg.contains("limit"),
        "{msg}"
    );
    let mut broken = environment_image(1);
    broken.truncate(broken.len() - 40);
    let a = request(addr, "POST", "/api/v1/scenes", None, &broken).await;
    assert_eq!(a.status, 400, "{}", a.body);
    assert!(a.error().1.contains("Radiance"), "{}", a.body);
    let exr_magic = [0x76, 0x2f, 0x31, 0x01, 1, 2, 3, 4];
    let a = request(addr, "POST", "/api/v1/scenes", None, &exr_magic).await;
    assert_eq!(a.status, 400, "{}", a.body);
    assert!(a.error().1.contains("OpenEXR"), "{}", a.body);
    assert_eq!(
        core.store().scene_bytes(None).await.unwrap(),
        environment_image(0).len() as u64
    );
    // A job naming an image nobody uploaded is refused at submission, naming the field.
    let mut job = small_job("builtin:cornell-box");
    let unknown = "ab".repeat(32);
    job.environment = Some(tessera_api::EnvironmentSettings::new(unknown.clone()));
    let e = tessera_api::ApiError::from(core.submit(job.clone(), None).await.unwrap_err());
    assert_eq!(e.status(), 400, "{e:?}");
    assert!(
        e.message.contains("environment.source") && e.message.contains(&unknown),
        "{e:?}"
    );
    // Named in capitals, the image is the same upload: the job is queued, and deleting
    // the image is refused while the job needs it.
    job.environment = Some(tessera_api::EnvironmentSettings::new(hash.to_uppercase()));
    let (queued, _) = core.submit(job, None).await.unwrap();
    assert_eq!(
        queued.settings.environment.as_ref().unwrap().source,
        hash,
        "the stored settings name the image as it is stored"
    );
    let path = format!("/api/v1/scenes/{hash}");
    let a = request(addr, "DELETE", &path, None, b"").await;
    assert_eq!(a.status, 409, "{}", a.body);
    assert!(
        a.error().1.contains(&format!("jobs {}", queued.id)),
        "{}",
        a.body
    );
    // Retention keeps it too.
    let later = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_millis() as u64
        + 1_000;
    assert_eq!(core.retain_scenes(later).await.unwrap(), 0);
    core.cancel(queued.id).await.unwrap();
    let a = request(addr, "DELETE", &path, None, b"").await;
    assert_eq!(a.status, 204, "{}", a.body);
    let _ = stop.send(());
}

#[tokio::test]
async fn retention_deletes_unused_scenes_and_keeps_those_jobs_need() {
    let dir = tempfile::tempdir().unwrap();
    let core = Coordinator::open(CoordinatorConfig::new(dir.path()))
        .await
        .unwrap();
    let unused = core.upload_scene(scene(0, 0)).await.unwrap().hash;
    let needed = core.upload_scene(scene(1, 0)).await.unwrap().hash;
    core.submit(small_job(&needed), None).await.unwrap();
    // A cutoff before the uploads: nothing is old enough.
    assert_eq!(core.retain_scenes(1).await.unwrap(), 0);
    let later = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_millis() as u64
        + 1_000;
    assert_eq!(core.retain_scenes(later).await.unwrap(), 1);
    let store = core.store();
    assert!(!store.scene_exists(&unused).await.unwrap());
    assert!(core.scene_bytes(&unused).is_err());
    assert!(store.scene_exists(&needed).await.unwrap());
    assert!(core.scene_bytes(&needed).is_ok());
}

/// A tmpfs of `mb` MiB mounted on a new directory, unmounted when dropped.
struct Tmpfs(PathBuf);

impl Tmpfs {
    /// `None` (the test passes, saying why) when it cannot be mounted and `CI` is not set.
    fn mount(mb: u32) -> Option<Self> {
        let dir =
            std::env::temp_dir().join(format!("tessera-full-disk-{}-{}", std::process::id(), mb));
        std::fs::create_dir_all(&dir).unwrap();
        let out = std::process::Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={mb}m"), "tmpfs"])
            .arg(&dir)
            .output();
        match out {
            Ok(o) if o.status.success() => Some(Self(dir)),
            other => {
                let why = match other {
                    Ok(o) => String::from_utf8_lossy(&o.stderr).into_owned(),
                    Err(e) => e.to_string(),
                };
                assert!(
                    std::env::var_os("CI").is_none(),
                    "CI is set but a tmpfs cannot be mounted (run as root): {why}"
                );
                eprintln!("skipped: a tmpfs cannot be mounted here (needs root): {why}");
                None
            }
        }
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = std::process::Command::new("umount")
            .arg("-l")
            .arg(&self.0)
            .status();
        let _ = std::fs::remove_dir(&self.0);
    }
}

/// Fills the filesystem of `dir` with the file `dir/fill` until a write fails for want
/// of space.
fn fill(dir: &Path) {
    use std::io::Write;
    let mut f = std::fs::File::create(dir.join("fill")).unwrap();
    let chunk = vec![0u8; 64 << 10];
    loop {
        if let Err(e) = f.write_all(&chunk).and_then(|_| f.sync_all()) {
            assert!(tessera_coordinator::space::is_no_space(&e), "{e}");
            break;
        }
    }
    // The last bytes, down to a block.
    let mut small = vec![0u8; 4096];
    while f.write_all(&small).is_ok() {}
    small.truncate(512);
    while f.write_all(&small).is_ok() {}
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_coordinator_starts_on_a_full_disk_serves_reads_and_resumes_writes_when_space_returns() {
    let Some(fs) = Tmpfs::mount(16) else {
        return;
    };
    let data = fs.0.join("data");
    let cfg = CoordinatorConfig::new(&data);
    // A farm with a job and a scene, stopped cleanly.
    let core = Coordinator::open(cfg.clone()).await.unwrap();
    let hash = core.upload_scene(scene(0, 0)).await.unwrap().hash;
    let (job, _) = core
        .submit(small_job("builtin:cornell-box"), None)
        .await
        .unwrap();
    core.store().end_run().await.unwrap();
    core.store().close().await;
    drop(core);
    fill(&fs.0);
    // Before: the open refused ("not writable", a disk I/O error on the -shm file).
    let core = Coordinator::open(cfg.clone()).await.unwrap();
    assert!(core.read_only() && core.disk_full());
    let (addr, stop) = serve(core).await;
    // Reads: the job's status, the job list, the dashboard.
    let a = request(addr, "GET", &format!("/api/v1/jobs/{}", job.id), None, b"").await;
    assert_eq!(a.status, 200, "{}", a.body);
    assert_eq!(a.json()["id"].as_u64(), Some(job.id));
    assert_eq!(
        request(addr, "GET", "/api/v1/jobs", None, b"").await.status,
        200
    );
    assert_eq!(request(addr, "GET", "/", None, b"").await.status, 200);
    // Unhealthy, and writes refused with 507 naming the full disk.
    assert_eq!(
        request(addr, "GET", "/healthz", None, b"").await.status,
        503
    );
    let body = serde_json::to_vec(&small_job("builtin:cornell-box")).unwrap();
    let a = request(addr, "POST", "/api/v1/jobs", None, &body).await;
    assert_eq!(a.status, 507, "{}", a.body);
    let (code, msg) = a.error();
    assert_eq!(code, "insufficient_storage");
    assert!(
        msg.contains("disk of the store is full") && msg.contains("space is freed"),
        "{msg}"
    );
    let a = request(addr, "POST", "/api/v1/scenes", None, &scene(1, 0)).await;
    assert_eq!(a.status, 507, "{}", a.body);
    let a = request(addr, "DELETE", &format!("/api/v1/scenes/{hash}"), None, b"").await;
    assert_eq!(a.status, 507, "{}", a.body);
    // Space returns: writes resume without a restart.
    std::fs::remove_file(fs.0.join("fill")).unwrap();
    let accepted = bounded("writes to resume once space is freed", async {
        loop {
            let a = request(addr, "POST", "/api/v1/jobs", None, &body).await;
            if a.status == 201 || a.status == 200 {
                return a.json()["id"].as_u64().unwrap();
            }
            assert_eq!(a.status, 507, "{}", a.body);
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
    })
    .await;
    assert!(accepted > job.id);
    assert_eq!(
        request(addr, "GET", "/healthz", None, b"").await.status,
        200
    );
    // The job from before the full disk was resumed; the scene is still there.
    let a = request(addr, "GET", &format!("/api/v1/jobs/{}", job.id), None, b"").await;
    assert_eq!(a.status, 200, "{}", a.body);
    assert_eq!(a.json()["state"].as_str(), Some("queued"));
    let a = request(addr, "DELETE", &format!("/api/v1/scenes/{hash}"), None, b"").await;
    assert_eq!(a.status, 204, "{}", a.body);
    let _ = stop.send(());
    tokio::time::sleep(Duration::from_millis(300)).await;
    drop(fs);
}
