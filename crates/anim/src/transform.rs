//! Transform-coded clips (clip codec 2): face captures within a vertex-space error budget.
//!
//! A face tracker's 52 channels move together (left and right, jaw and lips) and carry white
//! noise that the budget forbids removing where it moves vertices visibly. The per-curve codec
//! ([`crate::compress`]) bounds the error by the triangle inequality over every channel at the
//! worst vertex, which leaves most of the budget unspent; this one:
//!
//! - **analyses the clip two ways and keeps the smaller.** (a) Decorrelated in vertex space:
//!   with `G = Dᵀ D` (the Gram matrix of the targets' deltas, `D` the 3V × K delta matrix, a
//!   tiny ridge so it is invertible) and `z = R w`, `RᵀR = G`, the squared length of `z` is the
//!   summed squared vertex displacement; the principal directions `u_j` of the clip's `z` (its
//!   frames around their mean) are the chapter's PCA (GPU Gems 3 ch. 15) measured where the
//!   error is measured. The clip stores the mean and each kept direction in weight space
//!   (`b_j = R⁻¹ u_j`), counted in its size. (b) The channels themselves, each with the step
//!   `allocation` gives: error spent where vertices are crowded least. Low-rank clean clips
//!   take (a); captures, whose noise is independent per channel, take (b);
//! - **quantizes every coefficient with one step `δ`** (equal steps spend equal squared error
//!   per component: the reverse water-filling of a Gaussian source), and keeps only the
//!   directions whose coefficients ever exceed `δ/2` (the others decode as 0 within the same
//!   error a quantizer would make); the basis entries get the bits their largest coefficient
//!   needs;
//! - **measures instead of bounding.** `δ` is the largest one (a bisection in log scale) whose
//!   decoded clip keeps every vertex of every frame within `max_error × diagonal` of the
//!   original — measured on the decoder's own output in f64, as ACL measures its bit rates.
//!   The bound is therefore a property of the stored bytes, not of an inequality;
//! - **predicts per segment and stream.** Each [`SEGMENT`] frames decode alone (random access,
//!   as the curve codec); within one, each stream chooses the predictor of its residuals that
//!   costs least (none, the previous value, the line through two, the mean of two or of four):
//!   a linear predictor multiplies white noise's variance by 6, a smooth curve wants it.
//!   Residuals are zigzag varints, a segment is one zstd frame with its checksum.
//!
//! Nothing is denoised beyond the budget: the error is measured against the noisy input.

use crate::varint::{get_varint, put_varint, unzigzag, zigzag};
use crowdmorph_core::rig::{Clip, MAX_FRAMES, Rig};

/// Why a transform-coded clip does not decode.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum DecodeError {
    /// A segment is corrupt or truncated.
    #[error("segment {0}: {1}")]
    Corrupt(usize, String),
    /// The header disagrees with itself or with the rig (version, shape, basis, segments).
    #[error("{0}")]
    Malformed(String),
}

/// The version of this codec's stored form (a later layout is a new number, so old records
/// still read with the code that wrote them).
pub const VERSION: u32 = 1;

/// Frames per independently decodable segment (as the curve codec).
pub const SEGMENT: u32 = 32;

/// zstd level of the segments (clips are compressed once, decoded often).
const LEVEL: i32 = 19;

/// Ridge added to the delta Gram matrix, relative to its largest eigenvalue: directions that
/// move vertices less than this are left to the ridge.
const RIDGE: f64 = 1e-7;

/// Bisection steps of the quantization step's search (in log scale over six decades: the step
/// found is within 1.4 % of the largest that passes, which costs at most 0.02 bits a sample).
const SEARCH_STEPS: usize = 10;

/// A clip coded by [`compress`].
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TransformCoded {
    /// [`VERSION`] of the layout.
    pub version: u32,
    /// Clip name.
    pub name: String,
    /// Frames per second.
    pub fps: f32,
    /// Frames.
    pub frames: u32,
    /// Weight channels.
    pub targets: u32,
    /// Per channel, the clip's mean weight.
    pub mean: Vec<f32>,
    /// Per kept direction, the scale of its integer entries.
    pub scales: Vec<f32>,
    /// Kept directions × channels as integers (zigzag varints, one zstd frame), direction `j`
    /// being `scales[j] × basis[j]` already multiplied by the quantization step: a frame is
    /// `mean + Σⱼ qⱼ · scales[j] · basis[j]`. Each direction has the precision its largest
    /// coefficient needs (a direction only ever multiplied by ±2 needs few bits).
    pub basis: Vec<u8>,
    /// The zstd-compressed segments of the integer coefficients `qⱼ`.
    pub segments: Vec<Vec<u8>>,
}

impl TransformCoded {
    /// Kept directions.
    pub fn components(&self) -> usize {
        self.scales.len()
    }

