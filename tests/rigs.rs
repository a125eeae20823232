//! Every real rig in `../shared/data` loads into exactly what its file says: positions,
//! normals, triangles, target names and sparse deltas in rig space, and clips that sample the
//! file's animation curves — each checked against the independent reader in `util`.

use crowdmorph::import::{ImportOptions, load_path};
use crowdmorph::rig::{DEFAULT_DELTA_THRESHOLD, Rig};
use glam::{DMat3, DVec3};

use crate::util::builder::{Builder, Component};
use crate::util::{RefDoc, normal_matrix, rig_files};
use crowdmorph::import::gltf::rig_from_slice;
use serde_json::json;

fn load(path: &std::path::Path) -> Rig {
    load_path(path, &ImportOptions::default()).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

fn close(a: glam::Vec3, b: DVec3, tol: f64) -> bool {
    (a.as_dvec3() - b).abs().max_element() <= tol
}

#[test]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
fn loaded_geometry_and_targets_equal_the_file() {
    let files = rig_files();
    for path in files {
        let rig = load(&path);
        let doc = RefDoc::load(&path);
        let prims = doc.scene_primitives();
        let name = path.file_name().unwrap().to_string_lossy();
        assert_eq!(rig.primitives.len(), prims.len(), "{name}: primitive count");
        let diag = rig.bbox().diagonal() as f64;
        let tol = 1e-6 * diag.max(1.0);
        for (pi, (got, want)) in rig.primitives.iter().zip(&prims).enumerate() {
            let ctx = format!("{name} primitive {pi}");
            assert_eq!(
                got.positions.len(),
                want.positions.len(),
                "{ctx}: vertex count"
            );
            for (v, (&g, &w)) in got.positions.iter().zip(&want.positions).enumerate() {
                let w = want.world.transform_point3(w);
                assert!(close(g, w, tol), "{ctx}: position {v}: {g} vs {w}");
            }
            let flip = DMat3::from_mat4(want.world).determinant() < 0.0;
            let mut idx = want.indices.clone();
            if flip {
                for t in idx.chunks_exact_mut(3) {
                    t.swap(1, 2);
                }
            }
            assert_eq!(got.indices, idx, "{ctx}: triangles");
            let nm = normal_matrix(want.world);
            match &want.normals {
                Some(ns) => {
                    assert!(
                        got.normals_from_file,
                        "{ctx}: normals should come from the file"
                    );
                    for (v, (&g, &w)) in got.normals.iter().zip(ns).enumerate() {
                        let w = (nm * w).normalize();
                        assert!(close(g, w, 1e-6), "{ctx}: normal {v}: {g} vs {w}");
                    }
                }
                None => {
                    assert!(!got.normals_from_file, "{ctx}: normals must be computed");
                    assert!(
                        got.normals.iter().all(|n| (n.length() - 1.0).abs() < 1e-5),
                        "{ctx}: unit normals"
                    );
                }
            }

            // Targets: rig-wide names, and exactly the vertices above the threshold.
            let linear = DMat3::from_mat4(want.world);
            for (k, t) in want.targets.iter().enumerate() {
                let tname = &want.target_names[k];
                let id = rig
                    .target_id(tname)
                    .unwrap_or_else(|| panic!("{ctx}: target {tname} missing"));
                let sparse = got.targets.iter().find(|s| s.target == id);
                let mut expected_vertices = Vec::new();
                for v in 0..want.positions.len() {
                    let dp = linear * t.positions[v];
                    let exceeds = |d: DVec3| d.abs().max_element() > DEFAULT_DELTA_THRESHOLD as f64;
                    // Normal and tangent deltas are stored relative to the transformed (then
                    // normalized) base vectors, so they are scaled like them.
                    let dn = t
                        .normals
                        .as_ref()
                        .map(|n| nm * n[v] / (nm * want.normals.as_ref().unwrap()[v]).length());
                    let dt = match (&t.tangents, &want.tangents) {
                        (Some(d), Some(base)) => Some(linear * d[v] / (linear * base[v]).length()),
                        _ => None,
                    };
                    if exceeds(dp) || dn.is_some_and(exceeds) || dt.is_some_and(exceeds) {
                        expected_vertices.push((v as u32, dp));
                    }
                }
                match sparse {
                    None => assert!(
                        expected_vertices.is_empty(),
                        "{ctx}: target {tname} dropped but moves {} vertices",
                        expected_vertices.len()
                    ),
                    Some(s) => {
                        let got_v: Vec<u32> = s.vertices.clone();
                        let want_v: Vec<u32> = expected_vertices.iter().map(|e| e.0).collect();
                        assert_eq!(got_v, want_v, "{ctx}: target {tname}: stored vertices");
                        for (i, (_, dp)) in expected_vertices.iter().enumerate() {
                            assert!(
                                close(s.positions[i], *dp, tol),
                                "{ctx}: target {tname}: delta {i}"
                            );
                        }
                        assert_eq!(
                            s.normals.is_some(),
                            t.normals.is_some(),
                            "{ctx}: {tname} normal deltas"
                        );
                    }
                }
            }
        }
        // Every rig-wide name comes from some mesh; nothing invented.
        let mut names: Vec<&String> = prims.iter().flat_map(|p| &p.target_names).collect();
        names.sort();
        names.dedup();
        assert_eq!(names.len(), rig.targets.len(), "{name}: rig-wide targets");
        rig.validate().expect("valid rig");
    }
}

#[test]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
fn clips_sample_the_file_animation_at_30_fps() {
    let files = rig_files();
    let mut checked = 0;
    for path in files {
        let rig = load(&path);
        let doc = RefDoc::load(&path);
        let prims = doc.scene_primitives();
        let anims = doc.weight_animations();
        assert_eq!(
            rig.clips.len(),
            anims.len(),
            "{}: one clip per weights animation",
            path.display()
        );
        for (name, channels) in anims {
            let clip = &rig.clips[rig
                .clip_index(&name)
                .unwrap_or_else(|| panic!("clip {name} missing"))];
            let last = channels
                .iter()
                .map(|c| *c.times.last().unwrap())
                .fold(0.0, f64::max);
            assert_eq!(
                clip.frames as usize,
                (last * 30.0 + 1e-3).floor() as usize + 1,
                "{name}: frame count"
            );
            assert_eq!(clip.fps, 30.0);
            for ch in &channels {
                let prim = prims
                    .iter()
                    .find(|p| p.node == ch.node)
                    .expect("channel node in scene");
                let width = prim.target_names.len();
                for f in 0..clip.frames {
                    let t = (f as f32 / 30.0) as f64;
                    let want = ch.sample(t, width);
                    for (k, tn) in prim.target_names.iter().enumerate() {
                        let id = rig.target_id(tn).unwrap() as usize;
                        let got = clip.weight(id, f) as f64;
                        assert!(
                            (got - want[k]).abs() < 1e-6,
                            "{name} frame {f} {tn}: {got} vs {}",
                            want[k]
                        );
                    }
                }
            }
            checked += 1;
        }
    }
    assert!(
        checked >= 5,
        "expected the Khronos animations, checked {checked}"
    );
}

#[test]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
fn ict_facekit_has_53_named_targets_and_sparse_deltas() {
    let files = rig_files();
    let rig = load(&files[0]);
    assert_eq!(rig.vertex_count(), 26_719);
    assert_eq!(rig.triangle_count(), 52_220);
    assert_eq!(rig.targets.len(), 53);
    assert!(rig.target_id("jawOpen").is_some() && rig.target_id("eyeBlink_L").is_some());
    // The data README: with |delta| > 1e-4 a target touches 10-68 % of the vertices; at the
    // default 1e-6 threshold every target is sparse but none is empty.
    let nnz = rig.target_nnz();
    let v = rig.vertex_count() as f64;
    for (name, &n) in rig.targets.iter().zip(&nnz) {
        let f = n as f64 / v;
        assert!(f > 0.2 && f < 0.75, "{name}: {f:.3} of the vertices");
    }
}

const QUAD: [[f32; 3]; 5] = [
    [0.0, 0.0, 0.0],
    [1.0, 0.0, 0.0],
    [1.0, 1.0, 0.0],
    [0.0, 1.0, 0.0],
    [0.5, 0.5, 0.0],
];
const QUAD_TRIS: [u32; 12] = [0, 1, 4, 1, 2, 4, 2, 3, 4, 3, 0, 4];

#[test]
fn sparse_target_accessors_import_their_deltas() {
    let mut b = Builder::new();
    let pos = b.accessor_vec3(&QUAD);
    let idx = b.indices_u32(&QUAD_TRIS);
    let sparse = b.accessor_sparse_vec3(5, &[1, 3], &[[0.0, 0.0, 0.25], [0.5, 0.0, 0.0]]);
    let mesh = b.mesh(
        vec![json!({ "attributes": { "POSITION": pos }, "indices": idx, "targets": [{ "POSITION": sparse }] })],
        Some(&["lift"]),
    );
    let node = b.node(Some(mesh));
    b.scene(&[node]);
    for bytes in [b.to_glb(), b.to_gltf_data_uri()] {
        let rig = rig_from_slice(&bytes, &ImportOptions::default()).expect("import");
        let t = &rig.primitives[0].targets[0];
        assert_eq!(rig.targets, vec!["lift".to_string()]);
        assert_eq!(t.vertices, vec![1, 3], "only the sparse elements move");
        assert_eq!(
            t.positions,
            vec![
                glam::Vec3::new(0.0, 0.0, 0.25),
                glam::Vec3::new(0.5, 0.0, 0.0)
            ]
        );
    }
}

#[test]
fn quantized_positions_and_deltas_decode_and_take_the_node_transform() {
    // KHR_mesh_quantization style: normalized i16 positions, normalized i8 deltas, and a node
    // scale + translation that dequantizes them.
    let q: Vec<i64> = QUAD
        .iter()
        .flatten()
        .map(|&c| (c * 32767.0).round() as i64)
        .collect();
    let d: [i64; 15] = [0, 0, 0, 0, 0, 127, 0, 0, 0, -127, 0, 0, 0, 0, 64];
    let mut b = Builder::new();
    let pos = b.accessor_ints(Component::I16, &q, "VEC3", true);
    b.accessor_mut(pos)["min"] = json!([0, 0, 0]);
    b.accessor_mut(pos)["max"] = json!([1, 1, 0]);
    let delta = b.accessor_ints(Component::I8, &d, "VEC3", true);
    let idx = b.indices_u32(&QUAD_TRIS);
    let mesh = b.mesh(
        vec![json!({ "attributes": { "POSITION": pos }, "indices": idx, "targets": [{ "POSITION": delta }] })],
        None,
    );
    let node = b.node(Some(mesh));
    b.json_mut()["nodes"][node]["scale"] = json!([2.0, 2.0, 2.0]);
    b.json_mut()["nodes"][node]["translation"] = json!([10.0, 0.0, 0.0]);
    b.json_mut()["extensionsUsed"] = json!(["KHR_mesh_quantization"]);
    b.json_mut()["extensionsRequired"] = json!(["KHR_mesh_quantization"]);
    b.scene(&[node]);
    let rig = rig_from_slice(&b.to_glb(), &ImportOptions::default()).expect("import");
    let p = &rig.primitives[0];
    for (got, want) in p.positions.iter().zip(QUAD) {
        let want = glam::Vec3::from(want) * 2.0 + glam::Vec3::new(10.0, 0.0, 0.0);
        assert!((*got - want).abs().max_element() < 1e-4, "{got} vs {want}");
    }
    let t = &p.targets[0];
    assert_eq!(
        rig.targets,
        vec!["target_0".to_string()],
        "unnamed targets get target_<i>"
    );
    assert_eq!(t.vertices, vec![1, 3, 4]);
    // Deltas take the node's linear part (scale 2) but not its translation.
    let want = [
        [0.0, 0.0, 2.0],
        [-2.0, 0.0, 0.0],
        [0.0, 0.0, 2.0 * 64.0 / 127.0],
    ];
    for (got, w) in t.positions.iter().zip(want) {
        assert!(
            (*got - glam::Vec3::from(w)).abs().max_element() < 1e-6,
            "{got} vs {w:?}"
        );
    }
}

#[test]
fn mirrored_node_flips_winding_and_transforms_normals_by_the_inverse_transpose() {
    let mut b = Builder::new();
    let mesh = b.mesh_with_targets(
        &QUAD,
        Some(&QUAD_TRIS),
        &[vec![[0.0, 0.0, 1.0]; 5]],
        Some(&["push"]),
    );
    let child = b.node(Some(mesh));
    b.json_mut()["nodes"][child]["scale"] = json!([-1.0, 3.0, 1.0]);
    let parent = b.node(None);
    b.json_mut()["nodes"][parent]["children"] = json!([child]);
    b.json_mut()["nodes"][parent]["rotation"] = json!([0.0, 0.0, 0.70710677, 0.70710677]);
    b.scene(&[parent]);
    let rig = rig_from_slice(&b.to_glb(), &ImportOptions::default()).expect("import");
    let p = &rig.primitives[0];
    // det < 0: every triangle's winding is reversed so it still faces outward.
    for (got, want) in p.indices.chunks_exact(3).zip(QUAD_TRIS.chunks_exact(3)) {
        assert_eq!(got, [want[0], want[2], want[1]]);
    }
    // The quad lies in z = 0 and the transform keeps z, so after the flip normals face +z, and
    // the +z delta stays +z (the linear part leaves z alone).
    for n in &p.normals {
        assert!((*n - glam::Vec3::Z).length() < 1e-5, "normal {n}");
    }
    // Rotation by 90° about z after the (-1, 3, 1) scale: (x, y) → (-3y, -x).
    assert!(
        (p.positions[1] - glam::Vec3::new(0.0, -1.0, 0.0)).length() < 1e-5,
        "{}",
        p.positions[1]
    );
    assert!(
        (p.positions[3] - glam::Vec3::new(-3.0, 0.0, 0.0)).length() < 1e-5,
        "{}",
        p.positions[3]
    );
    assert!((p.targets[0].positions[0] - glam::Vec3::Z).length() < 1e-6);
}

#[test]
fn base_colour_factors_come_from_the_materials_and_survive_the_store() {
    // Two primitives: one with a material's base colour, one without (glTF's white).
    let mut b = Builder::new();
    let tri = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
    let mut p0 = b.primitive(&tri, None, &[]);
    p0["material"] = json!(0);
    let p1 = b.primitive(&tri, None, &[]);
    let mesh = b.mesh(vec![p0, p1], None);
    let node = b.node(Some(mesh));
    b.scene(&[node]);
    b.json_mut()["materials"] = json!([{
        "pbrMetallicRoughness": { "baseColorFactor": [0.8, 0.5, 0.25, 1.0] }
    }]);
    let rig = rig_from_slice(&b.to_glb(), &ImportOptions::default()).expect("rig");
    assert_eq!(rig.primitives[0].base_color, [0.8, 0.5, 0.25, 1.0]);
    assert_eq!(rig.primitives[1].base_color, [1.0; 4]);

    // The store keeps them.
    let dir = std::env::temp_dir().join(format!("crowdmorph-colours-{}", std::process::id()));
    let store = crowdmorph::store::Store::open(&dir).expect("store");
    store
        .put(crowdmorph::store::RecordRef::Rig {
            id: "c",
            rig: &rig,
            clips: &rig.clips,
        })
        .expect("put");
    match crowdmorph::store::Store::read(&store.path_of("c")).expect("read") {
        crowdmorph::store::Record::Rig(r) => {
            assert_eq!(r.rig.primitives[0].base_color, [0.8, 0.5, 0.25, 1.0]);
            assert_eq!(r.rig, rig);
        }
        other => panic!("unexpected record {other:?}"),
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// The file's `TEXCOORD_0` of each primitive of the default scene, in scene order, decoded by
/// the test's own reader (normalized integers per the spec); `None` for a primitive without.
fn file_uvs(doc: &RefDoc) -> Vec<Option<Vec<[f64; 2]>>> {
    doc.scene_attribute("TEXCOORD_0")
        .into_iter()
        .map(|(uv, _)| {
            uv.map(|(v, comps)| {
                assert_eq!(comps, 2, "TEXCOORD_0 is VEC2");
                v.chunks(2).map(|c| [c[0], c[1]]).collect()
            })
        })
        .collect()
}

/// `got` equals the file's texture coordinates to f32 rounding.
fn assert_uvs(got: Option<&Vec<glam::Vec2>>, want: Option<&Vec<[f64; 2]>>, ctx: &str) {
    match (got, want) {
        (None, None) => {}
        (Some(g), Some(w)) => {
            assert_eq!(g.len(), w.len(), "{ctx}: texture coordinate count");
            for (v, (g, w)) in g.iter().zip(w).enumerate() {
                let err = (f64::from(g.x) - w[0])
                    .abs()
                    .max((f64::from(g.y) - w[1]).abs());
                assert!(
                    err <= 1e-6 * w[0].abs().max(w[1].abs()).max(1.0),
                    "{ctx}: vertex {v}: {g} vs {w:?}"
                );
            }
        }
        (g, w) => panic!(
            "{ctx}: texture coordinates {} in the rig, {} in the file",
            if g.is_some() { "present" } else { "absent" },
            if w.is_some() { "present" } else { "absent" }
        ),
    }
}

/// Puts `rig` in a fresh data dir and reads its record back.
fn stored_and_read(rig: &Rig, tag: &str) -> Rig {
    let dir = std::env::temp_dir().join(format!("crowdmorph-uvs-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let store = crowdmorph::store::Store::open(&dir).expect("store");
    store
        .put(crowdmorph::store::RecordRef::Rig {
            id: "uv",
            rig,
            clips: &rig.clips,
        })
        .expect("put");
    let back = match crowdmorph::store::Store::read(&store.path_of("uv")).expect("read") {
        crowdmorph::store::Record::Rig(r) => r.rig,
        _ => panic!("a rig record"),
    };
    let _ = std::fs::remove_dir_all(&dir);
    back.validate().expect("valid after the store");
    back
}

#[test]
fn texture_coordinates_come_from_the_file_and_survive_the_store() {
    // A quad whose TEXCOORD_0 is normalized UNSIGNED_SHORT (as gltfpack and VRoid quantize
    // it), beside a triangle without texture coordinates.
    let mut b = Builder::new();
    let quad = [
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [1.0, 1.0, 0.0],
        [0.0, 1.0, 0.0],
    ];
    let mut p0 = b.primitive(&quad, Some(&[0, 1, 2, 0, 2, 3]), &[]);
    let uv = b.accessor_ints(
        Component::U16,
        &[0, 65535, 65535, 65535, 32768, 12345, 1, 0],
        "VEC2",
        true,
    );
    p0["attributes"]["TEXCOORD_0"] = json!(uv);
    let tri = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
    let p1 = b.primitive(&tri, None, &[]);
    let mesh = b.mesh(vec![p0, p1], None);
    let node = b.node(Some(mesh));
    b.scene(&[node]);
    let glb = b.to_glb();
    let rig = rig_from_slice(&glb, &ImportOptions::default()).expect("rig");
    let want = file_uvs(&RefDoc::from_bytes(&glb, std::path::Path::new(".")));
    for (i, (p, w)) in rig.primitives.iter().zip(&want).enumerate() {
        assert_uvs(p.look.uv0.as_ref(), w.as_ref(), &format!("primitive {i}"));
    }
    assert!(rig.primitives[0].look.uv0.is_some() && rig.primitives[1].look.uv0.is_none());
    let back = stored_and_read(&rig, "quad");
    assert_eq!(
        back, rig,
        "the record keeps every primitive's texture coordinates"
    );

    // A TEXCOORD_0 with fewer elements than the primitive has vertices is refused, naming it.
    let mut b = Builder::new();
    let mut p = b.primitive(&quad, Some(&[0, 1, 2, 0, 2, 3]), &[]);
    p["attributes"]["TEXCOORD_0"] = json!(b.accessor_f32(&[0.0, 0.0, 1.0, 0.0], "VEC2"));
    let mesh = b.mesh(vec![p], None);
    let node = b.node(Some(mesh));
    b.scene(&[node]);
    let e = rig_from_slice(&b.to_glb(), &ImportOptions::default())
        .expect_err("two texture coordinates for four vertices")
        .to_string();
    assert!(e.contains("TEXCOORD_0"), "{e}");
    // So is one of another shape (VEC3), and one whose count is absurd: refused from the
    // header, before anything is decoded or allocated.
    for (values, count) in [
        (vec![0.0f32; 12], None),
        (vec![0.0f32; 8], Some(1u64 << 40)),
    ] {
        let mut b = Builder::new();
        let mut p = b.primitive(&quad, Some(&[0, 1, 2, 0, 2, 3]), &[]);
        let ty = if count.is_some() { "VEC2" } else { "VEC3" };
        let a = b.accessor_f32(&values, ty);
        if let Some(c) = count {
            b.accessor_mut(a)["count"] = json!(c);
        }
        p["attributes"]["TEXCOORD_0"] = json!(a);
        let mesh = b.mesh(vec![p], None);
        let node = b.node(Some(mesh));
        b.scene(&[node]);
        let e = rig_from_slice(&b.to_glb(), &ImportOptions::default())
            .expect_err("a bad TEXCOORD_0")
            .to_string();
        let named = if count.is_some() {
            "ends at" // the header's bounds check, before any decoding
        } else {
            "TEXCOORD_0 must be VEC2"
        };
        assert!(e.contains(named), "{ty}: {e}");
    }
}

#[test]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
fn shared_rigs_texture_coordinates_equal_the_files_through_store_and_mesh_levels() {
    let dir = crate::util::data_dir().join("khronos");
    let mut with_uvs = 0;
    for path in rig_files() {
        let name = path.file_name().unwrap().to_string_lossy().to_string();
        let rig = load(&path);
        let want = file_uvs(&RefDoc::load(&path));
        assert_eq!(rig.primitives.len(), want.len(), "{name}: primitives");
        for (i, (p, w)) in rig.primitives.iter().zip(&want).enumerate() {
            assert_uvs(
                p.look.uv0.as_ref(),
                w.as_ref(),
                &format!("{name} primitive {i}"),
            );
            with_uvs += usize::from(w.is_some());
        }
    }
    // MorphStressTest and MorphPrimitivesTest carry texture coordinates (they are textured).
    assert!(
        with_uvs >= 4,
        "{with_uvs} primitives with TEXCOORD_0 among the shared rigs"
    );

    for file in [
        "MorphPrimitivesTest/glTF/MorphPrimitivesTest.gltf",
        "MorphStressTest/glTF/MorphStressTest.gltf",
    ] {
        let mut rig = load(&dir.join(file));
        // Mesh levels at half and a quarter of the triangles: each kept vertex keeps its
        // source vertex's texture coordinates.
        let spec = crowdmorph::engine::lod::LodSpec {
            method: crowdmorph::engine::lod::OrderMethod::FileOrder,
            mesh_fractions: vec![0.5, 0.25],
            ..Default::default()
        };
        rig.lod = crowdmorph::engine::lod::build_lod(&rig, &spec, None, None).expect("lod");
        rig.validate().expect("valid with mesh levels");
        let levels = crowdmorph::rig::mesh_level_rigs(&rig).expect("mesh levels");
        assert_eq!(levels.len(), 2);
        for (m, level) in levels.iter().enumerate() {
            for (i, (lp, src)) in level
                .primitives
                .iter()
                .zip(rig.primitives.iter())
                .enumerate()
            {
                let kept = &rig.lod.meshes[m].primitives[i].vertices;
                let want: Option<Vec<glam::Vec2>> = src
                    .look
                    .uv0
                    .as_ref()
                    .map(|uv| kept.iter().map(|&v| uv[v as usize]).collect());
                assert_eq!(lp.look.uv0, want, "{file} mesh level {m} primitive {i}");
                assert_eq!(
                    lp.look.uv0.as_ref().map(Vec::len),
                    src.look.uv0.as_ref().map(|_| lp.positions.len()),
                    "{file} mesh level {m} primitive {i}: one per kept vertex"
                );
            }
        }
        // The store keeps them with the mesh levels.
        let back = stored_and_read(&rig, "shared");
        assert_eq!(back, rig, "{file}: the store round trip");
    }
}
