//! A bake on a worker node: a training job that asks for a bake, run by a
//! worker over the shared stores (a real S3 server), ends in a splats
//! model that an API node describes, renders and exports.

use reqwest::StatusCode;
use serde_json::{Value, json};

use crate::cluster::{Backend, Cluster, serial};
use crate::common::Svc;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_worker_bakes_what_it_trained_and_an_api_node_serves_the_splats() {
    let _serial = serial().await;
    let cluster = Cluster::start_on(Backend::S3).await;
    let api = cluster.node("api", "api-a", &[]);
    let worker = cluster.node("worker", "worker-1", &[]);
    let svc = Svc::remote(api.base.clone());

    let scene = svc.upload_ball().await;
    let body = json!({
        "scene_id": scene, "model": "nerf-tiny", "budget": { "steps": 60 }, "seed": 1, "batch_rays": 256,
        "bake": { "steps": 30 },
    });
    let (s, train) = svc.post_json("/v1/jobs", body).await;
    assert_eq!(s, StatusCode::ACCEPTED, "{train}");
    let bake_id = train["bake"]["job_id"].as_str().expect("the bake's id, given at once").to_string();
    let done = |v: &Value| v["status"] != "queued" && v["status"] != "running";
    let train = svc.wait_job(train["id"].as_str().unwrap(), 120.0, done).await;
    assert_eq!(train["status"], "succeeded", "{train}");
    let bake = svc.wait_job(&bake_id, 180.0, done).await;
    assert_eq!(bake["status"], "succeeded", "{bake}");
    assert_eq!(bake["kind"], "bake", "{bake}");
    assert_eq!(bake["source_model_id"], train["model_id"], "{bake}");
    assert_eq!(bake["progress"]["step"], 30, "{bake}");

    // The worker ran both jobs, reading the photos and the trained model
    // from the shared stores and writing the splats there.
    let sql = cluster.sql().await;
    for id in [train["id"].as_str().unwrap(), &bake_id] {
        let who: String =
            sql.query_one("SELECT worker_id FROM job_runs WHERE job_id = $1", &[&id]).await.unwrap().get(0);
        assert_eq!(who, "worker-1", "job {id}");
    }

    // The API node, which ran neither, serves the splats model.
    let model = bake["model_id"].as_str().unwrap();
    let (s, m) = svc.get(&format!("/v1/models/{model}")).await;
    assert_eq!(s, StatusCode::OK, "{m}");
    assert_eq!(m["model"], "splats", "{m}");
    let get = |path: String| {
        let (url, client) = (svc.url(&path), svc.client.clone());
        async move {
            let r = client.get(url).send().await.unwrap();
            (r.status(), r.bytes().await.unwrap().to_vec())
        }
    };
    let (s, splat) = get(format!("/v1/models/{model}/export?format=splat")).await;
    assert_eq!(s, StatusCode::OK);
    assert!(!splat.is_empty() && splat.len() % 32 == 0, "a .splat of 32-byte records: {} bytes", splat.len());
    let (s, png) = get(format!("/v1/models/{model}/render?azimuth=30&elevation=20&width=24&height=20")).await;
    assert_eq!(s, StatusCode::OK);
    assert!(png.starts_with(b"\x89PNG"), "a PNG");
    drop((api, worker));
}
