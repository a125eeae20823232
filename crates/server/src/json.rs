//! JSON crowd-frame responses, written straight into a reused buffer.
//!
//! Serializing a [`crowdmorph_proto::CrowdFrameResponse`] with serde copied every payload into
//! a `Blob`, base64-encoded it into a fresh `String`, let serde_json scan that string for
//! characters to escape, and wrote the result into a fresh buffer whose page faults cost as
//! much as the encoding. Here the small fields go through serde_json (so escaping and number
//! formatting are serde_json's own) and each payload is base64-encoded once, with SIMD
//! (`base64-simd`), from the engine's shared bytes into a buffer taken from a small pool and
//! given back when the response body has been sent. The bytes are exactly serde_json's
//! encoding of the response (a test checks it).

use std::sync::Arc;

use bytes::Bytes;
use crowdmorph_proto::{Format, FrameTimings, HeadBuffer};
use serde::Serialize;

use super::pool::Pool;
use crowdmorph_store::codec::FrameBufferParts;

/// Buffers kept for reuse.
const POOL_BUFFERS: usize = 4;
/// Most bytes the kept buffers may hold together (see [`Pool`]).
const POOL_TOTAL_BYTES: usize = 192 << 20;

/// A pool of response buffers.
#[derive(Debug)]
pub struct JsonPool(Pool<Vec<u8>>);

impl Default for JsonPool {
    fn default() -> Self {
        JsonPool(Pool::new(POOL_BUFFERS, POOL_TOTAL_BYTES))
    }
}

/// A response body that returns its buffer to the pool when dropped.
struct Pooled {
    buf: Vec<u8>,
    pool: Arc<JsonPool>,
}

impl AsRef<[u8]> for Pooled {
    fn as_ref(&self) -> &[u8] {
        &self.buf
    }
}

impl Drop for Pooled {
    fn drop(&mut self) {
        let mut buf = std::mem::take(&mut self.buf);
        buf.clear();
        self.pool.0.put(buf);
    }
}

impl JsonPool {
    fn take(&self, capacity: usize) -> Vec<u8> {
        // The smallest kept buffer that fits, else the largest (it grows once).
        let reused = self.0.take_best(|b| {
            let c = b.capacity();
            Some(if c >= capacity {
                (true, std::cmp::Reverse(c))
            } else {
                (false, std::cmp::Reverse(usize::MAX - c))
            })
        });
        let mut buf = reused.unwrap_or_default();
        buf.reserve(capacity);
        buf
    }
}

