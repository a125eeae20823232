//! A session's tick: every head resolved once, each viewer's jobs per head grouped by what
//! their buffers hold, one submission to the batcher per group, and the fan-out of messages
//! relative to what each viewer last received. The fan-out of tick N runs on a blocking thread
//! while tick N + 1 is resolved and blended (one in flight, so outboxes get messages in tick
//! order). The tick task is supervised: a panic, in it or in its fan-out, ends its session.
//! Viewers that blend themselves get each head's resolved pose instead ([`poses`]), with no
//! engine work.

mod poses;

use std::collections::HashMap;
use std::sync::atomic::Ordering;
use std::sync::{Arc, Weak};
use std::time::Duration;

use bytes::Bytes;
use crowdmorph_proto::{
    CameraSpec, Format, HEAD_MISSING, HEAD_UNCHANGED, LodChoice, MessageEncoding, RenderRequest,
    SessionHead, ViewerOutput,
};
use glam::Vec3;
use rayon::prelude::*;
use tokio::time::Instant;

use super::render::Rendering;
use crate::admission::live::{live_joints, live_joints_bytes};
use crate::admission::resolve::{
    head_reach, job_output_bytes, job_request, joint_overrides, requested_joints,
};
use crate::registry::{MAX_F16, RigEntry};
use crate::scheduler::Scheduler;
use crate::scheduler::{JobRequest, ScheduleError};
use crate::sessions::Sessions;
use crate::sessions::{
    Baseline, Encoded, HeadKey, MIN_FPS, MISSING_KEY, Outgoing, SentLayers, Session, Viewer,
    ViewerSettings, bump, close,
};
use crowdmorph_anim::graph::{Graph, Player};
use crowdmorph_anim::live::apply_weights;
use crowdmorph_core::rig::{FrameMode, JointPose, Pose, clamp_weights, layer_weights};

use crate::admission::alive::AliveTick;
use crate::admission::layers::{
    layered_joints, layered_joints_bytes, layers_bytes, resolve_layers,
};
use crate::admission::names::{LiveNames, live_names};
use crate::http::ApiError;

use crate::session_stream::delta;
use crate::session_stream::encode::{
    JobKey as Key, MessageContent, encode_delta, encode_layers, encode_vertices,
};

/// What a session's tick needs of the server beside rendering ([`Rendering`], for viewers
/// that want images): the sessions and the batcher.
pub trait Ticking: Rendering {
    /// The crowd sessions.
    fn sessions(&self) -> &Sessions;
    /// The batcher the tick submits its jobs to.
    fn scheduler(&self) -> &Scheduler;
}

/// Starts the tick task of `session`, supervised: if it panics (a bug), the session ends —
/// removed from the server, its viewers closed with 1011 — and the panic is logged once and
/// counted (`crowdmorph_session_panics_total`), rather than leaving a session registered that
/// never ticks, never idles out and counts toward `--max-sessions`.
pub fn supervise<S: Ticking>(session: Arc<Session>, app: Weak<S::Owner>) {
    let task = tokio::spawn(run_session::<S>(session.clone(), app.clone()));
    tokio::spawn(async move {
        let Err(e) = task.await else { return };
        if !e.is_panic() {
            return;
        }
        let payload = e.into_panic();
        let why = payload
            .downcast_ref::<&str>()
            .map(|s| (*s).to_string())
            .or_else(|| payload.downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "a panic".into());
        tracing::error!(session = %session.id, panic = %why, "a session's tick task panicked; the session ends");
        if let Some(state) = S::upgrade(&app) {
            bump_panic(&state);
            state.sessions().remove(&session.id);
        }
        session.stop(close::INTERNAL, "session ended: internal error");
    });
}

fn bump_panic<S: Ticking>(state: &S) {
    state.metrics().session_panics.inc();
}

/// The tick task of one session.
async fn run_session<S: Ticking>(session: Arc<Session>, app: Weak<S::Owner>) {
    // `fps` is at least MIN_FPS (checked at creation): a period of at most ten seconds.
    let period = Duration::from_secs_f64(1.0 / f64::from(session.fps.max(MIN_FPS)));
    let start = Instant::now();
    let mut slot: u64 = 0;
    // The graph heads' state lives with the task that advances it.
    let mut players = Players::default();
    // The previous tick's fan-out, still encoding on a blocking thread while this tick's
    // heads are blended: fan-outs run one at a time and in tick order.
    let mut fanning = FanOuts::default();
    loop {
        let due = start + period.mul_f64(slot as f64);
        // Woken for the tick, for the idle timeout (whichever comes first: a slow session
        // still ends on time), when its viewers change, or when it stops.
        let idle_at = session.idle_deadline();
        let wake = idle_at.map_or(due, |t| t.min(due));
        tokio::select! {
            () = tokio::time::sleep_until(wake) => {}
            () = session.stopping.notified() => {}
            () = session.viewers_changed.notified() => {}
        }
        if session.stopped.load(Ordering::Acquire) {
            break;
        }
        let Some(state) = S::upgrade(&app) else { break };
        if session.idle_deadline().is_some_and(|t| Instant::now() >= t) {
            tracing::info!(session = %session.id, "session ended: no viewer for its idle timeout");
            state.sessions().remove(&session.id);
            session.stop(close::AWAY, "session ended (idle)");
            break;
        }
        if Instant::now() < due {
            continue;
        }
        if session.panic_next_tick.swap(false, Ordering::AcqRel) {
            panic!("test hook: a session tick panics");
        }
        let tick = slot + 1;
        let computed = tick_once(&state, &session, tick, &mut players, &mut fanning).await;
        let done = Instant::now();
        let next_due = start + period.mul_f64((slot + 1) as f64);
        let m = &state.sessions().metrics;
        let mut next = slot + 1;
        if done > next_due {
            // Ticks whose time passed while this one ran are skipped, not queued: the next is
            // the latest whose time has come.
            let behind = (done.duration_since(start).as_secs_f64() / period.as_secs_f64()) as u64;
            if behind > next {
                let skipped = behind - next;
                bump(&m.ticks_skipped, skipped);
                session.with_stats(|s| s.ticks_skipped += skipped);
                next = behind;
            }
        }
        match computed {
            Ticked::Delivered(jobs) => {
                let late = done > next_due;
                bump(
                    if late {
                        &m.ticks_late
                    } else {
                        &m.ticks_on_time
                    },
                    1,
                );
                bump(&m.jobs, jobs);
                session.with_stats(|s| {
                    s.ticks += 1;
                    s.ticks_late += u64::from(late);
                    s.jobs += jobs;
                });
            }
            Ticked::Skipped => {
                bump(&m.ticks_skipped, 1);
                session.with_stats(|s| s.ticks_skipped += 1);
            }
            Ticked::NoViewers => {}
        }
        slot = next;
    }
}

enum Ticked {
    /// Computed and handed to the outboxes, with the unique jobs it submitted.
    Delivered(u64),
    Skipped,
    NoViewers,
}

/// One head resolved for this tick.
#[derive(Clone)]
struct HeadAt {
    rig: u32,
    /// What it shows: its clip's frame, or a graph head's pose.
    pose: Pose,
    /// Its joint overrides, before a viewer's LOD level drops any.
    joints: JointPose,
    levels: u32,
    f16_ok: bool,
}

