//! Live-driven session heads (issue 47 item 3) over real sockets: producers `POST` samples to
//! `/v1/sessions/{id}/live` or stream them over its WebSocket, and a viewer's vertices are
//! checked against the f64 oracle. A live head's vertices are always the oracle's blend
//! `base + α·(live − base)` (its base the clip frame of the tick, `live` the same frame with the
//! driven targets replaced); α is read back from the vertices and must rise, hold and fall
//! by at most one fade step per tick. The jitter buffer plays out-of-order timecodes in
//! order. Producers sending garbage get named errors, floods are shed and closed, idle and
//! surplus producer sockets are closed, and the viewer's ticks keep coming throughout.

use std::time::Duration;

use crowdmorph::server::ServerConfig;
use crowdmorph::server::sessions::SessionLimits;
use crowdmorph_client::Method;
use futures_util::{SinkExt, StreamExt};
use glam::DVec3;
use serde_json::{Value, json};
use tokio_tungstenite::tungstenite::Message;

use super::TestServer;
use super::layers::{channels, frame_weights};
use super::sessions::{View, call, connect, create, next_close, next_tick};
use crate::util::rig_oracle;

/// Posts one live message; the status and the JSON answer.
async fn post_live(server: &TestServer, id: &str, body: Value) -> (u16, Value) {
    call(
        server,
        Method::POST,
        &format!("/v1/sessions/{id}/live"),
        body,
    )
    .await
}

/// Posts one live message with `client` (a producer task's own handle); the status.
async fn send_live(client: &crowdmorph_client::Client, id: &str, body: &Value) -> u16 {
    client
        .send(
            Method::POST,
            &format!("/v1/sessions/{id}/live"),
            Some("application/json"),
            None,
            bytes::Bytes::from(body.to_string()),
        )
        .await
        .expect("post live")
        .status
}

/// α and the relative residual of `got` as `base + α·(live − base)`, by least squares.
fn share(got: &[f32], base: &[DVec3], live: &[DVec3]) -> (f64, f64) {
    let (mut num, mut den) = (0.0, 0.0);
    for (g, (b, l)) in got.chunks_exact(3).zip(base.iter().zip(live)) {
        let g = DVec3::new(f64::from(g[0]), f64::from(g[1]), f64::from(g[2]));
        let d = *l - *b;
        num += (g - *b).dot(d);
        den += d.dot(d);
    }
    let a = num / den;
    let mut worst: f64 = 0.0;
    for (g, (b, l)) in got.chunks_exact(3).zip(base.iter().zip(live)) {
        let g = DVec3::new(f64::from(g[0]), f64::from(g[1]), f64::from(g[2]));
        worst = worst.max((g - (*b + a * (*l - *b))).length());
    }
    (a, worst)
}

