//! `POST /v1/loadtest` and `GET /v1/loadtest/{id}`: a bounded synthetic load generated inside
//! the server, so that an operator can measure a box without a client machine.
//!
//! The load is the open loop of [`crowdmorph_load`], with in-process lanes instead of connections:
//! each synthetic request is an encoded crowd-frame body handed to the crowd-frame handler
//! itself ([`super::frames::crowd_frame_from`]), so it is decoded, resolved, admitted, batched,
//! deduplicated and encoded exactly as a client's — only the socket is missing. Its jobs are
//! queued at `Priority::Low`: they fill the engine time
//! clients leave and never push a client's request back by more than the one batch already
//! computing. Its heads and requests carry `source="loadtest"` in the metrics.
//!
//! Bounds: one load at a time (409 `loadtest_running`, before the load is planned); the
//! crowd's rig, clip and LOD lists at most [`load::MAX_MIX`] entries each; the request body
//! charged to the queue memory while it is decoded; duration, rate and lanes capped by
//! flags (400 past them); what the load can hold at once — its request bodies, and each lane's
//! output and decode reservation — at most half the queue memory, and the lanes at most half
//! the batch queue, so that clients always find room. The bodies are charged to the queue
//! memory before they are made (on the blocking pool when large) and until the load ends; a
//! body longer than `--max-request-bytes`, which the handler would refuse with 413, refuses
//! the load with 400. A `POST` that waits for its load answers 202 with the running status
//! when the request's deadline would otherwise cut it.

use std::sync::Arc;
use std::time::Duration;

