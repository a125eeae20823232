//! Motion graphs by rig: the specs as stored (`PUT /v1/rigs/{id}/graphs/{name}`), and each
//! resolved against the rig generation that last used it, with its nodes' motion measured on
//! the CPU engine (what bounds a session head's cross-fades, `crowdmorph_anim::graph`).
//!
//! A measurement evaluates every frame the graph's nodes play once, however many nodes share
//! it: per clip, the union of the nodes' frame ranges is walked and each frame's step from the
//! one before is kept, and a node's motion is the largest step inside its range. Its price
//! ([`measure_work`]) is known before it starts, and it stops at its cancellation.

use std::collections::{BTreeMap, HashMap};
use std::sync::{Arc, Mutex};

use crowdmorph_proto::MotionGraph;

use crate::registry::RigEntry;
use crowdmorph_anim::graph::Graph;
use crowdmorph_core::cancel::{Cancel, Cancelled};
use crowdmorph_engine::{BlendJob, OutputSpec, WeightBatch};

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
    primitives: Arc<Vec<crowdmorph_core::rig::Primitive>>,
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
    /// LOD); else measured now, its memory charged first through `reserve` (the caller's
    /// budget: this module sits below admission and knows no queue memory). `None` when the rig has
    /// no such graph, it no longer fits the rig (a clip it plays was deleted), the
    /// measurement would cost more than `max_work` (a graph stored under a larger
    /// `--max-graph-work`), or its memory is not available now.
    pub fn resolved<R>(
        &self,
        entry: &RigEntry,
        name: &str,
        reserve: impl FnOnce(u64) -> Option<R>,
        max_work: u64,
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
                if measure_work(entry, &graph) > max_work {
                    return None;
                }
                let _charge = reserve(measure_bytes(entry, &graph))?;
                graph.set_motion(measure(entry, &graph, &Cancel::never()).ok()?);
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

/// Per clip, the frames a graph's nodes play: their ranges merged where they overlap or
/// touch, as `(clip, first, last)` sorted by clip and first frame.
fn played(graph: &Graph) -> Vec<(u32, u32, u32)> {
    let mut ranges: Vec<(u32, u32, u32)> = graph
        .nodes
        .iter()
        .map(|n| (n.clip, n.first, n.first + n.len - 1))
        .collect();
    ranges.sort_unstable();
    let mut merged: Vec<(u32, u32, u32)> = Vec::with_capacity(ranges.len());
    for (c, a, b) in ranges {
        match merged.last_mut() {
            Some(m) if m.0 == c && a <= m.2.saturating_add(1) => m.2 = m.2.max(b),
            _ => merged.push((c, a, b)),
        }
    }
    merged
}

/// Frames a measurement of `graph` evaluates: each frame its nodes play, once.
fn played_frames(graph: &Graph) -> u64 {
    played(graph)
        .iter()
        .map(|&(_, a, b)| u64::from(b - a) + 1)
        .sum()
}

/// Work of evaluating one frame of `rig` on the CPU engine, in the unit of
/// `--max-graph-work`: each stored delta blended, each vertex written (and skinned by up to four
/// bones) and compared with the frame before.
pub fn frame_work(rig: &crowdmorph_core::rig::Rig) -> u64 {
    let deltas = rig.delta_count();
    let vertices = rig.vertex_count() as u64;
    let skinned = if rig.skeleton.is_some() { 4 } else { 0 };
    deltas + vertices * (2 + skinned)
}

/// What measuring `graph`'s motion costs, in the unit of `--max-graph-work`: the frames its
/// nodes play (each once, [`played`]) times [`frame_work`].
pub fn measure_work(entry: &RigEntry, graph: &Graph) -> u64 {
    played_frames(graph).saturating_mul(frame_work(entry.rig()))
}

/// Queue memory that measuring `graph`'s motion holds: [`MEASURE_FRAMES`] frames of the rig's
/// vertices (positions in f32) and their weights, and a step per frame played.
pub fn measure_bytes(entry: &RigEntry, graph: &Graph) -> u64 {
    let rig = entry.rig();
    (MEASURE_FRAMES as u64 + 1)
        * (rig.vertex_count() as u64 * 12 + rig.targets.len() as u64 * 9 + 64)
        + played_frames(graph) * 4
        + graph.nodes.len() as u64 * 12
}

/// Each node's largest per-frame vertex displacement, on the CPU engine at LOD 0 (the caller
/// has charged [`measure_bytes`]). Every frame the nodes play is evaluated once ([`played`]);
/// the work stops at `cancel`, checked every [`MEASURE_FRAMES`] frames.
pub fn measure(entry: &RigEntry, graph: &Graph, cancel: &Cancel) -> Result<Vec<f32>, Cancelled> {
    let rig = entry.rig();
    let cpu = entry.prepared.cpu();
    let ranges = played(graph);
    // Per merged range, the step into each of its frames from the one before (0 for its first).
    let mut steps: Vec<Vec<f32>> = Vec::with_capacity(ranges.len());
    for &(clip, first, last) in &ranges {
        let mut step = Vec::with_capacity((last - first) as usize + 1);
        let mut prev: Option<Vec<f32>> = None;
        let mut at = first;
        while at <= last {
            cancel.check()?;
            let end = last.min(at.saturating_add(MEASURE_FRAMES as u32 - 1));
            let jobs: Vec<BlendJob> = (at..=end).map(|f| BlendJob::frame(clip, f, 0)).collect();
            let out = WeightBatch::gather(rig, &jobs)
                .ok()
                .and_then(|batch| cpu.evaluate(&batch, OutputSpec::default()).ok());
            for j in 0..jobs.len() {
                // A frame the engine could not evaluate (it evaluated each when the rig was
                // prepared) counts as no step, as before.
                let Some(p) = out.as_ref().map(|o| o.job_positions(j)) else {
                    step.push(0.0);
                    prev = None;
                    continue;
                };
                let d = prev.as_ref().map_or(0.0, |q| {
                    p.chunks_exact(3)
                        .zip(q.chunks_exact(3))
                        .map(|(a, b)| {
                            ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2))
                                .sqrt()
                        })
                        .fold(0.0, f32::max)
                });
                step.push(d);
                prev = Some(p);
            }
            if end == u32::MAX {
                break;
            }
            at = end + 1;
        }
        steps.push(step);
    }
    Ok(graph
        .nodes
        .iter()
        .map(|n| {
            let last = n.first + n.len - 1;
            // The merged range that holds the node: the last one of its clip starting at or
            // before its first frame.
            let k = ranges.partition_point(|&(c, a, _)| (c, a) <= (n.clip, n.first));
            let Some(r) = k.checked_sub(1) else {
                return 0.0;
            };
            let (_, start, _) = ranges[r];
            // Steps between the node's own frames: into its second through its last.
            let (a, b) = ((n.first - start) as usize + 1, (last - start) as usize);
            if a > b {
                return 0.0;
            }
            steps[r]
                .get(a..=b)
                .map_or(0.0, |s| s.iter().copied().fold(0.0, f32::max))
        })
        .collect())
}