/// A live head over a clip follows its input: it fades in by at most one step (`dt / fade`)
/// per tick to the oracle's override of the driven targets, holds it while input comes,
/// holds the last input for `hold_ms` once it stops, then fades back to the clip by at most
/// one step per tick, ending where a head without input is.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_live_head_follows_input_holds_it_and_fades_back_without_a_pop() {
    let server = TestServer::start(ServerConfig::default()).await;
    let rig = crowdmorph::embedded::default_rig();
    let info = create(
        &server,
        json!({"fps": 30, "heads": [
            {"head": 1, "rig": "default-head", "clip": "talk",
             "live": {"hold_ms": 300, "fade_ms": 200}},
            {"head": 2, "rig": "default-head", "clip": "talk"}]}),
    )
    .await;
    let mut ws = connect(&server, &info.id, json!({"format": "f32"})).await;
    let driven = [
        ("jawOpen", 0.9),
        ("eyeBlinkLeft", 0.7),
        ("browInnerUp", 0.8),
    ];
    let talk = &rig.clips[rig.clip_index("talk").expect("talk")];
    let weights = |tick: u64, live: bool| {
        let mut w = frame_weights(&rig, "talk", ((tick - 1) % u64::from(talk.frames)) as u32);
        if live {
            for (name, v) in driven {
                for k in channels(&rig, &[name]) {
                    w[k] = v;
                }
            }
        }
        w
    };
    let b = rig.bbox();
    let diag = f64::from((b.max - b.min).length());
    // The producer: a sample every 25 ms until told to stop.
    let (stop, mut stopped) = tokio::sync::oneshot::channel::<()>();
    let producer = {
        let server_client = server.client.clone();
        let id = info.id.clone();
        let body = json!({"heads": [{"head": 1,
            "weights": driven.iter().map(|(n, v)| ((*n).to_string(), json!(v)))
                .collect::<serde_json::Map<_, _>>()}]});
        tokio::spawn(async move {
            let mut sent = 0u32;
            loop {
                let status = send_live(&server_client, &id, &body).await;
                assert_eq!(status, 200);
                sent += 1;
                tokio::select! {
                    _ = &mut stopped => return sent,
                    () = tokio::time::sleep(Duration::from_millis(25)) => {}
                }
            }
        })
    };
    let step = 1.0 / 6.0; // 200 ms of fade at 30 ticks a second
    let mut view = View::default();
    let (mut last_a, mut last_tick) = (0.0f64, 0u64);
    let mut phase = 0; // 0: fading in, 1: held at 1, 2: stopped, 3: faded out
    let mut at_one = 0;
    let mut stop = Some(stop);
    let mut after_out = 0;
    for _ in 0..600 {
        let t = next_tick(&mut ws).await;
        view.apply(&t);
        let got = view.heads.get(&1).expect("head 1");
        let (base, _) = rig_oracle(&rig, &weights(t.tick, false));
        let (live, _) = rig_oracle(&rig, &weights(t.tick, true));
        let (a, off) = share(got, &base, &live);
        assert!(
            off <= 1e-4 * diag,
            "tick {}: not a blend of the clip and its input (off by {off:e})",
            t.tick
        );
        assert!((-1e-3..=1.0 + 1e-3).contains(&a), "tick {}: α {a}", t.tick);
        if last_tick > 0 {
            let bound = (t.tick - last_tick) as f64 * step + 1e-3;
            assert!(
                (a - last_a).abs() <= bound,
                "tick {}: α went from {last_a} to {a}, more than {bound}",
                t.tick
            );
        }
        if std::env::var_os("LIVE_DEBUG").is_some() {
            eprintln!("tick {} α {a:.4} off {off:e}", t.tick);
        }
        match phase {
            0 if a > 1.0 - 2e-3 => phase = 1,
            0 => assert!(a >= last_a - 1e-4, "fading in, α fell to {a}"),
            1 => {
                assert!(
                    a > 1.0 - 2e-3,
                    "tick {}: input stopped showing ({a})",
                    t.tick
                );
                at_one += 1;
                if at_one == 10 {
                    if let Some(s) = stop.take() {
                        let _ = s.send(());
                    }
                    phase = 2;
                }
            }
            2 if a < 2e-3 => phase = 3,
            2 => assert!(a <= last_a + 1e-4, "fading out, α rose to {a}"),
            _ => {
                // Faded out: head 1 is head 2 again.
                let plain = view.heads.get(&2).expect("head 2");
                assert!(crate::util::max_abs_diff(got, &base) <= 1e-4 * diag);
                assert!(crate::util::max_abs_diff(plain, &base) <= 1e-4 * diag);
                after_out += 1;
            }
        }
        last_a = a;
        last_tick = t.tick;
        if after_out == 5 {
            break;
        }
    }
    assert_eq!(
        after_out, 5,
        "the head faded in, held and faded out (phase {phase})"
    );
    let sent = producer.await.expect("producer");
    assert!(sent >= 10, "{sent} samples");
    server.stop().await;
}

