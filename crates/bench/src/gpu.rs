//! `crowdmorph bench gpu`: the scenes of Costigan et al. 2016 (§6, Figures 5 and 6) on any
//! backend — one head, 100 heads with unique animation, and 100 heads sharing 10 animations
//! (the instanced case) — at 100 %, 50 % and 25 % of the shapes, reporting the GPU time from
//! timestamp queries and the CPU round-trip time (submit to vertex buffers in host memory).
//!
//! The same table with `--backend cpu` gives the CPU engine's round trip (no GPU time).
//! `--unique 1,100,4096,16384` measures crowds of that many unique heads instead (a batch the
//! size of a busy server's), with the round trip split into the passes, the copy to staging
//! memory and its mapping, and the host's copy out of it; `--format q16` has the device write
//! the wire's 16-bit format, `--format q16r` the residual planes too (the row then also times
//! what coding them on the host would cost, as the CPU engine does). A batch whose output
//! exceeds the device's largest buffer (4,096 paper-scale heads in f32 on most devices) runs in
//! pieces, each staged and read back while the next computes: the row gives the pieces and the
//! GPU and host-copy time per piece (the medians over the batch divided by the pieces).

use std::path::Path;
use std::time::Instant;

use anyhow::{Context, Result};
use serde::Serialize;

use super::sample::Samples;
use crowdmorph_core::plan::{JobKey, Plan};
use crowdmorph_core::rig::Rig;
use crowdmorph_engine::lod::plot::{Plot, Series};
use crowdmorph_engine::{
    BackendInfo, BlendJob, BlendOutput, Engine, OutputSpec, Precision, PreparedRig, Q16Reference,
    code_residuals,
};

/// One measured scene.
#[derive(Clone, Debug, Serialize)]
pub struct SceneResult {
    /// Rig name.
    pub rig: String,
    /// Scene name.
    pub scene: String,
    /// Heads in the crowd.
    pub heads: usize,
    /// Unique jobs among them.
    pub unique: usize,
    /// LOD level.
    pub lod: u32,
    /// Shapes evaluated.
    pub shapes: u32,
    /// Percentage of the rig's shapes.
    pub shape_percent: f64,
    /// Output format of the batch (`f32`, `f16`, `q16`, `q16r`).
    pub format: String,
    /// Bytes of the batch's output (positions) in that format.
    pub output_bytes: u64,
    /// Median GPU time of the batch's passes, from timestamp queries.
    pub gpu_ms: Option<f64>,
    /// Median time between the passes and the host copy: the device's copy to staging memory,
    /// its mapping, and the submission (round trip − passes − host copy).
    pub copy_map_ms: Option<f64>,
    /// Median host time after mapping: the copy into host arrays (and any host encoding).
    pub host_ms: Option<f64>,
    /// Median round trip: submit to buffers in host memory.
    pub round_trip_ms: f64,
    /// Unique head evaluations per second of GPU time.
    pub unique_heads_per_gpu_s: Option<f64>,
    /// Heads per second of round trip.
    pub heads_per_s: f64,
    /// Output bytes per second of host copy time.
    pub host_bytes_per_s: Option<f64>,
    /// `q16r`: median host time to code the batch's q16 positions as residual planes, on
    /// every core (what the CPU engine spends, and the GPU engine did before `pack_q16r`).
    pub host_coding_ms: Option<f64>,
    /// Pieces the GPU staged and read the batch back in (1 unless its output exceeds the
    /// device's largest buffer or the memory budget's room); the per-piece times are the
    /// medians divided by it.
    pub pieces: Option<usize>,
}

/// The device's limits that bound a batch.
#[derive(Clone, Debug, Serialize)]
pub struct DeviceLimits {
    /// Largest buffer.
    pub max_buffer_size: u64,
    /// Largest storage binding (a sub-batch's output fits one).
    pub max_storage_buffer_binding_size: u64,
    /// Workgroups per dispatch dimension.
    pub max_compute_workgroups_per_dimension: u32,
    /// Invocations per workgroup.
    pub max_compute_invocations_per_workgroup: u32,
    /// The engine's `--max-gpu-memory` budget.
    pub memory_budget: u64,
    /// Whether the GPU time comes from timestamp queries.
    pub timestamps: bool,
}

