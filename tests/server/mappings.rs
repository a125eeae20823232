//! A rig's named masks and mappings over HTTP (issue 47 items 1 and 4): masks stored,
//! listed, deleted and kept across a restart, a layer naming one equal to the same mask
//! inline; mappings (`a2f`, a rig's own with gain, offset, clamp, many-to-one and
//! one-to-many, a VRM file's `vrm` with `isBinary` and overrides) giving the same vertices as
//! the weights they map to sent directly; CSV clips through a mapping; and every malformed
//! mask, mapping or use of one a named 4xx.

use bytes::Bytes;
use crowdmorph::server::ServerConfig;
use crowdmorph_client::{Encoding, Method};
use crowdmorph_proto::{
    CONTENT_TYPE_BINCODE, CrowdFrameRequest, CrowdFrameResponse, Head, LiveWeights, MapEntry,
    Mapping, OutputOptions,
};
use serde_json::{Value, json};

use super::layers::loose;
use super::sessions::call;
use super::{TestServer, stored_config, temp_dir};

fn code(v: &Value) -> &str {
    v["error"]["code"].as_str().unwrap_or("")
}

fn named(pairs: &[(&str, f32)]) -> Option<Box<LiveWeights>> {
    Some(Box::new(LiveWeights::Named(
        pairs.iter().map(|(n, w)| (n.to_string(), *w)).collect(),
    )))
}

/// A live head of `rig` with named weights, through `mapping` when given.
fn live(id: u64, rig: &str, pairs: &[(&str, f32)], mapping: Option<&str>) -> Head {
    Head {
        head: id,
        rig: rig.into(),
        weights: named(pairs),
        mapping: mapping.map(str::to_string),
        ..Head::default()
    }
}

async fn frame(server: &TestServer, heads: Vec<Head>) -> CrowdFrameResponse {
    let req = CrowdFrameRequest {
        heads,
        output: OutputOptions::default(),
        wrap: true,
    };
    let (resp, _) = server
        .client
        .crowd_frame(&req, Encoding::Bincode)
        .await
        .expect("frame");
    resp
}

fn positions(resp: &CrowdFrameResponse, head: usize) -> Vec<f32> {
    let b = &resp.buffers[resp.heads[head].buffer as usize];
    super::positions_f32(resp.format, b)
}

/// Heads in pairs (mapped, direct): each pair's vertices are the same, and differ from the
/// rest pose (the weights did something).
async fn pairs_agree(server: &TestServer, mut heads: Vec<Head>) {
    let n = heads.len();
    // The pose without any weight sent, last.
    let rest = live(999, &heads[0].rig.clone(), &[], None);
    heads.push(rest);
    let resp = frame(server, heads).await;
    let rest = positions(&resp, n);
    for i in (0..n).step_by(2) {
        let (a, b) = (positions(&resp, i), positions(&resp, i + 1));
        assert_eq!(a, b, "heads {i} and {}", i + 1);
        assert_ne!(a, rest, "heads {i} and {} are the rest pose", i + 1);
    }
}

async fn put(server: &TestServer, path: &str, body: Value) -> (u16, Value) {
    call(server, Method::PUT, path, body).await
}

async fn get(server: &TestServer, path: &str) -> (u16, Value) {
    call(server, Method::GET, path, Value::Null).await
}

