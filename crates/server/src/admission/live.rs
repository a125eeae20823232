//! Live input checked against a head's rig (issue 47): a session head's [`LiveSpec`] when it
//! is added or changed, and each producer sample (`POST /v1/sessions/{id}/live`, the live
//! WebSocket) resolved into the sparse [`LiveValues`] the tick plays: weights by channel
//! (matched as a crowd frame's live weights are), Live Link Face's head and eye angles by the
//! rig's joint-map column, node rotations by node. Errors are the 4xx a producer gets.

use std::collections::HashSet;

use crowdmorph_anim::live::LiveValues;
use crowdmorph_core::rig::{ARKIT_NAMES, MAX_LIVE_WEIGHT, quoted_name};
use crowdmorph_import::clips::{checked_name, is_live_link_angle, loose};
use crowdmorph_proto::{LiveSample, LiveSpec, LiveWeights};

use crate::admission::names::{LiveNames, is_arkit_name};
use crate::http::ApiError;
use crate::registry::RigEntry;

/// Longest hold, fade and delay a live head may ask for, milliseconds.
pub const MAX_HOLD_MS: u32 = 60_000;
/// Longest fade, milliseconds.
pub const MAX_FADE_MS: u32 = 10_000;
/// Longest delay behind the producer's clock, milliseconds.
pub const MAX_DELAY_MS: u32 = 5_000;

fn invalid(message: String) -> ApiError {
    ApiError::bad_request("invalid_live", message)
}

/// A head's live settings: durations within their limits, filter parameters finite and
/// positive.
pub fn check_spec(spec: &LiveSpec) -> Result<(), ApiError> {
    for (what, v, max) in [
        ("hold_ms", spec.hold_ms, MAX_HOLD_MS),
        ("fade_ms", spec.fade_ms, MAX_FADE_MS),
        ("delay_ms", spec.delay_ms, MAX_DELAY_MS),
    ] {
        if v > max {
            return Err(invalid(format!("live.{what} is {v}; at most {max}")));
        }
    }
    if let Some(s) = &spec.smoothing {
        let ok = |v: f32| v.is_finite() && v > 0.0 && v <= 1e4;
        if !(ok(s.min_cutoff)
            && ok(s.d_cutoff)
            && s.beta.is_finite()
            && (0.0..=1e4).contains(&s.beta))
        {
            return Err(invalid(format!(
                "live.smoothing {s:?}: cutoffs must be in (0, 10000] Hz and beta in [0, 10000]"
            )));
        }
    }
    Ok(())
}

/// Bytes [`resolve_sample`] builds for `sample`, at most: per weight a channel list entry
/// for every channel of its name (a name may drive several), an angle or a rotation, with the
/// check's set of seen channels.
pub fn sample_bytes(rig_channels: usize, sample: &LiveSample) -> u64 {
    let n = sample.weights.as_ref().map_or(0, LiveWeights::len) as u64;
    let j = sample.joints.0.len() as u64;
    // Weights: at most every channel once (each name's channels are unique), plus the seen
    // set; angles and rotations one entry each.
    let channels = (rig_channels as u64).max(n);
    64 + channels * (8 + 16) + n * 8 + j * 24
}

