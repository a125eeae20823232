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

use std::collections::{BTreeMap, HashMap, HashSet};
use std::fmt::Write as _;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::time::Duration;

use axum::body::Body;
use axum::extract::ws::{CloseFrame, Message, WebSocket, WebSocketUpgrade};
use axum::extract::{Path, State};
use axum::http::{HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use bytes::Bytes;
use crowdmorph_proto::{
    CameraSpec, Format, FrameTimings, HEAD_MISSING, HEAD_UNCHANGED, HeadBuffer, HeadChange,
    ImageFormat, ImageOptions, LodChoice, Placement, RenderRequest, SessionHead, SessionPatch,
    SessionRequest, SessionStats, ViewerHello, ViewerOutput, ViewerUpdate,
};
use glam::Vec3;
use tokio::sync::{Notify, OwnedSemaphorePermit};
use tokio::time::Instant;

use super::api::{ApiResult, job_request, respond};
use super::registry::{MAX_F16, RigEntry};
use super::scheduler::{JobRequest, ScheduleError};
use super::{ApiError, AppState, Inner};
use crate::codec::{FrameBufferParts, FrameResponseEncoder};
use crate::render::scene;
use crate::rig::FrameMode;

/// Limits of the session API: flags of `serve`, flattened into [`super::ServerConfig`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::Args)]
pub struct SessionLimits {
    /// Crowd sessions that may exist at once (503 too_many_sessions past it).
    #[arg(
        long = "max-sessions",
        env = "CROWDMORPH_MAX_SESSIONS",
        default_value = "64",
        value_parser = super::config::at_least_one
    )]
    pub max_sessions: usize,
    /// Heads one session may hold (413 too_many_heads past it).
    #[arg(
        id = "max_session_heads",
        long = "max-session-heads",
        env = "CROWDMORPH_MAX_SESSION_HEADS",
        default_value = "10000",
        value_parser = super::config::at_least_one
    )]
    pub max_heads: usize,
    /// Viewers one session may have at once (more are closed with 1013).
    #[arg(
        id = "max_session_viewers",
        long = "max-session-viewers",
        env = "CROWDMORPH_MAX_SESSION_VIEWERS",
        default_value = "32",
        value_parser = super::config::at_least_one
    )]
    pub max_viewers: usize,
    /// Messages per second a session viewer may send, camera and LOD updates, averaged over a
    /// second (more close it with 1008).
    #[arg(
        long = "max-viewer-messages",
        env = "CROWDMORPH_MAX_VIEWER_MESSAGES",
        default_value_t = 60,
        value_parser = clap::value_parser!(u32).range(1..)
    )]
    pub max_viewer_messages: u32,
    /// How long a viewer has to send its hello before it is closed with 1008.
    #[arg(skip = Duration::from_secs(10))]
    pub hello_timeout: Duration,
    /// Most pixels of one session viewer's image (a hello asking for more is closed with
    /// 1008; default 1920 × 1080).
    #[arg(
        long = "max-viewer-pixels",
        env = "CROWDMORPH_MAX_VIEWER_PIXELS",
        default_value_t = DEFAULT_MAX_VIEWER_PIXELS,
        value_parser = clap::value_parser!(u64).range(1..)
    )]
    pub max_viewer_pixels: u64,
}

impl Default for SessionLimits {
    fn default() -> Self {
        super::ServerConfig::default().sessions
    }
}

/// Largest text message a viewer may send.
pub const MAX_VIEWER_MESSAGE_BYTES: usize = 64 << 10;
/// How long a close frame may take to go out before the socket is dropped.
const CLOSE_TIMEOUT: Duration = Duration::from_secs(1);
/// Highest tick rate.
const MAX_FPS: f32 = 120.0;
/// Lowest tick rate: a tick every ten seconds. Below it a period is a client's typo (1e-30
/// ticks per second is a period past what a `Duration` holds).
pub const MIN_FPS: f32 = 0.1;
/// Default of [`SessionLimits::max_viewer_pixels`]: a full-HD image.
pub const DEFAULT_MAX_VIEWER_PIXELS: u64 = 1920 * 1080;
/// Longest idle timeout, seconds (a day).
const MAX_IDLE_TIMEOUT_S: u32 = 86_400;

/// RFC 6455 close codes the stream uses.
mod close {
    /// Normal closure.
    pub const NORMAL: u16 = 1000;
    /// Going away: the session was deleted or ended, or the server is stopping.
    pub const AWAY: u16 = 1001;
    /// Policy violation: a bad hello or update, too many messages.
    pub const POLICY: u16 = 1008;
    /// A message too big to process.
    pub const TOO_BIG: u16 = 1009;
    /// The server hit an unexpected condition (a bug).
    pub const INTERNAL: u16 = 1011;
    /// Try again later: the session is full.
    pub const AGAIN: u16 = 1013;
}

/// Counters over all sessions, for `/metrics`.
#[derive(Debug, Default)]
pub struct SessionMetrics {
    ticks: AtomicU64,
    ticks_late: AtomicU64,
    ticks_skipped: AtomicU64,
    jobs: AtomicU64,
    sent: AtomicU64,
    dropped_slow: AtomicU64,
    dropped_memory: AtomicU64,
    dropped_rendering: AtomicU64,
    bytes_sent: AtomicU64,
    viewers_refused: AtomicU64,
    viewers_closed_policy: AtomicU64,
}

fn bump(c: &AtomicU64, n: u64) {
    c.fetch_add(n, Ordering::Relaxed);
}

/// Every session of the server, by id.
#[derive(Debug, Default)]
pub struct Sessions {
    map: Mutex<BTreeMap<String, Arc<Session>>>,
    next_id: AtomicU64,
    /// Counters over all sessions.
    pub metrics: SessionMetrics,
}

impl Sessions {
    fn get(&self, id: &str) -> Result<Arc<Session>, ApiError> {
        self.map
            .lock()
            .ok()
            .and_then(|m| m.get(id).cloned())
            .ok_or_else(|| {
                ApiError::new(
                    StatusCode::NOT_FOUND,
                    "unknown_session",
                    format!("no session {}", crate::rig::quoted_name(id)),
                )
            })
    }

    fn all(&self) -> Vec<Arc<Session>> {
        self.map
            .lock()
            .map(|m| m.values().cloned().collect())
            .unwrap_or_default()
    }

    fn remove(&self, id: &str) -> Option<Arc<Session>> {
        self.map.lock().ok()?.remove(id)
    }

    /// Test hook: makes session `id`'s next tick panic, so that the tick task's supervision
    /// can be tested. Returns whether the session exists.
    #[doc(hidden)]
    pub fn panic_next_tick(&self, id: &str) -> bool {
        self.get(id)
            .map(|s| s.panic_next_tick.store(true, Ordering::Release))
            .is_ok()
    }

    /// Ends every session (the server is stopping): viewers are closed with 1001.
    pub fn close_all(&self, reason: &str) {
        let all: Vec<Arc<Session>> = self
            .map
            .lock()
            .map(|mut m| std::mem::take(&mut *m).into_values().collect())
            .unwrap_or_default();
        for s in all {
            s.stop(close::AWAY, reason);
        }
    }

