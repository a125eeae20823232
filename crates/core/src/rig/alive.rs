//! Liveliness without authoring (issue 47): procedural layers that make a crowd look alive —
//! blinks, eye saccades, look-at a world point, breathing — each a pure function of a head's
//! seed and the session clock (and, for look-at, its placement), so equal inputs give
//! bit-equal weights and heads with equal seeds stay clones. No I/O, no state between ticks.
//!
//! The processes (times in seconds; `U` a uniform draw from the head's seed):
//! - **Blinks**: a jittered clock. Blink `n` starts at `φ + n·P + U·J` with `P` =
//!   [`BLINK_PERIOD_S`] (4 s) and `J` = [`BLINK_JITTER_S`] (3.4 s), `φ` a per-seed phase. An
//!   interval is `P` plus the difference of two uniforms: triangular on `[P − J, P + J]` =
//!   [0.6, 7.4] s, mean exactly 4 s (15 a minute, the low end of the 15–20 blinks a minute
//!   people make at rest), standard deviation `J/√6` ≈ 1.4 s. A jittered clock rather than a
//!   renewal process (gamma, shifted exponential) because it is looked up in O(1) at any
//!   time without replaying the blinks before it, and it never puts two blinks within 0.6 s.
//!   A blink lasts 150–250 ms (uniform): the lids close over its first third (fast) and open
//!   over the rest (slower), smoothstep ramps. It overrides `eyeBlinkLeft`/`Right` by its
//!   closure `a`: `w ← (1 − a)·w + a`, so a clip's own blinks and squints show between.
//! - **Saccades**: the same clock with period [`SACCADE_PERIOD_S`] (1.1 s) and jitter
//!   [`SACCADE_JITTER_S`] (0.9 s): fixations of 0.2–2.0 s. Each fixation looks at a random
//!   offset, yaw within ±[`SACCADE_YAW_DEG`] and pitch within ±[`SACCADE_PITCH_DEG`], reached
//!   in [`SACCADE_MOVE_S`] (40 ms, a linear move). Saccades add to look-at.
//! - **Look-at**: the target in the head's frame (its position, yaw and scale undone) seen
//!   from the rig's eyes (their joints' rest midpoint, else the centroid of the vertices its
//!   blink targets move, else its bounding box's centre): a yaw (positive toward the
//!   character's left, +X) and a pitch (positive up). On a skinned rig with a head joint the
//!   head takes [`HEAD_SHARE`] of it, limited to ±[`HEAD_YAW_DEG`] and ±[`HEAD_PITCH_DEG`];
//!   the eyes take the rest, limited to ±[`EYE_LIMIT_DEG`].
//! - **Breathing**: `b = ½ − ½·cos(2π f t + φ)`, `f` in [0.2, 0.3] Hz per seed: added to
//!   `jawOpen` (× 0.03) and `noseSneerLeft`/`Right` (× 0.05), and on a skinned rig a chest (or
//!   neck) joint pitched by ±[`BREATH_CHEST_DEG`].
//!
//! Eye targets (ARKit names, the character's own left and right): a gaze toward the
//! character's left raises `eyeLookOutLeft` and `eyeLookInRight`, toward its right
//! `eyeLookInLeft` and `eyeLookOutRight`, up `eyeLookUp*`, down `eyeLookDown*`; each by
//! `angle / 30°` ([`LOOK_FULL_DEG`]), clamped to [0, 1], overriding what is below. On a
//! skinned rig the eye joints (those the rig's joint map turns for `LeftEyeYaw`, ...) turn by
//! the same angles about rig axes, from the pose below. A rig without a layer's targets or
//! joints gets nothing from that layer.

use glam::{Mat4, Quat, Vec3};

use super::{Rig, Skeleton, TargetId, Trs};
use crate::rng::SplitMix64;

