//! The server's state: everything a handler needs, built once ([`AppState::new`]) and shared
//! by every request. It is the composition root: it holds the engine, the batcher, the
//! registry, the budgets and each resource's state, and imports no handler.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

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
use super::services::render::Rendering;
use super::services::tick::Ticking;
use super::sessions::Sessions;
use super::shed::ShedLog;
use super::topologies::RenderState;
use crowdmorph_core::budget::{Budget, MemoryPool};
use crowdmorph_core::rig::RigShape;
use crowdmorph_engine::Engine;
use crowdmorph_store::objects::{LodClaim, Misses, SharedStore, Unusable};
use crowdmorph_store::{
    Record, Store, StoreError, StoredBuiltin, StoredClips, StoredRig, geometry_fingerprint,
};

/// How long one operation on the shared store may take, retries included, before it is
/// reported unavailable.
const STORE_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(5);

/// Shared state of every handler.
#[derive(Clone, Debug)]
pub struct AppState(pub(crate) Arc<Inner>);

/// Most entries `/readyz` lists as skipped (the oldest go first).
const MAX_SKIPPED: usize = 256;

/// A stored file or generation that was not used, and why.
#[derive(Debug, PartialEq, Eq)]
pub(crate) struct Skipped {
    /// The rig it is about, when known: cleared once a later generation of it is held.
    pub(crate) rig: Option<String>,
    /// The generation it is about (0 in the data dir: any later write supersedes it).
    pub(crate) generation: u64,
    /// The report.
    pub(crate) why: String,
}

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
    /// The rig store shared with other replicas (`--store`), in place of the data dir.
    pub(crate) shared: Option<Arc<SharedStore>>,
    /// Rig ids the shared store did not have when last asked.
    pub(crate) store_misses: Misses,
    /// Generations of the shared store that could not be used (each reported once).
    pub(crate) store_unusable: Unusable,
    /// Other replicas' LOD claims as last seen, with when their heartbeat last moved.
    pub(crate) lod_claims_seen: Mutex<std::collections::HashMap<String, (LodClaim, Instant)>>,
    /// This replica's LOD claim heartbeat.
    pub(crate) lod_beat: std::sync::atomic::AtomicU64,
    pub(crate) ready: AtomicBool,
    pub(crate) load_started: AtomicBool,
    /// What `/readyz` reports as skipped, each until what it is about is superseded.
    pub(crate) skipped: Mutex<Vec<Skipped>>,
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
        if let Some(s) = &self.shared {
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
            shared,
            store_misses: Default::default(),
            store_unusable: Default::default(),
            lod_claims_seen: Mutex::new(Default::default()),
            lod_beat: Default::default(),
            ready: AtomicBool::new(false),
            load_started: AtomicBool::new(false),
            skipped: Mutex::new(Vec::new()),
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
        if let Some(shared) = self.shared.clone() {
            self.load_shared(&shared).await;
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
        // Rigs that still have the import's quick order get the metric-based one. With a
        // shared store only the built-in rig (which no upload computes it for): a stored rig's
        // order is computed where it was uploaded, or, if that replica died first, by the one
        // that takes its claim over (`tend_lod`), and arrives as its next generation.
        for entry in self.registry.all() {
            if self.shared.is_none() || entry.builtin {
                self.start_auto_lod(&entry);
            }
        }
    }

    /// Reports `why` in `/readyz` for as long as the server runs.
    pub(crate) fn skip(&self, why: String) {
        self.push_skipped(Skipped {
            rig: None,
            generation: 0,
            why,
        });
    }

    /// Reports `why`, about generation `generation` of rig `id` (0 in the data dir), in
    /// `/readyz` until a later generation of the rig is held or the rig is deleted
    /// ([`AppState::clear_skipped`]).
    pub(crate) fn skip_rig(&self, id: &str, generation: u64, why: String) {
        self.push_skipped(Skipped {
            rig: Some(id.to_string()),
            generation,
            why,
        });
    }

    fn push_skipped(&self, entry: Skipped) {
        if let Ok(mut s) = self.skipped.lock()
            && !s.contains(&entry)
        {
            // A report per file or generation; a bound on what a flood of damage could add.
            if s.len() >= MAX_SKIPPED {
                s.remove(0);
            }
            s.push(entry);
        }
    }

    /// Forgets what was reported about generations of rig `id` before `below`: a newer one
    /// is held now, or the rig is gone.
    pub(crate) fn clear_skipped(&self, id: &str, below: u64) {
        if let Ok(mut s) = self.skipped.lock() {
            s.retain(|e| e.rig.as_deref() != Some(id) || e.generation >= below);
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
        self.engine.info().kind == crowdmorph_engine::BackendKind::Gpu
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
            // Reports about a rig's record are cleared when the rig is written or deleted.
            let rig = path
                .file_stem()
                .and_then(|s| s.to_str())
                .map(|s| s.split('@').next().unwrap_or(s).to_string());
            let skip = |why: String| match &rig {
                Some(id) => self.skip_rig(id, 0, why),
                None => self.skip(why),
            };
            if let Err(e) = budget.reserve(2 * size, || format!("stored record {file}")) {
                tracing::error!(error = %e, "skipping a stored rig that does not fit in memory");
                skip(e.to_string());
                continue;
            }
            let record = match Store::read_reporting(&path) {
                Ok((r, dropped)) => {
                    for why in dropped {
                        skip(why);
                    }
                    r
                }
                Err(e) => {
                    tracing::error!(error = %e, "skipping a stored rig that cannot be loaded");
                    skip(e.to_string());
                    continue;
                }
            };
            match self.load_record(record, &budget) {
                Ok(true) => n += 1,
                Ok(false) => {}
                Err(why) => skip(why),
            }
        }
        // Motion graphs come after the rigs they belong to; a graph file that does not parse
        // is skipped and reported, and graphs of a rig that is gone are left unused.
        let budget = Arc::new(Budget::new(
            self.pool.limit(),
            "--max-rig-memory",
            Some(self.pool.clone()),
        ));
        let (graphs, skipped) = store.load_graphs(|bytes, path| {
            budget
                .charge(bytes, || format!("stored graph file {}", path.display()))
                .map(drop)
                .map_err(|e| e.to_string())
        });
        for why in skipped {
            tracing::error!(error = %why, "skipping a stored graph file that cannot be read");
            self.skip(why);
        }
        for g in graphs {
            if self.registry.get(&g.rig).is_some() {
                self.graphs.load(g.rig, g.graphs);
            }
        }
        Ok(n)
    }

    /// Registers one stored record; `Ok(true)` for an uploaded rig, `Ok(false)` for the
    /// built-in rig's clips and LOD.
    fn load_record(&self, record: Record, budget: &Budget) -> Result<bool, String> {
        match record {
            Record::Rig(r) => self.load_rig(*r, budget).map(|()| true),
            Record::Clips(c) => self.load_clips(c, budget).map(|()| false),
            Record::Builtin(c) => self.load_builtin(c, budget).map(|()| false),
        }
    }

    /// Charges what preparing `rig` takes to the loading's budget.
    pub(crate) fn charge_preparing(
        &self,
        rig: &crowdmorph_core::rig::Rig,
        budget: &Budget,
    ) -> Result<(), String> {
        let c = RigShape::of(rig).cost(self.on_gpu());
        budget
            .charge(c.layout + c.transient, || {
                format!("preparing stored rig {:?}", rig.name)
            })
            .map_err(|e| e.to_string())
    }

    /// An uploaded rig's record: a new entry.
    fn load_rig(&self, r: StoredRig, budget: &Budget) -> Result<(), String> {
        if self.registry.get(&r.id).is_some() {
            return Err(format!("stored rig {:?} clashes with a built-in id", r.id));
        }
        let rig = Arc::new(r.rig);
        self.charge_preparing(&rig, budget)?;
        let prepared = self
            .engine
            .prepare(rig.clone())
            .map_err(|e| format!("stored rig {:?}: {e}", r.id))?;
        let charge = budget.keep(prepared.memory().host_bytes as u64);
        self.registry.insert(Arc::new(RigEntry::new(NewEntry {
            id: r.id,
            builtin: None,
            prepared,
            generation: self.registry.generation(),
            layout: ClipLayout::in_record(&rig.clips),
            charge,
            qbox: quantization_box(&rig),
        })));
        Ok(())
    }

    /// A clip file: a new generation of its rig with the clips appended.
    fn load_clips(&self, c: StoredClips, budget: &Budget) -> Result<(), String> {
        let Some(entry) = self.registry.get(&c.id) else {
            // The rig's record was deleted and the process stopped before its clip
            // files were: leftovers of a delete, not data anyone can reach.
            if let Some(store) = &self.store {
                tracing::warn!(rig = %c.id, seq = c.seq, "removing clips of a deleted rig");
                let _ = store.remove_clips(&c.id, c.seq);
            }
            return Ok(());
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
        self.charge_preparing(&rig, budget)?;
        let prepared = self
            .engine
            .update_clips(&entry.prepared, rig.clone())
            .map_err(|e| format!("clip file {} of rig {:?}: {e}", c.seq, c.id))?;
        let mut layout = entry.layout.clone();
        layout.files.push((c.seq, names));
        self.publish_successor(&entry, prepared, &rig, layout);
        Ok(())
    }

    /// Registers the next generation of `entry`: `rig` prepared, with its clips in `layout`.
    fn publish_successor(
        &self,
        entry: &RigEntry,
        prepared: crowdmorph_engine::PreparedRig,
        rig: &crowdmorph_core::rig::Rig,
        layout: ClipLayout,
    ) {
        self.registry.insert(Arc::new(entry.successor(
            prepared,
            quantization_box(rig),
            layout,
            self.registry.generation(),
            None,
        )));
    }

    /// The built-in rig's stored clips and LOD: a new generation of it.
    fn load_builtin(&self, c: StoredBuiltin, budget: &Budget) -> Result<(), String> {
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
        self.charge_preparing(&rig, budget)?;
        let prepared = if lod_changed {
            self.engine.prepare(rig.clone())
        } else {
            self.engine.update_clips(&entry.prepared, rig.clone())
        }
        .map_err(|e| format!("stored clips and LOD of {:?}: {e}", c.id))?;
        self.publish_successor(&entry, prepared, &rig, layout);
        Ok(())
    }

    /// Whether stored rigs have been loaded.
    pub fn is_ready(&self) -> bool {
        self.ready.load(Ordering::Acquire)
    }

    /// Files and generations skipped, with reasons, that nothing has superseded yet.
    pub fn skipped(&self) -> Vec<String> {
        self.skipped
            .lock()
            .map(|s| s.iter().map(|e| e.why.clone()).collect())
            .unwrap_or_default()
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
            self.renderer()
                .map(crowdmorph_engine::render::gpu::Renderer::memory),
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

    fn on_gpu(&self) -> bool {
        AppState::on_gpu(self)
    }
}

impl Ticking for AppState {
    fn sessions(&self) -> &Sessions {
        &self.sessions
    }

    fn scheduler(&self) -> &Scheduler {
        &self.scheduler
    }

    fn graphs(&self) -> &crate::graphs::Graphs {
        &self.graphs
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
