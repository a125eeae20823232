//! [`GpuContext::submit`]: a batch of one rig on the device. It checks the batch, cuts it into
//! pieces that each fit one staging buffer and the memory budget (`batch::plan_pieces`), and
//! submits the first ([`GpuContext::submit_piece`]; [`Pending`] submits the others as it
//! reads). A piece is cut into sub-batches (`batch::plan_batch`); it takes a slot that serves
//! it, uploads its job records, the live weights, the residual reference and its bone
//! matrices, records every sub-batch's passes (`passes`) and the copies of its outputs,
//! submits, and asks for the mappings its [`Piece`] will read.
//!
//! Invariants: nothing is recorded for a batch that does not fit (one job's output or bone
//! matrices over the largest buffer, outputs kept on the device over one buffer); an
//! out-of-memory error while a slot or the outputs are made is reported as such, and a
//! validation error while recording fails the device (it is a bug). A piece's results are the
//! bytes the whole batch would have had: each job is computed alone, whatever its piece.

use std::collections::VecDeque;
use std::ops::Range;
use std::sync::Arc;

use super::GpuError;
use super::batch::{BatchCounts, BatchPlan, PieceLimits, plan_batch, plan_pieces, slot_needs};
use super::context::GpuContext;
use super::device::padded;
use super::layout::GpuJob;
use super::map::MapResults;
use super::readback::{DeviceOutput, Pending, Piece, Readout, Rest};
use super::rig::GpuRig;
use crate::{OutputSpec, Precision};
use crowdmorph_core::rig::BoneMatrix;

