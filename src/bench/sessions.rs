//! `crowdmorph bench sessions`: one crowd session streamed to several viewers, the mission's
//! multi-viewer simulation, measured in-process over loopback WebSockets.
//!
//! Workload (defaults from the sessions issue): 1,000 heads playing 100 animations (distinct
//! clip and offset pairs, so 100 blends a tick), 8 viewers at 30 ticks/s, q16, every viewer at
//! LOD 0 (so the viewers share every blend). Viewers are the load generator's WebSocket
//! clients ([`crate::load::session::Viewer`]) in the same process that only count bytes and
//! messages: they cost little next to the server, and their CPU is inside the process figure,
//! which says so.
//!
//! Reported: ticks on time, late and skipped (the session's own counters), CPU time of the
//! process per computed tick, engine time per tick (the batcher's compute histogram), bytes and
//! messages per viewer per second, messages dropped by slow viewers.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use bytes::Bytes;
use crowdmorph_proto::{Format, SessionInfo, ViewerHello};
use serde::Serialize;

use super::server::{BenchServer, process_cpu};
use crate::engine::BackendChoice;
use crate::server::ServerConfig;

/// What to measure.
#[derive(Clone, Debug)]
pub struct SessionBenchOptions {
    /// Heads in the session.
    pub heads: usize,
    /// Distinct animations (clip and offset pairs) among them.
    pub animations: usize,
    /// Viewers connected.
    pub viewers: usize,
    /// Ticks per second.
    pub fps: f32,
    /// Buffer format of every viewer.
    pub format: Format,
    /// Seconds to measure (after one second of warm-up).
    pub seconds: f64,
    /// Engine.
    pub backend: BackendChoice,
    /// The server's `--max-gpu-memory` (`None`: the default).
    pub gpu_memory: Option<u64>,
    /// Heads walk a motion graph over every clip (random walks, one seed per animation)
    /// instead of playing clips.
    pub graph: bool,
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
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("starting the tokio runtime")?;
    runtime.block_on(run(rig_bytes, opt))
}

struct ViewerCount {
    bytes: AtomicU64,
    messages: AtomicU64,
}

async fn run(rig_bytes: Option<Vec<u8>>, opt: &SessionBenchOptions) -> Result<SessionBenchReport> {
    let config = ServerConfig {
        backend: opt.backend,
        gpu_memory: opt.gpu_memory,
        no_auto_lod: true,
        render_backend: crate::server::RenderBackend::Off,
        sessions: crate::server::sessions::SessionLimits {
            max_heads: opt.heads.max(1),
            max_viewers: opt.viewers.max(1),
            ..Default::default()
        },
        ..ServerConfig::default()
    };
    let BenchServer {
        addr,
        client,
        rig_id,
        stop_tx,
        server,
        ..
    } = BenchServer::start(config, rig_bytes).await?;
    let info = client.rig(&rig_id).await.context("reading the rig")?;
    if info.clips.is_empty() {
        bail!("rig {rig_id:?} has no clips to play");
    }
    // Animation a plays clip a mod C from an offset that makes (clip, frame) distinct; with
    // --graph it is a random walk with seed a from node a mod C of a graph over every clip.
    let clips = &info.clips;
    if opt.graph {
        put_graph(&client, &rig_id, clips).await?;
    }
    let side = (opt.heads as f64).sqrt().ceil() as usize;
    let heads: Vec<serde_json::Value> = (0..opt.heads)
        .map(|i| {
            let a = i % opt.animations;
            let clip = &clips[a % clips.len()];
            let offset = (a / clips.len()) * 3;
            let position = [(i % side) as f32 * 0.4, 0.0, -((i / side) as f32) * 0.4];
            if opt.graph {
                serde_json::json!({
                    "head": i, "rig": rig_id, "position": position,
                    "graph": {"name": "bench", "start": clip.name, "seed": a},
                })
            } else {
                serde_json::json!({
                    "head": i, "rig": rig_id, "clip": clip.name, "offset": offset,
                    "position": position,
                })
            }
        })
        .collect();
    let body = serde_json::json!({"fps": opt.fps, "idle_timeout_s": 600, "heads": heads});
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
    let session: SessionInfo = serde_json::from_slice(&reply.body)?;

    let counts: Vec<Arc<ViewerCount>> = (0..opt.viewers)
        .map(|_| {
            Arc::new(ViewerCount {
                bytes: AtomicU64::new(0),
                messages: AtomicU64::new(0),
            })
        })
        .collect();
    let hello = ViewerHello {
        format: opt.format,
        ..ViewerHello::default()
    };
    let url = crate::load::session::stream_url(&format!("http://{addr}"), &session.id)?;
    let mut readers = Vec::new();
    for c in &counts {
        let mut viewer = crate::load::session::Viewer::connect(&url, &hello)
            .await
            .context("connecting a viewer")?;
        let c = c.clone();
        readers.push(tokio::spawn(async move {
            while let crate::load::session::ViewerEvent::Tick(b, _) = viewer.next().await {
                c.bytes.fetch_add(b.len() as u64, Ordering::Relaxed);
                c.messages.fetch_add(1, Ordering::Relaxed);
            }
        }));
    }
    // Warm-up, then the window.
    tokio::time::sleep(Duration::from_secs(1)).await;
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
    for r in readers {
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
        format: opt.format.name().to_string(),
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
        cores: std::thread::available_parallelism().map_or(1, usize::from),
    })
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
    format!(
        "bench sessions: rig {} ({} vertices), {} heads playing {} animations{}, {} viewers, \
         {} ticks/s, {}, {:.1} s, {} cores\n\
         ticks computed          {} of {:.0} due ({:.1} % on time), {} late, {} skipped\n\
         unique jobs per tick    {:.1} (shared by all viewers)\n\
         CPU per tick            {:.2} ms (process: server + viewers), engine {:.2} ms\n\
         per viewer              {:.1} messages/s, {:.2} MB/s\n\
         messages dropped        {} (outbox replaced before sending)\n",
        r.rig,
        r.vertices,
        r.heads,
        r.animations,
        if r.graph {
            " (random walks over a motion graph)"
        } else {
            ""
        },
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
    )
}
