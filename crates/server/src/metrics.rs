//! Server metrics through `prometheus-client`: one [`Registry`] per server, owned by
//! [`Metrics`] (tests start many servers in one process, so nothing is global), encoded as
//! OpenMetrics text for `GET /metrics`.
//!
//! Counters and histograms are updated where the work happens. The gauges that other parts of
//! the server own (rigs, semaphores, memory pools, the session map: [`Gauges`]) are set just
//! before each encoding, in [`Metrics::encode`], rather than read by a custom collector: a
//! collector would need a handle on `AppState`, which owns this registry (a reference cycle,
//! or a `Weak` to upgrade on every scrape), while the `/metrics` handler already has both.
//! A lock held from setting them to the end of the encoding makes each page one reading.

use std::borrow::Cow;
use std::sync::Mutex;
use std::sync::atomic::AtomicU64;
use std::time::{Duration, Instant};

use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::Histogram;
use prometheus_client::registry::{Metric, Registry};

/// The `Content-Type` of [`Metrics::encode`]'s text: OpenMetrics 1.0.0, which Prometheus
/// scrapes (it asks for it first).
pub const CONTENT_TYPE: &str = "application/openmetrics-text; version=1.0.0; charset=utf-8";

/// Bucket bounds in seconds for latencies (50 µs to 10 s).
const SECONDS: &[f64] = &[
    5e-5, 1e-4, 2.5e-4, 5e-4, 1e-3, 2.5e-3, 5e-3, 1e-2, 2.5e-2, 5e-2, 0.1, 0.25, 0.5, 1.0, 2.5,
    10.0,
];

/// Bucket bounds for counts (jobs per batch, heads per request).
const COUNTS: &[f64] = &[
    1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0, 256.0, 512.0, 1024.0, 4096.0, 16384.0,
];

/// Every reason a request is refused for (`crowdmorph_rejected_total{reason}`).
const REJECT_REASONS: &[&str] = &[
    "overloaded",
    "timeout",
    "queue_full",
    "queue_memory",
    "deadline",
    "render_busy",
    "render_too_costly",
];

/// Every kind of work and reason that `crowdmorph_cancelled_total` counts.
const CANCELLED: &[(&str, &str)] = &[
    ("frame", "dropped"),
    ("frame", "deadline"),
    ("render", "dropped"),
    ("render", "deadline"),
    ("session_frame", "dropped"),
    ("session_frame", "deadline"),
    ("lod", "dropped"),
    ("graph", "dropped"),
    ("graph", "deadline"),
];

/// Every reason a connection is closed for (`crowdmorph_connections_closed_total{reason}`).
const CLOSE_REASONS: &[&str] = &[
    "closed",
    "error",
    "header_timeout",
    "idle_timeout",
    "evicted",
    "refused",
    "shutdown",
];

/// A gauge of a whole number (bytes, counts).
pub type U64Gauge = Gauge<u64, AtomicU64>;
/// A gauge of a real number (seconds, ratios).
pub type F64Gauge = Gauge<f64, AtomicU64>;
/// A counter of a real number (seconds).
pub type F64Counter = Counter<f64, AtomicU64>;

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

/// The `reason` label (of refusals, closed connections and viewers).
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct ReasonLabel {
    /// Why.
    pub reason: Cow<'static, str>,
}

impl ReasonLabel {
    /// The label set `{reason="<reason>"}`.
    pub fn new(reason: impl Into<Cow<'static, str>>) -> ReasonLabel {
        ReasonLabel {
            reason: reason.into(),
        }
    }
}

/// The `how` label of store repairs.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct HowLabel {
    how: &'static str,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct RouteLabels {
    route: String,
    status: u16,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct CancelledLabels {
    work: &'static str,
    reason: &'static str,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct SourceLabel {
    source: &'static str,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct SourceStatusLabels {
    source: &'static str,
    status: u16,
}

/// Heads served per second over the last completed one-second window.
#[derive(Debug)]
struct RateWindow {
    start: Instant,
    count: u64,
    last_rate: f64,
}