    /// Bytes of the stored form: the segments (a 4-byte length each), the mean, the scales,
    /// the coded basis and a 24-byte header.
    pub fn bytes(&self) -> usize {
        self.segments.iter().map(|s| s.len() + 4).sum::<usize>()
            + 4 * self.mean.len()
            + 4 * self.scales.len()
            + self.basis.len()
            + 24
    }

    /// Bytes of the clip's f32 table.
    pub fn f32_bytes(&self) -> usize {
        self.frames as usize * self.targets as usize * 4
    }

    /// Checks the header before anything is allocated from it: the version, a shape a clip may
    /// have, a rig of `targets` channels, at most one direction per channel, one segment per
    /// [`SEGMENT`] frames, finite means and scales.
    pub fn check(&self, targets: usize) -> Result<(), DecodeError> {
        let bad = |m: String| Err(DecodeError::Malformed(m));
        if self.version != VERSION {
            return bad(format!("transform codec version {}", self.version));
        }
        if self.frames == 0 || self.frames as usize > MAX_FRAMES {
            return bad(format!("{} frames", self.frames));
        }
        let k = self.targets as usize;
        if k != targets || self.mean.len() != k {
            return bad(format!(
                "{} channels ({} means) for a rig of {targets}",
                self.targets,
                self.mean.len()
            ));
        }
        let m = self.scales.len();
        if m > k {
            return bad(format!("{m} directions for {k} channels"));
        }
        if self.segments.len() != self.frames.div_ceil(SEGMENT) as usize {
            return bad(format!(
                "{} segments for {} frames",
                self.segments.len(),
                self.frames
            ));
        }
        if self.mean.iter().chain(&self.scales).any(|x| !x.is_finite()) {
            return bad("a mean or scale is not finite".into());
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

    /// The basis in f64, direction-major (the decoder's one multiplication order).
    fn directions(&self) -> Result<Vec<f64>, DecodeError> {
        let (k, m) = (self.targets as usize, self.scales.len());
        if self.mean.len() != k || m > k {
            return Err(DecodeError::Malformed(
                "mean or directions of the wrong size".into(),
            ));
        }
        let bad = |why: &str| DecodeError::Malformed(format!("basis: {why}"));
        // At most 5 bytes an i32 varint: a bound that also refuses a frame claiming more.
        let raw =
            zstd::bulk::decompress(&self.basis, m * k * 5).map_err(|e| bad(&e.to_string()))?;
        let mut at = 0;
        let mut out = Vec::with_capacity(m * k);
        for i in 0..m * k {
            let z = get_varint(&raw, &mut at).ok_or_else(|| bad("truncated"))?;
            let v = i32::try_from(unzigzag(z)).map_err(|_| bad("an entry past 32 bits"))?;
            out.push(f64::from(self.scales[i / k]) * f64::from(v));
        }
        if at != raw.len() {
            return Err(bad("trailing bytes"));
        }
        Ok(out)
    }
}

/// What the encoder needs of a rig: the Gram matrix of its deltas (K × K, f64) and which
/// channels move a vertex at all.
#[derive(Clone, Debug)]
pub struct Metric {
    /// Channels.
    pub k: usize,
    /// `Σᵥ Δₐ(v)·Δ_b(v)` over every primitive's vertices.
    pub gram: Vec<f64>,
    /// Per channel, whether it moves any vertex.
    pub moves: Vec<bool>,
    /// Per channel, its longest delta.
    pub longest: Vec<f64>,
    /// Every (channel, vertex in all primitives' order, squared delta length) of the deltas.
    pub energy: Vec<(u32, u32, f64)>,
    /// Vertices over all primitives.
    pub vertices: usize,
}

impl Metric {
    /// The metric of `rig`'s position deltas.
    pub fn of(rig: &Rig) -> Metric {
        let k = rig.targets.len();
        let mut gram = vec![0f64; k * k];
        for p in rig.primitives.iter() {
            // Pairs of sparse targets by merging their ascending vertex lists: no dense copy
            // of a target (K dense arrays of a large rig would be gigabytes), K × nnz work.
            for (i, ta) in p.targets.iter().enumerate() {
                for tb in &p.targets[i..] {
                    let (mut x, mut y, mut sum) = (0usize, 0usize, 0f64);
                    while x < ta.vertices.len() && y < tb.vertices.len() {
                        match ta.vertices[x].cmp(&tb.vertices[y]) {
                            std::cmp::Ordering::Less => x += 1,
                            std::cmp::Ordering::Greater => y += 1,
                            std::cmp::Ordering::Equal => {
                                sum += ta.positions[x].as_dvec3().dot(tb.positions[y].as_dvec3());
                                x += 1;
                                y += 1;
                            }
                        }
                    }
                    let (a, b) = (ta.target as usize, tb.target as usize);
                    gram[a * k + b] += sum;
                    if a != b {
                        gram[b * k + a] += sum;
                    }
                }
            }
        }
        let moves = (0..k).map(|i| gram[i * k + i] > 0.0).collect();
        let mut longest = vec![0f64; k];
        let mut energy = Vec::new();
        let mut offset = 0u32;
        for p in rig.primitives.iter() {
            for t in &p.targets {
                let l = t.positions.iter().map(|d| d.length()).fold(0.0, f32::max);
                longest[t.target as usize] = longest[t.target as usize].max(f64::from(l));
                for (&v, d) in t.vertices.iter().zip(&t.positions) {
                    let e = d.as_dvec3().length_squared();
                    if e > 0.0 {
                        energy.push((t.target, offset + v, e));
                    }
                }
            }
            offset += p.positions.len() as u32;
        }
        Metric {
            k,
            gram,
            moves,
            longest,
            energy,
            vertices: offset as usize,
        }
    }
}

/// The clip's principal directions in the metric's space, strongest first.
struct Analysis {
    k: usize,
    n: usize,
    /// Per channel, the mean (as stored, f32).
    mean: Vec<f32>,
    /// Per direction, its weight-space vector (K).
    dirs: Vec<Vec<f64>>,
    /// Per direction, its coefficient at every frame (n), in vertex-distance units.
    coeffs: Vec<Vec<f64>>,
}

fn analyse(metric: &Metric, clip: &Clip) -> Analysis {
    let (k, n) = (clip.targets as usize, clip.frames as usize);
    let w = &clip.weights;
    let mean: Vec<f32> = (0..k)
        .map(|t| {
            let s: f64 = w[t * n..(t + 1) * n].iter().map(|&x| f64::from(x)).sum();
            (s / n as f64) as f32
        })
        .collect();
    // Channels that move vertices: the others decode as their mean (they move nothing).
    let act: Vec<usize> = (0..k)
        .filter(|&t| metric.moves.get(t).copied().unwrap_or(false))
        .collect();
    let a = act.len();
    if a == 0 {
        return Analysis {
            k,
            n,
            mean,
            dirs: Vec::new(),
            coeffs: Vec::new(),
        };
    }
    let mut g: Vec<f64> = (0..a * a)
        .map(|i| metric.gram[act[i / a] * metric.k + act[i % a]])
        .collect();
    let (gl, gv) = crowdmorph_core::linalg::jacobi(g.clone(), a);
    let top = gl.iter().copied().fold(0.0, f64::max);
    for i in 0..a {
        g[i * a + i] += RIDGE * top;
    }
    let (gl, gv) = if top > 0.0 {
        crowdmorph_core::linalg::jacobi(g, a)
    } else {
        (gl, gv)
    };
    // R = Λ^½ Vᵀ (a × a, row-major) and R⁻¹ = V Λ^-½.
    let sq: Vec<f64> = gl.iter().map(|&l| l.max(RIDGE * top).sqrt()).collect();
    let r: Vec<f64> = (0..a * a)
        .map(|i| {
            let (row, col) = (i / a, i % a);
            sq[row] * gv[col * a + row]
        })
        .collect();
    let rinv: Vec<f64> = (0..a * a)
        .map(|i| {
            let (row, col) = (i / a, i % a);
            gv[row * a + col] / sq[col]
        })
        .collect();
    // z = R (w − mean) per frame (a × n).
    let mut z = vec![0f64; a * n];
    for f in 0..n {
        let x: Vec<f64> = act
            .iter()
            .map(|&t| f64::from(w[t * n + f]) - f64::from(mean[t]))
            .collect();
        for i in 0..a {
            z[i * n + f] = (0..a).map(|j| r[i * a + j] * x[j]).sum();
        }
    }
    let mut cov = vec![0f64; a * a];
    for i in 0..a {
        for j in i..a {
            let s: f64 = (0..n).map(|f| z[i * n + f] * z[j * n + f]).sum();
            cov[i * a + j] = s;
            cov[j * a + i] = s;
        }
    }
    let (cl, cv) = crowdmorph_core::linalg::jacobi(cov, a);
    let mut order: Vec<usize> = (0..a).collect();
    order.sort_by(|&x, &y| cl[y].total_cmp(&cl[x]));
    let mut dirs = Vec::with_capacity(a);
    let mut coeffs = Vec::with_capacity(a);
    for &j in &order {
        let u: Vec<f64> = (0..a).map(|i| cv[i * a + j]).collect();
        let mut b = vec![0f64; k];
        for (i, &t) in act.iter().enumerate() {
            b[t] = (0..a).map(|c| rinv[i * a + c] * u[c]).sum();
        }
        coeffs.push(
            (0..n)
                .map(|f| (0..a).map(|i| u[i] * z[i * n + f]).sum())
                .collect(),
        );
        dirs.push(b);
    }
    Analysis {
        k,
        n,
        mean,
        dirs,
        coeffs,
    }
}

/// Per channel, the squared weight step of one unit of `δ` (0 for channels that do not move in
/// the clip): errors are spent where vertices are crowded least. Quantization errors are
/// independent, so a vertex's squared error adds up over the channels that move it,
/// `Σₖ xₖ ‖Δₖ(v)‖²`; a channel alone in its region (an eyelid, a brow) may take the whole
/// budget, one that shares the mouth corners with twenty others a part. Starting from the
/// curve codec's allocation (`xₖ = 1 / Lₖ²`: one step moves the longest delta by one unit),
/// each channel scales its step until the most loaded vertex where it is strong (at least half
/// its peak) carries one unit, a few damped rounds (a heuristic for the convex problem
/// `min −Σ log xₖ` subject to every vertex's load ≤ 1; the step search then calibrates it).
fn allocation(metric: &Metric, moving: &[bool]) -> Vec<f64> {
    let k = metric.k;
    let mut x: Vec<f64> = (0..k)
        .map(|t| {
            let l = metric.longest[t];
            if moving[t] && l > 0.0 {
                1.0 / (l * l)
            } else {
                0.0
            }
        })
        .collect();
    let mut peak = vec![0f64; k];
    for &(t, _, e) in &metric.energy {
        peak[t as usize] = peak[t as usize].max(e);
    }
    let mut load = vec![0f64; metric.vertices];
    for _ in 0..12 {
        load.iter_mut().for_each(|l| *l = 0.0);
        for &(t, v, e) in &metric.energy {
            load[v as usize] += x[t as usize] * e;
        }
        let mut worst = vec![0f64; k];
        for &(t, v, e) in &metric.energy {
            if e >= 0.5 * peak[t as usize] {
                worst[t as usize] = worst[t as usize].max(load[v as usize]);
            }
        }
        for t in 0..k {
            if x[t] > 0.0 && worst[t] > 0.0 {
                x[t] /= worst[t].sqrt();
            }
        }
    }
    x
}

/// The clip's channels as they are, each step as `allocation` gives, for clips whose
/// channels do not move together (or carry noise of their own).
fn analyse_channels(metric: &Metric, clip: &Clip) -> Analysis {
    let (k, n) = (clip.targets as usize, clip.frames as usize);
    let w = &clip.weights;
    let mean: Vec<f32> = (0..k)
        .map(|t| {
            let s: f64 = w[t * n..(t + 1) * n].iter().map(|&x| f64::from(x)).sum();
            (s / n as f64) as f32
        })
        .collect();
    let moving: Vec<bool> = (0..k)
        .map(|t| {
            let row = &w[t * n..(t + 1) * n];
            row.iter().any(|&x| x != row[0])
        })
        .collect();
    let x = allocation(metric, &moving);
    let mut dirs = Vec::new();
    let mut coeffs = Vec::new();
    for t in 0..k {
        let step = x[t].sqrt();
        if !(step > 0.0 && step.is_finite()) {
            continue;
        }
        let mut b = vec![0f64; k];
        b[t] = step;
        dirs.push(b);
        coeffs.push(
            w[t * n..(t + 1) * n]
                .iter()
                .map(|&x| (f64::from(x) - f64::from(mean[t])) / step)
                .collect(),
        );
    }
    Analysis {
        k,
        n,
        mean,
        dirs,
        coeffs,
    }
}

/// Predictors a stream may choose per segment.
const PREDICTORS: u8 = 5;

/// The prediction of a segment's next sample from `h`, its samples before (oldest first), by
/// predictor `order`: 0 none, 1 the previous value, 2 the line through the two before, 3 the
/// mean of the two before, 4 the mean of the four before (white noise around a slow curve:
/// averaging shrinks the noise the residual inherits). Too short a history falls back to the
/// previous value, an empty one to 0. `None` on overflow (only a damaged stream gets there).
fn predict(order: u8, h: &[i64]) -> Option<i64> {
    let at = |back: usize| h[h.len() - back];
    match (order, h.len()) {
        (0, _) | (_, 0) => Some(0),
        (2, n) if n >= 2 => at(1).checked_mul(2)?.checked_sub(at(2)),
        (3, n) if n >= 2 => Some(at(1).checked_add(at(2))?.div_euclid(2)),
        (4, n) if n >= 4 => Some(
            at(1)
                .checked_add(at(2))?
                .checked_add(at(3))?
                .checked_add(at(4))?
                .div_euclid(4),
        ),
        _ => Some(at(1)),
    }
}

/// The residuals of `q` under predictor `order`.
fn residuals(order: u8, q: &[i64]) -> impl Iterator<Item = i64> + '_ {
    (0..q.len()).map(move |i| q[i] - predict(order, &q[..i]).unwrap_or(0))
}

/// Codes `q` (streams × `n` frames, each stream a row) into segments.
fn encode_segments(q: &[Vec<i64>], n: usize) -> std::io::Result<Vec<Vec<u8>>> {
    let mut zstd = zstd::bulk::Compressor::new(LEVEL)?;
    zstd.set_parameter(zstd::zstd_safe::CParameter::ChecksumFlag(true))?;
    let mut segments = Vec::new();
    for start in (0..n).step_by(SEGMENT as usize) {
        let end = (start + SEGMENT as usize).min(n);
        let mut raw = Vec::with_capacity((end - start + 1) * q.len());
        for stream in q {
            let s = &stream[start..end];
            // The cheapest predictor, by the bits its residuals need.
            let cost =
                |o: u8| -> f64 { residuals(o, s).map(|r| (1.0 + r.abs() as f64).log2()).sum() };
            let order = (0..PREDICTORS)
                .min_by(|&a, &b| cost(a).total_cmp(&cost(b)))
                .unwrap_or(0);
            raw.push(order);
            for r in residuals(order, s) {
                put_varint(&mut raw, zigzag(r));
            }
        }
        segments.push(zstd.compress(&raw)?);
    }
    Ok(segments)
}

/// Decodes segment `s` of `c` into `out` (targets × frames, the clip's layout), with the
/// basis `dirs` ([`TransformCoded::directions`]).
fn decode_segment(
    c: &TransformCoded,
    dirs: &[f64],
    s: usize,
    out: &mut [f32],
) -> Result<(), DecodeError> {
    let (n, k, m) = (c.frames as usize, c.targets as usize, c.scales.len());
    let start = s * SEGMENT as usize;
    let end = (start + SEGMENT as usize).min(n);
    let len = end - start;
    let seg = c
        .segments
        .get(s)
        .ok_or_else(|| DecodeError::Corrupt(s, "missing".into()))?;
    // An order byte and at most 10 bytes a varint: a bound that also refuses a zstd frame
    // claiming more.
    let raw = zstd::bulk::decompress(seg, m * (1 + len * 10))
        .map_err(|e| DecodeError::Corrupt(s, e.to_string()))?;
    let corrupt = |why: &str| DecodeError::Corrupt(s, why.into());
    let mut q = vec![0i64; m * len];
    let mut at = 0;
    for j in 0..m {
        let order = *raw.get(at).ok_or_else(|| corrupt("truncated"))?;
        at += 1;
        if order >= PREDICTORS {
            return Err(corrupt("unknown predictor"));
        }
        let row = &mut q[j * len..(j + 1) * len];
        for i in 0..len {
            let r = get_varint(&raw, &mut at).ok_or_else(|| corrupt("truncated"))?;
            let v = predict(order, &row[..i])
                .and_then(|p| p.checked_add(unzigzag(r)))
                .ok_or_else(|| corrupt("coefficient overflows"))?;
            row[i] = v;
        }
    }
    if at != raw.len() {
        return Err(corrupt("trailing bytes"));
    }
    for t in 0..k {
        for i in 0..len {
            let mut x = f64::from(c.mean[t]);
            for j in 0..m {
                x += q[j * len + i] as f64 * dirs[j * k + t];
            }
            let w = x as f32;
            if !w.is_finite() {
                return Err(corrupt("a weight is not finite"));
            }
            out[t * n + start + i] = w;
        }
    }
    Ok(())
}

/// The whole table (targets × frames). Call [`TransformCoded::check`] first on untrusted input
/// (this checks only what it indexes).
pub fn decode(c: &TransformCoded) -> Result<Vec<f32>, DecodeError> {
    let dirs = c.directions()?;
    let mut out = vec![0f32; c.frames as usize * c.targets as usize];
    for s in 0..c.frames.div_ceil(SEGMENT) as usize {
        decode_segment(c, &dirs, s, &mut out)?;
    }
    Ok(out)
}

/// One frame's weights, decoding only its segment (random access).
pub fn decode_frame(c: &TransformCoded, frame: u32) -> Result<Vec<f32>, DecodeError> {
    if frame >= c.frames {
        return Err(DecodeError::Malformed(format!(
            "frame {frame} of {}",
            c.frames
        )));
    }
    let (n, k) = (c.frames as usize, c.targets as usize);
    let dirs = c.directions()?;
    let mut table = vec![0f32; n * k];
    decode_segment(c, &dirs, (frame / SEGMENT) as usize, &mut table)?;
    Ok((0..k).map(|t| table[t * n + frame as usize]).collect())
}

/// The clip coded with quantization step `delta` (in vertex-distance units of the analysis).
fn encode_at(a: &Analysis, clip: &Clip, delta: f64) -> std::io::Result<TransformCoded> {
    let (k, n) = (a.k, a.n);
    let mut scales = Vec::new();
    let mut entries = Vec::new();
    let mut q: Vec<Vec<i64>> = Vec::new();
    for (b, c) in a.dirs.iter().zip(&a.coeffs) {
        // A direction whose coefficients never pass half a step decodes as 0 within the same
        // error its quantizer would make.
        if c.iter().all(|x| x.abs() <= delta / 2.0) {
            continue;
        }
        let qs: Vec<i64> = c.iter().map(|x| (x / delta).round() as i64).collect();
        // Entries to 2⁻⁶ of the largest coefficient's step: 6 bits more than that coefficient
        // has, so the basis's rounding moves a frame by a small part of the coefficients' own.
        let big = qs
            .iter()
            .map(|x| x.unsigned_abs())
            .max()
            .unwrap_or(1)
            .max(1);
        let bits = (64 - big.leading_zeros() + 6).clamp(4, 24);
        let peak = b.iter().fold(0.0f64, |m, x| m.max(x.abs())) * delta;
        let scale = (peak / f64::from(1u32 << bits)) as f32;
        if !(peak.is_finite() && scale.is_normal()) {
            continue;
        }
        let s = f64::from(scale);
        for x in b {
            put_varint(&mut entries, zigzag((x * delta / s).round() as i64));
        }
        scales.push(scale);
        q.push(qs);
    }
    let mut zstd = zstd::bulk::Compressor::new(LEVEL)?;
    zstd.set_parameter(zstd::zstd_safe::CParameter::ChecksumFlag(true))?;
    Ok(TransformCoded {
        version: VERSION,
        name: clip.name.clone(),
        fps: clip.fps,
        frames: clip.frames,
        targets: k as u32,
        mean: a.mean.clone(),
        scales,
        basis: zstd.compress(&entries)?,
        segments: encode_segments(&q, n)?,
    })
}

/// The largest vertex error of `decoded` (targets × frames) against `clip` over every frame
/// and vertex, as a fraction of the diagonal (f64 sums of the sparse deltas; the maximum of
/// [`crate::compress::measure`] without keeping every sample).
pub fn max_vertex_error(rig: &Rig, clip: &Clip, decoded: &[f32]) -> f64 {
    max_vertex_error_until(rig, clip, decoded, f64::INFINITY)
}

/// [`max_vertex_error`], stopping at the first frame past `limit` (a fraction of the diagonal)
/// with a value past it.
fn max_vertex_error_until(rig: &Rig, clip: &Clip, decoded: &[f32], limit: f64) -> f64 {
    let n = clip.frames as usize;
    let diag = f64::from(rig.bbox().diagonal()).max(1e-12);
    let mut worst = 0f64;
    let mut d = Vec::new();
    for f in 0..n {
        for p in rig.primitives.iter() {
            d.clear();
            d.resize(p.positions.len(), glam::DVec3::ZERO);
            for t in &p.targets {
                let k = t.target as usize;
                let dw = f64::from(decoded[k * n + f]) - f64::from(clip.weights[k * n + f]);
                if dw != 0.0 {
                    for (&v, delta) in t.vertices.iter().zip(&t.positions) {
                        d[v as usize] += dw * delta.as_dvec3();
                    }
                }
            }
            worst = d.iter().fold(worst, |m, x| m.max(x.length_squared()));
        }
        if worst.sqrt() / diag > limit {
            break;
        }
    }
    worst.sqrt() / diag
}

/// Compresses `clip` of `rig` so that no vertex of any frame moves by more than
/// `max_error × diagonal` from the original (measured on the decoded clip), with the metric of
/// `rig` ([`Metric::of`], computed once per rig). `None` when even the finest step tried
/// misses the budget (the caller keeps the curve codec).
pub fn compress(
    rig: &Rig,
    metric: &Metric,
    clip: &Clip,
    max_error: f32,
) -> std::io::Result<Option<TransformCoded>> {
    let budget = f64::from(max_error);
    let e = budget * f64::from(rig.bbox().diagonal());
    if e.is_nan() || e <= 0.0 || metric.k != clip.targets as usize {
        return Ok(None);
    }
    let passes = |c: &TransformCoded| -> Result<bool, std::io::Error> {
        let table = decode(c).map_err(|e| std::io::Error::other(e.to_string()))?;
        Ok(max_vertex_error_until(rig, clip, &table, budget) <= budget)
    };
    // Both analyses: the principal directions in vertex space (channels that move together),
    // and the channels themselves (channels that do not); the smaller coded clip wins.
    let mut best: Option<TransformCoded> = None;
    for a in [analyse(metric, clip), analyse_channels(metric, clip)] {
        // The step lies within these six decades of the budget: a coefficient's error of δ/2
        // moves the vertices' root sum of squares (or a channel's longest delta) by δ/2, so
        // no vertex by more; spread over the thousands of vertices a face's directions move,
        // the largest moves one or two orders less.
        let (mut lo, mut hi) = (e * 1e-2, e * 1e4);
        let first = encode_at(&a, clip, lo)?;
        if !passes(&first)? {
            continue;
        }
        let mut found = first;
        for _ in 0..SEARCH_STEPS {
            let mid = (lo * hi).sqrt();
            let c = encode_at(&a, clip, mid)?;
            if passes(&c)? {
                lo = mid;
                if c.bytes() < found.bytes() {
                    found = c;
                }
            } else {
                hi = mid;
            }
        }
        if best.as_ref().is_none_or(|b| found.bytes() < b.bytes()) {
            best = Some(found);
        }
    }
    Ok(best)
}

/// Most bytes of coded clips [`remember`] keeps (the oldest go first).
const REMEMBERED_BYTES: usize = 64 << 20;

/// Coded forms of the clips this process put into stored form or read from a store, so that a
/// store writing a clip again writes the same bytes: this codec's decoded clip is not a fixed
/// point of its encoder (the mean and directions of the decoded frames differ from the
/// original's), so the coded form has to be kept beside the clip it decodes to. A clip whose
/// coded form was dropped is written exactly (plainly or by the curve codec when it is that
/// codec's fixed point), never as other weights.
static REMEMBERED: std::sync::Mutex<Vec<(u64, std::sync::Arc<TransformCoded>)>> =
    std::sync::Mutex::new(Vec::new());

/// A hash of everything of `clip` its coded form decodes to.
fn clip_key(clip: &Clip) -> u64 {
    use std::hash::{Hash, Hasher};
    let mut h = std::hash::DefaultHasher::new();
    clip.name.hash(&mut h);
    clip.fps.to_bits().hash(&mut h);
    clip.frames.hash(&mut h);
    clip.targets.hash(&mut h);
    for w in clip.weights.iter() {
        w.to_bits().hash(&mut h);
    }
    h.finish()
}

/// Keeps `coded` as the stored form of `decoded` (what it decodes to) for [`recall`].
pub fn remember(coded: &TransformCoded, decoded: &Clip) {
    let key = clip_key(decoded);
    let Ok(mut kept) = REMEMBERED.lock() else {
        return;
    };
    kept.retain(|(k, _)| *k != key);
    kept.push((key, std::sync::Arc::new(coded.clone())));
    let mut total: usize = kept.iter().map(|(_, c)| c.bytes()).sum();
    while total > REMEMBERED_BYTES && !kept.is_empty() {
        total -= kept.remove(0).1.bytes();
    }
}

/// The coded form [`remember`] kept for `clip`, if it still decodes to exactly its weights.
pub fn recall(clip: &Clip) -> Option<TransformCoded> {
    let key = clip_key(clip);
    let coded = REMEMBERED
        .lock()
        .ok()?
        .iter()
        .find(|(k, _)| *k == key)
        .map(|(_, c)| c.clone())?;
    let same = coded.name == clip.name
        && coded.fps.to_bits() == clip.fps.to_bits()
        && coded.frames == clip.frames
        && coded.targets == clip.targets
        && decode(&coded).is_ok_and(|w| w.as_slice() == &clip.weights[..]);
    same.then(|| (*coded).clone())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The real Live Link Face capture kept with the tests (`tests/data/live-link-face`), on
    /// the embedded head, whose 51 targets carry the ARKit names (the head and eye angles and
    /// the one ARKit name it lacks are skipped).
    fn capture(rig: &Rig) -> Clip {
        let path = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../tests/data/live-link-face/MySlate_3_Jason_Millers_iPhone.csv"
        );
        let bytes = std::fs::read(path).expect("the capture is in the repository");
        let options = crowdmorph_import::clips::ClipOptions {
            fps: 60.0,
            ignore_unknown: true,
            budget: None,
        };
        crowdmorph_import::clip_from_csv(rig, "capture", &bytes, &options)
            .expect("imports")
            .clip
    }