#[tokio::test]
async fn a2f_and_a_rigs_own_mapping_give_the_weights_they_map_to() {
    let server = TestServer::start(ServerConfig::default()).await;
    // a2f: Audio2Face's capitalised names onto the ARKit targets of the same name.
    let a2f = [
        ("JawOpen", 0.6),
        ("EyeBlinkLeft", 0.9),
        ("MouthSmileRight", 0.4),
        ("BrowInnerUp", 0.3),
    ];
    let arkit: Vec<(String, f32)> = a2f
        .iter()
        .map(|(n, w)| {
            (
                crowdmorph::rig::ARKIT_NAMES
                    .iter()
                    .find(|a| a.eq_ignore_ascii_case(n))
                    .expect("an ARKit name")
                    .to_string(),
                *w,
            )
        })
        .collect();
    let arkit: Vec<(&str, f32)> = arkit.iter().map(|(n, w)| (n.as_str(), *w)).collect();
    // A rig's own: one-to-many (Smile), many-to-one summed then clamped (Open, Open2), gain and
    // offset (Brow).
    let (status, v) = put(
        &server,
        "/v1/rigs/default-head/mappings/mine",
        json!({"entries": [
            {"source": "Smile", "target": "mouthSmileLeft", "gain": 0.5},
            {"source": "Smile", "target": "mouthSmile_R", "gain": 0.5},
            {"source": "Open", "target": "jawOpen", "gain": 2, "offset": 0.1, "clamp": [0, 1]},
            {"source": "Open2", "target": "jawOpen"},
            {"source": "Brow", "target": "browInnerUp", "gain": -0.5, "offset": 0.75}
        ]}),
    )
    .await;
    assert_eq!(status, 200, "{v}");
    assert_eq!(v["mapping"]["entries"][3]["gain"], json!(1.0), "{v}");
    let heads = vec![
        live(1, "default-head", &a2f, Some("a2f")),
        live(2, "default-head", &arkit, None),
        // Smile 0.8 → 0.4 each side; jawOpen 2·0.3 + 0.1 + 0.5 = 1.2, clamped to 1; brow
        // 0.75 − 0.5·0.5 = 0.5.
        live(
            3,
            "default-head",
            &[("Smile", 0.8), ("Open", 0.3), ("Open2", 0.5), ("Brow", 0.5)],
            Some("mine"),
        ),
        live(
            4,
            "default-head",
            &[
                ("mouthSmileLeft", 0.4),
                ("mouthSmileRight", 0.4),
                ("jawOpen", 1.0),
                ("browInnerUp", 0.5),
            ],
            None,
        ),
        // Sources matched loosely; one not sent sets nothing (Open2 alone: 0.2).
        live(5, "default-head", &[("open_2", 0.2)], Some("mine")),
        live(6, "default-head", &[("jawOpen", 0.2)], None),
    ];
    pairs_agree(&server, heads.clone()).await;
    // The same through JSON.
    let body = json!({"heads": [
        {"head": 1, "rig": "default-head", "weights": {"JawOpen": 0.6}, "mapping": "a2f"},
        {"head": 2, "rig": "default-head", "weights": {"jawOpen": 0.6}}
    ]});
    let (status, v) = call(&server, Method::POST, "/v1/crowd/frame", body).await;
    assert_eq!(status, 200, "{v}");
    assert_eq!(v["heads"][0]["buffer"], v["heads"][1]["buffer"], "one job");
    // Mapped weights over a clip replace the targets they reach, as weights by name do.
    let over = |id, w: &[(&str, f32)], m: Option<&str>| Head {
        clip: "talk".into(),
        frame: 4,
        ..live(id, "default-head", w, m)
    };
    pairs_agree(
        &server,
        vec![
            over(7, &[("Smile", 0.6)], Some("mine")),
            over(
                8,
                &[("mouthSmileLeft", 0.3), ("mouthSmileRight", 0.3)],
                None,
            ),
        ],
    )
    .await;
    // Listed: the built-in ones, then the rig's.
    let (_, list) = get(&server, "/v1/rigs/default-head/mappings").await;
    let names: Vec<&str> = list["mappings"]
        .as_array()
        .expect("list")
        .iter()
        .map(|m| m["name"].as_str().unwrap_or(""))
        .collect();
    assert_eq!(names, ["arkit", "a2f", "oculus-visemes", "mine"], "{list}");
    let (status, v) = get(&server, "/v1/rigs/default-head/mappings/oculus-visemes").await;
    assert_eq!((status, v["builtin"].as_bool()), (200, Some(true)), "{v}");
    assert_eq!(v["mapping"]["sources"].as_array().map(Vec::len), Some(15));
    server.stop().await;
}

