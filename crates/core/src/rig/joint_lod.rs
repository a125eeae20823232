//! Level of detail for joints: which nodes a far head may hold at rest.
//!
//! Shapes are cut by an importance order (`lod.rs`); joints are cut by what they move. A
//! node's *effect* is the farthest it can carry a vertex away from where its parent puts it:
//! the largest `w × |p − pivot|` over the vertices it moves (`w` the share of the vertex's bone
//! weights on bones at or under the node, `p` the vertex at rest, `pivot` the node's rest
//! origin), times the chord `2 sin(θ/2)` of the largest angle θ it turns through — the largest
//! turn from rest any clip gives it, and never less than [`REFERENCE_TURN`], since a request
//! may turn it too — plus the largest distance a clip translates it from rest. An eye moves its eyeball by about its
//! radius times its turn; a head or a jaw moves half the face.
//!
//! Level `l ≥ 1` holds at rest the nodes whose effect is at most [`drop_fraction`]`(l)` of the
//! rig's bounding-box diagonal: their clip channels and any request's overrides are replaced by
//! their rest transform, so heads that differ only by them are one job. The dropped nodes and
//! the error bound (their largest effect) are stated in the LOD report. Level 0 keeps every
//! node.

use glam::{Mat4, Quat, Vec3};

use super::{JointPose, JointSet, Rig, Skeleton};

/// The turn assumed for a node that no clip turns (or turns less): about 20°, an eye's or a
/// head's usual range, which a request's override may give it.
pub const REFERENCE_TURN: f32 = 0.35;

/// Most (vertex influence, ancestor) steps the effect measure takes, each O(1); past it, every
/// node counts as moving everything (never dropped), so a hostile chain of 65,535 nodes under
/// many vertices costs no more than this.
pub const MAX_EFFECT_STEPS: usize = 1 << 24;

/// Share of the diagonal under which level `l` drops a node: 0 at level 0, then 0.25 %,
/// 0.5 %, 1 %, 2 %, ... (× 2 a level).
pub fn drop_fraction(level: usize) -> f32 {
    if level == 0 {
        0.0
    } else {
        0.0025 * 2f32.powi((level as i32 - 1).min(8))
    }
}

/// What each node moves and, per LOD level, the nodes it holds at rest.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct JointLod {
    /// Per skeleton node, its effect in rig units (infinite where not measured).
    pub effect: Vec<f32>,
    /// The rig's bounding-box diagonal the thresholds are relative to.
    pub diagonal: f32,
    /// Per LOD level, the nodes held at rest, ascending.
    pub dropped: Vec<Vec<u32>>,
    /// Per LOD level, the overrides that hold them (shared by every job of the level).
    rest: Vec<JointPose>,
    /// Per node, the largest translation length and absolute scale it has at rest or in a
    /// clip ([`Skeleton::extents`]): the q16 box holds every pose within them, so an
    /// override may not exceed them.
    pub extents: (Vec<f64>, Vec<f64>),
}

/// The joints one LOD level animates.
#[derive(Clone, Copy, Debug)]
pub struct JointLevel<'a> {
    dropped: &'a [u32],
    rest: Option<&'a JointPose>,
}

impl JointLevel<'_> {
    /// A level that keeps every joint.
    pub const ALL: JointLevel<'static> = JointLevel {
        dropped: &[],
        rest: None,
    };

    /// Whether the level animates `node`.
    pub fn keeps(&self, node: u32) -> bool {
        self.dropped.binary_search(&node).is_err()
    }

    /// A job's overrides at this level: those of kept nodes, and rest for each dropped one.
    pub fn joints(&self, requested: &JointPose) -> JointPose {
        match self.rest {
            None => requested.clone(),
            Some(rest) if requested.is_none() => rest.clone(),
            Some(rest) => {
                let mut sets: Vec<JointSet> = requested
                    .sets()
                    .iter()
                    .copied()
                    .filter(|s| self.keeps(s.node))
                    .collect();
                sets.extend_from_slice(rest.sets());
                JointPose::new(sets)
            }
        }
    }
}

