//! Live input for session heads (issue 47): a head with a [`LiveSpec`] shows what producers
//! (a face tracker, Audio2Face, Live Link Face) send for it by `POST /v1/sessions/{id}/live`
//! or over the WebSocket at `GET /v1/sessions/{id}/live`, as [`LiveInput`] messages.
//!
//! At each tick a live head shows its input over its base (its clip or graph pose with its
//! layers, or the neutral without a clip): by timecode through a jitter buffer when producers
//! send `t`, else the newest sample, optionally smoothed by a One Euro filter. Without input
//! for `hold_ms` it fades back to its base over `fade_ms`; input that comes back fades in the
//! same way, so neither pops.

use serde::{Deserialize, Serialize};

use crate::{JointOverrides, LiveWeights};

fn hold_ms() -> u32 {
    500
}

fn fade_ms() -> u32 {
    250
}

fn delay_ms() -> u32 {
    100
}

fn min_cutoff() -> f32 {
    1.0
}

fn d_cutoff() -> f32 {
    1.0
}

/// How a session head follows live input (`SessionHead::live`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LiveSpec {
    /// Milliseconds the last input is held once producers go quiet, before the head fades
    /// back to its base (0..=60,000; default 500).
    #[serde(default = "hold_ms")]
    pub hold_ms: u32,
    /// Milliseconds a fade to or from live input takes (0..=10,000; default 250).
    #[serde(default = "fade_ms")]
    pub fade_ms: u32,
    /// With timecodes (`t`): how far behind the producer's clock the head plays, so that late
    /// samples still arrive in time to be interpolated (0..=5,000; default 100).
    #[serde(default = "delay_ms")]
    pub delay_ms: u32,
    /// Without timecodes: smooth the newest sample with a One Euro filter.
    #[serde(default)]
    pub smoothing: Option<OneEuro>,
    /// A rig mapping the producer's named weights go through first (`arkit`, `a2f`,
    /// `oculus-visemes`, `vrm` or one of the rig's own; 404 `unknown_mapping` when the head is
    /// added); Live Link's head and eye angles still turn joints.
    #[serde(default)]
    pub mapping: Option<String>,
}

impl Default for LiveSpec {
    fn default() -> Self {
        LiveSpec {
            hold_ms: hold_ms(),
            fade_ms: fade_ms(),
            delay_ms: delay_ms(),
            smoothing: None,
            mapping: None,
        }
    }
}

/// The One Euro filter's parameters (Casiez, Roussel and Vogel, CHI 2012): a low-pass whose
/// cutoff rises with the speed of the signal, so a still face does not jitter and a fast
/// one does not lag.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OneEuro {
    /// Cutoff at rest, Hz (> 0; default 1).
    #[serde(default = "min_cutoff")]
    pub min_cutoff: f32,
    /// How fast the cutoff rises with speed (≥ 0; default 0: a plain low-pass).
    #[serde(default)]
    pub beta: f32,
    /// Cutoff of the speed's own low-pass, Hz (> 0; default 1).
    #[serde(default = "d_cutoff")]
    pub d_cutoff: f32,
}

/// `POST /v1/sessions/{id}/live` body, and one message on the live WebSocket.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LiveInput {
    /// One sample per head (a head may appear more than once, with different `t`).
    pub heads: Vec<LiveSample>,
}

/// One producer sample for one live head.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LiveSample {
    /// The session head (it must have `live`).
    pub head: u64,
    /// Weights by name (through the head's mapping, when it has one) or dense in the rig's
    /// target order; Live Link Face's head and eye angles among named weights turn joints
    /// through the rig's joint map.
    #[serde(default)]
    pub weights: Option<LiveWeights>,
    /// Local rotations of named skeleton nodes (`{"Head": {"rotation": [x, y, z, w]}}`);
    /// live joints carry rotations only.
    #[serde(default)]
    pub joints: JointOverrides,
    /// The producer's timecode, seconds (any origin, increasing): samples are then played
    /// by timecode `delay_ms` behind the producer, reordered when they arrive out of order.
    #[serde(default)]
    pub t: Option<f64>,
}

/// The answer to `POST /v1/sessions/{id}/live`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct LiveAck {
    /// Samples taken.
    pub accepted: u32,
}
