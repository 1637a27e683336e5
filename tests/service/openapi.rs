//! The router and openapi.yaml list the same routes.

use reqwest::StatusCode;
use serde_json::Value;

use crate::common::*;

/// `(method, path)` of every operation in openapi.yaml (a small reader for
/// the layout of that file: paths at two spaces, methods at four).
fn spec_routes() -> Vec<(String, String)> {
    let spec = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/openapi.yaml")).unwrap();
    let mut out = Vec::new();
    let (mut in_paths, mut path) = (false, String::new());
    for line in spec.lines() {
        if !line.starts_with(' ') {
            in_paths = line == "paths:";
        } else if in_paths && line.starts_with("  /") {
            path = line.trim().trim_end_matches(':').to_string();
        } else if in_paths
            && let Some(m) = ["get:", "post:", "delete:", "put:", "patch:"].iter().find(|m| line == format!("    {m}"))
        {
            out.push((m.trim_end_matches(':').to_uppercase(), path.clone()));
        }
    }
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn router_and_openapi_list_the_same_routes() {
    let data = tempfile::tempdir().unwrap();
    let svc = Svc::start(config(data.path())).await;
    let routes = spec_routes();
    assert!(routes.len() >= 12, "{routes:?}");
    let mut paths: Vec<&String> = routes.iter().map(|(_, p)| p).collect();
    paths.dedup();
    for path in paths {
        let concrete = path.replace("{id}", "x_none").replace("{photo}", "x_photo");
        let url = svc.url(&concrete);
        for method in ["GET", "POST", "DELETE", "PUT", "PATCH"] {
            let r = svc.client.request(method.parse().unwrap(), &url).send().await.unwrap();
            let status = r.status();
            let allow = r.headers().get("allow").map(|a| a.to_str().unwrap().to_string());
            let body = r.text().await.unwrap();
            let in_spec = routes.iter().any(|(m, p)| m == method && p == path);
            if in_spec {
                // Served: any answer but "no such route" or "wrong method".
                assert!(status != StatusCode::METHOD_NOT_ALLOWED && !body.contains("no route"), "{method} {path}");
            } else {
                assert_eq!(status, StatusCode::METHOD_NOT_ALLOWED, "{method} {path} is served but not in the spec");
                // The JSON envelope, naming the method, the path and the
                // methods allowed, and the `Allow` header listing them.
                let v: Value = serde_json::from_str(&body).unwrap_or_else(|e| panic!("{method} {path}: {e}: {body:?}"));
                assert_error(&v, "method_not_allowed");
                let allow = allow.unwrap_or_else(|| panic!("{method} {path}: no Allow header"));
                let msg = v["error"]["message"].as_str().unwrap();
                for (m, _) in routes.iter().filter(|(_, p)| p == path) {
                    assert!(allow.split(',').any(|a| a.trim() == m), "{method} {path}: Allow: {allow}");
                    assert!(msg.contains(m.as_str()), "{msg}");
                }
                assert!(msg.contains(method) && msg.contains(&concrete), "{msg}");
            }
        }
    }
    // An answer to HEAD has no body, 405 or not.
    let r = svc.client.head(svc.url("/v1/jobs/x_none/cancel")).send().await.unwrap();
    assert_eq!((r.status(), r.headers()["allow"].to_str().unwrap()), (StatusCode::METHOD_NOT_ALLOWED, "POST"));
    assert!(r.bytes().await.unwrap().is_empty());
    svc.stop().await;
}
