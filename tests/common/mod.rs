//! Support shared by the tests: a real server on 127.0.0.1:0 (in process or
//! as the binary), tiny generated scenes and their archives, and readers for
//! what the service answers; the tiny model configs ([`tiny`]), PSNR
//! ([`psnr`]) and the MP4 reader ([`mp4`]) in their own modules; a real
//! PostgreSQL per test in [`pg`], a real S3 server per test in [`s3`].
#![allow(dead_code)] // each test binary uses its own part of this module

pub mod cdp;
pub mod mp4;
pub mod pg;
pub mod poses;
pub mod procs;
pub mod psnr;
pub mod s3;
pub mod tiny;

use std::io::Write;
use std::path::Path;
use std::time::{Duration, Instant};

use radiance::api::{Server, ServiceConfig};
use radiance::engine::dataset::synthetic::BallScene;
use reqwest::{Client, StatusCode};
use serde_json::{Value, json};

/// How many times its stall limit `Svc::wait_job` waits in all for a job
/// that keeps moving (a machine several times slower, or busy).
pub const MOVING_JOB_WAITS: f64 = 5.0;

pub fn scene_dir(dir: &Path) {
    BallScene { size: 16, views: 8, ..Default::default() }.write_blender(dir).unwrap();
}

/// Every file under `dir` as (relative name, bytes), sorted.
pub fn files(dir: &Path) -> Vec<(String, Vec<u8>)> {
    fn walk(root: &Path, d: &Path, out: &mut Vec<(String, Vec<u8>)>) {
        for e in std::fs::read_dir(d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                walk(root, &p, out);
            } else {
                let rel = p.strip_prefix(root).unwrap().to_string_lossy().into_owned();
                out.push((rel, std::fs::read(&p).unwrap()));
            }
        }
    }
    let mut v = Vec::new();
    walk(dir, dir, &mut v);
    v.sort();
    v
}

pub fn zip_of(entries: &[(String, Vec<u8>)]) -> Vec<u8> {
    let mut w = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let opts = zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Deflated);
    for (name, data) in entries {
        w.start_file(name.as_str(), opts).unwrap();
        w.write_all(data).unwrap();
    }
    w.finish().unwrap().into_inner()
}

/// A tar.gz whose entry names are written raw (so `..` can be tested).
pub fn tar_gz_of(entries: &[(String, Vec<u8>)]) -> Vec<u8> {
    let gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
    let mut b = tar::Builder::new(gz);
    for (name, data) in entries {
        let mut h = tar::Header::new_gnu();
        h.as_gnu_mut().unwrap().name[..name.len()].copy_from_slice(name.as_bytes());
        h.set_size(data.len() as u64);
        h.set_mode(0o644);
        h.set_entry_type(tar::EntryType::Regular);
        h.set_cksum();
        b.append(&h, data.as_slice()).unwrap();
    }
    b.into_inner().unwrap().finish().unwrap()
}

pub fn ball_files() -> Vec<(String, Vec<u8>)> {
    let d = tempfile::tempdir().unwrap();
    scene_dir(d.path());
    files(d.path())
}

pub fn ball() -> BallScene {
    BallScene { size: 16, views: 8, ..Default::default() }
}

pub fn ngp_files() -> Vec<(String, Vec<u8>)> {
    let d = tempfile::tempdir().unwrap();
    ball().write_ngp(d.path()).unwrap();
    files(d.path())
}

pub fn llff_files() -> Vec<(String, Vec<u8>)> {
    let d = tempfile::tempdir().unwrap();
    ball().write_llff(d.path()).unwrap();
    files(d.path())
}