    /// Appends the session metrics in the Prometheus text format.
    pub fn write_metrics(&self, out: &mut String) {
        let sessions = self.all();
        let viewers: usize = sessions.iter().map(|s| s.viewer_count()).sum();
        let m = &self.metrics;
        let get = |c: &AtomicU64| c.load(Ordering::Relaxed);
        let _ = writeln!(
            out,
            "# HELP crowdmorph_sessions Crowd sessions that exist now.\n\
             # TYPE crowdmorph_sessions gauge\ncrowdmorph_sessions {}\n\
             # HELP crowdmorph_session_viewers Viewers connected to sessions now.\n\
             # TYPE crowdmorph_session_viewers gauge\ncrowdmorph_session_viewers {viewers}\n\
             # HELP crowdmorph_session_ticks_total Session ticks by result: on_time and late \
             were computed and delivered; skipped were never computed.\n\
             # TYPE crowdmorph_session_ticks_total counter\n\
             crowdmorph_session_ticks_total{{result=\"on_time\"}} {}\n\
             crowdmorph_session_ticks_total{{result=\"late\"}} {}\n\
             crowdmorph_session_ticks_total{{result=\"skipped\"}} {}\n\
             # HELP crowdmorph_session_jobs_total Unique jobs sessions submitted to the batcher.\n\
             # TYPE crowdmorph_session_jobs_total counter\ncrowdmorph_session_jobs_total {}\n\
             # HELP crowdmorph_session_messages_total Stream messages by result: sent, or dropped \
             because a newer tick replaced them (slow), the queue memory was full (memory) or \
             the viewer's previous image was still rendering (rendering).\n\
             # TYPE crowdmorph_session_messages_total counter\n\
             crowdmorph_session_messages_total{{result=\"sent\"}} {}\n\
             crowdmorph_session_messages_total{{result=\"dropped_slow\"}} {}\n\
             crowdmorph_session_messages_total{{result=\"dropped_memory\"}} {}\n\
             crowdmorph_session_messages_total{{result=\"dropped_rendering\"}} {}\n\
             # HELP crowdmorph_session_bytes_sent_total Bytes of stream messages sent.\n\
             # TYPE crowdmorph_session_bytes_sent_total counter\n\
             crowdmorph_session_bytes_sent_total {}\n\
             # HELP crowdmorph_session_viewers_closed_total Viewers the server closed, by reason.\n\
             # TYPE crowdmorph_session_viewers_closed_total counter\n\
             crowdmorph_session_viewers_closed_total{{reason=\"full\"}} {}\n\
             crowdmorph_session_viewers_closed_total{{reason=\"policy\"}} {}",
            sessions.len(),
            get(&m.ticks).saturating_sub(get(&m.ticks_late)),
            get(&m.ticks_late),
            get(&m.ticks_skipped),
            get(&m.jobs),
            get(&m.sent),
            get(&m.dropped_slow),
            get(&m.dropped_memory),
            get(&m.dropped_rendering),
            get(&m.bytes_sent),
            get(&m.viewers_refused),
            get(&m.viewers_closed_policy),
        );
    }
}

/// One session.
#[derive(Debug)]
pub struct Session {
    id: String,
    fps: f32,
    wrap: bool,
    idle_timeout_s: u32,
    inner: Mutex<SessionInner>,
    /// Wakes the tick task when the session stops.
    stopping: Notify,
    stopped: AtomicBool,
    /// Wakes the tick task when its viewers change, so an idle timeout is kept whatever the
    /// tick period.
    viewers_changed: Notify,
    /// Test hook: the next tick panics (the supervision of the tick task is tested with it).
    panic_next_tick: AtomicBool,
}

#[derive(Debug)]
struct SessionInner {
    /// The heads of the last tick.
    heads: Arc<Vec<SessionHead>>,
    /// The heads after the patches received since, applied at the next tick.
    next_heads: Option<Arc<Vec<SessionHead>>>,
    /// Bumped whenever `heads` changes; viewers get the layout when theirs is older.
    layout_rev: u64,
    viewers: Vec<Arc<Viewer>>,
    next_viewer: u64,
    tick: u64,
    stats: SessionStats,
    /// When the last viewer left (or the session started without one).
    idle_since: Option<Instant>,
}

/// What identifies a head's buffer for a viewer: the same key means the same vertices.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
struct HeadKey {
    generation: u64,
    clip: u32,
    frame: u32,
    lod: u32,
}

const MISSING_KEY: HeadKey = HeadKey {
    generation: u64::MAX,
    clip: 0,
    frame: 0,
    lod: 0,
};

/// What a viewer last received: "unchanged" is relative to this.
#[derive(Clone, Debug)]
struct Baseline {
    version: u64,
    /// `u64::MAX` before the first message.
    layout_rev: u64,
    keys: Arc<Vec<HeadKey>>,
}

/// A message encoded once, possibly shared by several viewers, holding its queue memory.
#[derive(Debug)]
struct Encoded {
    bytes: Bytes,
    _memory: OwnedSemaphorePermit,
}

#[derive(Debug)]
struct Outgoing {
    message: Arc<Encoded>,
    /// The viewer's baseline once this is sent.
    after: Baseline,
}

#[derive(Debug)]
struct Outbox {
    pending: Option<Outgoing>,
    sent: Baseline,
}

/// A viewer's choices: its hello, then its updates.
#[derive(Clone, Debug)]
struct ViewerSettings {
    output: ViewerOutput,
    format: Format,
    normals: bool,
    camera: Option<CameraSpec>,
    lod: LodChoice,
    image: ImageOptions,
}

#[derive(Debug)]
struct Viewer {
    settings: Mutex<ViewerSettings>,
    outbox: Mutex<Outbox>,
    ready: Notify,
    /// A close the server asked for (the session ended), and its wake-up.
    close: Mutex<Option<(u16, String)>>,
    closing: Notify,
    /// An image for this viewer is being rendered.
    rendering: AtomicBool,
    /// Raised when the viewer leaves: an image being rendered for it stops.
    gone: crate::cancel::Cancel,
}

impl Viewer {
    fn new(settings: ViewerSettings) -> Viewer {
        Viewer {
            settings: Mutex::new(settings),
            outbox: Mutex::new(Outbox {
                pending: None,
                sent: Baseline {
                    version: 0,
                    layout_rev: u64::MAX,
                    keys: Arc::new(Vec::new()),
                },
            }),
            ready: Notify::new(),
            close: Mutex::new(None),
            closing: Notify::new(),
            rendering: AtomicBool::new(false),
            gone: crate::cancel::Cancel::manual(),
        }
    }

    fn settings(&self) -> Option<ViewerSettings> {
        self.settings.lock().ok().map(|s| s.clone())
    }

    fn ask_close(&self, code: u16, reason: &str) {
        if let Ok(mut c) = self.close.lock() {
            c.get_or_insert((code, reason.to_string()));
        }
        self.closing.notify_one();
    }

    fn close_asked(&self) -> Option<(u16, String)> {
        self.close.lock().ok().and_then(|c| c.clone())
    }
}

impl Session {
    fn viewer_count(&self) -> usize {
        self.inner.lock().map(|i| i.viewers.len()).unwrap_or(0)
    }

    /// Stops the tick task and closes every viewer.
    fn stop(&self, code: u16, reason: &str) {
        self.stopped.store(true, Ordering::Release);
        self.stopping.notify_one();
        let viewers = self
            .inner
            .lock()
            .map(|i| i.viewers.clone())
            .unwrap_or_default();
        for v in viewers {
            v.ask_close(code, reason);
        }
    }

    /// What `SessionInfo` says of this session now. Under the lock it takes a reference to
    /// the heads, not a copy: the GETs need no token, and copying every head of every session
    /// (64 × 10,000) under each session's lock was work and memory a caller could ask for at
    /// will.
    fn info(&self) -> InfoNow {
        let (heads, viewers, tick, stats) = match self.inner.lock() {
            Ok(i) => (
                i.next_heads.clone().unwrap_or_else(|| i.heads.clone()),
                i.viewers.len() as u32,
                i.tick,
                i.stats,
            ),
            Err(_) => (Arc::default(), 0, 0, SessionStats::default()),
        };
        InfoNow {
            id: self.id.clone(),
            fps: self.fps,
            wrap: self.wrap,
            idle_timeout_s: self.idle_timeout_s,
            tick,
            heads,
            viewers,
            stats,
        }
    }

    fn with_stats(&self, f: impl FnOnce(&mut SessionStats)) {
        if let Ok(mut i) = self.inner.lock() {
            f(&mut i.stats);
        }
    }
}

