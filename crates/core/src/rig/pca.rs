//! The variable-PCA form of a rig's deltas (GPU Gems 3 ch. 15's "variable PCA", applied to the
//! blendshapes rather than to captured frames): per region of vertices, `C_r` components
//! instead of the `K` shapes, so that `Δ_r · w ≈ B_r · (M_r · w)`.
//!
//! Regions are runs of consecutive vertices of one primitive (meshes list neighbouring
//! vertices near each other, and a run is contiguous in the output, so evaluating one needs no
//! gather or scatter); each has its own component count, so regions many shapes move in
//! different ways (eyes, mouth) keep more components than regions few shapes touch. A head
//! costs `Σ_r C_r·K` multiply-adds for its coefficients and `Σ_r 3·n_r·C_r` for its positions,
//! against `3·Σ_k nnz_k` for the sparse shapes; `crowdmorph_engine::lod::pca` builds the form within an
//! error budget and says where it is smaller and faster. Pure data: the engines evaluate it
//! (`engine::cpu::pca`, `crates/engine/shaders/pca.wgsl`).

use std::sync::Arc;

use glam::Vec3;
use serde::{Deserialize, Serialize};

use super::{Clip, Lod, LodLevel, Primitive, Rig, RigError, SparseTarget};

/// One region of a [`DeltaPca`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct PcaRegion {
    /// Its first vertex (rig-wide index).
    pub first: u32,
    /// Its vertices, consecutive from `first`.
    pub count: u32,
    /// Its components `C_r` (0: no shape moves it).
    pub components: u32,
    /// Offset in [`DeltaPca::basis`] of its first component (each `3 × count` floats,
    /// x, y, z per vertex).
    pub basis: u32,
    /// Index of its first component among all of the form's components: its rows of
    /// [`DeltaPca::map`] start at `coef × targets`, and a head's coefficients are laid out the
    /// same way.
    pub coef: u32,
}

/// The deltas of a rig as regional principal components.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct DeltaPca {
    /// Weight channels `K`.
    pub targets: u32,
    /// Rig-wide vertices (all primitives, in the rig's order).
    pub vertices: u32,
    /// The error budget it was built within, as a fraction of the rig's diagonal.
    pub max_error: f32,
    /// Regions, covering every vertex in order.
    pub regions: Vec<PcaRegion>,
    /// Components of every region (see [`PcaRegion::basis`]).
    pub basis: Vec<f32>,
    /// Per component, its row over the `K` channels: coefficient = row · w.
    pub map: Vec<f32>,
}

impl DeltaPca {
    /// All regions' components together (the length of one head's coefficient vector).
    pub fn components(&self) -> usize {
        self.map.len() / (self.targets as usize).max(1)
    }

    /// Bytes it stores: basis, map and regions.
    pub fn bytes(&self) -> usize {
        4 * (self.basis.len() + self.map.len()) + 20 * self.regions.len()
    }

    /// Multiply-adds per head: coefficients, then positions.
    pub fn madds_per_head(&self) -> usize {
        self.map.len() + self.basis.len()
    }

    /// Pass `pca_coefficients`: each component's coefficient `map_c · w` (only the channels
    /// with a non-zero weight are visited).
    pub fn coefficients(&self, weights: &[f32]) -> Vec<f32> {
        let k = self.targets as usize;
        let mut coef = vec![0f32; self.components()];
        for (t, &w) in weights.iter().enumerate().take(k) {
            if w == 0.0 {
                continue;
            }
            for (c, x) in coef.iter_mut().enumerate() {
                *x += self.map[c * k + t] * w;
            }
        }
        coef
    }

