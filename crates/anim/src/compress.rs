//! Compressed clips: weight tables stored with an error budget stated in vertex space
//! (GPU Gems 3 ch. 15 compresses its captured animation; ACL's per-curve codec is the anchor).
//!
//! **The budget.** A clip is compressed so that no vertex of any frame moves by more than
//! `max_error × diagonal`. Weight channel `k` is quantized with step `s_k = 2·c·E / L_k` (`L_k`:
//! its longest delta; `E = max_error × diagonal`), with `c = 1 / maxᵥ Σₖ ‖Δₖ(v)‖ / L_k`, so
//! that at every vertex `Σₖ (s_k / 2)·‖Δₖ(v)‖ ≤ E`: a weight that moves a large delta gets
//! more bits, and the bound holds by the triangle inequality whatever the errors' signs.
//!
//! **The codec** (per curve, ACL's approach): quantized weights predicted linearly from the two
//! before (`2q[t−1] − q[t−2]`), the residuals zigzag varints, curve after curve; frames are cut
//! into segments of [`SEGMENT`] frames, each predicted from its own start and entropy-coded
//! with zstd on its own (with its content checksum, so a damaged segment is an error, not other
//! weights), so any frame decodes from its segment alone.
//!
//! **PCA** (the chapter's codec): a [`Basis`] — the mean and principal components of every
//! frame of the library's clips, shared by them — and per clip the fewest components that keep
//! half the budget, their per-frame coefficients coded as curves are with steps that keep the
//! other half ([`compress_pca`]). The caller keeps the smaller of the two per clip.

use crate::varint::{get_varint, put_varint, unzigzag, zigzag};
use crowdmorph_core::rig::{Clip, Rig};

/// Frames per independently decodable segment.
pub const SEGMENT: u32 = 32;

/// zstd level of the segments (clips are compressed once, decoded often).
const LEVEL: i32 = 19;

/// A clip compressed by [`compress`].
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Compressed {
    /// Clip name.
    pub name: String,
    /// Frames per second.
    pub fps: f32,
    /// Frames.
    pub frames: u32,
    /// Weight channels.
    pub targets: u32,
    /// Per channel, the quantization step (0: the channel is constant, stored as its value).
    pub steps: Vec<f32>,
    /// Per channel, the value of step 0 (quantized weights are `base + q × step`).
    pub bases: Vec<f32>,
    /// The zstd-compressed segments.
    pub segments: Vec<Vec<u8>>,
    /// PCA-coded: the streams are the first this many components' coefficients of a
    /// [`Basis`] (decode with [`decode_with`]); `None`: the streams are the weight curves.
    pub components: Option<usize>,
}

impl Compressed {
    /// `clip` coded as `streams` (curves, or `components` PCA coefficients).
    fn of(clip: &Clip, (steps, bases, segments): Streams, components: Option<usize>) -> Compressed {
        Compressed {
            name: clip.name.clone(),
            fps: clip.fps,
            frames: clip.frames,
            targets: clip.targets,
            steps,
            bases,
            segments,
            components,
        }
    }

    /// Bytes of the compressed form: the segments, the steps and bases, a small header.
    pub fn bytes(&self) -> usize {
        self.segments.iter().map(|s| s.len() + 4).sum::<usize>() + self.steps.len() * 8 + 16
    }

    /// Bytes of the clip's f32 table.
    pub fn f32_bytes(&self) -> usize {
        self.frames as usize * self.targets as usize * 4
    }
}

/// Why a compressed clip does not decode.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum DecodeError {
    /// A segment is corrupt or truncated.
    #[error("segment {0}: {1}")]
    Corrupt(usize, String),
    /// The header disagrees with itself or with the rig (its shape, steps, segment count).
    #[error("{0}")]
    Malformed(String),
}

