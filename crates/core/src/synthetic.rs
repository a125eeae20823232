//! Synthetic rigs for benchmarks and tests.
//!
//! [`paper_scale_rig`] has the size of the rig in Costigan et al. 2016 (72 blendshapes, 43,788
//! vertices) with localized deltas: each target moves a contiguous band of at most 1/20 of the
//! vertices, as facial blendshapes move a region of the face. It is deterministic.
//!
//! [`skinned_head`] is the embedded head with five joints beside its 51 blendshapes (neck,
//! head, jaw, one per eye), the shape of a Ready Player Me or MetaHuman face: what skinning
//! costs on a face, and a face whose eyes and jaw tests can turn.
//!
//! [`face_capture`] is a face tracker's recording (52 ARKit channels at 60 fps from a few
//! latent facial actions, with tracker noise, jitter and dropouts) of any length, for the clip
//! codecs: how it is made is documented there.

use crate::rng::SplitMix64;
use glam::Vec3;

use crate::rig::{Clip, Lod, Primitive, Rig, sparsify, vertex_normals};

/// Vertices of the paper's head model.
pub const PAPER_VERTICES: usize = 43_788;
/// Blendshapes of the paper's head model.
pub const PAPER_TARGETS: usize = 72;

/// A 72-target, 43,788-vertex rig with localized deltas and one 60-frame clip ("anim") whose
/// weights are active about three times in four.
pub fn paper_scale_rig() -> Rig {
    banded_rig("paper-scale", PAPER_VERTICES, 209, PAPER_TARGETS)
}

/// A rig of `n` vertices on a sphere (rows of `side`) and `n_targets` targets, each moving a
/// contiguous band of at most 1/20 of the vertices, with one 60-frame clip ("anim") whose
/// weights are active about three times in four. Many targets on few vertices give long
/// active lists of which each tile of vertices sees only a part. Deterministic.
pub fn banded_rig(name: &str, n: usize, side: usize, n_targets: usize) -> Rig {
    let positions: Vec<Vec3> = (0..n)
        .map(|i| {
            let (u, v) = (
                (i % side) as f32 / side as f32,
                (i / side) as f32 / side as f32,
            );
            let (a, b) = (u * std::f32::consts::TAU, v * std::f32::consts::PI);
            Vec3::new(a.cos() * b.sin(), b.cos(), a.sin() * b.sin()) * 10.0
        })
        .collect();
    let mut indices = Vec::new();
    let s = side as u32;
    for r in 0..(n / side - 1) as u32 {
        for c in 0..s - 1 {
            let i = r * s + c;
            indices.extend_from_slice(&[i, i + s, i + 1, i + 1, i + s, i + s + 1]);
        }
    }
    let normals = vertex_normals(&positions, &indices);
    let mut rng = SplitMix64(72);
    let targets = (0..n_targets as u32)
        .map(|t| {
            let center = rng.below(n);
            let shortest = 200.min(n / 40);
            let radius = shortest + rng.below(n / 20 - shortest);
            let dir = Vec3::new(rng.unit() - 0.5, rng.unit() - 0.5, rng.unit() - 0.5);
            let dp: Vec<Vec3> = (0..n)
                .map(|v| {
                    let d = (v as i64 - center as i64).unsigned_abs() as usize;
                    if d < radius {
                        dir * (1.0 - d as f32 / radius as f32)
                    } else {
                        Vec3::ZERO
                    }
                })
                .collect();
            sparsify(t, &dp, None, None, 1e-6)
        })
        .collect();
    let primitives = vec![Primitive {
        name: "paper".into(),
        positions,
        normals,
        normals_from_file: false,
        tangents: None,
        indices,
        targets,
        base_color: Primitive::default_base_color(),
        skin: None,
        look: Default::default(),
    }];
    let frames = 60;
    let weights: Vec<f32> = (0..n_targets * frames)
        .map(|_| if rng.below(4) == 0 { 0.0 } else { rng.unit() })
        .collect();
    let lod = Lod::by_delta_energy(&primitives, n_targets);
    Rig {
        name: name.into(),
        targets: (0..n_targets).map(|t| format!("shape{t}")).collect(),
        default_weights: vec![0.0; n_targets],
        primitives: std::sync::Arc::new(primitives),
        clips: vec![Clip {
            name: "anim".into(),
            fps: 30.0,
            frames: frames as u32,
            targets: n_targets as u32,
            weights: std::sync::Arc::new(weights),
            joints: None,
        }],
        lod,
        skeleton: None,
        import_notes: Vec::new(),
        appearance: None,
    }
}

