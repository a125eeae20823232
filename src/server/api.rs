//! The HTTP handlers: health, metrics, rigs, clips, meshes and crowd frames.
//!
//! Every handler returns `Result<Response, ApiError>`, so every failure is a JSON error that
//! names the problem. Request bodies are read with explicit limits (413 past them); CPU-heavy
//! work (imports, engine preparation, persistence) runs on the blocking pool, and crowd frames
//! go through the batcher, so tokio workers only parse, route and encode.

use std::collections::HashMap;
use std::sync::Arc;
use std::time::Instant;

use axum::body::Body;
use axum::extract::{Path, Query, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use bytes::Bytes;
use crowdmorph_proto::{
    CONTENT_TYPE_BINCODE, CONTENT_TYPE_JSON, ClipList, ClipUpload, CrowdFrameRequest, Format,
    FrameTimings, Head, HeadBuffer, Readiness, RigList,
};
use http_body_util::BodyExt;
use serde::Serialize;
use serde::de::DeserializeOwned;
use tokio::sync::OwnedSemaphorePermit;

use super::metrics::Source;
use super::registry::{
    ClipLayout, RigEntry, check_output_range, clip_info, clip_infos, clips_named, quantization_box,
    sanitize_id, valid_id,
};
use super::scheduler::{JobRequest, Priority, ScheduleError};
use super::{ApiError, AppState};
use crate::budget::{Budget, BudgetError};
use crate::codec::{self, FrameBufferParts, FrameResponseEncoder};
use crate::import::clips::{ClipImport, ClipOptions};
use crate::import::gltf::GltfImport;
use crate::import::{ImportError, ImportOptions};
use crate::plan::{JobKey, Plan};
use crate::rig::quoted_name;
use crate::rig::{ACTIVE_WEIGHT_EPSILON, FrameMode, Rig, RigShape};
use crate::store::RecordRef;

pub(super) type ApiResult = Result<Response, ApiError>;

// ---------------------------------------------------------------------------------------------
// Plumbing: bodies, content negotiation, auth.

/// Reads a body of at most `limit` bytes; 413 past it (checked from Content-Length first, so an
/// oversized upload is refused before it is read).
async fn read_body(
    headers: &HeaderMap,
    body: Body,
    limit: usize,
    timeout: std::time::Duration,
) -> Result<Bytes, ApiError> {
    let too_large = || {
        ApiError::new(
            StatusCode::PAYLOAD_TOO_LARGE,
            "body_too_large",
            format!("request body is larger than the limit of {limit} bytes"),
        )
    };
    if let Some(len) = headers
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<u64>().ok())
        && len > limit as u64
    {
        return Err(too_large());
    }
    // A client that trickles its body holds a connection and a concurrency slot: it gets as
    // long as the request would be allowed to take, no more.
    let collected =
        tokio::time::timeout(timeout, http_body_util::Limited::new(body, limit).collect())
            .await
            .map_err(|_| {
                ApiError::new(
                    StatusCode::REQUEST_TIMEOUT,
                    "body_timeout",
                    format!(
                        "the request body did not arrive within {} s",
                        timeout.as_secs_f32()
                    ),
                )
            })?;
    match collected {
        Ok(c) => Ok(c.to_bytes()),
        Err(e) if e.is::<http_body_util::LengthLimitError>() => Err(too_large()),
        Err(e) => Err(ApiError::bad_request(
            "body_unreadable",
            format!("could not read the request body: {e}"),
        )),
    }
}

impl AppState {
    /// Reads a rig or clip upload: the upload size limit, the admin timeout. The body is
    /// charged to the upload's budget before it is read (its Content-Length, else the most
    /// an upload may send).
    pub(super) async fn upload_body(
        &self,
        headers: &HeaderMap,
        body: Body,
        budget: &Budget,
    ) -> Result<Bytes, ApiError> {
        let declared = headers
            .get(header::CONTENT_LENGTH)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.parse::<u64>().ok())
            .unwrap_or(self.config.max_upload_bytes as u64)
            .min(self.config.max_upload_bytes as u64);
        budget
            .charge(declared, || format!("an upload body of {declared} bytes"))
            .map_err(|e| budget_error(e, "upload_too_large"))?;
        read_body(
            headers,
            body,
            self.config.max_upload_bytes,
            self.config.admin_timeout,
        )
        .await
    }

    /// Reads any other request: the request size limit, the request timeout.
    pub(super) async fn request_body(
        &self,
        headers: &HeaderMap,
        body: Body,
    ) -> Result<Bytes, ApiError> {
        read_body(
            headers,
            body,
            self.config.max_request_bytes,
            self.config.request_timeout,
        )
        .await
    }
}

fn content_type(headers: &HeaderMap) -> String {
    headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .map(|v| {
            v.split(';')
                .next()
                .unwrap_or_default()
                .trim()
                .to_ascii_lowercase()
        })
        .unwrap_or_default()
}

/// Whether the client asked for bincode responses.
fn wants_bincode(headers: &HeaderMap) -> bool {
    headers
        .get_all(header::ACCEPT)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .any(|v| v.to_ascii_lowercase().contains(CONTENT_TYPE_BINCODE))
}

/// Content types a web page may send to any origin without a CORS preflight (a "simple"
/// request), plus no type at all. A body arriving with one of them may come from any page
/// the user has open, so no request body is accepted with them: a page on another origin
/// cannot make this server (on localhost, say) change or compute anything.
const SIMPLE_CONTENT_TYPES: [&str; 4] = [
    "",
    "text/plain",
    "application/x-www-form-urlencoded",
    "multipart/form-data",
];

/// 415 for a body sent with a type web pages can send unasked.
fn simple_content_type(ct: &str, expected: &str) -> ApiError {
    let got = if ct.is_empty() {
        "no Content-Type".to_string()
    } else {
        format!("Content-Type {ct:?}")
    };
    ApiError::new(
        StatusCode::UNSUPPORTED_MEDIA_TYPE,
        "unsupported_media_type",
        format!(
            "the body came with {got}; send it as {expected} (types a web page on another \
             origin could send without asking are refused)"
        ),
    )
}

/// The body's content type, refused when a cross-origin page could have sent it.
fn checked_content_type(headers: &HeaderMap, expected: &str) -> Result<String, ApiError> {
    let ct = content_type(headers);
    if SIMPLE_CONTENT_TYPES.contains(&ct.as_str()) {
        return Err(simple_content_type(&ct, expected));
    }
    Ok(ct)
}

/// Decodes a request body as JSON or bincode according to its Content-Type.
pub(super) fn decode<T: DeserializeOwned>(headers: &HeaderMap, body: &[u8]) -> Result<T, ApiError> {
    let expected = "application/json (or application/x-bincode)";
    let ct = checked_content_type(headers, expected)?;
    match ct.as_str() {
        CONTENT_TYPE_BINCODE => codec::request_from_wire(body)
            .map_err(|e| ApiError::bad_request("malformed_bincode", e.to_string())),
        CONTENT_TYPE_JSON => {
            // The path (`heads[3].frame`) tells a human which field is wrong.
            let mut de = serde_json::Deserializer::from_slice(body);
            let value = serde_path_to_error::deserialize(&mut de).map_err(|e| {
                let path = e.path().to_string();
                let inner = e.into_inner();
                let at = if path == "." {
                    String::new()
                } else {
                    format!(" at {path}")
                };
                ApiError::bad_request("malformed_json", format!("malformed JSON{at}: {inner}"))
            })?;
            de.end().map_err(|e| {
                ApiError::bad_request("malformed_json", format!("malformed JSON: {e}"))
            })?;
            Ok(value)
        }
        other => Err(ApiError::new(
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "unsupported_media_type",
            format!("content type {other:?} is not {CONTENT_TYPE_JSON} or {CONTENT_TYPE_BINCODE}"),
        )),
    }
}

