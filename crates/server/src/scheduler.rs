//! The dynamic batcher: every crowd request's unique jobs go through one queue, identical jobs
//! of different requests are computed once, and the engine sees one evaluation per rig (and
//! output kind) per batch.
//!
//! Shape (after mini-redis and the usual actor pattern): one tokio task owns all scheduling
//! state — no locks — and talks to a single dedicated compute thread over channels, so the
//! engine's synchronous, rayon-parallel `evaluate` never runs on a tokio worker.
//!
//! - A request is split into *slots*, one per unique job, keyed by rig generation, pose (a
//!   clip frame, a blend or live weights), LOD, wire format and normals. A job whose key is already queued or computing joins that
//!   slot (it is *coalesced*); otherwise a new slot goes to the back of the pending queue.
//! - When the engine is idle, pending work is dispatched at once: a lone request is never held
//!   for a batch delay (as the best dynamic batchers do; the old timer-only rule made a
//!   1-head request wait ≈ 2 ms, tokio's timer granularity, for ≈ 0.3 ms of compute). While
//!   the engine is busy, pending work accumulates, so batches grow with load; when it has room
//!   again (on the GPU, a second batch while one computes) a batch is closed as soon as the
//!   pending cost (vertices × (active shapes + 1) per job) reaches `batch_cost`, or the oldest
//!   pending job has waited `batch_delay`. `hold_when_idle` restores the timer-only rule.
//! - Two priority classes. Client requests are [`Priority::Normal`]; synthetic load
//!   (`POST /v1/loadtest`) is [`Priority::Low`]: its slots wait in a queue of their own that is
//!   dispatched only when no normal work is waiting and the engine is idle, and a batch holds
//!   one class only. So a client request waits behind at most the one low batch already
//!   computing, never behind queued synthetic work. A normal job that coalesces with a queued
//!   low slot promotes it to the normal queue.
//! - Room is one batch on the CPU engine, three on the GPU: the compute thread submits every
//!   batch it has to the GPU before it waits for the oldest, so upload, compute and readback of
//!   consecutive batches overlap and the device has work queued while the host copies a
//!   finished batch out (the GPU engine's pooled slots are the ring of buffers).
//! - A slot whose waiting requests have all gone (client disconnected, deadline passed) is
//!   dropped before it is computed; a slot that some live request still needs is computed even
//!   if others gave up on it, so a client that disconnects never cancels shared work.
//! - Results are shared, never copied: positions and normals are [`Bytes`] views of the
//!   engine's output buffer, which lives as long as any response still sends part of it.

use std::collections::{HashMap, VecDeque};
use std::sync::Arc;
use std::time::{Duration, Instant};

use bytes::Bytes;
use crowdmorph_proto::Format;
use tokio::sync::{mpsc, oneshot};

use super::metrics::Metrics;
use super::pool::{Pool, Reusable};
use super::registry::RigEntry;
use crowdmorph_core::rig::{JointPose, Pose};
use crowdmorph_engine::{
    Begun, BlendJob, BlendOutput, Engine, OutputSpec, Precision, Q16Reference, VertexData,
};

/// One unique job of a crowd request, resolved against a rig entry.
#[derive(Clone, Debug)]
pub struct JobRequest {
    /// The rig at the generation the request saw.
    pub entry: Arc<RigEntry>,
    /// The weights to evaluate (a clip frame, a canonical blend, live weights).
    pub pose: Pose,
    /// LOD level.
    pub lod: u32,
    /// Joint overrides (skinned rigs).
    pub joints: JointPose,
    /// Cost: vertices × (active shapes + 1).
    pub cost: u64,
}

/// A computed job: its payloads in the wire format.
#[derive(Debug)]
pub struct JobOutput {
    /// Positions.
    pub positions: Bytes,
    /// Normals, when asked for.
    pub normals: Option<Bytes>,
}

/// What a crowd request gets back: one output per job, in the order submitted.
#[derive(Debug)]
pub struct Outcome {
    /// Outputs parallel to the submitted jobs.
    pub outputs: Vec<Arc<JobOutput>>,
    /// From submission to the start of the last batch that computed one of its jobs.
    pub queue: Duration,
    /// Engine wall time of the batches that computed its jobs.
    pub compute_ns: u64,
    /// GPU time of those batches, when known.
    pub gpu_ns: Option<u64>,
}

/// Why a submission failed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ScheduleError {
    /// The queue holds `queue_requests` requests already.
    #[error("the batch queue is full")]
    QueueFull,
    /// The server is shutting down.
    #[error("the server is shutting down")]
    ShuttingDown,
    /// The engine failed on a batch holding one of the jobs.
    #[error("engine: {0}")]
    Engine(String),
}

/// Batching parameters.
#[derive(Clone, Copy, Debug)]
pub struct BatchConfig {
    /// Requests that may wait at once.
    pub queue_requests: usize,
    /// Cost at which a batch closes.
    pub batch_cost: u64,
    /// Longest a job waits for its batch to fill while the engine is busy.
    pub batch_delay: Duration,
    /// Hold work for `batch_delay` (or `batch_cost`) even when the engine is idle, instead of
    /// dispatching it at once: more coalescing of identical jobs at low load, at the price of
    /// the delay on every lone request. Off by default; tests use it to keep requests queued.
    pub hold_when_idle: bool,
}

/// The class a submission's jobs are queued in.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Priority {
    /// Client requests: always dispatched before low-priority work.
    #[default]
    Normal,
    /// Synthetic load (`POST /v1/loadtest`): dispatched only when no normal work waits and the
    /// engine is idle, so it fills the engine time clients leave and never starves them.
    Low,
}