/// Samples with timecodes play by timecode, `delay_ms` behind the producer: a ramp sent at
/// 20 Hz with every pair swapped on the wire shows as a ramp that never goes back, with values
/// between the samples' (interpolated at 30 ticks a second), on a live head without a clip
/// (its base the neutral).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn timecoded_samples_are_reordered_and_interpolated() {
    let server = TestServer::start(ServerConfig::default()).await;
    let rig = crowdmorph::embedded::default_rig();
    let info = create(
        &server,
        json!({"fps": 30, "heads": [
            {"head": 5, "rig": "default-head", "live": {"delay_ms": 200, "fade_ms": 0}}]}),
    )
    .await;
    let mut ws = connect(&server, &info.id, json!({"format": "f32"})).await;
    let jaw = channels(&rig, &["jawOpen"]);
    let mut w = vec![0.0; rig.targets.len()];
    let (neutral, _) = rig_oracle(&rig, &w);
    for &k in &jaw {
        w[k] = 1.0;
    }
    let (open, _) = rig_oracle(&rig, &w);
    let producer = {
        let server_client = server.client.clone();
        let id = info.id.clone();
        tokio::spawn(async move {
            let sample = |k: u32| {
                json!({"head": 5, "weights": {"jawOpen": f64::from(k) * 0.04},
                       "t": 1000.0 + f64::from(k) * 0.05})
            };
            // Pairs sent late-first: (1, 0), (3, 2), ...
            for k in (0..26).step_by(2) {
                for j in [k + 1, k] {
                    let body = json!({ "heads": [sample(j)] });
                    assert_eq!(send_live(&server_client, &id, &body).await, 200);
                }
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
        })
    };
    let mut view = View::default();
    let mut seen: Vec<f64> = Vec::new();
    for _ in 0..200 {
        let t = next_tick(&mut ws).await;
        view.apply(&t);
        let got = view.heads.get(&5).expect("head 5");
        let (a, off) = share(got, &neutral, &open);
        assert!(
            off <= 1e-4 * 0.1 + 1e-5,
            "only the jaw moves (off by {off:e})"
        );
        seen.push(a);
        if a > 0.999 {
            break;
        }
    }
    producer.await.expect("producer");
    assert!(
        *seen.last().expect("ticks") > 0.999,
        "the ramp reached 1: {seen:?}"
    );
    for w in seen.windows(2) {
        assert!(w[1] >= w[0] - 2e-3, "the ramp went back: {seen:?}");
    }
    // Samples are multiples of 0.04; ticks between them show values between.
    let between = seen
        .iter()
        .filter(|a| {
            let r = (*a / 0.04).fract();
            **a > 0.01 && **a < 0.99 && (0.1..0.9).contains(&r)
        })
        .count();
    assert!(between >= 3, "interpolated values shown: {seen:?}");
    server.stop().await;
}