/// A session's [`crowdmorph_proto::SessionInfo`], holding its heads by reference: it serializes
/// to exactly the bytes a `SessionInfo` of the same values does (same fields in the same order;
/// an `Arc` is written as what it holds), without copying the heads first.
#[derive(Debug, serde::Serialize)]
struct InfoNow {
    id: String,
    fps: f32,
    wrap: bool,
    idle_timeout_s: u32,
    tick: u64,
    heads: Arc<Vec<SessionHead>>,
    viewers: u32,
    stats: SessionStats,
}

/// [`crowdmorph_proto::SessionList`] of [`InfoNow`]s, the same way.
#[derive(Debug, serde::Serialize)]
struct ListNow {
    sessions: Vec<InfoNow>,
}

/// Most bytes a session's info takes in JSON besides its heads: the field names, the id and
/// every number at its widest (14 `u64`s and `u32`s of at most 20 digits, one `f32`).
const INFO_JSON_BYTES: u64 = 640;

/// Most bytes one head takes in JSON besides its two names: the field names and every number
/// at its widest (`u64`, `i64`: 20 characters; five `f32`s: 15 each), with the separators.
const HEAD_JSON_BYTES: u64 = 200;

/// Most bytes a string takes in JSON: each byte at most a six-byte `\u00XX` escape.
fn json_str_bytes(s: &str) -> u64 {
    2 + s
        .bytes()
        .map(|b| match b {
            b'"' | b'\\' => 2,
            0..=0x1f => 6,
            _ => 1,
        })
        .sum::<u64>()
}

impl InfoNow {
    /// Most bytes this takes serialized, in JSON or bincode (JSON is the larger): what
    /// answering with it charges to the queue memory before the body is built.
    fn response_bytes(&self) -> u64 {
        info_bytes(&self.id, &self.heads)
    }
}

/// [`InfoNow::response_bytes`] of a session `id` with `heads`, known before the session is
/// created or a patch applied: their answers are charged before the change, so that a full
/// queue refuses the request (503, nothing changed) instead of its answer (a retry would
/// change it twice).
fn info_bytes(id: &str, heads: &[SessionHead]) -> u64 {
    let heads: u64 = heads
        .iter()
        .map(|h| HEAD_JSON_BYTES + json_str_bytes(&h.rig) + json_str_bytes(&h.clip))
        .sum();
    INFO_JSON_BYTES + json_str_bytes(id) + heads
}

/// Keeps a queue memory permit with a response body until the body has been sent (or the
/// connection dropped).
struct HeldBody {
    body: Body,
    _permit: OwnedSemaphorePermit,
}

impl http_body::Body for HeldBody {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(
        mut self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<Option<Result<http_body::Frame<Bytes>, Self::Error>>> {
        std::pin::Pin::new(&mut self.body).poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.body.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.body.size_hint()
    }
}

/// Answers a GET with session infos, their largest serialized size charged to the queue
/// memory first (503 `queue_full` when it is full) and held until the body is sent: a listing
/// of 64 sessions of 10,000 heads is tens of megabytes, and the GETs need no token.
fn respond_infos<T: serde::Serialize>(
    state: &AppState,
    headers: &HeaderMap,
    status: StatusCode,
    bytes: u64,
    value: &T,
) -> ApiResult {
    let permit = state.reserve_queue_memory(bytes)?;
    respond_held(headers, status, value, permit)
}

/// [`respond`], keeping `permit` (the answer's charge) until the body has been sent.
fn respond_held<T: serde::Serialize>(
    headers: &HeaderMap,
    status: StatusCode,
    value: &T,
    permit: OwnedSemaphorePermit,
) -> ApiResult {
    let response = respond(headers, status, value)?;
    let (parts, body) = response.into_parts();
    Ok(Response::from_parts(
        parts,
        Body::new(HeldBody {
            body,
            _permit: permit,
        }),
    ))
}

// ---------------------------------------------------------------------------------------------
// Checking requests.

fn invalid(message: String) -> ApiError {
    ApiError::bad_request("invalid_session", message)
}

impl AppState {
    /// Checks one head: its rig and clip exist, its placement is drawable.
    fn check_session_head(&self, h: &SessionHead) -> Result<(), ApiError> {
        let entry = self.rig(&h.rig).map_err(|e| ApiError {
            message: format!("head {}: {}", h.head, e.message),
            ..e
        })?;
        if entry.clip_index(&h.clip).is_none() {
            // The same message as a crowd frame's (at most 20 names, whatever the rig holds).
            let e = super::api::unknown_clip(&entry, &h.clip);
            return Err(ApiError {
                message: format!("head {}: {}", h.head, e.message),
                ..e
            });
        }
        scene::placement_matrix(&placement(h))
            .map_err(|e| invalid(format!("head {}: {e}", h.head)))?;
        Ok(())
    }

    fn check_head_count(&self, n: usize) -> Result<(), ApiError> {
        let max = self.config.sessions.max_heads;
        if n > max {
            return Err(ApiError::new(
                StatusCode::PAYLOAD_TOO_LARGE,
                "too_many_heads",
                format!(
                    "{n} heads is more than the limit of {max} per session (--max-session-heads)"
                ),
            ));
        }
        Ok(())
    }
}

fn placement(h: &SessionHead) -> Placement {
    Placement {
        head: h.head,
        position: h.position,
        yaw: h.yaw,
        scale: h.scale,
    }
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

/// The heads after a patch, checked; `Err` names the first problem.
///
/// The same result as applying the lists one entry at a time: removes in order (a repeated
/// id is unknown the second time, its head being gone), then changes in order (a head changed
/// twice gets both, each checked as it lands), then the count, then adds. Each list costs one
/// hash lookup per entry, not a scan of the heads.
fn patched(
    state: &AppState,
    heads: &[SessionHead],
    patch: &SessionPatch,
) -> Result<Vec<SessionHead>, ApiError> {
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
    for HeadChange {
        head,
        clip,
        offset,
        position,
        yaw,
        scale,
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
        state.check_session_head(h)?;
    }
    if !removed.is_empty() {
        out.retain(|h| !removed.contains(&h.head));
    }
    state.check_head_count(out.len() + patch.add.len())?;
    let mut ids: HashSet<u64> = out.iter().map(|h| h.head).collect();
    for h in &patch.add {
        if !ids.insert(h.head) {
            return Err(ApiError::new(
                StatusCode::CONFLICT,
                "head_exists",
                format!("the session already has a head {}", h.head),
            ));
        }
        state.check_session_head(h)?;
        out.push(h.clone());
    }
    Ok(out)
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

pub(super) async fn create_session(
    State(state): State<AppState>,
    headers: HeaderMap,
    body: Body,
) -> ApiResult {
    state.check_admin(&headers)?;
    state.check_ready()?;
    let req: SessionRequest = state.crowd_request(&headers, body).await?;
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
    state.check_head_count(req.heads.len())?;
    let mut ids = HashSet::new();
    for h in &req.heads {
        if !ids.insert(h.head) {
            return Err(invalid(format!("head id {} appears twice", h.head)));
        }
        state.check_session_head(h)?;
    }
    let n = state.sessions.next_id.fetch_add(1, Ordering::Relaxed) + 1;
    let id = format!("s{n}");
    let answer = state.reserve_queue_memory(info_bytes(&id, &req.heads))?;
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
        }),
        stopping: Notify::new(),
        stopped: AtomicBool::new(false),
        viewers_changed: Notify::new(),
        panic_next_tick: AtomicBool::new(false),
    });
    {
        let mut map = state
            .sessions
            .map
            .lock()
            .map_err(|_| ApiError::internal("session map poisoned"))?;
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
        map.insert(id.clone(), session.clone());
    }
    supervise(session.clone(), Arc::downgrade(&state.0));
    let info = session.info();
    tracing::info!(session = %id, heads = info.heads.len(), fps = req.fps, "session created");
    // Charged before the session existed (`answer`): a 503 now would tell a client that
    // retries to make a second one.
    respond_held(&headers, StatusCode::CREATED, &info, answer)
}

