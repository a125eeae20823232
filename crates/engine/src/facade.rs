//! The engine the rest of the program talks to: one backend chosen at start, rigs prepared for
//! it, batches evaluated on it, and a fallback to the CPU engine when the GPU goes away.
//!
//! Every prepared rig keeps its CPU layout even when a GPU holds it too: the CPU engine is the
//! oracle, and it is what keeps the service answering (degraded) after a device loss or an
//! out-of-memory error, without losing any rig.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use serde::Serialize;

use super::cpu::CpuRig;
use super::gpu::{
    ClipTables, DeviceOutput, GpuContext, GpuError, GpuOptions, GpuRig, Pending, Readout,
};
use super::{
    BlendJob, BlendOutput, EngineError, OutputSpec, Precision, Q16Reference, WeightBatch,
    code_residuals,
};
use crowdmorph_core::rig::Rig;

/// Which engine to use, as asked on the command line.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum BackendChoice {
    /// A hardware GPU when there is one, else the CPU engine. Software adapters (llvmpipe,
    /// lavapipe) are never picked automatically: they are slower than the CPU engine.
    #[default]
    Auto,
    /// The CPU engine.
    Cpu,
    /// A GPU adapter, software ones included; an error when there is none.
    Gpu,
}

impl std::str::FromStr for BackendChoice {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s.to_ascii_lowercase().as_str() {
            "auto" => Ok(BackendChoice::Auto),
            "cpu" => Ok(BackendChoice::Cpu),
            "gpu" => Ok(BackendChoice::Gpu),
            other => Err(format!("unknown backend {other:?} (auto, cpu or gpu)")),
        }
    }
}

/// What kind of engine evaluates batches.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum BackendKind {
    /// The CPU engine.
    Cpu,
    /// A wgpu device.
    Gpu,
}

/// The chosen backend, for logs, `inspect`, `bench`, `/readyz` and metrics.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct BackendInfo {
    /// The engine in use now (CPU after a GPU fault).
    pub kind: BackendKind,
    /// The GPU adapter's name, when a GPU was chosen.
    pub adapter: Option<String>,
    /// The adapter's device type (discrete, integrated, cpu...), when a GPU was chosen.
    pub device_type: Option<String>,
    /// The CPU kernel family (avx512, avx2+fma, portable).
    pub cpu_isa: String,
    /// True when a GPU was in use and failed: the CPU engine answers instead.
    pub degraded: bool,
    /// Why the engine is degraded, when it is.
    pub degraded_reason: Option<String>,
}

/// Host and device memory a prepared rig occupies.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct RigMemory {
    /// Bytes of the rig's arrays plus the CPU engine's layout.
    pub host_bytes: usize,
    /// Bytes resident on the GPU (0 on the CPU backend).
    pub device_bytes: usize,
}

/// A rig ready for evaluation on the engine that prepared it.
#[derive(Clone)]
pub struct PreparedRig {
    rig: Arc<Rig>,
    cpu: Arc<CpuRig>,
    gpu: Option<Arc<GpuRig>>,
    memory: RigMemory,
    /// The rig's mesh levels (`rig.lod.meshes`), each prepared as the derived rig the engines
    /// evaluate: a job whose LOD level names mesh `m` runs on `meshes[m]`; then its PCA levels
    /// (`rig.lod.pca`): a level naming form `p` runs on `meshes[rig.lod.meshes.len() + p]`.
    meshes: Vec<PreparedRig>,
    /// For a PCA level's derived rig, its form: live weights become its coefficients.
    pca: Option<Arc<crowdmorph_core::rig::DeltaPca>>,
}

impl std::fmt::Debug for PreparedRig {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PreparedRig")
            .field("rig", &self.rig.name)
            .field("memory", &self.memory)
            .finish()
    }
}

impl PreparedRig {
    /// The rig.
    pub fn rig(&self) -> &Arc<Rig> {
        &self.rig
    }

    /// Memory it occupies.
    pub fn memory(&self) -> RigMemory {
        self.memory
    }

    /// The CPU engine's layout of this rig.
    pub fn cpu(&self) -> &CpuRig {
        &self.cpu
    }

    /// The rig's resident GPU data, when it is on a GPU.
    pub fn gpu(&self) -> Option<&GpuRig> {
        self.gpu.as_deref()
    }

    /// Which of [`PreparedRig::mesh_levels`] LOD level `lod` evaluates (`None`: this rig, or
    /// no such level): its mesh level, else its PCA level, which comes after them.
    pub fn mesh_of(&self, lod: u32) -> Option<usize> {
        let l = self.rig.lod.levels.get(lod as usize)?;
        l.mesh
            .map(|m| m as usize)
            .or_else(|| l.pca.map(|p| self.rig.lod.meshes.len() + p as usize))
    }

