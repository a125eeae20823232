//! The five importance metrics of Costigan et al. 2016 §4.1, each comparing an expression with
//! the neutral face.
//!
//! Geometric: mean squared vertex error (Eq. 2) and the symmetric Hausdorff distance between
//! the two vertex sets (Eq. 3, both directions, the larger). Image: pixel MSE (Eq. 4), mean SSIM
//! (Wang, Bovik, Sheikh and Simoncelli 2004) and the perceptual difference of Yee 2004 (the
//! published `pdiff` algorithm: a Laplacian pyramid of luminance, Barten's contrast sensitivity
//! function, Daly's visual masking, Ward's threshold-versus-intensity luminance adaptation; the
//! result is the number of pixels whose difference is visible). Images are the grayscale renders
//! of the reference rasterizer (`super::raster`), read as linear luminance.

use glam::Vec3;
use rstar::RTree;

/// Mean squared length of per-vertex displacements over `vertices` vertices (Eq. 2); vertices
/// absent from `deltas` do not move.
pub fn geometric_mse(deltas: &[Vec3], vertices: usize) -> f64 {
    if vertices == 0 {
        return 0.0;
    }
    deltas
        .iter()
        .map(|d| f64::from(d.length_squared()))
        .sum::<f64>()
        / vertices as f64
}

/// A spatial index over a vertex set, for nearest-vertex queries.
pub struct PointIndex {
    tree: RTree<[f32; 3]>,
}

impl PointIndex {
    /// Indexes `points` (bulk-loaded, so the tree and its answers are deterministic).
    pub fn new(points: &[Vec3]) -> PointIndex {
        PointIndex {
            tree: RTree::bulk_load(points.iter().map(|p| p.to_array()).collect()),
        }
    }

    /// Distance from `p` to the nearest indexed point (infinite when the index is empty).
    pub fn nearest_distance(&self, p: Vec3) -> f32 {
        self.tree
            .nearest_neighbor(p.to_array())
            .map_or(f32::INFINITY, |q| p.distance(Vec3::from_array(*q)))
    }
}

/// Symmetric Hausdorff distance (Eq. 3, the larger of both directions) between the neutral
/// vertex set and the same set displaced by sparse `deltas` at `moved` (indices into
/// `neutral`), given an index over `neutral`.
///
/// Only moved vertices can be far from the other set: an unmoved vertex is in both. And a
/// moved vertex is never farther from the other set than from its own twin, |Δ|; so candidates
/// are visited by |Δ| descending and the search stops once |Δ| cannot beat the distance found.
/// The answer is exact, and costs a handful of nearest-neighbour queries rather than O(n²).
pub fn hausdorff(
    neutral: &[Vec3],
    neutral_index: &PointIndex,
    moved: &[u32],
    deltas: &[Vec3],
) -> f64 {
    let mut by_len: Vec<(f32, usize)> = deltas
        .iter()
        .enumerate()
        .map(|(k, d)| (d.length(), k))
        .filter(|&(l, _)| l > 0.0)
        .collect();
    if by_len.is_empty() {
        return 0.0;
    }
    by_len.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
    let mut posed = neutral.to_vec();
    for (&v, &d) in moved.iter().zip(deltas) {
        if let Some(p) = posed.get_mut(v as usize) {
            *p += d;
        }
    }
    let posed_index = PointIndex::new(&posed);
    let mut h = 0f32;
    // Neutral → expression: a moved vertex's neutral position against the posed set.
    for &(len, k) in &by_len {
        if len <= h {
            break;
        }
        let Some(&v) = moved.get(k) else { continue };
        h = h.max(posed_index.nearest_distance(neutral[v as usize]));
    }
    // Expression → neutral.
    for &(len, k) in &by_len {
        if len <= h {
            break;
        }
        let Some(&v) = moved.get(k) else { continue };
        h = h.max(neutral_index.nearest_distance(posed[v as usize]));
    }
    f64::from(h)
}

/// Mean squared pixel difference (Eq. 4). Images must have the same size.
pub fn image_mse(a: &[f32], b: &[f32]) -> f64 {
    if a.is_empty() {
        return 0.0;
    }
    a.iter()
        .zip(b)
        .map(|(&x, &y)| {
            let d = f64::from(x) - f64::from(y);
            d * d
        })
        .sum::<f64>()
        / a.len() as f64
}

/// Side of the SSIM window (Wang et al. 2004: 11 × 11).
pub const SSIM_WINDOW: usize = 11;
/// Standard deviation of the SSIM Gaussian window, in pixels.
pub const SSIM_SIGMA: f64 = 1.5;
/// SSIM stabilising constant K1 (C1 = (K1·L)²).
pub const SSIM_K1: f64 = 0.01;
/// SSIM stabilising constant K2 (C2 = (K2·L)²).
pub const SSIM_K2: f64 = 0.03;

