//! The HTTP transport (axum): `/v1/jobs…`, SSE events, `/v1/curves:fair`, probes, metrics and
//! the OpenAPI doc.
//!
//! Each handler parses its request into the job core's terms ([`JobSpec`], [`UploadRef`]),
//! calls one [`Jobs`] method, and renders the result; every error leaves as a [`Problem`]. The
//! wire shapes here ([`JobView`], [`JobParams`]…) are the contract clients outside the repo rely
//! on (issue 3), so they are separate from the core's types and change only deliberately.

// `Problem` is large (~170 bytes), and clippy would box it. Errors are the cold path here: at
// most one is built per request, so moving it costs nothing measurable next to the I/O.
#![allow(clippy::result_large_err)]

use super::auth::SecurityAddon;
use super::problem::{clip, Problem};
use crate::jobs::curve::{CurveInput, CurveOutcome, CurveSpec};
use crate::jobs::spec::{AnglesSpec, AxisSpec, BoundarySpec, FilterSpec, PrescribedSpec};
use crate::jobs::{
    format_media_type, format_name, parse_format, rfc3339, Caller, JobEvent, JobSpec, JobState,
    JobStatus, UploadRef,
};
use axum::body::Body;
use axum::extract::{FromRequest, Path, Request, State};
use axum::http::{header, HeaderMap, HeaderName, HeaderValue, StatusCode, Uri};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{Html, IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use base64::Engine as _;
use futures::StreamExt;
use serde::{Deserialize, Serialize};
use std::convert::Infallible;
use std::time::Duration;
use utoipa::{IntoParams, OpenApi, ToSchema};
use willow::flow::Method;
use willow::mesh::io::Format;

/// SSE keep-alive comments every 15 s: shorter than the 30–60 s idle timeouts of common
/// proxies and load balancers, so a quiet stream (a long step) is not cut.
const SSE_KEEPALIVE: Duration = Duration::from_secs(15);

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

pub use super::state::AppState;

/// Bytes a multipart upload may carry beyond the mesh itself: boundaries, part headers and the
/// `params` JSON part. 1 MiB is far more than those need and small next to a mesh.
pub const MULTIPART_SLACK: u64 = 1 << 20;

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

// ---------------------------------------------------------------------------------------------
// Wire types

/// Job parameters as JSON: the `params` part of a multipart upload. Every field is optional;
/// the server's defaults fill the rest. The shape is that of a job's reported `params`, so
/// those can be sent again as they are. (A raw upload takes the same parameters in the query
/// string: [`JobQuery`].)
#[derive(Debug, Default, Clone, Deserialize, Serialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct JobParams {
    /// `conformal` (default), `mcf`, `cmcf`, `bilaplacian` or `taubin`.
    pub method: Option<String>,
    /// Flow steps to take (default 20).
    #[schema(minimum = 1)]
    pub steps: Option<usize>,
    /// Time step τ (default 0.5; conformal needs 0 < τ < 1).
    pub tau: Option<f64>,
    /// Inverse iterations per step (default 1).
    pub iterations: Option<usize>,
    /// Keep positions every this many steps (default 1).
    pub frame_interval: Option<usize>,
    /// Send positions in frames (default true).
    pub include_positions: Option<bool>,
    /// Deadline in seconds from submission (default: the server's).
    pub deadline_secs: Option<f64>,
    /// Exactness constraints for genus > 0 (default true). Conformal flow only.
    pub exactness: Option<bool>,
    /// Möbius balancing (default false). Conformal flow only.
    pub mobius_balancing: Option<bool>,
    /// Spectral filter `{"sigma": σ, "k": k}` (default none). Conformal flow only.
    #[schema(value_type = Option<super::schema::FilterSpecSchema>)]
    pub filter: Option<FilterSpec>,
    /// `"free"` (default), `"fixed"`, `"cmc"` or `{"prescribed": {…}}`. Conformal flow only.
    #[schema(value_type = Option<super::schema::BoundarySpecSchema>)]
    pub boundary: Option<BoundarySpec>,
    /// Safeguarded steps: a step that raises W or damages the mesh is retried at a smaller τ
    /// (default true). Every method.
    pub safeguard: Option<bool>,
}

impl JobParams {
    /// The job spec these parameters ask for (validated later by the core).
    pub fn into_spec(self) -> Result<JobSpec, Problem> {
        let mut spec = JobSpec::default();
        if let Some(m) = self.method {
            spec.method = Method::parse(&m).map_err(|e| bad_field("method", e))?;
        }
        if let Some(v) = self.steps {
            spec.steps = v;
        }
        if let Some(v) = self.tau {
            spec.tau = v;
        }
        if let Some(v) = self.iterations {
            spec.iterations = v;
        }
        if let Some(v) = self.frame_interval {
            spec.frame_interval = v;
        }
        if let Some(v) = self.include_positions {
            spec.include_positions = v;
        }
        spec.deadline_secs = self.deadline_secs;
        if let Some(v) = self.exactness {
            spec.exactness = v;
        }
        if let Some(v) = self.mobius_balancing {
            spec.mobius_balancing = v;
        }
        spec.filter = self.filter;
        if let Some(v) = self.boundary {
            spec.boundary = v;
        }
        if let Some(v) = self.safeguard {
            spec.safeguard = v;
        }
        Ok(spec)
    }
}

/// 400 `invalid_parameter` naming `field`, as the core's own parameter errors do.
fn bad_field(field: &str, reason: impl std::fmt::Display) -> Problem {
    Problem::bad_request(
        "invalid_parameter",
        format!("invalid parameter `{field}`: {reason}"),
    )
    .with("field", field)
}

