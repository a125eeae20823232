//! Rigs: `POST /v1/rigs` (a glTF/GLB imported within its budget, prepared, persisted, then
//! visible), `GET /v1/rigs[/{id}]`, `DELETE /v1/rigs/{id}` and `GET /v1/rigs/{id}/mesh`, and the import's phases
//! that clips share (the upload body, the import's errors). Preparing within a budget and
//! persisting are [`crate::services::persist`]'s.

use std::sync::Arc;

use axum::body::Body;
use axum::extract::{Path, State};
use axum::http::{HeaderMap, StatusCode, header};
use axum::response::IntoResponse;
use bytes::Bytes;
use crowdmorph_proto::{CONTENT_TYPE_JSON, RigList};

use crate::admission::mapping::to_wire;
use crate::http::{
    self, Accept, Admin, ApiError, ApiResult, Query, Ready, blocking, checked_content_type,
    read_body,
};
use crate::registry::{
    ClipLayout, NewEntry, RigEntry, check_output_range, quantization_box, sanitize_id, valid_id,
};
use crate::rig_maps::NamedMaps;
use crate::services::Parts;
use crate::services::lod::{rig_info, start_auto_lod};
use crate::services::persist::{
    clip_error, persist_delete, persist_maps, persist_record, prepare_charged,
};
use crate::services::replicas::forget_rig;
use crate::state::AppState;
use crowdmorph_core::budget::Budget;
use crowdmorph_core::rig::{NamedMapping, Rig, quoted_name};
use crowdmorph_import::gltf::GltfImport;
use crowdmorph_import::{ImportError, ImportOptions};

/// Tables the size of a clip's f32 weights that compressing it holds at once, at most: the
/// transform codec's coefficients in f64 (2), a candidate's quantized coefficients in i64 (2)
/// and its decoded table (1), beside the coded bytes (under 1); the curve codec holds less.
const ENCODER_TABLES: u64 = 6;

/// Puts arriving clips into the form a compressing store keeps (`serve --compress-clips`):
/// the server then plays the clip its record decodes to, before and after a restart. What
/// compressing a clip holds at once is charged to the upload's budget before it starts:
/// [`ENCODER_TABLES`] times the clip's f32 table.
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
        let bytes = clip.weights.len() as u64 * 4 * ENCODER_TABLES;
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
/// to the upload's budget before it is read: its Content-Length up front, or without one
/// (chunked) each piece before it is kept, so that a short or empty chunked upload is not
/// refused for what it might have sent.
pub async fn upload_body(
    state: &AppState,
    headers: &HeaderMap,
    body: Body,
    budget: &Budget,
) -> Result<Bytes, ApiError> {
    let limits = state.upload_limits();
    if headers.get(header::CONTENT_LENGTH).is_none() {
        // Chunked (or inflated): charged as it arrives, not for the most it could be.
        return http::body::read_body_charged(body, limits, budget, |e| {
            ApiError::budget(e, "upload_too_large")
        })
        .await;
    }
    let declared = http::body::declared_length(headers, limits.bytes);
    budget
        .charge(declared, || format!("an upload body of {declared} bytes"))
        .map_err(|e| ApiError::budget(e, "upload_too_large"))?;
    read_body(headers, body, limits).await
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
        ImportError::Image { .. } => ApiError::bad_request("invalid_image", e.to_string()),
        _ => ApiError::bad_request("invalid_rig", e.to_string()),
    }
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
        max_texture_size: state.config.max_texture_size,
        ..ImportOptions::default()
    };
    let engine = state.engine.clone();
    let gpu = state.on_gpu();
    let b = budget.clone();
    let clip_error = clip_error(&state);
    let (rig, prepared, qbox, vrm) =
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
    persist_record(&state, &id, rig.clone(), false, &layout).await?;
    // A VRM avatar's expressions: its `vrm` mapping, stored with the rig before it is served.
    let maps = vrm.map(|m| NamedMaps {
        mappings: Arc::new([("vrm".to_string(), to_wire(&m))].into_iter().collect()),
        ..NamedMaps::default()
    });
    if let Some(maps) = &maps {
        persist_maps(&state, &id, maps.clone()).await?;
    }
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
    state.registry.maps.set(&id, maps.unwrap_or_default());
    state.registry.insert(entry.clone());
    drop(budget);
    crowdmorph_core::budget::return_freed_memory();
    tracing::info!(rig = %id, vertices = entry.vertices, channels = rig.targets.len(), "rig registered");
    start_auto_lod(&state, &entry);
    Accept::of(&headers).reply(StatusCode::CREATED, &rig_info(&state, &entry))
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
        Option<NamedMapping>,
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
    let vrm = vrm_expressions(&bytes, budget, &mut rig)?;
    // The body is not needed past the build (which consumed the import that borrowed it):
    // gone before the engine's copies are made.
    drop(bytes);
    let mut clips = std::mem::take(&mut rig.clips);
    stored_form(&rig, &mut clips, clip_error, budget)?;
    rig.clips = clips;
    check_output_range(&rig).map_err(|m| ApiError::bad_request("invalid_rig", m))?;
    let (rig, prepared) = prepare_charged(engine, budget, Arc::new(rig), gpu)?;
    let qbox = quantization_box(&rig);
    Ok((rig, prepared, qbox, vrm))
}

