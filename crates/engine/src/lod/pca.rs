//! Building the variable-PCA form of a rig's deltas ([`DeltaPca`]) within an error budget, and
//! the comparison that decides whether a LOD level should use it.
//!
//! **Regions.** Each primitive's vertices are cut into runs of [`REGION`] consecutive ones:
//! meshes list neighbouring vertices near each other, which the same shapes tend to move
//! together, and a run is contiguous in the output.
//!
//! **Components.** In region `r` the deltas form a `3n × K` matrix `D`. The eigenvectors `v_c`
//! of `DᵀD` (strongest first) give the components `b_c = D·v_c` and the map rows `v_c`, so that
//! `D·w ≈ Σ_{c<C} b_c (v_c · w)` is the best rank-`C` approximation of `D` (uncentred: the
//! neutral is the mean a delta is measured from). `C_r` is the fewest components for which
//! every vertex of the region stays within `max_error × diagonal` on every test pose.
//!
//! **Test poses** (the same for both forms, so their errors compare): each shape alone at
//! weight 1, and every frame of the rig's clips. A LOD level of the sparse form drops the
//! shapes after the first `N` of the importance order; its error on the same poses is what
//! [`compare_levels`] gives the PCA form as its budget.

use crowdmorph_core::rig::{DeltaPca, PcaRegion, Rig, TargetId};

/// Vertices per region.
pub const REGION: usize = 256;

/// One region's dense deltas: `rows = 3n` (x, y, z per vertex), row-major over the `K`
/// channels, for the `count` vertices from rig-wide vertex `first`.
struct Dense {
    first: u32,
    count: u32,
    d: Vec<f64>,
}

/// Every region of `rig`, with its deltas made dense.
fn regions(rig: &Rig) -> Vec<Dense> {
    let k = rig.targets.len();
    let offsets = rig.vertex_offsets();
    let mut out = Vec::new();
    for (pi, p) in rig.primitives.iter().enumerate() {
        let first = out.len();
        for start in (0..p.positions.len()).step_by(REGION) {
            let n = REGION.min(p.positions.len() - start);
            out.push(Dense {
                first: (offsets[pi] + start) as u32,
                count: n as u32,
                d: vec![0f64; 3 * n * k],
            });
        }
        for t in &p.targets {
            let k_t = t.target as usize;
            for (&v, d) in t.vertices.iter().zip(&t.positions) {
                let (r, s) = (v as usize / REGION, v as usize % REGION);
                let dense = &mut out[first + r];
                for a in 0..3 {
                    dense.d[(3 * s + a) * k + k_t] = f64::from(d[a]);
                }
            }
        }
    }
    out
}

/// The test poses: each channel alone at 1, then every clip frame (K weights each).
fn test_poses(rig: &Rig) -> Vec<Vec<f32>> {
    let k = rig.targets.len();
    let mut poses: Vec<Vec<f32>> = (0..k)
        .map(|i| (0..k).map(|j| if i == j { 1.0 } else { 0.0 }).collect())
        .collect();
    for c in &rig.clips {
        for f in 0..c.frames {
            let mut w = vec![0f32; k];
            c.frame_weights(f, &mut w);
            poses.push(w);
        }
    }
    poses
}

/// `D · W` of a region for the test poses: `3n × m`, row-major.
fn apply(d: &[f64], k: usize, poses: &[Vec<f32>]) -> Vec<f64> {
    let rows = d.len() / k.max(1);
    let m = poses.len();
    let mut out = vec![0f64; rows * m];
    for row in 0..rows {
        let dr = &d[row * k..(row + 1) * k];
        for (j, w) in poses.iter().enumerate() {
            out[row * m + j] = dr.iter().zip(w).map(|(a, &b)| a * f64::from(b)).sum();
        }
    }
    out
}

/// Largest per-vertex length of a `3n × m` residual.
fn worst(residual: &[f64], m: usize) -> f64 {
    let mut w = 0f64;
    for v in residual.chunks(3 * m) {
        for j in 0..m {
            let (x, y, z) = (v[j], v[m + j], v[2 * m + j]);
            w = w.max((x * x + y * y + z * z).sqrt());
        }
    }
    w
}

