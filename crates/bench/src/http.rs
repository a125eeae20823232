//! `crowdmorph bench http`: crowd frames over loopback HTTP against the same work done
//! in-process, plus latency at half the saturated load and bytes per head of each format.
//!
//! Workload: every request is a crowd of `heads` heads over `unique` distinct frames of one
//! rig at LOD 0. A deterministic random clip of 1,024 frames (all weights active) is added to
//! the rig first, and request `i` plays frames `(i × unique + h mod unique) mod 1024`, so that
//! concurrent requests rarely share jobs: the server gets no help from cross-request
//! coalescing that the in-process loop would not get.
//!
//! - In-process: plan + `Engine::evaluate` in a loop on this thread (the engine itself uses
//!   every core through rayon), heads per second.
//! - Saturation: `clients` connections send requests back to back (bincode both ways; the
//!   client reads each body whole but does not decode it, so that it steals as little CPU as
//!   possible from the server on the same machine), heads per second.
//! - JSON: the same crowds and connections with JSON requests and responses, right after.
//! - The Python peer (`--python-peer`): the dense aiohttp + numpy server of
//!   [`super::peers`], checked once against crowdmorph's vertices and then driven by the same
//!   client loop with the same bincode bodies, while crowdmorph idles.
//! - Half load: requests arrive at a fixed rate of half the saturated request rate (open
//!   loop), latency percentiles from an HDR histogram.
//! - Ceiling: what any server could reach on this machine, from CPU costs measured in the
//!   same run. The copies into and out of a loopback socket cost about as much CPU as the
//!   blend itself, so bandwidth is not the limit: CPU is. The ceiling is
//!   `cores / (socket CPU per response + engine CPU per request) × heads per request`, where
//!   the socket CPU is measured by moving response-sized messages through plain loopback TCP
//!   between writer and reader threads (process CPU time from `getrusage`), and the engine CPU
//!   per request comes from the in-process run. The client's own decoding is not counted, as
//!   the saturation client does not decode.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use bytes::Bytes;
use crowdmorph_client::{Client, Compression, Encoding};
use crowdmorph_proto::{CrowdFrameRequest, Format, Head, OutputOptions};
use hdrhistogram::Histogram;
use serde::Serialize;

use super::server::BenchServer;
use crowdmorph_core::plan::{JobKey, Plan};
use crowdmorph_core::rig::Rig;
use crowdmorph_engine::{BlendJob, Engine, OutputSpec};
use crowdmorph_load::http::HttpTarget;
use crowdmorph_load::{self as load, Live, LoadReport, Percentiles, RunOptions, WireEncoding};
use crowdmorph_server::ServerConfig;

/// Frames of the benchmark clip.
const CLIP_FRAMES: usize = 1024;
/// Name of the benchmark clip.
const CLIP: &str = "bench-random";

/// What to measure (also `crowdmorph bench http`'s flags).
#[derive(Clone, Debug, clap::Args)]
pub struct HttpBenchOptions {
    /// Heads per request.
    #[arg(long, default_value_t = 100)]
    pub heads: usize,
    /// Unique jobs per request.
    #[arg(long, default_value_t = 100)]
    pub unique: usize,
    /// Format of the throughput runs.
    #[arg(long, default_value = "f32", value_parser = super::format_arg())]
    pub format: Format,
    /// Concurrent connections at saturation.
    #[arg(long, default_value_t = 4)]
    pub clients: usize,
    /// Seconds per measurement.
    #[arg(long, default_value_t = 3.0)]
    pub seconds: f64,
    /// Engine of the server and of the in-process comparison (the same one for both).
    #[arg(long, default_value = "auto")]
    pub backend: crowdmorph_engine::BackendChoice,
    /// Also measure the dense Python server (aiohttp + numpy,
    /// clients/python/bench/dense_server.py) on the same requests, with this Python
    /// (default /usr/bin/python3).
    #[arg(long, value_name = "PYTHON", num_args = 0..=1, default_missing_value = "/usr/bin/python3")]
    pub python_peer: Option<std::path::PathBuf>,
    /// Where the Python peer runs numpy: off its event loop (thread) or on it (inline).
    #[arg(long = "python-peer-compute", default_value = "thread", value_parser = ["thread", "inline"])]
    pub python_compute: String,
    /// The server's `--max-gpu-memory` (`None`: the default), also the in-process engine's
    /// (the CLI's `--max-gpu-memory`).
    #[arg(skip)]
    pub gpu_memory: Option<u64>,
    /// The server's `--gpu-deltas`, also the in-process engine's (the CLI's `--gpu-deltas`).
    #[arg(skip)]
    pub gpu_deltas: crowdmorph_engine::gpu::DeltaFormat,
    /// Upload these clips first (`.csv`/`.json` files in a folder, named by file stem) and
    /// play them (the link benchmark plays these instead of the rig's own).
    #[arg(long, value_name = "DIR")]
    pub clips: Option<std::path::PathBuf>,
    /// Instead: measure each encoding on loopback and over shaped links at these rates
    /// (comma-separated, e.g. 1gbit,100mbit; a network namespace and a tbf-shaped veth
    /// pair each, removed at the end; needs root and iproute2, else only loopback).
    #[arg(long = "link", value_delimiter = ',', value_name = "RATES")]
    pub links: Vec<super::link::LinkSpec>,
}

impl Default for HttpBenchOptions {
    fn default() -> Self {
        HttpBenchOptions {
            heads: 100,
            unique: 100,
            format: Format::F32,
            clients: 4,
            seconds: 3.0,
            backend: crowdmorph_engine::BackendChoice::Auto,
            python_peer: None,
            python_compute: "thread".to_string(),
            gpu_memory: None,
            gpu_deltas: Default::default(),
            clips: None,
            links: Vec::new(),
        }
    }
}