/// Per channel, the quantization step of the module doc's budget (0 for channels that move
/// no vertex).
pub fn steps(rig: &Rig, max_error: f32) -> Vec<f32> {
    let k = rig.targets.len();
    let mut longest = vec![0f32; k];
    for p in rig.primitives.iter() {
        for t in &p.targets {
            let l = t.positions.iter().map(|d| d.length()).fold(0.0, f32::max);
            longest[t.target as usize] = longest[t.target as usize].max(l);
        }
    }
    // maxᵥ Σₖ ‖Δₖ(v)‖ / L_k, per primitive's vertices.
    let mut worst = 0f32;
    for p in rig.primitives.iter() {
        let mut sum = vec![0f32; p.positions.len()];
        for t in &p.targets {
            let l = longest[t.target as usize];
            if l > 0.0 {
                for (&v, d) in t.vertices.iter().zip(&t.positions) {
                    sum[v as usize] += d.length() / l;
                }
            }
        }
        worst = sum.into_iter().fold(worst, f32::max);
    }
    let budget = max_error * rig.bbox().diagonal();
    let c = if worst > 0.0 { 1.0 / worst } else { 0.0 };
    longest
        .iter()
        .map(|&l| if l > 0.0 { 2.0 * c * budget / l } else { 0.0 })
        .collect()
}

/// Compresses `clip` of `rig` within `max_error × diagonal` per vertex (zstd fails only when
/// it cannot allocate).
pub fn compress(rig: &Rig, clip: &Clip, max_error: f32) -> std::io::Result<Compressed> {
    let k = clip.targets as usize;
    let mut steps = steps(rig, max_error);
    steps.resize(k, 0.0);
    let streams = encode_streams(&clip.weights, clip.frames as usize, steps)?;
    Ok(Compressed::of(clip, streams, None))
}

/// Encoded streams: per stream its step and base, then the zstd segments.
type Streams = (Vec<f32>, Vec<f32>, Vec<Vec<u8>>);

/// Quantizes `values` (streams × `n` frames, row-major) with `steps` per stream, predicts and
/// entropy-codes them in segments; a constant stream (or one of step 0) is its first value.
fn encode_streams(values: &[f32], n: usize, mut steps: Vec<f32>) -> std::io::Result<Streams> {
    let k = steps.len();
    let mut bases = vec![0f32; k];
    for t in 0..k {
        let curve = &values[t * n..(t + 1) * n];
        let constant = curve.iter().all(|&w| w == curve[0]);
        bases[t] = curve.first().copied().unwrap_or(0.0);
        // A NaN or non-positive step (a channel that moves nothing) stores the constant.
        if constant || steps[t].is_nan() || steps[t] <= 0.0 {
            steps[t] = 0.0;
        }
    }
    let q = |t: usize, f: usize| -> i64 {
        if steps[t] == 0.0 {
            0
        } else {
            (f64::from(values[t * n + f] - bases[t]) / f64::from(steps[t])).round() as i64
        }
    };
    let mut segments = Vec::new();
    // Each segment carries zstd's content checksum, so a damaged one fails to decode instead
    // of decoding to other weights.
    let mut zstd = zstd::bulk::Compressor::new(LEVEL)?;
    zstd.set_parameter(zstd::zstd_safe::CParameter::ChecksumFlag(true))?;
    for start in (0..n).step_by(SEGMENT as usize) {
        let end = (start + SEGMENT as usize).min(n);
        let mut raw = Vec::with_capacity((end - start) * k);
        for (t, &step) in steps.iter().enumerate() {
            if step == 0.0 {
                continue;
            }
            let (mut p1, mut p2) = (0i64, 0i64);
            for (i, f) in (start..end).enumerate() {
                let predicted = match i {
                    0 => 0,
                    1 => p1,
                    _ => 2 * p1 - p2,
                };
                let v = q(t, f);
                put_varint(&mut raw, zigzag(v - predicted));
                p2 = p1;
                p1 = v;
            }
        }
        segments.push(zstd.compress(&raw)?);
    }
    Ok((steps, bases, segments))
}

