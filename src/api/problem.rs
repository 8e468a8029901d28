//! RFC 9457 problem details: every HTTP error leaves through [`Problem`]. A [`JobError`] takes
//! its status from the one table in [`super::status`] and its retry hint from the core; here it
//! gets its body.

use super::status;
use crate::jobs::JobError;
use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use serde::Serialize;
use serde_json::{Map, Value};

/// The media type of problem responses.
pub const PROBLEM_JSON: &str = "application/problem+json";

/// An `application/problem+json` body. `type` is `urn:willow:problem:{code}`, so clients can
/// branch on it (or on the `code` extension) without parsing `detail`.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct Problem {
    #[serde(rename = "type")]
    pub type_: String,
    pub title: String,
    #[serde(serialize_with = "ser_status")]
    #[schema(value_type = u16)]
    pub status: StatusCode,
    /// What exactly was wrong, for people.
    pub detail: String,
    /// The request path.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub instance: Option<String>,
    /// Stable machine-readable code (for meshes: `MeshError::code`).
    pub code: String,
    /// Extension members: `field`, `limit`, `retry_after_secs`, `capacity`, `job_id`…
    #[serde(flatten)]
    #[schema(value_type = Object)]
    pub extensions: Map<String, Value>,
    #[serde(skip)]
    pub retry_after: Option<u64>,
}

fn ser_status<S: serde::Serializer>(s: &StatusCode, ser: S) -> Result<S::Ok, S::Error> {
    ser.serialize_u16(s.as_u16())
}

/// Longest piece of user input (a name, a parameter value, a parser's message about it) echoed
/// in an error: enough to recognise it, and a 1 MB bogus value does not become a 1 MB error.
pub const MAX_ECHO_CHARS: usize = 256;

/// Longest error message (`detail`, `grpc-message`) as a whole: the fixed text plus a few
/// clipped echoes. gRPC sends the message in a header, which proxies and clients cap at 8 to
/// 16 KiB, so this also keeps every status deliverable.
pub const MAX_DETAIL_CHARS: usize = 1024;

/// At most [`MAX_ECHO_CHARS`] characters of `s`, with an ellipsis when cut.
pub fn clip(s: &str) -> String {
    clip_to(s, MAX_ECHO_CHARS)
}

/// An error message capped at [`MAX_DETAIL_CHARS`]: the backstop for any path that echoes
/// user text without clipping it first.
pub fn cap_detail(s: String) -> String {
    if s.chars().count() <= MAX_DETAIL_CHARS {
        s
    } else {
        clip_to(&s, MAX_DETAIL_CHARS)
    }
}

fn clip_to(s: &str, max: usize) -> String {
    if s.chars().count() <= max {
        s.to_string()
    } else {
        let mut out: String = s.chars().take(max).collect();
        out.push('…');
        out
    }
}

impl Problem {
    pub fn new(status: StatusCode, code: &str, detail: impl Into<String>) -> Problem {
        let detail = cap_detail(detail.into());
        Problem {
            type_: format!("urn:willow:problem:{code}"),
            title: status.canonical_reason().unwrap_or("Error").to_string(),
            status,
            detail,
            instance: None,
            code: code.to_string(),
            extensions: Map::new(),
            retry_after: None,
        }
    }

    /// An extension member. Text values are clipped: they are often user input (a job id
    /// from the path, a field name from the query).
    pub fn with(mut self, key: &str, value: impl Into<Value>) -> Problem {
        let value = match value.into() {
            Value::String(s) => Value::String(clip(&s)),
            other => other,
        };
        self.extensions.insert(key.to_string(), value);
        self
    }

    /// The request path (clipped: it holds the client's ids).
    pub fn instance(mut self, path: impl Into<String>) -> Problem {
        self.instance = Some(clip(&path.into()));
        self
    }

    pub fn bad_request(code: &str, detail: impl Into<String>) -> Problem {
        Problem::new(StatusCode::BAD_REQUEST, code, detail)
    }

    /// 413 naming the limit, for bodies refused before they reach the job core.
    pub fn too_large(what: &str, limit: u64) -> Problem {
        Problem::new(
            StatusCode::PAYLOAD_TOO_LARGE,
            "too_large",
            format!("{what} exceeds the limit of {limit}"),
        )
        .with("what", what)
        .with("limit", limit)
    }
}

