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

/// Each primitive's `(TEXCOORD_0, material)` as the file has them, in the rig's order.
fn file_primitives(doc: &RefDoc) -> Vec<(Option<Vec<f64>>, Option<u64>)> {
    let mut out = Vec::new();
    let mut at = None;
    let mut k = 0;
    for p in doc.scene_primitives() {
        k = if at == Some((p.node, p.mesh)) {
            k + 1
        } else {
            0
        };
        at = Some((p.node, p.mesh));
        let prim = &doc.json["meshes"][p.mesh]["primitives"][k];
        let uv = prim["attributes"]["TEXCOORD_0"]
            .as_u64()
            .map(|a| doc.accessor(a as usize).0);
        out.push((uv, prim["material"].as_u64()));
    }
    out
}

fn f32s(b: &[u8]) -> Vec<f32> {
    b.chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

/// The mesh's texture coordinates and materials equal the file's.
fn check_mesh(mesh: &MeshResponse, doc: &RefDoc, ctx: &str) {
    let want = file_primitives(doc);
    assert_eq!(mesh.primitives.len(), want.len(), "{ctx}: primitives");
    let uvs = f32s(&mesh.uvs.0);
    assert_eq!(
        uvs.len(),
        mesh.vertices as usize * 2,
        "{ctx}: one u, v per vertex"
    );
    for (p, (uv, material)) in mesh.primitives.iter().zip(&want) {
        assert_eq!(
            p.material.map(u64::from),
            *material,
            "{ctx}: {} material",
            p.name
        );
        let got = &uvs[p.first_vertex as usize * 2..(p.first_vertex + p.vertices) as usize * 2];
        match uv {
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
            None => assert!(got.iter().all(|&g| g == 0.0), "{ctx}: zeros without"),
        }
    }
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
