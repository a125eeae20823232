//! The router and the serving loop: [`app`] builds every route with its layers (usable in
//! tests with `tower::ServiceExt::oneshot`), [`serve`] runs it on a listener until a shutdown
//! future resolves, then drains the batcher.

use std::future::Future;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use axum::Router;
use axum::error_handling::HandleErrorLayer;
use axum::extract::{DefaultBodyLimit, MatchedPath, Request, State};
use axum::http::{HeaderName, HeaderValue, Method, StatusCode, header};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post, put};
use tokio::net::TcpListener;
use tower::ServiceBuilder;
use tower_http::classify::ServerErrorsFailureClass;
use tower_http::cors::{AllowOrigin, CorsLayer};
use tower_http::request_id::{
    MakeRequestId, PropagateRequestIdLayer, RequestId, SetRequestIdLayer,
};
use tower_http::trace::TraceLayer;

use super::ServerError;
use super::config::ServerConfig;
use super::conn;
use super::http::{ApiError, SERVER_TIMING, encoding};
use super::metrics::Metrics;
use super::routes;
use super::services::render::{IMAGE_HEIGHT, IMAGE_WIDTH};
use super::services::replicas::Replicating;
use super::shed::SHED_LOG_EVERY;
use super::state::AppState;

/// Request ids: a process-wide counter, in hex, unless the client sent `x-request-id`.
#[derive(Clone, Debug, Default)]
struct Counter(Arc<AtomicU64>);

impl MakeRequestId for Counter {
    fn make_request_id<B>(&mut self, _: &axum::http::Request<B>) -> Option<RequestId> {
        let n = self.0.fetch_add(1, Ordering::Relaxed);
        HeaderValue::from_str(&format!("{n:08x}"))
            .ok()
            .map(RequestId::new)
    }
}

/// Charges what compressing the response will hold (its encoder) to the queue memory before
/// the response is made, kept until its body has been sent; without room, the response goes
/// out plain (the `Accept-Encoding` the compression layer would read is dropped). A WebSocket
/// upgrade is never compressed by it, so it is not charged.
async fn charge_compression(
    State(state): State<AppState>,
    mut req: Request,
    next: Next,
) -> Response {
    let Some(e) = encoding::accepted(req.headers()) else {
        // Nothing compressed is acceptable: the identity encoding it is, whatever the header
        // says of identity (`encoding`'s doc), never the compression layer's 406.
        req.headers_mut().remove(header::ACCEPT_ENCODING);
        return next.run(req).await;
    };
    if req.headers().contains_key(header::UPGRADE) {
        return next.run(req).await;
    }
    match state.queue_memory.reserve(encoding::encoder_bytes(e)) {
        Ok(charge) => super::http::body::hold(next.run(req).await, charge),
        Err(_) => {
            req.headers_mut().remove(header::ACCEPT_ENCODING);
            next.run(req).await
        }
    }
}

/// Charges what inflating a compressed request body holds (its decoder,
/// [`encoding::decoder_bytes`]) to the queue memory before the body is read, kept until the
/// response has been sent; without room, a 503 `queue_full` (413 when it exceeds the whole
/// queue memory), as for any other request memory.
async fn charge_inflation(State(state): State<AppState>, req: Request, next: Next) -> Response {
    let Some(bytes) = encoding::decoder_bytes(req.headers()) else {
        return next.run(req).await;
    };
    match state.queue_memory.reserve(bytes) {
        Ok(charge) => super::http::body::hold(next.run(req).await, charge),
        Err(e) => e.into_response(),
    }
}

/// Counts every response by route and status.
async fn count_requests(State(state): State<AppState>, req: Request, next: Next) -> Response {
    let route = req
        .extensions()
        .get::<MatchedPath>()
        .map_or_else(|| "unmatched".to_string(), |p| p.as_str().to_string());
    let resp = next.run(req).await;
    state.metrics.request(&route, resp.status().as_u16());
    resp
}

/// Sheds load: past `max_concurrency` requests in progress, new ones get 503 at once rather
/// than queueing without bound (one semaphore for the whole router, unlike a tower layer,
/// which axum would instantiate per route).
async fn shed_load(State(state): State<AppState>, req: Request, next: Next) -> Response {
    match state.inflight.clone().try_acquire_owned() {
        Ok(permit) => {
            let resp = next.run(req).await;
            drop(permit);
            resp
        }
        Err(_) => {
            state.metrics.reject("overloaded");
            ApiError::unavailable(
                "overloaded",
                "too many requests in progress; retry shortly",
                1,
            )
            .into_response()
        }
    }
}

