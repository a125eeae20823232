//! The report of a load run (the same for `crowdmorph load --json` and `POST /v1/loadtest`) and
//! its text table.

use hdrhistogram::Histogram;
use serde::{Deserialize, Serialize};

/// Percentiles of a distribution, milliseconds.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Percentiles {
    /// Median.
    pub p50: f64,
    /// 90th percentile.
    pub p90: f64,
    /// 99th percentile.
    pub p99: f64,
    /// 99.9th percentile.
    pub p999: f64,
    /// Largest value.
    pub max: f64,
    /// Mean.
    pub mean: f64,
    /// Values recorded.
    pub count: u64,
}

impl Percentiles {
    /// Of a histogram of microseconds.
    pub fn of(h: &Histogram<u64>) -> Percentiles {
        if h.is_empty() {
            return Percentiles::default();
        }
        let ms = |us: u64| us as f64 / 1e3;
        Percentiles {
            p50: ms(h.value_at_quantile(0.5)),
            p90: ms(h.value_at_quantile(0.9)),
            p99: ms(h.value_at_quantile(0.99)),
            p999: ms(h.value_at_quantile(0.999)),
            max: ms(h.max()),
            mean: h.mean() / 1e3,
            count: h.len(),
        }
    }
}

/// Failed requests with one status and code.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ErrorCount {
    /// HTTP status; 0 when no response came.
    pub status: u16,
    /// The JSON error body's code (`queue_full`, ...), `transport` or `connect` without a
    /// response, empty when the body had none.
    pub code: String,
    /// How many.
    pub count: u64,
}

/// The server's own timings of the successful requests (their `Server-Timing` headers).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ServerTimings {
    /// From admission to the start of the batch that computed the request's last job.
    pub queue_ms: Percentiles,
    /// Engine wall time of the request's batches.
    pub compute_ms: Percentiles,
    /// Building the response body.
    pub encode_ms: Percentiles,
    /// From the request's arrival (a session's tick start) to the response (the tick's
    /// message) being ready to send.
    #[serde(default)]
    pub total_ms: Percentiles,
}

/// One viewer of a sessions run, over the window.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ViewerReport {
    /// Tick messages received.
    pub received: u64,
    /// Ticks missed: gaps in the tick numbers received.
    pub missed: u64,
    /// Bytes of the messages received.
    pub bytes: u64,
    /// Heads whose new buffer the messages carried.
    pub heads: u64,
    /// Mean latency of its messages from their ticks' due times, milliseconds.
    pub latency_mean_ms: f64,
    /// Largest such latency, milliseconds.
    pub latency_max_ms: f64,
    /// The close code, when the stream was closed before the viewer was done.
    pub close_code: Option<u16>,
    /// Its reason.
    pub close_reason: Option<String>,
}

/// What a sessions run (`crowdmorph load --session`) measured besides the common fields.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SessionReport {
    /// The session's id.
    pub id: String,
    /// Whether the run created the session (and deleted it at the end).
    pub created: bool,
    /// Its ticks per second.
    pub fps: f64,
    /// Its heads.
    pub heads: u64,
    /// Viewers connected.
    pub viewers: usize,
    /// Ticks due per viewer in the window.
    pub ticks_due: u64,
    /// Tick messages received in the window, all viewers together.
    pub ticks_received: u64,
    /// Ticks missed (gaps in the tick numbers), all viewers together.
    pub ticks_missed: u64,
    /// Mean bytes of a message.
    pub bytes_per_message: f64,
    /// Mean heads whose new buffer a message carried.
    pub changed_heads_per_message: f64,
    /// Each viewer.
    pub per_viewer: Vec<ViewerReport>,
}

