//! Each [`Priced`] request type against what decoding it really allocates, measured by a
//! counting allocator on the test's own thread: the decoding reservation covers the body and
//! the peak of its decoding, and the price covers the decoded value's heap (plus what the
//! handler builds per item, which the price states next to the type). A price that under-counts
//! the real allocation, or a reservation that a decoding outgrows, fails here rather than in a
//! review.

#![allow(clippy::unwrap_used)]

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::collections::BTreeMap;

use crowdmorph_proto::{
    CrowdFrameRequest, Format, Head, HeadChange, LodLevelRequest, LodRequest, OutputOptions,
    Placement, RenderRequest, SessionHead, SessionPatch, SessionRequest,
};
use serde::Serialize;
use serde::de::DeserializeOwned;

use super::Priced;
use super::resolve::heads_held_bytes;
use crate::http::Accept;
use crate::loadtests::LoadtestRequest;
use crate::routes::render::RENDER_BYTES_PER_HEAD;
use crowdmorph_load::CrowdShape;

/// The system allocator, counting the bytes live on each thread and their peak.
struct Counting;

thread_local! {
    static LIVE: Cell<i64> = const { Cell::new(0) };
    static PEAK: Cell<i64> = const { Cell::new(0) };
}

fn note(delta: i64) {
    // `try_with`: allocations made while the thread's locals are torn down go uncounted.
    let _ = LIVE.try_with(|live| {
        let now = live.get() + delta;
        live.set(now);
        let _ = PEAK.try_with(|peak| peak.set(peak.get().max(now)));
    });
}

// SAFETY: every call is forwarded to `System` unchanged; only counters are updated.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // SAFETY: the caller's contract is `System`'s.
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            note(layout.size() as i64);
        }
        p
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        // SAFETY: as for `alloc`.
        let p = unsafe { System.alloc_zeroed(layout) };
        if !p.is_null() {
            note(layout.size() as i64);
        }
        p
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: as for `alloc`.
        unsafe { System.dealloc(ptr, layout) };
        note(-(layout.size() as i64));
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        // SAFETY: as for `alloc`.
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if !p.is_null() {
            note(new_size as i64 - layout.size() as i64);
        }
        p
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

/// What decoding `body` into `T` allocated on this thread: the bytes still live after it (the
/// value's heap, as the value is returned) and the peak above the start.
fn measure_decode<T: DeserializeOwned>(bincode: bool, body: &[u8]) -> (T, u64, u64) {
    let mut headers = axum::http::HeaderMap::new();
    let ct = if bincode {
        crowdmorph_proto::CONTENT_TYPE_BINCODE
    } else {
        crowdmorph_proto::CONTENT_TYPE_JSON
    };
    headers.insert(
        axum::http::header::CONTENT_TYPE,
        axum::http::HeaderValue::from_static(ct),
    );
    let start = LIVE.with(Cell::get);
    PEAK.with(|p| p.set(start));
    let value: T = crate::http::negotiate::decode(&headers, body).unwrap();
    let live = LIVE.with(Cell::get) - start;
    let peak = PEAK.with(Cell::get) - start;
    (value, live.max(0) as u64, peak.max(0) as u64)
}

/// Decodes `value`'s JSON and bincode bodies and checks the type's reservation and price
/// against what decoding allocated; returns, per encoding, the value's real heap and its
/// price, for the type's own checks.
fn check<T: Serialize + DeserializeOwned + Priced>(what: &str, value: &T) -> Vec<(u64, u64)> {
    let json = serde_json::to_vec(value).unwrap();
    let bincode = crowdmorph_store::codec::to_wire(value).unwrap();
    let mut seen = Vec::new();
    for (is_bincode, body) in [(false, &json), (true, &bincode)] {
        let (decoded, live, peak) = measure_decode::<T>(is_bincode, body);
        let len = body.len() as u64;
        // What the queue memory really takes: its charges are whole KiB.
        let reserved = T::decoding(is_bincode, len).div_ceil(1024) * 1024;
        eprintln!(
            "{what} (bincode {is_bincode}): body {len}, decode peak {peak}, reserved {reserved}, \
             value {live}, price {:?}",
            [false, true].map(|b| decoded.price(Accept { bincode: b }))
        );
        assert!(
            len + peak <= reserved,
            "{what} (bincode {is_bincode}): a {len}-byte body peaked at {peak} bytes while \
             decoded, past its reservation of {reserved}"
        );
        for accept in [Accept { bincode: false }, Accept { bincode: true }] {
            let price = decoded.price(accept);
            seen.push((live, price));
        }
    }
    seen
}

/// Heads of every kind: plain, blended (every third), live by name (every fifth) and dense
/// (every seventh), some with a near-clone tolerance (every eleventh).
fn heads(n: usize) -> Vec<Head> {
    use crowdmorph_proto::{BlendLayer, LiveWeights};
    (0..n)
        .map(|i| {
            let mut h = Head {
                head: i as u64,
                rig: "default-head".into(),
                clip: if i % 2 == 0 { "talk" } else { "blink" }.into(),
                frame: i as i64,
                lod: 0,
                ..Default::default()
            };
            if i % 3 == 1 {
                h.blend = vec![BlendLayer {
                    clip: "smile".into(),
                    frame: 2,
                    t: 0.5,
                }];
            }
            if i % 5 == 2 {
                h.clip.clear();
                h.weights = Some(Box::new(LiveWeights::Named(vec![
                    ("jawOpen".into(), 0.5),
                    ("eyeBlinkLeft".into(), 1.0),
                ])));
            } else if i % 7 == 3 {
                h.clip.clear();
                h.weights = Some(Box::new(LiveWeights::Dense(vec![0.25; 51])));
            }
            if i % 11 == 4 {
                // A near-clone: an inline f32, nothing more to decode.
                h.tolerance = Some(0.001);
            }
            h
        })
        .collect()
}

