//! Skeletons: the node transforms that pose a rig after its morph targets.
//!
//! glTF 2.0 evaluates a mesh as morph targets first, then skinning (§3.7.3). Two things in a
//! scene move vertices by node transforms, and both become *bones* here:
//! - a skin (`JOINTS_n`/`WEIGHTS_n`): joint `j`'s matrix is `global(j) × inverseBind(j)`;
//! - a mesh parented to an animated node (RobotExpressive's head, arms and legs are rigid
//!   meshes under its joints): one bone for every vertex, weight 1.
//!
//! A [`Bone`] is a node of the [`Skeleton`] and a bind matrix; its matrix in a pose is
//! `global(node) × bind`. Rig space holds every primitive at rest, so that LOD metrics, mesh
//! simplification and bounding boxes see the mesh a user sees:
//! - a rigid primitive's bind is the inverse of its node's rest global transform, so the bone
//!   is the identity at rest;
//! - a skinned primitive is stored as `C × v` with `C = rest(j₀) × inverseBind(j₀)` for its
//!   skin's first joint, and each joint's bind is `inverseBind(j) × C⁻¹`: then
//!   `global(j) × bind(j) × (C v) = global(j) × inverseBind(j) × v` exactly, for any `C`.
//!
//! A pose sets each node's local translation, rotation and scale ([`Trs`]): the rest values,
//! a clip's baked [`JointTable`] at a frame, or a blend of several (translations and scales
//! summed by fraction, rotations by normalized weighted sum with signs aligned to the first
//! term, nlerp). [`Skeleton::bone_matrices`] resolves the hierarchy once per pose, parents
//! before children, and the engines apply the bones per vertex.

use std::sync::Arc;

use glam::{Mat3, Mat4, Quat, Vec3, Vec4};
use serde::{Deserialize, Serialize};

use super::JointMap;

/// `SkelNode::parent` of a root.
pub const NO_PARENT: u32 = u32::MAX;

/// Most bones a rig may have: bone ids are `u16` per vertex.
pub const MAX_BONES: usize = u16::MAX as usize;

/// Most nodes a skeleton may hold.
pub const MAX_SKELETON_NODES: usize = 1 << 16;

/// Influences per vertex kept; a file with more keeps the largest four, renormalized.
pub const INFLUENCES: usize = 4;

/// Largest distance of a vertex's weights' sum from 1 that is renormalized rather than
/// refused (glTF asks for normalized weights; exporters round them).
pub const WEIGHT_SUM_TOLERANCE: f32 = 0.01;

/// A node's local transform: translation, unit rotation (x, y, z, w) and scale, as glTF
/// stores them.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq)]
pub struct Trs {
    /// Translation.
    pub translation: [f32; 3],
    /// Rotation quaternion, x, y, z, w.
    pub rotation: [f32; 4],
    /// Scale.
    pub scale: [f32; 3],
}

impl Default for Trs {
    fn default() -> Self {
        Trs {
            translation: [0.0; 3],
            rotation: [0.0, 0.0, 0.0, 1.0],
            scale: [1.0; 3],
        }
    }
}

impl Trs {
    /// Floats per transform in a [`JointTable`].
    pub const FLOATS: usize = 10;

    /// The matrix `T × R × S` (the rotation normalized first).
    pub fn matrix(&self) -> Mat4 {
        Mat4::from_scale_rotation_translation(
            Vec3::from(self.scale),
            Quat::from_array(self.rotation).normalize(),
            Vec3::from(self.translation),
        )
    }

    /// From the ten floats of a table row: translation, rotation, scale.
    pub fn from_floats(v: &[f32]) -> Trs {
        Trs {
            translation: [v[0], v[1], v[2]],
            rotation: [v[3], v[4], v[5], v[6]],
            scale: [v[7], v[8], v[9]],
        }
    }

    /// `(1 − a) × from + a × to`: translations and scales by fraction, rotations by nlerp (the
    /// second flipped into the first's hemisphere), as a blend of two terms
    /// ([`Skeleton::locals_blend`]).
    pub fn nlerp(from: &Trs, to: &Trs, a: f32) -> Trs {
        let (f, t) = (from.floats(), to.floats());
        let flip = if Vec4::from(from.rotation).dot(Vec4::from(to.rotation)) < 0.0 {
            -1.0
        } else {
            1.0
        };
        let mut v = [0f32; 10];
        for k in 0..10 {
            let tk = if (3..7).contains(&k) {
                flip * t[k]
            } else {
                t[k]
            };
            v[k] = (1.0 - a) * f[k] + a * tk;
        }
        let mut out = Trs::from_floats(&v);
        out.rotation = Vec4::from(out.rotation)
            .try_normalize()
            .unwrap_or(Vec4::W)
            .to_array();
        out
    }

