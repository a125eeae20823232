//! Textures that change with the expression (GPU Gems 3 ch. 15, issue 46 item 7): a
//! material's base colour becomes `base(uv) + Σ_k c_k · T_k(uv)` in linear RGBA, clamped to
//! [0, 1], before the material's factor. One mechanism, two forms, because both are the same
//! linear combination:
//! - **target textures** (wrinkle maps): layer = texture − base, its
//!   coefficient the target's final weight clamped to [0, 1], so at weight 1 the surface shows
//!   the wrinkle texture (glTF `extras` on the material; README "Appearance"; the type is
//!   [`super::TargetTexture`], beside the materials);
//! - **animated textures of a clip** ([`AnimatedTexture`]): the chapter's PCA form, a mean and
//!   K components with K coefficients per frame. Its layers are `mean − base` (coefficient: the
//!   clip's share of the pose) and the components (coefficients: the frame's, times that share),
//!   so a blend or a graph transition blends them with the same fractions as the weights.
//!
//! Components are region-masked (a component of region r is zero outside r), which keeps the
//! decode one uniform sum however many components each region has: the chapter's per-region
//! counts (more where the eyes are) cost nothing in the shader.
//!
//! [`layer_inputs`] is the per-job vector every layer reads its coefficient from; clones of a
//! job share their pose, so they share it too (the renderer puts it in the draw's uniform).

use serde::{Deserialize, Serialize};

use super::{Pose, Rig};

/// Most layers one material sums (the shader's `coefficients: array<vec4<f32>, 4>`).
pub const MAX_LAYERS: usize = 16;

/// Largest side of an animated texture: the `--max-texture-size` default.
pub const MAX_ANIMATED_SIZE: u32 = 4096;

/// One region of an [`AnimatedTexture`]: a rectangle and how many components it keeps. A
/// pixel belongs to the first region whose rectangle holds it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TextureRegion {
    /// Its name (in reports).
    pub name: String,
    /// `[x, y, width, height]` in pixels, rows top to bottom.
    pub rect: [u32; 4],
    /// Components kept for it.
    pub components: u32,
}

/// A clip's animated base colour in the chapter's PCA form.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AnimatedTexture {
    /// The clip it plays with (a name of [`Rig::clips`]).
    pub clip: String,
    /// The material whose base colour it replaces.
    pub material: u32,
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Frames of coefficients (the clip's frame count).
    pub frames: u32,
    /// The regions, in precedence order.
    pub regions: Vec<TextureRegion>,
    /// Linear RGB per pixel, rows top to bottom (`width × height × 3`).
    pub mean: Vec<f32>,
    /// The components, each linear RGB per pixel like `mean`, zero outside its region.
    pub components: Vec<Vec<f32>>,
    /// Per component, the region it belongs to.
    pub component_region: Vec<u32>,
    /// `frames × components`, row-major: frame `f`'s coefficient of component `k` is
    /// `coefficients[f * K + k]`.
    pub coefficients: Vec<f32>,
}

/// Why an animated texture is refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum AnimatedTextureError {
    /// Sizes or counts that do not agree, or are out of range.
    #[error("animated texture: {0}")]
    Malformed(String),
}

impl AnimatedTexture {
    /// Components (K).
    pub fn layers(&self) -> usize {
        self.components.len()
    }

    /// Host bytes it holds.
    pub fn bytes(&self) -> u64 {
        let floats = self.mean.len()
            + self.components.iter().map(Vec::len).sum::<usize>()
            + self.coefficients.len();
        floats as u64 * 4 + self.component_region.len() as u64 * 4 + 64 * self.regions.len() as u64
    }

    /// Frame `f`'s coefficients (empty past the end).
    pub fn coefficients_at(&self, f: u32) -> &[f32] {
        let k = self.layers();
        self.coefficients
            .get(f as usize * k..(f as usize + 1) * k)
            .unwrap_or(&[])
    }

    /// Index of the region pixel `(x, y)` belongs to.
    pub fn region_of(regions: &[TextureRegion], x: u32, y: u32) -> Option<usize> {
        regions.iter().position(|r| {
            let [rx, ry, rw, rh] = r.rect;
            x >= rx && y >= ry && x - rx < rw && y - ry < rh
        })
    }

    /// The CPU reference decode of frame `f` in f64: linear RGB per pixel, not clamped.
    pub fn decode(&self, f: u32) -> Vec<f64> {
        let c = self.coefficients_at(f);
        let mut out: Vec<f64> = self.mean.iter().map(|&v| f64::from(v)).collect();
        for (comp, &ck) in self.components.iter().zip(c) {
            for (o, &v) in out.iter_mut().zip(comp) {
                *o += f64::from(ck) * f64::from(v);
            }
        }
        out
    }

