//! Wire types of the crowdmorph protocol.
//!
//! This crate is deliberately small and dependency-light so that clients can share it with the
//! server. The byte-level specification lives in `proto/README.md`; the types here are the Rust
//! mirror of that document, and [`wire`] holds the one bincode configuration both sides use.
//!
//! Every message has two encodings, chosen per request by HTTP headers:
//! - JSON (`application/json`), for humans and curl; vertex payloads ([`Blob`]) are base64
//!   strings of their little-endian bytes.
//! - bincode 2 with its standard configuration (`application/x-bincode`): little-endian,
//!   variable-length integers, fields in declaration order. A [`Blob`] is a padding byte string
//!   followed by the payload byte string, so that a server can align payloads for zero-copy
//!   reads (see the README).

#![warn(missing_docs)]

pub mod graph;
pub mod live;
pub mod mapping;
pub mod pose;
pub mod session;
#[cfg(feature = "unpack")]
pub mod skim;
pub mod stream;
pub mod wire;

pub use graph::{BuiltGraph, GraphEdge, GraphInfo, GraphList, GraphNode, GraphPlay, MotionGraph};
pub use live::{LiveAck, LiveInput, LiveSample, LiveSpec, OneEuro};
pub use mapping::{
    MapEntry, MapOverride, MapSource, Mapping, MappingInfo, MappingList, MaskInfo, MaskList,
};
pub use pose::{
    CrowdPoseResponse, HeadPose, MAX_F16_WEIGHT, NodePose, RigChannels, TickPoses, f16_to_f32,
    f32_to_f16, weights_f16_le,
};
pub use session::{
    Alive, DEFAULT_KEYFRAME_EVERY, DEFAULT_SESSION_FPS, DEFAULT_SESSION_IDLE_TIMEOUT_S,
    HEAD_MISSING, HEAD_UNCHANGED, HeadChange, HeadLayers, LodChoice, MAX_KEYFRAME_EVERY,
    MAX_VIEWER_TOLERANCE, MessageEncoding, PackedMessage, SessionHead, SessionInfo, SessionList,
    SessionPatch, SessionRequest, SessionStats, StreamMessage, TickDelta, TickFrame, TickLayers,
    TickVertices, ViewerHello, ViewerOutput, ViewerUpdate,
};
pub use stream::{Applied, Received, StreamError, StreamState};

use serde::de::{self, SeqAccess, Visitor};
use serde::ser::SerializeTuple;
use serde::{Deserialize, Deserializer, Serialize, Serializer};

/// Version of the wire protocol spoken by this crate.
pub const PROTOCOL_VERSION: u32 = 1;

/// Content type of JSON bodies.
pub const CONTENT_TYPE_JSON: &str = "application/json";

/// Content type of bincode 2 bodies.
pub const CONTENT_TYPE_BINCODE: &str = "application/x-bincode";

/// Alignment, in bytes from the start of the body, that the server gives every [`Blob`] payload
/// in bincode responses, so that clients can view it as a typed array without copying.
pub const BLOB_ALIGN: usize = 16;

/// Scalar format of vertex buffers on the wire.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Format {
    /// IEEE binary32, 4 bytes per component (bincode variant index 0).
    #[default]
    F32,
    /// IEEE binary16, 2 bytes per component (variant index 1); relative error ≤ 2^-11.
    F16,
    /// int16 quantized inside the rig's quantization box, 2 bytes per component (variant
    /// index 2); absolute error ≤ half a step per axis, stated in [`Quantization::max_error`].
    Q16,
    /// q16 as residuals against the buffer's reference (variant index 3): each int16 `q`
    /// minus the reference's `r` (the q16 buffer of the same rig, LOD and box with every weight
    /// 0: the neutral), wrapping, zigzag-coded as u16, sent as two byte planes (all low bytes,
    /// then all high bytes). Decodes bit for bit to q16; small, so it compresses well.
    Q16R,
    /// No vertex buffer: per head its final weights (binary16) and moved joints, for a client
    /// that blends itself (variant index 4; a crowd frame answers with a
    /// [`CrowdPoseResponse`]). Crowd frames only: renders, session viewers (who ask with
    /// `"output": "weights"`) and load tests refuse it.
    Weights,
}

impl Format {
    /// Bytes of one scalar component.
    pub fn component_bytes(self) -> usize {
        match self {
            Format::F32 => 4,
            Format::F16 | Format::Q16 | Format::Q16R | Format::Weights => 2,
        }
    }

    /// Whether the format is a vertex buffer's (every format but [`Format::Weights`]).
    pub fn is_vertices(self) -> bool {
        self != Format::Weights
    }

    /// Whether the payload is int16 in the rig's box (q16, or q16 residuals).
    pub fn quantized(self) -> bool {
        matches!(self, Format::Q16 | Format::Q16R)
    }

    /// The lowercase name used in JSON and query strings.
    pub fn name(self) -> &'static str {
        match self {
            Format::F32 => "f32",
            Format::F16 => "f16",
            Format::Q16 => "q16",
            Format::Q16R => "q16r",
            Format::Weights => "weights",
        }
    }
}

impl std::str::FromStr for Format {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s.to_ascii_lowercase().as_str() {
            "f32" => Ok(Format::F32),
            "f16" => Ok(Format::F16),
            "q16" => Ok(Format::Q16),
            "q16r" => Ok(Format::Q16R),
            "weights" => Ok(Format::Weights),
            other => Err(format!(
                "unknown format {other:?} (f32, f16, q16, q16r or weights)"
            )),
        }
    }
}

/// Bytes that travel as one contiguous little-endian array (vertex positions, normals, indices).
///
/// JSON: a base64 string (standard alphabet, padded). bincode: a byte string of zero padding
/// followed by a byte string of payload, each a varint length then the bytes.
#[derive(Clone, Default, PartialEq, Eq)]
pub struct Blob(pub Vec<u8>);

impl std::fmt::Debug for Blob {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Blob({} bytes)", self.0.len())
    }
}

impl Blob {
    /// The payload read as little-endian f32 values (a trailing partial value is ignored).
    pub fn to_f32(&self) -> Vec<f32> {
        self.0
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect()
    }

    /// The payload read as little-endian u16 values (binary16 bit patterns).
    pub fn to_u16(&self) -> Vec<u16> {
        self.0
            .chunks_exact(2)
            .map(|b| u16::from_le_bytes([b[0], b[1]]))
            .collect()
    }

    /// The payload read as little-endian i16 values (q16 components).
    pub fn to_i16(&self) -> Vec<i16> {
        self.0
            .chunks_exact(2)
            .map(|b| i16::from_le_bytes([b[0], b[1]]))
            .collect()
    }

    /// The payload read as little-endian u32 values (indices).
    pub fn to_u32(&self) -> Vec<u32> {
        self.0
            .chunks_exact(4)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect()
    }
}

/// Serializes a byte slice with `serialize_bytes` (a varint length then the bytes in bincode).
struct RawBytes<'a>(&'a [u8]);

impl Serialize for RawBytes<'_> {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_bytes(self.0)
    }
}