/// Mean SSIM of two `width × height` images with dynamic range 1 (Wang et al. 2004): an
/// 11 × 11 circular Gaussian window (σ = 1.5) normalised to sum 1, K1 = 0.01, K2 = 0.03, the map
/// averaged over the window positions that fit inside the image (MATLAB `filter2(..., 'valid')`
/// as in the authors' `ssim_index.m`). Identical images score exactly 1. Images smaller than the
/// window are compared as a single window of their own size.
pub fn ssim(a: &[f32], b: &[f32], width: usize, height: usize) -> f64 {
    if width == 0 || height == 0 {
        return 1.0;
    }
    let c1 = (SSIM_K1 * 1.0).powi(2);
    let c2 = (SSIM_K2 * 1.0).powi(2);
    let win = SSIM_WINDOW.min(width).min(height);
    let half = (win as f64 - 1.0) / 2.0;
    let mut kernel: Vec<f64> = (0..win)
        .map(|i| {
            let x = i as f64 - half;
            (-(x * x) / (2.0 * SSIM_SIGMA * SSIM_SIGMA)).exp()
        })
        .collect();
    let sum: f64 = kernel.iter().sum();
    kernel.iter_mut().for_each(|k| *k /= sum);
    let (ow, oh) = (width - win + 1, height - win + 1);
    // Separable 'valid' filtering of the five moment images at once.
    let px = |img: &[f32], x: usize, y: usize| f64::from(img[y * width + x]);
    let mut rows = vec![[0f64; 5]; ow * height];
    for y in 0..height {
        for x in 0..ow {
            let mut acc = [0f64; 5];
            for (k, &w) in kernel.iter().enumerate() {
                let (p, q) = (px(a, x + k, y), px(b, x + k, y));
                acc[0] += w * p;
                acc[1] += w * q;
                acc[2] += w * p * p;
                acc[3] += w * q * q;
                acc[4] += w * p * q;
            }
            rows[y * ow + x] = acc;
        }
    }
    let mut total = 0f64;
    for y in 0..oh {
        for x in 0..ow {
            let mut m = [0f64; 5];
            for (k, &w) in kernel.iter().enumerate() {
                let r = &rows[(y + k) * ow + x];
                for c in 0..5 {
                    m[c] += w * r[c];
                }
            }
            let (mu_a, mu_b) = (m[0], m[1]);
            let var_a = m[2] - mu_a * mu_a;
            let var_b = m[3] - mu_b * mu_b;
            let cov = m[4] - mu_a * mu_b;
            total += ((2.0 * mu_a * mu_b + c1) * (2.0 * cov + c2))
                / ((mu_a * mu_a + mu_b * mu_b + c1) * (var_a + var_b + c2));
        }
    }
    total / (ow * oh) as f64
}

/// Viewing conditions of Yee's metric (the `perceptualdiff` defaults).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct YeeParams {
    /// Horizontal field of view of the image, in degrees.
    pub field_of_view: f32,
    /// Luminance of a full-intensity pixel, in cd/m².
    pub luminance: f32,
}

impl Default for YeeParams {
    fn default() -> Self {
        YeeParams {
            field_of_view: 45.0,
            luminance: 100.0,
        }
    }
}

/// Levels of the Laplacian pyramid in Yee's metric.
const PYRAMID_LEVELS: usize = 8;

/// Threshold-versus-intensity (Ward Larson, Rushmeier and Piatko 1997): the just-noticeable
/// luminance difference at adaptation luminance `a` (cd/m²).
fn tvi(a: f32) -> f32 {
    let log_a = a.log10();
    let r = if log_a < -3.94 {
        -2.86
    } else if log_a < -1.44 {
        (0.405 * log_a + 1.6).powf(2.18) - 2.86
    } else if log_a < -0.0184 {
        log_a - 0.395
    } else if log_a < 1.9 {
        (0.249 * log_a + 0.65).powf(2.7) - 0.72
    } else {
        log_a - 1.255
    };
    10f32.powf(r)
}

/// Barten's contrast sensitivity at `cpd` cycles per degree and adaptation luminance `lum`.
fn csf(cpd: f32, lum: f32) -> f32 {
    let a = 440.0 * (1.0 + 0.7 / lum).powf(-0.2);
    let b = 0.3 * (1.0 + 100.0 / lum).powf(0.15);
    a * cpd * (-b * cpd).exp() * (1.0 + 0.06 * (b * cpd).exp()).sqrt()
}