/// Joint names of [`skinned_head`], parents first.
pub const HEAD_JOINTS: [&str; 5] = ["Neck", "Head", "Jaw", "LeftEye", "RightEye"];

/// The embedded head with a five-joint skeleton: `Neck` at the base of the mesh, `Head` above
/// it, `Jaw` (pivot below the ears) and `LeftEye`/`RightEye` at the eyeballs' centres, the last
/// three children of `Head`. The eyeballs follow their eye joints rigidly; the face follows
/// `Jaw` below the mouth at the front and `Neck` at the bottom, with smooth weights, and
/// `Head` elsewhere (up to three influences a vertex). Every clip gains a joint table: the
/// head turns and nods gently, the eyes look left and right and up, and the jaw opens in
/// `talk`. Deterministic.
pub fn skinned_head() -> Rig {
    use crate::rig::{Bone, Influences, JointTable, NO_PARENT, SkelNode, Skeleton, Trs};
    use glam::{Mat4, Quat};
    let mut rig = crate::embedded::default_rig();
    let eye = |name: &str| -> Vec3 {
        let p = rig.primitives.iter().find(|p| p.name == name);
        p.map_or(Vec3::ZERO, |p| {
            p.positions.iter().copied().sum::<Vec3>() / p.positions.len().max(1) as f32
        })
    };
    let (eye_l, eye_r) = (eye("eye_L"), eye("eye_R"));
    let bbox = rig.bbox();
    let (lo, hi) = (bbox.min, bbox.max);
    let height = hi.y - lo.y;
    let z_mid = 0.5 * (lo.z + hi.z);
    // Global rest positions of the joints (the head looks along +Z, +Y up).
    let at = [
        Vec3::new(0.0, lo.y, z_mid - 0.1 * height),
        Vec3::new(0.0, lo.y + 0.2 * height, z_mid - 0.05 * height),
        Vec3::new(0.0, eye_l.y - 0.18 * height, z_mid),
        eye_l,
        eye_r,
    ];
    let parent = [NO_PARENT, 0, 1, 1, 1];
    let nodes: Vec<SkelNode> = (0..5)
        .map(|i| {
            let p = parent[i];
            let local = if p == NO_PARENT {
                at[i]
            } else {
                at[i] - at[p as usize]
            };
            SkelNode {
                name: HEAD_JOINTS[i].into(),
                parent: p,
                rest: Trs {
                    translation: local.to_array(),
                    ..Trs::default()
                },
            }
        })
        .collect();
    let bones: Vec<Bone> = (0..5)
        .map(|i| Bone {
            node: i as u32,
            bind: Mat4::from_translation(-at[i]).to_cols_array(),
        })
        .collect();
    let smooth = |t: f32| {
        let t = t.clamp(0.0, 1.0);
        t * t * (3.0 - 2.0 * t)
    };
    let mouth_y = at[2].y - 0.05 * height;
    let mut prims = rig.primitives.as_ref().clone();
    for p in &mut prims {
        let n = p.positions.len();
        let mut inf = Influences {
            joints: Vec::with_capacity(n),
            weights: Vec::with_capacity(n),
        };
        for v in &p.positions {
            let (j, w) = match p.name.as_str() {
                "eye_L" => ([3, 0, 0, 0], [1.0, 0.0, 0.0, 0.0]),
                "eye_R" => ([4, 0, 0, 0], [1.0, 0.0, 0.0, 0.0]),
                _ => {
                    let jaw = smooth((mouth_y - v.y) / (0.1 * height))
                        * smooth((v.z - z_mid) / (0.15 * height));
                    let neck = smooth((lo.y + 0.3 * height - v.y) / (0.2 * height));
                    let (jaw, neck) = if jaw + neck > 1.0 {
                        (jaw / (jaw + neck), neck / (jaw + neck))
                    } else {
                        (jaw, neck)
                    };
                    // Largest first; zero weights are unused entries.
                    let mut pairs = [(1u16, (1.0 - jaw - neck).max(0.0)), (2, jaw), (0, neck)];
                    pairs.sort_by(|a, b| b.1.total_cmp(&a.1));
                    (
                        [pairs[0].0, pairs[1].0, pairs[2].0, 0],
                        [pairs[0].1, pairs[1].1, pairs[2].1, 0.0],
                    )
                }
            };
            inf.joints.push(j);
            inf.weights.push(w);
        }
        p.skin = Some(inf);
    }
    rig.primitives = std::sync::Arc::new(prims);
    let skeleton = Skeleton {
        nodes,
        bones,
        map: None,
    };
    for (ci, clip) in rig.clips.iter_mut().enumerate() {
        let frames = clip.frames as usize;
        let mut values = Vec::with_capacity(frames * 5 * Trs::FLOATS);
        for f in 0..frames {
            let t = f as f32 / clip.fps;
            let phase = ci as f32 * 0.7;
            let jaw_open = if clip.name == "talk" {
                0.22 * (0.5 - 0.5 * (t * 9.0).cos())
            } else {
                0.03 * (1.0 + (t * 1.3 + phase).sin())
            };
            let rot = [
                Quat::from_rotation_x(0.04 * (t * 0.9 + phase).sin()),
                Quat::from_rotation_y(0.25 * (t * 1.1 + phase).sin())
                    * Quat::from_rotation_x(0.1 * (t * 1.7).sin()),
                Quat::from_rotation_x(jaw_open),
                Quat::from_rotation_y(0.3 * (t * 2.3 + phase).sin())
                    * Quat::from_rotation_x(0.15 * (t * 1.9).cos()),
                Quat::from_rotation_y(0.3 * (t * 2.3 + phase).sin())
                    * Quat::from_rotation_x(0.15 * (t * 1.9).cos()),
            ];
            for (node, q) in skeleton.nodes.iter().zip(rot) {
                let trs = Trs {
                    rotation: q.to_array(),
                    ..node.rest
                };
                values.extend_from_slice(&trs.floats());
            }
        }
        clip.joints = Some(std::sync::Arc::new(JointTable {
            nodes: (0..5).collect(),
            frames: frames as u32,
            values,
        }));
    }
    rig.skeleton = Some(std::sync::Arc::new(skeleton));
    rig.name = "skinned-head".into();
    rig
}

