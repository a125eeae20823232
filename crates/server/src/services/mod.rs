//! The server's jobs that are more than a handler: each module does one, and sees the server
//! only through a narrow context trait (as [`crate::admission::Admission`] does) that
//! [`crate::state::AppState`] implements in `state.rs`. A service names nothing of `state`,
//! `routes` or `app`: what it needs is listed in its trait, so a reader sees what it may touch,
//! and a test could hand it another context.
//!
//! | module | what it is |
//! |---|---|
//! | [`render`] | render admission and drawing: a request checked, resolved, laid out and priced against the render budgets, then drawn and encoded (`POST /v1/crowd/render` and the session viewers' frames) |
//! | [`tick`] | a session's tick: heads resolved, jobs grouped and submitted to the batcher, the fan-out of each viewer's message (encoded by `session_stream`), supervised |
//!
//! [`Parts`] is what every service may read: the rigs, the engine, the metrics, the
//! configuration and the queue memory. Each service's trait adds what only it uses.

pub mod render;
pub mod tick;

use std::sync::{Arc, Weak};

use crate::admission::Admission;
use crate::config::ServerConfig;
use crate::metrics::Metrics;
use crate::registry::Registry;
use crowdmorph_engine::Engine;

/// What every service may read of the server, and a weak handle to it for work that must not
/// keep a stopped server alive (a background build, a session's tick).
pub trait Parts: Admission + Clone + Send + Sync + 'static {
    /// What a weak handle points at.
    type Owner: Send + Sync + 'static;
    /// The registered rigs.
    fn registry(&self) -> &Registry;
    /// The engine.
    fn engine(&self) -> &Arc<Engine>;
    /// The metrics.
    fn metrics(&self) -> &Arc<Metrics>;
    /// Every limit, timeout and default.
    fn config(&self) -> &ServerConfig;
    /// A handle that does not keep the server alive.
    fn downgrade(&self) -> Weak<Self::Owner>;
    /// The server again, while it runs.
    fn upgrade(weak: &Weak<Self::Owner>) -> Option<Self>;
}
