//! Motion graphs (Kovar et al. 2002; GPU Gems 3 ch. 15 sequences captured clips the same way):
//! named graphs of a rig whose nodes are clips (or frame ranges of them) and whose edges are
//! cross-faded transitions, played by session heads (`proto/README.md`, "Motion graphs").

use serde::{Deserialize, Serialize};

/// `PUT /v1/rigs/{id}/graphs/{name}` request, and the graph in [`GraphInfo`].
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MotionGraph {
    /// The nodes; names unique within the graph.
    pub nodes: Vec<GraphNode>,
    /// The transitions.
    pub edges: Vec<GraphEdge>,
}

/// A node: a clip of the rig, or the frame range `[first, last]` of one.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GraphNode {
    /// Node name (1–64 characters).
    pub name: String,
    /// Clip name within the rig.
    pub clip: String,
    /// First and last frame played (inclusive); absent, the whole clip.
    #[serde(default)]
    pub frames: Option<[u32; 2]>,
}

/// A transition from node `from` to node `to`: the target's first frame fades in over `fade`
/// frames while the source keeps playing.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GraphEdge {
    /// Source node name.
    pub from: String,
    /// Target node name.
    pub to: String,
    /// Cross-fade length in frames of the target's clip (at least 1, at most either node's
    /// length).
    pub fade: u32,
    /// Frames of the source node (counted from its first frame) where the transition may
    /// start, inclusive; absent, only at `length − fade`, so that the fade ends with the
    /// source.
    #[serde(default)]
    pub window: Option<[u32; 2]>,
}

/// `GET /v1/rigs/{id}/graphs/{name}` response (also the answer to `PUT`).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct GraphInfo {
    /// The rig.
    pub rig: String,
    /// The graph's name.
    pub name: String,
    /// The graph as stored.
    pub graph: MotionGraph,
}

/// `POST /v1/rigs/{id}/graphs/{name}?auto=1` response: the graph built from the rig's clips
/// and stored, with each edge's cost (the mean RMS vertex distance, over the fade's window,
/// between the frames it blends, as a fraction of the rig's diagonal; 0 for an edge that
/// plays a clip on).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct BuiltGraph {
    /// The graph as stored.
    pub info: GraphInfo,
    /// Per edge of `info.graph`, its cost.
    pub costs: Vec<f32>,
    /// Candidate transitions found.
    pub candidates: u32,
    /// Nodes dropped outside the largest strongly connected component.
    pub dropped_nodes: u32,
}

/// `GET /v1/rigs/{id}/graphs` response.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct GraphList {
    /// The rig's graphs, by name.
    pub graphs: Vec<GraphInfo>,
}

/// How a session head plays a motion graph: from node `start`, either through `script` (node
/// names, each reached by an edge from the one before; the head then stays in the last) or,
/// without a script, on a random walk seeded by `seed`. Heads with the same graph, start,
/// seed and script are clones.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GraphPlay {
    /// Graph name within the head's rig.
    pub name: String,
    /// Node the head starts in.
    pub start: String,
    /// Seed of the random walk.
    #[serde(default)]
    pub seed: u64,
    /// Nodes to visit in order (empty: a random walk).
    #[serde(default)]
    pub script: Vec<String>,
}
