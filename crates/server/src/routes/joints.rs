//! `/v1/rigs/{id}/joint-map`: which clip columns turn a skinned rig's joints. [`get_joint_map`]
//! answers with the map in force (the rig's own, or the defaults for Ready Player Me and VRM
//! humanoid names); [`put_joint_map`] checks a map against the skeleton and makes it the rig's,
//! as a new generation, stored; [`delete_joint_map`] goes back to the defaults. Clips uploaded
//! afterwards are read with it (`crowdmorph_import::clips`); clips already there keep their
//! joint tables.

use std::sync::Arc;

use axum::extract::{Path, State};
use axum::http::StatusCode;
use crowdmorph_proto::{JointChannelSpec, JointMapInfo, JointMapSpec};

use crate::admission::{Decoded, Priced};
use crate::http::{Accept, Admin, ApiError, ApiResult, Ready, blocking};
use crate::registry::RigEntry;
use crate::services::Parts;
use crate::services::persist::next_generation;
use crate::services::persist::prepare_charged;
use crate::state::AppState;
use crowdmorph_core::rig::{JointChannel, JointMap, MAX_JOINT_CHANNELS, Rig};

/// Longest column name a map may hold.
const MAX_COLUMN: usize = 256;

/// A map's names, held until it is checked and installed.
impl Priced for JointMapSpec {
    fn price(&self, _: Accept) -> u64 {
        self.channels.capacity() as u64 * size_of::<JointChannelSpec>() as u64
            + self
                .channels
                .iter()
                .map(|c| c.column.capacity() as u64 + c.node.capacity() as u64)
                .sum::<u64>()
    }
}

/// The answer for `entry`'s map in force.
fn info(id: &str, rig: &Rig) -> JointMapInfo {
    let Some(sk) = &rig.skeleton else {
        return JointMapInfo {
            rig: id.to_string(),
            default: true,
            channels: Vec::new(),
        };
    };
    JointMapInfo {
        rig: id.to_string(),
        default: sk.map.is_none(),
        channels: sk
            .joint_map()
            .channels
            .iter()
            .map(|c| JointChannelSpec {
                column: c.column.clone(),
                node: sk.nodes[c.node as usize].name.clone(),
                axis: c.axis,
                scale: c.scale,
            })
            .collect(),
    }
}

fn invalid(message: String) -> ApiError {
    ApiError::bad_request("invalid_joint_map", message)
}

/// The map `spec` names, checked against `entry`'s skeleton.
fn resolve(entry: &RigEntry, spec: &JointMapSpec) -> Result<JointMap, ApiError> {
    let sk = entry.rig().skeleton.as_ref().ok_or_else(|| {
        invalid(format!(
            "rig {:?} has no skeleton (no skins and no animated nodes): no column can turn a \
             joint of it",
            entry.id
        ))
    })?;
    if spec.channels.len() > MAX_JOINT_CHANNELS {
        return Err(invalid(format!(
            "{} channels; at most {MAX_JOINT_CHANNELS}",
            spec.channels.len()
        )));
    }
    let mut channels = Vec::with_capacity(spec.channels.len());
    for (i, c) in spec.channels.iter().enumerate() {
        if c.column.trim().is_empty() || c.column.len() > MAX_COLUMN {
            return Err(invalid(format!(
                "channels[{i}].column must be 1–{MAX_COLUMN} characters"
            )));
        }
        // Columns are matched loosely, which a control character would vanish from.
        crowdmorph_import::clips::checked_name(&c.column)
            .map_err(|why| invalid(format!("channels[{i}].column: {why}")))?;
        let node = entry.joint_node(&c.node).map_err(|why| {
            ApiError::bad_request(
                "unknown_joints",
                format!(
                    "channels[{i}].node is {}, {why} (GET /v1/rigs/{} with Accept: \
                     application/json lists every node in skeleton.node_names)",
                    crowdmorph_core::rig::quoted_name(&c.node),
                    entry.id
                ),
            )
        })?;
        let axis = glam::Vec3::from(c.axis);
        let len = axis.length();
        if !(len.is_finite() && len > 1e-6 && c.scale.is_finite()) || c.scale.abs() > 1e6 {
            return Err(invalid(format!(
                "channels[{i}] ({:?}): the axis must be a finite, non-zero vector and the scale \
                 finite (within ±1e6)",
                c.column
            )));
        }
        channels.push(JointChannel {
            column: c.column.clone(),
            node,
            axis: (axis / len).to_array(),
            scale: c.scale,
        });
    }
    // Columns are matched in any loose spelling, so two that spell alike would be one column.
    let mut seen = std::collections::HashSet::with_capacity(channels.len());
    for c in &channels {
        if !seen.insert(crowdmorph_import::clips::loose(&c.column)) {
            return Err(invalid(format!(
                "column {:?} is mapped twice (columns match in any loose spelling)",
                c.column
            )));
        }
    }
    let map = JointMap { channels };
    map.check(sk).map_err(invalid)?;
    Ok(map)
}

