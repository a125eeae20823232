//! `crowdmorph bench cpu`: throughput of the CPU engine against what bounds it, all measured
//! in the same run on the same machine:
//!
//! - the honest dense peer: `C = [W 1] · [D; neutral]`, an sgemm of the same blend (weights
//!   augmented with a column of ones, deltas with the neutral mesh as a last row, so one pass
//!   writes the finished positions) into a reused, warm output buffer; the `gemm` crate
//!   (AVX-512 kernels) and `matrixmultiply` (AVX2) are both timed and the faster is the
//!   baseline;
//! - with `--numpy`, the best numpy blend a user could write (`np.matmul(W, D, out=OUT)` then
//!   `OUT += neutral`, warm, reused output) on the same jobs, in a Python subprocess;
//! - the roofline terms: the multiply-adds the sparse kernel executes at the machine's measured
//!   FMA peak, and the output bytes at the measured copy bandwidth (a parallel copy of the same
//!   bytes between warm buffers);
//! - the wire formats (f32, f16, q16) written by the kernel's output stage;
//! - a clip's frames against four-layer blends of them (what a blend adds to the gather);
//! - on a skinned rig, the blend and skin passes against the blend alone (`--skinned-head` for
//!   the embedded head with five joints);
//! - batches of 1, 10, 100, 1,000 and 4,096 unique jobs per engine call, against the dense
//!   peer at each size, the same kernel without its cache blocking ([`Blocking::NONE`]), and
//!   the roofline at each size (the copy and the kernel's streaming write measured at that
//!   output's size), and the per-call overhead of one job;
//! - LOD: the cost of each level against the deltas it keeps (a least-squares line whose
//!   intercept is the output-write floor), and the simplified meshes' levels, whose outputs
//!   shrink with their vertices;
//! - the PCA level: each full-mesh LOD level against the variable-PCA form of the deltas built
//!   within that level's error (`lod::pca`), its size, multiply-adds and time on the same jobs
//!   (its derived rig on the same CPU engine), and whether it is both smaller and faster.
//!
//! Workload: `unique` distinct jobs whose weights are drawn uniformly from [0.05, 1) for every
//! target (all shapes active: the most expensive case), spread over `heads` heads; head `h`
//! plays job `h mod unique`. Times are medians over repeated runs with warm buffers.

use std::time::Instant;

use anyhow::Result;
use indicatif::ProgressBar;
use rayon::prelude::*;
use serde::Serialize;

use super::sample::{Samples, sample};
use crowdmorph_core::plan::{JobKey, Plan};
use crowdmorph_core::rig::Rig;
use crowdmorph_core::rng::SplitMix64;
use crowdmorph_engine::cpu::{Blocking, CpuRig, fma_probe, stream_probe};
use crowdmorph_engine::{BlendJob, BlendOutput, OutputSpec, Precision, WeightBatch};

/// What to measure (also `crowdmorph bench cpu`'s flags).
#[derive(Clone, Debug, clap::Args)]
pub struct BenchOptions {
    /// Heads in the crowd.
    #[arg(long, default_value_t = 100)]
    pub heads: usize,
    /// Unique jobs among the heads.
    #[arg(long, default_value_t = 100)]
    pub unique: usize,
    /// LOD level.
    #[arg(long, default_value_t = 0)]
    pub lod: u32,
    /// Compute normals too.
    #[arg(long)]
    pub normals: bool,
    /// Delta-block KiB of one span of the kernel's cache blocking (default: half the L2 of a
    /// core; see `cpu::Blocking`).
    #[arg(long)]
    pub span_kib: Option<usize>,
    /// Cut outputs larger than this many MiB into spans (default: the engine's,
    /// `cpu::BLOCKING_MIN_OUTPUT`).
    #[arg(long)]
    pub block_from_mib: Option<usize>,
    /// Unique jobs per engine call of the batch-size table.
    #[arg(long, value_delimiter = ',', default_value = "1,10,100,1000,4096")]
    pub batches: Vec<usize>,
    /// Simplified meshes to build and time when the rig has none (fractions of the
    /// triangles; `none` for none).
    #[arg(long, default_value = "0.5,0.25,0.1", value_parser = super::fractions_arg)]
    pub mesh_fractions: ::std::vec::Vec<f32>,
    /// Seconds per measurement (at least 5 runs each).
    #[arg(long, default_value_t = 1.0)]
    pub seconds: f64,
    /// Show progress bars (the CLI's: unless `--json`).
    #[arg(skip = true)]
    pub progress: bool,
    /// Also time the warm numpy blend (`np.matmul(W, D, out=OUT); OUT += neutral`) on the
    /// same jobs with this Python (default /usr/bin/python3).
    #[arg(long, value_name = "PYTHON", num_args = 0..=1, default_missing_value = "/usr/bin/python3")]
    pub numpy: Option<std::path::PathBuf>,
}

impl Default for BenchOptions {
    fn default() -> Self {
        BenchOptions {
            heads: 100,
            unique: 100,
            lod: 0,
            normals: false,
            span_kib: None,
            block_from_mib: None,
            batches: vec![1, 10, 100, 1000, 4096],
            mesh_fractions: vec![0.5, 0.25, 0.1],
            seconds: 1.0,
            progress: true,
            numpy: None,
        }
    }
}

/// The machine's bounds, measured in the run.
#[derive(Debug, Serialize)]
pub struct Machine {
    /// Multiply-add peak of the kernel family on every worker thread, GFLOP/s.
    pub fma_peak_gflops: f64,
    /// Bytes per second a parallel copy between warm buffers writes, GB/s.
    pub copy_gb_per_s: f64,
}

/// The roofline of the main measurement (f32, `unique` jobs).
#[derive(Debug, Serialize)]
pub struct Roofline {
    /// FLOPs the sparse kernel executes (2 per multiply-add, padding lanes of blocks included).
    pub sparse_gflop: f64,
    /// FLOPs of the stored non-zero deltas alone (what a perfectly packed layout would do).
    pub useful_gflop: f64,
    /// FLOPs of the dense peer (`unique × (targets + 1) × 3V × 2`).
    pub dense_gflop: f64,
    /// Output bytes of the call.
    pub output_bytes: usize,
    /// `sparse_gflop` at the FMA peak, ms.
    pub compute_ms: f64,
    /// `output_bytes` at the copy bandwidth, ms.
    pub write_ms: f64,
    /// The bound with compute and write fully overlapped: `max(compute, write)`.
    pub overlapped_ms: f64,
    /// The bound with no overlap: `compute + write`.
    pub serial_ms: f64,
    /// `overlapped_ms / eval_ms`: how close the engine comes to the ideal.
    pub fraction_of_overlapped: f64,
    /// GFLOP/s the kernel reaches (sparse FLOPs over the measured time).
    pub achieved_gflops: f64,
}

