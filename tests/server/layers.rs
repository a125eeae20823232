//! Layers and masks over HTTP (issue 47 items 1 and 2): heads with `layers`, live `weights`
//! over a clip and a `clamp` come back as the f64 weight-space sum this file writes from the
//! rig's clip tables (override `(1 − a)·w + a·layer`, additive `w + a·(layer − reference)`,
//! `a = weight × mask`), evaluated by the tests' f64 oracle, on the CPU engine and on the GPU
//! one; their joints layer against the skinning oracle; equal final weights share a job; and
//! every malformed layer is a named 4xx.

use std::collections::HashMap;

use crowdmorph::server::ServerConfig;
use crowdmorph_client::Encoding;
use crowdmorph_proto::{
    CrowdFrameRequest, Head, Layer, LayerMode, LiveWeights, Mask, OutputOptions,
};
use glam::DVec3;

use super::TestServer;
use crate::util::skin::Local;
use crate::util::{RefDoc, rig_oracle};

fn request(heads: Vec<Head>) -> CrowdFrameRequest {
    CrowdFrameRequest {
        heads,
        output: OutputOptions::default(),
        wrap: true,
    }
}

/// Head `head`'s f32 positions in a crowd frame.
fn positions(resp: &crowdmorph_proto::CrowdFrameResponse, head: usize) -> Vec<f32> {
    let b = &resp.buffers[resp.heads[head].buffer as usize];
    super::positions_f32(resp.format, b)
}

/// The embedded rig's weights of `clip` at `frame`, per channel, in f64.
pub(super) fn frame_weights(rig: &crowdmorph::rig::Rig, clip: &str, frame: u32) -> Vec<f64> {
    let c = &rig.clips[rig.clip_index(clip).expect("clip")];
    (0..rig.targets.len())
        .map(|k| f64::from(c.weight(k, frame)))
        .collect()
}

/// A name as the protocol matches it loosely (`proto/README.md`): lower case, letters and
/// digits only, a trailing `left`/`right` as `l`/`r` (`mouthSmileLeft` is `mouthSmile_L`).
pub(super) fn loose(name: &str) -> String {
    let s: String = name
        .chars()
        .filter(char::is_ascii_alphanumeric)
        .map(|c| c.to_ascii_lowercase())
        .collect();
    if let Some(stem) = s.strip_suffix("left") {
        format!("{stem}l")
    } else if let Some(stem) = s.strip_suffix("right") {
        format!("{stem}r")
    } else {
        s
    }
}

/// Channel ids of each target name of `names` present in the rig, matched loosely.
pub(super) fn channels(rig: &crowdmorph::rig::Rig, names: &[&str]) -> Vec<usize> {
    let mut out: Vec<usize> = rig
        .targets
        .iter()
        .enumerate()
        .filter(|(_, t)| names.iter().any(|n| loose(n) == loose(t)))
        .map(|(k, _)| k)
        .collect();
    out.sort_unstable();
    out
}