    /// What jobs at LOD level `lod` are evaluated on: this rig, or one of its mesh levels.
    pub fn at_level(&self, lod: u32) -> &PreparedRig {
        self.mesh_of(lod)
            .and_then(|m| self.meshes.get(m))
            .unwrap_or(self)
    }

    /// The prepared mesh levels, in `rig.lod.meshes` order, then the PCA levels (same
    /// vertices and triangles as this rig).
    pub fn mesh_levels(&self) -> &[PreparedRig] {
        &self.meshes
    }

    /// The reference `q16r` residuals of this rig (or level: [`PreparedRig::at_level`]) are
    /// coded against in box `b`: its q16 positions with every weight 0, computed by the CPU
    /// engine (the neutral, quantized as any q16 output is, which the GPU reproduces; a client
    /// fetches it as that frame).
    pub fn q16_reference(&self, b: super::Quantization) -> Result<Vec<i16>, EngineError> {
        let zero = [vec![0f32; self.rig.targets.len()]];
        let batch = WeightBatch::from_target_weights(&self.rig, &zero, 0)?;
        let spec = OutputSpec {
            normals: false,
            precision: Precision::Q16(b),
        };
        match self.cpu.evaluate(&batch, spec)?.positions {
            super::VertexData::Q16(r, _) => Ok(r),
            _ => Err(EngineError::Residuals(
                "the CPU engine's q16 reference is not q16".into(),
            )),
        }
    }

    /// Checks every job and picks the rig they run on, with the jobs as that rig reads them
    /// (a PCA level's rig takes live weights as its coefficients); all must share one level.
    fn route<'j>(
        &self,
        jobs: &'j [BlendJob],
    ) -> Result<(&PreparedRig, std::borrow::Cow<'j, [BlendJob]>), EngineError> {
        let target = self.route_rig(jobs)?;
        let Some(form) = &target.pca else {
            return Ok((target, std::borrow::Cow::Borrowed(jobs)));
        };
        let mapped = jobs
            .iter()
            .map(|j| match &j.pose {
                crowdmorph_core::rig::Pose::Live(_) => {
                    let w: Vec<f32> = (0..self.rig.targets.len())
                        .map(|t| j.pose.weight(&self.rig, t))
                        .collect();
                    BlendJob {
                        pose: crowdmorph_core::rig::Pose::live(&form.coefficients(&w)),
                        lod: j.lod,
                        joints: j.joints.clone(),
                    }
                }
                _ => j.clone(),
            })
            .collect();
        Ok((target, std::borrow::Cow::Owned(mapped)))
    }

    /// [`PreparedRig::route`]'s choice of rig.
    fn route_rig(&self, jobs: &[BlendJob]) -> Result<&PreparedRig, EngineError> {
        for j in jobs {
            j.check(&self.rig)?;
        }
        let mut mesh = None;
        for (i, j) in jobs.iter().enumerate() {
            let m = self.mesh_of(j.lod);
            if i > 0 && m != mesh {
                return Err(EngineError::MixedMeshLevels);
            }
            mesh = m;
        }
        Ok(match mesh {
            Some(m) => self.meshes.get(m).ok_or_else(|| {
                EngineError::Mesh(format!("LOD names mesh level {m}, which is not prepared"))
            })?,
            None => self,
        })
    }
}

/// Where [`Engine::evaluate_for_render`] left a batch's positions and normals.
#[derive(Debug)]
pub enum RenderBuffers {
    /// Host arrays (the CPU engine, or a degraded GPU engine).
    Host(BlendOutput),
    /// Buffers on the engine's GPU device.
    Device(DeviceOutput),
}

impl RenderBuffers {
    /// How many jobs the buffers hold.
    pub fn jobs(&self) -> usize {
        match self {
            RenderBuffers::Host(h) => h.jobs,
            RenderBuffers::Device(d) => d.jobs,
        }
    }
}

/// Times of one evaluation.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Timings {
    /// Wall time from the call to the result in host memory (the paper's CPU round trip).
    pub wall_ns: u64,
    /// Time the GPU spent on the batch's passes, from timestamp queries (GPU backend only).
    pub gpu_ns: Option<u64>,
    /// Host time after the GPU's results were mapped: copying them into host arrays and
    /// encoding what the device did not (GPU backend only).
    pub host_ns: Option<u64>,
    /// Pieces the GPU staged and read the batch back in: 1 unless it exceeded the device's
    /// largest buffer or the memory budget's room (GPU backend only).
    pub pieces: Option<usize>,
}

