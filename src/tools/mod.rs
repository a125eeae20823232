//! The command-line tools as library functions: `inspect`, `eval`, `render`, `bench`,
//! `load` and `lod set`.
//!
//! They live in the library so that tests can call them and `main.rs` stays a thin shell that
//! parses arguments. Being tools rather than request paths, they report errors with `anyhow`.

pub mod bench;
pub mod bench_gpu;
pub mod load;
pub mod render;
pub mod synthetic;

use std::fmt::Write as _;
use std::io::Write as _;
use std::path::Path;

use anyhow::{Context, Result, bail};
use serde::Serialize;

use crate::engine::{BlendJob, Engine, OutputSpec};
use crate::import::{ImportOptions, load_path};
use crate::rig::{FrameMode, Rig};

/// Loads a rig from a file, or the embedded default rig when `path` is `None`.
pub fn load_rig(path: Option<&Path>) -> Result<Rig> {
    match path {
        Some(p) => load_path(p, &ImportOptions::default())
            .with_context(|| format!("loading {}", p.display())),
        None => Ok(crate::embedded::default_rig()),
    }
}

/// What `inspect` reports about a rig.
#[derive(Debug, Serialize)]
pub struct RigSummary {
    /// Rig name.
    pub name: String,
    /// Vertices over all primitives.
    pub vertices: usize,
    /// Triangles over all primitives.
    pub triangles: usize,
    /// Bounding-box diagonal of the neutral mesh.
    pub bbox_diagonal: f32,
    /// Per-primitive facts.
    pub primitives: Vec<PrimitiveSummary>,
    /// Per-target facts.
    pub targets: Vec<TargetSummary>,
    /// Per-clip facts.
    pub clips: Vec<ClipSummary>,
    /// LOD order method and shapes per level.
    pub lod_method: String,
    /// Shapes evaluated at each LOD level.
    pub lod_levels: Vec<u32>,
    /// Host memory of the rig's arrays.
    pub host_bytes: usize,
    /// The engine the rig was prepared on, when asked.
    pub backend: Option<crate::engine::BackendInfo>,
    /// Memory of the prepared rig on that engine (host layout + device).
    pub memory: Option<crate::engine::RigMemory>,
    /// The adapter `crowdmorph render` and the server draw rendered frames with, when asked.
    pub renderer: Option<String>,
    /// Why nothing can render, when nothing can.
    pub renderer_error: Option<String>,
    /// Target names with more than one weight channel, and how many (see [`crate::rig`]).
    pub split_targets: Vec<(String, usize)>,
    /// The glTF extensions the file uses and how the importer treated each (empty for the
    /// embedded rig); see [`file_extensions`].
    pub extensions: Vec<crate::import::extensions::ExtensionUse>,
}

/// The glTF extensions a rig file uses or requires and how the importer treats each: read
/// (quantized or meshopt-compressed data), ignored (textures, optional ones) or unsupported.
/// `None` (the embedded rig) has none.
pub fn file_extensions(
    path: Option<&Path>,
) -> Result<Vec<crate::import::extensions::ExtensionUse>> {
    let Some(path) = path else {
        return Ok(Vec::new());
    };
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    crate::import::gltf::extension_report(&bytes)
        .with_context(|| format!("reading the extensions of {}", path.display()))
}

/// One primitive in [`RigSummary`].
#[derive(Debug, Serialize)]
pub struct PrimitiveSummary {
    /// `mesh/index`.
    pub name: String,
    /// Vertex count.
    pub vertices: usize,
    /// Triangle count.
    pub triangles: usize,
    /// Targets that move this primitive.
    pub targets: usize,
    /// Whether normals came from the file.
    pub normals_from_file: bool,
    /// Whether the file has tangents.
    pub tangents: bool,
    /// Whether its targets carry normal deltas.
    pub normal_deltas: bool,
}

/// One target in [`RigSummary`].
#[derive(Debug, Serialize)]
pub struct TargetSummary {
    /// Target name, with `#k` for the k-th weight channel of a name that has several.
    pub name: String,
    /// Stored (non-zero) vertex deltas over all primitives.
    pub nnz: usize,
    /// Position in the LOD order (0 = most important).
    pub lod_slot: u32,
}

/// One clip in [`RigSummary`].
#[derive(Debug, Serialize)]
pub struct ClipSummary {
    /// Clip name.
    pub name: String,
    /// Frames in the table.
    pub frames: u32,
    /// Sampling rate.
    pub fps: f32,
    /// Seconds.
    pub duration: f32,
}

