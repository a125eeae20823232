//! `crowdmorph load`: the open-loop load generator of [`crowdmorph::load`] against a running server
//! over HTTP, at a fixed rate or ramping to the highest rate whose p99 meets a target, or
//! (`--session`) N viewers of one crowd session; with a live progress line on standard error
//! (only when it is a terminal).

use std::sync::Arc;
use std::time::Duration;

use anyhow::{Context, Result, bail};

use bytes::Bytes;
use crowdmorph_proto::{CameraSpec, LodChoice, SessionHead, SessionInfo, ViewerHello};
use serde::Serialize;

use crowdmorph::load::http::HttpTarget;
use crowdmorph::load::session::SessionLoad;
use crowdmorph::load::{
    self, CrowdShape, Live, LoadReport, RampOptions, RampReport, RigClips, RunOptions, WireEncoding,
};

/// Arguments of `load`.
#[derive(clap::Args)]
pub struct Args {
    /// The server.
    #[arg(
        long,
        env = "CROWDMORPH_SERVER",
        default_value = "http://127.0.0.1:8080"
    )]
    pub(super) url: String,
    /// Requests per second (with --ramp, the first rate tried).
    #[arg(long, default_value_t = 100.0)]
    pub(super) rate: f64,
    /// Seconds measured (with --ramp, per rate).
    #[arg(long, default_value_t = 10.0)]
    pub(super) duration: f64,
    /// Seconds sent before each measured window, left out of the report.
    #[arg(long, default_value_t = 1.0)]
    pub(super) warmup: f64,
    /// Seconds unanswered requests may take after the window before they count as unfinished.
    #[arg(long, default_value_t = 10.0)]
    pub(super) grace: f64,
    /// HTTP/1.1 connections; requests go to them in turn, one at a time on each.
    #[arg(long, default_value_t = 4, value_parser = clap::value_parser!(u64).range(1..=100_000))]
    pub(super) connections: u64,
    /// Heads per request.
    #[arg(long, default_value_t = 100, value_parser = clap::value_parser!(u32).range(1..))]
    pub(super) heads: u32,
    /// Share of the heads that are unique jobs, in (0, 1]; the rest are clones.
    #[arg(long, default_value_t = 1.0)]
    pub(super) unique: f64,
    /// A rig to play (repeatable; each job picks one uniformly).
    #[arg(long = "rig", default_value = "default-head")]
    pub(super) rigs: Vec<String>,
    /// A clip of the mix, NAME[:WEIGHT] (repeatable; default every clip of the rig equally).
    #[arg(long = "clip", value_parser = parse_weighted)]
    pub(super) clips: Vec<(String, f64)>,
    /// A LOD level of the mix, LEVEL[:WEIGHT] (repeatable; default 0).
    #[arg(long = "lod", value_parser = parse_weighted_lod)]
    pub(super) lods: Vec<(u32, f64)>,
    /// Vertex format.
    #[arg(long, default_value = "f32", value_parser = crowdmorph::bench::format_arg())]
    pub(super) format: crowdmorph_proto::Format,
    /// Ask for normals too.
    #[arg(long)]
    pub(super) normals: bool,
    /// Request and response encoding.
    #[arg(long, value_enum, default_value_t = Encoding::Bincode)]
    pub(super) encoding: Encoding,
    /// Seed of the clip and LOD picks.
    #[arg(long, default_value_t = 1)]
    pub(super) seed: u64,
    /// Find the highest rate whose p99 stays under --p99-ms: double the rate from --rate until
    /// a run misses, then bisect.
    #[arg(long)]
    pub(super) ramp: bool,
    /// The ramp's p99 target, milliseconds.
    #[arg(long, default_value_t = 10.0)]
    pub(super) p99_ms: f64,
    /// The highest rate the ramp tries.
    #[arg(long, default_value_t = 1e6)]
    pub(super) max_rate: f64,
    /// Most runs of the ramp.
    #[arg(long, default_value_t = 12)]
    pub(super) max_steps: usize,
    /// Load a crowd session instead: create one from the crowd flags (--heads, --unique,
    /// --rig, --clip; --lod, --format and --normals go to the viewers), connect --viewers
    /// viewers to its stream for the run, delete it at the end.
    #[arg(long)]
    pub(super) session: bool,
    /// Watch this existing session instead of creating one (implies --session).
    #[arg(long, value_name = "ID")]
    pub(super) session_id: Option<String>,
    /// Viewers of the session.
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u64).range(1..=100_000))]
    pub(super) viewers: u64,
    /// Ticks per second of the session created.
    #[arg(long, default_value_t = 30.0)]
    pub(super) fps: f32,
    /// LOD by distance from each viewer's camera (in front of the crowd's grid), METRES:LEVEL
    /// (repeatable, ascending metres), instead of the --lod mix.
    #[arg(long = "lod-by-distance", value_name = "METRES:LEVEL", value_parser = parse_distance_level)]
    pub(super) lod_by_distance: Vec<[f32; 2]>,
    /// Bearer token for creating and deleting the session.
    #[arg(long, env = "CROWDMORPH_ADMIN_TOKEN", hide_env_values = true)]
    pub(super) admin_token: Option<String>,
    /// Print JSON.
    #[arg(long)]
    pub(super) json: bool,
}

