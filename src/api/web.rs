//! The web app: `GET /` and `GET /assets/{name}` serve the page, its script
//! and its style sheet, embedded in the binary (`web/` at build time), so
//! `radiance serve` is all a user runs. The page talks to the same REST API
//! as every other client.
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

/// Every file of the page.
pub const ASSETS: [Asset; 3] = [
    Asset { name: "index.html", content_type: "text/html; charset=utf-8", body: include_str!("../../web/index.html") },
    Asset { name: "app.js", content_type: "text/javascript; charset=utf-8", body: include_str!("../../web/app.js") },
    Asset { name: "style.css", content_type: "text/css; charset=utf-8", body: include_str!("../../web/style.css") },
];

/// The strong entity tag of an asset: its CRC-32 and length, quoted.
pub fn etag(asset: &Asset) -> String {
    format!("\"{:08x}-{:x}\"", crc32fast::hash(asset.body.as_bytes()), asset.body.len())
}

fn serve(asset: &Asset, headers: &HeaderMap) -> Response {
    let tag = etag(asset);
    let cached = headers
        .get(IF_NONE_MATCH)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.split(',').any(|t| t.trim() == tag || t.trim() == "*"));
    let common = [
        (ETAG, HeaderValue::from_str(&tag).unwrap_or(HeaderValue::from_static("\"0\""))),
        (CACHE_CONTROL, HeaderValue::from_static("no-cache")),
    ];
    if cached {
        return (StatusCode::NOT_MODIFIED, common).into_response();
    }
    (common, [(CONTENT_TYPE, HeaderValue::from_static(asset.content_type))], asset.body).into_response()
}

/// `GET /`: the page.
pub async fn index(headers: HeaderMap) -> Response {
    serve(&ASSETS[0], &headers)
}

/// `GET /assets/{name}`: the script and the style sheet.
pub async fn asset(Path(name): Path<String>, headers: HeaderMap) -> Response {
    match ASSETS.iter().find(|a| a.name == name) {
        Some(a) => serve(a, &headers),
        None => ApiError::new(Code::NotFound, format!("no asset '{name}'")).into_response(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_page_links_its_assets_and_they_are_served() {
        let page = ASSETS[0].body;
        for a in &ASSETS[1..] {
            assert!(page.contains(&format!("/assets/{}", a.name)), "index.html does not link {}", a.name);
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
    }
}