/// Summarises a rig for `inspect`.
pub fn summarize(rig: &Rig) -> RigSummary {
    let nnz = rig.target_nnz();
    let slots = rig.lod.slots();
    RigSummary {
        name: rig.name.clone(),
        vertices: rig.vertex_count(),
        triangles: rig.triangle_count(),
        bbox_diagonal: rig.bbox().diagonal(),
        primitives: rig
            .primitives
            .iter()
            .map(|p| PrimitiveSummary {
                name: p.name.clone(),
                vertices: p.positions.len(),
                triangles: p.indices.len() / 3,
                targets: p.targets.len(),
                normals_from_file: p.normals_from_file,
                tangents: p.tangents.is_some(),
                normal_deltas: p.has_normal_deltas(),
            })
            .collect(),
        targets: rig
            .channel_labels()
            .into_vec()
            .into_iter()
            .enumerate()
            .map(|(i, name)| TargetSummary {
                name,
                nnz: nnz[i],
                lod_slot: slots[i],
            })
            .collect(),
        clips: rig
            .clips
            .iter()
            .map(|c| ClipSummary {
                name: c.name.clone(),
                frames: c.frames,
                fps: c.fps,
                duration: c.duration(),
            })
            .collect(),
        lod_method: rig.lod.method.clone(),
        lod_levels: rig.lod.levels.iter().map(|l| l.shapes).collect(),
        host_bytes: rig.host_bytes(),
        backend: None,
        memory: None,
        renderer: None,
        renderer_error: None,
        split_targets: rig
            .split_targets()
            .into_iter()
            .map(|(n, c)| (n.to_string(), c))
            .collect(),
        extensions: Vec::new(),
    }
}

/// [`summarize`] plus the backend and the memory the rig takes once prepared on `engine`.
pub fn summarize_on(rig: &Rig, engine: &Engine) -> Result<RigSummary> {
    let mut s = summarize(rig);
    let prepared = engine.prepare(std::sync::Arc::new(rig.clone()))?;
    s.backend = Some(engine.info());
    s.memory = Some(prepared.memory());
    match crate::render::crowd::RenderDevice::open(
        engine,
        crate::render::crowd::RenderBackend::Auto,
    ) {
        Ok(d) => s.renderer = Some(d.name()),
        Err(why) => s.renderer_error = Some(why),
    }
    Ok(s)
}

/// Human-readable `inspect` output.
pub fn inspect_text(s: &RigSummary) -> String {
    let mut o = String::new();
    let _ = writeln!(
        o,
        "rig {:?}: {} vertices, {} triangles, {} targets, {} clips, bbox diagonal {:.4}, {:.1} MiB",
        s.name,
        s.vertices,
        s.triangles,
        s.targets.len(),
        s.clips.len(),
        s.bbox_diagonal,
        s.host_bytes as f64 / (1 << 20) as f64
    );
    let _ = writeln!(o, "primitives:");
    for p in s.primitives.iter() {
        let _ = writeln!(
            o,
            "  {:<24} {:>8} vertices {:>8} triangles {:>4} targets  normals: {}{}",
            p.name,
            p.vertices,
            p.triangles,
            p.targets,
            if p.normals_from_file {
                "file"
            } else {
                "computed"
            },
            if p.normal_deltas {
                ", normal deltas"
            } else {
                ""
            }
        );
    }
    let _ = writeln!(
        o,
        "targets (nnz = stored vertex deltas; slot = LOD order, {}):",
        s.lod_method
    );
    for t in &s.targets {
        let _ = writeln!(
            o,
            "  {:<24} nnz {:>8}  slot {:>3}",
            t.name, t.nnz, t.lod_slot
        );
    }
    if !s.split_targets.is_empty() {
        let list: Vec<String> = s
            .split_targets
            .iter()
            .map(|(n, c)| format!("{n} ×{c}"))
            .collect();
        let _ = writeln!(
            o,
            "targets with several weight channels (nodes animated differently; glTF clips \
             drive each node's own, name-addressed clips all of them): {}",
            list.join(", ")
        );
    }
    let _ = writeln!(o, "clips:");
    if s.clips.is_empty() {
        let _ = writeln!(o, "  (none)");
    }
    for c in &s.clips {
        let _ = writeln!(
            o,
            "  {:<24} {:>6} frames at {} fps ({:.2} s)",
            c.name, c.frames, c.fps, c.duration
        );
    }
    let _ = writeln!(o, "LOD levels (shapes): {:?}", s.lod_levels);
    if let (Some(b), Some(m)) = (&s.backend, &s.memory) {
        let _ = writeln!(
            o,
            "backend: {:?} {} (CPU kernels {}); prepared rig: {:.1} MiB host, {:.1} MiB device",
            b.kind,
            b.adapter.as_deref().unwrap_or(""),
            b.cpu_isa,
            m.host_bytes as f64 / (1 << 20) as f64,
            m.device_bytes as f64 / (1 << 20) as f64
        );
    }
    if !s.extensions.is_empty() {
        let _ = writeln!(o, "glTF extensions:");
        for e in &s.extensions {
            let _ = writeln!(
                o,
                "  {:<32} {}{}: {}",
                e.name,
                e.handling,
                if e.required { " (required)" } else { "" },
                e.note
            );
        }
    }
    match (&s.renderer, &s.renderer_error) {
        (Some(r), _) => {
            let _ = writeln!(o, "renderer: {r}");
        }
        (None, Some(why)) => {
            let _ = writeln!(o, "renderer: none ({why})");
        }
        (None, None) => {}
    }
    o
}

