//! One blended frame written to a file (`crowdmorph eval`): a Wavefront OBJ mesh (positions,
//! normals, each primitive's triangles) or raw little-endian f32 x, y, z per vertex.

use std::io::Write as _;
use std::path::Path;
use std::sync::Arc;

use crate::{BlendJob, Engine, EngineError, OutputSpec};
use crowdmorph_core::rig::{ClipError, FrameMode, Rig};

/// Why a frame could not be written.
#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    /// The rig has no such clip.
    #[error("rig {rig:?} has no clip {clip:?} (clips: {clips})")]
    UnknownClip {
        /// The rig.
        rig: String,
        /// The clip asked for.
        clip: String,
        /// The clips it has.
        clips: String,
    },
    /// The frame is outside the clip.
    #[error(transparent)]
    Frame(#[from] ClipError),
    /// The output's name says neither `.obj` nor `.bin`.
    #[error("output must end in .obj or .bin: {0}")]
    Kind(String),
    /// The engine failed.
    #[error(transparent)]
    Engine(#[from] EngineError),
    /// Writing failed.
    #[error("writing {path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// What failed.
        source: std::io::Error,
    },
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
) -> Result<(), ExportError> {
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
) -> Result<(), ExportError> {
    let ci = rig
        .clip_index(clip)
        .ok_or_else(|| ExportError::UnknownClip {
            rig: rig.name.clone(),
            clip: clip.to_string(),
            clips: rig
                .clips
                .iter()
                .map(|c| c.name.as_str())
                .collect::<Vec<_>>()
                .join(", "),
        })?;
    let f = rig.clips[ci].resolve_frame(frame, mode)?;
    let job = BlendJob::frame(ci as u32, f, lod);
    let kind = out
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    // Checked before anything is evaluated or created: a bad name leaves no empty file.
    let obj = match kind.as_deref() {
        Some("obj") => true,
        Some("bin") => false,
        _ => return Err(ExportError::Kind(out.display().to_string())),
    };
    let spec = OutputSpec {
        normals: obj,
        ..OutputSpec::default()
    };
    let prepared = engine.prepare(Arc::new(rig.clone()))?;
    let evaluation = engine.evaluate(&prepared, &[job], spec)?;
    tracing::info!(backend = ?evaluation.kind, wall_ms = evaluation.timings.wall_ns as f64 / 1e6, "evaluated");
    let result = evaluation.output;
    let io = |source| ExportError::Io {
        path: out.display().to_string(),
        source,
    };
    let file = std::fs::File::create(out).map_err(io)?;
    let mut w = std::io::BufWriter::new(file);
    let positions = result.job_positions(0);
    if obj {
        let normals = result.job_normals(0).unwrap_or_default();
        write_obj(&mut w, rig, clip, f, lod, &positions, &normals).map_err(io)?;
    } else {
        w.write_all(bytemuck::cast_slice(&positions)).map_err(io)?;
    }
    w.flush().map_err(io)
}

/// The OBJ text of one frame: its vertices, normals and each primitive's faces.
fn write_obj(
    w: &mut impl std::io::Write,
    rig: &Rig,
    clip: &str,
    frame: u32,
    lod: u32,
    positions: &[f32],
    normals: &[f32],
) -> std::io::Result<()> {
    writeln!(
        w,
        "# crowdmorph eval: rig {:?}, clip {clip:?}, frame {frame}, lod {lod}",
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
    Ok(())
}
