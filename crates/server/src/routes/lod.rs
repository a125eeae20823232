//! Level of detail on the server: `GET`/`PUT /v1/rigs/{id}/lod`. The builds themselves, the
//! background job's and a `PUT`'s, are [`crate::services::lod`]'s.
//!
//! A rig is usable the moment it is registered, with the import's quick delta-energy order
//! (`status: imported`); the job then scores the targets, simplifies the meshes and swaps in a
//! new generation of the rig (`status: ready`), persisted like any other change. The job works
//! on a snapshot and applies its result to whatever version of the rig is current, as long as
//! the geometry is the one it scored — LOD depends on geometry and targets, not on clips, so
//! clips uploaded meanwhile are kept. A `PUT` or a delete cancels a running job, and so does
//! shutdown; a `PUT` is itself a job, cancelled when its client goes away.

use std::sync::Arc;

use axum::extract::{Path, State};
use axum::http::StatusCode;
use crowdmorph_proto::LodRequest;

use crate::admission::{Decoded, Priced, names_bytes, names_reservation};
use crate::http::{Accept, Admin, ApiError, ApiResult, Ready};
use crate::lod_jobs::LodJob;
use crate::services::Parts;
use crate::services::lod::{apply, build, lod_info, rig_info};
use crate::state::AppState;
use crowdmorph_engine::lod::{LevelSpec, LodSpec, OrderMethod};

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
    accept.reply(StatusCode::OK, &lod_info(&state, &entry))
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
    let (lod, budget) = build(&state, rig.clone(), spec, &job).await?;
    let entry = apply(&state, &id, &rig, lod, &job, &budget).await?;
    // Done: the job is forgotten before the answer reports the rig's LOD status.
    drop(guard);
    tracing::info!(rig = %id, method = %entry.rig().lod.method, "LOD set");
    accept.reply(StatusCode::OK, &rig_info(&state, &entry))
}
