//! Session viewers that ask for fewer bytes: temporal residuals (`TickDelta`) and packed
//! (compressed) messages decode, through `crowdmorph_proto::StreamState`, to exactly the q16
//! buffers a plain q16 viewer of the same session gets, also across a patch, a LOD change and
//! a slow viewer's skipped ticks; keyframes come when the protocol says.

use std::collections::{BTreeMap, HashMap};
use std::time::Duration;

use crowdmorph_client::Method;
use crowdmorph_proto::{StreamMessage, StreamState};
use futures_util::SinkExt;
use serde_json::{Value, json};
use tokio_tungstenite::tungstenite::Message;

use super::TestServer;
use super::sessions::{Ws, call, connect, create, head, next_raw};

/// Per head id, its q16 positions and normals bytes.
type Decoded = BTreeMap<u64, (Vec<u8>, Option<Vec<u8>>)>;

/// A viewer's stream decoded tick by tick, with what its messages were.
#[derive(Default)]
struct Watch {
    state: StreamState,
    ticks: BTreeMap<u64, Decoded>,
    bytes: u64,
    packed: u64,
    deltas: u64,
    from_residuals: usize,
    /// Per head: the ticks at which it got a keyframe (temporal viewers).
    keyframes: HashMap<u64, Vec<u64>>,
    /// Per head: the ticks at which it got residuals.
    residual_ticks: HashMap<u64, Vec<u64>>,
}

impl Watch {
    fn take(&mut self, raw: &[u8]) {
        self.bytes += raw.len() as u64;
        let m: StreamMessage = crowdmorph_proto::wire::response_from_bincode(raw).expect("decodes");
        let inner = match m {
            StreamMessage::Packed(p) => {
                self.packed += 1;
                let bytes = p.unpack().expect("unpacks");
                crowdmorph_proto::wire::response_from_bincode(&bytes).expect("inner decodes")
            }
            m => m,
        };
        if let StreamMessage::Delta(d) = &inner {
            self.deltas += 1;
            for h in &d.heads {
                if let Some(&r) = d.residual.get(h.buffer as usize) {
                    let at = if r {
                        &mut self.residual_ticks
                    } else {
                        &mut self.keyframes
                    };
                    at.entry(h.head).or_default().push(d.tick);
                }
            }
        }
        let got = self.state.receive(raw).expect("applies");
        let crowdmorph_proto::Received::Vertices(a) = got else {
            panic!("asked for vertices")
        };
        self.from_residuals += a.from_residuals;
        let decoded: Decoded = self
            .state
            .layout()
            .iter()
            .filter_map(|h| {
                let b = self.state.buffer(h.head)?;
                Some((
                    h.head,
                    (
                        b.positions.0.clone(),
                        b.normals.as_ref().map(|n| n.0.clone()),
                    ),
                ))
            })
            .collect();
        self.ticks.insert(a.tick, decoded);
    }
}

fn crowd() -> Vec<Value> {
    let clips = ["talk", "smile", "surprise", "idle"];
    (0..10u64)
        .map(|i| {
            // Heads 0 and 4, 1 and 5 are clones; the rest play their own frames.
            let offset = if i < 8 { (i % 4) as i64 * 3 } else { i as i64 };
            head(i, clips[i as usize % 4], offset, [i as f32, 0.0, 0.0])
        })
        .collect()
}

/// Reads every viewer in turn until each has `ticks` ticks in common with the first.
async fn read_common(sockets: &mut [Ws], watches: &mut [Watch], ticks: usize) {
    for _ in 0..400 {
        for (ws, w) in sockets.iter_mut().zip(watches.iter_mut()) {
            let raw = next_raw(ws).await;
            w.take(&raw);
        }
        let plain = &watches[0].ticks;
        let common = |w: &Watch| w.ticks.keys().filter(|t| plain.contains_key(t)).count();
        if watches[1..].iter().all(|w| common(w) >= ticks) {
            return;
        }
    }
    panic!("the viewers never had {ticks} ticks in common");
}

