//! `crowdmorph bench cpu|gpu|http|render|sessions|codecs`: the benchmarks of [`crowdmorph::bench`],
//! each printed as its report.

use std::path::PathBuf;

use anyhow::Result;
use clap::Subcommand;
use crowdmorph::bench;
use crowdmorph::engine::{BackendChoice, Engine};
use crowdmorph::render::crowd::RenderBackend;
use serde::Serialize;

use super::{GpuMemoryArgs, load_rig, with_spinner};

/// `crowdmorph bench ...`. Each benchmark's own flags are its options struct's
/// (`#[command(flatten)]`); what is here picks the rig, the engine and the output.
#[derive(Subcommand)]
pub enum Command {
    /// The scenes of Costigan et al. 2016 (1 head, 100 unique, 100 sharing 10 animations) at
    /// 100/50/25 % shapes: GPU time and round-trip time, on the paper-scale synthetic rig and
    /// any --rig.
    Gpu {
        /// More rigs to measure (glTF/GLB), after the paper-scale synthetic rig.
        #[arg(long)]
        rig: Vec<PathBuf>,
        /// Leave out the paper-scale synthetic rig.
        #[arg(long)]
        no_paper: bool,
        /// Also the embedded head with five joints (measured with and without its skeleton:
        /// what the skin pass costs on the device).
        #[arg(long)]
        skinned_head: bool,
        /// Engine (gpu includes software adapters such as lavapipe).
        #[arg(long, default_value = "gpu")]
        backend: BackendChoice,
        /// Write the table as a PNG plot (like the paper's Figures 5 and 6).
        #[arg(long)]
        plot: Option<PathBuf>,
        /// Also run the same scenes on the CPU engine (a second table, same plot).
        #[arg(long)]
        with_cpu: bool,
        #[command(flatten)]
        opt: bench::gpu::GpuBenchOptions,
        #[command(flatten)]
        gpu: GpuMemoryArgs,
        /// Print JSON.
        #[arg(long)]
        json: bool,
    },
    /// Crowd frames over loopback HTTP against the same work in-process; latency at half
    /// load; bytes per head of each format.
    Http {
        /// glTF/GLB rig (default: the embedded head).
        #[arg(long)]
        rig: Option<PathBuf>,
        #[command(flatten)]
        opt: bench::http::HttpBenchOptions,
        #[command(flatten)]
        gpu: GpuMemoryArgs,
        /// Print JSON.
        #[arg(long)]
        json: bool,
    },
    /// One crowd session streamed to several viewers over loopback WebSockets: ticks on time,
    /// CPU per tick, bytes per viewer per second.
    Sessions {
        /// glTF/GLB rig (default: the embedded head).
        #[arg(long)]
        rig: Option<PathBuf>,
        #[command(flatten)]
        opt: bench::sessions::SessionBenchOptions,
        #[command(flatten)]
        gpu: GpuMemoryArgs,
        /// Print JSON.
        #[arg(long)]
        json: bool,
    },
    /// Rendered frames: ms per frame split into compute, render, readback and encode, for a
    /// crowd of unique heads (head i plays frame i) on the default grid and camera.
    Render {
        /// glTF/GLB rig (default: the embedded head; a rig without clips plays a synthetic
        /// random clip).
        #[arg(long)]
        rig: Option<PathBuf>,
        /// Heads in the crowd, each a different frame (at most 100,000, as `render`).
        #[arg(
            long,
            default_value_t = 100,
            value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..=100_000)
        )]
        heads: usize,
        /// Image width, pixels.
        #[arg(long, default_value_t = 1280)]
        width: u32,
        /// Image height, pixels.
        #[arg(long, default_value_t = 720)]
        height: u32,
        /// Image format.
        #[arg(long, default_value = "png")]
        format: crowdmorph_proto::ImageFormat,
        /// LOD level of every head.
        #[arg(long, default_value_t = 0)]
        lod: u32,
        /// Seconds to measure (at least 5 frames, after a warm-up frame).
        #[arg(long, default_value_t = 3.0)]
        seconds: f64,
        /// Engine.
        #[arg(long, default_value = "auto")]
        backend: BackendChoice,
        /// Adapter that draws (auto or gpu).
        #[arg(long, default_value = "auto")]
        render_backend: RenderBackend,
        /// Textures: `rig` (as the rig has them), `on` (generated ones when it has none),
        /// `off` (its materials' factors only), or `both` (off, then on, and their ratio).
        #[arg(long, default_value = "rig")]
        textures: bench::render::TextureChoice,
        #[command(flatten)]
        gpu: GpuMemoryArgs,
        /// Print JSON.
        #[arg(long)]
        json: bool,
    },
    /// The CPU engine against the dense sgemm of the same blend and its roofline (FMA peak,
    /// copy bandwidth), the wire formats, batch sizes and LOD levels, measured in the same run.
    Cpu {
        /// glTF/GLB rig (default: the embedded head).
        #[arg(long, conflicts_with = "skinned_head")]
        rig: Option<PathBuf>,
        /// The embedded head with five joints (neck, head, jaw, eyes) instead: what skinning
        /// costs on a face.
        #[arg(long)]
        skinned_head: bool,
        #[command(flatten)]
        opt: bench::cpu::BenchOptions,
        /// Print JSON.
        #[arg(long)]
        json: bool,
    },
    /// The ways a head's q16 buffer can travel, on real frames: against nothing, the neutral
    /// or the previous frame; byte planes or meshoptimizer's vertex codec; zstd levels or zlib.
    /// Bytes per head and encode/decode CPU per head, each checked lossless.
    Codecs {
        /// glTF/GLB rig (default: the embedded head).
        #[arg(long)]
        rig: Option<PathBuf>,
        #[command(flatten)]
        opt: bench::codecs::CodecBenchOptions,
        /// Print JSON.
        #[arg(long)]
        json: bool,
    },
}