/// Blink clock period, seconds: the mean interval.
pub const BLINK_PERIOD_S: f64 = 4.0;
/// Blink clock jitter, seconds (< period − longest blink, so blinks never overlap).
pub const BLINK_JITTER_S: f64 = 3.4;
/// Shortest blink, seconds.
pub const BLINK_MIN_S: f64 = 0.15;
/// Longest blink, seconds.
pub const BLINK_MAX_S: f64 = 0.25;
/// Saccade clock period, seconds: the mean fixation.
pub const SACCADE_PERIOD_S: f64 = 1.1;
/// Saccade clock jitter, seconds.
pub const SACCADE_JITTER_S: f64 = 0.9;
/// How long a saccade's move takes, seconds.
pub const SACCADE_MOVE_S: f64 = 0.04;
/// Largest saccade yaw offset, degrees.
pub const SACCADE_YAW_DEG: f32 = 6.0;
/// Largest saccade pitch offset, degrees.
pub const SACCADE_PITCH_DEG: f32 = 4.0;
/// Eye angle at which an `eyeLook*` weight reaches 1, degrees.
pub const LOOK_FULL_DEG: f32 = 30.0;
/// Farthest an eye joint turns from the pose below, degrees.
pub const EYE_LIMIT_DEG: f32 = 30.0;
/// Share of a look-at's angles the head joint takes.
pub const HEAD_SHARE: f32 = 0.4;
/// Farthest the head joint turns left or right for a look-at, degrees.
pub const HEAD_YAW_DEG: f32 = 35.0;
/// Farthest the head joint turns up or down for a look-at, degrees.
pub const HEAD_PITCH_DEG: f32 = 20.0;
/// Breathing frequencies, Hz: `[lowest, highest]`.
pub const BREATH_HZ: [f64; 2] = [0.2, 0.3];
/// How far breathing pitches the chest joint each way, degrees.
pub const BREATH_CHEST_DEG: f32 = 0.8;

/// Targets breathing adds to, with their amplitude.
const BREATH_TARGETS: [(&str, f32); 3] = [
    ("jawOpen", 0.03),
    ("noseSneerLeft", 0.05),
    ("noseSneerRight", 0.05),
];
/// Chest-like nodes breathing turns, first found wins: Ready Player Me, VRM, VRoid, then
/// necks.
const CHEST_NAMES: [&str; 7] = [
    "Spine2",
    "upperChest",
    "chest",
    "J_Bip_C_UpperChest",
    "J_Bip_C_Chest",
    "Neck",
    "neck",
];

// Streams of random draws, so a blink's and a saccade's numbers are independent.
const PHASE: u64 = 1;
const BLINK: u64 = 2;
const SACCADE: u64 = 3;
const GAZE: u64 = 4;
const BREATH: u64 = 5;

/// Which procedural layers a head has, and its seed.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct AliveParams {
    /// Blinks.
    pub blink: bool,
    /// Eye saccades.
    pub saccades: bool,
    /// A world point to look at.
    pub look_at: Option<[f32; 3]>,
    /// Breathing.
    pub breathing: bool,
    /// The seed ([`head_seed`] of the head id when the client gives none).
    pub seed: u64,
}

/// Where a head stands: its placement in the world (as a session head's).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Placement {
    /// The rig origin's world position.
    pub position: [f32; 3],
    /// Turn about +Y, degrees.
    pub yaw_deg: f32,
    /// Uniform scale.
    pub scale: f32,
}

/// The seed a head without one of its own gets: its id, mixed.
pub fn head_seed(head: u64) -> u64 {
    SplitMix64(head ^ 0xA11E_0000_0000_0047).next_u64()
}

/// Draws for item `n` of a stream of a seed.
fn draws(seed: u64, stream: u64, n: i64) -> SplitMix64 {
    let base = SplitMix64(seed.wrapping_add(stream.wrapping_mul(0x9E37_79B9_7F4A_7C15))).next_u64();
    let mut r = SplitMix64(base ^ (n as u64).wrapping_mul(0xD1B5_4A32_D192_ED03));
    r.next_u64();
    r
}

/// A per-seed, per-stream phase in `[0, period)`.
fn phase(seed: u64, stream: u64, period: f64) -> f64 {
    draws(seed, PHASE, stream as i64).f64() * period
}

/// Blink `n`'s start and length, seconds.
pub fn blink_start(seed: u64, n: i64) -> (f64, f64) {
    let mut r = draws(seed, BLINK, n);
    let start =
        phase(seed, BLINK, BLINK_PERIOD_S) + n as f64 * BLINK_PERIOD_S + r.f64() * BLINK_JITTER_S;
    (start, BLINK_MIN_S + r.f64() * (BLINK_MAX_S - BLINK_MIN_S))
}

fn smoothstep(x: f64) -> f64 {
    let x = x.clamp(0.0, 1.0);
    x * x * (3.0 - 2.0 * x)
}

