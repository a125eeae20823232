//! The GPU engine against the CPU engine (the oracle), on a real device: in CI and on machines
//! without a GPU that is Mesa's lavapipe (software Vulkan), opened explicitly — the `auto`
//! backend never picks it. Each test opens its own device.
//!
//! Tolerances: positions within 1e-5 × the bounding-box diagonal; unit normals within 1e-5 when
//! blended from normal deltas, and within 1e-3 when recomputed from positions (the two engines
//! sum face normals in different orders: 0 on the real rigs, up to 4.3e-4 on the synthetic
//! paper-scale rig); f16 outputs may round the other way on one side, so they
//! are allowed one binary16 step more: max |coordinate| × 2^-10 for positions, 2^-10 for normals.

use crate::util::gpu_test;
use std::sync::Arc;

use crowdmorph::engine::gpu::{DeltaFormat, GpuOptions};
use crowdmorph::engine::{BackendChoice, BackendKind, BlendJob, Engine, OutputSpec, Precision};
use crowdmorph::import::{ImportOptions, load_path};
use crowdmorph::rig::{MAX_BLEND_LAYERS, Pose, Rig};

use crate::util::{Rng, open_gpu, paper_scale_rig, rig_files, with_random_clip};

/// `n` random jobs of `rig` and a quarter of them again (clones): plain clip frames, blends of
/// up to five frames, and live weights (some negative, some past one), in about equal parts,
/// so every parity test also holds the GPU's weight-space blend to the CPU's.
fn random_jobs(rig: &Rig, seed: u64, n: usize) -> Vec<BlendJob> {
    let mut rng = Rng(seed);
    let frame = |rng: &mut Rng| {
        let clip = rng.below(rig.clips.len());
        (
            clip as u32,
            rng.below(rig.clips[clip].frames as usize) as u32,
        )
    };
    let mut jobs: Vec<BlendJob> = (0..n)
        .map(|i| {
            let lod = rng.below(rig.lod.levels.len()) as u32;
            let pose = match i % 3 {
                0 => {
                    let (clip, frame) = frame(&mut rng);
                    Pose::Frame { clip, frame }
                }
                1 => {
                    let layers: Vec<(u32, u32, f32)> = (0..1 + rng.below(MAX_BLEND_LAYERS))
                        .map(|_| {
                            let (c, f) = frame(&mut rng);
                            (c, f, rng.unit() / MAX_BLEND_LAYERS as f32)
                        })
                        .collect();
                    Pose::blend(frame(&mut rng), &layers)
                }
                _ => {
                    let w: Vec<f32> = (0..rig.targets.len())
                        .map(|_| rng.unit() * 2.0 - 0.5)
                        .collect();
                    Pose::live(&w)
                }
            };
            BlendJob::posed(pose, lod)
        })
        .collect();
    let clones = jobs[..n / 4].to_vec();
    jobs.extend(clones);
    jobs
}

fn max_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

/// Evaluates `jobs` on the GPU engine and on the CPU engine and compares every buffer.
fn check_parity(gpu_engine: &Engine, rig: Rig, jobs: &[BlendJob]) {
    check_parity_with(gpu_engine, rig.clone(), rig, jobs);
}

/// As [`check_parity`], with the CPU engine evaluating `cpu_rig` (the GPU's rig with its deltas
/// as the device stores them).
fn check_parity_with(gpu_engine: &Engine, rig: Rig, cpu_rig: Rig, jobs: &[BlendJob]) {
    let rig = Arc::new(rig);
    let cpu_engine = Engine::cpu();
    let g = gpu_engine.prepare(rig.clone()).expect("upload");
    let c = cpu_engine.prepare(Arc::new(cpu_rig)).expect("prepare");
    assert!(
        g.gpu().is_some() && g.memory().device_bytes > 0,
        "{}: rig is resident",
        rig.name
    );
    let diag = rig.bbox().diagonal();
    // A PCA level's rig has no normal deltas: its normals are recomputed on both engines.
    let recomputed = !rig.has_normal_deltas()
        || jobs
            .iter()
            .any(|j| rig.lod.levels[j.lod as usize].pca.is_some());
    let qbox = crowdmorph::server::registry::quantization_box(&rig);
    for spec in [
        OutputSpec {
            normals: true,
            precision: Precision::F32,
        },
        OutputSpec {
            normals: true,
            precision: Precision::F16,
        },
        OutputSpec {
            normals: false,
            precision: Precision::F32,
        },
        // The GPU blends q16 jobs in f32 and the engine encodes them on the host.
        OutputSpec {
            normals: true,
            precision: Precision::Q16(qbox),
        },
    ] {
        let got = gpu_engine.evaluate(&g, jobs, spec).expect("gpu evaluate");
        let want = cpu_engine.evaluate(&c, jobs, spec).expect("cpu evaluate");
        assert_eq!(
            got.kind,
            Some(BackendKind::Gpu),
            "{}: computed on the GPU, not the fallback: {:?}",
            rig.name,
            gpu_engine.info().degraded_reason
        );
        assert!(
            !gpu_engine.info().degraded,
            "{}: {:?}",
            rig.name,
            gpu_engine.info().degraded_reason
        );
        assert_eq!(got.output.jobs, jobs.len());
        let f16 = spec.precision == Precision::F16;
        // Each side is within the stated error of its own f32 blend.
        let (q16_pos, q16_nrm) = match spec.precision {
            Precision::Q16(b) => (
                2.0 * b.max_error.iter().copied().fold(0.0, f32::max),
                2.0 * crowdmorph_proto::Q16_NORMAL_MAX_ERROR,
            ),
            _ => (0.0, 0.0),
        };
        assert!(got.output.positions.is_kind(spec.precision));
        for j in 0..jobs.len() {
            let (gp, cp) = (got.output.job_positions(j), want.output.job_positions(j));
            let max_coord = cp.iter().map(|x| x.abs()).fold(0.0, f32::max);
            let tol = 1e-5 * diag + if f16 { max_coord / 1024.0 } else { 0.0 } + q16_pos;
            let d = max_diff(&gp, &cp);
            assert!(
                d <= tol,
                "{} {spec:?} job {j}: positions differ by {d:e} (tolerance {tol:e})",
                rig.name
            );
            if spec.normals {
                let (gn, cn) = (
                    got.output.job_normals(j).expect("normals"),
                    want.output.job_normals(j).expect("normals"),
                );
                let tol = if recomputed { 1e-3 } else { 1e-5 }
                    + if f16 { 1.0 / 1024.0 } else { 0.0 }
                    + q16_nrm;
                let d = max_diff(&gn, &cn);
                assert!(
                    d <= tol,
                    "{} {spec:?} job {j}: normals differ by {d:e} (tolerance {tol:e})",
                    rig.name
                );
            }
        }
        if let Some(ctx) = gpu_engine.gpu()
            && ctx.has_timestamps()
        {
            assert!(
                got.timings.gpu_ns.is_some_and(|t| t > 0),
                "timestamp queries give a GPU time"
            );
        }
    }
}