/// Daly's visual masking elevation for a (CSF-weighted) contrast.
fn mask(contrast: f32) -> f32 {
    let a = (392.498 * contrast).powf(0.7);
    let b = (0.0153 * a).powf(4.0);
    (1.0 + b).powf(0.25)
}

/// Yee's Gaussian pyramid (all levels at full resolution, 5-tap filter, mirrored borders):
/// level 0 is the image, level i + 1 the blur of level i.
fn pyramid(img: &[f32], width: usize, height: usize) -> Vec<Vec<f32>> {
    const K: [f32; 5] = [0.05, 0.25, 0.4, 0.25, 0.05];
    let mirror = |i: i64, n: usize| -> usize {
        let n = n as i64;
        let j = if i < 0 {
            -i
        } else if i >= n {
            2 * n - i - 1
        } else {
            i
        };
        j.clamp(0, n - 1) as usize
    };
    let mut levels = vec![img.to_vec()];
    let mut tmp = vec![0f32; img.len()];
    for _ in 1..PYRAMID_LEVELS {
        let Some(prev) = levels.last() else { break };
        for y in 0..height {
            for x in 0..width {
                let mut s = 0f32;
                for (k, &w) in K.iter().enumerate() {
                    s += w * prev[y * width + mirror(x as i64 + k as i64 - 2, width)];
                }
                tmp[y * width + x] = s;
            }
        }
        let mut next = vec![0f32; img.len()];
        for y in 0..height {
            for x in 0..width {
                let mut s = 0f32;
                for (k, &w) in K.iter().enumerate() {
                    s += w * tmp[mirror(y as i64 + k as i64 - 2, height) * width + x];
                }
                next[y * width + x] = s;
            }
        }
        levels.push(next);
    }
    levels
}

/// A reference image prepared for Yee's metric (its pyramid), so the neutral face is
/// decomposed once and compared against every expression.
pub struct YeeReference {
    width: usize,
    height: usize,
    pyramid: Vec<Vec<f32>>,
    params: YeeParams,
}

impl YeeReference {
    /// Prepares `img` (`width × height`, linear intensities in [0, 1]).
    pub fn new(img: &[f32], width: usize, height: usize, params: YeeParams) -> YeeReference {
        let lum: Vec<f32> = img.iter().map(|&v| v.max(0.0) * params.luminance).collect();
        YeeReference {
            width,
            height,
            pyramid: pyramid(&lum, width, height),
            params,
        }
    }

