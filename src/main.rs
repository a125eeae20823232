//! The `crowdmorph` binary: parses the command line, sets up tracing, and calls the library.

use std::io::IsTerminal as _;
use std::path::PathBuf;

use anyhow::Result;
use clap::{Parser, Subcommand, ValueEnum};
use crowdmorph::engine::{BackendChoice, Engine};
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
        /// Backend to report the rig's memory on (auto: a hardware GPU if any, else the CPU).
        #[arg(long, default_value = "auto", env = "CROWDMORPH_BACKEND")]
        backend: BackendChoice,
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
        /// Engine: a hardware GPU if any, else the CPU (auto); or force cpu / gpu.
        #[arg(long, default_value = "auto", env = "CROWDMORPH_BACKEND")]
        backend: BackendChoice,
    },
    /// Draw a crowd of a rig's heads (the default grid and front camera) and write the image:
    /// the same path as POST /v1/crowd/render, offline.
    Render(Box<RenderArgs>),
    /// Measure throughput.
    Bench {
        #[command(subcommand)]
        which: BenchCommand,
    },
    /// Run the HTTP server (the embedded rig is always registered).
    Serve(Box<ServeArgs>),
    /// Load a running server: crowd-frame requests at a fixed rate (open loop, latency from
    /// each request's intended send time), or --ramp to the highest rate whose p99 meets a
    /// target; a report as a table or --json.
    Load(Box<LoadArgs>),
    /// Level of detail: importance orders, their error over a clip, simplified meshes.
    Lod {
        #[command(subcommand)]
        which: LodCommand,
    },
}

#[derive(Subcommand)]
enum LodCommand {
    /// Per LOD level, the error against the full rig over a clip for every importance order
    /// (five metrics, combined, file order): a table, --json, and a PNG plot.
    Report {
        /// glTF/GLB rig (default: the embedded head).
        file: Option<PathBuf>,
        /// Clip name; `random` makes a deterministic synthetic clip (for rigs without clips).
        #[arg(long)]
        clip: String,
        /// Targets to pin to the front of every order (repeatable).
        #[arg(long = "pin")]
        pins: Vec<String>,
        /// Write the plot here (PNG).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Side of the renders the image metrics compare, in pixels.
        #[arg(long, default_value_t = 384)]
        size: u32,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Score every target with the five metrics and print the importance order.
    Order {
        /// glTF/GLB rig (default: the embedded head).
        file: Option<PathBuf>,
        /// combined, geometric-mse, hausdorff, image-mse, ssim, yee or file-order.
        #[arg(long, default_value = "combined")]
        method: String,
        /// Targets to pin to the front (repeatable).
        #[arg(long = "pin")]
        pins: Vec<String>,
        /// Side of the renders the image metrics compare, in pixels.
        #[arg(long, default_value_t = 384)]
        size: u32,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Set a registered rig's LOD on a running server (PUT /v1/rigs/{id}/lod): order, pins,
    /// table and mesh levels. The server rebuilds it, persists it with the rig and uses it for
    /// later frames.
    Set {
        /// Rig id on the server.
        id: String,
        /// Server address.
        #[arg(
            long,
            env = "CROWDMORPH_SERVER",
            default_value = "http://127.0.0.1:8080"
        )]
        server: String,
        /// Bearer token, when the server has an admin token.
        #[arg(long, env = "CROWDMORPH_ADMIN_TOKEN", hide_env_values = true)]
        token: Option<String>,
        /// combined (default), geometric-mse, hausdorff, image-mse, ssim, yee or file-order.
        #[arg(long)]
        method: Option<String>,
        /// Targets to pin to the front (repeatable).
        #[arg(long = "pin")]
        pins: Vec<String>,
        /// A level of the table, SHAPES or SHAPES:MESH (repeatable, level 0 first; default
        /// 100/50/25/10/0 % of the targets).
        #[arg(long = "level", value_parser = tools::parse_lod_level)]
        levels: Vec<crowdmorph_proto::LodLevelRequest>,
        /// Simplified meshes to build, as fractions of the triangles.
        #[arg(long, value_delimiter = ',')]
        mesh_fractions: Vec<f32>,
        /// Print the rig as JSON instead of the table.
        #[arg(long)]
        json: bool,
    },
    /// Detect feature points and build simplified mesh levels.
    Mesh {
        /// glTF/GLB rig (default: the embedded head).
        file: Option<PathBuf>,
        /// Triangle fractions of the levels.
        #[arg(long, value_delimiter = ',', default_values_t = [0.5f32, 0.25, 0.1])]
        fractions: Vec<f32>,
        /// Write each level's neutral mesh as OBJ into this folder.
        #[arg(long)]
        obj_dir: Option<PathBuf>,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
    },
}

