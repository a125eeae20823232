//! Server configuration: every limit and timeout in one place. [`ServerConfig`] is also the
//! `serve` command's flags (`clap::Args`, flattened into it): each setting, its flag, its
//! environment variable, its default and its `--help` text are written once, here. The
//! [`Default`] is those defaults without reading the environment (tests build on it).

use std::path::PathBuf;
use std::time::Duration;

use clap::{Args, FromArgMatches};

use crowdmorph_engine::BackendChoice;
pub use crowdmorph_engine::render::crowd::RenderBackend;

/// Everything [`super::run`] needs to know besides the listener.
#[derive(Clone, Debug, Args)]
pub struct ServerConfig {
    /// Where rigs and clips are persisted; `None` keeps them in memory only (tests). `serve`
    /// sets it from its own `--data-dir`.
    #[arg(skip)]
    pub data_dir: Option<PathBuf>,
    /// Engine: auto (a hardware GPU if there is one, else the CPU engine), cpu or gpu.
    #[arg(long, env = "CROWDMORPH_BACKEND", default_value = "auto")]
    pub backend: BackendChoice,
    /// Bearer token (`Authorization: Bearer T`) required by every change and by load tests:
    /// POST /v1/rigs, DELETE /v1/rigs/{id}, PUT /v1/rigs/{id}/lod, PUT /v1/rigs/{id}/joint-map,
    /// DELETE /v1/rigs/{id}/joint-map, PUT /v1/rigs/{id}/graphs/{name}, POST
    /// /v1/rigs/{id}/graphs/{name}, DELETE /v1/rigs/{id}/graphs/{name}, PUT
    /// /v1/rigs/{id}/masks/{name}, DELETE /v1/rigs/{id}/masks/{name}, PUT
    /// /v1/rigs/{id}/mappings/{name}, DELETE /v1/rigs/{id}/mappings/{name}, POST
    /// /v1/rigs/{id}/clips, DELETE /v1/rigs/{id}/clips/{clip}, PUT
    /// /v1/rigs/{id}/clips/{clip}/texture, DELETE /v1/rigs/{id}/clips/{clip}/texture, POST
    /// /v1/sessions, PUT
    /// /v1/sessions/{id}, PATCH /v1/sessions/{id}, DELETE /v1/sessions/{id}, POST
    /// /v1/sessions/{id}/live, GET /v1/sessions/{id}/live (the producers' socket), POST /v1/loadtest
    /// and GET /v1/loadtest/{id}. Open when unset; crowd frames, renders, the other GETs and
    /// session streams never need it.
    #[arg(long, env = "CROWDMORPH_ADMIN_TOKEN", hide_env_values = true, value_parser = non_empty)]
    pub admin_token: Option<String>,
    /// Largest rig or clip upload, bytes.
    #[arg(long, env = "CROWDMORPH_MAX_UPLOAD_BYTES", default_value_t = 256 << 20)]
    pub max_upload_bytes: usize,
    /// Largest body of other requests, bytes.
    #[arg(long, env = "CROWDMORPH_MAX_REQUEST_BYTES", default_value_t = 16 << 20)]
    pub max_request_bytes: usize,
    /// Most heads per crowd request.
    #[arg(long, env = "CROWDMORPH_MAX_HEADS", default_value_t = 100_000)]
    pub max_heads: usize,
    /// Most clips one rig may have (a clip upload past it gets 413 too_many_clips): a graph
    /// built from the clips compares every pair of them.
    #[arg(
        long,
        env = "CROWDMORPH_MAX_CLIPS",
        default_value_t = 256,
        value_parser = at_least_one
    )]
    pub max_clips: usize,
    /// Most work one motion graph may take before it is stored, priced before it starts:
    /// for `?auto=1`, frame pairs compared times the numbers per frame compared (about
    /// (frames of all clips)² × (targets, or 768 on a skinned rig)), plus the measurement; for
    /// a PUT, each frame its nodes play (once) times the deltas and vertices blended per frame.
    /// Past it: 413 graph_too_costly. The default is a few seconds of one core.
    #[arg(
        long,
        env = "CROWDMORPH_MAX_GRAPH_WORK",
        default_value_t = DEFAULT_MAX_GRAPH_WORK,
        value_parser = clap::value_parser!(u64).range(1..)
    )]
    pub max_graph_work: u64,
    /// Most memory one upload (rig or clips) or LOD build may hold, bytes: what its file's
    /// headers say it will cost (decoded arrays, baked clip tables, engine layouts, the stored
    /// record) is checked against this before any work, then every allocation is charged as
    /// it happens (413 past it).
    #[arg(
        long,
        env = "CROWDMORPH_MAX_UPLOAD_MEMORY",
        alias = "max-decoded-bytes",
        default_value_t = 1 << 30
    )]
    pub max_upload_memory: u64,
    /// Largest side of a kept texture, pixels: an uploaded image larger than this is halved
    /// until it fits (the upload's notes say so). Decoding still needs the full image within
    /// `--max-upload-memory`.
    #[arg(
        long,
        env = "CROWDMORPH_MAX_TEXTURE_SIZE",
        default_value_t = crowdmorph_import::DEFAULT_MAX_TEXTURE_SIZE,
        value_parser = clap::value_parser!(u32).range(1..=16384)
    )]
    pub max_texture_size: u32,
    /// Most memory all rigs together may hold, with uploads and LOD builds in progress, bytes
    /// (503 past it; default: half the machine's memory).
    #[arg(long, env = "CROWDMORPH_MAX_RIG_MEMORY")]
    pub max_rig_memory: Option<u64>,
    /// Most GPU memory resident rigs, batch buffers and render targets may hold on each
    /// device, bytes (a rig over it gets 413, one that does not fit now 503; default: ¾ of a
    /// discrete GPU's memory, else 2 GiB or the device's largest buffer if larger).
    #[arg(long = "max-gpu-memory", env = "CROWDMORPH_MAX_GPU_MEMORY")]
    pub gpu_memory: Option<u64>,
    /// How rigs keep their blendshape deltas on the GPU: f32 (as imported), or f16 (half the
    /// memory and the traffic of the blend; each delta rounded to binary16, about 1/2048 of
    /// itself; a rig with a delta past 65,504 keeps f32). No effect on the CPU engine.
    #[arg(
        long = "gpu-deltas",
        env = "CROWDMORPH_GPU_DELTAS",
        default_value = "f32"
    )]
    pub gpu_deltas: crowdmorph_engine::gpu::DeltaFormat,
    /// Crowd requests that may wait for the batcher at once (more get 503).
    #[arg(long, env = "CROWDMORPH_QUEUE_REQUESTS", default_value_t = 1024)]
    pub queue_requests: usize,
    /// Output bytes admitted crowd requests may hold at once, queued, computing or being sent
    /// (more get 503; one request larger than it, 413).
    #[arg(long, env = "CROWDMORPH_QUEUE_MEMORY_BYTES", default_value_t = 2 << 30)]
    pub queue_memory_bytes: usize,
    /// A batch closes at this cost (vertices × active shapes over its unique jobs; default
    /// 2e8 on the CPU engine, about 100 ICT FaceKit heads, and 3.2e9 on a GPU, about 2,200,
    /// so that a 10,000-head tick is a few engine calls, not fifty)...
    #[arg(long, env = "CROWDMORPH_BATCH_COST")]
    pub batch_cost: Option<u64>,
    /// ...or when its oldest job has waited this many microseconds, while the engine is busy
    /// (an idle engine takes work at once).
    #[arg(
        long = "batch-delay-us",
        env = "CROWDMORPH_BATCH_DELAY_US",
        default_value = "1000",
        value_parser = micros
    )]
    pub batch_delay: Duration,
    /// Hold work for the batch delay even when the engine is idle (more coalescing of
    /// identical jobs at low load; every lone request waits the delay).
    #[arg(long, env = "CROWDMORPH_BATCH_HOLD_WHEN_IDLE")]
    pub batch_hold_when_idle: bool,
    /// Crowd-request deadline, milliseconds, from arrival to the response being ready (504
    /// past it).
    #[arg(
        long = "request-timeout-ms",
        env = "CROWDMORPH_REQUEST_TIMEOUT_MS",
        default_value = "10000",
        value_parser = millis
    )]
    pub request_timeout: Duration,
    /// Deadline of uploads and other requests, seconds (504 past it).
    #[arg(
        long = "admin-timeout-s",
        env = "CROWDMORPH_ADMIN_TIMEOUT_S",
        default_value = "300",
        value_parser = seconds
    )]
    pub admin_timeout: Duration,
    /// Requests handled at once; more are shed with 503.
    #[arg(long, env = "CROWDMORPH_MAX_CONCURRENCY", default_value_t = 2048)]
    pub max_concurrency: usize,
    /// Connections open at once; past it the longest-idle one is closed to admit a new one,
    /// and with every one busy the new one gets 503 `too_many_connections` (default: `serve`
    /// derives it from the open-file limit, which it first raises to its hard maximum; at most
    /// 65536; 4096 elsewhere).
    #[arg(long, env = "CROWDMORPH_MAX_CONNECTIONS", value_parser = at_least_one)]
    pub max_connections: Option<usize>,
    /// Milliseconds a request's headers may take, from the accept or from the request's first
    /// byte on a kept-alive connection; then the connection is closed (bytes trickling in do
    /// not extend it).
    #[arg(
        long = "header-timeout-ms",
        env = "CROWDMORPH_HEADER_TIMEOUT_MS",
        default_value = "10000",
        value_parser = millis_positive
    )]
    pub header_timeout: Duration,
    /// Seconds a kept-alive connection may wait for its next request.
    #[arg(
        long = "idle-timeout-s",
        env = "CROWDMORPH_IDLE_TIMEOUT_S",
        default_value = "60",
        value_parser = seconds_positive
    )]
    pub idle_timeout: Duration,
    /// Origins allowed by CORS, comma-separated (`*` for any; none by default, which disables
    /// CORS headers).
    #[arg(
        long = "cors-origin",
        env = "CROWDMORPH_CORS_ORIGINS",
        value_delimiter = ','
    )]
    pub cors_origins: Vec<String>,
    /// Do not order new rigs' blendshapes by the importance metrics (nor build their 50/25/10 %
    /// mesh levels) in the background after registration and at start; they keep the
    /// import's quick order until PUT /v1/rigs/{id}/lod.
    #[arg(long, env = "CROWDMORPH_NO_AUTO_LOD")]
    pub no_auto_lod: bool,
    /// Pixels that rendered frames in flight may hold together: a W × H image takes W × H
    /// until it is sent (413 image_too_large over it, 503 render_busy when full; default 64
    /// Mpixels, about 3 GiB at ~48 bytes a pixel in flight).
    #[arg(
        long,
        env = "CROWDMORPH_RENDER_PIXELS",
        default_value_t = DEFAULT_RENDER_PIXELS,
        value_parser = clap::value_parser!(u64).range(1..)
    )]
    pub render_pixels: u64,
    /// Estimated milliseconds of rendering (blending, drawing and encoding, priced from what
    /// each render draws) that rendered frames in flight may hold together: a render estimated
    /// past it gets 413 render_too_costly, one that does not fit now 503 render_busy. One
    /// admitted past its request deadline gets 504 and stops at its next stage.
    #[arg(
        long = "render-work-ms",
        env = "CROWDMORPH_RENDER_WORK_MS",
        default_value = "4000",
        value_parser = millis_positive
    )]
    pub render_work: Duration,
    /// Share (0 to 1) of the pixel and render work budgets that session viewers' frames may
    /// hold together, so that HTTP renders keep being served while viewers stream.
    #[arg(
        long,
        env = "CROWDMORPH_VIEWER_RENDER_SHARE",
        default_value_t = 0.5,
        value_parser = share
    )]
    pub viewer_render_share: f64,
    /// Adapter that draws rendered frames: auto (the engine's GPU, else any adapter, software
    /// ones such as lavapipe included), gpu (hardware only) or off.
    #[arg(long, env = "CROWDMORPH_RENDER_BACKEND", default_value = "auto")]
    pub render_backend: RenderBackend,
    /// Store clips compressed (per-curve quantization, linear prediction, zstd segments)
    /// within this fraction of the rig's bounding-box diagonal per vertex, e.g. 3e-4; clips
    /// are put into that form as they arrive, so the same frames are served before and after a
    /// restart (default: stored exactly).
    #[arg(long, env = "CROWDMORPH_COMPRESS_CLIPS", value_parser = clip_error)]
    pub compress_clips: Option<f32>,
    /// A rig store shared by replicas, in place of the data dir: `file:///dir` (a directory
    /// they all reach) or `s3://bucket/prefix` (any S3-compatible store; endpoint and
    /// credentials from the AWS_* environment variables, e.g. AWS_ENDPOINT_URL,
    /// AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY, AWS_REGION, AWS_ALLOW_HTTP). Every change
    /// is a new generation of its rig, written with a conditional put.
    #[arg(long, env = "CROWDMORPH_STORE", value_parser = store_url)]
    pub store: Option<String>,
    /// How often a replica reads what other replicas changed in the shared store,
    /// milliseconds: the longest a delete or a new clip takes to reach it.
    #[arg(
        long = "store-refresh-ms",
        env = "CROWDMORPH_STORE_REFRESH_MS",
        default_value = "2000",
        value_parser = millis_positive
    )]
    pub store_refresh: Duration,
    /// Limits of crowd sessions.
    #[command(flatten)]
    pub sessions: SessionLimits,
    /// Longest POST /v1/loadtest, warm-up included, seconds; 0 disables the endpoint.
    #[arg(
        long = "loadtest-max-duration-s",
        env = "CROWDMORPH_LOADTEST_MAX_DURATION_S",
        default_value = "60",
        value_parser = seconds
    )]
    pub loadtest_max_duration: Duration,
    /// Highest request rate of a load test, requests per second.
    #[arg(long, env = "CROWDMORPH_LOADTEST_MAX_RATE", default_value_t = 10_000.0)]
    pub loadtest_max_rate: f64,
    /// Most requests a load test keeps in flight (never more than half of --queue-requests).
    #[arg(
        long,
        env = "CROWDMORPH_LOADTEST_MAX_CONCURRENCY",
        default_value_t = 64
    )]
    pub loadtest_max_concurrency: usize,
}

