//! Blendshape level of detail (Costigan et al. 2016, §2 and §4).
//!
//! Level `l` evaluates only the first `levels[l].shapes` targets of an importance order and
//! skips the rest — the paper's early exit after N_Bs shapes. Level 0 is always all shapes. The
//! order is a permutation of the rig's targets, most important first.
//!
//! A level may also name a simplified mesh ([`MeshLevel`]): a subset of each primitive's
//! vertices with its own triangles, so a far head costs fewer vertices as well as fewer shapes.
//! The mesh levels are pure data here; `crowdmorph_engine::lod` builds them, and `MeshLevel::derive_rig`
//! (in `mesh_level.rs`) derives the rig an engine evaluates for them. Fields added after the first release carry `#[serde(default)]` so that
//! rigs persisted before them still read back; they are always written (no
//! `skip_serializing_if`), so non-self-describing encodings such as bincode stay symmetric.

use serde::{Deserialize, Serialize};

use super::{Primitive, TargetId};

/// `Lod::method` of the quick order every import gets ([`Lod::by_delta_energy`]), before a
/// metric-based order (the `lod` module) replaces it.
pub const IMPORT_LOD_METHOD: &str = "delta-energy";

/// Default LOD table as fractions of the target count: 100 / 50 / 25 / 10 / 0 %.
pub const DEFAULT_LOD_FRACTIONS: [f32; 5] = [1.0, 0.5, 0.25, 0.1, 0.0];

/// One level of the LOD table.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq, Eq)]
pub struct LodLevel {
    /// How many targets of the importance order this level evaluates.
    pub shapes: u32,
    /// Index into [`Lod::meshes`] of the simplified mesh this level evaluates; `None` is the
    /// full mesh.
    #[serde(default)]
    pub mesh: Option<u32>,
    /// Index into [`Lod::pca`] of the variable-PCA form this level evaluates instead of its
    /// shapes (only on the full mesh; `crowdmorph_engine::lod::pca` picks it where it is smaller and
    /// faster at the level's error).
    #[serde(default)]
    pub pca: Option<u32>,
}

impl LodLevel {
    /// A level on the full mesh.
    pub fn shapes(shapes: u32) -> Self {
        LodLevel {
            shapes,
            mesh: None,
            pca: None,
        }
    }
}

/// A simplified mesh of the whole rig: per primitive, the surviving vertices and new triangles.
///
/// Simplification only ever keeps original vertices (half-edge collapses), so the vertex
/// correspondence to the full mesh is a subset and every surviving vertex keeps its own neutral
/// position and deltas; nothing is resampled.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct MeshLevel {
    /// Fraction of the full mesh's triangles this level was asked for (0, 1].
    pub triangle_fraction: f32,
    /// One entry per rig primitive, in order.
    pub primitives: Vec<MeshLevelPrimitive>,
}

/// One primitive of a [`MeshLevel`].
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct MeshLevelPrimitive {
    /// For each simplified vertex, its index in the full primitive; strictly ascending.
    pub vertices: Vec<u32>,
    /// Triangle list into `vertices` (not into the full primitive).
    pub indices: Vec<u32>,
}

impl MeshLevel {
    /// Vertices over all primitives.
    pub fn vertex_count(&self) -> usize {
        self.primitives.iter().map(|p| p.vertices.len()).sum()
    }

    /// Triangles over all primitives.
    pub fn triangle_count(&self) -> usize {
        self.primitives.iter().map(|p| p.indices.len() / 3).sum()
    }

    /// For each vertex of the level in evaluation order (primitives concatenated), its vertex
    /// in the full rig's evaluation order. `offsets` is [`super::Rig::vertex_offsets`].
    pub fn vertex_map(&self, offsets: &[usize]) -> Vec<u32> {
        self.primitives
            .iter()
            .zip(offsets)
            .flat_map(|(p, &o)| p.vertices.iter().map(move |&v| o as u32 + v))
            .collect()
    }
}