/// `--max-gpu-memory` of the commands that open GPU devices besides `serve` (same meaning).
#[derive(clap::Args, Clone, Copy, Debug)]
struct GpuMemoryArgs {
    /// Most GPU memory resident rigs, batch buffers and render targets may hold on each device,
    /// bytes (a rig or frame over it is refused, naming the flag; default: 2 GiB, or the
    /// device's largest buffer if larger).
    #[arg(long, env = "CROWDMORPH_MAX_GPU_MEMORY")]
    max_gpu_memory: Option<u64>,
}

impl GpuMemoryArgs {
    /// The GPU context options the flag asks for.
    fn options(self) -> crowdmorph::engine::gpu::GpuOptions {
        crowdmorph::engine::gpu::GpuOptions {
            memory: self.max_gpu_memory,
            ..Default::default()
        }
    }
}

/// Arguments of `render`.
#[derive(clap::Args)]
struct RenderArgs {
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
    gpu: GpuMemoryArgs,
    /// Print what was drawn as JSON.
    #[arg(long)]
    json: bool,
}

#[derive(Subcommand)]
enum BenchCommand {
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
        /// Heads in the crowd, each a different frame.
        #[arg(long, default_value_t = 100)]
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
        render_backend: crowdmorph::render::crowd::RenderBackend,
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
}

/// Arguments of `load`.
#[derive(clap::Args)]
struct LoadArgs {
    /// The server.
    #[arg(
        long,
        env = "CROWDMORPH_SERVER",
        default_value = "http://127.0.0.1:8080"
    )]
    url: String,
    /// Requests per second (with --ramp, the first rate tried).
    #[arg(long, default_value_t = 100.0)]
    rate: f64,
    /// Seconds measured (with --ramp, per rate).
    #[arg(long, default_value_t = 10.0)]
    duration: f64,
    /// Seconds sent before each measured window, left out of the report.
    #[arg(long, default_value_t = 1.0)]
    warmup: f64,
    /// Seconds unanswered requests may take after the window before they count as unfinished.
    #[arg(long, default_value_t = 10.0)]
    grace: f64,
    /// HTTP/1.1 connections; requests go to them in turn, one at a time on each.
    #[arg(long, default_value_t = 4, value_parser = clap::value_parser!(u64).range(1..=100_000))]
    connections: u64,
    /// Heads per request.
    #[arg(long, default_value_t = 100, value_parser = clap::value_parser!(u32).range(1..))]
    heads: u32,
    /// Share of the heads that are unique jobs, in (0, 1]; the rest are clones.
    #[arg(long, default_value_t = 1.0)]
    unique: f64,
    /// A rig to play (repeatable; each job picks one uniformly).
    #[arg(long = "rig", default_value = "default-head")]
    rigs: Vec<String>,
    /// A clip of the mix, NAME[:WEIGHT] (repeatable; default every clip of the rig equally).
    #[arg(long = "clip", value_parser = tools::load::parse_weighted)]
    clips: Vec<(String, f64)>,
    /// A LOD level of the mix, LEVEL[:WEIGHT] (repeatable; default 0).
    #[arg(long = "lod", value_parser = tools::load::parse_weighted_lod)]
    lods: Vec<(u32, f64)>,
    /// Vertex format.
    #[arg(long, value_enum, default_value_t = WireFormat::F32)]
    format: WireFormat,
    /// Ask for normals too.
    #[arg(long)]
    normals: bool,
    /// Request and response encoding.
    #[arg(long, value_enum, default_value_t = Encoding::Bincode)]
    encoding: Encoding,
    /// Seed of the clip and LOD picks.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Find the highest rate whose p99 stays under --p99-ms: double the rate from --rate until
    /// a run misses, then bisect.
    #[arg(long)]
    ramp: bool,
    /// The ramp's p99 target, milliseconds.
    #[arg(long, default_value_t = 10.0)]
    p99_ms: f64,
    /// The highest rate the ramp tries.
    #[arg(long, default_value_t = 1e6)]
    max_rate: f64,
    /// Most runs of the ramp.
    #[arg(long, default_value_t = 12)]
    max_steps: usize,
    /// Load a crowd session instead: create one from the crowd flags (--heads, --unique,
    /// --rig, --clip; --lod, --format and --normals go to the viewers), connect --viewers
    /// viewers to its stream for the run, delete it at the end.
    #[arg(long)]
    session: bool,
    /// Watch this existing session instead of creating one (implies --session).
    #[arg(long, value_name = "ID")]
    session_id: Option<String>,
    /// Viewers of the session.
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u64).range(1..=100_000))]
    viewers: u64,
    /// Ticks per second of the session created.
    #[arg(long, default_value_t = 30.0)]
    fps: f32,
    /// LOD by distance from each viewer's camera (in front of the crowd's grid), METRES:LEVEL
    /// (repeatable, ascending metres), instead of the --lod mix.
    #[arg(long = "lod-by-distance", value_name = "METRES:LEVEL", value_parser = tools::load::parse_distance_level)]
    lod_by_distance: Vec<[f32; 2]>,
    /// Bearer token for creating and deleting the session.
    #[arg(long, env = "CROWDMORPH_ADMIN_TOKEN", hide_env_values = true)]
    admin_token: Option<String>,
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