/// Encodes a response as bincode when asked for, JSON otherwise.
pub(super) fn respond<T: Serialize>(
    headers: &HeaderMap,
    status: StatusCode,
    value: &T,
) -> ApiResult {
    let (ct, body) = if wants_bincode(headers) {
        (
            CONTENT_TYPE_BINCODE,
            codec::to_wire(value).map_err(ApiError::internal)?,
        )
    } else {
        (
            CONTENT_TYPE_JSON,
            serde_json::to_vec(value).map_err(ApiError::internal)?,
        )
    };
    Ok((
        status,
        [(header::CONTENT_TYPE, HeaderValue::from_static(ct))],
        body,
    )
        .into_response())
}

/// Compares without an early exit, so the time taken does not reveal the token's prefix.
fn same(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

impl AppState {
    /// Uploads and deletes need `Authorization: Bearer <token>` when a token is configured.
    pub(super) fn check_admin(&self, headers: &HeaderMap) -> Result<(), ApiError> {
        let Some(token) = &self.config.admin_token else {
            return Ok(());
        };
        // The scheme name is case-insensitive (RFC 7235 §2.1); the token is not.
        let given = headers
            .get(header::AUTHORIZATION)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.trim().split_once(' '))
            .filter(|(scheme, _)| scheme.eq_ignore_ascii_case("bearer"))
            .map(|(_, token)| token.trim());
        match given {
            Some(g) if same(g.as_bytes(), token.as_bytes()) => Ok(()),
            Some(_) => Err(ApiError::new(
                StatusCode::UNAUTHORIZED,
                "bad_token",
                "the bearer token is not the admin token",
            )),
            None => Err(ApiError::new(
                StatusCode::UNAUTHORIZED,
                "token_required",
                "uploads and deletes need an Authorization: Bearer <admin token> header",
            )),
        }
    }

    pub(super) fn check_ready(&self) -> Result<(), ApiError> {
        if self.is_ready() {
            Ok(())
        } else {
            Err(ApiError::unavailable(
                "loading",
                "stored rigs are still loading; retry shortly",
                1,
            ))
        }
    }

    pub(super) fn rig(&self, id: &str) -> Result<Arc<RigEntry>, ApiError> {
        self.registry.get(id).ok_or_else(|| unknown_rig(self, id))
    }

    /// Persists a rig's record: its geometry and LOD with the clips `layout` keeps in the
    /// record (for the built-in rig: its extra clips and LOD).
    pub(super) async fn persist_record(
        &self,
        id: &str,
        rig: Arc<Rig>,
        builtin: bool,
        layout: &ClipLayout,
    ) -> Result<(), ApiError> {
        if self.store.is_none() {
            return Ok(());
        }
        let state = self.clone();
        let id = id.to_string();
        let names = layout.record.clone();
        blocking(move || {
            let Some(store) = &state.store else {
                return Ok(());
            };
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
            store.put(record).map_err(ApiError::internal)
        })
        .await
    }

    /// Persists clip file `seq` of a rig with `clips`, or deletes it when there are none.
    pub(super) async fn persist_clips(
        &self,
        id: &str,
        seq: u64,
        clips: Vec<crate::rig::Clip>,
    ) -> Result<(), ApiError> {
        if self.store.is_none() {
            return Ok(());
        }
        let state = self.clone();
        let id = id.to_string();
        blocking(move || {
            let Some(store) = &state.store else {
                return Ok(());
            };
            if clips.is_empty() {
                store.remove_clips(&id, seq)
            } else {
                store.put(RecordRef::Clips {
                    id: &id,
                    seq,
                    clips: &clips,
                })
            }
            .map_err(ApiError::internal)
        })
        .await
    }
}

fn unknown_rig(state: &AppState, id: &str) -> ApiError {
    let mut ids: Vec<String> = state.registry.all().iter().map(|e| e.id.clone()).collect();
    ids.truncate(20);
    ApiError::not_found(
        "unknown_rig",
        format!("no rig {} (rigs: {})", quoted_name(id), ids.join(", ")),
    )
}

pub(super) fn unknown_clip(entry: &RigEntry, clip: &str) -> ApiError {
    let names: Vec<&str> = entry
        .rig()
        .clips
        .iter()
        .take(20)
        .map(|c| c.name.as_str())
        .collect();
    ApiError::not_found(
        "unknown_clip",
        format!(
            "rig {:?} has no clip {} (clips: {})",
            entry.id,
            quoted_name(clip),
            names.join(", ")
        ),
    )
}

/// A refused memory charge: 413 when the operation can never fit its limit, 503 (retry
/// later) when the server's pool is full now. Both messages name the bytes and the flag.
pub(super) fn budget_error(e: BudgetError, too_large: &'static str) -> ApiError {
    match e {
        BudgetError::TooLarge { .. } => {
            ApiError::new(StatusCode::PAYLOAD_TOO_LARGE, too_large, e.to_string())
        }
        BudgetError::Full { .. } => ApiError::unavailable("memory_full", e.to_string(), 5),
    }
}

/// A rig the engine could not prepare: over the GPU memory budget, answered as the host
/// budget answers (413 `too_large`, 503 `memory_full`, naming `--max-gpu-memory`); anything
/// else the device cannot hold, 422 `cannot_prepare`.
fn prepare_error(e: crate::engine::EngineError, too_large: &'static str) -> ApiError {
    match e {
        crate::engine::EngineError::GpuMemory(b) => budget_error(b, too_large),
        e => ApiError::new(
            StatusCode::UNPROCESSABLE_ENTITY,
            "cannot_prepare",
            e.to_string(),
        ),
    }
}

/// Errors of a clip import: like a rig's, with the clip's code for a clip too large.
fn clip_import_error(e: ImportError) -> ApiError {
    match e {
        ImportError::Budget(b) => budget_error(b, "clip_too_large"),
        e => import_error(e),
    }
}