/// Bytes on the wire for one format.
#[derive(Debug, Serialize)]
pub struct FormatSize {
    /// Format.
    pub format: String,
    /// Normals included.
    pub normals: bool,
    /// bincode response bytes per head.
    pub bincode_bytes_per_head: f64,
    /// JSON response bytes per head.
    pub json_bytes_per_head: f64,
    /// Raw vertex payload bytes per unique head (`vertices × 3 × component bytes`, doubled
    /// with normals).
    pub payload_bytes_per_unique_head: usize,
    /// bincode bytes per head as the server sends them with `Accept-Encoding: zstd`.
    pub zstd_bytes_per_head: f64,
    /// ... and with `Accept-Encoding: gzip`.
    pub gzip_bytes_per_head: f64,
    /// CPU of compressing one such response as the server does (zstd level 1), median ms on
    /// this thread.
    pub zstd_ms: f64,
    /// ... with gzip level 1.
    pub gzip_ms: f64,
}

/// Median ms of compressing `body` as the server's compression layer does.
fn compress_ms(body: &[u8], zstd: bool) -> f64 {
    use std::io::Write;
    let once = || {
        if zstd {
            let _ = std::hint::black_box(zstd::bulk::compress(body, 1));
        } else {
            let mut e = flate2::write::GzEncoder::new(
                Vec::with_capacity(body.len() / 2),
                flate2::Compression::fast(),
            );
            let _ = e.write_all(body);
            let _ = std::hint::black_box(e.finish());
        }
    };
    super::sample::sample(0.3, 5, once).median()
}

/// The benchmark result.
#[derive(Debug, Serialize)]
pub struct HttpBenchReport {
    /// The engine both sides used.
    pub backend: crowdmorph_engine::BackendInfo,
    /// Rig name.
    pub rig: String,
    /// Vertices per head.
    pub vertices: usize,
    /// Targets.
    pub targets: usize,
    /// Heads per request.
    pub heads: usize,
    /// Unique jobs per request.
    pub unique: usize,
    /// Format of the throughput runs.
    pub format: String,
    /// Connections at saturation.
    pub clients: usize,
    /// In-process heads per second (plan + engine evaluate).
    pub inprocess_heads_per_s: f64,
    /// In-process milliseconds per crowd.
    pub inprocess_ms_per_crowd: f64,
    /// Heads per second over loopback HTTP at saturation.
    pub http_heads_per_s: f64,
    /// `http_heads_per_s / inprocess_heads_per_s`.
    pub http_fraction_of_inprocess: f64,
    /// Raw loopback TCP throughput over as many connections as the saturation run, measured in
    /// the same run (large writes, no HTTP): the most bytes per second any server on this
    /// machine can hand to its clients here.
    pub loopback_bytes_per_s: f64,
    /// Bincode response bytes per head of the throughput runs.
    pub response_bytes_per_head: f64,
    /// `loopback_bytes_per_s / response_bytes_per_head`: the loopback roofline in heads/s.
    pub loopback_roofline_heads_per_s: f64,
    /// `http_heads_per_s / loopback_roofline_heads_per_s`.
    pub http_fraction_of_loopback: f64,
    /// Logical cores of this machine (the CPU the server and its clients share).
    pub cores: usize,
    /// Process CPU seconds (user + system) the in-process run spent per crowd request.
    pub engine_cpu_s_per_request: f64,
    /// Process CPU seconds per byte moved through plain loopback TCP (writer and reader
    /// threads, response-sized messages, as many connections as the saturation run).
    pub socket_cpu_s_per_byte: f64,
    /// `socket_cpu_s_per_byte × response bytes per request`: the copies' CPU per response.
    pub socket_cpu_s_per_response: f64,
    /// Process CPU seconds per request during the HTTP saturation run (server and client).
    pub http_cpu_s_per_request: f64,
    /// `cores / (socket_cpu_s_per_response + engine_cpu_s_per_request) × heads`: the most
    /// heads per second any server can hand to clients on this machine for this format.
    pub ceiling_heads_per_s: f64,
    /// `http_heads_per_s / ceiling_heads_per_s` (goal ≥ 0.85). This assumes the run had every
    /// core to itself: on a machine shared with other work it understates the server.
    pub http_fraction_of_ceiling: f64,
    /// `(socket_cpu_s_per_response + engine_cpu_s_per_request) / http_cpu_s_per_request`: the
    /// same comparison in CPU per request, which other load on the machine barely moves.
    pub http_cpu_fraction_of_ceiling: f64,
    /// Requests that failed during the saturation run.
    pub saturation_errors: u64,
    /// Heads per second at saturation with JSON requests and responses (same crowds, same
    /// connections), measured right after the bincode run.
    pub json_heads_per_s: f64,
    /// `json_heads_per_s / http_heads_per_s` (goal ≥ 0.5).
    pub json_over_bincode: f64,
    /// JSON response bytes per head.
    pub json_bytes_per_head: f64,
    /// Requests that failed during the JSON run.
    pub json_errors: u64,
    /// The dense Python peer, when asked for (`--python-peer`).
    pub python: Option<PythonPeerReport>,
    /// Latency percentiles at saturation, ms.
    pub saturation_p50_ms: f64,
    /// 99th percentile at saturation, ms.
    pub saturation_p99_ms: f64,
    /// Request rate of the half-load run.
    pub half_load_requests_per_s: f64,
    /// Median latency at half load, ms.
    pub half_load_p50_ms: f64,
    /// 99th percentile at half load, ms.
    pub half_load_p99_ms: f64,
    /// `p99 / p50` at half load (goal ≤ 3).
    pub half_load_p99_over_p50: f64,
    /// Requests that failed during the half-load run.
    pub half_load_errors: u64,
    /// Mean jobs per batch the server formed over the whole run.
    pub mean_batch_jobs: f64,
    /// Bytes per head of each format.
    pub sizes: Vec<FormatSize>,
}

/// The dense Python peer (aiohttp + numpy) driven like crowdmorph.
#[derive(Debug, Serialize)]
pub struct PythonPeerReport {
    /// The interpreter.
    pub python: String,
    /// numpy's version.
    pub numpy: String,
    /// The BLAS library numpy loaded.
    pub blas: String,
    /// Where the peer ran numpy (`thread`: off the event loop; `inline`).
    pub compute: String,
    /// Largest position difference from crowdmorph's response to the same request.
    pub max_error: f64,
    /// The tolerance it was checked against (1e-5 of the bounding-box diagonal).
    pub tolerance: f64,
    /// Heads per second at saturation (same client loop, bodies and connections).
    pub heads_per_s: f64,
    /// `http_heads_per_s / heads_per_s` (goal ≥ 3).
    pub crowdmorph_over_python: f64,
    /// `ceiling_heads_per_s / heads_per_s`: the most any server could be over the peer on this
    /// machine, from the same run's ceiling. Below 3, the 3× goal is out of every server's
    /// reach here (both pay the same socket copies per response).
    pub ceiling_over_python: f64,
    /// Median latency at saturation, ms.
    pub p50_ms: f64,
    /// 99th percentile at saturation, ms.
    pub p99_ms: f64,
    /// Requests that failed.
    pub errors: u64,
}