/// Arguments of `serve`; every flag is also an environment variable.
#[derive(clap::Args)]
struct ServeArgs {
    /// Address to listen on.
    #[arg(long, env = "CROWDMORPH_ADDR", default_value = "127.0.0.1:8080")]
    addr: std::net::SocketAddr,
    /// Where rigs and clips are stored (default: crowdmorph under the user's data dir).
    #[arg(long, env = "CROWDMORPH_DATA_DIR")]
    data_dir: Option<PathBuf>,
    /// Engine: auto, cpu or gpu.
    #[arg(long, env = "CROWDMORPH_BACKEND", default_value = "auto")]
    backend: BackendChoice,
    /// Bearer token required for every change: rig and clip uploads and deletes, LOD changes,
    /// creating, changing and deleting crowd sessions, and load tests (open when unset;
    /// crowd frames, renders, GETs and session streams never need it).
    #[arg(long, env = "CROWDMORPH_ADMIN_TOKEN", hide_env_values = true)]
    admin_token: Option<String>,
    /// Largest rig or clip upload, bytes.
    #[arg(long, env = "CROWDMORPH_MAX_UPLOAD_BYTES", default_value_t = 256 << 20)]
    max_upload_bytes: usize,
    /// Largest body of other requests, bytes.
    #[arg(long, env = "CROWDMORPH_MAX_REQUEST_BYTES", default_value_t = 16 << 20)]
    max_request_bytes: usize,
    /// Most heads per crowd request.
    #[arg(long, env = "CROWDMORPH_MAX_HEADS", default_value_t = 100_000)]
    max_heads: usize,
    /// Most memory one upload (rig or clips) or LOD build may hold, bytes: estimated from the
    /// file's headers before any work, then charged as it is allocated (413 past it).
    #[arg(
        long,
        env = "CROWDMORPH_MAX_UPLOAD_MEMORY",
        alias = "max-decoded-bytes",
        default_value_t = 1 << 30
    )]
    max_upload_memory: u64,
    /// Most memory all rigs together may hold, with uploads and LOD builds in progress,
    /// bytes (503 past it; default: half the machine's memory).
    #[arg(long, env = "CROWDMORPH_MAX_RIG_MEMORY")]
    max_rig_memory: Option<u64>,
    /// Most GPU memory resident rigs, batch buffers and render targets may hold on each device,
    /// bytes (a rig over it gets 413, one that does not fit now 503; default: 2 GiB, or the
    /// device's largest buffer if larger).
    #[arg(long, env = "CROWDMORPH_MAX_GPU_MEMORY")]
    max_gpu_memory: Option<u64>,
    /// Crowd requests that may wait for the batcher at once (more get 503).
    #[arg(long, env = "CROWDMORPH_QUEUE_REQUESTS", default_value_t = 1024)]
    queue_requests: usize,
    /// Output bytes admitted crowd requests may hold at once (more get 503).
    #[arg(long, env = "CROWDMORPH_QUEUE_MEMORY_BYTES", default_value_t = 2 << 30)]
    queue_memory_bytes: usize,
    /// A batch closes at this cost (vertices × active shapes over its unique jobs)...
    #[arg(long, env = "CROWDMORPH_BATCH_COST", default_value_t = 200_000_000)]
    batch_cost: u64,
    /// ...or when its oldest job has waited this many microseconds, while the engine is busy
    /// (an idle engine takes work at once).
    #[arg(long, env = "CROWDMORPH_BATCH_DELAY_US", default_value_t = 1000)]
    batch_delay_us: u64,
    /// Hold work for the batch delay even when the engine is idle (more coalescing of
    /// identical jobs at low load; every lone request waits the delay).
    #[arg(long, env = "CROWDMORPH_BATCH_HOLD_WHEN_IDLE")]
    batch_hold_when_idle: bool,
    /// Crowd-request deadline, milliseconds (504 past it).
    #[arg(long, env = "CROWDMORPH_REQUEST_TIMEOUT_MS", default_value_t = 10_000)]
    request_timeout_ms: u64,
    /// Deadline of uploads and other requests, seconds.
    #[arg(long, env = "CROWDMORPH_ADMIN_TIMEOUT_S", default_value_t = 300)]
    admin_timeout_s: u64,
    /// Requests handled at once; more are shed with 503.
    #[arg(long, env = "CROWDMORPH_MAX_CONCURRENCY", default_value_t = 2048)]
    max_concurrency: usize,
    /// Connections open at once; past it the longest-idle one is closed to admit a new one, and
    /// with every one busy the new one gets 503 (default: from the open-file limit, which
    /// `serve` first raises to its hard maximum; at most 65536).
    #[arg(long, env = "CROWDMORPH_MAX_CONNECTIONS", value_parser = clap::value_parser!(u64).range(1..))]
    max_connections: Option<u64>,
    /// Milliseconds a request's headers may take, from the accept or from the request's first
    /// byte on a kept-alive connection; then the connection is closed.
    #[arg(long, env = "CROWDMORPH_HEADER_TIMEOUT_MS", default_value_t = 10_000, value_parser = clap::value_parser!(u64).range(1..))]
    header_timeout_ms: u64,
    /// Seconds a kept-alive connection may wait for its next request.
    #[arg(long, env = "CROWDMORPH_IDLE_TIMEOUT_S", default_value_t = 60, value_parser = clap::value_parser!(u64).range(1..))]
    idle_timeout_s: u64,
    /// Origins allowed by CORS, comma-separated (`*` for any; none by default).
    #[arg(long, env = "CROWDMORPH_CORS_ORIGINS", value_delimiter = ',')]
    cors_origin: Vec<String>,
    /// Do not order new rigs' blendshapes by the importance metrics (nor build mesh levels)
    /// in the background; they keep the import's quick order until PUT /v1/rigs/{id}/lod.
    #[arg(long, env = "CROWDMORPH_NO_AUTO_LOD")]
    no_auto_lod: bool,
    /// Pixels that rendered frames in flight may hold together (a W × H image takes W × H;
    /// 503 render_busy past it; default 64 Mpixels).
    #[arg(long, env = "CROWDMORPH_RENDER_PIXELS", default_value_t = crowdmorph::server::config::DEFAULT_RENDER_PIXELS, value_parser = clap::value_parser!(u64).range(1..))]
    render_pixels: u64,
    /// Estimated milliseconds of rendering (blending, drawing and encoding, priced from what
    /// each render draws) that rendered frames in flight may hold together: a render estimated
    /// past it gets 413 render_too_costly, one that does not fit now 503 render_busy.
    #[arg(long, env = "CROWDMORPH_RENDER_WORK_MS", default_value_t = crowdmorph::server::config::DEFAULT_RENDER_WORK.as_millis() as u64, value_parser = clap::value_parser!(u64).range(1..))]
    render_work_ms: u64,
    /// Share (0 to 1) of the pixel and render work budgets that session viewers' frames may
    /// hold together, so that HTTP renders keep being served while viewers stream.
    #[arg(long, env = "CROWDMORPH_VIEWER_RENDER_SHARE", default_value_t = crowdmorph::server::config::DEFAULT_VIEWER_RENDER_SHARE, value_parser = parse_share)]
    viewer_render_share: f64,
    /// Most pixels of one session viewer's image (a hello asking for more is closed with
    /// 1008; default 1920 × 1080).
    #[arg(long, env = "CROWDMORPH_MAX_VIEWER_PIXELS", default_value_t = crowdmorph::server::sessions::DEFAULT_MAX_VIEWER_PIXELS, value_parser = clap::value_parser!(u64).range(1..))]
    max_viewer_pixels: u64,
    /// Adapter that draws rendered frames: auto (the engine's GPU, else any adapter, software
    /// ones such as lavapipe included), gpu (hardware only) or off.
    #[arg(long, env = "CROWDMORPH_RENDER_BACKEND", default_value = "auto")]
    render_backend: crowdmorph::server::RenderBackend,
    /// Crowd sessions that may exist at once (503 too_many_sessions past it).
    #[arg(long, env = "CROWDMORPH_MAX_SESSIONS", default_value_t = 64, value_parser = clap::value_parser!(u64).range(1..))]
    max_sessions: u64,
    /// Heads one session may hold (413 too_many_heads past it).
    #[arg(long, env = "CROWDMORPH_MAX_SESSION_HEADS", default_value_t = 10_000, value_parser = clap::value_parser!(u64).range(1..))]
    max_session_heads: u64,
    /// Viewers one session may have at once (more are closed with 1013).
    #[arg(long, env = "CROWDMORPH_MAX_SESSION_VIEWERS", default_value_t = 32, value_parser = clap::value_parser!(u64).range(1..))]
    max_session_viewers: u64,
    /// Messages per second a session viewer may send (more close it with 1008).
    #[arg(long, env = "CROWDMORPH_MAX_VIEWER_MESSAGES", default_value_t = 60, value_parser = clap::value_parser!(u32).range(1..))]
    max_viewer_messages: u32,
    /// Longest POST /v1/loadtest, warm-up included, seconds; 0 disables the endpoint.
    #[arg(long, env = "CROWDMORPH_LOADTEST_MAX_DURATION_S", default_value_t = 60)]
    loadtest_max_duration_s: u64,
    /// Highest request rate of a load test, requests per second.
    #[arg(long, env = "CROWDMORPH_LOADTEST_MAX_RATE", default_value_t = 10_000.0)]
    loadtest_max_rate: f64,
    /// Most requests a load test keeps in flight (never more than half of --queue-requests).
    #[arg(
        long,
        env = "CROWDMORPH_LOADTEST_MAX_CONCURRENCY",
        default_value_t = 64
    )]
    loadtest_max_concurrency: usize,
}

