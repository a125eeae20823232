//! A job's final pose for a client that blends itself (`"format": "weights"` crowd frames,
//! `"output": "weights"` viewers): its weight per channel as binary16 and, on a skinned rig,
//! the local transforms of the nodes its pose moves from rest — exactly what the engine would
//! blend and skin at LOD 0, so a client applying them to the rig (neutral + Σ w·delta, then the
//! skin) draws what the server's vertices show. Shared by `routes::frames` and the session
//! tick; what a pose holds is priced here ([`pose_bytes`]) so both charge it before it exists.

use crowdmorph_core::rig::{JointPose, Pose, Rig, Trs};
use crowdmorph_proto::{Blob, HeadPose, NodePose, weights_f16_le};

use crate::http::ApiError;

/// Most bytes one [`HeadPose`] of `rig` holds in memory and takes encoded (bincode, or JSON
/// when `json`: base64 weights, every float spelled out): its weights, one [`NodePose`] per
/// node of the skeleton at most, and their encoding, with room for the vectors' headers.
pub fn pose_bytes(rig: &Rig, json: bool) -> u64 {
    let channels = rig.targets.len() as u64;
    let nodes = rig.skeleton.as_ref().map_or(0, |s| s.nodes.len()) as u64;
    let held = 64 + 2 * channels + nodes * size_of::<NodePose>() as u64;
    // bincode: a node is at most 5 + 16 + 13 + 13 bytes; JSON about 200 characters (ten
    // floats of up to 15, the names and separators), base64 weights 4/3 of their bytes.
    let encoded = if json {
        64 + 3 * channels + nodes * 200
    } else {
        16 + 2 * channels + nodes * 48
    };
    held + encoded
}

/// Bytes the scratch of [`head_pose`] holds for `rig`: one local transform per node.
pub fn scratch_bytes(rig: &Rig) -> u64 {
    rig.skeleton
        .as_ref()
        .map_or(0, |s| (s.nodes.len() * size_of::<Trs>()) as u64)
}

/// The final pose of a job of `rig` that plays `pose` with `joints` over it: every channel's
/// weight (saturated to binary16's range), and every node whose local transform differs from
/// its rest one. `locals` is scratch (charged by the caller: [`scratch_bytes`]).
pub fn head_pose(rig: &Rig, pose: &Pose, joints: &JointPose, locals: &mut Vec<Trs>) -> HeadPose {
    let weights = Blob(weights_f16_le(&pose.weights(rig)));
    let Some(sk) = &rig.skeleton else {
        return HeadPose {
            weights,
            joints: Vec::new(),
        };
    };
    // As the engines pose a job: its pose's joint terms, then its overrides (layers, live
    // angles and the head's own joints, already merged into `joints`).
    sk.locals_of(&pose.skin_terms(rig), locals);
    joints.apply(sk, locals);
    let moved = sk
        .nodes
        .iter()
        .zip(locals.iter())
        .enumerate()
        .filter(|(_, (n, l))| n.rest != **l)
        .map(|(i, (n, l))| NodePose {
            node: i as u32,
            rotation: l.rotation,
            translation: (l.translation != n.rest.translation).then_some(l.translation),
            scale: (l.scale != n.rest.scale).then_some(l.scale),
        })
        .collect();
    HeadPose {
        weights,
        joints: moved,
    }
}

/// 400 `invalid_output`: output options that do not go together (a weights crowd frame with
/// normals, or a head with a LOD level).
pub fn invalid_output(message: String) -> ApiError {
    ApiError::bad_request("invalid_output", message)
}
