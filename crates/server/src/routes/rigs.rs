//! Rigs: `POST /v1/rigs` (a glTF/GLB imported within its budget, prepared, persisted, then
//! visible), `GET /v1/rigs[/{id}]`, `DELETE /v1/rigs/{id}` and `GET /v1/rigs/{id}/mesh`; and
//! what changing a rig takes, shared with clips and LOD: preparing within a budget, persisting.

use std::sync::Arc;

use axum::body::Body;
use axum::extract::{Path, State};
use axum::http::{HeaderMap, StatusCode};
use axum::response::IntoResponse;
use bytes::Bytes;
use crowdmorph_proto::{CONTENT_TYPE_JSON, RigList};

use crate::admission::resolve::unknown_rig;
use crate::http::{
    self, Accept, Admin, ApiError, ApiResult, Query, Ready, blocking, checked_content_type,
    read_body,
};
use crate::registry::{
    ClipLayout, NewEntry, RigEntry, check_output_range, clips_named, quantization_box, sanitize_id,
    valid_id,
};
use crate::state::AppState;
use crowdmorph_core::budget::{Budget, BudgetError};
use crowdmorph_core::rig::{Rig, RigShape, quoted_name};
use crowdmorph_import::gltf::GltfImport;
use crowdmorph_import::{ImportError, ImportOptions};
use crowdmorph_store::objects::{Change, SharedStore};
use crowdmorph_store::{RecordRef, Store, StoreError};

impl AppState {
    /// The error budget clips are stored within, when the store compresses them.
    pub fn clip_error(&self) -> Option<f32> {
        match &self.shared {
            Some(s) => s.clip_error(),
            None => self.store.as_ref().and_then(|s| s.clip_error()),
        }
    }

    /// Rig `id`, or 404 `unknown_rig` listing the rigs there are.
    pub fn rig(&self, id: &str) -> Result<Arc<RigEntry>, ApiError> {
        self.registry
            .get(id)
            .ok_or_else(|| unknown_rig(&self.registry, id))
    }

    /// Makes `rig` (prepared as `prepared`, same geometry and clips as `entry`'s generation)
    /// rig `id`'s next generation: stored first, then served; it takes over `entry`'s memory
    /// charge, set to what it now holds. The caller holds the admin lock.
    pub async fn next_generation(
        &self,
        id: &str,
        entry: &RigEntry,
        (rig, prepared): Prepared,
    ) -> Result<Arc<RigEntry>, ApiError> {
        self.persist_record(id, rig, entry.builtin, &entry.layout)
            .await?;
        let next = Arc::new(entry.successor(
            prepared,
            entry.qbox,
            entry.layout.clone(),
            self.registry.generation(),
            None,
        ));
        self.registry.insert(next.clone());
        Ok(next)
    }

    /// Persists a rig's record: its geometry and LOD with the clips `layout` keeps in the
    /// record (for the built-in rig: its extra clips and LOD).
    pub async fn persist_record(
        &self,
        id: &str,
        rig: Arc<Rig>,
        builtin: bool,
        layout: &ClipLayout,
    ) -> Result<(), ApiError> {
        if self.store.is_none() && self.shared.is_none() {
            return Ok(());
        }
        let state = self.clone();
        let rid = id.to_string();
        let names = layout.record.clone();
        let staged = blocking(move || {
            let id = rid;
            let clips = clips_named(&rig, &names);
            let record = if builtin {
                RecordRef::Builtin {
                    id: &id,
                    clips: &clips,
                    rig: &rig,
                }
            } else {
                RecordRef::Rig {
                    id: &id,
                    rig: &rig,
                    clips: &clips,
                }
            };
            match (&state.shared, &state.store) {
                (Some(shared), _) => shared.stage(record).map(Some).map_err(ApiError::internal),
                (None, Some(store)) => store.put(record).map(|()| None).map_err(ApiError::internal),
                (None, None) => Ok(None),
            }
        })
        .await?;
        if self.shared.is_none() {
            // The data dir's record of the rig is written anew: what was reported about the
            // one before is superseded.
            self.clear_skipped(id, u64::MAX);
        }
        self.commit_staged(id, staged).await
    }

