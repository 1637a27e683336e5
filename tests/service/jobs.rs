//! Training jobs: a short job and its renders, request checks, cancel, events, videos.

use std::time::{Duration, Instant};

use radiance::engine::dataset::synthetic::BallScene;
use radiance::engine::models::config::ModelConfig;
use reqwest::StatusCode;
use serde_json::{Value, json};

use crate::common::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn short_job_succeeds_and_renders_by_matrix_and_orbit() {
    let data = tempfile::tempdir().unwrap();
    let svc = Svc::start(config(data.path())).await;
    let scene = svc.upload_ball().await;
    let id = svc.job(&scene, json!({ "steps": 40 })).await;
    let job = svc.wait_job(&id, 120.0, |v| v["status"] != "queued" && v["status"] != "running").await;
    assert_eq!(job["status"], "succeeded", "{job}");
    assert_eq!(job["progress"]["step"], 40);
    assert!(job["finished_at"].as_u64().is_some());
    let model = job["model_id"].as_str().unwrap().to_string();

    let (s, m) = svc.get(&format!("/v1/models/{model}")).await;
    assert_eq!(s, StatusCode::OK, "{m}");
    assert_eq!(
        (m["steps"].as_u64(), m["scene_id"].as_str(), m["complete"].as_bool()),
        (Some(40), Some(&*scene), Some(true))
    );
    assert!(m["test_psnr"].as_f64().is_some_and(|p| p.is_finite()), "{m}");
    assert!(m["size_bytes"].as_u64().unwrap() > 0);
    let (_, list) = svc.get("/v1/models").await;
    assert_eq!(list.as_array().unwrap().len(), 1);
    let (_, done) = svc.get("/v1/jobs?status=succeeded").await;
    assert_eq!(done.as_array().unwrap().len(), 1);
    assert_eq!(job["kind"], "train");
    assert!(job["progress"]["test_psnr"].as_f64().is_some(), "{job}");
    let (_, none) = svc.get("/v1/jobs?status=running").await;
    assert_eq!(none, json!([]));

    // By matrix: a camera at z = 3 looking down -z at the ball; default size.
    let img = svc.png(&format!("/v1/models/{model}/render?c2w=1,0,0,0,0,1,0,0,0,0,1,3")).await;
    assert_eq!((img.width(), img.height()), (16, 16));
    // By orbit, with a size and the other outputs.
    let img = svc.png(&format!("/v1/models/{model}/render?azimuth=45&elevation=20&width=24&height=20")).await;
    assert_eq!((img.width(), img.height()), (24, 20));
    let img = svc.png(&format!("/v1/models/{model}/render?azimuth=0&output=depth&background=black")).await;
    assert_eq!(img.width(), 16);
    let img = svc.png(&format!("/v1/models/{model}/render?background=transparent")).await;
    assert!(img.color().has_alpha());

    for bad in ["width=100000&height=100000", "c2w=1,2,3", "c2w=2,0,0,0,0,1,0,0,0,0,1,3", "output=nope", "fov=0"] {
        let (s, v) = svc.get(&format!("/v1/models/{model}/render?{bad}")).await;
        assert_eq!(s, StatusCode::BAD_REQUEST, "{bad}: {v}");
        assert_error(&v, "bad_request");
    }
    let (s, _) = svc.get("/v1/models/mdl_missing/render").await;
    assert_eq!(s, StatusCode::NOT_FOUND);

    // Orbit videos, as jobs: a GIF that decodes to its frames, an MP4 whose
    // boxes hold one H.264 sample per frame.
    let (job, gif, ct) =
        svc.video(&model, json!({ "frames": 6, "fps": 12, "width": 24, "height": 16, "format": "gif" })).await;
    assert_eq!(ct, "image/gif");
    assert_eq!(job["format"], "gif");
    use image::AnimationDecoder;
    let frames = image::codecs::gif::GifDecoder::new(std::io::Cursor::new(&gif)).unwrap().into_frames();
    let frames = frames.collect_frames().unwrap();
    assert_eq!(frames.len(), 6);
    assert_eq!(frames[0].buffer().dimensions(), (24, 16));
    let (_, mp4, ct) = svc.video(&model, json!({ "frames": 5, "fps": 10, "width": 32, "height": 16 })).await;
    assert_eq!(ct, "video/mp4");
    let top: Vec<String> = mp4::boxes(&mp4).into_iter().map(|(k, _)| k).collect();
    assert!(top.starts_with(&["ftyp".to_string()]) && top.contains(&"moov".into()) && top.contains(&"mdat".into()));
    let stsz = mp4::child(&mp4, &["moov", "trak", "mdia", "minf", "stbl", "stsz"]);
    assert_eq!(u32::from_be_bytes(stsz[8..12].try_into().unwrap()), 5, "samples in stsz");
    let bad_videos = [
        (json!({ "frames": 0 }), StatusCode::BAD_REQUEST),
        (json!({ "format": "avi" }), StatusCode::BAD_REQUEST),
        (json!({ "width": 100000 }), StatusCode::BAD_REQUEST),
        (json!({ "surprise": 1 }), StatusCode::BAD_REQUEST),
        (json!({ "width": 33, "height": 17, "format": "mp4" }), StatusCode::BAD_REQUEST),
    ];
    for (body, want) in bad_videos {
        let (s, v) = svc.post_json(&format!("/v1/models/{model}/videos"), body.clone()).await;
        assert_eq!(s, want, "{body}: {v}");
    }
    let (s, _) = svc.post_json("/v1/models/mdl_missing/videos", json!({})).await;
    assert_eq!(s, StatusCode::NOT_FOUND);
    let (s, _) = svc.get("/v1/videos/vid_missing").await;
    assert_eq!(s, StatusCode::NOT_FOUND);

    let metrics = svc.client.get(svc.url("/metrics")).send().await.unwrap().text().await.unwrap();
    assert!(metrics.contains("radiance_jobs{status=\"succeeded\"} 3"), "{metrics}");
    assert!(metrics.contains("radiance_render_seconds_count 4"), "{metrics}");
    svc.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn job_requests_are_checked() {
    let data = tempfile::tempdir().unwrap();
    let svc = Svc::start(config(data.path())).await;
    let scene = svc.upload_ball().await;
    let cases = [
        (json!({ "scene_id": "scn_nope", "budget": { "steps": 1 } }), StatusCode::NOT_FOUND),
        (json!({ "scene_id": scene, "budget": {} }), StatusCode::BAD_REQUEST),
        (json!({ "scene_id": scene, "budget": { "seconds": -1 } }), StatusCode::BAD_REQUEST),
        (json!({ "scene_id": scene, "model": "gpt", "budget": { "steps": 1 } }), StatusCode::BAD_REQUEST),
        (json!({ "scene_id": scene, "budget": { "steps": 1 }, "surprise": 1 }), StatusCode::BAD_REQUEST),
    ];
    for (body, want) in cases {
        let (s, v) = svc.post_json("/v1/jobs", body.clone()).await;
        assert_eq!(s, want, "{body}: {v}");
        assert!(v["error"]["code"].is_string(), "{v}");
    }
    // A configuration out of range: each failing field is named, in the
    // message and in the details.
    let mut config = serde_json::to_value(ModelConfig::preset("instant-tiny").unwrap()).unwrap();
    config["grid"]["log2_table"] = json!(40);
    config["hidden"] = json!(0);
    let body = json!({ "scene_id": scene, "model": "instant-tiny", "budget": { "steps": 1 }, "config": config });
    let (s, v) = svc.post_json("/v1/jobs", body).await;
    assert_eq!(s, StatusCode::BAD_REQUEST, "{v}");
    assert_error(&v, "bad_request");
    let msg = v["error"]["message"].as_str().unwrap();
    assert!(msg.contains("grid.log2_table is 40, allowed 8..=24") && msg.contains("hidden is 0"), "{msg}");
    assert!(!msg.contains("geo_features"), "only the failing fields are named: {msg}");
    assert_eq!(
        v["error"]["details"],
        json!({ "fields": [
            { "field": "grid.log2_table", "value": 40, "allowed": "8..=24" },
            { "field": "hidden", "value": 0, "allowed": "1..=256" },
        ] })
    );
    let (s, v) = svc.get("/v1/jobs?status=sleeping").await;
    assert_eq!(s, StatusCode::BAD_REQUEST, "{v}");
    let (s, _) = svc.post_json("/v1/jobs/job_nope/cancel", json!({})).await;
    assert_eq!(s, StatusCode::NOT_FOUND);
    svc.stop().await;
}

/// A job's `masks`: accepted, kept in the job and used by its training;
/// a bad value is a 400 naming the field; masks asked of a scene without
/// any fail the job, saying so.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn jobs_take_masks_and_bad_values_are_named() {
    let data = tempfile::tempdir().unwrap();
    let svc = Svc::start(config(data.path())).await;
    let (s, v) = svc.upload("application/zip", zip_of(&llff_masked_files())).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    let masked = v["id"].as_str().unwrap().to_string();
    let (s, v) = svc.upload("application/zip", zip_of(&llff_files())).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    let plain = v["id"].as_str().unwrap().to_string();
    let body = |scene: &str, masks: Value| json!({ "scene_id": scene, "model": "nerf-tiny", "budget": { "steps": 3 }, "batch_rays": 64, "masks": masks });

    for masks in ["ignore", "composite", "score", "off", "auto"] {
        let (s, job) = svc.post_json("/v1/jobs", body(&masked, json!(masks))).await;
        assert_eq!(s, StatusCode::ACCEPTED, "{job}");
        assert_eq!(job["masks"], masks, "{job}");
        let id = job["id"].as_str().unwrap().to_string();
        let job = svc.wait_job(&id, 60.0, |v| v["status"] != "queued" && v["status"] != "running").await;
        assert_eq!(job["status"], "succeeded", "{masks}: {job}");
    }
    // Absent means auto.
    let mut b = body(&masked, json!(null));
    b.as_object_mut().unwrap().remove("masks");
    let (s, job) = svc.post_json("/v1/jobs", b).await;
    assert_eq!((s, job["masks"].as_str()), (StatusCode::ACCEPTED, Some("auto")), "{job}");

    for bad in [json!("sometimes"), json!("IGNORE"), json!(3), json!(["ignore"])] {
        let (s, v) = svc.post_json("/v1/jobs", body(&masked, bad.clone())).await;
        assert_eq!(s, StatusCode::BAD_REQUEST, "{bad}: {v}");
        assert_error(&v, "bad_request");
        assert!(v["error"]["message"].as_str().unwrap().contains("masks"), "{v}");
        assert_eq!(v["error"]["details"]["field"], "masks", "{v}");
        assert_eq!(v["error"]["details"]["value"], bad, "{v}");
    }

    // Masks asked of opaque photos without a mask folder: the job fails
    // with the loader's reason.
    let (s, job) = svc.post_json("/v1/jobs", body(&plain, json!("ignore"))).await;
    assert_eq!(s, StatusCode::ACCEPTED, "{job}");
    let id = job["id"].as_str().unwrap().to_string();
    let job = svc.wait_job(&id, 60.0, |v| v["status"] != "queued" && v["status"] != "running").await;
    assert_eq!(job["status"], "failed", "{job}");
    assert!(job["error"].as_str().unwrap().contains("masks 'ignore' needs masks"), "{job}");
    svc.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cancel_stops_a_running_job_and_keeps_its_model() {
    let data = tempfile::tempdir().unwrap();
    let svc = Svc::start(config(data.path())).await;
    let scene = svc.upload_ball().await;
    let id = svc.job(&scene, json!({ "seconds": 600 })).await;
    let queued = svc.job(&scene, json!({ "steps": 5 })).await;
    svc.wait_job(&id, 60.0, |v| v["status"] == "running" && v["progress"]["step"].as_u64() > Some(5)).await;

    // The scene is in use.
    let r = svc.client.delete(svc.url(&format!("/v1/scenes/{scene}"))).send().await.unwrap();
    assert_eq!(r.status(), StatusCode::CONFLICT);
    assert_error(&r.json().await.unwrap(), "conflict");

    // A queued job is canceled at once.
    let (s, v) = svc.post_json(&format!("/v1/jobs/{queued}/cancel"), json!({})).await;
    assert_eq!((s, v["status"].as_str()), (StatusCode::ACCEPTED, Some("canceled")), "{v}");

    let (s, _) = svc.post_json(&format!("/v1/jobs/{id}/cancel"), json!({})).await;
    assert_eq!(s, StatusCode::ACCEPTED);
    // Within 30 s of a 600 s budget: the cancel stopped it (30 s leaves room
    // for this in-process server's two runtime threads being starved).
    let job = svc.wait_job(&id, 30.0, |v| v["status"] == "canceled").await;
    let (s, v) = svc.post_json(&format!("/v1/jobs/{id}/cancel"), json!({})).await;
    assert_eq!(s, StatusCode::CONFLICT, "{v}");

    let model = job["model_id"].as_str().expect("a canceled job keeps its model");
    let (_, m) = svc.get(&format!("/v1/models/{model}")).await;
    assert!(m["steps"].as_u64().unwrap() > 5, "{m}");
    let img = svc.png(&format!("/v1/models/{model}/render?azimuth=90")).await;
    assert_eq!(img.width(), 16);

    let r = svc.client.delete(svc.url(&format!("/v1/scenes/{scene}"))).send().await.unwrap();
    assert_eq!(r.status(), StatusCode::NO_CONTENT);
    // Models outlive their scene.
    svc.png(&format!("/v1/models/{model}/render?azimuth=10")).await;
    svc.stop().await;
}

/// A job's event stream (`GET /v1/jobs/{id}/events`), read an event at a time.
struct Events {
    r: reqwest::Response,
    buf: Vec<u8>,
}

impl Events {
    async fn open(svc: &Svc, id: &str) -> Events {
        let r = svc.client.get(svc.url(&format!("/v1/jobs/{id}/events"))).send().await.unwrap();
        assert_eq!(r.status(), StatusCode::OK);
        assert_eq!(r.headers()["content-type"], "text/event-stream");
        Events { r, buf: Vec::new() }
    }

    /// The next event (its name and job), `None` once the stream has
    /// closed; fails after 120 s without either.
    async fn next(&mut self) -> Option<(String, Value)> {
        loop {
            while let Some(at) = self.buf.windows(2).position(|w| w == b"\n\n") {
                let block: Vec<u8> = self.buf.drain(..at + 2).collect();
                let block = String::from_utf8(block).unwrap();
                let data: String = block.lines().filter_map(|l| l.strip_prefix("data: ")).collect();
                if data.is_empty() {
                    continue; // a keep-alive comment
                }
                let name = block.lines().find_map(|l| l.strip_prefix("event: ")).unwrap_or("").to_string();
                return Some((name, serde_json::from_str(&data).unwrap()));
            }
            let chunk = tokio::time::timeout(Duration::from_secs(120), self.r.chunk()).await;
            match chunk.expect("an event or the end within 120 s").unwrap() {
                Some(bytes) => self.buf.extend_from_slice(&bytes),
                None => {
                    assert!(String::from_utf8_lossy(&self.buf).trim().is_empty(), "a cut event: {:?}", self.buf);
                    return None;
                }
            }
        }
    }

    /// The progress events up to the `end` event, and that one; the stream
    /// must then close.
    async fn until_end(&mut self) -> (Vec<Value>, Value) {
        let mut progress = Vec::new();
        let end = loop {
            let (name, job) = self.next().await.expect("the stream closes only after its `end` event");
            match name.as_str() {
                "progress" => progress.push(job),
                "end" => break job,
                _ => panic!("unexpected event '{name}': {job}"),
            }
        };
        assert!(self.next().await.is_none(), "the stream closes after its `end` event");
        (progress, end)
    }
}

/// Steps never go back across a stream's events.
fn assert_steps_rise(events: &[Value]) {
    let steps: Vec<u64> = events.iter().map(|j| j["progress"]["step"].as_u64().unwrap()).collect();
    assert!(steps.windows(2).all(|w| w[0] <= w[1]), "{steps:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn instant_job_streams_events_and_stops_at_its_target_psnr() {
    let data = tempfile::tempdir().unwrap();
    let mut cfg = config(data.path());
    // A held-out estimate every 0.02 s of training.
    cfg.scheduler.heldout_every = 0.02;
    let svc = Svc::start(cfg).await;
    let scene = svc.upload_ball().await;
    let post = async |budget: Value| {
        let body = json!({ "scene_id": scene, "model": "instant-tiny", "budget": budget });
        let (s, job) = svc.post_json("/v1/jobs", body).await;
        assert_eq!(s, StatusCode::ACCEPTED, "{job}");
        assert_eq!((job["kind"].as_str(), job["config"]["kind"].as_str()), (Some("train"), Some("instant")), "{job}");
        job["id"].as_str().unwrap().to_string()
    };
    // A job without a target, then one with a 28 dB target, which the ball
    // scene passes within a second: one job runs at a time, so the second
    // waits until the first is canceled, and each stream is read in a state
    // that holds while it is read (the first training, the second queued).
    let first = post(json!({ "seconds": 600 })).await;
    let target = post(json!({ "target_psnr": 28.0, "seconds": 60 })).await;
    let mut first_events = Events::open(&svc, &first).await;
    let mut events = Events::open(&svc, &target).await;
    let (name, queued) = events.next().await.expect("a first event");
    assert_eq!((name.as_str(), queued["status"].as_str()), ("progress", Some("queued")), "{queued}");

    // A training job's stream: progress events carrying its held-out estimate.
    let t0 = Instant::now();
    let mut progress = Vec::new();
    let estimates = loop {
        let (name, job) = first_events.next().await.expect("the stream stays open while the job runs");
        assert_eq!(name, "progress", "{job}");
        progress.push(job);
        let estimates: Vec<f64> = progress
            .iter()
            .filter(|j| j["status"] == "running")
            .filter_map(|j| j["progress"]["test_psnr"].as_f64())
            .collect();
        if progress.len() >= 2 && !estimates.is_empty() {
            break estimates;
        }
        assert!(t0.elapsed() < Duration::from_secs(120), "no held-out estimate streamed in 120 s: {progress:?}");
    };
    eprintln!("held-out estimates while running: {estimates:?}");
    // Canceled, it ends its stream with one `end` event; then it closes.
    let (s, v) = svc.post_json(&format!("/v1/jobs/{first}/cancel"), json!({})).await;
    assert_eq!(s, StatusCode::ACCEPTED, "{v}");
    let (more, end) = first_events.until_end().await;
    progress.extend(more);
    assert_eq!(end["status"], "canceled", "{end}");
    assert_steps_rise(&progress);

    // The target job's stream, from its queued state to its end.
    let (mut target_progress, done) = events.until_end().await;
    target_progress.insert(0, queued);
    assert_steps_rise(&target_progress);
    eprintln!("done after {} s", done["progress"]["elapsed"]);

    // It stopped at the target, long before its time budget.
    assert_eq!(done["status"], "succeeded", "{done}");
    let p = &done["progress"];
    assert!(p["elapsed"].as_f64().unwrap() < 50.0, "{done}");
    let model = done["model_id"].as_str().unwrap();
    let (_, m) = svc.get(&format!("/v1/models/{model}")).await;
    assert_eq!(m["model"], "instant-tiny");
    assert!(m["test_psnr"].as_f64().unwrap() > 26.0, "{m}");

    // Depth is composited over the far plane: a camera at z = 3 looking
    // down -z sees the ball (radius 0.6) at 2.4 in its centre pixel; looking
    // up +z it sees nothing, which is white, the far plane.
    let far = m["view"]["far"].as_f64().unwrap();
    let depth = |c2w: &str| format!("/v1/models/{model}/render?c2w={c2w}&width=17&height=17&output=depth");
    let img = svc.png(&depth("1,0,0,0,0,1,0,0,0,0,1,3")).await.into_luma16();
    let (centre, corner) = (img.get_pixel(8, 8)[0] as f64, img.get_pixel(0, 0)[0]);
    let want = 2.4 / far * 65535.0;
    // Within 0.3: the expected depth of a small model spreads around the
    // surface, and a centre opacity short of 1 adds its share of the far plane.
    assert!((centre - want).abs() < 0.3 / far * 65535.0, "centre {centre}, want {want} (far {far})");
    assert!(corner > 60000, "the corner misses the ball: {corner}");
    let img = svc.png(&depth("-1,0,0,0,0,1,0,0,0,0,-1,3")).await.into_luma16();
    assert!(img.pixels().all(|p| p[0] == 65535), "{:?}", img.as_raw());
    assert_eq!((p["diverged_steps"].as_u64(), p["rollbacks"].as_u64()), (Some(0), Some(0)), "{done}");
    let (s, _) = svc.get("/v1/jobs/job_nope/events").await;
    assert_eq!(s, StatusCode::NOT_FOUND);
    svc.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn mp4_of_an_odd_sized_scene_is_the_size_its_job_says() {
    let data = tempfile::tempdir().unwrap();
    let svc = Svc::start(config(data.path())).await;
    let dir = tempfile::tempdir().unwrap();
    BallScene { size: 17, views: 8, ..Default::default() }.write_blender(dir.path()).unwrap();
    let (s, v) = svc.upload("application/zip", zip_of(&files(dir.path()))).await;
    assert_eq!((s, &v["resolution"]), (StatusCode::CREATED, &json!([17, 17])), "{v}");
    let id = svc.job(v["id"].as_str().unwrap(), json!({ "steps": 2 })).await;
    let job = svc.wait_job(&id, 60.0, |v| v["status"] != "queued" && v["status"] != "running").await;
    let model = job["model_id"].as_str().unwrap_or_else(|| panic!("{job}"));

    // The cameras' 17x17 becomes 16x16, in the job and in the file.
    let (job, mp4, _) = svc.video(model, json!({ "frames": 2, "fps": 10, "format": "mp4" })).await;
    assert_eq!((job["width"].as_u64(), job["height"].as_u64()), (Some(16), Some(16)), "{job}");
    assert_eq!(mp4::track_size(&mp4), (16, 16));
    // Asked for explicitly, an odd side is refused, naming the even sizes.
    let (s, v) = svc.post_json(&format!("/v1/models/{model}/videos"), json!({ "width": 33, "height": 17 })).await;
    assert_eq!(s, StatusCode::BAD_REQUEST, "{v}");
    let msg = v["error"]["message"].as_str().unwrap();
    assert!(msg.contains("33x17") && msg.contains("32x16 or 34x18") && msg.contains("gif"), "{msg}");
    // GIF keeps the cameras' size.
    let (job, _, _) = svc.video(model, json!({ "frames": 2, "fps": 10, "format": "gif" })).await;
    assert_eq!((job["width"].as_u64(), job["height"].as_u64()), (Some(17), Some(17)), "{job}");
    svc.stop().await;
}

/// Posts a training job that must be accepted; returns its record.
async fn accepted(svc: &Svc, body: Value) -> Value {
    let (s, job) = svc.post_json("/v1/jobs", body.clone()).await;
    assert_eq!(s, StatusCode::ACCEPTED, "{body}: {job}");
    job
}

/// `model` `auto` (the default) is resolved when the job is posted, from
/// what the scene's record says: the ball's transparent pixels give
/// `instant`, the same ball photographed opaque (LLFF) `capture`, and its
/// masks composited as alpha `instant` again; a record from before scenes
/// were measured is measured by loading its dataset. A preset or a config
/// overrides it. The job, the model record and the checkpoint keep why.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn auto_chooses_the_model_by_the_scene_and_says_why() {
    let data = tempfile::tempdir().unwrap();
    let mut cfg = config(data.path());
    cfg.scheduler.run_jobs = false;
    let svc = Svc::start(cfg).await;
    let ball = svc.upload_ball().await;
    let (s, v) = svc.upload("application/zip", zip_of(&llff_masked_files())).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    let photos = v["id"].as_str().unwrap().to_string();
    let (_, scene) = svc.get(&format!("/v1/scenes/{photos}")).await;
    assert_eq!(
        (scene["kind"]["transparent_images"].as_u64(), scene["kind"]["forward_facing"].as_bool()),
        (Some(0), Some(false)),
        "{scene}"
    );
    let body = |scene: &str| json!({ "scene_id": scene, "budget": { "steps": 2 } });

    let (_, b) = svc.get(&format!("/v1/scenes/{ball}")).await;
    let n = b["images"]["train"].as_u64().unwrap();
    let job = accepted(&svc, body(&ball)).await;
    assert_eq!(job["model"], "instant", "{job}");
    let object =
        format!("{n} of {n} training images have transparent pixels: an object on an empty background, the fast model");
    assert_eq!(job["model_reason"], json!(object), "{job}");
    let settings: ModelConfig = serde_json::from_value(job["config"].clone()).unwrap();
    assert_eq!(settings, ModelConfig::preset("instant").unwrap(), "the preset's settings, unchanged");

    let job = accepted(&svc, body(&photos)).await;
    let reason = job["model_reason"].as_str().unwrap_or_default().to_string();
    assert_eq!(job["model"], "capture-360", "{job}");
    assert!(reason.starts_with("opaque photographs (cameras all around their focus, axes up to "), "{reason}");
    let mut composite = body(&photos);
    composite["masks"] = json!("composite");
    let job = accepted(&svc, composite).await;
    assert_eq!(job["model"], "instant", "{job}");
    assert!(job["model_reason"].as_str().unwrap().starts_with("the masks in masks_8/ are the images' alpha"), "{job}");

    // A named preset, or a config, decides alone.
    let mut named = body(&photos);
    named["model"] = json!("nerf-tiny");
    let job = accepted(&svc, named).await;
    assert!(job["model"] == "nerf-tiny" && job.get("model_reason").is_none(), "{job}");
    let mut configured = body(&photos);
    configured["config"] = serde_json::to_value(ModelConfig::preset("instant-tiny").unwrap()).unwrap();
    let job = accepted(&svc, configured).await;
    assert!(job["model"] == "instant" && job.get("model_reason").is_none(), "{job}");
    svc.stop().await;

    // A record from before the kind was kept: the dataset is loaded.
    let record = data.path().join("scenes").join(&photos).join("scene.json");
    let mut old: Value = serde_json::from_slice(&std::fs::read(&record).unwrap()).unwrap();
    assert!(old.as_object_mut().unwrap().remove("kind").is_some());
    std::fs::write(&record, serde_json::to_vec(&old).unwrap()).unwrap();
    let svc = Svc::start(config(data.path())).await;
    let (_, scene) = svc.get(&format!("/v1/scenes/{photos}")).await;
    assert!(scene.get("kind").is_none(), "{scene}");
    let job = accepted(&svc, body(&photos)).await;
    assert_eq!((&job["model"], job["model_reason"].as_str()), (&json!("capture-360"), Some(reason.as_str())), "{job}");

    // The ball's job runs: its model record and checkpoint keep the choice.
    let job = accepted(&svc, body(&ball)).await;
    let id = job["id"].as_str().unwrap();
    let job = svc.wait_job(id, 120.0, |v| v["status"] != "queued" && v["status"] != "running").await;
    assert_eq!(job["status"], "succeeded", "{job}");
    let model = job["model_id"].as_str().unwrap().to_string();
    let (_, m) = svc.get(&format!("/v1/models/{model}")).await;
    assert_eq!((&m["model"], &m["model_reason"]), (&json!("instant"), &json!(object)), "{m}");
    svc.stop().await;
    let ckpt = radiance::datadir::DataDir::open(data.path()).unwrap().checkpoint(&model);
    let restored = radiance::engine::train::persist::load(&ckpt).unwrap();
    let choice = restored.train.model_choice.expect("the checkpoint keeps the choice");
    assert_eq!((choice.preset.as_str(), choice.reason), ("instant", object));
}

/// `drop_transients`: refused for a model that cannot find transients; a
/// capture job keeps it, its model record says what was dropped per
/// training photo, and each photo's mask is served as a PNG of its size.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn jobs_drop_transients_and_serve_the_masks() {
    let data = tempfile::tempdir().unwrap();
    let svc = Svc::start(config(data.path())).await;
    let (s, v) = svc.upload("application/zip", zip_of(&llff_files())).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    let scene = v["id"].as_str().unwrap().to_string();
    let body =
        |model: &str| json!({ "scene_id": scene, "model": model, "budget": { "steps": 40 }, "drop_transients": true });
    let (s, v) = svc.post_json("/v1/jobs", body("nerf-tiny")).await;
    assert_eq!(s, StatusCode::BAD_REQUEST, "{v}");
    assert_eq!(v["error"]["details"]["field"], "drop_transients", "{v}");
    assert!(v["error"]["message"].as_str().unwrap().contains("needs a capture model"), "{v}");
    // Unasked, another model trains on every pixel.
    let nerf = accepted(&svc, json!({ "scene_id": scene, "model": "nerf-tiny", "budget": { "steps": 2 } })).await;
    assert!(nerf.get("drop_transients").is_none(), "{nerf}");
    let nerf = nerf["id"].as_str().unwrap().to_string();
    svc.wait_job(&nerf, 120.0, |v| v["status"] != "queued" && v["status"] != "running").await;

    let job = accepted(&svc, body("capture-tiny")).await;
    assert_eq!(job["drop_transients"], true, "{job}");
    let id = job["id"].as_str().unwrap().to_string();
    let job = svc.wait_job(&id, 120.0, |v| v["status"] != "queued" && v["status"] != "running").await;
    assert_eq!(job["status"], "succeeded", "{job}");
    let model = job["model_id"].as_str().unwrap().to_string();
    let (_, m) = svc.get(&format!("/v1/models/{model}")).await;
    let photos = m["transients"]["photos"].as_array().unwrap_or_else(|| panic!("{m}"));
    let (_, sc) = svc.get(&format!("/v1/scenes/{scene}")).await;
    assert_eq!(photos.len() as u64, sc["images"]["train"].as_u64().unwrap(), "{m}");
    let dropped = m["transients"]["dropped"].as_f64().unwrap();
    assert!((0.0..=1.0).contains(&dropped), "{m}");
    let name = photos[0]["name"].as_str().unwrap();
    let r = svc.client.get(svc.url(&format!("/v1/models/{model}/transients/{name}"))).send().await.unwrap();
    assert_eq!((r.status(), r.headers()["content-type"].to_str().unwrap()), (StatusCode::OK, "image/png"));
    let mask = image::load_from_memory(&r.bytes().await.unwrap()).unwrap().to_luma8();
    let b = ball();
    assert_eq!(mask.dimensions(), (b.size, b.size));
    assert!(mask.pixels().all(|p| p.0[0] == 0 || p.0[0] == 255));
    let (s, v) = svc.get(&format!("/v1/models/{model}/transients/nope")).await;
    assert_eq!(s, StatusCode::NOT_FOUND, "{v}");
    assert!(v["error"]["message"].as_str().unwrap().contains("training photo 'nope' not found"), "{v}");

    // A capture model drops transients unless told not to; one trained on
    // every pixel has no masks.
    let default = accepted(&svc, json!({ "scene_id": scene, "model": "capture-tiny", "budget": { "steps": 2 } })).await;
    assert_eq!(default["drop_transients"], true, "{default}");
    let default = default["id"].as_str().unwrap().to_string();
    svc.wait_job(&default, 120.0, |v| v["status"] != "queued" && v["status"] != "running").await;
    let body =
        json!({ "scene_id": scene, "model": "capture-tiny", "budget": { "steps": 2 }, "drop_transients": false });
    let job = accepted(&svc, body).await;
    assert!(job.get("drop_transients").is_none(), "{job}");
    let id = job["id"].as_str().unwrap().to_string();
    let job = svc.wait_job(&id, 120.0, |v| v["status"] != "queued" && v["status"] != "running").await;
    let plain = job["model_id"].as_str().unwrap().to_string();
    let (_, m) = svc.get(&format!("/v1/models/{plain}")).await;
    assert!(m.get("transients").is_none(), "{m}");
    let (s, v) = svc.get(&format!("/v1/models/{plain}/transients/{name}")).await;
    assert_eq!(s, StatusCode::CONFLICT, "{v}");
    assert!(v["error"]["message"].as_str().unwrap().contains("it did not drop transients"), "{v}");
    svc.stop().await;
}
