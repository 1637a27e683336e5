//! What clients see of a distributed deployment through its API nodes: a
//! cancel reaches the worker, the event stream ends, any API node renders
//! a model and serves a video another node enqueued, and a worker node
//! serves health, readiness and metrics only.

use std::time::{Duration, Instant};

use reqwest::StatusCode;
use serde_json::{Value, json};

use crate::cluster::{Backend, Cluster, serial};
use crate::common::Svc;

/// The events of a job's stream, read to its end (bounded).
async fn events(svc: &Svc, id: &str) -> Vec<(String, Value)> {
    let r = svc.client.get(svc.url(&format!("/v1/jobs/{id}/events"))).send().await.unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    assert_eq!(r.headers()["content-type"], "text/event-stream");
    let text = tokio::time::timeout(Duration::from_secs(120), r.text()).await.expect("the stream ends").unwrap();
    text.split("\n\n")
        .filter(|b| b.contains("data:"))
        .map(|block| {
            let name = block.lines().find_map(|l| l.strip_prefix("event: ")).unwrap_or("").to_string();
            let data: String = block.lines().filter_map(|l| l.strip_prefix("data: ")).collect();
            (name, serde_json::from_str(&data).unwrap())
        })
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn api_nodes_cancel_stream_render_and_serve_videos_from_the_shared_stores() {
    api_nodes_cancel_stream_render_and_serve_videos_from_the_shared_stores_on(Backend::File).await;
}

/// The same over a real S3 server: checkpoints, scenes and videos go
/// through S3 (one PUT or a multipart upload by size, listings, reads).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn api_nodes_cancel_stream_render_and_serve_videos_from_the_shared_stores_on_s3() {
    api_nodes_cancel_stream_render_and_serve_videos_from_the_shared_stores_on(Backend::S3).await;
}

