//! A crowd of one rig drawn offline (`crowdmorph render`; `crowdmorph bench render` draws the
//! same crowd repeatedly), through the same layout, draw and encoding path as
//! `POST /v1/crowd/render`.
//!
//! The crowd is `heads` heads of one clip at one LOD on the default grid and camera; with
//! `spread`, head `i` plays frame `frame + i` (every head unique), otherwise every head is a
//! clone of one job. [`RenderOptions::textures`] draws the same crowd with or without
//! textures: a rig without any gets generated ones ([`with_generated_textures`]: base colour,
//! packed occlusion-roughness-metallic and a normal map on planar texture coordinates), so
//! `bench render` can price texture sampling on any rig.

use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

use crowdmorph_proto::{ImageFormat, ImageOptions};
use serde::Serialize;

use crate::gpu::GpuOptions;
use crate::render::crowd::{self, CrowdError, CrowdGroup, RenderBackend, RenderDevice};
use crate::render::encode::{self, EncodeError, ImageError};
use crate::render::gpu::{Frame, MeshTopology, RenderError, View};
use crate::render::scene::{self, SceneError};
use crate::{BackendKind, Engine, EngineError, PreparedRig};
use crowdmorph_core::plan::{JobKey, Plan};
use crowdmorph_core::rig::{ClipError, FrameMode, Rig};

