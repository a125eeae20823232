//! A VRM avatar's expressions as the rig's `vrm` mapping (`crowdmorph_core::rig::mapping`).
//!
//! VRM 1.0 (`extensions.VRMC_vrm.expressions`, vrm-specification
//! `specification/VRMC_vrm-1.0/expressions.md`): `preset` and `custom` objects of expressions
//! by name; each expression's `morphTargetBinds` `{node, index, weight}` (weight in [0, 1])
//! name morph target `index` of the mesh of node `node`, `isBinary` makes it binary, and
//! `overrideBlink` / `overrideLookAt` / `overrideMouth` (`none`, `block`, `blend`) override the
//! procedural groups. VRM 0.x (`extensions.VRM.blendShapeMaster.blendShapeGroups`): groups
//! with `presetName` (renamed to VRM 1.0's names: `joy` → `happy`, `a` → `aa`, `blink_l` →
//! `blinkLeft`, ...; `unknown` keeps the group's `name`), `binds` `{mesh, index, weight}` with
//! weights in [0, 100], and `isBinary`; 0.x has no overrides.
//!
//! A morph target is named as the importer names it (`mesh.extras.targetNames`, else
//! `target_<i>`, `super::scene`), so an entry's target is that name and reaches every rig
//! channel of it. Material color and texture transform binds are not read.

use serde_json::Value;

use crowdmorph_core::rig::{
    MAX_MAP_ENTRIES, NamedEntry, NamedMapping, NamedSource, Override, Procedural,
};

/// What makes a VRM block unusable: named, so that the upload's answer can say why.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum VrmError {
    /// More binds or expressions than a mapping may have.
    #[error("the VRM expressions have {0} binds or expressions; at most {MAX_MAP_ENTRIES}")]
    TooLarge(usize),
    /// A bind that names no mesh or morph target of the file.
    #[error("VRM expression {expression:?}: {why}")]
    Bind {
        /// The expression.
        expression: String,
        /// What is wrong.
        why: String,
    },
}

/// The glTF JSON of a `.glb` (its first chunk) or a `.gltf` file, unparsed; `None` when the
/// bytes are neither.
pub fn gltf_json(bytes: &[u8]) -> Option<&[u8]> {
    if bytes.len() >= 20 && &bytes[0..4] == b"glTF" {
        let len = u32::from_le_bytes(bytes[12..16].try_into().ok()?) as usize;
        if &bytes[16..20] != b"JSON" {
            return None;
        }
        return bytes.get(20..20usize.checked_add(len)?);
    }
    let start = bytes.iter().position(|b| !b.is_ascii_whitespace())?;
    (bytes[start] == b'{').then_some(bytes)
}

/// The `vrm` mapping of a glTF document, when it has VRM expressions (1.0 first, else 0.x)
/// that bind morph targets.
pub fn vrm_mapping(root: &Value) -> Result<Option<NamedMapping>, VrmError> {
    let ext = root.get("extensions");
    let m = if let Some(e) = ext
        .and_then(|e| e.get("VRMC_vrm"))
        .and_then(|v| v.get("expressions"))
    {
        vrm1(root, e)?
    } else if let Some(groups) = ext
        .and_then(|e| e.get("VRM"))
        .and_then(|v| v.get("blendShapeMaster"))
        .and_then(|v| v.get("blendShapeGroups"))
        .and_then(Value::as_array)
    {
        vrm0(root, groups)?
    } else {
        return Ok(None);
    };
    let most = m.entries.len().max(m.sources.len());
    if most > MAX_MAP_ENTRIES {
        return Err(VrmError::TooLarge(most));
    }
    Ok((!m.sources.is_empty()).then_some(m))
}

/// Morph target `index`'s name in mesh `mesh`, as the importer names it.
fn target_name(root: &Value, mesh: u64, index: u64) -> Result<String, String> {
    let m = root
        .get("meshes")
        .and_then(|m| m.get(mesh as usize))
        .ok_or_else(|| format!("mesh {mesh} does not exist"))?;
    let count = m
        .get("primitives")
        .and_then(|p| p.get(0))
        .and_then(|p| p.get("targets"))
        .and_then(Value::as_array)
        .map_or(0, Vec::len) as u64;
    if index >= count {
        return Err(format!(
            "mesh {mesh} has {count} morph targets, not {}",
            index + 1
        ));
    }
    let named = m
        .get("extras")
        .and_then(|e| e.get("targetNames"))
        .and_then(Value::as_array)
        .filter(|n| n.len() as u64 == count)
        .and_then(|n| n.get(index as usize))
        .and_then(Value::as_str);
    Ok(named.map_or_else(|| format!("target_{index}"), str::to_string))
}

