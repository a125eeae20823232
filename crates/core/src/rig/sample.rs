//! Keyframe sampling as the glTF 2.0 specification defines it (Appendix C, "Animation sampler
//! interpolation modes"), for tracks of several scalars per key (morph weights).
//!
//! Before the first key the first value holds, after the last key the last value holds.

use serde::{Deserialize, Serialize};

/// glTF sampler interpolation.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Interpolation {
    /// Hold the value of the key at or before `t`.
    Step,
    /// Linear interpolation between the surrounding keys.
    Linear,
    /// Cubic Hermite spline with per-key in- and out-tangents.
    CubicSpline,
}

/// A keyframed track of `width` scalars per key.
#[derive(Clone, Debug, PartialEq)]
pub struct KeyTrack {
    /// Key times in seconds, non-decreasing.
    pub times: Vec<f32>,
    /// For STEP and LINEAR: `keys × width` values. For CUBICSPLINE: `keys × 3 × width`, per key
    /// the in-tangents, then the values, then the out-tangents (glTF layout).
    pub values: Vec<f32>,
    /// Scalars per key (the number of morph targets the channel drives).
    pub width: usize,
    /// Interpolation mode.
    pub interpolation: Interpolation,
}

impl KeyTrack {
    /// Checks that times and values agree and are usable. Returns a description of the problem.
    pub fn check(&self) -> Result<(), String> {
        let keys = self.times.len();
        if keys == 0 {
            return Err("sampler has no keyframes".into());
        }
        let per_key = match self.interpolation {
            Interpolation::CubicSpline => 3 * self.width,
            _ => self.width,
        };
        if self.values.len() != keys * per_key {
            return Err(format!(
                "sampler output has {} values, expected {} keys × {per_key}",
                self.values.len(),
                keys
            ));
        }
        if self.times.iter().any(|t| !t.is_finite()) || self.values.iter().any(|v| !v.is_finite()) {
            return Err("sampler contains a non-finite value (NaN or infinity)".into());
        }
        if self.times.windows(2).any(|w| w[1] < w[0]) {
            return Err("sampler key times are not increasing".into());
        }
        Ok(())
    }

    /// Time of the last key.
    pub fn last_time(&self) -> f32 {
        self.times.last().copied().unwrap_or(0.0)
    }

    fn value(&self, key: usize, j: usize) -> f32 {
        match self.interpolation {
            Interpolation::CubicSpline => self.values[(key * 3 + 1) * self.width + j],
            _ => self.values[key * self.width + j],
        }
    }
}

/// Samples `track` at time `t` into `out` (length `track.width`). The track must have passed
/// [`KeyTrack::check`].
pub fn sample_track(track: &KeyTrack, t: f32, out: &mut [f32]) {
    let times = &track.times;
    let n = times.len();
    let w = track.width.min(out.len());
    if n == 0 {
        return;
    }
    // Index of the first key strictly after t.
    let next = times.partition_point(|&k| k <= t);
    if next == 0 {
        for (j, o) in out.iter_mut().enumerate().take(w) {
            *o = track.value(0, j);
        }
        return;
    }
    if next == n {
        for (j, o) in out.iter_mut().enumerate().take(w) {
            *o = track.value(n - 1, j);
        }
        return;
    }
    let k = next - 1;
    let (t0, t1) = (times[k], times[next]);
    let td = t1 - t0;
    if track.interpolation == Interpolation::Step || td <= 0.0 {
        for (j, o) in out.iter_mut().enumerate().take(w) {
            *o = track.value(k, j);
        }
        return;
    }
    let s = (t - t0) / td;
    match track.interpolation {
        Interpolation::Step | Interpolation::Linear => {
            for (j, o) in out.iter_mut().enumerate().take(w) {
                let (a, b) = (track.value(k, j), track.value(next, j));
                *o = a + (b - a) * s;
            }
        }
        Interpolation::CubicSpline => {
            let (s2, s3) = (s * s, s * s * s);
            let h00 = 2.0 * s3 - 3.0 * s2 + 1.0;
            let h10 = s3 - 2.0 * s2 + s;
            let h01 = -2.0 * s3 + 3.0 * s2;
            let h11 = s3 - s2;
            let width = track.width;
            for (j, o) in out.iter_mut().enumerate().take(w) {
                let p0 = track.values[(k * 3 + 1) * width + j];
                let m0 = track.values[(k * 3 + 2) * width + j] * td;
                let p1 = track.values[(next * 3 + 1) * width + j];
                let m1 = track.values[(next * 3) * width + j] * td;
                *o = h00 * p0 + h10 * m0 + h01 * p1 + h11 * m1;
            }
        }
    }
}

/// Samples a rotation track (width 4, quaternions x, y, z, w) at time `t` as glTF asks:
/// spherical linear interpolation (shortest path) for LINEAR, the key for STEP, and the
/// cubic Hermite spline normalized for CUBICSPLINE. `out` gets a unit quaternion.
pub fn sample_rotation(track: &KeyTrack, t: f32, out: &mut [f32; 4]) {
    let times = &track.times;
    let n = times.len();
    let next = times.partition_point(|&k| k <= t);
    if track.interpolation == Interpolation::Linear && next > 0 && next < n {
        let k = next - 1;
        let td = times[next] - times[k];
        let q = |key: usize| {
            glam::Quat::from_xyzw(
                track.value(key, 0),
                track.value(key, 1),
                track.value(key, 2),
                track.value(key, 3),
            )
            .normalize()
        };
        let s = if td > 0.0 { (t - times[k]) / td } else { 0.0 };
        *out = q(k).slerp(q(next), s).normalize().to_array();
        return;
    }
    sample_track(track, t, out);
    let q = glam::Vec4::from(*out);
    *out = q.try_normalize().unwrap_or(glam::Vec4::W).to_array();
}

#[cfg(test)]
mod tests {
    use super::*;

    fn track(interpolation: Interpolation, values: Vec<f32>) -> KeyTrack {
        KeyTrack {
            times: vec![1.0, 2.0],
            values,
            width: 1,
            interpolation,
        }
    }

    #[test]
    fn linear_step_and_hold() {
        let lin = track(Interpolation::Linear, vec![0.0, 1.0]);
        let mut o = [0.0];
        for (t, want) in [(0.0, 0.0), (1.0, 0.0), (1.25, 0.25), (2.0, 1.0), (9.0, 1.0)] {
            sample_track(&lin, t, &mut o);
            assert!((o[0] - want).abs() < 1e-6, "t={t}: {} vs {want}", o[0]);
        }
        let step = track(Interpolation::Step, vec![0.0, 1.0]);
        sample_track(&step, 1.99, &mut o);
        assert_eq!(o[0], 0.0);
        sample_track(&step, 2.0, &mut o);
        assert_eq!(o[0], 1.0);
    }

    #[test]
    fn cubic_hermite_matches_formula() {
        // in, value, out for each key; tangents in units per second.
        let cub = track(
            Interpolation::CubicSpline,
            vec![0.0, 0.0, 2.0, -1.0, 1.0, 0.0],
        );
        let mut o = [0.0];
        sample_track(&cub, 1.5, &mut o);
        // s = 0.5, td = 1: h00=.5 h10=.125 h01=.5 h11=-.125 → 0 + .125*2 + .5*1 + (-.125)(-1)
        assert!((o[0] - 0.875).abs() < 1e-6);
    }
}
