//! `crowdmorph render`: a crowd of a rig's heads drawn to an image file
//! ([`crowdmorph::render::offline`]).

use std::path::PathBuf;

use anyhow::Result;
use crowdmorph::engine::{BackendChoice, Engine};
use crowdmorph::render::offline::{self as r, RenderReport};
use serde::Serialize;

use super::GpuMemoryArgs;

/// Arguments of `render`.
#[derive(clap::Args)]
pub struct Args {
    /// glTF/GLB rig (default: the embedded head).
    file: Option<PathBuf>,
    /// Clip name (default: talk when the rig has it, else its first clip, else the neutral
    /// pose); `random` makes a synthetic clip for rigs without one.
    #[arg(long)]
    clip: Option<String>,
    /// Frame number (wraps past the end).
    #[arg(long, default_value_t = 0, allow_negative_numbers = true)]
    frame: i64,
    /// Heads in the crowd, on a grid.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u64).range(0..=100_000))]
    heads: u64,
    /// Head i plays frame N + i (every head unique) instead of all heads cloning frame N.
    #[arg(long)]
    spread: bool,
    /// LOD level of every head.
    #[arg(long, default_value_t = 0)]
    lod: u32,
    /// Image width, pixels.
    #[arg(long, default_value_t = crowdmorph_proto::DEFAULT_IMAGE_WIDTH)]
    width: u32,
    /// Image height, pixels.
    #[arg(long, default_value_t = crowdmorph_proto::DEFAULT_IMAGE_HEIGHT)]
    height: u32,
    /// Image format (default: from the --out extension, else png).
    #[arg(long)]
    format: Option<crowdmorph_proto::ImageFormat>,
    /// JPEG quality, 1-100.
    #[arg(long, default_value_t = crowdmorph_proto::DEFAULT_JPEG_QUALITY)]
    quality: u8,
    /// Output file.
    #[arg(long, default_value = "crowd.png")]
    out: PathBuf,
    /// Engine: a hardware GPU if any, else the CPU (auto); or force cpu / gpu.
    #[arg(long, default_value = "auto", env = "CROWDMORPH_BACKEND")]
    backend: BackendChoice,
    /// Adapter that draws: auto (the engine's GPU, else any adapter, lavapipe included) or
    /// gpu (hardware only).
    #[arg(long, default_value = "auto", env = "CROWDMORPH_RENDER_BACKEND")]
    render_backend: crowdmorph::render::crowd::RenderBackend,
    #[command(flatten)]
    pub(super) gpu: GpuMemoryArgs,
    /// Print what was drawn as JSON.
    #[arg(long)]
    json: bool,
}

/// What `render` wrote: the report, and where (as text, one line on standard error).
#[derive(Serialize)]
#[serde(transparent)]
struct Wrote {
    report: RenderReport,
    #[serde(skip)]
    out: PathBuf,
}

impl std::fmt::Display for Wrote {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let r = &self.report;
        writeln!(
            f,
            "wrote {} ({}×{} {}, {} heads, {} unique; rendered on {})",
            self.out.display(),
            r.width,
            r.height,
            r.format,
            r.heads,
            r.unique,
            r.adapter
        )
    }
}

impl super::Report for Wrote {
    fn text_on_stderr(&self) -> bool {
        true
    }
}

/// Runs `render`.
pub fn run(a: Args) -> Result<()> {
    let rig = super::load_rig(a.file.as_deref())?;
    let engine = Engine::with_options(a.backend, a.gpu.options())?;
    let format = a
        .format
        .or_else(|| r::format_of(&a.out))
        .unwrap_or_default();
    let opt = r::RenderOptions {
        clip: a.clip,
        frame: a.frame,
        heads: usize::try_from(a.heads)?,
        lod: a.lod,
        spread: a.spread,
        image: crowdmorph_proto::ImageOptions {
            width: a.width,
            height: a.height,
            format,
            quality: a.quality,
            ..crowdmorph_proto::ImageOptions::default()
        },
        backend: a.render_backend,
        gpu_memory: a.gpu.max_gpu_memory,
        // The rig as it is: its textures, if the import gave it any.
        textures: None,
    };
    let report = r::render_to_file(&engine, &rig, &opt, &a.out)?;
    super::emit(&Wrote { report, out: a.out }, a.json)
}