/// One closed-loop saturation run.
struct Saturation {
    heads_per_s: f64,
    hist: Histogram<u64>,
    errors: u64,
    /// Process CPU seconds over the measured window.
    cpu_s: f64,
    requests: u64,
    /// Response body bytes as they came over the wire, of the counted requests.
    wire_bytes: u64,
}

/// `clients` connections send `bodies` (cycled) back to back for `seconds` after a 0.5 s
/// warm-up; each response is read whole but not decoded, so that the client steals as little
/// CPU as possible from the server on the same machine. The same loop drives crowdmorph in
/// either encoding and the Python peer.
async fn saturate(
    client: &Client,
    bodies: &Arc<Vec<Bytes>>,
    enc: Encoding,
    heads: usize,
    clients: usize,
    seconds: f64,
) -> Result<Saturation> {
    let counter = Arc::new(AtomicU64::new(0));
    let wire = Arc::new(AtomicU64::new(0));
    let errors = Arc::new(AtomicU64::new(0));
    let warm_until = Instant::now() + Duration::from_millis(500);
    let end = warm_until + Duration::from_secs_f64(seconds);
    let mut tasks = Vec::new();
    for c in 0..clients.max(1) {
        let client = client.clone();
        let bodies = bodies.clone();
        let counter = counter.clone();
        let wire = wire.clone();
        let errors = errors.clone();
        let heads = heads as u64;
        tasks.push(tokio::spawn(async move {
            let mut hist = Histogram::<u64>::new_with_bounds(1, 600_000_000, 3)?;
            let mut i = c;
            while Instant::now() < end {
                let t = Instant::now();
                let body = bodies[i % bodies.len()].clone();
                i += 7;
                match client.crowd_frame_drain(body, enc).await {
                    Ok((200, len)) => {
                        if t >= warm_until && Instant::now() <= end {
                            counter.fetch_add(heads, Ordering::Relaxed);
                            wire.fetch_add(len as u64, Ordering::Relaxed);
                            hist.record(t.elapsed().as_micros() as u64)?;
                        }
                    }
                    _ => {
                        errors.fetch_add(1, Ordering::Relaxed);
                    }
                }
            }
            anyhow::Ok(hist)
        }));
    }
    // Process CPU over the measured window (after the warm-up; the few requests in flight at
    // its edges make this approximate).
    tokio::time::sleep_until(tokio::time::Instant::from_std(warm_until)).await;
    let cpu0 = process_cpu_s();
    let mut hist = Histogram::<u64>::new_with_bounds(1, 600_000_000, 3)?;
    for t in tasks {
        hist.add(t.await??)?;
    }
    let cpu_s = process_cpu_s() - cpu0;
    let counted = counter.load(Ordering::Relaxed);
    Ok(Saturation {
        heads_per_s: counted as f64 / seconds,
        hist,
        errors: errors.load(Ordering::Relaxed),
        cpu_s,
        requests: (counted / heads.max(1) as u64).max(1),
        wire_bytes: wire.load(Ordering::Relaxed),
    })
}

/// Starts the dense Python peer on `rig` (served as `rig_id`), checks its response to one
/// crowd against crowdmorph's, and drives it with the same bodies and connections.
async fn measure_python_peer(
    python: &std::path::Path,
    opt: &HttpBenchOptions,
    rig: &Rig,
    rig_id: &str,
    ours: &Client,
    bodies: &Arc<Vec<Bytes>>,
    crowdmorph_heads_per_s: f64,
) -> Result<PythonPeerReport> {
    use super::peers as pypeer;
    if opt.format == Format::Q16 {
        bail!(
            "the Python peer serves f32 and f16 only: run --python-peer with --format f32 or f16"
        );
    }
    // Removed when this returns, whichever way; the peer is killed before it (declared after).
    let dir = pypeer::temp_dir("crowdmorph-pypeer-")?;
    let scripts = pypeer::write_scripts(&dir.path().join("py"))?;
    let rig_dir = dir.path().join("rig");
    pypeer::export_rig(rig, rig_id, &rig_dir)?;
    let peer = pypeer::PythonPeer::start(python, &scripts, &rig_dir, &opt.python_compute)?;
    let client = Client::new(peer.url());
    let req = crowd(opt, rig_id, 3, opt.format, false);
    let (a, _) = ours.crowd_frame(&req, Encoding::Bincode).await?;
    let (b, _) = client
        .crowd_frame(&req, Encoding::Bincode)
        .await
        .context("the Python peer's response")?;
    let tolerance = 1e-5 * rig.bbox().diagonal();
    let max_error = pypeer::compare_responses(&a, &b, tolerance)
        .context("the Python peer's response differs from crowdmorph's")?;
    let sat = saturate(
        &client,
        bodies,
        Encoding::Bincode,
        opt.heads,
        opt.clients,
        opt.seconds,
    )
    .await?;
    let (numpy, blas) = (peer.numpy.clone(), peer.blas.clone());
    drop(peer);
    Ok(PythonPeerReport {
        python: python.display().to_string(),
        numpy,
        blas,
        compute: opt.python_compute.clone(),
        max_error: f64::from(max_error),
        tolerance: f64::from(tolerance),
        heads_per_s: sat.heads_per_s,
        crowdmorph_over_python: crowdmorph_heads_per_s / sat.heads_per_s.max(1e-9),
        // Filled in by the caller, which has the ceiling.
        ceiling_over_python: 0.0,
        p50_ms: Percentiles::of(&sat.hist).p50,
        p99_ms: Percentiles::of(&sat.hist).p99,
        errors: sat.errors,
    })
}

