//! The integration test binary: one binary, modules per area, shared helpers in `util`.
//!
//! Tests that read the real rigs in `../shared/data` print why and return early when that
//! folder is absent (it is present in CI and in every development checkout).

// A test that meets an unexpected error should fail loudly, which is what unwrap does.
#![allow(clippy::unwrap_used)]

mod util;

mod bad_input;
mod engine;
mod gpu;
mod lod;
mod planner;
mod rigs;
mod sampling;
mod server;
mod shaders;