/// Job parameters in the query string of a raw upload. The names are those of [`JobParams`];
/// nested fields are dotted paths (as Google's HTTP transcoding spells them), lists are comma
/// separated: `?filter.sigma=0.01&filter.k=2`,
/// `?boundary=prescribed&boundary.prescribed.frame_angle=0.2&boundary.prescribed.angles.per_loop=0.1,-0.1`.
/// Any `boundary.prescribed.*` parameter implies `boundary=prescribed`.
#[derive(Debug, Default, Clone, Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct JobQuery {
    /// `conformal` (default), `mcf`, `cmcf`, `bilaplacian` or `taubin`.
    pub method: Option<String>,
    /// Flow steps to take (default 20).
    #[param(minimum = 1)]
    pub steps: Option<usize>,
    /// Time step τ (default 0.5; conformal needs 0 < τ < 1).
    pub tau: Option<f64>,
    /// Inverse iterations per step (default 1).
    pub iterations: Option<usize>,
    /// Keep positions every this many steps (default 1).
    pub frame_interval: Option<usize>,
    /// Send positions in frames (default true).
    pub include_positions: Option<bool>,
    /// Deadline in seconds from submission (default: the server's).
    pub deadline_secs: Option<f64>,
    /// Exactness constraints for genus > 0 (default true). Conformal flow only.
    pub exactness: Option<bool>,
    /// Möbius balancing (default false). Conformal flow only.
    pub mobius_balancing: Option<bool>,
    /// Spectral filter strength σ > 0, unitless; needs `filter.k`. Conformal flow only.
    #[serde(rename = "filter.sigma")]
    #[param(rename = "filter.sigma")]
    pub filter_sigma: Option<f64>,
    /// Spectral filter shape k, 0..=3; needs `filter.sigma`.
    #[serde(rename = "filter.k")]
    #[param(rename = "filter.k")]
    pub filter_k: Option<u32>,
    /// `free` (default), `fixed`, `cmc` or `prescribed`. Conformal flow only.
    pub boundary: Option<String>,
    /// Prescribed vectors: φ in radians, |φ| ≤ 1.5 (default 0).
    #[serde(rename = "boundary.prescribed.frame_angle")]
    #[param(rename = "boundary.prescribed.frame_angle")]
    pub frame_angle: Option<f64>,
    /// Prescribed vectors: `tangent` (the default rotation axis).
    #[serde(rename = "boundary.prescribed.axis")]
    #[param(rename = "boundary.prescribed.axis")]
    pub axis: Option<String>,
    /// Prescribed vectors: a fixed rotation axis `x,y,z`, finite and non-zero.
    #[serde(rename = "boundary.prescribed.axis.fixed")]
    #[param(rename = "boundary.prescribed.axis.fixed")]
    pub axis_fixed: Option<String>,
    /// Prescribed vectors: one rotation angle in radians for every boundary vertex (default 0).
    #[serde(rename = "boundary.prescribed.angles.uniform")]
    #[param(rename = "boundary.prescribed.angles.uniform")]
    pub angles_uniform: Option<f64>,
    /// Prescribed vectors: one angle per boundary loop, `a,b,…` (as many as the mesh has loops).
    #[serde(rename = "boundary.prescribed.angles.per_loop")]
    #[param(rename = "boundary.prescribed.angles.per_loop")]
    pub angles_per_loop: Option<String>,
    /// Safeguarded steps: a step that raises W or damages the mesh is retried at a smaller τ
    /// (default true). Every method.
    pub safeguard: Option<bool>,
}

impl JobQuery {
    /// The same parameters in their JSON shape.
    pub fn into_params(self) -> Result<JobParams, Problem> {
        let filter = match (self.filter_sigma, self.filter_k) {
            (None, None) => None,
            (Some(sigma), Some(k)) => Some(FilterSpec { sigma, k }),
            (Some(_), None) => return Err(bad_field("filter.k", "required with `filter.sigma`")),
            (None, Some(_)) => return Err(bad_field("filter.sigma", "required with `filter.k`")),
        };
        let prescribed_given = self.frame_angle.is_some()
            || self.axis.is_some()
            || self.axis_fixed.is_some()
            || self.angles_uniform.is_some()
            || self.angles_per_loop.is_some();
        let boundary = match self.boundary.as_deref().map(str::to_ascii_lowercase) {
            None if !prescribed_given => None,
            None => Some(BoundarySpec::Prescribed(PrescribedSpec::default())),
            Some(name) => Some(match name.as_str() {
                "free" => BoundarySpec::Free,
                "fixed" => BoundarySpec::Fixed,
                "cmc" => BoundarySpec::Cmc,
                "prescribed" => BoundarySpec::Prescribed(PrescribedSpec::default()),
                other => {
                    return Err(bad_field(
                        "boundary",
                        format!("expected `free`, `fixed`, `cmc` or `prescribed`, got `{other}`"),
                    ))
                }
            }),
        };
        let boundary = match boundary {
            Some(BoundarySpec::Prescribed(mut p)) => {
                if let Some(a) = self.frame_angle {
                    p.frame_angle = a;
                }
                p.axis = match (self.axis.as_deref(), self.axis_fixed.as_deref()) {
                    (Some(_), Some(_)) => {
                        return Err(bad_field(
                            "boundary.prescribed.axis",
                            "give either `boundary.prescribed.axis=tangent` or `boundary.prescribed.axis.fixed=x,y,z`, not both",
                        ))
                    }
                    (Some(name), None) if name.eq_ignore_ascii_case("tangent") => {
                        AxisSpec::Tangent
                    }
                    (Some(other), None) => {
                        return Err(bad_field(
                            "boundary.prescribed.axis",
                            format!(
                                "expected `tangent` (a fixed axis is `boundary.prescribed.axis.fixed=x,y,z`), got `{other}`"
                            ),
                        ))
                    }
                    (None, Some(text)) => {
                        let field = "boundary.prescribed.axis.fixed";
                        let v = parse_list(field, text)?;
                        let xyz: [f64; 3] = v.try_into().map_err(|v: Vec<f64>| {
                            bad_field(field, format!("expected 3 numbers x,y,z, got {}", v.len()))
                        })?;
                        AxisSpec::Fixed(xyz)
                    }
                    (None, None) => AxisSpec::Tangent,
                };
                p.angles = match (self.angles_uniform, self.angles_per_loop.as_deref()) {
                    (Some(_), Some(_)) => {
                        return Err(bad_field(
                            "boundary.prescribed.angles",
                            "give either `angles.uniform` or `angles.per_loop`, not both",
                        ))
                    }
                    (Some(a), None) => AnglesSpec::Uniform(a),
                    (None, Some(text)) => AnglesSpec::PerLoop(parse_list(
                        "boundary.prescribed.angles.per_loop",
                        text,
                    )?),
                    (None, None) => AnglesSpec::default(),
                };
                Some(BoundarySpec::Prescribed(p))
            }
            Some(other) if prescribed_given => {
                return Err(bad_field(
                    "boundary",
                    format!(
                        "`boundary.prescribed.*` parameters need `boundary=prescribed`, got `{}`",
                        serde_json::to_string(&other)
                            .unwrap_or_default()
                            .trim_matches('"')
                    ),
                ))
            }
            other => other,
        };
        Ok(JobParams {
            method: self.method,
            steps: self.steps,
            tau: self.tau,
            iterations: self.iterations,
            frame_interval: self.frame_interval,
            include_positions: self.include_positions,
            deadline_secs: self.deadline_secs,
            exactness: self.exactness,
            mobius_balancing: self.mobius_balancing,
            filter,
            boundary,
            safeguard: self.safeguard,
        })
    }
}

/// Comma-separated numbers (`0.1,-0.2`); empty text is an empty list.
fn parse_list(field: &str, text: &str) -> Result<Vec<f64>, Problem> {
    if text.trim().is_empty() {
        return Ok(Vec::new());
    }
    text.split(',')
        .map(|t| {
            t.trim()
                .parse::<f64>()
                .map_err(|_| bad_field(field, format!("`{}` is not a number", t.trim())))
        })
        .collect()
}

