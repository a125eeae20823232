//! Server metrics in the Prometheus text format (version 0.0.4), hand-rolled: a few atomic
//! counters and fixed-bucket histograms are all the server needs, and writing them out is
//! simpler than adapting a registry crate's global state to per-test servers.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

/// Bucket bounds in seconds for latencies (50 µs to 10 s).
const SECONDS: &[f64] = &[
    5e-5, 1e-4, 2.5e-4, 5e-4, 1e-3, 2.5e-3, 5e-3, 1e-2, 2.5e-2, 5e-2, 0.1, 0.25, 0.5, 1.0, 2.5,
    10.0,
];

/// Bucket bounds for counts (jobs per batch, heads per request).
const COUNTS: &[f64] = &[
    1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0, 256.0, 512.0, 1024.0, 4096.0, 16384.0,
];

/// Where a crowd request came from, so that synthetic load can be told apart from real
/// traffic: the `source` label of `crowdmorph_heads_total` and `crowdmorph_crowd_frames_total`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Source {
    /// A client over HTTP.
    Api,
    /// `POST /v1/loadtest`: synthetic load generated inside the server.
    Loadtest,
}

impl Source {
    /// The label value.
    pub fn label(self) -> &'static str {
        match self {
            Source::Api => "api",
            Source::Loadtest => "loadtest",
        }
    }
}

/// A cumulative histogram with fixed bucket bounds.
#[derive(Debug)]
pub struct Histogram {
    bounds: &'static [f64],
    counts: Vec<AtomicU64>,
    /// Sum of observations in millionths of the unit.
    sum_micro: AtomicU64,
    count: AtomicU64,
}

impl Histogram {
    fn new(bounds: &'static [f64]) -> Histogram {
        Histogram {
            bounds,
            counts: bounds.iter().map(|_| AtomicU64::new(0)).collect(),
            sum_micro: AtomicU64::new(0),
            count: AtomicU64::new(0),
        }
    }

    /// Records one observation.
    pub fn observe(&self, v: f64) {
        if let Some(i) = self.bounds.iter().position(|&b| v <= b) {
            self.counts[i].fetch_add(1, Ordering::Relaxed);
        }
        self.sum_micro
            .fetch_add((v.max(0.0) * 1e6) as u64, Ordering::Relaxed);
        self.count.fetch_add(1, Ordering::Relaxed);
    }

    /// Number of observations.
    pub fn count(&self) -> u64 {
        self.count.load(Ordering::Relaxed)
    }

    fn write(&self, out: &mut String, name: &str, help: &str) {
        let _ = writeln!(out, "# HELP {name} {help}\n# TYPE {name} histogram");
        let mut acc = 0;
        for (b, c) in self.bounds.iter().zip(&self.counts) {
            acc += c.load(Ordering::Relaxed);
            let _ = writeln!(out, "{name}_bucket{{le=\"{b}\"}} {acc}");
        }
        let count = self.count();
        let _ = writeln!(out, "{name}_bucket{{le=\"+Inf\"}} {count}");
        let sum = self.sum_micro.load(Ordering::Relaxed) as f64 / 1e6;
        let _ = writeln!(out, "{name}_sum {sum}\n{name}_count {count}");
    }
}

/// Heads served per second over the last completed one-second window.
#[derive(Debug)]
struct RateWindow {
    start: Instant,
    count: u64,
    last_rate: f64,
}

