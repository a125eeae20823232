//! crowdmorph-engine: blend engines, rendered frames, level of detail and export.
//!
//! | module | what it is |
//! |---|---|
//! | the crate root | what engines share ([`WeightBatch`], [`OutputSpec`], [`VertexData::encode`], [`code_residuals`]) |
//! | `facade` | [`Engine`]: picks the backend, prepares rigs with their mesh and PCA levels, routes and pipelines batches, falls back to the CPU |
//! | [`cpu`] | the CPU engine: the oracle and the no-GPU production engine |
//! | [`gpu`] | the wgpu engine, one file per job (context, rig upload, slots, batch plan, submit, passes, readback: its own map); its WGSL passes are in `shaders/` |
//! | [`export`] | one blended frame written as OBJ or raw f32 (`crowdmorph eval`) |
//! | [`render`] | rendered frames: scene layout, cost, the wgpu renderer, encoding, offline renders |
//! | [`lod`] | level of detail: importance metrics and orders, reports, feature-preserving mesh levels, PCA levels of the deltas, the reference rasterizer |
//!
//! # Blend engines and what they share
//!
//! An engine evaluates Eq. 1 of Costigan et al. 2016, `v = base + Σ_k w_k Δ_k`, for a batch of
//! unique jobs of one rig. The weights of a batch are gathered once into a [`WeightBatch`] in
//! LOD slot order (slot `s` is the `s`-th target of the rig's importance order), with every
//! weight that is past the job's LOD or inactive (|w| ≤ 1e-6, Lorach 2007) set to exactly zero.
//! Engines then visit only slots that are active for some job of the batch.
//!
//! Output is one contiguous buffer per batch in which job `j` owns
//! `[j·V·3, (j+1)·V·3)`: x, y, z per vertex, all primitives concatenated in file order.

pub mod cpu;
pub mod export;
mod facade;
pub mod glb;
pub mod gpu;
pub mod lod;
pub mod render;

pub use facade::{
    BackendChoice, BackendInfo, BackendKind, Begun, Engine, Evaluation, PendingEvaluation,
    PreparedRig, RenderBuffers, RigMemory, Timings,
};

pub use crowdmorph_proto::Quantization;
use half::f16;
use rayon::prelude::*;

use crowdmorph_core::rig::{
    ACTIVE_WEIGHT_EPSILON, JointPose, LodError, Pose, PoseError, Rig, SkinPoses,
};

/// One unique job of a rig: which pose (a clip frame, a blend, live weights) at which LOD
/// level, with the joint overrides a request set (on a skinned rig).
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct BlendJob {
    /// The weights to evaluate.
    pub pose: Pose,
    /// LOD level.
    pub lod: u32,
    /// Nodes whose local transforms a request set, applied after the pose's.
    pub joints: JointPose,
}

impl BlendJob {
    /// A job playing one frame of one clip.
    pub fn frame(clip: u32, frame: u32, lod: u32) -> BlendJob {
        BlendJob {
            pose: Pose::Frame { clip, frame },
            lod,
            joints: JointPose::NONE,
        }
    }

    /// A job evaluating `pose` at `lod`, without joint overrides.
    pub fn posed(pose: Pose, lod: u32) -> BlendJob {
        BlendJob {
            pose,
            lod,
            joints: JointPose::NONE,
        }
    }

    /// Checks the job against its rig (clips, frames, live weights and LOD level exist) and
    /// returns how many shapes its LOD level evaluates.
    pub fn check(&self, rig: &Rig) -> Result<u32, EngineError> {
        self.pose.check(rig)?;
        Ok(rig.lod.shapes_at(self.lod)?)
    }
}

impl From<&crowdmorph_core::plan::JobKey> for BlendJob {
    /// The engine's view of a planned job (the rig is chosen by the caller).
    fn from(k: &crowdmorph_core::plan::JobKey) -> BlendJob {
        BlendJob {
            pose: k.pose.clone(),
            lod: k.lod,
            joints: k.joints.clone(),
        }
    }
}

/// Scalar format of output vertex buffers: what goes on the wire, produced by the engine.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub enum Precision {
    /// IEEE binary32.
    #[default]
    F32,
    /// IEEE binary16, rounded to nearest even (relative error ≤ 2^-11 per component).
    F16,
    /// int16 in a box (proto/README.md, "Formats"): positions as
    /// `round((x - min) / step) - 32768` per axis of the given box, unit normals as
    /// `round(n × 32767)`; both rounded to nearest even and clamped to the int16 range.
    Q16(Quantization),
}