/// The heads of the weight tests and, for each, its final weights written out here.
pub(super) fn layered_heads(rig: &crowdmorph::rig::Rig) -> Vec<(Head, Vec<f64>)> {
    let smile = frame_weights(rig, "smile", 5);
    let surprise = |f| frame_weights(rig, "surprise", f);
    let talk = |f| frame_weights(rig, "talk", f);
    let lower: Vec<&str> = crowdmorph::rig::builtin_mask("lower_face").expect("mask");
    let lower = channels(rig, &lower);
    let eyes = channels(rig, &["eyeBlinkLeft", "eyeBlinkRight"]);
    let jaw = channels(rig, &["jawOpen"]);
    let mut out = Vec::new();

    // 1. talk 3, then smile 5 over the lower face at 0.6, then surprise 8 added from its
    // frame 0 at 0.5 on the blinks (left at 1, right at 0.5), clamped to [0, 1].
    let mut w = talk(3);
    for &k in &lower {
        w[k] = 0.4 * w[k] + 0.6 * smile[k];
    }
    let (s8, s0) = (surprise(8), surprise(0));
    for (&k, m) in eyes.iter().zip([1.0, 0.5]) {
        w[k] += 0.5 * m * (s8[k] - s0[k]);
    }
    w.iter_mut().for_each(|v| *v = v.clamp(0.0, 1.0));
    out.push((
        Head {
            layers: vec![
                Layer {
                    mask: Some(Mask::Named("lower_face".into())),
                    ..Layer::over("smile", 5, 0.6)
                },
                Layer {
                    mode: LayerMode::Additive,
                    reference: Some(0),
                    mask: Some(Mask::Weights(vec![
                        ("eyeBlinkLeft".into(), 1.0),
                        ("eyeBlinkRight".into(), 0.5),
                    ])),
                    ..Layer::over("surprise", 8, 0.5)
                },
            ],
            clamp: Some([0.0, 1.0]),
            ..Head::playing(1, "default-head", "talk", 3)
        },
        w,
    ));

    // 2. The whole of surprise 20 added at 0.7 over talk 10 (reference: the neutral).
    let mut w = talk(10);
    for (v, s) in w.iter_mut().zip(surprise(20)) {
        *v += 0.7 * s;
    }
    out.push((
        Head {
            layers: vec![Layer {
                mode: LayerMode::Additive,
                ..Layer::over("surprise", 20, 0.7)
            }],
            ..Head::playing(2, "default-head", "talk", 10)
        },
        w,
    ));

    // 3. Live weights over a clip: jawOpen replaced (override), then the same added.
    let mut w = talk(6);
    for &k in &jaw {
        w[k] = 0.9;
    }
    out.push((
        Head {
            weights: Some(Box::new(LiveWeights::Named(vec![("jawOpen".into(), 0.9)]))),
            ..Head::playing(3, "default-head", "talk", 6)
        },
        w,
    ));
    let mut w = talk(6);
    for &k in &jaw {
        w[k] += 0.25;
    }
    out.push((
        Head {
            weights: Some(Box::new(LiveWeights::Named(vec![("jawOpen".into(), 0.25)]))),
            weights_mode: LayerMode::Additive,
            ..Head::playing(4, "default-head", "talk", 6)
        },
        w,
    ));

    // 4. Layers over live weights: the tracker's smile, the lower face of talk 12 at 0.5.
    let t12 = talk(12);
    let mut w = vec![0.0; rig.targets.len()];
    for k in channels(rig, &["mouthSmileLeft", "mouthSmileRight"]) {
        w[k] = 0.8;
    }
    for &k in &lower {
        w[k] = 0.5 * w[k] + 0.5 * t12[k];
    }
    out.push((
        Head {
            layers: vec![Layer {
                mask: Some(Mask::Named("lower_face".into())),
                ..Layer::over("talk", 12, 0.5)
            }],
            ..Head::live(
                5,
                "default-head",
                LiveWeights::Named(vec![
                    ("mouthSmileLeft".into(), 0.8),
                    ("mouthSmileRight".into(), 0.8),
                ]),
            )
        },
        w,
    ));
    out
}

/// Checks every head of `layered_heads` against the oracle on `server`.
async fn layered_heads_match_the_oracle(server: &TestServer) {
    let rig = crowdmorph::embedded::default_rig();
    let cases = layered_heads(&rig);
    let req = request(cases.iter().map(|(h, _)| h.clone()).collect());
    let (resp, _) = server
        .client
        .crowd_frame(&req, Encoding::Bincode)
        .await
        .expect("frame");
    let b = rig.bbox();
    let diag = f64::from((b.max - b.min).length());
    for (i, (head, w)) in cases.iter().enumerate() {
        let (want, _) = rig_oracle(&rig, w);
        let got = positions(&resp, i);
        let d = crate::util::max_abs_diff(&got, &want);
        // Live weights are quantized to 2^-12: a few hundred-thousandths of the diagonal.
        assert!(
            d <= 1e-4 * diag,
            "head {} ({:?}): off by {d:e} of a diagonal of {diag}",
            head.head,
            head.layers
        );
        // And the layers did something: the base alone is further away.
        let base = Head {
            layers: Vec::new(),
            weights: None,
            clamp: None,
            ..head.clone()
        };
        if !base.clip.is_empty() {
            let base_w = frame_weights(&rig, &base.clip, base.frame as u32);
            let (base_pos, _) = rig_oracle(&rig, &base_w);
            let moved = crate::util::max_abs_diff(&got, &base_pos);
            assert!(
                moved > 100.0 * d.max(1e-7 * diag),
                "head {}: the layers moved it by only {moved:e}",
                head.head
            );
        }
    }
}