pub(super) async fn list_sessions(State(state): State<AppState>, headers: HeaderMap) -> ApiResult {
    let sessions: Vec<InfoNow> = state.sessions.all().iter().map(|s| s.info()).collect();
    let bytes = 32 + sessions.iter().map(InfoNow::response_bytes).sum::<u64>();
    respond_infos(
        &state,
        &headers,
        StatusCode::OK,
        bytes,
        &ListNow { sessions },
    )
}

pub(super) async fn get_session(
    State(state): State<AppState>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> ApiResult {
    let info = state.sessions.get(&id)?.info();
    respond_infos(
        &state,
        &headers,
        StatusCode::OK,
        info.response_bytes(),
        &info,
    )
}

pub(super) async fn patch_session(
    State(state): State<AppState>,
    Path(id): Path<String>,
    headers: HeaderMap,
    body: Body,
) -> ApiResult {
    state.check_admin(&headers)?;
    let s = state.sessions.get(&id)?;
    let patch: SessionPatch = state.crowd_request(&headers, body).await?;
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
        let next = Arc::new(patched(&state, &base, &patch)?);
        // The answer lists the patched heads: charged before the patch is in (see
        // `info_bytes`).
        let answer = state.reserve_queue_memory(info_bytes(&s.id, &next))?;
        let mut i = s
            .inner
            .lock()
            .map_err(|_| ApiError::internal("session poisoned"))?;
        let now = i.next_heads.clone().unwrap_or_else(|| i.heads.clone());
        if Arc::ptr_eq(&now, &base) {
            i.next_heads = Some(next);
            break answer;
        }
    };
    respond_held(&headers, StatusCode::OK, &s.info(), answer)
}