/// The ball scene as an LLFF dataset with its photos in `images_8/` and
/// the ball's silhouettes (its alpha, 0 or 255) as masks in `masks_8/`,
/// PNGs with the photos' stems.
pub fn llff_masked_files() -> Vec<(String, Vec<u8>)> {
    let d = tempfile::tempdir().unwrap();
    ball().write_llff(d.path()).unwrap();
    std::fs::rename(d.path().join("images"), d.path().join("images_8")).unwrap();
    std::fs::create_dir_all(d.path().join("masks_8")).unwrap();
    for (k, f) in ball().dataset().frames.iter().enumerate() {
        let alpha: Vec<u8> = f.image.rgba.chunks(4).map(|p| p[3]).collect();
        let mask = image::GrayImage::from_raw(f.image.width, f.image.height, alpha).unwrap();
        mask.save(d.path().join(format!("masks_8/img{k:03}.png"))).unwrap();
    }
    files(d.path())
}

/// The ball scene as a COLMAP dataset, its model binary or text.
pub fn colmap_files(binary: bool) -> Vec<(String, Vec<u8>)> {
    let d = tempfile::tempdir().unwrap();
    ball().write_colmap(d.path(), binary).unwrap();
    files(d.path())
}

/// A multipart form with one part per file; `by_filename` names the parts
/// `file` and puts the path in the filename, else the field name is the path.
pub fn form_of(entries: &[(String, Vec<u8>)], by_filename: bool) -> reqwest::multipart::Form {
    let mut form = reqwest::multipart::Form::new();
    for (name, data) in entries {
        let part = reqwest::multipart::Part::bytes(data.clone()).file_name(name.clone());
        form = form.part(if by_filename { "file".to_string() } else { name.clone() }, part);
    }
    form
}

pub struct Svc {
    /// `None` when talking to a server in a child process.
    pub server: Option<Server>,
    pub client: Client,
    pub base: String,
}

/// The tests' HTTP client. reqwest is built with `rustls-no-provider` (the
/// object store's TLS, with ring rather than aws-lc), so a process must
/// install a crypto provider before it builds a client, even one that only
/// speaks plain HTTP to 127.0.0.1; installing it twice is harmless.
pub fn http_client() -> Client {
    let _ = rustls::crypto::ring::default_provider().install_default();
    Client::new()
}

impl Svc {
    pub async fn start(config: ServiceConfig) -> Svc {
        let server = Server::start(config, "127.0.0.1:0".parse().unwrap()).await.unwrap();
        let base = format!("http://{}", server.addr);
        Svc { server: Some(server), client: http_client(), base }
    }

    pub fn remote(base: String) -> Svc {
        Svc { server: None, client: http_client(), base }
    }

    pub async fn stop(self) {
        if let Some(s) = self.server {
            s.shutdown().await.unwrap();
        }
    }

    pub fn url(&self, path: &str) -> String {
        format!("{}{path}", self.base)
    }

    pub async fn get(&self, path: &str) -> (StatusCode, Value) {
        let r = self.client.get(self.url(path)).send().await.unwrap();
        let s = r.status();
        (s, r.json().await.unwrap_or(Value::Null))
    }

    pub async fn post_json(&self, path: &str, body: Value) -> (StatusCode, Value) {
        let r = self.client.post(self.url(path)).json(&body).send().await.unwrap();
        let s = r.status();
        (s, r.json().await.unwrap_or(Value::Null))
    }

    pub async fn put_json(&self, path: &str, body: Value) -> (StatusCode, Value) {
        let r = self.client.put(self.url(path)).json(&body).send().await.unwrap();
        let s = r.status();
        (s, r.json().await.unwrap_or(Value::Null))
    }

    pub async fn delete(&self, path: &str) -> (StatusCode, Value) {
        let r = self.client.delete(self.url(path)).send().await.unwrap();
        let s = r.status();
        (s, r.json().await.unwrap_or(Value::Null))
    }

    pub async fn upload(&self, content_type: &str, body: Vec<u8>) -> (StatusCode, Value) {
        let r = self
            .client
            .post(self.url("/v1/scenes"))
            .header("content-type", content_type)
            .body(body)
            .send()
            .await
            .unwrap();
        let s = r.status();
        (s, r.json().await.unwrap_or(Value::Null))
    }

