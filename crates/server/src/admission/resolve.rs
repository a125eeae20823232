//! Turning a request's heads into work: each head resolved against one snapshot of the rig it
//! names (clip, frame and LOD checked), the unique jobs planned, and what they cost — output
//! bytes held, weight rows, the batcher's cost — priced before any of it is done.

use std::collections::HashMap;
use std::sync::Arc;

use crowdmorph_proto::{
    BlendLayer, Format, Head, JointOverrides, JointTransform, LayerMode, LiveWeights,
    MAX_HEAD_LAYERS,
};

use crate::admission::layers::{
    decoded_layers_bytes, finish_weights, layered_joints, layered_joints_bytes, layers_bytes,
    resolve_layers,
};
use crate::admission::mapping::{ResolvedMapping, mapping_spec, resolve_mapping, resolved_bytes};
use crate::admission::names::{LiveNames, is_arkit_name, live_names};
pub use crate::admission::names::{unknown_clip, unknown_rig};

use crate::admission::memory::{Charge, QueueMemory};
use crate::http::ApiError;
use crate::registry::{MAX_F16, Registry, RigEntry};
use crate::scheduler::JobRequest;
use crowdmorph_core::plan::{JobKey, Plan};
use crowdmorph_core::rig::quoted_name;
use crowdmorph_core::rig::{
    ACTIVE_WEIGHT_EPSILON, ARKIT_NAMES, FrameMode, JointPose, JointSet, MAX_BLEND_LAYERS,
    MAX_JOINT_OVERRIDES, MAX_JOINT_VALUE, MAX_LIVE_WEIGHT, MAX_NEAR_TOLERANCE, Pose, Rig,
    layer_weights,
};
use crowdmorph_import::clips::{checked_name, is_live_link_angle, loose};

/// Largest coordinate (in absolute value) a rig's positions can reach, from its q16 box.
pub fn head_reach(entry: &RigEntry) -> f64 {
    let q = &entry.qbox;
    (0..3)
        .map(|a| {
            let lo = f64::from(q.min[a]);
            let hi = lo + f64::from(q.step[a]) * 65535.0;
            lo.abs().max(hi.abs())
        })
        .fold(0.0, f64::max)
}

/// Crowd heads resolved against one snapshot of each rig they name: what both crowd endpoints
/// compute from.
pub struct ResolvedHeads {
    /// The rigs, in order of first appearance; `JobKey::rig` indexes this.
    pub rigs: Vec<Arc<RigEntry>>,
    /// Unique jobs and each head's job.
    pub plan: Plan,
    /// What the live weights' poses hold (none without live heads), charged before they
    /// were built; the request keeps it until it is answered.
    pub charge: Option<Charge>,
}

/// Bytes one job's output holds while it is computed and sent: positions (and normals) in the
/// wire format, three times that as JSON (base64 text and its escape), plus, with normals in a
/// 16-bit format on a rig whose normals are recomputed, the f32 positions and normals the CPU
/// engine blends before the normals pass and the encoding, and, for q16 on the GPU engine
/// (`gpu`), the f32 outputs it reads back and quantizes on the host. The job's weights are
/// counted too ([`JOB_WEIGHT_BYTES_PER_TARGET`] per rig target): on a rig of many targets and
/// few vertices they outweigh the output. Every admission (crowd frames, sessions, load tests)
/// charges this.
pub fn job_output_bytes(rig: &Rig, format: Format, normals: bool, json: bool, gpu: bool) -> u64 {
    let v3 = rig.vertex_count() as u64 * 3;
    let comp = format.component_bytes() as u64;
    let outputs = if normals { 2 } else { 1 };
    let wire = v3 * comp * outputs * if json { 3 } else { 1 };
    let f32_first =
        (normals && comp < 4 && rig.recomputes_normals()) || (gpu && format.quantized());
    let weights = rig.targets.len() as u64 * JOB_WEIGHT_BYTES_PER_TARGET + 16;
    // q16 residuals are coded against a reference (one job's components), on the host with
    // planes of one job per worker, for the device from a copy padded to whole words (per
    // batch group; charged per job, which bounds it).
    let residual = if format == Format::Q16R { 4 * v3 } else { 0 };
    // A skinned rig's jobs hold their bone matrices (96 bytes a bone), resolved on the host
    // for both engines (the skin itself is in the output stage, no second f32 buffer).
    let skin = rig
        .skeleton
        .as_ref()
        .map_or(0, |s| s.bones.len() as u64 * 96);
    wire + if f32_first { v3 * 4 * outputs } else { 0 } + weights + residual + skin
}

