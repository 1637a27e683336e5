//! Uploads as a hostile client sends them (issue 35), against the real
//! server binary with the real COLMAP and ffmpeg: decompression bombs
//! refused from their headers at upload (the server's peak memory read from
//! /proc), photos that cannot be posed refused at upload, the poses job's
//! memory estimate following its input. A server killed (-9) at any stage
//! leaves no process and no folder, and every server here stays under 500
//! MB (its peak RSS, checked before each kill and at the end) and never
//! panics (its stderr, read when it is dropped).

use std::path::Path;

use radiance::engine::dataset::textured::TexturedScene;
use reqwest::StatusCode;
use serde_json::Value;

use crate::common::poses::bomb_png;
use crate::common::procs::{freeze_at as freeze_at_stage, processes_in, wait_until_gone};
use crate::common::*;

/// The textured scene's photos (no poses) at `w`x`h`, under `photos/`.
fn photos_at(views: usize, width: u32, height: u32) -> Vec<(String, Vec<u8>)> {
    let d = tempfile::tempdir().unwrap();
    TexturedScene { views, width, height, ..Default::default() }.write_photos(d.path()).unwrap();
    files(d.path()).into_iter().map(|(n, b)| (format!("photos/{n}"), b)).collect()
}

fn png(w: u32, h: u32) -> Vec<u8> {
    let img = image::RgbImage::from_fn(w, h, |x, y| image::Rgb([(x * 13) as u8, (y * 7) as u8, 99]));
    let mut out = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut out), image::ImageFormat::Png).unwrap();
    out
}

fn message(v: &Value) -> &str {
    v["error"]["message"].as_str().unwrap_or_default()
}

/// The most memory a server may have held at its peak.
const MAX_PEAK_RSS: u64 = 500 << 20;

struct Server {
    child: Served,
    svc: Svc,
}

impl Server {
    fn start(data: &Path) -> Self {
        let (child, base) = spawn_binary_with(data, &[]);
        Self { child, svc: Svc::remote(base) }
    }

    /// Asserts the server's peak memory so far is under [`MAX_PEAK_RSS`].
    fn assert_peak_rss(&self) {
        let peak = self.child.peak_rss();
        eprintln!("server peak RSS {} MiB", peak >> 20);
        assert!(peak < MAX_PEAK_RSS, "server peak RSS {} MiB", peak >> 20);
    }