/// What a load run measured, over the window after the warm-up.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct LoadReport {
    /// Target requests per second.
    pub rate: f64,
    /// The measured window (so far, while running), seconds.
    pub duration_s: f64,
    /// Warm-up before the window, seconds (not in the report).
    pub warmup_s: f64,
    /// Connections (in-process callers for `POST /v1/loadtest`) the requests were spread over.
    pub lanes: usize,
    /// Heads per request.
    pub heads_per_request: u64,
    /// Requests whose intended send time fell in the window.
    pub sent: u64,
    /// Of those, answered 200.
    pub ok: u64,
    /// Answered with an error status, or not at all (the connection failed).
    pub errors: u64,
    /// Still unanswered when the run stopped waiting (the end of the window plus a grace).
    pub unfinished: u64,
    /// Successful requests per second.
    pub achieved_rate: f64,
    /// Heads of successful requests per second.
    pub heads_per_s: f64,
    /// Response bytes of successful requests per second.
    pub bytes_per_s: f64,
    /// Latency of successful requests from their intended send time (corrected for
    /// coordinated omission), milliseconds.
    pub latency_ms: Percentiles,
    /// Failures by status and code.
    pub errors_by: Vec<ErrorCount>,
    /// The server's timings, when its responses carried `Server-Timing`.
    pub server_ms: Option<ServerTimings>,
    /// Whether the run is over.
    pub finished: bool,
    /// Whether it was stopped early (shutdown, or its grace ran out).
    pub cancelled: bool,
    /// A sessions run's own fields. There `rate` is the tick messages due per second (all
    /// viewers), `lanes` the viewers, `heads_per_request` the session's heads, `sent` the ticks
    /// due, `ok` those received, `errors` the viewers closed with an error, `unfinished` the
    /// due ticks not received, `heads_per_s` the changed heads delivered and the latency is
    /// from each tick's due time (see `crowdmorph::load::session`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub session: Option<SessionReport>,
}

/// One rate tried by a ramp.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RampStep {
    /// Requests per second.
    pub rate: f64,
    /// Whether it met the target.
    pub met: bool,
    /// Its report.
    pub report: LoadReport,
}

/// The result of `--ramp`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RampReport {
    /// The p99 target, milliseconds.
    pub p99_target_ms: f64,
    /// The highest rate that met it, if any did.
    pub best_rate: Option<f64>,
    /// That rate's step.
    pub best: Option<RampStep>,
    /// Every rate tried, in order.
    pub steps: Vec<RampStep>,
}

fn si(v: f64) -> String {
    match v {
        v if v >= 1e9 => format!("{:.2} G", v / 1e9),
        v if v >= 1e6 => format!("{:.2} M", v / 1e6),
        v if v >= 1e3 => format!("{:.2} k", v / 1e3),
        v => format!("{v:.1} "),
    }
}

fn percentiles_line(p: &Percentiles) -> String {
    format!(
        "p50 {:.3}  p90 {:.3}  p99 {:.3}  p99.9 {:.3}  max {:.3}  mean {:.3}",
        p.p50, p.p90, p.p99, p.p999, p.max, p.mean
    )
}

/// Per-viewer lines are printed up to this many viewers; `--json` always has them all.
const VIEWER_LINES: usize = 16;

impl SessionReport {
    fn text(&self, r: &LoadReport) -> String {
        let mut s = format!(
            "session {} ({}): {} heads at {} ticks/s, {} viewers, {:.1} s (after {:.1} s of warm-up)\n",
            self.id,
            if self.created {
                "created for the run"
            } else {
                "attached"
            },
            self.heads,
            self.fps,
            self.viewers,
            r.duration_s,
            r.warmup_s
        );
        s += &format!(
            "  achieved   {:>10.1} messages/s   {}heads/s   {}B/s\n",
            r.achieved_rate,
            si(r.heads_per_s),
            si(r.bytes_per_s)
        );
        s += &format!(
            "  ticks      {} due per viewer, {} received of {} ({} missed, {} not received in all), {} viewers closed with an error\n",
            self.ticks_due, self.ticks_received, r.sent, self.ticks_missed, r.unfinished, r.errors
        );
        s += &format!(
            "  messages   {}B and {:.1} changed heads each (mean)\n",
            si(self.bytes_per_message),
            self.changed_heads_per_message
        );
        s += &format!(
            "  latency ms {}   (from the tick's due time)\n",
            percentiles_line(&r.latency_ms)
        );
        if self.per_viewer.len() <= VIEWER_LINES {
            for (i, v) in self.per_viewer.iter().enumerate() {
                s += &format!(
                    "  viewer {i:<3} {} received, {} missed, {}B, latency mean {:.3} max {:.3} ms{}\n",
                    v.received,
                    v.missed,
                    si(v.bytes as f64),
                    v.latency_mean_ms,
                    v.latency_max_ms,
                    v.close_code
                        .map_or(String::new(), |c| format!(", closed {c}"))
                );
            }
        }
        s
    }
}

