//! Which glTF extensions a file uses, and what the importer does with each.
//!
//! A rig needs geometry, morph targets, node transforms and weight animations; materials and
//! textures decide how it looks (`super::material`). So an extension is:
//! - *read* when it changes how that data is stored: `KHR_mesh_quantization` (integer
//!   attributes) and `EXT_meshopt_compression` / `KHR_meshopt_compression` (compressed buffer
//!   views, see [`super::meshopt`]); or when the renderer draws it: `KHR_texture_transform`,
//!   `EXT_texture_webp`, `KHR_materials_emissive_strength`, `KHR_materials_unlit`;
//! - *ignored* when it only touches textures and images and is not drawn
//!   (`KHR_texture_basisu`: KTX2 is not decoded, the fallback image is drawn) — even when the
//!   file lists it as required, since a viewer that cannot decode a KTX2 texture still has the
//!   mesh — or when the file does not require it (a material extension not drawn is also
//!   named in the import's notes, per material);
//! - *unsupported* otherwise, when required: `KHR_draco_mesh_compression` (with how to convert
//!   the file) and anything unknown whose meaning could change the geometry.
//!
//! Whether an unknown extension touches only textures is read from where the document uses it:
//! every `extensions` object that names it lies under `textures`, `images` or `samplers`, or in
//! a material's texture reference (`baseColorTexture`, `normalTexture`, ...).

use std::collections::{HashMap, HashSet};

use serde::Serialize;
use serde_json::Value;

use super::meshopt;

/// How the importer treats one extension of a file.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct ExtensionUse {
    /// Extension name.
    pub name: String,
    /// Whether the file lists it in `extensionsRequired`.
    pub required: bool,
    /// `read`, `ignored` or `unsupported`.
    pub handling: &'static str,
    /// Why, in a sentence.
    pub note: String,
}

/// The extension that marks Draco-compressed geometry.
pub const DRACO: &str = "KHR_draco_mesh_compression";

/// How to convert a file that needs an extension crowdmorph does not read (empty when there is
/// no known conversion). Shown in the import error.
pub fn conversion_hint(name: &str) -> &'static str {
    if name == DRACO {
        ": Draco-compressed geometry is not decoded here. Convert the file first, e.g. \
         `npx @gltf-transform/cli cp in.glb plain.glb` (writes it without Draco), optionally \
         then `gltfpack -i plain.glb -o small.glb -c` (EXT_meshopt_compression, which \
         crowdmorph reads)"
    } else {
        ""
    }
}

/// Where in the document an extension is used: in texture data, elsewhere, both or nowhere.
#[derive(Clone, Copy, Default)]
struct Uses {
    texture: bool,
    other: bool,
}

impl Uses {
    /// Whether the extension is used in texture data and nowhere else.
    fn texture_only(self) -> bool {
        self.texture && !self.other
    }
}

/// Where each extension of `names` is used in the document, read in one walk over it: every
/// `extensions` object met is looked up in an index of the names, so a file that lists many
/// extensions costs one walk, not one per extension. Bytes: the index and the result, a few
/// dozen per name, which the caller has already paid for as part of the parsed document.
fn uses_of(root: &Value, names: &[&str]) -> Vec<Uses> {
    // A name listed twice is looked up under its first place and copied to the others.
    let mut index: HashMap<&str, usize> = HashMap::with_capacity(names.len());
    for (i, &n) in names.iter().enumerate() {
        index.entry(n).or_insert(i);
    }
    let mut uses = vec![Uses::default(); names.len()];
    if let Some(map) = root.as_object() {
        for (k, v) in map {
            // Materials too: no material extension changes the geometry.
            let texture = matches!(k.as_str(), "textures" | "images" | "samplers" | "materials");
            scan(v, &index, texture, &mut uses);
        }
    }
    for (i, n) in names.iter().enumerate() {
        if let Some(&first) = index.get(n) {
            uses[i] = uses[first];
        }
    }
    uses
}

/// Records every `extensions.<name>` object under `value` whose name is in `index` (name → its
/// place in `uses`); `texture` says whether `value` lies in texture data (see the module
/// documentation).
fn scan(value: &Value, index: &HashMap<&str, usize>, texture: bool, uses: &mut [Uses]) {
    match value {
        Value::Object(map) => {
            if let Some(exts) = map.get("extensions").and_then(Value::as_object) {
                for name in exts.keys() {
                    if let Some(u) = index.get(name.as_str()).and_then(|&i| uses.get_mut(i)) {
                        if texture {
                            u.texture = true;
                        } else {
                            u.other = true;
                        }
                    }
                }
            }
            for (k, v) in map {
                let inner = texture || k.ends_with("Texture");
                scan(v, index, inner, uses);
            }
        }
        Value::Array(items) => {
            for v in items {
                scan(v, index, texture, uses);
            }
        }
        _ => {}
    }
}

/// Which of `names` the document uses in texture data and nowhere else, in one walk over it
/// (see [`uses_of`]).
pub(crate) fn texture_only(root: &Value, names: &[&str]) -> Vec<bool> {
    uses_of(root, names)
        .into_iter()
        .map(Uses::texture_only)
        .collect()
}