struct Submission {
    jobs: Vec<JobRequest>,
    format: Format,
    normals: bool,
    priority: Priority,
    reply: oneshot::Sender<Result<Outcome, ScheduleError>>,
}

/// Handle to the batcher.
#[derive(Debug)]
pub struct Scheduler {
    tx: std::sync::Mutex<Option<mpsc::Sender<Submission>>>,
    metrics: Arc<Metrics>,
    limit: u64,
    task: tokio::sync::Mutex<Option<tokio::task::JoinHandle<()>>>,
}

/// The receiving end of a submission.
pub type Ticket = oneshot::Receiver<Result<Outcome, ScheduleError>>;

impl Scheduler {
    /// Starts the scheduling task and the compute thread.
    pub fn start(engine: Arc<Engine>, metrics: Arc<Metrics>, cfg: BatchConfig) -> Scheduler {
        // Admission is counted in `queue_depth` (requests in the batcher until answered); the
        // channel only hands them over and never holds more than that.
        let (tx, rx) = mpsc::channel(cfg.queue_requests.max(1));
        let (work_tx, work_rx) = std::sync::mpsc::channel::<WorkBatch>();
        let (done_tx, done_rx) = mpsc::unbounded_channel::<BatchDone>();
        let worker_metrics = metrics.clone();
        let depth = if engine.info().kind == crowdmorph_engine::BackendKind::Gpu {
            GPU_DEPTH
        } else {
            1
        };
        let spawned = std::thread::Builder::new()
            .name("crowdmorph-compute".into())
            .spawn(move || compute_thread(&engine, &worker_metrics, &work_rx, &done_tx, depth));
        if let Err(e) = &spawned {
            tracing::error!(error = %e, "cannot start the compute thread");
        }
        let state = State::new(cfg, metrics, work_tx, depth);
        let limit = cfg.queue_requests.max(1) as u64;
        let depth_metrics = state.metrics.clone();
        let task = tokio::spawn(state.run(rx, done_rx));
        Scheduler {
            tx: std::sync::Mutex::new(Some(tx)),
            metrics: depth_metrics,
            limit,
            task: tokio::sync::Mutex::new(Some(task)),
        }
    }

    /// Queues the jobs of one client request; the ticket resolves when every job is computed.
    pub fn submit(
        &self,
        jobs: Vec<JobRequest>,
        format: Format,
        normals: bool,
    ) -> Result<Ticket, ScheduleError> {
        self.submit_with(jobs, format, normals, Priority::Normal)
    }

    /// Queues the jobs of one request in a priority class.
    pub fn submit_with(
        &self,
        jobs: Vec<JobRequest>,
        format: Format,
        normals: bool,
        priority: Priority,
    ) -> Result<Ticket, ScheduleError> {
        let (reply, rx) = oneshot::channel();
        let sub = Submission {
            jobs,
            format,
            normals,
            priority,
            reply,
        };
        let tx = self
            .tx
            .lock()
            .map_err(|_| ScheduleError::ShuttingDown)?
            .clone()
            .ok_or(ScheduleError::ShuttingDown)?;
        let depth = self.metrics.queue_depth.inner();
        if depth.fetch_add(1, std::sync::atomic::Ordering::AcqRel) >= self.limit {
            depth.fetch_sub(1, std::sync::atomic::Ordering::AcqRel);
            return Err(ScheduleError::QueueFull);
        }
        tx.try_send(sub).map_err(|e| {
            depth.fetch_sub(1, std::sync::atomic::Ordering::AcqRel);
            match e {
                mpsc::error::TrySendError::Full(_) => ScheduleError::QueueFull,
                mpsc::error::TrySendError::Closed(_) => ScheduleError::ShuttingDown,
            }
        })?;
        Ok(rx)
    }

    /// Stops accepting work, computes everything already queued, and waits for the batcher.
    pub async fn shutdown(&self) {
        if let Ok(mut tx) = self.tx.lock() {
            tx.take();
        }
        if let Some(task) = self.task.lock().await.take() {
            let _ = task.await;
        }
    }
}

type SlotId = u64;
type ReqId = u64;

#[derive(Clone, Debug, PartialEq, Eq, Hash)]
struct SlotKey {
    generation: u64,
    pose: Pose,
    lod: u32,
    joints: JointPose,
    format: Format,
    normals: bool,
}

struct Slot {
    key: SlotKey,
    entry: Arc<RigEntry>,
    cost: u64,
    created: Instant,
    waiters: Vec<(ReqId, usize)>,
    /// The queue it waits in (or waited in, once dispatched).
    priority: Priority,
    /// Still in a pending queue (not yet dispatched).
    queued: bool,
}

struct ReqState {
    outputs: Vec<Option<Arc<JobOutput>>>,
    remaining: usize,
    reply: oneshot::Sender<Result<Outcome, ScheduleError>>,
    enqueued: Instant,
    last_start: Option<Instant>,
    compute_ns: u64,
    gpu_ns: Option<u64>,
    batches: Vec<u64>,
}

struct WorkGroup {
    entry: Arc<RigEntry>,
    /// The group's wire format (q16 residuals: the engine's q16, coded by the engine against
    /// the rig level's reference).
    format: Format,
    spec: OutputSpec,
    /// Unique engine jobs of the group.
    jobs: Vec<BlendJob>,
    /// Index of each job in `jobs`, to find it again.
    job_at: HashMap<BlendJob, usize>,
    /// Each slot, its wire format and the engine job it is made from. The engine writes the
    /// group's wire format itself, so a group has one format.
    slots: Vec<(SlotId, Format, usize)>,
}

