//! The one module of this crate that touches bincode: wire messages and stored records.
//!
//! Keeping bincode behind this module means its pinned version (2.0.1; upstream is frozen)
//! could be replaced by another encoding of the same bytes without touching the server or the
//! store. Wire messages use the protocol's configuration from [`crowdmorph_proto::wire`] so that
//! the server and every Rust client encode identically; stored records use the same standard
//! configuration with a larger decode limit, since they are checksummed before being decoded.
//!
//! [`FrameResponseEncoder`] writes a crowd-frame response piece by piece instead of through
//! serde: the bytes are exactly the bincode encoding of a
//! [`CrowdFrameResponse`](crowdmorph_proto::CrowdFrameResponse), but vertex payloads are not
//! copied (they are [`Bytes`] views of the engine's output) and each payload is preceded by
//! zero padding that aligns it to [`BLOB_ALIGN`] bytes from the start of the body.

use bytes::Bytes;
pub use crowdmorph_proto::wire::put_varint;
use crowdmorph_proto::wire::{self, WireError};
use crowdmorph_proto::{BLOB_ALIGN, Format, FrameTimings, HeadBuffer, Quantization};
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};

/// Why a value could not be encoded or decoded.
#[derive(Debug, thiserror::Error)]
pub enum CodecError {
    /// A wire message is malformed.
    #[error(transparent)]
    Wire(#[from] WireError),
    /// A stored record is malformed.
    #[error("stored record: {0}")]
    Stored(String),
}

/// Encodes a wire message (request or response) as bincode.
pub fn to_wire<T: Serialize>(value: &T) -> Result<Vec<u8>, CodecError> {
    Ok(wire::to_bincode(value)?)
}

/// Length of [`to_wire`]'s encoding of `value`, without encoding it.
pub fn wire_len<T: Serialize>(value: &T) -> Result<usize, CodecError> {
    Ok(wire::bincode_len(value)?)
}

/// Decodes a request body sent as bincode (untrusted: decoding is byte-limited).
pub fn request_from_wire<T: DeserializeOwned>(bytes: &[u8]) -> Result<T, CodecError> {
    Ok(wire::request_from_bincode(bytes)?)
}

/// Decodes a response body sent as bincode.
pub fn response_from_wire<T: DeserializeOwned>(bytes: &[u8]) -> Result<T, CodecError> {
    Ok(wire::response_from_bincode(bytes)?)
}

/// Most bytes a stored record may claim when decoded.
const STORED_DECODE_LIMIT: usize = 1 << 36;

/// Encodes a record for the store.
pub fn to_stored<T: Serialize>(value: &T) -> Result<Vec<u8>, CodecError> {
    bincode::serde::encode_to_vec(value, bincode::config::standard())
        .map_err(|e| CodecError::Stored(e.to_string()))
}

/// Encodes a record for the store straight into `writer`, so a large record never exists as
/// a second in-memory copy. Returns the bytes written.
pub fn to_stored_writer<T: Serialize, W: std::io::Write>(
    value: &T,
    writer: &mut W,
) -> Result<usize, CodecError> {
    bincode::serde::encode_into_std_write(value, writer, bincode::config::standard())
        .map_err(|e| CodecError::Stored(e.to_string()))
}

/// Length of [`to_stored`]'s encoding of `value`, without holding it: the value is encoded
/// into a counter (a section's length is written before its bytes, and a rig's section is
/// too big to encode twice into memory).
pub fn stored_len<T: Serialize>(value: &T) -> Result<u64, CodecError> {
    struct Count(u64);
    impl std::io::Write for Count {
        fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
            self.0 += buf.len() as u64;
            Ok(buf.len())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }
    let mut count = Count(0);
    to_stored_writer(value, &mut count)?;
    Ok(count.0)
}

/// [`from_stored`] with decode limit `LIMIT`.
fn decode_stored<T: DeserializeOwned, const LIMIT: usize>(
    bytes: &[u8],
) -> Result<(T, usize), bincode::error::DecodeError> {
    let cfg = bincode::config::standard().with_limit::<LIMIT>();
    bincode::serde::decode_from_slice(bytes, cfg)
}

/// [`from_stored_borrowed`] with decode limit `LIMIT`.
fn borrow_stored<'a, T: Deserialize<'a>, const LIMIT: usize>(
    bytes: &'a [u8],
) -> Result<(T, usize), bincode::error::DecodeError> {
    let cfg = bincode::config::standard().with_limit::<LIMIT>();
    bincode::serde::borrow_decode_from_slice(bytes, cfg)
}

/// Calls `$decode::<_, LIMIT>($bytes)` with the decode limit for a record of `$bytes`' length
/// (see [`from_stored`]), and checks that the record used every byte.
macro_rules! stored_by_limit {
    ($decode:ident, $bytes:expr) => {{
        let bytes = $bytes;
        let n = bytes.len();
        let decoded = if n <= 1 << 20 {
            $decode::<_, { 1 << 20 }>(bytes)
        } else if n <= 1 << 24 {
            $decode::<_, { 1 << 24 }>(bytes)
        } else if n <= 1 << 28 {
            $decode::<_, { 1 << 28 }>(bytes)
        } else if n <= 1 << 32 {
            $decode::<_, { 1 << 32 }>(bytes)
        } else {
            $decode::<_, STORED_DECODE_LIMIT>(bytes)
        };
        let (value, used) = decoded.map_err(|e| CodecError::Stored(e.to_string()))?;
        if used != bytes.len() {
            return Err(CodecError::Stored(format!(
                "{} bytes after the record",
                bytes.len() - used
            )));
        }
        Ok(value)
    }};
}

/// Decodes a record read from the store; the whole slice must be one record.
///
/// bincode allocates a string or byte buffer of the length it reads before it reads the bytes,
/// up to its decode limit; through serde nothing else claims memory, and a string's bytes are
/// in the record, so a limit of the record's length rounded up to a power of 16 (at least
/// 1 MiB, at most [`STORED_DECODE_LIMIT`]) refuses no valid record, and a damaged length
/// allocates no more than that limit, not gigabytes.
pub fn from_stored<T: DeserializeOwned>(bytes: &[u8]) -> Result<T, CodecError> {
    stored_by_limit!(decode_stored, bytes)
}

/// [`from_stored`] for a value that borrows its strings and byte strings from `bytes`
/// (`&str`, `&[u8]`): a large byte section is read where it lies instead of being copied, so
/// that decoding it from the record holds it once, not twice.
pub fn from_stored_borrowed<'a, T: Deserialize<'a>>(bytes: &'a [u8]) -> Result<T, CodecError> {
    stored_by_limit!(borrow_stored, bytes)
}

/// One unique buffer of a crowd-frame response, with its payloads as shared bytes.
#[derive(Clone, Debug)]
pub struct FrameBufferParts<'a> {
    /// Rig id.
    pub rig: &'a str,
    /// Clip name.
    pub clip: &'a str,
    /// Frame played.
    pub frame: u32,
    /// LOD level.
    pub lod: u32,
    /// Vertices.
    pub vertices: u32,
    /// Dequantization box (q16 only).
    pub quantization: Option<Quantization>,
    /// Position payload.
    pub positions: Bytes,
    /// Normal payload, when asked for.
    pub normals: Option<Bytes>,
}

