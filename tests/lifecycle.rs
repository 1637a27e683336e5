//! What piles up on disk: deleting jobs, models and videos (and what depends
//! on what), orphaned files at start-up, the optimiser state dropped from
//! finished models, and the disk use the service reports.

mod common;

use std::time::{Duration, Instant};

use common::*;
use reqwest::StatusCode;
use serde_json::{Value, json};

async fn delete(svc: &Svc, path: &str) -> (StatusCode, Value) {
    let r = svc.client.delete(svc.url(path)).send().await.unwrap();
    let s = r.status();
    (s, r.json().await.unwrap_or(Value::Null))
}

/// `radiance_disk_bytes{kind="KIND"}` from /metrics.
async fn disk_bytes(svc: &Svc, kind: &str) -> u64 {
    let text = svc.client.get(svc.url("/metrics")).send().await.unwrap().text().await.unwrap();
    let prefix = format!("radiance_disk_bytes{{kind=\"{kind}\"}} ");
    let line = text.lines().find_map(|l| l.strip_prefix(&prefix)).unwrap_or_else(|| panic!("no {prefix}in {text}"));
    line.parse().unwrap()
}

async fn raw(svc: &Svc, path: &str) -> (StatusCode, Vec<u8>) {
    let r = svc.client.get(svc.url(path)).send().await.unwrap();
    (r.status(), r.bytes().await.unwrap().to_vec())
}

fn is_final(v: &Value) -> bool {
    !matches!(v["status"].as_str(), Some("queued" | "running"))
}

fn cached(svc: &Svc, model: &str) -> bool {
    let state = &svc.server.as_ref().unwrap().state;
    state.model_cache.lock().unwrap().iter().any(|c| c.id == model)
}