fn number(v: &Value, key: &str) -> Option<f64> {
    v.get(key).and_then(Value::as_f64)
}

fn override_of(v: &Value, key: &str) -> Override {
    match v.get(key).and_then(Value::as_str) {
        Some("block") => Override::Block,
        Some("blend") => Override::Blend,
        _ => Override::None,
    }
}

fn vrm1(root: &Value, expressions: &Value) -> Result<NamedMapping, VrmError> {
    let mut out = NamedMapping::default();
    for kind in ["preset", "custom"] {
        let Some(map) = expressions.get(kind).and_then(Value::as_object) else {
            continue;
        };
        for (name, e) in map {
            let bad = |why: String| VrmError::Bind {
                expression: name.clone(),
                why,
            };
            let binds = e.get("morphTargetBinds").and_then(Value::as_array);
            for b in binds.into_iter().flatten() {
                let node = number(b, "node").ok_or_else(|| bad("a bind without a node".into()))?;
                let index =
                    number(b, "index").ok_or_else(|| bad("a bind without an index".into()))?;
                let mesh = root
                    .get("nodes")
                    .and_then(|n| n.get(node as usize))
                    .and_then(|n| number(n, "mesh"))
                    .ok_or_else(|| bad(format!("node {node} has no mesh")))?;
                let target = target_name(root, mesh as u64, index as u64).map_err(bad)?;
                out.entries.push(NamedEntry {
                    source: name.clone(),
                    target,
                    gain: number(b, "weight").unwrap_or(1.0) as f32,
                    offset: 0.0,
                    clamp: None,
                });
                if out.entries.len() > MAX_MAP_ENTRIES {
                    return Err(VrmError::TooLarge(out.entries.len()));
                }
            }
            // VRM 1.0 treats an override of an expression's own group as none.
            let own = Procedural::of(name);
            let mut overrides = [
                override_of(e, "overrideBlink"),
                override_of(e, "overrideLookAt"),
                override_of(e, "overrideMouth"),
            ];
            if let Some(g) = own {
                overrides[g as usize] = Override::None;
            }
            out.sources.push(NamedSource {
                name: name.clone(),
                binary: e.get("isBinary").and_then(Value::as_bool).unwrap_or(false),
                overrides,
            });
            if out.sources.len() > MAX_MAP_ENTRIES {
                return Err(VrmError::TooLarge(out.sources.len()));
            }
        }
    }
    Ok(out)
}

/// VRM 0.x's preset names as VRM 1.0 names them (`unknown`: none).
fn preset_1_0(preset: &str) -> Option<&'static str> {
    Some(match preset {
        "neutral" => "neutral",
        "a" => "aa",
        "i" => "ih",
        "u" => "ou",
        "e" => "ee",
        "o" => "oh",
        "blink" => "blink",
        "blink_l" => "blinkLeft",
        "blink_r" => "blinkRight",
        "joy" => "happy",
        "angry" => "angry",
        "sorrow" => "sad",
        "fun" => "relaxed",
        "lookup" => "lookUp",
        "lookdown" => "lookDown",
        "lookleft" => "lookLeft",
        "lookright" => "lookRight",
        _ => return None,
    })
}

