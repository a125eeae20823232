//! The `crowdmorph` binary: parses the command line, sets up tracing, and calls the library.

use std::path::PathBuf;

use anyhow::Result;
use clap::{Parser, Subcommand, ValueEnum};
use crowdmorph::engine::Precision;
use crowdmorph::rig::FrameMode;
use crowdmorph::tools::{self, bench};

#[derive(Parser)]
#[command(
    name = "crowdmorph",
    version,
    about = "Blendshape crowd animation: rigs, clips and a fast blend engine"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Describe a rig: primitives, targets with their non-zero counts, clips, LOD table.
    Inspect {
        /// glTF/GLB rig (default: the embedded head).
        file: Option<PathBuf>,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Blend one frame of a clip and write it as .obj (mesh) or .bin (raw little-endian f32 xyz).
    Eval {
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
    },
    /// Measure throughput.
    Bench {
        #[command(subcommand)]
        which: BenchCommand,
    },
}

#[derive(Subcommand)]
enum BenchCommand {
    /// The CPU engine against a dense sgemm and the memcpy roofline, measured in the same run.
    Cpu {
        /// glTF/GLB rig (default: the embedded head).
        #[arg(long)]
        rig: Option<PathBuf>,
        /// Heads in the crowd.
        #[arg(long, default_value_t = 100)]
        heads: usize,
        /// Unique jobs among the heads.
        #[arg(long, default_value_t = 100)]
        unique: usize,
        /// LOD level.
        #[arg(long, default_value_t = 0)]
        lod: u32,
        /// Output precision.
        #[arg(long, value_enum, default_value_t = Format::F32)]
        format: Format,
        /// Compute normals too.
        #[arg(long)]
        normals: bool,
        /// Seconds per measurement.
        #[arg(long, default_value_t = 1.0)]
        seconds: f64,
        /// Print JSON.
        #[arg(long)]
        json: bool,
    },
}

#[derive(Clone, Copy, ValueEnum)]
enum Format {
    F32,
    F16,
}

fn main() -> Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .init();
    let cli = Cli::parse();
    match cli.command {
        Command::Inspect { file, json } => {
            let rig = tools::load_rig(file.as_deref())?;
            let summary = tools::summarize(&rig);
            if json {
                println!("{}", serde_json::to_string_pretty(&summary)?);
            } else {
                print!("{}", tools::inspect_text(&summary));
            }
        }
        Command::Eval {
            file,
            clip,
            frame,
            clamp,
            lod,
            out,
        } => {
            let rig = tools::load_rig(file.as_deref())?;
            let clip = match clip {
                Some(c) => c,
                None => rig.clips.first().map(|c| c.name.clone()).ok_or_else(|| {
                    anyhow::anyhow!("rig {:?} has no clips; nothing to play", rig.name)
                })?,
            };
            let mode = if clamp {
                FrameMode::Clamp
            } else {
                FrameMode::Wrap
            };
            tools::eval_to_file(&rig, &clip, frame, lod, mode, &out)?;
            eprintln!(
                "wrote {} ({} vertices, clip {clip:?}, frame {frame}, lod {lod})",
                out.display(),
                rig.vertex_count()
            );
        }
        Command::Bench {
            which:
                BenchCommand::Cpu {
                    rig,
                    heads,
                    unique,
                    lod,
                    format,
                    normals,
                    seconds,
                    json,
                },
        } => {
            let rig = tools::load_rig(rig.as_deref())?;
            let opt = bench::BenchOptions {
                heads,
                unique,
                lod,
                precision: match format {
                    Format::F32 => Precision::F32,
                    Format::F16 => Precision::F16,
                },
                normals,
                seconds,
                progress: !json,
            };
            let report = bench::bench_cpu(&rig, &opt)?;
            if json {
                println!("{}", serde_json::to_string_pretty(&report)?);
            } else {
                print!("{}", bench::report_text(&report));
            }
        }
    }
    Ok(())
}