/// Why an offline render failed.
#[derive(Debug, thiserror::Error)]
pub enum OfflineError {
    /// No adapter can render (the reason names what to install).
    #[error("{0}")]
    NoRenderer(String),
    /// The rig has no such clip.
    #[error("rig {rig:?} has no clip {clip:?} (clips: {clips})")]
    UnknownClip {
        /// The rig.
        rig: String,
        /// The clip asked for.
        clip: String,
        /// The clips it has.
        clips: String,
    },
    /// The LOD level is past the rig's last.
    #[error("LOD {lod} out of range: rig {rig:?} has levels 0..{last}")]
    Lod {
        /// The rig.
        rig: String,
        /// The level asked for.
        lod: u32,
        /// Its last level.
        last: usize,
    },
    /// The image options.
    #[error(transparent)]
    Image(#[from] ImageError),
    /// A frame outside the clip.
    #[error(transparent)]
    Clip(#[from] ClipError),
    /// The scene layout.
    #[error(transparent)]
    Scene(#[from] SceneError),
    /// The engine.
    #[error(transparent)]
    Engine(#[from] EngineError),
    /// The renderer.
    #[error(transparent)]
    Render(#[from] RenderError),
    /// Drawing the crowd.
    #[error(transparent)]
    Crowd(#[from] CrowdError),
    /// Encoding the image.
    #[error(transparent)]
    Encode(#[from] EncodeError),
    /// Writing the file.
    #[error("writing {path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// What failed.
        source: std::io::Error,
    },
}

type Result<T, E = OfflineError> = std::result::Result<T, E>;

/// The clip `--clip random` makes for a rig (deterministic random weights, one frame per head
/// at least): ICT FaceKit and other rigs without animation can still be benchmarked.
pub const RANDOM_CLIP: &str = "random";

/// The one-frame clip of all-zero weights a rig without clips is drawn with by default.
pub const NEUTRAL_CLIP: &str = "neutral";

/// What to draw.
#[derive(Clone, Debug)]
pub struct RenderOptions {
    /// Clip name (default: `talk` when the rig has it, else its first clip, else the neutral
    /// pose); `random` makes a synthetic clip when the rig has none of that name.
    pub clip: Option<String>,
    /// Frame of the first head (wraps past the end).
    pub frame: i64,
    /// Heads in the crowd.
    pub heads: usize,
    /// LOD level of every head.
    pub lod: u32,
    /// Head `i` plays frame `frame + i` (unique heads) instead of cloning one job.
    pub spread: bool,
    /// Size, encoding and background.
    pub image: ImageOptions,
    /// Which adapter renders.
    pub backend: RenderBackend,
    /// `--max-gpu-memory` of a device opened for rendering only (on the engine's device, the
    /// engine's budget applies); `None`: the default.
    pub gpu_memory: Option<u64>,
    /// `None`: the rig as it is; `Some(true)`: with textures (generated ones when the rig has
    /// none); `Some(false)`: its materials' factors without their textures.
    pub textures: Option<bool>,
}

impl Default for RenderOptions {
    fn default() -> Self {
        RenderOptions {
            clip: None,
            frame: 0,
            heads: 1,
            lod: 0,
            spread: false,
            image: ImageOptions::default(),
            backend: RenderBackend::Auto,
            gpu_memory: None,
            textures: None,
        }
    }
}

/// Times of one drawn and encoded frame, milliseconds.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct StageTimes {
    /// Engine evaluation of the unique jobs.
    pub compute_ms: f64,
    /// Drawing.
    pub render_ms: f64,
    /// Copying the pixels to host memory.
    pub readback_ms: f64,
    /// Encoding the image.
    pub encode_ms: f64,
    /// All four.
    pub total_ms: f64,
}

/// What was drawn, and on what.
#[derive(Clone, Debug, Serialize)]
pub struct RenderReport {
    /// Rig name.
    pub rig: String,
    /// The adapter that rendered.
    pub adapter: String,
    /// Whether it is the engine's own device (outputs drawn where they were computed).
    pub shared_device: bool,
    /// The engine that blended.
    pub engine: BackendKind,
    /// Vertices per head at the drawn LOD.
    pub vertices: usize,
    /// Heads drawn.
    pub heads: usize,
    /// Unique jobs among them.
    pub unique: usize,
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// Image encoding.
    pub format: String,
    /// Encoded bytes.
    pub bytes: usize,
    /// The most texture slots a primitive samples (0: drawn without textures).
    pub texture_slots: u32,
    /// Bytes of textures on the device.
    pub texture_bytes: u64,
    /// Times of the (last, or median) frame.
    pub times: StageTimes,
    /// Frames measured (1 for `render`).
    pub runs: usize,
}

/// A crowd laid out and planned, ready to draw as often as wanted.
pub struct Crowd {
    rig: String,
    vertices: usize,
    prepared: PreparedRig,
    groups: Vec<crowd::PlannedGroup>,
    topologies: Vec<Arc<MeshTopology>>,
    view: View,
    frame: Frame,
    unique: usize,
    texture_slots: u32,
}

/// The rig with the clip `opt` asks for added when it is a synthetic one (`random`, or the
/// neutral pose of a rig without clips).
fn playable(rig: &Rig, opt: &RenderOptions) -> Rig {
    match opt.clip.as_deref() {
        Some(RANDOM_CLIP) if rig.clip_index(RANDOM_CLIP).is_none() => {
            crowdmorph_core::synthetic::with_random_clip_of(
                rig.clone(),
                RANDOM_CLIP,
                opt.heads.max(24),
                7,
            )
        }
        None if rig.clips.is_empty() => {
            let mut r = rig.clone();
            r.clips.push(crowdmorph_core::rig::Clip {
                name: NEUTRAL_CLIP.into(),
                fps: crowdmorph_core::rig::DEFAULT_FPS,
                frames: 1,
                targets: r.targets.len() as u32,
                weights: Arc::new(vec![0.0; r.targets.len()]),
                joints: None,
            });
            r
        }
        _ => rig.clone(),
    }
}

/// Lays out and plans the crowd `opt` asks for, and uploads its topologies to `device`.
pub fn build(
    engine: &Engine,
    device: &RenderDevice,
    rig: &Rig,
    opt: &RenderOptions,
) -> Result<Crowd> {
    encode::check_image(&opt.image, device.renderer.max_size())?;
    // One copy of the rig: the engine's preparation shares it.
    let mut rig = playable(rig, opt);
    match opt.textures {
        Some(true) if super::appearance::texture_slots(&rig) == 0 => {
            rig = with_generated_textures(&rig, GENERATED_TEXTURE_SIZE);
        }
        Some(false) => strip_textures(&mut rig),
        _ => {}
    }
    let rig = Arc::new(rig);
    let clip = match &opt.clip {
        Some(c) => rig.clip_index(c).ok_or_else(|| OfflineError::UnknownClip {
            rig: rig.name.clone(),
            clip: c.clone(),
            clips: rig
                .clips
                .iter()
                .map(|c| c.name.as_str())
                .collect::<Vec<_>>()
                .join(", "),
        })?,
        None => rig.clip_index("talk").unwrap_or(0),
    };
    let levels = rig.lod.levels.len();
    if opt.lod as usize >= levels {
        return Err(OfflineError::Lod {
            rig: rig.name.clone(),
            lod: opt.lod,
            last: levels.saturating_sub(1),
        });
    }
    let keys = (0..opt.heads)
        .map(|i| {
            let frame = opt.frame + if opt.spread { i as i64 } else { 0 };
            Ok(JobKey::frame(
                0,
                clip as u32,
                rig.clips[clip].resolve_frame(frame, FrameMode::Wrap)?,
                opt.lod,
            ))
        })
        .collect::<Result<Vec<_>>>()?;
    let plan = Plan::new(keys);
    let boxes = vec![rig.bbox(); opt.heads];
    let ids: Vec<u64> = (0..opt.heads as u64).collect();
    let aspect = opt.image.width as f32 / opt.image.height as f32;
    let layout = scene::layout(&boxes, None, &ids, None, None, aspect)?;
    let prepared = engine.prepare(rig.clone())?;
    let groups = crowd::plan_groups(&plan, &layout.transforms, |k| prepared.mesh_of(k.lod));
    let topologies = groups
        .iter()
        .map(|g| {
            let level = g
                .mesh
                .and_then(|m| prepared.mesh_levels().get(m))
                .unwrap_or(&prepared);
            Ok(Arc::new(device.renderer.topology(level.rig())?))
        })
        .collect::<Result<Vec<_>>>()?;
    Ok(Crowd {
        rig: rig.name.clone(),
        vertices: prepared.at_level(opt.lod).rig().vertex_count(),
        groups,
        topologies,
        view: layout.view,
        frame: crowd::to_frame(opt.image.width, opt.image.height, opt.image.background),
        unique: plan.jobs.len(),
        texture_slots: super::appearance::texture_slots(&rig),
        prepared,
    })
}

/// Side of the images [`with_generated_textures`] makes.
pub const GENERATED_TEXTURE_SIZE: u32 = 512;

/// `rig` with generated textures: every primitive gets planar texture coordinates over the
/// rig's front (x, y) box when it has none, and a material of its base colour that samples
/// three `size`² images with full mip chains — a light pattern for base colour, a packed
/// occlusion (R), roughness (G) and metallic (B) image read by two slots, and a normal map of
/// gentle bumps (the renderer generates the tangents). Four of the five slots: what a typical
/// PBR head samples.
pub fn with_generated_textures(rig: &Rig, size: u32) -> Rig {
    use crowdmorph_core::rig::{
        Appearance, ImageData, ImageMime, Material, Sampler, TexRef, Texture,
    };
    let size = size.max(1);
    let b = rig.bbox();
    let extent = (b.max - b.min).max(glam::Vec3::splat(1e-12));
    let mut primitives: Vec<_> = rig.primitives.iter().cloned().collect();
    let mut materials = Vec::with_capacity(primitives.len());
    let r = |texture| {
        Some(TexRef {
            texture,
            tex_coord: 0,
            transform: None,
        })
    };
    for (k, p) in primitives.iter_mut().enumerate() {
        if p.look
            .uv0
            .as_ref()
            .is_none_or(|u| u.len() != p.positions.len())
        {
            p.look.uv0 = Some(
                p.positions
                    .iter()
                    .map(|v| {
                        glam::Vec2::new(
                            (v.x - b.min.x) / extent.x,
                            1.0 - (v.y - b.min.y) / extent.y,
                        )
                    })
                    .collect(),
            );
        }
        p.look.material = Some(k as u32);
        materials.push(Material {
            name: Some(format!("generated {k}")),
            base_color_texture: r(0),
            metallic_roughness_texture: r(1),
            occlusion_texture: r(1),
            normal_texture: r(2),
            ..Material::untextured(p.base_color)
        });
    }
    let pattern = |f: &dyn Fn(f32, f32) -> [u8; 4]| {
        let mut rgba = Vec::with_capacity((size * size * 4) as usize);
        for y in 0..size {
            for x in 0..size {
                let (u, v) = (
                    (x as f32 + 0.5) / size as f32,
                    (y as f32 + 0.5) / size as f32,
                );
                rgba.extend_from_slice(&f(u, v));
            }
        }
        let pixels = box_mips(size, size, rgba);
        ImageData {
            mime: ImageMime::Png,
            bytes: Arc::from(&[][..]),
            width: size,
            height: size,
            downscaled_from: None,
            pixels: Some(Arc::new(pixels)),
        }
    };
    let wave = |u: f32, v: f32| {
        let tau = std::f32::consts::TAU;
        ((u * 24.0 * tau).sin() * (v * 24.0 * tau).sin()) * 0.5 + 0.5
    };
    let base = pattern(&|u, v| {
        let c = (225.0 + 30.0 * wave(u * 0.37, v * 0.41)) as u8;
        [c, c, c, 255]
    });
    let orm = pattern(&|u, v| {
        let w = wave(u, v);
        [(205.0 + 50.0 * w) as u8, (150.0 + 60.0 * w) as u8, 0, 255]
    });
    let normal = pattern(&|u, v| {
        let tau = std::f32::consts::TAU;
        let (dx, dy) = ((u * 24.0 * tau).cos() * 0.25, (v * 24.0 * tau).cos() * 0.25);
        let n = glam::Vec3::new(dx, dy, 1.0).normalize();
        let enc = |c: f32| ((c * 0.5 + 0.5) * 255.0).round() as u8;
        [enc(n.x), enc(n.y), enc(n.z), 255]
    });
    let texture = |image| Texture {
        sampler: Some(0),
        image: Some(image),
    };
    let mut out = rig.clone();
    out.primitives = Arc::new(primitives);
    out.appearance = Some(Arc::new(Appearance {
        materials,
        textures: vec![texture(0), texture(1), texture(2)],
        samplers: vec![Sampler::default()],
        images: vec![base, orm, normal],
        notes: vec!["textures generated for a benchmark".into()],
        ..Appearance::default()
    }));
    out
}

/// A full mip chain of an RGBA8 image by 2×2 box means of the bytes (generated test images
/// only: a real import averages colour in linear light).
fn box_mips(width: u32, height: u32, rgba: Vec<u8>) -> crowdmorph_core::rig::Mips {
    use crowdmorph_core::rig::{MipLevel, Mips};
    let mut levels = vec![MipLevel {
        width,
        height,
        rgba,
    }];
    while let Some(l) = levels.last().filter(|l| l.width > 1 || l.height > 1) {
        let (w, h) = ((l.width / 2).max(1), (l.height / 2).max(1));
        let mut next = Vec::with_capacity((w * h * 4) as usize);
        for y in 0..h {
            for x in 0..w {
                for c in 0..4 {
                    let at = |dx: u32, dy: u32| {
                        let (sx, sy) = (
                            (2 * x + dx).min(l.width - 1),
                            (2 * y + dy).min(l.height - 1),
                        );
                        u32::from(l.rgba[((sy * l.width + sx) * 4 + c) as usize])
                    };
                    next.push(((at(0, 0) + at(1, 0) + at(0, 1) + at(1, 1) + 2) / 4) as u8);
                }
            }
        }
        levels.push(MipLevel {
            width: w,
            height: h,
            rgba: next,
        });
    }
    Mips { levels }
}

/// Drops every texture reference of `rig`'s materials (their factors stay): the same crowd
/// drawn untextured.
fn strip_textures(rig: &mut Rig) {
    if let Some(a) = &rig.appearance {
        let mut a = (**a).clone();
        for m in &mut a.materials {
            m.base_color_texture = None;
            m.metallic_roughness_texture = None;
            m.normal_texture = None;
            m.occlusion_texture = None;
            m.emissive_texture = None;
        }
        rig.appearance = Some(Arc::new(a));
    }
}

/// Draws and encodes the crowd once.
pub fn draw_once(
    engine: &Engine,
    device: &RenderDevice,
    c: &Crowd,
    image: &ImageOptions,
) -> Result<(Vec<u8>, StageTimes)> {
    let groups: Vec<CrowdGroup<'_>> = c
        .groups
        .iter()
        .zip(&c.topologies)
        .map(|(g, t)| CrowdGroup {
            prepared: &c.prepared,
            topology: t.clone(),
            jobs: g.jobs.clone(),
            instances: g.instances.clone(),
        })
        .collect();
    let drawn = crowd::draw(engine, device, &groups, &c.view, &c.frame)?;
    let encoding = Instant::now();
    let out = drawn.output;
    let bytes = encode::encode(out.rgba, out.width, out.height, image.format, image.quality)?;
    let ms = |ns: u64| ns as f64 / 1e6;
    let mut t = StageTimes {
        compute_ms: ms(drawn.compute_ns),
        render_ms: ms(out.render_ns),
        readback_ms: ms(out.readback_ns),
        encode_ms: encoding.elapsed().as_secs_f64() * 1e3,
        total_ms: 0.0,
    };
    t.total_ms = t.compute_ms + t.render_ms + t.readback_ms + t.encode_ms;
    Ok((bytes, t))
}

/// What drawing `c` at `opt` reports, with the times of `runs` frames.
pub fn report(
    engine: &Engine,
    device: &RenderDevice,
    c: &Crowd,
    opt: &RenderOptions,
    bytes: usize,
    times: StageTimes,
    runs: usize,
) -> RenderReport {
    RenderReport {
        rig: c.rig.clone(),
        adapter: device.name(),
        shared_device: device.shared,
        engine: engine.info().kind,
        vertices: c.vertices,
        heads: opt.heads,
        unique: c.unique,
        width: opt.image.width,
        height: opt.image.height,
        format: opt.image.format.name().to_string(),
        bytes,
        texture_slots: c.texture_slots,
        texture_bytes: c.topologies.first().map_or(0, |t| t.texture_bytes()),
        times,
        runs,
    }
}

/// The renderer `opt` asks for, next to `engine`.
pub fn open_device(engine: &Engine, opt: &RenderOptions) -> Result<RenderDevice> {
    let options = GpuOptions {
        memory: opt.gpu_memory,
        ..GpuOptions::default()
    };
    RenderDevice::open_with(engine, opt.backend, options).map_err(OfflineError::NoRenderer)
}

/// Draws the crowd `opt` describes and returns the encoded image.
pub fn render_image(
    engine: &Engine,
    rig: &Rig,
    opt: &RenderOptions,
) -> Result<(Vec<u8>, RenderReport)> {
    let device = open_device(engine, opt)?;
    let c = build(engine, &device, rig, opt)?;
    let (bytes, times) = draw_once(engine, &device, &c, &opt.image)?;
    let r = report(engine, &device, &c, opt, bytes.len(), times, 1);
    Ok((bytes, r))
}

/// `crowdmorph render`: draws the crowd and writes the image to `out`.
pub fn render_to_file(
    engine: &Engine,
    rig: &Rig,
    opt: &RenderOptions,
    out: &Path,
) -> Result<RenderReport> {
    let (bytes, report) = render_image(engine, rig, opt)?;
    std::fs::write(out, &bytes).map_err(|source| OfflineError::Io {
        path: out.display().to_string(),
        source,
    })?;
    Ok(report)
}

/// The image format a file name asks for: `.png`, `.jpg`/`.jpeg`, `.rgba`/`.raw`.
pub fn format_of(path: &Path) -> Option<ImageFormat> {
    match path.extension()?.to_str()?.to_ascii_lowercase().as_str() {
        "png" => Some(ImageFormat::Png),
        "jpg" | "jpeg" => Some(ImageFormat::Jpeg),
        "rgba" | "raw" => Some(ImageFormat::Rgba),
        _ => None,
    }
}

/// Human-readable `bench render` (and `render`) output.
impl std::fmt::Display for RenderReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let r = self;
        let t = &r.times;
        write!(
            f,
            "{} heads ({} unique) of {:?}, {} vertices each, {} texture slots ({} bytes), \
             {}×{} {} ({} bytes)\n\
         engine {:?}, renderer {}{}\n\
         ms per frame (median of {}): compute {:.2}, render {:.2}, readback {:.2}, encode {:.2}, \
         total {:.2} ({:.1} frames/s)\n",
            r.heads,
            r.unique,
            r.rig,
            r.vertices,
            r.texture_slots,
            r.texture_bytes,
            r.width,
            r.height,
            r.format,
            r.bytes,
            r.engine,
            r.adapter,
            if r.shared_device {
                " (the engine's device)"
            } else {
                ""
            },
            r.runs,
            t.compute_ms,
            t.render_ms,
            t.readback_ms,
            t.encode_ms,
            t.total_ms,
            if t.total_ms > 0.0 {
                1e3 / t.total_ms
            } else {
                0.0
            }
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn file_names_choose_the_format() {
        assert_eq!(format_of(Path::new("a/crowd.png")), Some(ImageFormat::Png));
        assert_eq!(format_of(Path::new("crowd.JPG")), Some(ImageFormat::Jpeg));
        assert_eq!(format_of(Path::new("crowd.jpeg")), Some(ImageFormat::Jpeg));
        assert_eq!(format_of(Path::new("crowd.rgba")), Some(ImageFormat::Rgba));
        assert_eq!(format_of(Path::new("crowd")), None);
        assert_eq!(format_of(Path::new("crowd.gif")), None);
    }
}
