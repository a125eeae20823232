//! Motion graphs: `PUT /v1/rigs/{id}/graphs/{name}` checked, stored across restarts, listed in
//! the rig; session heads walking a graph over the WebSocket stream, where clones stay clones
//! and no transition pops — also when a `PATCH` interrupts one and then reverses it.

use bytes::Bytes;
use crowdmorph::server::ServerConfig;
use crowdmorph_client::Method;
use crowdmorph_proto::{CONTENT_TYPE_BINCODE, GraphEdge, MotionGraph};
use serde_json::{Value, json};

use super::sessions::{View, call, connect, create, next_tick};
use super::{TestServer, stored_config, temp_dir};

/// Three moods of the embedded head: talk ⇄ smile → surprise → talk, and talk again from talk.
fn moods() -> Value {
    json!({
        "nodes": [
            {"name": "talk", "clip": "talk"},
            {"name": "smile", "clip": "smile", "frames": [0, 59]},
            {"name": "surprise", "clip": "surprise"},
        ],
        "edges": [
            {"from": "talk", "to": "smile", "fade": 10},
            {"from": "talk", "to": "talk", "fade": 6},
            {"from": "smile", "to": "talk", "fade": 10, "window": [20, 40]},
            {"from": "smile", "to": "surprise", "fade": 12},
            {"from": "surprise", "to": "talk", "fade": 8},
        ],
    })
}

async fn put(server: &TestServer, name: &str, graph: Value) -> (u16, Value) {
    call(
        server,
        Method::PUT,
        &format!("/v1/rigs/default-head/graphs/{name}"),
        graph,
    )
    .await
}

fn code(v: &Value) -> &str {
    v["error"]["code"].as_str().unwrap_or("")
}

#[tokio::test]
async fn graphs_are_checked_listed_stored_and_deleted() {
    let dir = temp_dir("graphs");
    let server = TestServer::start(stored_config(&dir)).await;
    let (status, v) = put(&server, "moods", moods()).await;
    assert_eq!(status, 200, "{v}");
    assert_eq!(v["graph"]["nodes"].as_array().unwrap().len(), 3);
    let (_, rig) = call(&server, Method::GET, "/v1/rigs/default-head", Value::Null).await;
    assert_eq!(rig["graphs"], json!(["moods"]));
    // Bad graphs: each a 4xx naming the field.
    let with = |f: &dyn Fn(&mut Value)| {
        let mut g = moods();
        f(&mut g);
        g
    };
    let cases: Vec<(Value, u16, &str, &str)> = vec![
        (
            with(&|g| g["edges"][0]["fade"] = json!(0)),
            400,
            "invalid_graph",
            "edges[0].fade",
        ),
        (
            with(&|g| g["edges"][1]["fade"] = json!(0)),
            400,
            "invalid_graph",
            "edges[1].fade",
        ),
        (
            with(&|g| g["edges"][3]["fade"] = json!(100_000)),
            400,
            "invalid_graph",
            "longer",
        ),
        (
            with(&|g| g["edges"][2]["window"] = json!([50, 70])),
            400,
            "invalid_graph",
            "window",
        ),
        (
            with(&|g| g["edges"][4]["to"] = json!("nobody")),
            400,
            "invalid_graph",
            "edges[4].to",
        ),
        (
            with(&|g| {
                g["edges"].as_array_mut().unwrap().pop();
            }),
            400,
            "invalid_graph",
            "surprise",
        ),
        (
            with(&|g| g["nodes"][1]["clip"] = json!("nope")),
            404,
            "unknown_clip",
            "nope",
        ),
        (
            with(&|g| g["nodes"][1]["frames"] = json!([0, 100_000])),
            400,
            "invalid_graph",
            "nodes[1].frames",
        ),
        (
            json!({"nodes": [], "edges": []}),
            400,
            "invalid_graph",
            "nodes",
        ),
    ];
    for (g, status, want, needle) in cases {
        let (s, v) = put(&server, "bad", g.clone()).await;
        assert_eq!((s, code(&v)), (status, want), "{g}: {v}");
        let message = v["error"]["message"].as_str().unwrap();
        assert!(
            message.contains(needle),
            "{message:?} should name {needle:?}"
        );
    }
    // A million edges in a small bincode body: refused before any work, nothing kept.
    let huge = MotionGraph {
        nodes: Vec::new(),
        edges: vec![GraphEdge::default(); 1_000_000],
    };
    let body = crowdmorph_proto::wire::to_bincode(&huge).unwrap();
    assert!(body.len() < 8 << 20, "{} bytes", body.len());
    let reply = server
        .client
        .send(
            Method::PUT,
            "/v1/rigs/default-head/graphs/huge",
            Some(CONTENT_TYPE_BINCODE),
            None,
            Bytes::from(body),
        )
        .await
        .unwrap();
    assert!(
        reply.status == 400 || reply.status == 413,
        "{}: {}",
        reply.status,
        String::from_utf8_lossy(&reply.body)
    );
    let (_, list) = call(
        &server,
        Method::GET,
        "/v1/rigs/default-head/graphs",
        Value::Null,
    )
    .await;
    assert_eq!(list["graphs"].as_array().unwrap().len(), 1, "{list}");
    // Sessions name graphs and nodes that exist.
    for (graph, start, status, want) in [
        ("nope", "talk", 404, "unknown_graph"),
        ("moods", "nope", 404, "unknown_node"),
    ] {
        let (s, v) = call(
            &server,
            Method::POST,
            "/v1/sessions",
            json!({"heads": [{"head": 1, "rig": "default-head",
                              "graph": {"name": graph, "start": start}}]}),
        )
        .await;
        assert_eq!((s, code(&v)), (status, want), "{v}");
    }
    // Stored with the rig: a restarted server has it.
    server.stop().await;
    let server = TestServer::start(stored_config(&dir)).await;
    let (status, v) = call(
        &server,
        Method::GET,
        "/v1/rigs/default-head/graphs/moods",
        Value::Null,
    )
    .await;
    assert_eq!(status, 200, "{v}");
    assert_eq!(v["graph"]["edges"].as_array().unwrap().len(), 5);
    let (status, _) = call(
        &server,
        Method::DELETE,
        "/v1/rigs/default-head/graphs/moods",
        Value::Null,
    )
    .await;
    assert_eq!(status, 204);
    let (status, v) = call(
        &server,
        Method::GET,
        "/v1/rigs/default-head/graphs/moods",
        Value::Null,
    )
    .await;
    assert_eq!((status, code(&v)), (404, "unknown_graph"));
    server.stop().await;
    let _ = std::fs::remove_dir_all(&dir);
}

