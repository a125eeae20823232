//! Regions of a rig: where its face is, in rig space at rest, for a camera that frames faces
//! (`"camera": {"frame": "faces"}` of `POST /v1/crowd/render`).
//!
//! A file says nothing about where a face is, so the region is inferred, from the first of
//! these that gives one:
//! 1. a skeleton's head joint ([`head_node`]): the box of the vertices whose skin weights on
//!    that node and its descendants sum to at least [`HEAD_WEIGHT`] — the head and what hangs
//!    from it (jaw, eyes), without the neck and body that follow it only partly or not at all.
//!    Long hair and some collars hang from the head joint to the shoulders, so where targets
//!    move part of that box (a face kit's do: the chin is the lowest point they move), its
//!    bottom is raised to that point less [`CHIN_MARGIN`] of what is left (the top of the head
//!    and the sides stay);
//! 2. the box of the vertices that some morph target moves by more than [`MOVED_FRACTION`] of
//!    that target's largest displacement: blendshapes are made for faces, and a face kit's
//!    targets leave the back of the head, the neck and the shoulders still (the threshold is
//!    relative so that a target's noise, not its motion, is what is left out);
//! 3. the whole rig's box.
//!
//! The walk is one pass over the skin influences, or two over the stored deltas, and
//! allocates a flag per skeleton node and a float per weight channel (both bounded by the
//! rig's own limits); callers keep the result, a few floats, per rig version.

use glam::Vec3;

use super::{Aabb, NO_PARENT, Rig, Skeleton};

/// Least share of a vertex's skin weights on the head joint and its descendants for the vertex
/// to be part of the face region.
pub const HEAD_WEIGHT: f32 = 0.5;

/// Room left below the lowest vertex the targets move, when it trims a head joint's box, as a
/// fraction of the trimmed box's height: the chin's underside and a little neck.
pub const CHIN_MARGIN: f32 = 0.08;

/// A vertex is in the target region when some target moves it by more than this fraction of
/// the largest displacement of that target.
pub const MOVED_FRACTION: f32 = 0.01;

/// Where a rig's face region came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RegionSource {
    /// The vertices weighted to the head joint, skeleton node `node`, and its descendants.
    HeadJoint {
        /// Index of the head joint in [`Skeleton::nodes`].
        node: u32,
    },
    /// The vertices the morph targets move.
    Targets,
    /// The whole rig: neither a head joint nor a target gave a region.
    Whole,
}

/// A box in rig space at rest, and how it was found.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Region {
    /// The box.
    pub bbox: Aabb,
    /// What it holds.
    pub source: RegionSource,
}

/// Whether a node name names a head joint: `head`, whole, as the name or as one of its tokens
/// (runs of letters and digits), ignoring case. So `Head`, `J_Bip_C_Head`, `mixamorig:Head`,
/// `Bip01_Head` and `head.001` do, and `HeadTop_End`, `forehead` and `Headphones` do not
/// (the top of the head and other things named after it are not the joint the face follows).
pub fn is_head_name(name: &str) -> bool {
    name.split(|c: char| !c.is_alphanumeric())
        .any(|token| token.eq_ignore_ascii_case("head"))
}

/// The head joint of a skeleton: the first node, parents before children, whose name
/// [`is_head_name`]. A parent comes first, so a `Head` wins over its own `Head_end`.
pub fn head_node(skeleton: &Skeleton) -> Option<u32> {
    skeleton
        .nodes
        .iter()
        .position(|n| is_head_name(&n.name))
        .map(|i| i as u32)
}

impl Rig {
    /// The rig's face region (see the module documentation). Cheap enough to compute once per
    /// rig version, not per request: callers cache it.
    pub fn face_region(&self) -> Region {
        if let Some(sk) = &self.skeleton
            && let Some(node) = head_node(sk)
            && let Some(mut bbox) = head_box(self, sk, node)
        {
            if let Some(moved) = moved_box(self) {
                let chin = moved.min.y;
                if chin > bbox.min.y && chin < bbox.max.y {
                    bbox.min.y = (chin - CHIN_MARGIN * (bbox.max.y - chin)).max(bbox.min.y);
                }
            }
            return Region {
                bbox,
                source: RegionSource::HeadJoint { node },
            };
        }
        if let Some(bbox) = moved_box(self) {
            return Region {
                bbox,
                source: RegionSource::Targets,
            };
        }
        Region {
            bbox: self.bbox(),
            source: RegionSource::Whole,
        }
    }
}

/// A growing box; `None` until a point is added.
#[derive(Default)]
struct Bounds(Option<Aabb>);

