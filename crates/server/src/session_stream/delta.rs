//! What a viewer that asked for less gets: temporal residuals (`TickDelta`: each head's q16
//! buffer against the one this viewer last received for it, keyframes on join, on LOD or rig
//! change and every `keyframe_every` ticks) and compressed messages (`PackedMessage`, zstd or
//! zlib). `proto/README.md`, "The stream", has the bytes.
//!
//! The reference of a head is what the viewer's socket actually took (the outbox's baseline),
//! never a message an outbox replaced, so a viewer that skips ticks still decodes exactly. The
//! references outlive the tick, so they are copies of the outputs ([`Retained`]: the outputs are
//! views of a whole batch's buffer) charged to the queue memory like everything else.

use std::collections::HashMap;
use std::sync::Arc;

use bytes::Bytes;
use crowdmorph_proto::{HEAD_MISSING, HEAD_UNCHANGED, MessageEncoding};
use rayon::prelude::*;

use crate::admission::memory::{Charge, QueueMemory};
use crate::sessions::{Baseline, Encoded, HeadKey, HeadPrev, Retained};

/// Each temporal viewer's message, per head: `0` for a keyframe, else the address of the
/// reference it is coded against (two viewers whose heads have the same references get the
/// same bytes, so the fan-out's cache shares them).
pub(crate) type Bases = Vec<usize>;

/// The copies of a tick's outputs that temporal viewers keep, one per (group, job).
#[derive(Default)]
pub(crate) struct RetainedCache(HashMap<(usize, u32), Arc<Retained>>);

impl RetainedCache {
    /// Copies the outputs of the jobs in `jobs` (of group `g`) that are not kept yet, each
    /// charged first, on every core. `None` when the queue memory is full.
    fn fill(
        &mut self,
        memory: &QueueMemory,
        g: usize,
        jobs: impl Iterator<Item = u32>,
        outputs: &[Arc<crate::scheduler::JobOutput>],
    ) -> Option<()> {
        let mut todo = Vec::new();
        // One flag per job of the group (counted in the tick's bookkeeping, as its entries).
        let mut queued = vec![false; outputs.len()];
        for j in jobs {
            let out = outputs.get(j as usize)?;
            if self.0.contains_key(&(g, j)) || std::mem::replace(&mut queued[j as usize], true) {
                continue;
            }
            let bytes = out.positions.len() + out.normals.as_ref().map_or(0, |n| n.len());
            todo.push((j, memory.reserve(bytes as u64).ok()?));
        }
        let copies: Vec<(u32, Arc<Retained>)> = todo
            .into_par_iter()
            .map(|(j, charge)| {
                let out = &outputs[j as usize];
                let r = Retained {
                    positions: Bytes::copy_from_slice(&out.positions),
                    normals: out.normals.as_ref().map(|n| Bytes::copy_from_slice(n)),
                    _memory: charge,
                };
                (j, Arc::new(r))
            })
            .collect();
        for (j, r) in copies {
            self.0.insert((g, j), r);
        }
        Some(())
    }

    /// The kept copy of job `j` of group `g`, once [`RetainedCache::fill`] made it.
    fn get(&self, g: usize, j: u32) -> Option<Arc<Retained>> {
        self.0.get(&(g, j)).cloned()
    }
}

/// A temporal viewer's plan for one message: per head its base (see [`Bases`]) and the
/// reference a residual head is coded against, and the baseline's references once it is sent.
pub(crate) struct DeltaPlan {
    pub(crate) bases: Bases,
    pub(crate) refs: Vec<Option<Arc<Retained>>>,
    pub(crate) cur: Vec<Option<Arc<Retained>>>,
    pub(crate) after: Arc<HashMap<u64, HeadPrev>>,
}

/// What [`plan`] reads of the tick.
pub(crate) struct PlanInput<'a> {
    pub(crate) tick: u64,
    pub(crate) head_ids: &'a [u64],
    pub(crate) entries: &'a [u32],
    pub(crate) keys: &'a [HeadKey],
    pub(crate) every: u32,
    pub(crate) group: usize,
    pub(crate) outputs: &'a [Arc<crate::scheduler::JobOutput>],
}