    /// The ten floats of a table row.
    pub fn floats(&self) -> [f32; 10] {
        let (t, r, s) = (self.translation, self.rotation, self.scale);
        [t[0], t[1], t[2], r[0], r[1], r[2], r[3], s[0], s[1], s[2]]
    }

    fn finite(&self) -> bool {
        self.floats().iter().all(|v| v.is_finite())
            && Vec4::from(self.rotation).length_squared() > 1e-12
    }
}

/// A node of the hierarchy that bones hang from.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct SkelNode {
    /// The glTF node's name (or `node<i>`), what joint overrides will name.
    pub name: String,
    /// Index of the parent in [`Skeleton::nodes`] (smaller than this node's), or [`NO_PARENT`].
    pub parent: u32,
    /// Local transform at rest.
    pub rest: Trs,
}

/// A bone: a node's global transform in the pose times a fixed bind matrix.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq)]
pub struct Bone {
    /// Index in [`Skeleton::nodes`].
    pub node: u32,
    /// Column-major bind matrix.
    pub bind: [f32; 16],
}

/// The node hierarchy and bones of a rig whose vertices follow node transforms.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct Skeleton {
    /// Every node a bone depends on, parents before children.
    pub nodes: Vec<SkelNode>,
    /// The bones vertices name in [`Influences::joints`].
    pub bones: Vec<Bone>,
    /// The clip columns that turn its nodes, when the rig was given its own
    /// (`PUT /v1/rigs/{id}/joint-map`); `None` is [`JointMap::defaults`]. Skipped by serde:
    /// the store keeps it beside the skin record.
    #[serde(skip)]
    pub map: Option<JointMap>,
}

/// Per vertex of one primitive: up to four bones and their weights (summing to one).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct Influences {
    /// Bone ids, into [`Skeleton::bones`].
    pub joints: Vec<[u16; INFLUENCES]>,
    /// Weights, parallel to `joints`; unused entries are 0.
    pub weights: Vec<[f32; INFLUENCES]>,
}

/// A clip's node transforms, baked at the clip's rate: for each animated node, its local
/// transform at every frame. Nodes it does not animate keep their rest transform.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct JointTable {
    /// Animated nodes (into [`Skeleton::nodes`]), strictly ascending.
    pub nodes: Vec<u32>,
    /// Frames, equal to the clip's.
    pub frames: u32,
    /// `frames × nodes × Trs::FLOATS`, frame-major.
    pub values: Vec<f32>,
}

impl JointTable {
    /// The transform of the table's `k`-th node at `frame`.
    pub fn at(&self, frame: u32, k: usize) -> Trs {
        let row = (frame as usize * self.nodes.len() + k) * Trs::FLOATS;
        Trs::from_floats(&self.values[row..row + Trs::FLOATS])
    }

    /// Bytes the table holds.
    pub fn bytes(&self) -> u64 {
        self.values.len() as u64 * 4 + self.nodes.len() as u64 * 4
    }
}

/// One bone's matrices in a pose, as both engines read them: the affine `3 × 4` transform of
/// positions (rows: x, y, z, each `[m0, m1, m2, t]`) and the inverse transpose of its linear
/// part for normals (rows padded to four).
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct BoneMatrix {
    /// Rows of the position transform.
    pub position: [[f32; 4]; 3],
    /// Rows of the normal transform (the fourth column is 0).
    pub normal: [[f32; 4]; 3],
}

impl BoneMatrix {
    /// The identity.
    pub const IDENTITY: BoneMatrix = BoneMatrix {
        position: [
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
        ],
        normal: [
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
        ],
    };

    /// From a column-major affine matrix.
    pub fn from_mat4(m: Mat4) -> BoneMatrix {
        let r = m.transpose().to_cols_array_2d();
        let linear = Mat3::from_mat4(m);
        let n = if linear.determinant().abs() > f32::MIN_POSITIVE {
            linear.inverse().transpose()
        } else {
            Mat3::IDENTITY
        };
        let nr = n.transpose().to_cols_array_2d();
        BoneMatrix {
            position: [r[0], r[1], r[2]],
            normal: [
                [nr[0][0], nr[0][1], nr[0][2], 0.0],
                [nr[1][0], nr[1][1], nr[1][2], 0.0],
                [nr[2][0], nr[2][1], nr[2][2], 0.0],
            ],
        }
    }

