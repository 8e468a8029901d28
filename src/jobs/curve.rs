//! Synchronous curve fairing: the isometric curvature flow of planar polylines (paper §5) as
//! one request and one answer, for every transport.
//!
//! Why not a job: a curve step costs about 0.1 ms at 2k points, so a whole request (parse,
//! a few hundred steps, answer) takes milliseconds, less than storing a job and polling it
//! would. What it shares with jobs is the discipline:
//!
//! - **Bounded CPU.** The flow runs on a blocking thread, never on the async runtime, behind a
//!   semaphore of [`Config::curve_slots`] permits. The permits are separate from the job
//!   workers because a mesh job may hold its worker for hours; sharing them would make a cheap
//!   curve wait behind it. A request that finds every permit taken waits at most
//!   [`SLOT_WAIT`] (and never past its deadline), then gets [`JobError::Busy`] (HTTP 429,
//!   gRPC RESOURCE_EXHAUSTED, both with a retry delay) instead of queueing without bound.
//! - **Named limits.** Points, steps, file bytes and the points carried by frames are each
//!   limited ([`JobLimits`]); a request over one is refused before the flow starts.
//! - **A deadline.** Checked between steps like a job's ([`Config::curve_default_deadline`],
//!   at most [`Config::curve_max_deadline`], and never later than the client's own deadline);
//!   past it the request fails with [`JobError::DeadlineExceeded`]. A client that goes away
//!   (its future dropped) stops the flow at the next step too, and a server shutting down stops
//!   it with [`JobError::ShuttingDown`].
//! - **Hostile input is an error, never a panic.** Parsing and validation are the library's
//!   ([`Curve::from_json`], [`Curve::from_obj`], [`Curve::new`]): too few points, NaN or
//!   infinite coordinates, repeated points (a closed curve that repeats its first point at the
//!   end has a zero-length edge), cusps. Positions that stop being finite fail the request
//!   with [`JobError::Numerical`].

use super::{join_err, Config, JobError, JobLimits, Jobs};
use bytes::Bytes;
use serde::Serialize;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};
use tokio_util::sync::CancellationToken;
use willow::curve::{Curve, CurveError, CurveFlow, CurveParams, CurveStepMetrics};

/// Longest a request waits for a curve slot. Requests take milliseconds, so a slot frees up
/// quickly unless the server is saturated, and then a prompt 429 is more useful than a hang.
pub const SLOT_WAIT: Duration = Duration::from_secs(1);

/// `Retry-After` of a [`JobError::Busy`]: one request's worth of time, rounded up.
const BUSY_RETRY_SECS: u64 = 1;

/// Steps a curve request takes when it names none (the same as `willow curve`).
pub const DEFAULT_CURVE_STEPS: usize = 8;

/// The curve to fair, as a transport received it.
pub enum CurveInput {
    /// `{"points": [[x, y], …], "closed": bool}`, or a bare `[[x, y], …]` array (open): the
    /// format `willow curve` reads ([`Curve::from_json`]).
    Json(Bytes),
    /// OBJ `v` lines and one `l` line; repeating the first index closes the curve
    /// ([`Curve::from_obj`]).
    Obj(Bytes),
    /// Points the transport already decoded.
    Points { points: Vec<[f64; 2]>, closed: bool },
}

/// What to run on a curve. Transports fill it from their parameters; [`Jobs::fair_curve`]
/// validates it.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct CurveSpec {
    /// Flow steps (≥ 1, at most [`JobLimits::max_curve_steps`]).
    pub steps: usize,
    /// Time step with the paper's meaning (§4): unconstrained curvature becomes (1 − 2τ)κ each
    /// step, so 0 < τ < 1; 0.5 removes it in one step.
    pub tau: f64,
    /// Return the points every `frame_interval`-th step (and step 0 and the last) in
    /// [`CurveOutcome::frames`]; `None` returns only the final curve.
    pub frame_interval: Option<usize>,
    /// Time budget in seconds; `None` takes [`Config::curve_default_deadline`]. The outcome
    /// reports the budget that applied.
    pub deadline_secs: Option<f64>,
}

impl Default for CurveSpec {
    fn default() -> Self {
        CurveSpec {
            steps: DEFAULT_CURVE_STEPS,
            tau: CurveParams::default().tau,
            frame_interval: None,
            deadline_secs: None,
        }
    }
}

impl CurveSpec {
    /// Check every field against the server's limits; the error names the field.
    pub fn validate(&self, config: &Config) -> Result<(), JobError> {
        let bad =
            |field: &'static str, reason: String| Err(JobError::InvalidSpec { field, reason });
        if self.steps == 0 {
            return bad("steps", "must be at least 1".into());
        }
        if self.steps > config.limits.max_curve_steps {
            return Err(JobError::TooLarge {
                what: "steps",
                limit: config.limits.max_curve_steps as u64,
            });
        }
        // §4: the factor (1 − 2τ) must stay inside (−1, 1).
        if !(self.tau > 0.0 && self.tau < 1.0) {
            return bad(
                "tau",
                format!(
                    "must be > 0 and < 1 (paper §4: κ ← (1 − 2τ)κ), got {}",
                    self.tau
                ),
            );
        }
        if self.frame_interval == Some(0) {
            return bad("frame_interval", "must be at least 1 when given".into());
        }
        if let Some(d) = self.deadline_secs {
            let max = config.curve_max_deadline.as_secs_f64();
            if !(d.is_finite() && d > 0.0) {
                return bad(
                    "deadline_secs",
                    format!("must be a finite number > 0, got {d}"),
                );
            }
            if d > max {
                return bad(
                    "deadline_secs",
                    format!("must be at most {max} (the server's maximum for curves), got {d}"),
                );
            }
        }
        Ok(())
    }

