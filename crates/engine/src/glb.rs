//! One self-contained GLB of a rig's mesh at one level, with its materials, textures and
//! images and no morph targets, skins or animation (`GET /v1/rigs/{id}/model.glb?lod=L`).
//!
//! It is what a three.js, Babylon, Unity or Godot client loads once: the primitives in the
//! rig's evaluation order, so the vertices of the mesh are those of every crowd frame of that
//! level (the client writes each frame's positions and normals into them). Rig space holds
//! the rest pose with node transforms applied, so the GLB has one node without a transform.

use serde_json::{Value, json};

use crowdmorph_core::rig::{Appearance, ImageMime, Rig};

/// Why a GLB could not be written.
#[derive(Debug, thiserror::Error)]
pub enum GlbError {
    /// The GLB would pass glTF's 4 GiB limit on a binary chunk.
    #[error("the GLB would hold {0} bytes of binary data, past glTF's 4 GiB")]
    TooLarge(u64),
    /// The JSON could not be written.
    #[error("writing the glTF JSON: {0}")]
    Json(String),
}

/// Bytes [`model_glb`] writes for `rig` at most (what a caller charges before making it):
/// every vertex attribute, the indices, the images and room for the JSON.
pub fn model_glb_bytes(rig: &Rig) -> u64 {
    let per_vertex: u64 = rig
        .primitives
        .iter()
        .map(|p| {
            let n = p.positions.len() as u64;
            let l = &p.look;
            n * (12
                + 12
                + p.tangents.as_ref().map_or(0, |_| 16)
                + l.uv0.as_ref().map_or(0, |_| 8)
                + l.uv1.as_ref().map_or(0, |_| 8)
                + l.colors.as_ref().map_or(0, |_| 16))
                + p.indices.len() as u64 * 4
                + 4 * 7
        })
        .sum();
    let images: u64 = rig.appearance.as_ref().map_or(0, |a| {
        a.images.iter().map(|i| i.bytes.len() as u64 + 3).sum()
    });
    per_vertex + images + 4096 + rig.primitives.len() as u64 * 1024
}

/// The BIN chunk being written and the JSON arrays that describe it.
struct Writer {
    bin: Vec<u8>,
    views: Vec<Value>,
    accessors: Vec<Value>,
}

impl Writer {
    /// Appends `bytes` as a buffer view (4-byte aligned), returning its index.
    fn view(&mut self, bytes: &[u8], target: Option<u32>) -> usize {
        self.bin.resize(self.bin.len().div_ceil(4) * 4, 0);
        let mut v = json!({ "buffer": 0, "byteOffset": self.bin.len(), "byteLength": bytes.len() });
        if let Some(t) = target {
            v["target"] = t.into();
        }
        self.bin.extend_from_slice(bytes);
        self.views.push(v);
        self.views.len() - 1
    }

    /// Appends float vectors as an accessor of `kind` (`VEC2`/`VEC3`/`VEC4`).
    fn floats(&mut self, data: &[f32], comps: usize, kind: &str, bounds: bool) -> usize {
        let view = self.view(bytemuck::cast_slice(data), Some(34962));
        let mut a = json!({
            "bufferView": view, "componentType": 5126, "count": data.len() / comps, "type": kind,
        });
        if bounds {
            let mut min = vec![f32::INFINITY; comps];
            let mut max = vec![f32::NEG_INFINITY; comps];
            for v in data.chunks_exact(comps) {
                for c in 0..comps {
                    min[c] = min[c].min(v[c]);
                    max[c] = max[c].max(v[c]);
                }
            }
            a["min"] = min.into();
            a["max"] = max.into();
        }
        self.accessors.push(a);
        self.accessors.len() - 1
    }
}

