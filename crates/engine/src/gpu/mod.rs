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

pub mod layout;
mod map;

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, Weak};

pub use self::map::MapResults;

pub use self::layout::DeltaFormat;
use self::layout::{
    ActiveParams, Attribute, BlendParams, GpuJob, GpuTerm, JOBS_PER_GROUP, NO_LIVE, NormalParams,
    PackParams, Q16PackParams, SkinParams, build_chunks, pack_influences,
};
use super::cpu::NormalTopology;
use super::{BlendJob, BlendOutput, OutputSpec, Precision, Q16Scale, VertexData};
use crowdmorph_core::budget::{BudgetError, Charge, MemoryPool};
use crowdmorph_core::rig::{BoneMatrix, LIVE_STEP, Pose, Rig};

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

/// Whether the device is still usable, and why not.
#[derive(Default)]
struct Health {
    lost: AtomicBool,
    reason: Mutex<Option<String>>,
}

impl Health {
    fn fail(&self, reason: String) {
        if let Ok(mut r) = self.reason.lock() {
            r.get_or_insert(reason);
        }
        self.lost.store(true, Ordering::SeqCst);
    }
    fn check(&self) -> Result<(), GpuError> {
        if self.lost.load(Ordering::SeqCst) {
            let reason = self
                .reason
                .lock()
                .ok()
                .and_then(|r| r.clone())
                .unwrap_or_default();
            Err(GpuError::Lost(reason))
        } else {
            Ok(())
        }
    }
}

struct Pipelines {
    active: wgpu::ComputePipeline,
    blend: BlendPipelines,
    /// `blend` reading binary16 deltas (its `F16_DELTAS` override set), made only on a
    /// context whose rigs store them ([`GpuOptions::deltas`]).
    blend_f16: Option<BlendPipelines>,
    face: wgpu::ComputePipeline,
    vertex: wgpu::ComputePipeline,
    pack: wgpu::ComputePipeline,
    pack_q16: wgpu::ComputePipeline,
    pack_q16r: wgpu::ComputePipeline,
    skin: wgpu::ComputePipeline,
}

/// `blend` for each output it writes (its `PACK` override): f32, or the 16-bit wire formats
/// (q16r's planes too) written by the blend itself where nothing reads f32 positions after it.
struct BlendPipelines {
    f32: wgpu::ComputePipeline,
    q16: wgpu::ComputePipeline,
    f16: wgpu::ComputePipeline,
    q16r: wgpu::ComputePipeline,
}

impl BlendPipelines {
    fn new(device: &wgpu::Device, module: &wgpu::ShaderModule, f16_deltas: bool) -> Self {
        let deltas = f64::from(u8::from(f16_deltas));
        let make = |pack: f64| {
            pipeline_with(
                device,
                module,
                "blend_packed",
                &[("F16_DELTAS", deltas), ("PACK", pack)],
            )
        };
        BlendPipelines {
            f32: pipeline_with(device, module, "blend", &[("F16_DELTAS", deltas)]),
            q16: make(1.0),
            f16: make(2.0),
            q16r: make(3.0),
        }
    }

    /// The pipeline writing `precision` itself (q16 as residual planes with `residuals`), or
    /// f32 (`fused` false).
    fn writing(
        &self,
        precision: Precision,
        fused: bool,
        residuals: bool,
    ) -> &wgpu::ComputePipeline {
        match (precision, fused, residuals) {
            (Precision::Q16(_), true, true) => &self.q16r,
            (Precision::Q16(_), true, false) => &self.q16,
            (Precision::F16, true, _) => &self.f16,
            _ => &self.f32,
        }
    }
}

/// An open device with the engine's pipelines.
pub struct GpuContext {
    device: wgpu::Device,
    queue: wgpu::Queue,
    adapter: wgpu::AdapterInfo,
    pipelines: Pipelines,
    /// Nanoseconds per timestamp tick, when the device has timestamp queries.
    timestamp_period: Option<f32>,
    max_binding: u64,
    max_chunk: u64,
    max_buffer: u64,
    deltas: DeltaFormat,
    health: Arc<Health>,
    pool: Mutex<Vec<Slot>>,
    /// The device memory budget every input-sized buffer (rigs, batch slots, outputs kept for
    /// drawing, a renderer's targets) is charged to before it is created.
    memory: Arc<MemoryPool>,
    /// The other holders of memory kept only for reuse on this device (a renderer, the
    /// server's topology cache), which [`GpuContext::charge`] asks to give it back when the
    /// budget is full.
    reclaimers: Mutex<Vec<Weak<dyn Reclaim>>>,
}

impl std::fmt::Debug for GpuContext {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuContext")
            .field("adapter", &self.adapter.name)
            .field("backend", &self.adapter.backend)
            .field("max_binding", &self.max_binding)
            .finish()
    }
}

/// Whether an adapter is real hardware (not a CPU rasterizer like llvmpipe).
pub fn is_hardware(info: &wgpu::AdapterInfo) -> bool {
    matches!(
        info.device_type,
        wgpu::DeviceType::DiscreteGpu
            | wgpu::DeviceType::IntegratedGpu
            | wgpu::DeviceType::VirtualGpu
    )
}

fn rank(info: &wgpu::AdapterInfo) -> u8 {
    match info.device_type {
        wgpu::DeviceType::DiscreteGpu => 0,
        wgpu::DeviceType::IntegratedGpu => 1,
        wgpu::DeviceType::VirtualGpu => 2,
        wgpu::DeviceType::Cpu => 3,
        wgpu::DeviceType::Other => 4,
    }
}

/// The WGSL source of each compute pass's module, by its file in `crates/engine/shaders/`: the file after
/// the shared pieces of `crates/engine/shaders/lib/` it uses, joined at compile time (WGSL has no include).
/// The engine compiles exactly these, and `crates/engine/tests/shaders.rs` validates exactly these.
pub const SHADERS: [(&str, &str); 7] = [
    (
        "active.wgsl",
        concat!(
            include_str!("../../shaders/lib/scan.wgsl"),
            include_str!("../../shaders/active.wgsl")
        ),
    ),
    (
        "blend.wgsl",
        concat!(
            include_str!("../../shaders/lib/scan.wgsl"),
            include_str!("../../shaders/lib/q16.wgsl"),
            include_str!("../../shaders/blend.wgsl")
        ),
    ),
    (
        "face_normals.wgsl",
        include_str!("../../shaders/face_normals.wgsl"),
    ),
    (
        "vertex_normals.wgsl",
        include_str!("../../shaders/vertex_normals.wgsl"),
    ),
    ("pack_f16.wgsl", include_str!("../../shaders/pack_f16.wgsl")),
    (
        "pack_q16.wgsl",
        concat!(
            include_str!("../../shaders/lib/q16.wgsl"),
            include_str!("../../shaders/pack_q16.wgsl")
        ),
    ),
    ("skin.wgsl", include_str!("../../shaders/skin.wgsl")),
];

fn shader(device: &wgpu::Device, label: &str, source: &str) -> wgpu::ShaderModule {
    device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some(label),
        source: wgpu::ShaderSource::Wgsl(source.into()),
    })
}

fn pipeline(
    device: &wgpu::Device,
    module: &wgpu::ShaderModule,
    entry: &str,
) -> wgpu::ComputePipeline {
    pipeline_with(device, module, entry, &[])
}

/// A pipeline with its pipeline-overridable constants set.
fn pipeline_with(
    device: &wgpu::Device,
    module: &wgpu::ShaderModule,
    entry: &str,
    constants: &[(&str, f64)],
) -> wgpu::ComputePipeline {
    device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some(entry),
        layout: None,
        module,
        entry_point: Some(entry),
        compilation_options: wgpu::PipelineCompilationOptions {
            constants,
            ..Default::default()
        },
        cache: None,
    })
}