    /// `M p` (the affine transform of a point).
    #[inline(always)]
    pub fn point(&self, p: Vec3) -> Vec3 {
        let r = &self.position;
        Vec3::new(
            r[0][0] * p.x + r[0][1] * p.y + r[0][2] * p.z + r[0][3],
            r[1][0] * p.x + r[1][1] * p.y + r[1][2] * p.z + r[1][3],
            r[2][0] * p.x + r[2][1] * p.y + r[2][2] * p.z + r[2][3],
        )
    }

    /// The normal transform of `n` (not normalized).
    #[inline(always)]
    pub fn normal(&self, n: Vec3) -> Vec3 {
        let r = &self.normal;
        Vec3::new(
            r[0][0] * n.x + r[0][1] * n.y + r[0][2] * n.z,
            r[1][0] * n.x + r[1][1] * n.y + r[1][2] * n.z,
            r[2][0] * n.x + r[2][1] * n.y + r[2][2] * n.z,
        )
    }
}

/// Why a skeleton, its influences or a joint table is not acceptable.
pub fn check(
    skeleton: &Skeleton,
    influences: &[(&str, usize, &Influences)],
    tables: &[(&str, u32, &JointTable)],
) -> Result<(), String> {
    let nodes = skeleton.nodes.len();
    if nodes > MAX_SKELETON_NODES || skeleton.bones.len() > MAX_BONES {
        return Err(format!(
            "{nodes} skeleton nodes and {} bones: at most {MAX_SKELETON_NODES} and {MAX_BONES}",
            skeleton.bones.len()
        ));
    }
    for (i, n) in skeleton.nodes.iter().enumerate() {
        if n.parent != NO_PARENT && n.parent as usize >= i {
            return Err(format!(
                "skeleton node {i} ({:?}) has parent {}, which does not come before it",
                n.name, n.parent
            ));
        }
        if !n.rest.finite() {
            return Err(format!(
                "skeleton node {i} ({:?}) has a non-finite or zero-rotation rest transform",
                n.name
            ));
        }
    }
    for (b, bone) in skeleton.bones.iter().enumerate() {
        if bone.node as usize >= nodes {
            return Err(format!("bone {b} names node {} of {nodes}", bone.node));
        }
        if !bone.bind.iter().all(|v| v.is_finite()) {
            return Err(format!("bone {b} has a non-finite bind matrix"));
        }
    }
    for &(prim, vertices, inf) in influences {
        if inf.joints.len() != vertices || inf.weights.len() != vertices {
            return Err(format!(
                "primitive {prim:?}: {} joint and {} weight sets for {vertices} vertices",
                inf.joints.len(),
                inf.weights.len()
            ));
        }
        for (v, (j, w)) in inf.joints.iter().zip(&inf.weights).enumerate() {
            if let Some(b) = j.iter().find(|&&b| b as usize >= skeleton.bones.len()) {
                return Err(format!(
                    "primitive {prim:?}, vertex {v}: bone {b} of {}",
                    skeleton.bones.len()
                ));
            }
            let sum: f32 = w.iter().sum();
            if w.iter().any(|x| !x.is_finite() || *x < 0.0)
                || (sum - 1.0).abs() > WEIGHT_SUM_TOLERANCE
            {
                return Err(format!(
                    "primitive {prim:?}, vertex {v}: joint weights {w:?} are not non-negative \
                     numbers summing to 1"
                ));
            }
        }
    }
    for &(clip, frames, t) in tables {
        if t.frames != frames
            || t.values.len() != t.frames as usize * t.nodes.len() * Trs::FLOATS
            || t.nodes.windows(2).any(|w| w[0] >= w[1])
            || t.nodes.last().is_some_and(|&n| n as usize >= nodes)
        {
            return Err(format!(
                "clip {clip:?}: joint table of {} nodes × {} frames does not fit the skeleton \
                 ({nodes} nodes) and the clip ({frames} frames)",
                t.nodes.len(),
                t.frames
            ));
        }
        if !t.values.iter().all(|v| v.is_finite()) {
            return Err(format!(
                "clip {clip:?}: joint table holds a non-finite value"
            ));
        }
    }
    Ok(())
}

