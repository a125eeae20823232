//! Server configuration: every limit and timeout in one place, with the defaults `serve` uses.

use std::path::PathBuf;
use std::time::Duration;

use crate::engine::BackendChoice;
pub use crate::render::crowd::RenderBackend;

/// Everything [`super::run`] needs to know besides the listener.
#[derive(Clone, Debug)]
pub struct ServerConfig {
    /// Where rigs and clips are persisted; `None` keeps them in memory only (tests).
    pub data_dir: Option<PathBuf>,
    /// Engine to use.
    pub backend: BackendChoice,
    /// Bearer token required for uploads and deletes; `None` leaves them open.
    pub admin_token: Option<String>,
    /// Largest rig or clip upload body.
    pub max_upload_bytes: usize,
    /// Largest body of any other request.
    pub max_request_bytes: usize,
    /// Most heads in one crowd request.
    pub max_heads: usize,
    /// Most host memory one upload (rig or clips) or LOD build may hold at once: what its
    /// file's headers say it will cost (decoded arrays, baked clip tables, engine layouts,
    /// the stored record) is checked against this before any work, then every allocation is
    /// charged as it happens. Past it, 413 (`--max-upload-memory`).
    pub max_upload_memory: u64,
    /// Most host memory all rigs together may hold, with the uploads and LOD builds in
    /// progress; work that would go past it gets 503 (`--max-rig-memory`).
    pub max_rig_memory: u64,
    /// Most crowd requests waiting for the batcher at once; more get 503.
    pub queue_requests: usize,
    /// Most output bytes that admitted crowd requests may hold at once (queued, computing or
    /// being sent); a request that would exceed it gets 503, one larger than it gets 413.
    pub queue_memory_bytes: usize,
    /// A batch closes when the cost (vertices × active shapes, summed over its unique jobs)
    /// reaches this.
    pub batch_cost: u64,
    /// ... or when its oldest job has waited this long (while the engine is busy: an idle
    /// engine takes work at once, unless `batch_hold_when_idle`).
    pub batch_delay: Duration,
    /// Hold work for `batch_delay` even when the engine is idle (the batcher's behaviour before
    /// idle dispatch): more coalescing at low load, the delay added to every lone request.
    pub batch_hold_when_idle: bool,
    /// Deadline of a crowd request, from arrival to its response being ready; past it, 504.
    pub request_timeout: Duration,
    /// Deadline of any other request (uploads included); past it, 504.
    pub admin_timeout: Duration,
    /// Requests handled at once; more are shed with 503.
    pub max_concurrency: usize,
    /// Most connections open at once. Past it, the connection idle the longest (no request in
    /// progress) is closed to admit the new one; when every connection has a request in
    /// progress, the new one is answered 503 `too_many_connections` and closed. Keep it below
    /// the open-file limit: `crowdmorph serve` derives its default from that limit.
    pub max_connections: usize,
    /// A request's headers must arrive complete within this long of the connection being
    /// accepted, or of the request's first byte on a kept-alive connection; else the
    /// connection is closed. Bytes trickling in do not extend it.
    pub header_timeout: Duration,
    /// A kept-alive connection with no request in progress is closed after this long without
    /// the first byte of a new request.
    pub idle_timeout: Duration,
    /// Origins allowed by CORS (`*` for any); empty disables CORS headers.
    pub cors_origins: Vec<String>,
    /// Order each new rig's blendshapes by the five importance metrics and build its 50/25/10 %
    /// mesh levels in the background after registration (and at start for stored rigs that
    /// still have the import's quick order).
    pub auto_lod: bool,
    /// Pixels that renders in flight may hold together (`POST /v1/crowd/render`): a W × H
    /// image takes W × H of them until its response is built. One larger than this gets 413,
    /// one that does not fit now 503 `render_busy` (`--render-pixels`).
    pub render_pixels: u64,
    /// Estimated time of the renders in flight together (blending, drawing and encoding, from
    /// what each draws: [`crate::render::cost`]); a render estimated past this gets 413
    /// `render_too_costly`, one that does not fit now 503 `render_busy` (`--render-work-ms`).
    /// One admitted past its request deadline gets 504 and stops at its next stage.
    pub render_work: Duration,
    /// Share (0 to 1) of the pixel and render work budgets that session viewers' frames may
    /// hold together, so HTTP renders keep being served while viewers stream
    /// (`--viewer-render-share`).
    pub viewer_render_share: f64,
    /// Which adapter draws rendered frames (`--render-backend`).
    pub render_backend: RenderBackend,
    /// Bytes of GPU buffers and textures whose size an input decides (resident rigs, batch
    /// buffers, render targets) each device may hold at once (`--max-gpu-memory`; `None`:
    /// [`crate::engine::gpu::default_gpu_memory`] of the device's limits).
    pub gpu_memory: Option<u64>,
    /// Limits of crowd sessions.
    pub sessions: super::sessions::SessionLimits,
    /// Longest `POST /v1/loadtest` (warm-up and measured window together); zero disables the
    /// endpoint (`--loadtest-max-duration-s`).
    pub loadtest_max_duration: Duration,
    /// Highest request rate a load test may ask for, requests per second
    /// (`--loadtest-max-rate`).
    pub loadtest_max_rate: f64,
    /// Most lanes (requests in flight) of a load test; never more than half of
    /// `queue_requests` (`--loadtest-max-concurrency`).
    pub loadtest_max_concurrency: usize,
}

