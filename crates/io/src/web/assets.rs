//! The pages, scripts and styles, built into the binary: nothing to install
//! beside it and no Node toolchain to build them. Plain ES modules and SVG,
//! no framework and no map library (docs/web.md says why).

use axum::extract::Path;
use axum::http::{StatusCode, header};
use axum::response::{Html, IntoResponse, Response};

use super::security::error;

/// `(name, content type, body)` of every asset under `/assets/`.
const ASSETS: &[(&str, &str, &str)] = &[
    (
        "style.css",
        "text/css; charset=utf-8",
        include_str!("assets/style.css"),
    ),
    (
        "site.js",
        "text/javascript; charset=utf-8",
        include_str!("assets/site.js"),
    ),
    (
        "map.js",
        "text/javascript; charset=utf-8",
        include_str!("assets/map.js"),
    ),
    (
        "edit.js",
        "text/javascript; charset=utf-8",
        include_str!("assets/edit.js"),
    ),
];

pub(super) const MAP_PAGE: &str = include_str!("assets/map.html");
pub(super) const EDIT_PAGE: &str = include_str!("assets/edit.html");

pub(super) async fn map_page() -> Html<&'static str> {
    Html(MAP_PAGE)
}

pub(super) async fn edit_page() -> Html<&'static str> {
    Html(EDIT_PAGE)
}

pub(super) async fn asset(Path(name): Path<String>) -> Response {
    match ASSETS.iter().find(|(n, _, _)| *n == name) {
        Some((_, kind, body)) => (
            [
                (header::CONTENT_TYPE, *kind),
                (header::CACHE_CONTROL, "no-cache"),
            ],
            *body,
        )
            .into_response(),
        None => error(StatusCode::NOT_FOUND, "not_found", "no such asset"),
    }
}
