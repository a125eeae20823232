//! Weight channels: which (node, morph target) pairs of a glTF file share one weight.
//!
//! glTF animates morph weights per node: a `weights` channel drives the targets of one node's
//! mesh, and a node no channel animates stays at its default weights (`node.weights`, else
//! `mesh.weights`, else 0). A rig addresses weights rig-wide, one row of every clip table per
//! *channel*. The plain mapping — one channel per target name — is right whenever every node
//! that has a name behaves the same for it (the usual case: a face capture writes the same
//! curve to the head, the teeth and the eyes) and wrong otherwise (a clip that animates the head
//! alone would move the teeth too).
//!
//! So the importer partitions the pairs by behaviour: two pairs share a channel exactly when
//! they have the same name (and the same occurrence of it within their mesh), the same default
//! weight and, in every animation, the same curve — the same interpolation, key times and
//! values, compared bit for bit — or no curve at all. A rig whose nodes share curves therefore
//! gets exactly one channel per name, in the order the names first appear, as before; only
//! the pairs that differ get channels of their own, appended after them. Engines, clip tables
//! and LOD need no other change: a split name is just more channels.

use std::collections::HashMap;
use std::collections::hash_map::DefaultHasher;
use std::hash::{Hash, Hasher};

use super::ImportError;
use super::accessor::Source;
use super::scene::{
    AnimationTracks, Instance, MeshNames, WeightTrack, mesh_target_count, weight_tracks,
};
use crowdmorph_core::rig::{Interpolation, MAX_TARGETS, RigError, TargetId};

/// The channels of a document: their names and default weights, and the channel of each
/// (node, morph target index) pair of the scene's mesh instances.
#[derive(Clone, Debug, Default, PartialEq)]
pub(crate) struct ChannelPlan {
    /// Target name of each channel.
    pub(crate) names: Vec<String>,
    /// Default weight of each channel.
    pub(crate) defaults: Vec<f32>,
    /// Node index → the channel of each of its mesh's targets.
    pub(crate) node_channels: HashMap<usize, Vec<TargetId>>,
}

impl ChannelPlan {
    /// Number of channels.
    pub(crate) fn len(&self) -> usize {
        self.names.len()
    }
}

/// One (node, target) pair: where it is and what it starts as.
struct Unit {
    /// Index of the instance (scene traversal order).
    instance: usize,
    /// Morph target index within the node's mesh.
    k: usize,
    /// Equivalence class so far.
    class: usize,
}

/// A class found while refining: (its first unit, the track that drives it, its new class
/// id).
type Representative = (usize, usize, usize);

/// Bytes the plan's bookkeeping holds per (node, target) pair, charged before it is built.
const UNIT_BYTES: u64 = 64;

/// Default weight of each of a node's `count` targets: `node.weights`, else `mesh.weights`,
/// else 0 (glTF 2.0 §3.7.2.1); arrays of the wrong length are ignored.
pub(crate) fn node_defaults(inst: &Instance<'_>, count: usize) -> Vec<f32> {
    inst.node
        .weights()
        .filter(|w| w.len() == count)
        .or_else(|| inst.mesh.weights().filter(|w| w.len() == count))
        .map_or_else(|| vec![0.0; count], <[f32]>::to_vec)
}

/// The curve of component `k` of `track`: its interpolation, times and values, for hashing
/// and bitwise comparison.
struct Curve<'t> {
    track: &'t WeightTrack,
    k: usize,
}

