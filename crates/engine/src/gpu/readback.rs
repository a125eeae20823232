//! A submitted batch's results: where they go ([`Readout`]), the batch until they are read
//! ([`Pending`]: waiting for it piece by piece, its GPU time, copying each piece's staging
//! memory into the caller's arrays on every core, [`Readback`]), or the outputs left on the
//! device for a renderer ([`DeviceOutput`]).
//!
//! A batch too big for one staging buffer (or for the memory budget) is cut into pieces
//! (`batch::plan_pieces`): the first is submitted with the batch, and each later one is
//! submitted (`GpuContext::submit_piece`) before the previous one is copied out, so one
//! piece's readback overlaps the next one's passes, and at most two pieces' slots are alive.
//!
//! Invariants: a piece's slot goes back to the pool only after a successful wait, with
//! everything it mapped unmapped; a batch dropped without a wait is waited for and unmapped,
//! so no buffer stays mapped and no work is left uncollected; a mapping is read only after
//! its callback reported (`MapResults::wait`).

use std::collections::VecDeque;
use std::ops::Range;
use std::sync::Arc;

use super::GpuError;
use super::batch::Region;
use super::context::GpuContext;
use super::layout::GpuJob;
use super::map::MapResults;
use super::rig::GpuRig;
use super::slot::Slot;
use crate::{BlendOutput, OutputSpec, Precision, Q16Scale, VertexData};
use crowdmorph_core::budget::Charge;
use crowdmorph_core::rig::BoneMatrix;

/// Where a batch's results go ([`GpuContext::submit`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Readout<'r> {
    /// They stay on the device, in f32, for a renderer ([`Pending::wait_resident`]).
    Device,
    /// They are read back in the spec's format ([`Pending::wait_into`]).
    Host,
    /// They are read back, the q16 positions coded on the device as residual planes against
    /// this reference (one job's components: `crowdmorph_proto::q16r_encode`'s `reference`);
    /// normals stay q16.
    Residuals(&'r [i16]),
}

/// A submitted batch whose results are not read yet.
pub struct Pending<'a> {
    pub(super) ctx: &'a GpuContext,
    /// Pieces submitted and not read yet, in job order (at most two).
    pub(super) inflight: VecDeque<Piece>,
    /// What the pieces not submitted yet need, when the batch is cut into pieces.
    pub(super) rest: Option<Rest>,
    /// Pieces of the batch.
    pub(super) pieces: usize,
    pub(super) jobs: usize,
    pub(super) vertices: usize,
    pub(super) spec: OutputSpec,
    pub(super) readback: bool,
    /// Without readback: the batch's outputs, copied out of the slots so they outlive them.
    pub(super) resident: Option<DeviceOutput>,
    /// Host time spent copying the batch out of mapped memory (set by `finish`).
    pub(super) host_ns: u64,
}

/// One submitted piece of a batch: its slot until it is read.
pub(super) struct Piece {
    pub(super) slot: Option<Slot>,
    pub(super) submission: wgpu::SubmissionIndex,
    /// Its sub-batches; their `job` counts from the piece's first job.
    pub(super) regions: Vec<Region>,
    /// Its first job in the batch.
    pub(super) first: usize,
    /// Bytes of the staging buffer it mapped.
    pub(super) staged: u64,
    pub(super) mapped: MapResults,
}

/// The inputs of a batch's pieces not submitted yet (copies: the caller's arrays are only
/// borrowed by `submit`).
pub(super) struct Rest {
    pub(super) rig: Arc<GpuRig>,
    pub(super) jobs: Vec<GpuJob>,
    pub(super) live: Vec<f32>,
    pub(super) bones: Vec<BoneMatrix>,
    pub(super) reference: Option<Vec<i16>>,
    pub(super) pieces: VecDeque<Range<usize>>,
}

/// A batch's outputs left on the device (`submit(.., Readout::Device)`): f32 x, y, z per
/// vertex, job `j` from byte `j · vertices · 12`, in buffers usable as vertex buffers. They
/// are the batch's own, not the pooled slot's, so they live as long as a renderer holds them.
#[derive(Clone, Debug)]
pub struct DeviceOutput {
    /// Blended positions.
    pub positions: wgpu::Buffer,
    /// Unit normals, when asked for.
    pub normals: Option<wgpu::Buffer>,
    /// Vertices per job.
    pub vertices: usize,
    /// Jobs.
    pub jobs: usize,
    /// The buffers' bytes in the device's memory budget, given back when the last clone is
    /// dropped.
    pub(super) _charge: Arc<Charge>,
}

impl DeviceOutput {
    /// Byte offset of job `j`'s data in either buffer.
    pub fn offset(&self, j: usize) -> u64 {
        (j * self.vertices * 12) as u64
    }
}

