//! The integration test binary: one binary, modules per area, shared helpers in `util`.
//!
//! Tests that need the real rigs in `../shared/data` (or `$CROWDMORPH_TEST_DATA`), a GPU
//! adapter or Python with pytest are marked `#[cfg_attr(not(<cfg>), ignore = "<reason>")]` with
//! the cfgs `build.rs` sets when it finds them (`crowdmorph_test_data`, `crowdmorph_gpu_driver`,
//! `crowdmorph_python`): without the resource they are listed as ignored with the reason, and
//! with it they must pass.

// A test that meets an unexpected error should fail loudly, which is what unwrap does.
#![allow(clippy::unwrap_used)]

mod util;

mod animation;
mod bad_input;
mod channels;
mod cli;
mod compressed;
mod cost;
mod engine;
mod gpu;
mod lod;
mod planner;
mod python_client;
mod render;
mod rigs;
mod sampling;
mod server;
mod skin;
mod tidy;