/// Deterministic all-active weights in [0.05, 1): a JSON clip for the rig.
fn bench_clip_json(rig: &Rig) -> String {
    let mut state = 0x5EED_u64;
    let mut next = || {
        state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        0.05 + 0.95 * ((z >> 40) as f64 / (1u64 << 24) as f64)
    };
    // By name: a name with several weight channels is one column, which drives them all.
    let names = rig.target_names();
    let frames: Vec<Vec<f64>> = (0..CLIP_FRAMES)
        .map(|_| {
            (0..names.len())
                .map(|_| (next() * 1e4).round() / 1e4)
                .collect()
        })
        .collect();
    serde_json::json!({ "fps": 30, "targets": names, "frames": frames }).to_string()
}

fn crowd(
    opt: &HttpBenchOptions,
    rig_id: &str,
    i: u64,
    format: Format,
    normals: bool,
) -> CrowdFrameRequest {
    let base = i as usize * opt.unique;
    CrowdFrameRequest {
        heads: (0..opt.heads)
            .map(|h| Head {
                head: h as u64,
                rig: rig_id.to_string(),
                clip: CLIP.to_string(),
                frame: ((base + h % opt.unique) % CLIP_FRAMES) as i64,
                lod: 0,
                ..Default::default()
            })
            .collect(),
        output: OutputOptions { normals, format },
        wrap: true,
    }
}

/// Bytes per second `connections` loopback TCP connections carry together with large writes
/// and reads, in this process's runtime (as the server and client share it): the roofline for
/// moving response bytes from a server to its clients on this machine.
async fn loopback_throughput(connections: usize, seconds: f64) -> Result<f64> {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
    let addr = listener.local_addr()?;
    super::link::tcp_throughput(listener, addr, connections, seconds).await
}

/// CPU seconds (user + system) this process has used so far, all threads together.
fn process_cpu_s() -> f64 {
    super::server::process_cpu().as_secs_f64()
}

/// CPU seconds per byte this process spends moving `message` byte messages through
/// `connections` plain loopback TCP connections for about `seconds`: one writer and one
/// reader thread per connection, each message written whole and read whole into a reused
/// buffer, as a server writes a response and a client reads it. Returns
/// `(cpu seconds per byte, bytes per wall second)`.
fn socket_cpu_per_byte(connections: usize, message: usize, seconds: f64) -> Result<(f64, f64)> {
    use std::io::{Read, Write};
    let listener = std::net::TcpListener::bind("127.0.0.1:0")?;
    let addr = listener.local_addr()?;
    let n = connections.max(1);
    let message = message.max(1);
    let deadline = Instant::now() + Duration::from_secs_f64(seconds);
    let cpu0 = process_cpu_s();
    let start = Instant::now();
    let total = std::thread::scope(|scope| -> Result<usize> {
        let mut readers = Vec::new();
        let mut writers = Vec::new();
        for _ in 0..n {
            let mut rx = std::net::TcpStream::connect(addr)?;
            let (mut tx, _) = listener.accept()?;
            tx.set_nodelay(true)?;
            writers.push(scope.spawn(move || -> Result<()> {
                let chunk = vec![7u8; message];
                // At least one message, even when setting up the connections took the whole
                // (short) window.
                loop {
                    tx.write_all(&chunk)?;
                    if Instant::now() >= deadline {
                        return Ok(());
                    }
                }
            }));
            readers.push(scope.spawn(move || -> Result<usize> {
                let mut buf = vec![0u8; message];
                let mut total = 0usize;
                loop {
                    let got = rx.read(&mut buf)?;
                    if got == 0 {
                        return Ok(total);
                    }
                    total += got;
                }
            }));
        }
        for w in writers {
            w.join()
                .map_err(|_| anyhow::anyhow!("socket writer panicked"))??;
        }
        let mut total = 0usize;
        for r in readers {
            total += r
                .join()
                .map_err(|_| anyhow::anyhow!("socket reader panicked"))??;
        }
        Ok(total)
    })?;
    let wall = start.elapsed().as_secs_f64();
    let cpu = process_cpu_s() - cpu0;
    if total == 0 {
        bail!("no bytes moved through the loopback socket");
    }
    Ok((cpu / total as f64, total as f64 / wall))
}

/// Open-loop load at `rate` requests per second over as many connections as the saturation
/// run used, through [`crowdmorph_load::run`]: `bodies` in turn, bincode, for `opt.seconds` after
/// a 300 ms warm-up.
async fn half_load(
    addr: std::net::SocketAddr,
    bodies: &[Bytes],
    rate: f64,
    opt: &HttpBenchOptions,
) -> Result<LoadReport> {
    let target = HttpTarget::new(
        &format!("http://{addr}"),
        bodies.to_vec(),
        WireEncoding::Bincode,
    )?;
    let lanes = target.lanes(opt.clients).await?;
    let live = Live::new(RunOptions {
        rate,
        duration: Duration::from_secs_f64(opt.seconds),
        warmup: Duration::from_millis(300),
        grace: Duration::from_secs(10),
        heads_per_request: opt.heads as u64,
    });
    Ok(load::run(lanes, &live).await?)
}

/// Runs the benchmark: `rig_bytes` is a GLB/glTF to upload, or `None` for the embedded head.
pub fn bench_http(rig_bytes: Option<Vec<u8>>, opt: &HttpBenchOptions) -> Result<HttpBenchReport> {
    if opt.unique == 0 || opt.heads < opt.unique || opt.unique > CLIP_FRAMES {
        bail!("need heads >= unique >= 1 and unique <= {CLIP_FRAMES}");
    }
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("starting the tokio runtime")?;
    runtime.block_on(run(rig_bytes, opt))
}

/// The server of both HTTP benchmarks.
fn bench_config(opt: &HttpBenchOptions) -> ServerConfig {
    ServerConfig {
        max_heads: opt.heads.max(1000),
        request_timeout: Duration::from_secs(60),
        backend: opt.backend,
        gpu_memory: opt.gpu_memory,
        gpu_deltas: opt.gpu_deltas,
        // The background LOD job would score the embedded head (seconds of CPU) during the
        // measurement, on the same cores.
        no_auto_lod: true,
        // Frames only: no rendering device to open.
        render_backend: crowdmorph_server::RenderBackend::Off,
        ..ServerConfig::default()
    }
}