    /// Checks sizes, counts and values (for uploads and stored records).
    pub fn validate(&self) -> Result<(), AnimatedTextureError> {
        let bad = |s: String| Err(AnimatedTextureError::Malformed(s));
        if self.width == 0
            || self.height == 0
            || self.width > MAX_ANIMATED_SIZE
            || self.height > MAX_ANIMATED_SIZE
        {
            return bad(format!(
                "{} × {} pixels (1 to {MAX_ANIMATED_SIZE} a side)",
                self.width, self.height
            ));
        }
        let texels = self.width as usize * self.height as usize * 3;
        if self.mean.len() != texels {
            return bad(format!("mean of {} values, want {texels}", self.mean.len()));
        }
        // One layer is the mean's.
        if self.layers() + 1 > MAX_LAYERS {
            return bad(format!(
                "{} components: at most {} (one of the {MAX_LAYERS} layers is the mean)",
                self.layers(),
                MAX_LAYERS - 1
            ));
        }
        if let Some(k) = self.components.iter().position(|c| c.len() != texels) {
            return bad(format!("component {k} does not have {texels} values"));
        }
        if self.component_region.len() != self.layers()
            || self
                .component_region
                .iter()
                .any(|&r| r as usize >= self.regions.len())
        {
            return bad("each component needs a region of the texture".into());
        }
        let want = self.frames as usize * self.layers();
        if self.coefficients.len() != want {
            return bad(format!(
                "{} coefficients for {} frames × {} components",
                self.coefficients.len(),
                self.frames,
                self.layers()
            ));
        }
        let finite = self
            .mean
            .iter()
            .chain(self.components.iter().flatten())
            .chain(&self.coefficients)
            .all(|v| v.is_finite());
        if !finite {
            return bad("a value is not finite".into());
        }
        Ok(())
    }
}

/// The first bytes of [`AnimatedTexture::to_bytes`]: `CMAT` and format version 1.
pub const TEXTURE_MAGIC: [u8; 8] = *b"CMAT\x01\0\0\0";

/// Longest region name in the byte form.
const MAX_REGION_NAME: usize = 256;

/// Bytes of the fixed header after the magic: material, width, height, frames, regions,
/// components (u32 each).
const HEADER: usize = 6 * 4;

impl AnimatedTexture {
    /// The byte form `PUT /v1/rigs/{id}/clips/{clip}/texture` takes, `crowdmorph clips
    /// compress-texture` writes and the store keeps (proto/README.md): little-endian,
    /// [`TEXTURE_MAGIC`]; material, width, height, frames, regions R, components K (u32); per
    /// region its name (u32 length, UTF-8), `x, y, w, h`, components (u32); per component its
    /// region (u32); then f32s: the mean (`w × h × 3`), the K components (each `w × h × 3`),
    /// the coefficients (`frames × K`). The clip is named by the URL, not the bytes. Every
    /// size is in the header, so a reader checks the length and charges before allocating.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(self.bytes() as usize + 64);
        out.extend_from_slice(&TEXTURE_MAGIC);
        for v in [
            self.material,
            self.width,
            self.height,
            self.frames,
            self.regions.len() as u32,
            self.components.len() as u32,
        ] {
            out.extend_from_slice(&v.to_le_bytes());
        }
        for r in &self.regions {
            out.extend_from_slice(&(r.name.len() as u32).to_le_bytes());
            out.extend_from_slice(r.name.as_bytes());
            for v in r.rect.iter().chain([&r.components]) {
                out.extend_from_slice(&v.to_le_bytes());
            }
        }
        for r in &self.component_region {
            out.extend_from_slice(&r.to_le_bytes());
        }
        for v in self
            .mean
            .iter()
            .chain(self.components.iter().flatten())
            .chain(&self.coefficients)
        {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out
    }

    /// Host bytes the texture the header of `bytes` declares will hold once decoded, with the
    /// header checked (sizes within limits, the length exactly what they need): what a reader
    /// charges before [`AnimatedTexture::from_bytes`] allocates.
    pub fn declared_bytes(bytes: &[u8]) -> Result<u64, AnimatedTextureError> {
        Ok(Self::layout(bytes)?.1)
    }

