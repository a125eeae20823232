//! Synthetic rigs for benchmarks and tests.
//!
//! [`paper_scale_rig`] has the size of the rig in Costigan et al. 2016 (72 blendshapes, 43,788
//! vertices) with localized deltas: each target moves a contiguous band of at most 1/20 of the
//! vertices, as facial blendshapes move a region of the face. It is deterministic.

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
    let n = PAPER_VERTICES;
    let side = 209;
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
    let targets = (0..PAPER_TARGETS as u32)
        .map(|t| {
            let center = rng.below(n);
            let radius = 200 + rng.below(n / 20 - 200);
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
    }];
    let frames = 60;
    let weights: Vec<f32> = (0..PAPER_TARGETS * frames)
        .map(|_| if rng.below(4) == 0 { 0.0 } else { rng.unit() })
        .collect();
    let lod = Lod::by_delta_energy(&primitives, PAPER_TARGETS);
    Rig {
        name: "paper-scale".into(),
        targets: (0..PAPER_TARGETS).map(|t| format!("shape{t}")).collect(),
        default_weights: vec![0.0; PAPER_TARGETS],
        primitives: std::sync::Arc::new(primitives),
        clips: vec![Clip {
            name: "anim".into(),
            fps: 30.0,
            frames: frames as u32,
            targets: PAPER_TARGETS as u32,
            weights: std::sync::Arc::new(weights),
            joints: None,
        }],
        lod,
        skeleton: None,
        import_notes: Vec::new(),
    }
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

#[cfg(test)]
mod tests {
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
