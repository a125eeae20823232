//! The engine's WGSL modules and the compute pipelines made from them: [`SHADERS`] (each pass's
//! file after the shared pieces it uses), and [`Pipelines`], one per entry point, made once
//! per context.
//!
//! Invariants: the engine compiles exactly [`SHADERS`] (which `crates/engine/tests/shaders.rs`
//! validates); a pipeline is named after its WGSL entry point, which is also the name of the
//! function in `passes` that dispatches it and of its CPU mirror; bind group layouts are the
//! shaders' own (`layout: None`).

use super::layout::DeltaFormat;
use crate::Precision;

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

/// The engine's compute pipelines, one per entry point it dispatches (and per `blend` output).
pub(super) struct Pipelines {
    pub(super) active: wgpu::ComputePipeline,
    pub(super) blend: BlendPipelines,
    /// `blend` reading binary16 deltas (its `F16_DELTAS` override set), made only on a
    /// context whose rigs store them ([`GpuOptions::deltas`]).
    pub(super) blend_f16: Option<BlendPipelines>,
    pub(super) face: wgpu::ComputePipeline,
    pub(super) vertex: wgpu::ComputePipeline,
    pub(super) pack: wgpu::ComputePipeline,
    pub(super) pack_q16: wgpu::ComputePipeline,
    pub(super) pack_q16r: wgpu::ComputePipeline,
    pub(super) skin: wgpu::ComputePipeline,
}

impl Pipelines {
    /// Compiles [`SHADERS`] on `device` and makes every pipeline, `blend`'s binary16-delta ones
    /// only where rigs store their deltas so (`deltas`).
    pub(super) fn new(device: &wgpu::Device, deltas: DeltaFormat) -> Pipelines {
        let [active, blend, face, vertex, pack, pack_q16, skin] =
            SHADERS.map(|(name, source)| shader(device, name, source));
        Pipelines {
            active: pipeline(device, &active, "build_active"),
            blend: BlendPipelines::new(device, &blend, false),
            blend_f16: (deltas == DeltaFormat::F16)
                .then(|| BlendPipelines::new(device, &blend, true)),
            face: pipeline(device, &face, "face_normals"),
            vertex: pipeline(device, &vertex, "vertex_normals"),
            pack: pipeline(device, &pack, "pack_f16"),
            pack_q16: pipeline(device, &pack_q16, "pack_q16"),
            pack_q16r: pipeline(device, &pack_q16, "pack_q16r"),
            skin: pipeline(device, &skin, "skin"),
        }
    }
}

/// `blend` for each output it writes (its `PACK` override): f32, or the 16-bit wire formats
/// (q16r's planes too) written by the blend itself where nothing reads f32 positions after it.
pub(super) struct BlendPipelines {
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
    pub(super) fn writing(
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