/// The importance order and the LOD table of a rig.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct Lod {
    /// Rig-wide target ids, most important first; a permutation of `0..targets`.
    pub order: Vec<TargetId>,
    /// Level → how much of the order it evaluates. Level 0 evaluates every target.
    pub levels: Vec<LodLevel>,
    /// How the order was obtained (e.g. `"delta-energy"`), for reports.
    pub method: String,
    /// Targets pinned to the front by hand (Costigan et al. found every metric undervalues
    /// blinks); `order` starts with exactly these, in this order.
    #[serde(default)]
    pub pinned: Vec<TargetId>,
    /// Simplified meshes that levels may name.
    #[serde(default)]
    pub meshes: Vec<MeshLevel>,
    /// Variable-PCA forms of the deltas that levels may name.
    #[serde(default)]
    pub pca: Vec<super::DeltaPca>,
}

/// Why a LOD table is not acceptable.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum LodError {
    /// The order is not a permutation of the targets.
    #[error("LOD order is not a permutation of the {0} targets")]
    NotAPermutation(usize),
    /// The table is empty, level 0 is not all shapes, or a level asks for too many shapes.
    #[error("LOD table: {0}")]
    BadTable(String),
    /// A simplified mesh level is malformed.
    #[error("LOD mesh {0}: {1}")]
    BadMesh(usize, String),
    /// A request named a level the rig does not have.
    #[error("LOD level {level} out of range (rig has {levels} levels)")]
    LevelOutOfRange {
        /// Requested level.
        level: u32,
        /// Levels in the table.
        levels: usize,
    },
}

/// Shape counts of the default table for `n` targets (rounded to nearest).
pub fn default_lod_levels(n: usize) -> Vec<LodLevel> {
    DEFAULT_LOD_FRACTIONS
        .iter()
        .map(|f| LodLevel::shapes((n as f32 * f).round() as u32))
        .collect()
}

impl Lod {
    /// The order that keeps the targets in file order (the paper's "unordered truncation").
    pub fn file_order(n: usize) -> Self {
        Lod {
            order: (0..n as TargetId).collect(),
            levels: default_lod_levels(n),
            method: "file-order".into(),
            pinned: Vec::new(),
            meshes: Vec::new(),
            pca: Vec::new(),
        }
    }

    /// Orders targets by the total squared length of their position deltas, largest first
    /// (ties by id): a cheap geometric-MSE proxy used until a rig gets a metric-based order.
    pub fn by_delta_energy(primitives: &[Primitive], n: usize) -> Self {
        let mut energy = vec![0f64; n];
        for p in primitives {
            for t in &p.targets {
                if let Some(e) = energy.get_mut(t.target as usize) {
                    *e += t
                        .positions
                        .iter()
                        .map(|d| f64::from(d.length_squared()))
                        .sum::<f64>();
                }
            }
        }
        let mut order: Vec<TargetId> = (0..n as TargetId).collect();
        order.sort_by(|&a, &b| {
            energy[b as usize]
                .total_cmp(&energy[a as usize])
                .then(a.cmp(&b))
        });
        Lod {
            order,
            levels: default_lod_levels(n),
            method: IMPORT_LOD_METHOD.into(),
            pinned: Vec::new(),
            meshes: Vec::new(),
            pca: Vec::new(),
        }
    }

    /// Number of targets evaluated at `level`.
    pub fn shapes_at(&self, level: u32) -> Result<u32, LodError> {
        self.levels
            .get(level as usize)
            .map(|l| l.shapes)
            .ok_or(LodError::LevelOutOfRange {
                level,
                levels: self.levels.len(),
            })
    }

    /// Slot of each target in the order (inverse permutation).
    pub fn slots(&self) -> Vec<u32> {
        let mut slot = vec![0; self.order.len()];
        for (s, &t) in self.order.iter().enumerate() {
            if let Some(x) = slot.get_mut(t as usize) {
                *x = s as u32;
            }
        }
        slot
    }