/// Deserializes a byte string into a `Vec<u8>`.
struct ByteBuf(Vec<u8>);

impl<'de> Deserialize<'de> for ByteBuf {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl<'de> Visitor<'de> for V {
            type Value = ByteBuf;
            fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str("a byte string")
            }
            fn visit_bytes<E: de::Error>(self, v: &[u8]) -> Result<ByteBuf, E> {
                Ok(ByteBuf(v.to_vec()))
            }
            fn visit_byte_buf<E: de::Error>(self, v: Vec<u8>) -> Result<ByteBuf, E> {
                Ok(ByteBuf(v))
            }
            fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<ByteBuf, A::Error> {
                let mut out = Vec::new();
                while let Some(b) = seq.next_element::<u8>()? {
                    out.push(b);
                }
                Ok(ByteBuf(out))
            }
        }
        d.deserialize_byte_buf(V)
    }
}

impl Serialize for Blob {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        use base64::Engine as _;
        if s.is_human_readable() {
            s.serialize_str(&base64::engine::general_purpose::STANDARD.encode(&self.0))
        } else {
            // No padding when encoded through serde; the server's encoder aligns payloads.
            let mut t = s.serialize_tuple(2)?;
            t.serialize_element(&RawBytes(&[]))?;
            t.serialize_element(&RawBytes(&self.0))?;
            t.end()
        }
    }
}

impl<'de> Deserialize<'de> for Blob {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        use base64::Engine as _;
        if d.is_human_readable() {
            let s = String::deserialize(d)?;
            base64::engine::general_purpose::STANDARD
                .decode(s.as_bytes())
                .map(Blob)
                .map_err(|e| de::Error::custom(format!("invalid base64 payload: {e}")))
        } else {
            struct V;
            impl<'de> Visitor<'de> for V {
                type Value = Blob;
                fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                    f.write_str("padding bytes then payload bytes")
                }
                fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Blob, A::Error> {
                    let _pad: ByteBuf = seq
                        .next_element()?
                        .ok_or_else(|| de::Error::invalid_length(0, &self))?;
                    let data: ByteBuf = seq
                        .next_element()?
                        .ok_or_else(|| de::Error::invalid_length(1, &self))?;
                    Ok(Blob(data.0))
                }
            }
            d.deserialize_tuple(2, V)
        }
    }
}

/// One head of a crowd: which rig plays which clip at which frame and level of detail,
/// optionally blended with other clip frames, or driven by live weights instead of a clip.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Head {
    /// The client's id for this head; echoed in the response, never interpreted.
    pub head: u64,
    /// Rig id (as returned by `POST /v1/rigs`; the embedded rig is `default-head`).
    pub rig: String,
    /// Clip name within the rig (empty, or absent in JSON, when `weights` drive the head).
    #[serde(default)]
    pub clip: String,
    /// Frame number; past the end it wraps when the request's `wrap` is true.
    #[serde(default)]
    pub frame: i64,
    /// Level of detail (0 = all shapes).
    #[serde(default)]
    pub lod: u32,
    /// Up to four layers blended over the clip frame, in weight space:
    /// `w = (1 − Σt)·clip[frame] + Σ tᵢ·clipᵢ[frameᵢ]`, each `t` in [0, 1], `Σt ≤ 1`.
    #[serde(default)]
    pub blend: Vec<BlendLayer>,
    /// Live weights (a face tracker's or an Audio2Face-style service's), instead of a clip:
    /// by name, or one per weight channel in the rig's order.
    /// Boxed: a head without them stays small (the server reserves memory per body byte).
    #[serde(default)]
    pub weights: Option<Box<LiveWeights>>,
    /// On a rig with a skeleton: local transforms of named nodes set for this head, over what
    /// its clip, blend or weights pose (`{"LeftEye": {"rotation": [x, y, z, w]}}`).
    #[serde(default)]
    pub joints: JointOverrides,
    /// Up to [`MAX_HEAD_LAYERS`] layers applied in order over the head's base (its clip frame
    /// with its blend, or its live weights): see [`Layer`].
    #[serde(default)]
    pub layers: Vec<Layer>,
    /// With `weights` and a `clip`: whether the weights replace the targets they name (an
    /// override layer masked to those names, the default) or are added to them. They apply
    /// after the layers: live input is on top.
    #[serde(default)]
    pub weights_mode: LayerMode,
    /// Every final weight clamped into `[lo, hi]`, after layers and weights.
    #[serde(default)]
    pub clamp: Option<[f32; 2]>,
    /// A mapping of the rig (`GET /v1/rigs/{id}/mappings`: `arkit`, `a2f`,
    /// `oculus-visemes`, `vrm` or one of its own) that `weights` by name go through first:
    /// their names are the mapping's sources. Dense weights with a mapping are a 400.
    #[serde(default)]
    pub mapping: Option<String>,
    /// Near-clones: the error this head's vertices may have, in units of the rig's diagonal
    /// (finite, 0 ..= 0.1). Its final weights are rounded to the coarsest step whose worst
    /// case (`step/2 ×` the largest per-vertex sum of delta lengths over its level's targets)
    /// stays within it, so that heads whose poses differ by less are one job. Absent or 0: the
    /// exact pose.
    #[serde(default)]
    pub tolerance: Option<f32>,
}

/// Most layers one head may have.
pub const MAX_HEAD_LAYERS: usize = 8;

/// One layer over a head's base pose: frame `frame` of clip `clip` applied to the targets its
/// `mask` selects (every target without one) by `weight`, by override
/// (`w ← (1 − a)·w + a·layer`, `a = weight × mask`) or by addition
/// (`w ← w + a·(layer − reference)`, the reference frame `reference` of the same clip or, absent,
/// the neutral). On a skinned rig the clip's joints are layered too (rotations by slerp; an
/// additive layer adds its rotation relative to the reference), on the nodes `joint_mask`
/// names (every node the clip animates without one).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Layer {
    /// Clip name within the head's rig.
    pub clip: String,
    /// Frame, wrapped or clamped like the head's own (session heads: frames from the session
    /// clock's frame).
    #[serde(default)]
    pub frame: i64,
    /// Weight in [0, 1] (default 1).
    #[serde(default = "one")]
    pub weight: f32,
    /// Override (default) or additive.
    #[serde(default)]
    pub mode: LayerMode,
    /// Which targets, and how much of each.
    #[serde(default)]
    pub mask: Option<Mask>,
    /// Additive layers: the frame of the layer's clip it is measured from (absent: the
    /// neutral, every weight 0).
    #[serde(default)]
    pub reference: Option<i64>,
    /// Skeleton nodes the layer may move (absent: every node its clip animates).
    #[serde(default)]
    pub joint_mask: Option<Vec<String>>,
}

impl Layer {
    /// A layer of `weight` × frame `frame` of `clip`, override, unmasked.
    pub fn over(clip: &str, frame: i64, weight: f32) -> Layer {
        Layer {
            clip: clip.into(),
            frame,
            weight,
            mode: LayerMode::Override,
            mask: None,
            reference: None,
            joint_mask: None,
        }
    }
}

