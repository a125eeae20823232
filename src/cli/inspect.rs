//! `crowdmorph inspect`: what a rig holds (primitives, targets, clips, LOD), the memory it takes
//! on an engine, the adapter that would render it, and the glTF extensions of its file.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use crowdmorph::engine::{BackendChoice, Engine};
use crowdmorph::rig::Rig;
use serde::Serialize;

/// Arguments of `inspect`.
#[derive(clap::Args)]
pub struct Args {
    /// glTF/GLB rig (default: the embedded head).
    file: Option<PathBuf>,
    /// Print JSON instead of text.
    #[arg(long)]
    json: bool,
    /// Backend to report the rig's memory on (auto: a hardware GPU if any, else the CPU).
    #[arg(long, default_value = "auto", env = "CROWDMORPH_BACKEND")]
    backend: BackendChoice,
}

/// Runs `inspect`.
pub fn run(a: Args) -> Result<()> {
    let rig = super::load_rig(a.file.as_deref())?;
    let engine = Engine::new(a.backend)?;
    let mut summary = summarize_on(&rig, &engine)?;
    summary.extensions = file_extensions(a.file.as_deref())?;
    super::emit(&summary, a.json)
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
    pub backend: Option<crowdmorph::engine::BackendInfo>,
    /// Memory of the prepared rig on that engine (host layout + device).
    pub memory: Option<crowdmorph::engine::RigMemory>,
    /// The adapter `crowdmorph render` and the server draw rendered frames with, when asked.
    pub renderer: Option<String>,
    /// Why nothing can render, when nothing can.
    pub renderer_error: Option<String>,
    /// Target names with more than one weight channel, and how many (see `crowdmorph::rig`).
    pub split_targets: Vec<(String, usize)>,
    /// The glTF extensions the file uses and how the importer treated each (empty for the
    /// embedded rig); see [`file_extensions`].
    pub extensions: Vec<crowdmorph::import::extensions::ExtensionUse>,
    /// The skeleton of a skinned rig.
    pub skeleton: Option<crowdmorph_proto::SkeletonInfo>,
    /// What the import approximated or left out.
    pub import_notes: Vec<String>,
}

/// The glTF extensions a rig file uses or requires and how the importer treats each: read
/// (quantized or meshopt-compressed data), ignored (textures, optional ones) or unsupported.
/// `None` (the embedded rig) has none.
pub fn file_extensions(
    path: Option<&Path>,
) -> Result<Vec<crowdmorph::import::extensions::ExtensionUse>> {
    let Some(path) = path else {
        return Ok(Vec::new());
    };
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    crowdmorph::import::gltf::extension_report(&bytes)
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
        skeleton: crowdmorph::server::registry::skeleton_info(rig),
        import_notes: rig.import_notes.clone(),
    }
}

/// [`summarize`] plus the backend and the memory the rig takes once prepared on `engine`.
pub fn summarize_on(rig: &Rig, engine: &Engine) -> Result<RigSummary> {
    let mut s = summarize(rig);
    let prepared = engine.prepare(std::sync::Arc::new(rig.clone()))?;
    s.backend = Some(engine.info());
    s.memory = Some(prepared.memory());
    match crowdmorph::render::crowd::RenderDevice::open(
        engine,
        crowdmorph::render::crowd::RenderBackend::Auto,
    ) {
        Ok(d) => s.renderer = Some(d.name()),
        Err(why) => s.renderer_error = Some(why),
    }
    Ok(s)
}

/// Human-readable `inspect` output.
fn inspect_text(s: &RigSummary) -> String {
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
    if let Some(k) = &s.skeleton {
        let _ = writeln!(
            o,
            "skeleton: {} nodes, {} bones; {} skinned vertices, {} rigid under a node; \
             {} of {} clips animate nodes (morph targets first, then skinning)",
            k.nodes,
            k.bones,
            k.skinned_vertices,
            k.rigid_vertices,
            k.clips_with_joints.len(),
            s.clips.len()
        );
        let _ = writeln!(o, "  animated nodes: {}", k.animated_nodes.join(", "));
        // What joint overrides and joint maps may name: every node, not only the animated ones.
        let _ = writeln!(o, "  nodes: {}", k.node_names.join(", "));
    }
    for n in &s.import_notes {
        let _ = writeln!(o, "import note: {n}");
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

impl std::fmt::Display for RigSummary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&inspect_text(self))
    }
}

impl super::Report for RigSummary {}