/// Plans a temporal viewer's message against its baseline: a head is a keyframe when it has
/// no reference (the viewer's first message, a new head, one back from missing), when its LOD,
/// rig generation or length changed, or when its last keyframe is `every` ticks old. First
/// keyframes are staggered over the interval by head position. `None`: out of queue memory.
pub(crate) fn plan(
    memory: &QueueMemory,
    base: &Baseline,
    input: &PlanInput<'_>,
    retained: &mut RetainedCache,
) -> Option<DeltaPlan> {
    let n = input.entries.len();
    let every = u64::from(input.every.max(1));
    let mut plan = DeltaPlan {
        bases: vec![0; n],
        refs: vec![None; n],
        cur: vec![None; n],
        after: Arc::new(HashMap::new()),
    };
    let mut after = HashMap::with_capacity(n);
    let sent = input
        .entries
        .iter()
        .copied()
        .filter(|&e| e != HEAD_MISSING && e != HEAD_UNCHANGED);
    retained.fill(memory, input.group, sent, input.outputs)?;
    for i in 0..n {
        let id = input.head_ids[i];
        let prev = base.prev.get(&id);
        let j = match input.entries[i] {
            HEAD_MISSING => continue,
            HEAD_UNCHANGED => {
                if let Some(p) = prev {
                    after.insert(id, p.clone());
                }
                continue;
            }
            j => j,
        };
        let cur = retained.get(input.group, j)?;
        let key = &input.keys[i];
        let residual_of = prev.filter(|p| {
            p.lod == key.lod
                && p.generation == key.generation
                && p.data.positions.len() == cur.positions.len()
                && p.data.normals.as_ref().map(|b| b.len()) == cur.normals.as_ref().map(|b| b.len())
                && input.tick < p.key_tick.saturating_add(every)
        });
        let key_tick = match (residual_of, prev) {
            (Some(p), _) => p.key_tick,
            // A head seen before gets its keyframe now and counts from now.
            (None, Some(_)) => input.tick,
            // A first keyframe: staggered, so that the next ones do not all fall on one tick.
            (None, None) => input.tick.saturating_sub(i as u64 % every),
        };
        if let Some(p) = residual_of {
            plan.bases[i] = Arc::as_ptr(&p.data) as usize;
            plan.refs[i] = Some(p.data.clone());
        }
        after.insert(
            id,
            HeadPrev {
                data: cur.clone(),
                generation: key.generation,
                lod: key.lod,
                key_tick,
            },
        );
        plan.cur[i] = Some(cur);
    }
    plan.after = Arc::new(after);
    Some(plan)
}

/// Messages at least this large are compressed by zstd's own worker threads: one viewer's
/// message is otherwise compressed on one core, and for a crowd of large heads that is most
/// of a tick (ICT FaceKit, 200 heads a tick on two cores: 8.5 → 12 ticks/s with two workers).
/// Smaller messages are not worth the workers' start (zstd's jobs are at least 512 KiB).
const PARALLEL_ZSTD_BYTES: usize = 4 << 20;

/// Most worker threads one message's zstd may use.
const MAX_ZSTD_WORKERS: u32 = 4;

/// zstd worker threads for a message of at most `bound` compressed bytes: none below
/// [`PARALLEL_ZSTD_BYTES`] or on one core, else one per core up to [`MAX_ZSTD_WORKERS`].
fn zstd_workers(bound: usize) -> u32 {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get()) as u32;
    if bound < PARALLEL_ZSTD_BYTES || cores < 2 {
        0
    } else {
        cores.min(MAX_ZSTD_WORKERS)
    }
}

/// Bytes an encoder of `e` holds while it compresses a message of at most `bound` compressed
/// bytes (as for HTTP responses; with zstd's workers, their job buffers and contexts too:
/// measured in `tests`).
fn encoder_bytes(e: MessageEncoding, bound: usize) -> u64 {
    use crate::http::encoding::{Encoding, encoder_bytes};
    match e {
        MessageEncoding::Zstd => {
            encoder_bytes(Encoding::Zstd) + zstd_workers_bytes(zstd_workers(bound))
        }
        MessageEncoding::Deflate => encoder_bytes(Encoding::Gzip),
    }
}