/// Smooth clips of the embedded head (a raised cosine over 90 frames on a few targets each), so
/// that a pop — a cut between two of them — is far larger than any step inside them, unlike
/// the built-in clips, whose blinks move the eyelids further in one frame than most cuts do.
const SMOOTH: [(&str, &[&str]); 3] = [
    ("slow-jaw", &["jawOpen"]),
    ("slow-smile", &["mouthSmile_L", "mouthSmile_R"]),
    ("slow-brow", &["browInnerUp", "eyeWide_L", "eyeWide_R"]),
];

async fn upload_smooth_clips(server: &TestServer) {
    for (name, targets) in SMOOTH {
        let frames: Vec<Vec<f32>> = (0..90)
            .map(|f| {
                let w = 0.5 - 0.5 * (std::f32::consts::TAU * f as f32 / 90.0).cos();
                vec![w; targets.len()]
            })
            .collect();
        let body = json!({"fps": 30, "targets": targets, "frames": frames}).to_string();
        let reply = server
            .client
            .send(
                Method::POST,
                &format!("/v1/rigs/default-head/clips?name={name}"),
                Some("application/json"),
                None,
                Bytes::from(body),
            )
            .await
            .unwrap();
        assert_eq!(
            reply.status,
            201,
            "{}",
            String::from_utf8_lossy(&reply.body)
        );
    }
}

/// A graph over the smooth clips: jaw ⇄ smile → brow → jaw, and jaw again from jaw.
fn smooth_graph() -> Value {
    json!({
        "nodes": [
            {"name": "jaw", "clip": "slow-jaw"},
            {"name": "smile", "clip": "slow-smile", "frames": [10, 80]},
            {"name": "brow", "clip": "slow-brow"},
        ],
        "edges": [
            {"from": "jaw", "to": "smile", "fade": 10, "window": [30, 60]},
            {"from": "jaw", "to": "jaw", "fade": 6},
            {"from": "smile", "to": "jaw", "fade": 10, "window": [20, 40]},
            {"from": "smile", "to": "brow", "fade": 12},
            {"from": "brow", "to": "jaw", "fade": 8, "window": [40, 70]},
        ],
    })
}

