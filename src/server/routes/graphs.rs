//! `/v1/rigs/{id}/graphs`: a rig's motion graphs — [`put_graph`] checks a graph against the
//! rig and measures its nodes' motion before it is stored and listed; [`list_graphs`],
//! [`get_graph`] and [`delete_graph`]. Session heads play them (`sessions/tick.rs`).

use std::sync::Arc;

use axum::extract::{Path, State};
use axum::http::StatusCode;
use axum::response::IntoResponse;
use crowdmorph_proto::{GraphInfo, GraphList, MotionGraph};

use crate::graph::GraphError;
use crate::server::admission::{Decoded, Priced};
use crate::server::graphs::{MAX_GRAPHS_PER_RIG, measure_bytes, resolve_and_measure};
use crate::server::http::{Accept, Admin, ApiError, ApiResult, Ready, blocking};
use crate::server::registry::valid_id;
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
    if !valid_id(&name) {
        return Err(ApiError::bad_request(
            "invalid_name",
            format!(
                "graph name {} must be 1–64 characters of A-Z a-z 0-9 . _ - and not start with a dot",
                crate::rig::quoted_name(&name)
            ),
        ));
    }
    let (count, exists) = state.graphs.count(&id, &name);
    if !exists && count >= MAX_GRAPHS_PER_RIG {
        return Err(ApiError::bad_request(
            "invalid_graph",
            format!("rig {id:?} has {count} graphs, the most a rig may have"),
        ));
    }
    // Resolving holds the graph a second time; measuring holds a few frames of vertices.
    let _work = state
        .queue_memory
        .reserve(crate::graph::Graph::bytes(&spec, entry.rig()) + measure_bytes(&entry))?;
    let checked = {
        let (entry, spec) = (entry.clone(), spec.clone());
        blocking(move || resolve_and_measure(&entry, &spec).map_err(graph_error)).await?
    };
    let _admin = state.admin.lock().await;
    let all = state.graphs.insert(
        &id,
        &name,
        spec.clone(),
        entry.generation,
        Arc::new(checked),
    );
    if state.store.is_some() {
        let s = state.clone();
        let rid = id.clone();
        blocking(move || {
            s.store
                .as_ref()
                .map_or(Ok(()), |st| st.put_graphs(&rid, &all))
                .map_err(ApiError::internal)
        })
        .await?;
    }
    accept.reply(
        StatusCode::OK,
        &GraphInfo {
            rig: id,
            name,
            graph: spec,
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
    let all = state
        .graphs
        .remove(&id, &name)
        .ok_or_else(|| unknown_graph(&id, &name, &state.graphs.names(&id)))?;
    if state.store.is_some() {
        let s = state.clone();
        blocking(move || {
            s.store
                .as_ref()
                .map_or(Ok(()), |st| st.put_graphs(&id, &all))
                .map_err(ApiError::internal)
        })
        .await?;
    }
    Ok(StatusCode::NO_CONTENT.into_response())
}
