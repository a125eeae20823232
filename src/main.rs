//! The `crowdmorph` binary: parses the command line, sets up tracing, and runs the command
//! (one module per subcommand in `src/cli/`).

mod cli;

use std::io::IsTerminal as _;

use clap::Parser as _;

fn main() -> anyhow::Result<()> {
    // Mesa's device-select Vulkan layer prints "XDG_RUNTIME_DIR is invalid or not set" twice
    // each time wgpu probes Vulkan outside a desktop session (servers, containers, CI): harmless,
    // but it reads like a failure. NODEVICE_SELECT=1 turns that layer off; wgpu ranks the
    // adapters itself, so the layer's reordering is not needed. A value the user set is kept.
    if std::env::var_os("NODEVICE_SELECT").is_none() {
        // SAFETY: this is the first statement of `main`, before anything that starts a thread
        // (tracing, the tokio runtime, rayon, wgpu), and Rust starts none before `main`: no
        // other thread exists that could read the environment while it is written.
        unsafe { std::env::set_var("NODEVICE_SELECT", "1") };
    }
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        // Colour only on a terminal, and never with NO_COLOR set (https://no-color.org): logs
        // written to a file or a pipe carry no escape codes.
        .with_ansi(
            std::io::stderr().is_terminal()
                && std::env::var_os("NO_COLOR").is_none_or(|v| v.is_empty()),
        )
        .init();
    cli::run(cli::Cli::parse())
}
