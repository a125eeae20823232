//! `crowdmorph clips graph`: a motion graph built from a rig file's clips (Kovar et al. 2002),
//! its edges' costs, and the graph as JSON to `PUT /v1/rigs/{id}/graphs/{name}`.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Subcommand;
use serde::Serialize;

use crowdmorph::graph::{BuildOptions, Built, Graph, build};

#[derive(Subcommand)]
/// `crowdmorph clips ...`.
pub enum Command {
    /// Find transitions between the rig's clips (frame distances in vertex space over a window,
    /// local minima under a threshold), cut the clips into nodes there, prune to the largest
    /// strongly connected component, and report each edge's cost.
    Graph {
        /// glTF/GLB rig with clips (default: the embedded head).
        rig: Option<PathBuf>,
        /// Frames compared per transition, and its cross-fade.
        #[arg(long, default_value_t = 5)]
        window: u32,
        /// Largest mean RMS vertex distance of a transition, as a fraction of the rig's
        /// bounding-box diagonal.
        #[arg(long, default_value_t = 0.02)]
        threshold: f32,
        /// Most transitions per (source clip, target clip).
        #[arg(long, default_value_t = 8)]
        per_pair: usize,
        /// Write the graph here as JSON (the body of `PUT /v1/rigs/{id}/graphs/{name}`).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Compress the rig's clips within a vertex-space error budget (per-curve quantization,
    /// the library's PCA, or the clip's own transform in vertex space, whichever is smallest per
    /// clip; temporal prediction, zstd segments) and report, as ACL does, the ratio against
    /// f32 per clip and over all, the largest vertex error, its p99 and the share of samples
    /// under the budget.
    Compress {
        /// glTF/GLB rig with clips (default: the embedded head).
        rig: Option<PathBuf>,
        /// Also a CSV clip by target name (a Live Link Face capture, `clips export`'s files);
        /// repeat for more. Columns the rig has no target for (head and eye angles) are skipped.
        #[arg(long = "clip")]
        clips: Vec<PathBuf>,
        /// Frame rate of the CSV clips' rows.
        #[arg(long, default_value_t = 60.0)]
        fps: f32,
        /// Also a synthetic tracker capture of this many frames at 60 fps (52 ARKit channels,
        /// `crowdmorph::synthetic::face_capture`, seed 48), as a clip `synthetic-capture`.
        #[arg(long)]
        synthetic_capture: Option<usize>,
        /// Largest vertex error, as a fraction of the rig's bounding-box diagonal.
        #[arg(long, default_value_t = 3e-4)]
        max_error: f32,
        /// Write the decoded weights here as CSV (`clip,frame,` then one column per channel),
        /// so that the error can be checked independently.
        #[arg(long)]
        out: Option<PathBuf>,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Write each of the rig's clips as CSV by target name (`<clip>.csv`: a header of the
    /// target names, one row of weights per frame), the form `POST /v1/rigs/{id}/clips` and
    /// `bench --clips DIR` read: the embedded head's ARKit-named clips then drive another
    /// ARKit-named face.
    Export {
        /// glTF/GLB rig with clips (default: the embedded head).
        rig: Option<PathBuf>,
        /// The folder to write the files into (made if missing).
        #[arg(long)]
        out: PathBuf,
    },
    /// Compress an animated texture (an image sequence, one image per clip frame) with PCA per
    /// region (GPU Gems 3 ch. 15: a mean, each region's leading components, one coefficient per
    /// frame each) into the body of `PUT /v1/rigs/{id}/clips/{clip}/texture`, and report each
    /// region's reconstruction error in 8-bit sRGB units.
    CompressTexture {
        /// A folder of PNG, JPEG or WebP frames, played in file-name order, all one size.
        #[arg(long)]
        frames: PathBuf,
        /// Regions as JSON, `[{"name": "eyes", "rect": [x, y, w, h], "components": 8}, ...]`;
        /// a pixel belongs to the first region that holds it (default: an eye band across rows
        /// 20–45 % with 8 components, the rest with 4).
        #[arg(long)]
        regions: Option<PathBuf>,
        /// The clip it plays with.
        #[arg(long)]
        clip: String,
        /// The material whose base colour it animates.
        #[arg(long, default_value_t = 0)]
        material: u32,
        /// Where to write the compressed texture.
        #[arg(short, long)]
        out: PathBuf,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
    },
}

/// What `clips compress-texture` reports.
#[derive(Serialize)]
pub struct TextureReport {
    /// Frames read.
    pub frames: u32,
    /// Their size.
    pub width: u32,
    /// Their size.
    pub height: u32,
    /// Bytes written.
    pub bytes: usize,
    /// Per region (and `(none)` for pixels no region holds).
    pub regions: Vec<crowdmorph::texture::RegionError>,
}

impl super::Report for TextureReport {}

impl std::fmt::Display for TextureReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "{} frames of {} × {} → {} bytes",
            self.frames, self.width, self.height, self.bytes
        )?;
        for r in &self.regions {
            writeln!(
                f,
                "  {:>12} {:>2} components {:>8} pixels  RMS {:.3}  max {:.2} (8-bit sRGB)",
                r.name, r.components, r.pixels, r.rms_8bit, r.max_8bit
            )?;
        }
        Ok(())
    }
}

