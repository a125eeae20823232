//! Level of detail on the server: `GET`/`PUT /v1/rigs/{id}/lod`, and the background job that
//! orders every newly registered rig's blendshapes by the five metrics of Costigan et al. 2016
//! and builds its simplified mesh levels.
//!
//! A rig is usable the moment it is registered, with the import's quick delta-energy order
//! (`status: imported`); the job then scores the targets, simplifies the meshes and swaps in a
//! new generation of the rig (`status: ready`), persisted like any other change. The job works
//! on a snapshot and applies its result to whatever version of the rig is current, as long as
//! the geometry is the one it scored — LOD depends on geometry and targets, not on clips, so
//! clips uploaded meanwhile are kept. A `PUT` or a delete cancels a running job, and so does
//! shutdown; a `PUT` is itself a job, cancelled when its client goes away.

use std::sync::{Arc, Weak};

use axum::extract::{Path, State};
use axum::http::StatusCode;
use crowdmorph_proto::{LodInfo, LodRequest, RigInfo};

use super::rigs::prepare_charged;
use crate::admission::{Decoded, Priced, names_bytes, names_reservation};
use crate::http::{Accept, Admin, ApiError, ApiResult, Ready, blocking};
use crate::lod_jobs::LodJob;
use crate::registry::RigEntry;
use crate::state::{AppState, Inner};
use crowdmorph_core::budget::Budget;
use crowdmorph_core::rig::{Lod, Rig};
use crowdmorph_engine::lod::{LevelSpec, LodBuildError, LodSpec, OrderMethod, build_lod};

/// Mesh levels the background job builds, as fractions of the triangles (the 50, 25
/// and 10 %); with the default table, LOD levels 1, 2 and 3 use them, and level 4 (no shapes)
/// the coarsest.
pub const AUTO_MESH_FRACTIONS: [f32; 3] = [0.5, 0.25, 0.1];

/// A `PUT`'s job for as long as the request is served: dropping it (the handler finished, or
/// its future was dropped because the client went away or the request timed out) cancels the
/// build and forgets the job.
struct PutGuard {
    state: AppState,
    id: String,
    job: Arc<LodJob>,
}

impl Drop for PutGuard {
    fn drop(&mut self) {
        self.job.progress.cancel();
        self.state.lod_jobs.finish(&self.id, &self.job);
    }
}

impl AppState {
    /// What the API reports about a rig, with the LOD job's status overlaid.
    pub(crate) fn rig_info(&self, entry: &RigEntry) -> RigInfo {
        let mut info = entry.info();
        info.graphs = self.graphs.names(&entry.id);
        info.lod = self.lod_info(entry);
        info
    }

    fn lod_info(&self, entry: &RigEntry) -> LodInfo {
        let mut lod = entry.lod_info();
        if let Some(job) = self.lod_jobs.get(&entry.id) {
            match job.failed.lock().ok().and_then(|f| f.clone()) {
                Some(e) => {
                    lod.status = "failed".into();
                    lod.error = Some(e);
                }
                None => {
                    lod.status = "computing".into();
                    lod.progress = job.progress.fraction();
                }
            }
        }
        lod
    }

    /// Builds a LOD on the blocking pool once a build permit is free (builds are
    /// CPU-heavy and share the rayon pool with the CPU engine).
    async fn build(
        &self,
        rig: Arc<Rig>,
        spec: LodSpec,
        job: &Arc<LodJob>,
    ) -> Result<(Lod, Arc<Budget>), ApiError> {
        build_with(&Arc::downgrade(&self.0), rig, spec, job).await
    }