impl Pending<'_> {
    /// Waits for the batch and returns its buffers (empty without readback) and GPU time.
    pub fn wait(self) -> Result<(BlendOutput, Option<u64>), GpuError> {
        let mut out = BlendOutput::default();
        let r = self.wait_into(&mut out)?;
        Ok((out, r.gpu_ns))
    }

    /// Waits for the batch and reads its buffers into `out`, reusing `out`'s arrays (a warm
    /// buffer of the same length is overwritten, not zeroed or reallocated), copied from the
    /// mapped staging memory on every core, piece by piece; returns the GPU time and the
    /// host's copy time.
    pub fn wait_into(mut self, out: &mut BlendOutput) -> Result<Readback, GpuError> {
        let gpu_ns = self.finish(Some(out))?;
        Ok(Readback {
            gpu_ns,
            host_ns: self.host_ns,
            pieces: self.pieces,
        })
    }

    /// Waits for a batch submitted without readback and returns its outputs where they are,
    /// on the device, with the GPU time.
    pub fn wait_resident(mut self) -> Result<(DeviceOutput, Option<u64>), GpuError> {
        let gpu_ns = self.finish(None)?;
        let out = self
            .resident
            .take()
            .ok_or_else(|| GpuError::Internal("the batch was submitted with readback".into()))?;
        Ok((out, gpu_ns))
    }

    /// Pieces the batch is cut into (1 when it fits one staging buffer and the budget).
    pub fn pieces(&self) -> usize {
        self.pieces
    }

    /// Submits the next piece not submitted yet, if any.
    fn submit_next(&mut self) -> Result<(), GpuError> {
        let Some(rest) = &mut self.rest else {
            return Ok(());
        };
        let Some(range) = rest.pieces.pop_front() else {
            return Ok(());
        };
        let piece = self.ctx.submit_piece(
            &rest.rig,
            &rest.jobs,
            &rest.live,
            &rest.bones,
            rest.reference.as_deref(),
            self.spec,
            self.readback,
            range,
            self.resident.as_ref(),
        )?;
        self.inflight.push_back(piece);
        Ok(())
    }

    /// Waits for every piece; with readback, reads its buffers into `out`. Each piece's slot
    /// goes back to the pool after it is read, and the next piece is submitted before a
    /// piece is waited for. Returns the GPU time, summed over the pieces.
    fn finish(&mut self, mut out: Option<&mut BlendOutput>) -> Result<Option<u64>, GpuError> {
        if let Some(out) = out.as_deref_mut() {
            out.vertices = self.vertices;
            out.jobs = self.jobs;
            if !self.readback {
                out.positions = VertexData::default();
                out.normals = None;
            } else if !self.spec.normals {
                out.normals = None;
            }
        }
        let mut gpu_ns: Option<u64> = None;
        while let Some(mut piece) = self.inflight.pop_front() {
            // The next piece computes while this one is waited for and copied out.
            if let Err(e) = self.submit_next() {
                self.inflight.push_front(piece);
                return Err(e);
            }
            let result = self.read_piece(&piece, out.as_deref_mut());
            if let Some(slot) = piece.slot.take() {
                unmap(&slot, self.readback);
                // After a success only: a failed batch's slot may be in any state.
                if result.is_ok() {
                    self.ctx.pool.put(slot);
                }
            }
            if let Some(ns) = result? {
                gpu_ns = Some(gpu_ns.unwrap_or(0) + ns);
            }
        }
        Ok(gpu_ns)
    }

    /// Waits for one piece; with readback, reads its buffers into their jobs' place in `out`.
    /// Returns its GPU time.
    fn read_piece(
        &mut self,
        piece: &Piece,
        out: Option<&mut BlendOutput>,
    ) -> Result<Option<u64>, GpuError> {
        let ctx = self.ctx;
        let slot = piece
            .slot
            .as_ref()
            .ok_or_else(|| GpuError::Internal("no slot".into()))?;
        let expected = usize::from(self.readback) + usize::from(slot.queries.is_some());
        // Waits for the mapping callbacks too, not only the submission: a render or another
        // batch on this device may have collected them on its own thread (see `map`).
        let mapped = piece
            .mapped
            .wait(&ctx.device, piece.submission.clone(), expected);
        ctx.health()?;
        if let Err(msg) = mapped {
            ctx.health.fail(msg.clone());
            return Err(GpuError::Lost(msg));
        }
        let gpu_ns = match (&slot.queries, ctx.timestamp_period) {
            (Some((_, _, read)), Some(period)) => {
                let view = read
                    .get_mapped_range(0..16 * piece.regions.len() as u64)
                    .map_err(|e| GpuError::Internal(e.to_string()))?;
                let mut ticks = vec![0u64; 2 * piece.regions.len()];
                bytemuck::cast_slice_mut::<u64, u8>(&mut ticks).copy_from_slice(&view);
                let total: u64 = ticks
                    .chunks_exact(2)
                    .map(|t| t[1].saturating_sub(t[0]))
                    .sum();
                Some((total as f64 * f64::from(period)) as u64)
            }
            _ => None,
        };
        let Some(out) = out else {
            return Ok(gpu_ns);
        };
        if !self.readback {
            return Ok(gpu_ns);
        }
        let copy_start = std::time::Instant::now();
        let comps = self.jobs * self.vertices * 3;
        let view = slot
            .staging
            .get_mapped_range(0..piece.staged)
            .map_err(|e| GpuError::Internal(e.to_string()))?;
        let staged: &[u8] = &view;
        let read = |into: &mut VertexData, region_of: &dyn Fn(&Region) -> u64, normals: bool| {
            // The device wrote the wire format: f32, or 16-bit values packed by `pack_f16` /
            // `pack_q16`.
            // A warm array of the same kind is taken out of `into`, overwritten, put back.
            match (self.spec.precision, std::mem::take(into)) {
                (Precision::F32, old) => {
                    let mut v = match old {
                        VertexData::F32(v) => v,
                        _ => Vec::new(),
                    };
                    self.copy_regions(piece, &mut v, comps, staged, region_of);
                    *into = VertexData::F32(v);
                }
                (Precision::F16, old) => {
                    let mut v = match old {
                        VertexData::F16(v) => v,
                        _ => Vec::new(),
                    };
                    self.copy_regions(piece, &mut v, comps, staged, region_of);
                    *into = VertexData::F16(v);
                }
                (Precision::Q16(b), old) => {
                    let mut v = match old {
                        VertexData::Q16(v, _) => v,
                        _ => Vec::new(),
                    };
                    self.copy_regions(piece, &mut v, comps, staged, region_of);
                    let scale = if normals {
                        Q16Scale::Unit
                    } else {
                        Q16Scale::Box(b)
                    };
                    *into = VertexData::Q16(v, scale);
                }
            }
        };
        read(&mut out.positions, &|r| r.positions, false);
        if self.spec.normals {
            let mut n = out.normals.take().unwrap_or_default();
            read(&mut n, &|r| r.normals, true);
            out.normals = Some(n);
        }
        drop(view);
        self.host_ns += copy_start.elapsed().as_nanos() as u64;
        Ok(gpu_ns)
    }

    /// Copies each region of `piece`'s `staged` memory into its jobs' place in `v` (resized
    /// to `comps`, the whole batch's, by the first piece), in parts of about a megabyte on
    /// every core: at ICT FaceKit's size a batch is hundreds of megabytes, which one thread
    /// copies at a fraction of the bus's rate.
    fn copy_regions<T: bytemuck::Pod + Default + Send>(
        &self,
        piece: &Piece,
        v: &mut Vec<T>,
        comps: usize,
        staged: &[u8],
        region_of: &dyn Fn(&Region) -> u64,
    ) {
        use rayon::prelude::*;
        const PART: usize = 1 << 20;
        if v.len() != comps {
            v.resize(comps, T::default());
        }
        let per_job = self.vertices * 3;
        let size = size_of::<T>();
        let part = (PART / size).max(1);
        for r in &piece.regions {
            let job = piece.first + r.job;
            let dst = &mut v[job * per_job..(job + r.jobs) * per_job];
            let at = region_of(r) as usize;
            let src = &staged[at..at + size_of_val(dst)];
            dst.par_chunks_mut(part)
                .zip(src.par_chunks(part * size))
                .for_each(|(d, s)| bytemuck::cast_slice_mut::<T, u8>(d).copy_from_slice(s));
        }
    }
}

