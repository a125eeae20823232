//! What a job plays: one frame of a clip, a blend of clip frames, or live weights.
//!
//! GPU Gems 3 ch. 15 blends animation in weight space: blending the weights of two frames before
//! the shapes are summed is the same as blending the two meshes, because Eq. 1 is linear in the
//! weights. A [`Pose`] is that weight vector, described compactly enough to be a dedupe key:
//!
//! - [`Pose::Frame`]: one frame of one clip (what a head played before blends existed);
//! - [`Pose::Blend`]: up to [`MAX_TERMS`] clip frames with fractions that sum to one, kept in
//!   a canonical form (fractions quantized to multiples of `1/T_ONE`, terms sorted by clip and
//!   frame, equal terms merged, zero terms dropped), so that two heads asking for the same blend
//!   in a different order, or with float noise in their fractions, share one job;
//! - [`Pose::Live`]: a dense weight per rig channel, quantized to multiples of
//!   [`LIVE_STEP`], as a face tracker or an Audio2Face-style service sends them.
//!
//! **Quantization error.** A fraction moves by at most `1/(2·T_ONE)` = 2^-13 when it is
//! quantized (plus at most 2^-12 on the largest layer when rounding pushed the sum past one),
//! so a blended weight moves by at most 2^-12 × the largest difference between its layers'
//! weights, and a vertex by at most that times `Σ_k ‖Δ_k‖` over the shapes whose weights differ.
//! A live weight moves by at most `LIVE_STEP / 2` = 2^-13. For ARKit-range weights (0–1) on
//! the embedded head that is below 1e-4 of the head's diagonal; documented in
//! `proto/README.md` ("Blends and live weights").

use std::sync::Arc;

use super::{ClipError, Rig, SkinTerm};

/// Blend fractions are multiples of `1 / T_ONE`.
pub const T_ONE: u32 = 4096;

/// Live weights are multiples of this (2^-12).
pub const LIVE_STEP: f32 = 1.0 / 4096.0;

/// Largest magnitude of a live weight: far past any rig's useful range (ARKit weights are 0–1),
/// small enough that a quantized weight fits an `i32` with room to spare.
pub const MAX_LIVE_WEIGHT: f32 = 64.0;

/// Blend layers a head may add to its own clip frame.
pub const MAX_BLEND_LAYERS: usize = 4;

/// Terms of a blend: the head's frame and its layers.
pub const MAX_TERMS: usize = MAX_BLEND_LAYERS + 1;

/// Apple ARKit's 52 blendshape names (`ARFaceAnchor.BlendShapeLocation`), what face trackers
/// and Audio2Face-style services send every frame. A live weight whose name is one of these
/// (in any loose spelling) but which the rig lacks is ignored, since the rig cannot show it —
/// the embedded head has no `tongueOut` — while any other unknown name is an error.
pub const ARKIT_NAMES: [&str; 52] = [
    "eyeBlinkLeft",
    "eyeLookDownLeft",
    "eyeLookInLeft",
    "eyeLookOutLeft",
    "eyeLookUpLeft",
    "eyeSquintLeft",
    "eyeWideLeft",
    "eyeBlinkRight",
    "eyeLookDownRight",
    "eyeLookInRight",
    "eyeLookOutRight",
    "eyeLookUpRight",
    "eyeSquintRight",
    "eyeWideRight",
    "jawForward",
    "jawLeft",
    "jawRight",
    "jawOpen",
    "mouthClose",
    "mouthFunnel",
    "mouthPucker",
    "mouthLeft",
    "mouthRight",
    "mouthSmileLeft",
    "mouthSmileRight",
    "mouthFrownLeft",
    "mouthFrownRight",
    "mouthDimpleLeft",
    "mouthDimpleRight",
    "mouthStretchLeft",
    "mouthStretchRight",
    "mouthRollLower",
    "mouthRollUpper",
    "mouthShrugLower",
    "mouthShrugUpper",
    "mouthPressLeft",
    "mouthPressRight",
    "mouthLowerDownLeft",
    "mouthLowerDownRight",
    "mouthUpperUpLeft",
    "mouthUpperUpRight",
    "browDownLeft",
    "browDownRight",
    "browInnerUp",
    "browOuterUpLeft",
    "browOuterUpRight",
    "cheekPuff",
    "cheekSquintLeft",
    "cheekSquintRight",
    "noseSneerLeft",
    "noseSneerRight",
    "tongueOut",
];

