//! The rig model: pure data, no I/O, no GPU.
//!
//! A [`Rig`] is what every engine evaluates: the primitives of a glTF file's default scene in rig
//! space, their morph targets stored sparse, the rig-wide target names that weights address, the
//! animation clips (weight tables, targets × frames) and the level-of-detail order. Importers
//! build it, engines prepare their own layouts from it, and the server persists it. Keeping it free
//! of I/O and of `wgpu` means every layer above can depend on it without dragging the others in.
//!
//! Conventions:
//! - Weights are addressed rig-wide by [`TargetId`], an index into [`Rig::targets`]: a *weight
//!   channel*, one row of every clip table and one LOD slot. A primitive's
//!   [`SparseTarget::target`] says which channel drives it, so one weight drives every primitive
//!   that has that channel.
//! - A channel is named by its target name, and usually each name has one channel. A glTF file
//!   whose animations (or default weights) treat two nodes that share a target name differently
//!   gets one channel per distinct behaviour, so the name then maps to several channels
//!   ([`Rig::target_ids`]). Sources that address targets by name (CSV and JSON clips, LOD pins)
//!   write every channel of the name; glTF animations write each node's own channel.
//! - The evaluation vertex space is all primitives concatenated in order; [`Rig::vertex_offsets`]
//!   maps a primitive to its first vertex there. Output buffers use this order.
//! - A skinned rig ([`Rig::skeleton`]) is posed as glTF does: morph targets first, then each
//!   vertex by its bones ([`Primitive::skin`]) in the job's pose; clips carry the joint
//!   transforms beside their weights ([`Clip::joints`]). Rig space holds the rest pose
//!   (`skin.rs`).

mod alive;
mod animated_texture;
mod appearance;
mod clip;
mod cost;
mod joint_lod;
mod joint_map;
mod layer;
mod lod;
mod mapping;
mod mesh_level;
mod pca;
mod pose;
mod regions;
mod sample;
mod skin;

pub use alive::{
    AliveParams, AliveRig, BLINK_JITTER_S, BLINK_PERIOD_S, LOOK_FULL_DEG, Placement, blink_amount,
    blink_start, breath, head_seed, look_angles, saccade_offset,
};
pub use animated_texture::{
    AnimatedTexture, AnimatedTextureError, MAX_ANIMATED_SIZE, MAX_LAYERS, TEXTURE_MAGIC,
    TextureRegion, layer_inputs,
};
pub use appearance::{
    AlphaMode, Appearance, Filter, ImageData, ImageMime, Material, MipLevel, Mips, Sampler, Slot,
    TargetTexture, TexRef, Texture, UvTransform, Wrap,
};
pub use clip::{Clip, ClipError, ClipIndex, DEFAULT_FPS, FrameMode, MAX_FRAMES};
pub use cost::{CPU_BLOCK, PrimShape, RigCost, RigShape, SkinShape};
pub use joint_lod::{JointLevel, JointLod, REFERENCE_TURN, drop_fraction};
pub use joint_map::{
    JointChannel, JointMap, LIVE_LINK_COLUMNS, MAX_JOINT_CHANNELS, rest_rotations,
};
pub use layer::{
    LayerMode, MAX_POSE_LAYERS, PoseLayer, Selection, blend_trs, builtin_mask, clamp_weights,
    layer_locals, layer_weights,
};
pub use lod::{
    IMPORT_LOD_METHOD, Lod, LodError, LodLevel, MeshLevel, MeshLevelPrimitive, default_lod_levels,
};
pub use mapping::{
    BUILTIN_MAPPINGS, MAX_MAP_ENTRIES, MAX_MAP_VALUE, MapTable, MapTerm, MappingError, NamedEntry,
    NamedMapping, NamedSource, OCULUS_VISEMES, Override, Procedural, SourceRule, a2f_names,
    builtin_mapping, capitalised,
};
pub use mesh_level::mesh_level_rigs;
pub use pca::{DeltaPca, PcaRegion, pca_level_rigs};
pub use pose::{
    ARKIT_NAMES, LIVE_STEP, MAX_BLEND_LAYERS, MAX_LIVE_WEIGHT, MAX_NEAR_SHIFT, MAX_NEAR_TOLERANCE,
    MAX_TERMS, Pose, PoseError, T_ONE, Term, near_clone_bound, near_clone_shift, quantize_live,
};
pub use regions::{HEAD_WEIGHT, MOVED_FRACTION, Region, RegionSource, head_node, is_head_name};
pub use sample::{Interpolation, KeyTrack, sample_rotation, sample_track};
pub use skin::{
    Bone, BoneMatrix, BoneScratch, INFLUENCES, Influences, JOINT_STEP, JointIndex, JointLookup,
    JointPose, JointSet, JointTable, MAX_BONES, MAX_JOINT_OVERRIDES, MAX_JOINT_VALUE, NO_BONE,
    NO_PARENT, SkelNode, Skeleton, SkinPoses, SkinTerm, Trs, WEIGHT_SUM_TOLERANCE,
    for_each_influence, top_influences,
};

use std::sync::Arc;

use glam::{Vec2, Vec3, Vec4};
use serde::{Deserialize, Serialize};

/// Index of a target in [`Rig::targets`].
pub type TargetId = u32;

