//! crowdmorph-load: the load generator.
//!
//! | module | what it is |
//! |---|---|
//! | the crate root | the open-loop core: [`run`], [`Lane`], [`Live`], [`ramp`] |
//! | [`http`] | HTTP lanes: one socket per lane, no pool |
//! | `shape` | crowd shapes ([`CrowdShape`]): deterministic request bodies from a seed |
//! | [`session`] | sessions mode: N viewers of one session ([`session::Viewer`]) |
//! | `report` | reports: percentiles, throughput, errors by code |
//!
//! The load generator behind `crowdmorph load` and `POST /v1/loadtest`: an open loop at a fixed
//! request rate, latency corrected for coordinated omission, HdrHistogram percentiles.
//!
//! Shape (after wrk2): request `i` is *intended* to be sent at `start + i / rate`, whatever
//! happened to the requests before it. A dispatcher thread hands each request, at its intended
//! time, to one of the *lanes* in turn (a lane is one HTTP/1.1 connection for `crowdmorph load`,
//! one in-process caller for the endpoint); a lane sends its requests one after another, so a
//! slow server makes them queue, and each latency is measured from the intended send time, not
//! from when the lane got round to it. A closed loop (send, wait, send) would instead slow down
//! with the server and hide exactly the stalls an operator needs to see.
//!
//! The core ([`run`]) is generic over how a request is sent ([`Lane`]): [`http`] sends real HTTP
//! requests with hyper, `crates/server/src/routes/loadtest.rs` calls the crowd-frame handler in-process.
//! Sessions (N viewers of one session, [`session`]) turned out not to be a [`Lane`]: the
//! server's tick clock, not a dispatcher, decides when their messages go. They share [`Live`]
//! and the report instead, with the latency of a tick measured from its due time on the
//! session's clock; `--ramp` is for request rates only.
//!
//! - [`CrowdShape`] describes the crowds (heads per request, unique share, rigs, clip and LOD
//!   mixes, format, normals, encoding) and makes deterministic request bodies from a seed.
//! - [`Live`] holds the counters and histograms of a run while it runs, so that a progress line
//!   or `GET /v1/loadtest/{id}` can read the report so far.
//! - [`ramp`] looks for the highest rate whose p99 stays under a target.

pub mod http;
mod report;
pub mod session;
mod shape;

use std::collections::BTreeMap;
use std::future::Future;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

use hdrhistogram::Histogram;

pub use report::{
    ErrorCount, LoadReport, Percentiles, RampReport, RampStep, ServerTimings, SessionReport,
    ViewerReport,
};
pub use shape::{BodySizes, CrowdShape, MAX_MIX, RigClips, WireEncoding};

/// Why a load could not be generated.
#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    /// The load or the crowd shape asks for something impossible.
    #[error("{0}")]
    Invalid(String),
    /// A connection to the server could not be opened.
    #[error("cannot connect to {addr}: {source}")]
    Connect {
        /// The address.
        addr: String,
        /// Why.
        source: std::io::Error,
    },
    /// The HTTP handshake or a request failed before the run started.
    #[error("HTTP: {0}")]
    Http(String),
    /// A request body could not be encoded.
    #[error("encoding a request: {0}")]
    Encode(String),
    /// A session's stream sent what the generator cannot read.
    #[error("session stream: {0}")]
    Stream(String),
}

/// What one request got back.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Reply {
    /// HTTP status; 0 when no response came (the connection failed).
    pub status: u16,
    /// The error code of a JSON error body (`queue_full`, ...), or `transport`/`connect` when no
    /// response came.
    pub code: Option<String>,
    /// Response body bytes.
    pub bytes: u64,
    /// What the response's `Server-Timing` header says.
    pub timing: ServerTiming,
}

/// Bytes of an error body kept to read its code; a longer body is counted, not kept.
const ERROR_BODY_LIMIT: usize = 64 << 10;