/// A share in [0, 1].
fn parse_share(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if (0.0..=1.0).contains(&v) => Ok(v),
        _ => Err(format!("{s:?} is not a number in [0, 1]")),
    }
}

/// Descriptors kept for everything but connections: stored rig files, the engine's device
/// files, the listener, and the refused connections being answered.
const RESERVED_FILES: u64 = 320;

/// Raises the soft open-file limit to the hard one, as every connection holds a descriptor, and
/// returns the limit then in force (`None` where it cannot be read).
#[cfg(unix)]
#[allow(clippy::unnecessary_cast)] // rlim_t is u64 on Linux, not on every unix.
fn raise_open_file_limit() -> Option<u64> {
    let mut lim = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: getrlimit writes one rlimit through a pointer to a live local.
    if unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut lim) } != 0 {
        return None;
    }
    if lim.rlim_cur >= lim.rlim_max {
        return Some(lim.rlim_cur as u64);
    }
    let raised = libc::rlimit {
        rlim_cur: lim.rlim_max,
        rlim_max: lim.rlim_max,
    };
    // SAFETY: setrlimit reads one rlimit through a pointer to a live local.
    if unsafe { libc::setrlimit(libc::RLIMIT_NOFILE, &raised) } == 0 {
        tracing::info!(
            from = lim.rlim_cur as u64,
            to = lim.rlim_max as u64,
            "raised the open-file limit"
        );
        Some(lim.rlim_max as u64)
    } else {
        // macOS, for one, refuses an unlimited hard limit as the soft one; the soft one stays.
        Some(lim.rlim_cur as u64)
    }
}