impl Bounds {
    fn add(&mut self, p: Vec3) {
        let b = self.0.get_or_insert(Aabb { min: p, max: p });
        b.min = b.min.min(p);
        b.max = b.max.max(p);
    }
}

/// The box of the vertices whose weights on `head` and the nodes under it sum to at least
/// [`HEAD_WEIGHT`]; `None` when no vertex does.
fn head_box(rig: &Rig, sk: &Skeleton, head: u32) -> Option<Aabb> {
    // Parents come before children, so one pass marks every descendant.
    let mut under = vec![false; sk.nodes.len()];
    for i in 0..sk.nodes.len() {
        let parent = sk.nodes[i].parent;
        under[i] = i as u32 == head
            || (parent != NO_PARENT && under.get(parent as usize).copied().unwrap_or(false));
    }
    let bone_under = |bone: u16| {
        sk.bones
            .get(bone as usize)
            .and_then(|b| under.get(b.node as usize))
            .copied()
            .unwrap_or(false)
    };
    let mut bounds = Bounds::default();
    for p in rig.primitives.iter() {
        let Some(skin) = &p.skin else { continue };
        for ((pos, joints), weights) in p.positions.iter().zip(&skin.joints).zip(&skin.weights) {
            let on_head: f32 = joints
                .iter()
                .zip(weights)
                .filter(|&(&j, &w)| w != 0.0 && bone_under(j))
                .map(|(_, &w)| w)
                .sum();
            if on_head >= HEAD_WEIGHT {
                bounds.add(*pos);
            }
        }
    }
    bounds.0
}