/// The numpy peer: `np.matmul(W, D, out=OUT); OUT += neutral` on the same `unique` jobs, warm
/// and into a reused output (issue 13's honest baseline), timed in a Python subprocess by
/// `clients/python/bench/numpy_blend.py`.
#[derive(Debug, Serialize)]
pub struct NumpyPeer {
    /// The interpreter.
    pub python: String,
    /// numpy's version.
    pub numpy: String,
    /// The BLAS library numpy loaded.
    pub blas: String,
    /// Median ms, warm, reused output.
    pub warm_ms: f64,
    /// Median ms of `W @ D + neutral` allocating its output each time.
    pub alloc_ms: f64,
    /// `warm_ms / eval_ms`: how many times faster the kernel is.
    pub kernel_speedup: f64,
    /// `warm_ms / dense_baseline_ms`: the Rust dense peer against numpy's.
    pub dense_baseline_speedup: f64,
}

/// One wire format through the kernel's output stage.
#[derive(Debug, Serialize)]
pub struct FormatRow {
    /// `f32`, `f16` or `q16`.
    pub format: String,
    /// Median ms for `unique` jobs.
    pub eval_ms: f64,
    /// Unique jobs per second.
    pub unique_heads_per_s: f64,
    /// Bytes of one job's positions (and normals).
    pub bytes_per_head: usize,
    /// `unique_heads_per_s` over f32's.
    pub vs_f32: f64,
}

/// One batch size: unique jobs per engine call.
#[derive(Debug, Serialize)]
pub struct BatchRow {
    /// Unique jobs in the call.
    pub unique: usize,
    /// Median ms of the call (weights gathered, output written).
    pub eval_ms: f64,
    /// Microseconds per job.
    pub us_per_head: f64,
    /// Median ms of the dense peer for the same jobs.
    pub dense_ms: f64,
    /// `dense_ms / eval_ms`.
    pub speedup_vs_dense: f64,
    /// Delta-block bytes of one span of the kernel's cache blocking (0 when this call's
    /// output is small enough to run unblocked).
    pub span_bytes: usize,
    /// Median ms of the same kernel without cache blocking ([`Blocking::NONE`]: one chunk
    /// for every job per unit of work).
    pub unblocked_ms: f64,
    /// `unblocked_ms / eval_ms`: what the blocking gains.
    pub blocking_speedup: f64,
    /// Multiply-adds the kernel executes (sparse FLOPs) at the FMA peak, ms.
    pub compute_ms: f64,
    /// The output's bytes at the copy bandwidth measured at this size (a parallel copy
    /// between warm buffers of the output's size), ms.
    pub write_ms: f64,
    /// The output's bytes written with the kernel's streaming stores and nothing else
    /// (`stream_probe`), ms: the physical limit of the write.
    pub stream_write_ms: f64,
    /// `max(compute_ms, write_ms)`: the overlapped roofline.
    pub overlapped_ms: f64,
    /// `overlapped_ms / eval_ms`.
    pub fraction_of_overlapped: f64,
    /// `max(compute_ms, stream_write_ms) / eval_ms`: against the physical limits.
    pub fraction_of_stream_bound: f64,
}

/// Cost of a LOD level relative to level 0.
#[derive(Debug, Serialize)]
pub struct LodScaling {
    /// LOD level.
    pub level: u32,
    /// Shapes evaluated.
    pub shapes: u32,
    /// Fraction of all stored deltas those shapes hold.
    pub delta_fraction: f64,
    /// Median ms at this level.
    pub eval_ms: f64,
    /// Median evaluation time at this level / at level 0.
    pub cost_ratio: f64,
}

/// `eval_ms ≈ floor_ms + slope_ms × delta_fraction` over the full-mesh levels.
#[derive(Debug, Serialize)]
pub struct LodFit {
    /// Cost with no deltas: writing every output vertex.
    pub floor_ms: f64,
    /// Cost of all the deltas above the floor (ms per 100 % of the deltas).
    pub slope_ms: f64,
    /// Coefficient of determination of the line.
    pub r2: f64,
    /// `floor_ms` over the roofline's `write_ms`.
    pub floor_vs_write: f64,
}

/// A simplified mesh at full shapes.
#[derive(Debug, Serialize)]
pub struct MeshRow {
    /// Fraction of the triangles asked for.
    pub triangle_fraction: f32,
    /// Vertices of the mesh level.
    pub vertices: usize,
    /// Output bytes of `unique` jobs (f32 positions).
    pub output_bytes: usize,
    /// Median ms of `unique` jobs.
    pub eval_ms: f64,
    /// Time relative to the full mesh.
    pub cost_ratio: f64,
    /// Output size relative to the full mesh.
    pub bytes_ratio: f64,
}

/// The bench result, printed as JSON with `--json`.
#[derive(Debug, Serialize)]
pub struct BenchReport {
    /// Rig name.
    pub rig: String,
    /// Vertices per head.
    pub vertices: usize,
    /// Rig targets.
    pub targets: usize,
    /// Heads in the crowd.
    pub heads: usize,
    /// Unique jobs.
    pub unique: usize,
    /// LOD level.
    pub lod: u32,
    /// Shapes evaluated at that level.
    pub shapes: u32,
    /// Output precision of the main measurement.
    pub precision: String,
    /// Normals computed too.
    pub normals: bool,
    /// Kernel family.
    pub isa: String,
    /// Worker threads.
    pub threads: usize,
    /// Fraction of stored block lanes that hold a real delta.
    pub block_fill: f64,
    /// What `block_fill` would be with tiles of consecutive vertices (before the layout
    /// regroups each chunk's vertices).
    pub block_fill_vertex_order: f64,
    /// Median ms of the f32 blend with this layout and with tiles of consecutive vertices,
    /// calls alternating between the two in one loop (the fair comparison under load).
    pub layout_ms: [f64; 2],
    /// Bytes of the CPU layout (neutral and delta blocks), which every call streams once.
    pub layout_bytes: usize,
    /// The machine's measured bounds.
    pub machine: Machine,
    /// Median ms to evaluate the unique jobs (weights gathered, output written), f32.
    pub eval_ms: f64,
    /// Median ms for the whole crowd: planning + evaluation.
    pub crowd_ms: f64,
    /// Unique jobs evaluated per second.
    pub unique_heads_per_s: f64,
    /// Heads served per second (clones included).
    pub heads_per_s: f64,
    /// Evaluation time per (job × vertex × shape), the dense-equivalent work unit.
    pub ns_per_vertex_shape: f64,
    /// Evaluation time per stored non-zero delta per job.
    pub ns_per_delta: f64,
    /// The roofline terms of `eval_ms`.
    pub roofline: Roofline,
    /// The dense peer with the `gemm` crate, median ms.
    pub dense_gemm_ms: f64,
    /// The dense peer with `matrixmultiply`, median ms.
    pub dense_matrixmultiply_ms: f64,
    /// The faster of the two: the dense baseline, median ms.
    pub dense_baseline_ms: f64,
    /// Unique heads per second of the dense baseline.
    pub dense_baseline_heads_per_s: f64,
    /// `unique_heads_per_s / dense_baseline_heads_per_s`.
    pub speedup_vs_dense: f64,
    /// The best numpy blend a user could write, when asked for (`--numpy`).
    pub numpy: Option<NumpyPeer>,
    /// Plain parallel copy of the same output bytes, median ms.
    pub memcpy_ms: f64,
    /// `memcpy_ms / eval_ms`.
    pub fraction_of_memcpy: f64,
    /// The wire formats at `unique` jobs.
    pub formats: Vec<FormatRow>,
    /// `unique` clip frames against `unique` four-layer blends, weights gathered from a table.
    pub blend: BlendRow,
    /// Engine calls of several sizes.
    pub batches: Vec<BatchRow>,
    /// One job per call, median ms.
    pub one_head_ms: f64,
    /// `one_head_ms` less the per-job cost at `unique` jobs: the fixed cost of a call.
    pub one_head_overhead_ms: f64,
    /// Cost of a crowd 10× larger with the same unique jobs, relative to this crowd.
    pub clone_crowd_cost_ratio: f64,
    /// Cost of each LOD level relative to level 0 (full mesh levels).
    pub lod_scaling: Vec<LodScaling>,
    /// The line through `lod_scaling`.
    pub lod_fit: LodFit,
    /// The simplified meshes at all shapes.
    pub mesh_levels: Vec<MeshRow>,
    /// Each full-mesh LOD level against the PCA form within its error.
    pub pca: Vec<PcaRow>,
    /// On a skinned rig, what the skin pass adds to the blend.
    pub skin: Option<SkinRow>,
}