#[tokio::test]
async fn every_a2f_and_arkit_source_reaches_a_target_of_the_embedded_head() {
    let server = TestServer::start(ServerConfig::default()).await;
    let rig = crowdmorph::embedded::default_rig();
    for name in ["arkit", "a2f"] {
        let (status, v) = get(&server, &format!("/v1/rigs/default-head/mappings/{name}")).await;
        assert_eq!(status, 200, "{v}");
        let entries = v["mapping"]["entries"].as_array().expect("entries");
        assert!(entries.len() >= 46, "{name}: {}", entries.len());
        for e in entries {
            let (s, t) = (
                e["source"].as_str().unwrap_or(""),
                e["target"].as_str().unwrap_or(""),
            );
            assert!(s.starts_with(char::is_uppercase), "{name}: {s}");
            assert!(crowdmorph::rig::ARKIT_NAMES.contains(&t), "{name}: {t}");
            // The embedded head has every ARKit name but tongueOut, which a2f leaves out.
            if name == "a2f" || t != "tongueOut" {
                assert!(
                    rig.targets.iter().any(|r| loose(r) == loose(t)),
                    "{name}: {t} is not a target of the embedded head"
                );
            }
        }
    }
    server.stop().await;
}

#[tokio::test]
async fn masks_are_stored_listed_deleted_and_kept_across_a_restart() {
    let dir = temp_dir("masks");
    let server = TestServer::start(stored_config(&dir)).await;
    let (status, v) = put(
        &server,
        "/v1/rigs/default-head/masks/lips",
        json!({"jawOpen": 1.0, "mouthFunnel": 0.5}),
    )
    .await;
    assert_eq!(status, 200, "{v}");
    let (status, _) = put(
        &server,
        "/v1/rigs/default-head/mappings/mine",
        json!({"entries": [{"source": "Open", "target": "jawOpen", "gain": 0.5}]}),
    )
    .await;
    assert_eq!(status, 200);
    let (status, v) = get(&server, "/v1/rigs/default-head/masks").await;
    assert_eq!(status, 200);
    assert_eq!(v["masks"][0]["name"], "lips", "{v}");
    // A layer naming the mask is the layer with the mask inline: one job, one buffer (and
    // not the base's).
    let layered = |id, mask: Value| {
        json!({"head": id, "rig": "default-head", "clip": "talk", "frame": 2,
               "layers": [{"clip": "smile", "frame": 7, "weight": 0.8, "mask": mask}]})
    };
    let same_job = |server: &TestServer| {
        let body = json!({"heads": [
            layered(1, json!("lips")),
            layered(2, json!({"mouthFunnel": 0.5, "jawOpen": 1.0})),
            json!({"head": 3, "rig": "default-head", "clip": "talk", "frame": 2})
        ]});
        let client = server.client.clone();
        async move {
            let r = client
                .send(
                    Method::POST,
                    "/v1/crowd/frame",
                    Some("application/json"),
                    Some("application/json"),
                    Bytes::from(body.to_string()),
                )
                .await
                .expect("answer");
            assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
            let v: Value = serde_json::from_slice(&r.body).expect("JSON");
            assert_eq!(v["heads"][0]["buffer"], v["heads"][1]["buffer"], "{v}");
            assert_ne!(v["heads"][0]["buffer"], v["heads"][2]["buffer"], "{v}");
        }
    };
    same_job(&server).await;
    // Stored with the rig: a restarted server has the mask and the mapping.
    server.stop().await;
    let server = TestServer::start(stored_config(&dir)).await;
    let (status, v) = get(&server, "/v1/rigs/default-head/masks/lips").await;
    assert_eq!(status, 200, "{v}");
    assert_eq!(v["mask"], json!({"jawOpen": 1.0, "mouthFunnel": 0.5}));
    let (status, v) = get(&server, "/v1/rigs/default-head/mappings/mine").await;
    assert_eq!(status, 200, "{v}");
    same_job(&server).await;
    pairs_agree(
        &server,
        vec![
            live(1, "default-head", &[("Open", 0.8)], Some("mine")),
            live(2, "default-head", &[("jawOpen", 0.4)], None),
        ],
    )
    .await;
    // A session head may name the mask.
    let session = json!({"heads": [{"head": 1, "rig": "default-head", "clip": "talk",
        "layers": [{"clip": "smile", "mask": "lips"}]}]});
    let (status, v) = call(&server, Method::POST, "/v1/sessions", session.clone()).await;
    assert_eq!(status, 201, "{v}");
    // Deleted: gone, and a layer naming it is a 400 naming it.
    let (status, _) = call(
        &server,
        Method::DELETE,
        "/v1/rigs/default-head/masks/lips",
        Value::Null,
    )
    .await;
    assert_eq!(status, 204);
    let (status, v) = get(&server, "/v1/rigs/default-head/masks/lips").await;
    assert_eq!((status, code(&v)), (404, "unknown_mask"), "{v}");
    let (status, v) = call(&server, Method::POST, "/v1/sessions", session).await;
    assert_eq!((status, code(&v)), (400, "invalid_layer"), "{v}");
    assert!(
        v["error"]["message"]
            .as_str()
            .unwrap_or("")
            .contains("lips"),
        "{v}"
    );
    server.stop().await;
    let server = TestServer::start(stored_config(&dir)).await;
    let (status, _) = get(&server, "/v1/rigs/default-head/masks/lips").await;
    assert_eq!(status, 404, "the delete was stored");
    server.stop().await;
    let _ = std::fs::remove_dir_all(&dir);
}

