//! How much each LOD level loses over a clip, for every importance order.
//!
//! For an order and a level, every frame of the clip is compared with the full rig (level 0):
//! the per-vertex distances are summarised as the maximum and the RMS over all frames and
//! vertices, both as fractions of the bounding-box diagonal. Comparing the orders of the five
//! metrics, the combined order and the file order (the paper's unordered truncation) shows what
//! ordering buys.
//!
//! Rigs without clips (ICT FaceKit) get a synthetic one ([`synthetic_clip`]): smooth,
//! deterministic activations of every target, a few at a time, like captured facial animation.

use crowdmorph_core::rng::SplitMix64;
use std::fmt::Write as _;

use serde::{Deserialize, Serialize};

use glam::Vec3;
use rayon::prelude::*;

use super::order::{OrderMethod, Scores, SparseIndex};
use super::pin_front;
use super::plot::{Plot, Series};
use crowdmorph_core::rig::{
    ACTIVE_WEIGHT_EPSILON, Clip, ClipError, DEFAULT_FPS, Lod, LodError, LodLevel, Rig, TargetId,
    default_lod_levels,
};

/// Error of one level of one order over a clip.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LevelError {
    /// Level index.
    pub level: u32,
    /// Shapes the level evaluates.
    pub shapes: u32,
    /// Largest vertex distance to the full rig over the clip, / bbox diagonal.
    pub max: f64,
    /// RMS vertex distance to the full rig over the clip and all vertices, / bbox diagonal.
    pub rms: f64,
}

/// One order's errors at every level.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct OrderReport {
    /// `combined`, a metric's name, or `file-order`.
    pub method: String,
    /// Target names in order, most important first.
    pub order: Vec<String>,
    /// Errors per level.
    pub levels: Vec<LevelError>,
}

/// The report `crowdmorph lod report` prints.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LodReport {
    /// Rig name.
    pub rig: String,
    /// Clip name.
    pub clip: String,
    /// Frames evaluated.
    pub frames: u32,
    /// Vertices of the rig.
    pub vertices: usize,
    /// Bounding-box diagonal the errors are divided by.
    pub bbox_diagonal: f32,
    /// Targets pinned to the front of every order.
    pub pinned: Vec<String>,
    /// Per order.
    pub orders: Vec<OrderReport>,
    /// Scores the orders came from.
    pub scores: Scores,
    /// On a skinned rig, what each LOD level does to its joints (empty otherwise).
    #[serde(default)]
    pub joints: Vec<JointLevelReport>,
}

/// The joints one LOD level holds at rest (`crowdmorph_core::rig::JointLod`) and what that costs.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JointLevelReport {
    /// Level index.
    pub level: u32,
    /// Nodes held at rest, by name.
    pub dropped: Vec<String>,
    /// The sum of their effects, / bbox diagonal: the most holding them can move a vertex in
    /// a pose within their ranges (estimated from the rest pose's lever arms).
    pub bound: f64,
    /// Measured over the report's clip: the largest vertex distance between the level's
    /// joints and every joint (all shapes both times), / bbox diagonal.
    pub measured: f64,
}

/// Frames of a clip the joint measurement evaluates at most (evenly spread).
const JOINT_FRAMES: u32 = 64;

