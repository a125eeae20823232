//! Benchmarks, their peers and their harness (the crate that replaced the old `bench` feature): what
//! `crowdmorph bench cpu|gpu|http|render|sessions|codecs` run, kept out of the product modules.
//!
//! | module | what it is |
//! |---|---|
//! | [`sample`] | [`sample::Samples`] and [`sample::sample`]: the one timing helper (median, percentiles) |
//! | [`server`] | a server in this process on a loopback port with the rig to measure; process CPU time |
//! | [`cpu`] | `bench cpu`: the CPU engine against dense peers (`gemm`, `matrixmultiply`, warm numpy) and the roofline |
//! | [`gpu`] | `bench gpu`: the paper's scenes on any backend, with a plot |
//! | [`http`] | `bench http`: loopback HTTP against in-process work, half load through [`crowdmorph_load`], the socket ceiling |
//! | [`sessions`] | `bench sessions`: one session streamed to several viewers |
//! | [`link`] | `--link`: the server also behind shaped veth links in namespaces of its own |
//! | [`render`] | `bench render`: the offline crowd drawn repeatedly |
//! | [`codecs`] | `bench codecs`: each way a head's q16 buffer can travel (references, byte planes or meshopt, zstd levels, zlib) on real frames |
//! | [`peers`] | the Python peers: the rig as `.npy`, warm numpy, the dense aiohttp + numpy server |
//!
//! Harness code reports errors with `anyhow`, as the binary does: nothing here is on a request
//! path, and the product never calls it.

pub mod codecs;
pub mod cpu;
pub mod gpu;
pub mod http;
pub mod link;
pub mod peers;
pub mod render;
pub mod sample;
pub mod server;
pub mod sessions;

/// The parser of every `--format` flag of the CLI (the benchmarks' and `load`'s): `f32`,
/// `f16`, `q16` or `q16r`, each listed with what it is in `--help`.
pub fn format_arg() -> impl clap::builder::TypedValueParser<Value = crowdmorph_proto::Format> {
    use clap::builder::{PossibleValue, TypedValueParser};
    clap::builder::PossibleValuesParser::new([
        PossibleValue::new("f32").help("IEEE binary32"),
        PossibleValue::new("f16").help("IEEE binary16"),
        PossibleValue::new("q16").help("int16 quantized in the rig's box"),
        PossibleValue::new("q16r")
            .help("q16 as residuals against the neutral, in byte planes (compresses well)"),
    ])
    .try_map(|s| s.parse::<crowdmorph_proto::Format>())
}

/// The parser of `--mesh-fractions`: fractions of the triangles, comma-separated, or `none`.
pub fn fractions_arg(s: &str) -> Result<Vec<f32>, String> {
    if s == "none" {
        return Ok(Vec::new());
    }
    s.split(',')
        .map(|f| f.trim().parse::<f32>().map_err(|e| format!("{f:?}: {e}")))
        .collect()
}

/// A progress bar on standard error for a benchmark of `len` steps (hidden when standard error
/// is not a terminal, so JSON on standard output stays clean).
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
