//! Blendshape level of detail (Costigan et al. 2016, §2 and §4).
//!
//! Level `l` evaluates only the first `levels[l].shapes` targets of an importance order and
//! skips the rest — the paper's early exit after N_Bs shapes. Level 0 is always all shapes. The
//! order is a permutation of the rig's targets, most important first.

use serde::{Deserialize, Serialize};

use super::{Primitive, TargetId};

/// Default LOD table as fractions of the target count: 100 / 50 / 25 / 10 / 0 %.
pub const DEFAULT_LOD_FRACTIONS: [f32; 5] = [1.0, 0.5, 0.25, 0.1, 0.0];

/// One level of the LOD table.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq, Eq)]
pub struct LodLevel {
    /// How many targets of the importance order this level evaluates.
    pub shapes: u32,
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
        .map(|f| LodLevel {
            shapes: (n as f32 * f).round() as u32,
        })
        .collect()
}

impl Lod {
    /// The order that keeps the targets in file order (the paper's "unordered truncation").
    pub fn file_order(n: usize) -> Self {
        Lod {
            order: (0..n as TargetId).collect(),
            levels: default_lod_levels(n),
            method: "file-order".into(),
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
            method: "delta-energy".into(),
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
        let Some(first) = self.levels.first() else {
            return Err(LodError::BadTable("no levels".into()));
        };
        if first.shapes as usize != n {
            return Err(LodError::BadTable(format!(
                "level 0 must evaluate all {n} shapes, not {}",
                first.shapes
            )));
        }
        if self.levels.len() > 64 {
            return Err(LodError::BadTable("more than 64 levels".into()));
        }
        if let Some(l) = self.levels.iter().find(|l| l.shapes as usize > n) {
            return Err(LodError::BadTable(format!(
                "a level asks for {} shapes of {n}",
                l.shapes
            )));
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
}