/// Producers that send garbage, flood, stall or pile up: each gets a named answer, and the
/// viewer's ticks keep coming.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_flooding_and_idle_producers_get_named_answers_while_ticks_go_on() {
    let server = TestServer::start(ServerConfig {
        sessions: SessionLimits {
            max_live_rate: 40,
            max_live_producers: 1,
            live_idle_timeout: Duration::from_secs(1),
            ..SessionLimits::default()
        },
        ..ServerConfig::default()
    })
    .await;
    let info = create(
        &server,
        json!({"fps": 30, "heads": [
            {"head": 1, "rig": "default-head", "clip": "talk", "live": {}},
            {"head": 2, "rig": "default-head", "clip": "talk"}]}),
    )
    .await;
    let id = info.id.clone();
    let mut viewer = connect(&server, &id, json!({"format": "q16"})).await;
    let many: serde_json::Map<String, Value> = (0..200_000)
        .map(|i| (format!("n{i}"), json!(0.5)))
        .collect();
    for (body, status, code) in [
        (
            json!({"heads": [{"head": 9, "weights": {"jawOpen": 1}}]}),
            404,
            "unknown_head",
        ),
        (
            json!({"heads": [{"head": 2, "weights": {"jawOpen": 1}}]}),
            400,
            "not_live",
        ),
        (
            json!({"heads": [{"head": 1, "weights": {"jawOpen": 1e39}}]}),
            400,
            "invalid_live",
        ),
        (
            json!({"heads": [{"head": 1, "weights": {"knees": 1}}]}),
            400,
            "unknown_targets",
        ),
        (
            json!({"heads": [{"head": 1, "weights": [0.5, 0.5]}]}),
            400,
            "invalid_live",
        ),
        (
            json!({"heads": [{"head": 1, "weights": many}]}),
            400,
            "invalid_live",
        ),
        (
            json!({"heads": [{"head": 1, "joints": {"Head": {"rotation": [0, 0, 0, 1]}}}]}),
            400,
            "unknown_joints",
        ),
        (json!({"heads": [{"head": 1, "t": "soon"}]}), 400, ""),
    ] {
        let (s, v) = post_live(&server, &id, body).await;
        assert_eq!(s, status, "{v}");
        if !code.is_empty() {
            assert_eq!(v["error"]["code"], code, "{v}");
        }
    }
    let (s, v) = post_live(&server, "nope", json!({"heads": []})).await;
    assert_eq!(
        (s, v["error"]["code"].as_str()),
        (404, Some("unknown_session"))
    );
    // A POST flood past 40 a second: refused with 429 live_rate_exceeded.
    let mut refused = 0;
    for _ in 0..120 {
        let (s, v) = post_live(&server, &id, json!({"heads": [{"head": 1}]})).await;
        if s == 429 {
            assert_eq!(v["error"]["code"], "live_rate_exceeded", "{v}");
            refused += 1;
        }
    }
    assert!(refused > 0, "a flood is refused");
    let ticks_before = next_tick(&mut viewer).await.tick;
    // One producer socket at a time: a second is closed with 1013.
    let url = format!("ws://{}/v1/sessions/{id}/live", server.addr);
    tokio::time::sleep(Duration::from_millis(1100)).await; // the POST flood's second passes
    let (mut p1, _) = tokio_tungstenite::connect_async(&url).await.expect("p1");
    // Bincode with a NaN weight: an error message naming it, the socket kept.
    let nan = crowdmorph_proto::LiveInput {
        heads: vec![crowdmorph_proto::LiveSample {
            head: 1,
            weights: Some(crowdmorph_proto::LiveWeights::Named(vec![(
                "jawOpen".into(),
                f32::NAN,
            )])),
            ..Default::default()
        }],
    };
    p1.send(Message::binary(
        crowdmorph_proto::wire::to_bincode(&nan).expect("bincode"),
    ))
    .await
    .expect("send");
    let answer = tokio::time::timeout(Duration::from_secs(10), p1.next())
        .await
        .expect("an answer")
        .expect("open")
        .expect("message");
    let text = answer.clone().into_text().expect("a text message");
    assert!(!text.is_empty(), "{answer:?}");
    let v: Value = serde_json::from_str(&text).unwrap_or_else(|e| panic!("{e}: {answer:?}"));
    assert_eq!(v["error"]["code"], "invalid_live", "{v}");
    let (mut p2, _) = tokio_tungstenite::connect_async(&url).await.expect("p2");
    let (code, reason) = next_close(&mut p2).await;
    assert_eq!(code, 1013, "{reason}");
    assert!(reason.contains("--max-live-producers"), "{reason}");
    // A socket flood: shed, then closed with 1008 live_rate_exceeded, while ticks go on.
    let flood = json!({"heads": [{"head": 1, "weights": {"jawOpen": 0.5}}]}).to_string();
    let mut sent = 0;
    for _ in 0..10_000 {
        if p1.send(Message::text(flood.clone())).await.is_err() {
            break;
        }
        sent += 1;
    }
    let (code, reason) = next_close(&mut p1).await;
    assert_eq!(code, 1008, "after {sent} messages: {reason}");
    assert!(reason.contains("live_rate_exceeded"), "{reason}");
    let after = next_tick(&mut viewer).await.tick;
    assert!(
        after > ticks_before,
        "ticks went on: {ticks_before} then {after}"
    );
    // A producer that sends nothing is closed once idle, freeing its slot.
    let (mut p3, _) = tokio_tungstenite::connect_async(&url).await.expect("p3");
    let (code, reason) = next_close(&mut p3).await;
    assert_eq!(code, 1001, "{reason}");
    assert!(reason.contains("idle"), "{reason}");
    // The metrics count each kind.
    let page = server.client.metrics().await.expect("metrics");
    for result in ["accepted", "shed", "invalid"] {
        let line = format!("crowdmorph_session_live_messages_total{{result=\"{result}\"}}");
        let n: f64 = page
            .lines()
            .find_map(|l| l.strip_prefix(&line))
            .and_then(|v| v.trim().parse().ok())
            .unwrap_or(0.0);
        assert!(n > 0.0, "{result}: {n}");
    }
    let last = next_tick(&mut viewer).await.tick;
    assert!(last > after, "ticks still go on: {after} then {last}");
    server.stop().await;
}