async fn run(rig_bytes: Option<Vec<u8>>, opt: &HttpBenchOptions) -> Result<HttpBenchReport> {
    let BenchServer {
        state,
        addr,
        client,
        rig_id,
        stop_tx,
        server,
    } = BenchServer::start(bench_config(opt), rig_bytes).await?;
    if let Some(dir) = &opt.clips {
        super::server::upload_clips(&client, &rig_id, dir).await?;
    }
    let entry = state
        .registry
        .get(&rig_id)
        .context("the rig is not registered")?;
    let clip = bench_clip_json(entry.rig());
    client
        .upload_clip(
            &rig_id,
            &format!("name={CLIP}"),
            "application/json",
            Bytes::from(clip),
        )
        .await
        .context("uploading the benchmark clip")?;
    let entry = state
        .registry
        .get(&rig_id)
        .context("the rig is not registered")?;
    let rig = entry.rig().clone();
    let clip_index = rig.clip_index(CLIP).context("benchmark clip missing")? as u32;

    // Bytes per head of every format, and a check that bincode decodes.
    let mut sizes = Vec::new();
    for normals in [false, true] {
        for format in [Format::F32, Format::F16, Format::Q16, Format::Q16R] {
            let req = crowd(opt, &rig_id, 0, format, normals);
            let (resp, b) = client.crowd_frame(&req, Encoding::Bincode).await?;
            if resp.heads.len() != opt.heads || resp.buffers.len() != opt.unique {
                bail!("unexpected response shape");
            }
            let (_, j) = client.crowd_frame(&req, Encoding::Json).await?;
            let body = Client::encode(&req, Encoding::Bincode)?;
            let plain = client
                .crowd_frame_raw(body.clone(), Encoding::Bincode)
                .await?;
            let mut wire = [0f64; 2];
            for (i, c) in [Compression::Zstd, Compression::Gzip]
                .into_iter()
                .enumerate()
            {
                let r = Client::new(client.base())
                    .with_compression(c)
                    .crowd_frame_raw(body.clone(), Encoding::Bincode)
                    .await?;
                wire[i] = r.wire_bytes as f64 / opt.heads as f64;
            }
            sizes.push(FormatSize {
                zstd_bytes_per_head: wire[0],
                gzip_bytes_per_head: wire[1],
                zstd_ms: compress_ms(&plain.body, true),
                gzip_ms: compress_ms(&plain.body, false),
                format: format.name().to_string(),
                normals,
                bincode_bytes_per_head: b as f64 / opt.heads as f64,
                json_bytes_per_head: j as f64 / opt.heads as f64,
                payload_bytes_per_unique_head: entry.vertices
                    * 3
                    * format.component_bytes()
                    * if normals { 2 } else { 1 },
            });
        }
    }

    // In-process: the same crowds through plan + engine on this thread.
    let engine = Engine::with_options(
        opt.backend,
        crowdmorph_engine::gpu::GpuOptions {
            memory: opt.gpu_memory,
            deltas: opt.gpu_deltas,
            ..Default::default()
        },
    )?;
    let backend = engine.info();
    let prepared = engine.prepare(Arc::new(rig.clone()))?;
    let spec = OutputSpec {
        normals: false,
        precision: match opt.format {
            Format::F32 => crowdmorph_engine::Precision::F32,
            Format::F16 => crowdmorph_engine::Precision::F16,
            Format::Q16 | Format::Q16R => crowdmorph_engine::Precision::Q16(
                crowdmorph_server::registry::quantization_box(&rig),
            ),
            Format::Weights => bail!("bench http measures vertex buffers: format weights has none"),
        },
    };
    let inproc = tokio::task::spawn_blocking({
        let opt = opt.clone();
        move || -> Result<(f64, f64, f64)> {
            let mut out = crowdmorph_engine::BlendOutput::default();
            let mut one = |i: u64| -> Result<()> {
                let base = i as usize * opt.unique;
                let plan = Plan::new((0..opt.heads).map(|h| {
                    JobKey::frame(
                        0,
                        clip_index,
                        ((base + h % opt.unique) % CLIP_FRAMES) as u32,
                        0,
                    )
                }));
                let jobs: Vec<BlendJob> = plan.jobs.iter().map(BlendJob::from).collect();
                // Warm output buffers, as the server's pool gives it.
                engine.evaluate_into(&prepared, &jobs, spec, &mut out)?;
                std::hint::black_box(&out);
                Ok(())
            };
            for i in 0..3 {
                one(i)?;
            }
            let cpu0 = process_cpu_s();
            let start = Instant::now();
            let mut n = 0u64;
            while start.elapsed().as_secs_f64() < opt.seconds || n < 5 {
                one(n)?;
                n += 1;
            }
            let s = start.elapsed().as_secs_f64();
            let cpu = process_cpu_s() - cpu0;
            Ok((
                (n as usize * opt.heads) as f64 / s,
                s * 1e3 / n as f64,
                cpu / n as f64,
            ))
        }
    })
    .await??;

    // Pre-encoded request bodies (clients should not spend CPU encoding).
    let bodies: Arc<Vec<Bytes>> = Arc::new(
        (0..64)
            .map(|i| {
                Client::encode(
                    &crowd(opt, &rig_id, i, opt.format, false),
                    Encoding::Bincode,
                )
            })
            .collect::<Result<_, _>>()?,
    );

    // Saturation: closed loop, `clients` connections, bincode.
    let sat = saturate(
        &client,
        &bodies,
        Encoding::Bincode,
        opt.heads,
        opt.clients,
        opt.seconds,
    )
    .await?;
    let sat_cpu = sat.cpu_s;
    let http_heads_per_s = sat.heads_per_s;
    let http_requests = sat.requests;
    // The same crowds in JSON, both ways.
    let json_bodies: Arc<Vec<Bytes>> = Arc::new(
        (0..64)
            .map(|i| Client::encode(&crowd(opt, &rig_id, i, opt.format, false), Encoding::Json))
            .collect::<Result<_, _>>()?,
    );
    let json = saturate(
        &client,
        &json_bodies,
        Encoding::Json,
        opt.heads,
        opt.clients,
        opt.seconds,
    )
    .await?;
    let json_bytes_per_head = {
        let req = crowd(opt, &rig_id, 1, opt.format, false);
        let (_, j) = client.crowd_frame(&req, Encoding::Json).await?;
        j as f64 / opt.heads as f64
    };
    let loopback_bytes_per_s = loopback_throughput(opt.clients, opt.seconds.min(2.0)).await?;
    let response_bytes_per_head = {
        let req = crowd(opt, &rig_id, 1, opt.format, false);
        let (_, b) = client.crowd_frame(&req, Encoding::Bincode).await?;
        b as f64 / opt.heads as f64
    };
    let loopback_roofline_heads_per_s = loopback_bytes_per_s / response_bytes_per_head;
    // The copies' CPU, measured with response-sized messages on plain threads while the
    // server is idle.
    let response_bytes = response_bytes_per_head * opt.heads as f64;
    let (socket_cpu_s_per_byte, _) = {
        let (clients, message, secs) = (opt.clients, response_bytes as usize, opt.seconds.min(2.0));
        tokio::task::spawn_blocking(move || socket_cpu_per_byte(clients, message, secs)).await??
    };
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let socket_cpu_s_per_response = socket_cpu_s_per_byte * response_bytes;
    let ceiling_heads_per_s =
        cores as f64 / (socket_cpu_s_per_response + inproc.2) * opt.heads as f64;

    // Half load: the load generator's open loop at half the saturated request rate, each
    // latency from the request's due time (corrected for coordinated omission, as `crowdmorph
    // load` reports it).
    let rate = (http_heads_per_s / opt.heads as f64 / 2.0).max(0.5);
    let half = half_load(addr, &bodies, rate, opt).await?;

    let batches = state.metrics.batches.get().max(1);
    let computed = state.metrics.jobs_computed.get();

    // The Python peer last, while crowdmorph idles (its check asks crowdmorph once more).
    let mut python = match &opt.python_peer {
        Some(python) => Some(
            measure_python_peer(
                python,
                opt,
                &rig,
                &rig_id,
                &client,
                &bodies,
                http_heads_per_s,
            )
            .await?,
        ),
        None => None,
    };
    if let Some(p) = &mut python {
        p.ceiling_over_python = ceiling_heads_per_s / p.heads_per_s.max(1e-9);
    }
    let _ = stop_tx.send(());
    server.await??;

    let Percentiles { p50, p99, .. } = half.latency_ms;
    Ok(HttpBenchReport {
        backend,
        rig: rig.name.clone(),
        vertices: entry.vertices,
        targets: rig.targets.len(),
        heads: opt.heads,
        unique: opt.unique,
        format: opt.format.name().to_string(),
        clients: opt.clients,
        inprocess_heads_per_s: inproc.0,
        inprocess_ms_per_crowd: inproc.1,
        http_heads_per_s,
        http_fraction_of_inprocess: http_heads_per_s / inproc.0,
        loopback_bytes_per_s,
        response_bytes_per_head,
        loopback_roofline_heads_per_s,
        http_fraction_of_loopback: http_heads_per_s / loopback_roofline_heads_per_s,
        cores,
        engine_cpu_s_per_request: inproc.2,
        socket_cpu_s_per_byte,
        socket_cpu_s_per_response,
        http_cpu_s_per_request: sat_cpu / http_requests as f64,
        ceiling_heads_per_s,
        http_fraction_of_ceiling: http_heads_per_s / ceiling_heads_per_s,
        http_cpu_fraction_of_ceiling: (socket_cpu_s_per_response + inproc.2)
            / (sat_cpu / http_requests as f64),
        saturation_errors: sat.errors,
        json_heads_per_s: json.heads_per_s,
        json_over_bincode: json.heads_per_s / http_heads_per_s.max(1e-9),
        json_bytes_per_head,
        json_errors: json.errors,
        python,
        saturation_p50_ms: Percentiles::of(&sat.hist).p50,
        saturation_p99_ms: Percentiles::of(&sat.hist).p99,
        half_load_requests_per_s: rate,
        half_load_p50_ms: p50,
        half_load_p99_ms: p99,
        half_load_p99_over_p50: if p50 > 0.0 { p99 / p50 } else { 0.0 },
        half_load_errors: half.errors + half.unfinished,
        mean_batch_jobs: computed as f64 / batches as f64,
        sizes,
    })
}

