//! Liveliness without authoring (issue 47 item 5) in real sessions: clip-less heads show the
//! neutral and stream; heads with equal seeds stay one job per tick; a thousand heads with
//! their own seeds never blink together; a look-at point moves the `eyeLook*` targets by the
//! documented angles (checked against the f64 oracle of the weights written here from the
//! geometry), and turns a skinned avatar's eye and head joints toward it.

use std::collections::HashMap;

use bytes::Bytes;
use crowdmorph::server::ServerConfig;
use crowdmorph_client::Method;
use crowdmorph_proto::{HEAD_MISSING, HEAD_UNCHANGED};
use glam::{DQuat, DVec3};
use serde_json::{Value, json};

use super::TestServer;
use super::layers::loose;
use super::sessions::{View, call, connect, create, info, next_tick};
use crate::util::rig_oracle;

/// The channel of ARKit's `name` in the embedded rig (which spells it `_L`/`_R`).
fn channel(rig: &crowdmorph::rig::Rig, name: &str) -> usize {
    rig.targets
        .iter()
        .position(|t| loose(t) == loose(name))
        .unwrap_or_else(|| panic!("the default head has {name}"))
}

/// How `got` turned about +Y from `rest` over the vertices `range` (x, y, z triples):
/// `Σ (p − c) × (p' − p)`'s Y component, `c` their centroid at rest — positive for a turn that
/// takes +Z toward +X, whatever the centre of the turn.
fn turn_about_y(rest: &[DVec3], got: &[f32], range: std::ops::Range<usize>) -> f64 {
    let c = range.clone().map(|i| rest[i]).sum::<DVec3>() / range.len() as f64;
    range
        .map(|i| {
            let q = DVec3::new(
                got[3 * i].into(),
                got[3 * i + 1].into(),
                got[3 * i + 2].into(),
            );
            (rest[i] - c).cross(q - rest[i]).y
        })
        .sum()
}

/// Where the embedded rig's eyes are, as `proto/README.md` documents it for a rig without eye
/// joints: the centroid of the base positions of the vertices its blink targets move.
fn eye_centre(rig: &crowdmorph::rig::Rig) -> DVec3 {
    let blinks = [channel(rig, "eyeBlinkLeft"), channel(rig, "eyeBlinkRight")];
    let (mut sum, mut n) = (DVec3::ZERO, 0.0);
    for p in rig.primitives.iter() {
        for t in p
            .targets
            .iter()
            .filter(|t| blinks.contains(&(t.target as usize)))
        {
            for &v in &t.vertices {
                sum += p.positions[v as usize].as_dvec3();
                n += 1.0;
            }
        }
    }
    assert!(n > 0.0, "the blink targets move vertices");
    sum / n
}

async fn patch(server: &TestServer, id: &str, body: Value) -> (u16, Value) {
    call(server, Method::PATCH, &format!("/v1/sessions/{id}"), body).await
}