impl Curve<'_> {
    /// The values of component `k`, key by key (with both tangents for CUBICSPLINE).
    fn values(&self) -> impl Iterator<Item = f32> + '_ {
        let t = &self.track.track;
        let width = t.width;
        let parts = if t.interpolation == Interpolation::CubicSpline {
            3
        } else {
            1
        };
        (0..t.times.len() * parts)
            .map(move |i| t.values.get(i * width + self.k).copied().unwrap_or(0.0))
    }

    fn hash(&self) -> u64 {
        let mut h = DefaultHasher::new();
        (self.track.track.interpolation as u8).hash(&mut h);
        for t in &self.track.track.times {
            t.to_bits().hash(&mut h);
        }
        for v in self.values() {
            v.to_bits().hash(&mut h);
        }
        h.finish()
    }

    fn same(&self, other: &Curve<'_>) -> bool {
        let (a, b) = (&self.track.track, &other.track.track);
        a.interpolation == b.interpolation
            && a.times.len() == b.times.len()
            && a.times
                .iter()
                .zip(&b.times)
                .all(|(x, y)| x.to_bits() == y.to_bits())
            && self
                .values()
                .zip(other.values())
                .all(|(x, y)| x.to_bits() == y.to_bits())
    }
}

/// Partitions the (node, target) pairs of `instances` into weight channels by their names
/// (`names`, read once per mesh), default weights and the curves every animation gives them
/// (see the module documentation). Every animation's keyframes are decoded once, charged to
/// the source's budget, and returned with the plan (still charged) for baking; the channel
/// names the plan keeps are charged too. More than [`MAX_TARGETS`] channels is refused.
pub(crate) fn plan_channels(
    doc: &gltf::Document,
    source: &Source<'_>,
    instances: &[Instance<'_>],
    names: &MeshNames,
) -> Result<(ChannelPlan, Vec<AnimationTracks>), ImportError> {
    let budget = source.budget();
    let mut counts = Vec::with_capacity(instances.len());
    for inst in instances {
        counts.push(mesh_target_count(&inst.mesh)?);
    }
    let total: u64 = counts.iter().map(|&c| c as u64).sum();
    let bookkeeping = total.saturating_mul(UNIT_BYTES);
    budget.charge(bookkeeping, || {
        format!("weight channels of {total} (node, target) pairs")
    })?;

    // Initial classes: name, occurrence of the name within the mesh, default weight.
    let mut units = Vec::with_capacity(total as usize);
    let mut names_of = Vec::with_capacity(instances.len());
    let mut classes: HashMap<(&str, usize, u32), usize> = HashMap::new();
    let mut n_classes = 0;
    // Each instance's units are contiguous: instance i's are `first_unit[i]..first_unit[i + 1]`.
    let mut first_unit = Vec::with_capacity(instances.len() + 1);
    for (i, inst) in instances.iter().enumerate() {
        first_unit.push(units.len());
        let count = counts[i];
        let names = names.of(&inst.mesh);
        let defaults = node_defaults(inst, count);
        let mut seen: HashMap<&str, usize> = HashMap::new();
        for (k, name) in names.iter().enumerate() {
            let occurrence = seen.entry(name.as_str()).or_default();
            let key = (name.as_str(), *occurrence, defaults[k].to_bits());
            *occurrence += 1;
            let class = *classes.entry(key).or_insert_with(|| {
                n_classes += 1;
                n_classes - 1
            });
            units.push(Unit {
                instance: i,
                k,
                class,
            });
        }
        names_of.push((names, defaults));
    }
    first_unit.push(units.len());
    drop(classes);

    // Refinement: in each animation, a class splits by the curves its members get.
    let node_instance: HashMap<usize, usize> = instances
        .iter()
        .enumerate()
        .map(|(i, inst)| (inst.node.index(), i))
        .collect();
    let width = |node: &gltf::Node<'_>| node_instance.get(&node.index()).map(|&i| counts[i]);
    let mut animations = Vec::new();
    for anim in doc.animations() {
        let tracks = weight_tracks(source, &anim, &width)?;
        if tracks.is_empty() {
            continue;
        }
        // The track that drives each instance (a later channel on the same node wins, as in
        // baking).
        let mut driven: HashMap<usize, usize> = HashMap::new();
        for (j, t) in tracks.iter().enumerate() {
            if let Some(&i) = node_instance.get(&t.node) {
                driven.insert(i, j);
            }
        }
        // Only the units of driven nodes can leave their class: each (class, curve) group of
        // them gets a fresh class id, the others keep theirs. The partition is the one a pass
        // over every unit gives, for work in the driven pairs (bounded by the decoded
        // keyframes) instead of every pair of the scene per animation, which made a file of
        // many one-track animations over a large scene quadratic.
        let mut driven_instances: Vec<(usize, usize)> =
            driven.iter().map(|(&i, &j)| (i, j)).collect();
        driven_instances.sort_unstable();
        let curve = |ui: usize, track: usize| Curve {
            track: &tracks[track],
            k: units[ui].k,
        };
        // New class of each driven unit: (old class, curve hash) buckets, each holding the
        // representatives found so far (more than one only on a hash collision) and the track
        // that drives them.
        let mut buckets: HashMap<(usize, u64), Vec<Representative>> = HashMap::new();
        let mut moved: Vec<(usize, usize)> = Vec::new();
        for &(i, j) in &driven_instances {
            let range = first_unit.get(i).copied().unwrap_or(0)
                ..first_unit.get(i + 1).copied().unwrap_or(0);
            for ui in range {
                let c = curve(ui, j);
                let reps = buckets.entry((units[ui].class, c.hash())).or_default();
                let found = reps
                    .iter()
                    .find(|&&(rep, track, _)| c.same(&curve(rep, track)));
                let class = match found {
                    Some(&(_, _, class)) => class,
                    None => {
                        reps.push((ui, j, n_classes));
                        n_classes += 1;
                        n_classes - 1
                    }
                };
                moved.push((ui, class));
            }
        }
        drop(buckets);
        for (ui, class) in moved {
            units[ui].class = class;
        }
        animations.push(AnimationTracks {
            index: anim.index(),
            tracks,
        });
    }

    // Channel ids: first the class of each name's first pair, in the order names first
    // appear (one channel per name when nothing splits, as a plain name mapping gives), then
    // every other class in the order its first pair appears.
    // Class ids grew with every split: number them densely (the partition is what counts).
    let mut dense: HashMap<usize, usize> = HashMap::new();
    for u in &mut units {
        let next = dense.len();
        u.class = *dense.entry(u.class).or_insert(next);
    }
    let n_classes = dense.len();
    drop(dense);
    let mut channel_of = vec![None::<TargetId>; n_classes];
    let mut plan = ChannelPlan::default();
    let mut named: std::collections::HashSet<&str> = std::collections::HashSet::new();
    for pass in 0..2 {
        for u in &units {
            let (names, defaults) = &names_of[u.instance];
            let name = names[u.k].as_str();
            if channel_of[u.class].is_some() || (pass == 0 && named.contains(name)) {
                continue;
            }
            named.insert(name);
            channel_of[u.class] = Some(plan.names.len() as TargetId);
            if plan.names.len() >= MAX_TARGETS {
                return Err(RigError::TooLarge(format!(
                    "more than {MAX_TARGETS} weight channels (targets, counted once per \
                     differently animated node)"
                ))
                .into());
            }
            // The plan's names become the rig's: charged here, kept by the import.
            budget.charge(24 + name.len() as u64, || {
                format!("the name of weight channel {}", plan.names.len())
            })?;
            plan.names.push(name.to_string());
            plan.defaults.push(defaults[u.k]);
        }
    }
    for (i, inst) in instances.iter().enumerate() {
        plan.node_channels
            .insert(inst.node.index(), Vec::with_capacity(counts[i]));
    }
    for u in &units {
        let id = channel_of[u.class].unwrap_or_default();
        if let Some(v) = plan
            .node_channels
            .get_mut(&instances[u.instance].node.index())
        {
            v.push(id);
        }
    }
    drop(units);
    drop(names_of);
    // What stays is the node → channel map (4 bytes a pair) and the channel names.
    budget.release(bookkeeping.saturating_sub(total * 4));
    Ok((plan, animations))
}

/// How many (node, target) pairs of `by_node` write each of `channels` weight channels, for
/// [`curves_agree`].
pub(crate) fn channel_writers(
    by_node: &HashMap<usize, Vec<Vec<TargetId>>>,
    channels: usize,
) -> Vec<u32> {
    let mut writers = vec![0u32; channels];
    for ids in by_node.values() {
        for &c in ids.iter().flatten() {
            if let Some(w) = writers.get_mut(c as usize) {
                *w += 1;
            }
        }
    }
    writers
}

/// Checks that an animation matched node by node onto `rig` gives every weight channel one
/// curve: all the (node, target) pairs that write a channel (`by_node`: node → channels of
/// each target; `writers`: how many pairs write each channel, from [`channel_writers`]) get
/// the same curve from `tracks`, or none. A rig made its channels from its
/// own file's animations, so a later animation that moves two nodes apart where the rig moves
/// them together cannot be played as glTF viewers would; the message names both nodes.
pub(crate) fn curves_agree(
    rig: &crowdmorph_core::rig::Rig,
    tracks: &[WeightTrack],
    by_node: &HashMap<usize, Vec<Vec<TargetId>>>,
    writers: &[u32],
) -> Result<(), String> {
    let driven: HashMap<usize, &WeightTrack> = tracks.iter().map(|t| (t.node, t)).collect();
    // The common case, in the driven pairs only: a channel agrees when every pair that writes
    // it is driven (`writers` counts them) with one curve, or none is driven. Only when that
    // fails are all pairs walked in node order, for the message naming the first two nodes
    // that differ (a walk of every pair per animation made many animations quadratic).
    let mut seen: HashMap<TargetId, (u32, Curve<'_>)> = HashMap::new();
    let mut agree = true;
    let mut driven_nodes: Vec<(&usize, &&WeightTrack)> = driven.iter().collect();
    driven_nodes.sort_unstable_by_key(|&(n, _)| *n);
    'pairs: for (node, &track) in driven_nodes {
        let Some(ids) = by_node.get(node) else {
            continue;
        };
        for (k, channels) in ids.iter().enumerate() {
            for &c in channels {
                let curve = Curve { track, k };
                match seen.get_mut(&c) {
                    None => {
                        seen.insert(c, (1, curve));
                    }
                    Some((n, first)) if first.same(&curve) => *n += 1,
                    Some(_) => {
                        agree = false;
                        break 'pairs;
                    }
                }
            }
        }
    }
    if agree
        && seen
            .iter()
            .all(|(&c, (n, _))| writers.get(c as usize).is_some_and(|&w| w == *n))
    {
        return Ok(());
    }
    let mut nodes: Vec<(usize, &Vec<Vec<TargetId>>)> =
        by_node.iter().map(|(&n, ids)| (n, ids)).collect();
    nodes.sort_unstable_by_key(|&(n, _)| n);
    let mut first: HashMap<TargetId, (usize, Option<Curve<'_>>)> = HashMap::new();
    for (node, ids) in nodes {
        for (k, channels) in ids.iter().enumerate() {
            for &c in channels {
                let curve = driven.get(&node).map(|&track| Curve { track, k });
                match first.get(&c) {
                    None => {
                        first.insert(c, (node, curve));
                    }
                    Some((other, seen)) => {
                        let agree = match (seen, &curve) {
                            (Some(a), Some(b)) => a.same(b),
                            (None, None) => true,
                            _ => false,
                        };
                        if !agree {
                            let name = rig.targets.get(c as usize).map_or("?", String::as_str);
                            return Err(format!(
                                "nodes {other} and {node} get different curves for target \
                                 {name:?}, which rig {:?} drives with one weight channel (its own \
                                 animations move those nodes alike); add this animation to the \
                                 rig's file and upload the rig again, or send it as a CSV or \
                                 JSON clip, which drives every node by name",
                                rig.name
                            ));
                        }
                    }
                }
            }
        }
    }
    Ok(())
}
