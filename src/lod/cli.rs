//! `crowdmorph lod ...` as library functions: the binary parses arguments and calls these.
//!
//! Like `crate::tools`, these are tools rather than request paths, so they report errors with
//! `anyhow` and print what they compute.

use std::path::Path;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use serde::Serialize;

use super::mesh::{FeaturePoints, SimplifyOptions, build_mesh_levels, mesh_level_rig};
use super::order::{Metric, OrderMethod, ScoreOptions, Scores, score_targets};
use super::report::{LodReport, lod_report, report_png, report_text, synthetic_clip};
use super::{pin_front, resolve_targets};
use crate::render::{Camera, neutral_positions, render_pose};
use crate::rig::{Rig, TargetId};

/// Name of the synthetic clip `lod report --clip random` generates.
pub const RANDOM_CLIP: &str = "random";

/// Frames of the synthetic clip.
pub const RANDOM_CLIP_FRAMES: usize = 150;

/// Seed of the synthetic clip (fixed, so reports are reproducible).
pub const RANDOM_CLIP_SEED: u64 = 0x00C0_FFEE;

/// Scores the rig's targets and times it.
pub fn score(rig: &Rig, image_size: u32) -> Result<(Scores, f64)> {
    let started = Instant::now();
    let scores = score_targets(
        rig,
        &ScoreOptions {
            image_size,
            ..ScoreOptions::default()
        },
        None,
    )?;
    Ok((scores, started.elapsed().as_secs_f64()))
}

/// Resolves `--clip`: a clip of the rig, or `random` for a synthetic one (added to the rig).
pub fn resolve_clip(rig: &mut Rig, name: &str) -> Result<usize> {
    if let Some(i) = rig.clip_index(name) {
        return Ok(i);
    }
    if name == RANDOM_CLIP {
        let clip = synthetic_clip(rig, RANDOM_CLIP, RANDOM_CLIP_FRAMES, RANDOM_CLIP_SEED)?;
        rig.clips.push(clip);
        return Ok(rig.clips.len() - 1);
    }
    let names: Vec<&str> = rig.clips.iter().map(|c| c.name.as_str()).collect();
    bail!(
        "rig {:?} has no clip {name:?} (clips: {}; `random` makes a synthetic one)",
        rig.name,
        if names.is_empty() {
            "none".to_string()
        } else {
            names.join(", ")
        }
    )
}

/// `crowdmorph lod report`: the report, printed as text or JSON, and optionally a PNG plot.
pub fn report_command(
    rig: &mut Rig,
    clip: &str,
    pins: &[String],
    image_size: u32,
    png_out: Option<&Path>,
    json: bool,
) -> Result<LodReport> {
    let ci = resolve_clip(rig, clip)?;
    let pins = resolve_targets(rig, pins)?;
    let (scores, seconds) = score(rig, image_size)?;
    eprintln!(
        "scored {} targets with 5 metrics in {seconds:.2} s",
        rig.targets.len()
    );
    let report = lod_report(rig, ci, &scores, &pins)?;
    if json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print!("{}", report_text(&report));
    }
    if let Some(out) = png_out {
        let bytes = report_png(&report)?;
        std::fs::write(out, bytes).with_context(|| format!("writing {}", out.display()))?;
        eprintln!("wrote {}", out.display());
    }
    Ok(report)
}

/// What `crowdmorph lod order --json` prints.
#[derive(Debug, Serialize)]
pub struct OrderOutput {
    /// Rig name.
    pub rig: String,
    /// Method of the printed order.
    pub method: String,
    /// Pinned targets.
    pub pinned: Vec<String>,
    /// The order, most important first.
    pub order: Vec<String>,
    /// Every metric's order (before pinning).
    pub metric_orders: Vec<(String, Vec<String>)>,
    /// Per-target scores.
    pub scores: Scores,
    /// Seconds the scoring took.
    pub seconds: f64,
}

/// `crowdmorph lod order`: the importance order of the rig's targets under `method`, with
/// `pins` first.
pub fn order_command(
    rig: &Rig,
    method: &str,
    pins: &[String],
    image_size: u32,
    json: bool,
) -> Result<OrderOutput> {
    let method = OrderMethod::from_name(method).with_context(|| {
        let names: Vec<&str> = OrderMethod::all().iter().map(|m| m.name()).collect();
        format!("unknown order method {method:?} ({})", names.join(", "))
    })?;
    let pin_ids = resolve_targets(rig, pins)?;
    let (scores, seconds) = score(rig, image_size)?;
    let labels = rig.channel_labels();
    let names = |o: &[TargetId]| labels.of(o);
    let order = pin_front(&scores.order(method), &pin_ids);
    let out = OrderOutput {
        rig: rig.name.clone(),
        method: method.name().to_string(),
        pinned: names(&pin_ids),
        order: names(&order),
        metric_orders: Metric::ALL
            .iter()
            .map(|&m| (m.name().to_string(), names(&scores.metric_order(m))))
            .collect(),
        scores,
        seconds,
    };
    if json {
        println!("{}", serde_json::to_string_pretty(&out)?);
    } else {
        println!(
            "rig {:?}: {} targets scored in {:.2} s ({} px renders); order {}{}:",
            out.rig,
            rig.targets.len(),
            out.seconds,
            out.scores.image_size,
            out.method,
            if out.pinned.is_empty() {
                String::new()
            } else {
                format!(", pinned {}", out.pinned.join(" "))
            }
        );
        for (i, n) in out.order.iter().enumerate() {
            println!("  {:>3}  {n}", i + 1);
        }
    }
    Ok(out)
}