/// The gauges set from [`Gauges`] (and from the counters) just before each encoding.
#[derive(Debug, Default)]
struct ScrapeGauges {
    connections_limit: U64Gauge,
    unique_job_ratio: F64Gauge,
    heads_per_second: F64Gauge,
    queue_memory_bytes: U64Gauge,
    queue_memory_limit: U64Gauge,
    render_pixels: U64Gauge,
    render_pixels_limit: U64Gauge,
    render_work_seconds: F64Gauge,
    render_work_limit_seconds: F64Gauge,
    gpu_memory_bytes: U64Gauge,
    gpu_memory_limit: U64Gauge,
    rigs: U64Gauge,
    host_bytes: U64Gauge,
    device_bytes: U64Gauge,
    rig_memory_bytes: U64Gauge,
    rig_memory_limit: U64Gauge,
    degraded: U64Gauge,
    loading: U64Gauge,
    sessions: U64Gauge,
    session_viewers: U64Gauge,
}

/// Every metric the server exports, and the registry that encodes them.
#[derive(Debug)]
pub struct Metrics {
    registry: Registry,
    requests: Family<RouteLabels, Counter>,
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
    /// Heads served to clients (`crowdmorph_heads_total{source="api"}`).
    heads: Counter,
    /// Heads served to `POST /v1/loadtest`'s synthetic requests (`source="loadtest"`).
    loadtest_heads: Counter,
    /// Crowd-frame requests answered, by source and status: one count per response, made by
    /// the handler (`api::crowd_frame_from`), the one place that sees synthetic requests too.
    /// A client's response is also counted by route in `requests`, as every HTTP response is.
    crowd_frames: Family<SourceStatusLabels, Counter>,
    /// Unique jobs asked for, summed over requests (after in-request dedupe).
    pub jobs_requested: Counter,
    /// Jobs the engine computed.
    pub jobs_computed: Counter,
    /// Jobs that joined an identical job of another request already queued or computing.
    pub jobs_coalesced: Counter,
    /// Jobs dropped before computing because every request waiting for them had gone.
    pub jobs_cancelled: Counter,
    /// Batches dispatched.
    pub batches: Counter,
    /// Engine dispatches (one per rig and output kind per batch).
    pub dispatches: Counter,
    /// Batches begun on the engine while an earlier one was still computing (GPU pipelining).
    pub batches_pipelined: Counter,
    /// GPU time of evaluations, seconds.
    pub gpu_seconds: F64Counter,
    /// Batches a healthy GPU engine ran on the CPU because its memory budget was full (the
    /// engine counts them; brought up to its count at each scrape).
    gpu_fallbacks: Counter,
    /// LOD builds computing now (background jobs and PUTs).
    pub lod_builds_running: U64Gauge,
    /// LOD builds that stopped early because they were cancelled (a newer PUT, a delete,
    /// shutdown, or the server state being dropped).
    pub lod_builds_cancelled: Counter,
    /// Requests refused by reason (`overloaded`, `queue_full`, `deadline`, `timeout`, ...).
    rejected: Family<ReasonLabel, Counter>,
    /// Work stopped before it finished because its request was gone or late, by kind of work
    /// (`render`, `session_frame`, `frame`, `lod`) and reason (`dropped`, `deadline`).
    cancelled: Family<CancelledLabels, Counter>,
    /// Session tick tasks that panicked (each ended its session).
    pub session_panics: Counter,
    /// Rigs looked up in the shared store because a request named one this replica did not
    /// hold, and those the store had.
    store_lookups: Counter,
    store_lookups_found: Counter,
    /// Time those lookups took (the listing, and the read of a rig found).
    store_lookup_seconds: Histogram,
    /// Refreshes from the shared store that failed (the store did not answer).
    store_refresh_failures: Counter,
    /// Damaged objects of the shared store repaired, by how (`restored` from this replica's
    /// copy, or from an `earlier_copy` or dropped).
    store_repairs: Family<HowLabel, Counter>,
    /// Connections admitted and not yet closed.
    pub connections_open: U64Gauge,
    /// Connections accepted from the listener, refused ones included.
    pub connections_accepted: Counter,
    /// Connections closed, by reason (`closed`, `error`, `header_timeout`, `idle_timeout`,
    /// `evicted`, `refused`, `shutdown`).
    connections_closed: Family<ReasonLabel, Counter>,
    /// Failed `accept` calls other than a connection reset before it was accepted (e.g. the
    /// open-file limit reached).
    pub accept_errors: Counter,
    /// Crowd requests waiting in or being served by the batcher; the batcher's admission
    /// count itself (`Gauge::inner` for its compare-and-undo).
    pub queue_depth: U64Gauge,
    rate: Mutex<RateWindow>,
    /// Set and encoded under this lock, one scrape at a time.
    scraped: Mutex<ScrapeGauges>,
}

