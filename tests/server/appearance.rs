//! What a rig looks like, end to end: the shared textured rigs (MorphStressTest: two PNGs on two
//! texture coordinate sets; MorphPrimitivesTest: a JPEG) uploaded as a user's exporter writes
//! them (images in the GLB's buffer views, or as data URIs), then the mesh's texture
//! coordinates and material indices, `GET /materials` and `GET /textures/{i}` checked against
//! the files themselves, before and after a restart.

use std::path::Path;

use bytes::Bytes;
use crowdmorph::server::ServerConfig;
use crowdmorph_client::{Encoding, Method};
use crowdmorph_proto::MeshResponse;

use super::{TestServer, stored_config, temp_dir, upload_bytes};
use crate::util::RefDoc;

/// The shared textured rigs: file, and whether to send it as a GLB (images in buffer views)
/// rather than a `.gltf` with data URIs.
fn textured() -> [(std::path::PathBuf, bool); 2] {
    let k = crate::util::data_dir().join("khronos");
    [
        (k.join("MorphStressTest/glTF/MorphStressTest.gltf"), false),
        (
            k.join("MorphPrimitivesTest/glTF/MorphPrimitivesTest.gltf"),
            true,
        ),
    ]
}

fn bytes_of(path: &Path, glb: bool) -> Bytes {
    if glb {
        Bytes::from(crate::util::pack::self_contained_glb(path))
    } else {
        upload_bytes(path)
    }
}

/// One primitive as the file has it: `TEXCOORD_0`, `TEXCOORD_1`, `COLOR_0` (as read, VEC3 or
/// VEC4) with its component count, and the material.
struct FilePrimitive {
    uv0: Option<Vec<f64>>,
    uv1: Option<Vec<f64>>,
    color: Option<(Vec<f64>, usize)>,
    material: Option<u64>,
}

/// Each primitive of the file, in the rig's order.
fn file_primitives(doc: &RefDoc) -> Vec<FilePrimitive> {
    let uv0 = doc.scene_attribute("TEXCOORD_0");
    let uv1 = doc.scene_attribute("TEXCOORD_1");
    let color = doc.scene_attribute("COLOR_0");
    uv0.into_iter()
        .zip(uv1)
        .zip(color)
        .map(|(((uv0, material), (uv1, _)), (color, _))| FilePrimitive {
            uv0: uv0.map(|a| a.0),
            uv1: uv1.map(|a| a.0),
            color,
            material,
        })
        .collect()
}

