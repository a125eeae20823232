//! `POST /v1/crowd/frame`: a crowd's heads turned into blended vertex buffers, a pipeline of
//! named phases — [`decode`] (the body and its held share charged), [`plan`] (heads resolved
//! against one snapshot of each rig, unique jobs), [`admit`] (the output memory the jobs will
//! hold), [`compute`] (the batcher, within the deadline) and [`encode`] (bincode or JSON,
//! sharing the engine's buffers). `POST /v1/loadtest` runs the same pipeline for its synthetic
//! requests ([`crowd_frame_from`]). A request for `"format": "weights"` takes a shorter one
//! ([`poses`]): planned the same way, answered with each unique job's final pose, no engine.

use std::collections::HashMap;
use std::time::{Duration, Instant};

use axum::body::Body;
use axum::extract::State;
use axum::http::{HeaderMap, StatusCode, header};
use axum::response::{IntoResponse, Response};
use bytes::Bytes;
use crowdmorph_proto::{
    CONTENT_TYPE_BINCODE, CONTENT_TYPE_JSON, CrowdFrameRequest, CrowdPoseResponse, Format,
    FrameTimings, HeadBuffer, HeadPose,
};

use crate::admission::poses::{head_pose, invalid_output, pose_bytes, scratch_bytes};
use crate::admission::resolve::{heads_held_bytes, job_output_bytes, job_request};
use crate::admission::{
    Admission, Charge, Held, Priced, ResolvedHeads, decode_held, resolve_heads,
};
use crate::http::timing::Arrived;
use crate::http::{
    Accept, ApiError, ApiResult, Ready, SERVER_TIMING, ServerTiming, blocking, chunked_body,
};
use crate::json;
use crate::metrics::{DropCounter, Source};
use crate::scheduler::{JobRequest, Outcome, Priority, ScheduleError};
use crate::services::replicas::after_lookups;
use crate::state::AppState;
use crowdmorph_core::cancel::Cancelled;
use crowdmorph_core::rig::FrameMode;
use crowdmorph_store::codec::{FrameBufferParts, FrameResponseEncoder};

/// What a crowd-frame request holds per head from its decoding until its response is sent:
/// the decoded head and its two names, its job index in the plan, its `HeadBuffer`, and its
/// entry in the encoded response (at most 64 bytes as JSON, 16 as bincode).
impl Priced for CrowdFrameRequest {
    fn price(&self, accept: Accept) -> u64 {
        let entry = if accept.bincode { 16 } else { 64 };
        let built = size_of::<u32>() + size_of::<HeadBuffer>() + entry;
        heads_held_bytes(&self.heads, built as u64)
    }
}

impl From<ScheduleError> for ApiError {
    fn from(e: ScheduleError) -> ApiError {
        match e {
            ScheduleError::QueueFull => {
                ApiError::unavailable("queue_full", "the batch queue is full; retry shortly", 1)
            }
            ScheduleError::ShuttingDown => {
                ApiError::unavailable("shutting_down", "the server is shutting down", 5)
            }
            ScheduleError::Engine(e) => ApiError::internal(e),
        }
    }
}

/// `POST /v1/crowd/frame`.
pub async fn crowd_frame(
    State(state): State<AppState>,
    Arrived(arrived): Arrived,
    headers: HeaderMap,
    body: Body,
) -> Response {
    crowd_frame_from(&state, arrived, &headers, body, Source::Api).await
}

/// `POST /v1/crowd/frame` for a request from `source`: the route's handler, and what
/// `POST /v1/loadtest` calls for each synthetic request, so that synthetic load goes through
/// the same decoding, admission, batcher and encoders as real traffic. Loadtest requests are
/// queued at low priority and counted under their own label.
pub async fn crowd_frame_from(
    state: &AppState,
    arrived: Instant,
    headers: &HeaderMap,
    body: Body,
    source: Source,
) -> Response {
    // Counted as cancelled if this future is dropped (the client hung up) before it answers;
    // its queued jobs are then dropped by the batcher before they are computed.
    let waiting = DropCounter::new(state.metrics.clone(), "frame");
    let resp = frame(state, arrived, headers, body, source)
        .await
        .into_response();
    waiting.finish();
    state.metrics.crowd_frame(source, resp.status().as_u16());
    resp
}

