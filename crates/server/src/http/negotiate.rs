//! Content negotiation: request bodies decoded as JSON or bincode by their Content-Type
//! (types a cross-origin page could send unasked are refused), responses encoded as the
//! client's `Accept` asks ([`Accept`], an extractor, and its [`Accept::reply`]).

use std::convert::Infallible;

use axum::extract::FromRequestParts;
use axum::http::request::Parts;
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use crowdmorph_proto::{CONTENT_TYPE_BINCODE, CONTENT_TYPE_JSON};
use serde::Serialize;
use serde::de::DeserializeOwned;

use super::error::{ApiError, ApiResult};
use crowdmorph_store::codec;

/// The encoding a client asked responses in: bincode when its `Accept` names
/// `application/x-bincode`, JSON otherwise.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Accept {
    /// Bincode rather than JSON.
    pub bincode: bool,
}

impl Accept {
    /// What `headers` ask for.
    pub fn of(headers: &HeaderMap) -> Accept {
        Accept {
            bincode: headers
                .get_all(header::ACCEPT)
                .iter()
                .filter_map(|v| v.to_str().ok())
                .any(|v| v.to_ascii_lowercase().contains(CONTENT_TYPE_BINCODE)),
        }
    }

    /// `value` as a response with `status`, encoded as asked.
    pub fn reply<T: Serialize>(self, status: StatusCode, value: &T) -> ApiResult {
        let (ct, body) = if self.bincode {
            (
                CONTENT_TYPE_BINCODE,
                codec::to_wire(value).map_err(ApiError::internal)?,
            )
        } else {
            (
                CONTENT_TYPE_JSON,
                serde_json::to_vec(value).map_err(ApiError::internal)?,
            )
        };
        Ok((
            status,
            [(header::CONTENT_TYPE, HeaderValue::from_static(ct))],
            body,
        )
            .into_response())
    }

    /// The Content-Type of a response in this encoding.
    pub fn content_type(self) -> &'static str {
        if self.bincode {
            CONTENT_TYPE_BINCODE
        } else {
            CONTENT_TYPE_JSON
        }
    }
}

impl<S: Send + Sync> FromRequestParts<S> for Accept {
    type Rejection = Infallible;

    async fn from_request_parts(parts: &mut Parts, _: &S) -> Result<Accept, Infallible> {
        Ok(Accept::of(&parts.headers))
    }
}

/// The request's media type, lowercase, without parameters (`""` without one).
pub fn content_type(headers: &HeaderMap) -> String {
    headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .map(|v| {
            v.split(';')
                .next()
                .unwrap_or_default()
                .trim()
                .to_ascii_lowercase()
        })
        .unwrap_or_default()
}

/// Content types a web page may send to any origin without a CORS preflight (a "simple"
/// request), plus no type at all. A body arriving with one of them may come from any page
/// the user has open, so no request body is accepted with them: a page on another origin
/// cannot make this server (on localhost, say) change or compute anything.
const SIMPLE_CONTENT_TYPES: [&str; 4] = [
    "",
    "text/plain",
    "application/x-www-form-urlencoded",
    "multipart/form-data",
];

/// 415 for a body sent with a type web pages can send unasked.
fn simple_content_type(ct: &str, expected: &str) -> ApiError {
    let got = if ct.is_empty() {
        "no Content-Type".to_string()
    } else {
        format!("Content-Type {ct:?}")
    };
    ApiError::new(
        StatusCode::UNSUPPORTED_MEDIA_TYPE,
        "unsupported_media_type",
        format!(
            "the body came with {got}; send it as {expected} (types a web page on another \
             origin could send without asking are refused)"
        ),
    )
}

/// The body's content type, refused when a cross-origin page could have sent it.
pub fn checked_content_type(headers: &HeaderMap, expected: &str) -> Result<String, ApiError> {
    let ct = content_type(headers);
    if SIMPLE_CONTENT_TYPES.contains(&ct.as_str()) {
        return Err(simple_content_type(&ct, expected));
    }
    Ok(ct)
}

/// Decodes a request body as JSON or bincode according to its Content-Type.
pub fn decode<T: DeserializeOwned>(headers: &HeaderMap, body: &[u8]) -> Result<T, ApiError> {
    let expected = "application/json (or application/x-bincode)";
    let ct = checked_content_type(headers, expected)?;
    match ct.as_str() {
        CONTENT_TYPE_BINCODE => decode_as(true, body),
        CONTENT_TYPE_JSON => decode_as(false, body),
        other => Err(ApiError::new(
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "unsupported_media_type",
            format!("content type {other:?} is not {CONTENT_TYPE_JSON} or {CONTENT_TYPE_BINCODE}"),
        )),
    }
}

/// Decodes `body` as bincode or as JSON (400 `malformed_bincode` or `malformed_json`, the
/// latter with the path of the field that is wrong): a request body once its type is known,
/// or a WebSocket message (binary or text).
pub fn decode_as<T: DeserializeOwned>(bincode: bool, body: &[u8]) -> Result<T, ApiError> {
    if bincode {
        return codec::request_from_wire(body)
            .map_err(|e| ApiError::bad_request("malformed_bincode", e.to_string()));
    }
    // The path (`heads[3].frame`) tells a human which field is wrong.
    let mut de = serde_json::Deserializer::from_slice(body);
    let value = serde_path_to_error::deserialize(&mut de).map_err(|e| {
        let path = e.path().to_string();
        let inner = e.into_inner();
        let at = if path == "." {
            String::new()
        } else {
            format!(" at {path}")
        };
        ApiError::bad_request("malformed_json", format!("malformed JSON{at}: {inner}"))
    })?;
    de.end()
        .map_err(|e| ApiError::bad_request("malformed_json", format!("malformed JSON: {e}")))?;
    Ok(value)
}

/// Whether `headers` say the body is bincode.
pub fn is_bincode(headers: &HeaderMap) -> bool {
    content_type(headers) == CONTENT_TYPE_BINCODE
}

/// A response of `status` with a JSON `text` body.
pub fn json_text(status: StatusCode, text: impl Into<axum::body::Body>) -> Response {
    (
        status,
        [(
            header::CONTENT_TYPE,
            HeaderValue::from_static(CONTENT_TYPE_JSON),
        )],
        text.into(),
    )
        .into_response()
}
