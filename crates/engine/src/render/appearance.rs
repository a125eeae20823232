//! A rig's appearance on the renderer's device: its images as textures with their mip chains,
//! the glTF samplers, one texture bind group per material, and the static per-vertex
//! attributes (texture coordinates, vertex colours, tangents) every topology carries.
//!
//! Why it is built this way:
//! - Images are uploaded as `Rgba8Unorm` with an `Rgba8UnormSrgb` view format: one texture
//!   serves a colour slot (base colour, emissive: sampled through the sRGB view, so the
//!   hardware decodes before filtering, as glTF asks) and a data slot (metallic-roughness,
//!   normal, occlusion: the linear view) alike. The mip chain is the one the import made
//!   ([`crowdmorph_core::rig::Mips`]), so minification filters the same levels on every device.
//! - A [`GpuAppearance`] belongs to one [`Appearance`] (an `Arc` every generation, mesh level
//!   and clone of a rig shares), so the renderer uploads it once however many topologies of the
//!   rig draw with it, and it is freed — its memory given back to `--max-gpu-memory` — when the
//!   last of them is dropped (the server's cache purges them when the rig is deleted).
//! - Every byte is charged to the device's budget before it is allocated; an image whose
//!   pixels were not decoded (`ImageData::pixels` is `None`), or a slot without an image, draws
//!   as if the material had no texture there, never as an error.
//! - Attributes are static: they do not move with morph targets, so they are uploaded once per
//!   topology beside its indices, 32 bytes a vertex (f32 texture coordinates, unorm16 colours,
//!   snorm16 tangents), and nothing per frame.

use std::sync::Arc;

use crowdmorph_core::budget::{BudgetError, Charge};
use crowdmorph_core::rig::{
    Appearance, Filter, MAX_LAYERS, MipLevel, Primitive, Rig, Sampler, Slot, Wrap,
};

use super::brdf::srgb8_to_linear;
use crate::gpu::GpuContext;

/// Texture slots of a material, in binding order: base colour, metallic-roughness, normal,
/// occlusion, emissive (the shader's bindings 0–4 and their samplers 5–9).
pub(super) const SLOTS: [Slot; 5] = [
    Slot::BaseColor,
    Slot::MetallicRoughness,
    Slot::Normal,
    Slot::Occlusion,
    Slot::Emissive,
];

/// The texture coordinate set of a slot the material leaves empty (the shader's
/// `NO_TEXTURE`).
pub(super) const NO_TEXTURE: u32 = 255;

/// Binding of a material's layers (`layer_tex`, a 2D array of signed linear RGBA).
const LAYER_BINDING: u32 = 2 * SLOTS.len() as u32;

/// The format of layers: signed (a wrinkle darkens as often as it lightens), linear, and
/// filterable everywhere; 11 bits of mantissa keep a layer within 1/2048 of its value.
const LAYER_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba16Float;

/// Bytes of one layer texel.
const LAYER_TEXEL: u64 = 8;

/// What one layer of a material is made of, in the order the material sums them (see
/// `crowdmorph_core::rig::animated_texture`): its target textures, then each clip texture's
/// mean and components.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LayerKind {
    /// `Appearance::target_textures[i]` − the base.
    Target(usize),
    /// `Appearance::clip_textures[i]`'s mean − the base.
    ClipMean(usize),
    /// Component `k` of `Appearance::clip_textures[i]`.
    ClipComponent(usize, usize),
}

impl LayerKind {
    /// Its name in `GET /v1/rigs/{id}/layers`.
    pub fn name(self) -> &'static str {
        match self {
            LayerKind::Target(_) => "target",
            LayerKind::ClipMean(_) => "clip_mean",
            LayerKind::ClipComponent(..) => "clip_component",
        }
    }
}

/// The layers material `m` of `a` sums, at most [`MAX_LAYERS`] (validation refuses more).
pub fn material_layers(a: &Appearance, m: usize) -> Vec<LayerKind> {
    let mut out: Vec<LayerKind> = a
        .target_textures
        .iter()
        .enumerate()
        .filter(|(_, t)| t.material as usize == m)
        .map(|(i, _)| LayerKind::Target(i))
        .collect();
    for (i, t) in a.clip_textures.iter().enumerate() {
        if t.material as usize == m {
            out.push(LayerKind::ClipMean(i));
            out.extend((0..t.layers()).map(|k| LayerKind::ClipComponent(i, k)));
        }
    }
    out.truncate(MAX_LAYERS);
    out
}

/// Where layer `kind` of a rig reads its coefficient in the job's
/// `crowdmorph_core::rig::layer_inputs` vector, and whether it is clamped to [0, 1] (a
/// target's weight is; PCA coefficients are signed). `None`: never drawn (a target name the
/// rig does not have).
pub fn layer_source(rig: &Rig, a: &Appearance, kind: LayerKind) -> Option<(u32, bool)> {
    let clip_at = |i: usize| -> usize {
        rig.targets.len()
            + a.clip_textures[..i.min(a.clip_textures.len())]
                .iter()
                .map(|t| 1 + t.layers())
                .sum::<usize>()
    };
    match kind {
        LayerKind::Target(i) => {
            let name = &a.target_textures.get(i)?.target;
            let t = *rig.target_ids(name).first()?;
            Some((t, true))
        }
        LayerKind::ClipMean(i) => Some((clip_at(i) as u32, false)),
        LayerKind::ClipComponent(i, k) => Some((clip_at(i) as u32 + 1 + k as u32, false)),
    }
}

/// An RGBA8 sRGB level as linear RGBA f32 (alpha is linear already).
fn linear_level(l: &MipLevel) -> Vec<[f32; 4]> {
    l.rgba
        .chunks_exact(4)
        .map(|p| {
            [
                srgb8_to_linear(p[0]),
                srgb8_to_linear(p[1]),
                srgb8_to_linear(p[2]),
                f32::from(p[3]) / 255.0,
            ]
        })
        .collect()
}