/// How closed the eyes are at time `t` (0 open, 1 closed).
pub fn blink_amount(seed: u64, t: f64) -> f32 {
    let n = ((t - phase(seed, BLINK, BLINK_PERIOD_S)) / BLINK_PERIOD_S).floor() as i64;
    let mut a: f64 = 0.0;
    for k in [n - 1, n] {
        let (s, d) = blink_start(seed, k);
        if t >= s && t < s + d {
            let u = (t - s) / d;
            let close = 1.0 / 3.0;
            a = a.max(if u < close {
                smoothstep(u / close)
            } else {
                1.0 - smoothstep((u - close) / (1.0 - close))
            });
        }
    }
    a as f32
}

/// Saccade `n`'s start, seconds.
fn saccade_start(seed: u64, n: i64) -> f64 {
    phase(seed, SACCADE, SACCADE_PERIOD_S)
        + n as f64 * SACCADE_PERIOD_S
        + draws(seed, SACCADE, n).f64() * SACCADE_JITTER_S
}

/// Fixation `n`'s gaze offset, radians (yaw, pitch).
fn fixation(seed: u64, n: i64) -> (f32, f32) {
    let mut r = draws(seed, GAZE, n);
    let yaw = (2.0 * r.unit() - 1.0) * SACCADE_YAW_DEG;
    let pitch = (2.0 * r.unit() - 1.0) * SACCADE_PITCH_DEG;
    (yaw.to_radians(), pitch.to_radians())
}

/// The saccades' gaze offset at time `t`, radians (yaw toward the character's left, pitch up).
pub fn saccade_offset(seed: u64, t: f64) -> (f32, f32) {
    let mut n = ((t - phase(seed, SACCADE, SACCADE_PERIOD_S)) / SACCADE_PERIOD_S).floor() as i64;
    let mut s = saccade_start(seed, n);
    if t < s {
        n -= 1;
        s = saccade_start(seed, n);
    }
    let to = fixation(seed, n);
    let moved = (t - s) / SACCADE_MOVE_S;
    if moved >= 1.0 {
        return to;
    }
    let from = fixation(seed, n - 1);
    let a = moved.max(0.0) as f32;
    (from.0 + a * (to.0 - from.0), from.1 + a * (to.1 - from.1))
}

/// Breathing at time `t`, in [0, 1].
pub fn breath(seed: u64, t: f64) -> f32 {
    let mut r = draws(seed, BREATH, 0);
    let f = BREATH_HZ[0] + r.f64() * (BREATH_HZ[1] - BREATH_HZ[0]);
    let phi = r.f64() * std::f64::consts::TAU;
    (0.5 - 0.5 * (std::f64::consts::TAU * f * t + phi).cos()) as f32
}

/// The direction from `eyes` (rig space) of a head placed at `place` to the world point
/// `target`, as (yaw toward the character's left, pitch up), radians. A target at the eyes
/// is straight ahead.
pub fn look_angles(eyes: Vec3, place: &Placement, target: [f32; 3]) -> (f32, f32) {
    let turn = Quat::from_rotation_y(place.yaw_deg.rem_euclid(360.0).to_radians());
    let from = Vec3::from(place.position) + turn * (eyes * place.scale);
    let d = turn.inverse() * (Vec3::from(target) - from);
    if !d.is_finite() || d.length_squared() == 0.0 {
        return (0.0, 0.0);
    }
    (d.x.atan2(d.z), d.y.atan2(d.x.hypot(d.z)))
}

/// What a rig offers the procedural layers, found once per rig: its channels by ARKit name,
/// the joints its joint map turns for the head and eyes, a chest joint, where its eyes are.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct AliveRig {
    /// `eyeBlinkLeft`, `eyeBlinkRight` channels.
    blink: Vec<TargetId>,
    /// Per direction (out-left/in-right, in-left/out-right, up, down) the channels raised.
    look: [Vec<TargetId>; 4],
    /// Breathing's channels and amplitudes.
    breath: Vec<(TargetId, f32)>,
    /// Eye nodes (left, right), if the skeleton's joint map turns them.
    eyes: Vec<u32>,
    /// Head node.
    head: Option<u32>,
    /// Chest (or neck) node.
    chest: Option<u32>,
    /// Where the eyes are, rig space.
    eye_origin: Vec3,
}

