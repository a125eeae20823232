//! Motion graphs: `PUT /v1/rigs/{id}/graphs/{name}` checked, stored across restarts, listed in
//! the rig; session heads walking a graph over the WebSocket stream, where clones stay clones
//! and no transition pops — also when a `PATCH` interrupts one and then reverses it.

use bytes::Bytes;
use crowdmorph::server::ServerConfig;
use crowdmorph_client::Method;
use crowdmorph_proto::{CONTENT_TYPE_BINCODE, GraphEdge, MotionGraph};
use serde_json::{Value, json};

use super::attack::{binary, cores_used, cpu_seconds, metric};
use super::joints::{robot_path, robot_pose};
use super::sessions::{View, call, connect, create, next_tick};
use super::{TestServer, stored_config, temp_dir, upload_bytes};

/// Three nodes `n[0]` ⇄ `n[1]` → `n[2]` → `n[0]`, and `n[0]` again from `n[0]`, playing `clips`
/// (the middle one frames `mid`), with the edges' start windows `w` (absent: the default).
fn three_nodes(n: [&str; 3], clips: [&str; 3], mid: [u32; 2], w: [Option<[u32; 2]>; 5]) -> Value {
    let edge = |from: &str, to: &str, fade: u32, window: Option<[u32; 2]>| json!({"from": from, "to": to, "fade": fade, "window": window});
    json!({
        "nodes": [
            {"name": n[0], "clip": clips[0]},
            {"name": n[1], "clip": clips[1], "frames": mid},
            {"name": n[2], "clip": clips[2]},
        ],
        "edges": [
            edge(n[0], n[1], 10, w[0]),
            edge(n[0], n[0], 6, w[1]),
            edge(n[1], n[0], 10, w[2]),
            edge(n[1], n[2], 12, w[3]),
            edge(n[2], n[0], 8, w[4]),
        ],
    })
}

/// Three moods of the embedded head's own clips.
fn moods() -> Value {
    let names = ["talk", "smile", "surprise"];
    three_nodes(
        names,
        names,
        [0, 59],
        [None, None, Some([20, 40]), None, None],
    )
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

/// A request without a body: its status and JSON answer.
async fn bodiless(server: &TestServer, method: Method, path: &str) -> (u16, Value) {
    call(server, method, path, Value::Null).await
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
    let (_, list) = bodiless(&server, Method::GET, "/v1/rigs/default-head/graphs").await;
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
    let (status, v) = bodiless(&server, Method::GET, "/v1/rigs/default-head/graphs/moods").await;
    assert_eq!(status, 200, "{v}");
    assert_eq!(v["graph"]["edges"].as_array().unwrap().len(), 5);
    let (status, _) = bodiless(
        &server,
        Method::DELETE,
        "/v1/rigs/default-head/graphs/moods",
    )
    .await;
    assert_eq!(status, 204);
    let (status, v) = bodiless(&server, Method::GET, "/v1/rigs/default-head/graphs/moods").await;
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
        post_clip(&server.client, name, body).await;
    }
}