fn import_error(e: ImportError) -> ApiError {
    match e {
        ImportError::Budget(b) => budget_error(b, "rig_too_large"),
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

/// Prepares `rig` for the engine after charging what that adds (the CPU layout and, on a GPU,
/// the upload's staging copies, or the stored record, whichever is larger) to `budget`.
pub(super) fn prepare_charged(
    engine: &crate::engine::Engine,
    budget: &Budget,
    rig: Arc<Rig>,
    gpu: bool,
) -> Result<
    (
        Arc<Rig>,
        crate::engine::PreparedRig,
        crowdmorph_proto::Quantization,
    ),
    ApiError,
> {
    let cost = RigShape::of(&rig).cost(gpu);
    // A rig whose resident GPU copy alone exceeds the GPU memory budget is refused up front,
    // as one over the host budget is; one that does not fit next to the rigs already there is
    // refused by the engine's charges (503, or 413 for one buffer over the whole budget).
    if let Some(pool) = engine.gpu_memory().filter(|_| gpu)
        && cost.device > pool.limit()
    {
        return Err(budget_error(
            BudgetError::TooLarge {
                what: format!(
                    "a rig of {} vertices and {} targets on the GPU",
                    rig.vertex_count(),
                    rig.targets.len()
                ),
                needed: cost.device,
                limit: pool.limit(),
                flag: crate::engine::gpu::GPU_MEMORY_FLAG,
            },
            "rig_too_large",
        ));
    }
    budget
        .charge(cost.layout + cost.transient, || {
            format!("preparing a rig of {} vertices", rig.vertex_count())
        })
        .map_err(|e| budget_error(e, "rig_too_large"))?;
    let prepared = engine
        .prepare(rig.clone())
        .map_err(|e| prepare_error(e, "rig_too_large"))?;
    let qbox = quantization_box(&rig);
    Ok((rig, prepared, qbox))
}

pub(super) async fn blocking<T: Send + 'static>(
    f: impl FnOnce() -> Result<T, ApiError> + Send + 'static,
) -> Result<T, ApiError> {
    tokio::task::spawn_blocking(f)
        .await
        .map_err(ApiError::internal)?
}

// ---------------------------------------------------------------------------------------------
// Health and metrics.

pub(super) async fn healthz() -> Response {
    (
        [(header::CONTENT_TYPE, CONTENT_TYPE_JSON)],
        r#"{"status":"ok"}"#,
    )
        .into_response()
}

pub(super) async fn readyz(State(state): State<AppState>) -> Response {
    let info = state.engine.info();
    let status = if !state.is_ready() {
        "loading"
    } else if info.degraded {
        "degraded"
    } else {
        "ready"
    };
    let body = Readiness {
        status: status.to_string(),
        backend: format!("{:?}", info.kind).to_lowercase(),
        cpu_isa: info.cpu_isa,
        degraded_reason: info.degraded_reason,
        rigs: state.registry.len() as u32,
        skipped_files: state.skipped(),
        renderer: state.render.adapter_name(),
    };
    let code = if state.is_ready() {
        StatusCode::OK
    } else {
        StatusCode::SERVICE_UNAVAILABLE
    };
    let json = serde_json::to_vec(&body).unwrap_or_default();
    (code, [(header::CONTENT_TYPE, CONTENT_TYPE_JSON)], json).into_response()
}

pub(super) async fn metrics(State(state): State<AppState>) -> Response {
    let mut text = state.metrics.render(state.gauges());
    state.sessions.write_metrics(&mut text);
    ([(header::CONTENT_TYPE, "text/plain; version=0.0.4")], text).into_response()
}

pub(super) async fn not_found() -> ApiError {
    ApiError::not_found(
        "no_route",
        "no such endpoint; see /v1/rigs and /v1/crowd/frame",
    )
}

// ---------------------------------------------------------------------------------------------
// Rigs.

#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RigQuery {
    name: Option<String>,
}

pub(super) async fn upload_rig(
    State(state): State<AppState>,
    query: Result<Query<RigQuery>, axum::extract::rejection::QueryRejection>,
    headers: HeaderMap,
    body: Body,
) -> ApiResult {
    state.check_admin(&headers)?;
    state.check_ready()?;
    let Query(query) = query.map_err(|e| ApiError::bad_request("bad_query", e.body_text()))?;
    if let Some(n) = &query.name
        && !valid_id(n)
    {
        return Err(ApiError::bad_request(
            "invalid_name",
            format!(
                "rig name {} must be 1-64 characters of A-Z a-z 0-9 . _ - (not starting with a dot)",
                quoted_name(n)
            ),
        ));
    }
    let rig_types = "model/gltf-binary (a GLB), model/gltf+json (a glTF with embedded buffers) \
                     or application/octet-stream";
    let ct = checked_content_type(&headers, rig_types)?;
    if ![
        "model/gltf-binary",
        "model/gltf+json",
        "application/octet-stream",
        CONTENT_TYPE_JSON,
    ]
    .contains(&ct.as_str())
    {
        return Err(ApiError::new(
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "unsupported_media_type",
            format!("a rig upload is {rig_types}, not {ct:?}"),
        ));
    }
    // One of two upload slots before the body is read: each upload may hold up to
    // `--max-upload-memory`, its body included.
    let _slot = state.uploads.acquire().await.map_err(ApiError::internal)?;
    let budget = state.op_budget();
    let bytes = state.upload_body(&headers, body, &budget).await?;
    let options = ImportOptions {
        base_dir: None,
        name: query.name.clone(),
        budget: Some(budget.clone()),
        ..ImportOptions::default()
    };
    let engine = state.engine.clone();
    let gpu = state.on_gpu();
    let b = budget.clone();
    let (rig, prepared, qbox) = blocking(move || {
        let import = GltfImport::open(&bytes, &options).map_err(import_error)?;
        // Everything the upload will hold, from the headers, before any decoding: the rig's
        // arrays (every target counted dense), the largest transient decode, the engine's
        // layouts and the stored record.
        let estimate = import.shape().cost(gpu);
        let need = b.used() + import.import_bytes() + estimate.layout + estimate.transient;
        let shape = import.shape();
        b.reserve(need, || {
            format!(
                "a rig of {} vertices, {} weight channels and {} clip table cells",
                shape.vertices(),
                shape.targets,
                shape.clip_cells
            )
        })
        .map_err(|e| budget_error(e, "rig_too_large"))?;
        let rig = import.build(&options).map_err(import_error)?;
        drop(bytes);
        check_output_range(&rig).map_err(|m| ApiError::bad_request("invalid_rig", m))?;
        let rig = Arc::new(rig);
        prepare_charged(&engine, &b, rig, gpu)
    })
    .await?;
    let id = query.name.unwrap_or_else(|| sanitize_id(&rig.name));
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
    let entry = Arc::new(RigEntry {
        id: id.clone(),
        builtin: false,
        builtin_clips: 0,
        vertices: rig.vertex_count(),
        qbox,
        generation: state.registry.generation(),
        prepared,
        layout,
        charge: std::sync::Mutex::new(charge),
        clip_names: Default::default(),
    });
    state.registry.insert(entry.clone());
    drop(budget);
    crate::budget::return_freed_memory();
    tracing::info!(rig = %id, vertices = entry.vertices, channels = rig.targets.len(), "rig registered");
    state.start_auto_lod(&entry);
    respond(&headers, StatusCode::CREATED, &state.rig_info(&entry))
}

pub(super) async fn list_rigs(State(state): State<AppState>, headers: HeaderMap) -> ApiResult {
    state.check_ready()?;
    let rigs = state
        .registry
        .all()
        .iter()
        .map(|e| state.rig_info(e))
        .collect();
    respond(&headers, StatusCode::OK, &RigList { rigs })
}