/// What skinning adds on a skinned rig (issue 28's goal: at most 30 % on top of the blend for
/// a five-joint face): `unique` jobs of the rig's clip frames (real poses) evaluated by the
/// rig, and by the same rig with its skeleton removed (the blend alone), alternating in one
/// loop.
#[derive(Clone, Debug, Serialize)]
pub struct SkinRow {
    /// Bones of the skeleton.
    pub bones: usize,
    /// Non-zero influences per vertex, on average.
    pub influences_per_vertex: f64,
    /// Median ms: the blend alone.
    pub blend_ms: f64,
    /// Median ms: blend, then skin.
    pub skinned_ms: f64,
    /// `skinned_ms / blend_ms − 1`.
    pub overhead: f64,
}

/// `rig` without its skeleton: the same blend, no skin pass.
pub(crate) fn without_skeleton(rig: &Rig) -> Rig {
    let mut r = rig.clone();
    r.skeleton = None;
    r.primitives = std::sync::Arc::new(
        rig.primitives
            .iter()
            .map(|p| crowdmorph_core::rig::Primitive {
                skin: None,
                ..p.clone()
            })
            .collect(),
    );
    for c in &mut r.clips {
        c.joints = None;
    }
    r
}

/// Measures [`SkinRow`] on a skinned rig with clips (`None` otherwise).
fn skin_row(
    rig: &Rig,
    cpu: &CpuRig,
    opt: &BenchOptions,
    spec: OutputSpec,
    bar: Option<&ProgressBar>,
) -> Result<Option<SkinRow>> {
    let Some(sk) = &rig.skeleton else {
        return Ok(None);
    };
    let poses: Vec<(u32, u32)> = rig
        .clips
        .iter()
        .enumerate()
        .filter(|(_, c)| c.joints.is_some())
        .flat_map(|(ci, c)| (0..c.frames).map(move |f| (ci as u32, f)))
        .collect();
    if poses.is_empty() {
        return Ok(None);
    }
    let jobs: Vec<BlendJob> = (0..opt.unique)
        .map(|i| {
            let (c, f) = poses[i * poses.len().max(1) / opt.unique.max(1) % poses.len()];
            BlendJob::frame(c, f, opt.lod)
        })
        .collect();
    let plain = without_skeleton(rig);
    let plain_cpu = CpuRig::new(&plain);
    let mut outs = [BlendOutput::default(), BlendOutput::default()];
    let mut times = [Vec::new(), Vec::new()];
    let start = Instant::now();
    for round in 0.. {
        if round >= 7 && (start.elapsed().as_secs_f64() >= 2.0 * opt.seconds || round >= 2000) {
            break;
        }
        for (i, out) in outs.iter_mut().enumerate() {
            let t = Instant::now();
            if i == 0 {
                plain_cpu.evaluate_into(&WeightBatch::gather(&plain, &jobs)?, spec, out)?;
            } else {
                cpu.evaluate_into(&WeightBatch::gather(rig, &jobs)?, spec, out)?;
            }
            if round >= 2 {
                times[i].push(t.elapsed().as_secs_f64() * 1e3);
            }
        }
    }
    if let Some(b) = bar {
        b.inc(2);
    }
    let [blend_ms, skinned_ms] = times.map(|t| Samples::new(t).median());
    let (mut used, mut vertices) = (0usize, 0usize);
    for p in rig.primitives.iter() {
        if let Some(s) = &p.skin {
            used += s.weights.iter().flatten().filter(|&&w| w != 0.0).count();
            vertices += s.weights.len();
        }
    }
    Ok(Some(SkinRow {
        bones: sk.bones.len(),
        influences_per_vertex: used as f64 / vertices.max(1) as f64,
        blend_ms,
        skinned_ms,
        overhead: skinned_ms / blend_ms - 1.0,
    }))
}

/// A LOD level against the variable-PCA form of the deltas built within its error.
#[derive(Debug, Serialize)]
pub struct PcaRow {
    /// Sizes, multiply-adds and errors of the two forms.
    #[serde(flatten)]
    pub level: crowdmorph_engine::lod::pca::PcaLevel,
    /// Median ms of the sparse level (`lod_scaling`).
    pub sparse_ms: f64,
    /// Median ms of the PCA form's rig (`DeltaPca::derive_rig`) on the same jobs, their
    /// weights mapped to its coefficients: the CPU engine and output stage the server runs.
    pub pca_ms: f64,
    /// Whether the PCA form is both smaller and faster (where a LOD table would use it).
    pub pays: bool,
    /// Whether `lod::pca::pays` (the cost model `build_lod` decides with) agrees.
    pub model_pays: bool,
}

