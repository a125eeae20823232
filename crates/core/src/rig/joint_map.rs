//! Which clip columns turn which joints: Live Link Face's head and eye angles.
//!
//! Apple's ARKit, and the Live Link Face app that records it, send the head's and each eye's
//! yaw, pitch and roll beside the 52 blendshape weights (`HeadYaw`, `HeadPitch`, `HeadRoll`,
//! `LeftEyeYaw`, ..., `RightEyeRoll`). A [`JointMap`] says which skeleton node each such column
//! turns, about which axis and by how much per unit. A rig without one of its own gets
//! [`JointMap::defaults`]: `Head`, `LeftEye` and `RightEye` as Ready Player Me names its bones,
//! `head`, `leftEye`, `rightEye` (VRM humanoid bone names) and VRoid Studio's `J_Bip_C_Head`,
//! `J_Adj_L_FaceEye`, `J_Adj_R_FaceEye`, whichever the skeleton has.
//!
//! A column's value `v` turns its node by `v × scale` radians about `axis`, an axis of *rig
//! space* (glTF's: +Y up, +Z out of the face, +X to the character's left), about the node's
//! origin, so the same map serves bones whatever their local axes are: the node's local
//! rotation becomes `rest × G⁻¹ Δ G`, with `G` its global rotation at rest and `Δ` the
//! rotations of its columns composed in the map's order (yaw, then pitch, then roll in the
//! defaults). Then, with its ancestors at rest, its global orientation is `Δ G`: the rest pose
//! turned in rig axes.

use glam::{Quat, Vec3};
use serde::{Deserialize, Serialize};

use super::{Skeleton, Trs};

/// One column that turns a node.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JointChannel {
    /// The clip column (matched in any loose spelling, as target names are).
    pub column: String,
    /// Index in [`Skeleton::nodes`].
    pub node: u32,
    /// Unit axis in rig space.
    pub axis: [f32; 3],
    /// Radians per unit of the column.
    pub scale: f32,
}

/// A rig's columns that turn joints (see the module doc).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct JointMap {
    /// The channels, in the order their rotations compose per node.
    pub channels: Vec<JointChannel>,
}

/// Most channels a map may have.
pub const MAX_JOINT_CHANNELS: usize = 256;

/// Live Link Face's angle columns: (column, the default node names, the rig-space axis).
pub const LIVE_LINK_COLUMNS: [(&str, &[&str], [f32; 3]); 9] = [
    ("HeadYaw", HEAD_NAMES, [0.0, 1.0, 0.0]),
    ("HeadPitch", HEAD_NAMES, [1.0, 0.0, 0.0]),
    ("HeadRoll", HEAD_NAMES, [0.0, 0.0, 1.0]),
    ("LeftEyeYaw", LEFT_EYE_NAMES, [0.0, 1.0, 0.0]),
    ("LeftEyePitch", LEFT_EYE_NAMES, [1.0, 0.0, 0.0]),
    ("LeftEyeRoll", LEFT_EYE_NAMES, [0.0, 0.0, 1.0]),
    ("RightEyeYaw", RIGHT_EYE_NAMES, [0.0, 1.0, 0.0]),
    ("RightEyePitch", RIGHT_EYE_NAMES, [1.0, 0.0, 0.0]),
    ("RightEyeRoll", RIGHT_EYE_NAMES, [0.0, 0.0, 1.0]),
];

/// Node names of a head, first found wins: Ready Player Me, VRM humanoid, VRoid Studio.
pub const HEAD_NAMES: &[&str] = &["Head", "head", "J_Bip_C_Head"];
/// Node names of the left eye.
pub const LEFT_EYE_NAMES: &[&str] = &["LeftEye", "leftEye", "J_Adj_L_FaceEye"];
/// Node names of the right eye.
pub const RIGHT_EYE_NAMES: &[&str] = &["RightEye", "rightEye", "J_Adj_R_FaceEye"];