use axum::body::Body;
use axum::extract::{Path, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::Response;
use bytes::Bytes;
use serde::Deserialize;

use super::frames::crowd_frame_from;
use crate::admission::resolve::job_output_bytes;
use crate::admission::{
    Charge, Decoded, Priced, decode_reservation, names_bytes, names_reservation,
};
use crate::config::ServerConfig;
use crate::http::timing::Arrived;
use crate::http::{Accept, Admin, ApiError, ApiResult, Query, Ready, blocking};
use crate::loadtests::{KEEP_DONE, LoadtestRequest, Run};
use crate::metrics::Source;
use crate::state::AppState;
use crowdmorph_load::{self as load, CrowdShape, Lane, Live, Reply, RigClips, RunOptions};

/// Request bodies generated per load; request `i` sends body `i mod RING`.
const RING: usize = 64;

/// Bodies larger than this in all are made on the blocking pool, not on an async worker.
const BUILD_INLINE_BYTES: u64 = 64 << 10;

pub(crate) fn already_running(id: &str) -> ApiError {
    ApiError::new(
        StatusCode::CONFLICT,
        "loadtest_running",
        format!("load test {id} is running (GET /v1/loadtest/{id}); one runs at a time"),
    )
}

/// Marks a run finished when dropped (see the load task).
struct FinishOnDrop {
    state: AppState,
    run: Arc<Run>,
}

impl Drop for FinishOnDrop {
    fn drop(&mut self) {
        self.state.loadtests.finish(&self.run);
    }
}

/// A lane that calls the crowd-frame handler in-process.
struct InProcessLane {
    state: AppState,
    bodies: Arc<Vec<Bytes>>,
    content_type: HeaderValue,
}

impl Lane for InProcessLane {
    async fn send(&mut self, i: u64) -> Reply {
        let body = self.bodies[(i % self.bodies.len() as u64) as usize].clone();
        let mut headers = HeaderMap::new();
        headers.insert(header::CONTENT_TYPE, self.content_type.clone());
        headers.insert(header::ACCEPT, self.content_type.clone());
        headers.insert(header::CONTENT_LENGTH, HeaderValue::from(body.len()));
        let resp = crowd_frame_from(
            &self.state,
            std::time::Instant::now(),
            &headers,
            Body::from(body),
            Source::Loadtest,
        )
        .await;
        read_reply(resp).await
    }
}

/// Status, Server-Timing and body size of a handler's response; the body is dropped chunk by
/// chunk as it would be sent (which releases its queue memory), and read only when it is an
/// error, for its code.
async fn read_reply(resp: Response) -> Reply {
    load::read_reply(resp).await.0
}

impl Priced for LoadtestRequest {
    /// The crowd's lists, held until the load is planned (and capped at `load::MAX_MIX`): the
    /// rig names, and the clip and LOD maps as B-tree nodes (see [`btree_bytes`]) plus the
    /// clip names.
    fn price(&self, _: Accept) -> u64 {
        let c = &self.crowd;
        names_bytes(&c.rigs)
            + btree_bytes(c.clips.len(), size_of::<(String, f64)>())
            + c.clips.keys().map(|n| n.capacity() as u64).sum::<u64>()
            + btree_bytes(c.lods.len(), size_of::<(u32, f64)>())
    }

    fn decoding(bincode: bool, len: u64) -> u64 {
        names_reservation(bincode, len)
    }
}

/// At most what a `BTreeMap` of `len` entries of `entry` bytes allocates: std's nodes hold 11
/// entries (internal nodes 12 edge pointers more, counted for every node) behind a 16-byte
/// header, and every node but the root holds at least 5, so there are at most `len / 5 + 1`.
fn btree_bytes(len: usize, entry: usize) -> u64 {
    if len == 0 {
        return 0;
    }
    ((len / 5 + 1) * (16 + 11 * entry + 12 * size_of::<usize>())) as u64
}

fn invalid(message: impl Into<String>) -> ApiError {
    ApiError::bad_request("invalid_loadtest", message)
}

/// Checks a load against the caps and the registry, its memory included, before anything
/// is made.
fn plan_loadtest(state: &AppState, req: &LoadtestRequest) -> Result<Plan, ApiError> {
    let cfg = &state.config;
    check_pace(cfg, req)?;
    let crowd = &req.crowd;
    if crowd.heads as usize > cfg.max_heads {
        return Err(ApiError::bad_request(
            "too_many_heads",
            format!(
                "{} heads is more than the limit of {} per request",
                crowd.heads, cfg.max_heads
            ),
        ));
    }
    // The lists are checked (and capped at `load::MAX_MIX`) before any rig is looked up.
    crowd.check().map_err(|e| invalid(e.to_string()))?;
    let (rigs, max_job_bytes) = rig_mix(state, crowd)?;
    let sizes = crowd
        .body_sizes(&rigs, RING)
        .map_err(|e| invalid(e.to_string()))?;
    check_held(cfg, req, &sizes, max_job_bytes)?;
    let opts = RunOptions {
        rate: req.rate,
        duration: Duration::from_secs_f64(req.duration_s),
        warmup: Duration::from_secs_f64(req.warmup_s),
        // A synthetic request gets the deadline of any crowd request, then 504.
        grace: cfg.request_timeout + Duration::from_secs(1),
        heads_per_request: u64::from(crowd.heads),
    };
    opts.check().map_err(|e| invalid(e.to_string()))?;
    Ok(Plan {
        rigs: Arc::new(rigs),
        sizes,
        opts,
    })
}

/// The distinct rigs a load plays, each looked up and described once (a rig listed many
/// times, to weight it, costs one copy of its clip names), and the largest output of one
/// of their jobs.
fn rig_mix(state: &AppState, crowd: &CrowdShape) -> Result<(Vec<RigClips>, u64), ApiError> {
    let mut rigs: Vec<RigClips> = Vec::new();
    let json = crowd.encoding == load::WireEncoding::Json;
    let gpu = state.engine.gpu_memory().is_some();
    let mut max_job_bytes = 0u64;
    for id in &crowd.rigs {
        if rigs.iter().any(|r| &r.id == id) {
            continue;
        }
        let entry = crate::services::Parts::rig(state, id)?;
        let rig = entry.rig();
        max_job_bytes = max_job_bytes.max(job_output_bytes(
            rig,
            crowd.format,
            crowd.normals,
            json,
            gpu,
        ));
        rigs.push(RigClips {
            id: id.clone(),
            clips: rig.clips.iter().map(|c| c.name.clone()).collect(),
            lod_levels: rig.lod.levels.len() as u32,
        });
    }
    Ok((rigs, max_job_bytes))
}

/// Charges the bodies of a planned load to the queue memory (503 when it is too full
/// now), then makes them, on the blocking pool when they are large. Keeps the charge of
/// the bodies made, which the load holds until it ends; 400 when a body is longer than
/// the handler accepts.
async fn loadtest_bodies(
    state: &AppState,
    crowd: &CrowdShape,
    plan: &Plan,
) -> Result<(Vec<Bytes>, Charge), ApiError> {
    let bound = plan.sizes.body.saturating_mul(RING as u64);
    let mut memory = state
        .queue_memory
        .reserve(bound.saturating_add(plan.sizes.building))?;
    let make = {
        let crowd = crowd.clone();
        let rigs = plan.rigs.clone();
        move || {
            crowd
                .bodies(&rigs, RING)
                .map_err(|e| invalid(e.to_string()))
        }
    };
    let bodies = if bound > BUILD_INLINE_BYTES {
        blocking(make).await?
    } else {
        make()?
    };
    let limit = state.config.max_request_bytes;
    if let Some(longest) = bodies.iter().map(Bytes::len).max()
        && longest > limit
    {
        return Err(ApiError::bad_request(
            "loadtest_too_large",
            format!(
                "the load's requests would be {longest} bytes long, more than the server \
                 accepts (--max-request-bytes {limit}), and each would be refused with \
                 413; use fewer heads"
            ),
        ));
    }
    // Keep what the bodies take; the estimate's slack and the building's transient memory
    // go back now.
    let made: u64 = bodies.iter().map(|b| b.len() as u64).sum();
    memory.keep(made);
    Ok((bodies, memory))
}

/// The load's duration, rate and lanes against the server's caps.
fn check_pace(cfg: &ServerConfig, req: &LoadtestRequest) -> Result<(), ApiError> {
    let max_s = cfg.loadtest_max_duration.as_secs_f64();
    if max_s <= 0.0 {
        return Err(ApiError::new(
            StatusCode::FORBIDDEN,
            "loadtest_disabled",
            "load tests are disabled on this server (--loadtest-max-duration-s 0)",
        ));
    }
    let positive = |v: f64| v.is_finite() && v > 0.0;
    if !(positive(req.duration_s) && req.warmup_s.is_finite() && req.warmup_s >= 0.0) {
        return Err(invalid(format!(
            "duration_s must be positive and warmup_s at least 0, not {} and {}",
            req.duration_s, req.warmup_s
        )));
    }
    if req.duration_s + req.warmup_s > max_s {
        return Err(ApiError::bad_request(
            "loadtest_too_long",
            format!(
                "duration_s + warmup_s = {} s is more than this server allows \
                 (--loadtest-max-duration-s {max_s})",
                req.duration_s + req.warmup_s
            ),
        ));
    }
    if !positive(req.rate) {
        return Err(invalid(format!(
            "rate must be a positive number of requests per second, not {}",
            req.rate
        )));
    }
    if req.rate > cfg.loadtest_max_rate {
        return Err(ApiError::bad_request(
            "loadtest_rate_too_high",
            format!(
                "rate {} is more requests per second than this server allows \
                 (--loadtest-max-rate {})",
                req.rate, cfg.loadtest_max_rate
            ),
        ));
    }
    // Half the batch queue stays free for clients.
    let max_lanes = cfg
        .loadtest_max_concurrency
        .min(cfg.queue_requests / 2)
        .max(1);
    if req.concurrency == 0 || req.concurrency as usize > max_lanes {
        return Err(invalid(format!(
            "concurrency must be 1 to {max_lanes} (--loadtest-max-concurrency, and half of \
             --queue-requests), not {}",
            req.concurrency
        )));
    }
    Ok(())
}

/// What the load may hold at once stays within half the queue memory: its bodies, and per
/// lane the output of one request and what the handler reserves while it decodes one of
/// those bodies.
fn check_held(
    cfg: &ServerConfig,
    req: &LoadtestRequest,
    sizes: &load::BodySizes,
    max_job_bytes: u64,
) -> Result<(), ApiError> {
    let crowd = &req.crowd;
    let output = u64::from(crowd.unique_jobs()) * max_job_bytes;
    let decoding = decode_reservation(crowd.encoding == load::WireEncoding::Bincode, sizes.body);
    let per_request = output.saturating_add(decoding);
    let bodies = sizes.body.saturating_mul(RING as u64);
    let held = per_request
        .saturating_mul(u64::from(req.concurrency))
        .saturating_add(bodies);
    let room = cfg.queue_memory_bytes as u64 / 2;
    if held > room {
        return Err(ApiError::bad_request(
            "loadtest_too_large",
            format!(
                "{} lanes of {output} bytes of output and {decoding} bytes reserved while \
                 decoding each, plus {RING} request bodies of up to {} bytes ({bodies} \
                 bytes), would hold {held} bytes, more than half the queue memory ({room} \
                 of --queue-memory-bytes); use fewer lanes, fewer heads, fewer unique heads \
                 or a smaller format",
                req.concurrency, sizes.body
            ),
        ));
    }
    Ok(())
}

/// A load checked against the caps: the rigs it plays, its bodies' sizes, its timing.
struct Plan {
    /// One per distinct rig, shared with the task that makes the bodies.
    rigs: Arc<Vec<RigClips>>,
    sizes: load::BodySizes,
    opts: RunOptions,
}

/// `?wait=false`: answer 202 at once instead of when the load is done.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LoadtestQuery {
    wait: Option<bool>,
}

