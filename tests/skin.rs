//! Skinned rigs: RobotExpressive (CC0; 4 skins of 43 joints, rigid meshes under its joints,
//! 14 node-animated clips) evaluated by the engines against the independent f64 evaluator in
//! `util::skin`, with tolerances relative to the rig's diagonal; blends; the q16 box.

use std::path::PathBuf;

use crowdmorph::engine::cpu::CpuRig;
use crowdmorph::engine::{BlendJob, BlendOutput, OutputSpec, Precision, WeightBatch};
use crowdmorph::import::{ImportOptions, load_path};
use crowdmorph::rig::{Pose, Rig};
use glam::DVec3;

use crate::util::RefDoc;
use crate::util::skin::Posed;

fn robot_path() -> PathBuf {
    crate::util::data_dir().join("robot-expressive/RobotExpressive.glb")
}

fn robot() -> (Rig, RefDoc) {
    let path = robot_path();
    let rig = load_path(&path, &ImportOptions::default())
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    (rig, RefDoc::load(&path))
}

fn evaluate(rig: &Rig, jobs: &[BlendJob]) -> BlendOutput {
    let batch = WeightBatch::gather(rig, jobs).expect("batch");
    let spec = OutputSpec {
        normals: true,
        precision: Precision::F32,
    };
    CpuRig::new(rig).evaluate(&batch, spec).expect("evaluate")
}

/// Largest position and normal distance of job `j` of `out` from the reference pose.
fn distance(out: &BlendOutput, j: usize, want: &[Posed]) -> (f64, f64) {
    let p = out.job_positions(j);
    let n = out.job_normals(j).expect("normals");
    let (mut dp, mut dn) = (0f64, 0f64);
    let mut v = 0;
    for prim in want {
        for (k, w) in prim.positions.iter().enumerate() {
            let g = DVec3::new(
                f64::from(p[3 * v]),
                f64::from(p[3 * v + 1]),
                f64::from(p[3 * v + 2]),
            );
            dp = dp.max((g - *w).length());
            if let Some(wn) = &prim.normals {
                let gn = DVec3::new(
                    f64::from(n[3 * v]),
                    f64::from(n[3 * v + 1]),
                    f64::from(n[3 * v + 2]),
                );
                dn = dn.max((gn - wn[k]).length());
            }
            v += 1;
        }
    }
    assert_eq!(v * 3, p.len(), "the reference has every vertex");
    (dp, dn)
}

#[test]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
fn robot_clips_match_the_independent_evaluator_at_several_frames() {
    let (rig, doc) = robot();
    assert!(rig.is_skinned(), "RobotExpressive follows its skeleton");
    let diag = f64::from(rig.bbox().diagonal());
    let rest = doc.pose(&doc.rest_locals());
    assert_eq!(
        rest.len(),
        rig.primitives.len(),
        "one posed instance per primitive"
    );
    let mut moved = 0f64;
    for (ci, clip) in rig.clips.iter().enumerate() {
        assert!(clip.joints.is_some(), "{}: node animation baked", clip.name);
        let frames = [0, clip.frames / 3, clip.frames / 2 + 1, clip.frames - 1];
        let jobs: Vec<BlendJob> = frames
            .iter()
            .map(|&f| BlendJob::frame(ci as u32, f, 0))
            .collect();
        let out = evaluate(&rig, &jobs);
        for (j, &f) in frames.iter().enumerate() {
            let t = f64::from(f) / f64::from(clip.fps);
            let want = doc.pose(&doc.locals_at(&clip.name, t));
            let (dp, dn) = distance(&out, j, &want);
            assert!(
                dp <= 1e-5 * diag,
                "{} frame {f}: position off by {dp:e} (diagonal {diag})",
                clip.name
            );
            assert!(dn <= 1e-4, "{} frame {f}: normal off by {dn:e}", clip.name);
            // How far the clip moves a vertex from rest: the pose is not the bind pose.
            let (from_rest, _) = distance(&out, j, &rest);
            moved = moved.max(from_rest);
        }
    }
    assert!(
        moved > 0.1 * diag,
        "the clips move the robot (largest move {moved}, diagonal {diag})"
    );
}

#[test]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
fn a_blend_of_two_clips_nlerps_their_joints() {
    let (rig, doc) = robot();
    let wave = rig.clip_index("Wave").expect("Wave") as u32;
    let run = rig.clip_index("Running").expect("Running") as u32;
    let job = BlendJob {
        pose: Pose::blend((wave, 20), &[(run, 9, 0.375)]),
        lod: 0,
    };
    let out = evaluate(&rig, &[job]);
    let fps = f64::from(rig.clips[wave as usize].fps);
    let terms = vec![
        (0.625, doc.locals_at("Wave", 20.0 / fps)),
        (0.375, doc.locals_at("Running", 9.0 / fps)),
    ];
    let want = doc.pose(&RefDoc::blend_locals(&terms));
    let diag = f64::from(rig.bbox().diagonal());
    let (dp, dn) = distance(&out, 0, &want);
    assert!(dp <= 1e-5 * diag, "blend: position off by {dp:e}");
    assert!(dn <= 1e-4, "blend: normal off by {dn:e}");
    // Neither clip alone is the blend.
    for (name, f) in [("Wave", 20.0), ("Running", 9.0)] {
        let alone = doc.pose(&doc.locals_at(name, f / fps));
        let (d, _) = distance(&out, 0, &alone);
        assert!(d > 1e-3 * diag, "the blend differs from {name} alone ({d})");
    }
}