/// A batch result with its timings.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Evaluation {
    /// The blended buffers.
    pub output: BlendOutput,
    /// How long it took.
    pub timings: Timings,
    /// Which engine computed it.
    pub kind: Option<BackendKind>,
}

/// The engine: a backend plus the fallback logic.
pub struct Engine {
    choice: BackendChoice,
    gpu: Option<Arc<GpuContext>>,
    degraded: AtomicBool,
    degraded_reason: std::sync::Mutex<Option<String>>,
    fallbacks: Fallbacks,
}

/// Batches a healthy GPU engine ran on the CPU because the device's memory budget was full:
/// counted for `/metrics`, and warned about at most once per [`Fallbacks::WARN_EVERY`] (a CPU
/// batch is about a hundred times slower on a big device, so an operator must hear of it, but
/// a log line per batch would flood the log).
#[derive(Default)]
struct Fallbacks {
    count: std::sync::atomic::AtomicU64,
    /// When the last WARN was written, and the count then.
    warned: std::sync::Mutex<Option<(Instant, u64)>>,
}

impl Fallbacks {
    const WARN_EVERY: std::time::Duration = std::time::Duration::from_secs(10);

    fn record(&self, what: &str, e: &crowdmorph_core::budget::BudgetError) {
        let n = self.count.fetch_add(1, Ordering::Relaxed) + 1;
        let Ok(mut w) = self.warned.lock() else {
            return;
        };
        let (since, before) = match *w {
            Some((t, _)) if t.elapsed() < Self::WARN_EVERY => return,
            Some((t, c)) => (Some(t.elapsed()), c),
            None => (None, 0),
        };
        *w = Some((Instant::now(), n));
        drop(w);
        tracing::warn!(
            fallbacks = n - before,
            seconds = since.map(|d| d.as_secs()),
            error = %e,
            "GPU memory budget full: {what} ran on the CPU engine (raise --max-gpu-memory; \
             crowdmorph_gpu_fallbacks_total counts them)"
        );
    }
}

impl std::fmt::Debug for Engine {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Engine")
            .field("info", &self.info())
            .finish()
    }
}

fn gpu_to_engine(e: GpuError) -> EngineError {
    match e {
        GpuError::DoesNotFit(m) | GpuError::OutOfMemory(m) => EngineError::DoesNotFit(m),
        GpuError::Memory(b) => EngineError::GpuMemory(b),
        other => EngineError::NoGpu(other.to_string()),
    }
}

/// An evaluation started by [`Engine::begin`]: a submitted GPU batch, or nothing yet (the
/// CPU engine works in [`Engine::finish_into`]).
pub struct Begun<'a> {
    start: Instant,
    gpu: Option<PendingEvaluation<'a>>,
    /// What the CPU engine codes the positions against (the GPU batch carries its own).
    reference: Option<Q16Reference>,
}

/// A batch submitted with [`Engine::submit`], not yet collected.
pub struct PendingEvaluation<'a> {
    engine: &'a Engine,
    rig: PreparedRig,
    jobs: Vec<BlendJob>,
    spec: OutputSpec,
    /// Positions coded as residual planes against this: by the device on a GPU batch, on the
    /// host where the batch ran on the CPU.
    reference: Option<Q16Reference>,
    start: Instant,
    state: PendingState<'a>,
}

enum PendingState<'a> {
    Gpu(Box<Pending<'a>>),
    Ready(Result<Evaluation, EngineError>),
}

impl PendingEvaluation<'_> {
    /// Waits for the batch. A GPU fault while it ran degrades the engine and the batch is
    /// computed on the CPU instead, so the caller still gets a correct result.
    pub fn wait(self) -> Result<Evaluation, EngineError> {
        let mut output = BlendOutput::default();
        let (timings, kind) = self.wait_into(&mut output)?;
        Ok(Evaluation {
            output,
            timings,
            kind: Some(kind),
        })
    }

    /// Waits for the batch and writes its buffers into `out`, reusing `out`'s arrays where
    /// they fit (a GPU batch is copied out of its mapped staging memory on every core; the
    /// device already wrote f16 and q16). A GPU fault degrades the engine and the batch is
    /// computed on the CPU into `out` instead.
    pub fn wait_into(self, out: &mut BlendOutput) -> Result<(Timings, BackendKind), EngineError> {
        let on_cpu = |e: Evaluation, out: &mut BlendOutput| {
            *out = e.output;
            if let Some(r) = &self.reference {
                code_residuals(&mut out.positions, r)?;
            }
            Ok((e.timings, e.kind.unwrap_or(BackendKind::Cpu)))
        };
        match self.state {
            PendingState::Ready(r) => on_cpu(r?, out),
            PendingState::Gpu(pending) => match pending.wait_into(out) {
                Ok(r) => {
                    // Anything the device did not encode (it encodes every format and codes
                    // residuals today) is encoded here with the CPU kernels' arithmetic.
                    let encode = Instant::now();
                    out.encode_as(self.spec);
                    Ok((
                        Timings {
                            wall_ns: self.start.elapsed().as_nanos() as u64,
                            gpu_ns: r.gpu_ns,
                            host_ns: Some(r.host_ns + encode.elapsed().as_nanos() as u64),
                            pieces: Some(r.pieces),
                        },
                        BackendKind::Gpu,
                    ))
                }
                Err(e) => {
                    // A later piece of a batch cut in pieces may find the memory budget full
                    // (the device is fine); anything else is a fault.
                    match &e {
                        GpuError::Memory(b) => self.engine.fallbacks.record("a batch", b),
                        _ => self.engine.degrade(&e),
                    }
                    let e = self
                        .engine
                        .evaluate_cpu(&self.rig, &self.jobs, self.spec, self.start)?;
                    on_cpu(e, out)
                }
            },
        }
    }
}

