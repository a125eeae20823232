//! The server's state: everything a handler needs, built once ([`AppState::new`]) and shared
//! by every request. It is the composition root: it holds the engine, the batcher, the
//! registry, the budgets and each resource's state, and imports no handler.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use tokio::sync::Semaphore;

use super::ServerError;
use super::admission::{Admission, QueueMemory, RenderBudget};
use super::config::ServerConfig;
use super::http::{BodyLimits, Gate};
use super::json::JsonPool;
use super::loadtests::Loadtests;
use super::lod_jobs::LodJobs;
use super::metrics::{Gauges, Metrics};
use super::registry::{BUILTIN_ID, ClipLayout, NewEntry, Registry, RigEntry, quantization_box};
use super::scheduler::{BatchConfig, Scheduler};
use super::services::Parts;
use super::services::lod::{self, Building};
use super::services::persist::{self, Persisting};
use super::services::render::Rendering;
use super::services::replicas::{Replica, Replicating, load_shared};
use super::services::tick::Ticking;
use super::sessions::Sessions;
use super::shed::ShedLog;
use super::skipped::Skipped;
use super::topologies::RenderState;
use super::topologies::SharedTopologies;
use crowdmorph_core::budget::{Budget, MemoryPool};
use crowdmorph_engine::Engine;
use crowdmorph_engine::render::gpu::Renderer;
use crowdmorph_store::Store;
use crowdmorph_store::objects::SharedStore;

/// How long one operation on the shared store may take, retries included, before it is
/// reported unavailable.
const STORE_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(5);

/// Shared state of every handler.
#[derive(Clone, Debug)]
pub struct AppState(pub(crate) Arc<Inner>);

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
    /// Persistence, when a data dir is configured (and no shared store).
    pub store: Option<Store>,
    /// The rig store shared with other replicas (`--store`, in place of the data dir) and what
    /// this replica keeps of it.
    pub(crate) replica: Replica,
    pub(crate) ready: AtomicBool,
    pub(crate) load_started: AtomicBool,
    /// What `/readyz` reports as skipped, each until what it is about is superseded.
    pub(crate) skipped: Skipped,
    /// Serializes rig and clip changes (and their writes to disk).
    pub(crate) admin: tokio::sync::Mutex<()>,
    /// Host memory of rigs and of the work that makes them (`--max-rig-memory`).
    pub pool: Arc<MemoryPool>,
    /// Output and request memory admitted requests hold (`--queue-memory-bytes`).
    pub queue_memory: QueueMemory,
    /// Imports run at most two at a time (each may hold up to `max_upload_memory`); the
    /// permit is taken before the body is read.
    pub(crate) uploads: Semaphore,
    /// Requests being handled; past `max_concurrency` new ones are shed.
    pub(crate) inflight: Arc<Semaphore>,
    /// Background LOD computations by rig id.
    pub(crate) lod_jobs: LodJobs,
    /// LOD builds run at most two at a time: each keeps the rayon pool busy for seconds.
    pub(crate) lod_builds: Arc<Semaphore>,
    /// The rate-limited summary of shed and timed-out requests.
    pub(crate) shed_log: ShedLog,
    /// Pixels and estimated work that renders in flight hold (`--render-pixels`,
    /// `--render-work-ms`, `--viewer-render-share`).
    pub(crate) render_budget: RenderBudget,
    /// The renderer (or why there is none) and its topologies.
    pub(crate) render: RenderState,
    /// Crowd sessions by id.
    pub sessions: Sessions,
    /// Motion graphs by rig.
    pub graphs: crate::graphs::Graphs,
    /// Reused buffers of JSON crowd frames.
    pub(crate) json_pool: Arc<JsonPool>,
    /// `POST /v1/loadtest`: the load running and the last ones done.
    pub(crate) loadtests: Loadtests,
}

impl Drop for Inner {
    /// The state's owner is gone (the server stopped, a test ended): LOD builds still
    /// computing for it are cancelled rather than left running on the blocking pool, which
    /// would also hold up the runtime's shutdown; the shared store's staging files go.
    fn drop(&mut self) {
        self.lod_jobs.cancel_all();
        if let Some(s) = &self.replica.store {
            s.clean_up();
        }
    }
}

impl std::ops::Deref for AppState {
    type Target = Inner;
    fn deref(&self) -> &Inner {
        &self.0
    }
}

/// The renderer: never fails the start; without an adapter, render requests say why and
/// everything else works.
fn open_renderer(
    engine: &Arc<Engine>,
    config: &ServerConfig,
    gpu_options: crowdmorph_engine::gpu::GpuOptions,
) -> RenderState {
    let render = RenderState::new(crowdmorph_engine::render::crowd::RenderDevice::open_with(
        engine,
        config.render_backend,
        gpu_options,
    ));
    match &render.device {
        Ok(d) => tracing::info!(adapter = %d.name(), shared = d.shared, "renderer ready"),
        Err(why) => tracing::warn!(%why, "rendering unavailable"),
    }
    render
}