/// Measures [`PcaRow`]s for the full-mesh levels of `lod_scaling`.
fn pca_rows(
    rig: &Rig,
    weights: &[Vec<f32>],
    lod_scaling: &[LodScaling],
    spec: OutputSpec,
    seconds: f64,
    bar: Option<&ProgressBar>,
) -> Result<Vec<PcaRow>> {
    let mut rows = Vec::new();
    for (level, form) in
        crowdmorph_engine::lod::pca::compare_levels(rig, crowdmorph_engine::lod::PCA_FLOOR)
    {
        let Some(sparse_ms) = lod_scaling
            .iter()
            .find(|l| l.level == level.level)
            .map(|l| l.eval_ms)
        else {
            continue;
        };
        let derived = form.derive_rig(rig)?;
        let cpu = CpuRig::new(&derived);
        let coefs: Vec<Vec<f32>> = weights.iter().map(|w| form.coefficients(w)).collect();
        let batch = WeightBatch::from_target_weights(&derived, &coefs, 0)?;
        let mut out = BlendOutput::default();
        cpu.evaluate_into(&batch, spec, &mut out)?;
        let pca_ms = median_ms(seconds, bar, &format!("pca {}", level.level), || {
            let _ = cpu.evaluate_into(&batch, spec, &mut out);
        });
        rows.push(PcaRow {
            pays: pca_ms < sparse_ms && level.pca_bytes < level.sparse_bytes,
            model_pays: crowdmorph_engine::lod::pca::pays(
                &form,
                level.sparse_madds,
                level.sparse_bytes,
            ),
            level,
            sparse_ms,
            pca_ms,
        });
    }
    Ok(rows)
}

/// What a four-layer blend adds (GPU Gems 3 ch. 15, blending in weight space): `unique` jobs
/// that each play one frame of a clip against `unique` jobs that each blend five of its frames,
/// both gathered from the clip table as the server gathers them, then evaluated. With
/// all-active random weights the active set does not grow with the blend, so the difference is
/// the gather's; a blend of real frames with different active shapes also pays for the union.
#[derive(Clone, Debug, Serialize)]
pub struct BlendRow {
    /// Median ms: gather and evaluate the frames.
    pub frames_ms: f64,
    /// Median ms: gather and evaluate the blends.
    pub blends_ms: f64,
    /// `blends_ms / frames_ms − 1`.
    pub overhead: f64,
}

/// Measures [`BlendRow`]: `weights` become the frames of a clip of a copy of `rig` (the
/// engine layout `cpu` is shared: a clip does not change geometry).
fn blend_row(
    rig: &Rig,
    cpu: &CpuRig,
    weights: &[Vec<f32>],
    opt: &BenchOptions,
    spec: OutputSpec,
    bar: Option<&ProgressBar>,
) -> Result<BlendRow> {
    let (n, k) = (weights.len(), rig.targets.len());
    let mut table = vec![0f32; k * n];
    for (f, w) in weights.iter().enumerate() {
        for (t, &x) in w.iter().enumerate() {
            table[t * n + f] = x;
        }
    }
    let mut rig = rig.clone();
    rig.clips.push(crowdmorph_core::rig::Clip::new(
        "bench-blend",
        30.0,
        k,
        n,
        table,
    )?);
    let c = (rig.clips.len() - 1) as u32;
    let at = |i: usize| (i % n) as u32;
    let frames: Vec<BlendJob> = (0..n).map(|i| BlendJob::frame(c, at(i), opt.lod)).collect();
    let blends: Vec<BlendJob> = (0..n)
        .map(|i| BlendJob {
            pose: crowdmorph_core::rig::Pose::blend(
                (c, at(i)),
                &[
                    (c, at(i + 1), 0.25),
                    (c, at(i + 2), 0.25),
                    (c, at(i + 3), 0.125),
                    (c, at(i + 4), 0.125),
                ],
            ),
            lod: opt.lod,
            joints: crowdmorph_core::rig::JointPose::NONE,
        })
        .collect();
    // Alternating in one loop, as `layout_ab` does: the two differ by a few per cent, less
    // than the drift between two back-to-back medians on a busy machine.
    let mut outs = [BlendOutput::default(), BlendOutput::default()];
    let mut times = [Vec::new(), Vec::new()];
    let start = Instant::now();
    for round in 0.. {
        if round >= 7 && (start.elapsed().as_secs_f64() >= 2.0 * opt.seconds || round >= 2000) {
            break;
        }
        for (i, (jobs, out)) in [&frames, &blends].into_iter().zip(&mut outs).enumerate() {
            let t = Instant::now();
            cpu.evaluate_into(&WeightBatch::gather(&rig, jobs)?, spec, out)?;
            if round >= 2 {
                times[i].push(t.elapsed().as_secs_f64() * 1e3);
            }
        }
    }
    if let Some(b) = bar {
        b.inc(2);
    }
    let [frames_ms, blends_ms] = times.map(|t| Samples::new(t).median());
    Ok(BlendRow {
        frames_ms,
        blends_ms,
        overhead: blends_ms / frames_ms - 1.0,
    })
}

/// Random all-active weights for `n` jobs, by target id.
pub fn random_weights(rig: &Rig, n: usize, seed: u64) -> Vec<Vec<f32>> {
    let mut rng = SplitMix64(seed);
    (0..n)
        .map(|_| {
            (0..rig.targets.len())
                .map(|_| 0.05 + 0.95 * rng.unit())
                .collect()
        })
        .collect()
}

/// Median of `f`'s wall time in milliseconds ([`sample`]: at least 5 runs, about `seconds`),
/// counted as a step of the progress bar.
fn median_ms(seconds: f64, bar: Option<&ProgressBar>, label: &str, f: impl FnMut()) -> f64 {
    if let Some(b) = bar {
        b.set_message(label.to_string());
    }
    let ms = sample(seconds, 5, f).median();
    if let Some(b) = bar {
        b.inc(1);
    }
    ms
}

/// The dense peer: `[W 1]` (jobs × (K + 1)) and `[D; neutral]` ((K + 1) × 3V), row-major.
struct Dense {
    k1: usize,
    n3: usize,
    /// Deltas of every target, dense, then the neutral positions.
    d: Vec<f32>,
    /// Weights of every job, then 1.
    w: Vec<f32>,
}

impl Dense {
    fn new(rig: &Rig, weights: &[Vec<f32>]) -> Dense {
        let k = rig.targets.len();
        let n3 = rig.vertex_count() * 3;
        let mut d = vec![0f32; (k + 1) * n3];
        let offsets = rig.vertex_offsets();
        for (pi, p) in rig.primitives.iter().enumerate() {
            for (i, x) in p.positions.iter().enumerate() {
                let at = k * n3 + (offsets[pi] + i) * 3;
                d[at..at + 3].copy_from_slice(&x.to_array());
            }
            for t in &p.targets {
                for (i, &vert) in t.vertices.iter().enumerate() {
                    let at = t.target as usize * n3 + (offsets[pi] + vert as usize) * 3;
                    d[at..at + 3].copy_from_slice(&t.positions[i].to_array());
                }
            }
        }
        let w = weights
            .iter()
            .flat_map(|w| w.iter().copied().chain([1.0]))
            .collect();
        Dense {
            k1: k + 1,
            n3,
            d,
            w,
        }
    }

