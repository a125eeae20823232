//! glTF materials, textures, samplers and images: what a rig looks like ([`Appearance`]).
//!
//! Read from the document's JSON with serde structs of our own rather than the `gltf` crate's
//! typed API: that API unwraps a texture without a `source` (which `EXT_texture_webp` and
//! `KHR_texture_basisu` allow) and an image view without a `mimeType`, and hides extensions
//! behind cargo features. Every index is checked here, so a dangling one is a 400 naming it.
//!
//! Two phases, so the budget is reserved before anything is decoded:
//! 1. [`Pending::read`] (from `document_shape`): parses the tables, fetches each image a
//!    material reaches (a buffer view, a data URI, or a file beside a `.gltf` on the command
//!    line) and reads its header. [`Pending::kept_bytes`] and [`Pending::peak_decode`] go into
//!    the import's reservation: a tiny PNG that declares 50,000 × 50,000 is refused there, a
//!    413 naming `--max-upload-memory`, before any pixel is allocated.
//! 2. [`Pending::decode`] (from `build_rig`): decodes each image (charged as it allocates),
//!    downscales it to `--max-texture-size`, and builds the [`Appearance`].
//!
//! What a material asks for that is not drawn (clearcoat, sheen, transmission, VRM MToon,
//! KTX2 without a fallback image...) becomes a sentence in [`Appearance::notes`], which the
//! upload's answer and `inspect` list.

use std::collections::HashMap;
use std::sync::Arc;

use base64::Engine as _;
use serde::Deserialize;
use serde_json::{Map, Value};

use super::ImportError;
use super::accessor::Source;
use super::image::{self, ImageError, ImageHeader};
use crowdmorph_core::budget::Budget;
use crowdmorph_core::rig::{
    AlphaMode, Appearance, Filter, ImageData, ImageMime, MAX_LAYERS, Material, Sampler,
    TargetTexture, TexRef, Texture, UvTransform, Wrap,
};

/// Material extensions the renderer draws.
const DRAWN_MATERIAL_EXTENSIONS: &[&str] =
    &["KHR_materials_emissive_strength", "KHR_materials_unlit"];

/// The part of a glTF document this module reads; serde skips the rest.
#[derive(Deserialize, Default)]
#[serde(default)]
struct Doc {
    materials: Vec<JMaterial>,
    textures: Vec<JTexture>,
    images: Vec<JImage>,
    samplers: Vec<JSampler>,
}

#[derive(Deserialize, Default)]
#[serde(default, rename_all = "camelCase")]
struct JMaterial {
    name: Option<String>,
    pbr_metallic_roughness: Option<JPbr>,
    normal_texture: Option<JInfo>,
    occlusion_texture: Option<JInfo>,
    emissive_texture: Option<JInfo>,
    emissive_factor: Option<[f32; 3]>,
    alpha_mode: Option<String>,
    alpha_cutoff: Option<f32>,
    double_sided: bool,
    extensions: Map<String, Value>,
    extras: Option<Value>,
}

/// `extras.crowdmorph` of a material: our convention for textures that fade in with a morph
/// target's weight (README "Appearance"). Extras are free-form, so a shape that does not
/// parse is a note, never a refusal.
#[derive(Deserialize, Default)]
#[serde(default, rename_all = "camelCase")]
struct JCrowdmorphExtras {
    target_textures: Vec<JTargetTexture>,
}

/// One entry of `targetTextures`: a morph target's name and the base colour at its weight 1.
#[derive(Deserialize)]
#[serde(rename_all = "camelCase")]
struct JTargetTexture {
    target: String,
    base_color_texture: JInfo,
}

#[derive(Deserialize, Default)]
#[serde(default, rename_all = "camelCase")]
struct JPbr {
    base_color_factor: Option<[f32; 4]>,
    base_color_texture: Option<JInfo>,
    metallic_factor: Option<f32>,
    roughness_factor: Option<f32>,
    metallic_roughness_texture: Option<JInfo>,
}

/// glTF `textureInfo` (and its normal and occlusion variants).
#[derive(Deserialize, Default)]
#[serde(default, rename_all = "camelCase")]
struct JInfo {
    index: Option<u32>,
    tex_coord: u32,
    scale: Option<f32>,
    strength: Option<f32>,
    extensions: Map<String, Value>,
}