pub(super) async fn get_rig(
    State(state): State<AppState>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> ApiResult {
    state.check_ready()?;
    respond(&headers, StatusCode::OK, &state.rig_info(&*state.rig(&id)?))
}

pub(super) async fn delete_rig(
    State(state): State<AppState>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> ApiResult {
    state.check_admin(&headers)?;
    state.check_ready()?;
    let _admin = state.admin.lock().await;
    let entry = state.rig(&id)?;
    if entry.builtin {
        return Err(ApiError::new(
            StatusCode::FORBIDDEN,
            "builtin_rig",
            format!("rig {id:?} is built in and cannot be deleted"),
        ));
    }
    if state.store.is_some() {
        let s = state.clone();
        let rid = id.clone();
        blocking(move || {
            s.store
                .as_ref()
                .map_or(Ok(()), |st| st.remove(&rid))
                .map_err(ApiError::internal)
        })
        .await?;
    }
    state.lod_jobs.cancel(&id);
    state.registry.remove(&id);
    if let Ok(mut t) = state.render.topologies.lock() {
        t.purge(&id);
    }
    drop(entry);
    // The rig's memory is freed when the last request using it is done; hand what is free
    // now back to the OS, so that deleting a large rig lowers the resident size.
    crate::budget::return_freed_memory();
    tracing::info!(rig = %id, "rig deleted");
    Ok(StatusCode::NO_CONTENT.into_response())
}

#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct MeshQuery {
    /// LOD level whose (possibly simplified) mesh to return; default 0, the full mesh.
    lod: Option<u32>,
}

pub(super) async fn get_mesh(
    State(state): State<AppState>,
    Path(id): Path<String>,
    query: Result<Query<MeshQuery>, axum::extract::rejection::QueryRejection>,
    headers: HeaderMap,
) -> ApiResult {
    state.check_ready()?;
    let Query(query) = query.map_err(|e| ApiError::bad_request("bad_query", e.body_text()))?;
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
    // in base64 and digits): charged to the queue memory until it is encoded.
    let at = entry.prepared.at_level(lod).rig();
    let bytes = (at.vertex_count() * 24 + at.triangle_count() * 12) as u64;
    let factor = if wants_bincode(&headers) { 2 } else { 4 };
    let _held = state.reserve_queue_memory(bytes * factor)?;
    let mesh = blocking(move || Ok(entry.mesh(lod))).await?;
    respond(&headers, StatusCode::OK, &mesh)
}

// ---------------------------------------------------------------------------------------------
// Clips.

#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct ClipQuery {
    name: Option<String>,
    fps: Option<f32>,
    #[serde(default)]
    ignore_unknown: bool,
}

enum ClipSource {
    Csv,
    Json,
    Gltf,
}

fn clip_source(ct: &str, body: &[u8]) -> ClipSource {
    match ct {
        "text/csv" | "application/csv" => ClipSource::Csv,
        "model/gltf-binary" | "model/gltf+json" => ClipSource::Gltf,
        CONTENT_TYPE_JSON => {
            // A glTF document is JSON too; it is the one with an "asset" object.
            if body.windows(8).take(4096).any(|w| w == b"\"asset\":") {
                ClipSource::Gltf
            } else {
                ClipSource::Json
            }
        }
        _ if body.starts_with(b"glTF") => ClipSource::Gltf,
        _ if body.iter().find(|b| !b.is_ascii_whitespace()) == Some(&b'{') => ClipSource::Json,
        _ => ClipSource::Csv,
    }
}

pub(super) async fn upload_clips(
    State(state): State<AppState>,
    Path(id): Path<String>,
    query: Result<Query<ClipQuery>, axum::extract::rejection::QueryRejection>,
    headers: HeaderMap,
    body: Body,
) -> ApiResult {
    state.check_admin(&headers)?;
    state.check_ready()?;
    let Query(query) = query.map_err(|e| ApiError::bad_request("bad_query", e.body_text()))?;
    if let Some(n) = &query.name
        && !valid_id(n)
    {
        return Err(ApiError::bad_request(
            "invalid_name",
            format!(
                "clip name {} must be 1-64 characters of A-Z a-z 0-9 . _ -",
                quoted_name(n)
            ),
        ));
    }
    if let Some(fps) = query.fps
        && !(fps.is_finite() && fps > 0.0 && fps <= 1000.0)
    {
        return Err(ApiError::bad_request(
            "invalid_fps",
            format!("fps {fps} must be in (0, 1000]"),
        ));
    }
    state.rig(&id)?;
    let ct = checked_content_type(&headers, "text/csv, application/json or model/gltf-binary")?;
    let _slot = state.uploads.acquire().await.map_err(ApiError::internal)?;
    let budget = state.op_budget();
    let bytes = state.upload_body(&headers, body, &budget).await?;
    let source = clip_source(&ct, &bytes);
    if !matches!(source, ClipSource::Gltf) && query.name.is_none() {
        return Err(ApiError::bad_request(
            "missing_name",
            "CSV and JSON clips need a name: POST /v1/rigs/{id}/clips?name=NAME",
        ));
    }
    // Clips are imported against a snapshot, outside the lock that serializes rig changes:
    // they depend only on the rig's target names, which no change of the same rig alters.
    let base = state.rig(&id)?;
    let options = ClipOptions {
        fps: query.fps.unwrap_or(crate::rig::DEFAULT_FPS),
        ignore_unknown: query.ignore_unknown,
        budget: Some(budget.clone()),
    };
    let name = query.name.clone();
    let snapshot = base.clone();
    let imports = blocking(move || {
        let rig = snapshot.rig();
        let imports: Vec<ClipImport> = match source {
            ClipSource::Csv => vec![
                crate::import::clip_from_csv(
                    rig,
                    name.as_deref().unwrap_or("clip"),
                    &bytes,
                    &options,
                )
                .map_err(clip_import_error)?,
            ],
            ClipSource::Json => vec![
                crate::import::clip_from_json(
                    rig,
                    name.as_deref().unwrap_or("clip"),
                    &bytes,
                    &options,
                )
                .map_err(clip_import_error)?,
            ],
            ClipSource::Gltf => {
                let mut v = crate::import::clips_from_gltf(rig, &bytes, &options)
                    .map_err(clip_import_error)?;
                let single = v.len() == 1;
                for c in &mut v {
                    c.clip.name = match (&name, single) {
                        (Some(n), true) => n.clone(),
                        (Some(n), false) => format!("{n}.{}", sanitize_id(&c.clip.name)),
                        (None, _) => sanitize_id(&c.clip.name),
                    };
                }
                v
            }
        };
        Ok(imports)
    })
    .await?;
    let _admin = state.admin.lock().await;
    // Re-read under the lock: another change may have landed since. It must still be the
    // same rig (not deleted and uploaded again with other targets).
    let entry = state.rig(&id)?;
    if !Arc::ptr_eq(&entry.rig().primitives, &base.rig().primitives)
        || entry.rig().targets != base.rig().targets
    {
        return Err(ApiError::new(
            StatusCode::CONFLICT,
            "rig_changed",
            format!("rig {id:?} was replaced while its clips were imported; upload them again"),
        ));
    }
    let engine = state.engine.clone();
    let current = entry.clone();
    let (rig, prepared, qbox, added, ignored, table_bytes) = blocking(move || {
        let mut new = current.rig().clone();
        let mut ignored: Vec<String> = Vec::new();
        // Hash sets, not scans of what came before: a file may hold thousands of clips and
        // name thousands of unknown targets.
        let mut seen_ignored = std::collections::HashSet::new();
        let mut added_names = std::collections::HashSet::new();
        let mut added = Vec::new();
        let mut table_bytes = 0u64;
        for imp in imports {
            if current.clip_index(&imp.clip.name).is_some()
                || !added_names.insert(imp.clip.name.clone())
            {
                return Err(ApiError::new(
                    StatusCode::CONFLICT,
                    "clip_exists",
                    format!(
                        "rig {:?} has a clip {:?} already; DELETE it first or choose another ?name=",
                        current.id, imp.clip.name
                    ),
                ));
            }
            for i in imp.ignored.iter() {
                if seen_ignored.insert(i.clone()) {
                    ignored.push(i.clone());
                }
            }
            added.push(crowdmorph_proto::ClipInfo {
                name: imp.clip.name.clone(),
                frames: imp.clip.frames,
                fps: imp.clip.fps,
            });
            table_bytes += imp.clip.weights.len() as u64 * 4;
            new.clips.push(imp.clip);
        }
        new.validate()
            .map_err(|e| ApiError::bad_request("invalid_clip", e.to_string()))?;
        check_output_range(&new).map_err(|m| ApiError::bad_request("invalid_clip", m))?;
        let new = Arc::new(new);
        let prepared = engine
            .update_clips(&current.prepared, new.clone())
            .map_err(|e| prepare_error(e, "clip_too_large"))?;
        let qbox = quantization_box(&new);
        Ok((new, prepared, qbox, added, ignored, table_bytes))
    })
    .await?;
    // The new clips go to a clip file of their own: the rig's record is not rewritten.
    let names: Vec<String> = added.iter().map(|c| c.name.clone()).collect();
    let seq = entry.layout.next_seq();
    state
        .persist_clips(&id, seq, clips_named(&rig, &names))
        .await?;
    let mut layout = entry.layout.clone();
    layout.files.push((seq, names));
    // The new generation holds the old one's charge plus the new tables.
    state.registry.insert(Arc::new(entry.successor(
        prepared,
        qbox,
        layout,
        state.registry.generation(),
        Some(budget.keep(table_bytes)),
    )));
    drop(budget);
    crate::budget::return_freed_memory();
    tracing::info!(rig = %id, clips = added.len(), ignored = ignored.len(), "clips added");
    respond(
        &headers,
        StatusCode::CREATED,
        &ClipUpload {
            rig: id,
            added,
            ignored,
        },
    )
}

