//! Crowd sessions in the server state: the sessions by id, each session's heads, viewers
//! and counters, a viewer's settings and one-message outbox, and the session API's limits.
//! The handlers, the viewer protocol and the tick are `routes::sessions`; nothing here knows
//! the server state.

use std::collections::{BTreeMap, HashMap};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use bytes::Bytes;
use crowdmorph_proto::{
    CameraSpec, Format, ImageOptions, LodChoice, Placement, SessionHead, SessionStats, ViewerOutput,
};
use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use tokio::sync::Notify;
use tokio::time::Instant;

use super::metrics::ReasonLabel;

pub use super::config::{DEFAULT_MAX_VIEWER_PIXELS, SessionLimits};

/// Largest text message a viewer may send.
pub const MAX_VIEWER_MESSAGE_BYTES: usize = 64 << 10;
/// How long a close frame may take to go out before the socket is dropped.
pub(crate) const CLOSE_TIMEOUT: Duration = Duration::from_secs(1);
/// Highest tick rate.
pub(crate) const MAX_FPS: f32 = 120.0;
/// Lowest tick rate: a tick every ten seconds. Below it a period is a client's typo (1e-30
/// ticks per second is a period past what a `Duration` holds).
pub const MIN_FPS: f32 = 0.1;
/// Longest idle timeout, seconds (a day).
pub(crate) const MAX_IDLE_TIMEOUT_S: u32 = 86_400;

/// RFC 6455 close codes the stream uses.
pub(crate) mod close {
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

    /// A close reason cut to at most 123 bytes (RFC 6455 §5.5).
    pub fn truncate(mut s: String) -> String {
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
}

/// Checks a viewer's LOD choice: at most 64 distances, finite and ascending (the tick's
/// binary search relies on it), whole levels ≥ 0; a close code and reason otherwise.
pub(crate) fn check_lod(l: &LodChoice) -> Result<(), (u16, String)> {
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

/// Where head `h` stands in the crowd, as the renderer places it.
pub(crate) fn placement(h: &SessionHead) -> Placement {
    Placement {
        head: h.head,
        position: h.position,
        yaw: h.yaw,
        scale: h.scale,
    }
}

/// Counters over all sessions, for `/metrics`: handles on series of the server's registry
/// (see [`SessionMetrics::register`]), each label value made at the start so that every
/// series is there at 0.
#[derive(Debug)]
pub struct SessionMetrics {
    ticks: Family<ResultLabel, Counter>,
    pub(crate) ticks_on_time: Counter,
    pub(crate) ticks_late: Counter,
    pub(crate) ticks_skipped: Counter,
    pub(crate) jobs: Counter,
    messages: Family<ResultLabel, Counter>,
    pub(crate) sent: Counter,
    pub(crate) dropped_slow: Counter,
    pub(crate) dropped_memory: Counter,
    pub(crate) dropped_rendering: Counter,
    pub(crate) bytes_sent: Counter,
    viewers_closed: Family<ReasonLabel, Counter>,
    pub(crate) viewers_refused: Counter,
    pub(crate) viewers_closed_policy: Counter,
    live: Family<ResultLabel, Counter>,
    pub(crate) live_accepted: Counter,
    pub(crate) live_shed: Counter,
    pub(crate) live_invalid: Counter,
}

/// The `result` label of the session tick and message counters.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct ResultLabel {
    result: &'static str,
}

impl Default for SessionMetrics {
    fn default() -> Self {
        let ticks = Family::<ResultLabel, Counter>::default();
        let messages = Family::<ResultLabel, Counter>::default();
        let viewers_closed = Family::<ReasonLabel, Counter>::default();
        let live = Family::<ResultLabel, Counter>::default();
        let result = |f: &Family<ResultLabel, Counter>, result| {
            f.get_or_create_owned(&ResultLabel { result })
        };
        SessionMetrics {
            ticks_on_time: result(&ticks, "on_time"),
            ticks_late: result(&ticks, "late"),
            ticks_skipped: result(&ticks, "skipped"),
            jobs: Counter::default(),
            sent: result(&messages, "sent"),
            dropped_slow: result(&messages, "dropped_slow"),
            dropped_memory: result(&messages, "dropped_memory"),
            dropped_rendering: result(&messages, "dropped_rendering"),
            bytes_sent: Counter::default(),
            // A viewer refused because its session is full is closed with reason `full`.
            viewers_refused: viewers_closed.get_or_create_owned(&ReasonLabel::new("full")),
            viewers_closed_policy: viewers_closed.get_or_create_owned(&ReasonLabel::new("policy")),
            live_accepted: result(&live, "accepted"),
            live_shed: result(&live, "shed"),
            live_invalid: result(&live, "invalid"),
            live,
            ticks,
            messages,
            viewers_closed,
        }
    }
}

impl SessionMetrics {
    /// Registers the session counters with the server's registry (once, before the
    /// registry's [`Metrics`](super::metrics::Metrics) is shared).
    pub fn register(&self, r: &mut prometheus_client::registry::Registry) {
        r.register(
            "crowdmorph_session_ticks",
            "Session ticks by result: on_time and late were computed and delivered; skipped \
             were never computed",
            self.ticks.clone(),
        );
        r.register(
            "crowdmorph_session_jobs",
            "Unique jobs sessions submitted to the batcher",
            self.jobs.clone(),
        );
        r.register(
            "crowdmorph_session_messages",
            "Stream messages by result: sent, or dropped because a newer tick replaced them \
             (slow), the queue memory was full (memory) or the viewer's previous image was \
             still rendering (rendering)",
            self.messages.clone(),
        );
        r.register(
            "crowdmorph_session_bytes_sent",
            "Bytes of stream messages sent",
            self.bytes_sent.clone(),
        );
        r.register(
            "crowdmorph_session_live_messages",
            "Live input messages by result: accepted, shed over the session's --max-live-rate, \
             or invalid (refused with a named error)",
            self.live.clone(),
        );
        r.register(
            "crowdmorph_session_viewers_closed",
            "Viewers the server closed, by reason",
            self.viewers_closed.clone(),
        );
    }
}

pub(crate) fn bump(c: &Counter, n: u64) {
    c.inc_by(n);
}

/// Every session of the server, by id.
#[derive(Debug, Default)]
pub struct Sessions {
    pub(crate) map: Mutex<BTreeMap<String, Arc<Session>>>,
    pub(crate) next_id: AtomicU64,
    /// Counters over all sessions.
    pub metrics: SessionMetrics,
}

impl Sessions {
    /// Session `id`, if it exists.
    pub(crate) fn get(&self, id: &str) -> Option<Arc<Session>> {
        self.map.lock().ok().and_then(|m| m.get(id).cloned())
    }