#[derive(Deserialize, Default)]
#[serde(default)]
struct JTexture {
    sampler: Option<u32>,
    source: Option<u32>,
    extensions: Map<String, Value>,
}

#[derive(Deserialize, Default)]
#[serde(default, rename_all = "camelCase")]
struct JImage {
    uri: Option<String>,
    mime_type: Option<String>,
    buffer_view: Option<u32>,
}

#[derive(Deserialize, Default)]
#[serde(default, rename_all = "camelCase")]
struct JSampler {
    mag_filter: Option<u32>,
    min_filter: Option<u32>,
    wrap_s: Option<u32>,
    wrap_t: Option<u32>,
}

/// `KHR_texture_transform` as the file writes it.
#[derive(Deserialize, Default)]
#[serde(default, rename_all = "camelCase")]
struct JTransform {
    offset: Option<[f32; 2]>,
    rotation: Option<f32>,
    scale: Option<[f32; 2]>,
    tex_coord: Option<u32>,
}

/// One image a material reaches, fetched and sized, not decoded.
struct FetchedImage {
    /// Index in the file's `images`.
    file_index: usize,
    bytes: Arc<[u8]>,
    declared: Option<ImageMime>,
    header: ImageHeader,
}

/// The appearance of a document between its two phases (see the module documentation).
pub(crate) struct Pending {
    materials: Vec<Material>,
    /// The materials' `extras.crowdmorph.targetTextures`.
    target_textures: Vec<TargetTexture>,
    textures: Vec<Texture>,
    samplers: Vec<Sampler>,
    /// Fetched images, in the order [`Texture::image`] indexes them.
    images: Vec<FetchedImage>,
    notes: Vec<String>,
    max_texture_size: u32,
    /// Bytes charged for the fetched images (released as they become the rig's).
    fetched_bytes: u64,
}

impl Pending {
    /// Phase 1: the tables, and every image a material reaches fetched (charged) and sized.
    pub(crate) fn read(
        json: &[u8],
        source: &Source<'_>,
        doc: &gltf::Document,
        base_dir: Option<&std::path::Path>,
        max_texture_size: u32,
    ) -> Result<Option<Pending>, ImportError> {
        let budget = source.budget();
        // The tables are small beside the JSON the import already charged; a second parse
        // holds at most as much again.
        budget.charge(json.len() as u64, || "reading the materials".into())?;
        let parsed: Result<Doc, _> = serde_json::from_slice(json);
        budget.release(json.len() as u64);
        let d = parsed.map_err(|e| ImportError::Json(format!("materials: {e}")))?;
        if d.materials.is_empty() {
            return Ok(None);
        }
        let mut notes = Vec::new();
        let samplers: Vec<Sampler> = d.samplers.iter().map(sampler).collect();
        // Which file image each texture draws, and the images that needs, in first-use order.
        let mut wanted: Vec<usize> = Vec::new();
        let mut slot_of: HashMap<usize, u32> = HashMap::new();
        let mut textures = Vec::with_capacity(d.textures.len());
        for (t, tex) in d.textures.iter().enumerate() {
            if let Some(s) = tex.sampler
                && s as usize >= samplers.len()
            {
                return Err(ImportError::Invalid(format!(
                    "textures[{t}] uses sampler {s} of {}",
                    samplers.len()
                )));
            }
            let image = texture_source(t, tex, d.images.len(), &mut notes)?;
            let image = image.map(|i| {
                *slot_of.entry(i).or_insert_with(|| {
                    wanted.push(i);
                    (wanted.len() - 1) as u32
                })
            });
            textures.push(Texture {
                sampler: tex.sampler,
                image,
            });
        }
        let mut materials = Vec::with_capacity(d.materials.len());
        let mut target_textures = Vec::new();
        for (m, jm) in d.materials.iter().enumerate() {
            let (mat, targets) = material(m, jm, textures.len(), &mut notes)?;
            materials.push(mat);
            target_textures.extend(targets.into_iter().map(|(target, texture)| TargetTexture {
                material: m as u32,
                target,
                texture,
            }));
        }
        // Fetch only what a material reaches.
        let reached: std::collections::HashSet<u32> = materials
            .iter()
            .flat_map(|m| m.texture_refs().map(|(_, r)| r.texture))
            .chain(target_textures.iter().map(|t| t.texture.texture))
            .collect();
        let mut images = Vec::new();
        let mut fetched_bytes = 0;
        let mut remap: HashMap<u32, u32> = HashMap::new();
        for (slot, &file_index) in wanted.iter().enumerate() {
            let used = textures
                .iter()
                .enumerate()
                .any(|(t, tex)| tex.image == Some(slot as u32) && reached.contains(&(t as u32)));
            if !used {
                continue;
            }
            let j = &d.images[file_index];
            let Some(bytes) = fetch(file_index, j, source, doc, base_dir, &mut notes)? else {
                continue;
            };
            fetched_bytes += bytes.len() as u64;
            let header = image::sniff(&bytes).map_err(|problem| ImportError::Image {
                index: file_index,
                problem,
            })?;
            remap.insert(slot as u32, images.len() as u32);
            images.push(FetchedImage {
                file_index,
                declared: j.mime_type.as_deref().and_then(ImageMime::parse),
                bytes,
                header,
            });
        }
        for t in &mut textures {
            t.image = t.image.and_then(|s| remap.get(&s).copied());
        }
        Ok(Some(Pending {
            materials,
            target_textures,
            textures,
            samplers,
            images,
            notes,
            max_texture_size,
            fetched_bytes,
        }))
    }

