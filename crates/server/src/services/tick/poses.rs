//! The tick's viewers that blend themselves (`"output": "weights"`): each head's final pose —
//! exactly what the tick resolved for it ([`super::HeadAt`]: its clip, graph, layers, live
//! input, clamps and joints) — sent as binary16 weights and moved joints, with the heads whose
//! pose did not change since the viewer's socket last took a message marked unchanged, as
//! vertex viewers' are. No engine work: a tick whose viewers all want poses submits no blend.
//! Heads that share rig, pose and joints (clones) share one pose, built once a tick for all
//! these viewers.

use std::collections::HashMap;
use std::sync::Arc;

use crowdmorph_core::rig::{JointPose, Pose};
use crowdmorph_proto::{
    FrameTimings, HEAD_MISSING, HEAD_UNCHANGED, HeadBuffer, HeadPose, MessageEncoding, SessionHead,
};

use super::{Resolved, Ticking, dropped_memory};
use crate::admission::poses::{head_pose, pose_bytes, scratch_bytes};
use crate::session_stream::poses::{PosesContent, encode_poses};
use crate::sessions::{
    Baseline, Encoded, HeadKey, MISSING_KEY, Outgoing, Session, Viewer, ViewerSettings, bump,
};

/// A poses message's identity within a tick: whether it carries the layout, each head's
/// entry, and its packing. The same key, the same bytes.
type MessageKey = (bool, Vec<u32>, Option<MessageEncoding>);

/// What every weights viewer's message of a tick is made of.
pub(super) struct TickPosesInput<'a> {
    pub(super) tick: u64,
    pub(super) heads: &'a [SessionHead],
    pub(super) layout_rev: u64,
    pub(super) resolved: &'a Resolved,
    pub(super) arrived: std::time::Instant,
}

/// The tick's unique poses: each head's pose (`None`: its rig or clip is gone), its key for
/// "unchanged", and each unique pose built when a message first needs it.
struct Poses<'a> {
    /// Per unique (rig, pose, joints): the rig, pose and joints.
    jobs: Vec<(u32, &'a Pose, &'a JointPose)>,
    /// Per head, its unique pose.
    head_job: Vec<Option<u32>>,
    /// Per head, what identifies its pose for "unchanged".
    keys: Arc<Vec<HeadKey>>,
    /// Per unique pose, built once.
    built: Vec<Option<HeadPose>>,
}

/// Sends this tick to every viewer in `viewers` (all asked for `"output": "weights"`). The
/// tick's poses and their messages are charged to the queue memory before they are built; a
/// viewer whose message does not fit is skipped this tick (counted as dropped).
pub(super) fn fan_out<S: Ticking>(
    state: &S,
    session: &Session,
    t: &TickPosesInput<'_>,
    viewers: &[(Arc<Viewer>, ViewerSettings)],
) {
    if viewers.is_empty() {
        return;
    }
    let rigs = &t.resolved.rigs;
    // The index and keys: per head a key and an entry, per unique pose an entry.
    let bookkeeping = t.heads.len() as u64 * (2 * size_of::<HeadKey>() as u64 + 64);
    let Ok(_index_memory) = state.queue_memory().reserve(bookkeeping) else {
        for _ in viewers {
            dropped_memory(state, session);
        }
        return;
    };
    let mut index: HashMap<(u32, &Pose, &JointPose), u32> = HashMap::new();
    let mut jobs = Vec::new();
    let mut keys = Vec::with_capacity(t.heads.len());
    let head_job: Vec<Option<u32>> = t
        .resolved
        .at
        .iter()
        .map(|a| {
            let Some(a) = a else {
                keys.push(MISSING_KEY);
                return None;
            };
            keys.push(HeadKey {
                generation: rigs[a.rig as usize].generation,
                pose: a.pose.clone(),
                lod: 0,
                joints: a.joints.clone(),
            });
            let n = jobs.len() as u32;
            let j = *index.entry((a.rig, &a.pose, &a.joints)).or_insert(n);
            if j == n {
                jobs.push((a.rig, &a.pose, &a.joints));
            }
            Some(j)
        })
        .collect();
    drop(index);
    // Every unique pose may be built (and kept for the tick's messages), with one posing
    // scratch.
    let poses_bytes = jobs
        .iter()
        .map(|(r, _, _)| pose_bytes(rigs[*r as usize].rig(), false))
        .sum::<u64>()
        + jobs
            .iter()
            .map(|(r, _, _)| scratch_bytes(rigs[*r as usize].rig()))
            .max()
            .unwrap_or(0);
    let Ok(_poses_memory) = state.queue_memory().reserve(poses_bytes) else {
        for _ in viewers {
            dropped_memory(state, session);
        }
        return;
    };
    let mut poses = Poses {
        built: vec![None; jobs.len()],
        jobs,
        head_job,
        keys: Arc::new(keys),
    };
    let mut messages: HashMap<MessageKey, Arc<Encoded>> = HashMap::new();
    let mut locals = Vec::new();
    for (viewer, settings) in viewers {
        deliver(
            state,
            session,
            t,
            &mut poses,
            (viewer, settings),
            &mut messages,
            &mut locals,
        );
    }
}

