//! The rate-limited log of shed and timed-out requests: counted in metrics, summarized in at
//! most one WARN line a second.

use std::sync::Mutex;
use std::time::Duration;

use axum::http::StatusCode;

/// How often at most [`ShedLog`] writes a line.
pub const SHED_LOG_EVERY: Duration = Duration::from_secs(1);

/// Requests answered 503 (shed, queue full, not ready) or 504 (past a deadline) are normal
/// operation under load: each is counted in metrics (`crowdmorph_rejected_total` by reason,
/// `crowdmorph_http_requests_total` by status), and the log gets at most one WARN line per
/// [`SHED_LOG_EVERY`] with how many there were. tower-http's default `on_failure` logged each
/// one at ERROR instead: 215,479 lines (74 MB) in 30 s of a storm of 600 connections.
#[derive(Debug, Default)]
pub struct ShedLog(Mutex<ShedCounts>);

#[derive(Debug, Default)]
struct ShedCounts {
    unavailable: u64,
    timed_out: u64,
    /// When the last line was written.
    last: Option<std::time::Instant>,
}

impl ShedLog {
    /// Counts a 503 or 504 answer.
    pub fn record(&self, status: StatusCode) {
        let Ok(mut counts) = self.0.lock() else {
            return;
        };
        if status == StatusCode::GATEWAY_TIMEOUT {
            counts.timed_out += 1;
        } else {
            counts.unavailable += 1;
        }
        counts.write_if_due();
    }

    /// Writes what is pending if a line is due; `serve` calls it every [`SHED_LOG_EVERY`], so
    /// the end of a burst is reported too, not only when the next one starts.
    pub fn flush(&self) {
        if let Ok(mut counts) = self.0.lock() {
            counts.write_if_due();
        }
    }
}

impl ShedCounts {
    fn write_if_due(&mut self) {
        let now = std::time::Instant::now();
        if self.unavailable + self.timed_out == 0
            || self
                .last
                .is_some_and(|t| now.duration_since(t) < SHED_LOG_EVERY)
        {
            return;
        }
        // Not inside the span of the request that happened to trigger the line.
        tracing::warn!(
            parent: None,
            unavailable_503 = self.unavailable,
            timed_out_504 = self.timed_out,
            "requests shed or past their deadline since the last such line \
             (see crowdmorph_rejected_total)"
        );
        self.unavailable = 0;
        self.timed_out = 0;
        self.last = Some(now);
    }
}