/// How a layer (or a head's weights over its clip) combines with what is below it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LayerMode {
    /// Replace, by the layer's weight (variant 0).
    #[default]
    Override,
    /// Add the difference from the reference (variant 1).
    Additive,
}

/// A layer's targets. In JSON: an array of target names (each at 1), an object of names to
/// weights in [0, 1], or a string: a built-in mask (`upper_face`, `lower_face`, `eyes`,
/// `brows`, `mouth`, over ARKit's names in any loose spelling). In bincode an enum: variant 0
/// `Names(Vec<String>)`, 1 `Weights(Vec<(String, f32)>)`, 2 `Named(String)`.
#[derive(Clone, Debug, PartialEq)]
pub enum Mask {
    /// These targets, each at 1.
    Names(Vec<String>),
    /// These targets, each at its weight.
    Weights(Vec<(String, f32)>),
    /// A built-in mask by name.
    Named(String),
}

/// [`Mask`] as bincode carries it.
#[derive(Serialize, Deserialize)]
enum MaskWire {
    Names(Vec<String>),
    Weights(Vec<(String, f32)>),
    Named(String),
}

impl Serialize for Mask {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        use serde::ser::SerializeMap;
        if !s.is_human_readable() {
            let wire = match self.clone() {
                Mask::Names(n) => MaskWire::Names(n),
                Mask::Weights(w) => MaskWire::Weights(w),
                Mask::Named(n) => MaskWire::Named(n),
            };
            return wire.serialize(s);
        }
        match self {
            Mask::Names(n) => n.serialize(s),
            Mask::Named(n) => n.serialize(s),
            Mask::Weights(w) => {
                let mut m = s.serialize_map(Some(w.len()))?;
                for (k, v) in w {
                    m.serialize_entry(k, v)?;
                }
                m.end()
            }
        }
    }
}

impl<'de> Deserialize<'de> for Mask {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Mask, D::Error> {
        if !d.is_human_readable() {
            return MaskWire::deserialize(d).map(|w| match w {
                MaskWire::Names(n) => Mask::Names(n),
                MaskWire::Weights(w) => Mask::Weights(w),
                MaskWire::Named(n) => Mask::Named(n),
            });
        }
        struct V;
        impl<'de> Visitor<'de> for V {
            type Value = Mask;
            fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str(
                    "a mask: an array of target names, an object of names to weights, or a \
                     built-in mask's name",
                )
            }
            fn visit_str<E: de::Error>(self, v: &str) -> Result<Mask, E> {
                Ok(Mask::Named(v.to_string()))
            }
            fn visit_seq<A: SeqAccess<'de>>(self, mut a: A) -> Result<Mask, A::Error> {
                // Capped while decoding: the server charges the body before it decodes it.
                let mut v = Vec::with_capacity(a.size_hint().unwrap_or(0).min(256));
                while let Some(n) = a.next_element::<String>()? {
                    v.push(n);
                }
                Ok(Mask::Names(v))
            }
            fn visit_map<A: de::MapAccess<'de>>(self, mut m: A) -> Result<Mask, A::Error> {
                let mut v = Vec::with_capacity(m.size_hint().unwrap_or(0).min(256));
                while let Some((k, w)) = m.next_entry::<String, f32>()? {
                    v.push((k, w));
                }
                Ok(Mask::Weights(v))
            }
        }
        d.deserialize_any(V)
    }
}

impl Head {
    /// A head playing `frame` of `clip` at LOD 0, with no blend.
    pub fn playing(head: u64, rig: &str, clip: &str, frame: i64) -> Head {
        Head {
            head,
            rig: rig.into(),
            clip: clip.into(),
            frame,
            ..Head::default()
        }
    }

    /// A head driven by live weights.
    pub fn live(head: u64, rig: &str, weights: LiveWeights) -> Head {
        Head {
            head,
            rig: rig.into(),
            weights: Some(Box::new(weights)),
            ..Head::default()
        }
    }
}

/// Local transforms of named skeleton nodes that a request sets for one head, replacing what
/// its clip (or blend, or rest pose) gives those nodes; components left out keep it. In JSON an
/// object by node name (`{"LeftEye": {"rotation": [0, 0.17, 0, 0.985]}}`); in bincode a
/// `Vec<(String, JointTransform)>`.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct JointOverrides(pub Vec<(String, JointTransform)>);

impl JointOverrides {
    /// How many nodes it sets.
    pub fn len(&self) -> usize {
        self.0.len()
    }

    /// True when it sets none.
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }

    /// One node's rotation (x, y, z, w).
    pub fn rotation(node: &str, rotation: [f32; 4]) -> JointOverrides {
        JointOverrides(vec![(
            node.into(),
            JointTransform {
                rotation: Some(rotation),
                ..JointTransform::default()
            },
        )])
    }
}

/// A node's local transform, or part of it: what glTF's animation channels set.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JointTransform {
    /// Translation, rig units.
    #[serde(default)]
    pub translation: Option<[f32; 3]>,
    /// Rotation quaternion x, y, z, w (normalized by the server; not zero).
    #[serde(default)]
    pub rotation: Option<[f32; 4]>,
    /// Scale per axis.
    #[serde(default)]
    pub scale: Option<[f32; 3]>,
}

impl Serialize for JointOverrides {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        use serde::ser::SerializeMap;
        if s.is_human_readable() {
            let mut m = s.serialize_map(Some(self.0.len()))?;
            for (k, t) in &self.0 {
                m.serialize_entry(k, t)?;
            }
            m.end()
        } else {
            self.0.serialize(s)
        }
    }
}

impl<'de> Deserialize<'de> for JointOverrides {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<JointOverrides, D::Error> {
        if !d.is_human_readable() {
            return Vec::<(String, JointTransform)>::deserialize(d).map(JointOverrides);
        }
        struct V;
        impl<'de> Visitor<'de> for V {
            type Value = JointOverrides;
            fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str("an object of joint transforms by node name")
            }
            fn visit_map<A: de::MapAccess<'de>>(
                self,
                mut m: A,
            ) -> Result<JointOverrides, A::Error> {
                // Capped while decoding: the server charges the body before it decodes it.
                let mut v = Vec::with_capacity(m.size_hint().unwrap_or(0).min(256));
                while let Some((k, t)) = m.next_entry::<String, JointTransform>()? {
                    v.push((k, t));
                }
                Ok(JointOverrides(v))
            }
        }
        d.deserialize_map(V)
    }
}

/// `PUT /v1/rigs/{id}/joint-map` request, and what `GET` answers (in [`JointMapInfo`]): the
/// clip columns that turn a skinned rig's joints — Live Link Face's `HeadYaw`, ...,
/// `RightEyeRoll` by default (`proto/README.md`, "Joint channels in clips").
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JointMapSpec {
    /// The channels, in the order their rotations compose per node.
    pub channels: Vec<JointChannelSpec>,
}

fn y_axis() -> [f32; 3] {
    [0.0, 1.0, 0.0]
}

fn one_radian() -> f32 {
    1.0
}