    /// The table checks of [`Lod::validate`], which need only the number of targets `n` and
    /// of mesh levels `meshes`: a LOD build runs them before its seconds of scoring and
    /// simplifying, so that a request with a bad table is refused at once.
    pub fn validate_levels(
        levels: &[LodLevel],
        n: usize,
        meshes: usize,
        pcas: usize,
    ) -> Result<(), LodError> {
        let Some(first) = levels.first() else {
            return Err(LodError::BadTable("no levels".into()));
        };
        if first.shapes as usize != n {
            return Err(LodError::BadTable(format!(
                "level 0 must evaluate all {n} shapes, not {}",
                first.shapes
            )));
        }
        if levels.len() > 64 {
            return Err(LodError::BadTable("more than 64 levels".into()));
        }
        if let Some(l) = levels.iter().find(|l| l.shapes as usize > n) {
            return Err(LodError::BadTable(format!(
                "a level asks for {} shapes of {n}",
                l.shapes
            )));
        }
        if first.mesh.is_some() || first.pca.is_some() {
            return Err(LodError::BadTable(
                "level 0 must evaluate the full mesh and its shapes".into(),
            ));
        }
        if levels.iter().any(|l| l.mesh.is_some() && l.pca.is_some()) {
            return Err(LodError::BadTable(
                "a level names both a mesh and a PCA form".into(),
            ));
        }
        if let Some(p) = levels
            .iter()
            .filter_map(|l| l.pca)
            .find(|&p| p as usize >= pcas)
        {
            return Err(LodError::BadTable(format!(
                "a level names PCA form {p} of {pcas}"
            )));
        }
        if let Some(m) = levels
            .iter()
            .filter_map(|l| l.mesh)
            .find(|&m| m as usize >= meshes)
        {
            return Err(LodError::BadTable(format!(
                "a level names mesh {m} of {}",
                meshes
            )));
        }
        Ok(())
    }

    /// Checks that the order is a permutation and the table is usable.
    pub fn validate(&self, n: usize) -> Result<(), LodError> {
        if self.order.len() != n {
            return Err(LodError::NotAPermutation(n));
        }
        let mut seen = vec![false; n];
        for &t in &self.order {
            match seen.get_mut(t as usize) {
                Some(s) if !*s => *s = true,
                _ => return Err(LodError::NotAPermutation(n)),
            }
        }
        Lod::validate_levels(&self.levels, n, self.meshes.len(), self.pca.len())?;
        for (i, f) in self.pca.iter().enumerate() {
            f.validate()
                .map_err(|e| LodError::BadTable(format!("PCA form {i}: {e}")))?;
            if f.targets as usize != n {
                return Err(LodError::BadTable(format!(
                    "PCA form {i} has {} channels of {n}",
                    f.targets
                )));
            }
        }
        if self.pinned.len() > n || self.order.get(..self.pinned.len()) != Some(&self.pinned[..]) {
            return Err(LodError::BadTable(
                "the order does not start with the pinned targets".into(),
            ));
        }
        for (i, m) in self.meshes.iter().enumerate() {
            m.validate().map_err(|e| LodError::BadMesh(i, e))?;
        }
        Ok(())
    }

