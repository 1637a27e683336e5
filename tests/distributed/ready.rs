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

/// `radiance serve` with `args`, expected to fail: its stderr, and how long
/// it took (bounded).
fn refused(args: &[&str], data: &std::path::Path) -> (String, Duration) {
    let t0 = Instant::now();
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_radiance"))
        .args(["serve", "--addr", "127.0.0.1:0", "--threads", "1", "--data-dir"])
        .arg(data)
        .args(args)
        .env_remove("RADIANCE_API_KEY")
        .env("NO_COLOR", "1")
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    loop {
        if child.try_wait().unwrap().is_some() {
            break;
        }
        if t0.elapsed() > Duration::from_secs(30) {
            let _ = child.kill();
            panic!("radiance serve {args:?} still running after 30 s");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let out = child.wait_with_output().unwrap();
    assert!(!out.status.success(), "radiance serve {args:?} started");
    (String::from_utf8_lossy(&out.stderr).into_owned(), t0.elapsed())
}

#[tokio::test]
async fn a_node_waits_for_its_database_for_a_bounded_time_and_says_which() {
    let _serial = serial().await;
    let data = tempfile::tempdir().unwrap();
    let store = format!("file://{}", data.path().join("store").display());
    // A port nothing listens on.
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let db = format!("postgres://radiance:s3cret@127.0.0.1:{port}/radiance");
    let args = ["--role", "worker", "--database-url", &db, "--object-store", &store, "--startup-wait-seconds", "2"];
    let (err, took) = refused(&args, data.path());
    assert!(
        err.contains(&format!(
            "PostgreSQL (127.0.0.1:{port} (database radiance, user radiance)) is not reachable after"
        )),
        "{err}"
    );
    assert!(!err.contains("s3cret"), "the password is never shown: {err}");
    // Tried once a second until the next try would pass the 2 s given.
    assert!(took >= Duration::from_secs(1) && took < Duration::from_secs(20), "{took:?}");

    let (err, _) = refused(
        &["--role", "api", "--database-url", &db, "--object-store", &store, "--lease-seconds", "0"],
        data.path(),
    );
    assert!(err.contains("--lease-seconds must be between 1 and 3600"), "{err}");
    let (err, _) = refused(&["--role", "worker"], data.path());
    assert!(err.contains("--role worker needs the shared stores"), "{err}");
    let (err, _) = refused(&["--database-url", &db, "--object-store", &store, "--node-id", "a b"], data.path());
    assert!(err.contains("--node-id \"a b\": expected"), "{err}");
}
