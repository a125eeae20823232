//! Near-clones (issue 48): a crowd head's `tolerance` lets the server round its weights so
//! that heads whose poses differ by less share one job. Every rounded head comes back within
//! `tolerance × diagonal` of the f64 oracle of its exact pose (Euclidean, per vertex); no
//! tolerance, or 0, is exactly today's plan; a large one cuts the unique jobs; bad ones are a
//! named 400.

use crowdmorph::server::ServerConfig;
use crowdmorph_client::Encoding;
use crowdmorph_proto::{BlendLayer, CrowdFrameRequest, CrowdFrameResponse, Head, OutputOptions};

use super::TestServer;
use super::layers::frame_weights;
use crate::util::{effective_weights, rig_oracle};

/// Slack for the engine's own f32 arithmetic against the f64 oracle (the exact heads are
/// within it too: checked below), as a fraction of the diagonal.
const ENGINE_SLACK: f64 = 1e-6;

/// 90 frames of `talk` at LOD 0 and 2, every third blended with `smile` at 0.3, each with
/// `tolerance`; and the exact f64 weights of each.
fn crowd(tolerance: Option<f32>) -> (Vec<Head>, Vec<Vec<f64>>) {
    let rig = crowdmorph::embedded::default_rig();
    let frames = |name: &str| rig.clips[rig.clip_index(name).expect("clip")].frames;
    let (talk_frames, smile_frames) = (frames("talk"), frames("smile"));
    let mut heads = Vec::new();
    let mut weights = Vec::new();
    for lod in [0u32, 2] {
        for frame in 0..90u32 {
            let id = u64::from(lod * 1000 + frame);
            let mut head = Head {
                lod,
                tolerance,
                ..Head::playing(id, "default-head", "talk", i64::from(frame))
            };
            let talk = frame_weights(&rig, "talk", frame % talk_frames);
            let w = if frame % 3 == 0 {
                let s = frame % smile_frames;
                head.blend = vec![BlendLayer {
                    clip: "smile".into(),
                    frame: i64::from(s),
                    t: 0.3,
                }];
                // The blend as the server quantizes it: 0.3 in 1/4096ths.
                let t = (0.3f64 * 4096.0).round() / 4096.0;
                let smile = frame_weights(&rig, "smile", s);
                talk.iter()
                    .zip(&smile)
                    .map(|(a, b)| (1.0 - t) * a + t * b)
                    .collect()
            } else {
                talk
            };
            heads.push(head);
            weights.push(w);
        }
    }
    (heads, weights)
}

async fn frame(server: &TestServer, heads: Vec<Head>) -> CrowdFrameResponse {
    let req = CrowdFrameRequest {
        heads,
        output: OutputOptions::default(),
        wrap: true,
    };
    server
        .client
        .crowd_frame(&req, Encoding::Bincode)
        .await
        .expect("frame")
        .0
}

/// Per head, the largest Euclidean distance of its served vertices from the oracle of its
/// exact pose at its level, as a fraction of the diagonal.
fn errors(resp: &CrowdFrameResponse, heads: &[Head], weights: &[Vec<f64>]) -> Vec<f64> {
    let rig = crowdmorph::embedded::default_rig();
    let diag = f64::from(rig.bbox().diagonal());
    heads
        .iter()
        .zip(weights)
        .enumerate()
        .map(|(i, (h, w))| {
            assert_eq!(resp.heads[i].head, h.head);
            let (want, _) = rig_oracle(&rig, &effective_weights(&rig, w, h.lod));
            let b = &resp.buffers[resp.heads[i].buffer as usize];
            super::max_distance(&super::positions_f32(resp.format, b), &want) / diag
        })
        .collect()
}

#[tokio::test]
async fn near_clones_stay_within_their_tolerance_of_the_exact_pose() {
    let server = TestServer::start(ServerConfig::default()).await;
    let (heads, weights) = crowd(None);
    let exact = frame(&server, heads.clone()).await;
    let exact_err = errors(&exact, &heads, &weights);
    let worst_exact = exact_err.iter().copied().fold(0.0, f64::max);
    assert!(
        worst_exact <= ENGINE_SLACK,
        "exact heads off by {worst_exact:e}"
    );

    // Tolerance 0: today's plan, bit for bit.
    let (zero_heads, _) = crowd(Some(0.0));
    let zero = frame(&server, zero_heads).await;
    assert_eq!(zero.heads, exact.heads);
    assert_eq!(zero.buffers, exact.buffers);

    let mut jobs = vec![exact.buffers.len()];
    for e in [1e-4f32, 1e-3, 1e-2, 5e-2] {
        let (near_heads, _) = crowd(Some(e));
        let near = frame(&server, near_heads.clone()).await;
        let err = errors(&near, &near_heads, &weights);
        let worst = err.iter().copied().fold(0.0, f64::max);
        let moved = err.iter().filter(|&&d| d > 2.0 * ENGINE_SLACK).count();
        eprintln!(
            "tolerance {e:e}: {} unique jobs for {} heads (exact: {}), worst error {worst:.3e} \
             diagonals, {moved} heads moved",
            near.buffers.len(),
            near_heads.len(),
            exact.buffers.len()
        );
        for (h, d) in near_heads.iter().zip(&err) {
            assert!(
                *d <= f64::from(e) + ENGINE_SLACK,
                "tolerance {e}: head {} (lod {}) off by {d:e} diagonals",
                h.head,
                h.lod
            );
        }
        jobs.push(near.buffers.len());
        if e >= 1e-2 {
            assert!(moved > 0, "tolerance {e}: no head was rounded");
        }
    }
    // The largest tolerance needs far fewer jobs. (Not monotone in general: two weights that
    // round to one fine step may straddle a coarse step's midpoint.)
    assert!(
        jobs[jobs.len() - 1] * 2 <= jobs[0],
        "tolerance 0.05 cut the jobs only from {} to {}",
        jobs[0],
        jobs[jobs.len() - 1]
    );
    server.stop().await;
}

