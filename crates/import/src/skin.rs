//! Skins and node animation of a glTF file, as the rig's [`Skeleton`].
//!
//! Which primitives follow nodes (see `crates/core/src/rig/skin.rs` for the model):
//! - a mesh instance whose node has a `skin` is skinned: its `JOINTS_n`/`WEIGHTS_n` sets name
//!   the skin's joints, at most four kept per vertex (the largest, renormalized; the largest
//!   weight dropped is reported);
//! - an instance without a skin whose node, or an ancestor of it, is animated by a
//!   translation, rotation or scale channel hangs rigidly from its node;
//! - any other instance is static.
//!
//! The skeleton keeps the nodes bones depend on (each bone's node and its ancestors), parents
//! first. Translation, rotation and scale channels on those nodes are baked per clip into a
//! [`JointTable`] at the clip's rate (rotations by slerp, as glTF asks); channels on nodes
//! that move no mesh change nothing drawn and are left out (counted in the report).

use std::collections::{HashMap, HashSet};

use glam::Mat4;
use gltf::animation::Property;

use super::ImportError;
use super::accessor::Source;
use super::scene::Instance;
use crowdmorph_core::budget::Budget;
use crowdmorph_core::rig::{
    Bone, INFLUENCES, Influences, Interpolation, JointTable, KeyTrack, MAX_BONES, NO_PARENT,
    SkelNode, Skeleton, Trs, WEIGHT_SUM_TOLERANCE, sample_rotation, sample_track, top_influences,
};

/// How one mesh instance follows the skeleton.
#[derive(Clone, Debug)]
pub(crate) enum Attach {
    /// Every vertex on one bone.
    Rigid(u16),
    /// Skinned: `world` is the `C` its vertices are stored under in rig space (see
    /// `crates/core/src/rig/skin.rs`), `bones` the bone of each of the skin's joints.
    Skinned { world: Mat4, bones: Vec<u16> },
}

/// The skeleton a file's scene needs, and how each mesh instance follows it.
pub(crate) struct SkeletonPlan {
    pub(crate) skeleton: Skeleton,
    /// glTF node index → skeleton node.
    pub(crate) node_ids: HashMap<usize, u32>,
    /// Mesh instance node index → how it follows.
    pub(crate) attach: HashMap<usize, Attach>,
    /// Bytes charged for the skeleton while it is built.
    pub(crate) charged: u64,
}

/// What the import did with skins and node animation, for the upload's answer and `inspect`.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SkinReport {
    /// Translation, rotation and scale channels baked into clips.
    pub joint_channels: usize,
    /// Such channels on nodes that move no mesh (left out).
    pub channels_on_unused_nodes: usize,
    /// The largest weight dropped from a vertex with more than four influences.
    pub largest_dropped_weight: f32,
}

impl SkinReport {
    /// What the import approximated or left out, a sentence each (`Rig::import_notes`).
    pub fn notes(&self) -> Vec<String> {
        let mut notes = Vec::new();
        if self.channels_on_unused_nodes > 0 {
            notes.push(format!(
                "{} translation/rotation/scale animation channels target nodes that move no mesh \
                 (no skin uses them and no mesh hangs from them): left out",
                self.channels_on_unused_nodes
            ));
        }
        if self.largest_dropped_weight > 0.0 {
            notes.push(format!(
                "vertices with more than {INFLUENCES} joint influences keep their largest \
                 {INFLUENCES}, renormalized; the largest weight dropped is {:.4}",
                self.largest_dropped_weight
            ));
        }
        notes
    }
}

fn parents(doc: &gltf::Document) -> Vec<Option<usize>> {
    let mut parent = vec![None; doc.nodes().len()];
    for n in doc.nodes() {
        for c in n.children() {
            parent[c.index()] = Some(n.index());
        }
    }
    parent
}

/// Nodes animated by translation, rotation or scale channels in any animation.
fn animated_nodes(doc: &gltf::Document) -> HashSet<usize> {
    doc.animations()
        .flat_map(|a| a.channels())
        .filter(|c| c.target().property() != Property::MorphTargetWeights)
        .map(|c| c.target().node().index())
        .collect()
}

