//! Readiness follows the shared stores: a node whose database is gone
//! answers `/readyz` 503 `unavailable` (and stays alive: `/healthz` 200).

use std::time::{Duration, Instant};

use reqwest::StatusCode;

use crate::cluster::{Cluster, serial};
use crate::common::{Svc, assert_error};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn readyz_is_503_while_the_database_is_down() {
    let _serial = serial().await;
    let mut cluster = Cluster::start().await;
    let (api, worker) = (cluster.node("api", "api-1", &[]), cluster.node("worker", "worker-1", &[]));
    let nodes = [Svc::remote(api.base.clone()), Svc::remote(worker.base.clone())];
    for svc in &nodes {
        let (s, v) = svc.get("/readyz").await;
        assert_eq!((s, v["status"].as_str()), (StatusCode::OK, Some("ready")), "{v}");
    }
    cluster.stop_database();
    let stopped = Instant::now();
    for svc in &nodes {
        loop {
            let (s, v) = svc.get("/readyz").await;
            if s == StatusCode::SERVICE_UNAVAILABLE {
                assert_error(&v, "unavailable");
                assert!(v["error"]["message"].as_str().unwrap().contains("the job store"), "{v}");
                break;
            }
            assert!(stopped.elapsed() < Duration::from_secs(10), "still ready 10 s after the database stopped: {v}");
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        let (s, v) = svc.get("/healthz").await;
        assert_eq!(s, StatusCode::OK, "alive all the same: {v}");
    }
    eprintln!("both nodes unready {:.2} s after the database stopped", stopped.elapsed().as_secs_f64());
    drop((api, worker));
}