/// What one rig holds on the device.
#[derive(Clone, Debug, Serialize)]
pub struct Resident {
    /// Rig name.
    pub rig: String,
    /// Bytes resident on the device (geometry and clip tables; 0 on the CPU engine).
    pub device_bytes: u64,
    /// How its deltas are stored there (`f32`, `f16`; `None` on the CPU engine).
    pub deltas: Option<String>,
}

/// The whole table.
#[derive(Clone, Debug, Serialize)]
pub struct GpuBenchReport {
    /// The engine that ran it.
    pub backend: BackendInfo,
    /// The device's limits (GPU engine only).
    pub limits: Option<DeviceLimits>,
    /// Each rig measured, as resident.
    pub rigs: Vec<Resident>,
    /// One row per (rig, scene, LOD).
    pub scenes: Vec<SceneResult>,
}

/// The three scenes: (name, heads, unique animations).
pub const SCENES: [(&str, usize, usize); 3] = [
    ("1 head", 1, 1),
    ("100 unique", 100, 100),
    ("100 heads, 10 animations", 100, 10),
];

/// What to measure (also `crowdmorph bench gpu`'s flags).
#[derive(Clone, Debug, Default, clap::Args)]
pub struct GpuBenchOptions {
    /// Seconds per measurement (at least 3 runs).
    #[arg(long, default_value_t = 1.0)]
    pub seconds: f64,
    /// Instead of the paper's scenes: crowds of this many unique heads each (comma-separated,
    /// e.g. 1,100,4096,16384), at LOD 0, on a clip long enough that every head is a different
    /// frame.
    #[arg(long, value_delimiter = ',')]
    pub unique: Vec<usize>,
    /// Output format of every batch: `f32`, `f16`, `q16` (in each rig's quantization box) or
    /// `q16r` (its positions as residual planes against the neutral).
    #[arg(long, default_value = "f32", value_parser = super::format_arg())]
    pub format: crowdmorph_proto::Format,
}

/// Runs every scene on `engine` for each rig: the paper's three at LOD levels 0, 1 and 2
/// (100/50/25 % by default), or `opt.unique`'s at LOD 0.
pub fn bench_gpu(engine: &Engine, rigs: &[Rig], opt: &GpuBenchOptions) -> Result<GpuBenchReport> {
    let mut scenes = Vec::new();
    let plan: Vec<(String, usize, usize, u32)> = if opt.unique.is_empty() {
        SCENES
            .iter()
            .flat_map(|&(name, heads, unique)| {
                (0..3u32).map(move |lod| (name.to_string(), heads, unique, lod))
            })
            .collect()
    } else {
        opt.unique
            .iter()
            .map(|&n| (format!("{n} unique"), n, n, 0))
            .collect()
    };
    let frames = plan.iter().map(|p| p.2).max().unwrap_or(1).max(128);
    // A skinned rig is measured twice: as it is, and without its skeleton (the blend alone),
    // so the table shows what the skin pass adds on this device.
    let rigs: Vec<Rig> = rigs
        .iter()
        .flat_map(|r| {
            let twin = r.is_skinned().then(|| {
                let mut plain = super::cpu::without_skeleton(r);
                plain.name = format!("{} without skin", r.name);
                plain
            });
            std::iter::once(r.clone()).chain(twin)
        })
        .collect();
    let bar = super::progress_bar((rigs.len() * plan.len()) as u64, "bench gpu");
    let mut resident = Vec::new();
    for rig in &rigs {
        // A clip of its own with more frames than heads, so "N unique" is N unique jobs; on a
        // skinned rig its frames take the joints of the rig's clips' frames in turn.
        let rig = crowdmorph_core::synthetic::with_random_clip_of(rig.clone(), "bench", frames, 1);
        let rig = with_joint_frames(rig);
        let clip = (rig.clips.len() - 1) as u32;
        let precision = match opt.format {
            crowdmorph_proto::Format::F16 => Precision::F16,
            crowdmorph_proto::Format::Q16 | crowdmorph_proto::Format::Q16R => {
                Precision::Q16(crowdmorph_server::registry::quantization_box(&rig))
            }
            crowdmorph_proto::Format::F32 => Precision::F32,
            crowdmorph_proto::Format::Weights => {
                anyhow::bail!("bench gpu blends vertices: format weights has none")
            }
        };
        let prepared = engine
            .prepare(std::sync::Arc::new(rig.clone()))
            .with_context(|| format!("preparing {}", rig.name))?;
        let residuals = opt.format == crowdmorph_proto::Format::Q16R;
        resident.push(Resident {
            rig: rig.name.clone(),
            device_bytes: prepared.memory().device_bytes as u64,
            deltas: prepared.gpu().map(|g| g.deltas().to_string()),
        });
        for (name, heads, unique, lod) in &plan {
            if *lod >= rig.lod.levels.len() as u32 {
                continue;
            }
            bar.set_message(format!("{} {name} LOD {lod}", rig.name));
            let reference = match precision {
                Precision::Q16(b) if residuals => {
                    Some(prepared.at_level(*lod).q16_reference(b)?.into())
                }
                _ => None,
            };
            let scene = Scene {
                name,
                heads: *heads,
                unique: *unique,
                clip,
                lod: *lod,
                precision,
                reference,
            };
            let row = measure(engine, &prepared, &scene, opt.seconds)?;
            // Each row on stderr as it is measured: a run stopped by a timeout (a big crowd on
            // a slow device) keeps the rows it finished.
            let ms = |v: Option<f64>| v.map_or("-".into(), |v| format!("{v:.3}"));
            bar.suspend(|| {
                eprintln!(
                    "bench gpu: {} | {} | {}: round trip {:.3} ms, GPU {} ms, host {} ms, {} pieces",
                    row.rig,
                    row.scene,
                    row.format,
                    row.round_trip_ms,
                    ms(row.gpu_ms),
                    ms(row.host_ms),
                    row.pieces.map_or("-".into(), |p| p.to_string()),
                );
            });
            scenes.push(row);
            bar.inc(1);
        }
    }
    bar.finish_and_clear();
    let limits = engine.gpu().map(|ctx| {
        let l = ctx.device().limits();
        DeviceLimits {
            max_buffer_size: l.max_buffer_size,
            max_storage_buffer_binding_size: l.max_storage_buffer_binding_size,
            max_compute_workgroups_per_dimension: l.max_compute_workgroups_per_dimension,
            max_compute_invocations_per_workgroup: l.max_compute_invocations_per_workgroup,
            memory_budget: ctx.memory().limit(),
            timestamps: ctx.has_timestamps(),
        }
    });
    Ok(GpuBenchReport {
        backend: engine.info(),
        limits,
        rigs: resident,
        scenes,
    })
}

