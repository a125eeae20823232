//! `/v1/rigs/{id}/graphs`: a rig's motion graphs — [`put_graph`] checks a graph against the
//! rig and measures its nodes' motion before it is stored and listed; [`build_graph`] builds
//! one from the clips; [`list_graphs`], [`get_graph`] and [`delete_graph`]. Session heads play
//! them (`sessions/tick.rs`).
//!
//! The work of a graph is bounded before it starts: the name, the query and the graph's shape
//! are checked first, then its work is priced (`crowdmorph_anim::graph::build_work`,
//! `crate::graphs::measure_work`) and refused past `--max-graph-work` (413
//! `graph_too_costly`); the work then runs on the blocking pool with a [`Cancel`] whose
//! deadline is the request's admin deadline and whose guard this handler holds, so that it
//! stops a few milliseconds after the 504, or after the client hangs up.

use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::extract::{Path, State};
use axum::http::StatusCode;
use axum::response::IntoResponse;
use crowdmorph_proto::{BuiltGraph, GraphInfo, GraphList, MotionGraph};

use crate::admission::{Decoded, Priced};
use crate::graphs::{MAX_GRAPHS_PER_RIG, measure, measure_bytes, measure_work};
use crate::http::timing::Arrived;
use crate::http::{Accept, Admin, ApiError, ApiResult, Query, Ready, blocking};
use crate::registry::{RigEntry, valid_id};
use crate::services::Parts;
use crate::services::persist::persist_graphs;
use crate::state::AppState;
use crowdmorph_anim::graph::{Graph, GraphError};
use crowdmorph_core::cancel::{Cancel, CancelOnDrop, Cancelled};

/// A graph's names and edges, held until it is resolved and stored.
impl Priced for MotionGraph {
    fn price(&self, _: Accept) -> u64 {
        let nodes = self.nodes.capacity() as u64 * size_of::<crowdmorph_proto::GraphNode>() as u64
            + self
                .nodes
                .iter()
                .map(|n| n.name.capacity() as u64 + n.clip.capacity() as u64)
                .sum::<u64>();
        let edges = self.edges.capacity() as u64 * size_of::<crowdmorph_proto::GraphEdge>() as u64
            + self
                .edges
                .iter()
                .map(|e| e.from.capacity() as u64 + e.to.capacity() as u64)
                .sum::<u64>();
        nodes + edges
    }
}

/// 404 `unknown_graph`.
pub(crate) fn unknown_graph(rig: &str, name: &str, have: &[String]) -> ApiError {
    ApiError::not_found(
        "unknown_graph",
        format!(
            "rig {rig:?} has no graph {} (graphs: {})",
            crowdmorph_core::rig::quoted_name(name),
            have.join(", ")
        ),
    )
}

fn graph_error(e: GraphError) -> ApiError {
    match e {
        GraphError::UnknownClip { .. } => ApiError::not_found("unknown_clip", e.to_string()),
        GraphError::Invalid(m) => ApiError::bad_request("invalid_graph", m),
    }
}

/// 413 `graph_too_costly`: `what` would take `work` units, more than `--max-graph-work`.
fn too_costly(state: &AppState, what: &str, work: u64) -> ApiError {
    ApiError::new(
        StatusCode::PAYLOAD_TOO_LARGE,
        "graph_too_costly",
        format!(
            "{what} would take {work} units of work, more than --max-graph-work ({}); use fewer \
             or shorter clips or nodes, or raise the flag",
            state.config.max_graph_work
        ),
    )
}

/// The answer to graph work stopped by its cancellation: 504 past the admin deadline, 503
/// `cancelled` when the client went away (no one reads it).
fn cancelled(c: Cancelled) -> ApiError {
    match c {
        Cancelled::Deadline => ApiError::new(
            StatusCode::GATEWAY_TIMEOUT,
            "deadline_exceeded",
            "the graph was not ready within the admin deadline (--admin-timeout-s)",
        ),
        Cancelled::Dropped => ApiError::unavailable("cancelled", "the request was cancelled", 1),
    }
}

/// The cancellation of one graph request: its admin deadline counted from its arrival, and
/// the guard that raises it when the handler's future is dropped.
fn cancel_for(state: &AppState, arrived: Instant) -> (Cancel, CancelOnDrop) {
    let left = state
        .config
        .admin_timeout
        .saturating_sub(arrived.elapsed())
        .max(Duration::from_millis(1));
    Cancel::new(Some(Instant::now() + left))
}

/// Runs graph work on the blocking pool and answers its cancellation. The work counts its
/// own cancellation: after a hang-up no one awaits its answer.
async fn graph_work<T: Send + 'static>(
    state: &AppState,
    f: impl FnOnce() -> Result<Result<T, Cancelled>, ApiError> + Send + 'static,
) -> Result<T, ApiError> {
    let metrics = state.metrics.clone();
    blocking(move || {
        let done = f()?;
        if let Err(c) = &done {
            metrics.cancelled("graph", *c);
        }
        Ok(done)
    })
    .await?
    .map_err(cancelled)
}

