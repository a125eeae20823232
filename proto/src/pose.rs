//! Poses for clients that blend themselves (three.js, Unity and other engines with GPU morph
//! targets): per head its final weights and the local transforms of the skeleton nodes its pose
//! moves, instead of a vertex buffer. A crowd frame asks with `"format": "weights"` (the answer
//! is a [`CrowdPoseResponse`]); a session viewer with `"output": "weights"` (its ticks are
//! [`TickPoses`], stream variant 5). `GET /v1/rigs/{id}/channels` ([`RigChannels`]) names what
//! the numbers are about once: the rig's weight channels and its skeleton's nodes.
//!
//! Weights travel as IEEE binary16 (2 bytes a channel: 52 ARKit weights are 104 bytes where
//! one q16 buffer of an ICT-sized head is 160 KB); [`f16_to_f32`] and [`f32_to_f16`] are the
//! conversions, written out so that this crate needs no float library.

use serde::{Deserialize, Serialize};

use crate::{Blob, Format, FrameTimings, HeadBuffer, SessionHead};

/// Largest finite binary16 value: weights beyond ±this are sent as ±this.
pub const MAX_F16_WEIGHT: f32 = 65504.0;

/// One head's final pose: what the server would blend, for a client that blends itself.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct HeadPose {
    /// One IEEE binary16 (little-endian) per weight channel of the rig, in channel order (the
    /// `targets` of `GET /v1/rigs/{id}/channels`): the weights after blends, layers, live
    /// input and clamps, as the engine would apply them at LOD 0.
    pub weights: Blob,
    /// On a rig with a skeleton: every node whose local transform is not its rest transform,
    /// in node order (the `nodes` of `GET /v1/rigs/{id}/channels`); nodes not listed are at
    /// rest. Empty on a rig without a skeleton.
    pub joints: Vec<NodePose>,
}

impl HeadPose {
    /// The weights as f32, one per channel.
    pub fn weights_f32(&self) -> Vec<f32> {
        self.weights.to_u16().into_iter().map(f16_to_f32).collect()
    }
}

/// A node's local transform in a pose, where it differs from the node's rest transform.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct NodePose {
    /// The node's index in `GET /v1/rigs/{id}/channels`' `nodes`.
    pub node: u32,
    /// Local rotation, unit quaternion x, y, z, w (always sent, also when only a translation
    /// or scale moved).
    pub rotation: [f32; 4],
    /// Local translation, when it differs from the rest translation (absent: the rest one).
    pub translation: Option<[f32; 3]>,
    /// Local scale, when it differs from the rest scale (absent: the rest one).
    pub scale: Option<[f32; 3]>,
}

/// `POST /v1/crowd/frame` response to `"format": "weights"`: no vertex buffer, no engine
/// work; per unique pose its weights and moved nodes (heads that agree share one, as clones
/// share a buffer).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CrowdPoseResponse {
    /// Always [`Format::Weights`]: the first field of either crowd-frame answer says which
    /// one follows.
    pub format: Format,
    /// Unique poses, in order of first appearance among the heads.
    pub poses: Vec<HeadPose>,
    /// One entry per request head, in request order: an index into `poses`.
    pub heads: Vec<HeadBuffer>,
    /// Timings (`queue_us` and `compute_us` are 0: no batch computed them).
    pub timings: FrameTimings,
}

/// A session tick for a viewer that asked for `"output": "weights"` (stream variant 5): the
/// poses of the heads whose weights or joints changed since the last message this viewer
/// received, [`crate::HEAD_UNCHANGED`] for the others.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TickPoses {
    /// Tick number (the session's clock, starting at 1).
    pub tick: u64,
    /// The session's heads and placements, when they changed since the last message this
    /// viewer received (always present in its first message).
    pub layout: Option<Vec<SessionHead>>,
    /// Poses of the heads whose pose changed for this viewer.
    pub poses: Vec<HeadPose>,
    /// One entry per session head, in layout order: an index into `poses`,
    /// [`crate::HEAD_UNCHANGED`] or [`crate::HEAD_MISSING`].
    pub heads: Vec<HeadBuffer>,
    /// Where the tick's time went (`queue_us` and `compute_us` are 0: no engine work).
    pub timings: FrameTimings,
}

/// `GET /v1/rigs/{id}/channels`: what a [`HeadPose`]'s numbers are about.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct RigChannels {
    /// Rig id.
    pub rig: String,
    /// One label per weight channel, in channel order: the target's name, or `name#k` for
    /// the k-th channel of a name that has several (`RigInfo.split_targets`), as the LOD
    /// order labels them.
    pub targets: Vec<String>,
    /// Every node of the skeleton, parents first (glTF node names, or `node<i>`); empty for a
    /// rig without a skeleton.
    pub nodes: Vec<String>,
}