/// `rig` whose last clip (the bench's) takes, frame by frame, the joint transforms of its
/// other clips' frames in turn, so that skinned heads are posed, not at rest.
fn with_joint_frames(mut rig: Rig) -> Rig {
    let Some(sk) = rig.skeleton.clone() else {
        return rig;
    };
    let Some((last, others)) = rig.clips.split_last_mut() else {
        return rig;
    };
    let poses: Vec<Vec<crowdmorph_core::rig::Trs>> = others
        .iter()
        .filter(|c| c.joints.is_some())
        .flat_map(|c| {
            let sk = &sk;
            (0..c.frames).map(move |f| {
                let mut l = Vec::new();
                sk.locals_at(c.joints.as_deref(), f, &mut l);
                l
            })
        })
        .take(last.frames as usize)
        .collect();
    if poses.is_empty() {
        return rig;
    }
    let nodes: Vec<u32> = (0..sk.nodes.len() as u32).collect();
    let values = (0..last.frames as usize)
        .flat_map(|f| poses[f % poses.len()].iter().flat_map(|t| t.floats()))
        .collect();
    last.joints = Some(std::sync::Arc::new(crowdmorph_core::rig::JointTable {
        nodes,
        frames: last.frames,
        values,
    }));
    rig
}

/// One scene to measure.
struct Scene<'a> {
    name: &'a str,
    heads: usize,
    unique: usize,
    clip: u32,
    lod: u32,
    precision: Precision,
    /// `q16r`'s reference.
    reference: Option<Q16Reference>,
}