/// The pipeline, phase by phase.
async fn frame(
    state: &AppState,
    arrived: Instant,
    headers: &HeaderMap,
    body: Body,
    source: Source,
) -> ApiResult {
    Ready::check(state.is_ready())?;
    let accept = Accept::of(headers);
    let req = decode(state, headers, body).await?;
    if req.output.format == Format::Weights {
        return poses(state, arrived, accept, req, source).await;
    }
    let planned = after_lookups(state, &req.heads, || plan(state, &req)).await?;
    let mut admitted = admit(state, &req, planned, accept)?;
    let outcome = compute(state, arrived, &req, &mut admitted, source).await?;
    state.metrics.served_to(source, req.heads.len() as u64);
    state.metrics.request_heads.observe(req.heads.len() as f64);
    state
        .metrics
        .request_seconds
        .observe(arrived.elapsed().as_secs_f64());
    encode(state, arrived, accept, req, admitted, outcome).await
}

/// Decode: the body read within its limits and decoded, its held share charged.
async fn decode(
    state: &AppState,
    headers: &HeaderMap,
    body: Body,
) -> Result<Held<CrowdFrameRequest>, ApiError> {
    decode_held(state.queue_memory(), state.body_limits(), headers, body).await
}

/// Plan: every head resolved against one snapshot of its rig, the unique jobs.
fn plan(state: &AppState, req: &CrowdFrameRequest) -> Result<ResolvedHeads, ApiError> {
    let mode = if req.wrap {
        FrameMode::Wrap
    } else {
        FrameMode::Strict
    };
    resolve_heads(
        &state.registry,
        state.queue_memory(),
        state.config.max_heads,
        &req.heads,
        mode,
        req.output.format == Format::F16,
    )
}

/// A planned request admitted: its jobs priced for the batcher and the memory its response will
/// hold, charged.
struct Admitted {
    resolved: ResolvedHeads,
    /// (bytes per job, vertices) of each rig level the request uses.
    per_level: HashMap<(u32, u32), (u64, u32)>,
    jobs: Vec<JobRequest>,
    /// The outputs and the heads' share, held until the body is sent.
    charge: Charge,
}

/// Admit: the output memory the jobs will hold, priced per rig and level before any per-job
/// work (a request refused as too large costs a lookup per unique job), taken with the heads'
/// share already held; 413 when together they are more than the whole queue memory.
fn admit(
    state: &AppState,
    req: &Held<CrowdFrameRequest>,
    resolved: ResolvedHeads,
    accept: Accept,
) -> Result<Admitted, ApiError> {
    let (format, normals) = (req.output.format, req.output.normals);
    let gpu = state.engine.gpu_memory().is_some();
    let ResolvedHeads { rigs, plan, .. } = &resolved;
    let mut per_level: HashMap<(u32, u32), (u64, u32)> = HashMap::new();
    let mut out_bytes = 0u64;
    for k in &plan.jobs {
        let (bytes, _) = *per_level.entry((k.rig, k.lod)).or_insert_with(|| {
            let rig = rigs[k.rig as usize].prepared.at_level(k.lod).rig();
            (
                job_output_bytes(rig, format, normals, !accept.bincode, gpu),
                rig.vertex_count() as u32,
            )
        });
        out_bytes = out_bytes.saturating_add(bytes);
    }
    let limit = state.queue_memory.limit();
    if !state
        .queue_memory
        .fits(out_bytes.saturating_add(req.charge().bytes()))
    {
        return Err(ApiError::new(
            StatusCode::PAYLOAD_TOO_LARGE,
            "response_too_large",
            format!(
                "the response would hold {out_bytes} bytes of vertex data, more than the server's \
                 queue memory of {limit} bytes (--queue-memory-bytes); ask for fewer unique heads or a \
                 smaller format"
            ),
        ));
    }
    let charge = state.queue_memory.reserve(out_bytes)?;
    let jobs: Vec<JobRequest> = plan
        .jobs
        .iter()
        .map(|k| job_request(&rigs[k.rig as usize], &k.pose, k.lod, &k.joints))
        .collect();
    Ok(Admitted {
        resolved,
        per_level,
        jobs,
        charge,
    })
}

/// 504 for a frame not ready within the request deadline, counted.
fn past_deadline(state: &AppState) -> ApiError {
    state.metrics.reject("deadline");
    state.metrics.cancelled("frame", Cancelled::Deadline);
    ApiError::new(
        StatusCode::GATEWAY_TIMEOUT,
        "deadline_exceeded",
        format!(
            "the frame was not ready within the request deadline of {} ms",
            state.config.request_timeout.as_millis()
        ),
    )
}