/// `src` (`sw × sh`) resampled to `w × h` by the nearest texel (the identity when the sizes
/// agree).
fn resample(src: &[[f32; 4]], sw: u32, sh: u32, w: u32, h: u32) -> Vec<[f32; 4]> {
    if (sw, sh) == (w, h) {
        return src.to_vec();
    }
    let mut out = Vec::with_capacity(w as usize * h as usize);
    for y in 0..h {
        let sy = ((u64::from(y) * 2 + 1) * u64::from(sh) / (2 * u64::from(h))) as usize;
        for x in 0..w {
            let sx = ((u64::from(x) * 2 + 1) * u64::from(sw) / (2 * u64::from(w))) as usize;
            out.push(src[sy.min(sh as usize - 1) * sw as usize + sx.min(sw as usize - 1)]);
        }
    }
    out
}

/// The next mip level of `src` (`w × h`): the mean of each 2×2 block (of what exists at an
/// odd edge), in linear values, as a mip of a linear quantity should be.
fn halve(src: &[[f32; 4]], w: u32, h: u32) -> Vec<[f32; 4]> {
    let (nw, nh) = ((w / 2).max(1), (h / 2).max(1));
    let mut out = Vec::with_capacity(nw as usize * nh as usize);
    for y in 0..nh {
        for x in 0..nw {
            let mut sum = [0f32; 4];
            let mut n = 0f32;
            for dy in 0..2 {
                for dx in 0..2 {
                    let (sx, sy) = (x * 2 + dx, y * 2 + dy);
                    if sx < w && sy < h {
                        let p = src[(sy * w + sx) as usize];
                        for c in 0..4 {
                            sum[c] += p[c];
                        }
                        n += 1.0;
                    }
                }
            }
            out.push(sum.map(|v| v / n.max(1.0)));
        }
    }
    out
}

/// A source of layer texels: an image's linear levels, or a float array at its own size.
enum LayerSource<'a> {
    Image(&'a [MipLevel]),
    Float { rgb: &'a [f32], w: u32, h: u32 },
}

impl LayerSource<'_> {
    /// Level 0 as linear RGBA at `w × h`.
    fn level0(&self, w: u32, h: u32) -> Vec<[f32; 4]> {
        match self {
            LayerSource::Image(levels) => match levels.first() {
                Some(l) => resample(&linear_level(l), l.width, l.height, w, h),
                None => vec![[0.0; 4]; w as usize * h as usize],
            },
            LayerSource::Float { rgb, w: sw, h: sh } => {
                let px: Vec<[f32; 4]> = rgb
                    .chunks_exact(3)
                    .map(|c| [c[0], c[1], c[2], 0.0])
                    .collect();
                resample(&px, *sw, *sh, w, h)
            }
        }
    }

    /// Level `k` of an image whose own chain has it at exactly `w × h`.
    fn own_level(&self, k: usize, w: u32, h: u32) -> Option<Vec<[f32; 4]>> {
        match self {
            LayerSource::Image(levels) => levels
                .get(k)
                .filter(|l| (l.width, l.height) == (w, h))
                .map(linear_level),
            LayerSource::Float { .. } => None,
        }
    }
}

/// Why an appearance could not be uploaded.
#[derive(Debug, thiserror::Error, Clone, PartialEq)]
pub enum AppearanceError {
    /// An image's decoded pixels do not match its size or its mip chain is malformed (a bug
    /// of whatever decoded it; refused rather than read out of bounds).
    #[error("image {image}: {problem}")]
    Pixels {
        /// The image's index.
        image: usize,
        /// What is wrong.
        problem: String,
    },
    /// The device's memory budget (`--max-gpu-memory`) refused the textures.
    #[error("GPU memory: {0}")]
    Memory(#[from] BudgetError),
}

/// One vertex's static attributes (vertex buffer slot 3): texture coordinates of sets 0 and 1,
/// the linear vertex colour as unorm16 and the rest tangent as snorm16 (w: handedness).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub(super) struct VertexAttrs {
    pub(super) uv0: [f32; 2],
    pub(super) uv1: [f32; 2],
    pub(super) color: [u16; 4],
    pub(super) tangent: [i16; 4],
}

/// Bytes of [`VertexAttrs`] per vertex.
pub(super) const ATTR_STRIDE: u64 = size_of::<VertexAttrs>() as u64;

/// The vertex layout of [`VertexAttrs`] at shader locations 9–12.
pub(super) const ATTR_FORMATS: [wgpu::VertexAttribute; 4] = wgpu::vertex_attr_array![
    9 => Float32x2, 10 => Float32x2, 11 => Unorm16x4, 12 => Snorm16x4
];

impl VertexAttrs {
    fn unorm16(c: f32) -> u16 {
        let c = if c.is_finite() {
            c.clamp(0.0, 1.0)
        } else {
            1.0
        };
        (c * 65535.0).round() as u16
    }

    fn snorm16(c: f32) -> i16 {
        let c = if c.is_finite() {
            c.clamp(-1.0, 1.0)
        } else {
            0.0
        };
        (c * 32767.0).round() as i16
    }

    fn uv(v: glam::Vec2) -> [f32; 2] {
        if v.is_finite() {
            v.to_array()
        } else {
            [0.0; 2]
        }
    }
}

/// Appends `p`'s attributes to `out`: what the primitive has, defaults for what it lacks
/// (coordinates 0, colour white, tangent zero — the shader then leaves the normal alone).
/// `tangents` are the primitive's rest tangents when it has or was given any. An array whose
/// length is not the primitive's vertex count (a malformed rig) counts as absent.
pub(super) fn push_attrs(
    out: &mut Vec<VertexAttrs>,
    p: &Primitive,
    tangents: Option<&[glam::Vec4]>,
) {
    let n = p.positions.len();
    let fit = |len: usize| len == n;
    let uv0 = p.look.uv0.as_deref().filter(|a| fit(a.len()));
    let uv1 = p.look.uv1.as_deref().filter(|a| fit(a.len()));
    let colors = p.look.colors.as_deref().filter(|a| fit(a.len()));
    let tangents = tangents.filter(|a| fit(a.len()));
    out.extend((0..n).map(|i| VertexAttrs {
        uv0: uv0.map_or([0.0; 2], |a| VertexAttrs::uv(a[i])),
        uv1: uv1.map_or([0.0; 2], |a| VertexAttrs::uv(a[i])),
        color: colors.map_or([u16::MAX; 4], |a| a[i].to_array().map(VertexAttrs::unorm16)),
        tangent: tangents.map_or([0; 4], |a| a[i].to_array().map(VertexAttrs::snorm16)),
    }));
}

