//! The CPU engine against the f64 dense evaluation, for every real rig, the embedded head and
//! random rigs; every kernel family this CPU has; f32, f16 and q16; positions and normals;
//! mixed clips, frames and LODs with clones; the 16-bit formats bit for bit against the
//! scalar encoding of the same family's f32 output; a job alone and in a batch.
//!
//! Tolerances: positions within 1e-5 × the rig's bounding-box diagonal (f32). binary16 keeps
//! 11 significant bits, so f16 positions are allowed an extra `max |coordinate| × 2^-11`, and
//! f16 normals an extra 2^-11; q16 positions the box's stated `max_error`, q16 normals
//! 1/65534. Normals are unit vectors: within 1e-4 when blended from normal deltas, 1e-3 when
//! recomputed from blended f32 positions (cross products of short edges).

use crowdmorph::engine::cpu::{CpuRig, Isa};
use crowdmorph::engine::{
    BlendJob, BlendOutput, OutputSpec, Precision, Q16Scale, Quantization, VertexData, WeightBatch,
};
use crowdmorph::import::{ImportOptions, load_path};
use crowdmorph::rig::Rig;
use glam::DVec3;

use crate::util::{RefDoc, Rng, effective_weights, max_abs_diff, ref_eval, rig_files, rig_oracle};

const F16_REL: f64 = 1.0 / 2048.0;

/// Jobs for a rig: clips, frames and LODs at random, with clones (repeated jobs).
fn random_jobs(rig: &Rig, rng: &mut Rng, n: usize) -> Vec<BlendJob> {
    let mut jobs: Vec<BlendJob> = (0..n)
        .map(|_| {
            let clip = rng.below(rig.clips.len());
            BlendJob::frame(
                clip as u32,
                rng.below(rig.clips[clip].frames as usize) as u32,
                rng.below(rig.lod.levels.len()) as u32,
            )
        })
        .collect();
    // Clones: the engine evaluates what it is given; repeated jobs must come out identical.
    jobs.extend_from_slice(&jobs.clone()[..n / 3]);
    jobs
}

/// Per-job weights by target id (the clip's, or random when the rig has no clips) and the
/// batch that asks for them.
fn workload(rig: &Rig, seed: u64, n: usize) -> (Vec<(Vec<f64>, u32)>, WeightBatch) {
    let mut rng = Rng(seed);
    if rig.clips.is_empty() {
        let per_job: Vec<(Vec<f64>, u32)> = (0..n)
            .map(|_| {
                let w = (0..rig.targets.len())
                    .map(|_| {
                        if rng.below(4) == 0 {
                            0.0
                        } else {
                            rng.f64() * 1.2 - 0.1
                        }
                    })
                    .collect();
                (w, rng.below(rig.lod.levels.len()) as u32)
            })
            .collect();
        // One single-job batch per job, concatenated: each job keeps its own LOD.
        let mut batch = WeightBatch {
            slots: rig.targets.len(),
            weights: Vec::new(),
            shapes: Vec::new(),
            skin: None,
        };
        for (w, lod) in &per_job {
            let w32: Vec<f32> = w.iter().map(|&x| x as f32).collect();
            let b = WeightBatch::from_target_weights(rig, &[w32], *lod).expect("batch");
            batch.weights.extend(b.weights);
            batch.shapes.extend(b.shapes);
        }
        (per_job, batch)
    } else {
        let jobs = random_jobs(rig, &mut rng, n);
        let per_job = jobs
            .iter()
            .map(|j| {
                let w = (0..rig.targets.len())
                    .map(|t| j.pose.weight(rig, t) as f64)
                    .collect();
                (w, j.lod)
            })
            .collect();
        (per_job, WeightBatch::gather(rig, &jobs).expect("gather"))
    }
}

