//! `crowdmorph eval`: one frame of a clip blended and written as OBJ or raw f32
//! ([`crowdmorph::export`]).

use std::path::PathBuf;

use anyhow::Result;
use crowdmorph::engine::{BackendChoice, Engine};
use crowdmorph::rig::FrameMode;
use serde::Serialize;

/// Arguments of `eval`.
#[derive(clap::Args)]
pub struct Args {
    /// glTF/GLB rig (default: the embedded head).
    file: Option<PathBuf>,
    /// Clip name (default: the rig's first clip).
    #[arg(long)]
    clip: Option<String>,
    /// Frame number; past the end it wraps unless --clamp.
    #[arg(long, default_value_t = 0, allow_negative_numbers = true)]
    frame: i64,
    /// Hold the last frame instead of looping.
    #[arg(long)]
    clamp: bool,
    /// LOD level (0 = all shapes).
    #[arg(long, default_value_t = 0)]
    lod: u32,
    /// Output file, .obj or .bin.
    #[arg(long, default_value = "head.obj")]
    out: PathBuf,
    /// Engine: a hardware GPU if any, else the CPU (auto); or force cpu / gpu.
    #[arg(long, default_value = "auto", env = "CROWDMORPH_BACKEND")]
    backend: BackendChoice,
}

/// What `eval` wrote.
#[derive(Serialize)]
struct Wrote {
    out: PathBuf,
    vertices: usize,
    clip: String,
    frame: i64,
    lod: u32,
}

impl std::fmt::Display for Wrote {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "wrote {} ({} vertices, clip {:?}, frame {}, lod {})",
            self.out.display(),
            self.vertices,
            self.clip,
            self.frame,
            self.lod
        )
    }
}

impl super::Report for Wrote {
    fn text_on_stderr(&self) -> bool {
        true
    }
}

/// Runs `eval`.
pub fn run(a: Args) -> Result<()> {
    let rig = super::load_rig(a.file.as_deref())?;
    let clip =
        match a.clip {
            Some(c) => c,
            None => rig.clips.first().map(|c| c.name.clone()).ok_or_else(|| {
                anyhow::anyhow!("rig {:?} has no clips; nothing to play", rig.name)
            })?,
        };
    let mode = if a.clamp {
        FrameMode::Clamp
    } else {
        FrameMode::Wrap
    };
    let engine = Engine::new(a.backend)?;
    crowdmorph::export::eval_with(&engine, &rig, &clip, a.frame, a.lod, mode, &a.out)?;
    let wrote = Wrote {
        vertices: rig.vertex_count(),
        out: a.out,
        clip,
        frame: a.frame,
        lod: a.lod,
    };
    super::emit(&wrote, false)
}