/// Rest tangents for a primitive without any, from its positions, normals and the texture
/// coordinates `uv` its normal map reads: meshoptimizer's MikkTSpace-compatible generator
/// (per triangle corner), reduced to one per vertex by averaging the corners of the
/// handedness most of them have (a vertex on a mirror seam keeps its majority side). The
/// generator's handedness is turned round: glTF's v runs down the image, MikkTSpace's up, so
/// glTF's bitangent `cross(n, t) · w` points the other way (three.js negates it too). `None`
/// when the arrays do not match the vertices.
pub(super) fn generate_tangents(p: &Primitive, uv: &[glam::Vec2]) -> Option<Vec<glam::Vec4>> {
    let n = p.positions.len();
    if uv.len() != n || p.normals.len() != n || p.indices.is_empty() {
        return None;
    }
    let positions: &[[f32; 3]] = bytemuck::cast_slice(&p.positions);
    let normals: &[[f32; 3]] = bytemuck::cast_slice(&p.normals);
    let uvs: &[[f32; 2]] = bytemuck::cast_slice(uv);
    let corners = meshopt::generate_tangents(
        Some(&p.indices),
        positions,
        normals,
        uvs,
        meshopt::TangentOptions::Compatible,
    );
    // Per vertex: the sums and counts of its corners' tangents by handedness.
    let mut sums = vec![[glam::Vec3::ZERO; 2]; n];
    let mut counts = vec![[0u32; 2]; n];
    for (&v, t) in p.indices.iter().zip(&corners) {
        let side = usize::from(t[3] < 0.0);
        if t[3] == 0.0 {
            continue;
        }
        sums[v as usize][side] += glam::Vec3::new(t[0], t[1], t[2]);
        counts[v as usize][side] += 1;
    }
    Some(
        sums.iter()
            .zip(&counts)
            .map(|(s, c)| {
                let side = usize::from(c[1] > c[0]);
                // MikkTSpace's +1 is glTF's −1 (see above).
                let w = if side == 0 { -1.0 } else { 1.0 };
                match s[side].try_normalize() {
                    Some(t) => t.extend(w),
                    None => glam::Vec4::ZERO,
                }
            })
            .collect(),
    )
}

/// The bind group layout of group 2: five 2D float textures, then their five samplers, then
/// the expression layers' 2D array.
pub(super) fn texture_layout(device: &wgpu::Device) -> wgpu::BindGroupLayout {
    let texture = |binding: u32, view_dimension| wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::FRAGMENT,
        ty: wgpu::BindingType::Texture {
            sample_type: wgpu::TextureSampleType::Float { filterable: true },
            view_dimension,
            multisampled: false,
        },
        count: None,
    };
    let slots = SLOTS.len() as u32;
    let mut entries: Vec<_> = (0..slots)
        .map(|k| texture(k, wgpu::TextureViewDimension::D2))
        .collect();
    entries.extend((0..slots).map(|k| wgpu::BindGroupLayoutEntry {
        binding: slots + k,
        visibility: wgpu::ShaderStages::FRAGMENT,
        ty: wgpu::BindingType::Sampler(wgpu::SamplerBindingType::Filtering),
        count: None,
    }));
    entries.push(texture(LAYER_BINDING, wgpu::TextureViewDimension::D2Array));
    device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
        label: Some("render textures"),
        entries: &entries,
    })
}

/// What a slot without a texture is bound to: a 1×1 white texture and glTF's default sampler
/// (never sampled: the shader skips slots flagged [`NO_TEXTURE`], but a bind group needs
/// something in every binding), and the bind group of a material without textures.
pub(super) struct Fallback {
    view: wgpu::TextureView,
    /// A 1×1, one-layer array of zeros: the layers of a material without any.
    layers: wgpu::TextureView,
    sampler: wgpu::Sampler,
    /// Group 2 for a primitive whose material samples no texture.
    pub(super) group: wgpu::BindGroup,
}

impl Fallback {
    /// Made once per renderer (4 bytes of texture: not charged, like the pipelines).
    pub(super) fn new(
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        layout: &wgpu::BindGroupLayout,
    ) -> Fallback {
        let texture = one_texel(
            device,
            queue,
            "render white",
            wgpu::TextureFormat::Rgba8Unorm,
            &[255; 4],
        );
        let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
        let zeros = one_texel(
            device,
            queue,
            "render no layers",
            LAYER_FORMAT,
            &[0u8; LAYER_TEXEL as usize],
        );
        let layers = zeros.create_view(&wgpu::TextureViewDescriptor {
            dimension: Some(wgpu::TextureViewDimension::D2Array),
            ..wgpu::TextureViewDescriptor::default()
        });
        let sampler = device.create_sampler(&sampler_descriptor(&Sampler::default()));
        let views = [&view; SLOTS.len()];
        let samplers = [&sampler; SLOTS.len()];
        let group = bind_group(device, layout, &views, &samplers, &layers);
        Fallback {
            view,
            layers,
            sampler,
            group,
        }
    }
}

/// A rig's textures on the renderer's device and one bind group per material that samples any
/// (see the module documentation).
pub struct GpuAppearance {
    /// Per material, its bind group when it samples at least one texture.
    groups: Vec<Option<wgpu::BindGroup>>,
    /// Per material, which of its [`SLOTS`] have a texture uploaded.
    textured: Vec<[bool; SLOTS.len()]>,
    /// Per material, the layers uploaded ([`material_layers`], in that order).
    layers: Vec<usize>,
    bytes: u64,
    /// The textures' bytes in the device's memory budget.
    _charge: Charge,
}

impl std::fmt::Debug for GpuAppearance {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuAppearance")
            .field("materials", &self.groups.len())
            .field("bytes", &self.bytes)
            .finish()
    }
}

impl GpuAppearance {
    /// Bytes its textures occupy on the device.
    pub fn bytes(&self) -> u64 {
        self.bytes
    }

    /// The bind group of material `m`, when it samples any texture.
    pub(super) fn group(&self, m: usize) -> Option<&wgpu::BindGroup> {
        self.groups.get(m).and_then(Option::as_ref)
    }