/// The variable-PCA form of `rig`'s deltas, every vertex within `max_error × diagonal` on
/// the test poses (module doc).
pub fn build(rig: &Rig, max_error: f32) -> DeltaPca {
    let k = rig.targets.len();
    let budget = f64::from(max_error) * f64::from(rig.bbox().diagonal());
    let poses = test_poses(rig);
    let m = poses.len();
    let mut form = DeltaPca {
        targets: k as u32,
        vertices: rig.vertex_count() as u32,
        max_error,
        ..DeltaPca::default()
    };
    for region in regions(rig) {
        let n = region.count as usize;
        let rows = 3 * n;
        let mut gram = vec![0f64; k * k];
        for row in region.d.chunks(k) {
            for i in 0..k {
                if row[i] == 0.0 {
                    continue;
                }
                for j in 0..k {
                    gram[i * k + j] += row[i] * row[j];
                }
            }
        }
        let (values, vectors) = crowdmorph_core::linalg::jacobi(gram, k);
        let mut order: Vec<usize> = (0..k).collect();
        order.sort_by(|&a, &b| values[b].total_cmp(&values[a]));
        let mut residual = apply(&region.d, k, &poses);
        let mut kept: Vec<(Vec<f64>, Vec<f64>)> = Vec::new();
        for &c in &order {
            if worst(&residual, m) <= budget {
                break;
            }
            let v: Vec<f64> = (0..k).map(|i| vectors[i * k + c]).collect();
            let b: Vec<f64> = region
                .d
                .chunks(k)
                .map(|row| row.iter().zip(&v).map(|(a, x)| a * x).sum())
                .collect();
            let vw: Vec<f64> = poses
                .iter()
                .map(|w| v.iter().zip(w).map(|(a, &x)| a * f64::from(x)).sum())
                .collect();
            for row in 0..rows {
                for j in 0..m {
                    residual[row * m + j] -= b[row] * vw[j];
                }
            }
            kept.push((b, v));
        }
        form.regions.push(PcaRegion {
            first: region.first,
            count: region.count,
            components: kept.len() as u32,
            basis: form.basis.len() as u32,
            coef: form.components() as u32,
        });
        for (b, v) in kept {
            form.basis.extend(b.iter().map(|&x| x as f32));
            form.map.extend(v.iter().map(|&x| x as f32));
        }
    }
    form
}

/// Largest vertex error of `form` on the test poses, as a fraction of the diagonal (f64,
/// against the exact deltas).
pub fn error(rig: &Rig, form: &DeltaPca) -> f64 {
    let k = rig.targets.len();
    let poses = test_poses(rig);
    let m = poses.len();
    let mut w = 0f64;
    for (region, r) in regions(rig).iter().zip(&form.regions) {
        let mut residual = apply(&region.d, k, &poses);
        let rows = 3 * r.count as usize;
        for c in 0..r.components as usize {
            let b = &form.basis[r.basis as usize + c * rows..][..rows];
            let row = &form.map[(r.coef as usize + c) * k..][..k];
            let vw: Vec<f64> = poses
                .iter()
                .map(|p| row.iter().zip(p).map(|(a, &x)| f64::from(*a * x)).sum())
                .collect();
            for i in 0..rows {
                for j in 0..m {
                    residual[i * m + j] -= f64::from(b[i]) * vw[j];
                }
            }
        }
        w = w.max(worst(&residual, m));
    }
    w / f64::from(rig.bbox().diagonal())
}

/// The sparse form's error when only the first `shapes` of `order` are evaluated, on the same
/// test poses, as a fraction of the diagonal.
pub fn level_error(rig: &Rig, order: &[TargetId], shapes: u32) -> f64 {
    let k = rig.targets.len();
    let mut dropped = vec![true; k];
    for &t in order.iter().take(shapes as usize) {
        dropped[t as usize] = false;
    }
    let poses: Vec<Vec<f32>> = test_poses(rig)
        .into_iter()
        .map(|w| {
            w.iter()
                .zip(&dropped)
                .map(|(&x, &d)| if d { x } else { 0.0 })
                .collect()
        })
        .collect();
    let m = poses.len();
    let w = regions(rig)
        .iter()
        .map(|r| worst(&apply(&r.d, k, &poses), m))
        .fold(0f64, f64::max);
    w / f64::from(rig.bbox().diagonal())
}

/// Multiply-adds per head of the sparse form at the first `shapes` of `order` (all active).
pub fn level_madds(rig: &Rig, order: &[TargetId], shapes: u32) -> usize {
    let kept: std::collections::HashSet<u32> =
        order.iter().take(shapes as usize).copied().collect();
    rig.primitives
        .iter()
        .flat_map(|p| &p.targets)
        .filter(|t| kept.contains(&t.target))
        .map(|t| 3 * t.vertices.len())
        .sum()
}