/// One term of a blend: `t / T_ONE` of a clip's frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct Term {
    /// Clip index within the rig.
    pub clip: u32,
    /// Frame of that clip (already wrapped or clamped).
    pub frame: u32,
    /// Fraction, in units of `1 / T_ONE` (1..=T_ONE).
    pub t: u32,
}

impl Term {
    /// The term's fraction as an `f32` (exact: `T_ONE` is a power of two).
    pub fn fraction(&self) -> f32 {
        self.t as f32 / T_ONE as f32
    }
}

/// The weights a job evaluates, before its level of detail cuts them.
#[derive(Clone, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Pose {
    /// One frame of one clip.
    Frame {
        /// Clip index within the rig.
        clip: u32,
        /// Frame of that clip (already wrapped or clamped).
        frame: u32,
    },
    /// Two to [`MAX_TERMS`] clip frames, canonical (see the module doc); fractions sum to
    /// `T_ONE`.
    Blend(Arc<[Term]>),
    /// One quantized weight per rig channel (`w = q × LIVE_STEP`).
    Live(Arc<[i32]>),
}

/// Why a pose does not fit its rig.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum PoseError {
    /// A term names a clip the rig does not have.
    #[error("clip index {0} out of range")]
    NoSuchClip(u32),
    /// A term names a frame outside its clip.
    #[error(transparent)]
    Frame(#[from] ClipError),
    /// Live weights of the wrong length.
    #[error("{got} live weights for a rig of {want} channels")]
    LiveLength {
        /// Weights given.
        got: usize,
        /// Channels of the rig.
        want: usize,
    },
    /// A blend that is not in canonical form (built by hand, not by [`Pose::blend`]).
    #[error("blend terms are not canonical")]
    NotCanonical,
}

impl Pose {
    /// The canonical pose of `terms` (clip, frame, fraction in `[0, 1]`), whose fractions must
    /// sum to at most one (callers check, and say which field is wrong): the first term's
    /// fraction is raised so that they sum to exactly one. Quantized, sorted, merged; a blend
    /// of one frame with itself, or whose other fractions are all zero, is that
    /// [`Pose::Frame`].
    pub fn blend(base: (u32, u32), layers: &[(u32, u32, f32)]) -> Pose {
        let mut terms: Vec<Term> = Vec::with_capacity(layers.len() + 1);
        let mut sum = 0u32;
        for &(clip, frame, t) in layers {
            let t = (f64::from(t.clamp(0.0, 1.0)) * f64::from(T_ONE)).round() as u32;
            sum += t;
            terms.push(Term { clip, frame, t });
        }
        // Rounding may push the layers a step or two past one: take it from the largest.
        if sum > T_ONE {
            let excess = sum - T_ONE;
            if let Some(big) = terms.iter_mut().max_by_key(|t| t.t) {
                big.t -= excess.min(big.t);
            }
            sum = T_ONE;
        }
        terms.push(Term {
            clip: base.0,
            frame: base.1,
            t: T_ONE - sum,
        });
        terms.retain(|t| t.t > 0);
        terms.sort_unstable_by_key(|t| (t.clip, t.frame));
        let mut merged: Vec<Term> = Vec::with_capacity(terms.len());
        for t in terms {
            match merged.last_mut() {
                Some(m) if (m.clip, m.frame) == (t.clip, t.frame) => m.t += t.t,
                _ => merged.push(t),
            }
        }
        match merged.as_slice() {
            [only] => Pose::Frame {
                clip: only.clip,
                frame: only.frame,
            },
            _ => Pose::Blend(merged.into()),
        }
    }

    /// The live pose of `weights` (one per rig channel, finite, within
    /// ±[`MAX_LIVE_WEIGHT`]; callers check).
    pub fn live(weights: &[f32]) -> Pose {
        Pose::Live(weights.iter().map(|&w| quantize_live(w)).collect())
    }