impl Engine {
    /// Batches (and renders' jobs) a healthy GPU engine ran on the CPU because the device's
    /// memory budget was full, since the engine started.
    pub fn cpu_fallbacks(&self) -> u64 {
        self.fallbacks.count.load(Ordering::Relaxed)
    }

    /// The CPU engine.
    pub fn cpu() -> Engine {
        Engine {
            choice: BackendChoice::Cpu,
            gpu: None,
            degraded: AtomicBool::new(false),
            degraded_reason: std::sync::Mutex::new(None),
            fallbacks: Fallbacks::default(),
        }
    }

    /// Creates the engine for `choice`. `Gpu` fails when no adapter can be opened; `Auto`
    /// uses a hardware adapter when there is one and the CPU engine otherwise.
    pub fn new(choice: BackendChoice) -> Result<Engine, EngineError> {
        Engine::with_options(choice, GpuOptions::default())
    }

    /// [`Engine::new`] with the GPU context's options (the server's `--max-gpu-memory`).
    pub fn with_options(choice: BackendChoice, options: GpuOptions) -> Result<Engine, EngineError> {
        match choice {
            BackendChoice::Cpu => Ok(Engine::cpu()),
            BackendChoice::Auto => match GpuContext::open(false, options) {
                Ok(ctx) => Ok(Engine::with_gpu(ctx, BackendChoice::Auto)),
                Err(e) => {
                    tracing::info!(reason = %e, "no hardware GPU; using the CPU engine");
                    Ok(Engine::cpu())
                }
            },
            BackendChoice::Gpu => GpuContext::open(true, options)
                .map(|ctx| Engine::with_gpu(ctx, BackendChoice::Gpu))
                .map_err(|e| EngineError::NoGpu(e.to_string())),
        }
    }

    /// An engine on a GPU context the caller opened (tests inject their own device).
    pub fn with_gpu(ctx: GpuContext, choice: BackendChoice) -> Engine {
        let a = ctx.adapter();
        tracing::info!(adapter = %a.name, backend = ?a.backend, device_type = ?a.device_type, "GPU engine");
        Engine {
            choice,
            gpu: Some(Arc::new(ctx)),
            degraded: AtomicBool::new(false),
            degraded_reason: std::sync::Mutex::new(None),
            fallbacks: Fallbacks::default(),
        }
    }

    /// The GPU context, when a GPU was chosen (even if it has since failed).
    pub fn gpu(&self) -> Option<&GpuContext> {
        self.gpu.as_deref()
    }

    /// The GPU context, shared: a renderer on the same device reads the engine's outputs
    /// where they are.
    pub fn gpu_shared(&self) -> Option<Arc<GpuContext>> {
        self.gpu.clone()
    }

    /// The GPU's memory budget (`--max-gpu-memory`), while the GPU engine is in use.
    pub fn gpu_memory(&self) -> Option<&Arc<crowdmorph_core::budget::MemoryPool>> {
        self.gpu_active().map(GpuContext::memory)
    }

    /// The GPU context while it is healthy.
    fn gpu_active(&self) -> Option<&GpuContext> {
        if self.degraded.load(Ordering::SeqCst) {
            return None;
        }
        self.gpu.as_deref()
    }

    /// Switches to the CPU engine for good after a GPU fault, keeping every rig.
    fn degrade(&self, e: &GpuError) {
        if !self.degraded.swap(true, Ordering::SeqCst) {
            tracing::error!(error = %e, "GPU engine failed; continuing on the CPU engine (degraded)");
            if let Ok(mut r) = self.degraded_reason.lock() {
                *r = Some(e.to_string());
            }
        }
    }

