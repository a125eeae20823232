//! Clips of a rig: `POST /v1/rigs/{id}/clips` (CSV, JSON or glTF animations, matched to the
//! rig's targets, each source kind by its own import), `GET` a list or one, `DELETE` one (with
//! its texture), and `PUT`/`GET`/`DELETE /v1/rigs/{id}/clips/{clip}/texture`: the clip's
//! animated texture (PCA, beside it).

use std::sync::Arc;

use axum::body::Body;
use axum::extract::{Path, State};
use axum::http::{HeaderMap, StatusCode};
use axum::response::IntoResponse;
use crowdmorph_proto::{CONTENT_TYPE_JSON, ClipInfo, ClipList, ClipUpload, Quantization};

use super::rigs::{check_name, clip_import_error, upload_body};
use crate::admission::mapping::{mapping_spec, resolve_mapping, resolved_bytes};
use crate::admission::names::LiveNames;
use crate::admission::resolve::unknown_clip;
use crate::http::cache::Validator;
use crate::http::{
    Accept, Admin, ApiError, ApiResult, Query, Ready, blocking, checked_content_type,
};
use crate::registry::{
    RigEntry, check_output_range, clip_info, clip_infos, clips_named, quantization_box, sanitize_id,
};
use crate::services::Parts;
use crate::services::persist::prepare_error;
use crate::services::persist::{clip_error, persist_clips, persist_record};
use crate::state::AppState;
use crowdmorph_core::rig::NamedMapping;
use crowdmorph_core::rig::{AnimatedTexture, Rig};
use crowdmorph_engine::{Engine, PreparedRig};
use crowdmorph_import::ImportError;
use crowdmorph_import::clips::{ClipImport, ClipOptions};

#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ClipQuery {
    name: Option<String>,
    fps: Option<f32>,
    #[serde(default)]
    ignore_unknown: bool,
    /// A mapping of the rig whose sources a CSV clip's columns are (`?mapping=a2f`).
    mapping: Option<String>,
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