    /// Checks the pose against its rig: clips, frames and the live vector's length.
    pub fn check(&self, rig: &Rig) -> Result<(), PoseError> {
        let frame_ok = |clip: u32, frame: u32| -> Result<(), PoseError> {
            let c = rig
                .clips
                .get(clip as usize)
                .ok_or(PoseError::NoSuchClip(clip))?;
            if frame >= c.frames {
                return Err(ClipError::FrameOutOfRange {
                    clip: c.name.clone(),
                    frame: i64::from(frame),
                    frames: c.frames,
                }
                .into());
            }
            Ok(())
        };
        match self {
            Pose::Frame { clip, frame } => frame_ok(*clip, *frame),
            Pose::Blend(terms) => {
                let sum: u32 = terms.iter().map(|t| t.t).sum();
                let sorted = terms
                    .windows(2)
                    .all(|p| (p[0].clip, p[0].frame) < (p[1].clip, p[1].frame));
                if terms.len() < 2 || terms.len() > MAX_TERMS || sum != T_ONE || !sorted {
                    return Err(PoseError::NotCanonical);
                }
                terms.iter().try_for_each(|t| frame_ok(t.clip, t.frame))
            }
            Pose::Live(w) if w.len() != rig.targets.len() => Err(PoseError::LiveLength {
                got: w.len(),
                want: rig.targets.len(),
            }),
            Pose::Live(_) => Ok(()),
        }
    }

    /// Weight of channel `target` (the pose must have passed [`Pose::check`]). A blend sums
    /// its terms in order, `Σ fraction × weight` in f32: the GPU's `build_active` does the
    /// same, in the same order.
    #[inline]
    pub fn weight(&self, rig: &Rig, target: usize) -> f32 {
        match self {
            Pose::Frame { clip, frame } => rig.clips[*clip as usize].weight(target, *frame),
            Pose::Blend(terms) => terms.iter().fold(0.0f32, |acc, t| {
                acc + t.fraction() * rig.clips[t.clip as usize].weight(target, t.frame)
            }),
            Pose::Live(w) => w[target] as f32 * LIVE_STEP,
        }
    }

    /// Every channel's weight (length = rig channels).
    pub fn weights(&self, rig: &Rig) -> Vec<f32> {
        (0..rig.targets.len())
            .map(|t| self.weight(rig, t))
            .collect()
    }

    /// The clip frame a response names for this pose: the frame itself, a blend's largest
    /// term (the first of equals), none for live weights.
    pub fn shown(&self) -> Option<(u32, u32)> {
        match self {
            Pose::Frame { clip, frame } => Some((*clip, *frame)),
            Pose::Blend(terms) => terms
                .iter()
                .rev()
                .max_by_key(|t| t.t)
                .map(|t| (t.clip, t.frame)),
            Pose::Live(_) => None,
        }
    }

    /// The joint terms of this pose on a rig with a skeleton (`SkinPoses`): a clip frame is
    /// one term, a blend one per clip term (nlerp of their transforms), live weights none
    /// (the rest pose: a weight vector names no joint).
    pub fn skin_terms(&self, rig: &Rig) -> Vec<SkinTerm> {
        let table = |clip: u32| rig.clips.get(clip as usize).and_then(|c| c.joints.clone());
        match self {
            Pose::Frame { clip, frame } => vec![SkinTerm {
                fraction: 1.0,
                table: table(*clip),
                frame: *frame,
            }],
            Pose::Blend(terms) => terms
                .iter()
                .map(|t| SkinTerm {
                    fraction: t.fraction(),
                    table: table(t.clip),
                    frame: t.frame,
                })
                .collect(),
            Pose::Live(_) => Vec::new(),
        }
    }

    /// Heap bytes the pose holds (for queue-memory charges).
    pub fn heap_bytes(&self) -> u64 {
        match self {
            Pose::Frame { .. } => 0,
            Pose::Blend(t) => 16 + size_of_val(&t[..]) as u64,
            Pose::Live(w) => 16 + size_of_val(&w[..]) as u64,
        }
    }
}

/// Largest near-clone tolerance, in units of the rig's diagonal: past a tenth of the head the
/// pose is unrecognisable anyway, and steps stay far inside an `i32` of [`LIVE_STEP`]s.
pub const MAX_NEAR_TOLERANCE: f32 = 0.1;