/// A batch being filled: its groups and where each group key's group is.
#[derive(Default)]
struct BatchGroups {
    groups: Vec<WorkGroup>,
    at: HashMap<(u64, Format, bool, Option<usize>), usize>,
}

impl BatchGroups {
    /// Adds slot `id`'s job to its group, once per distinct job of the group.
    fn add(&mut self, id: SlotId, slot: &Slot) {
        let precision = match slot.key.format {
            Format::F32 => Precision::F32,
            Format::F16 => Precision::F16,
            // q16 residuals are q16 from the engine, coded against the reference by it.
            Format::Q16 | Format::Q16R => Precision::Q16(slot.entry.qbox),
            // Never submitted: a weights answer is built from the plan, with no engine work
            // (`routes::frames`, the session tick's poses). Were one submitted, it would be
            // blended as f32, not misread.
            Format::Weights => Precision::F32,
        };
        let gkey = (
            slot.key.generation,
            slot.key.format,
            slot.key.normals,
            slot.entry.prepared.mesh_of(slot.key.lod),
        );
        let groups = &mut self.groups;
        let g = *self.at.entry(gkey).or_insert_with(|| {
            groups.push(WorkGroup {
                entry: slot.entry.clone(),
                format: slot.key.format,
                spec: OutputSpec {
                    normals: slot.key.normals,
                    precision,
                },
                jobs: Vec::new(),
                job_at: HashMap::new(),
                slots: Vec::new(),
            });
            groups.len() - 1
        });
        let group = &mut groups[g];
        let job = BlendJob {
            pose: slot.key.pose.clone(),
            lod: slot.key.lod,
            joints: slot.key.joints.clone(),
        };
        let j = match group.job_at.get(&job) {
            Some(&j) => j,
            None => {
                group.jobs.push(job.clone());
                group.job_at.insert(job, group.jobs.len() - 1);
                group.jobs.len() - 1
            }
        };
        group.slots.push((id, slot.key.format, j));
    }
}

struct WorkBatch {
    id: u64,
    groups: Vec<WorkGroup>,
}

struct BatchDone {
    id: u64,
    results: Vec<(SlotId, Result<Arc<JobOutput>, String>)>,
    wall_ns: u64,
    gpu_ns: Option<u64>,
}

struct State {
    cfg: BatchConfig,
    metrics: Arc<Metrics>,
    work: Option<std::sync::mpsc::Sender<WorkBatch>>,
    slots: HashMap<SlotId, Slot>,
    index: HashMap<SlotKey, SlotId>,
    /// Normal slots waiting for a batch, oldest first, and their total cost.
    pending: VecDeque<SlotId>,
    pending_cost: u64,
    /// Low-priority slots waiting, oldest first, and their cost. A slot promoted to the normal
    /// queue stays here as a stale entry, skipped when met (`trim_low`, `pop`).
    low: VecDeque<SlotId>,
    low_cost: u64,
    requests: HashMap<ReqId, ReqState>,
    /// Batches at the compute thread, and how many it may hold.
    in_flight: usize,
    depth: usize,
    next_id: u64,
    next_batch: u64,
}

impl State {
    /// An empty scheduler state: nothing queued, nothing in flight.
    fn new(
        cfg: BatchConfig,
        metrics: Arc<Metrics>,
        work: std::sync::mpsc::Sender<WorkBatch>,
        depth: usize,
    ) -> State {
        State {
            cfg,
            metrics,
            work: Some(work),
            slots: HashMap::new(),
            index: HashMap::new(),
            pending: VecDeque::new(),
            pending_cost: 0,
            low: VecDeque::new(),
            low_cost: 0,
            requests: HashMap::new(),
            in_flight: 0,
            depth,
            next_id: 0,
            next_batch: 0,
        }
    }

    async fn run(
        mut self,
        mut rx: mpsc::Receiver<Submission>,
        mut done_rx: mpsc::UnboundedReceiver<BatchDone>,
    ) {
        let mut closed = false;
        loop {
            self.trim_low();
            if closed && self.pending.is_empty() && self.low.is_empty() && self.in_flight == 0 {
                break;
            }
            let wake = self.wake();
            let timer_armed = wake.is_some() && self.in_flight < self.depth;
            let sleep_until = wake.unwrap_or_else(Instant::now);
            tokio::select! {
                biased;
                done = done_rx.recv(), if self.in_flight > 0 => {
                    match done {
                        Some(done) => self.finish(done),
                        None => {
                            // The compute thread is gone: fail everything still waiting.
                            tracing::error!("the compute thread stopped");
                            self.fail_all("the compute thread stopped");
                            self.in_flight = 0;
                            self.work = None;
                        }
                    }
                }
                sub = rx.recv(), if !closed => {
                    match sub {
                        Some(sub) => self.add(sub),
                        None => closed = true,
                    }
                }
                () = tokio::time::sleep_until(sleep_until.into()), if timer_armed => {}
            }
            self.dispatch(closed);
        }
        self.fail_all("the server is shutting down");
    }