/// Maps errors of the tower layers (the timeout) to JSON errors.
async fn layer_error(metrics: Arc<Metrics>, err: tower::BoxError) -> Response {
    if err.is::<tower::timeout::error::Elapsed>() {
        metrics.reject("timeout");
        ApiError::new(
            StatusCode::GATEWAY_TIMEOUT,
            "deadline_exceeded",
            "the request took longer than the server's timeout",
        )
        .into_response()
    } else {
        ApiError::internal(err).into_response()
    }
}

/// Logs a failed response: 503 and 504 to the [`ShedLog`], anything else (a 500: a bug or a
/// broken engine) at ERROR with its request's span, as tower-http's default does.
fn log_failure(
    state: &AppState,
    class: ServerErrorsFailureClass,
    latency: Duration,
    span: &tracing::Span,
) {
    match class {
        ServerErrorsFailureClass::StatusCode(s)
            if s == StatusCode::SERVICE_UNAVAILABLE || s == StatusCode::GATEWAY_TIMEOUT =>
        {
            state.shed_log.record(s);
        }
        other => tracing::error!(
            parent: span,
            classification = %other,
            latency_ms = latency.as_secs_f64() * 1e3,
            "response failed"
        ),
    }
}

/// Gives the errors axum answers by itself (a method a route does not have, a path segment
/// that is not valid UTF-8, a missing query parameter) the same JSON body as every
/// [`ApiError`], keeping their status and headers (`Allow` on a 405). Their plain-text
/// message, which names the problem and nothing internal, becomes the JSON message.
async fn json_errors(req: Request, next: Next) -> Response {
    let resp = next.run(req).await;
    let status = resp.status();
    let is_json = resp
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with(crowdmorph_proto::CONTENT_TYPE_JSON));
    if !(status.is_client_error() || status.is_server_error()) || is_json {
        return resp;
    }
    let (mut parts, body) = resp.into_parts();
    let text = axum::body::to_bytes(body, 4096).await.unwrap_or_default();
    let text = String::from_utf8_lossy(&text).trim().to_string();
    let code = match status {
        StatusCode::METHOD_NOT_ALLOWED => "method_not_allowed",
        StatusCode::NOT_FOUND => "not_found",
        StatusCode::PAYLOAD_TOO_LARGE => "body_too_large",
        StatusCode::UNSUPPORTED_MEDIA_TYPE => "unsupported_media_type",
        s if s.is_server_error() => "internal",
        _ => "bad_request",
    };
    let message = if text.is_empty() || status.is_server_error() {
        status
            .canonical_reason()
            .unwrap_or("request failed")
            .to_string()
    } else {
        text
    };
    let json = ApiError::new(status, code, message).into_response();
    parts.headers.remove(header::CONTENT_LENGTH);
    parts.headers.insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static(crowdmorph_proto::CONTENT_TYPE_JSON),
    );
    Response::from_parts(parts, json.into_body())
}

/// The router with every route and layer; `state` should have loaded its stored rigs (or be
/// loading them in the background).
pub fn app(state: AppState) -> Router {
    let request_id = HeaderName::from_static("x-request-id");
    let cfg = &state.config;
    let routes = resources()
        .fallback(routes::health::not_found)
        // A rig the path names that another replica wrote is read from the shared store
        // before the handler looks for it (crowds look up their heads' rigs themselves).
        .layer(middleware::from_fn_with_state(
            state.clone(),
            routes::replicas::look_up_rigs,
        ))
        // Bodies are read with explicit per-route limits (see http::body::read_body), after
        // a compressed one is inflated: the limits bound the inflated bytes.
        .layer(DefaultBodyLimit::disable())
        .layer(middleware::from_fn(encoding::inflate_request))
        .layer(middleware::from_fn_with_state(
            state.clone(),
            charge_inflation,
        ))
        .layer(middleware::from_fn(json_errors))
        .layer(encoding::compress_layer())
        .layer(middleware::from_fn_with_state(
            state.clone(),
            charge_compression,
        ))
        .layer(middleware::from_fn_with_state(state.clone(), shed_load))
        .layer(middleware::from_fn_with_state(
            state.clone(),
            count_requests,
        ))
        .layer(middleware::from_fn(crate::http::timing::stamp_arrival));
    let timeout = cfg.handler_timeout() + Duration::from_secs(1);
    let routes = routes.layer(
        ServiceBuilder::new()
            .layer(HandleErrorLayer::new({
                let metrics = state.metrics.clone();
                move |err| layer_error(metrics.clone(), err)
            }))
            .timeout(timeout),
    );
    let routes = match cors(&cfg.cors_origins, &request_id) {
        Some(c) => routes.layer(c),
        None => routes,
    };
    let failures = state.clone();
    routes
        .layer(PropagateRequestIdLayer::new(request_id.clone()))
        .layer(
            TraceLayer::new_for_http()
                .make_span_with(|req: &axum::http::Request<_>| {
                    let id = req
                        .headers()
                        .get("x-request-id")
                        .and_then(|v| v.to_str().ok())
                        .unwrap_or("-");
                    tracing::info_span!("request", id = %id, method = %req.method(), uri = %req.uri())
                })
                .on_failure(
                    move |class: ServerErrorsFailureClass, latency: Duration, span: &tracing::Span| {
                        log_failure(&failures, class, latency, span)
                    },
                ),
        )
        .layer(SetRequestIdLayer::new(request_id, Counter::default()))
        .with_state(state)
}