/// `POST /v1/crowd/frame` of a JSON body: status and body text.
async fn post_json(server: &TestServer, body: &serde_json::Value) -> (u16, String) {
    let r = server
        .client
        .send(
            crowdmorph_client::Method::POST,
            "/v1/crowd/frame",
            Some("application/json"),
            Some("application/json"),
            bytes::Bytes::from(body.to_string()),
        )
        .await
        .expect("an answer");
    (r.status, String::from_utf8_lossy(&r.body).into_owned())
}

#[tokio::test]
async fn layered_heads_are_the_weight_space_sum_of_their_layers() {
    let server = TestServer::start(ServerConfig::default()).await;
    layered_heads_match_the_oracle(&server).await;
    server.stop().await;
}

crate::util::gpu_test!(
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn layered_heads_on_the_gpu_engine_are_the_same_sum() {
        let server = TestServer::start(ServerConfig {
            backend: crowdmorph::engine::BackendChoice::Gpu,
            ..ServerConfig::default()
        })
        .await;
        layered_heads_match_the_oracle(&server).await;
        server.stop().await;
    }
);

#[tokio::test]
async fn equal_final_weights_share_one_job() {
    // The same layer written three ways (a list mask, a map of ones, the same in JSON): one
    // job; a different weight: another.
    let server = TestServer::start(ServerConfig::default()).await;
    let names = ["jawOpen".to_string(), "mouthFunnel".to_string()];
    let head = |id, mask: Mask, weight| Head {
        layers: vec![Layer {
            mask: Some(mask),
            ..Layer::over("smile", 7, weight)
        }],
        ..Head::playing(id, "default-head", "talk", 2)
    };
    let req = request(vec![
        head(1, Mask::Names(names.to_vec()), 0.5),
        head(
            2,
            Mask::Weights(names.iter().map(|n| (n.clone(), 1.0)).collect()),
            0.5,
        ),
        head(3, Mask::Names(names.iter().rev().cloned().collect()), 0.5),
        head(4, Mask::Names(names.to_vec()), 0.75),
    ]);
    for encoding in [Encoding::Json, Encoding::Bincode] {
        let (resp, _) = server
            .client
            .crowd_frame(&req, encoding)
            .await
            .expect("frame");
        let b: Vec<u32> = resp.heads.iter().map(|h| h.buffer).collect();
        assert_eq!(resp.buffers.len(), 2, "{encoding:?}: {b:?}");
        assert_eq!((b[0], b[1], b[2]), (b[0], b[0], b[0]));
        assert_ne!(b[3], b[0]);
    }
    server.stop().await;
}

