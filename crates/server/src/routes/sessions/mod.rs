//! Crowd sessions: one simulated crowd advanced on a fixed tick and streamed to many viewers
//! over WebSockets (`/v1/sessions`, `GET /v1/sessions/{id}/stream`).
//!
//! Shape: [`Sessions`] (in the server state) owns every [`Session`] by id. Each session has one
//! tick task, started with it and tied to it: the task holds the server state only weakly and
//! stops when the session is deleted, ends idle, or the state is dropped. Each viewer is one
//! task that owns its socket and reads a one-message outbox.
//!
//! A tick, once per `1/fps`:
//! 1. applies pending patches (the layout changes at a tick, never inside one);
//! 2. resolves every head to (rig generation, clip, frame) once, then each viewer's LOD per head
//!    (fixed, or by distance from its camera);
//! 3. takes the union over vertex viewers of (rig, clip, frame, LOD) per (format, normals), and
//!    submits it to the server's batcher like a crowd-frame request, so it also coalesces
//!    with HTTP traffic: two viewers at the same LOD cost one blend;
//! 4. fans out: each viewer gets the buffers of the heads whose job changed since the last
//!    message *it received* (others are "unchanged"). Identical messages (same group, same
//!    head vector) are encoded once and shared.
//!
//! Back-pressure: the outbox holds one message. A newer tick replaces an unsent one (counted as
//! dropped), so a slow viewer gets the latest tick, never delays the tick or other viewers, and
//! holds at most one queued and one in-flight message. A tick that cannot be computed in time is
//! skipped, not queued: the next tick is the first whose time has not passed. Viewers that want
//! images get them rendered on the blocking pool, one at a time per viewer (a tick that finds
//! the previous image still rendering skips that viewer).

use std::collections::{HashMap, HashSet};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

