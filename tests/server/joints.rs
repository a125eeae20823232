//! Joints over HTTP: per-head overrides in crowd frames, renders and sessions (posed as the
//! independent evaluator poses them, deduplicated after quantization, cut by far LOD levels,
//! refused with the problem named), and Live Link Face's head and eye columns in CSV clips,
//! turned into joint tables through the rig's joint map (its own, or the defaults), kept
//! across a restart.

use bytes::Bytes;
use crowdmorph::server::ServerConfig;
use crowdmorph_client::{Encoding, Method};
use crowdmorph_proto::{
    CrowdFrameRequest, Format, Head, JointChannelSpec, JointMapSpec, JointOverrides, OutputOptions,
};
use glam::{DMat4, DQuat, DVec3};
use serde_json::json;

use super::sessions::{View, call, connect, create, next_tick};
use super::{
    TestServer, api_error, max_distance, positions_f32, stored_config, temp_dir, upload_bytes,
};
use crate::util::RefDoc;
use crate::util::builder::skinned_triangle_rig;
use crate::util::skin::Local;

pub(super) fn robot_path() -> std::path::PathBuf {
    crate::util::data_dir().join("robot-expressive/RobotExpressive.glb")
}

fn head(id: u64, rig: &str, clip: &str, frame: i64, lod: u32, joints: JointOverrides) -> Head {
    Head {
        head: id,
        rig: rig.into(),
        clip: clip.into(),
        frame,
        lod,
        joints,
        ..Default::default()
    }
}

fn request(heads: Vec<Head>) -> CrowdFrameRequest {
    CrowdFrameRequest {
        heads,
        output: OutputOptions {
            normals: false,
            format: Format::F32,
        },
        wrap: true,
    }
}

/// Each head's f32 positions and buffer index.
async fn frame(server: &TestServer, req: &CrowdFrameRequest) -> (Vec<Vec<f32>>, Vec<u32>) {
    let (resp, _) = server
        .client
        .crowd_frame(req, Encoding::Bincode)
        .await
        .expect("frame");
    let positions = resp
        .heads
        .iter()
        .map(|h| positions_f32(Format::F32, &resp.buffers[h.buffer as usize]))
        .collect();
    (positions, resp.heads.iter().map(|h| h.buffer).collect())
}

/// A server holding the skinned triangle (nodes `Root` and `Jaw`, clips `open` and `wag`) as
/// rig `jaw`.
async fn jaw_server() -> TestServer {
    let server = TestServer::start(ServerConfig::default()).await;
    let (b, _) = skinned_triangle_rig();
    server
        .client
        .upload_rig("jaw", Bytes::from(b.to_glb()))
        .await
        .expect("upload");
    server
}

fn diff(a: &[f32], b: &[f32]) -> f32 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

/// The glTF node index named `name`.
fn node(doc: &RefDoc, name: &str) -> usize {
    doc.json["nodes"]
        .as_array()
        .expect("nodes")
        .iter()
        .position(|n| n["name"].as_str() == Some(name))
        .unwrap_or_else(|| panic!("no node {name}"))
}

/// The robot's posed positions, all primitives concatenated, with `set` applied to its
/// locals first.
pub(super) fn robot_pose(
    doc: &RefDoc,
    clip: &str,
    frame: i64,
    set: &dyn Fn(&mut Vec<Local>),
) -> Vec<DVec3> {
    let mut locals = doc.locals_at(clip, frame as f64 / 30.0);
    set(&mut locals);
    doc.pose(&locals)
        .into_iter()
        .flat_map(|p| p.positions)
        .collect()
}