/// Registers `metric` as family `name` with `help`, and returns it: the handle the server
/// records through shares its series with the registry.
fn registered<M: Metric + Clone>(r: &mut Registry, name: &str, help: &str, metric: M) -> M {
    r.register(name, help, metric.clone());
    metric
}

impl Default for Metrics {
    // Long on purpose: the one table of every family the server registers, with its name and
    // help text, in the order README.md's metrics table lists them; split into pieces, a
    // family's registration and its handle in the struct would be written in two places.
    fn default() -> Self {
        // Help texts go without their final period: the registry adds one.
        let mut r = Registry::default();
        let requests = registered(
            &mut r,
            "crowdmorph_http_requests",
            "HTTP requests by route and status",
            Family::<RouteLabels, Counter>::default(),
        );
        let rejected = registered(
            &mut r,
            "crowdmorph_rejected",
            "Requests refused or abandoned, by reason",
            Family::<ReasonLabel, Counter>::default(),
        );
        let cancelled = registered(
            &mut r,
            "crowdmorph_cancelled",
            "Work stopped at a stage boundary because its request was gone or past its \
             deadline, by kind of work and reason",
            Family::<CancelledLabels, Counter>::default(),
        );
        let connections_closed = registered(
            &mut r,
            "crowdmorph_connections_closed",
            "Connections closed, by reason",
            Family::<ReasonLabel, Counter>::default(),
        );
        // The series of a known label value are made at 0 from the start, as `heads` and the
        // session counters are: the encoder writes no family that has no series yet, and a
        // series that appears with its first event loses that event to `rate()`. Routes and
        // statuses come as they are answered.
        for reason in REJECT_REASONS {
            let _ = rejected.get_or_create(&ReasonLabel::new(*reason));
        }
        for &(work, reason) in CANCELLED {
            let _ = cancelled.get_or_create(&CancelledLabels { work, reason });
        }
        for reason in CLOSE_REASONS {
            let _ = connections_closed.get_or_create(&ReasonLabel::new(*reason));
        }
        let mut histogram = |name: &str, help: &str, bounds: &[f64]| {
            registered(&mut r, name, help, Histogram::new(bounds.iter().copied()))
        };
        let queue_seconds = histogram(
            "crowdmorph_queue_seconds",
            "Time crowd requests waited from admission to the start of their last batch",
            SECONDS,
        );
        let compute_seconds = histogram(
            "crowdmorph_compute_seconds",
            "Engine wall time per batch",
            SECONDS,
        );
        let request_seconds = histogram(
            "crowdmorph_request_seconds",
            "Crowd request latency from arrival to response ready",
            SECONDS,
        );
        let batch_jobs = histogram("crowdmorph_batch_jobs", "Unique jobs per batch", COUNTS);
        let request_heads = histogram(
            "crowdmorph_request_heads",
            "Heads per crowd request",
            COUNTS,
        );
        // Counters are registered without `_total`: the encoder appends it to their samples.
        let mut counter =
            |name: &str, help: &str| registered(&mut r, name, help, Counter::default());
        let connections_accepted = counter(
            "crowdmorph_connections_accepted",
            "Connections accepted, refused ones included",
        );
        let accept_errors = counter(
            "crowdmorph_accept_errors",
            "Failed accepts (e.g. the open-file limit reached)",
        );
        let connections_open = registered(
            &mut r,
            "crowdmorph_connections_open",
            "Connections open now",
            U64Gauge::default(),
        );
        let s = ScrapeGauges::default();
        r.register(
            "crowdmorph_connections_limit",
            "Most connections open at once; past it the longest-idle one is closed",
            s.connections_limit.clone(),
        );
        let heads_by_source = registered(
            &mut r,
            "crowdmorph_heads",
            "Heads served, by source (api: clients; loadtest: POST /v1/loadtest)",
            Family::<SourceLabel, Counter>::default(),
        );
        // Both series exist from the start, at 0, as they always have.
        let heads = heads_by_source.get_or_create_owned(&SourceLabel {
            source: Source::Api.label(),
        });
        let loadtest_heads = heads_by_source.get_or_create_owned(&SourceLabel {
            source: Source::Loadtest.label(),
        });
        let crowd_frames = registered(
            &mut r,
            "crowdmorph_crowd_frames",
            "Crowd-frame requests answered, by source and status, each once (a client's is \
             also in crowdmorph_http_requests_total under its route: do not add the two)",
            Family::<SourceStatusLabels, Counter>::default(),
        );
        let mut counter =
            |name: &str, help: &str| registered(&mut r, name, help, Counter::default());
        let jobs_requested = counter(
            "crowdmorph_jobs_requested",
            "Unique jobs asked for, summed over requests",
        );
        let jobs_computed = counter("crowdmorph_jobs_computed", "Jobs the engine computed");
        let jobs_coalesced = counter(
            "crowdmorph_jobs_coalesced",
            "Jobs that joined an identical in-flight job of another request",
        );
        let jobs_cancelled = counter(
            "crowdmorph_jobs_cancelled",
            "Jobs dropped before computing because no request waited for them any more",
        );
        let batches = counter("crowdmorph_batches", "Batches dispatched");
        let dispatches = counter(
            "crowdmorph_engine_dispatches",
            "Engine evaluations (one per rig and output kind per batch)",
        );
        let batches_pipelined = counter(
            "crowdmorph_batches_pipelined",
            "Batches submitted to the GPU while an earlier batch was still computing",
        );
        let lod_builds_cancelled = counter(
            "crowdmorph_lod_builds_cancelled",
            "LOD builds stopped early by a newer PUT, a delete or shutdown",
        );
        let gpu_fallbacks = counter(
            "crowdmorph_gpu_fallbacks",
            "Batches the GPU engine ran on the CPU because the GPU memory budget \
             (--max-gpu-memory) was full",
        );
        let session_panics = counter(
            "crowdmorph_session_panics",
            "Session tick tasks that panicked; each ended its session (a bug: the log has it)",
        );
        let store_lookups = counter(
            "crowdmorph_store_lookups",
            "Rigs looked up in the shared store (--store) because a request named one this \
             replica did not hold",
        );
        let store_lookups_found = counter(
            "crowdmorph_store_lookups_found",
            "Store lookups that found the rig and loaded it",
        );
        let store_refresh_failures = counter(
            "crowdmorph_store_refresh_failures",
            "Refreshes from the shared store that failed because it did not answer",
        );
        let store_repairs = registered(
            &mut r,
            "crowdmorph_store_repairs",
            "Generations of the shared store written to repair damaged objects (missing, \
             short or failing their checksum), by how: restored from this replica's copy of \
             the very objects, or from an earlier intact copy (objects without one dropped)",
            Family::<HowLabel, Counter>::default(),
        );
        for how in ["restored", "earlier_copy"] {
            let _ = store_repairs.get_or_create(&HowLabel { how });
        }
        let store_lookup_seconds = registered(
            &mut r,
            "crowdmorph_store_lookup_seconds",
            "Time a store lookup took: one listing, and the read of a rig found",
            Histogram::new(SECONDS.iter().copied()),
        );
        let lod_builds_running = registered(
            &mut r,
            "crowdmorph_lod_builds_running",
            "LOD builds computing now",
            U64Gauge::default(),
        );
        let gpu_seconds = registered(
            &mut r,
            "crowdmorph_gpu_seconds",
            "GPU time of evaluations",
            F64Counter::default(),
        );
        r.register(
            "crowdmorph_unique_job_ratio",
            "Jobs computed per head served (1 = no sharing; lower = more clones and coalescing)",
            s.unique_job_ratio.clone(),
        );
        r.register(
            "crowdmorph_heads_per_second",
            "Heads served during the last complete second",
            s.heads_per_second.clone(),
        );
        let queue_depth = registered(
            &mut r,
            "crowdmorph_queue_depth",
            "Crowd requests in the batcher",
            U64Gauge::default(),
        );
        let gauges: [(&str, &str, &U64Gauge); 4] = [
            (
                "crowdmorph_queue_memory_bytes",
                "Output bytes admitted crowd requests hold",
                &s.queue_memory_bytes,
            ),
            (
                "crowdmorph_queue_memory_limit_bytes",
                "Limit on the output bytes admitted requests may hold",
                &s.queue_memory_limit,
            ),
            (
                "crowdmorph_render_pixels",
                "Pixels rendered frames in flight hold",
                &s.render_pixels,
            ),
            (
                "crowdmorph_render_pixels_limit",
                "Limit on the pixels rendered frames in flight may hold (--render-pixels)",
                &s.render_pixels_limit,
            ),
        ];
        for (name, help, g) in gauges {
            r.register(name, help, g.clone());
        }
        r.register(
            "crowdmorph_render_work_seconds",
            "Estimated seconds of work that rendered frames in flight hold",
            s.render_work_seconds.clone(),
        );
        r.register(
            "crowdmorph_render_work_limit_seconds",
            "Limit on the estimated work of rendered frames in flight (--render-work-ms)",
            s.render_work_limit_seconds.clone(),
        );
        let gauges: [(&str, &str, &U64Gauge); 11] = [
            (
                "crowdmorph_gpu_memory_bytes",
                "Bytes charged to the GPU memory budget: rigs, batches, render targets \
                 (0 without a GPU)",
                &s.gpu_memory_bytes,
            ),
            (
                "crowdmorph_gpu_memory_limit_bytes",
                "The GPU memory budget (--max-gpu-memory per device; 0 without a GPU)",
                &s.gpu_memory_limit,
            ),
            ("crowdmorph_rigs", "Rigs registered", &s.rigs),
            (
                "crowdmorph_rig_host_bytes",
                "Host bytes resident for rigs",
                &s.host_bytes,
            ),
            (
                "crowdmorph_rig_device_bytes",
                "Device bytes resident for rigs",
                &s.device_bytes,
            ),
            (
                "crowdmorph_rig_memory_bytes",
                "Host bytes charged to the rig memory pool: resident rigs, uploads and LOD \
                 builds in progress",
                &s.rig_memory_bytes,
            ),
            (
                "crowdmorph_rig_memory_limit_bytes",
                "Size of the rig memory pool (--max-rig-memory)",
                &s.rig_memory_limit,
            ),
            (
                "crowdmorph_backend_degraded",
                "1 when the GPU was lost and the CPU engine answers",
                &s.degraded,
            ),
            (
                "crowdmorph_loading",
                "1 while stored rigs are loading",
                &s.loading,
            ),
            (
                "crowdmorph_sessions",
                "Crowd sessions that exist now",
                &s.sessions,
            ),
            (
                "crowdmorph_session_viewers",
                "Viewers connected to sessions now",
                &s.session_viewers,
            ),
        ];
        for (name, help, g) in gauges {
            r.register(name, help, g.clone());
        }
        Metrics {
            registry: r,
            requests,
            queue_seconds,
            compute_seconds,
            request_seconds,
            batch_jobs,
            request_heads,
            heads,
            loadtest_heads,
            crowd_frames,
            jobs_requested,
            jobs_computed,
            jobs_coalesced,
            jobs_cancelled,
            batches,
            dispatches,
            batches_pipelined,
            gpu_seconds,
            gpu_fallbacks,
            lod_builds_running,
            lod_builds_cancelled,
            rejected,
            cancelled,
            session_panics,
            store_lookups,
            store_lookups_found,
            store_lookup_seconds,
            store_refresh_failures,
            store_repairs,
            connections_open,
            connections_accepted,
            connections_closed,
            accept_errors,
            queue_depth,
            rate: Mutex::new(RateWindow {
                start: Instant::now(),
                count: 0,
                last_rate: 0.0,
            }),
            scraped: Mutex::new(s),
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
                .cancelled(self.work, crowdmorph_core::cancel::Cancelled::Dropped);
        }
    }
}

