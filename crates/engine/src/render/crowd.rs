//! Drawing a planned crowd: the path `POST /v1/crowd/render`, `crowdmorph render` and
//! `crowdmorph bench render` share.
//!
//! Unique jobs come in groups that share a rig and a mesh level (one engine call each, as the
//! engine requires); every job is drawn once per group with one instance per head that uses
//! it, so clones cost a transform, not a blend or a vertex upload. With the GPU engine on the
//! renderer's device the blended buffers never leave it (`RenderBuffers::Device`); otherwise
//! they are host arrays the renderer uploads once per unique job.
//!
//! [`RenderDevice::open`] picks the adapter: the engine's GPU when it has one, else one opened
//! for rendering only (Mesa's lavapipe on machines without a GPU), and never fails: without an
//! adapter it keeps the reason, for `render_unavailable` answers, `/readyz` and `inspect`.

use std::collections::HashMap;
use std::sync::Arc;
use std::time::Instant;

use glam::Mat4;

use super::gpu::{
    Frame, MeshTopology, RenderError, RenderOutput, Renderer, SceneMesh, VertexSource, View,
};
use crate::gpu::{GpuContext, GpuOptions, is_hardware};
use crate::{BlendJob, Engine, EngineError, OutputSpec, PreparedRig, RenderBuffers, VertexData};
use crowdmorph_core::cancel::{Cancel, Cancelled};
use crowdmorph_core::plan::{JobKey, Plan};
use crowdmorph_core::rig::layer_inputs;

/// What to install when no adapter can render.
pub const INSTALL_HINT: &str = "install a Vulkan driver: on Debian and Ubuntu, \
     `apt-get install mesa-vulkan-drivers` (Mesa's lavapipe renders on the CPU)";

/// Which adapter draws rendered frames.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum RenderBackend {
    /// The engine's GPU when it has one (its outputs are drawn where they are), else any
    /// adapter, software ones (lavapipe) included.
    #[default]
    Auto,
    /// A hardware GPU only: the engine's, or one opened for rendering; never a software one.
    Gpu,
    /// No rendering.
    Off,
}

impl std::str::FromStr for RenderBackend {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s.to_ascii_lowercase().as_str() {
            "auto" => Ok(RenderBackend::Auto),
            "gpu" => Ok(RenderBackend::Gpu),
            "off" => Ok(RenderBackend::Off),
            other => Err(format!(
                "unknown render backend {other:?} (auto, gpu or off)"
            )),
        }
    }
}