/// What `crowdmorph lod mesh --json` prints.
#[derive(Debug, Serialize)]
pub struct MeshOutput {
    /// Rig name.
    pub rig: String,
    /// Full mesh vertices and triangles.
    pub full: (usize, usize),
    /// Per level: asked fraction, vertices, triangles, stored deltas of the derived rig.
    pub levels: Vec<MeshLevelSummary>,
    /// Detected feature points.
    pub features: FeaturePoints,
}

/// One level of [`MeshOutput`].
#[derive(Debug, Serialize)]
pub struct MeshLevelSummary {
    /// Triangle fraction asked for.
    pub fraction: f32,
    /// Vertices kept.
    pub vertices: usize,
    /// Triangles kept.
    pub triangles: usize,
    /// Stored (non-zero) deltas over all targets of the derived rig.
    pub deltas: usize,
    /// Feature points that survived (all of them, by construction).
    pub features_kept: usize,
}

/// `crowdmorph lod mesh`: feature points and simplified levels; `obj_dir` writes each level's
/// neutral mesh as OBJ and a front render as PNG, for inspection.
pub fn mesh_command(
    rig: &Rig,
    fractions: &[f32],
    obj_dir: Option<&Path>,
    json: bool,
) -> Result<MeshOutput> {
    let started = Instant::now();
    let (levels, features) = build_mesh_levels(rig, fractions, &SimplifyOptions::default(), None)?;
    let seconds = started.elapsed().as_secs_f64();
    let keep = features.vertices();
    let offsets = rig.vertex_offsets();
    let mut out = MeshOutput {
        rig: rig.name.clone(),
        full: (rig.vertex_count(), rig.triangle_count()),
        levels: Vec::new(),
        features,
    };
    for m in &levels {
        let derived = mesh_level_rig(rig, m)?;
        let map = m.vertex_map(&offsets);
        let kept = keep.iter().filter(|v| map.binary_search(v).is_ok()).count();
        out.levels.push(MeshLevelSummary {
            fraction: m.triangle_fraction,
            vertices: derived.vertex_count(),
            triangles: derived.triangle_count(),
            deltas: derived.target_nnz().iter().sum(),
            features_kept: kept,
        });
        if let Some(dir) = obj_dir {
            std::fs::create_dir_all(dir)?;
            let path = dir.join(format!("mesh_{:.0}.obj", m.triangle_fraction * 100.0));
            std::fs::write(&path, neutral_obj(&derived))
                .with_context(|| format!("writing {}", path.display()))?;
            let camera = Camera::for_rig(rig, 768);
            let frame = render_pose(&derived, &neutral_positions(&derived), &camera);
            let path = path.with_extension("png");
            std::fs::write(&path, frame.image.to_png()?)
                .with_context(|| format!("writing {}", path.display()))?;
        }
    }
    if json {
        println!("{}", serde_json::to_string_pretty(&out)?);
    } else {
        println!(
            "rig {:?}: {} vertices, {} triangles; {} feature points ({} landmarks, \
             {} on the lip line, {} motion peaks); simplified in {seconds:.2} s",
            out.rig,
            out.full.0,
            out.full.1,
            keep.len(),
            out.features.landmarks.len(),
            out.features.lip_line.len(),
            out.features.motion_peaks.len()
        );
        let neutral = neutral_positions(rig);
        for l in &out.features.landmarks {
            let p = neutral[l.vertex as usize];
            println!(
                "  {:<16} vertex {:>7} at ({:.3}, {:.3}, {:.3})",
                l.name, l.vertex, p.x, p.y, p.z
            );
        }
        for l in &out.levels {
            println!(
                "  {:>5.1} %: {:>7} vertices {:>7} triangles {:>9} deltas, features kept {}/{}",
                l.fraction * 100.0,
                l.vertices,
                l.triangles,
                l.deltas,
                l.features_kept,
                keep.len()
            );
        }
    }
    Ok(out)
}

/// The neutral mesh of a rig as OBJ text.
fn neutral_obj(rig: &Rig) -> String {
    use std::fmt::Write as _;
    let mut s = String::new();
    let mut base = 1;
    for p in rig.primitives.iter() {
        let _ = writeln!(s, "o {}", p.name.replace(char::is_whitespace, "_"));
        for v in &p.positions {
            let _ = writeln!(s, "v {} {} {}", v.x, v.y, v.z);
        }
        for t in p.indices.chunks_exact(3) {
            let _ = writeln!(s, "f {} {} {}", t[0] + base, t[1] + base, t[2] + base);
        }
        base += p.positions.len() as u32;
    }
    s
}
