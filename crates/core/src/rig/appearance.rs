//! What a rig looks like: its glTF materials, textures, samplers and images.
//!
//! The geometry side (texture coordinates, vertex colours, a primitive's material index) is
//! per vertex and lives in [`super::VertexLook`]; this module holds what primitives share, once
//! per rig ([`super::Rig::appearance`]), so clones and mesh levels share it too (an `Arc`).
//!
//! The model mirrors glTF 2.0's metallic-roughness material (the spec's section 3.9) with the
//! extensions the renderer draws (`KHR_texture_transform`, `KHR_materials_emissive_strength`,
//! `KHR_materials_unlit`, `EXT_texture_webp`); anything a file asks for that is not drawn is a
//! sentence in [`Appearance::notes`], never silent. Images keep their encoded bytes (what the
//! store persists and `GET /v1/rigs/{id}/textures/{i}` serves); their decoded pixels with the
//! mip chain ([`Mips`]) are rebuilt from those bytes on every load and charged to the rig pool,
//! so the store never holds pixels.

use std::sync::Arc;

use glam::Vec2;
use serde::{Deserialize, Serialize};

use super::animated_texture::{AnimatedTexture, MAX_LAYERS};

/// A rig's materials and what they sample. Indices follow the file's arrays after import
/// (a texture's `image`, a material's texture references), so the JSON clients get is
/// glTF-shaped.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Appearance {
    /// glTF materials, by index ([`super::VertexLook::material`] names one).
    pub materials: Vec<Material>,
    /// glTF textures: an image and a sampler each.
    pub textures: Vec<Texture>,
    /// glTF samplers.
    pub samplers: Vec<Sampler>,
    /// The images, encoded as uploaded (or re-encoded after a downscale).
    pub images: Vec<ImageData>,
    /// What the import did not draw or changed, one sentence each (an unsupported material
    /// extension, a KTX2 texture without a fallback, a downscaled image).
    pub notes: Vec<String>,
    /// Textures that fade in with a morph target's weight (wrinkle maps), from the materials'
    /// `extras.crowdmorph.targetTextures` ([`super::animated_texture`]).
    #[serde(default)]
    pub target_textures: Vec<TargetTexture>,
    /// Clips' animated base colours (PCA), uploaded beside their clips; not in the JSON
    /// tables (their arrays are stored as their own section).
    #[serde(skip)]
    pub clip_textures: Vec<Arc<AnimatedTexture>>,
}

/// glTF's `material`, as the renderer draws it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Material {
    /// The file's name of the material.
    pub name: Option<String>,
    /// `pbrMetallicRoughness.baseColorFactor`, linear RGBA.
    pub base_color_factor: [f32; 4],
    /// `pbrMetallicRoughness.baseColorTexture` (sRGB).
    pub base_color_texture: Option<TexRef>,
    /// `pbrMetallicRoughness.metallicFactor`.
    pub metallic_factor: f32,
    /// `pbrMetallicRoughness.roughnessFactor`.
    pub roughness_factor: f32,
    /// `pbrMetallicRoughness.metallicRoughnessTexture` (B metallic, G roughness; linear).
    pub metallic_roughness_texture: Option<TexRef>,
    /// `normalTexture` (tangent space, linear).
    pub normal_texture: Option<TexRef>,
    /// `normalTexture.scale`.
    pub normal_scale: f32,
    /// `occlusionTexture` (R channel, linear).
    pub occlusion_texture: Option<TexRef>,
    /// `occlusionTexture.strength`.
    pub occlusion_strength: f32,
    /// `emissiveFactor`, linear RGB.
    pub emissive_factor: [f32; 3],
    /// `KHR_materials_emissive_strength.emissiveStrength` (1 without the extension).
    pub emissive_strength: f32,
    /// `emissiveTexture` (sRGB).
    pub emissive_texture: Option<TexRef>,
    /// `alphaMode`.
    pub alpha_mode: AlphaMode,
    /// `alphaCutoff` (used with [`AlphaMode::Mask`]).
    pub alpha_cutoff: f32,
    /// `doubleSided`.
    pub double_sided: bool,
    /// `KHR_materials_unlit`: drawn with its base colour only.
    pub unlit: bool,
}

