//! `crowdmorph lod report|order|mesh|set`: importance orders, their error over a clip and
//! simplified meshes of a rig file, and setting a running server's LOD.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use serde::Serialize;

use crowdmorph::lod::mesh::{FeaturePoints, SimplifyOptions, build_mesh_levels, mesh_level_rig};
use crowdmorph::lod::order::{Metric, OrderMethod, ScoreOptions, Scores, score_targets};
use crowdmorph::lod::raster::{Camera, neutral_positions, render_pose};
use crowdmorph::lod::report::{LodReport, lod_report, report_png, synthetic_clip};
use crowdmorph::lod::{pin_front, resolve_targets};
use crowdmorph::rig::{Rig, TargetId};

use clap::Subcommand;

#[derive(Subcommand)]
/// `crowdmorph lod ...`.
pub enum Command {
    /// Per LOD level, the error against the full rig over a clip for every importance order
    /// (five metrics, combined, file order): a table, --json, and a PNG plot.
    Report {
        /// glTF/GLB rig (default: the embedded head).
        file: Option<PathBuf>,
        /// Clip name; `random` makes a deterministic synthetic clip (for rigs without clips).
        #[arg(long)]
        clip: String,
        /// Targets to pin to the front of every order (repeatable).
        #[arg(long = "pin")]
        pins: Vec<String>,
        /// Write the plot here (PNG).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Side of the renders the image metrics compare, in pixels.
        #[arg(long, default_value_t = 384)]
        size: u32,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Score every target with the five metrics and print the importance order.
    Order {
        /// glTF/GLB rig (default: the embedded head).
        file: Option<PathBuf>,
        /// combined, geometric-mse, hausdorff, image-mse, ssim, yee or file-order.
        #[arg(long, default_value = "combined")]
        method: String,
        /// Targets to pin to the front (repeatable).
        #[arg(long = "pin")]
        pins: Vec<String>,
        /// Side of the renders the image metrics compare, in pixels.
        #[arg(long, default_value_t = 384)]
        size: u32,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Set a registered rig's LOD on a running server (PUT /v1/rigs/{id}/lod): order, pins,
    /// table and mesh levels. The server rebuilds it, persists it with the rig and uses it for
    /// later frames.
    Set {
        /// Rig id on the server.
        id: String,
        /// Server address.
        #[arg(
            long,
            env = "CROWDMORPH_SERVER",
            default_value = "http://127.0.0.1:8080"
        )]
        server: String,
        /// Bearer token, when the server has an admin token.
        #[arg(long, env = "CROWDMORPH_ADMIN_TOKEN", hide_env_values = true)]
        token: Option<String>,
        /// combined (default), geometric-mse, hausdorff, image-mse, ssim, yee or file-order.
        #[arg(long)]
        method: Option<String>,
        /// Targets to pin to the front (repeatable).
        #[arg(long = "pin")]
        pins: Vec<String>,
        /// A level of the table, SHAPES or SHAPES:MESH (repeatable, level 0 first; default
        /// 100/50/25/10/0 % of the targets).
        #[arg(long = "level", value_parser = parse_lod_level)]
        levels: Vec<crowdmorph_proto::LodLevelRequest>,
        /// Simplified meshes to build, as fractions of the triangles.
        #[arg(long, value_delimiter = ',')]
        mesh_fractions: Vec<f32>,
        /// Print the rig as JSON instead of the table.
        #[arg(long)]
        json: bool,
    },
    /// Detect feature points and build simplified mesh levels.
    Mesh {
        /// glTF/GLB rig (default: the embedded head).
        file: Option<PathBuf>,
        /// Triangle fractions of the levels.
        #[arg(long, value_delimiter = ',', default_values_t = [0.5f32, 0.25, 0.1])]
        fractions: Vec<f32>,
        /// Write each level's neutral mesh as OBJ into this folder.
        #[arg(long)]
        obj_dir: Option<PathBuf>,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
    },
}

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