impl GpuContext {
    /// Records and submits a batch of jobs of one rig (records from [`GpuRig::job`], with the
    /// live weights it gathered and, on a skinned rig, [`GpuRig::bones`] bone matrices per
    /// job). Read back ([`Readout::Host`], [`Readout::Residuals`]), results are copied to
    /// staging memory for [`Pending::wait`]; left on the device ([`Readout::Device`]) they are
    /// for a renderer and `wait` returns only the timing. A batch bigger than one staging
    /// buffer, or than the memory budget has room for, runs in pieces ([`Pending::pieces`]).
    pub fn submit<'a>(
        &'a self,
        rig: &Arc<GpuRig>,
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
        let packed16 = matches!(spec.precision, Precision::F16 | Precision::Q16(_));
        if !readback && packed16 {
            return Err(GpuError::Internal(
                "device-resident outputs are f32 (they are drawn as vertex buffers)".into(),
            ));
        }
        let counts = self.counts(rig, n, live.len(), reference.map(<[i16]>::len), spec);
        let limits = PieceLimits {
            max_binding: self.max_binding,
            align: u64::from(self.device.limits().min_storage_buffer_offset_alignment),
            max_buffer: self.max_piece,
            room: Some(self.room()),
            fused: rig.blend_packs(spec),
            readback,
            timestamps: self.timestamp_period.is_some(),
        };
        let Some(pieces) = plan_pieces(&counts, &limits) else {
            return Err(GpuError::DoesNotFit(format!(
                "one job's output ({} bytes) or bone matrices ({} bytes) exceed the device's \
                 largest buffer ({} bytes)",
                v * 12 * (1 + u64::from(spec.normals)),
                counts.bone_bytes,
                self.max_piece
            )));
        };
        // Without readback the outputs are copied into buffers of their own (f32 only: they
        // are for drawing), since each sub-batch reuses the slot's output buffers. They are
        // one buffer each (a renderer binds them whole): more than the largest buffer is
        // refused, whatever the pieces.
        let resident = if readback {
            None
        } else {
            let bytes = n as u64 * v * 12;
            if bytes > self.max_buffer {
                return Err(GpuError::DoesNotFit(format!(
                    "batch output of {bytes} bytes kept on the device exceeds the device's \
                     largest buffer ({} bytes)",
                    self.max_buffer
                )));
            }
            use wgpu::BufferUsages as U;
            let usage = U::VERTEX | U::STORAGE | U::COPY_DST | U::COPY_SRC;
            let charge = self.charge(padded(bytes) * (1 + u64::from(spec.normals)), || {
                format!("{n} jobs' outputs kept on the GPU for drawing")
            })?;
            let oom = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
            let out = DeviceOutput {
                _charge: Arc::new(charge),
                positions: self.buffer("resident positions", bytes, usage),
                normals: spec
                    .normals
                    .then(|| self.buffer("resident normals", bytes, usage)),
                vertices: v as usize,
                jobs: n,
            };
            if let Some(e) = pollster::block_on(oom.pop()) {
                return Err(GpuError::OutOfMemory(e.to_string()));
            }
            Some(out)
        };
        let mut pieces: VecDeque<Range<usize>> = pieces.into();
        let count = pieces.len();
        let first = pieces.pop_front().unwrap_or(0..0);
        let piece = self.submit_piece(
            rig,
            jobs,
            live,
            bones,
            reference,
            spec,
            readback,
            first,
            resident.as_ref(),
        )?;
        // The later pieces are submitted as the earlier ones are read: they need copies of
        // the inputs the caller only lends.
        let rest = (!pieces.is_empty()).then(|| Rest {
            rig: rig.clone(),
            jobs: jobs.to_vec(),
            live: live.to_vec(),
            bones: bones.to_vec(),
            reference: reference.map(<[i16]>::to_vec),
            pieces,
        });
        Ok(Pending {
            ctx: self,
            inflight: VecDeque::from([piece]),
            rest,
            pieces: count,
            jobs: n,
            vertices: v as usize,
            spec,
            readback,
            resident,
            host_ns: 0,
        })
    }

    /// What decides how `jobs` jobs of `rig` are cut ([`BatchCounts`]).
    fn counts(
        &self,
        rig: &GpuRig,
        jobs: usize,
        live: usize,
        reference: Option<usize>,
        spec: OutputSpec,
    ) -> BatchCounts {
        let recompute = spec.normals && rig.topology.is_some();
        let tris = rig
            .topology
            .as_ref()
            .map_or(0, |t| u64::from(t.n_triangles));
        BatchCounts {
            jobs,
            vertices: rig.vertices as u64,
            slots: rig.slots,
            triangles: if recompute { tris } else { 0 },
            bone_bytes: (rig.bones() * size_of::<BoneMatrix>()) as u64,
            live,
            reference,
            // 16-bit formats are packed on the device: half the bytes are copied and read
            // back.
            normals: spec.normals,
            packed16: matches!(spec.precision, Precision::F16 | Precision::Q16(_)),
        }
    }

    /// Records and submits the piece `range` of a batch ([`GpuContext::submit`]'s inputs,
    /// checked there): its slot, uploads, passes and copies, to staging memory or into
    /// `resident` at its jobs' offsets.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn submit_piece(
        &self,
        rig: &GpuRig,
        jobs: &[GpuJob],
        live: &[f32],
        bones: &[BoneMatrix],
        reference: Option<&[i16]>,
        spec: OutputSpec,
        readback: bool,
        range: Range<usize>,
        resident: Option<&DeviceOutput>,
    ) -> Result<Piece, GpuError> {
        self.health()?;
        let v = rig.vertices as u64;
        let per_job_bones = rig.bones();
        let first = range.start;
        let bones = &bones[range.start * per_job_bones..range.end * per_job_bones];
        let jobs = &jobs[range];
        let counts = self.counts(
            rig,
            jobs.len(),
            live.len(),
            reference.map(<[i16]>::len),
            spec,
        );
        let packed16 = counts.packed16;
        let per_job_out = v * 12;
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
            ..
        } = plan;
        let subs = regions.len();
        let elem = if packed16 { 2 } else { 4 };
        // Slot buffers are the big allocations of a batch: an out-of-memory error here is
        // reported as such (the engine then falls back to the CPU), not as a bug.
        let oom = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let slot = self.slot(needs);
        if let Some(e) = pollster::block_on(oom.pop()) {
            return Err(GpuError::OutOfMemory(e.to_string()));
        }
        let slot = slot?;
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
            if let Some(out) = resident {
                let bytes = r.jobs as u64 * per_job_out;
                let at = (first + r.job) as u64 * per_job_out;
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
        Ok(Piece {
            slot: Some(slot),
            submission,
            regions,
            first,
            staged: staging.max(4),
            mapped,
        })
    }
}