/// One column that turns a node: by `value × scale` radians about `axis` (rig space: +Y up,
/// +Z out of the face, +X to the character's left), about the node's origin.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JointChannelSpec {
    /// Clip column (matched in any loose spelling, as target names are).
    pub column: String,
    /// Skeleton node name.
    pub node: String,
    /// Unit axis in rig space (default +Y).
    #[serde(default = "y_axis")]
    pub axis: [f32; 3],
    /// Radians per unit (default 1).
    #[serde(default = "one_radian")]
    pub scale: f32,
}

/// `GET /v1/rigs/{id}/joint-map` response (also the answer to `PUT` and `DELETE`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JointMapInfo {
    /// Rig id.
    pub rig: String,
    /// True when the rig has no map of its own and these are the defaults (Ready Player Me
    /// and VRM humanoid names).
    pub default: bool,
    /// The channels in force.
    pub channels: Vec<JointChannelSpec>,
}

/// One blend layer of a head: fraction `t` of frame `frame` of clip `clip` (same rig).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BlendLayer {
    /// Clip name within the head's rig.
    pub clip: String,
    /// Frame, wrapped or clamped like the head's own.
    #[serde(default)]
    pub frame: i64,
    /// Fraction in [0, 1].
    pub t: f32,
}

/// Live weights of a head. In JSON an object (`{"jawOpen": 0.6}`: names matched as a CSV
/// clip's columns are, ARKit's 52 names included, each driving every channel of its name;
/// names not given are 0) or an array (one weight per name of [`RigInfo::targets`], in that
/// order). In bincode an enum: variant 0 `Named(Vec<(String, f32)>)`, variant 1
/// `Dense(Vec<f32>)`.
#[derive(Clone, Debug, PartialEq)]
pub enum LiveWeights {
    /// Weights by target name, in the order given.
    Named(Vec<(String, f32)>),
    /// One weight per target name, in the order of [`RigInfo::targets`].
    Dense(Vec<f32>),
}

impl LiveWeights {
    /// How many weights it carries.
    pub fn len(&self) -> usize {
        match self {
            LiveWeights::Named(v) => v.len(),
            LiveWeights::Dense(v) => v.len(),
        }
    }

    /// True when it carries none.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// The tagged form bincode uses (JSON uses an object or an array instead).
#[derive(Serialize, Deserialize)]
enum LiveWeightsTagged {
    Named(Vec<(String, f32)>),
    Dense(Vec<f32>),
}

impl Serialize for LiveWeights {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        use serde::ser::SerializeMap;
        match (self, s.is_human_readable()) {
            (LiveWeights::Named(v), true) => {
                let mut m = s.serialize_map(Some(v.len()))?;
                for (k, w) in v {
                    m.serialize_entry(k, w)?;
                }
                m.end()
            }
            (LiveWeights::Dense(v), true) => v.serialize(s),
            (LiveWeights::Named(v), false) => {
                s.serialize_newtype_variant("LiveWeights", 0, "Named", v)
            }
            (LiveWeights::Dense(v), false) => {
                s.serialize_newtype_variant("LiveWeights", 1, "Dense", v)
            }
        }
    }
}

impl<'de> Deserialize<'de> for LiveWeights {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<LiveWeights, D::Error> {
        if !d.is_human_readable() {
            return Ok(match LiveWeightsTagged::deserialize(d)? {
                LiveWeightsTagged::Named(v) => LiveWeights::Named(v),
                LiveWeightsTagged::Dense(v) => LiveWeights::Dense(v),
            });
        }
        struct V;
        impl<'de> Visitor<'de> for V {
            type Value = LiveWeights;
            fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str("an object of weights by name, or an array of weights")
            }
            fn visit_map<A: de::MapAccess<'de>>(self, mut m: A) -> Result<LiveWeights, A::Error> {
                // Capped while decoding too: the server charges the body before it decodes,
                // and a weight is never larger in memory than three times its text.
                let mut v = Vec::with_capacity(m.size_hint().unwrap_or(0).min(1024));
                while let Some((k, w)) = m.next_entry::<String, f32>()? {
                    v.push((k, w));
                }
                Ok(LiveWeights::Named(v))
            }
            fn visit_seq<A: SeqAccess<'de>>(self, mut q: A) -> Result<LiveWeights, A::Error> {
                let mut v = Vec::with_capacity(q.size_hint().unwrap_or(0).min(1024));
                while let Some(w) = q.next_element::<f32>()? {
                    v.push(w);
                }
                Ok(LiveWeights::Dense(v))
            }
        }
        d.deserialize_any(V)
    }
}

/// What the buffers of a crowd frame contain.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OutputOptions {
    /// Also send unit normals.
    #[serde(default)]
    pub normals: bool,
    /// Scalar format of the buffers.
    #[serde(default)]
    pub format: Format,
}

fn yes() -> bool {
    true
}

/// `POST /v1/crowd/frame` request.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CrowdFrameRequest {
    /// The heads, in the order the response lists them.
    pub heads: Vec<Head>,
    /// Output format and contents.
    #[serde(default)]
    pub output: OutputOptions,
    /// Frames past the end of a clip loop (true, the default) or are an error (false).
    #[serde(default = "yes")]
    pub wrap: bool,
}

/// How to turn q16 components back into rig-space coordinates:
/// `x = min[a] + (q + 32768) × step[a]` for axis `a` (0 = x, 1 = y, 2 = z).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Quantization {
    /// Lower corner of the quantization box.
    pub min: [f32; 3],
    /// Size of one quantization step per axis: `(max - min) / 65535`.
    pub step: [f32; 3],
    /// Largest absolute error of a dequantized position per axis: half a step, plus a few
    /// units in the last place of the largest coordinate for rounding to f32.
    pub max_error: [f32; 3],
}

impl Quantization {
    /// Dequantizes interleaved x, y, z components.
    pub fn dequantize(&self, q: &[i16]) -> Vec<f32> {
        q.iter()
            .enumerate()
            .map(|(i, &c)| {
                let a = i % 3;
                self.min[a] + (f32::from(c) + 32768.0) * self.step[a]
            })
            .collect()
    }
}

/// Largest absolute error of a q16 normal component: normals are `q / 32767`.
pub const Q16_NORMAL_MAX_ERROR: f32 = 0.5 / 32767.0;

/// One unique blended buffer of a crowd frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FrameBuffer {
    /// Rig id.
    pub rig: String,
    /// Clip name.
    pub clip: String,
    /// Frame of the clip's table actually played (after wrapping).
    pub frame: u32,
    /// Level of detail.
    pub lod: u32,
    /// Vertices in the buffer (all primitives of the rig concatenated in file order).
    pub vertices: u32,
    /// How to dequantize positions; present exactly when the format is q16.
    pub quantization: Option<Quantization>,
    /// x, y, z per vertex in the response's format: `vertices × 3 × component bytes`.
    pub positions: Blob,
    /// Unit normals, when asked for, in the same format (q16: `q / 32767`).
    pub normals: Option<Blob>,
}

/// Which buffer a head uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct HeadBuffer {
    /// The head id from the request.
    pub head: u64,
    /// Index into [`CrowdFrameResponse::buffers`].
    pub buffer: u32,
}

