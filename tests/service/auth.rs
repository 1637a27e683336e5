//! The API key.

use std::time::{Duration, Instant};

use reqwest::StatusCode;

use crate::common::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn api_key_is_required_when_configured() {
    let data = tempfile::tempdir().unwrap();
    let mut cfg = config(data.path());
    cfg.api_key = Some("s3cret".into());
    let svc = Svc::start(cfg).await;
    let (s, v) = svc.get("/v1/scenes").await;
    assert_eq!(s, StatusCode::UNAUTHORIZED);
    assert_error(&v, "unauthorized");
    // The scheme name is case-insensitive (RFC 9110); every 401 carries the
    // challenge.
    let cases = [
        (None, StatusCode::UNAUTHORIZED),
        (Some("Bearer wrong"), StatusCode::UNAUTHORIZED),
        (Some("Basic s3cret"), StatusCode::UNAUTHORIZED),
        (Some("Bearers3cret"), StatusCode::UNAUTHORIZED),
        (Some("Bearer s3cret"), StatusCode::OK),
        (Some("bearer s3cret"), StatusCode::OK),
        (Some("BEARER s3cret"), StatusCode::OK),
    ];
    for (header, want) in cases {
        let mut req = svc.client.get(svc.url("/v1/scenes"));
        if let Some(h) = header {
            req = req.header("authorization", h);
        }
        let r = req.send().await.unwrap();
        assert_eq!(r.status(), want, "{header:?}");
        let challenge = r.headers().get("www-authenticate").map(|v| v.to_str().unwrap().to_string());
        let want_challenge = (want == StatusCode::UNAUTHORIZED).then(|| r#"Bearer realm="radiance""#.to_string());
        assert_eq!(challenge, want_challenge, "{header:?}");
    }
    let (s, _) = svc.get("/healthz").await;
    assert_eq!(s, StatusCode::OK);
    svc.stop().await;
}

#[test]
fn serve_refuses_an_empty_api_key() {
    let data = tempfile::tempdir().unwrap();
    let by_env = ["RADIANCE_API_KEY", ""];
    for (args, env) in [(&[][..], Some(by_env)), (&["--api-key", ""][..], None), (&["--api-key", "  "][..], None)] {
        let mut cmd = std::process::Command::new(env!("CARGO_BIN_EXE_radiance"));
        cmd.args(["serve", "--addr", "127.0.0.1:0", "--data-dir"]).arg(data.path()).args(args);
        cmd.env_remove("RADIANCE_API_KEY");
        if let Some([k, v]) = env {
            cmd.env(k, v);
        }
        let mut child = cmd.stdout(std::process::Stdio::piped()).stderr(std::process::Stdio::piped()).spawn().unwrap();
        let t0 = Instant::now();
        while child.try_wait().unwrap().is_none() {
            if t0.elapsed() > Duration::from_secs(20) {
                child.kill().unwrap();
                panic!("{args:?} {env:?}: the server started with an empty API key");
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        let out = child.wait_with_output().unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{args:?} {env:?}");
        assert!(stderr.contains("RADIANCE_API_KEY / --api-key is set but empty"), "{args:?} {env:?}: {stderr}");
        assert!(out.stdout.is_empty(), "it never listened: {}", String::from_utf8_lossy(&out.stdout));
    }
}