/// `POST /v1/loadtest`: runs a load and answers its report (or 202 at once with `?wait=false`).
pub async fn start_loadtest(
    State(state): State<AppState>,
    Arrived(arrived): Arrived,
    _admin: Admin,
    Query(query): Query<LoadtestQuery>,
    _ready: Ready,
    accept: Accept,
    Decoded(req): Decoded<LoadtestRequest>,
) -> ApiResult {
    let (req, decoded) = req.into_parts();
    // A second load is refused before it is planned (rig lookups, clip lists, body sizes):
    // concurrent POSTs do not all pay for a plan only one of them can run.
    if let Some(id) = state.loadtests.running() {
        return Err(already_running(&id));
    }
    let plan = plan_loadtest(&state, &req)?;
    // Planned: its rig, clip and LOD lists are capped (`load::MAX_MIX` entries each).
    drop(decoded);
    let (bodies, bodies_memory) = loadtest_bodies(&state, &req.crowd, &plan).await?;
    let lanes = req.concurrency as usize;
    let live = Live::new(plan.opts);
    let run = state
        .loadtests
        .start(req, live.clone())
        .map_err(|running| match running {
            Some(id) => already_running(&id),
            None => ApiError::internal("the loadtest registry lock is poisoned"),
        })?;
    tracing::info!(
        id = %run.id,
        rate = run.request.rate,
        duration_s = run.request.duration_s,
        heads = run.request.crowd.heads,
        "load test started"
    );
    spawn_load(&state, &run, live, lanes, bodies, bodies_memory);
    if query.wait == Some(false) {
        return accept.reply(StatusCode::ACCEPTED, &run.status());
    }
    // Waiting past the handler's deadline would end in the router's 504 while the load runs
    // on: at the deadline, answer what `?wait=false` would have (202, running) instead.
    let left = state
        .config
        .handler_timeout()
        .saturating_sub(arrived.elapsed());
    let mut done = run.done.subscribe();
    match tokio::time::timeout(left, done.wait_for(|d| *d)).await {
        Ok(_) => accept.reply(StatusCode::OK, &run.status()),
        Err(_) => accept.reply(StatusCode::ACCEPTED, &run.status()),
    }
}