#[derive(Debug, Serialize, ToSchema)]
pub struct Progress {
    pub step: usize,
    pub total_steps: usize,
}

#[derive(Debug, Serialize, ToSchema)]
pub struct LatestMetrics {
    /// Metrics of the latest completed step (`null` before the job started).
    #[schema(value_type = Option<Object>)]
    pub latest: Option<willow::metrics::StepMetrics>,
}

#[derive(Debug, Serialize, ToSchema)]
pub struct Links {
    #[serde(rename = "self")]
    pub self_: String,
    pub events: String,
    pub frames: String,
    pub result: String,
    pub cancel: String,
}

/// A job as HTTP clients see it.
#[derive(Debug, Serialize, ToSchema)]
pub struct JobView {
    pub id: String,
    /// `queued`, `running`, `succeeded`, `failed` or `cancelled`.
    pub state: String,
    pub progress: Progress,
    pub metrics: LatestMetrics,
    /// Why the job failed or was cancelled; on a `succeeded` job, why it stopped before
    /// `total_steps` (then `error_code` is `no_progress`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// `deadline_exceeded`, `cancelled`, `numerical`, … for a failed or cancelled job;
    /// `no_progress` on a succeeded job the safeguard stopped early (no acceptable step even at
    /// τ/1024): its result is the last accepted surface, the one after `progress.step`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error_code: Option<String>,
    /// The parameters the job runs with, defaults filled in.
    #[schema(value_type = super::schema::JobSpecSchema)]
    pub params: JobSpec,
    /// `obj`, `glb` or `gltf`.
    pub input_format: String,
    /// Vertices in the uploaded file's order: `positions_b64` decodes to this many f32 xyz.
    pub vertex_count: usize,
    pub face_count: usize,
    /// RFC 3339 UTC.
    pub created_time: String,
    pub started_time: Option<String>,
    pub finished_time: Option<String>,
    /// When a finished job is deleted (then 410 Gone).
    pub expire_time: Option<String>,
    pub links: Links,
}

impl From<JobStatus> for JobView {
    fn from(s: JobStatus) -> JobView {
        let base = format!("/v1/jobs/{}", s.id);
        JobView {
            state: s.state.as_str().to_string(),
            progress: Progress {
                step: s.step,
                total_steps: s.total_steps,
            },
            metrics: LatestMetrics { latest: s.latest },
            error: s.error,
            error_code: s.error_code,
            params: s.spec,
            input_format: format_name(s.input_format).to_string(),
            vertex_count: s.vertex_count,
            face_count: s.face_count,
            created_time: rfc3339(s.created_at),
            started_time: s.started_at.map(rfc3339),
            finished_time: s.finished_at.map(rfc3339),
            expire_time: s.expires_at.map(rfc3339),
            links: Links {
                events: format!("{base}/events"),
                frames: format!("{base}/frames"),
                result: format!("{base}/result"),
                cancel: format!("{base}/cancel"),
                self_: base,
            },
            id: s.id,
        }
    }
}

#[derive(Debug, Serialize, ToSchema)]
pub struct JobList {
    pub jobs: Vec<JobView>,
    /// Pass as `page_token` for the next page; absent on the last page.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub next_page_token: Option<String>,
}

#[derive(Debug, Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct ListQuery {
    /// Only jobs in this state.
    pub state: Option<String>,
    /// 1..1000 (default 50).
    pub page_size: Option<usize>,
    pub page_token: Option<String>,
}

#[derive(Debug, Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct FramesQuery {
    /// First step to return (default 0).
    pub from_step: Option<usize>,
    /// 1..10000 (default 100).
    pub page_size: Option<usize>,
}

#[derive(Debug, Serialize, ToSchema)]
pub struct FrameList {
    /// Metrics of each step, in order (`step` 0 is the input).
    #[schema(value_type = Vec<Object>)]
    pub frames: Vec<willow::metrics::StepMetrics>,
    /// Pass as `from_step` for the next page; absent on the last page.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub next_from_step: Option<usize>,
}

#[derive(Debug, Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct FormatQuery {
    /// `glb`, `gltf` or `obj`. Default: a frame is `glb`; the result is in the input's own
    /// format, as gRPC `DownloadResult` sends it (what you upload is what you get back).
    pub format: Option<String>,
}

#[derive(Debug, Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct EventsQuery {
    /// First step to replay (default 0). The `Last-Event-ID` header, when sent, wins: the
    /// stream resumes after that step.
    pub from_step: Option<usize>,
}

/// The `data` of an SSE `frame` event.
#[derive(Debug, Serialize, ToSchema)]
pub struct FrameEvent {
    pub step: usize,
    #[schema(value_type = Object)]
    pub metrics: willow::metrics::StepMetrics,
    /// Little-endian f32 xyz per vertex in the uploaded file's vertex order, base64; present
    /// at the frame interval when the job includes positions.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub positions_b64: Option<String>,
}

// ---------------------------------------------------------------------------------------------
// Helpers

/// The query string as `T`. Parsed here rather than by axum's `Query`, whose rejection is text
/// without the parameter's name: a type error (`?tau=abc`, `?steps=1.5`) becomes 400
/// `invalid_parameter` with `field` = the parameter, as every other parameter error does.
fn query<T: serde::de::DeserializeOwned>(uri: &Uri) -> Result<T, Problem> {
    let raw = uri.query().unwrap_or("");
    let de = serde_urlencoded::Deserializer::new(form_urlencoded::parse(raw.as_bytes()));
    serde_path_to_error::deserialize(de).map_err(|e| {
        let field = e.path().to_string();
        let inner = e.into_inner().to_string();
        // An unknown parameter has no path (it is not a field of `T`): name it from the message.
        let field = if field.is_empty() || field == "." || field == "?" {
            unknown_field_name(&inner).unwrap_or_default()
        } else {
            field
        };
        if field.is_empty() {
            Problem::bad_request(
                "invalid_parameter",
                format!("invalid query string: {}", clip(&inner)),
            )
        } else {
            bad_field(&field, clip(&inner))
        }
    })
}

/// The name in serde's "unknown field `x`, expected …".
fn unknown_field_name(message: &str) -> Option<String> {
    let rest = message.strip_prefix("unknown field `")?;
    Some(rest.split_once('`')?.0.to_string())
}

/// The requested output format; `None` when the query names none (each route has its default).
fn parse_out_format(q: &FormatQuery) -> Result<Option<Format>, Problem> {
    match &q.format {
        None => Ok(None),
        Some(f) => parse_format(f).map(Some).ok_or_else(|| {
            Problem::bad_request(
                "invalid_parameter",
                format!(
                    "invalid parameter `format`: expected `glb`, `gltf` or `obj`, got `{}`",
                    clip(f)
                ),
            )
            .with("field", "format")
        }),
    }
}