impl Drop for Pending<'_> {
    fn drop(&mut self) {
        // A pending batch dropped without `wait` (or after a failed one) must not leave its
        // buffers mapped or the device with work nobody collects; wait for its pieces and
        // discard the results. Pieces not submitted yet are not.
        for mut piece in self.inflight.drain(..) {
            let _ = self.ctx.device.poll(wgpu::PollType::Wait {
                submission_index: Some(piece.submission.clone()),
                timeout: None,
            });
            if let Some(slot) = piece.slot.take() {
                unmap(&slot, self.readback);
            }
        }
    }
}

/// What [`Pending::wait_into`] measured.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Readback {
    /// GPU time of the batch's passes, from timestamp queries.
    pub gpu_ns: Option<u64>,
    /// Host time copying the batch out of mapped staging memory into the caller's arrays.
    pub host_ns: u64,
    /// Pieces the batch was staged and read back in (1 when it fit one staging buffer and
    /// the memory budget).
    pub pieces: usize,
}

/// Unmaps the buffers a batch mapped: the staging buffer only when it read back (unmapping a
/// buffer that was never mapped is a validation error, which would fail the device), and the
/// timestamp readback.
fn unmap(slot: &Slot, readback: bool) {
    if readback {
        slot.staging.unmap();
    }
    if let Some((_, _, read)) = &slot.queries {
        read.unmap();
    }
}