    /// Commits a change staged for the shared store (none for the data dir, written already).
    async fn commit_staged(&self, id: &str, staged: Option<Change>) -> Result<(), ApiError> {
        match (&self.shared, staged) {
            (Some(shared), Some(change)) => self.commit_shared(shared, id, change).await,
            _ => Ok(()),
        }
    }

    /// Persists rig `id`'s motion graphs, all of them (none removes them).
    pub async fn persist_graphs(
        &self,
        id: &str,
        graphs: std::collections::BTreeMap<String, crowdmorph_proto::MotionGraph>,
    ) -> Result<(), ApiError> {
        if let Some(shared) = &self.shared {
            let change = SharedStore::graphs_change(id, &graphs).map_err(ApiError::internal)?;
            return self.commit_shared(shared, id, change).await;
        }
        let id = id.to_string();
        self.on_data_dir(move |st| st.put_graphs(&id, &graphs))
            .await
    }

    /// Removes rig `id` from the store: its record, clip files and graphs (a tombstone
    /// generation in a shared store).
    pub async fn persist_delete(&self, id: &str) -> Result<(), ApiError> {
        if let Some(shared) = &self.shared {
            self.commit_shared(shared, id, Change::Delete).await?;
            shared.release_lod(id).await;
            return Ok(());
        }
        self.clear_skipped(id, u64::MAX);
        let id = id.to_string();
        self.on_data_dir(move |st| st.remove(&id)).await
    }

    /// Runs `f` on the data dir's store on a blocking thread; nothing without one.
    async fn on_data_dir(
        &self,
        f: impl FnOnce(&Store) -> Result<(), StoreError> + Send + 'static,
    ) -> Result<(), ApiError> {
        if self.store.is_none() {
            return Ok(());
        }
        let state = self.clone();
        blocking(move || {
            state
                .store
                .as_ref()
                .map_or(Ok(()), f)
                .map_err(ApiError::internal)
        })
        .await
    }

    /// Persists clip file `seq` of `rig` with `clips`, or deletes it when there are none.
    pub async fn persist_clips(
        &self,
        id: &str,
        seq: u64,
        rig: Arc<Rig>,
        clips: Vec<crowdmorph_core::rig::Clip>,
    ) -> Result<(), ApiError> {
        if self.store.is_none() && self.shared.is_none() {
            return Ok(());
        }
        let state = self.clone();
        let rid = id.to_string();
        let staged = blocking(move || {
            let id = rid;
            let record = RecordRef::Clips {
                id: &id,
                seq,
                clips: &clips,
                rig: &rig,
            };
            match (&state.shared, &state.store) {
                (Some(_), _) if clips.is_empty() => Ok(Some(SharedStore::clips_removed(&id, seq))),
                (Some(shared), _) => shared.stage(record).map(Some).map_err(ApiError::internal),
                (None, Some(store)) if clips.is_empty() => store
                    .remove_clips(&id, seq)
                    .map(|()| None)
                    .map_err(ApiError::internal),
                (None, Some(store)) => store.put(record).map(|()| None).map_err(ApiError::internal),
                (None, None) => Ok(None),
            }
        })
        .await?;
        self.commit_staged(id, staged).await
    }
}

/// Puts arriving clips into the form a compressing store keeps (`serve --compress-clips`):
/// the server then plays the clip its record decodes to, before and after a restart. Each
/// decoded table is charged to the upload's budget before it is made.
pub fn stored_form(
    rig: &Rig,
    clips: &mut [crowdmorph_core::rig::Clip],
    max_error: Option<f32>,
    budget: &Budget,
) -> Result<(), ApiError> {
    let Some(e) = max_error else {
        return Ok(());
    };
    for clip in clips {
        let bytes = clip.weights.len() as u64 * 4;
        budget
            .charge(bytes, || format!("compressing clip {:?}", clip.name))
            .map_err(|e| ApiError::budget(e, "clip_too_large"))?;
        let (_, decoded) =
            crowdmorph_anim::compress::stored_form(rig, clip, e).map_err(ApiError::internal)?;
        *clip = decoded;
    }
    Ok(())
}

