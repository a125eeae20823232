//! `crowdmorph bench sessions`: one crowd session streamed to several viewers, the mission's
//! multi-viewer simulation, measured in-process over loopback WebSockets.
//!
//! Workload (defaults from the sessions issue): 1,000 heads playing 100 animations (distinct
//! clip and offset pairs, so 100 blends a tick), 8 viewers at 30 ticks/s, q16, every viewer at
//! LOD 0 (so the viewers share every blend). Viewers are the load generator's WebSocket
//! clients ([`crowdmorph_load::session::Viewer`]) in the same process that only count bytes and
//! messages: they cost little next to the server, and their CPU is inside the process figure,
//! which says so.
//!
//! Reported: ticks on time, late and skipped (the session's own counters), CPU time of the
//! process per computed tick, engine time per tick (the batcher's compute histogram), bytes and
//! messages per viewer per second, messages dropped by slow viewers.
//!
//! With `--link` ([`bench_session_links`]) one viewer per mode (f32, q16, q16 + zstd,
//! temporal, temporal + deflate, temporal + zstd) watches the same session in turn, over
//! loopback and over each shaped link ([`super::link`]); each message is skimmed for its buffer
//! count (inflated when packed, as any viewer must), so heads/s is buffers received per
//! second. A head whose frame did not change since the viewer's last message has no buffer
//! in it, so a session offers at most (distinct frames of its clips) × 30 unique heads/s
//! with 30 fps clips, whatever its tick rate.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use bytes::Bytes;
use crowdmorph_proto::{Format, MessageEncoding, SessionInfo, ViewerHello};
use serde::Serialize;

use super::server::{BenchServer, process_cpu};
use crowdmorph_engine::BackendChoice;
use crowdmorph_server::ServerConfig;

/// What to measure (also `crowdmorph bench sessions`' flags).
#[derive(Clone, Debug, clap::Args)]
pub struct SessionBenchOptions {
    /// Heads in the session.
    #[arg(long, default_value_t = 1000)]
    pub heads: usize,
    /// Distinct animations (clip and offset pairs) among the heads.
    #[arg(long, default_value_t = 100)]
    pub animations: usize,
    /// Viewers.
    #[arg(long, default_value_t = 8)]
    pub viewers: usize,
    /// Ticks per second.
    #[arg(long, default_value_t = 30.0)]
    pub fps: f32,
    /// Buffer format of every viewer.
    #[arg(long, default_value = "q16", value_parser = super::format_arg())]
    pub format: Format,
    /// Viewers ask for `"output": "weights"` instead (each changed head's binary16 weights and
    /// moved joints, no vertices, no engine work; `--format` is then unused; not with
    /// `--link`).
    #[arg(long)]
    pub weights: bool,
    /// Seconds to measure (after one second of warm-up).
    #[arg(long, default_value_t = 10.0)]
    pub seconds: f64,
    /// Engine.
    #[arg(long, default_value = "auto")]
    pub backend: BackendChoice,
    /// The server's `--max-gpu-memory` (`None`: the default; the CLI's `--max-gpu-memory`).
    #[arg(skip)]
    pub gpu_memory: Option<u64>,
    /// The server's `--gpu-deltas` (the CLI's `--gpu-deltas`).
    #[arg(skip)]
    pub gpu_deltas: crowdmorph_engine::gpu::DeltaFormat,
    /// Heads walk a motion graph over every clip (one random walk per animation) instead of
    /// playing clips.
    #[arg(long)]
    pub graph: bool,
    /// Upload these clips first (`.csv`/`.json` files in a folder, named by file stem) and
    /// play them instead of the rig's own.
    #[arg(long, value_name = "DIR")]
    pub clips: Option<std::path::PathBuf>,
    /// Instead: one viewer at a time per mode (f32, q16, temporal, compressed) on loopback
    /// and over shaped links at these rates (comma-separated, e.g. 1gbit,100mbit; a network
    /// namespace and a tbf-shaped veth pair each, removed at the end; needs root and
    /// iproute2, else only loopback).
    #[arg(long = "link", value_delimiter = ',', value_name = "RATES")]
    pub links: Vec<super::link::LinkSpec>,
    /// With --link: only these viewer modes (comma-separated: f32, q16, q16+zstd, temporal,
    /// temporal+deflate, temporal+zstd; default all of [`VIEWER_MODES`]).
    #[arg(long, value_delimiter = ',', value_name = "MODES")]
    pub modes: Vec<ViewerMode>,
    /// Upload a smooth synthetic clip of this many frames over every target and play it
    /// (after `clips`, if any): a rig without clips, such as ICT FaceKit, gets one, and a
    /// session can offer more unique heads a tick than the rig's clips have frames.
    #[arg(
        long,
        value_name = "FRAMES",
        value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..=100_000)
    )]
    pub long_clip: Option<usize>,
    /// Of the heads, this many (the first) are live: their lips (the rig's jaw and mouth
    /// targets) follow input over their clip, sent with timecodes by `--producers` producer
    /// sockets at `--live-hz`, each carrying its share of the live heads in every message.
    #[arg(long, default_value_t = 0)]
    pub live: usize,
    /// Samples per second each live head gets.
    #[arg(long, default_value_t = 30.0)]
    pub live_hz: f64,
    /// Producer sockets feeding the live heads.
    #[arg(long, default_value_t = 10)]
    pub producers: usize,
    /// Every head is alive (the session's default: blinks, saccades, breathing).
    #[arg(long)]
    pub alive: bool,
    /// With `--alive`: every head also looks at a point that circles the crowd once every
    /// 10 s, moved by a `PATCH` of the session's `alive` ten times a second.
    #[arg(long)]
    pub look_at_moving: bool,
    /// Near-clones (issue 48): instead of the usual measurement, an f32 viewer with LOD by
    /// distance (a camera in front of the crowd, levels 0/1/2/3 from 0/4/8/14 m) and this
    /// tolerance per metre (`ViewerHello::tolerance`) against one without: unique jobs per
    /// tick of each alone, then both at once, every head's buffer compared with its exact one
    /// for `--compare-ticks` ticks.
    #[arg(long, value_name = "PER_METRE")]
    pub tolerance: Option<f32>,
    /// With `--tolerance`: ticks whose every head is compared.
    #[arg(long, default_value_t = 10)]
    pub compare_ticks: usize,
}

/// Name of the clip `--long-clip` uploads.
const LONG_CLIP: &str = "bench-long";

