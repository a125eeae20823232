//! Crowd sessions over real sockets: the REST side (`/v1/sessions`) and the WebSocket stream.
//! Viewers are tokio-tungstenite clients that decode each binary message with the proto crate
//! and keep every head's vertices as a viewer would (applying "unchanged" and layouts), so the
//! tests check what a viewer ends up drawing, not just message counts.

use crate::util::gpu_test;
use std::collections::HashMap;
use std::time::Duration;

use bytes::Bytes;
use crowdmorph::server::ServerConfig;
use crowdmorph::server::sessions::SessionLimits;
use crowdmorph_client::Method;
use crowdmorph_proto::{
    CrowdFrameRequest, Format, HEAD_MISSING, HEAD_UNCHANGED, Head, OutputOptions, SessionInfo,
    StreamMessage, TickVertices,
};
use futures_util::{SinkExt, StreamExt};
use serde_json::{Value, json};
use tokio_tungstenite::tungstenite::Message;

use super::{TestServer, positions_f32};

pub(super) type Ws =
    tokio_tungstenite::WebSocketStream<tokio_tungstenite::MaybeTlsStream<tokio::net::TcpStream>>;

pub(super) const READ: Duration = Duration::from_secs(20);

pub(super) async fn call(
    server: &TestServer,
    method: Method,
    path: &str,
    body: Value,
) -> (u16, Value) {
    let bytes = if body.is_null() {
        Bytes::new()
    } else {
        Bytes::from(body.to_string())
    };
    let ct = (!body.is_null()).then_some("application/json");
    let reply = server
        .client
        .send(method, path, ct, None, bytes)
        .await
        .expect("request");
    let value = if reply.body.is_empty() {
        Value::Null
    } else {
        serde_json::from_slice(&reply.body).expect("JSON body")
    };
    (reply.status, value)
}

pub(super) async fn create(server: &TestServer, body: Value) -> SessionInfo {
    let (status, v) = call(server, Method::POST, "/v1/sessions", body).await;
    assert_eq!(status, 201, "{v}");
    serde_json::from_value(v).expect("SessionInfo")
}

pub(super) async fn info(server: &TestServer, id: &str) -> SessionInfo {
    let (status, v) = call(
        server,
        Method::GET,
        &format!("/v1/sessions/{id}"),
        Value::Null,
    )
    .await;
    assert_eq!(status, 200, "{v}");
    serde_json::from_value(v).expect("SessionInfo")
}

pub(super) fn head(id: u64, clip: &str, offset: i64, position: [f32; 3]) -> Value {
    json!({"head": id, "rig": "default-head", "clip": clip, "offset": offset, "position": position})
}

/// `n` heads playing "idle", ids 0.., on a grid of 100 per row one metre apart.
fn idle_grid(n: u64) -> Vec<Value> {
    (0..n)
        .map(|i| head(i, "idle", 0, [(i % 100) as f32, 0.0, (i / 100) as f32]))
        .collect()
}

pub(super) async fn connect(server: &TestServer, id: &str, hello: Value) -> Ws {
    let url = format!("ws://{}/v1/sessions/{id}/stream", server.addr);
    let (mut ws, _) = tokio_tungstenite::connect_async(url)
        .await
        .expect("connect");
    ws.send(Message::text(hello.to_string()))
        .await
        .expect("hello");
    ws
}

/// The next binary message; panics on a close or a timeout.
pub(super) async fn next_raw(ws: &mut Ws) -> Bytes {
    loop {
        let msg = tokio::time::timeout(READ, ws.next())
            .await
            .expect("a tick within the timeout")
            .expect("stream open")
            .expect("message");
        match msg {
            Message::Binary(b) => return b,
            Message::Close(c) => panic!("closed: {c:?}"),
            _ => {}
        }
    }
}

/// The next tick message; panics on a close or a timeout.
pub(super) async fn next_tick(ws: &mut Ws) -> TickVertices {
    let b = next_raw(ws).await;
    let m: StreamMessage =
        crowdmorph_proto::wire::response_from_bincode(&b).expect("StreamMessage");
    match m {
        StreamMessage::Vertices(v) => v,
        StreamMessage::Frame(_) => panic!("asked for vertices, got a frame"),
        StreamMessage::Delta(_) | StreamMessage::Packed(_) | StreamMessage::Layers(_) => {
            panic!("asked for plain vertices, got residuals or a packed message")
        }
        StreamMessage::Poses(_) => panic!("asked for vertices, got poses"),
    }
}

/// The close frame the server sends next (skipping data messages).
pub(super) async fn next_close(ws: &mut Ws) -> (u16, String) {
    loop {
        let msg = tokio::time::timeout(READ, ws.next())
            .await
            .expect("a close within the timeout");
        match msg {
            Some(Ok(Message::Close(Some(c)))) => return (u16::from(c.code), c.reason.to_string()),
            Some(Ok(Message::Close(None))) | None => return (0, String::new()),
            Some(Ok(_)) => {}
            Some(Err(e)) => panic!("stream error before a close: {e}"),
        }
    }
}

/// What a viewer draws: each head's positions, as f32, after applying messages in order.
#[derive(Default)]
pub(super) struct View {
    layout: Vec<u64>,
    pub(super) heads: HashMap<u64, Vec<f32>>,
    pub(super) lods: HashMap<u64, u32>,
}

impl View {
    pub(super) fn apply(&mut self, t: &TickVertices) {
        if let Some(l) = &t.layout {
            self.layout = l.iter().map(|h| h.head).collect();
        }
        assert_eq!(
            t.heads.len(),
            self.layout.len(),
            "one entry per layout head"
        );
        for (h, id) in t.heads.iter().zip(&self.layout) {
            assert_eq!(h.head, *id, "heads in layout order");
            match h.buffer {
                HEAD_UNCHANGED => assert!(
                    self.heads.contains_key(id),
                    "head {id} unchanged before it had a buffer"
                ),
                HEAD_MISSING => {
                    self.heads.remove(id);
                }
                b => {
                    let buf = &t.buffers[b as usize];
                    self.heads.insert(*id, positions_f32(t.format, buf));
                    self.lods.insert(*id, buf.lod);
                }
            }
        }
    }
}

