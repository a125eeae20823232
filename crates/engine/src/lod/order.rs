//! Scoring every target against the neutral face, and importance orders from the scores.
//!
//! Each target is posed at weight 1 and compared with the neutral face under the five metrics
//! of Costigan et al. 2016 §4.1 ([`Metric`]). A metric's order sorts targets by its importance
//! (bigger difference first). The paper found the metrics broadly agree but each has blind
//! spots, so the combined order sorts by the mean rank over all five; and since every metric
//! undervalues blinks, [`pin_front`] moves hand-picked targets to the front. Every order is
//! deterministic: ties fall back to the geometric MSE, then to the target id.

use std::collections::HashSet;
use std::time::Instant;

use glam::Vec3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::metrics::{
    PointIndex, YeeParams, YeeReference, geometric_mse, hausdorff, image_mse, ssim,
};
use super::{LodBuildError, Progress};
use crate::lod::raster::{Camera, neutral_positions, render_pose};
use crowdmorph_core::rig::{Rig, TargetId};

/// One of the importance metrics of §4.1.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Metric {
    /// Mean squared vertex displacement (Eq. 2).
    GeometricMse,
    /// Symmetric Hausdorff distance between the vertex sets (Eq. 3).
    Hausdorff,
    /// Mean squared pixel difference of the front renders (Eq. 4).
    ImageMse,
    /// Structural dissimilarity of the front renders, 1 − mean SSIM (Wang et al. 2004).
    Ssim,
    /// Pixels whose difference Yee's 2004 perceptual metric finds visible.
    Yee,
}

impl Metric {
    /// All five, in the paper's order.
    pub const ALL: [Metric; 5] = [
        Metric::GeometricMse,
        Metric::Hausdorff,
        Metric::ImageMse,
        Metric::Ssim,
        Metric::Yee,
    ];

    /// Short name used in reports, JSON and the `method` of a LOD table.
    pub fn name(self) -> &'static str {
        match self {
            Metric::GeometricMse => "geometric-mse",
            Metric::Hausdorff => "hausdorff",
            Metric::ImageMse => "image-mse",
            Metric::Ssim => "ssim",
            Metric::Yee => "yee",
        }
    }

    /// The metric with this [`Metric::name`].
    pub fn from_name(name: &str) -> Option<Metric> {
        Metric::ALL.into_iter().find(|m| m.name() == name)
    }
}

/// How to order targets.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum OrderMethod {
    /// Mean rank over the five metrics.
    #[default]
    Combined,
    /// One metric's order.
    Metric(Metric),
    /// Targets as the file lists them: the paper's unordered truncation.
    FileOrder,
}

impl OrderMethod {
    /// Name used in reports and as the LOD table's `method`.
    pub fn name(self) -> &'static str {
        match self {
            OrderMethod::Combined => "combined",
            OrderMethod::Metric(m) => m.name(),
            OrderMethod::FileOrder => "file-order",
        }
    }

    /// The combined order, the five metrics, and file order: what the report compares.
    pub fn all() -> Vec<OrderMethod> {
        let mut v = vec![OrderMethod::Combined];
        v.extend(Metric::ALL.map(OrderMethod::Metric));
        v.push(OrderMethod::FileOrder);
        v
    }

    /// The method with this [`OrderMethod::name`].
    pub fn from_name(name: &str) -> Option<OrderMethod> {
        OrderMethod::all().into_iter().find(|m| m.name() == name)
    }
}

/// Scores of one target against the neutral face.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TargetScore {
    /// Rig-wide target id.
    pub target: TargetId,
    /// Target name.
    pub name: String,
    /// Mean squared vertex displacement, rig units².
    pub geometric_mse: f64,
    /// Symmetric Hausdorff distance, rig units.
    pub hausdorff: f64,
    /// Mean squared pixel difference (intensities in [0, 1]).
    pub image_mse: f64,
    /// Mean SSIM (1 = identical).
    pub ssim: f64,
    /// Pixels that fail Yee's perceptual test.
    pub yee_failed_pixels: u64,
}

impl TargetScore {
    /// Importance under `metric`: bigger means the expression differs more from neutral.
    pub fn importance(&self, metric: Metric) -> f64 {
        match metric {
            Metric::GeometricMse => self.geometric_mse,
            Metric::Hausdorff => self.hausdorff,
            Metric::ImageMse => self.image_mse,
            Metric::Ssim => 1.0 - self.ssim,
            Metric::Yee => self.yee_failed_pixels as f64,
        }
    }
}

/// Every target's scores, in target id order.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Scores {
    /// One entry per rig target, index = target id.
    pub targets: Vec<TargetScore>,
    /// Side of the square renders the image metrics compared, in pixels.
    pub image_size: u32,
}

