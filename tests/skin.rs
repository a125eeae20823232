//! Skinned rigs: RobotExpressive (CC0; 4 skins of 43 joints, rigid meshes under its joints,
//! 14 node-animated clips) evaluated by the engines against the independent f64 evaluator in
//! `util::skin`, with tolerances relative to the rig's diagonal; blends; the q16 box.

use crate::util::gpu_test;
use std::path::PathBuf;

use crowdmorph::engine::cpu::CpuRig;
use crowdmorph::engine::{BlendJob, BlendOutput, OutputSpec, Precision, WeightBatch};
use crowdmorph::import::{ImportOptions, load_path};
use crowdmorph::rig::{JointPose, JointSet, Pose, Rig};
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
    let job = BlendJob::posed(Pose::blend((wave, 20), &[(run, 9, 0.375)]), 0);
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
            jobs.push(BlendJob::posed(
                Pose::blend((ci as u32, f), &[(other as u32, g, 0.5)]),
                0,
            ));
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

/// Jobs of `rig` with joint overrides: `(node name, rotation)` pairs set on a clip frame.
fn with_joints(rig: &Rig, job: BlendJob, sets: &[(&str, glam::Quat)]) -> BlendJob {
    let sk = rig.skeleton.as_ref().expect("skinned");
    let node = |name: &str| {
        sk.nodes
            .iter()
            .position(|n| n.name == name)
            .unwrap_or_else(|| panic!("no node {name}")) as u32
    };
    BlendJob {
        joints: JointPose::new(
            sets.iter()
                .map(|&(n, q)| JointSet::new(node(n), None, Some(q.to_array()), None))
                .collect(),
        ),
        ..job
    }
}

/// The GPU engine (lavapipe) against the CPU engine on `jobs` of `rig`, in f32 with normals
/// and in q16: positions within 1e-5 of the diagonal, normals within 1e-3, and the device's
/// q16 the scalar encoding of its own f32 bit for bit; the answer says the GPU computed it.
/// Returns the GPU's f32 output (with normals).
fn gpu_agrees_with_cpu(rig: &Rig, jobs: &[BlendJob]) -> BlendOutput {
    use crowdmorph::engine::gpu::GpuOptions;
    use crowdmorph::engine::{BackendChoice, BackendKind, Engine};
    let engine = Engine::with_gpu(
        crate::util::open_gpu(GpuOptions::default()),
        BackendChoice::Gpu,
    );
    let prepared = engine
        .prepare(std::sync::Arc::new(rig.clone()))
        .expect("prepare");
    assert!(
        prepared.memory().device_bytes > 0,
        "the skinned rig is resident on the device"
    );
    let f32_spec = OutputSpec {
        normals: true,
        precision: Precision::F32,
    };
    let mut gpu = BlendOutput::default();
    let (_, kind) = engine
        .evaluate_into(&prepared, jobs, f32_spec, &mut gpu)
        .expect("evaluate");
    assert_eq!(kind, BackendKind::Gpu, "the skin pass runs on the device");
    let cpu = evaluate(rig, jobs);
    let diag = rig.bbox().diagonal();
    for j in 0..jobs.len() {
        let dp = gpu
            .job_positions(j)
            .iter()
            .zip(cpu.job_positions(j))
            .map(|(a, b)| (a - b).abs())
            .fold(0f32, f32::max);
        assert!(dp <= 1e-5 * diag, "job {j}: GPU position off by {dp:e}");
        let dn = gpu
            .job_normals(j)
            .expect("normals")
            .iter()
            .zip(cpu.job_normals(j).expect("normals"))
            .map(|(a, b)| (a - b).abs())
            .fold(0f32, f32::max);
        assert!(dn <= 1e-3, "job {j}: GPU normal off by {dn:e}");
    }
    let qbox = crowdmorph::server::registry::quantization_box(rig);
    let q16 = OutputSpec {
        normals: false,
        precision: Precision::Q16(qbox),
    };
    let mut packed = BlendOutput::default();
    engine
        .evaluate_into(&prepared, jobs, q16, &mut packed)
        .expect("q16");
    let mut plain = BlendOutput::default();
    let f32_only = OutputSpec {
        normals: false,
        precision: Precision::F32,
    };
    engine
        .evaluate_into(&prepared, jobs, f32_only, &mut plain)
        .expect("f32");
    let want =
        crowdmorph::engine::VertexData::encode(&plain.positions.to_f32(), q16.precision, false);
    assert_eq!(
        packed.positions, want,
        "the device's q16 is its f32 encoded"
    );
    gpu
}