impl Default for Material {
    /// glTF's default material (spec 3.9.6): white, metallic 1, roughness 1, opaque.
    fn default() -> Self {
        Material {
            name: None,
            base_color_factor: [1.0; 4],
            base_color_texture: None,
            metallic_factor: 1.0,
            roughness_factor: 1.0,
            metallic_roughness_texture: None,
            normal_texture: None,
            normal_scale: 1.0,
            occlusion_texture: None,
            occlusion_strength: 1.0,
            emissive_factor: [0.0; 3],
            emissive_strength: 1.0,
            emissive_texture: None,
            alpha_mode: AlphaMode::Opaque,
            alpha_cutoff: 0.5,
            double_sided: false,
            unlit: false,
        }
    }
}

impl Material {
    /// What a primitive without a material is drawn with: its base colour, dielectric and
    /// half rough. glTF's default material (metallic 1, roughness 1) is black without an
    /// environment map, which no user wants from a head without a material.
    pub fn untextured(base_color: [f32; 4]) -> Material {
        Material {
            base_color_factor: base_color,
            metallic_factor: 0.0,
            roughness_factor: 0.5,
            ..Material::default()
        }
    }

    /// Every texture reference of the material with the slot it fills.
    pub fn texture_refs(&self) -> impl Iterator<Item = (Slot, &TexRef)> {
        [
            (Slot::BaseColor, &self.base_color_texture),
            (Slot::MetallicRoughness, &self.metallic_roughness_texture),
            (Slot::Normal, &self.normal_texture),
            (Slot::Occlusion, &self.occlusion_texture),
            (Slot::Emissive, &self.emissive_texture),
        ]
        .into_iter()
        .filter_map(|(s, r)| r.as_ref().map(|r| (s, r)))
    }
}

/// A texture slot of a material.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Slot {
    /// Base colour (sRGB).
    BaseColor,
    /// Metallic (B) and roughness (G), linear.
    MetallicRoughness,
    /// Tangent-space normals, linear.
    Normal,
    /// Ambient occlusion (R), linear.
    Occlusion,
    /// Emissive colour (sRGB).
    Emissive,
}

impl Slot {
    /// Whether the slot holds colours (sampled through an sRGB view) rather than data.
    pub fn is_srgb(self) -> bool {
        matches!(self, Slot::BaseColor | Slot::Emissive)
    }
}

/// glTF's `alphaMode`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum AlphaMode {
    /// Alpha ignored.
    #[default]
    Opaque,
    /// Drawn where alpha ≥ the cutoff, a hole elsewhere.
    Mask,
    /// Blended over what is behind it.
    Blend,
}

impl AlphaMode {
    /// The glTF spelling.
    pub fn as_str(self) -> &'static str {
        match self {
            AlphaMode::Opaque => "OPAQUE",
            AlphaMode::Mask => "MASK",
            AlphaMode::Blend => "BLEND",
        }
    }
}

/// A texture that fades in with a morph target's weight (a wrinkle map).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TargetTexture {
    /// The material (index into [`super::Appearance::materials`]) whose base colour it changes.
    pub material: u32,
    /// The morph target's name ([`Rig::targets`]); a name the rig does not have is an import
    /// note and the layer stays at zero.
    pub target: String,
    /// The base colour texture at weight 1 (sRGB, as `baseColorTexture`).
    pub texture: TexRef,
}

/// A material's reference to a texture (glTF `textureInfo`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TexRef {
    /// Index into [`Appearance::textures`].
    pub texture: u32,
    /// Which texture coordinate set it reads (0 or 1).
    pub tex_coord: u8,
    /// `KHR_texture_transform`, when the reference has one.
    pub transform: Option<UvTransform>,
}

/// `KHR_texture_transform`: `uv' = T(offset) · R(rotation) · S(scale) · uv`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct UvTransform {
    /// Translation.
    pub offset: [f32; 2],
    /// Rotation in radians, counter-clockwise as the UVs are seen with glTF's origin at the
    /// image's top left (v down): the image turns clockwise on the surface.
    pub rotation: f32,
    /// Scale.
    pub scale: [f32; 2],
}

impl Default for UvTransform {
    fn default() -> Self {
        UvTransform {
            offset: [0.0; 2],
            rotation: 0.0,
            scale: [1.0; 2],
        }
    }
}