fn set_rotation(locals: &mut [Local], n: usize, q: DQuat) {
    if let Local::Trs(_, r, _) = &mut locals[n] {
        *r = q;
    } else {
        panic!("node {n} is given as a matrix");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
async fn joint_overrides_turn_the_robots_head_and_clones_stay_one_job() {
    let path = robot_path();
    let server = TestServer::start(ServerConfig::default()).await;
    let info = server
        .client
        .upload_rig("robot", upload_bytes(&path))
        .await
        .expect("upload");
    let doc = RefDoc::load(&path);
    let diag = {
        let (lo, hi) = (info.bbox.min, info.bbox.max);
        DVec3::from(hi.map(f64::from)).distance(DVec3::from(lo.map(f64::from)))
    };
    let turn = DQuat::from_rotation_y(0.7) * DQuat::from_rotation_x(0.2);
    let q = turn.as_quat().to_array();
    // Float noise and the other sign of the same rotation are the same override.
    let noisy = q.map(|c| c * (1.0 + 3e-8));
    let flipped = q.map(|c| -c);
    let other = DQuat::from_rotation_y(-0.4).as_quat().to_array();
    let wave = |id: u64, joints: JointOverrides| head(id, "robot", "Wave", 20, 0, joints);
    let req = request(vec![
        wave(0, JointOverrides::default()),
        wave(1, JointOverrides::rotation("Head", q)),
        wave(2, JointOverrides::rotation("Head", noisy)),
        wave(3, JointOverrides::rotation("Head", flipped)),
        wave(4, JointOverrides::rotation("Head", other)),
    ]);
    let (got, buffers) = frame(&server, &req).await;
    assert_eq!(
        buffers,
        [0, 1, 1, 1, 2],
        "three unique jobs among five heads"
    );
    let head_node = node(&doc, "Head");
    let want = robot_pose(&doc, "Wave", 20, &|l| set_rotation(l, head_node, turn));
    let d = max_distance(&got[1], &want);
    assert!(d <= 1e-5 * diag, "the turned head is off by {d:e}");
    let plain = robot_pose(&doc, "Wave", 20, &|_| {});
    assert!(max_distance(&got[0], &plain) <= 1e-5 * diag);
    assert!(
        max_distance(&got[1], &plain) > 1e-2 * diag,
        "the override moves the head"
    );
    // JSON carries the same override as an object by node name.
    let body = json!({"heads": [{"head": 9, "rig": "robot", "clip": "Wave", "frame": 20,
        "joints": {"Head": {"rotation": q}}}]});
    let reply = server
        .client
        .send(
            Method::POST,
            "/v1/crowd/frame",
            Some("application/json"),
            Some("application/x-bincode"),
            Bytes::from(body.to_string()),
        )
        .await
        .expect("json frame");
    assert_eq!(reply.status, 200);
    let resp: crowdmorph_proto::CrowdFrameResponse =
        crowdmorph_proto::wire::response_from_bincode(&reply.body).expect("response");
    assert_eq!(positions_f32(Format::F32, &resp.buffers[0]), got[1]);

    // A render of the turned head draws, and differs from the plain one.
    let render = |joints: JointOverrides| {
        json!({"heads": [head(0, "robot", "Wave", 20, 0, joints)],
               "camera": {"position": [0, 3, 9], "target": [0, 3, 0]},
               "image": {"width": 96, "height": 96, "format": "rgba"}})
    };
    let mut images = Vec::new();
    for joints in [
        JointOverrides::default(),
        JointOverrides::rotation("Head", q),
    ] {
        let reply = server
            .client
            .send(
                Method::POST,
                "/v1/crowd/render",
                Some("application/json"),
                None,
                Bytes::from(render(joints).to_string()),
            )
            .await
            .expect("render");
        assert_eq!(reply.status, 200);
        images.push(reply.body);
    }
    assert_ne!(images[0], images[1], "the rendered head turns");
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
async fn far_levels_hold_small_joints_at_rest_so_heads_that_differ_there_are_clones() {
    let path = robot_path();
    let rig = crowdmorph::import::load_path(&path, &Default::default()).expect("robot");
    let lod = crowdmorph::rig::JointLod::of(&rig);
    let far = (rig.lod.levels.len() - 1) as u32;
    let sk = rig.skeleton.as_ref().expect("skinned");
    let small = lod.dropped[far as usize]
        .iter()
        .map(|&n| sk.nodes[n as usize].name.clone())
        .find(|n| n.starts_with("Index") || n.starts_with("Thumb") || n.starts_with("Middle"))
        .expect("a finger is held at rest at the far level");
    assert!(
        !lod.dropped[far as usize].contains(
            &sk.nodes
                .iter()
                .position(|n| n.name == "Hips")
                .map_or(u32::MAX, |i| i as u32)
        ),
        "the hips move the whole body and are never dropped"
    );
    let server = TestServer::start(ServerConfig::default()).await;
    server
        .client
        .upload_rig("robot", upload_bytes(&path))
        .await
        .expect("upload");
    let a = DQuat::from_rotation_z(0.5).as_quat().to_array();
    let b = DQuat::from_rotation_z(-0.5).as_quat().to_array();
    for (level, unique) in [(0u32, 2usize), (far, 1)] {
        let req = request(vec![
            head(
                0,
                "robot",
                "Idle",
                5,
                level,
                JointOverrides::rotation(&small, a),
            ),
            head(
                1,
                "robot",
                "Idle",
                5,
                level,
                JointOverrides::rotation(&small, b),
            ),
        ]);
        let (_, buffers) = frame(&server, &req).await;
        let n = buffers
            .iter()
            .collect::<std::collections::HashSet<_>>()
            .len();
        assert_eq!(n, unique, "level {level}: {small} turned two ways");
    }
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hostile_joint_overrides_are_refused_naming_the_problem() {
    let server = jaw_server().await;
    let many: serde_json::Map<String, serde_json::Value> = (0..300)
        .map(|i| (format!("n{i}"), json!({"rotation": [0, 0, 0, 1]})))
        .collect();
    let cases = [
        (
            "jaw",
            json!({"Nose": {"rotation": [0, 0, 0, 1]}}),
            "unknown_joints",
            "Nose",
        ),
        (
            "jaw",
            json!({"Jaw": {"rotation": [0, 0, 0, 0]}}),
            "invalid_joints",
            "rotation",
        ),
        (
            "jaw",
            json!({"Jaw": {"rotation": [0, 0, 0]}}),
            "malformed_json",
            "rotation",
        ),
        (
            "jaw",
            json!({"Jaw": {"scale": [1e30, 1, 1]}}),
            "invalid_joints",
            "scale",
        ),
        (
            "jaw",
            json!({"Jaw": {"translation": [0, 50, 0]}}),
            "invalid_joints",
            "translation",
        ),
        ("jaw", json!({"Jaw": {"spin": 1}}), "malformed_json", "spin"),
        (
            "jaw",
            serde_json::Value::Object(many),
            "invalid_joints",
            "at most",
        ),
        (
            "default-head",
            json!({"Jaw": {"rotation": [0, 0, 0, 1]}}),
            "invalid_joints",
            "skeleton",
        ),
    ];
    for (rig, joints, code, needle) in cases {
        let body = json!({"heads": [{"head": 1, "rig": rig, "clip": if rig == "jaw" {"open"} else {"talk"},
            "frame": 3, "joints": joints}]});
        let reply = server
            .client
            .send(
                Method::POST,
                "/v1/crowd/frame",
                Some("application/json"),
                None,
                Bytes::from(body.to_string()),
            )
            .await
            .expect("reply");
        let v: serde_json::Value = serde_json::from_slice(&reply.body).expect("JSON error");
        assert_eq!(reply.status, 400, "{v}");
        assert_eq!(v["error"]["code"], code, "{v}");
        let m = v["error"]["message"].as_str().unwrap_or_default();
        assert!(m.contains(needle), "{code}: {m:?} should name {needle:?}");
    }
    // NaN travels only in bincode; a node named twice only in a hand-written JSON object.
    let nan = request(vec![head(
        1,
        "jaw",
        "open",
        3,
        0,
        JointOverrides::rotation("Jaw", [f32::NAN, 0.0, 0.0, 1.0]),
    )]);
    let result = server.client.crowd_frame(&nan, Encoding::Bincode).await;
    let m = api_error(result, 400, "invalid_joints");
    assert!(m.contains("rotation"), "{m}");
    let twice = r#"{"heads":[{"head":1,"rig":"jaw","clip":"open","frame":3,
        "joints":{"Jaw":{"rotation":[0,0,0,1]},"Jaw":{"rotation":[0,1,0,1]}}}]}"#;
    let reply = server
        .client
        .send(
            Method::POST,
            "/v1/crowd/frame",
            Some("application/json"),
            None,
            Bytes::from(twice),
        )
        .await
        .expect("reply");
    assert_eq!(reply.status, 400);
    assert!(String::from_utf8_lossy(&reply.body).contains("twice"));
    // A session head is checked the same way when it is added.
    let (status, v) = call(
        &server,
        Method::POST,
        "/v1/sessions",
        json!({"heads": [{"head": 1, "rig": "jaw", "clip": "open",
            "joints": {"Nose": {"rotation": [0, 0, 0, 1]}}}]}),
    )
    .await;
    assert_eq!(
        (status, v["error"]["code"].as_str()),
        (400, Some("unknown_joints")),
        "{v}"
    );
    // And the server still serves.
    let ok = request(vec![head(
        1,
        "jaw",
        "open",
        3,
        0,
        JointOverrides::rotation("Jaw", [0.0, 0.0, 0.2, 1.0]),
    )]);
    let (got, _) = frame(&server, &ok).await;
    assert_eq!(got.len(), 1);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn session_heads_keep_their_overrides_and_patches_change_them() {
    let server = jaw_server().await;
    let open = [0.0, 0.0, 0.38268343, 0.9238795];
    let s = create(
        &server,
        json!({"fps": 20, "wrap": false, "heads": [
            {"head": 1, "rig": "jaw", "clip": "open", "offset": 1000},
            {"head": 2, "rig": "jaw", "clip": "open", "offset": 1000,
             "joints": {"Jaw": {"rotation": open}}}]}),
    )
    .await;
    assert_eq!(s.heads[1].joints, JointOverrides::rotation("Jaw", open));
    let mut ws = connect(&server, &s.id, json!({"format": "f32"})).await;
    let mut view = View::default();
    let t = next_tick(&mut ws).await;
    view.apply(&t);
    // Clamped past the end, both play the last frame; head 2 as a crowd frame with the same
    // override draws it.
    let rig = server.client.rig("jaw").await.expect("rig");
    let frames = rig
        .clips
        .iter()
        .find(|c| c.name == "open")
        .expect("open")
        .frames;
    let last = |joints| {
        request(vec![head(
            1,
            "jaw",
            "open",
            i64::from(frames) - 1,
            0,
            joints,
        )])
    };
    let want_plain = frame(&server, &last(JointOverrides::default()))
        .await
        .0
        .remove(0);
    let want_open = frame(&server, &last(JointOverrides::rotation("Jaw", open)))
        .await
        .0
        .remove(0);
    assert_eq!(view.heads[&1], want_plain);
    assert_eq!(view.heads[&2], want_open);
    assert!(
        diff(&want_plain, &want_open) > 0.1,
        "the override opens the jaw"
    );
    // A patch clears head 2's overrides and gives head 1 some: they swap.
    let (status, v) = call(
        &server,
        Method::PATCH,
        &format!("/v1/sessions/{}", s.id),
        json!({"change": [{"head": 1, "joints": {"Jaw": {"rotation": open}}},
                          {"head": 2, "joints": {}}]}),
    )
    .await;
    assert_eq!(status, 200, "{v}");
    for _ in 0..40 {
        let t = next_tick(&mut ws).await;
        view.apply(&t);
        if view.heads[&1] == want_open {
            break;
        }
    }
    assert_eq!(view.heads[&1], want_open, "the patch reached the stream");
    assert_eq!(view.heads[&2], want_plain);
    server.stop().await;
}

/// Live Link Face's columns for a few frames: the head turns, the eyes are recorded too.
fn live_link_csv(rows: &[(f32, f32, f32)]) -> String {
    let mut csv = String::from(
        "Timecode,BlendShapeCount,EyeBlinkLeft,HeadYaw,HeadPitch,HeadRoll,LeftEyeYaw,LeftEyePitch,\
         LeftEyeRoll,RightEyeYaw,RightEyePitch,RightEyeRoll\n",
    );
    for (i, (yaw, pitch, roll)) in rows.iter().enumerate() {
        csv.push_str(&format!(
            "00:00:00:{i:02}.000,61,0.1,{yaw},{pitch},{roll},0.2,0.1,0,0.2,0.1,0\n"
        ));
    }
    csv
}

/// The expected local rotation of node `n` turned by `delta` in rig axes: `rest × G⁻¹ Δ G`,
/// with `G` the node's global rotation at rest (from the f64 document).
fn turned(doc: &RefDoc, n: usize, delta: DQuat) -> DQuat {
    let rest = doc.rest_locals();
    let g: DMat4 = doc.globals(&rest)[n].expect("in the scene");
    let (_, gr, _) = g.to_scale_rotation_translation();
    let Local::Trs(_, r, _) = rest[n] else {
        panic!("node {n} is given as a matrix")
    };
    r * gr.inverse() * delta * gr
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
async fn live_link_columns_turn_the_head_and_a_rigs_own_map_is_kept() {
    let path = robot_path();
    let dir = temp_dir("joint-map");
    let doc = RefDoc::load(&path);
    let s1 = TestServer::start(stored_config(&dir)).await;
    let info = s1
        .client
        .upload_rig("robot", upload_bytes(&path))
        .await
        .expect("upload");
    let diag = {
        let (lo, hi) = (info.bbox.min, info.bbox.max);
        DVec3::from(hi.map(f64::from)).distance(DVec3::from(lo.map(f64::from)))
    };
    // The defaults map the head's three angles to the robot's `Head` (a Ready Player Me
    // name); it has no eye joints, so their columns are reported, not refused.
    let map = s1.client.joint_map("robot").await.expect("map");
    assert!(map.default);
    let columns: Vec<&str> = map.channels.iter().map(|c| c.column.as_str()).collect();
    assert_eq!(columns, ["HeadYaw", "HeadPitch", "HeadRoll"]);
    assert!(map.channels.iter().all(|c| c.node == "Head"));
    let rows = [(0.0, 0.0, 0.0), (0.3, 0.1, 0.0), (-0.5, 0.2, 0.1)];
    let up = s1
        .client
        .upload_clip(
            "robot",
            "name=look&ignore_unknown=true",
            "text/csv",
            Bytes::from(live_link_csv(&rows)),
        )
        .await
        .expect("clip");
    assert!(
        up.ignored.iter().any(|n| n == "LeftEyeYaw"),
        "eye angles the rig cannot show are reported: {:?}",
        up.ignored
    );
    let head_node = node(&doc, "Head");
    let check = |got: &[f32], (yaw, pitch, roll): (f32, f32, f32), what: &str| {
        let delta = DQuat::from_rotation_y(f64::from(yaw))
            * DQuat::from_rotation_x(f64::from(pitch))
            * DQuat::from_rotation_z(f64::from(roll));
        let q = turned(&doc, head_node, delta);
        let mut locals = doc.rest_locals();
        set_rotation(&mut locals, head_node, q);
        let want: Vec<DVec3> = doc
            .pose(&locals)
            .into_iter()
            .flat_map(|p| p.positions)
            .collect();
        let d = max_distance(got, &want);
        assert!(d <= 1e-5 * diag, "{what}: off by {d:e}");
    };
    let req = request(
        (0..3)
            .map(|f| head(f, "robot", "look", f as i64, 0, JointOverrides::default()))
            .collect(),
    );
    let (got, _) = frame(&s1, &req).await;
    for (f, r) in rows.iter().enumerate() {
        check(&got[f], *r, &format!("default map, frame {f}"));
    }
    assert!(
        diff(&got[0], &got[2]) > 1e-3 * diag as f32,
        "the head turns"
    );

    // The rig's own map: HeadYaw turns the neck about +X, at half a radian per unit.
    let own = JointMapSpec {
        channels: vec![JointChannelSpec {
            column: "HeadYaw".into(),
            node: "Neck".into(),
            axis: [1.0, 0.0, 0.0],
            scale: 0.5,
        }],
    };
    let set = s1.client.set_joint_map("robot", &own).await.expect("PUT");
    assert!(!set.default);
    assert_eq!(set.channels, own.channels);
    let bad = JointMapSpec {
        channels: vec![JointChannelSpec {
            column: "HeadYaw".into(),
            node: "Tail".into(),
            axis: [0.0, 1.0, 0.0],
            scale: 1.0,
        }],
    };
    let m = api_error(
        s1.client.set_joint_map("robot", &bad).await,
        400,
        "unknown_joints",
    );
    assert!(m.contains("Tail"), "{m}");
    let zero_axis = JointMapSpec {
        channels: vec![JointChannelSpec {
            axis: [0.0, 0.0, 0.0],
            ..own.channels[0].clone()
        }],
    };
    api_error(
        s1.client.set_joint_map("robot", &zero_axis).await,
        400,
        "invalid_joint_map",
    );
    // Too many channels, and two columns that spell alike (columns match loosely).
    let channel = |column: String| JointChannelSpec {
        column,
        ..own.channels[0].clone()
    };
    let many = JointMapSpec {
        channels: (0..300).map(|i| channel(format!("c{i}"))).collect(),
    };
    let m = api_error(
        s1.client.set_joint_map("robot", &many).await,
        400,
        "invalid_joint_map",
    );
    assert!(m.contains("at most 256"), "{m}");
    let alike = JointMapSpec {
        channels: vec![channel("HeadYaw".into()), channel("head_yaw".into())],
    };
    let m = api_error(
        s1.client.set_joint_map("robot", &alike).await,
        400,
        "invalid_joint_map",
    );
    assert!(m.contains("twice"), "{m}");
    assert!(
        !s1.client.joint_map("robot").await.expect("map").default,
        "a refused map changes nothing"
    );
    s1.client
        .upload_clip(
            "robot",
            "name=nod&ignore_unknown=true",
            "text/csv",
            Bytes::from(live_link_csv(&rows)),
        )
        .await
        .expect("clip with the rig's map");
    let neck_node = node(&doc, "Neck");
    let nod_req = request(vec![head(
        0,
        "robot",
        "nod",
        2,
        0,
        JointOverrides::default(),
    )]);
    let (nod, _) = frame(&s1, &nod_req).await;
    let q = turned(&doc, neck_node, DQuat::from_rotation_x(-0.25));
    let mut locals = doc.rest_locals();
    set_rotation(&mut locals, neck_node, q);
    let want: Vec<DVec3> = doc
        .pose(&locals)
        .into_iter()
        .flat_map(|p| p.positions)
        .collect();
    let d = max_distance(&nod[0], &want);
    assert!(d <= 1e-5 * diag, "the rig's map: off by {d:e}");
    // A live head's weights may carry the same angles: they turn the joints the same way
    // (here by the rig's own map: HeadYaw turns the neck).
    let live = request(vec![Head::live(
        5,
        "robot",
        crowdmorph_proto::LiveWeights::Named(vec![
            ("HeadYaw".into(), -0.5),
            ("LeftEyeYaw".into(), 0.2),
        ]),
    )]);
    let (live_got, _) = frame(&s1, &live).await;
    let d = max_distance(&live_got[0], &want);
    assert!(d <= 1e-5 * diag, "live angles: off by {d:e}");
    let (look_before, _) = frame(&s1, &req).await;
    s1.stop().await;

    // After a restart: the map, and both clips' joint tables.
    let s2 = TestServer::start(stored_config(&dir)).await;
    let map = s2
        .client
        .joint_map("robot")
        .await
        .expect("map after restart");
    assert_eq!(map.channels, own.channels, "the rig's own map is kept");
    assert_eq!(frame(&s2, &req).await.0, look_before);
    assert_eq!(frame(&s2, &nod_req).await.0, nod);
    let reset = s2.client.reset_joint_map("robot").await.expect("DELETE");
    assert!(reset.default);
    s2.stop().await;
    let _ = std::fs::remove_dir_all(&dir);
}

/// The robot's `RigInfo` lists every node a joint override or joint map may name, and counts
/// each bone once (its four skins list the same 43 joints, and rigid meshes hang from 15 more
/// nodes); `unknown_joints` says where the names are.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
async fn the_robots_nodes_are_listed_and_its_bones_counted_once() {
    let path = robot_path();
    let doc = RefDoc::load(&path);
    let server = TestServer::start(ServerConfig::default()).await;
    server
        .client
        .upload_rig("robot", upload_bytes(&path))
        .await
        .expect("upload");
    let info = server.client.rig("robot").await.expect("rig");
    let sk = info.skeleton.expect("a skeleton");
    let followed = crate::util::skin::followed_nodes(&doc.json);
    let skin_entries: usize = doc.json["skins"]
        .as_array()
        .expect("skins")
        .iter()
        .map(|s| s["joints"].as_array().map_or(0, Vec::len))
        .sum();
    assert!(
        followed.len() < skin_entries,
        "the skins share joints: {} nodes, {skin_entries} entries",
        followed.len()
    );
    assert_eq!(sk.bones as usize, followed.len());
    assert_eq!(sk.node_names.len(), sk.nodes as usize);
    let name = |n: usize| doc.json["nodes"][n]["name"].as_str().expect("named");
    for &n in &followed {
        assert!(sk.node_names.iter().any(|x| x == name(n)), "{}", name(n));
    }
    for a in &sk.animated_nodes {
        assert!(sk.node_names.contains(a), "{a}");
    }
    // The bincode form is the pinned layout: no names there.
    let bin = server
        .client
        .send(
            Method::GET,
            "/v1/rigs/robot",
            None,
            Some("application/x-bincode"),
            Bytes::new(),
        )
        .await
        .expect("bincode");
    let decoded: crowdmorph_proto::RigInfo =
        crowdmorph_proto::wire::response_from_bincode(&bin.body).expect("decodes");
    let k = decoded.skeleton.expect("a skeleton");
    assert!(k.node_names.is_empty());
    assert_eq!(k.bones, sk.bones);

    // A name no node has: the message says where the names are.
    let wrong = request(vec![head(
        1,
        "robot",
        "Idle",
        0,
        0,
        JointOverrides::rotation("Nose", [0.0, 0.0, 0.0, 1.0]),
    )]);
    let m = api_error(
        server.client.crowd_frame(&wrong, Encoding::Bincode).await,
        400,
        "unknown_joints",
    );
    assert!(m.contains("skeleton.node_names"), "{m}");

    server.stop().await;
}

/// The jaw rig with a map of its own: `HeadYaw` and `HeadPitch` turn `Jaw`.
async fn jaw_with_head_columns() -> TestServer {
    let server = jaw_server().await;
    let channel = |column: &str, axis: [f32; 3]| JointChannelSpec {
        column: column.into(),
        node: "Jaw".into(),
        axis,
        scale: 1.0,
    };
    let map = JointMapSpec {
        channels: vec![
            channel("HeadYaw", [0.0, 1.0, 0.0]),
            channel("HeadPitch", [1.0, 0.0, 0.0]),
        ],
    };
    server.client.set_joint_map("jaw", &map).await.expect("map");
    server
}

/// Uploads `csv` as clip `name` of the jaw rig.
async fn jaw_csv(
    server: &TestServer,
    name: &str,
    csv: String,
) -> Result<crowdmorph_proto::ClipUpload, crowdmorph_client::ClientError> {
    server
        .client
        .upload_clip(
            "jaw",
            &format!("name={name}&ignore_unknown=true"),
            "text/csv",
            Bytes::from(csv),
        )
        .await
}

/// Two spellings of one joint column are refused naming both, as two of one target are (one
/// of them was dropped silently).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_joint_column_spelled_twice_is_refused_naming_both() {
    let server = jaw_with_head_columns().await;
    let m = api_error(
        jaw_csv(&server, "twice", "HeadYaw,head_yaw\n0.1,0.2\n".into()).await,
        400,
        "invalid_clip",
    );
    assert!(m.contains("\"HeadYaw\" and \"head_yaw\""), "{m}");
    server.stop().await;
}

/// A joint map's column with a control character is refused: columns are matched loosely,
/// which would drop the character (`Head\0Yaw` would take `HeadYaw`'s values).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_joint_map_column_with_a_control_character_is_refused() {
    let server = jaw_server().await;
    let map = JointMapSpec {
        channels: vec![JointChannelSpec {
            column: "Head\u{0}Yaw".into(),
            node: "Jaw".into(),
            axis: [0.0, 1.0, 0.0],
            scale: 1.0,
        }],
    };
    let m = api_error(
        server.client.set_joint_map("jaw", &map).await,
        400,
        "invalid_joint_map",
    );
    assert!(m.contains("control character"), "{m}");
    assert!(server.client.joint_map("jaw").await.expect("map").default);
    server.stop().await;
}

/// An angle column's values are capped as the same angle sent as a live weight is (±64): past
/// it, refused naming the row and column (1e30 was taken).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn angle_columns_past_64_are_refused_naming_row_and_column() {
    let server = jaw_with_head_columns().await;
    for (i, (angle, ok)) in [(64.0f32, true), (-64.0, true), (64.5, false), (1e30, false)]
        .into_iter()
        .enumerate()
    {
        let csv = format!("HeadPitch,HeadYaw\n0,0\n0.25,{angle}\n");
        let got = jaw_csv(&server, &format!("angle{i}"), csv).await;
        if ok {
            got.expect("an angle of ±64 is taken");
        } else {
            let m = api_error(got, 400, "invalid_clip");
            assert!(m.contains("row 3, column \"HeadYaw\""), "{angle}: {m}");
        }
    }
    server.stop().await;
}

