//! The browser viewer (`clients/web`), served at `GET /viewer` from files embedded in the
//! binary, so that a server needs no files beside it and the page needs no network but the
//! server itself.
//!
//! Only the files listed in [`FILES`] are served, each with its own content type (module
//! scripts are refused by browsers under any type but JavaScript); any other name is the JSON
//! 404 every unknown path gets. The page needs no admin token to load; creating and changing a
//! session does, when the server has one, and the page sends it from `?token=`.

use axum::extract::Path;
use axum::http::{HeaderValue, header};
use axum::response::{IntoResponse, Response};

use crate::http::ApiError;

/// Name, content type and bytes of each file of the viewer.
pub const FILES: &[(&str, &str, &str)] = &[
    (
        "index.html",
        "text/html; charset=utf-8",
        include_str!("../../../../clients/web/index.html"),
    ),
    (
        "viewer.css",
        "text/css; charset=utf-8",
        include_str!("../../../../clients/web/viewer.css"),
    ),
    (
        "main.js",
        "text/javascript; charset=utf-8",
        include_str!("../../../../clients/web/main.js"),
    ),
    (
        "api.js",
        "text/javascript; charset=utf-8",
        include_str!("../../../../clients/web/api.js"),
    ),
    (
        "bincode.js",
        "text/javascript; charset=utf-8",
        include_str!("../../../../clients/web/bincode.js"),
    ),
    (
        "camera.js",
        "text/javascript; charset=utf-8",
        include_str!("../../../../clients/web/camera.js"),
    ),
    (
        "render.js",
        "text/javascript; charset=utf-8",
        include_str!("../../../../clients/web/render.js"),
    ),
];

/// What the page may load and connect to: its own origin only (the stream's WebSocket
/// included), and the empty `data:` favicon.
const CSP: &str = "default-src 'self'; img-src 'self' data:; connect-src 'self'; \
                   object-src 'none'; base-uri 'none'; frame-ancestors 'none'";

/// `GET /viewer`: the page.
pub async fn index() -> Response {
    serve("index.html")
}

/// `GET /viewer/{file}`: one of the page's scripts or its style sheet.
pub async fn file(Path(name): Path<String>) -> Response {
    serve(&name)
}

fn serve(name: &str) -> Response {
    let Some((_, content_type, body)) = FILES.iter().find(|(n, _, _)| *n == name) else {
        let names: Vec<&str> = FILES.iter().map(|(n, _, _)| *n).collect();
        return ApiError::not_found(
            "no_route",
            format!(
                "the viewer has no file {name:?} (files: {})",
                names.join(", ")
            ),
        )
        .into_response();
    };
    (
        [
            (header::CONTENT_TYPE, HeaderValue::from_static(content_type)),
            (
                header::CONTENT_SECURITY_POLICY,
                HeaderValue::from_static(CSP),
            ),
            (
                header::X_CONTENT_TYPE_OPTIONS,
                HeaderValue::from_static("nosniff"),
            ),
            // The files change with the binary: a browser must not keep an old script
            // beside a new page.
            (header::CACHE_CONTROL, HeaderValue::from_static("no-cache")),
        ],
        *body,
    )
        .into_response()
}