impl UvTransform {
    /// The transform as the rows of a 2×3 matrix (`uv' = M · (u, v, 1)`): `translation *
    /// rotation * scale` with `rotation` the rows `(cos, sin)` and `(-sin, cos)`, as three.js,
    /// Babylon.js, Blender and the Khronos sample `TextureTransformTest` have it. The
    /// extension's GLSL listing, read column-major, is the transpose (counter-clockwise with v
    /// up): it contradicts the extension's own example and sample (KhronosGroup/glTF#1563).
    pub fn rows(&self) -> [[f32; 3]; 2] {
        let (s, c) = self.rotation.sin_cos();
        let [sx, sy] = self.scale;
        let [ox, oy] = self.offset;
        [[c * sx, s * sy, ox], [-s * sx, c * sy, oy]]
    }

    /// Applies the transform to one coordinate.
    pub fn apply(&self, uv: Vec2) -> Vec2 {
        let [r0, r1] = self.rows();
        Vec2::new(
            r0[0] * uv.x + r0[1] * uv.y + r0[2],
            r1[0] * uv.x + r1[1] * uv.y + r1[2],
        )
    }
}

/// glTF's `texture`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Texture {
    /// Index into [`Appearance::samplers`]; glTF's default sampler without one.
    pub sampler: Option<u32>,
    /// Index into [`Appearance::images`]; `None` when the texture's only source is one the
    /// import cannot decode (a KTX2 image without a fallback): drawn with its factors.
    pub image: Option<u32>,
}

/// glTF's `sampler`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Sampler {
    /// Magnification filter.
    pub mag: Filter,
    /// Minification filter within a mip level.
    pub min: Filter,
    /// Filter between mip levels; `None`: the base level only.
    pub mipmap: Option<Filter>,
    /// Wrap along u.
    pub wrap_s: Wrap,
    /// Wrap along v.
    pub wrap_t: Wrap,
}

impl Default for Sampler {
    /// What glTF leaves to the implementation when a texture has no sampler: trilinear,
    /// repeating (three.js's choice too).
    fn default() -> Self {
        Sampler {
            mag: Filter::Linear,
            min: Filter::Linear,
            mipmap: Some(Filter::Linear),
            wrap_s: Wrap::Repeat,
            wrap_t: Wrap::Repeat,
        }
    }
}

/// A texture filter.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Filter {
    /// Nearest texel.
    Nearest,
    /// Bilinear.
    Linear,
}

/// A texture wrap mode.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Wrap {
    /// glTF 33071.
    ClampToEdge,
    /// glTF 33648.
    MirroredRepeat,
    /// glTF 10497.
    Repeat,
}

/// How an image's bytes are encoded.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum ImageMime {
    /// `image/png`.
    Png,
    /// `image/jpeg`.
    Jpeg,
    /// `image/webp` (`EXT_texture_webp`).
    Webp,
}

impl ImageMime {
    /// The MIME type.
    pub fn as_str(self) -> &'static str {
        match self {
            ImageMime::Png => "image/png",
            ImageMime::Jpeg => "image/jpeg",
            ImageMime::Webp => "image/webp",
        }
    }

    /// The type a MIME string names, if it is one the import reads.
    pub fn parse(mime: &str) -> Option<ImageMime> {
        match mime {
            "image/png" => Some(ImageMime::Png),
            "image/jpeg" | "image/jpg" => Some(ImageMime::Jpeg),
            "image/webp" => Some(ImageMime::Webp),
            _ => None,
        }
    }

    /// The usual file extension.
    pub fn extension(self) -> &'static str {
        match self {
            ImageMime::Png => "png",
            ImageMime::Jpeg => "jpg",
            ImageMime::Webp => "webp",
        }
    }
}

/// One image of the rig: its encoded bytes and, once decoded, its pixels.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ImageData {
    /// How [`ImageData::bytes`] is encoded.
    pub mime: ImageMime,
    /// The encoded image.
    pub bytes: Arc<[u8]>,
    /// Width in pixels of the encoded image.
    pub width: u32,
    /// Height in pixels of the encoded image.
    pub height: u32,
    /// The file's size when the import downscaled it to `--max-texture-size`.
    pub downscaled_from: Option<[u32; 2]>,
    /// The decoded pixels with their mip chain; never serialized (rebuilt on load).
    #[serde(skip)]
    pub pixels: Option<Arc<Mips>>,
}

