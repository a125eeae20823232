//! crowdmorph-anim: animation over crowdmorph-core's rigs.
//!
//! | module | what it is |
//! |---|---|
//! | [`compress`] | compressed clips within a vertex-space error budget: per-curve quantization or PCA, temporal prediction, zstd segments |
//! | [`graph`] | motion graphs checked against a rig, and the player that walks one with bounded cross-fades |

pub mod compress;
pub mod graph;
