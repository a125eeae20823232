//! Synthetic rigs for benchmarks and tests.
//!
//! [`paper_scale_rig`] has the size of the rig in Costigan et al. 2016 (72 blendshapes, 43,788
//! vertices) with localized deltas: each target moves a contiguous band of at most 1/20 of the
//! vertices, as facial blendshapes move a region of the face. It is deterministic.
//!
//! [`skinned_head`] is the embedded head with five joints beside its 51 blendshapes (neck,
//! head, jaw, one per eye), the shape of a Ready Player Me or MetaHuman face: what skinning
//! costs on a face, and a face whose eyes and jaw tests can turn.

use crate::rng::SplitMix64;
use glam::Vec3;

use crate::rig::{Clip, Lod, Primitive, Rig, sparsify, vertex_normals};

/// Vertices of the paper's head model.
pub const PAPER_VERTICES: usize = 43_788;
/// Blendshapes of the paper's head model.
pub const PAPER_TARGETS: usize = 72;

/// A 72-target, 43,788-vertex rig with localized deltas and one 60-frame clip ("anim") whose
/// weights are active about three times in four.
pub fn paper_scale_rig() -> Rig {
    banded_rig("paper-scale", PAPER_VERTICES, 209, PAPER_TARGETS)
}

/// A rig of `n` vertices on a sphere (rows of `side`) and `n_targets` targets, each moving a
/// contiguous band of at most 1/20 of the vertices, with one 60-frame clip ("anim") whose
/// weights are active about three times in four. Many targets on few vertices give long
/// active lists of which each tile of vertices sees only a part. Deterministic.
pub fn banded_rig(name: &str, n: usize, side: usize, n_targets: usize) -> Rig {
    let positions: Vec<Vec3> = (0..n)
        .map(|i| {
            let (u, v) = (
                (i % side) as f32 / side as f32,
                (i / side) as f32 / side as f32,
            );
            let (a, b) = (u * std::f32::consts::TAU, v * std::f32::consts::PI);
            Vec3::new(a.cos() * b.sin(), b.cos(), a.sin() * b.sin()) * 10.0
        })
        .collect();
    let mut indices = Vec::new();
    let s = side as u32;
    for r in 0..(n / side - 1) as u32 {
        for c in 0..s - 1 {
            let i = r * s + c;
            indices.extend_from_slice(&[i, i + s, i + 1, i + 1, i + s, i + s + 1]);
        }
    }
    let normals = vertex_normals(&positions, &indices);
    let mut rng = SplitMix64(72);
    let targets = (0..n_targets as u32)
        .map(|t| {
            let center = rng.below(n);
            let shortest = 200.min(n / 40);
            let radius = shortest + rng.below(n / 20 - shortest);
            let dir = Vec3::new(rng.unit() - 0.5, rng.unit() - 0.5, rng.unit() - 0.5);
            let dp: Vec<Vec3> = (0..n)
                .map(|v| {
                    let d = (v as i64 - center as i64).unsigned_abs() as usize;
                    if d < radius {
                        dir * (1.0 - d as f32 / radius as f32)
                    } else {
                        Vec3::ZERO
                    }
                })
                .collect();
            sparsify(t, &dp, None, None, 1e-6)
        })
        .collect();
    let primitives = vec![Primitive {
        name: "paper".into(),
        positions,
        normals,
        normals_from_file: false,
        tangents: None,
        indices,
        targets,
        base_color: Primitive::default_base_color(),
        skin: None,
        look: Default::default(),
    }];
    let frames = 60;
    let weights: Vec<f32> = (0..n_targets * frames)
        .map(|_| if rng.below(4) == 0 { 0.0 } else { rng.unit() })
        .collect();
    let lod = Lod::by_delta_energy(&primitives, n_targets);
    Rig {
        name: name.into(),
        targets: (0..n_targets).map(|t| format!("shape{t}")).collect(),
        default_weights: vec![0.0; n_targets],
        primitives: std::sync::Arc::new(primitives),
        clips: vec![Clip {
            name: "anim".into(),
            fps: 30.0,
            frames: frames as u32,
            targets: n_targets as u32,
            weights: std::sync::Arc::new(weights),
            joints: None,
        }],
        lod,
        skeleton: None,
        import_notes: Vec::new(),
        appearance: None,
    }
}