#[tokio::test]
async fn malformed_masks_mappings_and_their_uses_are_named_4xx() {
    let server = TestServer::start(ServerConfig::default()).await;
    let long = "x".repeat(300);
    let cases: Vec<(&str, Value, u16, &str)> = vec![
        ("masks/m", json!(["nope"]), 400, "unknown_targets"),
        ("masks/m", json!({"jawOpen": 2.0}), 400, "invalid_mask"),
        ("masks/m", json!("upper_face"), 400, "invalid_mask"),
        ("masks/m", json!([long.clone()]), 400, "invalid_mask"),
        ("masks/.m", json!(["jawOpen"]), 400, "invalid_name"),
        (
            "mappings/m",
            json!({"entries": [{"source": "A", "target": "nope"}]}),
            400,
            "unknown_targets",
        ),
        (
            "mappings/m",
            json!({"entries": [{"source": long, "target": "jawOpen"}]}),
            400,
            "invalid_mapping",
        ),
        (
            "mappings/m",
            json!({"entries": [{"source": "A", "target": "jawOpen", "gain": 1e9}]}),
            400,
            "invalid_mapping",
        ),
        (
            "mappings/m",
            json!({"entries": [{"source": "A", "target": "jawOpen", "clamp": [1, 0]}]}),
            400,
            "invalid_mapping",
        ),
        (
            "mappings/m",
            json!({"entries": [
                {"source": "A", "target": "jawOpen", "clamp": [0, 0.2]},
                {"source": "B", "target": "jawOpen", "clamp": [0.5, 1]}]}),
            400,
            "invalid_mapping",
        ),
        (
            "mappings/m",
            json!({"entries": vec![json!({"source": "A", "target": "jawOpen"}); 1025]}),
            400,
            "invalid_mapping",
        ),
        (
            "mappings/a2f",
            json!({"entries": [{"source": "A", "target": "jawOpen"}]}),
            400,
            "invalid_name",
        ),
        (
            "mappings/m",
            json!({"entries": [], "extra": 1}),
            400,
            "invalid_body",
        ),
    ];
    for (path, body, status, want) in cases {
        let (s, v) = put(&server, &format!("/v1/rigs/default-head/{path}"), body).await;
        if want == "invalid_body" {
            assert_eq!(s, status, "{path}: {v}");
            continue;
        }
        assert_eq!((s, code(&v)), (status, want), "{path}: {v}");
    }
    // NaN travels in bincode only.
    let nan = Mapping {
        entries: vec![MapEntry {
            source: "A".into(),
            target: "jawOpen".into(),
            gain: f32::NAN,
            offset: 0.0,
            clamp: None,
        }],
        sources: Vec::new(),
    };
    let r = server
        .client
        .send(
            Method::PUT,
            "/v1/rigs/default-head/mappings/m",
            Some(CONTENT_TYPE_BINCODE),
            Some("application/json"),
            Bytes::from(crowdmorph_proto::wire::to_bincode(&nan).expect("bincode")),
        )
        .await
        .expect("answer");
    let v: Value = serde_json::from_slice(&r.body).expect("JSON");
    assert_eq!((r.status, code(&v)), (400, "invalid_mapping"), "{v}");
    assert!(
        v["error"]["message"]
            .as_str()
            .unwrap_or("")
            .contains("gain"),
        "{v}"
    );
    // Nothing was stored.
    let (_, v) = get(&server, "/v1/rigs/default-head/masks").await;
    assert_eq!(v["masks"], json!([]));
    let (status, v) = get(&server, "/v1/rigs/default-head/mappings/m").await;
    assert_eq!((status, code(&v)), (404, "unknown_mapping"), "{v}");
    let (status, v) = call(
        &server,
        Method::DELETE,
        "/v1/rigs/default-head/mappings/arkit",
        Value::Null,
    )
    .await;
    assert_eq!((status, code(&v)), (400, "invalid_name"), "{v}");
    // Heads naming a mapping badly.
    let head = |extra: Value| {
        let mut h = json!({"head": 5, "rig": "default-head"});
        for (k, v) in extra.as_object().expect("object") {
            h[k] = v.clone();
        }
        json!({"heads": [h]})
    };
    let uses: Vec<(Value, u16, &str, &str)> = vec![
        (
            head(json!({"weights": {"JawOpen": 0.5}, "mapping": "nope"})),
            404,
            "unknown_mapping",
            "nope",
        ),
        (
            head(json!({"weights": [0.5], "mapping": "a2f"})),
            400,
            "invalid_weights",
            "by name",
        ),
        (
            head(json!({"clip": "talk", "mapping": "a2f"})),
            400,
            "invalid_weights",
            "by name",
        ),
        (
            head(json!({"weights": {"Knee": 0.5}, "mapping": "a2f"})),
            400,
            "invalid_weights",
            "Knee",
        ),
        (
            head(json!({"weights": {"JawOpen": 0.5, "jaw_open": 0.2}, "mapping": "a2f"})),
            400,
            "invalid_weights",
            "twice",
        ),
        (
            head(json!({"weights": {"JawOpen": 1e6}, "mapping": "a2f"})),
            400,
            "invalid_weights",
            "JawOpen",
        ),
    ];
    for (body, status, want, names) in uses {
        let (got, v) = call(&server, Method::POST, "/v1/crowd/frame", body.clone()).await;
        assert_eq!((got, code(&v)), (status, want), "{body}: {v}");
        let m = v["error"]["message"].as_str().unwrap_or("");
        assert!(m.contains(names) && m.contains("head 0"), "{body}: {v}");
    }
    server.stop().await;
}