    /// Every frame decoded alone equals the whole table's decode.
    fn assert_random_access(c: &TransformCoded, table: &[f32]) {
        let n = c.frames as usize;
        for f in 0..c.frames {
            let alone = decode_frame(c, f).expect("one frame");
            for (t, w) in alone.iter().enumerate() {
                assert_eq!(
                    w.to_bits(),
                    table[t * n + f as usize].to_bits(),
                    "frame {f}"
                );
            }
        }
    }

    #[test]
    fn embedded_clips_keep_the_budget_and_frames_decode_alone() {
        let rig = crowdmorph_core::embedded::default_rig();
        let metric = Metric::of(&rig);
        for clip in &rig.clips {
            let c = compress(&rig, &metric, clip, 3e-4)
                .expect("compresses")
                .expect("within budget");
            c.check(rig.targets.len()).expect("checks");
            let table = decode(&c).expect("decodes");
            // The independent oracle: every (frame, vertex) in f64, sorted.
            let r = crate::compress::measure(&rig, clip, &table, 3e-4);
            assert!(r.max <= 3e-4, "{}: {r:?}", clip.name);
            assert_random_access(&c, &table);
        }
    }

    #[test]
    fn a_real_capture_keeps_the_budget_against_its_noisy_original() {
        let rig = crowdmorph_core::embedded::default_rig();
        let clip = capture(&rig);
        assert_eq!(clip.frames, 328);
        let metric = Metric::of(&rig);
        for budget in [3e-4f32, 1e-4] {
            let c = compress(&rig, &metric, &clip, budget)
                .expect("compresses")
                .expect("within budget");
            let table = decode(&c).expect("decodes");
            let r = crate::compress::measure(&rig, &clip, &table, budget);
            assert!(r.max <= f64::from(budget), "{budget}: {r:?}");
            assert!(r.max > 0.0, "lossy: the noise is not kept exactly");
            assert_random_access(&c, &table);
            // Through the stored form's checks too.
            let back = c.to_clip(rig.targets.len()).expect("a clip");
            assert_eq!(*back.weights, table);
        }
    }

