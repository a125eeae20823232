//! Layers over a head's base pose (issue 47): a clip frame applied over what the head already
//! shows, on the targets (and joints) a mask selects, by override or by addition — what
//! Unreal's layered and additive blends, Houdini's additive clip layers and Audio2Face's
//! upper/lower-face masks do.
//!
//! Eq. 1 is linear in the weights, so layering in weight space is layering the meshes:
//! - **override**, fraction `a = weight × mask_k`: `w_k ← (1 − a)·w_k + a·layer_k`;
//! - **additive**: `w_k ← w_k + a·(layer_k − reference_k)`, the reference a frame of the
//!   layer's clip or, absent, the neutral (every weight 0): a layer that adds a smile adds
//!   what its frame has more than its reference.
//!
//! On a skinned rig the layer's clip also moves the joints its table animates (a joint mask
//! narrows them): override slerps each node's rotation toward the layer's (translation and
//! scale by lerp), additive applies the layer's local rotation relative to its reference
//! (`base · (reference⁻¹ · layer)^a`) and adds its translation and scale differences.
//!
//! The result is one weight per channel (and a node's local transforms): the server quantizes
//! it as live weights, so heads whose layers give equal weights still share one job.

use std::sync::Arc;

use glam::{Quat, Vec3};

use super::{Rig, Skeleton, Trs};

/// Most layers one head may have.
pub const MAX_POSE_LAYERS: usize = 8;

/// Channels (or skeleton nodes) a layer touches, ascending, each with its mask weight in
/// [0, 1].
pub type Selection = Arc<[(u32, f32)]>;

/// How a layer combines with what is below it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum LayerMode {
    /// Masked channels move toward the layer's values by its weight.
    Override,
    /// Masked channels gain the weight times the layer's difference from its reference.
    Additive,
}

/// One layer resolved against a rig: indices checked, names matched, the mask a sparse list.
#[derive(Clone, Debug, PartialEq)]
pub struct PoseLayer {
    /// Clip index within the rig.
    pub clip: u32,
    /// Frame of that clip (already wrapped or clamped).
    pub frame: u32,
    /// The layer's weight, in [0, 1].
    pub weight: f32,
    /// Override or additive.
    pub mode: LayerMode,
    /// Per masked channel its mask weight in [0, 1], channels ascending; `None`: every channel
    /// at 1.
    pub mask: Option<Selection>,
    /// Additive only: the frame of the same clip the layer is measured from; `None`: neutral.
    pub reference: Option<u32>,
    /// Skeleton nodes the layer may move, with their mask weights, nodes ascending; `None`:
    /// every node its clip's joint table animates, at 1.
    pub joint_mask: Option<Selection>,
}

impl PoseLayer {
    /// Heap bytes it holds (for queue-memory charges).
    pub fn heap_bytes(&self) -> u64 {
        let list =
            |m: &Option<Selection>| m.as_ref().map_or(0, |m| 16 + size_of_val(&m[..]) as u64);
        list(&self.mask) + list(&self.joint_mask)
    }
}

/// Applies `layers` in order to `w` (one weight per rig channel; clips and frames checked).
pub fn layer_weights(rig: &Rig, w: &mut [f32], layers: &[PoseLayer]) {
    let n = w.len();
    for l in layers {
        let clip = &rig.clips[l.clip as usize];
        let mut apply = |k: usize, m: f32| {
            let a = l.weight * m;
            let value = clip.weight(k, l.frame);
            match l.mode {
                LayerMode::Override => w[k] = (1.0 - a) * w[k] + a * value,
                LayerMode::Additive => {
                    let reference = l.reference.map_or(0.0, |r| clip.weight(k, r));
                    w[k] += a * (value - reference);
                }
            }
        };
        match &l.mask {
            None => (0..n).for_each(|k| apply(k, 1.0)),
            Some(mask) => mask
                .iter()
                .filter(|(k, _)| (*k as usize) < n)
                .for_each(|&(k, m)| apply(k as usize, m)),
        }
    }
}

/// Applies `layers` in order to a skeleton's local transforms `locals` (one per node): each
/// layer's clip moves the nodes of its joint table (a clip without one moves none), narrowed
/// by the joint mask (a masked node the table does not animate is left alone).
pub fn layer_locals(rig: &Rig, sk: &Skeleton, locals: &mut [Trs], layers: &[PoseLayer]) {
    let mut layer = Vec::new();
    let mut reference = Vec::new();
    for l in layers {
        let Some(table) = rig.clips[l.clip as usize].joints.as_deref() else {
            continue;
        };
        sk.locals_at(Some(table), l.frame, &mut layer);
        match l.reference {
            Some(r) => sk.locals_at(Some(table), r, &mut reference),
            None => sk.locals_at(None, 0, &mut reference),
        }
        let mut apply = |n: usize, m: f32| {
            let (Some(base), Some(to), Some(from)) =
                (locals.get(n).copied(), layer.get(n), reference.get(n))
            else {
                return;
            };
            let a = l.weight * m;
            locals[n] = match l.mode {
                LayerMode::Override => blend_trs(&base, to, a),
                LayerMode::Additive => add_trs(&base, from, to, a),
            };
        };
        match &l.joint_mask {
            None => table.nodes.iter().for_each(|&n| apply(n as usize, 1.0)),
            // A mask narrows what the clip animates: a node its table does not hold keeps
            // what is below (its rest would otherwise pull it back).
            Some(mask) => mask
                .iter()
                .filter(|(n, _)| table.nodes.binary_search(n).is_ok())
                .for_each(|&(n, m)| apply(n as usize, m)),
        }
    }
}