    /// What the engine is running on.
    pub fn info(&self) -> BackendInfo {
        let degraded = self.degraded.load(Ordering::SeqCst);
        let adapter = self.gpu.as_deref().map(|g| g.adapter());
        BackendInfo {
            kind: if self.gpu.is_some() && !degraded {
                BackendKind::Gpu
            } else {
                BackendKind::Cpu
            },
            adapter: adapter.map(|a| format!("{} ({:?})", a.name, a.backend)),
            device_type: adapter.map(|a| format!("{:?}", a.device_type)),
            cpu_isa: super::cpu::Isa::detect().name().to_string(),
            degraded,
            degraded_reason: self
                .degraded_reason
                .lock()
                .map(|r| r.clone())
                .unwrap_or(None),
        }
    }

    /// The backend that was asked for.
    pub fn choice(&self) -> BackendChoice {
        self.choice
    }

    /// Memory of a prepared rig. Mesh levels share the full rig's clip tables (host and
    /// device), so only their geometry and layouts count; a PCA level has clip tables of its
    /// own (in coefficients), so all of it counts.
    fn memory(rig: &Rig, cpu: &CpuRig, gpu: Option<&GpuRig>, meshes: &[PreparedRig]) -> RigMemory {
        let level = |m: &PreparedRig| match m.pca {
            Some(_) => m.memory,
            None => RigMemory {
                host_bytes: m.rig.geometry_bytes() + m.cpu.bytes(),
                device_bytes: m.gpu.as_ref().map_or(0, |g| g.geometry_bytes() as usize),
            },
        };
        let mut memory = RigMemory {
            host_bytes: rig.host_bytes() + cpu.bytes(),
            device_bytes: gpu.map_or(0, |g| g.device_bytes() as usize),
        };
        for m in meshes.iter().map(level) {
            memory.host_bytes += m.host_bytes;
            memory.device_bytes += m.device_bytes;
        }
        memory
    }

    /// The outcome of putting something on the GPU: what the device cannot hold is refused
    /// (the caller's error); any other failure is a device fault, which degrades the engine
    /// and leaves the rig host-side only.
    fn resident<T>(&self, r: Result<T, GpuError>) -> Result<Option<T>, EngineError> {
        match r {
            Ok(g) => Ok(Some(g)),
            Err(e @ (GpuError::DoesNotFit(_) | GpuError::OutOfMemory(_) | GpuError::Memory(_))) => {
                Err(gpu_to_engine(e))
            }
            Err(e) => {
                self.degrade(&e);
                Ok(None)
            }
        }
    }

    /// Prepares one rig (a full rig or a mesh level's derived rig) with the given resident
    /// clip tables, without mesh levels of its own.
    fn prepare_one(
        &self,
        rig: Arc<Rig>,
        tables: Option<&Arc<ClipTables>>,
    ) -> Result<PreparedRig, EngineError> {
        let cpu = Arc::new(CpuRig::new(&rig));
        let gpu = match (self.gpu_active(), tables) {
            (Some(ctx), Some(t)) => self
                .resident(GpuRig::upload(ctx, &rig, t.clone()))?
                .map(Arc::new),
            _ => None,
        };
        let memory = Self::memory(&rig, &cpu, gpu.as_deref(), &[]);
        Ok(PreparedRig {
            rig,
            cpu,
            gpu,
            memory,
            meshes: Vec::new(),
            pca: None,
        })
    }

    /// Prepares a rig: builds the CPU layout and, on a GPU, uploads geometry, deltas, clip
    /// tables and LOD order; the same for each of its mesh levels, which share its clip
    /// tables. A rig the GPU cannot hold is refused with `DoesNotFit`.
    pub fn prepare(&self, rig: Arc<Rig>) -> Result<PreparedRig, EngineError> {
        let derived = crowdmorph_core::rig::mesh_level_rigs(&rig)
            .map_err(|e| EngineError::Mesh(e.to_string()))?;
        let gpu = self.gpu_active();
        // The geometry is checked before the clip tables go up, so a rig the device cannot
        // hold is refused for what it is.
        let tables = match gpu {
            Some(ctx) => {
                self.resident(GpuRig::check_fits(ctx, &rig))?;
                self.resident(ClipTables::upload(ctx, &rig))?
            }
            None => None,
        };
        let mut meshes = derived
            .into_iter()
            .map(|d| self.prepare_one(Arc::new(d), tables.as_ref()))
            .collect::<Result<Vec<_>, _>>()?;
        // PCA levels: their own rigs, with their own (coefficient) clip tables.
        let pcas = crowdmorph_core::rig::pca_level_rigs(&rig)
            .map_err(|e| EngineError::Mesh(e.to_string()))?;
        for (form, derived) in rig.lod.pca.iter().zip(pcas) {
            let derived = Arc::new(derived);
            let own = match gpu {
                Some(ctx) => self.resident(ClipTables::upload(ctx, &derived))?,
                None => None,
            };
            let mut level = self.prepare_one(derived, own.as_ref())?;
            level.pca = Some(Arc::new(form.clone()));
            meshes.push(level);
        }
        let mut full = self.prepare_one(rig, tables.as_ref())?;
        full.memory = Self::memory(&full.rig, &full.cpu, full.gpu.as_deref(), &meshes);
        full.meshes = meshes;
        Ok(full)
    }

