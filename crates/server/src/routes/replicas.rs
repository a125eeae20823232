//! The lookup before a 404 on a replica of a shared store: a request about a rig this replica
//! does not hold looks it up in the store first ([`crate::services::replicas`] does the work).

use axum::extract::{Request, State};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

use crate::services::replicas::{find_missing, missing};
use crate::state::AppState;

/// Middleware: a request about a rig this replica does not hold (`/v1/rigs/{id}...`) looks it
/// up in the shared store first, so that a replica a balancer sends it to after another one
/// failed serves it rather than 404. (Crowd frames, renders and sessions look up their heads'
/// rigs in their handlers, the `?rig=` hint among them: one bound of lookups per request.)
pub async fn look_up_rigs(State(state): State<AppState>, request: Request, next: Next) -> Response {
    if state.replica.store.is_some() && state.is_ready() {
        let from_path = request
            .uri()
            .path()
            .strip_prefix("/v1/rigs/")
            .map(|rest| rest.split('/').next().unwrap_or_default());
        let ids = missing(&state, from_path);
        if let Err(e) = find_missing(&state, ids).await {
            return e.into_response();
        }
    }
    next.run(request).await
}
