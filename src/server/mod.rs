//! The HTTP server: rigs and clips over a REST API, crowd frames through the dynamic batcher.
//!
//! Shape (after the axum examples): [`AppState`] holds everything a handler needs, [`app`]
//! builds the [`Router`] (usable in tests with `tower::ServiceExt::oneshot`), and [`run`] serves
//! it on a listener until a shutdown future resolves, then drains the batcher. `main.rs` only
//! parses the command line, sets up tracing and calls [`run`].
//!
//! | module | what it is |
//! |---|---|
//! | [`config`] | every limit, timeout and default |
//! | `conn` | the accept loop: header and idle timeouts, the connection cap |
//! | [`error`] | [`ApiError`]: the JSON error body of every 4xx/5xx |
//! | [`registry`] | rigs prepared for the engine, q16 boxes, API descriptions |
//! | [`scheduler`] | the dynamic batcher with cross-request dedupe |
//! | [`metrics`] | Prometheus text metrics |
//! | `api` | the handlers |
//! | `json` | JSON crowd frames written straight into reused buffers |
//! | `render` | `POST /v1/crowd/render`: a picture of a crowd |
//! | [`sessions`] | crowd sessions: a crowd on a fixed tick, streamed to many viewers over WebSockets |
//! | [`loadtest`] | `POST /v1/loadtest`: synthetic load through the real batcher, at low priority |
//! | `viewer` | `GET /viewer`: the browser viewer's embedded files |

mod api;
pub mod config;
mod conn;
pub mod error;
mod json;
pub mod loadtest;
mod lod;
pub mod metrics;
mod pool;
pub mod registry;
mod render;
pub mod scheduler;
pub mod sessions;
mod viewer;

use std::future::Future;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use axum::Router;
use axum::error_handling::HandleErrorLayer;
use axum::extract::{DefaultBodyLimit, MatchedPath, Request, State};
use axum::http::{HeaderName, HeaderValue, Method, StatusCode, header};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use tokio::net::TcpListener;
use tokio::sync::Semaphore;
use tower::ServiceBuilder;
use tower_http::classify::ServerErrorsFailureClass;
use tower_http::cors::{AllowOrigin, CorsLayer};
use tower_http::request_id::{
    MakeRequestId, PropagateRequestIdLayer, RequestId, SetRequestIdLayer,
};
use tower_http::trace::TraceLayer;

pub use config::{RenderBackend, ServerConfig, default_data_dir};
pub use error::ApiError;

use crate::budget::{Budget, MemoryPool};
use crate::engine::{Engine, EngineError};
use crate::rig::RigShape;
use crate::store::{Record, Store, StoreError, geometry_fingerprint};
use metrics::{Gauges, Metrics};
use registry::{BUILTIN_ID, ClipLayout, Registry, RigEntry, quantization_box};
use scheduler::{BatchConfig, Scheduler};