    /// Bytes the rig keeps of its appearance once decoded: each image's encoded bytes (at
    /// most the fetched ones, or a downscaled re-encoding) and its final mip chain.
    pub(crate) fn kept_bytes(&self) -> u64 {
        self.images
            .iter()
            .map(|i| {
                let (w, h) = fitted(i.header.width, i.header.height, self.max_texture_size);
                i.bytes.len() as u64 + crowdmorph_core::rig::Mips::chain_bytes(w, h)
            })
            .sum()
    }

    /// Most bytes decoding one image holds at once beyond what it keeps.
    pub(crate) fn peak_decode(&self) -> u64 {
        self.images
            .iter()
            .map(|i| {
                // The WebP decoder copies the compressed stream besides (see `image::decode`).
                let copy = if i.header.mime == ImageMime::Webp {
                    2 * i.bytes.len() as u64
                } else {
                    0
                };
                image::decode_cost(&i.header, self.max_texture_size) + copy
            })
            .max()
            .unwrap_or(0)
    }

    /// Phase 2: decodes every image (charged as it allocates) and builds the appearance.
    pub(crate) fn decode(self, budget: &Budget) -> Result<Appearance, ImportError> {
        let mut notes = self.notes;
        let mut images = Vec::with_capacity(self.images.len());
        for f in self.images {
            let (data, more): (ImageData, Vec<String>) = image::decode(
                f.file_index,
                f.bytes,
                Some(f.declared.unwrap_or(f.header.mime)),
                self.max_texture_size,
                budget,
            )
            .map_err(|e| match e {
                ImageError::Invalid { index, problem } => ImportError::Image { index, problem },
                ImageError::Budget(b) => ImportError::Budget(b),
            })?;
            notes.extend(more);
            images.push(data);
        }
        // The fetched bytes are now the images' own (or were dropped for a downscaled copy,
        // which decode charged): they stay charged as the rig's.
        let _ = self.fetched_bytes;
        Ok(Appearance {
            materials: self.materials,
            textures: self.textures,
            samplers: self.samplers,
            images,
            notes,
            target_textures: self.target_textures,
            clip_textures: Vec::new(),
        })
    }
}

/// The size an image is stored at: halved until both sides fit `max` (as the decoder does).
fn fitted(mut w: u32, mut h: u32, max: u32) -> (u32, u32) {
    let max = max.max(1);
    while w > max || h > max {
        w = (w / 2).max(1);
        h = (h / 2).max(1);
    }
    (w, h)
}