/// Reads a crowd-frame response the way every lane does: the status and `Server-Timing` from
/// its head, the body counted frame by frame (each frame dropped as read, as it would be sent),
/// and kept, up to [`ERROR_BODY_LIMIT`], only when it is an error, for its code. The flag is
/// false when the body broke off before its end.
pub async fn read_reply<B>(resp: hyper::Response<B>) -> (Reply, bool)
where
    B: http_body::Body<Data = bytes::Bytes> + Unpin,
{
    use http_body_util::BodyExt;

    let status = resp.status().as_u16();
    let timing = resp
        .headers()
        .get("server-timing")
        .and_then(|v| v.to_str().ok())
        .map(ServerTiming::parse)
        .unwrap_or_default();
    let mut body = resp.into_body();
    let mut bytes = 0u64;
    let mut kept = Vec::new();
    let mut complete = true;
    while let Some(frame) = body.frame().await {
        let Ok(frame) = frame else {
            complete = false;
            break;
        };
        if let Some(d) = frame.data_ref() {
            bytes += d.len() as u64;
            if status != 200 && kept.len() < ERROR_BODY_LIMIT {
                kept.extend_from_slice(&d[..d.len().min(ERROR_BODY_LIMIT - kept.len())]);
            }
        }
    }
    let code = (status != 200).then(|| {
        serde_json::from_slice::<crowdmorph_proto::ErrorBody>(&kept)
            .map(|e| e.error.code)
            .unwrap_or_default()
    });
    let reply = Reply {
        status,
        code,
        bytes,
        timing,
    };
    (reply, complete)
}

/// The server's own account of a crowd frame (its `Server-Timing` header).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ServerTiming {
    /// From admission to the start of the last batch that computed one of its jobs.
    pub queue: Option<Duration>,
    /// Engine wall time of those batches.
    pub compute: Option<Duration>,
    /// Building the response body.
    pub encode: Option<Duration>,
    /// From arrival to the response being ready to send.
    pub total: Option<Duration>,
}

impl ServerTiming {
    /// Parses `queue;dur=0.012, compute;dur=0.310, encode;dur=0.002, total;dur=0.4` (W3C
    /// Server Timing, milliseconds); unknown metrics and malformed entries are ignored.
    pub fn parse(header: &str) -> ServerTiming {
        let mut t = ServerTiming::default();
        for entry in header.split(',') {
            let mut parts = entry.split(';').map(str::trim);
            let name = parts.next().unwrap_or_default();
            let dur = parts
                .filter_map(|p| p.strip_prefix("dur="))
                .find_map(|v| v.trim_matches('"').parse::<f64>().ok())
                .filter(|v| v.is_finite() && *v >= 0.0)
                .map(|ms| Duration::from_secs_f64(ms / 1e3));
            match name {
                "queue" => t.queue = dur,
                "compute" => t.compute = dur,
                "encode" => t.encode = dur,
                "total" => t.total = dur,
                _ => {}
            }
        }
        t
    }
}

/// One way of sending requests, one at a time: an HTTP connection, an in-process caller.
pub trait Lane: Send + 'static {
    /// Sends request number `i` (the lane picks its body, e.g. `i` modulo a ring of bodies)
    /// and waits for the whole response.
    fn send(&mut self, i: u64) -> impl Future<Output = Reply> + Send;
}

/// The timing of a run.
#[derive(Clone, Debug, PartialEq)]
pub struct RunOptions {
    /// Requests per second, all lanes together.
    pub rate: f64,
    /// The measured window.
    pub duration: Duration,
    /// Sent before the measured window and left out of the report (connections, caches and
    /// the server's buffer pool warm up).
    pub warmup: Duration,
    /// How long requests still unanswered at the end of the window may take before the run
    /// stops waiting; those left are reported as unfinished.
    pub grace: Duration,
    /// Heads in each request (for heads per second).
    pub heads_per_request: u64,
}

impl RunOptions {
    /// Checks the rate and durations.
    pub fn check(&self) -> Result<(), LoadError> {
        if !(self.rate.is_finite() && self.rate > 0.0) {
            return Err(LoadError::Invalid(format!(
                "the rate must be a positive number of requests per second, not {}",
                self.rate
            )));
        }
        if self.duration.is_zero() {
            return Err(LoadError::Invalid("the duration must be positive".into()));
        }
        let total = (self.warmup + self.duration).as_secs_f64() * self.rate;
        if total > 1e10 {
            return Err(LoadError::Invalid(format!(
                "{total:.0} requests is more than this generator can plan"
            )));
        }
        Ok(())
    }
}

/// Latencies are recorded in microseconds, up to an hour, with 3 significant digits.
fn histogram() -> Histogram<u64> {
    // Constant, valid bounds: this cannot fail whatever the input.
    Histogram::new_with_bounds(1, 3_600_000_000, 3).expect("valid histogram bounds")
}

