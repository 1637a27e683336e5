//! The tower-http layers around the router, in one place:
//!
//! - request ids: every request gets an `x-request-id` (a client's own is
//!   kept), answered back in the response and carried by the `request`
//!   span in which the handler's logs are written;
//! - tracing: one log line per answer (at `info` for requests that change
//!   something or fail, at `debug` for successful reads, which the viewer
//!   sends many of);
//! - compression (gzip, for clients that accept it) of text and JSON
//!   answers; never of images, videos or event streams;
//! - a body limit (`--max-upload-mb`) on every request, and an idle timeout
//!   on reading request bodies (a stalled upload ends with 400);
//! - CORS, only when origins are configured (`--cors-origin`).
//!
//! Routes that answer at once also get a timeout (`quick`); renders, event
//! streams, uploads and video downloads take as long as their work does.
//! tower-http's own 408 and 413 answers are given the API's JSON envelope by
//! [`envelopes`].

use std::time::Duration;

use axum::Router;
use axum::extract::Request;
use axum::http::header::{ALLOW, AUTHORIZATION, CONTENT_TYPE};
use axum::http::{HeaderName, HeaderValue, Method, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use axum::routing::MethodRouter;
use tower_http::compression::CompressionLayer;
use tower_http::compression::predicate::{DefaultPredicate, NotForContentType, Predicate};
use tower_http::cors::CorsLayer;
use tower_http::limit::RequestBodyLimitLayer;
use tower_http::request_id::{MakeRequestUuid, PropagateRequestIdLayer, RequestId, SetRequestIdLayer};
use tower_http::timeout::{RequestBodyTimeoutLayer, TimeoutLayer};
use tower_http::trace::{DefaultOnFailure, TraceLayer};
use tracing::Level;

use super::archive::Limit;
use super::{ApiError, AppState, Code};

/// How long a route that answers at once may take.
pub const QUICK_TIMEOUT: Duration = Duration::from_secs(30);

/// How long a request body may stall between two chunks.
pub const BODY_IDLE_TIMEOUT: Duration = Duration::from_secs(60);

/// A timeout (408) for a route that does no long work.
pub fn quick(route: MethodRouter<AppState>) -> MethodRouter<AppState> {
    route.layer(TimeoutLayer::with_status_code(StatusCode::REQUEST_TIMEOUT, QUICK_TIMEOUT))
}

/// Wraps the whole router in the layers listed in the module comment.
pub fn around(router: Router, max_body_bytes: u64, cors_origins: &[String]) -> Router {
    let limit = usize::try_from(max_body_bytes).unwrap_or(usize::MAX);
    let x_request_id = HeaderName::from_static("x-request-id");
    let compress = DefaultPredicate::new().and(NotForContentType::const_new("video/"));
    let trace = TraceLayer::new_for_http()
        .make_span_with(|req: &Request| {
            let id = req.extensions().get::<RequestId>().and_then(|id| id.header_value().to_str().ok()).unwrap_or("");
            tracing::info_span!("request", id = %id, method = %req.method(), path = %req.uri().path())
        })
        .on_request(())
        .on_response(|res: &Response, latency: Duration, _span: &tracing::Span| {
            let ms = latency.as_secs_f64() * 1e3;
            let status = res.status().as_u16();
            if res.status().is_success() || res.status() == StatusCode::NOT_MODIFIED {
                tracing::debug!(status, ms, "answered");
            } else {
                tracing::info!(status, ms, "answered");
            }
        })
        .on_failure(DefaultOnFailure::new().level(Level::WARN));
    let mut router = router
        .layer(RequestBodyTimeoutLayer::new(BODY_IDLE_TIMEOUT))
        .layer(RequestBodyLimitLayer::new(limit))
        // Outside the limit, whose 413 it wraps.
        .layer(axum::middleware::from_fn(move |req: Request, next: Next| envelopes(req, next, max_body_bytes)))
        .layer(CompressionLayer::new().gzip(true).compress_when(compress))
        .layer(PropagateRequestIdLayer::new(x_request_id.clone()))
        .layer(trace)
        .layer(SetRequestIdLayer::new(x_request_id, MakeRequestUuid));
    if let Some(cors) = cors(cors_origins) {
        router = router.layer(cors);
    }
    router
}

/// CORS for the given origins (none: no CORS layer, so browsers keep
/// other origins out).
fn cors(origins: &[String]) -> Option<CorsLayer> {
    if origins.is_empty() {
        return None;
    }
    let origins: Vec<HeaderValue> = origins.iter().filter_map(|o| HeaderValue::from_str(o).ok()).collect();
    Some(
        CorsLayer::new()
            .allow_origin(origins)
            .allow_methods([Method::GET, Method::POST, Method::DELETE])
            .allow_headers([AUTHORIZATION, CONTENT_TYPE])
            .expose_headers([HeaderName::from_static("x-request-id")]),
    )
}

/// Gives the answers that do not come from a handler the JSON envelope
/// every other error has: axum's 405 (a known path, another method), and
/// tower-http's 408 (timeout) and 413 (body over the limit, from its
/// `Content-Length`). For the 405 a middleware rather than
/// `Router::method_not_allowed_fallback`, because only the finished answer
/// carries the `Allow` header that axum computes, which the message quotes
/// and the answer keeps. (axum still drops the body of an answer to HEAD.)
pub async fn envelopes(req: Request, next: Next, max_body_bytes: u64) -> Response {
    let (method, path) = (req.method().clone(), req.uri().path().to_string());
    let response = next.run(req).await;
    let is_json = response.headers().get(CONTENT_TYPE).is_some_and(|c| c.as_bytes().starts_with(b"application/json"));
    match response.status() {
        StatusCode::METHOD_NOT_ALLOWED if !is_json => {
            let allow = response.headers().get(ALLOW).cloned();
            let allowed = allow.as_ref().and_then(|a| a.to_str().ok()).unwrap_or("none").replace(',', ", ");
            let message = format!("{method} is not allowed on {path} (allowed: {allowed})");
            let mut envelope = ApiError::new(Code::MethodNotAllowed, message).into_response();
            if let Some(a) = allow {
                envelope.headers_mut().insert(ALLOW, a);
            }
            envelope
        }
        StatusCode::PAYLOAD_TOO_LARGE if !is_json => {
            let message = format!("the request body is larger than {max_body_bytes} bytes");
            ApiError::too_large(message, Limit::Bytes(max_body_bytes)).into_response()
        }
        StatusCode::REQUEST_TIMEOUT if !is_json => {
            let secs = QUICK_TIMEOUT.as_secs();
            ApiError::new(Code::Timeout, format!("{method} {path} took longer than {secs} s")).into_response()
        }
        _ => response,
    }
}
