//! A `.gltf` with external buffers and images (the shared Khronos samples) packed into one
//! self-contained GLB, as a user's exporter would write it for an upload: every buffer and
//! image becomes part of the BIN chunk, images as buffer views with their `mimeType`.

use std::path::Path;

use serde_json::{Value, json};

use super::builder::glb_from_parts;

/// The GLB of the `.gltf` at `path`, its external files read from beside it.
pub fn self_contained_glb(path: &Path) -> Vec<u8> {
    let dir = path.parent().expect("a file in a folder");
    let mut doc: Value =
        serde_json::from_slice(&std::fs::read(path).expect("the .gltf reads")).expect("JSON");
    let mut bin: Vec<u8> = Vec::new();
    let align = |bin: &mut Vec<u8>| bin.resize(bin.len().div_ceil(4) * 4, 0);
    // Each buffer's start in the BIN chunk.
    let mut starts = Vec::new();
    for b in doc["buffers"].as_array().cloned().unwrap_or_default() {
        align(&mut bin);
        starts.push(bin.len());
        let uri = b["uri"].as_str().expect("an external buffer");
        let bytes = std::fs::read(dir.join(uri)).expect("the buffer file reads");
        let len = b["byteLength"].as_u64().expect("byteLength") as usize;
        bin.extend_from_slice(&bytes[..len]);
    }
    for v in doc["bufferViews"].as_array_mut().into_iter().flatten() {
        let buffer = v["buffer"].as_u64().expect("buffer") as usize;
        let offset = v["byteOffset"].as_u64().unwrap_or(0) as usize;
        v["buffer"] = json!(0);
        v["byteOffset"] = json!(starts[buffer] + offset);
    }
    let mut views = doc["bufferViews"].as_array().cloned().unwrap_or_default();
    for image in doc["images"].as_array_mut().into_iter().flatten() {
        let Some(uri) = image["uri"].as_str().map(str::to_string) else {
            continue;
        };
        let bytes = std::fs::read(dir.join(&uri)).expect("the image file reads");
        align(&mut bin);
        views.push(json!({ "buffer": 0, "byteOffset": bin.len(), "byteLength": bytes.len() }));
        bin.extend_from_slice(&bytes);
        let mime = if uri.ends_with(".png") {
            "image/png"
        } else if uri.ends_with(".webp") {
            "image/webp"
        } else {
            "image/jpeg"
        };
        let obj = image.as_object_mut().expect("an image object");
        obj.remove("uri");
        obj.insert("bufferView".into(), json!(views.len() - 1));
        obj.insert("mimeType".into(), json!(mime));
    }
    doc["bufferViews"] = json!(views);
    align(&mut bin);
    doc["buffers"] = json!([{ "byteLength": bin.len() }]);
    glb_from_parts(&serde_json::to_vec(&doc).expect("JSON"), Some(&bin))
}