#[tokio::test]
async fn a_csv_clip_through_a_mapping_is_the_clip_of_its_targets() {
    let server = TestServer::start(ServerConfig::default()).await;
    let upload = |query: &'static str, csv: &'static str| {
        let client = server.client.clone();
        async move {
            client
                .send(
                    Method::POST,
                    &format!("/v1/rigs/default-head/clips?{query}"),
                    Some("text/csv"),
                    Some("application/json"),
                    Bytes::from(csv),
                )
                .await
                .expect("answer")
        }
    };
    let mapped = upload(
        "name=mapped&mapping=a2f",
        "Timecode,JawOpen,EyeBlinkLeft\n00:00,0.5,0.25\n00:01,0.75,\n",
    )
    .await;
    assert_eq!(
        mapped.status,
        201,
        "{}",
        String::from_utf8_lossy(&mapped.body)
    );
    let direct = upload(
        "name=direct",
        "Timecode,jawOpen,eyeBlinkLeft\n00:00,0.5,0.25\n00:01,0.75,0\n",
    )
    .await;
    assert_eq!(
        direct.status,
        201,
        "{}",
        String::from_utf8_lossy(&direct.body)
    );
    let play = |id, clip: &str, f| Head::playing(id, "default-head", clip, f);
    pairs_agree(
        &server,
        vec![
            play(1, "mapped", 0),
            play(2, "direct", 0),
            play(3, "mapped", 1),
            play(4, "direct", 1),
        ],
    )
    .await;
    let bad = upload("name=bad&mapping=nope", "JawOpen\n1\n").await;
    assert_eq!(bad.status, 404, "{}", String::from_utf8_lossy(&bad.body));
    let none = upload("name=bad&mapping=a2f", "Knee\n1\n").await;
    assert_eq!(none.status, 400, "{}", String::from_utf8_lossy(&none.body));
    server.stop().await;
}