use axum::body::Body;
use axum::extract::ws::WebSocketUpgrade;
use axum::extract::{Path, State};
use axum::http::{HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use crowdmorph_proto::{HeadChange, SessionHead, SessionPatch, SessionRequest, SessionStats};
use tokio::sync::Notify;
use tokio::time::Instant;

use crate::admission::alive::check_alive;
use crate::admission::resolve::{requested_joints, unknown_clip};
use crate::admission::{Admission, Charge, Decoded, Priced, decode_held};
use crate::http::body::hold;
use crate::http::{Accept, Admin, ApiError, ApiResult, Ready};
use crate::services::Parts;
use crate::services::replicas::{find_missing, missing};
use crate::sessions::{
    InfoNow, ListNow, MAX_FPS, MAX_IDLE_TIMEOUT_S, MAX_VIEWER_MESSAGE_BYTES, MIN_FPS, Session,
    SessionInner, close, info_bytes,
};
use crate::state::AppState;
use crowdmorph_engine::render::scene;

mod live;
mod viewer;

pub use live::{live_socket, post_live};

/// Answers a GET with session infos, their largest serialized size charged to the queue
/// memory first (503 `queue_full` when it is full) and held until the body is sent: a listing
/// of 64 sessions of 10,000 heads is tens of megabytes, and the GETs need no token.
fn respond_infos<T: serde::Serialize>(
    state: &AppState,
    accept: Accept,
    status: StatusCode,
    bytes: u64,
    value: &T,
) -> ApiResult {
    let charge = state.queue_memory.reserve(bytes)?;
    respond_held(accept, status, value, charge)
}

/// An answer that keeps `charge` (its memory) until the body has been sent.
fn respond_held<T: serde::Serialize>(
    accept: Accept,
    status: StatusCode,
    value: &T,
    charge: Charge,
) -> ApiResult {
    Ok(hold(accept.reply(status, value)?, charge))
}

/// Session `id`, or 404 `unknown_session`.
fn session(state: &AppState, id: &str) -> Result<Arc<Session>, ApiError> {
    state.sessions.get(id).ok_or_else(|| {
        ApiError::new(
            StatusCode::NOT_FOUND,
            "unknown_session",
            format!("no session {}", crowdmorph_core::rig::quoted_name(id)),
        )
    })
}

// ---------------------------------------------------------------------------------------------
// Checking requests.

fn invalid(message: String) -> ApiError {
    ApiError::bad_request("invalid_session", message)
}

/// Checks one head: its rig and clip exist, its placement is drawable.
fn check_session_head(state: &AppState, h: &SessionHead) -> Result<(), ApiError> {
    let entry = state.rig(&h.rig).map_err(|e| ApiError {
        message: format!("head {}: {}", h.head, e.message),
        ..e
    })?;
    if let Some(play) = &h.graph {
        let graph = state
            .graphs
            .resolved(
                &entry,
                &play.name,
                |bytes| state.queue_memory.reserve(bytes).ok(),
                state.config.max_graph_work,
            )
            .ok_or_else(|| {
                let e = crate::routes::graphs::unknown_graph(
                    &entry.id,
                    &play.name,
                    &state.graphs.names(&entry.id),
                );
                ApiError {
                    message: format!("head {}: {}", h.head, e.message),
                    ..e
                }
            })?;
        graph
            .play(play)
            .map_err(|m| ApiError::not_found("unknown_node", format!("head {}: {m}", h.head)))?;
    } else if !h.clip.is_empty() && entry.clip_index(&h.clip).is_none() {
        // An empty clip is the neutral (every weight 0, joints at rest): how a rig with no
        // clips (most avatars as they arrive) is put in a session, alive or not.
        // The same message as a crowd frame's (at most 20 names, whatever the rig holds).
        let e = unknown_clip(&entry, &h.clip);
        return Err(ApiError {
            message: format!("head {}: {}", h.head, e.message),
            ..e
        });
    }
    scene::placement_matrix(&crate::sessions::placement(h))
        .map_err(|e| invalid(format!("head {}: {e}", h.head)))?;
    requested_joints(&entry, &h.joints)
        .map_err(|(code, m)| ApiError::bad_request(code, format!("head {}: {m}", h.head)))?;
    if let Some(l) = &h.live {
        if let Some(m) = &l.mapping {
            crate::admission::mapping::mapping_spec(&entry, &state.registry.maps, m).map_err(
                |e| ApiError {
                    message: format!("head {}: {}", h.head, e.message),
                    ..e
                },
            )?;
        }
        crate::admission::live::check_spec(l).map_err(|e| ApiError {
            message: format!("head {}: {}", h.head, e.message),
            ..e
        })?;
    }
    if let Some(a) = &h.alive {
        check_alive(a).map_err(|e| ApiError {
            message: format!("head {}: {}", h.head, e.message),
            ..e
        })?;
    }
    check_session_layers(state, &entry, h).map_err(|e| ApiError {
        message: format!("head {}: {}", h.head, e.message),
        ..e
    })?;
    Ok(())
}

/// A head's layers and clamp resolve against its rig (their frames as the head's offset is,
/// at the session clock's start), charged while they are checked.
fn check_session_layers(
    state: &AppState,
    entry: &crate::registry::RigEntry,
    h: &SessionHead,
) -> Result<(), ApiError> {
    if h.layers.is_empty() && h.clamp.is_none() {
        return Ok(());
    }
    if h.layers.len() > crowdmorph_proto::MAX_HEAD_LAYERS {
        return Err(ApiError::bad_request(
            "invalid_layer",
            format!(
                "{} layers; a head has at most {}",
                h.layers.len(),
                crowdmorph_proto::MAX_HEAD_LAYERS
            ),
        ));
    }
    let rig = entry.rig();
    let _held = state.queue_memory.reserve(
        crate::admission::layers::layers_bytes(rig, &h.layers)
            + crate::admission::names::LiveNames::bytes(rig)
            + 4 * rig.targets.len() as u64,
    )?;
    let names = crate::admission::names::live_names(&state.registry, entry);
    crate::admission::layers::resolve_layers(entry, &names, &h.layers, |clip, frame, _| {
        rig.clips[clip as usize]
            .resolve_frame(frame, crowdmorph_core::rig::FrameMode::Wrap)
            .map_err(|e| ApiError::bad_request("frame_out_of_range", e.to_string()))
    })?;
    let mut w = vec![0.0; rig.targets.len()];
    crate::admission::layers::finish_weights(rig, &mut w, h.clamp)
}

fn check_head_count(state: &AppState, n: usize) -> Result<(), ApiError> {
    let max = state.config.sessions.max_heads;
    if n > max {
        return Err(ApiError::new(
            StatusCode::PAYLOAD_TOO_LARGE,
            "too_many_heads",
            format!("{n} heads is more than the limit of {max} per session (--max-session-heads)"),
        ));
    }
    Ok(())
}

/// Refuses a patch whose `remove` or `change` list is longer than a session may hold heads:
/// neither can name more distinct heads than that, and an uncapped list (a 16 MiB bincode body
/// holds millions of changes, each a lookup and a head check on the async worker) is work the
/// client decides.
fn check_patch_size(state: &AppState, patch: &SessionPatch) -> Result<(), ApiError> {
    let max = state.config.sessions.max_heads;
    for (field, n) in [
        ("remove", patch.remove.len()),
        ("change", patch.change.len()),
    ] {
        if n > max {
            return Err(invalid(format!(
                "{field} has {n} entries, more than the limit of {max} heads per session \
                 (--max-session-heads)"
            )));
        }
    }
    Ok(())
}

/// A graph head sent to a node by a patch: (head id, node name).
type Jump = (u64, String);

/// The heads after a patch, checked, and the jumps it asks for; `Err` names the first
/// problem.
///
/// The same result as applying the lists one entry at a time: removes in order (a repeated
/// id is unknown the second time, its head being gone), then changes in order (a head changed
/// twice gets both, each checked as it lands), then the count, then adds. Each list costs one
/// hash lookup per entry, not a scan of the heads.
fn patched(
    state: &AppState,
    heads: &[SessionHead],
    patch: &SessionPatch,
) -> Result<(Vec<SessionHead>, Vec<Jump>), ApiError> {
    check_patch_size(state, patch)?;
    // Where each id stands; ids are unique in a session, but the first one wins as a scan's
    // would if they were not.
    let mut at: HashMap<u64, usize> = HashMap::with_capacity(heads.len());
    for (k, h) in heads.iter().enumerate() {
        at.entry(h.head).or_insert(k);
    }
    let mut removed: HashSet<u64> = HashSet::with_capacity(patch.remove.len());
    for id in &patch.remove {
        if !at.contains_key(id) || !removed.insert(*id) {
            return Err(unknown_head(*id));
        }
    }
    let mut out: Vec<SessionHead> = heads.to_vec();
    let mut jumps = Vec::new();
    for HeadChange {
        head,
        clip,
        offset,
        position,
        yaw,
        scale,
        node,
        joints,
        layers,
        clamp,
        live,
        alive,
    } in &patch.change
    {
        let h = at
            .get(head)
            .filter(|_| !removed.contains(head))
            .and_then(|&k| out.get_mut(k))
            .ok_or_else(|| unknown_head(*head))?;
        if let Some(c) = clip {
            h.clip.clone_from(c);
        }
        if let Some(o) = offset {
            h.offset = *o;
        }
        if let Some(p) = position {
            h.position = *p;
        }
        if let Some(y) = yaw {
            h.yaw = *y;
        }
        if let Some(s) = scale {
            h.scale = *s;
        }
        if let Some(j) = joints {
            h.joints.clone_from(j);
        }
        if let Some(l) = layers {
            h.layers.clone_from(l);
        }
        if let Some(c) = clamp {
            h.clamp = Some(*c);
        }
        if let Some(l) = live {
            h.live = Some(l.clone());
        }
        if let Some(a) = alive {
            h.alive = Some(a.clone());
        }
        check_session_head(state, h)?;
        if let Some(n) = node {
            let play = h.graph.as_ref().ok_or_else(|| {
                invalid(format!(
                    "change of head {head}: `node` is for heads that play a graph"
                ))
            })?;
            let to = crowdmorph_proto::GraphPlay {
                start: n.clone(),
                script: Vec::new(),
                ..play.clone()
            };
            check_session_head(
                state,
                &SessionHead {
                    graph: Some(to),
                    ..h.clone()
                },
            )?;
            jumps.push((*head, n.clone()));
        }
    }
    if !removed.is_empty() {
        out.retain(|h| !removed.contains(&h.head));
    }
    check_head_count(state, out.len() + patch.add.len())?;
    let mut ids: HashSet<u64> = out.iter().map(|h| h.head).collect();
    for h in &patch.add {
        if !ids.insert(h.head) {
            return Err(ApiError::new(
                StatusCode::CONFLICT,
                "head_exists",
                format!("the session already has a head {}", h.head),
            ));
        }
        check_session_head(state, h)?;
        out.push(h.clone());
    }
    Ok((out, jumps))
}

fn unknown_head(id: u64) -> ApiError {
    ApiError::new(
        StatusCode::NOT_FOUND,
        "unknown_head",
        format!("the session has no head {id}"),
    )
}

// ---------------------------------------------------------------------------------------------
// Handlers.

/// A session's heads move into the session, where `--max-session-heads` and `--max-sessions`
/// bound them; only their decoding is charged (and the answer, separately, until sent).
impl Priced for SessionRequest {
    fn price(&self, _: Accept) -> u64 {
        0
    }
}

/// A patch is applied into new head lists (charged as the answer that lists them) and
/// dropped; only its decoding is charged.
impl Priced for SessionPatch {
    fn price(&self, _: Accept) -> u64 {
        0
    }
}

/// `POST /v1/sessions`: checks the request, registers the session and starts its tick task.
pub async fn create_session(
    State(state): State<AppState>,
    _admin: Admin,
    _ready: Ready,
    accept: Accept,
    Decoded(req): Decoded<SessionRequest>,
) -> ApiResult {
    find_missing(
        &state,
        missing(&state, req.heads.iter().map(|h| h.rig.as_str())),
    )
    .await?;
    create(&state, None, accept, req)
}

/// `PUT /v1/sessions/{id}`: a session with the client's id (1–64 of `A–Z a–z 0–9 . _ -`), so
/// that a load balancer hashing on the id sends its creation and every viewer of it to one
/// replica; 409 `session_exists` when the id is taken (a running session is never replaced).
pub async fn put_session(
    State(state): State<AppState>,
    _admin: Admin,
    _ready: Ready,
    accept: Accept,
    Path(id): Path<String>,
    Decoded(req): Decoded<SessionRequest>,
) -> ApiResult {
    check_session_id(&id)?;
    find_missing(
        &state,
        missing(&state, req.heads.iter().map(|h| h.rig.as_str())),
    )
    .await?;
    create(&state, Some(id), accept, req)
}

/// Longest client-chosen session id.
pub const MAX_SESSION_ID: usize = 64;

/// A client-chosen session id: 1–[`MAX_SESSION_ID`] bytes of ASCII letters, digits, `.`, `_`
/// and `-` (safe in a path, a log line and a balancer's hash key).
fn check_session_id(id: &str) -> Result<(), ApiError> {
    let ok = (1..=MAX_SESSION_ID).contains(&id.len())
        && id
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'.' | b'_' | b'-'));
    if ok {
        Ok(())
    } else {
        Err(invalid(format!(
            "a session id is 1-{MAX_SESSION_ID} of A-Z a-z 0-9 . _ - (got {} bytes)",
            id.len()
        )))
    }
}

