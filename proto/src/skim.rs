//! Skimming a bincode stream message: its tick, head and buffer counts and timings, read
//! without decoding or copying its buffers (`crowdmorph load --sessions`, `bench sessions`: a
//! viewer that measures the stream rather than draws it). The layout it walks is
//! `proto/README.md`'s, "The stream"; the golden files check it (`proto/tests/golden.rs`).

use crate::stream::StreamError;
use crate::{FrameTimings, HEAD_MISSING};

/// What a load generator or a benchmark reads of a stream message, without copying its
/// buffers.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TickSummary {
    /// The tick number.
    pub tick: u64,
    /// Heads the message lists (every session head for vertex buffers and poses; 0 for an
    /// image).
    pub heads: u64,
    /// Of those, heads whose new buffer the message carries (neither unchanged nor missing).
    pub changed: u64,
    /// Buffers (or poses) the message carries.
    pub buffers: u64,
    /// The server's timings of the tick (vertex buffers and poses only).
    pub timings: Option<FrameTimings>,
}

/// Reads bincode as `proto/README.md` describes it, skipping what it does not need.
struct Skim<'a> {
    bytes: &'a [u8],
}

fn malformed(what: &str) -> StreamError {
    StreamError(format!("a malformed stream message ({what})"))
}

impl Skim<'_> {
    /// Passes over one `Layer`: clip, frame, weight, mode, mask, reference, joint mask.
    fn skip_layer(&mut self) -> Result<(), StreamError> {
        self.skip_bytes("layer clip")?;
        self.varint("layer frame")?;
        self.skip(4, "layer weight")?;
        self.varint("layer mode")?;
        if self.some("layer mask")? {
            match self.varint("mask variant")? {
                0 => {
                    for _ in 0..self.varint("mask names")? {
                        self.skip_bytes("mask name")?;
                    }
                }
                1 => {
                    for _ in 0..self.varint("mask weights")? {
                        self.skip_bytes("mask name")?;
                        self.skip(4, "mask weight")?;
                    }
                }
                2 => self.skip_bytes("mask name")?,
                _ => return Err(malformed("mask variant")),
            }
        }
        if self.some("layer reference")? {
            self.varint("layer reference")?;
        }
        if self.some("joint mask")? {
            for _ in 0..self.varint("joint mask")? {
                self.skip_bytes("joint mask node")?;
            }
        }
        Ok(())
    }

    /// Passes over an `Option<Vec<SessionHead>>` (a tick's layout).
    fn skip_layout(&mut self) -> Result<(), StreamError> {
        if self.some("layout")? {
            for _ in 0..self.varint("layout")? {
                self.varint("head id")?;
                self.skip_bytes("rig")?;
                self.skip_bytes("clip")?;
                self.varint("offset")?;
                // position [f32; 3], yaw and scale: fixed 4-byte floats.
                self.skip(20, "placement")?;
                if self.some("graph")? {
                    self.skip_bytes("graph name")?;
                    self.skip_bytes("graph start")?;
                    self.varint("graph seed")?;
                    for _ in 0..self.varint("graph script")? {
                        self.skip_bytes("graph script node")?;
                    }
                }
                // Joint overrides: a name, then translation, rotation and scale, each an
                // `Option` of 3, 4 and 3 fixed 4-byte floats.
                for _ in 0..self.varint("joints")? {
                    self.skip_bytes("joint name")?;
                    for (what, floats) in [("translation", 3), ("rotation", 4), ("scale", 3)] {
                        if self.some(what)? {
                            self.skip(4 * floats, what)?;
                        }
                    }
                }
                for _ in 0..self.varint("layers")? {
                    self.skip_layer()?;
                }
                if self.some("clamp")? {
                    self.skip(8, "clamp")?;
                }
                // Live settings: three durations, a One Euro filter's three floats and a
                // mapping's name, both optional.
                if self.some("live")? {
                    self.varint("live hold_ms")?;
                    self.varint("live fade_ms")?;
                    self.varint("live delay_ms")?;
                    if self.some("live smoothing")? {
                        self.skip(12, "live smoothing")?;
                    }
                    if self.some("live mapping")? {
                        self.skip_bytes("live mapping")?;
                    }
                }
                // Liveliness: four flags, an optional point (3 fixed 4-byte floats) and an
                // optional seed.
                if self.some("alive")? {
                    self.byte("alive blink")?;
                    self.byte("alive saccades")?;
                    if self.some("alive look_at")? {
                        self.skip(12, "alive look_at")?;
                    }
                    self.byte("alive breathing")?;
                    if self.some("alive seed")? {
                        self.varint("alive seed")?;
                    }
                }
            }
        }
        Ok(())
    }

    /// A tick's `FrameTimings`.
    fn timings(&mut self) -> Result<FrameTimings, StreamError> {
        let queue_us = self.varint("timings")?;
        let compute_us = self.varint("timings")?;
        let total_us = self.varint("timings")?;
        let gpu_us = if self.some("timings")? {
            Some(self.varint("timings")?)
        } else {
            None
        };
        Ok(FrameTimings {
            queue_us,
            compute_us,
            total_us,
            gpu_us,
        })
    }

    /// A tick's head entries: (heads, heads whose new buffer or pose it carries).
    fn head_entries(&mut self) -> Result<(u64, u64), StreamError> {
        let heads = self.varint("heads")?;
        let mut changed = 0;
        for _ in 0..heads {
            self.varint("head id")?;
            if self.varint("head buffer")? < u64::from(HEAD_MISSING) {
                changed += 1;
            }
        }
        Ok((heads, changed))
    }

    fn skip(&mut self, n: u64, what: &str) -> Result<(), StreamError> {
        let n = usize::try_from(n).map_err(|_| malformed(what))?;
        self.bytes = self.bytes.get(n..).ok_or_else(|| malformed(what))?;
        Ok(())
    }

    fn byte(&mut self, what: &str) -> Result<u8, StreamError> {
        let (&b, rest) = self.bytes.split_first().ok_or_else(|| malformed(what))?;
        self.bytes = rest;
        Ok(b)
    }

    /// bincode's variable-length integer (also a zigzag-encoded signed one, when skipped).
    fn varint(&mut self, what: &str) -> Result<u64, StreamError> {
        let width = match self.byte(what)? {
            b @ 0..=250 => return Ok(u64::from(b)),
            251 => 2,
            252 => 4,
            253 => 8,
            _ => return Err(malformed(what)),
        };
        let raw = self.bytes.get(..width).ok_or_else(|| malformed(what))?;
        let mut le = [0u8; 8];
        le[..width].copy_from_slice(raw);
        self.bytes = &self.bytes[width..];
        Ok(u64::from_le_bytes(le))
    }

    /// A string or byte string: its length, then its bytes.
    fn skip_bytes(&mut self, what: &str) -> Result<(), StreamError> {
        let n = self.varint(what)?;
        self.skip(n, what)
    }

    /// An `Option`'s tag.
    fn some(&mut self, what: &str) -> Result<bool, StreamError> {
        match self.byte(what)? {
            0 => Ok(false),
            1 => Ok(true),
            _ => Err(malformed(what)),
        }
    }

    /// A `Blob`: padding bytes, then payload bytes.
    fn skip_blob(&mut self, what: &str) -> Result<(), StreamError> {
        self.skip_bytes(what)?;
        self.skip_bytes(what)
    }
}