fn measure(
    engine: &Engine,
    prepared: &PreparedRig,
    scene: &Scene<'_>,
    seconds: f64,
) -> Result<SceneResult> {
    let rig = prepared.rig();
    let lod = scene.lod;
    // Heads play `unique` different frames; clones share them (the planner dedupes).
    let keys =
        (0..scene.heads).map(|h| JobKey::frame(0, scene.clip, (h % scene.unique) as u32, lod));
    let plan = Plan::new(keys);
    let jobs: Vec<BlendJob> = plan.jobs.iter().map(BlendJob::from).collect();
    let spec = OutputSpec {
        normals: false,
        precision: scene.precision,
    };
    // One output reused across runs, as the server's buffer pool does: a fresh 50 MB buffer
    // per run would time its page faults, not the engine. The first run warms it, and the
    // GPU's pipelines and slot buffers.
    let mut out = BlendOutput::default();
    let evaluate = |out: &mut BlendOutput| {
        let begun = engine.begin(prepared, &jobs, spec, scene.reference.clone())?;
        engine.finish_into(begun, prepared, &jobs, spec, out)
    };
    evaluate(&mut out)?;
    let host_coding_ms = match &scene.reference {
        Some(r) => Some(host_coding(engine, prepared, &jobs, spec, r)?),
        None => None,
    };
    let mut round = Vec::new();
    let mut gpu = Vec::new();
    let mut host = Vec::new();
    let mut between = Vec::new();
    let mut pieces = None;
    let start = Instant::now();
    while round.len() < 3 || (start.elapsed().as_secs_f64() < seconds && round.len() < 100) {
        let t = Instant::now();
        let (timings, _) = evaluate(&mut out)?;
        let ms = t.elapsed().as_secs_f64() * 1e3;
        pieces = timings.pieces;
        round.push(ms);
        let g = timings.gpu_ns.map(|ns| ns as f64 / 1e6);
        let h = timings.host_ns.map(|ns| ns as f64 / 1e6);
        if let Some(g) = g {
            gpu.push(g);
        }
        if let Some(h) = h {
            host.push(h);
            between.push((ms - h - g.unwrap_or(0.0)).max(0.0));
        }
    }
    let median = |v: Vec<f64>| (!v.is_empty()).then(|| Samples::new(v).median());
    let round_trip_ms = Samples::new(round).median();
    let gpu_ms = median(gpu);
    let host_ms = median(host);
    let shapes = rig.lod.shapes_at(lod)?;
    let output_bytes = out.positions.as_bytes().len() as u64;
    Ok(SceneResult {
        rig: rig.name.clone(),
        scene: scene.name.to_string(),
        heads: scene.heads,
        unique: plan.jobs.len(),
        lod,
        shapes,
        shape_percent: 100.0 * f64::from(shapes) / rig.targets.len().max(1) as f64,
        format: match (scene.precision, &scene.reference) {
            (Precision::F32, _) => "f32",
            (Precision::F16, _) => "f16",
            (Precision::Q16(_), None) => "q16",
            (Precision::Q16(_), Some(_)) => "q16r",
        }
        .to_string(),
        output_bytes,
        gpu_ms,
        copy_map_ms: median(between),
        host_ms,
        round_trip_ms,
        unique_heads_per_gpu_s: gpu_ms.map(|ms| plan.jobs.len() as f64 / (ms / 1e3)),
        heads_per_s: scene.heads as f64 / (round_trip_ms / 1e3),
        host_bytes_per_s: host_ms.map(|ms| output_bytes as f64 / (ms / 1e3).max(1e-12)),
        host_coding_ms,
        pieces,
    })
}

/// Median host time to code `jobs`' q16 positions as residual planes against `reference`
/// (each run codes a fresh copy of the same q16 output, copied outside the timing).
fn host_coding(
    engine: &Engine,
    prepared: &PreparedRig,
    jobs: &[BlendJob],
    spec: OutputSpec,
    reference: &[i16],
) -> Result<f64> {
    let mut q16 = BlendOutput::default();
    engine.evaluate_into(prepared, jobs, spec, &mut q16)?;
    let mut work = q16.positions.clone();
    let mut times = Vec::new();
    for _ in 0..7 {
        work.clone_from(&q16.positions);
        let t = Instant::now();
        code_residuals(&mut work, reference)?;
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    Ok(Samples::new(times).median())
}

/// The table as text.
impl std::fmt::Display for GpuBenchReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&report_text(self))
    }
}