/// The vertex viewers that share a format and normals: their jobs go to the batcher as one
/// submission.
struct Group {
    format: Format,
    normals: bool,
    jobs: Vec<JobRequest>,
    keys: Vec<Key>,
    index: HashMap<Key, u32>,
}

/// Most bytes a tick's bookkeeping holds at once for `heads` heads and `viewers` viewers:
/// each head's resolved rig, clip and frame; per viewer its job per head, the keys it is sent,
/// the entries of its message and the fan-out cache's copy of them; per group (viewers that
/// share a format and normals: at most six) the jobs, their keys and the index over them, with
/// room for the vectors' and the map's growth. At the session limits (10,000 heads, dozens of
/// viewers) this is tens of megabytes per tick, so it is charged to the queue memory before
/// any of it is built.
///
/// Heads with joint overrides also get, per group, their overrides merged with what each LOD
/// level holds at rest: `joint_sets` is the most sets those merges and the heads' own resolved
/// overrides hold over all heads (see `Resolved::joint_sets`).
fn tick_bookkeeping_bytes(heads: usize, viewers: usize, joint_sets: usize) -> u64 {
    let groups = viewers.min(6);
    // A temporal viewer also builds its next baseline's map of references (the last one is
    // alive until the socket takes the message): two map entries per head.
    let per_viewer = size_of::<Option<u32>>()
        + size_of::<HeadKey>()
        + 2 * size_of::<u32>()
        + 2 * (size_of::<(u64, crate::sessions::HeadPrev)>() + 16);
    let per_group = 2 * (size_of::<JobRequest>() + size_of::<Key>())
        + 3 * (size_of::<Key>() + size_of::<u32>() + 1);
    let per_head = size_of::<Option<HeadAt>>() + viewers * per_viewer + groups * per_group;
    let joints = (groups * joint_sets * size_of::<crowdmorph_core::rig::JointSet>()) as u64;
    (heads as u64)
        .saturating_mul(per_head as u64)
        .saturating_add(joints)
}

/// A head's LOD level for a viewer. By distance, it needs the camera's eye: without a camera,
/// or with a framing one (whose eye the render's layout places, after the levels are chosen),
/// every head gets level 0.
fn level_for(lod: &LodChoice, camera: Option<&CameraSpec>, position: [f32; 3]) -> u32 {
    match lod {
        LodChoice::Fixed(l) => *l,
        LodChoice::ByDistance { by_distance } => {
            let Some(eye) = camera.and_then(|c| c.position) else {
                return 0;
            };
            let d = Vec3::from(position).distance(Vec3::from(eye));
            level_at(by_distance, d)
        }
    }
}

/// The level of the last entry whose metres ≤ `d` (0 nearer than the first). The table is
/// ascending (`check_lod` refuses any other), so the entries at or below `d` are a prefix and
/// a binary search finds its end: this runs per head, per viewer, per tick.
fn level_at(by_distance: &[[f32; 2]], d: f32) -> u32 {
    match by_distance.partition_point(|[m, _]| *m <= d) {
        0 => 0,
        n => by_distance.get(n - 1).map_or(0, |[_, l]| *l as u32),
    }
}

/// One tick: the four phases of the module doc — [`resolve`] every head once, [`group`] each
/// viewer's jobs by what its buffers hold (image viewers' frames start on the blocking pool),
/// [`submit`] each group to the batcher, [`fan_out`] the messages.
async fn tick_once<S: Ticking>(
    state: &S,
    session: &Arc<Session>,
    tick: u64,
    players: &mut Players,
    fanning: &mut FanOuts,
) -> Ticked {
    let arrived = std::time::Instant::now();
    let Some(TickInput {
        heads,
        layout_rev,
        viewers,
        jumps,
    }) = take_heads(session, tick)
    else {
        return Ticked::Skipped;
    };
    // Graph heads move on every tick, watched or not, so that what a viewer joining later
    // sees does not depend on when others watched.
    let resolved = resolve(state, session, &heads, tick, players, jumps);
    if viewers.is_empty() {
        return Ticked::NoViewers;
    }
    // What this tick builds per head is charged first, as every request's memory is.
    let near_viewers = viewers
        .iter()
        .filter(|v| v.settings().is_some_and(|s| s.tolerance > 0.0))
        .count();
    let near = if near_viewers == 0 {
        0
    } else {
        let channels = resolved
            .rigs
            .iter()
            .map(|r| r.rig().targets.len())
            .max()
            .unwrap_or(0);
        near_clone_bytes(heads.len(), near_viewers, channels)
    };
    let Ok(bookkeeping) = state.queue_memory().reserve(
        tick_bookkeeping_bytes(heads.len(), viewers.len(), resolved.joint_sets())
            .saturating_add(near),
    ) else {
        return Ticked::Skipped;
    };
    let mut grouped = group(&resolved, &heads, &viewers);
    for (v, s) in std::mem::take(&mut grouped.frames) {
        start_frame(state, session, &heads, &resolved, tick, v, s);
    }
    let posed = poses::TickPosesInput {
        tick,
        heads: &heads,
        layout_rev,
        resolved: &resolved,
        arrived,
    };
    poses::fan_out(state, session, &posed, &std::mem::take(&mut grouped.poses));
    if grouped.groups.iter().all(|g| g.jobs.is_empty()) && grouped.plans.is_empty() {
        return Ticked::Delivered(0);
    }
    let jobs: u64 = grouped.groups.iter().map(|g| g.jobs.len() as u64).sum();
    let Some(submitted) = submit(state, &mut grouped.groups).await else {
        return Ticked::Skipped;
    };
    let work = FanOutWork {
        state: state.clone(),
        session: session.clone(),
        tick,
        heads,
        layout_rev,
        rigs: resolved.rigs,
        arrived,
        grouped,
        submitted,
        _bookkeeping: bookkeeping,
    };
    fanning.start(work).await;
    Ticked::Delivered(jobs)
}

/// A tick's fan-out, owned, so that it runs on a blocking thread while the next tick blends:
/// on two cores the engine and the encoding of messages (residual planes, compression) then
/// overlap instead of taking turns. It holds the tick's outputs and bookkeeping charges until
/// every message is in its outbox.
struct FanOutWork<S> {
    state: S,
    session: Arc<Session>,
    tick: u64,
    heads: Arc<Vec<SessionHead>>,
    layout_rev: u64,
    rigs: Vec<Arc<RigEntry>>,
    arrived: std::time::Instant,
    grouped: Grouped,
    submitted: Submitted,
    _bookkeeping: crate::admission::Charge,
}

impl<S: Ticking> FanOutWork<S> {
    fn run(self) {
        // Temporal viewers' references are by head id: collected once a tick for all of them.
        let head_ids: Vec<u64> = self.heads.iter().map(|h| h.head).collect();
        let tick_heads = TickHeads {
            tick: self.tick,
            heads: &self.heads,
            head_ids: &head_ids,
            layout_rev: self.layout_rev,
            rigs: &self.rigs,
            arrived: self.arrived,
        };
        fan_out(
            &self.state,
            &self.session,
            &tick_heads,
            &self.grouped,
            &self.submitted.outcomes,
        );
    }
}

/// The session's fan-out in flight: at most one, so that a viewer's messages are put in its
/// outbox in tick order ("unchanged" and residuals refer to the message before).
#[derive(Default)]
struct FanOuts(Option<tokio::task::JoinHandle<()>>);