/// `POST /v1/rigs/{id}/clips`: check the query, read the body under the upload's budget,
/// import it against a snapshot of the rig (one function per source kind), then, under the
/// lock that serializes rig changes, merge the clips into a new generation, store it, publish.
pub async fn upload_clips(
    State(state): State<AppState>,
    _admin: Admin,
    _ready: Ready,
    Path(id): Path<String>,
    Query(query): Query<ClipQuery>,
    headers: HeaderMap,
    body: Body,
) -> ApiResult {
    query.check()?;
    // A rig at its clip limit is refused before its body is read.
    check_clip_count(&*state.rig(&id)?, 1, state.config.max_clips)?;
    let ct = checked_content_type(&headers, "text/csv, application/json or model/gltf-binary")?;
    let _slot = state.uploads.acquire().await.map_err(ApiError::internal)?;
    let budget = state.op_budget();
    let bytes = upload_body(&state, &headers, body, &budget).await?;
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
    let mapping = match query.mapping.as_deref() {
        None => None,
        Some(_) if !matches!(source, ClipSource::Csv) => {
            return Err(ApiError::bad_request(
                "bad_query",
                "?mapping= applies to CSV clips, whose columns are the mapping's sources",
            ));
        }
        Some(m) => Some((m.to_string(), mapping_spec(&base, &state.registry.maps, m)?)),
    };
    let options = ClipOptions {
        fps: query.fps.unwrap_or(crowdmorph_core::rig::DEFAULT_FPS),
        ignore_unknown: query.ignore_unknown,
        budget: Some(budget.clone()),
    };
    let name = query.name;
    let snapshot = base.clone();
    let clip_error = clip_error(&state);
    let imports = blocking(move || {
        let rig = snapshot.rig();
        let mut imports = match source {
            ClipSource::Csv => match &mapping {
                None => named_clip(
                    crowdmorph_import::clip_from_csv,
                    rig,
                    name,
                    &bytes,
                    &options,
                ),
                Some((m, spec)) => {
                    let mapped = mapped_csv(&snapshot, m, spec, &bytes, &options)?;
                    named_clip(
                        crowdmorph_import::clip_from_csv,
                        rig,
                        name,
                        &mapped,
                        &options,
                    )
                }
            },
            ClipSource::Json => named_clip(
                crowdmorph_import::clip_from_json,
                rig,
                name,
                &bytes,
                &options,
            ),
            ClipSource::Gltf => gltf_clips(rig, name, &bytes, &options),
        }?;
        let budget = options
            .budget
            .as_deref()
            .ok_or_else(|| ApiError::internal("a clip upload without its budget"))?;
        for import in &mut imports {
            super::rigs::stored_form(
                rig,
                std::slice::from_mut(&mut import.clip),
                clip_error,
                budget,
            )?;
        }
        Ok(imports)
    })
    .await?;
    let _admin = state.admin.lock().await;
    // Re-read under the lock: another change may have landed since.
    let entry = state.rig(&id)?;
    same_rig(&entry, &base)?;
    check_clip_count(&entry, imports.len(), state.config.max_clips)?;
    let engine = state.engine.clone();
    let current = entry.clone();
    let merged = blocking(move || merge_clips(&engine, &current, imports)).await?;
    // The new clips go to a clip file of their own: the rig's record is not rewritten.
    let names: Vec<String> = merged.added.iter().map(|c| c.name.clone()).collect();
    let seq = entry.layout.next_seq();
    persist_clips(
        &state,
        &id,
        seq,
        merged.rig.clone(),
        clips_named(&merged.rig, &names),
    )
    .await?;
    let mut layout = entry.layout.clone();
    layout.files.push((seq, names));
    // The new generation holds the old one's charge plus the new tables.
    state.registry.insert(Arc::new(entry.successor(
        merged.prepared,
        merged.qbox,
        layout,
        state.registry.generation(),
        Some(budget.keep(merged.table_bytes)),
    )));
    drop(budget);
    crowdmorph_core::budget::return_freed_memory();
    tracing::info!(rig = %id, clips = merged.added.len(), ignored = merged.ignored.len(), "clips added");
    Accept::of(&headers).reply(
        StatusCode::CREATED,
        &ClipUpload {
            rig: id,
            added: merged.added,
            ignored: merged.ignored,
        },
    )
}

impl ClipQuery {
    /// A 400 for a malformed `?name=` or `?fps=`, before any of the body is read.
    fn check(&self) -> Result<(), ApiError> {
        check_name("clip", self.name.as_deref())?;
        if let Some(fps) = self.fps
            && !(fps.is_finite() && fps > 0.0 && fps <= 1000.0)
        {
            return Err(ApiError::bad_request(
                "invalid_fps",
                format!("fps {fps} must be in (0, 1000]"),
            ));
        }
        Ok(())
    }
}

/// An importer of one named clip: CSV (a frame a row, a target a column) or JSON
/// (`{"fps", "targets", "weights"}`).
type ClipReader = fn(&Rig, &str, &[u8], &ClipOptions) -> Result<ClipImport, ImportError>;

/// The one clip of a CSV or JSON body, named by `?name=`.
fn named_clip(
    read: ClipReader,
    rig: &Rig,
    name: Option<String>,
    bytes: &[u8],
    options: &ClipOptions,
) -> Result<Vec<ClipImport>, ApiError> {
    let name = name.as_deref().unwrap_or("clip");
    let clip = read(rig, name, bytes, options).map_err(clip_import_error)?;
    Ok(vec![clip])
}

