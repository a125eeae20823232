//! Animated textures compressed with PCA per region (GPU Gems 3 ch. 15.3): a sequence of
//! linear RGB frames becomes a mean and, per region, the leading principal components with
//! one coefficient per frame each ([`AnimatedTexture`]), and [`measure`] reports each region's
//! reconstruction error.
//!
//! Why it is done this way:
//! - Frames are few and pixels many, so each region's PCA diagonalizes the `F × F` Gram matrix
//!   of its centred frames (cyclic Jacobi in f64, `crowdmorph_core::linalg::jacobi`) rather
//!   than the `3P × 3P` covariance: the components are `Xᵀ v / √λ`, the coefficients `√λ v`.
//! - A component is an RGB image, one coefficient per frame: unlike the chapter, which treats
//!   the three channels as three samples of one distribution (three coefficients per component
//!   per frame), this keeps the decode one scalar per layer, the same sum as a wrinkle map's.
//! - Regions get their own counts (the chapter's: more where the eyes are); a component is zero
//!   outside its region, so the decode stays one uniform sum over at most 15 layers (the 16th
//!   is the mean's).
//! - PCA is done on linear values, which is where the renderer adds the layers.

use crowdmorph_core::linalg::jacobi;
use crowdmorph_core::rig::{AnimatedTexture, MAX_LAYERS, TextureRegion};

/// Why frames could not be compressed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TextureError {
    /// Frames, sizes or regions that do not fit together.
    #[error("animated texture: {0}")]
    Invalid(String),
}

/// One region's reconstruction error over every frame.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct RegionError {
    /// The region's name.
    pub name: String,
    /// Components it kept.
    pub components: u32,
    /// Pixels it owns.
    pub pixels: usize,
    /// RMS error of the linear values (0–1), over its pixels' channels and every frame.
    pub rms_linear: f64,
    /// RMS error in 8-bit sRGB units (the decode clamped and encoded, against the frame's).
    pub rms_8bit: f64,
    /// Largest error in 8-bit sRGB units.
    pub max_8bit: f64,
}

/// The default regions of a `width × height` face texture, the chapter's idea: a band across
/// the eyes (rows 20–45 %) with 8 components, the rest with 4.
pub fn default_regions(width: u32, height: u32) -> Vec<TextureRegion> {
    let y0 = height / 5;
    let y1 = (height * 9).div_ceil(20);
    vec![
        TextureRegion {
            name: "eyes".into(),
            rect: [0, y0, width, (y1 - y0).max(1)],
            components: 8,
        },
        TextureRegion {
            name: "rest".into(),
            rect: [0, 0, width, height],
            components: 4,
        },
    ]
}

/// sRGB encoding of a linear value, unrounded, in 8-bit units.
fn srgb255(c: f64) -> f64 {
    let c = c.clamp(0.0, 1.0);
    let s = if c <= 0.003_130_8 {
        c * 12.92
    } else {
        1.055 * c.powf(1.0 / 2.4) - 0.055
    };
    s * 255.0
}