fn assert_same(plain: &Watch, other: &Watch, what: &str) -> usize {
    let mut compared = 0;
    for (tick, decoded) in &other.ticks {
        if let Some(want) = plain.ticks.get(tick) {
            assert_eq!(
                decoded.keys().collect::<Vec<_>>(),
                want.keys().collect::<Vec<_>>(),
                "{what}: heads at tick {tick}"
            );
            for (head, got) in decoded {
                assert!(
                    got == &want[head],
                    "{what}: head {head} at tick {tick} differs"
                );
            }
            compared += 1;
        }
    }
    compared
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn temporal_and_packed_viewers_decode_exactly_what_a_q16_viewer_gets() {
    let server = TestServer::start(crowdmorph::server::ServerConfig::default()).await;
    let s = create(&server, json!({"fps": 15, "heads": crowd()})).await;
    let hellos = [
        json!({"format": "q16", "normals": true}),
        json!({"format": "q16", "normals": true, "temporal": true}),
        json!({"format": "q16", "normals": true, "temporal": true, "keyframe_every": 3,
               "compression": "zstd"}),
        json!({"format": "q16", "normals": true, "temporal": true, "compression": "deflate"}),
        json!({"format": "q16", "normals": true, "compression": "zstd"}),
    ];
    let mut sockets = Vec::new();
    for h in &hellos {
        sockets.push(connect(&server, &s.id, h.clone()).await);
    }
    let mut watches: Vec<Watch> = (0..hellos.len()).map(|_| Watch::default()).collect();
    read_common(&mut sockets, &mut watches, 6).await;

    // Mid-stream: a patch (a head removed, one changed, one added) and a LOD change for the
    // temporal viewers — keyframes for what changed, residuals again after.
    let path = format!("/v1/sessions/{}", s.id);
    let patch = json!({"remove": [9], "change": [{"head": 2, "clip": "talk"}],
                       "add": [head(20, "smile", 5, [0.0, 0.0, 3.0])]});
    let (status, body) = call(&server, Method::PATCH, &path, patch).await;
    assert_eq!(status, 200, "{body}");
    for ws in &mut sockets {
        ws.send(Message::text(r#"{"lod": 1}"#))
            .await
            .expect("update");
    }
    let before: Vec<usize> = watches.iter().map(|w| w.ticks.len()).collect();
    read_common(&mut sockets, &mut watches, 14).await;
    for (w, b) in watches.iter().zip(&before) {
        assert!(
            w.ticks.len() > b + 4,
            "every viewer read on after the changes"
        );
    }
    let last = watches[0].ticks.values().next_back().expect("ticks");
    assert!(
        last.contains_key(&20) && !last.contains_key(&9),
        "the patch applied"
    );

    let (plain, rest) = watches.split_first().expect("viewers");
    for (w, h) in rest.iter().zip(&hellos[1..]) {
        let compared = assert_same(plain, w, &h.to_string());
        assert!(compared >= 14, "{h}: {compared} ticks compared");
    }
    for (w, h) in rest.iter().zip(&hellos[1..]).take(3) {
        assert!(
            w.deltas > 0 && w.from_residuals > 0,
            "{h}: residuals were sent"
        );
    }
    assert_eq!(watches[4].deltas, 0, "a plain viewer gets no residuals");
    for (i, w) in watches.iter().enumerate() {
        let packed = hellos[i].get("compression").is_some();
        assert_eq!(w.packed > 0, packed, "{}", hellos[i]);
        if packed {
            assert_eq!(w.packed as usize, w.ticks.len(), "every message packed");
        }
    }
    // Keyframes at least every 3 ticks where asked: a head's residuals are never 3 or more
    // ticks after its last keyframe.
    let k3 = &watches[2];
    for (head, ticks) in &k3.residual_ticks {
        let keys = &k3.keyframes[head];
        for t in ticks {
            let last_key = keys
                .iter()
                .filter(|k| *k < t)
                .max()
                .expect("a keyframe first");
            assert!(
                t - last_key < 3,
                "head {head}: residuals at {t}, keyframe at {last_key}"
            );
        }
    }
    // The first messages are keyframes for every head, and heads added later start with one.
    for w in &watches[1..4] {
        let first = *w.ticks.keys().next().expect("ticks");
        for head in 0..9u64 {
            assert_eq!(w.keyframes[&head].first(), Some(&first), "head {head}");
        }
        assert!(
            !w.residual_ticks
                .get(&20)
                .is_some_and(|r| { r.first() < w.keyframes.get(&20).and_then(|k| k.first()) })
        );
    }
    // Fewer bytes: per tick, temporal + zstd against plain q16 (both with normals).
    let per_tick = |w: &Watch| w.bytes as f64 / w.ticks.len() as f64;
    assert!(
        per_tick(&watches[3]) < per_tick(&watches[0]) / 2.0,
        "temporal + deflate {} B/tick, q16 {} B/tick",
        per_tick(&watches[3]),
        per_tick(&watches[0])
    );
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_slow_temporal_viewer_skips_ticks_and_still_decodes_exactly() {
    let server = TestServer::start(crowdmorph::server::ServerConfig::default()).await;
    // Uncompressed residuals of 40 unique heads with normals are megabytes a message, so a
    // viewer that naps fills its socket's buffers and its outbox starts replacing messages.
    let clips = ["talk", "smile", "surprise", "idle"];
    let heads: Vec<Value> = (0..40u64)
        .map(|i| head(i, clips[i as usize % 4], i as i64 * 2, [i as f32, 0.0, 0.0]))
        .collect();
    let s = create(&server, json!({"fps": 30, "heads": heads})).await;
    let mut plain_ws = connect(&server, &s.id, json!({"format": "q16", "normals": true})).await;
    let mut slow_ws = connect(
        &server,
        &s.id,
        json!({"format": "q16", "normals": true, "temporal": true}),
    )
    .await;
    let mut slow = Watch::default();
    // The plain viewer reads everything in its own task; the slow one naps between reads, so
    // its outbox replaces messages it has not taken.
    let reader = tokio::spawn(async move {
        let mut w = Watch::default();
        for _ in 0..120 {
            let raw = next_raw(&mut plain_ws).await;
            w.take(&raw);
        }
        w
    });
    for _ in 0..20 {
        let raw = next_raw(&mut slow_ws).await;
        slow.take(&raw);
        tokio::time::sleep(Duration::from_millis(150)).await;
    }
    drop(slow_ws);
    let plain = reader.await.expect("the plain reader");
    let ticks: Vec<u64> = slow.ticks.keys().copied().collect();
    let skipped = ticks.windows(2).filter(|w| w[1] > w[0] + 1).count();
    assert!(skipped >= 5, "the slow viewer skipped ticks: {ticks:?}");
    assert!(slow.from_residuals > 0, "and still got residuals");
    let compared = assert_same(&plain, &slow, "slow viewer");
    assert!(compared >= 5, "{compared} ticks compared: {ticks:?}");
    let stats = super::sessions::info(&server, &s.id).await.stats;
    assert!(stats.messages_dropped > 0, "{stats:?}");
    server.stop().await;
}