    pub(crate) fn all(&self) -> Vec<Arc<Session>> {
        self.map
            .lock()
            .map(|m| m.values().cloned().collect())
            .unwrap_or_default()
    }

    pub(crate) fn remove(&self, id: &str) -> Option<Arc<Session>> {
        self.map.lock().ok()?.remove(id)
    }

    /// Test hook: makes session `id`'s next tick panic, so that the tick task's supervision
    /// can be tested. Returns whether the session exists.
    #[doc(hidden)]
    pub fn panic_next_tick(&self, id: &str) -> bool {
        self.get(id)
            .map(|s| s.panic_next_tick.store(true, Ordering::Release))
            .is_some()
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

    /// Sessions that exist now and the viewers connected to them, for the gauges
    /// `crowdmorph_sessions` and `crowdmorph_session_viewers`.
    pub fn counts(&self) -> (u64, u64) {
        let sessions = self.all();
        let viewers: usize = sessions.iter().map(|s| s.viewer_count()).sum();
        (sessions.len() as u64, viewers as u64)
    }
}

/// One session.
#[derive(Debug)]
pub struct Session {
    pub(crate) id: String,
    pub(crate) fps: f32,
    pub(crate) wrap: bool,
    pub(crate) idle_timeout_s: u32,
    pub(crate) inner: Mutex<SessionInner>,
    /// Wakes the tick task when the session stops.
    pub(crate) stopping: Notify,
    pub(crate) stopped: AtomicBool,
    /// Wakes the tick task when its viewers change, so an idle timeout is kept whatever the
    /// tick period.
    pub(crate) viewers_changed: Notify,
    /// Test hook: the next tick panics (the supervision of the tick task is tested with it).
    pub(crate) panic_next_tick: AtomicBool,
    /// Its live heads' input from producers.
    pub(crate) live: crate::live::LiveInputs,
}

#[derive(Debug)]
pub(crate) struct SessionInner {
    /// The heads of the last tick.
    pub(crate) heads: Arc<Vec<SessionHead>>,
    /// The heads after the patches received since, applied at the next tick.
    pub(crate) next_heads: Option<Arc<Vec<SessionHead>>>,
    /// Bumped whenever `heads` changes; viewers get the layout when theirs is older.
    pub(crate) layout_rev: u64,
    pub(crate) viewers: Vec<Arc<Viewer>>,
    pub(crate) next_viewer: u64,
    pub(crate) tick: u64,
    pub(crate) stats: SessionStats,
    /// When the last viewer left (or the session started without one).
    pub(crate) idle_since: Option<Instant>,
    /// Graph heads sent to a node by patches since the last tick: (head id, node), in order.
    pub(crate) jumps: Vec<(u64, String)>,
    /// Liveliness of the heads without their own (`SessionRequest::alive`, as the last patch
    /// left it); read by each tick.
    pub(crate) alive: Option<crowdmorph_proto::Alive>,
}

/// What identifies a head's buffer for a viewer: the same key means the same vertices.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub(crate) struct HeadKey {
    pub(crate) generation: u64,
    pub(crate) pose: crowdmorph_core::rig::Pose,
    pub(crate) lod: u32,
    pub(crate) joints: crowdmorph_core::rig::JointPose,
}

pub(crate) const MISSING_KEY: HeadKey = HeadKey {
    generation: u64::MAX,
    pose: crowdmorph_core::rig::Pose::Frame { clip: 0, frame: 0 },
    lod: 0,
    joints: crowdmorph_core::rig::JointPose::NONE,
};

/// What a viewer last received: "unchanged" is relative to this.
#[derive(Clone, Debug)]
pub(crate) struct Baseline {
    pub(crate) version: u64,
    /// `u64::MAX` before the first message.
    pub(crate) layout_rev: u64,
    pub(crate) keys: Arc<Vec<HeadKey>>,
    /// For a temporal viewer: per head id, the buffer it last received (what residuals are
    /// against). Empty for other viewers.
    pub(crate) prev: Arc<HashMap<u64, HeadPrev>>,
    /// For a viewer that asked for `layers`: per head id, the compact layer inputs it last
    /// received (a head is sent its inputs when they differ). Empty for other viewers.
    pub(crate) layers: Arc<SentLayers>,
}

/// What a viewer that asked for `layers` last received: per head id, its compact layer inputs
/// (shared with the tick that computed them), holding their queue memory.
#[derive(Debug, Default)]
pub(crate) struct SentLayers {
    pub(crate) inputs: HashMap<u64, Arc<[f32]>>,
    pub(crate) _memory: Option<crate::admission::memory::Charge>,
}

impl Baseline {
    /// Before the first message.
    pub(crate) fn empty() -> Baseline {
        Baseline {
            version: 0,
            layout_rev: u64::MAX,
            keys: Arc::new(Vec::new()),
            prev: Arc::new(HashMap::new()),
            layers: Arc::new(SentLayers::default()),
        }
    }
}

/// A copy of one job's q16 output that temporal viewers keep as their reference after the tick's
/// outputs are gone (a copy: the outputs are views of a whole batch's buffer), holding its
/// queue memory.
#[derive(Debug)]
pub(crate) struct Retained {
    pub(crate) positions: Bytes,
    pub(crate) normals: Option<Bytes>,
    pub(crate) _memory: crate::admission::memory::Charge,
}

/// What a temporal viewer last received for one head.
#[derive(Clone, Debug)]
pub(crate) struct HeadPrev {
    pub(crate) data: Arc<Retained>,
    pub(crate) generation: u64,
    pub(crate) lod: u32,
    /// The tick from which its next keyframe is counted.
    pub(crate) key_tick: u64,
}

/// A message encoded once, possibly shared by several viewers, holding its queue memory.
#[derive(Debug)]
pub(crate) struct Encoded {
    pub(crate) bytes: Bytes,
    /// Whatever keeps its memory charged (a queue-memory charge), given back with it.
    pub(crate) _memory: Box<dyn std::fmt::Debug + Send + Sync>,
}

#[derive(Debug)]
pub(crate) struct Outgoing {
    /// The tick's expression-layer inputs (`StreamMessage` variant 4), sent just before
    /// `message` so that a head draws its new layers with its new vertices.
    pub(crate) layers: Option<Encoded>,
    pub(crate) message: Arc<Encoded>,
    /// The viewer's baseline once this is sent.
    pub(crate) after: Baseline,
}

#[derive(Debug)]
pub(crate) struct Outbox {
    pub(crate) pending: Option<Outgoing>,
    pub(crate) sent: Baseline,
}

/// A viewer's choices: its hello, then its updates.
#[derive(Clone, Debug)]
pub(crate) struct ViewerSettings {
    pub(crate) output: ViewerOutput,
    pub(crate) format: Format,
    pub(crate) normals: bool,
    pub(crate) camera: Option<CameraSpec>,
    pub(crate) lod: LodChoice,
    pub(crate) image: ImageOptions,
    /// Residuals against each head's previous buffer: `Some(keyframe interval)`.
    pub(crate) temporal: Option<u32>,
    /// Messages compressed with this.
    pub(crate) compression: Option<crowdmorph_proto::MessageEncoding>,
    /// Also send each head's expression-layer inputs when they change.
    pub(crate) layers: bool,
    /// Near-clones: a head `d` metres from the camera's eye may be off by `tolerance × d`
    /// diagonals (0: exact poses).
    pub(crate) tolerance: f32,
}

#[derive(Debug)]
pub(crate) struct Viewer {
    pub(crate) settings: Mutex<ViewerSettings>,
    pub(crate) outbox: Mutex<Outbox>,
    pub(crate) ready: Notify,
    /// A close the server asked for (the session ended), and its wake-up.
    pub(crate) close: Mutex<Option<(u16, String)>>,
    pub(crate) closing: Notify,
    /// An image for this viewer is being rendered.
    pub(crate) rendering: AtomicBool,
    /// Raised when the viewer leaves: an image being rendered for it stops.
    pub(crate) gone: crowdmorph_core::cancel::Cancel,
}

impl Viewer {
    pub(crate) fn new(settings: ViewerSettings) -> Viewer {
        Viewer {
            settings: Mutex::new(settings),
            outbox: Mutex::new(Outbox {
                pending: None,
                sent: Baseline::empty(),
            }),
            ready: Notify::new(),
            close: Mutex::new(None),
            closing: Notify::new(),
            rendering: AtomicBool::new(false),
            gone: crowdmorph_core::cancel::Cancel::manual(),
        }
    }

