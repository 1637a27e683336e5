//! The one error type of the API and its code -> status table.
//!
//! Client errors explain themselves to the client; internal errors are
//! logged with their detail and answered with a generic message. The
//! errors of the parts handlers call (scheduler, archives, datasets,
//! checkpoints, videos, files, worker tasks) convert here, in one place, so
//! handlers use `?`.
//!
//! `details` is null or an object a program can act on:
//! - `not_found`: `{"kind": "scene"|"job"|"model"|"video", "id"}`;
//! - `conflict`: the same, and the job in the way (`job`, `job_status`);
//! - `payload_too_large`: the limit passed, `limit_bytes`, `limit_entries`
//!   or `limit_ratio`;
//! - `bad_request` on one input: `{"field", "value", "allowed"}` (the
//!   query parameter or body field, the value given, what is allowed);
//!   on a model configuration: `{"fields": [...]}` of those;
//! - `queue_full`: `{"queued"}`; `resource_limit` and
//!   `insufficient_storage`: see `limits`.

use axum::Json;
use axum::http::header::WWW_AUTHENTICATE;
use axum::http::{HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use serde_json::{Value, json};

use super::archive::{ArchiveError, Limit};
use crate::engine::front::{AppearanceError, CheckpointError, DatasetError};
use crate::jobs::SchedError;
use crate::media::video::VideoError;

/// Stable error codes, as clients see them.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Code {
    BadRequest,
    Unauthorized,
    NotFound,
    MethodNotAllowed,
    Conflict,
    PayloadTooLarge,
    UnsupportedMediaType,
    InvalidDataset,
    /// A crop box that cannot be used (`PUT /v1/models/{id}/crop`).
    InvalidCrop,
    QueueFull,
    /// The job would need more memory than the server allows one job.
    ResourceLimit,
    /// The job's output would leave less free disk than the reserve.
    InsufficientStorage,
    /// A route that answers at once took too long (`layers::QUICK_TIMEOUT`).
    Timeout,
    Internal,
    /// A store the node needs cannot serve now (/readyz).
    Unavailable,
}

impl Code {
    /// The table: code name and HTTP status.
    pub fn info(self) -> (&'static str, StatusCode) {
        match self {
            Code::BadRequest => ("bad_request", StatusCode::BAD_REQUEST),
            Code::Unauthorized => ("unauthorized", StatusCode::UNAUTHORIZED),
            Code::NotFound => ("not_found", StatusCode::NOT_FOUND),
            Code::MethodNotAllowed => ("method_not_allowed", StatusCode::METHOD_NOT_ALLOWED),
            Code::Conflict => ("conflict", StatusCode::CONFLICT),
            Code::PayloadTooLarge => ("payload_too_large", StatusCode::PAYLOAD_TOO_LARGE),
            Code::UnsupportedMediaType => ("unsupported_media_type", StatusCode::UNSUPPORTED_MEDIA_TYPE),
            Code::InvalidDataset => ("invalid_dataset", StatusCode::UNPROCESSABLE_ENTITY),
            Code::InvalidCrop => ("invalid_crop", StatusCode::UNPROCESSABLE_ENTITY),
            Code::QueueFull => ("queue_full", StatusCode::SERVICE_UNAVAILABLE),
            Code::ResourceLimit => ("resource_limit", StatusCode::UNPROCESSABLE_ENTITY),
            Code::InsufficientStorage => ("insufficient_storage", StatusCode::INSUFFICIENT_STORAGE),
            Code::Timeout => ("timeout", StatusCode::REQUEST_TIMEOUT),
            Code::Internal => ("internal", StatusCode::INTERNAL_SERVER_ERROR),
            Code::Unavailable => ("unavailable", StatusCode::SERVICE_UNAVAILABLE),
        }
    }
}

/// The challenge every 401 carries (RFC 9110 section 11.6.1 requires one),
/// telling the client which scheme the service takes.
pub const BEARER_CHALLENGE: &str = "Bearer realm=\"radiance\"";

/// `{"error": {"code", "message", "details"}}` with the code's status.
#[derive(Debug)]
pub struct ApiError {
    pub code: Code,
    pub message: String,
    pub details: Value,
}

pub type ApiResult<T> = Result<T, ApiError>;

