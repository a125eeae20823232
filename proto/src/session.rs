//! Crowd sessions: one simulated crowd on a fixed tick, streamed to many viewers over a
//! WebSocket (`GET /v1/sessions/{id}/stream`).
//!
//! The REST side (`/v1/sessions`) creates, inspects, changes and deletes sessions with the
//! messages below, in JSON or bincode like every other message. The stream side is a WebSocket:
//! the viewer's text messages are JSON ([`ViewerHello`] first, then [`ViewerUpdate`]s), and
//! the server's binary messages are bincode [`StreamMessage`]s, one per tick.

use serde::{Deserialize, Serialize};

use crate::{Blob, CameraSpec, Format, FrameBuffer, FrameTimings, HeadBuffer, ImageFormat};
use crate::{ImageOptions, yes};

/// Default ticks per second of a session.
pub const DEFAULT_SESSION_FPS: f32 = 30.0;
/// Default seconds a session lives without viewers before it ends.
pub const DEFAULT_SESSION_IDLE_TIMEOUT_S: u32 = 60;
/// [`HeadBuffer::buffer`] of a head whose job is the same as in the last message this viewer
/// received: keep drawing what it had.
pub const HEAD_UNCHANGED: u32 = u32::MAX;
/// [`HeadBuffer::buffer`] of a head that has nothing to draw this tick: its rig or clip was
/// deleted after the head was added.
pub const HEAD_MISSING: u32 = u32::MAX - 1;

fn default_fps() -> f32 {
    DEFAULT_SESSION_FPS
}

fn default_idle() -> u32 {
    DEFAULT_SESSION_IDLE_TIMEOUT_S
}

fn one() -> f32 {
    1.0
}

/// One head of a session: what it plays and where it stands.
///
/// At tick `t` (from 1) it plays frame `offset + floor((t − 1) × clip_fps / session_fps)` of its clip (wrapped
/// or clamped by the session's `wrap`). Heads that share rig, clip and offset are clones: one
/// blend per tick serves all of them.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SessionHead {
    /// The client's id for this head, unique within the session.
    pub head: u64,
    /// Rig id.
    pub rig: String,
    /// Clip name within the rig (ignored when `graph` is given).
    #[serde(default)]
    pub clip: String,
    /// Frames the head is ahead of the session's clock.
    #[serde(default)]
    pub offset: i64,
    /// Where the rig's origin goes, world units.
    #[serde(default)]
    pub position: [f32; 3],
    /// Turn about +Y, degrees (0: facing +Z).
    #[serde(default)]
    pub yaw: f32,
    /// Uniform scale, > 0.
    #[serde(default = "one")]
    pub scale: f32,
    /// A motion graph to play instead of `clip` (`proto/README.md`, "Motion graphs").
    #[serde(default)]
    pub graph: Option<crate::GraphPlay>,
    /// On a rig with a skeleton: local transforms of named nodes set for this head, over its
    /// clip's or graph's pose (as a crowd frame's `Head::joints`).
    #[serde(default)]
    pub joints: crate::JointOverrides,
    /// Layers over the head's clip or graph pose, as a crowd frame's `Head::layers`; a layer's
    /// `frame` counts from the session clock, as `offset` does (an additive `reference` is a
    /// fixed frame).
    #[serde(default)]
    pub layers: Vec<crate::Layer>,
    /// Every final weight clamped into `[lo, hi]`, as a crowd frame's `Head::clamp`.
    #[serde(default)]
    pub clamp: Option<[f32; 2]>,
    /// Driven by live input (`POST /v1/sessions/{id}/live`) over its clip or graph pose and
    /// its layers (or over the neutral, without a clip): see [`crate::LiveSpec`].
    #[serde(default)]
    pub live: Option<crate::LiveSpec>,
    /// Procedural liveliness for this head (blinks, saccades, look-at, breathing), applied
    /// after its layers; absent, the session's [`SessionRequest::alive`] (if any) applies.
    #[serde(default)]
    pub alive: Option<Alive>,
}

/// Liveliness without authoring (`proto/README.md`, "Liveliness"): procedural layers a
/// session adds over a head's pose, each a pure function of the head's seed and the session
/// clock, so heads with equal seeds (and placements, for `look_at`) stay clones.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Alive {
    /// Blinks: one about every 4 s, each 150-250 ms (`eyeBlinkLeft`/`Right`).
    #[serde(default)]
    pub blink: bool,
    /// Eye saccades: small random gaze offsets held 0.2-2 s (`eyeLook*`, eye joints).
    #[serde(default)]
    pub saccades: bool,
    /// A world point the eyes (and on a skinned rig, partly the head) turn toward.
    #[serde(default)]
    pub look_at: Option<[f32; 3]>,
    /// Slow breathing/idle motion (about 0.25 Hz) on a few targets or a chest joint.
    #[serde(default)]
    pub breathing: bool,
    /// The seed of the head's blinks, saccades and breathing; absent, one derived from the
    /// head id (so a crowd never blinks in unison).
    #[serde(default)]
    pub seed: Option<u64>,
}

