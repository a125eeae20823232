//! Mesh levels as rigs: a simplified mesh level of a rig (kept vertices and their triangles,
//! built by the `lod` module) turned into the ordinary [`Rig`] every engine evaluates.
//!
//! The derived rig keeps only the level's original vertices, in ascending order, with every
//! target's deltas restricted to them (a target left with none is dropped from that primitive).
//! Targets, default weights, clips and the LOD order are the full rig's, so weights and levels
//! mean the same; the derived rig has no mesh levels of its own.

use std::sync::Arc;

use glam::Vec3;

use super::{Lod, MeshLevel, Primitive, Rig, RigError, SparseTarget};

fn mismatch(problem: String) -> RigError {
    RigError::Inconsistent {
        primitive: String::new(),
        problem: format!("mesh level does not fit the rig: {problem}"),
    }
}

impl MeshLevel {
    /// The rig this mesh level is evaluated as: per primitive only the kept vertices (neutral
    /// positions, normals, tangents taken over), the level's triangles, and every target's
    /// deltas restricted to the kept vertices. Refused when the level does not fit `rig`.
    pub fn derive_rig(&self, rig: &Rig) -> Result<Rig, RigError> {
        let level = self;
        if level.primitives.len() != rig.primitives.len() {
            return Err(mismatch(format!(
                "{} primitives, rig has {}",
                level.primitives.len(),
                rig.primitives.len()
            )));
        }
        let mut primitives = Vec::with_capacity(rig.primitives.len());
        for (p, l) in rig.primitives.iter().zip(&level.primitives) {
            let n = p.positions.len();
            if l.vertices.last().is_some_and(|&v| v as usize >= n)
                || l.vertices.windows(2).any(|w| w[0] >= w[1])
            {
                return Err(mismatch(format!(
                    "primitive {:?}: kept vertices out of range or not ascending",
                    p.name
                )));
            }
            let mut remap = vec![u32::MAX; n];
            for (new, &old) in l.vertices.iter().enumerate() {
                remap[old as usize] = new as u32;
            }
            let pick =
                |a: &[Vec3]| -> Vec<Vec3> { l.vertices.iter().map(|&v| a[v as usize]).collect() };
            let targets = p
                .targets
                .iter()
                .filter_map(|t| {
                    let keep: Vec<usize> = (0..t.vertices.len())
                        .filter(|&k| remap[t.vertices[k] as usize] != u32::MAX)
                        .collect();
                    if keep.is_empty() {
                        return None;
                    }
                    let sub = |a: &[Vec3]| -> Vec<Vec3> { keep.iter().map(|&k| a[k]).collect() };
                    Some(SparseTarget {
                        target: t.target,
                        vertices: keep
                            .iter()
                            .map(|&k| remap[t.vertices[k] as usize])
                            .collect(),
                        positions: sub(&t.positions),
                        normals: t.normals.as_deref().map(sub),
                        tangents: t.tangents.as_deref().map(sub),
                    })
                })
                .collect();
            primitives.push(Primitive {
                name: p.name.clone(),
                positions: pick(&p.positions),
                normals: pick(&p.normals),
                normals_from_file: p.normals_from_file,
                tangents: p
                    .tangents
                    .as_ref()
                    .map(|t| l.vertices.iter().map(|&v| t[v as usize]).collect()),
                indices: l.indices.clone(),
                targets,
                base_color: p.base_color,
                skin: p.skin.as_ref().map(|s| super::Influences {
                    joints: l.vertices.iter().map(|&v| s.joints[v as usize]).collect(),
                    weights: l.vertices.iter().map(|&v| s.weights[v as usize]).collect(),
                }),
                look: p.look.pick(&l.vertices),
            });
        }
        let lod = Lod {
            levels: rig
                .lod
                .levels
                .iter()
                .map(|lv| super::LodLevel::shapes(lv.shapes))
                .collect(),
            meshes: Vec::new(),
            pca: Vec::new(),
            ..rig.lod.clone()
        };
        let derived = Rig {
            name: format!(
                "{}@{}%",
                rig.name,
                (level.triangle_fraction * 100.0).round()
            ),
            targets: rig.targets.clone(),
            default_weights: rig.default_weights.clone(),
            primitives: Arc::new(primitives),
            clips: rig.clips.clone(),
            lod,
            skeleton: rig.skeleton.clone(),
            import_notes: rig.import_notes.clone(),
            appearance: rig.appearance.clone(),
        };
        derived.validate()?;
        Ok(derived)
    }
}

/// The derived rig for every mesh level of `rig.lod`, in order.
pub fn mesh_level_rigs(rig: &Rig) -> Result<Vec<Rig>, RigError> {
    rig.lod.meshes.iter().map(|m| m.derive_rig(rig)).collect()
}