    /// The rig this form is evaluated as, by either engine's ordinary kernels: the same
    /// primitives (neutral, triangles), each component a target over its region's vertices
    /// (its basis as the deltas, no normal deltas, so normals are recomputed from the blended
    /// positions), and every clip mapped into coefficients (`C × frames`: blends stay linear,
    /// so blending coefficient frames is blending the weights). Its LOD table has `rig`'s
    /// levels, each evaluating every component.
    pub fn derive_rig(&self, rig: &Rig) -> Result<Rig, RigError> {
        let bad = |problem: String| RigError::Inconsistent {
            primitive: String::new(),
            problem: format!("PCA level does not fit the rig: {problem}"),
        };
        self.validate().map_err(bad)?;
        if self.targets as usize != rig.targets.len()
            || self.vertices as usize != rig.vertex_count()
        {
            return Err(bad(format!(
                "built for {} channels and {} vertices",
                self.targets, self.vertices
            )));
        }
        let offsets = rig.vertex_offsets();
        let mut primitives = Vec::with_capacity(rig.primitives.len());
        let mut regions = self.regions.iter().peekable();
        for (p, &first) in rig.primitives.iter().zip(&offsets) {
            let end = first + p.positions.len();
            let mut targets = Vec::new();
            while let Some(r) = regions.next_if(|r| (r.first as usize) < end) {
                let lo = r.first as usize - first;
                if lo + r.count as usize > p.positions.len() {
                    return Err(bad(format!(
                        "region at vertex {} crosses primitives",
                        r.first
                    )));
                }
                let n3 = 3 * r.count as usize;
                for c in 0..r.components as usize {
                    let b = &self.basis[r.basis as usize + c * n3..][..n3];
                    targets.push(SparseTarget {
                        target: r.coef + c as u32,
                        vertices: (lo as u32..lo as u32 + r.count).collect(),
                        positions: b.chunks(3).map(Vec3::from_slice).collect(),
                        normals: None,
                        tangents: None,
                    });
                }
            }
            primitives.push(Primitive {
                name: p.name.clone(),
                positions: p.positions.clone(),
                normals: p.normals.clone(),
                normals_from_file: p.normals_from_file,
                tangents: p.tangents.clone(),
                indices: p.indices.clone(),
                targets,
                base_color: p.base_color,
                skin: p.skin.clone(),
                look: p.look.clone(),
            });
        }
        let c = self.components();
        let mut clips = self.map_clips(&rig.clips)?;
        // The joint tables do not depend on the deltas' basis: shared as they are.
        for (c, o) in clips.iter_mut().zip(&rig.clips) {
            c.joints.clone_from(&o.joints);
        }
        let derived = Rig {
            name: format!("{}@pca{:.0e}", rig.name, self.max_error),
            targets: (0..c).map(|i| format!("pca{i}")).collect(),
            default_weights: self.coefficients(&rig.default_weights),
            primitives: Arc::new(primitives),
            clips,
            lod: Lod {
                order: (0..c as u32).collect(),
                levels: rig
                    .lod
                    .levels
                    .iter()
                    .map(|_| LodLevel::shapes(c as u32))
                    .collect(),
                method: "pca".into(),
                pinned: Vec::new(),
                meshes: Vec::new(),
                pca: Vec::new(),
            },
            skeleton: rig.skeleton.clone(),
            import_notes: rig.import_notes.clone(),
            appearance: rig.appearance.clone(),
        };
        derived.validate()?;
        Ok(derived)
    }

    /// `clips` (of the form's rig) as the derived rig plays them: each frame's weights mapped
    /// into the coefficients (`C × frames`).
    pub fn map_clips(&self, clips: &[Clip]) -> Result<Vec<Clip>, super::ClipError> {
        let c = self.components();
        clips
            .iter()
            .map(|clip| {
                let n = clip.frames as usize;
                let mut table = vec![0f32; c * n];
                let mut w = vec![0f32; self.targets as usize];
                for f in 0..n {
                    clip.frame_weights(f as u32, &mut w);
                    for (j, x) in self.coefficients(&w).into_iter().enumerate() {
                        table[j * n + f] = x;
                    }
                }
                Clip::new(clip.name.clone(), clip.fps, c, n, table)
            })
            .collect()
    }

    /// Checks that the arrays agree with the regions (a form built elsewhere, or damaged).
    pub fn validate(&self) -> Result<(), String> {
        let k = self.targets as usize;
        let mut next = 0u32;
        let mut coef = 0u32;
        let mut basis = 0u64;
        for (i, r) in self.regions.iter().enumerate() {
            if r.first != next || r.coef != coef || u64::from(r.basis) != basis {
                return Err(format!("region {i} is not where the one before it ends"));
            }
            next = r.first.checked_add(r.count).ok_or("region overflow")?;
            coef = coef.checked_add(r.components).ok_or("component overflow")?;
            basis += 3 * u64::from(r.count) * u64::from(r.components);
        }
        if next != self.vertices {
            return Err(format!(
                "regions cover {next} vertices, the rig has {}",
                self.vertices
            ));
        }
        if basis != self.basis.len() as u64 || coef as usize * k != self.map.len() {
            return Err("basis or map size disagrees with the regions".into());
        }
        Ok(())
    }
}

/// The rigs of `rig`'s PCA levels (`rig.lod.pca`), in order.
pub fn pca_level_rigs(rig: &Rig) -> Result<Vec<Rig>, RigError> {
    rig.lod.pca.iter().map(|f| f.derive_rig(rig)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn form() -> DeltaPca {
        DeltaPca {
            targets: 2,
            vertices: 3,
            max_error: 1e-3,
            regions: vec![
                PcaRegion {
                    first: 0,
                    count: 2,
                    components: 1,
                    basis: 0,
                    coef: 0,
                },
                PcaRegion {
                    first: 2,
                    count: 1,
                    components: 0,
                    basis: 6,
                    coef: 1,
                },
            ],
            basis: vec![0.5; 6],
            map: vec![1.0, 0.0],
        }
    }

    #[test]
    fn a_form_whose_arrays_disagree_with_its_regions_is_refused() {
        form().validate().expect("consistent");
        assert_eq!(form().coefficients(&[0.25, 9.0]), vec![0.25]);
        let mut f = form();
        f.regions[1].first = 3;
        assert!(f.validate().is_err(), "a gap between regions");
        let mut f = form();
        f.basis.pop();
        assert!(f.validate().is_err(), "a short basis");
        let mut f = form();
        f.vertices = u32::MAX;
        assert!(f.validate().is_err(), "more vertices than regions cover");
        let mut f = form();
        f.regions[0].count = u32::MAX;
        assert!(f.validate().is_err(), "a region past u32");
        let mut f = form();
        f.map.push(1.0);
        assert!(f.validate().is_err(), "a map row too many");
    }
}