impl GpuContext {
    /// The adapters of the backends `WGPU_BACKEND` names, else of the primary ones (Vulkan,
    /// Metal, DX12) or, with `with_gl`, of every backend. GL is probed only when nothing else
    /// was found: its EGL probe logs an ERROR on every machine without a GL driver (a server
    /// on Vulkan, or with no GPU at all), which reads like a failure at every start.
    fn adapters(with_gl: bool) -> Vec<wgpu::Adapter> {
        let mut desc = wgpu::InstanceDescriptor::new_without_display_handle_from_env();
        if std::env::var_os("WGPU_BACKEND").is_none() && !with_gl {
            desc.backends = wgpu::Backends::PRIMARY;
        }
        let backends = desc.backends;
        let instance = wgpu::Instance::new(desc);
        pollster::block_on(instance.enumerate_adapters(backends))
    }

    /// Opens the best adapter: hardware only when `allow_software` is false (the `auto`
    /// backend), any adapter otherwise. `WGPU_BACKEND`, `WGPU_ADAPTER_NAME` (a substring of the
    /// adapter name) narrow the choice.
    pub fn open(allow_software: bool, options: GpuOptions) -> Result<GpuContext, GpuError> {
        let mut adapters = Self::adapters(false);
        if adapters.is_empty() && std::env::var_os("WGPU_BACKEND").is_none() {
            adapters = Self::adapters(true);
        }
        let name_filter = std::env::var("WGPU_ADAPTER_NAME")
            .ok()
            .map(|s| s.to_lowercase());
        adapters.retain(|a| {
            let info = a.get_info();
            (allow_software || is_hardware(&info))
                && name_filter
                    .as_ref()
                    .is_none_or(|n| info.name.to_lowercase().contains(n))
        });
        adapters.sort_by_key(|a| rank(&a.get_info()));
        let Some(adapter) = adapters.into_iter().next() else {
            return Err(GpuError::NoAdapter(if allow_software {
                "wgpu found no adapter (is a Vulkan driver such as mesa-vulkan-drivers installed?)"
                    .into()
            } else {
                "no hardware adapter (software adapters are used only with --backend gpu)".into()
            }));
        };
        let features = adapter.features() & wgpu::Features::TIMESTAMP_QUERY;
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("crowdmorph"),
            required_features: features,
            required_limits: adapter.limits(),
            experimental_features: wgpu::ExperimentalFeatures::default(),
            memory_hints: wgpu::MemoryHints::Performance,
            trace: wgpu::Trace::Off,
        }))
        .map_err(|e| GpuError::Device(e.to_string()))?;
        let options = GpuOptions {
            memory: options.memory.or_else(|| discrete_gpu_memory(&adapter)),
            ..options
        };
        Ok(Self::from_device(
            device,
            queue,
            adapter.get_info(),
            options,
        ))
    }

    /// Builds the engine on a device the caller opened (tests inject their own).
    pub fn from_device(
        device: wgpu::Device,
        queue: wgpu::Queue,
        adapter: wgpu::AdapterInfo,
        options: GpuOptions,
    ) -> GpuContext {
        let health = Arc::new(Health::default());
        let h = health.clone();
        device.set_device_lost_callback(move |reason, message| {
            h.fail(format!("{reason:?}: {message}"));
        });
        let h = health.clone();
        device.on_uncaptured_error(Arc::new(move |error: wgpu::Error| {
            tracing::error!(%error, "uncaptured GPU error; the GPU engine stops and the CPU engine takes over");
            h.fail(error.to_string());
        }));
        let [active, blend, face, vertex, pack, pack_q16, skin] =
            SHADERS.map(|(name, source)| shader(&device, name, source));
        let pipelines = Pipelines {
            active: pipeline(&device, &active, "build_active"),
            blend: BlendPipelines::new(&device, &blend, false),
            blend_f16: (options.deltas == DeltaFormat::F16)
                .then(|| BlendPipelines::new(&device, &blend, true)),
            face: pipeline(&device, &face, "face_normals"),
            vertex: pipeline(&device, &vertex, "vertex_normals"),
            pack: pipeline(&device, &pack, "pack_f16"),
            pack_q16: pipeline(&device, &pack_q16, "pack_q16"),
            pack_q16r: pipeline(&device, &pack_q16, "pack_q16r"),
            skin: pipeline(&device, &skin, "skin"),
        };
        let limits = device.limits();
        let mut max_binding = limits.max_storage_buffer_binding_size;
        if let Some(m) = options.max_binding {
            max_binding = max_binding.min(m);
        }
        let timestamp_period = device
            .features()
            .contains(wgpu::Features::TIMESTAMP_QUERY)
            .then(|| queue.get_timestamp_period());
        GpuContext {
            device,
            queue,
            adapter,
            pipelines,
            timestamp_period,
            max_binding,
            max_chunk: options
                .max_chunk
                .map_or(max_binding, |c| c.min(max_binding)),
            max_buffer: limits.max_buffer_size,
            deltas: options.deltas,
            health,
            pool: Mutex::new(Vec::new()),
            memory: MemoryPool::new(
                options
                    .memory
                    .unwrap_or_else(|| default_gpu_memory(&limits)),
                GPU_MEMORY_FLAG,
            ),
            reclaimers: Mutex::new(Vec::new()),
        }
    }

    /// The device memory budget (what is charged and allowed; charge through
    /// [`GpuContext::charge`], which makes room by freeing what is kept only for reuse).
    pub fn memory(&self) -> &Arc<MemoryPool> {
        &self.memory
    }

    /// Charges `bytes` of device memory about to be allocated for `what`. When the budget is
    /// full, everything kept on this device only for reuse — the engine's idle batch slots and
    /// whatever the registered [`Reclaim`]ers keep (a renderer's last targets and buffers,
    /// cached topologies) — is given back and the charge tried once more: kept forever, such
    /// memory would refuse every later rig upload, batch or render ("retry shortly" that never
    /// succeeds). Call it holding no lock a reclaimer may need (each uses `try_lock`, so a held
    /// one only means that holder's memory is not freed).
    pub fn charge(&self, bytes: u64, what: impl Fn() -> String) -> Result<Charge, BudgetError> {
        match self.memory.charge(bytes, &what) {
            Err(BudgetError::Full { .. }) if self.reclaim() => self.memory.charge(bytes, what),
            r => r,
        }
    }

    /// Registers a holder of memory kept only for reuse on this device, asked to give it back
    /// when a charge finds the budget full (until it is dropped).
    pub fn register_reclaim(&self, reclaimer: Weak<dyn Reclaim>) {
        if let Ok(mut r) = self.reclaimers.lock() {
            r.retain(|w| w.strong_count() > 0);
            r.push(reclaimer);
        }
    }

    /// Gives back everything kept only for reuse on this device; whether anything was. The
    /// reclaimers are called with no lock of the context held (the list is copied first), so
    /// one may drop buffers or take its own locks freely.
    fn reclaim(&self) -> bool {
        let mut freed = self.free_idle_slots();
        let live: Vec<Arc<dyn Reclaim>> = match self.reclaimers.lock() {
            Ok(mut r) => {
                r.retain(|w| w.strong_count() > 0);
                r.iter().filter_map(Weak::upgrade).collect()
            }
            Err(_) => Vec::new(),
        };
        for r in live {
            freed |= r.reclaim();
        }
        freed
    }

    /// Drops the pooled batch slots, giving their memory back; whether there were any. A
    /// thread that holds the pool (choosing or building a slot) is not waited for.
    fn free_idle_slots(&self) -> bool {
        let idle = match self.pool.try_lock() {
            Ok(mut pool) => std::mem::take(&mut *pool),
            Err(_) => return false,
        };
        !idle.is_empty()
    }

    /// The adapter in use.
    pub fn adapter(&self) -> &wgpu::AdapterInfo {
        &self.adapter
    }

    /// The queue (a renderer on the same device records its passes here).
    pub fn queue(&self) -> &wgpu::Queue {
        &self.queue
    }

    /// The device (tests use it to simulate a loss with `destroy`).
    pub fn device(&self) -> &wgpu::Device {
        &self.device
    }

    /// Largest storage binding the engine uses.
    pub fn max_binding(&self) -> u64 {
        self.max_binding
    }

    /// Whether GPU times are measured.
    pub fn has_timestamps(&self) -> bool {
        self.timestamp_period.is_some()
    }

    /// Err once the device is lost or has reported an error.
    pub fn health(&self) -> Result<(), GpuError> {
        self.health.check()
    }

    fn buffer(&self, label: &str, size: u64, usage: wgpu::BufferUsages) -> wgpu::Buffer {
        self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: padded(size),
            usage,
            mapped_at_creation: false,
        })
    }

    fn init(&self, label: &str, bytes: &[u8], usage: wgpu::BufferUsages) -> wgpu::Buffer {
        // Bindings may not be empty; pad tiny or empty arrays to 16 bytes.
        let mut padded;
        let contents = if bytes.len() < 16 || !bytes.len().is_multiple_of(4) {
            padded = bytes.to_vec();
            padded.resize(bytes.len().max(16).next_multiple_of(4), 0);
            &padded[..]
        } else {
            bytes
        };
        // Not `create_buffer_init`: it maps the buffer and panics if the device is gone, while
        // a queued write just reports the loss through the device's error handling.
        let buffer = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: contents.len() as u64,
            usage: usage | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        self.queue.write_buffer(&buffer, 0, contents);
        buffer
    }

    /// Bytes `init` allocates for `data`, for charging before it does.
    fn init_bytes<T>(data: &[T]) -> u64 {
        padded(size_of_val(data) as u64)
    }

    fn uniform<T: bytemuck::Pod>(&self, value: &T) -> wgpu::Buffer {
        self.init(
            "params",
            bytemuck::bytes_of(value),
            wgpu::BufferUsages::UNIFORM,
        )
    }
}

