//! The GPU renderer (wgpu, offscreen): a picture of a crowd of blended heads, for thin clients.
//!
//! What it draws: each [`SceneMesh`] is one blended vertex buffer (positions and per-vertex
//! normals, evaluation order) with its rig's — or mesh level's — triangles ([`MeshTopology`]),
//! drawn once per instance with the instance's model matrix. Shading is glTF 2.0's
//! metallic-roughness BRDF (Appendix B) of each primitive's material — or, for a primitive
//! without one, its base colour as a half-rough dielectric — under a key light at the camera's
//! upper left, a dimmer fill from its lower right and a hemisphere ambient ([`brdf`], the
//! shader's CPU mirror, which also gives reference renderers the same lights). Lights are
//! fixed relative to the camera, and nothing depends on time or randomness, so the same input
//! gives the same picture. The frame is drawn with 4× MSAA and a
//! reversed-Z depth buffer (depth 1 at `near`, 0 at `far`, in f32: precision where the heads
//! are, whatever near/far the caller gives), resolved into an `Rgba8UnormSrgb` texture — the
//! shader works in linear colour and the target encodes sRGB — and read back as tightly packed
//! RGBA8 rows.
//!
//! Why it is built this way:
//! - The batcher computes each unique job once; clones of a job are **instances** of one vertex
//!   buffer, each with its own model matrix (one instanced draw per primitive), so a crowd of
//!   clones uploads and transforms nothing per clone. Normal matrices (inverse transpose of the
//!   model's 3×3) are computed once per instance on the host, which keeps the vertex shader to
//!   two matrix products and stays correct under non-uniform scale.
//! - Topology is per rig or mesh level: a LOD mesh level is an ordinary rig with fewer vertices
//!   and triangles of its own, so its heads draw with its own index buffer, uploaded once by
//!   [`Renderer::topology`] and kept by the caller next to the prepared rig. The topology
//!   also carries what does not move with morph targets — texture coordinates, vertex colours,
//!   tangents — and the rig's textures ([`super::appearance`]), uploaded once per rig however
//!   many mesh levels draw with them.
//! - Draw order: every mesh's opaque and masked primitives first, instanced; then each
//!   alpha-blended primitive of each instance, from the farthest to the nearest, depth-tested
//!   without writing depth (blending is not commutative). Single-sided primitives cull back
//!   faces unless an instance of the draw mirrors; double-sided ones light their back faces
//!   as the surface's other side.
//! - Vertex data comes from wherever it is ([`VertexSource`]): host slices (CPU engine output)
//!   are uploaded once per mesh per render with `queue.write_buffer`; buffers already on the
//!   renderer's device (the GPU engine's outputs) are bound where they are, with no readback.
//! - Everything a render allocates is proportional to its input (vertex data, instances, draws)
//!   or to `width × height`; the last render's targets and buffers are kept for the next one
//!   when they are small (128 MiB in all), since a server renders the same sizes repeatedly.
//!   Every charge goes through [`GpuContext::charge`], and the kept ones are registered with
//!   the context ([`Reclaim`]): a charge that finds the device's budget full — a rig upload, a
//!   batch, a render — frees them first, so memory kept only for reuse never refuses work.
//! - Work runs inside validation and out-of-memory error scopes, so a failed render is a
//!   [`RenderError`] for this request, not an uncaptured error that would stop the GPU engine
//!   sharing the device; bad input is refused before anything reaches the device.
//! - The render pass and the copy back are two submissions, so their times can be told apart:
//!   timestamp queries time the pass when the device has them (else wall time), and the copy +
//!   map back is wall time, which is what a client waits for.

use std::num::NonZeroU64;
use std::ops::Range;
use std::sync::{Arc, Mutex, Weak};
use std::time::Instant;

use glam::{Mat3, Mat4, Vec3};

use super::appearance::{
    self, ATTR_FORMATS, ATTR_STRIDE, Fallback, GpuAppearance, NO_TEXTURE, SLOTS,
};
use super::brdf;
use crate::gpu::{GpuContext, MapResults, Reclaim};
use crowdmorph_core::budget::{BudgetError, Charge};
use crowdmorph_core::cancel::{Cancel, Cancelled};
use crowdmorph_core::rig::MAX_LAYERS;
use crowdmorph_core::rig::{AlphaMode, Appearance, Material, Primitive, Rig};

/// MSAA samples per pixel.
pub const SAMPLES: u32 = 4;
/// The resolved (and read back) colour format: the shader writes linear colour, the target
/// stores sRGB.
const COLOR_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8UnormSrgb;
/// Depth: f32 with reversed Z.
const DEPTH_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;
/// Targets and buffers of a render are kept for the next render only while they total at most
/// this many bytes; larger frames allocate per render, so a rare huge picture does not keep its
/// memory on the device.
const RETAIN_BYTES: u64 = 128 << 20;
/// Bytes of one vertex attribute (f32 x, y, z).
const VERTEX_STRIDE: u64 = 12;
/// Most triangles (summed over instances) one render pass draws on a hardware GPU. A crowd of
/// more is drawn in several passes, each submitted and waited for before the next, so that a
/// cancelled render stops within one pass. One pass (the common case) clears, draws and
/// resolves as before; with more, the multisampled colour and depth are stored between them
/// (at 1080p, 66 MB a pass: microseconds of a GPU's bandwidth).
pub const PASS_TRIANGLES: u64 = 1 << 22;

/// [`PASS_TRIANGLES`] on a software adapter (lavapipe). llvmpipe bins every triangle of a
/// submission before it rasterizes, about 240 bytes each (measured: 62 MB for a pass of 2^18,
/// 213 MB for 2^20, kept in its pool afterwards), so the pass bounds a render's host memory as
/// well as its cancellation latency: 2^18 is about 90 ms of drawing there (2.9 M triangles/s
/// on two cores), at 10–20 % more time than passes of 2^20.
pub const SOFTWARE_PASS_TRIANGLES: u64 = 1 << 18;

/// Bytes a software rasterizer holds per triangle of a pass while it draws (llvmpipe's bins,
/// measured at about 240). Its device runs one submission at a time, so this times
/// [`SOFTWARE_PASS_TRIANGLES`] bounds its bins whatever the number of renders in flight: a
/// software renderer charges that much (64 MiB) to its device's budget when it is created.
pub const SOFTWARE_BIN_BYTES: u64 = 256;

/// What a renderer on `adapter` charges its device's budget when it is created: a software
/// rasterizer's bins for one pass, nothing on a GPU.
pub fn fixed_bytes(adapter: &wgpu::AdapterInfo) -> u64 {
    if crate::gpu::is_hardware(adapter) {
        0
    } else {
        SOFTWARE_PASS_TRIANGLES * SOFTWARE_BIN_BYTES
    }
}

/// Where a mesh's vertex attribute lives.
#[derive(Clone, Copy, Debug)]
pub enum VertexSource<'a> {
    /// f32 x, y, z per vertex (evaluation order: all primitives concatenated), on the host.
    Host(&'a [f32]),
    /// The same layout in a buffer on the renderer's device, from `offset` bytes; the buffer
    /// was created with VERTEX usage. (A buffer of another device is a caller's bug that wgpu
    /// cannot always detect; size, alignment and usage are checked.)
    Device {
        /// The buffer.
        buffer: &'a wgpu::Buffer,
        /// Byte offset of vertex 0 (a multiple of 4).
        offset: u64,
    },
}

/// A rig's (or mesh level's) triangles uploaded once: one index buffer over the evaluation
/// vertex order, the static per-vertex attributes (texture coordinates, colours, tangents),
/// the rig's textures, and each primitive's index range with its material.
pub struct MeshTopology {
    /// The context (so the device) the index buffer lives on; a render on another context
    /// refuses it. Compared by pointer: `wgpu::Device`'s equality compares ids, which devices
    /// of different wgpu instances can share.
    ctx: Arc<GpuContext>,
    indices: wgpu::Buffer,
    /// [`appearance::VertexAttrs`] per vertex (vertex buffer slot 3).
    attrs: wgpu::Buffer,
    /// The rig's textures and material bind groups, shared with its other topologies.
    appearance: Option<Arc<GpuAppearance>>,
    primitives: Vec<TopologyPrimitive>,
    vertices: u32,
    triangles: u32,
    /// The index and attribute buffers' bytes in the device's memory budget.
    _charge: Charge,
}

/// One primitive's slice of a topology's index buffer, and what it is drawn with.
#[derive(Clone, Debug)]
struct TopologyPrimitive {
    indices: Range<u32>,
    /// Its material's uniform slot, made once at upload.
    material: MaterialUniform,
    /// The material whose texture bind group it draws with (`None`: the untextured one).
    textures: Option<usize>,
    /// Per layer its material sums, where its coefficient is in a job's layer inputs and
    /// whether it is clamped to [0, 1] (`None`: a target the rig does not have; stays zero).
    layer_sources: Vec<Option<(u32, bool)>>,
    /// Alpha-blended: drawn after everything opaque, sorted far to near.
    blend: bool,
    /// Both sides drawn (else back faces are culled where that is safe).
    double_sided: bool,
    /// Centre of its neutral vertices in rig space: where a blended primitive sorts.
    centroid: Vec3,
}

impl std::fmt::Debug for MeshTopology {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("MeshTopology")
            .field("vertices", &self.vertices)
            .field("triangles", &self.triangles)
            .field("primitives", &self.primitives.len())
            .finish()
    }
}

impl MeshTopology {
    /// Vertices a vertex source for this topology holds.
    pub fn vertices(&self) -> u32 {
        self.vertices
    }

    /// Triangles drawn per instance.
    pub fn triangles(&self) -> u32 {
        self.triangles
    }

    /// Bytes it occupies on the device: indices, attributes, and the rig's textures (which
    /// its other topologies share: counted in each, so a cache that bounds them errs high).
    pub fn bytes(&self) -> u64 {
        self.indices.size() + self.attrs.size() + self.appearance.as_ref().map_or(0, |a| a.bytes())
    }

    /// Bytes of the rig's textures on the device (part of [`MeshTopology::bytes`]).
    pub fn texture_bytes(&self) -> u64 {
        self.appearance.as_ref().map_or(0, |a| a.bytes())
    }

    /// How many texture fetches (5 slots and up to 16 layers) the primitive that samples the
    /// most makes: what a pixel of this mesh costs in texture fetches at most.
    pub fn texture_slots(&self) -> u32 {
        self.primitives
            .iter()
            .map(|p| {
                // Each layer is one more fetch.
                p.material.sets[..SLOTS.len()]
                    .iter()
                    .filter(|&&s| s != NO_TEXTURE)
                    .count() as u32
                    + p.material.layers[0]
            })
            .max()
            .unwrap_or(0)
    }
}

