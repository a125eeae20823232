//! A head's `layers` resolved against its rig and applied (`crowdmorph_core::rig::layer`),
//! shared by crowd frames (`resolve`) and session ticks (`services::tick`): clips and frames
//! checked, masks matched by loose name (a rig's named masks first, then the built-in ones),
//! joint masks by node name, then the final weights
//! clamped and checked, and on a skinned rig the layered joints as overrides. Errors are the
//! 4xx a request gets, without the head: callers name it.

use std::sync::Arc;

use crowdmorph_core::rig::{
    JointPose, LayerMode, MAX_LIVE_WEIGHT, Pose, PoseLayer, Rig, Selection, Skeleton, Trs,
    builtin_mask, clamp_weights, layer_locals, quoted_name,
};
use crowdmorph_import::clips::checked_name;
use crowdmorph_proto::{Layer, Mask};

use crate::admission::names::{LiveNames, is_arkit_name, unknown_clip};
use crate::http::ApiError;
use crate::registry::RigEntry;

fn invalid(message: String) -> ApiError {
    ApiError::bad_request("invalid_layer", message)
}

/// Bytes a head's decoded `layers` hold (by capacity, with their names): charged with the
/// request body.
pub fn decoded_layers_bytes(layers: &Vec<Layer>) -> u64 {
    let text = |v: &String| v.capacity() as u64;
    layers.capacity() as u64 * size_of::<Layer>() as u64
        + layers
            .iter()
            .map(|l| {
                let mask = match &l.mask {
                    None => 0,
                    Some(Mask::Names(n)) => {
                        n.capacity() as u64 * size_of::<String>() as u64
                            + n.iter().map(text).sum::<u64>()
                    }
                    Some(Mask::Weights(w)) => {
                        w.capacity() as u64 * size_of::<(String, f32)>() as u64
                            + w.iter().map(|(n, _)| text(n)).sum::<u64>()
                    }
                    Some(Mask::Named(n)) => text(n),
                };
                let joints = l.joint_mask.as_ref().map_or(0, |j| {
                    j.capacity() as u64 * size_of::<String>() as u64
                        + j.iter().map(text).sum::<u64>()
                });
                text(&l.clip) + mask + joints
            })
            .sum::<u64>()
}

/// Bytes [`resolve_layers`] builds for `layers` on `rig`, at most: each layer, and per mask a
/// dense row of the rig's channels and the sparse list made of it (twice: built, then shared),
/// per joint mask the same of the skeleton's nodes.
pub fn layers_bytes(rig: &Rig, layers: &[Layer]) -> u64 {
    let channels = rig.targets.len() as u64;
    let nodes = rig.skeleton.as_ref().map_or(0, |s| s.nodes.len()) as u64;
    let mut bytes = (layers.len() * size_of::<PoseLayer>()) as u64;
    for l in layers {
        if l.mask.is_some() {
            bytes += 32 + 4 * channels + 2 * 8 * channels;
        }
        if l.joint_mask.is_some() {
            bytes += 32 + 2 * 8 * nodes;
        }
    }
    bytes
}

/// `layers` resolved against `entry`'s rig: each clip (404 `unknown_clip`), its frame and
/// reference frame through `frame(clip, frame, is_reference)` (a session plays a layer's
/// frames from its clock but keeps its reference where it is), its weight, mask (400 `unknown_targets` for a
/// non-ARKit name the rig lacks) and joint mask (400 `unknown_joints`); anything else wrong is
/// a 400 `invalid_layer` naming `layers[i]`. The caller charges [`layers_bytes`] first.
pub(crate) fn resolve_layers(
    entry: &RigEntry,
    names: &LiveNames,
    layers: &[Layer],
    mut frame: impl FnMut(u32, i64, bool) -> Result<u32, ApiError>,
) -> Result<Vec<PoseLayer>, ApiError> {
    let mut out = Vec::with_capacity(layers.len());
    for (i, l) in layers.iter().enumerate() {
        let at = |e: ApiError| ApiError {
            message: format!("layers[{i}]: {}", e.message),
            ..e
        };
        if !(l.weight.is_finite() && (0.0..=1.0).contains(&l.weight)) {
            return Err(at(invalid(format!(
                "weight is {}; it must be in [0, 1]",
                l.weight
            ))));
        }
        let clip = entry
            .clip_index(&l.clip)
            .ok_or_else(|| at(unknown_clip(entry, &l.clip)))? as u32;
        let f = frame(clip, l.frame, false).map_err(at)?;
        let reference = match (l.reference, l.mode) {
            (None, _) => None,
            (Some(r), crowdmorph_proto::LayerMode::Additive) => {
                Some(frame(clip, r, true).map_err(at)?)
            }
            (Some(_), crowdmorph_proto::LayerMode::Override) => {
                return Err(at(invalid(
                    "reference applies to additive layers only (\"mode\": \"additive\")".into(),
                )));
            }
        };
        let mask = match &l.mask {
            None => None,
            Some(m) => Some(mask(names, m).map_err(|e| ApiError {
                message: format!("layers[{i}].mask: {}", e.message),
                ..e
            })?),
        };
        let joint_mask = match &l.joint_mask {
            None => None,
            Some(nodes) => Some(joint_mask(entry, nodes).map_err(|e| ApiError {
                message: format!("layers[{i}].joint_mask {}", e.message),
                ..e
            })?),
        };
        out.push(PoseLayer {
            clip,
            frame: f,
            weight: l.weight,
            mode: match l.mode {
                crowdmorph_proto::LayerMode::Override => LayerMode::Override,
                crowdmorph_proto::LayerMode::Additive => LayerMode::Additive,
            },
            mask,
            reference,
            joint_mask,
        });
    }
    Ok(out)
}