#[cfg(not(unix))]
fn raise_open_file_limit() -> Option<u64> {
    None
}

/// The connection cap: `--max-connections`, else the open-file limit less
/// [`RESERVED_FILES`] (at least half of it), at most 65,536 (choosing which connection to evict
/// scans the open ones).
fn max_connections(flag: Option<u64>, open_files: Option<u64>) -> usize {
    let derived = open_files.map(|limit| {
        limit
            .saturating_sub(RESERVED_FILES)
            .max(limit / 2)
            .clamp(1, 65_536)
    });
    let cap = match (flag, derived) {
        (Some(n), _) => n,
        (None, Some(n)) => n,
        (None, None) => crowdmorph::server::ServerConfig::default().max_connections as u64,
    };
    if let Some(limit) = open_files
        && cap + RESERVED_FILES > limit
    {
        tracing::warn!(
            max_connections = cap,
            open_file_limit = limit,
            "the connection cap leaves little room under the open-file limit"
        );
    }
    tracing::info!(max_connections = cap, open_file_limit = ?open_files, "connection cap");
    usize::try_from(cap).unwrap_or(usize::MAX)
}

fn run_serve(a: ServeArgs) -> Result<()> {
    use crowdmorph::server::{self, ServerConfig};
    let open_files = raise_open_file_limit();
    let config = ServerConfig {
        data_dir: Some(a.data_dir.unwrap_or_else(server::default_data_dir)),
        backend: a.backend,
        admin_token: a.admin_token.filter(|t| !t.is_empty()),
        max_upload_bytes: a.max_upload_bytes,
        max_request_bytes: a.max_request_bytes,
        max_heads: a.max_heads,
        max_upload_memory: a.max_upload_memory,
        max_rig_memory: a
            .max_rig_memory
            .unwrap_or_else(server::config::default_rig_memory),
        queue_requests: a.queue_requests,
        queue_memory_bytes: a.queue_memory_bytes,
        batch_cost: a.batch_cost,
        batch_delay: std::time::Duration::from_micros(a.batch_delay_us),
        batch_hold_when_idle: a.batch_hold_when_idle,
        request_timeout: std::time::Duration::from_millis(a.request_timeout_ms),
        admin_timeout: std::time::Duration::from_secs(a.admin_timeout_s),
        max_concurrency: a.max_concurrency,
        max_connections: max_connections(a.max_connections, open_files),
        header_timeout: std::time::Duration::from_millis(a.header_timeout_ms),
        idle_timeout: std::time::Duration::from_secs(a.idle_timeout_s),
        cors_origins: a.cors_origin,
        auto_lod: !a.no_auto_lod,
        render_pixels: a.render_pixels,
        render_work: std::time::Duration::from_millis(a.render_work_ms),
        viewer_render_share: a.viewer_render_share,
        gpu_memory: a.max_gpu_memory,
        render_backend: a.render_backend,
        sessions: server::sessions::SessionLimits {
            max_sessions: usize::try_from(a.max_sessions).unwrap_or(usize::MAX),
            max_heads: usize::try_from(a.max_session_heads).unwrap_or(usize::MAX),
            max_viewers: usize::try_from(a.max_session_viewers).unwrap_or(usize::MAX),
            max_viewer_messages: a.max_viewer_messages,
            max_viewer_pixels: a.max_viewer_pixels,
            ..server::sessions::SessionLimits::default()
        },
        loadtest_max_duration: std::time::Duration::from_secs(a.loadtest_max_duration_s),
        loadtest_max_rate: a.loadtest_max_rate,
        loadtest_max_concurrency: a.loadtest_max_concurrency,
    };
    if let Some(d) = &config.data_dir {
        tracing::info!(data_dir = %d.display(), "data directory");
    }
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    runtime.block_on(async move {
        let listener = tokio::net::TcpListener::bind(a.addr)
            .await
            .map_err(|e| anyhow::anyhow!("cannot listen on {}: {e}", a.addr))?;
        server::run(listener, config, server::shutdown_signal()).await?;
        anyhow::Ok(())
    })
}