    /// `c[..jobs × 3V] = W[..jobs] · D` with the `gemm` crate on every worker thread.
    fn gemm(&self, jobs: usize, c: &mut [f32]) {
        assert!(c.len() >= jobs * self.n3 && self.w.len() >= jobs * self.k1);
        // SAFETY: the pointers and strides describe the row-major matrices checked above:
        // W is jobs × k1, D is k1 × n3, C is jobs × n3 (column stride 1, row stride n3).
        unsafe {
            gemm::gemm(
                jobs,
                self.n3,
                self.k1,
                c.as_mut_ptr(),
                1,
                self.n3 as isize,
                false,
                self.w.as_ptr(),
                1,
                self.k1 as isize,
                self.d.as_ptr(),
                1,
                self.n3 as isize,
                0.0,
                1.0,
                false,
                false,
                false,
                gemm::Parallelism::Rayon(rayon::current_num_threads()),
            );
        }
    }

    /// The same product with `matrixmultiply` (its own threads).
    fn matrixmultiply(&self, jobs: usize, c: &mut [f32]) {
        assert!(c.len() >= jobs * self.n3 && self.w.len() >= jobs * self.k1);
        // SAFETY: as in `gemm`.
        unsafe {
            matrixmultiply::sgemm(
                jobs,
                self.k1,
                self.n3,
                1.0,
                self.w.as_ptr(),
                self.k1 as isize,
                1,
                self.d.as_ptr(),
                self.n3 as isize,
                1,
                0.0,
                c.as_mut_ptr(),
                self.n3 as isize,
                1,
            );
        }
    }
}

/// GFLOP/s of `isa`'s multiply-adds on every worker thread.
fn fma_peak(isa: crowdmorph_engine::cpu::Isa, seconds: f64, bar: Option<&ProgressBar>) -> f64 {
    let threads = rayon::current_num_threads();
    // About 10 ms per run on a machine near 150 GFLOP/s per thread (AVX-512: 384 FLOP per
    // iteration), long enough that the fork and join of the threads do not count.
    let iterations = 1 << 22;
    let mut flops = 0u64;
    let ms = median_ms(seconds, bar, "fma peak", || {
        flops = (0..threads)
            .into_par_iter()
            .map(|_| fma_probe(isa, iterations))
            .sum();
    });
    flops as f64 / ms / 1e6
}

/// Least squares `y = a + b x`: `(a, b, r²)`.
fn fit_line(points: &[(f64, f64)]) -> (f64, f64, f64) {
    let n = points.len() as f64;
    if points.len() < 2 {
        return (points.first().map_or(0.0, |p| p.1), 0.0, 1.0);
    }
    let (sx, sy) = points
        .iter()
        .fold((0.0, 0.0), |(a, b), p| (a + p.0, b + p.1));
    let (mx, my) = (sx / n, sy / n);
    let sxx: f64 = points.iter().map(|p| (p.0 - mx).powi(2)).sum();
    let sxy: f64 = points.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
    let syy: f64 = points.iter().map(|p| (p.1 - my).powi(2)).sum();
    let b = if sxx > 0.0 { sxy / sxx } else { 0.0 };
    let a = my - b * mx;
    let r2 = if syy > 0.0 {
        (sxy * sxy) / (sxx * syy)
    } else {
        1.0
    };
    (a, b, r2)
}