fn micros(d: Duration) -> u64 {
    u64::try_from(d.as_micros()).unwrap_or(u64::MAX).max(1)
}

/// What the lanes record; one lock, taken once per response.
struct Recorder {
    latency: Histogram<u64>,
    queue: Histogram<u64>,
    compute: Histogram<u64>,
    encode: Histogram<u64>,
    total: Histogram<u64>,
    /// Requests of the window handed to a lane.
    sent: u64,
    ok: u64,
    failed: u64,
    heads: u64,
    bytes: u64,
    errors: BTreeMap<(u16, String), u64>,
    /// A sessions run's own tallies.
    session: Option<session::SessionTally>,
}

impl Recorder {
    fn new() -> Recorder {
        Recorder {
            latency: histogram(),
            queue: histogram(),
            compute: histogram(),
            encode: histogram(),
            total: histogram(),
            sent: 0,
            ok: 0,
            failed: 0,
            heads: 0,
            bytes: 0,
            errors: BTreeMap::new(),
            session: None,
        }
    }

    /// Records the server's own timings of one answer.
    fn record_server(&mut self, t: &ServerTiming) {
        for (h, d) in [
            (&mut self.queue, t.queue),
            (&mut self.compute, t.compute),
            (&mut self.encode, t.encode),
            (&mut self.total, t.total),
        ] {
            if let Some(d) = d {
                h.saturating_record(micros(d));
            }
        }
    }
}

/// A run's state while it runs: counters and histograms anyone can read a report from.
pub struct Live {
    opts: RunOptions,
    lanes: AtomicU64,
    start: OnceLock<Instant>,
    /// When [`run`] returned: a finished run's elapsed time stops there.
    end: OnceLock<Instant>,
    cancelled: AtomicBool,
    finished: AtomicBool,
    /// Requests handed to lanes, warm-up included.
    dispatched: AtomicU64,
    /// Responses received, warm-up included.
    completed: AtomicU64,
    rec: Mutex<Recorder>,
}

impl std::fmt::Debug for Live {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Live")
            .field("opts", &self.opts)
            .field("dispatched", &self.dispatched)
            .field("completed", &self.completed)
            .finish_non_exhaustive()
    }
}

impl Live {
    /// A run that has not started.
    pub fn new(opts: RunOptions) -> Arc<Live> {
        Arc::new(Live {
            opts,
            lanes: AtomicU64::new(0),
            start: OnceLock::new(),
            end: OnceLock::new(),
            cancelled: AtomicBool::new(false),
            finished: AtomicBool::new(false),
            dispatched: AtomicU64::new(0),
            completed: AtomicU64::new(0),
            rec: Mutex::new(Recorder::new()),
        })
    }

    /// The run's options.
    pub fn options(&self) -> &RunOptions {
        &self.opts
    }

    /// Stops the run: nothing more is sent, and [`run`] returns once the requests being
    /// answered are.
    pub fn cancel(&self) {
        self.cancelled.store(true, Ordering::Release);
    }

    /// Whether [`Live::cancel`] was called.
    pub fn is_cancelled(&self) -> bool {
        self.cancelled.load(Ordering::Acquire)
    }

    /// Whether [`run`] has returned.
    pub fn is_finished(&self) -> bool {
        self.finished.load(Ordering::Acquire)
    }

    /// Seconds since the run started (warm-up included), up to when it finished.
    pub fn elapsed(&self) -> f64 {
        self.start.get().map_or(0.0, |s| {
            let until = self.end.get().copied().unwrap_or_else(Instant::now);
            until.saturating_duration_since(*s).as_secs_f64()
        })
    }

    /// Requests handed to lanes and responses received so far, warm-up included.
    pub fn counts(&self) -> (u64, u64) {
        (
            self.dispatched.load(Ordering::Relaxed),
            self.completed.load(Ordering::Relaxed),
        )
    }

    /// The measured window so far: from the end of the warm-up to now, at most the duration.
    fn window(&self) -> Duration {
        let Some(start) = self.start.get() else {
            return Duration::ZERO;
        };
        if self.is_finished() {
            return self.opts.duration;
        }
        Instant::now()
            .saturating_duration_since(*start + self.opts.warmup)
            .min(self.opts.duration)
    }

    fn in_window(&self, intended: Instant) -> bool {
        self.start.get().is_some_and(|s| {
            let from = *s + self.opts.warmup;
            intended >= from && intended < from + self.opts.duration
        })
    }