/// A rotation of tiny but finite, non-zero components is that rotation, normalized (in f32
/// their squares vanish); only all-zero or non-finite ones are refused.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tiny_rotations_are_normalized_and_only_zero_ones_refused() {
    let server = jaw_server().await;
    let at = |q: [f32; 4]| {
        request(vec![head(
            1,
            "jaw",
            "open",
            3,
            0,
            JointOverrides::rotation("Jaw", q),
        )])
    };
    let (unit, _) = frame(&server, &at([0.0, 0.0, 0.6, 0.8])).await;
    let (rest, _) = frame(&server, &at([0.0, 0.0, 0.0, 1.0])).await;
    assert!(diff(&unit[0], &rest[0]) > 1e-2, "the rotation shows");
    for q in [
        [0.0, 0.0, 6e-21, 8e-21],
        [0.0, 0.0, 6e-39, 8e-39],
        [0.0, 0.0, 6e5, 8e5],
    ] {
        let (got, _) = frame(&server, &at(q)).await;
        assert!(diff(&got[0], &unit[0]) <= 1e-6, "{q:?}");
    }
    for q in [[0.0, 0.0, 0.0, 0.0], [0.0, 0.0, f32::INFINITY, 1.0]] {
        let m = api_error(
            server.client.crowd_frame(&at(q), Encoding::Bincode).await,
            400,
            "invalid_joints",
        );
        assert!(m.contains("not all zero"), "{q:?}: {m}");
    }
    server.stop().await;
}