/// Creates a session: with the client's `id`, or the next free `s<n>` the server picks.
fn create(
    state: &AppState,
    id: Option<String>,
    accept: Accept,
    req: crate::admission::Held<SessionRequest>,
) -> ApiResult {
    let (req, _decoded) = req.into_parts();
    if !(MIN_FPS..=MAX_FPS).contains(&req.fps) {
        return Err(invalid(format!(
            "fps {} is not in [{MIN_FPS}, {MAX_FPS}]",
            req.fps
        )));
    }
    if !(1..=MAX_IDLE_TIMEOUT_S).contains(&req.idle_timeout_s) {
        return Err(invalid(format!(
            "idle_timeout_s {} is not in 1..={MAX_IDLE_TIMEOUT_S}",
            req.idle_timeout_s
        )));
    }
    if let Some(a) = &req.alive {
        check_alive(a)?;
    }
    check_head_count(state, req.heads.len())?;
    let mut ids = HashSet::new();
    for h in &req.heads {
        if !ids.insert(h.head) {
            return Err(invalid(format!("head id {} appears twice", h.head)));
        }
        check_session_head(state, h)?;
    }
    let chosen = id.is_some();
    let mut map = state
        .sessions
        .map
        .lock()
        .map_err(|_| ApiError::internal("session map poisoned"))?;
    let id = match id {
        Some(id) => {
            if map.contains_key(&id) {
                return Err(ApiError::new(
                    StatusCode::CONFLICT,
                    "session_exists",
                    format!("a session {id:?} exists; delete it first, or pick another id"),
                ));
            }
            id
        }
        // Skipping ids that clients chose.
        None => loop {
            let n = state.sessions.next_id.fetch_add(1, Ordering::Relaxed) + 1;
            let id = format!("s{n}");
            if !map.contains_key(&id) {
                break id;
            }
        },
    };
    if map.len() >= state.config.sessions.max_sessions {
        return Err(ApiError::unavailable(
            "too_many_sessions",
            format!(
                "{} sessions exist, the most this server keeps (--max-sessions); delete one",
                map.len()
            ),
            5,
        ));
    }
    let answer = state.queue_memory.reserve(info_bytes(&id, &req.heads))?;
    let session = Arc::new(Session {
        id: id.clone(),
        fps: req.fps,
        wrap: req.wrap,
        idle_timeout_s: req.idle_timeout_s,
        inner: Mutex::new(SessionInner {
            heads: Arc::new(req.heads),
            next_heads: None,
            layout_rev: 0,
            viewers: Vec::new(),
            next_viewer: 0,
            tick: 0,
            stats: SessionStats::default(),
            idle_since: Some(Instant::now()),
            jumps: Vec::new(),
            alive: req.alive,
        }),
        stopping: Notify::new(),
        stopped: AtomicBool::new(false),
        viewers_changed: Notify::new(),
        panic_next_tick: AtomicBool::new(false),
        live: crate::live::LiveInputs::default(),
    });
    map.insert(id.clone(), session.clone());
    drop(map);
    crate::services::tick::supervise::<AppState>(session.clone(), state.downgrade());
    let info = session.info();
    tracing::info!(session = %id, heads = info.heads.len(), fps = req.fps, chosen, "session created");
    // Charged before the session existed (`answer`): a 503 now would tell a client that
    // retries to make a second one.
    respond_held(accept, StatusCode::CREATED, &info, answer)
}

