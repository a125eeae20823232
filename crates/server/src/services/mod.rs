//! The server's jobs that are more than a handler: each module does one, and sees the server
//! only through a narrow context trait (as [`crate::admission::Admission`] does) that
//! [`crate::state::AppState`] implements in `state.rs`. A service names nothing of `state`,
//! `routes` or `app`: what it needs is listed in its trait, so a reader sees what it may touch,
//! and a test could hand it another context.
//!
//! | module | what it is |
//! |---|---|
//! | [`lod`] | LOD builds: the background job that orders a new rig's blendshapes by the five metrics and builds its mesh levels, and a `PUT`'s build, applied as the rig's next generation |
//! | [`persist`] | rig persistence: a rig's record, clip files, motion graphs or delete written to the data dir or committed to the shared store before the change is served; the data dir's load at start |
//! | [`render`] | render admission and drawing: a request checked, resolved, laid out and priced against the render budgets, then drawn and encoded (`POST /v1/crowd/render` and the session viewers' frames) |
//! | [`replicas`] | one replica of a shared store: commits (409 `store_conflict`, 503 `store_unavailable` or `store_damaged`) with the repair of damaged objects, the start's load, the periodic refresh, LOD claims, and the lookup of a rig a request names that this replica does not hold |
//! | [`tick`] | a session's tick: heads resolved, jobs grouped and submitted to the batcher, the fan-out of each viewer's message (encoded by `session_stream`), supervised |
//!
//! [`Parts`] is what every service may read: the rigs, the engine, the metrics, the
//! configuration and the queue memory. Each service's trait adds what only it uses.

pub mod lod;
pub mod persist;
pub mod render;
pub mod replicas;
pub mod tick;

use std::sync::{Arc, Weak};

use crate::admission::Admission;
use crate::admission::resolve::unknown_rig;
use crate::config::ServerConfig;
use crate::graphs::Graphs;
use crate::http::ApiError;
use crate::metrics::Metrics;
use crate::registry::{Registry, RigEntry};
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
    /// Motion graphs by rig.
    fn graphs(&self) -> &Graphs;
    /// A handle that does not keep the server alive.
    fn downgrade(&self) -> Weak<Self::Owner>;
    /// The server again, while it runs.
    fn upgrade(weak: &Weak<Self::Owner>) -> Option<Self>;

    /// Rig `id`, or 404 `unknown_rig` listing the rigs there are.
    fn rig(&self, id: &str) -> Result<Arc<RigEntry>, ApiError> {
        self.registry()
            .get(id)
            .ok_or_else(|| unknown_rig(self.registry(), id))
    }

    /// Whether the engine keeps rigs on a GPU (their layouts are then uploaded too).
    fn on_gpu(&self) -> bool {
        self.engine().info().kind == crowdmorph_engine::BackendKind::Gpu
    }
}
