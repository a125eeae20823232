//! crowdmorph: a network animation server for blendshape (morph-target) crowds.
//!
//! Layout: outside tests, each module depends only on the ones above it in this table (no
//! cycles). `ARCHITECTURE.md` maps the tree and its invariants; `docs/design/` has the longer why.
//!
//! | module | what it is |
//! |---|---|
//! | [`rng`] | SplitMix64: deterministic numbers for synthetic rigs, clips and workloads |
//! | [`linalg`] | the symmetric eigendecomposition the PCA codecs share (cyclic Jacobi) |
//! | [`budget`] | memory budgets: every allocation an input sizes is charged before it happens |
//! | [`cancel`] | a request's cancellation token: work off the runtime stops at its next stage when the request is gone or late |
//! | [`rig`] | pure data: primitives, sparse targets, clips (weight tables), LOD order and mesh levels, the variable-PCA form of the deltas; keyframe sampling; the memory cost model |
//! | [`import`] | glTF/GLB, CSV and JSON readers that build a validated [`rig::Rig`] |
//! | [`embedded`] | the procedural default rig that needs no files |
//! | [`synthetic`] | synthetic rigs and clips: the paper-scale rig, deterministic random clips |
//! | [`plan`] | the batch planner: a crowd of heads → unique jobs + per-head index |
//! | [`compress`] | compressed clips within a vertex-space error budget: per-curve quantization or PCA, temporal prediction, zstd segments |
//! | [`graph`] | motion graphs checked against a rig, and the player that walks one with bounded cross-fades |
//! | [`engine`] | blend engines; [`engine::cpu`] is the oracle and the no-GPU production engine |
//! | [`export`] | one blended frame written as OBJ or raw f32 (`crowdmorph eval`) |
//! | [`render`] | rendered frames: scene layout, cost, the wgpu renderer, encoding, offline renders |
//! | [`lod`] | level of detail: importance metrics and orders, reports, feature-preserving mesh levels, PCA levels of the deltas, the reference rasterizer |
//! | [`codec`] | the one module that touches bincode: wire messages and stored records |
//! | [`store`] | persistence: checksummed, atomically replaced files under the data dir, one per rig and one per later batch of its clips; `store::objects`, the shared store of several replicas (a directory or S3, generations by manifest) |
//! | [`load`] | the load generator: open loop, latency corrected for coordinated omission, HdrHistogram reports |
//! | [`server`] | the HTTP server: routes, the HTTP layer, admission, the batcher, sessions, metrics |
//! | [`bench`] | benchmarks, their peers and harness (feature `bench`) |
//!
//! The binary (`src/main.rs`, one module per subcommand in `src/cli/`) parses the command line,
//! sets up tracing, calls into the library and prints each command's report.

pub mod budget;
pub mod cancel;
pub mod codec;
pub mod compress;
pub mod embedded;
pub mod engine;
pub mod export;
pub mod graph;
pub mod import;
pub mod linalg;
pub mod load;
pub mod lod;
pub mod plan;
pub mod render;
pub mod rig;
pub mod rng;
pub mod server;
pub mod store;
pub mod synthetic;

#[cfg(feature = "bench")]
pub mod bench;