/// Gauges read from the rest of the server when metrics are encoded.
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
    /// Batches the GPU engine ran on the CPU because its budget was full, since it started.
    pub gpu_fallbacks: u64,
    /// Crowd sessions that exist now.
    pub sessions: u64,
    /// Viewers connected to sessions now.
    pub session_viewers: u64,
}

impl Metrics {
    /// The registry, for parts of the server that register metrics of their own (the session
    /// counters) before the `Metrics` is shared.
    pub fn registry_mut(&mut self) -> &mut Registry {
        &mut self.registry
    }

    /// Counts a finished HTTP request by route and status.
    pub fn request(&self, route: &str, status: u16) {
        self.requests
            .get_or_create(&RouteLabels {
                route: route.to_string(),
                status,
            })
            .inc();
    }

    /// Counts a lookup in the shared store of a rig a request named, found or not.
    pub fn store_lookup(&self, found: bool, took: Duration) {
        self.store_lookups.inc();
        if found {
            self.store_lookups_found.inc();
        }
        self.store_lookup_seconds.observe(took.as_secs_f64());
    }

    /// Counts a repair of damaged objects in the shared store (`restored` or `earlier_copy`).
    pub fn store_repaired(&self, how: &'static str) {
        self.store_repairs.get_or_create(&HowLabel { how }).inc();
    }