/// Where the time of a crowd frame went, in microseconds.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct FrameTimings {
    /// From admission to the start of the last engine batch that computed one of its buffers
    /// (0 when every buffer joined a batch already running).
    pub queue_us: u64,
    /// Engine wall time of the batches that computed its buffers.
    pub compute_us: u64,
    /// From the request's arrival to its response being ready to send.
    pub total_us: u64,
    /// GPU time of those batches, when the GPU engine computed them.
    pub gpu_us: Option<u64>,
}

/// `POST /v1/crowd/frame` response.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CrowdFrameResponse {
    /// Format of every buffer.
    pub format: Format,
    /// Whether buffers carry normals.
    pub normals: bool,
    /// Unique buffers, in order of first appearance among the heads; clones share one.
    pub buffers: Vec<FrameBuffer>,
    /// One entry per request head, in request order.
    pub heads: Vec<HeadBuffer>,
    /// Timings.
    pub timings: FrameTimings,
}

/// Memory a rig occupies on the server.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Memory {
    /// Host bytes (rig arrays plus the CPU engine's layout).
    pub host_bytes: u64,
    /// Device bytes (0 without a GPU).
    pub device_bytes: u64,
}

/// Axis-aligned box.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Aabb {
    /// Lower corner.
    pub min: [f32; 3],
    /// Upper corner.
    pub max: [f32; 3],
}

/// A clip of a rig.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ClipInfo {
    /// Name (unique within the rig).
    pub name: String,
    /// Frames in the table.
    pub frames: u32,
    /// Sampling rate.
    pub fps: f32,
}

/// A primitive of a rig.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct PrimitiveInfo {
    /// `mesh/index` as found in the file.
    pub name: String,
    /// Vertices.
    pub vertices: u32,
    /// Triangles.
    pub triangles: u32,
}

/// A registered rig, as `POST /v1/rigs` and `GET /v1/rigs[/{id}]` describe it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RigInfo {
    /// Id used in URLs and crowd requests.
    pub id: String,
    /// Name from the file or the upload.
    pub name: String,
    /// Whether this is the embedded rig (always present, never deletable).
    pub builtin: bool,
    /// Vertices over all primitives.
    pub vertices: u32,
    /// Triangles over all primitives.
    pub triangles: u32,
    /// Primitives in evaluation order.
    pub primitives: Vec<PrimitiveInfo>,
    /// Target names, each once, in the order of their first weight channel.
    pub targets: Vec<String>,
    /// Clips.
    pub clips: Vec<ClipInfo>,
    /// Level of detail: importance order, table and status.
    pub lod: LodInfo,
    /// Bounding box of the neutral mesh.
    pub bbox: Aabb,
    /// Memory resident for the rig.
    pub memory: Memory,
    /// Target names that have more than one weight channel (empty for most rigs): a glTF file
    /// whose animations or default weights treat nodes that share a target name differently
    /// (a head animated while its teeth are not) gets one channel per behaviour, so each node
    /// plays its own curve. Clips by name write every channel of a name; LOD orders list the
    /// channels of such a name as `name#1`, `name#2`, ...
    #[serde(default)]
    pub split_targets: Vec<SplitTarget>,
    /// Names of the rig's motion graphs (`GET /v1/rigs/{id}/graphs`); JSON readers should treat
    /// a missing field as empty.
    #[serde(default)]
    pub graphs: Vec<String>,
    /// The skeleton its vertices follow after the morph targets, for a skinned rig (null
    /// otherwise). Added after `graphs`; JSON readers should treat a missing field as null.
    #[serde(default)]
    pub skeleton: Option<SkeletonInfo>,
    /// What the import approximated or left out of the file, a sentence each (empty when
    /// nothing was). JSON readers should treat a missing field as empty.
    #[serde(default)]
    pub import_notes: Vec<String>,
}

/// A skinned rig's skeleton (see [`RigInfo::skeleton`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SkeletonInfo {
    /// Nodes of the hierarchy its bones hang from.
    pub nodes: u32,
    /// Distinct nodes vertices follow: the joints of its skins (a node several skins list
    /// counts once), and each node a rigid mesh hangs from.
    pub bones: u32,
    /// Vertices moved by a skin's joints.
    pub skinned_vertices: u32,
    /// Vertices of meshes that hang rigidly from an animated node.
    pub rigid_vertices: u32,
    /// Names of the nodes some clip animates.
    pub animated_nodes: Vec<String>,
    /// Clips that animate nodes (the others leave the skeleton at rest).
    pub clips_with_joints: Vec<String>,
    /// Every node's name, parents before children: the names joint overrides and joint maps
    /// may use. In JSON only (absent when empty): the bincode layout of `RigInfo` is pinned,
    /// so in bincode this field takes no bytes and reads as empty ([`json_only`]).
    #[serde(default, skip_serializing_if = "Vec::is_empty", with = "json_only")]
    pub node_names: Vec<String>,
}

/// A field that only human-readable encodings (JSON) carry: bincode writes it as `()`, which is
/// no bytes, and reads it back as the type's default. For fields added to a message whose
/// bincode layout is pinned by golden files.
mod json_only {
    use serde::{Deserialize, Deserializer, Serialize, Serializer};

    pub fn serialize<T: Serialize, S: Serializer>(value: &T, s: S) -> Result<S::Ok, S::Error> {
        if s.is_human_readable() {
            value.serialize(s)
        } else {
            s.serialize_unit()
        }
    }

    pub fn deserialize<'de, T, D>(d: D) -> Result<T, D::Error>
    where
        T: Deserialize<'de> + Default,
        D: Deserializer<'de>,
    {
        if d.is_human_readable() {
            T::deserialize(d)
        } else {
            <()>::deserialize(d).map(|()| T::default())
        }
    }
}

/// A target name with several weight channels (see [`RigInfo::split_targets`]).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct SplitTarget {
    /// Target name.
    pub name: String,
    /// Weight channels it has (at least 2).
    pub channels: u32,
}

/// A rig's level of detail (`GET /v1/rigs/{id}/lod`, and inside [`RigInfo`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LodInfo {
    /// How the order was made: `delta-energy` (the import's quick order), `combined`,
    /// `file-order`, a metric name, or `explicit`.
    pub method: String,
    /// `imported` (quick order, no metric scoring yet), `computing`, `ready` or `failed`.
    pub status: String,
    /// Fraction done while `computing` (0–1).
    pub progress: f32,
    /// Why the last computation failed, when it did.
    pub error: Option<String>,
    /// Target names, most important first.
    pub order: Vec<String>,
    /// Targets pinned to the front of the order.
    pub pinned: Vec<String>,
    /// The table, level 0 first.
    pub levels: Vec<LodLevelInfo>,
}

/// One LOD level.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct LodLevelInfo {
    /// Shapes evaluated (the first `shapes` of the order).
    pub shapes: u32,
    /// Simplified mesh used (index into the rig's mesh levels), `None` for the full mesh.
    pub mesh: Option<u32>,
    /// Vertices of a buffer at this level.
    pub vertices: u32,
    /// Triangles of the mesh at this level (`GET /v1/rigs/{id}/mesh?lod=L` has them).
    pub triangles: u32,
}