    /// Starts the background LOD job for a rig that still has the import's quick order.
    ///
    /// The job holds the server state only weakly: dropping the last handle to the state
    /// (the server stopping, a test ending) cancels it instead of leaving it computing.
    pub(crate) fn start_auto_lod(&self, entry: &RigEntry) {
        if !self.config.auto_lod()
            || entry.rig().lod.method != crowdmorph_core::rig::IMPORT_LOD_METHOD
        {
            return;
        }
        let rig = entry.prepared.rig().clone();
        // A rig without triangles (points only) has no mesh to simplify: order only.
        let has_triangles = rig.primitives.iter().any(|p| !p.indices.is_empty());
        let spec = LodSpec {
            mesh_fractions: if has_triangles {
                AUTO_MESH_FRACTIONS.to_vec()
            } else {
                Vec::new()
            },
            ..LodSpec::default()
        };
        let job = self.lod_jobs.start(&entry.id, true);
        let weak = Arc::downgrade(&self.0);
        let id = entry.id.clone();
        tokio::spawn(async move {
            // With a shared store the build is claimed first, so that other replicas leave it
            // to this one while its heartbeat (each refresh) goes on, and take it over if this
            // replica dies before the result is committed.
            if let Ok(state) = upgrade(&weak)
                && let Some(shared) = state.shared_store().cloned()
            {
                drop(state);
                if let Err(e) = shared.claim_lod(&id, 0, false).await {
                    tracing::warn!(rig = %id, error = %e, "cannot claim the LOD build in the store");
                }
            }
            let outcome = async {
                let (lod, budget) = build_with(&weak, rig.clone(), spec, &job).await?;
                let state = upgrade(&weak)?;
                apply(&state, &id, &rig, lod, &job, &budget).await
            }
            .await;
            let Ok(state) = upgrade(&weak) else {
                return;
            };
            match outcome {
                Ok(_) => {
                    tracing::info!(rig = %id, "metric-ordered LOD and mesh levels ready");
                    state.lod_jobs.finish(&id, &job);
                    // Its result is the rig's newest generation: nobody needs the claim.
                    if let Some(shared) = state.shared_store() {
                        shared.release_lod(&id).await;
                    }
                }
                Err(_) if job.progress.is_cancelled() => {
                    tracing::debug!(rig = %id, "background LOD cancelled");
                }
                Err(e) => {
                    tracing::warn!(rig = %id, error = %e.message, "background LOD failed; the rig keeps its import order");
                    if let Ok(mut f) = job.failed.lock() {
                        *f = Some(e.message.to_string());
                    }
                }
            }
        });
    }
}

/// The state, if it still exists.
fn upgrade(weak: &Weak<Inner>) -> Result<AppState, ApiError> {
    weak.upgrade()
        .map(AppState)
        .ok_or_else(|| ApiError::unavailable("shutting_down", "the server is stopping", 1))
}

/// [`AppState::build`] holding the state only while it takes a permit and reserves memory,
/// not during the seconds of computing.
async fn build_with(
    weak: &Weak<Inner>,
    rig: Arc<Rig>,
    spec: LodSpec,
    job: &Arc<LodJob>,
) -> Result<(Lod, Arc<Budget>), ApiError> {
    let (permit, budget, metrics) = {
        let state = upgrade(weak)?;
        let permit = state
            .lod_builds
            .clone()
            .acquire_owned()
            .await
            .map_err(|_| ApiError::unavailable("shutting_down", "the server is stopping", 1))?;
        // The build's working memory is reserved before it starts; the same budget then
        // pays for preparing the rig with its new levels.
        let budget = state.op_budget();
        let work = crowdmorph_engine::lod::build_bytes(&rig, &spec);
        budget
            .reserve(work, || format!("a LOD build of rig {:?}", rig.name))
            .map_err(|e| ApiError::budget(e, "lod_too_large"))?;
        (permit, budget, state.metrics.clone())
    };
    let progress = job.progress.clone();
    let running = Running::new(metrics.clone());
    let built = tokio::task::spawn_blocking(move || build_lod(&rig, &spec, None, Some(&progress)))
        .await
        .map_err(ApiError::internal);
    running.finish();
    drop(permit);
    let lod = built?.map_err(|e| match e {
        LodBuildError::Cancelled => {
            metrics.lod_builds_cancelled.inc();
            cancelled()
        }
        e => ApiError::bad_request("invalid_lod", e.to_string()),
    })?;
    Ok((lod, budget))
}

