//! crowdmorph: a network animation server for blendshape (morph-target) crowds.
//!
//! Layout (each layer depends only on the ones above it):
//!
//! | module | what it is |
//! |---|---|
//! | [`rng`] | SplitMix64: deterministic numbers for synthetic rigs, clips and workloads |
//! | [`budget`] | memory budgets: every allocation an input sizes is charged before it happens |
//! | [`cancel`] | a request's cancellation token: work off the runtime stops at its next stage when the request is gone or late |
//! | [`rig`] | pure data: primitives, sparse targets, clips (weight tables), LOD order; keyframe sampling math |
//! | [`import`] | glTF/GLB, CSV and JSON readers that build a validated [`rig::Rig`] |
//! | [`embedded`] | the procedural default rig that needs no files |
//! | [`plan`] | the batch planner: a crowd of heads → unique jobs + per-head index |
//! | [`engine`] | blend engines; [`engine::cpu`] is the oracle and the no-GPU production engine |
//! | [`render`] | a deterministic CPU software rasterizer (front view, z-buffer, Lambert) for image metrics |
//! | [`lod`] | level of detail: importance metrics and orders, LOD tables and reports, feature-preserving mesh levels |
//! | [`codec`] | the one module that touches bincode: wire messages and stored records |
//! | [`store`] | persistence: one checksummed, atomically replaced file per rig under the data dir |
//! | [`load`] | the load generator: open loop, latency corrected for coordinated omission, HdrHistogram reports |
//! | [`server`] | the HTTP API (axum), the dynamic batcher with cross-request dedupe, metrics, `POST /v1/loadtest` |
//! | [`tools`] | the CLI's commands (`inspect`, `eval`, `bench`) as library functions |
//!
//! The binary (`src/main.rs`) only parses the command line, sets up tracing and calls into
//! [`tools`].

pub mod budget;
pub mod cancel;
pub mod codec;
pub mod embedded;
pub mod engine;
pub mod import;
pub mod load;
pub mod lod;
pub mod plan;
pub mod render;
pub mod rig;
pub mod rng;
pub mod server;
pub mod store;
pub mod tools;