/// What a batch holds per job and rig target besides the outputs: the job's row of the
/// gathered weights (`WeightBatch`, 4 bytes per target) and its lane of the CPU kernel's
/// group tables (4 bytes of weight and, per group of 8 jobs, a byte per target), rounded up.
/// The GPU engine gathers the same rows before it uploads them.
pub const JOB_WEIGHT_BYTES_PER_TARGET: u64 = 9;

/// Bytes `heads` hold decoded (each `Head` and its two names), plus `built` bytes a head of
/// what a handler builds from them: the per-head share a crowd frame keeps charged until its
/// response is sent, and a render until its frame is drawn.
pub fn heads_held_bytes(heads: &Vec<Head>, built: u64) -> u64 {
    // The vector's slots by capacity: decoding JSON grows it by doubling, up to twice its
    // length.
    let slots = heads.capacity() as u64 * size_of::<Head>() as u64;
    let names: u64 = heads
        .iter()
        .map(|h| h.rig.capacity() as u64 + h.clip.capacity() as u64 + animation_bytes(h))
        .sum();
    slots + heads.len() as u64 * built + names
}

/// Bytes a head's blend layers and live weights hold decoded (by capacity, with their names).
fn animation_bytes(h: &Head) -> u64 {
    let layers = h.blend.capacity() as u64 * size_of::<BlendLayer>() as u64
        + h.blend
            .iter()
            .map(|l| l.clip.capacity() as u64)
            .sum::<u64>();
    let weights = match h.weights.as_deref() {
        None => 0,
        Some(LiveWeights::Dense(w)) => size_of::<LiveWeights>() as u64 + w.capacity() as u64 * 4,
        Some(LiveWeights::Named(w)) => {
            size_of::<LiveWeights>() as u64
                + w.capacity() as u64 * size_of::<(String, f32)>() as u64
                + w.iter().map(|(n, _)| n.capacity() as u64).sum::<u64>()
        }
    };
    layers + weights + joints_bytes(&h.joints) + decoded_layers_bytes(&h.layers)
}

/// Bytes a head's joint overrides hold decoded (by capacity, with their names).
pub fn joints_bytes(j: &JointOverrides) -> u64 {
    j.0.capacity() as u64 * size_of::<(String, JointTransform)>() as u64
        + j.0.iter().map(|(n, _)| n.capacity() as u64).sum::<u64>()
}

/// Bytes the [`JointPose`] of `n` overrides holds.
pub fn joint_pose_bytes(n: usize) -> u64 {
    if n == 0 {
        0
    } else {
        16 + (n * size_of::<JointSet>()) as u64
    }
}