/// A smooth synthetic clip as CSV: every target of `targets` a sine between 0 and 1 with its
/// own period (20–120 frames) and phase, from a fixed seed, so that consecutive frames differ
/// as an animation's do and any prefix of heads plays distinct frames.
fn long_clip_csv(targets: &[String], frames: usize) -> Result<Vec<u8>> {
    let mut rng = crowdmorph_core::rng::SplitMix64(0x10_c1_1b);
    let waves: Vec<(f32, f32)> = targets
        .iter()
        .map(|_| {
            (
                20.0 + 100.0 * rng.unit(),
                std::f32::consts::TAU * rng.unit(),
            )
        })
        .collect();
    let mut w = csv::Writer::from_writer(Vec::new());
    w.write_record(targets)?;
    for f in 0..frames {
        w.write_record(waves.iter().map(|&(period, phase)| {
            let x = 0.5 + 0.5 * (std::f32::consts::TAU * f as f32 / period + phase).sin();
            format!("{x:.4}")
        }))?;
    }
    w.into_inner().map_err(|e| anyhow::anyhow!("{e}"))
}

/// A viewer mode of `bench sessions --link`, by its name in the report (`q16 + zstd`, spaces
/// optional on the command line).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ViewerMode {
    format: Format,
    temporal: bool,
    compression: Option<MessageEncoding>,
}

impl std::str::FromStr for ViewerMode {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let want: String = s.chars().filter(|c| !c.is_whitespace()).collect();
        VIEWER_MODES
            .iter()
            .map(|&(format, temporal, compression)| ViewerMode {
                format,
                temporal,
                compression,
            })
            .find(|m| m.name().replace(' ', "") == want)
            .ok_or_else(|| {
                let names: Vec<String> = VIEWER_MODES
                    .iter()
                    .map(|&(f, t, c)| mode_name(f, t, c).replace(' ', ""))
                    .collect();
                format!("unknown viewer mode {s:?}: one of {}", names.join(", "))
            })
    }
}

impl ViewerMode {
    fn name(self) -> String {
        mode_name(self.format, self.temporal, self.compression)
    }
}

/// The measurement.
#[derive(Clone, Debug, Serialize)]
pub struct SessionBenchReport {
    /// The rig's id and vertex count.
    pub rig: String,
    /// Vertices of one buffer.
    pub vertices: u32,
    /// Heads, animations, viewers, fps, format, seconds as measured.
    pub heads: usize,
    /// Distinct animations.
    pub animations: usize,
    /// Whether the heads walked a motion graph.
    pub graph: bool,
    /// Viewers.
    pub viewers: usize,
    /// Target ticks per second.
    pub fps: f32,
    /// Buffer format.
    pub format: String,
    /// Measured seconds.
    pub seconds: f64,
    /// Ticks computed and delivered in the window.
    pub ticks: u64,
    /// Of those, finished after the next tick was due.
    pub ticks_late: u64,
    /// Ticks skipped.
    pub ticks_skipped: u64,
    /// Ticks the clock asked for in the window (`seconds × fps`).
    pub ticks_due: f64,
    /// Share of due ticks computed on time.
    pub on_time_share: f64,
    /// Unique jobs per computed tick (shared by every viewer).
    pub jobs_per_tick: f64,
    /// Process CPU time per computed tick, milliseconds (server and the in-process viewers).
    pub cpu_ms_per_tick: f64,
    /// Engine wall time per computed tick, milliseconds.
    pub engine_ms_per_tick: f64,
    /// Bytes received per viewer per second (mean over viewers).
    pub bytes_per_viewer_per_s: f64,
    /// Messages received per viewer per second (mean over viewers).
    pub messages_per_viewer_per_s: f64,
    /// Messages replaced in outboxes before they were sent.
    pub messages_dropped: u64,
    /// Every head alive (blinks, saccades, breathing), and looking at a moving point.
    pub alive: bool,
    /// The look-at point moved ten times a second.
    pub look_at_moving: bool,
    /// Live heads, their producers and samples per second each.
    pub live: usize,
    /// Producer sockets.
    pub producers: usize,
    /// Samples per second per live head.
    pub live_hz: f64,
    /// Live messages the producers sent in the window, per second.
    pub live_messages_per_s: f64,
    /// Cores of this machine.
    pub cores: usize,
}

/// Runs the benchmark on a server started in this process.
pub fn bench_sessions(
    rig_bytes: Option<Vec<u8>>,
    opt: &SessionBenchOptions,
) -> Result<SessionBenchReport> {
    if opt.animations == 0 || opt.heads < opt.animations || opt.viewers == 0 || opt.fps <= 0.0 {
        bail!("need heads >= animations >= 1, viewers >= 1 and fps > 0");
    }
    if opt.live > opt.heads
        || (opt.live > 0 && (opt.producers == 0 || !(opt.live_hz > 0.0 && opt.live_hz <= 1000.0)))
    {
        bail!("need live <= heads, and with live heads producers >= 1 and live-hz in (0, 1000]");
    }
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("starting the tokio runtime")?;
    runtime.block_on(run(rig_bytes, opt))
}

struct ViewerCount {
    bytes: AtomicU64,
    messages: AtomicU64,
    /// Buffers the messages carried (counted by the link benchmark, which reads each message).
    buffers: AtomicU64,
}

/// The server of both session benchmarks.
fn bench_config(opt: &SessionBenchOptions) -> ServerConfig {
    ServerConfig {
        backend: opt.backend,
        gpu_memory: opt.gpu_memory,
        gpu_deltas: opt.gpu_deltas,
        no_auto_lod: true,
        render_backend: crowdmorph_server::RenderBackend::Off,
        sessions: crowdmorph_server::sessions::SessionLimits {
            max_heads: opt.heads.max(1),
            max_viewers: opt.viewers.max(1),
            ..Default::default()
        },
        ..ServerConfig::default()
    }
}