impl Scores {
    /// Targets by importance under `metric`, most important first (ties: geometric MSE, id).
    pub fn metric_order(&self, metric: Metric) -> Vec<TargetId> {
        let mut order: Vec<TargetId> = (0..self.targets.len() as TargetId).collect();
        order.sort_by(|&a, &b| {
            let (sa, sb) = (&self.targets[a as usize], &self.targets[b as usize]);
            sb.importance(metric)
                .total_cmp(&sa.importance(metric))
                .then(sb.geometric_mse.total_cmp(&sa.geometric_mse))
                .then(a.cmp(&b))
        });
        order
    }

    /// Fractional rank of each target under `metric` (1 = most important; tied scores share
    /// the mean of their ranks, so ties favour no target).
    pub fn ranks(&self, metric: Metric) -> Vec<f64> {
        let n = self.targets.len();
        let mut idx: Vec<usize> = (0..n).collect();
        let imp = |i: usize| self.targets[i].importance(metric);
        idx.sort_by(|&a, &b| imp(b).total_cmp(&imp(a)).then(a.cmp(&b)));
        let mut ranks = vec![0.0; n];
        let mut i = 0;
        while i < n {
            let mut j = i;
            while j + 1 < n && imp(idx[j + 1]) == imp(idx[i]) {
                j += 1;
            }
            let r = (i + j) as f64 / 2.0 + 1.0;
            for &k in &idx[i..=j] {
                ranks[k] = r;
            }
            i = j + 1;
        }
        ranks
    }

    /// Mean rank of each target over the five metrics.
    pub fn mean_ranks(&self) -> Vec<f64> {
        let mut mean = vec![0.0; self.targets.len()];
        for m in Metric::ALL {
            for (acc, r) in mean.iter_mut().zip(self.ranks(m)) {
                *acc += r / Metric::ALL.len() as f64;
            }
        }
        mean
    }

    /// The combined order: mean rank ascending (ties: geometric MSE, then id).
    pub fn combined_order(&self) -> Vec<TargetId> {
        let mean = self.mean_ranks();
        let mut order: Vec<TargetId> = (0..self.targets.len() as TargetId).collect();
        order.sort_by(|&a, &b| {
            let (ia, ib) = (a as usize, b as usize);
            mean[ia]
                .total_cmp(&mean[ib])
                .then(
                    self.targets[ib]
                        .geometric_mse
                        .total_cmp(&self.targets[ia].geometric_mse),
                )
                .then(a.cmp(&b))
        });
        order
    }

    /// The order `method` gives.
    pub fn order(&self, method: OrderMethod) -> Vec<TargetId> {
        match method {
            OrderMethod::Combined => self.combined_order(),
            OrderMethod::Metric(m) => self.metric_order(m),
            OrderMethod::FileOrder => (0..self.targets.len() as TargetId).collect(),
        }
    }
}

/// Moves `pins` to the front of `order`, in the order given; the rest keep their order.
/// Unknown or repeated pins are ignored (callers resolve names first and report them).
pub fn pin_front(order: &[TargetId], pins: &[TargetId]) -> Vec<TargetId> {
    // Sets, not scans of `order` and of the pins so far per pin and per target: pinning
    // every target of a 4,096-channel rig stays linear.
    let listed: HashSet<TargetId> = order.iter().copied().collect();
    let mut pinned: HashSet<TargetId> = HashSet::with_capacity(pins.len());
    let mut out: Vec<TargetId> = Vec::with_capacity(order.len());
    for &p in pins {
        if listed.contains(&p) && pinned.insert(p) {
            out.push(p);
        }
    }
    out.extend(order.iter().copied().filter(|t| !pinned.contains(t)));
    out
}

/// How to score.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ScoreOptions {
    /// Side of the square front renders, in pixels.
    pub image_size: u32,
    /// Viewing conditions for Yee's metric.
    pub yee: YeeParams,
}

impl Default for ScoreOptions {
    fn default() -> Self {
        ScoreOptions {
            image_size: 384,
            yee: YeeParams::default(),
        }
    }
}

/// Sparse displacement of one target over the whole rig: global vertex ids (ascending) and
/// their deltas at weight 1. This scans every sparse target of the rig: to gather many
/// targets, build a [`SparseIndex`] once.
pub fn target_displacement(
    rig: &Rig,
    offsets: &[usize],
    target: TargetId,
) -> (Vec<u32>, Vec<Vec3>) {
    let mut vertices = Vec::new();
    let mut deltas = Vec::new();
    for (p, &o) in rig.primitives.iter().zip(offsets) {
        for t in p.targets.iter().filter(|t| t.target == target) {
            vertices.extend(t.vertices.iter().map(|&v| o as u32 + v));
            deltas.extend_from_slice(&t.positions);
        }
    }
    (vertices, deltas)
}