/// Every metric the server exports.
#[derive(Debug)]
pub struct Metrics {
    requests: Mutex<BTreeMap<(String, u16), u64>>,
    /// Time crowd requests waited from admission to the start of their last batch.
    pub queue_seconds: Histogram,
    /// Engine wall time per batch.
    pub compute_seconds: Histogram,
    /// Whole crowd-request latency (arrival to response ready).
    pub request_seconds: Histogram,
    /// Unique jobs per batch.
    pub batch_jobs: Histogram,
    /// Heads per crowd request.
    pub request_heads: Histogram,
    /// Heads served to clients.
    pub heads: AtomicU64,
    /// Heads served to `POST /v1/loadtest`'s synthetic requests.
    pub loadtest_heads: AtomicU64,
    /// Crowd-frame requests answered, by source and status: one count per response, made by
    /// the handler (`api::crowd_frame_from`), the one place that sees synthetic requests too.
    /// A client's response is also counted by route in `requests`, as every HTTP response is.
    crowd_frames: Mutex<BTreeMap<(Source, u16), u64>>,
    /// Unique jobs asked for, summed over requests (after in-request dedupe).
    pub jobs_requested: AtomicU64,
    /// Jobs the engine computed.
    pub jobs_computed: AtomicU64,
    /// Jobs that joined an identical job of another request already queued or computing.
    pub jobs_coalesced: AtomicU64,
    /// Jobs dropped before computing because every request waiting for them had gone.
    pub jobs_cancelled: AtomicU64,
    /// Batches dispatched.
    pub batches: AtomicU64,
    /// Engine dispatches (one per rig and output kind per batch).
    pub dispatches: AtomicU64,
    /// Batches begun on the engine while an earlier one was still computing (GPU pipelining).
    pub batches_pipelined: AtomicU64,
    /// GPU time, nanoseconds.
    pub gpu_ns: AtomicU64,
    /// LOD builds computing now (background jobs and PUTs).
    pub lod_builds_running: AtomicU64,
    /// LOD builds that stopped early because they were cancelled (a newer PUT, a delete,
    /// shutdown, or the server state being dropped).
    pub lod_builds_cancelled: AtomicU64,
    /// Requests refused by reason (`overloaded`, `queue_full`, `deadline`, `timeout`, ...).
    rejected: Mutex<BTreeMap<&'static str, u64>>,
    /// Work stopped before it finished because its request was gone or late, by kind of work
    /// (`render`, `session_frame`, `frame`, `lod`) and reason (`dropped`, `deadline`).
    cancelled: Mutex<BTreeMap<(&'static str, &'static str), u64>>,
    /// Session tick tasks that panicked (each ended its session).
    pub session_panics: AtomicU64,
    /// Connections admitted and not yet closed.
    pub connections_open: AtomicU64,
    /// Connections accepted from the listener, refused ones included.
    pub connections_accepted: AtomicU64,
    /// Connections closed, by reason (`closed`, `error`, `header_timeout`, `idle_timeout`,
    /// `evicted`, `refused`, `shutdown`).
    connections_closed: Mutex<BTreeMap<&'static str, u64>>,
    /// Failed `accept` calls other than a connection reset before it was accepted (e.g. the
    /// open-file limit reached).
    pub accept_errors: AtomicU64,
    /// Crowd requests waiting in or being served by the batcher.
    pub queue_depth: AtomicU64,
    rate: Mutex<RateWindow>,
}

impl Default for Metrics {
    fn default() -> Self {
        Metrics {
            requests: Mutex::new(BTreeMap::new()),
            queue_seconds: Histogram::new(SECONDS),
            compute_seconds: Histogram::new(SECONDS),
            request_seconds: Histogram::new(SECONDS),
            batch_jobs: Histogram::new(COUNTS),
            request_heads: Histogram::new(COUNTS),
            heads: AtomicU64::new(0),
            loadtest_heads: AtomicU64::new(0),
            crowd_frames: Mutex::new(BTreeMap::new()),
            jobs_requested: AtomicU64::new(0),
            jobs_computed: AtomicU64::new(0),
            jobs_coalesced: AtomicU64::new(0),
            jobs_cancelled: AtomicU64::new(0),
            batches: AtomicU64::new(0),
            dispatches: AtomicU64::new(0),
            batches_pipelined: AtomicU64::new(0),
            gpu_ns: AtomicU64::new(0),
            lod_builds_running: AtomicU64::new(0),
            lod_builds_cancelled: AtomicU64::new(0),
            rejected: Mutex::new(BTreeMap::new()),
            cancelled: Mutex::new(BTreeMap::new()),
            session_panics: AtomicU64::new(0),
            connections_open: AtomicU64::new(0),
            connections_accepted: AtomicU64::new(0),
            connections_closed: Mutex::new(BTreeMap::new()),
            accept_errors: AtomicU64::new(0),
            queue_depth: AtomicU64::new(0),
            rate: Mutex::new(RateWindow {
                start: Instant::now(),
                count: 0,
                last_rate: 0.0,
            }),
        }
    }
}