/// Uploads `opt.clips`, then creates the session of `opt` on rig `rig_id`: animation `a`
/// plays clip `a mod C` (of the uploaded clips, else the rig's) from an offset that spreads
/// the clip's animations evenly over it; with `opt.graph` it is a random walk with seed `a` from node
/// `a mod C` of a graph over every clip.
async fn create_session(
    client: &crowdmorph_client::Client,
    rig_id: &str,
    opt: &SessionBenchOptions,
) -> Result<(SessionInfo, crowdmorph_proto::RigInfo)> {
    let mut uploaded = match &opt.clips {
        Some(dir) => Some(super::server::upload_clips(client, rig_id, dir).await?),
        None => None,
    };
    let mut info = client.rig(rig_id).await.context("reading the rig")?;
    if let Some(frames) = opt.long_clip {
        let csv = long_clip_csv(&info.targets, frames)?;
        client
            .upload_clip(
                rig_id,
                &format!("name={LONG_CLIP}"),
                "text/csv",
                Bytes::from(csv),
            )
            .await
            .context("uploading the long clip")?;
        uploaded
            .get_or_insert_with(Vec::new)
            .push(LONG_CLIP.to_string());
        info = client.rig(rig_id).await.context("reading the rig")?;
    }
    let clips: Vec<crowdmorph_proto::ClipInfo> = info
        .clips
        .iter()
        .filter(|c| uploaded.as_ref().is_none_or(|u| u.contains(&c.name)))
        .cloned()
        .collect();
    if clips.is_empty() {
        bail!("rig {rig_id:?} has no clips to play");
    }
    if opt.graph {
        put_graph(client, rig_id, &clips).await?;
    }
    let side = (opt.heads as f64).sqrt().ceil() as usize;
    let heads: Vec<serde_json::Value> = (0..opt.heads)
        .map(|i| {
            let a = i % opt.animations;
            let clip = &clips[a % clips.len()];
            // The animations of one clip spread evenly over it: distinct frames while there
            // are no more of them than the clip has frames.
            let per_clip = opt.animations.div_ceil(clips.len());
            let offset = (a / clips.len()) * clip.frames as usize / per_clip;
            let position = [(i % side) as f32 * 0.4, 0.0, -((i / side) as f32) * 0.4];
            // Live heads play their clip (an emotion, their lips live over it).
            let mut head = if opt.graph && i >= opt.live {
                serde_json::json!({
                    "head": i, "rig": rig_id, "position": position,
                    "graph": {"name": "bench", "start": clip.name, "seed": a},
                })
            } else {
                serde_json::json!({
                    "head": i, "rig": rig_id, "clip": clip.name, "offset": offset,
                    "position": position,
                })
            };
            if i < opt.live {
                head["live"] = serde_json::json!({"delay_ms": 100});
            }
            head
        })
        .collect();
    let mut body = serde_json::json!({"fps": opt.fps, "idle_timeout_s": 600, "heads": heads});
    if opt.alive {
        body["alive"] = alive_at(opt, 0.0);
    }
    let reply = client
        .send(
            hyper::Method::POST,
            "/v1/sessions",
            Some("application/json"),
            None,
            Bytes::from(body.to_string()),
        )
        .await
        .context("creating the session")?;
    if reply.status != 201 {
        bail!(
            "creating the session: {} {}",
            reply.status,
            String::from_utf8_lossy(&reply.body)
        );
    }
    Ok((serde_json::from_slice(&reply.body)?, info))
}

async fn run(rig_bytes: Option<Vec<u8>>, opt: &SessionBenchOptions) -> Result<SessionBenchReport> {
    let BenchServer {
        addr,
        client,
        rig_id,
        stop_tx,
        server,
        ..
    } = BenchServer::start(bench_config(opt), rig_bytes).await?;
    let (session, info) = create_session(&client, &rig_id, opt).await?;

    let counts: Vec<Arc<ViewerCount>> = (0..opt.viewers)
        .map(|_| {
            Arc::new(ViewerCount {
                bytes: AtomicU64::new(0),
                messages: AtomicU64::new(0),
                buffers: AtomicU64::new(0),
            })
        })
        .collect();
    let hello = if opt.weights {
        ViewerHello {
            output: crowdmorph_proto::ViewerOutput::Weights,
            ..ViewerHello::default()
        }
    } else {
        ViewerHello {
            format: opt.format,
            ..ViewerHello::default()
        }
    };
    let url = crowdmorph_load::session::stream_url(&format!("http://{addr}"), &session.id)?;
    let mut readers = Vec::new();
    for c in &counts {
        let mut viewer = crowdmorph_load::session::Viewer::connect(&url, &hello)
            .await
            .context("connecting a viewer")?;
        let c = c.clone();
        readers.push(tokio::spawn(async move {
            while let crowdmorph_load::session::ViewerEvent::Tick(b, _) = viewer.next().await {
                c.bytes.fetch_add(b.len() as u64, Ordering::Relaxed);
                c.messages.fetch_add(1, Ordering::Relaxed);
            }
        }));
    }
    let sent = Arc::new(AtomicU64::new(0));
    let mut producers = start_producers(&addr.to_string(), &session.id, &info, opt, &sent).await?;
    producers.extend(start_director(&client, &session.id, opt));
    // Warm-up, then the window.
    tokio::time::sleep(Duration::from_secs(1)).await;
    let sent0 = sent.load(Ordering::Relaxed);
    let snapshot = || async {
        let s: SessionInfo = serde_json::from_slice(
            &client
                .send(
                    hyper::Method::GET,
                    &format!("/v1/sessions/{}", session.id),
                    None,
                    None,
                    Bytes::new(),
                )
                .await?
                .body,
        )?;
        let page = client.metrics().await?;
        let compute =
            crowdmorph_client::metric(&page, "crowdmorph_compute_seconds_sum").unwrap_or(0.0);
        anyhow::Ok((s.stats, compute))
    };
    let bytes0: Vec<u64> = counts
        .iter()
        .map(|c| c.bytes.load(Ordering::Relaxed))
        .collect();
    let msgs0: Vec<u64> = counts
        .iter()
        .map(|c| c.messages.load(Ordering::Relaxed))
        .collect();
    let (s0, compute0) = snapshot().await?;
    let cpu0 = process_cpu();
    let t0 = Instant::now();
    tokio::time::sleep(Duration::from_secs_f64(opt.seconds)).await;
    let seconds = t0.elapsed().as_secs_f64();
    let cpu = process_cpu().saturating_sub(cpu0);
    let live_sent = sent.load(Ordering::Relaxed) - sent0;
    let (s1, compute1) = snapshot().await?;
    let bytes: u64 = counts
        .iter()
        .zip(&bytes0)
        .map(|(c, b)| c.bytes.load(Ordering::Relaxed) - b)
        .sum();
    let msgs: u64 = counts
        .iter()
        .zip(&msgs0)
        .map(|(c, m)| c.messages.load(Ordering::Relaxed) - m)
        .sum();
    let _ = stop_tx.send(());
    for r in readers.into_iter().chain(producers) {
        r.abort();
    }
    let _ = server.await;

    let ticks = s1.ticks - s0.ticks;
    let late = s1.ticks_late - s0.ticks_late;
    let due = seconds * f64::from(opt.fps);
    let per_tick = |x: f64| if ticks == 0 { 0.0 } else { x / ticks as f64 };
    let n = opt.viewers as f64;
    Ok(SessionBenchReport {
        rig: rig_id,
        vertices: info.vertices,
        heads: opt.heads,
        animations: opt.animations,
        graph: opt.graph,
        viewers: opt.viewers,
        fps: opt.fps,
        format: if opt.weights {
            "weights".to_string()
        } else {
            opt.format.name().to_string()
        },
        seconds,
        ticks,
        ticks_late: late,
        ticks_skipped: s1.ticks_skipped - s0.ticks_skipped,
        ticks_due: due,
        on_time_share: ((ticks - late) as f64 / due).min(1.0),
        jobs_per_tick: per_tick((s1.jobs - s0.jobs) as f64),
        cpu_ms_per_tick: per_tick(cpu.as_secs_f64() * 1e3),
        engine_ms_per_tick: per_tick((compute1 - compute0) * 1e3),
        bytes_per_viewer_per_s: bytes as f64 / n / seconds,
        messages_per_viewer_per_s: msgs as f64 / n / seconds,
        messages_dropped: s1.messages_dropped - s0.messages_dropped,
        alive: opt.alive,
        look_at_moving: opt.alive && opt.look_at_moving,
        live: opt.live,
        producers: if opt.live > 0 { opt.producers } else { 0 },
        live_hz: opt.live_hz,
        live_messages_per_s: live_sent as f64 / seconds,
        cores: std::thread::available_parallelism().map_or(1, usize::from),
    })
}