fn quat(q: [f32; 4]) -> Quat {
    Quat::from_array(q).normalize()
}

/// `from` moved toward `to` by `a`: rotation by slerp, translation and scale by lerp.
pub fn blend_trs(from: &Trs, to: &Trs, a: f32) -> Trs {
    Trs {
        translation: Vec3::from(from.translation)
            .lerp(Vec3::from(to.translation), a)
            .to_array(),
        rotation: quat(from.rotation)
            .slerp(quat(to.rotation), a)
            .normalize()
            .to_array(),
        scale: Vec3::from(from.scale)
            .lerp(Vec3::from(to.scale), a)
            .to_array(),
    }
}

/// `base` with `a` of the change from `reference` to `layer`, in the node's local frame.
fn add_trs(base: &Trs, reference: &Trs, layer: &Trs, a: f32) -> Trs {
    let delta = quat(reference.rotation).inverse() * quat(layer.rotation);
    let part = Quat::IDENTITY.slerp(delta, a);
    let add = |b: [f32; 3], r: [f32; 3], l: [f32; 3]| {
        (Vec3::from(b) + a * (Vec3::from(l) - Vec3::from(r))).to_array()
    };
    Trs {
        translation: add(base.translation, reference.translation, layer.translation),
        rotation: (quat(base.rotation) * part).normalize().to_array(),
        scale: add(base.scale, reference.scale, layer.scale),
    }
}

/// Clamps every weight into `[lo, hi]`.
pub fn clamp_weights(w: &mut [f32], [lo, hi]: [f32; 2]) {
    for v in w {
        *v = v.clamp(lo, hi);
    }
}

/// ARKit's names in the built-in masks (`upper_face`, `lower_face`, `eyes`, `brows`, `mouth`),
/// matched against a rig's targets in any loose spelling; `None` for another name.
pub fn builtin_mask(name: &str) -> Option<Vec<&'static str>> {
    let arkit = super::ARKIT_NAMES;
    let pick = |f: &dyn Fn(&str) -> bool| arkit.iter().copied().filter(|n| f(n)).collect();
    let eyes = |n: &str| n.starts_with("eye");
    let brows = |n: &str| n.starts_with("brow");
    let lower = |n: &str| {
        n.starts_with("jaw")
            || n.starts_with("mouth")
            || n.starts_with("tongue")
            || n == "cheekPuff"
    };
    Some(match name {
        "eyes" => pick(&eyes),
        "brows" => pick(&brows),
        "mouth" => pick(&|n| n.starts_with("mouth") || n == "jawOpen"),
        "lower_face" => pick(&lower),
        "upper_face" => pick(&|n| !lower(n)),
        _ => return None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn built_in_masks_split_the_arkit_names() {
        let upper = builtin_mask("upper_face").expect("upper");
        let lower = builtin_mask("lower_face").expect("lower");
        assert_eq!(upper.len() + lower.len(), 52, "every name in one half");
        assert!(upper.iter().all(|n| !lower.contains(n)));
        assert!(upper.contains(&"eyeBlinkLeft") && upper.contains(&"browInnerUp"));
        assert!(upper.contains(&"cheekSquintLeft") && upper.contains(&"noseSneerLeft"));
        assert!(lower.contains(&"jawOpen") && lower.contains(&"mouthSmileLeft"));
        assert_eq!(builtin_mask("eyes").expect("eyes").len(), 14);
        assert_eq!(builtin_mask("brows").expect("brows").len(), 5);
        assert!(builtin_mask("mouth").expect("mouth").contains(&"jawOpen"));
        assert!(builtin_mask("knees").is_none());
    }

    #[test]
    fn additive_rotation_is_the_layers_change_from_its_reference() {
        let turn = |deg: f32| Quat::from_rotation_y(deg.to_radians()).to_array();
        let t = |r| Trs {
            rotation: r,
            ..Trs::default()
        };
        let base = t(turn(30.0));
        let out = add_trs(&base, &t(turn(10.0)), &t(turn(50.0)), 0.5);
        let got = quat(out.rotation).angle_between(Quat::from_rotation_y(50f32.to_radians()));
        assert!(got < 1e-3, "30° + ½·(50° − 10°) = 50°, off by {got}");
        let over = blend_trs(&base, &t(turn(90.0)), 0.5);
        let got = quat(over.rotation).angle_between(Quat::from_rotation_y(60f32.to_radians()));
        assert!(got < 1e-3, "halfway from 30° to 90° is 60°, off by {got}");
    }
}