/// `PUT /v1/rigs/{id}/graphs/{name}`: checks the name, then the graph against the rig (every
/// clip, range, edge and window; every node has a way out), prices and measures each node's
/// motion, stores it with the rig and answers with it.
pub async fn put_graph(
    State(state): State<AppState>,
    Arrived(arrived): Arrived,
    _admin: Admin,
    _ready: Ready,
    accept: Accept,
    Path((id, name)): Path<(String, String)>,
    Decoded(req): Decoded<MotionGraph>,
) -> ApiResult {
    let (spec, _decoded) = req.into_parts();
    let entry = state.rig(&id)?;
    check_name(&state, &id, &name)?;
    let (cancel, _guard) = cancel_for(&state, arrived);
    let info = store(&state, &entry, &id, &name, spec, cancel).await?;
    accept.reply(StatusCode::OK, &info)
}

/// 400 `invalid_name` for a malformed graph name, 400 `invalid_graph` for a new graph past
/// the rig's limit: checked before any work.
fn check_name(state: &AppState, id: &str, name: &str) -> Result<(), ApiError> {
    if !valid_id(name) {
        return Err(ApiError::bad_request(
            "invalid_name",
            format!(
                "graph name {} must be 1–64 characters of A-Z a-z 0-9 . _ - and not start with a dot",
                crowdmorph_core::rig::quoted_name(name)
            ),
        ));
    }
    let (count, exists) = state.graphs.count(id, name);
    if !exists && count >= MAX_GRAPHS_PER_RIG {
        return Err(ApiError::bad_request(
            "invalid_graph",
            format!("rig {id:?} has {count} graphs, the most a rig may have"),
        ));
    }
    Ok(())
}

/// Checks `spec` against the rig, prices and measures its nodes' motion (stopping at
/// `cancel`) and stores it as graph `name` of rig `id`, in memory and on disk. The caller
/// has checked the name ([`check_name`]).
async fn store(
    state: &AppState,
    entry: &Arc<RigEntry>,
    id: &str,
    name: &str,
    spec: MotionGraph,
    cancel: Cancel,
) -> Result<GraphInfo, ApiError> {
    // Resolving holds the graph a second time.
    let _resolved = state
        .queue_memory
        .reserve(Graph::bytes(&spec, entry.rig()))?;
    let mut graph = {
        let (entry, spec) = (entry.clone(), spec.clone());
        blocking(move || {
            Graph::resolve(&spec, entry.rig(), |n| entry.clip_index(n)).map_err(graph_error)
        })
        .await?
    };
    let work = measure_work(entry, &graph);
    if work > state.config.max_graph_work {
        return Err(too_costly(
            state,
            &format!("measuring the motion of the frames its nodes play ({name:?})"),
            work,
        ));
    }
    // Measuring holds a few frames of vertices and a step per frame played.
    let _measuring = state.queue_memory.reserve(measure_bytes(entry, &graph))?;
    let checked = {
        let entry = entry.clone();
        graph_work(state, move || {
            Ok(measure(&entry, &graph, &cancel).map(|motion| {
                graph.set_motion(motion);
                graph
            }))
        })
        .await?
    };
    // Stored first, then served: a write the store refuses (409, 503) changes nothing here.
    let _admin = state.admin.lock().await;
    let mut all = state.graphs.specs(id);
    all.insert(name.to_string(), spec.clone());
    persist_graphs(state, id, all).await?;
    state
        .graphs
        .insert(entry, name, spec.clone(), Arc::new(checked));
    Ok(GraphInfo {
        rig: id.to_string(),
        name: name.to_string(),
        graph: spec,
    })
}

/// `POST /v1/rigs/{id}/graphs/{name}` query: `auto=1` builds the graph from the rig's clips.
#[derive(Debug, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AutoQuery {
    /// Must be 1 (or true): the only kind of POST.
    #[serde(default)]
    pub auto: String,
    /// Frames compared per transition, and its fade (1–120).
    #[serde(default)]
    pub window: Option<u32>,
    /// Largest transition cost, as a fraction of the rig's diagonal (0–1).
    #[serde(default)]
    pub threshold: Option<f32>,
}