impl AliveRig {
    /// Most bytes [`AliveRig::new`] holds for `rig`: its lists, at most every channel (by
    /// name, a name may have several) in each.
    pub fn bytes_for(rig: &Rig) -> u64 {
        let nodes = rig.skeleton.as_ref().map_or(0, |s| s.nodes.len()) as u64;
        size_of::<AliveRig>() as u64 + 8 * 8 * rig.targets.len() as u64 + 64 * (nodes + 8)
    }

    /// The rig's layers' targets, found by `find` (a name's channels, in any loose spelling
    /// the caller accepts; empty when the rig lacks it), and its joints.
    pub fn new(rig: &Rig, find: impl Fn(&str) -> Vec<TargetId>) -> AliveRig {
        let many = |names: &[&str]| {
            let mut v: Vec<TargetId> = names.iter().flat_map(|n| find(n)).collect();
            v.sort_unstable();
            v.dedup();
            v
        };
        let blink = many(&["eyeBlinkLeft", "eyeBlinkRight"]);
        let look = [
            many(&["eyeLookOutLeft", "eyeLookInRight"]),
            many(&["eyeLookInLeft", "eyeLookOutRight"]),
            many(&["eyeLookUpLeft", "eyeLookUpRight"]),
            many(&["eyeLookDownLeft", "eyeLookDownRight"]),
        ];
        let breath = BREATH_TARGETS
            .iter()
            .flat_map(|&(n, a)| find(n).into_iter().map(move |k| (k, a)))
            .collect();
        let (mut eyes, mut head, mut chest) = (Vec::new(), None, None);
        let mut eye_origin = None;
        if let Some(sk) = &rig.skeleton {
            let map = sk.joint_map();
            let node = |column: &str| {
                map.channels
                    .iter()
                    .find(|c| c.column == column)
                    .map(|c| c.node)
            };
            head = node("HeadYaw");
            eyes = ["LeftEyeYaw", "RightEyeYaw"]
                .iter()
                .filter_map(|c| node(c))
                .collect();
            eyes.dedup();
            chest = CHEST_NAMES
                .iter()
                .find_map(|n| sk.nodes.iter().position(|x| x.name == *n).map(|i| i as u32));
            if !eyes.is_empty() {
                let at = rest_positions(sk);
                let sum: Vec3 = eyes.iter().map(|&e| at[e as usize]).sum();
                eye_origin = Some(sum / eyes.len() as f32);
            }
        }
        let eye_origin = eye_origin
            .or_else(|| moved_centroid(rig, &blink))
            .unwrap_or_else(|| {
                let b = rig.bbox();
                (b.min + b.max) * 0.5
            });
        AliveRig {
            blink,
            look,
            breath,
            eyes,
            head,
            chest,
            eye_origin: if eye_origin.is_finite() {
                eye_origin
            } else {
                Vec3::ZERO
            },
        }
    }

    /// Where the rig's eyes are, rig space.
    pub fn eye_origin(&self) -> Vec3 {
        self.eye_origin
    }

    /// Whether the rig has eye joints, so a look-at turns joints.
    pub fn has_eye_joints(&self) -> bool {
        !self.eyes.is_empty()
    }

    /// Whether the rig has joints the layers turn (head, eyes or chest).
    pub fn has_joints(&self) -> bool {
        !self.eyes.is_empty() || self.head.is_some() || self.chest.is_some()
    }

    /// Whether `p` changes anything on this rig's weights or joints.
    pub fn moves(&self, p: &AliveParams) -> bool {
        let gaze = p.saccades || p.look_at.is_some();
        (p.blink && !self.blink.is_empty())
            || (gaze && (self.look.iter().any(|l| !l.is_empty()) || !self.eyes.is_empty()))
            || (p.breathing && (!self.breath.is_empty() || self.chest.is_some()))
    }