/// A triangle with three morph targets (`Fcl_Joy`, `Fcl_Blink`, `Fcl_A`) and `vrm` as the
/// document's VRM block.
fn vrm_rig(extension: &str, vrm: Value) -> Vec<u8> {
    let mut b = crate::util::builder::Builder::new();
    let tri = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
    let targets = vec![
        vec![[0.0, 0.0, 0.1]; 3],
        vec![[0.0, 0.2, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]],
        vec![[0.3, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.4]],
    ];
    let mesh = b.mesh_with_targets(
        &tri,
        Some(&[0, 1, 2]),
        &targets,
        Some(&["Fcl_Joy", "Fcl_Blink", "Fcl_A"]),
    );
    let node = b.node(Some(mesh));
    b.scene(&[node]);
    b.json_mut()["extensionsUsed"] = json!([extension]);
    b.json_mut()["extensions"] = json!({ extension: vrm });
    b.to_glb()
}

#[tokio::test]
async fn vrm_expressions_become_the_rigs_vrm_mapping() {
    let server = TestServer::start(ServerConfig::default()).await;
    let glb = vrm_rig(
        "VRMC_vrm",
        json!({"specVersion": "1.0", "expressions": {
            "preset": {
                "happy": {"isBinary": true, "overrideBlink": "block",
                          "morphTargetBinds": [{"node": 0, "index": 0, "weight": 1.0}]},
                "blink": {"morphTargetBinds": [{"node": 0, "index": 1, "weight": 1.0}]},
                "aa": {"morphTargetBinds": [{"node": 0, "index": 2, "weight": 0.5}]}
            },
            "custom": {
                "soft": {"overrideMouth": "blend",
                         "morphTargetBinds": [{"node": 0, "index": 0, "weight": 0.25}]}
            }
        }}),
    );
    let info = server
        .client
        .upload_rig("vrm1", Bytes::from(glb))
        .await
        .expect("upload");
    assert!(
        !info.import_notes.iter().any(|n| n.contains("VRM")),
        "{:?}",
        info.import_notes
    );
    let (status, v) = get(&server, "/v1/rigs/vrm1/mappings/vrm").await;
    assert_eq!(status, 200, "{v}");
    assert_eq!(
        v["mapping"]["sources"].as_array().map(Vec::len),
        Some(4),
        "{v}"
    );
    let heads = vec![
        // happy 0.7 is binary 1 and blocks blink; aa is no blink: 0.6 · 0.5.
        live(
            1,
            "vrm1",
            &[("happy", 0.7), ("blink", 1.0), ("aa", 0.6)],
            Some("vrm"),
        ),
        live(2, "vrm1", &[("Fcl_Joy", 1.0), ("Fcl_A", 0.3)], None),
        // happy 0.4 is binary 0: blink stays.
        live(3, "vrm1", &[("happy", 0.4), ("blink", 1.0)], Some("vrm")),
        live(4, "vrm1", &[("Fcl_Blink", 1.0)], None),
        // soft 0.25 blends the mouth: aa 0.8 · (1 − 0.25) · 0.5 = 0.3; soft itself 0.0625.
        live(5, "vrm1", &[("soft", 0.25), ("aa", 0.8)], Some("vrm")),
        live(6, "vrm1", &[("Fcl_Joy", 0.0625), ("Fcl_A", 0.3)], None),
    ];
    pairs_agree(&server, heads).await;
    // VRM 0.x: presets renamed as 1.0 names them, weights in percent.
    let glb = vrm_rig(
        "VRM",
        json!({"blendShapeMaster": {"blendShapeGroups": [
            {"name": "Joy", "presetName": "joy", "binds": [{"mesh": 0, "index": 0, "weight": 100}]},
            {"name": "A", "presetName": "a", "isBinary": true,
             "binds": [{"mesh": 0, "index": 2, "weight": 50}]}
        ]}}),
    );
    server
        .client
        .upload_rig("vrm0", Bytes::from(glb))
        .await
        .expect("upload");
    let heads = vec![
        live(1, "vrm0", &[("happy", 0.5), ("aa", 0.7)], Some("vrm")),
        live(2, "vrm0", &[("Fcl_Joy", 0.5), ("Fcl_A", 0.5)], None),
    ];
    pairs_agree(&server, heads).await;
    // A rig without VRM has no vrm mapping, and nobody may PUT one.
    let (status, v) = get(&server, "/v1/rigs/default-head/mappings/vrm").await;
    assert_eq!((status, code(&v)), (404, "unknown_mapping"), "{v}");
    let (status, v) = put(
        &server,
        "/v1/rigs/vrm0/mappings/vrm",
        json!({"entries": [{"source": "A", "target": "Fcl_A"}]}),
    )
    .await;
    assert_eq!((status, code(&v)), (400, "invalid_name"), "{v}");
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_session_head_whose_mask_is_deleted_is_missing_from_later_ticks() {
    use super::sessions::{View, connect, create, next_tick};
    let server = TestServer::start(ServerConfig::default()).await;
    let (status, v) = put(
        &server,
        "/v1/rigs/default-head/masks/lips",
        json!(["jawOpen"]),
    )
    .await;
    assert_eq!(status, 200, "{v}");
    let info = create(
        &server,
        json!({"fps": 30, "heads": [
            {"head": 1, "rig": "default-head", "clip": "talk",
             "layers": [{"clip": "smile", "weight": 0.8, "mask": "lips"}]},
            {"head": 2, "rig": "default-head", "clip": "talk", "position": [1, 0, 0]}]}),
    )
    .await;
    let mut ws = connect(&server, &info.id, json!({"format": "f32"})).await;
    let mut view = View::default();
    for _ in 0..60 {
        view.apply(&next_tick(&mut ws).await);
        if view.heads.len() == 2 {
            break;
        }
    }
    assert_eq!(
        view.heads.len(),
        2,
        "both heads shown while the mask exists"
    );
    let (status, _) = call(
        &server,
        Method::DELETE,
        "/v1/rigs/default-head/masks/lips",
        Value::Null,
    )
    .await;
    assert_eq!(status, 204);
    // As a head whose graph or clip is deleted: missing from the next ticks, the other kept.
    let mut gone = false;
    for _ in 0..60 {
        view.apply(&next_tick(&mut ws).await);
        if !view.heads.contains_key(&1) {
            gone = true;
            break;
        }
    }
    assert!(gone, "head 1 still shown after its mask was deleted");
    assert!(view.heads.contains_key(&2), "head 2 kept");
    server.stop().await;
}