#[derive(Clone, Copy, ValueEnum)]
enum WireFormat {
    F32,
    F16,
    Q16,
}

impl From<WireFormat> for crowdmorph_proto::Format {
    fn from(f: WireFormat) -> Self {
        match f {
            WireFormat::F32 => crowdmorph_proto::Format::F32,
            WireFormat::F16 => crowdmorph_proto::Format::F16,
            WireFormat::Q16 => crowdmorph_proto::Format::Q16,
        }
    }
}

#[derive(Clone, Copy, ValueEnum)]
enum Encoding {
    Bincode,
    Json,
}

#[derive(Clone, Copy, ValueEnum)]
enum Format {
    F32,
    F16,
}

fn main() -> Result<()> {
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
    let cli = Cli::parse();
    match cli.command {
        Command::Inspect {
            file,
            json,
            backend,
        } => {
            let rig = tools::load_rig(file.as_deref())?;
            let engine = Engine::new(backend)?;
            let mut summary = tools::summarize_on(&rig, &engine)?;
            summary.extensions = tools::file_extensions(file.as_deref())?;
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
            backend,
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
            let engine = Engine::new(backend)?;
            tools::eval_with(&engine, &rig, &clip, frame, lod, mode, &out)?;
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
                    normals,
                    batches,
                    mesh_fractions,
                    seconds,
                    numpy,
                    json,
                },
        } => {
            let rig = tools::load_rig(rig.as_deref())?;
            let mesh_fractions = if mesh_fractions == "none" {
                Vec::new()
            } else {
                mesh_fractions
                    .split(',')
                    .map(|f| f.trim().parse::<f32>())
                    .collect::<Result<Vec<_>, _>>()
                    .map_err(|e| anyhow::anyhow!("--mesh-fractions: {e}"))?
            };
            let opt = bench::BenchOptions {
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
            let report = bench::bench_cpu(&rig, &opt)?;
            if json {
                println!("{}", serde_json::to_string_pretty(&report)?);
            } else {
                print!("{}", bench::report_text(&report));
            }
        }
        Command::Lod { which } => run_lod(which)?,
        Command::Bench {
            which:
                BenchCommand::Gpu {
                    rig,
                    no_paper,
                    backend,
                    seconds,
                    plot,
                    with_cpu,
                    gpu,
                    json,
                },
        } => {
            use crowdmorph::tools::bench_gpu;
            let engine = Engine::with_options(backend, gpu.options())?;
            let mut rigs = Vec::new();
            if !no_paper {
                rigs.push(tools::synthetic::paper_scale_rig());
            }
            for p in &rig {
                rigs.push(tools::load_rig(Some(p))?);
            }
            let mut reports = vec![bench_gpu::bench_gpu(&engine, &rigs, seconds)?];
            if with_cpu {
                reports.push(bench_gpu::bench_gpu(&Engine::cpu(), &rigs, seconds)?);
            }
            if let Some(path) = &plot {
                bench_gpu::write_plot(&reports, path)?;
            }
            if json {
                println!("{}", serde_json::to_string_pretty(&reports)?);
            } else {
                for r in &reports {
                    print!("{}", bench_gpu::report_text(r));
                }
            }
        }
        Command::Serve(args) => run_serve(*args)?,
        Command::Load(args) => run_load(*args)?,
        Command::Render(args) => run_render(*args)?,
        Command::Bench {
            which:
                BenchCommand::Render {
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
                },
        } => {
            use crowdmorph::tools::render as r;
            let rig = tools::load_rig(rig.as_deref())?;
            let engine = Engine::with_options(backend, gpu.options())?;
            let opt = r::RenderOptions {
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
                ..r::RenderOptions::default()
            };
            let bar = tools::spinner("bench render");
            let report = r::bench_render(&engine, &rig, &opt, seconds, 5);
            bar.finish_and_clear();
            let report = report?;
            if json {
                println!("{}", serde_json::to_string_pretty(&report)?);
            } else {
                print!("{}", r::report_text(&report));
            }
        }
        Command::Bench {
            which:
                BenchCommand::Sessions {
                    rig,
                    heads,
                    animations,
                    viewers,
                    fps,
                    format,
                    seconds,
                    backend,
                    gpu,
                    json,
                },
        } => {
            use crowdmorph::server::bench_sessions as sessions;
            let bytes = match &rig {
                Some(p) => Some(crowdmorph::server::bench::self_contained_bytes(p)?),
                None => None,
            };
            let opt = sessions::SessionBenchOptions {
                heads,
                animations,
                viewers,
                fps,
                format: format.into(),
                seconds,
                backend,
                gpu_memory: gpu.max_gpu_memory,
            };
            let bar = tools::spinner("bench sessions");
            let report = sessions::bench_sessions(bytes, &opt);
            bar.finish_and_clear();
            let report = report?;
            if json {
                println!("{}", serde_json::to_string_pretty(&report)?);
            } else {
                print!("{}", sessions::report_text(&report));
            }
        }
        Command::Bench {
            which:
                BenchCommand::Http {
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
                    json,
                },
        } => {
            use crowdmorph::server::bench as http;
            let bytes = match &rig {
                Some(p) => Some(http::self_contained_bytes(p)?),
                None => None,
            };
            let opt = http::HttpBenchOptions {
                heads,
                unique,
                format: format.into(),
                clients,
                seconds,
                backend,
                python_peer,
                python_compute: python_peer_compute,
                gpu_memory: gpu.max_gpu_memory,
            };
            let bar = tools::spinner("bench http: in-process, loopback, saturation, half load");
            let report = http::bench_http(bytes, &opt);
            bar.finish_and_clear();
            let report = report?;
            if json {
                println!("{}", serde_json::to_string_pretty(&report)?);
            } else {
                print!("{}", http::report_text(&report));
            }
        }
    }
    Ok(())
}