impl Precision {
    /// Bytes of one component.
    pub fn component_bytes(self) -> usize {
        match self {
            Precision::F32 => 4,
            Precision::F16 | Precision::Q16(_) => 2,
        }
    }

    /// Short name for logs and bench output.
    pub fn name(self) -> &'static str {
        match self {
            Precision::F32 => "f32",
            Precision::F16 => "f16",
            Precision::Q16(_) => "q16",
        }
    }
}

/// What a batch should produce.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct OutputSpec {
    /// Also produce unit normals.
    pub normals: bool,
    /// Scalar format of the buffers (positions and normals alike).
    pub precision: Precision,
}

/// Why an engine could not evaluate a batch.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum EngineError {
    /// A job's pose does not fit the rig (clip, frame or live weights).
    #[error(transparent)]
    Pose(#[from] PoseError),
    /// A job names a LOD level the rig does not have.
    #[error(transparent)]
    Lod(#[from] LodError),
    /// The weight batch does not fit the prepared rig.
    #[error("weight batch has {got} slots, rig has {want}")]
    SlotMismatch {
        /// Slots in the batch.
        got: usize,
        /// Slots in the rig.
        want: usize,
    },
    /// A batch carries joint poses for a rig without a skeleton, or none for a rig with one.
    #[error("the batch's joint poses do not fit the rig's skeleton")]
    SkinMismatch,
    /// The output would be larger than the engine allows in one batch.
    #[error("batch output of {0} bytes is too large")]
    TooLarge(usize),
    /// A GPU was asked for and none could be opened.
    #[error("no GPU: {0}")]
    NoGpu(String),
    /// One batch mixes jobs of different mesh levels (their outputs differ in size).
    #[error("a batch must not mix LOD levels that use different meshes")]
    MixedMeshLevels,
    /// A mesh level cannot be derived from the rig.
    #[error("mesh level: {0}")]
    Mesh(String),
    /// The rig does not fit in the device's memory or limits.
    #[error("rig does not fit on the GPU: {0}")]
    DoesNotFit(String),
    /// The GPU memory budget (`--max-gpu-memory`) refused a rig: too large for it ever, or
    /// too large for what the device holds now (the server answers as for its host memory
    /// budget: 413 or 503).
    #[error("rig does not fit the GPU memory budget: {0}")]
    GpuMemory(crowdmorph_core::budget::BudgetError),
    /// Residual coding was asked for outputs it cannot code: not q16, or a reference that is
    /// not one job's components.
    #[error("q16 residuals: {0}")]
    Residuals(String),
}

/// Weights of a batch of jobs, in LOD slot order, zero where inactive or past the LOD.
#[derive(Clone, Debug, PartialEq)]
pub struct WeightBatch {
    /// Number of slots (= rig targets).
    pub slots: usize,
    /// `jobs × slots`, job-major.
    pub weights: Vec<f32>,
    /// Per job, how many slots its LOD level evaluates.
    pub shapes: Vec<u32>,
    /// On a skinned rig, each job's pose for the skin pass (after the blend); `None` else.
    pub skin: Option<SkinPoses>,
}

impl WeightBatch {
    /// Number of jobs.
    pub fn jobs(&self) -> usize {
        self.shapes.len()
    }

    /// The slot weights of job `j`.
    pub fn job(&self, j: usize) -> &[f32] {
        &self.weights[j * self.slots..(j + 1) * self.slots]
    }

    /// Gathers the weights of `jobs` from the rig's clip tables: a blend in weight space,
    /// term by term (`Pose::weight`), as the GPU's `build_active` does.
    pub fn gather(rig: &Rig, jobs: &[BlendJob]) -> Result<WeightBatch, EngineError> {
        let slots = rig.targets.len();
        let mut batch = WeightBatch {
            slots,
            weights: vec![0.0; jobs.len() * slots],
            shapes: Vec::with_capacity(jobs.len()),
            skin: rig.skeleton.as_ref().map(|sk| SkinPoses {
                skeleton: sk.clone(),
                jobs: Vec::with_capacity(jobs.len()),
                overrides: Vec::with_capacity(jobs.len()),
            }),
        };
        for (j, job) in jobs.iter().enumerate() {
            let shapes = job.check(rig)?;
            let row = &mut batch.weights[j * slots..(j + 1) * slots];
            let order = rig.lod.order.iter().enumerate().take(shapes as usize);
            match &job.pose {
                // The common case, kept a plain table read.
                &Pose::Frame { clip, frame } => {
                    let clip = &rig.clips[clip as usize];
                    for (s, &t) in order {
                        row[s] = active(clip.weight(t as usize, frame));
                    }
                }
                pose => {
                    for (s, &t) in order {
                        row[s] = active(pose.weight(rig, t as usize));
                    }
                }
            }
            batch.shapes.push(shapes);
            if let Some(skin) = &mut batch.skin {
                skin.jobs.push(job.pose.skin_terms(rig));
                skin.overrides.push(job.joints.clone());
            }
        }
        Ok(batch)
    }

    /// Builds a batch from per-job weights indexed by target id (not slot), each evaluated at
    /// the given LOD level. Used by benchmarks and LOD reports that synthesise weights.
    pub fn from_target_weights(
        rig: &Rig,
        weights: &[Vec<f32>],
        lod: u32,
    ) -> Result<WeightBatch, EngineError> {
        let slots = rig.targets.len();
        let shapes = rig.lod.shapes_at(lod)?;
        let mut batch = WeightBatch {
            slots,
            weights: vec![0.0; weights.len() * slots],
            shapes: vec![shapes; weights.len()],
            // Synthesised weights name no clip: a skinned rig stands at rest.
            skin: rig.skeleton.as_ref().map(|sk| SkinPoses {
                skeleton: sk.clone(),
                jobs: vec![Vec::new(); weights.len()],
                overrides: vec![JointPose::NONE; weights.len()],
            }),
        };
        for (j, w) in weights.iter().enumerate() {
            let row = &mut batch.weights[j * slots..(j + 1) * slots];
            for (s, &t) in rig.lod.order.iter().enumerate().take(shapes as usize) {
                row[s] = active(w.get(t as usize).copied().unwrap_or(0.0));
            }
        }
        Ok(batch)
    }

    /// Number of (job, slot) pairs with a non-zero weight.
    pub fn active_pairs(&self) -> usize {
        self.weights.iter().filter(|w| **w != 0.0).count()
    }
}

/// Every job's bone matrices on a skinned rig, job-major (`jobs × bones`): what the GPU's
/// `skin` pass reads. The terms are those [`WeightBatch::gather`] gives the CPU's `skin`,
/// resolved by the same [`SkinPoses::bones`], on every core; a rig without a skeleton has
/// none.
pub fn bone_matrices(
    rig: &Rig,
    jobs: &[BlendJob],
) -> Result<Vec<crowdmorph_core::rig::BoneMatrix>, EngineError> {
    let Some(sk) = &rig.skeleton else {
        return Ok(Vec::new());
    };
    let poses = SkinPoses {
        skeleton: sk.clone(),
        jobs: jobs.iter().map(|j| j.pose.skin_terms(rig)).collect(),
        overrides: jobs.iter().map(|j| j.joints.clone()).collect(),
    };
    Ok(resolve_bones(&poses))
}

/// Every job's bone matrices of `poses` (`jobs × bones`, job-major), each job's resolved once
/// ([`SkinPoses::bones`]), on every core.
pub(crate) fn resolve_bones(poses: &SkinPoses) -> Vec<crowdmorph_core::rig::BoneMatrix> {
    let bones = poses.skeleton.bones.len();
    let mut out = vec![crowdmorph_core::rig::BoneMatrix::IDENTITY; poses.jobs.len() * bones];
    if bones > 0 {
        out.par_chunks_mut(bones).enumerate().for_each_init(
            crowdmorph_core::rig::BoneScratch::default,
            |scratch, (j, dst)| {
                poses.bones(j, scratch);
                dst.copy_from_slice(&scratch.bones);
            },
        );
    }
    out
}

/// Zeroes weights too small to matter, so engines can skip them exactly.
#[inline]
fn active(w: f32) -> f32 {
    if w.abs() > ACTIVE_WEIGHT_EPSILON {
        w
    } else {
        0.0
    }
}

/// How the integers of a q16 buffer map back to f32.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Q16Scale {
    /// Positions: `x = min[a] + (q + 32768) × step[a]` for axis `a` of the box.
    Box(Quantization),
    /// Unit normals: `n = q / 32767`.
    Unit,
}