/// Runs the CPU benchmark.
pub fn bench_cpu(rig: &Rig, opt: &BenchOptions) -> Result<BenchReport> {
    anyhow::ensure!(
        opt.unique >= 1 && opt.heads >= opt.unique,
        "need heads >= unique >= 1"
    );
    anyhow::ensure!(
        opt.batches.iter().all(|&b| b >= 1),
        "batch sizes must be at least 1"
    );
    let cpu = CpuRig::new(rig);
    let blocking = cpu.blocking();
    let cpu = cpu.with_blocking(Blocking {
        span_bytes: opt.span_kib.map_or(blocking.span_bytes, |kib| kib << 10),
        min_output_bytes: opt
            .block_from_mib
            .map_or(blocking.min_output_bytes, |mib| mib << 20),
    });
    let v = rig.vertex_count();
    let k = rig.targets.len();
    let n3 = v * 3;
    let largest = opt
        .batches
        .iter()
        .copied()
        .max()
        .unwrap_or(0)
        .max(opt.unique);
    let weights = random_weights(rig, largest, 0x5EED);
    let qbox = crowdmorph_server::registry::quantization_box(rig);
    let spec_of = |precision: Precision| OutputSpec {
        normals: opt.normals,
        precision,
    };
    let spec = spec_of(Precision::F32);
    let levels = rig.lod.levels.len() as u32;
    let steps = 2 * u64::from(levels) + 5 * opt.batches.len() as u64 + 16;
    let bar = opt.progress.then(|| super::progress_bar(steps, "bench"));
    let bar = bar.as_ref();

    // The machine's bounds.
    let fma_peak_gflops = fma_peak(cpu.isa(), opt.seconds, bar);
    let out_bytes = opt.unique * n3 * 4 * if opt.normals { 2 } else { 1 };
    let src = vec![1u8; out_bytes];
    let mut dst = vec![0u8; out_bytes];
    let memcpy_ms = median_ms(opt.seconds, bar, "memcpy", || {
        dst.par_chunks_mut(1 << 18)
            .zip(src.par_chunks(1 << 18))
            .for_each(|(d, s)| d.copy_from_slice(s));
    });
    drop((src, dst));
    let copy_gb_per_s = out_bytes as f64 / memcpy_ms / 1e6;

    // The crowd: plan, gather, evaluate.
    let mut out = BlendOutput::default();
    let crowd = |heads: usize, out: &mut BlendOutput| -> Result<()> {
        let plan =
            Plan::new((0..heads).map(|h| JobKey::frame(0, 0, (h % opt.unique) as u32, opt.lod)));
        let w: Vec<Vec<f32>> = plan
            .jobs
            .iter()
            .map(|j| match j.pose {
                crowdmorph_core::rig::Pose::Frame { frame, .. } => weights[frame as usize].clone(),
                _ => Vec::new(),
            })
            .collect();
        let batch = WeightBatch::from_target_weights(rig, &w, opt.lod)?;
        cpu.evaluate_into(&batch, spec, out)?;
        Ok(())
    };
    crowd(opt.heads, &mut out)?;
    let crowd_ms = median_ms(opt.seconds, bar, "crowd", || {
        let _ = crowd(opt.heads, &mut out);
    });
    let crowd10_ms = median_ms(opt.seconds, bar, "10x crowd", || {
        let _ = crowd(opt.heads * 10, &mut out);
    });

    // One engine call of `n` unique jobs at `level` in `precision`, weights gathered as the
    // server gathers them (per call).
    let call_on =
        |cpu: &CpuRig, n: usize, level: u32, precision: Precision, label: &str| -> Result<f64> {
            let spec = spec_of(precision);
            let w = &weights[..n];
            let mut out = BlendOutput::default();
            cpu.evaluate_into(
                &WeightBatch::from_target_weights(rig, w, level)?,
                spec,
                &mut out,
            )?;
            Ok(median_ms(opt.seconds, bar, label, || {
                if let Ok(batch) = WeightBatch::from_target_weights(rig, w, level) {
                    let _ = cpu.evaluate_into(&batch, spec, &mut out);
                }
            }))
        };
    let call = |n: usize, level: u32, precision: Precision, label: &str| -> Result<f64> {
        call_on(&cpu, n, level, precision, label)
    };

    // The wire formats.
    let eval_ms = call(opt.unique, opt.lod, Precision::F32, "f32")?;
    let mut formats = Vec::new();
    for precision in [Precision::F32, Precision::F16, Precision::Q16(qbox)] {
        let ms = if precision == Precision::F32 {
            eval_ms
        } else {
            call(opt.unique, opt.lod, precision, precision.name())?
        };
        formats.push(FormatRow {
            format: precision.name().to_string(),
            eval_ms: ms,
            unique_heads_per_s: opt.unique as f64 / (ms / 1e3),
            bytes_per_head: n3 * precision.component_bytes() * if opt.normals { 2 } else { 1 },
            vs_f32: eval_ms / ms,
        });
    }

    let blend = blend_row(rig, &cpu, &weights[..opt.unique], opt, spec, bar)?;
    let skin = skin_row(rig, &cpu, opt, spec, bar)?;

    let layout_ms = layout_ab(
        rig,
        &cpu,
        &weights[..opt.unique],
        opt.lod,
        spec,
        opt.seconds,
    )?;

    // LOD levels on the full mesh, and the line through them.
    let total_nnz: usize = cpu.slot_nnz().iter().sum();
    let mut lod_scaling = Vec::new();
    let base_ms = if opt.lod == 0 {
        eval_ms
    } else {
        call(opt.unique, 0, Precision::F32, "lod 0")?
    };
    for level in 0..levels {
        if rig.lod.levels[level as usize].mesh.is_some() {
            continue;
        }
        let ms = match level {
            l if l == opt.lod => eval_ms,
            0 => base_ms,
            l => call(opt.unique, l, Precision::F32, &format!("lod {l}"))?,
        };
        let shapes = rig.lod.shapes_at(level)?;
        let nnz: usize = cpu.slot_nnz()[..shapes as usize].iter().sum();
        lod_scaling.push(LodScaling {
            level,
            shapes,
            delta_fraction: nnz as f64 / total_nnz.max(1) as f64,
            eval_ms: ms,
            cost_ratio: ms / base_ms,
        });
    }
    let points: Vec<(f64, f64)> = lod_scaling
        .iter()
        .map(|l| (l.delta_fraction, l.eval_ms))
        .collect();
    let (floor_ms, slope_ms, r2) = fit_line(&points);
    let pca = pca_rows(
        rig,
        &weights[..opt.unique],
        &lod_scaling,
        spec,
        opt.seconds,
        bar,
    )?;

    // Dense peers and batch sizes.
    let dense = Dense::new(rig, &weights);
    let mut c = vec![0f32; largest * n3];
    let dense_gemm_ms = median_ms(opt.seconds, bar, "dense gemm", || {
        dense.gemm(opt.unique, &mut c)
    });
    let dense_matrixmultiply_ms = median_ms(opt.seconds, bar, "dense matrixmultiply", || {
        dense.matrixmultiply(opt.unique, &mut c)
    });
    let use_gemm = dense_gemm_ms <= dense_matrixmultiply_ms;
    let dense_baseline_ms = dense_gemm_ms.min(dense_matrixmultiply_ms);
    let mut batches = Vec::new();
    let unblocked = cpu.clone().with_blocking(Blocking::NONE);
    let full_blocks = cpu.blocks_below(u32::MAX) as f64;
    for &n in &opt.batches {
        let ms = if n == opt.unique && opt.lod == 0 {
            base_ms
        } else {
            call(n, 0, Precision::F32, &format!("{n} per call"))?
        };
        let unblocked_ms = call_on(&unblocked, n, 0, Precision::F32, &format!("{n} unblocked"))?;
        // The write's bounds at this output's size: the copy (into the dense peer's buffer,
        // warm) and the kernel's streaming stores alone.
        let bytes = n * n3 * 4;
        let copy_ms = {
            let src = vec![1u8; bytes];
            let dst: &mut [u8] = bytemuck::cast_slice_mut(&mut c[..n * n3]);
            median_ms(opt.seconds, bar, &format!("copy {n}"), || {
                dst.par_chunks_mut(1 << 18)
                    .zip(src.par_chunks(1 << 18))
                    .for_each(|(d, s)| d.copy_from_slice(s));
            })
        };
        let stream_write_ms = {
            let dst: &mut [u8] = bytemuck::cast_slice_mut(&mut c[..n * n3]);
            median_ms(opt.seconds, bar, &format!("stream {n}"), || {
                stream_probe(cpu.isa(), dst)
            })
        };
        let compute_ms = n as f64 * full_blocks * 96.0 / 1e9 / fma_peak_gflops * 1e3;
        let dense_ms = if n == opt.unique {
            dense_baseline_ms
        } else {
            median_ms(opt.seconds, bar, &format!("dense {n}"), || {
                if use_gemm {
                    dense.gemm(n, &mut c)
                } else {
                    dense.matrixmultiply(n, &mut c)
                }
            })
        };
        let overlapped_ms = compute_ms.max(copy_ms);
        batches.push(BatchRow {
            unique: n,
            eval_ms: ms,
            us_per_head: ms * 1e3 / n as f64,
            dense_ms,
            speedup_vs_dense: dense_ms / ms,
            span_bytes: if bytes > cpu.blocking().min_output_bytes {
                cpu.blocking().span_bytes
            } else {
                0
            },
            unblocked_ms,
            blocking_speedup: unblocked_ms / ms,
            compute_ms,
            write_ms: copy_ms,
            stream_write_ms,
            overlapped_ms,
            fraction_of_overlapped: overlapped_ms / ms,
            fraction_of_stream_bound: compute_ms.max(stream_write_ms) / ms,
        });
    }
    drop(c);
    let numpy = match &opt.numpy {
        Some(python) => {
            if let Some(b) = bar {
                b.set_message("numpy");
            }
            let t = super::peers::numpy_blend_ms(python, rig, &weights[..opt.unique], opt.seconds)?;
            Some(NumpyPeer {
                python: python.display().to_string(),
                numpy: t.numpy,
                blas: t.blas,
                warm_ms: t.warm_ms,
                alloc_ms: t.alloc_ms,
                kernel_speedup: t.warm_ms / base_ms,
                dense_baseline_speedup: t.warm_ms / dense_baseline_ms,
            })
        }
        None => None,
    };
    let one_head_ms = match batches.iter().find(|b| b.unique == 1) {
        Some(b) => b.eval_ms,
        None => call(1, 0, Precision::F32, "1 per call")?,
    };

    // Simplified meshes: the rig's own, or built here.
    let meshes = if rig.lod.meshes.is_empty() && !opt.mesh_fractions.is_empty() {
        let (levels, _) = crowdmorph_engine::lod::mesh::build_mesh_levels(
            rig,
            &opt.mesh_fractions,
            &crowdmorph_engine::lod::mesh::SimplifyOptions::default(),
            None,
        )?;
        levels
    } else {
        rig.lod.meshes.clone()
    };
    let mut mesh_levels = Vec::new();
    let full_bytes = opt.unique * n3 * 4;
    for m in &meshes {
        let derived = m.derive_rig(rig)?;
        let mcpu = CpuRig::new(&derived);
        let w = &weights[..opt.unique];
        let batch = WeightBatch::from_target_weights(&derived, w, 0)?;
        let mut out = BlendOutput::default();
        mcpu.evaluate_into(&batch, spec, &mut out)?;
        let ms = median_ms(opt.seconds, bar, "mesh level", || {
            let _ = mcpu.evaluate_into(&batch, spec, &mut out);
        });
        let bytes = out.positions.as_bytes().len();
        mesh_levels.push(MeshRow {
            triangle_fraction: m.triangle_fraction,
            vertices: derived.vertex_count(),
            output_bytes: bytes,
            eval_ms: ms,
            cost_ratio: ms / base_ms,
            bytes_ratio: bytes as f64 / full_bytes as f64,
        });
    }
    if let Some(b) = bar {
        b.finish_and_clear();
    }

    let shapes = rig.lod.shapes_at(opt.lod)?;
    let nnz_used: usize = cpu.slot_nnz()[..shapes as usize].iter().sum();
    let jobs = opt.unique as f64;
    let sparse_gflop = jobs * cpu.blocks_below(shapes) as f64 * 96.0 / 1e9;
    let useful_gflop = jobs * nnz_used as f64 * 6.0 / 1e9;
    let dense_gflop = jobs * (k + 1) as f64 * n3 as f64 * 2.0 / 1e9;
    let compute_ms = sparse_gflop / fma_peak_gflops * 1e3;
    let write_ms = out_bytes as f64 / copy_gb_per_s / 1e6;
    let unique_heads_per_s = jobs / (eval_ms / 1e3);
    let dense_baseline_heads_per_s = jobs / (dense_baseline_ms / 1e3);
    Ok(BenchReport {
        rig: rig.name.clone(),
        vertices: v,
        targets: k,
        heads: opt.heads,
        unique: opt.unique,
        lod: opt.lod,
        shapes,
        precision: "f32".to_string(),
        normals: opt.normals,
        isa: cpu.isa().name().to_string(),
        threads: rayon::current_num_threads(),
        block_fill: cpu.block_fill(),
        block_fill_vertex_order: cpu.block_fill_in_vertex_order(),
        layout_ms,
        layout_bytes: cpu.bytes(),
        machine: Machine {
            fma_peak_gflops,
            copy_gb_per_s,
        },
        eval_ms,
        crowd_ms,
        unique_heads_per_s,
        heads_per_s: opt.heads as f64 / (crowd_ms / 1e3),
        ns_per_vertex_shape: eval_ms * 1e6 / (opt.unique * v * shapes.max(1) as usize) as f64,
        ns_per_delta: eval_ms * 1e6 / (opt.unique * nnz_used.max(1)) as f64,
        roofline: Roofline {
            sparse_gflop,
            useful_gflop,
            dense_gflop,
            output_bytes: out_bytes,
            compute_ms,
            write_ms,
            overlapped_ms: compute_ms.max(write_ms),
            serial_ms: compute_ms + write_ms,
            fraction_of_overlapped: compute_ms.max(write_ms) / eval_ms,
            achieved_gflops: sparse_gflop / eval_ms * 1e3,
        },
        dense_gemm_ms,
        dense_matrixmultiply_ms,
        dense_baseline_ms,
        dense_baseline_heads_per_s,
        speedup_vs_dense: unique_heads_per_s / dense_baseline_heads_per_s,
        numpy,
        memcpy_ms,
        fraction_of_memcpy: memcpy_ms / eval_ms,
        formats,
        blend,
        skin,
        batches,
        one_head_ms,
        one_head_overhead_ms: one_head_ms - base_ms / jobs,
        clone_crowd_cost_ratio: crowd10_ms / crowd_ms,
        lod_fit: LodFit {
            floor_ms,
            slope_ms,
            r2,
            floor_vs_write: floor_ms / write_ms,
        },
        lod_scaling,
        mesh_levels,
        pca,
    })
}