/// What the renderer does with an appearance extension it draws.
fn drawn(name: &str) -> Option<&'static str> {
    Some(match name {
        "KHR_texture_transform" => "texture coordinate offset, rotation and scale are applied",
        "EXT_texture_webp" => "WebP images are decoded and drawn",
        "KHR_materials_emissive_strength" => "emissive strength is drawn",
        "KHR_materials_unlit" => "unlit materials are drawn with their base colour",
        _ => return None,
    })
}

/// How one extension is handled (see the module documentation); `uses` says where the
/// document uses it.
fn classify(name: &str, required: bool, uses: Uses) -> ExtensionUse {
    let (handling, note) = if name == "KHR_mesh_quantization" {
        (
            "read",
            "integer and normalized-integer positions, normals, tangents and morph deltas are dequantized".to_string(),
        )
    } else if matches!(name, "VRMC_vrm" | "VRM") {
        (
            "read",
            "VRM expressions become the rig's `vrm` mapping (GET /v1/rigs/{id}/mappings/vrm); \
             humanoid, look-at, first-person and meta are not used"
                .to_string(),
        )
    } else if meshopt::EXTENSIONS.contains(&name) {
        (
            "read",
            "compressed buffer views are decompressed (attributes, indices; octahedral, quaternion and exponential filters)".to_string(),
        )
    } else if uses.texture_only() {
        match drawn(name) {
            Some(note) => ("read", note.to_string()),
            None if name == "KHR_texture_basisu" => (
                "ignored",
                "KTX2 images are not decoded; a texture's fallback image is drawn when it names one, else its material's factors".to_string(),
            ),
            None => (
                "ignored",
                "used only by materials, textures and images, and not drawn (the import's notes name each use)"
                    .to_string(),
            ),
        }
    } else if !required {
        (
            "ignored",
            "optional, and not needed to blend the rig".to_string(),
        )
    } else if name == DRACO {
        (
            "unsupported",
            conversion_hint(name).trim_start_matches(": ").to_string(),
        )
    } else {
        (
            "unsupported",
            "required, and crowdmorph cannot tell whether it changes the geometry".to_string(),
        )
    };
    ExtensionUse {
        name: name.to_string(),
        required,
        handling,
        note,
    }
}

/// Every extension a glTF document (its JSON) uses or requires, with how it is handled.
pub(crate) fn report(root: &Value) -> Vec<ExtensionUse> {
    let list = |key: &str| -> Vec<String> {
        root.get(key)
            .and_then(Value::as_array)
            .map(|a| {
                a.iter()
                    .filter_map(Value::as_str)
                    .map(str::to_string)
                    .collect()
            })
            .unwrap_or_default()
    };
    let required = list("extensionsRequired");
    let required_set: HashSet<&str> = required.iter().map(String::as_str).collect();
    let mut names = list("extensionsUsed");
    let mut listed: HashSet<String> = names.iter().cloned().collect();
    for r in &required {
        if listed.insert(r.clone()) {
            names.push(r.clone());
        }
    }
    let refs: Vec<&str> = names.iter().map(String::as_str).collect();
    let uses = uses_of(root, &refs);
    names
        .iter()
        .zip(uses)
        .map(|(n, u)| classify(n, required_set.contains(n.as_str()), u))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn texture_extensions_are_told_from_geometry_ones() {
        let doc = json!({
            "extensionsUsed": ["KHR_texture_basisu", "KHR_texture_transform", "EXT_weird", "KHR_draco_mesh_compression", "KHR_mesh_quantization"],
            "extensionsRequired": ["KHR_texture_basisu", "EXT_weird", "KHR_draco_mesh_compression", "KHR_mesh_quantization"],
            "textures": [{"extensions": {"KHR_texture_basisu": {"source": 0}}}],
            "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0,
                "extensions": {"KHR_texture_transform": {"scale": [2, 2]}}}}}],
            "meshes": [{"primitives": [{"attributes": {},
                "extensions": {"KHR_draco_mesh_compression": {}, "EXT_weird": {}}}]}],
            "nodes": [{"extensions": {"EXT_weird": {}}}],
        });
        let r = report(&doc);
        let get = |n: &str| r.iter().find(|e| e.name == n).expect("listed");
        assert_eq!(get("KHR_texture_basisu").handling, "ignored");
        assert!(get("KHR_texture_basisu").required);
        // Drawn since issue 46: read, as materials and textures are.
        assert_eq!(get("KHR_texture_transform").handling, "read");
        assert!(get("KHR_texture_basisu").note.contains("fallback image"));
        assert_eq!(get("EXT_weird").handling, "unsupported");
        assert_eq!(get("KHR_draco_mesh_compression").handling, "unsupported");
        assert!(
            get("KHR_draco_mesh_compression")
                .note
                .contains("gltf-transform")
        );
        assert_eq!(get("KHR_mesh_quantization").handling, "read");
        // Required but used nowhere: it may change how accessors read, so it is refused.
        assert_eq!(
            texture_only(&json!({"extensionsRequired": ["X"]}), &["X"]),
            [false]
        );
        // One walk answers for every name, each as if asked alone.
        let names = [
            "KHR_texture_basisu",
            "KHR_texture_transform",
            "EXT_weird",
            "KHR_draco_mesh_compression",
            "absent",
            "KHR_texture_basisu",
        ];
        assert_eq!(
            texture_only(&doc, &names),
            [true, true, false, false, false, true]
        );
    }
}