/// Which file image texture `t` draws: a WebP source when it names one, else its plain
/// source; a KTX2 source is never decoded (its fallback `source` is drawn, or nothing).
fn texture_source(
    t: usize,
    tex: &JTexture,
    images: usize,
    notes: &mut Vec<String>,
) -> Result<Option<usize>, ImportError> {
    let ext_source = |name: &str| -> Option<Option<u64>> {
        tex.extensions
            .get(name)
            .map(|v| v.get("source").and_then(Value::as_u64))
    };
    let check = |what: &str, i: u64| -> Result<usize, ImportError> {
        if i as usize >= images {
            return Err(ImportError::Invalid(format!(
                "textures[{t}]{what} refers to image {i} of {images}"
            )));
        }
        Ok(i as usize)
    };
    if let Some(Some(webp)) = ext_source("EXT_texture_webp") {
        return Ok(Some(check(".extensions.EXT_texture_webp.source", webp)?));
    }
    let fallback = match tex.source {
        Some(s) => Some(check(".source", u64::from(s))?),
        None => None,
    };
    if ext_source("KHR_texture_basisu").is_some() {
        notes.push(match fallback {
            Some(i) => format!(
                "texture {t}: KTX2 (KHR_texture_basisu) is not decoded; its fallback image {i} is drawn"
            ),
            None => format!(
                "texture {t}: KTX2 (KHR_texture_basisu) is not decoded and it names no fallback image; drawn with its material's factors"
            ),
        });
    }
    for name in tex.extensions.keys() {
        if name != "EXT_texture_webp" && name != "KHR_texture_basisu" {
            notes.push(format!("texture {t}: {name} not read"));
        }
    }
    Ok(fallback)
}

/// glTF's sampler codes to ours (unknown codes: glTF's defaults).
fn sampler(s: &JSampler) -> Sampler {
    let wrap = |w: Option<u32>| match w {
        Some(33071) => Wrap::ClampToEdge,
        Some(33648) => Wrap::MirroredRepeat,
        _ => Wrap::Repeat,
    };
    let d = Sampler::default();
    let (min, mipmap) = match s.min_filter {
        Some(9728) => (Filter::Nearest, None),
        Some(9729) => (Filter::Linear, None),
        Some(9984) => (Filter::Nearest, Some(Filter::Nearest)),
        Some(9985) => (Filter::Linear, Some(Filter::Nearest)),
        Some(9986) => (Filter::Nearest, Some(Filter::Linear)),
        Some(9987) => (Filter::Linear, Some(Filter::Linear)),
        _ => (d.min, d.mipmap),
    };
    Sampler {
        mag: match s.mag_filter {
            Some(9728) => Filter::Nearest,
            _ => Filter::Linear,
        },
        min,
        mipmap,
        wrap_s: wrap(s.wrap_s),
        wrap_t: wrap(s.wrap_t),
    }
}