/// Default sparsity threshold: a vertex is stored in a target only if some component of one of
/// its deltas exceeds this, in rig units. ICT FaceKit's OBJ rounding noise sits below it.
pub const DEFAULT_DELTA_THRESHOLD: f32 = 1e-6;

/// A weight whose magnitude is at most this is treated as inactive (Lorach 2007: only active
/// shapes are visited).
pub const ACTIVE_WEIGHT_EPSILON: f32 = 1e-6;

/// A blendshape rig: neutral primitives, sparse morph targets, clips and LOD order.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct Rig {
    /// Human-readable name (file stem or the name given on upload).
    pub name: String,
    /// The weight channels, by target name; a [`TargetId`] indexes this list. A name appears
    /// more than once when the file's nodes that share it are animated differently (see the
    /// module documentation); it appears once otherwise.
    pub targets: Vec<String>,
    /// Weight of each channel when a clip does not animate it (glTF `node.weights`, else
    /// `mesh.weights`, else 0).
    pub default_weights: Vec<f32>,
    /// The primitives, in file order (default scene traversal order). Shared by every
    /// version of the rig (a new clip or LOD makes a new version, not a copy of the geometry).
    pub primitives: Arc<Vec<Primitive>>,
    /// Animation clips: weight tables over all rig-wide targets.
    pub clips: Vec<Clip>,
    /// Importance order of the targets and the LOD table.
    pub lod: Lod,
    /// The node hierarchy its vertices follow, when some primitive is skinned or hangs from
    /// an animated node (`crates/core/src/rig/skin.rs`). Skipped by serde: the store keeps it beside the
    /// primitives (its records are positional).
    #[serde(skip)]
    pub skeleton: Option<Arc<Skeleton>>,
    /// What the import approximated or left out of the file, one sentence each (the upload's
    /// answer and `inspect` show them). Stored with the skeleton of a skinned rig; others
    /// report them at upload only.
    #[serde(skip)]
    pub import_notes: Vec<String>,
    /// Materials, textures, samplers and images ([`Appearance`]), when the file has any;
    /// shared by every version and clone of the rig. Skipped by serde: the store keeps it in
    /// a section of its own.
    #[serde(skip)]
    pub appearance: Option<Arc<Appearance>>,
}

/// A rig's weight channels by target name, for operations that look up many names (the
/// columns of a CSV or JSON clip, the targets of a glTF clip): one hash probe per lookup
/// instead of a scan of every channel, which made a clip naming all of a 4,096-channel rig's
/// targets quadratic. The channel ids are kept in one array, grouped by name (channel order
/// within a name), so a lookup returns a slice and building allocates two arrays, not one per
/// name.
#[derive(Clone, Debug)]
pub struct TargetIndex<'r> {
    /// Every channel id, grouped by name, ascending within a name.
    order: Vec<TargetId>,
    /// Name → its range of `order` (start, length).
    ranges: std::collections::HashMap<&'r str, (u32, u32)>,
}

impl<'r> TargetIndex<'r> {
    /// Most bytes an index over `targets` channels holds: four per channel in `order`, and
    /// the name map, allocated once for `targets` names (a `&str` and a range per bucket, a
    /// control byte each; see [`map_bytes`]).
    pub fn bytes_for(targets: usize) -> u64 {
        targets as u64 * 4 + map_bytes(targets, 16 + 8)
    }

    /// Indexes the channel names `targets` (a rig's [`Rig::targets`]).
    pub fn new(targets: &'r [String]) -> TargetIndex<'r> {
        let mut order: Vec<TargetId> = (0..targets.len() as TargetId).collect();
        // Stable: a name's channels stay in channel order.
        order.sort_by(|&a, &b| targets[a as usize].cmp(&targets[b as usize]));
        // Sized once for every name at most, so it never grows (what `bytes_for` counts).
        let mut ranges = std::collections::HashMap::with_capacity(targets.len());
        let mut start = 0;
        while start < order.len() {
            let name = targets[order[start] as usize].as_str();
            let len = order[start..]
                .iter()
                .take_while(|&&id| targets[id as usize] == name)
                .count();
            ranges.insert(name, (start as u32, len as u32));
            start += len;
        }
        TargetIndex { order, ranges }
    }

    /// Every weight channel of the target with this name, in channel order (empty when there
    /// is no such target); what [`Rig::target_ids`] returns.
    pub fn ids(&self, name: &str) -> &[TargetId] {
        self.ranges.get(name).map_or(&[], |&(start, len)| {
            &self.order[start as usize..(start + len) as usize]
        })
    }

    /// The distinct names.
    pub fn names(&self) -> impl Iterator<Item = &'r str> + '_ {
        self.ranges.keys().copied()
    }

    /// What [`Rig::channel_by_label`] finds, through this index.
    pub fn channel_by_label(&self, label: &str) -> Option<TargetId> {
        if let [id] = self.ids(label) {
            return Some(*id);
        }
        let (name, k) = label.rsplit_once('#')?;
        kth_channel(self.ids(name), k)
    }
}

/// The channel a label's `#k` suffix picks among `ids`, the channels of a name that has
/// several (`k` counts from 1); `None` for a name with one channel or a bad `k`.
fn kth_channel(ids: &[TargetId], k: &str) -> Option<TargetId> {
    let k: usize = k.parse().ok()?;
    (ids.len() > 1 && k >= 1)
        .then(|| ids.get(k - 1).copied())
        .flatten()
}

/// Longest prefix of a client's name (a rig id, clip or target name) an error message quotes.
pub const QUOTED_NAME_CHARS: usize = 64;

/// A name as an error message quotes it: Rust-quoted, its first [`QUOTED_NAME_CHARS`]
/// characters and its length when longer. A 15 MB name in a request is not echoed back whole.
pub fn quoted_name(s: &str) -> String {
    match s.char_indices().nth(QUOTED_NAME_CHARS) {
        None => format!("{s:?}"),
        Some((end, _)) => format!("{:?}... ({} bytes)", &s[..end], s.len()),
    }
}

/// Most bytes a `std` hash map built `with_capacity(n)` (and never grown past `n`) allocates
/// for entries of `entry` bytes: hashbrown's buckets (the next power of two at its 7/8 load
/// factor) of an entry and a control byte each, plus one group of control bytes.
pub fn map_bytes(n: usize, entry: u64) -> u64 {
    let buckets = (n.saturating_mul(8) / 7 + 1).next_power_of_two().max(4) as u64;
    buckets * (entry + 1) + 16
}

/// Every channel's label, in channel order ([`Rig::channel_labels`]).
#[derive(Clone, Debug, PartialEq)]
pub struct ChannelLabels(Vec<String>);

impl ChannelLabels {
    /// The labels of `ids`, in their order (`#id` for an id past the channels, as
    /// [`Rig::channel_label`] says it).
    pub fn of(&self, ids: &[TargetId]) -> Vec<String> {
        ids.iter()
            .map(|&t| {
                self.0
                    .get(t as usize)
                    .cloned()
                    .unwrap_or_else(|| format!("#{t}"))
            })
            .collect()
    }