#[tokio::test]
async fn bad_tolerances_are_named_400s() {
    let server = TestServer::start(ServerConfig::default()).await;
    for bad in [-1e-3f32, 0.2, f32::NAN, f32::INFINITY] {
        let req = CrowdFrameRequest {
            heads: vec![
                Head::playing(1, "default-head", "talk", 0),
                Head {
                    tolerance: Some(bad),
                    ..Head::playing(7, "default-head", "talk", 1)
                },
            ],
            output: OutputOptions::default(),
            wrap: true,
        };
        let message = super::api_error(
            server.client.crowd_frame(&req, Encoding::Bincode).await,
            400,
            "invalid_tolerance",
        );
        assert!(message.contains("head 1 (id 7)"), "{message}");
    }
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_session_viewers_near_clones_stay_within_their_distance_tolerance() {
    use super::sessions::{View, connect, create, head, next_tick};
    use serde_json::json;

    let server = TestServer::start(ServerConfig::default()).await;
    let rig = crowdmorph::embedded::default_rig();
    let diag = f64::from(rig.bbox().diagonal());
    let talk = &rig.clips[rig.clip_index("talk").expect("talk")];
    // 40 heads of talk at their own offsets, 1 m apart in depth, and 20 exact clones of the
    // first 20 half a metre behind them.
    let mut heads = Vec::new();
    let mut at: Vec<(u64, i64, [f32; 3])> = Vec::new();
    for i in 0..60u64 {
        let (offset, z) = if i < 40 {
            (i as i64, -(i as f32))
        } else {
            ((i - 40) as i64, -((i - 40) as f32) - 0.5)
        };
        let p = [0.0, 0.0, z];
        heads.push(head(i, "talk", offset, p));
        at.push((i, offset, p));
    }
    let s = create(&server, json!({"heads": heads})).await;
    let eye = [0.0f32, 0.0, 3.0];
    let per_metre = 2e-4f32;
    let hello = |tolerance: Option<f32>| {
        let mut h = json!({"format": "f32",
            "camera": {"position": eye, "target": [0, 0, -10]},
            "lod": {"by_distance": [[0, 0], [10, 1], [25, 2]]}});
        if let Some(t) = tolerance {
            h["tolerance"] = json!(t);
        }
        h
    };
    let mut exact_ws = connect(&server, &s.id, hello(None)).await;
    let mut near_ws = connect(&server, &s.id, hello(Some(per_metre))).await;
    let (mut exact, mut near) = (View::default(), View::default());
    let (mut te, mut tn) = (
        next_tick(&mut exact_ws).await,
        next_tick(&mut near_ws).await,
    );
    // The first message of each carries every head's job once: fewer for near-clones.
    let (exact_jobs, near_jobs) = (te.buffers.len(), tn.buffers.len());
    let mut compared = 0;
    let mut rounded = 0;
    let mut worst_ratio = 0f64;
    while compared < 5 {
        while te.tick < tn.tick {
            exact.apply(&te);
            te = next_tick(&mut exact_ws).await;
        }
        while tn.tick < te.tick {
            near.apply(&tn);
            tn = next_tick(&mut near_ws).await;
        }
        if te.tick != tn.tick {
            continue;
        }
        exact.apply(&te);
        near.apply(&tn);
        let tick = te.tick;
        for &(id, offset, p) in &at {
            // The exact pose: talk at offset + tick − 1 (30 fps clip, 30 ticks/s), wrapped.
            let frame = (offset + tick as i64 - 1).rem_euclid(i64::from(talk.frames)) as u32;
            let lod = near.lods[&id];
            assert_eq!(
                lod, exact.lods[&id],
                "head {id}: both viewers see one level"
            );
            let w = frame_weights(&rig, "talk", frame);
            let (want, _) = rig_oracle(&rig, &effective_weights(&rig, &w, lod));
            let d = glam::Vec3::from(p).distance(glam::Vec3::from(eye));
            let allowed = (f64::from(per_metre) * f64::from(d)).min(0.1);
            let err = super::max_distance(&near.heads[&id], &want) / diag;
            let exact_err = super::max_distance(&exact.heads[&id], &want) / diag;
            assert!(
                exact_err <= ENGINE_SLACK,
                "head {id}: exact off by {exact_err:e}"
            );
            assert!(
                err <= allowed + ENGINE_SLACK,
                "tick {tick} head {id} at {d} m: off by {err:e} diagonals, allowed {allowed:e}"
            );
            if err > 2.0 * ENGINE_SLACK {
                rounded += 1;
                worst_ratio = worst_ratio.max(err / allowed);
            }
        }
        compared += 1;
        te = next_tick(&mut exact_ws).await;
        tn = next_tick(&mut near_ws).await;
    }
    eprintln!(
        "session near-clones: {near_jobs} jobs for the near viewer, {exact_jobs} exact; \
         {rounded} rounded head buffers over 5 ticks, worst error / allowance {worst_ratio:.3}"
    );
    assert!(rounded > 0, "no head was rounded");
    assert!(
        near_jobs < exact_jobs,
        "near-clones: {near_jobs} jobs, exact: {exact_jobs}"
    );
    server.stop().await;
}
