//! The integration test binary: one binary, modules per area, shared helpers in `util`. It
//! tests the workspace from outside, through the umbrella library (`crowdmorph::...`), a real
//! server on a socket, the CLI and real clients; a test that needs only one crate lives in that
//! crate instead (`crates/engine/tests/shaders.rs`, each module's unit tests).
//!
//! A test that needs something a machine may lack is marked
//! `#[cfg_attr(not(<cfg>), ignore = "<reason>")]` with the cfg `build.rs` sets when it finds
//! it: the shared rigs in `../shared/data` or `$CROWDMORPH_TEST_DATA` (`crowdmorph_test_data`),
//! a Vulkan driver (`crowdmorph_gpu_driver`, through `util::gpu_test!`), Chromium
//! (`crowdmorph_chromium`), three.js from npm (`crowdmorph_threejs`), Python with pytest, or
//! numpy and aiohttp (`crowdmorph_python`, `crowdmorph_python_peer`), nginx, HAProxy,
//! SeaweedFS, kubernetes-validate, and root with network namespaces (`crowdmorph_nginx`,
//! `crowdmorph_haproxy`, `crowdmorph_seaweedfs`, `crowdmorph_kubernetes_validate`,
//! `crowdmorph_shaped_links`). Without it the test is listed as ignored with the reason; with
//! it, it must pass.

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
mod render_materials;
mod rigs;
mod sampling;
mod server;
mod skin;
mod tidy;