    /// All the labels, in channel order.
    pub fn into_vec(self) -> Vec<String> {
        self.0
    }
}

/// One primitive of the rig, in rig space.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct Primitive {
    /// `mesh name/primitive index` as found in the file, for reports.
    pub name: String,
    /// Neutral positions.
    pub positions: Vec<Vec3>,
    /// Neutral unit normals (from the file, or computed from the triangles when absent).
    pub normals: Vec<Vec3>,
    /// Whether [`Primitive::normals`] came from the file rather than being computed.
    pub normals_from_file: bool,
    /// Neutral tangents (xyz unit, w handedness) when the file has them.
    pub tangents: Option<Vec<Vec4>>,
    /// Triangle list indices into this primitive's vertices.
    pub indices: Vec<u32>,
    /// Morph targets of this primitive, each naming its rig-wide target.
    pub targets: Vec<SparseTarget>,
    /// Base colour factor of the primitive's glTF material (linear RGBA; glTF's default white
    /// when it has none), for rendered frames. Skipped by serde: the store keeps it beside the
    /// primitives, since its records are positional (bincode) and this came after the first.
    #[serde(skip, default = "Primitive::default_base_color")]
    pub base_color: [f32; 4],
    /// Per vertex, the bones of [`Rig::skeleton`] that pose it after its morph targets, when
    /// it follows any (skipped by serde like `base_color`).
    #[serde(skip)]
    pub skin: Option<Influences>,
    /// What the vertices carry for the primitive's appearance (texture coordinates), parallel
    /// to [`Primitive::positions`]; skipped by serde like `base_color` (the store keeps it in
    /// a section of its own).
    #[serde(skip)]
    pub look: VertexLook,
}

/// Per-vertex appearance data of a primitive, parallel to its positions, and the material it
/// is drawn with. Nothing here moves with a morph target: it is what a mesh level keeps of
/// each source vertex it keeps.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct VertexLook {
    /// Texture coordinates of set 0 (glTF `TEXCOORD_0`), as the file has them (normalized
    /// integers decoded to floats).
    pub uv0: Option<Vec<Vec2>>,
    /// Texture coordinates of set 1 (`TEXCOORD_1`), as the file has them (a material may read
    /// them for any slot; an occlusion map often does).
    pub uv1: Option<Vec<Vec2>>,
    /// Vertex colours (`COLOR_0`), linear RGBA (RGB files get alpha 1).
    pub colors: Option<Vec<Vec4>>,
    /// Index of its material in [`Rig::appearance`]; `None`: drawn with
    /// [`Material::untextured`] of its base colour.
    pub material: Option<u32>,
}

impl VertexLook {
    /// The data of vertices `vertices` of a primitive (a mesh level's kept source vertices).
    pub fn pick(&self, vertices: &[u32]) -> VertexLook {
        fn pick<T: Copy>(a: &Option<Vec<T>>, vertices: &[u32]) -> Option<Vec<T>> {
            a.as_ref()
                .map(|a| vertices.iter().map(|&v| a[v as usize]).collect())
        }
        VertexLook {
            uv0: pick(&self.uv0, vertices),
            uv1: pick(&self.uv1, vertices),
            colors: pick(&self.colors, vertices),
            material: self.material,
        }
    }

    /// Bytes of its arrays.
    pub fn bytes(&self) -> usize {
        self.uv0.as_ref().map_or(0, |uv| uv.len() * 8)
            + self.uv1.as_ref().map_or(0, |uv| uv.len() * 8)
            + self.colors.as_ref().map_or(0, |c| c.len() * 16)
    }