/// `GET /v1/sessions`: every session, its answer charged until sent.
pub async fn list_sessions(State(state): State<AppState>, accept: Accept) -> ApiResult {
    let sessions: Vec<InfoNow> = state.sessions.all().iter().map(|s| s.info()).collect();
    let bytes = 32 + sessions.iter().map(InfoNow::response_bytes).sum::<u64>();
    respond_infos(&state, accept, StatusCode::OK, bytes, &ListNow { sessions })
}

/// `GET /v1/sessions/{id}`.
pub async fn get_session(
    State(state): State<AppState>,
    accept: Accept,
    Path(id): Path<String>,
) -> ApiResult {
    let info = session(&state, &id)?.info();
    respond_infos(&state, accept, StatusCode::OK, info.response_bytes(), &info)
}

/// `PATCH /v1/sessions/{id}`: the heads as they will be at the next tick, checked, swapped in.
pub async fn patch_session(
    State(state): State<AppState>,
    _admin: Admin,
    Path(id): Path<String>,
    headers: HeaderMap,
    body: Body,
) -> ApiResult {
    let s = session(&state, &id)?;
    // Decoded after the session is found, so an unknown one is a 404 whatever the body.
    let (patch, _decoded) =
        decode_held::<SessionPatch>(&state.queue_memory, state.body_limits(), &headers, body)
            .await?
            .into_parts();
    let accept = Accept::of(&headers);
    if let Some(a) = &patch.alive {
        check_alive(a)?;
    }
    // Checked against the heads as they will be, then swapped in under the lock (a patch that
    // raced with another is checked again on the newer heads).
    let answer = loop {
        let base = {
            let i = s
                .inner
                .lock()
                .map_err(|_| ApiError::internal("session poisoned"))?;
            i.next_heads.clone().unwrap_or_else(|| i.heads.clone())
        };
        // A patch that only moves the session's liveliness (a look-at point each tick)
        // keeps the heads as they are: no copy, no check, no new layout for the viewers.
        let no_head_change =
            patch.remove.is_empty() && patch.change.is_empty() && patch.add.is_empty();
        if no_head_change && patch.alive.is_some() {
            let answer = state.queue_memory.reserve(info_bytes(&s.id, &base))?;
            let mut i = s
                .inner
                .lock()
                .map_err(|_| ApiError::internal("session poisoned"))?;
            i.alive.clone_from(&patch.alive);
            break answer;
        }
        let (next, jumps) = patched(&state, &base, &patch)?;
        let next = Arc::new(next);
        // The answer lists the patched heads: charged before the patch is in (see
        // `info_bytes`).
        let answer = state.queue_memory.reserve(info_bytes(&s.id, &next))?;
        let mut i = s
            .inner
            .lock()
            .map_err(|_| ApiError::internal("session poisoned"))?;
        let now = i.next_heads.clone().unwrap_or_else(|| i.heads.clone());
        if Arc::ptr_eq(&now, &base) {
            i.next_heads = Some(next);
            i.jumps.extend(jumps);
            if patch.alive.is_some() {
                i.alive.clone_from(&patch.alive);
            }
            break answer;
        }
    };
    respond_held(accept, StatusCode::OK, &s.info(), answer)
}