impl ApiError {
    pub fn new(code: Code, message: impl Into<String>) -> Self {
        Self { code, message: message.into(), details: Value::Null }
    }
    pub fn with_details(mut self, details: Value) -> Self {
        self.details = details;
        self
    }
    pub fn bad_request(m: impl Into<String>) -> Self {
        Self::new(Code::BadRequest, m)
    }
    /// A bad input: the query parameter or body field, the value given and
    /// what is allowed, in the message's words and in `details`.
    pub fn bad_field(message: impl Into<String>, field: &str, value: impl serde::Serialize, allowed: &str) -> Self {
        let details = json!({ "field": field, "value": value, "allowed": allowed });
        Self::bad_request(message).with_details(details)
    }
    /// `kind` is `scene`, `job`, `model` or `video`.
    pub fn not_found(kind: &str, id: &str) -> Self {
        Self::new(Code::NotFound, format!("{kind} '{id}' not found")).with_details(json!({ "kind": kind, "id": id }))
    }
    /// Over a size limit of uploads.
    pub fn too_large(message: impl Into<String>, limit: Limit) -> Self {
        let details = match limit {
            Limit::Bytes(n) => json!({ "limit_bytes": n }),
            Limit::Entries(n) => json!({ "limit_entries": n }),
            Limit::Ratio(n) => json!({ "limit_ratio": n }),
        };
        Self::new(Code::PayloadTooLarge, message).with_details(details)
    }
    pub fn conflict(m: impl Into<String>) -> Self {
        Self::new(Code::Conflict, m)
    }
    pub fn internal(m: impl std::fmt::Display) -> Self {
        Self::new(Code::Internal, m.to_string())
    }
}

/// A conflict with the job in the way.
fn in_use(message: String, kind: &str, id: &str, job: &str, status: &str) -> ApiError {
    ApiError::conflict(message).with_details(json!({ "kind": kind, "id": id, "job": job, "job_status": status }))
}

impl From<SchedError> for ApiError {
    fn from(e: SchedError) -> Self {
        let message = e.to_string();
        match &e {
            SchedError::SceneNotFound(id) => Self::not_found("scene", id),
            SchedError::SceneNotReady { scene, status, .. } => {
                Self::conflict(message).with_details(json!({ "kind": "scene", "id": scene, "status": status }))
            }
            SchedError::JobNotFound(id) => Self::not_found("job", id),
            SchedError::ModelNotFound(id) => Self::not_found("model", id),
            SchedError::VideoNotFound(id) => Self::not_found("video", id),
            SchedError::QueueFull(n) => Self::new(Code::QueueFull, message).with_details(json!({ "queued": n })),
            SchedError::SceneInUse { scene, job, status } => in_use(message, "scene", scene, job, status),
            SchedError::ModelInUse { model, job, status } => in_use(message, "model", model, job, status),
            SchedError::VideoInUse { video, job, status } => in_use(message, "video", video, job, status),
            SchedError::AlreadyFinal { id, status } | SchedError::JobNotFinal { id, status } => {
                Self::conflict(message).with_details(json!({ "kind": "job", "id": id, "status": status }))
            }
            SchedError::Io(_) => Self::internal(e),
        }
    }
}

impl From<ArchiveError> for ApiError {
    fn from(e: ArchiveError) -> Self {
        match e {
            ArchiveError::Bad(m) => Self::bad_request(m),
            ArchiveError::TooLarge { message, limit } => Self::too_large(message, limit),
            ArchiveError::Io(e) => Self::internal(e),
        }
    }
}

/// The uploaded dataset does not load (the caller names its files relative
/// to the upload).
impl From<DatasetError> for ApiError {
    fn from(e: DatasetError) -> Self {
        Self::new(Code::InvalidDataset, e.to_string())
    }
}

/// A stored checkpoint that does not load is the server's fault.
impl From<CheckpointError> for ApiError {
    fn from(e: CheckpointError) -> Self {
        Self::internal(e)
    }
}

/// Video settings the encoder refuses (size, frame rate) are the client's.
impl From<VideoError> for ApiError {
    fn from(e: VideoError) -> Self {
        match e {
            VideoError::Encoder { .. } => Self::internal(e),
            e => Self::bad_request(e.to_string()),
        }
    }
}

/// An `appearance` the model does not have is the client's: the message
/// and `details.allowed` name the images it does have.
impl From<AppearanceError> for ApiError {
    fn from(e: AppearanceError) -> Self {
        match &e {
            AppearanceError::NotTrained { image, valid } => {
                Self::bad_field(e.to_string(), "appearance", image, &format!("mean, or a training image: {valid}"))
            }
            AppearanceError::NoCameras => {
                Self::bad_field(e.to_string(), "appearance", "nearest", "mean, or a training image's index")
            }
        }
    }
}

impl From<std::io::Error> for ApiError {
    fn from(e: std::io::Error) -> Self {
        Self::internal(e)
    }
}

impl From<tokio::task::JoinError> for ApiError {
    fn from(e: tokio::task::JoinError) -> Self {
        Self::internal(format!("worker task failed: {e}"))
    }
}

