//! What the web app relies on, over the wire: the page and its caching,
//! the tower-http layers, the demo scene, and videos along camera paths.

use image::AnimationDecoder;
use reqwest::StatusCode;
use serde_json::{Value, json};

use crate::common::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_page_layers_and_demo_scene() {
    let data = tempfile::tempdir().unwrap();
    let mut cfg = config(data.path());
    cfg.max_upload_bytes = 1 << 20;
    let svc = Svc::start(cfg).await;
    // The page, revalidated by its ETag.
    let r = svc.client.get(svc.url("/")).send().await.unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    assert!(r.headers()["content-type"].to_str().unwrap().starts_with("text/html"));
    let etag = r.headers()["etag"].clone();
    let id = r.headers()["x-request-id"].to_str().unwrap().to_string();
    assert!(id.len() >= 32, "a request id: {id}");
    assert!(r.text().await.unwrap().contains("/assets/app.js"));
    let r = svc.client.get(svc.url("/")).header("if-none-match", etag).send().await.unwrap();
    assert_eq!(r.status(), StatusCode::NOT_MODIFIED);
    // Compressed for clients that accept it; a client's request id is kept.
    let r = svc
        .client
        .get(svc.url("/assets/app.js"))
        .header("accept-encoding", "gzip")
        .header("x-request-id", "mine-42")
        .send()
        .await
        .unwrap();
    assert_eq!((r.status(), r.headers()["content-encoding"].to_str().unwrap()), (StatusCode::OK, "gzip"));
    assert_eq!(r.headers()["x-request-id"], "mine-42");
    let (s, v) = svc.get("/assets/nope.js").await;
    assert_eq!(s, StatusCode::NOT_FOUND, "{v}");
    // A body over the limit, refused from its Content-Length with the
    // envelope. Sent by hand, headers only: a client still writing the 2 MiB
    // when the server answers and closes would see a broken pipe instead.
    let answer = {
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        let mut conn = tokio::net::TcpStream::connect(svc.base.trim_start_matches("http://")).await.unwrap();
        let head = format!(
            "POST /v1/jobs HTTP/1.1\r\nHost: localhost\r\nContent-Type: application/json\r\n\
             Content-Length: {}\r\nConnection: close\r\n\r\n",
            2 << 20
        );
        conn.write_all(head.as_bytes()).await.unwrap();
        let mut answer = Vec::new();
        tokio::time::timeout(std::time::Duration::from_secs(10), conn.read_to_end(&mut answer)).await.unwrap().unwrap();
        String::from_utf8_lossy(&answer).into_owned()
    };
    assert!(answer.starts_with("HTTP/1.1 413"), "{answer}");
    let v: Value = serde_json::from_str(answer.split("\r\n\r\n").nth(1).unwrap_or("")).unwrap();
    assert_error(&v, "payload_too_large");
    assert_eq!(v["error"]["details"]["limit_bytes"], 1 << 20);
    // No CORS unless configured.
    let r = svc.client.get(svc.url("/v1/scenes")).header("origin", "https://elsewhere.example").send().await.unwrap();
    assert!(r.headers().get("access-control-allow-origin").is_none());
    // The demo scene.
    let (s, v) = svc.post_json("/v1/demo", json!({})).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    assert_eq!((v["format"].as_str(), v["images"]["train"].as_u64()), (Some("blender"), Some(32)));
    assert_eq!(v["resolution"], json!([96, 96]));
    // A second demo is its own scene with the same files (generated once,
    // copied after).
    let (s2, v2) = svc.post_json("/v1/demo", json!({})).await;
    assert_eq!(s2, StatusCode::CREATED, "{v2}");
    assert_ne!(v2["id"], v["id"]);
    assert_eq!((&v2["size_bytes"], &v2["images"]), (&v["size_bytes"], &v["images"]));
    assert!(v["size_bytes"].as_u64().unwrap() > 36 * 1000, "{v}");
    svc.stop().await;

    // With an origin configured, that origin (only) may call the API.
    let data = tempfile::tempdir().unwrap();
    let mut cfg = config(data.path());
    cfg.cors_origins = vec!["https://app.example".into()];
    let svc = Svc::start(cfg).await;
    let ask = |origin: &'static str| {
        svc.client
            .request(reqwest::Method::OPTIONS, svc.url("/v1/scenes"))
            .header("origin", origin)
            .header("access-control-request-method", "POST")
            .send()
    };
    let r = ask("https://app.example").await.unwrap();
    assert_eq!(r.headers()["access-control-allow-origin"], "https://app.example");
    let r = ask("https://elsewhere.example").await.unwrap();
    assert!(r.headers().get("access-control-allow-origin").is_none());
    svc.stop().await;
}

