//! Server-Sent Events: a job's `state`, one `frame` per step, then `done`.

use super::jobs::{record_job, JobView};
use super::params::{query, EventsQuery};
use crate::api::download::DownloadBudget;
use crate::api::problem::{clip, Problem};
use crate::api::state::AppState;
use crate::jobs::{Caller, JobEvent};
use axum::extract::{Path, State};
use axum::http::{HeaderMap, Uri};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::Extension;
use base64::Engine as _;
use futures::StreamExt;
use serde::Serialize;
use std::convert::Infallible;
use std::time::Duration;
use utoipa::ToSchema;

/// SSE keep-alive comments every 15 s: shorter than the 30–60 s idle timeouts of common
/// proxies and load balancers, so a quiet stream (a long step) is not cut.
const SSE_KEEPALIVE: Duration = Duration::from_secs(15);

/// The `data` of an SSE `frame` event.
#[derive(Debug, Serialize, ToSchema)]
pub struct FrameEvent {
    pub step: usize,
    #[schema(value_type = Object)]
    pub metrics: willow::metrics::StepMetrics,
    /// Little-endian f32 xyz per vertex in the uploaded file's vertex order, base64, relative
    /// to `origin` when that is present; present at the frame interval when the job includes
    /// positions.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub positions_b64: Option<String>,
    /// With `positions_b64` when the model lies farther from the origin than its own size
    /// (map-grid coordinates): each vertex is `origin` + its f32 offset, added in f64, so the
    /// frame keeps ~1e-7 of the model's size where f32 coordinates would snap to the f32 grid
    /// of their distance (0.5 at 5e6). The same in every frame of a job; absent for a model
    /// around the origin, where `positions_b64` holds the coordinates themselves.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub origin: Option<[f64; 3]>,
    /// Present (true) on step 0 of a job with `refine` or `fill_holes`: the positions are the
    /// refined or filled mesh's
    /// (the file's vertices, then the new ones), not the upload's; fetch its faces and UVs
    /// from `GET /v1/jobs/{id}/frames/0`.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub connectivity_changed: bool,
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
    budget: Option<Extension<DownloadBudget>>,
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
    // A client that does not keep up with the connection's write floor is cut off: the
    // stream ends and its EventSource reconnects with `Last-Event-ID` (see jobs::watch).
    let floor = budget
        .map(|Extension(b)| b.watch_floor())
        .unwrap_or_default();
    let stream = match st.jobs.watch_with_floor(&caller, &id, from, floor).await {
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
                origin: f
                    .positions
                    .as_deref()
                    .filter(|p| !p.at_zero())
                    .map(|p| p.origin),
                positions_b64: f.positions.map(|p| {
                    base64::engine::general_purpose::STANDARD
                        .encode(crate::jobs::codec::f32s_to_bytes(&p.relative))
                }),
                connectivity_changed: f.connectivity_changed,
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