/// A LOD build in progress, for the metrics: counted running while it lives, and — if the
/// request future awaiting it is dropped first (the client of a `PUT` hung up; the guard
/// cancels the build itself) — counted cancelled, since nobody will see its result.
struct Running {
    metrics: Arc<crate::metrics::Metrics>,
    finished: bool,
}

impl Running {
    fn new(metrics: Arc<crate::metrics::Metrics>) -> Running {
        metrics.lod_builds_running.inc();
        Running {
            metrics,
            finished: false,
        }
    }

    fn finish(mut self) {
        self.finished = true;
    }
}

impl Drop for Running {
    fn drop(&mut self) {
        self.metrics.lod_builds_running.dec();
        if !self.finished {
            self.metrics.lod_builds_cancelled.inc();
            self.metrics
                .cancelled("lod", crowdmorph_core::cancel::Cancelled::Dropped);
        }
    }
}

fn cancelled() -> ApiError {
    ApiError::new(
        StatusCode::CONFLICT,
        "lod_cancelled",
        "the LOD computation was cancelled by a newer PUT or a delete of the rig",
    )
}

/// Swaps in a new generation of rig `id` with `lod`, if its geometry is still the one `scored`
/// had and `job` was not cancelled meanwhile. The new rig is prepared for the engine first,
/// then persisted, then made current: what is on disk always loads, and what is served is
/// always on disk.
async fn apply(
    state: &AppState,
    id: &str,
    scored: &Arc<Rig>,
    lod: Lod,
    job: &Arc<LodJob>,
    budget: &Arc<Budget>,
) -> Result<Arc<RigEntry>, ApiError> {
    let _admin = state.admin.lock().await;
    // Checked under the admin lock, which a PUT's apply and a delete also take: a job that
    // was cancelled before this point never overwrites their result.
    if job.progress.is_cancelled() {
        return Err(cancelled());
    }
    let entry = state.registry.get(id).ok_or_else(|| {
        ApiError::not_found(
            "unknown_rig",
            format!("rig {id:?} was deleted while its LOD was computed"),
        )
    })?;
    let current = entry.prepared.rig().clone();
    let scored = scored.clone();
    let engine = state.engine.clone();
    let gpu = state.on_gpu();
    let b = budget.clone();
    let rid = id.to_string();
    // Comparing and cloning a big rig, validating and preparing it are CPU work: off the
    // async threads.
    let prepared = blocking(move || {
        if !Arc::ptr_eq(&current, &scored)
            && (current.primitives != scored.primitives || current.targets != scored.targets)
        {
            return Err(ApiError::new(
                StatusCode::CONFLICT,
                "rig_changed",
                format!("rig {rid:?} changed while its LOD was computed"),
            ));
        }
        let mut rig = (*current).clone();
        rig.lod = lod;
        rig.validate()
            .map_err(|e| ApiError::bad_request("invalid_lod", e.to_string()))?;
        prepare_charged(&engine, &b, Arc::new(rig), gpu)
    })
    .await?;
    // The new generation takes over the rig's charge, set to what it now holds (its mesh
    // levels included).
    state.next_generation(id, &entry, prepared).await
}

impl Priced for LodRequest {
    /// The lists it holds until they are capped against the rig: the names of the order and
    /// the pins, the table's levels, the mesh fractions.
    fn price(&self, _: Accept) -> u64 {
        self.order.as_ref().map_or(0, names_bytes)
            + names_bytes(&self.pinned)
            + self.levels.as_ref().map_or(0, |l| {
                l.capacity() as u64 * size_of::<crowdmorph_proto::LodLevelRequest>() as u64
            })
            + self.mesh_fractions.capacity() as u64 * 4
    }

    fn decoding(bincode: bool, len: u64) -> u64 {
        names_reservation(bincode, len)
    }
}

