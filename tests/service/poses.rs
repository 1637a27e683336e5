//! Photo-only uploads: the scene is `posing` while a `poses` job runs the
//! real COLMAP on it, then `ready` (trainable) or `failed` with the reason;
//! cancel and restarts as for every job; refused at once when the server
//! has no COLMAP or the photos cannot be posed.

use std::time::Duration;

use radiance::api::ServiceConfig;
use radiance::engine::dataset::textured::TexturedScene;
use reqwest::StatusCode;
use serde_json::{Value, json};

use crate::common::*;

fn with_colmap(dir: &std::path::Path) -> ServiceConfig {
    let mut c = config(dir);
    c.scheduler.poses = Some(crate::common::poses::setup());
    c
}

/// The textured scene's photos (no poses), under `photos/`.
fn photo_files(views: usize) -> Vec<(String, Vec<u8>)> {
    let d = tempfile::tempdir().unwrap();
    TexturedScene { views, ..Default::default() }.write_photos(d.path()).unwrap();
    files(d.path()).into_iter().map(|(n, b)| (format!("photos/{n}"), b)).collect()
}

async fn scene(svc: &Svc, id: &str) -> Value {
    let (s, v) = svc.get(&format!("/v1/scenes/{id}")).await;
    assert_eq!(s, StatusCode::OK, "{v}");
    v
}

fn is_final(v: &Value) -> bool {
    ["succeeded", "failed", "canceled"].contains(&v["status"].as_str().unwrap_or(""))
}