/// Runs a started load on its own task: a client that hangs up does not stop it (it stays
/// readable with GET until later loads push it out).
fn spawn_load(
    state: &AppState,
    run: &Arc<Run>,
    live: Arc<Live>,
    lanes: usize,
    bodies: Vec<Bytes>,
    bodies_memory: Charge,
) {
    let bodies = Arc::new(bodies);
    let content_type = HeaderValue::from_static(run.request.crowd.encoding.content_type());
    let lanes: Vec<InProcessLane> = (0..lanes)
        .map(|_| InProcessLane {
            state: state.clone(),
            bodies: bodies.clone(),
            content_type: content_type.clone(),
        })
        .collect();
    let task_state = state.clone();
    let task_run = run.clone();
    tokio::spawn(async move {
        // Ends the run in the registry however the task ends, a panic included, so that a
        // failed load never blocks later ones with 409.
        let _finish = FinishOnDrop {
            state: task_state,
            run: task_run.clone(),
        };
        // Dropped before `_finish`: the bodies' queue memory is back when the run reads done.
        let _bodies_memory = bodies_memory;
        if let Err(e) = load::run(lanes, &live).await {
            tracing::error!(id = %task_run.id, error = %e, "load test failed to run");
            live.cancel();
        }
        let r = live.snapshot();
        tracing::info!(
            id = %task_run.id,
            achieved_rate = r.achieved_rate,
            p99_ms = r.latency_ms.p99,
            errors = r.errors,
            "load test finished"
        );
    });
}

/// `GET /v1/loadtest/{id}`: a load's progress (the report so far) or its final report.
pub async fn get_loadtest(
    State(state): State<AppState>,
    _admin: Admin,
    accept: Accept,
    Path(id): Path<String>,
) -> ApiResult {
    let run = state.loadtests.find(&id).ok_or_else(|| {
        ApiError::not_found(
            "unknown_loadtest",
            format!(
                "no load test {} (the server keeps the last {KEEP_DONE})",
                crowdmorph_core::rig::quoted_name(&id)
            ),
        )
    })?;
    accept.reply(StatusCode::OK, &run.status())
}
