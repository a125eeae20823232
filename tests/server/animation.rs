//! Blends and live weights over HTTP: heads with `blend` layers or `weights` come back as the
//! CPU engine blends their weights, clones of a blend (in any layer order, with float noise in
//! the fractions) share one buffer, and every malformed blend or weight is a 400 naming it.

use bytes::Bytes;
use crowdmorph::engine::Engine;
use crowdmorph::rig::Pose;
use crowdmorph::server::ServerConfig;
use crowdmorph_client::{Encoding, Method};
use crowdmorph_proto::{
    BlendLayer, CONTENT_TYPE_BINCODE, CONTENT_TYPE_JSON, CrowdFrameRequest, Head, LiveWeights,
    OutputOptions,
};
use serde_json::json;

use super::TestServer;

fn request(heads: Vec<Head>) -> CrowdFrameRequest {
    CrowdFrameRequest {
        heads,
        output: OutputOptions::default(),
        wrap: true,
    }
}

fn blended(head: u64, clip: &str, frame: i64, layers: &[(&str, i64, f32)]) -> Head {
    Head {
        blend: layers
            .iter()
            .map(|&(clip, frame, t)| BlendLayer {
                clip: clip.into(),
                frame,
                t,
            })
            .collect(),
        ..Head::playing(head, "default-head", clip, frame)
    }
}

/// The embedded rig's CPU evaluation of `pose`, positions in f32.
fn expected(pose: Pose) -> Vec<f32> {
    let rig = std::sync::Arc::new(crowdmorph::embedded::default_rig());
    let engine = Engine::cpu();
    let prepared = engine.prepare(rig).expect("prepare");
    crate::util::pose_positions(&engine, &prepared, pose)
}

