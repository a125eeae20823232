//! crowdmorph: a network animation server for blendshape (morph-target) crowds.
//!
//! This library is the umbrella of the workspace: it re-exports each layer's crate under the
//! module name the layer has always had, so that the binary (`src/main.rs`, one module per
//! subcommand in `src/cli/`) and the black-box integration tests (`tests/`) read
//! `crowdmorph::rig::Rig`, `crowdmorph::engine::Engine`, ... Code inside the workspace names the
//! crate it uses instead. `ARCHITECTURE.md` has the crate map and where a change goes.
//!
//! | module | crate | what it is |
//! |---|---|---|
//! | [`rng`], [`linalg`], [`budget`], [`cancel`], [`rig`], [`embedded`], [`synthetic`], [`plan`] | `crowdmorph-core` | the data layer |
//! | [`compress`], [`transform`], [`graph`], [`texture`] | `crowdmorph-anim` | compressed clips (per curve, and transform-coded captures), motion graphs, PCA-animated textures |
//! | [`import`] | `crowdmorph-import` | glTF/GLB, CSV and JSON readers that build a validated [`rig::Rig`] |
//! | [`engine`], [`export`], [`render`], [`lod`] | `crowdmorph-engine` | blend engines (CPU oracle, wgpu), renders, LOD, export |
//! | [`codec`], [`store`] | `crowdmorph-store` | the record codec; the data dir and the shared store |
//! | [`load`] | `crowdmorph-load` | the load generator |
//! | [`server`] | `crowdmorph-server` | the HTTP server |
//! | [`bench`](mod@bench) | `crowdmorph-bench` | benchmarks, their peers and harness |

pub use crowdmorph_core::{budget, cancel, embedded, linalg, plan, rig, rng, synthetic};

pub use crowdmorph_anim::{compress, graph, texture, transform};

pub use crowdmorph_import as import;

pub use crowdmorph_engine as engine;
pub use crowdmorph_engine::{export, lod, render};

pub use crowdmorph_store as store;
pub use crowdmorph_store::codec;

pub use crowdmorph_load as load;

pub use crowdmorph_server as server;

pub use crowdmorph_bench as bench;