#[test]
#[cfg_attr(
    not(all(crowdmorph_test_data, crowdmorph_gpu_driver)),
    ignore = "needs ../shared/data and a Vulkan adapter (apt-get install mesa-vulkan-drivers)"
)]
fn the_gpu_skin_pass_matches_the_cpu_engine_on_the_robot() {
    let (rig, doc) = robot();
    let wave = rig.clip_index("Wave").expect("Wave") as u32;
    let run = rig.clip_index("Running").expect("Running") as u32;
    let mut jobs: Vec<BlendJob> = (0..6).map(|f| BlendJob::frame(wave, f * 7, 0)).collect();
    jobs.push(BlendJob::posed(
        Pose::blend((wave, 20), &[(run, 9, 0.375)]),
        0,
    ));
    jobs.push(with_joints(
        &rig,
        BlendJob::frame(run, 4, 0),
        &[("Head", glam::Quat::from_rotation_y(0.6))],
    ));
    let gpu = gpu_agrees_with_cpu(&rig, &jobs);
    // And against the independent evaluator directly, frame by frame.
    let diag = f64::from(rig.bbox().diagonal());
    let fps = f64::from(rig.clips[wave as usize].fps);
    for f in 0..6u32 {
        let want = doc.pose(&doc.locals_at("Wave", f64::from(f * 7) / fps));
        let (dp, _) = distance(&gpu, f as usize, &want);
        assert!(
            dp <= 1e-5 * diag,
            "GPU, Wave frame {}: off by {dp:e}",
            f * 7
        );
    }
}

gpu_test!(
    #[test]
    fn the_gpu_skin_pass_matches_the_cpu_engine_on_a_face_with_overrides() {
        let rig = crowdmorph::synthetic::skinned_head();
        let talk = rig.clip_index("talk").expect("talk") as u32;
        let jobs = vec![
            BlendJob::frame(talk, 10, 0),
            with_joints(
                &rig,
                BlendJob::frame(talk, 10, 0),
                &[
                    ("LeftEye", glam::Quat::from_rotation_y(0.4)),
                    ("RightEye", glam::Quat::from_rotation_y(0.4)),
                    ("Jaw", glam::Quat::from_rotation_x(0.2)),
                ],
            ),
            BlendJob::frame(talk, 77, 2),
        ];
        let _ = gpu_agrees_with_cpu(&rig, &jobs);
    }
);

#[test]
fn a_face_turns_its_eyes_by_joint_override() {
    // Overrides replace the clip's rotation of the named nodes, as an animation channel
    // would: the engine matches the f64 evaluator given the same local transforms, and the
    // eyes, only they, move against the clip's own pose.
    let rig = crowdmorph::synthetic::skinned_head();
    let diag = f64::from(rig.bbox().diagonal());
    let talk = rig.clip_index("talk").expect("talk");
    let look = glam::Quat::from_rotation_y(0.45) * glam::Quat::from_rotation_x(-0.2);
    let plain = BlendJob::frame(talk as u32, 25, 0);
    let turned = with_joints(
        &rig,
        plain.clone(),
        &[("LeftEye", look), ("RightEye", look)],
    );
    let out = evaluate(&rig, &[plain, turned]);
    let (want, _) = rig_pose_f64_with(&rig, talk, 25, &|name, trs| {
        if name == "LeftEye" || name == "RightEye" {
            trs.rotation = look.to_array();
        }
    });
    let eyes = rig.vertex_offsets()[1]..rig.vertex_count();
    let (a, b) = (out.job_positions(0), out.job_positions(1));
    let (mut dp, mut eye_move, mut face_move) = (0f64, 0f64, 0f64);
    for (v, w) in want.iter().enumerate() {
        let g = DVec3::new(
            f64::from(b[3 * v]),
            f64::from(b[3 * v + 1]),
            f64::from(b[3 * v + 2]),
        );
        let before = DVec3::new(
            f64::from(a[3 * v]),
            f64::from(a[3 * v + 1]),
            f64::from(a[3 * v + 2]),
        );
        dp = dp.max((g - *w).length());
        if eyes.contains(&v) {
            eye_move = eye_move.max((g - before).length());
        } else {
            face_move = face_move.max((g - before).length());
        }
    }
    assert!(dp <= 1e-5 * diag, "position off by {dp:e}");
    assert!(eye_move > 2e-3 * diag, "the eyes turn ({eye_move})");
    assert_eq!(face_move, 0.0, "nothing else moves");
}

/// The f64 pose of `rig`'s clip `clip` at `frame` from the rig's own arrays: morph targets
/// (`util::rig_oracle`), then each vertex by its bones, with node transforms composed in f64
/// from the joint table; normals recomputed from the posed mesh where the rig recomputes them.
fn rig_pose_f64(rig: &Rig, clip: usize, frame: u32) -> (Vec<DVec3>, Vec<DVec3>) {
    rig_pose_f64_with(rig, clip, frame, &|_, _| {})
}

