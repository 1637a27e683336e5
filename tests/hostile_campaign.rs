//! The hostile campaign of issue 35, run again on demand: about 300
//! requests as a stranger with the key would send them, and 14 kill -9s of
//! the server at each stage of a poses job and of a video job, against the
//! release server binary with the real COLMAP and ffmpeg. It prints the
//! counts the issue asks for: cases, kills, 5xx, panics, hangs, wrong 2xx
//! answers, leftover folders, orphan processes and peak memory.
//!
//! Ignored by default (it takes minutes and wants the release build):
//!
//!     cargo build --release --locked
//!     cargo test --locked --test hostile_campaign -- --ignored --nocapture
//!
//! `RADIANCE_BIN` names another server binary (default
//! `target/release/radiance`). The server listens on 127.0.0.1 only, on a
//! data directory of its own; its stderr goes to a file whose lines saying
//! "panicked" are counted. Every request and every wait is bounded in time:
//! a request not answered within 90 s, or a job not final within its
//! bound, counts as a hang. The test fails if any count but cases and
//! kills is not zero.

mod common;

use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use common::poses::bomb_png;
use common::*;
use radiance::engine::dataset::textured::TexturedScene;
use serde_json::{Value, json};

/// Answers a hostile request may get: refusals.
const REFUSED: &[u16] = &[400, 404, 405, 409, 413, 415, 422];
/// A request not answered within this is a hang.
const REQUEST_LIMIT: Duration = Duration::from_secs(90);

fn binary() -> PathBuf {
    let bin = std::env::var_os("RADIANCE_BIN")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("target/release/radiance"));
    assert!(bin.is_file(), "{} is missing: run `cargo build --release --locked` first", bin.display());
    bin
}

/// One server process on a data directory, its stderr in `log`.
struct Server {
    child: Child,
    base: String,
    addr: String,
}

/// A server the campaign leaves behind (a failed assertion) is killed.
impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// What the campaign counts.
#[derive(Default)]
struct Tally {
    cases: usize,
    kills: usize,
    answers_5xx: Vec<String>,
    wrong_2xx: Vec<String>,
    hangs: Vec<String>,
    /// Refusals with another code than expected (not counted as failures,
    /// listed).
    other: Vec<String>,
    leftovers: Vec<String>,
    orphans: Vec<String>,
    /// Jobs of the kill scenarios that did not end as they should.
    jobs: Vec<String>,
}

struct Campaign {
    bin: PathBuf,
    root: PathBuf,
    logs: Vec<PathBuf>,
    t: Tally,
    client: reqwest::Client,
    peak_server: Arc<AtomicU64>,
    peak_child: Arc<AtomicU64>,
    peak_child_name: Arc<Mutex<String>>,
}

fn status_of(v: u16) -> String {
    if v == 0 { "no answer (connection closed)".into() } else { v.to_string() }
}

/// Processes whose command line names `dir`, not counting servers
/// (`radiance serve`) unless `servers`.
fn processes_in(dir: &Path, servers: bool) -> Vec<(u32, String)> {
    let needle = dir.display().to_string();
    let mut found = Vec::new();
    let Ok(procs) = std::fs::read_dir("/proc") else { return found };
    for e in procs.flatten() {
        let Ok(pid) = e.file_name().to_string_lossy().parse::<u32>() else { continue };
        let Ok(cmd) = std::fs::read(e.path().join("cmdline")) else { continue };
        let cmd = String::from_utf8_lossy(&cmd).replace('\0', " ");
        let is_server = cmd.contains(" serve --addr");
        if cmd.contains(&needle) && (servers || !is_server) && !cmd.contains("hostile_campaign") {
            found.push((pid, cmd));
        }
    }
    found
}

fn vm_hwm(pid: u32) -> Option<u64> {
    let s = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    Some(line.split_whitespace().nth(1)?.parse::<u64>().ok()? * 1024)
}

impl Campaign {
    fn start(&mut self, data: &Path, args: &[&str]) -> Server {
        use std::io::BufRead;
        let log = self.root.join(format!("serve-{}.stderr", self.logs.len()));
        let mut child = Command::new(&self.bin)
            .args(["serve", "--addr", "127.0.0.1:0", "--threads", "2", "--checkpoint-every", "0.5"])
            .args(args)
            .arg("--data-dir")
            .arg(data)
            .env_remove("RADIANCE_API_KEY")
            .stdout(Stdio::piped())
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .unwrap();
        self.logs.push(log);
        let mut line = String::new();
        std::io::BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
        let addr = line.trim().strip_prefix("listening on ").unwrap_or_else(|| panic!("server said: {line}"));
        let addr = addr.trim_start_matches("http://").to_string();
        Server { child, base: format!("http://{addr}"), addr }
    }

    fn note_peak(&self, s: &Server) {
        if let Some(p) = vm_hwm(s.child.id()) {
            self.peak_server.fetch_max(p, Ordering::Relaxed);
        }
    }

    /// kill -9 of the server; 10 s later (the parent-death signal acts at
    /// once; the rest is room for a starved test thread) no process of
    /// `data` may be left.
    fn kill(&mut self, s: &mut Server, data: &Path, when: &str) {
        self.note_peak(s);
        s.child.kill().unwrap();
        s.child.wait().unwrap();
        self.t.kills += 1;
        let t = Instant::now();
        while !processes_in(data, true).is_empty() && t.elapsed() < Duration::from_secs(10) {
            std::thread::sleep(Duration::from_millis(50));
        }
        for (pid, cmd) in processes_in(data, true) {
            self.t.orphans.push(format!("10 s after the kill {when}: {pid} {cmd}"));
        }
    }