#[tokio::test]
async fn malformed_layers_are_named_4xx() {
    let server = TestServer::start(ServerConfig::default()).await;
    let head = |layer: Layer| Head {
        layers: vec![layer],
        ..Head::playing(7, "default-head", "talk", 2)
    };
    let cases: Vec<(&str, Head, u16, &str)> = vec![
        (
            "a weight past 1",
            head(Layer::over("smile", 1, 1.5)),
            400,
            "invalid_layer",
        ),
        (
            "a NaN weight",
            head(Layer::over("smile", 1, f32::NAN)),
            400,
            "invalid_layer",
        ),
        (
            "an unknown clip",
            head(Layer::over("nope", 1, 0.5)),
            404,
            "unknown_clip",
        ),
        (
            "an unknown built-in mask",
            head(Layer {
                mask: Some(Mask::Named("knees".into())),
                ..Layer::over("smile", 1, 0.5)
            }),
            400,
            "invalid_layer",
        ),
        (
            "a mask naming a target the rig lacks",
            head(Layer {
                mask: Some(Mask::Names(vec!["elbowBend".into()])),
                ..Layer::over("smile", 1, 0.5)
            }),
            400,
            "unknown_targets",
        ),
        (
            "a mask weight past 1",
            head(Layer {
                mask: Some(Mask::Weights(vec![("jawOpen".into(), 2.0)])),
                ..Layer::over("smile", 1, 0.5)
            }),
            400,
            "invalid_layer",
        ),
        (
            "a reference on an override layer",
            head(Layer {
                reference: Some(0),
                ..Layer::over("smile", 1, 0.5)
            }),
            400,
            "invalid_layer",
        ),
        (
            "a joint mask on a rig without a skeleton",
            head(Layer {
                joint_mask: Some(vec!["Head".into()]),
                ..Layer::over("smile", 1, 0.5)
            }),
            400,
            "invalid_layer",
        ),
        (
            "nine layers",
            Head {
                layers: vec![Layer::over("smile", 1, 0.1); 9],
                ..Head::playing(7, "default-head", "talk", 2)
            },
            400,
            "invalid_layer",
        ),
        (
            "a mask naming more than the rig and ARKit have",
            head(Layer {
                mask: Some(Mask::Names(vec!["jawOpen".into(); 200])),
                ..Layer::over("smile", 1, 0.5)
            }),
            400,
            "invalid_layer",
        ),
        (
            "a blend without a clip, under layers",
            Head {
                layers: vec![Layer::over("smile", 1, 0.5)],
                blend: vec![crowdmorph_proto::BlendLayer {
                    clip: "smile".into(),
                    frame: 0,
                    t: 0.5,
                }],
                ..Head::live(
                    7,
                    "default-head",
                    LiveWeights::Named(vec![("jawOpen".into(), 0.5)]),
                )
            },
            400,
            "invalid_weights",
        ),
        (
            "an upside-down clamp",
            Head {
                clamp: Some([1.0, 0.0]),
                ..Head::playing(7, "default-head", "talk", 2)
            },
            400,
            "invalid_layer",
        ),
    ];
    for (what, h, status, code) in cases {
        let req = request(vec![Head::playing(1, "default-head", "talk", 0), h]);
        let err = server
            .client
            .crowd_frame(&req, Encoding::Bincode)
            .await
            .expect_err(what);
        let text = format!("{err}");
        assert!(
            text.contains(&status.to_string()) && text.contains(code),
            "{what}: {text}"
        );
        assert!(text.contains("head 1"), "{what} names the head: {text}");
    }
    // JSON masks in each of their three shapes parse; a number does not.
    let body = serde_json::json!({"heads": [{
    "head": 1, "rig": "default-head", "clip": "talk", "frame": 1,
    "layers": [
        {"clip": "smile", "frame": 2, "weight": 0.5, "mask": ["jawOpen"]},
        {"clip": "smile", "frame": 2, "mask": {"jawOpen": 0.5}},
        {"clip": "surprise", "frame": 3, "mode": "additive", "reference": 0, "mask": "eyes"}
    ]}]});
    let r = post_json(&server, &body).await;
    assert_eq!(r.0, 200, "{}", r.1);
    let body = serde_json::json!({"heads": [{
        "head": 1, "rig": "default-head", "clip": "talk", "frame": 1,
        "layers": [{"clip": "smile", "mask": 3}]}]});
    let r = post_json(&server, &body).await;
    assert_eq!(r.0, 400, "{}", r.1);
    assert!(r.1.contains("mask"), "{}", r.1);
    server.stop().await;
}

