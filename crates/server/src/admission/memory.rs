//! The queue memory and charges that travel with what they pay for.
//!
//! [`QueueMemory`] is the server's `--queue-memory-bytes`: the output admitted crowd requests
//! hold (queued, computing, being sent), the request bodies being decoded, and what each
//! request keeps per head until its response is sent. A [`Charge`] is a piece of it; dropping
//! it gives the memory back. A [`Held`] is a value together with the charge that pays for it:
//! a decoded request body is only obtainable as one ([`decode_held`], and the
//! `Decoded` extractor of [`super`]), so a handler cannot forget to charge it; what a value
//! costs is its type's [`Priced`] footprint, stated next to the code that builds from it.

use std::sync::Arc;

use axum::body::Body;
use axum::http::{HeaderMap, StatusCode};
use serde::de::DeserializeOwned;
use tokio::sync::{OwnedSemaphorePermit, Semaphore};

use crate::http::negotiate::{self, Accept};
use crate::http::{ApiError, BodyLimits, body};
use crate::metrics::Metrics;

/// Bytes of one permit of the queue memory.
const UNIT: u64 = 1024;

/// The queue memory (`--queue-memory-bytes`), in KiB permits.
#[derive(Debug)]
pub struct QueueMemory {
    metrics: Arc<Metrics>,
    /// The permits and their count, shared with the charges that give them back.
    drain: Arc<Drain>,
}

/// A piece of the queue memory, given back when dropped (its permit first, then its
/// [`Drain`] looks at what is left).
#[derive(Debug)]
pub struct Charge(OwnedSemaphorePermit, DrainOnDrop);

/// Queue memory charged and given back since the last trim after which the queue draining
/// hands the freed memory back to the operating system: an overload (dozens of 16 MiB bodies
/// decoding, some at once, some one after another) leaves the process hundreds of MB larger
/// than it needs until the allocator is trimmed, whether or not the requests overlapped.
const DRAINED_VOLUME: u64 = 4 * crowdmorph_core::budget::TRIM_AFTER_BYTES;

/// What may still be charged for the queue to count as drained.
const DRAINED_USE: u64 = crowdmorph_core::budget::TRIM_AFTER_BYTES;

/// The queue memory's volume since the last trim it asked for, and the check made as each
/// charge is given back.
#[derive(Debug)]
struct Drain {
    semaphore: Arc<Semaphore>,
    units: u32,
    /// Bytes charged since the last trim this asked for.
    volume: std::sync::atomic::AtomicU64,
    /// A drain trim ran while requests were still finishing (up to [`DRAINED_USE`] charged):
    /// what they free after it is trimmed once the queue is empty.
    tail: std::sync::atomic::AtomicBool,
}

impl Drain {
    fn used(&self) -> u64 {
        let free = self.semaphore.available_permits() as u64;
        u64::from(self.units).saturating_sub(free) * UNIT
    }

    /// After a charge is given back: once at least [`DRAINED_VOLUME`] has gone through the
    /// queue and at most [`DRAINED_USE`] is still charged, the requests that held it are over:
    /// their memory goes back to the operating system
    /// ([`crowdmorph_core::budget::return_freed_memory_soon`], at most one trim every two seconds).
    ///
    /// The last requests of an overload end after that trim (measured: 30–100 MiB of a debug
    /// server's heap left behind after 32 bodies of 100,000 heads), so when it ran with some
    /// memory still charged, the charge that empties the queue asks for one more.
    fn released(&self) {
        use std::sync::atomic::Ordering;
        let volume = self.volume.load(Ordering::Acquire);
        let used = self.used();
        if volume >= DRAINED_VOLUME
            && used <= DRAINED_USE
            && self
                .volume
                .compare_exchange(volume, 0, Ordering::AcqRel, Ordering::Acquire)
                .is_ok()
        {
            self.tail.store(used > 0, Ordering::Release);
            crowdmorph_core::budget::return_freed_memory_soon();
        } else if used == 0 && self.tail.swap(false, Ordering::AcqRel) {
            crowdmorph_core::budget::return_freed_memory_soon();
        }
    }
}

/// Runs [`Drain::released`] when the charge holding it is dropped, after its permit.
#[derive(Debug)]
struct DrainOnDrop(Arc<Drain>);

impl Drop for DrainOnDrop {
    fn drop(&mut self) {
        self.0.released();
    }
}

impl Charge {
    /// Bytes it holds (whole KiB).
    pub fn bytes(&self) -> u64 {
        self.0.num_permits() as u64 * UNIT
    }