/// `GET /v1/rigs/{id}/joint-map`.
pub async fn get_joint_map(
    State(state): State<AppState>,
    _ready: Ready,
    accept: Accept,
    Path(id): Path<String>,
) -> ApiResult {
    let entry = state.rig(&id)?;
    accept.reply(StatusCode::OK, &info(&id, entry.rig()))
}

/// `PUT /v1/rigs/{id}/joint-map`: check the map against the skeleton, then install it (a new
/// generation of the rig, stored first) and answer with it.
pub async fn put_joint_map(
    State(state): State<AppState>,
    _admin: Admin,
    _ready: Ready,
    accept: Accept,
    Path(id): Path<String>,
    Decoded(req): Decoded<JointMapSpec>,
) -> ApiResult {
    let (spec, _decoded) = req.into_parts();
    let entry = install(&state, &id, Some(&spec)).await?;
    accept.reply(StatusCode::OK, &info(&id, entry.rig()))
}

/// `DELETE /v1/rigs/{id}/joint-map`: back to the default map.
pub async fn delete_joint_map(
    State(state): State<AppState>,
    _admin: Admin,
    _ready: Ready,
    accept: Accept,
    Path(id): Path<String>,
) -> ApiResult {
    let entry = state.rig(&id)?;
    let Some(sk) = &entry.rig().skeleton else {
        return Err(invalid(format!("rig {id:?} has no skeleton")));
    };
    // Already the defaults: nothing to change, no new generation.
    let entry = if sk.map.is_none() {
        entry
    } else {
        install(&state, &id, None).await?
    };
    accept.reply(StatusCode::OK, &info(&id, entry.rig()))
}

/// Makes the map `spec` names (`None`: the defaults) rig `id`'s, under the lock that
/// serializes rig changes: the names resolved against the generation the lock found, then the
/// rig with its skeleton's map replaced, prepared, stored, then served.
async fn install(
    state: &AppState,
    id: &str,
    spec: Option<&JointMapSpec>,
) -> Result<Arc<RigEntry>, ApiError> {
    let _admin = state.admin.lock().await;
    let entry = state.rig(id)?;
    let map = spec.map(|s| resolve(&entry, s)).transpose()?;
    let current = entry.prepared.rig().clone();
    let engine = state.engine.clone();
    let gpu = state.on_gpu();
    let budget = state.op_budget();
    let prepared = blocking(move || {
        let mut rig = (*current).clone();
        let mut sk = rig
            .skeleton
            .as_deref()
            .cloned()
            .ok_or_else(|| invalid("the rig lost its skeleton".into()))?;
        sk.map = map;
        rig.skeleton = Some(Arc::new(sk));
        rig.validate().map_err(|e| invalid(e.to_string()))?;
        prepare_charged(&engine, &budget, Arc::new(rig), gpu)
    })
    .await?;
    next_generation(state, id, &entry, prepared).await
}