/// Counts a request's work as cancelled (`reason="dropped"`) when dropped before
/// [`DropCounter::finish`]: what a handler holds while it waits, so that a client hanging up
/// (its future dropped) is counted.
#[derive(Debug)]
pub struct DropCounter {
    metrics: std::sync::Arc<Metrics>,
    work: &'static str,
    armed: bool,
}

impl DropCounter {
    /// Armed for work of kind `work`.
    pub fn new(metrics: std::sync::Arc<Metrics>, work: &'static str) -> DropCounter {
        DropCounter {
            metrics,
            work,
            armed: true,
        }
    }

    /// The work finished (or was answered): nothing to count.
    pub fn finish(mut self) {
        self.armed = false;
    }
}

impl Drop for DropCounter {
    fn drop(&mut self) {
        if self.armed {
            self.metrics
                .cancelled(self.work, crate::cancel::Cancelled::Dropped);
        }
    }
}

/// Gauges read from the rest of the server when metrics are rendered.
#[derive(Debug, Default, Clone, Copy)]
pub struct Gauges {
    /// Rigs registered.
    pub rigs: u64,
    /// Host bytes of all rigs.
    pub host_bytes: u64,
    /// Device bytes of all rigs.
    pub device_bytes: u64,
    /// Output bytes admitted crowd requests hold now.
    pub queue_memory_bytes: u64,
    /// The limit on that.
    pub queue_memory_limit: u64,
    /// Bytes the memory pool holds: resident rigs plus uploads and LOD builds in progress.
    pub rig_memory_bytes: u64,
    /// The pool's size (`--max-rig-memory`).
    pub rig_memory_limit: u64,
    /// 1 when the engine runs degraded (GPU lost).
    pub degraded: bool,
    /// 1 while stored rigs are loading.
    pub loading: bool,
    /// The most connections open at once.
    pub connections_limit: u64,
    /// Pixels renders in flight hold now.
    pub render_pixels: u64,
    /// The limit on that (`--render-pixels`).
    pub render_pixels_limit: u64,
    /// Estimated seconds of work renders in flight hold.
    pub render_work_seconds: f64,
    /// The limit on that (`--render-work-ms`).
    pub render_work_limit_seconds: f64,
    /// Bytes charged to the GPU memory budgets (the engine's and the renderer's devices, each
    /// counted once); 0 without a GPU.
    pub gpu_memory_bytes: u64,
    /// The sum of those budgets (`--max-gpu-memory` per device).
    pub gpu_memory_limit: u64,
}

impl Metrics {
    /// Counts a finished HTTP request by route and status.
    pub fn request(&self, route: &str, status: u16) {
        if let Ok(mut m) = self.requests.lock() {
            *m.entry((route.to_string(), status)).or_insert(0) += 1;
        }
    }

    /// Counts a refused request.
    pub fn reject(&self, reason: &'static str) {
        if let Ok(mut m) = self.rejected.lock() {
            *m.entry(reason).or_insert(0) += 1;
        }
    }

    /// Counts work of kind `work` stopped by its cancellation.
    pub fn cancelled(&self, work: &'static str, why: crate::cancel::Cancelled) {
        let reason = match why {
            crate::cancel::Cancelled::Dropped => "dropped",
            crate::cancel::Cancelled::Deadline => "deadline",
        };
        if let Ok(mut m) = self.cancelled.lock() {
            *m.entry((work, reason)).or_insert(0) += 1;
        }
    }

    /// Counts a closed connection.
    pub fn connection_closed(&self, reason: &'static str) {
        if let Ok(mut m) = self.connections_closed.lock() {
            *m.entry(reason).or_insert(0) += 1;
        }
    }

    /// Connections closed so far for this reason (for tests).
    pub fn connections_closed_with(&self, reason: &str) -> u64 {
        self.connections_closed
            .lock()
            .map(|m| m.get(reason).copied().unwrap_or(0))
            .unwrap_or(0)
    }