impl JointLod {
    /// Measures `rig`'s nodes and decides its levels (nothing without a skeleton).
    pub fn of(rig: &Rig) -> JointLod {
        let Some(sk) = &rig.skeleton else {
            return JointLod::default();
        };
        let diagonal = rig.bbox().diagonal();
        let effect = effects(rig, sk);
        let mut dropped = Vec::with_capacity(rig.lod.levels.len());
        let mut rest = Vec::with_capacity(rig.lod.levels.len());
        for l in 0..rig.lod.levels.len() {
            let limit = drop_fraction(l) * diagonal;
            let d: Vec<u32> = (0..sk.nodes.len() as u32)
                .filter(|&n| l > 0 && effect[n as usize] <= limit)
                .collect();
            rest.push(JointPose::new(
                d.iter().map(|&n| JointSet::rest(n)).collect(),
            ));
            dropped.push(d);
        }
        JointLod {
            effect,
            diagonal,
            dropped,
            rest,
            extents: sk.extents(&rig.clips),
        }
    }

    /// The joints level `lod` animates (every one past the table, where requests are refused
    /// anyway).
    pub fn level(&self, lod: u32) -> JointLevel<'_> {
        match (self.dropped.get(lod as usize), self.rest.get(lod as usize)) {
            (Some(d), Some(r)) if !d.is_empty() => JointLevel {
                dropped: d,
                rest: Some(r),
            },
            _ => JointLevel::ALL,
        }
    }

    /// The largest effect among level `lod`'s dropped nodes: how far, at most, holding them
    /// at rest moves a vertex from where the full skeleton would put it (rig units).
    pub fn error(&self, lod: u32) -> f32 {
        self.dropped
            .get(lod as usize)
            .map_or(0.0, |d| d.iter().map(|&n| self.effect[n as usize]).sum())
    }

    /// Bytes it holds.
    pub fn bytes(&self) -> u64 {
        self.effect.len() as u64 * 20
            + self
                .dropped
                .iter()
                .zip(&self.rest)
                .map(|(d, r)| d.len() as u64 * 4 + r.heap_bytes() + 48)
                .sum::<u64>()
    }
}

