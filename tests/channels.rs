//! glTF's per-node animation rule: files with several nodes whose meshes share target names,
//! built in code, against an independent evaluator written here — each node's `weights`
//! channel sampled per the glTF 2.0 spec (Appendix C) in f64, nodes no channel animates held at
//! `node.weights`, else `mesh.weights`, else 0, and each node blended with its own weights.
//!
//! The files: a head mesh (targets `jaw`, `blink`) on node 0 and a teeth mesh with the same
//! target names on nodes 1 and 2 (a mesh instanced twice, the second copy moved aside).
//! Node 1 has `node.weights`; node 2 falls back to the teeth's `mesh.weights`. Tolerance:
//! positions within 1e-5 × the bounding-box diagonal (f32 blending of f32-baked weights).

use std::sync::Arc;

use crowdmorph::engine::{BlendJob, Engine, OutputSpec};
use crowdmorph::import::clips::ClipOptions;
use crowdmorph::import::gltf::rig_from_slice;
use crowdmorph::import::{ImportOptions, clip_from_csv, clips_from_gltf};
use crowdmorph::lod::{LodSpec, OrderMethod, build_lod};
use crowdmorph::rig::Rig;
use glam::DVec3;

use crate::util::builder::Builder;
use crate::util::{RefDoc, ref_eval};

/// Baking rate of the test clips: keys at 0, 0.5 and 1 s land on frames and between them.
pub const FPS: f32 = 8.0;

/// A 3 × 3 grid of vertices in the z = 0 plane, `size` wide, at `x0`, with its 8 triangles.
fn grid(x0: f32, size: f32) -> (Vec<[f32; 3]>, Vec<u32>) {
    let mut p = Vec::new();
    for j in 0..3 {
        for i in 0..3 {
            p.push([x0 + size * i as f32 / 2.0, size * j as f32 / 2.0, 0.0]);
        }
    }
    let mut idx = Vec::new();
    for j in 0..2u32 {
        for i in 0..2u32 {
            let a = j * 3 + i;
            idx.extend_from_slice(&[a, a + 1, a + 4, a, a + 4, a + 3]);
        }
    }
    (p, idx)
}

/// `jaw` moves the bottom row down and forward; `blink` moves the top row in z, with a
/// different shape per mesh so that every node's weights show in its vertices.
fn targets(scale: f32) -> Vec<Vec<[f32; 3]>> {
    let jaw = (0..9)
        .map(|v| {
            if v < 3 {
                [0.1 * scale * v as f32, -0.8 * scale, 0.3 * scale]
            } else {
                [0.0; 3]
            }
        })
        .collect();
    let blink = (0..9)
        .map(|v| {
            if v >= 6 {
                [0.0, 0.05 * scale, -0.6 * scale]
            } else if v >= 3 {
                [0.0, 0.0, -0.1 * scale]
            } else {
                [0.0; 3]
            }
        })
        .collect();
    vec![jaw, blink]
}

