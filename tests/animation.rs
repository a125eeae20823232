//! Blends and live weights in the engines (GPU Gems 3 ch. 15: blending in weight space is
//! blending the meshes), against an f64 evaluation of the blended weights that does not use the
//! library's `Pose::weight`.
//!
//! Tolerances (relative to the rig's bounding-box diagonal `d`): positions 1e-5·d, as for plain
//! frames. The fractions used are multiples of 1/16, which the 1/4096 quantization keeps
//! exactly; live weights add their stated quantization bound, 2^-13 × Σₖ maxᵥ‖Δₖ(v)‖.

use std::sync::Arc;

use crowdmorph::engine::{BlendJob, Engine, OutputSpec, WeightBatch};
use crowdmorph::import::{ImportOptions, load_path};
use crowdmorph::rig::{LIVE_STEP, Pose, Rig};
use glam::DVec3;

use crate::util::{Rng, effective_weights, pose_positions, rig_files, rig_oracle};

/// Largest distance between a buffer and oracle positions.
fn max_dist(got: &[f32], want: &[DVec3]) -> f64 {
    got.chunks_exact(3)
        .zip(want)
        .map(|(g, w)| (DVec3::new(f64::from(g[0]), f64::from(g[1]), f64::from(g[2])) - *w).length())
        .fold(0.0, f64::max)
}

/// A blend as `Pose::blend` takes it: the base (clip, frame) and the layers (clip, frame, t).
type Blend = ((u32, u32), Vec<(u32, u32, f32)>);

/// Random blends of `rig`: a base frame and 1–4 layers with fractions in sixteenths.
fn random_blends(rig: &Rig, seed: u64, n: usize) -> Vec<Blend> {
    let mut rng = Rng(seed);
    let frame = |rng: &mut Rng| {
        let c = rng.below(rig.clips.len());
        (c as u32, rng.below(rig.clips[c].frames as usize) as u32)
    };
    (0..n)
        .map(|_| {
            let base = frame(&mut rng);
            let mut left = 16;
            let layers = (0..1 + rng.below(4))
                .map(|_| {
                    let k = rng.below(left / 2 + 1);
                    left -= k;
                    let (c, f) = frame(&mut rng);
                    (c, f, k as f32 / 16.0)
                })
                .collect();
            (base, layers)
        })
        .collect()
}

/// The blend's weights per channel in f64, from the clip tables directly.
fn blend_weights(rig: &Rig, base: (u32, u32), layers: &[(u32, u32, f32)]) -> Vec<f64> {
    let at = |c: u32, f: u32, t: usize| f64::from(rig.clips[c as usize].weight(t, f));
    let rest = 1.0 - layers.iter().map(|l| f64::from(l.2)).sum::<f64>();
    (0..rig.targets.len())
        .map(|t| {
            rest * at(base.0, base.1, t)
                + layers
                    .iter()
                    .map(|&(c, f, x)| f64::from(x) * at(c, f, t))
                    .sum::<f64>()
        })
        .collect()
}

fn rigs() -> Vec<Rig> {
    let mut rigs = vec![crowdmorph::embedded::default_rig()];
    if cfg!(crowdmorph_test_data) {
        for f in rig_files() {
            let rig = load_path(&f, &ImportOptions::default()).expect("load");
            if !rig.clips.is_empty() {
                rigs.push(rig);
            }
        }
    }
    rigs
}

#[test]
fn blends_match_the_f64_blend_of_their_frames() {
    for rig in rigs() {
        let diag = f64::from(rig.bbox().diagonal());
        let blends = random_blends(&rig, 7, 24);
        let jobs: Vec<BlendJob> = blends
            .iter()
            .map(|(base, layers)| BlendJob {
                pose: Pose::blend(*base, layers),
                lod: 0,
                joints: Default::default(),
            })
            .collect();
        let engine = Engine::cpu();
        let prepared = engine.prepare(Arc::new(rig.clone())).expect("prepare");
        let out = engine
            .evaluate(&prepared, &jobs, OutputSpec::default())
            .expect("evaluate");
        for (j, (base, layers)) in blends.iter().enumerate() {
            let w = effective_weights(&rig, &blend_weights(&rig, *base, layers), 0);
            let (want, _) = rig_oracle(&rig, &w);
            let d = max_dist(&out.output.job_positions(j), &want);
            assert!(
                d <= 1e-5 * diag,
                "{} blend {j} {base:?} {layers:?}: {d:e} from the oracle (diag {diag})",
                rig.name
            );
        }
    }
}