/// The build spec a `PUT` asks for (its lists moved, not copied).
fn spec_of(req: LodRequest) -> Result<LodSpec, ApiError> {
    let method = match &req.method {
        None => OrderMethod::Combined,
        Some(m) => OrderMethod::from_name(m).ok_or_else(|| {
            let names: Vec<&str> = OrderMethod::all().iter().map(|m| m.name()).collect();
            ApiError::bad_request(
                "invalid_lod",
                format!(
                    "unknown method {} (methods: {})",
                    crowdmorph_core::rig::quoted_name(m),
                    names.join(", ")
                ),
            )
        })?,
    };
    let spec = LodSpec {
        method,
        order: req.order,
        pinned: req.pinned,
        levels: req.levels.as_ref().map(|levels| {
            levels
                .iter()
                .map(|l| LevelSpec {
                    shapes: Some(l.shapes),
                    fraction: None,
                    mesh: l.mesh,
                })
                .collect()
        }),
        mesh_fractions: req.mesh_fractions,
        ..LodSpec::default()
    };
    spec.check()
        .map_err(|e| ApiError::bad_request("invalid_lod", e.to_string()))?;
    Ok(spec)
}

/// `GET /v1/rigs/{id}/lod`.
pub async fn get_lod(
    State(state): State<AppState>,
    _ready: Ready,
    accept: Accept,
    Path(id): Path<String>,
) -> ApiResult {
    let entry = state.rig(&id)?;
    accept.reply(StatusCode::OK, &state.lod_info(&entry))
}

/// `PUT /v1/rigs/{id}/lod`: rebuilds the order, table and mesh levels as asked, then answers
/// with the rig (its new generation is what later frames use).
pub async fn put_lod(
    State(state): State<AppState>,
    _admin: Admin,
    _ready: Ready,
    accept: Accept,
    Path(id): Path<String>,
    Decoded(req): Decoded<LodRequest>,
) -> ApiResult {
    let (req, decoded) = req.into_parts();
    let entry = state.rig(&id)?;
    // Neither list can name more channels than the rig has without naming one twice.
    let targets = entry.rig().targets.len();
    for (what, len) in [
        ("order", req.order.as_ref().map_or(0, Vec::len)),
        ("pinned", req.pinned.len()),
    ] {
        if len > targets {
            return Err(ApiError::bad_request(
                "invalid_lod",
                format!(
                    "{what} lists {len} names; rig {id:?} has {targets} targets, so at most \
                     {targets}"
                ),
            ));
        }
    }
    let spec = spec_of(req)?;
    // Names and table are checked against the rig before anything else: a bad request is
    // refused without a build, and without cancelling the job it would have replaced.
    // The check resolves names through an index of the rig's channels (one at a time), with
    // per channel a seen-flag (1 byte), a resolved id (4) and a kept pin (4): charged while it
    // runs.
    let checking = state
        .queue_memory
        .reserve(crowdmorph_core::rig::TargetIndex::bytes_for(targets) + 9 * targets as u64)?;
    crowdmorph_engine::lod::check_request(entry.rig(), &spec)
        .map_err(|e| ApiError::bad_request("invalid_lod", e.to_string()))?;
    drop(checking);
    // Checked: its lists are at most a rig's worth of names and 64 levels.
    drop(decoded);
    // The PUT replaces whatever was computing for this rig, and is itself replaced by a later
    // PUT or a delete; `guard` cancels it if this handler stops early.
    let job = state.lod_jobs.start(&id, false);
    let guard = PutGuard {
        state: state.clone(),
        id: id.clone(),
        job: job.clone(),
    };
    let rig = entry.prepared.rig().clone();
    let (lod, budget) = state.build(rig.clone(), spec, &job).await?;
    let entry = apply(&state, &id, &rig, lod, &job, &budget).await?;
    // Done: the job is forgotten before the answer reports the rig's LOD status.
    drop(guard);
    tracing::info!(rig = %id, method = %entry.rig().lod.method, "LOD set");
    accept.reply(StatusCode::OK, &state.rig_info(&entry))
}
