//! The web app: `GET /` and `GET /assets/{path}` serve the page, its
//! script modules, its style sheet and the vendored libraries of the splat
//! viewer (`web/vendor/`: Spark and three.js as published on npm, with
//! their licences; `scripts/vendor-web` fetches them), all embedded in the
//! binary (`web/` at build time), so `radiance serve` is all a user runs.
//! The page talks to the same REST API as every other client.
//!
//! Caching: every answer carries a strong `ETag` (a hash of the file as
//! built) and `Cache-Control: no-cache`, so a browser keeps its copy and
//! revalidates it (`304 Not Modified`) instead of fetching it again; a new
//! build changes the tags. Compression is the router's (see `layers`).

use axum::extract::Path;
use axum::http::header::{CACHE_CONTROL, CONTENT_TYPE, ETAG, IF_NONE_MATCH};
use axum::http::{HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};

use super::{ApiError, Code};

/// One embedded file.
pub struct Asset {
    pub name: &'static str,
    pub content_type: &'static str,
    pub body: &'static str,
}

const HTML: &str = "text/html; charset=utf-8";
const JS: &str = "text/javascript; charset=utf-8";
const CSS: &str = "text/css; charset=utf-8";
const TEXT: &str = "text/plain; charset=utf-8";

/// Every file of the page, by its path under `web/` (`/assets/PATH`); the
/// page first. The vendored files are as published (see
/// `web/vendor/README.md`): about 4.6 MB of the binary.
#[rustfmt::skip]
pub const ASSETS: [Asset; 22] = [
    Asset { name: "index.html", content_type: HTML, body: include_str!("../../web/index.html") },
    Asset { name: "app.js", content_type: JS, body: include_str!("../../web/app.js") },
    Asset { name: "api.js", content_type: JS, body: include_str!("../../web/api.js") },
    Asset { name: "ui.js", content_type: JS, body: include_str!("../../web/ui.js") },
    Asset { name: "scenes.js", content_type: JS, body: include_str!("../../web/scenes.js") },
    Asset { name: "training.js", content_type: JS, body: include_str!("../../web/training.js") },
    Asset { name: "viewer.js", content_type: JS, body: include_str!("../../web/viewer.js") },
    Asset { name: "videos.js", content_type: JS, body: include_str!("../../web/videos.js") },
    Asset { name: "splats.js", content_type: JS, body: include_str!("../../web/splats.js") },
    Asset { name: "crop.js", content_type: JS, body: include_str!("../../web/crop.js") },
    Asset { name: "mesh.js", content_type: JS, body: include_str!("../../web/mesh.js") },
    Asset { name: "style.css", content_type: CSS, body: include_str!("../../web/style.css") },
    Asset { name: "vendor/model-viewer/model-viewer.min.js", content_type: JS, body: include_str!("../../web/vendor/model-viewer/model-viewer.min.js") },
    Asset { name: "vendor/model-viewer/LICENSE", content_type: TEXT, body: include_str!("../../web/vendor/model-viewer/LICENSE") },
    Asset { name: "vendor/spark/spark.module.min.js", content_type: JS, body: include_str!("../../web/vendor/spark/spark.module.min.js") },
    Asset { name: "vendor/spark/LICENSE", content_type: TEXT, body: include_str!("../../web/vendor/spark/LICENSE") },
    Asset { name: "vendor/three/LICENSE", content_type: TEXT, body: include_str!("../../web/vendor/three/LICENSE") },
    Asset { name: "vendor/three/three.module.min.js", content_type: JS, body: include_str!("../../web/vendor/three/three.module.min.js") },
    Asset { name: "vendor/three/three.core.min.js", content_type: JS, body: include_str!("../../web/vendor/three/three.core.min.js") },
    Asset { name: "vendor/three/addons/controls/OrbitControls.js", content_type: JS, body: include_str!("../../web/vendor/three/addons/controls/OrbitControls.js") },
    Asset { name: "vendor/three/addons/controls/TransformControls.js", content_type: JS, body: include_str!("../../web/vendor/three/addons/controls/TransformControls.js") },
    Asset { name: "vendor/three/addons/postprocessing/Pass.js", content_type: JS, body: include_str!("../../web/vendor/three/addons/postprocessing/Pass.js") },
];

/// The vendored libraries' licence files; each is served too.
pub const LICENSES: [&str; 3] = ["vendor/model-viewer/LICENSE", "vendor/spark/LICENSE", "vendor/three/LICENSE"];

/// The strong entity tag of an asset: its CRC-32 and length, quoted.
pub fn etag(asset: &Asset) -> String {
    format!("\"{:08x}-{:x}\"", crc32fast::hash(asset.body.as_bytes()), asset.body.len())
}