/// A live head whose settings name a mapping shows its producer's names through it: Live
/// Link's capitalised names through the built-in `a2f` give exactly the vertices of the same
/// weights sent by the rig's own names to a head without one. An unknown mapping is refused
/// when the head is added, and dense weights cannot go through one.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_live_heads_mapping_turns_producer_names_into_targets() {
    let server = TestServer::start(ServerConfig::default()).await;
    let info = create(
        &server,
        json!({"fps": 30, "heads": [
            {"head": 1, "rig": "default-head", "live": {"mapping": "a2f", "fade_ms": 0}},
            {"head": 2, "rig": "default-head", "live": {"fade_ms": 0}}]}),
    )
    .await;
    let id = info.id.clone();
    let (s, v) = post_live(
        &server,
        &id,
        json!({"heads": [
            {"head": 1, "weights": {"JawOpen": 0.7, "MouthSmileLeft": 0.5, "HeadYaw": 0.1}},
            {"head": 2, "weights": {"jawOpen": 0.7, "mouthSmileLeft": 0.5}}]}),
    )
    .await;
    assert_eq!(s, 200, "{v}");
    assert_eq!(v["accepted"], 2);
    let mut ws = connect(&server, &id, json!({"format": "f32"})).await;
    let rig = crowdmorph::embedded::default_rig();
    let (neutral, _) = rig_oracle(&rig, &vec![0.0; rig.targets.len()]);
    let mut view = View::default();
    let mut seen = false;
    for _ in 0..60 {
        let t = next_tick(&mut ws).await;
        view.apply(&t);
        let (a, b) = (view.heads.get(&1), view.heads.get(&2));
        if let (Some(a), Some(b)) = (a, b)
            && crate::util::max_abs_diff(a, &neutral) > 1e-3
        {
            assert_eq!(a, b, "tick {}: the mapped head differs", t.tick);
            seen = true;
            break;
        }
    }
    assert!(seen, "the live heads showed their input");
    let (s, v) = post_live(
        &server,
        &id,
        json!({"heads": [{"head": 1, "weights": vec![0.5; rig.targets.len()]}]}),
    )
    .await;
    assert_eq!(
        (s, v["error"]["code"].as_str()),
        (400, Some("invalid_live")),
        "{v}"
    );
    let (s, v) = call(
        &server,
        Method::PATCH,
        &format!("/v1/sessions/{id}"),
        json!({"add": [{"head": 3, "rig": "default-head", "live": {"mapping": "nope"}}]}),
    )
    .await;
    assert_eq!(
        (s, v["error"]["code"].as_str()),
        (404, Some("unknown_mapping")),
        "{v}"
    );
    assert!(
        v["error"]["message"]
            .as_str()
            .unwrap_or("")
            .contains("head 3"),
        "{v}"
    );
    server.stop().await;
}

