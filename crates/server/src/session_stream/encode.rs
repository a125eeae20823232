//! A viewer's vertex message encoded: a [`crowdmorph_proto::TickVertices`] or, for a
//! temporal viewer, a [`crowdmorph_proto::TickDelta`] of residuals planned by
//! [`super::delta`], and a layers viewer's [`crowdmorph_proto::TickLayers`], optionally
//! packed; every byte charged to the queue memory before it is allocated. The tick (`crate::services::tick`) decides what each viewer gets; this
//! module only writes it, given the queue memory and nothing else of the server.

use std::collections::HashMap;
use std::sync::Arc;

use bytes::Bytes;
use crowdmorph_core::rig::{JointPose, Pose};
use crowdmorph_proto::{
    Format, FrameTimings, HEAD_MISSING, HEAD_UNCHANGED, HeadBuffer, MessageEncoding, SessionHead,
};
use crowdmorph_store::codec::{FrameBufferParts, FrameResponseEncoder};
use rayon::prelude::*;

use super::delta;
use crate::admission::memory::QueueMemory;
use crate::registry::RigEntry;
use crate::sessions::{Encoded, Retained};

/// A job of a tick's group: rig (index into the tick's rigs), pose, LOD level, joint overrides
/// at that level.
pub(crate) type JobKey = (u32, Pose, u32, JointPose);

/// What a viewer's vertex message is made of.
pub(crate) struct MessageContent<'a> {
    /// The tick.
    pub(crate) tick: u64,
    /// The layout, when the message carries it.
    pub(crate) layout: Option<&'a [SessionHead]>,
    /// The jobs of the viewer's group, by index, as `(rig, pose, LOD, joints)`.
    pub(crate) keys: &'a [JobKey],
    /// The group's buffer format.
    pub(crate) format: Format,
    /// Whether the group's buffers carry normals.
    pub(crate) normals: bool,
    /// The group's batch.
    pub(crate) outcome: &'a crate::scheduler::Outcome,
    /// The rigs the keys name.
    pub(crate) rigs: &'a [Arc<RigEntry>],
    /// The session's heads.
    pub(crate) heads: &'a [SessionHead],
    /// Each head's entry: a job of the group, `HEAD_UNCHANGED` or `HEAD_MISSING`.
    pub(crate) entries: &'a [u32],
    /// When the tick started.
    pub(crate) arrived: std::time::Instant,
}

impl MessageContent<'_> {
    fn timings(&self) -> FrameTimings {
        FrameTimings {
            queue_us: self.outcome.queue.as_micros() as u64,
            compute_us: self.outcome.compute_ns / 1000,
            total_us: self.arrived.elapsed().as_micros() as u64,
            gpu_us: self.outcome.gpu_ns.map(|g| g / 1000),
        }
    }

    /// A buffer's parts for job `e` of the group, with these payloads.
    fn part(&self, e: u32, positions: Bytes, normals: Option<Bytes>) -> FrameBufferParts<'_> {
        let (r, pose, l, _) = &self.keys[e as usize];
        let entry = &self.rigs[*r as usize];
        let (clip, frame) = entry.shown(pose);
        FrameBufferParts {
            rig: &entry.id,
            clip,
            frame,
            lod: *l,
            vertices: entry.prepared.at_level(*l).rig().vertex_count() as u32,
            quantization: self.format.quantized().then_some(entry.qbox),
            positions,
            normals: if self.normals { normals } else { None },
        }
    }
}

/// The buffers of a viewer's message (in order of first appearance among the heads) and each
/// head's entry: a buffer index, or `HEAD_UNCHANGED` / `HEAD_MISSING`.
fn message_buffers<'a>(c: &'a MessageContent<'a>) -> (Vec<FrameBufferParts<'a>>, Vec<HeadBuffer>) {
    let mut local: HashMap<u32, u32> = HashMap::new();
    let mut parts: Vec<FrameBufferParts<'a>> = Vec::new();
    let head_buffers: Vec<HeadBuffer> = c
        .heads
        .iter()
        .zip(c.entries)
        .map(|(h, &e)| {
            let buffer = if e == HEAD_UNCHANGED || e == HEAD_MISSING {
                e
            } else {
                *local.entry(e).or_insert_with(|| {
                    let out = &c.outcome.outputs[e as usize];
                    parts.push(c.part(e, out.positions.clone(), out.normals.clone()));
                    (parts.len() - 1) as u32
                })
            };
            HeadBuffer {
                head: h.head,
                buffer,
            }
        })
        .collect();
    (parts, head_buffers)
}