/// A vertex buffer in one of the output precisions: the bytes the wire carries.
#[derive(Clone, Debug, PartialEq)]
pub enum VertexData {
    /// binary32 components.
    F32(Vec<f32>),
    /// binary16 components.
    F16(Vec<f16>),
    /// int16 components and how they map back to f32.
    Q16(Vec<i16>, Q16Scale),
}

impl Default for VertexData {
    fn default() -> Self {
        VertexData::F32(Vec::new())
    }
}

impl VertexData {
    /// Number of scalar components.
    pub fn len(&self) -> usize {
        match self {
            VertexData::F32(v) => v.len(),
            VertexData::F16(v) => v.len(),
            VertexData::Q16(v, _) => v.len(),
        }
    }

    /// Whether the buffer is empty.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The components as f32 (converting from f16, dequantizing q16).
    pub fn to_f32(&self) -> Vec<f32> {
        self.range_f32(0..self.len())
    }

    /// Components `r` as f32.
    fn range_f32(&self, r: std::ops::Range<usize>) -> Vec<f32> {
        match self {
            VertexData::F32(v) => v[r].to_vec(),
            VertexData::F16(v) => v[r].iter().map(|h| h.to_f32()).collect(),
            VertexData::Q16(v, Q16Scale::Unit) => {
                v[r].iter().map(|&q| f32::from(q) / 32767.0).collect()
            }
            // Components start at an x (every range here is whole vertices).
            VertexData::Q16(v, Q16Scale::Box(b)) => b.dequantize(&v[r]),
        }
    }