/// Coarsest near-clone step, as a power of two of [`LIVE_STEP`]s: 2^19 steps is 128, twice
/// [`MAX_LIVE_WEIGHT`], so every weight rounds to 0 or ±128 and counts stay within ±2^20.
pub const MAX_NEAR_SHIFT: u32 = 19;

/// The near-clone bound of one LOD level, `M_L = max_v Σ_{t in level} ‖δ_t(v)‖`: the most a
/// vertex of `rig` (the rig the level is evaluated on: the full rig or its mesh level) moves
/// per unit of weight error on every one of the level's `targets`.
///
/// **The bound proved.** A level evaluates `p(v) = n(v) + Σ_t w_t δ_t(v)` over its targets. If
/// every weight moves by at most `s/2` (rounding to a multiple of `s`), then
/// `‖p̂(v) − p(v)‖ = ‖Σ_t (ŵ_t − w_t) δ_t(v)‖ ≤ Σ_t |ŵ_t − w_t| ‖δ_t(v)‖ ≤ s/2 · M_L` by the
/// triangle inequality — a Euclidean bound on each vertex's displacement (hence on each
/// coordinate). A target split over several primitives adds each primitive's delta at that
/// primitive's own vertex; the sums are taken per primitive vertex, in f64, rounded up to f32.
pub fn near_clone_bound(rig: &Rig, targets: &[super::TargetId]) -> f32 {
    let mut wanted = vec![false; rig.targets.len()];
    for &t in targets {
        if let Some(w) = wanted.get_mut(t as usize) {
            *w = true;
        }
    }
    let mut worst = 0f64;
    // One f64 per vertex of the largest primitive, reused: a transient third of what the
    // rig's own positions hold.
    let mut sum: Vec<f64> = Vec::new();
    for p in rig.primitives.iter() {
        sum.clear();
        sum.resize(p.positions.len(), 0.0);
        for st in &p.targets {
            if !wanted.get(st.target as usize).copied().unwrap_or(false) {
                continue;
            }
            for (&v, d) in st.vertices.iter().zip(&st.positions) {
                if let Some(s) = sum.get_mut(v as usize) {
                    *s += f64::from(d.length());
                }
            }
        }
        worst = sum.iter().copied().fold(worst, f64::max);
    }
    let up = worst as f32;
    if f64::from(up) < worst {
        up.next_up()
    } else {
        up
    }
}

/// The coarsest near-clone step for a level whose bound is `bound` (see
/// [`near_clone_bound`]) when each vertex may move by `error` (absolute, the rig's units):
/// `k` such that `s = LIVE_STEP · 2^k` is the largest power-of-two multiple of [`LIVE_STEP`]
/// with `s/2 · bound ≤ error`. `None` when even [`LIVE_STEP`] is too coarse (or `error` is
/// not a positive finite number): the pose stays exact.
pub fn near_clone_shift(bound: f32, error: f64) -> Option<u32> {
    if !(error.is_finite() && error > 0.0 && bound.is_finite()) {
        return None;
    }
    let bound = f64::from(bound);
    (0..=MAX_NEAR_SHIFT)
        .rev()
        .find(|&k| f64::from(LIVE_STEP) * f64::from(1u32 << k) / 2.0 * bound <= error)
}

impl Pose {
    /// This pose as a near-clone at a level that evaluates `targets`: its weights rounded to
    /// the nearest multiple of `LIVE_STEP · 2^shift` (a [`Pose::Live`], so equal rounded
    /// vectors are one job whatever step produced them), and the channels the level does not
    /// evaluate set to 0 (exact: the level never reads them). Each weight the level reads
    /// moves by at most half a step, so a vertex moves by at most `step/2 · M_L`
    /// ([`near_clone_bound`]).
    ///
    /// `None` (keep the exact pose) when a weight is past ±[`MAX_LIVE_WEIGHT`] or not finite,
    /// or on a rig with a skeleton: its clip poses move joints (a weight vector poses none),
    /// and skinning can stretch a delta's error by its bones' scales, which the bound does not
    /// count.
    pub fn near_clone(&self, rig: &Rig, targets: &[super::TargetId], shift: u32) -> Option<Pose> {
        let shift = shift.min(MAX_NEAR_SHIFT);
        if rig.skeleton.is_some() {
            return None;
        }
        let step = f64::from(1u32 << shift);
        let mut q = vec![0i32; rig.targets.len()];
        for &t in targets {
            let t = t as usize;
            if t >= q.len() {
                continue;
            }
            let w = self.weight(rig, t);
            if !w.is_finite() || w.abs() > MAX_LIVE_WEIGHT {
                return None;
            }
            // In f64 (exact for an f32 weight over a power of two): the nearest multiple of
            // the step, as a count of LIVE_STEPs.
            let steps = (f64::from(w) / f64::from(LIVE_STEP) / step).round();
            q[t] = (steps * step) as i32;
        }
        Some(Pose::Live(q.into()))
    }
}