    pub async fn upload_ball(&self) -> String {
        let (s, v) = self.upload("application/zip", zip_of(&ball_files())).await;
        assert_eq!(s, StatusCode::CREATED, "{v}");
        v["id"].as_str().unwrap().to_string()
    }

    pub async fn job(&self, scene: &str, budget: Value) -> String {
        let body = json!({ "scene_id": scene, "model": "nerf-tiny", "budget": budget, "seed": 1, "batch_rays": 256 });
        let (s, v) = self.post_json("/v1/jobs", body).await;
        assert_eq!(s, StatusCode::ACCEPTED, "{v}");
        assert_eq!(v["status"], "queued");
        v["id"].as_str().unwrap().to_string()
    }

    /// The demo scene (`POST /v1/demo`) trained for `steps` steps of
    /// `instant-tiny` (seed 1): the finished training job.
    pub async fn trained_demo(&self, steps: u64) -> Value {
        let (s, scene) = self.post_json("/v1/demo", json!({})).await;
        assert_eq!(s, StatusCode::CREATED, "{scene}");
        let body = json!({ "scene_id": scene["id"], "model": "instant-tiny", "budget": { "steps": steps }, "seed": 1 });
        let (s, train) = self.post_json("/v1/jobs", body).await;
        assert_eq!(s, StatusCode::ACCEPTED, "{train}");
        let done = |v: &Value| !matches!(v["status"].as_str(), Some("queued" | "running"));
        let train = self.wait_job(train["id"].as_str().unwrap(), 300.0, done).await;
        assert_eq!(train["status"], "succeeded", "{train}");
        train
    }

