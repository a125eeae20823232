//! Extractors whose rejection is the API's JSON error: [`Admin`] (the admin token, when the
//! server has one), [`Ready`] (stored rigs loaded) and [`Query`] (a query string that parses).
//! Handlers name what they need in their signature instead of checking by hand.

use axum::extract::FromRequestParts;
use axum::http::request::Parts;
use axum::http::{StatusCode, header};
use serde::de::DeserializeOwned;

use super::error::ApiError;

/// What the extractors need of the server's state.
pub trait Gate {
    /// The admin token, when changes need one.
    fn admin_token(&self) -> Option<&str>;
    /// Whether stored rigs have been loaded.
    fn is_ready(&self) -> bool;
}

/// Proof that the request may change things: it carries `Authorization: Bearer <token>` with
/// the server's admin token, or the server has none.
#[derive(Clone, Copy, Debug)]
pub struct Admin;

/// Compares without an early exit, so the time taken does not reveal the token's prefix.
fn same(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

impl Admin {
    /// Checks `headers` against `token`.
    pub fn check(headers: &axum::http::HeaderMap, token: Option<&str>) -> Result<Admin, ApiError> {
        let Some(token) = token else {
            return Ok(Admin);
        };
        // The scheme name is case-insensitive (RFC 7235 §2.1); the token is not.
        let given = headers
            .get(header::AUTHORIZATION)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.trim().split_once(' '))
            .filter(|(scheme, _)| scheme.eq_ignore_ascii_case("bearer"))
            .map(|(_, token)| token.trim());
        match given {
            Some(g) if same(g.as_bytes(), token.as_bytes()) => Ok(Admin),
            Some(_) => Err(ApiError::new(
                StatusCode::UNAUTHORIZED,
                "bad_token",
                "the bearer token is not the admin token",
            )),
            None => Err(ApiError::new(
                StatusCode::UNAUTHORIZED,
                "token_required",
                "uploads and deletes need an Authorization: Bearer <admin token> header",
            )),
        }
    }
}

impl<S: Gate + Send + Sync> FromRequestParts<S> for Admin {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Admin, ApiError> {
        Admin::check(&parts.headers, state.admin_token())
    }
}

/// Proof that the server has loaded its stored rigs (503 `loading` until then).
#[derive(Clone, Copy, Debug)]
pub struct Ready;

impl Ready {
    /// `Ready` when `ready`, else the 503.
    pub fn check(ready: bool) -> Result<Ready, ApiError> {
        if ready {
            Ok(Ready)
        } else {
            Err(ApiError::unavailable(
                "loading",
                "stored rigs are still loading; retry shortly",
                1,
            ))
        }
    }
}

impl<S: Gate + Send + Sync> FromRequestParts<S> for Ready {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Ready, ApiError> {
        let _ = parts;
        Ready::check(state.is_ready())
    }
}

/// A query string parsed into `T`; 400 `bad_query` naming the problem otherwise.
#[derive(Clone, Debug)]
pub struct Query<T>(pub T);

impl<T: DeserializeOwned, S: Send + Sync> FromRequestParts<S> for Query<T> {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Query<T>, ApiError> {
        axum::extract::Query::<T>::from_request_parts(parts, state)
            .await
            .map(|axum::extract::Query(q)| Query(q))
            .map_err(|e| ApiError::bad_request("bad_query", e.body_text()))
    }
}