gpu_test!(
    #[test]
    fn gpu_matches_cpu_on_the_embedded_head() {
        let engine = Engine::with_gpu(open_gpu(GpuOptions::default()), BackendChoice::Gpu);
        let rig = with_random_clip(crowdmorph::embedded::default_rig(), 0);
        let jobs = random_jobs(&rig, 100, 33);
        check_parity(&engine, rig, &jobs);
    }
);

gpu_test!(
    #[test]
    fn gpu_matches_cpu_at_pca_levels() {
        let engine = Engine::with_gpu(open_gpu(GpuOptions::default()), BackendChoice::Gpu);
        let mut rig = with_random_clip(crowdmorph::embedded::default_rig(), 0);
        let spec = crowdmorph::lod::LodSpec {
            method: crowdmorph::lod::OrderMethod::FileOrder,
            ..Default::default()
        };
        rig.lod = crowdmorph::lod::build_lod(&rig, &spec, None, None).expect("lod");
        let levels: Vec<u32> = (0..rig.lod.levels.len() as u32)
            .filter(|&l| rig.lod.levels[l as usize].pca.is_some())
            .collect();
        assert!(!levels.is_empty(), "{:?}", rig.lod.levels);
        // One level per call (a call evaluates one level's rig), every kind of pose.
        for l in levels {
            let mut jobs = random_jobs(&rig, 200 + u64::from(l), 24);
            for j in &mut jobs {
                j.lod = l;
            }
            check_parity(&engine, rig.clone(), &jobs);
        }
    }
);

gpu_test!(
    #[test]
    #[cfg_attr(
        all(crowdmorph_gpu_driver, not(crowdmorph_test_data)),
        ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
    )]
    fn gpu_matches_cpu_on_every_real_rig() {
        let engine = Engine::with_gpu(open_gpu(GpuOptions::default()), BackendChoice::Gpu);
        for (i, f) in rig_files().into_iter().enumerate() {
            // Seeds continue after the embedded head's, as when one test covered all the rigs.
            let i = i as u64 + 1;
            let rig = load_path(&f, &ImportOptions::default()).expect("load");
            let rig = with_random_clip(rig, i);
            let n = if rig.vertex_count() > 10_000 { 10 } else { 33 };
            let jobs = random_jobs(&rig, 100 + i, n);
            check_parity(&engine, rig, &jobs);
        }
    }
);

/// `rig` with every position and normal delta as `format` stores it on the device.
fn with_deltas_as(rig: &Rig, format: DeltaFormat) -> Rig {
    let mut primitives = (*rig.primitives).clone();
    for t in primitives.iter_mut().flat_map(|p| p.targets.iter_mut()) {
        let round =
            |v: &mut glam::Vec3| *v = glam::Vec3::from_array(v.to_array().map(|x| format.round(x)));
        t.positions.iter_mut().for_each(round);
        t.normals.iter_mut().flatten().for_each(round);
    }
    Rig {
        primitives: Arc::new(primitives),
        ..rig.clone()
    }
}

gpu_test!(
    #[test]
    fn f16_deltas_blend_as_the_cpu_engine_does_with_the_deltas_rounded() {
        // `--gpu-deltas f16`: the device holds each delta as the nearest binary16, its delta blocks
        // at half the bytes; the CPU engine on a rig whose deltas were rounded the same way is its oracle, and
        // the CPU engine on the exact rig differs by the rounding (more than zero, far less than
        // the rig).
        let f16 = Engine::with_gpu(
            open_gpu(GpuOptions {
                deltas: DeltaFormat::F16,
                ..GpuOptions::default()
            }),
            BackendChoice::Gpu,
        );
        let f32 = Engine::with_gpu(open_gpu(GpuOptions::default()), BackendChoice::Gpu);
        let mut rigs = vec![crowdmorph::embedded::default_rig(), paper_scale_rig()];
        rigs.extend(
            rig_files().into_iter().take(1).map(|f| {
                with_random_clip(load_path(&f, &ImportOptions::default()).expect("load"), 3)
            }),
        );
        for (i, rig) in rigs.into_iter().enumerate() {
            let half = f16.prepare(Arc::new(rig.clone())).expect("upload");
            let full = f32.prepare(Arc::new(rig.clone())).expect("upload");
            let (h, w) = (half.gpu().expect("resident"), full.gpu().expect("resident"));
            assert_eq!(
                (h.deltas(), w.deltas()),
                (DeltaFormat::F16, DeltaFormat::F32)
            );
            assert!(
                h.geometry_bytes() < w.geometry_bytes(),
                "{}: {} bytes with f16 deltas, {} with f32",
                rig.name,
                h.geometry_bytes(),
                w.geometry_bytes()
            );
            let jobs = random_jobs(&rig, 700 + i as u64, 12);
            let spec = OutputSpec {
                normals: false,
                precision: Precision::F32,
            };
            let cpu = Engine::cpu();
            let exact = cpu.prepare(Arc::new(rig.clone())).expect("prepare");
            let got = f16.evaluate(&half, &jobs, spec).expect("gpu");
            let want = cpu.evaluate(&exact, &jobs, spec).expect("cpu");
            let d = max_diff(
                &got.output.positions.to_f32(),
                &want.output.positions.to_f32(),
            );
            let rounded = with_deltas_as(&rig, DeltaFormat::F16);
            let oracle = cpu.prepare(Arc::new(rounded.clone())).expect("prepare");
            let near = cpu.evaluate(&oracle, &jobs, spec).expect("cpu");
            let e = max_diff(
                &got.output.positions.to_f32(),
                &near.output.positions.to_f32(),
            );
            let diag = rig.bbox().diagonal();
            // The rounding, not float noise, is what separates the GPU from the exact blend.
            assert!(
                d > 10.0 * e && d < 1e-3 * diag,
                "{}: f16 deltas move positions by {d:e} from the exact blend, {e:e} from the \
                 rounded one (diagonal {diag})",
                rig.name
            );
            check_parity_with(&f16, rig, rounded, &jobs);
        }
    }
);

gpu_test!(
    #[test]
    fn long_active_lists_compacted_per_tile_match() {
        // 600 targets on 4,096 vertices: a group's active list runs past one staging batch of 256
        // entries, and each tile of 64 vertices keeps only the few slots that move it, so the
        // blend's per-tile compaction and the active-list scan are exercised across batches.
        let engine = Engine::with_gpu(open_gpu(GpuOptions::default()), BackendChoice::Gpu);
        let rig = crowdmorph::synthetic::banded_rig("banded", 4096, 64, 600);
        let mut jobs = random_jobs(&rig, 600, 20);
        // Live weights over every slot of LOD 0, two thirds of them non-zero: lists of 400 entries,
        // in the first group and in the last, which has three jobs (the half-work loop).
        let w: Vec<f32> = (0..600).map(|t| (t % 3) as f32 * 0.25).collect();
        assert_eq!(rig.lod.levels[0].shapes, 600);
        assert!(w.iter().filter(|&&x| x != 0.0).count() > 256);
        jobs.insert(3, BlendJob::posed(Pose::live(&w), 0));
        jobs.push(BlendJob::posed(Pose::live(&w), 0));
        assert_eq!(jobs.len() % 8, 3);
        check_parity(&engine, rig, &jobs);
    }
);

