//! The probes and metrics: `/healthz`, `/readyz`, `/metrics` (also all a worker node serves).

use crate::api::state::AppState;
use axum::extract::State;
use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};

/// Liveness: the process answers.
#[utoipa::path(get, path = "/healthz", tag = "ops", responses((status = 200, description = "ok")))]
pub async fn healthz() -> &'static str {
    "ok"
}

/// Readiness: not draining, workers alive and making progress.
#[utoipa::path(get, path = "/readyz", tag = "ops",
    responses((status = 200, description = "ready"), (status = 503, description = "draining, backend unreachable, storage full or stalled")))]
pub async fn readyz(State(st): State<AppState>) -> Response {
    if st.jobs.is_ready() {
        (StatusCode::OK, "ready").into_response()
    } else {
        let why = if st.jobs.is_draining() {
            "draining"
        } else if !st.jobs.backend_connected() {
            "backend unreachable"
        } else if st.jobs.storage_full() {
            "storage full"
        } else {
            "workers stalled"
        };
        (StatusCode::SERVICE_UNAVAILABLE, why).into_response()
    }
}

/// Prometheus metrics (OpenMetrics text).
#[utoipa::path(get, path = "/metrics", tag = "ops", responses((status = 200, description = "OpenMetrics text")))]
pub async fn metrics(State(st): State<AppState>) -> Response {
    let mut res = st.jobs.metrics_text().into_response();
    res.headers_mut().insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("application/openmetrics-text; version=1.0.0; charset=utf-8"),
    );
    res
}