/// The mesh format of a media type (parameters such as `; charset=` ignored).
fn format_of_media_type(ct: &str) -> Option<Format> {
    let essence = ct
        .split(';')
        .next()
        .unwrap_or("")
        .trim()
        .to_ascii_lowercase();
    match essence.as_str() {
        "model/obj" => Some(Format::Obj),
        "model/gltf-binary" => Some(Format::Glb),
        "model/gltf+json" => Some(Format::Gltf),
        _ => None,
    }
}

fn unsupported_media_type(got: &str) -> Problem {
    Problem::new(
        StatusCode::UNSUPPORTED_MEDIA_TYPE,
        "unsupported_media_type",
        format!(
            "Content-Type `{got}` is not accepted: send model/obj, model/gltf-binary or \
             model/gltf+json as the raw body, or multipart/form-data with a `mesh` file part"
        ),
    )
}

fn job_response(status: StatusCode, s: JobStatus) -> Response {
    let location = format!("/v1/jobs/{}", s.id);
    let mut res = (status, Json(JobView::from(s))).into_response();
    if let Ok(v) = HeaderValue::from_str(&location) {
        res.headers_mut().insert(header::LOCATION, v);
    }
    res
}

fn mesh_response(id: &str, name: &str, format: Format, bytes: Vec<u8>) -> Response {
    let mut res = (StatusCode::OK, bytes).into_response();
    let h = res.headers_mut();
    h.insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static(format_media_type(format)),
    );
    if let Ok(v) = HeaderValue::from_str(&format!(
        "attachment; filename=\"{id}-{name}.{}\"",
        format_name(format)
    )) {
        h.insert(header::CONTENT_DISPOSITION, v);
    }
    res
}

fn record_job(id: &str) {
    tracing::Span::current().record("job_id", id);
}

// ---------------------------------------------------------------------------------------------
// Handlers

/// Submit a job: the mesh as the raw body (parameters in the query) or as multipart.
#[utoipa::path(
    post, path = "/v1/jobs", tag = "jobs",
    params(JobQuery,
        ("Idempotency-Key" = Option<String>, Header, description = "Retries with the same key and request return the same job")),
    request_body(description = "The mesh: raw `model/obj`, `model/gltf-binary` or `model/gltf+json`, or `multipart/form-data` with a `mesh` file part and an optional `params` JSON part (same fields as the query)",
        content(
            (Vec<u8> = "model/obj"), (Vec<u8> = "model/gltf-binary"), (Vec<u8> = "model/gltf+json"),
            (Vec<u8> = "multipart/form-data"))),
    responses(
        (status = 202, description = "Accepted; `Location` is the job", body = JobView),
        (status = 400, description = "Bad parameters", body = Problem, content_type = "application/problem+json"),
        (status = 413, description = "Too large (the limit is named)", body = Problem, content_type = "application/problem+json"),
        (status = 415, description = "Unknown content type", body = Problem, content_type = "application/problem+json"),
        (status = 422, description = "Invalid mesh, or idempotency key reused with another request", body = Problem, content_type = "application/problem+json"),
        (status = 429, description = "Queue full; see Retry-After", body = Problem, content_type = "application/problem+json"),
        (status = 503, description = "Shutting down", body = Problem, content_type = "application/problem+json"),
    )
)]
pub async fn create_job(State(st): State<AppState>, caller: Caller, req: Request) -> Response {
    match create_job_inner(&st, &caller, req).await {
        Ok(s) => {
            record_job(&s.id);
            job_response(StatusCode::ACCEPTED, s)
        }
        Err(p) => p.instance("/v1/jobs").into_response(),
    }
}

async fn create_job_inner(
    st: &AppState,
    caller: &Caller,
    req: Request,
) -> Result<JobStatus, Problem> {
    let limit = st.jobs.config().limits.max_upload_bytes;
    let headers = req.headers().clone();
    let key = match headers.get("idempotency-key") {
        None => None,
        Some(v) => Some(
            v.to_str()
                .map_err(|_| {
                    Problem::bad_request(
                        "invalid_parameter",
                        "the Idempotency-Key header must be visible ASCII",
                    )
                    .with("field", "Idempotency-Key")
                })?
                .trim()
                .trim_matches('"')
                .to_string(),
        ),
    };
    let content_type = headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("")
        .to_string();
    if content_type.is_empty() {
        return Err(unsupported_media_type("(none)"));
    }
    if let Some(len) = headers
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<u64>().ok())
    {
        // Multipart adds boundaries and the params part; the mesh part is checked below.
        let allowed = if content_type.starts_with("multipart/") {
            limit + MULTIPART_SLACK
        } else {
            limit
        };
        if len > allowed {
            drain_refused(req.into_body()).await;
            return Err(Problem::from(crate::jobs::JobError::TooLarge {
                what: "upload bytes",
                limit,
            }));
        }
    }
    let query_given = req.uri().query().is_some_and(|q| !q.is_empty());
    let query_params = query::<JobQuery>(req.uri())?.into_params()?;

    let (data, format, params) = if let Some(format) = format_of_media_type(&content_type) {
        let data = read_limited(req.into_body(), limit)
            .await
            .map_err(|_| Problem::too_large("upload bytes", limit))?;
        (data, format, query_params)
    } else if content_type
        .to_ascii_lowercase()
        .starts_with("multipart/form-data")
    {
        // Buffered whole before parsing: it is bounded by the limit and the slack (the mesh
        // part is buffered anyway), and a body that grows past the bound without announcing
        // its length is then drained before its 413 like a raw one, rather than answered
        // mid-upload by the parser's error (a reset connection for the sending client).
        let (parts, body) = req.into_parts();
        let data = read_limited(body, limit.saturating_add(MULTIPART_SLACK))
            .await
            .map_err(|_| Problem::too_large("upload bytes", limit))?;
        let req = Request::from_parts(parts, Body::from(data));
        read_multipart(req, limit, query_params, query_given).await?
    } else {
        return Err(unsupported_media_type(&content_type));
    };
    let spec = params.into_spec()?;
    st.jobs
        .submit(caller, UploadRef::Bytes { data, format }, spec, key)
        .await
        .map_err(Problem::from)
}

