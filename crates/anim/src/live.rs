//! Live input over time (issue 47): what a live session head shows at a tick, from the
//! samples its producers sent. Pure and clock-free (times are seconds on the caller's clock),
//! so every rule here is tested without sockets or sleeps.
//!
//! - [`JitterBuffer`]: samples with the producer's timecodes, kept in timecode order (a late
//!   one slots in where it belongs), played `delay` behind the producer's clock as Live
//!   Link's "interpolate by timecode" does. The producer's clock is mapped onto the server's
//!   by the smallest `arrival − t` seen (the least-delayed sample), allowed to creep up by
//!   [`DRIFT`] so that a slower producer clock is followed.
//! - [`OneEuroFilter`]: Casiez, Roussel and Vogel (CHI 2012), for producers without
//!   timecodes: a low-pass whose cutoff rises with the signal's speed.
//! - [`Fade`]: the share of live input in what the head shows, moved linearly by at most
//!   `dt / fade` per tick, so input that starts or stops never pops.
//!
//! A sample's values are sparse and keyed: weights by channel, Live Link angles by joint-map
//! column, rotations by skeleton node, each list ascending. Two samples interpolate key by
//! key; a key only one of them has takes that one's value.

use std::collections::VecDeque;

use glam::Quat;

/// How far (seconds per second) the clock offset may creep up between samples: a producer
/// clock 0.1 % slower than the server's is followed without the buffer running dry.
pub const DRIFT: f64 = 1e-3;
/// A timecode this far (seconds) outside the buffer's range means the producer's clock
/// restarted or jumped: the buffer starts over.
pub const RESET_GAP_S: f64 = 5.0;

/// One sample's values, each list ascending by key and each key once.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LiveValues {
    /// (weight channel, weight).
    pub weights: Vec<(u32, f32)>,
    /// (joint-map column, angle in the column's unit).
    pub angles: Vec<(u32, f32)>,
    /// (skeleton node, local rotation `[x, y, z, w]`, unit).
    pub rotations: Vec<(u32, [f32; 4])>,
}

impl LiveValues {
    /// Bytes it holds on the heap, by capacity (for queue-memory charges).
    pub fn heap_bytes(&self) -> u64 {
        (self.weights.capacity() * 8 + self.angles.capacity() * 8 + self.rotations.capacity() * 20)
            as u64
    }

    /// Bytes [`LiveValues::lerp`] (or a filter step) builds from `a` and `b`, at most.
    pub fn lerp_bytes(a: &LiveValues, b: &LiveValues) -> u64 {
        ((a.weights.len() + b.weights.len()) * 8
            + (a.angles.len() + b.angles.len()) * 8
            + (a.rotations.len() + b.rotations.len()) * 20) as u64
    }

    /// `a` moved toward `b` by `s` in [0, 1]: weights and angles by lerp, rotations by slerp.
    pub fn lerp(a: &LiveValues, b: &LiveValues, s: f32) -> LiveValues {
        LiveValues {
            weights: merge(&a.weights, &b.weights, |x, y| x + s * (y - x)),
            angles: merge(&a.angles, &b.angles, |x, y| x + s * (y - x)),
            rotations: merge(&a.rotations, &b.rotations, |x, y| slerp(x, y, s)),
        }
    }
}

/// The union of two ascending keyed lists: `both(a, b)` where a key is in both, else the one
/// value there is.
fn merge<T: Copy>(a: &[(u32, T)], b: &[(u32, T)], both: impl Fn(T, T) -> T) -> Vec<(u32, T)> {
    let mut out = Vec::with_capacity(a.len().max(b.len()));
    let (mut i, mut j) = (0, 0);
    while i < a.len() || j < b.len() {
        match (a.get(i), b.get(j)) {
            (Some(&(ka, va)), Some(&(kb, vb))) if ka == kb => {
                out.push((ka, both(va, vb)));
                i += 1;
                j += 1;
            }
            (Some(&(ka, va)), Some(&(kb, _))) if ka < kb => {
                out.push((ka, va));
                i += 1;
            }
            (Some(_), Some(&(kb, vb))) | (None, Some(&(kb, vb))) => {
                out.push((kb, vb));
                j += 1;
            }
            (Some(&(ka, va)), None) => {
                out.push((ka, va));
                i += 1;
            }
            (None, None) => break,
        }
    }
    out
}

fn slerp(a: [f32; 4], b: [f32; 4], s: f32) -> [f32; 4] {
    Quat::from_array(a)
        .normalize()
        .slerp(Quat::from_array(b).normalize(), s)
        .normalize()
        .to_array()
}