    /// SIGTERM, then the server's exit within 30 s (else kill -9, a hang).
    fn stop(&mut self, mut s: Server) {
        self.note_peak(&s);
        let _ = Command::new("kill").args(["-TERM", &s.child.id().to_string()]).status();
        let t = Instant::now();
        while s.child.try_wait().unwrap().is_none() {
            if t.elapsed() > Duration::from_secs(30) {
                self.t.hangs.push("the server did not stop within 30 s of SIGTERM".into());
                let _ = s.child.kill();
                let _ = s.child.wait();
                break;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// Sends one case; `allowed` are the answers it may get (0: the
    /// connection closed without one).
    async fn case(&mut self, name: &str, allowed: &[u16], req: reqwest::RequestBuilder) -> (u16, Value) {
        self.t.cases += 1;
        let r = tokio::time::timeout(REQUEST_LIMIT, async {
            match req.send().await {
                Ok(r) => {
                    let s = r.status().as_u16();
                    let body = r.bytes().await.map(|b| b.to_vec()).unwrap_or_default();
                    (s, serde_json::from_slice(&body).unwrap_or(Value::Null))
                }
                Err(_) => (0, Value::Null),
            }
        })
        .await;
        let Ok((s, v)) = r else {
            self.t.hangs.push(format!("{name}: no answer within {} s", REQUEST_LIMIT.as_secs()));
            return (0, Value::Null);
        };
        self.judge(name, allowed, s, &v.to_string());
        (s, v)
    }

    fn judge(&mut self, name: &str, allowed: &[u16], s: u16, body: &str) {
        let body: String = body.chars().take(300).collect();
        if s < 500 && allowed.contains(&s) {
            return;
        }
        if s >= 500 {
            self.t.answers_5xx.push(format!("{name}: {s} {body}"));
        } else if (200..300).contains(&s) {
            self.t.wrong_2xx.push(format!("{name}: {s} {body}"));
        } else {
            self.t.other.push(format!("{name}: {} (expected {allowed:?}) {body}", status_of(s)));
        }
    }

    /// Sends raw bytes on a new connection (what a client library would not
    /// send); the answer's status, 0 when the server closed without one.
    /// `half_close` ends the request's side of the connection once sent (a
    /// body cut short); otherwise the server closes it (`Connection: close`
    /// or an error).
    async fn raw(
        &mut self,
        name: &str,
        addr: &str,
        allowed: &[u16],
        bytes: Vec<u8>,
        forbidden: &str,
        half_close: bool,
    ) {
        self.t.cases += 1;
        let addr = addr.to_string();
        let r = tokio::task::spawn_blocking(move || -> Result<(u16, String), String> {
            let mut c = std::net::TcpStream::connect(&addr).map_err(|e| e.to_string())?;
            c.set_read_timeout(Some(REQUEST_LIMIT)).unwrap();
            c.set_write_timeout(Some(REQUEST_LIMIT)).unwrap();
            let _ = c.write_all(&bytes);
            if half_close {
                let _ = c.shutdown(std::net::Shutdown::Write);
            }
            let mut out = Vec::new();
            let mut buf = [0u8; 8192];
            loop {
                match c.read(&mut buf) {
                    Ok(0) => break,
                    Ok(n) => out.extend_from_slice(&buf[..n]),
                    Err(e)
                        if e.kind() == std::io::ErrorKind::WouldBlock || e.kind() == std::io::ErrorKind::TimedOut =>
                    {
                        if out.is_empty() {
                            return Err("timeout".into());
                        }
                        break;
                    }
                    Err(_) => break,
                }
                if out.len() > 1 << 20 {
                    break;
                }
            }
            let text = String::from_utf8_lossy(&out).into_owned();
            let status = text.strip_prefix("HTTP/1.1 ").and_then(|t| t.get(..3)).and_then(|c| c.parse().ok());
            Ok((status.unwrap_or(0), text))
        })
        .await
        .unwrap();
        match r {
            Err(_) => self.t.hangs.push(format!("{name}: no answer within {} s", REQUEST_LIMIT.as_secs())),
            Ok((s, text)) => {
                if !forbidden.is_empty() && text.contains(forbidden) {
                    self.t.wrong_2xx.push(format!("{name}: {s} and the answer holds '{forbidden}'"));
                } else {
                    let body = text.split("\r\n\r\n").nth(1).unwrap_or("").to_string();
                    self.judge(name, allowed, s, &body);
                }
            }
        }
    }

    /// Polls a job until `done` says so or `secs` pass (a hang).
    async fn wait_job(&mut self, base: &str, id: &str, secs: f64, done: impl Fn(&Value) -> bool) -> Value {
        let t = Instant::now();
        loop {
            let r = self.client.get(format!("{base}/v1/jobs/{id}")).timeout(Duration::from_secs(30)).send().await;
            if let Ok(r) = r {
                if r.status().is_server_error() {
                    self.t.answers_5xx.push(format!("GET /v1/jobs/{id}: {}", r.status()));
                }
                let v: Value = r.json().await.unwrap_or(Value::Null);
                if done(&v) {
                    return v;
                }
                if t.elapsed().as_secs_f64() > secs {
                    self.t.hangs.push(format!("job {id}: not there within {secs} s: {v}"));
                    return v;
                }
            } else if t.elapsed().as_secs_f64() > secs {
                self.t.hangs.push(format!("job {id}: no answer within {secs} s"));
                return Value::Null;
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }
}

fn is_final(v: &Value) -> bool {
    ["succeeded", "failed", "canceled"].contains(&v["status"].as_str().unwrap_or(""))
}

/// The textured scene's photos (no poses) at `w`x`h`, under `photos/`.
fn photos_at(views: usize, w: u32, h: u32) -> Vec<(String, Vec<u8>)> {
    let d = tempfile::tempdir().unwrap();
    TexturedScene { views, width: w, height: h, ..Default::default() }.write_photos(d.path()).unwrap();
    files(d.path()).into_iter().map(|(n, b)| (format!("photos/{n}"), b)).collect()
}

fn png(w: u32, h: u32) -> Vec<u8> {
    let img = image::RgbImage::from_fn(w, h, |x, y| image::Rgb([(x * 13) as u8, (y * 7) as u8, 99]));
    let mut out = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut out), image::ImageFormat::Png).unwrap();
    out
}

/// A real 16x16 JPEG whose frame header is changed to declare `w`x`h`.
fn bomb_jpeg(w: u16, h: u16) -> Vec<u8> {
    let img = image::RgbImage::from_fn(16, 16, |x, y| image::Rgb([(x * 9) as u8, (y * 5) as u8, 7]));
    let mut out = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut out), image::ImageFormat::Jpeg).unwrap();
    let sof = (0..out.len() - 9).find(|&i| out[i] == 0xFF && (out[i + 1] == 0xC0 || out[i + 1] == 0xC2)).unwrap();
    out[sof + 5..sof + 7].copy_from_slice(&h.to_be_bytes());
    out[sof + 7..sof + 9].copy_from_slice(&w.to_be_bytes());
    out
}

/// A tar (gzipped or not) with an entry of a given type.
fn tar_with(entries: &[(String, Vec<u8>)], special: Option<(&str, tar::EntryType, &str)>, gz: bool) -> Vec<u8> {
    let mut b = tar::Builder::new(Vec::new());
    for (name, data) in entries {
        let mut h = tar::Header::new_gnu();
        h.as_gnu_mut().unwrap().name[..name.len()].copy_from_slice(name.as_bytes());
        h.set_size(data.len() as u64);
        h.set_mode(0o644);
        h.set_entry_type(tar::EntryType::Regular);
        h.set_cksum();
        b.append(&h, data.as_slice()).unwrap();
    }
    if let Some((name, kind, link)) = special {
        let mut h = tar::Header::new_gnu();
        h.set_path(name).unwrap();
        h.set_size(0);
        h.set_mode(0o644);
        h.set_entry_type(kind);
        if !link.is_empty() {
            h.set_link_name(link).unwrap();
        }
        h.set_cksum();
        b.append(&h, std::io::empty()).unwrap();
    }
    let tar = b.into_inner().unwrap();
    if !gz {
        return tar;
    }
    let mut z = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
    z.write_all(&tar).unwrap();
    z.finish().unwrap()
}

/// Sets the checksum of the tar's first header after a change to it.
fn tar_checksum(t: &mut [u8]) {
    let sum: u32 = t[..512].iter().enumerate().map(|(i, &b)| if (148..156).contains(&i) { 32 } else { b as u32 }).sum();
    t[148..156].copy_from_slice(format!("{sum:06o}\0 ").as_bytes());
}

/// A zip whose entry `name` inflates to `bytes` zeros.
fn zip_bomb(name: &str, bytes: usize) -> Vec<u8> {
    let mut w = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let opts = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Deflated)
        .large_file(bytes > u32::MAX as usize);
    w.start_file(name, opts).unwrap();
    let zeros = vec![0u8; 1 << 20];
    for _ in 0..bytes >> 20 {
        w.write_all(&zeros).unwrap();
    }
    w.finish().unwrap().into_inner()
}

/// An MP4 (H.264) of `frames` frames of ffmpeg's lavfi `source`.
fn mp4(dir: &Path, name: &str, source: &str, size: &str, frames: u32) -> Vec<u8> {
    let path = dir.join(name);
    let sep = if source.contains('=') { ":" } else { "=" };
    let ok = Command::new("ffmpeg")
        .args(["-loglevel", "error", "-y", "-f", "lavfi", "-i", &format!("{source}{sep}size={size}:rate=12")])
        .args(["-frames:v", &frames.to_string(), "-c:v", "libx264", "-preset", "ultrafast", "-pix_fmt", "yuv420p"])
        .arg(&path)
        .status()
        .unwrap()
        .success();
    assert!(ok, "ffmpeg made no {name}");
    std::fs::read(path).unwrap()
}

/// A walk around the textured scene filmed at 12 fps: `views` frames.
fn walk_mp4(dir: &Path, views: usize) -> Vec<u8> {
    let frames = dir.join(format!("walk{views}"));
    TexturedScene { width: 320, height: 240, views, fov: 0.9 }.write_photos(&frames).unwrap();
    let clip = dir.join(format!("walk{views}.mp4"));
    let ok = Command::new("ffmpeg")
        .args(["-loglevel", "error", "-y", "-framerate", "12", "-i"])
        .arg(frames.join("view_%03d.png"))
        .args(["-c:v", "libx264", "-crf", "12", "-pix_fmt", "yuv420p"])
        .arg(&clip)
        .status()
        .unwrap()
        .success();
    assert!(ok);
    std::fs::read(clip).unwrap()
}

fn with_replaced(files: &[(String, Vec<u8>)], suffix: &str, bytes: Vec<u8>) -> (Vec<(String, Vec<u8>)>, String) {
    let mut f = files.to_vec();
    let k = f.iter().position(|(n, _)| n.ends_with(suffix)).unwrap();
    f[k].1 = bytes;
    let name = f[k].0.clone();
    (f, name)
}