fn entry(binding: u32, buffer: &wgpu::Buffer) -> wgpu::BindGroupEntry<'_> {
    wgpu::BindGroupEntry {
        binding,
        resource: buffer.as_entire_binding(),
    }
}

/// One chunk of a resident rig.
struct GpuChunk {
    tile_begin: u32,
    tiles: u32,
    base: wgpu::Buffer,
    blocks: wgpu::Buffer,
    masks: wgpu::Buffer,
}

struct GpuTopology {
    triangles: wgpu::Buffer,
    recomputed: wgpu::Buffer,
    incident_start: wgpu::Buffer,
    incident: wgpu::Buffer,
    n_triangles: u32,
    n_recomputed: u32,
}

/// A skinned rig's influences on the device.
struct GpuSkin {
    /// [`layout::INFLUENCE_WORDS`] words per vertex.
    influences: wgpu::Buffer,
    /// Bones of the rig: matrices per job in a batch.
    bones: u32,
}

/// Bytes of a buffer `GpuContext::buffer` or `init` makes for `size` bytes: bindings may not
/// be empty, so tiny arrays are padded to 16 bytes, and sizes to whole words.
fn padded(size: u64) -> u64 {
    size.max(16).next_multiple_of(4)
}

/// A rig resident on the GPU.
pub struct GpuRig {
    vertices: u32,
    /// How its delta blocks are stored (both attributes alike).
    deltas: DeltaFormat,
    slots: u32,
    words: u32,
    positions: Vec<GpuChunk>,
    /// Empty when every vertex's normal is recomputed from positions.
    normals: Vec<GpuChunk>,
    order: wgpu::Buffer,
    /// The clip tables, shared by every mesh level of the rig.
    tables: Arc<ClipTables>,
    topology: Option<GpuTopology>,
    /// On a skinned rig, every vertex's bones for the `skin` pass.
    skin: Option<GpuSkin>,
    /// LOD shape counts per level.
    lod_shapes: Vec<u32>,
    geometry_bytes: u64,
    /// The geometry's bytes in the device's memory budget, shared by the versions of the rig
    /// that share the geometry (new clips); given back when the last one is dropped.
    charge: Arc<Charge>,
}

/// A rig's clip tables resident on the device: every clip's `targets × frames` table, one
/// after another in one storage buffer. A rig's mesh levels evaluate the same clips, so they
/// share this buffer instead of holding copies (a clip table is often the largest array a rig
/// has).
pub struct ClipTables {
    buffer: wgpu::Buffer,
    /// (offset in `buffer`, in f32, and frames) per clip.
    clips: Vec<(u32, u32)>,
    bytes: u64,
    /// Its bytes in the device's memory budget.
    _charge: Charge,
}

impl std::fmt::Debug for ClipTables {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ClipTables")
            .field("clips", &self.clips.len())
            .field("bytes", &self.bytes)
            .finish()
    }
}

impl ClipTables {
    /// Uploads every clip table of `rig`, each written in place (no concatenated host copy).
    pub fn upload(ctx: &GpuContext, rig: &Rig) -> Result<Arc<ClipTables>, GpuError> {
        ctx.health()?;
        let total: u64 = rig.clips.iter().map(|c| c.weights.len() as u64 * 4).sum();
        if total > ctx.max_binding {
            return Err(GpuError::DoesNotFit(format!(
                "clip tables of {total} bytes exceed one storage binding of {} bytes",
                ctx.max_binding
            )));
        }
        let storage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST;
        let charge = ctx.charge(padded(total), || {
            format!("{} clip tables ({total} bytes) on the GPU", rig.clips.len())
        })?;
        let buffer = ctx.buffer("tables", total, storage);
        let mut clips = Vec::with_capacity(rig.clips.len());
        let mut at = 0u64;
        for c in &rig.clips {
            clips.push(((at / 4) as u32, c.frames));
            if !c.weights.is_empty() {
                ctx.queue
                    .write_buffer(&buffer, at, bytemuck::cast_slice(&c.weights[..]));
            }
            at += c.weights.len() as u64 * 4;
        }
        Ok(Arc::new(ClipTables {
            bytes: buffer.size(),
            buffer,
            clips,
            _charge: charge,
        }))
    }

    /// Bytes resident on the device.
    pub fn bytes(&self) -> u64 {
        self.bytes
    }
}

impl std::fmt::Debug for GpuRig {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuRig")
            .field("vertices", &self.vertices)
            .field("chunks", &self.positions.len())
            .field("device_bytes", &self.device_bytes())
            .finish()
    }
}

impl GpuRig {
    /// Whether `blend_packed` writes a batch's output in `spec`'s 16-bit format (q16r's planes
    /// too) itself: where nothing reads f32 positions after the blend, that is no skin and no
    /// normals (recomputed from them, or blended by a second dispatch whose output the pack
    /// pass would then read). Its slot then needs no f32 output buffer.
    fn blend_packs(&self, spec: OutputSpec) -> bool {
        matches!(spec.precision, Precision::Q16(_) | Precision::F16)
            && !spec.normals
            && self.skin.is_none()
    }