/// Why a crowd could not be drawn.
#[derive(Debug, thiserror::Error)]
pub enum CrowdError {
    /// The engine refused or failed a group's evaluation.
    #[error("evaluating the crowd: {0}")]
    Engine(#[from] EngineError),
    /// The renderer failed.
    #[error(transparent)]
    Render(#[from] RenderError),
    /// The engine's output is not what drawing needs (f32 positions and normals).
    #[error("engine output: {0}")]
    Output(String),
    /// The render's request was cancelled or passed its deadline.
    #[error("stopped: {0}")]
    Cancelled(#[from] Cancelled),
}

/// A renderer and whether it draws on the engine's own device.
pub struct RenderDevice {
    /// The renderer.
    pub renderer: Renderer,
    /// True when the renderer shares the engine's GPU device, so the engine's device outputs
    /// can be drawn where they are.
    pub shared: bool,
}

impl std::fmt::Debug for RenderDevice {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RenderDevice")
            .field("adapter", &adapter_name(self.renderer.adapter()))
            .field("shared", &self.shared)
            .finish()
    }
}

/// An adapter's name as `/readyz`, `inspect` and logs give it: `name (backend)`.
pub fn adapter_name(info: &wgpu::AdapterInfo) -> String {
    format!("{} ({:?})", info.name, info.backend)
}

impl RenderDevice {
    /// Opens the renderer `backend` asks for, next to `engine`. `Err` is why there is none
    /// (a message for a person, naming what to install); it never panics and never blocks for
    /// long (device creation is tens of milliseconds on lavapipe).
    pub fn open(engine: &Engine, backend: RenderBackend) -> Result<RenderDevice, String> {
        RenderDevice::open_with(engine, backend, GpuOptions::default())
    }

    /// [`RenderDevice::open`] with the options of a context opened for rendering only (its
    /// memory budget; on the engine's device the engine's budget applies).
    pub fn open_with(
        engine: &Engine,
        backend: RenderBackend,
        options: GpuOptions,
    ) -> Result<RenderDevice, String> {
        if backend == RenderBackend::Off {
            return Err("rendering is off (--render-backend off)".into());
        }
        let engine_gpu = engine
            .gpu_shared()
            .filter(|ctx| ctx.health().is_ok())
            .filter(|ctx| backend == RenderBackend::Auto || is_hardware(ctx.adapter()));
        if let Some(ctx) = engine_gpu {
            match Renderer::new(ctx) {
                Ok(renderer) => {
                    return Ok(RenderDevice {
                        renderer,
                        shared: true,
                    });
                }
                Err(e) => tracing::warn!(
                    error = %e,
                    "cannot render on the engine's GPU; opening another adapter for rendering"
                ),
            }
        }
        let software = backend == RenderBackend::Auto;
        let ctx = GpuContext::open(software, options).map_err(|e| {
            if software {
                format!("no adapter can render ({e}); {INSTALL_HINT}")
            } else {
                format!(
                    "no hardware GPU can render ({e}); use --render-backend auto to render on a \
                     software adapter"
                )
            }
        })?;
        let renderer = Renderer::new(Arc::new(ctx))
            .map_err(|e| format!("cannot create the renderer: {e}; {INSTALL_HINT}"))?;
        Ok(RenderDevice {
            renderer,
            shared: false,
        })
    }

    /// The adapter's name (`name (backend)`).
    pub fn name(&self) -> String {
        adapter_name(self.renderer.adapter())
    }
}

/// The renderer's frame: size and an sRGB 0–255 background.
pub fn to_frame(width: u32, height: u32, background: [u8; 3]) -> Frame {
    Frame {
        width,
        height,
        background: background.map(|c| f32::from(c) / 255.0),
    }
}

/// Unique jobs of one rig that share a mesh level, and the instances of each: what one engine
/// call evaluates and one topology draws.
#[derive(Clone, Debug, PartialEq)]
pub struct PlannedGroup {
    /// The rig (`JobKey::rig`).
    pub rig: u32,
    /// The mesh level (`None`: the full mesh).
    pub mesh: Option<usize>,
    /// The unique jobs.
    pub jobs: Vec<BlendJob>,
    /// Per job, the world transform of every head that shows it (clones are instances).
    pub instances: Vec<Vec<Mat4>>,
}

/// Splits a plan's unique jobs into groups of one rig and one mesh level, in order of first
/// appearance, with each head's transform (`transforms[h]`) as an instance of its job.
/// `mesh_of` names the mesh level of a job's rig and LOD.
pub fn plan_groups(
    plan: &Plan,
    transforms: &[Mat4],
    mesh_of: impl Fn(&JobKey) -> Option<usize>,
) -> Vec<PlannedGroup> {
    let mut groups: Vec<PlannedGroup> = Vec::new();
    let mut at: HashMap<(u32, Option<usize>), usize> = HashMap::new();
    let mut place = Vec::with_capacity(plan.jobs.len());
    for k in &plan.jobs {
        let mesh = mesh_of(k);
        let g = *at.entry((k.rig, mesh)).or_insert_with(|| {
            groups.push(PlannedGroup {
                rig: k.rig,
                mesh,
                jobs: Vec::new(),
                instances: Vec::new(),
            });
            groups.len() - 1
        });
        place.push((g, groups[g].jobs.len()));
        groups[g].jobs.push(BlendJob::from(k));
        groups[g].instances.push(Vec::new());
    }
    for (&j, m) in plan.head_job.iter().zip(transforms) {
        let (g, p) = place[j as usize];
        groups[g].instances[p].push(*m);
    }
    groups
}

/// A [`PlannedGroup`] ready to draw: its rig and the topology of its mesh level.
pub struct CrowdGroup<'a> {
    /// The rig (the engine routes the jobs to their mesh level).
    pub prepared: &'a PreparedRig,
    /// The mesh level's topology, on the renderer's device.
    pub topology: Arc<MeshTopology>,
    /// The unique jobs.
    pub jobs: Vec<BlendJob>,
    /// Per job, the world transform of every head that shows it.
    pub instances: Vec<Vec<Mat4>>,
}

/// A drawn crowd: the pixels and where the time went.
pub struct Drawn {
    /// The image, RGBA8 rows top-down.
    pub output: RenderOutput,
    /// Engine wall time of every group's evaluation, nanoseconds.
    pub compute_ns: u64,
}

/// Host bytes that evaluating `vertices` of one job for drawing may hold (f32 positions and
/// normals), for admission.
pub fn job_bytes(vertices: usize) -> u64 {
    vertices as u64 * 24
}

/// Most vertices (jobs × the mesh's vertices) one engine call of a render blends: a group with
/// more unique jobs is blended in several calls, with a cancellation check between them.
pub const BLEND_CHUNK_VERTICES: usize = 1 << 22;

/// Evaluates every group and draws the crowd.
pub fn draw(
    engine: &Engine,
    device: &RenderDevice,
    groups: &[CrowdGroup<'_>],
    view: &View,
    frame: &Frame,
) -> Result<Drawn, CrowdError> {
    draw_until(engine, device, groups, view, frame, &Cancel::never())
}

/// [`draw`] that stops at the next stage boundary — between engine calls, between render
/// passes, before the readback — once `cancel` says so ([`CrowdError::Cancelled`]).
pub fn draw_until(
    engine: &Engine,
    device: &RenderDevice,
    groups: &[CrowdGroup<'_>],
    view: &View,
    frame: &Frame,
    cancel: &Cancel,
) -> Result<Drawn, CrowdError> {
    let start = Instant::now();
    let spec = OutputSpec {
        normals: true,
        precision: crate::Precision::F32,
    };
    // Every group is evaluated before anything is drawn: the draw borrows all outputs at once.
    // A group's jobs go in chunks of at most BLEND_CHUNK_VERTICES: (group, first job, output).
    let mut outputs: Vec<(usize, usize, RenderBuffers)> = Vec::with_capacity(groups.len());
    for (gi, g) in groups.iter().enumerate() {
        let per_call = (BLEND_CHUNK_VERTICES / (g.topology.vertices() as usize).max(1)).max(1);
        for (ci, jobs) in g.jobs.chunks(per_call).enumerate() {
            cancel.check()?;
            let buffers = if device.shared {
                engine.evaluate_for_render(g.prepared, jobs)?.0
            } else {
                // Device buffers of another device cannot be drawn here: read them back.
                RenderBuffers::Host(engine.evaluate(g.prepared, jobs, spec)?.output)
            };
            outputs.push((gi, ci * per_call, buffers));
        }
    }
    // Per job its layer inputs (wrinkle weights, clip texture coefficients): a function of
    // the pose, so of the job, which every instance shares. Empty for a rig without layers;
    // otherwise about the rig's channel count of floats per job, like its weights.
    let layers: Vec<Vec<Vec<f32>>> = groups
        .iter()
        .map(|g| {
            g.jobs
                .iter()
                .map(|job| layer_inputs(g.prepared.rig(), &job.pose, job.lod))
                .collect()
        })
        .collect();
    let compute_ns = start.elapsed().as_nanos() as u64;
    cancel.check()?;
    let mut meshes = Vec::new();
    for (gi, first, out) in &outputs {
        let g = &groups[*gi];
        let n = out.jobs();
        for (j, instances) in g.instances[*first..].iter().take(n).enumerate() {
            if instances.is_empty() {
                continue;
            }
            let (positions, normals) = sources(out, j, g.topology.vertices() as usize)?;
            meshes.push(SceneMesh {
                topology: &g.topology,
                positions,
                normals,
                instances,
                layers: layers[*gi].get(first + j).map_or(&[][..], Vec::as_slice),
            });
        }
    }
    let output = device.renderer.render_until(&meshes, view, frame, cancel)?;
    Ok(Drawn { output, compute_ns })
}

/// Job `j`'s positions and normals where the engine left them.
fn sources(
    out: &RenderBuffers,
    j: usize,
    vertices: usize,
) -> Result<(VertexSource<'_>, VertexSource<'_>), CrowdError> {
    match out {
        RenderBuffers::Device(d) => {
            if d.vertices != vertices || j >= d.jobs {
                return Err(CrowdError::Output(format!(
                    "device output of {} jobs × {} vertices for job {j} of a {vertices}-vertex mesh",
                    d.jobs, d.vertices
                )));
            }
            let normals = d
                .normals
                .as_ref()
                .ok_or_else(|| CrowdError::Output("no normals on the device".into()))?;
            Ok((
                VertexSource::Device {
                    buffer: &d.positions,
                    offset: d.offset(j),
                },
                VertexSource::Device {
                    buffer: normals,
                    offset: d.offset(j),
                },
            ))
        }
        RenderBuffers::Host(h) => {
            if h.vertices != vertices || j >= h.jobs {
                return Err(CrowdError::Output(format!(
                    "host output of {} jobs × {} vertices for job {j} of a {vertices}-vertex mesh",
                    h.jobs, h.vertices
                )));
            }
            let range = j * vertices * 3..(j + 1) * vertices * 3;
            let normals = h
                .normals
                .as_ref()
                .ok_or_else(|| CrowdError::Output("no normals".into()))?;
            Ok((
                VertexSource::Host(job_f32(&h.positions, range.clone())?),
                VertexSource::Host(job_f32(normals, range)?),
            ))
        }
    }
}

/// One job's components of an f32 host buffer.
fn job_f32(d: &VertexData, range: std::ops::Range<usize>) -> Result<&[f32], CrowdError> {
    match d {
        VertexData::F32(v) => v
            .get(range)
            .ok_or_else(|| CrowdError::Output("a short host buffer".into())),
        VertexData::F16(_) | VertexData::Q16(..) => Err(CrowdError::Output(
            "16-bit output where f32 was asked".into(),
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn key(rig: u32, frame: u32, lod: u32) -> JobKey {
        JobKey::frame(rig, 0, frame, lod)
    }

    #[test]
    fn clones_are_instances_of_one_job_and_mesh_levels_split_groups() {
        // Heads: two clones of (rig 0, frame 1), one at LOD 2 (a simplified mesh), one of
        // rig 1, and a LOD 1 head that still uses the full mesh.
        let plan = Plan::new([
            key(0, 1, 0),
            key(0, 1, 0),
            key(0, 1, 2),
            key(1, 5, 0),
            key(0, 2, 1),
        ]);
        let t: Vec<Mat4> = (0..5)
            .map(|h| Mat4::from_translation(glam::Vec3::X * h as f32))
            .collect();
        let groups = plan_groups(&plan, &t, |k| (k.lod >= 2).then_some(0));
        assert_eq!(groups.len(), 3);
        let full = &groups[0];
        assert_eq!((full.rig, full.mesh), (0, None));
        assert_eq!(full.jobs.len(), 2, "LOD 0 and LOD 1 share the full mesh");
        assert_eq!(full.instances[0], vec![t[0], t[1]], "clones are instances");
        assert_eq!(full.instances[1], vec![t[4]]);
        assert_eq!((groups[1].rig, groups[1].mesh), (0, Some(0)));
        assert_eq!(groups[1].instances, vec![vec![t[2]]]);
        assert_eq!((groups[2].rig, groups[2].mesh), (1, None));
        assert_eq!(groups[2].jobs, vec![BlendJob::frame(0, 5, 0)]);
        let heads: usize = groups.iter().flat_map(|g| &g.instances).map(Vec::len).sum();
        assert_eq!(heads, 5, "every head is drawn once");
    }

    #[test]
    fn no_heads_means_no_groups() {
        assert!(plan_groups(&Plan::new([]), &[], |_| None).is_empty());
    }

    #[test]
    fn backgrounds_are_srgb_fractions() {
        let f = to_frame(3, 2, [255, 0, 51]);
        assert_eq!((f.width, f.height), (3, 2));
        assert_eq!(f.background, [1.0, 0.0, 0.2]);
    }
}
