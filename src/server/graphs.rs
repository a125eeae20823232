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
    /// Name → the graph resolved and measured against a rig generation.
    resolved: HashMap<String, Resolved>,
}

/// A graph resolved against one rig generation, with what its measured motion depends on.
#[derive(Debug, Clone)]
struct Resolved {
    generation: u64,
    graph: Arc<Graph>,
    inputs: MotionInputs,
}

/// What a graph's measured motion is a function of: the rig's geometry and each node's clip
/// table (shared, not copied, by every generation that keeps them).
#[derive(Debug, Clone)]
struct MotionInputs {
    primitives: Arc<Vec<crate::rig::Primitive>>,
    tables: Vec<Arc<Vec<f32>>>,
}

impl MotionInputs {
    fn of(entry: &RigEntry, graph: &Graph) -> MotionInputs {
        let rig = entry.rig();
        MotionInputs {
            primitives: rig.primitives.clone(),
            tables: graph
                .nodes
                .iter()
                .map(|n| rig.clips[n.clip as usize].weights.clone())
                .collect(),
        }
    }

    /// The same geometry and the same tables, node by node.
    fn same(&self, other: &MotionInputs) -> bool {
        Arc::ptr_eq(&self.primitives, &other.primitives)
            && self.tables.len() == other.tables.len()
            && self
                .tables
                .iter()
                .zip(&other.tables)
                .all(|(a, b)| Arc::ptr_eq(a, b))
    }
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

    /// Adds or replaces a graph (resolved against `entry`'s generation); returns the rig's
    /// graphs to persist.
    pub fn insert(
        &self,
        entry: &RigEntry,
        name: &str,
        spec: MotionGraph,
        resolved: Arc<Graph>,
    ) -> BTreeMap<String, MotionGraph> {
        let rig = entry.id.as_str();
        let generation = entry.generation;
        let inputs = MotionInputs::of(entry, &resolved);
        self.with(|m| {
            let r = m.entry(rig.to_string()).or_default();
            r.specs.insert(name.to_string(), spec);
            r.resolved.insert(
                name.to_string(),
                Resolved {
                    generation,
                    graph: resolved,
                    inputs,
                },
            );
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

    /// Graph `name` of `entry`'s rig resolved against `entry`'s generation: cached; else
    /// resolved again (names to indices, cheap) with the motion measured for an earlier
    /// generation when what it depends on is unchanged (the geometry and the nodes' clip
    /// tables, shared by generations that keep them: a clip added or deleted elsewhere, a new
    /// LOD); else measured now, its memory charged to `memory` first. `None` when the rig has
    /// no such graph, it no longer fits the rig (a clip it plays was deleted), or the
    /// measurement's memory is not available now.
    pub fn resolved(
        &self,
        entry: &RigEntry,
        name: &str,
        memory: &crate::server::admission::QueueMemory,
    ) -> Option<Arc<Graph>> {
        enum Found {
            Current(Arc<Graph>),
            Stale(MotionGraph, Option<Resolved>),
        }
        let found = self.with(|m| {
            let r = m.get(&entry.id)?;
            let earlier = r.resolved.get(name);
            match earlier {
                Some(e) if e.generation == entry.generation => {
                    Some(Found::Current(e.graph.clone()))
                }
                _ => r
                    .specs
                    .get(name)
                    .map(|s| Found::Stale(s.clone(), earlier.cloned())),
            }
        })?;
        let (spec, earlier) = match found {
            Found::Current(g) => return Some(g),
            Found::Stale(spec, earlier) => (spec, earlier),
        };
        let rig = entry.rig();
        let mut graph = Graph::resolve(&spec, rig, |n| entry.clip_index(n)).ok()?;
        let inputs = MotionInputs::of(entry, &graph);
        match earlier.filter(|e| e.inputs.same(&inputs) && e.graph.nodes.len() == graph.nodes.len())
        {
            Some(e) => graph.set_motion(
                (0..graph.nodes.len() as u32)
                    .map(|n| e.graph.motion(n))
                    .collect(),
            ),
            None => {
                let _charge = memory.reserve(measure_bytes(entry)).ok()?;
                graph.set_motion(measure(entry, &graph));
            }
        }
        let graph = Arc::new(graph);
        self.with(|m| {
            if let Some(r) = m.get_mut(&entry.id) {
                r.resolved.insert(
                    name.to_string(),
                    Resolved {
                        generation: entry.generation,
                        graph: graph.clone(),
                        inputs,
                    },
                );
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
    let mut graph = Graph::resolve(spec, entry.rig(), |n| entry.clip_index(n))?;
    graph.set_motion(measure(entry, &graph));
    Ok(graph)
}

/// Each node's largest per-frame vertex displacement, on the CPU engine at LOD 0.
fn measure(entry: &RigEntry, graph: &Graph) -> Vec<f32> {
    let rig = entry.rig();
    let cpu = entry.prepared.cpu();
    graph
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
        .collect()
}