/// Joint names of [`skinned_head`], parents first.
pub const HEAD_JOINTS: [&str; 5] = ["Neck", "Head", "Jaw", "LeftEye", "RightEye"];

/// The embedded head with a five-joint skeleton: `Neck` at the base of the mesh, `Head` above
/// it, `Jaw` (pivot below the ears) and `LeftEye`/`RightEye` at the eyeballs' centres, the last
/// three children of `Head`. The eyeballs follow their eye joints rigidly; the face follows
/// `Jaw` below the mouth at the front and `Neck` at the bottom, with smooth weights, and
/// `Head` elsewhere (up to three influences a vertex). Every clip gains a joint table: the
/// head turns and nods gently, the eyes look left and right and up, and the jaw opens in
/// `talk`. Deterministic.
pub fn skinned_head() -> Rig {
    use crate::rig::{Bone, Influences, JointTable, NO_PARENT, SkelNode, Skeleton, Trs};
    use glam::{Mat4, Quat};
    let mut rig = crate::embedded::default_rig();
    let eye = |name: &str| -> Vec3 {
        let p = rig.primitives.iter().find(|p| p.name == name);
        p.map_or(Vec3::ZERO, |p| {
            p.positions.iter().copied().sum::<Vec3>() / p.positions.len().max(1) as f32
        })
    };
    let (eye_l, eye_r) = (eye("eye_L"), eye("eye_R"));
    let bbox = rig.bbox();
    let (lo, hi) = (bbox.min, bbox.max);
    let height = hi.y - lo.y;
    let z_mid = 0.5 * (lo.z + hi.z);
    // Global rest positions of the joints (the head looks along +Z, +Y up).
    let at = [
        Vec3::new(0.0, lo.y, z_mid - 0.1 * height),
        Vec3::new(0.0, lo.y + 0.2 * height, z_mid - 0.05 * height),
        Vec3::new(0.0, eye_l.y - 0.18 * height, z_mid),
        eye_l,
        eye_r,
    ];
    let parent = [NO_PARENT, 0, 1, 1, 1];
    let nodes: Vec<SkelNode> = (0..5)
        .map(|i| {
            let p = parent[i];
            let local = if p == NO_PARENT {
                at[i]
            } else {
                at[i] - at[p as usize]
            };
            SkelNode {
                name: HEAD_JOINTS[i].into(),
                parent: p,
                rest: Trs {
                    translation: local.to_array(),
                    ..Trs::default()
                },
            }
        })
        .collect();
    let bones: Vec<Bone> = (0..5)
        .map(|i| Bone {
            node: i as u32,
            bind: Mat4::from_translation(-at[i]).to_cols_array(),
        })
        .collect();
    let smooth = |t: f32| {
        let t = t.clamp(0.0, 1.0);
        t * t * (3.0 - 2.0 * t)
    };
    let mouth_y = at[2].y - 0.05 * height;
    let mut prims = rig.primitives.as_ref().clone();
    for p in &mut prims {
        let n = p.positions.len();
        let mut inf = Influences {
            joints: Vec::with_capacity(n),
            weights: Vec::with_capacity(n),
        };
        for v in &p.positions {
            let (j, w) = match p.name.as_str() {
                "eye_L" => ([3, 0, 0, 0], [1.0, 0.0, 0.0, 0.0]),
                "eye_R" => ([4, 0, 0, 0], [1.0, 0.0, 0.0, 0.0]),
                _ => {
                    let jaw = smooth((mouth_y - v.y) / (0.1 * height))
                        * smooth((v.z - z_mid) / (0.15 * height));
                    let neck = smooth((lo.y + 0.3 * height - v.y) / (0.2 * height));
                    let (jaw, neck) = if jaw + neck > 1.0 {
                        (jaw / (jaw + neck), neck / (jaw + neck))
                    } else {
                        (jaw, neck)
                    };
                    // Largest first; zero weights are unused entries.
                    let mut pairs = [(1u16, (1.0 - jaw - neck).max(0.0)), (2, jaw), (0, neck)];
                    pairs.sort_by(|a, b| b.1.total_cmp(&a.1));
                    (
                        [pairs[0].0, pairs[1].0, pairs[2].0, 0],
                        [pairs[0].1, pairs[1].1, pairs[2].1, 0.0],
                    )
                }
            };
            inf.joints.push(j);
            inf.weights.push(w);
        }
        p.skin = Some(inf);
    }
    rig.primitives = std::sync::Arc::new(prims);
    let skeleton = Skeleton {
        nodes,
        bones,
        map: None,
    };
    for (ci, clip) in rig.clips.iter_mut().enumerate() {
        let frames = clip.frames as usize;
        let mut values = Vec::with_capacity(frames * 5 * Trs::FLOATS);
        for f in 0..frames {
            let t = f as f32 / clip.fps;
            let phase = ci as f32 * 0.7;
            let jaw_open = if clip.name == "talk" {
                0.22 * (0.5 - 0.5 * (t * 9.0).cos())
            } else {
                0.03 * (1.0 + (t * 1.3 + phase).sin())
            };
            let rot = [
                Quat::from_rotation_x(0.04 * (t * 0.9 + phase).sin()),
                Quat::from_rotation_y(0.25 * (t * 1.1 + phase).sin())
                    * Quat::from_rotation_x(0.1 * (t * 1.7).sin()),
                Quat::from_rotation_x(jaw_open),
                Quat::from_rotation_y(0.3 * (t * 2.3 + phase).sin())
                    * Quat::from_rotation_x(0.15 * (t * 1.9).cos()),
                Quat::from_rotation_y(0.3 * (t * 2.3 + phase).sin())
                    * Quat::from_rotation_x(0.15 * (t * 1.9).cos()),
            ];
            for (node, q) in skeleton.nodes.iter().zip(rot) {
                let trs = Trs {
                    rotation: q.to_array(),
                    ..node.rest
                };
                values.extend_from_slice(&trs.floats());
            }
        }
        clip.joints = Some(std::sync::Arc::new(JointTable {
            nodes: (0..5).collect(),
            frames: frames as u32,
            values,
        }));
    }
    rig.skeleton = Some(std::sync::Arc::new(skeleton));
    rig.name = "skinned-head".into();
    rig
}