    fn record(&self, intended: Instant, done: Instant, reply: &Reply) {
        self.completed.fetch_add(1, Ordering::Relaxed);
        if !self.in_window(intended) {
            return;
        }
        let Ok(mut guard) = self.rec.lock() else {
            return;
        };
        let r = &mut *guard;
        if reply.status == 200 {
            r.ok += 1;
            r.heads += self.opts.heads_per_request;
            r.bytes += reply.bytes;
            r.latency
                .saturating_record(micros(done.saturating_duration_since(intended)));
            r.record_server(&reply.timing);
        } else {
            r.failed += 1;
            let code = reply.code.clone().unwrap_or_default();
            *r.errors.entry((reply.status, code)).or_insert(0) += 1;
        }
    }

    /// The report of what has been measured so far (the final one once the run is over).
    pub fn snapshot(&self) -> LoadReport {
        let window = self.window().as_secs_f64();
        let per_s = |n: u64| if window > 0.0 { n as f64 / window } else { 0.0 };
        let lanes = self.lanes.load(Ordering::Relaxed) as usize;
        let Ok(r) = self.rec.lock() else {
            return LoadReport::default();
        };
        let server = ServerTimings {
            queue_ms: Percentiles::of(&r.queue),
            compute_ms: Percentiles::of(&r.compute),
            encode_ms: Percentiles::of(&r.encode),
            total_ms: Percentiles::of(&r.total),
        };
        let session = r
            .session
            .as_ref()
            .map(|s| s.report(self.opts.warmup.as_secs_f64(), window));
        // A sessions run is due its ticks, viewer by viewer; what was neither received nor
        // closed with an error is unfinished.
        let sent = session
            .as_ref()
            .map_or(r.sent, |s| s.ticks_due * s.viewers as u64);
        LoadReport {
            rate: self.opts.rate,
            duration_s: window,
            warmup_s: self.opts.warmup.as_secs_f64(),
            lanes,
            heads_per_request: self.opts.heads_per_request,
            sent,
            ok: r.ok,
            errors: r.failed,
            unfinished: match (&session, self.is_finished()) {
                (_, false) => 0,
                (None, true) => sent.saturating_sub(r.ok + r.failed),
                (Some(_), true) => sent.saturating_sub(r.ok),
            },
            achieved_rate: per_s(r.ok),
            heads_per_s: per_s(r.heads),
            bytes_per_s: per_s(r.bytes),
            latency_ms: Percentiles::of(&r.latency),
            errors_by: r
                .errors
                .iter()
                .map(|((status, code), &count)| ErrorCount {
                    status: *status,
                    code: code.clone(),
                    count,
                })
                .collect(),
            server_ms: (r.queue.len() + r.compute.len() + r.encode.len() + r.total.len() > 0)
                .then_some(server),
            session,
            finished: self.is_finished(),
            cancelled: self.is_cancelled(),
        }
    }
}

/// How often a waiting dispatcher looks at the cancel flag.
const CANCEL_POLL: Duration = Duration::from_millis(50);

/// Hands request `i` to lane `i mod lanes` at `start + i / rate`, on a thread of its own:
/// `std::thread::sleep` wakes within tens of microseconds, where tokio's timer rounds to a
/// millisecond, which would add up to a millisecond of the generator's own to every latency.
fn dispatch(
    live: &Live,
    start: Instant,
    lanes: &[tokio::sync::mpsc::UnboundedSender<(u64, Instant)>],
) {
    let opts = &live.opts;
    let total = ((opts.warmup + opts.duration).as_secs_f64() * opts.rate).ceil() as u64;
    for i in 0..total {
        let intended = start + Duration::from_secs_f64(i as f64 / opts.rate);
        loop {
            if live.is_cancelled() {
                return;
            }
            let now = Instant::now();
            if now >= intended {
                break;
            }
            std::thread::sleep((intended - now).min(CANCEL_POLL));
        }
        if live.in_window(intended)
            && let Ok(mut r) = live.rec.lock()
        {
            r.sent += 1;
        }
        live.dispatched.fetch_add(1, Ordering::Relaxed);
        let lane = &lanes[(i % lanes.len() as u64) as usize];
        if lane.send((i, intended)).is_err() {
            return;
        }
    }
}