    /// Whether material `m` has a texture uploaded in slot `k` of [`SLOTS`].
    pub(super) fn has(&self, m: usize, k: usize) -> bool {
        self.textured.get(m).is_some_and(|t| t[k])
    }

    /// Layers material `m` has uploaded.
    pub(super) fn layers(&self, m: usize) -> usize {
        self.layers.get(m).copied().unwrap_or(0)
    }
}

/// The levels of image `index` to upload: the first level at most `max_size` a side and every
/// level after it that halves correctly (a chain cut short is uploaded as far as it is whole).
fn usable_levels(
    index: usize,
    levels: &[MipLevel],
    max_size: u32,
) -> Result<&[MipLevel], AppearanceError> {
    let bad = |problem: String| AppearanceError::Pixels {
        image: index,
        problem,
    };
    for (k, l) in levels.iter().enumerate() {
        let want = u64::from(l.width) * u64::from(l.height) * 4;
        if l.width == 0 || l.height == 0 || l.rgba.len() as u64 != want {
            return Err(bad(format!(
                "level {k} is {}×{} with {} bytes of RGBA8",
                l.width,
                l.height,
                l.rgba.len()
            )));
        }
    }
    // Past the device's largest texture (an import with a larger --max-texture-size than this
    // device allows): start at the first level that fits rather than refuse the rig.
    let first = levels
        .iter()
        .position(|l| l.width <= max_size && l.height <= max_size)
        .ok_or_else(|| bad(format!("no mip level fits {max_size} pixels a side")))?;
    let mut end = first + 1;
    while end < levels.len() {
        let (prev, next) = (&levels[end - 1], &levels[end]);
        if next.width != (prev.width / 2).max(1) || next.height != (prev.height / 2).max(1) {
            break;
        }
        end += 1;
    }
    Ok(&levels[first..end])
}

/// Per image of an appearance, the mip levels to upload (`None`: nothing).
type Chains<'a> = Vec<Option<&'a [MipLevel]>>;

/// Bytes the textures of `a` would occupy on a device whose largest texture is `max_size`
/// (what [`upload`] charges), and per image the levels it would upload.
fn plan(a: &Appearance, max_size: u32) -> Result<(u64, Chains<'_>), AppearanceError> {
    let mut used = vec![false; a.images.len()];
    let layer_refs = a.target_textures.iter().map(|t| &t.texture);
    for r in a
        .materials
        .iter()
        .flat_map(|m| m.texture_refs().map(|(_, r)| r))
        .chain(layer_refs)
    {
        if let Some(i) = a
            .textures
            .get(r.texture as usize)
            .and_then(|t| t.image)
            .filter(|&i| (i as usize) < used.len())
        {
            used[i as usize] = true;
        }
    }
    let mut bytes = 0u64;
    let mut levels = Vec::with_capacity(a.images.len());
    for (i, image) in a.images.iter().enumerate() {
        let chain = match (&image.pixels, used[i]) {
            (Some(p), true) if !p.levels.is_empty() => Some(usable_levels(i, &p.levels, max_size)?),
            _ => None,
        };
        bytes += chain.map_or(0, |c| c.iter().map(|l| l.rgba.len() as u64).sum());
        levels.push(chain);
    }
    for m in 0..a.materials.len() {
        let k = material_layers(a, m).len() as u64;
        if k > 0 {
            let dims = layer_dims(a, m, &levels, max_size)?;
            bytes += dims
                .iter()
                .map(|&(w, h)| u64::from(w) * u64::from(h))
                .sum::<u64>()
                * k
                * LAYER_TEXEL;
        }
    }
    Ok((bytes, levels))
}

/// The usable chain of the image texture reference `r` reaches, from [`plan`]'s chains.
fn chain_of<'a>(
    a: &Appearance,
    r: &crowdmorph_core::rig::TexRef,
    chains: &Chains<'a>,
) -> Option<&'a [MipLevel]> {
    let i = a.textures.get(r.texture as usize)?.image? as usize;
    *chains.get(i)?
}

/// The sizes of material `m`'s layer levels: its base colour texture's (so a layer texel is
/// the base texel it changes, and the two filter alike), else the first layer's size halved
/// down to 1 × 1.
fn layer_dims(
    a: &Appearance,
    m: usize,
    chains: &Chains<'_>,
    max_size: u32,
) -> Result<Vec<(u32, u32)>, AppearanceError> {
    let base = a.materials[m]
        .base_color_texture
        .as_ref()
        .and_then(|r| chain_of(a, r, chains));
    if let Some(c) = base {
        return Ok(c.iter().map(|l| (l.width, l.height)).collect());
    }
    let first = material_layers(a, m).into_iter().find_map(|k| match k {
        LayerKind::Target(i) => {
            let c = chain_of(a, &a.target_textures[i].texture, chains)?;
            c.first().map(|l| (l.width, l.height))
        }
        LayerKind::ClipMean(i) | LayerKind::ClipComponent(i, _) => {
            let t = &a.clip_textures[i];
            Some((t.width, t.height))
        }
    });
    let (mut w, mut h) = first.unwrap_or((1, 1));
    if w > max_size || h > max_size {
        return Err(AppearanceError::Pixels {
            image: m,
            problem: format!("material {m}'s layers are {w}×{h}, past {max_size} a side"),
        });
    }
    let mut out = vec![(w, h)];
    while (w, h) != (1, 1) {
        w = (w / 2).max(1);
        h = (h / 2).max(1);
        out.push((w, h));
    }
    Ok(out)
}

/// One level of one layer of a material, as [`build_layers`] hands it out.
#[derive(Debug)]
pub struct LayerLevel<'a> {
    /// The layer (its index in [`material_layers`]).
    pub layer: usize,
    /// The mip level (0: the largest).
    pub level: usize,
    /// Width in texels.
    pub width: u32,
    /// Height in texels.
    pub height: u32,
    /// Signed linear RGBA as binary16, rows top to bottom (`width × height × 4` values).
    pub texels: &'a [half::f16],
}