/// Bytes of the sparse deltas at the first `shapes` of `order`: a 12-byte delta and a 4-byte
/// index each.
pub fn level_bytes(rig: &Rig, order: &[TargetId], shapes: u32) -> usize {
    level_madds(rig, order, shapes) / 3 * 16
}

/// Whether the PCA form pays at a level: fewer multiply-adds per head and fewer bytes than the
/// level's sparse shapes (`bench cpu`'s PCA rows check the cost model against time).
pub fn pays(form: &DeltaPca, sparse_madds: usize, sparse_bytes: usize) -> bool {
    form.madds_per_head() < sparse_madds && form.bytes() < sparse_bytes
}

/// Working memory of [`build`] on `rig` at most: every region's dense deltas (in f64: `regions`
/// makes them all before the first is reduced), the form itself (every region keeping every
/// component), and one region's test-pose residual and eigenvectors, in f64.
pub fn build_bytes(rig: &Rig) -> u64 {
    let (v, k) = (rig.vertex_count() as u64, rig.targets.len() as u64);
    let m = k + rig.clips.iter().map(|c| u64::from(c.frames)).sum::<u64>();
    let rows = 3 * REGION as u64;
    8 * 3 * v * k
        + 4 * (rows.max(3 * v) * k + k * (v / REGION as u64 + 1) * k)
        + 8 * rows * (k + 2 * m)
        + 4 * m * k
        + 24 * k * k
}

/// One LOD level of the sparse form against the PCA form built within its error.
#[derive(Clone, Debug, serde::Serialize)]
pub struct PcaLevel {
    /// LOD level.
    pub level: u32,
    /// Shapes the sparse level evaluates.
    pub shapes: u32,
    /// Its error on the test poses (fraction of the diagonal).
    pub sparse_error: f64,
    /// Its multiply-adds per head.
    pub sparse_madds: usize,
    /// Its delta bytes.
    pub sparse_bytes: usize,
    /// The PCA form's budget: the level's error, at least `floor`.
    pub pca_budget: f64,
    /// Its measured error.
    pub pca_error: f64,
    /// Its components, all regions together.
    pub components: usize,
    /// Its multiply-adds per head.
    pub pca_madds: usize,
    /// Its bytes.
    pub pca_bytes: usize,
}

/// For each full-mesh level of `rig`'s LOD table, the PCA form built within that level's
/// error (at least `floor × diagonal`: level 0 is exact, and no lossy form matches it).
pub fn compare_levels(rig: &Rig, floor: f32) -> Vec<(PcaLevel, DeltaPca)> {
    rig.lod
        .levels
        .iter()
        .enumerate()
        .filter(|(_, l)| l.mesh.is_none())
        .map(|(i, l)| {
            let order = &rig.lod.order;
            let sparse_error = level_error(rig, order, l.shapes);
            let budget = (sparse_error as f32).max(floor);
            let form = build(rig, budget);
            let row = PcaLevel {
                level: i as u32,
                shapes: l.shapes,
                sparse_error,
                sparse_madds: level_madds(rig, order, l.shapes),
                sparse_bytes: level_bytes(rig, order, l.shapes),
                pca_budget: f64::from(budget),
                pca_error: error(rig, &form),
                components: form.components(),
                pca_madds: form.madds_per_head(),
                pca_bytes: form.bytes(),
            };
            (row, form)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_build_charge_holds_the_dense_deltas_and_the_form() {
        let rig = crowdmorph_core::embedded::default_rig();
        let dense: u64 = regions(&rig).iter().map(|r| r.d.len() as u64 * 8).sum();
        let exact = build(&rig, 1e-9);
        assert!(build_bytes(&rig) >= dense + exact.bytes() as u64);
    }

    #[test]
    fn the_form_keeps_its_budget_and_every_component_is_the_deltas() {
        let rig = crowdmorph_core::embedded::default_rig();
        for budget in [1e-3f32, 1e-4] {
            let form = build(&rig, budget);
            form.validate().expect("consistent");
            let e = error(&rig, &form);
            assert!(e <= f64::from(budget) * 1.001, "{e} > {budget}");
        }
        // A budget no lossy form meets keeps every component a region needs: the exact deltas.
        let exact = build(&rig, 1e-9);
        assert!(error(&rig, &exact) < 1e-6);
        // Never more components than channels.
        assert!(
            exact
                .regions
                .iter()
                .all(|r| r.components as usize <= rig.targets.len())
        );
        let k = rig.targets.len();
        assert_eq!(level_error(&rig, &rig.lod.order, k as u32), 0.0);
        assert!(level_error(&rig, &rig.lod.order, 0) > 0.0);
    }
}