/// A clip-less head (an empty clip plays the neutral) looking at a point to its left, one to
/// its right, and a turned head looking up along its own front: each head's vertices are the
/// oracle's for the weights the documented geometry gives (an angle of 30° is weight 1; toward
/// the character's left, +X, raises `eyeLookOutLeft` and `eyeLookInRight`), and not the
/// mirror's.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn look_at_moves_the_eye_targets_toward_the_point() {
    let server = TestServer::start(ServerConfig::default()).await;
    let rig = crowdmorph::embedded::default_rig();
    let c = eye_centre(&rig);
    let d = 10.0;
    let left = c + DVec3::new(d * 15f64.to_radians().tan(), 0.0, d);
    let right = c + DVec3::new(-d * 15f64.to_radians().tan(), 0.0, d);
    // Head 3 stands at (5, 0, 0) turned 90° (its front is world +X): a point 10° above its
    // eyes, straight ahead of it.
    let turn = DQuat::from_rotation_y(90f64.to_radians());
    let at3 = DVec3::new(5.0, 0.0, 0.0);
    let up = at3 + turn * (c + DVec3::new(0.0, d * 10f64.to_radians().tan(), d));
    let alive = |p: DVec3| json!({"look_at": [p.x, p.y, p.z]});
    let s = create(
        &server,
        json!({"fps": 30, "heads": [
            {"head": 1, "rig": "default-head", "alive": alive(left)},
            {"head": 2, "rig": "default-head", "alive": alive(right)},
            {"head": 3, "rig": "default-head", "position": [5, 0, 0], "yaw": 90,
             "alive": alive(up)},
            {"head": 4, "rig": "default-head"}]}),
    )
    .await;
    assert!(s.heads.iter().all(|h| h.clip.is_empty()));
    let mut ws = connect(&server, &s.id, json!({"format": "f32"})).await;
    let mut view = View::default();
    let t = next_tick(&mut ws).await;
    view.apply(&t);
    let n = rig.targets.len();
    let weights = |pairs: &[(&str, f64)]| {
        let mut w = vec![0.0; n];
        for (name, v) in pairs {
            w[channel(&rig, name)] = *v;
        }
        w
    };
    let b = rig.bbox();
    let diag = f64::from((b.max - b.min).length());
    let to_left = weights(&[("eyeLookOutLeft", 0.5), ("eyeLookInRight", 0.5)]);
    let to_right = weights(&[("eyeLookInLeft", 0.5), ("eyeLookOutRight", 0.5)]);
    let upward = weights(&[("eyeLookUpLeft", 1.0 / 3.0), ("eyeLookUpRight", 1.0 / 3.0)]);
    let neutral = vec![0.0; n];
    for (head, want, not) in [
        (1, &to_left, &to_right),
        (2, &to_right, &to_left),
        (3, &upward, &neutral),
        (4, &neutral, &to_left),
    ] {
        let got = view.heads.get(&head).expect("every head is shown");
        let (pos, _) = rig_oracle(&rig, want);
        let off = crate::util::max_abs_diff(got, &pos);
        assert!(off <= 1e-4 * diag, "head {head}: off by {off:e} of {diag}");
        let (other, _) = rig_oracle(&rig, not);
        let apart = crate::util::max_abs_diff(got, &other);
        assert!(
            apart > 1e-3 * diag,
            "head {head}: as the other side, {apart:e}"
        );
    }
    // Read from the geometry alone: the left eyeball turned toward +X (the point), the other
    // way for the point on the right.
    let at = rig.vertex_offsets();
    let eye = rig
        .primitives
        .iter()
        .position(|p| p.name == "eye_L")
        .expect("an eye_L primitive");
    let eye = at[eye]..at[eye] + rig.primitives[eye].positions.len();
    let (rest, _) = rig_oracle(&rig, &neutral);
    let l = turn_about_y(&rest, view.heads.get(&1).expect("head 1"), eye.clone());
    let r = turn_about_y(&rest, view.heads.get(&2).expect("head 2"), eye);
    assert!(l > 0.0 && r < 0.0, "left {l:e}, right {r:e}");
    // The session's point moved by a patch (its default, for heads without their own): a head
    // with no `alive` of its own follows it; the answer shows it.
    let (status, v) = patch(
        &server,
        &s.id,
        json!({"alive": {"look_at": [left.x, left.y, left.z]}}),
    )
    .await;
    assert_eq!(status, 200, "{v}");
    assert_eq!(
        v["alive"]["look_at"][0].as_f64().map(|x| x as f32),
        Some(left.x as f32)
    );
    let (pos, _) = rig_oracle(&rig, &to_left);
    let mut followed = false;
    for _ in 0..30 {
        let t = next_tick(&mut ws).await;
        view.apply(&t);
        let got = view.heads.get(&4).expect("head 4");
        if crate::util::max_abs_diff(got, &pos) <= 1e-4 * diag {
            followed = true;
            break;
        }
    }
    assert!(followed, "head 4 looks at the session's point");
    // A head's own `alive` with everything off keeps it out of the session's.
    let (status, v) = patch(
        &server,
        &s.id,
        json!({"change": [{"head": 4, "alive": {}}]}),
    )
    .await;
    assert_eq!(status, 200, "{v}");
    let mut stopped = false;
    for _ in 0..30 {
        let t = next_tick(&mut ws).await;
        view.apply(&t);
        if crate::util::max_abs_diff(view.heads.get(&4).expect("head 4"), &rest) <= 1e-4 * diag {
            stopped = true;
            break;
        }
    }
    assert!(stopped, "head 4 is back at the neutral");
    server.stop().await;
}