impl FanOuts {
    /// Waits for the previous fan-out (a panic in it is the tick task's panic, so the
    /// supervisor ends the session), then starts `work`'s.
    async fn start<S: Ticking>(&mut self, work: FanOutWork<S>) {
        self.finish().await;
        self.0 = Some(tokio::task::spawn_blocking(move || work.run()));
    }

    /// Waits for the fan-out in flight, if any.
    async fn finish(&mut self) {
        if let Some(h) = self.0.take()
            && let Err(e) = h.await
            && e.is_panic()
        {
            std::panic::resume_unwind(e.into_panic());
        }
    }
}

/// Applies the patches received since the last tick (the layout changes at a tick, never
/// inside one) and takes what this tick works on: the heads, the layout's revision, the
/// viewers. `None` when the session's lock is poisoned.
fn take_heads(session: &Session, tick: u64) -> Option<TickInput> {
    let mut i = session.inner.lock().ok()?;
    if let Some(n) = i.next_heads.take() {
        i.heads = n;
        i.layout_rev += 1;
    }
    i.tick = tick;
    Some(TickInput {
        heads: i.heads.clone(),
        layout_rev: i.layout_rev,
        viewers: i.viewers.clone(),
        jumps: std::mem::take(&mut i.jumps),
    })
}

/// What a tick works on, taken under the session's lock.
struct TickInput {
    heads: Arc<Vec<SessionHead>>,
    layout_rev: u64,
    viewers: Vec<Arc<Viewer>>,
    /// Graph heads sent to a node since the last tick.
    jumps: Vec<(u64, String)>,
}

/// Every head of a tick resolved once: the rigs it names (at this tick's generation), and per
/// head its rig, clip and frame (`None`: its rig or clip is gone).
struct Resolved {
    rigs: Vec<Arc<RigEntry>>,
    at: Vec<Option<HeadAt>>,
    /// What the layered heads' resolved layers, final weights and joints hold this tick.
    _layered: Option<crate::admission::Charge>,
}

impl Resolved {
    /// The most joint sets the heads with overrides can hold merged with a LOD level's rest
    /// holds: their own plus the most nodes any level of their rig drops, summed. (Heads
    /// without overrides share each level's rest holds.)
    fn joint_sets(&self) -> usize {
        self.at
            .iter()
            .flatten()
            .filter(|a| !a.joints.is_none())
            .map(|a| {
                let dropped = self.rigs[a.rig as usize]
                    .joint_lod()
                    .dropped
                    .iter()
                    .map(Vec::len)
                    .max()
                    .unwrap_or(0);
                // The head's own (resolved from the session's heads, which the session limits
                // bound), and the merge.
                2 * a.joints.sets().len() + dropped
            })
            .sum()
    }
}

/// Resolve: each head's rig at this tick's generation and what it shows — its clip's frame,
/// or for a graph head the pose its player reaches this tick (jumps applied first).
fn resolve<S: Ticking>(
    state: &S,
    session: &Session,
    heads: &[SessionHead],
    tick: u64,
    players: &mut Players,
    jumps: Vec<(u64, String)>,
) -> Resolved {
    let mode = if session.wrap {
        FrameMode::Wrap
    } else {
        FrameMode::Clamp
    };
    let steps = players.steps_to(tick, session.fps);
    let mut jumps_by_head: HashMap<u64, Vec<String>> = HashMap::new();
    for (h, node) in jumps {
        jumps_by_head.entry(h).or_default().push(node);
    }
    let mut rigs: Vec<Arc<RigEntry>> = Vec::new();
    let mut rig_at: HashMap<&str, Option<u32>> = HashMap::new();
    let mut names: HashMap<u32, LiveNames> = HashMap::new();
    let mut layered: Option<crate::admission::Charge> = None;
    // Live heads' input, read once for every head (one lock of the producers' side).
    let live_now = if players.live_heads || heads.iter().any(|h| h.live.is_some()) {
        players.live_heads = heads.iter().any(|h| h.live.is_some());
        players.live.at(
            &session.live,
            heads,
            tick,
            session.fps,
            state.queue_memory(),
        )
    } else {
        HashMap::new()
    };
    let mut alive = AliveTick::new(session.alive(), tick, session.fps);
    let at = heads
        .iter()
        .map(|h| {
            let ri = *rig_at.entry(h.rig.as_str()).or_insert_with(|| {
                state.registry().get(&h.rig).map(|e| {
                    rigs.push(e);
                    (rigs.len() - 1) as u32
                })
            });
            let ri = ri?;
            let entry = &rigs[ri as usize];
            let rig = entry.rig();
            // Checked when the head was added or changed; a rig changed since then leaves out
            // a head whose overrides no longer fit it, as it does a head whose clip is gone.
            let requested = requested_joints(entry, &h.joints).ok()?;
            let own = requested.clone();
            let (pose, joints) = match &h.graph {
                // A graph head's player fades its overrides in, as it fades its jumps.
                Some(play) => {
                    let graph = state.graphs().resolved(
                        entry,
                        &play.name,
                        |bytes| state.queue_memory().reserve(bytes).ok(),
                        state.config().max_graph_work,
                    )?;
                    let jumps = jumps_by_head.remove(&h.head).unwrap_or_default();
                    players.pose(h.head, play, &graph, rig, &jumps, requested, steps)?
                }
                None if h.clip.is_empty() => {
                    (alive.neutral(state.queue_memory(), ri, rig)?, requested)
                }
                None => {
                    let ci = entry.clip_index(&h.clip)?;
                    let clip = &rig.clips[ci];
                    let elapsed = (tick - 1) as f64 * f64::from(clip.fps) / f64::from(session.fps);
                    let frame = clip
                        .resolve_frame(h.offset.saturating_add(elapsed as i64), mode)
                        .ok()?;
                    (
                        Pose::Frame {
                            clip: ci as u32,
                            frame,
                        },
                        requested,
                    )
                }
            };
            // Input of the rig's generation now (a rig changed since waits for new samples).
            let live = live_now
                .get(&h.head)
                .filter(|l| l.generation == entry.generation);
            let (pose, joints) = if h.layers.is_empty()
                && h.clamp.is_none()
                && live.is_none()
                && !alive.on(h)
            {
                (pose, joints)
            } else {
                // Checked when the head was added or changed, as its overrides are; charged
                // for the tick (its layers, the rig's names once, the final weights, joints).
                let mut bytes =
                    layers_bytes(rig, &h.layers) + 8 * (16 + 4 * rig.targets.len() as u64);
                if !names.contains_key(&ri) {
                    bytes += LiveNames::bytes(rig);
                }
                if let Some(sk) = &rig.skeleton {
                    bytes += layered_joints_bytes(sk);
                    if live.is_some() {
                        bytes += live_joints_bytes(sk.nodes.len());
                    }
                }
                let more = state.queue_memory().reserve(bytes).ok()?;
                match &mut layered {
                    Some(c) => c.merge(more),
                    None => layered = Some(more),
                }
                let names = names
                    .entry(ri)
                    .or_insert_with(|| live_names(state.registry(), entry));
                let layers = resolve_layers(entry, names, &h.layers, |clip, frame, reference| {
                    // A layer's frames play from the clock, as the head's offset does; its
                    // additive reference is a fixed frame.
                    let c = &rig.clips[clip as usize];
                    let elapsed = if reference {
                        0
                    } else {
                        ((tick - 1) as f64 * f64::from(c.fps) / f64::from(session.fps)) as i64
                    };
                    c.resolve_frame(frame.saturating_add(elapsed), mode)
                        .map_err(|e| ApiError::bad_request("frame_out_of_range", e.to_string()))
                })
                .ok()?;
                let mut w = pose.weights(rig);
                layer_weights(rig, &mut w, &layers);
                if alive.on(h) {
                    alive.weights(state.queue_memory(), ri, rig, h, &mut w)?;
                }
                // Live input on top of the layers and liveliness (a tracker's eyes over
                // procedural blinks), by its share while it fades in or out.
                if let Some(l) = live {
                    apply_weights(&mut w, &l.values, l.alpha);
                }
                // The clamp was checked when the head was added; a weight the layers carry
                // past ±64 at some frame is held there (as live weights are), the head kept.
                if let Some(c) = h.clamp {
                    clamp_weights(&mut w, c);
                }
                // The head's own overrides stay on top of its layers' joints, live input on
                // top of both.
                let joints = layered_joints(entry, &pose, &joints, &layers).overlay(&own);
                let joints = alive.joints(state.queue_memory(), ri, entry, h, joints)?;
                let joints = match live {
                    Some(l) => live_joints(entry, &joints, &l.values, l.alpha),
                    None => joints,
                };
                (Pose::live(&w), joints)
            };
            Some(HeadAt {
                rig: ri,
                pose,
                joints,
                levels: rig.lod.levels.len() as u32,
                f16_ok: head_reach(entry) <= MAX_F16,
            })
        })
        .collect();
    players.keep(heads);
    Resolved {
        rigs,
        at,
        _layered: alive.charge_into(layered),
    }
}