/// A head's joint overrides resolved against its rig's skeleton: names to nodes, values
/// checked and quantized (a job's LOD level then drops the nodes it does not animate, through
/// `JointLod::level`). The error is (code, message): 400 `unknown_joints` for a name no node
/// has (or several have), 400 `invalid_joints` for a rig without a skeleton, too many
/// overrides, a node named twice or a value that is not finite, out of range or a zero
/// rotation. The caller charges [`joint_pose_bytes`] first.
pub fn requested_joints(
    entry: &RigEntry,
    joints: &JointOverrides,
) -> Result<JointPose, (&'static str, String)> {
    if joints.is_empty() {
        return Ok(JointPose::NONE);
    }
    let rig = entry.rig();
    let Some(sk) = &rig.skeleton else {
        return Err((
            "invalid_joints",
            format!(
                "rig {:?} has no skeleton (no skins and no animated nodes): joints cannot pose it",
                entry.id
            ),
        ));
    };
    let most = sk.nodes.len().min(MAX_JOINT_OVERRIDES);
    if joints.len() > most {
        return Err((
            "invalid_joints",
            format!(
                "{} joint overrides; rig {:?} takes at most {most}",
                joints.len(),
                entry.id
            ),
        ));
    }
    let invalid = |m: String| ("invalid_joints", m);
    let facts = entry.joint_lod();
    let mut sets = Vec::with_capacity(joints.len());
    for (name, t) in &joints.0 {
        let node = entry.joint_node(name).map_err(|why| {
            (
                "unknown_joints",
                format!(
                    "joints name {}, {why} (GET /v1/rigs/{} with Accept: application/json lists every node that can be set in skeleton.node_names)",
                    quoted_name(name),
                    entry.id
                ),
            )
        })?;
        let field = |what: &str| format!("joints[{}].{what}", quoted_name(name));
        let bounded = |v: &[f32]| {
            v.iter()
                .all(|x| x.is_finite() && x.abs() <= MAX_JOINT_VALUE)
        };
        if let Some(v) = &t.translation
            && !bounded(v)
        {
            return Err(invalid(format!(
                "{} is {v:?}; each must be finite, within ±{MAX_JOINT_VALUE:e}",
                field("translation")
            )));
        }
        if let Some(v) = &t.scale
            && !bounded(v)
        {
            return Err(invalid(format!(
                "{} is {v:?}; each must be finite, within ±{MAX_JOINT_VALUE:e}",
                field("scale")
            )));
        }
        // The q16 box holds every pose whose nodes stay within the translations and scales
        // they have at rest or in a clip (rotations keep lengths): an override may not leave
        // it.
        let (t_max, s_max) = &facts.extents;
        // Room for f32 rounding and for a value that went through the 2^-20 quantization once
        // already (a session's pose sent to the renderer as overrides).
        let slack = |m: f64| m * (1.0 + 1e-6) + 4.0 * crowdmorph_core::rig::JOINT_STEP;
        if let Some(v) = &t.translation {
            let len = v.iter().map(|&c| f64::from(c).powi(2)).sum::<f64>().sqrt();
            if len > slack(t_max[node as usize]) {
                return Err(invalid(format!(
                    "{} has length {len}, more than node {} reaches at rest or in any clip ({}): the rig's output range (its q16 box) is sized for those",
                    field("translation"),
                    quoted_name(name),
                    t_max[node as usize]
                )));
            }
        }
        if let Some(v) = &t.scale {
            let big = v.iter().fold(0f64, |m, &c| m.max(f64::from(c).abs()));
            if big > slack(s_max[node as usize]) {
                return Err(invalid(format!(
                    "{} is {v:?}, larger than node {} is scaled at rest or in any clip ({}): the rig's output range (its q16 box) is sized for those",
                    field("scale"),
                    quoted_name(name),
                    s_max[node as usize]
                )));
            }
        }
        // A rotation of any finite, non-zero length is that rotation: normalized here in f64,
        // where the squares of f32 components cannot underflow (in f32, components of 1e-30
        // square to zero and the rotation would become the identity).
        let rotation = match &t.rotation {
            None => None,
            Some(q) => {
                let len2: f64 = q.iter().map(|&c| f64::from(c) * f64::from(c)).sum();
                let bounded = q
                    .iter()
                    .all(|c| c.is_finite() && c.abs() <= MAX_JOINT_VALUE);
                // Bounded components have a finite length; only all zeros have none.
                if !bounded || len2 == 0.0 {
                    return Err(invalid(format!(
                        "{} is {q:?}; a rotation is a quaternion x, y, z, w of finite components, \
                         not all zero (any non-zero length is normalized)",
                        field("rotation")
                    )));
                }
                let len = len2.sqrt();
                Some(q.map(|c| (f64::from(c) / len) as f32))
            }
        };
        if sets.iter().any(|s: &JointSet| s.node == node) {
            return Err(invalid(format!(
                "joints set node {} twice",
                quoted_name(name)
            )));
        }
        sets.push(JointSet::new(node, t.translation, rotation, t.scale));
    }
    Ok(JointPose::new(sets))
}

/// Resolves every head against one snapshot of each rig it names (a rig changed or
/// deleted meanwhile does not change this request), checks clip, frame and LOD, and plans
/// the unique jobs. `f16` refuses rigs whose coordinates f16 cannot hold. Errors name the
/// head by position and id.
pub fn resolve_heads(
    registry: &Registry,
    memory: &QueueMemory,
    max_heads: usize,
    heads: &[Head],
    mode: FrameMode,
    f16: bool,
) -> Result<ResolvedHeads, ApiError> {
    let n_heads = heads.len();
    if n_heads > max_heads {
        return Err(ApiError::bad_request(
            "too_many_heads",
            format!(
                "{n_heads} heads is more than the limit of {} per request",
                max_heads
            ),
        ));
    }
    let mut lookups = Lookups {
        registry,
        memory,
        rigs: Vec::new(),
        rig_at: HashMap::new(),
        clip_at: HashMap::new(),
        live: HashMap::new(),
        charge: None,
        row: Vec::new(),
        live_joints: JointPose::NONE,
        mappings: HashMap::new(),
        mapped: Vec::new(),
    };
    let mut keys = Vec::with_capacity(n_heads);
    for (h, head) in heads.iter().enumerate() {
        let ri = lookups.rig(h, head)?;
        let entry = &lookups.rigs[ri as usize];
        if f16 && head_reach(entry) > MAX_F16 {
            return Err(ApiError::bad_request(
                "format_overflow",
                format!(
                    "head {h} (id {}): rig {:?} reaches coordinates of {:e}, past the largest \
                     f16 ({}); ask for f32 or q16",
                    head.head,
                    entry.id,
                    head_reach(entry),
                    MAX_F16
                ),
            ));
        }
        let pose = lookups.pose(h, head, ri, mode)?;
        let entry = &lookups.rigs[ri as usize];
        let rig = entry.rig();
        if head.lod as usize >= rig.lod.levels.len() {
            return Err(ApiError::bad_request(
                "lod_out_of_range",
                format!(
                    "head {h} (id {}): LOD {} out of range: rig {:?} has levels 0..{}",
                    head.head,
                    head.lod,
                    entry.id,
                    rig.lod.levels.len() - 1
                ),
            ));
        }
        let joints = lookups.joints(h, head, ri)?;
        let pose = lookups.near_clone(h, head, ri, pose)?;
        keys.push(JobKey {
            rig: ri,
            pose,
            lod: head.lod,
            joints,
        });
    }
    let Lookups { rigs, charge, .. } = lookups;
    Ok(ResolvedHeads {
        rigs,
        plan: Plan::new(keys),
        charge,
    })
}

