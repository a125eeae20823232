//! Poses for clients that blend themselves (issue 47 item 6): `"format": "weights"` crowd
//! frames and `"output": "weights"` viewers get each head's final weights (binary16) and moved
//! joints. The weights are checked against the f64 weight-space sums `tests/server/layers.rs`
//! writes from the clip tables; applied to the rig by the f64 oracle (neutral + Σ w·delta, then
//! the reference skinning of the file) they reproduce the server's own vertices for the head,
//! within the bound binary16's rounding of the weights allows. Unchanged heads are marked
//! unchanged, clones share a pose, a session whose viewers all want poses submits no blend,
//! and bad combinations are named 4xx answers or 1008 closes.

use std::collections::HashMap;

use crowdmorph::server::ServerConfig;
use crowdmorph_client::{Encoding, Method};
use crowdmorph_proto::{
    BlendLayer, CrowdFrameRequest, CrowdPoseResponse, Format, HEAD_MISSING, HEAD_UNCHANGED, Head,
    HeadPose, OutputOptions, StreamMessage, StreamState,
};
use futures_util::SinkExt;
use glam::DVec3;
use serde_json::json;

use super::layers::{channels, frame_weights, layered_heads};
use super::sessions::{View, call, connect, create, next_close, next_raw, next_tick};
use super::{TestServer, positions_f32};
use crate::util::rig_oracle;

/// Largest distance a binary16 rounding of `w` (and, for a layered or live head, the server's
/// 2^-12 quantization before it) moves a weight.
fn weight_tolerance(w: f64) -> f64 {
    w.abs() * 2f64.powi(-11) + 2f64.powi(-13) + 2f64.powi(-24)
}

/// Per channel of `rig`, the longest delta of its targets.
fn longest_deltas(rig: &crowdmorph::rig::Rig) -> Vec<f64> {
    let mut out = vec![0.0f64; rig.targets.len()];
    for p in rig.primitives.iter() {
        for t in &p.targets {
            let m = t
                .positions
                .iter()
                .map(|d| f64::from(d.length()))
                .fold(0.0, f64::max);
            out[t.target as usize] = out[t.target as usize].max(m);
        }
    }
    out
}

/// How far the vertices of weights `w` can be from those of weights within
/// [`weight_tolerance`] of them, plus the engines' f32 evaluation (1e-5 of the diagonal).
fn vertex_tolerance(rig: &crowdmorph::rig::Rig, w: &[f64], diag: f64) -> f64 {
    longest_deltas(rig)
        .iter()
        .zip(w)
        .map(|(d, w)| d * weight_tolerance(*w))
        .sum::<f64>()
        + 1e-5 * diag
}

fn diagonal(rig: &crowdmorph::rig::Rig) -> f64 {
    let b = rig.bbox();
    f64::from((b.max - b.min).length())
}

fn f64s(pose: &HeadPose) -> Vec<f64> {
    pose.weights_f32().into_iter().map(f64::from).collect()
}

/// Asserts that `pose`'s weights are `want` within binary16's rounding.
fn assert_weights(pose: &HeadPose, want: &[f64], what: &str) {
    let got = f64s(pose);
    assert_eq!(got.len(), want.len(), "{what}: one weight per channel");
    for (k, (g, w)) in got.iter().zip(want).enumerate() {
        assert!(
            (g - w).abs() <= weight_tolerance(*w),
            "{what}: channel {k} is {g}, the oracle's {w}"
        );
    }
}