/// Reads a rig or clip upload: the upload size limit, the admin timeout. The body is charged
/// to the upload's budget before it is read (its Content-Length, else the most an upload may
/// send).
pub async fn upload_body(
    state: &AppState,
    headers: &HeaderMap,
    body: Body,
    budget: &Budget,
) -> Result<Bytes, ApiError> {
    let limits = state.upload_limits();
    let declared = http::body::declared_length(headers, limits.bytes);
    budget
        .charge(declared, || format!("an upload body of {declared} bytes"))
        .map_err(|e| ApiError::budget(e, "upload_too_large"))?;
    read_body(headers, body, limits).await
}

/// A rig the engine could not prepare: over the GPU memory budget, answered as the host
/// budget answers (413 `too_large`, 503 `memory_full`, naming `--max-gpu-memory`); anything
/// else the device cannot hold, 422 `cannot_prepare`.
pub fn prepare_error(e: crowdmorph_engine::EngineError, too_large: &'static str) -> ApiError {
    match e {
        crowdmorph_engine::EngineError::GpuMemory(b) => ApiError::budget(b, too_large),
        e => ApiError::new(
            StatusCode::UNPROCESSABLE_ENTITY,
            "cannot_prepare",
            e.to_string(),
        ),
    }
}

/// Errors of a clip import: like a rig's, with the clip's code for a clip too large.
pub fn clip_import_error(e: ImportError) -> ApiError {
    match e {
        ImportError::Budget(b) => ApiError::budget(b, "clip_too_large"),
        e => import_error(e),
    }
}

pub fn import_error(e: ImportError) -> ApiError {
    match e {
        ImportError::Budget(b) => ApiError::budget(b, "rig_too_large"),
        ImportError::UnknownTargets(_) => ApiError::bad_request(
            "unknown_targets",
            format!("{e}; add ?ignore_unknown=true to import the rest and report these"),
        ),
        ImportError::ClipSource(_) | ImportError::Clip(_) => {
            ApiError::bad_request("invalid_clip", e.to_string())
        }
        _ => ApiError::bad_request("invalid_rig", e.to_string()),
    }
}

/// A rig and its preparation for the engine.
pub type Prepared = (Arc<Rig>, crowdmorph_engine::PreparedRig);

/// Prepares `rig` for the engine after charging what that adds (the CPU layout and, on a GPU,
/// the upload's staging copies, or the stored record, whichever is larger) to `budget`.
pub fn prepare_charged(
    engine: &crowdmorph_engine::Engine,
    budget: &Budget,
    rig: Arc<Rig>,
    gpu: bool,
) -> Result<Prepared, ApiError> {
    let cost = RigShape::of(&rig).cost(gpu);
    // A rig whose resident GPU copy alone exceeds the GPU memory budget is refused up front,
    // as one over the host budget is; one that does not fit next to the rigs already there is
    // refused by the engine's charges (503, or 413 for one buffer over the whole budget).
    if let Some(pool) = engine.gpu_memory().filter(|_| gpu)
        && cost.device > pool.limit()
    {
        return Err(ApiError::budget(
            BudgetError::TooLarge {
                what: format!(
                    "a rig of {} vertices and {} targets on the GPU",
                    rig.vertex_count(),
                    rig.targets.len()
                ),
                needed: cost.device,
                limit: pool.limit(),
                flag: crowdmorph_engine::gpu::GPU_MEMORY_FLAG,
            },
            "rig_too_large",
        ));
    }
    budget
        .charge(cost.layout + cost.transient, || {
            format!("preparing a rig of {} vertices", rig.vertex_count())
        })
        .map_err(|e| ApiError::budget(e, "rig_too_large"))?;
    let prepared = engine
        .prepare(rig.clone())
        .map_err(|e| prepare_error(e, "rig_too_large"))?;
    Ok((rig, prepared))
}

#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RigQuery {
    name: Option<String>,
}