/// Runs `load` and prints its report.
pub fn run(a: Args) -> Result<()> {
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
        format: a.format,
        normals: a.normals,
        encoding: match a.encoding {
            Encoding::Bincode => WireEncoding::Bincode,
            Encoding::Json => WireEncoding::Json,
        },
        seed: a.seed,
    };
    let cmd = LoadCommand {
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
        session: (a.session || a.session_id.is_some()).then(|| SessionMode {
            viewers: a.viewers as usize,
            fps: a.fps,
            attach: a.session_id,
            admin_token: a.admin_token,
            lod_by_distance: (!a.lod_by_distance.is_empty()).then_some(a.lod_by_distance),
        }),
    };
    let outcome = load(&cmd)?;
    super::emit(&outcome, a.json)
}

/// Request and response encoding of `load`.
#[derive(Clone, Copy, clap::ValueEnum)]
pub enum Encoding {
    /// application/x-bincode.
    Bincode,
    /// application/json.
    Json,
}

/// Request bodies generated; request `i` sends body `i mod RING`.
const RING: usize = 64;

/// What `crowdmorph load` was asked to do.
#[derive(Clone, Debug)]
pub struct LoadCommand {
    /// `http://host:port` of the server.
    pub url: String,
    /// Requests per second (the first rate of a ramp).
    pub rate: f64,
    /// Seconds measured (per step of a ramp).
    pub duration: f64,
    /// Seconds sent before each measured window.
    pub warmup: f64,
    /// Seconds unanswered requests may take after the window before they count as unfinished.
    pub grace: f64,
    /// Connections.
    pub connections: usize,
    /// The crowds.
    pub crowd: CrowdShape,
    /// Ramp instead of one fixed rate.
    pub ramp: Option<RampOptions>,
    /// Draw the progress line (it is drawn only when standard error is a terminal).
    pub progress: bool,
    /// Viewers of a session instead of crowd-frame requests.
    pub session: Option<SessionMode>,
}

/// `crowdmorph load --session`: what the viewers watch.
#[derive(Clone, Debug)]
pub struct SessionMode {
    /// Viewers connected.
    pub viewers: usize,
    /// Ticks per second of a session the run creates.
    pub fps: f32,
    /// Watch this existing session instead of creating one from the crowd shape.
    pub attach: Option<String>,
    /// Bearer token for creating and deleting the session.
    pub admin_token: Option<String>,
    /// `[metres, level]` pairs: LOD by distance from each viewer's camera instead of the
    /// crowd shape's LOD mix.
    pub lod_by_distance: Option<Vec<[f32; 2]>>,
}