async fn read_multipart(
    req: Request,
    limit: u64,
    query_params: JobParams,
    query_given: bool,
) -> Result<(bytes::Bytes, Format, JobParams), Problem> {
    let mut mp = axum::extract::Multipart::from_request(req, &())
        .await
        .map_err(|e| Problem::bad_request("invalid_multipart", e.body_text()))?;
    let mut mesh: Option<(bytes::Bytes, Format)> = None;
    let mut params: Option<JobParams> = None;
    loop {
        let field = match mp.next_field().await {
            Ok(Some(f)) => f,
            Ok(None) => break,
            Err(e) if e.status() == StatusCode::PAYLOAD_TOO_LARGE => {
                return Err(Problem::too_large("upload bytes", limit))
            }
            Err(e) => return Err(Problem::bad_request("invalid_multipart", e.body_text())),
        };
        let name = field.name().unwrap_or("").to_string();
        // A second `mesh` or `params` part would silently replace the first: refuse it, so a
        // client that meant to send one job's worth learns what it actually sent.
        let seen = match name.as_str() {
            "mesh" => mesh.is_some(),
            "params" => params.is_some(),
            _ => false,
        };
        if seen {
            return Err(Problem::bad_request(
                "invalid_multipart",
                format!("more than one `{name}` part: send exactly one"),
            )
            .with("field", name));
        }
        match name.as_str() {
            "mesh" => {
                let by_type = field.content_type().and_then(format_of_media_type);
                let by_name = field
                    .file_name()
                    .and_then(|n| n.rsplit_once('.').and_then(|(_, ext)| parse_format(ext)));
                let shown = field
                    .content_type()
                    .map(str::to_string)
                    .or_else(|| field.file_name().map(str::to_string))
                    .unwrap_or_else(|| "(none)".into());
                let format = by_type.or(by_name).ok_or_else(|| {
                    Problem::new(
                        StatusCode::UNSUPPORTED_MEDIA_TYPE,
                        "unsupported_media_type",
                        format!(
                            "the `mesh` part's type `{shown}` is not a mesh format: give it Content-Type \
                             model/obj, model/gltf-binary or model/gltf+json, or a .obj/.glb/.gltf file name"
                        ),
                    )
                })?;
                let data = field.bytes().await.map_err(|e| {
                    if e.status() == StatusCode::PAYLOAD_TOO_LARGE {
                        Problem::too_large("upload bytes", limit)
                    } else {
                        Problem::bad_request("invalid_multipart", e.body_text())
                    }
                })?;
                if data.len() as u64 > limit {
                    return Err(Problem::too_large("upload bytes", limit));
                }
                mesh = Some((data, format));
            }
            "params" => {
                // Two sources of parameters would have to be merged by rules nobody reads:
                // one request, one place.
                if query_given {
                    return Err(Problem::bad_request(
                        "invalid_parameter",
                        "parameters given both in the `params` part and in the query string: \
                         send them in one place",
                    )
                    .with("field", "params"));
                }
                let text = field
                    .bytes()
                    .await
                    .map_err(|e| Problem::bad_request("invalid_multipart", e.body_text()))?;
                let p: JobParams = serde_json::from_slice(&text).map_err(|e| {
                    Problem::bad_request(
                        "invalid_parameter",
                        format!("the `params` part is not valid job parameters: {e}"),
                    )
                    .with("field", "params")
                })?;
                params = Some(p);
            }
            other => {
                return Err(Problem::bad_request(
                    "invalid_multipart",
                    format!(
                        "unexpected part `{}`: only `mesh` and `params` are accepted",
                        clip(other)
                    ),
                ))
            }
        }
    }
    let (data, format) = mesh.ok_or_else(|| {
        Problem::bad_request("missing_mesh", "the multipart body has no `mesh` file part")
    })?;
    Ok((data, format, params.unwrap_or(query_params)))
}

/// The job's status (poll this).
#[utoipa::path(get, path = "/v1/jobs/{id}", tag = "jobs",
    params(("id" = String, Path)),
    responses((status = 200, description = "The job", body = JobView),
        (status = 404, description = "No such job", body = Problem, content_type = "application/problem+json"),
        (status = 410, description = "Expired", body = Problem, content_type = "application/problem+json")))]
pub async fn get_job(
    State(st): State<AppState>,
    caller: Caller,
    Path(id): Path<String>,
) -> Response {
    record_job(&id);
    match st.jobs.get(&caller, &id).await {
        Ok(s) => (StatusCode::OK, Json(JobView::from(s))).into_response(),
        Err(e) => Problem::from(e)
            .instance(format!("/v1/jobs/{id}"))
            .into_response(),
    }
}

/// Jobs, newest first, paged.
#[utoipa::path(get, path = "/v1/jobs", tag = "jobs", params(ListQuery),
    responses((status = 200, description = "A page of jobs, newest first", body = JobList),
        (status = 400, description = "Bad parameters (`state`, `page_size`, `page_token`; the field is named)", body = Problem, content_type = "application/problem+json")))]
pub async fn list_jobs(State(st): State<AppState>, caller: Caller, uri: Uri) -> Response {
    let run = async {
        let q: ListQuery = query(&uri)?;
        let state = match q.state.as_deref() {
            None | Some("") => None,
            Some(s) => Some(JobState::parse(s).ok_or_else(|| {
                Problem::bad_request(
                    "invalid_parameter",
                    format!("invalid parameter `state`: expected queued, running, succeeded, failed or cancelled, got `{s}`"),
                )
                .with("field", "state")
            })?),
        };
        let (jobs, next) = st
            .jobs
            .list(&caller, state, q.page_size.unwrap_or(0), q.page_token)
            .await?;
        Ok::<_, Problem>(JobList {
            jobs: jobs.into_iter().map(JobView::from).collect(),
            next_page_token: next,
        })
    };
    match run.await {
        Ok(list) => Json(list).into_response(),
        Err(p) => p.instance("/v1/jobs").into_response(),
    }
}

/// Cancel: a queued job is cancelled at once, a running one at its next step.
#[utoipa::path(post, path = "/v1/jobs/{id}/cancel", tag = "jobs",
    params(("id" = String, Path)),
    responses((status = 202, description = "Cancelled, or cancellation requested (a running job stops at its next step)", body = JobView),
        (status = 404, description = "No such job", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "Already finished", body = Problem, content_type = "application/problem+json")))]
pub async fn cancel_job(
    State(st): State<AppState>,
    caller: Caller,
    Path(id): Path<String>,
) -> Response {
    record_job(&id);
    match st.jobs.cancel(&caller, &id).await {
        Ok(s) => job_response(StatusCode::ACCEPTED, s),
        Err(e) => Problem::from(e)
            .instance(format!("/v1/jobs/{id}/cancel"))
            .into_response(),
    }
}

/// Delete a finished job and its files.
#[utoipa::path(delete, path = "/v1/jobs/{id}", tag = "jobs",
    params(("id" = String, Path)),
    responses((status = 204, description = "Deleted"),
        (status = 404, description = "No such job", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "Queued or running", body = Problem, content_type = "application/problem+json")))]
pub async fn delete_job(
    State(st): State<AppState>,
    caller: Caller,
    Path(id): Path<String>,
) -> Response {
    record_job(&id);
    match st.jobs.delete(&caller, &id).await {
        Ok(()) => StatusCode::NO_CONTENT.into_response(),
        Err(e) => Problem::from(e)
            .instance(format!("/v1/jobs/{id}"))
            .into_response(),
    }
}