    /// Counts a refresh from the shared store that failed.
    pub fn store_refresh_failed(&self) {
        self.store_refresh_failures.inc();
    }

    /// Counts a refused request.
    pub fn reject(&self, reason: &'static str) {
        self.rejected.get_or_create(&ReasonLabel::new(reason)).inc();
    }

    /// Counts work of kind `work` stopped by its cancellation.
    pub fn cancelled(&self, work: &'static str, why: crowdmorph_core::cancel::Cancelled) {
        let reason = match why {
            crowdmorph_core::cancel::Cancelled::Dropped => "dropped",
            crowdmorph_core::cancel::Cancelled::Deadline => "deadline",
        };
        self.cancelled
            .get_or_create(&CancelledLabels { work, reason })
            .inc();
    }

    /// Counts a closed connection.
    pub fn connection_closed(&self, reason: &'static str) {
        self.connections_closed
            .get_or_create(&ReasonLabel::new(reason))
            .inc();
    }

    /// Connections closed so far for this reason (for tests).
    pub fn connections_closed_with(&self, reason: &str) -> u64 {
        self.connections_closed
            .get(&ReasonLabel::new(reason.to_string()))
            .map_or(0, |c| c.get())
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
        .inc_by(heads);
        if let Ok(mut w) = self.rate.lock() {
            roll(&mut w);
            w.count += heads;
        }
    }