/// What each LOD level of `rig` does to its joints over clip `clip` (none without a
/// skeleton): the dropped nodes, their bound, and the error measured with the CPU engine.
pub fn joint_levels(rig: &Rig, clip: usize) -> Result<Vec<JointLevelReport>, ReportError> {
    use crate::cpu::CpuRig;
    use crate::{BlendJob, OutputSpec, WeightBatch};
    let Some(sk) = &rig.skeleton else {
        return Ok(Vec::new());
    };
    let c = rig.clips.get(clip).ok_or(ReportError::NoSuchClip(clip))?;
    let joint_lod = crowdmorph_core::rig::JointLod::of(rig);
    let diag = f64::from(rig.bbox().diagonal()).max(1e-30);
    let step = c.frames.div_ceil(JOINT_FRAMES).max(1);
    let frames: Vec<u32> = (0..c.frames).step_by(step as usize).collect();
    let cpu = CpuRig::new(rig);
    let evaluate = |level: Option<u32>| -> Result<Vec<f32>, ReportError> {
        let jobs: Vec<BlendJob> = frames
            .iter()
            .map(|&f| BlendJob {
                joints: level.map_or(crowdmorph_core::rig::JointPose::NONE, |l| {
                    joint_lod
                        .level(l)
                        .joints(&crowdmorph_core::rig::JointPose::NONE)
                }),
                ..BlendJob::frame(clip as u32, f, 0)
            })
            .collect();
        let batch =
            WeightBatch::gather(rig, &jobs).map_err(|e| ReportError::Engine(e.to_string()))?;
        let out = cpu
            .evaluate(&batch, OutputSpec::default())
            .map_err(|e| ReportError::Engine(e.to_string()))?;
        Ok(out.positions.to_f32())
    };
    let full = evaluate(None)?;
    let mut out = Vec::with_capacity(rig.lod.levels.len());
    for l in 0..rig.lod.levels.len() as u32 {
        let dropped = joint_lod
            .dropped
            .get(l as usize)
            .cloned()
            .unwrap_or_default();
        let measured = if dropped.is_empty() {
            0.0
        } else {
            let cut = evaluate(Some(l))?;
            full.chunks_exact(3)
                .zip(cut.chunks_exact(3))
                .map(|(a, b)| {
                    let d: f64 = (0..3).map(|k| f64::from(a[k] - b[k]).powi(2)).sum();
                    d.sqrt()
                })
                .fold(0f64, f64::max)
        };
        out.push(JointLevelReport {
            level: l,
            dropped: dropped
                .iter()
                .map(|&n| sk.nodes[n as usize].name.clone())
                .collect(),
            bound: f64::from(joint_lod.error(l)) / diag,
            measured: measured / diag,
        });
    }
    Ok(out)
}

impl LodReport {
    /// The report of the order named `method`.
    pub fn order(&self, method: &str) -> Option<&OrderReport> {
        self.orders.iter().find(|o| o.method == method)
    }
}

/// A deterministic plausible clip for a rig without animation: `frames` frames at 30 fps in
/// which every target rises and falls in two smooth raised-cosine bumps (10–40 frames wide,
/// peaks 0.3–1.0) at random times, so about a third of the targets are active in a frame.
pub fn synthetic_clip(rig: &Rig, name: &str, frames: usize, seed: u64) -> Result<Clip, ClipError> {
    let n = rig.targets.len();
    let frames = frames.max(1);
    let mut weights = vec![0f32; n * frames];
    for t in 0..n {
        let mut rng = SplitMix64(seed ^ (t as u64).wrapping_mul(0xA076_1D64_78BD_642F));
        for _ in 0..2 {
            let centre = rng.unit() * frames as f32;
            let width = 10.0 + 30.0 * rng.unit();
            let peak = 0.3 + 0.7 * rng.unit();
            for f in 0..frames {
                let x = (f as f32 - centre) / (width * 0.5);
                if x.abs() < 1.0 {
                    let w = &mut weights[t * frames + f];
                    let bump = peak * 0.5 * (1.0 + (std::f32::consts::PI * x).cos());
                    *w = (*w + bump).min(1.0);
                }
            }
        }
    }
    Clip::new(name, DEFAULT_FPS, n, frames, weights)
}

/// Why a report could not be made.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ReportError {
    /// The clip index is out of range.
    #[error("clip index {0} out of range")]
    NoSuchClip(usize),
    /// The order or the levels are not valid for the rig.
    #[error(transparent)]
    Lod(#[from] LodError),
    /// The engine could not evaluate the clip (joint measurement).
    #[error("evaluating the clip: {0}")]
    Engine(String),
}

/// Every target's displacement over the whole rig, sparse (global vertex ids), prepared once
/// and shared by every order a report compares.
pub struct Displacements {
    vertices: usize,
    targets: Vec<(Vec<u32>, Vec<Vec3>)>,
}

impl Displacements {
    /// Gathers the displacements of every target of `rig`.
    pub fn new(rig: &Rig) -> Displacements {
        let sparse = SparseIndex::new(rig);
        Displacements {
            vertices: rig.vertex_count(),
            targets: (0..rig.targets.len() as TargetId)
                .map(|t| sparse.displacement(rig, t))
                .collect(),
        }
    }
}