/// The result: one report, or a ramp's.
#[derive(Debug, Serialize)]
#[serde(untagged)]
pub enum LoadOutcome {
    /// A fixed rate.
    Fixed(LoadReport),
    /// `--ramp`.
    Ramp(RampReport),
}

impl std::fmt::Display for LoadOutcome {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            LoadOutcome::Fixed(r) => f.write_str(&r.text()),
            LoadOutcome::Ramp(r) => f.write_str(&r.text()),
        }
    }
}

impl super::Report for LoadOutcome {}

/// Runs the command to the end.
pub fn load(cmd: &LoadCommand) -> Result<LoadOutcome> {
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("starting the tokio runtime")?;
    runtime.block_on(run_command(cmd))
}

/// What the server says about the rigs of the shape.
async fn describe_rigs(url: &str, crowd: &CrowdShape) -> Result<Vec<RigClips>> {
    let client = crowdmorph_client::Client::new(url.trim_end_matches('/'));
    let mut rigs = Vec::new();
    for id in &crowd.rigs {
        let info = client
            .rig(id)
            .await
            .map_err(|e| anyhow::anyhow!("{e}"))
            .with_context(|| format!("asking {url} about rig {id:?}"))?;
        rigs.push(RigClips {
            id: id.clone(),
            clips: info.clips.iter().map(|c| c.name.clone()).collect(),
            lod_levels: info.lod.levels.len() as u32,
        });
    }
    Ok(rigs)
}

async fn run_command(cmd: &LoadCommand) -> Result<LoadOutcome> {
    load::http::authority_of(&cmd.url)?;
    if let Some(mode) = &cmd.session {
        return Ok(LoadOutcome::Fixed(run_session(cmd, mode).await?));
    }
    let rigs = describe_rigs(&cmd.url, &cmd.crowd).await?;
    let bodies = cmd.crowd.bodies_with_rigs(&rigs, RING)?;
    let target = HttpTarget::with_rig_hints(&cmd.url, bodies, cmd.crowd.encoding)?;
    let opts = |rate: f64| RunOptions {
        rate,
        duration: Duration::from_secs_f64(cmd.duration.max(0.0)),
        warmup: Duration::from_secs_f64(cmd.warmup.max(0.0)),
        grace: Duration::from_secs_f64(cmd.grace.max(0.0)),
        heads_per_request: u64::from(cmd.crowd.heads),
    };
    opts(cmd.rate).check()?;
    match &cmd.ramp {
        None => Ok(LoadOutcome::Fixed(
            run_at(&target, cmd.connections, opts(cmd.rate), cmd.progress).await?,
        )),
        Some(ramp) => {
            let ramp = RampOptions {
                start_rate: cmd.rate,
                ..ramp.clone()
            };
            let report = load::ramp(&ramp, |rate| {
                let target = target.clone();
                let opts = opts(rate);
                async move {
                    run_at(&target, cmd.connections, opts, cmd.progress)
                        .await
                        .map_err(|e| load::LoadError::Invalid(format!("{e:#}")))
                }
            })
            .await?;
            Ok(LoadOutcome::Ramp(report))
        }
    }
}

/// One run at a fixed rate over fresh connections.
async fn run_at(
    target: &Arc<HttpTarget>,
    connections: usize,
    opts: RunOptions,
    progress: bool,
) -> Result<LoadReport> {
    let lanes = target.lanes(connections).await?;
    let rate = opts.rate;
    let live = Live::new(opts);
    let line = move |live: &Live| {
        let r = live.snapshot();
        let (sent, done) = live.counts();
        format!(
            "{rate:.0} req/s: {:.1} s, {sent} sent, {} in flight, {} ok, {} errors; \
             p50 {:.2} ms, p99 {:.2} ms; {:.0} heads/s",
            live.elapsed(),
            sent.saturating_sub(done),
            r.ok,
            r.errors,
            r.latency_ms.p50,
            r.latency_ms.p99,
            r.heads_per_s
        )
    };
    Ok(with_progress(&live, progress, line, load::run(lanes, &live)).await?)
}

