//! The GPU engine (wgpu): rigs and their whole animation resident on the device, one compute
//! dispatch per pass per batch.
//!
//! Costigan et al. 2016 keep the blendshapes and the animation texture on the GPU so that a
//! frame costs only a tiny upload; here a rig's tiles of delta blocks, neutral mesh, LOD order
//! and every clip's weight table are uploaded once ([`GpuRig::upload`]), and a batch uploads
//! only its job list (16 bytes per unique job). Passes per batch, each a WGSL file in
//! `crates/engine/shaders/` mirrored by a CPU function of the same name:
//!
//! 1. `build_active` — per group of eight jobs, Lorach's list of active slots and weights, read
//!    from the resident clip tables (built on the GPU: the tables already live there, so
//!    building it on the CPU would mean keeping a second copy of every clip host-side per batch
//!    and uploading `slots × jobs` weights instead of one small record per job);
//! 2. `blend` — per (group of 8 jobs, tile of 64 vertices), Eq. 1 over the active list;
//! 3. `face_normals` + `vertex_normals` — normals recomputed from blended (and skinned)
//!    positions where the rig has no normal deltas (or `blend` again on normal deltas where it
//!    has them, run before `skin`);
//! 4. `skin` — on a skinned rig, after the blend (glTF's order): each vertex by its bones'
//!    matrices in its job's pose, resolved on the host once per unique job and uploaded with
//!    the batch (96 bytes a bone);
//! 5. `pack_f16` or `pack_q16` — binary16 or int16 (q16) output on request, so that half the
//!    bytes cross the bus and the host does not encode; `pack_q16r` writes q16 positions as
//!    the wire's residual planes against a reference ([`Readout::Residuals`]), so the host
//!    does not code them either. Where nothing reads f32 positions after the blend (no skin,
//!    no normals) `blend` writes q16, binary16 or q16r's planes itself (its `PACK` override)
//!    and there is no pack pass: 6 bytes a vertex written instead of 12 + 12 + 6.
//!
//! Results are copied to a mappable staging buffer only when the caller wants vertex buffers;
//! staging buffers live in a small pool, so a batch can be recorded and submitted while the
//! previous one is still being read back ([`GpuContext::submit`] / [`Pending::wait`]).
//! Timestamp queries around each sub-batch's pass give the GPU time.
//!
//! Every function takes the context (which owns `Device` and `Queue`), so tests can open their
//! own device with [`GpuContext::from_device`].
//!
//! | module | what it is |
//! |---|---|
//! | this file | [`GpuError`], [`GpuOptions`], the device memory budget's defaults ([`default_gpu_memory`], [`discrete_gpu_memory`]), [`Reclaim`], and the re-exports |
//! | `device` | what every file that touches the device shares: buffer sizes and creation, the device's health |
//! | `pipelines` | [`SHADERS`] and the compute pipelines made from them, one per entry point |
//! | `context` | [`GpuContext`]: adapter choice, the device, its pipelines, memory budget and reclaimers, buffer helpers |
//! | `slot` | a batch's buffers (`Slot`), what a batch needs of one, and their pool |
//! | `rig` | the upload: [`GpuRig`] (geometry, topology, influences, LOD order) and [`ClipTables`] |
//! | `batch` | a batch cut into pieces and sub-batches, laid out on the device and sized (`plan_pieces`, `plan_batch`, `slot_needs`: pure functions with unit tests) |
//! | `submit` | [`GpuContext::submit`]: a batch cut into pieces, each piece's slot, uploads and commands |
//! | `passes` | one sub-batch's compute passes, one function per WGSL entry point |
//! | `readback` | [`Readout`], [`Pending`]: waiting for a batch and reading it back piece by piece ([`Readback`]), or keeping it on the device ([`DeviceOutput`]) |
//! | [`layout`] | host-side layout of the delta blocks and the `#[repr(C)]` structs the shaders read |
//! | `map` | [`MapResults`]: a batch's buffer mappings, collected whichever thread polls |
//!
//! The files are layered, each importing only those above it: this file; `device`, `layout`,
//! `map`; `pipelines`, `slot`; `context`; `rig`, `batch`; `passes`, `readback`; `submit`.

mod batch;
mod context;
mod device;
pub mod layout;
mod map;
mod passes;
mod pipelines;
mod readback;
mod rig;
mod slot;
mod submit;

pub use self::context::{GpuContext, is_hardware};
pub use self::layout::DeltaFormat;
pub use self::map::MapResults;
pub use self::pipelines::SHADERS;
pub use self::readback::{DeviceOutput, Pending, Readback, Readout};
pub use self::rig::{ClipTables, GpuRig};
use crowdmorph_core::budget::BudgetError;

