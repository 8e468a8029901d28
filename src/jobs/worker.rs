//! The bounded worker pool: `workers` async loops, each taking one job at a time from the
//! queue and running its flow on a blocking thread.
//!
//! The pool size bounds CPU use, not the tokio blocking pool (which allows 512 threads): at most
//! `workers` flows run at once, each single-threaded. Between steps a flow checks, in order,
//! its cancellation token (→ cancelled), the shutdown token (→ re-queued) and its deadline
//! (→ failed, `deadline_exceeded`); a step itself is never interrupted, so cancellation latency
//! is one step.

use super::{join_err, now_ms, Frame, Inner, JobError, JobEvent, JobState, JobStatus, Jobs};
use crate::flow::{new_flow, FlowError};
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio_util::sync::CancellationToken;

/// Decrements the live-worker count however the loop ends (return or panic), so readiness
/// reports a dead pool.
struct AliveGuard<'a>(&'a Inner);

impl Drop for AliveGuard<'_> {
    fn drop(&mut self) {
        self.0.workers_alive.fetch_sub(1, Ordering::SeqCst);
    }
}

/// One worker: take a job, run it to the end on a blocking thread, repeat until `stop`.
pub(crate) async fn worker_loop(jobs: Jobs, n: usize, stop: CancellationToken) {
    let inner = jobs.inner.clone();
    inner.workers_alive.fetch_add(1, Ordering::SeqCst);
    let _alive = AliveGuard(&inner);
    loop {
        let id = tokio::select! {
            biased;
            _ = stop.cancelled() => break,
            id = inner.queue.pop() => id,
        };
        inner.telemetry.queue_depth.set(inner.queue.len() as i64);
        let token = inner
            .active
            .lock()
            .ok()
            .and_then(|a| a.get(&id).map(|a| a.cancel.clone()))
            .unwrap_or_default();
        let span = tracing::info_span!("job", job_id = %id, worker = n);
        inner.running.fetch_add(1, Ordering::SeqCst);
        inner
            .telemetry
            .running
            .set(inner.running.load(Ordering::SeqCst) as i64);
        let run_inner = inner.clone();
        let run_id = id.clone();
        let outcome = tokio::task::spawn_blocking(move || {
            span.in_scope(|| run_job(&run_inner, &run_id, &token))
        })
        .await
        .map_err(join_err)
        .and_then(|r| r);
        inner.running.fetch_sub(1, Ordering::SeqCst);
        inner
            .telemetry
            .running
            .set(inner.running.load(Ordering::SeqCst) as i64);
        inner.last_progress_ms.store(now_ms(), Ordering::SeqCst);
        if let Err(e) = outcome {
            // The job could not even be recorded as failed (store error or a panic in the
            // flow): try once more to fail it alone, and keep the worker going.
            tracing::error!(job_id = %id, error = %e, "job aborted");
            let _ = finish(
                &inner,
                &id,
                JobState::Failed,
                Some(("internal", e.to_string())),
            );
        }
    }
}

/// From this many vertices on, a job may use the cores idle workers leave: its factorization
/// has subtrees worth a thread each (below, a step takes milliseconds and threads only add
/// their start-up cost).
pub const PARALLEL_JOB_VERTICES: usize = 100_000;

/// Threads for a job of `vertices` vertices: 1 for small jobs, so many of them share the
/// cores; for a large one, the cores of the workers that are idle (`running` counts this job)
/// when nothing waits in the queue. A job keeps its budget to the end, so a burst that
/// arrives after it starts shares the machine with it for its duration (the workers bound the
/// count of flows, not of threads).
pub fn thread_budget(
    vertices: usize,
    workers: usize,
    running: usize,
    queued: usize,
    cores: usize,
) -> usize {
    if vertices < PARALLEL_JOB_VERTICES || queued > 0 {
        return 1;
    }
    let idle = workers.saturating_sub(running.max(1));
    (1 + idle).min(cores).max(1)
}

/// What ended a run early.
enum Stop {
    Cancelled(usize),
    Shutdown,
    Deadline(usize),
}