    /// When the oldest waiting job of the queue that would be dispatched next is due: the
    /// normal queue's, else (only with the engine idle) the low queue's.
    fn wake(&self) -> Option<Instant> {
        let front = match self.pending.front() {
            Some(id) => Some(id),
            None if self.in_flight == 0 => self.low.front(),
            None => None,
        };
        front
            .and_then(|id| self.slots.get(id))
            .map(|s| s.created + self.cfg.batch_delay)
    }

    /// Drops stale entries (promoted, dispatched or failed slots) from the front of the low
    /// queue, so that its front is a slot that really waits there.
    fn trim_low(&mut self) {
        while let Some(id) = self.low.front() {
            if self
                .slots
                .get(id)
                .is_some_and(|s| s.queued && s.priority == Priority::Low)
            {
                break;
            }
            self.low.pop_front();
        }
    }

    /// The next slot waiting in `priority`'s queue, taken off it (its cost too).
    fn pop(&mut self, priority: Priority) -> Option<SlotId> {
        loop {
            let id = match priority {
                Priority::Normal => self.pending.pop_front()?,
                Priority::Low => self.low.pop_front()?,
            };
            let Some(slot) = self.slots.get_mut(&id) else {
                continue;
            };
            if !slot.queued || slot.priority != priority {
                // A promoted slot's stale entry in the low queue.
                continue;
            }
            slot.queued = false;
            match priority {
                Priority::Normal => self.pending_cost = self.pending_cost.saturating_sub(slot.cost),
                Priority::Low => self.low_cost = self.low_cost.saturating_sub(slot.cost),
            }
            return Some(id);
        }
    }

    fn add(&mut self, sub: Submission) {
        let n = sub.jobs.len();
        if n == 0 {
            self.metrics.queue_depth.dec();
            let _ = sub.reply.send(Ok(Outcome {
                outputs: Vec::new(),
                queue: Duration::ZERO,
                compute_ns: 0,
                gpu_ns: None,
            }));
            return;
        }
        let req = self.next_id;
        self.next_id += 1;
        let now = Instant::now();
        for (i, job) in sub.jobs.into_iter().enumerate() {
            let key = SlotKey {
                generation: job.entry.generation,
                pose: job.pose.clone(),
                lod: job.lod,
                joints: job.joints.clone(),
                format: sub.format,
                normals: sub.normals,
            };
            if !self.join(&key, (req, i), sub.priority) {
                self.queue_slot(key, job, (req, i), sub.priority, now);
            }
        }
        self.requests.insert(
            req,
            ReqState {
                outputs: vec![None; n],
                remaining: n,
                reply: sub.reply,
                enqueued: now,
                last_start: None,
                compute_ns: 0,
                gpu_ns: None,
                batches: Vec::new(),
            },
        );
    }

    /// Adds a waiter to the slot already queued or computing for `key` (a clone in this or
    /// another request); false when there is none. A client joining low-priority work moves it
    /// to the normal queue.
    fn join(&mut self, key: &SlotKey, waiter: (ReqId, usize), priority: Priority) -> bool {
        let Some(&id) = self.index.get(key) else {
            return false;
        };
        let Some(slot) = self.slots.get_mut(&id) else {
            return false;
        };
        slot.waiters.push(waiter);
        self.metrics.jobs_coalesced.inc();
        if priority == Priority::Normal && slot.priority == Priority::Low {
            slot.priority = Priority::Normal;
            if slot.queued {
                self.low_cost = self.low_cost.saturating_sub(slot.cost);
                self.pending_cost += slot.cost;
                self.pending.push_back(id);
            }
        }
        true
    }

    /// A new slot for `key`, at the back of its class's queue.
    fn queue_slot(
        &mut self,
        key: SlotKey,
        job: JobRequest,
        waiter: (ReqId, usize),
        priority: Priority,
        now: Instant,
    ) {
        let id = self.next_id;
        self.next_id += 1;
        match priority {
            Priority::Normal => {
                self.pending_cost += job.cost;
                self.pending.push_back(id);
            }
            Priority::Low => {
                self.low_cost += job.cost;
                self.low.push_back(id);
            }
        }
        self.index.insert(key.clone(), id);
        self.slots.insert(
            id,
            Slot {
                key,
                entry: job.entry,
                cost: job.cost,
                created: now,
                waiters: vec![waiter],
                priority,
                queued: true,
            },
        );
    }

    fn alive(&self, req: ReqId) -> bool {
        self.requests
            .get(&req)
            .is_some_and(|r| !r.reply.is_closed())
    }

    fn drop_request(&mut self, req: ReqId) {
        if self.requests.remove(&req).is_some() {
            self.metrics.queue_depth.dec();
        }
    }

    /// Closes and sends a batch when the engine has room and a batch is due (see
    /// [`State::due_class`]). A batch holds one class.
    fn dispatch(&mut self, closing: bool) {
        self.trim_low();
        if self.in_flight >= self.depth || (self.pending.is_empty() && self.low.is_empty()) {
            return;
        }
        let Some(work) = self.work.clone() else {
            // No compute thread any more: answer at once rather than leave the jobs pending,
            // which would also keep the batch timer firing in a busy loop.
            self.fail_all("the compute thread stopped");
            return;
        };
        let Some(class) = self.due_class(closing) else {
            return;
        };
        let batch_id = self.next_batch;
        self.next_batch += 1;
        let (groups, jobs) = self.fill_batch(class);
        if groups.is_empty() {
            return;
        }
        let m = &self.metrics;
        m.batches.inc();
        m.dispatches.inc_by(groups.len() as u64);
        m.batch_jobs.observe(jobs as f64);
        if work
            .send(WorkBatch {
                id: batch_id,
                groups,
            })
            .is_err()
        {
            tracing::error!("the compute thread is gone");
            self.work = None;
            self.fail_all("the compute thread stopped");
            return;
        }
        self.in_flight += 1;
    }