/// A skinned head's joints layer as its weights do: RobotExpressive running (frame 9) with
/// its arms from waving (frame 20), by override at 0.5 and by addition relative to the wave's
/// frame 0, against the skinning oracle's own slerp of the file's transforms.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
async fn a_skinned_heads_joints_layer_against_the_skinning_oracle() {
    let path = crate::util::data_dir().join("robot-expressive/RobotExpressive.glb");
    let server = TestServer::start(ServerConfig::default()).await;
    let info = server
        .client
        .upload_rig("robot", super::upload_bytes(&path))
        .await
        .expect("upload");
    let doc = RefDoc::load(&path);
    let names: Vec<String> = doc.json["nodes"]
        .as_array()
        .expect("nodes")
        .iter()
        .map(|n| n["name"].as_str().unwrap_or("").to_string())
        .collect();
    // The arm nodes the wave animates.
    let wave_nodes: std::collections::BTreeSet<usize> = doc.json["animations"]
        .as_array()
        .expect("animations")
        .iter()
        .filter(|a| a["name"] == "Wave")
        .flat_map(|a| a["channels"].as_array().expect("channels").iter())
        .filter_map(|c| c["target"]["node"].as_u64())
        .map(|n| n as usize)
        .collect();
    let arm: Vec<String> = wave_nodes
        .iter()
        .map(|&i| names[i].clone())
        .filter(|n| n.contains("Arm") || n.contains("Hand"))
        .collect();
    assert!(arm.len() >= 2, "{arm:?}");
    let at = |clip: &str, f: f64| doc.locals_at(clip, f / 30.0);
    let (run, wave, wave0) = (at("Running", 9.0), at("Wave", 20.0), at("Wave", 0.0));
    let by_name: HashMap<&str, usize> = names
        .iter()
        .enumerate()
        .map(|(i, n)| (n.as_str(), i))
        .collect();
    let trs = |l: &Local| match *l {
        Local::Trs(t, r, s) => (t, r.normalize(), s),
        Local::Matrix(_) => panic!("a matrix node in the mask"),
    };
    let mut over = run.clone();
    let mut added = run.clone();
    for n in &arm {
        let i = by_name[n.as_str()];
        let ((bt, br, bs), (lt, lr, ls), (rt, rr, rs)) =
            (trs(&run[i]), trs(&wave[i]), trs(&wave0[i]));
        over[i] = Local::Trs(bt.lerp(lt, 0.5), br.slerp(lr, 0.5), bs.lerp(ls, 0.5));
        added[i] = Local::Trs(
            bt + (lt - rt),
            (br * (rr.inverse() * lr)).normalize(),
            bs + (ls - rs),
        );
    }
    // The joint mask also names a node the run animates and the wave does not: a mask
    // narrows what the layer's clip moves, so that node keeps the run's transform.
    let animated = |name: &str| -> std::collections::BTreeSet<usize> {
        doc.json["animations"]
            .as_array()
            .expect("animations")
            .iter()
            .filter(|a| a["name"] == name)
            .flat_map(|a| a["channels"].as_array().expect("channels").iter())
            .filter_map(|c| c["target"]["node"].as_u64())
            .map(|n| n as usize)
            .collect()
    };
    let run_only = animated("Running")
        .difference(&animated("Wave"))
        .map(|&i| names[i].clone())
        .find(|n| !n.is_empty() && names.iter().filter(|m| *m == n).count() == 1)
        .expect("a node the run animates and the wave does not");
    let mut joint_mask = arm.clone();
    joint_mask.push(run_only);
    let layered = |mode, weight, reference| Layer {
        mode,
        reference,
        joint_mask: Some(joint_mask.clone()),
        // The robot's clips move no morph target: the mask keeps the weights as they are.
        mask: Some(Mask::Names(Vec::new())),
        ..Layer::over("Wave", 20, weight)
    };
    let req = request(vec![
        Head {
            layers: vec![layered(LayerMode::Override, 0.5, None)],
            ..Head::playing(1, "robot", "Running", 9)
        },
        Head {
            layers: vec![layered(LayerMode::Additive, 1.0, Some(0))],
            ..Head::playing(2, "robot", "Running", 9)
        },
        Head::playing(3, "robot", "Running", 9),
    ]);
    let (resp, _) = server
        .client
        .crowd_frame(&req, Encoding::Bincode)
        .await
        .expect("frame");
    let diag = {
        let (lo, hi) = (info.bbox.min, info.bbox.max);
        DVec3::from(hi.map(f64::from)).distance(DVec3::from(lo.map(f64::from)))
    };
    let posed = |locals: &[Local]| -> Vec<DVec3> {
        doc.pose(locals)
            .into_iter()
            .flat_map(|p| p.positions)
            .collect()
    };
    for (head, want) in [(0, posed(&over)), (1, posed(&added)), (2, posed(&run))] {
        let got = positions(&resp, head);
        let d = crate::util::max_abs_diff(&got, &want);
        // Overrides are quantized (2^-16 of a unit quaternion, 2^-12 of a unit translation).
        assert!(d <= 2e-4 * diag, "head {head}: off by {d:e} of {diag}");
    }
    // The layers moved the arms: the plain running head is elsewhere.
    let plain = positions(&resp, 2);
    let moved = crate::util::max_abs_diff(&plain, &posed(&over));
    assert!(moved > 1e-2 * diag, "the wave moved the arms by {moved:e}");
    server.stop().await;
}

