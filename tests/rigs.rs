//! Every real rig in `../shared/data` loads into exactly what its file says: positions,
//! normals, triangles, target names and sparse deltas in rig space, and clips that sample the
//! file's animation curves — each checked against the independent reader in `util`.

use crowdmorph::import::{ImportOptions, load_path};
use crowdmorph::rig::{DEFAULT_DELTA_THRESHOLD, Rig};
use glam::{DMat3, DVec3};

use crate::util::{RefDoc, normal_matrix, rig_files};

fn load(path: &std::path::Path) -> Rig {
    load_path(path, &ImportOptions::default()).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

fn close(a: glam::Vec3, b: DVec3, tol: f64) -> bool {
    (a.as_dvec3() - b).abs().max_element() <= tol
}

#[test]
fn loaded_geometry_and_targets_equal_the_file() {
    let Some(files) = rig_files() else { return };
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
fn clips_sample_the_file_animation_at_30_fps() {
    let Some(files) = rig_files() else { return };
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
fn ict_facekit_has_53_named_targets_and_sparse_deltas() {
    let Some(files) = rig_files() else { return };
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
