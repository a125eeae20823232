//! crowdmorph-anim: animation over crowdmorph-core's rigs.
//!
//! | module | what it is |
//! |---|---|
//! | [`compress`] | compressed clips within a vertex-space error budget: per-curve quantization or PCA, temporal prediction, zstd segments |
//! | [`transform`] | clip codec 2 for face captures: channels decorrelated in vertex space, one quantization step found by measuring the decoded clip, per-segment predictors |
//! | [`live`] | live input over time: the jitter buffer that plays producer samples by timecode, the One Euro filter, fades in and out |
//! | [`graph`] | motion graphs checked against a rig, and the player that walks one with bounded cross-fades |
//! | `varint` | zigzag LEB128 varints, the residual streams of both clip codecs |
//! | [`texture`] | animated textures compressed with PCA per region (GPU Gems 3 ch. 15), and their error per region |

pub mod compress;
pub mod graph;
pub mod live;
pub mod texture;
pub mod transform;
mod varint;