impl From<JobError> for Problem {
    fn from(e: JobError) -> Problem {
        let status = status::of_error(&e).http;
        let retry_after = e.retry_after_secs();
        let code = e.code();
        let detail = match &e {
            JobError::Unavailable(msg) => {
                tracing::warn!(error = %msg, "backend unavailable");
                "the job backend is unavailable; retry shortly".to_string()
            }
            JobError::StorageFull { detail } => {
                tracing::warn!(error = %detail, "storage full");
                e.to_string()
            }
            JobError::Internal(msg) => {
                // The cause goes to the log, not to the client.
                tracing::error!(error = %msg, "internal error");
                "internal error; see the server log".to_string()
            }
            other => other.to_string(),
        };
        let mut p = Problem::new(status, code, detail);
        p.retry_after = retry_after;
        // Extension members: what the client needs to act, by name.
        match e {
            JobError::NotFound(id) | JobError::Gone(id) => p.with("job_id", id),
            JobError::FrameNotFound { id, step, .. } => p.with("job_id", id).with("step", step),
            JobError::UploadNotFound(id) => p.with("upload_id", id),
            JobError::QueueFull {
                retry_after_secs,
                capacity,
            } => p
                .with("retry_after_secs", retry_after_secs)
                .with("capacity", capacity),
            JobError::QuotaExceeded {
                quota,
                limit,
                used,
                retry_after_secs,
            } => {
                let p = p
                    .with("quota", quota)
                    .with("limit", limit)
                    .with("retry_after_secs", retry_after_secs);
                match used {
                    Some(used) => p.with("used", used),
                    None => p,
                }
            }
            JobError::InvalidSpec { field, .. } => p.with("field", field),
            JobError::TooLarge { what, limit } => p.with("what", what).with("limit", limit),
            JobError::RefineTooLarge {
                what,
                planned,
                limit,
            } => p
                .with("field", "refine")
                .with("what", what)
                .with("planned", planned)
                .with("limit", limit),
            JobError::InvalidCurve(curve) => {
                use willow::curve::CurveError;
                // Where in the input: a point index, or an OBJ line.
                match curve {
                    CurveError::NonFinite { index, .. }
                    | CurveError::ZeroLengthEdge { index }
                    | CurveError::Cusp { index } => p.with("index", index),
                    CurveError::Obj { line, .. } if line > 0 => p.with("line", line),
                    _ => p,
                }
            }
            JobError::Busy {
                retry_after_secs,
                slots,
            } => p
                .with("retry_after_secs", retry_after_secs)
                .with("capacity", slots),
            JobError::DeadlineExceeded { step, steps, .. } => {
                p.with("step", step).with("steps", steps)
            }
            JobError::Numerical { step, .. } => p.with("step", step),
            // As the transports' own `downloads_busy` (api::download::Busy), with the scope
            // that was full: the server's budget, asked by a render.
            JobError::DownloadsBusy {
                retry_after_secs,
                wanted,
                budget,
            } => p
                .with("scope", "render")
                .with("retry_after_secs", retry_after_secs)
                .with("wanted_bytes", wanted)
                .with("budget_bytes", budget),
            JobError::StorageFull { .. } => {
                p.with("retry_after_secs", crate::jobs::STORAGE_FULL_RETRY_SECS)
            }
            JobError::InvalidMesh(_)
            | JobError::Conflict(_)
            | JobError::IdempotencyMismatch(_)
            | JobError::ShuttingDown
            | JobError::Unavailable(_)
            | JobError::Internal(_) => p,
        }
    }
}

impl IntoResponse for Problem {
    fn into_response(self) -> Response {
        let body = serde_json::to_vec(&self).unwrap_or_else(|_| b"{}".to_vec());
        let mut res = (self.status, body).into_response();
        res.headers_mut()
            .insert(header::CONTENT_TYPE, HeaderValue::from_static(PROBLEM_JSON));
        if let Some(secs) = self.retry_after {
            res.headers_mut()
                .insert(header::RETRY_AFTER, HeaderValue::from(secs));
        }
        res
    }
}