/// The report as text (its [`std::fmt::Display`]).
pub fn report_text(r: &GpuBenchReport) -> String {
    let mut s = format!(
        "backend: {:?} {}{}\n",
        r.backend.kind,
        r.backend.adapter.as_deref().unwrap_or("(CPU engine)"),
        if r.backend.degraded {
            " — DEGRADED"
        } else {
            ""
        }
    );
    if let Some(l) = &r.limits {
        s += &format!(
            "limits: largest buffer {} MiB, storage binding {} MiB, {} workgroups per dimension, {} invocations per workgroup; memory budget {} MiB; timestamps {}\n",
            l.max_buffer_size >> 20,
            l.max_storage_buffer_binding_size >> 20,
            l.max_compute_workgroups_per_dimension,
            l.max_compute_invocations_per_workgroup,
            l.memory_budget >> 20,
            if l.timestamps { "yes" } else { "no" },
        );
    }
    for rig in &r.rigs {
        if let Some(d) = &rig.deltas {
            s += &format!(
                "resident: {} {} bytes on the device, {d} deltas\n",
                rig.rig, rig.device_bytes
            );
        }
    }
    let ms = |v: Option<f64>| v.map_or("-".into(), |v| format!("{v:.3}"));
    let w = r
        .scenes
        .iter()
        .map(|sc| sc.rig.len())
        .max()
        .unwrap_or(0)
        .max(16);
    s += &format!(
        "{:<w$} {:<26} {:>6} {:>6} {:>4} {:>10} {:>10} {:>9} {:>12} {:>16} {:>10} {:>6} {:>12} {:>12}{}\n",
        "rig",
        "scene",
        "unique",
        "shapes",
        "fmt",
        "GPU ms",
        "copy+map",
        "host ms",
        "round-trip ms",
        "unique heads/GPU s",
        "host MB/s",
        "pieces",
        "GPU ms/piece",
        "host ms/piece",
        if r.scenes.iter().any(|sc| sc.host_coding_ms.is_some()) {
            "  host coding ms"
        } else {
            ""
        }
    );
    for sc in &r.scenes {
        let per_piece = |v: Option<f64>| Some(v? / sc.pieces? as f64);
        s += &format!(
            "{:<w$} {:<26} {:>6} {:>5.0}% {:>4} {:>10} {:>10} {:>9} {:>12.3} {:>16} {:>10} {:>6} {:>12} {:>12}{}\n",
            sc.rig,
            sc.scene,
            sc.unique,
            sc.shape_percent,
            sc.format,
            ms(sc.gpu_ms),
            ms(sc.copy_map_ms),
            ms(sc.host_ms),
            sc.round_trip_ms,
            sc.unique_heads_per_gpu_s
                .map_or("-".into(), |v| format!("{v:.0}")),
            sc.host_bytes_per_s
                .map_or("-".into(), |v| format!("{:.0}", v / 1e6)),
            sc.pieces.map_or("-".into(), |p| p.to_string()),
            ms(per_piece(sc.gpu_ms)),
            ms(per_piece(sc.host_ms)),
            sc.host_coding_ms
                .map_or(String::new(), |v| format!(" {v:>15.3}")),
        );
    }
    s
}

/// Draws the table like the paper's Figures 5 and 6: a column per scene, a row per timer (GPU
/// time, round trip), time against the share of shapes, one line per rig.
pub fn write_plot(reports: &[GpuBenchReport], path: &Path) -> Result<()> {
    let mut panels = Vec::new();
    for timer in ["GPU ms", "round trip ms"] {
        for (scene, _, _) in SCENES {
            let mut series = Vec::new();
            for r in reports {
                let backend = format!("{:?}", r.backend.kind).to_lowercase();
                let mut rigs: Vec<&str> = r.scenes.iter().map(|s| s.rig.as_str()).collect();
                rigs.dedup();
                for rig in rigs {
                    let points: Vec<(f64, f64)> = r
                        .scenes
                        .iter()
                        .filter(|s| s.rig == rig && s.scene == scene)
                        .filter_map(|s| {
                            let y = if timer == "GPU ms" {
                                s.gpu_ms?
                            } else {
                                s.round_trip_ms
                            };
                            Some((s.shape_percent, y))
                        })
                        .collect();
                    if !points.is_empty() {
                        series.push(Series {
                            label: format!("{backend} {rig}"),
                            points,
                        });
                    }
                }
            }
            panels.push((format!("{scene}: {timer} vs % shapes"), series));
        }
    }
    let plot = Plot {
        title: "crowdmorph bench gpu (Costigan et al. 2016, Figs. 5-6 scenes)".into(),
        panels,
    };
    let png = plot.to_png().context("encoding the plot")?;
    std::fs::write(path, png).with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}