    /// Whether it carries nothing (what the store leaves out).
    pub fn is_empty(&self) -> bool {
        *self == VertexLook::default()
    }
}

/// A morph target restricted to the vertices it moves.
///
/// `vertices` is strictly ascending; the delta arrays are parallel to it. Normal and tangent
/// deltas are present only when the file has them for this target.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct SparseTarget {
    /// Rig-wide target this belongs to.
    pub target: TargetId,
    /// Vertex indices (into the primitive) with a delta above the threshold, ascending.
    pub vertices: Vec<u32>,
    /// Position deltas, parallel to `vertices`.
    pub positions: Vec<Vec3>,
    /// Normal deltas, parallel to `vertices`, when the file has them.
    pub normals: Option<Vec<Vec3>>,
    /// Tangent deltas (xyz), parallel to `vertices`, when the file has them.
    pub tangents: Option<Vec<Vec3>>,
}

/// Axis-aligned bounding box.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq)]
pub struct Aabb {
    /// Minimum corner.
    pub min: Vec3,
    /// Maximum corner.
    pub max: Vec3,
}

impl Aabb {
    /// Length of the diagonal; tolerances are stated relative to it.
    pub fn diagonal(&self) -> f32 {
        (self.max - self.min).length()
    }
}

/// Why a rig is not acceptable.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum RigError {
    /// The rig has no vertices at all.
    #[error("rig has no vertices")]
    NoVertices,
    /// A primitive's arrays disagree in length or reference vertices that do not exist.
    #[error("primitive {primitive:?}: {problem}")]
    Inconsistent {
        /// Primitive name.
        primitive: String,
        /// What is wrong.
        problem: String,
    },
    /// A value is NaN or infinite.
    #[error("{what} contains a non-finite value (NaN or infinity)")]
    NonFinite {
        /// Which array.
        what: String,
    },
    /// A clip is malformed.
    #[error(transparent)]
    Clip(#[from] ClipError),
    /// The LOD table is malformed.
    #[error(transparent)]
    Lod(#[from] LodError),
    /// Too many vertices or targets for the engines' index types.
    #[error("rig too large: {0}")]
    TooLarge(String),
}

/// Most vertices a rig may have (all primitives together); keeps indices in `u32` with room.
pub const MAX_VERTICES: usize = 1 << 26;
/// Most rig-wide targets; slots are stored as `u16` in the engines.
pub const MAX_TARGETS: usize = 4096;

impl Rig {
    /// Total number of vertices over all primitives.
    pub fn vertex_count(&self) -> usize {
        self.primitives.iter().map(|p| p.positions.len()).sum()
    }

    /// Vertex deltas stored over every target of every primitive (the sparse entries a blend of
    /// all shapes visits).
    pub fn delta_count(&self) -> u64 {
        self.primitives
            .iter()
            .flat_map(|p| p.targets.iter())
            .map(|t| t.vertices.len() as u64)
            .sum()
    }

    /// First vertex of each primitive in the concatenated evaluation vertex space, plus the total.
    pub fn vertex_offsets(&self) -> Vec<usize> {
        let mut offsets = Vec::with_capacity(self.primitives.len() + 1);
        let mut acc = 0;
        for p in self.primitives.iter() {
            offsets.push(acc);
            acc += p.positions.len();
        }
        offsets.push(acc);
        offsets
    }

    /// Total number of triangles.
    pub fn triangle_count(&self) -> usize {
        self.primitives.iter().map(|p| p.indices.len() / 3).sum()
    }

    /// Bounding box of the neutral positions.
    pub fn bbox(&self) -> Aabb {
        let mut min = Vec3::splat(f32::INFINITY);
        let mut max = Vec3::splat(f32::NEG_INFINITY);
        for p in self.primitives.iter() {
            for &v in &p.positions {
                min = min.min(v);
                max = max.max(v);
            }
        }
        if min.x > max.x {
            min = Vec3::ZERO;
            max = Vec3::ZERO;
        }
        Aabb { min, max }
    }

    /// The first weight channel of the target with this name (its only one, unless the name
    /// has several: see [`Rig::target_ids`]).
    pub fn target_id(&self, name: &str) -> Option<TargetId> {
        self.targets
            .iter()
            .position(|t| t == name)
            .map(|i| i as TargetId)
    }

    /// Every weight channel of the target with this name, in channel order (empty when the rig
    /// has no such target). Sources that address targets by name write all of them. This scans
    /// every channel: an operation that looks up many names builds a [`Rig::target_index`]
    /// once instead.
    pub fn target_ids(&self, name: &str) -> Vec<TargetId> {
        self.targets
            .iter()
            .enumerate()
            .filter(|(_, t)| *t == name)
            .map(|(i, _)| i as TargetId)
            .collect()
    }

    /// The name → channels map of this rig, built once (see [`TargetIndex`]); its size is
    /// [`TargetIndex::bytes_for`] this rig, which a caller charges to its budget first.
    pub fn target_index(&self) -> TargetIndex<'_> {
        TargetIndex::new(&self.targets)
    }

    /// The distinct target names, in order of their first channel.
    pub fn target_names(&self) -> Vec<&str> {
        let mut seen = std::collections::HashSet::with_capacity(self.targets.len());
        self.targets
            .iter()
            .filter(|t| seen.insert(t.as_str()))
            .map(String::as_str)
            .collect()
    }

    /// The names that have more than one weight channel, with how many, in order of their
    /// first channel.
    pub fn split_targets(&self) -> Vec<(&str, usize)> {
        let mut counts: std::collections::HashMap<&str, usize> =
            std::collections::HashMap::with_capacity(self.targets.len());
        for t in &self.targets {
            *counts.entry(t.as_str()).or_default() += 1;
        }
        self.target_names()
            .into_iter()
            .filter_map(|n| counts.get(n).filter(|&&c| c > 1).map(|&c| (n, c)))
            .collect()
    }

    /// A label for channel `id` that tells a name's channels apart in reports: the name, with
    /// `#k` (k counted from 1 in channel order) when the name has several channels.
    pub fn channel_label(&self, id: TargetId) -> String {
        let Some(name) = self.targets.get(id as usize) else {
            return format!("#{id}");
        };
        let before = self.targets[..id as usize]
            .iter()
            .filter(|t| *t == name)
            .count();
        let after = self.targets[id as usize + 1..]
            .iter()
            .filter(|t| *t == name)
            .count();
        if before + after == 0 {
            name.clone()
        } else {
            format!("{name}#{}", before + 1)
        }
    }

    /// Every channel's [`Rig::channel_label`], in channel order, in one pass (labelling the
    /// channels one call at a time would scan them all per call).
    pub fn channel_labels(&self) -> ChannelLabels {
        let mut total: std::collections::HashMap<&str, usize> =
            std::collections::HashMap::with_capacity(self.targets.len());
        for t in &self.targets {
            *total.entry(t.as_str()).or_default() += 1;
        }
        let mut seen: std::collections::HashMap<&str, usize> =
            std::collections::HashMap::with_capacity(total.len());
        ChannelLabels(
            self.targets
                .iter()
                .map(|t| {
                    let k = seen.entry(t.as_str()).or_default();
                    *k += 1;
                    if total.get(t.as_str()).copied().unwrap_or(0) > 1 {
                        format!("{t}#{k}")
                    } else {
                        t.clone()
                    }
                })
                .collect(),
        )
    }

    /// The channel a [`Rig::channel_label`] names: `name#k` is the k-th channel of `name`
    /// (a plain name with a single channel is its label too).
    pub fn channel_by_label(&self, label: &str) -> Option<TargetId> {
        let ids = self.target_ids(label);
        if ids.len() == 1 {
            return ids.first().copied();
        }
        let (name, k) = label.rsplit_once('#')?;
        kth_channel(&self.target_ids(name), k)
    }

    /// Index of the clip with this name.
    pub fn clip_index(&self, name: &str) -> Option<usize> {
        self.clips.iter().position(|c| c.name == name)
    }

    /// Number of stored (non-zero) vertex deltas of each rig-wide target, over all primitives.
    pub fn target_nnz(&self) -> Vec<usize> {
        let mut nnz = vec![0usize; self.targets.len()];
        for p in self.primitives.iter() {
            for t in &p.targets {
                if let Some(n) = nnz.get_mut(t.target as usize) {
                    *n += t.vertices.len();
                }
            }
        }
        nnz
    }

    /// Whether any target of any primitive carries normal deltas.
    pub fn has_normal_deltas(&self) -> bool {
        self.primitives.iter().any(Primitive::has_normal_deltas)
    }

    /// Whether normals, when asked for, are recomputed from the blended positions for some
    /// primitive (one that moves and whose targets carry no normal deltas): engines then
    /// blend its positions in f32 first, whatever the wire format.
    pub fn recomputes_normals(&self) -> bool {
        self.primitives
            .iter()
            .any(|p| !p.targets.is_empty() && !p.has_normal_deltas())
    }

    /// Host memory held by the rig's arrays, in bytes: geometry, clip tables and LOD.
    pub fn host_bytes(&self) -> usize {
        self.geometry_bytes()
            + self.clip_bytes()
            + self.lod_bytes()
            + self.appearance.as_ref().map_or(0, |a| a.bytes())
    }

    /// Bytes of the primitives' arrays (neutral mesh, indices, sparse deltas).
    pub fn geometry_bytes(&self) -> usize {
        self.primitives.iter().map(Primitive::bytes).sum()
    }

    /// Bytes of the clip tables.
    pub fn clip_bytes(&self) -> usize {
        self.clips.iter().map(|c| c.weights.len() * 4).sum()
    }

    /// Bytes of the LOD order, table, mesh levels and PCA forms.
    pub fn lod_bytes(&self) -> usize {
        self.lod.order.len() * 4
            + self.lod.levels.len() * 8
            + self
                .lod
                .meshes
                .iter()
                .flat_map(|m| &m.primitives)
                .map(|p| (p.vertices.len() + p.indices.len()) * 4)
                .sum::<usize>()
            + self.lod.pca.iter().map(DeltaPca::bytes).sum::<usize>()
    }

    /// Checks every invariant the engines rely on. Importers call it before handing a rig out,
    /// and persistence calls it after reading one back, so a rig in memory is always valid.
    pub fn validate(&self) -> Result<(), RigError> {
        let n_targets = self.targets.len();
        if n_targets > MAX_TARGETS {
            return Err(RigError::TooLarge(format!(
                "{n_targets} targets (at most {MAX_TARGETS})"
            )));
        }
        let total = self.vertex_count();
        if total == 0 {
            return Err(RigError::NoVertices);
        }
        if total > MAX_VERTICES {
            return Err(RigError::TooLarge(format!(
                "{total} vertices (at most {MAX_VERTICES})"
            )));
        }
        if self.default_weights.len() != n_targets {
            return Err(RigError::Inconsistent {
                primitive: String::new(),
                problem: format!(
                    "{} default weights for {n_targets} targets",
                    self.default_weights.len()
                ),
            });
        }
        check_finite("default weights", self.default_weights.iter().copied())?;
        for p in self.primitives.iter() {
            p.validate(n_targets)?;
        }
        self.validate_appearance()?;
        for c in &self.clips {
            c.validate(n_targets)?;
        }
        self.lod.validate(n_targets)?;
        let counts: Vec<usize> = self.primitives.iter().map(|p| p.positions.len()).collect();
        self.lod.validate_meshes(&counts)?;
        self.validate_skeleton()
    }

    /// The appearance's part of [`Rig::validate`]: its own indices, and every primitive's
    /// material inside it (a primitive naming a material needs an appearance).
    fn validate_appearance(&self) -> Result<(), RigError> {
        let bad = |primitive: &str, problem: String| RigError::Inconsistent {
            primitive: primitive.to_string(),
            problem,
        };
        let materials = self.appearance.as_ref().map_or(0, |a| a.materials.len());
        if let Some(a) = &self.appearance {
            a.validate()
                .map_err(|p| bad("", format!("appearance: {p}")))?;
        }
        for p in self.primitives.iter() {
            if let Some(m) = p.look.material
                && m as usize >= materials
            {
                return Err(bad(
                    &p.name,
                    format!("material {m} out of range ({materials} materials)"),
                ));
            }
        }
        Ok(())
    }

    /// The skeleton's part of [`Rig::validate`]: influences only with a skeleton, bones and
    /// parents in range, weights summing to one, joint tables that fit their clips.
    fn validate_skeleton(&self) -> Result<(), RigError> {
        let skinned = |p: &Primitive| p.skin.is_some();
        let tables = self.clips.iter().any(|c| c.joints.is_some());
        let Some(sk) = &self.skeleton else {
            if self.primitives.iter().any(skinned) || tables {
                return Err(RigError::Inconsistent {
                    primitive: String::new(),
                    problem: "joint influences or joint tables without a skeleton".into(),
                });
            }
            return Ok(());
        };
        let influences: Vec<(&str, usize, &Influences)> = self
            .primitives
            .iter()
            .filter_map(|p| {
                p.skin
                    .as_ref()
                    .map(|s| (p.name.as_str(), p.positions.len(), s))
            })
            .collect();
        let tables: Vec<(&str, u32, &JointTable)> = self
            .clips
            .iter()
            .filter_map(|c| c.joints.as_deref().map(|t| (c.name.as_str(), c.frames, t)))
            .collect();
        skin::check(sk, &influences, &tables).map_err(|problem| RigError::Inconsistent {
            primitive: String::new(),
            problem: format!("skeleton: {problem}"),
        })?;
        if let Some(map) = &sk.map {
            map.check(sk).map_err(|problem| RigError::Inconsistent {
                primitive: String::new(),
                problem: format!("joint map: {problem}"),
            })?;
        }
        Ok(())
    }

    /// Whether the rig's vertices follow a skeleton (evaluation skins after blending).
    pub fn is_skinned(&self) -> bool {
        self.skeleton.is_some()
    }

    /// Vertices that follow several bones or a bone of their own (a skin), and vertices of
    /// primitives whose every vertex follows one same bone (a rigid mesh under a node).
    pub fn skinned_and_rigid_vertices(&self) -> (usize, usize) {
        let (mut skinned, mut rigid) = (0, 0);
        for p in self.primitives.iter() {
            let Some(s) = &p.skin else { continue };
            let first = s.joints.first().map(|j| j[0]);
            let one_bone = s
                .joints
                .iter()
                .zip(&s.weights)
                .all(|(j, w)| Some(j[0]) == first && w[0] == 1.0);
            if one_bone {
                rigid += s.joints.len();
            } else {
                skinned += s.joints.len();
            }
        }
        (skinned, rigid)
    }

    /// Names of the skeleton nodes some clip animates, in skeleton order.
    pub fn animated_node_names(&self) -> Vec<&str> {
        let Some(sk) = &self.skeleton else {
            return Vec::new();
        };
        let mut animated = vec![false; sk.nodes.len()];
        for t in self.clips.iter().filter_map(|c| c.joints.as_deref()) {
            for &n in &t.nodes {
                if let Some(a) = animated.get_mut(n as usize) {
                    *a = true;
                }
            }
        }
        sk.nodes
            .iter()
            .zip(animated)
            .filter(|(_, a)| *a)
            .map(|(n, _)| n.name.as_str())
            .collect()
    }
}