/// `POST /v1/rigs/{id}/graphs/{name}?auto=1[&window=W][&threshold=T]`: builds a graph from
/// the rig's clips (`crowdmorph_anim::graph::build`, Kovar et al.), stores it as `PUT` would, and
/// answers with it and its edges' costs.
pub async fn build_graph(
    State(state): State<AppState>,
    Arrived(arrived): Arrived,
    _admin: Admin,
    _ready: Ready,
    accept: Accept,
    Path((id, name)): Path<(String, String)>,
    Query(q): Query<AutoQuery>,
) -> ApiResult {
    if !matches!(q.auto.as_str(), "1" | "true") {
        return Err(ApiError::bad_request(
            "bad_query",
            "POST builds a graph from the clips: send ?auto=1 (PUT stores one you made)",
        ));
    }
    let mut opt = crowdmorph_anim::graph::BuildOptions::default();
    if let Some(w) = q.window {
        if !(1..=120).contains(&w) {
            return Err(ApiError::bad_request(
                "bad_query",
                format!("window is {w}; it must be 1 to 120 frames"),
            ));
        }
        opt.window = w;
    }
    if let Some(t) = q.threshold {
        if !(t.is_finite() && (0.0..=1.0).contains(&t)) {
            return Err(ApiError::bad_request(
                "bad_query",
                format!("threshold is {t}; it must be in [0, 1] (a fraction of the diagonal)"),
            ));
        }
        opt.threshold = t;
    }
    let entry = state.rig(&id)?;
    check_name(&state, &id, &name)?;
    let bytes = crowdmorph_anim::graph::build_bytes(entry.rig(), opt).ok_or_else(|| {
        ApiError::bad_request(
            "invalid_graph",
            format!(
                "rig {id:?} has clips too long to compare frame by frame (more than {} frame \
                 pairs); build the graph offline with `crowdmorph clips graph` and PUT it",
                crowdmorph_anim::graph::MAX_BUILD_PAIRS
            ),
        )
    })?;
    // The build and the measurement of what it builds (its nodes play each frame at most
    // once, so at most every frame), priced together before either starts.
    let rig = entry.rig();
    let frames: u64 = rig.clips.iter().map(|c| u64::from(c.frames)).sum();
    let work = crowdmorph_anim::graph::build_work(rig, opt)
        .saturating_add(frames.saturating_mul(crate::graphs::frame_work(rig)));
    if work > state.config.max_graph_work {
        return Err(too_costly(
            &state,
            &format!(
                "building a graph from rig {id:?}'s {} clips ({frames} frames)",
                rig.clips.len()
            ),
            work,
        ));
    }
    let _work = state.queue_memory.reserve(bytes)?;
    let (cancel, _guard) = cancel_for(&state, arrived);
    let built = {
        let (entry, cancel) = (entry.clone(), cancel.clone());
        graph_work(&state, move || {
            Ok(crowdmorph_anim::graph::build(entry.rig(), opt, &cancel))
        })
        .await?
    }
    .ok_or_else(|| {
        ApiError::bad_request(
            "invalid_graph",
            format!(
                "rig {id:?}: no cycle of transitions under the threshold {} (raise threshold or \
                 lower window)",
                opt.threshold
            ),
        )
    })?;
    let info = store(&state, &entry, &id, &name, built.graph, cancel).await?;
    accept.reply(
        StatusCode::OK,
        &BuiltGraph {
            info,
            costs: built.costs,
            candidates: built.candidates as u32,
            dropped_nodes: built.dropped_nodes as u32,
        },
    )
}

/// `GET /v1/rigs/{id}/graphs`.
pub async fn list_graphs(
    State(state): State<AppState>,
    accept: Accept,
    Path(id): Path<String>,
) -> ApiResult {
    let _entry = state.rig(&id)?;
    let graphs = state
        .graphs
        .specs(&id)
        .into_iter()
        .map(|(name, graph)| GraphInfo {
            rig: id.clone(),
            name,
            graph,
        })
        .collect();
    accept.reply(StatusCode::OK, &GraphList { graphs })
}

/// `GET /v1/rigs/{id}/graphs/{name}`.
pub async fn get_graph(
    State(state): State<AppState>,
    accept: Accept,
    Path((id, name)): Path<(String, String)>,
) -> ApiResult {
    let _entry = state.rig(&id)?;
    let graph = state
        .graphs
        .spec(&id, &name)
        .ok_or_else(|| unknown_graph(&id, &name, &state.graphs.names(&id)))?;
    accept.reply(
        StatusCode::OK,
        &GraphInfo {
            rig: id,
            name,
            graph,
        },
    )
}

/// `DELETE /v1/rigs/{id}/graphs/{name}`: sessions playing it keep their heads where they are
/// (a head whose graph is gone is missing from later ticks, as one whose clip is gone).
pub async fn delete_graph(
    State(state): State<AppState>,
    _admin: Admin,
    Path((id, name)): Path<(String, String)>,
) -> ApiResult {
    let _entry = state.rig(&id)?;
    let _admin = state.admin.lock().await;
    let mut all = state.graphs.specs(&id);
    if all.remove(&name).is_none() {
        return Err(unknown_graph(&id, &name, &state.graphs.names(&id)));
    }
    // Stored first, then removed here: a delete the store refuses changes nothing.
    persist_graphs(&state, &id, all).await?;
    state.graphs.remove(&id, &name);
    Ok(StatusCode::NO_CONTENT.into_response())
}