fn f32s(b: &[u8]) -> Vec<f32> {
    b.chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

/// A per-vertex column of the mesh (`width` floats a vertex) against the file's, per
/// primitive: the file's values where it has them, else `missing`; an empty column when no
/// primitive has any.
fn check_column(
    mesh: &MeshResponse,
    blob: &[u8],
    width: usize,
    file: &[Option<Vec<f64>>],
    missing: &[f32],
    ctx: &str,
) {
    let got = f32s(blob);
    if file.iter().all(Option::is_none) {
        assert!(got.is_empty(), "{ctx}: a column no primitive has is empty");
        return;
    }
    assert_eq!(
        got.len(),
        mesh.vertices as usize * width,
        "{ctx}: per vertex"
    );
    for (p, want) in mesh.primitives.iter().zip(file) {
        let got =
            &got[p.first_vertex as usize * width..(p.first_vertex + p.vertices) as usize * width];
        match want {
            Some(w) => {
                assert_eq!(got.len(), w.len(), "{ctx}: {}", p.name);
                for (g, w) in got.iter().zip(w) {
                    assert!(
                        (f64::from(*g) - w).abs() <= 1e-6,
                        "{ctx}: {} {g} vs {w}",
                        p.name
                    );
                }
            }
            None => assert!(
                got.chunks_exact(width).all(|v| v == missing),
                "{ctx}: {} without",
                p.name
            ),
        }
    }
}

/// The mesh's texture coordinates (both sets), colours and materials equal the file's.
fn check_mesh(mesh: &MeshResponse, doc: &RefDoc, ctx: &str) {
    let want = file_primitives(doc);
    assert_eq!(mesh.primitives.len(), want.len(), "{ctx}: primitives");
    for (p, w) in mesh.primitives.iter().zip(&want) {
        assert_eq!(
            p.material.map(u64::from),
            w.material,
            "{ctx}: {} material",
            p.name
        );
    }
    let uv0: Vec<_> = want.iter().map(|w| w.uv0.clone()).collect();
    check_column(mesh, &mesh.uvs.0, 2, &uv0, &[0.0; 2], &format!("{ctx} uvs"));
    let uv1: Vec<_> = want.iter().map(|w| w.uv1.clone()).collect();
    assert!(
        !ctx.starts_with("morphstresstest") || uv1.iter().any(Option::is_some),
        "{ctx}: MorphStressTest has set 1 (its occlusion map reads it)"
    );
    check_column(
        mesh,
        &mesh.uvs1.0,
        2,
        &uv1,
        &[0.0; 2],
        &format!("{ctx} uvs1"),
    );
    // RGB colours get alpha 1.
    let colors: Vec<_> = want
        .iter()
        .map(|w| {
            w.color.as_ref().map(|(v, n)| match n {
                3 => v
                    .chunks_exact(3)
                    .flat_map(|c| [c[0], c[1], c[2], 1.0])
                    .collect(),
                _ => v.clone(),
            })
        })
        .collect();
    check_column(
        mesh,
        &mesh.colors.0,
        4,
        &colors,
        &[1.0; 4],
        &format!("{ctx} colors"),
    );
}

/// `/materials` and every `/textures/{i}` against the file: material names and factors, and
/// each image's bytes exactly as the file has them (no image is over the default 4096).
async fn check_appearance(server: &TestServer, id: &str, path: &Path, doc: &RefDoc) {
    let client = &server.client;
    let m = client.materials(id).await.expect("materials");
    let file_materials = doc.json["materials"].as_array().expect("materials");
    let got = m["materials"].as_array().expect("an array");
    assert_eq!(got.len(), file_materials.len(), "{id}: materials");
    for (g, f) in got.iter().zip(file_materials) {
        assert_eq!(g["name"], f["name"], "{id}");
        assert_eq!(
            g["doubleSided"].as_bool(),
            Some(f["doubleSided"].as_bool().unwrap_or(false))
        );
        let pbr = &f["pbrMetallicRoughness"];
        for k in ["metallicFactor", "roughnessFactor"] {
            if let Some(v) = pbr[k].as_f64() {
                let got = g["pbrMetallicRoughness"][k].as_f64().expect(k);
                assert!((got - v).abs() < 1e-6, "{id}: {k} {got} vs {v}");
            }
        }
        assert_eq!(
            g["pbrMetallicRoughness"]["baseColorTexture"]["index"],
            pbr["baseColorTexture"]["index"],
            "{id}"
        );
    }
    let images = m["images"].as_array().expect("images");
    let file_images = doc.json["images"].as_array().expect("images");
    assert_eq!(
        images.len(),
        file_images.len(),
        "{id}: every image is drawn"
    );
    let textures = m["textures"].as_array().expect("textures");
    for (t, ft) in textures
        .iter()
        .zip(doc.json["textures"].as_array().expect("textures"))
    {
        // Images are kept in first-use order; here that is the file's.
        assert_eq!(t["source"], ft["source"], "{id}");
    }
    for (i, (im, fi)) in images.iter().zip(file_images).enumerate() {
        let file = std::fs::read(
            path.parent()
                .expect("dir")
                .join(fi["uri"].as_str().expect("an external image")),
        )
        .expect("the image file");
        let uri = im["uri"].as_str().expect("uri");
        let (bytes, ct) = client.texture_at(uri).await.expect("texture");
        assert_eq!(ct, fi["mimeType"].as_str().expect("mime"), "{id} image {i}");
        assert_eq!(&bytes[..], &file[..], "{id} image {i}: the file's bytes");
        let (w, h) = header_size(&file);
        assert_eq!(
            (im["width"].as_u64(), im["height"].as_u64()),
            (Some(w), Some(h))
        );
        // Cache headers: immutable by its versioned URI, revalidated without it.
        let etag = format!("\"{}\"", im["etag"].as_str().expect("etag"));
        let reply = client
            .send(Method::GET, uri, None, None, Bytes::new())
            .await
            .expect("send");
        let header = |r: &crowdmorph_client::Reply, h: &str| {
            r.headers
                .get(h)
                .and_then(|v| v.to_str().ok())
                .unwrap_or_default()
                .to_string()
        };
        assert_eq!(header(&reply, "etag"), etag);
        assert!(header(&reply, "cache-control").contains("immutable"));
        let plain = format!("/v1/rigs/{id}/textures/{i}");
        let reply = client
            .send_with(Method::GET, &plain, &[], Bytes::new())
            .await
            .expect("send");
        assert_eq!(reply.status, 200);
        assert_eq!(header(&reply, "cache-control"), "no-cache");
        let reply = client
            .send_with(
                Method::GET,
                &plain,
                &[("if-none-match", etag.as_str())],
                Bytes::new(),
            )
            .await
            .expect("send");
        assert_eq!(reply.status, 304, "{id} image {i}: not modified");
        assert!(reply.body.is_empty());
    }
    let missing = client
        .texture(id, images.len())
        .await
        .expect_err("one past the last image");
    assert!(missing.to_string().contains("unknown_texture"), "{missing}");
}

/// `model.glb` read back by the importer (which runs the `gltf` crate's validation): the
/// mesh endpoint's vertices, triangles and texture coordinates, one material per file
/// material, and the images' bytes.
async fn check_model(server: &TestServer, id: &str) {
    let client = &server.client;
    let glb = client.model_glb(id, 0).await.expect("model.glb");
    let rig = crowdmorph::import::gltf::rig_from_slice(
        &glb,
        &crowdmorph::import::ImportOptions::default(),
    )
    .expect("the GLB imports");
    assert!(
        rig.targets.is_empty() && rig.clips.is_empty(),
        "no morph targets or clips"
    );
    let mesh = client.mesh(id, Encoding::Bincode).await.expect("mesh");
    assert_eq!(rig.vertex_count(), mesh.vertices as usize, "{id}: vertices");
    let positions: Vec<f32> = rig
        .primitives
        .iter()
        .flat_map(|p| p.positions.iter().flat_map(|v| v.to_array()))
        .collect();
    assert_eq!(
        positions,
        f32s(&mesh.positions.0),
        "{id}: the mesh's vertex order"
    );
    let uvs: Vec<f32> = rig
        .primitives
        .iter()
        .flat_map(|p| p.look.uv0.iter().flatten().flat_map(|v| v.to_array()))
        .collect();
    assert_eq!(uvs, f32s(&mesh.uvs.0), "{id}: texture coordinates");
    let indices: Vec<u32> = rig
        .primitives
        .iter()
        .zip(&mesh.primitives)
        .flat_map(|(p, m)| p.indices.iter().map(move |i| i + m.first_vertex))
        .collect();
    let want: Vec<u32> = mesh
        .indices
        .0
        .chunks_exact(4)
        .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    assert_eq!(indices, want, "{id}: triangles");
    let a = rig.appearance.as_deref().expect("materials in the GLB");
    let m = client.materials(id).await.expect("materials");
    assert_eq!(
        a.materials.len(),
        m["materials"].as_array().map_or(0, Vec::len)
    );
    for (i, im) in a.images.iter().enumerate() {
        let (bytes, _) = client.texture(id, i).await.expect("texture");
        assert_eq!(&im.bytes[..], &bytes[..], "{id}: image {i} in the GLB");
    }
    for (p, mp) in rig.primitives.iter().zip(&mesh.primitives) {
        assert_eq!(
            p.look.material, mp.material,
            "{id}: material of {}",
            mp.name
        );
    }
}

/// An image's size from its header, read here without the server's code: PNG's IHDR, or the
/// first JPEG start-of-frame marker.
fn header_size(b: &[u8]) -> (u64, u64) {
    if b.starts_with(b"\x89PNG") {
        let be = |at: usize| u32::from_be_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]]);
        return (u64::from(be(16)), u64::from(be(20)));
    }
    let mut at = 2;
    while at + 9 < b.len() {
        let (marker, len) = (
            b[at + 1],
            u16::from_be_bytes([b[at + 2], b[at + 3]]) as usize,
        );
        if (0xC0..=0xCF).contains(&marker) && ![0xC4, 0xC8, 0xCC].contains(&marker) {
            let h = u16::from_be_bytes([b[at + 5], b[at + 6]]);
            let w = u16::from_be_bytes([b[at + 7], b[at + 8]]);
            return (u64::from(w), u64::from(h));
        }
        at += 2 + len;
    }
    panic!("no image size found")
}