/// Exact length of the JSON encoding of the payloads (base64 with padding, plus quotes).
fn payload_len(parts: &[FrameBufferParts<'_>]) -> usize {
    let b64 = |n: usize| n.div_ceil(3) * 4 + 2;
    parts
        .iter()
        .map(|p| b64(p.positions.len()) + p.normals.as_ref().map_or(0, |n| b64(n.len())))
        .sum()
}

fn push_json<T: Serialize + ?Sized>(out: &mut Vec<u8>, v: &T) {
    // Writing plain data (strings, numbers, arrays of them) into a Vec cannot fail.
    let _ = serde_json::to_writer(&mut *out, v);
}

fn push_blob(out: &mut Vec<u8>, data: &[u8]) {
    out.push(b'"');
    base64_simd::STANDARD.encode_append(data, out);
    out.push(b'"');
}

/// Encodes a crowd-frame response as JSON into a pooled buffer.
pub fn encode_frame(
    pool: &Arc<JsonPool>,
    format: Format,
    normals: bool,
    parts: &[FrameBufferParts<'_>],
    heads: &[HeadBuffer],
    timings: &FrameTimings,
) -> Bytes {
    let mut out = pool.take(payload_len(parts) + 256 * parts.len() + 40 * heads.len() + 256);
    out.extend_from_slice(b"{\"format\":");
    push_json(&mut out, &format);
    out.extend_from_slice(b",\"normals\":");
    push_json(&mut out, &normals);
    out.extend_from_slice(b",\"buffers\":[");
    for (i, p) in parts.iter().enumerate() {
        if i > 0 {
            out.push(b',');
        }
        out.extend_from_slice(b"{\"rig\":");
        push_json(&mut out, p.rig);
        out.extend_from_slice(b",\"clip\":");
        push_json(&mut out, p.clip);
        out.extend_from_slice(b",\"frame\":");
        push_json(&mut out, &p.frame);
        out.extend_from_slice(b",\"lod\":");
        push_json(&mut out, &p.lod);
        out.extend_from_slice(b",\"vertices\":");
        push_json(&mut out, &p.vertices);
        out.extend_from_slice(b",\"quantization\":");
        push_json(&mut out, &p.quantization);
        out.extend_from_slice(b",\"positions\":");
        push_blob(&mut out, &p.positions);
        out.extend_from_slice(b",\"normals\":");
        match &p.normals {
            Some(n) => push_blob(&mut out, n),
            None => out.extend_from_slice(b"null"),
        }
        out.push(b'}');
    }
    out.extend_from_slice(b"],\"heads\":");
    push_json(&mut out, heads);
    out.extend_from_slice(b",\"timings\":");
    push_json(&mut out, timings);
    out.push(b'}');
    Bytes::from_owner(Pooled {
        buf: out,
        pool: pool.clone(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crowdmorph_proto::{Blob, CrowdFrameResponse, FrameBuffer, Quantization};

    // Long on purpose: one table of every format and buffer kind, each checked against
    // serde_json's bytes, then the same pool reused; split up, the reuse would not be tested.
    #[test]
    fn the_bytes_are_serde_jsons_and_buffers_are_reused() {
        let pool = Arc::new(JsonPool::default());
        let q = Quantization {
            min: [-1.0, 0.5, 1e-7],
            step: [1e-4, 2.5e-5, 3.0],
            max_error: [5e-5, 1.25e-5, 1.5],
        };
        // Payload lengths 0, 1, 2 and 3 mod 3 exercise the base64 padding.
        let payloads: Vec<Vec<u8>> = (0..4u8)
            .map(|k| {
                (0..(30 + k as usize))
                    .map(|i| (i as u8).wrapping_mul(37) ^ k)
                    .collect()
            })
            .collect();
        let parts: Vec<FrameBufferParts<'_>> = payloads
            .iter()
            .enumerate()
            .map(|(i, p)| FrameBufferParts {
                rig: if i == 0 {
                    "default-head"
                } else {
                    "r\"ig\\ \u{e9}\n"
                },
                clip: "talk",
                frame: i as u32 * 1000,
                lod: i as u32,
                vertices: 10,
                quantization: (i % 2 == 1).then_some(q),
                positions: Bytes::from(p.clone()),
                normals: (i >= 2).then(|| Bytes::from(p[..p.len() - 1].to_vec())),
            })
            .collect();
        let heads = vec![
            HeadBuffer { head: 7, buffer: 0 },
            HeadBuffer {
                head: u64::MAX,
                buffer: 3,
            },
        ];
        let timings = FrameTimings {
            queue_us: 1,
            compute_us: 2,
            total_us: 3,
            gpu_us: Some(4),
        };
        let resp = CrowdFrameResponse {
            format: Format::Q16,
            normals: true,
            buffers: parts
                .iter()
                .map(|p| FrameBuffer {
                    rig: p.rig.into(),
                    clip: p.clip.into(),
                    frame: p.frame,
                    lod: p.lod,
                    vertices: p.vertices,
                    quantization: p.quantization,
                    positions: Blob(p.positions.to_vec()),
                    normals: p.normals.as_ref().map(|n| Blob(n.to_vec())),
                })
                .collect(),
            heads: heads.clone(),
            timings,
        };
        let want = serde_json::to_vec(&resp).expect("serde");
        let got = encode_frame(&pool, Format::Q16, true, &parts, &heads, &timings);
        assert_eq!(
            String::from_utf8_lossy(&got),
            String::from_utf8_lossy(&want)
        );
        let ptr = got.as_ptr();
        drop(got);
        let again = encode_frame(&pool, Format::Q16, true, &parts, &heads, &timings);
        assert_eq!(again.as_ptr(), ptr, "the buffer came back from the pool");
        assert_eq!(&again[..], &want[..]);
        // No buffers, no heads.
        let empty = encode_frame(&pool, Format::F32, false, &[], &[], &timings);
        let want = serde_json::to_vec(&CrowdFrameResponse {
            format: Format::F32,
            normals: false,
            buffers: vec![],
            heads: vec![],
            timings,
        })
        .expect("serde");
        assert_eq!(&empty[..], &want[..]);
    }
}
