//! Admission: what a request costs, charged before any of its work — the queue memory and its
//! charges ([`memory`]), the render budgets ([`render`]), heads resolved into priced jobs
//! ([`resolve`]), the names they match ([`names`]), their layers ([`layers`], shared with
//! session ticks), mappings ([`mapping`]), their final poses for clients that blend themselves
//! ([`poses`]), a session head's liveliness ([`alive`]) and live input ([`live`]). [`Decoded`] is the extractor of a request body: it hands a handler the
//! decoded value only together with its charge.

pub mod alive;
pub mod layers;
pub mod live;
pub mod mapping;
pub mod memory;
pub mod names;
pub mod poses;
pub mod render;
pub mod resolve;

#[cfg(test)]
mod priced_tests;

use axum::extract::{FromRequest, Request};
use serde::de::DeserializeOwned;

pub use memory::{
    Charge, Held, Priced, QueueMemory, decode_held, decode_reservation, names_bytes,
    names_reservation,
};
pub use render::{RenderBudget, RenderPermits, Renderee};
pub use resolve::{ResolvedHeads, resolve_heads};

use crate::http::{ApiError, BodyLimits};

/// What admission needs of the server's state.
pub trait Admission {
    /// The queue memory.
    fn queue_memory(&self) -> &QueueMemory;
    /// The limits of a request body (not an upload).
    fn body_limits(&self) -> BodyLimits;
}

/// A request body decoded (JSON or bincode, by its Content-Type) and charged: the value comes
/// with the queue memory its [`Priced`] footprint holds, kept until the handler lets go of it
/// (into the response that sends what was built from it).
#[derive(Debug)]
pub struct Decoded<T>(pub Held<T>);

impl<T, S> FromRequest<S> for Decoded<T>
where
    T: DeserializeOwned + Priced + Send,
    S: Admission + Send + Sync,
{
    type Rejection = ApiError;

    async fn from_request(req: Request, state: &S) -> Result<Decoded<T>, ApiError> {
        let (parts, body) = req.into_parts();
        decode_held(
            state.queue_memory(),
            state.body_limits(),
            &parts.headers,
            body,
        )
        .await
        .map(Decoded)
    }
}