/// A graph over the smooth clips.
fn smooth_graph() -> Value {
    three_nodes(
        ["jaw", "smile", "brow"],
        ["slow-jaw", "slow-smile", "slow-brow"],
        [10, 80],
        [Some([30, 60]), None, Some([20, 40]), None, Some([40, 70])],
    )
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

#[tokio::test]
async fn a_graph_built_from_the_clips_is_stored_and_played() {
    let server = TestServer::start(ServerConfig::default()).await;
    let (status, v) = bodiless(
        &server,
        Method::POST,
        "/v1/rigs/default-head/graphs/auto?auto=1&window=5",
    )
    .await;
    assert_eq!(status, 200, "{v}");
    let edges = v["info"]["graph"]["edges"].as_array().unwrap().len();
    assert!(edges > 3, "{v}");
    assert_eq!(v["costs"].as_array().unwrap().len(), edges);
    let start = v["info"]["graph"]["nodes"][0]["name"]
        .as_str()
        .unwrap()
        .to_string();
    let (status, got) = bodiless(&server, Method::GET, "/v1/rigs/default-head/graphs/auto").await;
    assert_eq!(status, 200);
    assert_eq!(got["graph"], v["info"]["graph"]);
    let info = create(
        &server,
        json!({"heads": [{"head": 1, "rig": "default-head",
                          "graph": {"name": "auto", "start": start, "seed": 5}}]}),
    )
    .await;
    let mut ws = connect(&server, &info.id, json!({"format": "f32"})).await;
    for _ in 0..5 {
        assert_eq!(next_tick(&mut ws).await.heads.len(), 1);
    }
    for (query, needle) in [
        ("", "auto=1"),
        ("?auto=0", "auto=1"),
        ("?auto=1&window=0", "window"),
        ("?auto=1&threshold=-1", "threshold"),
    ] {
        let (status, v) = bodiless(
            &server,
            Method::POST,
            &format!("/v1/rigs/default-head/graphs/auto2{query}"),
        )
        .await;
        assert_eq!((status, code(&v)), (400, "bad_query"), "{query}: {v}");
        assert!(
            v["error"]["message"].as_str().unwrap().contains(needle),
            "{v}"
        );
    }
    server.stop().await;
}

/// The largest distance a vertex of the robot moves between consecutive frames of `clip`
/// (`frames` of them), as the independent evaluator poses it.
fn robot_clip_step(doc: &crate::util::RefDoc, clip: &str, frames: i64) -> f64 {
    let mut prev = robot_pose(doc, clip, 0, &|_| {});
    let mut largest = 0f64;
    for f in 1..frames {
        let p = robot_pose(doc, clip, f, &|_| {});
        let d = prev
            .iter()
            .zip(&p)
            .map(|(a, b)| a.distance(*b))
            .fold(0.0, f64::max);
        largest = largest.max(d);
        prev = p;
    }
    largest
}

/// A server holding RobotExpressive as rig `robot`.
async fn robot_server(config: ServerConfig) -> TestServer {
    let server = TestServer::start(config).await;
    server
        .client
        .upload_rig("robot", upload_bytes(&robot_path()))
        .await
        .expect("upload");
    server
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
async fn a_skinned_heads_transitions_and_joint_changes_do_not_pop() {
    // The reproduction: RobotExpressive (its clips move joints only), a graph Sitting
    // ⇄ Idle with fade 1, one head, an f32 viewer; a PATCH sends it to `sit`, later turns its
    // head by a joint override and then takes the override away.
    let server = robot_server(ServerConfig::default()).await;
    let doc = crate::util::RefDoc::load(&robot_path());
    let largest_step = robot_clip_step(&doc, "Sitting", 13).max(robot_clip_step(&doc, "Idle", 101));
    let bound = 1.5 * largest_step as f32;
    let graph = json!({
        "nodes": [{"name": "sit", "clip": "Sitting"}, {"name": "idle", "clip": "Idle"}],
        "edges": [{"from": "sit", "to": "idle", "fade": 1},
                  {"from": "idle", "to": "sit", "fade": 1}],
    });
    let (status, v) = call(&server, Method::PUT, "/v1/rigs/robot/graphs/rest", graph).await;
    assert_eq!(status, 200, "{v}");
    let info = create(
        &server,
        json!({"fps": 30, "heads": [{"head": 1, "rig": "robot",
               "graph": {"name": "rest", "start": "idle", "seed": 3}}]}),
    )
    .await;
    let mut ws = connect(&server, &info.id, json!({"format": "f32"})).await;
    let turn = glam::Quat::from_rotation_y(0.8).to_array();
    let patches: Vec<(u64, Value)> = vec![
        (10, json!({"head": 1, "node": "sit"})),
        (
            400,
            json!({"head": 1, "joints": {"Head": {"rotation": turn}}}),
        ),
        (700, json!({"head": 1, "joints": {}})),
    ];
    let mut patched_at = 0;
    let mut view = View::default();
    let mut last: Option<(u64, Vec<f32>)> = None;
    let (mut largest, mut compared) = (0f32, 0);
    // Per patch, the ticks its fade showed the frozen pose as the larger share: a jump fades
    // from the clip terms it froze, and a blend's buffer names its largest term, so the same
    // clip frame is named on consecutive ticks while the clock moves the clips (30 fps, one
    // frame a tick) on.
    let mut fading = vec![0u32; patches.len()];
    let mut clips = std::collections::BTreeSet::new();
    let mut named: Option<(u64, String, u32)> = None;
    for _ in 0..1000 {
        let t = next_tick(&mut ws).await;
        view.apply(&t);
        if let Some(b) = t.heads.first().map(|h| h.buffer)
            && let Some(buf) = t.buffers.get(b as usize)
        {
            if let Some((tick, clip, frame)) = &named
                && *tick + 1 == t.tick
                && (clip.as_str(), *frame) == (buf.clip.as_str(), buf.frame)
                && patched_at > 0
            {
                fading[patched_at - 1] += 1;
            }
            named = Some((t.tick, buf.clip.clone(), buf.frame));
            clips.insert(buf.clip.clone());
        }
        let now = view.heads.get(&1).cloned().expect("the head is shown");
        if let Some((tick, prev)) = &last
            && *tick + 1 == t.tick
        {
            let d = max_step(prev, &now);
            largest = largest.max(d);
            compared += 1;
            assert!(
                d <= bound,
                "tick {}: a vertex moved {d} in one tick, more than 1.5 × the clips' largest \
                 step ({bound})",
                t.tick
            );
        }
        last = Some((t.tick, now));
        while patched_at < patches.len() && t.tick >= patches[patched_at].0 {
            let (status, v) = call(
                &server,
                Method::PATCH,
                &format!("/v1/sessions/{}", info.id),
                json!({"change": [patches[patched_at].1]}),
            )
            .await;
            assert_eq!(status, 200, "{v}");
            patched_at += 1;
        }
    }
    eprintln!(
        "largest per-tick step {largest} (bound {bound}, clips' largest step {largest_step}); \
         ticks fading per patch {fading:?}; clips shown {clips:?}; {compared} ticks compared"
    );
    assert_eq!(patched_at, patches.len());
    assert!(compared > 500, "{compared} consecutive ticks compared");
    for (k, n) in fading.iter().enumerate() {
        assert!(*n > 1, "patch {k} faded over more than one tick ({n})");
    }
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
async fn a_graph_built_from_a_skinned_rigs_clips_weighs_what_the_joints_move() {
    // RobotExpressive's clips move joints only: a frame distance of weights alone made every
    // transition free, cut every clip after its first window and dropped most nodes.
    let server = robot_server(ServerConfig::default()).await;
    let (status, v) = bodiless(&server, Method::POST, "/v1/rigs/robot/graphs/auto?auto=1").await;
    assert_eq!(status, 200, "{v}");
    let built: crowdmorph_proto::BuiltGraph = serde_json::from_value(v).expect("BuiltGraph");
    let g = &built.info.graph;
    let rig = server.client.rig("robot").await.expect("rig");
    let diag = glam::DVec3::from(rig.bbox.max.map(f64::from))
        .distance(glam::DVec3::from(rig.bbox.min.map(f64::from)));
    let frames_of = |clip: &str| rig.clips.iter().find(|c| c.name == clip).unwrap().frames;
    let doc = crate::util::RefDoc::load(&robot_path());
    let node = |name: &str| g.nodes.iter().find(|n| n.name == name).unwrap();
    // Each transition's cost against the independent evaluator: the mean over its window of
    // the RMS distance over all the robot's vertices between the frames it joins, as a
    // fraction of the diagonal (the build samples 256 vertices; the tolerance is for that).
    let (window, threshold) = (5u32, 0.02f64);
    let mut transitions = 0;
    let mut positive = 0;
    for (e, &cost) in g.edges.iter().zip(&built.costs).filter(|(e, _)| e.fade > 1) {
        let (from, to) = (node(&e.from), node(&e.to));
        let i = from.frames.unwrap()[0] + e.window.unwrap()[0];
        let j = to.frames.unwrap()[0];
        let mut sum = 0.0;
        for k in 0..window {
            let a = robot_pose(&doc, &from.clip, i64::from(i + k), &|_| {});
            let b = robot_pose(&doc, &to.clip, i64::from(j + k), &|_| {});
            let ms = a
                .iter()
                .zip(&b)
                .map(|(p, q)| p.distance_squared(*q))
                .sum::<f64>()
                / a.len() as f64;
            sum += ms.sqrt();
        }
        let oracle = sum / f64::from(window) / diag;
        let cost = f64::from(cost);
        eprintln!(
            "{} -> {}: cost {cost:.5}, all vertices {oracle:.5}",
            e.from, e.to
        );
        assert!(
            oracle <= 2.0 * threshold,
            "{} -> {}: the frames it joins are {oracle} apart",
            e.from,
            e.to
        );
        assert!(
            (cost - oracle).abs() <= 0.5 * oracle.max(cost) + 1e-4,
            "{} -> {}: cost {cost}, all vertices {oracle}",
            e.from,
            e.to
        );
        transitions += 1;
        positive += usize::from(cost > 0.0);
    }
    assert!(transitions >= 10, "{transitions} transitions");
    assert!(
        positive * 4 >= transitions * 3,
        "transitions between different poses cost something: {positive} of {transitions}"
    );
    // Clips are kept whole: the nodes of a clip the walk plays cover it from its first frame
    // to its last, not just its first window.
    let mut covered: std::collections::BTreeMap<&str, Vec<bool>> = Default::default();
    for n in &g.nodes {
        let f = frames_of(&n.clip);
        let c = covered
            .entry(n.clip.as_str())
            .or_insert_with(|| vec![false; f as usize]);
        let [a, b] = n.frames.unwrap();
        for x in a..=b {
            c[x as usize] = true;
        }
    }
    let whole: Vec<&str> = covered
        .iter()
        .filter(|(_, c)| c.len() > 2 * window as usize && c.iter().all(|&x| x))
        .map(|(n, _)| *n)
        .collect();
    eprintln!(
        "{} nodes, {} edges, {} dropped; whole clips {whole:?}",
        g.nodes.len(),
        g.edges.len(),
        built.dropped_nodes
    );
    assert!(whole.len() >= 3, "clips played whole: {whole:?}");
    assert!(
        g.nodes.len() > built.dropped_nodes as usize,
        "most nodes are kept: {} kept, {} dropped",
        g.nodes.len(),
        built.dropped_nodes
    );
    server.stop().await;
}

/// Uploads clip `name` of `frames` frames to the embedded head: `jawOpen` on a slow raised
/// cosine (every other channel at 0), `frames` × one number of JSON.
async fn upload_long_clip(client: &crowdmorph_client::Client, name: &str, frames: usize) {
    let rows: Vec<[f32; 1]> = (0..frames)
        .map(|f| [0.5 - 0.5 * (std::f32::consts::TAU * f as f32 / 300.0).cos()])
        .collect();
    let body = json!({"fps": 30, "targets": ["jawOpen"], "frames": rows}).to_string();
    post_clip(client, name, body).await;
}

/// Posts the JSON clip `body` to the embedded head as clip `name`, expecting 201.
async fn post_clip(client: &crowdmorph_client::Client, name: &str, body: String) {
    let reply = client
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

/// One node per range of clip `clip`, named `n0`, `n1`, ..., each with a self-loop.
fn nodes_on(clip: &str, ranges: &[[u32; 2]]) -> Value {
    let nodes: Vec<Value> = ranges
        .iter()
        .enumerate()
        .map(|(i, r)| json!({"name": format!("n{i}"), "clip": clip, "frames": r}))
        .collect();
    let edges: Vec<Value> = (0..ranges.len())
        .map(|i| json!({"from": format!("n{i}"), "to": format!("n{i}"), "fade": 1}))
        .collect();
    json!({"nodes": nodes, "edges": edges})
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn graph_work_is_priced_before_it_starts_and_the_name_checked_first() {
    let limit: u64 = 40_000_000;
    let server = TestServer::start(ServerConfig {
        max_graph_work: limit,
        ..ServerConfig::default()
    })
    .await;
    let rig = server.state.registry.get("default-head").unwrap();
    // A clip long enough that measuring it alone is past the limit.
    let per_frame = crowdmorph::server::graphs::frame_work(rig.rig());
    let frames = (limit / per_frame + 2) as usize;
    upload_long_clip(&server.client, "long", frames).await;
    upload_smooth_clips(&server).await;
    let rig = server.state.registry.get("default-head").unwrap();
    let build_price = crowdmorph::graph::build_work(rig.rig(), Default::default());
    eprintln!("a frame costs {per_frame}, the build {build_price}; limit {limit}");
    assert!(build_price > limit);
    let code_and_message = |v: &Value| {
        (
            code(v).to_string(),
            v["error"]["message"].as_str().unwrap_or("").to_string(),
        )
    };
    // The build: refused with what it would cost, naming the flag.
    let (status, v) = bodiless(
        &server,
        Method::POST,
        "/v1/rigs/default-head/graphs/auto?auto=1",
    )
    .await;
    let (c, m) = code_and_message(&v);
    assert_eq!((status, c.as_str()), (413, "graph_too_costly"), "{v}");
    assert!(
        m.contains("--max-graph-work") && m.contains(&limit.to_string()),
        "{m}"
    );
    // A PUT whose nodes play the long clip: its measurement is priced the same way.
    let long = nodes_on("long", &[[0, frames as u32 - 1]]);
    let (status, v) = put(&server, "long", long.clone()).await;
    let (c, m) = code_and_message(&v);
    assert_eq!((status, c.as_str()), (413, "graph_too_costly"), "{v}");
    assert!(m.contains("--max-graph-work"), "{m}");
    // The name is checked before the price, whatever the work would be.
    for path in [
        "/v1/rigs/default-head/graphs/.hidden?auto=1",
        "/v1/rigs/default-head/graphs/bad%20name?auto=1",
    ] {
        let (status, v) = bodiless(&server, Method::POST, path).await;
        assert_eq!((status, code(&v)), (400, "invalid_name"), "{path}: {v}");
    }
    let (status, v) = put(&server, ".hidden", long).await;
    assert_eq!((status, code(&v)), (400, "invalid_name"), "{v}");
    let (_, list) = bodiless(&server, Method::GET, "/v1/rigs/default-head/graphs").await;
    assert_eq!(list["graphs"], json!([]), "nothing refused was stored");
    // Within the limit: nodes sharing frames of one clip, each measured as its own range of
    // frames — checked against the largest step between the node's frames, through the CPU
    // engine.
    let ranges = [
        [0, 89],
        [10, 80],
        [30, 31],
        [45, 45],
        [0, 44],
        [44, 89],
        [5, 20],
    ];
    let (status, v) = put(&server, "overlap", nodes_on("slow-jaw", &ranges)).await;
    assert_eq!(status, 200, "{v}");
    let entry = server.state.registry.get("default-head").unwrap();
    let graph = server
        .state
        .graphs
        .resolved(
            &entry,
            "overlap",
            |b| server.state.queue_memory.reserve(b).ok(),
            limit,
        )
        .expect("resolved");
    let engine = crowdmorph::engine::Engine::cpu();
    let prepared = engine
        .prepare(std::sync::Arc::new(entry.rig().clone()))
        .unwrap();
    let c = entry.clip_index("slow-jaw").unwrap() as u32;
    let frame = |f| {
        crate::util::pose_positions(
            &engine,
            &prepared,
            crowdmorph::rig::Pose::Frame { clip: c, frame: f },
        )
    };
    for (n, [a, b]) in ranges.iter().enumerate() {
        let mut want = 0f32;
        for f in a + 1..=*b {
            want = want.max(max_step(&frame(f - 1), &frame(f)));
        }
        let got = graph.motion(n as u32);
        assert!(
            (got - want).abs() <= 1e-6 * want.max(1e-6),
            "node {n} {:?}: measured {got}, its frames' largest step {want}",
            [a, b]
        );
        if a == b {
            assert_eq!(got, 0.0, "a one-frame node does not move");
        } else {
            assert!(got > 0.0);
        }
    }
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_rig_holds_at_most_max_clips_clips() {
    let server = TestServer::start(ServerConfig {
        max_clips: 6,
        ..ServerConfig::default()
    })
    .await;
    let have = server
        .state
        .registry
        .get("default-head")
        .unwrap()
        .rig()
        .clips
        .len();
    assert_eq!(have, 4, "the embedded head's own clips");
    upload_long_clip(&server.client, "five", 10).await;
    upload_long_clip(&server.client, "six", 10).await;
    let body = json!({"fps": 30, "targets": ["jawOpen"], "frames": [[0.5], [0.6]]}).to_string();
    let reply = server
        .client
        .send(
            Method::POST,
            "/v1/rigs/default-head/clips?name=seven",
            Some("application/json"),
            None,
            Bytes::from(body),
        )
        .await
        .unwrap();
    assert_eq!(
        reply.status,
        413,
        "{}",
        String::from_utf8_lossy(&reply.body)
    );
    let e = reply.error().expect("a JSON error");
    assert_eq!(e.error.code, "too_many_clips");
    assert!(
        e.error.message.contains("--max-clips"),
        "{}",
        e.error.message
    );
    assert_eq!(
        server
            .state
            .registry
            .get("default-head")
            .unwrap()
            .rig()
            .clips
            .len(),
        6
    );
    // After a delete there is room again.
    let (status, _) = bodiless(&server, Method::DELETE, "/v1/rigs/default-head/clips/five").await;
    assert_eq!(status, 204);
    upload_long_clip(&server.client, "seven", 10).await;
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
async fn a_rig_file_with_more_animations_than_max_clips_is_refused() {
    let server = TestServer::start(ServerConfig {
        max_clips: 6,
        ..ServerConfig::default()
    })
    .await;
    let reply = server
        .client
        .send(
            Method::POST,
            "/v1/rigs?name=robot",
            Some("model/gltf-binary"),
            None,
            upload_bytes(&robot_path()),
        )
        .await
        .unwrap();
    assert_eq!(
        reply.status,
        413,
        "{}",
        String::from_utf8_lossy(&reply.body)
    );
    let e = reply.error().expect("a JSON error");
    assert_eq!(e.error.code, "too_many_clips");
    assert!(
        e.error.message.contains("--max-clips"),
        "{}",
        e.error.message
    );
    assert!(server.state.registry.get("robot").is_none());
    server.stop().await;
}

/// The raw bytes of a `POST` with no body, written by hand so that the test can hang up.
async fn hang_up_after(addr: &str, path: &str, wait: std::time::Duration, pid: u32) -> f64 {
    use tokio::io::AsyncWriteExt;
    let mut tcp = tokio::net::TcpStream::connect(addr).await.expect("connect");
    let head = format!("POST {path} HTTP/1.1\r\nhost: {addr}\r\ncontent-length: 0\r\n\r\n");
    tcp.write_all(head.as_bytes()).await.expect("write");
    tokio::time::sleep(wait).await;
    let busy = cores_used(pid, std::time::Duration::from_millis(500)).await;
    drop(tcp);
    busy
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_graph_build_stops_at_its_deadline_or_when_its_client_goes() {
    // The reproduction: a build of long clips with `--admin-timeout-s` short. Its 504
    // came at 11 s (the router's timeout) and the build ran on for 14 CPU-s; the work limit is
    // raised here so that the build is admitted and has to be stopped.
    let (proc, client) = binary(
        "graph-deadline",
        &[
            ("CROWDMORPH_ADMIN_TIMEOUT_S", "4"),
            ("CROWDMORPH_MAX_GRAPH_WORK", "1000000000000000"),
        ],
    )
    .await;
    let pid = proc.child.id();
    for k in 0..8 {
        upload_long_clip(&client, &format!("long{k}"), 2000).await;
    }
    // An invalid name is refused before any of the build's tens of CPU-seconds: far less than
    // one second of CPU (the margin absorbs the request itself and a busy machine).
    let before = cpu_seconds(pid);
    let r = client
        .send(
            Method::POST,
            "/v1/rigs/default-head/graphs/bad%20name?auto=1",
            None,
            None,
            Bytes::new(),
        )
        .await
        .unwrap();
    let spent = cpu_seconds(pid) - before;
    assert_eq!(r.status, 400, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.error().unwrap().error.code, "invalid_name");
    assert!(spent < 1.0, "an invalid name cost {spent:.2} CPU-s");
    // A client that hangs up while the build runs: the build stops. "Busy" only shows the
    // build was running (a shared machine may give it less than a core); "idle" is measured
    // over a second that starts 1.5 s after the hang-up.
    let addr = proc.base.trim_start_matches("http://").to_string();
    let busy = hang_up_after(
        &addr,
        "/v1/rigs/default-head/graphs/gone?auto=1",
        std::time::Duration::from_millis(1000),
        pid,
    )
    .await;
    assert!(busy > 0.3, "the build was running: {busy:.2} cores");
    tokio::time::sleep(std::time::Duration::from_millis(1500)).await;
    let used = cores_used(pid, std::time::Duration::from_secs(1)).await;
    assert!(
        used < 0.25,
        "building for a client that left: {used:.2} cores"
    );
    // The deadline: a 504 at the admin deadline, and the process idle soon after.
    let before = cpu_seconds(pid);
    let r = client
        .send(
            Method::POST,
            "/v1/rigs/default-head/graphs/late?auto=1",
            None,
            None,
            Bytes::new(),
        )
        .await
        .unwrap();
    assert_eq!(r.status, 504, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.error().unwrap().error.code, "deadline_exceeded");
    let until = cpu_seconds(pid) - before;
    assert!(until > 1.0, "the build ran until its 504: {until:.2} CPU-s");
    tokio::time::sleep(std::time::Duration::from_millis(1500)).await;
    let used = cores_used(pid, std::time::Duration::from_secs(1)).await;
    assert!(
        used < 0.25,
        "the process still uses {used:.2} cores after the 504"
    );
    let page = client.metrics().await.expect("metrics");
    for reason in ["deadline", "dropped"] {
        assert_eq!(
            metric(
                &page,
                &format!("crowdmorph_cancelled_total{{work=\"graph\",reason=\"{reason}\"}}")
            ),
            1.0,
            "{reason}"
        );
    }
    let (_, list) = {
        let r = client
            .send(
                Method::GET,
                "/v1/rigs/default-head/graphs",
                None,
                None,
                Bytes::new(),
            )
            .await
            .unwrap();
        (r.status, serde_json::from_slice::<Value>(&r.body).unwrap())
    };
    assert_eq!(list["graphs"], json!([]), "no stopped build was stored");
    eprintln!("until the 504: {until:.2} CPU-s; while building {busy:.2} cores");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_thousand_nodes_on_one_clip_are_measured_once() {
    // The 1,024-node PUT whose nodes all play one 2,048-frame clip: it took 114 s,
    // measuring the same frames once per node. Its cost is compared with a PUT of the clip
    // as one node, in CPU time of the server process; the margin (3× and half a second) is
    // far below the 1,024× of a measurement per node.
    let (proc, client) = binary("graph-nodes", &[]).await;
    let pid = proc.child.id();
    upload_long_clip(&client, "long", 2048).await;
    let put_cpu = |name: &'static str, graph: Value| {
        let client = client.clone();
        async move {
            let before = cpu_seconds(pid);
            let r = client
                .send(
                    Method::PUT,
                    &format!("/v1/rigs/default-head/graphs/{name}"),
                    Some("application/json"),
                    None,
                    Bytes::from(graph.to_string()),
                )
                .await
                .unwrap();
            assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
            cpu_seconds(pid) - before
        }
    };
    let one = put_cpu("one", nodes_on("long", &[[0, 2047]])).await;
    let many = put_cpu("many", nodes_on("long", &[[0, 2047]; 1024])).await;
    eprintln!("one node: {one:.3} CPU-s; 1,024 nodes: {many:.3} CPU-s");
    assert!(
        many < 3.0 * one + 0.5,
        "1,024 nodes on one clip cost {many:.2} CPU-s, one node {one:.2}"
    );
}
