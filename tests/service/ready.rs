//! Operations: `/readyz` (the stores can serve) and the node's role in
//! `/metrics`.

use reqwest::StatusCode;

use crate::common::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn readyz_follows_the_data_directory_and_metrics_name_the_role() {
    let data = tempfile::tempdir().unwrap();
    let mut cfg = config(data.path());
    cfg.api_key = Some("k".into());
    let svc = Svc::start(cfg).await;
    // No key needed, as for /healthz (probes carry none).
    let (s, v) = svc.get("/readyz").await;
    assert_eq!(s, StatusCode::OK, "{v}");
    assert_eq!((v["status"].as_str(), v["role"].as_str()), (Some("ready"), Some("all")), "{v}");

    // The data directory stops being usable: not ready, naming the store
    // (and not the server's paths), until it is usable again.
    let tmp = data.path().join("tmp");
    std::fs::remove_dir(&tmp).unwrap();
    let (s, v) = svc.get("/readyz").await;
    assert_eq!(s, StatusCode::SERVICE_UNAVAILABLE, "{v}");
    assert_error(&v, "unavailable");
    let message = v["error"]["message"].as_str().unwrap();
    assert!(message.contains("artifact store") && !message.contains(&*data.path().to_string_lossy()), "{message}");
    std::fs::create_dir(&tmp).unwrap();
    assert_eq!(svc.get("/readyz").await.0, StatusCode::OK);

    let metrics = svc.client.get(svc.url("/metrics")).bearer_auth("k").send().await.unwrap().text().await.unwrap();
    let info = format!("radiance_node_info{{role=\"all\",version=\"{}\"}} 1", env!("CARGO_PKG_VERSION"));
    assert!(metrics.lines().any(|l| l == info), "{metrics}");
    assert!(metrics.contains("# TYPE radiance_node_info gauge"), "{metrics}");
    svc.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_server_refuses_a_role_it_cannot_play() {
    let data = tempfile::tempdir().unwrap();
    let mut cfg = config(data.path());
    cfg.role = radiance::api::Role::Worker;
    let e = radiance::api::Server::start(cfg, "127.0.0.1:0".parse().unwrap()).await.err().expect("refused");
    assert_eq!(e.kind(), std::io::ErrorKind::Unsupported);
    // Over its own data directory (no shared stores), a node plays `all` only.
    assert!(e.to_string().contains("role 'worker' needs the shared job and artifact stores"), "{e}");
    assert!(std::fs::read_dir(data.path()).unwrap().next().is_none(), "it opened the data directory");
}