    pub(crate) fn settings(&self) -> Option<ViewerSettings> {
        self.settings.lock().ok().map(|s| s.clone())
    }

    pub(crate) fn ask_close(&self, code: u16, reason: &str) {
        if let Ok(mut c) = self.close.lock() {
            c.get_or_insert((code, reason.to_string()));
        }
        self.closing.notify_one();
    }

    pub(crate) fn close_asked(&self) -> Option<(u16, String)> {
        self.close.lock().ok().and_then(|c| c.clone())
    }
}

impl Session {
    pub(crate) fn viewer_count(&self) -> usize {
        self.inner.lock().map(|i| i.viewers.len()).unwrap_or(0)
    }

    /// Stops the tick task and closes every viewer.
    pub(crate) fn stop(&self, code: u16, reason: &str) {
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
    pub(crate) fn info(&self) -> InfoNow {
        let (heads, viewers, tick, stats, alive) = match self.inner.lock() {
            Ok(i) => (
                i.next_heads.clone().unwrap_or_else(|| i.heads.clone()),
                i.viewers.len() as u32,
                i.tick,
                i.stats,
                i.alive.clone(),
            ),
            Err(_) => (Arc::default(), 0, 0, SessionStats::default(), None),
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
            alive,
        }
    }

    /// The session's liveliness for heads without their own.
    pub(crate) fn alive(&self) -> Option<crowdmorph_proto::Alive> {
        self.inner.lock().ok().and_then(|i| i.alive.clone())
    }

    pub(crate) fn with_stats(&self, f: impl FnOnce(&mut SessionStats)) {
        if let Ok(mut i) = self.inner.lock() {
            f(&mut i.stats);
        }
    }
}

/// A session's [`crowdmorph_proto::SessionInfo`], holding its heads by reference: it serializes
/// to exactly the bytes a `SessionInfo` of the same values does (same fields in the same order;
/// an `Arc` is written as what it holds), without copying the heads first.
#[derive(Debug, serde::Serialize)]
pub(crate) struct InfoNow {
    pub(crate) id: String,
    pub(crate) fps: f32,
    pub(crate) wrap: bool,
    pub(crate) idle_timeout_s: u32,
    pub(crate) tick: u64,
    pub(crate) heads: Arc<Vec<SessionHead>>,
    pub(crate) viewers: u32,
    pub(crate) stats: SessionStats,
    pub(crate) alive: Option<crowdmorph_proto::Alive>,
}

/// [`crowdmorph_proto::SessionList`] of [`InfoNow`]s, the same way.
#[derive(Debug, serde::Serialize)]
pub(crate) struct ListNow {
    pub(crate) sessions: Vec<InfoNow>,
}

/// Most bytes a session's info takes in JSON besides its heads: the field names, the id and
/// every number at its widest (14 `u64`s and `u32`s of at most 20 digits, one `f32`).
pub(crate) const INFO_JSON_BYTES: u64 = 640;

/// Most bytes one head takes in JSON besides its two names: the field names and every number
/// at its widest (`u64`, `i64`: 20 characters; five `f32`s: 15 each), with the separators.
pub(crate) const HEAD_JSON_BYTES: u64 = 200;

/// Most bytes a string takes in JSON: each byte at most a six-byte `\u00XX` escape.
pub(crate) fn json_str_bytes(s: &str) -> u64 {
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
    pub(crate) fn response_bytes(&self) -> u64 {
        info_bytes(&self.id, &self.heads)
    }
}

/// [`InfoNow::response_bytes`] of a session `id` with `heads`, known before the session is
/// created or a patch applied: their answers are charged before the change, so that a full
/// queue refuses the request (503, nothing changed) instead of its answer (a retry would
/// change it twice).
pub(crate) fn info_bytes(id: &str, heads: &[SessionHead]) -> u64 {
    let heads: u64 = heads
        .iter()
        .map(|h| {
            HEAD_JSON_BYTES
                + json_str_bytes(&h.rig)
                + json_str_bytes(&h.clip)
                + extras_json_bytes(h)
        })
        .sum();
    // The session's `alive` is charged at its widest: a patch may set it later.
    INFO_JSON_BYTES
        + alive_json_bytes(Some(&crowdmorph_proto::Alive::default()))
        + json_str_bytes(id)
        + heads
}

/// Most bytes a field takes in JSON besides its strings: its name, an `f32` triple or
/// quadruple at its widest (15 characters a number), separators.
const FIELD_JSON_BYTES: u64 = 100;

/// Most bytes a head's graph, joint overrides, layers and clamp take in JSON.
fn extras_json_bytes(h: &SessionHead) -> u64 {
    let names = |v: &[String]| v.iter().map(|n| json_str_bytes(n) + 1).sum::<u64>();
    let graph = h.graph.as_ref().map_or(0, |g| {
        2 * FIELD_JSON_BYTES + json_str_bytes(&g.name) + json_str_bytes(&g.start) + names(&g.script)
    });
    let joints: u64 = h
        .joints
        .0
        .iter()
        .map(|(n, _)| json_str_bytes(n) + 3 * FIELD_JSON_BYTES)
        .sum::<u64>();
    let layers: u64 = h
        .layers
        .iter()
        .map(|l| {
            let mask = match &l.mask {
                None => 0,
                Some(crowdmorph_proto::Mask::Names(n)) => names(n),
                Some(crowdmorph_proto::Mask::Weights(w)) => {
                    w.iter().map(|(n, _)| json_str_bytes(n) + 17).sum::<u64>()
                }
                Some(crowdmorph_proto::Mask::Named(n)) => json_str_bytes(n),
            };
            3 * FIELD_JSON_BYTES
                + json_str_bytes(&l.clip)
                + mask
                + l.joint_mask.as_deref().map_or(0, names)
        })
        .sum();
    // `"layers":[],"clamp":null` and a clamp's two numbers when it has one.
    let clamp = 32 + h.clamp.map_or(0, |_| 32);
    // `"live":null`, or its three durations, its filter's three numbers and its mapping.
    let live = 16
        + h.live.as_ref().map_or(0, |l| {
            8 * FIELD_JSON_BYTES + l.mapping.as_deref().map_or(0, json_str_bytes)
        });
    graph + joints + layers + clamp + live + alive_json_bytes(h.alive.as_ref())
}

/// Most bytes an `alive` field takes in JSON: `"alive":null`, or its name, four flags, a
/// point and a `u64` seed at their widest.
pub(crate) fn alive_json_bytes(alive: Option<&crowdmorph_proto::Alive>) -> u64 {
    16 + alive.map_or(0, |_| 200)
}

impl Session {
    /// When the session ends for want of viewers, if it has none now.
    pub(crate) fn idle_deadline(&self) -> Option<Instant> {
        let since = self.inner.lock().ok().and_then(|i| i.idle_since)?;
        Some(since + Duration::from_secs(u64::from(self.idle_timeout_s)))
    }
}
