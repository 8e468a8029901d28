//! The job routes: submit (raw or multipart), status, list, cancel, delete, frames and the
//! result, and the job as HTTP clients see it ([`JobView`]).

use super::body::{drain_refused, read_limited, MULTIPART_SLACK};
use super::params::{parse_out_format, query, spec_from_json, FormatQuery, FramesQuery, ListQuery};
use super::range::{self, Answer};
use super::spec_query::JobQuery;
use crate::api::download::{self, Download, DownloadBudget};
use crate::api::problem::{clip, Problem};
use crate::api::state::AppState;
use crate::jobs::{
    format_media_type, format_name, parse_format, rfc3339, Caller, JobSpec, JobState, JobStatus,
    MeshDownload, UploadRef,
};
use axum::body::Body;
use axum::extract::{Extension, FromRequest, Path, Request, State};
use axum::http::{header, HeaderMap, HeaderValue, Method, StatusCode, Uri};
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde::Serialize;
use utoipa::ToSchema;
use willow::mesh::io::Format;

#[derive(Debug, Serialize, ToSchema)]
pub struct Progress {
    pub step: usize,
    pub total_steps: usize,
    /// `step / total_steps × 100`; 100 once the job succeeded (also when it stopped early).
    pub percent_complete: f64,
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
    /// `total_steps` (then `error_code` is its `outcome`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// `deadline_exceeded`, `cancelled`, `numerical`, … for a failed or cancelled job; on a
    /// succeeded job that stopped before `total_steps`, its `outcome` (`converged`,
    /// `no_progress`, …): its result is the surface after `progress.step`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error_code: Option<String>,
    /// How a succeeded job's run ended: `completed` (ran its steps), `converged` (W stopped
    /// falling), `target_reached` (`until_willmore`), `max_deviation` (the next step would have
    /// passed it; the result is the step before), `no_progress` (the safeguard found no
    /// acceptable step), …. Absent until the job has succeeded.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub outcome: Option<String>,
    /// Why, for people.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub outcome_reason: Option<String>,
    /// What `repair` changed in the upload (file numbering): dropped degenerate faces, split
    /// vertices, added surface vertices. Absent without `repair`; stored with the job.
    #[serde(skip_serializing_if = "Option::is_none")]
    #[schema(value_type = Option<Object>)]
    pub repairs: Option<willow::mesh::io::Repairs>,
    /// What the result cannot keep of the upload as it was, for people: e.g. a compressed
    /// glTF written back as plain float attributes, morph targets dropped. Absent when none.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub notes: Vec<String>,
    /// The parameters the job runs with, defaults filled in.
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
        let (outcome, outcome_reason) = s.outcome().unzip();
        JobView {
            repairs: s.repairs.clone(),
            notes: s.notes.clone(),
            outcome,
            outcome_reason,
            state: s.state.as_str().to_string(),
            progress: Progress {
                step: s.step,
                total_steps: s.total_steps,
                percent_complete: s.percent_complete(),
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
            id: s.id.into(),
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

#[derive(Debug, Serialize, ToSchema)]
pub struct FrameList {
    /// Metrics of each step, in order (`step` 0 is the input).
    #[schema(value_type = Vec<Object>)]
    pub frames: Vec<willow::metrics::StepMetrics>,
    /// Pass as `from_step` for the next page; absent on the last page.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub next_from_step: Option<usize>,
}

/// The mesh media types a raw upload may carry (the canonical one of each format; the
/// aliases [`Format::from_mime`] accepts are listed in docs/http.md, `POST /v1/jobs`).
const MESH_MEDIA_TYPES: &str = "model/obj, model/gltf-binary, model/gltf+json, model/stl, \
                                model/x-ply or model/x-off";

/// Is `ct` the generic binary type (or the text type some clients send for any file), for
/// which the content itself decides the format?
fn is_generic_media_type(ct: &str) -> bool {
    let essence = ct.split(';').next().unwrap_or("").trim();
    essence.eq_ignore_ascii_case("application/octet-stream")
}

/// The format of an upload sent as `application/octet-stream`: what its bytes show it is
/// (magic, binary STL length, keywords), or a 415 that says what they are instead.
fn sniffed_format(data: &[u8]) -> Result<Format, Problem> {
    Format::sniff(data).ok_or_else(|| {
        let what = willow::mesh::io::foreign_content(data)
            .map(|w| format!(" (the body is {w})"))
            .unwrap_or_default();
        Problem::new(
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "unsupported_media_type",
            format!(
                "the application/octet-stream body is not a mesh format Willow recognizes{what}: \
                 send it as {MESH_MEDIA_TYPES}"
            ),
        )
    })
}

fn unsupported_media_type(got: &str) -> Problem {
    Problem::new(
        StatusCode::UNSUPPORTED_MEDIA_TYPE,
        "unsupported_media_type",
        format!(
            "Content-Type `{got}` is not accepted: send {MESH_MEDIA_TYPES} (or \
             application/octet-stream, recognized by content) as the raw body, or \
             multipart/form-data with a `mesh` file part"
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

fn mesh_response(
    id: &str,
    name: &str,
    format: Format,
    download: Download,
    content_range: Option<String>,
) -> Response {
    let status = if content_range.is_some() {
        StatusCode::PARTIAL_CONTENT
    } else {
        StatusCode::OK
    };
    let mut res = (status, download.into_body()).into_response();
    let h = res.headers_mut();
    h.insert(header::ACCEPT_RANGES, HeaderValue::from_static("bytes"));
    if let Some(v) = content_range.and_then(|r| HeaderValue::from_str(&r).ok()) {
        h.insert(header::CONTENT_RANGE, v);
    }
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

/// A mesh download as the request's `Range` asks (see `range`): the whole file (200), one
/// byte range of it (206), or 416 for a range past its end. The range is cut before the
/// download starts, so its charge and deadline are the range's.
async fn ranged(
    budget: Option<&DownloadBudget>,
    data: MeshDownload,
    headers: &HeaderMap,
    asked: Option<range::Asked>,
    (id, name, format): (&str, &str, Format),
) -> Result<Response, Problem> {
    let len = data.len();
    match range::answer(asked, len) {
        Answer::Whole => {
            let download = download::start(budget, data).await?;
            Ok(mesh_response(id, name, format, download, None))
        }
        Answer::Part { first, last } => {
            let download = download::start(budget, data.range(first, last)).await?;
            let content_range = format!("bytes {first}-{last}/{len}");
            Ok(mesh_response(
                id,
                name,
                format,
                download,
                Some(content_range),
            ))
        }
        Answer::Unsatisfiable => {
            let asked = headers
                .get(header::RANGE)
                .map(|v| String::from_utf8_lossy(v.as_bytes()).into_owned())
                .unwrap_or_default();
            let mut res = Problem::new(
                StatusCode::RANGE_NOT_SATISFIABLE,
                "range_not_satisfiable",
                format!(
                    "`Range: {}` starts at or past the end of this download, which is {len} bytes",
                    clip(&asked)
                ),
            )
            .with("field", "Range")
            .with("length", len)
            .into_response();
            let h = res.headers_mut();
            h.insert(header::ACCEPT_RANGES, HeaderValue::from_static("bytes"));
            if let Ok(v) = HeaderValue::from_str(&format!("bytes */{len}")) {
                h.insert(header::CONTENT_RANGE, v);
            }
            Ok(res)
        }
    }
}

pub(super) fn record_job(id: &str) {
    tracing::Span::current().record("job_id", id);
}

/// Submit a job: the mesh as the raw body (parameters in the query) or as multipart.
#[utoipa::path(
    post, path = "/v1/jobs", tag = "jobs",
    params(JobQuery,
        ("Idempotency-Key" = Option<String>, Header, description = "Retries with the same key and request return the same job")),
    request_body(description = "The mesh: raw `model/obj`, `model/gltf-binary`, `model/gltf+json`, `model/stl` (also `application/sla`, `application/vnd.ms-pki.stl`), `model/x-ply` (also `application/ply`) or `model/x-off` (PLY and OFF have no registered type), or `application/octet-stream` recognized by its content; or `multipart/form-data` with a `mesh` file part (typed, or named `.obj/.gltf/.glb/.stl/.ply/.off`) and an optional `params` JSON part (same fields as the query)",
        content(
            (Vec<u8> = "model/obj"), (Vec<u8> = "model/gltf-binary"), (Vec<u8> = "model/gltf+json"),
            (Vec<u8> = "model/stl"), (Vec<u8> = "model/x-ply"), (Vec<u8> = "model/x-off"),
            (Vec<u8> = "application/octet-stream"), (Vec<u8> = "multipart/form-data"))),
    responses(
        (status = 202, description = "Accepted; `Location` is the job", body = JobView),
        (status = 400, description = "Bad parameters", body = Problem, content_type = "application/problem+json"),
        (status = 413, description = "Too large (the limit is named)", body = Problem, content_type = "application/problem+json"),
        (status = 415, description = "Unknown content type", body = Problem, content_type = "application/problem+json"),
        (status = 422, description = "Invalid mesh, or idempotency key reused with another request", body = Problem, content_type = "application/problem+json"),
        (status = 429, description = "Queue full; see Retry-After", body = Problem, content_type = "application/problem+json"),
        (status = 503, description = "Shutting down", body = Problem, content_type = "application/problem+json"),
        (status = 507, description = "The server's disk is full (`storage_full`); see Retry-After", body = Problem, content_type = "application/problem+json"),
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
    let query_spec = super::spec_query::spec_from_query(req.uri())?;

    let (data, format, spec) = if let Some(format) = Format::from_mime(&content_type) {
        let data = read_limited(req.into_body(), limit)
            .await
            .map_err(|_| Problem::too_large("upload bytes", limit))?;
        (data, format, query_spec)
    } else if is_generic_media_type(&content_type) {
        let data = read_limited(req.into_body(), limit)
            .await
            .map_err(|_| Problem::too_large("upload bytes", limit))?;
        let format = sniffed_format(&data)?;
        (data, format, query_spec)
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
        read_multipart(req, limit, query_spec, query_given).await?
    } else {
        return Err(unsupported_media_type(&content_type));
    };
    st.jobs
        .submit(caller, UploadRef::Bytes { data, format }, spec, key)
        .await
        .map_err(Problem::from)
}

async fn read_multipart(
    req: Request,
    limit: u64,
    query_spec: JobSpec,
    query_given: bool,
) -> Result<(bytes::Bytes, Format, JobSpec), Problem> {
    let mut mp = axum::extract::Multipart::from_request(req, &())
        .await
        .map_err(|e| Problem::bad_request("invalid_multipart", e.body_text()))?;
    let mut mesh: Option<(bytes::Bytes, Format)> = None;
    let mut params: Option<JobSpec> = None;
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
                let by_type = field.content_type().and_then(Format::from_mime);
                let by_name = field
                    .file_name()
                    .and_then(|n| n.rsplit_once('.').and_then(|(_, ext)| parse_format(ext)));
                let shown = field
                    .content_type()
                    .map(str::to_string)
                    .or_else(|| field.file_name().map(str::to_string))
                    .unwrap_or_else(|| "(none)".into());
                // Browsers send `application/octet-stream` (or nothing) for .stl/.ply/.off:
                // the type, then the file name, then the content decide.
                let generic = field.content_type().is_none_or(is_generic_media_type);
                let declared = by_type.or(by_name);
                if declared.is_none() && !generic {
                    return Err(Problem::new(
                        StatusCode::UNSUPPORTED_MEDIA_TYPE,
                        "unsupported_media_type",
                        format!(
                            "the `mesh` part's type `{shown}` is not a mesh format: give it Content-Type \
                             {MESH_MEDIA_TYPES}, or a .obj/.glb/.gltf/.stl/.ply/.off file name"
                        ),
                    ));
                }
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
                let format = match declared {
                    Some(f) => f,
                    None => sniffed_format(&data)?,
                };
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
                let p = spec_from_json(&text)?;
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
    Ok((data, format, params.unwrap_or(query_spec)))
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
            // Any case, as every name the API defines (`method`, `format`, `boundary`…) and
            // as gRPC's `state=QUEUED` filter; the stored names are lower case.
            Some(s) => Some(JobState::parse(&s.to_ascii_lowercase()).ok_or_else(|| {
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
    params(("id" = String, Path), ("step" = usize, Path), FormatQuery, ("Range" = Option<String>, Header, description = "One byte range, `bytes=first-last`, `bytes=first-` or `bytes=-suffix`, to resume a download (206); several ranges, another unit or an `If-Range` header are ignored (200, the whole file)")),
    responses((status = 200, description = "The mesh (`Accept-Ranges: bytes`)", content((Vec<u8> = "model/gltf-binary"), (Vec<u8> = "model/gltf+json"), (Vec<u8> = "model/obj"), (Vec<u8> = "model/stl"), (Vec<u8> = "model/x-ply"), (Vec<u8> = "model/x-off"))),
        (status = 206, description = "One byte range of the mesh (`Range`), with `Content-Range`", content((Vec<u8> = "model/gltf-binary"), (Vec<u8> = "model/gltf+json"), (Vec<u8> = "model/obj"), (Vec<u8> = "model/stl"), (Vec<u8> = "model/x-ply"), (Vec<u8> = "model/x-off"))),
        (status = 400, description = "Bad parameters (`format`, `step`; the field is named)", body = Problem, content_type = "application/problem+json"),
        (status = 404, description = "Unknown job, or a step without positions", body = Problem, content_type = "application/problem+json"),
        (status = 410, description = "Expired", body = Problem, content_type = "application/problem+json"),
        (status = 416, description = "The `Range` starts at or past the end (`range_not_satisfiable`; `Content-Range: bytes */length`)", body = Problem, content_type = "application/problem+json"),
        (status = 503, description = "No room in the download memory budget (`downloads_busy`; `scope`: `connection` or `server` for downloads waiting to be read, `render` for a first render that found no room in time; `Retry-After`)", body = Problem, content_type = "application/problem+json")))]
pub async fn frame_mesh(
    State(st): State<AppState>,
    caller: Caller,
    Path((id, step)): Path<(String, String)>,
    budget: Option<Extension<DownloadBudget>>,
    method: Method,
    headers: HeaderMap,
    uri: Uri,
) -> Response {
    record_job(&id);
    let run = async {
        let asked = range::asked(&method, &headers);
        let step: usize = step.parse().map_err(|_| {
            Problem::bad_request(
                "invalid_parameter",
                format!("invalid step `{step}`: expected a non-negative integer"),
            )
            .with("field", "step")
        })?;
        let format = parse_out_format(&query(&uri)?)?.unwrap_or(Format::Glb);
        let budget = budget.as_ref().map(|Extension(b)| b);
        // Refused before rendering when no budget is left: a refusal costs nothing.
        budget.map(DownloadBudget::check).transpose()?;
        let bytes = st
            .jobs
            .frame_download(
                &caller,
                &id,
                step,
                format,
                budget.map(DownloadBudget::memory),
            )
            .await?;
        let name = format!("step{step}");
        ranged(budget, bytes, &headers, asked, (&id, &name, format)).await
    };
    match run.await {
        Ok(r) => r,
        Err(p) => p.instance(uri.path().to_string()).into_response(),
    }
}

/// The faired mesh, with the input's UVs, materials and textures; in the input's format unless
/// `format` asks for another.
#[utoipa::path(get, path = "/v1/jobs/{id}/result", tag = "jobs",
    params(("id" = String, Path), FormatQuery, ("Range" = Option<String>, Header, description = "One byte range, `bytes=first-last`, `bytes=first-` or `bytes=-suffix`, to resume a download (206); several ranges, another unit or an `If-Range` header are ignored (200, the whole file)")),
    responses((status = 200, description = "The mesh (`Accept-Ranges: bytes`)", content((Vec<u8> = "model/gltf-binary"), (Vec<u8> = "model/gltf+json"), (Vec<u8> = "model/obj"), (Vec<u8> = "model/stl"), (Vec<u8> = "model/x-ply"), (Vec<u8> = "model/x-off"))),
        (status = 206, description = "One byte range of the mesh (`Range`), with `Content-Range`", content((Vec<u8> = "model/gltf-binary"), (Vec<u8> = "model/gltf+json"), (Vec<u8> = "model/obj"), (Vec<u8> = "model/stl"), (Vec<u8> = "model/x-ply"), (Vec<u8> = "model/x-off"))),
        (status = 400, description = "Bad parameters (`format`; the field is named)", body = Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such job", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "Not succeeded (yet)", body = Problem, content_type = "application/problem+json"),
        (status = 410, description = "Expired", body = Problem, content_type = "application/problem+json"),
        (status = 416, description = "The `Range` starts at or past the end (`range_not_satisfiable`; `Content-Range: bytes */length`)", body = Problem, content_type = "application/problem+json"),
        (status = 503, description = "No room in the download memory budget (`downloads_busy`; `scope`: `connection` or `server` for downloads waiting to be read, `render` for a first render that found no room in time; `Retry-After`)", body = Problem, content_type = "application/problem+json")))]
pub async fn job_result(
    State(st): State<AppState>,
    caller: Caller,
    Path(id): Path<String>,
    budget: Option<Extension<DownloadBudget>>,
    method: Method,
    headers: HeaderMap,
    uri: Uri,
) -> Response {
    record_job(&id);
    let run = async {
        let asked = range::asked(&method, &headers);
        let budget = budget.as_ref().map(|Extension(b)| b);
        budget.map(DownloadBudget::check).transpose()?;
        let format = match parse_out_format(&query(&uri)?)? {
            Some(f) => f,
            None => st.jobs.get(&caller, &id).await?.input_format,
        };
        let bytes = st
            .jobs
            .result_download(&caller, &id, format, budget.map(DownloadBudget::memory))
            .await?;
        ranged(budget, bytes, &headers, asked, (&id, "result", format)).await
    };
    match run.await {
        Ok(r) => r,
        Err(p) => p.instance(uri.path().to_string()).into_response(),
    }
}
