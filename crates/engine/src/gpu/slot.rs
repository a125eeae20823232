//! A batch's buffers on the device ([`Slot`]), what a batch needs of one ([`SlotNeeds`]), and
//! the pool that keeps idle slots for the next batches ([`SlotPool`]).
//!
//! Invariants: a slot's buffers are charged to the device's memory budget before they are
//! made, and the charge lives as long as the slot; a slot goes back to the pool only after its
//! batch succeeded (a failed batch's slot may be in any state); a batch that no pooled slot
//! fits replaces them all with one that serves it and everything they served.

use std::sync::Mutex;

use super::GpuError;
use super::device::{buffer, padded};
use super::layout::JOBS_PER_GROUP;
use crowdmorph_core::budget::{BudgetError, Charge};

/// Per-batch buffers, pooled so consecutive batches reuse them and overlap.
pub(super) struct Slot {
    pub(super) jobs: wgpu::Buffer,
    pub(super) active_weights: wgpu::Buffer,
    pub(super) active_slots: wgpu::Buffer,
    pub(super) active_count: wgpu::Buffer,
    pub(super) positions: wgpu::Buffer,
    pub(super) normals: wgpu::Buffer,
    pub(super) faces: wgpu::Buffer,
    pub(super) packed_positions: wgpu::Buffer,
    pub(super) packed_normals: wgpu::Buffer,
    pub(super) staging: wgpu::Buffer,
    /// A skinned rig's bone matrices, every sub-batch's at its own aligned offset.
    pub(super) bones: wgpu::Buffer,
    pub(super) queries: Option<(wgpu::QuerySet, wgpu::Buffer, wgpu::Buffer)>,
    /// Its buffers' bytes in the device's memory budget.
    _charge: Charge,
}

/// Sizes a batch needs from a slot.
#[derive(Clone, Copy, PartialEq, Eq)]
pub(super) struct SlotNeeds {
    pub(super) jobs: u64,
    pub(super) active: u64,
    pub(super) output: u64,
    /// Normals output (4 bytes when the batch has none).
    pub(super) normals: u64,
    /// f16 output of positions, and of normals (4 bytes when unused).
    pub(super) packed: u64,
    pub(super) packed_normals: u64,
    pub(super) faces: u64,
    pub(super) staging: u64,
    pub(super) bones: u64,
    pub(super) queries: u32,
}

impl SlotNeeds {
    /// Element-wise maximum: a slot that serves both.
    fn max(self, o: SlotNeeds) -> SlotNeeds {
        SlotNeeds {
            jobs: self.jobs.max(o.jobs),
            active: self.active.max(o.active),
            output: self.output.max(o.output),
            normals: self.normals.max(o.normals),
            packed: self.packed.max(o.packed),
            packed_normals: self.packed_normals.max(o.packed_normals),
            faces: self.faces.max(o.faces),
            staging: self.staging.max(o.staging),
            bones: self.bones.max(o.bones),
            queries: self.queries.max(o.queries),
        }
    }
}

impl SlotNeeds {
    /// Bytes a slot serving these needs allocates (and charges), with timestamp queries where
    /// the device has them: what `Slot::new` charges, so that a batch is cut into pieces whose
    /// slots fit the memory budget before any is made.
    pub(super) fn bytes(&self, timestamps: bool) -> u64 {
        let n = self;
        let query_bytes = if timestamps {
            2 * padded(u64::from(n.queries.max(2)) * 8)
        } else {
            0
        };
        [
            n.jobs,
            n.active * JOBS_PER_GROUP as u64,
            n.active,
            n.active,
            n.output,
            n.normals,
            n.faces,
            n.packed,
            n.packed_normals,
            n.staging,
            n.bones,
        ]
        .into_iter()
        .map(padded)
        .sum::<u64>()
            + query_bytes
    }
}