/// A CSV clip whose columns are mapping `name`'s sources, rewritten onto the rig's targets
/// (`crowdmorph_import::mapped`): each row through the mapping, a target a row does not set
/// at the rig's default weight. What it builds is charged to the upload's budget.
fn mapped_csv(
    entry: &RigEntry,
    name: &str,
    spec: &NamedMapping,
    bytes: &[u8],
    options: &ClipOptions,
) -> Result<Vec<u8>, ApiError> {
    let rig = entry.rig();
    let budget = options
        .budget
        .as_deref()
        .ok_or_else(|| ApiError::internal("a clip upload without its budget"))?;
    let held = LiveNames::bytes(rig) + resolved_bytes(spec, rig) + 64 * rig.targets.len() as u64;
    budget
        .charge(held, || format!("mapping {name:?} for a CSV clip"))
        .map_err(|e| clip_import_error(ImportError::Budget(e)))?;
    let names = LiveNames::new(rig);
    let resolved = resolve_mapping(entry, &names, name, spec)?;
    // One column per target name the mapping reaches (channels sharing a name get one).
    let mut targets: Vec<String> = Vec::new();
    let mut column: Vec<(u32, usize)> = Vec::new();
    for c in resolved.channels() {
        let t = &rig.targets[c as usize];
        let at = targets.iter().position(|n| n == t).unwrap_or_else(|| {
            targets.push(t.clone());
            targets.len() - 1
        });
        column.push((c, at));
    }
    let defaults: Vec<f32> = column
        .iter()
        .map(|&(c, _)| rig.default_weights[c as usize])
        .collect();
    let mut out = Vec::new();
    let mapped = crowdmorph_import::mapped::map_csv(
        bytes,
        budget,
        &|n| resolved.is_source(n),
        &targets,
        &mut |pairs, values| {
            for (&(_, at), &d) in column.iter().zip(&defaults) {
                values[at] = d;
            }
            resolved.map(pairs, &mut out).map_err(|e| e.message)?;
            for &(c, w) in &out {
                if let Ok(k) = column.binary_search_by_key(&c, |p| p.0) {
                    values[column[k].1] = w;
                }
            }
            Ok(())
        },
    )
    .map_err(clip_import_error);
    budget.release(held);
    mapped
}

/// Every animation of a glTF file: named after the animation, or `?name=` for a file with
/// one, `NAME.<animation>` for several.
fn gltf_clips(
    rig: &Rig,
    name: Option<String>,
    bytes: &[u8],
    options: &ClipOptions,
) -> Result<Vec<ClipImport>, ApiError> {
    let mut clips =
        crowdmorph_import::clips_from_gltf(rig, bytes, options).map_err(clip_import_error)?;
    let single = clips.len() == 1;
    for c in &mut clips {
        c.clip.name = match (&name, single) {
            (Some(n), true) => n.clone(),
            (Some(n), false) => format!("{n}.{}", sanitize_id(&c.clip.name)),
            (None, _) => sanitize_id(&c.clip.name),
        };
    }
    Ok(clips)
}

/// 413 `too_many_clips` when adding `adding` clips would give the rig more than `max`
/// (`--max-clips`): a graph built from the clips compares every pair of them.
pub(crate) fn check_clip_count(
    entry: &RigEntry,
    adding: usize,
    max: usize,
) -> Result<(), ApiError> {
    let have = entry.rig().clips.len();
    if have.saturating_add(adding) <= max {
        return Ok(());
    }
    Err(ApiError::new(
        StatusCode::PAYLOAD_TOO_LARGE,
        "too_many_clips",
        format!(
            "rig {:?} has {have} clips; {adding} more would pass --max-clips ({max}); DELETE \
             some first",
            entry.id
        ),
    ))
}

/// A 409 unless `entry` is still the rig the clips were imported against (not deleted and
/// uploaded again with other targets).
fn same_rig(entry: &RigEntry, base: &RigEntry) -> Result<(), ApiError> {
    if Arc::ptr_eq(&entry.rig().primitives, &base.rig().primitives)
        && entry.rig().targets == base.rig().targets
    {
        return Ok(());
    }
    Err(ApiError::new(
        StatusCode::CONFLICT,
        "rig_changed",
        format!(
            "rig {:?} was replaced while its clips were imported; upload them again",
            entry.id
        ),
    ))
}

/// A rig generation with new clips, prepared for the engine.
struct Merged {
    rig: Arc<Rig>,
    prepared: PreparedRig,
    qbox: Quantization,
    added: Vec<ClipInfo>,
    ignored: Vec<String>,
    /// Bytes of the new weight tables, kept in the rig's charge.
    table_bytes: u64,
}