    /// Refuses (`DoesNotFit`) a rig with more vertices than one job's output binding holds,
    /// before anything is uploaded. It costs nothing; [`GpuRig::upload`] also checks the
    /// triangles of recomputed normals, once it has built their topology.
    pub fn check_fits(ctx: &GpuContext, rig: &Rig) -> Result<(), GpuError> {
        ctx.health()?;
        let vertices = rig.vertex_count();
        let per_job = (vertices * 3 * 4) as u64;
        if per_job > ctx.max_binding {
            return Err(GpuError::DoesNotFit(format!(
                "{vertices} vertices: one job's output ({per_job} bytes) exceeds the {}-byte \
                 storage binding",
                ctx.max_binding
            )));
        }
        let bones = rig.skeleton.as_ref().map_or(0, |s| s.bones.len()) as u64;
        let bone_bytes = bones * size_of::<BoneMatrix>() as u64;
        if bone_bytes > ctx.max_binding
            || (vertices * layout::INFLUENCE_WORDS * 4) as u64 > ctx.max_binding
        {
            return Err(GpuError::DoesNotFit(format!(
                "{bones} bones: one job's bone matrices or the influences exceed the \
                 {}-byte storage binding",
                ctx.max_binding
            )));
        }
        Ok(())
    }

    fn fits(ctx: &GpuContext, rig: &Rig, topology: &NormalTopology) -> Result<(), GpuError> {
        Self::check_fits(ctx, rig)?;
        let vertices = rig.vertex_count();
        let tri_bytes = topology.triangles.len() as u64 * 12;
        if tri_bytes > ctx.max_binding
            || topology.triangles.len() > 65_535 * 64
            || topology.vertices.len() > 65_535 * 64
            || vertices > 65_535 * 64 * 65_535
        {
            return Err(GpuError::DoesNotFit(format!(
                "{} triangles of recomputed normals exceed the device's dispatch or binding limits",
                topology.triangles.len()
            )));
        }
        Ok(())
    }

    /// Uploads everything a batch of this rig reads, with clip tables `tables` (uploaded with
    /// [`ClipTables::upload`], and shared with the rig's other mesh levels). Refuses
    /// (`DoesNotFit`) rigs the device cannot hold, instead of failing later in the middle of a
    /// batch.
    pub fn upload(
        ctx: &GpuContext,
        rig: &Rig,
        tables: Arc<ClipTables>,
    ) -> Result<GpuRig, GpuError> {
        let vertices = rig.vertex_count();
        let topology = NormalTopology::of(rig);
        Self::fits(ctx, rig, &topology)?;
        if tables.clips.len() != rig.clips.len() {
            return Err(GpuError::DoesNotFit(format!(
                "{} clip tables for a rig with {} clips",
                tables.clips.len(),
                rig.clips.len()
            )));
        }
        // Laid out on the host first, so that everything the device will hold is charged to
        // its memory budget before any buffer is created.
        let deltas = if ctx.deltas.holds(rig) {
            ctx.deltas
        } else {
            tracing::warn!(
                rig = %rig.name,
                "a delta exceeds binary16's range (65,504): this rig keeps f32 deltas on the GPU"
            );
            DeltaFormat::F32
        };
        let position_chunks = build_chunks(rig, Attribute::Positions, ctx.max_chunk, deltas);
        let normal_chunks = if topology.vertices.len() < vertices {
            build_chunks(rig, Attribute::Normals, ctx.max_chunk, deltas)
        } else {
            Vec::new()
        };
        let chunk_bytes: u64 = position_chunks
            .iter()
            .chain(&normal_chunks)
            .map(|c| {
                GpuContext::init_bytes(&c.base)
                    + GpuContext::init_bytes(&c.blocks)
                    + GpuContext::init_bytes(&c.masks)
            })
            .sum();
        let topology_bytes = if topology.vertices.is_empty() {
            0
        } else {
            GpuContext::init_bytes(&topology.triangles)
                + GpuContext::init_bytes(&topology.vertices)
                + GpuContext::init_bytes(&topology.incident_start)
                + GpuContext::init_bytes(&topology.incident)
        };
        let influences = rig.is_skinned().then(|| pack_influences(rig));
        let skin_bytes = influences.as_deref().map_or(0, GpuContext::init_bytes);
        let charge = Arc::new(ctx.charge(
            chunk_bytes + topology_bytes + skin_bytes + GpuContext::init_bytes(&rig.lod.order),
            || {
                format!(
                    "a rig of {vertices} vertices and {} targets on the GPU",
                    rig.targets.len()
                )
            },
        )?);
        let scope = ctx.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let storage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST;
        let upload_chunks = |chunks: Vec<layout::Chunk>| -> Vec<GpuChunk> {
            chunks
                .into_iter()
                .map(|c| GpuChunk {
                    tile_begin: c.tile_begin,
                    tiles: c.tiles,
                    base: ctx.init("base", bytemuck::cast_slice(&c.base), storage),
                    blocks: ctx.init("blocks", bytemuck::cast_slice(&c.blocks), storage),
                    masks: ctx.init("masks", bytemuck::cast_slice(&c.masks), storage),
                })
                .collect()
        };
        let positions = upload_chunks(position_chunks);
        let normals = upload_chunks(normal_chunks);
        let order: Vec<u32> = rig.lod.order.clone();
        let topo = (!topology.vertices.is_empty()).then(|| GpuTopology {
            triangles: ctx.init(
                "triangles",
                bytemuck::cast_slice(&topology.triangles),
                storage,
            ),
            recomputed: ctx.init(
                "recomputed",
                bytemuck::cast_slice(&topology.vertices),
                storage,
            ),
            incident_start: ctx.init(
                "incident_start",
                bytemuck::cast_slice(&topology.incident_start),
                storage,
            ),
            incident: ctx.init(
                "incident",
                bytemuck::cast_slice(&topology.incident),
                storage,
            ),
            n_triangles: topology.triangles.len() as u32,
            n_recomputed: topology.vertices.len() as u32,
        });
        let chunk_bytes = |cs: &[GpuChunk]| -> u64 {
            cs.iter()
                .map(|c| c.base.size() + c.blocks.size() + c.masks.size())
                .sum()
        };
        let topo_bytes = topo.as_ref().map_or(0, |t| {
            t.triangles.size() + t.recomputed.size() + t.incident_start.size() + t.incident.size()
        });
        let skin = influences.map(|words| GpuSkin {
            influences: ctx.init("influences", bytemuck::cast_slice(&words), storage),
            bones: rig.skeleton.as_ref().map_or(0, |s| s.bones.len()) as u32,
        });
        let skin_bytes = skin.as_ref().map_or(0, |s| s.influences.size());
        let gpu = GpuRig {
            vertices: vertices as u32,
            deltas,
            slots: rig.targets.len() as u32,
            words: rig.targets.len().div_ceil(32).max(1) as u32,
            geometry_bytes: chunk_bytes(&positions)
                + chunk_bytes(&normals)
                + topo_bytes
                + skin_bytes
                + order.len() as u64 * 4,
            positions,
            normals,
            order: ctx.init("order", bytemuck::cast_slice(&order), storage),
            tables,
            topology: topo,
            skin,
            lod_shapes: rig.lod.levels.iter().map(|l| l.shapes).collect(),
            charge,
        };
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::OutOfMemory(e.to_string()));
        }
        ctx.health()?;
        Ok(gpu)
    }

    /// A copy of this resident rig with new clip tables (geometry and LOD order unchanged).
    pub fn with_clips(
        &self,
        ctx: &GpuContext,
        tables: Arc<ClipTables>,
    ) -> Result<GpuRig, GpuError> {
        ctx.health()?;
        Ok(GpuRig {
            vertices: self.vertices,
            deltas: self.deltas,
            slots: self.slots,
            words: self.words,
            positions: self.positions.iter().map(GpuChunk::share).collect(),
            normals: self.normals.iter().map(GpuChunk::share).collect(),
            order: self.order.clone(),
            tables,
            topology: self.topology.as_ref().map(|t| GpuTopology {
                triangles: t.triangles.clone(),
                recomputed: t.recomputed.clone(),
                incident_start: t.incident_start.clone(),
                incident: t.incident.clone(),
                n_triangles: t.n_triangles,
                n_recomputed: t.n_recomputed,
            }),
            skin: self.skin.as_ref().map(|s| GpuSkin {
                influences: s.influences.clone(),
                bones: s.bones,
            }),
            lod_shapes: self.lod_shapes.clone(),
            charge: self.charge.clone(),
            geometry_bytes: self.geometry_bytes,
        })
    }

    /// Bytes resident on the device: geometry and clip tables.
    pub fn device_bytes(&self) -> u64 {
        self.geometry_bytes + self.tables.bytes
    }

    /// Bytes of the geometry alone (what a mesh level adds: it shares the clip tables).
    pub fn geometry_bytes(&self) -> u64 {
        self.geometry_bytes
    }

    /// How its deltas are stored on the device.
    pub fn deltas(&self) -> DeltaFormat {
        self.deltas
    }

    /// The clip tables this rig reads.
    pub fn tables(&self) -> &Arc<ClipTables> {
        &self.tables
    }

    /// Storage-binding chunks the rig was split into.
    pub fn chunks(&self) -> usize {
        self.positions.len()
    }

    /// Bones per job of a skinned rig (0 otherwise): how many matrices
    /// [`GpuContext::submit`] takes per job.
    pub fn bones(&self) -> usize {
        self.skin.as_ref().map_or(0, |s| s.bones as usize)
    }

    /// The job record for `job`; `None` if its clips, frames or LOD level are out of range.
    /// Live weights are appended to `live` (one per channel, by target id) and the record
    /// points at them.
    pub fn job(&self, job: &BlendJob, live: &mut Vec<f32>) -> Option<GpuJob> {
        let shapes = *self.lod_shapes.get(job.lod as usize)?;
        let mut out = GpuJob {
            shapes,
            live: NO_LIVE,
            ..GpuJob::default()
        };
        let term = |clip: u32, frame: u32, t: f32| -> Option<GpuTerm> {
            let &(table, frames) = self.tables.clips.get(clip as usize)?;
            (frame < frames).then_some(GpuTerm {
                table,
                frames,
                frame,
                t,
            })
        };
        match &job.pose {
            &Pose::Frame { clip, frame } => {
                out.terms = 1;
                out.term[0] = term(clip, frame, 1.0)?;
            }
            Pose::Blend(terms) => {
                if terms.len() > out.term.len() {
                    return None;
                }
                out.terms = terms.len() as u32;
                for (slot, t) in out.term.iter_mut().zip(terms.iter()) {
                    *slot = term(t.clip, t.frame, t.fraction())?;
                }
            }
            Pose::Live(w) => {
                if w.len() != self.slots as usize {
                    return None;
                }
                out.live = u32::try_from(live.len()).ok()?;
                live.extend(w.iter().map(|&q| q as f32 * LIVE_STEP));
            }
        }
        Some(out)
    }
}