/// Puts one viewer's message in its outbox: its entries relative to what its socket last
/// took, planned again if the socket took a message meanwhile ("unchanged" must refer to what
/// it received).
fn deliver<'a, S: Ticking>(
    state: &S,
    session: &Session,
    t: &TickPosesInput<'a>,
    poses: &mut Poses<'a>,
    (viewer, settings): (&Arc<Viewer>, &ViewerSettings),
    messages: &mut HashMap<MessageKey, Arc<Encoded>>,
    locals: &mut Vec<crowdmorph_core::rig::Trs>,
) {
    for _attempt in 0..4 {
        let Some(base) = viewer.outbox.lock().ok().map(|o| o.sent.clone()) else {
            return;
        };
        let keys = &poses.keys;
        let with_layout = base.layout_rev != t.layout_rev || base.keys.len() != keys.len();
        let entries: Vec<u32> = poses
            .head_job
            .iter()
            .enumerate()
            .map(|(i, j)| match j {
                _ if !with_layout && base.keys[i] == keys[i] => HEAD_UNCHANGED,
                None => HEAD_MISSING,
                Some(j) => *j,
            })
            .collect();
        let key = (with_layout, entries, settings.compression);
        let message = match messages.get(&key) {
            Some(m) => m.clone(),
            None => {
                let Some(m) = encode(state, t, poses, &key.1, with_layout, key.2, locals) else {
                    return dropped_memory(state, session);
                };
                let m = Arc::new(m);
                messages.insert(key, m.clone());
                m
            }
        };
        let Ok(mut o) = viewer.outbox.lock() else {
            return;
        };
        if o.sent.version != base.version {
            continue;
        }
        if o.pending.is_some() {
            bump(&state.sessions().metrics.dropped_slow, 1);
            session.with_stats(|s| s.messages_dropped += 1);
        }
        o.pending = Some(Outgoing {
            layers: None,
            message,
            after: Baseline {
                version: base.version + 1,
                layout_rev: t.layout_rev,
                keys: poses.keys.clone(),
                prev: base.prev.clone(),
                layers: base.layers.clone(),
            },
        });
        drop(o);
        viewer.ready.notify_one();
        return;
    }
}

/// Encodes the message of `entries` (a unique pose per changed head, in order of first
/// appearance), building the poses it needs that no message needed before. `None`: out of
/// queue memory.
fn encode<'a, S: Ticking>(
    state: &S,
    t: &TickPosesInput<'a>,
    poses: &mut Poses<'a>,
    entries: &[u32],
    with_layout: bool,
    compression: Option<MessageEncoding>,
    locals: &mut Vec<crowdmorph_core::rig::Trs>,
) -> Option<Encoded> {
    let rigs = &t.resolved.rigs;
    let mut local: HashMap<u32, u32> = HashMap::new();
    let mut order: Vec<u32> = Vec::new();
    let heads: Vec<HeadBuffer> = t
        .heads
        .iter()
        .zip(entries)
        .map(|(h, &e)| {
            let buffer = if e == HEAD_UNCHANGED || e == HEAD_MISSING {
                e
            } else {
                *local.entry(e).or_insert_with(|| {
                    order.push(e);
                    (order.len() - 1) as u32
                })
            };
            HeadBuffer {
                head: h.head,
                buffer,
            }
        })
        .collect();
    for &j in &order {
        let slot = &mut poses.built[j as usize];
        if slot.is_none() {
            let (r, pose, joints) = poses.jobs[j as usize];
            *slot = Some(head_pose(rigs[r as usize].rig(), pose, joints, locals));
        }
    }
    let carried: Vec<&HeadPose> = order
        .iter()
        .filter_map(|&j| poses.built[j as usize].as_ref())
        .collect();
    let content = PosesContent {
        tick: t.tick,
        layout: with_layout.then_some(t.heads),
        poses: &carried,
        heads: &heads,
        timings: FrameTimings {
            queue_us: 0,
            compute_us: 0,
            total_us: t.arrived.elapsed().as_micros() as u64,
            gpu_us: None,
        },
    };
    encode_poses(state.queue_memory(), &content, compression)
}
