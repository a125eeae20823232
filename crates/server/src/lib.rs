//! The HTTP server: rigs and clips over a REST API, crowd frames through the dynamic batcher,
//! rendered frames, crowd sessions over WebSockets, in-process load tests.
//!
//! Layers, each importing only the ones below it: `app` (the router) → `routes` (one file
//! per resource: the handlers, in named phases) → [`state`] (the composition root: the
//! [`AppState`] every handler gets, which implements each service's context) → `services` (the
//! jobs that are more than a handler, each seeing the state only through its own narrow
//! trait) → [`admission`] (what a request costs, charged before its
//! work: the queue memory, the render budgets, heads resolved into priced jobs) → [`http`]
//! (what every handler shares: bodies, negotiation, extractors, the JSON error) and the core
//! (the batcher, the registry, the connections, each resource's state). [`http`] imports
//! nothing of the server; no service imports `routes` or [`state`]; no core module imports
//! `routes`, [`state`], `services` or [`admission`], and
//! the only one that uses [`http`] is `conn` (its 503 is an [`ApiError`]). No two files
//! import each other (`tests/tidy.rs` checks the whole crate).
//!
//! | module | what it is |
//! |---|---|
//! | `app` | [`app`]: the router and its layers; [`serve`] and [`run`] |
//! | `routes` | the handlers: `health`, `rigs`, `clips`, `frames`, `render`, `lod`, `graphs`, `masks`, `mappings`, `loadtest`, `viewer`, `replicas` (the lookup before a 404, as middleware), and `sessions` (its REST handlers, `sessions::viewer` the viewer socket) |
//! | `services` | the jobs beyond a handler, one per module, each behind its context trait (`services::Parts` and what each adds): `persist` (a change prepared within a budget and persisted), `replicas` (the shared store: commits and repairs, refreshes, LOD claims, lookups), `lod` (LOD builds), `render` (render admission and drawing), `tick` (a session's tick and fan-out) |
//! | [`state`] | [`AppState`]: engine, batcher, registry, budgets, each resource's state |
//! | [`config`] | every limit, timeout and default, the session limits included; the `serve` command's flags |
//! | [`admission`] | the queue memory and its charges ([`admission::memory`]), the render budgets ([`admission::render`]), heads resolved into jobs ([`admission::resolve`]) |
//! | [`http`] | JSON errors ([`ApiError`]), bodies within limits that keep their charge until sent, content negotiation, the `Admin`, `Ready` and `Query` extractors, `Server-Timing` |
//! | [`scheduler`] | the dynamic batcher with cross-request dedupe |
//! | [`registry`] | rigs prepared for the engine as immutable generations, q16 boxes, API descriptions |
//! | [`metrics`] | one `prometheus-client` registry per server: every family `/metrics` exports |
//! | `conn` | the accept loop: header and idle timeouts, the connection cap |
//! | `json` | JSON crowd frames written straight into reused buffers |
//! | `pool` | reused output buffers, bounded in count and bytes |
//! | `session_stream` | what a session viewer is sent: temporal residuals, packed messages, the encoded messages (taking the queue memory, not the state) |
//! | `shed` | the rate-limited log of shed and timed-out requests |
//! | `skipped` | what `/readyz` reports as skipped, until superseded |
//! | [`sessions`] | crowd sessions' state: sessions, viewers, outboxes, limits |
//! | `live` | live heads' input: producers' samples with their memory, the input rate budget, and what each live head shows (owned by the tick) |
//! | [`graphs`] | motion graphs by rig: as stored, and resolved and measured per rig generation |
//! | [`rig_maps`] | a rig's named masks and mappings as stored (persisted with its graphs) |
//! | [`loadtests`] | the load tests running and done |
//! | `lod_jobs` | LOD jobs by rig |
//! | `topologies` | the renderer and the mesh topologies cached on its device |
//!
//! `ARCHITECTURE.md` has the path of a request and the four budgets; `docs/design/` the why.

pub mod admission;
mod app;
pub mod config;
mod conn;
pub mod graphs;
pub mod http;
mod json;
mod live;
pub mod loadtests;
mod lod_jobs;
pub mod metrics;
mod pool;
pub mod registry;
pub mod rig_maps;
mod routes;
pub mod scheduler;
mod services;
mod session_stream;
pub mod sessions;
mod shed;
mod skipped;
pub mod state;
mod topologies;

pub use app::{app, run, serve, serve_also, shutdown_signal};
pub use config::{RenderBackend, ServerConfig, default_data_dir};
pub use http::ApiError;
pub use state::{AppState, Inner};

use crowdmorph_engine::EngineError;
use crowdmorph_store::StoreError;

/// Why the server could not start or stopped abnormally.
#[derive(Debug, thiserror::Error)]
pub enum ServerError {
    /// The engine could not be created (e.g. `--backend gpu` without a GPU).
    #[error("engine: {0}")]
    Engine(#[from] EngineError),
    /// The data directory is unusable.
    #[error("data directory: {0}")]
    Store(#[from] StoreError),
    /// The shared rig store (`--store`) cannot be opened or used.
    #[error("{0}")]
    SharedStore(#[from] crowdmorph_store::objects::SharedError),
    /// Serving failed.
    #[error("serving: {0}")]
    Io(#[from] std::io::Error),
}