gpu_test!(
    #[test]
    fn paper_scale_rig_over_the_binding_limit_is_chunked_and_matches() {
        // Chunks of at most 256 KiB split the rig's delta blocks several ways, and 4 MiB bindings
        // split a batch's output (525 KB a job) into sub-batches of seven jobs, which start in the
        // middle of the blend's groups of eight.
        let ctx = open_gpu(GpuOptions {
            max_binding: Some(4 << 20),
            max_chunk: Some(256 << 10),
            ..GpuOptions::default()
        });
        let engine = Engine::with_gpu(ctx, BackendChoice::Gpu);
        let rig = paper_scale_rig();
        let prepared = engine.prepare(Arc::new(rig.clone())).expect("upload");
        let chunks = prepared.gpu().expect("resident").chunks();
        assert!(
            chunks >= 3,
            "expected the rig split into chunks, got {chunks}"
        );
        let jobs = random_jobs(&rig, 7, 12);
        check_parity(&engine, rig, &jobs);
    }
);

gpu_test!(
    #[test]
    fn a_rig_the_device_cannot_hold_is_refused_clearly() {
        // With 64 KiB bindings one job's output of the embedded head (7,262 vertices, 87 KB) cannot
        // fit.
        let ctx = open_gpu(GpuOptions {
            max_binding: Some(64 << 10),
            ..GpuOptions::default()
        });
        let engine = Engine::with_gpu(ctx, BackendChoice::Gpu);
        let err = engine
            .prepare(Arc::new(crowdmorph::embedded::default_rig()))
            .expect_err("refused");
        let msg = err.to_string();
        assert!(
            msg.contains("does not fit") && msg.contains("vertices"),
            "{msg}"
        );
        assert!(
            !engine.info().degraded,
            "refusing a rig is not a device fault"
        );
    }
);

gpu_test!(
    #[test]
    fn device_loss_falls_back_to_the_cpu_engine_without_losing_rigs() {
        let ctx = open_gpu(GpuOptions::default());
        let engine = Engine::with_gpu(ctx, BackendChoice::Gpu);
        let rig = Arc::new(crowdmorph::embedded::default_rig());
        let prepared = engine.prepare(rig.clone()).expect("upload");
        let jobs = random_jobs(&rig, 3, 8);
        let spec = OutputSpec {
            normals: true,
            precision: Precision::F32,
        };
        let before = engine.evaluate(&prepared, &jobs, spec).expect("gpu");
        assert_eq!(before.kind, Some(BackendKind::Gpu));

        engine.gpu().expect("gpu").device().destroy();

        let after = engine
            .evaluate(&prepared, &jobs, spec)
            .expect("still answers");
        assert_eq!(
            after.kind,
            Some(BackendKind::Cpu),
            "the CPU engine took over"
        );
        let info = engine.info();
        assert!(info.degraded && info.kind == BackendKind::Cpu, "{info:?}");
        assert!(info.degraded_reason.is_some());
        let cpu = Engine::cpu();
        let want = cpu
            .evaluate(&cpu.prepare(rig.clone()).expect("prepare"), &jobs, spec)
            .expect("cpu");
        assert_eq!(after.output, want.output, "same answer as the CPU engine");
        // New rigs are still accepted (host-side) after the loss.
        let again = engine.prepare(rig).expect("prepare after loss");
        assert!(again.gpu().is_none());
        assert_eq!(
            engine.evaluate(&again, &jobs, spec).expect("cpu").output,
            want.output
        );
    }
);

gpu_test!(
    #[test]
    fn consecutive_batches_overlap_and_results_stay_on_the_device_without_readback() {
        let ctx = open_gpu(GpuOptions::default());
        let engine = Engine::with_gpu(ctx, BackendChoice::Gpu);
        let rig = Arc::new(crowdmorph::embedded::default_rig());
        let prepared = engine.prepare(rig.clone()).expect("upload");
        let spec = OutputSpec::default();
        let a = random_jobs(&rig, 1, 8);
        let b = random_jobs(&rig, 2, 8);
        // Submit both before collecting either: the second is recorded while the first runs.
        let pa = engine.submit(&prepared, &a, spec, true).expect("submit a");
        let pb = engine.submit(&prepared, &b, spec, true).expect("submit b");
        let (rb, ra) = (pb.wait().expect("b"), pa.wait().expect("a"));
        let cpu = Engine::cpu();
        let c = cpu.prepare(rig).expect("prepare");
        let diag = prepared.rig().bbox().diagonal();
        for (got, jobs) in [(ra, &a), (rb, &b)] {
            let want = cpu.evaluate(&c, jobs, spec).expect("cpu");
            for j in 0..jobs.len() {
                assert!(
                    max_diff(&got.output.job_positions(j), &want.output.job_positions(j))
                        <= 1e-5 * diag
                );
            }
        }
        let kept = engine
            .submit(&prepared, &a, spec, false)
            .expect("submit")
            .wait()
            .expect("wait");
        assert_eq!(kept.kind, Some(BackendKind::Gpu));
        assert!(
            kept.output.positions.is_empty(),
            "no readback was asked for"
        );
        // Collecting it left the device healthy: the next batch still runs on the GPU.
        assert!(
            !engine.info().degraded,
            "{:?}",
            engine.info().degraded_reason
        );
        let again = engine.evaluate(&prepared, &b, spec).expect("again");
        assert_eq!(again.kind, Some(BackendKind::Gpu));
    }
);