/// Gives a rig without clips a deterministic random one named "random" (24 frames, weights
/// active about two times in three), so benchmarks and GPU jobs have tables to read.
pub fn with_random_clip(rig: Rig, seed: u64) -> Rig {
    if rig.clips.is_empty() {
        with_random_clip_of(rig, "random", 24, seed)
    } else {
        rig
    }
}

/// Appends a deterministic random clip `name` of `frames` frames (weights active about two
/// times in three).
pub fn with_random_clip_of(mut rig: Rig, name: &str, frames: usize, seed: u64) -> Rig {
    {
        let mut rng = SplitMix64(seed);
        let t = rig.targets.len();
        let weights: Vec<f32> = (0..t * frames)
            .map(|_| if rng.below(3) == 0 { 0.0 } else { rng.unit() })
            .collect();
        rig.clips.push(Clip {
            name: name.into(),
            fps: 30.0,
            frames: frames as u32,
            targets: t as u32,
            weights: std::sync::Arc::new(weights),
            joints: None,
        });
    }
    rig
}

/// The 52 ARKit blendshape names, in Live Link Face's column order.
pub const ARKIT_NAMES: [&str; 52] = [
    "EyeBlinkLeft",
    "EyeLookDownLeft",
    "EyeLookInLeft",
    "EyeLookOutLeft",
    "EyeLookUpLeft",
    "EyeSquintLeft",
    "EyeWideLeft",
    "EyeBlinkRight",
    "EyeLookDownRight",
    "EyeLookInRight",
    "EyeLookOutRight",
    "EyeLookUpRight",
    "EyeSquintRight",
    "EyeWideRight",
    "JawForward",
    "JawRight",
    "JawLeft",
    "JawOpen",
    "MouthClose",
    "MouthFunnel",
    "MouthPucker",
    "MouthRight",
    "MouthLeft",
    "MouthSmileLeft",
    "MouthSmileRight",
    "MouthFrownLeft",
    "MouthFrownRight",
    "MouthDimpleLeft",
    "MouthDimpleRight",
    "MouthStretchLeft",
    "MouthStretchRight",
    "MouthRollLower",
    "MouthRollUpper",
    "MouthShrugLower",
    "MouthShrugUpper",
    "MouthPressLeft",
    "MouthPressRight",
    "MouthLowerDownLeft",
    "MouthLowerDownRight",
    "MouthUpperUpLeft",
    "MouthUpperUpRight",
    "BrowDownLeft",
    "BrowDownRight",
    "BrowInnerUp",
    "BrowOuterUpLeft",
    "BrowOuterUpRight",
    "CheekPuff",
    "CheekSquintLeft",
    "CheekSquintRight",
    "NoseSneerLeft",
    "NoseSneerRight",
    "TongueOut",
];