/// Samples with producer timecodes, in timecode order, with the producer's clock offset.
/// `S` carries a sample's values and whatever the caller keeps with them (its memory charge).
#[derive(Debug)]
pub struct JitterBuffer<S> {
    samples: VecDeque<(f64, S)>,
    /// Server time minus producer time of the least-delayed sample (crept up by [`DRIFT`]).
    offset: Option<f64>,
    /// When `offset` was last set, server seconds.
    offset_at: f64,
    cap: usize,
}

impl<S: AsRef<LiveValues>> JitterBuffer<S> {
    /// An empty buffer that keeps at most `cap` samples (the oldest go first).
    pub fn new(cap: usize) -> JitterBuffer<S> {
        JitterBuffer {
            samples: VecDeque::new(),
            offset: None,
            offset_at: 0.0,
            cap: cap.max(2),
        }
    }

    /// Samples held.
    pub fn len(&self) -> usize {
        self.samples.len()
    }

    /// True when it holds none.
    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }

    /// Takes a sample of producer time `t` that arrived at server time `arrived`; returns
    /// what no longer fits (a sample of the same timecode it replaces, or the oldest).
    pub fn push(&mut self, t: f64, arrived: f64, sample: S) -> Vec<S> {
        let mut out = Vec::new();
        if let (Some((first, _)), Some((last, _))) = (self.samples.front(), self.samples.back())
            && (t < first - RESET_GAP_S || t > last + RESET_GAP_S)
        {
            out.extend(self.samples.drain(..).map(|(_, s)| s));
            self.offset = None;
        }
        let o = arrived - t;
        self.offset = Some(match self.offset {
            Some(p) => o.min(p + DRIFT * (arrived - self.offset_at).max(0.0)),
            None => o,
        });
        self.offset_at = arrived;
        let k = self.samples.partition_point(|(u, _)| *u < t);
        if self.samples.get(k).is_some_and(|(u, _)| *u == t) {
            if let Some(old) = self.samples.get_mut(k) {
                out.push(std::mem::replace(&mut old.1, sample));
            }
        } else {
            self.samples.insert(k, (t, sample));
        }
        while self.samples.len() > self.cap {
            if let Some((_, s)) = self.samples.pop_front() {
                out.push(s);
            }
        }
        out
    }

    /// The values to show at server time `now`, `delay` seconds behind the producer: the two
    /// samples around that producer time interpolated, the first before it, or the last
    /// after it (held). Samples before the one at or before that time are dropped.
    pub fn at(&mut self, now: f64, delay: f64) -> Option<LiveValues> {
        let tau = now - self.offset? - delay;
        let k = self.samples.partition_point(|(t, _)| *t <= tau);
        if k >= 2 {
            self.samples.drain(..k - 1);
        }
        let (t0, s0) = self.samples.front()?;
        match self.samples.get(1) {
            Some((t1, s1)) if tau > *t0 => {
                let s = ((tau - t0) / (t1 - t0)).clamp(0.0, 1.0) as f32;
                Some(LiveValues::lerp(s0.as_ref(), s1.as_ref(), s))
            }
            _ => Some(s0.as_ref().clone()),
        }
    }

    /// Empties it, returning what it held.
    pub fn clear(&mut self) -> Vec<S> {
        self.offset = None;
        self.samples.drain(..).map(|(_, s)| s).collect()
    }
}

/// One Euro filter parameters: cutoff at rest (Hz), speed coefficient, the speed's cutoff (Hz).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OneEuroParams {
    /// Cutoff at rest, Hz (> 0).
    pub min_cutoff: f32,
    /// How much the cutoff rises per unit of speed.
    pub beta: f32,
    /// Cutoff of the speed's low-pass, Hz (> 0).
    pub d_cutoff: f32,
}

/// Per key: the filtered value and the filtered speed.
#[derive(Clone, Copy, Debug, Default)]
struct Track {
    x: f32,
    dx: f32,
}

/// A One Euro filter over a head's values, one track per key (rotations per component, kept
/// on the previous rotation's hemisphere and renormalised).
#[derive(Debug, Default)]
pub struct OneEuroFilter {
    weights: Vec<(u32, Track)>,
    angles: Vec<(u32, Track)>,
    rotations: Vec<(u32, [Track; 4])>,
}

/// The smoothing factor of a first-order low-pass of cutoff `hz` sampled every `dt` s.
fn alpha(hz: f32, dt: f32) -> f32 {
    let tau = 1.0 / (2.0 * std::f32::consts::PI * hz.max(1e-6));
    1.0 / (1.0 + tau / dt)
}

fn step(track: Option<Track>, x: f32, dt: f32, p: OneEuroParams) -> Track {
    let Some(prev) = track else {
        return Track { x, dx: 0.0 };
    };
    let a_d = alpha(p.d_cutoff, dt);
    let dx = prev.dx + a_d * ((x - prev.x) / dt - prev.dx);
    let cutoff = p.min_cutoff + p.beta * dx.abs();
    let a = alpha(cutoff, dt);
    Track {
        x: prev.x + a * (x - prev.x),
        dx,
    }
}

