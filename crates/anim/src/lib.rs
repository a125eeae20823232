//! crowdmorph-anim: animation over crowdmorph-core's rigs.
//!
//! | module | what it is |
//! |---|---|
//! | [`compress`] | compressed clips within a vertex-space error budget: per-curve quantization or PCA, temporal prediction, zstd segments |
//! | [`graph`] | motion graphs checked against a rig, and the player that walks one with bounded cross-fades |
//! | [`texture`] | animated textures compressed with PCA per region (GPU Gems 3 ch. 15), and their error per region |

pub mod compress;
pub mod graph;
pub mod texture;