/// `POST /v1/rigs`: check the name and type, read the body under the upload's budget,
/// import and prepare it on a blocking thread (charged from the file's headers before any
/// decoding), then store and publish it under the lock that serializes rig changes.
pub async fn upload_rig(
    State(state): State<AppState>,
    _admin: Admin,
    _ready: Ready,
    Query(query): Query<RigQuery>,
    headers: HeaderMap,
    body: Body,
) -> ApiResult {
    query.check()?;
    rig_content_type(&headers)?;
    // One of two upload slots before the body is read: each upload may hold up to
    // `--max-upload-memory`, its body included.
    let _slot = state.uploads.acquire().await.map_err(ApiError::internal)?;
    let budget = state.op_budget();
    let bytes = upload_body(&state, &headers, body, &budget).await?;
    let options = ImportOptions {
        base_dir: None,
        name: query.name.clone(),
        budget: Some(budget.clone()),
        ..ImportOptions::default()
    };
    let engine = state.engine.clone();
    let gpu = state.on_gpu();
    let b = budget.clone();
    let clip_error = state.clip_error();
    let (rig, prepared, qbox) =
        blocking(move || import_rig(&engine, &b, bytes, &options, gpu, clip_error)).await?;
    let id = query.name.unwrap_or_else(|| sanitize_id(&rig.name));
    if rig.clips.len() > state.config.max_clips {
        return Err(ApiError::new(
            StatusCode::PAYLOAD_TOO_LARGE,
            "too_many_clips",
            format!(
                "the file has {} animations, more than --max-clips ({}) a rig may have",
                rig.clips.len(),
                state.config.max_clips
            ),
        ));
    }
    let _admin = state.admin.lock().await;
    if state.registry.get(&id).is_some() {
        return Err(ApiError::new(
            StatusCode::CONFLICT,
            "rig_exists",
            format!(
                "a rig {id:?} exists already; DELETE /v1/rigs/{id} first or choose another ?name="
            ),
        ));
    }
    // On disk before it is visible: a crash after this point loses nothing acknowledged.
    let layout = ClipLayout::in_record(&rig.clips);
    state
        .persist_record(&id, rig.clone(), false, &layout)
        .await?;
    let charge = budget.keep(prepared.memory().host_bytes as u64);
    let entry = Arc::new(RigEntry::new(NewEntry {
        id: id.clone(),
        builtin: None,
        prepared,
        generation: state.registry.generation(),
        layout,
        charge,
        qbox,
    }));
    state.registry.insert(entry.clone());
    drop(budget);
    crowdmorph_core::budget::return_freed_memory();
    tracing::info!(rig = %id, vertices = entry.vertices, channels = rig.targets.len(), "rig registered");
    state.start_auto_lod(&entry);
    Accept::of(&headers).reply(StatusCode::CREATED, &state.rig_info(&entry))
}

impl RigQuery {
    /// A 400 for a malformed `?name=`, before any of the body is read.
    fn check(&self) -> Result<(), ApiError> {
        check_name("rig", self.name.as_deref())
    }
}

/// A 400 `invalid_name` unless `name` (of a rig or clip) is a valid id.
pub fn check_name(what: &str, name: Option<&str>) -> Result<(), ApiError> {
    match name {
        Some(n) if !valid_id(n) => Err(ApiError::bad_request(
            "invalid_name",
            format!(
                "{what} name {} must be 1-64 characters of A-Z a-z 0-9 . _ - (not starting \
                 with a dot)",
                quoted_name(n)
            ),
        )),
        _ => Ok(()),
    }
}

/// A 415 unless the body is a glTF file.
fn rig_content_type(headers: &HeaderMap) -> Result<(), ApiError> {
    let rig_types = "model/gltf-binary (a GLB), model/gltf+json (a glTF with embedded buffers) \
                     or application/octet-stream";
    let ct = checked_content_type(headers, rig_types)?;
    if [
        "model/gltf-binary",
        "model/gltf+json",
        "application/octet-stream",
        CONTENT_TYPE_JSON,
    ]
    .contains(&ct.as_str())
    {
        return Ok(());
    }
    Err(ApiError::new(
        StatusCode::UNSUPPORTED_MEDIA_TYPE,
        "unsupported_media_type",
        format!("a rig upload is {rig_types}, not {ct:?}"),
    ))
}

/// Imports and prepares an uploaded file. Everything the upload will hold is charged from the
/// file's headers, before any decoding: the rig's arrays (every target counted dense), the
/// largest transient decode, the engine's layouts and the stored record.
fn import_rig(
    engine: &crowdmorph_engine::Engine,
    budget: &Budget,
    bytes: Bytes,
    options: &ImportOptions,
    gpu: bool,
    clip_error: Option<f32>,
) -> Result<
    (
        Arc<Rig>,
        crowdmorph_engine::PreparedRig,
        crowdmorph_proto::Quantization,
    ),
    ApiError,