async fn lane_loop<L: Lane>(
    mut lane: L,
    mut rx: tokio::sync::mpsc::UnboundedReceiver<(u64, Instant)>,
    live: Arc<Live>,
) {
    while let Some((i, intended)) = rx.recv().await {
        if live.is_cancelled() {
            break;
        }
        let reply = lane.send(i).await;
        live.record(intended, Instant::now(), &reply);
    }
}

/// Runs the load through `lanes` (at least one) and returns the final report. Must be called
/// inside a tokio runtime; the lanes run as tasks on it.
pub async fn run<L: Lane>(lanes: Vec<L>, live: &Arc<Live>) -> Result<LoadReport, LoadError> {
    live.opts.check()?;
    if lanes.is_empty() {
        return Err(LoadError::Invalid("a run needs at least one lane".into()));
    }
    live.lanes.store(lanes.len() as u64, Ordering::Relaxed);
    let mut txs = Vec::with_capacity(lanes.len());
    let mut tasks = tokio::task::JoinSet::new();
    for lane in lanes {
        let (tx, rx) = tokio::sync::mpsc::unbounded_channel();
        txs.push(tx);
        tasks.spawn(lane_loop(lane, rx, live.clone()));
    }
    let start = Instant::now();
    let _ = live.start.set(start);
    let dispatcher = {
        let live = live.clone();
        std::thread::Builder::new()
            .name("crowdmorph-load".into())
            .spawn(move || dispatch(&live, start, &txs))
            .map_err(|e| LoadError::Invalid(format!("cannot start the dispatcher: {e}")))?
    };
    let deadline = start + live.opts.warmup + live.opts.duration + live.opts.grace;
    let all = async { while tasks.join_next().await.is_some() {} };
    if tokio::time::timeout_at(deadline.into(), all).await.is_err() {
        // Requests still queued or unanswered after the grace are left unfinished.
        live.cancel();
        tasks.abort_all();
        while tasks.join_next().await.is_some() {}
    }
    // The dispatcher has returned (its lanes are gone, or it saw the cancel flag within
    // CANCEL_POLL); joining it off the async workers keeps them free meanwhile.
    let _ = tokio::task::spawn_blocking(move || dispatcher.join()).await;
    let _ = live.end.set(Instant::now());
    live.finished.store(true, Ordering::Release);
    Ok(live.snapshot())
}

/// What `--ramp` looks for.
#[derive(Clone, Debug, PartialEq)]
pub struct RampOptions {
    /// The first rate tried.
    pub start_rate: f64,
    /// The highest rate tried.
    pub max_rate: f64,
    /// The p99 a rate must stay under, milliseconds.
    pub p99_ms: f64,
    /// The share of failed or unfinished requests a rate may have.
    pub max_error_share: f64,
    /// The search stops when the highest good rate and the lowest bad one are this close
    /// (relative), or after `max_steps` runs.
    pub precision: f64,
    /// Most runs.
    pub max_steps: usize,
}

impl Default for RampOptions {
    fn default() -> Self {
        RampOptions {
            start_rate: 10.0,
            max_rate: 1e6,
            p99_ms: 10.0,
            max_error_share: 0.001,
            precision: 0.05,
            max_steps: 12,
        }
    }
}

impl RampOptions {
    /// Whether a run at its rate met the target: p99 under it, the rate achieved (every
    /// request answered), few errors.
    pub fn met(&self, r: &LoadReport) -> bool {
        let bad = r.errors + r.unfinished;
        r.ok > 0
            && r.latency_ms.p99 <= self.p99_ms
            && (bad as f64) <= self.max_error_share * r.sent.max(1) as f64
    }
}