impl JointMap {
    /// The default map of `skeleton`: each Live Link column whose node (by the names above)
    /// the skeleton has, one unit a radian.
    pub fn defaults(skeleton: &Skeleton) -> JointMap {
        let find = |names: &[&str]| {
            names.iter().find_map(|n| {
                let mut hits = skeleton
                    .nodes
                    .iter()
                    .enumerate()
                    .filter(|(_, x)| x.name == *n);
                match (hits.next(), hits.next()) {
                    (Some((i, _)), None) => Some(i as u32),
                    _ => None,
                }
            })
        };
        JointMap {
            channels: LIVE_LINK_COLUMNS
                .iter()
                .filter_map(|&(column, names, axis)| {
                    Some(JointChannel {
                        column: column.into(),
                        node: find(names)?,
                        axis,
                        scale: 1.0,
                    })
                })
                .collect(),
        }
    }

    /// Why the map does not fit `skeleton`, if it does not.
    pub fn check(&self, skeleton: &Skeleton) -> Result<(), String> {
        if self.channels.len() > MAX_JOINT_CHANNELS {
            return Err(format!(
                "{} joint channels; at most {MAX_JOINT_CHANNELS}",
                self.channels.len()
            ));
        }
        for (i, c) in self.channels.iter().enumerate() {
            if c.node as usize >= skeleton.nodes.len() {
                return Err(format!(
                    "channel {i} names node {} of {}",
                    c.node,
                    skeleton.nodes.len()
                ));
            }
            let axis = Vec3::from(c.axis);
            if !axis.is_finite() || (axis.length() - 1.0).abs() > 1e-3 || !c.scale.is_finite() {
                return Err(format!(
                    "channel {i} ({:?}): the axis must be a unit vector and the scale finite",
                    c.column
                ));
            }
            if self.channels[..i].iter().any(|o| o.column == c.column) {
                return Err(format!("column {:?} is mapped twice", c.column));
            }
        }
        Ok(())
    }

    /// Bytes it holds.
    pub fn bytes(&self) -> u64 {
        self.channels
            .iter()
            .map(|c| size_of::<JointChannel>() as u64 + c.column.len() as u64)
            .sum()
    }

    /// The nodes its channels turn, ascending, each once.
    pub fn nodes(&self, of: &[usize]) -> Vec<u32> {
        let mut n: Vec<u32> = of.iter().map(|&c| self.channels[c].node).collect();
        n.sort_unstable();
        n.dedup();
        n
    }

    /// Node `node`'s local transform when channels `of` (indices into `channels`) have
    /// `values`: its rest, turned by their rotations in rig axes (see the module doc).
    /// `rest_globals` are every node's global rotation at rest ([`rest_rotations`]).
    pub fn local(
        &self,
        skeleton: &Skeleton,
        rest_globals: &[Quat],
        node: u32,
        of: &[usize],
        values: &[f32],
    ) -> Trs {
        let n = &skeleton.nodes[node as usize];
        // In the map's order, whatever order the source gives the columns in: rotations do
        // not commute.
        let mut delta = Quat::IDENTITY;
        for (c, ch) in self.channels.iter().enumerate() {
            if ch.node != node {
                continue;
            }
            if let Some(k) = of.iter().position(|&o| o == c) {
                let v = values.get(k).copied().unwrap_or(0.0);
                delta *= Quat::from_axis_angle(Vec3::from(ch.axis).normalize(), v * ch.scale);
            }
        }
        let g = rest_globals[node as usize];
        let rest = Quat::from_array(n.rest.rotation).normalize();
        Trs {
            rotation: (rest * g.inverse() * delta * g).normalize().to_array(),
            ..n.rest
        }
    }
}

/// Every node's global rotation at rest (parents first).
pub fn rest_rotations(skeleton: &Skeleton) -> Vec<Quat> {
    let mut out: Vec<Quat> = Vec::with_capacity(skeleton.nodes.len());
    for n in &skeleton.nodes {
        let local = Quat::from_array(n.rest.rotation).normalize();
        let g = match out.get(n.parent as usize) {
            Some(p) => *p * local,
            None => local,
        };
        out.push(g);
    }
    out
}
