//! Validators of bodies clients cache (images, layer texels, clip textures): the `ETag`, the
//! `Cache-Control` a versioned URL earns (`immutable` when its `?v=` is the tag), and the 304
//! a matching `If-None-Match` gets.

use axum::body::Body;
use axum::http::{HeaderMap, HeaderName, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};

use super::error::ApiError;

/// A body's `ETag` and `Cache-Control`.
pub struct Validator {
    quoted: String,
    etag: HeaderValue,
    cache: HeaderValue,
}

impl Validator {
    /// The validator of a body whose tag (unquoted) is `tag`, asked for at a URL whose `?v=`
    /// was `version`: `immutable` for a year when that is the tag, else `no-cache` (revalidate
    /// each time, a 304 when unchanged).
    pub fn new(tag: &str, version: Option<&str>) -> Result<Validator, ApiError> {
        let quoted = format!("\"{tag}\"");
        Ok(Validator {
            etag: HeaderValue::from_str(&quoted).map_err(ApiError::internal)?,
            quoted,
            cache: HeaderValue::from_static(if version == Some(tag) {
                "public, max-age=31536000, immutable"
            } else {
                "no-cache"
            }),
        })
    }

    /// The 304 for a request whose `If-None-Match` names this tag (or `*`).
    pub fn not_modified(&self, headers: &HeaderMap) -> Option<Response> {
        let matches = headers
            .get(header::IF_NONE_MATCH)
            .and_then(|v| v.to_str().ok())
            .is_some_and(|v| {
                v.split(',')
                    .any(|t| t.trim() == self.quoted || t.trim() == "*")
            });
        matches.then(|| (StatusCode::NOT_MODIFIED, self.headers()).into_response())
    }

    /// `ETag` and `Cache-Control`, for the answer with the body.
    pub fn headers(&self) -> [(HeaderName, HeaderValue); 2] {
        [
            (header::ETAG, self.etag.clone()),
            (header::CACHE_CONTROL, self.cache.clone()),
        ]
    }

    /// The 200 with `body` of type `content_type`, this validator's headers, and `keep` (what
    /// the body's memory is charged to, or what holds it) kept until the body is sent.
    pub fn respond<K: Send + Unpin + 'static>(
        &self,
        content_type: &'static str,
        body: impl Into<Body>,
        keep: K,
    ) -> Response {
        let response = (
            StatusCode::OK,
            [(header::CONTENT_TYPE, HeaderValue::from_static(content_type))],
            self.headers(),
            body.into(),
        )
            .into_response();
        super::body::hold(response, keep)
    }
}
