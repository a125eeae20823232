//! A rig's expression layers for clients that sum them themselves (the browser viewer):
//! `GET /v1/rigs/{id}/layers` (per material, its layers' kinds, where each reads its
//! coefficient and the sizes of its levels) and `GET /v1/rigs/{id}/layers/{m}` (material `m`'s
//! texels: little-endian binary16 RGBA, layer by layer, each layer's levels largest first,
//! rows top to bottom).
//!
//! The texels come from `crowdmorph_engine::render::appearance::layer_texels`, the function
//! the renderer uploads from, so a client sums exactly what the server's render sums. A
//! coefficient is read from the compact per-head vector a session viewer that asked for
//! `layers` is sent (`StreamMessage` variant 4): the entries of
//! `crowdmorph_core::rig::layer_inputs` some layer reads
//! (`crowdmorph_engine::render::appearance::layer_input_indices`), which `input` indexes.
//!
//! The texels change only with the rig, so their `ETag` is the rig's generation and material:
//! the `texels` URI `/layers` gives carries it as `?v=`, and a request with a matching `v` is
//! answered `Cache-Control: immutable` (a viewer fetches them once per rig generation); without
//! it, `no-cache` with the `ETag` (and a 304 to `If-None-Match`), as `/textures/{i}` does.

use axum::extract::{Path, State};
use axum::http::HeaderMap;
use crowdmorph_core::rig::{MAX_ANIMATED_SIZE, Rig};
use crowdmorph_engine::render::appearance::{
    LayerPlan, layer_input_indices, layer_plan, layer_texels,
};

use crate::http::cache::Validator;
use crate::http::{self, ApiError, ApiResult, Query, Ready};
use crate::routes::appearance::TextureQuery;
use crate::services::Parts;
use crate::state::AppState;

/// The largest texture the layers are planned for: the renderer's device allows at least
/// this (images are imported at most `--max-texture-size` a side, animated textures at most
/// [`MAX_ANIMATED_SIZE`]), so the levels are the ones it uploads.
fn max_size(state: &AppState) -> u32 {
    state.config.max_texture_size.max(MAX_ANIMATED_SIZE)
}

/// The `ETag` token of material `m`'s texels in generation `generation`.
fn etag(generation: u64, m: usize) -> String {
    format!("g{generation}-m{m}")
}

/// Bytes of one material's entry in `/layers` besides its layers and levels (the rig id is
/// in its URI).
const MATERIAL_ENTRY_BYTES: u64 = 256;

/// Bytes of one layer's or one level's entry in `/layers`.
const LAYER_ENTRY_BYTES: u64 = 64;

/// Per material with layers, its index and plan.
fn plans(rig: &Rig, max_size: u32) -> Result<Vec<(usize, LayerPlan)>, ApiError> {
    let materials = rig.appearance.as_deref().map_or(0, |a| a.materials.len());
    let mut out = Vec::new();
    for m in 0..materials {
        if let Some(p) = layer_plan(rig, m, max_size).map_err(ApiError::internal)? {
            out.push((m, p));
        }
    }
    Ok(out)
}

/// `GET /v1/rigs/{id}/layers`: per material with layers, its level sizes, its layers (kind,
/// the index of its coefficient in a head's compact inputs, whether that is clamped to
/// [0, 1]) and the URI of its texels; and `inputs`, the length of a head's compact inputs.
pub async fn get_layers(
    State(state): State<AppState>,
    _ready: Ready,
    Path(id): Path<String>,
) -> ApiResult {
    let entry = state.rig(&id)?;
    let rig = entry.rig();
    // The JSON grows with the materials and their layers: charged to the queue memory (the
    // value and its text) until it is sent.
    let held = state
        .queue_memory
        .reserve(rig.appearance.as_deref().map_or(0, |a| {
            2 * (a.materials.len() as u64 * (MATERIAL_ENTRY_BYTES + id.len() as u64)
                + (a.target_textures.len() as u64
                    + a.clip_textures
                        .iter()
                        .map(|t| 1 + t.layers() as u64)
                        .sum::<u64>())
                    * LAYER_ENTRY_BYTES
                    * 2)
        }))?;
    let indices = layer_input_indices(rig);
    let mut materials = Vec::new();
    for (m, plan) in plans(rig, max_size(&state))? {
        let layers: Vec<serde_json::Value> = plan
            .kinds
            .iter()
            .zip(&plan.sources)
            .map(|(kind, source)| {
                // A layer whose target the rig does not have reads no input: always 0.
                let input = source.and_then(|(at, _)| indices.binary_search(&at).ok());
                serde_json::json!({
                    "kind": kind.name(),
                    "input": input,
                    "clamp": source.is_some_and(|(_, clamp)| clamp),
                })
            })
            .collect();
        let (width, height) = plan.levels[0];
        materials.push(serde_json::json!({
            "material": m,
            "width": width,
            "height": height,
            "levels": plan.levels.iter().map(|&(w, h)| [w, h]).collect::<Vec<_>>(),
            "layers": layers,
            "bytes": plan.bytes(),
            "texels": format!("/v1/rigs/{id}/layers/{m}?v={}", etag(entry.generation, m)),
        }));
    }
    let body = serde_json::json!({ "materials": materials, "inputs": indices.len() });
    Ok(http::body::json_held(&body, held))
}

/// `GET /v1/rigs/{id}/layers/{m}`: material `m`'s layer texels (see the module documentation).
pub async fn get_layer_texels(
    State(state): State<AppState>,
    _ready: Ready,
    Path((id, index)): Path<(String, String)>,
    Query(query): Query<TextureQuery>,
    headers: HeaderMap,
) -> ApiResult {
    let entry = state.rig(&id)?;
    let max_size = max_size(&state);
    let unknown = || {
        ApiError::not_found(
            "unknown_layers",
            format!(
                "rig {id:?} has no material {index:?} with layers (GET /v1/rigs/{id}/layers \
                 lists them)"
            ),
        )
    };
    let m = index.parse::<usize>().map_err(|_| unknown())?;
    let plan = layer_plan(entry.rig(), m, max_size)
        .map_err(ApiError::internal)?
        .ok_or_else(unknown)?;
    let validator = Validator::new(&etag(entry.generation, m), query.v.as_deref())?;
    if let Some(not_modified) = validator.not_modified(&headers) {
        return Ok(not_modified);
    }
    // The body, and while it is built one level of one layer in f32 four times over (the
    // level, the level it halves, the base it is against, the source's own level) plus its
    // binary16: charged before any of it is allocated; the body keeps its share until sent.
    let bytes = plan.bytes();
    let (w0, h0) = plan.levels[0];
    let work = u64::from(w0) * u64::from(h0) * (4 * 16 + 8);
    let mut held = state.queue_memory.reserve(bytes + work)?;
    let body = http::blocking(move || {
        let mut out = Vec::with_capacity(bytes as usize);
        layer_texels(entry.rig(), m, max_size, |l| {
            for t in l.texels {
                out.extend_from_slice(&t.to_le_bytes());
            }
        })
        .map_err(ApiError::internal)?;
        if out.len() as u64 != bytes {
            return Err(ApiError::internal(format!(
                "material {m}'s layers are {} bytes, planned {bytes}",
                out.len()
            )));
        }
        Ok(out)
    })
    .await?;
    held.keep(bytes);
    Ok(validator.respond("application/octet-stream", body, held))
}
