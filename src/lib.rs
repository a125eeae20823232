//! crowdmorph: a network animation server for blendshape (morph-target) crowds.
//!
//! Layout (each layer depends only on the ones above it):
//!
//! | module | what it is |
//! |---|---|
//! | [`rig`] | pure data: primitives, sparse targets, clips (weight tables), LOD order; keyframe sampling math |
//! | [`import`] | glTF/GLB, CSV and JSON readers that build a validated [`rig::Rig`] |
//! | [`embedded`] | the procedural default rig that needs no files |
//! | [`plan`] | the batch planner: a crowd of heads → unique jobs + per-head index |
//! | [`engine`] | blend engines; [`engine::cpu`] is the oracle and the no-GPU production engine |
//! | [`tools`] | the CLI's commands (`inspect`, `eval`, `bench`) as library functions |
//!
//! The binary (`src/main.rs`) only parses the command line, sets up tracing and calls into
//! [`tools`].

pub mod embedded;
pub mod engine;
pub mod import;
pub mod plan;
pub mod rig;
pub mod tools;