    /// Takes `other` into this charge: both are given back together.
    pub fn merge(&mut self, other: Charge) {
        let Charge(permit, _drain) = other;
        self.0.merge(permit);
    }

    /// Gives back all but `bytes` of it now.
    pub fn keep(&mut self, bytes: u64) {
        let keep = bytes.div_ceil(UNIT).max(1) as usize;
        if let Some(extra) = self.0.num_permits().checked_sub(keep).filter(|&n| n > 0) {
            drop(self.0.split(extra));
        }
    }
}

impl QueueMemory {
    /// `bytes` of queue memory (at least one KiB, at most what a semaphore counts); refusals
    /// are counted in `metrics`.
    pub fn new(bytes: usize, metrics: Arc<Metrics>) -> QueueMemory {
        let units = u32::try_from((bytes as u64 / UNIT).max(1))
            .unwrap_or(u32::MAX)
            .min(Semaphore::MAX_PERMITS as u32);
        let semaphore = Arc::new(Semaphore::new(units as usize));
        QueueMemory {
            drain: Arc::new(Drain {
                semaphore,
                units,
                volume: std::sync::atomic::AtomicU64::new(0),
                tail: std::sync::atomic::AtomicBool::new(false),
            }),
            metrics,
        }
    }

    /// The whole queue memory, bytes.
    pub fn limit(&self) -> u64 {
        u64::from(self.drain.units) * UNIT
    }

    /// Bytes charged now.
    pub fn used(&self) -> u64 {
        self.drain.used()
    }

    /// Takes `bytes`: 503 `queue_full` when the queue memory is full now, 413
    /// `queue_memory_exceeded` when `bytes` is more than all of it (taking all of it would let
    /// the holder allocate past the limit).
    pub fn reserve(&self, bytes: u64) -> Result<Charge, ApiError> {
        let units = bytes.div_ceil(UNIT).max(1);
        if units > u64::from(self.drain.units) {
            return Err(self.exceeded(bytes));
        }
        self.drain
            .semaphore
            .clone()
            .try_acquire_many_owned(units as u32)
            .map(|permit| {
                self.drain
                    .volume
                    .fetch_add(units * UNIT, std::sync::atomic::Ordering::AcqRel);
                Charge(permit, DrainOnDrop(self.drain.clone()))
            })
            .map_err(|_| {
                self.metrics.reject("queue_memory");
                ApiError::unavailable(
                    "queue_full",
                    "the server is holding as much output as it may; retry shortly",
                    1,
                )
            })
    }

    /// Whether `bytes` can ever be charged (not more than the whole queue memory).
    pub fn fits(&self, bytes: u64) -> bool {
        bytes.div_ceil(UNIT) <= u64::from(self.drain.units)
    }

    /// 413 for something that needs `bytes`, more than all of the queue memory: it could
    /// never be admitted (counted as a queue-memory rejection).
    pub fn exceeded(&self, bytes: u64) -> ApiError {
        self.metrics.reject("queue_memory");
        ApiError::new(
            StatusCode::PAYLOAD_TOO_LARGE,
            "queue_memory_exceeded",
            format!(
                "this needs {bytes} bytes of queue memory, more than the server's {} \
                 (--queue-memory-bytes)",
                self.limit()
            ),
        )
    }
}

/// A value and the charge that pays for it: the charge lives as long as the value is used
/// (moved along with it, into the response that sends it).
#[derive(Debug)]
pub struct Held<T> {
    value: T,
    charge: Charge,
}

impl<T> Held<T> {
    /// `value` paid for by `charge`.
    pub fn new(value: T, charge: Charge) -> Held<T> {
        Held { value, charge }
    }

    /// The value and its charge, apart: whoever takes the charge keeps the memory held.
    pub fn into_parts(self) -> (T, Charge) {
        (self.value, self.charge)
    }

    /// The charge.
    pub fn charge(&self) -> &Charge {
        &self.charge
    }
}

impl<T> std::ops::Deref for Held<T> {
    type Target = T;
    fn deref(&self) -> &T {
        &self.value
    }
}

/// What a decoded request costs while a request holds it: the decoded value's heap, and what
/// the handler builds from it per item until its response is sent. `accept` is the response's
/// encoding (a JSON answer holds more per head than a bincode one).
pub trait Priced {
    /// Bytes.
    fn price(&self, accept: Accept) -> u64;