impl Primitive {
    /// glTF's default base colour factor: white.
    pub fn default_base_color() -> [f32; 4] {
        [1.0; 4]
    }

    /// Bytes of this primitive's arrays.
    pub fn bytes(&self) -> usize {
        let mut b = self.positions.len() * 12 + self.normals.len() * 12 + self.indices.len() * 4;
        b += self.tangents.as_ref().map_or(0, |t| t.len() * 16);
        b += self.look.bytes();
        for t in &self.targets {
            b += t.vertices.len() * 4 + t.positions.len() * 12;
            b += t.normals.as_ref().map_or(0, |n| n.len() * 12);
            b += t.tangents.as_ref().map_or(0, |n| n.len() * 12);
        }
        b
    }

    /// Whether any of this primitive's targets carries normal deltas.
    pub fn has_normal_deltas(&self) -> bool {
        self.targets.iter().any(|t| t.normals.is_some())
    }

    fn validate(&self, n_targets: usize) -> Result<(), RigError> {
        let bad = |problem: String| RigError::Inconsistent {
            primitive: self.name.clone(),
            problem,
        };
        let n = self.positions.len();
        if self.normals.len() != n {
            return Err(bad(format!(
                "{} normals for {n} positions",
                self.normals.len()
            )));
        }
        if let Some(t) = &self.tangents
            && t.len() != n
        {
            return Err(bad(format!("{} tangents for {n} positions", t.len())));
        }
        for (what, len) in [
            ("texture coordinates", self.look.uv0.as_ref().map(Vec::len)),
            (
                "texture coordinates of set 1",
                self.look.uv1.as_ref().map(Vec::len),
            ),
            ("vertex colours", self.look.colors.as_ref().map(Vec::len)),
        ] {
            if let Some(len) = len
                && len != n
            {
                return Err(bad(format!("{len} {what} for {n} positions")));
            }
        }
        if !self.indices.len().is_multiple_of(3) {
            return Err(bad(format!(
                "{} indices is not a triangle list",
                self.indices.len()
            )));
        }
        if let Some(&i) = self.indices.iter().find(|&&i| i as usize >= n) {
            return Err(bad(format!("index {i} out of range for {n} vertices")));
        }
        let what = |s: &str| format!("primitive {:?} {s}", self.name);
        check_finite(
            &what("positions"),
            self.positions.iter().flat_map(|v| v.to_array()),
        )?;
        check_finite(
            &what("normals"),
            self.normals.iter().flat_map(|v| v.to_array()),
        )?;
        if let Some(t) = &self.tangents {
            check_finite(&what("tangents"), t.iter().flat_map(|v| v.to_array()))?;
        }
        for (name, uv) in [
            ("texture coordinates", &self.look.uv0),
            ("texture coordinates of set 1", &self.look.uv1),
        ] {
            if let Some(uv) = uv {
                check_finite(&what(name), uv.iter().flat_map(|v| v.to_array()))?;
            }
        }
        if let Some(c) = &self.look.colors {
            check_finite(&what("vertex colours"), c.iter().flat_map(|v| v.to_array()))?;
        }
        let mut seen = vec![false; n_targets];
        for t in &self.targets {
            let id = t.target as usize;
            if id >= n_targets {
                return Err(bad(format!(
                    "target id {id} out of range ({n_targets} targets)"
                )));
            }
            if std::mem::replace(&mut seen[id], true) {
                return Err(bad(format!("target id {id} appears twice")));
            }
            let m = t.vertices.len();
            if t.positions.len() != m
                || t.normals.as_ref().is_some_and(|d| d.len() != m)
                || t.tangents.as_ref().is_some_and(|d| d.len() != m)
            {
                return Err(bad(format!("target {id}: delta arrays differ in length")));
            }
            if t.vertices.windows(2).any(|w| w[0] >= w[1]) {
                return Err(bad(format!(
                    "target {id}: vertex list not strictly ascending"
                )));
            }
            if t.vertices.last().is_some_and(|&v| v as usize >= n) {
                return Err(bad(format!("target {id}: vertex out of range")));
            }
            check_finite(
                &what("position deltas"),
                t.positions.iter().flat_map(|v| v.to_array()),
            )?;
            if let Some(d) = &t.normals {
                check_finite(&what("normal deltas"), d.iter().flat_map(|v| v.to_array()))?;
            }
            if let Some(d) = &t.tangents {
                check_finite(&what("tangent deltas"), d.iter().flat_map(|v| v.to_array()))?;
            }
        }
        Ok(())
    }
}

