//! Motion graphs by rig: the specs as stored (`PUT /v1/rigs/{id}/graphs/{name}`), and each
//! resolved against the rig generation that last used it, with its nodes' motion measured on
//! the CPU engine (what bounds a session head's cross-fades, `crate::graph`).

use std::collections::{BTreeMap, HashMap};
use std::sync::{Arc, Mutex};

use crowdmorph_proto::MotionGraph;

use crate::engine::{BlendJob, OutputSpec, WeightBatch};
use crate::graph::{Graph, GraphError};
use crate::server::registry::RigEntry;

/// Most graphs one rig may have.
pub const MAX_GRAPHS_PER_RIG: usize = 64;

/// Frames evaluated at once while a graph's motion is measured: what [`measure_bytes`]
/// charges is this many frames of the rig's vertices.
const MEASURE_FRAMES: usize = 16;

/// Every rig's graphs.
#[derive(Debug, Default)]
pub struct Graphs {
    by_rig: Mutex<HashMap<String, RigGraphs>>,
}

#[derive(Debug, Default)]
struct RigGraphs {
    specs: BTreeMap<String, MotionGraph>,
    /// Name → (rig generation, the graph resolved and measured against it).
    resolved: HashMap<String, (u64, Arc<Graph>)>,
}

impl Graphs {
    fn with<T>(&self, f: impl FnOnce(&mut HashMap<String, RigGraphs>) -> T) -> T {
        let mut g = self
            .by_rig
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        f(&mut g)
    }

    /// The names of rig `rig`'s graphs, sorted.
    pub fn names(&self, rig: &str) -> Vec<String> {
        self.with(|m| {
            m.get(rig)
                .map(|r| r.specs.keys().cloned().collect())
                .unwrap_or_default()
        })
    }

    /// Rig `rig`'s graph `name` as stored.
    pub fn spec(&self, rig: &str, name: &str) -> Option<MotionGraph> {
        self.with(|m| m.get(rig).and_then(|r| r.specs.get(name).cloned()))
    }

    /// Rig `rig`'s graphs as stored, by name.
    pub fn specs(&self, rig: &str) -> BTreeMap<String, MotionGraph> {
        self.with(|m| m.get(rig).map(|r| r.specs.clone()).unwrap_or_default())
    }

    /// How many graphs rig `rig` has, and whether `name` is one of them.
    pub fn count(&self, rig: &str, name: &str) -> (usize, bool) {
        self.with(|m| {
            m.get(rig)
                .map_or((0, false), |r| (r.specs.len(), r.specs.contains_key(name)))
        })
    }

    /// Adds or replaces a graph (resolved against `generation`); returns the rig's graphs to
    /// persist.
    pub fn insert(
        &self,
        rig: &str,
        name: &str,
        spec: MotionGraph,
        generation: u64,
        resolved: Arc<Graph>,
    ) -> BTreeMap<String, MotionGraph> {
        self.with(|m| {
            let r = m.entry(rig.to_string()).or_default();
            r.specs.insert(name.to_string(), spec);
            r.resolved.insert(name.to_string(), (generation, resolved));
            r.specs.clone()
        })
    }

    /// Removes a graph; `None` if there is no such graph, else the rig's graphs to persist.
    pub fn remove(&self, rig: &str, name: &str) -> Option<BTreeMap<String, MotionGraph>> {
        self.with(|m| {
            let r = m.get_mut(rig)?;
            r.specs.remove(name)?;
            r.resolved.remove(name);
            Some(r.specs.clone())
        })
    }

    /// Forgets a deleted rig's graphs.
    pub fn drop_rig(&self, rig: &str) {
        self.with(|m| m.remove(rig));
    }

    /// Takes the graphs loaded from the store (resolved on first use).
    pub fn load(&self, rig: String, specs: BTreeMap<String, MotionGraph>) {
        self.with(|m| {
            m.entry(rig).or_default().specs = specs;
        });
    }

    /// Graph `name` of `entry`'s rig resolved against `entry`'s generation: cached, or
    /// resolved and measured now (after a clip or LOD change made a new generation).
    /// `None` when the rig has no such graph or it no longer fits the rig (a clip it plays was
    /// deleted).
    pub fn resolved(&self, entry: &RigEntry, name: &str) -> Option<Arc<Graph>> {
        let spec = self.with(|m| {
            let r = m.get(&entry.id)?;
            match r.resolved.get(name) {
                Some((g, graph)) if *g == entry.generation => Some(Err(graph.clone())),
                _ => r.specs.get(name).cloned().map(Ok),
            }
        })?;
        let spec = match spec {
            Err(cached) => return Some(cached),
            Ok(spec) => spec,
        };
        let graph = Arc::new(resolve_and_measure(entry, &spec).ok()?);
        self.with(|m| {
            if let Some(r) = m.get_mut(&entry.id) {
                r.resolved
                    .insert(name.to_string(), (entry.generation, graph.clone()));
            }
        });
        Some(graph)
    }
}

/// Queue memory that measuring a graph's motion holds: [`MEASURE_FRAMES`] frames of the rig's
/// vertices (positions in f32) and their weights.
pub fn measure_bytes(entry: &RigEntry) -> u64 {
    let rig = entry.rig();
    (MEASURE_FRAMES as u64 + 1)
        * (rig.vertex_count() as u64 * 12 + rig.targets.len() as u64 * 9 + 64)
}

/// `spec` resolved against `entry`'s rig, with each node's largest per-frame vertex
/// displacement measured on the CPU engine (the caller has charged [`measure_bytes`]).
pub fn resolve_and_measure(entry: &RigEntry, spec: &MotionGraph) -> Result<Graph, GraphError> {
    let rig = entry.rig();
    let mut graph = Graph::resolve(spec, rig, |n| entry.clip_index(n))?;
    let cpu = entry.prepared.cpu();
    let motion = graph
        .nodes
        .iter()
        .map(|n| {
            let mut largest = 0f32;
            let mut prev: Option<Vec<f32>> = None;
            let frames: Vec<u32> = (n.first..n.first + n.len).collect();
            for chunk in frames.chunks(MEASURE_FRAMES) {
                let jobs: Vec<BlendJob> = chunk
                    .iter()
                    .map(|&f| BlendJob::frame(n.clip, f, 0))
                    .collect();
                let Ok(batch) = WeightBatch::gather(rig, &jobs) else {
                    continue;
                };
                let Ok(out) = cpu.evaluate(&batch, OutputSpec::default()) else {
                    continue;
                };
                for j in 0..jobs.len() {
                    let p = out.job_positions(j);
                    if let Some(q) = &prev {
                        let d = p
                            .chunks_exact(3)
                            .zip(q.chunks_exact(3))
                            .map(|(a, b)| {
                                ((a[0] - b[0]).powi(2)
                                    + (a[1] - b[1]).powi(2)
                                    + (a[2] - b[2]).powi(2))
                                .sqrt()
                            })
                            .fold(0.0, f32::max);
                        largest = largest.max(d);
                    }
                    prev = Some(p);
                }
            }
            largest
        })
        .collect();
    graph.set_motion(motion);
    Ok(graph)
}