/// One vertex buffer and the heads that draw it.
#[derive(Clone, Copy, Debug)]
pub struct SceneMesh<'a> {
    /// The triangles of the rig or mesh level the vertex data was evaluated on.
    pub topology: &'a MeshTopology,
    /// Blended positions, in rig space.
    pub positions: VertexSource<'a>,
    /// Blended unit normals, in rig space.
    pub normals: VertexSource<'a>,
    /// One model matrix (rig space → world) per head drawing this buffer.
    pub instances: &'a [Mat4],
    /// The job's layer inputs (`crowdmorph_core::rig::layer_inputs`: final target weights,
    /// then clip textures' coefficients), which every instance shares: instances are clones
    /// of one job, so one pose. Empty: every layer at zero.
    pub layers: &'a [f32],
}

/// The camera: the scene layout's view type (right-handed, Y up).
pub use super::scene::View;

/// The picture's size and background.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Frame {
    /// Width in pixels, 1..=[`Renderer::max_size`].
    pub width: u32,
    /// Height in pixels, 1..=[`Renderer::max_size`].
    pub height: u32,
    /// sRGB, 0..=1 each
    pub background: [f32; 3],
}

/// A rendered picture.
#[derive(Clone, Debug, PartialEq)]
pub struct RenderOutput {
    /// RGBA8 sRGB, rows top-down, exactly width*4 bytes each (no padding)
    pub rgba: Vec<u8>,
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// GPU (or wall, without timestamps) time of the render pass, and of the copy + map back.
    pub render_ns: u64,
    /// Wall time of the copy to the staging buffer and its mapping back to the host.
    pub readback_ns: u64,
}

/// Why a render (or a topology upload) failed.
#[derive(Debug, thiserror::Error, Clone, PartialEq)]
pub enum RenderError {
    /// The device was lost, ran out of memory, or reported a validation error.
    #[error("GPU render failed: {0}")]
    Device(String),
    /// A size past the device's limits (texture size, largest buffer).
    #[error("too large to render: {0}")]
    TooLarge(String),
    /// Bad input: a vertex source that does not match its topology, a bad view, zero size...
    #[error("invalid render input: {0}")]
    Invalid(String),
    /// The device's memory budget (`--max-gpu-memory`) refused the render's targets or
    /// buffers: `TooLarge` when they can never fit, `Full` when what the device holds now
    /// leaves no room.
    #[error("GPU memory: {0}")]
    Memory(#[from] BudgetError),
    /// The render's request was cancelled or passed its deadline between two passes.
    #[error("render stopped: {0}")]
    Cancelled(#[from] Cancelled),
}

impl From<appearance::AppearanceError> for RenderError {
    fn from(e: appearance::AppearanceError) -> RenderError {
        match e {
            appearance::AppearanceError::Memory(b) => RenderError::Memory(b),
            other => RenderError::Invalid(other.to_string()),
        }
    }
}

/// The per-render uniform block the shader's `Camera` mirrors: the view and the lights
/// ([`brdf::reference_lights`]).
#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
struct CameraUniform {
    view_proj: [f32; 16],
    eye: [f32; 4],
    key: [f32; 4],
    fill: [f32; 4],
    up: [f32; 4],
    sky: [f32; 4],
    ground: [f32; 4],
}

/// One primitive draw's material, the shader's `Material`: a glTF metallic-roughness
/// material's factors and flags.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
struct MaterialUniform {
    /// Linear RGBA base colour factor.
    base: [f32; 4],
    /// Emissive factor × strength (rgb).
    emissive: [f32; 4],
    /// Metallic, roughness, normal scale, occlusion strength.
    pbr: [f32; 4],
    /// Alpha cutoff, alpha mode (0 opaque, 1 mask, 2 blend), unlit, double-sided.
    alpha: [f32; 4],
    /// Texture coordinate set per slot of [`SLOTS`] (then three unused), [`NO_TEXTURE`] for
    /// an empty one (the shader's `sets` and `sets2`).
    sets: [u32; 8],
    /// Per slot, the two rows of its `KHR_texture_transform` (xyz; w unused).
    transforms: [[f32; 4]; 10],
    /// Layers summed (0: none), their texture coordinate set (they read through the base
    /// colour's transform), two unused.
    layers: [u32; 4],
    /// Each layer's coefficient for this draw (filled per draw from its job's layer inputs).
    coefficients: [[f32; 4]; MAX_LAYERS / 4],
}

impl MaterialUniform {
    /// The uniform of `m`, every factor clamped to its range (a NaN to the factor's default),
    /// so that no input reaches the shader as a NaN.
    fn of(m: &Material) -> MaterialUniform {
        let unit = |v: f32, default: f32| {
            if v.is_finite() {
                v.clamp(0.0, 1.0)
            } else {
                default
            }
        };
        let finite = |v: f32, default: f32| if v.is_finite() { v } else { default };
        let strength = finite(m.emissive_strength, 1.0).max(0.0);
        let e = m.emissive_factor.map(|c| unit(c, 0.0) * strength);
        let mode = match m.alpha_mode {
            AlphaMode::Opaque => 0.0,
            AlphaMode::Mask => 1.0,
            AlphaMode::Blend => 2.0,
        };
        let flag = |b: bool| if b { 1.0 } else { 0.0 };
        let mut transforms = [[0.0; 4]; 10];
        for k in 0..SLOTS.len() {
            transforms[2 * k] = [1.0, 0.0, 0.0, 0.0];
            transforms[2 * k + 1] = [0.0, 1.0, 0.0, 0.0];
        }
        MaterialUniform {
            sets: [NO_TEXTURE; 8],
            transforms,
            layers: [0; 4],
            coefficients: [[0.0; 4]; MAX_LAYERS / 4],
            base: m.base_color_factor.map(|c| unit(c, 1.0)),
            emissive: [e[0], e[1], e[2], 0.0],
            pbr: [
                unit(m.metallic_factor, 1.0),
                unit(m.roughness_factor, 1.0),
                finite(m.normal_scale, 1.0),
                unit(m.occlusion_strength, 1.0),
            ],
            alpha: [
                finite(m.alpha_cutoff, 0.5),
                mode,
                flag(m.unlit),
                flag(m.double_sided),
            ],
        }
    }

    /// The uniform of material `index` of `a` as drawn by primitive `p`: [`MaterialUniform::of`]
    /// with a texture coordinate set and transform for each slot that has a texture uploaded
    /// (`gpu`) and whose set the primitive has; other slots draw as if empty.
    fn textured(m: &Material, index: usize, gpu: &GpuAppearance, p: &Primitive) -> MaterialUniform {
        let mut u = MaterialUniform::of(m);
        let n = p.positions.len();
        let has_set = |set: u8| match set {
            0 => p.look.uv0.as_ref().is_some_and(|a| a.len() == n),
            1 => p.look.uv1.as_ref().is_some_and(|a| a.len() == n),
            _ => false,
        };
        for (k, slot) in SLOTS.iter().enumerate() {
            let Some((_, r)) = m.texture_refs().find(|(s, _)| s == slot) else {
                continue;
            };
            if !gpu.has(index, k) || !has_set(r.tex_coord) {
                continue;
            }
            u.sets[k] = u32::from(r.tex_coord);
            if let Some(t) = r.transform {
                let [r0, r1] = t.rows();
                if r0.iter().chain(&r1).all(|v| v.is_finite()) {
                    u.transforms[2 * k] = [r0[0], r0[1], r0[2], 0.0];
                    u.transforms[2 * k + 1] = [r1[0], r1[1], r1[2], 0.0];
                }
            }
        }
        // Layers are texel for texel the base colour's: read through its set and transform,
        // or set 0 untransformed when the material has no base colour texture.
        let set = if u.sets[0] == NO_TEXTURE {
            0
        } else {
            u.sets[0]
        };
        let layers = gpu.layers(index).min(MAX_LAYERS);
        if layers > 0 && has_set(set as u8) {
            u.layers = [layers as u32, set, 0, 0];
        }
        u
    }

    /// This uniform with the coefficients of a draw whose job's layer inputs are `inputs`.
    fn with_coefficients(&self, sources: &[Option<(u32, bool)>], inputs: &[f32]) -> Self {
        let mut u = *self;
        for (k, source) in sources.iter().enumerate().take(u.layers[0] as usize) {
            let c = source
                .and_then(|(at, clamp)| {
                    let v = *inputs.get(at as usize)?;
                    Some(if clamp { v.clamp(0.0, 1.0) } else { v })
                })
                .filter(|v| v.is_finite())
                .unwrap_or(0.0);
            u.coefficients[k / 4][k % 4] = c;
        }
        u
    }
}

/// One instance in the per-instance vertex buffer: model matrix and normal matrix by columns.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct InstanceData {
    model: [f32; 16],
    normal: [f32; 12],
}

/// Render targets of one size, and the staging buffer their copy lands in.
struct Targets {
    width: u32,
    height: u32,
    msaa: wgpu::TextureView,
    depth: wgpu::TextureView,
    resolve: wgpu::Texture,
    resolve_view: wgpu::TextureView,
    staging: wgpu::Buffer,
    /// Padded bytes per row in `staging`.
    row: u32,
    /// Their bytes in the device's memory budget.
    charge: Charge,
}

impl Targets {
    /// Device bytes of the targets of a `width × height` frame whose readback rows are `row`
    /// bytes: MSAA colour and depth (4 bytes × samples each), the resolved colour and the
    /// staging copy.
    fn bytes_of(width: u32, height: u32, row: u32) -> u64 {
        let pixels = u64::from(width) * u64::from(height);
        pixels * 4 * u64::from(SAMPLES) * 2 + pixels * 4 + u64::from(row) * u64::from(height)
    }