/// The assets' tags, computed once (the vendored library is megabytes).
fn tag_of(index: usize) -> &'static str {
    static TAGS: std::sync::OnceLock<Vec<String>> = std::sync::OnceLock::new();
    &TAGS.get_or_init(|| ASSETS.iter().map(etag).collect())[index]
}

fn serve(index: usize, headers: &HeaderMap) -> Response {
    let asset = &ASSETS[index];
    let tag = tag_of(index);
    let cached = headers
        .get(IF_NONE_MATCH)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.split(',').any(|t| t.trim() == tag || t.trim() == "*"));
    let common = [
        (ETAG, HeaderValue::from_str(tag).unwrap_or(HeaderValue::from_static("\"0\""))),
        (CACHE_CONTROL, HeaderValue::from_static("no-cache")),
    ];
    if cached {
        return (StatusCode::NOT_MODIFIED, common).into_response();
    }
    (common, [(CONTENT_TYPE, HeaderValue::from_static(asset.content_type))], asset.body).into_response()
}

/// `GET /`: the page.
pub async fn index(headers: HeaderMap) -> Response {
    serve(0, &headers)
}

/// `GET /assets/{*path}`: the scripts, the style sheet, the vendored
/// libraries and their licences.
pub async fn asset(Path(name): Path<String>, headers: HeaderMap) -> Response {
    match ASSETS.iter().position(|a| a.name == name) {
        Some(i) => serve(i, &headers),
        None => ApiError::new(Code::NotFound, format!("no asset '{name}'")).into_response(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every file under `web/` (the folder as built).
    fn files_of_web() -> Vec<String> {
        fn walk(root: &std::path::Path, dir: &std::path::Path, out: &mut Vec<String>) {
            for e in std::fs::read_dir(dir).unwrap() {
                let p = e.unwrap().path();
                if p.is_dir() {
                    walk(root, &p, out);
                } else {
                    out.push(p.strip_prefix(root).unwrap().to_string_lossy().replace('\\', "/"));
                }
            }
        }
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("web");
        let mut out = Vec::new();
        walk(&root, &root, &mut out);
        out
    }

    #[test]
    fn every_file_of_web_is_served_and_linked() {
        let served: Vec<&str> = ASSETS.iter().map(|a| a.name).collect();
        for f in files_of_web() {
            assert!(
                served.contains(&f.as_str()) || f == "vendor/README.md",
                "web/{f} is not in ASSETS: add it to the table"
            );
        }
        // The page loads the app and the style sheet; the app's modules
        // import one another: each is named by some other file (but the
        // splat viewer, which pages import when they show splats).
        let page = ASSETS[0].body;
        assert!(page.contains("<script type=\"module\" src=\"/assets/app.js\">"));
        assert!(page.contains("/assets/style.css"));
        for a in ASSETS.iter().filter(|a| a.name.ends_with(".js") && !["app.js", "splats.js"].contains(&a.name)) {
            let file = a.name.rsplit('/').next().unwrap();
            assert!(ASSETS.iter().any(|b| b.name != a.name && b.body.contains(file)), "nothing loads {}", a.name);
        }
        for l in LICENSES {
            assert!(served.contains(&l), "{l}");
        }
        let tags: std::collections::HashSet<String> = ASSETS.iter().map(etag).collect();
        assert_eq!(tags.len(), ASSETS.len());
    }

    #[tokio::test]
    async fn a_matching_etag_gets_304() {
        let r = index(HeaderMap::new()).await;
        assert_eq!(r.status(), StatusCode::OK);
        let tag = r.headers()[ETAG].clone();
        assert_eq!(r.headers()[CACHE_CONTROL], "no-cache");
        let mut h = HeaderMap::new();
        h.insert(IF_NONE_MATCH, tag);
        assert_eq!(index(h).await.status(), StatusCode::NOT_MODIFIED);
        let mut h = HeaderMap::new();
        h.insert(IF_NONE_MATCH, HeaderValue::from_static("\"other\""));
        assert_eq!(index(h).await.status(), StatusCode::OK);
        assert_eq!(asset(Path("nope.js".into()), HeaderMap::new()).await.status(), StatusCode::NOT_FOUND);
        // A vendored file, in a folder, revalidates the same way.
        let r = asset(Path("vendor/spark/spark.module.min.js".into()), HeaderMap::new()).await;
        assert_eq!(r.status(), StatusCode::OK);
        assert_eq!(r.headers()[CONTENT_TYPE], JS);
        let mut h = HeaderMap::new();
        h.insert(IF_NONE_MATCH, r.headers()[ETAG].clone());
        let again = asset(Path("vendor/spark/spark.module.min.js".into()), h).await;
        assert_eq!(again.status(), StatusCode::NOT_MODIFIED);
    }
}