/// Codes `jobs` of `rig` as q16r on `engine`'s device against a random reference (so that
/// differences wrap and every zigzag case occurs; the server's, the neutral, gives small
/// residuals only) and checks the planes against the host's coding of the device's own q16,
/// bit for bit, and a client's decoding, job by job.
fn device_codes_residuals(engine: &Engine, rig: Rig, jobs: &[BlendJob], normals: bool) {
    use crowdmorph::engine::{Q16Reference, VertexData, code_residuals};
    let qbox = crowdmorph::server::registry::quantization_box(&rig);
    let name = rig.name.clone();
    let prepared = engine.prepare(Arc::new(rig)).expect("upload");
    let spec = OutputSpec {
        normals,
        precision: Precision::Q16(qbox),
    };
    let plain = engine.evaluate(&prepared, jobs, spec).expect("q16");
    let v3 = plain.output.vertices * 3;
    let mut rng = Rng(3);
    let reference: Q16Reference = (0..v3).map(|_| rng.next_u64() as i16).collect();
    let coded = engine
        .submit_coded(&prepared, jobs, spec, true, Some(reference.clone()))
        .expect("submit")
        .wait()
        .expect("wait");
    assert_eq!(coded.kind, Some(BackendKind::Gpu));
    let mut expected = plain.output.positions.clone();
    code_residuals(&mut expected, &reference).expect("host coding");
    assert_eq!(coded.output.positions, expected, "{name}: residual planes");
    assert_eq!(
        coded.output.normals, plain.output.normals,
        "{name}: normals stay q16"
    );
    let VertexData::Q16(q, _) = &plain.output.positions else {
        panic!("q16 positions")
    };
    let planes = coded.output.positions.as_bytes();
    for j in 0..jobs.len() {
        let decoded =
            crowdmorph_proto::q16r_decode(&planes[2 * j * v3..2 * (j + 1) * v3], &reference)
                .expect("decodes");
        assert_eq!(decoded, q[j * v3..(j + 1) * v3], "{name}: job {j}");
    }
}

gpu_test!(
    #[test]
    fn the_device_codes_q16_residuals_as_the_host_does_across_sub_batches() {
        use crowdmorph::engine::{EngineError, Q16Reference};
        // 128 KiB bindings hold five jobs (24 KB of f32 each) of a rig of 2,001 vertices: the 16
        // jobs run in sub-batches of 5, 5, 5 and 1. With 6,003 components a job (odd), every odd
        // job's planes start in the middle of a word, a word holds the end of one job's high plane
        // and the start of the next job's low plane, and each sub-batch ends in half a word.
        // Positions only: the blend codes them itself (`PACK` 3).
        let engine = Engine::with_gpu(
            open_gpu(GpuOptions {
                max_binding: Some(128 << 10),
                ..GpuOptions::default()
            }),
            BackendChoice::Gpu,
        );
        let odd = crowdmorph::synthetic::banded_rig("odd", 2001, 50, 40);
        assert_eq!(odd.vertex_count() % 2, 1);
        let jobs = random_jobs(&odd, 5, 13);
        assert_eq!(jobs.len(), 16);
        device_codes_residuals(&engine, odd.clone(), &jobs, false);
        // With recomputed normals (which stay q16) on the embedded head, in one batch: 21,786
        // components a job, so each job's high plane starts in the middle of a word. The blend
        // writes f32 here and `pack_q16r` codes them.
        let head = with_random_clip(crowdmorph::embedded::default_rig(), 7);
        let head_jobs = random_jobs(&head, 11, 9);
        let whole = Engine::with_gpu(open_gpu(GpuOptions::default()), BackendChoice::Gpu);
        device_codes_residuals(&whole, head, &head_jobs, true);
        // A reference of the wrong size is refused before anything is submitted, and the device
        // stays in use.
        let qbox = crowdmorph::server::registry::quantization_box(&odd);
        let prepared = engine.prepare(Arc::new(odd)).expect("upload");
        let spec = OutputSpec {
            normals: false,
            precision: Precision::Q16(qbox),
        };
        let short: Q16Reference = vec![0i16; 6002].into();
        let refused = engine.submit_coded(&prepared, &jobs, spec, true, Some(short));
        assert!(
            matches!(refused, Err(EngineError::Residuals(_))),
            "a short reference was not refused"
        );
        assert!(!engine.info().degraded);
    }
);

gpu_test!(
    #[test]
    fn the_blend_writes_q16_and_f16_itself_bit_for_bit() {
        use crowdmorph::engine::VertexData;
        // Positions only, on an unskinned rig: the blend writes the 16-bit format itself. The odd
        // rig (2,001 vertices) has words shared by two vertices and by two jobs; 128 KiB bindings
        // run its 16 jobs in sub-batches of 5, 5, 5 and 1, the last groups of eight short, and
        // 16 KiB chunks split its deltas into dispatches whose tiles share words at their edges.
        let engine = Engine::with_gpu(
            open_gpu(GpuOptions {
                max_binding: Some(128 << 10),
                max_chunk: Some(16 << 10),
                ..GpuOptions::default()
            }),
            BackendChoice::Gpu,
        );
        let whole = Engine::with_gpu(open_gpu(GpuOptions::default()), BackendChoice::Gpu);
        // And the pipelines that read binary16 deltas.
        let halves = Engine::with_gpu(
            open_gpu(GpuOptions {
                deltas: DeltaFormat::F16,
                ..GpuOptions::default()
            }),
            BackendChoice::Gpu,
        );
        let odd = crowdmorph::synthetic::banded_rig("odd", 2001, 50, 40);
        let chunks = engine
            .prepare(Arc::new(odd.clone()))
            .expect("upload")
            .gpu()
            .expect("resident")
            .chunks();
        assert!(chunks >= 3, "the odd rig in {chunks} chunks");
        let head = with_random_clip(crowdmorph::embedded::default_rig(), 7);
        let paper = paper_scale_rig();
        for (engine, rig, n) in [
            (&engine, odd.clone(), 13),
            (&whole, head, 13),
            (&whole, paper, 19),
            (&halves, odd, 13),
        ] {
            let jobs = random_jobs(&rig, 17, n);
            let qbox = crowdmorph::server::registry::quantization_box(&rig);
            let name = rig.name.clone();
            let prepared = engine.prepare(Arc::new(rig)).expect("upload");
            let f32_spec = OutputSpec {
                normals: false,
                precision: Precision::F32,
            };
            let blended = engine.evaluate(&prepared, &jobs, f32_spec).expect("f32");
            let VertexData::F32(pos) = &blended.output.positions else {
                panic!("f32 positions")
            };
            for precision in [Precision::Q16(qbox), Precision::F16] {
                let spec = OutputSpec {
                    normals: false,
                    precision,
                };
                // Twice: the second batch finds the words of the first in the pooled buffer.
                for _ in 0..2 {
                    let got = engine.evaluate(&prepared, &jobs, spec).expect("16-bit");
                    assert_eq!(got.kind, Some(BackendKind::Gpu));
                    assert_eq!(
                        got.output.positions,
                        VertexData::encode(pos, precision, false),
                        "{name} {precision:?}: the device's encoding of its own f32 blend"
                    );
                }
            }
        }
        for e in [&engine, &whole, &halves] {
            assert!(!e.info().degraded, "{:?}", e.info().degraded_reason);
        }
    }
);

