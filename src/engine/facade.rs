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
use super::{BlendJob, BlendOutput, EngineError, OutputSpec, WeightBatch};
use crate::rig::Rig;

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
    memory: RigMemory,
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
}

/// Times of one evaluation.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Timings {
    /// Wall time from the call to the result in host memory (the paper's CPU round trip).
    pub wall_ns: u64,
    /// Time the GPU spent on the batch's passes, from timestamp queries (GPU backend only).
    pub gpu_ns: Option<u64>,
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
    degraded: AtomicBool,
    degraded_reason: std::sync::Mutex<Option<String>>,
}

impl std::fmt::Debug for Engine {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Engine")
            .field("info", &self.info())
            .finish()
    }
}

impl Engine {
    /// The CPU engine.
    pub fn cpu() -> Engine {
        Engine {
            choice: BackendChoice::Cpu,
            degraded: AtomicBool::new(false),
            degraded_reason: std::sync::Mutex::new(None),
        }
    }

    /// Creates the engine for `choice`. `Gpu` fails when no adapter can be opened; `Auto`
    /// falls back to the CPU engine (and says so in the log).
    pub fn new(choice: BackendChoice) -> Result<Engine, EngineError> {
        match choice {
            BackendChoice::Cpu | BackendChoice::Auto => Ok(Engine::cpu()),
            BackendChoice::Gpu => Err(EngineError::NoGpu("the GPU engine is not built yet".into())),
        }
    }

    /// What the engine is running on.
    pub fn info(&self) -> BackendInfo {
        let degraded = self.degraded.load(Ordering::Relaxed);
        BackendInfo {
            kind: BackendKind::Cpu,
            adapter: None,
            device_type: None,
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

    /// Prepares a rig: builds the CPU layout and, on a GPU, uploads geometry, deltas, clip
    /// tables and LOD order.
    pub fn prepare(&self, rig: Arc<Rig>) -> Result<PreparedRig, EngineError> {
        let cpu = Arc::new(CpuRig::new(&rig));
        let memory = RigMemory {
            host_bytes: rig.host_bytes() + cpu.bytes(),
            device_bytes: 0,
        };
        Ok(PreparedRig { rig, cpu, memory })
    }

    /// Re-prepares after the rig's clips changed (the geometry and LOD order are unchanged), so
    /// only the clip tables are rebuilt.
    pub fn update_clips(
        &self,
        prepared: &PreparedRig,
        rig: Arc<Rig>,
    ) -> Result<PreparedRig, EngineError> {
        if rig.lod.order != prepared.rig.lod.order || rig.primitives != prepared.rig.primitives {
            return self.prepare(rig);
        }
        let memory = RigMemory {
            host_bytes: rig.host_bytes() + prepared.cpu.bytes(),
            device_bytes: prepared.memory.device_bytes,
        };
        Ok(PreparedRig {
            rig,
            cpu: prepared.cpu.clone(),
            memory,
        })
    }

    /// Evaluates unique jobs of one rig.
    pub fn evaluate(
        &self,
        rig: &PreparedRig,
        jobs: &[BlendJob],
        spec: OutputSpec,
    ) -> Result<Evaluation, EngineError> {
        let start = Instant::now();
        let batch = WeightBatch::gather(&rig.rig, jobs)?;
        let output = rig.cpu.evaluate(&batch, spec)?;
        Ok(Evaluation {
            output,
            timings: Timings {
                wall_ns: start.elapsed().as_nanos() as u64,
                gpu_ns: None,
            },
            kind: Some(BackendKind::Cpu),
        })
    }
}