/// On a skinned avatar, a live head's joints follow its producer: Live Link Face's `HeadYaw`
/// through the rig's joint map and an explicit node rotation give, at full share, exactly the
/// vertices of a crowd frame asking for the same angle and rotation (the path the skinning
/// oracle checks in `layers.rs` and `joints.rs`), and differ from the neutral.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_skinned_live_heads_joints_follow_angles_and_rotations() {
    let path = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/avatars/valid-white-f-1/White_F_1_Casual.glb");
    let server = TestServer::start(ServerConfig::default()).await;
    let glb = std::fs::read(&path).expect("avatar");
    server
        .client
        .upload_rig("avatar", bytes::Bytes::from(glb))
        .await
        .expect("upload");
    let nodes = server
        .client
        .rig_channels("avatar")
        .await
        .expect("channels")
        .nodes;
    let eye = nodes
        .iter()
        .find(|n| n.to_ascii_lowercase().contains("eye"))
        .expect("an eye node")
        .clone();
    let turn = [0.0, 0.258_819, 0.0, 0.965_926]; // 30° about +Y
    let info = create(
        &server,
        json!({"fps": 30, "heads": [
            {"head": 1, "rig": "avatar", "live": {"fade_ms": 0}},
            {"head": 2, "rig": "avatar"}]}),
    )
    .await;
    let (s, v) = post_live(
        &server,
        &info.id,
        json!({"heads": [{"head": 1, "weights": {"HeadYaw": 0.5},
                          "joints": {eye.clone(): {"rotation": turn}}}]}),
    )
    .await;
    assert_eq!(s, 200, "{v}");
    let want = server
        .client
        .crowd_frame(
            &crowdmorph_proto::CrowdFrameRequest {
                heads: vec![crowdmorph_proto::Head {
                    head: 1,
                    rig: "avatar".into(),
                    weights: Some(Box::new(crowdmorph_proto::LiveWeights::Named(vec![(
                        "HeadYaw".into(),
                        0.5,
                    )]))),
                    joints: crowdmorph_proto::JointOverrides::rotation(&eye, turn),
                    ..Default::default()
                }],
                output: crowdmorph_proto::OutputOptions {
                    format: crowdmorph_proto::Format::F32,
                    ..Default::default()
                },
                wrap: true,
            },
            crowdmorph_client::Encoding::Bincode,
        )
        .await
        .expect("crowd frame")
        .0;
    let want = super::positions_f32(want.format, &want.buffers[0]);
    // Tolerances relative to the avatar's diagonal: the live path slerps to the rotation at
    // full share and normalises it, which may differ from the override in the last bits.
    let (mut lo, mut hi) = ([f32::MAX; 3], [f32::MIN; 3]);
    for p in want.chunks_exact(3) {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    let diag = (0..3).map(|k| (hi[k] - lo[k]).powi(2)).sum::<f32>().sqrt();
    let off = |a: &[f32], b: &[f32]| {
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0f32, f32::max)
    };
    let mut ws = connect(&server, &info.id, json!({"format": "f32"})).await;
    let mut view = View::default();
    let mut best = f32::MAX;
    for _ in 0..60 {
        let t = next_tick(&mut ws).await;
        view.apply(&t);
        let (Some(live), Some(plain)) = (view.heads.get(&1), view.heads.get(&2)) else {
            continue;
        };
        best = best.min(off(live, &want));
        if best <= 1e-5 * diag {
            assert!(off(live, plain) > 1e-3 * diag, "the input moved the head");
            break;
        }
    }
    assert!(
        best <= 1e-5 * diag,
        "the live head shows the crowd frame's pose: off by {best:e} of {diag}"
    );
    server.stop().await;
}

/// Live input is a session write: with an admin token, a POST or a producer socket without it
/// is a 401, and with it the sample is taken.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn live_input_needs_the_admin_token() {
    let mut server = TestServer::start(ServerConfig {
        admin_token: Some("s3cret".into()),
        ..ServerConfig::default()
    })
    .await;
    let open = server.client.clone();
    server.client = server.client.clone().with_token("s3cret");
    let info = create(
        &server,
        json!({"heads": [{"head": 1, "rig": "default-head", "live": {}}]}),
    )
    .await;
    let body = json!({"heads": [{"head": 1, "weights": {"jawOpen": 0.5}}]});
    assert_eq!(send_live(&open, &info.id, &body).await, 401);
    let url = format!("ws://{}/v1/sessions/{}/live", server.addr, info.id);
    match tokio_tungstenite::connect_async(&url).await {
        Err(tokio_tungstenite::tungstenite::Error::Http(r)) => assert_eq!(r.status(), 401),
        other => panic!("a producer without the token: {other:?}"),
    }
    let (s, v) = post_live(&server, &info.id, body).await;
    assert_eq!((s, v["accepted"].as_u64()), (200, Some(1)), "{v}");
    server.stop().await;
}