/// Decodes segment `s` into `out` (targets × frames, row-major, the clip's layout).
fn decode_segment(c: &Compressed, s: usize, out: &mut [f32]) -> Result<(), DecodeError> {
    let n = c.frames as usize;
    let start = s * SEGMENT as usize;
    let end = (start + SEGMENT as usize).min(n);
    let len = end - start;
    let active = c.steps.iter().filter(|&&x| x != 0.0).count();
    let seg = c
        .segments
        .get(s)
        .ok_or_else(|| DecodeError::Corrupt(s, "missing".into()))?;
    // At most 10 bytes a varint: a bound that also refuses a zstd frame claiming more.
    let raw = zstd::bulk::decompress(seg, active * len * 10)
        .map_err(|e| DecodeError::Corrupt(s, e.to_string()))?;
    let mut at = 0;
    for t in 0..c.steps.len() {
        let row = &mut out[t * n + start..t * n + end];
        if c.steps[t] == 0.0 {
            row.fill(c.bases[t]);
            continue;
        }
        let (mut p1, mut p2) = (0i64, 0i64);
        for (i, w) in row.iter_mut().enumerate() {
            let predicted = match i {
                0 => 0,
                1 => p1,
                _ => 2 * p1 - p2,
            };
            let r = get_varint(&raw, &mut at)
                .ok_or_else(|| DecodeError::Corrupt(s, "truncated".into()))?;
            let v = predicted + unzigzag(r);
            *w = c.bases[t] + (v as f64 * f64::from(c.steps[t])) as f32;
            p2 = p1;
            p1 = v;
        }
    }
    if at != raw.len() {
        return Err(DecodeError::Corrupt(s, "trailing bytes".into()));
    }
    Ok(())
}

/// The decoded streams (streams × frames).
fn decode_streams(c: &Compressed) -> Result<Vec<f32>, DecodeError> {
    let mut out = vec![0f32; c.frames as usize * c.steps.len()];
    for s in 0..c.segments.len() {
        decode_segment(c, s, &mut out)?;
    }
    Ok(out)
}

/// The whole table (targets × frames) of a curve-coded clip.
pub fn decode(c: &Compressed) -> Result<Vec<f32>, DecodeError> {
    if c.components.is_some() {
        return Err(DecodeError::Corrupt(
            0,
            "PCA-coded: decode with its basis".into(),
        ));
    }
    decode_streams(c)
}

/// The whole table (targets × frames) of a clip coded either way.
pub fn decode_with(c: &Compressed, basis: &Basis) -> Result<Vec<f32>, DecodeError> {
    let Some(m) = c.components else {
        return decode(c);
    };
    let coeffs = decode_streams(c)?;
    Ok(reconstruct(basis, m, &coeffs, c.frames as usize))
}

/// Weights (targets × n) from `m` components' coefficients (m × n): `mean + Σ c_j U_j`.
fn reconstruct(basis: &Basis, m: usize, coeffs: &[f32], n: usize) -> Vec<f32> {
    let k = basis.mean.len();
    let mut out = vec![0f32; k * n];
    for t in 0..k {
        for f in 0..n {
            out[t * n + f] = basis.mean[t]
                + (0..m)
                    .map(|j| basis.components[j][t] * coeffs[j * n + f])
                    .sum::<f32>();
        }
    }
    out
}

/// One frame's weights of a curve-coded clip, decoding only its segment.
pub fn decode_frame(c: &Compressed, frame: u32) -> Result<Vec<f32>, DecodeError> {
    let n = c.frames as usize;
    let mut table = vec![0f32; n * c.steps.len()];
    decode_segment(c, (frame / SEGMENT) as usize, &mut table)?;
    Ok((0..c.steps.len())
        .map(|t| table[t * n + frame as usize])
        .collect())
}

impl Compressed {
    /// Checks the header before anything is allocated from it: a shape a clip may have, one
    /// step and base per channel of a rig with `targets` channels, one segment per
    /// [`SEGMENT`] frames, finite steps and bases, and curves (not PCA coefficients).
    pub fn check(&self, targets: usize) -> Result<(), DecodeError> {
        let bad = |m: String| Err(DecodeError::Malformed(m));
        if self.components.is_some() {
            return bad("PCA-coded without its basis".into());
        }
        if self.frames == 0 || self.frames as usize > crowdmorph_core::rig::MAX_FRAMES {
            return bad(format!("{} frames", self.frames));
        }
        if self.targets as usize != targets
            || self.steps.len() != targets
            || self.bases.len() != targets
        {
            return bad(format!(
                "{} channels ({} steps, {} bases) for a rig of {targets}",
                self.targets,
                self.steps.len(),
                self.bases.len()
            ));
        }
        if self.segments.len() != self.frames.div_ceil(SEGMENT) as usize {
            return bad(format!(
                "{} segments for {} frames",
                self.segments.len(),
                self.frames
            ));
        }
        if let Some(t) = (0..targets).find(|&t| {
            !(self.steps[t].is_finite() && self.steps[t] >= 0.0 && self.bases[t].is_finite())
        }) {
            return bad(format!("channel {t}: step or base not finite"));
        }
        Ok(())
    }