/// The encodings `bench http --link` measures on every route: format, then compression.
const LINK_ENCODINGS: [(Format, Option<Compression>); 6] = [
    (Format::F32, None),
    (Format::Q16, None),
    (Format::Q16, Some(Compression::Zstd)),
    (Format::Q16R, None),
    (Format::Q16R, Some(Compression::Gzip)),
    (Format::Q16R, Some(Compression::Zstd)),
];

/// One route and encoding of `bench http --link`.
#[derive(Debug, Serialize)]
pub struct LinkRow {
    /// `loopback` or the link's rate.
    pub route: String,
    /// Format, and `+ zstd` or `+ gzip` when the responses were compressed.
    pub encoding: String,
    /// Unique heads per second at saturation (every head of a request is unique).
    pub heads_per_s: f64,
    /// Response bytes per head as they came over the wire.
    pub bytes_per_head: f64,
    /// The route's plain TCP throughput ÷ bytes per head: the most any server could send.
    pub route_limit_heads_per_s: f64,
    /// `heads_per_s` ÷ q16's on the same route (goals: ≥ 3 for the best encoding over
    /// 1 Gbit/s; over loopback no format below 0.9).
    pub over_q16: f64,
    /// Process CPU (server and client) per head, microseconds.
    pub cpu_us_per_head: f64,
    /// Requests that failed.
    pub errors: u64,
}