fn run_load(a: LoadArgs) -> Result<()> {
    use crowdmorph::load::{CrowdShape, RampOptions, WireEncoding};
    let crowd = CrowdShape {
        heads: a.heads,
        unique: a.unique,
        rigs: a.rigs,
        clips: a.clips.into_iter().collect(),
        lods: if a.lods.is_empty() {
            CrowdShape::default().lods
        } else {
            a.lods.into_iter().collect()
        },
        format: match a.format {
            WireFormat::F32 => crowdmorph_proto::Format::F32,
            WireFormat::F16 => crowdmorph_proto::Format::F16,
            WireFormat::Q16 => crowdmorph_proto::Format::Q16,
        },
        normals: a.normals,
        encoding: match a.encoding {
            Encoding::Bincode => WireEncoding::Bincode,
            Encoding::Json => WireEncoding::Json,
        },
        seed: a.seed,
    };
    let cmd = tools::load::LoadCommand {
        url: a.url,
        rate: a.rate,
        duration: a.duration,
        warmup: a.warmup,
        grace: a.grace,
        connections: usize::try_from(a.connections)?,
        crowd,
        ramp: a.ramp.then(|| RampOptions {
            p99_ms: a.p99_ms,
            max_rate: a.max_rate,
            max_steps: a.max_steps,
            ..RampOptions::default()
        }),
        progress: true,
        session: (a.session || a.session_id.is_some()).then(|| tools::load::SessionMode {
            viewers: a.viewers as usize,
            fps: a.fps,
            attach: a.session_id,
            admin_token: a.admin_token,
            lod_by_distance: (!a.lod_by_distance.is_empty()).then_some(a.lod_by_distance),
        }),
    };
    let outcome = tools::load::load(&cmd)?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&outcome)?);
    } else {
        print!("{}", outcome.text());
    }
    Ok(())
}