/// `sample` resolved against `entry`'s rig: its weights by channel (names matched as a crowd
/// frame's live weights are: exactly, else by their loose spelling; ARKit and Live Link names
/// the rig lacks are skipped, others are 400 `unknown_targets`), its angles by joint-map
/// column, its joints' rotations by node (400 `unknown_joints`; live joints carry rotations
/// only). Values must be finite, weights within ±[`MAX_LIVE_WEIGHT`]. The caller charges
/// [`sample_bytes`] first.
pub(crate) fn resolve_sample(
    entry: &RigEntry,
    names: &LiveNames,
    sample: &LiveSample,
) -> Result<LiveValues, ApiError> {
    let rig = entry.rig();
    let at = |m: String| invalid(format!("head {}: {m}", sample.head));
    let weight = |what: &dyn std::fmt::Display, w: f32| {
        if w.is_finite() && w.abs() <= MAX_LIVE_WEIGHT {
            Ok(())
        } else {
            Err(at(format!(
                "weights[{what}] is {w}; a weight must be finite, within ±{MAX_LIVE_WEIGHT}"
            )))
        }
    };
    if let Some(t) = sample.t
        && !t.is_finite()
    {
        return Err(at(format!(
            "t is {t}; a timecode is a finite number of seconds"
        )));
    }
    let mut out = LiveValues::default();
    match &sample.weights {
        None => {}
        Some(LiveWeights::Dense(w)) => {
            if w.len() != names.by_position.len() {
                return Err(at(format!(
                    "{} dense weights for rig {:?}, which has {} targets (RigInfo.targets)",
                    w.len(),
                    entry.id,
                    names.by_position.len()
                )));
            }
            for (i, (&w, ids)) in w.iter().zip(&names.by_position).enumerate() {
                weight(&i, w)?;
                out.weights.extend(ids.iter().map(|&id| (id, w)));
            }
        }
        Some(LiveWeights::Named(pairs)) => {
            // Each target once, plus ARKit's and Live Link's names the rig may lack.
            if pairs.len() > names.by_position.len() + ARKIT_NAMES.len() + 16 {
                return Err(at(format!(
                    "{} named weights for rig {:?}, which has {} targets",
                    pairs.len(),
                    entry.id,
                    names.by_position.len()
                )));
            }
            let angles = entry.live_angles();
            let mut seen = HashSet::with_capacity(pairs.len());
            for (name, w) in pairs {
                weight(&quoted_name(name), *w)?;
                checked_name(name)
                    .map_err(|why| at(format!("weights[{}]: {why}", quoted_name(name))))?;
                let ids = names.ids(name);
                if ids.is_empty() {
                    if let Some(&c) = angles.as_deref().and_then(|a| a.columns.get(&loose(name))) {
                        if out.angles.iter().any(|a| a.0 == c as u32) {
                            return Err(at(format!("weights name {} twice", quoted_name(name))));
                        }
                        out.angles.push((c as u32, *w));
                        continue;
                    }
                    if is_arkit_name(name) || is_live_link_angle(name) {
                        // A tracker sends all 52 (and Live Link its angles) every frame; this
                        // rig cannot show this one.
                        continue;
                    }
                    return Err(ApiError::bad_request(
                        "unknown_targets",
                        format!(
                            "head {}: weights name {}, which rig {:?} does not have (GET /v1/rigs/{} lists its targets)",
                            sample.head,
                            quoted_name(name),
                            entry.id,
                            entry.id
                        ),
                    ));
                }
                if !seen.insert(ids[0]) {
                    return Err(at(format!(
                        "weights name the target of {} twice",
                        quoted_name(name)
                    )));
                }
                out.weights.extend(ids.iter().map(|&id| (id, *w)));
            }
        }
    }
    if !sample.joints.0.is_empty() {
        let Some(sk) = &rig.skeleton else {
            return Err(ApiError::bad_request(
                "unknown_joints",
                format!(
                    "head {}: rig {:?} has no skeleton; live joints need one",
                    sample.head, entry.id
                ),
            ));
        };
        if sample.joints.0.len() > sk.nodes.len() {
            return Err(at(format!(
                "{} joints; the rig has {} nodes",
                sample.joints.0.len(),
                sk.nodes.len()
            )));
        }
        for (name, t) in &sample.joints.0 {
            let node = sk
                .nodes
                .iter()
                .position(|n| n.name == *name)
                .ok_or_else(|| {
                    ApiError::bad_request(
                        "unknown_joints",
                        format!(
                            "head {}: rig {:?} has no node {} (GET /v1/rigs/{}/joints lists them)",
                            sample.head,
                            entry.id,
                            quoted_name(name),
                            entry.id
                        ),
                    )
                })?;
            if t.translation.is_some() || t.scale.is_some() {
                return Err(at(format!(
                    "joints[{}]: live joints carry rotations only",
                    quoted_name(name)
                )));
            }
            let Some(r) = t.rotation else {
                return Err(at(format!("joints[{}] has no rotation", quoted_name(name))));
            };
            let q = glam::Quat::from_array(r);
            if !q.is_finite() || q.length() < 1e-3 {
                return Err(at(format!(
                    "joints[{}].rotation {r:?} is not a rotation (finite, length near 1)",
                    quoted_name(name)
                )));
            }
            if out.rotations.iter().any(|r| r.0 == node as u32) {
                return Err(at(format!("joints name {} twice", quoted_name(name))));
            }
            out.rotations.push((node as u32, q.normalize().to_array()));
        }
    }
    out.weights.sort_unstable_by_key(|e| e.0);
    out.weights.dedup_by_key(|e| e.0);
    out.angles.sort_unstable_by_key(|e| e.0);
    out.rotations.sort_unstable_by_key(|e| e.0);
    Ok(out)
}

/// Bytes [`live_joints`] builds on a rig of `nodes` skeleton nodes: three arrays of local
/// transforms and the overrides made of them.
pub fn live_joints_bytes(nodes: usize) -> u64 {
    3 * (16 + (nodes * size_of::<crowdmorph_core::rig::Trs>()) as u64)
        + 2 * (16 + (nodes * size_of::<crowdmorph_core::rig::JointSet>()) as u64)
}

/// A live head's joints: `below` (overrides of every node not at rest, as a layered head's
/// are) with `values`' angles (through the rig's joint map) and rotations taken `alpha` of
/// the way (slerp), as overrides of every node not at rest. `below` itself on a rig without
/// a skeleton or for values that turn no joint.
pub fn live_joints(
    entry: &RigEntry,
    below: &crowdmorph_core::rig::JointPose,
    values: &LiveValues,
    alpha: f32,
) -> crowdmorph_core::rig::JointPose {
    let rig = entry.rig();
    let Some(sk) = &rig.skeleton else {
        return below.clone();
    };
    if values.angles.is_empty() && values.rotations.is_empty() {
        return below.clone();
    }
    let mut rest = Vec::with_capacity(sk.nodes.len());
    sk.locals_at(None, 0, &mut rest);
    let mut locals = rest.clone();
    below.apply(sk, &mut locals);
    let mut with = locals.clone();
    if !values.angles.is_empty()
        && let Some(a) = entry.live_angles()
    {
        let angles: Vec<(usize, f32)> = values
            .angles
            .iter()
            .map(|&(c, v)| (c as usize, v))
            .collect();
        a.joints(rig, &angles).apply(sk, &mut with);
    }
    for &(n, r) in &values.rotations {
        if let Some(l) = with.get_mut(n as usize) {
            l.rotation = r;
        }
    }
    for (l, w) in locals.iter_mut().zip(&with) {
        if l != w {
            *l = crowdmorph_core::rig::blend_trs(l, w, alpha);
        }
    }
    crowdmorph_core::rig::JointPose::from_locals(&locals, &rest)
}