    /// Counts an answered crowd-frame request by source and status.
    pub fn crowd_frame(&self, source: Source, status: u16) {
        self.crowd_frames
            .get_or_create(&SourceStatusLabels {
                source: source.label(),
                status,
            })
            .inc();
    }

    /// Every metric as OpenMetrics text (ending in `# EOF`; [`CONTENT_TYPE`]), with the
    /// gauges `g` read from the rest of the server just before.
    pub fn encode(&self, g: Gauges) -> Result<String, std::fmt::Error> {
        let s = self.scraped.lock().map_err(|_| std::fmt::Error)?;
        s.connections_limit.set(g.connections_limit);
        let heads = self.heads.get() + self.loadtest_heads.get();
        let computed = self.jobs_computed.get();
        s.unique_job_ratio.set(if heads == 0 {
            1.0
        } else {
            computed as f64 / heads as f64
        });
        let rate = self
            .rate
            .lock()
            .map(|mut w| {
                roll(&mut w);
                w.last_rate
            })
            .unwrap_or(0.0);
        s.heads_per_second.set(rate);
        s.queue_memory_bytes.set(g.queue_memory_bytes);
        s.queue_memory_limit.set(g.queue_memory_limit);
        s.render_pixels.set(g.render_pixels);
        s.render_pixels_limit.set(g.render_pixels_limit);
        s.render_work_seconds.set(g.render_work_seconds);
        s.render_work_limit_seconds.set(g.render_work_limit_seconds);
        s.gpu_memory_bytes.set(g.gpu_memory_bytes);
        s.gpu_memory_limit.set(g.gpu_memory_limit);
        // Under the scrape lock: two scrapes cannot both add the same difference.
        let counted = self.gpu_fallbacks.get();
        if g.gpu_fallbacks > counted {
            self.gpu_fallbacks.inc_by(g.gpu_fallbacks - counted);
        }
        s.rigs.set(g.rigs);
        s.host_bytes.set(g.host_bytes);
        s.device_bytes.set(g.device_bytes);
        s.rig_memory_bytes.set(g.rig_memory_bytes);
        s.rig_memory_limit.set(g.rig_memory_limit);
        s.degraded.set(u64::from(g.degraded));
        s.loading.set(u64::from(g.loading));
        s.sessions.set(g.sessions);
        s.session_viewers.set(g.session_viewers);
        let mut out = String::with_capacity(16384);
        prometheus_client::encoding::text::encode(&mut out, &self.registry)?;
        drop(s);
        Ok(out)
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