/// Holds the COLMAP program of `stage` still once it runs (SIGSTOP, see
/// `procs::freeze_at`), failing if `job` ends first.
async fn freeze_at(svc: &Svc, dir: &std::path::Path, job: &str, stage: &str) {
    let ended = async || is_final(&svc.get(&format!("/v1/jobs/{job}")).await.1);
    crate::common::procs::freeze_at(dir, stage, ended).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn photos_without_poses_are_posed_then_trained_and_rendered() {
    let data = tempfile::tempdir().unwrap();
    let svc = Svc::start(with_colmap(data.path())).await;
    let (_, health) = svc.get("/healthz").await;
    assert_eq!(health["features"], json!({ "photo_uploads": true, "video_uploads": true }));

    let (s, v) = svc.upload("application/zip", zip_of(&photo_files(16))).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    assert_eq!((v["status"].as_str(), v["format"].as_str()), (Some("posing"), Some("colmap")), "{v}");
    assert_eq!((v["poses"]["source"].as_str(), v["poses"]["photos"].as_u64()), (Some("photos"), Some(16)), "{v}");
    assert_eq!(v["resolution"], json!([320, 240]));
    let id = v["id"].as_str().unwrap().to_string();
    let job_id = v["poses"]["job_id"].as_str().unwrap().to_string();

    // Not trainable while posing: 409 naming why.
    let (s, e) =
        svc.post_json("/v1/jobs", json!({ "scene_id": id, "model": "nerf-tiny", "budget": { "steps": 5 } })).await;
    if scene(&svc, &id).await["status"] == "posing" {
        assert_eq!(s, StatusCode::CONFLICT, "{e}");
        assert_error(&e, "conflict");
        assert!(e["error"]["message"].as_str().unwrap().contains("is posing"), "{e}");
        assert_eq!(e["error"]["details"]["status"], "posing");
    }

    let (s, job) = svc.get(&format!("/v1/jobs/{job_id}")).await;
    assert_eq!((s, job["kind"].as_str(), job["scene_id"].as_str()), (StatusCode::OK, Some("poses"), Some(id.as_str())));
    // Progress moves through COLMAP's stages, in order (those seen: a poll
    // may miss a short one).
    const ORDER: [&str; 5] = ["preparing photos", "feature extraction", "matching", "mapping", "checking the result"];
    let mut stages: Vec<String> = Vec::new();
    let done = loop {
        let (_, j) = svc.get(&format!("/v1/jobs/{job_id}")).await;
        if let Some(st) = j["progress"]["stage"].as_str()
            && stages.last().map(String::as_str) != Some(st)
        {
            stages.push(st.to_string());
        }
        if is_final(&j) {
            break j;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    assert_eq!(done["status"], "succeeded", "{done}");
    assert_eq!((done["progress"]["step"].as_u64(), done["progress"]["total_steps"].as_u64()), (Some(1000), Some(1000)));
    let at: Vec<Option<usize>> = stages.iter().map(|s| ORDER.iter().position(|o| o == s)).collect();
    assert!(at.iter().all(Option::is_some) && at.windows(2).all(|w| w[0] < w[1]), "{stages:?}");

    let ready = scene(&svc, &id).await;
    assert_eq!(ready["status"], "ready", "{ready}");
    let report = &ready["poses"]["report"];
    // Each of COLMAP's steps ran, timed in the report.
    let secs = &report["seconds"];
    for step in ["features", "matching", "mapping"] {
        assert!(secs[step].as_f64().is_some_and(|s| s > 0.0), "{step}: {ready}");
    }
    assert_eq!((report["images"].as_u64(), report["registered"].as_u64()), (Some(16), Some(16)), "{ready}");
    assert!(report["mean_reprojection_error_px"].as_f64().is_some_and(|e| e > 0.0 && e < 1.0), "{ready}");
    assert_eq!(ready["images"], json!({ "train": 14, "val": 2, "test": 2 }));
    assert!(ready["view"]["radius"].as_f64().unwrap() > 0.0, "{ready}");
    // The photos as uploaded are gone: the dataset holds them as trained on.
    let dir = data.path().join("scenes").join(&id);
    assert!(!dir.join("upload").exists() && dir.join("data/sparse/0/images.bin").is_file());

    let train = svc.job(&id, json!({ "steps": 20 })).await;
    let trained = svc.wait_job(&train, 120.0, is_final).await;
    assert_eq!(trained["status"], "succeeded", "{trained}");
    let model = trained["model_id"].as_str().unwrap();
    let img = svc.png(&format!("/v1/models/{model}/render?azimuth=30&elevation=20&width=64")).await;
    assert_eq!(img.width(), 64);
    svc.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn photo_uploads_that_cannot_be_posed_fail_clearly() {
    // Without COLMAP: refused at once, everything else still works.
    let data = tempfile::tempdir().unwrap();
    let svc = Svc::start(config(data.path())).await;
    let (_, health) = svc.get("/healthz").await;
    assert_eq!(health["features"]["photo_uploads"], false);
    let (s, v) = svc.upload("application/zip", zip_of(&photo_files(4))).await;
    assert_eq!(s, StatusCode::UNPROCESSABLE_ENTITY, "{v}");
    assert_error(&v, "invalid_dataset");
    let msg = v["error"]["message"].as_str().unwrap();
    assert!(msg.contains("pose estimation is disabled") && msg.contains("COLMAP"), "{msg}");
    svc.upload_ball().await;
    svc.stop().await;

    let data = tempfile::tempdir().unwrap();
    let svc = Svc::start(with_colmap(data.path())).await;
    // One photo, loose in a multipart upload.
    let one: Vec<_> = photo_files(1);
    let (s, v) = svc.upload_form(form_of(&one, true)).await;
    assert_eq!(s, StatusCode::UNPROCESSABLE_ENTITY, "{v}");
    assert!(v["error"]["message"].as_str().unwrap().contains("1 photo and no camera poses"), "{v}");
    // A "photo" that is not an image.
    let mut bad = photo_files(4);
    bad[2].1 = b"not a jpeg at all".to_vec();
    let (s, v) = svc.upload("application/zip", zip_of(&bad)).await;
    assert_eq!(s, StatusCode::UNPROCESSABLE_ENTITY, "{v}");
    let msg = v["error"]["message"].as_str().unwrap();
    assert!(msg.contains(&bad[2].0) && msg.contains("not a readable JPEG or PNG"), "{msg}");
    assert_no_scene_files(data.path());

    // Photos of noise: accepted, then the job fails and the scene says why.
    let noise = crate::common::poses::noise_pngs(5);
    let (s, v) = svc.upload("application/zip", zip_of(&noise)).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    let id = v["id"].as_str().unwrap().to_string();
    let job = svc.wait_job(v["poses"]["job_id"].as_str().unwrap(), 120.0, is_final).await;
    assert_eq!(job["status"], "failed", "{job}");
    let failed = scene(&svc, &id).await;
    assert_eq!(failed["status"], "failed", "{failed}");
    let err = failed["error"].as_str().unwrap();
    assert!(err.starts_with("pose estimation failed: ") && err.contains("overlap"), "{err}");
    let (s, e) = svc.post_json("/v1/jobs", json!({ "scene_id": id, "budget": { "steps": 5 } })).await;
    assert_eq!(s, StatusCode::CONFLICT, "{e}");
    assert!(e["error"]["message"].as_str().unwrap().contains("overlap"), "{e}");
    // A failed scene is deleted like any other.
    let r = svc.client.delete(svc.url(&format!("/v1/scenes/{id}"))).send().await.unwrap();
    assert_eq!(r.status(), StatusCode::NO_CONTENT);
    svc.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_poses_job_survives_a_restart_and_can_be_canceled() {
    let data = tempfile::tempdir().unwrap();
    // First life: queued only.
    let mut cfg = with_colmap(data.path());
    cfg.scheduler.run_jobs = false;
    let svc = Svc::start(cfg).await;
    let (s, v) = svc.upload("application/zip", zip_of(&photo_files(16))).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    let (id, job) = (v["id"].as_str().unwrap().to_string(), v["poses"]["job_id"].as_str().unwrap().to_string());
    svc.stop().await;

    // Second life: it runs; stop the server in the middle of COLMAP, held
    // (SIGSTOP) in feature extraction so it cannot finish first.
    let svc = Svc::start(with_colmap(data.path())).await;
    freeze_at(&svc, data.path(), &job, "feature extraction").await;
    let at = |j: &Value| j["status"] == "running" && j["progress"]["stage"] == "feature extraction";
    svc.wait_job(&job, 60.0, at).await;
    svc.stop().await;
    assert_eq!(scene_on_disk(data.path(), &id)["status"], "posing");

    // Third life: it runs again from the start and succeeds; no working
    // folder of the interrupted run is left.
    let svc = Svc::start(with_colmap(data.path())).await;
    let done = svc.wait_job(&job, 120.0, is_final).await;
    assert_eq!((done["status"].as_str(), done["attempts"].as_u64()), (Some("succeeded"), Some(2)), "{done}");
    assert_eq!(scene(&svc, &id).await["status"], "ready");
    let names: Vec<String> = std::fs::read_dir(data.path().join("scenes").join(&id))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert_eq!(names.len(), 2, "{names:?}"); // data/ and scene.json

    // Cancel a running one: the job is canceled, the scene says so.
    let (_, v) = svc.upload("application/zip", zip_of(&photo_files(16))).await;
    let (id, job) = (v["id"].as_str().unwrap().to_string(), v["poses"]["job_id"].as_str().unwrap().to_string());
    // Held in matching, so the cancel lands while COLMAP runs.
    freeze_at(&svc, data.path(), &job, "matching").await;
    svc.wait_job(&job, 60.0, |j| j["status"] == "running" && j["progress"]["stage"] == "matching").await;
    let (s, _) = svc.post_json(&format!("/v1/jobs/{job}/cancel"), json!({})).await;
    assert_eq!(s, StatusCode::ACCEPTED);
    let ended = svc.wait_job(&job, 30.0, is_final).await;
    assert_eq!(ended["status"], "canceled", "{ended}");
    let sc = scene(&svc, &id).await;
    assert_eq!((sc["status"].as_str(), sc["error"].as_str()), (Some("failed"), Some("pose estimation was canceled")));
    svc.stop().await;
}

fn scene_on_disk(data: &std::path::Path, id: &str) -> Value {
    serde_json::from_slice(&std::fs::read(data.join("scenes").join(id).join("scene.json")).unwrap()).unwrap()
}

#[test]
fn serve_says_at_start_up_whether_photo_uploads_work() {
    use std::io::{BufRead, Read};
    let data = tempfile::tempdir().unwrap();
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_radiance"))
        .args(["serve", "--addr", "127.0.0.1:0", "--threads", "1", "--colmap", "/nonexistent/colmap", "--data-dir"])
        .arg(data.path())
        .env_remove("RADIANCE_COLMAP")
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let mut line = String::new();
    std::io::BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
    assert!(line.starts_with("listening on http://"), "{line}");
    let base = line.trim().trim_start_matches("listening on ").to_string();
    let health = {
        use std::io::Write;
        let mut conn = std::net::TcpStream::connect(base.trim_start_matches("http://")).unwrap();
        conn.write_all(b"GET /healthz HTTP/1.0\r\nHost: localhost\r\n\r\n").unwrap();
        let mut answer = String::new();
        conn.read_to_string(&mut answer).unwrap();
        let body = answer.split("\r\n\r\n").nth(1).unwrap_or("").to_string();
        serde_json::from_str::<Value>(&body).unwrap_or_default()
    };
    let _ = child.kill();
    let mut err = String::new();
    child.stderr.take().unwrap().read_to_string(&mut err).unwrap();
    let _ = child.wait();
    assert_eq!(health["features"]["photo_uploads"], false, "{health}");
    assert!(
        err.contains("photo-only uploads are disabled")
            && err.contains("/nonexistent/colmap")
            && err.contains("apt-get"),
        "{err}"
    );
}