fn run_render(a: RenderArgs) -> Result<()> {
    use crowdmorph::tools::render as r;
    let rig = tools::load_rig(a.file.as_deref())?;
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
    };
    let report = r::render_to_file(&engine, &rig, &opt, &a.out)?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        eprintln!(
            "wrote {} ({}×{} {}, {} heads, {} unique; rendered on {})",
            a.out.display(),
            report.width,
            report.height,
            report.format,
            report.heads,
            report.unique,
            report.adapter
        );
    }
    Ok(())
}

fn run_lod(which: LodCommand) -> Result<()> {
    use crowdmorph::lod::cli;
    match which {
        LodCommand::Set {
            id,
            server,
            token,
            method,
            pins,
            levels,
            mesh_fractions,
            json,
        } => {
            let request = crowdmorph_proto::LodRequest {
                method,
                pinned: pins,
                levels: (!levels.is_empty()).then_some(levels),
                mesh_fractions,
                ..crowdmorph_proto::LodRequest::default()
            };
            let info = tools::lod_set(&server, token.as_deref(), &id, &request)?;
            if json {
                println!("{}", serde_json::to_string_pretty(&info)?);
            } else {
                print!("{}", tools::lod_table_text(&info));
            }
        }
        LodCommand::Report {
            file,
            clip,
            pins,
            out,
            size,
            json,
        } => {
            let mut rig = tools::load_rig(file.as_deref())?;
            cli::report_command(&mut rig, &clip, &pins, size, out.as_deref(), json)?;
        }
        LodCommand::Order {
            file,
            method,
            pins,
            size,
            json,
        } => {
            let rig = tools::load_rig(file.as_deref())?;
            cli::order_command(&rig, &method, &pins, size, json)?;
        }
        LodCommand::Mesh {
            file,
            fractions,
            obj_dir,
            json,
        } => {
            let rig = tools::load_rig(file.as_deref())?;
            cli::mesh_command(&rig, &fractions, obj_dir.as_deref(), json)?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use clap::{CommandFactory, Parser};

    use super::{BenchCommand, Cli, Command};

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
                which: BenchCommand::Http { python_peer, .. },
            } => python_peer,
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
                which: BenchCommand::Cpu { numpy, .. },
            } => assert_eq!(numpy, Some(std::path::PathBuf::from("/usr/bin/python3"))),
            _ => panic!("parsed as another command"),
        }
    }

    #[test]
    fn render_and_every_bench_command_with_a_gpu_take_max_gpu_memory() {
        let memory = |args: &[&str]| match Cli::try_parse_from(args).expect("parses").command {
            Command::Render(a) => a.gpu.max_gpu_memory,
            Command::Bench {
                which:
                    BenchCommand::Gpu { gpu, .. }
                    | BenchCommand::Render { gpu, .. }
                    | BenchCommand::Sessions { gpu, .. }
                    | BenchCommand::Http { gpu, .. },
            } => gpu.max_gpu_memory,
            _ => panic!("parsed as another command"),
        };
        for cmd in [
            &["render"][..],
            &["bench", "gpu"],
            &["bench", "render"],
            &["bench", "sessions"],
            &["bench", "http"],
        ] {
            let mut args = vec!["crowdmorph"];
            args.extend_from_slice(cmd);
            assert_eq!(memory(&args), None, "{cmd:?}: the default");
            args.extend_from_slice(&["--max-gpu-memory", "67108864"]);
            assert_eq!(memory(&args), Some(64 << 20), "{cmd:?}");
        }
    }

    #[test]
    fn bench_http_takes_json_and_backend_flags() {
        let cli =
            Cli::try_parse_from(["crowdmorph", "bench", "http", "--json", "--backend", "cpu"])
                .expect("bench http --json --backend cpu parses");
        match cli.command {
            Command::Bench {
                which: BenchCommand::Http { json, backend, .. },
            } => {
                assert!(json);
                assert_eq!(backend, crowdmorph::engine::BackendChoice::Cpu);
            }
            _ => panic!("parsed as another command"),
        }
    }
}