impl Slot {
    /// A slot serving `n` on `device` (with timestamp queries where it has them), its bytes
    /// charged through `charge` before any buffer is made.
    pub(super) fn new(
        device: &wgpu::Device,
        timestamps: bool,
        n: SlotNeeds,
        charge: impl FnOnce(u64, &dyn Fn() -> String) -> Result<Charge, BudgetError>,
    ) -> Result<Slot, GpuError> {
        use wgpu::BufferUsages as U;
        let storage = U::STORAGE | U::COPY_SRC | U::COPY_DST;
        let bytes = n.bytes(timestamps);
        let charge = charge(bytes, &|| {
            format!(
                "a batch's buffers ({} bytes of output, {} of readback) on the GPU",
                n.output, n.staging
            )
        })?;
        let queries = timestamps.then(|| {
            let count = n.queries.max(2);
            (
                device.create_query_set(&wgpu::QuerySetDescriptor {
                    label: Some("batch timestamps"),
                    ty: wgpu::QueryType::Timestamp,
                    count,
                }),
                buffer(
                    device,
                    "timestamps",
                    u64::from(count) * 8,
                    U::QUERY_RESOLVE | U::COPY_SRC,
                ),
                buffer(
                    device,
                    "timestamps readback",
                    u64::from(count) * 8,
                    U::MAP_READ | U::COPY_DST,
                ),
            )
        });
        Ok(Slot {
            jobs: buffer(device, "jobs", n.jobs, storage),
            active_weights: buffer(
                device,
                "active weights",
                n.active * JOBS_PER_GROUP as u64,
                storage,
            ),
            active_slots: buffer(device, "active slots", n.active, storage),
            active_count: buffer(device, "active count", n.active, storage),
            positions: buffer(device, "positions", n.output, storage),
            normals: buffer(device, "normals", n.normals, storage),
            faces: buffer(device, "faces", n.faces, storage),
            packed_positions: buffer(device, "packed positions", n.packed, storage),
            packed_normals: buffer(device, "packed normals", n.packed_normals, storage),
            staging: buffer(device, "staging", n.staging, U::MAP_READ | U::COPY_DST),
            bones: buffer(device, "bones", n.bones, storage),
            queries,
            _charge: charge,
        })
    }

    /// What this slot can serve.
    pub(super) fn capacity(&self) -> SlotNeeds {
        SlotNeeds {
            jobs: self.jobs.size(),
            active: self.active_slots.size(),
            output: self.positions.size(),
            normals: self.normals.size(),
            packed: self.packed_positions.size(),
            packed_normals: self.packed_normals.size(),
            faces: self.faces.size(),
            staging: self.staging.size(),
            bones: self.bones.size(),
            queries: self.queries.as_ref().map_or(0, |q| q.0.count()),
        }
    }

    /// Bytes it holds in the memory budget.
    fn bytes(&self) -> u64 {
        self._charge.bytes()
    }

    fn fits(&self, n: SlotNeeds) -> bool {
        let c = self.capacity();
        c.max(n) == c
    }
}

/// The idle slots of a context, reused by the batches that fit them.
#[derive(Default)]
pub(super) struct SlotPool(Mutex<Vec<Slot>>);

impl SlotPool {
    /// A pooled slot that serves `needs`, or else one made by `make`, which holds the pool
    /// while it makes it (so a reclaim it triggers does not wait for the pool).
    pub(super) fn take(
        &self,
        needs: SlotNeeds,
        make: impl FnOnce(SlotNeeds) -> Result<Slot, GpuError>,
    ) -> Result<Slot, GpuError> {
        let mut pool = self
            .0
            .lock()
            .map_err(|_| GpuError::Internal("slot pool poisoned".into()))?;
        match pool.iter().position(|s| s.fits(needs)) {
            Some(i) => Ok(pool.swap_remove(i)),
            None => {
                // No pooled slot is big enough: replace them all with one that serves
                // this batch and everything they served, so that alternating batch
                // shapes (with and without normals, f16 and f32) do not reallocate.
                // The old slots are dropped (and their memory given back) first.
                let merged = pool.drain(..).fold(needs, |acc, s| acc.max(s.capacity()));
                make(merged)
            }
        }
    }

    /// Returns a slot whose batch is done, for the next batch to reuse.
    pub(super) fn put(&self, slot: Slot) {
        if let Ok(mut pool) = self.0.lock() {
            pool.push(slot);
        }
    }

    /// Bytes the idle slots hold in the memory budget (0 while another thread holds the pool:
    /// then they are not idle for long). A batch counts them as room, since a charge that finds
    /// the budget full frees them first.
    pub(super) fn idle_bytes(&self) -> u64 {
        match self.0.try_lock() {
            Ok(pool) => pool.iter().map(Slot::bytes).sum(),
            Err(_) => 0,
        }
    }

    /// Drops the pooled batch slots, giving their memory back; whether there were any. A
    /// thread that holds the pool (choosing or building a slot) is not waited for.
    pub(super) fn free_idle(&self) -> bool {
        let idle = match self.0.try_lock() {
            Ok(mut pool) => std::mem::take(&mut *pool),
            Err(_) => return false,
        };
        !idle.is_empty()
    }
}