    /// Counts heads served to a client (for heads/s).
    pub fn served(&self, heads: u64) {
        self.served_to(Source::Api, heads);
    }

    /// Counts heads served to `source`; the heads/s gauge counts every source.
    pub fn served_to(&self, source: Source, heads: u64) {
        match source {
            Source::Api => &self.heads,
            Source::Loadtest => &self.loadtest_heads,
        }
        .fetch_add(heads, Ordering::Relaxed);
        if let Ok(mut w) = self.rate.lock() {
            roll(&mut w);
            w.count += heads;
        }
    }

    /// Counts an answered crowd-frame request by source and status.
    pub fn crowd_frame(&self, source: Source, status: u16) {
        if let Ok(mut m) = self.crowd_frames.lock() {
            *m.entry((source, status)).or_insert(0) += 1;
        }
    }

    /// Requests counted so far with this route and status (for tests and the benchmark).
    pub fn requests_with(&self, route: &str, status: u16) -> u64 {
        self.requests
            .lock()
            .map(|m| m.get(&(route.to_string(), status)).copied().unwrap_or(0))
            .unwrap_or(0)
    }

    /// Renders every metric in the Prometheus text format.
    pub fn render(&self, g: Gauges) -> String {
        let mut o = String::with_capacity(8192);
        let c = |o: &mut String, name: &str, help: &str, v: u64| {
            let _ = writeln!(o, "# HELP {name} {help}\n# TYPE {name} counter\n{name} {v}");
        };
        let gauge = |o: &mut String, name: &str, help: &str, v: f64| {
            let _ = writeln!(o, "# HELP {name} {help}\n# TYPE {name} gauge\n{name} {v}");
        };
        let _ = writeln!(
            o,
            "# HELP crowdmorph_http_requests_total HTTP requests by route and status.\n\
             # TYPE crowdmorph_http_requests_total counter"
        );
        if let Ok(m) = self.requests.lock() {
            for ((route, status), n) in m.iter() {
                let _ = writeln!(
                    o,
                    "crowdmorph_http_requests_total{{route=\"{route}\",status=\"{status}\"}} {n}"
                );
            }
        }
        let _ = writeln!(
            o,
            "# HELP crowdmorph_rejected_total Requests refused or abandoned, by reason.\n\
             # TYPE crowdmorph_rejected_total counter"
        );
        if let Ok(m) = self.rejected.lock() {
            for (reason, n) in m.iter() {
                let _ = writeln!(o, "crowdmorph_rejected_total{{reason=\"{reason}\"}} {n}");
            }
        }
        let _ = writeln!(
            o,
            "# HELP crowdmorph_cancelled_total Work stopped at a stage boundary because its \
             request was gone or past its deadline, by kind of work and reason.\n\
             # TYPE crowdmorph_cancelled_total counter"
        );
        if let Ok(m) = self.cancelled.lock() {
            for ((work, reason), n) in m.iter() {
                let _ = writeln!(
                    o,
                    "crowdmorph_cancelled_total{{work=\"{work}\",reason=\"{reason}\"}} {n}"
                );
            }
        }
        let _ = writeln!(
            o,
            "# HELP crowdmorph_connections_closed_total Connections closed, by reason.\n\
             # TYPE crowdmorph_connections_closed_total counter"
        );
        if let Ok(m) = self.connections_closed.lock() {
            for (reason, n) in m.iter() {
                let _ = writeln!(
                    o,
                    "crowdmorph_connections_closed_total{{reason=\"{reason}\"}} {n}"
                );
            }
        }
        self.queue_seconds.write(
            &mut o,
            "crowdmorph_queue_seconds",
            "Time crowd requests waited from admission to the start of their last batch.",
        );
        self.compute_seconds.write(
            &mut o,
            "crowdmorph_compute_seconds",
            "Engine wall time per batch.",
        );
        self.request_seconds.write(
            &mut o,
            "crowdmorph_request_seconds",
            "Crowd request latency from arrival to response ready.",
        );
        self.batch_jobs
            .write(&mut o, "crowdmorph_batch_jobs", "Unique jobs per batch.");
        self.request_heads.write(
            &mut o,
            "crowdmorph_request_heads",
            "Heads per crowd request.",
        );
        let load = |a: &AtomicU64| a.load(Ordering::Relaxed);
        c(
            &mut o,
            "crowdmorph_connections_accepted_total",
            "Connections accepted, refused ones included.",
            load(&self.connections_accepted),
        );
        c(
            &mut o,
            "crowdmorph_accept_errors_total",
            "Failed accepts (e.g. the open-file limit reached).",
            load(&self.accept_errors),
        );
        gauge(
            &mut o,
            "crowdmorph_connections_open",
            "Connections open now.",
            load(&self.connections_open) as f64,
        );
        gauge(
            &mut o,
            "crowdmorph_connections_limit",
            "Most connections open at once; past it the longest-idle one is closed.",
            g.connections_limit as f64,
        );
        let heads = load(&self.heads);
        let loadtest_heads = load(&self.loadtest_heads);
        let computed = load(&self.jobs_computed);
        let _ = writeln!(
            o,
            "# HELP crowdmorph_heads_total Heads served, by source (api: clients; loadtest: \
             POST /v1/loadtest).\n# TYPE crowdmorph_heads_total counter\n\
             crowdmorph_heads_total{{source=\"api\"}} {heads}\n\
             crowdmorph_heads_total{{source=\"loadtest\"}} {loadtest_heads}"
        );
        let _ = writeln!(
            o,
            "# HELP crowdmorph_crowd_frames_total Crowd-frame requests answered, by source and \
             status, each once (a client's is also in crowdmorph_http_requests_total under its \
             route: do not add the two).\n# TYPE crowdmorph_crowd_frames_total counter"
        );
        if let Ok(m) = self.crowd_frames.lock() {
            for ((source, status), n) in m.iter() {
                let _ = writeln!(
                    o,
                    "crowdmorph_crowd_frames_total{{source=\"{}\",status=\"{status}\"}} {n}",
                    source.label()
                );
            }
        }
        let heads = heads + loadtest_heads;
        c(
            &mut o,
            "crowdmorph_jobs_requested_total",
            "Unique jobs asked for, summed over requests.",
            load(&self.jobs_requested),
        );
        c(
            &mut o,
            "crowdmorph_jobs_computed_total",
            "Jobs the engine computed.",
            computed,
        );
        c(
            &mut o,
            "crowdmorph_jobs_coalesced_total",
            "Jobs that joined an identical in-flight job of another request.",
            load(&self.jobs_coalesced),
        );
        c(
            &mut o,
            "crowdmorph_jobs_cancelled_total",
            "Jobs dropped before computing because no request waited for them any more.",
            load(&self.jobs_cancelled),
        );
        c(
            &mut o,
            "crowdmorph_batches_total",
            "Batches dispatched.",
            load(&self.batches),
        );
        c(
            &mut o,
            "crowdmorph_engine_dispatches_total",
            "Engine evaluations (one per rig and output kind per batch).",
            load(&self.dispatches),
        );
        c(
            &mut o,
            "crowdmorph_batches_pipelined_total",
            "Batches submitted to the GPU while an earlier batch was still computing.",
            load(&self.batches_pipelined),
        );
        c(
            &mut o,
            "crowdmorph_lod_builds_cancelled_total",
            "LOD builds stopped early by a newer PUT, a delete or shutdown.",
            load(&self.lod_builds_cancelled),
        );
        c(
            &mut o,
            "crowdmorph_session_panics_total",
            "Session tick tasks that panicked; each ended its session (a bug: the log has it).",
            load(&self.session_panics),
        );
        gauge(
            &mut o,
            "crowdmorph_lod_builds_running",
            "LOD builds computing now.",
            load(&self.lod_builds_running) as f64,
        );
        let _ = writeln!(
            o,
            "# HELP crowdmorph_gpu_seconds_total GPU time of evaluations.\n\
             # TYPE crowdmorph_gpu_seconds_total counter\ncrowdmorph_gpu_seconds_total {}",
            load(&self.gpu_ns) as f64 / 1e9
        );
        gauge(
            &mut o,
            "crowdmorph_unique_job_ratio",
            "Jobs computed per head served (1 = no sharing; lower = more clones and coalescing).",
            if heads == 0 {
                1.0
            } else {
                computed as f64 / heads as f64
            },
        );
        let rate = self
            .rate
            .lock()
            .map(|mut w| {
                roll(&mut w);
                w.last_rate
            })
            .unwrap_or(0.0);
        gauge(
            &mut o,
            "crowdmorph_heads_per_second",
            "Heads served during the last complete second.",
            rate,
        );
        gauge(
            &mut o,
            "crowdmorph_queue_depth",
            "Crowd requests in the batcher.",
            load(&self.queue_depth) as f64,
        );
        gauge(
            &mut o,
            "crowdmorph_queue_memory_bytes",
            "Output bytes admitted crowd requests hold.",
            g.queue_memory_bytes as f64,
        );
        gauge(
            &mut o,
            "crowdmorph_queue_memory_limit_bytes",
            "Limit on the output bytes admitted requests may hold.",
            g.queue_memory_limit as f64,
        );
        gauge(
            &mut o,
            "crowdmorph_render_pixels",
            "Pixels rendered frames in flight hold.",
            g.render_pixels as f64,
        );
        gauge(
            &mut o,
            "crowdmorph_render_pixels_limit",
            "Limit on the pixels rendered frames in flight may hold (--render-pixels).",
            g.render_pixels_limit as f64,
        );
        gauge(
            &mut o,
            "crowdmorph_render_work_seconds",
            "Estimated seconds of work that rendered frames in flight hold.",
            g.render_work_seconds,
        );
        gauge(
            &mut o,
            "crowdmorph_render_work_limit_seconds",
            "Limit on the estimated work of rendered frames in flight (--render-work-ms).",
            g.render_work_limit_seconds,
        );
        gauge(
            &mut o,
            "crowdmorph_gpu_memory_bytes",
            "Bytes charged to the GPU memory budget: rigs, batches, render targets (0 without a GPU).",
            g.gpu_memory_bytes as f64,
        );
        gauge(
            &mut o,
            "crowdmorph_gpu_memory_limit_bytes",
            "The GPU memory budget (--max-gpu-memory per device; 0 without a GPU).",
            g.gpu_memory_limit as f64,
        );
        gauge(&mut o, "crowdmorph_rigs", "Rigs registered.", g.rigs as f64);
        gauge(
            &mut o,
            "crowdmorph_rig_host_bytes",
            "Host bytes resident for rigs.",
            g.host_bytes as f64,
        );
        gauge(
            &mut o,
            "crowdmorph_rig_device_bytes",
            "Device bytes resident for rigs.",
            g.device_bytes as f64,
        );
        gauge(
            &mut o,
            "crowdmorph_rig_memory_bytes",
            "Host bytes charged to the rig memory pool: resident rigs, uploads and LOD builds in progress.",
            g.rig_memory_bytes as f64,
        );
        gauge(
            &mut o,
            "crowdmorph_rig_memory_limit_bytes",
            "Size of the rig memory pool (--max-rig-memory).",
            g.rig_memory_limit as f64,
        );
        gauge(
            &mut o,
            "crowdmorph_backend_degraded",
            "1 when the GPU was lost and the CPU engine answers.",
            f64::from(u8::from(g.degraded)),
        );
        gauge(
            &mut o,
            "crowdmorph_loading",
            "1 while stored rigs are loading.",
            f64::from(u8::from(g.loading)),
        );
        o
    }
}

fn roll(w: &mut RateWindow) {
    let elapsed = w.start.elapsed();
    if elapsed >= Duration::from_secs(1) {
        // A window that ended more than a second ago with nothing after it reads as idle.
        w.last_rate = if elapsed < Duration::from_secs(2) {
            w.count as f64 / elapsed.as_secs_f64()
        } else {
            0.0
        };
        w.count = 0;
        w.start = Instant::now();
    }
}