/// Default of [`ServerConfig::render_pixels`]: 64 Mpixels (64 × 2^20), four 4096 × 4096
/// images or 72 of 1280 × 720. A pixel in flight costs about 48 bytes (4× MSAA colour and
/// depth, the resolved and staging copies on the device — host memory on lavapipe — the
/// pixels read back and the encoded image), so the default bounds renders to about 3 GiB.
pub const DEFAULT_RENDER_PIXELS: u64 = 64 << 20;

/// Default of [`ServerConfig::max_graph_work`]: 10^10 units, a few seconds of one core (the
/// frame comparisons of a build run at about 1 ns a unit in an optimized build: RobotExpressive's
/// 14 clips, 2.7 × 10^8 units, build in 0.24 s with the rig's import). The eight ICT
/// clips of 2,048 frames (1.6 × 10^10) are past it; a thousand nodes on one such clip (3 × 10^9,
/// each frame measured once) are within it.
pub const DEFAULT_MAX_GRAPH_WORK: u64 = 10_000_000_000;

/// Connections [`ServerConfig::connection_cap`] allows when neither the flag nor `serve` set
/// them.
pub const DEFAULT_MAX_CONNECTIONS: usize = 4096;

impl Default for ServerConfig {
    /// The defaults the attributes above state, without reading the environment.
    fn default() -> Self {
        let command = ServerConfig::augment_args(clap::Command::new("defaults"))
            .mut_args(|a| a.env(None::<&'static str>));
        let matches = command
            .try_get_matches_from(["defaults"])
            .expect("the defaults parse: every default above is a valid value");
        ServerConfig::from_arg_matches(&matches)
            .expect("the defaults parse: every default above is a valid value")
    }
}

impl ServerConfig {
    /// How long any handler may run: the longer of the two deadlines. The router's timeout
    /// layer answers 504 a second after it, so a handler that waits (`POST /v1/loadtest`)
    /// answers by itself before then.
    pub fn handler_timeout(&self) -> Duration {
        self.admin_timeout.max(self.request_timeout)
    }

    /// Whether new rigs get their metric order and mesh levels in the background.
    pub fn auto_lod(&self) -> bool {
        !self.no_auto_lod
    }

    /// The connection cap: `--max-connections`, else [`DEFAULT_MAX_CONNECTIONS`].
    pub fn connection_cap(&self) -> usize {
        self.max_connections.unwrap_or(DEFAULT_MAX_CONNECTIONS)
    }

    /// The rig memory pool's limit: `--max-rig-memory`, else [`default_rig_memory`].
    pub fn rig_memory(&self) -> u64 {
        self.max_rig_memory.unwrap_or_else(default_rig_memory)
    }

    /// The batch cost of an engine of `kind`: `--batch-cost`, else [`CPU_BATCH_COST`] or
    /// [`GPU_BATCH_COST`].
    pub fn batch_cost(&self, kind: crowdmorph_engine::BackendKind) -> u64 {
        self.batch_cost
            .unwrap_or(match kind {
                crowdmorph_engine::BackendKind::Gpu => GPU_BATCH_COST,
                crowdmorph_engine::BackendKind::Cpu => CPU_BATCH_COST,
            })
            .max(1)
    }
}

/// Default batch cost on the CPU engine: about 100 ICT FaceKit heads (3–4 ms on two cores).
pub const CPU_BATCH_COST: u64 = 200_000_000;

/// Default batch cost on a GPU: 16 times the CPU's, about 2,200 ICT FaceKit or 1,000
/// paper-scale heads a batch — one sub-batch of a large device and, at the rates issue 26
/// estimates for an H200 (1–2 M heads/s), about a millisecond of GPU time, so a 10,000-head
/// tick is a handful of engine calls. An idle engine still takes a lone request at once.
pub const GPU_BATCH_COST: u64 = 16 * CPU_BATCH_COST;

/// The default data directory: `<user data dir>/crowdmorph` (e.g.
/// `~/.local/share/crowdmorph` on Linux), else `./crowdmorph-data`.
pub fn default_data_dir() -> PathBuf {
    dirs::data_dir()
        .map(|d| d.join("crowdmorph"))
        .unwrap_or_else(|| PathBuf::from("crowdmorph-data"))
}

/// The default of [`ServerConfig::max_rig_memory`]: half the machine's memory (from
/// `/proc/meminfo`), else 8 GiB.
pub fn default_rig_memory() -> u64 {
    std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|m| {
            m.lines()
                .find_map(|l| l.strip_prefix("MemTotal:"))
                .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
        })
        .map_or(8 << 30, |kib| kib * 1024 / 2)
}

fn number(s: &str) -> Result<u64, String> {
    s.trim()
        .parse::<u64>()
        .map_err(|e| format!("{s:?} is not a whole number: {e}"))
}

/// A duration given in milliseconds.
pub fn millis(s: &str) -> Result<Duration, String> {
    number(s).map(Duration::from_millis)
}

/// A duration given in microseconds.
pub fn micros(s: &str) -> Result<Duration, String> {
    number(s).map(Duration::from_micros)
}

/// A duration given in seconds.
pub fn seconds(s: &str) -> Result<Duration, String> {
    number(s).map(Duration::from_secs)
}

fn positive(d: Duration, s: &str) -> Result<Duration, String> {
    if d.is_zero() {
        Err(format!("{s:?} must be at least 1"))
    } else {
        Ok(d)
    }
}

fn millis_positive(s: &str) -> Result<Duration, String> {
    positive(millis(s)?, s)
}

fn seconds_positive(s: &str) -> Result<Duration, String> {
    positive(seconds(s)?, s)
}

/// A clip error budget: a fraction of the diagonal in (0, 0.01].
fn clip_error(s: &str) -> Result<f32, String> {
    let e: f32 = s
        .trim()
        .parse()
        .map_err(|_| format!("{s:?} is not a number"))?;
    if e > 0.0 && e <= 0.01 {
        Ok(e)
    } else {
        Err(format!(
            "{s} must be in (0, 0.01] (a fraction of the rig's diagonal)"
        ))
    }
}

/// Default of [`SessionLimits::max_viewer_pixels`]: a full-HD image.
pub const DEFAULT_MAX_VIEWER_PIXELS: u64 = 1920 * 1080;

/// Limits of the session API: flags of `serve`, flattened into [`ServerConfig`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::Args)]
pub struct SessionLimits {
    /// Crowd sessions that may exist at once (503 too_many_sessions past it).
    #[arg(
        long = "max-sessions",
        env = "CROWDMORPH_MAX_SESSIONS",
        default_value = "64",
        value_parser = at_least_one
    )]
    pub max_sessions: usize,
    /// Heads one session may hold (413 too_many_heads past it).
    #[arg(
        id = "max_session_heads",
        long = "max-session-heads",
        env = "CROWDMORPH_MAX_SESSION_HEADS",
        default_value = "10000",
        value_parser = at_least_one
    )]
    pub max_heads: usize,
    /// Viewers one session may have at once (more are closed with 1013).
    #[arg(
        id = "max_session_viewers",
        long = "max-session-viewers",
        env = "CROWDMORPH_MAX_SESSION_VIEWERS",
        default_value = "32",
        value_parser = at_least_one
    )]
    pub max_viewers: usize,
    /// Messages per second a session viewer may send, camera and LOD updates, averaged over a
    /// second (more close it with 1008).
    #[arg(
        long = "max-viewer-messages",
        env = "CROWDMORPH_MAX_VIEWER_MESSAGES",
        default_value_t = 60,
        value_parser = clap::value_parser!(u32).range(1..)
    )]
    pub max_viewer_messages: u32,
    /// How long a viewer has to send its hello before it is closed with 1008.
    #[arg(skip = Duration::from_secs(10))]
    pub hello_timeout: Duration,
    /// Most pixels of one session viewer's image (a hello asking for more is closed with
    /// 1008; default 1920 × 1080).
    #[arg(
        long = "max-viewer-pixels",
        env = "CROWDMORPH_MAX_VIEWER_PIXELS",
        default_value_t = DEFAULT_MAX_VIEWER_PIXELS,
        value_parser = clap::value_parser!(u64).range(1..)
    )]
    pub max_viewer_pixels: u64,
    /// Live input messages per second one session takes from its producers (a POST past it
    /// gets 429 live_rate_exceeded; a socket's extra messages are shed, and a socket that
    /// keeps flooding is closed with 1008).
    #[arg(
        long = "max-live-rate",
        env = "CROWDMORPH_MAX_LIVE_RATE",
        default_value_t = 1000,
        value_parser = clap::value_parser!(u32).range(1..)
    )]
    pub max_live_rate: u32,
    /// Live input sockets one session may have open at once (more are closed with 1013).
    #[arg(
        long = "max-live-producers",
        env = "CROWDMORPH_MAX_LIVE_PRODUCERS",
        default_value = "16",
        value_parser = at_least_one
    )]
    pub max_live_producers: usize,
    /// How long a live producer's socket may send nothing before it is closed with 1001 (a
    /// dead producer does not hold a slot for ever).
    #[arg(skip = Duration::from_secs(30))]
    pub live_idle_timeout: Duration,
}