/// Runs `work` with a progress line that shows `line` of `live` four times a second.
/// indicatif hides the line when standard error is not a terminal; then nothing is drawn and
/// no snapshot is taken.
async fn with_progress<T>(
    live: &Arc<Live>,
    progress: bool,
    line: impl Fn(&Live) -> String + Send + 'static,
    work: impl Future<Output = T>,
) -> T {
    let bar = progress
        .then(indicatif::ProgressBar::new_spinner)
        .filter(|b| !b.is_hidden());
    if let Some(b) = &bar {
        b.enable_steady_tick(Duration::from_millis(120));
    }
    let ticker = bar.clone().map(|bar| {
        let live = live.clone();
        tokio::spawn(async move {
            loop {
                tokio::time::sleep(Duration::from_millis(250)).await;
                bar.set_message(line(&live));
            }
        })
    });
    let result = work.await;
    if let Some(t) = ticker {
        t.abort();
    }
    if let Some(b) = bar {
        b.finish_and_clear();
    }
    result
}

/// Heads of a session stand on a square grid this far apart (metres), in rows going away
/// from the viewers' cameras along −Z.
const GRID: f32 = 0.4;

/// The session's heads from the crowd shape: head `h` plays what head `h` of the shape's
/// first request plays, its frame as the offset (so the shape's unique jobs are the session's
/// distinct animations and the rest are clones), on a square grid.
fn session_heads(crowd: &CrowdShape, rigs: &[RigClips]) -> Result<Vec<SessionHead>> {
    let request = crowd
        .requests(rigs, 1)?
        .pop()
        .context("the crowd shape made no request")?;
    let side = (request.heads.len() as f64).sqrt().ceil().max(1.0) as usize;
    Ok(request
        .heads
        .into_iter()
        .enumerate()
        .map(|(i, h)| SessionHead {
            head: h.head,
            rig: h.rig,
            clip: h.clip,
            offset: h.frame,
            position: [(i % side) as f32 * GRID, 0.0, -((i / side) as f32) * GRID],
            yaw: 0.0,
            scale: 1.0,
            graph: None,
            joints: h.joints,
            layers: h.layers,
            clamp: h.clamp,
            live: None,
            alive: None,
        })
        .collect())
}

/// A camera in front of the grid of `heads` heads, at eye height, looking at its middle.
fn grid_camera(heads: usize) -> CameraSpec {
    let side = (heads as f64).sqrt().ceil().max(1.0) as f32;
    let middle = (side - 1.0) * GRID / 2.0;
    CameraSpec::looking([middle, 1.6, 3.0], [middle, 1.6, -middle])
}

/// One hello per viewer: the shape's format and normals, and the LOD by distance or from
/// the shape's LOD mix (in proportion to its weights).
fn hellos(crowd: &CrowdShape, mode: &SessionMode, heads: usize) -> Vec<ViewerHello> {
    let levels = load::session::viewer_lods(&crowd.lods, mode.viewers);
    levels
        .into_iter()
        .map(|level| ViewerHello {
            format: crowd.format,
            normals: crowd.normals,
            camera: mode.lod_by_distance.is_some().then(|| grid_camera(heads)),
            lod: match &mode.lod_by_distance {
                Some(table) => LodChoice::ByDistance {
                    by_distance: table.clone(),
                },
                None => LodChoice::Fixed(level),
            },
            ..ViewerHello::default()
        })
        .collect()
}

/// Sends a session request and returns the reply, an error naming `what` on a transport
/// failure.
async fn session_call(
    client: &crowdmorph_client::Client,
    method: hyper::Method,
    path: &str,
    body: Option<String>,
    what: &str,
) -> Result<crowdmorph_client::Reply> {
    client
        .send(
            method,
            path,
            body.as_ref().map(|_| crowdmorph_proto::CONTENT_TYPE_JSON),
            Some(crowdmorph_proto::CONTENT_TYPE_JSON),
            body.map(Bytes::from).unwrap_or_default(),
        )
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))
        .with_context(|| what.to_string())
}