impl PartialEq for ImageData {
    /// Images are equal when their encodings are: pixels are a function of the bytes.
    fn eq(&self, other: &Self) -> bool {
        self.mime == other.mime
            && self.bytes == other.bytes
            && self.width == other.width
            && self.height == other.height
            && self.downscaled_from == other.downscaled_from
    }
}

/// Decoded RGBA8 pixels (straight alpha, as encoded: sRGB or linear is the sampling slot's
/// business), the full mip chain from the base level down to 1 × 1.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mips {
    /// Level 0 first; each `(width, height, rgba)`.
    pub levels: Vec<MipLevel>,
}

/// One level of a [`Mips`] chain.
#[derive(Clone, Debug, PartialEq)]
pub struct MipLevel {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// `width × height × 4` bytes, rows top to bottom.
    pub rgba: Vec<u8>,
}

impl Mips {
    /// Bytes of every level.
    pub fn bytes(&self) -> usize {
        self.levels.iter().map(|l| l.rgba.len()).sum()
    }

    /// Bytes a full RGBA8 chain of a `width × height` image holds, without making it (what
    /// is charged before decoding).
    pub fn chain_bytes(width: u32, height: u32) -> u64 {
        let (mut w, mut h, mut total) = (width.max(1) as u64, height.max(1) as u64, 0u64);
        loop {
            total += w * h * 4;
            if w == 1 && h == 1 {
                return total;
            }
            w = (w / 2).max(1);
            h = (h / 2).max(1);
        }
    }
}

impl Appearance {
    /// Host bytes held: encoded images, decoded chains and the small tables.
    pub fn bytes(&self) -> usize {
        let images: usize = self
            .images
            .iter()
            .map(|i| i.bytes.len() + i.pixels.as_ref().map_or(0, |p| p.bytes()))
            .sum();
        images
            + self
                .clip_textures
                .iter()
                .map(|t| t.bytes() as usize)
                .sum::<usize>()
            + self
                .target_textures
                .iter()
                .map(|t| size_of::<TargetTexture>() + t.target.len())
                .sum::<usize>()
            + self.materials.len() * size_of::<Material>()
            + self.textures.len() * size_of::<Texture>()
            + self.samplers.len() * size_of::<Sampler>()
            + self.notes.iter().map(String::len).sum::<usize>()
    }

    /// Bytes of the decoded chains of every image (what a load charges before decoding).
    pub fn decoded_bytes(&self) -> u64 {
        self.images
            .iter()
            .map(|i| Mips::chain_bytes(i.width, i.height))
            .sum()
    }

    /// The image a material slot samples, when it has one the import could decode.
    pub fn image_of(&self, r: &TexRef) -> Option<&ImageData> {
        let t = self.textures.get(r.texture as usize)?;
        self.images.get(t.image? as usize)
    }

    /// The sampler of a texture reference (glTF's default when none is named).
    pub fn sampler_of(&self, r: &TexRef) -> Sampler {
        self.textures
            .get(r.texture as usize)
            .and_then(|t| t.sampler)
            .and_then(|s| self.samplers.get(s as usize).copied())
            .unwrap_or_default()
    }