/// What `workers` zstd workers add to a level-1 context: per worker its own context and a
/// job's input and output buffers (jobs of about 2 MiB at level 1, with a window of overlap),
/// plus the buffers zstd pools for jobs waiting to start (up to 2 × workers + 3). Measured
/// after 48 MiB through a context on a loaded machine (`tests`): 9–11 MiB with 1 worker,
/// 15 MiB with 2, 18–20 MiB with 3, 22–24 MiB with 4; this charges about twice that.
fn zstd_workers_bytes(workers: u32) -> u64 {
    if workers == 0 {
        0
    } else {
        (8 << 20) + u64::from(workers) * (10 << 20)
    }
}

/// Most bytes compressing `n` bytes can make (zstd's bound; deflate's stored blocks add 5
/// bytes per 16 KiB block, less than that).
fn packed_bound(n: usize) -> usize {
    zstd::zstd_safe::compress_bound(n).max(n + n / 16_384 * 5 + 64)
}

/// A message of `raw_len` bytes, given as its encoded pieces in order, compressed into a
/// `PackedMessage` (`StreamMessage` variant 3) as the pieces stream through the encoder: the
/// encoder's memory and the output's bound are charged first, the output kept. `None`: out of
/// queue memory, or the codec failed.
pub(crate) fn pack(
    memory: &QueueMemory,
    pieces: &[Bytes],
    raw_len: usize,
    e: MessageEncoding,
) -> Option<Encoded> {
    let bound = packed_bound(raw_len);
    let mut charge: Charge = memory
        .reserve(encoder_bytes(e, bound) + 2 * bound as u64 + 32)
        .ok()?;
    let data = compress(pieces, bound, e)?;
    let out = packed_bytes(e, raw_len, &data);
    drop(data);
    charge.keep(out.len() as u64);
    Some(Encoded {
        bytes: Bytes::from(out),
        _memory: Box::new(charge),
    })
}

/// The bincode of a `StreamMessage::Packed` of `data`, written without copying it twice.
fn packed_bytes(e: MessageEncoding, raw_len: usize, data: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(data.len() + 32);
    crowdmorph_store::codec::put_varint(&mut out, 3);
    crowdmorph_store::codec::put_varint(
        &mut out,
        match e {
            MessageEncoding::Zstd => 0,
            MessageEncoding::Deflate => 1,
        },
    );
    crowdmorph_store::codec::put_varint(&mut out, raw_len as u64);
    // The blob: an empty pad, then the data (nothing inside needs aligning).
    out.push(0);
    crowdmorph_store::codec::put_varint(&mut out, data.len() as u64);
    out.extend_from_slice(data);
    out
}

