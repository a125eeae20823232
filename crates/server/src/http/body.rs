//! Request bodies read within a limit and a deadline, and response bodies that carry the
//! charge of the memory they hold until they are sent.

use std::time::Duration;

use axum::body::Body;
use axum::http::{HeaderMap, StatusCode, header};
use bytes::Bytes;
use http_body_util::BodyExt;

use crowdmorph_core::budget::{Budget, BudgetError};

use super::error::ApiError;

/// How large a body may be and how long it may take to arrive.
#[derive(Clone, Copy, Debug)]
pub struct BodyLimits {
    /// Most bytes (413 past it).
    pub bytes: usize,
    /// Longest it may trickle in (408 past it).
    pub timeout: Duration,
}

/// The length a request declares (its Content-Length), at most `limit`; `limit` when it does
/// not say.
pub fn declared_length(headers: &HeaderMap, limit: usize) -> u64 {
    headers
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<u64>().ok())
        .unwrap_or(limit as u64)
        .min(limit as u64)
}

/// 408: a body that did not arrive within its time.
fn timed_out(limits: BodyLimits) -> ApiError {
    ApiError::new(
        StatusCode::REQUEST_TIMEOUT,
        "body_timeout",
        format!(
            "the request body did not arrive within {} s",
            limits.timeout.as_secs_f32()
        ),
    )
}

/// Reads a body within `limits`: 413 past the size (checked from Content-Length first, so an
/// oversized upload is refused before it is read), 408 past the deadline.
pub async fn read_body(
    headers: &HeaderMap,
    body: Body,
    limits: BodyLimits,
) -> Result<Bytes, ApiError> {
    let limit = limits.bytes;
    let too_large = || {
        ApiError::new(
            StatusCode::PAYLOAD_TOO_LARGE,
            "body_too_large",
            format!("request body is larger than the limit of {limit} bytes"),
        )
    };
    if let Some(len) = headers
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<u64>().ok())
        && len > limit as u64
    {
        return Err(too_large());
    }
    // A client that trickles its body holds a connection and a concurrency slot: it gets as
    // long as the request would be allowed to take, no more.
    let collected = tokio::time::timeout(
        limits.timeout,
        http_body_util::Limited::new(body, limit).collect(),
    )
    .await
    .map_err(|_| timed_out(limits))?;
    match collected {
        Ok(c) => Ok(c.to_bytes()),
        Err(e) if e.is::<http_body_util::LengthLimitError>() => {
            // `limit` bytes were read (a bomb inflates to the limit) and are free again: hand
            // them back, or a refused 256 MiB bomb leaves the process ~500 MB larger.
            if limit as u64 >= crowdmorph_core::budget::TRIM_AFTER_BYTES {
                crowdmorph_core::budget::return_freed_memory_soon();
            }
            Err(too_large())
        }
        Err(e) => Err(ApiError::bad_request(
            "body_unreadable",
            format!("could not read the request body: {e}"),
        )),
    }
}

/// Reads a body that declares no length (chunked, or inflated by a `Content-Encoding`) within
/// `limits`, charging each piece to `budget` before keeping it, so that an upload is charged
/// for what arrives rather than for the most it could be, and an empty one costs nothing and
/// reaches its route's own check. Pieces are joined into one buffer at the end: that copy is
/// charged before it is made and the pieces' charge released once they are dropped. 413
/// `body_too_large` past the size, 408 past the deadline, or `refused` of the budget's error.
pub async fn read_body_charged(
    body: Body,
    limits: BodyLimits,
    budget: &Budget,
    refused: impl Fn(BudgetError) -> ApiError,
) -> Result<Bytes, ApiError> {
    let limit = limits.bytes;
    let read = async {
        let mut body = body;
        let mut pieces: Vec<Bytes> = Vec::new();
        let mut total = 0usize;
        while let Some(frame) = body.frame().await {
            let frame = frame.map_err(|e| {
                ApiError::bad_request(
                    "body_unreadable",
                    format!("could not read the request body: {e}"),
                )
            })?;
            let Ok(data) = frame.into_data() else {
                continue;
            };
            total += data.len();
            if total > limit {
                // What was read is free again: hand it back, as `read_body` does for a bomb.
                drop(pieces);
                budget.release((total - data.len()) as u64);
                if limit as u64 >= crowdmorph_core::budget::TRIM_AFTER_BYTES {
                    crowdmorph_core::budget::return_freed_memory_soon();
                }
                return Err(ApiError::new(
                    StatusCode::PAYLOAD_TOO_LARGE,
                    "body_too_large",
                    format!("request body is larger than the limit of {limit} bytes"),
                ));
            }
            budget
                .charge(data.len() as u64, || {
                    format!("an upload body of {total} bytes so far")
                })
                .map_err(&refused)?;
            pieces.push(data);
        }
        Ok(match pieces.len() {
            0 => Bytes::new(),
            1 => pieces.swap_remove(0),
            _ => {
                budget
                    .charge(total as u64, || {
                        format!("joining an upload body of {total} bytes")
                    })
                    .map_err(&refused)?;
                let joined: Bytes = pieces.concat().into();
                drop(pieces);
                budget.release(total as u64);
                joined
            }
        })
    };
    tokio::time::timeout(limits.timeout, read)
        .await
        .map_err(|_| timed_out(limits))?
}