/// A pose looking at the origin from `eye` (z up), as 12 numbers.
fn look_at(eye: [f32; 3]) -> Vec<f32> {
    use radiance::engine::geometry::camera;
    use radiance::engine::geometry::math::Vec3;
    let m = camera::look_at(Vec3::from_array(eye), Vec3::splat(0.0), Vec3::new(0.0, 0.0, 1.0)).unwrap();
    m.iter().flatten().copied().collect()
}

fn mean_abs_diff(a: &image::RgbaImage, b: &image::RgbImage) -> f64 {
    let sum: u64 =
        a.pixels().zip(b.pixels()).map(|(p, q)| (0..3).map(|c| p[c].abs_diff(q[c]) as u64).sum::<u64>()).sum();
    sum as f64 / (3 * a.width() * a.height()) as f64
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn videos_follow_camera_paths() {
    let data = tempfile::tempdir().unwrap();
    let svc = Svc::start(config(data.path())).await;
    let scene = svc.upload_ball().await;
    let id = svc.job(&scene, json!({ "steps": 30 })).await;
    let job = svc.wait_job(&id, 120.0, |v| v["status"] != "queued" && v["status"] != "running").await;
    let model = job["model_id"].as_str().unwrap().to_string();

    // Three keyframes: the video starts at the first and ends at the last.
    let (first, last) = (look_at([3.0, 0.0, 1.0]), look_at([0.0, -3.0, 2.0]));
    let path =
        json!([{ "c2w": first, "fov": 50.0 }, { "c2w": look_at([2.0, 2.0, 0.5]) }, { "c2w": last, "fov": 40.0 }]);
    let body = json!({ "path": path, "frames": 9, "fps": 9, "width": 32, "height": 32, "format": "gif" });
    let (job, gif, _) = svc.video(&model, body).await;
    assert_eq!((job["path"].as_array().map(Vec::len), job["path"][2]["time"].as_f64()), (Some(3), Some(2.0)), "{job}");
    let frames = image::codecs::gif::GifDecoder::new(std::io::Cursor::new(&gif)).unwrap().into_frames();
    let frames = frames.collect_frames().unwrap();
    assert_eq!(frames.len(), 9);
    for (frame, c2w, fov) in [(&frames[0], &first, 50.0), (&frames[8], &last, 40.0)] {
        let q: Vec<String> = c2w.iter().map(|x| x.to_string()).collect();
        let url = format!("/v1/models/{model}/render?c2w={}&width=32&height=32&fov={fov}", q.join(","));
        let still = svc.png(&url).await.to_rgb8();
        let d = mean_abs_diff(frame.buffer(), &still);
        // GIF's 256-colour palette, not the camera, is all that differs.
        assert!(d < 3.0, "frame differs from the keyframe's render by {d} levels on average");
    }
    let first_frame = image::DynamicImage::ImageRgba8(frames[0].buffer().clone()).to_rgb8();
    let middle = mean_abs_diff(frames[4].buffer(), &first_frame);
    assert!(middle > 1.0, "the camera moved: {middle}");

    // nerfstudio's camera_path.json: its frames, size and frame rate.
    let m16: Vec<f32> = first.iter().copied().chain([0.0, 0.0, 0.0, 1.0]).collect();
    let file = json!({
        "render_width": 32, "render_height": 16, "fps": 10, "seconds": 0.2,
        "camera_path": [
            { "camera_to_world": m16, "fov": 40.0, "aspect": 2.0 },
            { "camera_to_world": look_at([0.0, 3.0, 1.0]).into_iter().chain([0.0, 0.0, 0.0, 1.0]).collect::<Vec<f32>>(), "fov": 40.0, "aspect": 2.0 },
            { "camera_to_world": m16, "fov": 40.0, "aspect": 2.0 },
        ],
    });
    let (job, _, ct) = svc.video(&model, json!({ "path": file, "format": "gif" })).await;
    assert_eq!(ct, "image/gif");
    assert_eq!(
        (job["frames"].as_u64(), job["fps"].as_u64(), job["width"].as_u64(), job["height"].as_u64()),
        (Some(3), Some(10), Some(32), Some(16))
    );

    // Refused, naming the field.
    let bad = [
        (json!({ "path": path, "elevation": 10 }), "elevation"),
        (json!({ "path": [{ "c2w": [1, 0, 0] }] }), "path[0].c2w"),
        (json!({ "path": [{ "c2w": first, "time": 1 }, { "c2w": last, "time": 0.5 }] }), "path"),
        (json!({ "path": "around" }), "path"),
    ];
    for (body, field) in bad {
        let (s, v) = svc.post_json(&format!("/v1/models/{model}/videos"), body.clone()).await;
        assert_eq!(s, StatusCode::BAD_REQUEST, "{body}: {v}");
        assert_eq!(v["error"]["details"]["field"], field, "{v}");
    }
    svc.stop().await;
}