#[test]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
fn the_q16_box_holds_every_frame_and_blend_of_a_skinned_rig() {
    let (rig, _) = robot();
    let q = crowdmorph::server::registry::quantization_box(&rig);
    let mut jobs: Vec<BlendJob> = Vec::new();
    for (ci, c) in rig.clips.iter().enumerate() {
        for f in (0..c.frames).step_by(4) {
            jobs.push(BlendJob::frame(ci as u32, f, 0));
            let other = (ci + 5) % rig.clips.len();
            let g = f % rig.clips[other].frames;
            jobs.push(BlendJob {
                pose: Pose::blend((ci as u32, f), &[(other as u32, g, 0.5)]),
                lod: 0,
            });
        }
    }
    let out = evaluate(&rig, &jobs);
    let p = out.positions.to_f32();
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for (i, &x) in p.iter().enumerate() {
        let a = i % 3;
        let top = q.min[a] + q.step[a] * 65535.0;
        assert!(
            x >= q.min[a] && x <= top,
            "component {a} = {x} outside [{}, {top}]",
            q.min[a]
        );
        lo[a] = lo[a].min(x);
        hi[a] = hi[a].max(x);
    }
    // The box is a bound, not a guess: say how much of its range the poses use.
    for a in 0..3 {
        let used = f64::from(hi[a] - lo[a]) / (f64::from(q.step[a]) * 65535.0);
        eprintln!("axis {a}: poses use {:.0} % of the q16 box", used * 100.0);
        assert!(
            used > 0.2,
            "axis {a}: the box is not absurdly loose ({used})"
        );
    }
}

#[test]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
fn clones_share_joint_matrices_and_batches_do_not_mix_poses() {
    // A batch of the same frame many times, in a mixed batch, equals that frame alone: the
    // bones of one job never leak into another's vertices.
    let (rig, _) = robot();
    let wave = rig.clip_index("Wave").expect("Wave") as u32;
    let alone = evaluate(&rig, &[BlendJob::frame(wave, 30, 0)]);
    let mut jobs = Vec::new();
    for k in 0..24 {
        jobs.push(BlendJob::frame(wave, 30, 0));
        jobs.push(BlendJob::frame(
            (k % rig.clips.len()) as u32,
            k as u32 % 13,
            0,
        ));
    }
    let mixed = evaluate(&rig, &jobs);
    for j in (0..jobs.len()).step_by(2) {
        assert_eq!(mixed.job_positions(j), alone.job_positions(0), "job {j}");
        assert_eq!(mixed.job_normals(j), alone.job_normals(0), "job {j}");
    }
}

#[test]
#[cfg_attr(
    not(all(crowdmorph_test_data, crowdmorph_gpu_driver)),
    ignore = "needs ../shared/data and a Vulkan adapter (apt-get install mesa-vulkan-drivers)"
)]
fn the_gpu_backend_evaluates_a_skinned_rig_on_the_cpu_engine_and_says_so() {
    use crowdmorph::engine::gpu::GpuOptions;
    use crowdmorph::engine::{BackendChoice, BackendKind, Engine};
    // The WGSL skin pass is not written: a skinned rig is not uploaded, and its jobs are
    // computed by the CPU engine, which answers exactly as it does alone.
    let engine = Engine::with_gpu(
        crate::util::open_gpu(GpuOptions::default()),
        BackendChoice::Gpu,
    );
    let (rig, _) = robot();
    let wave = rig.clip_index("Wave").expect("Wave") as u32;
    let jobs: Vec<BlendJob> = (0..8).map(|f| BlendJob::frame(wave, f * 7, 0)).collect();
    let prepared = engine
        .prepare(std::sync::Arc::new(rig.clone()))
        .expect("prepare");
    assert_eq!(prepared.memory().device_bytes, 0, "nothing uploaded");
    let spec = OutputSpec {
        normals: true,
        precision: Precision::F32,
    };
    let mut out = BlendOutput::default();
    let (_, kind) = engine
        .evaluate_into(&prepared, &jobs, spec, &mut out)
        .expect("evaluate");
    assert_eq!(
        kind,
        BackendKind::Cpu,
        "the answer names the engine that computed it"
    );
    let want = evaluate(&rig, &jobs);
    for j in 0..jobs.len() {
        assert_eq!(out.job_positions(j), want.job_positions(j), "job {j}");
    }
}