#[test]
fn a_frame_blended_with_itself_and_the_endpoints_are_the_frames() {
    let rig = crowdmorph::embedded::default_rig();
    let talk = rig.clip_index("talk").unwrap() as u32;
    let smile = rig.clip_index("smile").unwrap() as u32;
    let engine = Engine::cpu();
    let prepared = engine.prepare(Arc::new(rig.clone())).expect("prepare");
    let eval = |pose: Pose| pose_positions(&engine, &prepared, pose);
    let a = eval(Pose::Frame {
        clip: talk,
        frame: 40,
    });
    let b = eval(Pose::Frame {
        clip: smile,
        frame: 3,
    });
    assert_ne!(a, b, "the two frames differ");
    assert_eq!(eval(Pose::blend((talk, 40), &[(talk, 40, 0.3)])), a);
    assert_eq!(eval(Pose::blend((talk, 40), &[(smile, 3, 0.0)])), a);
    assert_eq!(eval(Pose::blend((talk, 40), &[(smile, 3, 1.0)])), b);
    // Halfway is the midpoint of the meshes (Eq. 1 is linear in the weights).
    let mid = eval(Pose::blend((talk, 40), &[(smile, 3, 0.5)]));
    let diag = rig.bbox().diagonal();
    for ((m, x), y) in mid.iter().zip(&a).zip(&b) {
        assert!((m - (x + y) / 2.0).abs() <= 1e-5 * diag);
    }
}

#[test]
fn live_weights_equal_the_clip_frame_that_has_them() {
    for rig in rigs() {
        let diag = f64::from(rig.bbox().diagonal());
        // What quantizing every weight by at most LIVE_STEP / 2 can move a vertex.
        let bound: f64 = f64::from(LIVE_STEP) / 2.0
            * rig
                .primitives
                .iter()
                .flat_map(|p| p.targets.iter())
                .map(|t| {
                    t.positions
                        .iter()
                        .map(|d| f64::from(d.length()))
                        .fold(0.0, f64::max)
                })
                .sum::<f64>();
        let engine = Engine::cpu();
        let prepared = engine.prepare(Arc::new(rig.clone())).expect("prepare");
        let mut rng = Rng(11);
        for _ in 0..6 {
            let c = rng.below(rig.clips.len());
            let f = rng.below(rig.clips[c].frames as usize) as u32;
            let mut w = vec![0.0; rig.targets.len()];
            rig.clips[c].frame_weights(f, &mut w);
            let frame = BlendJob::frame(c as u32, f, 0);
            let live = BlendJob::posed(Pose::live(&w), 0);
            let out = engine
                .evaluate(&prepared, &[frame, live], OutputSpec::default())
                .expect("evaluate");
            let want: Vec<DVec3> = out
                .output
                .job_positions(0)
                .chunks_exact(3)
                .map(|p| DVec3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2])))
                .collect();
            let d = max_dist(&out.output.job_positions(1), &want);
            assert!(
                d <= bound + 1e-5 * diag,
                "{} clip {c} frame {f}: live weights are {d:e} from the frame (bound {bound:e})",
                rig.name
            );
        }
    }
}

#[test]
fn blends_gather_the_same_weights_in_any_order() {
    let rig = crowdmorph::embedded::default_rig();
    let a = Pose::blend((0, 10), &[(1, 5, 0.25), (2, 7, 0.125)]);
    let b = Pose::blend((0, 10), &[(2, 7, 0.125 + 1e-7), (1, 5, 0.25 - 1e-7)]);
    assert_eq!(a, b);
    let batch =
        WeightBatch::gather(&rig, &[BlendJob::posed(a, 0), BlendJob::posed(b, 0)]).expect("gather");
    assert_eq!(batch.job(0), batch.job(1));
    assert!(batch.active_pairs() > 0);
}

/// Every node of `g` reaches every other along its edges.
fn strongly_connected(g: &crowdmorph_proto::MotionGraph) -> bool {
    let names: Vec<&str> = g.nodes.iter().map(|n| n.name.as_str()).collect();
    let idx = |n: &str| names.iter().position(|x| *x == n).unwrap();
    let reach = |forward: bool| {
        let mut seen = vec![false; names.len()];
        let mut todo = vec![0usize];
        seen[0] = true;
        while let Some(n) = todo.pop() {
            for e in &g.edges {
                let (a, b) = (idx(&e.from), idx(&e.to));
                let (a, b) = if forward { (a, b) } else { (b, a) };
                if a == n && !seen[b] {
                    seen[b] = true;
                    todo.push(b);
                }
            }
        }
        seen.into_iter().all(|s| s)
    };
    reach(true) && reach(false)
}