    /// Checks that every index points inside its array, for records read from a store or
    /// built by hand: the renderer and the endpoints index without checking again.
    pub fn validate(&self) -> Result<(), String> {
        for (i, m) in self.materials.iter().enumerate() {
            for (slot, r) in m.texture_refs() {
                if r.texture as usize >= self.textures.len() {
                    return Err(format!(
                        "material {i}: {slot:?} texture {} of {}",
                        r.texture,
                        self.textures.len()
                    ));
                }
                if r.tex_coord > 1 {
                    return Err(format!(
                        "material {i}: {slot:?} reads texture coordinate set {}",
                        r.tex_coord
                    ));
                }
            }
            let finite = m
                .base_color_factor
                .iter()
                .chain(&m.emissive_factor)
                .chain(&[
                    m.metallic_factor,
                    m.roughness_factor,
                    m.normal_scale,
                    m.occlusion_strength,
                    m.emissive_strength,
                    m.alpha_cutoff,
                ])
                .all(|v| v.is_finite());
            if !finite {
                return Err(format!("material {i}: a factor is not finite"));
            }
        }
        for (i, t) in self.textures.iter().enumerate() {
            if t.sampler.is_some_and(|s| s as usize >= self.samplers.len()) {
                return Err(format!("texture {i}: no sampler {:?}", t.sampler));
            }
            if t.image.is_some_and(|s| s as usize >= self.images.len()) {
                return Err(format!("texture {i}: no image {:?}", t.image));
            }
        }
        for (i, im) in self.images.iter().enumerate() {
            if im.width == 0 || im.height == 0 {
                return Err(format!("image {i} is {} × {}", im.width, im.height));
            }
        }
        for (i, t) in self.target_textures.iter().enumerate() {
            if t.material as usize >= self.materials.len()
                || t.texture.texture as usize >= self.textures.len()
                || t.texture.tex_coord > 1
            {
                return Err(format!(
                    "target texture {i} ({:?}): material {} of {}, texture {} of {}",
                    t.target,
                    t.material,
                    self.materials.len(),
                    t.texture.texture,
                    self.textures.len()
                ));
            }
        }
        for t in &self.clip_textures {
            t.validate()
                .map_err(|e| format!("clip {:?}: {e}", t.clip))?;
            if t.material as usize >= self.materials.len() {
                return Err(format!(
                    "clip {:?}: animated texture of material {} of {}",
                    t.clip,
                    t.material,
                    self.materials.len()
                ));
            }
        }
        for m in 0..self.materials.len() {
            let n = self.layer_count(m);
            if n > MAX_LAYERS {
                return Err(format!(
                    "material {m}: {n} texture layers (target textures, and each animated \
                     texture's mean and components); at most {MAX_LAYERS}"
                ));
            }
        }
        Ok(())
    }

    /// Layers material `m` sums: its target textures, then each clip texture's mean and
    /// components.
    pub fn layer_count(&self, m: usize) -> usize {
        self.target_textures
            .iter()
            .filter(|t| t.material as usize == m)
            .count()
            + self
                .clip_textures
                .iter()
                .filter(|t| t.material as usize == m)
                .map(|t| 1 + t.layers())
                .sum::<usize>()
    }
}

/// glTF's JSON of a texture reference (`textureInfo`, with `scale` or `strength` where the
/// slot has one).
fn tex_json(r: &TexRef, extra: Option<(&str, f32)>) -> serde_json::Value {
    let mut o = serde_json::json!({ "index": r.texture, "texCoord": r.tex_coord });
    if let Some((k, v)) = extra {
        o[k] = v.into();
    }
    if let Some(t) = &r.transform {
        o["extensions"] = serde_json::json!({ "KHR_texture_transform": {
            "offset": t.offset, "rotation": t.rotation, "scale": t.scale } });
    }
    o
}

impl Material {
    /// The material as glTF 2.0 JSON (what `GET /v1/rigs/{id}/materials` and `model.glb`
    /// carry), with the extensions it uses.
    pub fn gltf_json(&self) -> serde_json::Value {
        let mut pbr = serde_json::json!({
            "baseColorFactor": self.base_color_factor,
            "metallicFactor": self.metallic_factor,
            "roughnessFactor": self.roughness_factor,
        });
        if let Some(r) = &self.base_color_texture {
            pbr["baseColorTexture"] = tex_json(r, None);
        }
        if let Some(r) = &self.metallic_roughness_texture {
            pbr["metallicRoughnessTexture"] = tex_json(r, None);
        }
        let mut m = serde_json::json!({
            "pbrMetallicRoughness": pbr,
            "emissiveFactor": self.emissive_factor,
            "alphaMode": self.alpha_mode.as_str(),
            "doubleSided": self.double_sided,
        });
        if let Some(n) = &self.name {
            m["name"] = n.as_str().into();
        }
        if self.alpha_mode == AlphaMode::Mask {
            m["alphaCutoff"] = self.alpha_cutoff.into();
        }
        if let Some(r) = &self.normal_texture {
            m["normalTexture"] = tex_json(r, Some(("scale", self.normal_scale)));
        }
        if let Some(r) = &self.occlusion_texture {
            m["occlusionTexture"] = tex_json(r, Some(("strength", self.occlusion_strength)));
        }
        if let Some(r) = &self.emissive_texture {
            m["emissiveTexture"] = tex_json(r, None);
        }
        let mut ext = serde_json::Map::new();
        if self.emissive_strength != 1.0 {
            ext.insert(
                "KHR_materials_emissive_strength".into(),
                serde_json::json!({ "emissiveStrength": self.emissive_strength }),
            );
        }
        if self.unlit {
            ext.insert("KHR_materials_unlit".into(), serde_json::json!({}));
        }
        if !ext.is_empty() {
            m["extensions"] = ext.into();
        }
        m
    }
}