/// `POST /v1/sessions` request.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SessionRequest {
    /// Ticks per second, in (0, 120].
    #[serde(default = "default_fps")]
    pub fps: f32,
    /// Clips loop (true) or hold their last frame (false).
    #[serde(default = "yes")]
    pub wrap: bool,
    /// Seconds without viewers after which the session ends (1..=86,400).
    #[serde(default = "default_idle")]
    pub idle_timeout_s: u32,
    /// The crowd.
    pub heads: Vec<SessionHead>,
    /// Liveliness for every head without its own `alive`.
    #[serde(default)]
    pub alive: Option<Alive>,
}

/// Counters of a session since it started.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct SessionStats {
    /// Ticks computed and delivered to the viewers' outboxes (a tick without viewers is not
    /// computed; [`SessionInfo::tick`] counts every tick).
    pub ticks: u64,
    /// Of those, ticks whose blends finished after the next tick was due.
    pub ticks_late: u64,
    /// Ticks never computed, because an earlier one was still running or the server was out
    /// of queue memory (skipped, not queued).
    pub ticks_skipped: u64,
    /// Unique jobs (rig, clip, frame, LOD, format) the computed ticks submitted to the batcher.
    pub jobs: u64,
    /// Messages handed to viewers' sockets.
    pub messages_sent: u64,
    /// Messages replaced in a slow viewer's outbox by a newer tick before it could be sent.
    pub messages_dropped: u64,
    /// Bytes of the messages sent.
    pub bytes_sent: u64,
}

/// `GET /v1/sessions/{id}` response (also the answer to create and change).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SessionInfo {
    /// Session id.
    pub id: String,
    /// Ticks per second.
    pub fps: f32,
    /// Clips loop.
    pub wrap: bool,
    /// Seconds without viewers before the session ends.
    pub idle_timeout_s: u32,
    /// The session's clock: the last tick whose time has come (tick n is due (n − 1)/fps s
    /// after the start), computed or not: ticks without viewers and skipped ticks count here,
    /// not in [`SessionStats::ticks`] (0 before the first).
    pub tick: u64,
    /// The heads, in the order tick messages list them.
    pub heads: Vec<SessionHead>,
    /// Viewers connected now.
    pub viewers: u32,
    /// Counters.
    pub stats: SessionStats,
    /// The session's liveliness for heads without their own (`SessionRequest::alive`, as the
    /// last patch left it).
    pub alive: Option<Alive>,
}

/// `GET /v1/sessions` response.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SessionList {
    /// Sessions, ordered by id.
    pub sessions: Vec<SessionInfo>,
}

/// A change to one head; absent fields stay as they are.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HeadChange {
    /// The head to change.
    pub head: u64,
    /// New clip (of the same rig).
    #[serde(default)]
    pub clip: Option<String>,
    /// New offset.
    #[serde(default)]
    pub offset: Option<i64>,
    /// New position.
    #[serde(default)]
    pub position: Option<[f32; 3]>,
    /// New yaw, degrees.
    #[serde(default)]
    pub yaw: Option<f32>,
    /// New scale.
    #[serde(default)]
    pub scale: Option<f32>,
    /// For a head playing a graph: the node to go to now. The head fades from the pose it
    /// shows (also in the middle of a transition) into the node's first frame.
    #[serde(default)]
    pub node: Option<String>,
    /// New joint overrides (replacing the head's; an empty object clears them).
    #[serde(default)]
    pub joints: Option<crate::JointOverrides>,
    /// New layers (replacing the head's; an empty array clears them).
    #[serde(default)]
    pub layers: Option<Vec<crate::Layer>>,
    /// New clamp (`[lo, hi]`); absent keeps the head's, and `[-64, 64]` lifts it.
    #[serde(default)]
    pub clamp: Option<[f32; 2]>,
    /// New live settings (the head becomes live, or its settings change; its input so far
    /// is kept).
    #[serde(default)]
    pub live: Option<crate::LiveSpec>,
    /// New liveliness of the head's own (replacing it; one with everything off stops the
    /// session's default for this head).
    #[serde(default)]
    pub alive: Option<Alive>,
}