/// Run one job to a terminal state (or back to the queue on shutdown).
fn run_job(inner: &Arc<Inner>, id: &str, token: &CancellationToken) -> Result<(), JobError> {
    let queued = inner.store.status(id)?;
    if queued.state != JobState::Queued {
        return Ok(()); // cancelled (or deleted) while waiting
    }
    if token.is_cancelled() {
        finish(
            inner,
            id,
            JobState::Cancelled,
            Some(("cancelled", "cancelled while queued".into())),
        )?;
        return Ok(());
    }
    let deadline_ms = queued.created_at
        + queued
            .spec
            .deadline_secs
            .map(Duration::from_secs_f64)
            .unwrap_or(inner.config.default_deadline)
            .as_millis() as u64;
    let check = |step: usize| -> Option<Stop> {
        if token.is_cancelled() {
            Some(Stop::Cancelled(step))
        } else if inner.shutdown.is_cancelled() {
            Some(Stop::Shutdown)
        } else if now_ms() > deadline_ms {
            Some(Stop::Deadline(step))
        } else {
            None
        }
    };
    if let Some(stop) = check(0) {
        return stopped(inner, id, stop, &queued);
    }
    // Open the live channel before the first event (watchers may have opened it already).
    inner.hub.open(id);
    let Some(running) = inner.store.set_running(id, now_ms())? else {
        return Ok(());
    };
    inner.hub.send(id, JobEvent::State(running.clone()));
    tracing::info!(steps = running.total_steps, "job started");
    let started = Instant::now();

    let asset = match inner
        .store
        .read_asset(id, &inner.config.limits.mesh_limits())
    {
        Ok(a) => a,
        Err(JobError::InvalidMesh(e)) => {
            finish(
                inner,
                id,
                JobState::Failed,
                Some(("invalid_mesh", e.to_string())),
            )?;
            return Ok(());
        }
        Err(e) => return Err(e),
    };
    let spec = &running.spec;
    let mut params = spec.flow_params();
    params.threads = thread_budget(
        asset.surface().vertex_count(),
        inner.config.workers,
        inner.running.load(Ordering::SeqCst),
        inner.queue.len(),
        std::thread::available_parallelism().map_or(1, |n| n.get()),
    );
    let mut flow = match new_flow(asset.surface(), &params) {
        Ok(f) => f,
        Err(e) => {
            finish(
                inner,
                id,
                JobState::Failed,
                Some((flow_error_code(&e), e.to_string())),
            )?;
            return Ok(());
        }
    };

    let emit = |step: usize, mut metrics: crate::metrics::StepMetrics, positions: &[[f64; 3]]| {
        metrics.step = step;
        let payload = if spec.keeps_positions(step) {
            let file_order = asset.file_positions(positions);
            inner
                .store
                .write_frame_positions(id, step, &file_order, positions)?;
            Some(Arc::new(file_order))
        } else {
            None
        };
        inner.store.record_frame(id, &metrics, payload.is_some())?;
        inner.last_progress_ms.store(now_ms(), Ordering::SeqCst);
        inner.hub.send(
            id,
            JobEvent::Frame(Frame {
                step,
                metrics,
                positions: payload,
            }),
        );
        Ok::<_, JobError>(())
    };

    emit(0, flow.initial_metrics(), flow.positions())?;
    // Set when the safeguard finds no acceptable step: the job then ends early, succeeded,
    // with this (code, reason) as its note (see `JobStatus::error_code`).
    let mut stopped_early = None;
    for step in 1..=spec.steps {
        if let Some(stop) = check(step - 1) {
            return stopped(inner, id, stop, &running);
        }
        let t = Instant::now();
        let metrics = match flow.step() {
            Ok(m) => m,
            // The safeguard put the flow back on the last accepted surface (step − 1), whose
            // frame is already stored: that surface is the result. Succeeded rather than failed,
            // so "succeeded ⇔ has a result" stays true for the store and for every client.
            Err(e @ FlowError::NoProgress { .. }) => {
                tracing::info!(step, reason = %e, "flow stopped early");
                stopped_early = Some((flow_error_code(&e), e.to_string()));
                break;
            }
            Err(e) => {
                tracing::warn!(step, error = %e, "flow failed");
                finish(
                    inner,
                    id,
                    JobState::Failed,
                    Some((flow_error_code(&e), e.to_string())),
                )?;
                return Ok(());
            }
        };
        inner
            .telemetry
            .step_seconds
            .observe(t.elapsed().as_secs_f64());
        // Accepted safeguarded steps are finite by construction; with the safeguard off a
        // diverging flow may not be, and nothing non-finite is streamed or stored.
        if let Some(bad) = first_non_finite(flow.positions()) {
            finish(
                inner,
                id,
                JobState::Failed,
                Some((
                    "numerical",
                    format!("numerical failure at step {step}: vertex {bad} is not finite"),
                )),
            )?;
            return Ok(());
        }
        emit(step, metrics, flow.positions())?;
    }
    debug_assert!(first_non_finite(flow.positions()).is_none());
    inner.store.write_result(id, flow.positions())?;
    let elapsed = started.elapsed();
    // Moving average with weight 1/4 for the newest job: reacts within a few jobs.
    let prev = inner.avg_job_ms.load(Ordering::Relaxed);
    let ms = elapsed.as_millis() as u64;
    inner
        .avg_job_ms
        .store((prev * 3 + ms) / 4, Ordering::Relaxed);
    finish(inner, id, JobState::Succeeded, stopped_early)?;
    tracing::info!(elapsed_ms = ms, "job succeeded");
    Ok(())
}

