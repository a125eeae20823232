//! `/v1/rigs/{id}/masks`: a rig's named masks, which layers name (`"mask": "name"`, looked up
//! before the built-in `upper_face`, `lower_face`, `eyes`, `brows`, `mouth`). [`put_mask`]
//! checks a mask's names against the rig as a layer's inline mask is checked and stores it
//! with the rig's motion graphs; [`list_masks`], [`get_mask`], [`delete_mask`]. A session head
//! whose layer names a mask that is deleted is missing from later ticks, as one whose graph
//! or clip is deleted.

use axum::extract::{Path, State};
use axum::http::StatusCode;
use axum::response::IntoResponse;
use crowdmorph_proto::{Mask, MaskInfo, MaskList};

use crate::admission::layers::check_mask;
use crate::admission::mapping::MAX_MAP_NAME;
use crate::admission::names::LiveNames;
use crate::admission::{Decoded, Priced};
use crate::http::{Accept, Admin, ApiError, ApiResult, Ready};
use crate::registry::valid_id;
use crate::rig_maps::{MAX_MASKS_PER_RIG, NamedMaps};
use crate::services::Parts;
use crate::services::persist::persist_maps;
use crate::state::AppState;
use crowdmorph_core::rig::quoted_name;

/// A mask's names, held until it is checked and stored.
impl Priced for Mask {
    fn price(&self, _: Accept) -> u64 {
        match self {
            Mask::Names(n) => {
                (n.capacity() * size_of::<String>() + n.iter().map(String::capacity).sum::<usize>())
                    as u64
            }
            Mask::Weights(w) => {
                (w.capacity() * size_of::<(String, f32)>()
                    + w.iter().map(|(n, _)| n.capacity()).sum::<usize>()) as u64
            }
            Mask::Named(n) => n.capacity() as u64,
        }
    }
}

fn invalid(message: String) -> ApiError {
    ApiError::bad_request("invalid_mask", message)
}

/// 404 `unknown_mask`, listing (at most 20 of) the rig's masks.
fn unknown_mask(state: &AppState, rig: &str, name: &str) -> ApiError {
    let masks = state.registry.maps.masks(rig);
    let have: Vec<&str> = masks.keys().map(String::as_str).take(20).collect();
    ApiError::not_found(
        "unknown_mask",
        format!(
            "rig {rig:?} has no mask {} (masks: {})",
            quoted_name(name),
            have.join(", ")
        ),
    )
}

/// 400 `invalid_name` for a malformed mask name.
fn check_name(name: &str) -> Result<(), ApiError> {
    if valid_id(name) {
        return Ok(());
    }
    Err(ApiError::bad_request(
        "invalid_name",
        format!(
            "mask name {} must be 1–64 characters of A-Z a-z 0-9 . _ - and not start with a dot",
            quoted_name(name)
        ),
    ))
}

/// The mask's own checks: a list or weights (not the name of another mask), each name at
/// most [`MAX_MAP_NAME`] bytes.
fn check_shape(mask: &Mask) -> Result<(), ApiError> {
    let names: Vec<&str> = match mask {
        Mask::Names(n) => n.iter().map(String::as_str).collect(),
        Mask::Weights(w) => w.iter().map(|(n, _)| n.as_str()).collect(),
        Mask::Named(n) => {
            return Err(invalid(format!(
                "the body is the name {}; a rig's mask is a list of target names or an object \
                 of names to weights in [0, 1]",
                quoted_name(n)
            )));
        }
    };
    match names.iter().find(|n| n.len() > MAX_MAP_NAME) {
        Some(n) => Err(invalid(format!(
            "a name is {} bytes long; a name has at most {MAX_MAP_NAME}",
            n.len()
        ))),
        None => Ok(()),
    }
}

/// `PUT /v1/rigs/{id}/masks/{name}`: checks the name and the mask against the rig (every name
/// the rig's or ARKit's, weights in [0, 1]), stores it with the rig and answers with it.
pub async fn put_mask(
    State(state): State<AppState>,
    _admin: Admin,
    _ready: Ready,
    accept: Accept,
    Path((id, name)): Path<(String, String)>,
    Decoded(req): Decoded<Mask>,
) -> ApiResult {
    let (mask, _decoded) = req.into_parts();
    let entry = state.rig(&id)?;
    check_name(&name)?;
    check_shape(&mask)?;
    let rig = entry.rig();
    let _checking = state
        .queue_memory
        .reserve(LiveNames::bytes(rig) + crate::admission::layers::mask_bytes(rig))?;
    check_mask(&LiveNames::new(rig), &mask).map_err(|e| match e.code {
        "invalid_layer" => invalid(e.message),
        _ => e,
    })?;
    // Stored first, then served: a write the store refuses (409, 503) changes nothing here.
    let _admin = state.admin.lock().await;
    let now = state.registry.maps.of(&id);
    if !now.masks.contains_key(&name) && now.masks.len() >= MAX_MASKS_PER_RIG {
        return Err(invalid(format!(
            "rig {id:?} has {} masks, the most a rig may have",
            now.masks.len()
        )));
    }
    let mut masks = (*now.masks).clone();
    masks.insert(name.clone(), mask.clone());
    let next = NamedMaps {
        masks: masks.into(),
        ..now
    };
    persist_maps(&state, &id, next.clone()).await?;
    state.registry.maps.set(&id, next);
    accept.reply(
        StatusCode::OK,
        &MaskInfo {
            rig: id,
            name,
            mask,
        },
    )
}

/// `GET /v1/rigs/{id}/masks`.
pub async fn list_masks(
    State(state): State<AppState>,
    accept: Accept,
    Path(id): Path<String>,
) -> ApiResult {
    let _entry = state.rig(&id)?;
    let masks = state
        .registry
        .maps
        .masks(&id)
        .iter()
        .map(|(name, mask)| MaskInfo {
            rig: id.clone(),
            name: name.clone(),
            mask: mask.clone(),
        })
        .collect();
    accept.reply(StatusCode::OK, &MaskList { masks })
}

/// `GET /v1/rigs/{id}/masks/{name}`.
pub async fn get_mask(
    State(state): State<AppState>,
    accept: Accept,
    Path((id, name)): Path<(String, String)>,
) -> ApiResult {
    let _entry = state.rig(&id)?;
    let mask = state
        .registry
        .maps
        .masks(&id)
        .get(&name)
        .cloned()
        .ok_or_else(|| unknown_mask(&state, &id, &name))?;
    accept.reply(
        StatusCode::OK,
        &MaskInfo {
            rig: id,
            name,
            mask,
        },
    )
}

/// `DELETE /v1/rigs/{id}/masks/{name}`: layers naming it then get the built-in mask of that
/// name, if there is one, else 400 (crowd frames); session heads naming it are missing from
/// later ticks.
pub async fn delete_mask(
    State(state): State<AppState>,
    _admin: Admin,
    Path((id, name)): Path<(String, String)>,
) -> ApiResult {
    let _entry = state.rig(&id)?;
    let _admin = state.admin.lock().await;
    let now = state.registry.maps.of(&id);
    if !now.masks.contains_key(&name) {
        return Err(unknown_mask(&state, &id, &name));
    }
    let mut masks = (*now.masks).clone();
    masks.remove(&name);
    let next = NamedMaps {
        masks: masks.into(),
        ..now
    };
    // Stored first, then removed here: a delete the store refuses changes nothing.
    persist_maps(&state, &id, next.clone()).await?;
    state.registry.maps.set(&id, next);
    Ok(StatusCode::NO_CONTENT.into_response())
}
