//! What the scene instances and what its animations' weight channels hold, read once and
//! charged: the scene's mesh instances with their world matrices, the target counts and names
//! of their meshes, and the decoded keyframes of every `weights` channel. The rig importer, the
//! weight-channel planner and the clip reader all read the document through these; this module
//! depends on none of them.

use std::sync::Arc;

use glam::Mat4;
use gltf::animation::{Interpolation as GltfInterpolation, Property};
use serde::Deserialize;

use super::ImportError;
use super::accessor::Source;
use crowdmorph_core::budget::Budget;
use crowdmorph_core::rig::{Interpolation, KeyTrack};

/// Deepest node hierarchy we follow.
const MAX_DEPTH: usize = 256;

/// Structural characters outside strings in a JSON text. Each starts at most one value or
/// object member, so together they bound how many nodes the parsed document has.
pub(crate) fn json_nodes(json: &[u8]) -> u64 {
    let (mut n, mut in_string, mut escaped) = (0u64, false, false);
    for &b in json {
        if in_string {
            if escaped {
                escaped = false;
            } else if b == b'\\' {
                escaped = true;
            } else if b == b'"' {
                in_string = false;
            }
        } else {
            match b {
                b'"' => in_string = true,
                b',' | b':' | b'[' | b'{' => n += 1,
                _ => {}
            }
        }
    }
    n
}

#[derive(Deserialize)]
struct MeshExtras {
    #[serde(rename = "targetNames")]
    target_names: Option<Vec<String>>,
}

/// Heap bytes a list of names holds: each `String`'s header and text.
pub(crate) fn names_bytes(names: &[String]) -> u64 {
    names.iter().map(|n| 24 + n.capacity() as u64).sum()
}

/// Target names of a mesh with `count` targets: `extras.targetNames`, else `target_<i>`. The
/// names are charged to `budget` before they are allocated, at a bound (each name holds at
/// most its own text, and a `String` header of 24 bytes, doubled for the list's growth, per
/// structural character of the extras: every list element but the first follows a comma),
/// which is brought down to the names' exact bytes once they are read. The caller releases
/// [`names_bytes`] of the result when it drops it.
fn mesh_target_names(
    mesh: &gltf::Mesh<'_>,
    count: usize,
    budget: &Budget,
) -> Result<Vec<String>, ImportError> {
    let what = || format!("target names of mesh {}", mesh_label(mesh));
    let mut names = None;
    if let Some(raw) = mesh.extras().as_ref() {
        let text = raw.get();
        let bound = text.len() as u64 + (json_nodes(text.as_bytes()) + 1) * 48;
        budget.charge(bound, what)?;
        names = serde_json::from_str::<MeshExtras>(raw.get())
            .ok()
            .and_then(|e| e.target_names)
            .filter(|n| n.len() == count)
            .map(|mut n| {
                n.shrink_to_fit();
                n
            });
        budget.release(bound);
    }
    // Exact once read; the generated names have at most 7 + 20 characters.
    let bytes = names
        .as_deref()
        .map_or(count as u64 * (24 + 27), names_bytes);
    budget.charge(bytes, what)?;
    let names = names.unwrap_or_else(|| (0..count).map(|i| format!("target_{i}")).collect());
    let exact = names_bytes(&names);
    budget.release(bytes.saturating_sub(exact));
    Ok(names)
}

/// The target names of every mesh the scene instances, read once per mesh however many nodes
/// instance it (see [`mesh_target_names`]), and charged while they are held.
pub(crate) struct MeshNames {
    /// Mesh index → its target names (empty for a mesh the scene does not instance).
    by_mesh: Vec<Vec<String>>,
    /// Bytes charged for them, released on drop.
    bytes: u64,
    budget: Arc<Budget>,
}

impl MeshNames {
    /// Reads the names of every mesh of `instances`, refusing meshes whose primitives disagree
    /// on their target count.
    pub(crate) fn read(
        doc: &gltf::Document,
        instances: &[Instance<'_>],
        budget: &Arc<Budget>,
    ) -> Result<MeshNames, ImportError> {
        let meshes = doc.meshes().len();
        let table = meshes as u64 * 24;
        budget.charge(table, || format!("target names of {meshes} meshes"))?;
        let mut out = MeshNames {
            by_mesh: vec![Vec::new(); meshes],
            bytes: table,
            budget: budget.clone(),
        };
        let mut done = vec![false; meshes];
        for inst in instances {
            let m = inst.mesh.index();
            if done.get(m).copied().unwrap_or(true) {
                continue;
            }
            done[m] = true;
            let count = mesh_target_count(&inst.mesh)?;
            let names = mesh_target_names(&inst.mesh, count, budget)?;
            out.bytes += names_bytes(&names);
            out.by_mesh[m] = names;
        }
        Ok(out)
    }

    /// The target names of `mesh` (empty when it was not read).
    pub(crate) fn of(&self, mesh: &gltf::Mesh<'_>) -> &[String] {
        self.by_mesh.get(mesh.index()).map_or(&[], Vec::as_slice)
    }
}

impl Drop for MeshNames {
    fn drop(&mut self) {
        self.budget.release(self.bytes);
    }
}

/// Number of morph targets of a mesh; all its primitives must agree (glTF 2.0 §3.7.2.2).
pub(crate) fn mesh_target_count(mesh: &gltf::Mesh<'_>) -> Result<usize, ImportError> {
    let mut counts = mesh.primitives().map(|p| p.morph_targets().len());
    let first = counts.next().unwrap_or(0);
    if let Some(other) = counts.find(|&c| c != first) {
        return Err(ImportError::Mesh {
            mesh: mesh_label(mesh),
            problem: format!("primitives have different target counts ({first} and {other})"),
        });
    }
    Ok(first)
}

pub(crate) fn mesh_label(mesh: &gltf::Mesh<'_>) -> String {
    mesh.name()
        .map_or_else(|| format!("#{}", mesh.index()), str::to_string)
}

/// A mesh instance found in the scene: which node, its world matrix.
pub(crate) struct Instance<'a> {
    pub(crate) node: gltf::Node<'a>,
    pub(crate) mesh: gltf::Mesh<'a>,
    pub(crate) world: Mat4,
}