    /// The clip it decodes to, checked as an imported clip is ([`Clip::validate`]).
    pub fn to_clip(&self, targets: usize) -> Result<Clip, DecodeError> {
        self.check(targets)?;
        let weights = decode(self)?;
        Clip::new(
            self.name.clone(),
            self.fps,
            targets,
            self.frames as usize,
            weights,
        )
        .map_err(|e| DecodeError::Malformed(e.to_string()))
    }
}

/// A clip's stored form: curve-coded, or transform-coded ([`crate::transform`]).
#[derive(Clone, Debug, PartialEq)]
pub enum Stored {
    /// The curve codec of this module (a fixed point: its decoded clip codes to itself).
    Curves(Compressed),
    /// The transform codec (kept by [`crate::transform::remember`] for the store's writer).
    Transform(crate::transform::TransformCoded),
}

impl Stored {
    /// Bytes of the coded form.
    pub fn bytes(&self) -> usize {
        match self {
            Stored::Curves(c) => c.bytes(),
            Stored::Transform(t) => t.bytes(),
        }
    }
}

/// `clip` as a store that compresses clips keeps it: the smaller of the curve codec and the
/// transform codec within the budget, and the clip that decodes from it (what the server then
/// plays, so that what it serves before and after a restart is the same). Applying it again
/// changes nothing for a curve-coded clip: decoded weights sit on their channel's quantization
/// lattice, which quantizes to itself. A transform-coded clip is not its encoder's fixed point,
/// so its coded form is remembered ([`crate::transform::remember`]) and a store writes that;
/// applying this again to its decoded clip returns that remembered form.
pub fn stored_form(rig: &Rig, clip: &Clip, max_error: f32) -> std::io::Result<(Stored, Clip)> {
    if let Some(t) = crate::transform::recall(clip) {
        return Ok((Stored::Transform(t), clip.clone()));
    }
    let (c, decoded) = curves_stored_form(rig, clip, max_error)?;
    let metric = crate::transform::Metric::of(rig);
    if let Some(t) =
        crate::transform::compress(rig, &metric, clip, max_error)?.filter(|t| t.bytes() < c.bytes())
    {
        let decoded = t
            .to_clip(rig.targets.len())
            .map_err(|e| std::io::Error::other(e.to_string()))?;
        crate::transform::remember(&t, &decoded);
        return Ok((Stored::Transform(t), decoded));
    }
    Ok((Stored::Curves(c), decoded))
}

/// `clip` curve-coded within the budget and the clip that decodes from it (a fixed point:
/// applying it to that clip gives the same bytes and the same clip).
pub fn curves_stored_form(
    rig: &Rig,
    clip: &Clip,
    max_error: f32,
) -> std::io::Result<(Compressed, Clip)> {
    let c = compress(rig, clip, max_error)?;
    let decoded = c
        .to_clip(rig.targets.len())
        .map_err(|e| std::io::Error::other(e.to_string()))?;
    Ok((c, decoded))
}

/// A blend of PCA-coded frames, done where the chapter does it: on the coefficients. Each
/// term is a clip coded with `basis`, a frame and a fraction; the fractions sum to 1 (the
/// caller's canonical blend, [`crowdmorph_core::rig::Pose`]). Only each frame's segment is decoded, the
/// coefficients are mixed, and one frame's weights are rebuilt — the same weights as blending
/// the decoded frames, since `mean + U·Σ tᵢcᵢ = Σ tᵢ(mean + U·cᵢ)` when `Σ tᵢ = 1`.
pub fn blend_pca(
    basis: &Basis,
    terms: &[(&Compressed, u32, f32)],
) -> Result<Vec<f32>, DecodeError> {
    let m = terms
        .iter()
        .map(|(c, _, _)| c.components.unwrap_or(0))
        .max()
        .unwrap_or(0);
    if m > basis.components.len() {
        return Err(DecodeError::Malformed(format!(
            "{m} components of a basis of {}",
            basis.components.len()
        )));
    }
    let mut mixed = vec![0f32; m];
    for &(c, frame, t) in terms {
        let Some(mc) = c.components else {
            return Err(DecodeError::Malformed(format!(
                "clip {:?} is not PCA-coded",
                c.name
            )));
        };
        if frame >= c.frames || c.steps.len() != mc {
            return Err(DecodeError::Malformed(format!(
                "frame {frame} of clip {:?} ({} frames, {} streams for {mc} components)",
                c.name,
                c.frames,
                c.steps.len()
            )));
        }
        let n = c.frames as usize;
        let mut table = vec![0f32; n * mc];
        decode_segment(c, (frame / SEGMENT) as usize, &mut table)?;
        for (j, x) in mixed.iter_mut().enumerate().take(mc) {
            *x += t * table[j * n + frame as usize];
        }
    }
    Ok(reconstruct(basis, m, &mixed, 1))
}