/// Encodes a [`crowdmorph_proto::TickVertices`] stream message: the variant, the tick and the
/// layout, then the same fields as a crowd-frame response, with payloads aligned to 16 bytes
/// from the start of the message. Its length is computed first and charged to the queue
/// memory before anything of its size is allocated; `None` when the queue memory is full.
pub(crate) fn encode_vertices(
    memory: &QueueMemory,
    c: &MessageContent<'_>,
    compression: Option<MessageEncoding>,
) -> Option<Encoded> {
    let (parts, head_buffers) = message_buffers(c);
    encode_message(memory, c, 0, &[], &parts, &head_buffers, compression)
}

/// Encodes a [`crowdmorph_proto::TickDelta`]: as [`encode_vertices`], with each buffer a
/// keyframe or residual planes against the head's reference, and a flag per buffer. Heads
/// share a buffer when they share the job and the reference. The residuals are charged before
/// they are computed.
pub(crate) fn encode_delta(
    memory: &QueueMemory,
    c: &MessageContent<'_>,
    plan: &delta::DeltaPlan,
    compression: Option<MessageEncoding>,
) -> Option<Encoded> {
    let residual_bytes: u64 = (0..c.entries.len())
        .filter_map(|i| Some((plan.refs[i].as_ref()?, plan.cur[i].as_ref()?)))
        .map(|(_, cur)| (cur.positions.len() + cur.normals.as_ref().map_or(0, |n| n.len())) as u64)
        .sum();
    let _residual_memory = memory.reserve(residual_bytes).ok()?;
    // Each distinct (job, reference) is one buffer: numbered in order of first appearance,
    // then coded on every core (the residual planes are the viewer's per-head work).
    let mut local: HashMap<(u32, usize), u32> = HashMap::new();
    let mut todo: Vec<(u32, &Retained, Option<&Retained>)> = Vec::new();
    let mut head_buffers = Vec::with_capacity(c.heads.len());
    for (i, (h, &e)) in c.heads.iter().zip(c.entries).enumerate() {
        let buffer = match (e, &plan.cur[i]) {
            (HEAD_UNCHANGED | HEAD_MISSING, _) | (_, None) => e,
            (e, Some(cur)) => *local.entry((e, plan.bases[i])).or_insert_with(|| {
                todo.push((e, cur, plan.refs[i].as_deref()));
                (todo.len() - 1) as u32
            }),
        };
        head_buffers.push(HeadBuffer {
            head: h.head,
            buffer,
        });
    }
    let payloads: Vec<(Bytes, Option<Bytes>)> = todo
        .par_iter()
        .map(|&(_, cur, reference)| match reference {
            None => (cur.positions.clone(), cur.normals.clone()),
            Some(r) => {
                let p = crowdmorph_proto::q16r_encode_le(&cur.positions, &r.positions);
                let n = cur.normals.as_ref().zip(r.normals.as_ref());
                let n = n.map(|(n, rn)| Bytes::from(crowdmorph_proto::q16r_encode_le(n, rn)));
                (Bytes::from(p), n)
            }
        })
        .collect();
    let residual: Vec<bool> = todo.iter().map(|t| t.2.is_some()).collect();
    let parts: Vec<FrameBufferParts<'_>> = todo
        .iter()
        .zip(payloads)
        .map(|(&(e, _, _), (p, n))| c.part(e, p, n))
        .collect();
    let residual_len = crowdmorph_store::codec::wire_len(&residual).unwrap_or(0);
    let residual = crowdmorph_store::codec::to_wire(&residual).ok()?;
    debug_assert_eq!(residual.len(), residual_len);
    encode_message(memory, c, 2, &residual, &parts, &head_buffers, compression)
}