/// Compares one job's output with expected positions and normals.
fn check_job(
    ctx: &str,
    out: &BlendOutput,
    j: usize,
    want_p: &[DVec3],
    want_n: &[DVec3],
    diag: f64,
    recomputed: bool,
) {
    let pos_tol = pos_tol(out, want_p, diag);
    let nrm_tol = if recomputed { 1e-3 } else { 1e-4 }
        + match out.positions {
            VertexData::F32(_) => 0.0,
            VertexData::F16(_) => F16_REL,
            VertexData::Q16(..) => f64::from(crowdmorph_proto::Q16_NORMAL_MAX_ERROR),
        };
    let dp = max_abs_diff(&out.job_positions(j), want_p);
    assert!(
        dp <= pos_tol,
        "{ctx} job {j}: positions differ by {dp:e} (tolerance {pos_tol:e})"
    );
    let dn = max_abs_diff(&out.job_normals(j).expect("normals"), want_n);
    assert!(
        dn <= nrm_tol,
        "{ctx} job {j}: normals differ by {dn:e} (tolerance {nrm_tol:e})"
    );
}

/// Tolerance of positions in `out`'s format against the f64 oracle.
fn pos_tol(out: &BlendOutput, want_p: &[DVec3], diag: f64) -> f64 {
    let max_coord = want_p
        .iter()
        .map(|p| p.abs().max_element())
        .fold(0.0, f64::max);
    1e-5 * diag
        + match &out.positions {
            VertexData::F32(_) => 0.0,
            VertexData::F16(_) => max_coord * F16_REL,
            VertexData::Q16(_, Q16Scale::Box(b)) => {
                f64::from(b.max_error.iter().copied().fold(0.0, f32::max))
            }
            VertexData::Q16(_, Q16Scale::Unit) => panic!("positions in the normals' scale"),
        }
}