impl Default for SessionLimits {
    fn default() -> Self {
        ServerConfig::default().sessions
    }
}

/// A count of at least one.
pub(crate) fn at_least_one(s: &str) -> Result<usize, String> {
    match number(s)? {
        0 => Err(format!("{s:?} must be at least 1")),
        n => usize::try_from(n).map_err(|e| e.to_string()),
    }
}

/// A share in [0, 1].
pub fn share(s: &str) -> Result<f64, String> {
    match s.trim().parse::<f64>() {
        Ok(v) if (0.0..=1.0).contains(&v) => Ok(v),
        _ => Err(format!("{s:?} is not a number in [0, 1]")),
    }
}

/// A store URL that is not empty (an empty one set in the environment would silently mean
/// "no shared store").
fn store_url(s: &str) -> Result<String, String> {
    if s.trim().is_empty() {
        Err("the store URL is empty: a path, file:///dir or s3://bucket/prefix".into())
    } else {
        Ok(s.trim().to_string())
    }
}

/// A token that is not empty (an empty one set in the environment leaves the server open).
fn non_empty(s: &str) -> Result<String, String> {
    if s.is_empty() {
        Err("the admin token is empty".into())
    } else {
        Ok(s.to_string())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_batch_cost_defaults_to_the_engines_and_the_flag_wins() {
        use crowdmorph_engine::BackendKind;
        let mut c = ServerConfig::default();
        assert_eq!(c.batch_cost, None);
        assert_eq!(c.batch_cost(BackendKind::Cpu), CPU_BATCH_COST);
        assert_eq!(c.batch_cost(BackendKind::Gpu), GPU_BATCH_COST);
        c.batch_cost = Some(5);
        assert_eq!(c.batch_cost(BackendKind::Gpu), 5);
        c.batch_cost = Some(0);
        assert_eq!(c.batch_cost(BackendKind::Cpu), 1, "a batch always closes");
    }

    #[test]
    fn the_defaults_are_the_flags_defaults_and_every_flag_says_what_it_does() {
        let d = ServerConfig::default();
        assert_eq!(d.request_timeout, Duration::from_secs(10));
        assert_eq!(d.batch_delay, Duration::from_micros(1000));
        assert_eq!(d.render_work, Duration::from_secs(4));
        assert_eq!(d.render_pixels, DEFAULT_RENDER_PIXELS);
        assert!(d.auto_lod(), "--no-auto-lod is off by default");
        assert_eq!(d.sessions, SessionLimits::default());
        assert_eq!(
            (d.data_dir, d.admin_token, d.max_connections),
            (None, None, None)
        );
        let command = ServerConfig::augment_args(clap::Command::new("serve"));
        for a in command.get_arguments() {
            let help = a.get_help().map(|h| h.to_string()).unwrap_or_default();
            assert!(help.len() > 10, "--{:?} has no help text", a.get_long());
            assert!(
                a.get_env().is_some(),
                "--{:?} has no environment variable",
                a.get_long()
            );
        }
    }

    #[test]
    fn flags_parse_into_the_config() {
        let command = ServerConfig::augment_args(clap::Command::new("serve"))
            .mut_args(|a| a.env(None::<&'static str>));
        let m = command
            .try_get_matches_from([
                "serve",
                "--request-timeout-ms",
                "250",
                "--no-auto-lod",
                "--max-session-heads",
                "7",
                "--cors-origin",
                "a,b",
            ])
            .expect("flags");
        let c = ServerConfig::from_arg_matches(&m).expect("config");
        assert_eq!(c.request_timeout, Duration::from_millis(250));
        assert!(!c.auto_lod());
        assert_eq!(c.sessions.max_heads, 7);
        assert_eq!(c.cors_origins, vec!["a", "b"]);
        // A switch (its environment variable, CROWDMORPH_NO_AUTO_LOD=true, is read as the
        // switch: the real binary's tests start servers with it).
        let command = ServerConfig::augment_args(clap::Command::new("serve"));
        let m = command
            .try_get_matches_from(["serve", "--no-auto-lod"])
            .expect("flag");
        assert!(
            !ServerConfig::from_arg_matches(&m)
                .expect("config")
                .auto_lod()
        );
        for bad in [
            ["serve", "--viewer-render-share", "1.5"],
            ["serve", "--header-timeout-ms", "0"],
            ["serve", "--max-connections", "0"],
            ["serve", "--compress-clips", "0"],
            ["serve", "--compress-clips", "NaN"],
        ] {
            let command = ServerConfig::augment_args(clap::Command::new("serve"));
            assert!(command.try_get_matches_from(bad).is_err(), "{bad:?}");
        }
    }
}
