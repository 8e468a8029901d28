//! The HTTP transport (axum): `/v1/jobs…`, SSE events, `/v1/curves:fair`, probes, metrics and
//! the OpenAPI doc.
//!
//! Each handler parses its request into the job core's terms
//! ([`JobSpec`](crate::jobs::JobSpec), [`UploadRef`](crate::jobs::UploadRef)), calls one
//! [`Jobs`](crate::jobs::Jobs) method, and renders the result; every error leaves as a
//! [`Problem`]. The wire shapes here ([`JobView`], [`JobSpec`](crate::jobs::JobSpec)…) are the contract clients
//! outside the repo rely on (issue 3), so they are separate from the core's types and change
//! only deliberately.
//!
//! This file holds the routes, the OpenAPI document, the docs page and the fallback; the rest
//! lives beside it:
//! - `params`: the request shapes (job parameters, query strings) and the query-string parser;
//! - `jobs`: the job routes and [`JobView`];
//! - `events`: Server-Sent Events;
//! - `curves`: `POST /v1/curves:fair`;
//! - `probes`: `/healthz`, `/readyz`, `/metrics`;
//! - `body`: the 413 and 415 policies and bounded body reading and draining;
//! - `range`: single byte ranges on mesh downloads (206, 416);
//! - `head`: 414 and 431 for request heads over the server's limits.
//!
//! The web page's routes (`api::web`) are merged beside these by `api::server::app`.

// `Problem` is large (~170 bytes), and clippy would box it. Errors are the cold path here: at
// most one is built per request, so moving it costs nothing measurable next to the I/O.
#![allow(clippy::result_large_err)]

mod body;
mod curves;
mod events;
mod head;
mod jobs;
mod params;
mod probes;
mod range;
mod spec_query;

pub use super::state::AppState;
pub(super) use body::DRAIN_MAX_BYTES;
pub use body::{problem_for_plain_413, refuse_content_encoding, MULTIPART_SLACK};
pub use curves::{fair_curve, CurveBody, CurveFrameView, CurveParamsView, CurveQuery, CurveResult};
pub use events::{job_events, FrameEvent};
pub use head::{refuse_oversized_head, MAX_HEADERS, MAX_HEADER_BYTES, MAX_URI_BYTES};
pub use jobs::{
    cancel_job, create_job, delete_job, frame_mesh, get_job, job_result, list_frames, list_jobs,
    FrameList, JobList, JobView, LatestMetrics, Links, Progress,
};
pub use params::{EventsQuery, FormatQuery, FramesQuery, ListQuery};
pub use probes::{healthz, metrics, readyz};
pub use spec_query::JobQuery;

use super::auth::SecurityAddon;
use super::problem::Problem;
use crate::jobs::Caller;
use axum::body::Body;
use axum::extract::Request;
use axum::http::{header, HeaderName, StatusCode};
use axum::response::{Html, IntoResponse, Response};
use axum::routing::{get, post};
use axum::Router;
use utoipa::OpenApi;

/// The caller the authentication layer put on the request: every job route takes it. A
/// request without one (a route the layer does not cover) is refused rather than served as
/// anyone: the layer fails closed.
impl<S: Send + Sync> axum::extract::FromRequestParts<S> for Caller {
    type Rejection = Response;

    async fn from_request_parts(
        parts: &mut axum::http::request::Parts,
        _state: &S,
    ) -> Result<Self, Self::Rejection> {
        parts.extensions.get::<Caller>().cloned().ok_or_else(|| {
            Problem::new(
                StatusCode::UNAUTHORIZED,
                "unauthenticated",
                "this route needs credentials and none were checked",
            )
            .into_response()
        })
    }
}

/// The HTTP routes (the REST API, probes, metrics, docs), state applied. The web page's own
/// routes are merged beside them by `api::server::app`.
pub fn routes(state: AppState) -> Router {
    Router::new()
        .route("/v1/jobs", post(create_job).get(list_jobs))
        .route("/v1/jobs/{id}", get(get_job).delete(delete_job))
        .route("/v1/jobs/{id}/cancel", post(cancel_job))
        .route("/v1/jobs/{id}/events", get(job_events))
        .route("/v1/jobs/{id}/frames", get(list_frames))
        .route("/v1/jobs/{id}/frames/{step}", get(frame_mesh))
        .route("/v1/jobs/{id}/result", get(job_result))
        // AIP-136 custom method: a literal colon, not a path parameter.
        .route("/v1/curves:fair", post(fair_curve))
        .route("/healthz", get(healthz))
        .route("/readyz", get(readyz))
        .route("/metrics", get(metrics))
        .route("/openapi.json", get(openapi_json))
        .route("/docs", get(docs))
        .with_state(state)
}

