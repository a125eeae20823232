//! A submitted batch's results: where they go ([`Readout`]), the batch until they are read
//! ([`Pending`]: waiting for it, its GPU time, copying the staging memory into the caller's
//! arrays on every core, [`Readback`]), or the outputs left on the device for a renderer
//! ([`DeviceOutput`]).
//!
//! Invariants: a batch's slot goes back to the pool only after a successful wait, with
//! everything it mapped unmapped; a batch dropped without a wait is waited for and unmapped,
//! so no buffer stays mapped and no work is left uncollected; a mapping is read only after
//! its callback reported (`MapResults::wait`).

use std::sync::Arc;

use super::GpuError;
use super::batch::Region;
use super::context::GpuContext;
use super::map::MapResults;
use super::slot::Slot;
use crate::{BlendOutput, OutputSpec, Precision, Q16Scale, VertexData};
use crowdmorph_core::budget::Charge;

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
    pub(super) slot: Option<Slot>,
    pub(super) submission: wgpu::SubmissionIndex,
    pub(super) regions: Vec<Region>,
    pub(super) jobs: usize,
    pub(super) vertices: usize,
    pub(super) spec: OutputSpec,
    pub(super) readback: bool,
    /// Bytes of the staging buffer this batch mapped.
    pub(super) staged: u64,
    pub(super) mapped: MapResults,
    /// Without readback: the batch's outputs, copied out of the slot so they outlive it.
    pub(super) resident: Option<DeviceOutput>,
    /// Host time spent copying the batch out of mapped memory (set by `finish`).
    pub(super) host_ns: u64,
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
    /// mapped staging memory on every core; returns the GPU time and the host's copy time.
    pub fn wait_into(mut self, out: &mut BlendOutput) -> Result<Readback, GpuError> {
        let result = self.finish(Some(out));
        self.release(result.is_ok());
        let gpu_ns = result?;
        Ok(Readback {
            gpu_ns,
            host_ns: self.host_ns,
        })
    }

    /// Waits for a batch submitted without readback and returns its outputs where they are,
    /// on the device, with the GPU time.
    pub fn wait_resident(mut self) -> Result<(DeviceOutput, Option<u64>), GpuError> {
        let result = self.finish(None);
        self.release(result.is_ok());
        let gpu_ns = result?;
        let out = self
            .resident
            .take()
            .ok_or_else(|| GpuError::Internal("the batch was submitted with readback".into()))?;
        Ok((out, gpu_ns))
    }

    /// Unmaps what this batch mapped and returns its slot to the pool (after a success: a
    /// failed batch's slot may be in any state).
    fn release(&mut self, reuse: bool) {
        if let Some(slot) = self.slot.take() {
            unmap(&slot, self.readback);
            if reuse {
                self.ctx.pool.put(slot);
            }
        }
    }

    /// Waits for the batch; with readback, reads its buffers into `out`. Returns the GPU time.
    fn finish(&mut self, out: Option<&mut BlendOutput>) -> Result<Option<u64>, GpuError> {
        let ctx = self.ctx;
        let expected = usize::from(self.readback)
            + usize::from(self.slot.as_ref().is_some_and(|s| s.queries.is_some()));
        // Waits for the mapping callbacks too, not only the submission: a render or another
        // batch on this device may have collected them on its own thread (see `map`).
        let mapped = self
            .mapped
            .wait(&ctx.device, self.submission.clone(), expected);
        ctx.health()?;
        if let Err(msg) = mapped {
            ctx.health.fail(msg.clone());
            return Err(GpuError::Lost(msg));
        }
        let slot = self
            .slot
            .as_ref()
            .ok_or_else(|| GpuError::Internal("no slot".into()))?;
        let gpu_ns = match (&slot.queries, ctx.timestamp_period) {
            (Some((_, _, read)), Some(period)) => {
                let view = read
                    .get_mapped_range(0..16 * self.regions.len() as u64)
                    .map_err(|e| GpuError::Internal(e.to_string()))?;
                let mut ticks = vec![0u64; 2 * self.regions.len()];
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
        out.vertices = self.vertices;
        out.jobs = self.jobs;
        if !self.readback {
            out.positions = VertexData::default();
            out.normals = None;
            return Ok(gpu_ns);
        }
        let copy_start = std::time::Instant::now();
        let comps = self.jobs * self.vertices * 3;
        let view = slot
            .staging
            .get_mapped_range(0..self.staged)
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
                    self.copy_regions(&mut v, comps, staged, region_of);
                    *into = VertexData::F32(v);
                }
                (Precision::F16, old) => {
                    let mut v = match old {
                        VertexData::F16(v) => v,
                        _ => Vec::new(),
                    };
                    self.copy_regions(&mut v, comps, staged, region_of);
                    *into = VertexData::F16(v);
                }
                (Precision::Q16(b), old) => {
                    let mut v = match old {
                        VertexData::Q16(v, _) => v,
                        _ => Vec::new(),
                    };
                    self.copy_regions(&mut v, comps, staged, region_of);
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
        } else {
            out.normals = None;
        }
        self.host_ns = copy_start.elapsed().as_nanos() as u64;
        Ok(gpu_ns)
    }

    /// Copies each region of `staged` into its jobs' place in `v` (resized to `comps`), in
    /// parts of about a megabyte on every core: at ICT FaceKit's size a batch is hundreds of
    /// megabytes, which one thread copies at a fraction of the bus's rate.
    fn copy_regions<T: bytemuck::Pod + Default + Send>(
        &self,
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
        for r in &self.regions {
            let dst = &mut v[r.job * per_job..(r.job + r.jobs) * per_job];
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
        // A pending batch dropped without `wait` must not leave its buffers mapped or the
        // device with work nobody collects; wait for it and discard the result.
        if self.slot.is_some() {
            let _ = self.ctx.device.poll(wgpu::PollType::Wait {
                submission_index: Some(self.submission.clone()),
                timeout: None,
            });
            if let Some(slot) = self.slot.take() {
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