impl GpuChunk {
    fn share(&self) -> GpuChunk {
        GpuChunk {
            tile_begin: self.tile_begin,
            tiles: self.tiles,
            base: self.base.clone(),
            blocks: self.blocks.clone(),
            masks: self.masks.clone(),
        }
    }
}

/// Per-batch buffers, pooled so consecutive batches reuse them and overlap.
struct Slot {
    jobs: wgpu::Buffer,
    active_weights: wgpu::Buffer,
    active_slots: wgpu::Buffer,
    active_count: wgpu::Buffer,
    positions: wgpu::Buffer,
    normals: wgpu::Buffer,
    faces: wgpu::Buffer,
    packed_positions: wgpu::Buffer,
    packed_normals: wgpu::Buffer,
    staging: wgpu::Buffer,
    /// A skinned rig's bone matrices, every sub-batch's at its own aligned offset.
    bones: wgpu::Buffer,
    queries: Option<(wgpu::QuerySet, wgpu::Buffer, wgpu::Buffer)>,
    /// Its buffers' bytes in the device's memory budget.
    _charge: Charge,
}

/// Sizes a batch needs from a slot.
#[derive(Clone, Copy, PartialEq, Eq)]
struct SlotNeeds {
    jobs: u64,
    active: u64,
    output: u64,
    /// Normals output (4 bytes when the batch has none).
    normals: u64,
    /// f16 output of positions, and of normals (4 bytes when unused).
    packed: u64,
    packed_normals: u64,
    faces: u64,
    staging: u64,
    bones: u64,
    queries: u32,
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

impl Slot {
    fn new(ctx: &GpuContext, n: SlotNeeds) -> Result<Slot, GpuError> {
        use wgpu::BufferUsages as U;
        let storage = U::STORAGE | U::COPY_SRC | U::COPY_DST;
        let query_bytes = ctx
            .timestamp_period
            .map_or(0, |_| 2 * padded(u64::from(n.queries.max(2)) * 8));
        let bytes = [
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
            + query_bytes;
        let charge = ctx.charge(bytes, || {
            format!(
                "a batch's buffers ({} bytes of output, {} of readback) on the GPU",
                n.output, n.staging
            )
        })?;
        let queries = ctx.timestamp_period.map(|_| {
            let count = n.queries.max(2);
            (
                ctx.device.create_query_set(&wgpu::QuerySetDescriptor {
                    label: Some("batch timestamps"),
                    ty: wgpu::QueryType::Timestamp,
                    count,
                }),
                ctx.buffer(
                    "timestamps",
                    u64::from(count) * 8,
                    U::QUERY_RESOLVE | U::COPY_SRC,
                ),
                ctx.buffer(
                    "timestamps readback",
                    u64::from(count) * 8,
                    U::MAP_READ | U::COPY_DST,
                ),
            )
        });
        Ok(Slot {
            jobs: ctx.buffer("jobs", n.jobs, storage),
            active_weights: ctx.buffer("active weights", n.active * JOBS_PER_GROUP as u64, storage),
            active_slots: ctx.buffer("active slots", n.active, storage),
            active_count: ctx.buffer("active count", n.active, storage),
            positions: ctx.buffer("positions", n.output, storage),
            normals: ctx.buffer("normals", n.normals, storage),
            faces: ctx.buffer("faces", n.faces, storage),
            packed_positions: ctx.buffer("packed positions", n.packed, storage),
            packed_normals: ctx.buffer("packed normals", n.packed_normals, storage),
            staging: ctx.buffer("staging", n.staging, U::MAP_READ | U::COPY_DST),
            bones: ctx.buffer("bones", n.bones, storage),
            queries,
            _charge: charge,
        })
    }

    /// What this slot can serve.
    fn capacity(&self) -> SlotNeeds {
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

    fn fits(&self, n: SlotNeeds) -> bool {
        let c = self.capacity();
        c.max(n) == c
    }
}

/// Where each sub-batch's results sit in the staging buffer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Region {
    /// First job of the sub-batch.
    job: usize,
    /// Jobs in it.
    jobs: usize,
    positions: u64,
    normals: u64,
    /// Byte offset and length of the live weights in the jobs buffer (the same for every
    /// sub-batch).
    live: (u64, u64),
    /// Byte offset and length of the sub-batch's bone matrices in the slot's bones buffer.
    bones: (u64, u64),
    /// Byte offset and length of the residual reference in the jobs buffer, when the
    /// positions are coded against one (the same for every sub-batch).
    reference: Option<(u64, u64)>,
}

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
    ctx: &'a GpuContext,
    slot: Option<Slot>,
    submission: wgpu::SubmissionIndex,
    regions: Vec<Region>,
    jobs: usize,
    vertices: usize,
    spec: OutputSpec,
    readback: bool,
    /// Bytes of the staging buffer this batch mapped.
    staged: u64,
    mapped: MapResults,
    /// Without readback: the batch's outputs, copied out of the slot so they outlive it.
    resident: Option<DeviceOutput>,
    /// Host time spent copying the batch out of mapped memory (set by `finish`).
    host_ns: u64,
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
    _charge: Arc<Charge>,
}

impl DeviceOutput {
    /// Byte offset of job `j`'s data in either buffer.
    pub fn offset(&self, j: usize) -> u64 {
        (j * self.vertices * 12) as u64
    }
}

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
        let BatchPlan {
            sub,
            regions,
            live_at,
            live_bytes,
            reference_at,
            staging,
            bones_at,
        } = plan_batch(
            &BatchCounts {
                jobs: n,
                vertices: v,
                slots: rig.slots,
                triangles: if recompute { tris } else { 0 },
                bone_bytes,
                live: live.len(),
                reference: reference.map(<[i16]>::len),
                normals: spec.normals,
                packed16,
            },
            self.max_binding,
            u64::from(self.device.limits().min_storage_buffer_offset_alignment),
        );
        let subs = regions.len();
        let reference_range = regions.first().and_then(|r| r.reference);
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
        // Buffers are sized for the largest sub-batch this batch has (not for `sub`, which for
        // a small rig may be thousands of jobs), and only for the outputs it asks for.
        // Every pass writes only the jobs it was given, so outputs hold exactly those; the
        // active lists are per group of eight.
        let widest = sub.min(n.max(1)) as u64;
        let output = widest * per_job_out;
        let f16 = packed16;
        let needs = SlotNeeds {
            jobs: reference_range.map_or(live_at + live_bytes, |(at, len)| at + len),
            active: widest.div_ceil(JOBS_PER_GROUP as u64) * u64::from(rig.slots.max(1)) * 4,
            // The blend writes the 16-bit output itself: no f32 stage.
            output: if rig.blend_packs(spec) { 4 } else { output },
            normals: if spec.normals { output } else { 4 },
            packed: if f16 { output / 2 + 4 } else { 4 },
            packed_normals: if f16 && spec.normals {
                output / 2 + 4
            } else {
                4
            },
            faces: if recompute { widest * tris * 12 } else { 4 },
            staging: if readback { staging } else { 4 },
            bones: if bone_bytes > 0 { bones_at } else { 4 },
            // Timestamp queries only where the device has them.
            queries: if self.timestamp_period.is_some() {
                2 * subs as u32
            } else {
                0
            },
        };
        // Slot buffers are the big allocations of a batch: an out-of-memory error here is
        // reported as such (the engine then falls back to the CPU), not as a bug.
        let oom = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let slot = {
            let mut pool = self
                .pool
                .lock()
                .map_err(|_| GpuError::Internal("slot pool poisoned".into()))?;
            match pool.iter().position(|s| s.fits(needs)) {
                Some(i) => pool.swap_remove(i),
                None => {
                    // No pooled slot is big enough: replace them all with one that serves
                    // this batch and everything they served, so that alternating batch
                    // shapes (with and without normals, f16 and f32) do not reallocate.
                    // The old slots are dropped (and their memory given back) first.
                    let merged = pool.drain(..).fold(needs, |acc, s| acc.max(s.capacity()));
                    Slot::new(self, merged)?
                }
            }
        };
        // Without readback the outputs are copied into buffers of their own (f32 only: they
        // are for drawing), since each sub-batch reuses the slot's output buffers.
        let resident = if readback {
            None
        } else {
            if f16 {
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

    /// Records one sub-batch's passes into `encoder`, inside one timed compute pass.
    fn record(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        rig: &GpuRig,
        slot: &Slot,
        r: &Region,
        spec: OutputSpec,
        k: u32,
    ) {
        let (live_at, live_bytes) = r.live;
        let d = &self.device;
        let p = &self.pipelines;
        let jobs = r.jobs as u32;
        let groups = r.jobs.div_ceil(JOBS_PER_GROUP) as u32;
        let bind = |pipeline: &wgpu::ComputePipeline, entries: &[wgpu::BindGroupEntry<'_>]| {
            d.create_bind_group(&wgpu::BindGroupDescriptor {
                label: None,
                layout: &pipeline.get_bind_group_layout(0),
                entries,
            })
        };
        // The whole job list (the sub-batch starts at record `job_base`), then the live rows.
        let job_bytes = wgpu::BufferBinding {
            buffer: &slot.jobs,
            offset: 0,
            size: std::num::NonZeroU64::new(live_at),
        };
        let live_rows = wgpu::BufferBinding {
            buffer: &slot.jobs,
            offset: live_at,
            size: std::num::NonZeroU64::new(live_bytes),
        };
        let active_params = self.uniform(&ActiveParams {
            jobs,
            groups,
            slots: rig.slots,
            job_base: r.job as u32,
        });
        let active_bg = d.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("build_active"),
            layout: &p.active.get_bind_group_layout(0),
            entries: &[
                entry(0, &active_params),
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: wgpu::BindingResource::Buffer(job_bytes),
                },
                entry(2, &rig.tables.buffer),
                entry(3, &rig.order),
                entry(4, &slot.active_weights),
                entry(5, &slot.active_slots),
                entry(6, &slot.active_count),
                wgpu::BindGroupEntry {
                    binding: 7,
                    resource: wgpu::BindingResource::Buffer(live_rows),
                },
            ],
        });
        // A rig has f16 deltas only on a context made for them, which has these pipelines.
        let blends = match (rig.deltas, &p.blend_f16) {
            (DeltaFormat::F16, Some(f16)) => f16,
            _ => &p.blend,
        };
        let fused = rig.blend_packs(spec);
        let blend = blends.writing(spec.precision, fused, r.reference.is_some());
        // What `blend_packed` reads besides the blend's own bindings: the box (used unless it
        // writes binary16) and the residual reference (a small range where there is none).
        let packing = fused.then(|| {
            let q16 = self.uniform(&match spec.precision {
                Precision::Q16(b) => Q16PackParams::new(
                    &crate::Q16Params::new(b, false),
                    jobs * rig.vertices * 3,
                    0,
                    rig.vertices * 3,
                ),
                _ => Q16PackParams::default(),
            });
            let (at, len) = r.reference.unwrap_or((0, 4));
            (q16, at, len)
        });
        let blend_groups = |chunks: &[GpuChunk],
                            out: &wgpu::Buffer,
                            packed: &wgpu::Buffer,
                            normalize: u32|
         -> Vec<(wgpu::BindGroup, [u32; 3])> {
            chunks
                .iter()
                .map(|c| {
                    // Group first, so that the workgroups running side by side share a tile's
                    // deltas in the cache.
                    let tiles_y = c.tiles.min(65_535);
                    let tiles_z = c.tiles.div_ceil(tiles_y.max(1));
                    let params = self.uniform(&BlendParams {
                        vertices: rig.vertices,
                        tile_begin: c.tile_begin,
                        tiles: c.tiles,
                        slots: rig.slots,
                        words: rig.words,
                        jobs,
                        normalize,
                        tiles_y,
                    });
                    let mut entries = vec![
                        entry(0, &params),
                        entry(1, &c.base),
                        entry(2, &c.blocks),
                        entry(3, &c.masks),
                        entry(4, &slot.active_weights),
                        entry(5, &slot.active_slots),
                        entry(6, &slot.active_count),
                    ];
                    // `blend` writes f32 into `out`; `blend_packed` the wire format into
                    // `packed`, with the box and (q16r) the reference.
                    match &packing {
                        Some((q16, at, len)) => {
                            entries.push(entry(8, packed));
                            entries.push(entry(9, q16));
                            entries.push(wgpu::BindGroupEntry {
                                binding: 10,
                                resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                                    buffer: &slot.jobs,
                                    offset: *at,
                                    size: std::num::NonZeroU64::new(*len),
                                }),
                            });
                        }
                        None => entries.push(entry(7, out)),
                    }
                    let bg = bind(blend, &entries);
                    (bg, [groups, tiles_y, tiles_z])
                })
                .collect()
        };
        let pos_groups = blend_groups(&rig.positions, &slot.positions, &slot.packed_positions, 0);
        let nrm_groups = if spec.normals {
            blend_groups(&rig.normals, &slot.normals, &slot.packed_normals, 1)
        } else {
            Vec::new()
        };
        let skin_group = rig.skin.as_ref().map(|sk| {
            let tiles = rig.vertices.div_ceil(64);
            let x = tiles.clamp(1, 65_535);
            let params = self.uniform(&SkinParams {
                vertices: rig.vertices,
                jobs,
                bones: sk.bones,
                normals: u32::from(spec.normals && !rig.normals.is_empty()),
                row: x * 64,
                _pad: [0; 3],
            });
            let bones = wgpu::BufferBinding {
                buffer: &slot.bones,
                offset: r.bones.0,
                size: std::num::NonZeroU64::new(r.bones.1),
            };
            let bg = d.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("skin"),
                layout: &p.skin.get_bind_group_layout(0),
                entries: &[
                    entry(0, &params),
                    entry(1, &sk.influences),
                    wgpu::BindGroupEntry {
                        binding: 2,
                        resource: wgpu::BindingResource::Buffer(bones),
                    },
                    entry(3, &slot.positions),
                    entry(4, &slot.normals),
                ],
            });
            (bg, [x, jobs, tiles.div_ceil(x)])
        });
        let normal_groups = match (&rig.topology, spec.normals) {
            (Some(t), true) => {
                let params = self.uniform(&NormalParams {
                    vertices: rig.vertices,
                    triangles: t.n_triangles,
                    recomputed: t.n_recomputed,
                    jobs,
                });
                let face = bind(
                    &p.face,
                    &[
                        entry(0, &params),
                        entry(1, &slot.positions),
                        entry(2, &t.triangles),
                        entry(3, &slot.faces),
                    ],
                );
                let vertex = bind(
                    &p.vertex,
                    &[
                        entry(0, &params),
                        entry(4, &slot.faces),
                        entry(5, &t.recomputed),
                        entry(6, &t.incident_start),
                        entry(7, &t.incident),
                        entry(8, &slot.normals),
                    ],
                );
                Some((
                    face,
                    vertex,
                    t.n_triangles.div_ceil(64),
                    t.n_recomputed.div_ceil(64),
                ))
            }
            _ => None,
        };
        // 16-bit output: positions and normals packed by `pack_f16`, or by `pack_q16` with the
        // box's parameters for positions and the unit scale for normals; positions coded
        // against a reference by `pack_q16r` (the same words: two bytes a component).
        let count = jobs * rig.vertices * 3;
        let pairs = count.div_ceil(2);
        let (px, py) = {
            let x = pairs.div_ceil(64).clamp(1, 65_535);
            (x, pairs.div_ceil(x * 64).max(1))
        };
        let pack_uniform = |normals: bool| match spec.precision {
            Precision::Q16(b) => Some(self.uniform(&Q16PackParams::new(
                &crate::Q16Params::new(b, normals),
                count,
                px * 64,
                rig.vertices * 3,
            ))),
            Precision::F16 => Some(self.uniform(&PackParams {
                count,
                row: px * 64,
                _pad0: 0,
                _pad1: 0,
            })),
            Precision::F32 => None,
        };
        let pack_pipeline = match spec.precision {
            Precision::Q16(_) => &p.pack_q16,
            _ => &p.pack,
        };
        let mut pack_groups = Vec::new();
        let mut buffers = Vec::new();
        if !fused {
            buffers.push((false, &slot.positions, &slot.packed_positions));
        } else {
            // The blend or-s the halves that two invocations share into cleared words.
            let bytes = (u64::from(count) * 2).next_multiple_of(4);
            encoder.clear_buffer(&slot.packed_positions, 0, Some(bytes));
        }
        if spec.normals {
            buffers.push((true, &slot.normals, &slot.packed_normals));
        }
        for (normals, src, dst) in buffers {
            let Some(params) = pack_uniform(normals) else {
                continue;
            };
            let mut entries = vec![entry(0, &params), entry(1, src), entry(2, dst)];
            let pipeline = match r.reference {
                Some((at, len)) if !normals => {
                    entries.push(wgpu::BindGroupEntry {
                        binding: 3,
                        resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                            buffer: &slot.jobs,
                            offset: at,
                            size: std::num::NonZeroU64::new(len),
                        }),
                    });
                    &p.pack_q16r
                }
                _ => pack_pipeline,
            };
            pack_groups.push((pipeline, bind(pipeline, &entries)));
        }

        let timestamp_writes =
            slot.queries
                .as_ref()
                .map(|(qs, _, _)| wgpu::ComputePassTimestampWrites {
                    query_set: qs,
                    beginning_of_pass_write_index: Some(2 * k),
                    end_of_pass_write_index: Some(2 * k + 1),
                });
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("blend batch"),
            timestamp_writes,
        });
        pass.set_pipeline(&p.active);
        pass.set_bind_group(0, &active_bg, &[]);
        pass.dispatch_workgroups(groups, 1, 1);
        pass.set_pipeline(blend);
        for (bg, [x, y, z]) in pos_groups.iter().chain(&nrm_groups) {
            pass.set_bind_group(0, bg, &[]);
            pass.dispatch_workgroups(*x, *y, *z);
        }
        if let Some((bg, [x, y, z])) = &skin_group {
            pass.set_pipeline(&p.skin);
            pass.set_bind_group(0, bg, &[]);
            pass.dispatch_workgroups(*x, *y, *z);
        }
        if let Some((face, vertex, tx, vx)) = &normal_groups {
            pass.set_pipeline(&p.face);
            pass.set_bind_group(0, face, &[]);
            pass.dispatch_workgroups(*tx, jobs, 1);
            pass.set_pipeline(&p.vertex);
            pass.set_bind_group(0, vertex, &[]);
            pass.dispatch_workgroups(*vx, jobs, 1);
        }
        for (pipeline, bg) in &pack_groups {
            pass.set_pipeline(pipeline);
            pass.set_bind_group(0, bg, &[]);
            pass.dispatch_workgroups(px, py, 1);
        }
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
            if reuse && let Ok(mut pool) = self.ctx.pool.lock() {
                pool.push(slot);
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

/// What decides how a batch is cut into sub-batches ([`plan_batch`]).
#[derive(Clone, Copy, Debug)]
struct BatchCounts {
    /// Jobs in the batch.
    jobs: usize,
    /// Vertices per job.
    vertices: u64,
    /// The rig's LOD slots (the active lists hold eight weights per slot and group).
    slots: u32,
    /// Triangles whose face normals are recomputed (0: none are).
    triangles: u64,
    /// Bytes of one job's bone matrices (0 on a rig without a skeleton).
    bone_bytes: u64,
    /// Live weights uploaded with the batch.
    live: usize,
    /// Components of the residual reference, when positions are coded against one.
    reference: Option<usize>,
    /// Whether normals are read back too.
    normals: bool,
    /// Whether outputs are 16-bit (packed on the device).
    packed16: bool,
}

/// A batch's layout on the device: jobs per sub-batch, each sub-batch's [`Region`], where the
/// live weights and the reference follow the job records, and the staging and bone bytes.
#[derive(Debug, PartialEq)]
struct BatchPlan {
    /// Jobs per sub-batch (the last may hold fewer).
    sub: usize,
    /// One region per sub-batch, in job order.
    regions: Vec<Region>,
    /// Byte offset of the live weights in the jobs buffer.
    live_at: u64,
    /// Their bytes (at least one weight's).
    live_bytes: u64,
    /// Byte offset of the residual reference in the jobs buffer.
    reference_at: u64,
    /// Bytes of staging memory the read-back outputs take.
    staging: u64,
    /// Bytes of the bone matrices' buffer.
    bones_at: u64,
}

/// Cuts a batch into sub-batches that each fit one binding of `max_binding` bytes (outputs,
/// face normals, bone matrices, the active lists), in whole groups of eight jobs where that is
/// at least one group, and lays out each sub-batch's staging and bone ranges (bone ranges at
/// `align`, the device's storage offset alignment). A pure function of the counts, so that
/// the cut is tested without a device.
fn plan_batch(c: &BatchCounts, max_binding: u64, align: u64) -> BatchPlan {
    let n = c.jobs;
    let v = c.vertices;
    // The live weights follow the job records in the same buffer, at the first offset a
    // storage binding may start at.
    let live_at = ((n.max(1) * size_of::<GpuJob>()) as u64).next_multiple_of(align);
    let live_bytes = (c.live.max(1) * 4) as u64;
    // Then the residual reference, two q16 values a word.
    let reference_at = (live_at + live_bytes).next_multiple_of(align);
    let reference_range = c
        .reference
        .map(|r| (reference_at, (r as u64 * 2).next_multiple_of(4)));
    let per_job_out = v * 12;
    // Jobs per sub-batch: what one binding holds (outputs, face normals, bone matrices and
    // the active lists' eight weights per slot and group), in whole groups where that is at
    // least one group; a sub-batch may start mid-group, the passes do not mind.
    let mut sub = max_binding / per_job_out.max(1);
    sub = sub.min(max_binding / (u64::from(c.slots.max(1)) * 4));
    if c.triangles > 0 {
        sub = sub.min(max_binding / (c.triangles * 12));
    }
    if let Some(fit) = max_binding.checked_div(c.bone_bytes) {
        sub = sub.min(fit);
    }
    let sub = sub.min(65_535) as usize;
    let sub = if sub >= JOBS_PER_GROUP {
        sub / JOBS_PER_GROUP * JOBS_PER_GROUP
    } else {
        sub.max(1)
    };
    let subs = n.div_ceil(sub).max(1);
    let elem = if c.packed16 { 2 } else { 4 };
    let mut regions = Vec::with_capacity(subs);
    let mut staging = 0u64;
    let mut bones_at = 0u64;
    for k in 0..subs {
        let job = k * sub;
        let count = sub.min(n - job);
        let bytes = (count as u64 * v * 3 * elem).next_multiple_of(4);
        let positions = staging;
        staging += bytes;
        let normals = staging;
        if c.normals {
            staging += bytes;
        }
        let bones = (bones_at, (count as u64 * c.bone_bytes).max(16));
        bones_at = (bones_at + bones.1).next_multiple_of(align);
        regions.push(Region {
            job,
            jobs: count,
            positions,
            normals,
            live: (live_at, live_bytes),
            bones,
            reference: reference_range,
        });
    }
    BatchPlan {
        sub,
        regions,
        live_at,
        live_bytes,
        reference_at,
        staging,
        bones_at,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn counts(jobs: usize) -> BatchCounts {
        BatchCounts {
            jobs,
            vertices: 1000,
            slots: 51,
            triangles: 0,
            bone_bytes: 0,
            live: 0,
            reference: None,
            normals: false,
            packed16: false,
        }
    }

    /// Every job is in exactly one region, in order; the regions' staging ranges follow each
    /// other and each sub-batch's outputs fit one binding.
    fn check(c: &BatchCounts, max_binding: u64, align: u64) -> BatchPlan {
        let p = plan_batch(c, max_binding, align);
        let mut next_job = 0;
        let mut next_staging = 0;
        let elem = if c.packed16 { 2 } else { 4 };
        for r in &p.regions {
            assert_eq!(r.job, next_job, "{c:?}");
            assert!(r.jobs >= 1 && r.jobs <= p.sub);
            assert!(r.jobs as u64 * c.vertices * 12 <= max_binding.max(c.vertices * 12));
            assert_eq!(r.positions, next_staging);
            let bytes = (r.jobs as u64 * c.vertices * 3 * elem).next_multiple_of(4);
            next_staging = r.positions + bytes * if c.normals { 2 } else { 1 };
            assert_eq!(r.bones.0 % align, 0, "bone ranges start aligned");
            next_job += r.jobs;
        }
        assert_eq!(next_job, c.jobs);
        assert_eq!(p.staging, next_staging);
        assert_eq!(p.live_at % align, 0);
        assert_eq!(p.reference_at % align, 0);
        assert!(p.reference_at >= p.live_at + p.live_bytes);
        p
    }

    #[test]
    fn a_batch_that_fits_one_binding_is_one_sub_batch() {
        let p = check(&counts(100), 128 << 20, 256);
        assert_eq!(p.regions.len(), 1);
        assert_eq!(p.regions[0].jobs, 100);
        assert_eq!(p.staging, 100 * 1000 * 12);
    }

    #[test]
    fn a_batch_past_the_binding_is_cut_in_whole_groups() {
        // 12,000 bytes a job: a 1 MiB binding holds 87 jobs, cut to 80 (ten groups of eight).
        let p = check(&counts(1000), 1 << 20, 256);
        assert_eq!(p.sub, 80);
        assert_eq!(p.regions.len(), 13);
        assert_eq!(p.regions.last().map(|r| r.jobs), Some(1000 - 12 * 80));
        // 16-bit outputs with normals: half the bytes per output, two outputs each.
        let c = BatchCounts {
            packed16: true,
            normals: true,
            ..counts(1000)
        };
        let p = check(&c, 1 << 20, 256);
        assert_eq!(p.staging, 2 * (1000 * 1000 * 3 * 2));
    }

    #[test]
    fn face_normals_bones_and_small_bindings_bound_the_cut() {
        // Recomputed face normals of 50,000 triangles: 600,000 bytes a job, one job a binding.
        let c = BatchCounts {
            triangles: 50_000,
            ..counts(20)
        };
        let p = check(&c, 1 << 20, 256);
        assert_eq!((p.sub, p.regions.len()), (1, 20));
        // Bone matrices: each sub-batch's range aligned, and the buffer holds them all.
        let c = BatchCounts {
            bone_bytes: 5 * 48,
            ..counts(300)
        };
        let p = check(&c, 1 << 20, 256);
        let last = p.regions.last().expect("regions");
        assert!(p.bones_at >= last.bones.0 + last.bones.1);
        // A live row and a reference follow the job records, each at the alignment.
        let c = BatchCounts {
            live: 51 * 300,
            reference: Some(3000),
            ..counts(300)
        };
        let p = check(&c, 1 << 20, 256);
        assert_eq!(p.live_bytes, 51 * 300 * 4);
        assert_eq!(p.regions[0].reference, Some((p.reference_at, 6000)));
    }
}
