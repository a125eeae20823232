//! `crowdmorph bench cpu`: throughput of the CPU engine against two references measured in the
//! same run on the same work — a dense sgemm of the same blend (the obvious implementation) and
//! a plain parallel copy of the same output bytes (the memory roofline no blend can beat).
//!
//! Workload: `unique` distinct jobs whose weights are drawn uniformly from [0, 1) for every
//! target (all shapes active: the most expensive case), spread over `heads` heads; head `h`
//! plays job `h mod unique`. Times are medians over repeated runs with warm buffers.

use crate::rng::SplitMix64;
use std::time::Instant;

use anyhow::Result;
use indicatif::ProgressBar;
use rayon::prelude::*;
use serde::Serialize;

use crate::engine::cpu::CpuRig;
use crate::engine::{BlendOutput, OutputSpec, Precision, WeightBatch};
use crate::plan::{JobKey, Plan};
use crate::rig::Rig;

/// What to measure.
#[derive(Clone, Debug)]
pub struct BenchOptions {
    /// Heads in the crowd.
    pub heads: usize,
    /// Unique jobs among them.
    pub unique: usize,
    /// LOD level of every head.
    pub lod: u32,
    /// Output precision.
    pub precision: Precision,
    /// Also compute normals.
    pub normals: bool,
    /// Seconds to spend per measurement (at least 5 runs each).
    pub seconds: f64,
    /// Show progress bars.
    pub progress: bool,
}