/// The largest distance any vertex moves between consecutive frames of the smooth clips
/// (f32, CPU engine), as the server now holds them.
async fn largest_clip_step(server: &TestServer) -> f32 {
    let rig = server.state.registry.get("default-head").unwrap();
    let engine = crowdmorph::engine::Engine::cpu();
    let prepared = engine
        .prepare(std::sync::Arc::new(rig.rig().clone()))
        .unwrap();
    let mut largest = 0f32;
    for (name, _) in SMOOTH {
        let c = rig.clip_index(name).unwrap();
        let frames = rig.rig().clips[c].frames;
        let frame = |f| {
            crate::util::pose_positions(
                &engine,
                &prepared,
                crowdmorph::rig::Pose::Frame {
                    clip: c as u32,
                    frame: f,
                },
            )
        };
        let mut prev = frame(0);
        for f in 1..frames {
            let p = frame(f);
            largest = largest.max(max_step(&prev, &p));
            prev = p;
        }
    }
    largest
}

fn max_step(a: &[f32], b: &[f32]) -> f32 {
    a.chunks_exact(3)
        .zip(b.chunks_exact(3))
        .map(|(p, q)| {
            ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).sqrt()
        })
        .fold(0.0, f32::max)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn graph_heads_fade_without_pops_even_when_interrupted_and_clones_stay_clones() {
    let server = TestServer::start(ServerConfig::default()).await;
    upload_smooth_clips(&server).await;
    let (status, v) = put(&server, "smooth", smooth_graph()).await;
    assert_eq!(status, 200, "{v}");
    let walk = |head: u64, seed: u64, start: &str| {
        json!({"head": head, "rig": "default-head", "position": [head as f32, 0.0, 0.0],
               "graph": {"name": "smooth", "start": start, "seed": seed}})
    };
    let scripted = json!({"head": 4, "rig": "default-head",
        "graph": {"name": "smooth", "start": "jaw", "script": ["smile", "brow", "jaw"]}});
    let info = create(
        &server,
        json!({"fps": 30, "heads": [walk(1, 7, "jaw"), walk(2, 7, "jaw"), walk(3, 8, "smile"), scripted]}),
    )
    .await;
    let mut ws = connect(
        &server,
        &info.id,
        json!({"output": "vertices", "format": "f32"}),
    )
    .await;
    let bound = 1.5 * largest_clip_step(&server).await;
    let mut view = View::default();
    let mut last: Option<(u64, std::collections::HashMap<u64, Vec<f32>>)> = None;
    let mut largest = std::collections::HashMap::<u64, f32>::new();
    let mut clones_shared = 0;
    // Head 1 is sent to brow mid-walk, back to jaw three ticks later (a reversed,
    // interrupted transition), and to smile again; head 2, its clone until then, walks on.
    let patches: [(u64, &str); 3] = [(40, "brow"), (43, "jaw"), (70, "smile")];
    let mut patched_at = 0;
    for _ in 0..240 {
        let t = next_tick(&mut ws).await;
        view.apply(&t);
        if t.tick < 40 {
            let b: Vec<u32> = t.heads.iter().take(2).map(|h| h.buffer).collect();
            assert_eq!(b[0], b[1], "tick {}: heads 1 and 2 are clones", t.tick);
            clones_shared += 1;
        }
        if let Some((tick, prev)) = &last
            && *tick + 1 == t.tick
        {
            for (id, p) in &view.heads {
                if let Some(q) = prev.get(id) {
                    let d = max_step(q, p);
                    let m = largest.entry(*id).or_default();
                    *m = m.max(d);
                    assert!(
                        d <= bound,
                        "tick {}: head {id} moved {d} in one tick, more than 1.5 × the clips' \
                         largest step ({bound})",
                        t.tick
                    );
                }
            }
        }
        last = Some((t.tick, view.heads.clone()));
        while patched_at < patches.len() && t.tick >= patches[patched_at].0 {
            let (_, node) = patches[patched_at];
            let (status, v) = call(
                &server,
                Method::PATCH,
                &format!("/v1/sessions/{}", info.id),
                json!({"change": [{"head": 1, "node": node}]}),
            )
            .await;
            assert_eq!(status, 200, "{v}");
            patched_at += 1;
        }
    }
    eprintln!("bound {bound}, largest per-tick step per head {largest:?}");
    assert!(
        clones_shared > 10,
        "the clone check ran ({clones_shared} ticks)"
    );
    assert_eq!(patched_at, patches.len());
    for id in 1..=4 {
        assert!(
            largest.get(&id).copied().unwrap_or(0.0) > 0.0,
            "head {id} moved: {largest:?}"
        );
    }
    // Patches name a node of the head's graph, and only graph heads take one.
    let (status, v) = call(
        &server,
        Method::PATCH,
        &format!("/v1/sessions/{}", info.id),
        json!({"change": [{"head": 1, "node": "nowhere"}]}),
    )
    .await;
    assert_eq!((status, code(&v)), (404, "unknown_node"), "{v}");
    server.stop().await;
}