/// How the test file animates and defaults its nodes.
#[derive(Clone, Copy, Debug)]
pub enum Case {
    /// One animation that drives only the head (node 0) with this interpolation.
    HeadOnly(&'static str),
    /// One animation with different curves on the head (LINEAR) and teeth node 1
    /// (CUBICSPLINE); node 2 keeps its defaults.
    Different,
    /// Every node driven by the same curve (each through its own sampler and accessors) and
    /// the same defaults: the usual face-capture export.
    Shared,
}

/// Key times and values (width 2: `jaw`, `blink`) of the head's curve for `interpolation`.
fn head_curve(interpolation: &str) -> (Vec<f32>, Vec<f32>) {
    let times = vec![0.0, 0.5, 1.0];
    let values = match interpolation {
        "CUBICSPLINE" => vec![
            // key 0: in-tangents, values, out-tangents
            0.0, 0.0, 0.1, 0.9, 2.0, -1.0, //
            // key 1
            1.5, 0.5, 0.8, 0.2, -0.5, 1.0, //
            // key 2
            0.3, 0.3, 0.25, 0.7, 0.0, 0.0,
        ],
        _ => vec![0.1, 0.9, 0.8, 0.2, 0.25, 0.7],
    };
    (times, values)
}

/// The test file for `case`, as a GLB.
pub fn file(case: Case) -> Vec<u8> {
    let mut b = Builder::new();
    let (hp, hi) = grid(0.0, 2.0);
    let head = b.mesh_with_targets(&hp, Some(&hi), &targets(1.0), Some(&["jaw", "blink"]));
    let (tp, ti) = grid(0.5, 1.0);
    let teeth = b.mesh_with_targets(&tp, Some(&ti), &targets(0.5), Some(&["jaw", "blink"]));
    let n0 = b.node(Some(head));
    let n1 = b.node(Some(teeth));
    let n2 = b.node(Some(teeth));
    b.json_mut()["nodes"][n2]["translation"] = serde_json::json!([3.0, 0.0, 0.0]);
    b.scene(&[n0, n1, n2]);
    match case {
        Case::HeadOnly(interp) => {
            b.set_mesh_weights(head, &[0.05, 0.0]);
            b.set_mesh_weights(teeth, &[0.3, 0.1]);
            b.set_node_weights(n1, &[0.6, 0.2]);
            let (t, v) = head_curve(interp);
            b.animation_weights("talk", n0, &t, &v, interp);
        }
        Case::Different => {
            b.set_mesh_weights(teeth, &[0.3, 0.1]);
            b.set_node_weights(n0, &[0.5, 0.5]);
            let (t0, v0) = head_curve("LINEAR");
            let (t1, v1) = head_curve("CUBICSPLINE");
            b.animation_weights_nodes(
                "talk",
                &[(n0, &t0, &v0, "LINEAR"), (n1, &t1, &v1, "CUBICSPLINE")],
            );
        }
        Case::Shared => {
            b.set_mesh_weights(head, &[0.2, 0.0]);
            b.set_mesh_weights(teeth, &[0.2, 0.0]);
            let (t, v) = head_curve("STEP");
            b.animation_weights_nodes(
                "talk",
                &[
                    (n0, &t, &v, "STEP"),
                    (n1, &t, &v, "STEP"),
                    (n2, &t, &v, "STEP"),
                ],
            );
        }
    }
    b.to_glb()
}

/// Imports a test file with clips baked at [`FPS`].
pub fn import(bytes: &[u8]) -> Rig {
    rig_from_slice(
        bytes,
        &ImportOptions {
            fps: FPS,
            name: Some("two-nodes".into()),
            ..ImportOptions::default()
        },
    )
    .expect("the test file imports")
}

/// The independent evaluation: every primitive instance of the scene at time `t` of the
/// animation `anim`, each node with its own sampled (or default) weights, in f64.
pub fn reference(doc: &RefDoc, anim: &str, t: f64) -> Vec<DVec3> {
    let animations = doc.weight_animations();
    let channels = &animations
        .iter()
        .find(|(n, _)| n == anim)
        .expect("animation in the file")
        .1;
    let mut out = Vec::new();
    for prim in doc.scene_primitives() {
        let width = prim.targets.len();
        let w = match channels.iter().find(|c| c.node == prim.node) {
            Some(c) => c.sample(t, width),
            None => prim.default_weights.clone(),
        };
        out.extend(ref_eval(&prim, &w).0);
    }
    out
}

/// Largest distance between an engine buffer and reference positions.
fn max_dist(got: &[f32], want: &[DVec3]) -> f64 {
    assert_eq!(got.len(), want.len() * 3);
    got.chunks_exact(3)
        .zip(want)
        .map(|(g, w)| (DVec3::new(f64::from(g[0]), f64::from(g[1]), f64::from(g[2])) - *w).length())
        .fold(0.0, f64::max)
}

/// Every frame of `clip` on `engine` (LOD 0), one buffer per frame.
pub fn frames(engine: &Engine, rig: &Rig, clip: &str) -> Vec<Vec<f32>> {
    let ci = rig.clip_index(clip).expect("clip");
    let prepared = engine
        .prepare(Arc::new(rig.clone()))
        .expect("prepare the rig");
    let jobs: Vec<BlendJob> = (0..rig.clips[ci].frames)
        .map(|f| BlendJob::frame(ci as u32, f, 0))
        .collect();
    let evaluation = engine
        .evaluate(&prepared, &jobs, OutputSpec::default())
        .expect("evaluate");
    assert_eq!(
        evaluation.kind,
        Some(engine.info().kind),
        "computed on the engine's own backend"
    );
    let out = evaluation.output;
    (0..jobs.len()).map(|j| out.job_positions(j)).collect()
}

/// Checks every frame of the file's `talk` clip, evaluated on `engine`, against the
/// independent evaluator; returns the largest error relative to the bounding-box diagonal.
pub fn check_against_reference(engine: &Engine, case: Case) -> f64 {
    let bytes = file(case);
    let rig = import(&bytes);
    let doc = RefDoc::from_bytes(&bytes, std::path::Path::new("."));
    let diag = f64::from(rig.bbox().diagonal());
    let mut worst = 0.0f64;
    for (f, got) in frames(engine, &rig, "talk").iter().enumerate() {
        let want = reference(&doc, "talk", f as f64 / f64::from(FPS));
        let d = max_dist(got, &want) / diag;
        assert!(
            d <= 1e-5,
            "{case:?} frame {f}: off by {d:e} of the diagonal on {:?}",
            engine.info().kind
        );
        worst = worst.max(d);
    }
    worst
}

#[test]
fn one_animated_node_leaves_the_others_at_their_default_weights() {
    for interp in ["LINEAR", "STEP", "CUBICSPLINE"] {
        check_against_reference(&Engine::cpu(), Case::HeadOnly(interp));
        let rig = import(&file(Case::HeadOnly(interp)));
        // Head, teeth with node weights, teeth with mesh weights: three behaviours per name.
        assert_eq!(rig.split_targets(), vec![("jaw", 3), ("blink", 3)]);
        assert_eq!(rig.target_names(), vec!["jaw", "blink"]);
        // The first channel of each name comes first, as a plain name mapping orders them.
        assert_eq!(&rig.targets[..2], ["jaw", "blink"]);
        let jaw: Vec<f32> = rig
            .target_ids("jaw")
            .iter()
            .map(|&c| rig.default_weights[c as usize])
            .collect();
        assert_eq!(
            jaw,
            [0.05, 0.6, 0.3],
            "head mesh, node 1 node.weights, node 2 mesh.weights"
        );
    }
}

#[test]
fn differently_animated_nodes_each_play_their_own_curve() {
    check_against_reference(&Engine::cpu(), Case::Different);
    let rig = import(&file(Case::Different));
    assert_eq!(rig.split_targets(), vec![("jaw", 3), ("blink", 3)]);
}

#[test]
fn nodes_that_share_curves_share_channels_and_cost_nothing_more() {
    check_against_reference(&Engine::cpu(), Case::Shared);
    let rig = import(&file(Case::Shared));
    // One channel per name: the rig (and every clone and batch of it) is what the plain
    // name mapping made.
    assert_eq!(rig.targets, ["jaw", "blink"]);
    assert!(rig.split_targets().is_empty());
    assert_eq!(rig.clips[0].targets, 2);
}

#[test]
fn the_test_files_tell_the_two_rules_apart() {
    // Driving every node that has a name with the animated node's curve (the rule before
    // per-node channels) moves the other nodes: the reference must see that, or the tests
    // above could not fail.
    for case in [
        Case::HeadOnly("CUBICSPLINE"),
        Case::HeadOnly("STEP"),
        Case::Different,
    ] {
        let bytes = file(case);
        let doc = RefDoc::from_bytes(&bytes, std::path::Path::new("."));
        let prims = doc.scene_primitives();
        let animations = doc.weight_animations();
        let head = &animations[0].1[0];
        let mut worst = 0.0f64;
        let mut diag_min = DVec3::splat(f64::INFINITY);
        let mut diag_max = DVec3::splat(f64::NEG_INFINITY);
        for f in 0..=8 {
            let t = f64::from(f) / f64::from(FPS);
            let right = reference(&doc, "talk", t);
            let mut by_name = Vec::new();
            for p in &prims {
                by_name.extend(ref_eval(p, &head.sample(t, 2)).0);
            }
            for (a, b) in right.iter().zip(&by_name) {
                worst = worst.max((*a - *b).length());
                diag_min = diag_min.min(*a);
                diag_max = diag_max.max(*a);
            }
        }
        let rel = worst / (diag_max - diag_min).length();
        assert!(
            rel > 0.01,
            "{case:?}: the rules differ by only {rel:e} of the diagonal"
        );
    }
}

#[test]
fn eval_writes_what_the_reference_evaluates() {
    let bytes = file(Case::HeadOnly("CUBICSPLINE"));
    let rig = import(&bytes);
    let doc = RefDoc::from_bytes(&bytes, std::path::Path::new("."));
    let dir = std::env::temp_dir().join(format!("crowdmorph-channels-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let out = dir.join("frame.bin");
    crowdmorph::export::eval_to_file(&rig, "talk", 3, 0, crowdmorph::rig::FrameMode::Strict, &out)
        .unwrap();
    let raw = std::fs::read(&out).unwrap();
    let got: Vec<f32> = raw
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    let want = reference(&doc, "talk", 3.0 / f64::from(FPS));
    let d = max_dist(&got, &want) / f64::from(rig.bbox().diagonal());
    assert!(d <= 1e-5, "eval .bin off by {d:e}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn clips_by_name_drive_every_channel_of_the_name() {
    // A CSV column names a target: every node that has it moves (the ARKit / Live Link rule).
    let rig = import(&file(Case::HeadOnly("LINEAR")));
    let csv = "jaw\n0.25\n0.75\n";
    let clip = clip_from_csv(&rig, "capture", csv.as_bytes(), &ClipOptions::default())
        .unwrap()
        .clip;
    for &c in &rig.target_ids("jaw") {
        assert_eq!(
            [clip.weight(c as usize, 0), clip.weight(c as usize, 1)],
            [0.25, 0.75]
        );
    }
    // Names it does not mention hold each channel's own default.
    for &c in &rig.target_ids("blink") {
        assert_eq!(clip.weight(c as usize, 1), rig.default_weights[c as usize]);
    }
}

#[test]
fn gltf_clips_of_the_same_export_play_per_node_and_conflicts_are_named() {
    let rig = import(&file(Case::HeadOnly("LINEAR")));
    // The same file's animation, added again as a clip: it plays exactly as the rig's own.
    let again = clips_from_gltf(
        &rig,
        &file(Case::HeadOnly("LINEAR")),
        &ClipOptions {
            fps: FPS,
            ..ClipOptions::default()
        },
    )
    .unwrap();
    assert_eq!(again[0].clip.weights, rig.clips[0].weights);
    // A rig whose nodes share channels cannot play an animation that moves them apart.
    let shared = import(&file(Case::Shared));
    let err = clips_from_gltf(
        &shared,
        &file(Case::HeadOnly("LINEAR")),
        &ClipOptions {
            fps: FPS,
            ..ClipOptions::default()
        },
    );
    // The head-only file has other default weights but the same primitives: its animation
    // moves node 0 only, which the shared rig drives with the teeth's channels.
    let message = err.unwrap_err().to_string();
    assert!(
        message.contains("nodes 0 and 1") && message.contains("one weight channel"),
        "{message}"
    );
}

#[test]
fn lod_pins_by_name_take_every_channel_and_labels_name_one() {
    let rig = import(&file(Case::HeadOnly("STEP")));
    let spec = LodSpec {
        method: OrderMethod::FileOrder,
        pinned: vec!["blink".into()],
        ..LodSpec::default()
    };
    let lod = build_lod(&rig, &spec, None, None).unwrap();
    let blink = rig.target_ids("blink");
    assert_eq!(
        &lod.order[..3],
        &blink[..],
        "every blink channel pinned first"
    );
    assert_eq!(lod.pinned, blink);
    // A channel label names a single channel; an explicit order may mix names and labels.
    let one = LodSpec {
        order: Some(vec![
            "jaw#2".into(),
            "blink".into(),
            "jaw#1".into(),
            "jaw#3".into(),
        ]),
        ..LodSpec::default()
    };
    let lod = build_lod(&rig, &one, None, None).unwrap();
    let jaw = rig.target_ids("jaw");
    assert_eq!(lod.order[0], jaw[1]);
    assert_eq!(&lod.order[1..4], &blink[..]);
    assert_eq!(rig.channel_label(jaw[1]), "jaw#2");
    // A name listed twice (or a label and its name) is refused.
    let twice = LodSpec {
        pinned: vec!["jaw".into(), "jaw#1".into()],
        ..LodSpec::default()
    };
    assert!(build_lod(&rig, &twice, None, None).is_err());

    // A LOD level that keeps only the blink channels evaluates as the reference does with
    // every jaw weight at zero, on every node.
    let mut rig = rig;
    rig.lod = build_lod(
        &rig,
        &LodSpec {
            method: OrderMethod::FileOrder,
            pinned: vec!["blink".into()],
            levels: Some(vec![
                crowdmorph::lod::LevelSpec {
                    shapes: Some(6),
                    ..Default::default()
                },
                crowdmorph::lod::LevelSpec {
                    shapes: Some(3),
                    ..Default::default()
                },
            ]),
            ..LodSpec::default()
        },
        None,
        None,
    )
    .unwrap();
    let bytes = file(Case::HeadOnly("STEP"));
    let doc = RefDoc::from_bytes(&bytes, std::path::Path::new("."));
    let engine = Engine::cpu();
    let prepared = engine.prepare(Arc::new(rig.clone())).unwrap();
    let out = engine
        .evaluate(
            &prepared,
            &[BlendJob::frame(0, 5, 1)],
            OutputSpec::default(),
        )
        .unwrap()
        .output;
    let animations = doc.weight_animations();
    let mut want = Vec::new();
    for p in doc.scene_primitives() {
        let mut w = match animations[0].1.iter().find(|c| c.node == p.node) {
            Some(c) => c.sample(5.0 / f64::from(FPS), 2),
            None => p.default_weights.clone(),
        };
        w[0] = 0.0; // jaw is past the level's shapes
        want.extend(ref_eval(&p, &w).0);
    }
    let d = max_dist(&out.job_positions(0), &want) / f64::from(rig.bbox().diagonal());
    assert!(d <= 1e-5, "LOD level 1 off by {d:e}");
}

#[test]
fn split_channel_rigs_survive_the_store() {
    // Channels are a target list with repeated names: the record format is unchanged, so
    // records written before per-node channels load as they did, and new ones round-trip.
    use crowdmorph::store::{Record, RecordRef, Store};
    let rig = import(&file(Case::Different));
    let dir =
        std::env::temp_dir().join(format!("crowdmorph-channels-store-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let store = Store::open(&dir).unwrap();
    store
        .put(RecordRef::Rig {
            id: "split",
            rig: &rig,
            clips: &rig.clips,
        })
        .unwrap();
    let loaded = store.load_all().unwrap();
    match &loaded.records[..] {
        [Record::Rig(r)] => assert_eq!(r.rig, rig),
        other => panic!("unexpected records {other:?}"),
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_server_frames_each_node_with_its_own_weights_and_says_which_names_split() {
    use crowdmorph::server::ServerConfig;
    use crowdmorph_client::Encoding;
    use crowdmorph_proto::{CrowdFrameRequest, Format, Head, LodRequest, OutputOptions};

    let server = crate::server::TestServer::start(ServerConfig::default()).await;
    let c = &server.client;
    let bytes = file(Case::HeadOnly("CUBICSPLINE"));
    let info = c
        .upload_rig("split", bytes::Bytes::from(bytes.clone()))
        .await
        .unwrap();
    // The API lists each name once and says which have several channels.
    assert_eq!(info.targets, ["jaw", "blink"]);
    let split: Vec<(String, u32)> = info
        .split_targets
        .iter()
        .map(|s| (s.name.clone(), s.channels))
        .collect();
    assert_eq!(split, [("jaw".to_string(), 3), ("blink".to_string(), 3)]);
    assert_eq!(info.lod.order.len(), 6, "one LOD slot per channel");
    assert!(
        info.lod.order.contains(&"jaw#3".to_string()),
        "{:?}",
        info.lod.order
    );

    let doc = RefDoc::from_bytes(&bytes, std::path::Path::new("."));
    let rig = import(&bytes);
    let diag = f64::from(rig.bbox().diagonal());
    let req = CrowdFrameRequest {
        heads: (0..9)
            .map(|f| Head {
                head: f,
                rig: "split".into(),
                clip: "talk".into(),
                frame: f as i64,
                lod: 0,
                ..Default::default()
            })
            .collect(),
        output: OutputOptions {
            normals: false,
            format: Format::F32,
        },
        wrap: false,
    };
    // The server bakes at its own rate (30 fps); frame f is t = f / 30.
    let (resp, _) = c.crowd_frame(&req, Encoding::Bincode).await.unwrap();
    for h in &resp.heads {
        let b = &resp.buffers[h.buffer as usize];
        let want = reference(&doc, "talk", f64::from(b.frame) / 30.0);
        let got = crate::server::positions_f32(Format::F32, b);
        let d = max_dist(&got, &want) / diag;
        assert!(d <= 1e-5, "frame {}: off by {d:e}", b.frame);
    }

    // Pins by name take every channel; the order reads back as channel labels, which a
    // client can send again as an explicit order.
    let set = c
        .set_lod(
            "split",
            &LodRequest {
                method: Some("file-order".into()),
                pinned: vec!["blink".into()],
                ..LodRequest::default()
            },
        )
        .await
        .unwrap();
    assert_eq!(set.lod.pinned, ["blink#1", "blink#2", "blink#3"]);
    let again = c
        .set_lod(
            "split",
            &LodRequest {
                order: Some(set.lod.order.clone()),
                ..LodRequest::default()
            },
        )
        .await
        .unwrap();
    assert_eq!(again.lod.order, set.lod.order);
    server.stop().await;
}