    fn bytes(&self) -> u64 {
        self.charge.bytes()
    }
}

/// Per-render buffers: uploaded vertex data and instances, uniforms, timestamp queries.
struct Scratch {
    /// Instances and host vertex data (VERTEX | COPY_DST).
    scene: wgpu::Buffer,
    /// The camera, then one material slot per draw (UNIFORM | COPY_DST).
    uniforms: wgpu::Buffer,
    /// Query set of two timestamps, its resolve buffer and the mappable copy.
    queries: Option<(wgpu::QuerySet, wgpu::Buffer, wgpu::Buffer)>,
    /// The scene and uniform buffers' bytes in the device's memory budget (each moves with
    /// its buffer when that is kept for the next render).
    scene_charge: Charge,
    uniforms_charge: Charge,
}

impl Scratch {
    fn bytes(&self) -> u64 {
        self.scene.size() + self.uniforms.size()
    }
}

/// The offscreen renderer. `Send + Sync`: renders from several threads may run at once.
pub struct Renderer {
    ctx: Arc<GpuContext>,
    /// By [`pipeline_index`]: back faces culled or not, opaque or alpha-blended.
    pipelines: Vec<wgpu::RenderPipeline>,
    camera_layout: wgpu::BindGroupLayout,
    material_layout: wgpu::BindGroupLayout,
    texture_layout: wgpu::BindGroupLayout,
    /// What slots without a texture are bound to.
    fallback: Fallback,
    /// The appearances uploaded, by the rig appearance they were made of, while some topology
    /// holds them: every mesh level and generation of a rig shares one upload.
    appearances: Mutex<Vec<(Weak<Appearance>, Weak<GpuAppearance>)>>,
    /// Stride of material slots in the uniform buffer (the device's dynamic-offset alignment).
    uniform_align: u64,
    max_size: u32,
    max_buffer: u64,
    /// Nanoseconds per timestamp tick, when the device has timestamp queries.
    timestamp_period: Option<f64>,
    /// The last render's targets and buffers, for the next one; registered with the context,
    /// which frees them when a charge finds the device's budget full.
    kept: Arc<Kept>,
    /// On a software adapter, the rasterizer's bins for one pass (the host's memory there).
    _bins: Option<Charge>,
    /// A test's code to run inside every render's race window (see
    /// [`Renderer::set_after_submit`]).
    after_submit: Mutex<Option<AfterSubmit>>,
    /// Most triangles one render pass draws ([`PASS_TRIANGLES`]; tests lower it).
    pass_triangles: std::sync::atomic::AtomicU64,
}

/// The last render's targets and buffers, kept for the next render (a render that finds them
/// taken by a concurrent render makes its own). Only idle ones are here: a render takes them
/// out while it uses them.
#[derive(Default)]
struct Kept {
    targets: Mutex<Option<Targets>>,
    scratch: Mutex<Option<Scratch>>,
}

impl Reclaim for Kept {
    /// Drops the kept targets and buffers, giving their memory back (the next render makes new
    /// ones). A lock held means a render is putting them back or taking them out right now: it
    /// is not waited for.
    fn reclaim(&self) -> bool {
        let targets = self.targets.try_lock().ok().and_then(|mut t| t.take());
        let scratch = self.scratch.try_lock().ok().and_then(|mut s| s.take());
        targets.is_some() || scratch.is_some()
    }
}

/// Code a test runs inside a render, after its work is submitted and its frame's mapping
/// requested, before it waits for them; it gets the renderer's context.
pub type AfterSubmit = Arc<dyn Fn(&GpuContext) + Send + Sync>;

impl std::fmt::Debug for Renderer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Renderer")
            .field("adapter", &self.ctx.adapter().name)
            .field("max_size", &self.max_size)
            .finish()
    }
}

/// Validation and out-of-memory scopes around a piece of device work, popped in order.
struct Scopes {
    validation: wgpu::ErrorScopeGuard,
    oom: wgpu::ErrorScopeGuard,
}

impl Scopes {
    fn push(device: &wgpu::Device) -> Scopes {
        let oom = device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let validation = device.push_error_scope(wgpu::ErrorFilter::Validation);
        Scopes { validation, oom }
    }

    fn pop(self, what: &str) -> Result<(), RenderError> {
        // Inner scope first: scopes are a stack.
        let validation = pollster::block_on(self.validation.pop());
        let oom = pollster::block_on(self.oom.pop());
        if let Some(e) = oom {
            return Err(RenderError::Device(format!("{what}: out of memory: {e}")));
        }
        if let Some(e) = validation {
            return Err(RenderError::Device(format!("{what}: {e}")));
        }
        Ok(())
    }
}

fn lost(e: impl std::fmt::Display) -> RenderError {
    RenderError::Device(e.to_string())
}

fn nanos(since: Instant) -> u64 {
    u64::try_from(since.elapsed().as_nanos()).unwrap_or(u64::MAX)
}

/// sRGB-encoded channel → linear, the exact piecewise curve (the clear colour of an sRGB
/// target is given in linear).
fn srgb_to_linear(c: f32) -> f64 {
    let c = f64::from(c.clamp(0.0, 1.0));
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

/// Inverse transpose of `m`'s upper 3×3 up to a positive scale: the cofactor matrix
/// (columns b×c, c×a, a×b = det · M⁻ᵀ) times the sign of the determinant, scaled so its largest
/// entry is 1. Normals are renormalized per fragment, so the scale does not matter, and unlike
/// an inverse this is defined for singular matrices and cannot overflow for tiny scales.
fn normal_matrix(m: &Mat4) -> Mat3 {
    // In f64, so that neither tiny nor huge scales underflow or overflow on the way.
    let col = |v: glam::Vec4| v.truncate().as_dvec3();
    let (a, b, c) = (col(m.x_axis), col(m.y_axis), col(m.z_axis));
    let cof = glam::DMat3::from_cols(b.cross(c), c.cross(a), a.cross(b));
    let det = a.dot(b.cross(c));
    let largest = cof.abs().to_cols_array().into_iter().fold(0.0f64, f64::max);
    let scale = if largest > 0.0 && largest.is_finite() {
        1.0 / largest
    } else {
        1.0
    };
    (cof * if det < 0.0 { -scale } else { scale }).as_mat3()
}

/// Where one mesh's vertex attribute is bound from during the pass.
enum Bound<'a> {
    /// Uploaded from `data` to this offset of the scratch scene buffer.
    Scene { offset: u64, data: &'a [f32] },
    /// In the caller's buffer.
    Device {
        buffer: &'a wgpu::Buffer,
        offset: u64,
    },
}

/// A mesh as it will be drawn.
struct Draw<'a> {
    topology: &'a MeshTopology,
    positions: Bound<'a>,
    normals: Bound<'a>,
    /// Its instances' model matrices.
    models: &'a [Mat4],
    /// Its job's layer inputs ([`SceneMesh::layers`]).
    layers: &'a [f32],
    /// Offset of its instances in the scene buffer, and their count.
    instance_offset: u64,
    instances: u32,
    /// Material slot of its first primitive (slot 0 is the camera).
    first_material: u64,
    /// Whether back faces of its single-sided primitives may be culled: no instance mirrors
    /// (a mirror turns the triangles' winding round).
    cull: bool,
}

/// What one entry of a render's draw order draws: a mesh's opaque and masked primitives, all
/// instanced, or one blended primitive of one instance.
#[derive(Clone, Debug, PartialEq)]
struct Item {
    draw: usize,
    /// `None`: every primitive of the draw that is not blended; `Some(k)`: blended primitive
    /// `k` alone.
    primitive: Option<usize>,
    /// The draw's instances this item draws.
    instances: Range<u32>,
    /// Triangles per instance.
    triangles: u64,
}

/// A checked render: what is drawn in which order, and the sizes of the buffers it needs.
struct Layout<'a> {
    draws: Vec<Draw<'a>>,
    /// The draw order: every mesh's opaque primitives, then each blended primitive of each
    /// instance from the farthest to the nearest (alpha blending is not commutative, and the
    /// depth of what is behind must be final).
    items: Vec<Item>,
    scene_bytes: u64,
    uniform_bytes: u64,
}

/// Index into [`Renderer::pipelines`] of the pipeline that culls back faces or not and blends
/// or not.
fn pipeline_index(cull: bool, blend: bool) -> usize {
    usize::from(cull) + 2 * usize::from(blend)
}