/// `PUT /v1/rigs/{id}/lod` request: how to (re)build the rig's level of detail. Every field is
/// optional; `{}` means the combined metric order and the default table.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LodRequest {
    /// `combined` (default), `file-order`, `geometric-mse`, `hausdorff`, `image-mse`, `ssim`
    /// or `yee`.
    #[serde(default)]
    pub method: Option<String>,
    /// An explicit full order by target name (overrides `method`).
    #[serde(default)]
    pub order: Option<Vec<String>>,
    /// Targets moved to the front, in this order (the paper: metrics undervalue blinks).
    #[serde(default)]
    pub pinned: Vec<String>,
    /// The table; default 100/50/25/10/0 % of the targets.
    #[serde(default)]
    pub levels: Option<Vec<LodLevelRequest>>,
    /// Simplified meshes to build, as fractions of the triangles (e.g. `[0.5, 0.25, 0.1]`).
    #[serde(default)]
    pub mesh_fractions: Vec<f32>,
}

/// One level of a [`LodRequest`] table.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LodLevelRequest {
    /// Shapes evaluated.
    pub shapes: u32,
    /// Index into `mesh_fractions` of the simplified mesh this level uses.
    #[serde(default)]
    pub mesh: Option<u32>,
}

/// `GET /v1/rigs` response.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RigList {
    /// Every registered rig, ordered by id.
    pub rigs: Vec<RigInfo>,
}

/// A primitive's ranges in a [`MeshResponse`].
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct MeshPrimitive {
    /// `mesh/index`.
    pub name: String,
    /// First vertex of the primitive in the concatenated vertex space.
    pub first_vertex: u32,
    /// Vertices of the primitive.
    pub vertices: u32,
    /// First index of the primitive in [`MeshResponse::indices`].
    pub first_index: u32,
    /// Indices of the primitive (3 per triangle).
    pub indices: u32,
    /// Index of its material in `GET /v1/rigs/{id}/materials`; `None`: the rig has no
    /// materials, or the file gave this primitive none.
    pub material: Option<u32>,
}

/// `GET /v1/rigs/{id}/mesh` response: what a client fetches once to draw a rig's heads.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MeshResponse {
    /// Rig id.
    pub rig: String,
    /// The LOD level whose mesh this is (`?lod=L`; 0 = the full mesh).
    pub lod: u32,
    /// Vertices over all primitives.
    pub vertices: u32,
    /// Primitives in evaluation order.
    pub primitives: Vec<MeshPrimitive>,
    /// Bounding box of the neutral mesh.
    pub bbox: Aabb,
    /// The box q16 positions of this rig are quantized in (covers every clip's motion).
    pub quantization: Quantization,
    /// Triangle list, u32 little-endian, indexing the concatenated vertex space.
    pub indices: Blob,
    /// Neutral positions, f32 little-endian x, y, z per vertex.
    pub positions: Blob,
    /// Neutral unit normals, f32 little-endian x, y, z per vertex.
    pub normals: Blob,
    /// Texture coordinates of set 0, f32 little-endian u, v per vertex in the positions'
    /// order (zeros for a primitive without); empty when no primitive has any.
    pub uvs: Blob,
    /// Texture coordinates of set 1 (what a material's `texCoord: 1` reads, often an
    /// occlusion map), as [`MeshResponse::uvs`]; empty when no primitive has any.
    pub uvs1: Blob,
    /// Vertex colours (glTF `COLOR_0`, which multiplies the base colour), f32 little-endian
    /// linear r, g, b, a per vertex (1, 1, 1, 1 for a primitive without); empty when no
    /// primitive has any.
    pub colors: Blob,
}

/// `POST /v1/rigs/{id}/clips` response.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ClipUpload {
    /// Rig id.
    pub rig: String,
    /// The clips added.
    pub added: Vec<ClipInfo>,
    /// Source target names that match no rig target and were ignored (only with
    /// `ignore_unknown=true`; otherwise they are an error).
    pub ignored: Vec<String>,
}

/// `GET /v1/rigs/{id}/clips` response.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ClipList {
    /// Rig id.
    pub rig: String,
    /// Its clips.
    pub clips: Vec<ClipInfo>,
}

/// The body of every 4xx and 5xx response (always JSON).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ErrorBody {
    /// What went wrong.
    pub error: ErrorDetail,
}

/// Machine-readable code and human-readable message of an error.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ErrorDetail {
    /// Stable snake_case code, e.g. `unknown_rig`, `queue_full`.
    pub code: String,
    /// What is wrong, naming the offending value.
    pub message: String,
}

/// `GET /readyz` body.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Readiness {
    /// `ready`, `loading` or `degraded`.
    pub status: String,
    /// Engine kind (`cpu` or `gpu`).
    pub backend: String,
    /// CPU kernel family.
    pub cpu_isa: String,
    /// Why the engine is degraded, when it is.
    pub degraded_reason: Option<String>,
    /// Rigs registered.
    pub rigs: u32,
    /// Stored files that could not be loaded at start, with the reason.
    pub skipped_files: Vec<String>,
    /// The adapter that draws `POST /v1/crowd/render` images (e.g. `llvmpipe (LLVM 15.0.6,
    /// 256 bits) (Vulkan)`), or `None` when rendering is unavailable.
    #[serde(default)]
    pub renderer: Option<String>,
}

/// Where one head of a rendered crowd stands, in world units (`POST /v1/crowd/render`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Placement {
    /// The [`Head::head`] id this placement applies to (every head with that id).
    pub head: u64,
    /// Where the rig's origin goes.
    pub position: [f32; 3],
    /// Turn about +Y, in degrees (0: the head faces +Z, toward the default camera).
    #[serde(default)]
    pub yaw: f32,
    /// Uniform scale, > 0.
    #[serde(default = "one")]
    pub scale: f32,
}

pub(crate) fn one() -> f32 {
    1.0
}

/// A perspective camera of a rendered crowd, in world units: where it stands and what it looks
/// at, or a framing preset ([`CameraSpec::frame`]) that places it in front of the crowd.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraSpec {
    /// Where the eye is: required without [`CameraSpec::frame`], absent (or `null`) with one.
    /// Bincode carries it bare, as it always has, so a camera without it has no bincode form
    /// ([`bincode_required`]).
    #[serde(default, with = "bincode_required")]
    pub position: Option<[f32; 3]>,
    /// The point at the centre of the image (not equal to `position`); required and absent as
    /// `position` is.
    #[serde(default, with = "bincode_required")]
    pub target: Option<[f32; 3]>,
    /// Vertical field of view in degrees, in (0, 180).
    #[serde(default = "default_fov")]
    pub fov_y: f32,
    /// Near clip distance (> 0); derived from the scene's bounds when absent.
    #[serde(default)]
    pub near: Option<f32>,
    /// Far clip distance (> near); derived from the scene's bounds when absent.
    #[serde(default)]
    pub far: Option<f32>,
    /// A framing preset instead of a position and target: the front view that fits the heads'
    /// faces or their whole figures (see [`CameraFrame`]); `fov_y`, `near` and `far` still
    /// apply. In JSON only (absent when `None`): the bincode layout of `CameraSpec` is pinned,
    /// so in bincode this field takes no bytes and reads as `None` ([`json_only`]).
    #[serde(default, skip_serializing_if = "Option::is_none", with = "json_only")]
    pub frame: Option<CameraFrame>,
}