/// Finds the highest rate whose run meets `opts`: doubles the rate from `start_rate` until a
/// run misses the target (or `max_rate`), then bisects between the best good and the worst
/// bad rate. `step` runs the load at a rate and returns its report.
pub async fn ramp<F, Fut>(opts: &RampOptions, mut step: F) -> Result<RampReport, LoadError>
where
    F: FnMut(f64) -> Fut,
    Fut: Future<Output = Result<LoadReport, LoadError>>,
{
    if !(opts.start_rate > 0.0 && opts.max_rate >= opts.start_rate && opts.p99_ms > 0.0) {
        return Err(LoadError::Invalid(
            "a ramp needs 0 < start rate <= max rate and a positive p99 target".into(),
        ));
    }
    let mut steps = Vec::new();
    let mut good: Option<f64> = None;
    let mut bad: Option<f64> = None;
    let mut rate = opts.start_rate;
    for _ in 0..opts.max_steps.max(1) {
        let report = step(rate).await?;
        let met = opts.met(&report);
        steps.push(RampStep { rate, met, report });
        if met {
            good = Some(good.map_or(rate, |g: f64| g.max(rate)));
        } else {
            bad = Some(bad.map_or(rate, |b: f64| b.min(rate)));
        }
        rate = match (good, bad) {
            (Some(g), None) if g >= opts.max_rate => break,
            (Some(g), None) => (g * 2.0).min(opts.max_rate),
            (None, Some(b)) => b / 2.0,
            (Some(g), Some(b)) if b <= g * (1.0 + opts.precision) => break,
            (Some(g), Some(b)) => (g + b) / 2.0,
            (None, None) => break,
        };
        if rate < 1e-3 {
            break;
        }
    }
    let best = good.and_then(|g| steps.iter().find(|s| s.met && s.rate == g).cloned());
    Ok(RampReport {
        p99_target_ms: opts.p99_ms,
        best_rate: good,
        best,
        steps,
    })
}

#[cfg(test)]
mod tests {
    // A test that meets an unexpected error should fail loudly.
    #![allow(clippy::unwrap_used)]

    use super::*;

    #[test]
    fn server_timing_headers_parse() {
        let t = ServerTiming::parse(
            "queue;dur=0.012, compute;dur=1.5, encode;desc=\"x\";dur=0.002, total;dur=2, gpu;dur=9",
        );
        assert_eq!(t.queue, Some(Duration::from_micros(12)));
        assert_eq!(t.compute, Some(Duration::from_micros(1500)));
        assert_eq!(t.encode, Some(Duration::from_micros(2)));
        assert_eq!(t.total, Some(Duration::from_millis(2)));
        assert_eq!(
            ServerTiming::parse("nonsense;dur=x, queue"),
            ServerTiming::default()
        );
    }

    /// A lane that answers at once: 200 for even requests, 503 for odd ones.
    struct Echo;

    impl Lane for Echo {
        async fn send(&mut self, i: u64) -> Reply {
            if i.is_multiple_of(2) {
                Reply {
                    status: 200,
                    bytes: 10,
                    ..Reply::default()
                }
            } else {
                Reply {
                    status: 503,
                    code: Some("queue_full".into()),
                    ..Reply::default()
                }
            }
        }
    }

    #[tokio::test]
    async fn every_planned_request_is_sent_and_counted() {
        let live = Live::new(RunOptions {
            rate: 400.0,
            duration: Duration::from_millis(250),
            warmup: Duration::ZERO,
            grace: Duration::from_secs(5),
            heads_per_request: 3,
        });
        let r = run(vec![Echo, Echo], &live).await.unwrap();
        // 0.25 s at 400/s: requests 0..100, every one in the window.
        assert_eq!(r.sent, 100);
        assert_eq!((r.ok, r.errors, r.unfinished), (50, 50, 0));
        assert_eq!(
            r.errors_by,
            vec![ErrorCount {
                status: 503,
                code: "queue_full".into(),
                count: 50
            }]
        );
        assert_eq!(r.heads_per_s, 50.0 * 3.0 * 4.0);
        assert_eq!(r.bytes_per_s, 50.0 * 10.0 * 4.0);
        assert!(r.finished && !r.cancelled);
        assert_eq!(r.lanes, 2);
    }

    #[tokio::test]
    async fn the_ramp_bisects_between_good_and_bad_rates() {
        // A fake server whose p99 is fine up to 300 requests/s.
        let opts = RampOptions {
            start_rate: 100.0,
            max_rate: 10_000.0,
            p99_ms: 5.0,
            precision: 0.1,
            ..RampOptions::default()
        };
        let r = ramp(&opts, |rate| async move {
            let mut report = LoadReport {
                rate,
                sent: 100,
                ok: 100,
                ..LoadReport::default()
            };
            report.latency_ms.p99 = if rate <= 300.0 { 1.0 } else { 50.0 };
            Ok(report)
        })
        .await
        .unwrap();
        let rates: Vec<f64> = r.steps.iter().map(|s| s.rate).collect();
        assert_eq!(&rates[..3], &[100.0, 200.0, 400.0]);
        let best = r.best_rate.unwrap();
        assert!((300.0 / 1.1 - 1e-9..=300.0).contains(&best), "{rates:?}");
        assert_eq!(r.best.unwrap().rate, best);
    }
}
