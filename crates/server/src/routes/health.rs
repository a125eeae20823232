//! `/healthz` (the process answers), `/readyz` (stored rigs loaded; the engine and renderer),
//! `/metrics` (OpenMetrics) and the JSON 404 of every other path.

use axum::extract::State;
use axum::http::{StatusCode, header};
use axum::response::{IntoResponse, Response};
use crowdmorph_proto::Readiness;

use crate::http::ApiError;
use crate::http::negotiate::json_text;
use crate::metrics;
use crate::state::AppState;

pub async fn healthz() -> Response {
    json_text(StatusCode::OK, r#"{"status":"ok"}"#)
}

pub async fn readyz(State(state): State<AppState>) -> Response {
    let info = state.engine.info();
    let status = if !state.is_ready() {
        "loading"
    } else if info.degraded {
        "degraded"
    } else {
        "ready"
    };
    let body = Readiness {
        status: status.to_string(),
        backend: format!("{:?}", info.kind).to_lowercase(),
        cpu_isa: info.cpu_isa,
        degraded_reason: info.degraded_reason,
        rigs: state.registry.len() as u32,
        skipped_files: state.skipped(),
        renderer: state.render.adapter_name(),
    };
    let code = if state.is_ready() {
        StatusCode::OK
    } else {
        StatusCode::SERVICE_UNAVAILABLE
    };
    json_text(code, serde_json::to_vec(&body).unwrap_or_default())
}

pub async fn metrics(State(state): State<AppState>) -> Response {
    match state.metrics.encode(state.gauges()) {
        Ok(text) => ([(header::CONTENT_TYPE, metrics::CONTENT_TYPE)], text).into_response(),
        Err(e) => ApiError::internal(format!("encoding the metrics failed: {e}")).into_response(),
    }
}

pub async fn not_found() -> ApiError {
    ApiError::not_found(
        "no_route",
        "no such endpoint; see /v1/rigs and /v1/crowd/frame",
    )
}