    /// Steps whose points a response carries: 0, every `frame_interval`-th, and the last.
    pub fn keeps_frame(&self, step: usize) -> bool {
        match self.frame_interval {
            Some(k) => step.is_multiple_of(k.max(1)) || step == self.steps,
            None => false,
        }
    }

    /// How many frames [`CurveSpec::keeps_frame`] keeps.
    pub fn frame_count(&self) -> usize {
        match self.frame_interval {
            Some(k) => {
                let k = k.max(1);
                self.steps / k + 1 + usize::from(!self.steps.is_multiple_of(k))
            }
            None => 0,
        }
    }
}

/// The points of one step.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct CurveFrame {
    pub step: usize,
    pub points: Vec<[f64; 2]>,
}

/// A faired curve and how it got there.
#[derive(Clone, Debug)]
pub struct CurveOutcome {
    /// The spec that ran, defaults filled in (`deadline_secs` is the budget that applied).
    pub spec: CurveSpec,
    /// The final curve (same point count and order as the input, same `closed`).
    pub curve: Curve,
    /// Metrics of step 0 (the input) through the last step.
    pub metrics: Vec<CurveStepMetrics>,
    /// The kept frames, when the spec asked for them.
    pub frames: Vec<CurveFrame>,
}

pub use super::error::curve_error_code;

/// Why a run stopped early.
enum Stop {
    Cancelled,
    Shutdown,
}

impl Jobs {
    /// Fair a curve now: validate, take a curve slot, run the flow on a blocking thread, answer.
    /// `client_deadline` (a gRPC `grpc-timeout`, say) shortens the budget further. Dropping the
    /// returned future stops the flow at its next step.
    pub async fn fair_curve(
        &self,
        input: CurveInput,
        spec: CurveSpec,
        client_deadline: Option<Duration>,
    ) -> Result<CurveOutcome, JobError> {
        let start = Instant::now();
        if self.inner.draining.load(Ordering::SeqCst) {
            return Err(JobError::ShuttingDown);
        }
        let config = &self.inner.config;
        spec.validate(config)?;
        let limits = config.limits.clone();
        // Refuse what is plainly over a limit before waiting for a slot.
        match &input {
            CurveInput::Json(b) | CurveInput::Obj(b) if b.len() as u64 > limits.max_curve_bytes => {
                return Err(JobError::TooLarge {
                    what: "curve bytes",
                    limit: limits.max_curve_bytes,
                })
            }
            CurveInput::Points { points, .. } if points.len() > limits.max_curve_points => {
                return Err(JobError::TooLarge {
                    what: "curve points",
                    limit: limits.max_curve_points as u64,
                })
            }
            _ => {}
        }
        let budget = spec
            .deadline_secs
            .map(Duration::from_secs_f64)
            .unwrap_or(config.curve_default_deadline);
        let budget = client_deadline.map_or(budget, |c| c.min(budget));
        let deadline = start + budget;
        let spec = CurveSpec {
            deadline_secs: Some(budget.as_secs_f64()),
            ..spec
        };

        let wait = SLOT_WAIT.min(deadline.saturating_duration_since(Instant::now()));
        let slots = self.inner.curve_slots.clone();
        let permit = match tokio::time::timeout(wait, slots.acquire_owned()).await {
            Ok(Ok(permit)) => permit,
            // The semaphore is never closed; treat it like a full house all the same.
            Ok(Err(_)) | Err(_) => {
                return Err(JobError::Busy {
                    retry_after_secs: BUSY_RETRY_SECS,
                    slots: config.curve_slots,
                })
            }
        };
        // Cancelled when this future is dropped (the client went away): the blocking thread
        // sees it at the next step and frees the slot.
        let cancel = CancellationToken::new();
        let _stop_on_drop = cancel.clone().drop_guard();
        let shutdown = self.inner.shutdown.clone();
        let outcome = tokio::task::spawn_blocking(move || {
            let _permit = permit;
            let stop = || {
                if cancel.is_cancelled() {
                    Some(Stop::Cancelled)
                } else if shutdown.is_cancelled() {
                    Some(Stop::Shutdown)
                } else {
                    None
                }
            };
            run(input, spec, &limits, deadline, stop)
        })
        .await
        .map_err(join_err)?;
        tracing::debug!(
            elapsed_ms = start.elapsed().as_secs_f64() * 1e3,
            ok = outcome.is_ok(),
            "curve request"
        );
        outcome
    }
}

