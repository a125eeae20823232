//! `GET /v1/rigs/{id}/channels`: what the numbers of a pose answer are about, for a client
//! that blends itself (`"format": "weights"` crowd frames, `"output": "weights"` viewers): the
//! rig's weight channels in the order a pose's weights come, and its skeleton's nodes in the
//! order a pose's joints number them. Sent once per rig, not with every pose.

use axum::extract::{Path, State};
use axum::http::StatusCode;
use crowdmorph_proto::RigChannels;

use crate::http::{Accept, ApiResult, Ready};
use crate::services::Parts;
use crate::state::AppState;

/// Bytes an answer holds besides its names' own bytes: per name its `String` and, as JSON,
/// its quotes, escapes of the widest kind and separator.
const PER_NAME_BYTES: u64 = 64;

/// `GET /v1/rigs/{id}/channels`: the labels and names, charged to the queue memory (the value
/// and its encoding, each name at most six bytes a byte as JSON) until it is sent.
pub async fn get_channels(
    State(state): State<AppState>,
    _ready: Ready,
    accept: Accept,
    Path(id): Path<String>,
) -> ApiResult {
    let entry = state.rig(&id)?;
    let rig = entry.rig();
    let nodes = rig.skeleton.as_ref().map_or(&[][..], |s| &s.nodes[..]);
    let names: u64 = rig.targets.iter().map(|t| t.len() as u64 + 4).sum::<u64>()
        + nodes.iter().map(|n| n.name.len() as u64).sum::<u64>();
    let count = (rig.targets.len() + nodes.len()) as u64;
    let _held = state
        .queue_memory
        .reserve(7 * names + count * PER_NAME_BYTES + 256)?;
    let answer = RigChannels {
        rig: entry.id.clone(),
        targets: rig.channel_labels().into_vec(),
        nodes: nodes.iter().map(|n| n.name.clone()).collect(),
    };
    accept.reply(StatusCode::OK, &answer)
}