/// A session head's layers play their frames from the session clock, as its `offset` does,
/// while an additive layer's reference stays where it is; a patch replaces them. Each tick's
/// vertices are the f64 sum written here, evaluated by the oracle.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_session_heads_layers_play_from_the_session_clock() {
    use super::sessions::{View, call, connect, create, next_tick};
    use serde_json::json;
    let server = TestServer::start(ServerConfig::default()).await;
    let rig = crowdmorph::embedded::default_rig();
    let info = create(
        &server,
        json!({"fps": 30, "heads": [
            {"head": 1, "rig": "default-head", "clip": "talk", "offset": 3,
             "layers": [
                {"clip": "smile", "frame": 5, "weight": 0.6, "mask": "lower_face"},
                {"clip": "surprise", "frame": 20, "weight": 0.5, "mode": "additive",
                 "reference": 0, "mask": {"eyeBlink_L": 1, "eyeBlink_R": 0.5}}],
             "clamp": [0, 1]},
            {"head": 2, "rig": "default-head", "clip": "talk", "offset": 3}]}),
    )
    .await;
    let mut ws = connect(&server, &info.id, json!({"format": "f32"})).await;
    let lower = channels(
        &rig,
        &crowdmorph::rig::builtin_mask("lower_face").expect("mask"),
    );
    let blinks = channels(&rig, &["eyeBlinkLeft", "eyeBlinkRight"]);
    let at = |clip: &str, f: u64| {
        let c = &rig.clips[rig.clip_index(clip).expect("clip")];
        frame_weights(&rig, clip, (f % u64::from(c.frames)) as u32)
    };
    let want = |tick: u64| {
        // Clips and session at 30 fps: one frame a tick from each layer's frame.
        let e = tick - 1;
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
    };
    let b = rig.bbox();
    let diag = f64::from((b.max - b.min).length());
    let mut view = View::default();
    let mut checked = 0;
    let mut patched = false;
    while checked < 12 {
        let t = next_tick(&mut ws).await;
        view.apply(&t);
        let got = view.heads.get(&1).expect("head 1 is shown");
        let plain = view.heads.get(&2).expect("head 2 is shown");
        let expect = if patched {
            // The patch cleared the layers: head 1 is head 2 again.
            let e = t.tick - 1;
            at("talk", 3 + e)
        } else {
            want(t.tick)
        };
        let (pos, _) = rig_oracle(&rig, &expect);
        let d = crate::util::max_abs_diff(got, &pos);
        if d > 1e-4 * diag && patched {
            // The patch lands at a tick boundary; until it does, the layers still show.
            let (pos, _) = rig_oracle(&rig, &want(t.tick));
            let d = crate::util::max_abs_diff(got, &pos);
            assert!(d <= 1e-4 * diag, "tick {}: off by {d:e}", t.tick);
            continue;
        }
        assert!(d <= 1e-4 * diag, "tick {}: off by {d:e} of {diag}", t.tick);
        if !patched {
            let moved = crate::util::max_abs_diff(plain, &pos);
            assert!(
                moved > 1e-3 * diag,
                "tick {}: the layers moved it {moved:e}",
                t.tick
            );
        }
        checked += 1;
        if checked == 6 && !patched {
            let (status, v) = call(
                &server,
                crowdmorph_client::Method::PATCH,
                &format!("/v1/sessions/{}", info.id),
                json!({"change": [{"head": 1, "layers": []}]}),
            )
            .await;
            assert_eq!(status, 200, "{v}");
            // A cleared layer list still has the head's clamp, which talk's weights are within.
            patched = true;
        }
    }
    // Malformed layers are refused when the head is added, naming it.
    for (layer, code) in [
        (json!({"clip": "nope"}), "unknown_clip"),
        (json!({"clip": "smile", "weight": 2}), "invalid_layer"),
        (json!({"clip": "smile", "mask": "knees"}), "invalid_layer"),
    ] {
        let (status, v) = call(
            &server,
            crowdmorph_client::Method::PATCH,
            &format!("/v1/sessions/{}", info.id),
            json!({"add": [{"head": 9, "rig": "default-head", "clip": "talk",
                            "layers": [layer]}]}),
        )
        .await;
        assert!(status == 400 || status == 404, "{v}");
        assert_eq!(v["error"]["code"], code, "{v}");
        assert!(
            v["error"]["message"]
                .as_str()
                .unwrap_or("")
                .contains("head 9"),
            "{v}"
        );
    }
    server.stop().await;
}