    /// Reads the byte form (see [`AnimatedTexture::to_bytes`]) of clip `clip`'s texture,
    /// validated. Allocates what [`AnimatedTexture::declared_bytes`] says, no more.
    pub fn from_bytes(clip: &str, bytes: &[u8]) -> Result<AnimatedTexture, AnimatedTextureError> {
        let (h, _) = Self::layout(bytes)?;
        let mut at = h.floats_at;
        let mut floats = |n: usize| -> Vec<f32> {
            let v = bytes[at..at + 4 * n]
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect();
            at += 4 * n;
            v
        };
        let texels = h.width as usize * h.height as usize * 3;
        let mean = floats(texels);
        let components = (0..h.components).map(|_| floats(texels)).collect();
        let coefficients = floats(h.frames as usize * h.components);
        let t = AnimatedTexture {
            clip: clip.into(),
            material: h.material,
            width: h.width,
            height: h.height,
            frames: h.frames,
            regions: h.regions,
            mean,
            components,
            component_region: h.component_region,
            coefficients,
        };
        t.validate()?;
        Ok(t)
    }

    /// The header of `bytes`, checked, and the decoded texture's host bytes.
    fn layout(bytes: &[u8]) -> Result<(Header, u64), AnimatedTextureError> {
        let bad = |s: String| AnimatedTextureError::Malformed(s);
        if bytes.len() < TEXTURE_MAGIC.len() + HEADER || bytes[..8] != TEXTURE_MAGIC {
            return Err(bad(
                "not an animated texture (it starts with CMAT and version 1)".into(),
            ));
        }
        let mut at = TEXTURE_MAGIC.len();
        let u32_at = |at: &mut usize| -> Result<u32, AnimatedTextureError> {
            let b = bytes
                .get(*at..*at + 4)
                .ok_or_else(|| bad(format!("ends at byte {} inside its header", bytes.len())))?;
            *at += 4;
            Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        };
        let material = u32_at(&mut at)?;
        let width = u32_at(&mut at)?;
        let height = u32_at(&mut at)?;
        let frames = u32_at(&mut at)?;
        let regions = u32_at(&mut at)? as usize;
        let components = u32_at(&mut at)? as usize;
        if width == 0 || height == 0 || width > MAX_ANIMATED_SIZE || height > MAX_ANIMATED_SIZE {
            return Err(bad(format!(
                "{width} × {height} pixels (1 to {MAX_ANIMATED_SIZE} a side)"
            )));
        }
        if components > MAX_LAYERS - 1 {
            return Err(bad(format!(
                "{components} components (at most {})",
                MAX_LAYERS - 1
            )));
        }
        if regions == 0 || regions > MAX_LAYERS {
            return Err(bad(format!("{regions} regions (1 to {MAX_LAYERS})")));
        }
        if frames as usize > super::MAX_FRAMES {
            return Err(bad(format!(
                "{frames} frames (at most {})",
                super::MAX_FRAMES
            )));
        }
        let mut list = Vec::with_capacity(regions);
        for r in 0..regions {
            let len = u32_at(&mut at)? as usize;
            if len > MAX_REGION_NAME {
                return Err(bad(format!("region {r}'s name is {len} bytes")));
            }
            let name = bytes
                .get(at..at + len)
                .and_then(|b| std::str::from_utf8(b).ok())
                .ok_or_else(|| bad(format!("region {r}'s name is cut short or not UTF-8")))?
                .to_string();
            at += len;
            let rect = [
                u32_at(&mut at)?,
                u32_at(&mut at)?,
                u32_at(&mut at)?,
                u32_at(&mut at)?,
            ];
            let components = u32_at(&mut at)?;
            list.push(TextureRegion {
                name,
                rect,
                components,
            });
        }
        let component_region = (0..components)
            .map(|_| u32_at(&mut at))
            .collect::<Result<Vec<u32>, _>>()?;
        // In u64: at most 4096² × 3 × 16 + 2^16 × 15 floats, far from overflowing.
        let texels = u64::from(width) * u64::from(height) * 3;
        let floats = texels * (1 + components as u64) + u64::from(frames) * components as u64;
        let want = at as u64 + floats * 4;
        if bytes.len() as u64 != want {
            return Err(bad(format!(
                "{} bytes; its header declares {want} ({width} × {height}, {components} \
                 components, {frames} frames)",
                bytes.len()
            )));
        }
        Ok((
            Header {
                material,
                width,
                height,
                frames,
                components,
                regions: list,
                component_region,
                floats_at: at,
            },
            floats * 4,
        ))
    }
}

/// The header of the byte form, read.
struct Header {
    material: u32,
    width: u32,
    height: u32,
    frames: u32,
    components: usize,
    regions: Vec<TextureRegion>,
    component_region: Vec<u32>,
    floats_at: usize,
}