impl From<axum::extract::rejection::JsonRejection> for ApiError {
    fn from(e: axum::extract::rejection::JsonRejection) -> Self {
        use axum::extract::rejection::JsonRejection as J;
        match e {
            J::MissingJsonContentType(_) => {
                Self::new(Code::UnsupportedMediaType, "expected a JSON body (Content-Type: application/json)")
            }
            // A body over axum's limit for JSON (`DefaultBodyLimit`, 2 MiB).
            other if other.status() == StatusCode::PAYLOAD_TOO_LARGE => Self::too_large(
                format!("the JSON body is larger than {JSON_BODY_LIMIT} bytes"),
                Limit::Bytes(JSON_BODY_LIMIT as u64),
            ),
            other => Self::bad_request(other.body_text()),
        }
    }
}

/// The largest JSON body a route takes: axum's default body limit for its
/// `Json` extractor.
pub const JSON_BODY_LIMIT: usize = 2 << 20;

impl From<axum::extract::rejection::QueryRejection> for ApiError {
    fn from(e: axum::extract::rejection::QueryRejection) -> Self {
        Self::bad_request(e.body_text())
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let (name, status) = self.code.info();
        let message = if self.code == Code::Internal {
            tracing::error!(error = %self.message, "internal error");
            "internal error (see the server log)".to_string()
        } else {
            self.message
        };
        let body = json!({ "error": { "code": name, "message": message, "details": self.details } });
        let mut response = (status, Json(body)).into_response();
        if self.code == Code::Unauthorized {
            response.headers_mut().insert(WWW_AUTHENTICATE, HeaderValue::from_static(BEARER_CHALLENGE));
        }
        response
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn code_and_details(e: ApiError) -> (&'static str, Value) {
        (e.code.info().0, e.details)
    }

    #[test]
    fn scheduler_errors_keep_their_codes_and_name_what_they_are_about() {
        let e = ApiError::from(SchedError::ModelNotFound("mdl_a".into()));
        assert_eq!(code_and_details(e), ("not_found", json!({ "kind": "model", "id": "mdl_a" })));
        let e = ApiError::from(SchedError::JobNotFound("job_a".into()));
        assert_eq!(e.message, "job 'job_a' not found");
        let e =
            ApiError::from(SchedError::SceneInUse { scene: "scn_a".into(), job: "job_a".into(), status: "running" });
        let want = json!({ "kind": "scene", "id": "scn_a", "job": "job_a", "job_status": "running" });
        assert_eq!(code_and_details(e), ("conflict", want));
        let e = ApiError::from(SchedError::AlreadyFinal { id: "job_a".into(), status: "failed" });
        assert_eq!(code_and_details(e), ("conflict", json!({ "kind": "job", "id": "job_a", "status": "failed" })));
        assert_eq!(code_and_details(SchedError::QueueFull(7).into()), ("queue_full", json!({ "queued": 7 })));
        let e = ApiError::from(SchedError::Io(std::io::Error::other("disk on fire")));
        assert_eq!(code_and_details(e), ("internal", Value::Null));
    }

    #[test]
    fn archive_limits_are_in_the_details() {
        let e = ApiError::from(ArchiveError::TooLarge { message: "big".into(), limit: Limit::Bytes(1024) });
        assert_eq!(code_and_details(e), ("payload_too_large", json!({ "limit_bytes": 1024 })));
        let e = ApiError::from(ArchiveError::TooLarge { message: "many".into(), limit: Limit::Entries(3) });
        assert_eq!(e.details, json!({ "limit_entries": 3 }));
        let e = ApiError::from(ArchiveError::TooLarge { message: "bomb".into(), limit: Limit::Ratio(100) });
        assert_eq!(e.details, json!({ "limit_ratio": 100 }));
        assert_eq!(ApiError::from(ArchiveError::Bad("no".into())).code, Code::BadRequest);
    }

    #[test]
    fn the_body_carries_the_details_and_hides_internal_messages() {
        let body = |e: ApiError| {
            let r = e.into_response();
            let status = r.status();
            let rt = tokio::runtime::Builder::new_current_thread().build().unwrap();
            let bytes = rt.block_on(axum::body::to_bytes(r.into_body(), 1 << 16)).unwrap();
            (status, serde_json::from_slice::<Value>(&bytes).unwrap())
        };
        let (status, v) = body(ApiError::not_found("video", "vid_a"));
        assert_eq!(status, StatusCode::NOT_FOUND);
        assert_eq!(v["error"]["details"], json!({ "kind": "video", "id": "vid_a" }));
        let (status, v) = body(ApiError::internal("secret path /srv/x"));
        assert_eq!(status, StatusCode::INTERNAL_SERVER_ERROR);
        assert!(!v["error"]["message"].as_str().unwrap().contains("secret"), "{v}");
    }
}
