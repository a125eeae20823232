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
    let mut filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    // wgpu's GL backend logs its EGL probe at ERROR ("DRI2: failed to load driver") on every
    // machine that has Mesa's libEGL but no GL driver for its device: a server without a GPU
    // that probes GL as the last fallback (`GpuContext::adapters`) would log an error at each
    // start and first render. What matters is reported by crowdmorph itself (`/readyz`'s
    // renderer, `render_unavailable` naming what to install); `RUST_LOG` naming `wgpu_hal`
    // shows the probe again.
    if !std::env::var("RUST_LOG").is_ok_and(|v| v.contains("wgpu_hal")) {
        filter = filter.add_directive("wgpu_hal::gles::egl=off".parse()?);
    }
    tracing_subscriber::fmt()
        .with_env_filter(filter)
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
