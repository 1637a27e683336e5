//! A capture model's appearance in the API: `appearance=` of a render and
//! of a video request, a training image's index or the mean; an index the
//! model did not train on is a 400 naming the images it did.

use reqwest::StatusCode;
use serde_json::json;

use crate::common::*;

/// The first index of the list `training images: 1-3, 5` names.
fn first_index(message: &str) -> u32 {
    let list = message.split("training images: ").nth(1).unwrap_or_else(|| panic!("no list in: {message}"));
    list.split(|c: char| !c.is_ascii_digit()).next().unwrap().parse().unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn renders_and_videos_take_a_training_images_appearance() {
    let data = tempfile::tempdir().unwrap();
    let svc = Svc::start(config(data.path())).await;
    let scene = svc.upload_ball().await;
    let body = json!({ "scene_id": scene, "model": "capture-tiny", "budget": { "steps": 20 }, "seed": 1 });
    let (s, v) = svc.post_json("/v1/jobs", body).await;
    assert_eq!(s, StatusCode::ACCEPTED, "{v}");
    let id = v["id"].as_str().unwrap();
    let job = svc.wait_job(id, 120.0, |v| v["status"] != "queued" && v["status"] != "running").await;
    assert_eq!(job["status"], "succeeded", "{job}");
    let model = job["model_id"].as_str().unwrap().to_string();
    let render = format!("/v1/models/{model}/render?width=16&height=12");

    // An image the model never trained on: 400, naming those it did.
    let (s, v) = svc.get(&format!("{render}&appearance=99999")).await;
    assert_eq!(s, StatusCode::BAD_REQUEST, "{v}");
    assert_error(&v, "bad_request");
    let message = v["error"]["message"].as_str().unwrap();
    assert!(message.contains("image 99999") && message.contains("training images: "), "{message}");
    assert_eq!(
        (v["error"]["details"]["field"].as_str(), v["error"]["details"]["value"].as_u64()),
        (Some("appearance"), Some(99999))
    );
    let allowed = v["error"]["details"]["allowed"].as_str().unwrap();
    assert!(allowed.starts_with("mean, or a training image: "), "{allowed}");
    let first = first_index(message);

    // One that it did, and the mean: both render.
    let one = svc.png(&format!("{render}&appearance={first}")).await;
    let mean = svc.png(&format!("{render}&appearance=mean")).await;
    assert_eq!((one.width(), one.height(), mean.width(), mean.height()), (16, 12, 16, 12));
    for bad in ["nearest", "-1", "x", "99999999999"] {
        let (s, v) = svc.get(&format!("{render}&appearance={bad}")).await;
        assert_eq!(s, StatusCode::BAD_REQUEST, "{bad}: {v}");
        assert_eq!(v["error"]["details"]["field"], "appearance", "{v}");
    }

    // Videos: checked when asked for, the job records the choice.
    let videos = format!("/v1/models/{model}/videos");
    let (s, v) = svc.post_json(&videos, json!({ "frames": 2, "format": "gif", "appearance": "99999" })).await;
    assert_eq!(s, StatusCode::BAD_REQUEST, "{v}");
    assert!(v["error"]["message"].as_str().unwrap().contains("training images: "), "{v}");
    let (s, v) = svc.post_json(&videos, json!({ "frames": 2, "format": "gif", "appearance": "nearest" })).await;
    assert_eq!(s, StatusCode::BAD_REQUEST, "{v}");
    let body = json!({ "frames": 2, "width": 16, "height": 16, "format": "gif", "appearance": first.to_string() });
    let (job, gif, _) = svc.video(&model, body).await;
    assert_eq!(job["appearance"], first.to_string(), "{job}");
    assert!(!gif.is_empty());
    svc.stop().await;
}