> {
    let import = GltfImport::open(&bytes, options).map_err(import_error)?;
    let estimate = import.shape().cost(gpu);
    let need = budget.used() + import.import_bytes() + estimate.layout + estimate.transient;
    let shape = import.shape();
    budget
        .reserve(need, || {
            format!(
                "a rig of {} vertices, {} weight channels and {} clip table cells",
                shape.vertices(),
                shape.targets,
                shape.clip_cells
            )
        })
        .map_err(|e| ApiError::budget(e, "rig_too_large"))?;
    let mut rig = import.build(options).map_err(import_error)?;
    // The body is not needed past the build (which consumed the import that borrowed it):
    // gone before the engine's copies are made.
    drop(bytes);
    let mut clips = std::mem::take(&mut rig.clips);
    stored_form(&rig, &mut clips, clip_error, budget)?;
    rig.clips = clips;
    check_output_range(&rig).map_err(|m| ApiError::bad_request("invalid_rig", m))?;
    let (rig, prepared) = prepare_charged(engine, budget, Arc::new(rig), gpu)?;
    let qbox = quantization_box(&rig);
    Ok((rig, prepared, qbox))
}

pub async fn list_rigs(State(state): State<AppState>, _ready: Ready, accept: Accept) -> ApiResult {
    let rigs = state
        .registry
        .all()
        .iter()
        .map(|e| state.rig_info(e))
        .collect();
    accept.reply(StatusCode::OK, &RigList { rigs })
}

pub async fn get_rig(
    State(state): State<AppState>,
    _ready: Ready,
    Path(id): Path<String>,
    accept: Accept,
) -> ApiResult {
    accept.reply(StatusCode::OK, &state.rig_info(&*state.rig(&id)?))
}

pub async fn delete_rig(
    State(state): State<AppState>,
    _admin: Admin,
    _ready: Ready,
    Path(id): Path<String>,
) -> ApiResult {
    let _admin = state.admin.lock().await;
    let entry = state.rig(&id)?;
    if entry.builtin {
        return Err(ApiError::new(
            StatusCode::FORBIDDEN,
            "builtin_rig",
            format!("rig {id:?} is built in and cannot be deleted"),
        ));
    }
    state.persist_delete(&id).await?;
    state.forget_rig(&id);
    drop(entry);
    // The rig's memory is freed when the last request using it is done; hand what is free
    // now back to the OS, so that deleting a large rig lowers the resident size.
    crowdmorph_core::budget::return_freed_memory();
    tracing::info!(rig = %id, "rig deleted");
    Ok(StatusCode::NO_CONTENT.into_response())
}

#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MeshQuery {
    /// LOD level whose (possibly simplified) mesh to return; default 0, the full mesh.
    lod: Option<u32>,
}

pub async fn get_mesh(
    State(state): State<AppState>,
    _ready: Ready,
    Path(id): Path<String>,
    Query(query): Query<MeshQuery>,
    accept: Accept,
) -> ApiResult {
    let entry = state.rig(&id)?;
    let lod = query.lod.unwrap_or(0);
    let levels = entry.rig().lod.levels.len();
    if lod as usize >= levels {
        return Err(ApiError::bad_request(
            "lod_out_of_range",
            format!("LOD level {lod} out of range (rig {id:?} has {levels} levels)"),
        ));
    }
    // The response copies the level's positions, normals and indices (and JSON triples them
    // in base64 and digits): charged to the queue memory until it is sent.
    let at = entry.prepared.at_level(lod).rig();
    let bytes = (at.vertex_count() * 24 + at.triangle_count() * 12) as u64;
    let factor = if accept.bincode { 2 } else { 4 };
    let held = state.queue_memory.reserve(bytes * factor)?;
    // Built and encoded off the runtime; the charge goes with the body until it is sent.
    let response = blocking(move || accept.reply(StatusCode::OK, &entry.mesh(lod))).await?;
    Ok(http::body::hold(response, held))
}