/// `PATCH /v1/sessions/{id}` request: applied together, at the next tick, in the order
/// remove, change, add.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SessionPatch {
    /// Head ids to remove.
    #[serde(default)]
    pub remove: Vec<u64>,
    /// Changes to existing heads.
    #[serde(default)]
    pub change: Vec<HeadChange>,
    /// Heads to add (ids not in the session).
    #[serde(default)]
    pub add: Vec<SessionHead>,
    /// New session-wide liveliness for heads without their own (replacing it; one with
    /// everything off stops it), e.g. a look-at point moved every tick.
    #[serde(default)]
    pub alive: Option<Alive>,
}

/// What a viewer receives each tick.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ViewerOutput {
    /// Blended vertex buffers ([`TickVertices`]).
    #[default]
    Vertices,
    /// A rendered, encoded image from the viewer's camera ([`TickFrame`]).
    Frames,
    /// Each head's final weights and moved joints, for a viewer that blends itself
    /// ([`crate::TickPoses`], variant 5): no engine work for it.
    Weights,
}

/// Level of detail of a viewer: one level for every head, or a level by distance from the
/// viewer's camera.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum LodChoice {
    /// The same level for every head.
    Fixed(u32),
    /// `[[metres, level], ...]` with ascending metres: a head at distance `d` from the camera
    /// gets the level of the last entry whose metres ≤ `d` (level 0 nearer than the first).
    /// Levels past the rig's last are clamped to it.
    ByDistance {
        /// The table.
        by_distance: Vec<[f32; 2]>,
    },
}

impl Default for LodChoice {
    fn default() -> Self {
        LodChoice::Fixed(0)
    }
}

/// The first message of a viewer on the stream (JSON text).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ViewerHello {
    /// Vertex buffers, images or poses.
    #[serde(default)]
    pub output: ViewerOutput,
    /// Scalar format of vertex buffers.
    #[serde(default)]
    pub format: Format,
    /// Also send normals with vertex buffers.
    #[serde(default)]
    pub normals: bool,
    /// The viewer's camera: needed for images and for LOD by distance.
    #[serde(default)]
    pub camera: Option<CameraSpec>,
    /// Level of detail.
    #[serde(default)]
    pub lod: LodChoice,
    /// Size and encoding of images (output `frames`); absent, 640 × 480 JPEG quality 80.
    #[serde(default)]
    pub image: Option<ImageOptions>,
    /// Send each head's buffer as q16 residuals against the last buffer this viewer received
    /// for that head ([`TickDelta`]); needs format q16 and output vertices.
    #[serde(default)]
    pub temporal: bool,
    /// With `temporal`: every head gets a keyframe (its plain q16 buffer) at least every this
    /// many ticks, 1..=[`MAX_KEYFRAME_EVERY`]; absent, [`DEFAULT_KEYFRAME_EVERY`].
    #[serde(default)]
    pub keyframe_every: Option<u32>,
    /// Compress each binary message ([`PackedMessage`]); absent, messages go as they are.
    #[serde(default)]
    pub compression: Option<MessageEncoding>,
    /// Also send each head's expression-layer inputs ([`TickLayers`], variant 4) when they
    /// change, for a viewer that sums a rig's layers itself (`GET /v1/rigs/{id}/layers`).
    #[serde(default)]
    pub layers: bool,
    /// Near-clones for vertex buffers: a head `d` metres from the camera's eye may be off by
    /// `tolerance × d` times its rig's diagonal (a constant angular error; at most 0.1
    /// diagonals), its weights rounded as a crowd head's `tolerance` rounds them. Finite,
    /// 0 ..= [`MAX_VIEWER_TOLERANCE`] per metre; absent or 0 (or without a camera position):
    /// exact poses.
    #[serde(default)]
    pub tolerance: Option<f32>,
}

/// Largest [`ViewerHello::tolerance`], per metre: at 10 m a tenth of the head.
pub const MAX_VIEWER_TOLERANCE: f32 = 0.01;

/// Default [`ViewerHello::keyframe_every`]: two seconds at the default 30 ticks/s.
pub const DEFAULT_KEYFRAME_EVERY: u32 = 60;
/// Largest [`ViewerHello::keyframe_every`].
pub const MAX_KEYFRAME_EVERY: u32 = 3600;

/// How a viewer's binary messages are compressed.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MessageEncoding {
    /// Zstandard frame (RFC 8878), variant 0.
    Zstd,
    /// zlib stream (RFC 1950, what `DecompressionStream("deflate")` and Python's
    /// `zlib.decompress` read), variant 1.
    Deflate,
}