/// Default of [`ServerConfig::render_pixels`]: 64 Mpixels (64 × 2^20), four 4096 × 4096
/// images or 72 of 1280 × 720. A pixel in flight costs about 48 bytes (4× MSAA colour and
/// depth, the resolved and staging copies on the device — host memory on lavapipe — the
/// pixels read back and the encoded image), so the default bounds renders to about 3 GiB.
pub const DEFAULT_RENDER_PIXELS: u64 = 64 << 20;

/// Default of [`ServerConfig::render_work`]: 4 s of estimated rendering in flight. On two
/// cores of lavapipe that is a few full-HD frames of a hundred heads at once; a render that
/// waits behind all of it still answers well within the default 10 s deadline.
pub const DEFAULT_RENDER_WORK: Duration = Duration::from_secs(4);

/// Default of [`ServerConfig::viewer_render_share`]: viewers together hold at most half.
pub const DEFAULT_VIEWER_RENDER_SHARE: f64 = 0.5;

impl Default for ServerConfig {
    fn default() -> Self {
        ServerConfig {
            data_dir: None,
            backend: BackendChoice::Auto,
            admin_token: None,
            max_upload_bytes: 256 << 20,
            max_request_bytes: 16 << 20,
            max_heads: 100_000,
            max_upload_memory: 1 << 30,
            max_rig_memory: default_rig_memory(),
            queue_requests: 1024,
            queue_memory_bytes: 2 << 30,
            batch_cost: 200_000_000,
            batch_delay: Duration::from_micros(1000),
            batch_hold_when_idle: false,
            request_timeout: Duration::from_secs(10),
            admin_timeout: Duration::from_secs(300),
            max_concurrency: 2048,
            max_connections: 4096,
            header_timeout: Duration::from_secs(10),
            idle_timeout: Duration::from_secs(60),
            cors_origins: Vec::new(),
            auto_lod: true,
            render_pixels: DEFAULT_RENDER_PIXELS,
            render_work: DEFAULT_RENDER_WORK,
            viewer_render_share: DEFAULT_VIEWER_RENDER_SHARE,
            render_backend: RenderBackend::Auto,
            gpu_memory: None,
            sessions: super::sessions::SessionLimits::default(),
            loadtest_max_duration: Duration::from_secs(60),
            loadtest_max_rate: 10_000.0,
            loadtest_max_concurrency: 64,
        }
    }
}

impl ServerConfig {
    /// How long any handler may run: the longer of the two deadlines. The router's timeout
    /// layer answers 504 a second after it, so a handler that waits (`POST /v1/loadtest`)
    /// answers by itself before then.
    pub fn handler_timeout(&self) -> Duration {
        self.admin_timeout.max(self.request_timeout)
    }
}

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