/// The draw order of `draws` seen from `view` (see [`Layout::items`]).
fn draw_order(draws: &[Draw<'_>], view: &View) -> Vec<Item> {
    let mut items = Vec::with_capacity(draws.len());
    let mut blended: Vec<(f32, Item)> = Vec::new();
    let forward = (view.target - view.eye).normalize_or_zero();
    for (d, draw) in draws.iter().enumerate() {
        let prims = &draw.topology.primitives;
        let opaque: u64 = prims
            .iter()
            .filter(|p| !p.blend)
            .map(|p| u64::from(p.indices.end - p.indices.start) / 3)
            .sum();
        if prims.iter().any(|p| !p.blend) {
            items.push(Item {
                draw: d,
                primitive: None,
                instances: 0..draw.instances,
                triangles: opaque,
            });
        }
        for (k, p) in prims.iter().enumerate().filter(|(_, p)| p.blend) {
            for (i, model) in draw.models.iter().enumerate() {
                let depth = (model.transform_point3(p.centroid) - view.eye).dot(forward);
                blended.push((
                    depth,
                    Item {
                        draw: d,
                        primitive: Some(k),
                        instances: i as u32..i as u32 + 1,
                        triangles: u64::from(p.indices.end - p.indices.start) / 3,
                    },
                ));
            }
        }
    }
    // Far to near; equal depths keep the request's order (a stable sort). NaN depths (not
    // reachable: instances are finite) would sort last rather than panic.
    blended.sort_by(|a, b| b.0.total_cmp(&a.0));
    items.extend(blended.into_iter().map(|(_, item)| item));
    items
}

impl Renderer {
    /// The memory budget of the renderer's device (`--max-gpu-memory`), which its targets,
    /// scenes and index buffers are charged to.
    pub fn memory(&self) -> &Arc<crowdmorph_core::budget::MemoryPool> {
        self.ctx.memory()
    }

    /// Registers something else that keeps memory on the renderer's device only for reuse
    /// (the server's topology cache), so that a charge that finds the budget full frees it
    /// too ([`GpuContext::register_reclaim`]).
    pub fn register_reclaim(&self, reclaimer: Weak<dyn Reclaim>) {
        self.ctx.register_reclaim(reclaimer);
    }

    /// Builds the pipelines (back faces culled or not × opaque or blended) on the context's
    /// device (the device the GPU engine uses, so its outputs can be drawn where they are).
    pub fn new(ctx: Arc<GpuContext>) -> Result<Renderer, RenderError> {
        ctx.health().map_err(lost)?;
        let software = !crate::gpu::is_hardware(ctx.adapter());
        let bins = fixed_bytes(ctx.adapter());
        let bins = (bins > 0)
            .then(|| {
                ctx.charge(bins, || {
                    format!("a software rasterizer's bins for one render pass ({bins} bytes)")
                })
            })
            .transpose()?;
        let device = ctx.device();
        let scopes = Scopes::push(device);
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("render.wgsl"),
            source: wgpu::ShaderSource::Wgsl(include_str!("../../shaders/render.wgsl").into()),
        });
        let uniform_layout =
            |label: &str, visibility: wgpu::ShaderStages, dynamic: bool, size: usize| {
                device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                    label: Some(label),
                    entries: &[wgpu::BindGroupLayoutEntry {
                        binding: 0,
                        visibility,
                        ty: wgpu::BindingType::Buffer {
                            ty: wgpu::BufferBindingType::Uniform,
                            has_dynamic_offset: dynamic,
                            min_binding_size: NonZeroU64::new(size as u64),
                        },
                        count: None,
                    }],
                })
            };
        let camera_layout = uniform_layout(
            "render camera",
            wgpu::ShaderStages::VERTEX | wgpu::ShaderStages::FRAGMENT,
            false,
            size_of::<CameraUniform>(),
        );
        let material_layout = uniform_layout(
            "render material",
            wgpu::ShaderStages::FRAGMENT,
            true,
            size_of::<MaterialUniform>(),
        );
        let texture_layout = appearance::texture_layout(device);
        let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("render"),
            bind_group_layouts: &[
                Some(&camera_layout),
                Some(&material_layout),
                Some(&texture_layout),
            ],
            immediate_size: 0,
        });
        let position_attrs = wgpu::vertex_attr_array![0 => Float32x3];
        let normal_attrs = wgpu::vertex_attr_array![1 => Float32x3];
        let instance_attrs = wgpu::vertex_attr_array![
            2 => Float32x4, 3 => Float32x4, 4 => Float32x4, 5 => Float32x4,
            6 => Float32x4, 7 => Float32x4, 8 => Float32x4
        ];
        let buffers = [
            Some(wgpu::VertexBufferLayout {
                array_stride: VERTEX_STRIDE,
                step_mode: wgpu::VertexStepMode::Vertex,
                attributes: &position_attrs,
            }),
            Some(wgpu::VertexBufferLayout {
                array_stride: VERTEX_STRIDE,
                step_mode: wgpu::VertexStepMode::Vertex,
                attributes: &normal_attrs,
            }),
            Some(wgpu::VertexBufferLayout {
                array_stride: size_of::<InstanceData>() as u64,
                step_mode: wgpu::VertexStepMode::Instance,
                attributes: &instance_attrs,
            }),
            Some(wgpu::VertexBufferLayout {
                array_stride: ATTR_STRIDE,
                step_mode: wgpu::VertexStepMode::Vertex,
                attributes: &ATTR_FORMATS,
            }),
        ];
        let pipeline = |cull: bool, blend: bool| {
            device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
                label: Some("render"),
                layout: Some(&layout),
                vertex: wgpu::VertexState {
                    module: &module,
                    entry_point: Some("vs_main"),
                    compilation_options: wgpu::PipelineCompilationOptions::default(),
                    buffers: &buffers,
                },
                primitive: wgpu::PrimitiveState {
                    topology: wgpu::PrimitiveTopology::TriangleList,
                    // glTF's front faces are counter-clockwise; the import turns the triangles
                    // of mirrored nodes round, and draws whose instances mirror are never culled.
                    front_face: wgpu::FrontFace::Ccw,
                    cull_mode: cull.then_some(wgpu::Face::Back),
                    ..wgpu::PrimitiveState::default()
                },
                depth_stencil: Some(wgpu::DepthStencilState {
                    format: DEPTH_FORMAT,
                    // Blended surfaces are tested against what is opaque but do not hide each
                    // other: they are drawn far to near.
                    depth_write_enabled: Some(!blend),
                    // Reversed Z: nearer is larger.
                    depth_compare: Some(wgpu::CompareFunction::Greater),
                    stencil: wgpu::StencilState::default(),
                    bias: wgpu::DepthBiasState::default(),
                }),
                multisample: wgpu::MultisampleState {
                    count: SAMPLES,
                    mask: !0,
                    alpha_to_coverage_enabled: false,
                },
                fragment: Some(wgpu::FragmentState {
                    module: &module,
                    entry_point: Some("fs_main"),
                    compilation_options: wgpu::PipelineCompilationOptions::default(),
                    targets: &[Some(wgpu::ColorTargetState {
                        format: COLOR_FORMAT,
                        // Straight alpha over what is behind; the frame's alpha stays 1.
                        blend: blend.then_some(wgpu::BlendState {
                            color: wgpu::BlendComponent {
                                src_factor: wgpu::BlendFactor::SrcAlpha,
                                dst_factor: wgpu::BlendFactor::OneMinusSrcAlpha,
                                operation: wgpu::BlendOperation::Add,
                            },
                            alpha: wgpu::BlendComponent {
                                src_factor: wgpu::BlendFactor::One,
                                dst_factor: wgpu::BlendFactor::OneMinusSrcAlpha,
                                operation: wgpu::BlendOperation::Add,
                            },
                        }),
                        write_mask: wgpu::ColorWrites::ALL,
                    })],
                }),
                multiview_mask: None,
                cache: None,
            })
        };
        let pipelines = [(false, false), (true, false), (false, true), (true, true)]
            .map(|(cull, blend)| pipeline(cull, blend))
            .into_iter()
            .collect();
        let fallback = Fallback::new(device, ctx.queue(), &texture_layout);
        scopes.pop("building the render pipeline")?;
        let limits = device.limits();
        let timestamp_period = ctx
            .has_timestamps()
            .then(|| f64::from(ctx.queue().get_timestamp_period()));
        let kept = Arc::new(Kept::default());
        ctx.register_reclaim(Arc::downgrade(&kept) as Weak<dyn Reclaim>);
        Ok(Renderer {
            pipelines,
            camera_layout,
            material_layout,
            texture_layout,
            fallback,
            appearances: Mutex::new(Vec::new()),
            uniform_align: u64::from(limits.min_uniform_buffer_offset_alignment)
                .max(size_of::<CameraUniform>() as u64)
                .max(size_of::<MaterialUniform>() as u64)
                .next_power_of_two(),
            max_size: limits.max_texture_dimension_2d,
            max_buffer: limits.max_buffer_size,
            timestamp_period,
            kept,
            _bins: bins,
            after_submit: Mutex::new(None),
            pass_triangles: std::sync::atomic::AtomicU64::new(if software {
                SOFTWARE_PASS_TRIANGLES
            } else {
                PASS_TRIANGLES
            }),
            ctx,
        })
    }

    /// Most triangles one pass draws ([`PASS_TRIANGLES`], or [`SOFTWARE_PASS_TRIANGLES`] on a
    /// software adapter).
    pub fn pass_triangles(&self) -> u64 {
        self.pass_triangles
            .load(std::sync::atomic::Ordering::Relaxed)
    }

    /// Whether the adapter rasterizes on the CPU (lavapipe, SwiftShader).
    pub fn is_software(&self) -> bool {
        !crate::gpu::is_hardware(self.ctx.adapter())
    }

    /// Test hook: later renders draw at most `triangles` per pass (default
    /// [`Renderer::pass_triangles`]), so that the several-pass path is tested on small scenes.
    #[doc(hidden)]
    pub fn set_pass_triangles(&self, triangles: u64) {
        self.pass_triangles
            .store(triangles.max(1), std::sync::atomic::Ordering::Relaxed);
    }

    /// Test hook: `hook` runs in every later render after its work is submitted and its
    /// frame's mapping requested, before the render waits for them — the window in which a rig
    /// delete or another thread's device poll races it, which tests need to hit every time
    /// rather than by luck. `None` removes it.
    #[doc(hidden)]
    pub fn set_after_submit(&self, hook: Option<AfterSubmit>) {
        if let Ok(mut h) = self.after_submit.lock() {
            *h = hook;
        }
    }

    /// Runs the test hook, if one is set.
    fn after_submit(&self) {
        let hook = self.after_submit.lock().ok().and_then(|h| h.clone());
        if let Some(hook) = hook {
            hook(&self.ctx);
        }
    }

    /// The adapter the renderer draws on.
    pub fn adapter(&self) -> &wgpu::AdapterInfo {
        self.ctx.adapter()
    }

    /// Largest width or height (the device's 2D texture limit).
    pub fn max_size(&self) -> u32 {
        self.max_size
    }

    /// Uploads a rig's (or mesh level's) triangles: one index buffer over the evaluation vertex
    /// order (each primitive's indices offset by its first vertex), the static attributes of
    /// every vertex, the rig's textures (once per rig appearance: its other topologies share
    /// them), and per primitive its index range and material. Keep it as long as the rig: it is
    /// what every render of the rig's heads draws with.
    pub fn topology(&self, rig: &Rig) -> Result<MeshTopology, RenderError> {
        self.ctx.health().map_err(lost)?;
        let vertices = rig.vertex_count();
        let vertex_count = u32::try_from(vertices).map_err(|_| {
            RenderError::TooLarge(format!("{vertices} vertices do not fit 32-bit indices"))
        })?;
        let total_indices: usize = rig.primitives.iter().map(|p| p.indices.len()).sum();
        let bytes = total_indices as u64 * 4;
        let attr_bytes = vertices as u64 * ATTR_STRIDE;
        // Index ranges are u32 in draw calls.
        if bytes > self.max_buffer
            || attr_bytes > self.max_buffer
            || u32::try_from(total_indices).is_err()
        {
            return Err(RenderError::TooLarge(format!(
                "{total_indices} indices ({bytes} bytes) or {vertices} vertices' attributes \
                 ({attr_bytes} bytes) exceed the device's largest buffer ({} bytes) or 32-bit \
                 draw ranges",
                self.max_buffer
            )));
        }
        for p in rig.primitives.iter() {
            let n = p.positions.len() as u32;
            if !p.indices.len().is_multiple_of(3) {
                return Err(RenderError::Invalid(format!(
                    "primitive {:?}: {} indices is not a whole number of triangles",
                    p.name,
                    p.indices.len()
                )));
            }
            if let Some(&bad) = p.indices.iter().find(|&&i| i >= n) {
                return Err(RenderError::Invalid(format!(
                    "primitive {:?}: index {bad} past its {n} vertices",
                    p.name
                )));
            }
        }
        // The textures first: they are the largest part, and charged on their own.
        let gpu = match &rig.appearance {
            Some(a) if appearance::has_textures(a) => Some(self.gpu_appearance(a)?),
            _ => None,
        };
        let charge = self.ctx.charge(bytes.max(4) + attr_bytes.max(4), || {
            format!(
                "{} triangles' indices and {vertices} vertices' attributes on the GPU",
                total_indices / 3
            )
        })?;
        let mut indices = Vec::with_capacity(total_indices);
        let mut attrs = Vec::with_capacity(vertices);
        let mut primitives = Vec::with_capacity(rig.primitives.len());
        let mut first_vertex = 0u32;
        for p in rig.primitives.iter() {
            let start = indices.len() as u32;
            indices.extend(p.indices.iter().map(|&i| i + first_vertex));
            // Tangents only matter under a normal map; without the file's, they are made here
            // from the texture coordinates the map reads.
            let generated = match (&p.tangents, normal_map_set(rig, p)) {
                (None, Some(uv)) => appearance::generate_tangents(p, uv),
                _ => None,
            };
            appearance::push_attrs(
                &mut attrs,
                p,
                generated.as_deref().or(p.tangents.as_deref()),
            );
            // A primitive without a material draws its base colour, dielectric and half rough
            // (`Material::untextured`): glTF's default material is black without an
            // environment map. The rig's validation keeps the index in range; one that is not
            // falls back the same way rather than failing the upload.
            let named = p.look.material.and_then(|m| {
                let a = rig.appearance.as_ref()?;
                Some((m as usize, a.materials.get(m as usize)?))
            });
            let (material, textures) = match named {
                Some((index, m)) => match &gpu {
                    Some(g) => {
                        let u = MaterialUniform::textured(m, index, g, p);
                        let sampled = u.sets[..SLOTS.len()].iter().any(|&s| s != NO_TEXTURE);
                        (u, (sampled && g.group(index).is_some()).then_some(index))
                    }
                    None => (MaterialUniform::of(m), None),
                },
                None => (
                    MaterialUniform::of(&Material::untextured(p.base_color)),
                    None,
                ),
            };
            let (blend, double_sided) = match named {
                Some((_, m)) => (m.alpha_mode == AlphaMode::Blend, m.double_sided),
                None => (false, false),
            };
            let layer_sources = match (named, &rig.appearance) {
                (Some((index, _)), Some(a)) if material.layers[0] > 0 => {
                    appearance::material_layers(a, index)
                        .into_iter()
                        .map(|k| appearance::layer_source(rig, a, k))
                        .collect()
                }
                _ => Vec::new(),
            };
            let centroid =
                p.positions.iter().copied().sum::<Vec3>() / p.positions.len().max(1) as f32;
            if indices.len() as u32 > start {
                primitives.push(TopologyPrimitive {
                    indices: start..indices.len() as u32,
                    material,
                    textures,
                    layer_sources,
                    blend,
                    double_sided,
                    centroid: if centroid.is_finite() {
                        centroid
                    } else {
                        Vec3::ZERO
                    },
                });
            }
            first_vertex += p.positions.len() as u32;
        }
        let device = self.ctx.device();
        let scopes = Scopes::push(device);
        // Not `create_buffer_init`: it maps the buffer and panics if the device is gone, while a
        // queued write reports the loss through the error scope.
        let buffer = |label: &str, size: u64, usage: wgpu::BufferUsages| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: size.max(4),
                usage: usage | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            })
        };
        let index_buffer = buffer("render indices", bytes, wgpu::BufferUsages::INDEX);
        let attr_buffer = buffer("render attributes", attr_bytes, wgpu::BufferUsages::VERTEX);
        if !indices.is_empty() {
            self.ctx
                .queue()
                .write_buffer(&index_buffer, 0, bytemuck::cast_slice(&indices));
        }
        if !attrs.is_empty() {
            self.ctx
                .queue()
                .write_buffer(&attr_buffer, 0, bytemuck::cast_slice(&attrs));
        }
        scopes.pop("uploading a topology")?;
        self.ctx.health().map_err(lost)?;
        Ok(MeshTopology {
            ctx: self.ctx.clone(),
            indices: index_buffer,
            attrs: attr_buffer,
            appearance: gpu,
            primitives,
            vertices: vertex_count,
            triangles: (total_indices / 3) as u32,
            _charge: charge,
        })
    }

    /// The textures of `a` on this device: the upload another topology of the same rig
    /// appearance made while it is alive, else a new one.
    fn gpu_appearance(&self, a: &Arc<Appearance>) -> Result<Arc<GpuAppearance>, RenderError> {
        let live = |cache: &mut Vec<(Weak<Appearance>, Weak<GpuAppearance>)>| {
            cache.retain(|(_, g)| g.strong_count() > 0);
            cache
                .iter()
                .find(|(k, _)| std::ptr::eq(k.as_ptr(), Arc::as_ptr(a)))
                .and_then(|(_, g)| g.upgrade())
        };
        if let Some(g) = self.appearances.lock().ok().and_then(|mut c| live(&mut c)) {
            return Ok(g);
        }
        // Uploaded with no lock held: the charge may free what is kept for reuse. Two
        // topologies of one rig made at once may both upload; the later is kept in the cache.
        let scopes = Scopes::push(self.ctx.device());
        let uploaded = appearance::upload(
            &self.ctx,
            &self.texture_layout,
            &self.fallback,
            a,
            self.max_size,
        );
        scopes.pop("uploading a rig's textures")?;
        let g = Arc::new(uploaded?);
        if let Ok(mut c) = self.appearances.lock() {
            live(&mut c);
            c.push((Arc::downgrade(a), Arc::downgrade(&g)));
        }
        Ok(g)
    }

    /// Draws `meshes` (each once per instance) seen from `view` into a `frame`-sized picture
    /// and reads it back. No meshes gives the background alone.
    pub fn render(
        &self,
        meshes: &[SceneMesh<'_>],
        view: &View,
        frame: &Frame,
    ) -> Result<RenderOutput, RenderError> {
        self.render_until(meshes, view, frame, &Cancel::never())
    }

    /// [`Renderer::render`] that stops between passes (and before the readback) once `cancel`
    /// says so, with [`RenderError::Cancelled`]; a crowd of more than [`PASS_TRIANGLES`]
    /// triangles is drawn in several passes.
    pub fn render_until(
        &self,
        meshes: &[SceneMesh<'_>],
        view: &View,
        frame: &Frame,
        cancel: &Cancel,
    ) -> Result<RenderOutput, RenderError> {
        self.ctx.health().map_err(lost)?;
        let row = self.check_frame(frame)?;
        let camera = camera(view, frame)?;
        // Everything the input decides is checked and laid out before the device sees it.
        let layout = self.layout(meshes, view)?;

        let scopes = Scopes::push(self.ctx.device());
        let targets = self.take_targets(frame, row)?;
        let scratch = self.take_scratch(layout.scene_bytes, layout.uniform_bytes)?;
        self.upload(&layout, &camera, &scratch);
        let passes = self.encode_passes(&layout, frame, &targets, &scratch);
        let copy = self.encode_copy(frame, &targets, &scratch);
        let queue = self.ctx.queue();
        let start = Instant::now();
        let last = passes.len().saturating_sub(1);
        let mut pass_done = None;
        for (k, pass) in passes.into_iter().enumerate() {
            let done = queue.submit([pass]);
            if k < last {
                // Waited for, so that a cancelled render has at most one pass on the device. A
                // pass that failed validation was never submitted: its scope says why.
                if let Err(e) = self.ctx.device().poll(wgpu::PollType::Wait {
                    submission_index: Some(done.clone()),
                    timeout: None,
                }) {
                    scopes.pop("rendering")?;
                    return Err(lost(e));
                }
                if let Err(c) = cancel.check() {
                    scopes.pop("rendering")?;
                    return Err(c.into());
                }
            }
            pass_done = Some(done);
        }
        let copy_done = queue.submit([copy]);
        let mapped = MapResults::new();
        mapped.request(&targets.staging, ..);
        if let Some((_, _, read)) = &scratch.queries {
            mapped.request(read, 0..16);
        }
        scopes.pop("rendering")?;
        self.after_submit();

        self.ctx
            .device()
            .poll(wgpu::PollType::Wait {
                submission_index: pass_done,
                timeout: None,
            })
            .map_err(lost)?;
        let wall_render = nanos(start);
        // The copy is already queued; reading it back is the last thing a cancel can skip.
        cancel.check()?;
        let copy_start = Instant::now();
        // The callbacks, not only the submission: another thread's poll or submit may have
        // collected this frame's mappings and be about to report them (see `MapResults`).
        let expected = 1 + usize::from(scratch.queries.is_some());
        let mapped = mapped.wait(self.ctx.device(), copy_done, expected);
        self.ctx.health().map_err(lost)?;
        mapped
            .map_err(|e| RenderError::Device(format!("mapping the rendered frame failed: {e}")))?;
        let rgba = strip_padding(&targets, frame)?;
        let readback_ns = nanos(copy_start);
        let render_ns = self.pass_time(&scratch)?.unwrap_or(wall_render);
        self.keep(targets, scratch);
        Ok(RenderOutput {
            rgba,
            width: frame.width,
            height: frame.height,
            render_ns,
            readback_ns,
        })
    }

    /// Checks every mesh and places its instances and host vertex data in the scene buffer
    /// and its primitives' materials in the uniform buffer.
    fn layout<'a>(&self, meshes: &[SceneMesh<'a>], view: &View) -> Result<Layout<'a>, RenderError> {
        let mut draws = Vec::with_capacity(meshes.len());
        let mut scene_bytes = 0u64;
        let mut materials = 0u64;
        for (i, mesh) in meshes.iter().enumerate() {
            if let Some(draw) = self.plan(i, mesh, &mut scene_bytes, &mut materials)? {
                draws.push(draw);
            }
        }
        let uniform_bytes = (1 + materials) * self.uniform_align;
        // Dynamic offsets into the uniform buffer are u32.
        let uniform_limit = self.max_buffer.min(u64::from(u32::MAX));
        for (what, bytes, limit) in [
            ("vertex data", scene_bytes, self.max_buffer),
            ("uniforms", uniform_bytes, uniform_limit),
        ] {
            if bytes > limit {
                return Err(RenderError::TooLarge(format!(
                    "{bytes} bytes of {what} exceed the device's largest buffer ({limit} bytes)"
                )));
            }
        }
        let items = draw_order(&draws, view);
        Ok(Layout {
            draws,
            items,
            scene_bytes,
            uniform_bytes,
        })
    }

    /// Queues the uploads: instances and host vertex data into the scene buffer, the camera and
    /// one material slot per primitive draw into the uniform buffer.
    fn upload(&self, layout: &Layout<'_>, camera: &CameraUniform, scratch: &Scratch) {
        let queue = self.ctx.queue();
        for draw in &layout.draws {
            let instances: Vec<InstanceData> = draw
                .models
                .iter()
                .map(|m| {
                    let n = normal_matrix(m);
                    // The shader's `mirror`: a mirroring model turns front faces round.
                    let mirror = if mirrors(m) { -1.0 } else { 1.0 };
                    InstanceData {
                        model: m.to_cols_array(),
                        normal: [
                            n.x_axis.x, n.x_axis.y, n.x_axis.z, mirror, n.y_axis.x, n.y_axis.y,
                            n.y_axis.z, 0.0, n.z_axis.x, n.z_axis.y, n.z_axis.z, 0.0,
                        ],
                    }
                })
                .collect();
            queue.write_buffer(
                &scratch.scene,
                draw.instance_offset,
                bytemuck::cast_slice(&instances),
            );
            for bound in [&draw.positions, &draw.normals] {
                if let Bound::Scene { offset, data } = bound {
                    queue.write_buffer(&scratch.scene, *offset, bytemuck::cast_slice(data));
                }
            }
        }
        let mut uniforms = vec![0u8; layout.uniform_bytes as usize];
        uniforms[..size_of::<CameraUniform>()].copy_from_slice(bytemuck::bytes_of(camera));
        for draw in &layout.draws {
            for (k, p) in draw.topology.primitives.iter().enumerate() {
                let at = ((draw.first_material + k as u64) * self.uniform_align) as usize;
                let material = p.material.with_coefficients(&p.layer_sources, draw.layers);
                uniforms[at..at + size_of::<MaterialUniform>()]
                    .copy_from_slice(bytemuck::bytes_of(&material));
            }
        }
        queue.write_buffer(&scratch.uniforms, 0, &uniforms);
    }

    /// Records the render passes: the first clears, then per mesh one instanced draw per
    /// primitive, cut into passes of at most [`PASS_TRIANGLES`] triangles (a mesh with more
    /// instances than fit is split by instance ranges); the last resolves.
    fn encode_passes(
        &self,
        layout: &Layout<'_>,
        frame: &Frame,
        targets: &Targets,
        scratch: &Scratch,
    ) -> Vec<wgpu::CommandBuffer> {
        let device = self.ctx.device();
        let camera_bg = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("render camera"),
            layout: &self.camera_layout,
            entries: &[wgpu::BindGroupEntry {
                binding: 0,
                resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                    buffer: &scratch.uniforms,
                    offset: 0,
                    size: NonZeroU64::new(size_of::<CameraUniform>() as u64),
                }),
            }],
        });
        let material_bg = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("render material"),
            layout: &self.material_layout,
            entries: &[wgpu::BindGroupEntry {
                binding: 0,
                resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                    buffer: &scratch.uniforms,
                    offset: 0,
                    size: NonZeroU64::new(size_of::<MaterialUniform>() as u64),
                }),
            }],
        });
        let bg = frame.background.map(srgb_to_linear);
        let passes = pass_pieces(layout, self.pass_triangles());
        let n = passes.len();
        passes
            .into_iter()
            .enumerate()
            .map(|(k, pieces)| {
                let (first, last) = (k == 0, k + 1 == n);
                let mut encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
                    label: Some("render pass"),
                });
                {
                    // The first pass writes the start, the last the end (a pass in between
                    // writes neither: wgpu wants at least one index when timestamps are set).
                    let timestamp_writes =
                        scratch
                            .queries
                            .as_ref()
                            .filter(|_| first || last)
                            .map(|(set, _, _)| wgpu::RenderPassTimestampWrites {
                                query_set: set,
                                beginning_of_pass_write_index: first.then_some(0),
                                end_of_pass_write_index: last.then_some(1),
                            });
                    // Only the resolved picture is kept; between passes the multisampled
                    // colour and depth are.
                    let keep = if last {
                        wgpu::StoreOp::Discard
                    } else {
                        wgpu::StoreOp::Store
                    };
                    let color_load = if first {
                        wgpu::LoadOp::Clear(wgpu::Color {
                            r: bg[0],
                            g: bg[1],
                            b: bg[2],
                            a: 1.0,
                        })
                    } else {
                        wgpu::LoadOp::Load
                    };
                    let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
                        label: Some("crowd"),
                        color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                            view: &targets.msaa,
                            depth_slice: None,
                            resolve_target: last.then_some(&targets.resolve_view),
                            ops: wgpu::Operations {
                                load: color_load,
                                store: keep,
                            },
                        })],
                        depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                            view: &targets.depth,
                            depth_ops: Some(wgpu::Operations {
                                load: if first {
                                    wgpu::LoadOp::Clear(0.0)
                                } else {
                                    wgpu::LoadOp::Load
                                },
                                store: keep,
                            }),
                            stencil_ops: None,
                        }),
                        timestamp_writes,
                        occlusion_query_set: None,
                        multiview_mask: None,
                    });
                    pass.set_bind_group(0, &camera_bg, &[]);
                    for piece in pieces {
                        let item = &layout.items[piece.draw];
                        // Piece ranges count from the item's first instance.
                        let first = item.instances.start;
                        self.draw_piece(
                            &mut pass,
                            &layout.draws[item.draw],
                            item.primitive,
                            first + piece.instances.start..first + piece.instances.end,
                            scratch,
                            &material_bg,
                        );
                    }
                }
                encoder.finish()
            })
            .collect()
    }

    /// Records one mesh's instances `instances`: one instanced draw per opaque primitive
    /// (`primitive` `None`), or of blended primitive `primitive` alone.
    fn draw_piece(
        &self,
        pass: &mut wgpu::RenderPass<'_>,
        draw: &Draw<'_>,
        primitive: Option<usize>,
        instances: Range<u32>,
        scratch: &Scratch,
        material_bg: &wgpu::BindGroup,
    ) {
        let t = draw.topology;
        let attr = u64::from(t.vertices) * VERTEX_STRIDE;
        pass.set_index_buffer(t.indices.slice(..), wgpu::IndexFormat::Uint32);
        for (slot, bound) in [(0, &draw.positions), (1, &draw.normals)] {
            let (buffer, offset) = match bound {
                Bound::Scene { offset, .. } => (&scratch.scene, *offset),
                Bound::Device { buffer, offset } => (*buffer, *offset),
            };
            pass.set_vertex_buffer(slot, buffer.slice(offset..offset + attr));
        }
        let inst = u64::from(draw.instances) * size_of::<InstanceData>() as u64;
        pass.set_vertex_buffer(
            2,
            scratch
                .scene
                .slice(draw.instance_offset..draw.instance_offset + inst),
        );
        pass.set_vertex_buffer(3, t.attrs.slice(..));
        for (k, p) in t.primitives.iter().enumerate() {
            let wanted = match primitive {
                None => !p.blend,
                Some(only) => k == only,
            };
            if !wanted {
                continue;
            }
            let cull = draw.cull && !p.double_sided;
            pass.set_pipeline(&self.pipelines[pipeline_index(cull, p.blend)]);
            let offset = (draw.first_material + k as u64) * self.uniform_align;
            // Below `uniform_bytes`, checked to fit u32 above.
            let offset = u32::try_from(offset).unwrap_or(u32::MAX);
            pass.set_bind_group(1, material_bg, &[offset]);
            let textures = p
                .textures
                .and_then(|m| t.appearance.as_ref()?.group(m))
                .unwrap_or(&self.fallback.group);
            pass.set_bind_group(2, textures, &[]);
            pass.draw_indexed(p.indices.clone(), 0, instances.clone());
        }
    }

    /// Records the copy of the resolved picture into the staging buffer (rows padded to
    /// `COPY_BYTES_PER_ROW_ALIGNMENT`) and of the pass's timestamps.
    fn encode_copy(
        &self,
        frame: &Frame,
        targets: &Targets,
        scratch: &Scratch,
    ) -> wgpu::CommandBuffer {
        let mut encoder =
            self.ctx
                .device()
                .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                    label: Some("render readback"),
                });
        encoder.copy_texture_to_buffer(
            wgpu::TexelCopyTextureInfo {
                texture: &targets.resolve,
                mip_level: 0,
                origin: wgpu::Origin3d::ZERO,
                aspect: wgpu::TextureAspect::All,
            },
            wgpu::TexelCopyBufferInfo {
                buffer: &targets.staging,
                layout: wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(targets.row),
                    rows_per_image: Some(frame.height),
                },
            },
            wgpu::Extent3d {
                width: frame.width,
                height: frame.height,
                depth_or_array_layers: 1,
            },
        );
        if let Some((set, resolve, read)) = &scratch.queries {
            encoder.resolve_query_set(set, 0..2, resolve, 0);
            encoder.copy_buffer_to_buffer(resolve, 0, read, 0, 16);
        }
        encoder.finish()
    }

    /// GPU time of the render pass from its timestamps (mapped), when the device has them.
    fn pass_time(&self, scratch: &Scratch) -> Result<Option<u64>, RenderError> {
        let (Some((_, _, read)), Some(period)) = (&scratch.queries, self.timestamp_period) else {
            return Ok(None);
        };
        let mut ticks = [0u64; 2];
        {
            let view = read.get_mapped_range(0..16).map_err(lost)?;
            bytemuck::cast_slice_mut::<u64, u8>(&mut ticks).copy_from_slice(&view);
        }
        read.unmap();
        // A device whose counter misbehaves (end before start) keeps the wall time.
        Ok((ticks[1] > ticks[0]).then(|| ((ticks[1] - ticks[0]) as f64 * period) as u64))
    }

    /// Checks the frame's size; returns the padded bytes per row of the readback copy.
    fn check_frame(&self, frame: &Frame) -> Result<u32, RenderError> {
        let (w, h) = (frame.width, frame.height);
        if w == 0 || h == 0 {
            return Err(RenderError::Invalid(format!(
                "a {w}×{h} frame has no pixels"
            )));
        }
        if w > self.max_size || h > self.max_size {
            return Err(RenderError::TooLarge(format!(
                "a {w}×{h} frame is past the device's largest texture ({} pixels a side)",
                self.max_size
            )));
        }
        if let Some(c) = frame.background.iter().find(|c| !c.is_finite()) {
            return Err(RenderError::Invalid(format!(
                "background channel {c} is not finite"
            )));
        }
        // At most 4 · 2^32 bytes: no overflow in u64, and it fits u32 for texture sizes the
        // limit allows (checked below rather than assumed).
        let row =
            (u64::from(w) * 4).next_multiple_of(u64::from(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT));
        let staging = row * u64::from(h);
        if staging > self.max_buffer {
            return Err(RenderError::TooLarge(format!(
                "a {w}×{h} frame needs a {staging}-byte readback buffer, past the device's \
                 largest buffer ({} bytes)",
                self.max_buffer
            )));
        }
        u32::try_from(row).map_err(|_| RenderError::TooLarge(format!("{w} pixels wide")))
    }

    /// Checks one mesh and reserves its place in the scene and uniform buffers; `None` when it
    /// draws nothing (no instances or no triangles).
    fn plan<'a>(
        &self,
        i: usize,
        mesh: &SceneMesh<'a>,
        scene_bytes: &mut u64,
        materials: &mut u64,
    ) -> Result<Option<Draw<'a>>, RenderError> {
        let t = mesh.topology;
        if !Arc::ptr_eq(&t.ctx, &self.ctx) {
            return Err(RenderError::Invalid(format!(
                "mesh {i}: its topology was uploaded to another device"
            )));
        }
        if let Some(k) = mesh.instances.iter().position(|m| !m.is_finite()) {
            return Err(RenderError::Invalid(format!(
                "mesh {i}: instance {k}'s model matrix is not finite"
            )));
        }
        let instances = u32::try_from(mesh.instances.len()).map_err(|_| {
            RenderError::TooLarge(format!("mesh {i}: {} instances", mesh.instances.len()))
        })?;
        let attr = u64::from(t.vertices) * VERTEX_STRIDE;
        // Sources are checked whether or not the mesh draws anything: a bad one is a caller's
        // bug either way.
        let check = |what: &str, source: &VertexSource<'a>| -> Result<(), RenderError> {
            match *source {
                VertexSource::Host(data) => {
                    let want = u64::from(t.vertices) * 3;
                    if data.len() as u64 != want {
                        return Err(RenderError::Invalid(format!(
                            "mesh {i}: {} host {what} floats for a topology of {} vertices \
                             (expected {want})",
                            data.len(),
                            t.vertices,
                        )));
                    }
                }
                VertexSource::Device { buffer, offset } => {
                    if !buffer.usage().contains(wgpu::BufferUsages::VERTEX) {
                        return Err(RenderError::Invalid(format!(
                            "mesh {i}: the {what} buffer was not created with VERTEX usage"
                        )));
                    }
                    if !offset.is_multiple_of(wgpu::VERTEX_ALIGNMENT) {
                        return Err(RenderError::Invalid(format!(
                            "mesh {i}: {what} offset {offset} is not a multiple of {}",
                            wgpu::VERTEX_ALIGNMENT
                        )));
                    }
                    if offset
                        .checked_add(attr)
                        .is_none_or(|end| end > buffer.size())
                    {
                        return Err(RenderError::Invalid(format!(
                            "mesh {i}: the {what} buffer holds {} bytes; {attr} bytes ({} \
                             vertices) from offset {offset} run past its end",
                            buffer.size(),
                            t.vertices
                        )));
                    }
                }
            }
            Ok(())
        };
        check("position", &mesh.positions)?;
        check("normal", &mesh.normals)?;
        if !drawn(mesh) {
            return Ok(None);
        }
        let mut place = |source: &VertexSource<'a>| match *source {
            VertexSource::Host(data) => {
                let offset = *scene_bytes;
                *scene_bytes += attr.next_multiple_of(16);
                Bound::Scene { offset, data }
            }
            VertexSource::Device { buffer, offset } => Bound::Device { buffer, offset },
        };
        let positions = place(&mesh.positions);
        let normals = place(&mesh.normals);
        let instance_offset = *scene_bytes;
        *scene_bytes +=
            (u64::from(instances) * size_of::<InstanceData>() as u64).next_multiple_of(16);
        let first_material = 1 + *materials;
        *materials += t.primitives.len() as u64;
        Ok(Some(Draw {
            topology: t,
            positions,
            normals,
            models: mesh.instances,
            layers: mesh.layers,
            instance_offset,
            instances,
            first_material,
            cull: !mesh.instances.iter().any(mirrors),
        }))
    }

    /// The pooled targets when they have this size, else new ones, charged to the device's
    /// memory budget first (pooled ones of another size are dropped, and their charge given
    /// back, before). The charge may free what is kept for reuse (ours included), so no lock
    /// of `kept` is held across it.
    fn take_targets(&self, frame: &Frame, row: u32) -> Result<Targets, RenderError> {
        let pooled = self.kept.targets.lock().ok().and_then(|mut t| t.take());
        if let Some(t) = pooled
            && t.width == frame.width
            && t.height == frame.height
        {
            return Ok(t);
        }
        let charge = self
            .ctx
            .charge(Targets::bytes_of(frame.width, frame.height, row), || {
                format!(
                    "the render targets of a {}×{} frame",
                    frame.width, frame.height
                )
            })?;
        let device = self.ctx.device();
        let size = wgpu::Extent3d {
            width: frame.width,
            height: frame.height,
            depth_or_array_layers: 1,
        };
        let texture = |label: &str, format, samples, usage| {
            device.create_texture(&wgpu::TextureDescriptor {
                label: Some(label),
                size,
                mip_level_count: 1,
                sample_count: samples,
                dimension: wgpu::TextureDimension::D2,
                format,
                usage,
                view_formats: &[],
            })
        };
        let msaa = texture(
            "render msaa",
            COLOR_FORMAT,
            SAMPLES,
            wgpu::TextureUsages::RENDER_ATTACHMENT,
        );
        let depth = texture(
            "render depth",
            DEPTH_FORMAT,
            SAMPLES,
            wgpu::TextureUsages::RENDER_ATTACHMENT,
        );
        let resolve = texture(
            "render resolve",
            COLOR_FORMAT,
            1,
            wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
        );
        let staging = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("render staging"),
            size: u64::from(row) * u64::from(frame.height),
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let view = |t: &wgpu::Texture| t.create_view(&wgpu::TextureViewDescriptor::default());
        Ok(Targets {
            width: frame.width,
            height: frame.height,
            msaa: view(&msaa),
            depth: view(&depth),
            resolve_view: view(&resolve),
            resolve,
            staging,
            row,
            charge,
        })
    }

    /// The pooled buffers, each replaced by a new one (charged to the device's memory budget
    /// first, with no lock of `kept` held) when too small.
    fn take_scratch(&self, scene_bytes: u64, uniform_bytes: u64) -> Result<Scratch, RenderError> {
        let device = self.ctx.device();
        let buffer = |label: &str, size: u64, usage: wgpu::BufferUsages| {
            // Rounded up so that slightly different scenes reuse the buffer.
            let size = size
                .max(256)
                .next_multiple_of(64 << 10)
                .min(self.max_buffer);
            let charge = self
                .ctx
                .charge(size, || format!("a render's {label} buffer ({size} bytes)"))?;
            let buffer = device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size,
                usage,
                mapped_at_creation: false,
            });
            Ok::<_, RenderError>((buffer, charge))
        };
        let pooled = self.kept.scratch.lock().ok().and_then(|mut s| s.take());
        let (scene, uniforms, queries) = match pooled {
            Some(s) => (
                Some((s.scene, s.scene_charge)),
                Some((s.uniforms, s.uniforms_charge)),
                s.queries,
            ),
            None => (None, None, None),
        };
        // A pooled buffer too small is dropped (its charge given back) before its replacement
        // is charged.
        let (scene, scene_charge) = match scene.filter(|(b, _)| b.size() >= scene_bytes) {
            Some(kept) => kept,
            None => buffer(
                "render scene",
                scene_bytes,
                wgpu::BufferUsages::VERTEX | wgpu::BufferUsages::COPY_DST,
            )?,
        };
        let (uniforms, uniforms_charge) = match uniforms.filter(|(b, _)| b.size() >= uniform_bytes)
        {
            Some(kept) => kept,
            None => buffer(
                "render uniforms",
                uniform_bytes,
                wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            )?,
        };
        let queries = queries.or_else(|| {
            self.timestamp_period.map(|_| {
                let small = |label: &str, usage| {
                    device.create_buffer(&wgpu::BufferDescriptor {
                        label: Some(label),
                        size: 16,
                        usage,
                        mapped_at_creation: false,
                    })
                };
                (
                    device.create_query_set(&wgpu::QuerySetDescriptor {
                        label: Some("render timestamps"),
                        ty: wgpu::QueryType::Timestamp,
                        count: 2,
                    }),
                    small(
                        "render timestamps",
                        wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
                    ),
                    small(
                        "render timestamps readback",
                        wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                    ),
                )
            })
        });
        Ok(Scratch {
            scene,
            uniforms,
            queries,
            scene_charge,
            uniforms_charge,
        })
    }

    /// Returns a successful render's targets and buffers to the pool when they are small
    /// enough to keep; a failed render drops its own.
    fn keep(&self, targets: Targets, scratch: Scratch) {
        if targets.bytes() + scratch.bytes() > RETAIN_BYTES {
            return;
        }
        if let Ok(mut t) = self.kept.targets.lock() {
            *t = Some(targets);
        }
        if let Ok(mut s) = self.kept.scratch.lock() {
            *s = Some(scratch);
        }
    }
}