/// The rigs and clips a request names, each looked up once: a crowd of thousands of heads
/// names a handful.
struct Lookups<'h> {
    registry: &'h Registry,
    memory: &'h QueueMemory,
    /// One snapshot per distinct rig, in order of first mention.
    rigs: Vec<Arc<RigEntry>>,
    rig_at: HashMap<&'h str, u32>,
    clip_at: HashMap<(u32, &'h str), u32>,
    /// Per rig with live heads, its name matcher (built once, charged).
    live: HashMap<u32, LiveNames>,
    /// What the live weights' poses and matchers hold, charged before they are built.
    charge: Option<Charge>,
    /// One head's channel weights, reused.
    row: Vec<f32>,
    /// The joint transforms the current live head's angle weights (Live Link's `HeadYaw`, ...)
    /// set, taken by [`Lookups::joints`].
    live_joints: JointPose,
    /// Per rig and mapping name that heads use, the mapping resolved once (charged).
    mappings: HashMap<(u32, &'h str), ResolvedMapping>,
    /// The current mapped head's `(channel, weight)` pairs, reused.
    mapped: Vec<(u32, f32)>,
}

impl<'h> Lookups<'h> {
    /// The index of head `h`'s rig in `rigs`, or 404 naming the head.
    fn rig(&mut self, h: usize, head: &'h Head) -> Result<u32, ApiError> {
        if let Some(&i) = self.rig_at.get(head.rig.as_str()) {
            return Ok(i);
        }
        let e = self
            .registry
            .get(&head.rig)
            .ok_or_else(|| at_head(h, head, unknown_rig(self.registry, &head.rig)))?;
        self.rigs.push(e);
        let i = (self.rigs.len() - 1) as u32;
        self.rig_at.insert(head.rig.as_str(), i);
        Ok(i)
    }

    /// The index of clip `name` in rig `ri`, or 404 naming head `h`.
    fn clip(&mut self, h: usize, head: &Head, name: &'h str, ri: u32) -> Result<u32, ApiError> {
        if let Some(&c) = self.clip_at.get(&(ri, name)) {
            return Ok(c);
        }
        let entry = &self.rigs[ri as usize];
        let c = entry
            .clip_index(name)
            .ok_or_else(|| at_head(h, head, unknown_clip(entry, name)))? as u32;
        self.clip_at.insert((ri, name), c);
        Ok(c)
    }

    /// Frame `frame` of clip `ci` resolved by `mode`, or 400 naming head `h`.
    fn frame(
        &self,
        h: usize,
        head: &Head,
        ri: u32,
        ci: u32,
        frame: i64,
        mode: FrameMode,
    ) -> Result<u32, ApiError> {
        self.rigs[ri as usize].rig().clips[ci as usize]
            .resolve_frame(frame, mode)
            .map_err(|e| {
                ApiError::bad_request(
                    "frame_out_of_range",
                    format!("head {h} (id {}): {e}", head.head),
                )
            })
    }

    /// Head `h`'s pose: its clip frame with its blend, or its live weights; with layers, live
    /// weights over a clip or a clamp, the final weights those give, as live weights.
    fn pose(
        &mut self,
        h: usize,
        head: &'h Head,
        ri: u32,
        mode: FrameMode,
    ) -> Result<Pose, ApiError> {
        if head.mapping.is_some() && !matches!(head.weights.as_deref(), Some(LiveWeights::Named(_)))
        {
            return Err(invalid_weights(
                h,
                head,
                "a mapping maps weights by name: send \"weights\" as an object of the mapping's \
                 source names (dense weights, or none, have nothing to map)"
                    .into(),
            ));
        }
        let over_clip = head.weights.is_some() && !head.clip.is_empty();
        if head.weights.is_some() && head.clip.is_empty() && !head.blend.is_empty() {
            return Err(invalid_weights(
                h,
                head,
                "blend layers need a clip to blend: send weights with a clip (they then apply \
                 over it), or a clip and blend"
                    .into(),
            ));
        }
        if head.layers.is_empty() && head.clamp.is_none() && !over_clip {
            return match &head.weights {
                Some(weights) => self.live_pose(h, head, ri, weights),
                None => self.clip_pose(h, head, ri, mode),
            };
        }
        self.layered_pose(h, head, ri, mode)
    }

    /// Head `h`'s clip frame, blended with its blend layers.
    fn clip_pose(
        &mut self,
        h: usize,
        head: &'h Head,
        ri: u32,
        mode: FrameMode,
    ) -> Result<Pose, ApiError> {
        let ci = self.clip(h, head, &head.clip, ri)?;
        let frame = self.frame(h, head, ri, ci, head.frame, mode)?;
        if head.blend.is_empty() {
            return Ok(Pose::Frame { clip: ci, frame });
        }
        if head.blend.len() > MAX_BLEND_LAYERS {
            return Err(invalid_blend(
                h,
                head,
                format!(
                    "blend has {} layers; at most {MAX_BLEND_LAYERS}",
                    head.blend.len()
                ),
            ));
        }
        let mut layers = [(0u32, 0u32, 0f32); MAX_BLEND_LAYERS];
        let mut sum = 0f64;
        for (i, layer) in head.blend.iter().enumerate() {
            if !(layer.t.is_finite() && (0.0..=1.0).contains(&layer.t)) {
                return Err(invalid_blend(
                    h,
                    head,
                    format!("blend[{i}].t is {}; it must be in [0, 1]", layer.t),
                ));
            }
            sum += f64::from(layer.t);
            let c = self.clip(h, head, &layer.clip, ri)?;
            let f = self.frame(h, head, ri, c, layer.frame, mode)?;
            layers[i] = (c, f, layer.t);
        }
        if sum > 1.0 + 1e-6 {
            return Err(invalid_blend(
                h,
                head,
                format!("the blend's fractions sum to {sum}; Σt must be at most 1"),
            ));
        }
        Ok(Pose::blend((ci, frame), &layers[..head.blend.len()]))
    }

    /// Head `h`'s joint overrides (over what its live angles set), their bytes charged before
    /// they are built.
    fn joints(&mut self, h: usize, head: &Head, ri: u32) -> Result<JointPose, ApiError> {
        let from_weights = std::mem::take(&mut self.live_joints);
        let entry = self.rigs[ri as usize].clone();
        if !head.joints.is_empty() {
            let dropped = entry
                .joint_lod()
                .dropped
                .get(head.lod as usize)
                .map_or(0, Vec::len);
            self.charge_more(
                joint_pose_bytes(head.joints.len() + dropped)
                    + joint_pose_bytes(from_weights.sets().len()),
            )?;
        }
        let requested = requested_joints(&entry, &head.joints)
            .map_err(|(code, m)| at_head(h, head, ApiError::bad_request(code, m)))?;
        Ok(entry
            .joint_lod()
            .level(head.lod)
            .joints(&from_weights.overlay(&requested)))
    }

    /// Head `h`'s pose as a near-clone within its `tolerance` (`RigEntry::near_clone`),
    /// charged as a live pose is; the pose itself without one. A tolerance that is not a
    /// finite number in `0..=MAX_NEAR_TOLERANCE` is a 400 naming the head.
    fn near_clone(
        &mut self,
        h: usize,
        head: &'h Head,
        ri: u32,
        pose: Pose,
    ) -> Result<Pose, ApiError> {
        let Some(t) = head.tolerance else {
            return Ok(pose);
        };
        if !(t.is_finite() && (0.0..=MAX_NEAR_TOLERANCE).contains(&t)) {
            return Err(ApiError::bad_request(
                "invalid_tolerance",
                format!(
                    "head {h} (id {}): tolerance {t} must be a finite number in \
                     0..={MAX_NEAR_TOLERANCE} (a fraction of the rig's diagonal)",
                    head.head
                ),
            ));
        }
        if t == 0.0 {
            return Ok(pose);
        }
        let entry = self.rigs[ri as usize].clone();
        // The level was checked by the caller; a pose the near-clone does not apply to
        // (joints, a PCA level, too small a tolerance) stays exact.
        self.charge_more(16 + 4 * entry.rig().targets.len() as u64)?;
        Ok(entry
            .near_clone(&pose, head.lod, f64::from(t))
            .unwrap_or(pose))
    }

    /// Adds `bytes` to what the request's poses hold.
    fn charge_more(&mut self, bytes: u64) -> Result<(), ApiError> {
        let more = self.memory.reserve(bytes)?;
        match &mut self.charge {
            Some(c) => c.merge(more),
            None => self.charge = Some(more),
        }
        Ok(())
    }

    /// Head `h`'s final weights with its layers (`crowdmorph_core::rig::layer`): its base (its
    /// clip frame with blend, else its live weights), its layers in order, then its weights
    /// over the clip (replacing or adding to the channels they name), then its clamp; on a
    /// skinned rig the base's joints are layered the same way and go along as overrides
    /// (live weights pose no joint), taken by [`Lookups::joints`].
    fn layered_pose(
        &mut self,
        h: usize,
        head: &'h Head,
        ri: u32,
        mode: FrameMode,
    ) -> Result<Pose, ApiError> {
        let entry = self.rigs[ri as usize].clone();
        let rig = entry.rig();
        let channels = rig.targets.len();
        let (base, live_angles) = match (&head.weights, head.clip.is_empty()) {
            (Some(weights), true) => {
                let p = self.live_pose(h, head, ri, weights)?;
                (p, std::mem::take(&mut self.live_joints))
            }
            _ => (self.clip_pose(h, head, ri, mode)?, JointPose::NONE),
        };
        if head.layers.len() > MAX_HEAD_LAYERS {
            return Err(invalid_layer(
                h,
                head,
                format!(
                    "{} layers; a head has at most {MAX_HEAD_LAYERS}",
                    head.layers.len()
                ),
            ));
        }
        let mut bytes = layers_bytes(rig, &head.layers);
        if !self.live.contains_key(&ri) {
            bytes += LiveNames::bytes(rig);
        }
        self.charge_more(bytes)?;
        let names = self
            .live
            .entry(ri)
            .or_insert_with(|| live_names(self.registry, &entry));
        let rigs = &self.rigs;
        let layers = resolve_layers(&entry, names, &head.layers, |clip, frame, _| {
            rigs[ri as usize].rig().clips[clip as usize]
                .resolve_frame(frame, mode)
                .map_err(|e| ApiError::bad_request("frame_out_of_range", e.to_string()))
        })
        .map_err(|e| at_head(h, head, e))?;
        // The final weights, and the live pose built of them.
        self.charge_more(2 * (16 + channels as u64 * 4))?;
        let mut w = base.weights(rig);
        layer_weights(rig, &mut w, &layers);
        if let (Some(weights), false) = (&head.weights, head.clip.is_empty()) {
            let named = self.live_values(h, head, ri, weights)?;
            for &k in &named {
                let k = k as usize;
                match head.weights_mode {
                    LayerMode::Override => w[k] = self.row[k],
                    LayerMode::Additive => w[k] += self.row[k],
                }
            }
            // Angles sent with the weights (left in `live_joints`) turn joints as they do
            // without a clip: on top of the layers' joints below, as live input is.
        }
        finish_weights(rig, &mut w, head.clamp).map_err(|e| at_head(h, head, e))?;
        if let Some(sk) = &rig.skeleton {
            self.charge_more(layered_joints_bytes(sk))?;
            // A live base's angles are under the layers; weights over a clip, on top.
            let on_top = std::mem::take(&mut self.live_joints);
            self.live_joints =
                layered_joints(&entry, &base, &live_angles, &layers).overlay(&on_top);
        }
        Ok(Pose::live(&w))
    }

    /// Head `h`'s live weights over its clip: `self.row` holds them, and the channels they
    /// set are returned (every channel for dense weights).
    fn live_values(
        &mut self,
        h: usize,
        head: &'h Head,
        ri: u32,
        weights: &LiveWeights,
    ) -> Result<Vec<u32>, ApiError> {
        self.live_pose(h, head, ri, weights)?;
        let entry = self.rigs[ri as usize].clone();
        let rig = entry.rig();
        Ok(match weights {
            LiveWeights::Dense(_) => (0..rig.targets.len() as u32).collect(),
            // Mapped: the channels the mapping set (ascending, each once).
            LiveWeights::Named(_) if head.mapping.is_some() => {
                self.mapped.iter().map(|p| p.0).collect()
            }
            LiveWeights::Named(pairs) => {
                let names = self
                    .live
                    .entry(ri)
                    .or_insert_with(|| live_names(self.registry, &entry));
                let mut out: Vec<u32> = pairs
                    .iter()
                    .flat_map(|(n, _)| names.ids(n).iter().copied())
                    .collect();
                out.sort_unstable();
                out.dedup();
                out
            }
        })
    }

    /// Head `h`'s named weights through its mapping `name` into `self.row` (the mapping
    /// resolved once per request and rig, charged), the channels set left in `self.mapped`.
    fn mapped_row(
        &mut self,
        h: usize,
        head: &Head,
        ri: u32,
        name: &'h str,
        pairs: &[(String, f32)],
    ) -> Result<(), ApiError> {
        let entry = self.rigs[ri as usize].clone();
        if !self.mappings.contains_key(&(ri, name)) {
            let rig = entry.rig();
            let spec =
                mapping_spec(&entry, &self.registry.maps, name).map_err(|e| at_head(h, head, e))?;
            let mut bytes = 2 * spec.heap_bytes() + resolved_bytes(&spec, rig);
            if !self.live.contains_key(&ri) {
                bytes += LiveNames::bytes(rig);
            }
            self.charge_more(bytes)?;
            let registry = self.registry;
            let names = self
                .live
                .entry(ri)
                .or_insert_with(|| live_names(registry, &entry));
            let resolved =
                resolve_mapping(&entry, names, name, &spec).map_err(|e| at_head(h, head, e))?;
            // Its scratch (a value per source, a pair per term), reused by every head.
            self.charge_more(resolved.map_bytes())?;
            self.mappings.insert((ri, name), resolved);
        }
        if let Some(m) = self.mappings.get(&(ri, name)) {
            m.map(pairs, &mut self.mapped)
                .map_err(|e| at_head(h, head, e))?;
        }
        for &(k, w) in &self.mapped {
            if let Some(slot) = self.row.get_mut(k as usize) {
                *slot = w;
            }
        }
        Ok(())
    }

    /// Head `h`'s live weights as a pose, its bytes charged before it is built.
    fn live_pose(
        &mut self,
        h: usize,
        head: &'h Head,
        ri: u32,
        weights: &LiveWeights,
    ) -> Result<Pose, ApiError> {
        let entry = self.rigs[ri as usize].clone();
        let rig = entry.rig();
        let channels = rig.targets.len();
        let mut bytes = 16 + channels as u64 * 4;
        if !self.live.contains_key(&ri) {
            bytes += LiveNames::bytes(rig);
        }
        if self.row.capacity() < channels {
            bytes += channels as u64 * 4;
        }
        self.charge_more(bytes)?;
        // The rig's joint map as live weights read it (built once per generation, charged to
        // the rig).
        let live_angles = entry.live_angles();
        if let (Some(m), LiveWeights::Named(pairs)) = (head.mapping.as_deref(), weights) {
            // Channels the mapping does not set keep the rig's default weight.
            self.row.clear();
            self.row.extend_from_slice(&rig.default_weights);
            self.mapped_row(h, head, ri, m, pairs)?;
            return Ok(Pose::live(&self.row));
        }
        // Live Link's head and eye angles among named weights: (channel of the joint map, value).
        let mut angles: Vec<(usize, f32)> = Vec::new();
        let names = self
            .live
            .entry(ri)
            .or_insert_with(|| live_names(self.registry, &entry));
        // Channels not named keep the rig's default weight, as in a CSV clip.
        self.row.clear();
        self.row.extend_from_slice(&rig.default_weights);
        let check = |what: &dyn std::fmt::Display, w: f32| -> Result<(), ApiError> {
            if w.is_finite() && w.abs() <= MAX_LIVE_WEIGHT {
                Ok(())
            } else {
                Err(invalid_weights(
                    h,
                    head,
                    format!(
                        "weights[{what}] is {w}; a weight must be finite, within ±{MAX_LIVE_WEIGHT}"
                    ),
                ))
            }
        };
        match weights {
            LiveWeights::Dense(w) => {
                if w.len() != names.by_position.len() {
                    return Err(invalid_weights(
                        h,
                        head,
                        format!(
                            "{} dense weights for rig {:?}, which has {} targets (RigInfo.targets)",
                            w.len(),
                            entry.id,
                            names.by_position.len()
                        ),
                    ));
                }
                for (i, (&w, ids)) in w.iter().zip(&names.by_position).enumerate() {
                    check(&i, w)?;
                    for &id in ids {
                        self.row[id as usize] = w;
                    }
                }
            }
            LiveWeights::Named(pairs) => {
                // Each target once, plus ARKit names the rig may lack.
                if pairs.len() > names.by_position.len() + ARKIT_NAMES.len() {
                    return Err(invalid_weights(
                        h,
                        head,
                        format!(
                            "{} named weights for rig {:?}, which has {} targets",
                            pairs.len(),
                            entry.id,
                            names.by_position.len()
                        ),
                    ));
                }
                // Each channel once: a second weight for one name (or two spellings of it) is
                // an error, not a silent override.
                let mut seen = std::collections::HashSet::with_capacity(pairs.len());
                for (name, w) in pairs {
                    check(&quoted_name(name), *w)?;
                    // A NUL or another control character would vanish in the loose spelling
                    // and match a target the name does not spell.
                    checked_name(name).map_err(|why| {
                        invalid_weights(h, head, format!("weights[{}]: {why}", quoted_name(name)))
                    })?;
                    let ids = names.ids(name);
                    if ids.is_empty()
                        && let Some(&c) = live_angles
                            .as_deref()
                            .and_then(|a| a.columns.get(&loose(name)))
                    {
                        // A head or eye angle the rig's joint map turns a joint by.
                        if angles.iter().any(|a| a.0 == c) {
                            return Err(invalid_weights(
                                h,
                                head,
                                format!("weights name {} twice", quoted_name(name)),
                            ));
                        }
                        angles.push((c, *w));
                        continue;
                    }
                    if ids.is_empty() && (is_arkit_name(name) || is_live_link_angle(name)) {
                        // A tracker sends all 52 every frame (and Live Link its head and eye
                        // angles); this rig cannot show this one.
                        continue;
                    }
                    if ids.is_empty() {
                        return Err(at_head(
                            h,
                            head,
                            ApiError::bad_request(
                                "unknown_targets",
                                format!(
                                    "weights name {}, which rig {:?} does not have (GET /v1/rigs/{} lists its targets)",
                                    quoted_name(name),
                                    entry.id,
                                    entry.id
                                ),
                            ),
                        ));
                    }
                    if !seen.insert(ids[0]) {
                        return Err(invalid_weights(
                            h,
                            head,
                            format!("weights name the target of {} twice", quoted_name(name)),
                        ));
                    }
                    for &id in ids {
                        self.row[id as usize] = *w;
                    }
                }
            }
        }
        if let Some(a) = live_angles.as_deref()
            && !angles.is_empty()
        {
            self.charge_more(joint_pose_bytes(angles.len()))?;
            self.live_joints = a.joints(rig, &angles);
        }
        Ok(Pose::live(&self.row))
    }
}

/// Joint overrides by node name that [`requested_joints`] resolves back to `joints` (rest
/// holds as the rest values): how a session asks the renderer for the pose its viewers see.
pub fn joint_overrides(rig: &Rig, joints: &JointPose) -> JointOverrides {
    let Some(sk) = &rig.skeleton else {
        return JointOverrides::default();
    };
    JointOverrides(
        joints
            .sets()
            .iter()
            .filter_map(|s| {
                let node = sk.nodes.get(s.node as usize)?;
                let mut t = node.rest;
                s.apply(&node.rest, &mut t);
                let full = s.rest;
                Some((
                    node.name.clone(),
                    JointTransform {
                        translation: (full || s.translation.is_some()).then_some(t.translation),
                        rotation: (full || s.rotation.is_some()).then_some(t.rotation),
                        scale: (full || s.scale.is_some()).then_some(t.scale),
                    },
                ))
            })
            .collect(),
    )
}

/// 400 `invalid_layer` about head `h`.
fn invalid_layer(h: usize, head: &Head, message: String) -> ApiError {
    at_head(h, head, ApiError::bad_request("invalid_layer", message))
}

/// 400 `invalid_blend` about head `h`.
fn invalid_blend(h: usize, head: &Head, message: String) -> ApiError {
    at_head(h, head, ApiError::bad_request("invalid_blend", message))
}

/// 400 `invalid_weights` about head `h`.
fn invalid_weights(h: usize, head: &Head, message: String) -> ApiError {
    at_head(h, head, ApiError::bad_request("invalid_weights", message))
}

/// `e` with its message prefixed by the head it is about.
fn at_head(h: usize, head: &Head, e: ApiError) -> ApiError {
    ApiError {
        message: format!("head {h} (id {}): {}", head.head, e.message),
        ..e
    }
}

/// One unique job for the batcher, with its cost: vertices × (active shapes + 1) at the job's
/// pose and level of detail.
pub fn job_request(entry: &Arc<RigEntry>, pose: &Pose, lod: u32, joints: &JointPose) -> JobRequest {
    let rig = entry.rig();
    let shapes = rig.lod.shapes_at(lod).unwrap_or(0) as usize;
    let active = rig.lod.order[..shapes.min(rig.lod.order.len())]
        .iter()
        .filter(|&&t| pose.weight(rig, t as usize).abs() > ACTIVE_WEIGHT_EPSILON)
        .count() as u64;
    let v = entry.prepared.at_level(lod).rig().vertex_count() as u64;
    // The skin pass after the blend costs about what two shapes do per vertex.
    let skin = if rig.is_skinned() { 2 } else { 0 };
    JobRequest {
        entry: entry.clone(),
        pose: pose.clone(),
        lod,
        joints: joints.clone(),
        cost: v * (active + 1 + skin),
    }
}