/// `bench gpu`'s tables: the engine's, and the CPU engine's with `--with-cpu`.
#[derive(Serialize)]
#[serde(transparent)]
struct GpuReports(Vec<bench::gpu::GpuBenchReport>);

impl std::fmt::Display for GpuReports {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        self.0.iter().try_for_each(|r| write!(f, "{r}"))
    }
}

impl super::Report for GpuReports {}
impl super::Report for bench::cpu::BenchReport {}
impl super::Report for bench::http::HttpBenchReport {}
impl super::Report for bench::sessions::SessionBenchReport {}
impl super::Report for bench::sessions::SessionLinkReport {}
impl super::Report for bench::sessions::NearCloneReport {}
impl super::Report for bench::http::LinkBenchReport {}
impl super::Report for crowdmorph::render::offline::RenderReport {}
impl super::Report for bench::render::TextureComparison {}
impl super::Report for bench::codecs::CodecReport {}

/// The rig file a benchmark server uploads (its glTF with every buffer embedded), if any.
fn server_rig(rig: Option<&std::path::Path>) -> Result<Option<Vec<u8>>> {
    rig.map(bench::server::self_contained_bytes).transpose()
}

/// Runs one benchmark and prints its report.
pub fn run(which: Command) -> Result<()> {
    match which {
        Command::Cpu {
            rig,
            skinned_head,
            mut opt,
            json,
        } => {
            let rig = if skinned_head {
                crowdmorph::synthetic::skinned_head()
            } else {
                load_rig(rig.as_deref())?
            };
            opt.progress = !json;
            super::emit(&bench::cpu::bench_cpu(&rig, &opt)?, json)
        }
        Command::Gpu {
            rig,
            no_paper,
            skinned_head,
            backend,
            plot,
            with_cpu,
            opt,
            gpu,
            json,
        } => {
            if opt.unique.contains(&0) {
                anyhow::bail!("--unique counts must be at least 1");
            }
            let engine = Engine::with_options(backend, gpu.options())?;
            let mut rigs = Vec::new();
            if !no_paper {
                rigs.push(crowdmorph::synthetic::paper_scale_rig());
            }
            if skinned_head {
                rigs.push(crowdmorph::synthetic::skinned_head());
            }
            for p in &rig {
                rigs.push(load_rig(Some(p))?);
            }
            let mut reports = vec![bench::gpu::bench_gpu(&engine, &rigs, &opt)?];
            if with_cpu {
                reports.push(bench::gpu::bench_gpu(&Engine::cpu(), &rigs, &opt)?);
            }
            if let Some(path) = &plot {
                bench::gpu::write_plot(&reports, path)?;
            }
            super::emit(&GpuReports(reports), json)
        }
        Command::Render {
            rig,
            heads,
            width,
            height,
            format,
            lod,
            seconds,
            backend,
            render_backend,
            textures,
            gpu,
            json,
        } => {
            use bench::render::TextureChoice;
            let rig = load_rig(rig.as_deref())?;
            let engine = Engine::with_options(backend, gpu.options())?;
            let opt = crowdmorph::render::offline::RenderOptions {
                heads,
                lod,
                spread: true,
                image: crowdmorph_proto::ImageOptions {
                    width,
                    height,
                    format,
                    ..crowdmorph_proto::ImageOptions::default()
                },
                backend: render_backend,
                gpu_memory: gpu.max_gpu_memory,
                textures: match textures {
                    TextureChoice::Rig | TextureChoice::Both => None,
                    TextureChoice::On => Some(true),
                    TextureChoice::Off => Some(false),
                },
                ..crowdmorph::render::offline::RenderOptions::default()
            };
            if textures == TextureChoice::Both {
                let report = with_spinner("bench render --textures both", || {
                    bench::render::bench_render_textures(&engine, &rig, &opt, seconds, 5)
                });
                return super::emit(&report?, json);
            }
            let report = with_spinner("bench render", || {
                bench::render::bench_render(&engine, &rig, &opt, seconds, 5)
            });
            super::emit(&report?, json)
        }
        Command::Codecs { rig, opt, json } => {
            let rig = load_rig(rig.as_deref())?;
            let report = with_spinner("bench codecs", || bench::codecs::bench_codecs(rig, &opt));
            super::emit(&report?, json)
        }
        Command::Sessions {
            rig,
            opt,
            gpu,
            json,
        } => {
            let bytes = server_rig(rig.as_deref())?;
            let opt = bench::sessions::SessionBenchOptions {
                gpu_memory: gpu.max_gpu_memory,
                gpu_deltas: gpu.gpu_deltas,
                ..opt
            };
            if opt.tolerance.is_some() {
                let report = with_spinner("bench sessions --tolerance", || {
                    bench::sessions::bench_near_clones(bytes, &opt)
                });
                return super::emit(&report?, json);
            }
            if !opt.links.is_empty() {
                let report = with_spinner("bench sessions --link", || {
                    bench::sessions::bench_session_links(bytes, &opt)
                });
                return super::emit(&report?, json);
            }
            let report = with_spinner("bench sessions", || {
                bench::sessions::bench_sessions(bytes, &opt)
            });
            super::emit(&report?, json)
        }
        Command::Http {
            rig,
            opt,
            gpu,
            json,
        } => {
            let bytes = server_rig(rig.as_deref())?;
            let opt = bench::http::HttpBenchOptions {
                gpu_memory: gpu.max_gpu_memory,
                gpu_deltas: gpu.gpu_deltas,
                ..opt
            };
            if !opt.links.is_empty() {
                let report = with_spinner("bench http --link", || {
                    bench::http::bench_http_links(bytes, &opt)
                });
                return super::emit(&report?, json);
            }
            let report = with_spinner(
                "bench http: in-process, loopback, saturation, half load",
                || bench::http::bench_http(bytes, &opt),
            );
            super::emit(&report?, json)
        }
    }
}