/// The per-job vector layers read their coefficients from: the rig's final target weights
/// (after the LOD level's cut; `T` values), then per clip texture of the appearance, in its
/// order, the clip's share of the pose followed by its `K` components' blended coefficients.
/// Empty when the rig has no layers (the renderer then sums nothing).
pub fn layer_inputs(rig: &Rig, pose: &Pose, lod: u32) -> Vec<f32> {
    let Some(a) = &rig.appearance else {
        return Vec::new();
    };
    if a.target_textures.is_empty() && a.clip_textures.is_empty() {
        return Vec::new();
    }
    let shapes = rig.lod.shapes_at(lod).unwrap_or(u32::MAX) as usize;
    let mut out = vec![0f32; rig.targets.len()];
    // The LOD cut: only the first `shapes` of the importance order are evaluated, so only
    // those can show their wrinkles.
    for &t in rig.lod.order.iter().take(shapes) {
        if let Some(w) = out.get_mut(t as usize) {
            *w = pose.weight(rig, t as usize);
        }
    }
    // A pose's clip terms with their fractions (live weights play no clip).
    let terms: Vec<(u32, u32, f32)> = match pose {
        Pose::Frame { clip, frame } => vec![(*clip, *frame, 1.0)],
        Pose::Blend(t) => t.iter().map(|t| (t.clip, t.frame, t.fraction())).collect(),
        Pose::Live(_) => Vec::new(),
    };
    for ct in &a.clip_textures {
        let at = out.len();
        out.resize(at + 1 + ct.layers(), 0.0);
        for &(clip, frame, share) in &terms {
            // Its clip, with the frames it was made for (the upload checks both): a texture a
            // deleted clip left behind never reads past its coefficients on a later clip of
            // its name with another length.
            let Some(c) = rig.clips.get(clip as usize) else {
                continue;
            };
            if c.name != ct.clip || c.frames != ct.frames {
                continue;
            }
            out[at] += share;
            for (o, &c) in out[at + 1..].iter_mut().zip(ct.coefficients_at(frame)) {
                *o += share * c;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tiny() -> AnimatedTexture {
        AnimatedTexture {
            clip: "c".into(),
            material: 0,
            width: 2,
            height: 1,
            frames: 2,
            regions: vec![TextureRegion {
                name: "all".into(),
                rect: [0, 0, 2, 1],
                components: 1,
            }],
            mean: vec![0.5; 6],
            components: vec![vec![0.1, 0.0, 0.0, 0.0, 0.2, 0.0]],
            component_region: vec![0],
            coefficients: vec![1.0, -2.0],
        }
    }

    #[test]
    fn decode_is_the_mean_plus_the_frames_components() {
        let t = tiny();
        assert_eq!(t.validate(), Ok(()));
        let d = t.decode(1);
        assert!(
            (d[0] - 0.3).abs() < 1e-7 && (d[4] - 0.1).abs() < 1e-7,
            "{d:?}"
        );
        assert!(t.coefficients_at(2).is_empty());
        let mut bad = tiny();
        bad.coefficients.pop();
        assert!(bad.validate().is_err());
        bad = tiny();
        bad.mean[0] = f32::NAN;
        assert!(bad.validate().is_err());
    }

    #[test]
    fn the_byte_form_round_trips_and_refuses_a_length_its_header_does_not_declare() {
        let t = tiny();
        let b = t.to_bytes();
        assert_eq!(AnimatedTexture::declared_bytes(&b), Ok((6 + 6 + 2) * 4));
        assert_eq!(AnimatedTexture::from_bytes("c", &b), Ok(t));
        assert!(AnimatedTexture::from_bytes("c", &b[..b.len() - 1]).is_err());
        // A header that declares 4096 × 4096 over a short body: refused from the header.
        let mut big = b.clone();
        big[12..16].copy_from_slice(&4096u32.to_le_bytes());
        big[16..20].copy_from_slice(&4096u32.to_le_bytes());
        assert!(AnimatedTexture::declared_bytes(&big).is_err());
        big[12..16].copy_from_slice(&100_000u32.to_le_bytes());
        assert!(AnimatedTexture::declared_bytes(&big).is_err());
        assert!(AnimatedTexture::declared_bytes(b"CMAT").is_err());
    }

    #[test]
    fn the_first_region_holding_a_pixel_owns_it() {
        let r = |rect| TextureRegion {
            name: String::new(),
            rect,
            components: 1,
        };
        let regions = [r([1, 1, 2, 2]), r([0, 0, 4, 4])];
        assert_eq!(AnimatedTexture::region_of(&regions, 1, 2), Some(0));
        assert_eq!(AnimatedTexture::region_of(&regions, 3, 3), Some(1));
        assert_eq!(AnimatedTexture::region_of(&regions, 4, 0), None);
    }
}