#[tokio::test]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
async fn textured_rigs_give_clients_their_uvs_materials_and_images_across_a_restart() {
    let dir = temp_dir("appearance");
    let server = TestServer::start(stored_config(&dir)).await;
    let mut ids = Vec::new();
    for (path, glb) in textured() {
        let id = path
            .file_stem()
            .expect("stem")
            .to_string_lossy()
            .to_lowercase();
        let info = server
            .client
            .upload_rig(&id, bytes_of(&path, glb))
            .await
            .expect("upload");
        assert_eq!(info.id, id);
        let doc = RefDoc::load(&path);
        for enc in [Encoding::Bincode, Encoding::Json] {
            let mesh = server.client.mesh(&id, enc).await.expect("mesh");
            check_mesh(&mesh, &doc, &format!("{id} {enc:?}"));
        }
        check_appearance(&server, &id, &path, &doc).await;
        check_model(&server, &id).await;
        ids.push((id, path, doc));
    }
    server.stop().await;

    // The data dir keeps all of it.
    let server = TestServer::start(stored_config(&dir)).await;
    for (id, path, doc) in &ids {
        let mesh = server
            .client
            .mesh(id, Encoding::Bincode)
            .await
            .expect("mesh");
        check_mesh(&mesh, doc, &format!("{id} after a restart"));
        check_appearance(&server, id, path, doc).await;
    }
    server.stop().await;
    let _ = std::fs::remove_dir_all(&dir);
}

#[tokio::test]
async fn a_rig_without_materials_has_empty_appearance() {
    let server = TestServer::start(ServerConfig::default()).await;
    let m = server
        .client
        .materials("default-head")
        .await
        .expect("materials");
    for k in ["materials", "textures", "samplers", "images"] {
        assert_eq!(m[k], serde_json::json!([]), "{k}");
    }
    let mesh = server
        .client
        .mesh("default-head", Encoding::Bincode)
        .await
        .expect("mesh");
    assert!(mesh.uvs.0.is_empty());
    assert!(mesh.primitives.iter().all(|p| p.material.is_none()));
    server.stop().await;
}

/// A PNG of `w × h` RGBA pixels, each `(x, y, 0, 255)`.
fn png_of(w: u32, h: u32) -> Vec<u8> {
    let mut out = Vec::new();
    let mut e = png::Encoder::new(&mut out, w, h);
    e.set_color(png::ColorType::Rgba);
    e.set_depth(png::BitDepth::Eight);
    let mut writer = e.write_header().expect("header");
    let data: Vec<u8> = (0..h)
        .flat_map(|y| (0..w).flat_map(move |x| [x as u8, y as u8, 0, 255]))
        .collect();
    writer.write_image_data(&data).expect("pixels");
    drop(writer);
    out
}

/// A PNG that is only a signature, a header declaring `w × h` and an end: what a bomb sends.
fn png_header_only(w: u32, h: u32) -> Vec<u8> {
    let chunk = |kind: &[u8], data: &[u8]| {
        let mut c = (data.len() as u32).to_be_bytes().to_vec();
        c.extend_from_slice(kind);
        c.extend_from_slice(data);
        let crc = crc32fast::hash(&c[4..]);
        c.extend_from_slice(&crc.to_be_bytes());
        c
    };
    let mut ihdr = w.to_be_bytes().to_vec();
    ihdr.extend_from_slice(&h.to_be_bytes());
    ihdr.extend_from_slice(&[8, 6, 0, 0, 0]);
    let mut out = b"\x89PNG\r\n\x1a\n".to_vec();
    out.extend(chunk(b"IHDR", &ihdr));
    out.extend(chunk(b"IEND", &[]));
    out
}