/// Renormalizes a vertex's weights to sum to one, keeping the largest [`INFLUENCES`]; returns
/// the kept joints and weights and the weight that was dropped (before renormalizing).
pub fn top_influences(pairs: &mut [(u16, f32)]) -> ([u16; INFLUENCES], [f32; INFLUENCES], f32) {
    pairs.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
    let mut joints = [0u16; INFLUENCES];
    let mut weights = [0f32; INFLUENCES];
    let total: f32 = pairs.iter().map(|p| p.1).sum();
    let mut kept = 0.0;
    for (k, &(j, w)) in pairs.iter().take(INFLUENCES).enumerate() {
        joints[k] = j;
        weights[k] = w;
        kept += w;
    }
    if kept > 0.0 {
        for w in &mut weights {
            *w /= kept;
        }
    }
    (joints, weights, total - kept)
}

impl Skeleton {
    /// Every node's rest transform.
    pub fn rest(&self) -> Vec<Trs> {
        self.nodes.iter().map(|n| n.rest).collect()
    }

    /// The local transforms at `frame` of a clip with `table` (rest where it has none).
    pub fn locals_at(&self, table: Option<&JointTable>, frame: u32, out: &mut Vec<Trs>) {
        out.clear();
        out.extend(self.nodes.iter().map(|n| n.rest));
        if let Some(t) = table
            && frame < t.frames
        {
            for (k, &node) in t.nodes.iter().enumerate() {
                out[node as usize] = t.at(frame, k);
            }
        }
    }

    /// The local transforms a job's joint terms give, before its overrides: the rest pose
    /// without terms, one clip frame's, or their blend ([`Skeleton::locals_blend`]).
    pub fn locals_of(&self, terms: &[SkinTerm], out: &mut Vec<Trs>) {
        match terms {
            [] => self.locals_at(None, 0, out),
            [one] if one.fraction == 1.0 => self.locals_at(one.table.as_deref(), one.frame, out),
            terms => {
                let terms: Vec<_> = terms
                    .iter()
                    .map(|t| (t.fraction, t.table.as_deref(), t.frame))
                    .collect();
                self.locals_blend(&terms, out);
            }
        }
    }

    /// The local transforms of a blend: `terms` are (fraction, table, frame), fractions
    /// summing to one. Translations and scales are summed by fraction; rotations by nlerp
    /// (each term's quaternion flipped into the first term's hemisphere, summed, normalized).
    pub fn locals_blend(&self, terms: &[(f32, Option<&JointTable>, u32)], out: &mut Vec<Trs>) {
        let mut one = Vec::new();
        let mut acc: Vec<[f32; 10]> = vec![[0.0; 10]; self.nodes.len()];
        let mut first: Vec<Vec4> = Vec::new();
        for (i, &(f, table, frame)) in terms.iter().enumerate() {
            self.locals_at(table, frame, &mut one);
            if i == 0 {
                first = one.iter().map(|t| Vec4::from(t.rotation)).collect();
            }
            for ((a, t), q0) in acc.iter_mut().zip(&one).zip(&first) {
                let mut v = t.floats();
                if Vec4::from(t.rotation).dot(*q0) < 0.0 {
                    for r in &mut v[3..7] {
                        *r = -*r;
                    }
                }
                for (a, v) in a.iter_mut().zip(v) {
                    *a += f * v;
                }
            }
        }
        out.clear();
        out.extend(acc.iter().map(|a| {
            let mut t = Trs::from_floats(a);
            let q = Vec4::from(t.rotation);
            t.rotation = q.try_normalize().unwrap_or(Vec4::W).to_array();
            t
        }));
    }

    /// Each bone's matrices for the node transforms `locals` (one per node), appended to
    /// `out`. `globals` is scratch.
    pub fn bone_matrices(
        &self,
        locals: &[Trs],
        globals: &mut Vec<Mat4>,
        out: &mut Vec<BoneMatrix>,
    ) {
        globals.clear();
        for (n, l) in self.nodes.iter().zip(locals) {
            let local = l.matrix();
            let g = match globals.get(n.parent as usize) {
                Some(p) if n.parent != NO_PARENT => *p * local,
                _ => local,
            };
            globals.push(g);
        }
        out.extend(self.bones.iter().map(|b| {
            BoneMatrix::from_mat4(globals[b.node as usize] * Mat4::from_cols_array(&b.bind))
        }));
    }