/// `bench http --link`: heads per second and bytes per head of each encoding on loopback and
/// over each shaped link, on real clips.
#[derive(Debug, Serialize)]
pub struct LinkBenchReport {
    /// The engine.
    pub backend: crowdmorph_engine::BackendInfo,
    /// Rig name.
    pub rig: String,
    /// Vertices per head.
    pub vertices: usize,
    /// Heads per request, all unique.
    pub heads: usize,
    /// Connections.
    pub clients: usize,
    /// Seconds per measurement.
    pub seconds: f64,
    /// The clips played.
    pub clips: Vec<String>,
    /// The routes, with their measured TCP throughput.
    pub routes: Vec<super::link::Route>,
    /// Why the shaped links were skipped, when they were.
    pub skipped: Option<String>,
    /// One row per route and encoding.
    pub rows: Vec<LinkRow>,
}

/// Runs `bench http --link`: `rig_bytes` is a GLB/glTF to upload, or `None` for the embedded
/// head.
pub fn bench_http_links(
    rig_bytes: Option<Vec<u8>>,
    opt: &HttpBenchOptions,
) -> Result<LinkBenchReport> {
    if opt.heads == 0 {
        bail!("need heads >= 1");
    }
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("starting the tokio runtime")?;
    runtime.block_on(run_links(rig_bytes, opt))
}

/// A crowd of `opt.heads` unique heads: head `h` of request `i` plays pair
/// `(i + h × pairs ÷ heads) mod pairs` of every (clip, frame) of the clips played, so that
/// the heads of one response are spread over the clips, not consecutive frames that a
/// compressor would find in each other.
fn real_crowd(
    opt: &HttpBenchOptions,
    rig_id: &str,
    pairs: &[(String, u32)],
    i: usize,
    format: Format,
) -> CrowdFrameRequest {
    CrowdFrameRequest {
        heads: (0..opt.heads)
            .map(|h| {
                let (clip, frame) = &pairs[(i + h * (pairs.len() / opt.heads)) % pairs.len()];
                Head {
                    head: h as u64,
                    rig: rig_id.to_string(),
                    clip: clip.clone(),
                    frame: i64::from(*frame),
                    lod: 0,
                    ..Default::default()
                }
            })
            .collect(),
        output: OutputOptions {
            normals: false,
            format,
        },
        wrap: true,
    }
}

async fn run_links(rig_bytes: Option<Vec<u8>>, opt: &HttpBenchOptions) -> Result<LinkBenchReport> {
    let BenchServer {
        state,
        addr,
        client,
        rig_id,
        stop_tx,
        server,
    } = BenchServer::start(bench_config(opt), rig_bytes).await?;
    let uploaded = match &opt.clips {
        Some(dir) => Some(super::server::upload_clips(&client, &rig_id, dir).await?),
        None => None,
    };
    let entry = state
        .registry
        .get(&rig_id)
        .context("the rig is not registered")?;
    let rig = entry.rig();
    let played: Vec<&crowdmorph_core::rig::Clip> = rig
        .clips
        .iter()
        .filter(|c| uploaded.as_ref().is_none_or(|u| u.contains(&c.name)))
        .collect();
    let pairs: Vec<(String, u32)> = played
        .iter()
        .flat_map(|c| (0..c.frames).map(|f| (c.name.clone(), f)))
        .collect();
    if pairs.len() < opt.heads {
        bail!(
            "the clips played have {} frames in all, fewer than --heads {}: give --clips DIR",
            pairs.len(),
            opt.heads
        );
    }
    let bodies: Vec<Arc<Vec<Bytes>>> = [Format::F32, Format::Q16, Format::Q16R]
        .into_iter()
        .map(|format| {
            (0..64)
                .map(|i| {
                    Client::encode(
                        &real_crowd(opt, &rig_id, &pairs, i, format),
                        Encoding::Bincode,
                    )
                })
                .collect::<Result<Vec<_>, _>>()
                .map(Arc::new)
        })
        .collect::<Result<_, _>>()?;
    let routes =
        super::link::Routes::open(&state, addr, &opt.links, opt.clients, opt.seconds.min(2.0))
            .await?;
    let measured = measure_routes(opt, &routes.routes, &bodies).await;
    let (route_list, skipped) = (routes.routes.clone(), routes.skipped.clone());
    routes.close().await;
    let _ = stop_tx.send(());
    server.await??;
    Ok(LinkBenchReport {
        backend: state.engine.info(),
        rig: rig.name.clone(),
        vertices: entry.vertices,
        heads: opt.heads,
        clients: opt.clients,
        seconds: opt.seconds,
        clips: played.iter().map(|c| c.name.clone()).collect(),
        routes: route_list,
        skipped,
        rows: measured?,
    })
}

/// Every encoding of [`LINK_ENCODINGS`] on every route, one saturation run each.
async fn measure_routes(
    opt: &HttpBenchOptions,
    routes: &[super::link::Route],
    bodies: &[Arc<Vec<Bytes>>],
) -> Result<Vec<LinkRow>> {
    let mut rows = Vec::new();
    for route in routes {
        let first = rows.len();
        for (format, compression) in LINK_ENCODINGS {
            let mut client = Client::new(format!("http://{}", route.addr));
            if let Some(c) = compression {
                client = client.with_compression(c);
            }
            let bodies = &bodies[match format {
                Format::F32 => 0,
                Format::Q16R => 2,
                _ => 1,
            }];
            let sat = saturate(
                &client,
                bodies,
                Encoding::Bincode,
                opt.heads,
                opt.clients,
                opt.seconds,
            )
            .await?;
            // No request finished inside the window (a large response over a slow link):
            // zero heads/s, and no bytes per head to state.
            let counted = sat.heads_per_s * opt.seconds;
            let heads = counted.max(1.0);
            let bytes_per_head = sat.wire_bytes as f64 / heads;
            rows.push(LinkRow {
                route: route.name.clone(),
                encoding: match compression {
                    Some(c) => format!("{} + {}", format.name(), c.token()),
                    None => format.name().to_string(),
                },
                heads_per_s: sat.heads_per_s,
                bytes_per_head,
                route_limit_heads_per_s: if counted > 0.0 {
                    route.tcp_bytes_per_s / bytes_per_head
                } else {
                    0.0
                },
                // Filled in below, once q16 is measured.
                over_q16: 0.0,
                cpu_us_per_head: if counted > 0.0 {
                    sat.cpu_s * 1e6 / heads
                } else {
                    0.0
                },
                errors: sat.errors,
            });
        }
        let on_route = &mut rows[first..];
        if let Some(q16) = on_route.iter().find(|r| r.encoding == Format::Q16.name()) {
            let q16 = q16.heads_per_s.max(1e-9);
            for r in on_route {
                r.over_q16 = r.heads_per_s / q16;
            }
        }
    }
    Ok(rows)
}