/// The graph heads of one session, each with the player that walks its graph, and its live
/// heads' fades and filters, owned by the session's tick task.
#[derive(Default)]
pub(super) struct Players {
    by_head: HashMap<u64, PlayerOf>,
    /// The tick the players last advanced to.
    tick: u64,
    /// What the live heads showed.
    live: crate::live::LiveShown,
    /// Whether the last tick had live heads (their state is forgotten once none is left).
    live_heads: bool,
}

struct PlayerOf {
    play: crowdmorph_proto::GraphPlay,
    graph: Arc<Graph>,
    player: Player,
}

impl Players {
    /// Seconds to advance each player by, once per tick since the last (a skipped tick still
    /// moves the graph heads, as it moves every clip head); at most ten seconds' worth.
    fn steps_to(&mut self, tick: u64, fps: f32) -> (u64, f64) {
        let n = tick.saturating_sub(self.tick).max(1);
        self.tick = tick;
        let limit = (10.0 * f64::from(fps)).ceil().max(1.0) as u64;
        (n.min(limit), 1.0 / f64::from(fps.max(MIN_FPS)))
    }

    /// Head `id`'s pose after this tick, and its joint overrides (`Player::joints`: the head's
    /// own, or while a jump or a change of them fades, every node's faded transform): its
    /// player (new if the head is new, its play changed or its graph was replaced), given
    /// the head's `requested` overrides, sent through `jumps`, advanced `steps`.
    #[allow(clippy::too_many_arguments)]
    fn pose(
        &mut self,
        id: u64,
        play: &crowdmorph_proto::GraphPlay,
        graph: &Arc<Graph>,
        rig: &crowdmorph_core::rig::Rig,
        jumps: &[String],
        requested: JointPose,
        (steps, dt): (u64, f64),
    ) -> Option<(Pose, JointPose)> {
        let same_graph = |p: &PlayerOf| {
            Arc::ptr_eq(&p.graph, graph)
                || (p.graph.nodes.len() == graph.nodes.len()
                    && p.graph
                        .nodes
                        .iter()
                        .zip(&graph.nodes)
                        .all(|(a, b)| a.name == b.name))
        };
        let fresh = match self.by_head.get(&id) {
            Some(p) => p.play != *play || !same_graph(p),
            None => true,
        };
        if fresh {
            let (start, script, seed) = graph.play(play).ok()?;
            self.by_head.insert(
                id,
                PlayerOf {
                    play: play.clone(),
                    graph: graph.clone(),
                    player: Player::new(graph, start, script, seed)
                        .with_overrides(requested.clone()),
                },
            );
        }
        let p = self.by_head.get_mut(&id)?;
        p.graph = graph.clone();
        // Before the jumps: a patch that changes both fades once, from the pose shown with
        // the old overrides to the node with the new ones.
        p.player.set_overrides(graph, rig, requested);
        for node in jumps {
            if let Some(n) = graph.node(node) {
                p.player.jump(graph, rig, n);
            }
        }
        for _ in 0..steps {
            p.player.advance(graph, rig, dt);
        }
        Some((p.player.pose(graph, rig), p.player.joints(graph, rig)))
    }

    /// Forgets the players of heads no longer in the session.
    fn keep(&mut self, heads: &[SessionHead]) {
        if self.by_head.len() > heads.iter().filter(|h| h.graph.is_some()).count() {
            let ids: std::collections::HashSet<u64> = heads.iter().map(|h| h.head).collect();
            self.by_head.retain(|id, _| ids.contains(id));
        }
    }
}

/// The viewers of a tick sorted by what they get: vertex viewers' jobs per head, grouped by
/// format and normals, and the image viewers with their settings.
struct Grouped {
    groups: Vec<Group>,
    /// Per vertex viewer: its group and its job (an index into the group's) per head.
    plans: Vec<(Arc<Viewer>, usize, Vec<Option<u32>>)>,
    frames: Vec<(Arc<Viewer>, ViewerSettings)>,
    /// The viewers that blend themselves ([`poses`]).
    poses: Vec<(Arc<Viewer>, ViewerSettings)>,
}

/// Group: each vertex viewer's job per head (its LOD fixed or by distance from its camera),
/// deduplicated within the group of viewers that share a format and normals.
fn group(resolved: &Resolved, heads: &[SessionHead], viewers: &[Arc<Viewer>]) -> Grouped {
    let mut groups: Vec<Group> = Vec::new();
    let mut plans = Vec::new();
    let mut frames = Vec::new();
    let mut poses = Vec::new();
    for v in viewers {
        let Some(s) = v.settings() else { continue };
        if s.output == ViewerOutput::Frames {
            frames.push((v.clone(), s));
            continue;
        }
        if s.output == ViewerOutput::Weights {
            poses.push((v.clone(), s));
            continue;
        }
        let g = match groups
            .iter()
            .position(|g| g.format == s.format && g.normals == s.normals)
        {
            Some(g) => g,
            None => {
                groups.push(Group {
                    format: s.format,
                    normals: s.normals,
                    jobs: Vec::new(),
                    keys: Vec::new(),
                    index: HashMap::new(),
                });
                groups.len() - 1
            }
        };
        let jobs = groups[g].jobs_of(resolved, heads, &s);
        plans.push((v.clone(), g, jobs));
    }
    Grouped {
        groups,
        plans,
        frames,
        poses,
    }
}