    /// Re-prepares after the rig's clips changed (the geometry and LOD are unchanged), so
    /// only the clip tables are uploaded; the geometry, the layouts and the mesh levels'
    /// geometry are shared with `prepared`.
    pub fn update_clips(
        &self,
        prepared: &PreparedRig,
        rig: Arc<Rig>,
    ) -> Result<PreparedRig, EngineError> {
        let same_geometry = Arc::ptr_eq(&rig.primitives, &prepared.rig.primitives)
            || rig.primitives == prepared.rig.primitives;
        if rig.lod != prepared.rig.lod || !same_geometry {
            return self.prepare(rig);
        }
        let upload = |r: &Rig| match (self.gpu_active(), &prepared.gpu) {
            (Some(ctx), Some(_)) => self.resident(ClipTables::upload(ctx, r)),
            _ => Ok(None),
        };
        let tables = upload(&rig)?;
        let with_clips = |old: &PreparedRig,
                          rig: Arc<Rig>,
                          tables: &Option<Arc<ClipTables>>|
         -> Result<PreparedRig, EngineError> {
            let gpu = match (self.gpu_active(), &old.gpu, tables) {
                (Some(ctx), Some(g), Some(t)) => {
                    self.resident(g.with_clips(ctx, t.clone()))?.map(Arc::new)
                }
                _ => None,
            };
            Ok(PreparedRig {
                memory: Self::memory(&rig, &old.cpu, gpu.as_deref(), &[]),
                rig,
                cpu: old.cpu.clone(),
                gpu,
                meshes: Vec::new(),
                pca: old.pca.clone(),
            })
        };
        // Mesh levels evaluate the same clips: each gets the new (shared) tables, and keeps
        // its geometry, which a clip change does not touch. A PCA level keeps its geometry too;
        // its tables are the new clips mapped into its coefficients, its own.
        let meshes = prepared
            .meshes
            .iter()
            .map(|old| match &old.pca {
                None => {
                    // The appearance too: a clip's animated texture comes with its clips.
                    let level = Rig {
                        clips: rig.clips.clone(),
                        appearance: rig.appearance.clone(),
                        ..(*old.rig).clone()
                    };
                    with_clips(old, Arc::new(level), &tables)
                }
                Some(form) => {
                    let level = Rig {
                        clips: form
                            .map_clips(&rig.clips)
                            .map_err(|e| EngineError::Mesh(e.to_string()))?,
                        appearance: rig.appearance.clone(),
                        ..(*old.rig).clone()
                    };
                    let own = upload(&level)?;
                    with_clips(old, Arc::new(level), &own)
                }
            })
            .collect::<Result<Vec<_>, _>>()?;
        let mut full = with_clips(prepared, rig, &tables)?;
        full.memory = Self::memory(&full.rig, &full.cpu, full.gpu.as_deref(), &meshes);
        full.meshes = meshes;
        Ok(full)
    }

    fn evaluate_cpu(
        &self,
        rig: &PreparedRig,
        jobs: &[BlendJob],
        spec: OutputSpec,
        start: Instant,
    ) -> Result<Evaluation, EngineError> {
        let batch = WeightBatch::gather(&rig.rig, jobs)?;
        let output = rig.cpu.evaluate(&batch, spec)?;
        Ok(Evaluation {
            output,
            timings: Timings {
                wall_ns: start.elapsed().as_nanos() as u64,
                gpu_ns: None,
                host_ns: None,
                pieces: None,
            },
            kind: Some(BackendKind::Cpu),
        })
    }