#[test]
fn a_crowd_frame_is_priced_at_its_decoded_heads_and_what_is_built_per_head() {
    for n in [1, 37, 1000] {
        let req = CrowdFrameRequest {
            heads: heads(n),
            output: OutputOptions {
                normals: false,
                format: Format::F16,
            },
            wrap: true,
        };
        for (live, price) in check("crowd frame", &req) {
            assert!(
                live <= price,
                "{n} heads: {live} bytes decoded, priced at {price}"
            );
            // The price is the decoded heads (at least their `size_of`) and a stated per-head
            // share of what the handler builds: no more.
            let per_head =
                (size_of::<u32>() + size_of::<crowdmorph_proto::HeadBuffer>() + 64) as u64;
            assert!(price >= (n * size_of::<Head>()) as u64);
            assert!(
                price <= live + n as u64 * per_head,
                "{n} heads: priced at {price}, more than {live} decoded and {per_head} a head"
            );
        }
    }
}

#[test]
fn a_render_is_priced_at_its_heads_placements_and_scene() {
    let n = 500;
    let req = RenderRequest {
        heads: heads(n),
        wrap: true,
        placements: Some(
            (0..n)
                .map(|i| Placement {
                    head: i as u64,
                    position: [i as f32, 0.0, 0.0],
                    yaw: 0.5,
                    scale: 1.0,
                })
                .collect(),
        ),
        camera: None,
        image: None,
    };
    for (live, price) in check("render", &req) {
        assert!(live <= price, "{live} bytes decoded, priced at {price}");
        assert!(price >= n as u64 * (size_of::<Head>() + size_of::<Placement>()) as u64);
        assert!(price >= heads_held_bytes(&req.heads, RENDER_BYTES_PER_HEAD));
    }
}

#[test]
fn a_lod_request_is_priced_at_its_lists() {
    let names = |k: usize, p: &str| (0..k).map(|i| format!("{p}{i}")).collect::<Vec<_>>();
    let req = LodRequest {
        method: None,
        order: Some(names(400, "target_")),
        pinned: names(40, "eye_blink_"),
        levels: Some(
            (0..5)
                .map(|i| LodLevelRequest {
                    shapes: 400 >> i,
                    mesh: None,
                })
                .collect(),
        ),
        mesh_fractions: vec![0.5, 0.25, 0.1],
    };
    for (live, price) in check("lod", &req) {
        assert!(live <= price, "{live} bytes decoded, priced at {price}");
        assert!(price >= 440 * size_of::<String>() as u64);
    }
}

#[test]
fn a_loadtest_is_priced_at_its_crowds_lists() {
    let req = LoadtestRequest {
        rate: 100.0,
        duration_s: 1.0,
        warmup_s: 0.0,
        concurrency: 4,
        crowd: CrowdShape {
            rigs: (0..64).map(|i| format!("rig-{i}")).collect(),
            clips: (0..64).map(|i| (format!("clip-{i}"), 1.0)).collect(),
            lods: (0..8).map(|l| (l, 1.0)).collect::<BTreeMap<u32, f64>>(),
            ..CrowdShape::default()
        },
    };
    for (live, price) in check("loadtest", &req) {
        assert!(live <= price, "{live} bytes decoded, priced at {price}");
        assert!(price >= 64 * size_of::<String>() as u64);
    }
}

/// Sessions are priced at 0 once decoded: their heads are copied into the session's own lists,
/// charged as the answer that lists them, and the request is dropped. Only the decoding is
/// charged, so it must cover the decoded value too.
#[test]
fn a_session_and_its_patch_are_charged_while_decoded() {
    let session_heads = |n: usize| {
        (0..n)
            .map(|i| SessionHead {
                head: i as u64,
                rig: "default-head".into(),
                clip: "talk".into(),
                offset: i as i64,
                position: [0.0; 3],
                yaw: 0.0,
                scale: 1.0,
                graph: None,
                joints: Default::default(),
                layers: Vec::new(),
                clamp: None,
                live: None,
                alive: None,
            })
            .collect::<Vec<_>>()
    };
    let req = SessionRequest {
        fps: 30.0,
        wrap: true,
        idle_timeout_s: 60,
        heads: session_heads(800),
        alive: None,
    };
    for (live, price) in check("session", &req) {
        assert_eq!(price, 0);
        assert!(live > 0);
    }
    let patch = SessionPatch {
        remove: (0..300).collect(),
        change: (0..300)
            .map(|i| HeadChange {
                head: i,
                clip: Some("blink".into()),
                offset: None,
                position: Some([1.0, 0.0, 0.0]),
                yaw: None,
                scale: None,
                node: None,
                joints: None,
                layers: None,
                clamp: None,
                live: None,
                alive: None,
            })
            .collect(),
        add: session_heads(300),
        alive: None,
    };
    for (live, price) in check("session patch", &patch) {
        assert_eq!(price, 0);
        assert!(live > 0);
    }
}