/// The mesh instances of the default scene (or first scene, or all roots), in traversal order.
pub(crate) fn scene_instances(doc: &gltf::Document) -> Result<Vec<Instance<'_>>, ImportError> {
    let roots: Vec<gltf::Node<'_>> = match doc.default_scene().or_else(|| doc.scenes().next()) {
        Some(scene) => scene.nodes().collect(),
        None => {
            let mut is_child = vec![false; doc.nodes().len()];
            for n in doc.nodes() {
                for c in n.children() {
                    is_child[c.index()] = true;
                }
            }
            doc.nodes().filter(|n| !is_child[n.index()]).collect()
        }
    };
    let mut visited = vec![false; doc.nodes().len()];
    let mut out = Vec::new();
    let mut stack: Vec<(gltf::Node<'_>, Mat4, usize)> = roots
        .into_iter()
        .rev()
        .map(|n| (n, Mat4::IDENTITY, 0))
        .collect();
    while let Some((node, parent, depth)) = stack.pop() {
        if depth > MAX_DEPTH {
            return Err(ImportError::Invalid(format!(
                "node hierarchy deeper than {MAX_DEPTH}"
            )));
        }
        if std::mem::replace(&mut visited[node.index()], true) {
            return Err(ImportError::Invalid(format!(
                "node {} is reached twice (cycle or shared child)",
                node.index()
            )));
        }
        let local = Mat4::from_cols_array_2d(&node.transform().matrix());
        let world = parent * local;
        if !world.is_finite() {
            return Err(ImportError::Invalid(format!(
                "node {} has a non-finite transform",
                node.index()
            )));
        }
        if let Some(mesh) = node.mesh() {
            out.push(Instance {
                node: node.clone(),
                mesh,
                world,
            });
        }
        let children: Vec<_> = node.children().collect();
        for c in children.into_iter().rev() {
            stack.push((c, world, depth + 1));
        }
    }
    Ok(out)
}

/// Bytes the decoded keyframes of `tracks` hold (released once they are baked).
pub(crate) fn tracks_bytes(tracks: &[WeightTrack]) -> u64 {
    tracks
        .iter()
        .map(|t| (t.track.times.len() + t.track.values.len()) as u64 * 4)
        .sum()
}

/// One `weights` channel, decoded. Which weight channels its scalars write is the caller's
/// business (see the importer's `bake`): the rig's own file writes each node's channels, a clip
/// by name every channel of the name.
pub(crate) struct WeightTrack {
    /// The node the channel animates.
    pub(crate) node: usize,
    /// The accessor of its key times (whose declared `max` may stand for the last one).
    pub(crate) times_accessor: usize,
    pub(crate) track: KeyTrack,
}

/// The weight tracks of one animation of the rig's file, decoded while planning the channels
/// and kept until they are baked.
pub(crate) struct AnimationTracks {
    /// The animation's index in the document.
    pub(crate) index: usize,
    pub(crate) tracks: Vec<WeightTrack>,
}

/// Reads the `weights` channels of one animation. `width(node)` is the number of morph targets
/// of the node's mesh, `None` for a node outside the rig (its channels are skipped).
pub(crate) fn weight_tracks(
    source: &Source<'_>,
    anim: &gltf::Animation<'_>,
    width: &dyn Fn(&gltf::Node<'_>) -> Option<usize>,
) -> Result<Vec<WeightTrack>, ImportError> {
    let label = anim
        .name()
        .map_or_else(|| format!("#{}", anim.index()), str::to_string);
    let bad = |problem: String| ImportError::Animation {
        animation: label.clone(),
        problem,
    };
    let mut tracks = Vec::new();
    for channel in anim.channels() {
        if channel.target().property() != Property::MorphTargetWeights {
            continue;
        }
        let node = channel.target().node();
        let Some(width) = width(&node) else {
            tracing::warn!(animation = %label, node = node.index(), "weights channel targets a node outside the rig; ignored");
            continue;
        };
        let sampler = channel.sampler();
        let input = sampler.input();
        if input.dimensions() != gltf::accessor::Dimensions::Scalar {
            return Err(bad("sampler input must be SCALAR times".into()));
        }
        let times = source.read_f32(&input)?;
        let values = source.read_f32(&sampler.output())?;
        let interpolation = match sampler.interpolation() {
            GltfInterpolation::Step => Interpolation::Step,
            GltfInterpolation::Linear => Interpolation::Linear,
            GltfInterpolation::CubicSpline => Interpolation::CubicSpline,
        };
        let track = KeyTrack {
            times,
            values,
            width,
            interpolation,
        };
        track.check().map_err(&bad)?;
        tracks.push(WeightTrack {
            node: node.index(),
            times_accessor: input.index(),
            track,
        });
    }
    Ok(tracks)
}