/// The session's `alive` at `t` seconds: blinks, saccades, breathing, and with
/// `--look-at-moving` a point circling the crowd every 10 s at head height.
fn alive_at(opt: &SessionBenchOptions, t: f64) -> serde_json::Value {
    let mut a = serde_json::json!({"blink": true, "saccades": true, "breathing": true});
    if opt.look_at_moving {
        let side = (opt.heads as f64).sqrt().ceil() * 0.4;
        let phase = std::f64::consts::TAU * t / 10.0;
        a["look_at"] = serde_json::json!([
            side / 2.0 + side * phase.cos(),
            1.6,
            -side / 2.0 + side * phase.sin()
        ]);
    }
    a
}

/// The director: moves the crowd's look-at point ten times a second (a `PATCH` of the
/// session's `alive`), when `--look-at-moving` asks for it.
fn start_director(
    client: &crowdmorph_client::Client,
    session: &str,
    opt: &SessionBenchOptions,
) -> Option<tokio::task::JoinHandle<()>> {
    if !(opt.alive && opt.look_at_moving) {
        return None;
    }
    let (client, path, opt) = (
        client.clone(),
        format!("/v1/sessions/{session}"),
        opt.clone(),
    );
    Some(tokio::spawn(async move {
        let start = Instant::now();
        loop {
            tokio::time::sleep(Duration::from_millis(100)).await;
            let body = serde_json::json!({"alive": alive_at(&opt, start.elapsed().as_secs_f64())});
            let sent = client
                .send(
                    hyper::Method::PATCH,
                    &path,
                    Some("application/json"),
                    None,
                    Bytes::from(body.to_string()),
                )
                .await;
            if sent.is_err() {
                return;
            }
        }
    }))
}

/// The producers of `opt.live` heads: `opt.producers` sockets, producer `p` feeding heads
/// `p, p + P, ...` below `opt.live` at `opt.live_hz` with timecodes, one message a sample
/// time; each head's lips (the rig's jaw and mouth targets, else its first 16) a sine of its
/// own phase, as a talking face tracker's would move.
async fn start_producers(
    addr: &str,
    session: &str,
    info: &crowdmorph_proto::RigInfo,
    opt: &SessionBenchOptions,
    sent: &Arc<AtomicU64>,
) -> Result<Vec<tokio::task::JoinHandle<()>>> {
    if opt.live == 0 {
        return Ok(Vec::new());
    }
    let mut names: Vec<String> = info
        .targets
        .iter()
        .filter(|t| {
            let l = t.to_ascii_lowercase();
            l.starts_with("jaw") || l.starts_with("mouth")
        })
        .cloned()
        .collect();
    if names.is_empty() {
        names = info.targets.iter().take(16).cloned().collect();
    }
    let names = Arc::new(names);
    let url = crowdmorph_load::session::live_url(&format!("http://{addr}"), session)?;
    let period = Duration::from_secs_f64(1.0 / opt.live_hz);
    let start = Instant::now();
    let mut out = Vec::new();
    for p in 0..opt.producers.min(opt.live) {
        let mut producer = crowdmorph_load::session::Producer::connect(&url, None)
            .await
            .context("connecting a producer")?;
        let heads: Vec<u64> = (p..opt.live)
            .step_by(opt.producers)
            .map(|h| h as u64)
            .collect();
        let (names, sent) = (names.clone(), sent.clone());
        out.push(tokio::spawn(async move {
            let mut next = tokio::time::Instant::now();
            loop {
                let t = start.elapsed().as_secs_f64();
                let input = crowdmorph_proto::LiveInput {
                    heads: heads
                        .iter()
                        .map(|&h| crowdmorph_proto::LiveSample {
                            head: h,
                            weights: Some(crowdmorph_proto::LiveWeights::Named(
                                names
                                    .iter()
                                    .enumerate()
                                    .map(|(k, n)| {
                                        let phase = 0.13 * h as f64 + 0.37 * k as f64;
                                        let w = 0.5
                                            + 0.5
                                                * (std::f64::consts::TAU * (1.3 * t + phase)).sin();
                                        (n.clone(), (0.6 * w) as f32)
                                    })
                                    .collect(),
                            )),
                            joints: Default::default(),
                            t: Some(t),
                        })
                        .collect(),
                };
                if producer.send(&input).await.is_err() {
                    return;
                }
                sent.fetch_add(1, Ordering::Relaxed);
                next += period;
                tokio::time::sleep_until(next).await;
            }
        }));
    }
    Ok(out)
}

/// The viewer modes `bench sessions --link` measures on every route: format, temporal
/// residuals, per-message compression.
const VIEWER_MODES: [(Format, bool, Option<MessageEncoding>); 6] = [
    (Format::F32, false, None),
    (Format::Q16, false, None),
    (Format::Q16, false, Some(MessageEncoding::Zstd)),
    (Format::Q16, true, None),
    (Format::Q16, true, Some(MessageEncoding::Deflate)),
    (Format::Q16, true, Some(MessageEncoding::Zstd)),
];