impl Sampler {
    /// The sampler as glTF 2.0 JSON (its enum codes).
    pub fn gltf_json(&self) -> serde_json::Value {
        let wrap = |w: Wrap| match w {
            Wrap::ClampToEdge => 33071,
            Wrap::MirroredRepeat => 33648,
            Wrap::Repeat => 10497,
        };
        let min = match (self.min, self.mipmap) {
            (Filter::Nearest, None) => 9728,
            (Filter::Linear, None) => 9729,
            (Filter::Nearest, Some(Filter::Nearest)) => 9984,
            (Filter::Linear, Some(Filter::Nearest)) => 9985,
            (Filter::Nearest, Some(Filter::Linear)) => 9986,
            (Filter::Linear, Some(Filter::Linear)) => 9987,
        };
        serde_json::json!({
            "magFilter": if self.mag == Filter::Nearest { 9728 } else { 9729 },
            "minFilter": min,
            "wrapS": wrap(self.wrap_s),
            "wrapT": wrap(self.wrap_t),
        })
    }
}

/// Most bytes one material, texture or sampler takes in [`Appearance::gltf_json`], its
/// name aside, as a `serde_json::Value` or as text: every slot of a material filled, each with a
/// transform and every number at its longest, is 1,822 bytes of text, and a `Value` is allowed
/// four times its text (`a_full_material_fits_its_json_allowance`).
pub const JSON_ENTRY_BYTES: u64 = 8192;

impl Appearance {
    /// glTF 2.0's `materials`, `textures` and `samplers` arrays of the appearance, and
    /// `images` made by `image` from each image's index (a URI for clients, a buffer view in
    /// a GLB). A texture without a decodable image gets no `source` (glTF allows that when an
    /// extension provides one; a client draws it with the factors).
    pub fn gltf_json(
        &self,
        mut image: impl FnMut(usize, &ImageData) -> serde_json::Value,
    ) -> serde_json::Value {
        let textures: Vec<serde_json::Value> = self
            .textures
            .iter()
            .map(|t| {
                let mut o = serde_json::json!({});
                if let Some(s) = t.sampler {
                    o["sampler"] = s.into();
                }
                if let Some(i) = t.image {
                    o["source"] = i.into();
                }
                o
            })
            .collect();
        let materials: Vec<serde_json::Value> = self
            .materials
            .iter()
            .enumerate()
            .map(|(i, m)| {
                let mut j = m.gltf_json();
                let targets: Vec<serde_json::Value> = self
                    .target_textures
                    .iter()
                    .filter(|t| t.material as usize == i)
                    .map(|t| {
                        serde_json::json!({
                            "target": t.target,
                            "baseColorTexture": tex_json(&t.texture, None),
                        })
                    })
                    .collect();
                if !targets.is_empty() {
                    j["extras"] =
                        serde_json::json!({ "crowdmorph": { "targetTextures": targets } });
                }
                j
            })
            .collect();
        serde_json::json!({
            "materials": materials,
            "textures": textures,
            "samplers": self.samplers.iter().map(Sampler::gltf_json).collect::<Vec<_>>(),
            "images": self.images.iter().enumerate().map(|(i, d)| image(i, d)).collect::<Vec<_>>(),
        })
    }