/// The frames in `dir` (file-name order) as linear RGB, with their size.
fn read_frames(dir: &std::path::Path) -> Result<(u32, u32, Vec<Vec<f32>>)> {
    let mut paths: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("reading {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.extension().and_then(|e| e.to_str()).is_some_and(|e| {
                ["png", "jpg", "jpeg", "webp"].contains(&e.to_ascii_lowercase().as_str())
            })
        })
        .collect();
    paths.sort();
    anyhow::ensure!(
        !paths.is_empty(),
        "no PNG, JPEG or WebP frames in {}",
        dir.display()
    );
    anyhow::ensure!(
        paths.len() <= crowdmorph::rig::MAX_FRAMES,
        "{} frames; a clip holds at most {}",
        paths.len(),
        crowdmorph::rig::MAX_FRAMES
    );
    // The command line's own memory: frames are decoded one at a time, and the frames kept
    // (f32 RGB) are the input of the PCA.
    let budget = crowdmorph::budget::Budget::new(u64::MAX, "the command line", None);
    let mut size = None;
    let mut out = Vec::with_capacity(paths.len());
    for (i, p) in paths.iter().enumerate() {
        let bytes = std::fs::read(p).with_context(|| format!("reading {}", p.display()))?;
        let (image, _) = crowdmorph::import::image::decode(
            i,
            bytes.into(),
            None,
            crowdmorph::rig::MAX_ANIMATED_SIZE,
            &budget,
        )
        .map_err(|e| anyhow::anyhow!("{}: {e}", p.display()))?;
        let level = image
            .pixels
            .as_ref()
            .and_then(|m| m.levels.first())
            .with_context(|| format!("{}: no pixels", p.display()))?;
        let dims = (level.width, level.height);
        anyhow::ensure!(
            *size.get_or_insert(dims) == dims,
            "{} is {} × {}, the first frame {:?}",
            p.display(),
            dims.0,
            dims.1,
            size
        );
        out.push(
            level
                .rgba
                .chunks_exact(4)
                .flat_map(|px| [px[0], px[1], px[2]])
                .map(crowdmorph::render::brdf::srgb8_to_linear)
                .collect(),
        );
    }
    let (w, h) = size.unwrap_or((1, 1));
    Ok((w, h, out))
}

/// One clip of `clips compress`.
#[derive(Serialize)]
pub struct ClipRow {
    /// Clip name.
    pub clip: String,
    /// Frames.
    pub frames: u32,
    /// Codec used: `curves`, `pca` or `transform` (the smallest at the budget).
    pub codec: &'static str,
    /// Components kept (`pca`: of the library's basis; `transform`: the clip's own directions).
    pub components: Option<usize>,
    /// Bytes of the f32 table.
    pub f32_bytes: usize,
    /// Bytes compressed.
    pub bytes: usize,
    /// `f32_bytes / bytes`.
    pub ratio: f64,
    /// The vertex errors, as fractions of the diagonal.
    #[serde(flatten)]
    pub error: crowdmorph::compress::ErrorReport,
}