/// One route and viewer mode of `bench sessions --link`.
#[derive(Clone, Debug, Serialize)]
pub struct ViewerRow {
    /// `loopback` or the link's rate.
    pub route: String,
    /// Format, `temporal`, and `+ zstd` or `+ deflate` when messages were compressed.
    pub mode: String,
    /// Unique heads per second the viewer received: buffers its messages carried.
    pub heads_per_s: f64,
    /// Bytes per buffer it received, as they came over the wire.
    pub bytes_per_head: f64,
    /// Messages per second it received.
    pub messages_per_s: f64,
    /// Ticks per second the session computed meanwhile (below its rate when the machine's
    /// CPU, shared by the server and this viewer, ran out).
    pub ticks_per_s: f64,
    /// The route's plain TCP throughput ÷ bytes per head: the most any server could send.
    pub route_limit_heads_per_s: f64,
    /// `heads_per_s` ÷ q16's on the same route (goal: ≥ 6 for the best mode over 1 Gbit/s).
    pub over_q16: f64,
    /// Messages the viewer's outbox replaced before they were sent (the viewer was slower
    /// than the ticks).
    pub messages_dropped: u64,
}

/// `bench sessions --link`: one session, one viewer at a time per mode on loopback and over
/// each shaped link.
#[derive(Clone, Debug, Serialize)]
pub struct SessionLinkReport {
    /// The rig's id and vertex count.
    pub rig: String,
    /// Vertices of one buffer.
    pub vertices: u32,
    /// Heads in the session.
    pub heads: usize,
    /// Distinct animations.
    pub animations: usize,
    /// Target ticks per second.
    pub fps: f32,
    /// Seconds per viewer.
    pub seconds: f64,
    /// Unique jobs per tick (every viewer at LOD 0 shares them).
    pub jobs_per_tick: f64,
    /// Unique heads per second the session computed: what a viewer could get at most.
    pub offered_heads_per_s: f64,
    /// The routes, with their measured TCP throughput.
    pub routes: Vec<super::link::Route>,
    /// Why the shaped links were skipped, when they were.
    pub skipped: Option<String>,
    /// One row per route and mode.
    pub rows: Vec<ViewerRow>,
}

/// Runs `bench sessions --link` on a server started in this process.
pub fn bench_session_links(
    rig_bytes: Option<Vec<u8>>,
    opt: &SessionBenchOptions,
) -> Result<SessionLinkReport> {
    if opt.animations == 0 || opt.heads < opt.animations || opt.fps <= 0.0 {
        bail!("need heads >= animations >= 1 and fps > 0");
    }
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("starting the tokio runtime")?;
    runtime.block_on(run_links(rig_bytes, opt))
}

async fn run_links(
    rig_bytes: Option<Vec<u8>>,
    opt: &SessionBenchOptions,
) -> Result<SessionLinkReport> {
    let BenchServer {
        state,
        addr,
        client,
        rig_id,
        stop_tx,
        server,
    } = BenchServer::start(bench_config(opt), rig_bytes).await?;
    let (session, info) = create_session(&client, &rig_id, opt).await?;
    let routes =
        super::link::Routes::open(&state, addr, &opt.links, 1, opt.seconds.min(2.0)).await?;
    let stats0 = session_stats(&client, &session.id).await?;
    let measured = measure_viewers(opt, &client, &session.id, &routes.routes).await;
    let stats1 = session_stats(&client, &session.id).await?;
    let (route_list, skipped) = (routes.routes.clone(), routes.skipped.clone());
    routes.close().await;
    let _ = stop_tx.send(());
    let _ = server.await;
    let (rows, seconds) = measured?;
    let ticks = (stats1.ticks - stats0.ticks).max(1) as f64;
    let jobs_per_tick = (stats1.jobs - stats0.jobs) as f64 / ticks;
    Ok(SessionLinkReport {
        rig: rig_id,
        vertices: info.vertices,
        heads: opt.heads,
        animations: opt.animations,
        fps: opt.fps,
        seconds: opt.seconds,
        jobs_per_tick,
        offered_heads_per_s: jobs_per_tick * ticks / seconds,
        routes: route_list,
        skipped,
        rows,
    })
}

/// The session's counters.
async fn session_stats(
    client: &crowdmorph_client::Client,
    id: &str,
) -> Result<crowdmorph_proto::SessionStats> {
    let reply = client
        .send(
            hyper::Method::GET,
            &format!("/v1/sessions/{id}"),
            None,
            None,
            Bytes::new(),
        )
        .await?;
    Ok(serde_json::from_slice::<SessionInfo>(&reply.body)?.stats)
}

/// One viewer per mode and route, in turn, each for `opt.seconds` after a second's warm-up;
/// rows per message (the caller scales them by the jobs per tick), and the seconds the whole
/// measurement took.
async fn measure_viewers(
    opt: &SessionBenchOptions,
    client: &crowdmorph_client::Client,
    session: &str,
    routes: &[super::link::Route],
) -> Result<(Vec<ViewerRow>, f64)> {
    let start = Instant::now();
    let mut rows = Vec::new();
    for route in routes {
        let url = crowdmorph_load::session::stream_url(&format!("http://{}", route.addr), session)?;
        let first = rows.len();
        for (format, temporal, compression) in VIEWER_MODES {
            let mode = ViewerMode {
                format,
                temporal,
                compression,
            };
            if !opt.modes.is_empty() && !opt.modes.contains(&mode) {
                continue;
            }
            let hello = ViewerHello {
                format,
                temporal,
                compression,
                ..ViewerHello::default()
            };
            let mut viewer = crowdmorph_load::session::Viewer::connect(&url, &hello)
                .await
                .with_context(|| format!("connecting a viewer over {}", route.name))?;
            let count = Arc::new(ViewerCount {
                bytes: AtomicU64::new(0),
                messages: AtomicU64::new(0),
                buffers: AtomicU64::new(0),
            });
            // Each message is skimmed (inflated when packed) for its buffer count: a head
            // whose frame did not change since the viewer's last message has no buffer in it.
            let reader: tokio::task::JoinHandle<Result<(), String>> = tokio::spawn({
                let count = count.clone();
                async move {
                    loop {
                        match viewer.next().await {
                            crowdmorph_load::session::ViewerEvent::Tick(b, _) => {
                                let summary = crowdmorph_proto::skim::skim(&b)
                                    .map_err(|e| format!("an unreadable message: {e}"))?;
                                count.bytes.fetch_add(b.len() as u64, Ordering::Relaxed);
                                count.messages.fetch_add(1, Ordering::Relaxed);
                                count.buffers.fetch_add(summary.buffers, Ordering::Relaxed);
                            }
                            crowdmorph_load::session::ViewerEvent::Closed(code, why) => {
                                return Err(format!("closed with {code}: {why}"));
                            }
                            crowdmorph_load::session::ViewerEvent::Failed(e) => return Err(e),
                        }
                    }
                }
            });
            tokio::time::sleep(Duration::from_secs(1)).await;
            let s0 = session_stats(client, session).await?;
            let read = || {
                [&count.bytes, &count.messages, &count.buffers].map(|c| c.load(Ordering::Relaxed))
            };
            let first = read();
            let t0 = Instant::now();
            tokio::time::sleep(Duration::from_secs_f64(opt.seconds)).await;
            let secs = t0.elapsed().as_secs_f64();
            let last = read();
            let s1 = session_stats(client, session).await?;
            let [bytes, messages, buffers] = [0, 1, 2].map(|i| (last[i] - first[i]) as f64);
            let mode = mode_name(format, temporal, compression);
            if reader.is_finished() {
                let why = match reader.await {
                    Ok(Err(why)) => why,
                    _ => "its reader stopped".to_string(),
                };
                bail!("the {mode} viewer over {}: {why}", route.name);
            }
            reader.abort();
            // A message longer than the window at the link's rate (a large f32 tick over a
            // slow link) leaves the row at zero heads/s, with no bytes per head to state.
            let bytes_per_head = bytes / buffers.max(1.0);
            rows.push(ViewerRow {
                route: route.name.clone(),
                mode,
                heads_per_s: buffers / secs,
                bytes_per_head,
                messages_per_s: messages / secs,
                ticks_per_s: (s1.ticks - s0.ticks) as f64 / secs,
                route_limit_heads_per_s: if buffers > 0.0 {
                    route.tcp_bytes_per_s / bytes_per_head
                } else {
                    0.0
                },
                // Filled in below, once q16 is measured.
                over_q16: 0.0,
                messages_dropped: s1.messages_dropped - s0.messages_dropped,
            });
        }
        let on_route = &mut rows[first..];
        if let Some(q16) = on_route.iter().find(|r| r.mode == Format::Q16.name()) {
            let q16 = q16.heads_per_s.max(1e-9);
            for r in on_route {
                r.over_q16 = r.heads_per_s / q16;
            }
        }
    }
    Ok((rows, start.elapsed().as_secs_f64()))
}