    /// Polls a job until `pred` holds. Panics once the job has not moved
    /// (its status, attempt, stage and step all as they were) for `secs`,
    /// or after [`MOVING_JOB_WAITS`] times `secs` in all: a job that keeps
    /// moving on a slow or busy machine is waited for, a stuck one is not.
    pub async fn wait_job(&self, id: &str, secs: f64, pred: impl Fn(&Value) -> bool) -> Value {
        let t0 = Instant::now();
        let (mut last, mut moved) = (Value::Null, Instant::now());
        loop {
            let (s, v) = self.get(&format!("/v1/jobs/{id}")).await;
            assert_eq!(s, StatusCode::OK);
            if pred(&v) {
                return v;
            }
            let now = json!([v["status"], v["attempts"], v["progress"]["stage"], v["progress"]["step"]]);
            if now != last {
                (last, moved) = (now, Instant::now());
            }
            assert!(moved.elapsed().as_secs_f64() < secs, "the job did not move for {secs} s: {v}");
            assert!(t0.elapsed().as_secs_f64() < MOVING_JOB_WAITS * secs, "timed out waiting for job: {v}");
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }

    pub async fn upload_form(&self, form: reqwest::multipart::Form) -> (StatusCode, Value) {
        let r = self.client.post(self.url("/v1/scenes")).multipart(form).send().await.unwrap();
        let s = r.status();
        (s, r.json().await.unwrap_or(Value::Null))
    }

    /// Enqueues a video of `model` and waits for it; returns the job and
    /// the video's bytes and content type.
    pub async fn video(&self, model: &str, body: Value) -> (Value, Vec<u8>, String) {
        let (s, v) = self.post_json(&format!("/v1/models/{model}/videos"), body).await;
        assert_eq!(s, StatusCode::ACCEPTED, "{v}");
        assert_eq!((v["kind"].as_str(), v["model_id"].as_str()), (Some("video"), Some(model)), "{v}");
        let id = v["id"].as_str().unwrap().to_string();
        let job = self.wait_job(&id, 60.0, |v| v["status"] != "queued" && v["status"] != "running").await;
        assert_eq!(job["status"], "succeeded", "{job}");
        assert_eq!(job["progress"]["step"], job["frames"], "{job}");
        let r = self.client.get(self.url(&format!("/v1/videos/{}", job["video_id"].as_str().unwrap()))).send().await;
        let r = r.unwrap();
        assert_eq!(r.status(), StatusCode::OK);
        let ct = r.headers()["content-type"].to_str().unwrap().to_string();
        (job, r.bytes().await.unwrap().to_vec(), ct)
    }

    pub async fn png(&self, path: &str) -> image::DynamicImage {
        let r = self.client.get(self.url(path)).send().await.unwrap();
        assert_eq!(r.status(), StatusCode::OK, "{path}: {}", r.text().await.unwrap());
        assert_eq!(r.headers()["content-type"], "image/png");
        image::load_from_memory(&r.bytes().await.unwrap()).unwrap()
    }
}

pub fn config(dir: &Path) -> ServiceConfig {
    let mut c = ServiceConfig::new(dir);
    c.scheduler.checkpoint_every = 0.2;
    c
}

pub fn assert_error(v: &Value, code: &str) {
    assert_eq!(v["error"]["code"], code, "{v}");
    assert!(v["error"]["message"].as_str().is_some_and(|m| !m.is_empty()), "{v}");
}

/// Nothing left in the data directory but empty folders.
pub fn assert_no_scene_files(data: &Path) {
    for d in ["scenes", "tmp"] {
        let left: Vec<_> = std::fs::read_dir(data.join(d)).unwrap().collect();
        assert!(left.is_empty(), "{d}/ holds {left:?}");
    }
}

/// Starts the real binary; returns it and its base URL.
pub fn spawn_binary(data: &Path) -> (Served, String) {
    spawn_binary_with(data, &["--checkpoint-every", "0.2"])
}

/// Starts the real binary with more `serve` arguments; returns it and its
/// base URL once it listens. Its stderr goes to a file, read when it is
/// dropped: a test whose server panicked fails.
pub fn spawn_binary_with(data: &Path, args: &[&str]) -> (Served, String) {
    use std::io::BufRead;
    let stderr = tempfile::NamedTempFile::new().unwrap();
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_radiance"))
        .args(["serve", "--addr", "127.0.0.1:0", "--threads", "2"])
        .args(args)
        .arg("--data-dir")
        .arg(data)
        .env_remove("RADIANCE_API_KEY")
        .stdout(std::process::Stdio::piped())
        .stderr(stderr.reopen().unwrap())
        .spawn()
        .unwrap();
    let mut line = String::new();
    std::io::BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
    let served = Served { child, stderr };
    let addr = line.trim().strip_prefix("listening on ").unwrap_or_else(|| {
        panic!("unexpected output: {line}; stderr: {}", std::fs::read_to_string(served.stderr.path()).unwrap())
    });
    (served, addr.to_string())
}

/// The server binary as a child process (a [`std::process::Child`] through
/// `Deref`), with its stderr in a file. Dropped, it is killed if still
/// running, and the test fails if its stderr tells of a panic.
pub struct Served {
    child: std::process::Child,
    stderr: tempfile::NamedTempFile,
}

impl Served {
    /// The lines of the server's stderr so far that tell of a panic.
    pub fn panics(&self) -> Vec<String> {
        let log = std::fs::read(self.stderr.path()).unwrap();
        String::from_utf8_lossy(&log).lines().filter(|l| l.contains("panicked")).map(str::to_string).collect()
    }

    /// The server's peak resident memory (`VmHWM`) so far, bytes; the
    /// process must not have been waited for.
    pub fn peak_rss(&self) -> u64 {
        poses::peak_rss(self.child.id())
    }
}

impl std::ops::Deref for Served {
    type Target = std::process::Child;
    fn deref(&self) -> &std::process::Child {
        &self.child
    }
}

impl std::ops::DerefMut for Served {
    fn deref_mut(&mut self) -> &mut std::process::Child {
        &mut self.child
    }
}

impl Drop for Served {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        if !std::thread::panicking() {
            let panics = self.panics();
            assert!(panics.is_empty(), "the server panicked: {panics:?}");
        }
    }
}