/// The q16 box of a workload: the rig's own (every clip frame) when the jobs come from its
/// clips; for random weights, a box around the expected positions built as the registry
/// builds one (a relative margin, then `max_error = step / 2` plus 8 units in the last place
/// of the largest coordinate).
fn test_box(rig: &Rig, expected: &[(Vec<DVec3>, Vec<DVec3>)]) -> Quantization {
    if !rig.clips.is_empty() {
        return crowdmorph::server::registry::quantization_box(rig);
    }
    let (lo, hi) = expected.iter().flat_map(|(p, _)| p).fold(
        (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
        |(lo, hi), p| (lo.min(*p), hi.max(*p)),
    );
    let margin = (hi - lo).length().max(1e-30) * 1e-4;
    let (lo, hi) = (lo - DVec3::splat(margin), hi + DVec3::splat(margin));
    let step = ((hi - lo) / 65535.0).as_vec3().to_array();
    let ulp = lo.abs().max(hi.abs()) * f64::from(f32::EPSILON) * 8.0;
    Quantization {
        min: lo.as_vec3().to_array(),
        step,
        max_error: [0, 1, 2].map(|a| (f64::from(step[a]) * 0.5 + ulp[a]) as f32),
    }
}

fn specs(q: Quantization) -> [OutputSpec; 5] {
    [
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
        OutputSpec {
            normals: true,
            precision: Precision::Q16(q),
        },
        OutputSpec {
            normals: false,
            precision: Precision::Q16(q),
        },
    ]
}

#[test]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
fn cpu_engine_matches_f64_dense_evaluation_of_every_file() {
    let files = rig_files();
    for path in files {
        let name = path.file_name().unwrap().to_string_lossy().to_string();
        let rig = load_path(&path, &ImportOptions::default()).expect("load");
        let doc = RefDoc::load(&path);
        let prims = doc.scene_primitives();
        let diag = rig.bbox().diagonal() as f64;
        let n_jobs = if rig.vertex_count() > 10_000 { 6 } else { 24 };
        let (per_job, batch) = workload(&rig, 7, n_jobs);
        // Expected output per job, straight from the file's arrays in f64.
        let expected: Vec<(Vec<DVec3>, Vec<DVec3>)> = per_job
            .iter()
            .map(|(w, lod)| {
                let eff = effective_weights(&rig, w, *lod);
                let mut p = Vec::new();
                let mut n = Vec::new();
                for prim in &prims {
                    let pw: Vec<f64> = prim
                        .target_names
                        .iter()
                        .map(|tn| eff[rig.target_id(tn).expect("target") as usize])
                        .collect();
                    let (pp, nn) = ref_eval(prim, &pw);
                    p.extend(pp);
                    n.extend(nn);
                }
                (p, n)
            })
            .collect();
        let recomputed =
            !rig.has_normal_deltas() && rig.primitives.iter().any(|p| !p.targets.is_empty());
        let qbox = test_box(&rig, &expected);
        for isa in Isa::available() {
            let cpu = CpuRig::with_isa(&rig, isa);
            for spec in specs(qbox) {
                let out = cpu.evaluate(&batch, spec).expect("evaluate");
                assert_eq!(out.jobs, per_job.len());
                for (j, (p, n)) in expected.iter().enumerate() {
                    let ctx = format!("{name} {} {spec:?}", isa.name());
                    if spec.normals {
                        check_job(&ctx, &out, j, p, n, diag, recomputed);
                    } else {
                        let d = max_abs_diff(&out.job_positions(j), p);
                        let tol = pos_tol(&out, p, diag);
                        assert!(d <= tol, "{ctx} job {j}: {d:e} > {tol:e}");
                        assert!(out.normals.is_none(), "normals were not asked for");
                    }
                }
            }
        }
    }
}

/// Checks a file-less rig against the oracle computed from its own arrays.
fn check_rig_against_oracle(rig: &Rig, seed: u64, n_jobs: usize) {
    let diag = rig.bbox().diagonal() as f64;
    let (per_job, batch) = workload(rig, seed, n_jobs);
    let expected: Vec<_> = per_job
        .iter()
        .map(|(w, lod)| rig_oracle(rig, &effective_weights(rig, w, *lod)))
        .collect();
    let recomputed = !rig.has_normal_deltas();
    let qbox = test_box(rig, &expected);
    for isa in Isa::available() {
        let cpu = CpuRig::with_isa(rig, isa);
        for spec in specs(qbox) {
            let out = cpu.evaluate(&batch, spec).expect("evaluate");
            for (j, (p, n)) in expected.iter().enumerate() {
                let ctx = format!("{} {} {spec:?}", rig.name, isa.name());
                if spec.normals {
                    check_job(&ctx, &out, j, p, n, diag, recomputed);
                } else {
                    let d = max_abs_diff(&out.job_positions(j), p);
                    let tol = pos_tol(&out, p, diag);
                    assert!(d <= tol, "{ctx} job {j}: {d:e} > {tol:e}");
                }
            }
        }
    }
}

#[test]
fn cpu_engine_matches_oracle_on_the_embedded_head() {
    let rig = crowdmorph::embedded::default_rig();
    check_rig_against_oracle(&rig, 11, 40);
}

#[test]
fn cpu_engine_matches_oracle_on_random_rigs() {
    // Sizes straddle tile boundaries; one rig has normal deltas on some primitives only.
    for (seed, sizes, targets) in [
        (1, vec![1usize, 15, 16, 17], 5),
        (2, vec![3, 250, 33], 40),
        (3, vec![1000], 70),
        (4, vec![47, 64, 9, 200, 31], 12),
    ] {
        let rig = crate::util::random_rig(seed, &sizes, targets);
        check_rig_against_oracle(&rig, seed * 101, 37);
    }
}

#[test]
fn inactive_weights_leave_the_neutral_mesh_bitwise() {
    let rig = crowdmorph::embedded::default_rig();
    let tiny = vec![
        vec![1e-7f32; rig.targets.len()],
        vec![0.0; rig.targets.len()],
    ];
    let batch = WeightBatch::from_target_weights(&rig, &tiny, 0).expect("batch");
    assert_eq!(
        batch.active_pairs(),
        0,
        "weights at or below 1e-6 are inactive"
    );
    let out = CpuRig::new(&rig)
        .evaluate(&batch, OutputSpec::default())
        .expect("evaluate");
    let base: Vec<f32> = rig
        .primitives
        .iter()
        .flat_map(|p| p.positions.iter().flat_map(|v| v.to_array()))
        .collect();
    assert_eq!(out.job_positions(0), base);
    assert_eq!(out.job_positions(1), base);
}

#[test]
fn every_kernel_family_agrees_and_clones_are_identical() {
    let rig = crate::util::random_rig(9, &[301, 77], 30);
    let mut rng = Rng(5);
    let jobs = random_jobs(&rig, &mut rng, 30);
    let batch = WeightBatch::gather(&rig, &jobs).expect("gather");
    let outs: Vec<BlendOutput> = Isa::available()
        .into_iter()
        .map(|isa| {
            CpuRig::with_isa(&rig, isa)
                .evaluate(&batch, OutputSpec::default())
                .expect("evaluate")
        })
        .collect();
    for (i, j) in jobs.iter().enumerate() {
        // A clone (same job later in the list) is bitwise the same buffer content.
        if let Some(first) = jobs.iter().position(|k| k == j) {
            assert_eq!(outs[0].job_positions(i), outs[0].job_positions(first));
        }
        // Every family sums the same terms in the same order with fused multiply-adds, so they
        // agree bit for bit (Portable's unfused sums were up to 1e-6 × diagonal off).
        for o in &outs[1..] {
            let a = outs[0].job_positions(i);
            let b = o.job_positions(i);
            let differ = a
                .iter()
                .zip(&b)
                .filter(|(x, y)| x.to_bits() != y.to_bits())
                .count();
            assert_eq!(differ, 0, "job {i}: kernel families disagree");
        }
    }
    // The skin in the output stage too: a skinned face, posed and at rest (the rest pose's
    // q16 is the reference of q16r residuals, which must not depend on the CPU).
    let rig = crowdmorph::synthetic::skinned_head();
    let talk = rig.clip_index("talk").expect("talk") as u32;
    let zero = crowdmorph::rig::Pose::live(&vec![0.0; rig.targets.len()]);
    let jobs = [
        BlendJob::frame(talk, 10, 0),
        BlendJob::frame(talk, 77, 0),
        BlendJob::posed(zero, 0),
    ];
    let batch = WeightBatch::gather(&rig, &jobs).expect("gather");
    let outs: Vec<Vec<u32>> = Isa::available()
        .into_iter()
        .map(|isa| {
            let out = CpuRig::with_isa(&rig, isa)
                .evaluate(&batch, OutputSpec::default())
                .expect("evaluate");
            out.positions.to_f32().iter().map(|x| x.to_bits()).collect()
        })
        .collect();
    for o in &outs[1..] {
        assert!(o == &outs[0], "kernel families skin differently");
    }
}

#[test]
fn output_buffers_are_reused_across_batches() {
    let rig = crowdmorph::embedded::default_rig();
    let cpu = CpuRig::new(&rig);
    let mut out = BlendOutput::default();
    let job = |frame| BlendJob::frame(0, frame, 0);
    let big = WeightBatch::gather(&rig, &[job(1), job(2), job(3)]).expect("gather");
    cpu.evaluate_into(&big, OutputSpec::default(), &mut out)
        .expect("evaluate");
    let small = WeightBatch::gather(&rig, &[job(2)]).expect("gather");
    cpu.evaluate_into(&small, OutputSpec::default(), &mut out)
        .expect("evaluate");
    assert_eq!(out.jobs, 1);
    assert_eq!(out.positions.len(), rig.vertex_count() * 3);
    let fresh = cpu
        .evaluate(&small, OutputSpec::default())
        .expect("evaluate");
    assert_eq!(out, fresh);
}

#[test]
fn reused_buffers_holding_other_values_come_out_as_fresh_ones_in_every_format() {
    // The engine does not clear a reused buffer before the kernel writes it: a buffer whose
    // spare room holds NaN (a bigger batch's old output, then a small batch) grown for a
    // bigger batch again must come out bitwise equal to a fresh evaluation.
    let poisoned = |n: usize| -> (Vec<f32>, Vec<half::f16>, Vec<i16>) {
        let mut f = vec![f32::NAN; n];
        let mut h = vec![half::f16::NAN; n];
        let mut q = vec![i16::MIN; n];
        f.truncate(3);
        h.truncate(3);
        q.truncate(3);
        (f, h, q)
    };
    for (r, rig) in format_rigs().iter().enumerate() {
        let cpu = CpuRig::new(rig);
        let q = crowdmorph::server::registry::quantization_box(rig);
        let mut rng = Rng(0xB0FF + r as u64);
        let jobs = random_jobs(rig, &mut rng, 19);
        let batch = WeightBatch::gather(rig, &jobs).expect("gather");
        let n = 19 * rig.vertex_count() * 3;
        let f16 = OutputSpec {
            normals: false,
            precision: Precision::F16,
        };
        for spec in specs(q).into_iter().chain([f16]) {
            let fresh = cpu.evaluate(&batch, spec).expect("evaluate");
            let (f, h, qv) = poisoned(n);
            let data = |kind: &VertexData| match kind {
                VertexData::F32(_) => VertexData::F32(f.clone()),
                VertexData::F16(_) => VertexData::F16(h.clone()),
                VertexData::Q16(_, s) => VertexData::Q16(qv.clone(), *s),
            };
            let mut out = BlendOutput {
                positions: data(&fresh.positions),
                normals: fresh.normals.as_ref().map(data),
                ..BlendOutput::default()
            };
            cpu.evaluate_into(&batch, spec, &mut out).expect("evaluate");
            assert!(out == fresh, "rig {r}, {spec:?}");
        }
    }
}

/// Rigs for the format and batch tests: the embedded head (normals recomputed from the blended
/// positions) and random rigs with normal deltas on some primitives (normals blended in the
/// kernel) whose sizes straddle tiles.
fn format_rigs() -> Vec<Rig> {
    vec![
        crowdmorph::embedded::default_rig(),
        crate::util::random_rig(21, &[17, 250, 33], 40),
        crate::util::random_rig(22, &[1000], 12),
        interleaved_rig(&[700, 300, 45], 8, false).0,
    ]
}

#[test]
fn wire_formats_are_the_f32_blend_encoded_bit_for_bit_in_every_family() {
    // The kernel's output stage encodes from the registers the f32 path stores, with the
    // scalar reference's arithmetic: for every family, f16 and q16 outputs must be exactly
    // `VertexData::encode` of that family's f32 output, positions and normals.
    for rig in format_rigs() {
        let (per_job, batch) = workload(&rig, 31, 21);
        let expected: Vec<_> = per_job
            .iter()
            .map(|(w, lod)| rig_oracle(&rig, &effective_weights(&rig, w, *lod)))
            .collect();
        let qbox = test_box(&rig, &expected);
        for isa in Isa::available() {
            let cpu = CpuRig::with_isa(&rig, isa);
            for normals in [true, false] {
                let f = cpu
                    .evaluate(
                        &batch,
                        OutputSpec {
                            normals,
                            precision: Precision::F32,
                        },
                    )
                    .expect("f32");
                let VertexData::F32(fp) = &f.positions else {
                    panic!("f32 asked");
                };
                for precision in [Precision::F16, Precision::Q16(qbox)] {
                    let ctx = format!(
                        "{} {} {precision:?} normals {normals}",
                        rig.name,
                        isa.name()
                    );
                    let o = cpu
                        .evaluate(&batch, OutputSpec { normals, precision })
                        .expect("evaluate");
                    assert!(o.positions.is_kind(precision), "{ctx}");
                    assert!(
                        o.positions == VertexData::encode(fp, precision, false),
                        "{ctx}: positions differ from the encoded f32 blend"
                    );
                    match (&o.normals, &f.normals) {
                        (Some(got), Some(VertexData::F32(fnrm))) => assert!(
                            *got == VertexData::encode(fnrm, precision, true),
                            "{ctx}: normals differ from the encoded f32 blend"
                        ),
                        (None, None) => {}
                        _ => panic!("{ctx}: normals asked {normals}"),
                    }
                }
            }
        }
    }
}

#[test]
fn a_job_alone_equals_the_same_job_in_any_batch() {
    // Batches of 1 to 13 jobs take the kernels' 8-, 4-, 2- and 1-job paths; each job's sum
    // runs over the same blocks in the same order on every path, so the bits agree.
    for rig in format_rigs() {
        let (_, batch) = workload(&rig, 41, 13);
        for isa in Isa::available() {
            let cpu = CpuRig::with_isa(&rig, isa);
            let spec = OutputSpec {
                normals: true,
                precision: Precision::F32,
            };
            let all = cpu.evaluate(&batch, spec).expect("batch");
            for n in 1..=batch.jobs() {
                let part = WeightBatch {
                    slots: batch.slots,
                    weights: batch.weights[..n * batch.slots].to_vec(),
                    shapes: batch.shapes[..n].to_vec(),
                    skin: None,
                };
                let some = cpu.evaluate(&part, spec).expect("part");
                for j in 0..n {
                    assert_eq!(
                        some.job_positions(j),
                        all.job_positions(j),
                        "{} {}: job {j} of {n}",
                        rig.name,
                        isa.name()
                    );
                    assert_eq!(some.job_normals(j), all.job_normals(j));
                }
            }
        }
    }
}

/// A rig whose supports are interleaved: target `t` moves the vertices `v` with
/// `v % stride == t % stride` of every primitive, so every tile of sixteen consecutive vertices
/// is moved by `stride` targets, each in a few of its lanes (the worst case for a layout in
/// vertex order). With `grouped`, each primitive's vertices are renumbered so that those moved
/// by the same targets are consecutive (triangles keep their order); the second return value
/// maps each old global vertex index to its new one. Primitive 1 carries normal deltas, the
/// others have their normals recomputed; sizes straddle chunks and tiles.
fn interleaved_rig(sizes: &[usize], stride: usize, grouped: bool) -> (Rig, Vec<usize>) {
    use crowdmorph::rig::{Primitive, sparsify, vertex_normals};
    use glam::Vec3;
    let n_targets = 2 * stride + 1;
    let mut rng = Rng(77);
    let dirs: Vec<Vec3> = (0..n_targets)
        .map(|_| {
            Vec3::new(
                rng.f64() as f32 - 0.5,
                rng.f64() as f32 - 0.5,
                rng.f64() as f32 - 0.5,
            )
        })
        .collect();
    let mut primitives = Vec::new();
    let mut map = Vec::new();
    let mut first = 0;
    for (pi, &n) in sizes.iter().enumerate() {
        let mut old: Vec<usize> = (0..n).collect();
        if grouped {
            old.sort_by_key(|&i| (i % stride, i));
        }
        let mut new_of = vec![0; n];
        for (new, &o) in old.iter().enumerate() {
            new_of[o] = new;
        }
        map.extend(new_of.iter().map(|&v| first + v));
        first += n;
        let position = |i: usize| {
            let a = i as f32 * 0.37;
            Vec3::new(a.cos() * (1.0 + i as f32 * 1e-3), a.sin(), i as f32 * 1e-3)
        };
        let positions: Vec<Vec3> = old.iter().map(|&i| position(i)).collect();
        let indices: Vec<u32> = (0..n.saturating_sub(2))
            .flat_map(|i| [i, i + 1, i + 2])
            .map(|i| new_of[i] as u32)
            .collect();
        let normals = vertex_normals(&positions, &indices);
        let mut targets = Vec::new();
        // The last target moves every vertex, so tiles also share a slot.
        for (t, dir) in dirs.iter().enumerate() {
            let dp: Vec<Vec3> = old
                .iter()
                .map(|&i| {
                    if t == n_targets - 1 || i % stride == t % stride {
                        *dir * (1.0 + (i % 7) as f32 * 0.1)
                    } else {
                        Vec3::ZERO
                    }
                })
                .collect();
            let dn: Vec<Vec3> = dp.iter().map(|d| *d * 0.3).collect();
            let st = sparsify(t as u32, &dp, (pi == 1).then_some(&dn[..]), None, 1e-6);
            if !st.vertices.is_empty() {
                targets.push(st);
            }
        }
        primitives.push(Primitive {
            name: format!("p{pi}"),
            positions,
            normals,
            normals_from_file: false,
            tangents: None,
            indices,
            targets,
            base_color: Primitive::default_base_color(),
            skin: None,
            look: Default::default(),
        });
    }
    let name = format!("interleaved-{}", if grouped { "grouped" } else { "raw" });
    let rig = crate::util::rig_with_random_clip(name, primitives, n_targets, 10, 4, &mut rng);
    rig.validate().expect("interleaved rig is valid");
    (rig, map)
}

#[test]
fn vertices_regrouped_in_the_layout_come_out_in_vertex_order() {
    // 700 + 300 + 45 vertices: four chunks of 256, the last one short and ending in a partial
    // tile; chunks span primitive boundaries.
    let sizes = [700, 300, 45];
    let (raw, _) = interleaved_rig(&sizes, 8, false);
    let (grouped, map) = interleaved_rig(&sizes, 8, true);
    for isa in Isa::available() {
        let cpu = CpuRig::with_isa(&raw, isa);
        // In vertex order each tile holds nine blocks of which eight are an eighth full; the
        // layout regroups the chunks' vertices so tiles hold one interleaved target each.
        assert!(
            cpu.block_fill_in_vertex_order() < 0.25,
            "{}",
            cpu.block_fill_in_vertex_order()
        );
        assert!(cpu.block_fill() > 0.75, "fill {}", cpu.block_fill());
        let (blocks, in_order) = cpu.blocks();
        assert!(
            blocks * 3 < in_order,
            "{blocks} blocks, {in_order} in order"
        );
        // The grouped rig is nearly packed in vertex order already (whatever its layout
        // regroups, it is another order of the same sums): each vertex's nonzero terms come
        // in the same slot order in both layouts, the rest are terms of zero, so the outputs
        // agree bit for bit once the renumbering is undone.
        let reference = CpuRig::with_isa(&grouped, isa);
        let mut rng = Rng(3);
        let jobs = random_jobs(&raw, &mut rng, 19);
        let batch = WeightBatch::gather(&raw, &jobs).expect("gather");
        let spec = OutputSpec {
            normals: true,
            precision: Precision::F32,
        };
        let a = cpu.evaluate(&batch, spec).expect("raw");
        let b = reference.evaluate(&batch, spec).expect("grouped");
        // The same rig without the regrouping: the same bits.
        let plain = CpuRig::in_vertex_order(&raw, isa);
        assert_eq!(plain.blocks().0, in_order);
        for spec in [spec, OutputSpec::default()] {
            assert!(
                plain.evaluate(&batch, spec).expect("vertex order")
                    == cpu.evaluate(&batch, spec).expect("regrouped"),
                "{} {spec:?}: regrouped layout differs from vertex order",
                isa.name()
            );
        }
        for j in 0..jobs.len() {
            let (pa, pb) = (a.job_positions(j), b.job_positions(j));
            let (na, nb) = (
                a.job_normals(j).expect("normals"),
                b.job_normals(j).expect("normals"),
            );
            for (old, &new) in map.iter().enumerate() {
                assert_eq!(
                    pa[3 * old..3 * old + 3],
                    pb[3 * new..3 * new + 3],
                    "{} job {j} vertex {old}: positions",
                    isa.name()
                );
                assert_eq!(
                    na[3 * old..3 * old + 3],
                    nb[3 * new..3 * new + 3],
                    "{} job {j} vertex {old}: normals",
                    isa.name()
                );
            }
        }
    }
    // And both against the f64 oracle in every format.
    check_rig_against_oracle(&raw, 5, 23);
}