    /// The class of work a batch closes for now, if any: normal work at once when the engine
    /// is idle (unless `hold_when_idle`), else when its cost or its oldest job's delay says
    /// so; low-priority work only when no normal work waits and the engine is idle.
    fn due_class(&self, closing: bool) -> Option<Priority> {
        let now = Instant::now();
        let idle = self.in_flight == 0;
        let eager = idle && !self.cfg.hold_when_idle;
        let due = |front: Option<&SlotId>, cost: u64| {
            closing
                || eager
                || cost >= self.cfg.batch_cost
                || front
                    .and_then(|id| self.slots.get(id))
                    .is_some_and(|s| now >= s.created + self.cfg.batch_delay)
        };
        if !self.pending.is_empty() {
            // Normal work that is not due yet keeps low work waiting too: it must not find
            // the engine busy with synthetic load when its time comes.
            due(self.pending.front(), self.pending_cost).then_some(Priority::Normal)
        } else {
            ((idle || closing) && due(self.low.front(), self.low_cost)).then_some(Priority::Low)
        }
    }

    /// Pops `class` jobs up to the batch cost, in one engine call per rig version, wire
    /// format, output kind and mesh level (LOD levels on a simplified mesh produce buffers of
    /// a different size). A job nobody waits for any more is dropped, not computed. Returns
    /// the groups and their job count.
    fn fill_batch(&mut self, class: Priority) -> (Vec<WorkGroup>, usize) {
        let now = Instant::now();
        let mut batch = BatchGroups::default();
        let mut cost = 0u64;
        let mut jobs = 0usize;
        while cost < self.cfg.batch_cost {
            let Some(id) = self.pop(class) else {
                break;
            };
            let Some(slot) = self.slots.get(&id) else {
                continue;
            };
            let waiters: Vec<ReqId> = slot.waiters.iter().map(|w| w.0).collect();
            if !waiters.iter().any(|&r| self.alive(r)) {
                if let Some(slot) = self.slots.remove(&id) {
                    self.index.remove(&slot.key);
                }
                for r in waiters {
                    self.drop_request(r);
                }
                self.metrics.jobs_cancelled.inc();
                continue;
            }
            cost += slot.cost;
            jobs += 1;
            batch.add(id, slot);
            for &r in &waiters {
                if let Some(state) = self.requests.get_mut(&r) {
                    state.last_start = Some(now);
                }
            }
        }
        (batch.groups, jobs)
    }

    fn finish(&mut self, done: BatchDone) {
        self.in_flight = self.in_flight.saturating_sub(1);
        let m = &self.metrics;
        m.compute_seconds.observe(done.wall_ns as f64 / 1e9);
        if let Some(g) = done.gpu_ns {
            m.gpu_seconds.inc_by(g as f64 / 1e9);
        }
        for (id, result) in done.results {
            let Some(slot) = self.slots.remove(&id) else {
                continue;
            };
            self.index.remove(&slot.key);
            for (req, i) in slot.waiters {
                let Some(state) = self.requests.get_mut(&req) else {
                    continue;
                };
                match &result {
                    Ok(out) => {
                        if let Some(o) = state.outputs.get_mut(i)
                            && o.is_none()
                        {
                            *o = Some(out.clone());
                            state.remaining -= 1;
                        }
                        if !state.batches.contains(&done.id) {
                            state.batches.push(done.id);
                            state.compute_ns += done.wall_ns;
                            if let Some(g) = done.gpu_ns {
                                state.gpu_ns = Some(state.gpu_ns.unwrap_or(0) + g);
                            }
                        }
                        if state.remaining == 0 {
                            self.complete(req);
                        }
                    }
                    Err(e) => {
                        if let Some(state) = self.requests.remove(&req) {
                            self.metrics.queue_depth.dec();
                            let _ = state.reply.send(Err(ScheduleError::Engine(e.clone())));
                        }
                    }
                }
            }
        }
    }

    fn complete(&mut self, req: ReqId) {
        let Some(state) = self.requests.remove(&req) else {
            return;
        };
        self.metrics.queue_depth.dec();
        let queue = state
            .last_start
            .map(|s| s.saturating_duration_since(state.enqueued))
            .unwrap_or_default();
        self.metrics.queue_seconds.observe(queue.as_secs_f64());
        let outputs: Option<Vec<Arc<JobOutput>>> = state.outputs.into_iter().collect();
        let result = match outputs {
            Some(outputs) => Ok(Outcome {
                outputs,
                queue,
                compute_ns: state.compute_ns,
                gpu_ns: state.gpu_ns,
            }),
            None => Err(ScheduleError::Engine("a job was not computed".into())),
        };
        let _ = state.reply.send(result);
    }

    fn fail_all(&mut self, why: &str) {
        for (_, state) in self.requests.drain() {
            self.metrics.queue_depth.dec();
            let _ = state.reply.send(Err(if why.contains("shutting") {
                ScheduleError::ShuttingDown
            } else {
                ScheduleError::Engine(why.to_string())
            }));
        }
        self.slots.clear();
        self.index.clear();
        self.pending.clear();
        self.pending_cost = 0;
        self.low.clear();
        self.low_cost = 0;
    }
}