/// What `q16r` relies on (proto/README.md): the reference a client fetches from a server, its
/// engine's q16 frame of the neutral (every weight 0), is the CPU engine's, which the server
/// codes against, bit for bit, at every LOD level.
fn neutral_is_the_cpu_engines(engine: &Engine, rig: Rig) {
    let qbox = crowdmorph::server::registry::quantization_box(&rig);
    let name = rig.name.clone();
    let levels = rig.lod.levels.len() as u32;
    let zero = Pose::live(&vec![0.0; rig.targets.len()]);
    let prepared = engine.prepare(Arc::new(rig)).expect("upload");
    let spec = OutputSpec {
        normals: false,
        precision: Precision::Q16(qbox),
    };
    for lod in 0..levels {
        let job = BlendJob::posed(zero.clone(), lod);
        let got = engine.evaluate(&prepared, &[job], spec).expect("neutral");
        assert_eq!(got.kind, Some(BackendKind::Gpu));
        let crowdmorph::engine::VertexData::Q16(q, _) = got.output.positions else {
            panic!("q16")
        };
        let cpu = prepared
            .at_level(lod)
            .q16_reference(qbox)
            .expect("reference");
        let differ = q.iter().zip(&cpu).filter(|(a, b)| a != b).count();
        assert_eq!(differ, 0, "{name} LOD {lod}: {differ} components differ");
    }
}

gpu_test!(
    #[test]
    fn the_neutral_is_the_same_on_both_engines_skinned_or_not() {
        let engine = Engine::with_gpu(open_gpu(GpuOptions::default()), BackendChoice::Gpu);
        neutral_is_the_cpu_engines(&engine, crowdmorph::embedded::default_rig());
        // The skinned face stands at rest: each vertex by its bones' rest matrices, which are
        // the identity only up to rounding.
        neutral_is_the_cpu_engines(&engine, crowdmorph::synthetic::skinned_head());
    }
);

#[test]
#[cfg_attr(
    not(all(crowdmorph_gpu_driver, crowdmorph_test_data)),
    ignore = "needs a Vulkan adapter and ../shared/data (the shared test rigs)"
)]
fn the_neutral_is_the_same_on_both_engines_on_every_real_rig() {
    let engine = Engine::with_gpu(open_gpu(GpuOptions::default()), BackendChoice::Gpu);
    let mut files = rig_files();
    files.push(crate::util::data_dir().join("robot-expressive/RobotExpressive.glb"));
    for path in files {
        let rig = load_path(&path, &ImportOptions::default())
            .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        neutral_is_the_cpu_engines(&engine, rig);
    }
}

gpu_test!(
    #[test]
    fn the_device_packs_q16_and_f16_bit_for_bit_and_reads_back_into_warm_buffers() {
        use crowdmorph::engine::{BlendOutput, VertexData};
        let engine = Engine::with_gpu(open_gpu(GpuOptions::default()), BackendChoice::Gpu);
        let rig = with_random_clip(crowdmorph::embedded::default_rig(), 7);
        // An odd number of components per job, so the last packed half is padding.
        let jobs = random_jobs(&rig, 11, 13);
        let qbox = crowdmorph::server::registry::quantization_box(&rig);
        let rig = Arc::new(rig);
        let prepared = engine.prepare(rig).expect("upload");
        let f32_spec = OutputSpec {
            normals: true,
            precision: Precision::F32,
        };
        let blended = engine.evaluate(&prepared, &jobs, f32_spec).expect("f32");
        let VertexData::F32(pos) = &blended.output.positions else {
            panic!("f32 positions")
        };
        let Some(VertexData::F32(nrm)) = &blended.output.normals else {
            panic!("f32 normals")
        };
        for precision in [Precision::Q16(qbox), Precision::F16] {
            let spec = OutputSpec {
                normals: true,
                precision,
            };
            let mut out = BlendOutput::default();
            // Twice into the same output: the second read overwrites the first's arrays in place.
            let mut first_address = 0;
            for round in 0..2 {
                let pending = engine.submit(&prepared, &jobs, spec, true).expect("submit");
                let (_, kind) = pending.wait_into(&mut out).expect("wait");
                assert_eq!(kind, BackendKind::Gpu);
                let address = out.positions.as_bytes().as_ptr() as usize;
                if round == 0 {
                    first_address = address;
                } else {
                    assert_eq!(
                        address, first_address,
                        "{precision:?}: the warm array was reused"
                    );
                }
            }
            // The device's 16-bit output is the host's encoding of the device's own f32 blend.
            assert_eq!(
                out.positions,
                VertexData::encode(pos, precision, false),
                "{precision:?} positions"
            );
            assert_eq!(
                out.normals.as_ref().expect("normals"),
                &VertexData::encode(nrm, precision, true),
                "{precision:?} normals"
            );
        }
    }
);

#[test]
fn auto_never_picks_a_software_adapter() {
    let instance =
        wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
    let adapters = pollster::block_on(instance.enumerate_adapters(wgpu::Backends::all()));
    let hardware = adapters
        .iter()
        .any(|a| crowdmorph::engine::gpu::is_hardware(&a.get_info()));
    let engine = Engine::new(BackendChoice::Auto).expect("auto always works");
    let info = engine.info();
    if hardware {
        assert_eq!(
            info.kind,
            BackendKind::Gpu,
            "a hardware adapter exists: {info:?}"
        );
    } else {
        eprintln!(
            "no hardware adapter here ({} software); auto must choose the CPU",
            adapters.len()
        );
        assert_eq!(info.kind, BackendKind::Cpu, "{info:?}");
        assert!(info.adapter.is_none());
    }
}

gpu_test!(
    #[test]
    fn a_discrete_gpus_budget_defaults_to_most_of_its_memory_and_others_keep_the_fixed_one() {
        use crowdmorph::engine::gpu::{
            DISCRETE_GPU_MEMORY_SHARE, default_gpu_memory, device_local_heap, discrete_gpu_memory,
        };
        let instance =
            wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        let adapters = pollster::block_on(instance.enumerate_adapters(wgpu::Backends::VULKAN));
        assert!(!adapters.is_empty(), "a Vulkan adapter (lavapipe at least)");
        for a in &adapters {
            let info = a.get_info();
            // Every Vulkan device has a device-local heap; lavapipe's is the host's memory.
            let heap = device_local_heap(a).expect("a Vulkan adapter reports its heaps");
            assert!(heap >= 64 << 20, "{}: {heap} bytes", info.name);
            match discrete_gpu_memory(a) {
                Some(budget) => {
                    assert_eq!(info.device_type, wgpu::DeviceType::DiscreteGpu);
                    let share = (heap as f64 * DISCRETE_GPU_MEMORY_SHARE) as u64;
                    assert_eq!(budget, share.max(default_gpu_memory(&a.limits())));
                }
                None => assert_ne!(info.device_type, wgpu::DeviceType::DiscreteGpu, "{info:?}"),
            }
        }
    }
);