    /// Starts a batch of unique jobs of one rig. On a GPU the call returns once the batch is
    /// submitted, so the caller can prepare and submit the next one while this one runs;
    /// without `readback` the results stay on the device. On the CPU it computes right away.
    pub fn submit(
        &self,
        rig: &PreparedRig,
        jobs: &[BlendJob],
        spec: OutputSpec,
        readback: bool,
    ) -> Result<PendingEvaluation<'_>, EngineError> {
        self.submit_coded(rig, jobs, spec, readback, None)
    }

    /// [`Engine::submit`], the q16 positions read back coded as residual planes against
    /// `reference` where there is one (wire format `q16r`; the device codes them, or the host
    /// where the batch runs on the CPU).
    pub fn submit_coded(
        &self,
        rig: &PreparedRig,
        jobs: &[BlendJob],
        spec: OutputSpec,
        readback: bool,
        reference: Option<Q16Reference>,
    ) -> Result<PendingEvaluation<'_>, EngineError> {
        let start = Instant::now();
        let (rig, jobs) = rig.route(jobs)?;
        let jobs: &[BlendJob] = &jobs;
        if let Some(r) = &reference {
            check_reference(&rig.rig, spec, readback, r)?;
        }
        let readout = match (&reference, readback) {
            (_, false) => Readout::Device,
            (None, true) => Readout::Host,
            (Some(r), true) => Readout::Residuals(r),
        };
        let state = match (self.gpu_active(), &rig.gpu) {
            (Some(ctx), Some(g)) => {
                let (gpu_jobs, live, bones) = gpu_records(&rig.rig, g, jobs)?;
                match ctx.submit(g, &gpu_jobs, &live, &bones, spec, readout) {
                    Ok(p) => PendingState::Gpu(Box::new(p)),
                    Err(e @ GpuError::DoesNotFit(_)) => return Err(gpu_to_engine(e)),
                    // The device's memory budget is full now: this batch runs on the CPU,
                    // which holds every rig too; the device is fine.
                    Err(GpuError::Memory(e)) => {
                        self.fallbacks.record("a batch", &e);
                        PendingState::Ready(self.evaluate_cpu(rig, jobs, spec, start))
                    }
                    Err(e) => {
                        self.degrade(&e);
                        PendingState::Ready(self.evaluate_cpu(rig, jobs, spec, start))
                    }
                }
            }
            _ => PendingState::Ready(self.evaluate_cpu(rig, jobs, spec, start)),
        };
        Ok(PendingEvaluation {
            engine: self,
            rig: rig.clone(),
            jobs: jobs.to_vec(),
            spec,
            reference,
            start,
            state,
        })
    }

    /// Evaluates unique jobs of one rig into `out`, reusing its buffers on the CPU engine (a
    /// warm buffer saves the page faults of a fresh one, which cost as much as the blend for
    /// large batches). All jobs must share one mesh level; the output has that level's
    /// vertices. [`Engine::begin`] then [`Engine::finish_into`], back to back.
    pub fn evaluate_into(
        &self,
        rig: &PreparedRig,
        jobs: &[BlendJob],
        spec: OutputSpec,
        out: &mut BlendOutput,
    ) -> Result<(Timings, BackendKind), EngineError> {
        let begun = self.begin(rig, jobs, spec, None)?;
        self.finish_into(begun, rig, jobs, spec, out)
    }

    /// Starts an evaluation for [`Engine::finish_into`]: on the GPU the batch is submitted
    /// now and computes while the caller does other work (finishes an earlier batch, begins
    /// another rig's), which is how the server overlaps consecutive batches; the CPU engine
    /// does all its work in `finish_into`. With a `reference`, the q16 positions come out
    /// coded as residual planes against it (wire format `q16r`), on the device or the host.
    pub fn begin(
        &self,
        rig: &PreparedRig,
        jobs: &[BlendJob],
        spec: OutputSpec,
        reference: Option<Q16Reference>,
    ) -> Result<Begun<'_>, EngineError> {
        let start = Instant::now();
        // Only which rig: `submit` maps the jobs for it.
        let target = rig.route_rig(jobs)?;
        if self.gpu_active().is_some() && target.gpu.is_some() {
            return Ok(Begun {
                start,
                gpu: Some(self.submit_coded(rig, jobs, spec, true, reference)?),
                reference: None,
            });
        }
        if let Some(r) = &reference {
            check_reference(&target.rig, spec, true, r)?;
        }
        Ok(Begun {
            start,
            gpu: None,
            reference,
        })
    }

    /// Completes what [`Engine::begin`] started (with the same rig, jobs and spec) into
    /// `out`.
    pub fn finish_into(
        &self,
        begun: Begun<'_>,
        rig: &PreparedRig,
        jobs: &[BlendJob],
        spec: OutputSpec,
        out: &mut BlendOutput,
    ) -> Result<(Timings, BackendKind), EngineError> {
        if let Some(pending) = begun.gpu {
            return pending.wait_into(out);
        }
        let (target, jobs) = rig.route(jobs)?;
        let batch = WeightBatch::gather(&target.rig, &jobs)?;
        target.cpu.evaluate_into(&batch, spec, out)?;
        if let Some(r) = &begun.reference {
            code_residuals(&mut out.positions, r)?;
        }
        Ok((
            Timings {
                wall_ns: begun.start.elapsed().as_nanos() as u64,
                gpu_ns: None,
                host_ns: None,
                pieces: None,
            },
            BackendKind::Cpu,
        ))
    }

    /// Evaluates unique jobs of one rig for drawing: positions and unit normals in f32. On a
    /// healthy GPU they stay on the device ([`RenderBuffers::Device`], for a renderer sharing
    /// the engine's device); otherwise they are host arrays. A GPU fault degrades the engine
    /// and the jobs are computed on the CPU, as for every other evaluation.
    pub fn evaluate_for_render(
        &self,
        rig: &PreparedRig,
        jobs: &[BlendJob],
    ) -> Result<(RenderBuffers, Timings), EngineError> {
        let start = Instant::now();
        let spec = OutputSpec {
            normals: true,
            precision: Precision::F32,
        };
        let (target, jobs) = rig.route(jobs)?;
        let jobs: &[BlendJob] = &jobs;
        if let (Some(ctx), Some(g)) = (self.gpu_active(), &target.gpu) {
            let (gpu_jobs, live, bones) = gpu_records(&target.rig, g, jobs)?;
            match ctx
                .submit(g, &gpu_jobs, &live, &bones, spec, Readout::Device)
                .and_then(|p| {
                    let pieces = p.pieces();
                    Pending::wait_resident(p).map(|(out, gpu_ns)| (out, gpu_ns, pieces))
                }) {
                Ok((out, gpu_ns, pieces)) => {
                    let timings = Timings {
                        wall_ns: start.elapsed().as_nanos() as u64,
                        gpu_ns,
                        host_ns: None,
                        pieces: Some(pieces),
                    };
                    return Ok((RenderBuffers::Device(out), timings));
                }
                Err(e @ GpuError::DoesNotFit(_)) => return Err(gpu_to_engine(e)),
                // The device's memory budget is full now: these jobs are evaluated on the CPU
                // and drawn from host arrays; the device is fine.
                Err(GpuError::Memory(e)) => self.fallbacks.record("a render's jobs", &e),
                Err(e) => self.degrade(&e),
            }
        }
        let e = self.evaluate_cpu(target, jobs, spec, start)?;
        Ok((RenderBuffers::Host(e.output), e.timings))
    }

    /// Evaluates unique jobs of one rig and returns the buffers.
    pub fn evaluate(
        &self,
        rig: &PreparedRig,
        jobs: &[BlendJob],
        spec: OutputSpec,
    ) -> Result<Evaluation, EngineError> {
        self.submit(rig, jobs, spec, true)?.wait()
    }
}