    /// Bytes [`Appearance::gltf_json`]'s value and its text take at most, given `per_image`
    /// bytes for what the caller writes of each image: what a server charges before making
    /// them. Each table entry's keys and numbers fit [`JSON_ENTRY_BYTES`]; the strings the
    /// file chose (material names, notes) count 6 bytes a byte, as JSON may escape a byte as
    /// `\u00XX`.
    pub fn gltf_json_bytes(&self, per_image: u64) -> u64 {
        let entries = (self.materials.len() + self.textures.len() + self.samplers.len()) as u64;
        let names: u64 = self
            .materials
            .iter()
            .map(|m| m.name.as_ref().map_or(0, |n| n.len() as u64))
            .chain(self.notes.iter().map(|n| n.len() as u64))
            .sum();
        let images = self.images.len() as u64 * (per_image + JSON_ENTRY_BYTES);
        entries * JSON_ENTRY_BYTES + 6 * names + images + JSON_ENTRY_BYTES
    }

    /// The glTF extensions [`Appearance::gltf_json`] uses.
    pub fn extensions_used(&self) -> Vec<&'static str> {
        let mut out = Vec::new();
        let refs = || self.materials.iter().flat_map(|m| m.texture_refs());
        if refs().any(|(_, r)| r.transform.is_some()) {
            out.push("KHR_texture_transform");
        }
        if self.materials.iter().any(|m| m.emissive_strength != 1.0) {
            out.push("KHR_materials_emissive_strength");
        }
        if self.materials.iter().any(|m| m.unlit) {
            out.push("KHR_materials_unlit");
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_full_material_fits_its_json_allowance() {
        // Every number at its longest JSON spelling (a negative subnormal f32 prints ~16
        // characters), every slot filled with a transform, an unnamed material.
        let long = -1.234_567_8e-38_f32;
        let r = Some(TexRef {
            texture: u32::MAX,
            tex_coord: u8::MAX,
            transform: Some(UvTransform {
                offset: [long; 2],
                rotation: long,
                scale: [long; 2],
            }),
        });
        let m = Material {
            name: None,
            base_color_factor: [long; 4],
            base_color_texture: r.clone(),
            metallic_factor: long,
            roughness_factor: long,
            metallic_roughness_texture: r.clone(),
            normal_texture: r.clone(),
            normal_scale: long,
            occlusion_texture: r.clone(),
            occlusion_strength: long,
            emissive_factor: [long; 3],
            emissive_strength: long,
            emissive_texture: r,
            alpha_mode: AlphaMode::Mask,
            alpha_cutoff: long,
            double_sided: true,
            unlit: true,
        };
        let text = m.gltf_json().to_string().len() as u64;
        // A Value holds more than its text (map nodes, strings' capacity): allowed four times.
        assert!(4 * text < JSON_ENTRY_BYTES, "{text} bytes of JSON");
        let s = Sampler::default().gltf_json().to_string().len() as u64;
        assert!(4 * s < JSON_ENTRY_BYTES, "{s}");
    }

    #[test]
    fn a_chain_counts_every_level_down_to_one_pixel() {
        // 4×2: 32 + 2×1: 8 + 1×1: 4.
        assert_eq!(Mips::chain_bytes(4, 2), 44);
        assert_eq!(Mips::chain_bytes(1, 1), 4);
        // A square power of two approaches 4/3 of the base level.
        let base = 1024u64 * 1024 * 4;
        let chain = Mips::chain_bytes(1024, 1024);
        assert!(chain > base * 4 / 3 - 8 && chain <= base * 4 / 3 + 4);
    }

    #[test]
    fn a_texture_transform_is_the_extensions_matrix() {
        // The extension's example: offset (0, 1), rotation π/2, scale (0.5, 0.5) "utilizes
        // only the lower left quadrant of the source image, rotated clockwise 90°": the unit
        // square's corners land on the corners of u ∈ [0, 0.5], v ∈ [0.5, 1] (v down), the
        // top left (0, 0) at the quadrant's bottom left (0, 1), the top right (1, 0) at its
        // top left (0, 0.5).
        let t = UvTransform {
            offset: [0.0, 1.0],
            rotation: std::f32::consts::FRAC_PI_2,
            scale: [0.5, 0.5],
        };
        for (uv, want) in [
            ((0.0, 0.0), (0.0, 1.0)),
            ((1.0, 0.0), (0.0, 0.5)),
            ((1.0, 1.0), (0.5, 0.5)),
            ((0.0, 1.0), (0.5, 1.0)),
        ] {
            let p = t.apply(Vec2::new(uv.0, uv.1));
            assert!(
                (p - Vec2::new(want.0, want.1)).length() < 1e-6,
                "{uv:?}: {p}"
            );
        }
        assert_eq!(
            UvTransform::default().apply(Vec2::new(0.3, 0.7)),
            Vec2::new(0.3, 0.7)
        );
    }

    #[test]
    fn a_rotation_turns_the_texture_as_the_khronos_sample_expects() {
        // TextureTransformTest's rotation quad (UVs 0..1, rotation 22.5°): the arrow's tip,
        // texel (0.69, 0.69) of Arrow.png, must be drawn towards the green marker at the
        // bottom (below the unrotated tip), not the red one to its right. The point of the
        // quad that shows texel t is M⁻¹ · t.
        let t = UvTransform {
            rotation: std::f32::consts::FRAC_PI_8,
            ..UvTransform::default()
        };
        let tip = Vec2::new(0.69, 0.69);
        // Invert the 2×2 (a rotation, offset 0): the transpose.
        let [r0, r1] = t.rows();
        let at = Vec2::new(r0[0] * tip.x + r1[0] * tip.y, r0[1] * tip.x + r1[1] * tip.y);
        assert!((t.apply(at) - tip).length() < 1e-6);
        assert!(
            at.y > tip.y && at.x < tip.x,
            "the tip moves down and left: {at}"
        );
        // The sample's "All" quad against three.js' Matrix3::setUvTransform(ox, oy, s, s,
        // r, 0, 0), row-major (three.js scales after rotating, the same with one scale).
        let t = UvTransform {
            offset: [-0.2, -0.1],
            rotation: 0.3,
            scale: [1.5, 1.5],
        };
        let (s, c) = 0.3f32.sin_cos();
        let three = [[1.5 * c, 1.5 * s, -0.2], [-1.5 * s, 1.5 * c, -0.1]];
        let rows = t.rows();
        for (got, want) in rows.iter().flatten().zip(three.iter().flatten()) {
            assert!((got - want).abs() < 1e-6, "{rows:?} vs {three:?}");
        }
    }

    #[test]
    fn the_gltf_json_round_trips_the_codes_and_omits_defaults() {
        let s = Sampler {
            mag: Filter::Nearest,
            min: Filter::Linear,
            mipmap: Some(Filter::Nearest),
            wrap_s: Wrap::ClampToEdge,
            wrap_t: Wrap::MirroredRepeat,
        };
        assert_eq!(
            s.gltf_json(),
            serde_json::json!({"magFilter": 9728, "minFilter": 9985, "wrapS": 33071, "wrapT": 33648})
        );
        let m = Material {
            alpha_mode: AlphaMode::Mask,
            unlit: true,
            base_color_texture: Some(TexRef {
                texture: 2,
                tex_coord: 1,
                transform: None,
            }),
            ..Material::default()
        };
        let j = m.gltf_json();
        assert_eq!(j["alphaMode"], "MASK");
        assert_eq!(j["alphaCutoff"], 0.5);
        assert_eq!(j["pbrMetallicRoughness"]["baseColorTexture"]["index"], 2);
        assert_eq!(j["pbrMetallicRoughness"]["baseColorTexture"]["texCoord"], 1);
        assert!(j["extensions"]["KHR_materials_unlit"].is_object());
        assert!(j.get("normalTexture").is_none());
    }

    #[test]
    fn validate_names_a_dangling_index() {
        let mut a = Appearance {
            materials: vec![Material {
                base_color_texture: Some(TexRef {
                    texture: 0,
                    tex_coord: 0,
                    transform: None,
                }),
                ..Material::default()
            }],
            textures: vec![Texture {
                sampler: None,
                image: Some(0),
            }],
            ..Appearance::default()
        };
        assert!(
            a.validate()
                .expect_err("dangling")
                .contains("texture 0: no image")
        );
        a.textures[0].image = None;
        assert_eq!(a.validate(), Ok(()));
        if let Some(r) = a.materials[0].base_color_texture.as_mut() {
            r.texture = 3;
        }
        assert!(a.validate().expect_err("dangling").contains("material 0"));
    }
}