/// The box of the vertices some target moves by more than [`MOVED_FRACTION`] of that target's
/// largest displacement (over every primitive it drives); `None` when no target moves any.
fn moved_box(rig: &Rig) -> Option<Aabb> {
    let mut largest = vec![0f32; rig.targets.len()];
    for t in rig.primitives.iter().flat_map(|p| p.targets.iter()) {
        if let Some(m) = largest.get_mut(t.target as usize) {
            *m = t.positions.iter().map(|d| d.length()).fold(*m, f32::max);
        }
    }
    let mut bounds = Bounds::default();
    for p in rig.primitives.iter() {
        for t in &p.targets {
            let Some(&m) = largest.get(t.target as usize) else {
                continue;
            };
            if m <= 0.0 {
                continue;
            }
            let cut = m * MOVED_FRACTION;
            for (&v, d) in t.vertices.iter().zip(&t.positions) {
                if d.length() > cut
                    && let Some(&pos) = p.positions.get(v as usize)
                {
                    bounds.add(pos);
                }
            }
        }
    }
    bounds.0
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rig::{Bone, Influences, Lod, Primitive, SkelNode, SparseTarget, Trs};
    use std::sync::Arc;

    #[test]
    fn head_names_match_whole_tokens_only() {
        for name in [
            "Head",
            "head",
            "HEAD",
            "J_Bip_C_Head",
            "mixamorig:Head",
            "Bip01_Head",
            "Bip01 Head",
            "head.001",
            "Armature|Head",
            "Head_1",
        ] {
            assert!(is_head_name(name), "{name} names a head joint");
        }
        for name in [
            "HeadTop_End",
            "HeadTop",
            "mixamorig:HeadTop_End",
            "forehead",
            "Forehead_L",
            "Headphones",
            "Neck",
            "",
            "ahead",
            "Hea",
        ] {
            assert!(!is_head_name(name), "{name} does not name a head joint");
        }
    }

    fn node(name: &str, parent: u32) -> SkelNode {
        SkelNode {
            name: name.into(),
            parent,
            rest: Trs::default(),
        }
    }

    /// Vertex `i` of `n`: `(i, 7i mod n, 3i mod n)`. Every axis is a different order of the
    /// vertices, so a box of some of them tells which are in it (one too many or too few moves
    /// a side): a test of the box is a test of the set.
    fn spot(i: usize, n: usize) -> Vec3 {
        Vec3::new(i as f32, ((7 * i) % n) as f32, ((3 * i) % n) as f32)
    }

    /// The box of vertices `of` of `n` (see [`spot`]).
    fn box_of(of: &[usize], n: usize) -> Aabb {
        let mut b = Bounds::default();
        for &i in of {
            b.add(spot(i, n));
        }
        b.0.expect("some vertices")
    }

    /// One primitive of a vertex per entry of `influences` (its (bone, weight) pairs), at
    /// [`spot`]s, skinned to `nodes` (one bone each, in node order).
    fn column(nodes: Vec<SkelNode>, influences: &[&[(u16, f32)]]) -> Rig {
        let n = influences.len();
        let positions: Vec<Vec3> = (0..n).map(|i| spot(i, n)).collect();
        let mut skin = Influences {
            joints: Vec::new(),
            weights: Vec::new(),
        };
        for pairs in influences {
            let (mut j, mut w) = ([0u16; 4], [0f32; 4]);
            for (k, &(b, x)) in pairs.iter().enumerate() {
                j[k] = b;
                w[k] = x;
            }
            skin.joints.push(j);
            skin.weights.push(w);
        }
        let bones = (0..nodes.len() as u32)
            .map(|node| Bone {
                node,
                bind: glam::Mat4::IDENTITY.to_cols_array(),
            })
            .collect();
        Rig {
            name: "column".into(),
            targets: Vec::new(),
            default_weights: Vec::new(),
            primitives: Arc::new(vec![Primitive {
                name: "column/0".into(),
                normals: vec![Vec3::Z; positions.len()],
                positions,
                normals_from_file: false,
                tangents: None,
                indices: Vec::new(),
                targets: Vec::new(),
                base_color: Primitive::default_base_color(),
                skin: Some(skin),
                look: Default::default(),
            }]),
            clips: Vec::new(),
            lod: Lod::by_delta_energy(&[], 0),
            skeleton: Some(Arc::new(Skeleton {
                nodes,
                bones,
                map: None,
            })),
            import_notes: Vec::new(),
            appearance: None,
        }
    }

    #[test]
    fn the_head_region_holds_the_vertices_mostly_on_the_head_and_its_children() {
        // Hips → {forehead, Neck → {HeadTop, mixamorig:Head → {Jaw, HeadTop_End}}}: neither
        // `forehead` nor `HeadTop` is the head, and their vertices are not in its region.
        let nodes = vec![
            node("Hips", NO_PARENT),
            node("forehead", 0),
            node("Neck", 0),
            node("HeadTop", 2),
            node("mixamorig:Head", 2),
            node("Jaw", 4),
            node("HeadTop_End", 4),
        ];
        let rig = column(
            nodes,
            &[
                &[(0, 1.0)],
                &[(0, 1.0)],
                &[(3, 1.0)],
                &[(1, 1.0)],
                // Half on the neck, half on the hips: out.
                &[(2, 0.5), (0, 0.5)],
                // A third each on the neck, the head and the jaw: 2/3 under the head, in.
                &[(2, 1.0 / 3.0), (4, 1.0 / 3.0), (5, 1.0 / 3.0)],
                &[(5, 1.0)],
                // 0.4 on the head: out.
                &[(4, 0.4), (2, 0.6)],
                // Exactly half on HeadTop_End (under the head), half on HeadTop: in.
                &[(6, 0.5), (3, 0.5)],
                &[(4, 1.0)],
            ],
        );
        let sk = rig.skeleton.as_ref().expect("skinned");
        assert_eq!(head_node(sk), Some(4), "the head is mixamorig:Head");
        let r = rig.face_region();
        assert_eq!(r.source, RegionSource::HeadJoint { node: 4 });
        assert_eq!(r.bbox, box_of(&[5, 6, 8, 9], 10));
    }

    #[test]
    fn targets_moving_the_face_raise_the_head_boxs_bottom_to_the_chin() {
        // Head → everything: five vertices on the head at y = 7i mod 5 (0, 2, 4, 1, 3); a
        // target moves vertices 1 and 2 (y 2 and 4), so the chin is at 2 and hair hanging to
        // y = 0 is left out, bar the margin.
        let mut rig = column(
            vec![node("Hips", NO_PARENT), node("Head", 0)],
            &[&[(1u16, 1.0f32)][..]; 5],
        );
        let head = rig.face_region().bbox;
        assert_eq!(head, box_of(&[0, 1, 2, 3, 4], 5));
        let mut prims = rig.primitives.as_ref().clone();
        prims[0].targets = vec![SparseTarget {
            target: 0,
            vertices: vec![1, 2],
            positions: vec![Vec3::Z * 0.1; 2],
            normals: None,
            tangents: None,
        }];
        rig.primitives = Arc::new(prims);
        rig.targets = vec!["smile".into()];
        rig.default_weights = vec![0.0];
        let r = rig.face_region();
        assert_eq!(r.source, RegionSource::HeadJoint { node: 1 });
        let want_min_y = 2.0 - CHIN_MARGIN * (4.0 - 2.0);
        assert!((r.bbox.min.y - want_min_y).abs() < 1e-6, "{r:?}");
        assert_eq!(
            (r.bbox.max, r.bbox.min.x, r.bbox.min.z),
            (head.max, head.min.x, head.min.z)
        );
        // Targets that move below the head box (a body's) leave it as it is.
        let mut prims = rig.primitives.as_ref().clone();
        prims[0].targets[0].vertices = vec![0, 2];
        rig.primitives = Arc::new(prims);
        assert_eq!(rig.face_region().bbox, head);
    }

    #[test]
    fn without_a_head_joint_or_weight_on_it_the_targets_then_the_whole_rig_give_the_region() {
        // No node named head: the whole rig (no targets either).
        let rig = column(
            vec![node("Hips", NO_PARENT), node("HeadTop_End", 0)],
            &[&[(0, 1.0)], &[(1, 1.0)], &[(1, 1.0)]],
        );
        assert_eq!(rig.face_region().source, RegionSource::Whole);
        assert_eq!(rig.face_region().bbox, rig.bbox());
        // A head no vertex follows by half: not a region either.
        let mut rig = column(
            vec![node("Hips", NO_PARENT), node("Head", 0)],
            &[
                &[(0, 1.0)],
                &[(0, 0.6), (1, 0.4)],
                &[(0, 0.51), (1, 0.49)],
                &[(0, 1.0)],
                &[(0, 1.0)],
            ],
        );
        assert_eq!(rig.face_region().source, RegionSource::Whole);
        // Targets: the vertices some target moves by more than 1 % of that target's largest
        // move, over every primitive it drives. Target 0 moves vertex 3 of the second
        // primitive by 1 (its largest), vertex 1 of the first by 0.02 (in), vertex 0 of the
        // first and vertex 4 of the second by 0.005 (out); target 1 moves only vertex 2 of the
        // first, by 1e-3 (its own largest: in, though tiny).
        let delta = |v: &[u32], d: &[f32]| SparseTarget {
            target: 0,
            vertices: v.to_vec(),
            positions: d.iter().map(|&x| Vec3::new(0.0, x, 0.0)).collect(),
            normals: None,
            tangents: None,
        };
        let mut prims = rig.primitives.as_ref().clone();
        prims[0].targets = vec![
            delta(&[0, 1], &[0.005, 0.02]),
            SparseTarget {
                target: 1,
                ..delta(&[2], &[1e-3])
            },
        ];
        let mut second = prims[0].clone();
        second.name = "column/1".into();
        // Its vertices are the first's, 10 further along x.
        second.positions = second
            .positions
            .iter()
            .map(|p| *p + Vec3::X * 10.0)
            .collect();
        second.targets = vec![delta(&[3, 4], &[1.0, 0.005])];
        prims.push(second);
        rig.primitives = Arc::new(prims);
        rig.targets = vec!["a".into(), "b".into()];
        rig.default_weights = vec![0.0; 2];
        let r = rig.face_region();
        assert_eq!(r.source, RegionSource::Targets);
        let mut want = box_of(&[1, 2], 5);
        let third = spot(3, 5) + Vec3::X * 10.0;
        want.min = want.min.min(third);
        want.max = want.max.max(third);
        assert_eq!(r.bbox, want);
        // The skeleton's head, once followed, wins over the targets.
        let mut prims = rig.primitives.as_ref().clone();
        if let Some(s) = prims[0].skin.as_mut() {
            s.joints[4] = [1, 0, 0, 0];
            s.weights[4] = [1.0, 0.0, 0.0, 0.0];
        }
        rig.primitives = Arc::new(prims);
        let r = rig.face_region();
        assert_eq!(r.source, RegionSource::HeadJoint { node: 1 });
        assert_eq!(r.bbox, box_of(&[4], 5));
    }

    #[test]
    fn the_embedded_heads_regions_are_their_faces() {
        // Unskinned: the targets move the face, not the back of the head.
        let rig = crate::embedded::default_rig();
        let whole = rig.bbox();
        let r = rig.face_region();
        assert_eq!(r.source, RegionSource::Targets);
        assert!(r.bbox.min.cmpge(whole.min).all() && r.bbox.max.cmple(whole.max).all());
        assert!(
            r.bbox.min.z > whole.min.z,
            "the back of the head is still: {r:?} in {whole:?}"
        );
        // Skinned: the neck's base follows the neck, not the head.
        let rig = crate::synthetic::skinned_head();
        let r = rig.face_region();
        let sk = rig.skeleton.as_ref().expect("skinned");
        assert!(
            matches!(r.source, RegionSource::HeadJoint { node } if sk.nodes[node as usize].name == "Head"),
            "{r:?}"
        );
        assert!(
            r.bbox.min.y > whole.min.y && r.bbox.max.y <= whole.max.y,
            "{r:?} in {whole:?}"
        );
    }
}