    /// Checks the mesh levels against the rig's primitives (their vertex counts, in order):
    /// one entry per primitive and every kept vertex in range. [`Lod::validate`] checks the
    /// rest; `Rig::validate` calls both.
    pub fn validate_meshes(&self, vertex_counts: &[usize]) -> Result<(), LodError> {
        let total: usize = vertex_counts.iter().sum();
        let ends: Vec<usize> = vertex_counts
            .iter()
            .scan(0usize, |a, &n| {
                *a += n;
                Some(*a)
            })
            .collect();
        for (i, f) in self.pca.iter().enumerate() {
            let crosses = f.regions.iter().any(|r| {
                let (a, b) = (r.first as usize, (r.first + r.count) as usize);
                ends.iter().any(|&e| a < e && b > e)
            });
            if f.vertices as usize != total || crosses {
                return Err(LodError::BadTable(format!(
                    "PCA form {i} does not fit the rig's {total} vertices and primitives"
                )));
            }
        }
        for (i, m) in self.meshes.iter().enumerate() {
            if m.primitives.len() != vertex_counts.len() {
                return Err(LodError::BadMesh(
                    i,
                    format!(
                        "{} primitives, rig has {}",
                        m.primitives.len(),
                        vertex_counts.len()
                    ),
                ));
            }
            for (p, &n) in m.primitives.iter().zip(vertex_counts) {
                if p.vertices.last().is_some_and(|&v| v as usize >= n) {
                    return Err(LodError::BadMesh(
                        i,
                        format!("vertex out of range for a primitive of {n} vertices"),
                    ));
                }
            }
        }
        Ok(())
    }
}

impl MeshLevel {
    fn validate(&self) -> Result<(), String> {
        if !(self.triangle_fraction > 0.0 && self.triangle_fraction <= 1.0) {
            return Err(format!(
                "triangle fraction {} is not in (0, 1]",
                self.triangle_fraction
            ));
        }
        for p in self.primitives.iter() {
            if p.vertices.windows(2).any(|w| w[0] >= w[1]) {
                return Err("vertex list not strictly ascending".into());
            }
            if !p.indices.len().is_multiple_of(3) {
                return Err(format!(
                    "{} indices is not a triangle list",
                    p.indices.len()
                ));
            }
            if let Some(&i) = p.indices.iter().find(|&&i| i as usize >= p.vertices.len()) {
                return Err(format!(
                    "index {i} out of range for {} vertices",
                    p.vertices.len()
                ));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_levels_round() {
        let shapes: Vec<u32> = default_lod_levels(53).iter().map(|l| l.shapes).collect();
        assert_eq!(shapes, vec![53, 27, 13, 5, 0]);
    }

    #[test]
    fn validate_catches_duplicates() {
        let mut lod = Lod::file_order(3);
        assert!(lod.validate(3).is_ok());
        lod.order = vec![0, 0, 2];
        assert!(lod.validate(3).is_err());
    }

    #[test]
    fn validate_checks_pins_and_meshes() {
        let mut lod = Lod::file_order(3);
        lod.pinned = vec![2];
        assert!(lod.validate(3).is_err(), "order must start with the pins");
        lod.order = vec![2, 0, 1];
        assert!(lod.validate(3).is_ok());
        lod.levels[1].mesh = Some(0);
        assert!(lod.validate(3).is_err(), "mesh 0 does not exist");
        lod.meshes.push(MeshLevel {
            triangle_fraction: 0.5,
            primitives: vec![MeshLevelPrimitive {
                vertices: vec![0, 2, 5],
                indices: vec![0, 1, 2],
            }],
        });
        assert!(lod.validate(3).is_ok());
        assert!(lod.validate_meshes(&[6]).is_ok());
        assert!(lod.validate_meshes(&[5]).is_err(), "vertex 5 of 5");
        assert!(
            lod.validate_meshes(&[6, 6]).is_err(),
            "one entry per primitive"
        );
        lod.meshes[0].primitives[0].indices = vec![0, 1, 3];
        assert!(lod.validate(3).is_err(), "index past the kept vertices");
        lod.meshes[0].primitives[0].indices = vec![0, 1, 2];
        lod.levels[0].mesh = Some(0);
        assert!(lod.validate(3).is_err(), "level 0 is the full mesh");
    }

    #[test]
    fn old_persisted_tables_still_read() {
        let json = r#"{"order":[1,0],"levels":[{"shapes":2},{"shapes":1}],"method":"x"}"#;
        let lod: Lod = serde_json::from_str(json).expect("old table parses");
        assert!(lod.pinned.is_empty() && lod.meshes.is_empty());
        assert_eq!(lod.levels[1].mesh, None);
        assert!(lod.validate(2).is_ok());
    }
}
