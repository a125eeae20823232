//! The command line: one module per subcommand (ripgrep's shape). Each parses its arguments,
//! calls the library and returns a report that is `Serialize + Display`; [`emit`] prints it
//! as text or, with `--json`, as JSON. Errors are `anyhow`'s: the binary is the one place that
//! uses it.

mod bench;
mod clips;
mod eval;
mod inspect;
mod load;
mod lod;
mod render;
mod serve;

use std::path::Path;

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};
use crowdmorph::import::{ImportOptions, load_path};
use crowdmorph::rig::Rig;

/// The command line.
#[derive(Parser)]
#[command(
    name = "crowdmorph",
    version,
    about = "Blendshape crowd animation: rigs, clips and a fast blend engine"
)]
pub struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Describe a rig: primitives, targets with their non-zero counts, clips, LOD table.
    Inspect(inspect::Args),
    /// Blend one frame of a clip and write it as .obj (mesh) or .bin (raw little-endian f32 xyz).
    Eval(eval::Args),
    /// Draw a crowd of a rig's heads (the default grid and front camera) and write the image:
    /// the same path as POST /v1/crowd/render, offline.
    Render(Box<render::Args>),
    /// Measure throughput.
    Bench {
        #[command(subcommand)]
        which: bench::Command,
    },
    /// Run the HTTP server (the embedded rig is always registered).
    Serve(Box<serve::Args>),
    /// Load a running server: crowd-frame requests at a fixed rate (open loop, latency from
    /// each request's intended send time), or --ramp to the highest rate whose p99 meets a
    /// target; a report as a table or --json.
    Load(Box<load::Args>),
    /// Clips: motion graphs built from a rig's clips.
    Clips {
        #[command(subcommand)]
        which: clips::Command,
    },
    /// Level of detail: importance orders, their error over a clip, simplified meshes.
    Lod {
        #[command(subcommand)]
        which: lod::Command,
    },
}

/// Runs the command the line asks for.
pub fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Inspect(a) => inspect::run(a),
        Command::Eval(a) => eval::run(a),
        Command::Render(a) => render::run(*a),
        Command::Bench { which } => bench::run(which),
        Command::Serve(a) => serve::run(*a),
        Command::Load(a) => load::run(*a),
        Command::Lod { which } => lod::run(which),
        Command::Clips { which } => clips::run(which),
    }
}

/// What a command reports: text for a person, JSON for a program.
pub trait Report: serde::Serialize + std::fmt::Display {
    /// Whether the text goes to standard error (commands whose result is a file, so that
    /// standard output stays free), rather than standard output.
    fn text_on_stderr(&self) -> bool {
        false
    }
}

/// The one printer: `report` as pretty JSON on standard output with `json`, else as its text.
pub fn emit(report: &impl Report, json: bool) -> Result<()> {
    use std::io::Write as _;
    let written = if json {
        writeln!(
            std::io::stdout(),
            "{}",
            serde_json::to_string_pretty(report)?
        )
    } else if report.text_on_stderr() {
        write!(std::io::stderr(), "{report}")
    } else {
        write!(std::io::stdout(), "{report}")
    };
    match written {
        // `crowdmorph ... | head` closes the pipe early: not an error worth a panic.
        Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => Ok(()),
        other => Ok(other?),
    }
}

/// Loads a rig from a file, or the embedded default rig when `path` is `None`.
pub fn load_rig(path: Option<&Path>) -> Result<Rig> {
    match path {
        Some(p) => load_path(p, &ImportOptions::default())
            .with_context(|| format!("loading {}", p.display())),
        None => Ok(crowdmorph::embedded::default_rig()),
    }
}

/// `--max-gpu-memory` and `--gpu-deltas` of the commands that open GPU devices besides `serve`
/// (same meaning).
#[derive(clap::Args, Clone, Copy, Debug)]
pub struct GpuMemoryArgs {
    /// Most GPU memory resident rigs, batch buffers and render targets may hold on each device,
    /// bytes (a rig or frame over it is refused, naming the flag; default: ¾ of a discrete GPU's
    /// memory, else 2 GiB or the device's largest buffer if larger).
    #[arg(long, env = "CROWDMORPH_MAX_GPU_MEMORY")]
    pub max_gpu_memory: Option<u64>,
    /// How rigs keep their blendshape deltas on the GPU: f32, or f16 (half the memory and
    /// traffic, each delta rounded to binary16), as `serve --gpu-deltas`.
    #[arg(long, env = "CROWDMORPH_GPU_DELTAS", default_value = "f32")]
    pub gpu_deltas: crowdmorph::engine::gpu::DeltaFormat,
}

impl GpuMemoryArgs {
    /// The GPU context options the flag asks for.
    pub fn options(self) -> crowdmorph::engine::gpu::GpuOptions {
        crowdmorph::engine::gpu::GpuOptions {
            memory: self.max_gpu_memory,
            deltas: self.gpu_deltas,
            ..Default::default()
        }
    }
}

/// Runs `work` under a spinner on standard error (hidden when standard error is not a
/// terminal), for work whose steps are not counted; the spinner is cleared before the result
/// is printed.
pub fn with_spinner<T>(label: &str, work: impl FnOnce() -> T) -> T {
    let b = indicatif::ProgressBar::new_spinner();
    b.set_message(label.to_string());
    b.enable_steady_tick(std::time::Duration::from_millis(120));
    let out = work();
    b.finish_and_clear();
    out
}