/// Material `m` of the file, every texture index checked against `textures`.
/// Material `m` of the file, and its target textures (target name, texture reference).
fn material(
    m: usize,
    j: &JMaterial,
    textures: usize,
    notes: &mut Vec<String>,
) -> Result<(Material, Vec<(String, TexRef)>), ImportError> {
    let label = match &j.name {
        Some(n) => format!("material {m} {}", crowdmorph_core::rig::quoted_name(n)),
        None => format!("material {m}"),
    };
    let mut tex = |what: &str, info: &Option<JInfo>| -> Result<Option<TexRef>, ImportError> {
        let Some(info) = info else { return Ok(None) };
        let Some(index) = info.index else {
            return Err(ImportError::Invalid(format!(
                "materials[{m}].{what} has no index"
            )));
        };
        if index as usize >= textures {
            return Err(ImportError::Invalid(format!(
                "materials[{m}].{what} refers to texture {index} of {textures}"
            )));
        }
        let t: Option<JTransform> = match info.extensions.get("KHR_texture_transform") {
            Some(v) => Some(serde_json::from_value(v.clone()).map_err(|e| {
                ImportError::Invalid(format!(
                    "materials[{m}].{what}.extensions.KHR_texture_transform: {e}"
                ))
            })?),
            None => None,
        };
        let tex_coord = t
            .as_ref()
            .and_then(|t| t.tex_coord)
            .unwrap_or(info.tex_coord);
        if tex_coord > 1 {
            notes.push(format!(
                "{label}: {what} reads texture coordinate set {tex_coord}, which is not kept; drawn without it"
            ));
            return Ok(None);
        }
        Ok(Some(TexRef {
            texture: index,
            tex_coord: tex_coord as u8,
            transform: t.map(|t| UvTransform {
                offset: t.offset.unwrap_or([0.0; 2]),
                rotation: t.rotation.unwrap_or(0.0),
                scale: t.scale.unwrap_or([1.0; 2]),
            }),
        }))
    };
    let pbr = j.pbr_metallic_roughness.as_ref();
    let d = Material::default();
    let alpha_mode = match j.alpha_mode.as_deref() {
        None | Some("OPAQUE") => AlphaMode::Opaque,
        Some("MASK") => AlphaMode::Mask,
        Some("BLEND") => AlphaMode::Blend,
        Some(other) => {
            return Err(ImportError::Invalid(format!(
                "materials[{m}].alphaMode {other:?} is not OPAQUE, MASK or BLEND"
            )));
        }
    };
    let ext_f32 = |name: &str, key: &str| -> Option<f32> {
        j.extensions
            .get(name)
            .and_then(|v| v.get(key))
            .and_then(Value::as_f64)
            .map(|v| v as f32)
    };
    let out = Material {
        name: j.name.clone(),
        base_color_factor: pbr
            .and_then(|p| p.base_color_factor)
            .unwrap_or(d.base_color_factor),
        base_color_texture: tex(
            "pbrMetallicRoughness.baseColorTexture",
            &pbr.and_then(|p| p.base_color_texture.as_ref().map(clone_info)),
        )?,
        metallic_factor: pbr
            .and_then(|p| p.metallic_factor)
            .unwrap_or(d.metallic_factor),
        roughness_factor: pbr
            .and_then(|p| p.roughness_factor)
            .unwrap_or(d.roughness_factor),
        metallic_roughness_texture: tex(
            "pbrMetallicRoughness.metallicRoughnessTexture",
            &pbr.and_then(|p| p.metallic_roughness_texture.as_ref().map(clone_info)),
        )?,
        normal_texture: tex("normalTexture", &j.normal_texture)?,
        normal_scale: j
            .normal_texture
            .as_ref()
            .and_then(|n| n.scale)
            .unwrap_or(1.0),
        occlusion_texture: tex("occlusionTexture", &j.occlusion_texture)?,
        occlusion_strength: j
            .occlusion_texture
            .as_ref()
            .and_then(|n| n.strength)
            .unwrap_or(1.0),
        emissive_factor: j.emissive_factor.unwrap_or(d.emissive_factor),
        emissive_strength: ext_f32("KHR_materials_emissive_strength", "emissiveStrength")
            .unwrap_or(1.0),
        emissive_texture: tex("emissiveTexture", &j.emissive_texture)?,
        alpha_mode,
        alpha_cutoff: j.alpha_cutoff.unwrap_or(d.alpha_cutoff),
        double_sided: j.double_sided,
        unlit: j.extensions.contains_key("KHR_materials_unlit"),
    };
    // Parsed while `tex` (which holds `notes`) is alive: its notes are added after.
    let mut later = Vec::new();
    let mut targets = Vec::new();
    if let Some(v) = j.extras.as_ref().and_then(|e| e.get("crowdmorph")) {
        match serde_json::from_value::<JCrowdmorphExtras>(v.clone()) {
            Ok(x) => {
                for (k, t) in x.target_textures.iter().enumerate() {
                    if targets.len() == MAX_LAYERS {
                        later.push(format!(
                            "{label}: target textures past the first {MAX_LAYERS} not drawn"
                        ));
                        break;
                    }
                    let what = format!("extras.crowdmorph.targetTextures[{k}].baseColorTexture");
                    if let Some(r) = tex(&what, &Some(clone_info(&t.base_color_texture)))? {
                        targets.push((t.target.clone(), r));
                    }
                }
            }
            Err(e) => later.push(format!(
                "{label}: extras.crowdmorph not read ({e}); drawn without target textures"
            )),
        }
    }
    let finite = out
        .base_color_factor
        .iter()
        .chain(&out.emissive_factor)
        .chain(&[
            out.metallic_factor,
            out.roughness_factor,
            out.normal_scale,
            out.occlusion_strength,
            out.emissive_strength,
            out.alpha_cutoff,
        ])
        .all(|v| v.is_finite());
    if !finite {
        return Err(ImportError::Invalid(format!(
            "materials[{m}] has a factor out of range"
        )));
    }
    for name in j.extensions.keys() {
        if !DRAWN_MATERIAL_EXTENSIONS.contains(&name.as_str()) {
            notes.push(format!(
                "{label}: {name} not drawn; drawn as its glTF metallic-roughness material"
            ));
        }
    }
    notes.extend(later);
    Ok((out, targets))
}