/// The link report as text.
impl std::fmt::Display for LinkBenchReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "bench http --link: rig {:?} ({} vertices), {} unique heads per request, {} connections, {:.1} s each; engine {:?}; clips {}",
            self.rig,
            self.vertices,
            self.heads,
            self.clients,
            self.seconds,
            self.backend.kind,
            self.clips.join(", ")
        )?;
        if let Some(why) = &self.skipped {
            writeln!(f, "  shaped links skipped: {why}")?;
        }
        for route in &self.routes {
            writeln!(f, "{route}")?;
            writeln!(
                f,
                "    {:<12} {:>10} {:>12} {:>12} {:>8} {:>10} {:>6}",
                "encoding", "heads/s", "bytes/head", "TCP limit", "× q16", "CPU µs/h", "errors"
            )?;
            for r in self.rows.iter().filter(|r| r.route == route.name) {
                writeln!(
                    f,
                    "    {:<12} {:>10.0} {:>12.0} {:>12.0} {:>8.2} {:>10.1} {:>6}",
                    r.encoding,
                    r.heads_per_s,
                    r.bytes_per_head,
                    r.route_limit_heads_per_s,
                    r.over_q16,
                    r.cpu_us_per_head,
                    r.errors
                )?;
            }
        }
        Ok(())
    }
}

/// Human-readable report.
impl std::fmt::Display for HttpBenchReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&report_text(self))
    }
}

/// The report as text (its [`std::fmt::Display`]).
pub fn report_text(r: &HttpBenchReport) -> String {
    let mut s = format!(
        "rig {:?}: {} vertices × {} targets; {} heads / {} unique per request, {}, {} connections; engine {:?} {}\n",
        r.rig,
        r.vertices,
        r.targets,
        r.heads,
        r.unique,
        r.format,
        r.clients,
        r.backend.kind,
        r.backend.adapter.as_deref().unwrap_or("")
    );
    s += &format!(
        "  in-process      {:>10.0} heads/s  ({:.2} ms per crowd)\n",
        r.inprocess_heads_per_s, r.inprocess_ms_per_crowd
    );
    s += &format!(
        "  HTTP saturated  {:>10.0} heads/s  = {:.0} % of in-process (goal ≥ 70 %); p50 {:.2} ms, p99 {:.2} ms, {} errors\n",
        r.http_heads_per_s,
        r.http_fraction_of_inprocess * 100.0,
        r.saturation_p50_ms,
        r.saturation_p99_ms,
        r.saturation_errors
    );
    s += &format!(
        "  HTTP JSON       {:>10.0} heads/s  = {:.2}× bincode (goal ≥ 0.5); {:.0} bytes per head, {} errors\n",
        r.json_heads_per_s, r.json_over_bincode, r.json_bytes_per_head, r.json_errors
    );
    if let Some(p) = &r.python {
        s += &format!(
            "  Python peer     {:>10.0} heads/s  aiohttp + numpy {} ({}), compute {}; crowdmorph is {:.2}× it (goal ≥ 3; the ceiling below is {:.2}× it{}); p50 {:.2} ms, p99 {:.2} ms, {} errors; max difference {:.2e} (tolerance {:.2e})\n",
            p.heads_per_s,
            p.numpy,
            p.blas,
            p.compute,
            p.crowdmorph_over_python,
            p.ceiling_over_python,
            if p.ceiling_over_python < 3.0 {
                ": 3× is out of any server's reach here"
            } else {
                ""
            },
            p.p50_ms,
            p.p99_ms,
            p.errors,
            p.max_error,
            p.tolerance
        );
    }
    s += &format!(
        "  loopback TCP    {:>10.0} heads/s  = {:.2} GB/s ÷ {:.0} bytes per head; HTTP reaches {:.0} % of it\n",
        r.loopback_roofline_heads_per_s,
        r.loopback_bytes_per_s / 1e9,
        r.response_bytes_per_head,
        r.http_fraction_of_loopback * 100.0
    );
    s += &format!(
        "  ceiling         {:>10.0} heads/s  = {} cores ÷ ({:.3} ms socket copies per response + {:.3} ms engine per request); HTTP reaches {:.0} % of it (goal ≥ 85 %)\n                               HTTP spends {:.3} ms CPU per request (server and client): {:.0} % of the ceiling's CPU efficiency\n",
        r.ceiling_heads_per_s,
        r.cores,
        r.socket_cpu_s_per_response * 1e3,
        r.engine_cpu_s_per_request * 1e3,
        r.http_fraction_of_ceiling * 100.0,
        r.http_cpu_s_per_request * 1e3,
        r.http_cpu_fraction_of_ceiling * 100.0
    );
    s += &format!(
        "  HTTP half load  {:>10.1} requests/s: p50 {:.2} ms, p99 {:.2} ms, p99/p50 = {:.2} (goal ≤ 3), {} errors\n",
        r.half_load_requests_per_s,
        r.half_load_p50_ms,
        r.half_load_p99_ms,
        r.half_load_p99_over_p50,
        r.half_load_errors
    );
    s += &format!("  mean jobs per batch: {:.1}\n", r.mean_batch_jobs);
    s += "  bytes per head (all heads unique):\n";
    for f in &r.sizes {
        s += &format!(
            "    {:<4}{:<9} bincode {:>10.0}  JSON {:>10.0}  zstd {:>10.0}  gzip {:>10.0}  (payload {} per unique head; compressing a response: zstd {:.2} ms, gzip {:.2} ms)\n",
            f.format,
            if f.normals { "+normals" } else { "" },
            f.bincode_bytes_per_head,
            f.json_bytes_per_head,
            f.zstd_bytes_per_head,
            f.gzip_bytes_per_head,
            f.payload_bytes_per_unique_head,
            f.zstd_ms,
            f.gzip_ms
        );
    }
    s
}
