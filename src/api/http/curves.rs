//! `POST /v1/curves:fair`: planar curve fairing, synchronous.

use super::body::{drain_refused, read_limited};
use super::params::query;
use crate::api::problem::Problem;
use crate::api::state::AppState;
use crate::jobs::curve::{CurveInput, CurveOutcome, CurveSpec};
use axum::extract::{Request, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};

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
