//! A rig with a wrinkle map, as glTF: one quad with a base colour texture and, in the
//! material's `extras.crowdmorph.targetTextures`, a texture that fades in with its target
//! `brow`'s weight (and one for a target the rig does not have, which is never drawn). Shared
//! by the renderer's test (`tests/render_materials.rs`) and the browser viewer's
//! (`tests/server/viewer.rs`), so both draw the same layers.

use base64::Engine as _;
use serde_json::json;

use super::builder::Builder;

/// A PNG of `w × h` pixels, `rgb(x, y)` each.
pub fn png(w: u32, h: u32, rgb: impl Fn(u32, u32) -> [u8; 3]) -> Vec<u8> {
    let mut out = Vec::new();
    let mut e = png::Encoder::new(&mut out, w, h);
    e.set_color(png::ColorType::Rgb);
    e.set_depth(png::BitDepth::Eight);
    let rgb = &rgb;
    let data: Vec<u8> = (0..h)
        .flat_map(|y| (0..w).flat_map(move |x| rgb(x, y)))
        .collect();
    // A fixed image of a few pixels: a failure here is the test's own bug.
    e.write_header()
        .expect("header")
        .write_image_data(&data)
        .expect("pixels");
    out
}

/// The GLB: the quad `[-1, 1]²` at z = 0 facing +Z, texture coordinates (0, 0) at its top left
/// and (1, 1) at its bottom right, unlit (KHR_materials_unlit: the picture is the texture);
/// `brow` moves it `brow_delta` toward +Z. `base` and `wrinkle` are PNGs of the same size.
pub fn wrinkle_glb(base: &[u8], wrinkle: &[u8], brow_delta: f32) -> Vec<u8> {
    let mut b = Builder::new();
    let positions = [
        [-1.0, 1.0, 0.0],
        [1.0, 1.0, 0.0],
        [1.0, -1.0, 0.0],
        [-1.0, -1.0, 0.0],
    ];
    let mut p = b.primitive(
        &positions,
        Some(&[0, 3, 2, 0, 2, 1]),
        &[vec![[0.0, 0.0, brow_delta]; 4]],
    );
    p["attributes"]["TEXCOORD_0"] =
        json!(b.accessor_f32(&[0.0, 0.0, 1.0, 0.0, 1.0, 1.0, 0.0, 1.0], "VEC2"));
    p["material"] = json!(0);
    let mesh = b.mesh(vec![p], Some(&["brow"]));
    let node = b.node(Some(mesh));
    b.scene(&[node]);
    let uri = |png: &[u8]| {
        format!(
            "data:image/png;base64,{}",
            base64::engine::general_purpose::STANDARD.encode(png)
        )
    };
    let j = b.json_mut();
    j["images"] = json!([{ "uri": uri(base) }, { "uri": uri(wrinkle) }]);
    j["textures"] = json!([{ "source": 0 }, { "source": 1 }]);
    j["extensionsUsed"] = json!(["KHR_materials_unlit"]);
    j["materials"] = json!([{
        "pbrMetallicRoughness": { "baseColorTexture": { "index": 0 } },
        "extensions": { "KHR_materials_unlit": {} },
        "extras": { "crowdmorph": { "targetTextures": [
            { "target": "brow", "baseColorTexture": { "index": 1, "texCoord": 0 } },
            { "target": "noSuchTarget", "baseColorTexture": { "index": 1 } }
        ] } }
    }]);
    b.to_glb()
}