    /// Per node, the largest translation length and the largest absolute scale component it
    /// has at rest or in any of `clips`' frames: what bounds where a pose can put a vertex
    /// (rotations keep lengths), so joint overrides are held to them.
    pub fn extents(&self, clips: &[super::Clip]) -> (Vec<f64>, Vec<f64>) {
        let length = |t: [f32; 3]| t.iter().map(|&v| f64::from(v).powi(2)).sum::<f64>().sqrt();
        let scale = |s: [f32; 3]| s.iter().fold(0f64, |m, &v| m.max(f64::from(v).abs()));
        let mut t_max: Vec<f64> = self
            .nodes
            .iter()
            .map(|n| length(n.rest.translation))
            .collect();
        let mut s_max: Vec<f64> = self.nodes.iter().map(|n| scale(n.rest.scale)).collect();
        for table in clips.iter().filter_map(|c| c.joints.as_deref()) {
            for f in 0..table.frames {
                for (k, &node) in table.nodes.iter().enumerate() {
                    let trs = table.at(f, k);
                    let n = node as usize;
                    t_max[n] = t_max[n].max(length(trs.translation));
                    s_max[n] = s_max[n].max(scale(trs.scale));
                }
            }
        }
        (t_max, s_max)
    }

    /// The map of clip columns to joints in force: the rig's own, else the defaults.
    pub fn joint_map(&self) -> std::borrow::Cow<'_, JointMap> {
        match &self.map {
            Some(m) => std::borrow::Cow::Borrowed(m),
            None => std::borrow::Cow::Owned(JointMap::defaults(self)),
        }
    }

    /// Bytes the skeleton holds.
    pub fn bytes(&self) -> u64 {
        self.nodes
            .iter()
            .map(|n| n.name.len() as u64 + 72)
            .sum::<u64>()
            + self.bones.len() as u64 * 68
    }
}

/// Step of a quantized joint override component (2^-20): a rotation moves by under 2^-19 rad,
/// a translation or scale component by 2^-21 of a unit, so float noise does not split clones
/// and no pose a client can see is lost.
pub const JOINT_STEP: f64 = 1.0 / 1_048_576.0;

/// Largest magnitude of an override's translation, in rig units, and of its scale.
pub const MAX_JOINT_VALUE: f32 = 1.0e6;

/// Most joint overrides one head may carry (and never more than its rig's skeleton has nodes):
/// as many as the skeleton format allows, so that any pose of any rig, a motion graph's fade
/// included, can be sent to the renderer as overrides.
pub const MAX_JOINT_OVERRIDES: usize = MAX_SKELETON_NODES;

/// A node's local transform set by a request instead of its clip (`"joints"` in a head),
/// quantized to multiples of [`JOINT_STEP`] so that it can be part of a dedupe key. Each
/// component present replaces the clip's value (an animation channel's meaning in glTF); a
/// component absent keeps it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct JointSet {
    /// Index in [`Skeleton::nodes`].
    pub node: u32,
    /// The node is held at its rest transform (a LOD level that drops it), before any
    /// component below.
    pub rest: bool,
    /// Translation, in steps.
    pub translation: Option<[i64; 3]>,
    /// Unit rotation (x, y, z, w), in steps, in the hemisphere `w ≥ 0`.
    pub rotation: Option<[i32; 4]>,
    /// Scale, in steps.
    pub scale: Option<[i64; 3]>,
}

fn quantize(v: f32) -> i64 {
    let v = v.clamp(-MAX_JOINT_VALUE, MAX_JOINT_VALUE);
    (f64::from(v) / JOINT_STEP).round() as i64
}

fn dequantize(q: i64) -> f32 {
    (q as f64 * JOINT_STEP) as f32
}

impl JointSet {
    /// The override of `node` by the given components (finite; a rotation of non-zero
    /// length, normalized here; callers check and say which field is wrong).
    pub fn new(
        node: u32,
        translation: Option<[f32; 3]>,
        rotation: Option<[f32; 4]>,
        scale: Option<[f32; 3]>,
    ) -> JointSet {
        let rotation = rotation.map(|r| {
            let mut q = Vec4::from(r).try_normalize().unwrap_or(Vec4::W);
            // q and −q are one rotation: one of them is the key.
            let first = q.to_array().into_iter().rev().find(|c| *c != 0.0);
            if first.is_some_and(|c| c < 0.0) {
                q = -q;
            }
            q.to_array().map(|c| quantize(c) as i32)
        });
        JointSet {
            node,
            rest: false,
            translation: translation.map(|t| t.map(quantize)),
            rotation,
            scale: scale.map(|s| s.map(quantize)),
        }
    }