/// Each node's effect (see the module doc).
fn effects(rig: &Rig, sk: &Skeleton) -> Vec<f32> {
    let nodes = sk.nodes.len();
    // Rest globals: the pivots.
    let mut globals: Vec<Mat4> = Vec::with_capacity(nodes);
    for n in &sk.nodes {
        let local = n.rest.matrix();
        let g = match globals.get(n.parent as usize) {
            Some(p) => *p * local,
            None => local,
        };
        globals.push(g);
    }
    let pivots: Vec<Vec3> = globals.iter().map(|g| g.w_axis.truncate()).collect();
    // Largest turn and shift from rest in any clip.
    let mut turn = vec![REFERENCE_TURN; nodes];
    let mut shift = vec![0f32; nodes];
    for clip in &rig.clips {
        let Some(t) = &clip.joints else { continue };
        for (k, &n) in t.nodes.iter().enumerate() {
            let rest = sk.nodes[n as usize].rest;
            let q0 = Quat::from_array(rest.rotation).normalize();
            for f in 0..t.frames {
                let at = t.at(f, k);
                let q = Quat::from_array(at.rotation).normalize();
                let a = q0.angle_between(q);
                if a.is_finite() {
                    turn[n as usize] = turn[n as usize].max(a);
                }
                let d = (Vec3::from(at.translation) - Vec3::from(rest.translation)).length();
                shift[n as usize] = shift[n as usize].max(d);
            }
        }
    }
    // Lever arms: per vertex (where the rest pose puts it: a skin's bind pose need not be its
    // skeleton's rest), its weight at or under each ancestor of its bones.
    let mut rest_bones = Vec::with_capacity(sk.bones.len());
    sk.bone_matrices(&sk.rest(), &mut Vec::new(), &mut rest_bones);
    let mut lever = vec![0f32; nodes];
    let mut unmeasured = false;
    let mut steps = 0usize;
    // Per node, the current vertex's weight at or under it; `touched` lists the nodes to reset.
    let mut weight_under = vec![0f32; nodes];
    let mut touched: Vec<u32> = Vec::new();
    'outer: for p in rig.primitives.iter() {
        let Some(s) = &p.skin else { continue };
        for ((j, w), pos) in s.joints.iter().zip(&s.weights).zip(&p.positions) {
            for &n in &touched {
                weight_under[n as usize] = 0.0;
            }
            touched.clear();
            for (&b, &wb) in j.iter().zip(w) {
                if wb == 0.0 {
                    continue;
                }
                let mut n = sk.bones[b as usize].node;
                loop {
                    steps += 1;
                    if steps > MAX_EFFECT_STEPS {
                        unmeasured = true;
                        break 'outer;
                    }
                    if weight_under[n as usize] == 0.0 {
                        touched.push(n);
                    }
                    weight_under[n as usize] += wb;
                    let parent = sk.nodes[n as usize].parent;
                    if parent as usize >= nodes {
                        break;
                    }
                    n = parent;
                }
            }
            let at: Vec3 = (0..4)
                .filter(|&k| w[k] != 0.0)
                .map(|k| w[k] * rest_bones[j[k] as usize].point(*pos))
                .sum();
            for &n in &touched {
                let l = weight_under[n as usize].min(1.0) * (at - pivots[n as usize]).length();
                lever[n as usize] = lever[n as usize].max(l);
            }
        }
    }
    (0..nodes)
        .map(|n| {
            if unmeasured {
                f32::INFINITY
            } else {
                lever[n] * 2.0 * (turn[n].min(std::f32::consts::PI) / 2.0).sin() + shift[n]
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn far_levels_drop_the_eyes_and_keep_the_head() {
        let rig = crate::synthetic::skinned_head();
        let lod = JointLod::of(&rig);
        let sk = rig.skeleton.as_ref().expect("skinned");
        let name = |n: u32| sk.nodes[n as usize].name.as_str();
        for (n, e) in lod.effect.iter().enumerate() {
            eprintln!(
                "{}: {:.4} % of the diagonal",
                name(n as u32),
                100.0 * e / lod.diagonal
            );
        }
        assert!(lod.dropped[0].is_empty(), "level 0 keeps every joint");
        let dropped = |l: usize| -> Vec<&str> { lod.dropped[l].iter().map(|&n| name(n)).collect() };
        let last = rig.lod.levels.len() - 1;
        assert!(dropped(last).contains(&"LeftEye"), "{:?}", dropped(last));
        assert!(dropped(last).contains(&"RightEye"), "{:?}", dropped(last));
        for l in 0..=last {
            assert!(!dropped(l).contains(&"Head"), "level {l}: {:?}", dropped(l));
            assert!(!dropped(l).contains(&"Neck"), "level {l}: {:?}", dropped(l));
            // Each level drops at least what the one before it does.
            if l > 0 {
                assert!(
                    lod.dropped[l - 1]
                        .iter()
                        .all(|n| lod.dropped[l].contains(n))
                );
            }
        }
        // Overrides of dropped nodes become rest holds; others pass.
        let look = JointPose::new(vec![
            JointSet::new(3, None, Some([0.0, 0.3, 0.0, 1.0]), None),
            JointSet::new(1, None, Some([0.0, 0.1, 0.0, 1.0]), None),
        ]);
        let far = lod.level(last as u32).joints(&look);
        let near = lod.level(0).joints(&look);
        assert_eq!(near, look);
        assert!(far.sets().iter().any(|s| s.node == 3 && s.rest));
        assert!(far.sets().iter().any(|s| s.node == 1 && !s.rest));
        let other = JointPose::new(vec![
            JointSet::new(3, None, Some([0.0, -0.3, 0.0, 1.0]), None),
            JointSet::new(1, None, Some([0.0, 0.1, 0.0, 1.0]), None),
        ]);
        assert_eq!(
            lod.level(last as u32).joints(&other),
            far,
            "heads that differ only by dropped joints are clones"
        );
    }
}
