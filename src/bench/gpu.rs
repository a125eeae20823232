//! `crowdmorph bench gpu`: the scenes of Costigan et al. 2016 (§6, Figures 5 and 6) on any
//! backend — one head, 100 heads with unique animation, and 100 heads sharing 10 animations
//! (the instanced case) — at 100 %, 50 % and 25 % of the shapes, reporting the GPU time from
//! timestamp queries and the CPU round-trip time (submit to vertex buffers in host memory).
//!
//! The same table with `--backend cpu` gives the CPU engine's round trip (no GPU time).

use std::path::Path;
use std::time::Instant;

use anyhow::{Context, Result};
use serde::Serialize;

use super::sample::Samples;
use crate::engine::{BackendInfo, BlendJob, BlendOutput, Engine, OutputSpec, PreparedRig};
use crate::lod::plot::{Plot, Series};
use crate::plan::{JobKey, Plan};
use crate::rig::Rig;

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
    /// Median GPU time of the batch, from timestamp queries.
    pub gpu_ms: Option<f64>,
    /// Median round trip: submit to buffers in host memory.
    pub round_trip_ms: f64,
    /// Unique head evaluations per second of GPU time.
    pub unique_heads_per_gpu_s: Option<f64>,
    /// Heads per second of round trip.
    pub heads_per_s: f64,
}

/// The whole table.
#[derive(Clone, Debug, Serialize)]
pub struct GpuBenchReport {
    /// The engine that ran it.
    pub backend: BackendInfo,
    /// One row per (rig, scene, LOD).
    pub scenes: Vec<SceneResult>,
}

/// The three scenes: (name, heads, unique animations).
pub const SCENES: [(&str, usize, usize); 3] = [
    ("1 head", 1, 1),
    ("100 unique", 100, 100),
    ("100 heads, 10 animations", 100, 10),
];

/// Runs every scene on `engine` for each rig at LOD levels 0, 1 and 2 (100/50/25 % by
/// default), about `seconds` per measurement (at least 3 runs).
pub fn bench_gpu(engine: &Engine, rigs: &[Rig], seconds: f64) -> Result<GpuBenchReport> {
    let mut scenes = Vec::new();
    let bar = super::progress_bar((rigs.len() * SCENES.len() * 3) as u64, "bench gpu");
    for rig in rigs {
        // A clip of its own with more frames than heads, so "100 unique" is 100 unique jobs.
        let rig = crate::synthetic::with_random_clip_of(rig.clone(), "bench", 128, 1);
        let clip = (rig.clips.len() - 1) as u32;
        let prepared = engine
            .prepare(std::sync::Arc::new(rig.clone()))
            .with_context(|| format!("preparing {}", rig.name))?;
        for (name, heads, unique) in SCENES {
            for lod in 0..3u32.min(rig.lod.levels.len() as u32) {
                bar.set_message(format!("{} {name} LOD {lod}", rig.name));
                scenes.push(measure(
                    engine, &prepared, name, heads, unique, clip, lod, seconds,
                )?);
                bar.inc(1);
            }
        }
    }
    bar.finish_and_clear();
    Ok(GpuBenchReport {
        backend: engine.info(),
        scenes,
    })
}

#[allow(clippy::too_many_arguments)]
fn measure(
    engine: &Engine,
    prepared: &PreparedRig,
    scene: &str,
    heads: usize,
    unique: usize,
    clip: u32,
    lod: u32,
    seconds: f64,
) -> Result<SceneResult> {
    let rig = prepared.rig();
    // Heads play `unique` different frames; clones share them (the planner dedupes).
    let keys = (0..heads).map(|h| JobKey::frame(0, clip, (h % unique) as u32, lod));
    let plan = Plan::new(keys);
    let jobs: Vec<BlendJob> = plan.jobs.iter().map(BlendJob::from).collect();
    let spec = OutputSpec::default();
    // One output reused across runs, as the server's buffer pool does: a fresh 50 MB buffer
    // per run would time its page faults, not the engine. The first run warms it, and the
    // GPU's pipelines and slot buffers.
    let mut out = BlendOutput::default();
    engine.evaluate_into(prepared, &jobs, spec, &mut out)?;
    let mut round = Vec::new();
    let mut gpu = Vec::new();
    let start = Instant::now();
    while round.len() < 3 || (start.elapsed().as_secs_f64() < seconds && round.len() < 100) {
        let t = Instant::now();
        let (timings, _) = engine.evaluate_into(prepared, &jobs, spec, &mut out)?;
        round.push(t.elapsed().as_secs_f64() * 1e3);
        if let Some(ns) = timings.gpu_ns {
            gpu.push(ns as f64 / 1e6);
        }
    }
    let round_trip_ms = Samples::new(round).median();
    let gpu_ms = (!gpu.is_empty()).then(|| Samples::new(gpu).median());
    let shapes = rig.lod.shapes_at(lod)?;
    Ok(SceneResult {
        rig: rig.name.clone(),
        scene: scene.to_string(),
        heads,
        unique: plan.jobs.len(),
        lod,
        shapes,
        shape_percent: 100.0 * f64::from(shapes) / rig.targets.len().max(1) as f64,
        gpu_ms,
        round_trip_ms,
        unique_heads_per_gpu_s: gpu_ms.map(|ms| plan.jobs.len() as f64 / (ms / 1e3)),
        heads_per_s: heads as f64 / (round_trip_ms / 1e3),
    })
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
    s += &format!(
        "{:<16} {:<26} {:>6} {:>6} {:>10} {:>12} {:>16}\n",
        "rig", "scene", "unique", "shapes", "GPU ms", "round-trip ms", "unique heads/GPU s"
    );
    for sc in &r.scenes {
        s += &format!(
            "{:<16} {:<26} {:>6} {:>5.0}% {:>10} {:>12.3} {:>16}\n",
            sc.rig,
            sc.scene,
            sc.unique,
            sc.shape_percent,
            sc.gpu_ms.map_or("-".into(), |v| format!("{v:.3}")),
            sc.round_trip_ms,
            sc.unique_heads_per_gpu_s
                .map_or("-".into(), |v| format!("{v:.0}")),
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