/// Server-Sent Events: `state`, one `frame` per step (`id:` = step), then `done`.
#[utoipa::path(get, path = "/v1/jobs/{id}/events", tag = "jobs",
    params(("id" = String, Path), EventsQuery,
        ("Last-Event-ID" = Option<String>, Header, description = "Resume after this step")),
    responses((status = 200, description = "text/event-stream; frame data is a FrameEvent", body = FrameEvent, content_type = "text/event-stream"),
        (status = 400, description = "Bad parameters (`from_step`, `Last-Event-ID`; the field is named)", body = Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such job", body = Problem, content_type = "application/problem+json")))]
pub async fn job_events(
    State(st): State<AppState>,
    caller: Caller,
    Path(id): Path<String>,
    headers: HeaderMap,
    uri: Uri,
) -> Response {
    record_job(&id);
    let q: EventsQuery = match query(&uri) {
        Ok(q) => q,
        Err(p) => return p.instance(format!("/v1/jobs/{id}/events")).into_response(),
    };
    // A Last-Event-ID this server never sent (not a step number) is refused: replaying from
    // step 0 instead would hand the client frames it already has as if they were new.
    let last_event = match headers.get("last-event-id") {
        None => None,
        Some(v) => match v.to_str().ok().and_then(|v| v.trim().parse::<usize>().ok()) {
            Some(n) => Some(n),
            None => {
                return Problem::bad_request(
                    "invalid_parameter",
                    format!(
                        "invalid header `Last-Event-ID`: expected the step number of an event \
                         this stream sent, got `{}`",
                        clip(&String::from_utf8_lossy(v.as_bytes()))
                    ),
                )
                .with("field", "Last-Event-ID")
                .instance(format!("/v1/jobs/{id}/events"))
                .into_response()
            }
        },
    };
    let from = match last_event {
        Some(n) => n.saturating_add(1),
        None => q.from_step.unwrap_or(0),
    };
    let stream = match st.jobs.watch(&caller, &id, from).await {
        Ok(s) => s,
        Err(e) => {
            return Problem::from(e)
                .instance(format!("/v1/jobs/{id}/events"))
                .into_response()
        }
    };
    let stop = st.streams_stop.clone();
    let events = stream
        .map(|ev| Ok::<Event, Infallible>(sse_event(ev)))
        .take_until(async move { stop.cancelled().await });
    Sse::new(events)
        .keep_alive(KeepAlive::new().interval(SSE_KEEPALIVE))
        .into_response()
}

fn sse_event(ev: JobEvent) -> Event {
    let (name, data) = match ev {
        JobEvent::State(s) => ("state", serde_json::to_string(&JobView::from(s))),
        JobEvent::Done(s) => ("done", serde_json::to_string(&JobView::from(s))),
        JobEvent::Frame(f) => {
            let data = FrameEvent {
                step: f.step,
                metrics: f.metrics,
                positions_b64: f.positions.map(|p| {
                    base64::engine::general_purpose::STANDARD
                        .encode(crate::jobs::codec::f32s_to_bytes(&p))
                }),
            };
            return Event::default()
                .event("frame")
                .id(f.step.to_string())
                .data(serde_json::to_string(&data).unwrap_or_else(|_| "{}".into()));
        }
    };
    Event::default()
        .event(name)
        .data(data.unwrap_or_else(|_| "{}".into()))
}

/// Metrics of every step, paged by step.
#[utoipa::path(get, path = "/v1/jobs/{id}/frames", tag = "jobs",
    params(("id" = String, Path), FramesQuery),
    responses((status = 200, description = "A page of step metrics", body = FrameList),
        (status = 400, description = "Bad parameters (`page_size`, `page_token`; the field is named)", body = Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such job", body = Problem, content_type = "application/problem+json"),
        (status = 410, description = "Expired", body = Problem, content_type = "application/problem+json")))]
pub async fn list_frames(
    State(st): State<AppState>,
    caller: Caller,
    Path(id): Path<String>,
    uri: Uri,
) -> Response {
    record_job(&id);
    let run = async {
        let q: FramesQuery = query(&uri)?;
        let (frames, next) = st
            .jobs
            .frames(
                &caller,
                &id,
                q.from_step.unwrap_or(0),
                q.page_size.unwrap_or(0),
            )
            .await?;
        Ok::<_, Problem>(FrameList {
            frames,
            next_from_step: next,
        })
    };
    match run.await {
        Ok(list) => Json(list).into_response(),
        Err(p) => p.instance(format!("/v1/jobs/{id}/frames")).into_response(),
    }
}

/// The mesh after one step (steps that kept positions: 0, every frame interval, the last).
#[utoipa::path(get, path = "/v1/jobs/{id}/frames/{step}", tag = "jobs",
    params(("id" = String, Path), ("step" = usize, Path), FormatQuery),
    responses((status = 200, description = "The mesh", content((Vec<u8> = "model/gltf-binary"), (Vec<u8> = "model/gltf+json"), (Vec<u8> = "model/obj"))),
        (status = 400, description = "Bad parameters (`format`, `step`; the field is named)", body = Problem, content_type = "application/problem+json"),
        (status = 404, description = "Unknown job, or a step without positions", body = Problem, content_type = "application/problem+json"),
        (status = 410, description = "Expired", body = Problem, content_type = "application/problem+json")))]
pub async fn frame_mesh(
    State(st): State<AppState>,
    caller: Caller,
    Path((id, step)): Path<(String, String)>,
    uri: Uri,
) -> Response {
    record_job(&id);
    let run = async {
        let step: usize = step.parse().map_err(|_| {
            Problem::bad_request(
                "invalid_parameter",
                format!("invalid step `{step}`: expected a non-negative integer"),
            )
            .with("field", "step")
        })?;
        let format = parse_out_format(&query(&uri)?)?.unwrap_or(Format::Glb);
        let bytes = st.jobs.frame_mesh(&caller, &id, step, format).await?;
        Ok::<_, Problem>(mesh_response(&id, &format!("step{step}"), format, bytes))
    };
    match run.await {
        Ok(r) => r,
        Err(p) => p.instance(uri.path().to_string()).into_response(),
    }
}

/// The faired mesh, with the input's UVs, materials and textures; in the input's format unless
/// `format` asks for another.
#[utoipa::path(get, path = "/v1/jobs/{id}/result", tag = "jobs",
    params(("id" = String, Path), FormatQuery),
    responses((status = 200, description = "The mesh", content((Vec<u8> = "model/gltf-binary"), (Vec<u8> = "model/gltf+json"), (Vec<u8> = "model/obj"))),
        (status = 400, description = "Bad parameters (`format`; the field is named)", body = Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such job", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "Not succeeded (yet)", body = Problem, content_type = "application/problem+json"),
        (status = 410, description = "Expired", body = Problem, content_type = "application/problem+json")))]