/// The variant, the tick, the format and normals, the layout, `after_layout` (more encoded
/// fields), then buffers, heads and timings; charged before it is allocated. With
/// `compression`, the pieces go through the compressor as they are encoded, into a
/// `StreamMessage::Packed` ([`delta::pack`]): the whole message is never written out.
fn encode_message(
    memory: &QueueMemory,
    c: &MessageContent<'_>,
    variant: u64,
    after_layout: &[u8],
    parts: &[FrameBufferParts<'_>],
    head_buffers: &[HeadBuffer],
    compression: Option<MessageEncoding>,
) -> Option<Encoded> {
    let mut prefix = Vec::with_capacity(64);
    crowdmorph_store::codec::put_varint(&mut prefix, variant);
    crowdmorph_store::codec::put_varint(&mut prefix, c.tick);
    let timings = c.timings();
    // The layout's length (bincode, without encoding it; `None` is one byte), then the
    // message's: charged before either is allocated.
    let middle_len = crowdmorph_store::codec::wire_len(&c.layout).unwrap_or(1) + after_layout.len();
    let total = FrameResponseEncoder::encoded_len_within(
        prefix.len(),
        middle_len,
        c.format,
        c.normals,
        parts,
        head_buffers,
        &timings,
    );
    // Packed, the message's bytes only pass through the compressor, which `pack` charges.
    let unpacked = if compression.is_some() { 0 } else { total };
    let charge = memory.reserve((unpacked + middle_len) as u64).ok()?;
    let mut middle = crowdmorph_store::codec::to_wire(&c.layout).unwrap_or_else(|_| vec![0]);
    middle.extend_from_slice(after_layout);
    let chunks = FrameResponseEncoder::encode_within(
        prefix,
        &middle,
        c.format,
        c.normals,
        parts,
        head_buffers,
        &timings,
    );
    drop(middle);
    if let Some(e) = compression {
        let packed = delta::pack(memory, &chunks, total, e);
        drop(chunks);
        drop(charge);
        return packed;
    }
    let mut out = Vec::with_capacity(total);
    for c in &chunks {
        out.extend_from_slice(c);
    }
    debug_assert_eq!(out.len(), total, "the counted length is the encoding's");
    drop(chunks);
    let mut charge = charge;
    // The layout's encoding and the chunks are gone; the message keeps only its bytes.
    charge.keep(total as u64);
    Some(Encoded {
        bytes: Bytes::from(out),
        _memory: Box::new(charge),
    })
}

/// Encodes a [`crowdmorph_proto::TickLayers`] (`StreamMessage` variant 4) of `heads`' compact
/// layer inputs, written field by field (the bincode of the type: `tests/server/sessions.rs`
/// decodes it), optionally packed. Its bound is charged to the queue memory before it is
/// allocated; `None` when the queue memory is full.
pub(crate) fn encode_layers(
    memory: &QueueMemory,
    tick: u64,
    heads: &[(u64, Arc<[f32]>)],
    compression: Option<MessageEncoding>,
) -> Option<Encoded> {
    // A varint is at most 9 bytes: the variant, the tick and the count, then per head its id,
    // its length and its floats.
    let bound = 27 + heads.iter().map(|(_, v)| 18 + 4 * v.len()).sum::<usize>();
    let mut charge = memory.reserve(bound as u64).ok()?;
    let mut out = Vec::with_capacity(bound);
    let put = crowdmorph_store::codec::put_varint;
    put(&mut out, 4);
    put(&mut out, tick);
    put(&mut out, heads.len() as u64);
    for (head, inputs) in heads {
        put(&mut out, *head);
        put(&mut out, inputs.len() as u64);
        for v in inputs.iter() {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    if let Some(e) = compression {
        let len = out.len();
        let packed = delta::pack(memory, &[Bytes::from(out)], len, e);
        drop(charge);
        return packed;
    }
    charge.keep(out.len() as u64);
    Some(Encoded {
        bytes: Bytes::from(out),
        _memory: Box::new(charge),
    })
}