/// The pieces compressed as one stream (zstd level 1, or zlib at its fastest level) into
/// an output of at most `bound` bytes.
fn compress(pieces: &[Bytes], bound: usize, e: MessageEncoding) -> Option<Vec<u8>> {
    use std::io::Write;
    let out = Vec::with_capacity(bound);
    match e {
        MessageEncoding::Zstd => {
            let mut z = zstd::stream::write::Encoder::new(out, 1).ok()?;
            let workers = zstd_workers(bound);
            if workers > 0 {
                z.multithread(workers).ok()?;
            }
            for p in pieces {
                z.write_all(p).ok()?;
            }
            z.finish().ok()
        }
        MessageEncoding::Deflate => {
            let mut z = flate2::write::ZlibEncoder::new(out, flate2::Compression::fast());
            for p in pieces {
                z.write_all(p).ok()?;
            }
            z.finish().ok()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_charge_bounds_a_multithreaded_zstd_context() {
        use zstd::zstd_safe::{CCtx, CParameter, InBuffer, OutBuffer, zstd_sys::ZSTD_EndDirective};
        // A 48 MiB message of residual-like bytes (mostly small, some zeros) through a
        // level-1 context with the most workers the charge allows for.
        let mut x = 0u32;
        let chunk: Vec<u8> = (0..1 << 20)
            .map(|i| {
                x = x.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                if i % 3 == 0 { 0 } else { (x >> 28) as u8 }
            })
            .collect();
        for workers in 1..=MAX_ZSTD_WORKERS {
            let mut cctx = CCtx::create();
            cctx.set_parameter(CParameter::CompressionLevel(1))
                .expect("level");
            cctx.set_parameter(CParameter::NbWorkers(workers))
                .expect("zstd is built with its workers");
            let mut out = vec![0u8; 4 << 20];
            let mut most = 0;
            for _ in 0..48 {
                let mut input = InBuffer::around(&chunk);
                while input.pos() < chunk.len() {
                    let mut output = OutBuffer::around(&mut out[..]);
                    cctx.compress_stream2(
                        &mut output,
                        &mut input,
                        ZSTD_EndDirective::ZSTD_e_continue,
                    )
                    .expect("compress");
                }
                most = most.max(cctx.sizeof() as u64);
            }
            let charged =
                crate::http::encoding::encoder_bytes(crate::http::encoding::Encoding::Zstd)
                    + zstd_workers_bytes(workers);
            assert!(most <= charged, "{workers} workers: {most} > {charged}");
            assert!(
                most > charged / 8,
                "{workers} workers: {most}, charged {charged}"
            );
        }
    }

    #[test]
    fn large_messages_get_workers_on_several_cores() {
        assert_eq!(zstd_workers(PARALLEL_ZSTD_BYTES - 1), 0);
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get()) as u32;
        let big = zstd_workers(PARALLEL_ZSTD_BYTES);
        assert_eq!(
            big,
            if cores < 2 {
                0
            } else {
                cores.min(MAX_ZSTD_WORKERS)
            }
        );
        assert!(
            encoder_bytes(MessageEncoding::Zstd, PARALLEL_ZSTD_BYTES)
                >= encoder_bytes(MessageEncoding::Zstd, 0)
        );
    }

    #[test]
    fn a_packed_message_is_the_bincode_of_its_type_and_unpacks_to_the_message() {
        for e in [MessageEncoding::Zstd, MessageEncoding::Deflate] {
            let raw: Vec<u8> = (0..50_000u32).map(|i| (i % 251) as u8 / 3).collect();
            // In uneven pieces, as a message's encoder hands them over.
            let pieces: Vec<Bytes> = [0..7, 7..20_000, 20_000..50_000]
                .map(|r| Bytes::copy_from_slice(&raw[r]))
                .into();
            let data = compress(&pieces, packed_bound(raw.len()), e).expect("compresses");
            // A message large enough for zstd's workers round-trips too.
            let big: Vec<u8> = (0..(PARALLEL_ZSTD_BYTES + 12_345) as u32)
                .map(|i| (i % 251) as u8 / 7)
                .collect();
            let packed = compress(&[Bytes::from(big.clone())], packed_bound(big.len()), e)
                .expect("compresses");
            let unpacked = crowdmorph_proto::PackedMessage {
                encoding: e,
                length: big.len() as u64,
                data: crowdmorph_proto::Blob(packed),
            }
            .unpack()
            .expect("unpacks");
            assert!(unpacked == big, "{e:?}: a large message round-trips");
            assert!(data.len() < raw.len() / 4, "{e:?} {}", data.len());
            let message =
                crowdmorph_proto::StreamMessage::Packed(crowdmorph_proto::PackedMessage {
                    encoding: e,
                    length: raw.len() as u64,
                    data: crowdmorph_proto::Blob(data.clone()),
                });
            let mine = packed_bytes(e, raw.len(), &data);
            assert_eq!(
                crowdmorph_store::codec::to_wire(&message).expect("encodes"),
                mine
            );
            let crowdmorph_proto::StreamMessage::Packed(p) = message else {
                unreachable!()
            };
            assert_eq!(p.unpack().expect("unpacks"), raw);
            assert!(packed_bound(raw.len()) >= data.len());
        }
    }
}