/// The reply's JSON body as `T`, or an error with the server's code and message.
fn session_reply<T: serde::de::DeserializeOwned>(
    reply: &crowdmorph_client::Reply,
    ok: u16,
    what: &str,
) -> Result<T> {
    if reply.status != ok {
        let detail = reply.error().map_or_else(
            || String::from_utf8_lossy(&reply.body).into_owned(),
            |e| format!("{} {}", e.error.code, e.error.message),
        );
        bail!("{what}: the server answered {}: {detail}", reply.status);
    }
    serde_json::from_slice(&reply.body).with_context(|| format!("{what}: reading the answer"))
}

/// `--session`: creates the session (or finds the one to attach to), runs the viewers, and
/// deletes a session it created, whatever the run's outcome.
async fn run_session(cmd: &LoadCommand, mode: &SessionMode) -> Result<LoadReport> {
    if cmd.ramp.is_some() {
        bail!(
            "--ramp ramps a request rate and cannot be combined with --session \
             (run --session at a few --viewers counts instead)"
        );
    }
    if cmd.crowd.encoding == WireEncoding::Json {
        bail!("a session's stream is always bincode: --encoding json cannot apply to --session");
    }
    if mode.viewers == 0 {
        bail!("--session needs at least one viewer");
    }
    let mut client = crowdmorph_client::Client::new(cmd.url.trim_end_matches('/'));
    if let Some(t) = &mode.admin_token {
        client = client.with_token(t);
    }
    let (info, created) = match &mode.attach {
        Some(id) => {
            let what = format!("asking {} about session {id:?}", cmd.url);
            let reply = session_call(
                &client,
                hyper::Method::GET,
                &format!("/v1/sessions/{id}"),
                None,
                &what,
            )
            .await?;
            if reply.status == 404 {
                bail!("the server at {} has no session {id:?}", cmd.url);
            }
            (session_reply::<SessionInfo>(&reply, 200, &what)?, false)
        }
        None => {
            let rigs = describe_rigs(&cmd.url, &cmd.crowd).await?;
            let heads = session_heads(&cmd.crowd, &rigs)?;
            // The session outlives a run that stalls, but not for long after one that died.
            let lifetime = cmd.warmup + cmd.duration + cmd.grace + 60.0;
            let body = serde_json::json!({
                "fps": mode.fps,
                "idle_timeout_s": lifetime.clamp(60.0, 86_400.0).ceil() as u32,
                "heads": heads,
            });
            let what = "creating the session";
            let reply = session_call(
                &client,
                hyper::Method::POST,
                "/v1/sessions",
                Some(body.to_string()),
                what,
            )
            .await?;
            (session_reply::<SessionInfo>(&reply, 201, what)?, true)
        }
    };
    let load = SessionLoad {
        url: cmd.url.clone(),
        id: info.id.clone(),
        created,
        fps: f64::from(info.fps),
        heads: info.heads.len() as u64,
        hellos: hellos(&cmd.crowd, mode, info.heads.len()),
    };
    let result = watch(cmd, &load).await;
    if created {
        let what = format!("deleting session {:?}", info.id);
        let reply = session_call(
            &client,
            hyper::Method::DELETE,
            &format!("/v1/sessions/{}", info.id),
            None,
            &what,
        )
        .await;
        match reply {
            Ok(r) if r.status == 204 || r.status == 404 => {}
            Ok(r) => tracing::warn!("{what}: the server answered {}", r.status),
            Err(e) => tracing::warn!("{e:#}"),
        }
    }
    result
}