/// Refuses residual coding that cannot be done: only read-back q16 positions are coded, and
/// the reference must be one job's components of `rig`.
fn check_reference(
    rig: &Rig,
    spec: OutputSpec,
    readback: bool,
    reference: &[i16],
) -> Result<(), EngineError> {
    let per_job = rig.vertex_count() * 3;
    if !readback || !matches!(spec.precision, Precision::Q16(_)) {
        return Err(EngineError::Residuals(format!(
            "{} outputs {} are not coded",
            spec.precision.name(),
            if readback {
                "read back"
            } else {
                "left on the device"
            }
        )));
    }
    if per_job == 0 {
        return Err(EngineError::Residuals("a rig without vertices".into()));
    }
    if reference.len() != per_job {
        return Err(EngineError::Residuals(format!(
            "a reference of {} components for jobs of {per_job}",
            reference.len()
        )));
    }
    Ok(())
}

/// The GPU records of `jobs`, the live weights they point at and, on a skinned rig, each job's
/// bone matrices; each job checked against the rig first so that a bad one is the same error
/// on both engines.
#[allow(clippy::type_complexity)]
fn gpu_records(
    rig: &Rig,
    g: &GpuRig,
    jobs: &[BlendJob],
) -> Result<
    (
        Vec<crate::gpu::layout::GpuJob>,
        Vec<f32>,
        Vec<crowdmorph_core::rig::BoneMatrix>,
    ),
    EngineError,
> {
    let mut live = Vec::new();
    let mut records = Vec::with_capacity(jobs.len());
    for job in jobs {
        job.check(rig)?;
        let record = g.job(job, &mut live).ok_or_else(|| {
            EngineError::Mesh(format!(
                "the GPU copy of the rig does not match job {job:?}"
            ))
        })?;
        records.push(record);
    }
    let bones = if g.bones() > 0 {
        super::bone_matrices(rig, jobs)?
    } else {
        Vec::new()
    };
    Ok((records, live, bones))
}
