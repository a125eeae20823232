//! A session viewer's side of the stream: [`StreamState`] applies each binary message in order
//! and keeps what the viewer draws, the layout and every head's last buffer, so that
//! "unchanged" entries and temporal residuals ([`TickDelta`]) resolve to plain buffers.
//!
//! With the `unpack` feature, [`StreamState::receive`] also takes compressed messages
//! ([`PackedMessage`](crate::session::PackedMessage), zstd or zlib) straight from the socket.

use std::collections::HashMap;
use std::sync::Arc;

#[cfg(feature = "unpack")]
use crate::session::PackedMessage;
use crate::session::TickDelta;
use crate::{
    Blob, Format, FrameBuffer, HEAD_MISSING, HEAD_UNCHANGED, HeadBuffer, HeadPose, SessionHead,
    StreamMessage, TickFrame, TickPoses, TickVertices, q16r_decode,
};

/// Why a message could not be applied.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StreamError(pub String);

impl std::fmt::Display for StreamError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for StreamError {}

fn err<T>(s: impl Into<String>) -> Result<T, StreamError> {
    Err(StreamError(s.into()))
}

/// What one vertex message changed.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Applied {
    /// Its tick.
    pub tick: u64,
    /// Heads that got a new buffer.
    pub changed: usize,
    /// Of those, heads decoded from residuals against their previous buffer.
    pub from_residuals: usize,
    /// Buffers the message carried.
    pub buffers: usize,
}

/// What a message was.
#[derive(Debug, Clone, PartialEq)]
pub enum Received {
    /// Vertex buffers, applied.
    Vertices(Applied),
    /// An image.
    Frame(TickFrame),
    /// Expression-layer inputs ([`crate::TickLayers`]), kept per head: this many heads got new
    /// ones ([`StreamState::layer_inputs`]).
    Layers(usize),
    /// Poses ([`crate::TickPoses`]), applied: `buffers` counts the poses the message carried
    /// ([`StreamState::pose`]).
    Poses(Applied),
}

/// The viewer's picture of the session: the layout and each head's buffer, decoded.
#[derive(Debug, Default, Clone)]
pub struct StreamState {
    tick: u64,
    layout: Vec<SessionHead>,
    heads: HashMap<u64, Arc<FrameBuffer>>,
    layers: HashMap<u64, Vec<f32>>,
    poses: HashMap<u64, Arc<HeadPose>>,
}

impl StreamState {
    /// Nothing received yet.
    pub fn new() -> StreamState {
        StreamState::default()
    }

    /// The last tick applied (0 before the first).
    pub fn tick(&self) -> u64 {
        self.tick
    }

    /// The session's heads as last sent.
    pub fn layout(&self) -> &[SessionHead] {
        &self.layout
    }

    /// The buffer a head draws now (positions and normals in the message's format, temporal
    /// residuals already resolved), or `None` when it has nothing to draw.
    pub fn buffer(&self, head: u64) -> Option<&FrameBuffer> {
        self.heads.get(&head).map(|b| &**b)
    }

    /// The pose a head shows now (variant 5: its weights and moved joints, "unchanged"
    /// already resolved), or `None` when it has none.
    pub fn pose(&self, head: u64) -> Option<&HeadPose> {
        self.poses.get(&head).map(|p| &**p)
    }

    /// A head's expression-layer inputs as last sent (variant 4), or `None` when none came.
    pub fn layer_inputs(&self, head: u64) -> Option<&[f32]> {
        self.layers.get(&head).map(Vec::as_slice)
    }