/// What a worker node serves: the probes and its metrics, no API.
pub fn probe_routes(state: AppState) -> Router {
    Router::new()
        .route("/healthz", get(healthz))
        .route("/readyz", get(readyz))
        .route("/metrics", get(metrics))
        .with_state(state)
}

#[derive(OpenApi)]
#[openapi(
    info(title = "Willow fairing service", description = "Mesh fairing by conformal Willmore flow: submit a mesh, watch frames, fetch the result. Errors are RFC 9457 problem details."),
    paths(jobs::create_job, jobs::list_jobs, jobs::get_job, jobs::cancel_job, jobs::delete_job, events::job_events, jobs::list_frames, jobs::frame_mesh, jobs::job_result, curves::fair_curve, probes::healthz, probes::readyz, probes::metrics, super::auth::mint_stream_token),
    modifiers(&SecurityAddon),
    components(schemas(super::auth::StreamToken, JobView, JobList, crate::jobs::JobSpec, crate::jobs::spec::FilterSpec, crate::jobs::spec::DenoiseSpec, crate::jobs::spec::BoundarySpec, crate::jobs::spec::PrescribedSpec, crate::jobs::spec::AxisSpec, crate::jobs::spec::AnglesSpec, super::schema::RegionSchema, super::schema::SeamSchema, super::schema::PreserveSchema, FrameList, FrameEvent, Problem, Progress, LatestMetrics, Links, CurveResult, CurveBody, CurveFrameView, CurveParamsView)),
    tags((name = "jobs", description = "Fairing jobs"), (name = "curves", description = "Curve fairing (paper §5), synchronous"), (name = "ops", description = "Probes and metrics"))
)]
pub struct ApiDoc;

/// The OpenAPI 3.1 document.
pub async fn openapi_json() -> Response {
    match ApiDoc::openapi().to_json() {
        Ok(s) => ([(header::CONTENT_TYPE, "application/json")], s).into_response(),
        Err(e) => Problem::new(StatusCode::INTERNAL_SERVER_ERROR, "internal", e.to_string())
            .into_response(),
    }
}

/// The docs page: a small self-contained page (vendored in the binary, nothing fetched from
/// elsewhere) that renders `/openapi.json`.
pub async fn docs() -> Html<&'static str> {
    Html(include_str!("docs.html"))
}

/// Unknown paths: gRPC clients get `UNIMPLEMENTED` (gRPC status 12, HTTP 200 as the gRPC
/// protocol requires); everyone else a 404 problem.
pub async fn no_route(req: Request<Body>) -> Response {
    let is_grpc = req
        .headers()
        .get(header::CONTENT_TYPE)
        .is_some_and(|v| v.as_bytes().starts_with(b"application/grpc"));
    if is_grpc {
        return (
            StatusCode::OK,
            [
                (header::CONTENT_TYPE, "application/grpc"),
                (HeaderName::from_static("grpc-status"), "12"),
                (HeaderName::from_static("grpc-message"), "unknown method"),
            ],
        )
            .into_response();
    }
    Problem::new(
        StatusCode::NOT_FOUND,
        "no_route",
        format!("no route for {} {}", req.method(), req.uri().path()),
    )
    .instance(req.uri().path().to_string())
    .into_response()
}

/// Entry points for the fuzz targets in `fuzz/` (not an API: hidden from the docs, may change
/// at any time). They run the same code `create_job` runs, minus the network and the job core.
#[doc(hidden)]
pub mod fuzzing {
    use super::Problem;

    /// `POST /v1/jobs?{query}` with, when `params` is given, a multipart `params` part holding
    /// those bytes: the validated job spec, or the problem the client gets. A query that does
    /// not make a valid URI never reaches the handler (hyper refuses the request line), so it
    /// is `Ok(None)`.
    pub fn create_job_params(
        query: &str,
        params: Option<&[u8]>,
    ) -> Result<Option<crate::jobs::JobSpec>, Problem> {
        let Ok(uri) = format!("/v1/jobs?{query}").parse::<axum::http::Uri>() else {
            return Ok(None);
        };
        let query_spec = super::spec_query::spec_from_query(&uri)?;
        let spec = match params {
            None => query_spec,
            Some(text) => {
                if !query.is_empty() {
                    return Err(Problem::bad_request(
                        "invalid_parameter",
                        "parameters in both places",
                    ));
                }
                super::params::spec_from_json(text)?
            }
        };
        spec.validate(crate::api::grpc::fuzzing::default_config())
            .map_err(Problem::from)?;
        Ok(Some(spec))
    }
}
