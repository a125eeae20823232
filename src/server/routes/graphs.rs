//! `/v1/rigs/{id}/graphs`: a rig's motion graphs — [`put_graph`] checks a graph against the
//! rig and measures its nodes' motion before it is stored and listed; [`list_graphs`],
//! [`get_graph`] and [`delete_graph`]. Session heads play them (`sessions/tick.rs`).

use std::sync::Arc;

use axum::extract::{Path, State};
use axum::http::StatusCode;
use axum::response::IntoResponse;
use crowdmorph_proto::{BuiltGraph, GraphInfo, GraphList, MotionGraph};

use crate::graph::GraphError;
use crate::server::admission::{Decoded, Priced};
use crate::server::graphs::{MAX_GRAPHS_PER_RIG, measure_bytes, resolve_and_measure};
use crate::server::http::{Accept, Admin, ApiError, ApiResult, Query, Ready, blocking};
use crate::server::registry::{RigEntry, valid_id};
use crate::server::state::AppState;

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
            crate::rig::quoted_name(name),
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

/// `PUT /v1/rigs/{id}/graphs/{name}`: checks the graph against the rig (every clip, range,
/// edge and window; every node has a way out), measures each node's motion, stores it with the
/// rig and answers with it.
pub async fn put_graph(
    State(state): State<AppState>,
    _admin: Admin,
    _ready: Ready,
    accept: Accept,
    Path((id, name)): Path<(String, String)>,
    Decoded(req): Decoded<MotionGraph>,
) -> ApiResult {
    let (spec, _decoded) = req.into_parts();
    let entry = state.rig(&id)?;
    let info = store(&state, &entry, &id, &name, spec).await?;
    accept.reply(StatusCode::OK, &info)
}

/// Checks `spec` against the rig, measures its nodes' motion and stores it as graph `name`
/// of rig `id`, in memory and on disk.
async fn store(
    state: &AppState,
    entry: &Arc<RigEntry>,
    id: &str,
    name: &str,
    spec: MotionGraph,
) -> Result<GraphInfo, ApiError> {
    if !valid_id(name) {
        return Err(ApiError::bad_request(
            "invalid_name",
            format!(
                "graph name {} must be 1–64 characters of A-Z a-z 0-9 . _ - and not start with a dot",
                crate::rig::quoted_name(name)
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
    // Resolving holds the graph a second time; measuring holds a few frames of vertices.
    let _work = state
        .queue_memory
        .reserve(crate::graph::Graph::bytes(&spec, entry.rig()) + measure_bytes(entry))?;
    let checked = {
        let (entry, spec) = (entry.clone(), spec.clone());
        blocking(move || resolve_and_measure(&entry, &spec).map_err(graph_error)).await?
    };
    // Stored first, then served: a write the store refuses (409, 503) changes nothing here.
    let _admin = state.admin.lock().await;
    let mut all = state.graphs.specs(id);
    all.insert(name.to_string(), spec.clone());
    state.persist_graphs(id, all).await?;
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
/// the rig's clips (`crate::graph::build`, Kovar et al.), stores it as `PUT` would, and
/// answers with it and its edges' costs.
pub async fn build_graph(
    State(state): State<AppState>,
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
    let mut opt = crate::graph::BuildOptions::default();
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
    let bytes = crate::graph::build_bytes(entry.rig()).ok_or_else(|| {
        ApiError::bad_request(
            "invalid_graph",
            format!(
                "rig {id:?} has clips too long to compare frame by frame (more than {} frame \
                 pairs); build the graph offline with `crowdmorph clips graph` and PUT it",
                crate::graph::MAX_BUILD_PAIRS
            ),
        )
    })?;
    let _work = state.queue_memory.reserve(bytes)?;
    let built = {
        let entry = entry.clone();
        blocking(move || Ok::<_, ApiError>(crate::graph::build(entry.rig(), opt))).await?
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
    let info = store(&state, &entry, &id, &name, built.graph).await?;
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
    state.persist_graphs(&id, all).await?;
    state.graphs.remove(&id, &name);
    Ok(StatusCode::NO_CONTENT.into_response())
}