fn positions(resp: &crowdmorph_proto::CrowdFrameResponse, head: usize) -> Vec<f32> {
    let b = &resp.buffers[resp.heads[head].buffer as usize];
    b.positions
        .0
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

#[tokio::test]
async fn blended_and_live_heads_are_blended_in_weight_space_and_clones_share() {
    let server = TestServer::start(ServerConfig::default()).await;
    let rig = crowdmorph::embedded::default_rig();
    let (talk, smile, surprise) = (
        rig.clip_index("talk").unwrap() as u32,
        rig.clip_index("smile").unwrap() as u32,
        rig.clip_index("surprise").unwrap() as u32,
    );
    // The smile clip's frame 3 as live weights by name, as a tracker would send it.
    let mut w = vec![0.0; rig.targets.len()];
    rig.clips[smile as usize].frame_weights(3, &mut w);
    let named: Vec<(String, f32)> = rig
        .targets
        .iter()
        .zip(&w)
        .filter(|(_, w)| **w != 0.0)
        .map(|(n, w)| (n.clone(), *w))
        .collect();
    let heads = vec![
        blended(1, "talk", 40, &[("smile", 3, 0.25), ("surprise", 9, 0.125)]),
        // The same blend, layers swapped, fractions off by float noise.
        blended(
            2,
            "talk",
            40,
            &[("surprise", 9, 0.125 + 1e-7), ("smile", 3, 0.25 - 1e-7)],
        ),
        Head::live(3, "default-head", LiveWeights::Named(named)),
        Head::live(4, "default-head", LiveWeights::Dense(w.clone())),
        // t = 1: the layer's frame alone, the same job as playing it.
        blended(5, "talk", 40, &[("smile", 3, 1.0)]),
        Head::playing(6, "default-head", "smile", 3),
    ];
    for enc in [Encoding::Bincode, Encoding::Json] {
        let (resp, _) = server
            .client
            .crowd_frame(&request(heads.clone()), enc)
            .await
            .expect("frame");
        let buffer = |h: usize| resp.heads[h].buffer;
        assert_eq!(buffer(0), buffer(1), "{enc:?}: one blend, one buffer");
        assert_eq!(
            buffer(2),
            buffer(3),
            "{enc:?}: named and dense weights agree"
        );
        assert_eq!(buffer(4), buffer(5), "{enc:?}: t = 1 is the layer's frame");
        assert_eq!(resp.buffers.len(), 3, "{enc:?}: three unique jobs");
        let blend = Pose::blend((talk, 40), &[(smile, 3, 0.25), (surprise, 9, 0.125)]);
        assert_eq!(positions(&resp, 0), expected(blend), "{enc:?}");
        assert_eq!(positions(&resp, 2), expected(Pose::live(&w)), "{enc:?}");
        // A blend names its largest term; live weights name no clip.
        assert_eq!(resp.buffers[buffer(0) as usize].clip, "talk");
        assert_eq!(resp.buffers[buffer(2) as usize].clip, "");
    }
    // Loose ARKit spellings match as clip columns do.
    let (resp, _) = server
        .client
        .live_frame(
            "default-head",
            vec![
                LiveWeights::Named(vec![("JawOpen".into(), 0.6)]),
                LiveWeights::Named(vec![("jawOpen".into(), 0.6)]),
            ],
            0,
            OutputOptions::default(),
            Encoding::Bincode,
        )
        .await
        .expect("live frame");
    assert_eq!(resp.buffers.len(), 1);
    // A tracker's full ARKit frame: the embedded head has no tongue, so `tongueOut` is ignored
    // (any other unknown name is a 400, below).
    let mut arkit: Vec<(String, f32)> = crowdmorph::rig::ARKIT_NAMES
        .iter()
        .map(|n| (n.to_string(), 0.0))
        .collect();
    arkit[17].1 = 0.6;
    assert_eq!(arkit[17].0, "jawOpen");
    let (resp, _) = server
        .client
        .live_frame(
            "default-head",
            vec![
                LiveWeights::Named(arkit),
                LiveWeights::Named(vec![("jawOpen".into(), 0.6)]),
            ],
            0,
            OutputOptions::default(),
            Encoding::Json,
        )
        .await
        .expect("an ARKit frame");
    assert_eq!(resp.heads[0].buffer, resp.heads[1].buffer);
    server.stop().await;
}

#[tokio::test]
async fn rendered_frames_accept_blended_and_live_heads() {
    let server = TestServer::start(ServerConfig::default()).await;
    let body = json!({
        "heads": [
            {"head": 1, "rig": "default-head", "clip": "talk", "frame": 4,
             "blend": [{"clip": "smile", "frame": 2, "t": 0.5}]},
            {"head": 2, "rig": "default-head", "weights": {"jawOpen": 1.0}},
        ],
        "image": {"width": 64, "height": 48, "format": "png"},
    });
    let reply = server
        .client
        .send(
            Method::POST,
            "/v1/crowd/render",
            Some(CONTENT_TYPE_JSON),
            None,
            Bytes::from(body.to_string()),
        )
        .await
        .expect("send");
    assert_eq!(
        reply.status,
        200,
        "{}",
        String::from_utf8_lossy(&reply.body)
    );
    assert_eq!(reply.content_type.as_deref(), Some("image/png"));
    server.stop().await;
}

#[tokio::test]
async fn bad_blends_and_weights_are_400s_naming_the_field() {
    let server = TestServer::start(ServerConfig::default()).await;
    let head = |extra: serde_json::Value| {
        let mut h = json!({"head": 5, "rig": "default-head", "clip": "talk", "frame": 1});
        for (k, v) in extra.as_object().unwrap() {
            h[k] = v.clone();
        }
        h
    };
    let layer = |t: f64| json!({"clip": "smile", "frame": 0, "t": t});
    let cases = [
        (
            head(json!({"blend": [layer(1.5)]})),
            400,
            "invalid_blend",
            "blend[0].t",
        ),
        (
            head(json!({"blend": [layer(-0.1)]})),
            400,
            "invalid_blend",
            "blend[0].t",
        ),
        (
            head(json!({"blend": [layer(0.6), layer(0.6)]})),
            400,
            "invalid_blend",
            "sum",
        ),
        (
            head(json!({"blend": [layer(0.1), layer(0.1), layer(0.1), layer(0.1), layer(0.1)]})),
            400,
            "invalid_blend",
            "at most 4",
        ),
        (
            head(json!({"blend": [{"clip": "nope", "frame": 0, "t": 0.5}]})),
            404,
            "unknown_clip",
            "nope",
        ),
        (
            json!({"head": 5, "rig": "default-head", "weights": {"noSuchShape": 1.0}}),
            400,
            "unknown_targets",
            "noSuchShape",
        ),
        (
            json!({"head": 5, "rig": "default-head", "weights": {"jawOpen": 1e9}}),
            400,
            "invalid_weights",
            "jawOpen",
        ),
        (
            json!({"head": 5, "rig": "default-head", "weights": {"jawOpen": 1, "JawOpen": 0.5}}),
            400,
            "invalid_weights",
            "twice",
        ),
        (
            json!({"head": 5, "rig": "default-head", "weights": [0.5, 0.5]}),
            400,
            "invalid_weights",
            "dense weights",
        ),
        (
            // Weights over a clip are a layer (tests/server/layers.rs); a blend without a
            // clip has nothing to blend.
            json!({"head": 5, "rig": "default-head", "weights": {"jawOpen": 1},
                   "blend": [{"clip": "smile", "frame": 0, "t": 0.5}]}),
            400,
            "invalid_weights",
            "need a clip",
        ),
    ];
    for (h, status, code, needle) in cases {
        let body = json!({"heads": [h]}).to_string();
        let reply = server
            .client
            .send(
                Method::POST,
                "/v1/crowd/frame",
                Some(CONTENT_TYPE_JSON),
                None,
                Bytes::from(body.clone()),
            )
            .await
            .expect("send");
        assert_eq!(reply.status, status, "{body}");
        let e = reply.error().expect("a JSON error");
        assert_eq!(e.error.code, code, "{body}: {}", e.error.message);
        assert!(
            e.error.message.contains(needle) && e.error.message.contains("head 0"),
            "{body}: {:?} should name {needle:?} and the head",
            e.error.message
        );
    }
    // NaN and infinities cannot be written in JSON, but can in bincode.
    for bad in [f32::NAN, f32::INFINITY] {
        for h in [
            blended(5, "talk", 1, &[("smile", 0, bad)]),
            Head::live(5, "default-head", LiveWeights::Dense(vec![bad; 51])),
        ] {
            let body = crowdmorph_proto::wire::to_bincode(&request(vec![h])).unwrap();
            let reply = server
                .client
                .send(
                    Method::POST,
                    "/v1/crowd/frame",
                    Some(CONTENT_TYPE_BINCODE),
                    None,
                    Bytes::from(body),
                )
                .await
                .expect("send");
            assert_eq!(reply.status, 400);
            let code = reply.error().expect("a JSON error").error.code;
            assert!(
                code == "invalid_blend" || code == "invalid_weights",
                "{code}"
            );
        }
    }
    server.stop().await;
}
