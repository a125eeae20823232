//! The background LOD job: every newly registered rig's blendshapes ordered by the five metrics
//! of Costigan et al. 2016 and its simplified mesh levels built, then swapped in as the rig's
//! next generation (persisted like any other change); and a `PUT`'s build, which is the same
//! work. The job works on a snapshot and applies its result to whatever version of the rig is
//! current, as long as the geometry is the one it scored. It holds the server only weakly, so
//! the server stopping cancels it.

use std::sync::{Arc, Weak};

use axum::http::StatusCode;
use crowdmorph_proto::{LodInfo, RigInfo};
use tokio::sync::Semaphore;

use super::persist::{Persisting, next_generation, prepare_charged};
use crate::http::{ApiError, blocking};
use crate::lod_jobs::LodJob;
use crate::registry::RigEntry;
use crowdmorph_core::budget::Budget;
use crowdmorph_core::rig::{Lod, Rig};
use crowdmorph_engine::lod::{LodBuildError, LodSpec, build_lod};

/// What a LOD build needs beside persistence: the build permits and a budget per build.
pub trait Building: Persisting {
    /// LOD builds run at most two at a time: each keeps the rayon pool busy for seconds.
    fn lod_builds(&self) -> &Arc<Semaphore>;
    /// A budget for one build: `--max-upload-memory`, drawing from the rig memory pool.
    fn op_budget(&self) -> Arc<Budget>;
}

/// Mesh levels the background job builds, as fractions of the triangles (the 50, 25
/// and 10 %); with the default table, LOD levels 1, 2 and 3 use them, and level 4 (no shapes)
/// the coarsest.
pub const AUTO_MESH_FRACTIONS: [f32; 3] = [0.5, 0.25, 0.1];

/// What the API reports about a rig, with the LOD job's status overlaid.
pub fn rig_info<S: Building>(state: &S, entry: &RigEntry) -> RigInfo {
    let mut info = entry.info();
    info.graphs = state.graphs().names(&entry.id);
    info.lod = lod_info(state, entry);
    info
}

pub fn lod_info<S: Building>(state: &S, entry: &RigEntry) -> LodInfo {
    let mut lod = entry.lod_info();
    if let Some(job) = state.lod_jobs().get(&entry.id) {
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
pub async fn build<S: Building>(
    state: &S,
    rig: Arc<Rig>,
    spec: LodSpec,
    job: &Arc<LodJob>,
) -> Result<(Lod, Arc<Budget>), ApiError> {
    build_with::<S>(&state.downgrade(), rig, spec, job).await
}

/// Starts the background LOD job for a rig that still has the import's quick order.
///
/// The job holds the server state only weakly: dropping the last handle to the state
/// (the server stopping, a test ending) cancels it instead of leaving it computing.
pub fn start_auto_lod<S: Building>(state: &S, entry: &RigEntry) {
    if !state.config().auto_lod()
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
    let job = state.lod_jobs().start(&entry.id, true);
    let weak = state.downgrade();
    let id = entry.id.clone();
    tokio::spawn(async move {
        // With a shared store the build is claimed first, so that other replicas leave it
        // to this one while its heartbeat (each refresh) goes on, and take it over if this
        // replica dies before the result is committed.
        if let Ok(state) = upgrade::<S>(&weak)
            && let Some(shared) = state.shared_store().cloned()
        {
            drop(state);
            if let Err(e) = shared.claim_lod(&id, 0, false).await {
                tracing::warn!(rig = %id, error = %e, "cannot claim the LOD build in the store");
            }
        }
        let outcome = async {
            let (lod, budget) = build_with::<S>(&weak, rig.clone(), spec, &job).await?;
            let state = upgrade::<S>(&weak)?;
            apply(&state, &id, &rig, lod, &job, &budget).await
        }
        .await;
        let Ok(state) = upgrade::<S>(&weak) else {
            return;
        };
        match outcome {
            Ok(_) => {
                tracing::info!(rig = %id, "metric-ordered LOD and mesh levels ready");
                state.lod_jobs().finish(&id, &job);
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

/// The state, if it still exists.
fn upgrade<S: Building>(weak: &Weak<S::Owner>) -> Result<S, ApiError> {
    S::upgrade(weak)
        .ok_or_else(|| ApiError::unavailable("shutting_down", "the server is stopping", 1))
}

/// [`build`] holding the state only while it takes a permit and reserves memory,
/// not during the seconds of computing.
async fn build_with<S: Building>(
    weak: &Weak<S::Owner>,
    rig: Arc<Rig>,
    spec: LodSpec,
    job: &Arc<LodJob>,
) -> Result<(Lod, Arc<Budget>), ApiError> {
    let (permit, budget, metrics) = {
        let state = upgrade::<S>(weak)?;
        let permit = state
            .lod_builds()
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
        (permit, budget, state.metrics().clone())
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
pub async fn apply<S: Building>(
    state: &S,
    id: &str,
    scored: &Arc<Rig>,
    lod: Lod,
    job: &Arc<LodJob>,
    budget: &Arc<Budget>,
) -> Result<Arc<RigEntry>, ApiError> {
    let _admin = state.admin().lock().await;
    // Checked under the admin lock, which a PUT's apply and a delete also take: a job that
    // was cancelled before this point never overwrites their result.
    if job.progress.is_cancelled() {
        return Err(cancelled());
    }
    let entry = state.registry().get(id).ok_or_else(|| {
        ApiError::not_found(
            "unknown_rig",
            format!("rig {id:?} was deleted while its LOD was computed"),
        )
    })?;
    let current = entry.prepared.rig().clone();
    let scored = scored.clone();
    let engine = state.engine().clone();
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
    next_generation(state, id, &entry, prepared).await
}