    /// Holds `node` at its rest transform.
    pub fn rest(node: u32) -> JointSet {
        JointSet {
            node,
            rest: true,
            translation: None,
            rotation: None,
            scale: None,
        }
    }

    /// `local` with this override's components in place of its own (`rest`: the node's rest
    /// transform).
    pub fn apply(&self, rest: &Trs, local: &mut Trs) {
        if self.rest {
            *local = *rest;
        }
        if let Some(t) = self.translation {
            local.translation = t.map(dequantize);
        }
        if let Some(r) = self.rotation {
            let q = Vec4::from(r.map(|c| dequantize(i64::from(c))));
            local.rotation = q.try_normalize().unwrap_or(Vec4::W).to_array();
        }
        if let Some(s) = self.scale {
            local.scale = s.map(dequantize);
        }
    }
}

/// A job's joint overrides: none, or one [`JointSet`] per overridden node, sorted by node
/// (one per node), so that heads asking for the same overrides share a job.
#[derive(Clone, Debug, Default, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct JointPose(Option<Arc<[JointSet]>>);

impl JointPose {
    /// No overrides: every node as its pose says.
    pub const NONE: JointPose = JointPose(None);

    /// The canonical pose of `sets` (sorted by node; a node given twice keeps its last set).
    pub fn new(mut sets: Vec<JointSet>) -> JointPose {
        sets.retain(|s| {
            s.rest || s.translation.is_some() || s.rotation.is_some() || s.scale.is_some()
        });
        if sets.is_empty() {
            return JointPose(None);
        }
        sets.sort_by_key(|s| s.node);
        let mut out: Vec<JointSet> = Vec::with_capacity(sets.len());
        for s in sets {
            match out.last_mut() {
                Some(last) if last.node == s.node => *last = s,
                _ => out.push(s),
            }
        }
        JointPose(Some(out.into()))
    }

    /// The overrides, by node.
    pub fn sets(&self) -> &[JointSet] {
        self.0.as_deref().unwrap_or(&[])
    }

    /// Whether there are none.
    pub fn is_none(&self) -> bool {
        self.0.is_none()
    }

    /// These overrides with `top`'s on top: per node, `top`'s components replace these (a
    /// request's overrides over a graph fade's joints).
    pub fn overlay(&self, top: &JointPose) -> JointPose {
        if top.is_none() {
            return self.clone();
        }
        if self.is_none() {
            return top.clone();
        }
        let mut sets: Vec<JointSet> = self.sets().to_vec();
        for t in top.sets() {
            match sets.iter_mut().find(|s| s.node == t.node) {
                Some(s) => {
                    if t.rest {
                        *s = *t;
                    } else {
                        s.translation = t.translation.or(s.translation);
                        s.rotation = t.rotation.or(s.rotation);
                        s.scale = t.scale.or(s.scale);
                    }
                }
                None => sets.push(*t),
            }
        }
        JointPose::new(sets)
    }

    /// Applies the overrides to one local transform per node of `skeleton`.
    pub fn apply(&self, skeleton: &Skeleton, locals: &mut [Trs]) {
        for s in self.sets() {
            if let (Some(l), Some(n)) = (
                locals.get_mut(s.node as usize),
                skeleton.nodes.get(s.node as usize),
            ) {
                s.apply(&n.rest, l);
            }
        }
    }

    /// Overrides that make `given` (what a job's pose gives each node) into `locals`: every
    /// node whose transform differs, set whole.
    pub fn from_locals(locals: &[Trs], given: &[Trs]) -> JointPose {
        JointPose::new(
            locals
                .iter()
                .zip(given)
                .enumerate()
                .filter(|(_, (l, g))| l != g)
                .map(|(i, (l, _))| {
                    JointSet::new(
                        i as u32,
                        Some(l.translation),
                        Some(l.rotation),
                        Some(l.scale),
                    )
                })
                .collect(),
        )
    }

    /// Heap bytes it holds (for queue-memory charges).
    pub fn heap_bytes(&self) -> u64 {
        self.0
            .as_ref()
            .map_or(0, |s| 16 + size_of_val(&s[..]) as u64)
    }
}

/// A skeleton's nodes by name, for requests that name joints: node indices sorted by name
/// (four bytes a node), searched by bisection.
#[derive(Clone, Debug, Default)]
pub struct JointIndex {
    order: Vec<u32>,
}