/// The triangle rig with one material whose base colour texture is `image` (a data URI).
fn triangle_with_image(image: &[u8], mime: &str) -> Bytes {
    use base64::Engine as _;
    let mut b = crate::util::builder::triangle_rig();
    let j = b.json_mut();
    let data = base64::engine::general_purpose::STANDARD.encode(image);
    j["images"] = serde_json::json!([{ "uri": format!("data:{mime};base64,{data}") }]);
    j["textures"] = serde_json::json!([{ "source": 0 }]);
    j["materials"] =
        serde_json::json!([{ "pbrMetallicRoughness": { "baseColorTexture": { "index": 0 } } }]);
    j["meshes"][0]["primitives"][0]["material"] = serde_json::json!(0);
    Bytes::from(b.to_glb())
}

#[tokio::test]
async fn hostile_images_are_named_4xx_and_large_ones_are_downscaled() {
    let server = TestServer::start(ServerConfig {
        max_texture_size: 8,
        ..ServerConfig::default()
    })
    .await;
    let client = &server.client;
    let refused = |e: crowdmorph_client::ClientError| match e {
        crowdmorph_client::ClientError::Api {
            status,
            code,
            message,
            ..
        } => (status, code, message),
        other => panic!("expected an API error, got {other}"),
    };
    // A 69-byte PNG declaring 50,000 × 50,000: refused on its header, before decoding.
    let bomb = png_header_only(50_000, 50_000);
    assert!(bomb.len() < 100);
    let (status, code, message) = refused(
        client
            .upload_rig("bomb", triangle_with_image(&bomb, "image/png"))
            .await
            .expect_err("a bomb"),
    );
    assert_eq!((status, code.as_str()), (413, "rig_too_large"), "{message}");
    assert!(message.contains("--max-upload-memory"), "{message}");
    // Corrupt, truncated, empty, unknown: a 400 naming the image.
    let good = png_of(32, 16);
    let mut corrupt = good.clone();
    let n = corrupt.len();
    corrupt[n / 2] ^= 0xff;
    for (what, bytes) in [
        ("corrupt", corrupt),
        ("truncated", good[..good.len() / 2].to_vec()),
        ("unknown", b"GIF89a not really".to_vec()),
        ("zero", png_header_only(0, 0)),
    ] {
        let (status, code, message) = refused(
            client
                .upload_rig("bad", triangle_with_image(&bytes, "image/png"))
                .await
                .expect_err(what),
        );
        assert_eq!(
            (status, code.as_str()),
            (400, "invalid_image"),
            "{what}: {message}"
        );
        assert!(message.contains("image 0"), "{what}: {message}");
        // Nothing half-stored.
        assert!(
            client.rig("bad").await.is_err(),
            "{what}: no rig left behind"
        );
    }
    // 32 × 16 over --max-texture-size 8: halved twice, said so, served as the smaller PNG.
    let info = client
        .upload_rig("big", triangle_with_image(&good, "image/png"))
        .await
        .expect("a large image is downscaled");
    let m = client.materials(&info.id).await.expect("materials");
    let im = &m["images"][0];
    assert_eq!(
        (im["width"].as_u64(), im["height"].as_u64()),
        (Some(8), Some(4))
    );
    assert_eq!(im["downscaledFrom"], serde_json::json!([32, 16]));
    assert!(
        m["notes"].as_array().expect("notes").iter().any(|n| n
            .as_str()
            .is_some_and(|n| n.contains("32 × 16 → 8 × 4") && n.contains("--max-texture-size"))),
        "{m}"
    );
    let (bytes, ct) = client.texture(&info.id, 0).await.expect("texture");
    assert_eq!(ct, "image/png");
    let decoder = png::Decoder::new(std::io::Cursor::new(&bytes[..]));
    let reader = decoder.read_info().expect("a PNG");
    assert_eq!((reader.info().width, reader.info().height), (8, 4));
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
async fn model_glb_and_materials_are_charged_to_the_queue_memory() {
    // What the route charges for MorphStressTest's model (its arrays and both PNGs, twice:
    // the JSON values and the bytes), from the rig the importer makes of the same file.
    let path = textured()[0].0.clone();
    let rig = crowdmorph::import::load_path(&path, &crowdmorph::import::ImportOptions::default())
        .expect("import");
    let charge = 2 * crowdmorph::engine::glb::model_glb_bytes(&rig);
    let upload = bytes_of(&path, true);

    // A queue memory smaller than one model: a 413 naming the flag, never a 5xx; the small
    // `/materials` still answers.
    let small = (charge / 2) as usize;
    let server = TestServer::start(ServerConfig {
        queue_memory_bytes: small,
        ..ServerConfig::default()
    })
    .await;
    server
        .client
        .upload_rig("stress", upload.clone())
        .await
        .expect("upload");
    let reply = server
        .client
        .send(
            Method::GET,
            "/v1/rigs/stress/model.glb",
            None,
            None,
            Bytes::new(),
        )
        .await
        .expect("reply");
    assert_eq!(reply.status, 413, "{:?}", reply.error());
    let err = reply.error().expect("a JSON error");
    assert_eq!(err.error.code, "queue_memory_exceeded", "{err:?}");
    assert!(
        err.error.message.contains("--queue-memory-bytes"),
        "{err:?}"
    );
    server.client.materials("stress").await.expect("materials");
    assert_eq!(server.state.queue_memory.used(), 0);
    server.stop().await;

    // Room for two models at once, sixteen asked for together: each is the same 200, or a
    // 503 `queue_full` to retry; and once all are answered nothing stays charged.
    let server = TestServer::start(ServerConfig {
        queue_memory_bytes: (charge * 5 / 2) as usize,
        ..ServerConfig::default()
    })
    .await;
    server
        .client
        .upload_rig("stress", upload)
        .await
        .expect("upload");
    let want = server.client.model_glb("stress", 0).await.expect("model");
    let replies = futures_util::future::join_all((0..16).map(|_| {
        server.client.send(
            Method::GET,
            "/v1/rigs/stress/model.glb",
            None,
            None,
            Bytes::new(),
        )
    }))
    .await;
    let (mut ok, mut busy) = (0, 0);
    for r in replies {
        let r = r.expect("reply");
        match r.status {
            200 => {
                assert_eq!(r.body, want, "every model is the same bytes");
                ok += 1;
            }
            503 => {
                assert_eq!(r.error().expect("JSON").error.code, "queue_full");
                busy += 1;
            }
            s => panic!("status {s}: {:?}", r.error()),
        }
    }
    println!("16 model.glb at once under room for 2: {ok} answered, {busy} told to retry");
    assert!(ok >= 2, "{ok} answered");
    assert_eq!(server.state.queue_memory.used(), 0);
    server.stop().await;
}

#[tokio::test]
async fn vertex_colours_reach_the_mesh_in_linear_rgba() {
    // COLOR_0 as the exporters write it: normalized u8 RGBA (a VRoid-style vertex tint) and
    // float RGB (alpha 1 is implied). The mesh gives both as f32 linear RGBA.
    let cases: [(&str, Vec<f64>); 2] = [
        (
            "rgba8",
            vec![
                255.0, 0.0, 0.0, 255.0, 0.0, 128.0, 0.0, 64.0, 51.0, 102.0, 204.0, 0.0,
            ],
        ),
        (
            "rgb32",
            vec![0.25, 0.5, 1.0, 0.0, 0.125, 0.75, 1.0, 1.0, 1.0],
        ),
    ];
    let server = TestServer::start(ServerConfig::default()).await;
    for (name, values) in cases {
        let mut b = crate::util::builder::triangle_rig();
        let acc = if name == "rgba8" {
            let ints: Vec<i64> = values.iter().map(|&v| v as i64).collect();
            b.accessor_ints(crate::util::builder::Component::U8, &ints, "VEC4", true)
        } else {
            let floats: Vec<f32> = values.iter().map(|&v| v as f32).collect();
            b.accessor_f32(&floats, "VEC3")
        };
        b.mesh_mut(0)["primitives"][0]["attributes"]["COLOR_0"] = acc.into();
        server
            .client
            .upload_rig(name, Bytes::from(b.to_glb()))
            .await
            .expect("upload");
        // The file's colours as linear RGBA, decoded independently of the importer.
        let want: Vec<f64> = if name == "rgba8" {
            values.iter().map(|v| v / 255.0).collect()
        } else {
            values
                .chunks_exact(3)
                .flat_map(|c| [c[0], c[1], c[2], 1.0])
                .collect()
        };
        for enc in [Encoding::Bincode, Encoding::Json] {
            let mesh = server.client.mesh(name, enc).await.expect("mesh");
            let got = f32s(&mesh.colors.0);
            assert_eq!(got.len(), want.len(), "{name} {enc:?}");
            for (g, w) in got.iter().zip(&want) {
                assert!(
                    (f64::from(*g) - w).abs() <= 1e-6,
                    "{name} {enc:?}: {g} vs {w}"
                );
            }
            assert!(mesh.uvs1.0.is_empty(), "{name}: no set 1");
        }
    }
    server.stop().await;
}

/// The triangle rig with a textured material and a 3-frame clip `talk`, uploaded as `id`.
async fn rig_with_clip(server: &TestServer, id: &str) {
    server
        .client
        .upload_rig(id, triangle_with_image(&png_of(8, 8), "image/png"))
        .await
        .expect("rig");
    add_talk_clip(server, id).await;
}

/// Clip `talk` of three frames on rig `id`.
async fn add_talk_clip(server: &TestServer, id: &str) {
    server
        .client
        .upload_clip(
            id,
            "name=talk",
            "text/csv",
            Bytes::from_static(b"a,b\n0,0\n0.5,0\n1,0\n"),
        )
        .await
        .expect("clip");
}

/// An animated texture of `frames` frames, `w × h`, with three components, as
/// `crowdmorph clips compress-texture` writes it.
fn texture_bytes(w: u32, h: u32, frames: u32, material: u32) -> Vec<u8> {
    let seq: Vec<Vec<f32>> = (0..frames)
        .map(|f| {
            (0..w * h * 3)
                .map(|i| ((i * 7 + f * 13) % 23) as f32 / 23.0)
                .collect()
        })
        .collect();
    let regions = vec![crowdmorph::rig::TextureRegion {
        name: "all".into(),
        rect: [0, 0, w, h],
        components: 3,
    }];
    let mut t =
        crowdmorph::texture::compress("talk", material, w, h, &seq, &regions).expect("compress");
    t.material = material;
    t.to_bytes()
}

/// `PUT /v1/rigs/{id}/clips/{clip}/texture` of `body`: the status and the JSON answer.
async fn put_texture(
    server: &TestServer,
    id: &str,
    clip: &str,
    body: Vec<u8>,
) -> (u16, serde_json::Value) {
    let reply = server
        .client
        .send(
            Method::PUT,
            &format!("/v1/rigs/{id}/clips/{clip}/texture"),
            Some("application/octet-stream"),
            Some("application/json"),
            Bytes::from(body),
        )
        .await
        .expect("an answer");
    let json = serde_json::from_slice(&reply.body).expect("a JSON answer");
    (reply.status, json)
}

/// The status and error code of a refused `PUT` of a texture.
async fn refused_texture(
    server: &TestServer,
    id: &str,
    clip: &str,
    body: Vec<u8>,
) -> (u16, String, String) {
    let (status, v) = put_texture(server, id, clip, body).await;
    let code = v["error"]["code"].as_str().unwrap_or("").to_string();
    let message = v["error"]["message"].as_str().unwrap_or("").to_string();
    (status, code, message)
}

/// `PUT`s a texture as an HTTP/1.1 chunked body of `body` in two pieces (none when empty),
/// over a raw socket: the status, error code and message.
async fn chunked_texture(
    server: &TestServer,
    id: &str,
    clip: &str,
    body: &[u8],
) -> (u16, String, String) {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut req = format!(
        "PUT /v1/rigs/{id}/clips/{clip}/texture HTTP/1.1\r\nHost: x\r\n\
         Content-Type: application/octet-stream\r\nAccept: application/json\r\n\
         Transfer-Encoding: chunked\r\nConnection: close\r\n\r\n"
    )
    .into_bytes();
    let (a, b) = body.split_at(body.len() / 2);
    for piece in [a, b].into_iter().filter(|p| !p.is_empty()) {
        req.extend(format!("{:x}\r\n", piece.len()).bytes());
        req.extend(piece);
        req.extend(b"\r\n");
    }
    req.extend(b"0\r\n\r\n");
    let mut sock = tokio::net::TcpStream::connect(server.addr)
        .await
        .expect("connect");
    sock.write_all(&req).await.expect("send");
    let mut out = Vec::new();
    sock.read_to_end(&mut out).await.expect("answer");
    let text = String::from_utf8_lossy(&out).into_owned();
    let status = text
        .get(9..12)
        .and_then(|s| s.parse().ok())
        .unwrap_or_default();
    let json = text
        .find("\r\n\r\n")
        .and_then(|at| text.get(at + 4..))
        .and_then(|b| serde_json::from_str::<serde_json::Value>(b).ok())
        .unwrap_or_default();
    let code = json["error"]["code"].as_str().unwrap_or("").to_string();
    (status, code, text)
}

#[tokio::test]
async fn a_clips_animated_texture_is_accepted_and_hostile_ones_are_named_4xx() {
    // 4 MiB of upload memory (the triangle rig's import needs 3): a 112 × 112 texture of 15
    // components (2.3 MiB) is read, but its decoded arrays beside the body are not.
    let server = TestServer::start(ServerConfig {
        max_upload_memory: 4 << 20,
        ..ServerConfig::default()
    })
    .await;
    rig_with_clip(&server, "tri").await;
    let (status, v) = put_texture(&server, "tri", "talk", texture_bytes(4, 4, 3, 0)).await;
    assert_eq!(status, 200, "{v}");
    assert_eq!(
        v["components"], 2,
        "3 frames have at most 2 directions: {v}"
    );
    assert_eq!(
        (v["width"].as_u64(), v["material"].as_u64()),
        (Some(4), Some(0))
    );
    // Hostile and wrong bodies.
    let good = texture_bytes(4, 4, 3, 0);
    let mut declares_more = good.clone();
    declares_more[12..16].copy_from_slice(&4096u32.to_le_bytes());
    declares_more[16..20].copy_from_slice(&4096u32.to_le_bytes());
    let mut too_wide = good.clone();
    too_wide[12..16].copy_from_slice(&1_000_000u32.to_le_bytes());
    let mut nan = good.clone();
    let n = nan.len();
    nan[n - 4..].copy_from_slice(&f32::NAN.to_le_bytes());
    for (what, body) in [
        (
            "a header declaring 4096 × 4096 over a short body",
            declares_more,
        ),
        ("a side past 4096", too_wide),
        ("a truncated body", good[..good.len() - 3].to_vec()),
        ("no magic", b"GIF89a".to_vec()),
        ("a NaN coefficient", nan),
        ("2 frames for a clip of 3", texture_bytes(4, 4, 2, 0)),
        ("a material the rig lacks", texture_bytes(4, 4, 3, 7)),
    ] {
        let (status, code, message) = refused_texture(&server, "tri", "talk", body).await;
        assert_eq!(
            (status, code.as_str()),
            (400, "invalid_texture"),
            "{what}: {message}"
        );
    }
    // Larger than the upload memory once decoded: a 413 naming the flag.
    let side = 112u32;
    let big = texture_bytes(side, side, 3, 0);
    let mut big15 = big.clone();
    // Fifteen components are what the byte form allows; a real one is built here by the
    // header's count and zeros, which decode and validate.
    {
        let regions_at = 8 + 6 * 4;
        let name_len = 3;
        let header_end = regions_at + 4 + name_len + 5 * 4;
        let w = side as usize;
        let floats = w * w * 3 * 16 + 3 * 15;
        big15.truncate(header_end);
        big15[8 + 5 * 4..8 + 6 * 4].copy_from_slice(&15u32.to_le_bytes());
        big15[header_end - 4..header_end].copy_from_slice(&15u32.to_le_bytes());
        big15.extend(std::iter::repeat_n(0u8, 15 * 4));
        big15.extend(std::iter::repeat_n(0u8, floats * 4));
    }
    assert!(big15.len() < 4 << 20 && big15.len() > 2 << 20);
    let (status, code, message) = refused_texture(&server, "tri", "talk", big15).await;
    assert_eq!(
        (status, code.as_str()),
        (413, "texture_too_large"),
        "{message}"
    );
    assert!(message.contains("--max-upload-memory"), "{message}");
    // Chunked bodies (no Content-Length) are charged as they arrive, not for the most an
    // upload may send (which is past this server's upload memory): an empty one reaches the
    // texture's own check, a good one is taken.
    let (status, code, message) = chunked_texture(&server, "tri", "talk", &[]).await;
    assert_eq!(
        (status, code.as_str()),
        (400, "invalid_texture"),
        "an empty chunked body: {message}"
    );
    let (status, _, message) = chunked_texture(&server, "tri", "talk", &good).await;
    assert_eq!(status, 200, "a chunked texture: {message}");
    // Unknown rig and clip: 404 before the body is read.
    let (status, code, _) = refused_texture(&server, "tri", "nope", good.clone()).await;
    assert_eq!((status, code.as_str()), (404, "unknown_clip"));
    let (status, code, _) = refused_texture(&server, "nope", "talk", good).await;
    assert_eq!((status, code.as_str()), (404, "unknown_rig"));
    // The first texture is still served: the rig renders.
    assert!(server.client.rig("tri").await.is_ok());
}

#[tokio::test]
async fn a_clips_animated_texture_is_kept_across_a_restart() {
    let dir = temp_dir("clip-texture");
    let server = TestServer::start(stored_config(&dir)).await;
    rig_with_clip(&server, "tri").await;
    let before = host_bytes(&server, "tri").await;
    let body = texture_bytes(32, 32, 3, 0);
    let (status, v) = put_texture(&server, "tri", "talk", body.clone()).await;
    assert_eq!(status, 200, "{v}");
    let texture = v["bytes"].as_u64().expect("bytes");
    let with = host_bytes(&server, "tri").await;
    // The texture's arrays are the rig's memory now.
    assert!(with >= before + texture, "{before} + {texture} > {with}");
    server.stop().await;

    // The record's section 11 brings it back: the same memory, and a second texture for the
    // clip replaces it rather than adding to it.
    let server = TestServer::start(stored_config(&dir)).await;
    let after = host_bytes(&server, "tri").await;
    assert!(
        after >= before + texture,
        "{before} + {texture} > {after} after a restart"
    );
    // It comes back byte for byte in the form it was put, with an ETag and a 304.
    let got = get_texture(&server, "tri", "talk", None).await;
    assert_eq!((got.status, &got.body[..]), (200, &body[..]));
    let etag = got.etag.expect("an ETag");
    let again = get_texture(&server, "tri", "talk", Some(&etag)).await;
    assert_eq!(again.status, 304);
    let (status, _) = put_texture(&server, "tri", "talk", body.clone()).await;
    assert_eq!(status, 200);
    let again = host_bytes(&server, "tri").await;
    assert!(
        again < after + texture,
        "replaced, not added: {after} → {again}"
    );
    // DELETE of the texture: the clip stays, its texture and memory go.
    let r = delete(&server, "/v1/rigs/tri/clips/talk/texture").await;
    assert_eq!(r, 204);
    let gone = get_texture(&server, "tri", "talk", None).await;
    assert_eq!(gone.status, 404);
    assert!(gone.text.contains("unknown_texture"), "{}", gone.text);
    let without = host_bytes(&server, "tri").await;
    assert!(
        without + texture <= again,
        "the texture's {texture} B were released: {again} → {without}"
    );
    assert_eq!(
        delete(&server, "/v1/rigs/tri/clips/talk/texture").await,
        404
    );
    // Deleting the clip takes its texture along: a later clip of the same name and length
    // does not inherit it, before or after a restart.
    let (status, _) = put_texture(&server, "tri", "talk", body.clone()).await;
    assert_eq!(status, 200);
    assert_eq!(delete(&server, "/v1/rigs/tri/clips/talk").await, 204);
    let gone = get_texture(&server, "tri", "talk", None).await;
    assert!(gone.text.contains("unknown_clip"), "{}", gone.text);
    server.stop().await;
    let server = TestServer::start(stored_config(&dir)).await;
    add_talk_clip(&server, "tri").await;
    let gone = get_texture(&server, "tri", "talk", None).await;
    assert_eq!(gone.status, 404);
    assert!(gone.text.contains("unknown_texture"), "{}", gone.text);
    let fresh = host_bytes(&server, "tri").await;
    assert!(
        fresh < before + texture,
        "no texture came back: {before} + {texture} vs {fresh}"
    );
    server.stop().await;
    let _ = std::fs::remove_dir_all(&dir);
}

/// Host bytes rig `id` holds, as its info reports them.
async fn host_bytes(server: &TestServer, id: &str) -> u64 {
    server.client.rig(id).await.expect("rig").memory.host_bytes
}

/// A `GET` of a clip's texture: status, body, `ETag` and the body as text.
struct GotTexture {
    status: u16,
    body: Bytes,
    etag: Option<String>,
    text: String,
}

async fn get_texture(
    server: &TestServer,
    id: &str,
    clip: &str,
    if_none_match: Option<&str>,
) -> GotTexture {
    let mut headers = vec![("accept", "application/octet-stream, application/json")];
    if let Some(tag) = if_none_match {
        headers.push(("if-none-match", tag));
    }
    let reply = server
        .client
        .send_with(
            Method::GET,
            &format!("/v1/rigs/{id}/clips/{clip}/texture"),
            &headers,
            Bytes::new(),
        )
        .await
        .expect("an answer");
    GotTexture {
        status: reply.status,
        text: String::from_utf8_lossy(&reply.body).into_owned(),
        etag: reply.header("etag").map(str::to_string),
        body: reply.body,
    }
}

/// The status of a `DELETE` of `path`.
async fn delete(server: &TestServer, path: &str) -> u16 {
    server
        .client
        .send(Method::DELETE, path, None, None, Bytes::new())
        .await
        .expect("an answer")
        .status
}

/// Rig `tri` with a 64 × 64 base colour and clip `talk` of three frames.
async fn rig_with_large_base(server: &TestServer) {
    server
        .client
        .upload_rig("tri", triangle_with_image(&png_of(64, 64), "image/png"))
        .await
        .expect("rig");
    add_talk_clip(server, "tri").await;
}

/// `GET` of `path`: status, error code (empty for a success) and body.
async fn get_coded(server: &TestServer, path: &str) -> (u16, String, Bytes) {
    let r = server
        .client
        .send(Method::GET, path, None, None, Bytes::new())
        .await
        .expect("reply");
    let code = r.error().map(|e| e.error.code).unwrap_or_default();
    (r.status, code, r.body)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn clip_textures_and_layer_texels_are_charged_before_they_are_built() {
    // A 64 × 64 texture of two components is about 147 KB as its byte form; over a 64 × 64
    // base colour its layer texels (mean − base and the components, with mips) are about
    // 130 KB, and building them works through about 290 KB more: both past a 64 KiB queue
    // memory, a 413 naming the flag before anything is built; the small /layers JSON still
    // answers.
    let body = texture_bytes(64, 64, 3, 0);
    let server = TestServer::start(ServerConfig {
        queue_memory_bytes: 64 << 10,
        ..ServerConfig::default()
    })
    .await;
    rig_with_large_base(&server).await;
    let (status, v) = put_texture(&server, "tri", "talk", body.clone()).await;
    assert_eq!(status, 200, "{v}");
    for path in ["/v1/rigs/tri/clips/talk/texture", "/v1/rigs/tri/layers/0"] {
        let (status, code, body) = get_coded(&server, path).await;
        assert_eq!(
            (status, code.as_str()),
            (413, "queue_memory_exceeded"),
            "{path}"
        );
        let text = String::from_utf8_lossy(&body);
        assert!(text.contains("--queue-memory-bytes"), "{path}: {text}");
    }
    let (status, _, layers) = get_coded(&server, "/v1/rigs/tri/layers").await;
    assert_eq!(status, 200);
    let layers: serde_json::Value = serde_json::from_slice(&layers).expect("JSON");
    assert_eq!(
        layers["materials"][0]["layers"].as_array().map(Vec::len),
        Some(3)
    );
    assert_eq!(server.state.queue_memory.used(), 0);
    server.stop().await;

    // Room for a few of each at once, sixteen of each asked for together: each the same 200,
    // or a 503 `queue_full` to retry; nothing stays charged.
    let server = TestServer::start(ServerConfig {
        queue_memory_bytes: 1 << 20,
        ..ServerConfig::default()
    })
    .await;
    rig_with_large_base(&server).await;
    let (status, v) = put_texture(&server, "tri", "talk", body.clone()).await;
    assert_eq!(status, 200, "{v}");
    for path in ["/v1/rigs/tri/clips/talk/texture", "/v1/rigs/tri/layers/0"] {
        let (_, _, want) = get_coded(&server, path).await;
        assert!(!want.is_empty(), "{path}");
        if path.ends_with("/texture") {
            assert_eq!(&want[..], &body[..], "the texture as it was put");
        }
        let replies =
            futures_util::future::join_all((0..16).map(|_| get_coded(&server, path))).await;
        let (mut ok, mut busy) = (0, 0);
        for (status, code, got) in replies {
            match status {
                200 => {
                    assert_eq!(got, want, "{path}: every answer is the same bytes");
                    ok += 1;
                }
                503 => {
                    assert_eq!(code, "queue_full", "{path}");
                    busy += 1;
                }
                s => panic!("{path}: status {s} {code}"),
            }
        }
        println!("16 GET {path} at once: {ok} answered, {busy} told to retry");
        assert!(ok >= 1, "{path}: {ok} answered");
    }
    assert_eq!(server.state.queue_memory.used(), 0, "everything given back");
    server.stop().await;
}