    /// kill -9 (no chance to clean up), once its peak memory is checked.
    fn kill(&mut self) {
        self.assert_peak_rss();
        self.child.kill().unwrap();
        self.child.wait().unwrap();
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bombs_and_unposable_photos_are_refused_at_upload_from_their_headers() {
    let data = tempfile::tempdir().unwrap();
    let server = Server::start(data.path());
    let svc = &server.svc;
    let three = photos_at(3, 320, 240);

    // Photo-only uploads with a PNG of a few KB declaring 30000x30000 (2.7
    // GB decoded) or 100000x100000 (30 GB): 422 at upload, naming it.
    for (w, h) in [(30000, 30000), (20000, 20000), (100000, 100000)] {
        let mut files = three.clone();
        files.push(("photos/bomb.png".into(), bomb_png(w, h)));
        assert!(files[3].1.len() < 20_000);
        for (s, v) in
            [svc.upload("application/zip", zip_of(&files)).await, svc.upload_form(form_of(&files, true)).await]
        {
            assert_eq!(s, StatusCode::UNPROCESSABLE_ENTITY, "{v}");
            assert_error(&v, "invalid_dataset");
            let m = message(&v);
            assert!(m.contains("photos/bomb.png") && m.contains(&format!("{w}x{h} pixels")), "{m}");
            assert!(m.contains("more than the 50 megapixels"), "{m}");
        }
    }
    // A posed dataset (Blender) with a bomb among its images: refused before
    // the loader decodes it.
    let mut ball = ball_files();
    let k = ball.iter().position(|(n, _)| n.ends_with(".png")).unwrap();
    ball[k].1 = bomb_png(30000, 30000);
    let (s, v) = svc.upload("application/zip", zip_of(&ball)).await;
    assert_eq!(s, StatusCode::UNPROCESSABLE_ENTITY, "{v}");
    assert!(message(&v).contains(&ball[k].0) && message(&v).contains("30000x30000"), "{v}");

    // Photos the job would refuse a second later are refused now: mixed
    // sizes (one turned), and a 1x1 photo.
    let mut mixed = photos_at(4, 320, 240);
    mixed[3].1 = png(240, 320);
    let (s, v) = svc.upload("application/zip", zip_of(&mixed)).await;
    assert_eq!(s, StatusCode::UNPROCESSABLE_ENTITY, "{v}");
    let m = message(&v);
    assert!(m.contains("2 different sizes") && m.contains("1 at 240x320 (e.g. photos/view_003.png)"), "{m}");
    let mut tiny = three.clone();
    tiny.push(("photos/dot.png".into(), png(1, 1)));
    let (s, v) = svc.upload("application/zip", zip_of(&tiny)).await;
    assert_eq!(s, StatusCode::UNPROCESSABLE_ENTITY, "{v}");
    assert!(message(&v).contains("'photos/dot.png' is 1x1 pixels"), "{v}");
    assert_no_scene_files(data.path());

    // The poses job's memory estimate follows the photos: 1280x960 ones
    // count 16 times the decoding memory of 320x240 ones.
    let mut estimates = Vec::new();
    for (w, h) in [(320, 240), (1280, 960)] {
        let (s, v) = svc.upload("application/zip", zip_of(&photos_at(3, w, h))).await;
        assert_eq!(s, StatusCode::CREATED, "{v}");
        let (_, job) = svc.get(&format!("/v1/jobs/{}", v["poses"]["job_id"].as_str().unwrap())).await;
        estimates.push(job["memory_estimate_bytes"].as_u64().unwrap());
    }
    let base = radiance::jobs::poses::MEMORY_ESTIMATE_BYTES;
    let (small, large) = (estimates[0] - base, estimates[1] - base);
    assert!(small >= 320 * 240 * 3 * 3 && large == small * 16, "{estimates:?}");

    // Through all of it the server stayed small (bombs decoded would have
    // taken gigabytes).
    server.assert_peak_rss();
}

/// What a scene's folder holds besides `data/`, `upload/` and `scene.json`:
/// working folders and process lists a job left.
fn leftovers(data: &Path, scene: &str) -> Vec<String> {
    std::fs::read_dir(data.join("scenes").join(scene))
        .map(|d| {
            d.flatten()
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .filter(|n| !["data", "upload", "scene.json"].contains(&n.as_str()))
                .collect()
        })
        .unwrap_or_default()
}

/// Holds the program of `stage` still once it runs (`procs::freeze_at`),
/// failing if `job` ends first.
async fn freeze_at(svc: &Svc, dir: &Path, job: &str, stage: &str) -> i32 {
    freeze_at_stage(dir, stage, async || is_final(&svc.get(&format!("/v1/jobs/{job}")).await.1)).await
}

fn is_final(v: &Value) -> bool {
    ["succeeded", "failed", "canceled"].contains(&v["status"].as_str().unwrap_or(""))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_server_killed_at_each_stage_of_colmap_leaves_no_process_and_no_folder() {
    let data = tempfile::tempdir().unwrap();
    let mut server = Server::start(data.path());
    for stage in ["feature extraction", "matching", "mapping"] {
        let (s, v) = server.svc.upload("application/zip", zip_of(&photos_at(16, 320, 240))).await;
        assert_eq!(s, StatusCode::CREATED, "{v}");
        let (id, job) = (v["id"].as_str().unwrap().to_string(), v["poses"]["job_id"].as_str().unwrap().to_string());
        let pid = freeze_at(&server.svc, data.path(), &job, stage).await;
        // COLMAP held where it is: the job reports this stage (its report is
        // written before COLMAP starts, so this waits on nothing but the poll).
        server.svc.wait_job(&job, 60.0, |j| j["status"] == "running" && j["progress"]["stage"] == stage).await;
        eprintln!("killing the server with COLMAP's {stage} (pid {pid}) stopped");
        server.kill();
        wait_until_gone(data.path(), &format!("during {stage}"));
        // The next start runs the job again to its end and leaves nothing
        // of the first run.
        server = Server::start(data.path());
        let done = server.svc.wait_job(&job, 180.0, is_final).await;
        assert_eq!((done["status"].as_str(), done["crashes"].as_u64()), (Some("succeeded"), Some(1)), "{done}");
        let (_, sc) = server.svc.get(&format!("/v1/scenes/{id}")).await;
        assert_eq!(sc["status"], "ready", "{sc}");
        assert!(leftovers(data.path(), &id).is_empty(), "{:?}", leftovers(data.path(), &id));
        assert!(processes_in(data.path()).is_empty(), "{:?}", processes_in(data.path()));
    }
    server.assert_peak_rss();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_poses_job_failed_at_start_up_leaves_no_folder() {
    let data = tempfile::tempdir().unwrap();
    let mut server = Server::start(data.path());
    let (s, v) = server.svc.upload("application/zip", zip_of(&photos_at(16, 320, 240))).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    let (id, job) = (v["id"].as_str().unwrap().to_string(), v["poses"]["job_id"].as_str().unwrap().to_string());
    // Killed twice in the same stage: the job fails at the next start, as
    // one that takes the server down would.
    // The matcher is held (stopped) when seen, so that the kill lands in
    // matching and not after it saved its stage, however slow the machine.
    for attempt in 1..=2u64 {
        freeze_at(&server.svc, data.path(), &job, "matching").await;
        let at_work = |j: &Value| j["attempts"] == attempt && j["progress"]["stage"] == "matching";
        server.svc.wait_job(&job, 60.0, at_work).await;
        assert!(!leftovers(data.path(), &id).is_empty(), "no working folder while COLMAP runs");
        server.kill();
        wait_until_gone(data.path(), "during matching");
        server = Server::start(data.path());
    }
    let (_, j) = server.svc.get(&format!("/v1/jobs/{job}")).await;
    assert_eq!(j["status"], "failed", "{j}");
    let (_, sc) = server.svc.get(&format!("/v1/scenes/{id}")).await;
    assert_eq!(sc["status"], "failed", "{sc}");
    assert!(leftovers(data.path(), &id).is_empty(), "{:?}", leftovers(data.path(), &id));
    assert!(processes_in(data.path()).is_empty(), "{:?}", processes_in(data.path()));
    server.assert_peak_rss();
}

/// An MP4 (H.264) of `frames` frames of ffmpeg's `source` at 12 fps,
/// 320x240.
fn mp4(dir: &Path, name: &str, source: &str, frames: u32, faststart: bool) -> Vec<u8> {
    mp4_sized(dir, name, source, "320x240", frames, faststart)
}

fn mp4_sized(dir: &Path, name: &str, source: &str, size: &str, frames: u32, faststart: bool) -> Vec<u8> {
    let path = dir.join(name);
    let mut cmd = std::process::Command::new("ffmpeg");
    cmd.args([
        "-loglevel",
        "error",
        "-y",
        "-f",
        "lavfi",
        "-i",
        &format!("{source}{}size={size}:rate=12", if source.contains('=') { ":" } else { "=" }),
    ]);
    cmd.args(["-frames:v", &frames.to_string(), "-c:v", "libx264", "-pix_fmt", "yuv420p"]);
    if faststart {
        cmd.args(["-movflags", "+faststart"]);
    }
    assert!(cmd.arg(&path).status().unwrap().success());
    std::fs::read(path).unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn videos_that_cannot_give_views_are_refused_at_upload_saying_why() {
    let data = tempfile::tempdir().unwrap();
    let server = Server::start(data.path());
    let svc = &server.svc;
    let dir = tempfile::tempdir().unwrap();
    let good = mp4(dir.path(), "good.mp4", "testsrc", 48, true);
    let cases: Vec<(&str, Vec<u8>, &str)> = vec![
        ("empty.mp4", Vec::new(), "is not a video ffmpeg can read"),
        ("notes.mp4", b"just some text, not a video\n".to_vec(), "is not a video ffmpeg can read"),
        ("cut.mp4", good[..good.len() / 2].to_vec(), "is cut short: its index lists 48 frames, the file holds"),
        ("one.mp4", mp4(dir.path(), "one.mp4", "testsrc", 1, false), "has 1 distinct frame; pose estimation"),
        ("still.mp4", mp4(dir.path(), "still.mp4", "color=c=gray", 48, false), "has 1 distinct frame (48 in all"),
        (
            "tiny.mp4",
            mp4_sized(dir.path(), "tiny.mp4", "testsrc", "16x16", 48, false),
            "has frames of 16x16 pixels; pose estimation needs frames at least 32 pixels",
        ),
    ];
    for (name, bytes, says) in cases {
        let t = std::time::Instant::now();
        let (s, v) = svc.upload_form(form_of(&[(format!("clip/{name}"), bytes)], true)).await;
        assert_eq!(s, StatusCode::UNPROCESSABLE_ENTITY, "{name}: {v}");
        assert_error(&v, "invalid_dataset");
        let m = message(&v);
        assert!(m.contains(&format!("'clip/{name}'")) && m.contains(says), "{name}: {m}");
        assert!(!m.contains(&data.path().display().to_string()), "a server path in {m}");
        assert!(t.elapsed().as_secs_f64() < 20.0, "{name} took {:?}", t.elapsed());
    }
    assert_no_scene_files(data.path());
    // A real one is taken, its job counted for decoding its frames.
    let (s, v) = svc.upload_form(form_of(&[("clip/good.mp4".into(), good)], true)).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    let (_, job) = svc.get(&format!("/v1/jobs/{}", v["poses"]["job_id"].as_str().unwrap())).await;
    let base = radiance::jobs::poses::MEMORY_ESTIMATE_BYTES;
    assert_eq!(job["memory_estimate_bytes"].as_u64(), Some(base + 320 * 240 * 3 / 2 * 40), "{job}");
    server.assert_peak_rss();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn smaller_holes_answer_as_documented() {
    let data = tempfile::tempdir().unwrap();
    let server = Server::start(data.path());
    let svc = &server.svc;

    // A JSON body over 2 MiB (the issue sent 16 MB): 413 as openapi.yaml
    // says, with the limit. Just over it, so that what the server leaves
    // unread fits in the sockets' buffers and the client reads the answer.
    let big = format!("{{\"scene_id\": \"{}\"}}", "x".repeat((2 << 20) + (32 << 10)));
    let r = svc.client.post(svc.url("/v1/jobs")).header("content-type", "application/json").body(big).send().await;
    let r = r.unwrap();
    assert_eq!(r.status(), StatusCode::PAYLOAD_TOO_LARGE);
    let v: Value = r.json().await.unwrap();
    assert_error(&v, "payload_too_large");
    assert_eq!(v["error"]["details"]["limit_bytes"], 2 << 20, "{v}");

    // A zip naming one entry twice is refused, as multipart is.
    let mut files = ball_files();
    let pngs: Vec<usize> = (0..files.len()).filter(|&i| files[i].0.ends_with(".png")).collect();
    let (i, j) = pngs
        .iter()
        .flat_map(|&i| pngs.iter().map(move |&j| (i, j)))
        .find(|&(i, j)| i < j && files[i].0.len() == files[j].0.len())
        .unwrap();
    let (a, b) = (files[i].0.clone(), files[j].0.clone());
    files[j].1 = files[i].1.clone();
    let mut zip = zip_of(&files);
    let at: Vec<usize> = (0..zip.len() - b.len()).filter(|&i| zip[i..i + b.len()] == *b.as_bytes()).collect();
    for i in at {
        zip[i..i + b.len()].copy_from_slice(a.as_bytes());
    }
    let (s, v) = svc.upload("application/zip", zip).await;
    assert_eq!(s, StatusCode::BAD_REQUEST, "{v}");
    assert!(message(&v).contains(&format!("archive entry '{a}' appears twice")), "{v}");

    // Names longer than the file system takes (255 bytes a name, 1024 in
    // all) are the client's error, named, not the server's.
    let long = format!("images/{}.png", "n".repeat(1000));
    let (s, v) = svc.upload("application/zip", zip_of(&[(long, png(8, 8))])).await;
    assert_eq!(s, StatusCode::BAD_REQUEST, "{v}");
    assert!(message(&v).contains("longer than 255 bytes"), "{v}");
    let (s, v) = svc.upload_form(form_of(&[(format!("{}.png", "q".repeat(5000)), png(8, 8))], true)).await;
    assert_eq!(s, StatusCode::BAD_REQUEST, "{v}");
    assert!(message(&v).contains("5004 bytes long, more than 1024"), "{v}");

    // A photo whose header is whole and data cut short fails in its job,
    // which names it as uploaded, not by the server's folders.
    let mut photos = photos_at(3, 320, 240);
    let cut = photos[1].1.len() / 2;
    photos[1].1.truncate(cut);
    let (s, v) = svc.upload("application/zip", zip_of(&photos)).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    let job = svc.wait_job(v["poses"]["job_id"].as_str().unwrap(), 60.0, is_final).await;
    let err = job["error"].as_str().unwrap_or_default();
    assert_eq!(job["status"], "failed", "{job}");
    assert!(err.contains(&format!("photo '{}' cannot be decoded", photos[1].0)), "{err}");
    let (_, sc) = svc.get(&format!("/v1/scenes/{}", v["id"].as_str().unwrap())).await;
    let root = data.path().display().to_string();
    assert!(!err.contains(&root) && !sc["error"].as_str().unwrap().contains(&root), "{err} / {sc}");
    server.assert_peak_rss();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn three_kills_in_a_row_at_different_stages_cost_a_stage_each_not_the_job() {
    let data = tempfile::tempdir().unwrap();
    let mut server = Server::start(data.path());
    let (s, v) = server.svc.upload("application/zip", zip_of(&photos_at(16, 320, 240))).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    let (id, job) = (v["id"].as_str().unwrap().to_string(), v["poses"]["job_id"].as_str().unwrap().to_string());
    for (attempt, stage) in [(1u64, "feature extraction"), (2, "matching"), (3, "mapping")] {
        // COLMAP held at the stage, so the kill lands in it on any machine.
        freeze_at(&server.svc, data.path(), &job, stage).await;
        let at = |j: &Value| j["status"] == "running" && j["attempts"] == attempt && j["progress"]["stage"] == stage;
        server.svc.wait_job(&job, 60.0, at).await;
        server.kill();
        wait_until_gone(data.path(), &format!("during {stage}"));
        server = Server::start(data.path());
        let (_, j) = server.svc.get(&format!("/v1/jobs/{job}")).await;
        // A stage was finished since the last start: progress, not a crash in a row.
        assert!(j["status"] != "failed" && j["crashes"] == 1, "{j}");
    }
    let done = server.svc.wait_job(&job, 180.0, is_final).await;
    assert_eq!((done["status"].as_str(), done["attempts"].as_u64()), (Some("succeeded"), Some(4)), "{done}");
    let (_, sc) = server.svc.get(&format!("/v1/scenes/{id}")).await;
    assert_eq!(sc["status"], "ready", "{sc}");
    // The last run mapped only: features and matching were kept from the
    // runs before (0 s in this run), not done again.
    let secs = &sc["poses"]["report"]["seconds"];
    assert_eq!((secs["features"].as_f64(), secs["matching"].as_f64()), (Some(0.0), Some(0.0)), "{sc}");
    assert!(secs["mapping"].as_f64().unwrap() > 0.0, "{sc}");
    assert!(leftovers(data.path(), &id).is_empty(), "{:?}", leftovers(data.path(), &id));
    assert!(processes_in(data.path()).is_empty(), "{:?}", processes_in(data.path()));
    server.assert_peak_rss();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_video_job_killed_twice_keeps_its_frames_and_finishes() {
    let data = tempfile::tempdir().unwrap();
    let mut server = Server::start(data.path());
    let scene = server.svc.upload_ball().await;
    let train = server.svc.job(&scene, serde_json::json!({ "steps": 20 })).await;
    let trained = server.svc.wait_job(&train, 120.0, is_final).await;
    assert_eq!(trained["status"], "succeeded", "{trained}");
    let model = trained["model_id"].as_str().unwrap().to_string();
    let body = serde_json::json!({ "frames": 120, "fps": 10, "width": 96, "height": 96, "format": "gif" });
    let (s, v) = server.svc.post_json(&format!("/v1/models/{model}/videos"), body).await;
    assert_eq!(s, StatusCode::ACCEPTED, "{v}");
    let job = v["id"].as_str().unwrap().to_string();
    let frames_dir = data.path().join("videos").join(format!(".frames-{job}"));
    // The second life must render frames of its own before its kill (it
    // starts from those the first saved, whose count a late kill raises).
    let mut at_least = 10u64;
    for attempt in 1..=2u64 {
        let at = |j: &Value| {
            j["status"] == "running" && j["attempts"] == attempt && j["progress"]["step"].as_u64() >= Some(at_least)
        };
        server.svc.wait_job(&job, 120.0, at).await;
        server.kill();
        // The frames rendered so far are on disk, each a whole PNG.
        assert!(frames_dir.is_dir(), "the video finished before its kill {attempt}");
        let saved = std::fs::read_dir(&frames_dir).unwrap().count() as u64;
        assert!(saved >= at_least && saved + 10 < 120, "{saved} frames saved (of 120) at kill {attempt}");
        at_least = saved + 10;
        server = Server::start(data.path());
        let (_, j) = server.svc.get(&format!("/v1/jobs/{job}")).await;
        // Frames saved since the last start: progress, not a crash in a row.
        assert!(j["status"] != "failed" && j["crashes"] == 1, "{j}");
    }
    let done = server.svc.wait_job(&job, 180.0, is_final).await;
    assert_eq!((done["status"].as_str(), done["attempts"].as_u64()), (Some("succeeded"), Some(3)), "{done}");
    assert_eq!(done["progress"]["step"], 120, "{done}");
    assert!(!frames_dir.exists(), "the saved frames outlived their job");
    let r = server.svc.client.get(server.svc.url(&format!("/v1/videos/{}", done["video_id"].as_str().unwrap())));
    let bytes = r.send().await.unwrap().bytes().await.unwrap();
    let gif = image::codecs::gif::GifDecoder::new(std::io::Cursor::new(&bytes[..])).unwrap();
    use image::AnimationDecoder;
    assert_eq!(gif.into_frames().count(), 120);
    server.assert_peak_rss();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_video_upload_killed_during_frame_extraction_leaves_no_ffmpeg_and_finishes() {
    // A walk around the textured scene, filmed: 48 rendered views at 12 fps.
    let dir = tempfile::tempdir().unwrap();
    let scene = TexturedScene { width: 320, height: 240, views: 48, fov: 0.9 };
    scene.write_photos(&dir.path().join("frames")).unwrap();
    let clip = dir.path().join("walk.mp4");
    let status = std::process::Command::new("ffmpeg")
        .args(["-loglevel", "error", "-framerate", "12", "-i"])
        .arg(dir.path().join("frames/view_%03d.png"))
        .args(["-c:v", "libx264", "-crf", "12", "-pix_fmt", "yuv420p"])
        .arg(&clip)
        .status()
        .unwrap();
    assert!(status.success());
    let data = tempfile::tempdir().unwrap();
    let mut server = Server::start(data.path());
    let (s, v) = server.svc.upload_form(form_of(&[("walk.mp4".into(), std::fs::read(&clip).unwrap())], true)).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    let (id, job) = (v["id"].as_str().unwrap().to_string(), v["poses"]["job_id"].as_str().unwrap().to_string());
    // ffmpeg held while it writes the candidate frames (48 of them take
    // well under a second), so the kill lands in that stage on any machine.
    freeze_at(&server.svc, data.path(), &job, "extracting video frames").await;
    let extracting = |j: &Value| j["status"] == "running" && j["progress"]["stage"] == "extracting video frames";
    server.svc.wait_job(&job, 60.0, extracting).await;
    server.kill();
    wait_until_gone(data.path(), "during frame extraction");
    server = Server::start(data.path());
    let done = server.svc.wait_job(&job, 240.0, is_final).await;
    assert_eq!((done["status"].as_str(), done["crashes"].as_u64()), (Some("succeeded"), Some(1)), "{done}");
    let (_, sc) = server.svc.get(&format!("/v1/scenes/{id}")).await;
    assert_eq!((sc["status"].as_str(), sc["poses"]["report"]["source"].as_str()), (Some("ready"), Some("video")));
    assert!(leftovers(data.path(), &id).is_empty(), "{:?}", leftovers(data.path(), &id));
    assert!(processes_in(data.path()).is_empty(), "{:?}", processes_in(data.path()));
    server.assert_peak_rss();
}