/// Why the server could not start or stopped abnormally.
#[derive(Debug, thiserror::Error)]
pub enum ServerError {
    /// The engine could not be created (e.g. `--backend gpu` without a GPU).
    #[error("engine: {0}")]
    Engine(#[from] EngineError),
    /// The data directory is unusable.
    #[error("data directory: {0}")]
    Store(#[from] StoreError),
    /// Serving failed.
    #[error("serving: {0}")]
    Io(#[from] std::io::Error),
}

/// Shared state of every handler.
#[derive(Clone, Debug)]
pub struct AppState(Arc<Inner>);

/// What [`AppState`] holds.
#[derive(Debug)]
pub struct Inner {
    /// Configuration.
    pub config: ServerConfig,
    /// The engine.
    pub engine: Arc<Engine>,
    /// Registered rigs.
    pub registry: Registry,
    /// The batcher.
    pub scheduler: Scheduler,
    /// Metrics.
    pub metrics: Arc<Metrics>,
    /// Persistence, when a data dir is configured.
    pub store: Option<Store>,
    ready: AtomicBool,
    load_started: AtomicBool,
    skipped: Mutex<Vec<String>>,
    /// Serializes rig and clip changes (and their writes to disk).
    admin: tokio::sync::Mutex<()>,
    /// Host memory of rigs and of the work that makes them (`--max-rig-memory`).
    pub pool: Arc<MemoryPool>,
    /// Output memory admitted crowd requests hold, in KiB permits.
    memory: Arc<Semaphore>,
    memory_units: u32,
    /// Imports run at most two at a time (each may hold up to `max_upload_memory`); the
    /// permit is taken before the body is read.
    uploads: Semaphore,
    /// Requests being handled; past `max_concurrency` new ones are shed.
    inflight: Arc<Semaphore>,
    /// Background LOD computations by rig id.
    lod_jobs: lod::LodJobs,
    /// LOD builds run at most two at a time: each keeps the rayon pool busy for seconds.
    lod_builds: Arc<Semaphore>,
    /// The rate-limited summary of shed and timed-out requests.
    shed_log: ShedLog,
    /// Pixels and estimated work that renders in flight hold (`--render-pixels`,
    /// `--render-work-ms`, `--viewer-render-share`).
    render_budget: render::RenderBudget,
    /// The renderer (or why there is none) and its topologies.
    render: render::RenderState,
    /// Crowd sessions by id.
    pub sessions: sessions::Sessions,
    /// Reused buffers of JSON crowd frames.
    json_pool: Arc<json::JsonPool>,
    /// `POST /v1/loadtest`: the load running and the last ones done.
    loadtests: loadtest::Loadtests,
}

impl Drop for Inner {
    /// The state's owner is gone (the server stopped, a test ended): LOD builds still
    /// computing for it are cancelled rather than left running on the blocking pool, which
    /// would also hold up the runtime's shutdown.
    fn drop(&mut self) {
        self.lod_jobs.cancel_all();
    }
}

impl std::ops::Deref for AppState {
    type Target = Inner;
    fn deref(&self) -> &Inner {
        &self.0
    }
}

impl AppState {
    /// Creates the engine, the batcher and the registry with the embedded rig. Stored rigs are
    /// loaded by [`AppState::load_stored`]; until then the server is not ready. Must be called
    /// inside a tokio runtime.
    pub fn new(config: ServerConfig) -> Result<AppState, ServerError> {
        let config_concurrency = config.max_concurrency;
        let gpu_options = crate::engine::gpu::GpuOptions {
            memory: config.gpu_memory,
            ..Default::default()
        };
        let engine = Arc::new(Engine::with_options(config.backend, gpu_options)?);
        let info = engine.info();
        tracing::info!(
            backend = ?info.kind,
            adapter = ?info.adapter,
            cpu_isa = %info.cpu_isa,
            "engine ready"
        );
        // Never fails the start: without an adapter, render requests say why and everything
        // else works.
        let render = render::RenderState::new(crate::render::crowd::RenderDevice::open_with(
            &engine,
            config.render_backend,
            gpu_options,
        ));
        match &render.device {
            Ok(d) => tracing::info!(adapter = %d.name(), shared = d.shared, "renderer ready"),
            Err(why) => tracing::warn!(%why, "rendering unavailable"),
        }
        let store = match &config.data_dir {
            Some(dir) => Some(Store::open(dir)?),
            None => None,
        };
        let metrics = Arc::new(Metrics::default());
        let scheduler = Scheduler::start(
            engine.clone(),
            metrics.clone(),
            BatchConfig {
                queue_requests: config.queue_requests,
                batch_cost: config.batch_cost.max(1),
                batch_delay: config.batch_delay,
                hold_when_idle: config.batch_hold_when_idle,
            },
        );
        let memory_units = u32::try_from((config.queue_memory_bytes / 1024).max(1))
            .unwrap_or(u32::MAX)
            .min(Semaphore::MAX_PERMITS as u32);
        let render_budget = render::RenderBudget::new(
            config.render_pixels,
            config.render_work,
            config.viewer_render_share,
        );
        let registry = Registry::default();
        let pool = MemoryPool::new(config.rig_memory(), "--max-rig-memory");
        let builtin = Arc::new(crate::embedded::default_rig());
        let prepared = engine.prepare(builtin.clone())?;
        // The built-in rig is always there: its memory is taken from the pool unconditionally.
        let charge =
            Budget::new(u64::MAX, "", Some(pool.clone())).keep(prepared.memory().host_bytes as u64);
        registry.insert(Arc::new(RigEntry {
            id: BUILTIN_ID.to_string(),
            builtin: true,
            builtin_clips: builtin.clips.len(),
            vertices: builtin.vertex_count(),
            qbox: quantization_box(&builtin),
            generation: registry.generation(),
            prepared,
            layout: ClipLayout::default(),
            charge: Mutex::new(charge),
            clip_names: Default::default(),
        }));
        Ok(AppState(Arc::new(Inner {
            config,
            engine,
            registry,
            scheduler,
            metrics,
            store,
            ready: AtomicBool::new(false),
            load_started: AtomicBool::new(false),
            skipped: Mutex::new(Vec::new()),
            admin: tokio::sync::Mutex::new(()),
            pool,
            memory: Arc::new(Semaphore::new(memory_units as usize)),
            memory_units,
            uploads: Semaphore::new(2),
            inflight: Arc::new(Semaphore::new(
                config_concurrency.clamp(1, Semaphore::MAX_PERMITS),
            )),
            lod_jobs: lod::LodJobs::default(),
            lod_builds: Arc::new(Semaphore::new(2)),
            shed_log: ShedLog::default(),
            render_budget,
            render,
            sessions: sessions::Sessions::default(),
            json_pool: Arc::default(),
            loadtests: loadtest::Loadtests::default(),
        })))
    }

    /// Loads the rigs and clips stored under the data dir (skipping, with a logged reason,
    /// anything corrupt), then marks the server ready.
    /// Only the first call loads; later calls return at once.
    pub async fn load_stored(&self) {
        if self.load_started.swap(true, Ordering::AcqRel) {
            return;
        }
        if let Some(store_dir) = self.store.as_ref().map(|s| s.dir().to_path_buf()) {
            let state = self.clone();
            let loaded = tokio::task::spawn_blocking(move || state.load_blocking()).await;
            match loaded {
                Ok(Ok(n)) => {
                    tracing::info!(rigs = n, dir = %store_dir.display(), "stored rigs loaded")
                }
                Ok(Err(e)) => {
                    tracing::error!(error = %e, "cannot read the data directory");
                    self.skip(e.to_string());
                }
                Err(e) => {
                    tracing::error!(error = %e, "loading stored rigs failed");
                    self.skip(format!("loading failed: {e}"));
                }
            }
        }
        self.ready.store(true, Ordering::Release);
        // Rigs that still have the import's quick order get the metric-based one.
        for entry in self.registry.all() {
            self.start_auto_lod(&entry);
        }
    }

    fn skip(&self, why: String) {
        if let Ok(mut s) = self.skipped.lock() {
            s.push(why);
        }
    }

    /// A budget for one upload, clip import or LOD build: `--max-upload-memory`, drawing
    /// from the pool.
    pub(crate) fn op_budget(&self) -> Arc<Budget> {
        Arc::new(Budget::new(
            self.config.max_upload_memory,
            "--max-upload-memory",
            Some(self.pool.clone()),
        ))
    }

    /// Whether the engine keeps rigs on a GPU (their layouts are then uploaded too).
    pub(crate) fn on_gpu(&self) -> bool {
        self.engine.info().kind == crate::engine::BackendKind::Gpu
    }

    /// Loads the stored records one at a time, each charged to the memory pool before it is
    /// read (about twice its file: the bytes read and the rig decoded from them) and then
    /// holding what its prepared rig occupies. A record that does not fit is skipped and
    /// reported, never deleted.
    fn load_blocking(&self) -> Result<usize, StoreError> {
        let Some(store) = &self.store else {
            return Ok(0);
        };
        let mut n = 0;
        for (path, size) in store.record_files()? {
            let budget = Arc::new(Budget::new(
                self.pool.limit(),
                "--max-rig-memory",
                Some(self.pool.clone()),
            ));
            let file = path.display().to_string();
            if let Err(e) = budget.reserve(2 * size, || format!("stored record {file}")) {
                tracing::error!(error = %e, "skipping a stored rig that does not fit in memory");
                self.skip(e.to_string());
                continue;
            }
            let record = match Store::read(&path) {
                Ok(r) => r,
                Err(e) => {
                    tracing::error!(error = %e, "skipping a stored rig that cannot be loaded");
                    self.skip(e.to_string());
                    continue;
                }
            };
            match self.load_record(record, &budget) {
                Ok(true) => n += 1,
                Ok(false) => {}
                Err(why) => self.skip(why),
            }
        }
        Ok(n)
    }

    /// Registers one stored record; `Ok(true)` for an uploaded rig, `Ok(false)` for the
    /// built-in rig's clips and LOD.
    fn load_record(&self, record: Record, budget: &Budget) -> Result<bool, String> {
        let cost = |rig: &crate::rig::Rig| {
            let c = RigShape::of(rig).cost(self.on_gpu());
            budget
                .charge(c.layout + c.transient, || {
                    format!("preparing stored rig {:?}", rig.name)
                })
                .map_err(|e| e.to_string())
        };
        match record {
            Record::Rig(r) => {
                let r = *r;
                if self.registry.get(&r.id).is_some() {
                    return Err(format!("stored rig {:?} clashes with a built-in id", r.id));
                }
                let rig = Arc::new(r.rig);
                cost(&rig)?;
                let prepared = self
                    .engine
                    .prepare(rig.clone())
                    .map_err(|e| format!("stored rig {:?}: {e}", r.id))?;
                let charge = budget.keep(prepared.memory().host_bytes as u64);
                self.registry.insert(Arc::new(RigEntry {
                    id: r.id,
                    builtin: false,
                    builtin_clips: 0,
                    vertices: rig.vertex_count(),
                    qbox: quantization_box(&rig),
                    generation: self.registry.generation(),
                    prepared,
                    layout: ClipLayout::in_record(&rig.clips),
                    charge: Mutex::new(charge),
                    clip_names: Default::default(),
                }));
                Ok(true)
            }
            Record::Clips(c) => {
                let Some(entry) = self.registry.get(&c.id) else {
                    // The rig's record was deleted and the process stopped before its clip
                    // files were: leftovers of a delete, not data anyone can reach.
                    if let Some(store) = &self.store {
                        tracing::warn!(rig = %c.id, seq = c.seq, "removing clips of a deleted rig");
                        let _ = store.remove_clips(&c.id, c.seq);
                    }
                    return Ok(false);
                };
                let mut rig = entry.rig().clone();
                let names: Vec<String> = c.clips.iter().map(|c| c.name.clone()).collect();
                let mut seen = std::collections::HashSet::new();
                if let Some(dup) = names
                    .iter()
                    .find(|n| entry.clip_index(n).is_some() || !seen.insert(n.as_str()))
                {
                    return Err(format!(
                        "clip file {} of rig {:?} repeats clip {dup:?}",
                        c.seq, c.id
                    ));
                }
                rig.clips.extend(c.clips);
                rig.validate()
                    .map_err(|e| format!("clip file {} of rig {:?}: {e}", c.seq, c.id))?;
                let rig = Arc::new(rig);
                cost(&rig)?;
                let prepared = self
                    .engine
                    .update_clips(&entry.prepared, rig.clone())
                    .map_err(|e| format!("clip file {} of rig {:?}: {e}", c.seq, c.id))?;
                let mut layout = entry.layout.clone();
                layout.files.push((c.seq, names));
                self.registry.insert(Arc::new(entry.successor(
                    prepared,
                    quantization_box(&rig),
                    layout,
                    self.registry.generation(),
                    None,
                )));
                Ok(false)
            }
            Record::Builtin(c) => {
                let Some(entry) = self.registry.get(&c.id).filter(|e| e.builtin) else {
                    return Err(format!("stored clips for unknown built-in rig {:?}", c.id));
                };
                let mut rig = entry.rig().clone();
                let layout = ClipLayout {
                    record: c.clips.iter().map(|c| c.name.clone()).collect(),
                    files: entry.layout.files.clone(),
                };
                rig.clips.extend(c.clips);
                let mut lod_changed = false;
                if let Some((lod, geometry)) = c.lod {
                    if geometry == geometry_fingerprint(&rig) {
                        lod_changed = lod != rig.lod;
                        rig.lod = lod;
                    } else {
                        // This build's built-in rig is not the one the LOD was made for;
                        // the clips still apply, and the background job makes a new LOD.
                        tracing::warn!(rig = %c.id, "stored LOD is for another version of the built-in rig; recomputing it");
                    }
                }
                rig.validate()
                    .map_err(|e| format!("stored clips and LOD of {:?}: {e}", c.id))?;
                let rig = Arc::new(rig);
                cost(&rig)?;
                let prepared = if lod_changed {
                    self.engine.prepare(rig.clone())
                } else {
                    self.engine.update_clips(&entry.prepared, rig.clone())
                }
                .map_err(|e| format!("stored clips and LOD of {:?}: {e}", c.id))?;
                self.registry.insert(Arc::new(entry.successor(
                    prepared,
                    quantization_box(&rig),
                    layout,
                    self.registry.generation(),
                    None,
                )));
                Ok(false)
            }
        }
    }

    /// Whether stored rigs have been loaded.
    pub fn is_ready(&self) -> bool {
        self.ready.load(Ordering::Acquire)
    }

    /// Files skipped at load, with reasons.
    pub fn skipped(&self) -> Vec<String> {
        self.skipped.lock().map(|s| s.clone()).unwrap_or_default()
    }

    /// Current values of the gauges.
    pub fn gauges(&self) -> Gauges {
        let rigs = self.registry.all();
        let (host, device) = rigs.iter().fold((0u64, 0u64), |(h, d), e| {
            let m = e.prepared.memory();
            (h + m.host_bytes as u64, d + m.device_bytes as u64)
        });
        let free = self.memory.available_permits() as u64;
        // The engine and the renderer may share one device, and then one budget.
        let mut gpu_pools: Vec<&Arc<MemoryPool>> = Vec::new();
        for p in [
            self.engine.gpu_memory(),
            self.renderer().map(crate::render::gpu::Renderer::memory),
        ]
        .into_iter()
        .flatten()
        {
            if !gpu_pools.iter().any(|q| Arc::ptr_eq(q, p)) {
                gpu_pools.push(p);
            }
        }
        Gauges {
            rigs: rigs.len() as u64,
            host_bytes: host,
            device_bytes: device,
            queue_memory_bytes: (u64::from(self.memory_units).saturating_sub(free)) * 1024,
            queue_memory_limit: u64::from(self.memory_units) * 1024,
            rig_memory_bytes: self.pool.used(),
            rig_memory_limit: self.pool.limit(),
            degraded: self.engine.info().degraded,
            loading: !self.is_ready(),
            connections_limit: self.config.connection_cap() as u64,
            render_pixels: self.render_budget.pixels().0,
            render_pixels_limit: self.render_budget.pixels().1,
            render_work_seconds: self.render_budget.work_seconds().0,
            render_work_limit_seconds: self.render_budget.work_seconds().1,
            gpu_memory_bytes: gpu_pools.iter().map(|p| p.used()).sum(),
            gpu_memory_limit: gpu_pools.iter().map(|p| p.limit()).sum(),
        }
    }
}

/// Request ids: a process-wide counter, in hex, unless the client sent `x-request-id`.
#[derive(Clone, Debug, Default)]
struct Counter(Arc<AtomicU64>);

impl MakeRequestId for Counter {
    fn make_request_id<B>(&mut self, _: &axum::http::Request<B>) -> Option<RequestId> {
        let n = self.0.fetch_add(1, Ordering::Relaxed);
        HeaderValue::from_str(&format!("{n:08x}"))
            .ok()
            .map(RequestId::new)
    }
}

/// Counts every response by route and status.
async fn count_requests(State(state): State<AppState>, req: Request, next: Next) -> Response {
    let route = req
        .extensions()
        .get::<MatchedPath>()
        .map_or_else(|| "unmatched".to_string(), |p| p.as_str().to_string());
    let resp = next.run(req).await;
    state.metrics.request(&route, resp.status().as_u16());
    resp
}

/// Sheds load: past `max_concurrency` requests in progress, new ones get 503 at once rather
/// than queueing without bound (one semaphore for the whole router, unlike a tower layer,
/// which axum would instantiate per route).
async fn shed_load(State(state): State<AppState>, req: Request, next: Next) -> Response {
    match state.inflight.clone().try_acquire_owned() {
        Ok(permit) => {
            let resp = next.run(req).await;
            drop(permit);
            resp
        }
        Err(_) => {
            state.metrics.reject("overloaded");
            ApiError::unavailable(
                "overloaded",
                "too many requests in progress; retry shortly",
                1,
            )
            .into_response()
        }
    }
}

/// Maps errors of the tower layers (the timeout) to JSON errors.
async fn layer_error(metrics: Arc<Metrics>, err: tower::BoxError) -> Response {
    if err.is::<tower::timeout::error::Elapsed>() {
        metrics.reject("timeout");
        ApiError::new(
            StatusCode::GATEWAY_TIMEOUT,
            "deadline_exceeded",
            "the request took longer than the server's timeout",
        )
        .into_response()
    } else {
        ApiError::internal(err).into_response()
    }
}

/// How often at most [`ShedLog`] writes a line.
const SHED_LOG_EVERY: Duration = Duration::from_secs(1);

/// Requests answered 503 (shed, queue full, not ready) or 504 (past a deadline) are normal
/// operation under load: each is counted in metrics (`crowdmorph_rejected_total` by reason,
/// `crowdmorph_http_requests_total` by status), and the log gets at most one WARN line per
/// [`SHED_LOG_EVERY`] with how many there were. tower-http's default `on_failure` logged each
/// one at ERROR instead: 215,479 lines (74 MB) in 30 s of a storm of 600 connections.
#[derive(Debug, Default)]
struct ShedLog(Mutex<ShedCounts>);

#[derive(Debug, Default)]
struct ShedCounts {
    unavailable: u64,
    timed_out: u64,
    /// When the last line was written.
    last: Option<std::time::Instant>,
}

impl ShedLog {
    fn record(&self, status: StatusCode) {
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
    fn flush(&self) {
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

/// Logs a failed response: 503 and 504 to the [`ShedLog`], anything else (a 500: a bug or a
/// broken engine) at ERROR with its request's span, as tower-http's default does.
fn log_failure(
    state: &AppState,
    class: ServerErrorsFailureClass,
    latency: Duration,
    span: &tracing::Span,
) {
    match class {
        ServerErrorsFailureClass::StatusCode(s)
            if s == StatusCode::SERVICE_UNAVAILABLE || s == StatusCode::GATEWAY_TIMEOUT =>
        {
            state.shed_log.record(s);
        }
        other => tracing::error!(
            parent: span,
            classification = %other,
            latency_ms = latency.as_secs_f64() * 1e3,
            "response failed"
        ),
    }
}

/// Gives the errors axum answers by itself (a method a route does not have, a path segment
/// that is not valid UTF-8, a missing query parameter) the same JSON body as every
/// [`ApiError`], keeping their status and headers (`Allow` on a 405). Their plain-text
/// message, which names the problem and nothing internal, becomes the JSON message.
async fn json_errors(req: Request, next: Next) -> Response {
    let resp = next.run(req).await;
    let status = resp.status();
    let is_json = resp
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with(crowdmorph_proto::CONTENT_TYPE_JSON));
    if !(status.is_client_error() || status.is_server_error()) || is_json {
        return resp;
    }
    let (mut parts, body) = resp.into_parts();
    let text = axum::body::to_bytes(body, 4096).await.unwrap_or_default();
    let text = String::from_utf8_lossy(&text).trim().to_string();
    let code = match status {
        StatusCode::METHOD_NOT_ALLOWED => "method_not_allowed",
        StatusCode::NOT_FOUND => "not_found",
        StatusCode::PAYLOAD_TOO_LARGE => "body_too_large",
        StatusCode::UNSUPPORTED_MEDIA_TYPE => "unsupported_media_type",
        s if s.is_server_error() => "internal",
        _ => "bad_request",
    };
    let message = if text.is_empty() || status.is_server_error() {
        status
            .canonical_reason()
            .unwrap_or("request failed")
            .to_string()
    } else {
        text
    };
    let json = ApiError::new(status, code, message).into_response();
    parts.headers.remove(header::CONTENT_LENGTH);
    parts.headers.insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static(crowdmorph_proto::CONTENT_TYPE_JSON),
    );
    Response::from_parts(parts, json.into_body())
}

/// The router with every route and layer; `state` should have loaded its stored rigs (or be
/// loading them in the background).
pub fn app(state: AppState) -> Router {
    let request_id = HeaderName::from_static("x-request-id");
    let cfg = &state.config;
    let routes = Router::new()
        .route("/healthz", get(api::healthz))
        .route("/readyz", get(api::readyz))
        .route("/metrics", get(api::metrics))
        .route("/v1/rigs", post(api::upload_rig).get(api::list_rigs))
        .route("/v1/rigs/{id}", get(api::get_rig).delete(api::delete_rig))
        .route("/v1/rigs/{id}/mesh", get(api::get_mesh))
        .route("/v1/rigs/{id}/lod", get(lod::get_lod).put(lod::put_lod))
        .route(
            "/v1/rigs/{id}/clips",
            post(api::upload_clips).get(api::list_clips),
        )
        .route(
            "/v1/rigs/{id}/clips/{clip}",
            get(api::get_clip).delete(api::delete_clip),
        )
        .route("/v1/crowd/frame", post(api::crowd_frame))
        .route("/v1/crowd/render", post(render::crowd_render))
        .route("/viewer", get(viewer::index))
        .route("/viewer/{file}", get(viewer::file))
        .route(
            "/v1/sessions",
            post(sessions::create_session).get(sessions::list_sessions),
        )
        .route(
            "/v1/sessions/{id}",
            get(sessions::get_session)
                .patch(sessions::patch_session)
                .delete(sessions::delete_session),
        )
        .route("/v1/sessions/{id}/stream", get(sessions::stream))
        .route("/v1/loadtest", post(loadtest::start_loadtest))
        .route("/v1/loadtest/{id}", get(loadtest::get_loadtest))
        .fallback(api::not_found)
        // Bodies are read with explicit per-route limits (see api::read_body).
        .layer(DefaultBodyLimit::disable())
        .layer(middleware::from_fn(json_errors))
        .layer(middleware::from_fn_with_state(state.clone(), shed_load))
        .layer(middleware::from_fn_with_state(
            state.clone(),
            count_requests,
        ));
    let cors = (!cfg.cors_origins.is_empty()).then(|| {
        let origins = if cfg.cors_origins.iter().any(|o| o == "*") {
            AllowOrigin::any()
        } else {
            AllowOrigin::list(
                cfg.cors_origins
                    .iter()
                    .filter_map(|o| HeaderValue::from_str(o).ok()),
            )
        };
        CorsLayer::new()
            .allow_origin(origins)
            .allow_methods([
                Method::GET,
                Method::POST,
                Method::PUT,
                Method::PATCH,
                Method::DELETE,
            ])
            .allow_headers([header::CONTENT_TYPE, header::ACCEPT, header::AUTHORIZATION])
            .expose_headers([
                request_id.clone(),
                header::RETRY_AFTER,
                render::IMAGE_WIDTH,
                render::IMAGE_HEIGHT,
                render::SERVER_TIMING,
            ])
    });
    let timeout = cfg.handler_timeout() + Duration::from_secs(1);
    let routes = routes.layer(
        ServiceBuilder::new()
            .layer(HandleErrorLayer::new({
                let metrics = state.metrics.clone();
                move |err| layer_error(metrics.clone(), err)
            }))
            .timeout(timeout),
    );
    let routes = match cors {
        Some(c) => routes.layer(c),
        None => routes,
    };
    let failures = state.clone();
    routes
        .layer(PropagateRequestIdLayer::new(request_id.clone()))
        .layer(
            TraceLayer::new_for_http()
                .make_span_with(|req: &axum::http::Request<_>| {
                    let id = req
                        .headers()
                        .get("x-request-id")
                        .and_then(|v| v.to_str().ok())
                        .unwrap_or("-");
                    tracing::info_span!("request", id = %id, method = %req.method(), uri = %req.uri())
                })
                .on_failure(
                    move |class: ServerErrorsFailureClass, latency: Duration, span: &tracing::Span| {
                        log_failure(&failures, class, latency, span)
                    },
                ),
        )
        .layer(SetRequestIdLayer::new(request_id, Counter::default()))
        .with_state(state)
}

/// A future that resolves on SIGINT (Ctrl-C) or SIGTERM.
pub async fn shutdown_signal() {
    let ctrl_c = async {
        if let Err(e) = tokio::signal::ctrl_c().await {
            tracing::error!(error = %e, "cannot listen for Ctrl-C");
            std::future::pending::<()>().await;
        }
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(e) => {
                tracing::error!(error = %e, "cannot listen for SIGTERM");
                std::future::pending::<()>().await;
            }
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        () = ctrl_c => {},
        () = term => {},
    }
    tracing::info!("shutdown requested: finishing requests in flight");
}

/// Serves until `shutdown` resolves: loads stored rigs in the background (not ready until
/// done), then on shutdown stops accepting, lets requests in flight complete, drains the
/// batcher and returns.
pub async fn run(
    listener: TcpListener,
    config: ServerConfig,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), ServerError> {
    let state = AppState::new(config)?;
    serve(listener, state, shutdown).await
}

/// Like [`run`] with a state built by the caller (tests inspect it afterwards).
pub async fn serve(
    listener: TcpListener,
    state: AppState,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), ServerError> {
    if let Ok(addr) = listener.local_addr() {
        tracing::info!(%addr, "listening");
    }
    let loader = state.clone();
    tokio::spawn(async move { loader.load_stored().await });
    // Background LOD jobs are not requests in flight: stop them at once, or the runtime
    // would wait for their blocking work before the process can exit.
    let jobs = state.clone();
    let shutdown = async move {
        shutdown.await;
        jobs.lod_jobs.cancel_background();
    };
    let limits = conn::Limits {
        max_connections: state.config.connection_cap(),
        header_timeout: state.config.header_timeout,
        idle_timeout: state.config.idle_timeout,
    };
    let serving = conn::serve_connections(
        listener,
        app(state.clone()),
        state.metrics.clone(),
        limits,
        shutdown,
    );
    let summaries = async {
        let mut every = tokio::time::interval(SHED_LOG_EVERY);
        loop {
            every.tick().await;
            state.shed_log.flush();
        }
    };
    tokio::select! {
        () = serving => {}
        _ = summaries => {}
    }
    state.sessions.close_all("the server is stopping");
    state.loadtests.cancel_all();
    state.scheduler.shutdown().await;
    tracing::info!("stopped");
    Ok(())
}
