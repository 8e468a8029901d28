//! The web page (issue 13): `/` and its files under `/ui/`, embedded in the binary.
//!
//! `build.rs` bundles `web/` (the page's own HTML, JS and CSS with three.js and uPlot from npm,
//! pinned by `web/package-lock.json`) into `OUT_DIR/web` and gzips each file; they are
//! included here, so `willow serve` alone serves the page and the page loads nothing from
//! elsewhere. It uses only the public API, plus `/ui/config.json`: the job parameters'
//! defaults and limits, from the same values [`JobSpec::validate`] checks against.

use super::state::AppState;
use crate::jobs::JobSpec;
use axum::extract::{Path, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::{Json, Router};
use serde::Serialize;
use willow::flow::Method;

/// One embedded file of the page.
pub struct Asset {
    pub name: &'static str,
    pub content_type: &'static str,
    /// Strong ETag of `plain` (a hash from the build); the gzip form adds `-gz` inside it.
    pub etag: &'static str,
    pub plain: &'static [u8],
    pub gzip: &'static [u8],
}

include!(concat!(env!("OUT_DIR"), "/web/assets.rs"));

/// Browsers revalidate every time (a 304 when unchanged): file names carry no hash, so a
/// long max-age would keep an old page after an upgrade.
const CACHE_CONTROL: &str = "no-cache";

/// The page's routes, state applied; merged beside the REST routes (so the same layers apply).
pub fn routes(state: AppState) -> Router {
    Router::new()
        .route("/", get(index))
        .route("/ui/config.json", get(config))
        .route("/ui/{file}", get(asset))
        .with_state(state)
}

async fn index(headers: HeaderMap) -> Response {
    serve("index.html", &headers)
}

async fn asset(Path(file): Path<String>, headers: HeaderMap) -> Response {
    serve(&file, &headers)
}

fn serve(name: &str, headers: &HeaderMap) -> Response {
    let Some(asset) = ASSETS.iter().find(|a| a.name == name) else {
        return super::problem::Problem::new(
            StatusCode::NOT_FOUND,
            "no_route",
            format!("no web page file `{name}`"),
        )
        .into_response();
    };
    let gzip = accepts_gzip(headers);
    let etag = if gzip {
        format!("{}-gz\"", asset.etag.trim_end_matches('"'))
    } else {
        asset.etag.to_string()
    };
    let not_modified = headers
        .get(header::IF_NONE_MATCH)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.split(',').any(|t| t.trim() == etag || t.trim() == "*"));
    let mut res = if not_modified {
        StatusCode::NOT_MODIFIED.into_response()
    } else if gzip {
        let mut r = asset.gzip.into_response();
        r.headers_mut()
            .insert(header::CONTENT_ENCODING, HeaderValue::from_static("gzip"));
        r
    } else {
        asset.plain.into_response()
    };
    let h = res.headers_mut();
    h.insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static(asset.content_type),
    );
    h.insert(
        header::CACHE_CONTROL,
        HeaderValue::from_static(CACHE_CONTROL),
    );
    h.insert(header::VARY, HeaderValue::from_static("accept-encoding"));
    if let Ok(v) = HeaderValue::from_str(&etag) {
        h.insert(header::ETAG, v);
    }
    res
}

/// Whether `Accept-Encoding` lists gzip (or `*`) without `q=0`.
fn accepts_gzip(headers: &HeaderMap) -> bool {
    let Some(value) = headers
        .get(header::ACCEPT_ENCODING)
        .and_then(|v| v.to_str().ok())
    else {
        return false;
    };
    value.split(',').any(|item| {
        let mut parts = item.split(';');
        let coding = parts.next().unwrap_or("").trim();
        let refused = parts.any(|p| {
            p.trim()
                .strip_prefix("q=")
                .and_then(|q| q.trim().parse::<f32>().ok())
                .is_some_and(|q| q == 0.0)
        });
        (coding.eq_ignore_ascii_case("gzip") || coding == "*") && !refused
    })
}

/// What the page's form needs to offer exactly the values the API accepts.
#[derive(Serialize)]
struct PageConfig {
    /// A job's parameters when none are given (the API's defaults).
    defaults: JobSpec,
    limits: PageLimits,
    methods: Vec<String>,
}

#[derive(Serialize)]
struct PageLimits {
    max_steps: usize,
    max_upload_bytes: u64,
    max_deadline_secs: f64,
    max_iterations: usize,
    max_filter_k: u32,
    max_frame_angle: f64,
}

async fn config(State(st): State<AppState>) -> Json<PageConfig> {
    let c = st.jobs.config();
    Json(PageConfig {
        defaults: JobSpec::default(),
        limits: PageLimits {
            max_steps: c.limits.max_steps,
            max_upload_bytes: c.limits.max_upload_bytes,
            max_deadline_secs: c.max_deadline.as_secs_f64(),
            max_iterations: crate::jobs::MAX_ITERATIONS,
            max_filter_k: crate::jobs::spec::MAX_FILTER_K,
            max_frame_angle: willow::flow::prescribed::MAX_FRAME_ANGLE,
        },
        methods: Method::ALL.iter().map(|m| m.name().to_string()).collect(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_page_file_is_embedded_with_its_gzip_form() {
        for name in ["index.html", "app.js", "app.css"] {
            let a = ASSETS.iter().find(|a| a.name == name);
            let a = a.unwrap_or_else(|| panic!("{name} is not embedded"));
            assert!(!a.plain.is_empty());
            // gzip magic, and smaller than the plain file for everything but tiny files.
            assert_eq!(&a.gzip[..2], &[0x1f, 0x8b]);
            assert!(a.gzip.len() < a.plain.len());
        }
    }

    #[test]
    fn gzip_is_chosen_only_when_accepted() {
        let with = |v: &str| {
            let mut h = HeaderMap::new();
            h.insert(header::ACCEPT_ENCODING, HeaderValue::from_str(v).unwrap());
            accepts_gzip(&h)
        };
        assert!(with("gzip, deflate, br"));
        assert!(with("br;q=1.0, gzip;q=0.8"));
        assert!(with("*"));
        assert!(!with("gzip;q=0"));
        assert!(!with("br, deflate"));
        assert!(!accepts_gzip(&HeaderMap::new()));
    }
}