/// Heads that are clones but for where they stand, with one explicit seed, blinking, darting
/// their eyes and breathing: one job per tick. The same heads with the seeds their ids give
/// are many jobs a tick, and they move (not the neutral).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn equal_seeds_keep_clones_one_job_per_tick() {
    let server = TestServer::start(ServerConfig::default()).await;
    let heads = |seed: Option<u64>| -> Vec<Value> {
        (0..40)
            .map(|i| {
                let mut alive = json!({"blink": true, "saccades": true, "breathing": true});
                if let Some(s) = seed {
                    alive["seed"] = json!(s);
                }
                json!({"head": i, "rig": "default-head", "clip": "",
                       "position": [i as f32, 0.0, 0.0], "alive": alive})
            })
            .collect()
    };
    let rig = crowdmorph::embedded::default_rig();
    let (rest, _) = rig_oracle(&rig, &vec![0.0; rig.targets.len()]);
    let b = rig.bbox();
    let diag = f64::from((b.max - b.min).length());
    let mut per_tick = Vec::new();
    for seed in [Some(7), None] {
        let s = create(&server, json!({"fps": 30, "heads": heads(seed)})).await;
        let mut ws = connect(&server, &s.id, json!({"format": "f32"})).await;
        let mut view = View::default();
        let mut moved = 0;
        for _ in 0..20 {
            let t = next_tick(&mut ws).await;
            view.apply(&t);
            if crate::util::max_abs_diff(view.heads.get(&0).expect("head 0"), &rest) > 1e-4 * diag {
                moved += 1;
            }
        }
        drop(ws);
        assert!(
            moved >= 10,
            "seed {seed:?}: alive heads move ({moved} of 20 ticks)"
        );
        let i = info(&server, &s.id).await;
        assert!(i.stats.ticks >= 20, "{:?}", i.stats);
        per_tick.push(i.stats.jobs as f64 / i.stats.ticks as f64);
    }
    assert_eq!(per_tick[0], 1.0, "equal seeds: one job a tick");
    assert!(per_tick[1] > 20.0, "own seeds: {} jobs a tick", per_tick[1]);
    server.stop().await;
}

/// A thousand heads with the session's blinks and the seeds their ids give: at no tick do
/// they all blink, only a small fraction does (a blink is about 5 % of the time), and some do.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_thousand_heads_never_blink_in_unison() {
    let server = TestServer::start(ServerConfig::default()).await;
    let mut heads: Vec<Value> = (0..1000u64)
        .map(|i| {
            json!({"head": i, "rig": "default-head",
                   "position": [(i % 40) as f32, 0.0, (i / 40) as f32]})
        })
        .collect();
    // The neutral's buffer, for comparison: a head whose own `alive` is off.
    heads.push(json!({"head": 1000, "rig": "default-head", "alive": {}}));
    let s = create(
        &server,
        json!({"fps": 30, "heads": heads, "alive": {"blink": true}}),
    )
    .await;
    let mut ws = connect(&server, &s.id, json!({})).await;
    // Per head: whether its last buffer is not the neutral's.
    let mut blinking: HashMap<u64, bool> = HashMap::new();
    let mut neutral: Option<Vec<u8>> = None;
    let (mut most, mut seen) = (0usize, 0usize);
    for _ in 0..60 {
        let t = next_tick(&mut ws).await;
        let layout = t.layout.as_ref();
        if let Some(l) = layout {
            assert_eq!(l.len(), 1001);
        }
        let reference = t
            .heads
            .iter()
            .find(|h| h.head == 1000)
            .expect("head 1000 listed");
        if !matches!(reference.buffer, HEAD_UNCHANGED | HEAD_MISSING) {
            neutral = Some(t.buffers[reference.buffer as usize].positions.0.clone());
        }
        let neutral = neutral.as_ref().expect("the neutral's buffer came first");
        for h in &t.heads {
            match h.buffer {
                HEAD_UNCHANGED => {}
                HEAD_MISSING => panic!("head {} missing", h.head),
                b => {
                    blinking.insert(h.head, t.buffers[b as usize].positions.0 != *neutral);
                }
            }
        }
        let now = blinking.values().filter(|&&b| b).count();
        most = most.max(now);
        seen += now;
    }
    assert!(most < 150, "{most} of 1,000 heads blinking at one tick");
    assert!(seen > 0, "someone blinked in two seconds");
    server.stop().await;
}