/// A range of one draw's instances, drawn in one pass.
#[derive(Clone, Debug, PartialEq, Eq)]
struct Piece {
    draw: usize,
    instances: Range<u32>,
}

/// The draw order's items cut into passes of at most `budget` triangles (instances × the
/// item's triangles); an item with more is split by instance ranges, and one instance larger
/// than `budget` is a pass of its own. Always at least one pass, so the frame is cleared and
/// resolved. (A [`Piece`]'s `draw` is an index into [`Layout::items`], its instances relative
/// to the item's first.)
fn pass_pieces(layout: &Layout<'_>, budget: u64) -> Vec<Vec<Piece>> {
    let sizes: Vec<(u64, u32)> = layout
        .items
        .iter()
        .map(|i| (i.triangles, i.instances.end - i.instances.start))
        .collect();
    cut_passes(&sizes, budget)
}

/// The texture coordinates primitive `p`'s normal map reads, when its material has a normal
/// texture with decoded pixels and the primitive has that coordinate set.
fn normal_map_set<'a>(rig: &Rig, p: &'a Primitive) -> Option<&'a [glam::Vec2]> {
    let a = rig.appearance.as_ref()?;
    let m = a.materials.get(p.look.material? as usize)?;
    let r = m.normal_texture.as_ref()?;
    a.image_of(r)?.pixels.as_ref()?;
    match r.tex_coord {
        0 => p.look.uv0.as_deref(),
        1 => p.look.uv1.as_deref(),
        _ => None,
    }
}