/// Compresses `frames` (each `width × height × 3` linear RGB, rows top to bottom) of clip
/// `clip` for material `material`: the mean of every pixel, then per region its leading
/// components (at most its count, the frames less one, and what has non-zero variance).
pub fn compress(
    clip: &str,
    material: u32,
    width: u32,
    height: u32,
    frames: &[Vec<f32>],
    regions: &[TextureRegion],
) -> Result<AnimatedTexture, TextureError> {
    let bad = |s: String| Err(TextureError::Invalid(s));
    let texels = width as usize * height as usize * 3;
    if frames.is_empty() {
        return bad("no frames".into());
    }
    if let Some(f) = frames.iter().position(|f| f.len() != texels) {
        return bad(format!(
            "frame {f} has {} values, not {width} × {height} × 3",
            frames[f].len()
        ));
    }
    let wanted: u32 = regions.iter().map(|r| r.components).sum();
    if wanted as usize > MAX_LAYERS - 1 {
        return bad(format!(
            "{wanted} components in all; at most {} (one of the {MAX_LAYERS} layers is the mean)",
            MAX_LAYERS - 1
        ));
    }
    let n = frames.len();
    let mut mean = vec![0f64; texels];
    for f in frames {
        for (m, &v) in mean.iter_mut().zip(f) {
            *m += f64::from(v);
        }
    }
    mean.iter_mut().for_each(|m| *m /= n as f64);
    // Each pixel's region.
    let mut owner: Vec<Option<usize>> = Vec::with_capacity(texels / 3);
    for y in 0..height {
        for x in 0..width {
            owner.push(AnimatedTexture::region_of(regions, x, y));
        }
    }
    let mut components: Vec<Vec<f32>> = Vec::new();
    let mut component_region = Vec::new();
    // Per kept component, its coefficient per frame.
    let mut coef: Vec<Vec<f64>> = Vec::new();
    for (r, region) in regions.iter().enumerate() {
        if region.components == 0 {
            continue;
        }
        let idx: Vec<usize> = owner
            .iter()
            .enumerate()
            .filter(|(_, o)| **o == Some(r))
            .flat_map(|(p, _)| [3 * p, 3 * p + 1, 3 * p + 2])
            .collect();
        if idx.is_empty() {
            continue;
        }
        let centred: Vec<Vec<f64>> = frames
            .iter()
            .map(|f| idx.iter().map(|&i| f64::from(f[i]) - mean[i]).collect())
            .collect();
        let mut gram = vec![0f64; n * n];
        for a in 0..n {
            for b in a..n {
                let d: f64 = centred[a].iter().zip(&centred[b]).map(|(x, y)| x * y).sum();
                gram[a * n + b] = d;
                gram[b * n + a] = d;
            }
        }
        let (values, vectors) = jacobi(gram, n);
        let mut order: Vec<usize> = (0..n).collect();
        order.sort_by(|&a, &b| values[b].total_cmp(&values[a]));
        let floor = values.iter().copied().fold(0.0, f64::max) * 1e-12;
        for &e in order.iter().take(region.components as usize) {
            let lambda = values[e];
            if lambda <= floor.max(1e-18) {
                break;
            }
            let s = lambda.sqrt();
            let mut u = vec![0f64; idx.len()];
            for (f, c) in centred.iter().enumerate() {
                let w = vectors[f * n + e] / s;
                for (o, &v) in u.iter_mut().zip(c) {
                    *o += w * v;
                }
            }
            let mut layer = vec![0f32; texels];
            for (&i, &v) in idx.iter().zip(&u) {
                layer[i] = v as f32;
            }
            // The coefficients are the projections of the frames on the f32 component, so
            // that the decode's rounding of the component is compensated where it can be.
            let c: Vec<f64> = centred
                .iter()
                .map(|f| {
                    f.iter()
                        .zip(&idx)
                        .map(|(x, &i)| x * f64::from(layer[i]))
                        .sum()
                })
                .collect();
            components.push(layer);
            component_region.push(r as u32);
            coef.push(c);
        }
    }
    let k = components.len();
    let mut coefficients = vec![0f32; n * k];
    for (j, c) in coef.iter().enumerate() {
        for f in 0..n {
            coefficients[f * k + j] = c[f] as f32;
        }
    }
    let t = AnimatedTexture {
        clip: clip.into(),
        material,
        width,
        height,
        frames: n as u32,
        regions: regions.to_vec(),
        mean: mean.iter().map(|&m| m as f32).collect(),
        components,
        component_region,
        coefficients,
    };
    t.validate()
        .map_err(|e| TextureError::Invalid(e.to_string()))?;
    Ok(t)
}