    /// Number of pixels of `img` whose difference from the reference is perceptible
    /// (Yee 2004, luminance test; the images are grayscale, so the colour test does not apply).
    pub fn failing_pixels(&self, img: &[f32]) -> u64 {
        let (w, h) = (self.width, self.height);
        let lum: Vec<f32> = img
            .iter()
            .map(|&v| v.max(0.0) * self.params.luminance)
            .collect();
        // A pixel whose luminance is the same in both images passes whatever its threshold, so
        // only images that differ need a pyramid, and only differing pixels need the test.
        if lum.len() != w * h || lum == self.pyramid[0] {
            return 0;
        }
        let lb = pyramid(&lum, w, h);
        let la = &self.pyramid;
        let fov = self.params.field_of_view;
        let one_degree_pixels = 2.0 * (fov * 0.5).to_radians().tan() * 180.0 / std::f32::consts::PI;
        let pixels_per_degree = w as f32 / one_degree_pixels;
        let mut adaptation_level = 0;
        let mut num_pixels = 1.0f32;
        for i in 0..PYRAMID_LEVELS {
            adaptation_level = i;
            if num_pixels > one_degree_pixels {
                break;
            }
            num_pixels *= 2.0;
        }
        let mut cpd = [0f32; PYRAMID_LEVELS];
        cpd[0] = 0.5 * pixels_per_degree;
        for i in 1..PYRAMID_LEVELS {
            cpd[i] = 0.5 * cpd[i - 1];
        }
        let csf_max = csf(3.248, 100.0);
        let mut f_freq = [0f32; PYRAMID_LEVELS - 2];
        for (i, f) in f_freq.iter_mut().enumerate() {
            *f = csf_max / csf(cpd[i], 100.0);
        }
        let mut failed = 0u64;
        for i in 0..w * h {
            let delta = (la[0][i] - lb[0][i]).abs();
            if delta == 0.0 {
                continue;
            }
            let mut contrast = [0f32; PYRAMID_LEVELS - 2];
            let mut sum_contrast = 0f32;
            for (l, c) in contrast.iter_mut().enumerate() {
                let n1 = (la[l][i] - la[l + 1][i]).abs();
                let n2 = (lb[l][i] - lb[l + 1][i]).abs();
                let d1 = la[l + 2][i].abs();
                let d2 = lb[l + 2][i].abs();
                *c = n1.max(n2) / d1.max(d2).max(1e-5);
                sum_contrast += *c;
            }
            let sum_contrast = sum_contrast.max(1e-5);
            let adapt = ((la[adaptation_level][i] + lb[adaptation_level][i]) * 0.5).max(1e-5);
            let mut factor = 0f32;
            for (l, &c) in contrast.iter().enumerate() {
                let f_mask = mask(c * csf(cpd[l], adapt));
                factor += c * f_freq[l] * f_mask / sum_contrast;
            }
            let factor = factor.clamp(1.0, 10.0);
            if delta > factor * tvi(adapt) {
                failed += 1;
            }
        }
        failed
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn gradient(w: usize, h: usize) -> Vec<f32> {
        (0..w * h)
            .map(|i| {
                ((i % w) as f32 / w as f32 * 0.8 + (i / w) as f32 / h as f32 * 0.2)
                    .sin()
                    .abs()
            })
            .collect()
    }

    #[test]
    fn identical_images_score_perfect() {
        let a = gradient(64, 48);
        assert_eq!(image_mse(&a, &a), 0.0);
        assert_eq!(ssim(&a, &a, 64, 48), 1.0);
        let r = YeeReference::new(&a, 64, 48, YeeParams::default());
        assert_eq!(r.failing_pixels(&a), 0);
    }

    #[test]
    fn different_images_score_worse() {
        let a = gradient(64, 64);
        let mut b = a.clone();
        for y in 20..40 {
            for x in 20..40 {
                b[y * 64 + x] = 1.0 - b[y * 64 + x];
            }
        }
        assert!(image_mse(&a, &b) > 0.0);
        let s = ssim(&a, &b, 64, 64);
        assert!(s < 0.95 && s > -1.0, "{s}");
        let r = YeeReference::new(&a, 64, 64, YeeParams::default());
        let failed = r.failing_pixels(&b);
        // Only changed pixels can fail; strong contrast masks some of them (Daly's masking).
        assert!(failed > 0 && failed <= 400, "{failed}");
        // On a flat field a bright square is plainly visible. (The image must span enough
        // pixels per degree of the 45° field of view: at 64 pixels wide each pixel is 0.7°,
        // where contrast sensitivity is low and the same square passes.)
        let n = 384;
        let flat = vec![0.5f32; n * n];
        let mut square = flat.clone();
        for y in 140..240 {
            for x in 140..240 {
                square[y * n + x] = 0.8;
            }
        }
        let r = YeeReference::new(&flat, n, n, YeeParams::default());
        let failed = r.failing_pixels(&square);
        assert!(failed > 5_000 && failed <= 10_000, "{failed}");
        // A change far below the visibility threshold fails no pixel.
        let c: Vec<f32> = a.iter().map(|v| v * 1.0001).collect();
        assert_eq!(r.failing_pixels(&c), 0);
    }

    #[test]
    fn ssim_matches_a_hand_computed_constant_shift() {
        // Constant images a and b: σ = 0, so SSIM = (2ab + C1) / (a² + b² + C1).
        let a = vec![0.5f32; 16 * 16];
        let b = vec![0.25f32; 16 * 16];
        let c1 = 0.0001;
        let want = (2.0 * 0.5 * 0.25 + c1) / (0.25 + 0.0625 + c1);
        assert!((ssim(&a, &b, 16, 16) - want).abs() < 1e-9);
    }

    #[test]
    fn hausdorff_is_exact_on_a_small_set() {
        let neutral: Vec<Vec3> = (0..10).map(|i| Vec3::new(i as f32, 0.0, 0.0)).collect();
        let index = PointIndex::new(&neutral);
        // Vertex 3 moves up by 2: nearest neutral point of its new place is still at distance 2.
        assert_eq!(
            hausdorff(&neutral, &index, &[3], &[Vec3::new(0.0, 2.0, 0.0)]),
            2.0
        );
        // Vertex 3 slides onto vertex 4's place: the posed set still covers 4 but no longer 3,
        // whose nearest posed neighbours (2 and 4) are at distance 1.
        assert_eq!(hausdorff(&neutral, &index, &[3], &[Vec3::X]), 1.0);
        assert_eq!(hausdorff(&neutral, &index, &[], &[]), 0.0);
        assert!((geometric_mse(&[Vec3::new(0.0, 2.0, 0.0)], 10) - 0.4).abs() < 1e-12);
    }
}