/// Evaluates one frame of a clip on the CPU engine and writes it to `out` (`.obj` mesh or
/// `.bin` raw f32 xyz).
pub fn eval_to_file(
    rig: &Rig,
    clip: &str,
    frame: i64,
    lod: u32,
    mode: FrameMode,
    out: &Path,
) -> Result<()> {
    eval_with(&Engine::cpu(), rig, clip, frame, lod, mode, out)
}

/// [`eval_to_file`] on a given engine (the `--backend` of `crowdmorph eval`).
pub fn eval_with(
    engine: &Engine,
    rig: &Rig,
    clip: &str,
    frame: i64,
    lod: u32,
    mode: FrameMode,
    out: &Path,
) -> Result<()> {
    let ci = rig.clip_index(clip).with_context(|| {
        let names: Vec<&str> = rig.clips.iter().map(|c| c.name.as_str()).collect();
        format!(
            "rig {:?} has no clip {clip:?} (clips: {})",
            rig.name,
            names.join(", ")
        )
    })?;
    let f = rig.clips[ci].resolve_frame(frame, mode)?;
    let job = BlendJob {
        clip: ci as u32,
        frame: f,
        lod,
    };
    let kind = out
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    // Checked before anything is evaluated or created: a bad name leaves no empty file.
    let obj = match kind.as_deref() {
        Some("obj") => true,
        Some("bin") => false,
        _ => bail!("output must end in .obj or .bin: {}", out.display()),
    };
    let spec = OutputSpec {
        normals: obj,
        ..OutputSpec::default()
    };
    let prepared = engine.prepare(std::sync::Arc::new(rig.clone()))?;
    let evaluation = engine.evaluate(&prepared, &[job], spec)?;
    tracing::info!(backend = ?evaluation.kind, wall_ms = evaluation.timings.wall_ns as f64 / 1e6, "evaluated");
    let result = evaluation.output;
    let positions = result.job_positions(0);
    let file = std::fs::File::create(out).with_context(|| format!("creating {}", out.display()))?;
    let mut w = std::io::BufWriter::new(file);
    if obj {
        let normals = result.job_normals(0).unwrap_or_default();
        writeln!(
            w,
            "# crowdmorph eval: rig {:?}, clip {clip:?}, frame {f}, lod {lod}",
            rig.name
        )?;
        for p in positions.chunks_exact(3) {
            writeln!(w, "v {} {} {}", p[0], p[1], p[2])?;
        }
        for n in normals.chunks_exact(3) {
            writeln!(w, "vn {} {} {}", n[0], n[1], n[2])?;
        }
        let offsets = rig.vertex_offsets();
        for (pi, prim) in rig.primitives.iter().enumerate() {
            writeln!(w, "o {}", prim.name.replace(char::is_whitespace, "_"))?;
            for tri in prim.indices.chunks_exact(3) {
                let [a, b, c] = [0, 1, 2].map(|k| offsets[pi] + tri[k] as usize + 1);
                writeln!(w, "f {a}//{a} {b}//{b} {c}//{c}")?;
            }
        }
    } else {
        w.write_all(bytemuck::cast_slice(&positions))?;
    }
    w.flush()?;
    Ok(())
}

/// A progress bar on standard error for a command that takes seconds (hidden when standard
/// error is not a terminal, so JSON on standard output stays clean).
pub fn progress_bar(len: u64, label: &str) -> indicatif::ProgressBar {
    let b = indicatif::ProgressBar::new(len);
    b.set_style(
        indicatif::ProgressStyle::with_template(&format!(
            "{{spinner}} {label} {{pos}}/{{len}} {{msg}}"
        ))
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_spinner()),
    );
    b
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
pub fn lod_set(
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

/// The LOD table of a rig as text, a line per level.
pub fn lod_table_text(info: &crowdmorph_proto::RigInfo) -> String {
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

/// A spinner on standard error for work whose steps are not counted (hidden when standard
/// error is not a terminal); finish it with `finish_and_clear` before printing the result.
pub fn spinner(label: &str) -> indicatif::ProgressBar {
    let b = indicatif::ProgressBar::new_spinner();
    b.set_message(label.to_string());
    b.enable_steady_tick(std::time::Duration::from_millis(120));
    b
}