/// What `clips compress` reports.
#[derive(Serialize)]
pub struct CompressReport {
    /// The rig's name.
    pub rig: String,
    /// The budget, as a fraction of the diagonal.
    pub max_error: f32,
    /// Per clip.
    pub clips: Vec<ClipRow>,
    /// Bytes of the shared PCA basis (mean and the components the clips use), counted once.
    pub basis_bytes: usize,
    /// All clips: f32 bytes over compressed bytes (the basis included).
    pub ratio: f64,
}

impl super::Report for CompressReport {}

impl std::fmt::Display for CompressReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "rig {:?}, budget {:e} × diagonal: {:.1}× smaller than f32 over all clips \
             (shared PCA basis: {} bytes)",
            self.rig, self.max_error, self.ratio, self.basis_bytes
        )?;
        for c in &self.clips {
            writeln!(
                f,
                "  {:>16} {:>5} frames  {:>8} → {:>7} bytes ({:>5.1}×, {}{})  max {:.2e}  p99 {:.2e}  under budget {:.4} %",
                c.clip,
                c.frames,
                c.f32_bytes,
                c.bytes,
                c.ratio,
                c.codec,
                c.components
                    .map_or(String::new(), |m| format!(", {m} components")),
                c.error.max,
                c.error.p99,
                c.error.under_budget * 100.0
            )?;
        }
        Ok(())
    }
}

/// What `clips graph` reports.
#[derive(Serialize)]
pub struct GraphReport {
    /// The rig's name.
    pub rig: String,
    /// What was found.
    #[serde(flatten)]
    pub built: Built,
}

impl super::Report for GraphReport {}

impl std::fmt::Display for GraphReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let g = &self.built.graph;
        writeln!(
            f,
            "rig {:?}: {} candidate transitions; graph of {} nodes and {} edges ({} nodes outside \
             the largest strongly connected component dropped)",
            self.rig,
            self.built.candidates,
            g.nodes.len(),
            g.edges.len(),
            self.built.dropped_nodes
        )?;
        for (e, cost) in g.edges.iter().zip(&self.built.costs) {
            let kind = if *cost == 0.0 && e.fade == 1 {
                "plays on".to_string()
            } else {
                format!("cost {cost:.2e} × diagonal")
            };
            writeln!(
                f,
                "  {:>24} → {:<24} fade {:>2}, from frame {:>4}: {kind}",
                e.from,
                e.to,
                e.fade,
                e.window.map_or(0, |w| w[0])
            )?;
        }
        Ok(())
    }
}