/// A viewer mode as the report names it: `f32`, `q16`, `temporal`, then `+ zstd` or
/// `+ deflate`.
fn mode_name(format: Format, temporal: bool, compression: Option<MessageEncoding>) -> String {
    let mut mode = if temporal {
        "temporal".to_string()
    } else {
        format.name().to_string()
    };
    if let Some(c) = compression {
        mode += match c {
            MessageEncoding::Zstd => " + zstd",
            MessageEncoding::Deflate => " + deflate",
        };
    }
    mode
}

/// The link report as text.
impl std::fmt::Display for SessionLinkReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "bench sessions --link: rig {} ({} vertices), {} heads playing {} animations at {} ticks/s: {:.1} unique jobs per tick, {:.0} unique heads/s offered; one viewer at a time, {:.1} s each",
            self.rig,
            self.vertices,
            self.heads,
            self.animations,
            self.fps,
            self.jobs_per_tick,
            self.offered_heads_per_s,
            self.seconds
        )?;
        if let Some(why) = &self.skipped {
            writeln!(f, "  shaped links skipped: {why}")?;
        }
        for route in &self.routes {
            writeln!(f, "{route}")?;
            writeln!(
                f,
                "    {:<18} {:>10} {:>12} {:>10} {:>10} {:>12} {:>8} {:>8}",
                "viewer",
                "heads/s",
                "bytes/head",
                "msgs/s",
                "ticks/s",
                "TCP limit",
                "× q16",
                "dropped"
            )?;
            for r in self.rows.iter().filter(|r| r.route == route.name) {
                writeln!(
                    f,
                    "    {:<18} {:>10.0} {:>12.0} {:>10.1} {:>10.1} {:>12.0} {:>8.2} {:>8}",
                    r.mode,
                    r.heads_per_s,
                    r.bytes_per_head,
                    r.messages_per_s,
                    r.ticks_per_s,
                    r.route_limit_heads_per_s,
                    r.over_q16,
                    r.messages_dropped
                )?;
            }
        }
        Ok(())
    }
}

/// Stores graph `bench` on the rig: a node per clip, an edge from each to each (itself
/// included) fading over a quarter of the shorter clip (1–10 frames), leaving anywhere in
/// the second half of the source.
async fn put_graph(
    client: &crowdmorph_client::Client,
    rig: &str,
    clips: &[crowdmorph_proto::ClipInfo],
) -> Result<()> {
    let nodes: Vec<serde_json::Value> = clips
        .iter()
        .map(|c| serde_json::json!({"name": c.name, "clip": c.name}))
        .collect();
    let mut edges = Vec::new();
    for a in clips {
        for b in clips {
            let fade = (a.frames.min(b.frames) / 4).clamp(1, 10);
            // Leaving anywhere in the second half of the source spreads the crowd's
            // transitions over time.
            let last = a.frames.saturating_sub(fade);
            let window = [(a.frames / 2).min(last), last];
            edges.push(serde_json::json!({
                "from": a.name, "to": b.name, "fade": fade, "window": window,
            }));
        }
    }
    let body = serde_json::json!({"nodes": nodes, "edges": edges});
    let reply = client
        .send(
            hyper::Method::PUT,
            &format!("/v1/rigs/{rig}/graphs/bench"),
            Some("application/json"),
            None,
            Bytes::from(body.to_string()),
        )
        .await
        .context("storing the graph")?;
    if reply.status != 200 {
        bail!(
            "storing the graph: {} {}",
            reply.status,
            String::from_utf8_lossy(&reply.body)
        );
    }
    Ok(())
}

/// The report as a table.
impl std::fmt::Display for SessionBenchReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&report_text(self))
    }
}

