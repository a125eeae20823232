//! [`GpuContext`]: an open device with the engine's pipelines. Choosing the adapter
//! ([`GpuContext::open`], hardware first), or taking the caller's device
//! ([`GpuContext::from_device`]); the device memory budget and what may be reclaimed to make
//! room in it ([`GpuContext::charge`]); the pool of batch slots; and the buffer helpers every
//! upload and batch uses.
//!
//! Invariants: every input-sized buffer is charged through [`GpuContext::charge`] before it is
//! made, so that a full budget first frees what is kept only for reuse (idle slots, the
//! registered [`Reclaim`]ers); once the device is lost or reports an uncaptured error,
//! [`GpuContext::health`] fails for good and the engine falls back to the CPU.

use std::sync::{Arc, Mutex, Weak};

use super::device::{Health, buffer, padded};
use super::layout::DeltaFormat;
use super::pipelines::Pipelines;
use super::slot::{Slot, SlotNeeds, SlotPool};
use super::{
    GPU_MEMORY_FLAG, GpuError, GpuOptions, Reclaim, default_gpu_memory, discrete_gpu_memory,
};
use crowdmorph_core::budget::{BudgetError, Charge, MemoryPool};

/// An open device with the engine's pipelines.
pub struct GpuContext {
    pub(super) device: wgpu::Device,
    pub(super) queue: wgpu::Queue,
    adapter: wgpu::AdapterInfo,
    pub(super) pipelines: Pipelines,
    /// Nanoseconds per timestamp tick, when the device has timestamp queries.
    pub(super) timestamp_period: Option<f32>,
    pub(super) max_binding: u64,
    pub(super) max_chunk: u64,
    pub(super) max_buffer: u64,
    /// Bytes of a piece's staging and bone matrices: the largest buffer, or less
    /// ([`GpuOptions::max_piece_bytes`]).
    pub(super) max_piece: u64,
    pub(super) deltas: DeltaFormat,
    pub(super) health: Arc<Health>,
    /// Idle batch slots, for the next batches.
    pub(super) pool: SlotPool,
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
        let pipelines = Pipelines::new(&device, options.deltas);
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
            max_piece: options
                .max_piece_bytes
                .map_or(limits.max_buffer_size, |p| p.min(limits.max_buffer_size)),
            deltas: options.deltas,
            health,
            pool: SlotPool::default(),
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

    /// Bytes of the memory budget a batch may use now: what is free plus the idle slots (a
    /// charge that finds the budget full frees them first).
    pub(super) fn room(&self) -> u64 {
        let m = &self.memory;
        m.limit().saturating_sub(m.used()) + self.pool.idle_bytes()
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
        let mut freed = self.pool.free_idle();
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

    /// Whether GPU times are measured.
    pub fn has_timestamps(&self) -> bool {
        self.timestamp_period.is_some()
    }

    /// Err once the device is lost or has reported an error.
    pub fn health(&self) -> Result<(), GpuError> {
        self.health.check()
    }

    /// A buffer of `size` bytes ([`buffer`]).
    pub(super) fn buffer(&self, label: &str, size: u64, usage: wgpu::BufferUsages) -> wgpu::Buffer {
        buffer(&self.device, label, size, usage)
    }

    /// A buffer holding `bytes` (padded as [`padded`] says), written through the queue.
    pub(super) fn init(
        &self,
        label: &str,
        bytes: &[u8],
        usage: wgpu::BufferUsages,
    ) -> wgpu::Buffer {
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
    pub(super) fn init_bytes<T>(data: &[T]) -> u64 {
        padded(size_of_val(data) as u64)
    }

    /// A uniform buffer holding `value`.
    pub(super) fn uniform<T: bytemuck::Pod>(&self, value: &T) -> wgpu::Buffer {
        self.init(
            "params",
            bytemuck::bytes_of(value),
            wgpu::BufferUsages::UNIFORM,
        )
    }

    /// A pooled batch slot that serves `needs`, or a new one charged to the memory budget
    /// ([`SlotPool::take`]).
    pub(super) fn slot(&self, needs: SlotNeeds) -> Result<Slot, GpuError> {
        self.pool.take(needs, |n| {
            Slot::new(
                &self.device,
                self.timestamp_period.is_some(),
                n,
                |bytes, what| self.charge(bytes, what),
            )
        })
    }
}
