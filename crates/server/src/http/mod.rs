//! What every handler shares, and nothing of any one resource: the JSON error
//! ([`error::ApiError`]), bodies read within limits and responses that keep their charge until
//! sent ([`body`]), validators of cached bodies ([`cache`]), content negotiation ([`negotiate`]), `Content-Encoding` both ways
//! ([`encoding`]), the `Admin`, `Ready` and `Query`
//! extractors ([`extract`]) and `Server-Timing` ([`timing`]). It imports nothing of the
//! server above it.

pub mod body;
pub mod cache;
pub mod encoding;
pub mod error;
pub mod extract;
pub mod negotiate;
pub mod timing;

pub use body::{BodyLimits, chunked_body, read_body};
pub use error::{ApiError, ApiResult};
pub use extract::{Admin, Gate, Query, Ready};
pub use negotiate::{Accept, checked_content_type, decode};
pub use timing::{SERVER_TIMING, ServerTiming, ms};

/// Runs `f` on the blocking pool (CPU-heavy work: imports, engine preparation, persistence);
/// a panic there is a 500.
pub async fn blocking<T: Send + 'static>(
    f: impl FnOnce() -> Result<T, ApiError> + Send + 'static,
) -> Result<T, ApiError> {
    tokio::task::spawn_blocking(f)
        .await
        .map_err(ApiError::internal)?
}