impl CameraSpec {
    /// A camera at `position` looking at `target`, with the default field of view and clip
    /// planes derived from the scene.
    pub fn looking(position: [f32; 3], target: [f32; 3]) -> CameraSpec {
        CameraSpec {
            position: Some(position),
            target: Some(target),
            fov_y: DEFAULT_FOV_Y,
            near: None,
            far: None,
            frame: None,
        }
    }

    /// The framing preset `frame`, with the default field of view and derived clip planes (a
    /// JSON-only camera: see [`CameraSpec::frame`]).
    pub fn framing(frame: CameraFrame) -> CameraSpec {
        CameraSpec {
            position: None,
            target: None,
            frame: Some(frame),
            ..CameraSpec::looking([0.0; 3], [0.0; 3])
        }
    }
}

/// What a framing camera ([`CameraSpec::frame`]) fits in the image: a front view (looking down
/// −Z, as the default camera) at the distance where the box of what it frames fills the image
/// but for a margin.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum CameraFrame {
    /// Every head's face region: the vertices its head joint carries, else those its morph
    /// targets move, else the whole rig.
    Faces,
    /// Every head's whole figure: the view a request without a camera gets.
    Bodies,
}

impl CameraFrame {
    /// The lowercase name used in JSON.
    pub fn name(self) -> &'static str {
        match self {
            CameraFrame::Faces => "faces",
            CameraFrame::Bodies => "bodies",
        }
    }
}

/// A camera point that bincode carries bare (`[f32; 3]`, as before framing cameras existed)
/// and JSON as an optional array: JSON reads an absent or `null` point as `None`; bincode
/// reads one always, and cannot write `None` (a framing camera is JSON-only).
mod bincode_required {
    use serde::{Deserialize, Deserializer, Serialize, Serializer, ser::Error};

    pub fn serialize<S: Serializer>(value: &Option<[f32; 3]>, s: S) -> Result<S::Ok, S::Error> {
        if s.is_human_readable() {
            return value.serialize(s);
        }
        match value {
            Some(p) => p.serialize(s),
            None => Err(S::Error::custom(
                "a camera without a position or target (a framing camera) has no bincode \
                 form: send the request as JSON",
            )),
        }
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Option<[f32; 3]>, D::Error> {
        if d.is_human_readable() {
            Option::<[f32; 3]>::deserialize(d)
        } else {
            <[f32; 3]>::deserialize(d).map(Some)
        }
    }
}

/// Default vertical field of view of a rendered crowd, degrees.
pub const DEFAULT_FOV_Y: f32 = 30.0;

fn default_fov() -> f32 {
    DEFAULT_FOV_Y
}

/// Encoding of a rendered image.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ImageFormat {
    /// PNG, 8-bit RGBA (`image/png`; bincode variant index 0).
    #[default]
    Png,
    /// Baseline JPEG, 8-bit RGB (`image/jpeg`; variant index 1).
    Jpeg,
    /// Raw RGBA8, rows top-down, no header (`application/octet-stream`; variant index 2).
    Rgba,
}

impl ImageFormat {
    /// The lowercase name used in JSON and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            ImageFormat::Png => "png",
            ImageFormat::Jpeg => "jpeg",
            ImageFormat::Rgba => "rgba",
        }
    }

    /// The response's Content-Type.
    pub fn content_type(self) -> &'static str {
        match self {
            ImageFormat::Png => "image/png",
            ImageFormat::Jpeg => "image/jpeg",
            ImageFormat::Rgba => "application/octet-stream",
        }
    }
}

impl std::str::FromStr for ImageFormat {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s.to_ascii_lowercase().as_str() {
            "png" => Ok(ImageFormat::Png),
            "jpeg" | "jpg" => Ok(ImageFormat::Jpeg),
            "rgba" => Ok(ImageFormat::Rgba),
            other => Err(format!(
                "unknown image format {other:?} (png, jpeg or rgba)"
            )),
        }
    }
}

/// Default image width of a rendered crowd, pixels.
pub const DEFAULT_IMAGE_WIDTH: u32 = 640;
/// Default image height of a rendered crowd, pixels.
pub const DEFAULT_IMAGE_HEIGHT: u32 = 480;
/// Largest image side a server renders, pixels.
pub const MAX_IMAGE_SIDE: u32 = 4096;
/// Default JPEG quality.
pub const DEFAULT_JPEG_QUALITY: u8 = 90;
/// Default background colour (sRGB, 0–255).
pub const DEFAULT_BACKGROUND: [u8; 3] = [46, 50, 56];

fn default_width() -> u32 {
    DEFAULT_IMAGE_WIDTH
}

fn default_height() -> u32 {
    DEFAULT_IMAGE_HEIGHT
}

fn default_quality() -> u8 {
    DEFAULT_JPEG_QUALITY
}

fn default_background() -> [u8; 3] {
    DEFAULT_BACKGROUND
}

/// Size, encoding and background of a rendered image.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImageOptions {
    /// Width in pixels, 1..=4096.
    #[serde(default = "default_width")]
    pub width: u32,
    /// Height in pixels, 1..=4096.
    #[serde(default = "default_height")]
    pub height: u32,
    /// Encoding.
    #[serde(default)]
    pub format: ImageFormat,
    /// JPEG quality, 1..=100 (ignored by the other formats).
    #[serde(default = "default_quality")]
    pub quality: u8,
    /// Background colour, sRGB 0–255.
    #[serde(default = "default_background")]
    pub background: [u8; 3],
}

impl Default for ImageOptions {
    fn default() -> Self {
        ImageOptions {
            width: DEFAULT_IMAGE_WIDTH,
            height: DEFAULT_IMAGE_HEIGHT,
            format: ImageFormat::Png,
            quality: DEFAULT_JPEG_QUALITY,
            background: DEFAULT_BACKGROUND,
        }
    }
}

/// `POST /v1/crowd/render` request: a crowd (as in [`CrowdFrameRequest`]) and how to draw it.
/// The response is the image itself, not a message (see `proto/README.md`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RenderRequest {
    /// The heads; clones (same rig, clip, frame and LOD) are blended once and drawn as
    /// instances.
    pub heads: Vec<Head>,
    /// Frames past the end of a clip loop (true, the default) or are an error (false).
    #[serde(default = "yes")]
    pub wrap: bool,
    /// Where heads stand; heads without one are laid out on a grid, in request order.
    #[serde(default)]
    pub placements: Option<Vec<Placement>>,
    /// The camera; absent, a front view framing every head.
    #[serde(default)]
    pub camera: Option<CameraSpec>,
    /// Size and encoding; absent, 640 × 480 PNG.
    #[serde(default)]
    pub image: Option<ImageOptions>,
}