fn vrm0(root: &Value, groups: &[Value]) -> Result<NamedMapping, VrmError> {
    let mut out = NamedMapping::default();
    for (i, g) in groups.iter().enumerate() {
        let preset = g
            .get("presetName")
            .and_then(Value::as_str)
            .unwrap_or("unknown");
        let name = match preset_1_0(&preset.to_ascii_lowercase()) {
            Some(n) => n.to_string(),
            None => g
                .get("name")
                .and_then(Value::as_str)
                .map_or_else(|| format!("group_{i}"), str::to_string),
        };
        let bad = |why: String| VrmError::Bind {
            expression: name.clone(),
            why,
        };
        for b in g
            .get("binds")
            .and_then(Value::as_array)
            .into_iter()
            .flatten()
        {
            let mesh = number(b, "mesh").ok_or_else(|| bad("a bind without a mesh".into()))?;
            let index = number(b, "index").ok_or_else(|| bad("a bind without an index".into()))?;
            let target = target_name(root, mesh as u64, index as u64).map_err(bad)?;
            out.entries.push(NamedEntry {
                source: name.clone(),
                target,
                // 0.x weights are percentages.
                gain: (number(b, "weight").unwrap_or(100.0) / 100.0) as f32,
                offset: 0.0,
                clamp: None,
            });
            if out.entries.len() > MAX_MAP_ENTRIES {
                return Err(VrmError::TooLarge(out.entries.len()));
            }
        }
        if out.sources.iter().any(|s| s.name == name) {
            continue;
        }
        out.sources.push(NamedSource {
            name,
            binary: g.get("isBinary").and_then(Value::as_bool).unwrap_or(false),
            overrides: [Override::None; 3],
        });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn doc() -> Value {
        serde_json::json!({
            "nodes": [{"mesh": 0}],
            "meshes": [{
                "primitives": [{"targets": [{}, {}, {}]}],
                "extras": {"targetNames": ["Fcl_ALL_Joy", "Fcl_EYE_Close", "Fcl_MTH_A"]}
            }],
        })
    }

    #[test]
    fn vrm1_expressions() {
        let mut d = doc();
        d["extensions"] = serde_json::json!({"VRMC_vrm": {"expressions": {
            "preset": {
                "happy": {"isBinary": true, "overrideBlink": "block",
                          "morphTargetBinds": [{"node": 0, "index": 0, "weight": 0.8}]},
                "blink": {"overrideBlink": "blend",
                          "morphTargetBinds": [{"node": 0, "index": 1, "weight": 1.0}]}
            },
            "custom": {"wow": {"morphTargetBinds": [{"node": 0, "index": 2, "weight": 0.5}]}}
        }}});
        let m = vrm_mapping(&d).expect("ok").expect("a mapping");
        let happy = m.sources.iter().find(|s| s.name == "happy").expect("happy");
        assert!(happy.binary && happy.overrides[0] == Override::Block);
        // A blink's own blink override is none.
        let blink = m.sources.iter().find(|s| s.name == "blink").expect("blink");
        assert_eq!(blink.overrides, [Override::None; 3]);
        let e = m.entries.iter().find(|e| e.source == "wow").expect("wow");
        assert_eq!((e.target.as_str(), e.gain), ("Fcl_MTH_A", 0.5));
        d["extensions"]["VRMC_vrm"]["expressions"]["custom"]["wow"]["morphTargetBinds"][0]["index"] =
            9.into();
        assert!(matches!(vrm_mapping(&d), Err(VrmError::Bind { .. })));
    }

    #[test]
    fn vrm0_groups() {
        let mut d = doc();
        d["extensions"] = serde_json::json!({"VRM": {"blendShapeMaster": {"blendShapeGroups": [
            {"name": "Joy", "presetName": "joy", "binds": [{"mesh": 0, "index": 0, "weight": 100}]},
            {"name": "A", "presetName": "a", "isBinary": true,
             "binds": [{"mesh": 0, "index": 2, "weight": 50}]},
            {"name": "Extra", "presetName": "unknown", "binds": []}
        ]}}});
        let m = vrm_mapping(&d).expect("ok").expect("a mapping");
        let names: Vec<&str> = m.sources.iter().map(|s| s.name.as_str()).collect();
        assert_eq!(names, ["happy", "aa", "Extra"]);
        assert!(m.sources[1].binary);
        assert_eq!(m.entries[1].gain, 0.5);
        assert!(vrm_mapping(&doc()).expect("ok").is_none());
    }

    #[test]
    fn glb_json_chunk() {
        let json = br#"{"asset":{"version":"2.0"}}"#;
        let mut glb = b"glTF".to_vec();
        glb.extend(2u32.to_le_bytes());
        glb.extend(((20 + json.len()) as u32).to_le_bytes());
        glb.extend((json.len() as u32).to_le_bytes());
        glb.extend(b"JSON");
        glb.extend(json);
        assert_eq!(gltf_json(&glb), Some(&json[..]));
        assert_eq!(gltf_json(b"  {\"a\":1}"), Some(&b"  {\"a\":1}"[..]));
        assert_eq!(gltf_json(b"nope"), None);
    }
}