/// [`rig_pose_f64`] with each node's local transform first given to `set` (by node name),
/// which may replace parts of it: a request's joint overrides.
fn rig_pose_f64_with(
    rig: &Rig,
    clip: usize,
    frame: u32,
    set: &dyn Fn(&str, &mut crowdmorph::rig::Trs),
) -> (Vec<DVec3>, Vec<DVec3>) {
    use glam::{DMat4, DQuat};
    let c = &rig.clips[clip];
    let w: Vec<f64> = (0..rig.targets.len())
        .map(|t| f64::from(c.weight(t, frame)))
        .collect();
    let w = crate::util::effective_weights(rig, &w, 0);
    let (morphed, _) = crate::util::rig_oracle(rig, &w);
    let sk = rig.skeleton.as_ref().expect("skinned");
    let table = c.joints.as_ref().expect("joint table");
    let mut globals: Vec<DMat4> = Vec::new();
    for (i, n) in sk.nodes.iter().enumerate() {
        let mut trs = n.rest;
        if let Some(k) = table.nodes.iter().position(|&x| x as usize == i) {
            trs = table.at(frame, k);
        }
        set(&n.name, &mut trs);
        let local = DMat4::from_scale_rotation_translation(
            DVec3::from(trs.scale.map(f64::from)),
            DQuat::from_array(trs.rotation.map(f64::from)).normalize(),
            DVec3::from(trs.translation.map(f64::from)),
        );
        let g = match globals.get(n.parent as usize) {
            Some(p) => *p * local,
            None => local,
        };
        globals.push(g);
    }
    let bones: Vec<DMat4> = sk
        .bones
        .iter()
        .map(|b| globals[b.node as usize] * DMat4::from_cols_array(&b.bind.map(f64::from)))
        .collect();
    let mut posed = Vec::with_capacity(morphed.len());
    let mut normals = Vec::with_capacity(morphed.len());
    let mut v0 = 0;
    for p in rig.primitives.iter() {
        let skin = p.skin.as_ref().expect("every primitive skinned");
        let part: Vec<DVec3> = (0..p.positions.len())
            .map(|i| {
                let x = morphed[v0 + i];
                (0..4)
                    .map(|k| {
                        f64::from(skin.weights[i][k])
                            * bones[skin.joints[i][k] as usize].transform_point3(x)
                    })
                    .sum()
            })
            .collect();
        normals.extend(crate::util::ref_vertex_normals(&part, &p.indices));
        posed.extend(part);
        v0 += p.positions.len();
    }
    (posed, normals)
}

#[test]
fn a_skinned_face_turns_its_eyes_and_opens_its_jaw() {
    let rig = crowdmorph::synthetic::skinned_head();
    let diag = f64::from(rig.bbox().diagonal());
    let talk = rig.clip_index("talk").expect("talk");
    let idle = rig.clip_index("idle").expect("idle");
    let asked = [(talk, 0), (talk, 10), (talk, 25), (talk, 77), (idle, 50)];
    let jobs: Vec<BlendJob> = asked
        .iter()
        .map(|&(c, f)| BlendJob::frame(c as u32, f, 0))
        .collect();
    let out = evaluate(&rig, &jobs);
    let mut unskinned = rig.clone();
    unskinned.skeleton = None;
    unskinned.primitives = std::sync::Arc::new(
        rig.primitives
            .iter()
            .map(|p| crowdmorph::rig::Primitive {
                skin: None,
                ..p.clone()
            })
            .collect(),
    );
    for c in &mut unskinned.clips {
        c.joints = None;
    }
    let morph_only = evaluate(&unskinned, &jobs);
    let eyes = rig.vertex_offsets()[1]..rig.vertex_count();
    for (j, &(c, f)) in asked.iter().enumerate() {
        let (want_p, want_n) = rig_pose_f64(&rig, c, f);
        let got = out.job_positions(j);
        let got_n = out.job_normals(j).expect("normals");
        let (mut dp, mut dn, mut eye_move, mut moved) = (0f64, 0f64, 0f64, 0f64);
        let m = morph_only.job_positions(j);
        for v in 0..want_p.len() {
            let g = DVec3::new(
                f64::from(got[3 * v]),
                f64::from(got[3 * v + 1]),
                f64::from(got[3 * v + 2]),
            );
            let gn = DVec3::new(
                f64::from(got_n[3 * v]),
                f64::from(got_n[3 * v + 1]),
                f64::from(got_n[3 * v + 2]),
            );
            let mv = DVec3::new(
                f64::from(m[3 * v]),
                f64::from(m[3 * v + 1]),
                f64::from(m[3 * v + 2]),
            );
            dp = dp.max((g - want_p[v]).length());
            dn = dn.max((gn - want_n[v]).length());
            moved = moved.max((g - mv).length());
            if eyes.contains(&v) {
                eye_move = eye_move.max((g - mv).length());
            }
        }
        assert!(
            dp <= 1e-5 * diag,
            "clip {c} frame {f}: position off by {dp:e}"
        );
        assert!(dn <= 1e-3, "clip {c} frame {f}: normal off by {dn:e}");
        assert!(
            moved > 1e-3 * diag && eye_move > 1e-3 * diag,
            "clip {c} frame {f}: the joints move the face ({moved}) and the eyes ({eye_move})"
        );
    }
}