fn chain(parent: &[Option<usize>], mut n: usize) -> Result<Vec<usize>, ImportError> {
    let mut out = vec![n];
    while let Some(p) = parent[n] {
        if out.len() > 256 {
            return Err(ImportError::Invalid(
                "node hierarchy deeper than 256 (or cyclic)".into(),
            ));
        }
        out.push(p);
        n = p;
    }
    Ok(out)
}

fn rest(doc: &gltf::Document, n: usize) -> Trs {
    let (t, r, s) = doc
        .nodes()
        .nth(n)
        .map_or(([0.0; 3], [0.0, 0.0, 0.0, 1.0], [1.0; 3]), |node| {
            node.transform().decomposed()
        });
    Trs {
        translation: t,
        rotation: r,
        scale: s,
    }
}

fn rest_global(
    doc: &gltf::Document,
    parent: &[Option<usize>],
    n: usize,
) -> Result<Mat4, ImportError> {
    let mut m = Mat4::IDENTITY;
    for a in chain(parent, n)? {
        let node = doc
            .nodes()
            .nth(a)
            .ok_or_else(|| ImportError::Invalid(format!("node {a} is missing")))?;
        m = Mat4::from_cols_array_2d(&node.transform().matrix()) * m;
    }
    Ok(m)
}

fn invert(m: Mat4, what: impl Fn() -> String) -> Result<Mat4, ImportError> {
    let inv = m.inverse();
    if !m.is_finite() || m.determinant().abs() <= f32::MIN_POSITIVE || !inv.is_finite() {
        return Err(ImportError::Invalid(format!(
            "{} is singular or not finite",
            what()
        )));
    }
    Ok(inv)
}