/// A copy of a texture info (the closure above takes `&Option<JInfo>`).
fn clone_info(i: &JInfo) -> JInfo {
    JInfo {
        index: i.index,
        tex_coord: i.tex_coord,
        scale: i.scale,
        strength: i.strength,
        extensions: i.extensions.clone(),
    }
}

/// The encoded bytes of file image `i` (charged), or `None` with a note when the upload
/// cannot reach them (a file beside a `.gltf` sent to the server).
fn fetch(
    i: usize,
    j: &JImage,
    source: &Source<'_>,
    doc: &gltf::Document,
    base_dir: Option<&std::path::Path>,
    notes: &mut Vec<String>,
) -> Result<Option<Arc<[u8]>>, ImportError> {
    let budget = source.budget();
    let bad = |problem: String| ImportError::Image { index: i, problem };
    if let Some(v) = j.buffer_view {
        let view = doc
            .views()
            .nth(v as usize)
            .ok_or_else(|| bad(format!("refers to buffer view {v}, which does not exist")))?;
        let bytes = source.image_view(i, &view)?;
        budget.charge(bytes.len() as u64, || format!("image {i}"))?;
        return Ok(Some(Arc::from(bytes)));
    }
    let Some(uri) = &j.uri else {
        return Err(bad("has neither a uri nor a bufferView".into()));
    };
    if let Some(rest) = uri.strip_prefix("data:") {
        let (meta, data) = rest
            .split_once(',')
            .ok_or_else(|| bad("malformed data URI".into()))?;
        if !meta.ends_with(";base64") {
            return Err(bad("data URI is not base64".into()));
        }
        budget.charge(data.len() as u64 * 3 / 4 + 3, || format!("image {i}"))?;
        let bytes = base64::engine::general_purpose::STANDARD
            .decode(data.trim())
            .map_err(|e| bad(format!("bad base64 in data URI: {e}")))?;
        return Ok(Some(Arc::from(bytes)));
    }
    let Some(base) = base_dir else {
        notes.push(format!(
            "image {i} is the external file {uri:?}, which an upload cannot reach; send a GLB or a glTF with data URIs to draw it"
        ));
        return Ok(None);
    };
    let path = super::uri::resolve_relative(base, uri).map_err(bad)?;
    let len = std::fs::metadata(&path)
        .map_err(|e| bad(format!("cannot read {}: {e}", path.display())))?
        .len();
    budget.charge(len, || format!("image file {}", path.display()))?;
    let bytes =
        std::fs::read(&path).map_err(|e| bad(format!("cannot read {}: {e}", path.display())))?;
    Ok(Some(Arc::from(bytes)))
}

/// Gives every image of `rig`'s appearance its decoded pixels (a rig read back from a store
/// keeps only the encoded bytes), each charged to `budget` before it is decoded. Its mesh
/// levels and clones share the result (one `Arc`).
pub fn decode_stored_images(
    rig: &mut crowdmorph_core::rig::Rig,
    budget: &Budget,
) -> Result<(), ImportError> {
    let Some(a) = &rig.appearance else {
        return Ok(());
    };
    if a.images.iter().all(|i| i.pixels.is_some()) {
        return Ok(());
    }
    let mut out = Appearance::clone(a);
    for (i, im) in out.images.iter_mut().enumerate() {
        if im.pixels.is_none() {
            im.pixels = Some(image::decode_pixels(i, im, budget).map_err(|e| match e {
                ImageError::Invalid { index, problem } => ImportError::Image { index, problem },
                ImageError::Budget(b) => ImportError::Budget(b),
            })?);
        }
    }
    rig.appearance = Some(Arc::new(out));
    Ok(())
}