/// Reads the tick number, the head and buffer counts and the timings of a bincode
/// `StreamMessage`, passing over layouts and payloads without copying them; the whole message
/// must be one `StreamMessage`.
pub fn skim(message: &[u8]) -> Result<TickSummary, StreamError> {
    let mut s = Skim { bytes: message };
    let variant = s.varint("variant")?;
    if variant == 3 {
        // Packed: decompressed (bounded by its stated length), then skimmed.
        let encoding = match s.varint("encoding")? {
            0 => crate::MessageEncoding::Zstd,
            1 => crate::MessageEncoding::Deflate,
            _ => return Err(malformed("encoding")),
        };
        let length = s.varint("length")?;
        s.skip_bytes("pad")?;
        let n = usize::try_from(s.varint("data")?).map_err(|_| malformed("data"))?;
        let data = s.bytes.get(..n).ok_or_else(|| malformed("data"))?;
        if s.bytes.len() != n {
            return Err(malformed("bytes after the message"));
        }
        let packed = crate::PackedMessage {
            encoding,
            length,
            data: crate::Blob(data.to_vec()),
        };
        let inner = packed.unpack()?;
        if inner.first() == Some(&3) {
            return Err(malformed("a packed message inside a packed message"));
        }
        return skim(&inner);
    }
    let tick = s.varint("tick")?;
    let mut out = TickSummary {
        tick,
        ..TickSummary::default()
    };
    match variant {
        0 | 2 => {
            s.varint("format")?;
            s.byte("normals")?;
            s.skip_layout()?;
            if variant == 2 {
                // One residual flag per buffer.
                let flags = s.varint("residual flags")?;
                s.skip(flags, "residual flags")?;
            }
            out.buffers = s.varint("buffers")?;
            for _ in 0..out.buffers {
                s.skip_bytes("rig")?;
                s.skip_bytes("clip")?;
                s.varint("frame")?;
                s.varint("lod")?;
                s.varint("vertices")?;
                if s.some("quantization")? {
                    // min, step and max_error: nine 4-byte floats.
                    s.skip(36, "quantization")?;
                }
                s.skip_blob("positions")?;
                if s.some("normals")? {
                    s.skip_blob("normals")?;
                }
            }
            (out.heads, out.changed) = s.head_entries()?;
            out.timings = Some(s.timings()?);
        }
        1 => {
            s.varint("image format")?;
            s.varint("width")?;
            s.varint("height")?;
            s.skip_blob("image")?;
        }
        4 => {
            // Expression-layer inputs: no buffers, only the tick counts.
            for _ in 0..s.varint("layer heads")? {
                s.varint("head id")?;
                let n = s.varint("inputs")?;
                s.skip(n.saturating_mul(4), "inputs")?;
            }
        }
        5 => {
            // Poses: the layout, then per pose its binary16 weights (a blob) and moved nodes
            // (node, rotation, optional translation and scale), then the heads and timings.
            s.skip_layout()?;
            out.buffers = s.varint("poses")?;
            for _ in 0..out.buffers {
                s.skip_blob("weights")?;
                for _ in 0..s.varint("joints")? {
                    s.varint("node")?;
                    s.skip(16, "rotation")?;
                    for what in ["translation", "scale"] {
                        if s.some(what)? {
                            s.skip(12, what)?;
                        }
                    }
                }
            }
            (out.heads, out.changed) = s.head_entries()?;
            out.timings = Some(s.timings()?);
        }
        _ => return Err(malformed("unknown variant")),
    }
    if !s.bytes.is_empty() {
        return Err(malformed("bytes after the message"));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    // A test that meets an unexpected error should fail loudly.
    #![allow(clippy::unwrap_used)]

    use crate::{
        Blob, Format, FrameBuffer, HEAD_UNCHANGED, HeadBuffer, Quantization, SessionHead,
        StreamMessage, TickFrame, TickVertices,
    };

    use super::*;

    #[test]
    fn the_golden_tick_skims() {
        let golden = include_bytes!("../tests/golden/stream_vertices.bincode");
        let t = skim(golden).unwrap();
        assert_eq!(
            (t.tick, t.heads, t.changed, t.buffers),
            (452, 3, 1, 1),
            "{t:?}"
        );
        assert!(t.timings.is_some());
    }

    #[test]
    fn a_tick_with_layout_quantization_and_normals_skims_like_it_decodes() {
        let buffer = FrameBuffer {
            rig: "default-head".into(),
            clip: "talk".into(),
            frame: 70_000,
            lod: 2,
            vertices: 300,
            quantization: Some(Quantization {
                min: [0.0; 3],
                step: [1.0; 3],
                max_error: [0.5; 3],
            }),
            positions: Blob(vec![7; 1800]),
            normals: Some(Blob(vec![1; 1800])),
        };
        let layout: Vec<SessionHead> = (0..4)
            .map(|h| SessionHead {
                head: h * 1000,
                rig: "default-head".into(),
                clip: "smile".into(),
                offset: -3,
                position: [1.0, 2.0, 3.0],
                yaw: 90.0,
                scale: 1.5,
                // One head walks a graph, so the skim passes over one too.
                graph: (h == 2).then(|| crate::GraphPlay {
                    name: "moods".into(),
                    start: "talk".into(),
                    seed: u64::MAX,
                    script: vec!["smile".into(), "talk".into()],
                }),
                // And one sets a joint, so it passes over joint overrides.
                joints: if h == 1 {
                    crate::JointOverrides::rotation("LeftEye", [0.0, 0.1, 0.0, 1.0])
                } else {
                    Default::default()
                },
                // And one has layers of every mask kind and a clamp.
                layers: if h == 3 {
                    vec![
                        crate::Layer {
                            mask: Some(crate::Mask::Names(vec!["jawOpen".into()])),
                            joint_mask: Some(vec!["Head".into()]),
                            ..crate::Layer::over("talk", 2, 0.5)
                        },
                        crate::Layer {
                            mask: Some(crate::Mask::Weights(vec![("eyeBlinkLeft".into(), 0.5)])),
                            mode: crate::LayerMode::Additive,
                            reference: Some(-1),
                            ..crate::Layer::over("smile", -7, 1.0)
                        },
                        crate::Layer {
                            mask: Some(crate::Mask::Named("upper_face".into())),
                            ..crate::Layer::over("talk", 0, 0.25)
                        },
                    ]
                } else {
                    Vec::new()
                },
                clamp: (h == 3).then_some([0.0, 1.0]),
                // And one is live, with every setting.
                live: (h == 0).then(|| crate::LiveSpec {
                    smoothing: Some(crate::OneEuro {
                        min_cutoff: 1.5,
                        beta: 0.25,
                        d_cutoff: 1.0,
                    }),
                    mapping: Some("a2f".into()),
                    ..crate::LiveSpec::default()
                }),
                // And two are alive, one with a look-at point and a seed.
                alive: match h {
                    2 => Some(crate::Alive {
                        blink: true,
                        ..Default::default()
                    }),
                    3 => Some(crate::Alive {
                        saccades: true,
                        look_at: Some([1.0, 1.5, -2.0]),
                        breathing: true,
                        seed: Some(u64::MAX),
                        ..Default::default()
                    }),
                    _ => None,
                },
            })
            .collect();
        let m = StreamMessage::Vertices(TickVertices {
            tick: 1 << 40,
            format: Format::Q16,
            normals: true,
            layout: Some(layout),
            buffers: vec![buffer.clone(), buffer],
            heads: vec![
                HeadBuffer { head: 0, buffer: 0 },
                HeadBuffer {
                    head: 1000,
                    buffer: HEAD_UNCHANGED,
                },
                HeadBuffer {
                    head: 2000,
                    buffer: 1,
                },
                HeadBuffer {
                    head: 3000,
                    buffer: HEAD_MISSING,
                },
            ],
            timings: FrameTimings {
                queue_us: 5,
                compute_us: 300_000,
                total_us: 1 << 33,
                gpu_us: Some(9),
            },
        });
        let bytes = crate::wire::to_bincode(&m).unwrap();
        let t = skim(&bytes).unwrap();
        let t_vertices = t;
        assert_eq!((t.tick, t.heads, t.changed, t.buffers), (1 << 40, 4, 2, 2));
        assert_eq!(
            t.timings,
            Some(FrameTimings {
                queue_us: 5,
                compute_us: 300_000,
                total_us: 1 << 33,
                gpu_us: Some(9)
            })
        );
        // Every shorter prefix, and one byte more, is refused rather than misread.
        for n in 0..bytes.len() {
            assert!(skim(&bytes[..n]).is_err(), "prefix of {n} bytes");
        }
        let mut longer = bytes.clone();
        longer.push(0);
        assert!(skim(&longer).is_err());

        // The same tick as temporal residuals, then packed both ways, skims alike.
        let StreamMessage::Vertices(v) = m else {
            unreachable!()
        };
        let delta = StreamMessage::Delta(crate::TickDelta {
            tick: v.tick,
            format: v.format,
            normals: v.normals,
            layout: v.layout,
            residual: vec![true, false],
            buffers: v.buffers,
            heads: v.heads,
            timings: v.timings,
        });
        let delta_bytes = crate::wire::to_bincode(&delta).unwrap();
        assert_eq!(skim(&delta_bytes).unwrap(), t);
        for n in 0..delta_bytes.len() {
            assert!(skim(&delta_bytes[..n]).is_err(), "prefix of {n} bytes");
        }
        let zstd = zstd::bulk::compress(&delta_bytes, 1).unwrap();
        let mut z = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::fast());
        std::io::Write::write_all(&mut z, &delta_bytes).unwrap();
        let zlib = z.finish().unwrap();
        for (encoding, data) in [
            (crate::MessageEncoding::Zstd, zstd),
            (crate::MessageEncoding::Deflate, zlib),
        ] {
            let mut packed = crate::PackedMessage {
                encoding,
                length: delta_bytes.len() as u64,
                data: Blob(data),
            };
            let bytes = crate::wire::to_bincode(&StreamMessage::Packed(packed.clone()));
            assert_eq!(skim(&bytes.unwrap()).unwrap(), t, "{encoding:?}");
            // A packed message that lies about its length is refused, not misread.
            packed.length -= 1;
            let bytes = crate::wire::to_bincode(&StreamMessage::Packed(packed));
            assert!(skim(&bytes.unwrap()).is_err(), "{encoding:?}");
        }

        let frame = StreamMessage::Frame(TickFrame {
            tick: 9,
            format: crate::ImageFormat::Jpeg,
            width: 640,
            height: 480,
            image: Blob(vec![0; 100]),
        });
        let t = skim(&crate::wire::to_bincode(&frame).unwrap()).unwrap();
        assert_eq!((t.tick, t.heads, t.changed), (9, 0, 0));

        // A weights viewer's tick, with the same layout: poses in place of buffers.
        let StreamMessage::Delta(d) = delta else {
            unreachable!()
        };
        let pose = crate::HeadPose {
            weights: Blob(crate::weights_f16_le(&[0.25; 52])),
            joints: vec![
                crate::NodePose {
                    node: 300,
                    rotation: [0.0, 0.0, 0.0, 1.0],
                    translation: None,
                    scale: Some([1.0, 2.0, 1.0]),
                },
                crate::NodePose {
                    node: 7,
                    rotation: [0.6, 0.0, 0.0, 0.8],
                    translation: Some([0.0, 1.0, 0.0]),
                    scale: None,
                },
            ],
        };
        let poses = StreamMessage::Poses(crate::TickPoses {
            tick: d.tick,
            layout: d.layout,
            poses: vec![pose.clone(), pose],
            heads: d.heads,
            timings: d.timings,
        });
        let bytes = crate::wire::to_bincode(&poses).unwrap();
        assert_eq!(skim(&bytes).unwrap(), t_vertices);
        for n in 0..bytes.len() {
            assert!(skim(&bytes[..n]).is_err(), "prefix of {n} bytes");
        }
    }
}