    /// The gaze at time `t`, split into the head joint's share and the eyes', radians
    /// ((yaw, pitch) each); `None` without saccades or look-at.
    fn gaze(&self, p: &AliveParams, place: &Placement, t: f64) -> Option<[(f32, f32); 2]> {
        if !p.saccades && p.look_at.is_none() {
            return None;
        }
        let (mut yaw, mut pitch) = match p.look_at {
            Some(target) => look_angles(self.eye_origin, place, target),
            None => (0.0, 0.0),
        };
        let (mut hy, mut hp) = (0.0, 0.0);
        // Only a look-at turns the head: saccades are the eyes' own.
        if self.head.is_some() && p.look_at.is_some() {
            hy = (HEAD_SHARE * yaw).clamp(-HEAD_YAW_DEG.to_radians(), HEAD_YAW_DEG.to_radians());
            hp = (HEAD_SHARE * pitch)
                .clamp(-HEAD_PITCH_DEG.to_radians(), HEAD_PITCH_DEG.to_radians());
        }
        if p.saccades {
            let (sy, sp) = saccade_offset(p.seed, t);
            yaw += sy;
            pitch += sp;
        }
        let lim = EYE_LIMIT_DEG.to_radians();
        Some([
            (hy, hp),
            ((yaw - hy).clamp(-lim, lim), (pitch - hp).clamp(-lim, lim)),
        ])
    }

    /// Applies the layers `p` enables at time `t` to `w` (one weight per rig channel), for a
    /// head placed at `place`: blinks and gaze override their targets, breathing adds.
    pub fn apply_weights(&self, p: &AliveParams, place: &Placement, t: f64, w: &mut [f32]) {
        let mut set = |ks: &[TargetId], f: &dyn Fn(f32) -> f32| {
            for &k in ks {
                if let Some(v) = w.get_mut(k as usize) {
                    *v = f(*v);
                }
            }
        };
        if p.blink {
            let a = blink_amount(p.seed, t);
            set(&self.blink, &|v| (1.0 - a) * v + a);
        }
        if let Some([_, (yaw, pitch)]) = self.gaze(p, place, t) {
            let full = LOOK_FULL_DEG.to_radians();
            let amount = |x: f32| (x / full).clamp(0.0, 1.0);
            let [left, right, up, down] =
                [amount(yaw), amount(-yaw), amount(pitch), amount(-pitch)];
            set(&self.look[0], &|_| left);
            set(&self.look[1], &|_| right);
            set(&self.look[2], &|_| up);
            set(&self.look[3], &|_| down);
        }
        if p.breathing {
            let b = breath(p.seed, t);
            for &(k, amp) in &self.breath {
                if let Some(v) = w.get_mut(k as usize) {
                    *v += amp * b;
                }
            }
        }
    }

    /// Turns the skeleton's joints for the layers `p` enables at time `t`, from `locals` (one
    /// local transform per node, the pose below): the head by its share of a look-at, the
    /// eyes by the gaze, the chest by breathing — each about rig axes from where the pose
    /// below put it.
    pub fn apply_locals(
        &self,
        sk: &Skeleton,
        p: &AliveParams,
        place: &Placement,
        t: f64,
        locals: &mut [Trs],
    ) {
        if locals.len() != sk.nodes.len() {
            return;
        }
        let mut turns: Vec<(u32, Quat)> = Vec::with_capacity(4);
        if p.breathing
            && let Some(c) = self.chest
        {
            let b = breath(p.seed, t);
            let a = (BREATH_CHEST_DEG * (2.0 * b - 1.0)).to_radians();
            turns.push((c, Quat::from_rotation_x(-a)));
        }
        if let Some([(hy, hp), (ey, ep)]) = self.gaze(p, place, t) {
            if let Some(h) = self.head
                && (hy != 0.0 || hp != 0.0)
            {
                turns.push((h, gaze_turn(hy, hp)));
            }
            for &e in &self.eyes {
                turns.push((e, gaze_turn(ey, ep)));
            }
        }
        // Parents before children: a parent's turn moves the frame its children turn in.
        turns.sort_by_key(|(n, _)| *n);
        for (node, delta) in turns {
            let parent = parent_rotation(sk, locals, node);
            let l = &mut locals[node as usize];
            let r = Quat::from_array(l.rotation).normalize();
            l.rotation = (parent.inverse() * delta * parent * r)
                .normalize()
                .to_array();
        }
    }
}

/// The rotation that turns +Z (a gaze straight ahead) by `yaw` toward +X and `pitch` up.
fn gaze_turn(yaw: f32, pitch: f32) -> Quat {
    // Rotating about +X by a positive angle tips +Z down, hence the minus.
    Quat::from_rotation_y(yaw) * Quat::from_rotation_x(-pitch)
}