impl Group {
    /// A viewer's job per head in this group, adding the jobs the group does not have yet.
    fn jobs_of(
        &mut self,
        resolved: &Resolved,
        heads: &[SessionHead],
        s: &ViewerSettings,
    ) -> Vec<Option<u32>> {
        let eye = s.camera.as_ref().and_then(|c| c.position);
        if let Some(eye) = eye.filter(|_| s.tolerance > 0.0) {
            return self.near_jobs_of(resolved, heads, s, Vec3::from(eye));
        }
        heads
            .iter()
            .zip(&resolved.at)
            .map(|(h, a)| {
                let a = a.as_ref()?;
                if self.format == Format::F16 && !a.f16_ok {
                    return None;
                }
                let lod = level_for(&s.lod, s.camera.as_ref(), h.position).min(a.levels - 1);
                let entry = &resolved.rigs[a.rig as usize];
                let joints = entry.joint_lod().level(lod).joints(&a.joints);
                let key = (a.rig, a.pose.clone(), lod, joints);
                if let Some(&j) = self.index.get(&key) {
                    return Some(j);
                }
                self.jobs.push(job_request(entry, &a.pose, lod, &key.3));
                self.keys.push(key.clone());
                let j = (self.jobs.len() - 1) as u32;
                self.index.insert(key, j);
                Some(j)
            })
            .collect()
    }
}

impl Group {
    /// [`Group::jobs_of`] for a viewer with a near-clone `tolerance`: a head `d` metres from
    /// the eye may be off by `tolerance × d` diagonals (at most `MAX_NEAR_TOLERANCE`). Heads
    /// with the same exact job (exact clones) take the smallest of their errors, so that they
    /// stay one job; each exact job is then rounded once (`RigEntry::near_clone`) and keyed
    /// by its rounded weights, which other heads and other viewers of the group share where
    /// they agree. The memory is charged by [`near_clone_bytes`].
    fn near_jobs_of(
        &mut self,
        resolved: &Resolved,
        heads: &[SessionHead],
        s: &ViewerSettings,
        eye: Vec3,
    ) -> Vec<Option<u32>> {
        let max = f64::from(crowdmorph_core::rig::MAX_NEAR_TOLERANCE);
        // Pass 1: each head's exact key and error; per exact key the smallest error.
        let mut exact: Vec<Option<(Key, f64)>> = Vec::with_capacity(heads.len());
        let mut smallest: HashMap<Key, f64> = HashMap::new();
        for (h, a) in heads.iter().zip(&resolved.at) {
            let Some(a) = a.as_ref() else {
                exact.push(None);
                continue;
            };
            if self.format == Format::F16 && !a.f16_ok {
                exact.push(None);
                continue;
            }
            let lod = level_for(&s.lod, s.camera.as_ref(), h.position).min(a.levels - 1);
            let entry = &resolved.rigs[a.rig as usize];
            let joints = entry.joint_lod().level(lod).joints(&a.joints);
            let d = f64::from(Vec3::from(h.position).distance(eye));
            let e = (f64::from(s.tolerance) * d).min(max);
            let key = (a.rig, a.pose.clone(), lod, joints);
            smallest
                .entry(key.clone())
                .and_modify(|m| *m = m.min(e))
                .or_insert(e);
            exact.push(Some((key, e)));
        }
        // Pass 2: each exact key rounded once, then keyed by what it rounds to.
        let mut near: HashMap<Key, u32> = HashMap::with_capacity(smallest.len());
        exact
            .into_iter()
            .map(|k| {
                let (key, _) = k?;
                if let Some(&j) = near.get(&key) {
                    return Some(j);
                }
                let e = smallest.get(&key).copied().unwrap_or(0.0);
                let entry = &resolved.rigs[key.0 as usize];
                let pose = entry
                    .near_clone(&key.1, key.2, e)
                    .unwrap_or_else(|| key.1.clone());
                let rounded = (key.0, pose, key.2, key.3.clone());
                let j = match self.index.get(&rounded) {
                    Some(&j) => j,
                    None => {
                        self.jobs
                            .push(job_request(entry, &rounded.1, rounded.2, &rounded.3));
                        self.keys.push(rounded.clone());
                        let j = (self.jobs.len() - 1) as u32;
                        self.index.insert(rounded, j);
                        j
                    }
                };
                near.insert(key, j);
                Some(j)
            })
            .collect()
    }
}

/// Bytes [`Group::near_jobs_of`] holds for a tick beyond [`tick_bookkeeping_bytes`], for
/// `viewers` viewers with a tolerance: per head its exact key and error and two map entries,
/// and per head at most one rounded pose (a weight per channel of its rig), kept by the
/// group's keys and, until the next tick, the viewer's baseline (so twice).
fn near_clone_bytes(heads: usize, viewers: usize, channels: usize) -> u64 {
    let per_head = size_of::<Option<(Key, f64)>>()
        + 2 * (size_of::<Key>() + size_of::<f64>() + 8)
        + 2 * (16 + 4 * channels);
    (heads as u64)
        .saturating_mul(viewers as u64)
        .saturating_mul(per_head as u64)
}

/// What [`submit`] got back: each group's outcome, and the queue memory their outputs hold.
struct Submitted {
    outcomes: Vec<crate::scheduler::Outcome>,
    _memory: crate::admission::Charge,
}

/// Submit: the blended outputs charged to the queue memory, then one submission per group to
/// the batcher (so session jobs coalesce with HTTP traffic), waited for within the request
/// deadline. `None`: the tick is skipped (memory or queue full, a deadline, shutting down).
async fn submit<S: Ticking>(state: &S, groups: &mut [Group]) -> Option<Submitted> {
    let gpu = state.engine().gpu_memory().is_some();
    let out_bytes: u64 = groups
        .iter()
        .flat_map(|g| {
            g.jobs.iter().map(move |j| {
                let rig = j.entry.prepared.at_level(j.lod).rig();
                job_output_bytes(rig, g.format, g.normals, false, gpu)
            })
        })
        .sum();
    let memory = state.queue_memory().reserve(out_bytes).ok()?;
    let mut tickets = Vec::with_capacity(groups.len());
    for g in groups {
        state.metrics().jobs_requested.inc_by(g.jobs.len() as u64);
        // Moved, not cloned: the fan-out reads the plans, not the jobs.
        match state
            .scheduler()
            .submit(std::mem::take(&mut g.jobs), g.format, g.normals)
        {
            Ok(t) => tickets.push(t),
            Err(ScheduleError::QueueFull) => {
                state.metrics().reject("queue_full");
                return None;
            }
            Err(_) => return None,
        }
    }
    let mut outcomes = Vec::with_capacity(tickets.len());
    for t in tickets {
        match tokio::time::timeout(state.config().request_timeout, t).await {
            Ok(Ok(Ok(o))) => outcomes.push(o),
            _ => return None,
        }
    }
    Some(Submitted {
        outcomes,
        _memory: memory,
    })
}

/// What every viewer's message of a tick shares.
struct TickHeads<'a> {
    tick: u64,
    heads: &'a [SessionHead],
    /// Each head's id, in order.
    head_ids: &'a [u64],
    layout_rev: u64,
    rigs: &'a [Arc<RigEntry>],
    arrived: std::time::Instant,
}