/// Why a joint name does not name one node.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum JointLookup {
    /// No node has the name.
    Missing,
    /// Several nodes have it.
    Ambiguous(usize),
}

impl std::fmt::Display for JointLookup {
    /// The end of a sentence "... names `X`, ...": why `X` is not one node of the rig.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            JointLookup::Missing => f.write_str("which the rig's skeleton does not have"),
            JointLookup::Ambiguous(n) => write!(f, "which {n} nodes of the rig's skeleton share"),
        }
    }
}

impl JointIndex {
    /// The index of `skeleton`'s nodes.
    pub fn new(skeleton: &Skeleton) -> JointIndex {
        let mut order: Vec<u32> = (0..skeleton.nodes.len() as u32).collect();
        order.sort_by(|&a, &b| {
            skeleton.nodes[a as usize]
                .name
                .cmp(&skeleton.nodes[b as usize].name)
        });
        JointIndex { order }
    }

    /// The one node of `skeleton` (the one the index was built from) named `name`.
    pub fn find(&self, skeleton: &Skeleton, name: &str) -> Result<u32, JointLookup> {
        let name_of = |i: u32| {
            skeleton
                .nodes
                .get(i as usize)
                .map_or("", |n| n.name.as_str())
        };
        let k = self.order.partition_point(|&i| name_of(i) < name);
        let same = self.order[k..]
            .iter()
            .take_while(|&&i| name_of(i) == name)
            .count();
        match same {
            0 => Err(JointLookup::Missing),
            1 => Ok(self.order[k]),
            n => Err(JointLookup::Ambiguous(n)),
        }
    }
}

/// One term of a job's pose for the skin pass: a clip's joint table (none: the rest pose) at
/// a frame, weighted by its fraction of the blend.
#[derive(Clone, Debug, PartialEq)]
pub struct SkinTerm {
    /// Share of the blend; the terms of a pose sum to one.
    pub fraction: f32,
    /// The clip's joint transforms, or `None` where the clip animates no joint.
    pub table: Option<Arc<JointTable>>,
    /// Frame of the table.
    pub frame: u32,
}

/// What the skin pass needs of a batch: the skeleton and, per job, the terms of its pose and
/// its joint overrides. The CPU engine resolves the bones per job inside the pass (a few
/// hundred matrices in a thread's scratch), so a batch holds no `jobs × bones` array there.
#[derive(Clone, Debug, PartialEq)]
pub struct SkinPoses {
    /// The rig's skeleton.
    pub skeleton: Arc<Skeleton>,
    /// Per job, its terms; empty is the rest pose.
    pub jobs: Vec<Vec<SkinTerm>>,
    /// Per job, the nodes a request set (applied after the terms).
    pub overrides: Vec<JointPose>,
}

/// Scratch for resolving one job's bones.
#[derive(Default)]
pub struct BoneScratch {
    locals: Vec<Trs>,
    globals: Vec<Mat4>,
    /// The job's bone matrices, after [`SkinPoses::bones`].
    pub bones: Vec<BoneMatrix>,
}

impl SkinPoses {
    /// Resolves job `j`'s bone matrices into `scratch.bones`.
    pub fn bones(&self, j: usize, scratch: &mut BoneScratch) {
        let sk = &self.skeleton;
        sk.locals_of(&self.jobs[j], &mut scratch.locals);
        if let Some(o) = self.overrides.get(j) {
            o.apply(sk, &mut scratch.locals);
        }
        scratch.bones.clear();
        sk.bone_matrices(&scratch.locals, &mut scratch.globals, &mut scratch.bones);
    }

    /// Heap bytes the poses hold (the tables are shared with the rig's clips).
    pub fn bytes(&self) -> u64 {
        self.jobs
            .iter()
            .map(|t| 24 + (t.len() * size_of::<SkinTerm>()) as u64)
            .sum::<u64>()
            + self
                .overrides
                .iter()
                .map(|o| size_of::<JointPose>() as u64 + o.heap_bytes())
                .sum::<u64>()
    }
}

/// The bone of a vertex that follows none (a primitive neither skinned nor under an animated
/// node, or a first weight of 0): it is left as blended.
pub const NO_BONE: u16 = u16::MAX;