    /// Applies a decoded message. A message that does not fit what came before (an
    /// "unchanged" or residual head never received, a residual of the wrong length) is an
    /// error and leaves the state as it was.
    pub fn apply(&mut self, message: StreamMessage) -> Result<Received, StreamError> {
        match message {
            StreamMessage::Frame(f) => {
                self.tick = f.tick;
                Ok(Received::Frame(f))
            }
            StreamMessage::Vertices(v) => {
                let TickVertices {
                    tick,
                    layout,
                    buffers,
                    heads,
                    ..
                } = v;
                let residual = vec![false; buffers.len()];
                self.update(tick, layout, &residual, buffers, &heads)
                    .map(Received::Vertices)
            }
            StreamMessage::Delta(d) => {
                let TickDelta {
                    tick,
                    format,
                    layout,
                    residual,
                    buffers,
                    heads,
                    ..
                } = d;
                if format != Format::Q16 {
                    return err(format!("a temporal message in {}, not q16", format.name()));
                }
                if residual.len() != buffers.len() {
                    return err(format!(
                        "{} residual flags for {} buffers",
                        residual.len(),
                        buffers.len()
                    ));
                }
                self.update(tick, layout, &residual, buffers, &heads)
                    .map(Received::Vertices)
            }
            StreamMessage::Packed(_) => {
                err("a packed message: decompress it first (StreamState::receive)")
            }
            StreamMessage::Layers(l) => {
                let n = l.heads.len();
                for h in l.heads {
                    self.layers.insert(h.head, h.inputs);
                }
                Ok(Received::Layers(n))
            }
            StreamMessage::Poses(p) => self.update_poses(p).map(Received::Poses),
        }
    }

    /// Applies a [`TickPoses`]: each head's pose, "unchanged" resolved to the one it had.
    fn update_poses(&mut self, p: TickPoses) -> Result<Applied, StreamError> {
        let TickPoses {
            tick,
            layout,
            poses,
            heads,
            ..
        } = p;
        let layout = layout.unwrap_or_else(|| self.layout.clone());
        if heads.len() != layout.len() {
            return err(format!(
                "{} head entries for a layout of {}",
                heads.len(),
                layout.len()
            ));
        }
        let poses: Vec<Arc<HeadPose>> = poses.into_iter().map(Arc::new).collect();
        let mut next = HashMap::with_capacity(layout.len());
        let mut applied = Applied {
            tick,
            buffers: poses.len(),
            ..Applied::default()
        };
        for (h, e) in layout.iter().zip(&heads) {
            if h.head != e.head {
                return err(format!(
                    "entry for head {} where the layout has {}",
                    e.head, h.head
                ));
            }
            let pose = match e.buffer {
                HEAD_MISSING => continue,
                HEAD_UNCHANGED => match self.poses.get(&e.head) {
                    Some(p) => p.clone(),
                    None => return err(format!("head {} unchanged but never received", e.head)),
                },
                i => match poses.get(i as usize) {
                    Some(p) => {
                        applied.changed += 1;
                        p.clone()
                    }
                    None => {
                        return err(format!("head {} names pose {i} of {}", e.head, poses.len()));
                    }
                },
            };
            next.insert(e.head, pose);
        }
        self.tick = tick;
        self.layout = layout;
        self.poses = next;
        Ok(applied)
    }

    fn update(
        &mut self,
        tick: u64,
        layout: Option<Vec<SessionHead>>,
        residual: &[bool],
        buffers: Vec<FrameBuffer>,
        heads: &[HeadBuffer],
    ) -> Result<Applied, StreamError> {
        let layout = layout.unwrap_or_else(|| self.layout.clone());
        if heads.len() != layout.len() {
            return err(format!(
                "{} head entries for a layout of {}",
                heads.len(),
                layout.len()
            ));
        }
        let buffers: Vec<Arc<FrameBuffer>> = buffers.into_iter().map(Arc::new).collect();
        let mut next = HashMap::with_capacity(layout.len());
        let mut applied = Applied {
            tick,
            buffers: buffers.len(),
            ..Applied::default()
        };
        for (h, e) in layout.iter().zip(heads) {
            if h.head != e.head {
                return err(format!(
                    "entry for head {} where the layout has {}",
                    e.head, h.head
                ));
            }
            let buffer = match e.buffer {
                HEAD_MISSING => continue,
                HEAD_UNCHANGED => match self.heads.get(&e.head) {
                    Some(b) => b.clone(),
                    None => return err(format!("head {} unchanged but never received", e.head)),
                },
                i => {
                    let Some(b) = buffers.get(i as usize) else {
                        return err(format!(
                            "head {} names buffer {i} of {}",
                            e.head,
                            buffers.len()
                        ));
                    };
                    applied.changed += 1;
                    if residual[i as usize] {
                        let Some(prev) = self.heads.get(&e.head) else {
                            return err(format!(
                                "head {} has residuals but no earlier buffer",
                                e.head
                            ));
                        };
                        applied.from_residuals += 1;
                        Arc::new(
                            resolve(b, prev)
                                .map_err(|m| StreamError(format!("head {}: {m}", e.head)))?,
                        )
                    } else {
                        b.clone()
                    }
                }
            };
            next.insert(e.head, buffer);
        }
        self.tick = tick;
        self.layout = layout;
        self.heads = next;
        Ok(applied)
    }