/// Parse, check the limits that need the curve, and run the flow (on a blocking thread).
fn run(
    input: CurveInput,
    spec: CurveSpec,
    limits: &JobLimits,
    deadline: Instant,
    stop: impl Fn() -> Option<Stop>,
) -> Result<CurveOutcome, JobError> {
    let curve = match input {
        CurveInput::Json(b) => Curve::from_json(&b),
        CurveInput::Obj(b) => Curve::from_obj(&b),
        CurveInput::Points { points, closed } => Curve::new(points, closed),
    }
    .map_err(JobError::InvalidCurve)?;
    let n = curve.points.len();
    if n > limits.max_curve_points {
        return Err(JobError::TooLarge {
            what: "curve points",
            limit: limits.max_curve_points as u64,
        });
    }
    let frame_points = spec.frame_count().saturating_mul(n);
    if frame_points > limits.max_curve_frame_points {
        // Interval k keeps ⌈steps/k⌉ + 1 frames, so `fits` frames need k ≥ steps/(fits − 1).
        let fits = limits.max_curve_frame_points / n.max(1);
        let advice = if fits >= 2 {
            format!(
                "a frame_interval of at least {}, or none",
                spec.steps.div_ceil(fits - 1)
            )
        } else {
            "no frame_interval: even two frames of this curve are over it".to_string()
        };
        return Err(JobError::InvalidSpec {
            field: "frame_interval",
            reason: format!(
                "the frames would carry {frame_points} points in all, over the server's limit of \
                 {}: ask for {advice}",
                limits.max_curve_frame_points
            ),
        });
    }
    let mut flow = CurveFlow::new(curve, CurveParams { tau: spec.tau }).map_err(|e| match e {
        CurveError::InvalidParameter { name, reason } => JobError::InvalidSpec {
            field: if name == "tau" { "tau" } else { "curve" },
            reason,
        },
        other => JobError::InvalidCurve(other),
    })?;

    let mut metrics = Vec::new();
    metrics
        .try_reserve_exact(spec.steps + 1)
        .map_err(|_| JobError::Internal("out of memory for curve metrics".into()))?;
    metrics.push(flow.initial_metrics());
    let mut frames = Vec::new();
    let keep = |flow: &CurveFlow, frames: &mut Vec<CurveFrame>| {
        let mut points = Vec::new();
        points
            .try_reserve_exact(n)
            .map_err(|_| JobError::Internal("out of memory for curve frames".into()))?;
        points.extend_from_slice(flow.points());
        frames.push(CurveFrame {
            step: flow.step_count(),
            points,
        });
        Ok::<_, JobError>(())
    };
    if spec.keeps_frame(0) {
        keep(&flow, &mut frames)?;
    }
    for step in 1..=spec.steps {
        match stop() {
            Some(Stop::Cancelled) => {
                return Err(JobError::Internal(
                    "curve request abandoned by its client".into(),
                ))
            }
            Some(Stop::Shutdown) => return Err(JobError::ShuttingDown),
            None => {}
        }
        if Instant::now() > deadline {
            return Err(JobError::DeadlineExceeded {
                secs: spec.deadline_secs.unwrap_or(0.0),
                step: step - 1,
                steps: spec.steps,
            });
        }
        let m = flow.step();
        if let Some(i) = flow
            .points()
            .iter()
            .position(|p| !(p[0].is_finite() && p[1].is_finite()))
        {
            return Err(JobError::Numerical {
                step,
                reason: format!("point {i} is no longer finite"),
            });
        }
        metrics.push(m);
        if spec.keeps_frame(step) {
            keep(&flow, &mut frames)?;
        }
    }
    Ok(CurveOutcome {
        curve: flow.curve().clone(),
        spec,
        metrics,
        frames,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_count_matches_keeps_frame() {
        for steps in 1..20 {
            for k in 1..8 {
                let spec = CurveSpec {
                    steps,
                    frame_interval: Some(k),
                    ..CurveSpec::default()
                };
                let kept = (0..=steps).filter(|&s| spec.keeps_frame(s)).count();
                assert_eq!(spec.frame_count(), kept, "steps {steps}, interval {k}");
            }
        }
        assert_eq!(CurveSpec::default().frame_count(), 0);
    }

    #[test]
    fn every_curve_error_has_a_code() {
        let errors = [
            CurveError::TooFewPoints {
                closed: true,
                min: 3,
                got: 1,
            },
            CurveError::NonFinite {
                index: 0,
                x: f64::NAN,
                y: 0.0,
            },
            CurveError::ZeroLengthEdge { index: 2 },
            CurveError::Cusp { index: 1 },
            CurveError::Json("x".into()),
            CurveError::Obj {
                line: 1,
                reason: "x".into(),
            },
            CurveError::InvalidParameter {
                name: "tau",
                reason: "x".into(),
            },
            CurveError::OutOfMemory { points: 1 },
        ];
        let codes: std::collections::HashSet<_> = errors.iter().map(curve_error_code).collect();
        assert_eq!(codes.len(), errors.len(), "codes are distinct");
    }
}