    /// Bytes a body of `len` bytes may take while it is read and decoded into this type:
    /// [`decode_reservation`], unless the type is made of many small allocations.
    fn decoding(bincode: bool, len: u64) -> u64
    where
        Self: Sized,
    {
        decode_reservation(bincode, len)
    }
}

/// What a body made mostly of lists of names (a LOD request's order and pins, a load test's
/// rigs and clip mix) may take while decoded, besides [`decode_reservation`]: a `String` (24
/// bytes) per name, in a vector that may be twice as long as its names, for names as short as
/// 3 bytes of JSON (`"",`) or 1 byte of bincode (an empty name's length). Without it, 16 MiB
/// of `"",` decoded to 5.6 million strings that nothing counted.
pub fn names_reservation(bincode: bool, len: u64) -> u64 {
    decode_reservation(bincode, len).saturating_add(len.saturating_mul(if bincode {
        48
    } else {
        16
    }))
}

/// Heap bytes of a list of names: the vector's slots and each name's bytes.
pub fn names_bytes(names: &Vec<String>) -> u64 {
    names.capacity() as u64 * size_of::<String>() as u64
        + names.iter().map(|n| n.capacity() as u64).sum::<u64>()
}

/// Queue memory a request body of `declared` bytes reserves while it is read and decoded
/// (bincode or JSON): the body and what it decodes to. A head takes 104 bytes decoded (up to
/// twice that in a vector that grew by doubling, as past serde's cautious preallocation) from
/// at least 7 bytes of bincode or 20 of JSON (`{"head":0,"rig":""},`). `POST /v1/loadtest` counts the same for each of its
/// synthetic requests.
pub fn decode_reservation(bincode: bool, declared: u64) -> u64 {
    declared.saturating_mul(if bincode { 32 } else { 12 })
}

/// Reads and decodes a request body, charged: the body and what it decodes to are charged
/// while they are read ([`decode_reservation`]), then the decoded value keeps its
/// [`Priced::price`] (the rest given back, or more reserved).
pub async fn decode_held<T: DeserializeOwned + Priced>(
    memory: &QueueMemory,
    limits: BodyLimits,
    headers: &HeaderMap,
    body: Body,
) -> Result<Held<T>, ApiError> {
    let declared = body::declared_length(headers, limits.bytes);
    // A body whose decoding could need more than the whole queue memory (a large or unknown
    // length on a small queue) reserves all of it: the request-size limit bounds the rest, and
    // refusing would refuse every chunked body on such a server.
    let mut charge = memory
        .reserve(T::decoding(negotiate::is_bincode(headers), declared).min(memory.limit()))?;
    let bytes = body::read_body(headers, body, limits).await?;
    let value: T = negotiate::decode(headers, &bytes)?;
    drop(bytes);
    let need = value.price(Accept::of(headers));
    if !memory.fits(need) {
        // It could never be held, whatever else is queued: too large, not busy.
        return Err(memory.exceeded(need));
    }
    if need <= charge.bytes() {
        charge.keep(need);
    } else {
        charge.merge(memory.reserve(need - charge.bytes())?);
    }
    Ok(Held::new(value, charge))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn charges_are_whole_kib_and_given_back_when_dropped() {
        let q = QueueMemory::new(8 << 10, Arc::new(Metrics::default()));
        assert_eq!((q.limit(), q.used()), (8192, 0));
        let mut a = q.reserve(1).expect("a KiB");
        assert_eq!(a.bytes(), 1024);
        a.merge(q.reserve(3000).expect("three more"));
        assert_eq!((a.bytes(), q.used()), (4096, 4096));
        a.keep(1500);
        assert_eq!((a.bytes(), q.used()), (2048, 2048));
        let e = q.reserve(7000).expect_err("only 6 KiB free");
        assert_eq!((e.status.as_u16(), e.code), (503, "queue_full"));
        let e = q.reserve(9000).expect_err("more than all of it");
        assert_eq!((e.status.as_u16(), e.code), (413, "queue_memory_exceeded"));
        drop(a);
        assert_eq!(q.used(), 0);
        let held = Held::new(vec![1u8; 10], q.reserve(10).expect("charge"));
        assert_eq!((held.len(), q.used()), (10, 1024));
        let (v, c) = held.into_parts();
        drop(v);
        assert_eq!(
            q.used(),
            1024,
            "the charge outlives the value it was split from"
        );
        drop(c);
        assert_eq!(q.used(), 0);
    }
}