pub(crate) fn check_finite(
    what: &str,
    mut values: impl Iterator<Item = f32>,
) -> Result<(), RigError> {
    if values.all(f32::is_finite) {
        Ok(())
    } else {
        Err(RigError::NonFinite {
            what: what.to_string(),
        })
    }
}

/// Builds a sparse target from dense per-vertex deltas, keeping vertices where any component of
/// any delta exceeds `threshold` in magnitude.
pub fn sparsify(
    target: TargetId,
    positions: &[Vec3],
    normals: Option<&[Vec3]>,
    tangents: Option<&[Vec3]>,
    threshold: f32,
) -> SparseTarget {
    // A non-finite delta counts as exceeding, so that `Rig::validate` sees and refuses it
    // rather than the comparison silently dropping it.
    let exceeds = |v: Vec3| !v.is_finite() || v.abs().cmpgt(Vec3::splat(threshold)).any();
    let kept = |i: usize| {
        let n = normals.and_then(|n| n.get(i).copied());
        let t = tangents.and_then(|t| t.get(i).copied());
        exceeds(positions[i]) || n.is_some_and(exceeds) || t.is_some_and(exceeds)
    };
    // Counted first, so the arrays are allocated once at their size (see `sparse_len`).
    let m = sparse_len(positions, normals, tangents, threshold);
    let mut out = SparseTarget {
        target,
        vertices: Vec::with_capacity(m),
        positions: Vec::with_capacity(m),
        normals: normals.map(|_| Vec::with_capacity(m)),
        tangents: tangents.map(|_| Vec::with_capacity(m)),
    };
    for (i, &p) in positions.iter().enumerate() {
        let n = normals.and_then(|n| n.get(i).copied());
        let t = tangents.and_then(|t| t.get(i).copied());
        if kept(i) {
            out.vertices.push(i as u32);
            out.positions.push(p);
            if let (Some(v), Some(n)) = (out.normals.as_mut(), n) {
                v.push(n);
            }
            if let (Some(v), Some(t)) = (out.tangents.as_mut(), t) {
                v.push(t);
            }
        }
    }
    out
}