pub async fn job_result(
    State(st): State<AppState>,
    caller: Caller,
    Path(id): Path<String>,
    uri: Uri,
) -> Response {
    record_job(&id);
    let run = async {
        let format = match parse_out_format(&query(&uri)?)? {
            Some(f) => f,
            None => st.jobs.get(&caller, &id).await?.input_format,
        };
        let bytes = st.jobs.result(&caller, &id, format).await?;
        Ok::<_, Problem>(mesh_response(&id, "result", format, bytes))
    };
    match run.await {
        Ok(r) => r,
        Err(p) => p.instance(uri.path().to_string()).into_response(),
    }
}

/// Curve fairing parameters (query string of `POST /v1/curves:fair`).
#[derive(Debug, Default, Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct CurveQuery {
    /// Flow steps (default 8; the flow reaches its minimum in about six at τ = 0.5).
    #[param(minimum = 1)]
    pub steps: Option<usize>,
    /// Time step τ, 0 < τ < 1 (default 0.5): unconstrained curvature becomes (1 − 2τ)κ.
    pub tau: Option<f64>,
    /// Also return the points of step 0, every `frame_interval`-th step and the last in
    /// `frames` (default: no frames).
    pub frame_interval: Option<usize>,
    /// Time budget in seconds (default 10, at most 60).
    pub deadline_secs: Option<f64>,
}

/// A planar curve, in the JSON format `POST /v1/curves:fair` and `willow curve` read.
#[derive(Debug, Serialize, ToSchema)]
pub struct CurveBody {
    /// `[x, y]` per point, in order (a closed curve does not repeat its first point).
    pub points: Vec<[f64; 2]>,
    pub closed: bool,
}

/// The points of one step.
#[derive(Debug, Serialize, ToSchema)]
pub struct CurveFrameView {
    pub step: usize,
    pub points: Vec<[f64; 2]>,
}

/// The parameters a curve request ran with, defaults filled in.
#[derive(Debug, Serialize, ToSchema)]
pub struct CurveParamsView {
    #[schema(minimum = 1)]
    pub steps: usize,
    pub tau: f64,
    pub frame_interval: Option<usize>,
    /// The time budget that applied, in seconds.
    pub deadline_secs: f64,
}

/// A faired curve.
#[derive(Debug, Serialize, ToSchema)]
pub struct CurveResult {
    pub params: CurveParamsView,
    /// The faired curve: the input's points (same count and order) moved, same `closed`.
    pub curve: CurveBody,
    /// Per step from 0 (the input): `step`, `energy` (Σκ²ℓ*), `curvature_std_over_mean` (0 for a
    /// circle; `null` when the mean curvature is 0 but κ varies), `max_edge_length_distortion`,
    /// `closure_gap`, `poisson_residual`, `total_length`, `total_curvature`, `step_ms`.
    #[schema(value_type = Vec<Object>)]
    pub metrics: Vec<willow::curve::CurveStepMetrics>,
    /// The kept frames, present when `frame_interval` was given.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub frames: Option<Vec<CurveFrameView>>,
}

impl From<CurveOutcome> for CurveResult {
    fn from(o: CurveOutcome) -> CurveResult {
        CurveResult {
            params: CurveParamsView {
                steps: o.spec.steps,
                tau: o.spec.tau,
                frame_interval: o.spec.frame_interval,
                deadline_secs: o.spec.deadline_secs.unwrap_or_default(),
            },
            frames: o.spec.frame_interval.map(|_| {
                o.frames
                    .into_iter()
                    .map(|f| CurveFrameView {
                        step: f.step,
                        points: f.points,
                    })
                    .collect()
            }),
            curve: CurveBody {
                points: o.curve.points,
                closed: o.curve.closed,
            },
            metrics: o.metrics,
        }
    }
}

/// Fair a planar curve now (isometric curvature flow, paper §5): edge lengths kept, curvature
/// driven to a constant. Synchronous: the flow costs ~0.1 ms a step at 2k points. Runs on a
/// bounded set of blocking slots; when all are busy for a second the answer is 429 with
/// `Retry-After`.
#[utoipa::path(
    post, path = "/v1/curves:fair", tag = "curves",
    params(CurveQuery),
    request_body(description = "The curve: `application/json` (`{\"points\": [[x, y], …], \"closed\": bool}`, or a bare `[[x, y], …]` array, which is open) or `model/obj` (`v` lines and one `l` line; repeating the first index closes it)",
        content((Vec<u8> = "application/json"), (Vec<u8> = "model/obj"))),
    responses(
        (status = 200, description = "The faired curve, per-step metrics and the kept frames", body = CurveResult),
        (status = 400, description = "Bad parameters (the field is named)", body = Problem, content_type = "application/problem+json"),
        (status = 413, description = "Over a limit: `curve bytes`, `curve points` or `steps`", body = Problem, content_type = "application/problem+json"),
        (status = 415, description = "Not JSON or OBJ", body = Problem, content_type = "application/problem+json"),
        (status = 422, description = "A curve the flow cannot take: `too_few_points`, `non_finite`, `zero_length_edge`, `cusp`, `invalid_json`, `invalid_obj` (with `index` or `line`)", body = Problem, content_type = "application/problem+json"),
        (status = 429, description = "Every curve slot busy; see Retry-After", body = Problem, content_type = "application/problem+json"),
        (status = 503, description = "Shutting down", body = Problem, content_type = "application/problem+json"),
        (status = 504, description = "The time budget ran out", body = Problem, content_type = "application/problem+json"),
    )
)]
pub async fn fair_curve(State(st): State<AppState>, req: Request) -> Response {
    match fair_curve_inner(&st, req).await {
        Ok(result) => Json(result).into_response(),
        Err(p) => p.instance("/v1/curves:fair").into_response(),
    }
}

async fn fair_curve_inner(st: &AppState, req: Request) -> Result<CurveResult, Problem> {
    let limit = st.jobs.config().limits.max_curve_bytes;
    let q: CurveQuery = query(req.uri())?;
    let content_type = req
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("")
        .to_string();
    let essence = content_type
        .split(';')
        .next()
        .unwrap_or("")
        .trim()
        .to_ascii_lowercase();
    let obj = match essence.as_str() {
        "application/json" => false,
        "model/obj" => true,
        _ => {
            return Err(Problem::new(
                StatusCode::UNSUPPORTED_MEDIA_TYPE,
                "unsupported_media_type",
                format!(
                    "Content-Type `{}` is not accepted: send the curve as application/json or \
                     model/obj",
                    if content_type.is_empty() {
                        "(none)"
                    } else {
                        &content_type
                    }
                ),
            ))
        }
    };
    let announced = req
        .headers()
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<u64>().ok());
    if announced.is_some_and(|len| len > limit) {
        drain_refused(req.into_body()).await;
        return Err(Problem::too_large("curve bytes", limit));
    }
    let data = read_limited(req.into_body(), limit)
        .await
        .map_err(|_| Problem::too_large("curve bytes", limit))?;
    let input = if obj {
        CurveInput::Obj(data)
    } else {
        CurveInput::Json(data)
    };
    let defaults = CurveSpec::default();
    let spec = CurveSpec {
        steps: q.steps.unwrap_or(defaults.steps),
        tau: q.tau.unwrap_or(defaults.tau),
        frame_interval: q.frame_interval,
        deadline_secs: q.deadline_secs,
    };
    let outcome = st.jobs.fair_curve(input, spec, None).await?;
    Ok(CurveResult::from(outcome))
}