/// What a data directory holds that no finished job should leave: working
/// folders, process lists, staging, saved frames, temporaries, and scene
/// folders without a record.
fn leftovers_in(data: &Path, scenes: &[String]) -> Vec<String> {
    let mut out = Vec::new();
    fn walk(d: &Path, out: &mut Vec<PathBuf>) {
        for e in std::fs::read_dir(d).into_iter().flatten().flatten() {
            out.push(e.path());
            if e.file_type().is_ok_and(|t| t.is_dir()) {
                walk(&e.path(), out);
            }
        }
    }
    let mut all = Vec::new();
    walk(data, &mut all);
    for p in &all {
        let rel = p.strip_prefix(data).unwrap().to_string_lossy().into_owned();
        let name = p.file_name().unwrap().to_string_lossy();
        let parts: Vec<&str> = rel.split('/').collect();
        let bad = (parts[0] == "tmp" && parts.len() == 2)
            || name.starts_with(".data.posing")
            || name.starts_with(".frames-")
            || (name == ".processes" && std::fs::read_dir(p).is_ok_and(|mut d| d.next().is_some()))
            || name.contains(".tmp")
            || (parts[0] == "scenes" && parts.len() == 2 && !scenes.iter().any(|s| s == parts[1]))
            || (parts[0] == "scenes" && parts.len() == 3 && !["data", "upload", "scene.json"].contains(&parts[2]));
        if bad {
            out.push(rel);
        }
    }
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "the hostile campaign of issue 35: minutes, the release binary; run with --ignored"]
async fn hostile_campaign() {
    let started = Instant::now();
    let _ = http_client(); // installs the TLS crypto provider reqwest asks for
    let root = tempfile::tempdir().unwrap();
    let mut c = Campaign {
        bin: binary(),
        root: root.path().to_path_buf(),
        logs: Vec::new(),
        t: Tally::default(),
        client: reqwest::Client::builder().timeout(REQUEST_LIMIT).build().unwrap(),
        peak_server: Arc::default(),
        peak_child: Arc::default(),
        peak_child_name: Arc::default(),
    };
    let data = root.path().join("data");
    let keyed = root.path().join("keyed");
    let work = root.path().join("work");
    std::fs::create_dir_all(&work).unwrap();
    // Every 100 ms: the peak memory of the servers and of their children
    // (what names a data directory; not the campaign's own ffmpeg in work/).
    let stop = Arc::new(AtomicBool::new(false));
    let sampler = {
        let (stop, dirs) = (stop.clone(), [data.clone(), keyed.clone()]);
        let (ps, pc, pn) = (c.peak_server.clone(), c.peak_child.clone(), c.peak_child_name.clone());
        std::thread::spawn(move || {
            while !stop.load(Ordering::Relaxed) {
                for (pid, cmd) in dirs.iter().flat_map(|d| processes_in(d, true)) {
                    let Some(p) = vm_hwm(pid) else { continue };
                    if cmd.contains(" serve --addr") {
                        ps.fetch_max(p, Ordering::Relaxed);
                    } else if pc.fetch_max(p, Ordering::Relaxed) < p {
                        *pn.lock().unwrap() = cmd.split_whitespace().take(2).collect::<Vec<_>>().join(" ");
                    }
                }
                std::thread::sleep(Duration::from_millis(100));
            }
        })
    };

    let mut server = c.start(&data, &[]);
    let base = server.base.clone();
    let addr = server.addr.clone();
    let url = |p: &str| format!("{base}{p}");
    let cl = c.client.clone();
    let post = |ct: &str, body: Vec<u8>| cl.post(url("/v1/scenes")).header("content-type", ct).body(body);

    // ---- Archives ------------------------------------------------------
    let ball = ball_files();
    let zball = zip_of(&ball);
    let tball = tar_with(&ball, None, false);
    let gball = tar_with(&ball, None, true);
    for ct in ["application/zip", "application/x-tar", "application/gzip", "multipart/form-data; boundary=xyz"] {
        c.case(&format!("empty body as {ct}"), REFUSED, post(ct, Vec::new())).await;
    }
    let mut noise = vec![0u8; 1 << 20];
    let mut st = 0x9e3779b97f4a7c15u64;
    for b in noise.iter_mut() {
        st ^= st << 13;
        st ^= st >> 7;
        st ^= st << 17;
        *b = st as u8;
    }
    for ct in ["application/zip", "application/x-tar", "application/gzip"] {
        for n in [1 << 10, 1 << 20] {
            c.case(&format!("{n} random bytes as {ct}"), REFUSED, post(ct, noise[..n].to_vec())).await;
        }
    }
    for (kind, ct, bytes) in [
        ("zip", "application/zip", &zball),
        ("tar", "application/x-tar", &tball),
        ("tar.gz", "application/gzip", &gball),
    ] {
        for pct in [1, 25, 50, 75, 90, 99] {
            let at = bytes.len() * pct / 100;
            // A tar cut in its end-of-archive zeros has lost nothing.
            let whole = kind == "tar" && bytes[at..].iter().all(|&b| b == 0);
            let allowed: &[u16] = if whole { &[201] } else { REFUSED };
            c.case(&format!("{kind} cut at {pct}%"), allowed, post(ct, bytes[..at].to_vec())).await;
        }
    }
    for (ct, body) in [
        ("application/x-tar", zball.clone()),
        ("application/gzip", zball.clone()),
        ("application/zip", gball.clone()),
        ("text/plain", zball.clone()),
        ("application/json", zball.clone()),
        ("image/png", png(64, 64)),
    ] {
        c.case(&format!("a body under the wrong Content-Type {ct}"), REFUSED, post(ct, body)).await;
    }
    c.case("an upload without a Content-Type", REFUSED, cl.post(url("/v1/scenes")).body(zball.clone())).await;
    for evil in ["../evil.png", "/tmp/evil.png", "a/../../evil.png", "..\\..\\evil.png", "train/../../../evil.png"] {
        let mut f = ball.clone();
        f.push((evil.to_string(), png(8, 8)));
        c.case(&format!("zip entry '{evil}'"), REFUSED, post("application/zip", zip_of(&f))).await;
        c.case(&format!("tar.gz entry '{evil}'"), REFUSED, post("application/gzip", tar_gz_of(&f))).await;
        let form = form_of(&f, true);
        c.case(&format!("multipart part '{evil}'"), REFUSED, cl.post(url("/v1/scenes")).multipart(form)).await;
    }
    let (_, first_png) = with_replaced(&ball, ".png", Vec::new());
    let mut no_png: Vec<_> = ball.iter().filter(|(n, _)| *n != first_png).cloned().collect();
    no_png.sort();
    for (what, kind, link) in [
        ("a symlink to /etc/passwd", tar::EntryType::Symlink, "/etc/passwd"),
        ("a symlink out of the folder", tar::EntryType::Symlink, "../../../../etc/hostname"),
        ("a hard link to /etc/passwd", tar::EntryType::Link, "/etc/passwd"),
        ("a character device", tar::EntryType::Char, ""),
        ("a fifo", tar::EntryType::Fifo, ""),
    ] {
        let body = tar_with(&no_png, Some((&first_png, kind, link)), false);
        c.case(&format!("tar with {what} as {first_png}"), REFUSED, post("application/x-tar", body)).await;
    }
    // Entries named twice, in each form.
    let mut twice = ball.clone();
    twice.push(ball[ball.len() - 1].clone());
    c.case("tar naming an entry twice", REFUSED, post("application/x-tar", tar_with(&twice, None, false))).await;
    let form = form_of(&twice, true);
    c.case("multipart naming a file twice", REFUSED, cl.post(url("/v1/scenes")).multipart(form)).await;
    {
        // A zip with a second entry renamed onto the first.
        let pngs: Vec<usize> = (0..ball.len()).filter(|&i| ball[i].0.ends_with(".png")).collect();
        let (i, j) = pngs
            .iter()
            .flat_map(|&i| pngs.iter().map(move |&j| (i, j)))
            .find(|&(i, j)| i < j && ball[i].0.len() == ball[j].0.len())
            .unwrap();
        let (a, b) = (ball[i].0.clone(), ball[j].0.clone());
        let mut zip = zip_of(&ball);
        let at: Vec<usize> = (0..zip.len() - b.len()).filter(|&i| zip[i..i + b.len()] == *b.as_bytes()).collect();
        for i in at {
            zip[i..i + b.len()].copy_from_slice(a.as_bytes());
        }
        c.case("zip naming an entry twice", REFUSED, post("application/zip", zip)).await;
    }
    // Bombs and oddities of the archive itself.
    c.case("zip entry inflating to 3 GiB", REFUSED, post("application/zip", zip_bomb("train/r_0.png", 3 << 30))).await;
    c.case("zip entry inflating to 600 MiB", REFUSED, post("application/zip", zip_bomb("big.bin", 600 << 20))).await;
    let mut nested = ball.clone();
    nested.push(("inner.zip".into(), zip_bomb("x.png", 64 << 20)));
    c.case("zip inside a zip", &[201, 400, 413, 422], post("application/zip", zip_of(&nested))).await;
    let many: Vec<_> = (0..20000).map(|k| (format!("f/{k}.txt"), vec![b'x'])).collect();
    c.case("zip of 20000 tiny files", REFUSED, post("application/zip", zip_of(&many))).await;
    let deep = format!("{}x.png", "d/".repeat(300));
    c.case("zip entry 300 folders deep", REFUSED, post("application/zip", zip_of(&[(deep, png(8, 8))]))).await;
    let long = format!("{}.png", "n".repeat(1000));
    c.case("zip entry of a 1000-byte name", REFUSED, post("application/zip", zip_of(&[(long, png(8, 8))]))).await;
    let mut raw_name = tar_with(&[("images/\u{1}x.png".into(), png(8, 8))], None, false);
    raw_name[7] = 0xff; // a name that is not UTF-8
    tar_checksum(&mut raw_name);
    c.case("tar entry whose name is not UTF-8", REFUSED, post("application/x-tar", raw_name)).await;
    {
        // A tar header declaring 8 GB for an entry of a few bytes.
        let mut t = tar_with(&[("images/a.png".into(), png(8, 8))], None, false);
        let size = format!("{:011o}\0", (8u64 << 30) - 1);
        t[124..136].copy_from_slice(size.as_bytes());
        tar_checksum(&mut t);
        c.case("tar entry declaring 8 GB", REFUSED, post("application/x-tar", t)).await;
    }
    c.case("only a README", REFUSED, post("application/zip", zip_of(&[("README.txt".into(), b"hi".to_vec())]))).await;
    // Multipart as no library sends it.
    for (what, body) in [
        (
            "no closing boundary",
            "--xyz\r\nContent-Disposition: form-data; name=\"a.png\"; filename=\"a.png\"\r\n\r\nabc",
        ),
        ("a part with neither name nor filename", "--xyz\r\nContent-Disposition: form-data\r\n\r\nabc\r\n--xyz--\r\n"),
        ("a part without headers", "--xyz\r\n\r\nabc\r\n--xyz--\r\n"),
        ("garbage", "this is not multipart at all"),
    ] {
        c.case(&format!("multipart with {what}"), REFUSED, post("multipart/form-data; boundary=xyz", body.into()))
            .await;
    }
    c.case("multipart without a boundary", REFUSED, post("multipart/form-data", b"--x\r\n".to_vec())).await;
    let parts: Vec<_> = (0..3000).map(|k| (format!("p{k}.txt"), vec![b'y'])).collect();
    let form = form_of(&parts, false);
    c.case("multipart of 3000 parts", REFUSED, cl.post(url("/v1/scenes")).multipart(form)).await;
    let form = form_of(&[(format!("{}.png", "q".repeat(5000)), png(8, 8))], true);
    c.case("multipart with a 5000-byte file name", REFUSED, cl.post(url("/v1/scenes")).multipart(form)).await;

    // ---- Decompression bombs: headers declaring huge images ------------
    let three = photos_at(3, 320, 240);
    let pngs =
        [(20000u32, 20000u32), (30000, 30000), (100000, 100000), (65535, 65535), (1, 60_000_000), (60_000_000, 1)];
    for (w, h) in pngs {
        let mut f = three.clone();
        f.push(("photos/bomb.png".into(), bomb_png(w, h)));
        c.case(&format!("photos + PNG bomb {w}x{h} (zip)"), &[422], post("application/zip", zip_of(&f))).await;
        let form = form_of(&f, true);
        c.case(&format!("photos + PNG bomb {w}x{h} (multipart)"), &[422], cl.post(url("/v1/scenes")).multipart(form))
            .await;
    }
    for (w, h) in [(65000u16, 65000u16), (60000, 2000)] {
        let mut f = three.clone();
        f.push(("photos/bomb.jpg".into(), bomb_jpeg(w, h)));
        c.case(&format!("photos + JPEG bomb {w}x{h} (zip)"), &[422], post("application/zip", zip_of(&f))).await;
        let form = form_of(&f, true);
        c.case(&format!("photos + JPEG bomb {w}x{h} (multipart)"), &[422], cl.post(url("/v1/scenes")).multipart(form))
            .await;
    }
    let all_bombs: Vec<_> = (0..4).map(|k| (format!("photos/b{k}.png"), bomb_png(30000, 30000))).collect();
    c.case("four PNG bombs, nothing else", &[422], post("application/zip", zip_of(&all_bombs))).await;
    let datasets = [
        ("Blender", ball.clone(), ".png"),
        ("Instant-NGP", ngp_files(), ".png"),
        ("LLFF", llff_files(), ".png"),
        ("COLMAP", colmap_files(true), ".png"),
    ];
    for (kind, files, ext) in &datasets {
        for (w, h) in [(30000u32, 30000u32), (100000, 100000), (20000, 20000)] {
            let (f, name) = with_replaced(files, ext, bomb_png(w, h));
            c.case(&format!("{kind} dataset with {name} a {w}x{h} bomb"), &[422], post("application/zip", zip_of(&f)))
                .await;
        }
    }
    let (f, _) = with_replaced(&llff_masked_files(), "masks_8/img000.png", bomb_png(30000, 30000));
    c.case("LLFF dataset with a mask a 30000x30000 bomb", &[422], post("application/zip", zip_of(&f))).await;
    for (w, h) in [(0u32, 0u32), (0, 500)] {
        let mut p = bomb_png(1, 1);
        p[16..20].copy_from_slice(&w.to_be_bytes());
        p[20..24].copy_from_slice(&h.to_be_bytes());
        let crc = crc32fast::hash(&p[12..29]);
        p[29..33].copy_from_slice(&crc.to_be_bytes());
        let (f, name) = with_replaced(&ball, ".png", p.clone());
        c.case(&format!("Blender dataset with {name} declaring {w}x{h}"), REFUSED, post("application/zip", zip_of(&f)))
            .await;
        let mut f = three.clone();
        f.push(("photos/zero.png".into(), p));
        c.case(&format!("photos + a PNG declaring {w}x{h}"), REFUSED, post("application/zip", zip_of(&f))).await;
    }

    // ---- Photo-only sets the poses job could not use --------------------
    for n in [1, 2] {
        let f = photos_at(n, 320, 240);
        c.case(&format!("{n} photos"), &[422], post("application/zip", zip_of(&f))).await;
        c.case(&format!("{n} photos (multipart)"), &[422], cl.post(url("/v1/scenes")).multipart(form_of(&f, true)))
            .await;
    }
    let mut mixed = photos_at(4, 320, 240);
    mixed[3].1 = png(240, 320);
    c.case("photos of mixed sizes", &[422], post("application/zip", zip_of(&mixed))).await;
    c.case("photos of mixed sizes (multipart)", &[422], cl.post(url("/v1/scenes")).multipart(form_of(&mixed, true)))
        .await;
    for (w, h) in [(1u32, 1u32), (31, 31), (4000, 2)] {
        let f: Vec<_> = (0..4).map(|k| (format!("photos/p{k}.png"), png(w, h))).collect();
        c.case(&format!("4 photos of {w}x{h}"), &[422], post("application/zip", zip_of(&f))).await;
    }
    let mut tiny = three.clone();
    tiny.push(("photos/dot.png".into(), png(1, 1)));
    c.case("photos + a 1x1 photo", &[422], post("application/zip", zip_of(&tiny))).await;
    let lots: Vec<_> = (0..2001).map(|k| (format!("photos/p{k:04}.png"), png(40, 40))).collect();
    c.case("2001 photos", &[422, 413], post("application/zip", zip_of(&lots))).await;
    for (what, bytes) in [
        ("text named .jpg", b"this is not a photo".to_vec()),
        ("an empty .jpg", Vec::new()),
        ("a GIF named .png", {
            let mut g = Vec::new();
            image::RgbImage::new(320, 240)
                .write_to(&mut std::io::Cursor::new(&mut g), image::ImageFormat::Gif)
                .unwrap();
            g
        }),
        ("8 bytes of PNG signature", b"\x89PNG\r\n\x1a\n".to_vec()),
    ] {
        let mut f = three.clone();
        f.push(("photos/odd.jpg".into(), bytes));
        c.case(&format!("photos + {what}"), &[422], post("application/zip", zip_of(&f))).await;
    }

    // ---- Videos ----------------------------------------------------------
    let good = mp4(&work, "good.mp4", "testsrc", "320x240", 48);
    let videos: Vec<(&str, Vec<u8>)> = vec![
        ("empty.mp4", Vec::new()),
        ("notes.mp4", b"just some text, not a video\n".to_vec()),
        ("cut10.mp4", good[..good.len() / 10].to_vec()),
        ("cut50.mp4", good[..good.len() / 2].to_vec()),
        ("cut90.mp4", good[..good.len() * 9 / 10].to_vec()),
        ("one.mp4", mp4(&work, "one.mp4", "testsrc", "320x240", 1)),
        ("still.mp4", mp4(&work, "still.mp4", "color=c=gray", "320x240", 48)),
        ("tiny.mp4", mp4(&work, "tiny.mp4", "testsrc", "16x16", 48)),
        ("huge.mp4", mp4(&work, "huge.mp4", "testsrc", "8192x6400", 2)),
        ("photo.mov", png(320, 240)),
        ("noise.mkv", noise[..200_000].to_vec()),
        ("tail.mp4", [good.clone(), noise[..50_000].to_vec()].concat()),
    ];
    for (name, bytes) in &videos {
        // Trailing bytes after a whole video may be taken.
        let allowed: &[u16] = if *name == "tail.mp4" { &[422, 201] } else { &[422] };
        let f = vec![(format!("clip/{name}"), bytes.clone())];
        let form = form_of(&f, true);
        let (_, v) =
            c.case(&format!("video {name} (multipart)"), allowed, cl.post(url("/v1/scenes")).multipart(form)).await;
        cancel(&mut c, &base, &v).await;
        let (_, v) = c.case(&format!("video {name} (zip)"), allowed, post("application/zip", zip_of(&f))).await;
        cancel(&mut c, &base, &v).await;
    }
    let audio = {
        let p = work.join("audio.mp4");
        let ok = Command::new("ffmpeg")
            .args(["-loglevel", "error", "-y", "-f", "lavfi", "-i", "sine=duration=2", "-c:a", "aac"])
            .arg(&p)
            .status()
            .unwrap()
            .success();
        assert!(ok);
        std::fs::read(p).unwrap()
    };
    let form = form_of(&[("clip/audio.mp4".into(), audio)], true);
    c.case("an MP4 with sound only", &[422], cl.post(url("/v1/scenes")).multipart(form)).await;
    let two = vec![("a.mp4".into(), good.clone()), ("b.mp4".into(), good.clone())];
    c.case("two videos", &[422], cl.post(url("/v1/scenes")).multipart(form_of(&two, true))).await;
    let mut both = three.clone();
    both.push(("clip.mp4".into(), good.clone()));
    c.case("photos and a video", &[422], cl.post(url("/v1/scenes")).multipart(form_of(&both, true))).await;
    // A real video is taken; its poses job is cancelled while ffmpeg or
    // COLMAP runs (no process may outlive it).
    let form = form_of(&[("clip/good.mp4".into(), good.clone())], true);
    let (_, v) = c.case("a real video", &[201], cl.post(url("/v1/scenes")).multipart(form)).await;
    cancel(&mut c, &base, &v).await;
    let (_, v) = c.case("3 real photos", &[201], post("application/zip", zip_of(&three))).await;
    cancel(&mut c, &base, &v).await;

    // ---- Jobs, renders and videos: JSON as no client should send it ----
    let (_, v) = c.case("the ball scene", &[201], post("application/zip", zball.clone())).await;
    let scene = v["id"].as_str().unwrap_or("none").to_string();
    let (_, v) = c
        .case(
            "a 20-step job",
            &[202],
            cl.post(url("/v1/jobs")).json(&json!({ "scene_id": scene, "budget": { "steps": 20 } })),
        )
        .await;
    let job = v["id"].as_str().unwrap_or("none").to_string();
    let done = c.wait_job(&base, &job, 120.0, is_final).await;
    let model = done["model_id"].as_str().unwrap_or("none").to_string();
    let jobs_json = |body: String| cl.post(url("/v1/jobs")).header("content-type", "application/json").body(body);
    let mut bodies: Vec<(String, String)> = [
        "",
        "{",
        "null",
        "[]",
        "123",
        "\"x\"",
        "{\"scene_id\": 1, \"budget\": {\"steps\": 1}}",
        "{\"scene_id\": \"x\"}",
    ]
    .iter()
    .map(|b| (format!("jobs body {b:?}"), b.to_string()))
    .collect();
    let s = &scene;
    for (what, budget_and_more) in [
        ("an unknown scene", json!({ "scene_id": "scn_nope", "budget": { "steps": 1 } })),
        ("a traversing scene id", json!({ "scene_id": "../../etc/passwd", "budget": { "steps": 1 } })),
        ("no budget", json!({ "scene_id": s })),
        ("an empty budget", json!({ "scene_id": s, "budget": {} })),
        ("0 steps", json!({ "scene_id": s, "budget": { "steps": 0 } })),
        ("-1 steps", json!({ "scene_id": s, "budget": { "steps": -1 } })),
        ("1e18 steps", json!({ "scene_id": s, "budget": { "steps": 1_000_000_000_000_000_000u64 } })),
        ("1.5 steps", json!({ "scene_id": s, "budget": { "steps": 1.5 } })),
        ("0 seconds", json!({ "scene_id": s, "budget": { "seconds": 0 } })),
        ("1e300 seconds", json!({ "scene_id": s, "budget": { "seconds": 1e300 } })),
        ("seconds \"NaN\"", json!({ "scene_id": s, "budget": { "seconds": "NaN" } })),
        ("target_psnr 1000", json!({ "scene_id": s, "budget": { "target_psnr": 1000 } })),
        ("an unknown model", json!({ "scene_id": s, "model": "x", "budget": { "steps": 1 } })),
        ("a model path", json!({ "scene_id": s, "model": "../../etc", "budget": { "steps": 1 } })),
        ("seed -1", json!({ "scene_id": s, "seed": -1, "budget": { "steps": 1 } })),
        ("batch_rays 0", json!({ "scene_id": s, "batch_rays": 0, "budget": { "steps": 1 } })),
        ("batch_rays 1e9", json!({ "scene_id": s, "batch_rays": 1_000_000_000, "budget": { "steps": 1 } })),
        ("masks x", json!({ "scene_id": s, "masks": "x", "budget": { "steps": 1 } })),
        ("an unknown field", json!({ "scene_id": s, "foo": 1, "budget": { "steps": 1 } })),
        ("a config of no kind", json!({ "scene_id": s, "config": {}, "budget": { "steps": 1 } })),
        ("a config of a wrong kind", json!({ "scene_id": s, "config": { "kind": "gan" }, "budget": { "steps": 1 } })),
        (
            "a config with huge fields",
            json!({ "scene_id": s, "model": "instant", "config": { "kind": "instant", "levels": 1_000_000, "log2_table": 60 }, "budget": { "steps": 1 } }),
        ),
    ] {
        bodies.push((format!("job with {what}"), budget_and_more.to_string()));
    }
    bodies.push(("a 3 MiB body".into(), format!("{{\"scene_id\": \"{}\"}}", "x".repeat(3 << 20))));
    bodies.push(("100000 nested arrays".into(), "[".repeat(100_000)));
    bodies.push(("a body of 1e400".into(), format!("{{\"scene_id\": \"{s}\", \"budget\": {{\"seconds\": 1e400}}}}")));
    for (name, body) in bodies {
        c.case(&name, REFUSED, jobs_json(body)).await;
    }
    let big = format!("{{\"scene_id\": \"{}\"}}", "x".repeat(16 << 20));
    c.case("a 16 MB JSON body", &[413, 0], jobs_json(big)).await;
    c.case("JSON as text/plain", REFUSED, cl.post(url("/v1/jobs")).header("content-type", "text/plain").body("{}"))
        .await;
    c.case("non-UTF-8 JSON", REFUSED, jobs_json(String::from_utf8_lossy(b"{\"scene_id\": \"\xff\xfe\"}").into())).await;

    let render = |q: &str| cl.get(url(&format!("/v1/models/{model}/render?{q}")));
    let c2w = |v: &[f64]| v.iter().map(|x| x.to_string()).collect::<Vec<_>>().join(",");
    let eye = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 3.0];
    let mut big_c2w = eye;
    big_c2w[3] = 1e308;
    let mut scaled = eye;
    scaled[0] = 1000.0;
    let renders: Vec<String> = vec![
        "width=0&height=64".into(),
        "width=100000&height=64".into(),
        "width=-1&height=64".into(),
        "width=8192&height=8192".into(),
        "width=abc".into(),
        "width=64&height=64&fov=0".into(),
        "width=64&height=64&fov=180".into(),
        "width=64&height=64&fov=NaN".into(),
        "width=64&height=64&elevation=91".into(),
        "width=64&height=64&radius=0".into(),
        "width=64&height=64&radius=-1".into(),
        "width=64&height=64&radius=1e308".into(),
        "width=64&height=64&radius=inf".into(),
        "width=64&height=64&azimuth=inf".into(),
        "width=64&height=64&azimuth=1e308".into(),
        format!("width=64&height=64&c2w={}", c2w(&eye[..11])),
        format!("width=64&height=64&c2w={}", c2w(&[&eye[..], &[0.0][..]].concat())),
        format!("width=64&height=64&c2w={}", c2w(&[&eye[..], &[0.0; 5][..]].concat())),
        format!("width=64&height=64&c2w={}", c2w(&big_c2w)),
        format!("width=64&height=64&c2w={}", c2w(&[1e308; 12])),
        format!("width=64&height=64&c2w={}", c2w(&[0.0; 12])),
        format!("width=64&height=64&c2w={}", c2w(&scaled)),
        format!("width=64&height=64&c2w=NaN,{}", c2w(&eye[1..])),
        format!("width=64&height=64&c2w=inf,{}", c2w(&eye[1..])),
        format!("width=64&height=64&c2w={}&azimuth=10", c2w(&eye)),
        "width=64&height=64&c2w=a,b,c".into(),
        "width=64&height=64&output=x".into(),
        "width=64&height=64&background=x".into(),
        "width=64&height=64&appearance=-1".into(),
        "width=64&height=64&appearance=99999999999999999999".into(),
        "width=64&height=64&appearance=../x".into(),
    ];
    for q in renders {
        c.case(&format!("render ?{}", q.chars().take(80).collect::<String>()), REFUSED, render(&q)).await;
    }
    c.case("render of an unknown model", &[404], cl.get(url("/v1/models/mdl_nope/render?width=16&height=16"))).await;
    // A render that is fine: the model answers.
    c.case("a 32x32 render", &[200], render("width=32&height=32")).await;

    let videos_post = |b: Value| cl.post(url(&format!("/v1/models/{model}/videos"))).json(&b);
    let kf = |c2w: Value| json!({ "c2w": c2w });
    let rows = json!([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3]]);
    let cam16: Vec<f64> = vec![1., 0., 0., 0., 0., 1., 0., 0., 0., 0., 1., 3., 0., 0., 0., 1.];
    let ns = |path: Value, more: Value| {
        let mut v = json!({ "camera_path": path, "render_width": 32, "render_height": 32, "fps": 10, "seconds": 1 });
        for (k, x) in more.as_object().unwrap() {
            v[k] = x.clone();
        }
        json!({ "path": v, "format": "gif" })
    };
    let one_ns = json!([{ "camera_to_world": cam16, "fov": 50, "aspect": 1 }]);
    let video_bodies: Vec<(&str, Value)> = vec![
        ("frames 0", json!({ "frames": 0 })),
        ("frames 601", json!({ "frames": 601 })),
        ("frames 1e9", json!({ "frames": 1_000_000_000 })),
        ("fps 0", json!({ "fps": 0 })),
        ("fps 61", json!({ "fps": 61 })),
        ("fps 1e9", json!({ "fps": 1_000_000_000 })),
        ("width 15", json!({ "width": 15, "height": 32 })),
        ("width 4097", json!({ "width": 4097, "height": 32 })),
        ("an odd MP4 width", json!({ "width": 17, "height": 32, "format": "mp4" })),
        ("4096x4096 at 600 frames", json!({ "width": 4096, "height": 4096, "frames": 600 })),
        ("format avi", json!({ "format": "avi" })),
        ("elevation 90", json!({ "elevation": 90 })),
        ("radius 0", json!({ "radius": 0 })),
        ("fov 0", json!({ "fov": 0 })),
        ("appearance x", json!({ "appearance": "x" })),
        ("an unknown field", json!({ "foo": 1 })),
        ("an empty path", json!({ "path": [] })),
        ("10001 keyframes", json!({ "path": vec![kf(rows.clone()); 10001] })),
        (
            "a keyframe of 11 numbers",
            json!({ "path": [kf(json!([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1])), kf(rows.clone())] }),
        ),
        (
            "a keyframe of 1e308",
            json!({ "path": [kf(json!([[1e308, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3]])), kf(rows.clone())] }),
        ),
        ("a keyframe of strings", json!({ "path": [kf(json!([["a", 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3]]))] })),
        (
            "a singular keyframe",
            json!({ "path": [kf(json!([[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 3]])), kf(rows.clone())] }),
        ),
        ("times decreasing", json!({ "path": [{ "c2w": rows, "time": 2 }, { "c2w": rows, "time": 1 }] })),
        ("times on some keyframes", json!({ "path": [{ "c2w": rows, "time": 0 }, { "c2w": rows }] })),
        ("path with elevation", json!({ "path": [kf(rows.clone()), kf(rows.clone())], "elevation": 10 })),
        ("keyframe fov 500", json!({ "path": [{ "c2w": rows, "fov": 500 }, kf(rows.clone())] })),
        ("nerfstudio, no cameras", ns(json!([]), json!({}))),
        ("nerfstudio, 15 numbers", ns(json!([{ "camera_to_world": &cam16[..15], "fov": 50 }]), json!({}))),
        ("nerfstudio fps 0", ns(one_ns.clone(), json!({ "fps": 0 }))),
        ("nerfstudio fps 1e9", ns(one_ns.clone(), json!({ "fps": 1e9 }))),
        ("nerfstudio seconds -1", ns(one_ns.clone(), json!({ "seconds": -1 }))),
        ("nerfstudio seconds 1e9", ns(one_ns.clone(), json!({ "seconds": 1e9 }))),
        ("nerfstudio render_width -1", ns(one_ns.clone(), json!({ "render_width": -1 }))),
        ("nerfstudio render_width 1e9", ns(one_ns.clone(), json!({ "render_width": 1_000_000_000 }))),
        ("nerfstudio fov -5", ns(json!([{ "camera_to_world": cam16, "fov": -5, "aspect": 1 }]), json!({}))),
        ("nerfstudio aspect 0", ns(json!([{ "camera_to_world": cam16, "fov": 50, "aspect": 0 }]), json!({}))),
        ("nerfstudio c2w 1e308", ns(json!([{ "camera_to_world": vec![1e308; 16], "fov": 50 }]), json!({}))),
    ];
    for (what, b) in video_bodies {
        c.case(&format!("video with {what}"), REFUSED, videos_post(b)).await;
    }
    c.case("video of an unknown model", &[404], cl.post(url("/v1/models/mdl_nope/videos")).json(&json!({}))).await;

    // ---- Other routes ----------------------------------------------------
    for p in [
        "/v1/scenes/scn_nope",
        "/v1/models/mdl_nope",
        "/v1/jobs/job_nope",
        "/v1/videos/vid_nope",
        "/v1/jobs/job_nope/events",
    ] {
        c.case(&format!("GET {p}"), &[404], cl.get(url(p))).await;
    }
    for p in ["/v1/scenes/scn_nope", "/v1/models/mdl_nope", "/v1/videos/vid_nope", "/v1/jobs/job_nope"] {
        c.case(&format!("DELETE {p}"), &[404], cl.delete(url(p))).await;
    }
    c.case("cancel an unknown job", &[404], cl.post(url("/v1/jobs/job_nope/cancel"))).await;
    c.case("cancel a finished job", &[409, 200], cl.post(url(&format!("/v1/jobs/{job}/cancel")))).await;
    c.case("delete a scene a model uses", &[409, 204], cl.delete(url(&format!("/v1/scenes/{scene}")))).await;
    c.case("PUT /v1/scenes", &[405], cl.put(url("/v1/scenes"))).await;
    c.case("PATCH /v1/jobs", &[405], cl.patch(url("/v1/jobs"))).await;

    // ---- Paths and HTTP as no library sends them -------------------------
    let get = |p: &str| format!("GET {p} HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n").into_bytes();
    let trav = [
        "/../../../../etc/passwd",
        "/%2e%2e/%2e%2e/%2e%2e/etc/passwd",
        "/assets/..%2f..%2f..%2f..%2fetc%2fpasswd",
        "/assets/../../../../etc/passwd",
        "/assets/%2e%2e%2f%2e%2e%2fCargo.toml",
        "/assets/..%5c..%5cCargo.toml",
        "/v1/scenes/..%2f..%2f..%2fetc%2fpasswd",
        "/v1/videos/..%2F..%2Fscenes",
        "/v1/models/%2e%2e%2fmodels/render?width=8&height=8",
        "//etc/passwd",
        "/v1/scenes/%00",
        "/index.html%00.js",
        "/assets/app.js%00",
    ];
    for p in trav {
        let leak = if p.contains("Cargo") { "[package]" } else { "root:x:0" };
        c.raw(&format!("GET {p}"), &addr, &[404, 400, 200, 301, 308], get(p), leak, false).await;
    }
    let long_id = format!("/v1/scenes/{}", "a".repeat(20000));
    c.raw("GET a 20000-byte scene id", &addr, &[404, 400, 414, 431, 0], get(&long_id), "", false).await;
    // Within hyper's limits (about 400 KB of headers) a request is served.
    let huge_header =
        format!("GET /healthz HTTP/1.1\r\nHost: x\r\nConnection: close\r\nX-A: {}\r\n\r\n", "a".repeat(200_000));
    c.raw("a 200 KB header", &addr, &[200, 431, 400, 0], huge_header.into_bytes(), "", false).await;
    let huge_header = format!("GET /healthz HTTP/1.1\r\nHost: x\r\nX-A: {}\r\n\r\n", "a".repeat(2_000_000));
    c.raw("a 2 MB header", &addr, &[431, 400, 0], huge_header.into_bytes(), "", false).await;
    let many: String = (0..5000).map(|k| format!("X-{k}: v\r\n")).collect();
    c.raw(
        "5000 headers",
        &addr,
        &[431, 400, 0],
        format!("GET /healthz HTTP/1.1\r\nHost: x\r\nConnection: close\r\n{many}\r\n").into_bytes(),
        "",
        false,
    )
    .await;
    for (what, req) in [
        (
            "Content-Length -1",
            "POST /v1/jobs HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: -1\r\n\r\n{}",
        ),
        (
            "a body shorter than its Content-Length",
            "POST /v1/jobs HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: 1000\r\n\r\n{\"a\":",
        ),
        (
            "a bad chunk",
            "POST /v1/jobs HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nTransfer-Encoding: chunked\r\n\r\nzz\r\n{}\r\n0\r\n\r\n",
        ),
        (
            "an upload declaring 1 TB",
            "POST /v1/scenes HTTP/1.1\r\nHost: x\r\nContent-Type: application/zip\r\nContent-Length: 1000000000000\r\n\r\nPK",
        ),
        (
            "an upload cut short",
            "POST /v1/scenes HTTP/1.1\r\nHost: x\r\nContent-Type: application/zip\r\nContent-Length: 100000\r\n\r\nPK\x03\x04",
        ),
        (
            "both Content-Length and chunked",
            "POST /v1/jobs HTTP/1.1\r\nHost: x\r\nContent-Length: 2\r\nTransfer-Encoding: chunked\r\n\r\n0\r\n\r\n",
        ),
        ("HTTP/0.9", "GET /\r\n"),
        ("garbage", "\x16\x03\x01\x02\x00\x01\x00\x01\x7f\x03\x03 hello"),
        ("an unknown method", "BREW /v1/jobs HTTP/1.1\r\nHost: x\r\n\r\n"),
        ("a request line of 100 KB", &format!("GET /{} HTTP/1.1\r\nHost: x\r\n\r\n", "a".repeat(100_000))),
    ] {
        let allowed = &[400, 404, 405, 408, 411, 413, 414, 415, 422, 431, 0];
        c.raw(&format!("raw: {what}"), &addr, allowed, req.as_bytes().to_vec(), "", true).await;
    }

    // ---- Authentication (a second server with a key) ---------------------
    let keyed_srv = c.start(&keyed, &["--api-key", "s3cret-key"]);
    let kb = keyed_srv.base.clone();
    let routes = [
        ("GET", "/v1/scenes"),
        ("POST", "/v1/scenes"),
        ("GET", "/v1/jobs"),
        ("POST", "/v1/jobs"),
        ("GET", "/v1/models"),
        ("GET", "/v1/models/mdl_x/render"),
        ("POST", "/v1/demo"),
        ("GET", "/metrics"),
    ];
    for (m, p) in routes {
        let req = |auth: Option<String>| {
            let r = cl.request(m.parse().unwrap(), format!("{kb}{p}"));
            match auth {
                Some(a) => r.header("authorization", a),
                None => r,
            }
        };
        c.case(&format!("{m} {p} without a key"), &[401], req(None)).await;
        c.case(&format!("{m} {p} with a wrong key"), &[401], req(Some("Bearer wrong".into()))).await;
        c.case(&format!("{m} {p} with the key's prefix"), &[401], req(Some("Bearer s3cret".into()))).await;
        c.case(
            &format!("{m} {p} with a 50 KB key"),
            &[401, 431, 400],
            req(Some(format!("Bearer {}", "k".repeat(50_000)))),
        )
        .await;
    }
    c.case("the key in the query", &[401], cl.get(format!("{kb}/v1/scenes?api_key=s3cret-key"))).await;
    c.case("the key as Basic", &[401], cl.get(format!("{kb}/v1/scenes")).header("authorization", "Basic s3cret-key"))
        .await;
    c.case("healthz without a key", &[200], cl.get(format!("{kb}/healthz"))).await;
    c.case("the right key", &[200], cl.get(format!("{kb}/v1/scenes")).header("authorization", "Bearer s3cret-key"))
        .await;
    c.stop(keyed_srv);

    // Nothing a refused request sent may be left, and nothing of an
    // archive written outside the data directory.
    for p in ["evil.png", "../evil.png", "tmp/evil.png"] {
        if root.path().join("data").join(p).exists() {
            c.t.wrong_2xx.push(format!("{p} was written"));
        }
    }
    if Path::new("/tmp/evil.png").exists() {
        c.t.wrong_2xx.push("/tmp/evil.png was written".into());
    }
    let bulk_cases = c.t.cases;
    eprintln!("{bulk_cases} request cases in {:.0} s", started.elapsed().as_secs_f64());
    c.kills_phase(&mut server, &data, &work).await;
    eprintln!("kills done at {:.0} s", started.elapsed().as_secs_f64());

    // Every job final; then what is left.
    let (_, jobs) = get_json(&c.client, &format!("{}/v1/jobs", server.base)).await;
    for j in jobs.as_array().cloned().unwrap_or_default() {
        let id = j["id"].as_str().unwrap().to_string();
        c.wait_job(&server.base, &id, 300.0, is_final).await;
    }
    let (_, scenes) = get_json(&c.client, &format!("{}/v1/scenes", server.base)).await;
    let ids: Vec<String> =
        scenes.as_array().cloned().unwrap_or_default().iter().map(|s| s["id"].as_str().unwrap().to_string()).collect();
    c.stop(server);
    for l in leftovers_in(&data, &ids).into_iter().chain(leftovers_in(&keyed, &[])) {
        c.t.leftovers.push(l);
    }
    for (pid, cmd) in processes_in(root.path(), true) {
        c.t.orphans.push(format!("after the servers stopped: {pid} {cmd}"));
    }
    stop.store(true, Ordering::Relaxed);
    sampler.join().unwrap();

    let panics: Vec<String> = c
        .logs
        .iter()
        .flat_map(|l| std::fs::read_to_string(l).unwrap_or_default().lines().map(str::to_string).collect::<Vec<_>>())
        .filter(|l| l.contains("panicked"))
        .collect();
    let t = &c.t;
    let mib = |b: u64| format!("{:.0} MiB", b as f64 / (1 << 20) as f64);
    println!("\n| What | Count |\n| --- | --- |");
    println!("| cases tried (requests, uploads) | {} |", t.cases);
    println!("| kill -9s of the server | {} |", t.kills);
    println!("| 5xx answers | {} |", t.answers_5xx.len());
    println!("| panics (stderr lines saying \"panicked\") | {} |", panics.len());
    println!("| hangs | {} |", t.hangs.len());
    println!("| wrong 2xx answers | {} |", t.wrong_2xx.len());
    println!("| leftovers (folders, files) | {} |", t.leftovers.len());
    println!("| orphans (processes) | {} |", t.orphans.len());
    println!("| jobs of the kill runs that did not end as they should | {} |", t.jobs.len());
    println!("| peak RSS, servers | {} |", mib(c.peak_server.load(Ordering::Relaxed)));
    println!(
        "| peak RSS, their children (sampled every 100 ms) | {} ({}) |",
        mib(c.peak_child.load(Ordering::Relaxed)),
        c.peak_child_name.lock().unwrap()
    );
    println!("| refusals with another 4xx than expected (listed) | {} |", t.other.len());
    println!("| wall time | {:.0} s |", started.elapsed().as_secs_f64());
    for (what, list) in [
        ("5xx", &t.answers_5xx),
        ("panics", &panics),
        ("hangs", &t.hangs),
        ("wrong 2xx", &t.wrong_2xx),
        ("leftovers", &t.leftovers),
        ("orphans", &t.orphans),
        ("jobs", &t.jobs),
        ("other", &t.other),
    ] {
        for x in list {
            println!("{what}: {x}");
        }
    }
    let failures = t.answers_5xx.len()
        + panics.len()
        + t.hangs.len()
        + t.wrong_2xx.len()
        + t.leftovers.len()
        + t.orphans.len()
        + t.jobs.len();
    assert_eq!(failures, 0, "the campaign found problems (listed above)");
    assert!(c.peak_server.load(Ordering::Relaxed) < 500 << 20, "a server's peak RSS is over 500 MB");
}