/// Runs `crowdmorph clips ...`.
pub fn run(which: Command) -> Result<()> {
    match which {
        Command::CompressTexture {
            frames,
            regions,
            clip,
            material,
            out,
            json,
        } => {
            let (w, h, seq) = read_frames(&frames)?;
            let regions: Vec<crowdmorph::rig::TextureRegion> = match regions {
                Some(p) => {
                    let text =
                        std::fs::read(&p).with_context(|| format!("reading {}", p.display()))?;
                    serde_json::from_slice(&text)
                        .with_context(|| format!("{}: regions", p.display()))?
                }
                None => crowdmorph::texture::default_regions(w, h),
            };
            let t = crowdmorph::texture::compress(&clip, material, w, h, &seq, &regions)?;
            let errors = crowdmorph::texture::measure(&t, &seq);
            let bytes = t.to_bytes();
            std::fs::write(&out, &bytes).with_context(|| format!("writing {}", out.display()))?;
            super::emit(
                &TextureReport {
                    frames: t.frames,
                    width: w,
                    height: h,
                    bytes: bytes.len(),
                    regions: errors,
                },
                json,
            )
        }
        Command::Export { rig, out } => {
            let rig = super::load_rig(rig.as_deref())?;
            std::fs::create_dir_all(&out).with_context(|| format!("making {}", out.display()))?;
            for clip in &rig.clips {
                let frames = clip.frames as usize;
                let mut csv = rig.targets.join(",");
                csv.push('\n');
                for f in 0..frames {
                    let row: Vec<String> = (0..rig.targets.len())
                        .map(|t| clip.weights[t * frames + f].to_string())
                        .collect();
                    csv.push_str(&row.join(","));
                    csv.push('\n');
                }
                // Clip names become file names: keep them plain.
                let file: String = clip
                    .name
                    .chars()
                    .map(|c| {
                        if c.is_ascii_alphanumeric() || "-_.".contains(c) {
                            c
                        } else {
                            '_'
                        }
                    })
                    .collect();
                let path = out.join(format!("{file}.csv"));
                std::fs::write(&path, csv)
                    .with_context(|| format!("writing {}", path.display()))?;
                println!("{} ({} frames)", path.display(), frames);
            }
            Ok(())
        }
        Command::Compress {
            rig,
            clips,
            fps,
            synthetic_capture,
            max_error,
            out,
            json,
        } => {
            anyhow::ensure!(
                max_error.is_finite() && max_error > 0.0,
                "--max-error must be a positive fraction of the diagonal"
            );
            let mut rig = super::load_rig(rig.as_deref())?;
            let mut sources = Vec::new();
            for path in &clips {
                let bytes =
                    std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
                let name = path
                    .file_stem()
                    .map_or("capture".into(), |s| s.to_string_lossy().into_owned());
                sources.push((name, bytes, path.display().to_string(), fps));
            }
            if let Some(frames) = synthetic_capture {
                anyhow::ensure!(
                    (1..=crowdmorph::rig::MAX_FRAMES).contains(&frames),
                    "--synthetic-capture must be 1 to {} frames",
                    crowdmorph::rig::MAX_FRAMES
                );
                // Through the CSV reader, which maps the ARKit names onto the rig's targets.
                let table = crowdmorph::synthetic::face_capture(frames, 48);
                let mut csv = crowdmorph::synthetic::ARKIT_NAMES.join(",");
                csv.push('\n');
                for f in 0..frames {
                    let row: Vec<String> = (0..crowdmorph::synthetic::ARKIT_NAMES.len())
                        .map(|k| table[k * frames + f].to_string())
                        .collect();
                    csv.push_str(&row.join(","));
                    csv.push('\n');
                }
                sources.push((
                    "synthetic-capture".into(),
                    csv.into_bytes(),
                    "the synthetic capture".into(),
                    60.0,
                ));
            }
            for (name, bytes, path, fps) in sources {
                let options = crowdmorph::import::clips::ClipOptions {
                    fps,
                    ignore_unknown: true,
                    budget: None,
                };
                let import = crowdmorph::import::clip_from_csv(&rig, &name, &bytes, &options)
                    .with_context(|| format!("reading {path}"))?;
                rig.clips.push(import.clip);
            }
            let mut rows = Vec::new();
            let mut csv = String::new();
            if out.is_some() {
                csv.push_str("clip,frame");
                for t in &rig.targets {
                    csv.push(',');
                    csv.push_str(t);
                }
                csv.push('\n');
            }
            // The chapter's PCA basis, shared by the library: its bytes count once, when a
            // clip uses it.
            let basis = crowdmorph::compress::Basis::of(&rig);
            let metric = crowdmorph::transform::Metric::of(&rig);
            // Both library codecs per clip; PCA is used where it is smaller only if the
            // library's total, with the shared basis (the mean and as many components as the
            // PCA clips keep), is smaller than with curves alone. The transform codec carries
            // its own basis, so it is chosen per clip.
            let mut both = Vec::new();
            for clip in &rig.clips {
                let curves = crowdmorph::compress::compress(&rig, clip, max_error)?;
                let pca = crowdmorph::compress::compress_pca(&rig, clip, &basis, max_error)?
                    .filter(|p| p.bytes() < curves.bytes());
                let transform = crowdmorph::transform::compress(&rig, &metric, clip, max_error)?;
                both.push((curves, pca, transform));
            }
            let best_library = |c: &crowdmorph::compress::Compressed,
                                p: &Option<crowdmorph::compress::Compressed>,
                                t: &Option<crowdmorph::transform::TransformCoded>,
                                pca: bool| {
                let lib = match p {
                    Some(p) if pca => p.bytes(),
                    _ => c.bytes(),
                };
                t.as_ref().map_or(lib, |t| t.bytes().min(lib))
            };
            let curves_only: usize = both
                .iter()
                .map(|(c, p, t)| best_library(c, p, t, false))
                .sum();
            let used = both
                .iter()
                .filter_map(|(_, p, _)| p.as_ref()?.components)
                .max()
                .unwrap_or(0);
            let mixed: usize = both
                .iter()
                .map(|(c, p, t)| best_library(c, p, t, true))
                .sum::<usize>()
                + if used > 0 { basis.bytes(used) } else { 0 };
            let use_pca = used > 0 && mixed < curves_only;
            let mut basis_components = 0;
            for (clip, (curves, pca, transform)) in rig.clips.iter().zip(both) {
                let library = match pca {
                    Some(p) if use_pca => (p, "pca"),
                    _ => (curves, "curves"),
                };
                let (table, codec, components, bytes, f32_bytes) = match transform {
                    Some(t) if t.bytes() < library.0.bytes() => (
                        crowdmorph::transform::decode(&t)?,
                        "transform",
                        Some(t.components()),
                        t.bytes(),
                        t.f32_bytes(),
                    ),
                    _ => {
                        let (c, codec) = library;
                        basis_components = basis_components.max(c.components.unwrap_or(0));
                        (
                            crowdmorph::compress::decode_with(&c, &basis)?,
                            codec,
                            c.components,
                            c.bytes(),
                            c.f32_bytes(),
                        )
                    }
                };
                if out.is_some() {
                    let n = clip.frames as usize;
                    for fr in 0..n {
                        csv.push_str(&format!("{},{fr}", clip.name));
                        for t in 0..clip.targets as usize {
                            csv.push_str(&format!(",{}", table[t * n + fr]));
                        }
                        csv.push('\n');
                    }
                }
                rows.push(ClipRow {
                    clip: clip.name.clone(),
                    frames: clip.frames,
                    codec,
                    components,
                    f32_bytes,
                    bytes,
                    ratio: f32_bytes as f64 / bytes.max(1) as f64,
                    error: crowdmorph::compress::measure(&rig, clip, &table, max_error),
                });
            }
            if let Some(path) = out {
                std::fs::write(&path, csv)
                    .with_context(|| format!("writing {}", path.display()))?;
            }
            let (a, b) = rows
                .iter()
                .fold((0usize, 0usize), |(a, b), r| (a + r.f32_bytes, b + r.bytes));
            let shared = if basis_components > 0 {
                basis.bytes(basis_components)
            } else {
                0
            };
            let b = b + shared;
            super::emit(
                &CompressReport {
                    rig: rig.name.clone(),
                    max_error,
                    clips: rows,
                    basis_bytes: shared,
                    ratio: a as f64 / b.max(1) as f64,
                },
                json,
            )
        }
        Command::Graph {
            rig,
            window,
            threshold,
            per_pair,
            out,
            json,
        } => {
            let rig = super::load_rig(rig.as_deref())?;
            let built = build(
                &rig,
                BuildOptions {
                    window,
                    threshold,
                    per_pair,
                },
                &crowdmorph::cancel::Cancel::never(),
            )
            .context("the build was cancelled")?
            .with_context(|| {
                format!(
                    "rig {:?}: no cycle of transitions under the threshold {threshold} (raise \
                     --threshold or lower --window)",
                    rig.name
                )
            })?;
            // What the server would say of it.
            Graph::resolve(&built.graph, &rig, |n| rig.clip_index(n))
                .context("the built graph does not check")?;
            if let Some(path) = out {
                std::fs::write(&path, serde_json::to_vec_pretty(&built.graph)?)
                    .with_context(|| format!("writing {}", path.display()))?;
            }
            super::emit(
                &GraphReport {
                    rig: rig.name.clone(),
                    built,
                },
                json,
            )
        }
    }
}
