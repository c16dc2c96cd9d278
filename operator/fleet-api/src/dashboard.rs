//! The web dashboard: three static files embedded in the binary and served at `/dashboard/`.
//! They hold no fleet data and need no token to load; the page then asks the Fleet API
//! (`/api/v1`, authenticated and authorized per request) for everything it shows. A strict
//! Content-Security-Policy allows only these files and calls to this origin, so text a robot
//! reports can never run as script.

use axum::Router;
use axum::http::header::{
    CACHE_CONTROL, CONTENT_SECURITY_POLICY, CONTENT_TYPE, REFERRER_POLICY, X_CONTENT_TYPE_OPTIONS,
    X_FRAME_OPTIONS,
};
use axum::http::{HeaderName, HeaderValue};
use axum::response::{IntoResponse, Redirect, Response};
use axum::routing::get;

/// Where the dashboard is served.
pub const PATH: &str = "/dashboard/";

const INDEX: &str = include_str!("../dashboard/index.html");
const SCRIPT: &str = include_str!("../dashboard/app.js");
const STYLE: &str = include_str!("../dashboard/app.css");

/// Only this origin's files and API; no inline script or style elements, no framing.
const POLICY: &str = "default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' data:; \
     connect-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'";

/// The dashboard's routes (no state: the files are constants).
pub fn routes<S: Clone + Send + Sync + 'static>() -> Router<S> {
    Router::new()
        .route("/dashboard", get(|| async { Redirect::permanent(PATH) }))
        .route(
            PATH,
            get(|| async { file("text/html; charset=utf-8", INDEX) }),
        )
        .route(
            "/dashboard/app.js",
            get(|| async { file("text/javascript; charset=utf-8", SCRIPT) }),
        )
        .route(
            "/dashboard/app.css",
            get(|| async { file("text/css; charset=utf-8", STYLE) }),
        )
}

/// One embedded file with the headers every dashboard response carries. `no-cache`: a browser
/// revalidates, so an upgraded operator serves its own dashboard at once.
fn file(content_type: &'static str, body: &'static str) -> Response {
    let headers: [(HeaderName, HeaderValue); 6] = [
        (CONTENT_TYPE, HeaderValue::from_static(content_type)),
        (CACHE_CONTROL, HeaderValue::from_static("no-cache")),
        (CONTENT_SECURITY_POLICY, HeaderValue::from_static(POLICY)),
        (X_CONTENT_TYPE_OPTIONS, HeaderValue::from_static("nosniff")),
        (X_FRAME_OPTIONS, HeaderValue::from_static("DENY")),
        (REFERRER_POLICY, HeaderValue::from_static("no-referrer")),
    ];
    (headers, body).into_response()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The page loads its script and style by the paths served here, and holds no inline
    /// script or handler the policy would block.
    #[test]
    fn page_references_what_is_served_and_nothing_inline() {
        assert!(INDEX.contains(r#"<script src="app.js" defer></script>"#));
        assert!(INDEX.contains(r#"<link rel="stylesheet" href="app.css">"#));
        for inline in ["onclick=", "onload=", "<style", "javascript:", "style="] {
            assert!(!INDEX.contains(inline), "inline {inline} in index.html");
        }
        assert!(!SCRIPT.contains("innerHTML"), "app.js must not parse HTML");
    }
}