#[test]
fn graphs_built_from_clips_check_are_strongly_connected_and_cost_under_the_threshold() {
    let mut rigs = vec![crowdmorph::embedded::default_rig()];
    if cfg!(crowdmorph_test_data) {
        let path =
            crate::util::data_dir().join("khronos/MorphStressTest/glTF/MorphStressTest.gltf");
        rigs.push(load_path(&path, &ImportOptions::default()).expect("MorphStressTest"));
    }
    for rig in rigs {
        let opt = crowdmorph::graph::BuildOptions::default();
        let built = crowdmorph::graph::build(&rig, opt, &crowdmorph::cancel::Cancel::never())
            .expect("never cancelled")
            .expect("a graph");
        let g = &built.graph;
        eprintln!(
            "{}: {} candidates, {} nodes, {} edges, {} dropped",
            rig.name,
            built.candidates,
            g.nodes.len(),
            g.edges.len(),
            built.dropped_nodes
        );
        crowdmorph::graph::Graph::resolve(g, &rig, |n| rig.clip_index(n))
            .expect("the built graph checks");
        assert!(g.nodes.len() > 1 && strongly_connected(g), "{}", rig.name);
        assert_eq!(built.costs.len(), g.edges.len());
        assert!(built.costs.iter().all(|&c| c <= opt.threshold));
        let clips: std::collections::HashSet<&str> =
            g.nodes.iter().map(|n| n.clip.as_str()).collect();
        assert!(
            clips.len() >= 2,
            "{}: transitions join clips: {clips:?}",
            rig.name
        );
        // A transition's cost is what it says: the mean RMS vertex distance, over the fade,
        // between the frames it blends (checked on one, through the CPU engine).
        let engine = Engine::cpu();
        let prepared = engine.prepare(Arc::new(rig.clone())).expect("prepare");
        let diag = f64::from(rig.bbox().diagonal());
        let (e, cost) = g
            .edges
            .iter()
            .zip(&built.costs)
            .filter(|(e, _)| e.fade > 1)
            .max_by(|a, b| a.1.total_cmp(b.1))
            .expect("a transition");
        eprintln!("{}: checking {e:?}, cost {cost}", rig.name);
        let node = |name: &str| g.nodes.iter().find(|n| n.name == name).unwrap();
        let (from, to) = (node(&e.from), node(&e.to));
        let (fc, tc) = (
            rig.clip_index(&from.clip).unwrap() as u32,
            rig.clip_index(&to.clip).unwrap() as u32,
        );
        let i = from.frames.unwrap()[0] + e.window.unwrap()[0];
        let j = to.frames.unwrap()[0];
        let mut sum = 0.0;
        for k in 0..e.fade {
            let a = pose_positions(
                &engine,
                &prepared,
                Pose::Frame {
                    clip: fc,
                    frame: i + k,
                },
            );
            let b = pose_positions(
                &engine,
                &prepared,
                Pose::Frame {
                    clip: tc,
                    frame: j + k,
                },
            );
            let ms: f64 = a
                .chunks_exact(3)
                .zip(b.chunks_exact(3))
                .map(|(p, q)| (0..3).map(|c| f64::from(p[c] - q[c]).powi(2)).sum::<f64>())
                .sum::<f64>()
                / rig.vertex_count() as f64;
            sum += ms.sqrt();
        }
        let measured = sum / f64::from(e.fade) / diag;
        assert!(
            (measured - f64::from(*cost)).abs() <= 1e-4 + 1e-3 * measured,
            "{}: edge {e:?} costs {cost}, measured {measured}",
            rig.name
        );
    }
}

#[test]
fn compressed_clips_stay_within_their_vertex_budget_on_every_rig_with_clips() {
    for rig in rigs() {
        for clip in &rig.clips {
            for budget in [3e-4f32, 1e-3] {
                let c = crowdmorph::compress::compress(&rig, clip, budget).expect("compresses");
                let table = crowdmorph::compress::decode(&c).expect("decodes");
                let r = crowdmorph::compress::measure(&rig, clip, &table, budget);
                assert!(
                    r.max <= f64::from(budget) && r.under_budget == 1.0,
                    "{} {}: {r:?}",
                    rig.name,
                    clip.name
                );
                assert!(c.bytes() < c.f32_bytes(), "{} {}", rig.name, clip.name);
            }
        }
    }
}