/// `crowdmorph lod report`: the report, and optionally a PNG plot of it.
fn report_command(
    rig: &mut Rig,
    clip: &str,
    pins: &[String],
    image_size: u32,
    png_out: Option<&Path>,
) -> Result<LodReport> {
    let ci = resolve_clip(rig, clip)?;
    let pins = resolve_targets(rig, pins)?;
    let (scores, seconds) = score(rig, image_size)?;
    eprintln!(
        "scored {} targets with 5 metrics in {seconds:.2} s",
        rig.targets.len()
    );
    let report = lod_report(rig, ci, &scores, &pins)?;
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
    /// Targets of the rig.
    #[serde(skip)]
    pub targets: usize,
}

impl std::fmt::Display for OrderOutput {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "rig {:?}: {} targets scored in {:.2} s ({} px renders); order {}{}:",
            self.rig,
            self.targets,
            self.seconds,
            self.scores.image_size,
            self.method,
            if self.pinned.is_empty() {
                String::new()
            } else {
                format!(", pinned {}", self.pinned.join(" "))
            }
        )?;
        for (i, n) in self.order.iter().enumerate() {
            writeln!(f, "  {:>3}  {n}", i + 1)?;
        }
        Ok(())
    }
}

impl super::Report for OrderOutput {}

/// `crowdmorph lod order`: the importance order of the rig's targets under `method`, with
/// `pins` first.
fn order_command(rig: &Rig, method: &str, pins: &[String], image_size: u32) -> Result<OrderOutput> {
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
        targets: rig.targets.len(),
    };
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
    /// Seconds the simplification took.
    #[serde(skip)]
    pub seconds: f64,
    /// Feature points kept by every level.
    #[serde(skip)]
    pub feature_points: usize,
    /// Where each landmark is on the neutral mesh.
    #[serde(skip)]
    pub landmark_positions: Vec<[f32; 3]>,
}

impl std::fmt::Display for MeshOutput {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "rig {:?}: {} vertices, {} triangles; {} feature points ({} landmarks, \
             {} on the lip line, {} motion peaks); simplified in {:.2} s",
            self.rig,
            self.full.0,
            self.full.1,
            self.feature_points,
            self.features.landmarks.len(),
            self.features.lip_line.len(),
            self.features.motion_peaks.len(),
            self.seconds
        )?;
        for (l, p) in self.features.landmarks.iter().zip(&self.landmark_positions) {
            writeln!(
                f,
                "  {:<16} vertex {:>7} at ({:.3}, {:.3}, {:.3})",
                l.name, l.vertex, p[0], p[1], p[2]
            )?;
        }
        for l in &self.levels {
            writeln!(
                f,
                "  {:>5.1} %: {:>7} vertices {:>7} triangles {:>9} deltas, features kept {}/{}",
                l.fraction * 100.0,
                l.vertices,
                l.triangles,
                l.deltas,
                l.features_kept,
                self.feature_points
            )?;
        }
        Ok(())
    }
}