/// The first `m` components' coefficients of every frame of `clip` (m × frames).
fn project(basis: &Basis, clip: &Clip, m: usize) -> Vec<f32> {
    let (n, k) = (clip.frames as usize, basis.mean.len());
    let mut out = vec![0f32; m * n];
    let mut w = vec![0f32; k];
    for f in 0..n {
        clip.frame_weights(f as u32, &mut w);
        for j in 0..m {
            out[j * n + f] = (0..k)
                .map(|t| basis.components[j][t] * (w[t] - basis.mean[t]))
                .sum();
        }
    }
    out
}

/// Compresses `clip` with the library's PCA `basis`: the fewest components whose
/// reconstruction stays within half the budget (measured at every frame and vertex), their
/// coefficients quantized so that the other half bounds their error (component j's step is
/// `E / (m · M_j)`, `M_j = maxᵥ Σₖ |U_kj| ‖Δₖ(v)‖`), then predicted and entropy-coded as
/// curves are. `None` when even every component misses the budget.
pub fn compress_pca(
    rig: &Rig,
    clip: &Clip,
    basis: &Basis,
    max_error: f32,
) -> std::io::Result<Option<Compressed>> {
    let n = clip.frames as usize;
    let k = rig.targets.len();
    let coeffs_of = |m: usize| project(basis, clip, m);
    let half = max_error / 2.0;
    // The fewest components within half the budget: the error falls as components are added,
    // so a binary search over the count.
    let fits = |m: usize| {
        let table = reconstruct(basis, m, &coeffs_of(m), n);
        measure(rig, clip, &table, half).max <= f64::from(half)
    };
    if !fits(k) {
        return Ok(None);
    }
    let (mut lo, mut hi) = (0usize, k);
    while lo < hi {
        let mid = (lo + hi) / 2;
        if fits(mid) { hi = mid } else { lo = mid + 1 }
    }
    let m = lo;
    let budget = f64::from(half * rig.bbox().diagonal());
    let steps: Vec<f32> = (0..m)
        .map(|j| {
            let mut worst = 0f64;
            for p in rig.primitives.iter() {
                let mut sum = vec![0f64; p.positions.len()];
                for t in &p.targets {
                    let u = f64::from(basis.components[j][t.target as usize].abs());
                    for (&v, d) in t.vertices.iter().zip(&t.positions) {
                        sum[v as usize] += u * f64::from(d.length());
                    }
                }
                worst = sum.into_iter().fold(worst, f64::max);
            }
            if worst > 0.0 {
                (2.0 * budget / (m as f64 * worst)) as f32
            } else {
                0.0
            }
        })
        .collect();
    let streams = encode_streams(&coeffs_of(m), n, steps)?;
    Ok(Some(Compressed::of(clip, streams, Some(m))))
}

/// ACL's report of a compressed clip, in vertex space: each frame's largest vertex error
/// against the original, as a fraction of the diagonal.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct ErrorReport {
    /// Largest vertex error over all frames.
    pub max: f64,
    /// 99th percentile of the per-(frame, vertex) errors.
    pub p99: f64,
    /// Share of (frame, vertex) samples within the budget.
    pub under_budget: f64,
}