/// Every resource's routes: one module of `routes/` each.
fn resources() -> Router<AppState> {
    Router::new()
        .route("/healthz", get(routes::health::healthz))
        .route("/readyz", get(routes::health::readyz))
        .route("/metrics", get(routes::health::metrics))
        .route(
            "/v1/rigs",
            post(routes::rigs::upload_rig).get(routes::rigs::list_rigs),
        )
        .route(
            "/v1/rigs/{id}",
            get(routes::rigs::get_rig).delete(routes::rigs::delete_rig),
        )
        .route("/v1/rigs/{id}/mesh", get(routes::rigs::get_mesh))
        .route(
            "/v1/rigs/{id}/materials",
            get(routes::appearance::get_materials),
        )
        .route(
            "/v1/rigs/{id}/textures/{i}",
            get(routes::appearance::get_texture),
        )
        .route("/v1/rigs/{id}/layers", get(routes::layers::get_layers))
        .route(
            "/v1/rigs/{id}/channels",
            get(routes::channels::get_channels),
        )
        .route(
            "/v1/rigs/{id}/layers/{m}",
            get(routes::layers::get_layer_texels),
        )
        .route(
            "/v1/rigs/{id}/model.glb",
            get(routes::appearance::get_model),
        )
        .route(
            "/v1/rigs/{id}/lod",
            get(routes::lod::get_lod).put(routes::lod::put_lod),
        )
        .route(
            "/v1/rigs/{id}/joint-map",
            get(routes::joints::get_joint_map)
                .put(routes::joints::put_joint_map)
                .delete(routes::joints::delete_joint_map),
        )
        .route("/v1/rigs/{id}/graphs", get(routes::graphs::list_graphs))
        .route("/v1/rigs/{id}/masks", get(routes::masks::list_masks))
        .route(
            "/v1/rigs/{id}/masks/{name}",
            get(routes::masks::get_mask)
                .put(routes::masks::put_mask)
                .delete(routes::masks::delete_mask),
        )
        .route(
            "/v1/rigs/{id}/mappings",
            get(routes::mappings::list_mappings),
        )
        .route(
            "/v1/rigs/{id}/mappings/{name}",
            get(routes::mappings::get_mapping)
                .put(routes::mappings::put_mapping)
                .delete(routes::mappings::delete_mapping),
        )
        .route(
            "/v1/rigs/{id}/graphs/{name}",
            get(routes::graphs::get_graph)
                .put(routes::graphs::put_graph)
                .post(routes::graphs::build_graph)
                .delete(routes::graphs::delete_graph),
        )
        .route(
            "/v1/rigs/{id}/clips",
            post(routes::clips::upload_clips).get(routes::clips::list_clips),
        )
        .route(
            "/v1/rigs/{id}/clips/{clip}",
            get(routes::clips::get_clip).delete(routes::clips::delete_clip),
        )
        .route(
            "/v1/rigs/{id}/clips/{clip}/texture",
            put(routes::clips::put_clip_texture)
                .get(routes::clips::get_clip_texture)
                .delete(routes::clips::delete_clip_texture),
        )
        .route("/v1/crowd/frame", post(routes::frames::crowd_frame))
        .route("/v1/crowd/render", post(routes::render::crowd_render))
        .route("/viewer", get(routes::viewer::index))
        .route("/viewer/{file}", get(routes::viewer::file))
        .route(
            "/v1/sessions",
            post(routes::sessions::create_session).get(routes::sessions::list_sessions),
        )
        .route(
            "/v1/sessions/{id}",
            get(routes::sessions::get_session)
                .put(routes::sessions::put_session)
                .patch(routes::sessions::patch_session)
                .delete(routes::sessions::delete_session),
        )
        .route("/v1/sessions/{id}/stream", get(routes::sessions::stream))
        .route(
            "/v1/sessions/{id}/live",
            post(routes::sessions::post_live).get(routes::sessions::live_socket),
        )
        .route("/v1/loadtest", post(routes::loadtest::start_loadtest))
        .route("/v1/loadtest/{id}", get(routes::loadtest::get_loadtest))
}