/// How many vertices [`sparsify`] keeps for these deltas: importers charge the sparse
/// arrays to their memory budget before they are built.
pub fn sparse_len(
    positions: &[Vec3],
    normals: Option<&[Vec3]>,
    tangents: Option<&[Vec3]>,
    threshold: f32,
) -> usize {
    let exceeds = |v: Vec3| !v.is_finite() || v.abs().cmpgt(Vec3::splat(threshold)).any();
    (0..positions.len())
        .filter(|&i| {
            exceeds(positions[i])
                || normals.and_then(|n| n.get(i)).is_some_and(|&n| exceeds(n))
                || tangents.and_then(|t| t.get(i)).is_some_and(|&t| exceeds(t))
        })
        .count()
}

/// Area-weighted vertex normals of a triangle mesh; vertices on no triangle get +Z.
///
/// This is also the CPU mirror of the `recompute_normals` pass.
pub fn vertex_normals(positions: &[Vec3], indices: &[u32]) -> Vec<Vec3> {
    let mut acc = vec![Vec3::ZERO; positions.len()];
    for tri in indices.chunks_exact(3) {
        let [a, b, c] = [tri[0] as usize, tri[1] as usize, tri[2] as usize];
        let (Some(&pa), Some(&pb), Some(&pc)) =
            (positions.get(a), positions.get(b), positions.get(c))
        else {
            continue;
        };
        let n = (pb - pa).cross(pc - pa);
        acc[a] += n;
        acc[b] += n;
        acc[c] += n;
    }
    acc.into_iter()
        .map(|n| n.try_normalize().unwrap_or(Vec3::Z))
        .collect()
}