fn find<T: Copy>(list: &[(u32, T)], k: u32) -> Option<T> {
    list.binary_search_by_key(&k, |e| e.0)
        .ok()
        .map(|i| list[i].1)
}

impl OneEuroFilter {
    /// Bytes its state holds for values like `v` (for charges).
    pub fn bytes_for(v: &LiveValues) -> u64 {
        (v.weights.len() * 12 + v.angles.len() * 12 + v.rotations.len() * 36) as u64
    }

    /// `v` filtered, `dt` seconds after the last call (the first call passes `v` through).
    pub fn filter(&mut self, v: &LiveValues, dt: f32, p: OneEuroParams) -> LiveValues {
        let dt = dt.max(1e-4);
        let weights: Vec<(u32, Track)> = v
            .weights
            .iter()
            .map(|&(k, x)| (k, step(find(&self.weights, k), x, dt, p)))
            .collect();
        let angles: Vec<(u32, Track)> = v
            .angles
            .iter()
            .map(|&(k, x)| (k, step(find(&self.angles, k), x, dt, p)))
            .collect();
        let rotations: Vec<(u32, [Track; 4])> = v
            .rotations
            .iter()
            .map(|&(k, q)| {
                let prev = find(&self.rotations, k);
                // The same rotation as −q: keep the side of the last one, or the filter would
                // pass through zero.
                let dot: f32 = prev.map_or(1.0, |p| (0..4).map(|i| p[i].x * q[i]).sum());
                let q = if dot < 0.0 { q.map(|c| -c) } else { q };
                (
                    k,
                    std::array::from_fn(|i| step(prev.map(|p| p[i]), q[i], dt, p)),
                )
            })
            .collect();
        let out = LiveValues {
            weights: weights.iter().map(|&(k, t)| (k, t.x)).collect(),
            angles: angles.iter().map(|&(k, t)| (k, t.x)).collect(),
            rotations: rotations
                .iter()
                .map(|(k, t)| {
                    let q = Quat::from_array(t.map(|t| t.x));
                    let q = if q.length_squared() > 1e-12 {
                        q.normalize()
                    } else {
                        Quat::IDENTITY
                    };
                    (*k, q.to_array())
                })
                .collect(),
        };
        self.weights = weights;
        self.angles = angles;
        self.rotations = rotations;
        out
    }
}

/// The share of live input in what a head shows, in [0, 1].
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Fade {
    /// The share now.
    pub alpha: f32,
}

impl Fade {
    /// Moves the share toward 1 (input `on`) or 0 by `dt / fade` at most (at once when
    /// `fade` is 0), and returns it.
    pub fn step(&mut self, on: bool, dt: f64, fade: f64) -> f32 {
        let target = if on { 1.0 } else { 0.0 };
        self.alpha = if fade <= 0.0 {
            target
        } else {
            let d = (dt / fade) as f32;
            if on {
                (self.alpha + d).min(1.0)
            } else {
                (self.alpha - d).max(0.0)
            }
        };
        self.alpha
    }
}