/// Errors of `order` with `levels` over clip `clip` of `rig`.
///
/// A level evaluates the first `shapes` targets of the order, so its difference from the full
/// rig is exactly minus the weighted deltas of the targets it drops. That sum is accumulated in
/// f64 from the sparse deltas with the engines' rule for active weights (|w| > 1e-6), so level
/// 0 is exactly 0, a level of no shapes is the same for every order, and orders are compared
/// without the engines' f32 rounding in the way. (The engines are held to the same Eq. 1 by
/// their own tests against the f64 oracle.) Frames run in parallel; the reduction is in frame
/// order, so the result does not depend on the thread count.
pub fn clip_errors(
    rig: &Rig,
    disp: &Displacements,
    clip: usize,
    order: &[TargetId],
    levels: &[LodLevel],
) -> Result<Vec<LevelError>, ReportError> {
    let c = rig.clips.get(clip).ok_or(ReportError::NoSuchClip(clip))?;
    let n = rig.targets.len();
    let check = Lod {
        order: order.to_vec(),
        levels: levels.iter().map(|l| LodLevel::shapes(l.shapes)).collect(),
        method: "report".into(),
        pinned: Vec::new(),
        meshes: Vec::new(),
        pca: Vec::new(),
    };
    check.validate(n)?;
    // Levels by shape count, most shapes first: each drops a superset of the previous one's
    // targets, so one running sum serves them all.
    let mut by_shapes: Vec<usize> = (0..levels.len()).collect();
    by_shapes.sort_by(|&a, &b| levels[b].shapes.cmp(&levels[a].shapes).then(a.cmp(&b)));
    let per_frame: Vec<Vec<(f64, f64)>> = (0..c.frames)
        .into_par_iter()
        .map(|f| {
            let mut acc = vec![[0f64; 3]; disp.vertices];
            let mut stats = vec![(0f64, 0f64); levels.len()];
            let mut kept = n;
            for &l in &by_shapes {
                let shapes = levels[l].shapes as usize;
                for &t in &order[shapes..kept] {
                    let w = c.weight(t as usize, f);
                    if w.abs() <= ACTIVE_WEIGHT_EPSILON {
                        continue;
                    }
                    let (vs, ds) = &disp.targets[t as usize];
                    for (&v, d) in vs.iter().zip(ds) {
                        let a = &mut acc[v as usize];
                        a[0] += f64::from(w) * f64::from(d.x);
                        a[1] += f64::from(w) * f64::from(d.y);
                        a[2] += f64::from(w) * f64::from(d.z);
                    }
                }
                kept = kept.min(shapes);
                let (mut max, mut sum) = (0f64, 0f64);
                for a in &acc {
                    let d2 = a[0] * a[0] + a[1] * a[1] + a[2] * a[2];
                    sum += d2;
                    max = max.max(d2);
                }
                stats[l] = (max.sqrt(), sum);
            }
            stats
        })
        .collect();
    let diag = f64::from(rig.bbox().diagonal()).max(1e-30);
    let count = (c.frames as usize * disp.vertices).max(1) as f64;
    Ok(levels
        .iter()
        .enumerate()
        .map(|(l, lv)| {
            let (mut max, mut sum) = (0f64, 0f64);
            for s in &per_frame {
                max = max.max(s[l].0);
                sum += s[l].1;
            }
            LevelError {
                level: l as u32,
                shapes: lv.shapes,
                max: max / diag,
                rms: (sum / count).sqrt() / diag,
            }
        })
        .collect())
}

/// Builds the report for clip `clip` of `rig` from `scores`: the combined order, each metric's
/// order and file order, all with `pins` moved to the front, at the default levels.
pub fn lod_report(
    rig: &Rig,
    clip: usize,
    scores: &Scores,
    pins: &[TargetId],
) -> Result<LodReport, ReportError> {
    let levels = default_lod_levels(rig.targets.len());
    let c = rig.clips.get(clip).ok_or(ReportError::NoSuchClip(clip))?;
    let disp = Displacements::new(rig);
    let labels = rig.channel_labels();
    let mut orders = Vec::new();
    for method in OrderMethod::all() {
        let order = pin_front(&scores.order(method), pins);
        orders.push(OrderReport {
            method: method.name().to_string(),
            order: labels.of(&order),
            levels: clip_errors(rig, &disp, clip, &order, &levels)?,
        });
    }
    Ok(LodReport {
        rig: rig.name.clone(),
        clip: c.name.clone(),
        frames: c.frames,
        vertices: rig.vertex_count(),
        bbox_diagonal: rig.bbox().diagonal(),
        pinned: labels.of(pins),
        orders,
        scores: scores.clone(),
        joints: joint_levels(rig, clip)?,
    })
}

/// The report as a text table: per level, max and RMS error (% of the bbox diagonal) of each
/// order, then the per-target scores.
impl std::fmt::Display for LodReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&report_text(self))
    }
}