    /// Little-endian bytes of the buffer, as sent on the wire and written to `.bin` files.
    pub fn as_bytes(&self) -> &[u8] {
        match self {
            VertexData::F32(v) => bytemuck::cast_slice(v),
            VertexData::F16(v) => bytemuck::cast_slice(v),
            VertexData::Q16(v, _) => bytemuck::cast_slice(v),
        }
    }

    /// Bytes the buffer's allocation holds (its capacity, which a reused buffer keeps when a
    /// smaller batch shortens it).
    pub fn capacity_bytes(&self) -> usize {
        match self {
            VertexData::F32(v) => v.capacity() * 4,
            VertexData::F16(v) => v.capacity() * 2,
            VertexData::Q16(v, _) => v.capacity() * 2,
        }
    }

    /// Whether this buffer is of the kind `precision` produces (q16 of any box).
    pub fn is_kind(&self, precision: Precision) -> bool {
        matches!(
            (self, precision),
            (VertexData::F32(_), Precision::F32)
                | (VertexData::F16(_), Precision::F16)
                | (VertexData::Q16(..), Precision::Q16(_))
        )
    }

    /// Encodes f32 components in `precision`, in parallel: positions (`normals == false`) in
    /// the q16 box, unit normals as `q / 32767`. Engines that blend in f32 and cannot encode
    /// in their kernel (the GPU for q16; the CPU when normals are recomputed from the blended
    /// positions) use this; the results are bitwise those of the CPU kernel's output stage.
    pub fn encode(v: &[f32], precision: Precision, normals: bool) -> VertexData {
        const PART: usize = 3 << 14;
        match precision {
            Precision::F32 => VertexData::F32(v.to_vec()),
            Precision::F16 => {
                use half::slice::HalfFloatSliceExt;
                let mut out = vec![f16::ZERO; v.len()];
                out.par_chunks_mut(PART)
                    .zip(v.par_chunks(PART))
                    .for_each(|(o, i)| o.convert_from_f32_slice(i));
                VertexData::F16(out)
            }
            Precision::Q16(b) => {
                let q = Q16Params::new(b, normals);
                let mut out = vec![0i16; v.len()];
                // Parts are whole vertices, so component `i` of a part is axis `i % 3`.
                out.par_chunks_mut(PART)
                    .zip(v.par_chunks(PART))
                    .for_each(|(o, i)| {
                        for (k, (o, &x)) in o.iter_mut().zip(i).enumerate() {
                            *o = q.quantize(x, k % 3);
                        }
                    });
                let scale = if normals {
                    Q16Scale::Unit
                } else {
                    Q16Scale::Box(b)
                };
                VertexData::Q16(out, scale)
            }
        }
    }
}

/// The arithmetic of q16 output, shared by the scalar reference and every kernel family so
/// that they agree bit for bit: `q = round_even(clamp((x - sub[a]) × mul[a], lo, hi)) + add`,
/// all in f32. Positions: `sub = min`, `mul = 1 / step` (rounded to f32), clamp to
/// `[0, 65535]`, `add = -32768`. Normals: `sub = 0`, `mul = 32767`, clamp to
/// `[-32767, 32767]`, `add = 0`.
///
/// In f32 the quantized index can be off the exact `(x - min) / step` by at most
/// `3 × 2^-24 × |x - min|` (three roundings: the difference, `1 / step` and the product), that
/// is at most 3 units in the last place of the largest coordinate of the box; the box's stated
/// `max_error` (the registry's `quantization_box`) includes it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Q16Params {
    /// Subtracted per axis before scaling.
    pub sub: [f32; 3],
    /// Scale per axis.
    pub mul: [f32; 3],
    /// Lower clamp of the scaled value.
    pub lo: f32,
    /// Upper clamp of the scaled value.
    pub hi: f32,
    /// Added to the rounded integer.
    pub add: i32,
}