/// A skinned avatar with no clips at all (VALID's, as uploaded): in a session it shows its
/// neutral, and a look-at point to its left turns its eye (and head) joints left, one to its
/// right turns them right — the sign of the rotation read from the vertices themselves:
/// `Σ (p − c) × (p' − p)` over the vertices has a +Y component for a turn toward +X.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_clip_less_avatars_eye_joints_turn_toward_the_point() {
    let path = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/avatars/valid-white-f-1/White_F_1_Casual.glb");
    let server = TestServer::start(ServerConfig::default()).await;
    let glb = std::fs::read(&path).expect("avatar");
    let rig = server
        .client
        .upload_rig("avatar", Bytes::from(glb))
        .await
        .expect("upload");
    assert!(rig.clips.is_empty(), "the avatar arrives with no clip");
    let (lo, hi) = (rig.bbox.min, rig.bbox.max);
    let top = f64::from(hi[1]);
    let eye = DVec3::new(0.0, top - 0.1 * f64::from(hi[1] - lo[1]), 0.0);
    let point = |x: f64| eye + DVec3::new(x, 0.0, 1.0);
    let s = create(
        &server,
        json!({"fps": 30, "heads": [
            {"head": 1, "rig": "avatar"},
            {"head": 2, "rig": "avatar", "alive": {"look_at": point(0.8).to_array()}},
            {"head": 3, "rig": "avatar", "alive": {"look_at": point(-0.8).to_array()}}]}),
    )
    .await;
    // A non-empty clip the rig lacks is still a 404 naming it.
    let (status, v) = patch(
        &server,
        &s.id,
        json!({"add": [{"head": 9, "rig": "avatar", "clip": "wave"}]}),
    )
    .await;
    assert_eq!(
        (status, v["error"]["code"].as_str()),
        (404, Some("unknown_clip")),
        "{v}"
    );
    let mut ws = connect(&server, &s.id, json!({"format": "f32"})).await;
    let mut view = View::default();
    view.apply(&next_tick(&mut ws).await);
    let rest = view.heads.get(&1).expect("the neutral streams").clone();
    assert!(rest.iter().all(|v| v.is_finite()));
    let turn = |head: u64| -> f64 {
        let got = view.heads.get(&head).expect("head");
        let p: Vec<DVec3> = rest
            .chunks_exact(3)
            .map(|v| DVec3::new(v[0].into(), v[1].into(), v[2].into()))
            .collect();
        let q: Vec<DVec3> = got
            .chunks_exact(3)
            .map(|v| DVec3::new(v[0].into(), v[1].into(), v[2].into()))
            .collect();
        let moved: Vec<usize> = (0..p.len())
            .filter(|&i| p[i].distance(q[i]) > 1e-6)
            .collect();
        assert!(!moved.is_empty(), "head {head}: the look-at moved vertices");
        let c = moved.iter().map(|&i| p[i]).sum::<DVec3>() / moved.len() as f64;
        moved.iter().map(|&i| (p[i] - c).cross(q[i] - p[i]).y).sum()
    };
    let (l, r) = (turn(2), turn(3));
    assert!(l > 0.0 && r < 0.0, "left {l:e}, right {r:e}");
    // Equal and opposite angles, up to the skeleton's own asymmetry.
    assert!((l + r).abs() < 0.5 * l.abs(), "left {l:e}, right {r:e}");
    server.stop().await;
}

/// Hostile `alive` objects are named 4xx: a look-at point past the coordinates a placement
/// may have, unknown fields.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_alive_is_a_named_400() {
    let server = TestServer::start(ServerConfig::default()).await;
    for (body, code) in [
        (
            json!({"heads": [{"head": 1, "rig": "default-head",
                              "alive": {"look_at": [1e30, 0, 0]}}]}),
            "invalid_alive",
        ),
        (
            json!({"heads": [], "alive": {"look_at": [0, -2e6, 0]}}),
            "invalid_alive",
        ),
    ] {
        let (status, v) = call(&server, Method::POST, "/v1/sessions", body).await;
        assert_eq!(status, 400, "{v}");
        assert_eq!(v["error"]["code"], code, "{v}");
        assert!(
            v["error"]["message"]
                .as_str()
                .unwrap_or("")
                .contains("look_at"),
            "{v}"
        );
    }
    let (status, v) = call(
        &server,
        Method::POST,
        "/v1/sessions",
        json!({"heads": [{"head": 1, "rig": "default-head", "alive": {"wink": true}}]}),
    )
    .await;
    assert_eq!(status, 400, "{v}");
    let s = create(&server, json!({"heads": []})).await;
    let (status, v) = patch(&server, &s.id, json!({"alive": {"look_at": [0, 0, 1e9]}})).await;
    assert_eq!(
        (status, v["error"]["code"].as_str()),
        (400, Some("invalid_alive")),
        "{v}"
    );
    assert!(
        info(&server, &s.id).await.alive.is_none(),
        "nothing changed"
    );
    server.stop().await;
}