    /// Decodes one binary message from the socket (bincode, compressed or not) and applies it.
    #[cfg(feature = "unpack")]
    pub fn receive(&mut self, bytes: &[u8]) -> Result<Received, StreamError> {
        let message: StreamMessage = crate::wire::response_from_bincode(bytes)
            .map_err(|e| StreamError(format!("bad stream message: {e}")))?;
        let message = match message {
            StreamMessage::Packed(p) => {
                let inner = p.unpack()?;
                let m: StreamMessage = crate::wire::response_from_bincode(&inner)
                    .map_err(|e| StreamError(format!("bad packed message: {e}")))?;
                if matches!(m, StreamMessage::Packed(_)) {
                    return err("a packed message inside a packed message");
                }
                m
            }
            m => m,
        };
        self.apply(message)
    }
}

/// A head's buffer from residual planes `b` against its previous buffer `prev`.
fn resolve(b: &FrameBuffer, prev: &FrameBuffer) -> Result<FrameBuffer, String> {
    let positions = q16r_decode(&b.positions.0, &prev.positions.to_i16())?;
    let normals = match (&b.normals, &prev.normals) {
        (None, _) => None,
        (Some(n), Some(p)) => Some(blob_of(&q16r_decode(&n.0, &p.to_i16())?)),
        (Some(_), None) => return Err("residual normals but no earlier normals".into()),
    };
    Ok(FrameBuffer {
        positions: blob_of(&positions),
        normals,
        ..b.clone()
    })
}

fn blob_of(q: &[i16]) -> Blob {
    Blob(q.iter().flat_map(|v| v.to_le_bytes()).collect())
}

/// Most bytes a packed message may claim once decompressed (a tick of 1,000 ICT-sized heads
/// in f32 with normals is about 320 MB).
pub const MAX_UNPACKED_BYTES: u64 = 1 << 30;

#[cfg(feature = "unpack")]
impl PackedMessage {
    /// The message's bytes, decompressed; more or fewer than `length` is an error, found
    /// without inflating past `length`.
    pub fn unpack(&self) -> Result<Vec<u8>, StreamError> {
        use std::io::Read;
        if self.length > MAX_UNPACKED_BYTES {
            return err(format!(
                "a packed message claims {} bytes, more than {MAX_UNPACKED_BYTES}",
                self.length
            ));
        }
        let n = self.length as usize;
        let data = &self.data.0[..];
        if self.encoding == crate::MessageEncoding::Zstd {
            // One call into a buffer of the stated length: no zeroing, no staging copy (the
            // stream reader below does both). A frame that does not fit, or that is short or
            // bad, goes the streaming way, which names what is wrong.
            let mut out = Vec::with_capacity(n);
            if let Ok(mut z) = zstd::bulk::Decompressor::new()
                && z.decompress_to_buffer(data, &mut out).is_ok()
                && out.len() == n
            {
                return Ok(out);
            }
        }
        let mut out = Vec::with_capacity(n);
        let read = match self.encoding {
            crate::MessageEncoding::Zstd => zstd::stream::read::Decoder::new(data)
                .and_then(|d| d.take(n as u64 + 1).read_to_end(&mut out)),
            crate::MessageEncoding::Deflate => flate2::read::ZlibDecoder::new(data)
                .take(n as u64 + 1)
                .read_to_end(&mut out),
        };
        read.map_err(|e| StreamError(format!("bad {} data: {e}", self.encoding.name())))?;
        if out.len() != n {
            return err(format!(
                "a packed message of {} bytes claimed {n}",
                if out.len() > n {
                    "more".to_string()
                } else {
                    out.len().to_string()
                }
            ));
        }
        Ok(out)
    }
}