    #[test]
    fn channels_that_are_mixes_of_few_curves_need_that_many_directions() {
        // A property of the method, not of a rig: 51 channels mixed from 3 latent curves (with
        // loadings of both signs) span 3 directions, whatever the budget.
        let rig = crowdmorph_core::embedded::default_rig();
        let (k, n) = (rig.targets.len(), 300usize);
        let mut rng = crowdmorph_core::rng::SplitMix64(48);
        let load: Vec<[f32; 3]> = (0..k)
            .map(|_| [rng.unit() - 0.5, rng.unit() - 0.5, rng.unit() - 0.5])
            .collect();
        let mut w = vec![0f32; k * n];
        for f in 0..n {
            let x = f as f32 / 60.0;
            let l = [(x * 2.0).sin(), (x * 5.3).cos(), (x * 0.7).sin().powi(3)];
            for t in 0..k {
                w[t * n + f] =
                    0.5 + 0.3 * (load[t][0] * l[0] + load[t][1] * l[1] + load[t][2] * l[2]);
            }
        }
        let clip = Clip::new("mix", 60.0, k, n, w).expect("clip");
        let c = compress(&rig, &Metric::of(&rig), &clip, 1e-4)
            .expect("compresses")
            .expect("within budget");
        assert!(c.components() <= 3, "{} directions", c.components());
        let r = crate::compress::measure(&rig, &clip, &decode(&c).expect("decodes"), 1e-4);
        assert!(r.max <= 1e-4, "{r:?}");
    }