/// Fan out: each vertex viewer gets the buffers of the heads whose job changed since the last
/// message it received (the others "unchanged"); identical messages (same group, same head
/// vector) are encoded once and shared. Viewers are planned one by one (their references are
/// shared copies), then their distinct messages are encoded on every core — with several
/// temporal or compressed viewers, that encoding is most of a tick's work — and put in the
/// outboxes in viewer order.
fn fan_out<S: Ticking>(
    state: &S,
    session: &Session,
    t: &TickHeads<'_>,
    grouped: &Grouped,
    outcomes: &[crate::scheduler::Outcome],
) {
    let mut cache = Caches::default();
    let mut viewers = Vec::with_capacity(grouped.plans.len());
    for (v, g, jobs) in &grouped.plans {
        let group = &grouped.groups[*g];
        let keys = Arc::new(head_keys(group, jobs, t.rigs));
        let target = Target {
            viewer: v,
            group: (*g, group),
            outcome: &outcomes[*g],
            jobs,
            keys,
        };
        let first = prepare(state, session, t, &target, &mut cache);
        viewers.push((target, first));
    }
    // Each distinct message once, in parallel.
    let mut distinct: Vec<(&Target<'_>, &Prepared)> = Vec::new();
    let mut seen = std::collections::HashSet::new();
    for (target, p) in &viewers {
        if let Some(p) = p
            && !cache.messages.contains_key(&p.key)
            && seen.insert(&p.key)
        {
            distinct.push((target, p));
        }
    }
    let encoded: Vec<Option<Arc<Encoded>>> = distinct
        .par_iter()
        .map(|(target, p)| encode(state, t, target, p).map(Arc::new))
        .collect();
    for ((_, p), m) in distinct.iter().zip(encoded) {
        if let Some(m) = m {
            cache.messages.insert(p.key.clone(), m);
        }
    }
    for (target, first) in viewers {
        deliver(state, session, t, &target, first, &mut cache);
    }
}

/// One vertex viewer of a tick: its group, that group's outcome, its job per head and the key
/// of each head's buffer.
struct Target<'a> {
    viewer: &'a Arc<Viewer>,
    group: (usize, &'a Group),
    outcome: &'a crate::scheduler::Outcome,
    jobs: &'a [Option<u32>],
    keys: Arc<Vec<HeadKey>>,
}

/// A viewer's message planned against the baseline it had when planned.
struct Prepared {
    settings: ViewerSettings,
    base: Baseline,
    plan: Option<delta::DeltaPlan>,
    key: MessageKey,
    /// For a viewer that asked for `layers`: the tick's layer message (`None`: no head's inputs
    /// changed) and what the viewer will have received once it is sent.
    layers: Option<(Option<Encoded>, Arc<SentLayers>)>,
}

/// Plans a viewer's message against what its socket last took: each head's entry, and for a
/// temporal viewer what each buffer is coded against. `None` when the viewer is gone or its
/// plan did not fit the queue memory (counted as a dropped message).
fn prepare<S: Ticking>(
    state: &S,
    session: &Session,
    t: &TickHeads<'_>,
    target: &Target<'_>,
    cache: &mut Caches,
) -> Option<Prepared> {
    let settings = target.viewer.settings()?;
    let base = target.viewer.outbox.lock().ok()?.sent.clone();
    let keys = &target.keys;
    let with_layout = base.layout_rev != t.layout_rev || base.keys.len() != keys.len();
    let entries: Vec<u32> = target
        .jobs
        .iter()
        .enumerate()
        .map(|(i, j)| match j {
            _ if !with_layout && base.keys[i] == keys[i] => HEAD_UNCHANGED,
            None => HEAD_MISSING,
            Some(j) => *j,
        })
        .collect();
    let (g, _) = target.group;
    let plan = match settings.temporal {
        None => None,
        Some(every) => {
            let input = delta::PlanInput {
                tick: t.tick,
                head_ids: t.head_ids,
                entries: &entries,
                keys,
                every,
                group: g,
                outputs: &target.outcome.outputs,
            };
            match delta::plan(state.queue_memory(), &base, &input, &mut cache.retained) {
                Some(p) => Some(p),
                None => {
                    dropped_memory(state, session);
                    return None;
                }
            }
        }
    };
    let layers = if settings.layers {
        let Some(l) = plan_layers(state, t, target, &base, cache, settings.compression) else {
            dropped_memory(state, session);
            return None;
        };
        Some(l)
    } else {
        None
    };
    let key = MessageKey {
        group: g,
        with_layout,
        entries,
        bases: plan.as_ref().map(|p| p.bases.clone()),
        compression: settings.compression,
    };
    Some(Prepared {
        settings,
        base,
        plan,
        key,
        layers,
    })
}

/// A layers viewer's [`crowdmorph_proto::TickLayers`]: the compact layer inputs of each head
/// whose rig has layers and whose inputs differ from what the viewer last received (`None`
/// when none do: a rig without layers, or a still head, costs nothing), and the viewer's
/// record of what it has once the message is sent. Each job's inputs are computed once per
/// tick and shared by its heads and viewers. `None`: out of queue memory.
fn plan_layers<S: Ticking>(
    state: &S,
    t: &TickHeads<'_>,
    target: &Target<'_>,
    base: &Baseline,
    cache: &mut Caches,
    compression: Option<MessageEncoding>,
) -> Option<(Option<Encoded>, Arc<SentLayers>)> {
    let (g, group) = target.group;
    // Per head with layers: its entry in the record and its inputs (held by the record), and
    // while a job's inputs are computed, its full `layer_inputs`: charged first.
    let mut bytes = 0u64;
    for j in target.jobs.iter().flatten() {
        let r = group.keys[*j as usize].0;
        let (indices, full) = cache.rig_layers(t.rigs, r);
        if !indices.is_empty() {
            bytes += 4 * (indices.len() + full) as u64 + 64;
        }
    }
    if bytes == 0 {
        let unchanged = base.layers.inputs.is_empty();
        return Some((
            None,
            if unchanged {
                base.layers.clone()
            } else {
                Arc::default()
            },
        ));
    }
    let memory = state.queue_memory().reserve(bytes).ok()?;
    let mut inputs = HashMap::with_capacity(target.jobs.len());
    let mut changed: Vec<(u64, Arc<[f32]>)> = Vec::new();
    for (i, job) in target.jobs.iter().enumerate() {
        let Some(j) = *job else { continue };
        let Some(v) = cache.job_layers(t.rigs, g, group, j) else {
            continue;
        };
        let head = t.head_ids[i];
        if base.layers.inputs.get(&head) != Some(&v) {
            changed.push((head, v.clone()));
        }
        inputs.insert(head, v);
    }
    if changed.is_empty() && inputs.len() == base.layers.inputs.len() {
        return Some((None, base.layers.clone()));
    }
    let message = if changed.is_empty() {
        None
    } else {
        Some(encode_layers(
            state.queue_memory(),
            t.tick,
            &changed,
            compression,
        )?)
    };
    let sent = SentLayers {
        inputs,
        _memory: Some(memory),
    };
    Some((message, Arc::new(sent)))
}

/// Encodes a prepared message. `None`: out of queue memory.
fn encode<S: Ticking>(
    state: &S,
    t: &TickHeads<'_>,
    target: &Target<'_>,
    p: &Prepared,
) -> Option<Encoded> {
    let content = MessageContent {
        tick: t.tick,
        layout: p.key.with_layout.then_some(t.heads),
        keys: &target.group.1.keys,
        format: target.group.1.format,
        normals: target.group.1.normals,
        outcome: target.outcome,
        rigs: t.rigs,
        heads: t.heads,
        entries: &p.key.entries,
        arrived: t.arrived,
    };
    match &p.plan {
        None => encode_vertices(state.queue_memory(), &content, p.settings.compression),
        Some(plan) => encode_delta(state.queue_memory(), &content, plan, p.settings.compression),
    }
}

fn dropped_memory<S: Ticking>(state: &S, session: &Session) {
    bump(&state.sessions().metrics.dropped_memory, 1);
    session.with_stats(|s| s.messages_dropped += 1);
}

/// What identifies a viewer's message within a tick: the same key, the same bytes.
#[derive(Clone, PartialEq, Eq, Hash)]
struct MessageKey {
    group: usize,
    with_layout: bool,
    entries: Vec<u32>,
    /// Temporal viewers: per head, what its buffer is coded against.
    bases: Option<delta::Bases>,
    compression: Option<MessageEncoding>,
}

/// The fan-out's shared work: messages encoded once per key, references copied once per job,
/// layer inputs computed once per job.
#[derive(Default)]
struct Caches {
    messages: HashMap<MessageKey, Arc<Encoded>>,
    retained: delta::RetainedCache,
    /// Per rig of the tick: the `layer_inputs` entries its layers read, and that vector's
    /// length.
    rig_layers: HashMap<u32, (Arc<[u32]>, usize)>,
    /// Per (group, job): its compact layer inputs, `None` for a rig without layers.
    job_layers: HashMap<(usize, u32), Option<Arc<[f32]>>>,
}

impl Caches {
    /// Rig `r`'s layer input indices and the length of its `layer_inputs`.
    fn rig_layers(&mut self, rigs: &[Arc<RigEntry>], r: u32) -> (Arc<[u32]>, usize) {
        self.rig_layers
            .entry(r)
            .or_insert_with(|| {
                let rig = rigs[r as usize].prepared.rig();
                let indices = crowdmorph_engine::render::appearance::layer_input_indices(rig);
                let clips = rig.appearance.as_deref().map_or(0, |a| {
                    a.clip_textures
                        .iter()
                        .map(|c| 1 + c.layers())
                        .sum::<usize>()
                });
                (indices.into(), rig.targets.len() + clips)
            })
            .clone()
    }

    /// Job `j` of group `g`'s compact layer inputs (`None`: its rig has no layers).
    fn job_layers(
        &mut self,
        rigs: &[Arc<RigEntry>],
        g: usize,
        group: &Group,
        j: u32,
    ) -> Option<Arc<[f32]>> {
        if let Some(v) = self.job_layers.get(&(g, j)) {
            return v.clone();
        }
        let (r, pose, lod, _) = &group.keys[j as usize];
        let (indices, _) = self.rig_layers(rigs, *r);
        let v = (!indices.is_empty()).then(|| {
            let all =
                crowdmorph_core::rig::layer_inputs(rigs[*r as usize].prepared.rig(), pose, *lod);
            indices
                .iter()
                .map(|&k| all.get(k as usize).copied().unwrap_or(0.0))
                .collect::<Arc<[f32]>>()
        });
        self.job_layers.insert((g, j), v.clone());
        v
    }
}

/// Each head's key for a viewer (what its buffer is: rig generation, clip, frame, LOD).
fn head_keys(group: &Group, jobs: &[Option<u32>], rigs: &[Arc<RigEntry>]) -> Vec<HeadKey> {
    jobs.iter()
        .map(|j| match j {
            None => MISSING_KEY,
            Some(j) => {
                let (r, pose, l, joints) = &group.keys[*j as usize];
                HeadKey {
                    generation: rigs[*r as usize].generation,
                    pose: pose.clone(),
                    lod: *l,
                    joints: joints.clone(),
                }
            }
        })
        .collect()
}

/// Puts one viewer's message in its outbox: its entries relative to what it last received,
/// the message from `cache` (encoded by the fan-out, or here when another viewer did not
/// need the same one). Planned again when the viewer's socket took a message since `first`
/// was planned: "unchanged" must refer to what it last received.
fn deliver<S: Ticking>(
    state: &S,
    session: &Session,
    t: &TickHeads<'_>,
    target: &Target<'_>,
    first: Option<Prepared>,
    cache: &mut Caches,
) {
    let mut next = first;
    for _attempt in 0..4 {
        let Some(p) = next.take() else { return };
        let message = match cache.messages.get(&p.key) {
            Some(m) => m.clone(),
            None => {
                let Some(m) = encode(state, t, target, &p) else {
                    return dropped_memory(state, session);
                };
                let m = Arc::new(m);
                cache.messages.insert(p.key.clone(), m.clone());
                m
            }
        };
        let Ok(mut o) = target.viewer.outbox.lock() else {
            return;
        };
        if o.sent.version != p.base.version {
            drop(o);
            next = prepare(state, session, t, target, cache);
            continue;
        }
        if o.pending.is_some() {
            bump(&state.sessions().metrics.dropped_slow, 1);
            session.with_stats(|s| s.messages_dropped += 1);
        }
        let (layers, sent_layers) = match p.layers {
            Some((m, sent)) => (m, sent),
            None => (None, p.base.layers.clone()),
        };
        o.pending = Some(Outgoing {
            layers,
            message,
            after: Baseline {
                version: p.base.version + 1,
                layout_rev: t.layout_rev,
                keys: target.keys.clone(),
                prev: p
                    .plan
                    .map_or_else(|| p.base.prev.clone(), |plan| plan.after),
                layers: sent_layers,
            },
        });
        drop(o);
        target.viewer.ready.notify_one();
        return;
    }
}

/// Starts drawing this tick for a viewer that wants images, unless its previous image is
/// still being drawn.
#[allow(clippy::too_many_arguments)]
fn start_frame<S: Ticking>(
    state: &S,
    session: &Arc<Session>,
    heads: &[SessionHead],
    resolved: &Resolved,
    tick: u64,
    viewer: Arc<Viewer>,
    s: ViewerSettings,
) {
    if viewer.rendering.swap(true, Ordering::AcqRel) {
        bump(&state.sessions().metrics.dropped_rendering, 1);
        session.with_stats(|st| st.messages_dropped += 1);
        return;
    }
    let req = frame_request(heads, resolved, &s);
    let state = state.clone();
    let session = session.clone();
    let cancel = viewer
        .gone
        .with_deadline(std::time::Instant::now() + state.config().request_timeout);
    tokio::spawn(async move {
        let rendered = state.render_for_session(req, cancel).await;
        if let Some(message) = frame_message(&state, &viewer, tick, rendered) {
            put_frame(&state, &session, &viewer, message);
        }
        viewer.rendering.store(false, Ordering::Release);
    });
}

/// The request that draws a tick for a viewer: every resolved head at its LOD for the
/// viewer's camera, in its placement.
fn frame_request(heads: &[SessionHead], resolved: &Resolved, s: &ViewerSettings) -> RenderRequest {
    let mut req_heads = Vec::new();
    let mut placements = Vec::new();
    for (h, a) in heads.iter().zip(&resolved.at) {
        let Some(a) = a else { continue };
        let entry = &resolved.rigs[a.rig as usize];
        let lod = level_for(&s.lod, s.camera.as_ref(), h.position).min(a.levels - 1);
        req_heads.push(crowdmorph_proto::Head {
            head: h.head,
            rig: entry.id.clone(),
            lod,
            joints: joint_overrides(entry.rig(), &a.joints),
            ..pose_head(entry.rig(), &a.pose)
        });
        placements.push(crate::sessions::placement(h));
    }
    RenderRequest {
        heads: req_heads,
        wrap: true,
        placements: Some(placements),
        camera: s.camera,
        image: Some(s.image),
    }
}

/// A head of a render request that shows `pose`: a clip frame, a blend (its first term as
/// the base, the others as layers: the same canonical blend), or live weights by name (each
/// name takes its first channel's weight: a rig with split targets draws them alike).
fn pose_head(rig: &crowdmorph_core::rig::Rig, pose: &Pose) -> crowdmorph_proto::Head {
    let name = |c: u32| rig.clips[c as usize].name.clone();
    match pose {
        Pose::Frame { clip, frame } => crowdmorph_proto::Head {
            clip: name(*clip),
            frame: i64::from(*frame),
            ..Default::default()
        },
        Pose::Blend(terms) => crowdmorph_proto::Head {
            clip: name(terms[0].clip),
            frame: i64::from(terms[0].frame),
            blend: terms[1..]
                .iter()
                .map(|t| crowdmorph_proto::BlendLayer {
                    clip: name(t.clip),
                    frame: i64::from(t.frame),
                    t: t.fraction(),
                })
                .collect(),
            ..Default::default()
        },
        Pose::Live(q) => {
            let index = rig.target_index();
            let dense = rig
                .target_names()
                .iter()
                .map(|n| {
                    index.ids(n).first().map_or(0.0, |&c| {
                        q[c as usize] as f32 * crowdmorph_core::rig::LIVE_STEP
                    })
                })
                .collect();
            crowdmorph_proto::Head {
                weights: Some(Box::new(crowdmorph_proto::LiveWeights::Dense(dense))),
                ..Default::default()
            }
        }
    }
}

/// A drawn image as a stream message, charged to the queue memory (its length is known
/// without encoding it); `None` when it was not drawn or does not fit. An image the viewer's
/// own choice can never draw (over the viewers' share, too costly at its size) closes the
/// viewer with the reason, once, rather than failing at every tick.
fn frame_message<S: Ticking>(
    state: &S,
    viewer: &Viewer,
    tick: u64,
    rendered: Result<(Vec<u8>, u32, u32, crowdmorph_proto::ImageFormat), ApiError>,
) -> Option<Arc<Encoded>> {
    match rendered {
        Ok((image, width, height, format)) => {
            let message = crowdmorph_proto::StreamMessage::Frame(crowdmorph_proto::TickFrame {
                tick,
                format,
                width,
                height,
                image: crowdmorph_proto::Blob(image),
            });
            let len = crowdmorph_store::codec::wire_len(&message).ok()?;
            let Ok(charge) = state.queue_memory().reserve(len as u64) else {
                bump(&state.sessions().metrics.dropped_memory, 1);
                return None;
            };
            crowdmorph_store::codec::to_wire(&message)
                .ok()
                .map(|bytes| {
                    Arc::new(Encoded {
                        bytes: Bytes::from(bytes),
                        _memory: Box::new(charge),
                    })
                })
        }
        Err(e) if e.status.is_client_error() => {
            tracing::debug!(error = %e.message, "session frame cannot be drawn; closing the viewer");
            bump(&state.sessions().metrics.viewers_closed_policy, 1);
            viewer.ask_close(close::POLICY, &close::truncate(e.message));
            None
        }
        Err(e) => {
            // Busy (503), cancelled: this tick's image is skipped.
            tracing::debug!(error = %e.message, "session frame not drawn");
            bump(&state.sessions().metrics.dropped_rendering, 1);
            None
        }
    }
}

/// Puts an image message in the viewer's outbox (replacing an unsent one, counted).
fn put_frame<S: Ticking>(state: &S, session: &Session, viewer: &Viewer, message: Arc<Encoded>) {
    let Ok(mut o) = viewer.outbox.lock() else {
        return;
    };
    if o.pending.is_some() {
        bump(&state.sessions().metrics.dropped_slow, 1);
        session.with_stats(|st| st.messages_dropped += 1);
    }
    let after = Baseline {
        version: o.sent.version + 1,
        ..Baseline::empty()
    };
    o.pending = Some(Outgoing {
        layers: None,
        message,
        after,
    });
    drop(o);
    viewer.ready.notify_one();
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The linear search `level_at` replaced: the last entry whose metres ≤ `d`.
    fn level_by_scan(by_distance: &[[f32; 2]], d: f32) -> u32 {
        by_distance
            .iter()
            .rev()
            .find(|[m, _]| *m <= d)
            .map_or(0, |[_, l]| *l as u32)
    }

    #[test]
    fn the_binary_search_finds_the_level_the_scan_did() {
        let tables: Vec<Vec<[f32; 2]>> = vec![
            vec![],
            vec![[5.0, 3.0]],
            vec![[0.0, 1.0], [2.0, 2.0], [4.0, 3.0]],
            // Repeated thresholds: the last of them counts, as the scan's.
            vec![[1.0, 1.0], [3.0, 2.0], [3.0, 5.0], [3.0, 4.0], [6.0, 6.0]],
            // Negative thresholds, and the 64 entries `check_lod` allows.
            vec![[-2.0, 7.0], [-1.0, 0.0], [10.0, 2.0]],
            (0..64).map(|k| [k as f32 * 0.5, (k % 7) as f32]).collect(),
        ];
        for table in &tables {
            assert!(
                crate::sessions::check_lod(&LodChoice::ByDistance {
                    by_distance: table.clone()
                })
                .is_ok(),
                "{table:?} is a table viewers may send"
            );
            // On every threshold, just either side of it, between, below and above them all.
            let mut ds = vec![-1e30, -3.0, 0.0, 1e30, f32::INFINITY, f32::NAN];
            for [m, _] in table {
                ds.extend([*m, m.next_down(), m.next_up(), m + 0.25]);
            }
            for d in ds {
                assert_eq!(
                    level_at(table, d),
                    level_by_scan(table, d),
                    "{table:?} at {d}"
                );
            }
        }
        // Spot values, so the test does not only compare two searches with each other.
        let t = &tables[3];
        assert_eq!(
            [0.5, 1.0, 2.9, 3.0, 5.0, 6.0, 9.0].map(|d| level_at(t, d)),
            [0, 1, 1, 4, 4, 6, 6]
        );
        let camera = CameraSpec::looking([0.0, 0.0, 10.0], [0.0; 3]);
        let lod = LodChoice::ByDistance {
            by_distance: t.clone(),
        };
        assert_eq!(level_for(&lod, Some(&camera), [0.0, 0.0, 7.0]), 4);
        assert_eq!(level_for(&lod, None, [0.0, 0.0, 7.0]), 0);
        let framing = CameraSpec::framing(crowdmorph_proto::CameraFrame::Faces);
        assert_eq!(level_for(&lod, Some(&framing), [0.0, 0.0, 7.0]), 0);
        assert_eq!(level_for(&LodChoice::Fixed(3), Some(&camera), [0.0; 3]), 3);
    }
}