/// Plans the skeleton of `instances`; `None` when no instance follows a node.
pub(crate) fn plan(
    doc: &gltf::Document,
    source: &Source<'_>,
    instances: &[Instance<'_>],
) -> Result<Option<SkeletonPlan>, ImportError> {
    let parent = parents(doc);
    let animated = animated_nodes(doc);
    let mut needed: Vec<usize> = Vec::new();
    let mut follows = Vec::new();
    for inst in instances {
        let node = inst.node.index();
        if let Some(skin) = inst.node.skin() {
            let joints: Vec<usize> = skin.joints().map(|j| j.index()).collect();
            if joints.is_empty() || joints.len() > MAX_BONES {
                return Err(ImportError::Invalid(format!(
                    "skin {} has {} joints (1 to {MAX_BONES} are supported)",
                    skin.index(),
                    joints.len()
                )));
            }
            for &j in &joints {
                needed.extend(chain(&parent, j)?);
            }
            follows.push((node, Some(skin)));
        } else if chain(&parent, node)?.iter().any(|a| animated.contains(a)) {
            needed.extend(chain(&parent, node)?);
            follows.push((node, None));
        }
    }
    if follows.is_empty() {
        return Ok(None);
    }
    needed.sort_unstable();
    needed.dedup();
    // Parents before children: by depth, then index.
    let depth = |n: usize| chain(&parent, n).map(|c| c.len());
    let mut keyed = Vec::with_capacity(needed.len());
    for n in needed {
        keyed.push((depth(n)?, n));
    }
    keyed.sort_unstable();
    let budget: &Budget = source.budget();
    let charged = keyed.len() as u64 * 160;
    budget.charge(charged, || "the skeleton's nodes".into())?;
    let node_ids: HashMap<usize, u32> = keyed
        .iter()
        .enumerate()
        .map(|(i, &(_, n))| (n, i as u32))
        .collect();
    let nodes: Vec<SkelNode> = keyed
        .iter()
        .map(|&(_, n)| SkelNode {
            name: doc
                .nodes()
                .nth(n)
                .and_then(|x| x.name().map(str::to_string))
                .filter(|s| !s.is_empty())
                .unwrap_or_else(|| format!("node{n}")),
            parent: parent[n]
                .and_then(|p| node_ids.get(&p).copied())
                .unwrap_or(NO_PARENT),
            rest: rest(doc, n),
        })
        .collect();
    let mut bones: Vec<Bone> = Vec::new();
    let mut bone_ids: HashMap<(u32, [u32; 16]), u16> = HashMap::new();
    let mut bone = |node: usize, bind: Mat4| -> Result<u16, ImportError> {
        let id = node_ids[&node];
        let bind = bind.to_cols_array();
        let key = (id, bind.map(f32::to_bits));
        if let Some(&b) = bone_ids.get(&key) {
            return Ok(b);
        }
        if bones.len() >= MAX_BONES {
            return Err(ImportError::Invalid(format!("more than {MAX_BONES} bones")));
        }
        budget.charge(96, || "a bone".into())?;
        bones.push(Bone { node: id, bind });
        let b = (bones.len() - 1) as u16;
        bone_ids.insert(key, b);
        Ok(b)
    };
    let mut attach = HashMap::new();
    for (node, skin) in follows {
        match skin {
            None => {
                let g = rest_global(doc, &parent, node)?;
                let bind = invert(g, || format!("node {node}'s rest transform"))?;
                attach.insert(node, Attach::Rigid(bone(node, bind)?));
            }
            Some(skin) => {
                let joints: Vec<usize> = skin.joints().map(|j| j.index()).collect();
                let ibms = match skin.inverse_bind_matrices() {
                    Some(acc) => {
                        let m = source.read_mat4s(&acc)?;
                        if m.len() < joints.len() {
                            return Err(ImportError::Invalid(format!(
                                "skin {}: {} inverse bind matrices for {} joints",
                                skin.index(),
                                m.len(),
                                joints.len()
                            )));
                        }
                        m
                    }
                    None => vec![Mat4::IDENTITY; joints.len()],
                };
                if let Some(k) = ibms.iter().position(|m| !m.is_finite()) {
                    return Err(ImportError::Invalid(format!(
                        "skin {}: inverse bind matrix {k} is not finite",
                        skin.index()
                    )));
                }
                let c = rest_global(doc, &parent, joints[0])? * ibms[0];
                let c_inv = invert(c, || format!("skin {}'s bind pose", skin.index()))?;
                let mut ids = Vec::with_capacity(joints.len());
                for (j, m) in joints.iter().zip(&ibms) {
                    ids.push(bone(*j, *m * c_inv)?);
                }
                source.budget().release(ibms.len() as u64 * 64);
                attach.insert(
                    node,
                    Attach::Skinned {
                        world: c,
                        bones: ids,
                    },
                );
            }
        }
    }
    Ok(Some(SkeletonPlan {
        skeleton: Skeleton {
            nodes,
            bones,
            map: None,
        },
        node_ids,
        attach,
        charged,
    }))
}

/// A primitive's influences: every vertex on one bone, or its skin's joint sets mapped to
/// bones. `report` gets the largest weight dropped past four influences.
pub(crate) fn influences(
    source: &Source<'_>,
    prim: &gltf::Primitive<'_>,
    attach: &Attach,
    vertices: usize,
    report: &mut SkinReport,
) -> Result<Influences, ImportError> {
    let budget = source.budget();
    budget.charge(vertices as u64 * 24, || "joint influences".into())?;
    let bones = match attach {
        Attach::Rigid(b) => {
            return Ok(Influences {
                joints: vec![[*b, 0, 0, 0]; vertices],
                weights: vec![[1.0, 0.0, 0.0, 0.0]; vertices],
            });
        }
        Attach::Skinned { bones, .. } => bones,
    };
    let mut sets = Vec::new();
    for k in 0.. {
        let (Some(j), Some(w)) = (
            prim.get(&gltf::Semantic::Joints(k)),
            prim.get(&gltf::Semantic::Weights(k)),
        ) else {
            break;
        };
        for a in [&j, &w] {
            if a.count() != vertices {
                return Err(ImportError::Accessor {
                    index: a.index(),
                    problem: format!("has {} elements for {vertices} vertices", a.count()),
                });
            }
        }
        sets.push((source.read_vec4s(&j)?, source.read_vec4s(&w)?));
    }
    if sets.is_empty() {
        return Err(ImportError::Mesh {
            mesh: format!("primitive {}", prim.index()),
            problem: "is skinned but has no JOINTS_0 and WEIGHTS_0".into(),
        });
    }
    let mut out = Influences {
        joints: Vec::with_capacity(vertices),
        weights: Vec::with_capacity(vertices),
    };
    let mut pairs = Vec::with_capacity(sets.len() * 4);
    for v in 0..vertices {
        pairs.clear();
        for (j, w) in &sets {
            for c in 0..4 {
                let (joint, weight) = (j[v][c], w[v][c]);
                if weight == 0.0 {
                    continue;
                }
                let ok = joint >= 0.0 && joint.fract() == 0.0 && (joint as usize) < bones.len();
                if !ok {
                    return Err(ImportError::Mesh {
                        mesh: format!("primitive {}", prim.index()),
                        problem: format!(
                            "vertex {v} names joint {joint} of a {}-joint skin",
                            bones.len()
                        ),
                    });
                }
                if !weight.is_finite() || weight < 0.0 {
                    return Err(ImportError::Mesh {
                        mesh: format!("primitive {}", prim.index()),
                        problem: format!("vertex {v} has joint weight {weight}"),
                    });
                }
                pairs.push((bones[joint as usize], weight));
            }
        }
        let sum: f32 = pairs.iter().map(|p| p.1).sum();
        if (sum - 1.0).abs() > WEIGHT_SUM_TOLERANCE {
            return Err(ImportError::Mesh {
                mesh: format!("primitive {}", prim.index()),
                problem: format!(
                    "vertex {v}'s joint weights sum to {sum}, not 1 (within {WEIGHT_SUM_TOLERANCE})"
                ),
            });
        }
        // Equal bones (two joints of one skin can share one) merge before the top four.
        pairs.sort_unstable_by_key(|p| p.0);
        pairs.dedup_by(|b, a| {
            if a.0 == b.0 {
                a.1 += b.1;
                true
            } else {
                false
            }
        });
        let (j, w, dropped) = top_influences(&mut pairs);
        report.largest_dropped_weight = report.largest_dropped_weight.max(dropped);
        out.joints.push(j);
        out.weights.push(w);
    }
    let read = sets.len() as u64 * vertices as u64 * 32;
    drop(sets);
    budget.release(read);
    debug_assert_eq!(INFLUENCES, 4);
    Ok(out)
}

/// One decoded translation, rotation or scale channel of a skeleton node.
struct NodeTrack {
    node: u32,
    property: Property,
    track: KeyTrack,
}

/// The translation, rotation and scale channels of animation `anim` on skeleton nodes,
/// decoded (charged through `source`), and how many it had on other nodes.
fn node_tracks(
    source: &Source<'_>,
    anim: &gltf::Animation<'_>,
    node_ids: &HashMap<usize, u32>,
) -> Result<(Vec<NodeTrack>, usize), ImportError> {
    let label = anim
        .name()
        .map_or_else(|| format!("#{}", anim.index()), str::to_string);
    let bad = |problem: String| ImportError::Animation {
        animation: label.clone(),
        problem,
    };
    let mut out = Vec::new();
    let mut unused = 0;
    for ch in anim.channels() {
        let property = ch.target().property();
        if property == Property::MorphTargetWeights {
            continue;
        }
        let Some(&node) = node_ids.get(&ch.target().node().index()) else {
            unused += 1;
            continue;
        };
        let sampler = ch.sampler();
        let width = if property == Property::Rotation { 4 } else { 3 };
        let interpolation = match sampler.interpolation() {
            gltf::animation::Interpolation::Step => Interpolation::Step,
            gltf::animation::Interpolation::Linear => Interpolation::Linear,
            gltf::animation::Interpolation::CubicSpline => Interpolation::CubicSpline,
        };
        let output = sampler.output();
        let want = if property == Property::Rotation {
            gltf::accessor::Dimensions::Vec4
        } else {
            gltf::accessor::Dimensions::Vec3
        };
        if output.dimensions() != want {
            return Err(bad(format!(
                "a {property:?} channel's output must be {want:?}, not {:?}",
                output.dimensions()
            )));
        }
        let track = KeyTrack {
            times: source.read_f32(&sampler.input())?,
            values: source.read_f32(&output)?,
            width,
            interpolation,
        };
        track.check().map_err(&bad)?;
        out.push(NodeTrack {
            node,
            property,
            track,
        });
    }
    Ok((out, unused))
}

/// The joint channels of animation `anim`, decoded: what [`bake_joints`] takes.
pub(crate) struct JointTracks {
    tracks: Vec<NodeTrack>,
    bytes: u64,
}

impl JointTracks {
    /// The last key time of any channel (0 with none).
    pub(crate) fn last_time(&self) -> f32 {
        self.tracks
            .iter()
            .map(|t| t.track.last_time())
            .fold(0.0, f32::max)
    }

    /// Whether the animation moves any skeleton node.
    pub(crate) fn is_empty(&self) -> bool {
        self.tracks.is_empty()
    }
}

/// Decodes animation `anim`'s joint channels.
pub(crate) fn joint_tracks(
    source: &Source<'_>,
    anim: &gltf::Animation<'_>,
    plan: &SkeletonPlan,
    report: &mut SkinReport,
) -> Result<JointTracks, ImportError> {
    let (tracks, unused) = node_tracks(source, anim, &plan.node_ids)?;
    report.joint_channels += tracks.len();
    report.channels_on_unused_nodes += unused;
    let bytes = tracks
        .iter()
        .map(|t| (t.track.times.len() + t.track.values.len()) as u64 * 4)
        .sum();
    Ok(JointTracks { tracks, bytes })
}

/// Bakes `tracks` at `fps` into a table of `frames` frames (frame `f` at `f / fps` s), then
/// releases the keyframes' charge.
pub(crate) fn bake_joints(
    name: &str,
    tracks: JointTracks,
    skeleton: &Skeleton,
    frames: usize,
    fps: f32,
    budget: &Budget,
) -> Result<Option<JointTable>, ImportError> {
    if tracks.tracks.is_empty() {
        budget.release(tracks.bytes);
        return Ok(None);
    }
    let mut nodes: Vec<u32> = tracks.tracks.iter().map(|t| t.node).collect();
    nodes.sort_unstable();
    nodes.dedup();
    let len = frames * nodes.len() * Trs::FLOATS;
    budget.charge(len as u64 * 4, || {
        format!(
            "joint table of clip {name:?} ({} nodes × {frames} frames)",
            nodes.len()
        )
    })?;
    let mut values = Vec::with_capacity(len);
    for _ in 0..frames {
        for &n in &nodes {
            values.extend_from_slice(&skeleton.nodes[n as usize].rest.floats());
        }
    }
    for t in &tracks.tracks {
        let k = nodes.binary_search(&t.node).unwrap_or(0);
        let (at, width) = match t.property {
            Property::Translation => (0, 3),
            Property::Rotation => (3, 4),
            _ => (7, 3),
        };
        for f in 0..frames {
            let time = f as f32 / fps;
            let row = (f * nodes.len() + k) * Trs::FLOATS + at;
            if width == 4 {
                let mut q = [0.0; 4];
                sample_rotation(&t.track, time, &mut q);
                values[row..row + 4].copy_from_slice(&q);
            } else {
                let mut v = [0.0; 3];
                sample_track(&t.track, time, &mut v);
                values[row..row + 3].copy_from_slice(&v);
            }
        }
    }
    budget.release(tracks.bytes);
    if !values.iter().all(|v| v.is_finite()) {
        return Err(ImportError::Animation {
            animation: name.to_string(),
            problem: "a joint channel samples to a non-finite transform".into(),
        });
    }
    Ok(Some(JointTable {
        nodes,
        frames: frames as u32,
        values,
    }))
}