pub(super) async fn list_clips(
    State(state): State<AppState>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> ApiResult {
    state.check_ready()?;
    let entry = state.rig(&id)?;
    respond(
        &headers,
        StatusCode::OK,
        &ClipList {
            rig: id,
            clips: clip_infos(entry.rig()),
        },
    )
}

pub(super) async fn get_clip(
    State(state): State<AppState>,
    Path((id, clip)): Path<(String, String)>,
    headers: HeaderMap,
) -> ApiResult {
    state.check_ready()?;
    let entry = state.rig(&id)?;
    let ci = entry
        .clip_index(&clip)
        .ok_or_else(|| unknown_clip(&entry, &clip))?;
    respond(&headers, StatusCode::OK, &clip_info(&entry.rig().clips[ci]))
}

pub(super) async fn delete_clip(
    State(state): State<AppState>,
    Path((id, clip)): Path<(String, String)>,
    headers: HeaderMap,
) -> ApiResult {
    state.check_admin(&headers)?;
    state.check_ready()?;
    let _admin = state.admin.lock().await;
    let entry = state.rig(&id)?;
    let ci = entry
        .clip_index(&clip)
        .ok_or_else(|| unknown_clip(&entry, &clip))?;
    if entry.builtin && ci < entry.builtin_clips {
        return Err(ApiError::new(
            StatusCode::FORBIDDEN,
            "builtin_clip",
            format!("clip {clip:?} is part of the built-in rig and cannot be deleted"),
        ));
    }
    let engine = state.engine.clone();
    let base = entry.clone();
    let (rig, prepared, qbox) = blocking(move || {
        let mut new = base.rig().clone();
        new.clips.remove(ci);
        let new = Arc::new(new);
        let prepared = engine
            .update_clips(&base.prepared, new.clone())
            .map_err(ApiError::internal)?;
        let qbox = quantization_box(&new);
        Ok((new, prepared, qbox))
    })
    .await?;
    // Only the file that held the clip is rewritten: its clip file, or the rig's record.
    let layout = entry.layout.without(&clip);
    match entry.layout.file_of(&clip) {
        Some(seq) => {
            let rest = layout
                .files
                .iter()
                .find(|f| f.0 == seq)
                .map(|f| clips_named(&rig, &f.1))
                .unwrap_or_default();
            state.persist_clips(&id, seq, rest).await?;
        }
        None => {
            state
                .persist_record(&id, rig.clone(), entry.builtin, &layout)
                .await?;
        }
    }
    state.registry.insert(Arc::new(entry.successor(
        prepared,
        qbox,
        layout,
        state.registry.generation(),
        None,
    )));
    crate::budget::return_freed_memory();
    tracing::info!(rig = %id, clip = %clip, "clip deleted");
    Ok(StatusCode::NO_CONTENT.into_response())
}

// ---------------------------------------------------------------------------------------------
// Crowd frames.

impl AppState {
    /// Takes `bytes` of the queue memory (output held by admitted crowd requests, and
    /// request bodies being decoded); 503 when it is full, 413 when `bytes` is more than the
    /// whole queue memory (taking all of it would let the holder allocate past the limit).
    pub(super) fn reserve_queue_memory(
        &self,
        bytes: u64,
    ) -> Result<OwnedSemaphorePermit, ApiError> {
        let units = bytes.div_ceil(1024).max(1);
        if units > u64::from(self.memory_units) {
            return Err(self.queue_memory_exceeded(bytes));
        }
        let units = units as u32;
        self.memory
            .clone()
            .try_acquire_many_owned(units)
            .map_err(|_| {
                self.metrics.reject("queue_memory");
                ApiError::unavailable(
                    "queue_full",
                    "the server is holding as much output as it may; retry shortly",
                    1,
                )
            })
    }

    /// 413 for something that needs `bytes` of queue memory, more than all of it: it could
    /// never be admitted (counted as a queue-memory rejection).
    fn queue_memory_exceeded(&self, bytes: u64) -> ApiError {
        self.metrics.reject("queue_memory");
        ApiError::new(
            StatusCode::PAYLOAD_TOO_LARGE,
            "queue_memory_exceeded",
            format!(
                "this needs {bytes} bytes of queue memory, more than the server's {} \
                 (--queue-memory-bytes)",
                self.queue_memory_bytes()
            ),
        )
    }

    /// The whole queue memory, bytes.
    pub(super) fn queue_memory_bytes(&self) -> u64 {
        u64::from(self.memory_units) * 1024
    }
}

/// Largest coordinate (in absolute value) a rig's positions can reach, from its q16 box.
pub(super) fn head_reach(entry: &RigEntry) -> f64 {
    let q = &entry.qbox;
    (0..3)
        .map(|a| {
            let lo = f64::from(q.min[a]);
            let hi = lo + f64::from(q.step[a]) * 65535.0;
            lo.abs().max(hi.abs())
        })
        .fold(0.0, f64::max)
}

/// Keeps the admitted memory permit alive as long as the response body is being sent.
struct PermitBytes {
    bytes: Bytes,
    _permit: Option<OwnedSemaphorePermit>,
}

impl AsRef<[u8]> for PermitBytes {
    fn as_ref(&self) -> &[u8] {
        &self.bytes
    }
}

/// A body made of shared chunks with a known total length, so that hyper sends a
/// Content-Length (no chunked framing) and writes the chunks with vectored writes, uncopied.
struct ChunkBody {
    chunks: std::collections::VecDeque<Bytes>,
    remaining: u64,
}

impl http_body::Body for ChunkBody {
    type Data = Bytes;
    type Error = std::convert::Infallible;

    fn poll_frame(
        mut self: std::pin::Pin<&mut Self>,
        _: &mut std::task::Context<'_>,
    ) -> std::task::Poll<Option<Result<http_body::Frame<Bytes>, Self::Error>>> {
        let next = self.chunks.pop_front();
        if let Some(c) = &next {
            self.remaining -= c.len() as u64;
        }
        std::task::Poll::Ready(next.map(|c| Ok(http_body::Frame::data(c))))
    }

    fn is_end_stream(&self) -> bool {
        self.chunks.is_empty()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        http_body::SizeHint::with_exact(self.remaining)
    }
}

pub(super) fn chunked_body(mut chunks: Vec<Bytes>, permit: OwnedSemaphorePermit) -> Body {
    // The last chunk carries the permit: it is released when the whole body has been sent
    // (or the connection dropped).
    let last = chunks.pop().unwrap_or_default();
    chunks.push(Bytes::from_owner(PermitBytes {
        bytes: last,
        _permit: Some(permit),
    }));
    let remaining = chunks.iter().map(|c| c.len() as u64).sum();
    Body::new(ChunkBody {
        chunks: chunks.into_iter().filter(|c| !c.is_empty()).collect(),
        remaining,
    })
}

/// Crowd heads resolved against one snapshot of each rig they name: what both crowd endpoints
/// compute from.
pub(super) struct ResolvedHeads {
    /// The rigs, in order of first appearance; `JobKey::rig` indexes this.
    pub rigs: Vec<Arc<RigEntry>>,
    /// Unique jobs and each head's job.
    pub plan: Plan,
}

/// Bytes one job's output holds while it is computed and sent: positions (and normals) in the
/// wire format, three times that as JSON (base64 text and its escape), plus, with normals in a
/// 16-bit format on a rig whose normals are recomputed, the f32 positions and normals the CPU
/// engine blends before the normals pass and the encoding, and, for q16 on the GPU engine
/// (`gpu`), the f32 outputs it reads back and quantizes on the host. The job's weights are
/// counted too ([`JOB_WEIGHT_BYTES_PER_TARGET`] per rig target): on a rig of many targets and
/// few vertices they outweigh the output. Every admission (crowd frames, sessions, load tests)
/// charges this.
pub(super) fn job_output_bytes(
    rig: &Rig,
    format: Format,
    normals: bool,
    json: bool,
    gpu: bool,
) -> u64 {
    let v3 = rig.vertex_count() as u64 * 3;
    let comp = format.component_bytes() as u64;
    let outputs = if normals { 2 } else { 1 };
    let wire = v3 * comp * outputs * if json { 3 } else { 1 };
    let f32_first =
        (normals && comp < 4 && rig.recomputes_normals()) || (gpu && format == Format::Q16);
    let weights = rig.targets.len() as u64 * JOB_WEIGHT_BYTES_PER_TARGET + 16;
    wire + if f32_first { v3 * 4 * outputs } else { 0 } + weights
}

/// What a batch holds per job and rig target besides the outputs: the job's row of the
/// gathered weights (`WeightBatch`, 4 bytes per target) and its lane of the CPU kernel's
/// group tables (4 bytes of weight and, per group of 8 jobs, a byte per target), rounded up.
/// The GPU engine gathers the same rows before it uploads them.
pub(super) const JOB_WEIGHT_BYTES_PER_TARGET: u64 = 9;

/// What a crowd-frame request holds per head from its decoding until its response is sent:
/// the decoded head and its two names, its job index in the plan, its `HeadBuffer`, and its
/// entry in the encoded response (at most 64 bytes as JSON, 16 as bincode).
fn frame_held_bytes(req: &CrowdFrameRequest, json: bool) -> u64 {
    let built = size_of::<u32>() + size_of::<HeadBuffer>() + if json { 64 } else { 16 };
    heads_held_bytes(&req.heads, built as u64)
}

/// Bytes `heads` hold decoded (each `Head` and its two names), plus `built` bytes a head of
/// what a handler builds from them: the per-head share a crowd frame keeps charged until its
/// response is sent, and a render until its frame is drawn.
pub(super) fn heads_held_bytes(heads: &[Head], built: u64) -> u64 {
    let per_head = size_of::<Head>() as u64 + built;
    heads
        .iter()
        .map(|h| per_head + h.rig.capacity() as u64 + h.clip.capacity() as u64)
        .sum()
}

/// Queue memory a crowd request body of `declared` bytes reserves while it is read and decoded
/// (bincode or JSON): the body and what it decodes to, a head taking 72 bytes decoded from at
/// least 5 bytes of bincode or 40 of JSON. `POST /v1/loadtest` counts the same for each of its
/// synthetic requests.
pub(super) fn decode_reservation(bincode: bool, declared: u64) -> u64 {
    declared.saturating_mul(if bincode { 16 } else { 3 })
}

impl AppState {
    /// Reads and decodes a crowd request body (JSON or bincode). The body and what it decodes
    /// to are charged to the queue memory while they are read ([`decode_reservation`]).
    pub(super) async fn crowd_request<T: DeserializeOwned>(
        &self,
        headers: &HeaderMap,
        body: Body,
    ) -> Result<T, ApiError> {
        let (req, _) = self.crowd_request_held(headers, body, |_| 0).await?;
        Ok(req)
    }

    /// [`AppState::crowd_request`] for a request whose decoded form (and what is built per
    /// head from it) stays alive until its response is sent: `held` bytes of the decode
    /// reservation are kept (or more reserved) and returned, to be held as long.
    pub(super) async fn crowd_request_held<T: DeserializeOwned>(
        &self,
        headers: &HeaderMap,
        body: Body,
        held: impl FnOnce(&T) -> u64,
    ) -> Result<(T, OwnedSemaphorePermit), ApiError> {
        let declared = headers
            .get(header::CONTENT_LENGTH)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.parse::<u64>().ok())
            .unwrap_or(self.config.max_request_bytes as u64)
            .min(self.config.max_request_bytes as u64);
        // A body whose decoding could need more than the whole queue memory (a large or
        // unknown length on a small queue) reserves all of it: the request-size limit bounds
        // the rest, and refusing would refuse every chunked body on such a server.
        let decoding = self.reserve_queue_memory(
            decode_reservation(content_type(headers) == CONTENT_TYPE_BINCODE, declared)
                .min(self.queue_memory_bytes()),
        )?;
        let bytes = self.request_body(headers, body).await?;
        let req = decode(headers, &bytes)?;
        drop(bytes);
        let mut decoding = decoding;
        let need = held(&req);
        if need.div_ceil(1024) > u64::from(self.memory_units) {
            // It could never be held, whatever else is queued: too large, not busy.
            return Err(self.queue_memory_exceeded(need));
        }
        let units = need.div_ceil(1024) as usize;
        let have = decoding.num_permits();
        let kept = if units <= have {
            // The rest of the reservation is given back as `decoding` drops.
            decoding.split(units)
        } else {
            let more = self.reserve_queue_memory((units - have) as u64 * 1024)?;
            decoding.merge(more);
            Some(decoding)
        };
        let kept = kept.ok_or_else(|| ApiError::internal("splitting a queue-memory permit"))?;
        Ok((req, kept))
    }

    /// Resolves every head against one snapshot of each rig it names (a rig changed or
    /// deleted meanwhile does not change this request), checks clip, frame and LOD, and plans
    /// the unique jobs. `f16` refuses rigs whose coordinates f16 cannot hold. Errors name the
    /// head by position and id.
    pub(super) fn resolve_heads(
        &self,
        heads: &[Head],
        mode: FrameMode,
        f16: bool,
    ) -> Result<ResolvedHeads, ApiError> {
        let n_heads = heads.len();
        if n_heads > self.config.max_heads {
            return Err(ApiError::bad_request(
                "too_many_heads",
                format!(
                    "{n_heads} heads is more than the limit of {} per request",
                    self.config.max_heads
                ),
            ));
        }
        let mut rigs: Vec<Arc<RigEntry>> = Vec::new();
        let mut rig_at: HashMap<&str, u32> = HashMap::new();
        let mut clip_at: HashMap<(u32, &str), u32> = HashMap::new();
        let mut keys = Vec::with_capacity(n_heads);
        for (h, head) in heads.iter().enumerate() {
            let ri = match rig_at.get(head.rig.as_str()) {
                Some(&i) => i,
                None => {
                    let e = self.rig(&head.rig).map_err(|e| ApiError {
                        message: format!("head {h} (id {}): {}", head.head, e.message),
                        ..e
                    })?;
                    rigs.push(e);
                    let i = (rigs.len() - 1) as u32;
                    rig_at.insert(head.rig.as_str(), i);
                    i
                }
            };
            let entry = &rigs[ri as usize];
            let rig = entry.rig();
            if f16 && head_reach(entry) > super::registry::MAX_F16 {
                return Err(ApiError::bad_request(
                    "format_overflow",
                    format!(
                        "head {h} (id {}): rig {:?} reaches coordinates of {:e}, past the largest \
                         f16 ({}); ask for f32 or q16",
                        head.head,
                        entry.id,
                        head_reach(entry),
                        super::registry::MAX_F16
                    ),
                ));
            }
            let ci = match clip_at.get(&(ri, head.clip.as_str())) {
                Some(&c) => c,
                None => {
                    let c = entry.clip_index(&head.clip).ok_or_else(|| {
                        let e = unknown_clip(entry, &head.clip);
                        ApiError {
                            message: format!("head {h} (id {}): {}", head.head, e.message),
                            ..e
                        }
                    })? as u32;
                    clip_at.insert((ri, head.clip.as_str()), c);
                    c
                }
            };
            let clip = &rig.clips[ci as usize];
            let frame = clip.resolve_frame(head.frame, mode).map_err(|e| {
                ApiError::bad_request(
                    "frame_out_of_range",
                    format!("head {h} (id {}): {e}", head.head),
                )
            })?;
            if head.lod as usize >= rig.lod.levels.len() {
                return Err(ApiError::bad_request(
                    "lod_out_of_range",
                    format!(
                        "head {h} (id {}): LOD {} out of range: rig {:?} has levels 0..{}",
                        head.head,
                        head.lod,
                        entry.id,
                        rig.lod.levels.len() - 1
                    ),
                ));
            }
            keys.push(JobKey {
                rig: ri,
                clip: ci,
                frame,
                lod: head.lod,
            });
        }
        Ok(ResolvedHeads {
            rigs,
            plan: Plan::new(keys),
        })
    }
}

