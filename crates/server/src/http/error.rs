//! The one error type of the HTTP API and how it becomes a response.
//!
//! Every 4xx and 5xx body is JSON `{"error":{"code":"...","message":"..."}}` whatever the request's
//! encoding, so that a client can always read why. Messages name the offending value (rig id,
//! clip name, frame, limit) but never internals: an unexpected failure is logged with its detail
//! and answered with a generic `internal` error.

use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use crowdmorph_proto::{ErrorBody, ErrorDetail};

use crowdmorph_core::budget::BudgetError;

/// What every handler returns.
pub type ApiResult = Result<Response, ApiError>;

/// An API error: a status, a stable code and a message for the client.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{status} {code}: {message}")]
pub struct ApiError {
    /// HTTP status.
    pub status: StatusCode,
    /// Stable snake_case code.
    pub code: &'static str,
    /// Human-readable message naming the problem.
    pub message: String,
    /// Seconds after which a retry may succeed (503 only).
    pub retry_after: Option<u32>,
}

impl ApiError {
    /// An error with a status, code and message.
    pub fn new(status: StatusCode, code: &'static str, message: impl Into<String>) -> ApiError {
        ApiError {
            status,
            code,
            message: message.into(),
            retry_after: None,
        }
    }

    /// 400 with a code.
    pub fn bad_request(code: &'static str, message: impl Into<String>) -> ApiError {
        ApiError::new(StatusCode::BAD_REQUEST, code, message)
    }

    /// 404 with a code.
    pub fn not_found(code: &'static str, message: impl Into<String>) -> ApiError {
        ApiError::new(StatusCode::NOT_FOUND, code, message)
    }

    /// 503 with a Retry-After.
    pub fn unavailable(code: &'static str, message: impl Into<String>, retry: u32) -> ApiError {
        ApiError {
            retry_after: Some(retry),
            ..ApiError::new(StatusCode::SERVICE_UNAVAILABLE, code, message)
        }
    }

    /// 500 for an unexpected failure; `detail` goes to the log, not to the client.
    pub fn internal(detail: impl std::fmt::Display) -> ApiError {
        tracing::error!(%detail, "internal error");
        ApiError::new(
            StatusCode::INTERNAL_SERVER_ERROR,
            "internal",
            "internal error; the server log has the details",
        )
    }

    /// A refused memory charge: 413 `too_large` when the operation can never fit its limit,
    /// 503 `memory_full` (retry later) when the pool is full now. Both messages name the bytes
    /// and the flag.
    pub fn budget(e: BudgetError, too_large: &'static str) -> ApiError {
        match e {
            BudgetError::TooLarge { .. } => {
                ApiError::new(StatusCode::PAYLOAD_TOO_LARGE, too_large, e.to_string())
            }
            BudgetError::Full { .. } => ApiError::unavailable("memory_full", e.to_string(), 5),
        }
    }

    /// The JSON body.
    pub fn body(&self) -> ErrorBody {
        ErrorBody {
            error: ErrorDetail {
                code: self.code.to_string(),
                message: self.message.clone(),
            },
        }
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let body = serde_json::to_vec(&self.body()).unwrap_or_else(|_| b"{}".to_vec());
        let mut resp = (
            self.status,
            [(
                header::CONTENT_TYPE,
                HeaderValue::from_static(crowdmorph_proto::CONTENT_TYPE_JSON),
            )],
            body,
        )
            .into_response();
        if let Some(s) = self.retry_after {
            resp.headers_mut()
                .insert(header::RETRY_AFTER, HeaderValue::from(s));
        }
        if self.status == StatusCode::UNAUTHORIZED {
            resp.headers_mut()
                .insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer"));
        }
        resp
    }
}