/// Compute: the jobs through the batcher (coalescing with every other request's), within
/// the deadline; synthetic load at low priority.
async fn compute(
    state: &AppState,
    arrived: Instant,
    req: &CrowdFrameRequest,
    admitted: &mut Admitted,
    source: Source,
) -> Result<Outcome, ApiError> {
    state
        .metrics
        .jobs_requested
        .inc_by(admitted.jobs.len() as u64);
    let priority = match source {
        Source::Api => Priority::Normal,
        Source::Loadtest => Priority::Low,
    };
    let ticket = state
        .scheduler
        .submit_with(
            // Moved, not cloned: nothing reads the jobs after they are submitted.
            std::mem::take(&mut admitted.jobs),
            req.output.format,
            req.output.normals,
            priority,
        )
        .inspect_err(|e| {
            if *e == ScheduleError::QueueFull {
                state.metrics.reject("queue_full");
            }
        })?;
    let deadline = state
        .config
        .request_timeout
        .saturating_sub(arrived.elapsed());
    let outcome = match tokio::time::timeout(deadline, ticket).await {
        Err(_) => return Err(past_deadline(state)),
        Ok(Err(_)) => return Err(ApiError::internal("the batcher dropped a request")),
        Ok(Ok(r)) => r?,
    };
    // The last stage boundary: a response the client has already been told is late (or
    // that the router's timeout is about to answer) is not encoded.
    if arrived.elapsed() >= state.config.request_timeout {
        return Err(past_deadline(state));
    }
    Ok(outcome)
}

/// Encode: the response in the wire format asked for, its buffers shared with the engine's
/// output, the request's charge going with the body; `Server-Timing` says where the time
/// went (the body's `FrameTimings` cannot include the encoding that writes them).
async fn encode(
    state: &AppState,
    arrived: Instant,
    accept: Accept,
    req: Held<CrowdFrameRequest>,
    admitted: Admitted,
    outcome: Outcome,
) -> ApiResult {
    let (req, held) = req.into_parts();
    let Admitted {
        resolved:
            ResolvedHeads {
                rigs,
                plan,
                charge: poses,
            },
        per_level,
        mut charge,
        ..
    } = admitted;
    charge.merge(held);
    if let Some(poses) = poses {
        charge.merge(poses);
    }
    let (format, normals) = (req.output.format, req.output.normals);
    let heads: Vec<HeadBuffer> = req
        .heads
        .iter()
        .zip(&plan.head_job)
        .map(|(h, &j)| HeadBuffer {
            head: h.head,
            buffer: j,
        })
        .collect();
    let timings = FrameTimings {
        queue_us: outcome.queue.as_micros() as u64,
        compute_us: outcome.compute_ns / 1000,
        total_us: arrived.elapsed().as_micros() as u64,
        gpu_us: outcome.gpu_ns.map(|g| g / 1000),
    };
    let encoding = Instant::now();
    let parts: Vec<FrameBufferParts<'_>> = plan
        .jobs
        .iter()
        .zip(&outcome.outputs)
        .map(|(k, out)| {
            let entry = &rigs[k.rig as usize];
            let (clip, frame) = entry.shown(&k.pose);
            FrameBufferParts {
                rig: &entry.id,
                clip,
                frame,
                lod: k.lod,
                vertices: per_level.get(&(k.rig, k.lod)).map_or(0, |&(_, v)| v),
                quantization: format.quantized().then_some(entry.qbox),
                positions: out.positions.clone(),
                normals: if normals { out.normals.clone() } else { None },
            }
        })
        .collect();
    let (content_type, chunks) = if accept.bincode {
        (
            CONTENT_TYPE_BINCODE,
            FrameResponseEncoder::encode(format, normals, &parts, &heads, &timings),
        )
    } else {
        let json = json_frame(state, format, normals, &parts, heads, timings).await?;
        (CONTENT_TYPE_JSON, vec![json])
    };
    let mut resp = (
        StatusCode::OK,
        [(header::CONTENT_TYPE, content_type)],
        chunked_body(chunks, charge),
    )
        .into_response();
    let encoded = Instant::now();
    let mut timing = ServerTiming::default()
        .with("queue", outcome.queue)
        .with("compute", Duration::from_nanos(outcome.compute_ns))
        .with("encode", encoded.duration_since(encoding))
        .with("total", encoded.duration_since(arrived));
    if let Some(g) = outcome.gpu_ns {
        timing = timing.with("gpu", Duration::from_nanos(g));
    }
    if let Some(v) = timing.header() {
        resp.headers_mut().insert(SERVER_TIMING, v);
    }
    Ok(resp)
}

/// Payload bytes above which a JSON response is encoded on the blocking pool.
const JSON_INLINE_BYTES: usize = 64 << 10;