/// Whether a model matrix mirrors (its 3×3 has a negative determinant).
fn mirrors(m: &Mat4) -> bool {
    Mat3::from_mat4(*m).determinant() < 0.0
}

/// [`pass_pieces`] over (triangles per instance, instances) per draw.
fn cut_passes(sizes: &[(u64, u32)], budget: u64) -> Vec<Vec<Piece>> {
    let budget = budget.max(1);
    let mut passes: Vec<Vec<Piece>> = vec![Vec::new()];
    let mut room = budget;
    for (draw, &(triangles, instances)) in sizes.iter().enumerate() {
        let triangles = triangles.max(1);
        let mut next = 0u32;
        while next < instances {
            if room < triangles && passes.last().is_some_and(|p| !p.is_empty()) {
                passes.push(Vec::new());
                room = budget;
            }
            let fit = (room / triangles).max(1);
            let end = u64::from(next)
                .saturating_add(fit)
                .min(u64::from(instances)) as u32;
            if let Some(pass) = passes.last_mut() {
                pass.push(Piece {
                    draw,
                    instances: next..end,
                });
            }
            room = room.saturating_sub(u64::from(end - next) * triangles);
            next = end;
        }
    }
    passes
}

/// The picture from the mapped staging buffer, without the rows' padding; unmaps it.
fn strip_padding(targets: &Targets, frame: &Frame) -> Result<Vec<u8>, RenderError> {
    let width_bytes = frame.width as usize * 4;
    let mut rgba = Vec::with_capacity(width_bytes * frame.height as usize);
    {
        let view = targets.staging.get_mapped_range(..).map_err(lost)?;
        // The copy's rows are padded to 256 bytes; the picture's are not.
        for padded in view.chunks_exact(targets.row as usize) {
            rgba.extend_from_slice(&padded[..width_bytes]);
        }
    }
    targets.staging.unmap();
    Ok(rgba)
}