/// What the API nodes serve, with the objects kept by `backend`.
async fn api_nodes_cancel_stream_render_and_serve_videos_from_the_shared_stores_on(backend: Backend) {
    let _serial = serial().await;
    let t0 = Instant::now();
    let cluster = Cluster::start_on(backend).await;
    let (a, b) = (cluster.node("api", "api-a", &[]), cluster.node("api", "api-b", &[]));
    let worker = cluster.node("worker", "worker-1", &[]);
    let (svc_a, svc_b) = (Svc::remote(a.base.clone()), Svc::remote(b.base.clone()));

    // A worker node answers health, readiness and metrics, and nothing else.
    let w = Svc::remote(worker.base.clone());
    let (s, v) = w.get("/readyz").await;
    assert_eq!((s, v["role"].as_str()), (StatusCode::OK, Some("worker")), "{v}");
    let (s, _) = w.get("/v1/jobs").await;
    assert_eq!(s, StatusCode::NOT_FOUND);
    let metrics = w.client.get(w.url("/metrics")).send().await.unwrap().text().await.unwrap();
    assert!(metrics.contains("radiance_node_info{role=\"worker\",node=\"worker-1\""), "{metrics}");
    let (s, v) = svc_a.get("/readyz").await;
    assert_eq!((s, v["role"].as_str()), (StatusCode::OK, Some("api")), "{v}");

    // (c) A short job's events, from API node B, end with `end`.
    let scene = svc_a.upload_ball().await;
    let short = svc_a.job(&scene, json!({ "steps": 30 })).await;
    let evs = events(&svc_b, &short).await;
    let (last, progress) = evs.split_last().expect("events");
    assert_eq!(last.0, "end", "{evs:?}");
    assert_eq!(last.1["status"], "succeeded", "{}", last.1);
    assert!(progress.iter().all(|(n, _)| n == "progress"), "{evs:?}");
    eprintln!("events ended {:.1} s in", t0.elapsed().as_secs_f64());

    // (d) Renders of the finished model are the same bytes from either node.
    let model = last.1["model_id"].as_str().unwrap().to_string();
    let render = format!("/v1/models/{model}/render?azimuth=30&elevation=20&width=24&height=20");
    let png = |svc: &Svc| {
        let url = svc.url(&render);
        let client = svc.client.clone();
        async move {
            let r = client.get(url).send().await.unwrap();
            assert_eq!(r.status(), StatusCode::OK);
            r.bytes().await.unwrap().to_vec()
        }
    };
    let (png_a, png_b) = (png(&svc_a).await, png(&svc_b).await);
    assert!(png_a.starts_with(b"\x89PNG"), "a PNG");
    assert_eq!(png_a, png_b, "both API nodes render the same bytes");

    // A video enqueued on A is served by B, the bytes A serves.
    let body = json!({ "frames": 3, "width": 16, "height": 16, "format": "gif" });
    let (s, v) = svc_a.post_json(&format!("/v1/models/{model}/videos"), body).await;
    assert_eq!(s, StatusCode::ACCEPTED, "{v}");
    let video_job = v["id"].as_str().unwrap().to_string();
    let done = svc_b.wait_job(&video_job, 60.0, |v| v["status"] != "queued" && v["status"] != "running").await;
    assert_eq!(done["status"], "succeeded", "{done}");
    let video = done["video_id"].as_str().unwrap();
    let get = |svc: &Svc| svc.client.get(svc.url(&format!("/v1/videos/{video}"))).send();
    let (ra, rb) = (get(&svc_a).await.unwrap(), get(&svc_b).await.unwrap());
    assert_eq!((ra.status(), rb.status()), (StatusCode::OK, StatusCode::OK));
    let (va, vb) = (ra.bytes().await.unwrap(), rb.bytes().await.unwrap());
    assert!(vb.starts_with(b"GIF"), "a GIF");
    assert_eq!(va, vb);
    eprintln!("renders and video checked {:.1} s in", t0.elapsed().as_secs_f64());

    // (b) A cancel through API node B reaches the worker: `canceled`
    // within 15 s (a notice, else the next heartbeat, then a step and the
    // end's record, with four processes on two cores), its model kept.
    let long = svc_a.job(&scene, json!({ "steps": 1_000_000 })).await;
    svc_a.wait_job(&long, 60.0, |v| v["status"] == "running" && v["model_id"].is_string()).await;
    let asked = Instant::now();
    let (s, v) = svc_b.post_json(&format!("/v1/jobs/{long}/cancel"), json!({})).await;
    assert_eq!(s, StatusCode::ACCEPTED, "{v}");
    let canceled = svc_a.wait_job(&long, 60.0, |v| v["status"] != "running").await;
    let took = asked.elapsed();
    assert_eq!(canceled["status"], "canceled", "{canceled}");
    eprintln!("canceled {:.2} s after the request", took.as_secs_f64());
    assert!(took < Duration::from_secs(15), "the cancel took {took:?}");
    let kept = canceled["model_id"].as_str().unwrap();
    let (s, m) = svc_b.get(&format!("/v1/models/{kept}")).await;
    assert_eq!(s, StatusCode::OK, "{m}");
    assert!(m["steps"].as_u64().unwrap() > 0, "{m}");
    eprintln!("test done in {:.1} s", t0.elapsed().as_secs_f64());
    drop((a, b, worker));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_all_node_over_the_shared_stores_serves_and_runs_jobs() {
    let _serial = serial().await;
    let cluster = Cluster::start().await;
    let node = cluster.node("all", "all-1", &[]);
    let svc = Svc::remote(node.base.clone());
    let scene = svc.upload_ball().await;
    let id = svc.job(&scene, json!({ "steps": 30 })).await;
    let done = svc.wait_job(&id, 60.0, |v| v["status"] != "queued" && v["status"] != "running").await;
    assert_eq!(done["status"], "succeeded", "{done}");
    let (_, m) = svc.get(&format!("/v1/models/{}", done["model_id"].as_str().unwrap())).await;
    assert_eq!(m["steps"], 30, "{m}");
    let sql = cluster.sql().await;
    let worker: String =
        sql.query_one("SELECT worker_id FROM job_runs WHERE job_id = $1", &[&id]).await.unwrap().get(0);
    assert_eq!(worker, "all-1", "the node's own worker ran it");
    let metrics = svc.client.get(svc.url("/metrics")).send().await.unwrap().text().await.unwrap();
    assert!(metrics.contains("radiance_node_info{role=\"all\",node=\"all-1\""), "{metrics}");
    assert!(node.metric("radiance_train_steps_total").await >= 30.0, "{metrics}");
    assert_eq!(node.metric("radiance_worker_claims_total").await, 1.0);
    // The gauge drops once the job's thread has recorded the end and
    // cleaned up, just after clients see `succeeded`.
    let t0 = Instant::now();
    loop {
        let running = node.metric("radiance_worker_running_jobs").await;
        if running == 0.0 {
            break;
        }
        assert!(t0.elapsed() < Duration::from_secs(10), "{running} jobs still running 10 s after the job ended");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert_eq!(node.metric("radiance_worker_leases_lost_total").await, 0.0);
}