/// Median ms of `cpu` and of the same rig in vertex order (`CpuRig::in_vertex_order`) for one
/// call of `weights`, the two alternating call by call so that a change of load hits both.
fn layout_ab(
    rig: &Rig,
    cpu: &CpuRig,
    weights: &[Vec<f32>],
    lod: u32,
    spec: OutputSpec,
    seconds: f64,
) -> Result<[f64; 2]> {
    let plain = CpuRig::in_vertex_order(rig, cpu.isa());
    let batch = WeightBatch::from_target_weights(rig, weights, lod)?;
    let mut outs = [BlendOutput::default(), BlendOutput::default()];
    let mut times = [Vec::new(), Vec::new()];
    let start = Instant::now();
    for round in 0.. {
        if round >= 7 && (start.elapsed().as_secs_f64() >= seconds || round >= 1000) {
            break;
        }
        for (i, (c, out)) in [cpu, &plain].into_iter().zip(&mut outs).enumerate() {
            let t = Instant::now();
            c.evaluate_into(&batch, spec, out)?;
            // The first two rounds warm the caches and the output buffers.
            if round >= 2 {
                times[i].push(t.elapsed().as_secs_f64() * 1e3);
            }
        }
    }
    Ok(times.map(|t| Samples::new(t).median()))
}

/// The layout's fill, before and after the regrouping of vertices within chunks, and its size
/// (what one call streams).
fn layout_line(r: &BenchReport) -> String {
    format!(
        "  layout       block fill {:.0} % ({:.0} % with tiles of consecutive vertices), {:.1} MB; \
         alternating calls: {:.3} ms against {:.3} ms in vertex order ({:.2}×)\n",
        r.block_fill * 100.0,
        r.block_fill_vertex_order * 100.0,
        r.layout_bytes as f64 / 1e6,
        r.layout_ms[0],
        r.layout_ms[1],
        r.layout_ms[1] / r.layout_ms[0]
    )
}

