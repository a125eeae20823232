//! `/v1/rigs/{id}/mappings`: a rig's named mappings from a producer's names to its targets
//! (`crowdmorph_core::rig::mapping`). The built-in `arkit`, `a2f` and `oculus-visemes` need no
//! `PUT`, and `vrm` is read from the rig's VRM file when it is uploaded; those names are
//! reserved. [`put_mapping`] resolves a mapping against the rig (names, gains, offsets,
//! clamps) before it is stored with the rig's motion graphs; [`list_mappings`],
//! [`get_mapping`], [`delete_mapping`]. Crowd heads name one (`"mapping": "a2f"`), as do CSV
//! clips (`?mapping=`); a session head's live input through a deleted mapping is refused.

use axum::extract::{Path, State};
use axum::http::StatusCode;
use axum::response::IntoResponse;
use crowdmorph_core::rig::{BUILTIN_MAPPINGS, builtin_mapping, quoted_name};
use crowdmorph_proto::{Mapping, MappingInfo, MappingList};

use crate::admission::mapping::{
    mapping_bytes, mapping_spec, resolve_mapping, resolved_bytes, to_core, to_wire, unknown_mapping,
};
use crate::admission::names::LiveNames;
use crate::admission::{Decoded, Priced};
use crate::http::{Accept, Admin, ApiError, ApiResult, Ready};
use crate::registry::valid_id;
use crate::rig_maps::{MAX_MAPPINGS_PER_RIG, NamedMaps};
use crate::services::Parts;
use crate::services::persist::persist_maps;
use crate::state::AppState;

/// A mapping's entries and names, held until it is checked and stored.
impl Priced for Mapping {
    fn price(&self, _: Accept) -> u64 {
        mapping_bytes(self)
    }
}

/// 400 `invalid_name` for a malformed or reserved mapping name.
fn check_name(name: &str) -> Result<(), ApiError> {
    if !valid_id(name) {
        return Err(ApiError::bad_request(
            "invalid_name",
            format!(
                "mapping name {} must be 1–64 characters of A-Z a-z 0-9 . _ - and not start \
                 with a dot",
                quoted_name(name)
            ),
        ));
    }
    if BUILTIN_MAPPINGS.contains(&name) {
        return Err(ApiError::bad_request(
            "invalid_name",
            format!(
                "mapping {} is built in ({}); choose another name",
                quoted_name(name),
                BUILTIN_MAPPINGS.join(", ")
            ),
        ));
    }
    Ok(())
}

/// `PUT /v1/rigs/{id}/mappings/{name}`: checks the name, resolves the mapping against the rig
/// (400 `invalid_mapping`, `unknown_targets`), stores it with the rig and answers with it.
pub async fn put_mapping(
    State(state): State<AppState>,
    _admin: Admin,
    _ready: Ready,
    accept: Accept,
    Path((id, name)): Path<(String, String)>,
    Decoded(req): Decoded<Mapping>,
) -> ApiResult {
    let (mapping, _decoded) = req.into_parts();
    let entry = state.rig(&id)?;
    check_name(&name)?;
    let spec = to_core(&mapping);
    let rig = entry.rig();
    let _checking = state
        .queue_memory
        .reserve(spec.heap_bytes() + LiveNames::bytes(rig) + resolved_bytes(&spec, rig))?;
    resolve_mapping(&entry, &LiveNames::new(rig), &name, &spec)?;
    // Stored first, then served: a write the store refuses (409, 503) changes nothing here.
    let _admin = state.admin.lock().await;
    let now = state.registry.maps.of(&id);
    if !now.mappings.contains_key(&name) && now.mappings.len() >= MAX_MAPPINGS_PER_RIG {
        return Err(ApiError::bad_request(
            "invalid_mapping",
            format!(
                "rig {id:?} has {} mappings, the most a rig may have",
                now.mappings.len()
            ),
        ));
    }
    let mut mappings = (*now.mappings).clone();
    mappings.insert(name.clone(), mapping.clone());
    let next = NamedMaps {
        mappings: mappings.into(),
        ..now
    };
    persist_maps(&state, &id, next.clone()).await?;
    state.registry.maps.set(&id, next);
    accept.reply(
        StatusCode::OK,
        &MappingInfo {
            rig: id,
            name,
            builtin: false,
            mapping,
        },
    )
}

/// `GET /v1/rigs/{id}/mappings`: the built-in mappings (with the rig's `vrm` when it has
/// one), then the rig's own by name.
pub async fn list_mappings(
    State(state): State<AppState>,
    accept: Accept,
    Path(id): Path<String>,
) -> ApiResult {
    let _entry = state.rig(&id)?;
    let own = state.registry.maps.of(&id).mappings;
    let mut mappings: Vec<MappingInfo> = BUILTIN_MAPPINGS
        .iter()
        .filter_map(|&b| {
            let mapping = match builtin_mapping(b) {
                Some(m) => to_wire(&m),
                None => own.get(b)?.clone(),
            };
            Some(MappingInfo {
                rig: id.clone(),
                name: b.to_string(),
                builtin: true,
                mapping,
            })
        })
        .collect();
    mappings.extend(
        own.iter()
            .filter(|(n, _)| !BUILTIN_MAPPINGS.contains(&n.as_str()))
            .map(|(n, m)| MappingInfo {
                rig: id.clone(),
                name: n.clone(),
                builtin: false,
                mapping: m.clone(),
            }),
    );
    accept.reply(StatusCode::OK, &MappingList { mappings })
}

/// `GET /v1/rigs/{id}/mappings/{name}`.
pub async fn get_mapping(
    State(state): State<AppState>,
    accept: Accept,
    Path((id, name)): Path<(String, String)>,
) -> ApiResult {
    let entry = state.rig(&id)?;
    let spec = mapping_spec(&entry, &state.registry.maps, &name)?;
    accept.reply(
        StatusCode::OK,
        &MappingInfo {
            rig: id,
            builtin: BUILTIN_MAPPINGS.contains(&name.as_str()),
            name,
            mapping: to_wire(&spec),
        },
    )
}

/// `DELETE /v1/rigs/{id}/mappings/{name}` (a built-in one cannot be deleted, but a rig's
/// `vrm` can).
pub async fn delete_mapping(
    State(state): State<AppState>,
    _admin: Admin,
    Path((id, name)): Path<(String, String)>,
) -> ApiResult {
    let entry = state.rig(&id)?;
    if builtin_mapping(&name).is_some() {
        return Err(ApiError::bad_request(
            "invalid_name",
            format!(
                "mapping {} is built in and cannot be deleted",
                quoted_name(&name)
            ),
        ));
    }
    let _admin = state.admin.lock().await;
    let now = state.registry.maps.of(&id);
    if !now.mappings.contains_key(&name) {
        return Err(unknown_mapping(&entry, &state.registry.maps, &name));
    }
    let mut mappings = (*now.mappings).clone();
    mappings.remove(&name);
    let next = NamedMaps {
        mappings: mappings.into(),
        ..now
    };
    // Stored first, then removed here: a delete the store refuses changes nothing.
    persist_maps(&state, &id, next.clone()).await?;
    state.registry.maps.set(&id, next);
    Ok(StatusCode::NO_CONTENT.into_response())
}