/// A synthetic face-tracker capture: [`ARKIT_NAMES`] × `frames` weights at 60 fps
/// (channel-major, as [`Clip::weights`]), deterministic for a seed.
///
/// How it is made, and why it looks like a Live Link Face recording (the real one kept in
/// `tests/data/live-link-face` has the same traits): eight latent processes drive the 52
/// channels through fixed loadings, as a tracker's coefficients are a few facial actions seen
/// through 52 overlapping shapes —
/// - **speech**: phrases of 1.5–4 s separated by 0.5–1.5 s pauses; in a phrase, syllables at
///   4–6 Hz, each a viseme (jaw opening, lip rounding, lip spreading, lip closure for m/b/p)
///   reached through a critically damped second-order filter of 35 ms (jaw, lips, cheeks);
/// - **blinks** every 2–6 s: a fast asymmetric pulse (closing in 80 ms, reopening in 200 ms),
///   both eyes with a slight left/right difference, and a dip of the gaze;
/// - **gaze**: saccades every 0.4–2 s to a new yaw and pitch, each reached in about 40 ms,
///   split into the look-in/out/up/down channels of both eyes (conjugate);
/// - **brows** and **smile** (with cheek and eye squint): Ornstein–Uhlenbeck processes of 1.5 s
///   and 3 s; **jaw sideways** and **mouth press**: slower ones of small amplitude;
/// - each channel adds its resting offset (0–0.08, as ARKit reports for a neutral face),
///   white tracker noise with σ between 0.01 and 0.02 (per channel), and single-frame jitter
///   spikes (one frame in 200, ±0.05 on a group of channels); one frame in 500 starts a
///   tracking dropout of 2–8 frames where every channel holds its last value (a lost frame
///   repeated); then each weight is clamped to [0, 1].
pub fn face_capture(frames: usize, seed: u64) -> Vec<f32> {
    const FPS: f64 = 60.0;
    let mut rng = SplitMix64(seed);
    let n = frames;
    // Latents, each n frames: 0 jaw, 1 round, 2 spread, 3 closure, 4 blink, 5 yaw, 6 pitch,
    // 7 brows, 8 smile, 9 jaw side, 10 press.
    let mut lat = vec![vec![0f64; n]; 11];
    // Speech: viseme targets per syllable, filtered.
    let mut targets = vec![[0f64; 4]; n];
    let mut f = 0usize;
    while f < n {
        let phrase = ((1.5 + 2.5 * rng.f64()) * FPS) as usize;
        let end = (f + phrase).min(n);
        while f < end {
            let syll = (FPS / (4.0 + 2.0 * rng.f64())) as usize;
            let v = match rng.below(4) {
                0 => [0.25 + 0.4 * rng.f64(), 0.0, 0.3 * rng.f64(), 0.0],
                1 => [0.15 + 0.2 * rng.f64(), 0.5 + 0.4 * rng.f64(), 0.0, 0.0],
                2 => [0.1 + 0.2 * rng.f64(), 0.0, 0.4 + 0.4 * rng.f64(), 0.0],
                _ => [0.0, 0.0, 0.1 * rng.f64(), 0.6 + 0.4 * rng.f64()],
            };
            for t in targets.iter_mut().take(end.min(f + syll)).skip(f) {
                *t = v;
            }
            f += syll;
        }
        f += ((0.5 + rng.f64()) * FPS) as usize;
    }
    // Critically damped second order, time constant 35 ms, per viseme dimension.
    let w0 = 1.0 / (0.035 * FPS);
    for d in 0..4 {
        let (mut x, mut v) = (0f64, 0f64);
        for t in 0..n {
            let a = w0 * w0 * (targets[t][d] - x) - 2.0 * w0 * v;
            v += a;
            x += v;
            lat[d][t] = x;
        }
    }
    // Blinks.
    let mut t = (FPS * (1.0 + 2.0 * rng.f64())) as usize;
    while t < n {
        let (close, open) = (0.08 * FPS, 0.2 * FPS);
        let amp = 0.85 + 0.15 * rng.f64();
        for i in 0..(close + open) as usize {
            if t + i >= n {
                break;
            }
            let x = i as f64;
            lat[4][t + i] = amp
                * if x < close {
                    (x / close).powi(2)
                } else {
                    1.0 - ((x - close) / open).sqrt()
                };
        }
        t += (FPS * (2.0 + 4.0 * rng.f64())) as usize;
    }
    // Gaze saccades.
    let (mut yaw, mut pitch) = (0f64, 0f64);
    let (mut ty, mut tp) = (0f64, 0f64);
    let mut next = 0usize;
    let (mut yaws, mut pitches) = (vec![0f64; n], vec![0f64; n]);
    let gaze = yaws.iter_mut().zip(pitches.iter_mut()).zip(&lat[4]);
    for (t, ((y, p), blink)) in gaze.enumerate() {
        if t == next {
            ty = rng.f64() * 1.4 - 0.7;
            tp = rng.f64() * 0.9 - 0.45;
            next = t + (FPS * (0.4 + 1.6 * rng.f64())) as usize;
        }
        yaw += (ty - yaw) * 0.35;
        pitch += (tp - pitch) * 0.35;
        *y = yaw;
        *p = pitch - 0.3 * blink;
    }
    lat[5] = yaws;
    lat[6] = pitches;
    // Ornstein–Uhlenbeck processes: (latent, time constant s, stationary σ, mean).
    for (l, tau, sigma, mean) in [
        (7usize, 1.5, 0.25, 0.0),
        (8, 3.0, 0.25, 0.15),
        (9, 4.0, 0.08, 0.0),
        (10, 2.0, 0.1, 0.05),
    ] {
        let a = (-1.0 / (tau * FPS)).exp();
        let s = sigma * (1.0 - a * a).sqrt();
        let mut x = mean;
        for y in lat[l].iter_mut() {
            let g = (rng.f64() + rng.f64() + rng.f64() - 1.5) * 2.0; // ≈ N(0, 1)
            x = mean + a * (x - mean) + s * g;
            *y = x;
        }
    }
    let pos = |x: f64| x.max(0.0);
    let mut out = vec![0f32; ARKIT_NAMES.len() * n];
    let rest: Vec<f64> = (0..ARKIT_NAMES.len()).map(|_| 0.08 * rng.f64()).collect();
    let sigma: Vec<f64> = (0..ARKIT_NAMES.len())
        .map(|_| 0.01 + 0.01 * rng.f64())
        .collect();
    let asym = 0.9 + 0.2 * rng.f64();
    let mut held = 0usize;
    for t in 0..n {
        let l = |i: usize| lat[i][t];
        let (jaw, round, spread, close, blink) = (l(0), l(1), l(2), l(3), l(4));
        let (yaw, pitch, brow, smile, side, press) = (l(5), l(6), l(7), l(8), l(9), l(10));
        let values: [f64; 52] = [
            blink,                                         // EyeBlinkLeft
            pos(-pitch),                                   // EyeLookDownLeft
            pos(yaw),                                      // EyeLookInLeft
            pos(-yaw),                                     // EyeLookOutLeft
            pos(pitch),                                    // EyeLookUpLeft
            0.5 * pos(smile) + 0.2 * blink,                // EyeSquintLeft
            pos(brow) * 0.4,                               // EyeWideLeft
            blink * asym,                                  // EyeBlinkRight
            pos(-pitch),                                   // EyeLookDownRight
            pos(-yaw),                                     // EyeLookInRight
            pos(yaw),                                      // EyeLookOutRight
            pos(pitch),                                    // EyeLookUpRight
            0.5 * pos(smile) * asym + 0.2 * blink,         // EyeSquintRight
            pos(brow) * 0.4 * asym,                        // EyeWideRight
            0.1 * round,                                   // JawForward
            pos(side),                                     // JawRight
            pos(-side),                                    // JawLeft
            jaw + 0.3 * round,                             // JawOpen
            0.5 * close + 0.1 * jaw * round,               // MouthClose
            0.6 * round,                                   // MouthFunnel
            0.8 * round,                                   // MouthPucker
            pos(side) * 0.5,                               // MouthRight
            pos(-side) * 0.5,                              // MouthLeft
            pos(smile) + 0.3 * spread,                     // MouthSmileLeft
            (pos(smile) + 0.3 * spread) * asym,            // MouthSmileRight
            pos(-smile) * 0.5,                             // MouthFrownLeft
            pos(-smile) * 0.5 * asym,                      // MouthFrownRight
            0.3 * spread + 0.2 * pos(smile),               // MouthDimpleLeft
            0.3 * spread * asym + 0.2 * pos(smile),        // MouthDimpleRight
            0.5 * spread,                                  // MouthStretchLeft
            0.5 * spread * asym,                           // MouthStretchRight
            0.4 * close,                                   // MouthRollLower
            0.3 * close,                                   // MouthRollUpper
            0.3 * close + pos(-smile) * 0.3,               // MouthShrugLower
            0.2 * close,                                   // MouthShrugUpper
            pos(press) + 0.3 * close,                      // MouthPressLeft
            (pos(press) + 0.3 * close) * asym,             // MouthPressRight
            0.5 * jaw + 0.2 * spread,                      // MouthLowerDownLeft
            (0.5 * jaw + 0.2 * spread) * asym,             // MouthLowerDownRight
            0.3 * spread + 0.2 * pos(smile),               // MouthUpperUpLeft
            (0.3 * spread + 0.2 * pos(smile)) * asym,      // MouthUpperUpRight
            pos(-brow),                                    // BrowDownLeft
            pos(-brow) * asym,                             // BrowDownRight
            pos(brow),                                     // BrowInnerUp
            pos(brow) * 0.8,                               // BrowOuterUpLeft
            pos(brow) * 0.8 * asym,                        // BrowOuterUpRight
            0.0,                                           // CheekPuff
            0.6 * pos(smile),                              // CheekSquintLeft
            0.6 * pos(smile) * asym,                       // CheekSquintRight
            0.2 * pos(-smile) + 0.1 * pos(smile),          // NoseSneerLeft
            (0.2 * pos(-smile) + 0.1 * pos(smile)) * asym, // NoseSneerRight
            0.0,                                           // TongueOut
        ];
        // Dropouts hold the last frame; spikes jolt a group of channels for one frame.
        if held == 0 && rng.below(500) == 0 {
            held = 2 + rng.below(7);
        }
        let spike = rng.below(200) == 0;
        let group = rng.below(4);
        for (k, v) in values.iter().enumerate() {
            if held > 0 && t > 0 {
                out[k * n + t] = out[k * n + t - 1];
                continue;
            }
            let g = (rng.f64() + rng.f64() + rng.f64() - 1.5) * 2.0;
            let mut x = rest[k] + v + sigma[k] * g;
            if spike && k % 4 == group {
                x += 0.05 * (2.0 * rng.f64() - 1.0);
            }
            out[k * n + t] = x.clamp(0.0, 1.0) as f32;
        }
        held = held.saturating_sub(1);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::{ARKIT_NAMES, face_capture};

    #[test]
    fn the_synthetic_capture_is_deterministic_noisy_and_correlated() {
        let n = 1200;
        let a = face_capture(n, 7);
        assert_eq!(a, face_capture(n, 7));
        assert_ne!(a, face_capture(n, 8));
        assert_eq!(a.len(), ARKIT_NAMES.len() * n);
        assert!(a.iter().all(|w| (0.0..=1.0).contains(w)));
        let ch = |name: &str| {
            let k = ARKIT_NAMES.iter().position(|x| *x == name).expect("name");
            &a[k * n..(k + 1) * n]
        };
        // Tracker noise: frame-to-frame steps of about σ√2 even where nothing moves.
        let brow = ch("BrowInnerUp");
        let rough = brow.windows(2).map(|w| (w[1] - w[0]).abs()).sum::<f32>() / n as f32;
        assert!(rough > 0.005, "mean step {rough}");
        // Left and right blink together: correlation well above chance.
        let (l, r) = (ch("EyeBlinkLeft"), ch("EyeBlinkRight"));
        let mean = |x: &[f32]| x.iter().sum::<f32>() / x.len() as f32;
        let (ml, mr) = (mean(l), mean(r));
        let cov: f32 = l.iter().zip(r).map(|(a, b)| (a - ml) * (b - mr)).sum();
        let var = |x: &[f32], m: f32| x.iter().map(|a| (a - m) * (a - m)).sum::<f32>();
        let corr = cov / (var(l, ml) * var(r, mr)).sqrt();
        assert!(corr > 0.8, "blink correlation {corr}");
    }

    #[test]
    fn the_skinned_head_is_valid_and_its_joints_move_eyes_and_jaw() {
        let rig = super::skinned_head();
        rig.validate().expect("valid");
        let (skinned, rigid) = rig.skinned_and_rigid_vertices();
        assert_eq!(
            rigid, 444,
            "two eyeballs of 222 vertices each follow one bone"
        );
        assert_eq!(skinned, 6818);
        // Some face vertices follow the jaw and some the neck.
        let face = rig.primitives[0].skin.as_ref().expect("skin");
        let follows = |bone: u16| {
            face.joints
                .iter()
                .zip(&face.weights)
                .filter(|(j, w)| j.iter().zip(w.iter()).any(|(&j, &w)| j == bone && w > 0.5))
                .count()
        };
        assert!(follows(2) > 100, "jaw: {}", follows(2));
        assert!(follows(0) > 100, "neck: {}", follows(0));
        assert!(follows(1) > 3000, "head: {}", follows(1));
    }

    #[test]
    fn paper_scale_rig_is_valid_localized_and_deterministic() {
        let a = super::paper_scale_rig();
        a.validate().expect("valid");
        assert_eq!(a.vertex_count(), super::PAPER_VERTICES);
        assert_eq!(a.targets.len(), super::PAPER_TARGETS);
        assert!(
            a.target_nnz()
                .iter()
                .all(|&n| n > 0 && n <= super::PAPER_VERTICES / 10)
        );
        assert_eq!(a, super::paper_scale_rig());
    }
}