impl LoadReport {
    /// The human-readable table.
    pub fn text(&self) -> String {
        let mut s = match &self.session {
            Some(session) => session.text(self),
            None => self.requests_text(),
        };
        if let Some(t) = &self.server_ms {
            let mut first = true;
            for (name, p) in [
                ("queue  ", &t.queue_ms),
                ("compute", &t.compute_ms),
                ("encode ", &t.encode_ms),
                ("total  ", &t.total_ms),
            ] {
                if p.count > 0 {
                    let lead = if first {
                        "  server ms "
                    } else {
                        "            "
                    };
                    s += &format!("{lead}{name} {}\n", percentiles_line(p));
                    first = false;
                }
            }
        }
        for e in &self.errors_by {
            s += &format!(
                "  error      {} {} × {}\n",
                if e.status == 0 {
                    "-".to_string()
                } else {
                    e.status.to_string()
                },
                if e.code.is_empty() { "?" } else { &e.code },
                e.count
            );
        }
        s
    }

    fn requests_text(&self) -> String {
        let mut s = format!(
            "target {:.1} requests/s for {:.1} s (after {:.1} s of warm-up) over {} connections, {} heads per request\n",
            self.rate, self.duration_s, self.warmup_s, self.lanes, self.heads_per_request
        );
        s += &format!(
            "  achieved   {:>10.1} requests/s   {}heads/s   {}B/s\n",
            self.achieved_rate,
            si(self.heads_per_s),
            si(self.bytes_per_s)
        );
        s += &format!(
            "  requests   {} sent, {} ok, {} errors, {} unfinished{}\n",
            self.sent,
            self.ok,
            self.errors,
            self.unfinished,
            if self.cancelled {
                " (stopped early)"
            } else {
                ""
            }
        );
        s += &format!(
            "  latency ms {}   (from the intended send time)\n",
            percentiles_line(&self.latency_ms)
        );
        s
    }
}

impl RampReport {
    /// The human-readable table: one line per rate tried, then the best one in full.
    pub fn text(&self) -> String {
        let mut s = format!("ramp: highest rate with p99 ≤ {} ms\n", self.p99_target_ms);
        s += "  requests/s   achieved     p50 ms     p99 ms   errors  unfinished  met\n";
        for st in &self.steps {
            let r = &st.report;
            s += &format!(
                "  {:>10.1} {:>10.1} {:>10.3} {:>10.3} {:>8} {:>11}  {}\n",
                st.rate,
                r.achieved_rate,
                r.latency_ms.p50,
                r.latency_ms.p99,
                r.errors,
                r.unfinished,
                if st.met { "yes" } else { "no" }
            );
        }
        match &self.best {
            Some(b) => {
                s += &format!("best: {:.1} requests/s\n", b.rate);
                s += &b.report.text();
            }
            None => s += "no rate met the target\n",
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_sessions_table_names_ticks_viewers_closes_and_the_server_times_it_has() {
        let viewer = ViewerReport {
            received: 58,
            missed: 2,
            bytes: 58 << 20,
            heads: 580,
            latency_mean_ms: 4.0,
            latency_max_ms: 9.5,
            close_code: None,
            close_reason: None,
        };
        let r = LoadReport {
            rate: 60.0,
            duration_s: 2.0,
            lanes: 2,
            sent: 120,
            ok: 116,
            errors: 1,
            unfinished: 4,
            achieved_rate: 58.0,
            errors_by: vec![ErrorCount {
                status: 1013,
                code: "too many viewers".into(),
                count: 1,
            }],
            server_ms: Some(ServerTimings {
                total_ms: Percentiles {
                    p50: 1.5,
                    count: 116,
                    ..Percentiles::default()
                },
                ..ServerTimings::default()
            }),
            session: Some(SessionReport {
                id: "s7".into(),
                created: true,
                fps: 30.0,
                heads: 10,
                viewers: 2,
                ticks_due: 60,
                ticks_received: 116,
                ticks_missed: 2,
                bytes_per_message: 1e6,
                changed_heads_per_message: 10.0,
                per_viewer: vec![
                    viewer.clone(),
                    ViewerReport {
                        close_code: Some(1013),
                        ..viewer
                    },
                ],
            }),
            ..LoadReport::default()
        };
        let text = r.text();
        for line in [
            "session s7 (created for the run): 10 heads at 30 ticks/s, 2 viewers",
            "58.0 messages/s",
            "60 due per viewer, 116 received of 120 (2 missed, 4 not received in all), 1 viewers closed with an error",
            "viewer 1   58 received, 2 missed",
            ", closed 1013",
            "  server ms total   p50 1.500",
            "error      1013 too many viewers × 1",
        ] {
            assert!(text.contains(line), "{line:?} not in\n{text}");
        }
        // Timings the messages do not carry are left out rather than printed as zeros.
        assert!(!text.contains("encode"), "{text}");
        assert!(!text.contains("requests/s"), "{text}");
    }
}