/// The report as text (its [`std::fmt::Display`]).
pub fn report_text(r: &SessionBenchReport) -> String {
    let graph = if r.graph {
        " (random walks over a motion graph)"
    } else {
        ""
    };
    let alive = match (r.alive, r.look_at_moving) {
        (true, true) => ", alive (blinks, saccades, breathing, a moving look-at point)",
        (true, false) => ", alive (blinks, saccades, breathing)",
        _ => "",
    };
    let what = format!("{graph}{alive}");
    format!(
        "bench sessions: rig {} ({} vertices), {} heads playing {} animations{}, {} viewers, \
         {} ticks/s, {}, {:.1} s, {} cores\n\
         ticks computed          {} of {:.0} due ({:.1} % on time), {} late, {} skipped\n\
         unique jobs per tick    {:.1} (shared by all viewers)\n\
         CPU per tick            {:.2} ms (process: server + viewers), engine {:.2} ms\n\
         per viewer              {:.1} messages/s, {:.2} MB/s\n\
         messages dropped        {} (outbox replaced before sending)\n{}",
        r.rig,
        r.vertices,
        r.heads,
        r.animations,
        what,
        r.viewers,
        r.fps,
        r.format,
        r.seconds,
        r.cores,
        r.ticks,
        r.ticks_due,
        r.on_time_share * 100.0,
        r.ticks_late,
        r.ticks_skipped,
        r.jobs_per_tick,
        r.cpu_ms_per_tick,
        r.engine_ms_per_tick,
        r.messages_per_viewer_per_s,
        r.bytes_per_viewer_per_s / 1e6,
        r.messages_dropped,
        if r.live > 0 {
            format!(
                "live heads              {} fed by {} producers at {} Hz ({:.0} messages/s sent)\n",
                r.live, r.producers, r.live_hz, r.live_messages_per_s
            )
        } else {
            String::new()
        },
    )
}

/// Spacing of the bench crowd's grid, metres.
const GRID_STEP: f32 = 0.4;

/// The LOD by distance of the near-clone benchmark.
const NEAR_LOD: [[f32; 2]; 4] = [[0.0, 0.0], [4.0, 1.0], [8.0, 2.0], [14.0, 3.0]];

/// What `bench sessions --tolerance` measured.
#[derive(Clone, Debug, Serialize)]
pub struct NearCloneReport {
    /// The rig's id, vertices and diagonal.
    pub rig: String,
    /// Vertices of one full-level buffer.
    pub vertices: u32,
    /// The rig's diagonal.
    pub diagonal: f64,
    /// Heads in the session (motion-graph walks when `graph`).
    pub heads: usize,
    /// Distinct animations.
    pub animations: usize,
    /// Whether the heads walked a motion graph.
    pub graph: bool,
    /// Ticks per second.
    pub fps: f32,
    /// Nearest and farthest head from the camera, metres.
    pub depth_m: [f64; 2],
    /// Heads per LOD level of the table.
    pub heads_per_level: Vec<usize>,
    /// Tolerance per metre.
    pub tolerance_per_m: f32,
    /// Seconds each job count was measured over.
    pub seconds: f64,
    /// Unique jobs per computed tick, the exact viewer alone (NaN, `null` in JSON, when no
    /// tick was computed in the window).
    pub jobs_exact: f64,
    /// Unique jobs per computed tick, the near-clone viewer alone.
    pub jobs_near: f64,
    /// Ticks computed in each window.
    pub ticks: [u64; 2],
    /// Ticks compared head by head.
    pub compared_ticks: usize,
    /// Head buffers compared (heads × ticks).
    pub compared_heads: u64,
    /// Of those, heads whose near-clone buffer differs from the exact one.
    pub rounded_heads: u64,
    /// Largest vertex distance of a near-clone from its exact pose, as a fraction of the
    /// diagonal.
    pub worst_error: f64,
    /// Largest ratio of a head's vertex error to its own allowance `e(d) × diagonal` (must
    /// be ≤ 1).
    pub worst_ratio: f64,
    /// Heads past their allowance (must be 0).
    pub over: u64,
    /// Load average when it finished.
    pub load: String,
    /// Cores of this machine.
    pub cores: usize,
}

impl std::fmt::Display for NearCloneReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "near-clones: {} heads{} on {} ({} vertices, diagonal {:.4}), {} fps, f32, LOD by \
             distance {:?} (heads per level {:?}, {:.1}–{:.1} m from the camera)",
            self.heads,
            if self.graph {
                " walking a motion graph"
            } else {
                ""
            },
            self.rig,
            self.vertices,
            self.diagonal,
            self.fps,
            NEAR_LOD,
            self.heads_per_level,
            self.depth_m[0],
            self.depth_m[1]
        )?;
        writeln!(
            f,
            "  unique jobs per tick: exact {:.1}, near-clones (tolerance {} per metre) {:.1} \
             ({:.2}x fewer; {} and {} ticks over {:.0} s each)",
            self.jobs_exact,
            self.tolerance_per_m,
            self.jobs_near,
            self.jobs_exact / self.jobs_near,
            self.ticks[0],
            self.ticks[1],
            self.seconds
        )?;
        writeln!(
            f,
            "  compared {} head buffers over {} ticks: {} rounded; worst error {:.3e} \
             diagonals, worst error / allowance {:.3}, {} over their allowance",
            self.compared_heads,
            self.compared_ticks,
            self.rounded_heads,
            self.worst_error,
            self.worst_ratio,
            self.over
        )?;
        write!(f, "  load average {}, {} cores", self.load, self.cores)
    }
}

/// Runs `bench sessions --tolerance` on a server started in this process.
pub fn bench_near_clones(
    rig_bytes: Option<Vec<u8>>,
    opt: &SessionBenchOptions,
) -> Result<NearCloneReport> {
    let Some(t) = opt.tolerance else {
        bail!("bench_near_clones needs --tolerance");
    };
    if !(t.is_finite() && t > 0.0 && t <= crowdmorph_proto::MAX_VIEWER_TOLERANCE) {
        bail!(
            "--tolerance must be in (0, {}]",
            crowdmorph_proto::MAX_VIEWER_TOLERANCE
        );
    }
    if opt.animations == 0 || opt.heads < opt.animations || opt.fps <= 0.0 {
        bail!("need heads >= animations >= 1 and fps > 0");
    }
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("starting the tokio runtime")?;
    runtime.block_on(run_near_clones(rig_bytes, opt, t))
}

/// Euclidean distance of two points, in f64.
fn distance(a: &[f32], b: &[f32]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (f64::from(*x) - f64::from(*y)).powi(2))
        .sum::<f64>()
        .sqrt()
}

/// The bench crowd's camera: 3 m in front of the grid's middle column, at head height, looking
/// down its depth.
fn near_camera(heads: usize) -> crowdmorph_proto::CameraSpec {
    let side = (heads as f64).sqrt().ceil() as f32;
    let x = (side - 1.0) * GRID_STEP / 2.0;
    let depth = side * GRID_STEP;
    crowdmorph_proto::CameraSpec::looking([x, 0.3, 3.0], [x, 0.0, -depth / 2.0])
}