/// Output buffers whose responses have been sent, kept for the next batch: a warm buffer
/// costs no page faults, and for large outputs the page faults of a fresh allocation cost
/// several times the blend itself (ICT FaceKit, 100 jobs: 32 MB, ≈ 20 ms cold vs ≈ 2 ms warm).
#[derive(Debug)]
struct BufferPool(Pool<VertexData>);

/// Buffers kept at most; more are freed.
const POOL_BUFFERS: usize = 8;
/// Most bytes the kept buffers may hold together (see [`Pool`]).
const POOL_TOTAL_BYTES: usize = 512 << 20;

impl Reusable for VertexData {
    fn kept_bytes(&self) -> usize {
        self.capacity_bytes()
    }
}

impl Default for BufferPool {
    fn default() -> Self {
        BufferPool(Pool::new(POOL_BUFFERS, POOL_TOTAL_BYTES))
    }
}

impl BufferPool {
    /// The largest free buffer of the kind `precision` produces, or an empty one.
    fn take(&self, precision: Precision) -> VertexData {
        self.0
            .take_best(|d| d.is_kind(precision).then(|| d.len()))
            .unwrap_or_default()
    }

    fn put(&self, data: VertexData) {
        self.0.put(data);
    }
}

/// Owns an engine output buffer so that [`Bytes`] views can share it without copying; when
/// the last view is dropped (the last response using it has been sent), the buffer goes back
/// to the pool.
struct VertexBytes {
    data: VertexData,
    pool: Arc<BufferPool>,
}

impl AsRef<[u8]> for VertexBytes {
    fn as_ref(&self) -> &[u8] {
        self.data.as_bytes()
    }
}

impl Drop for VertexBytes {
    fn drop(&mut self) {
        self.pool.put(std::mem::take(&mut self.data));
    }
}

/// A batch whose groups have begun on the engine (on the GPU: submitted and computing).
struct Started<'a> {
    id: u64,
    start: Instant,
    groups: Vec<(WorkGroup, std::thread::Result<Result<Begun<'a>, String>>)>,
}

/// Batches the scheduler lets be in flight on a GPU engine, and the compute thread keeps
/// begun at once: while the host copies batch k out of mapped memory, batches k + 1 and k + 2
/// are already on the device, so the GPU never waits for the host between batches (with two,
/// it idled whenever batch k + 2 had not arrived before batch k + 1 was waited for).
const GPU_DEPTH: usize = 3;

/// The compute thread: begins every batch it has (up to `depth`; on the GPU that submits it)
/// before it waits for the oldest, blocking for a new one only when nothing is in flight.
fn compute_thread(
    engine: &Engine,
    metrics: &Metrics,
    rx: &std::sync::mpsc::Receiver<WorkBatch>,
    done: &mpsc::UnboundedSender<BatchDone>,
    depth: usize,
) {
    let pool = Arc::new(BufferPool::default());
    let mut in_flight: VecDeque<Started<'_>> = VecDeque::new();
    let mut open = true;
    loop {
        while open && in_flight.len() < depth.max(1) {
            let next = if in_flight.is_empty() {
                rx.recv().ok()
            } else {
                match rx.try_recv() {
                    Ok(batch) => Some(batch),
                    Err(std::sync::mpsc::TryRecvError::Empty) => break,
                    Err(std::sync::mpsc::TryRecvError::Disconnected) => None,
                }
            };
            let Some(batch) = next else {
                open = false;
                break;
            };
            if !in_flight.is_empty() {
                metrics.batches_pipelined.inc();
            }
            in_flight.push_back(begin_batch(engine, batch));
        }
        let Some(oldest) = in_flight.pop_front() else {
            break;
        };
        if done
            .send(finish_batch(engine, metrics, &pool, oldest))
            .is_err()
        {
            break;
        }
    }
}

/// Begins every group of a batch: on the GPU each is submitted before any is waited for.
fn begin_batch(engine: &Engine, batch: WorkBatch) -> Started<'_> {
    let start = Instant::now();
    let groups = batch
        .groups
        .into_iter()
        .map(|group| {
            let begun = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                let reference = match group.format {
                    Format::Q16R => Some(residual_reference(&group)?),
                    _ => None,
                };
                engine
                    .begin(&group.entry.prepared, &group.jobs, group.spec, reference)
                    .map_err(|e| e.to_string())
            }));
            (group, begun)
        })
        .collect();
    Started {
        id: batch.id,
        start,
        groups,
    }
}

/// Waits for (or, on the CPU, computes) every group of a begun batch and collects the results.
fn finish_batch(
    engine: &Engine,
    metrics: &Metrics,
    pool: &Arc<BufferPool>,
    batch: Started<'_>,
) -> BatchDone {
    let mut results = Vec::new();
    let mut gpu_ns: Option<u64> = None;
    for (group, begun) in batch.groups {
        let outcome = match begun {
            Ok(Ok(begun)) => std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                finish_group(engine, pool, &group, begun)
            })),
            Ok(Err(e)) => Ok(Err(e)),
            Err(panic) => Err(panic),
        };
        match outcome {
            Ok(Ok((outs, gpu))) => {
                if let Some(g) = gpu {
                    gpu_ns = Some(gpu_ns.unwrap_or(0) + g);
                }
                metrics.jobs_computed.inc_by(group.jobs.len() as u64);
                results.extend(
                    group
                        .slots
                        .iter()
                        .zip(outs)
                        .map(|(&(id, _, _), o)| (id, Ok(Arc::new(o)))),
                );
            }
            Ok(Err(e)) => {
                tracing::error!(rig = %group.entry.id, error = %e, "engine evaluation failed");
                results.extend(group.slots.iter().map(|&(id, _, _)| (id, Err(e.clone()))));
            }
            Err(_) => {
                tracing::error!(rig = %group.entry.id, "engine evaluation panicked");
                results.extend(
                    group
                        .slots
                        .iter()
                        .map(|&(id, _, _)| (id, Err("engine evaluation panicked".to_string()))),
                );
            }
        }
    }
    BatchDone {
        id: batch.id,
        results,
        wall_ns: batch.start.elapsed().as_nanos() as u64,
        gpu_ns,
    }
}

