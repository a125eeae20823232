//! `Server-Timing` (W3C): where a response's time went, for load generators and browsers'
//! developer tools.

use std::time::Duration;

use axum::http::{HeaderName, HeaderValue};

/// The Server-Timing header.
pub const SERVER_TIMING: HeaderName = HeaderName::from_static("server-timing");

/// A duration as a `Server-Timing` `dur` value: milliseconds with three decimals.
pub fn ms(d: Duration) -> String {
    format!("{:.3}", d.as_secs_f64() * 1e3)
}

/// When the request arrived: set by the router's first layer ([`stamp_arrival`]), before any
/// extractor reads the body, so deadlines count from the request's first moment.
#[derive(Clone, Copy, Debug)]
pub struct Arrived(pub std::time::Instant);

impl<S: Send + Sync> axum::extract::FromRequestParts<S> for Arrived {
    type Rejection = std::convert::Infallible;

    async fn from_request_parts(
        parts: &mut axum::http::request::Parts,
        _: &S,
    ) -> Result<Arrived, std::convert::Infallible> {
        Ok(parts
            .extensions
            .get::<Arrived>()
            .copied()
            .unwrap_or_else(|| Arrived(std::time::Instant::now())))
    }
}

/// The layer that stamps each request with its [`Arrived`] time.
pub async fn stamp_arrival(
    mut req: axum::extract::Request,
    next: axum::middleware::Next,
) -> axum::response::Response {
    req.extensions_mut()
        .insert(Arrived(std::time::Instant::now()));
    next.run(req).await
}

/// A `Server-Timing` value built one stage at a time.
#[derive(Clone, Debug, Default)]
pub struct ServerTiming(Vec<(&'static str, Duration)>);

impl ServerTiming {
    /// Adds stage `name` that took `d`.
    pub fn with(mut self, name: &'static str, d: Duration) -> ServerTiming {
        self.0.push((name, d));
        self
    }

    /// The header value (`name;dur=ms, ...`); `None` if it is not a valid header (it always
    /// is: names are static and durations digits).
    pub fn header(&self) -> Option<HeaderValue> {
        let text = self
            .0
            .iter()
            .map(|(n, d)| format!("{n};dur={}", ms(*d)))
            .collect::<Vec<_>>()
            .join(", ");
        HeaderValue::from_str(&text).ok()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn server_timing_durations_are_milliseconds_with_three_decimals() {
        assert_eq!(ms(Duration::from_nanos(1_234_567)), "1.235");
        assert_eq!(ms(Duration::ZERO), "0.000");
        let t = ServerTiming::default()
            .with("queue", Duration::from_micros(1500))
            .with("compute", Duration::from_nanos(2_000_400));
        assert_eq!(
            t.header().expect("a header").to_str().expect("ASCII"),
            "queue;dur=1.500, compute;dur=2.000"
        );
    }
}