async fn get_json(cl: &reqwest::Client, url: &str) -> (u16, Value) {
    match cl.get(url).timeout(Duration::from_secs(30)).send().await {
        Ok(r) => (r.status().as_u16(), r.json().await.unwrap_or(Value::Null)),
        Err(_) => (0, Value::Null),
    }
}

/// Cancels the poses job of an upload's answer, at once.
async fn cancel(c: &mut Campaign, base: &str, upload: &Value) {
    let Some(job) = upload["poses"]["job_id"].as_str() else { return };
    let r = c.client.post(format!("{base}/v1/jobs/{job}/cancel")).send().await;
    c.t.cases += 1;
    match r {
        Ok(r) => {
            let s = r.status().as_u16();
            c.judge(&format!("cancel poses job {job}"), &[200, 202, 409], s, "");
        }
        Err(e) => c.t.hangs.push(format!("cancel {job}: {e}")),
    }
    let done = c.wait_job(base, job, 60.0, is_final).await;
    if done["status"] != "canceled" && done["status"] != "failed" && done["status"] != "succeeded" {
        c.t.jobs.push(format!("poses job {job} after its cancel: {done}"));
    }
}

impl Campaign {
    /// Holds the program of a poses job's `stage` still once it runs
    /// (`common::procs::freeze_at`), so that the kill after it lands in
    /// that stage on any machine.
    async fn hold(&self, base: &str, data: &Path, job: &str, stage: &str) {
        let (client, url) = (self.client.clone(), format!("{base}/v1/jobs/{job}"));
        common::procs::freeze_at(data, stage, async || is_final(&get_json(&client, &url).await.1)).await;
    }