gpu_test!(
    #[test]
    fn every_pass_runs_within_webgpus_default_limits() {
        // A device that grants only WebGPU's default limits (eight storage buffers a stage among
        // them), as GL and downlevel adapters may: every pipeline the engine builds must fit, and
        // every output path must give what an unlimited device gives, bit for bit.
        use crowdmorph::engine::Q16Reference;
        use crowdmorph::engine::gpu::GpuContext;
        let instance =
            wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        let adapter = pollster::block_on(instance.enumerate_adapters(wgpu::Backends::VULKAN))
            .into_iter()
            .next()
            .expect("a Vulkan adapter (lavapipe at least)");
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("webgpu defaults"),
            required_features: adapter.features() & wgpu::Features::TIMESTAMP_QUERY,
            required_limits: wgpu::Limits::default(),
            ..Default::default()
        }))
        .expect("a device with the default limits");
        assert_eq!(device.limits().max_storage_buffers_per_shader_stage, 8);
        let deltas = DeltaFormat::F16;
        let options = GpuOptions {
            deltas,
            ..GpuOptions::default()
        };
        let limited = Engine::with_gpu(
            GpuContext::from_device(device, queue, adapter.get_info(), options),
            BackendChoice::Gpu,
        );
        let full = Engine::with_gpu(open_gpu(options), BackendChoice::Gpu);
        let odd = crowdmorph::synthetic::banded_rig("odd", 2001, 50, 40);
        let head = with_random_clip(crowdmorph::embedded::default_rig(), 7);
        let skinned = crowdmorph::synthetic::skinned_head();
        for rig in [odd, head, skinned] {
            let jobs = random_jobs(&rig, 23, 11);
            let qbox = crowdmorph::server::registry::quantization_box(&rig);
            let a = limited.prepare(Arc::new(rig.clone())).expect("upload");
            let b = full.prepare(Arc::new(rig.clone())).expect("upload");
            let neutral: Q16Reference = a.q16_reference(qbox).expect("reference").into();
            for precision in [Precision::F32, Precision::F16, Precision::Q16(qbox)] {
                for normals in [false, true] {
                    let spec = OutputSpec { normals, precision };
                    let reference = matches!(precision, Precision::Q16(_)).then(|| neutral.clone());
                    let run = |e: &Engine, p| {
                        e.submit_coded(p, &jobs, spec, true, reference.clone())
                            .expect("submit")
                            .wait()
                            .expect("wait")
                    };
                    let (x, y) = (run(&limited, &a), run(&full, &b));
                    assert_eq!(x.kind, Some(BackendKind::Gpu), "{}", rig.name);
                    assert_eq!(x.output, y.output, "{} {spec:?}", rig.name);
                }
            }
        }
        assert!(
            !limited.info().degraded,
            "{:?}",
            limited.info().degraded_reason
        );
    }
);