/// Liveness: the process answers.
#[utoipa::path(get, path = "/healthz", tag = "ops", responses((status = 200, description = "ok")))]
pub async fn healthz() -> &'static str {
    "ok"
}

/// Readiness: not draining, workers alive and making progress.
#[utoipa::path(get, path = "/readyz", tag = "ops",
    responses((status = 200, description = "ready"), (status = 503, description = "draining or stalled")))]
pub async fn readyz(State(st): State<AppState>) -> Response {
    if st.jobs.is_ready() {
        (StatusCode::OK, "ready").into_response()
    } else {
        let why = if st.jobs.is_draining() {
            "draining"
        } else if !st.jobs.backend_connected() {
            "backend unreachable"
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

#[derive(OpenApi)]
#[openapi(
    info(title = "Willow fairing service", description = "Mesh fairing by conformal Willmore flow: submit a mesh, watch frames, fetch the result. Errors are RFC 9457 problem details."),
    paths(create_job, list_jobs, get_job, cancel_job, delete_job, job_events, list_frames, frame_mesh, job_result, fair_curve, healthz, readyz, metrics, super::auth::mint_stream_token),
    modifiers(&SecurityAddon),
    components(schemas(super::auth::StreamToken, JobView, JobList, JobParams, super::schema::JobSpecSchema, super::schema::FilterSpecSchema, super::schema::BoundarySpecSchema, super::schema::PrescribedSpecSchema, super::schema::AxisSpecSchema, super::schema::AnglesSpecSchema, FrameList, FrameEvent, Problem, Progress, LatestMetrics, Links, CurveResult, CurveBody, CurveFrameView, CurveParamsView)),
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

/// Turn the errors produced below the handlers into problems: a 413 from tower-http's body
/// limit (plain text, no limit named) and axum's 405 for a known path with another method
/// (empty body). The 405 keeps its `Allow` header.
pub async fn problem_for_plain_413(
    State(limit): State<u64>,
    req: Request<Body>,
    next: axum::middleware::Next,
) -> Response {
    let method = req.method().clone();
    let path = req.uri().path().to_string();
    let res = next.run(req).await;
    let is_problem = res
        .headers()
        .get(header::CONTENT_TYPE)
        .is_some_and(|v| v.as_bytes().starts_with(b"application/problem+json"));
    if is_problem {
        return res;
    }
    match res.status() {
        StatusCode::PAYLOAD_TOO_LARGE => Problem::too_large("request body bytes", limit)
            .instance(path)
            .into_response(),
        StatusCode::METHOD_NOT_ALLOWED => {
            let allow = res.headers().get(header::ALLOW).cloned();
            let allowed = allow
                .as_ref()
                .and_then(|v| v.to_str().ok())
                .unwrap_or("")
                .to_string();
            let mut out = Problem::new(
                StatusCode::METHOD_NOT_ALLOWED,
                "method_not_allowed",
                format!("{method} is not allowed on {path}; allowed: {allowed}"),
            )
            .instance(path)
            .into_response();
            if let Some(v) = allow {
                out.headers_mut().insert(header::ALLOW, v);
            }
            out
        }
        _ => res,
    }
}

/// Entry points for the fuzz targets in `fuzz/` (not an API: hidden from the docs, may change
/// at any time). They run the same code `create_job` runs, minus the network and the job core.
#[doc(hidden)]
pub mod fuzzing {
    use super::{JobParams, JobQuery, Problem};
    use crate::jobs::JobSpec;

    /// `POST /v1/jobs?{query}` with, when `params` is given, a multipart `params` part holding
    /// those bytes: the validated job spec, or the problem the client gets. A query that does
    /// not make a valid URI never reaches the handler (hyper refuses the request line), so it
    /// is `Ok(None)`.
    pub fn create_job_params(
        query: &str,
        params: Option<&[u8]>,
    ) -> Result<Option<JobSpec>, Problem> {
        let Ok(uri) = format!("/v1/jobs?{query}").parse::<axum::http::Uri>() else {
            return Ok(None);
        };
        let query_params = super::query::<JobQuery>(&uri)?.into_params()?;
        let params = match params {
            None => query_params,
            Some(text) => {
                if !query.is_empty() {
                    return Err(Problem::bad_request(
                        "invalid_parameter",
                        "parameters in both places",
                    ));
                }
                serde_json::from_slice::<JobParams>(text).map_err(|e| {
                    Problem::bad_request("invalid_parameter", super::clip(&e.to_string()))
                })?
            }
        };
        let spec = params.into_spec()?;
        spec.validate(crate::api::grpc::fuzzing::default_config())
            .map_err(Problem::from)?;
        Ok(Some(spec))
    }
}

/// How much of a refused oversized body the server still reads before it answers, and for
/// how long. A server that answers 413 and closes while the client is still sending leaves
/// that client a broken pipe instead of the answer (seen in CI: a 120 KB curve against a
/// 64 KB limit). Bounded, so a hostile body costs the server at most this much.
pub(super) const DRAIN_MAX_BYTES: usize = 1 << 20;
const DRAIN_MAX_TIME: Duration = Duration::from_secs(2);

/// Reads and discards up to [`DRAIN_MAX_BYTES`] of `body` within [`DRAIN_MAX_TIME`].
async fn drain_refused(body: Body) {
    drain(body.into_data_stream(), 0).await;
}

async fn drain(mut stream: axum::body::BodyDataStream, mut read: usize) {
    let _ = tokio::time::timeout(DRAIN_MAX_TIME, async {
        while read < DRAIN_MAX_BYTES {
            match stream.next().await {
                Some(Ok(chunk)) => read += chunk.len(),
                _ => break,
            }
        }
    })
    .await;
}

/// The body, or `Err` when it is longer than `limit` bytes; then the rest is drained
/// ([`drain_refused`]) so that the client reads the refusal.
async fn read_limited(body: Body, limit: u64) -> Result<bytes::Bytes, ()> {
    let limit = usize::try_from(limit).unwrap_or(usize::MAX);
    let mut stream = body.into_data_stream();
    let mut data = bytes::BytesMut::new();
    while let Some(chunk) = stream.next().await {
        let chunk = chunk.map_err(|_| ())?;
        if data.len() + chunk.len() > limit {
            drain(stream, 0).await;
            return Err(());
        }
        data.extend_from_slice(&chunk);
    }
    Ok(data.freeze())
}