/// CORS for `--cors-origin` (none without one): the headers a browser client reads exposed.
fn cors(origins: &[String], request_id: &HeaderName) -> Option<CorsLayer> {
    if origins.is_empty() {
        return None;
    }
    let allow = if origins.iter().any(|o| o == "*") {
        AllowOrigin::any()
    } else {
        AllowOrigin::list(origins.iter().filter_map(|o| HeaderValue::from_str(o).ok()))
    };
    Some(
        CorsLayer::new()
            .allow_origin(allow)
            .allow_methods([
                Method::GET,
                Method::POST,
                Method::PUT,
                Method::PATCH,
                Method::DELETE,
            ])
            .allow_headers([header::CONTENT_TYPE, header::ACCEPT, header::AUTHORIZATION])
            .expose_headers([
                request_id.clone(),
                header::RETRY_AFTER,
                IMAGE_WIDTH,
                IMAGE_HEIGHT,
                SERVER_TIMING,
            ]),
    )
}

/// A future that resolves on SIGINT (Ctrl-C) or SIGTERM.
pub async fn shutdown_signal() {
    let ctrl_c = async {
        if let Err(e) = tokio::signal::ctrl_c().await {
            tracing::error!(error = %e, "cannot listen for Ctrl-C");
            std::future::pending::<()>().await;
        }
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(e) => {
                tracing::error!(error = %e, "cannot listen for SIGTERM");
                std::future::pending::<()>().await;
            }
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        () = ctrl_c => {},
        () = term => {},
    }
    tracing::info!("shutdown requested: finishing requests in flight");
}

/// Serves until `shutdown` resolves: loads stored rigs in the background (not ready until
/// done), then on shutdown stops accepting, lets requests in flight complete, drains the
/// batcher and returns.
pub async fn run(
    listener: TcpListener,
    config: ServerConfig,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), ServerError> {
    let state = AppState::new(config)?;
    // A shared store that does not answer or refuses writes stops the start, naming it.
    if let Some(shared) = state.shared_store() {
        shared.check().await?;
        tracing::info!(store = %shared.url(), "rig store reachable");
    }
    serve(listener, state, shutdown).await
}

/// The connection limits of `state`'s configuration.
fn limits(state: &AppState) -> conn::Limits {
    conn::Limits {
        max_connections: state.config.connection_cap(),
        header_timeout: state.config.header_timeout,
        idle_timeout: state.config.idle_timeout,
    }
}

/// Serves connections from one more listener with `state`'s app until `shutdown` resolves,
/// letting requests in flight complete, as [`serve`] does, but without the state's lifecycle
/// (loading stored rigs, closing sessions, draining the batcher), which stays with the one
/// [`serve`] of `state`: for a server reachable on several addresses, such as a benchmark's
/// shaped link beside loopback. Each listener has its own connection cap.
pub async fn serve_also(
    listener: TcpListener,
    state: AppState,
    shutdown: impl Future<Output = ()> + Send + 'static,
) {
    let limits = limits(&state);
    conn::serve_connections(
        listener,
        app(state.clone()),
        state.metrics.clone(),
        limits,
        shutdown,
    )
    .await;
}

/// Like [`run`] with a state built by the caller (tests inspect it afterwards).
pub async fn serve(
    listener: TcpListener,
    state: AppState,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), ServerError> {
    if let Ok(addr) = listener.local_addr() {
        tracing::info!(%addr, "listening");
    }
    let loader = state.clone();
    tokio::spawn(async move {
        loader.load_stored().await;
        crate::services::replicas::spawn_refresh(&loader);
    });
    // Background LOD jobs are not requests in flight: stop them at once, or the runtime
    // would wait for their blocking work before the process can exit.
    let jobs = state.clone();
    let shutdown = async move {
        shutdown.await;
        jobs.lod_jobs.cancel_background();
    };
    let serving = conn::serve_connections(
        listener,
        app(state.clone()),
        state.metrics.clone(),
        limits(&state),
        shutdown,
    );
    let summaries = async {
        let mut every = tokio::time::interval(SHED_LOG_EVERY);
        loop {
            every.tick().await;
            state.shed_log.flush();
        }
    };
    tokio::select! {
        () = serving => {}
        _ = summaries => {}
    }
    state.sessions.close_all("the server is stopping");
    state.loadtests.cancel_all();
    state.scheduler.shutdown().await;
    tracing::info!("stopped");
    Ok(())
}
