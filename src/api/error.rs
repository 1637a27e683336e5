//! The one error type of the API and its code -> status table.
//!
//! Client errors explain themselves to the client; internal errors are
//! logged with their detail and answered with a generic message.

use axum::Json;
use axum::http::header::WWW_AUTHENTICATE;
use axum::http::{HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use serde_json::{Value, json};

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
    QueueFull,
    /// The job would need more memory than the server allows one job.
    ResourceLimit,
    /// The job's output would leave less free disk than the reserve.
    InsufficientStorage,
    Internal,
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
            Code::QueueFull => ("queue_full", StatusCode::SERVICE_UNAVAILABLE),
            Code::ResourceLimit => ("resource_limit", StatusCode::UNPROCESSABLE_ENTITY),
            Code::InsufficientStorage => ("insufficient_storage", StatusCode::INSUFFICIENT_STORAGE),
            Code::Internal => ("internal", StatusCode::INTERNAL_SERVER_ERROR),
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
    pub fn not_found(what: &str, id: &str) -> Self {
        Self::new(Code::NotFound, format!("{what} '{id}' not found"))
    }
    pub fn conflict(m: impl Into<String>) -> Self {
        Self::new(Code::Conflict, m)
    }
    pub fn internal(m: impl std::fmt::Display) -> Self {
        Self::new(Code::Internal, m.to_string())
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
            other => Self::bad_request(other.body_text()),
        }
    }
}

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