/// An IEEE binary16 bit pattern as f32 (exact: every binary16 value is an f32).
pub fn f16_to_f32(h: u16) -> f32 {
    let negative = h & 0x8000 != 0;
    let exp = u32::from((h >> 10) & 0x1f);
    let man = u32::from(h & 0x3ff);
    let magnitude = match exp {
        // Zero and subnormals: man × 2^-24.
        0 => man as f32 * (1.0 / 16_777_216.0),
        31 => f32::from_bits(0x7f80_0000 | (man << 13)),
        e => f32::from_bits(((e + 112) << 23) | (man << 13)),
    };
    if negative { -magnitude } else { magnitude }
}

/// `v` as the nearest IEEE binary16 (ties to even), saturating at ±[`MAX_F16_WEIGHT`]; NaN
/// stays NaN.
pub fn f32_to_f16(v: f32) -> u16 {
    if v.is_nan() {
        return 0x7e00;
    }
    let sign = if v.is_sign_negative() { 0x8000u16 } else { 0 };
    let a = v.abs().min(MAX_F16_WEIGHT);
    let bits = a.to_bits();
    let exp = (bits >> 23) as i32 - 127;
    let out = if exp < -14 {
        // Subnormal (or zero): a multiple of 2^-24, rounded to even.
        let q = f64::from(a) * 16_777_216.0;
        round_even(q) as u16
    } else {
        // Normal: 10 mantissa bits kept, the rest rounded to even; a carry moves the exponent
        // up, which is the right answer (and `a` ≤ 65504 keeps it finite).
        let man = bits & 0x007f_ffff;
        let mut h = (((exp + 15) as u32) << 10) | (man >> 13);
        let rest = man & 0x1fff;
        if rest > 0x1000 || (rest == 0x1000 && h & 1 == 1) {
            h += 1;
        }
        h as u16
    };
    sign | out
}

fn round_even(q: f64) -> f64 {
    let r = q.round();
    if (r - q).abs() == 0.5 && r % 2.0 != 0.0 {
        r - q.signum()
    } else {
        r
    }
}

/// Weights as binary16 bytes, little-endian, one per weight.
pub fn weights_f16_le(weights: &[f32]) -> Vec<u8> {
    weights
        .iter()
        .flat_map(|&w| f32_to_f16(w).to_le_bytes())
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn binary16_round_trips_and_rounds_to_nearest_even() {
        // Every finite binary16 value decodes and encodes back to itself.
        for h in 0u16..=0xffff {
            let exp = (h >> 10) & 0x1f;
            if exp == 31 {
                continue;
            }
            assert_eq!(f32_to_f16(f16_to_f32(h)), h, "{h:#06x}");
        }
        assert_eq!(f16_to_f32(0x3c00), 1.0);
        assert_eq!(f16_to_f32(0xc000), -2.0);
        assert_eq!(f16_to_f32(0x0001), 2f32.powi(-24));
        assert_eq!(f16_to_f32(0x7bff), 65504.0);
        // Halfway between 1 and the next binary16 (1 + 2^-10): to the even one, 1.
        assert_eq!(f32_to_f16(1.0 + 2f32.powi(-11)), 0x3c00);
        // Just past halfway: up.
        assert_eq!(f32_to_f16(1.0 + 2f32.powi(-11) + 2f32.powi(-20)), 0x3c01);
        // Halfway between 1 + 2^-10 and 1 + 2^-9: to the even one, 1 + 2^-9.
        assert_eq!(f32_to_f16(1.0 + 3.0 * 2f32.powi(-11)), 0x3c02);
        // Saturating, and a subnormal halfway case to even.
        assert_eq!(f32_to_f16(1e9), 0x7bff);
        assert_eq!(f32_to_f16(-1e9), 0xfbff);
        assert_eq!(f32_to_f16(2f32.powi(-25)), 0x0000);
        assert_eq!(f32_to_f16(3.0 * 2f32.powi(-25)), 0x0002);
        assert_eq!(f32_to_f16(-0.0), 0x8000);
        // Relative error within 2^-11 over a range of weights.
        for i in 0..10_000 {
            let w = (i as f32 - 5000.0) * 0.000_731;
            let back = f16_to_f32(f32_to_f16(w));
            assert!(
                (back - w).abs() <= w.abs() * 2f32.powi(-11) + 2f32.powi(-25),
                "{w} → {back}"
            );
        }
    }
}