/// `node`'s parent's global rotation in the pose `locals`.
fn parent_rotation(sk: &Skeleton, locals: &[Trs], node: u32) -> Quat {
    let mut q = Quat::IDENTITY;
    let mut n = sk.nodes[node as usize].parent;
    // A skeleton lists parents before children; the step count bounds a malformed one.
    for _ in 0..sk.nodes.len() {
        let Some(x) = sk.nodes.get(n as usize) else {
            break;
        };
        q = Quat::from_array(locals[n as usize].rotation).normalize() * q;
        n = x.parent;
    }
    q
}

/// Every node's rest position, rig space.
fn rest_positions(sk: &Skeleton) -> Vec<Vec3> {
    let mut globals: Vec<Mat4> = Vec::with_capacity(sk.nodes.len());
    for n in &sk.nodes {
        let local = n.rest.matrix();
        let g = match globals.get(n.parent as usize) {
            Some(p) => *p * local,
            None => local,
        };
        globals.push(g);
    }
    globals.iter().map(|g| g.w_axis.truncate()).collect()
}

/// The centroid of the base positions of the vertices `channels` move, if any.
fn moved_centroid(rig: &Rig, channels: &[TargetId]) -> Option<Vec3> {
    let (mut sum, mut n) = (glam::DVec3::ZERO, 0u64);
    for p in rig.primitives.iter() {
        for t in p.targets.iter().filter(|t| channels.contains(&t.target)) {
            for &v in &t.vertices {
                if let Some(x) = p.positions.get(v as usize) {
                    sum += x.as_dvec3();
                    n += 1;
                }
            }
        }
    }
    (n > 0).then(|| (sum / n as f64).as_vec3())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Blink onsets of `seed` over `seconds`, found by sampling at 100 Hz (a rising edge of
    /// the closure), independent of how the clock is built.
    fn onsets(seed: u64, seconds: f64) -> Vec<f64> {
        let mut out = Vec::new();
        let mut was = false;
        for i in 0..(seconds * 100.0) as i64 {
            let t = i as f64 / 100.0;
            let now = blink_amount(seed, t) > 0.0;
            if now && !was {
                out.push(t);
            }
            was = now;
        }
        out
    }

    #[test]
    fn blink_intervals_average_the_documented_mean() {
        let mut intervals = Vec::new();
        for seed in 0..200u64 {
            let o = onsets(head_seed(seed), 120.0);
            intervals.extend(o.windows(2).map(|w| w[1] - w[0]));
        }
        let mean = intervals.iter().sum::<f64>() / intervals.len() as f64;
        assert!(
            (mean - BLINK_PERIOD_S).abs() <= 0.1 * BLINK_PERIOD_S,
            "mean interval {mean} s over {} intervals",
            intervals.len()
        );
        let least = intervals.iter().copied().fold(f64::INFINITY, f64::min);
        let most = intervals.iter().copied().fold(0.0, f64::max);
        assert!(least >= BLINK_PERIOD_S - BLINK_JITTER_S - 0.02, "{least}");
        assert!(most <= BLINK_PERIOD_S + BLINK_JITTER_S + 0.02, "{most}");
        // Spread, not a metronome: a standard deviation near J/√6.
        let sd = (intervals.iter().map(|i| (i - mean).powi(2)).sum::<f64>()
            / intervals.len() as f64)
            .sqrt();
        let want = BLINK_JITTER_S / 6f64.sqrt();
        assert!((sd - want).abs() < 0.15 * want, "sd {sd}, want {want}");
    }

    #[test]
    fn a_blink_closes_fast_and_opens_slower() {
        let seed = head_seed(7);
        let (s, d) = blink_start(seed, 3);
        assert!((BLINK_MIN_S..=BLINK_MAX_S).contains(&d));
        assert_eq!(blink_amount(seed, s - 0.001), 0.0);
        let peak = blink_amount(seed, s + d / 3.0);
        assert!(peak > 0.99, "closed at a third: {peak}");
        // A quarter of the way: closing faster than opening at the same distance from peak.
        let closing = blink_amount(seed, s + d / 6.0);
        let opening = blink_amount(seed, s + d / 3.0 + d / 6.0);
        assert!(opening > closing, "{closing} {opening}");
        assert_eq!(blink_amount(seed, s + d + 0.001), 0.0);
    }

    #[test]
    fn seeds_decide_when_heads_blink() {
        let a = onsets(head_seed(1), 60.0);
        let b = onsets(head_seed(2), 60.0);
        assert_eq!(a, onsets(head_seed(1), 60.0), "equal seeds, equal blinks");
        assert_ne!(a, b, "different seeds blink at different times");
        // Bit-equal at every tick, whatever else was asked before.
        for i in 0..300 {
            let t = i as f64 / 30.0;
            assert_eq!(blink_amount(99, t).to_bits(), blink_amount(99, t).to_bits());
        }
        // At 30 ticks a second over a minute, 1,000 seeds: never all closed at once, and at
        // most a small fraction blinking at any tick (a blink is ~5 % of the time).
        let mut worst = 0;
        for i in 0..1800 {
            let t = i as f64 / 30.0;
            let n = (0..1000u64)
                .filter(|&h| blink_amount(head_seed(h), t) > 0.0)
                .count();
            worst = worst.max(n);
        }
        assert!(worst < 150, "{worst} of 1000 heads blinking at one tick");
    }

    #[test]
    fn saccades_hold_small_offsets() {
        let seed = head_seed(3);
        // Moves begin where the offset changes after a still sample.
        let (mut moves, mut still) = (0, true);
        let mut last = saccade_offset(seed, 0.0);
        for i in 1..3000 {
            let t = i as f64 / 100.0;
            let (y, p) = saccade_offset(seed, t);
            assert!(y.abs() <= SACCADE_YAW_DEG.to_radians() + 1e-6);
            assert!(p.abs() <= SACCADE_PITCH_DEG.to_radians() + 1e-6);
            let moved = (y, p) != last;
            if moved && still {
                moves += 1;
            }
            still = !moved;
            last = (y, p);
        }
        // 30 s of fixations of 0.2-2.0 s, averaging 1.1 s: about 27 moves.
        assert!((18..=40).contains(&moves), "{moves}");
    }

    #[test]
    fn look_angles_follow_the_placement() {
        let place = Placement {
            position: [0.0, 0.0, 0.0],
            yaw_deg: 0.0,
            scale: 1.0,
        };
        // Ahead, to the character's left (+X), above.
        let (y, p) = look_angles(Vec3::ZERO, &place, [0.0, 0.0, 5.0]);
        assert!(y.abs() < 1e-6 && p.abs() < 1e-6);
        let (y, _) = look_angles(Vec3::ZERO, &place, [5.0, 0.0, 5.0]);
        assert!((y - 45f32.to_radians()).abs() < 1e-5, "{y}");
        let (_, p) = look_angles(Vec3::ZERO, &place, [0.0, 5.0, 5.0]);
        assert!((p - 45f32.to_radians()).abs() < 1e-5, "{p}");
        // The same point, the head turned 90° toward +X: now straight ahead.
        let turned = Placement {
            yaw_deg: 90.0,
            ..place
        };
        let (y, _) = look_angles(Vec3::ZERO, &turned, [5.0, 0.0, 0.0]);
        assert!(y.abs() < 1e-5, "{y}");
    }

    #[test]
    fn eye_weights_by_angle() {
        // Channels 0..8: out-left, in-right, in-left, out-right, up-l, up-r, down-l, down-r.
        let names = [
            "eyeLookOutLeft",
            "eyeLookInRight",
            "eyeLookInLeft",
            "eyeLookOutRight",
            "eyeLookUpLeft",
            "eyeLookUpRight",
            "eyeLookDownLeft",
            "eyeLookDownRight",
            "eyeBlinkLeft",
        ];
        let rig = crate::embedded::default_rig();
        let ar = AliveRig::new(&rig, |n| {
            names
                .iter()
                .position(|x| *x == n)
                .map(|i| vec![i as u32])
                .unwrap_or_default()
        });
        let origin = ar.eye_origin();
        let place = Placement {
            position: [0.0, 0.0, 0.0],
            yaw_deg: 0.0,
            scale: 1.0,
        };
        // 15° to the character's left, level with the eyes.
        let d = 10.0;
        let target = origin + Vec3::new(d * 15f32.to_radians().tan(), 0.0, d);
        let p = AliveParams {
            look_at: Some(target.to_array()),
            ..AliveParams::default()
        };
        let mut w = vec![0.0; 9];
        ar.apply_weights(&p, &place, 0.0, &mut w);
        assert!(
            (w[0] - 0.5).abs() < 1e-4 && (w[1] - 0.5).abs() < 1e-4,
            "{w:?}"
        );
        assert!(w[2..8].iter().all(|&v| v.abs() < 1e-4), "{w:?}");
        // Far below: down saturates at 1.
        let p = AliveParams {
            look_at: Some((origin + Vec3::new(0.0, -50.0, 1.0)).to_array()),
            ..p
        };
        ar.apply_weights(&p, &place, 0.0, &mut w);
        assert_eq!((w[6], w[7]), (1.0, 1.0));
        assert!(w[4] == 0.0 && w[5] == 0.0);
    }

    #[test]
    fn a_look_at_turns_the_head_by_its_share_and_the_eyes_by_the_rest() {
        use super::super::{NO_PARENT, SkelNode};
        let node = |name: &str, parent: u32, t: [f32; 3], r: Quat| SkelNode {
            name: name.into(),
            parent,
            rest: Trs {
                translation: t,
                rotation: r.to_array(),
                scale: [1.0; 3],
            },
        };
        // A head whose local axes are turned at rest (its bones need not be rig-aligned).
        let odd = Quat::from_rotation_y(1.1) * Quat::from_rotation_x(0.3);
        let sk = Skeleton {
            nodes: vec![
                node("Root", NO_PARENT, [0.0; 3], Quat::IDENTITY),
                node("Head", 0, [0.0, 1.6, 0.0], odd),
                node("LeftEye", 1, [0.03, 0.05, 0.08], odd.inverse()),
                node("RightEye", 1, [-0.03, 0.05, 0.08], Quat::IDENTITY),
            ],
            bones: Vec::new(),
            map: None,
        };
        let mut rig = crate::embedded::default_rig();
        rig.skeleton = Some(std::sync::Arc::new(sk.clone()));
        let ar = AliveRig::new(&rig, |_| Vec::new());
        assert!(ar.has_eye_joints() && ar.has_joints());
        let globals = |locals: &[Trs]| -> Vec<Quat> {
            let mut g: Vec<Quat> = Vec::new();
            for (n, l) in sk.nodes.iter().zip(locals) {
                let q = Quat::from_array(l.rotation);
                let p = g.get(n.parent as usize).copied().unwrap_or(Quat::IDENTITY);
                g.push(p * q);
            }
            g
        };
        let rest = sk.rest();
        let place = Placement {
            position: [0.0; 3],
            yaw_deg: 0.0,
            scale: 1.0,
        };
        // 60° to the character's left: the head takes 24°, the eyes the rest, held at 30°.
        let yaw = 60f32.to_radians();
        let target = ar.eye_origin() + 10.0 * Vec3::new(yaw.sin(), 0.0, yaw.cos());
        let p = AliveParams {
            look_at: Some(target.to_array()),
            ..AliveParams::default()
        };
        let mut locals = rest.clone();
        ar.apply_locals(&sk, &p, &place, 0.0, &mut locals);
        let (g0, g1) = (globals(&rest), globals(&locals));
        let turned = |n: usize| {
            let d = g1[n] * g0[n].inverse();
            let (axis, angle) = d.to_axis_angle();
            // About +Y, by `angle` (a turn toward +X).
            assert!(angle < 1e-4 || axis.y > 0.999, "node {n}: axis {axis}");
            angle.to_degrees()
        };
        let head = turned(1);
        assert!((head - 24.0).abs() < 0.05, "head {head}");
        for eye in [2, 3] {
            let e = turned(eye);
            assert!((e - 54.0).abs() < 0.05, "eye {eye}: {e}");
        }
        assert_eq!(locals[0], rest[0], "the root stays");
        // Saccades alone move the eyes only, within their offsets.
        let p = AliveParams {
            saccades: true,
            seed: 5,
            ..AliveParams::default()
        };
        let mut locals = rest.clone();
        ar.apply_locals(&sk, &p, &place, 3.0, &mut locals);
        assert_eq!(locals[1], rest[1], "saccades leave the head");
        let g1 = globals(&locals);
        let e = (g1[2] * g0[2].inverse())
            .angle_between(Quat::IDENTITY)
            .to_degrees();
        let most = SACCADE_YAW_DEG.hypot(SACCADE_PITCH_DEG);
        assert!(e > 0.0 && e <= most + 0.01, "{e}");
    }
}