/// Bytes [`check_mask`] builds on `rig`, at most: a dense row of its channels and the sparse
/// list made of it.
pub fn mask_bytes(rig: &Rig) -> u64 {
    32 + 4 * rig.targets.len() as u64 + 8 * rig.targets.len() as u64
}

/// Checks a mask against a rig as a layer's inline mask is checked (400 `invalid_layer`,
/// `unknown_targets`): what `PUT /v1/rigs/{id}/masks/{name}` stores. The caller charges
/// [`mask_bytes`] first.
pub(crate) fn check_mask(names: &LiveNames, m: &Mask) -> Result<(), ApiError> {
    mask(names, m).map(drop)
}

/// A layer's mask as channels with their weights, ascending: names matched as live weights
/// match them (ARKit names the rig lacks are skipped: it cannot show them), a rig's named mask
/// by name (`PUT /v1/rigs/{id}/masks/{name}`, checked as an inline one), else a built-in mask
/// by name; a channel named twice keeps its last weight. A list longer than the rig's names
/// and ARKit's together names something twice or nothing: a 400.
fn mask(names: &LiveNames, mask: &Mask) -> Result<Selection, ApiError> {
    let mask = match mask {
        Mask::Named(n) => match names.rig_mask(n) {
            // A stored mask is a list or weights (its PUT refuses a name).
            Some(stored @ (Mask::Names(_) | Mask::Weights(_))) => stored,
            _ => mask,
        },
        _ => mask,
    };
    let channels = names.by_position.iter().map(Vec::len).sum::<usize>();
    let most = names.by_position.len() + crowdmorph_core::rig::ARKIT_NAMES.len();
    let listed = match mask {
        Mask::Names(n) => n.len(),
        Mask::Weights(w) => w.len(),
        Mask::Named(_) => 0,
    };
    if listed > most {
        return Err(invalid(format!(
            "{listed} names for a rig of {} targets",
            names.by_position.len()
        )));
    }
    // One slot per channel (NaN: not in the mask), so repeats cost nothing.
    let mut dense = vec![f32::NAN; channels];
    let mut add = |name: &str, w: f32, strict: bool| -> Result<(), ApiError> {
        if !(w.is_finite() && (0.0..=1.0).contains(&w)) {
            return Err(invalid(format!(
                "{} has weight {w}; a mask weight must be in [0, 1]",
                quoted_name(name)
            )));
        }
        checked_name(name).map_err(|why| invalid(format!("{}: {why}", quoted_name(name))))?;
        let ids = names.ids(name);
        if ids.is_empty() && strict && !is_arkit_name(name) {
            return Err(ApiError::bad_request(
                "unknown_targets",
                format!("names {}, which the rig does not have", quoted_name(name)),
            ));
        }
        for &k in ids {
            if let Some(slot) = dense.get_mut(k as usize) {
                *slot = w;
            }
        }
        Ok(())
    };
    match mask {
        Mask::Names(list) => list.iter().try_for_each(|n| add(n, 1.0, true))?,
        Mask::Weights(list) => list.iter().try_for_each(|(n, w)| add(n, *w, true))?,
        Mask::Named(name) => match builtin_mask(name) {
            Some(list) => list.iter().try_for_each(|n| add(n, 1.0, false))?,
            None => {
                return Err(invalid(format!(
                    "no mask named {}: the rig has no such mask (GET /v1/rigs/{{id}}/masks), \
                     and the built-in masks are upper_face, lower_face, eyes, brows and mouth",
                    quoted_name(name)
                )));
            }
        },
    }
    let list: Vec<(u32, f32)> = dense
        .iter()
        .enumerate()
        .filter(|(_, w)| !w.is_nan())
        .map(|(k, &w)| (k as u32, w))
        .collect();
    Ok(list.into())
}