/// `current` with `imports` appended: a 409 for a name taken, a 400 for a table the rig
/// cannot take; the unknown target names, each once.
fn merge_clips(
    engine: &Engine,
    current: &RigEntry,
    imports: Vec<ClipImport>,
) -> Result<Merged, ApiError> {
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
        added.push(ClipInfo {
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
    let rig = Arc::new(new);
    let prepared = engine
        .update_clips(&current.prepared, rig.clone())
        .map_err(|e| prepare_error(e, "clip_too_large"))?;
    let qbox = quantization_box(&rig);
    Ok(Merged {
        rig,
        prepared,
        qbox,
        added,
        ignored,
        table_bytes,
    })
}

pub async fn list_clips(
    State(state): State<AppState>,
    _ready: Ready,
    Path(id): Path<String>,
    accept: Accept,
) -> ApiResult {
    let entry = state.rig(&id)?;
    accept.reply(
        StatusCode::OK,
        &ClipList {
            rig: id,
            clips: clip_infos(entry.rig()),
        },
    )
}

pub async fn get_clip(
    State(state): State<AppState>,
    _ready: Ready,
    Path((id, clip)): Path<(String, String)>,
    accept: Accept,
) -> ApiResult {
    let entry = state.rig(&id)?;
    let ci = entry
        .clip_index(&clip)
        .ok_or_else(|| unknown_clip(&entry, &clip))?;
    accept.reply(StatusCode::OK, &clip_info(&entry.rig().clips[ci]))
}

pub async fn delete_clip(
    State(state): State<AppState>,
    _admin: Admin,
    _ready: Ready,
    Path((id, clip)): Path<(String, String)>,
) -> ApiResult {
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
    let name = clip.clone();
    let (rig, prepared, qbox, had_texture) =
        changed_rig(&state, &entry, "clip_too_large", move |new| {
            new.clips.remove(ci);
            // Its animated texture goes with it: nothing plays it any more, and a later clip of
            // the same name must not inherit it.
            Ok(without_clip_texture(new, &name))
        })
        .await?;
    // Only the file that held the clip is rewritten: its clip file, or the rig's record — and
    // the record first when it held the clip's texture (a stop between the two leaves the
    // clip without its texture, never a texture whose clip is gone).
    let layout = entry.layout.without(&clip);
    match entry.layout.file_of(&clip) {
        Some(seq) => {
            if had_texture {
                persist_record(&state, &id, rig.clone(), entry.builtin, &layout).await?;
            }
            let rest = layout
                .files
                .iter()
                .find(|f| f.0 == seq)
                .map(|f| clips_named(&rig, &f.1))
                .unwrap_or_default();
            persist_clips(&state, &id, seq, rig.clone(), rest).await?;
        }
        None => {
            persist_record(&state, &id, rig.clone(), entry.builtin, &layout).await?;
        }
    }
    state.registry.insert(Arc::new(entry.successor(
        prepared,
        qbox,
        layout,
        state.registry.generation(),
        None,
    )));
    crowdmorph_core::budget::return_freed_memory();
    tracing::info!(rig = %id, clip = %clip, "clip deleted");
    Ok(StatusCode::NO_CONTENT.into_response())
}

/// What `PUT /v1/rigs/{id}/clips/{clip}/texture` answers.
#[derive(serde::Serialize)]
struct TextureUpload {
    rig: String,
    clip: String,
    material: u32,
    width: u32,
    height: u32,
    components: usize,
    /// Host bytes the texture holds (charged to the rig).
    bytes: u64,
}

/// A 400 `invalid_texture`.
fn invalid_texture(message: impl std::fmt::Display) -> ApiError {
    ApiError::bad_request("invalid_texture", message.to_string())
}

/// `PUT /v1/rigs/{id}/clips/{clip}/texture`: a clip's animated base colour in the byte form
/// of `crowdmorph clips compress-texture` (`AnimatedTexture::to_bytes`, proto/README.md). The
/// body is read under the upload's budget, its header checked and its decoded size charged
/// before anything is allocated (a header that declares more than the body holds is a 400,
/// more than `--max-upload-memory` a 413 `texture_too_large`); then, under the lock that
/// serializes rig changes, the rig's next generation carries it (replacing the clip's earlier
/// one), is stored and published. Its arrays stay charged to the rig until the rig drops it.
pub async fn put_clip_texture(
    State(state): State<AppState>,
    _admin: Admin,
    _ready: Ready,
    Path((id, clip)): Path<(String, String)>,
    headers: HeaderMap,
    body: Body,
) -> ApiResult {
    {
        let entry = state.rig(&id)?;
        entry
            .clip_index(&clip)
            .ok_or_else(|| unknown_clip(&entry, &clip))?;
    }
    checked_content_type(&headers, "application/octet-stream")?;
    let _slot = state.uploads.acquire().await.map_err(ApiError::internal)?;
    let budget = state.op_budget();
    let bytes = upload_body(&state, &headers, body, &budget).await?;
    let declared = AnimatedTexture::declared_bytes(&bytes).map_err(invalid_texture)?;
    budget
        .charge(declared, || {
            format!("an animated texture of {declared} bytes")
        })
        .map_err(|e| ApiError::budget(e, "texture_too_large"))?;
    let name = clip.clone();
    let texture =
        blocking(move || AnimatedTexture::from_bytes(&name, &bytes).map_err(invalid_texture))
            .await?;
    let _admin = state.admin.lock().await;
    // Re-read under the lock: another change may have landed since.
    let entry = state.rig(&id)?;
    let ci = entry
        .clip_index(&clip)
        .ok_or_else(|| unknown_clip(&entry, &clip))?;
    let frames = entry.rig().clips[ci].frames;
    if texture.frames != frames {
        return Err(invalid_texture(format!(
            "{} frames of coefficients for clip {clip:?} of {frames} frames",
            texture.frames
        )));
    }
    let reply = TextureUpload {
        rig: id.clone(),
        clip: clip.clone(),
        material: texture.material,
        width: texture.width,
        height: texture.height,
        components: texture.layers(),
        bytes: texture.bytes(),
    };
    let kept = budget.keep(declared);
    publish_appearance(
        &state,
        &entry,
        move |new| {
            let mut a = new.appearance.as_deref().cloned().unwrap_or_default();
            if texture.material as usize >= a.materials.len() {
                return Err(invalid_texture(format!(
                    "material {} of a rig with {} materials",
                    texture.material,
                    a.materials.len()
                )));
            }
            a.clip_textures.retain(|t| t.clip != texture.clip);
            a.clip_textures.push(Arc::new(texture));
            new.appearance = Some(Arc::new(a));
            new.validate().map_err(invalid_texture)
        },
        Some(kept),
    )
    .await?;
    drop(budget);
    crowdmorph_core::budget::return_freed_memory();
    tracing::info!(rig = %id, clip = %clip, components = reply.components, "clip texture set");
    Accept::of(&headers).reply(StatusCode::OK, &reply)
}

/// Publishes `entry`'s next generation with `change` made to a copy of its rig's appearance
/// (under the rig lock the caller holds): prepared again (the engine re-uses what did not
/// change), stored in the rig's record and registered, taking over `extra` (what the change
/// reserved). A change the engine cannot fit is a 413 `texture_too_large`.
async fn publish_appearance(
    state: &AppState,
    entry: &Arc<RigEntry>,
    change: impl FnOnce(&mut Rig) -> Result<(), ApiError> + Send + 'static,
    extra: Option<crowdmorph_core::budget::Charge>,
) -> Result<(), ApiError> {
    let (rig, prepared, qbox, ()) = changed_rig(state, entry, "texture_too_large", change).await?;
    persist_record(state, &entry.id, rig, entry.builtin, &entry.layout).await?;
    state.registry.insert(Arc::new(entry.successor(
        prepared,
        qbox,
        entry.layout.clone(),
        state.registry.generation(),
        extra,
    )));
    Ok(())
}

/// `entry`'s rig with `change` made to a copy, prepared (the engine re-uses what did not
/// change) on a blocking thread, with its q16 box and what `change` returned. A change the
/// engine cannot fit is a 413 `too_large`.
async fn changed_rig<T: Send + 'static>(
    state: &AppState,
    entry: &Arc<RigEntry>,
    too_large: &'static str,
    change: impl FnOnce(&mut Rig) -> Result<T, ApiError> + Send + 'static,
) -> Result<(Arc<Rig>, PreparedRig, Quantization, T), ApiError> {
    let engine = state.engine.clone();
    let current = entry.clone();
    blocking(move || {
        let mut new = current.rig().clone();
        let out = change(&mut new)?;
        let new = Arc::new(new);
        let prepared = engine
            .update_clips(&current.prepared, new.clone())
            .map_err(|e| prepare_error(e, too_large))?;
        let qbox = quantization_box(&new);
        Ok((new, prepared, qbox, out))
    })
    .await
}

/// Removes clip `clip`'s animated texture from `rig`'s appearance; whether it had one.
fn without_clip_texture(rig: &mut Rig, clip: &str) -> bool {
    let Some(a) = rig.appearance.as_deref() else {
        return false;
    };
    if !a.clip_textures.iter().any(|t| t.clip == clip) {
        return false;
    }
    let mut a = a.clone();
    a.clip_textures.retain(|t| t.clip != clip);
    rig.appearance = Some(Arc::new(a));
    true
}

/// Clip `clip`'s animated texture in `entry`, or the 404 that names what exists.
fn clip_texture(entry: &RigEntry, id: &str, clip: &str) -> Result<Arc<AnimatedTexture>, ApiError> {
    entry
        .clip_index(clip)
        .ok_or_else(|| unknown_clip(entry, clip))?;
    entry
        .rig()
        .appearance
        .as_deref()
        .and_then(|a| a.clip_textures.iter().find(|t| t.clip == clip))
        .cloned()
        .ok_or_else(|| {
            ApiError::not_found(
                "unknown_texture",
                format!(
                    "clip {clip:?} of rig {id:?} has no animated texture \
                     (PUT /v1/rigs/{id}/clips/{clip}/texture sets one)"
                ),
            )
        })
}

/// `GET /v1/rigs/{id}/clips/{clip}/texture`: the clip's animated texture in the byte form
/// `PUT` takes (`AnimatedTexture::to_bytes`, proto/README.md), so that a texture can be
/// fetched, kept and put back or onto another rig. Its bytes are charged to the queue memory
/// before they are written; the `ETag` is their checksum (a 304 to `If-None-Match`).
pub async fn get_clip_texture(
    State(state): State<AppState>,
    _ready: Ready,
    Path((id, clip)): Path<(String, String)>,
    headers: HeaderMap,
) -> ApiResult {
    let entry = state.rig(&id)?;
    let texture = clip_texture(&entry, &id, &clip)?;
    let names: u64 = texture.regions.iter().map(|r| r.name.len() as u64).sum();
    let held = state.queue_memory.reserve(texture.bytes() + 64 + names)?;
    let bytes = blocking(move || Ok(texture.to_bytes())).await?;
    let tag = format!("{:08x}-{}", crc32fast::hash(&bytes), bytes.len());
    let validator = Validator::new(&tag, None)?;
    if let Some(not_modified) = validator.not_modified(&headers) {
        return Ok(not_modified);
    }
    Ok(validator.respond("application/octet-stream", bytes, held))
}

/// `DELETE /v1/rigs/{id}/clips/{clip}/texture`: the clip plays with its material's own base
/// colour again; the rig's next generation is stored and published without the texture, and
/// its arrays are released with the earlier generation.
pub async fn delete_clip_texture(
    State(state): State<AppState>,
    _admin: Admin,
    _ready: Ready,
    Path((id, clip)): Path<(String, String)>,
) -> ApiResult {
    let _admin = state.admin.lock().await;
    let entry = state.rig(&id)?;
    clip_texture(&entry, &id, &clip)?;
    let name = clip.clone();
    publish_appearance(
        &state,
        &entry,
        move |new| {
            without_clip_texture(new, &name);
            Ok(())
        },
        None,
    )
    .await?;
    crowdmorph_core::budget::return_freed_memory();
    tracing::info!(rig = %id, clip = %clip, "clip texture deleted");
    Ok(StatusCode::NO_CONTENT.into_response())
}