/// Reads `len` f32 of `buffer` from byte `offset` back to the host (tests only).
fn read_back(
    ctx: &crowdmorph::engine::gpu::GpuContext,
    buffer: &wgpu::Buffer,
    offset: u64,
    len: usize,
) -> Vec<f32> {
    let bytes = (len * 4) as u64;
    let staging = ctx.device().create_buffer(&wgpu::BufferDescriptor {
        label: Some("test readback"),
        size: bytes,
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let mut encoder = ctx
        .device()
        .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
    encoder.copy_buffer_to_buffer(buffer, offset, &staging, 0, bytes);
    ctx.queue().submit([encoder.finish()]);
    staging.map_async(wgpu::MapMode::Read, .., |r| r.expect("map"));
    ctx.device()
        .poll(wgpu::PollType::wait_indefinitely())
        .expect("poll");
    let view = staging.get_mapped_range(..).expect("mapped");
    bytemuck::cast_slice::<u8, f32>(&view).to_vec()
}

gpu_test!(
    #[test]
    fn outputs_left_on_the_device_are_the_blend_and_the_engine_stays_healthy() {
        // Small bindings split 20 jobs into sub-batches (of eight: 2 MiB holds eight jobs' face
        // normals, 14,512 triangles each) that reuse the slot's output buffers: the resident outputs
        // must hold every job, not only the last sub-batch's.
        let ctx = open_gpu(GpuOptions {
            max_binding: Some(2 << 20),
            ..GpuOptions::default()
        });
        let engine = Engine::with_gpu(ctx, BackendChoice::Gpu);
        let rig = Arc::new(crowdmorph::embedded::default_rig());
        let prepared = engine.prepare(rig.clone()).expect("upload");
        let cpu = Engine::cpu();
        let c = cpu.prepare(rig.clone()).expect("prepare");
        let spec = OutputSpec {
            normals: true,
            precision: Precision::F32,
        };
        let diag = rig.bbox().diagonal();
        let v3 = rig.vertex_count() * 3;
        // Several batches in a row, then an ordinary read-back batch: none of them degrades the
        // engine (unmapping a never-mapped staging buffer used to).
        for seed in 0..3 {
            let jobs = random_jobs(&rig, 10 + seed, 20);
            let (buffers, _) = engine
                .evaluate_for_render(&prepared, &jobs)
                .expect("evaluate");
            let crowdmorph::engine::RenderBuffers::Device(out) = buffers else {
                panic!("a healthy GPU engine leaves render outputs on the device");
            };
            assert_eq!((out.jobs, out.vertices), (jobs.len(), rig.vertex_count()));
            let want = cpu.evaluate(&c, &jobs, spec).expect("cpu");
            let ctx = engine.gpu().expect("gpu");
            for j in 0..jobs.len() {
                let p = read_back(ctx, &out.positions, out.offset(j), v3);
                assert!(
                    max_diff(&p, &want.output.job_positions(j)) <= 1e-5 * diag,
                    "job {j}"
                );
                let n = read_back(
                    ctx,
                    out.normals.as_ref().expect("normals"),
                    out.offset(j),
                    v3,
                );
                let wn = want.output.job_normals(j).expect("normals");
                assert!(max_diff(&n, &wn) <= 1e-3, "normals of job {j}");
            }
            assert!(
                !engine.info().degraded,
                "{:?}",
                engine.info().degraded_reason
            );
        }
        let jobs = random_jobs(&rig, 99, 6);
        let got = engine.evaluate(&prepared, &jobs, spec).expect("read back");
        assert_eq!(got.kind, Some(BackendKind::Gpu));
        assert!(!engine.info().degraded);
    }
);

gpu_test!(
    #[test]
    fn gpu_plays_each_node_with_its_own_weights() {
        // Per-node channels are ordinary weight rows: the GPU engine, unchanged, follows the
        // independent glTF evaluator as the CPU engine does.
        use crate::channels::{Case, check_against_reference};
        let engine = Engine::with_gpu(open_gpu(GpuOptions::default()), BackendChoice::Gpu);
        for case in [
            Case::HeadOnly("CUBICSPLINE"),
            Case::HeadOnly("STEP"),
            Case::Different,
            Case::Shared,
        ] {
            check_against_reference(&engine, case);
            assert!(
                !engine.info().degraded,
                "{case:?}: {:?}",
                engine.info().degraded_reason
            );
        }
    }
);

gpu_test!(
    #[test]
    fn the_gpu_memory_budget_refuses_rigs_over_it_and_gets_back_a_dropped_rigs_memory() {
        use crowdmorph::budget::BudgetError;
        use crowdmorph::engine::EngineError;
        let rig = Arc::new(crowdmorph::embedded::default_rig());
        // What the rig holds on the device, under the default budget.
        let probe = Engine::with_gpu(open_gpu(GpuOptions::default()), BackendChoice::Gpu);
        let memory = probe.gpu_memory().expect("gpu").clone();
        let before = memory.used();
        let prepared = probe.prepare(rig.clone()).expect("upload");
        let bytes = memory.used() - before;
        assert!(
            bytes > 0 && bytes >= prepared.memory().device_bytes as u64,
            "charged {bytes}, resident {}",
            prepared.memory().device_bytes
        );
        drop(prepared);
        assert_eq!(
            memory.used(),
            before,
            "a dropped rig gives its GPU memory back"
        );

        // A budget smaller than the rig's vertex data: refused, naming the flag, nothing left
        // charged, and the device is fine.
        let small = Engine::with_gpu(
            open_gpu(GpuOptions {
                memory: Some(64 << 10),
                ..GpuOptions::default()
            }),
            BackendChoice::Gpu,
        );
        let e = small.prepare(rig.clone()).expect_err("over the budget");
        assert!(
            matches!(e, EngineError::GpuMemory(BudgetError::TooLarge { .. })),
            "{e:?}"
        );
        assert!(e.to_string().contains("--max-gpu-memory"), "{e}");
        assert_eq!(small.gpu_memory().expect("gpu").used(), 0);
        assert!(!small.info().degraded, "a refusal is not a device fault");

        // Room for one copy of the rig, not two: the second is refused while the first is
        // resident, and fits once it is gone.
        let one = Engine::with_gpu(
            open_gpu(GpuOptions {
                memory: Some(bytes + bytes / 2),
                ..GpuOptions::default()
            }),
            BackendChoice::Gpu,
        );
        let first = one.prepare(rig.clone()).expect("the first fits");
        let e = one.prepare(rig.clone()).expect_err("no room for a second");
        assert!(
            matches!(e, EngineError::GpuMemory(BudgetError::Full { .. })),
            "{e:?}"
        );
        drop(first);
        let second = one
            .prepare(rig.clone())
            .expect("fits once the first is dropped");

        // A batch whose buffers do not fit next to the rig runs on the CPU, with the same answer,
        // and leaves the GPU engine in use.
        let jobs = random_jobs(&rig, 5, 64);
        let spec = OutputSpec {
            normals: true,
            precision: Precision::F32,
        };
        let tight = Engine::with_gpu(
            open_gpu(GpuOptions {
                memory: Some(bytes + 1024),
                ..GpuOptions::default()
            }),
            BackendChoice::Gpu,
        );
        let resident = tight.prepare(rig.clone()).expect("the rig fits");
        assert_eq!(tight.cpu_fallbacks(), 0);
        let got = tight.evaluate(&resident, &jobs, spec).expect("evaluated");
        assert_eq!(got.kind, Some(BackendKind::Cpu), "the batch ran on the CPU");
        assert!(!tight.info().degraded, "{:?}", tight.info().degraded_reason);
        // Counted (for crowdmorph_gpu_fallbacks_total), each time.
        assert_eq!(tight.cpu_fallbacks(), 1);
        tight.evaluate(&resident, &jobs, spec).expect("again");
        assert_eq!(tight.cpu_fallbacks(), 2);
        let cpu = Engine::cpu();
        let want = cpu
            .evaluate(&cpu.prepare(rig.clone()).expect("prepare"), &jobs, spec)
            .expect("cpu");
        assert_eq!(got.output, want.output);
        drop(second);

        // Idle batch slots kept for reuse do not hold the budget against rigs: with room for two
        // copies of the rig plus half of one, a batch's pooled slot is given back when a second
        // copy would not fit beside it.
        let slot = {
            let r = probe.prepare(rig.clone()).expect("upload");
            let at = memory.used();
            let out = probe.evaluate(&r, &jobs, spec).expect("evaluated");
            assert_eq!(out.kind, Some(BackendKind::Gpu));
            memory.used() - at
        };
        assert!(
            slot > bytes / 2,
            "the pooled slot ({slot}) is larger than half the rig"
        );
        let pooled = Engine::with_gpu(
            open_gpu(GpuOptions {
                memory: Some(bytes + slot + bytes / 2),
                ..GpuOptions::default()
            }),
            BackendChoice::Gpu,
        );
        let first = pooled.prepare(rig.clone()).expect("the first fits");
        let out = pooled.evaluate(&first, &jobs, spec).expect("evaluated");
        assert_eq!(out.kind, Some(BackendKind::Gpu), "the batch ran on the GPU");
        let second = pooled
            .prepare(rig.clone())
            .expect("the idle slot makes room for a second copy");
        drop((first, second));
        assert_eq!(pooled.gpu_memory().expect("gpu").used(), 0);
    }
);

/// Evaluates `jobs` on `engine` and on the CPU engine, in `spec`, and checks every component
/// within the parity tolerances, and that the GPU read the batch back in `pieces` pieces or
/// more; returns the GPU's output.
fn pieces_match_the_cpu(
    engine: &Engine,
    rig: &Arc<Rig>,
    jobs: &[BlendJob],
    spec: OutputSpec,
    pieces: usize,
) -> crowdmorph::engine::BlendOutput {
    let prepared = engine.prepare(rig.clone()).expect("upload");
    let cpu = Engine::cpu();
    let c = cpu.prepare(rig.clone()).expect("prepare");
    let got = engine.evaluate(&prepared, jobs, spec).expect("gpu");
    assert_eq!(got.kind, Some(BackendKind::Gpu), "{spec:?}: on the GPU");
    assert!(
        got.timings.pieces.is_some_and(|p| p >= pieces),
        "{spec:?}: {:?} pieces",
        got.timings.pieces
    );
    let want = cpu.evaluate(&c, jobs, spec).expect("cpu");
    let diag = rig.bbox().diagonal();
    let (q16_pos, q16_nrm) = match spec.precision {
        Precision::Q16(b) => (
            2.0 * b.max_error.iter().copied().fold(0.0, f32::max),
            2.0 * crowdmorph_proto::Q16_NORMAL_MAX_ERROR,
        ),
        _ => (0.0, 0.0),
    };
    assert_eq!(got.output.jobs, jobs.len());
    for j in 0..jobs.len() {
        let cp = want.output.job_positions(j);
        // f16 may round the other way on one side: one binary16 step more.
        let f16 = if spec.precision == Precision::F16 {
            cp.iter().map(|x| x.abs()).fold(0.0, f32::max) / 1024.0
        } else {
            0.0
        };
        let d = max_diff(&got.output.job_positions(j), &cp);
        assert!(
            d <= 1e-5 * diag + q16_pos + f16,
            "{spec:?} job {j}: positions off by {d:e}"
        );
        if spec.normals {
            let (gn, cn) = (
                got.output.job_normals(j).expect("normals"),
                want.output.job_normals(j).expect("normals"),
            );
            // Recomputed from the skinned positions on both engines (summed in other orders).
            let d = max_diff(&gn, &cn);
            assert!(
                d <= 1e-3 + q16_nrm + if f16 > 0.0 { 1.0 / 1024.0 } else { 0.0 },
                "{spec:?} job {j}: normals off by {d:e}"
            );
        }
    }
    got.output
}

gpu_test!(
    #[test]
    fn batches_past_the_largest_buffer_are_read_back_in_pieces_as_one_batch() {
        // The skinned head (bone matrices per piece, normals recomputed from skinned positions),
        // 25 jobs, with pieces of at most 600,000 bytes of output: three jobs a piece in f32 with
        // normals (174 KB a job), six in q16. Every piece's results land at its jobs' place: the
        // same bytes as one batch on an engine without the limit, and the CPU engine's values.
        let rig = Arc::new(crowdmorph::synthetic::skinned_head());
        assert!(rig.is_skinned());
        let jobs = random_jobs(&rig, 21, 20);
        let pieced = Engine::with_gpu(
            open_gpu(GpuOptions {
                max_piece_bytes: Some(600_000),
                ..GpuOptions::default()
            }),
            BackendChoice::Gpu,
        );
        let whole = Engine::with_gpu(open_gpu(GpuOptions::default()), BackendChoice::Gpu);
        let one = whole.prepare(rig.clone()).expect("upload");
        let qbox = crowdmorph::server::registry::quantization_box(&rig);
        for (spec, pieces) in [
            (
                OutputSpec {
                    normals: true,
                    precision: Precision::F32,
                },
                8,
            ),
            (
                OutputSpec {
                    normals: false,
                    precision: Precision::F32,
                },
                4,
            ),
            (
                OutputSpec {
                    normals: true,
                    precision: Precision::Q16(qbox),
                },
                4,
            ),
            (
                OutputSpec {
                    normals: true,
                    precision: Precision::F16,
                },
                4,
            ),
        ] {
            let got = pieces_match_the_cpu(&pieced, &rig, &jobs, spec, pieces);
            let batch = whole.evaluate(&one, &jobs, spec).expect("one batch");
            assert_eq!(batch.timings.pieces, Some(1));
            assert_eq!(got, batch.output, "{spec:?}: the same bytes as one batch");
        }
        // q16r: the planes the device codes piece by piece are the host's coding of its q16.
        device_codes_residuals(&pieced, (*rig).clone(), &jobs, true);
        device_codes_residuals(&pieced, (*rig).clone(), &jobs, false);
        assert!(
            !pieced.info().degraded,
            "{:?}",
            pieced.info().degraded_reason
        );
    }
);

gpu_test!(
    #[test]
    fn a_batch_over_the_memory_budgets_room_runs_in_pieces_on_the_gpu() {
        // The embedded head's rig plus 6 MB of budget, and a batch of 200 jobs with normals
        // (35 MB of staging): before pieces it ran on the CPU; now each piece's slot fits half the
        // room, so two are alive at once, and it stays on the GPU.
        let rig = Arc::new(crowdmorph::embedded::default_rig());
        let probe = Engine::with_gpu(open_gpu(GpuOptions::default()), BackendChoice::Gpu);
        let memory = probe.gpu_memory().expect("gpu").clone();
        let before = memory.used();
        let prepared = probe.prepare(rig.clone()).expect("upload");
        let bytes = memory.used() - before;
        drop(prepared);
        let tight = Engine::with_gpu(
            open_gpu(GpuOptions {
                memory: Some(bytes + (6 << 20)),
                ..GpuOptions::default()
            }),
            BackendChoice::Gpu,
        );
        let jobs = random_jobs(&rig, 8, 160);
        assert_eq!(jobs.len(), 200);
        let spec = OutputSpec {
            normals: true,
            precision: Precision::F32,
        };
        pieces_match_the_cpu(&tight, &rig, &jobs, spec, 6);
        assert_eq!(tight.cpu_fallbacks(), 0);
        assert!(!tight.info().degraded, "{:?}", tight.info().degraded_reason);
    }
);

gpu_test!(
    #[test]
    fn outputs_kept_on_the_device_are_computed_in_pieces_into_one_buffer() {
        // Without readback only the bone matrices bound a piece: 2,000 bytes hold four jobs' of
        // the skinned head's five bones (96 bytes each: 480 a job), so 9 jobs take three pieces,
        // each copied to its jobs' place in the one resident buffer.
        let rig = Arc::new(crowdmorph::synthetic::skinned_head());
        let engine = Engine::with_gpu(
            open_gpu(GpuOptions {
                max_piece_bytes: Some(2000),
                ..GpuOptions::default()
            }),
            BackendChoice::Gpu,
        );
        let prepared = engine.prepare(rig.clone()).expect("upload");
        let jobs = random_jobs(&rig, 4, 8);
        assert!(jobs.len() >= 9);
        let (buffers, timings) = engine
            .evaluate_for_render(&prepared, &jobs)
            .expect("evaluate");
        assert!(
            timings.pieces.is_some_and(|p| p >= 3),
            "{:?} pieces",
            timings.pieces
        );
        let crowdmorph::engine::RenderBuffers::Device(out) = buffers else {
            panic!("a healthy GPU engine leaves render outputs on the device");
        };
        let cpu = Engine::cpu();
        let c = cpu.prepare(rig.clone()).expect("prepare");
        let spec = OutputSpec {
            normals: true,
            precision: Precision::F32,
        };
        let want = cpu.evaluate(&c, &jobs, spec).expect("cpu");
        let ctx = engine.gpu().expect("gpu");
        let (diag, v3) = (rig.bbox().diagonal(), rig.vertex_count() * 3);
        for j in 0..jobs.len() {
            let p = read_back(ctx, &out.positions, out.offset(j), v3);
            let d = max_diff(&p, &want.output.job_positions(j));
            assert!(d <= 1e-5 * diag, "job {j}: positions off by {d:e}");
            let n = read_back(
                ctx,
                out.normals.as_ref().expect("normals"),
                out.offset(j),
                v3,
            );
            let d = max_diff(&n, &want.output.job_normals(j).expect("normals"));
            assert!(d <= 1e-3, "job {j}: normals off by {d:e}");
        }
        assert!(
            !engine.info().degraded,
            "{:?}",
            engine.info().degraded_reason
        );
    }
);