/// Two skinned meshes on the same two joints, the second skin binding `Jaw` elsewhere (skins
/// of one avatar whose bind poses differ, as VRoid exports have them): the rig has a bone per
/// (joint, bind pose), but `bones` counts the nodes vertices follow, each once, and
/// `node_names` lists the skeleton's nodes.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_joint_two_skins_share_is_one_bone_and_every_node_is_listed() {
    let (mut b, t) = skinned_triangle_rig();
    // Root bound where the first skin binds it, Jaw at (0, 1.5, 0) rather than (0, 1, 0).
    #[rustfmt::skip]
    let ibm2 = b.accessor_f32(&[
        1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0,
        1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, -1.5, 0.0, 1.0,
    ], "MAT4");
    let mesh = b.json_mut()["nodes"][t.mesh_node]["mesh"].clone();
    let twin = b.node(None);
    let json = b.json_mut();
    json["nodes"][twin]["mesh"] = mesh;
    json["nodes"][twin]["skin"] = json!(1);
    let skins = json["skins"].as_array_mut().expect("skins");
    skins.push(json!({ "joints": [t.root, t.jaw], "inverseBindMatrices": ibm2 }));
    json["scenes"][0]["nodes"]
        .as_array_mut()
        .expect("scene nodes")
        .push(json!(twin));
    let followed = crate::util::skin::followed_nodes(json);
    assert_eq!(followed.len(), 2, "Root and Jaw");

    let server = TestServer::start(ServerConfig::default()).await;
    server
        .client
        .upload_rig("twins", Bytes::from(b.to_glb()))
        .await
        .expect("upload");
    let sk = server
        .client
        .rig("twins")
        .await
        .expect("rig")
        .skeleton
        .expect("a skeleton");
    assert_eq!(sk.bones as usize, followed.len(), "{sk:?}");
    assert_eq!(sk.node_names, ["Root", "Jaw"]);
    assert_eq!(sk.nodes, 2);
    // Both meshes follow the joints: a turned jaw moves both copies of its vertex.
    let (rest, _) = frame(
        &server,
        &request(vec![head(
            1,
            "twins",
            "open",
            0,
            0,
            JointOverrides::default(),
        )]),
    )
    .await;
    let (turned, _) = frame(
        &server,
        &request(vec![head(
            1,
            "twins",
            "open",
            0,
            0,
            JointOverrides::rotation("Jaw", [0.0, 0.0, 0.38, 0.92]),
        )]),
    )
    .await;
    assert_eq!(rest[0].len(), 2 * 3 * 3, "two triangles");
    let moved = |v: usize| (0..3).any(|c| (rest[0][3 * v + c] - turned[0][3 * v + c]).abs() > 1e-3);
    assert!(moved(1) && moved(4), "{rest:?} {turned:?}");
    server.stop().await;
}