/// Live weights over what a head shows: each channel the values name moves toward its live
/// weight by `alpha` (`w ← (1 − α)·w + α·live`); others keep theirs.
pub fn apply_weights(w: &mut [f32], v: &LiveValues, alpha: f32) {
    for &(k, x) in &v.weights {
        if let Some(slot) = w.get_mut(k as usize) {
            *slot = (1.0 - alpha) * *slot + alpha * x;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn values(w: f32) -> LiveValues {
        LiveValues {
            weights: vec![(3, w), (7, 1.0 - w)],
            angles: Vec::new(),
            rotations: Vec::new(),
        }
    }

    struct S(LiveValues);
    impl AsRef<LiveValues> for S {
        fn as_ref(&self) -> &LiveValues {
            &self.0
        }
    }

    #[test]
    fn the_jitter_buffer_reorders_and_interpolates_by_timecode() {
        let mut b = JitterBuffer::new(16);
        // Producer time 10..; the network delays by 20 ms, one sample by 145 ms more, so it
        // arrives after its successor.
        let sent = [(10.0, 0.0), (10.1, 0.1), (10.2, 0.2), (10.3, 0.3)];
        let arrival = |t: f64| t - 10.0 + 0.02 + if t == 10.1 { 0.145 } else { 0.0 };
        let mut order: Vec<_> = sent.to_vec();
        order.sort_by(|a, b| arrival(a.0).total_cmp(&arrival(b.0)));
        assert_eq!(order[1].0, 10.2, "out of order on arrival");
        for (t, w) in order {
            b.push(t, arrival(t), S(values(w as f32)));
        }
        // At server time 0.22 with 100 ms of delay: producer time 10.1 (offset −9.98).
        let v = b.at(0.2 + 0.02 + 0.05, 0.1).expect("values");
        // Producer time 10.15: halfway between the samples of 10.1 and 10.2.
        assert!((v.weights[0].1 - 0.15).abs() < 1e-4, "{v:?}");
        assert!((v.weights[1].1 - 0.85).abs() < 1e-4, "{v:?}");
        // Past the newest: held.
        let v = b.at(5.0, 0.1).expect("held");
        assert!((v.weights[0].1 - 0.3).abs() < 1e-6);
        assert_eq!(b.len(), 1, "samples before the one shown are dropped");
    }

    #[test]
    fn a_restarted_producer_clock_starts_the_buffer_over() {
        let mut b = JitterBuffer::new(4);
        b.push(100.0, 1.0, S(values(0.1)));
        b.push(100.1, 1.1, S(values(0.2)));
        let dropped = b.push(0.0, 1.2, S(values(0.9)));
        assert_eq!(dropped.len(), 2);
        let v = b.at(1.2, 0.0).expect("values");
        assert!((v.weights[0].1 - 0.9).abs() < 1e-6);
        // Over capacity the oldest go.
        for k in 1..10 {
            b.push(
                f64::from(k) * 0.01,
                1.2 + f64::from(k) * 0.01,
                S(values(0.0)),
            );
        }
        assert_eq!(b.len(), 4);
    }

    #[test]
    fn interpolation_keeps_keys_only_one_side_has() {
        let a = LiveValues {
            weights: vec![(1, 0.0), (2, 1.0)],
            ..Default::default()
        };
        let b = LiveValues {
            weights: vec![(2, 0.0), (5, 0.5)],
            ..Default::default()
        };
        let m = LiveValues::lerp(&a, &b, 0.25);
        assert_eq!(m.weights, vec![(1, 0.0), (2, 0.75), (5, 0.5)]);
    }

    #[test]
    fn one_euro_smooths_noise_at_rest_and_follows_a_fast_move() {
        let p = OneEuroParams {
            min_cutoff: 1.0,
            beta: 0.5,
            d_cutoff: 1.0,
        };
        let dt = 1.0 / 30.0;
        let mut f = OneEuroFilter::default();
        let mut rng = crowdmorph_core::rng::SplitMix64(7);
        // Noise of ±0.05 around 0.5: the filtered spread is a fraction of the raw one.
        let (mut raw_dev, mut out_dev) = (0.0f32, 0.0f32);
        for k in 0..300 {
            let noise = (rng.unit() - 0.5) * 0.1;
            let v = f.filter(&values(0.5 + noise), dt, p);
            if k > 60 {
                raw_dev = raw_dev.max(noise.abs());
                out_dev = out_dev.max((v.weights[0].1 - 0.5).abs());
            }
        }
        assert!(out_dev < 0.5 * raw_dev, "{out_dev} vs {raw_dev}");
        // A step to 1: with beta the filter is within 3 % of it after 10 frames; a plain
        // 1 Hz low-pass does not.
        let mut plain = OneEuroFilter::default();
        let slow = OneEuroParams { beta: 0.0, ..p };
        let (mut a, mut b) = (0.0, 0.0);
        for _ in 0..5 {
            f.filter(&values(0.5), dt, p);
            plain.filter(&values(0.5), dt, slow);
        }
        for _ in 0..10 {
            a = f.filter(&values(1.0), dt, p).weights[0].1;
            b = plain.filter(&values(1.0), dt, slow).weights[0].1;
        }
        assert!(a > 0.97 && b < 0.95, "fast {a}, plain {b}");
    }

    #[test]
    fn the_fade_moves_at_most_its_step() {
        let mut f = Fade::default();
        let dt = 1.0 / 30.0;
        let mut last = 0.0;
        let mut ticks = 0;
        while f.step(true, dt, 0.25) < 1.0 {
            assert!(f.alpha - last <= (dt / 0.25) as f32 + 1e-6);
            last = f.alpha;
            ticks += 1;
        }
        assert_eq!(ticks, 7, "0.25 s at 30 fps is 7.5 ticks");
        assert_eq!(f.step(false, dt, 0.0), 0.0, "no fade: at once");
        let mut w = [0.2, 0.4];
        apply_weights(
            &mut w,
            &LiveValues {
                weights: vec![(1, 1.0), (9, 1.0)],
                ..Default::default()
            },
            0.5,
        );
        assert_eq!(w, [0.2, 0.7], "channel 9 is past the rig's: ignored");
    }
}