type GroupResult = Result<(Vec<JobOutput>, Option<u64>), String>;

/// The reference a group's [`Format::Q16R`] positions are coded against: the q16 positions
/// of the group's rig (its mesh or PCA level) with every weight 0, which both engines compute
/// exactly (the neutral, quantized as any q16 output is), kept with the rig; clients fetch it
/// as that frame. Normals stay q16: recomputed normals differ between the engines in their
/// last bits, so a reference for them would not be the same everywhere.
fn residual_reference(group: &WorkGroup) -> Result<Q16Reference, String> {
    let Some(first) = group.jobs.first() else {
        return Err("q16 residuals of a group without jobs".into());
    };
    let Precision::Q16(b) = group.spec.precision else {
        return Err("q16 residuals of a group that is not q16".into());
    };
    let target = group.entry.prepared.at_level(first.lod);
    group.entry.q16_reference(target, || {
        target.q16_reference(b).map_err(|e| e.to_string())
    })
}

fn finish_group(
    engine: &Engine,
    pool: &Arc<BufferPool>,
    group: &WorkGroup,
    begun: Begun<'_>,
) -> GroupResult {
    // Warm pooled buffers: the CPU engine writes into them (no page faults); the GPU engine
    // replaces them with its readback. The engine writes the wire format, so the response
    // shares the buffer's bytes as they are.
    let mut out = BlendOutput {
        positions: pool.take(group.spec.precision),
        normals: group.spec.normals.then(|| pool.take(group.spec.precision)),
        ..BlendOutput::default()
    };
    let (timings, _) = engine
        .finish_into(
            begun,
            &group.entry.prepared,
            &group.jobs,
            group.spec,
            &mut out,
        )
        .map_err(|e| e.to_string())?;
    let gpu_ns = timings.gpu_ns;
    let v3 = out.vertices * 3;
    let n = group.jobs.len();
    let comp = group.spec.precision.component_bytes();
    if out.jobs != n
        || out.positions.len() != n * v3
        || !out.positions.is_kind(group.spec.precision)
    {
        return Err(format!(
            "engine returned {} jobs × {} components for {n} jobs of {v3} in {}",
            out.jobs,
            out.positions.len(),
            group.spec.precision.name()
        ));
    }
    let share = |d: VertexData| {
        Bytes::from_owner(VertexBytes {
            data: d,
            pool: pool.clone(),
        })
    };
    let pos_bytes = share(out.positions);
    let nrm_bytes = out.normals.map(share);
    let outs = group
        .slots
        .iter()
        .map(|&(_, _, j)| {
            let br = j * v3 * comp..(j + 1) * v3 * comp;
            JobOutput {
                positions: pos_bytes.slice(br.clone()),
                normals: nrm_bytes.as_ref().map(|b| b.slice(br)),
            }
        })
        .collect();
    Ok((outs, gpu_ns))
}

#[cfg(test)]
mod tests {
    //! The batcher's decisions, driven by hand: no compute thread, batches read off the work
    //! channel and finished with empty outputs, so every assertion is about order, not time.

    #![allow(clippy::unwrap_used)]

    use super::*;
    use crate::registry::{ClipLayout, NewEntry};
    use crowdmorph_core::budget::Budget;

    fn entry() -> Arc<RigEntry> {
        let engine = Engine::cpu();
        let rig = Arc::new(crowdmorph_core::embedded::default_rig());
        let prepared = engine.prepare(rig.clone()).unwrap();
        Arc::new(RigEntry::new(NewEntry {
            id: "default-head".into(),
            builtin: Some(rig.clips.len()),
            prepared,
            generation: 1,
            layout: ClipLayout::default(),
            charge: Budget::new(u64::MAX, "", None).keep(0),
            qbox: crate::registry::quantization_box(&rig),
        }))
    }

    fn state(hold_when_idle: bool) -> (State, std::sync::mpsc::Receiver<WorkBatch>) {
        let (tx, rx) = std::sync::mpsc::channel();
        let cfg = BatchConfig {
            queue_requests: 100,
            batch_cost: u64::MAX,
            batch_delay: Duration::from_secs(3600),
            hold_when_idle,
        };
        let state = State::new(cfg, Arc::new(Metrics::default()), tx, 1);
        (state, rx)
    }

    /// Submits one request for `frames` of clip 0 and returns its ticket.
    fn submit(state: &mut State, e: &Arc<RigEntry>, frames: &[u32], priority: Priority) -> Ticket {
        let (reply, ticket) = oneshot::channel();
        state.add(Submission {
            jobs: frames
                .iter()
                .map(|&frame| JobRequest {
                    entry: e.clone(),
                    pose: Pose::Frame { clip: 0, frame },
                    lod: 0,
                    joints: JointPose::NONE,
                    cost: 1,
                })
                .collect(),
            format: Format::F32,
            normals: false,
            priority,
            reply,
        });
        state.dispatch(false);
        ticket
    }