/// The viewers of `load` for the run's warm-up and window, with the progress line.
async fn watch(cmd: &LoadCommand, load: &SessionLoad) -> Result<LoadReport> {
    let opts = RunOptions {
        rate: load.rate(),
        duration: Duration::from_secs_f64(cmd.duration.max(0.0)),
        warmup: Duration::from_secs_f64(cmd.warmup.max(0.0)),
        grace: Duration::from_secs_f64(cmd.grace.max(0.0)),
        heads_per_request: load.heads,
    };
    opts.check()?;
    let live = Live::new(opts);
    let viewers = load.hellos.len();
    let fps = load.fps;
    let line = move |live: &Live| {
        let r = live.snapshot();
        let missed = r.session.as_ref().map_or(0, |s| s.ticks_missed);
        format!(
            "{viewers} viewers × {fps} ticks/s: {:.1} s, {} messages, {missed} missed, {} errors; \
             p50 {:.2} ms, p99 {:.2} ms; {:.0} heads/s",
            live.elapsed(),
            r.ok,
            r.errors,
            r.latency_ms.p50,
            r.latency_ms.p99,
            r.heads_per_s
        )
    };
    Ok(with_progress(&live, cmd.progress, line, load::session::run(load, &live)).await?)
}

/// Parses a mix entry `NAME[:WEIGHT]` (`--clip talk:3`); without a weight, 1.
pub fn parse_weighted(s: &str) -> Result<(String, f64)> {
    let (name, weight) = match s.rsplit_once(':') {
        Some((n, w)) if !n.is_empty() && w.trim().parse::<f64>().is_ok() => {
            (n, w.trim().parse::<f64>()?)
        }
        _ => (s, 1.0),
    };
    anyhow::ensure!(!name.is_empty(), "{s:?}: name a clip");
    anyhow::ensure!(
        weight.is_finite() && weight >= 0.0,
        "{s:?}: the weight must be a finite number >= 0"
    );
    Ok((name.to_string(), weight))
}

/// Parses a LOD mix entry `LEVEL[:WEIGHT]` (`--lod 2:0.25`); without a weight, 1.
pub fn parse_weighted_lod(s: &str) -> Result<(u32, f64)> {
    let (level, weight) = parse_weighted(s)?;
    let level = level
        .trim()
        .parse()
        .with_context(|| format!("{s:?}: the LOD level must be a whole number"))?;
    Ok((level, weight))
}

/// Parses `METRES:LEVEL` (`--lod-by-distance 8:1`).
pub fn parse_distance_level(s: &str) -> Result<[f32; 2]> {
    let (m, l) = s
        .split_once(':')
        .with_context(|| format!("{s:?}: write METRES:LEVEL"))?;
    let metres: f32 = m.trim().parse().with_context(|| format!("{s:?}: metres"))?;
    let level: u32 = l.trim().parse().with_context(|| format!("{s:?}: level"))?;
    anyhow::ensure!(
        metres.is_finite() && metres >= 0.0,
        "{s:?}: metres must be >= 0"
    );
    Ok([metres, level as f32])
}

#[cfg(test)]
mod tests {
    // A test that meets an unexpected error should fail loudly.
    #![allow(clippy::unwrap_used)]

    use super::*;

    #[test]
    fn mix_entries_parse() {
        assert_eq!(parse_weighted("talk:3").unwrap(), ("talk".into(), 3.0));
        assert_eq!(parse_weighted("talk").unwrap(), ("talk".into(), 1.0));
        // A colon that does not start a weight is part of the name.
        assert_eq!(parse_weighted("a:b").unwrap(), ("a:b".into(), 1.0));
        assert!(parse_weighted("talk:-1").is_err());
        assert_eq!(parse_weighted_lod("2:0.25").unwrap(), (2, 0.25));
        assert!(parse_weighted_lod("x:1").is_err());
        assert_eq!(parse_distance_level("8.5:2").unwrap(), [8.5, 2.0]);
        assert!(parse_distance_level("8").is_err());
        assert!(parse_distance_level("-1:2").is_err());
        assert!(parse_distance_level("1:x").is_err());
    }
}