/// Keeps what a response holds (its memory charge) alive until its last byte has been sent.
struct Owned<K> {
    bytes: Bytes,
    _keep: K,
}

impl<K> AsRef<[u8]> for Owned<K> {
    fn as_ref(&self) -> &[u8] {
        &self.bytes
    }
}

/// A body made of shared chunks with a known total length, so that hyper sends a
/// Content-Length (no chunked framing) and writes the chunks with vectored writes, uncopied.
struct ChunkBody {
    chunks: std::collections::VecDeque<Bytes>,
    remaining: u64,
}

impl http_body::Body for ChunkBody {
    type Data = Bytes;
    type Error = std::convert::Infallible;

    fn poll_frame(
        mut self: std::pin::Pin<&mut Self>,
        _: &mut std::task::Context<'_>,
    ) -> std::task::Poll<Option<Result<http_body::Frame<Bytes>, Self::Error>>> {
        let next = self.chunks.pop_front();
        if let Some(c) = &next {
            self.remaining -= c.len() as u64;
        }
        std::task::Poll::Ready(next.map(|c| Ok(http_body::Frame::data(c))))
    }

    fn is_end_stream(&self) -> bool {
        self.chunks.is_empty()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        http_body::SizeHint::with_exact(self.remaining)
    }
}

/// A response body of `chunks` that holds `keep` (a memory charge) until it has been sent, or
/// the connection dropped.
pub fn chunked_body<K: Send + 'static>(mut chunks: Vec<Bytes>, keep: K) -> Body {
    // The last chunk carries what is kept: released when the whole body has gone.
    let last = chunks.pop().unwrap_or_default();
    chunks.push(Bytes::from_owner(Owned {
        bytes: last,
        _keep: keep,
    }));
    let remaining = chunks.iter().map(|c| c.len() as u64).sum();
    Body::new(ChunkBody {
        chunks: chunks.into_iter().filter(|c| !c.is_empty()).collect(),
        remaining,
    })
}

/// Keeps `keep` with a response body until the body has been sent (or the connection dropped).
struct HoldBody<K> {
    body: Body,
    _keep: K,
}

impl<K: Unpin> http_body::Body for HoldBody<K> {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(
        mut self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<Option<Result<http_body::Frame<Bytes>, Self::Error>>> {
        std::pin::Pin::new(&mut self.body).poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.body.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.body.size_hint()
    }
}

/// A 200 JSON answer of `value`, keeping `keep` (the charge of the memory it was built in)
/// until it has been sent.
pub fn json_held<K: Send + Unpin + 'static>(
    value: &serde_json::Value,
    keep: K,
) -> axum::response::Response {
    use axum::response::IntoResponse;
    let response = (
        StatusCode::OK,
        [(
            header::CONTENT_TYPE,
            axum::http::HeaderValue::from_static(crowdmorph_proto::CONTENT_TYPE_JSON),
        )],
        value.to_string(),
    )
        .into_response();
    hold(response, keep)
}

/// `response` with `keep` (a memory charge) held until its body has been sent.
pub fn hold<K: Send + Unpin + 'static>(
    response: axum::response::Response,
    keep: K,
) -> axum::response::Response {
    let (parts, body) = response.into_parts();
    axum::response::Response::from_parts(parts, Body::new(HoldBody { body, _keep: keep }))
}