    /// The frames of the batch sent to the compute thread, if one was.
    fn sent(state: &State, rx: &std::sync::mpsc::Receiver<WorkBatch>) -> Option<(u64, Vec<u32>)> {
        let batch = rx.try_recv().ok()?;
        let mut frames: Vec<u32> = batch
            .groups
            .iter()
            .flat_map(|g| {
                g.slots
                    .iter()
                    .map(|&(id, _, _)| match state.slots[&id].key.pose {
                        Pose::Frame { frame, .. } => frame,
                        _ => u32::MAX,
                    })
            })
            .collect();
        frames.sort_unstable();
        Some((batch.id, frames))
    }

    /// Finishes batch `id` (every slot it computed gets an empty output) and dispatches.
    fn finish(state: &mut State, id: u64) {
        let results = state
            .slots
            .iter()
            .filter(|(_, s)| !s.queued)
            .map(|(&slot, _)| {
                let out = JobOutput {
                    positions: Bytes::new(),
                    normals: None,
                };
                (slot, Ok(Arc::new(out)))
            })
            .collect();
        state.finish(BatchDone {
            id,
            results,
            wall_ns: 0,
            gpu_ns: None,
        });
        state.dispatch(false);
    }

    fn answered(t: &mut Ticket) -> bool {
        matches!(t.try_recv(), Ok(Ok(_)))
    }

    #[test]
    fn a_lone_request_on_an_idle_engine_is_not_held_for_the_delay() {
        let e = entry();
        let (mut s, rx) = state(false);
        let _t = submit(&mut s, &e, &[1], Priority::Normal);
        assert_eq!(sent(&s, &rx), Some((0, vec![1])), "dispatched at once");
        // What arrives while the engine is busy waits for it and goes in one batch.
        let _a = submit(&mut s, &e, &[2], Priority::Normal);
        let _b = submit(&mut s, &e, &[3, 4], Priority::Normal);
        assert_eq!(sent(&s, &rx), None, "the engine is busy");
        finish(&mut s, 0);
        assert_eq!(sent(&s, &rx), Some((1, vec![2, 3, 4])));

        // With hold_when_idle, the old rule: nothing goes before the (hour-long) delay.
        let (mut s, rx) = state(true);
        let _t = submit(&mut s, &e, &[1], Priority::Normal);
        assert_eq!(sent(&s, &rx), None);
    }

    #[test]
    fn queued_low_priority_work_never_goes_before_a_client_request() {
        let e = entry();
        let (mut s, rx) = state(false);
        // A load test saturates the engine: one low batch computing, more low work queued.
        let mut low_a = submit(&mut s, &e, &[1], Priority::Low);
        assert_eq!(sent(&s, &rx), Some((0, vec![1])), "idle: low work may run");
        let mut low_b = submit(&mut s, &e, &[2, 3], Priority::Low);
        let mut low_c = submit(&mut s, &e, &[4], Priority::Low);
        // A client request arrives after them.
        let mut client = submit(&mut s, &e, &[10, 11], Priority::Normal);
        assert_eq!(sent(&s, &rx), None, "the engine is busy");
        finish(&mut s, 0);
        assert!(answered(&mut low_a));
        // The next batch is the client's alone, ahead of the low work queued before it.
        assert_eq!(sent(&s, &rx), Some((1, vec![10, 11])));
        finish(&mut s, 1);
        assert!(answered(&mut client));
        assert!(!answered(&mut low_b) && !answered(&mut low_c));
        // Then the low work, in one batch of its own.
        assert_eq!(sent(&s, &rx), Some((2, vec![2, 3, 4])));
        finish(&mut s, 2);
        assert!(answered(&mut low_b) && answered(&mut low_c));
        assert!(s.pending.is_empty() && s.low.is_empty() && s.requests.is_empty());
    }

    #[test]
    fn a_client_job_that_joins_a_queued_low_job_takes_it_to_the_front() {
        let e = entry();
        let (mut s, rx) = state(false);
        let _busy = submit(&mut s, &e, &[1], Priority::Low);
        assert_eq!(sent(&s, &rx), Some((0, vec![1])));
        let mut low = submit(&mut s, &e, &[2, 3], Priority::Low);
        // Frame 3 is already queued as low work: the client's job joins it.
        let mut client = submit(&mut s, &e, &[3], Priority::Normal);
        assert_eq!(s.metrics.jobs_coalesced.get(), 1);
        finish(&mut s, 0);
        assert_eq!(sent(&s, &rx), Some((1, vec![3])), "promoted, alone");
        finish(&mut s, 1);
        assert!(answered(&mut client));
        assert!(!answered(&mut low), "frame 2 is still queued");
        assert_eq!(sent(&s, &rx), Some((2, vec![2])));
        finish(&mut s, 2);
        assert!(answered(&mut low));
        assert_eq!((s.pending_cost, s.low_cost), (0, 0));
    }

    #[test]
    fn low_work_waits_while_a_client_request_waits_for_its_batch() {
        // With the old rule, a client job not yet due keeps the engine free for it.
        let e = entry();
        let (mut s, rx) = state(true);
        let _client = submit(&mut s, &e, &[1], Priority::Normal);
        let _low = submit(&mut s, &e, &[2], Priority::Low);
        assert_eq!(sent(&s, &rx), None);
        // Shutting down, everything goes: the client's work first.
        s.dispatch(true);
        assert_eq!(sent(&s, &rx), Some((0, vec![1])));
    }
}