/// Whether a mesh draws anything.
fn drawn(mesh: &SceneMesh<'_>) -> bool {
    !mesh.instances.is_empty() && mesh.topology.triangles > 0
}

/// The camera uniform for a view: reversed-Z perspective times the look-at view, and the
/// lights turned from view space (fixed relative to the camera) into world space.
fn camera(view: &View, frame: &Frame) -> Result<CameraUniform, RenderError> {
    let finite = view.eye.is_finite()
        && view.target.is_finite()
        && view.up.is_finite()
        && view.fov_y_deg.is_finite()
        && view.near.is_finite()
        && view.far.is_finite();
    if !finite {
        return Err(RenderError::Invalid(format!(
            "a view with non-finite values: {view:?}"
        )));
    }
    if !(view.fov_y_deg > 0.0 && view.fov_y_deg < 180.0) {
        return Err(RenderError::Invalid(format!(
            "field of view {}° is not in (0, 180)",
            view.fov_y_deg
        )));
    }
    if !(view.near > 0.0 && view.far > view.near) {
        return Err(RenderError::Invalid(format!(
            "near {} and far {} need 0 < near < far",
            view.near, view.far
        )));
    }
    let forward = (view.target - view.eye).normalize_or_zero();
    let right = forward.cross(view.up).normalize_or_zero();
    if forward == Vec3::ZERO || right == Vec3::ZERO {
        return Err(RenderError::Invalid(
            "the eye is at the target, or up is parallel to the view direction".into(),
        ));
    }
    // Depth 1 at the near plane and 0 at the far plane (reversed Z); the scene layout checked
    // this same matrix, so a request's view never fails here.
    let view_proj = view.clip_from_world(frame.width as f32 / frame.height as f32);
    if !view_proj.is_finite() {
        return Err(RenderError::Invalid(format!(
            "the view gives a non-finite projection: {view:?}"
        )));
    }
    let lights = brdf::reference_lights(view)
        .ok_or_else(|| RenderError::Invalid("a view without a direction has no lights".into()))?;
    let light = |l: brdf::DirectionalLight| l.direction.extend(l.intensity).to_array();
    Ok(CameraUniform {
        view_proj: view_proj.to_cols_array(),
        eye: view.eye.extend(1.0).to_array(),
        key: light(lights.key),
        fill: light(lights.fill),
        up: lights.up.extend(0.0).to_array(),
        sky: lights.sky.extend(0.0).to_array(),
        ground: lights.ground.extend(0.0).to_array(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn normal_matrix_is_the_inverse_transpose_up_to_a_positive_scale() {
        let models = [
            Mat4::IDENTITY,
            Mat4::from_scale(Vec3::new(2.0, 0.5, 3.0)),
            Mat4::from_scale_rotation_translation(
                Vec3::new(1.0, 4.0, 0.25),
                glam::Quat::from_euler(glam::EulerRot::XYZ, 0.3, -1.1, 2.0),
                Vec3::new(5.0, -2.0, 1.0),
            ),
            // A mirror: outward normals must stay outward.
            Mat4::from_scale(Vec3::new(-1.0, 1.0, 1.0)),
            Mat4::from_scale(Vec3::splat(1e-20)),
            Mat4::from_scale(Vec3::new(1e4, 1e-4, 1.0)),
        ];
        for m in models {
            // The reference in f64, where these scales neither underflow nor overflow.
            let want = glam::DMat3::from_mat4(m.as_dmat4()).inverse().transpose();
            let got = normal_matrix(&m);
            for v in [Vec3::X, Vec3::Y, Vec3::Z, Vec3::new(0.3, -0.7, 0.2)] {
                let a = (want * v.as_dvec3()).normalize().as_vec3();
                let b = (got * v).normalize();
                assert!((a - b).length() < 1e-5, "{m:?} {v:?}: {a:?} vs {b:?}");
            }
        }
    }

    /// The size and member offsets naga computes for the WGSL struct `name` of render.wgsl.
    fn wgsl_layout(name: &str) -> (u32, Vec<(String, u32)>) {
        let src = include_str!("../../shaders/render.wgsl");
        let module = naga::front::wgsl::parse_str(src).expect("render.wgsl parses");
        for (_, ty) in module.types.iter() {
            if ty.name.as_deref() != Some(name) {
                continue;
            }
            if let naga::TypeInner::Struct { members, span } = &ty.inner {
                let offsets = members
                    .iter()
                    .map(|m| (m.name.clone().unwrap_or_default(), m.offset))
                    .collect();
                return (*span, offsets);
            }
        }
        panic!("render.wgsl has no struct {name}");
    }

    #[test]
    fn uniform_structs_match_the_shaders_layout() {
        use std::mem::offset_of;
        let check = |name: &str, size: usize, fields: &[(&str, usize)]| {
            let (span, members) = wgsl_layout(name);
            assert_eq!(span as usize, size, "{name}: size");
            let got: Vec<(&str, usize)> = members
                .iter()
                .map(|(n, o)| (n.as_str(), *o as usize))
                .collect();
            assert_eq!(got, fields, "{name}: members and offsets");
        };
        check(
            "Camera",
            size_of::<CameraUniform>(),
            &[
                ("view_proj", offset_of!(CameraUniform, view_proj)),
                ("eye", offset_of!(CameraUniform, eye)),
                ("key", offset_of!(CameraUniform, key)),
                ("fill", offset_of!(CameraUniform, fill)),
                ("up", offset_of!(CameraUniform, up)),
                ("sky", offset_of!(CameraUniform, sky)),
                ("ground", offset_of!(CameraUniform, ground)),
            ],
        );
        check(
            "Material",
            size_of::<MaterialUniform>(),
            &[
                ("base", offset_of!(MaterialUniform, base)),
                ("emissive", offset_of!(MaterialUniform, emissive)),
                ("pbr", offset_of!(MaterialUniform, pbr)),
                ("alpha", offset_of!(MaterialUniform, alpha)),
                // `sets` is two vec4<u32> in WGSL (an array of u32 would be padded to 16
                // bytes an element in a uniform).
                ("sets", offset_of!(MaterialUniform, sets)),
                ("sets2", offset_of!(MaterialUniform, sets) + 16),
                ("transforms", offset_of!(MaterialUniform, transforms)),
                ("layers", offset_of!(MaterialUniform, layers)),
                ("coefficients", offset_of!(MaterialUniform, coefficients)),
            ],
        );
    }

    #[test]
    fn a_draws_coefficients_come_from_its_jobs_inputs_clamped_where_asked() {
        let mut u = MaterialUniform::of(&Material::default());
        u.layers[0] = 3;
        let sources = [Some((1, true)), None, Some((0, false)), Some((2, true))];
        let c = u.with_coefficients(&sources, &[-2.5, 1.7, 0.3]);
        // Layer 0 reads input 1 clamped, layer 1 has no source, layer 2 input 0 signed; the
        // fourth source is past the material's three layers.
        assert_eq!(c.coefficients[0], [1.0, 0.0, -2.5, 0.0]);
        // Inputs shorter than a source (a rig without layers sends none): zero.
        assert_eq!(u.with_coefficients(&sources, &[]).coefficients[0], [0.0; 4]);
    }

    #[test]
    fn material_uniforms_keep_nans_and_out_of_range_factors_out_of_the_shader() {
        let m = Material {
            base_color_factor: [f32::NAN, 2.0, -1.0, 0.5],
            metallic_factor: f32::INFINITY,
            roughness_factor: -3.0,
            emissive_factor: [0.5, f32::NAN, 1.0],
            emissive_strength: 4.0,
            alpha_mode: AlphaMode::Mask,
            alpha_cutoff: f32::NAN,
            double_sided: true,
            ..Material::default()
        };
        let u = MaterialUniform::of(&m);
        assert_eq!(u.base, [1.0, 1.0, 0.0, 0.5]);
        assert_eq!(u.pbr, [1.0, 0.0, 1.0, 1.0]);
        assert_eq!(u.emissive, [2.0, 0.0, 4.0, 0.0]);
        assert_eq!(u.alpha, [0.5, 1.0, 0.0, 1.0]);
        assert!(
            bytemuck::cast_slice::<MaterialUniform, f32>(&[u])
                .iter()
                .all(|v| v.is_finite())
        );
    }

    #[test]
    fn passes_hold_at_most_their_triangles_and_draw_every_instance_once() {
        // One pass for a small crowd, even an empty one.
        assert_eq!(cut_passes(&[], 100).len(), 1);
        assert_eq!(
            cut_passes(&[(10, 3), (5, 2)], 100),
            vec![vec![
                Piece {
                    draw: 0,
                    instances: 0..3
                },
                Piece {
                    draw: 1,
                    instances: 0..2
                }
            ]]
        );
        // Split by instance ranges; an instance larger than the budget is a pass of its own.
        let sizes = [(30u64, 10u32), (7, 1), (250, 2), (1, 0), (40, 5)];
        let passes = cut_passes(&sizes, 100);
        let mut drawn = vec![0u32; sizes.len()];
        for pass in &passes {
            assert!(!pass.is_empty());
            let tris: u64 = pass
                .iter()
                .map(|p| u64::from(p.instances.end - p.instances.start) * sizes[p.draw].0)
                .sum();
            let lone_big = pass.len() == 1 && sizes[pass[0].draw].0 > 100;
            assert!(tris <= 100 || lone_big, "{pass:?}: {tris}");
            for p in pass {
                assert_eq!(p.instances.start, drawn[p.draw], "in order, no gaps");
                drawn[p.draw] = p.instances.end;
            }
        }
        assert_eq!(drawn, vec![10, 1, 2, 0, 5]);
    }

    #[test]
    fn srgb_decoding_matches_the_curve() {
        assert_eq!(srgb_to_linear(0.0), 0.0);
        assert!((srgb_to_linear(1.0) - 1.0).abs() < 1e-12);
        assert!((srgb_to_linear(0.5) - 0.214_041).abs() < 1e-5);
    }

    #[test]
    fn bad_views_are_refused() {
        let frame = Frame {
            width: 4,
            height: 4,
            background: [0.0; 3],
        };
        let good = View {
            eye: Vec3::new(0.0, 0.0, 5.0),
            target: Vec3::ZERO,
            up: Vec3::Y,
            fov_y_deg: 30.0,
            near: 0.1,
            far: 100.0,
        };
        assert!(camera(&good, &frame).is_ok());
        for bad in [
            View {
                eye: Vec3::ZERO,
                ..good
            },
            View {
                up: Vec3::Z,
                ..good
            },
            View {
                fov_y_deg: 0.0,
                ..good
            },
            View {
                fov_y_deg: 180.0,
                ..good
            },
            View { near: 0.0, ..good },
            View { far: 0.1, ..good },
            View {
                near: f32::NAN,
                ..good
            },
        ] {
            assert!(
                matches!(camera(&bad, &frame), Err(RenderError::Invalid(_))),
                "{bad:?}"
            );
        }
    }
}