/// `rig` (one level's rig, e.g. from [`crowdmorph_core::rig::mesh_level_rigs`]) as a GLB.
pub fn model_glb(rig: &Rig) -> Result<Vec<u8>, GlbError> {
    let mut w = Writer {
        bin: Vec::with_capacity(model_glb_bytes(rig) as usize),
        views: Vec::new(),
        accessors: Vec::new(),
    };
    let mut primitives = Vec::with_capacity(rig.primitives.len());
    for p in rig.primitives.iter() {
        let flat3 =
            |v: &[glam::Vec3]| -> Vec<f32> { v.iter().flat_map(|v| v.to_array()).collect() };
        let mut attributes = serde_json::Map::new();
        attributes.insert(
            "POSITION".into(),
            w.floats(&flat3(&p.positions), 3, "VEC3", true).into(),
        );
        attributes.insert(
            "NORMAL".into(),
            w.floats(&flat3(&p.normals), 3, "VEC3", false).into(),
        );
        if let Some(t) = &p.tangents {
            let d: Vec<f32> = t.iter().flat_map(|v| v.to_array()).collect();
            attributes.insert("TANGENT".into(), w.floats(&d, 4, "VEC4", false).into());
        }
        for (name, uv) in [("TEXCOORD_0", &p.look.uv0), ("TEXCOORD_1", &p.look.uv1)] {
            if let Some(uv) = uv {
                let d: Vec<f32> = uv.iter().flat_map(|v| v.to_array()).collect();
                attributes.insert(name.into(), w.floats(&d, 2, "VEC2", false).into());
            }
        }
        if let Some(c) = &p.look.colors {
            let d: Vec<f32> = c.iter().flat_map(|v| v.to_array()).collect();
            attributes.insert("COLOR_0".into(), w.floats(&d, 4, "VEC4", false).into());
        }
        let view = w.view(bytemuck::cast_slice(&p.indices), Some(34963));
        w.accessors.push(json!({
            "bufferView": view, "componentType": 5125, "count": p.indices.len(), "type": "SCALAR",
        }));
        let mut prim = json!({
            "attributes": attributes, "indices": w.accessors.len() - 1, "mode": 4,
        });
        if let Some(m) = p.look.material {
            prim["material"] = m.into();
        }
        primitives.push(prim);
    }
    let mut doc = json!({
        "asset": { "version": "2.0", "generator": "crowdmorph model.glb" },
        "scene": 0,
        "scenes": [{ "nodes": [0] }],
        "nodes": [{ "mesh": 0, "name": rig.name }],
        "meshes": [{ "name": rig.name, "primitives": primitives }],
    });
    if let Some(a) = rig.appearance.as_deref() {
        appearance(&mut doc, &mut w, a);
    }
    w.bin.resize(w.bin.len().div_ceil(4) * 4, 0);
    if w.bin.len() as u64 > u64::from(u32::MAX) - 64 {
        return Err(GlbError::TooLarge(w.bin.len() as u64));
    }
    doc["accessors"] = w.accessors.into();
    doc["bufferViews"] = w.views.into();
    doc["buffers"] = json!([{ "byteLength": w.bin.len() }]);
    let json = serde_json::to_vec(&doc).map_err(|e| GlbError::Json(e.to_string()))?;
    Ok(container(&json, &w.bin))
}

/// Adds the appearance's tables to `doc`, its images as buffer views of `w`. WebP images go
/// through `EXT_texture_webp` (required: no fallback image is written).
fn appearance(doc: &mut Value, w: &mut Writer, a: &Appearance) {
    let mut tables = a.gltf_json(|_, image| {
        let view = w.view(&image.bytes, None);
        json!({ "bufferView": view, "mimeType": image.mime.as_str() })
    });
    let mut used: Vec<&str> = a.extensions_used();
    let mut required = Vec::new();
    for (t, tex) in a.textures.iter().enumerate() {
        let webp = tex
            .image
            .and_then(|i| a.images.get(i as usize))
            .is_some_and(|i| i.mime == ImageMime::Webp);
        if webp && let Some(obj) = tables["textures"][t].as_object_mut() {
            if let Some(source) = obj.remove("source") {
                obj.insert(
                    "extensions".into(),
                    json!({ "EXT_texture_webp": { "source": source } }),
                );
            }
            if !used.contains(&"EXT_texture_webp") {
                used.push("EXT_texture_webp");
                required.push("EXT_texture_webp");
            }
        }
    }
    for key in ["materials", "textures", "samplers", "images"] {
        let empty = tables[key].as_array().is_none_or(Vec::is_empty);
        if !empty {
            doc[key] = tables[key].take();
        }
    }
    if !used.is_empty() {
        doc["extensionsUsed"] = used.into();
    }
    if !required.is_empty() {
        doc["extensionsRequired"] = required.into();
    }
}

/// The GLB container: header, JSON chunk (space padded), BIN chunk (zero padded).
fn container(json: &[u8], bin: &[u8]) -> Vec<u8> {
    let pad = |n: usize| (4 - n % 4) % 4;
    let json_len = json.len() + pad(json.len());
    let bin_len = bin.len() + pad(bin.len());
    let total = 12 + 8 + json_len + 8 + bin_len;
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&(total as u32).to_le_bytes());
    out.extend_from_slice(&(json_len as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(json);
    out.resize(out.len() + pad(json.len()), b' ');
    out.extend_from_slice(&(bin_len as u32).to_le_bytes());
    out.extend_from_slice(b"BIN\0");
    out.extend_from_slice(bin);
    out.resize(out.len() + pad(bin.len()), 0);
    out
}