impl Q16Params {
    /// The parameters for positions in `b` (`normals == false`) or for unit normals.
    pub fn new(b: Quantization, normals: bool) -> Q16Params {
        if normals {
            Q16Params {
                sub: [0.0; 3],
                mul: [32767.0; 3],
                lo: -32767.0,
                hi: 32767.0,
                add: 0,
            }
        } else {
            Q16Params {
                sub: b.min,
                mul: b.step.map(|s| if s > 0.0 { 1.0 / s } else { 0.0 }),
                lo: 0.0,
                hi: 65535.0,
                add: -32768,
            }
        }
    }

    /// Quantizes one component of axis `a` (the scalar reference of the kernels).
    #[inline]
    pub fn quantize(&self, x: f32, a: usize) -> i16 {
        let u = (x - self.sub[a]) * self.mul[a];
        // Written as the vector max/min are defined (NaN goes to `lo`).
        let u = if u > self.lo { u } else { self.lo };
        let u = if u < self.hi { u } else { self.hi };
        (u.round_ties_even() as i32 + self.add) as i16
    }
}

/// The q16 values a batch's positions are coded against as residual planes (wire format
/// `q16r`, `crowdmorph_proto::q16r_encode`): one job's components, the q16 positions of the
/// batch's rig level with every weight 0, in the batch's box. Shared, since the server keeps
/// one per rig level and every batch of that level uses it.
pub type Q16Reference = std::sync::Arc<[i16]>;

/// Codes q16 positions in place as residual planes against `reference`, job by job (each job
/// `reference.len()` components): what the GPU's `pack_q16r` pass writes, done on the host
/// for the CPU engine and for a GPU batch that ran on the CPU.
pub fn code_residuals(positions: &mut VertexData, reference: &[i16]) -> Result<(), EngineError> {
    let v3 = reference.len();
    let VertexData::Q16(q, _) = positions else {
        let kind = match positions {
            VertexData::F32(_) => "f32",
            _ => "f16",
        };
        return Err(EngineError::Residuals(format!(
            "residuals of {kind} positions"
        )));
    };
    if v3 == 0 || q.len() % v3 != 0 {
        return Err(EngineError::Residuals(format!(
            "a reference of {v3} components for {} components of jobs",
            q.len()
        )));
    }
    // On every core, as the blend was: on the compute thread alone the coding took as long as
    // the blend of the whole group and cost a third of q16's heads/s over loopback. Each
    // worker codes a job into its own scratch (the planes interleave, so not in place), kept
    // between batches (a fresh one per job was page faults), then copies the planes over the
    // job's components.
    thread_local! {
        static PLANES: std::cell::RefCell<Vec<u8>> = const { std::cell::RefCell::new(Vec::new()) };
    }
    q.par_chunks_exact_mut(v3).for_each(|job| {
        PLANES.with_borrow_mut(|planes| {
            planes.resize(2 * v3, 0);
            crowdmorph_proto::q16r_encode(job, reference, planes);
            bytemuck::cast_slice_mut::<i16, u8>(job).copy_from_slice(planes);
        });
    });
    Ok(())
}

/// Result of a batch: job `j` owns components `[j·V·3, (j+1)·V·3)` of each buffer.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct BlendOutput {
    /// Vertices per job.
    pub vertices: usize,
    /// Jobs in the batch.
    pub jobs: usize,
    /// Blended positions.
    pub positions: VertexData,
    /// Unit normals, when asked for.
    pub normals: Option<VertexData>,
}

impl BlendOutput {
    /// Positions of job `j` as f32.
    pub fn job_positions(&self, j: usize) -> Vec<f32> {
        self.positions
            .range_f32(j * self.vertices * 3..(j + 1) * self.vertices * 3)
    }

    /// Normals of job `j` as f32, when computed.
    pub fn job_normals(&self, j: usize) -> Option<Vec<f32>> {
        self.normals
            .as_ref()
            .map(|n| n.range_f32(j * self.vertices * 3..(j + 1) * self.vertices * 3))
    }

    /// Re-encodes f32 buffers in `spec`'s precision (a no-op when they already are): for
    /// engines whose kernels produce f32 only in some cases.
    pub fn encode_as(&mut self, spec: OutputSpec) {
        if let VertexData::F32(v) = &self.positions
            && spec.precision != Precision::F32
        {
            self.positions = VertexData::encode(v, spec.precision, false);
        }
        if let Some(n) = &mut self.normals
            && let VertexData::F32(v) = n
            && spec.precision != Precision::F32
        {
            *n = VertexData::encode(v, spec.precision, true);
        }
    }
}