/// `POST /v1/crowd/frame` of `req` for weights, in `enc`, decoded with the proto types
/// directly (not through the client's helper), with the number of bytes.
async fn poses(server: &TestServer, req: &CrowdFrameRequest, enc: Encoding) -> CrowdPoseResponse {
    let mut req = req.clone();
    req.output.format = Format::Weights;
    let reply = server
        .client
        .send(
            Method::POST,
            "/v1/crowd/frame",
            Some(enc.content_type()),
            Some(enc.content_type()),
            crowdmorph_client::Client::encode(&req, enc).expect("encode"),
        )
        .await
        .expect("an answer");
    assert_eq!(
        reply.status,
        200,
        "{}",
        String::from_utf8_lossy(&reply.body)
    );
    match enc {
        Encoding::Json => serde_json::from_slice(&reply.body).expect("CrowdPoseResponse JSON"),
        Encoding::Bincode => {
            assert_eq!(reply.body[0], 4, "a weights answer starts with its format");
            crowdmorph_proto::wire::response_from_bincode(&reply.body).expect("CrowdPoseResponse")
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_weights_crowd_frame_is_each_heads_final_pose_in_json_and_bincode() {
    let server = TestServer::start(ServerConfig::default()).await;
    let rig = crowdmorph::embedded::default_rig();
    let diag = diagonal(&rig);
    let mut cases = layered_heads(&rig);
    // A plain clip frame, a blend, and a clone of the first layered head.
    cases.push((
        Head::playing(20, "default-head", "talk", 17),
        frame_weights(&rig, "talk", 17),
    ));
    let (talk, smile) = (
        frame_weights(&rig, "talk", 10),
        frame_weights(&rig, "smile", 3),
    );
    cases.push((
        Head {
            blend: vec![BlendLayer {
                clip: "smile".into(),
                frame: 3,
                t: 0.25,
            }],
            ..Head::playing(21, "default-head", "talk", 10)
        },
        talk.iter()
            .zip(&smile)
            .map(|(a, b)| 0.75 * a + 0.25 * b)
            .collect(),
    ));
    let clone = Head {
        head: 22,
        ..cases[0].0.clone()
    };
    let clone_weights = cases[0].1.clone();
    cases.push((clone, clone_weights));
    let req = CrowdFrameRequest {
        heads: cases.iter().map(|(h, _)| h.clone()).collect(),
        output: OutputOptions::default(),
        wrap: true,
    };
    let json = poses(&server, &req, Encoding::Json).await;
    let bin = poses(&server, &req, Encoding::Bincode).await;
    assert_eq!(
        (&json.format, &json.poses, &json.heads),
        (&bin.format, &bin.poses, &bin.heads),
        "JSON and bincode carry the same poses"
    );
    assert_eq!(bin.format, Format::Weights);
    assert_eq!(bin.heads.len(), cases.len());
    let last = cases.len() - 1;
    assert_eq!(
        bin.heads[last].buffer, bin.heads[0].buffer,
        "a clone shares its pose"
    );
    assert_eq!(bin.poses.len(), cases.len() - 1, "the other heads differ");
    // The server's own vertices of the same heads.
    let (frame, _) = server
        .client
        .crowd_frame(&req, Encoding::Bincode)
        .await
        .expect("frame");
    for (i, (head, want)) in cases.iter().enumerate() {
        assert_eq!(bin.heads[i].head, head.head);
        let pose = &bin.poses[bin.heads[i].buffer as usize];
        assert_weights(pose, want, &format!("head {}", head.head));
        assert!(pose.joints.is_empty(), "the embedded head has no skeleton");
        let (oracle, _) = rig_oracle(&rig, &f64s(pose));
        let b = &frame.buffers[frame.heads[i].buffer as usize];
        let server_vertices = positions_f32(frame.format, b);
        let d = crate::util::max_abs_diff(&server_vertices, &oracle);
        let tol = vertex_tolerance(&rig, &f64s(pose), diag);
        assert!(
            d <= tol,
            "head {}: its pose draws {d:e} away from the server's vertices (bound {tol:e}, \
             diagonal {diag})",
            head.head
        );
    }
    // The client's helper asks for the same.
    let (helper, len) = server
        .client
        .crowd_poses(&req, Encoding::Bincode)
        .await
        .expect("poses");
    assert_eq!(helper.poses, bin.poses);
    // 51 binary16 weights and a few bytes a pose: far from 51 × 3 × 4 bytes a vertex.
    assert!(len < 130 * bin.poses.len() + 64, "{len} bytes");
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_weights_viewer_gets_each_heads_final_pose_and_unchanged_heads_stay_unchanged() {
    let server = TestServer::start(ServerConfig::default()).await;
    let rig = crowdmorph::embedded::default_rig();
    let diag = diagonal(&rig);
    let clip_fps = f64::from(rig.clips[rig.clip_index("talk").expect("talk")].fps);
    // Ticks at twice the clips' rate: every frame lasts two ticks, so every other tick
    // changes nothing.
    let info = create(
        &server,
        json!({"fps": 2.0 * clip_fps, "heads": [
            {"head": 1, "rig": "default-head", "clip": "talk", "offset": 3,
             "layers": [
                {"clip": "smile", "frame": 5, "weight": 0.6, "mask": "lower_face"},
                {"clip": "surprise", "frame": 20, "weight": 0.5, "mode": "additive",
                 "reference": 0, "mask": {"eyeBlink_L": 1, "eyeBlink_R": 0.5}}],
             "clamp": [0, 1]},
            {"head": 2, "rig": "default-head", "clip": "talk", "offset": 3, "position": [1, 0, 0]},
            {"head": 3, "rig": "default-head", "clip": "talk", "offset": 3, "position": [2, 0, 0]},
            {"head": 4, "rig": "default-head", "clip": "idle", "offset": 5, "position": [3, 0, 0]}]}),
    )
    .await;
    let lower = channels(
        &rig,
        &crowdmorph::rig::builtin_mask("lower_face").expect("mask"),
    );
    let blinks = channels(&rig, &["eyeBlinkLeft", "eyeBlinkRight"]);
    let at = |clip: &str, f: u64| {
        let c = &rig.clips[rig.clip_index(clip).expect("clip")];
        frame_weights(&rig, clip, (f % u64::from(c.frames)) as u32)
    };
    // Each head's weights at a tick: frame `offset + floor((tick − 1) / 2)` of its clip, and
    // the layered head's sum (layers.rs, "a session head's layers ...").
    let want = |head: u64, tick: u64| -> Vec<f64> {
        let e = (tick - 1) / 2;
        match head {
            1 => {
                let (smile, s, s0) = (
                    at("smile", 5 + e),
                    at("surprise", 20 + e),
                    at("surprise", 0),
                );
                let mut w = at("talk", 3 + e);
                for &k in &lower {
                    w[k] = 0.4 * w[k] + 0.6 * smile[k];
                }
                for (&k, m) in blinks.iter().zip([1.0, 0.5]) {
                    w[k] += 0.5 * m * (s[k] - s0[k]);
                }
                w.iter_mut().for_each(|v| *v = v.clamp(0.0, 1.0));
                w
            }
            2 | 3 => at("talk", 3 + e),
            _ => at("idle", 5 + e),
        }
    };
    let mut ws = connect(&server, &info.id, json!({"output": "weights"})).await;
    let mut vs = connect(&server, &info.id, json!({"format": "f32"})).await;
    let mut state = StreamState::new();
    let mut view = View::default();
    let mut poses_at: HashMap<u64, Vec<HeadPose>> = HashMap::new();
    let mut vertices_at: HashMap<u64, Vec<Vec<f32>>> = HashMap::new();
    let (mut unchanged, mut changed, mut prev) = (0, 0, 0u64);
    for i in 0..24 {
        let raw = next_raw(&mut ws).await;
        assert_eq!(raw[0], 5, "a weights viewer gets variant 5");
        let m: StreamMessage =
            crowdmorph_proto::wire::response_from_bincode(&raw).expect("StreamMessage");
        let StreamMessage::Poses(p) = m.clone() else {
            panic!("asked for weights, got {m:?}")
        };
        assert_eq!(p.layout.is_some(), i == 0, "the layout comes once");
        assert_eq!(p.timings.compute_us, 0, "no engine work");
        state.apply(m).expect("the message applies");
        let tick = p.tick;
        if p.heads.iter().all(|h| h.buffer == HEAD_UNCHANGED) {
            assert!(p.poses.is_empty(), "nothing changed, nothing sent");
            if tick == prev + 1 {
                unchanged += 1;
            }
        } else {
            // Heads 2 and 3 are clones: one pose.
            assert_eq!(p.heads[1].buffer, p.heads[2].buffer, "{:?}", p.heads);
            assert!(p.heads.iter().all(|h| h.buffer != HEAD_MISSING));
            if tick == prev + 1 {
                changed += 1;
            }
        }
        prev = tick;
        let shown: Vec<HeadPose> = (1..=4)
            .map(|h| state.pose(h).expect("every head has a pose").clone())
            .collect();
        for (h, pose) in (1..=4).zip(&shown) {
            assert_weights(pose, &want(h, tick), &format!("tick {tick}, head {h}"));
        }
        poses_at.insert(tick, shown);
        // The vertex viewer's ticks, to compare with.
        let t = next_tick(&mut vs).await;
        view.apply(&t);
        vertices_at.insert(
            t.tick,
            (1..=4).map(|h| view.heads[&h].clone()).collect::<Vec<_>>(),
        );
    }
    assert!(
        unchanged >= 2 && changed >= 2,
        "unchanged {unchanged}, changed {changed}"
    );
    let mut compared = 0;
    for (tick, shown) in &poses_at {
        let Some(vertices) = vertices_at.get(tick) else {
            continue;
        };
        for (h, (pose, server_vertices)) in shown.iter().zip(vertices).enumerate() {
            let (oracle, _) = rig_oracle(&rig, &f64s(pose));
            let d = crate::util::max_abs_diff(server_vertices, &oracle);
            let tol = vertex_tolerance(&rig, &f64s(pose), diag);
            assert!(
                d <= tol,
                "tick {tick}, head {}: {d:e} from the server's vertices (bound {tol:e})",
                h + 1
            );
        }
        compared += 1;
    }
    assert!(compared >= 3, "only {compared} ticks seen by both viewers");
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_session_watched_only_for_weights_submits_no_blend() {
    let server = TestServer::start(ServerConfig::default()).await;
    let heads: Vec<serde_json::Value> = (0..20)
        .map(|i| json!({"head": i, "rig": "default-head", "clip": "talk", "offset": i}))
        .collect();
    let info = create(&server, json!({"fps": 30, "heads": heads})).await;
    let mut ws = connect(&server, &info.id, json!({"output": "weights"})).await;
    // A second one has its messages packed: the same poses once inflated.
    let mut packed = connect(
        &server,
        &info.id,
        json!({"output": "weights", "compression": "deflate"}),
    )
    .await;
    let (mut state, mut unpacked) = (StreamState::new(), StreamState::new());
    let mut seen: HashMap<u64, Vec<HeadPose>> = HashMap::new();
    let mut seen_packed: HashMap<u64, Vec<HeadPose>> = HashMap::new();
    let poses_of = |s: &StreamState| -> Vec<HeadPose> {
        (0..20)
            .map(|h| s.pose(h).expect("a pose").clone())
            .collect()
    };
    for _ in 0..8 {
        let raw = next_raw(&mut ws).await;
        let m: StreamMessage =
            crowdmorph_proto::wire::response_from_bincode(&raw).expect("StreamMessage");
        state.apply(m).expect("applies");
        seen.insert(state.tick(), poses_of(&state));
        let raw = next_raw(&mut packed).await;
        assert_eq!(raw[0], 3, "packed");
        unpacked.receive(&raw).expect("inflates and applies");
        seen_packed.insert(unpacked.tick(), poses_of(&unpacked));
    }
    let mut same = 0;
    for (tick, p) in &seen_packed {
        if let Some(plain) = seen.get(tick) {
            assert_eq!(p, plain, "tick {tick}");
            same += 1;
        }
    }
    assert!((0..20).all(|h| state.pose(h).is_some()));
    // An update may not give it a LOD level either.
    ws.send(tokio_tungstenite::tungstenite::Message::text(
        r#"{"lod": 1}"#,
    ))
    .await
    .expect("update");
    let (code, reason) = next_close(&mut ws).await;
    assert_eq!(code, 1008, "{reason}");
    assert!(reason.contains("LOD"), "{reason}");
    assert!(same >= 1, "no tick seen by both viewers");
    let s = super::sessions::info(&server, &info.id).await;
    assert!(s.stats.ticks >= 6, "{:?}", s.stats);
    assert_eq!(s.stats.jobs, 0, "no job went to the batcher: {:?}", s.stats);
    server.stop().await;
}

/// A skinned rig's poses: the rotations (and translations) of the nodes a clip frame and an
/// override move are the file's own, sampled by the reference reader; posed by the reference
/// skinning they give the server's vertices.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
async fn a_skinned_heads_pose_is_the_files_joints_and_reproduces_its_vertices() {
    use crate::util::RefDoc;
    use crate::util::skin::Local;
    let path = crate::util::data_dir().join("robot-expressive/RobotExpressive.glb");
    let server = TestServer::start(ServerConfig::default()).await;
    let info = server
        .client
        .upload_rig("robot", super::upload_bytes(&path))
        .await
        .expect("upload");
    let names = server.client.rig_channels("robot").await.expect("channels");
    assert_eq!(
        names.targets, info.targets,
        "the robot has no split targets"
    );
    assert!(!names.nodes.is_empty());
    let doc = RefDoc::load(&path);
    let doc_names: Vec<String> = doc.json["nodes"]
        .as_array()
        .expect("nodes")
        .iter()
        .map(|n| n["name"].as_str().unwrap_or("").to_string())
        .collect();
    let doc_node = |name: &str| -> usize {
        let found: Vec<usize> = (0..doc_names.len())
            .filter(|&i| doc_names[i] == name)
            .collect();
        assert_eq!(found.len(), 1, "node {name:?} is one node of the file");
        found[0]
    };
    // An override on a node the run turns: its rotation replaces the clip's.
    let turned = "Head";
    let q = glam::DQuat::from_xyzw(0.0, 0.2, 0.0, 0.98).normalize();
    let heads = vec![
        Head::playing(1, "robot", "Running", 9),
        Head {
            joints: crowdmorph_proto::JointOverrides::rotation(
                turned,
                [q.x as f32, q.y as f32, q.z as f32, q.w as f32],
            ),
            ..Head::playing(2, "robot", "Running", 9)
        },
    ];
    let req = CrowdFrameRequest {
        heads,
        output: OutputOptions::default(),
        wrap: true,
    };
    let posed = poses(&server, &req, Encoding::Bincode).await;
    let (frame, _) = server
        .client
        .crowd_frame(&req, Encoding::Bincode)
        .await
        .expect("frame");
    let diag = {
        let (lo, hi) = (info.bbox.min, info.bbox.max);
        DVec3::from(hi.map(f64::from)).distance(DVec3::from(lo.map(f64::from)))
    };
    let rest = doc.rest_locals();
    let trs = |l: &Local| match *l {
        Local::Trs(t, r, s) => (t, r.normalize(), s),
        Local::Matrix(_) => panic!("a matrix node moves"),
    };
    for i in 0..2 {
        let pose = &posed.poses[posed.heads[i].buffer as usize];
        let mut want = doc.locals_at("Running", 9.0 / 30.0);
        if i == 1 {
            let n = doc_node(turned);
            let (t, _, s) = trs(&want[n]);
            want[n] = Local::Trs(t, q, s);
        }
        // Every node the pose lists is the file's, sampled by the reference reader.
        let mut locals = rest.clone();
        let mut listed = std::collections::BTreeSet::new();
        for j in &pose.joints {
            let name = &names.nodes[j.node as usize];
            let n = doc_node(name);
            listed.insert(n);
            let (wt, wr, ws) = trs(&want[n]);
            let (rt, _, rs) = trs(&rest[n]);
            let r = glam::DQuat::from_array(j.rotation.map(f64::from));
            assert!(
                r.dot(wr).abs() >= 1.0 - 1e-7,
                "head {i}, node {name:?}: rotation {r:?}, the file's {wr:?}"
            );
            let t = j.translation.map_or(rt, |t| DVec3::from(t.map(f64::from)));
            let s = j.scale.map_or(rs, |s| DVec3::from(s.map(f64::from)));
            assert!(
                t.distance(wt) <= 1e-5 * diag,
                "head {i}, node {name:?}: {t} vs {wt}"
            );
            assert!(
                s.distance(ws) <= 1e-5,
                "head {i}, node {name:?}: {s} vs {ws}"
            );
            locals[n] = Local::Trs(t, r, s);
        }
        // And every node the run turns is listed.
        for (n, (w, r)) in want.iter().zip(&rest).enumerate() {
            let ((wt, wr, ws), (rt, rr, rs)) = (trs(w), trs(r));
            let moved = wr.dot(rr).abs() < 1.0 - 1e-6
                || wt.distance(rt) > 1e-5 * diag
                || ws.distance(rs) > 1e-5;
            if moved && names.nodes.contains(&doc_names[n]) {
                assert!(
                    listed.contains(&n),
                    "head {i}: node {:?} moved, not listed",
                    doc_names[n]
                );
            }
        }
        let head_turned = pose
            .joints
            .iter()
            .any(|j| names.nodes[j.node as usize] == turned);
        assert!(head_turned, "the run (and the override) turn {turned}");
        // Posed by the reference skinning, the pose is the server's vertices.
        let oracle: Vec<DVec3> = doc
            .pose(&locals)
            .into_iter()
            .flat_map(|p| p.positions)
            .collect();
        let b = &frame.buffers[frame.heads[i].buffer as usize];
        let d = crate::util::max_abs_diff(&positions_f32(frame.format, b), &oracle);
        // Overrides are quantized to 2^-20 a component; f32 skinning.
        assert!(d <= 2e-4 * diag, "head {i}: off by {d:e} of {diag}");
    }
    assert_ne!(
        posed.heads[0].buffer, posed.heads[1].buffer,
        "the override is part of the pose"
    );
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn weights_with_what_they_cannot_carry_are_refused_by_name() {
    let server = TestServer::start(ServerConfig::default()).await;
    // Crowd frames: normals, a LOD level.
    for (body, what) in [
        (
            json!({"heads": [{"head": 1, "rig": "default-head", "clip": "talk"}],
                   "output": {"format": "weights", "normals": true}}),
            "normals",
        ),
        (
            json!({"heads": [{"head": 1, "rig": "default-head", "clip": "talk", "lod": 1}],
                   "output": {"format": "weights"}}),
            "lod",
        ),
    ] {
        let (status, v) = call(&server, Method::POST, "/v1/crowd/frame", body).await;
        assert_eq!(status, 400, "{v}");
        assert_eq!(v["error"]["code"], "invalid_output", "{v}");
        assert!(
            v["error"]["message"]
                .as_str()
                .expect("message")
                .contains(what),
            "{v}"
        );
    }
    // A head the plan refuses is refused as for vertices.
    let (status, v) = call(
        &server,
        Method::POST,
        "/v1/crowd/frame",
        json!({"heads": [{"head": 1, "rig": "default-head", "clip": "nope"}],
               "output": {"format": "weights"}}),
    )
    .await;
    assert_eq!(
        (status, v["error"]["code"].as_str()),
        (404, Some("unknown_clip"))
    );
    // Load tests measure vertex buffers.
    let (status, v) = call(
        &server,
        Method::POST,
        "/v1/loadtest",
        json!({"rate": 10, "duration_s": 0.5, "crowd": {"format": "weights"}}),
    )
    .await;
    assert_eq!(status, 400, "{v}");
    assert_eq!(v["error"]["code"], "invalid_loadtest", "{v}");
    // Viewers: the hello names what does not go together.
    let info = create(
        &server,
        json!({"heads": [{"head": 1, "rig": "default-head", "clip": "talk"}]}),
    )
    .await;
    for (hello, why) in [
        (json!({"format": "weights"}), "output"),
        (json!({"output": "weights", "temporal": true}), "temporal"),
        (json!({"output": "weights", "format": "q16"}), "format"),
        (json!({"output": "weights", "normals": true}), "normals"),
        (json!({"output": "weights", "layers": true}), "layer"),
        (json!({"output": "weights", "lod": 2}), "LOD"),
    ] {
        let mut ws = connect(&server, &info.id, hello.clone()).await;
        let (code, reason) = next_close(&mut ws).await;
        assert_eq!(code, 1008, "{hello}: {reason}");
        assert!(reason.contains(why), "{hello}: {reason}");
    }
    // The channels of a rig, and of none.
    let rig = crowdmorph::embedded::default_rig();
    let names = server
        .client
        .rig_channels("default-head")
        .await
        .expect("channels");
    assert_eq!(names.targets, rig.channel_labels().into_vec());
    assert!(names.nodes.is_empty());
    super::api_error(server.client.rig_channels("nope").await, 404, "unknown_rig");
    server.stop().await;
}

/// Average bytes a message of `hello`'s viewer of session `id` takes, over `n` messages after
/// the first (which carries the layout).
async fn bytes_per_message(
    server: &TestServer,
    id: &str,
    hello: serde_json::Value,
    n: usize,
) -> f64 {
    let mut ws = connect(server, id, hello).await;
    let _first = next_raw(&mut ws).await;
    let mut total = 0usize;
    for _ in 0..n {
        total += next_raw(&mut ws).await.len();
    }
    total as f64 / n as f64
}

/// The note's numbers: bytes per viewer per tick with `"output": "weights"` against q16
/// vertices, for a crowd of `heads` heads of `rig` that all change every tick.
async fn weights_against_q16(server: &TestServer, rig: &str, clip: &str, heads: u64) -> (f64, f64) {
    let crowd: Vec<serde_json::Value> = (0..heads)
        .map(|i| json!({"head": i, "rig": rig, "clip": clip, "offset": 7 * i}))
        .collect();
    let info = create(server, json!({"fps": 30, "heads": crowd})).await;
    let weights = bytes_per_message(server, &info.id, json!({"output": "weights"}), 10).await;
    let q16 = bytes_per_message(server, &info.id, json!({"format": "q16"}), 10).await;
    let (status, _) = call(
        server,
        Method::DELETE,
        &format!("/v1/sessions/{}", info.id),
        serde_json::Value::Null,
    )
    .await;
    assert_eq!(status, 204);
    (weights, q16)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bytes_per_tick_with_weights_against_q16_on_the_embedded_head() {
    let server = TestServer::start(ServerConfig::default()).await;
    let heads = 50;
    let (weights, q16) = weights_against_q16(&server, "default-head", "talk", heads).await;
    println!(
        "default-head, {heads} heads changing every tick: {weights:.0} bytes per tick with \
         output weights, {q16:.0} with q16 vertices ({:.1}x)",
        q16 / weights
    );
    // 51 binary16 weights a head, and its entry: about 110 bytes a head.
    assert!(weights <= heads as f64 * 120.0 + 64.0, "{weights}");
    assert!(q16 > 10.0 * weights, "{q16} against {weights}");
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
async fn bytes_per_tick_with_weights_against_q16_on_ict_facekit() {
    let server = TestServer::start(ServerConfig::default()).await;
    let path = crate::util::data_dir().join("ict-facekit/ict_facekit_53.glb");
    let info = server
        .client
        .upload_rig("ict", super::upload_bytes(&path))
        .await
        .expect("upload");
    let clip = super::random_clip_json(&info.targets, 64, 47);
    let r = server
        .client
        .send(
            Method::POST,
            "/v1/rigs/ict/clips?name=random",
            Some("application/json"),
            None,
            bytes::Bytes::from(clip),
        )
        .await
        .expect("clip upload");
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let heads = 8;
    let (weights, q16) = weights_against_q16(&server, "ict", "random", heads).await;
    println!(
        "ict ({} vertices, {} targets), {heads} heads changing every tick: {weights:.0} bytes \
         per tick with output weights, {q16:.0} with q16 vertices ({:.0}x)",
        info.vertices,
        info.targets.len(),
        q16 / weights
    );
    assert!(weights <= heads as f64 * 125.0 + 64.0, "{weights}");
    assert!(q16 > 1000.0 * weights, "{q16} against {weights}");
    server.stop().await;
}