/// Human-readable bench output.
impl std::fmt::Display for BenchReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&report_text(self))
    }
}

/// The report as text (its [`std::fmt::Display`]).
pub fn report_text(r: &BenchReport) -> String {
    let mut s = format!(
        "rig {:?}: {} vertices × {} targets, {} heads / {} unique, LOD {} ({} shapes), {}{}, {} on {} threads\n",
        r.rig,
        r.vertices,
        r.targets,
        r.heads,
        r.unique,
        r.lod,
        r.shapes,
        r.precision,
        if r.normals { " + normals" } else { "" },
        r.isa,
        r.threads
    );
    let m = &r.machine;
    let f = &r.roofline;
    s += &format!(
        "  machine      FMA peak {:.0} GFLOP/s, copy {:.1} GB/s\n",
        m.fma_peak_gflops, m.copy_gb_per_s
    );
    s += &format!(
        "  blend      {:>8.3} ms  {:>10.0} unique heads/s  {:>10.0} heads/s  {:.0} GFLOP/s\n",
        r.eval_ms, r.unique_heads_per_s, r.heads_per_s, f.achieved_gflops
    );
    s += &format!(
        "  roofline     compute {:.3} ms ({:.3} GFLOP, block fill {:.0} %), write {:.3} ms ({:.1} MB): \
         overlapped {:.3} ms, serial {:.3} ms → blend at {:.0} % of the overlapped bound\n",
        f.compute_ms,
        f.sparse_gflop,
        r.block_fill * 100.0,
        f.write_ms,
        f.output_bytes as f64 / 1e6,
        f.overlapped_ms,
        f.serial_ms,
        f.fraction_of_overlapped * 100.0
    );
    s += &layout_line(r);
    s += &format!(
        "  dense        gemm {:.3} ms, matrixmultiply {:.3} ms ({:.3} GFLOP) → sparse is {:.2}× faster than the better\n",
        r.dense_gemm_ms, r.dense_matrixmultiply_ms, f.dense_gflop, r.speedup_vs_dense
    );
    if let Some(n) = &r.numpy {
        s += &format!(
            "  numpy        warm {:.3} ms, allocating {:.3} ms (numpy {}, {}) → the kernel is {:.2}× the warm numpy, the gemm peer {:.2}×\n",
            n.warm_ms, n.alloc_ms, n.numpy, n.blas, n.kernel_speedup, n.dense_baseline_speedup
        );
    }
    s += &format!(
        "  memcpy     {:>8.3} ms  (same bytes; {:.0} % of the blend's time)\n",
        r.memcpy_ms,
        r.fraction_of_memcpy * 100.0
    );
    for x in &r.formats {
        s += &format!(
            "  format {:>4} {:>8.3} ms  {:>10.0} unique heads/s  {:>8} bytes/head  {:.2}× f32's rate\n",
            x.format, x.eval_ms, x.unique_heads_per_s, x.bytes_per_head, x.vs_f32
        );
    }
    s += &format!(
        "  blend        {} frames {:.3} ms, {} four-layer blends {:.3} ms (weights gathered from a clip table): {:+.1} %\n",
        r.unique,
        r.blend.frames_ms,
        r.unique,
        r.blend.blends_ms,
        r.blend.overhead * 100.0
    );
    if let Some(k) = &r.skin {
        s += &format!(
            "  skin         {} bones, {:.2} influences/vertex: blend {:.3} ms, blend + skin {:.3} ms for {} clip frames: {:+.1} %\n",
            k.bones,
            k.influences_per_vertex,
            k.blend_ms,
            k.skinned_ms,
            r.unique,
            k.overhead * 100.0
        );
    }
    for b in &r.batches {
        s += &format!(
            "  {:>5} per call {:>9.3} ms  {:>8.2} µs/head  dense {:>9.3} ms  → {:.2}×;  unblocked {:>9.3} ms ({:.2}×, spans of {} KiB);  \
             roofline compute {:.3} ms, copy {:.3} ms, streaming write {:.3} ms → {:.0} % of the overlapped bound, {:.0} % against the streaming write\n",
            b.unique,
            b.eval_ms,
            b.us_per_head,
            b.dense_ms,
            b.speedup_vs_dense,
            b.unblocked_ms,
            b.blocking_speedup,
            b.span_bytes >> 10,
            b.compute_ms,
            b.write_ms,
            b.stream_write_ms,
            b.fraction_of_overlapped * 100.0,
            b.fraction_of_stream_bound * 100.0
        );
    }
    s += &format!(
        "  one head per call: {:.3} ms, {:.3} ms above its share of a {}-job call (each call streams the {:.1} MB layout once)\n",
        r.one_head_ms,
        r.one_head_overhead_ms,
        r.unique,
        r.layout_bytes as f64 / 1e6
    );
    s += &format!(
        "  10× crowd, same unique jobs: {:.2}× the cost\n",
        r.clone_crowd_cost_ratio
    );
    for l in &r.lod_scaling {
        s += &format!(
            "  LOD {} ({:>3} shapes, {:>5.1} % of deltas): {:.3} ms, {:.2}× the cost of LOD 0\n",
            l.level,
            l.shapes,
            l.delta_fraction * 100.0,
            l.eval_ms,
            l.cost_ratio
        );
    }
    let fit = &r.lod_fit;
    s += &format!(
        "  LOD line: {:.3} ms + {:.3} ms × deltas kept (r² {:.3}); the floor is {:.2}× the output write\n",
        fit.floor_ms, fit.slope_ms, fit.r2, fit.floor_vs_write
    );
    for p in &r.pca {
        let l = &p.level;
        s += &format!(
            "  PCA at LOD {} ({:>3} shapes, error {:.1e}): {:>5} components, {:>6.2} MB vs {:>6.2} MB sparse, {:>6.0} vs {:>6.0} kmadd/head, {:.3} ms vs {:.3} ms{}{}\n",
            l.level,
            l.shapes,
            l.pca_budget,
            l.components,
            l.pca_bytes as f64 / 1e6,
            l.sparse_bytes as f64 / 1e6,
            l.pca_madds as f64 / 1e3,
            l.sparse_madds as f64 / 1e3,
            p.pca_ms,
            p.sparse_ms,
            if p.pays { "  (pays)" } else { "" },
            if p.pays == p.model_pays {
                ""
            } else {
                "  (the cost model disagrees)"
            }
        );
    }
    for m in &r.mesh_levels {
        s += &format!(
            "  mesh {:>4.0} %: {:>6} vertices, {:>6.1} MB out ({:.2}×), {:.3} ms ({:.2}× the full mesh)\n",
            m.triangle_fraction * 100.0,
            m.vertices,
            m.output_bytes as f64 / 1e6,
            m.bytes_ratio,
            m.eval_ms,
            m.cost_ratio
        );
    }
    s
}