/// Writes the bincode encoding of a crowd-frame response as a list of chunks.
#[derive(Debug, Default)]
pub struct FrameResponseEncoder {
    chunks: Vec<Bytes>,
    head: Vec<u8>,
    offset: usize,
    /// Only count the bytes (see [`FrameResponseEncoder::encoded_len_within`]).
    count_only: bool,
}

/// Bytes a counting encoder lets its head grow to before it moves them into the count.
const COUNT_FLUSH_BYTES: usize = 4096;

impl FrameResponseEncoder {
    /// Encodes a whole response. Concatenating the chunks gives the body.
    pub fn encode(
        format: Format,
        normals: bool,
        buffers: &[FrameBufferParts<'_>],
        heads: &[HeadBuffer],
        timings: &FrameTimings,
    ) -> Vec<Bytes> {
        FrameResponseEncoder::encode_within(
            Vec::new(),
            &[],
            format,
            normals,
            buffers,
            heads,
            timings,
        )
    }

    /// Encodes a message that holds a response's fields: `prefix` (already encoded fields
    /// of the enclosing message, e.g. a session stream's variant and tick), the format and
    /// normals, `middle` (more encoded fields, e.g. the stream's layout), then the rest of the
    /// response. Payloads are aligned from the start of the prefix.
    pub fn encode_within(
        prefix: Vec<u8>,
        middle: &[u8],
        format: Format,
        normals: bool,
        buffers: &[FrameBufferParts<'_>],
        heads: &[HeadBuffer],
        timings: &FrameTimings,
    ) -> Vec<Bytes> {
        let mut e = FrameResponseEncoder {
            head: prefix,
            ..FrameResponseEncoder::default()
        };
        e.format(format, normals);
        e.head.extend_from_slice(middle);
        e.rest(buffers, heads, timings);
        e.chunks
    }

    /// The length of what [`FrameResponseEncoder::encode_within`] makes (all chunks together)
    /// from a prefix and a middle of these lengths, computed by the same code without
    /// allocating the message, so that its memory can be charged first.
    pub fn encoded_len_within(
        prefix_len: usize,
        middle_len: usize,
        format: Format,
        normals: bool,
        buffers: &[FrameBufferParts<'_>],
        heads: &[HeadBuffer],
        timings: &FrameTimings,
    ) -> usize {
        let mut e = FrameResponseEncoder {
            offset: prefix_len,
            count_only: true,
            ..FrameResponseEncoder::default()
        };
        e.format(format, normals);
        e.offset += middle_len;
        e.rest(buffers, heads, timings);
        e.offset
    }

    fn format(&mut self, format: Format, normals: bool) {
        // Unit enum variants are their index as a varint.
        self.varint(match format {
            Format::F32 => 0,
            Format::F16 => 1,
            Format::Q16 => 2,
            Format::Q16R => 3,
            Format::Weights => 4,
        });
        self.head.push(u8::from(normals));
    }

    /// Everything after the middle.
    fn rest(
        &mut self,
        buffers: &[FrameBufferParts<'_>],
        heads: &[HeadBuffer],
        timings: &FrameTimings,
    ) {
        let e = self;
        e.varint(buffers.len() as u64);
        for b in buffers {
            e.string(b.rig);
            e.string(b.clip);
            e.varint(u64::from(b.frame));
            e.varint(u64::from(b.lod));
            e.varint(u64::from(b.vertices));
            match &b.quantization {
                None => e.head.push(0),
                Some(q) => {
                    e.head.push(1);
                    for v in q.min.iter().chain(&q.step).chain(&q.max_error) {
                        e.head.extend_from_slice(&v.to_le_bytes());
                    }
                }
            }
            e.blob(b.positions.clone());
            match &b.normals {
                None => e.head.push(0),
                Some(n) => {
                    e.head.push(1);
                    e.blob(n.clone());
                }
            }
        }
        e.varint(heads.len() as u64);
        for h in heads {
            e.varint(h.head);
            e.varint(u64::from(h.buffer));
        }
        e.varint(timings.queue_us);
        e.varint(timings.compute_us);
        e.varint(timings.total_us);
        match timings.gpu_us {
            None => e.head.push(0),
            Some(g) => {
                e.head.push(1);
                e.varint(g);
            }
        }
        e.flush();
    }

    fn varint(&mut self, n: u64) {
        put_varint(&mut self.head, n);
        // A count needs no more than a small head: positions only depend on the total.
        if self.count_only && self.head.len() >= COUNT_FLUSH_BYTES {
            self.flush();
        }
    }

    fn string(&mut self, s: &str) {
        self.varint(s.len() as u64);
        self.head.extend_from_slice(s.as_bytes());
    }

    /// A blob is `pad: bytes` then `data: bytes`; the pad makes `data` start aligned.
    fn blob(&mut self, data: Bytes) {
        let mut len_bytes = Vec::with_capacity(9);
        put_varint(&mut len_bytes, data.len() as u64);
        // Position after the pad's own length byte (pads are < 251 bytes, so one byte).
        let at = self.offset + self.head.len() + 1;
        let pad = (BLOB_ALIGN - (at + len_bytes.len()) % BLOB_ALIGN) % BLOB_ALIGN;
        self.head.push(pad as u8);
        self.head.resize(self.head.len() + pad, 0);
        self.head.extend_from_slice(&len_bytes);
        self.flush();
        self.offset += data.len();
        if !data.is_empty() && !self.count_only {
            self.chunks.push(data);
        }
    }

    fn flush(&mut self) {
        if !self.head.is_empty() {
            self.offset += self.head.len();
            if self.count_only {
                self.head.clear();
            } else {
                self.chunks
                    .push(Bytes::from(std::mem::take(&mut self.head)));
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crowdmorph_proto::{Blob, CrowdFrameResponse, FrameBuffer};

    fn sample() -> (Vec<FrameBufferParts<'static>>, CrowdFrameResponse) {
        let p0: Vec<u8> = (0..36u8).collect();
        let n0: Vec<u8> = (100..136u8).collect();
        let p1: Vec<u8> = (0..300u32).map(|i| (i * 7) as u8).collect();
        let q = Quantization {
            min: [-1.0, -2.0, -3.0],
            step: [1e-4, 2e-4, 3e-4],
            max_error: [5e-5, 1e-4, 1.5e-4],
        };
        let parts = vec![
            FrameBufferParts {
                rig: "default-head",
                clip: "talk",
                frame: 12,
                lod: 0,
                vertices: 3,
                quantization: None,
                positions: Bytes::from(p0.clone()),
                normals: Some(Bytes::from(n0.clone())),
            },
            FrameBufferParts {
                rig: "r",
                clip: "a-very-long-clip-name",
                frame: 300,
                lod: 2,
                vertices: 25,
                quantization: Some(q),
                positions: Bytes::from(p1.clone()),
                normals: None,
            },
        ];
        let resp = CrowdFrameResponse {
            format: Format::Q16,
            normals: true,
            buffers: vec![
                FrameBuffer {
                    rig: "default-head".into(),
                    clip: "talk".into(),
                    frame: 12,
                    lod: 0,
                    vertices: 3,
                    quantization: None,
                    positions: Blob(p0),
                    normals: Some(Blob(n0)),
                },
                FrameBuffer {
                    rig: "r".into(),
                    clip: "a-very-long-clip-name".into(),
                    frame: 300,
                    lod: 2,
                    vertices: 25,
                    quantization: Some(q),
                    positions: Blob(p1),
                    normals: None,
                },
            ],
            heads: vec![
                HeadBuffer { head: 7, buffer: 0 },
                HeadBuffer {
                    head: 1 << 40,
                    buffer: 1,
                },
                HeadBuffer { head: 9, buffer: 0 },
            ],
            timings: FrameTimings {
                queue_us: 5,
                compute_us: 70_000,
                total_us: 1 << 33,
                gpu_us: Some(3),
            },
        };
        (parts, resp)
    }

    #[test]
    fn piecewise_encoding_decodes_as_the_message_with_aligned_payloads() {
        let (parts, resp) = sample();
        let chunks = FrameResponseEncoder::encode(
            resp.format,
            resp.normals,
            &parts,
            &resp.heads,
            &resp.timings,
        );
        let body: Vec<u8> = chunks.iter().flat_map(|c| c.iter().copied()).collect();
        let back: CrowdFrameResponse = response_from_wire(&body).expect("decodes");
        assert_eq!(back, resp);
        // Every payload starts aligned.
        assert_payloads_aligned(&chunks, &parts);
        // Without padding it is byte for byte the serde encoding.
        let plain = to_wire(&resp).expect("encode");
        let back: CrowdFrameResponse = response_from_wire(&plain).expect("decodes");
        assert_eq!(back, resp);
    }

    #[test]
    fn a_stream_tick_wraps_a_response_with_aligned_payloads() {
        use crowdmorph_proto::{SessionHead, StreamMessage, TickVertices};
        let (parts, resp) = sample();
        let layout = vec![SessionHead {
            head: 7,
            rig: "default-head".into(),
            clip: "talk".into(),
            offset: -3,
            position: [1.0, 2.0, 3.0],
            yaw: 45.0,
            scale: 2.0,
            graph: None,
            joints: Default::default(),
            layers: Vec::new(),
            clamp: None,
            live: None,
            alive: None,
        }];
        let mut prefix = Vec::new();
        put_varint(&mut prefix, 0);
        put_varint(&mut prefix, 1234);
        let middle = to_wire(&Some(layout.clone())).expect("layout");
        assert_eq!(
            wire_len(&Some(layout.clone())).expect("layout"),
            middle.len()
        );
        let counted = FrameResponseEncoder::encoded_len_within(
            prefix.len(),
            middle.len(),
            resp.format,
            resp.normals,
            &parts,
            &resp.heads,
            &resp.timings,
        );
        let chunks = FrameResponseEncoder::encode_within(
            prefix,
            &middle,
            resp.format,
            resp.normals,
            &parts,
            &resp.heads,
            &resp.timings,
        );
        let body: Vec<u8> = chunks.iter().flat_map(|c| c.iter().copied()).collect();
        let back: StreamMessage = response_from_wire(&body).expect("decodes");
        let want = StreamMessage::Vertices(TickVertices {
            tick: 1234,
            format: resp.format,
            normals: resp.normals,
            layout: Some(layout),
            buffers: resp.buffers.clone(),
            heads: resp.heads.clone(),
            timings: resp.timings,
        });
        assert_eq!(back, want);
        assert_payloads_aligned(&chunks, &parts);
        assert_eq!(counted, body.len(), "the length is known before encoding");
    }

    /// The length computed before encoding is the encoding's, whatever the prefix (which moves
    /// the payloads' padding) and however many heads (which the count does not hold at once).
    #[test]
    fn encoded_lengths_are_exact() {
        let (parts, resp) = sample();
        for prefix_len in 0..20 {
            for n in [0, 1, 3, 5_000] {
                let heads: Vec<HeadBuffer> = (0..n)
                    .map(|i| HeadBuffer {
                        head: (i as u64) << (i % 50),
                        buffer: (i % 2) as u32,
                    })
                    .collect();
                let middle = vec![7u8; prefix_len * 3];
                let want: usize = FrameResponseEncoder::encode_within(
                    vec![1u8; prefix_len],
                    &middle,
                    resp.format,
                    resp.normals,
                    &parts,
                    &heads,
                    &resp.timings,
                )
                .iter()
                .map(Bytes::len)
                .sum();
                let got = FrameResponseEncoder::encoded_len_within(
                    prefix_len,
                    middle.len(),
                    resp.format,
                    resp.normals,
                    &parts,
                    &heads,
                    &resp.timings,
                );
                assert_eq!(got, want, "prefix {prefix_len}, {n} heads");
            }
        }
    }

    /// Finds each part's payload among the chunks (the encoder passes payloads through as
    /// their own chunks, without copying) and checks that it starts at an offset of the body
    /// that is a multiple of [`BLOB_ALIGN`].
    fn assert_payloads_aligned(chunks: &[Bytes], parts: &[FrameBufferParts<'_>]) {
        let mut found = 0;
        let mut at = 0;
        for c in chunks {
            for p in parts {
                if c.as_ptr() == p.positions.as_ptr() {
                    assert_eq!(at % BLOB_ALIGN, 0, "payload at {at}");
                    found += 1;
                }
            }
            at += c.len();
        }
        assert_eq!(found, parts.len(), "every payload is its own chunk");
    }

    #[test]
    fn stored_records_roundtrip_and_refuse_trailing_bytes() {
        let clips = crowdmorph_core::embedded::default_rig().clips;
        let bytes = to_stored(&clips).expect("encode");
        let back: Vec<crowdmorph_core::rig::Clip> = from_stored(&bytes).expect("decode");
        assert_eq!(back, clips);
        let mut longer = bytes.clone();
        longer.push(0);
        assert!(from_stored::<Vec<crowdmorph_core::rig::Clip>>(&longer).is_err());
        assert!(from_stored::<Vec<crowdmorph_core::rig::Clip>>(&bytes[..bytes.len() / 2]).is_err());
        assert_eq!(stored_len(&clips).expect("count"), bytes.len() as u64);
    }

    /// A length that claims more than the record could hold is refused before it is
    /// allocated; one that fits is read.
    #[test]
    fn stored_lengths_past_the_limit_are_refused_before_allocating() {
        let name = "x".repeat(300);
        let bytes = to_stored(&name).expect("encode");
        assert_eq!(from_stored::<String>(&bytes).expect("decode"), name);
        // A string of 2^32 - 1 bytes in a record of 5: refused as over the limit, where an
        // allocation of 4 GiB would otherwise come first.
        let mut huge = vec![252u8];
        huge.extend_from_slice(&u32::MAX.to_le_bytes());
        let e = from_stored::<String>(&huge).expect_err("refused");
        assert!(e.to_string().to_lowercase().contains("limit"), "{e}");
    }
}