/// Why the GPU engine could not do something.
#[derive(Debug, thiserror::Error, Clone, PartialEq)]
pub enum GpuError {
    /// No adapter matched the request.
    #[error("no suitable GPU adapter: {0}")]
    NoAdapter(String),
    /// The device could not be opened.
    #[error("cannot open the GPU device: {0}")]
    Device(String),
    /// The device was lost (driver reset, `destroy`, hang).
    #[error("GPU device lost: {0}")]
    Lost(String),
    /// The device ran out of memory.
    #[error("GPU out of memory: {0}")]
    OutOfMemory(String),
    /// The rig or batch exceeds what the device can hold.
    #[error("does not fit on the GPU: {0}")]
    DoesNotFit(String),
    /// Any other device error (a validation error here is a bug in crowdmorph).
    #[error("GPU error: {0}")]
    Internal(String),
    /// The device's memory budget (`--max-gpu-memory`) refused a buffer: `TooLarge` when it
    /// can never fit, `Full` when what the device holds now leaves no room.
    #[error("GPU memory: {0}")]
    Memory(#[from] BudgetError),
}

/// Default of [`GpuOptions::memory`] where the device's memory is not known (software and
/// integrated adapters, non-Vulkan backends): 2 GiB, or the device's largest buffer when that
/// is larger (capped at 16 GiB), so that one buffer the device allows can always be charged.
/// A discrete GPU gets [`DISCRETE_GPU_MEMORY_SHARE`] of its memory instead.
pub const DEFAULT_GPU_MEMORY: u64 = 2 << 30;

/// The share of a discrete GPU's largest device-local memory heap that the budget defaults
/// to: the rest is left to the driver, other processes and what the budget does not count
/// (pipelines, small uniforms, the renderer's fixed buffers).
pub const DISCRETE_GPU_MEMORY_SHARE: f64 = 0.75;

/// The GPU memory cap of a device with `limits` when none is configured and its memory is
/// unknown.
pub fn default_gpu_memory(limits: &wgpu::Limits) -> u64 {
    DEFAULT_GPU_MEMORY.max(limits.max_buffer_size.min(16 << 30))
}

/// The budget a discrete GPU gets when none is configured: [`DISCRETE_GPU_MEMORY_SHARE`] of its
/// largest device-local heap, as Vulkan reports it (wgpu itself does not report memory), but
/// never less than [`default_gpu_memory`]. `None` for other adapters and backends.
pub fn discrete_gpu_memory(adapter: &wgpu::Adapter) -> Option<u64> {
    if adapter.get_info().device_type != wgpu::DeviceType::DiscreteGpu {
        return None;
    }
    let heap = device_local_heap(adapter)?;
    let share = (heap as f64 * DISCRETE_GPU_MEMORY_SHARE) as u64;
    Some(share.max(default_gpu_memory(&adapter.limits())))
}

/// The largest device-local memory heap of a Vulkan adapter, bytes (`None` on other backends).
pub fn device_local_heap(adapter: &wgpu::Adapter) -> Option<u64> {
    // SAFETY: the hal adapter is only read (a memory-properties query on its physical device,
    // through the instance that owns it); nothing is created or destroyed, and the guard
    // outlives the call.
    unsafe {
        let hal = adapter.as_hal::<wgpu::hal::api::Vulkan>()?;
        let instance = hal.shared_instance().raw_instance();
        let props = instance.get_physical_device_memory_properties(hal.raw_physical_device());
        let n = (props.memory_heap_count as usize).min(props.memory_heaps.len());
        // VK_MEMORY_HEAP_DEVICE_LOCAL_BIT is 0x1.
        props.memory_heaps[..n]
            .iter()
            .filter(|h| h.flags.as_raw() & 1 != 0)
            .map(|h| h.size)
            .max()
    }
}

/// Options of a GPU context.
#[derive(Clone, Copy, Debug, Default)]
pub struct GpuOptions {
    /// Use at most this many bytes per storage binding (tests lower it to force sub-batches).
    pub max_binding: Option<u64>,
    /// Cut rigs into chunks of at most this many bytes (tests lower it to force chunking; by
    /// default a chunk is as large as a storage binding).
    pub max_chunk: Option<u64>,
    /// Stage and read back a batch in pieces of at most this many bytes of output (and of bone
    /// matrices), as if the device's largest buffer were this small (tests lower it to force
    /// pieces; by default a piece is as large as the largest buffer).
    pub max_piece_bytes: Option<u64>,
    /// Bytes of buffers and textures whose size an input decides that the device may hold at
    /// once (`--max-gpu-memory`; default [`default_gpu_memory`]).
    pub memory: Option<u64>,
    /// How rigs uploaded from now on store their deltas (`--gpu-deltas`).
    pub deltas: DeltaFormat,
}

/// The flag that sets the GPU memory cap, for error messages.
pub const GPU_MEMORY_FLAG: &str = "--max-gpu-memory";

/// Something that keeps device memory only to save reallocations (a renderer's last targets,
/// a cache of uploaded topologies) and can give it back when a charge finds the device's budget
/// full. Registered with [`GpuContext::register_reclaim`] as a `Weak`, so the context keeps
/// nothing alive and the owner needs no unregistering.
pub trait Reclaim: Send + Sync {
    /// Drops what is kept only for reuse; whether anything was. Must not wait for a lock that a
    /// user of the kept things may hold while charging device memory (use `try_lock`: a holder
    /// is using it, so it is not idle), and must not charge device memory itself.
    fn reclaim(&self) -> bool;
}