/// `w` rounded to the nearest multiple of [`LIVE_STEP`], as an integer count of steps.
pub fn quantize_live(w: f32) -> i32 {
    let w = w.clamp(-MAX_LIVE_WEIGHT, MAX_LIVE_WEIGHT);
    (f64::from(w) / f64::from(LIVE_STEP)).round() as i32
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn blends_are_canonical() {
        let a = Pose::blend((0, 40), &[(2, 3, 0.25), (1, 5, 0.25)]);
        let b = Pose::blend((0, 40), &[(1, 5, 0.250_000_1), (2, 3, 0.249_999_9)]);
        assert_eq!(a, b, "order and float noise do not change a blend");
        let Pose::Blend(terms) = &a else {
            panic!("{a:?} is a blend")
        };
        assert_eq!(
            terms
                .iter()
                .map(|t| (t.clip, t.frame, t.t))
                .collect::<Vec<_>>(),
            vec![(0, 40, 2048), (1, 5, 1024), (2, 3, 1024)]
        );
        // A frame blended with itself, and a blend whose layers are all zero, are the frame.
        let frame = Pose::Frame { clip: 0, frame: 40 };
        assert_eq!(Pose::blend((0, 40), &[(0, 40, 0.7)]), frame);
        assert_eq!(Pose::blend((0, 40), &[(1, 2, 0.0)]), frame);
        // t = 1 is the layer alone.
        assert_eq!(
            Pose::blend((0, 40), &[(1, 2, 1.0)]),
            Pose::Frame { clip: 1, frame: 2 }
        );
        // Sums rounded past one are taken back from the largest layer.
        let p = Pose::blend((0, 0), &[(1, 0, 0.500_06), (2, 0, 0.499_94)]);
        let Pose::Blend(terms) = &p else {
            panic!("{p:?} is a blend")
        };
        assert_eq!(terms.iter().map(|t| t.t).sum::<u32>(), T_ONE);
    }

    #[test]
    fn live_weights_quantize_to_steps() {
        assert_eq!(quantize_live(0.6), (0.6f64 * 4096.0).round() as i32);
        assert_eq!(quantize_live(-1.0), -4096);
        assert_eq!(quantize_live(1e9), (MAX_LIVE_WEIGHT * 4096.0) as i32);
        assert_eq!(Pose::live(&[0.5, 0.500_000_1]), Pose::live(&[0.5, 0.5]));
    }

    /// Every vertex of `rig` posed by `pose`, in f64 from the sparse deltas (the oracle the
    /// near-clone tests compare against): only `targets` contribute, as at a LOD level.
    fn posed_f64(rig: &Rig, pose: &Pose, targets: &[u32]) -> Vec<[f64; 3]> {
        let mut out = Vec::new();
        for p in rig.primitives.iter() {
            let mut v: Vec<[f64; 3]> = p
                .positions
                .iter()
                .map(|x| [x.x, x.y, x.z].map(f64::from))
                .collect();
            for st in p.targets.iter().filter(|st| targets.contains(&st.target)) {
                let w = f64::from(pose.weight(rig, st.target as usize));
                for (&i, d) in st.vertices.iter().zip(&st.positions) {
                    let o = &mut v[i as usize];
                    for (a, c) in o.iter_mut().zip([d.x, d.y, d.z]) {
                        *a += w * f64::from(c);
                    }
                }
            }
            out.extend(v);
        }
        out
    }

    #[test]
    fn near_clones_move_no_vertex_past_half_a_step_times_the_bound() {
        let rig = crate::synthetic::with_random_clip(
            crate::synthetic::banded_rig("near", 2000, 40, 24),
            7,
        );
        let all: Vec<u32> = rig.lod.order.clone();
        let half: Vec<u32> = rig.lod.order[..12].to_vec();
        for targets in [&all[..], &half[..]] {
            let bound = near_clone_bound(&rig, targets);
            // The bound, dense and independently: per vertex, Σ over the level's targets.
            let mut dense = vec![0f64; rig.vertex_count()];
            for (t, _) in rig.targets.iter().enumerate() {
                if !targets.contains(&(t as u32)) {
                    continue;
                }
                let one = Pose::live(&{
                    let mut w = vec![0.0; rig.targets.len()];
                    w[t] = 1.0;
                    w
                });
                let rest = posed_f64(&rig, &Pose::live(&vec![0.0; rig.targets.len()]), targets);
                for (i, (a, b)) in posed_f64(&rig, &one, targets).iter().zip(&rest).enumerate() {
                    dense[i] += ((0..3).map(|c| (a[c] - b[c]).powi(2)).sum::<f64>()).sqrt();
                }
            }
            let want = dense.iter().copied().fold(0.0, f64::max);
            assert!(
                (f64::from(bound) - want).abs() <= 1e-5 * want
                    && f64::from(bound) >= want * (1.0 - 1e-6),
                "bound {bound} vs dense {want}"
            );
            let diag = f64::from(rig.bbox().diagonal());
            for (e, frame) in [(1e-4, 3u32), (1e-3, 9), (1e-2, 17)] {
                let error = e * diag;
                let k = near_clone_shift(bound, error).expect("a step fits");
                let step = f64::from(LIVE_STEP) * f64::from(1u32 << k);
                assert!(step / 2.0 * f64::from(bound) <= error);
                // The coarsest: twice the step would break the bound (unless capped).
                assert!(k == MAX_NEAR_SHIFT || step * f64::from(bound) > error);
                let exact = Pose::Frame { clip: 0, frame };
                let near = exact.near_clone(&rig, targets, k).expect("no joints");
                let (a, b) = (
                    posed_f64(&rig, &exact, targets),
                    posed_f64(&rig, &near, targets),
                );
                let worst = a
                    .iter()
                    .zip(&b)
                    .map(|(p, q)| ((0..3).map(|c| (p[c] - q[c]).powi(2)).sum::<f64>()).sqrt())
                    .fold(0.0, f64::max);
                assert!(worst <= error, "e {e}: moved {worst} > {error}");
                assert!(worst > 0.0, "e {e}: the near-clone is a different pose");
            }
        }
        // Too small an error for even one LIVE_STEP: the pose stays exact.
        assert_eq!(near_clone_shift(1.0, 1e-9), None);
        assert_eq!(near_clone_shift(1.0, 0.0), None);
        assert_eq!(near_clone_shift(0.0, 1e-9), Some(MAX_NEAR_SHIFT));
    }

    #[test]
    fn near_clones_of_near_poses_are_one_key() {
        let rig =
            crate::synthetic::with_random_clip(crate::synthetic::banded_rig("near", 500, 20, 8), 3);
        let order = rig.lod.order.clone();
        let a = Pose::live(&[0.5; 8]);
        let b = Pose::live(&[0.5 + 3.0 * LIVE_STEP; 8]);
        assert_ne!(a, b);
        // Steps of 16 LIVE_STEPs: both round to 0.5.
        assert_eq!(a.near_clone(&rig, &order, 4), b.near_clone(&rig, &order, 4));
        // A channel the level does not evaluate is dropped (0), so it cannot split a job.
        let mut w = [0.5; 8];
        w[order[7] as usize] = 0.9;
        assert_eq!(
            Pose::live(&w).near_clone(&rig, &order[..7], 0),
            a.near_clone(&rig, &order[..7], 0)
        );
        let near = Pose::live(&[0.5; 8]).near_clone(&rig, &order, 3);
        let Some(Pose::Live(q)) = near else {
            panic!("a near-clone is a live pose")
        };
        assert!(q.iter().all(|&x| x % 8 == 0));
    }
}