impl MessageEncoding {
    /// The name used in JSON and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            MessageEncoding::Zstd => "zstd",
            MessageEncoding::Deflate => "deflate",
        }
    }
}

/// A later message of a viewer (JSON text): a new camera or LOD, used from the next tick.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ViewerUpdate {
    /// New camera.
    #[serde(default)]
    pub camera: Option<CameraSpec>,
    /// New level of detail.
    #[serde(default)]
    pub lod: Option<LodChoice>,
}

/// A tick of blended vertex buffers for one viewer.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TickVertices {
    /// Tick number (the session's clock, starting at 1).
    pub tick: u64,
    /// Format of every buffer.
    pub format: Format,
    /// Whether buffers carry normals.
    pub normals: bool,
    /// The session's heads and placements, when they changed since the last message this
    /// viewer received (always present in its first message).
    pub layout: Option<Vec<SessionHead>>,
    /// Buffers of the heads whose job changed for this viewer.
    pub buffers: Vec<FrameBuffer>,
    /// One entry per session head, in layout order: an index into `buffers`,
    /// [`HEAD_UNCHANGED`] or [`HEAD_MISSING`].
    pub heads: Vec<HeadBuffer>,
    /// Where the tick's time went.
    pub timings: FrameTimings,
}

/// A tick of q16 vertex buffers for a viewer that asked for temporal residuals: [`TickVertices`]
/// with one flag per buffer. A buffer whose flag is false is a keyframe, plain q16; one whose
/// flag is true holds, for each head that names it, that head's q16 values as residual planes
/// (the coding of [`crate::Format::Q16R`], [`crate::q16r_encode`]) against the buffer this
/// viewer last received for the same head id. Normals, when sent, are coded the same way.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TickDelta {
    /// Tick number.
    pub tick: u64,
    /// What every buffer decodes to (q16).
    pub format: Format,
    /// Whether buffers carry normals.
    pub normals: bool,
    /// As in [`TickVertices`].
    pub layout: Option<Vec<SessionHead>>,
    /// Per buffer: residuals against each naming head's previous buffer (true) or a keyframe.
    pub residual: Vec<bool>,
    /// Buffers of the heads whose job changed for this viewer.
    pub buffers: Vec<FrameBuffer>,
    /// One entry per session head, in layout order, as in [`TickVertices`].
    pub heads: Vec<HeadBuffer>,
    /// Where the tick's time went.
    pub timings: FrameTimings,
}

/// The expression-layer inputs of the heads whose inputs changed since the viewer last
/// received them, sent before the tick's vertex message (a viewer that asked for `layers`).
/// Only heads whose rig has layers are listed; a tick where none changed sends nothing.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TickLayers {
    /// Tick number (the vertex message that follows has the same).
    pub tick: u64,
    /// The heads whose inputs changed.
    pub heads: Vec<HeadLayers>,
}

/// One head's expression-layer inputs: the entries of its job's layer inputs that some layer
/// of its rig reads, in the order `GET /v1/rigs/{id}/layers` numbers them (its `inputs`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct HeadLayers {
    /// The head's id.
    pub head: u64,
    /// Its inputs: a layer's coefficient is `inputs[input]`, clamped to [0, 1] where the
    /// layer says `clamp`.
    pub inputs: Vec<f32>,
}

/// A compressed stream message: `data` decompresses (by `encoding`) to `length` bytes, the
/// bincode of a [`StreamMessage`] that is not itself packed.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PackedMessage {
    /// The compression.
    pub encoding: MessageEncoding,
    /// Bytes of the message once decompressed.
    pub length: u64,
    /// The compressed bytes.
    pub data: Blob,
}

/// A tick rendered for one viewer.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TickFrame {
    /// Tick number.
    pub tick: u64,
    /// Encoding of `image`.
    pub format: ImageFormat,
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// The encoded image (PNG, JPEG, or raw RGBA8 rows top-down).
    pub image: Blob,
}

/// A binary message of the stream (bincode; variant index first).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum StreamMessage {
    /// Variant 0: vertex buffers.
    Vertices(TickVertices),
    /// Variant 1: an image.
    Frame(TickFrame),
    /// Variant 2: vertex buffers as temporal residuals (a viewer that asked for `temporal`).
    Delta(TickDelta),
    /// Variant 3: a compressed message (a viewer that asked for `compression`).
    Packed(PackedMessage),
    /// Variant 4: expression-layer inputs (a viewer that asked for `layers`).
    Layers(TickLayers),
    /// Variant 5: each changed head's final weights and moved joints (a viewer that asked for
    /// `"output": "weights"`).
    Poses(crate::TickPoses),
}