/// Gives a rig without clips a deterministic random one named "random" (24 frames, weights
/// active about two times in three), so benchmarks and GPU jobs have tables to read.
pub fn with_random_clip(rig: Rig, seed: u64) -> Rig {
    if rig.clips.is_empty() {
        with_random_clip_of(rig, "random", 24, seed)
    } else {
        rig
    }
}

/// Appends a deterministic random clip `name` of `frames` frames (weights active about two
/// times in three).
pub fn with_random_clip_of(mut rig: Rig, name: &str, frames: usize, seed: u64) -> Rig {
    {
        let mut rng = SplitMix64(seed);
        let t = rig.targets.len();
        let weights: Vec<f32> = (0..t * frames)
            .map(|_| if rng.below(3) == 0 { 0.0 } else { rng.unit() })
            .collect();
        rig.clips.push(Clip {
            name: name.into(),
            fps: 30.0,
            frames: frames as u32,
            targets: t as u32,
            weights: std::sync::Arc::new(weights),
            joints: None,
        });
    }
    rig
}

#[cfg(test)]
mod tests {
    #[test]
    fn the_skinned_head_is_valid_and_its_joints_move_eyes_and_jaw() {
        let rig = super::skinned_head();
        rig.validate().expect("valid");
        let (skinned, rigid) = rig.skinned_and_rigid_vertices();
        assert_eq!(
            rigid, 444,
            "two eyeballs of 222 vertices each follow one bone"
        );
        assert_eq!(skinned, 6818);
        // Some face vertices follow the jaw and some the neck.
        let face = rig.primitives[0].skin.as_ref().expect("skin");
        let follows = |bone: u16| {
            face.joints
                .iter()
                .zip(&face.weights)
                .filter(|(j, w)| j.iter().zip(w.iter()).any(|(&j, &w)| j == bone && w > 0.5))
                .count()
        };
        assert!(follows(2) > 100, "jaw: {}", follows(2));
        assert!(follows(0) > 100, "neck: {}", follows(0));
        assert!(follows(1) > 3000, "head: {}", follows(1));
    }

    #[test]
    fn paper_scale_rig_is_valid_localized_and_deterministic() {
        let a = super::paper_scale_rig();
        a.validate().expect("valid");
        assert_eq!(a.vertex_count(), super::PAPER_VERTICES);
        assert_eq!(a.targets.len(), super::PAPER_TARGETS);
        assert!(
            a.target_nnz()
                .iter()
                .all(|&n| n > 0 && n <= super::PAPER_VERTICES / 10)
        );
        assert_eq!(a, super::paper_scale_rig());
    }
}