    #[test]
    fn malformed_input_is_a_typed_error() {
        let rig = crowdmorph_core::embedded::default_rig();
        let k = rig.targets.len();
        let clip = &rig.clips[1];
        let c = compress(&rig, &Metric::of(&rig), clip, 3e-4)
            .expect("compresses")
            .expect("within budget");
        let malformed = |bad: TransformCoded, what: &str| {
            assert!(
                matches!(bad.to_clip(k), Err(DecodeError::Malformed(_))),
                "{what}"
            );
        };
        let mut bad = c.clone();
        bad.version = VERSION + 1;
        malformed(bad, "a later version");
        let mut bad = c.clone();
        bad.frames = u32::MAX;
        malformed(bad, "frames past the limit");
        let mut bad = c.clone();
        bad.basis.pop();
        malformed(bad, "a short basis");
        let mut bad = c.clone();
        bad.scales = vec![1.0; k + 1];
        bad.basis = vec![0; (k + 1) * k];
        malformed(bad, "more directions than channels");
        let mut bad = c.clone();
        bad.segments.pop();
        malformed(bad, "a missing segment");
        let mut bad = c.clone();
        bad.mean[0] = f32::NAN;
        malformed(bad, "a NaN mean");
        assert!(c.to_clip(k + 1).is_err(), "another rig's channel count");
        // Damaged segments: a flipped byte fails zstd's checksum, a cut one its frame.
        let mut bad = c.clone();
        let last = bad.segments[0].len() - 1;
        bad.segments[0][last] ^= 0x5a;
        assert!(matches!(decode(&bad), Err(DecodeError::Corrupt(0, _))));
        let mut bad = c.clone();
        bad.segments[0].truncate(4);
        assert!(matches!(decode(&bad), Err(DecodeError::Corrupt(0, _))));
        // A well-formed zstd frame whose coefficients overflow, or that holds too much or an
        // unknown predictor: errors, not panics or huge allocations.
        let m = c.components();
        assert!(m > 0);
        let len = SEGMENT.min(c.frames) as usize;
        let forge = |raw: &[u8]| {
            let mut bad = c.clone();
            bad.segments[0] = zstd::bulk::compress(raw, 1).expect("zstd");
            decode(&bad)
        };
        let mut stream = vec![2u8];
        for _ in 0..len {
            put_varint(&mut stream, zigzag(i64::MAX / 2));
        }
        let mut raw = stream.repeat(m);
        assert!(matches!(forge(&raw), Err(DecodeError::Corrupt(0, _))));
        raw.truncate(1);
        raw[0] = 7;
        assert!(matches!(forge(&raw), Err(DecodeError::Corrupt(0, _))));
        let huge = vec![0u8; m * (1 + len * 10) + 1];
        assert!(matches!(forge(&huge), Err(DecodeError::Corrupt(0, _))));
        assert!(decode_frame(&c, c.frames).is_err());
    }
}