/// Skeleton nodes by name, ascending, each at 1 (at most the skeleton's node count).
fn joint_mask(entry: &RigEntry, nodes: &[String]) -> Result<Selection, ApiError> {
    let Some(sk) = &entry.rig().skeleton else {
        return Err(invalid(format!(
            "on rig {:?}, which has no skeleton",
            entry.id
        )));
    };
    if nodes.len() > sk.nodes.len() {
        return Err(invalid(format!(
            "names {} nodes of a skeleton of {}",
            nodes.len(),
            sk.nodes.len()
        )));
    }
    let mut out = Vec::with_capacity(nodes.len());
    for n in nodes {
        let node = entry.joint_node(n).map_err(|why| {
            ApiError::bad_request("unknown_joints", format!("names {}, {why}", quoted_name(n)))
        })?;
        out.push((node, 1.0));
    }
    out.sort_by_key(|n: &(u32, f32)| n.0);
    out.dedup_by_key(|n| n.0);
    Ok(Arc::from(out))
}

/// Clamps the final weights (400 `invalid_layer` for a clamp that is not `lo ≤ hi`, both
/// finite) and checks them (400 `invalid_layer` for a weight past ±[`MAX_LIVE_WEIGHT`]).
pub fn finish_weights(rig: &Rig, w: &mut [f32], clamp: Option<[f32; 2]>) -> Result<(), ApiError> {
    if let Some([lo, hi]) = clamp {
        if !(lo.is_finite() && hi.is_finite() && lo <= hi) {
            return Err(invalid(format!(
                "clamp is [{lo}, {hi}]; it must be two finite numbers, lo ≤ hi"
            )));
        }
        clamp_weights(w, [lo, hi]);
    }
    if let Some((k, v)) = w
        .iter()
        .enumerate()
        .find(|(_, v)| !(v.is_finite() && v.abs() <= MAX_LIVE_WEIGHT))
    {
        return Err(invalid(format!(
            "the layers give target {} a weight of {v}; a weight must be finite, within \
             ±{MAX_LIVE_WEIGHT}",
            quoted_name(&rig.targets[k])
        )));
    }
    Ok(())
}

/// Bytes [`layered_joints`] builds on skeleton `sk`, at most.
pub fn layered_joints_bytes(sk: &Skeleton) -> u64 {
    // Node arrays: rest, the locals, a blend's three and a layer's two; and the overrides (a
    // `JointSet` per node at most) with the copies their overlays make.
    7 * (16 + (sk.nodes.len() * size_of::<Trs>()) as u64)
        + 3 * (16 + (sk.nodes.len() * size_of::<crowdmorph_core::rig::JointSet>()) as u64)
}

/// The joint overrides of a layered head on a skinned rig: what `base`'s clip terms give each
/// node, with `base_joints` applied, then `layers`, as overrides of every node not at rest
/// (the head's final pose is live weights, which pose no joint). Additive layers may carry a
/// node past the translations and scales it has at rest or in any clip, which the rig's q16
/// box is sized for (and a request's own overrides may not leave): each node is brought back
/// within them. [`JointPose::NONE`] without a skeleton.
pub fn layered_joints(
    entry: &RigEntry,
    base: &Pose,
    base_joints: &JointPose,
    layers: &[PoseLayer],
) -> JointPose {
    let rig = entry.rig();
    let Some(sk) = &rig.skeleton else {
        return JointPose::NONE;
    };
    let mut rest = Vec::with_capacity(sk.nodes.len());
    sk.locals_at(None, 0, &mut rest);
    let mut locals = Vec::with_capacity(sk.nodes.len());
    sk.locals_of(&base.skin_terms(rig), &mut locals);
    base_joints.apply(sk, &mut locals);
    layer_locals(rig, sk, &mut locals, layers);
    let (t_max, s_max) = &entry.joint_lod().extents;
    for ((l, &t), &sc) in locals.iter_mut().zip(t_max).zip(s_max) {
        let v = glam::Vec3::from(l.translation);
        let len = f64::from(v.length());
        if len > t {
            l.translation = (v * (t / len) as f32).to_array();
        }
        l.scale = l.scale.map(|c| c.clamp(-(sc as f32), sc as f32));
    }
    JointPose::from_locals(&locals, &rest)
}