pub(super) async fn delete_session(
    State(state): State<AppState>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> ApiResult {
    state.check_admin(&headers)?;
    let s = state.sessions.remove(&id).ok_or_else(|| {
        ApiError::new(
            StatusCode::NOT_FOUND,
            "unknown_session",
            format!("no session {}", crate::rig::quoted_name(&id)),
        )
    })?;
    s.stop(close::AWAY, "session deleted");
    tracing::info!(session = %id, "session deleted");
    Ok(StatusCode::NO_CONTENT.into_response())
}

pub(super) async fn stream(
    State(state): State<AppState>,
    Path(id): Path<String>,
    ws: WebSocketUpgrade,
) -> Result<Response, ApiError> {
    let session = state.sessions.get(&id)?;
    let metrics_owner = state.clone();
    Ok(ws
        .max_message_size(MAX_VIEWER_MESSAGE_BYTES)
        .max_frame_size(MAX_VIEWER_MESSAGE_BYTES)
        .on_upgrade(move |socket| async move {
            serve_viewer(metrics_owner, session, socket).await;
        }))
}

// ---------------------------------------------------------------------------------------------
// Viewers.

async fn close_with(socket: &mut WebSocket, code: u16, reason: &str) {
    let frame = CloseFrame {
        code,
        reason: reason.into(),
    };
    let _ = tokio::time::timeout(CLOSE_TIMEOUT, socket.send(Message::Close(Some(frame)))).await;
}

/// Reads the hello; `Err` is the close code and reason.
async fn read_hello(
    socket: &mut WebSocket,
    limits: &SessionLimits,
) -> Result<ViewerSettings, (u16, String)> {
    let timeout = limits.hello_timeout;
    let msg = match tokio::time::timeout(timeout, socket.recv()).await {
        Err(_) => {
            return Err((
                close::POLICY,
                format!("no hello within {:.1} s", timeout.as_secs_f64()),
            ));
        }
        Ok(None) => return Err((close::NORMAL, String::new())),
        Ok(Some(Err(e))) => return Err(socket_error(&e)),
        Ok(Some(Ok(m))) => m,
    };
    let text = match msg {
        Message::Text(t) => t,
        Message::Close(_) => return Err((close::NORMAL, String::new())),
        _ => {
            return Err((
                close::POLICY,
                "the first message must be a JSON hello (text)".into(),
            ));
        }
    };
    let hello: ViewerHello = parse_json(text.as_str(), "hello")?;
    check_lod(&hello.lod)?;
    let image = hello.image.unwrap_or(ImageOptions {
        format: ImageFormat::Jpeg,
        quality: 80,
        ..ImageOptions::default()
    });
    crate::render::encode::check_image(&image, crowdmorph_proto::MAX_IMAGE_SIDE)
        .map_err(|e| (close::POLICY, truncate(format!("bad image: {e}"))))?;
    let pixels = u64::from(image.width) * u64::from(image.height);
    if hello.output == ViewerOutput::Frames && pixels > limits.max_viewer_pixels {
        return Err((
            close::POLICY,
            truncate(format!(
                "bad image: {}x{} is more than {} pixels (--max-viewer-pixels)",
                image.width, image.height, limits.max_viewer_pixels
            )),
        ));
    }
    if let Some(c) = &hello.camera {
        check_camera(c, &image)?;
    }
    Ok(ViewerSettings {
        output: hello.output,
        format: hello.format,
        normals: hello.normals,
        camera: hello.camera,
        lod: hello.lod,
        image,
    })
}

fn socket_error(e: &axum::Error) -> (u16, String) {
    let text = e.to_string();
    if text.contains("too long") || text.contains("Space limit") || text.contains("size") {
        (
            close::TOO_BIG,
            format!("messages are limited to {MAX_VIEWER_MESSAGE_BYTES} bytes"),
        )
    } else {
        (close::POLICY, truncate(text))
    }
}

/// Close reasons are at most 123 bytes (RFC 6455 §5.5).
fn truncate(mut s: String) -> String {
    if s.len() > 123 {
        let mut end = 120;
        while !s.is_char_boundary(end) {
            end -= 1;
        }
        s.truncate(end);
        s.push_str("...");
    }
    s
}

fn parse_json<T: serde::de::DeserializeOwned>(text: &str, what: &str) -> Result<T, (u16, String)> {
    let mut de = serde_json::Deserializer::from_str(text);
    let value: T = serde_path_to_error::deserialize(&mut de).map_err(|e| {
        let path = e.path().to_string();
        (
            close::POLICY,
            truncate(format!("bad {what} at {path}: {}", e.into_inner())),
        )
    })?;
    de.end()
        .map_err(|e| (close::POLICY, truncate(format!("bad {what}: {e}"))))?;
    Ok(value)
}

/// Checks a viewer's camera as the renderer will use it, at its image's aspect: the checks of
/// `POST /v1/crowd/render` (range, a finite and invertible projection), so a camera that
/// could never draw is refused at the hello or update, not found out at every tick.
fn check_camera(c: &CameraSpec, image: &ImageOptions) -> Result<(), (u16, String)> {
    let aspect = image.width.max(1) as f32 / image.height.max(1) as f32;
    scene::layout(&[], &[], None, Some(c), aspect)
        .map(|_| ())
        .map_err(|e| (close::POLICY, truncate(format!("bad camera: {e}"))))
}

fn check_lod(l: &LodChoice) -> Result<(), (u16, String)> {
    if let LodChoice::ByDistance { by_distance } = l {
        if by_distance.len() > 64 {
            return Err((close::POLICY, "bad lod: at most 64 distances".into()));
        }
        let mut last = f32::NEG_INFINITY;
        for [m, level] in by_distance {
            if !m.is_finite() || *m < last {
                return Err((
                    close::POLICY,
                    "bad lod: distances must be finite and ascending".into(),
                ));
            }
            if !(level.is_finite() && *level >= 0.0 && level.fract() == 0.0) {
                return Err((
                    close::POLICY,
                    "bad lod: levels must be whole numbers ≥ 0".into(),
                ));
            }
            last = *m;
        }
    }
    Ok(())
}

/// Runs one viewer until it leaves, breaks a rule or the session ends.
async fn serve_viewer(state: AppState, session: Arc<Session>, mut socket: WebSocket) {
    let settings = match read_hello(&mut socket, &state.config.sessions).await {
        Ok(s) => s,
        Err((code, reason)) => {
            if code == close::POLICY || code == close::TOO_BIG {
                bump(&state.sessions.metrics.viewers_closed_policy, 1);
            }
            finish(&mut socket, code, &reason).await;
            return;
        }
    };
    if session.stopped.load(Ordering::Acquire) {
        close_with(&mut socket, close::AWAY, "session ended").await;
        return;
    }
    let viewer = Arc::new(Viewer::new(settings));
    let admitted = {
        let mut i = match session.inner.lock() {
            Ok(i) => i,
            Err(_) => return,
        };
        if i.viewers.len() >= state.config.sessions.max_viewers {
            false
        } else {
            i.viewers.push(viewer.clone());
            i.next_viewer += 1;
            i.idle_since = None;
            session.viewers_changed.notify_one();
            true
        }
    };
    if !admitted {
        bump(&state.sessions.metrics.viewers_refused, 1);
        let reason = format!(
            "the session has {} viewers, the most it takes (--max-session-viewers)",
            state.config.sessions.max_viewers
        );
        close_with(&mut socket, close::AGAIN, &reason).await;
        return;
    }
    let (code, reason) = viewer_loop(&state, &session, &viewer, &mut socket).await;
    // An image still rendering for it stops at its next stage.
    viewer.gone.cancel();
    if let Ok(mut i) = session.inner.lock() {
        i.viewers.retain(|v| !Arc::ptr_eq(v, &viewer));
        if i.viewers.is_empty() {
            i.idle_since = Some(Instant::now());
            session.viewers_changed.notify_one();
        }
    }
    if code == close::POLICY || code == close::TOO_BIG {
        bump(&state.sessions.metrics.viewers_closed_policy, 1);
    }
    finish(&mut socket, code, &reason).await;
}

/// Ends a viewer's socket: after the viewer's own close (1000, no reason) the WebSocket library
/// has queued the 1000 reply, and a second close would be refused, so that is only flushed out;
/// code 0 means the socket is gone; anything else is the server's close.
async fn finish(socket: &mut WebSocket, code: u16, reason: &str) {
    if code == close::NORMAL && reason.is_empty() {
        let _ = tokio::time::timeout(CLOSE_TIMEOUT, futures_util::SinkExt::flush(socket)).await;
    } else if code != 0 {
        close_with(socket, code, reason).await;
    }
}

/// The viewer's socket loop: sends what its outbox gets, reads its updates. Returns the close
/// to send (code 0: none, the socket is gone).
async fn viewer_loop(
    state: &AppState,
    session: &Session,
    viewer: &Viewer,
    socket: &mut WebSocket,
) -> (u16, String) {
    let limit = state.config.sessions.max_viewer_messages.max(1);
    let mut window = Instant::now();
    let mut in_window = 0u32;
    loop {
        if let Some(c) = viewer.close_asked() {
            return c;
        }
        tokio::select! {
            () = viewer.closing.notified() => {}
            () = viewer.ready.notified() => {
                let out = match viewer.outbox.lock() {
                    Ok(mut o) => o.pending.take().map(|p| {
                        o.sent = p.after;
                        p.message
                    }),
                    Err(_) => return (close::AWAY, "internal error".into()),
                };
                let Some(message) = out else { continue };
                let len = message.bytes.len() as u64;
                let send = socket.send(Message::Binary(message.bytes.clone()));
                tokio::select! {
                    r = send => if r.is_err() { return (0, String::new()) },
                    () = viewer.closing.notified() => {
                        return viewer.close_asked().unwrap_or((close::AWAY, String::new()));
                    }
                }
                drop(message);
                let m = &state.sessions.metrics;
                bump(&m.sent, 1);
                bump(&m.bytes_sent, len);
                session.with_stats(|s| {
                    s.messages_sent += 1;
                    s.bytes_sent += len;
                });
            }
            msg = socket.recv() => {
                let msg = match msg {
                    None => return (0, String::new()),
                    Some(Err(e)) => return socket_error(&e),
                    Some(Ok(m)) => m,
                };
                let now = Instant::now();
                if now.duration_since(window) >= Duration::from_secs(1) {
                    window = now;
                    in_window = 0;
                }
                in_window += 1;
                if in_window > limit {
                    return (
                        close::POLICY,
                        format!("more than {limit} messages per second (--max-viewer-messages)"),
                    );
                }
                match msg {
                    Message::Text(t) => {
                        let update: ViewerUpdate = match parse_json(t.as_str(), "update") {
                            Ok(u) => u,
                            Err(c) => return c,
                        };
                        if let Some(c) = &update.camera
                            && let Some(s) = viewer.settings()
                            && let Err(c) = check_camera(c, &s.image)
                        {
                            return c;
                        }
                        if let Some(l) = &update.lod
                            && let Err(c) = check_lod(l)
                        {
                            return c;
                        }
                        if let Ok(mut s) = viewer.settings.lock() {
                            if let Some(c) = update.camera {
                                s.camera = Some(c);
                            }
                            if let Some(l) = update.lod {
                                s.lod = l;
                            }
                        }
                    }
                    Message::Binary(_) => {
                        return (close::POLICY, "viewer messages are JSON text".into());
                    }
                    Message::Close(_) => return (close::NORMAL, String::new()),
                    Message::Ping(_) | Message::Pong(_) => {}
                }
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// The tick.

/// Starts the tick task of `session`, supervised: if it panics (a bug), the session ends —
/// removed from the server, its viewers closed with 1011 — and the panic is logged once and
/// counted (`crowdmorph_session_panics_total`), rather than leaving a session registered that
/// never ticks, never idles out and counts toward `--max-sessions`.
fn supervise(session: Arc<Session>, app: Weak<Inner>) {
    let task = tokio::spawn(run_session(session.clone(), app.clone()));
    tokio::spawn(async move {
        let Err(e) = task.await else { return };
        if !e.is_panic() {
            return;
        }
        let payload = e.into_panic();
        let why = payload
            .downcast_ref::<&str>()
            .map(|s| (*s).to_string())
            .or_else(|| payload.downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "a panic".into());
        tracing::error!(session = %session.id, panic = %why, "a session's tick task panicked; the session ends");
        if let Some(inner) = app.upgrade() {
            let state = AppState(inner);
            bump_panic(&state);
            state.sessions.remove(&session.id);
        }
        session.stop(close::INTERNAL, "session ended: internal error");
    });
}

fn bump_panic(state: &AppState) {
    state.metrics.session_panics.fetch_add(1, Ordering::Relaxed);
}

impl Session {
    /// When the session ends for want of viewers, if it has none now.
    fn idle_deadline(&self) -> Option<Instant> {
        let since = self.inner.lock().ok().and_then(|i| i.idle_since)?;
        Some(since + Duration::from_secs(u64::from(self.idle_timeout_s)))
    }
}

/// The tick task of one session.
async fn run_session(session: Arc<Session>, app: Weak<Inner>) {
    // `fps` is at least MIN_FPS (checked at creation): a period of at most ten seconds.
    let period = Duration::from_secs_f64(1.0 / f64::from(session.fps.max(MIN_FPS)));
    let start = Instant::now();
    let mut slot: u64 = 0;
    loop {
        let due = start + period.mul_f64(slot as f64);
        // Woken for the tick, for the idle timeout (whichever comes first: a slow session
        // still ends on time), when its viewers change, or when it stops.
        let idle_at = session.idle_deadline();
        let wake = idle_at.map_or(due, |t| t.min(due));
        tokio::select! {
            () = tokio::time::sleep_until(wake) => {}
            () = session.stopping.notified() => {}
            () = session.viewers_changed.notified() => {}
        }
        if session.stopped.load(Ordering::Acquire) {
            break;
        }
        let Some(inner) = app.upgrade() else { break };
        let state = AppState(inner);
        if session.idle_deadline().is_some_and(|t| Instant::now() >= t) {
            tracing::info!(session = %session.id, "session ended: no viewer for its idle timeout");
            state.sessions.remove(&session.id);
            session.stop(close::AWAY, "session ended (idle)");
            break;
        }
        if Instant::now() < due {
            continue;
        }
        if session.panic_next_tick.swap(false, Ordering::AcqRel) {
            panic!("test hook: a session tick panics");
        }
        let tick = slot + 1;
        let computed = tick_once(&state, &session, tick).await;
        let done = Instant::now();
        let next_due = start + period.mul_f64((slot + 1) as f64);
        let m = &state.sessions.metrics;
        let mut next = slot + 1;
        if done > next_due {
            // Ticks whose time passed while this one ran are skipped, not queued: the next is
            // the latest whose time has come.
            let behind = (done.duration_since(start).as_secs_f64() / period.as_secs_f64()) as u64;
            if behind > next {
                let skipped = behind - next;
                bump(&m.ticks_skipped, skipped);
                session.with_stats(|s| s.ticks_skipped += skipped);
                next = behind;
            }
        }
        match computed {
            Ticked::Delivered(jobs) => {
                let late = done > next_due;
                bump(&m.ticks, 1);
                bump(&m.jobs, jobs);
                if late {
                    bump(&m.ticks_late, 1);
                }
                session.with_stats(|s| {
                    s.ticks += 1;
                    s.ticks_late += u64::from(late);
                    s.jobs += jobs;
                });
            }
            Ticked::Skipped => {
                bump(&m.ticks_skipped, 1);
                session.with_stats(|s| s.ticks_skipped += 1);
            }
            Ticked::NoViewers => {}
        }
        slot = next;
    }
}

enum Ticked {
    /// Computed and handed to the outboxes, with the unique jobs it submitted.
    Delivered(u64),
    Skipped,
    NoViewers,
}

/// One head resolved for this tick.
#[derive(Clone, Copy)]
struct HeadAt {
    rig: u32,
    clip: u32,
    frame: u32,
    levels: u32,
    f16_ok: bool,
}

/// The vertex viewers that share a format and normals: their jobs go to the batcher as one
/// submission.
struct Group {
    format: Format,
    normals: bool,
    jobs: Vec<JobRequest>,
    keys: Vec<(u32, u32, u32, u32)>,
    index: HashMap<(u32, u32, u32, u32), u32>,
}

/// Most bytes a tick's bookkeeping holds at once for `heads` heads and `viewers` viewers:
/// each head's resolved rig, clip and frame; per viewer its job per head, the keys it is sent,
/// the entries of its message and the fan-out cache's copy of them; per group (viewers that
/// share a format and normals: at most six) the jobs, their keys and the index over them, with
/// room for the vectors' and the map's growth. At the session limits (10,000 heads, dozens of
/// viewers) this is tens of megabytes per tick, so it is charged to the queue memory before
/// any of it is built.
fn tick_bookkeeping_bytes(heads: usize, viewers: usize) -> u64 {
    type Key = (u32, u32, u32, u32);
    let groups = viewers.min(6);
    let per_viewer = size_of::<Option<u32>>() + size_of::<HeadKey>() + 2 * size_of::<u32>();
    let per_group = 2 * (size_of::<JobRequest>() + size_of::<Key>())
        + 3 * (size_of::<Key>() + size_of::<u32>() + 1);
    let per_head = size_of::<Option<HeadAt>>() + viewers * per_viewer + groups * per_group;
    (heads as u64).saturating_mul(per_head as u64)
}

fn level_for(lod: &LodChoice, camera: Option<&CameraSpec>, position: [f32; 3]) -> u32 {
    match lod {
        LodChoice::Fixed(l) => *l,
        LodChoice::ByDistance { by_distance } => {
            let Some(c) = camera else {
                return 0;
            };
            let d = Vec3::from(position).distance(Vec3::from(c.position));
            level_at(by_distance, d)
        }
    }
}

/// The level of the last entry whose metres ≤ `d` (0 nearer than the first). The table is
/// ascending (`check_lod` refuses any other), so the entries at or below `d` are a prefix and
/// a binary search finds its end: this runs per head, per viewer, per tick.
fn level_at(by_distance: &[[f32; 2]], d: f32) -> u32 {
    match by_distance.partition_point(|[m, _]| *m <= d) {
        0 => 0,
        n => by_distance.get(n - 1).map_or(0, |[_, l]| *l as u32),
    }
}

async fn tick_once(state: &AppState, session: &Arc<Session>, tick: u64) -> Ticked {
    let arrived = std::time::Instant::now();
    let (heads, layout_rev, viewers) = {
        let Ok(mut i) = session.inner.lock() else {
            return Ticked::Skipped;
        };
        if let Some(n) = i.next_heads.take() {
            i.heads = n;
            i.layout_rev += 1;
        }
        i.tick = tick;
        (i.heads.clone(), i.layout_rev, i.viewers.clone())
    };
    if viewers.is_empty() {
        return Ticked::NoViewers;
    }
    // What this tick builds per head is charged first, as every request's memory is.
    let Ok(_bookkeeping) =
        state.reserve_queue_memory(tick_bookkeeping_bytes(heads.len(), viewers.len()))
    else {
        return Ticked::Skipped;
    };

    // Every head once: its rig at this tick's generation, clip and frame.
    let mode = if session.wrap {
        FrameMode::Wrap
    } else {
        FrameMode::Clamp
    };
    let mut rigs: Vec<Arc<RigEntry>> = Vec::new();
    let mut rig_at: HashMap<&str, Option<u32>> = HashMap::new();
    let at: Vec<Option<HeadAt>> = heads
        .iter()
        .map(|h| {
            let ri = *rig_at.entry(h.rig.as_str()).or_insert_with(|| {
                state.registry.get(&h.rig).map(|e| {
                    rigs.push(e);
                    (rigs.len() - 1) as u32
                })
            });
            let ri = ri?;
            let entry = &rigs[ri as usize];
            let rig = entry.rig();
            let ci = entry.clip_index(&h.clip)?;
            let clip = &rig.clips[ci];
            let elapsed = (tick - 1) as f64 * f64::from(clip.fps) / f64::from(session.fps);
            let frame = clip
                .resolve_frame(h.offset.saturating_add(elapsed as i64), mode)
                .ok()?;
            Some(HeadAt {
                rig: ri,
                clip: ci as u32,
                frame,
                levels: rig.lod.levels.len() as u32,
                f16_ok: super::api::head_reach(entry) <= MAX_F16,
            })
        })
        .collect();

    // Each viewer's job per head, grouped by what its buffers hold.
    let mut groups: Vec<Group> = Vec::new();
    let mut plans: Vec<(Arc<Viewer>, usize, Vec<Option<u32>>)> = Vec::new();
    let mut frames: Vec<(Arc<Viewer>, ViewerSettings)> = Vec::new();
    for v in &viewers {
        let Some(s) = v.settings() else { continue };
        if s.output == ViewerOutput::Frames {
            frames.push((v.clone(), s));
            continue;
        }
        let g = match groups
            .iter()
            .position(|g| g.format == s.format && g.normals == s.normals)
        {
            Some(g) => g,
            None => {
                groups.push(Group {
                    format: s.format,
                    normals: s.normals,
                    jobs: Vec::new(),
                    keys: Vec::new(),
                    index: HashMap::new(),
                });
                groups.len() - 1
            }
        };
        let group = &mut groups[g];
        let jobs: Vec<Option<u32>> = heads
            .iter()
            .zip(&at)
            .map(|(h, a)| {
                let a = (*a)?;
                if group.format == Format::F16 && !a.f16_ok {
                    return None;
                }
                let lod = level_for(&s.lod, s.camera.as_ref(), h.position).min(a.levels - 1);
                let key = (a.rig, a.clip, a.frame, lod);
                Some(*group.index.entry(key).or_insert_with(|| {
                    group.keys.push(key);
                    group
                        .jobs
                        .push(job_request(&rigs[a.rig as usize], a.clip, a.frame, lod));
                    (group.jobs.len() - 1) as u32
                }))
            })
            .collect();
        plans.push((v.clone(), g, jobs));
    }

    // Images are drawn on the blocking pool, one at a time per viewer; they bypass the
    // batcher, as `POST /v1/crowd/render` does.
    for (v, s) in frames {
        start_frame(state, session, &heads, &at, &rigs, tick, v, s);
    }
    if groups.iter().all(|g| g.jobs.is_empty()) && plans.is_empty() {
        return Ticked::Delivered(0);
    }

    // The blended outputs count against the queue memory while the tick holds them.
    let gpu = state.engine.gpu_memory().is_some();
    let out_bytes: u64 = groups
        .iter()
        .flat_map(|g| {
            g.jobs.iter().map(move |j| {
                let rig = j.entry.prepared.at_level(j.lod).rig();
                super::api::job_output_bytes(rig, g.format, g.normals, false, gpu)
            })
        })
        .sum();
    let Ok(memory) = state.reserve_queue_memory(out_bytes) else {
        return Ticked::Skipped;
    };
    let mut tickets = Vec::with_capacity(groups.len());
    let jobs: u64 = groups.iter().map(|g| g.jobs.len() as u64).sum();
    for g in &groups {
        state
            .metrics
            .jobs_requested
            .fetch_add(g.jobs.len() as u64, Ordering::Relaxed);
        match state.scheduler.submit(g.jobs.clone(), g.format, g.normals) {
            Ok(t) => tickets.push(t),
            Err(ScheduleError::QueueFull) => {
                state.metrics.reject("queue_full");
                return Ticked::Skipped;
            }
            Err(_) => return Ticked::Skipped,
        }
    }
    let mut outcomes = Vec::with_capacity(tickets.len());
    for t in tickets {
        match tokio::time::timeout(state.config.request_timeout, t).await {
            Ok(Ok(Ok(o))) => outcomes.push(o),
            _ => return Ticked::Skipped,
        }
    }

    // Fan-out.
    let mut cache: HashMap<(usize, bool, Vec<u32>), Arc<Encoded>> = HashMap::new();
    for (v, g, jobs) in plans {
        let group = &groups[g];
        let outcome = &outcomes[g];
        let keys: Arc<Vec<HeadKey>> = Arc::new(
            jobs.iter()
                .map(|j| match j {
                    None => MISSING_KEY,
                    Some(j) => {
                        let (r, c, f, l) = group.keys[*j as usize];
                        HeadKey {
                            generation: rigs[r as usize].generation,
                            clip: c,
                            frame: f,
                            lod: l,
                        }
                    }
                })
                .collect(),
        );
        // Retried when the viewer's socket took a message meanwhile: "unchanged" must refer
        // to what it last received.
        for _attempt in 0..4 {
            let base = match v.outbox.lock() {
                Ok(o) => o.sent.clone(),
                Err(_) => break,
            };
            let with_layout = base.layout_rev != layout_rev || base.keys.len() != keys.len();
            let entries: Vec<u32> = jobs
                .iter()
                .enumerate()
                .map(|(i, j)| match j {
                    _ if !with_layout && base.keys[i] == keys[i] => HEAD_UNCHANGED,
                    None => HEAD_MISSING,
                    Some(j) => *j,
                })
                .collect();
            let cache_key = (g, with_layout, entries);
            let message = match cache.get(&cache_key) {
                Some(m) => m.clone(),
                None => {
                    let Some(m) = encode_vertices(
                        state,
                        tick,
                        with_layout.then_some(heads.as_slice()),
                        group,
                        outcome,
                        &rigs,
                        &heads,
                        &cache_key.2,
                        arrived,
                    ) else {
                        bump(&state.sessions.metrics.dropped_memory, 1);
                        session.with_stats(|s| s.messages_dropped += 1);
                        break;
                    };
                    let m = Arc::new(m);
                    cache.insert(cache_key, m.clone());
                    m
                }
            };
            let Ok(mut o) = v.outbox.lock() else { break };
            if o.sent.version != base.version {
                continue;
            }
            if o.pending.is_some() {
                bump(&state.sessions.metrics.dropped_slow, 1);
                session.with_stats(|s| s.messages_dropped += 1);
            }
            o.pending = Some(Outgoing {
                message,
                after: Baseline {
                    version: base.version + 1,
                    layout_rev,
                    keys: keys.clone(),
                },
            });
            drop(o);
            v.ready.notify_one();
            break;
        }
    }
    drop(memory);
    Ticked::Delivered(jobs)
}

/// Encodes a [`crowdmorph_proto::TickVertices`] stream message: the variant, the tick and the
/// layout, then the same fields as a crowd-frame response, with payloads aligned to 16 bytes
/// from the start of the message. Its length is computed first and charged to the queue
/// memory before anything of its size is allocated; `None` when the queue memory is full.
#[allow(clippy::too_many_arguments)]
fn encode_vertices(
    state: &AppState,
    tick: u64,
    layout: Option<&[SessionHead]>,
    group: &Group,
    outcome: &super::scheduler::Outcome,
    rigs: &[Arc<RigEntry>],
    heads: &[SessionHead],
    entries: &[u32],
    arrived: std::time::Instant,
) -> Option<Encoded> {
    let mut prefix = Vec::with_capacity(64);
    crate::codec::put_varint(&mut prefix, 0);
    crate::codec::put_varint(&mut prefix, tick);
    // Buffers in order of first appearance among the heads.
    let mut local: HashMap<u32, u32> = HashMap::new();
    let mut parts: Vec<FrameBufferParts<'_>> = Vec::new();
    let head_buffers: Vec<HeadBuffer> = heads
        .iter()
        .zip(entries)
        .map(|(h, &e)| {
            let buffer = if e == HEAD_UNCHANGED || e == HEAD_MISSING {
                e
            } else {
                *local.entry(e).or_insert_with(|| {
                    let (r, c, f, l) = group.keys[e as usize];
                    let entry = &rigs[r as usize];
                    let out = &outcome.outputs[e as usize];
                    parts.push(FrameBufferParts {
                        rig: &entry.id,
                        clip: &entry.rig().clips[c as usize].name,
                        frame: f,
                        lod: l,
                        vertices: entry.prepared.at_level(l).rig().vertex_count() as u32,
                        quantization: (group.format == Format::Q16).then_some(entry.qbox),
                        positions: out.positions.clone(),
                        normals: if group.normals {
                            out.normals.clone()
                        } else {
                            None
                        },
                    });
                    (parts.len() - 1) as u32
                })
            };
            HeadBuffer {
                head: h.head,
                buffer,
            }
        })
        .collect();
    let timings = FrameTimings {
        queue_us: outcome.queue.as_micros() as u64,
        compute_us: outcome.compute_ns / 1000,
        total_us: arrived.elapsed().as_micros() as u64,
        gpu_us: outcome.gpu_ns.map(|g| g / 1000),
    };
    // The layout's length (bincode, without encoding it; `None` is one byte), then the
    // message's: charged before either is allocated.
    let middle_len = crate::codec::wire_len(&layout).unwrap_or(1);
    let total = FrameResponseEncoder::encoded_len_within(
        prefix.len(),
        middle_len,
        group.format,
        group.normals,
        &parts,
        &head_buffers,
        &timings,
    );
    let memory = state
        .reserve_queue_memory((total + middle_len) as u64)
        .ok()?;
    let middle = crate::codec::to_wire(&layout).unwrap_or_else(|_| vec![0]);
    let chunks = FrameResponseEncoder::encode_within(
        prefix,
        &middle,
        group.format,
        group.normals,
        &parts,
        &head_buffers,
        &timings,
    );
    drop(middle);
    let mut out = Vec::with_capacity(total);
    for c in &chunks {
        out.extend_from_slice(c);
    }
    debug_assert_eq!(out.len(), total, "the counted length is the encoding's");
    drop(chunks);
    let mut memory = memory;
    let keep = (total as u64).div_ceil(1024).max(1) as usize;
    if let Some(extra) = memory.num_permits().checked_sub(keep).filter(|&n| n > 0) {
        // The layout's encoding and the chunks are gone; the message keeps only its bytes.
        drop(memory.split(extra));
    }
    Some(Encoded {
        bytes: Bytes::from(out),
        _memory: memory,
    })
}

/// Starts drawing this tick for a viewer that wants images, unless its previous image is
/// still being drawn.
#[allow(clippy::too_many_arguments)]
fn start_frame(
    state: &AppState,
    session: &Arc<Session>,
    heads: &[SessionHead],
    at: &[Option<HeadAt>],
    rigs: &[Arc<RigEntry>],
    tick: u64,
    viewer: Arc<Viewer>,
    s: ViewerSettings,
) {
    if viewer.rendering.swap(true, Ordering::AcqRel) {
        bump(&state.sessions.metrics.dropped_rendering, 1);
        session.with_stats(|st| st.messages_dropped += 1);
        return;
    }
    let mut req_heads = Vec::new();
    let mut placements = Vec::new();
    for (h, a) in heads.iter().zip(at) {
        let Some(a) = a else { continue };
        let entry = &rigs[a.rig as usize];
        let lod = level_for(&s.lod, s.camera.as_ref(), h.position).min(a.levels - 1);
        req_heads.push(crowdmorph_proto::Head {
            head: h.head,
            rig: entry.id.clone(),
            clip: entry.rig().clips[a.clip as usize].name.clone(),
            frame: i64::from(a.frame),
            lod,
        });
        placements.push(placement(h));
    }
    let req = RenderRequest {
        heads: req_heads,
        wrap: true,
        placements: Some(placements),
        camera: s.camera,
        image: Some(s.image),
    };
    let state = state.clone();
    let session = session.clone();
    let cancel = viewer
        .gone
        .with_deadline(std::time::Instant::now() + state.config.request_timeout);
    tokio::spawn(async move {
        let rendered = state.render_for_session(req, cancel).await;
        let delivered = match rendered {
            Ok((image, width, height, format)) => {
                let message = crowdmorph_proto::StreamMessage::Frame(crowdmorph_proto::TickFrame {
                    tick,
                    format,
                    width,
                    height,
                    image: crowdmorph_proto::Blob(image),
                });
                // The message's length is known without encoding it: charged first.
                match crate::codec::wire_len(&message) {
                    Ok(len) => match state.reserve_queue_memory(len as u64) {
                        Ok(permit) => crate::codec::to_wire(&message).ok().map(|bytes| {
                            Arc::new(Encoded {
                                bytes: Bytes::from(bytes),
                                _memory: permit,
                            })
                        }),
                        Err(_) => {
                            bump(&state.sessions.metrics.dropped_memory, 1);
                            None
                        }
                    },
                    Err(_) => None,
                }
            }
            Err(e) if e.status.is_client_error() => {
                // The viewer's own choice can never be drawn (its image over the viewers'
                // share, a crowd too costly at its size): tell it once and close it, rather
                // than failing at every tick.
                tracing::debug!(error = %e.message, "session frame cannot be drawn; closing the viewer");
                bump(&state.sessions.metrics.viewers_closed_policy, 1);
                viewer.ask_close(close::POLICY, &truncate(e.message));
                None
            }
            Err(e) => {
                // Busy (503), cancelled: this tick's image is skipped.
                tracing::debug!(error = %e.message, "session frame not drawn");
                bump(&state.sessions.metrics.dropped_rendering, 1);
                None
            }
        };
        if let Some(message) = delivered
            && let Ok(mut o) = viewer.outbox.lock()
        {
            if o.pending.is_some() {
                bump(&state.sessions.metrics.dropped_slow, 1);
                session.with_stats(|st| st.messages_dropped += 1);
            }
            let after = Baseline {
                version: o.sent.version + 1,
                layout_rev: u64::MAX,
                keys: Arc::new(Vec::new()),
            };
            o.pending = Some(Outgoing { message, after });
            drop(o);
            viewer.ready.notify_one();
        }
        viewer.rendering.store(false, Ordering::Release);
    });
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
        };
        for n in [0, 1, heads.len()] {
            let (a, b) = (now(&heads[..n]), before(&heads[..n]));
            let json = serde_json::to_vec(&a).expect("JSON");
            assert_eq!(json, serde_json::to_vec(&b).expect("JSON"));
            let wire = crate::codec::to_wire(&a).expect("bincode");
            assert_eq!(wire, crate::codec::to_wire(&b).expect("bincode"));
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
            crate::codec::to_wire(&list).expect("bincode"),
            crate::codec::to_wire(&old).expect("bincode")
        );
    }

    /// The linear search `level_at` replaced: the last entry whose metres ≤ `d`.
    fn level_by_scan(by_distance: &[[f32; 2]], d: f32) -> u32 {
        by_distance
            .iter()
            .rev()
            .find(|[m, _]| *m <= d)
            .map_or(0, |[_, l]| *l as u32)
    }

    #[test]
    fn the_binary_search_finds_the_level_the_scan_did() {
        let tables: Vec<Vec<[f32; 2]>> = vec![
            vec![],
            vec![[5.0, 3.0]],
            vec![[0.0, 1.0], [2.0, 2.0], [4.0, 3.0]],
            // Repeated thresholds: the last of them counts, as the scan's.
            vec![[1.0, 1.0], [3.0, 2.0], [3.0, 5.0], [3.0, 4.0], [6.0, 6.0]],
            // Negative thresholds, and the 64 entries `check_lod` allows.
            vec![[-2.0, 7.0], [-1.0, 0.0], [10.0, 2.0]],
            (0..64).map(|k| [k as f32 * 0.5, (k % 7) as f32]).collect(),
        ];
        for table in &tables {
            assert!(
                check_lod(&LodChoice::ByDistance {
                    by_distance: table.clone()
                })
                .is_ok(),
                "{table:?} is a table viewers may send"
            );
            // On every threshold, just either side of it, between, below and above them all.
            let mut ds = vec![-1e30, -3.0, 0.0, 1e30, f32::INFINITY, f32::NAN];
            for [m, _] in table {
                ds.extend([*m, m.next_down(), m.next_up(), m + 0.25]);
            }
            for d in ds {
                assert_eq!(
                    level_at(table, d),
                    level_by_scan(table, d),
                    "{table:?} at {d}"
                );
            }
        }
        // Spot values, so the test does not only compare two searches with each other.
        let t = &tables[3];
        assert_eq!(
            [0.5, 1.0, 2.9, 3.0, 5.0, 6.0, 9.0].map(|d| level_at(t, d)),
            [0, 1, 1, 4, 4, 6, 6]
        );
        let camera = CameraSpec {
            position: [0.0, 0.0, 10.0],
            target: [0.0; 3],
            fov_y: 30.0,
            near: None,
            far: None,
        };
        let lod = LodChoice::ByDistance {
            by_distance: t.clone(),
        };
        assert_eq!(level_for(&lod, Some(&camera), [0.0, 0.0, 7.0]), 4);
        assert_eq!(level_for(&lod, None, [0.0, 0.0, 7.0]), 0);
        assert_eq!(level_for(&LodChoice::Fixed(3), Some(&camera), [0.0; 3]), 3);
    }
}