#[test]
fn live_link_eye_and_head_columns_turn_the_faces_joints() {
    // A Live Link Face CSV (its metadata columns, ARKit weights, then the head's and eyes'
    // angles) on the skinned face: through the default joint map the angles turn `Head`,
    // `LeftEye` and `RightEye` about rig axes (their rest rotations are the identity, so the
    // local rotation is yaw about +Y, then pitch about +X, then roll about +Z), checked against
    // the f64 evaluator given those local rotations.
    use crowdmorph::import::clips::{ClipOptions, clip_from_csv};
    let mut rig = crowdmorph::synthetic::skinned_head();
    let csv = "Timecode,BlendShapeCount,JawOpen,EyeBlinkLeft,HeadYaw,HeadPitch,HeadRoll,\
               LeftEyeYaw,LeftEyePitch,LeftEyeRoll,RightEyeYaw,RightEyePitch,RightEyeRoll\n\
               00:00:00:00.000,61,0.1,0.0,0,0,0,0,0,0,0,0,0\n\
               00:00:00:01.000,61,0.3,0.5,0.2,-0.1,0.05,0.35,0.1,0,0.3,0.12,0\n";
    let imported = clip_from_csv(&rig, "live", csv.as_bytes(), &ClipOptions::default())
        .expect("a Live Link CSV on a rig with head and eye joints");
    assert!(imported.ignored.is_empty(), "{:?}", imported.ignored);
    let table = imported
        .clip
        .joints
        .clone()
        .expect("the angles became a joint table");
    let sk = rig.skeleton.clone().expect("skinned");
    let names: Vec<&str> = table
        .nodes
        .iter()
        .map(|&n| sk.nodes[n as usize].name.as_str())
        .collect();
    assert_eq!(names, ["Head", "LeftEye", "RightEye"]);
    // Rotations do not commute: the map's order composes them, not the file's.
    let swapped = "HeadPitch,HeadRoll,HeadYaw\n0,0,0\n-0.1,0.05,0.2\n";
    let other = clip_from_csv(&rig, "swapped", swapped.as_bytes(), &ClipOptions::default())
        .expect("the same angles, other column order");
    let head = |t: &crowdmorph::rig::JointTable| t.at(1, 0).rotation;
    assert_eq!(
        head(other.clip.joints.as_deref().expect("a table")),
        head(&table),
        "column order does not change the turn"
    );
    rig.clips.push(imported.clip);
    rig.validate().expect("valid with the new clip");
    let clip = rig.clips.len() - 1;
    let out = evaluate(&rig, &[BlendJob::frame(clip as u32, 1, 0)]);
    let turn = |yaw: f32, pitch: f32, roll: f32| {
        (glam::Quat::from_rotation_y(yaw)
            * glam::Quat::from_rotation_x(pitch)
            * glam::Quat::from_rotation_z(roll))
        .to_array()
    };
    let (want, _) = rig_pose_f64_with(&rig, clip, 1, &|name, trs| match name {
        "Head" => trs.rotation = turn(0.2, -0.1, 0.05),
        "LeftEye" => trs.rotation = turn(0.35, 0.1, 0.0),
        "RightEye" => trs.rotation = turn(0.3, 0.12, 0.0),
        _ => {}
    });
    let diag = f64::from(rig.bbox().diagonal());
    let got = out.job_positions(0);
    let d = want
        .iter()
        .enumerate()
        .map(|(v, w)| {
            (DVec3::new(
                f64::from(got[3 * v]),
                f64::from(got[3 * v + 1]),
                f64::from(got[3 * v + 2]),
            ) - *w)
                .length()
        })
        .fold(0f64, f64::max);
    assert!(d <= 1e-5 * diag, "off by {d:e}");
    // Frame 0 has every angle at 0: the skeleton at rest.
    let rest = evaluate(&rig, &[BlendJob::frame(clip as u32, 0, 0)]);
    let (want0, _) = rig_pose_f64_with(&rig, clip, 0, &|_, _| {});
    let p0 = rest.job_positions(0);
    for (v, w) in want0.iter().enumerate() {
        let g = DVec3::new(
            f64::from(p0[3 * v]),
            f64::from(p0[3 * v + 1]),
            f64::from(p0[3 * v + 2]),
        );
        assert!((g - *w).length() <= 1e-5 * diag);
    }
}