    /// The kills: at each stage of a photo-only upload's poses job, three
    /// in a row at different stages, during a video upload's frame
    /// extraction, twice during a rendered video, during training, twice
    /// in one stage (the job fails, and leaves nothing), during an upload
    /// in flight and during an upload's video probe.
    async fn kills_phase(&mut self, server: &mut Server, data: &Path, work: &Path) {
        // The queue empty first: the kills need the poses jobs running.
        let (_, jobs) = get_json(&self.client, &format!("{}/v1/jobs", server.base)).await;
        for j in jobs.as_array().cloned().unwrap_or_default() {
            let id = j["id"].as_str().unwrap().to_string();
            self.wait_job(&server.base, &id, 300.0, is_final).await;
        }
        let sixteen = zip_of(&photos_at(16, 320, 240));
        let upload = |c: &Campaign, s: &Server, body: Vec<u8>| {
            c.client.post(format!("{}/v1/scenes", s.base)).header("content-type", "application/zip").body(body)
        };
        // Once at each stage.
        for stage in ["feature extraction", "matching", "mapping"] {
            let (_, v) = self
                .case(&format!("16 photos (killed in {stage})"), &[201], upload(self, server, sixteen.clone()))
                .await;
            let job = v["poses"]["job_id"].as_str().unwrap_or("none").to_string();
            self.hold(&server.base, data, &job, stage).await;
            let at = |j: &Value| j["status"] == "running" && j["progress"]["stage"] == stage || is_final(j);
            self.wait_job(&server.base, &job, 180.0, at).await;
            self.kill(server, data, &format!("during {stage}"));
            *server = self.start(data, &[]);
            let done = self.wait_job(&server.base, &job, 300.0, is_final).await;
            if done["status"] != "succeeded" {
                self.t.jobs.push(format!("killed in {stage}: {done}"));
            }
        }
        // Three in a row at different stages of one job.
        let (_, v) = self.case("16 photos (killed three times)", &[201], upload(self, server, sixteen.clone())).await;
        let job = v["poses"]["job_id"].as_str().unwrap_or("none").to_string();
        for (attempt, stage) in [(1u64, "feature extraction"), (2, "matching"), (3, "mapping")] {
            self.hold(&server.base, data, &job, stage).await;
            let at = |j: &Value| {
                j["status"] == "running" && j["attempts"] == attempt && j["progress"]["stage"] == stage || is_final(j)
            };
            self.wait_job(&server.base, &job, 180.0, at).await;
            self.kill(server, data, &format!("three in a row: {stage}"));
            *server = self.start(data, &[]);
        }
        let done = self.wait_job(&server.base, &job, 300.0, is_final).await;
        if done["status"] != "succeeded" {
            self.t.jobs.push(format!("killed three times: {done}"));
        }
        // A video upload, during frame extraction.
        let clip = walk_mp4(work, 48);
        let form = form_of(&[("walk.mp4".into(), clip.clone())], true);
        let req = self.client.post(format!("{}/v1/scenes", server.base)).multipart(form);
        let (_, v) = self.case("a walk video (killed extracting frames)", &[201], req).await;
        let job = v["poses"]["job_id"].as_str().unwrap_or("none").to_string();
        self.hold(&server.base, data, &job, "extracting video frames").await;
        let at =
            |j: &Value| j["status"] == "running" && j["progress"]["stage"] == "extracting video frames" || is_final(j);
        self.wait_job(&server.base, &job, 120.0, at).await;
        self.kill(server, data, "during video frame extraction");
        *server = self.start(data, &[]);
        let done = self.wait_job(&server.base, &job, 300.0, is_final).await;
        if done["status"] != "succeeded" {
            self.t.jobs.push(format!("video killed extracting frames: {done}"));
        }
        // A rendered video, twice; then training, once.
        let (_, v) =
            self.case("the ball scene (for the kills)", &[201], upload(self, server, zip_of(&ball_files()))).await;
        let scene = v["id"].as_str().unwrap_or("none").to_string();
        let body = json!({ "scene_id": scene, "budget": { "steps": 20 } });
        let (_, v) = self
            .case(
                "a 20-step job (for the kills)",
                &[202],
                self.client.post(format!("{}/v1/jobs", server.base)).json(&body),
            )
            .await;
        let done = self.wait_job(&server.base, v["id"].as_str().unwrap_or("none"), 120.0, is_final).await;
        let model = done["model_id"].as_str().unwrap_or("none").to_string();
        let body = json!({ "frames": 60, "fps": 10, "width": 64, "height": 64, "format": "gif" });
        let req = self.client.post(format!("{}/v1/models/{model}/videos", server.base)).json(&body);
        let (_, v) = self.case("a 60-frame video (killed twice)", &[202], req).await;
        let job = v["id"].as_str().unwrap_or("none").to_string();
        for (attempt, at_least) in [(1u64, 5u64), (2, 25)] {
            let at = |j: &Value| {
                j["status"] == "running" && j["attempts"] == attempt && j["progress"]["step"].as_u64() >= Some(at_least)
                    || is_final(j)
            };
            self.wait_job(&server.base, &job, 300.0, at).await;
            self.kill(server, data, &format!("rendering a video (attempt {attempt})"));
            *server = self.start(data, &[]);
        }
        let done = self.wait_job(&server.base, &job, 300.0, is_final).await;
        if done["status"] != "succeeded" {
            self.t.jobs.push(format!("video killed twice: {done}"));
        }
        let body = json!({ "scene_id": scene, "budget": { "steps": 300 } });
        let (_, v) = self
            .case("a 300-step job (killed)", &[202], self.client.post(format!("{}/v1/jobs", server.base)).json(&body))
            .await;
        let job = v["id"].as_str().unwrap_or("none").to_string();
        let at = |j: &Value| j["model_id"].is_string() && j["progress"]["step"].as_u64() >= Some(10) || is_final(j);
        self.wait_job(&server.base, &job, 300.0, at).await;
        self.kill(server, data, "during training");
        *server = self.start(data, &[]);
        let done = self.wait_job(&server.base, &job, 180.0, is_final).await;
        if done["status"] != "succeeded" {
            self.t.jobs.push(format!("training killed: {done}"));
        }
        // Twice in the same stage: the job fails, leaving no folder.
        let (_, v) =
            self.case("16 photos (killed twice in matching)", &[201], upload(self, server, sixteen.clone())).await;
        let job = v["poses"]["job_id"].as_str().unwrap_or("none").to_string();
        for attempt in 1..=2u64 {
            self.hold(&server.base, data, &job, "matching").await;
            let at = |j: &Value| j["attempts"] == attempt && j["progress"]["stage"] == "matching" || is_final(j);
            self.wait_job(&server.base, &job, 180.0, at).await;
            self.kill(server, data, &format!("twice in matching ({attempt})"));
            *server = self.start(data, &[]);
        }
        let done = self.wait_job(&server.base, &job, 60.0, is_final).await;
        if done["status"] != "failed" {
            self.t.jobs.push(format!("killed twice in matching (should fail): {done}"));
        }
        // An upload in flight: half of its body sent.
        {
            let half = sixteen[..sixteen.len() / 2].to_vec();
            let head = format!(
                "POST /v1/scenes HTTP/1.1\r\nHost: x\r\nContent-Type: application/zip\r\nContent-Length: {}\r\n\r\n",
                sixteen.len()
            );
            let mut conn = std::net::TcpStream::connect(&server.addr).unwrap();
            conn.write_all(head.as_bytes()).unwrap();
            conn.write_all(&half).unwrap();
            self.t.cases += 1;
            std::thread::sleep(Duration::from_millis(500));
            self.kill(server, data, "during an upload in flight");
            drop(conn);
            *server = self.start(data, &[]);
        }
        // During an upload's video probe (a longer video decoded at upload).
        {
            let long = mp4(work, "long.mp4", "testsrc", "640x480", 1200);
            let form = form_of(&[("clip/long.mp4".into(), long)], true);
            let req = self.client.post(format!("{}/v1/scenes", server.base)).multipart(form).send();
            let probe = tokio::spawn(req);
            self.t.cases += 1;
            let t = Instant::now();
            while processes_in(data, false).is_empty() && t.elapsed() < Duration::from_secs(20) {
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
            if processes_in(data, false).is_empty() {
                eprintln!("no ffprobe/ffmpeg seen during the upload's probe; killed anyway");
            }
            self.kill(server, data, "during an upload's video probe");
            let _ = probe.await;
            *server = self.start(data, &[]);
        }
        self.note_peak(server);
    }
}