/// Encodes a JSON crowd-frame response; base64 of a big crowd takes milliseconds, so those
/// are encoded on the blocking pool, not on an async worker.
async fn json_frame(
    state: &AppState,
    format: Format,
    normals: bool,
    parts: &[FrameBufferParts<'_>],
    heads: Vec<HeadBuffer>,
    timings: FrameTimings,
) -> Result<Bytes, ApiError> {
    let pool = state.json_pool.clone();
    let payload: usize = parts
        .iter()
        .map(|p| p.positions.len() + p.normals.as_ref().map_or(0, Bytes::len))
        .sum();
    if payload <= JSON_INLINE_BYTES {
        return Ok(json::encode_frame(
            &pool, format, normals, parts, &heads, &timings,
        ));
    }
    let owned: Vec<(String, String, FrameBufferParts<'static>)> = parts
        .iter()
        .map(|p| {
            (
                p.rig.to_string(),
                p.clip.to_string(),
                FrameBufferParts {
                    rig: "",
                    clip: "",
                    ..p.clone()
                },
            )
        })
        .collect();
    blocking(move || {
        let parts: Vec<FrameBufferParts<'_>> = owned
            .iter()
            .map(|(rig, clip, p)| FrameBufferParts {
                rig,
                clip,
                ..p.clone()
            })
            .collect();
        Ok(json::encode_frame(
            &pool, format, normals, &parts, &heads, &timings,
        ))
    })
    .await
}

/// The pipeline of a `"format": "weights"` request: checked (no normals, no LOD level: a pose
/// is the head's whole pose), planned as any crowd frame (so clones share a pose and every 4xx
/// is the same), its poses' bytes charged, then each unique job's final pose built and encoded
/// — no batch, no engine.
async fn poses(
    state: &AppState,
    arrived: Instant,
    accept: Accept,
    req: Held<CrowdFrameRequest>,
    source: Source,
) -> ApiResult {
    if req.output.normals {
        return Err(invalid_output(
            "output.normals: a weights answer has no vertices to give normals of; ask for \
             \"normals\": false"
                .into(),
        ));
    }
    if let Some((h, head)) = req.heads.iter().enumerate().find(|(_, h)| h.lod != 0) {
        return Err(invalid_output(format!(
            "head {h} (id {}): lod {} with format weights; a weights answer is the head's whole \
             pose (LOD levels cut what the server blends): leave lod at 0",
            head.head, head.lod
        )));
    }
    let ResolvedHeads {
        rigs,
        plan,
        charge: resolved_charge,
    } = after_lookups(state, &req.heads, || plan(state, &req)).await?;
    let json = !accept.bincode;
    // Each unique pose, its encoding and the posing scratch; the heads' entries.
    let mut bytes = plan.head_job.len() as u64 * 2 * size_of::<HeadBuffer>() as u64 + 256;
    let mut scratch = 0;
    for k in &plan.jobs {
        let rig = rigs[k.rig as usize].rig();
        bytes = bytes.saturating_add(pose_bytes(rig, json));
        scratch = scratch_bytes(rig).max(scratch);
    }
    let mut charge = state.queue_memory.reserve(bytes.saturating_add(scratch))?;
    let (req, held) = req.into_parts();
    charge.merge(held);
    if let Some(c) = resolved_charge {
        charge.merge(c);
    }
    let mut locals = Vec::new();
    let poses: Vec<HeadPose> = plan
        .jobs
        .iter()
        .map(|k| head_pose(rigs[k.rig as usize].rig(), &k.pose, &k.joints, &mut locals))
        .collect();
    drop(locals);
    let heads: Vec<HeadBuffer> = req
        .heads
        .iter()
        .zip(&plan.head_job)
        .map(|(h, &j)| HeadBuffer {
            head: h.head,
            buffer: j,
        })
        .collect();
    state.metrics.served_to(source, req.heads.len() as u64);
    state.metrics.request_heads.observe(req.heads.len() as f64);
    let answer = CrowdPoseResponse {
        format: Format::Weights,
        poses,
        heads,
        timings: FrameTimings {
            queue_us: 0,
            compute_us: 0,
            total_us: arrived.elapsed().as_micros() as u64,
            gpu_us: None,
        },
    };
    let body = if accept.bincode {
        crowdmorph_store::codec::to_wire(&answer).map_err(ApiError::internal)?
    } else {
        serde_json::to_vec(&answer).map_err(ApiError::internal)?
    };
    drop(answer);
    state
        .metrics
        .request_seconds
        .observe(arrived.elapsed().as_secs_f64());
    let mut resp = (
        StatusCode::OK,
        [(header::CONTENT_TYPE, accept.content_type())],
        chunked_body(vec![Bytes::from(body)], charge),
    )
        .into_response();
    if let Some(v) = ServerTiming::default()
        .with("total", arrived.elapsed())
        .header()
    {
        resp.headers_mut().insert(SERVER_TIMING, v);
    }
    Ok(resp)
}