async fn run_near_clones(
    rig_bytes: Option<Vec<u8>>,
    opt: &SessionBenchOptions,
    t: f32,
) -> Result<NearCloneReport> {
    let opt = SessionBenchOptions {
        viewers: 2,
        ..opt.clone()
    };
    let BenchServer {
        addr,
        client,
        rig_id,
        stop_tx,
        server,
        state,
    } = BenchServer::start(bench_config(&opt), rig_bytes).await?;
    let (session, info) = create_session(&client, &rig_id, &opt).await?;
    let diagonal = distance(&info.bbox.max, &info.bbox.min);
    let camera = near_camera(opt.heads);
    let eye = camera.position.unwrap_or_default();
    let hello = |tolerance: Option<f32>| ViewerHello {
        format: Format::F32,
        camera: Some(camera),
        lod: crowdmorph_proto::LodChoice::ByDistance {
            by_distance: NEAR_LOD.to_vec(),
        },
        tolerance,
        ..ViewerHello::default()
    };
    let url = crowdmorph_load::session::stream_url(&format!("http://{addr}"), &session.id)?;
    let stats = || async {
        let s: SessionInfo = serde_json::from_slice(
            &client
                .send(
                    hyper::Method::GET,
                    &format!("/v1/sessions/{}", session.id),
                    None,
                    None,
                    Bytes::new(),
                )
                .await?
                .body,
        )?;
        anyhow::Ok(s.stats)
    };
    // Unique jobs per tick of one viewer alone: a reader drains its messages meanwhile.
    let jobs_alone = |tolerance: Option<f32>| {
        let hello = hello(tolerance);
        let url = url.clone();
        let stats = &stats;
        async move {
            let mut viewer = crowdmorph_load::session::Viewer::connect(&url, &hello)
                .await
                .context("connecting a viewer")?;
            let reader = tokio::spawn(async move {
                while let crowdmorph_load::session::ViewerEvent::Tick(..) = viewer.next().await {}
            });
            tokio::time::sleep(Duration::from_secs(1)).await;
            let s0 = stats().await?;
            tokio::time::sleep(Duration::from_secs_f64(opt.seconds)).await;
            let s1 = stats().await?;
            reader.abort();
            let ticks = s1.ticks - s0.ticks;
            // No tick computed in the window: no figure (NaN), not a zero.
            let jobs = if ticks == 0 {
                f64::NAN
            } else {
                (s1.jobs - s0.jobs) as f64 / ticks as f64
            };
            // Let the server notice the viewer left before the next one joins.
            tokio::time::sleep(Duration::from_millis(300)).await;
            anyhow::Ok((jobs, ticks))
        }
    };
    let (jobs_exact, ticks_exact) = jobs_alone(None).await?;
    let (jobs_near, ticks_near) = jobs_alone(Some(t)).await?;

    // Both at once: every head's buffer of one tick compared with the exact viewer's.
    let mut exact = crowdmorph_load::session::Viewer::connect(&url, &hello(None)).await?;
    let mut near = crowdmorph_load::session::Viewer::connect(&url, &hello(Some(t))).await?;
    let mut se = crowdmorph_proto::StreamState::new();
    let mut sn = crowdmorph_proto::StreamState::new();
    let mut compared = 0usize;
    let (mut heads_compared, mut rounded, mut over) = (0u64, 0u64, 0u64);
    let (mut worst, mut worst_ratio) = (0f64, 0f64);
    let read = |e: crowdmorph_load::session::ViewerEvent| match e {
        crowdmorph_load::session::ViewerEvent::Tick(b, _) => Ok(b),
        other => Err(anyhow::anyhow!("the stream ended: {other:?}")),
    };
    let deadline = Instant::now() + Duration::from_secs(120);
    while compared < opt.compare_ticks && Instant::now() < deadline {
        if se.tick() <= sn.tick() {
            let b = read(exact.next().await)?;
            se.receive(&b).map_err(|e| anyhow::anyhow!("{e}"))?;
        } else {
            let b = read(near.next().await)?;
            sn.receive(&b).map_err(|e| anyhow::anyhow!("{e}"))?;
        }
        if se.tick() != sn.tick() || se.tick() == 0 {
            continue;
        }
        compared += 1;
        for h in se.layout() {
            let (Some(a), Some(b)) = (se.buffer(h.head), sn.buffer(h.head)) else {
                continue;
            };
            heads_compared += 1;
            let (pa, pb) = (a.positions.to_f32(), b.positions.to_f32());
            if pa.len() != pb.len() {
                bail!("head {}: {} and {} floats", h.head, pa.len(), pb.len());
            }
            let err = pa
                .chunks_exact(3)
                .zip(pb.chunks_exact(3))
                .map(|(p, q)| distance(p, q))
                .fold(0.0, f64::max);
            if err > 0.0 {
                rounded += 1;
            }
            let d = distance(&h.position, &eye);
            let allowance = (f64::from(t) * d).min(0.1) * diagonal;
            worst = worst.max(err / diagonal);
            let ratio = if allowance > 0.0 {
                err / allowance
            } else if err > 0.0 {
                f64::INFINITY
            } else {
                0.0
            };
            worst_ratio = worst_ratio.max(ratio);
            // The two engines' runs of one pose are bit for bit the same: any error is the
            // rounding's.
            if err > allowance {
                over += 1;
            }
        }
    }
    exact.close().await;
    near.close().await;
    let _ = stop_tx.send(());
    let _ = server.await;
    drop(state);

    let side = (opt.heads as f64).sqrt().ceil() as usize;
    let mut heads_per_level = vec![0usize; NEAR_LOD.len()];
    let mut depth = [f64::INFINITY, 0f64];
    for i in 0..opt.heads {
        let p = [
            (i % side) as f32 * GRID_STEP,
            0.0,
            -((i / side) as f32) * GRID_STEP,
        ];
        let d = distance(&p, &eye);
        let l = NEAR_LOD
            .partition_point(|[m, _]| f64::from(*m) <= d)
            .saturating_sub(1);
        heads_per_level[l] += 1;
        depth = [depth[0].min(d), depth[1].max(d)];
    }
    Ok(NearCloneReport {
        rig: rig_id,
        vertices: info.vertices,
        diagonal,
        heads: opt.heads,
        animations: opt.animations,
        graph: opt.graph,
        fps: opt.fps,
        depth_m: depth,
        heads_per_level,
        tolerance_per_m: t,
        seconds: opt.seconds,
        jobs_exact,
        jobs_near,
        ticks: [ticks_exact, ticks_near],
        compared_ticks: compared,
        compared_heads: heads_compared,
        rounded_heads: rounded,
        worst_error: worst,
        worst_ratio,
        over,
        load: std::fs::read_to_string("/proc/loadavg")
            .map(|l| l.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
            .unwrap_or_default(),
        cores: std::thread::available_parallelism().map_or(1, usize::from),
    })
}