fn gif_body() -> Value {
    json!({ "frames": 4, "fps": 4, "width": 16, "height": 16, "format": "gif" })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn deletes_refuse_what_a_job_needs_and_free_the_disk() {
    let data = tempfile::tempdir().unwrap();
    let svc = Svc::start(config(data.path())).await;
    let scene = svc.upload_ball().await;
    let first = svc.job(&scene, json!({ "steps": 20 })).await;
    let done = svc.wait_job(&first, 120.0, is_final).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    let model = done["model_id"].as_str().unwrap().to_string();
    let (vjob, gif, _) = svc.video(&model, gif_body()).await;
    let video = vjob["video_id"].as_str().unwrap().to_string();
    let ckpt = data.path().join("models").join(format!("{model}.ckpt"));
    let (_, list) = svc.get("/v1/models").await;
    assert_eq!(list[0]["videos_bytes"], gif.len() as u64, "{list}");
    assert_eq!(list[0]["size_bytes"], std::fs::metadata(&ckpt).unwrap().len(), "{list}");
    let (_, one) = svc.get(&format!("/v1/models/{model}")).await;
    assert_eq!(one["videos_bytes"], gif.len() as u64, "{one}");

    // A long job runs (it writes its model); a video job of the first model waits behind it.
    let long = svc.job(&scene, json!({ "seconds": 600 })).await;
    let running = svc.wait_job(&long, 60.0, |v| v["status"] == "running" && v["model_id"].is_string()).await;
    let long_model = running["model_id"].as_str().unwrap().to_string();
    let (s, v) = svc.post_json(&format!("/v1/models/{model}/videos"), gif_body()).await;
    assert_eq!((s, v["status"].as_str()), (StatusCode::ACCEPTED, Some("queued")), "{v}");
    let waiting = v["id"].as_str().unwrap().to_string();
    for (path, what) in [
        (format!("/v1/jobs/{long}"), "cancel it first"),
        (format!("/v1/jobs/{waiting}"), "cancel it first"),
        (format!("/v1/models/{long_model}"), &*long),
        (format!("/v1/models/{model}"), &*waiting),
    ] {
        let (s, v) = delete(&svc, &path).await;
        assert_eq!(s, StatusCode::CONFLICT, "{path}: {v}");
        assert_error(&v, "conflict");
        assert!(v["error"]["message"].as_str().unwrap().contains(what), "{path}: {v}");
    }
    for path in ["/v1/models/mdl_none", "/v1/videos/vid_none", "/v1/jobs/job_none", "/v1/models/..%2Fx"] {
        let (s, v) = delete(&svc, path).await;
        assert_eq!(s, StatusCode::NOT_FOUND, "{path}: {v}");
        assert_error(&v, "not_found");
    }
    svc.post_json(&format!("/v1/jobs/{waiting}/cancel"), json!({})).await;
    svc.post_json(&format!("/v1/jobs/{long}/cancel"), json!({})).await;
    svc.wait_job(&long, 30.0, |v| v["status"] == "canceled").await;

    // The model goes: record, checkpoint and loaded copy; disk use drops by
    // the checkpoint; its video stays.
    svc.png(&format!("/v1/models/{model}/render")).await;
    assert!(cached(&svc, &model));
    let models_before = disk_bytes(&svc, "models").await;
    let ckpt_len = std::fs::metadata(&ckpt).unwrap().len();
    let (s, v) = delete(&svc, &format!("/v1/models/{model}")).await;
    assert_eq!(s, StatusCode::NO_CONTENT, "{v}");
    assert!(disk_bytes(&svc, "models").await + ckpt_len <= models_before);
    assert!(!ckpt.exists() && !data.path().join("models").join(format!("{model}.json")).exists());
    assert!(!cached(&svc, &model), "the API still holds the deleted model");
    for path in [format!("/v1/models/{model}"), format!("/v1/models/{model}/render")] {
        assert_eq!(svc.get(&path).await.0, StatusCode::NOT_FOUND, "{path}");
    }
    assert_eq!(delete(&svc, &format!("/v1/models/{model}")).await.0, StatusCode::NOT_FOUND);
    assert_eq!(raw(&svc, &format!("/v1/videos/{video}")).await, (StatusCode::OK, gif.clone()));

    // The video goes.
    let videos_before = disk_bytes(&svc, "videos").await;
    assert_eq!(delete(&svc, &format!("/v1/videos/{video}")).await.0, StatusCode::NO_CONTENT);
    assert!(disk_bytes(&svc, "videos").await + gif.len() as u64 <= videos_before);
    assert_eq!(svc.get(&format!("/v1/videos/{video}")).await.0, StatusCode::NOT_FOUND);
    assert_eq!(delete(&svc, &format!("/v1/videos/{video}")).await.0, StatusCode::NOT_FOUND);
    assert_eq!(std::fs::read_dir(data.path().join("videos")).unwrap().count(), 0);

    // Finished jobs' records go; the model a job made stays.
    for id in [&long, &first] {
        assert_eq!(delete(&svc, &format!("/v1/jobs/{id}")).await.0, StatusCode::NO_CONTENT);
        assert_eq!(svc.get(&format!("/v1/jobs/{id}")).await.0, StatusCode::NOT_FOUND);
    }
    assert_eq!(svc.get(&format!("/v1/models/{long_model}")).await.0, StatusCode::OK);

    // The scene goes.
    let scenes_before = disk_bytes(&svc, "scenes").await;
    assert!(scenes_before > 0);
    assert_eq!(delete(&svc, &format!("/v1/scenes/{scene}")).await.0, StatusCode::NO_CONTENT);
    assert_eq!(disk_bytes(&svc, "scenes").await, 0);
    svc.stop().await;

    // Deleted job records stay deleted after a restart.
    let svc = Svc::start(config(data.path())).await;
    let (_, jobs) = svc.get("/v1/jobs").await;
    let ids: Vec<&str> = jobs.as_array().unwrap().iter().map(|j| j["id"].as_str().unwrap()).collect();
    assert_eq!(ids, [vjob["id"].as_str().unwrap(), &*waiting]);
    svc.stop().await;
}

/// Polls a model until `pred` holds (panics after `secs`).
async fn wait_model(svc: &Svc, id: &str, secs: f64, pred: impl Fn(&Value) -> bool) -> Value {
    let t0 = Instant::now();
    loop {
        let (s, v) = svc.get(&format!("/v1/models/{id}")).await;
        assert_eq!(s, StatusCode::OK, "{v}");
        if pred(&v) {
            return v;
        }
        assert!(t0.elapsed().as_secs_f64() < secs, "timed out waiting for model: {v}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn finished_models_drop_their_optimiser_state_and_render_the_same() {
    let data = tempfile::tempdir().unwrap();
    // First life: the default retention (24 hours) keeps the state.
    let svc = Svc::start(config(data.path())).await;
    let scene = svc.upload_ball().await;
    // The fast model: its parameters, hence Adam's two moments, dominate its checkpoint.
    let body = json!({ "scene_id": scene, "model": "instant-tiny", "budget": { "steps": 20 } });
    let (s, job) = svc.post_json("/v1/jobs", body).await;
    assert_eq!(s, StatusCode::ACCEPTED, "{job}");
    let job = svc.wait_job(job["id"].as_str().unwrap(), 120.0, is_final).await;
    assert_eq!(job["status"], "succeeded", "{job}");
    let model = job["model_id"].as_str().unwrap().to_string();
    let view = format!("/v1/models/{model}/render?azimuth=30&elevation=20&width=24&height=20");
    let (s, before) = raw(&svc, &view).await;
    assert_eq!(s, StatusCode::OK);
    let m = svc.get(&format!("/v1/models/{model}")).await.1;
    assert_eq!(m["training_state"], true, "{m}");
    let full = m["size_bytes"].as_u64().unwrap();
    svc.stop().await;

    // Second life, keeping it for no time: the start-up sweep strips it.
    let mut cfg = config(data.path());
    cfg.scheduler.keep_training_state = Duration::ZERO;
    let svc = Svc::start(cfg).await;
    let m = wait_model(&svc, &model, 30.0, |m| m["training_state"] == false).await;
    let ckpt = data.path().join("models").join(format!("{model}.ckpt"));
    let stripped = m["size_bytes"].as_u64().unwrap();
    assert_eq!(stripped, std::fs::metadata(&ckpt).unwrap().len());
    assert!(stripped * 2 < full, "{full} -> {stripped} bytes");
    assert_eq!(raw(&svc, &view).await, (StatusCode::OK, before), "the stripped model renders other bytes");

    // A job that ends now is stripped at once, not at the next minute's sweep.
    let t0 = Instant::now();
    let job = svc.job(&scene, json!({ "steps": 5 })).await;
    let other = svc.wait_job(&job, 60.0, is_final).await["model_id"].as_str().unwrap().to_string();
    wait_model(&svc, &other, 20.0, |m| m["training_state"] == false).await;
    assert!(t0.elapsed() < Duration::from_secs(40), "{:?}", t0.elapsed());
    svc.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn start_up_removes_files_without_records_but_not_a_queued_jobs_checkpoint() {
    let data = tempfile::tempdir().unwrap();
    let mut cfg = config(data.path());
    cfg.scheduler.run_jobs = false;
    let svc = Svc::start(cfg.clone()).await;
    let scene = svc.upload_ball().await;
    let queued = svc.job(&scene, json!({ "steps": 5 })).await;
    svc.stop().await;
    let file = |d: &str, name: String| data.path().join(d).join(name);
    // What a job interrupted after its first checkpoint left, and what a
    // crash between deleting a record and its file leaves.
    let resumed = file("models", format!("mdl{}.ckpt", queued.trim_start_matches("job")));
    let orphans = [file("models", "mdl_gone.ckpt".into()), file("videos", "vid_gone.bin".into())];
    for p in orphans.iter().chain([&resumed]) {
        std::fs::write(p, b"x").unwrap();
    }
    let svc = Svc::start(cfg).await;
    assert!(orphans.iter().all(|p| !p.exists()), "orphans are left");
    assert!(resumed.exists(), "the queued job's checkpoint is gone");
    svc.stop().await;
}