#[cfg(test)]
mod tests {
    #[test]
    fn long_names_are_quoted_by_their_start_and_length() {
        assert_eq!(quoted_name("jawOpen"), "\"jawOpen\"");
        let long = "é".repeat(1 << 20);
        let q = quoted_name(&long);
        assert!(q.len() < 200, "{} bytes", q.len());
        assert!(
            q.starts_with("\"éé") && q.ends_with("... (2097152 bytes)"),
            "{q}"
        );
        let exact = "x".repeat(QUOTED_NAME_CHARS);
        assert_eq!(quoted_name(&exact), format!("{exact:?}"));
    }

    use super::*;

    #[test]
    fn the_target_index_answers_what_target_ids_scans_for() {
        // Names with several channels, interleaved, as a split-channel rig has them.
        let targets: Vec<String> = ["jaw", "blink", "jaw", "smile", "blink", "jaw", "x"]
            .iter()
            .map(|s| s.to_string())
            .collect();
        let index = TargetIndex::new(&targets);
        assert_eq!(index.ids("jaw"), [0, 2, 5]);
        assert_eq!(index.ids("blink"), [1, 4]);
        assert_eq!(index.ids("x"), [6]);
        assert!(index.ids("absent").is_empty());
        let mut names: Vec<&str> = index.names().collect();
        names.sort_unstable();
        assert_eq!(names, ["blink", "jaw", "smile", "x"]);
        // The embedded rig: every name, as the scan finds it.
        let rig = crate::embedded::default_rig();
        let index = rig.target_index();
        for name in &rig.targets {
            assert_eq!(index.ids(name), rig.target_ids(name), "{name}");
        }
        // The charge bounds what the map holds: built once, it never grew past the buckets
        // `map_bytes` counts (a table's capacity is 7/8 of its buckets).
        let n = rig.targets.len();
        assert!(index.ranges.capacity() >= n, "sized once for every name");
        let buckets = (map_bytes(n, 24) - 16) / 25;
        assert!(
            index.ranges.capacity() as u64 <= buckets,
            "{buckets} buckets"
        );
    }

    #[test]
    fn channel_labels_are_each_channels_label_in_one_pass() {
        let mut rig = crate::embedded::default_rig();
        // Split channels, interleaved, as a rig whose meshes reuse names has them.
        let n = rig.targets.len();
        for (i, t) in rig.targets.iter_mut().enumerate() {
            if i % 3 == 0 {
                *t = ["jaw", "blink"][i % 2].to_string();
            }
        }
        let labels = rig.channel_labels().into_vec();
        assert_eq!(labels.len(), n);
        for (i, l) in labels.iter().enumerate() {
            assert_eq!(*l, rig.channel_label(i as u32), "channel {i}");
            assert_eq!(rig.channel_by_label(l), Some(i as u32), "{l}");
        }
        assert!(labels.iter().any(|l| l == "jaw#2"));
    }
}
