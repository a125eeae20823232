//! `crowdmorph bench cpu|gpu|http|render|sessions|codecs`: the benchmarks of [`crowdmorph::bench`],
//! each printed as its report.

use std::path::PathBuf;

use anyhow::Result;
use clap::Subcommand;
use crowdmorph::bench;
use crowdmorph::engine::{BackendChoice, Engine};
use crowdmorph::render::crowd::RenderBackend;
use serde::Serialize;

use super::{GpuMemoryArgs, WireFormat, load_rig, with_spinner};

/// `crowdmorph bench ...`.
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
        /// Seconds per measurement.
        #[arg(long, default_value_t = 1.0)]
        seconds: f64,
        /// Write the table as a PNG plot (like the paper's Figures 5 and 6).
        #[arg(long)]
        plot: Option<PathBuf>,
        /// Also run the same scenes on the CPU engine (a second table, same plot).
        #[arg(long)]
        with_cpu: bool,
        /// Instead of the paper's scenes: crowds of this many unique heads each
        /// (comma-separated, e.g. 1,100,4096,16384), at LOD 0.
        #[arg(long, value_delimiter = ',')]
        unique: Vec<usize>,
        /// Output format of every batch.
        #[arg(long, value_enum, default_value_t = WireFormat::F32)]
        format: WireFormat,
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
        /// Heads per request.
        #[arg(long, default_value_t = 100)]
        heads: usize,
        /// Unique jobs per request.
        #[arg(long, default_value_t = 100)]
        unique: usize,
        /// Format of the throughput runs.
        #[arg(long, value_enum, default_value_t = WireFormat::F32)]
        format: WireFormat,
        /// Concurrent connections at saturation.
        #[arg(long, default_value_t = 4)]
        clients: usize,
        /// Seconds per measurement.
        #[arg(long, default_value_t = 3.0)]
        seconds: f64,
        /// Engine of the server and of the in-process comparison.
        #[arg(long, default_value = "auto")]
        backend: BackendChoice,
        /// Also measure the dense Python server (aiohttp + numpy,
        /// clients/python/bench/dense_server.py) on the same requests, with this Python
        /// (default /usr/bin/python3).
        #[arg(long, value_name = "PYTHON", num_args = 0..=1, default_missing_value = "/usr/bin/python3")]
        python_peer: Option<PathBuf>,
        /// Where the Python peer runs numpy: off its event loop (thread) or on it (inline).
        #[arg(long, default_value = "thread", value_parser = ["thread", "inline"])]
        python_peer_compute: String,
        #[command(flatten)]
        gpu: GpuMemoryArgs,
        /// Upload these clips first (`.csv`/`.json` files in a folder, named by file stem)
        /// and play them.
        #[arg(long, value_name = "DIR")]
        clips: Option<PathBuf>,
        /// Instead: measure each encoding on loopback and over shaped links at these rates
        /// (comma-separated, e.g. 1gbit,100mbit; a network namespace and a tbf-shaped veth
        /// pair each, removed at the end; needs root and iproute2, else only loopback).
        #[arg(long, value_delimiter = ',', value_name = "RATES")]
        link: Vec<bench::link::LinkSpec>,
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
        /// Heads in the session.
        #[arg(long, default_value_t = 1000)]
        heads: usize,
        /// Distinct animations (clip and offset pairs) among the heads.
        #[arg(long, default_value_t = 100)]
        animations: usize,
        /// Viewers.
        #[arg(long, default_value_t = 8)]
        viewers: usize,
        /// Ticks per second.
        #[arg(long, default_value_t = 30.0)]
        fps: f32,
        /// Buffer format of every viewer.
        #[arg(long, value_enum, default_value_t = WireFormat::Q16)]
        format: WireFormat,
        /// Seconds to measure.
        #[arg(long, default_value_t = 10.0)]
        seconds: f64,
        /// Engine.
        #[arg(long, default_value = "auto")]
        backend: BackendChoice,
        #[command(flatten)]
        gpu: GpuMemoryArgs,
        /// Heads walk a motion graph over every clip (one random walk per animation).
        #[arg(long)]
        graph: bool,
        /// Upload these clips first (`.csv`/`.json` files in a folder, named by file stem)
        /// and play them.
        #[arg(long, value_name = "DIR")]
        clips: Option<PathBuf>,
        /// Instead: one viewer at a time per mode (f32, q16, temporal, compressed) on loopback and over shaped links at these rates
        /// (comma-separated, e.g. 1gbit,100mbit; a network namespace and a tbf-shaped veth
        /// pair each, removed at the end; needs root and iproute2, else only loopback).
        #[arg(long, value_delimiter = ',', value_name = "RATES")]
        link: Vec<bench::link::LinkSpec>,
        /// With --link: only these viewer modes (comma-separated: f32, q16, q16+zstd,
        /// temporal, temporal+deflate, temporal+zstd; default all).
        #[arg(long, value_delimiter = ',', value_name = "MODES")]
        modes: Vec<bench::sessions::ViewerMode>,
        /// Upload a smooth synthetic clip of this many frames over every target and play it
        /// (a rig without clips, such as ICT FaceKit, or more unique heads a tick than the
        /// rig's clips have frames).
        #[arg(
            long,
            value_name = "FRAMES",
            value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..=100_000)
        )]
        long_clip: Option<usize>,
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
        /// Heads in the crowd.
        #[arg(long, default_value_t = 100)]
        heads: usize,
        /// Unique jobs among the heads.
        #[arg(long, default_value_t = 100)]
        unique: usize,
        /// LOD level.
        #[arg(long, default_value_t = 0)]
        lod: u32,
        /// Compute normals too.
        #[arg(long)]
        normals: bool,
        /// Unique jobs per engine call of the batch-size table.
        #[arg(long, value_delimiter = ',', default_value = "1,10,100,1000")]
        batches: Vec<usize>,
        /// Simplified meshes to build and time when the rig has none (fractions of the
        /// triangles; `none` for none).
        #[arg(long, default_value = "0.5,0.25,0.1")]
        mesh_fractions: String,
        /// Seconds per measurement.
        #[arg(long, default_value_t = 1.0)]
        seconds: f64,
        /// Also time the warm numpy blend (`np.matmul(W, D, out=OUT); OUT += neutral`) on the
        /// same jobs with this Python (default /usr/bin/python3).
        #[arg(long, value_name = "PYTHON", num_args = 0..=1, default_missing_value = "/usr/bin/python3")]
        numpy: Option<PathBuf>,
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
        /// Play these clips (`.csv`/`.json` files in a folder, named by file stem) instead of
        /// the rig's own.
        #[arg(long, value_name = "DIR")]
        clips: Option<PathBuf>,
        /// Frames in all, consecutive runs from every clip.
        #[arg(long, default_value_t = 240)]
        frames: usize,
        /// zstd levels of the residual rows (negative: its fast modes).
        #[arg(
            long,
            value_delimiter = ',',
            allow_hyphen_values = true,
            default_value = "-5,-1,1,3"
        )]
        zstd_levels: Vec<i32>,
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
impl super::Report for bench::http::LinkBenchReport {}
impl super::Report for crowdmorph::render::offline::RenderReport {}
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
            heads,
            unique,
            lod,
            normals,
            batches,
            mesh_fractions,
            seconds,
            numpy,
            json,
        } => {
            let rig = if skinned_head {
                crowdmorph::synthetic::skinned_head()
            } else {
                load_rig(rig.as_deref())?
            };
            let mesh_fractions = if mesh_fractions == "none" {
                Vec::new()
            } else {
                mesh_fractions
                    .split(',')
                    .map(|f| f.trim().parse::<f32>())
                    .collect::<Result<Vec<_>, _>>()
                    .map_err(|e| anyhow::anyhow!("--mesh-fractions: {e}"))?
            };
            let opt = bench::cpu::BenchOptions {
                heads,
                unique,
                lod,
                normals,
                batches,
                mesh_fractions,
                seconds,
                progress: !json,
                numpy,
            };
            super::emit(&bench::cpu::bench_cpu(&rig, &opt)?, json)
        }
        Command::Gpu {
            rig,
            no_paper,
            skinned_head,
            backend,
            seconds,
            plot,
            with_cpu,
            unique,
            format,
            gpu,
            json,
        } => {
            if unique.contains(&0) {
                anyhow::bail!("--unique counts must be at least 1");
            }
            let engine = Engine::with_options(backend, gpu.options())?;
            let opt = bench::gpu::GpuBenchOptions {
                seconds,
                unique,
                format: format.into(),
            };
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
            gpu,
            json,
        } => {
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
                ..crowdmorph::render::offline::RenderOptions::default()
            };
            let report = with_spinner("bench render", || {
                bench::render::bench_render(&engine, &rig, &opt, seconds, 5)
            });
            super::emit(&report?, json)
        }
        Command::Codecs {
            rig,
            clips,
            frames,
            zstd_levels,
            json,
        } => {
            let rig = load_rig(rig.as_deref())?;
            let opt = bench::codecs::CodecBenchOptions {
                clips,
                frames,
                zstd_levels,
            };
            let report = with_spinner("bench codecs", || bench::codecs::bench_codecs(rig, &opt));
            super::emit(&report?, json)
        }
        Command::Sessions {
            rig,
            heads,
            animations,
            viewers,
            fps,
            format,
            seconds,
            backend,
            gpu,
            graph,
            clips,
            link,
            modes,
            long_clip,
            json,
        } => {
            let bytes = server_rig(rig.as_deref())?;
            let opt = bench::sessions::SessionBenchOptions {
                heads,
                animations,
                viewers,
                fps,
                format: format.into(),
                seconds,
                backend,
                gpu_memory: gpu.max_gpu_memory,
                gpu_deltas: gpu.gpu_deltas,
                graph,
                clips,
                links: link,
                modes,
                long_clip,
            };
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
            heads,
            unique,
            format,
            clients,
            seconds,
            backend,
            python_peer,
            python_peer_compute,
            gpu,
            clips,
            link,
            json,
        } => {
            let bytes = server_rig(rig.as_deref())?;
            let opt = bench::http::HttpBenchOptions {
                heads,
                unique,
                format: format.into(),
                clients,
                seconds,
                backend,
                python_peer,
                python_compute: python_peer_compute,
                gpu_memory: gpu.max_gpu_memory,
                gpu_deltas: gpu.gpu_deltas,
                clips,
                links: link,
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
