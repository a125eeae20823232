//! crowdmorph-core: the data layer every other crate of crowdmorph builds on.
//!
//! Pure data and the small utilities that size and stop work: no tokio, axum, wgpu or
//! object_store, so `cargo test -p crowdmorph-core` builds a dozen crates. Each module depends
//! only on the ones above it in this table.
//!
//! | module | what it is |
//! |---|---|
//! | [`rng`] | SplitMix64: deterministic numbers for synthetic rigs, clips and workloads |
//! | [`linalg`] | the symmetric eigendecomposition the PCA codecs share (cyclic Jacobi) |
//! | [`budget`] | memory budgets: every allocation an input sizes is charged before it happens |
//! | [`cancel`] | a request's cancellation token: work off the runtime stops at its next stage when the request is gone or late |
//! | [`rig`] | pure data: primitives, sparse targets, clips (weight tables), LOD order and mesh levels, the variable-PCA form of the deltas; keyframe sampling; the memory cost model |
//! | [`embedded`] | the procedural default rig that needs no files |
//! | [`synthetic`] | synthetic rigs and clips: the paper-scale rig, deterministic random clips |
//! | [`plan`] | the batch planner: a crowd of heads → unique jobs + per-head index |

pub mod budget;
pub mod cancel;
pub mod embedded;
pub mod linalg;
pub mod plan;
pub mod rig;
pub mod rng;
pub mod synthetic;
