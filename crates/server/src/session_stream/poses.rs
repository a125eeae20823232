//! A weights viewer's message encoded: a [`crowdmorph_proto::TickPoses`] (`StreamMessage`
//! variant 5) of the poses its heads changed to, optionally packed; its length counted and
//! charged to the queue memory before it is allocated. The tick decides which heads changed
//! (`crate::services::tick`); this module only writes the message.

use bytes::Bytes;
use crowdmorph_proto::{FrameTimings, HeadBuffer, HeadPose, MessageEncoding, SessionHead};
use serde::Serialize;

use super::delta;
use crate::admission::memory::QueueMemory;
use crate::sessions::Encoded;

/// [`crowdmorph_proto::TickPoses`] by reference: the same fields in the same order, so the
/// same bincode (a slice of `&HeadPose` encodes as a `Vec<HeadPose>`), without copying the
/// layout or the poses first.
#[derive(Serialize)]
struct TickPosesRef<'a> {
    tick: u64,
    layout: Option<&'a [SessionHead]>,
    poses: &'a [&'a HeadPose],
    heads: &'a [HeadBuffer],
    timings: FrameTimings,
}

/// The variant index of `StreamMessage::Poses`, a one-byte varint.
const VARIANT: u8 = 5;

/// What one viewer's poses message holds.
pub(crate) struct PosesContent<'a> {
    /// The tick.
    pub(crate) tick: u64,
    /// The layout, when the message carries it.
    pub(crate) layout: Option<&'a [SessionHead]>,
    /// The poses it carries, numbered as `heads` name them.
    pub(crate) poses: &'a [&'a HeadPose],
    /// One entry per layout head.
    pub(crate) heads: &'a [HeadBuffer],
    /// The tick's timings.
    pub(crate) timings: FrameTimings,
}

/// Encodes a `StreamMessage::Poses`, packed with `compression` if asked; `None` when the
/// queue memory cannot hold it.
pub(crate) fn encode_poses(
    memory: &QueueMemory,
    c: &PosesContent<'_>,
    compression: Option<MessageEncoding>,
) -> Option<Encoded> {
    let message = TickPosesRef {
        tick: c.tick,
        layout: c.layout,
        poses: c.poses,
        heads: c.heads,
        timings: c.timings,
    };
    let len = 1 + crowdmorph_store::codec::wire_len(&message).ok()?;
    // The message, and the encoding it is copied from.
    let mut charge = memory.reserve(2 * len as u64).ok()?;
    let mut out = Vec::with_capacity(len);
    out.push(VARIANT);
    out.extend_from_slice(&crowdmorph_store::codec::to_wire(&message).ok()?);
    if let Some(e) = compression {
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