/// Where each target's sparse deltas are: for every target, its (primitive, sparse target)
/// pairs, found in one pass over the rig's sparse targets. [`target_displacement`] scans every
/// sparse target of the rig for the one target it gathers, so gathering all of them that way
/// is targets × sparse targets (4,096 × 123k on a big rig); through this index it is linear.
#[derive(Clone, Debug)]
pub struct SparseIndex {
    /// Start of each target's pairs in `at`, and the end of the last (targets + 1 entries).
    starts: Vec<u32>,
    /// (primitive, index into its `targets`), grouped by target, in primitive then sparse
    /// order within a target (the order [`target_displacement`] gathers them in).
    at: Vec<(u32, u32)>,
    /// First global vertex id of each primitive ([`Rig::vertex_offsets`]).
    offsets: Vec<usize>,
}

impl SparseIndex {
    /// Bytes an index over `rig` holds (charged with the LOD build: see `build_bytes`).
    pub fn bytes_for(rig: &Rig) -> u64 {
        let sparse: usize = rig.primitives.iter().map(|p| p.targets.len()).sum();
        4 * (rig.targets.len() as u64 + 1) + 8 * sparse as u64 + 8 * rig.primitives.len() as u64
    }

    /// Indexes the sparse targets of `rig` (a sparse target naming no channel of the rig is
    /// left out, as [`target_displacement`] never gathers it).
    pub fn new(rig: &Rig) -> SparseIndex {
        let n = rig.targets.len();
        let mut starts = vec![0u32; n + 1];
        for p in rig.primitives.iter() {
            for t in p.targets.iter().filter(|t| (t.target as usize) < n) {
                starts[t.target as usize + 1] += 1;
            }
        }
        for i in 0..n {
            starts[i + 1] += starts[i];
        }
        let mut next = starts.clone();
        let mut at = vec![(0u32, 0u32); starts[n] as usize];
        for (pi, p) in rig.primitives.iter().enumerate() {
            for (si, t) in p.targets.iter().enumerate() {
                if (t.target as usize) < n {
                    let slot = &mut next[t.target as usize];
                    at[*slot as usize] = (pi as u32, si as u32);
                    *slot += 1;
                }
            }
        }
        SparseIndex {
            starts,
            at,
            offsets: rig.vertex_offsets(),
        }
    }

    /// [`target_displacement`] of `target` through the index: the same vertices and deltas
    /// in the same order (empty for a target past the rig's channels). `rig` is the one the
    /// index was built from.
    pub fn displacement(&self, rig: &Rig, target: TargetId) -> (Vec<u32>, Vec<Vec3>) {
        let t = target as usize;
        let pairs = match (self.starts.get(t), self.starts.get(t + 1)) {
            (Some(&a), Some(&b)) => &self.at[a as usize..b as usize],
            _ => &[],
        };
        let mut vertices = Vec::new();
        let mut deltas = Vec::new();
        for &(pi, si) in pairs {
            let (p, o) = (&rig.primitives[pi as usize], self.offsets[pi as usize]);
            let st = &p.targets[si as usize];
            vertices.extend(st.vertices.iter().map(|&v| o as u32 + v));
            deltas.extend_from_slice(&st.positions);
        }
        (vertices, deltas)
    }
}

