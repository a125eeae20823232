//! [`GpuContext::submit`]: a batch of one rig on the device. It checks the batch, cuts it
//! (`batch`), takes a slot that serves it, uploads its job records, live weights, residual
//! reference and bone matrices, records every sub-batch's passes (`passes`) and the copies of
//! its outputs, submits, and asks for the mappings its [`Pending`] will read.
//!
//! Invariants: nothing is recorded for a batch that does not fit (the largest buffer, one
//! binding per sub-batch); an out-of-memory error while the slot and outputs are made is
//! reported as such, and a validation error while recording fails the device (it is a bug).

use std::sync::Arc;

use super::GpuError;
use super::batch::{BatchCounts, BatchPlan, plan_batch, slot_needs};
use super::context::GpuContext;
use super::device::padded;
use super::layout::GpuJob;
use super::map::MapResults;
use super::readback::{DeviceOutput, Pending, Readout};
use super::rig::GpuRig;
use crate::{OutputSpec, Precision};
use crowdmorph_core::rig::BoneMatrix;

impl GpuContext {
    /// Records and submits a batch of jobs of one rig (records from [`GpuRig::job`], with the
    /// live weights it gathered and, on a skinned rig, [`GpuRig::bones`] bone matrices per
    /// job). Read back ([`Readout::Host`], [`Readout::Residuals`]), results are copied to
    /// staging memory for [`Pending::wait`]; left on the device ([`Readout::Device`]) they are
    /// for a renderer and `wait` returns only the timing.
    pub fn submit<'a>(
        &'a self,
        rig: &GpuRig,
        jobs: &[GpuJob],
        live: &[f32],
        bones: &[BoneMatrix],
        spec: OutputSpec,
        readout: Readout<'_>,
    ) -> Result<Pending<'a>, GpuError> {
        self.health()?;
        let v = rig.vertices as u64;
        let n = jobs.len();
        let readback = readout != Readout::Device;
        let reference = match readout {
            Readout::Residuals(r) => {
                if !matches!(spec.precision, Precision::Q16(_)) || r.len() as u64 != 3 * v {
                    return Err(GpuError::Internal(format!(
                        "residuals of {} positions against a reference of {} components for \
                         {} per job",
                        spec.precision.name(),
                        r.len(),
                        3 * v
                    )));
                }
                Some(r)
            }
            _ => None,
        };
        let per_job_bones = rig.bones();
        if bones.len() != n * per_job_bones {
            return Err(GpuError::Internal(format!(
                "{} bone matrices for {n} jobs of a rig with {per_job_bones} bones",
                bones.len()
            )));
        }
        let bone_bytes = (per_job_bones * size_of::<BoneMatrix>()) as u64;
        let recompute = spec.normals && rig.topology.is_some();
        // 16-bit formats are packed on the device: half the bytes are copied and read back.
        let packed16 = matches!(spec.precision, Precision::F16 | Precision::Q16(_));
        let per_job_out = v * 12;
        let tris = rig
            .topology
            .as_ref()
            .map_or(0, |t| u64::from(t.n_triangles));
        let counts = BatchCounts {
            jobs: n,
            vertices: v,
            slots: rig.slots,
            triangles: if recompute { tris } else { 0 },
            bone_bytes,
            live: live.len(),
            reference: reference.map(<[i16]>::len),
            normals: spec.normals,
            packed16,
        };
        let plan = plan_batch(
            &counts,
            self.max_binding,
            u64::from(self.device.limits().min_storage_buffer_offset_alignment),
        );
        let needs = slot_needs(
            &counts,
            &plan,
            rig.blend_packs(spec),
            readback,
            self.timestamp_period.is_some(),
        );
        let BatchPlan {
            regions,
            live_at,
            reference_at,
            staging,
            bones_at,
            ..
        } = plan;
        let subs = regions.len();
        let elem = if packed16 { 2 } else { 4 };
        if bones_at > self.max_buffer {
            return Err(GpuError::DoesNotFit(format!(
                "a batch's bone matrices ({bones_at} bytes) exceed the device's largest buffer"
            )));
        }
        if staging > self.max_buffer {
            return Err(GpuError::DoesNotFit(format!(
                "batch output of {staging} bytes exceeds the device's largest buffer"
            )));
        }
        // Slot buffers are the big allocations of a batch: an out-of-memory error here is
        // reported as such (the engine then falls back to the CPU), not as a bug.
        let oom = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let slot = self.slot(needs)?;
        // Without readback the outputs are copied into buffers of their own (f32 only: they
        // are for drawing), since each sub-batch reuses the slot's output buffers.
        let resident = if readback {
            None
        } else {
            if packed16 {
                return Err(GpuError::Internal(
                    "device-resident outputs are f32 (they are drawn as vertex buffers)".into(),
                ));
            }
            let bytes = n as u64 * per_job_out;
            if bytes > self.max_buffer {
                return Err(GpuError::DoesNotFit(format!(
                    "batch output of {bytes} bytes exceeds the device's largest buffer"
                )));
            }
            use wgpu::BufferUsages as U;
            let usage = U::VERTEX | U::STORAGE | U::COPY_DST | U::COPY_SRC;
            let charge = self.charge(padded(bytes) * (1 + u64::from(spec.normals)), || {
                format!("{n} jobs' outputs kept on the GPU for drawing")
            })?;
            Some(DeviceOutput {
                _charge: Arc::new(charge),
                positions: self.buffer("resident positions", bytes, usage),
                normals: spec
                    .normals
                    .then(|| self.buffer("resident normals", bytes, usage)),
                vertices: v as usize,
                jobs: n,
            })
        };
        if let Some(e) = pollster::block_on(oom.pop()) {
            return Err(GpuError::OutOfMemory(e.to_string()));
        }
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        self.queue
            .write_buffer(&slot.jobs, 0, bytemuck::cast_slice(jobs));
        if !live.is_empty() {
            self.queue
                .write_buffer(&slot.jobs, live_at, bytemuck::cast_slice(live));
        }
        if let Some(r) = reference {
            // Writes are whole words: an odd count gets a padding value.
            if r.len() % 2 == 0 {
                self.queue
                    .write_buffer(&slot.jobs, reference_at, bytemuck::cast_slice(r));
            } else {
                let mut padded = Vec::with_capacity(r.len() + 1);
                padded.extend_from_slice(r);
                padded.push(0i16);
                self.queue
                    .write_buffer(&slot.jobs, reference_at, bytemuck::cast_slice(&padded));
            }
        }
        if per_job_bones > 0 {
            for r in &regions {
                let matrices = &bones[r.job * per_job_bones..(r.job + r.jobs) * per_job_bones];
                self.queue
                    .write_buffer(&slot.bones, r.bones.0, bytemuck::cast_slice(matrices));
            }
        }
        let mut encoder = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("batch"),
            });
        for (k, r) in regions.iter().enumerate() {
            self.record(&mut encoder, rig, &slot, r, spec, k as u32);
            if readback {
                let bytes = (r.jobs as u64 * v * 3 * elem).next_multiple_of(4);
                let (pos_src, nrm_src) = if packed16 {
                    (&slot.packed_positions, &slot.packed_normals)
                } else {
                    (&slot.positions, &slot.normals)
                };
                encoder.copy_buffer_to_buffer(pos_src, 0, &slot.staging, r.positions, bytes);
                if spec.normals {
                    encoder.copy_buffer_to_buffer(nrm_src, 0, &slot.staging, r.normals, bytes);
                }
            }
            if let Some(out) = &resident {
                let bytes = r.jobs as u64 * per_job_out;
                let at = r.job as u64 * per_job_out;
                encoder.copy_buffer_to_buffer(&slot.positions, 0, &out.positions, at, bytes);
                if let Some(n) = &out.normals {
                    encoder.copy_buffer_to_buffer(&slot.normals, 0, n, at, bytes);
                }
            }
        }
        if let Some((qs, resolve, read)) = &slot.queries {
            let count = 2 * subs as u32;
            encoder.resolve_query_set(qs, 0..count, resolve, 0);
            encoder.copy_buffer_to_buffer(resolve, 0, read, 0, u64::from(count) * 8);
        }
        let submission = self.queue.submit([encoder.finish()]);
        if let Some(e) = pollster::block_on(scope.pop()) {
            self.health.fail(e.to_string());
            return Err(GpuError::Internal(e.to_string()));
        }
        let mapped = MapResults::new();
        if readback {
            mapped.request(&slot.staging, 0..staging.max(4));
        }
        if let Some((_, _, read)) = &slot.queries {
            mapped.request(read, 0..16 * subs as u64);
        }
        Ok(Pending {
            ctx: self,
            slot: Some(slot),
            submission,
            regions,
            jobs: n,
            vertices: v as usize,
            spec,
            readback,
            staged: staging.max(4),
            mapped,
            resident,
            host_ns: 0,
        })
    }
}