/// The report as text (its [`std::fmt::Display`]).
pub fn report_text(r: &LodReport) -> String {
    let mut o = String::new();
    let _ = writeln!(
        o,
        "rig {:?}, clip {:?}: {} frames, {} vertices, bbox diagonal {:.4}{}",
        r.rig,
        r.clip,
        r.frames,
        r.vertices,
        r.bbox_diagonal,
        if r.pinned.is_empty() {
            String::new()
        } else {
            format!(", pinned: {}", r.pinned.join(" "))
        }
    );
    let _ = writeln!(
        o,
        "error against the full rig over the clip, % of the bbox diagonal (max / rms):"
    );
    let _ = write!(o, "{:<8}{:>7}", "level", "shapes");
    for ord in &r.orders {
        let _ = write!(o, " {:>19}", ord.method);
    }
    let _ = writeln!(o);
    let levels = r.orders.first().map_or(0, |x| x.levels.len());
    for l in 0..levels {
        let shapes = r.orders[0].levels[l].shapes;
        let _ = write!(o, "{l:<8}{shapes:>7}");
        for ord in &r.orders {
            let e = &ord.levels[l];
            let _ = write!(o, " {:>9.4} / {:<7.4}", e.max * 100.0, e.rms * 100.0);
        }
        let _ = writeln!(o);
    }
    if let (Some(best), Some(file)) = (r.order("combined"), r.order("file-order")) {
        let wins = best
            .levels
            .iter()
            .zip(&file.levels)
            .filter(|(a, b)| no_worse(a, b))
            .count();
        let _ = writeln!(
            o,
            "combined order vs unordered truncation: no worse (max and rms) at {wins} of {} levels",
            best.levels.len()
        );
    }
    if !r.joints.is_empty() {
        let _ = writeln!(
            o,
            "joints held at rest (error bound / measured over the clip, % of the bbox diagonal):"
        );
        for j in &r.joints {
            let _ = writeln!(
                o,
                "  level {}: {:>8.4} / {:<8.4} {}",
                j.level,
                j.bound * 100.0,
                j.measured * 100.0,
                if j.dropped.is_empty() {
                    "none".to_string()
                } else {
                    j.dropped.join(" ")
                }
            );
        }
    }
    let _ = writeln!(
        o,
        "scores against neutral ({} px renders; rank in the combined order):",
        r.scores.image_size
    );
    let _ = writeln!(
        o,
        "  {:<22} {:>5} {:>12} {:>10} {:>12} {:>9} {:>8}",
        "target", "rank", "geom MSE", "Hausdorff", "image MSE", "1-SSIM", "Yee px"
    );
    let combined = r.scores.combined_order();
    for (rank, &t) in combined.iter().enumerate() {
        let s = &r.scores.targets[t as usize];
        let _ = writeln!(
            o,
            "  {:<22} {:>5} {:>12.4e} {:>10.4} {:>12.4e} {:>9.5} {:>8}",
            s.name,
            rank + 1,
            s.geometric_mse,
            s.hausdorff,
            s.image_mse,
            1.0 - s.ssim,
            s.yee_failed_pixels
        );
    }
    o
}

/// Whether level error `a` is no worse than `b` in both max and RMS, allowing for f64
/// rounding (sums in a different order differ in the last bits).
pub fn no_worse(a: &LevelError, b: &LevelError) -> bool {
    let tol = |x: f64| x * 1e-9 + 1e-15;
    a.max <= b.max + tol(b.max) && a.rms <= b.rms + tol(b.rms)
}

/// The report as a PNG: RMS (left) and max (right) error per level for every order.
pub fn report_png(r: &LodReport) -> Result<Vec<u8>, png::EncodingError> {
    let series = |pick: fn(&LevelError) -> f64| -> Vec<Series> {
        r.orders
            .iter()
            .map(|o| Series {
                label: o.method.clone(),
                points: o
                    .levels
                    .iter()
                    .map(|e| (f64::from(e.shapes), pick(e) * 100.0))
                    .collect(),
            })
            .collect()
    };
    let plot = Plot {
        title: format!("{} / {}", r.rig, r.clip),
        panels: vec![
            ("RMS ERROR % DIAG VS SHAPES".to_string(), series(|e| e.rms)),
            ("MAX ERROR % DIAG VS SHAPES".to_string(), series(|e| e.max)),
        ],
    };
    plot.to_png()
}