/// Scores every target of `rig` against its neutral face under all five metrics, in parallel
/// over targets (rayon). `progress`, when given, counts finished targets and is checked for
/// cancellation between targets.
pub fn score_targets(
    rig: &Rig,
    opts: &ScoreOptions,
    progress: Option<&Progress>,
) -> Result<Scores, LodBuildError> {
    let started = Instant::now();
    let neutral = neutral_positions(rig);
    let sparse = SparseIndex::new(rig);
    let size = opts.image_size.clamp(16, 4096);
    let camera = Camera::for_rig(rig, size);
    let neutral_frame = render_pose(rig, &neutral, &camera);
    let (w, h) = (size as usize, size as usize);
    let yee_ref = YeeReference::new(&neutral_frame.image.pixels, w, h, opts.yee);
    let index = PointIndex::new(&neutral);
    let n = rig.targets.len();
    // Every label in one pass: `Rig::channel_label` per target scans every channel each time.
    let labels = rig.channel_labels().into_vec();
    if let Some(p) = progress {
        p.start(n);
    }
    let targets: Vec<Result<TargetScore, LodBuildError>> = (0..n as TargetId)
        .into_par_iter()
        .map(|t| {
            if progress.is_some_and(Progress::is_cancelled) {
                return Err(LodBuildError::Cancelled);
            }
            let (vertices, deltas) = sparse.displacement(rig, t);
            let mut posed = neutral.clone();
            for (&v, &d) in vertices.iter().zip(&deltas) {
                posed[v as usize] += d;
            }
            let frame = render_pose(rig, &posed, &camera);
            let a = &neutral_frame.image.pixels;
            let b = &frame.image.pixels;
            let score = TargetScore {
                target: t,
                name: labels[t as usize].clone(),
                geometric_mse: geometric_mse(&deltas, neutral.len()),
                hausdorff: hausdorff(&neutral, &index, &vertices, &deltas),
                image_mse: image_mse(a, b),
                ssim: ssim(a, b, w, h),
                yee_failed_pixels: yee_ref.failing_pixels(b),
            };
            if let Some(p) = progress {
                p.advance();
            }
            Ok(score)
        })
        .collect();
    let targets = targets.into_iter().collect::<Result<Vec<_>, _>>()?;
    tracing::debug!(
        rig = %rig.name,
        targets = n,
        seconds = started.elapsed().as_secs_f64(),
        "scored targets"
    );
    Ok(Scores {
        targets,
        image_size: size,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scores(values: &[(f64, u64)]) -> Scores {
        Scores {
            targets: values
                .iter()
                .enumerate()
                .map(|(i, &(g, y))| TargetScore {
                    target: i as TargetId,
                    name: format!("t{i}"),
                    geometric_mse: g,
                    hausdorff: g,
                    image_mse: g,
                    ssim: 1.0 - g,
                    yee_failed_pixels: y,
                })
                .collect(),
            image_size: 8,
        }
    }

    #[test]
    fn ranks_share_ties_and_orders_break_them_by_id() {
        let s = scores(&[(1.0, 0), (3.0, 0), (2.0, 5), (2.0, 0)]);
        assert_eq!(s.ranks(Metric::Yee), vec![3.0, 3.0, 1.0, 3.0]);
        assert_eq!(s.metric_order(Metric::GeometricMse), vec![1, 2, 3, 0]);
        // Mean rank: t1 = (1·4 + 3)/5, t2 = (2.5·4 + 1)/5 — t2 wins on Yee but not overall.
        assert_eq!(s.combined_order(), vec![1, 2, 3, 0]);
    }

    #[test]
    fn pins_go_first_in_the_given_order() {
        assert_eq!(pin_front(&[3, 1, 0, 2], &[2, 0, 2, 9]), vec![2, 0, 3, 1]);
        assert_eq!(pin_front(&[3, 1], &[]), vec![3, 1]);
    }

    /// `pin_front` as it was before the sets: scans of `order` and of the output per pin
    /// and per target. The set-based one must agree with it exactly.
    fn pin_front_by_scan(order: &[TargetId], pins: &[TargetId]) -> Vec<TargetId> {
        let mut out: Vec<TargetId> = Vec::with_capacity(order.len());
        for &p in pins {
            if order.contains(&p) && !out.contains(&p) {
                out.push(p);
            }
        }
        let rest: Vec<TargetId> = order.iter().copied().filter(|t| !out.contains(t)).collect();
        out.extend(rest);
        out
    }

    #[test]
    fn set_pins_agree_with_the_scan() {
        let rig = crowdmorph_core::embedded::default_rig();
        let n = rig.targets.len() as TargetId;
        let file: Vec<TargetId> = (0..n).collect();
        let reversed: Vec<TargetId> = (0..n).rev().collect();
        // An order with a repeated id keeps both copies of an unpinned one.
        let repeated: Vec<TargetId> = [3, 1, 3, 0, 2].to_vec();
        let pins: [Vec<TargetId>; 5] = [
            Vec::new(),
            vec![n - 1, 0, n / 2],
            vec![5, 5, n + 7, 2, 5],
            (0..n).rev().collect(),
            vec![3, 9, 1],
        ];
        for order in [&file, &reversed, &repeated] {
            for p in &pins {
                assert_eq!(pin_front(order, p), pin_front_by_scan(order, p), "{p:?}");
            }
        }
    }

    #[test]
    fn indexed_displacements_equal_the_scan() {
        let rig = crowdmorph_core::embedded::default_rig();
        let offsets = rig.vertex_offsets();
        let index = SparseIndex::new(&rig);
        let n = rig.targets.len() as TargetId;
        let mut gathered = 0;
        for t in 0..n + 2 {
            let (v, d) = index.displacement(&rig, t);
            let (sv, sd) = target_displacement(&rig, &offsets, t);
            assert_eq!(v, sv, "target {t}");
            // Bitwise: the same deltas, copied in the same order.
            let bits = |d: &[Vec3]| {
                d.iter()
                    .flat_map(|x| x.to_array().map(f32::to_bits))
                    .collect::<Vec<_>>()
            };
            assert_eq!(bits(&d), bits(&sd), "target {t}");
            gathered += v.len();
        }
        assert!(gathered > 0, "the embedded rig's targets move vertices");
    }

    #[test]
    fn method_names_round_trip() {
        for m in OrderMethod::all() {
            assert_eq!(OrderMethod::from_name(m.name()), Some(m));
        }
    }
}
