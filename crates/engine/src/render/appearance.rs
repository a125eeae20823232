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

use crowdmorph_core::budget::Charge;
use crowdmorph_core::rig::{Appearance, Filter, MipLevel, Primitive, Sampler, Slot, Wrap};

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

/// The bind group layout of group 2: five 2D float textures, then their five samplers.
pub(super) fn texture_layout(device: &wgpu::Device) -> wgpu::BindGroupLayout {
    let mut entries = Vec::with_capacity(2 * SLOTS.len());
    for k in 0..SLOTS.len() as u32 {
        entries.push(wgpu::BindGroupLayoutEntry {
            binding: k,
            visibility: wgpu::ShaderStages::FRAGMENT,
            ty: wgpu::BindingType::Texture {
                sample_type: wgpu::TextureSampleType::Float { filterable: true },
                view_dimension: wgpu::TextureViewDimension::D2,
                multisampled: false,
            },
            count: None,
        });
    }
    for k in 0..SLOTS.len() as u32 {
        entries.push(wgpu::BindGroupLayoutEntry {
            binding: SLOTS.len() as u32 + k,
            visibility: wgpu::ShaderStages::FRAGMENT,
            ty: wgpu::BindingType::Sampler(wgpu::SamplerBindingType::Filtering),
            count: None,
        });
    }
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
        let texture = device.create_texture(&wgpu::TextureDescriptor {
            label: Some("render white"),
            size: wgpu::Extent3d {
                width: 1,
                height: 1,
                depth_or_array_layers: 1,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: wgpu::TextureFormat::Rgba8Unorm,
            usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
            view_formats: &[],
        });
        write_level(queue, &texture, 0, 1, 1, &[255; 4]);
        let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
        let sampler = device.create_sampler(&sampler_descriptor(&Sampler::default()));
        let views = [&view; SLOTS.len()];
        let samplers = [&sampler; SLOTS.len()];
        let group = bind_group(device, layout, &views, &samplers);
        Fallback {
            view,
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
    for m in &a.materials {
        for (_, r) in m.texture_refs() {
            if let Some(i) = a
                .textures
                .get(r.texture as usize)
                .and_then(|t| t.image)
                .filter(|&i| (i as usize) < used.len())
            {
                used[i as usize] = true;
            }
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
    Ok((bytes, levels))
}

/// Whether `a` has anything to upload: some material samples an image with pixels.
pub(super) fn has_textures(a: &Appearance) -> bool {
    a.materials.iter().any(|m| {
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
) -> Result<GpuAppearance, super::gpu::RenderError> {
    let (bytes, chains) =
        plan(a, max_size).map_err(|e| super::gpu::RenderError::Invalid(e.to_string()))?;
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
    for m in &a.materials {
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
        groups.push(
            has.iter()
                .any(|&h| h)
                .then(|| bind_group(device, layout, &slot_views, &slot_samplers)),
        );
        textured.push(has);
    }
    Ok(GpuAppearance {
        groups,
        textured,
        bytes,
        _charge: charge,
    })
}

/// Queues the upload of one mip level (rows tightly packed: `write_texture` needs no 256-byte
/// row alignment).
fn write_level(
    queue: &wgpu::Queue,
    texture: &wgpu::Texture,
    level: u32,
    w: u32,
    h: u32,
    rgba: &[u8],
) {
    queue.write_texture(
        wgpu::TexelCopyTextureInfo {
            texture,
            mip_level: level,
            origin: wgpu::Origin3d::ZERO,
            aspect: wgpu::TextureAspect::All,
        },
        rgba,
        wgpu::TexelCopyBufferLayout {
            offset: 0,
            bytes_per_row: Some(w * 4),
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