fn config() -> ServerConfig {
    ServerConfig::default()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_viewers_with_different_cameras_get_the_same_vertices_for_shared_jobs() {
    let server = TestServer::start(config()).await;
    let rig = server.client.rig("default-head").await.expect("rig");
    let talk_fps = rig
        .clips
        .iter()
        .find(|c| c.name == "talk")
        .expect("talk")
        .fps;
    // Six heads, three of them clones of others (same clip and offset): four blends a tick.
    let s = create(
        &server,
        json!({"fps": 15, "heads": [
            head(1, "talk", 0, [0.0, 0.0, 0.0]), head(2, "talk", 0, [1.0, 0.0, 0.0]),
            head(3, "smile", 7, [2.0, 0.0, 0.0]), head(4, "smile", 7, [3.0, 0.0, 0.0]),
            head(5, "talk", 3, [4.0, 0.0, 0.0]), head(6, "surprise", 0, [5.0, 0.0, 0.0])]}),
    )
    .await;
    let cam_a = json!({"position": [0, 0, 5], "target": [0, 0, 0]});
    let cam_b = json!({"position": [8, 3, -4], "target": [2, 0, 0], "fov_y": 50});
    let mut a = connect(&server, &s.id, json!({"format": "f32", "camera": cam_a})).await;
    let mut b = connect(&server, &s.id, json!({"format": "f32", "camera": cam_b})).await;
    let (mut va, mut vb) = (View::default(), View::default());
    let mut by_tick_a: HashMap<u64, HashMap<u64, Vec<f32>>> = HashMap::new();
    let mut by_tick_b: HashMap<u64, HashMap<u64, Vec<f32>>> = HashMap::new();
    for _ in 0..12 {
        let ta = next_tick(&mut a).await;
        va.apply(&ta);
        by_tick_a.insert(ta.tick, va.heads.clone());
        let tb = next_tick(&mut b).await;
        vb.apply(&tb);
        by_tick_b.insert(tb.tick, vb.heads.clone());
    }
    let common: Vec<u64> = by_tick_a
        .keys()
        .filter(|t| by_tick_b.contains_key(t))
        .copied()
        .collect();
    assert!(
        common.len() >= 6,
        "the viewers saw the same ticks: {common:?}"
    );
    for t in &common {
        assert_eq!(
            by_tick_a[t], by_tick_b[t],
            "tick {t}: both viewers draw the same vertices"
        );
    }
    // Clones share their blend: heads 1 and 2, 3 and 4 have identical vertices.
    let last = &by_tick_a[common.iter().max().expect("a tick")];
    assert_eq!(last[&1], last[&2]);
    assert_eq!(last[&3], last[&4]);
    assert_ne!(last[&1], last[&5], "offset 3 plays another frame");

    // The vertices are what a crowd-frame request for the same frame gets.
    let t = *common.iter().max().expect("a tick");
    let frame = |offset: i64| offset + (((t - 1) as f64) * f64::from(talk_fps) / 15.0) as i64;
    let req = CrowdFrameRequest {
        heads: vec![
            Head {
                head: 1,
                rig: "default-head".into(),
                clip: "talk".into(),
                frame: frame(0),
                lod: 0,
                ..Default::default()
            },
            Head {
                head: 5,
                rig: "default-head".into(),
                clip: "talk".into(),
                frame: frame(3),
                lod: 0,
                ..Default::default()
            },
        ],
        output: OutputOptions {
            normals: false,
            format: Format::F32,
        },
        wrap: true,
    };
    let (resp, _) = server
        .client
        .crowd_frame(&req, crowdmorph_client::Encoding::Bincode)
        .await
        .expect("crowd frame");
    assert_eq!(
        by_tick_a[&t][&1],
        positions_f32(Format::F32, &resp.buffers[0])
    );
    assert_eq!(
        by_tick_a[&t][&5],
        positions_f32(Format::F32, &resp.buffers[resp.heads[1].buffer as usize])
    );

    // Two viewers at the same LOD cost one blend per unique job: 4 a tick, not 8.
    drop(a);
    drop(b);
    let i = info(&server, &s.id).await;
    assert!(i.stats.ticks >= 12, "{:?}", i.stats);
    assert!(
        i.stats.jobs <= 4 * i.stats.ticks,
        "jobs per tick are shared by viewers: {:?}",
        i.stats
    );
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn heads_whose_frame_did_not_change_are_sent_as_unchanged() {
    let server = TestServer::start(config()).await;
    let rig = server.client.rig("default-head").await.expect("rig");
    let fps = rig
        .clips
        .iter()
        .find(|c| c.name == "idle")
        .expect("idle")
        .fps;
    // Ticks at twice the clip's rate: every clip frame lasts two ticks.
    let s = create(
        &server,
        json!({"fps": 2.0 * fps, "heads": [head(1, "idle", 0, [0.0, 0.0, 0.0]), head(2, "idle", 0, [1.0, 0.0, 0.0])]}),
    )
    .await;
    let mut ws = connect(&server, &s.id, json!({"format": "q16"})).await;
    let first = next_tick(&mut ws).await;
    assert!(
        first.layout.is_some(),
        "the first message carries the layout"
    );
    assert_eq!(first.buffers.len(), 1, "two clones, one buffer");
    let mut unchanged = 0;
    let mut changed = 0;
    let mut prev = first.tick;
    for _ in 0..10 {
        let t = next_tick(&mut ws).await;
        assert!(t.layout.is_none(), "the layout did not change");
        assert!(t.tick > prev);
        if t.tick == prev + 1 {
            if t.heads.iter().all(|h| h.buffer == HEAD_UNCHANGED) {
                assert!(t.buffers.is_empty());
                unchanged += 1;
            } else {
                changed += 1;
            }
        }
        prev = t.tick;
    }
    assert!(
        unchanged >= 2 && changed >= 2,
        "unchanged {unchanged}, changed {changed}"
    );
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn lod_by_distance_gives_far_heads_fewer_shapes() {
    let server = TestServer::start(config()).await;
    let rig = server.client.rig("default-head").await.expect("rig");
    assert!(rig.lod.levels.len() >= 3, "the embedded rig has LOD levels");
    let s = create(
        &server,
        json!({"heads": [head(1, "talk", 0, [0.0, 0.0, 0.0]), head(2, "talk", 0, [0.0, 0.0, -30.0]),
                         head(3, "talk", 0, [0.0, 0.0, -300.0])]}),
    )
    .await;
    let hello = json!({"format": "f16",
        "camera": {"position": [0, 0, 5], "target": [0, 0, 0]},
        "lod": {"by_distance": [[0, 0], [20, 1], [100, 99]]}});
    let mut ws = connect(&server, &s.id, hello).await;
    let mut v = View::default();
    v.apply(&next_tick(&mut ws).await);
    let last = rig.lod.levels.len() as u32 - 1;
    assert_eq!(v.lods[&1], 0);
    assert_eq!(v.lods[&2], 1);
    assert_eq!(v.lods[&3], last, "levels past the rig's last are clamped");
    assert!(rig.lod.levels[1].shapes < rig.lod.levels[0].shapes);
    // Moving the camera next to the far head swaps the levels from the next tick on.
    ws.send(Message::text(
        json!({"camera": {"position": [0, 0, -295], "target": [0, 0, -300]}}).to_string(),
    ))
    .await
    .expect("update");
    let mut swapped = false;
    for _ in 0..20 {
        v.apply(&next_tick(&mut ws).await);
        if v.lods[&3] == 0 && v.lods[&1] == last {
            swapped = true;
            break;
        }
    }
    assert!(swapped, "levels follow the camera: {:?}", v.lods);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stalled_viewer_costs_another_almost_nothing_and_memory_stays_bounded() {
    let server = TestServer::start(config()).await;
    // Many unique heads with normals in f32: messages big enough to fill the stalled
    // viewer's socket buffers within a few seconds.
    let heads: Vec<Value> = (0..24)
        .map(|i| {
            let clip = ["idle", "talk", "smile", "surprise"][i % 4];
            head(i as u64, clip, (i * 5) as i64, [i as f32, 0.0, 0.0])
        })
        .collect();
    let s = create(&server, json!({"fps": 30, "heads": heads})).await;
    let hello = json!({"format": "f32", "normals": true});
    // The stalled viewer sends its hello and never reads again.
    let stalled = connect(&server, &s.id, hello.clone()).await;
    let mut good = connect(&server, &s.id, hello).await;
    let mut v = View::default();
    let first = next_tick(&mut good).await;
    v.apply(&first);
    let before = info(&server, &s.id).await.stats;
    let started = std::time::Instant::now();
    let mut delivered = 0u64;
    let mut last_tick = first.tick;
    while started.elapsed() < Duration::from_secs(10) {
        let t = next_tick(&mut good).await;
        v.apply(&t);
        assert!(t.tick > last_tick);
        last_tick = t.tick;
        delivered += 1;
    }
    let after = info(&server, &s.id).await.stats;
    let computed = after.ticks - before.ticks;
    assert!(computed >= 30, "the session ticked: {after:?}");
    // Ticks computed in the window that the good viewer did not get (allowing the one in
    // flight at each end).
    let missed = computed.saturating_sub(delivered + 2);
    assert!(
        (missed as f64) < 0.05 * computed as f64,
        "the good viewer got {delivered} of {computed} ticks ({after:?})"
    );
    assert!(
        after.messages_dropped > before.messages_dropped,
        "the stalled viewer's outbox replaced messages it could not send: {after:?}"
    );
    // What the server holds for the viewers is bounded: at most a queued and an in-flight
    // message each (plus the tick being computed), far below what 10 s of ticks would be.
    let page = server.client.metrics().await.expect("metrics");
    let held = crowdmorph_client::metric(&page, "crowdmorph_queue_memory_bytes").expect("gauge");
    let message = 24.0 * 2.0 * 3.0 * 4.0 * first_vertex_count(&first) as f64;
    assert!(
        held <= 6.0 * message + (1 << 20) as f64,
        "queue memory {held} bytes with messages of about {message}"
    );
    drop(stalled);
    server.stop().await;
}

fn first_vertex_count(t: &TickVertices) -> u32 {
    t.buffers.first().map_or(0, |b| b.vertices)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn idle_sessions_end() {
    let server = TestServer::start(config()).await;
    let s = create(
        &server,
        json!({"fps": 20, "idle_timeout_s": 1, "heads": [head(1, "talk", 0, [0.0, 0.0, 0.0])]}),
    )
    .await;
    // A viewer keeps it alive; after it leaves, the session ends within its timeout.
    let mut ws = connect(&server, &s.id, json!({})).await;
    for _ in 0..30 {
        next_tick(&mut ws).await;
    }
    assert_eq!(info(&server, &s.id).await.viewers, 1);
    ws.close(None).await.expect("close");
    drop(ws);
    let mut gone = false;
    for _ in 0..60 {
        tokio::time::sleep(Duration::from_millis(100)).await;
        let (status, _) = call(
            &server,
            Method::GET,
            &format!("/v1/sessions/{}", s.id),
            Value::Null,
        )
        .await;
        if status == 404 {
            gone = true;
            break;
        }
    }
    assert!(gone, "the idle session ended");
    let page = server.client.metrics().await.expect("metrics");
    assert_eq!(
        crowdmorph_client::metric(&page, "crowdmorph_sessions"),
        Some(0.0)
    );
    server.stop().await;
}

/// What README says of `tick` and `stats.ticks`: the clock counts every tick whose time came,
/// the stats only the ticks computed for viewers; so without a viewer `tick` runs and
/// `stats.ticks` stays 0, and later the ticks without a viewer stay the difference (at least).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tick_counts_every_tick_and_stats_ticks_only_those_computed_for_viewers() {
    let server = TestServer::start(config()).await;
    let s = create(
        &server,
        json!({"fps": 20, "heads": [head(1, "talk", 0, [0.0, 0.0, 0.0])]}),
    )
    .await;
    let mut idle = info(&server, &s.id).await;
    for _ in 0..500 {
        if idle.tick >= 10 {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
        idle = info(&server, &s.id).await;
    }
    assert!(idle.tick >= 10, "the clock runs without viewers: {idle:?}");
    // (A tick that came late on a busy machine would count as skipped: not checked here.)
    assert_eq!(
        (idle.stats.ticks, idle.stats.jobs),
        (0, 0),
        "nothing is computed without viewers"
    );
    let mut ws = connect(&server, &s.id, json!({})).await;
    for _ in 0..3 {
        next_tick(&mut ws).await;
    }
    let watched = info(&server, &s.id).await;
    assert!(watched.stats.ticks >= 3, "{:?}", watched.stats);
    // tick = ticks + skipped + ticks without viewers, less skipped ticks counted ahead.
    assert!(
        watched.tick >= watched.stats.ticks + idle.tick,
        "{} < {} + {}",
        watched.tick,
        watched.stats.ticks,
        idle.tick
    );
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_hellos_and_updates_close_with_1008_and_a_reason() {
    let server = TestServer::start(config()).await;
    let s = create(
        &server,
        json!({"heads": [head(1, "talk", 0, [0.0, 0.0, 0.0])]}),
    )
    .await;
    let url = format!("ws://{}/v1/sessions/{}/stream", server.addr, s.id);
    let cases: Vec<(Message, &str)> = vec![
        (Message::text("hello?"), "bad hello"),
        (Message::text(r#"{"format": "f64"}"#), "format"),
        // A residual format sessions cannot send is refused with why, not swapped.
        (Message::text(r#"{"format": "q16r"}"#), "q16r"),
        (
            Message::text(r#"{"format": "f32", "temporal": true}"#),
            "temporal residuals need format q16",
        ),
        (
            Message::text(r#"{"format": "q16", "temporal": true, "output": "frames"}"#),
            "not output frames",
        ),
        (
            Message::text(r#"{"output": "frames", "compression": "zstd"}"#),
            "images are already compressed",
        ),
        (
            Message::text(r#"{"format": "q16", "temporal": true, "keyframe_every": 0}"#),
            "keyframe_every must be 1..=3600",
        ),
        (
            Message::text(r#"{"format": "q16", "keyframe_every": 5}"#),
            "keyframe_every is for temporal viewers",
        ),
        (Message::text(r#"{"compression": "br"}"#), "compression"),
        (Message::text(r#"{"zoom": 2}"#), "zoom"),
        (
            Message::text(r#"{"camera": {"position": [0,0,1], "target": [0,0,1]}}"#),
            "camera",
        ),
        (
            Message::text(r#"{"lod": {"by_distance": [[10, 1], [5, 2]]}}"#),
            "ascending",
        ),
        (Message::binary(vec![1u8, 2, 3]), "JSON hello"),
        (
            Message::text(r#"{"tolerance": -0.001}"#),
            "tolerance -0.001",
        ),
        (Message::text(r#"{"tolerance": 0.5}"#), "tolerance 0.5"),
        (
            Message::text(r#"{"output": "frames", "tolerance": 0.001}"#),
            "images are drawn from exact poses",
        ),
        (
            Message::text(r#"{"output": "weights", "tolerance": 0.001}"#),
            "no tolerance",
        ),
    ];
    for (msg, expect) in cases {
        let (mut ws, _) = tokio_tungstenite::connect_async(&url)
            .await
            .expect("connect");
        ws.send(msg).await.expect("send");
        let (code, reason) = next_close(&mut ws).await;
        assert_eq!(code, 1008, "{expect}: {reason}");
        assert!(reason.contains(expect), "{reason:?} names {expect:?}");
    }
    // An update after a good hello is checked the same way.
    let mut ws = connect(&server, &s.id, json!({})).await;
    next_tick(&mut ws).await;
    ws.send(Message::text(r#"{"lod": -1}"#))
        .await
        .expect("send");
    let (code, reason) = next_close(&mut ws).await;
    assert_eq!(code, 1008, "{reason}");
    assert!(reason.contains("update"), "{reason}");
    // A message over 64 KiB is 1009.
    let (mut ws, _) = tokio_tungstenite::connect_async(&url)
        .await
        .expect("connect");
    ws.send(Message::text(" ".repeat(70_000)))
        .await
        .expect("send");
    let (code, _) = next_close(&mut ws).await;
    assert_eq!(code, 1009);
    let page = server.client.metrics().await.expect("metrics");
    assert!(
        crowdmorph_client::metric(
            &page,
            "crowdmorph_session_viewers_closed_total{reason=\"policy\"}"
        )
        .unwrap_or(0.0)
            >= 14.0
    );
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn deleting_a_session_closes_its_viewers_cleanly() {
    let server = TestServer::start(config()).await;
    let s = create(
        &server,
        json!({"heads": [head(1, "talk", 0, [0.0, 0.0, 0.0])]}),
    )
    .await;
    let mut a = connect(&server, &s.id, json!({})).await;
    let mut b = connect(&server, &s.id, json!({"format": "q16"})).await;
    next_tick(&mut a).await;
    next_tick(&mut b).await;
    let (status, _) = call(
        &server,
        Method::DELETE,
        &format!("/v1/sessions/{}", s.id),
        Value::Null,
    )
    .await;
    assert_eq!(status, 204);
    for ws in [&mut a, &mut b] {
        let (code, reason) = next_close(ws).await;
        assert_eq!((code, reason.as_str()), (1001, "session deleted"));
    }
    let (status, v) = call(
        &server,
        Method::GET,
        &format!("/v1/sessions/{}", s.id),
        Value::Null,
    )
    .await;
    assert_eq!(status, 404);
    assert_eq!(v["error"]["code"], "unknown_session");
    let (status, _) = call(
        &server,
        Method::DELETE,
        &format!("/v1/sessions/{}", s.id),
        Value::Null,
    )
    .await;
    assert_eq!(status, 404);
    // A stream request for it is a plain 404 before any upgrade.
    let url = format!("ws://{}/v1/sessions/{}/stream", server.addr, s.id);
    assert!(tokio_tungstenite::connect_async(url).await.is_err());
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn patches_apply_at_the_next_tick_and_bad_ones_are_refused() {
    let server = TestServer::start(ServerConfig {
        sessions: SessionLimits {
            max_heads: 4,
            max_sessions: 2,
            max_viewers: 1,
            ..SessionLimits::default()
        },
        ..config()
    })
    .await;
    let s = create(&server, json!({"heads": [head(1, "talk", 0, [0.0, 0.0, 0.0]), head(2, "smile", 0, [1.0, 0.0, 0.0])]})).await;
    let path = format!("/v1/sessions/{}", s.id);
    let mut ws = connect(&server, &s.id, json!({})).await;
    let mut v = View::default();
    v.apply(&next_tick(&mut ws).await);
    assert_eq!(v.layout, vec![1, 2]);

    let (status, body) = call(
        &server,
        Method::PATCH,
        &path,
        json!({"remove": [1], "change": [{"head": 2, "clip": "surprise", "yaw": 90}],
               "add": [head(9, "idle", 4, [0.0, 0.0, 2.0])]}),
    )
    .await;
    assert_eq!(status, 200, "{body}");
    assert_eq!(body["heads"].as_array().map(Vec::len), Some(2));
    let mut relaid = false;
    for _ in 0..10 {
        let t = next_tick(&mut ws).await;
        if let Some(l) = &t.layout {
            assert_eq!(l.iter().map(|h| h.head).collect::<Vec<_>>(), vec![2, 9]);
            assert_eq!(l[0].clip, "surprise");
            assert_eq!(l[0].yaw, 90.0);
            relaid = true;
        }
        v.apply(&t);
        if relaid {
            break;
        }
    }
    assert!(relaid, "a message carried the new layout");
    assert!(v.heads.contains_key(&9));

    // Refusals, each naming the problem.
    let cases = [
        (json!({"remove": [77]}), 404, "unknown_head"),
        (
            json!({"change": [{"head": 77, "yaw": 1}]}),
            404,
            "unknown_head",
        ),
        (
            json!({"add": [head(2, "talk", 0, [0.0, 0.0, 0.0])]}),
            409,
            "head_exists",
        ),
        (
            json!({"add": [{"head": 5, "rig": "default-head", "clip": "nope"}]}),
            404,
            "unknown_clip",
        ),
        (
            json!({"add": [{"head": 5, "rig": "nope", "clip": "talk"}]}),
            404,
            "unknown_rig",
        ),
        (
            json!({"change": [{"head": 2, "scale": 0}]}),
            400,
            "invalid_session",
        ),
        (
            json!({"add": [head(5, "talk", 0, [0.0, 0.0, 0.0]), head(6, "talk", 0, [0.0, 0.0, 0.0]),
                        head(7, "talk", 0, [0.0, 0.0, 0.0])]}),
            413,
            "too_many_heads",
        ),
        (json!({"add": 3}), 400, "malformed_json"),
    ];
    for (patch, status, code) in cases {
        let (st, body) = call(&server, Method::PATCH, &path, patch.clone()).await;
        assert_eq!(
            (st, body["error"]["code"].as_str()),
            (status, Some(code)),
            "{patch}: {body}"
        );
    }
    for (req, status, code) in [
        (json!({"fps": 0, "heads": []}), 400, "invalid_session"),
        (json!({"fps": 500, "heads": []}), 400, "invalid_session"),
        (
            json!({"idle_timeout_s": 0, "heads": []}),
            400,
            "invalid_session",
        ),
        (
            json!({"heads": [head(1, "talk", 0, [0.0, 0.0, 0.0]), head(1, "talk", 0, [0.0, 0.0, 0.0])]}),
            400,
            "invalid_session",
        ),
        (
            json!({"heads": [{"head": 1, "rig": "default-head", "clip": "talk", "position": [0, 1e39, 0]}]}),
            400,
            "invalid_session",
        ),
        (
            json!({"heads": [{"head": 1, "rig": "x", "clip": "talk"}]}),
            404,
            "unknown_rig",
        ),
    ] {
        let (st, body) = call(&server, Method::POST, "/v1/sessions", req.clone()).await;
        assert_eq!(
            (st, body["error"]["code"].as_str()),
            (status, Some(code)),
            "{req}: {body}"
        );
    }
    // A second viewer is one too many (max 1): 1013 with the reason.
    let mut extra = connect(&server, &s.id, json!({})).await;
    let (code, reason) = next_close(&mut extra).await;
    assert_eq!(code, 1013);
    assert!(reason.contains("--max-session-viewers"), "{reason}");
    // Two sessions exist at most.
    create(&server, json!({"heads": []})).await;
    let (st, body) = call(&server, Method::POST, "/v1/sessions", json!({"heads": []})).await;
    assert_eq!(
        (st, body["error"]["code"].as_str()),
        (503, Some("too_many_sessions"))
    );
    let (st, body) = call(&server, Method::GET, "/v1/sessions", Value::Null).await;
    assert_eq!(st, 200);
    assert_eq!(body["sessions"].as_array().map(Vec::len), Some(2));
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn patches_apply_entry_by_entry_and_long_lists_are_refused() {
    let server = TestServer::start(ServerConfig {
        sessions: SessionLimits {
            max_heads: 400,
            ..SessionLimits::default()
        },
        ..config()
    })
    .await;
    // Ids do not follow positions, so a lookup by position would be caught.
    let heads: Vec<Value> = (0..300u64)
        .map(|k| head(1_000 - k, "talk", 0, [k as f32, 0.0, 0.0]))
        .collect();
    let s = create(&server, json!({ "heads": heads })).await;
    let path = format!("/v1/sessions/{}", s.id);
    let ids = |i: &SessionInfo| i.heads.iter().map(|h| h.head).collect::<Vec<_>>();

    // Remove every third id, change the next one, add two: the heads keep their order, the
    // changed ones carry their change, the added ones come last.
    let remove: Vec<u64> = (0..300u64)
        .filter(|k| k % 3 == 0)
        .map(|k| 1_000 - k)
        .collect();
    let change: Vec<Value> = (0..300u64)
        .filter(|k| k % 3 == 1)
        .map(|k| json!({"head": 1_000 - k, "yaw": k as f32, "clip": "smile"}))
        .collect();
    let (st, body) = call(
        &server,
        Method::PATCH,
        &path,
        json!({"remove": remove, "change": change,
               "add": [head(5, "idle", 0, [0.0; 3]), head(1_000, "idle", 0, [0.0; 3])]}),
    )
    .await;
    assert_eq!(st, 200, "{body}");
    let after = info(&server, &s.id).await;
    let mut want: Vec<u64> = (0..300u64)
        .filter(|k| k % 3 != 0)
        .map(|k| 1_000 - k)
        .collect();
    want.extend([5, 1_000]);
    assert_eq!(ids(&after), want);
    for h in &after.heads[..200] {
        let k = 1_000 - h.head;
        assert_eq!(h.position, [k as f32, 0.0, 0.0], "head {}", h.head);
        if k % 3 == 1 {
            assert_eq!(
                (h.yaw, h.clip.as_str()),
                (k as f32, "smile"),
                "head {}",
                h.head
            );
        } else {
            assert_eq!((h.yaw, h.clip.as_str()), (0.0, "talk"), "head {}", h.head);
        }
    }

    // Repeated changes to one head apply in order: each field keeps its last value.
    let (st, body) = call(
        &server,
        Method::PATCH,
        &path,
        json!({"change": [{"head": 999, "yaw": 10}, {"head": 999, "scale": 2},
                          {"head": 999, "yaw": 20, "clip": "surprise"}]}),
    )
    .await;
    assert_eq!(st, 200, "{body}");
    let h = &info(&server, &s.id).await.heads[0];
    assert_eq!(
        (h.head, h.yaw, h.scale, h.clip.as_str()),
        (999, 20.0, 2.0, "surprise")
    );

    // Refused, and the session keeps its heads: each change is checked as it lands (a bad
    // one is not rescued by a later one), a second remove of an id finds it gone, a change
    // of a removed head finds it gone; removing an id then adding it back is fine.
    let before = ids(&info(&server, &s.id).await);
    for (patch, status, code, says) in [
        (
            json!({"change": [{"head": 999, "scale": 0}, {"head": 999, "scale": 1}]}),
            400,
            "invalid_session",
            "head 999",
        ),
        (
            json!({"remove": [998, 998]}),
            404,
            "unknown_head",
            "no head 998",
        ),
        (
            json!({"remove": [998], "change": [{"head": 998, "yaw": 1}]}),
            404,
            "unknown_head",
            "no head 998",
        ),
    ] {
        let (st, body) = call(&server, Method::PATCH, &path, patch.clone()).await;
        assert_eq!(
            (st, body["error"]["code"].as_str()),
            (status, Some(code)),
            "{patch}: {body}"
        );
        let message = body["error"]["message"].as_str().unwrap_or_default();
        assert!(message.contains(says), "{patch}: {message}");
        assert_eq!(ids(&info(&server, &s.id).await), before, "{patch}");
    }
    let (st, body) = call(
        &server,
        Method::PATCH,
        &path,
        json!({"remove": [998], "add": [head(998, "idle", 0, [0.0; 3])]}),
    )
    .await;
    assert_eq!(st, 200, "{body}");
    let now = ids(&info(&server, &s.id).await);
    assert_eq!(now.last(), Some(&998));
    assert_eq!(now.len(), before.len());

    // Lists longer than the session may hold heads are refused before any work, naming the
    // limit, even when every entry alone would do; a list at the limit is fine.
    let at_limit: Vec<Value> = (0..400).map(|_| json!({"head": 999})).collect();
    let (st, body) = call(&server, Method::PATCH, &path, json!({ "change": at_limit })).await;
    assert_eq!(st, 200, "{body}");
    let over: Vec<Value> = (0..401).map(|_| json!({"head": 999})).collect();
    let removes: Vec<u64> = now.iter().copied().chain(now.iter().copied()).collect();
    for (patch, field) in [
        (json!({ "change": over }), "change has 401 entries"),
        (json!({ "remove": removes }), "remove has 404 entries"),
    ] {
        let (st, body) = call(&server, Method::PATCH, &path, patch).await;
        assert_eq!(
            (st, body["error"]["code"].as_str()),
            (400, Some("invalid_session")),
            "{body}"
        );
        let message = body["error"]["message"].as_str().unwrap_or_default();
        assert!(
            message.contains(field)
                && message.contains("400")
                && message.contains("--max-session-heads"),
            "{message}"
        );
    }
    assert_eq!(ids(&info(&server, &s.id).await), now);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn session_changes_need_the_admin_token_and_streams_do_not() {
    let server = TestServer::start(ServerConfig {
        admin_token: Some("sesame".into()),
        ..config()
    })
    .await;
    let body = json!({"heads": [head(1, "talk", 0, [0.0, 0.0, 0.0])]});
    let (st, v) = call(&server, Method::POST, "/v1/sessions", body.clone()).await;
    assert_eq!(
        (st, v["error"]["code"].as_str()),
        (401, Some("token_required"))
    );
    let admin = server.client.clone().with_token("sesame");
    let reply = admin
        .send(
            Method::POST,
            "/v1/sessions",
            Some("application/json"),
            None,
            Bytes::from(body.to_string()),
        )
        .await
        .expect("create");
    assert_eq!(reply.status, 201);
    let s: SessionInfo = serde_json::from_slice(&reply.body).expect("info");
    let path = format!("/v1/sessions/{}", s.id);
    let (st, _) = call(&server, Method::PATCH, &path, json!({"remove": [1]})).await;
    assert_eq!(st, 401);
    let (st, _) = call(&server, Method::DELETE, &path, Value::Null).await;
    assert_eq!(st, 401);
    // Reading and watching need no token.
    assert_eq!(info(&server, &s.id).await.heads.len(), 1);
    let mut ws = connect(&server, &s.id, json!({})).await;
    next_tick(&mut ws).await;
    server.stop().await;
}

gpu_test!(
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_viewer_that_asks_for_frames_gets_images() {
        let server = TestServer::start(config()).await;
        let s = create(&server, json!({"fps": 10, "heads": [head(1, "talk", 0, [0.0, 0.0, 0.0]), head(2, "smile", 0, [0.3, 0.0, 0.0])]})).await;
        // No camera: the front view framing every head.
        let hello =
            json!({"output": "frames", "image": {"width": 160, "height": 120, "format": "png"}});
        let mut ws = connect(&server, &s.id, hello).await;
        let mut ticks = Vec::new();
        while ticks.len() < 3 {
            let msg = tokio::time::timeout(READ, ws.next())
                .await
                .expect("a frame")
                .expect("open")
                .expect("message");
            if let Message::Binary(b) = msg {
                let m: StreamMessage =
                    crowdmorph_proto::wire::response_from_bincode(&b).expect("decode");
                let StreamMessage::Frame(f) = m else {
                    panic!("asked for frames")
                };
                assert_eq!((f.width, f.height), (160, 120));
                let img = crate::util::image::Image::decode_png(&f.image.0).expect("a PNG");
                assert_eq!((img.width, img.height), (160, 120));
                let background = img.pixel(0, 0);
                let mut drawn = 0;
                for y in 0..img.height {
                    for x in 0..img.width {
                        drawn += usize::from(img.pixel(x, y) != background);
                    }
                }
                assert!(
                    drawn > 160 * 120 / 50,
                    "the heads are drawn: {drawn} pixels"
                );
                ticks.push(f.tick);
            }
        }
        assert!(ticks.windows(2).all(|w| w[1] > w[0]), "{ticks:?}");
        server.stop().await;
    }
);

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_silent_viewer_and_a_chatty_one_are_closed_with_the_rule_they_broke() {
    let server = TestServer::start(ServerConfig {
        sessions: SessionLimits {
            max_viewer_messages: 5,
            hello_timeout: Duration::from_millis(300),
            ..SessionLimits::default()
        },
        ..config()
    })
    .await;
    let s = create(
        &server,
        json!({"heads": [head(1, "talk", 0, [0.0, 0.0, 0.0])]}),
    )
    .await;
    // A viewer that never sends its hello is closed once the hello timeout passes.
    let url = format!("ws://{}/v1/sessions/{}/stream", server.addr, s.id);
    let (mut silent, _) = tokio_tungstenite::connect_async(&url)
        .await
        .expect("connect");
    let (code, reason) = next_close(&mut silent).await;
    assert_eq!(code, 1008, "{reason}");
    assert!(reason.contains("no hello within 0.3 s"), "{reason:?}");

    // A viewer that sends more updates in a second than allowed is closed, naming the limit;
    // five are fine.
    let mut chatty = connect(&server, &s.id, json!({})).await;
    next_tick(&mut chatty).await;
    let update = json!({"lod": 0}).to_string();
    for _ in 0..5 {
        chatty
            .send(Message::text(update.clone()))
            .await
            .expect("send");
    }
    next_tick(&mut chatty).await;
    for _ in 0..20 {
        if chatty.send(Message::text(update.clone())).await.is_err() {
            break;
        }
    }
    let (code, reason) = next_close(&mut chatty).await;
    assert_eq!(code, 1008, "{reason}");
    assert!(
        reason.contains("more than 5 messages per second"),
        "{reason:?}"
    );
    server.stop().await;
}

/// A tick's own bookkeeping (per head and viewer) is charged to the queue memory before it is
/// built: 10,000 clones of one head need one small blend, but their per-head lists for two
/// viewers (≈ 4 MB) do not fit in 3 MB, so those ticks are skipped (counted, and the
/// rejection named in the metrics), while a 100-head session ticks under the same limit.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_ticks_per_head_lists_are_charged_to_the_queue_memory() {
    let server = TestServer::start(ServerConfig {
        queue_memory_bytes: 3 << 20,
        ..config()
    })
    .await;
    let hello = json!({"format": "f32", "normals": true});
    let small = create(&server, json!({"fps": 30, "heads": idle_grid(100)})).await;
    let mut viewer = connect(&server, &small.id, hello.clone()).await;
    let first = next_tick(&mut viewer).await;
    assert_eq!(first.buffers.len(), 1, "100 clones share one job");
    drop(viewer);

    let large = create(&server, json!({"fps": 30, "heads": idle_grid(10_000)})).await;
    let _viewers = [
        connect(&server, &large.id, hello.clone()).await,
        connect(&server, &large.id, hello).await,
    ];
    let deadline = std::time::Instant::now() + Duration::from_secs(20);
    let stats = loop {
        // The session's answer (10,000 heads) is charged to the same small queue memory: a
        // GET that meets a tick's reservation is a 503 to retry, which is what the server
        // should answer.
        let (status, v) = call(
            &server,
            Method::GET,
            &format!("/v1/sessions/{}", large.id),
            Value::Null,
        )
        .await;
        if status == 503 && std::time::Instant::now() < deadline {
            tokio::time::sleep(Duration::from_millis(50)).await;
            continue;
        }
        assert_eq!(status, 200, "{v}");
        let stats = serde_json::from_value::<SessionInfo>(v)
            .expect("SessionInfo")
            .stats;
        if stats.ticks_skipped >= 3 || std::time::Instant::now() > deadline {
            break stats;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    assert!(stats.ticks_skipped >= 3, "{stats:?}");
    assert_eq!(stats.ticks, 0, "no tick fits: {stats:?}");
    let page = server.client.metrics().await.expect("metrics");
    let rejected =
        crowdmorph_client::metric(&page, "crowdmorph_rejected_total{reason=\"queue_memory\"}")
            .unwrap_or(0.0);
    assert!(rejected >= 3.0, "queue-memory rejections: {rejected}");
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_patchs_answer_is_charged_before_the_patch_applies() {
    use tokio::io::AsyncWriteExt;
    // A PATCH answers with every head of the session (≈ 230 bytes each as JSON), however small
    // the patch. That answer is charged before the patch applies: while a crowd body that is
    // still arriving holds most of the queue memory, a one-head patch to a 10,000-head session
    // is refused (503) and changes nothing; it used to apply and answer 2.3 MB uncharged.
    let server = TestServer::start(ServerConfig {
        queue_memory_bytes: 8 << 20,
        ..config()
    })
    .await;
    let s = create(&server, json!({"fps": 1, "heads": idle_grid(10_000)})).await;
    let path = format!("/v1/sessions/{}", s.id);
    let patch = json!({"change": [{"head": 1, "clip": "talk"}]});
    let held = || async {
        let page = server.client.metrics().await.expect("metrics");
        crowdmorph_client::metric(&page, "crowdmorph_queue_memory_bytes").expect("gauge")
    };

    // A JSON crowd body of 2.4 MB reserves three times its declared length (7.3 MB of the 8)
    // while it is read; this one never arrives.
    let mut stalled = tokio::net::TcpStream::connect(server.addr)
        .await
        .expect("connect");
    stalled
        .write_all(
            b"POST /v1/crowd/frame HTTP/1.1\r\nhost: test\r\ncontent-type: application/json\r\n\
              content-length: 2446677\r\n\r\n{\"heads\":[",
        )
        .await
        .expect("send the head of the request");
    let deadline = std::time::Instant::now() + READ;
    while held().await < (7 << 20) as f64 {
        assert!(
            std::time::Instant::now() < deadline,
            "the body's reservation"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    // A body that lists 10,000 heads is cut short in a failure message.
    let brief = |v: &Value| v.to_string().chars().take(300).collect::<String>();
    let (status, body) = call(&server, Method::PATCH, &path, patch.clone()).await;
    assert_eq!(status, 503, "{}", brief(&body));
    assert!(body.to_string().contains("queue_full"), "{body}");

    drop(stalled);
    while held().await >= (7 << 20) as f64 {
        assert!(
            std::time::Instant::now() < deadline,
            "the reservation given back"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let unchanged = info(&server, &s.id).await;
    assert_eq!(unchanged.heads.len(), 10_000);
    assert_eq!(
        unchanged.heads[1].clip, "idle",
        "the refused patch changed nothing"
    );
    // With the memory free, the same patch applies and answers every head.
    let (status, body) = call(&server, Method::PATCH, &path, patch).await;
    assert_eq!(status, 200, "{}", brief(&body));
    assert_eq!(body["heads"].as_array().map(Vec::len), Some(10_000));
    assert_eq!(body["heads"][1]["clip"], "talk");
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_session_can_have_the_clients_id_once_and_posts_skip_it() {
    let server = TestServer::start(config()).await;
    let body = json!({"fps": 10, "heads": [head(1, "talk", 0, [0.0, 0.0, 0.0])]});
    // The Rust client's PUT: the session is named as asked, and its viewer path works.
    let req: crowdmorph_proto::SessionRequest =
        serde_json::from_value(body.clone()).expect("request");
    let made = server
        .client
        .create_session(
            &req,
            Some("lobby-1.a_b"),
            crowdmorph_client::Encoding::Bincode,
        )
        .await
        .expect("PUT");
    assert_eq!(made.id, "lobby-1.a_b");
    assert_eq!(info(&server, "lobby-1.a_b").await.heads.len(), 1);
    // Taken: 409 naming it, and the running session is untouched.
    let (status, v) = call(
        &server,
        Method::PUT,
        "/v1/sessions/lobby-1.a_b",
        body.clone(),
    )
    .await;
    assert_eq!(
        (status, v["error"]["code"].as_str()),
        (409, Some("session_exists")),
        "{v}"
    );
    assert!(
        v["error"]["message"]
            .as_str()
            .is_some_and(|m| m.contains("lobby-1.a_b")),
        "{v}"
    );
    // Ids that are not path- and log-safe, or too long, are refused before anything is made.
    for bad in ["has%20space", "star*", &"x".repeat(65)] {
        let (status, v) = call(
            &server,
            Method::PUT,
            &format!("/v1/sessions/{bad}"),
            body.clone(),
        )
        .await;
        assert_eq!(
            (status, v["error"]["code"].as_str()),
            (400, Some("invalid_session")),
            "{bad}: {v}"
        );
    }
    // A client that takes "s1" and "s2" leaves POST the next free name.
    for id in ["s1", "s2"] {
        let (status, v) = call(
            &server,
            Method::PUT,
            &format!("/v1/sessions/{id}"),
            body.clone(),
        )
        .await;
        assert_eq!(status, 201, "{v}");
    }
    let posted = create(&server, body.clone()).await;
    assert_eq!(posted.id, "s3");
    let (status, v) = call(&server, Method::GET, "/v1/sessions", Value::Null).await;
    assert_eq!(status, 200);
    let ids: Vec<&str> = v["sessions"]
        .as_array()
        .expect("list")
        .iter()
        .filter_map(|s| s["id"].as_str())
        .collect();
    assert_eq!(ids.len(), 4, "{ids:?}");
    // A chosen id is deleted like any other.
    let (status, _) = call(
        &server,
        Method::DELETE,
        "/v1/sessions/lobby-1.a_b",
        Value::Null,
    )
    .await;
    assert_eq!(status, 204);
    server.stop().await;
}
