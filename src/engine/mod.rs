//! Blend engines and what they share.
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
mod facade;
pub mod gpu;

pub use facade::{
    BackendChoice, BackendInfo, BackendKind, Begun, Engine, Evaluation, PendingEvaluation,
    PreparedRig, RenderBuffers, RigMemory, Timings,
};

use half::f16;
use serde::{Deserialize, Serialize};

use crate::rig::{ACTIVE_WEIGHT_EPSILON, ClipError, LodError, Rig};

/// One unique job of a rig: which clip, which (resolved) frame, which LOD level.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct BlendJob {
    /// Clip index within the rig.
    pub clip: u32,
    /// Frame within the clip's table (already wrapped or clamped).
    pub frame: u32,
    /// LOD level.
    pub lod: u32,
}

impl BlendJob {
    /// Checks the job against its rig (clip, frame and LOD level exist) and returns how many
    /// shapes its LOD level evaluates.
    pub fn check(&self, rig: &Rig) -> Result<u32, EngineError> {
        let clip = rig
            .clips
            .get(self.clip as usize)
            .ok_or(EngineError::NoSuchClip(self.clip))?;
        if self.frame >= clip.frames {
            return Err(ClipError::FrameOutOfRange {
                clip: clip.name.clone(),
                frame: i64::from(self.frame),
                frames: clip.frames,
            }
            .into());
        }
        Ok(rig.lod.shapes_at(self.lod)?)
    }
}

impl From<&crate::plan::JobKey> for BlendJob {
    /// The engine's view of a planned job (the rig is chosen by the caller).
    fn from(k: &crate::plan::JobKey) -> BlendJob {
        BlendJob {
            clip: k.clip,
            frame: k.frame,
            lod: k.lod,
        }
    }
}

/// Scalar format of output vertex buffers.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Precision {
    /// IEEE binary32.
    #[default]
    F32,
    /// IEEE binary16 (relative error ≤ 2^-11 per component).
    F16,
}

/// What a batch should produce.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct OutputSpec {
    /// Also produce unit normals.
    pub normals: bool,
    /// Scalar format of the buffers.
    pub precision: Precision,
}

/// Why an engine could not evaluate a batch.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum EngineError {
    /// A job names a clip the rig does not have.
    #[error("clip index {0} out of range")]
    NoSuchClip(u32),
    /// A job names a frame outside its clip.
    #[error(transparent)]
    Frame(#[from] ClipError),
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

    /// Gathers the weights of `jobs` from the rig's clip tables.
    pub fn gather(rig: &Rig, jobs: &[BlendJob]) -> Result<WeightBatch, EngineError> {
        let slots = rig.targets.len();
        let mut batch = WeightBatch {
            slots,
            weights: vec![0.0; jobs.len() * slots],
            shapes: Vec::with_capacity(jobs.len()),
        };
        for (j, job) in jobs.iter().enumerate() {
            let shapes = job.check(rig)?;
            let clip = &rig.clips[job.clip as usize];
            let row = &mut batch.weights[j * slots..(j + 1) * slots];
            for (s, &t) in rig.lod.order.iter().enumerate().take(shapes as usize) {
                row[s] = active(clip.weight(t as usize, job.frame));
            }
            batch.shapes.push(shapes);
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

/// Zeroes weights too small to matter, so engines can skip them exactly.
#[inline]
fn active(w: f32) -> f32 {
    if w.abs() > ACTIVE_WEIGHT_EPSILON {
        w
    } else {
        0.0
    }
}

/// A vertex buffer in one of the output precisions.
#[derive(Clone, Debug, PartialEq)]
pub enum VertexData {
    /// binary32 components.
    F32(Vec<f32>),
    /// binary16 components.
    F16(Vec<f16>),
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
        }
    }

    /// Whether the buffer is empty.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The components as f32 (converting from f16 when needed).
    pub fn to_f32(&self) -> Vec<f32> {
        match self {
            VertexData::F32(v) => v.clone(),
            VertexData::F16(v) => v.iter().map(|h| h.to_f32()).collect(),
        }
    }

    /// Little-endian bytes of the buffer, as sent on the wire and written to `.bin` files.
    pub fn as_bytes(&self) -> &[u8] {
        match self {
            VertexData::F32(v) => bytemuck::cast_slice(v),
            VertexData::F16(v) => bytemuck::cast_slice(v),
        }
    }
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
        job_slice(&self.positions, self.vertices, j)
    }

    /// Normals of job `j` as f32, when computed.
    pub fn job_normals(&self, j: usize) -> Option<Vec<f32>> {
        self.normals
            .as_ref()
            .map(|n| job_slice(n, self.vertices, j))
    }
}

fn job_slice(data: &VertexData, vertices: usize, j: usize) -> Vec<f32> {
    let r = j * vertices * 3..(j + 1) * vertices * 3;
    match data {
        VertexData::F32(v) => v[r].to_vec(),
        VertexData::F16(v) => v[r].iter().map(|h| h.to_f32()).collect(),
    }
}