/// Residual planes of `q` (q16 components) against `reference` ([`Format::Q16R`]): `out` gets
/// the low bytes of `zigzag(q[i] − reference[i])` (wrapping, as u16), then the high bytes.
pub fn q16r_encode(q: &[i16], reference: &[i16], out: &mut [u8]) {
    let n = q.len();
    q16r_planes(q, &reference[..n], |c| c, &mut out[..2 * n]);
}

/// The residual planes of q16 components `cur` against `reference` (both little-endian int16
/// bytes of one length): [`q16r_encode`] on the bytes a q16 buffer travels as (a session's
/// temporal residuals code each viewer's buffers this way, without copying them into `i16`s
/// first).
pub fn q16r_encode_le(cur: &[u8], reference: &[u8]) -> Vec<u8> {
    let n = cur.len().min(reference.len()) / 2;
    let mut out = vec![0u8; 2 * n];
    let (cur, _) = cur[..2 * n].as_chunks::<2>();
    let (reference, _) = reference[..2 * n].as_chunks::<2>();
    q16r_planes(cur, reference, i16::from_le_bytes, &mut out);
    out
}

/// The one q16r coder behind [`q16r_encode`] and [`q16r_encode_le`]: components of any
/// representation `T` (read as i16 by `value`), `out` exactly `2 × q.len()` bytes.
#[inline(always)]
fn q16r_planes<T: Copy>(q: &[T], reference: &[T], value: impl Fn(T) -> i16, out: &mut [u8]) {
    let (lo, hi) = out.split_at_mut(q.len());
    // Fixed-size chunks without index checks, each zigzagged whole and then split into its
    // two planes: the compiler vectorizes this (3.4 µs for the embedded head's 21,786
    // components, against 5.5 µs element by element). A session runs it per viewer over every
    // changed buffer of every tick.
    const CHUNK: usize = 64;
    let mut qc = q.chunks_exact(CHUNK);
    let mut rc = reference.chunks_exact(CHUNK);
    let mut lc = lo.chunks_exact_mut(CHUNK);
    let mut hc = hi.chunks_exact_mut(CHUNK);
    let zigzag = |a: T, b: T| {
        let d = value(a).wrapping_sub(value(b));
        ((d << 1) ^ (d >> 15)) as u16
    };
    for (((a, b), l), h) in (&mut qc).zip(&mut rc).zip(&mut lc).zip(&mut hc) {
        let mut z = [0u16; CHUNK];
        for k in 0..CHUNK {
            z[k] = zigzag(a[k], b[k]);
        }
        for k in 0..CHUNK {
            l[k] = z[k] as u8;
            h[k] = (z[k] >> 8) as u8;
        }
    }
    let tail = qc.remainder().iter().zip(rc.remainder());
    for (((&a, &b), l), h) in tail.zip(lc.into_remainder()).zip(hc.into_remainder()) {
        let z = zigzag(a, b);
        *l = z as u8;
        *h = (z >> 8) as u8;
    }
}

/// The q16 components that [`q16r_encode`] coded as `planes` against `reference`.
pub fn q16r_decode(planes: &[u8], reference: &[i16]) -> Result<Vec<i16>, String> {
    let n = reference.len();
    if planes.len() != 2 * n {
        return Err(format!(
            "{} residual bytes for a reference of {n} components",
            planes.len()
        ));
    }
    let (lo, hi) = planes.split_at(n);
    Ok(lo
        .iter()
        .zip(hi)
        .zip(reference)
        .map(|((&l, &h), &r)| {
            let z = u16::from(l) | (u16::from(h) << 8);
            let d = ((z >> 1) as i16) ^ -((z & 1) as i16);
            r.wrapping_add(d)
        })
        .collect())
}

/// `path?rig=RIG` (percent-encoded) when there is a rig: the routing hint of a crowd frame or
/// render, which the server reads only to find a rig it does not hold, and a load balancer
/// hashes on (README, "Running more than one").
pub fn with_rig_hint(path: &str, rig: Option<&str>) -> String {
    match rig {
        Some(r) if !r.is_empty() => format!("{path}?rig={}", percent_encode(r)),
        _ => path.to_string(),
    }
}

/// `s` with every byte but ASCII letters, digits and `-._~` as `%XX` (RFC 3986's unreserved
/// characters): safe as a path segment or a query value.
pub fn percent_encode(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for b in s.bytes() {
        if b.is_ascii_alphanumeric() || matches!(b, b'-' | b'.' | b'_' | b'~') {
            out.push(b as char);
        } else {
            out.push_str(&format!("%{b:02X}"));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The planes as the spec defines them, element by element.
    fn planes_by_definition(q: &[i16], reference: &[i16]) -> Vec<u8> {
        let n = q.len();
        let mut out = vec![0u8; 2 * n];
        for i in 0..n {
            let d = q[i].wrapping_sub(reference[i]);
            let z = ((d << 1) ^ (d >> 15)) as u16;
            out[i] = z as u8;
            out[n + i] = (z >> 8) as u8;
        }
        out
    }

    #[test]
    fn q16r_on_little_endian_bytes_is_q16r_encode() {
        let cur: Vec<i16> = vec![0, 1, -1, i16::MAX, i16::MIN, 1234, -32000, 7];
        let reference: Vec<i16> = vec![0, 0, 0, i16::MIN, i16::MAX, 1000, 32000, 7];
        let bytes = |v: &[i16]| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
        let got = q16r_encode_le(&bytes(&cur), &bytes(&reference));
        let mut want = vec![0u8; 2 * cur.len()];
        q16r_encode(&cur, &reference, &mut want);
        assert_eq!(got, want);
        assert_eq!(q16r_decode(&got, &reference).expect("decodes"), cur);
        // Across the chunk edges of the vectorized loop.
        for n in [63, 64, 65, 128, 200] {
            let cur: Vec<i16> = (0..n)
                .map(|i| (i * 7919 % 65_536 - 32_768) as i16)
                .collect();
            let reference: Vec<i16> = (0..n)
                .map(|i| (i * 104_729 % 65_536 - 32_768) as i16)
                .collect();
            let mut want = vec![0u8; 2 * n as usize];
            q16r_encode(&cur, &reference, &mut want);
            assert_eq!(
                q16r_encode_le(&bytes(&cur), &bytes(&reference)),
                want,
                "n = {n}"
            );
        }
    }

    #[test]
    fn q16r_planes_match_the_definition_and_round_trip_at_every_chunk_edge() {
        let mut state = 0x1234_5678_u32;
        let mut next = || {
            state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (state >> 16) as u16 as i16
        };
        for n in [0, 1, 2, 63, 64, 65, 127, 128, 129, 3 * 7262] {
            let mut q: Vec<i16> = (0..n).map(|_| next()).collect();
            let reference: Vec<i16> = (0..n).map(|_| next()).collect();
            // The extremes, whose differences wrap.
            if n >= 2 {
                q[0] = i16::MIN;
                q[n - 1] = i16::MAX;
            }
            let mut planes = vec![0u8; 2 * n];
            q16r_encode(&q, &reference, &mut planes);
            assert_eq!(planes, planes_by_definition(&q, &reference), "n = {n}");
            assert_eq!(
                q16r_decode(&planes, &reference).expect("decodes"),
                q,
                "n = {n}"
            );
        }
    }
}