/// Measures `decoded` (targets × frames) against `clip` at every frame and vertex, with the
/// sparse deltas directly (the f64 sum of Eq. 1's differences).
pub fn measure(rig: &Rig, clip: &Clip, decoded: &[f32], max_error: f32) -> ErrorReport {
    let n = clip.frames as usize;
    let diag = f64::from(rig.bbox().diagonal()).max(1e-12);
    let mut errors: Vec<f64> = Vec::new();
    for f in 0..n {
        for p in rig.primitives.iter() {
            let mut d = vec![glam::DVec3::ZERO; p.positions.len()];
            for t in &p.targets {
                let k = t.target as usize;
                let dw = f64::from(decoded[k * n + f]) - f64::from(clip.weights[k * n + f]);
                if dw != 0.0 {
                    for (&v, delta) in t.vertices.iter().zip(&t.positions) {
                        d[v as usize] += dw * delta.as_dvec3();
                    }
                }
            }
            errors.extend(d.iter().map(|x| x.length() / diag));
        }
    }
    errors.sort_by(f64::total_cmp);
    let at = |q: f64| errors[((errors.len() as f64 - 1.0) * q).round() as usize];
    let under = errors
        .iter()
        .filter(|&&e| e <= f64::from(max_error) * (1.0 + 1e-6))
        .count();
    ErrorReport {
        max: errors.last().copied().unwrap_or(0.0),
        p99: if errors.is_empty() { 0.0 } else { at(0.99) },
        under_budget: under as f64 / errors.len().max(1) as f64,
    }
}

/// The chapter's PCA of a clip library: the mean weight vector of every frame of every clip
/// and the principal directions of the frames around it, strongest first (a Jacobi
/// eigendecomposition of the K × K covariance). The library's clips share it.
#[derive(Clone, Debug, PartialEq)]
pub struct Basis {
    /// Mean weights, per channel.
    pub mean: Vec<f32>,
    /// Components, each a unit vector over the channels, strongest first.
    pub components: Vec<Vec<f32>>,
}

impl Basis {
    /// The basis of `rig`'s clips (every component kept; [`compress_pca`] chooses how many).
    pub fn of(rig: &Rig) -> Basis {
        let k = rig.targets.len();
        let mut mean = vec![0f64; k];
        let mut count = 0f64;
        let mut w = vec![0f32; k];
        for c in &rig.clips {
            for f in 0..c.frames {
                c.frame_weights(f, &mut w);
                for (m, x) in mean.iter_mut().zip(&w) {
                    *m += f64::from(*x);
                }
                count += 1.0;
            }
        }
        for m in &mut mean {
            *m /= count.max(1.0);
        }
        let mut cov = vec![0f64; k * k];
        for c in &rig.clips {
            for f in 0..c.frames {
                c.frame_weights(f, &mut w);
                let d: Vec<f64> = w
                    .iter()
                    .zip(&mean)
                    .map(|(x, m)| f64::from(*x) - m)
                    .collect();
                for i in 0..k {
                    for j in 0..k {
                        cov[i * k + j] += d[i] * d[j];
                    }
                }
            }
        }
        let (values, vectors) = crowdmorph_core::linalg::jacobi(cov, k);
        let mut order: Vec<usize> = (0..k).collect();
        order.sort_by(|&a, &b| values[b].total_cmp(&values[a]));
        Basis {
            mean: mean.iter().map(|&m| m as f32).collect(),
            components: order
                .iter()
                .map(|&j| (0..k).map(|i| vectors[i * k + j] as f32).collect())
                .collect(),
        }
    }