/// Each region's error of `t`'s CPU decode against `frames` (linear RGB, as given to
/// [`compress`]), plus a last entry `"(none)"` for pixels no region holds, when there are any.
pub fn measure(t: &AnimatedTexture, frames: &[Vec<f32>]) -> Vec<RegionError> {
    let px = t.width as usize * t.height as usize;
    let mut owner = Vec::with_capacity(px);
    for y in 0..t.height {
        for x in 0..t.width {
            owner.push(AnimatedTexture::region_of(&t.regions, x, y).unwrap_or(t.regions.len()));
        }
    }
    let buckets = t.regions.len() + 1;
    let mut sq = vec![0f64; buckets];
    let mut sq8 = vec![0f64; buckets];
    let mut max8 = vec![0f64; buckets];
    let mut count = vec![0usize; buckets];
    for (f, frame) in frames.iter().enumerate().take(t.frames as usize) {
        let d = t.decode(f as u32);
        for (p, &o) in owner.iter().enumerate() {
            if f == 0 {
                count[o] += 1;
            }
            for c in 0..3 {
                let i = 3 * p + c;
                let (Some(&want), Some(&got)) = (frame.get(i), d.get(i)) else {
                    continue;
                };
                let want = f64::from(want);
                let e = got - want;
                sq[o] += e * e;
                let e8 = srgb255(got) - srgb255(want);
                sq8[o] += e8 * e8;
                max8[o] = max8[o].max(e8.abs());
            }
        }
    }
    let n = frames.len().min(t.frames as usize).max(1) as f64;
    (0..buckets)
        .filter(|&b| b < t.regions.len() || count[b] > 0)
        .map(|b| {
            let samples = (count[b] * 3).max(1) as f64 * n;
            RegionError {
                name: t
                    .regions
                    .get(b)
                    .map_or_else(|| "(none)".into(), |r| r.name.clone()),
                components: t
                    .component_region
                    .iter()
                    .filter(|&&r| r as usize == b)
                    .count() as u32,
                pixels: count[b],
                rms_linear: (sq[b] / samples).sqrt(),
                rms_8bit: (sq8[b] / samples).sqrt(),
                max_8bit: max8[b],
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_rank_one_sequence_is_exact_with_one_component() {
        // 4 × 2 pixels, 5 frames: the mean plus a ramp times one image.
        let (w, h) = (4u32, 2u32);
        let pattern: Vec<f32> = (0..w * h * 3).map(|i| (i % 7) as f32 / 20.0).collect();
        let frames: Vec<Vec<f32>> = (0..5)
            .map(|f| pattern.iter().map(|p| 0.3 + p * f as f32 / 5.0).collect())
            .collect();
        let regions = vec![TextureRegion {
            name: "all".into(),
            rect: [0, 0, w, h],
            components: 3,
        }];
        let t = compress("c", 0, w, h, &frames, &regions).expect("compress");
        assert_eq!(t.layers(), 1, "one direction of variance");
        let e = measure(&t, &frames);
        assert_eq!(e.len(), 1);
        assert!(e[0].rms_linear < 1e-6, "{e:?}");
    }

    fn srgb8(c: f64) -> u8 {
        srgb255(c).round() as u8
    }

    fn linear(c: u8) -> f64 {
        let c = f64::from(c) / 255.0;
        if c <= 0.04045 {
            c / 12.92
        } else {
            ((c + 0.055) / 1.055).powf(2.4)
        }
    }

    /// The generated sequence of the issue: 64 × 64, 30 frames. A static face colour, the
    /// eye band (rows 12–28, the default region) blinking and glancing (two images with their
    /// own rhythms: rank 2), the mouth (rows 40–56) opening and stretching (rank 2), and noise
    /// of ±2 8-bit units on every channel, all as 8-bit sRGB frames as a PNG sequence holds.
    /// Returns the frames in linear (what `compress` takes) and the clean signal's distance
    /// from them per default region (eyes, rest): the rank-2 signal is one approximation of
    /// the rank it keeps, so PCA's error can be no larger.
    fn generated() -> (Vec<Vec<f32>>, [f64; 2]) {
        let (w, h, frames) = (64u32, 64u32, 30u32);
        let mut rng = crowdmorph_core::rng::SplitMix64(46);
        let mut out = Vec::new();
        let mut sq = [0f64; 2];
        let mut count = [0f64; 2];
        let regions = default_regions(w, h);
        for f in 0..frames {
            let t = f64::from(f);
            let blink = (t * 0.7).sin().powi(8);
            let glance = (t * 0.23).cos();
            let open = 0.5 + 0.5 * (t * 0.31).sin();
            let stretch = (t * 0.53).cos();
            let mut frame = Vec::with_capacity((w * h * 3) as usize);
            for y in 0..h {
                for x in 0..w {
                    let (fx, fy) = (f64::from(x) / 64.0, f64::from(y) / 64.0);
                    let r = AnimatedTexture::region_of(&regions, x, y).unwrap_or(1);
                    for c in 0..3 {
                        let skin = [0.55, 0.35, 0.28][c] + 0.05 * (fx * 6.0 + fy * 3.0).sin();
                        let mut v = skin;
                        if (12..29).contains(&y) {
                            let lid = (-((fx * 4.0).fract() - 0.5).powi(2) * 30.0).exp();
                            v += blink * lid * [-0.2, -0.15, -0.12][c];
                            v += glance * 0.05 * (fx * 25.0).sin() * [1.0, 0.8, 0.6][c];
                        }
                        if (40..56).contains(&y) {
                            let lips = (-(fx - 0.5).powi(2) * 20.0).exp();
                            v += open * lips * [-0.15, -0.2, -0.18][c];
                            v += stretch * 0.06 * (fx * 9.0).cos() * lips;
                        }
                        let noise = (rng.f64() * 2.0 - 1.0) * 2.0;
                        let coded = srgb8(v.clamp(0.0, 1.0));
                        let noisy = (f64::from(coded) + noise).round().clamp(0.0, 255.0) as u8;
                        let lin = linear(noisy);
                        sq[r] += (lin - v).powi(2);
                        count[r] += 1.0;
                        frame.push(lin as f32);
                    }
                }
            }
            out.push(frame);
        }
        (out, [0, 1].map(|r| (sq[r] / count[r]).sqrt()))
    }

    #[test]
    fn a_generated_sequences_error_per_region_is_within_its_noise() {
        let (frames, noise) = generated();
        let regions = default_regions(64, 64);
        let t = compress("talk", 0, 64, 64, &frames, &regions).expect("compress");
        assert_eq!(t.layers(), 12, "8 components for the eyes, 4 for the rest");
        // The reference decode, independently of AnimatedTexture::decode: the mean plus each
        // component times its coefficient, in f64.
        let k = t.layers();
        for f in [0usize, 17, 29] {
            let d = t.decode(f as u32);
            for i in (0..d.len()).step_by(97) {
                let mut want = f64::from(t.mean[i]);
                for j in 0..k {
                    want += f64::from(t.coefficients[f * k + j]) * f64::from(t.components[j][i]);
                }
                assert!((d[i] - want).abs() < 1e-9);
            }
        }
        let errors = measure(&t, &frames);
        for (e, bound) in errors.iter().zip(noise) {
            println!(
                "region {:>4}: {:2} components, {:4} pixels, RMS {:.3} (8-bit sRGB), max {:.2}, \
                 RMS {:.5} linear (bound {:.5}: the clean signal's distance)",
                e.name, e.components, e.pixels, e.rms_8bit, e.max_8bit, e.rms_linear, bound
            );
            // PCA's k-component fit is the best of all rank-k fits around the mean; the clean
            // signal is rank 2 in each region, so its distance from the frames bounds the
            // error (plus f32 rounding of the stored arrays).
            assert!(e.rms_linear <= bound * 1.0001 + 1e-6, "{e:?} above {bound}");
        }
        // Without components the blink and the mouth are lost: the error is far larger.
        let none: Vec<TextureRegion> = regions
            .iter()
            .map(|r| TextureRegion {
                components: 0,
                ..r.clone()
            })
            .collect();
        let flat = compress("talk", 0, 64, 64, &frames, &none).expect("mean only");
        let flat_errors = measure(&flat, &frames);
        for (a, b) in errors.iter().zip(&flat_errors) {
            println!(
                "region {:>4} mean only: RMS {:.3} (8-bit sRGB), max {:.2}",
                b.name, b.rms_8bit, b.max_8bit
            );
            assert!(b.rms_8bit > 1.1 * a.rms_8bit, "{a:?} vs {b:?}");
        }
    }

    #[test]
    fn too_many_components_are_refused() {
        let regions = vec![TextureRegion {
            name: "all".into(),
            rect: [0, 0, 1, 1],
            components: 16,
        }];
        assert!(compress("c", 0, 1, 1, &[vec![0.0; 3]], &regions).is_err());
        assert!(compress("c", 0, 1, 1, &[], &default_regions(1, 1)).is_err());
    }
}