impl Default for BenchOptions {
    fn default() -> Self {
        BenchOptions {
            heads: 100,
            unique: 100,
            lod: 0,
            precision: Precision::F32,
            normals: false,
            seconds: 1.0,
            progress: true,
        }
    }
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
    /// Median evaluation time at this level / at level 0.
    pub cost_ratio: f64,
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
    /// Output precision.
    pub precision: String,
    /// Normals computed too.
    pub normals: bool,
    /// Kernel family.
    pub isa: String,
    /// Worker threads.
    pub threads: usize,
    /// Fraction of stored block lanes that hold a real delta.
    pub block_fill: f64,
    /// Median seconds to evaluate the unique jobs (weights gathered, output written).
    pub eval_ms: f64,
    /// Median seconds for the whole crowd: planning + evaluation.
    pub crowd_ms: f64,
    /// Unique jobs evaluated per second.
    pub unique_heads_per_s: f64,
    /// Heads served per second (clones included).
    pub heads_per_s: f64,
    /// Evaluation time per (job × vertex × shape), the dense-equivalent work unit.
    pub ns_per_vertex_shape: f64,
    /// Evaluation time per stored non-zero delta per job.
    pub ns_per_delta: f64,
    /// Dense sgemm (matrixmultiply) of the same blend, median ms.
    pub dense_baseline_ms: f64,
    /// Unique heads per second of the dense baseline.
    pub dense_baseline_heads_per_s: f64,
    /// Plain parallel copy of the same output bytes, median ms.
    pub memcpy_ms: f64,
    /// Unique heads per second of the copy: the roofline.
    pub memcpy_roofline_heads_per_s: f64,
    /// `unique_heads_per_s / dense_baseline_heads_per_s`.
    pub speedup_vs_dense: f64,
    /// `unique_heads_per_s / memcpy_roofline_heads_per_s`.
    pub fraction_of_roofline: f64,
    /// Cost of a crowd 10× larger with the same unique jobs, relative to this crowd.
    pub clone_crowd_cost_ratio: f64,
    /// Cost of each LOD level relative to level 0.
    pub lod_scaling: Vec<LodScaling>,
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

/// Median of `f`'s wall time in milliseconds, over at least 5 runs and about `seconds`.
fn median_ms(seconds: f64, bar: Option<&ProgressBar>, label: &str, mut f: impl FnMut()) -> f64 {
    f(); // Warm-up: page faults, caches, thread pool.
    f();
    let mut times = Vec::new();
    let start = Instant::now();
    if let Some(b) = bar {
        b.set_message(label.to_string());
    }
    while times.len() < 5 || (start.elapsed().as_secs_f64() < seconds && times.len() < 1000) {
        let t = Instant::now();
        f();
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    if let Some(b) = bar {
        b.inc(1);
    }
    times.sort_by(f64::total_cmp);
    times[times.len() / 2]
}

/// Runs the CPU benchmark.
pub fn bench_cpu(rig: &Rig, opt: &BenchOptions) -> Result<BenchReport> {
    anyhow::ensure!(
        opt.unique >= 1 && opt.heads >= opt.unique,
        "need heads >= unique >= 1"
    );
    let cpu = CpuRig::new(rig);
    let v = rig.vertex_count();
    let weights = random_weights(rig, opt.unique, 0x5EED);
    let spec = OutputSpec {
        normals: opt.normals,
        precision: opt.precision,
    };
    let levels = rig.lod.levels.len() as u32;
    let bar = opt
        .progress
        .then(|| super::progress_bar(u64::from(levels) + 4, "bench"));
    let bar = bar.as_ref();

    // The crowd: plan, gather, evaluate.
    let mut out = BlendOutput::default();
    let crowd = |heads: usize, out: &mut BlendOutput| -> Result<()> {
        let plan = Plan::new((0..heads).map(|h| JobKey {
            rig: 0,
            clip: 0,
            frame: (h % opt.unique) as u32,
            lod: opt.lod,
        }));
        let w: Vec<Vec<f32>> = plan
            .jobs
            .iter()
            .map(|j| weights[j.frame as usize].clone())
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

    // Evaluation alone, per LOD level.
    let mut eval_at = |level: u32| -> Result<f64> {
        let batch = WeightBatch::from_target_weights(rig, &weights, level)?;
        cpu.evaluate_into(&batch, spec, &mut out)?;
        Ok(median_ms(opt.seconds, bar, &format!("lod {level}"), || {
            let _ = cpu.evaluate_into(&batch, spec, &mut out);
        }))
    };
    let eval_ms = eval_at(opt.lod)?;
    let total_nnz: usize = cpu.slot_nnz().iter().sum();
    let mut lod_scaling = Vec::new();
    let base_ms = if opt.lod == 0 { eval_ms } else { eval_at(0)? };
    for level in 0..levels {
        let ms = if level == opt.lod {
            eval_ms
        } else {
            eval_at(level)?
        };
        let shapes = rig.lod.shapes_at(level)?;
        let nnz: usize = cpu.slot_nnz()[..shapes as usize].iter().sum();
        lod_scaling.push(LodScaling {
            level,
            shapes,
            delta_fraction: nnz as f64 / total_nnz.max(1) as f64,
            cost_ratio: ms / base_ms,
        });
    }

    // Dense baseline: C[U × 3V] = base + W[U × K] · D[K × 3V], with matrixmultiply's sgemm.
    let k = rig.targets.len();
    let n3 = v * 3;
    let mut dense = vec![0f32; k * n3];
    let mut base = Vec::with_capacity(n3);
    let offsets = rig.vertex_offsets();
    for (pi, p) in rig.primitives.iter().enumerate() {
        base.extend(p.positions.iter().flat_map(|x| x.to_array()));
        for t in &p.targets {
            for (i, &vert) in t.vertices.iter().enumerate() {
                let at = t.target as usize * n3 + (offsets[pi] + vert as usize) * 3;
                dense[at..at + 3].copy_from_slice(&t.positions[i].to_array());
            }
        }
    }
    let wmat: Vec<f32> = weights.iter().flatten().copied().collect();
    let mut c = vec![0f32; opt.unique * n3];
    let dense_ms = median_ms(opt.seconds, bar, "dense sgemm", || {
        c.par_chunks_mut(n3)
            .for_each(|row| row.copy_from_slice(&base));
        // SAFETY: the pointers and strides describe the row-major matrices allocated above:
        // W is unique × k, D is k × n3, C is unique × n3.
        unsafe {
            matrixmultiply::sgemm(
                opt.unique,
                k,
                n3,
                1.0,
                wmat.as_ptr(),
                k as isize,
                1,
                dense.as_ptr(),
                n3 as isize,
                1,
                1.0,
                c.as_mut_ptr(),
                n3 as isize,
                1,
            );
        }
    });
    drop(dense);

    // Roofline: copy the same number of output bytes.
    let bytes_per_comp = if opt.precision == Precision::F16 {
        2
    } else {
        4
    };
    let comps = opt.unique * n3 * if opt.normals { 2 } else { 1 };
    let src = vec![1u8; comps * bytes_per_comp];
    let mut dst = vec![0u8; comps * bytes_per_comp];
    let memcpy_ms = median_ms(opt.seconds, bar, "memcpy", || {
        dst.par_chunks_mut(1 << 18)
            .zip(src.par_chunks(1 << 18))
            .for_each(|(d, s)| d.copy_from_slice(s));
    });
    if let Some(b) = bar {
        b.finish_and_clear();
    }

    let shapes = rig.lod.shapes_at(opt.lod)?;
    let unique_heads_per_s = opt.unique as f64 / (eval_ms / 1e3);
    let dense_baseline_heads_per_s = opt.unique as f64 / (dense_ms / 1e3);
    let memcpy_roofline_heads_per_s = opt.unique as f64 / (memcpy_ms / 1e3);
    let nnz_used: usize = cpu.slot_nnz()[..shapes as usize].iter().sum();
    Ok(BenchReport {
        rig: rig.name.clone(),
        vertices: v,
        targets: k,
        heads: opt.heads,
        unique: opt.unique,
        lod: opt.lod,
        shapes,
        precision: format!("{:?}", opt.precision).to_lowercase(),
        normals: opt.normals,
        isa: cpu.isa().name().to_string(),
        threads: rayon::current_num_threads(),
        block_fill: cpu.block_fill(),
        eval_ms,
        crowd_ms,
        unique_heads_per_s,
        heads_per_s: opt.heads as f64 / (crowd_ms / 1e3),
        ns_per_vertex_shape: eval_ms * 1e6 / (opt.unique * v * shapes.max(1) as usize) as f64,
        ns_per_delta: eval_ms * 1e6 / (opt.unique * nnz_used.max(1)) as f64,
        dense_baseline_ms: dense_ms,
        dense_baseline_heads_per_s,
        memcpy_ms,
        memcpy_roofline_heads_per_s,
        speedup_vs_dense: unique_heads_per_s / dense_baseline_heads_per_s,
        fraction_of_roofline: unique_heads_per_s / memcpy_roofline_heads_per_s,
        clone_crowd_cost_ratio: crowd10_ms / crowd_ms,
        lod_scaling,
    })
}

/// Human-readable bench output.
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
    s += &format!(
        "  blend      {:>8.3} ms  {:>10.0} unique heads/s  {:>10.0} heads/s  {:.3} ns/vertex·shape\n",
        r.eval_ms, r.unique_heads_per_s, r.heads_per_s, r.ns_per_vertex_shape
    );
    s += &format!(
        "  dense sgemm{:>8.3} ms  {:>10.0} heads/s  → sparse is {:.2}× faster\n",
        r.dense_baseline_ms, r.dense_baseline_heads_per_s, r.speedup_vs_dense
    );
    s += &format!(
        "  memcpy     {:>8.3} ms  {:>10.0} heads/s  → blend reaches {:.0} % of the roofline\n",
        r.memcpy_ms,
        r.memcpy_roofline_heads_per_s,
        r.fraction_of_roofline * 100.0
    );
    s += &format!(
        "  10× crowd, same unique jobs: {:.2}× the cost\n",
        r.clone_crowd_cost_ratio
    );
    for l in &r.lod_scaling {
        s += &format!(
            "  LOD {} ({:>3} shapes, {:>5.1} % of deltas): {:.2}× the cost of LOD 0\n",
            l.level,
            l.shapes,
            l.delta_fraction * 100.0,
            l.cost_ratio
        );
    }
    s
}