    /// Bytes of the mean and `c` components (the library pays them once).
    pub fn bytes(&self, c: usize) -> usize {
        4 * self.mean.len() * (1 + c)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clips_round_trip_within_the_budget_and_frames_decode_alone() {
        let rig = crowdmorph_core::embedded::default_rig();
        for clip in &rig.clips {
            let c = compress(&rig, clip, 3e-4).expect("compresses");
            let table = decode(&c).expect("decodes");
            let r = measure(&rig, clip, &table, 3e-4);
            assert!(r.max <= 3e-4, "{}: {r:?}", clip.name);
            let f = clip.frames / 2;
            let alone = decode_frame(&c, f).expect("one frame");
            let n = clip.frames as usize;
            for (t, w) in alone.iter().enumerate() {
                assert_eq!(*w, table[t * n + f as usize]);
            }
        }
    }

    #[test]
    fn pca_keeps_its_budget_and_every_component_reproduces_the_input() {
        let rig = crowdmorph_core::embedded::default_rig();
        let basis = Basis::of(&rig);
        let k = rig.targets.len();
        // Orthonormal components.
        for a in 0..k.min(8) {
            for b in 0..k.min(8) {
                let dot: f32 = (0..k)
                    .map(|t| basis.components[a][t] * basis.components[b][t])
                    .sum();
                assert!(
                    (dot - if a == b { 1.0 } else { 0.0 }).abs() < 1e-4,
                    "{a}·{b} = {dot}"
                );
            }
        }
        for clip in &rig.clips {
            let c = compress_pca(&rig, clip, &basis, 3e-4)
                .expect("compresses")
                .expect("within budget");
            let table = decode_with(&c, &basis).expect("decodes");
            let r = measure(&rig, clip, &table, 3e-4);
            assert!(
                r.max <= 3e-4,
                "{}: {r:?} with {:?} components",
                clip.name,
                c.components
            );
            // Every component and no quantization to speak of: the input, to float error.
            let coeffs = project(&basis, clip, k);
            let full = reconstruct(&basis, k, &coeffs, clip.frames as usize);
            for (a, b) in full.iter().zip(clip.weights.iter()) {
                assert!((a - b).abs() <= 1e-5, "{}: {a} vs {b}", clip.name);
            }
        }
    }

    #[test]
    fn blending_pca_coefficients_equals_blending_the_decoded_frames() {
        let rig = crowdmorph_core::embedded::default_rig();
        let basis = Basis::of(&rig);
        let coded: Vec<(Compressed, Vec<f32>)> = rig
            .clips
            .iter()
            .map(|clip| {
                let c = compress_pca(&rig, clip, &basis, 3e-4)
                    .expect("compresses")
                    .expect("within budget");
                let table = decode_with(&c, &basis).expect("decodes");
                (c, table)
            })
            .collect();
        let k = rig.targets.len();
        let (a, b) = (&coded[0], &coded[1]);
        let (fa, fb) = (3u32, b.0.frames - 1);
        for t in [0.0f32, 0.25, 0.5, 1.0] {
            let got = blend_pca(&basis, &[(&a.0, fa, 1.0 - t), (&b.0, fb, t)]).expect("blend");
            assert_eq!(got.len(), k);
            for (i, g) in got.iter().enumerate() {
                let want = (1.0 - t) * a.1[i * a.0.frames as usize + fa as usize]
                    + t * b.1[i * b.0.frames as usize + fb as usize];
                assert!(
                    (g - want).abs() <= 1e-5,
                    "t {t}, channel {i}: {g} vs {want}"
                );
            }
        }
        // A curve-coded clip has no coefficients to blend.
        let curves = compress(&rig, &rig.clips[0], 3e-4).expect("compresses");
        assert!(blend_pca(&basis, &[(&curves, 0, 1.0)]).is_err());
    }

    #[test]
    fn the_stored_form_is_a_fixed_point() {
        let rig = crowdmorph_core::embedded::default_rig();
        for clip in &rig.clips {
            let (c, once) = curves_stored_form(&rig, clip, 3e-4).expect("form");
            let (c2, twice) = curves_stored_form(&rig, &once, 3e-4).expect("form");
            assert_eq!(once.weights, twice.weights, "{}", clip.name);
            assert_eq!(c, c2, "{}: the same bytes again", clip.name);
            assert!(measure(&rig, clip, &once.weights, 3e-4).max <= 3e-4);
            // A header that lies is refused before anything is allocated from it.
            let mut bad = c.clone();
            bad.frames = u32::MAX;
            assert!(matches!(
                bad.to_clip(rig.targets.len()),
                Err(DecodeError::Malformed(_))
            ));
            let mut bad = c.clone();
            bad.steps.pop();
            assert!(bad.to_clip(rig.targets.len()).is_err());
            assert!(c.to_clip(rig.targets.len() + 1).is_err());
        }
    }

    #[test]
    fn a_tiny_budget_reproduces_the_input_and_corruption_is_an_error() {
        let rig = crowdmorph_core::embedded::default_rig();
        let clip = &rig.clips[0];
        let c = compress(&rig, clip, 1e-9).expect("compresses");
        let table = decode(&c).expect("decodes");
        for (a, b) in table.iter().zip(clip.weights.iter()) {
            assert!((a - b).abs() <= 1e-6 * b.abs().max(1.0), "{a} vs {b}");
        }
        let mut bad = c.clone();
        let last = bad.segments[0].len() - 1;
        bad.segments[0][last] ^= 0x5a;
        bad.segments[0].truncate(last);
        assert!(decode(&bad).is_err());
    }
}