/// The first vertex with a non-finite coordinate, if any.
fn first_non_finite(positions: &[[f64; 3]]) -> Option<usize> {
    positions
        .iter()
        .position(|p| !p.iter().all(|c| c.is_finite()))
}

fn stopped(inner: &Arc<Inner>, id: &str, stop: Stop, status: &JobStatus) -> Result<(), JobError> {
    match stop {
        Stop::Cancelled(step) => {
            finish(
                inner,
                id,
                JobState::Cancelled,
                Some((
                    "cancelled",
                    format!("cancelled after step {step} of {}", status.total_steps),
                )),
            )?;
        }
        Stop::Deadline(step) => {
            let secs = status
                .spec
                .deadline_secs
                .unwrap_or(inner.config.default_deadline.as_secs_f64());
            finish(
                inner,
                id,
                JobState::Failed,
                Some((
                    "deadline_exceeded",
                    format!(
                        "deadline of {secs} s (from submission) exceeded after step {step} of {}",
                        status.total_steps
                    ),
                )),
            )?;
        }
        Stop::Shutdown => {
            inner.store.requeue(id)?;
            if let Ok(s) = inner.store.status(id) {
                inner.hub.send(id, JobEvent::State(s));
            }
            tracing::info!(
                "shutting down: job re-queued, it restarts from step 0 on the next start"
            );
        }
    }
    Ok(())
}

fn flow_error_code(e: &FlowError) -> &'static str {
    match e {
        FlowError::InvalidParameter { .. } => "invalid_parameter",
        FlowError::Unsupported(_) => "unsupported",
        FlowError::Numerical { .. } => "numerical",
        FlowError::NoProgress { .. } => "no_progress",
    }
}

/// Move a job to a terminal state, tell its watchers and close its channel. Idempotent: a job
/// that is already terminal is returned as it is.
pub(crate) fn finish(
    inner: &Inner,
    id: &str,
    state: JobState,
    error: Option<(&str, String)>,
) -> Result<JobStatus, JobError> {
    let now = now_ms();
    let expires = now + inner.config.result_ttl.as_millis() as u64;
    let code = error.as_ref().map(|(c, _)| c.to_string());
    let done = inner.store.finish(id, state, error, now, expires)?;
    let Some(status) = done else {
        return inner.store.status(id);
    };
    if let Ok(mut a) = inner.active.lock() {
        a.remove(id);
    }
    inner.hub.send(id, JobEvent::Done(status.clone()));
    inner.hub.close(id);
    inner.telemetry.record_outcome(
        state,
        code.as_deref(),
        status.started_at.map(|s| now.saturating_sub(s)),
    );
    if state == JobState::Failed {
        tracing::warn!(job_id = %id, error = status.error.as_deref().unwrap_or(""), "job failed");
    }
    Ok(status)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn small_jobs_run_on_one_thread_whatever_is_idle() {
        assert_eq!(thread_budget(PARALLEL_JOB_VERTICES - 1, 8, 1, 0, 16), 1);
    }

    #[test]
    fn a_large_job_takes_the_cores_of_idle_workers() {
        // Alone on 4 workers: itself and the three idle ones, within the cores.
        assert_eq!(thread_budget(PARALLEL_JOB_VERTICES, 4, 1, 0, 16), 4);
        assert_eq!(thread_budget(PARALLEL_JOB_VERTICES, 4, 1, 0, 2), 2);
        // Three of four workers busy: one idle worker's core.
        assert_eq!(thread_budget(PARALLEL_JOB_VERTICES, 4, 3, 0, 16), 2);
        // Every worker busy, or jobs waiting for one: no extra threads.
        assert_eq!(thread_budget(PARALLEL_JOB_VERTICES, 4, 4, 0, 16), 1);
        assert_eq!(thread_budget(PARALLEL_JOB_VERTICES, 4, 1, 2, 16), 1);
    }
}