/// Payload bytes above which a JSON response is encoded on the blocking pool.
const JSON_INLINE_BYTES: usize = 64 << 10;

/// Encodes a JSON crowd-frame response; base64 of a big crowd takes milliseconds, so those
/// are encoded on the blocking pool, not on an async worker.
async fn json_frame(
    state: &AppState,
    format: Format,
    normals: bool,
    parts: &[FrameBufferParts<'_>],
    heads: Vec<HeadBuffer>,
    timings: FrameTimings,
) -> Result<Bytes, ApiError> {
    let pool = state.json_pool.clone();
    let payload: usize = parts
        .iter()
        .map(|p| p.positions.len() + p.normals.as_ref().map_or(0, Bytes::len))
        .sum();
    if payload <= JSON_INLINE_BYTES {
        return Ok(super::json::encode_frame(
            &pool, format, normals, parts, &heads, &timings,
        ));
    }
    let owned: Vec<(String, String, FrameBufferParts<'static>)> = parts
        .iter()
        .map(|p| {
            (
                p.rig.to_string(),
                p.clip.to_string(),
                FrameBufferParts {
                    rig: "",
                    clip: "",
                    ..p.clone()
                },
            )
        })
        .collect();
    blocking(move || {
        let parts: Vec<FrameBufferParts<'_>> = owned
            .iter()
            .map(|(rig, clip, p)| FrameBufferParts {
                rig,
                clip,
                ..p.clone()
            })
            .collect();
        Ok(super::json::encode_frame(
            &pool, format, normals, &parts, &heads, &timings,
        ))
    })
    .await
}

/// One unique job for the batcher, with its cost: vertices × (active shapes + 1) at the job's
/// frame and level of detail.
pub(super) fn job_request(entry: &Arc<RigEntry>, clip: u32, frame: u32, lod: u32) -> JobRequest {
    let rig = entry.rig();
    let shapes = rig.lod.shapes_at(lod).unwrap_or(0) as usize;
    let table = &rig.clips[clip as usize];
    let active = rig.lod.order[..shapes.min(rig.lod.order.len())]
        .iter()
        .filter(|&&t| table.weight(t as usize, frame).abs() > ACTIVE_WEIGHT_EPSILON)
        .count() as u64;
    let v = entry.prepared.at_level(lod).rig().vertex_count() as u64;
    JobRequest {
        entry: entry.clone(),
        clip,
        frame,
        lod,
        cost: v * (active + 1),
    }
}

pub(super) async fn crowd_frame(
    State(state): State<AppState>,
    headers: HeaderMap,
    body: Body,
) -> Response {
    crowd_frame_from(&state, &headers, body, Source::Api).await
}

/// `POST /v1/crowd/frame` for a request from `source`: the route's handler, and what
/// `POST /v1/loadtest` calls for each synthetic request, so that synthetic load goes through
/// the same decoding, admission, batcher and encoders as real traffic. Loadtest requests are
/// queued at low priority and counted under their own label.
pub(super) async fn crowd_frame_from(
    state: &AppState,
    headers: &HeaderMap,
    body: Body,
    source: Source,
) -> Response {
    // Counted as cancelled if this future is dropped (the client hung up) before it answers;
    // its queued jobs are then dropped by the batcher before they are computed.
    let waiting = super::metrics::DropCounter::new(state.metrics.clone(), "frame");
    let resp = frame(state, headers, body, source).await.into_response();
    waiting.finish();
    state.metrics.crowd_frame(source, resp.status().as_u16());
    resp
}

/// Milliseconds with three decimals, as Server-Timing wants them.
async fn frame(state: &AppState, headers: &HeaderMap, body: Body, source: Source) -> ApiResult {
    let arrived = Instant::now();
    state.check_ready()?;
    let json = !wants_bincode(headers);
    let (req, held): (CrowdFrameRequest, _) = state
        .crowd_request_held(headers, body, |r: &CrowdFrameRequest| {
            frame_held_bytes(r, json)
        })
        .await?;
    let n_heads = req.heads.len();
    let format = req.output.format;
    let normals = req.output.normals;
    let mode = if req.wrap {
        FrameMode::Wrap
    } else {
        FrameMode::Strict
    };
    let ResolvedHeads { rigs, plan } =
        state.resolve_heads(&req.heads, mode, format == Format::F16)?;

    // Admission: the output memory this request will hold, then a place in the queue.
    let gpu = state.engine.gpu_memory().is_some();
    // Priced per rig and level (a LOD level on a simplified mesh has fewer vertices), before
    // any per-job work: a request refused as too large costs a lookup per unique job.
    // (bytes per job, vertices) of each rig level the request uses.
    let mut per_level: HashMap<(u32, u32), (u64, u32)> = HashMap::new();
    let mut out_bytes = 0u64;
    for k in &plan.jobs {
        let (bytes, _) = *per_level.entry((k.rig, k.lod)).or_insert_with(|| {
            let rig = rigs[k.rig as usize].prepared.at_level(k.lod).rig();
            (
                job_output_bytes(rig, format, normals, json, gpu),
                rig.vertex_count() as u32,
            )
        });
        out_bytes = out_bytes.saturating_add(bytes);
    }
    let units = out_bytes.div_ceil(1024).max(1);
    // The heads' share is already held (`held`): together they must fit the whole queue.
    if units.saturating_add(held.num_permits() as u64) > u64::from(state.memory_units) {
        return Err(ApiError::new(
            StatusCode::PAYLOAD_TOO_LARGE,
            "response_too_large",
            format!(
                "the response would hold {out_bytes} bytes of vertex data, more than the server's \
                 queue memory of {} bytes (--queue-memory-bytes); ask for fewer unique heads or a \
                 smaller format",
                u64::from(state.memory_units) * 1024
            ),
        ));
    }
    let mut permit = state.reserve_queue_memory(out_bytes)?;
    // Held with the outputs until the body is sent.
    permit.merge(held);
    let jobs: Vec<JobRequest> = plan
        .jobs
        .iter()
        .map(|k| job_request(&rigs[k.rig as usize], k.clip, k.frame, k.lod))
        .collect();
    state
        .metrics
        .jobs_requested
        .fetch_add(jobs.len() as u64, std::sync::atomic::Ordering::Relaxed);
    let priority = match source {
        Source::Api => Priority::Normal,
        Source::Loadtest => Priority::Low,
    };
    let ticket = state
        .scheduler
        .submit_with(jobs, format, normals, priority)
        .map_err(|e| match e {
            ScheduleError::QueueFull => {
                state.metrics.reject("queue_full");
                ApiError::unavailable("queue_full", "the batch queue is full; retry shortly", 1)
            }
            ScheduleError::ShuttingDown => {
                ApiError::unavailable("shutting_down", "the server is shutting down", 5)
            }
            ScheduleError::Engine(e) => ApiError::internal(e),
        })?;
    let deadline = state
        .config
        .request_timeout
        .saturating_sub(arrived.elapsed());
    let outcome = match tokio::time::timeout(deadline, ticket).await {
        Err(_) => {
            state.metrics.reject("deadline");
            state
                .metrics
                .cancelled("frame", crate::cancel::Cancelled::Deadline);
            return Err(ApiError::new(
                StatusCode::GATEWAY_TIMEOUT,
                "deadline_exceeded",
                format!(
                    "the frame was not ready within the request deadline of {} ms",
                    state.config.request_timeout.as_millis()
                ),
            ));
        }
        Ok(Err(_)) => return Err(ApiError::internal("the batcher dropped a request")),
        Ok(Ok(Err(ScheduleError::ShuttingDown))) => {
            return Err(ApiError::unavailable(
                "shutting_down",
                "the server is shutting down",
                5,
            ));
        }
        Ok(Ok(Err(e))) => return Err(ApiError::internal(e)),
        Ok(Ok(Ok(o))) => o,
    };

    // The last stage boundary: a response the client has already been told is late (or
    // that the router's timeout is about to answer) is not encoded.
    if arrived.elapsed() >= state.config.request_timeout {
        state.metrics.reject("deadline");
        state
            .metrics
            .cancelled("frame", crate::cancel::Cancelled::Deadline);
        return Err(ApiError::new(
            StatusCode::GATEWAY_TIMEOUT,
            "deadline_exceeded",
            format!(
                "the frame was not ready within the request deadline of {} ms",
                state.config.request_timeout.as_millis()
            ),
        ));
    }
    let heads: Vec<HeadBuffer> = req
        .heads
        .iter()
        .zip(&plan.head_job)
        .map(|(h, &j)| HeadBuffer {
            head: h.head,
            buffer: j,
        })
        .collect();
    let timings = FrameTimings {
        queue_us: outcome.queue.as_micros() as u64,
        compute_us: outcome.compute_ns / 1000,
        total_us: arrived.elapsed().as_micros() as u64,
        gpu_us: outcome.gpu_ns.map(|g| g / 1000),
    };
    state.metrics.served_to(source, n_heads as u64);
    state.metrics.request_heads.observe(n_heads as f64);
    state
        .metrics
        .request_seconds
        .observe(arrived.elapsed().as_secs_f64());
    // Server-Timing: where the time went, for load generators and browsers' dev tools
    // (the body's FrameTimings cannot include the encoding that writes them).
    let encoding = Instant::now();
    let server_timing = |encoded: Instant| {
        let mut t = format!(
            "queue;dur={}, compute;dur={}, encode;dur={}, total;dur={}",
            super::render::ms(outcome.queue),
            super::render::ms(std::time::Duration::from_nanos(outcome.compute_ns)),
            super::render::ms(encoded.duration_since(encoding)),
            super::render::ms(encoded.duration_since(arrived)),
        );
        if let Some(g) = outcome.gpu_ns {
            t += &format!(
                ", gpu;dur={}",
                super::render::ms(std::time::Duration::from_nanos(g))
            );
        }
        HeaderValue::from_str(&t).ok()
    };

    let parts: Vec<FrameBufferParts<'_>> = plan
        .jobs
        .iter()
        .zip(&outcome.outputs)
        .map(|(k, out)| {
            let entry = &rigs[k.rig as usize];
            FrameBufferParts {
                rig: &entry.id,
                clip: &entry.rig().clips[k.clip as usize].name,
                frame: k.frame,
                lod: k.lod,
                vertices: per_level.get(&(k.rig, k.lod)).map_or(0, |&(_, v)| v),
                quantization: (format == Format::Q16).then_some(entry.qbox),
                positions: out.positions.clone(),
                normals: if normals { out.normals.clone() } else { None },
            }
        })
        .collect();
    if wants_bincode(headers) {
        let chunks = FrameResponseEncoder::encode(format, normals, &parts, &heads, &timings);
        let mut resp = (
            StatusCode::OK,
            [(header::CONTENT_TYPE, CONTENT_TYPE_BINCODE)],
            chunked_body(chunks, permit),
        )
            .into_response();
        if let Some(v) = server_timing(Instant::now()) {
            resp.headers_mut().insert(super::render::SERVER_TIMING, v);
        }
        return Ok(resp);
    }
    let json = json_frame(state, format, normals, &parts, heads, timings).await?;
    let mut resp = (
        StatusCode::OK,
        [(header::CONTENT_TYPE, CONTENT_TYPE_JSON)],
        chunked_body(vec![json], permit),
    )
        .into_response();
    if let Some(v) = server_timing(Instant::now()) {
        resp.headers_mut().insert(super::render::SERVER_TIMING, v);
    }
    Ok(resp)
}