impl super::Report for MeshOutput {}

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
fn mesh_command(rig: &Rig, fractions: &[f32], obj_dir: Option<&Path>) -> Result<MeshOutput> {
    let started = Instant::now();
    let (levels, features) = build_mesh_levels(rig, fractions, &SimplifyOptions::default(), None)?;
    let seconds = started.elapsed().as_secs_f64();
    let keep = features.vertices();
    let offsets = rig.vertex_offsets();
    let neutral = neutral_positions(rig);
    let mut out = MeshOutput {
        rig: rig.name.clone(),
        full: (rig.vertex_count(), rig.triangle_count()),
        levels: Vec::new(),
        landmark_positions: features
            .landmarks
            .iter()
            .map(|l| neutral[l.vertex as usize].to_array())
            .collect(),
        features,
        seconds,
        feature_points: keep.len(),
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

/// Parses a `--level SHAPES[:MESH]` argument of `lod set` (the mesh is an index into the
/// request's mesh fractions).
pub fn parse_lod_level(s: &str) -> Result<crowdmorph_proto::LodLevelRequest> {
    let (shapes, mesh) = match s.split_once(':') {
        Some((a, b)) => (a, Some(b)),
        None => (s, None),
    };
    Ok(crowdmorph_proto::LodLevelRequest {
        shapes: shapes
            .trim()
            .parse()
            .with_context(|| format!("level {s:?}: shapes must be a whole number"))?,
        mesh: mesh
            .map(|m| m.trim().parse())
            .transpose()
            .with_context(|| format!("level {s:?}: the mesh must be a whole number"))?,
    })
}

/// `crowdmorph lod set`: sets a registered rig's LOD on a running server (`PUT
/// /v1/rigs/{id}/lod`), where it is rebuilt, persisted with the rig and used by later frames.
fn lod_set(
    server: &str,
    token: Option<&str>,
    id: &str,
    request: &crowdmorph_proto::LodRequest,
) -> Result<crowdmorph_proto::RigInfo> {
    let mut client = crowdmorph_client::Client::new(server.trim_end_matches('/'));
    if let Some(t) = token {
        client = client.with_token(t);
    }
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("starting the tokio runtime")?;
    runtime
        .block_on(client.set_lod(id, request))
        .with_context(|| format!("setting the LOD of rig {id:?} on {server}"))
}

/// A rig's LOD as `lod set` prints it: the table as text, the rig as JSON.
#[derive(Serialize)]
#[serde(transparent)]
pub struct LodTable(pub crowdmorph_proto::RigInfo);

impl std::fmt::Display for LodTable {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&lod_table_text(&self.0))
    }
}

impl super::Report for LodTable {}
impl super::Report for LodReport {}

/// The LOD table of a rig as text, a line per level.
fn lod_table_text(info: &crowdmorph_proto::RigInfo) -> String {
    let lod = &info.lod;
    let mut s = format!(
        "rig {:?}: LOD {} ({}), pinned [{}]\n",
        info.id,
        lod.method,
        lod.status,
        lod.pinned.join(", ")
    );
    for (i, l) in lod.levels.iter().enumerate() {
        let _ = writeln!(
            s,
            "  level {i}: {:>3} shapes, {} vertices, {} triangles{}",
            l.shapes,
            l.vertices,
            l.triangles,
            l.mesh.map_or(String::new(), |m| format!(" (mesh {m})"))
        );
    }
    s
}

/// Runs one `lod` command and prints its report.
pub fn run(which: Command) -> Result<()> {
    match which {
        Command::Set {
            id,
            server,
            token,
            method,
            pins,
            levels,
            mesh_fractions,
            json,
        } => {
            let request = crowdmorph_proto::LodRequest {
                method,
                pinned: pins,
                levels: (!levels.is_empty()).then_some(levels),
                mesh_fractions,
                ..crowdmorph_proto::LodRequest::default()
            };
            let info = lod_set(&server, token.as_deref(), &id, &request)?;
            super::emit(&LodTable(info), json)
        }
        Command::Report {
            file,
            clip,
            pins,
            out,
            size,
            json,
        } => {
            let mut rig = super::load_rig(file.as_deref())?;
            let report = report_command(&mut rig, &clip, &pins, size, out.as_deref())?;
            super::emit(&report, json)
        }
        Command::Order {
            file,
            method,
            pins,
            size,
            json,
        } => {
            let rig = super::load_rig(file.as_deref())?;
            super::emit(&order_command(&rig, &method, &pins, size)?, json)
        }
        Command::Mesh {
            file,
            fractions,
            obj_dir,
            json,
        } => {
            let rig = super::load_rig(file.as_deref())?;
            super::emit(&mesh_command(&rig, &fractions, obj_dir.as_deref())?, json)
        }
    }
}