/// A registry with the embedded rig, which is always there: its memory is taken from the
/// pool unconditionally.
fn builtin_registry(engine: &Engine, pool: &Arc<MemoryPool>) -> Result<Registry, ServerError> {
    let registry = Registry::default();
    let builtin = Arc::new(crowdmorph_core::embedded::default_rig());
    let prepared = engine.prepare(builtin.clone())?;
    let charge =
        Budget::new(u64::MAX, "", Some(pool.clone())).keep(prepared.memory().host_bytes as u64);
    registry.insert(Arc::new(RigEntry::new(NewEntry {
        id: BUILTIN_ID.to_string(),
        builtin: Some(builtin.clips.len()),
        prepared,
        generation: registry.generation(),
        layout: ClipLayout::default(),
        charge,
        qbox: quantization_box(&builtin),
    })));
    Ok(registry)
}

impl AppState {
    /// Creates the engine, the batcher and the registry with the embedded rig. Stored rigs are
    /// loaded by [`AppState::load_stored`]; until then the server is not ready. Must be called
    /// inside a tokio runtime.
    pub fn new(config: ServerConfig) -> Result<AppState, ServerError> {
        let config_concurrency = config.max_concurrency;
        let gpu_options = crowdmorph_engine::gpu::GpuOptions {
            memory: config.gpu_memory,
            deltas: config.gpu_deltas,
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
        let render = open_renderer(&engine, &config, gpu_options);
        // A shared store replaces the data dir, which then only holds its staging files.
        let shared = match &config.store {
            Some(url) => Some(Arc::new(SharedStore::open(
                url,
                &config.data_dir.clone().unwrap_or_else(std::env::temp_dir),
                STORE_TIMEOUT,
                config.compress_clips,
            )?)),
            None => None,
        };
        let store = match (&config.data_dir, &shared) {
            (Some(dir), None) => Some(Store::open(dir)?.compress_clips(config.compress_clips)),
            _ => None,
        };
        // The session counters are registered with the server's registry before it is shared.
        let sessions = Sessions::default();
        let mut metrics = Metrics::default();
        sessions.metrics.register(metrics.registry_mut());
        let metrics = Arc::new(metrics);
        let scheduler = Scheduler::start(
            engine.clone(),
            metrics.clone(),
            BatchConfig {
                queue_requests: config.queue_requests,
                batch_cost: config.batch_cost(info.kind),
                batch_delay: config.batch_delay,
                hold_when_idle: config.batch_hold_when_idle,
            },
        );
        let render_budget = RenderBudget::new(
            config.render_pixels,
            config.render_work,
            config.viewer_render_share,
        );
        let queue_memory = QueueMemory::new(config.queue_memory_bytes, metrics.clone());
        let pool = MemoryPool::new(config.rig_memory(), "--max-rig-memory");
        let registry = builtin_registry(&engine, &pool)?;
        Ok(AppState(Arc::new(Inner {
            config,
            engine,
            registry,
            scheduler,
            metrics,
            store,
            replica: Replica {
                store: shared,
                ..Replica::default()
            },
            ready: AtomicBool::new(false),
            load_started: AtomicBool::new(false),
            skipped: Skipped::default(),
            admin: tokio::sync::Mutex::new(()),
            pool,
            queue_memory,
            uploads: Semaphore::new(2),
            inflight: Arc::new(Semaphore::new(
                config_concurrency.clamp(1, Semaphore::MAX_PERMITS),
            )),
            lod_jobs: LodJobs::default(),
            lod_builds: Arc::new(Semaphore::new(2)),
            shed_log: ShedLog::default(),
            render_budget,
            render,
            sessions,
            graphs: Default::default(),
            json_pool: Arc::default(),
            loadtests: Loadtests::default(),
        })))
    }

    /// Loads the rigs and clips stored under the data dir (skipping, with a logged reason,
    /// anything corrupt), then marks the server ready.
    /// Only the first call loads; later calls return at once.
    pub async fn load_stored(&self) {
        if self.load_started.swap(true, Ordering::AcqRel) {
            return;
        }
        if let Some(shared) = self.replica.store.clone() {
            load_shared(self, &shared).await;
        }
        if let Some(store_dir) = self.store.as_ref().map(|s| s.dir().to_path_buf()) {
            let state = self.clone();
            let loaded = tokio::task::spawn_blocking(move || persist::load_blocking(&state)).await;
            match loaded {
                Ok(Ok(n)) => {
                    tracing::info!(rigs = n, dir = %store_dir.display(), "stored rigs loaded")
                }
                Ok(Err(e)) => {
                    tracing::error!(error = %e, "cannot read the data directory");
                    self.skipped.skip(e.to_string());
                }
                Err(e) => {
                    tracing::error!(error = %e, "loading stored rigs failed");
                    self.skipped.skip(format!("loading failed: {e}"));
                }
            }
        }
        self.ready.store(true, Ordering::Release);
        // Rigs that still have the import's quick order get the metric-based one. With a
        // shared store only the built-in rig (which no upload computes it for): a stored rig's
        // order is computed where it was uploaded, or, if that replica died first, by the one
        // that takes its claim over (`tend_lod`), and arrives as its next generation.
        for entry in self.registry.all() {
            if self.replica.store.is_none() || entry.builtin {
                lod::start_auto_lod(self, &entry);
            }
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

    /// The status of load test `id` (running, or one of the last few done), as
    /// `GET /v1/loadtest/{id}` answers it.
    pub fn loadtest(&self, id: &str) -> Option<crate::loadtests::LoadtestStatus> {
        self.loadtests.find(id).map(|r| r.status())
    }

    /// The renderer, when the server has one (tests reach its race-window hook,
    /// [`Renderer::set_after_submit`], through it).
    #[doc(hidden)]
    pub fn renderer(&self) -> Option<&Renderer> {
        self.render.device.as_ref().ok().map(|d| &d.renderer)
    }

    /// Whether stored rigs have been loaded.
    pub fn is_ready(&self) -> bool {
        self.ready.load(Ordering::Acquire)
    }

    /// Files and generations skipped, with reasons, that nothing has superseded yet.
    pub fn skipped(&self) -> Vec<String> {
        self.skipped.list()
    }

    /// Current values of the gauges.
    pub fn gauges(&self) -> Gauges {
        let rigs = self.registry.all();
        let (host, device) = rigs.iter().fold((0u64, 0u64), |(h, d), e| {
            let m = e.prepared.memory();
            (h + m.host_bytes as u64, d + m.device_bytes as u64)
        });
        let (sessions, session_viewers) = self.sessions.counts();
        // The engine and the renderer may share one device, and then one budget.
        let mut gpu_pools: Vec<&Arc<MemoryPool>> = Vec::new();
        for p in [
            self.engine.gpu_memory(),
            self.renderer().map(Renderer::memory),
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
            queue_memory_bytes: self.queue_memory.used(),
            queue_memory_limit: self.queue_memory.limit(),
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
            gpu_fallbacks: self.engine.cpu_fallbacks(),
            sessions,
            session_viewers,
        }
    }
}

impl Gate for AppState {
    fn admin_token(&self) -> Option<&str> {
        self.config.admin_token.as_deref()
    }

    fn is_ready(&self) -> bool {
        AppState::is_ready(self)
    }
}

impl Admission for AppState {
    fn queue_memory(&self) -> &QueueMemory {
        &self.queue_memory
    }

    fn body_limits(&self) -> BodyLimits {
        BodyLimits {
            bytes: self.config.max_request_bytes,
            timeout: self.config.request_timeout,
        }
    }
}

impl Parts for AppState {
    type Owner = Inner;

    fn registry(&self) -> &Registry {
        &self.registry
    }

    fn engine(&self) -> &Arc<Engine> {
        &self.engine
    }

    fn metrics(&self) -> &Arc<Metrics> {
        &self.metrics
    }

    fn config(&self) -> &ServerConfig {
        &self.config
    }

    fn graphs(&self) -> &crate::graphs::Graphs {
        &self.graphs
    }

    fn downgrade(&self) -> std::sync::Weak<Inner> {
        Arc::downgrade(&self.0)
    }

    fn upgrade(weak: &std::sync::Weak<Inner>) -> Option<AppState> {
        weak.upgrade().map(AppState)
    }
}

impl Rendering for AppState {
    fn render_state(&self) -> &RenderState {
        &self.render
    }

    fn render_budget(&self) -> &RenderBudget {
        &self.render_budget
    }
}

impl Ticking for AppState {
    fn sessions(&self) -> &Sessions {
        &self.sessions
    }

    fn scheduler(&self) -> &Scheduler {
        &self.scheduler
    }
}

impl Replicating for AppState {
    fn replica(&self) -> &Replica {
        &self.replica
    }

    fn admin(&self) -> &tokio::sync::Mutex<()> {
        &self.admin
    }

    fn lod_jobs(&self) -> &LodJobs {
        &self.lod_jobs
    }

    fn pool(&self) -> &Arc<MemoryPool> {
        &self.pool
    }

    fn topologies(&self) -> &SharedTopologies {
        &self.render.topologies
    }

    fn skips(&self) -> &Skipped {
        &self.skipped
    }

    fn start_auto_lod(&self, entry: &RigEntry) {
        lod::start_auto_lod(self, entry);
    }
}

impl Persisting for AppState {
    fn store(&self) -> Option<&Store> {
        self.store.as_ref()
    }
}

impl Building for AppState {
    fn lod_builds(&self) -> &Arc<Semaphore> {
        &self.lod_builds
    }

    fn op_budget(&self) -> Arc<Budget> {
        AppState::op_budget(self)
    }
}

impl AppState {
    /// The limits of a rig or clip upload body.
    pub fn upload_limits(&self) -> BodyLimits {
        BodyLimits {
            bytes: self.config.max_upload_bytes,
            timeout: self.config.admin_timeout,
        }
    }
}