#[cfg(test)]
mod tests {
    use clap::{CommandFactory, Parser};

    use super::{Cli, Command, bench::Command as BenchCommand};

    /// clap checks a command's definition (a field without `#[arg]`, a doc comment on the wrong
    /// field, clashing flags) only in debug builds and only when that subcommand is parsed; this
    /// checks the whole tree at once.
    #[test]
    fn the_command_line_definition_is_well_formed() {
        Cli::command().debug_assert();
    }

    #[test]
    fn load_takes_session_flags() {
        let cli = Cli::try_parse_from([
            "crowdmorph",
            "load",
            "--session-id",
            "s1",
            "--viewers",
            "3",
            "--fps",
            "20",
            "--lod-by-distance",
            "0:0",
            "--lod-by-distance",
            "8.5:2",
            "--admin-token",
            "secret",
        ])
        .expect("load with session flags parses");
        match cli.command {
            Command::Load(a) => {
                assert_eq!(a.session_id.as_deref(), Some("s1"));
                assert!(!a.session, "--session-id alone implies it later");
                assert_eq!((a.viewers, a.fps), (3, 20.0));
                assert_eq!(a.lod_by_distance, vec![[0.0, 0.0], [8.5, 2.0]]);
                assert_eq!(a.admin_token.as_deref(), Some("secret"));
            }
            _ => panic!("parsed as another command"),
        }
        assert!(
            Cli::try_parse_from(["crowdmorph", "load", "--session", "--viewers", "0"]).is_err()
        );
        assert!(Cli::try_parse_from(["crowdmorph", "load", "--lod-by-distance", "8"]).is_err());
    }

    #[test]
    fn python_peer_flags_default_to_the_system_python_and_take_a_path() {
        let peer = |args: &[&str]| match Cli::try_parse_from(args)
            .expect("bench http parses")
            .command
        {
            Command::Bench {
                which: BenchCommand::Http { opt, .. },
            } => opt.python_peer,
            _ => panic!("parsed as another command"),
        };
        assert_eq!(peer(&["crowdmorph", "bench", "http"]), None);
        assert_eq!(
            peer(&["crowdmorph", "bench", "http", "--python-peer", "--json"]),
            Some(std::path::PathBuf::from("/usr/bin/python3"))
        );
        assert_eq!(
            peer(&[
                "crowdmorph",
                "bench",
                "http",
                "--python-peer",
                "/opt/py/bin/python"
            ]),
            Some(std::path::PathBuf::from("/opt/py/bin/python"))
        );
        match Cli::try_parse_from(["crowdmorph", "bench", "cpu", "--numpy"])
            .expect("bench cpu --numpy parses")
            .command
        {
            Command::Bench {
                which: BenchCommand::Cpu { opt, .. },
            } => assert_eq!(
                opt.numpy,
                Some(std::path::PathBuf::from("/usr/bin/python3"))
            ),
            _ => panic!("parsed as another command"),
        }
    }

    #[test]
    fn serve_render_and_every_bench_command_with_a_gpu_take_the_gpu_flags() {
        use crowdmorph::engine::gpu::DeltaFormat;
        let flags = |args: &[&str]| match Cli::try_parse_from(args).expect("parses").command {
            Command::Serve(a) => (a.config().gpu_memory, a.config().gpu_deltas),
            Command::Render(a) => (a.gpu.max_gpu_memory, a.gpu.gpu_deltas),
            Command::Bench {
                which:
                    BenchCommand::Gpu { gpu, .. }
                    | BenchCommand::Render { gpu, .. }
                    | BenchCommand::Sessions { gpu, .. }
                    | BenchCommand::Http { gpu, .. },
            } => (gpu.max_gpu_memory, gpu.gpu_deltas),
            _ => panic!("parsed as another command"),
        };
        for cmd in [
            &["serve"][..],
            &["render"],
            &["bench", "gpu"],
            &["bench", "render"],
            &["bench", "sessions"],
            &["bench", "http"],
        ] {
            let mut args = vec!["crowdmorph"];
            args.extend_from_slice(cmd);
            assert_eq!(
                flags(&args),
                (None, DeltaFormat::F32),
                "{cmd:?}: the defaults"
            );
            args.extend_from_slice(&["--max-gpu-memory", "67108864", "--gpu-deltas", "f16"]);
            assert_eq!(flags(&args), (Some(64 << 20), DeltaFormat::F16), "{cmd:?}");
        }
        let err = Cli::try_parse_from(["crowdmorph", "serve", "--gpu-deltas", "f8"])
            .err()
            .expect("f8 is refused")
            .to_string();
        assert!(err.contains("f32 or f16"), "{err}");
    }

    #[test]
    fn bench_http_takes_json_and_backend_flags() {
        let cli =
            Cli::try_parse_from(["crowdmorph", "bench", "http", "--json", "--backend", "cpu"])
                .expect("bench http --json --backend cpu parses");
        match cli.command {
            Command::Bench {
                which: BenchCommand::Http { json, opt, .. },
            } => {
                assert!(json);
                assert_eq!(opt.backend, crowdmorph::engine::BackendChoice::Cpu);
            }
            _ => panic!("parsed as another command"),
        }
    }
}