/// Calls `f(vertex, bone, weight)` for every vertex of `rig` in evaluation order (primitives
/// concatenated) and each bone it follows with a non-zero weight, as both skin passes read the
/// influences; a vertex that follows none gives one `(NO_BONE, 1.0)`. The CPU engine's tiles
/// and the cost model that charges them both walk the influences through this.
pub fn for_each_influence(rig: &super::Rig, mut f: impl FnMut(usize, u16, f32)) {
    let mut v = 0;
    for p in rig.primitives.iter() {
        for i in 0..p.positions.len() {
            match &p.skin {
                Some(s) if s.weights[i][0] != 0.0 => {
                    for k in (0..INFLUENCES).filter(|&k| s.weights[i][k] != 0.0) {
                        f(v, s.joints[i][k], s.weights[i][k]);
                    }
                }
                _ => f(v, NO_BONE, 1.0),
            }
            v += 1;
        }
    }
}

impl Influences {
    /// Bytes the influences hold.
    pub fn bytes(&self) -> u64 {
        self.joints.len() as u64 * 24
    }

    /// Skins one vertex: `Σ w M p`, and the normal `normalize(Σ w N n)` when given.
    #[inline(always)]
    pub fn skin(
        &self,
        v: usize,
        bones: &[BoneMatrix],
        p: Vec3,
        n: Option<Vec3>,
    ) -> (Vec3, Option<Vec3>) {
        let (j, w) = (&self.joints[v], &self.weights[v]);
        let mut sp = Vec3::ZERO;
        let mut sn = Vec3::ZERO;
        for k in 0..INFLUENCES {
            if w[k] == 0.0 {
                continue;
            }
            let b = &bones[j[k] as usize];
            sp += w[k] * b.point(p);
            if let Some(n) = n {
                sn += w[k] * b.normal(n);
            }
        }
        (sp, n.map(|_| sn.try_normalize().unwrap_or(Vec3::Z)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_rigid_bone_is_the_identity_at_rest_and_follows_its_node() {
        let rest = Trs {
            translation: [1.0, 2.0, 0.0],
            rotation: Quat::from_rotation_z(0.3).to_array(),
            scale: [2.0; 3],
        };
        let sk = Skeleton {
            nodes: vec![SkelNode {
                name: "a".into(),
                parent: NO_PARENT,
                rest,
            }],
            bones: vec![Bone {
                node: 0,
                bind: rest.matrix().inverse().to_cols_array(),
            }],
            map: None,
        };
        let (mut g, mut out) = (Vec::new(), Vec::new());
        sk.bone_matrices(&sk.rest(), &mut g, &mut out);
        let p = Vec3::new(0.5, -1.0, 3.0);
        assert!((out[0].point(p) - p).length() < 1e-5);
        let mut moved = rest;
        moved.translation[0] += 1.0;
        out.clear();
        sk.bone_matrices(&[moved], &mut g, &mut out);
        assert!((out[0].point(p) - (p + Vec3::X)).length() < 1e-5);
    }

    #[test]
    fn top_influences_keep_four_and_renormalize() {
        let mut pairs = vec![(0, 0.1), (1, 0.4), (2, 0.05), (3, 0.25), (4, 0.2)];
        let (j, w, dropped) = top_influences(&mut pairs);
        assert_eq!(j, [1, 3, 4, 0]);
        assert!((dropped - 0.05).abs() < 1e-6);
        assert!((w.iter().sum::<f32>() - 1.0).abs() < 1e-6);
    }

    #[test]
    fn a_blend_of_a_rotation_with_itself_is_that_rotation() {
        let r = Quat::from_rotation_y(1.0);
        let t = JointTable {
            nodes: vec![0],
            frames: 2,
            values: [
                Trs::default().floats(),
                Trs {
                    rotation: (-r).to_array(),
                    ..Trs::default()
                }
                .floats(),
            ]
            .concat(),
        };
        let sk = Skeleton {
            nodes: vec![SkelNode {
                name: "a".into(),
                parent: NO_PARENT,
                rest: Trs::default(),
            }],
            bones: vec![],
            map: None,
        };
        let mut out = Vec::new();
        sk.locals_blend(&[(0.5, Some(&t), 1), (0.5, Some(&t), 1)], &mut out);
        let q = Quat::from_array(out[0].rotation);
        assert!(q.angle_between(r) < 1e-5);
        // Halfway between rest and the rotation: half the angle.
        sk.locals_blend(&[(0.5, Some(&t), 0), (0.5, Some(&t), 1)], &mut out);
        let q = Quat::from_array(out[0].rotation);
        assert!((q.angle_between(Quat::IDENTITY) - 0.5).abs() < 1e-4);
    }
}