/// `DELETE /v1/sessions/{id}`: its viewers are closed with 1001.
pub async fn delete_session(
    State(state): State<AppState>,
    _admin: Admin,
    Path(id): Path<String>,
) -> ApiResult {
    let s = state.sessions.remove(&id).ok_or_else(|| {
        ApiError::new(
            StatusCode::NOT_FOUND,
            "unknown_session",
            format!("no session {}", crowdmorph_core::rig::quoted_name(&id)),
        )
    })?;
    s.stop(close::AWAY, "session deleted");
    tracing::info!(session = %id, "session deleted");
    Ok(StatusCode::NO_CONTENT.into_response())
}

/// `GET /v1/sessions/{id}/stream`: the WebSocket upgrade of a viewer.
pub async fn stream(
    State(state): State<AppState>,
    Path(id): Path<String>,
    ws: WebSocketUpgrade,
) -> Result<Response, ApiError> {
    let session = session(&state, &id)?;
    let metrics_owner = state.clone();
    Ok(ws
        .max_message_size(MAX_VIEWER_MESSAGE_BYTES)
        .max_frame_size(MAX_VIEWER_MESSAGE_BYTES)
        .on_upgrade(move |socket| async move {
            viewer::serve_viewer(metrics_owner, session, socket).await;
        }))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crowdmorph_proto::{SessionInfo, SessionList};

    /// A head with every number at its widest in JSON, and names that need escaping.
    fn widest_head(head: u64, rig: &str, clip: &str) -> SessionHead {
        SessionHead {
            head,
            rig: rig.into(),
            clip: clip.into(),
            offset: i64::MIN,
            position: [-1.1754942e-38, -3.4028235e38, -1.4e-45],
            yaw: -1.1754942e-38,
            scale: -1.1754942e-38,
            graph: None,
            joints: Default::default(),
            layers: Vec::new(),
            clamp: None,
            live: None,
            alive: None,
        }
    }

    #[test]
    fn session_infos_serialize_as_before_within_their_charge() {
        let heads = vec![
            widest_head(u64::MAX, "default-head", "talk"),
            widest_head(0, "a\"b\\c\u{1}\n", "é"),
            SessionHead {
                head: 7,
                rig: "r".into(),
                clip: "c".into(),
                offset: 3,
                position: [1.0, 2.0, 3.0],
                yaw: 90.0,
                scale: 1.0,
                graph: Some(crowdmorph_proto::GraphPlay {
                    name: "\u{1}\"".repeat(40),
                    start: "\\".repeat(30),
                    seed: u64::MAX,
                    script: vec!["\u{2}".repeat(20); 5],
                }),
                joints: crowdmorph_proto::JointOverrides(vec![
                    (
                        "\u{3}".repeat(50),
                        crowdmorph_proto::JointTransform {
                            translation: Some([-1.1754942e-38, -3.4028235e38, -1.4e-45]),
                            rotation: Some([-1.1754942e-38; 4]),
                            scale: Some([-3.4028235e38; 3]),
                        },
                    );
                    3
                ]),
                layers: vec![crowdmorph_proto::Layer {
                    mask: Some(crowdmorph_proto::Mask::Weights(vec![(
                        "a\"b\u{1}".repeat(9),
                        -1.1754942e-38,
                    )])),
                    joint_mask: Some(vec!["\u{2}\u{3}".repeat(11); 2]),
                    reference: Some(i64::MIN),
                    ..crowdmorph_proto::Layer::over("\"\\", i64::MIN, -1.1754942e-38)
                }],
                clamp: Some([-1.1754942e-38, -3.4028235e38]),
                live: Some(crowdmorph_proto::LiveSpec {
                    hold_ms: u32::MAX,
                    fade_ms: u32::MAX,
                    delay_ms: u32::MAX,
                    smoothing: Some(crowdmorph_proto::OneEuro {
                        min_cutoff: -1.1754942e-38,
                        beta: -3.4028235e38,
                        d_cutoff: -1.4e-45,
                    }),
                    mapping: Some("\u{1}\"".repeat(40)),
                }),
                alive: Some(crowdmorph_proto::Alive {
                    blink: true,
                    saccades: true,
                    look_at: Some([-1.1754942e-38, -3.4028235e38, -1.4e-45]),
                    breathing: true,
                    seed: Some(u64::MAX),
                }),
            },
        ];
        let stats = SessionStats {
            ticks: u64::MAX,
            ticks_late: u64::MAX,
            ticks_skipped: u64::MAX,
            jobs: u64::MAX,
            messages_sent: u64::MAX,
            messages_dropped: u64::MAX,
            bytes_sent: u64::MAX,
        };
        let now = |heads: &[SessionHead]| InfoNow {
            id: "s18446744073709551615".into(),
            fps: -1.1754942e-38,
            wrap: false,
            idle_timeout_s: u32::MAX,
            tick: u64::MAX,
            heads: Arc::new(heads.to_vec()),
            viewers: u32::MAX,
            stats,
            alive: Some(crowdmorph_proto::Alive {
                look_at: Some([-1.1754942e-38, -3.4028235e38, -1.4e-45]),
                seed: Some(u64::MAX),
                ..Default::default()
            }),
        };
        let before = |heads: &[SessionHead]| SessionInfo {
            id: "s18446744073709551615".into(),
            fps: -1.1754942e-38,
            wrap: false,
            idle_timeout_s: u32::MAX,
            tick: u64::MAX,
            heads: heads.to_vec(),
            viewers: u32::MAX,
            stats,
            alive: Some(crowdmorph_proto::Alive {
                look_at: Some([-1.1754942e-38, -3.4028235e38, -1.4e-45]),
                seed: Some(u64::MAX),
                ..Default::default()
            }),
        };
        for n in [0, 1, heads.len()] {
            let (a, b) = (now(&heads[..n]), before(&heads[..n]));
            let json = serde_json::to_vec(&a).expect("JSON");
            assert_eq!(json, serde_json::to_vec(&b).expect("JSON"));
            let wire = crowdmorph_store::codec::to_wire(&a).expect("bincode");
            assert_eq!(wire, crowdmorph_store::codec::to_wire(&b).expect("bincode"));
            // The charge covers the body in either format, and is not wildly above it.
            let charged = a.response_bytes();
            assert!(json.len() as u64 <= charged, "{} > {charged}", json.len());
            assert!(wire.len() as u64 <= charged, "{} > {charged}", wire.len());
            assert!(
                charged <= 2 * json.len() as u64 + 64,
                "{charged} for {}",
                json.len()
            );
        }
        let list = ListNow {
            sessions: vec![now(&heads), now(&heads[..1])],
        };
        let old = SessionList {
            sessions: vec![before(&heads), before(&heads[..1])],
        };
        let json = serde_json::to_vec(&list).expect("JSON");
        assert_eq!(json, serde_json::to_vec(&old).expect("JSON"));
        assert_eq!(
            crowdmorph_store::codec::to_wire(&list).expect("bincode"),
            crowdmorph_store::codec::to_wire(&old).expect("bincode")
        );
    }
}