/// A VRM file's expressions as its `vrm` mapping (`crowdmorph_import::vrm`); the document's
/// JSON parsed once more, its size charged three times first. Expressions that do not fit
/// the file (a bind to a missing morph target) leave the rig without the mapping and say so
/// in its import notes: the avatar itself is fine.
fn vrm_expressions(
    bytes: &[u8],
    budget: &Budget,
    rig: &mut Rig,
) -> Result<Option<NamedMapping>, ApiError> {
    let Some(json) = crowdmorph_import::vrm::gltf_json(bytes) else {
        return Ok(None);
    };
    // Only a document that names VRM is parsed again.
    if !json.windows(3).any(|w| w == b"VRM") {
        return Ok(None);
    }
    let held = 3 * json.len() as u64;
    budget
        .charge(held, || "the VRM expressions of the file".to_string())
        .map_err(|e| ApiError::budget(e, "rig_too_large"))?;
    let found = serde_json::from_slice::<serde_json::Value>(json)
        .map_err(|e| e.to_string())
        .and_then(|doc| crowdmorph_import::vrm::vrm_mapping(&doc).map_err(|e| e.to_string()));
    budget.release(held);
    match found {
        Ok(m) => Ok(m),
        Err(why) => {
            rig.import_notes
                .push(format!("VRM expressions not read: {why}"));
            Ok(None)
        }
    }
}

pub async fn list_rigs(State(state): State<AppState>, _ready: Ready, accept: Accept) -> ApiResult {
    let rigs = state
        .registry
        .all()
        .iter()
        .map(|e| rig_info(&state, e))
        .collect();
    accept.reply(StatusCode::OK, &RigList { rigs })
}

pub async fn get_rig(
    State(state): State<AppState>,
    _ready: Ready,
    Path(id): Path<String>,
    accept: Accept,
) -> ApiResult {
    accept.reply(StatusCode::OK, &rig_info(&state, &*state.rig(&id)?))
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
    persist_delete(&state, &id).await?;
    forget_rig(&state, &id);
    drop(entry);
    // The rig's memory is freed when the last request using it is done; hand what is free
    // now back to the OS, so that deleting a large rig lowers the resident size.
    crowdmorph_core::budget::return_freed_memory();
    tracing::info!(rig = %id, "rig deleted");
    Ok(StatusCode::NO_CONTENT.into_response())
}

/// `?lod=L` of a mesh or model request.
#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MeshQuery {
    /// LOD level whose (possibly simplified) mesh to return; default 0, the full mesh.
    lod: Option<u32>,
}

impl MeshQuery {
    /// The level asked for (default 0), a 400 `lod_out_of_range` past the rig's levels.
    pub fn level(&self, entry: &RigEntry, id: &str) -> Result<u32, ApiError> {
        let lod = self.lod.unwrap_or(0);
        let levels = entry.rig().lod.levels.len();
        if lod as usize >= levels {
            return Err(ApiError::bad_request(
                "lod_out_of_range",
                format!("LOD level {lod} out of range (rig {id:?} has {levels} levels)"),
            ));
        }
        Ok(lod)
    }
}

/// Bytes of one vertex in a mesh response: positions and normals (12 each), two texture
/// coordinate sets (8 each) and a colour (16).
const MESH_VERTEX_BYTES: usize = 12 + 12 + 8 + 8 + 16;

pub async fn get_mesh(
    State(state): State<AppState>,
    _ready: Ready,
    Path(id): Path<String>,
    Query(query): Query<MeshQuery>,
    accept: Accept,
) -> ApiResult {
    let entry = state.rig(&id)?;
    let lod = query.level(&entry, &id)?;
    // The response copies the level's positions, normals, both texture coordinate sets,
    // colours and indices (and JSON triples them in base64 and digits): charged to the queue
    // memory until sent.
    let at = entry.prepared.at_level(lod).rig();
    let bytes = (at.vertex_count() * MESH_VERTEX_BYTES + at.triangle_count() * 12) as u64;
    let factor = if accept.bincode { 2 } else { 4 };
    let held = state.queue_memory.reserve(bytes * factor)?;
    // Built and encoded off the runtime; the charge goes with the body until it is sent.
    let response = blocking(move || accept.reply(StatusCode::OK, &entry.mesh(lod))).await?;
    Ok(http::body::hold(response, held))
}