/// Material `m`'s layers (see the module documentation of
/// `crowdmorph_core::rig::animated_texture`) texel by texel, as the renderer uploads them and
/// `GET /v1/rigs/{id}/layers/{m}` serves them: `f` gets each level of each layer, layer by
/// layer, each layer's levels largest first. The one place layer texels are made, so the
/// device and a browser sum the same values. The host holds one level of one layer at a time
/// (and the level it halves).
fn build_layers(
    a: &Appearance,
    m: usize,
    chains: &Chains<'_>,
    dims: &[(u32, u32)],
    mut f: impl FnMut(LayerLevel<'_>),
) {
    let kinds = material_layers(a, m);
    let base = a.materials[m]
        .base_color_texture
        .as_ref()
        .and_then(|r| chain_of(a, r, chains));
    let Some(&(w0, h0)) = dims.first() else {
        return;
    };
    let base_at = |k: usize, w: u32, h: u32| -> Vec<[f32; 4]> {
        match base.and_then(|c| c.get(k)) {
            Some(l) if (l.width, l.height) == (w, h) => linear_level(l),
            _ => vec![[1.0; 4]; w as usize * h as usize],
        }
    };
    for (layer, kind) in kinds.iter().enumerate() {
        let source = match *kind {
            LayerKind::Target(i) => LayerSource::Image(
                chain_of(a, &a.target_textures[i].texture, chains).unwrap_or(&[]),
            ),
            LayerKind::ClipMean(i) => {
                let t = &a.clip_textures[i];
                LayerSource::Float {
                    rgb: &t.mean,
                    w: t.width,
                    h: t.height,
                }
            }
            LayerKind::ClipComponent(i, k) => {
                let t = &a.clip_textures[i];
                LayerSource::Float {
                    rgb: t.components.get(k).map_or(&[][..], Vec::as_slice),
                    w: t.width,
                    h: t.height,
                }
            }
        };
        let mut cur = source.level0(w0, h0);
        for (k, &(w, h)) in dims.iter().enumerate() {
            if k > 0 {
                let (pw, ph) = dims[k - 1];
                cur = halve(&cur, pw, ph);
            }
            let target = source.own_level(k, w, h).unwrap_or_else(|| cur.clone());
            let texels: Vec<half::f16> = match kind {
                LayerKind::Target(_) => {
                    let b = base_at(k, w, h);
                    target
                        .iter()
                        .zip(&b)
                        .flat_map(|(t, b)| [0, 1, 2, 3].map(|c| t[c] - b[c]))
                        .map(half::f16::from_f32)
                        .collect()
                }
                // The mean replaces the base's colour and keeps its alpha.
                LayerKind::ClipMean(_) => {
                    let b = base_at(k, w, h);
                    target
                        .iter()
                        .zip(&b)
                        .flat_map(|(t, b)| [t[0] - b[0], t[1] - b[1], t[2] - b[2], 0.0])
                        .map(half::f16::from_f32)
                        .collect()
                }
                LayerKind::ClipComponent(..) => target
                    .iter()
                    .flat_map(|t| [t[0], t[1], t[2], 0.0])
                    .map(half::f16::from_f32)
                    .collect(),
            };
            f(LayerLevel {
                layer,
                level: k,
                width: w,
                height: h,
                texels: &texels,
            });
        }
    }
}

/// What material `m`'s layers are, for a client that sums them itself: each layer's kind and
/// where its coefficient comes from, and the sizes of its levels.
#[derive(Clone, Debug, PartialEq)]
pub struct LayerPlan {
    /// The layers, in the order the material sums them.
    pub kinds: Vec<LayerKind>,
    /// Per layer, its coefficient's index in `crowdmorph_core::rig::layer_inputs` and whether
    /// it is clamped to [0, 1] ([`layer_source`]); `None`: its coefficient is always 0.
    pub sources: Vec<Option<(u32, bool)>>,
    /// Each level's width and height, largest first (the renderer's mip chain).
    pub levels: Vec<(u32, u32)>,
}

impl LayerPlan {
    /// Bytes of every level of every layer as binary16 RGBA: what [`layer_texels`] hands out.
    pub fn bytes(&self) -> u64 {
        self.levels
            .iter()
            .map(|&(w, h)| u64::from(w) * u64::from(h))
            .sum::<u64>()
            * self.kinds.len() as u64
            * LAYER_TEXEL
    }
}

/// Material `m`'s layers as a renderer whose largest texture is `max_size` would upload them;
/// `None` when it has none (or `m` is not a material of `rig`).
pub fn layer_plan(
    rig: &Rig,
    m: usize,
    max_size: u32,
) -> Result<Option<LayerPlan>, AppearanceError> {
    let Some(a) = rig.appearance.as_deref() else {
        return Ok(None);
    };
    if m >= a.materials.len() {
        return Ok(None);
    }
    let kinds = material_layers(a, m);
    if kinds.is_empty() {
        return Ok(None);
    }
    let (_, chains) = plan(a, max_size)?;
    Ok(Some(LayerPlan {
        sources: kinds.iter().map(|&k| layer_source(rig, a, k)).collect(),
        levels: layer_dims(a, m, &chains, max_size)?,
        kinds,
    }))
}

/// Material `m`'s layer texels ([`build_layers`]) as a renderer whose largest texture is
/// `max_size` uploads them; nothing when it has none. The caller charges
/// [`LayerPlan::bytes`] for whatever it keeps.
pub fn layer_texels(
    rig: &Rig,
    m: usize,
    max_size: u32,
    f: impl FnMut(LayerLevel<'_>),
) -> Result<(), AppearanceError> {
    let Some(a) = rig.appearance.as_deref() else {
        return Ok(());
    };
    if m >= a.materials.len() || material_layers(a, m).is_empty() {
        return Ok(());
    }
    let (_, chains) = plan(a, max_size)?;
    let dims = layer_dims(a, m, &chains, max_size)?;
    build_layers(a, m, &chains, &dims, f);
    Ok(())
}

/// Every index of `crowdmorph_core::rig::layer_inputs` that a layer of `rig` reads, ascending:
/// the compact vector a session viewer is sent per head holds these entries in this order.
pub fn layer_input_indices(rig: &Rig) -> Vec<u32> {
    let Some(a) = rig.appearance.as_deref() else {
        return Vec::new();
    };
    let mut out: Vec<u32> = (0..a.materials.len())
        .flat_map(|m| material_layers(a, m))
        .filter_map(|k| layer_source(rig, a, k).map(|(at, _)| at))
        .collect();
    out.sort_unstable();
    out.dedup();
    out
}

/// Uploads material `m`'s layers ([`build_layers`]) as one 2D array texture of
/// [`LAYER_FORMAT`], level by level and layer by layer.
fn upload_layers(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    a: &Appearance,
    m: usize,
    chains: &Chains<'_>,
    max_size: u32,
) -> Result<Option<wgpu::TextureView>, AppearanceError> {
    let kinds = material_layers(a, m);
    if kinds.is_empty() {
        return Ok(None);
    }
    let dims = layer_dims(a, m, chains, max_size)?;
    let (w0, h0) = dims[0];
    let texture = device.create_texture(&wgpu::TextureDescriptor {
        label: Some("render layers"),
        size: wgpu::Extent3d {
            width: w0,
            height: h0,
            depth_or_array_layers: kinds.len() as u32,
        },
        mip_level_count: dims.len() as u32,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format: LAYER_FORMAT,
        usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
        view_formats: &[],
    });
    build_layers(a, m, chains, &dims, |l| {
        queue.write_texture(
            wgpu::TexelCopyTextureInfo {
                texture: &texture,
                mip_level: l.level as u32,
                origin: wgpu::Origin3d {
                    x: 0,
                    y: 0,
                    z: l.layer as u32,
                },
                aspect: wgpu::TextureAspect::All,
            },
            bytemuck::cast_slice(l.texels),
            wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(l.width * LAYER_TEXEL as u32),
                rows_per_image: Some(l.height),
            },
            wgpu::Extent3d {
                width: l.width,
                height: l.height,
                depth_or_array_layers: 1,
            },
        );
    });
    Ok(Some(texture.create_view(&wgpu::TextureViewDescriptor {
        dimension: Some(wgpu::TextureViewDimension::D2Array),
        ..wgpu::TextureViewDescriptor::default()
    })))
}

/// The most texture fetches one of `rig`'s primitives makes (slots with an image with
/// pixels, read through a coordinate set the primitive has, and its material's layers): what
/// the render cost model prices per pixel, without uploading anything.
pub fn texture_slots(rig: &Rig) -> u32 {
    let Some(a) = &rig.appearance else {
        return 0;
    };
    rig.primitives
        .iter()
        .filter_map(|p| {
            let m = a.materials.get(p.look.material? as usize)?;
            let n = p.positions.len();
            let has_set = |set: u8| match set {
                0 => p.look.uv0.as_ref().is_some_and(|u| u.len() == n),
                1 => p.look.uv1.as_ref().is_some_and(|u| u.len() == n),
                _ => false,
            };
            let layers = a.layer_count(p.look.material? as usize).min(MAX_LAYERS) as u32;
            Some(
                m.texture_refs()
                    .filter(|(_, r)| {
                        has_set(r.tex_coord) && a.image_of(r).is_some_and(|i| i.pixels.is_some())
                    })
                    .count() as u32
                    + layers,
            )
        })
        .max()
        .unwrap_or(0)
}

/// Whether `a` has anything to upload: some material samples an image with pixels, or sums
/// layers.
pub(super) fn has_textures(a: &Appearance) -> bool {
    !a.target_textures.is_empty()
        || !a.clip_textures.is_empty()
        || a.materials.iter().any(|m| {
            m.texture_refs()
                .any(|(_, r)| a.image_of(r).is_some_and(|i| i.pixels.is_some()))
        })
}

/// Uploads `a`'s textures to `ctx`'s device (charged first) and makes the materials' bind
/// groups. Errors of the device are left to the caller's error scope.
pub(super) fn upload(
    ctx: &Arc<GpuContext>,
    layout: &wgpu::BindGroupLayout,
    fallback: &Fallback,
    a: &Appearance,
    max_size: u32,
) -> Result<GpuAppearance, AppearanceError> {
    let (bytes, chains) = plan(a, max_size)?;
    let charge = ctx.charge(bytes, || {
        format!(
            "{} images' textures on the GPU ({bytes} bytes)",
            a.images.len()
        )
    })?;
    let device = ctx.device();
    let queue = ctx.queue();
    // Per image: the texture's linear and sRGB views.
    let mut views: Vec<Option<(wgpu::TextureView, wgpu::TextureView)>> =
        Vec::with_capacity(chains.len());
    for chain in &chains {
        let Some(chain) = chain else {
            views.push(None);
            continue;
        };
        let (w, h) = (chain[0].width, chain[0].height);
        let texture = device.create_texture(&wgpu::TextureDescriptor {
            label: Some("render image"),
            size: wgpu::Extent3d {
                width: w,
                height: h,
                depth_or_array_layers: 1,
            },
            mip_level_count: chain.len() as u32,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: wgpu::TextureFormat::Rgba8Unorm,
            usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
            view_formats: &[wgpu::TextureFormat::Rgba8UnormSrgb],
        });
        for (k, l) in chain.iter().enumerate() {
            write_level(queue, &texture, k as u32, l.width, l.height, &l.rgba);
        }
        let linear = texture.create_view(&wgpu::TextureViewDescriptor::default());
        let srgb = texture.create_view(&wgpu::TextureViewDescriptor {
            format: Some(wgpu::TextureFormat::Rgba8UnormSrgb),
            ..wgpu::TextureViewDescriptor::default()
        });
        views.push(Some((linear, srgb)));
    }
    // Samplers by their glTF description (a file has few, shared by many textures).
    let mut samplers: Vec<(Sampler, wgpu::Sampler)> = Vec::new();
    let mut groups = Vec::with_capacity(a.materials.len());
    let mut textured = Vec::with_capacity(a.materials.len());
    let mut layer_counts = Vec::with_capacity(a.materials.len());
    for (mi, m) in a.materials.iter().enumerate() {
        let layer_view = upload_layers(device, queue, a, mi, &chains, max_size)?;
        layer_counts.push(if layer_view.is_some() {
            material_layers(a, mi).len()
        } else {
            0
        });
        let mut slot_views: [&wgpu::TextureView; SLOTS.len()] = [&fallback.view; SLOTS.len()];
        let mut slot_samplers = [&fallback.sampler; SLOTS.len()];
        let mut has = [false; SLOTS.len()];
        for (slot, r) in m.texture_refs() {
            let Some(k) = SLOTS.iter().position(|s| *s == slot) else {
                continue;
            };
            let image = a.textures.get(r.texture as usize).and_then(|t| t.image);
            let Some((linear, srgb)) = image.and_then(|i| views.get(i as usize)?.as_ref()) else {
                continue;
            };
            let s = a.sampler_of(r);
            if !samplers.iter().any(|(d, _)| *d == s) {
                samplers.push((s, device.create_sampler(&sampler_descriptor(&s))));
            }
            slot_views[k] = if slot.is_srgb() { srgb } else { linear };
            has[k] = true;
        }
        for (k, slot) in SLOTS.iter().enumerate() {
            if has[k]
                && let Some((_, r)) = m.texture_refs().find(|(s, _)| s == slot)
            {
                let s = a.sampler_of(r);
                if let Some((_, sampler)) = samplers.iter().find(|(d, _)| *d == s) {
                    slot_samplers[k] = sampler;
                }
            }
        }
        groups.push((has.iter().any(|&h| h) || layer_view.is_some()).then(|| {
            bind_group(
                device,
                layout,
                &slot_views,
                &slot_samplers,
                layer_view.as_ref().unwrap_or(&fallback.layers),
            )
        }));
        textured.push(has);
    }
    Ok(GpuAppearance {
        groups,
        textured,
        layers: layer_counts,
        bytes,
        _charge: charge,
    })
}

/// A 1×1 texture of `format` holding `texel` (the fallbacks of slots and layers).
fn one_texel(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    label: &str,
    format: wgpu::TextureFormat,
    texel: &[u8],
) -> wgpu::Texture {
    let texture = device.create_texture(&wgpu::TextureDescriptor {
        label: Some(label),
        size: wgpu::Extent3d {
            width: 1,
            height: 1,
            depth_or_array_layers: 1,
        },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format,
        usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
        view_formats: &[],
    });
    write_texels(queue, &texture, 0, 1, 1, texel.len() as u32, texel);
    texture
}

/// Queues the upload of one mip level of RGBA8 (rows tightly packed: `write_texture` needs no
/// 256-byte row alignment).
fn write_level(
    queue: &wgpu::Queue,
    texture: &wgpu::Texture,
    level: u32,
    w: u32,
    h: u32,
    rgba: &[u8],
) {
    write_texels(queue, texture, level, w, h, 4, rgba);
}

/// Writes level `level` (`w × h` texels of `texel_bytes` each) of a 2D texture.
fn write_texels(
    queue: &wgpu::Queue,
    texture: &wgpu::Texture,
    level: u32,
    w: u32,
    h: u32,
    texel_bytes: u32,
    data: &[u8],
) {
    queue.write_texture(
        wgpu::TexelCopyTextureInfo {
            texture,
            mip_level: level,
            origin: wgpu::Origin3d::ZERO,
            aspect: wgpu::TextureAspect::All,
        },
        data,
        wgpu::TexelCopyBufferLayout {
            offset: 0,
            bytes_per_row: Some(w * texel_bytes),
            rows_per_image: Some(h),
        },
        wgpu::Extent3d {
            width: w,
            height: h,
            depth_or_array_layers: 1,
        },
    );
}

fn bind_group(
    device: &wgpu::Device,
    layout: &wgpu::BindGroupLayout,
    views: &[&wgpu::TextureView; SLOTS.len()],
    samplers: &[&wgpu::Sampler; SLOTS.len()],
    layers: &wgpu::TextureView,
) -> wgpu::BindGroup {
    let mut entries = Vec::with_capacity(2 * SLOTS.len());
    for (k, v) in views.iter().enumerate() {
        entries.push(wgpu::BindGroupEntry {
            binding: k as u32,
            resource: wgpu::BindingResource::TextureView(v),
        });
    }
    for (k, s) in samplers.iter().enumerate() {
        entries.push(wgpu::BindGroupEntry {
            binding: (SLOTS.len() + k) as u32,
            resource: wgpu::BindingResource::Sampler(s),
        });
    }
    entries.push(wgpu::BindGroupEntry {
        binding: LAYER_BINDING,
        resource: wgpu::BindingResource::TextureView(layers),
    });
    device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some("render material textures"),
        layout,
        entries: &entries,
    })
}

/// The wgpu sampler of a glTF sampler. Without a mipmap filter glTF samples the base level
/// only, which a clamp of the level of detail to 0 gives.
fn sampler_descriptor(s: &Sampler) -> wgpu::SamplerDescriptor<'static> {
    let wrap = |w: Wrap| match w {
        Wrap::ClampToEdge => wgpu::AddressMode::ClampToEdge,
        Wrap::MirroredRepeat => wgpu::AddressMode::MirrorRepeat,
        Wrap::Repeat => wgpu::AddressMode::Repeat,
    };
    let filter = |f: Filter| match f {
        Filter::Nearest => wgpu::FilterMode::Nearest,
        Filter::Linear => wgpu::FilterMode::Linear,
    };
    let mipmap_filter = match s.mipmap {
        Some(Filter::Linear) => wgpu::MipmapFilterMode::Linear,
        _ => wgpu::MipmapFilterMode::Nearest,
    };
    wgpu::SamplerDescriptor {
        label: Some("render sampler"),
        address_mode_u: wrap(s.wrap_s),
        address_mode_v: wrap(s.wrap_t),
        address_mode_w: wgpu::AddressMode::ClampToEdge,
        mag_filter: filter(s.mag),
        min_filter: filter(s.min),
        mipmap_filter,
        lod_min_clamp: 0.0,
        lod_max_clamp: if s.mipmap.is_some() { 32.0 } else { 0.0 },
        compare: None,
        anisotropy_clamp: 1,
        border_color: None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crowdmorph_core::rig::{ImageData, ImageMime, Material, Mips, TexRef, Texture};

    fn level(w: u32, h: u32) -> MipLevel {
        MipLevel {
            width: w,
            height: h,
            rgba: vec![7; (w * h * 4) as usize],
        }
    }

    #[test]
    fn a_chain_is_cut_where_it_stops_halving_and_starts_where_it_fits() {
        let chain = [level(8, 4), level(4, 2), level(2, 1), level(1, 1)];
        assert_eq!(usable_levels(0, &chain, 16).map(<[_]>::len), Ok(4));
        assert_eq!(
            usable_levels(0, &chain, 4).map(|l| (l.len(), l[0].width)),
            Ok((3, 4))
        );
        let broken = [level(8, 4), level(3, 2), level(1, 1)];
        assert_eq!(usable_levels(0, &broken, 16).map(<[_]>::len), Ok(1));
        let mut short = level(2, 2);
        short.rgba.pop();
        assert!(matches!(
            usable_levels(3, &[short], 16),
            Err(AppearanceError::Pixels { image: 3, .. })
        ));
        assert!(usable_levels(0, &[level(32, 32)], 16).is_err());
    }

    #[test]
    fn only_images_a_material_samples_and_that_have_pixels_are_charged() {
        let image = |pixels: bool| ImageData {
            mime: ImageMime::Png,
            bytes: Arc::from(&[0u8][..]),
            width: 4,
            height: 4,
            downscaled_from: None,
            pixels: pixels.then(|| {
                Arc::new(Mips {
                    levels: vec![level(4, 4), level(2, 2), level(1, 1)],
                })
            }),
        };
        let r = |texture| TexRef {
            texture,
            tex_coord: 0,
            transform: None,
        };
        let a = Appearance {
            materials: vec![Material {
                base_color_texture: Some(r(0)),
                emissive_texture: Some(r(1)),
                ..Material::default()
            }],
            textures: vec![
                Texture {
                    sampler: None,
                    image: Some(0),
                },
                Texture {
                    sampler: None,
                    image: Some(1),
                },
                Texture {
                    sampler: None,
                    image: Some(2),
                },
            ],
            // Image 1 has no pixels; image 2 is sampled by no material.
            images: vec![image(true), image(false), image(true)],
            ..Appearance::default()
        };
        let (bytes, levels) = plan(&a, 4096).expect("plan");
        assert_eq!(bytes, (16 + 4 + 1) * 4);
        assert!(levels[0].is_some() && levels[1].is_none() && levels[2].is_none());
        assert!(has_textures(&a));
        let none = Appearance {
            images: vec![image(false)],
            ..a.clone()
        };
        assert!(!has_textures(&Appearance {
            materials: vec![Material::default()],
            ..none
        }));
    }

    #[test]
    fn generated_tangents_follow_u_with_gltfs_handedness() {
        use glam::{Vec2, Vec3, Vec4};
        // A square facing +Z, u to the right and v down (glTF's image convention): the
        // tangent is +X, and the bitangent cross(n, t)·w must be +Y, "up" in the image.
        let p = Primitive {
            name: "quad".into(),
            positions: vec![
                Vec3::new(-1.0, 1.0, 0.0),
                Vec3::new(1.0, 1.0, 0.0),
                Vec3::new(1.0, -1.0, 0.0),
                Vec3::new(-1.0, -1.0, 0.0),
            ],
            normals: vec![Vec3::Z; 4],
            normals_from_file: true,
            tangents: None,
            indices: vec![0, 3, 2, 0, 2, 1],
            targets: Vec::new(),
            base_color: [1.0; 4],
            skin: None,
            look: Default::default(),
        };
        let uv = [
            Vec2::new(0.0, 0.0),
            Vec2::new(1.0, 0.0),
            Vec2::new(1.0, 1.0),
            Vec2::new(0.0, 1.0),
        ];
        let t = generate_tangents(&p, &uv).expect("tangents");
        for t in &t {
            assert!((*t - Vec4::new(1.0, 0.0, 0.0, 1.0)).length() < 1e-5, "{t}");
            let b = Vec3::Z.cross(t.truncate()) * t.w;
            assert!((b - Vec3::Y).length() < 1e-5);
        }
        // Mirrored along u (u to the left): the tangent turns round and so does w, so the
        // bitangent still points up the image.
        let mirrored: Vec<Vec2> = uv.iter().map(|c| Vec2::new(1.0 - c.x, c.y)).collect();
        for t in generate_tangents(&p, &mirrored).expect("tangents") {
            assert!((t - Vec4::new(-1.0, 0.0, 0.0, -1.0)).length() < 1e-5, "{t}");
        }
        assert!(generate_tangents(&p, &uv[..3]).is_none());
    }

    #[test]
    fn attributes_fill_what_a_primitive_lacks_with_defaults() {
        use glam::{Vec2, Vec3, Vec4};
        let mut p = Primitive {
            name: "p".into(),
            positions: vec![Vec3::ZERO; 2],
            normals: vec![Vec3::Z; 2],
            normals_from_file: false,
            tangents: None,
            indices: Vec::new(),
            targets: Vec::new(),
            base_color: [1.0; 4],
            skin: None,
            look: Default::default(),
        };
        p.look.uv0 = Some(vec![Vec2::new(0.25, 0.5), Vec2::new(f32::NAN, 1.0)]);
        // A colour array of the wrong length counts as absent.
        p.look.colors = Some(vec![Vec4::new(0.5, 0.0, 2.0, 1.0)]);
        let tangents = [Vec4::new(1.0, 0.0, 0.0, -1.0); 2];
        let mut out = Vec::new();
        push_attrs(&mut out, &p, Some(&tangents));
        assert_eq!(out.len(), 2);
        assert_eq!(out[0].uv0, [0.25, 0.5]);
        assert_eq!(out[1].uv0, [0.0, 0.0], "a NaN coordinate is zeroed");
        assert_eq!(out[0].uv1, [0.0, 0.0]);
        assert_eq!(out[0].color, [u16::MAX; 4]);
        assert_eq!(out[1].tangent, [32767, 0, 0, -32767]);
        assert_eq!(size_of::<VertexAttrs>(), 32);
        assert_eq!(std::mem::offset_of!(VertexAttrs, color), 16);
        assert_eq!(std::mem::offset_of!(VertexAttrs, tangent), 24);
        let offsets: Vec<u64> = ATTR_FORMATS.iter().map(|a| a.offset).collect();
        assert_eq!(
            offsets,
            vec![0, 8, 16, 24],
            "the vertex layout reads the struct"
        );
    }
}
