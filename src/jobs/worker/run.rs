//! One job's run on a blocking thread: its flow under the stopping rules
//! ([`willow::flow::stopping::Run`]), frames and checkpoints as it goes, and how it ends
//! (succeeded with an outcome, failed, cancelled, or back to the queue).

use super::super::codec::{
    decode_checkpoint, encode_checkpoint, encode_frame_positions, f64s_to_bytes,
};
use super::super::ports::{BlobKey, Fence};
use super::super::{
    now_ms, FailureCode, Frame, FramePositions, Inner, JobError, JobEvent, JobId, JobState,
    JobStatus,
};
use super::{finish, thread_budget, Outcome};
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::runtime::Handle;
use tokio_util::sync::CancellationToken;
use willow::flow::stopping::{Event, Run};
use willow::flow::{new_flow, Flow, FlowState};
use willow::mesh::io::Asset;

/// What ended a run early.
enum Stop {
    Cancelled(usize),
    Shutdown,
    Deadline(usize),
    /// The fence lost the job to another worker.
    Lost,
}

/// Run one job to a terminal state (or back to the queue on shutdown). Runs on a blocking
/// thread; the ports are async, and `rt` runs their calls.
pub(super) fn run_job(
    inner: &Arc<Inner>,
    rt: &Handle,
    id: &JobId,
    token: &CancellationToken,
    fence: &Fence,
    running: JobStatus,
) -> Result<Outcome, JobError> {
    let backend = &inner.backend;
    // Before every write: a worker that lost the job writes nothing more. One that has had no
    // word from the store for half a hold (frozen, or cut off) asks it first.
    let still_held = || -> Result<(), JobError> {
        if fence.lost.is_cancelled() {
            return Err(fence.lost_error(id));
        }
        if fence.stale(now_ms()) {
            rt.block_on(backend.store.renew(id, fence))?;
        }
        Ok(())
    };
    let deadline_ms = running.created_at
        + running
            .spec
            .deadline_secs
            .map(Duration::from_secs_f64)
            .unwrap_or(inner.config.default_deadline)
            .as_millis() as u64;
    let check = |step: usize| -> Option<Stop> {
        if fence.lost.is_cancelled() {
            Some(Stop::Lost)
        } else if token.is_cancelled() {
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
        return stopped(inner, rt, id, stop, &running, None, fence);
    }
    rt.block_on(backend.events.publish(id, JobEvent::State(running.clone())))?;
    let started = Instant::now();

    let asset = match read_asset(inner, rt, &running) {
        Ok(a) => a,
        Err(JobError::InvalidMesh(e)) => {
            return fail(
                inner,
                rt,
                id,
                fence,
                FailureCode::InvalidMesh,
                e.to_string(),
            );
        }
        Err(e) => return Err(e),
    };
    let spec = &running.spec;
    let sizes = super::super::stored::JobSizes {
        file_vertices: asset.file_vertex_count(),
        surface_vertices: asset.surface().vertex_count(),
    };
    // A run that ends before its last step, however it ends (cancelled, past its deadline,
    // failed), kept the frames up to `last`: the quota gets the rest of its plan back now,
    // not when the job expires. Best effort: a store that does not answer leaves the tenant
    // counted high, the safe side, until the job is deleted or expires.
    let settle = |last: usize| {
        let kept = super::super::stored::kept_bytes(spec, sizes, last);
        if let Err(e) = rt.block_on(backend.store.settle_planned(id, kept, fence)) {
            tracing::warn!(error = %e, last, "the plan of a run that ended early was not settled");
        }
    };
    let mut params = match spec.flow_params_for(&asset) {
        Ok(p) => p,
        // Admission checked the regions against this file; a stored job from before a change
        // of numbering is the only way here.
        Err(e) => {
            return fail(
                inner,
                rt,
                id,
                fence,
                FailureCode::InvalidParameter,
                e.to_string(),
            );
        }
    };
    params.threads = thread_budget(
        asset.surface().vertex_count(),
        inner.config.workers,
        inner.running.load(Ordering::SeqCst),
        backend.queue.depth(),
        std::thread::available_parallelism().map_or(1, |n| n.get()),
    );
    let mut flow = match new_flow(asset.surface(), &params) {
        Ok(f) => f,
        Err(e) => {
            return fail_flow(inner, rt, id, fence, &e);
        }
    };

    // Frames are sent relative to this (zero around the origin), see `FramePositions`.
    let frame_origin = asset.frame_origin();
    let emit = |step: usize, mut metrics: willow::metrics::StepMetrics, positions: &[[f64; 3]]| {
        metrics.step = step;
        still_held()?;
        let payload = if spec.keeps_positions(step) {
            let file_order = FramePositions {
                origin: frame_origin,
                relative: asset.file_positions_relative(positions, frame_origin),
            };
            let (key, welded) = frame_keys(id, step);
            rt.block_on(async {
                backend
                    .blobs
                    .put(key, encode_frame_positions(&file_order).into())
                    .await?;
                backend
                    .blobs
                    .put(welded, f64s_to_bytes(positions).into())
                    .await
            })?;
            Some(Arc::new(file_order))
        } else {
            None
        };
        rt.block_on(async {
            backend
                .store
                .record_frame(id, metrics, payload.is_some(), fence)
                .await?;
            inner.last_progress_ms.store(now_ms(), Ordering::SeqCst);
            backend
                .events
                .publish(
                    id,
                    JobEvent::Frame(Frame {
                        step,
                        metrics,
                        positions: payload,
                        connectivity_changed: false,
                    }),
                )
                .await
        })
    };

    let resumed_at = resume(inner, rt, id, flow.as_mut())?;
    let first = match &resumed_at {
        Some(at) => {
            let step = at.metrics.step;
            rt.block_on(backend.store.rewind(id, step, fence))?;
            inner.telemetry.resumed.inc();
            tracing::info!(step, "resumed from the checkpoint");
            step + 1
        }
        None => {
            rt.block_on(backend.store.rewind(id, 0, fence))?;
            emit(0, flow.initial_metrics(), flow.positions())?;
            tracing::info!(steps = running.total_steps, "job started");
            1
        }
    };
    // The stopping rules (`willow::flow::stopping`): the steps, convergence, `until_willmore`,
    // `max_deviation`, and the safeguard's "no acceptable step".
    let run = match resumed_at {
        Some(at) => Run::resumed(flow, &params, spec.steps, &at),
        None => Run::new(flow, &params, spec.steps),
    };
    let mut run = match run {
        Ok(r) => r,
        Err(e) => {
            settle(first - 1);
            return fail_flow(inner, rt, id, fence, &e);
        }
    };
    let mut last_checkpoint = (first - 1, Instant::now());
    let mut step = first;
    let (outcome, reason) = loop {
        if let Some(stop) = check(step - 1).filter(|_| !run.is_over()) {
            if matches!(stop, Stop::Cancelled(_) | Stop::Deadline(_)) {
                settle(step - 1);
            }
            return stopped(inner, rt, id, stop, &running, Some(&run), fence);
        }
        let t = Instant::now();
        let metrics = match run.advance() {
            Ok(Event::Step(m)) => m,
            // The run is over. On `no_progress` the safeguard put the flow back on the last
            // accepted surface; on `max_deviation` the run undid the step past the bound:
            // either way the flow is on the surface of the last frame stored, which is the
            // result. Succeeded rather than failed, so "succeeded ⇔ has a result" stays true
            // for the store and for every client.
            Ok(Event::Stopped { outcome, reason }) => break (outcome, reason),
            Err(e) => {
                tracing::warn!(step, error = %e, "flow failed");
                settle(step - 1);
                return fail_flow(inner, rt, id, fence, &e);
            }
        };
        inner
            .telemetry
            .step_seconds
            .observe(t.elapsed().as_secs_f64());
        // Accepted safeguarded steps are finite by construction; with the safeguard off a
        // diverging flow may not be, and nothing non-finite is streamed or stored.
        if let Some(bad) = first_non_finite(run.flow().positions()) {
            settle(step - 1);
            return fail(
                inner,
                rt,
                id,
                fence,
                FailureCode::Numerical,
                format!("numerical failure at step {step}: vertex {bad} is not finite"),
            );
        }
        emit(step, metrics, run.flow().positions())?;
        let due = step - last_checkpoint.0 >= inner.config.checkpoint_steps
            || last_checkpoint.1.elapsed() >= inner.config.checkpoint_interval;
        if due && step < spec.steps {
            still_held()?;
            if checkpoint(inner, rt, id, &run)? {
                // Progress that outlives this worker: a delivery after it is not a repeat.
                rt.block_on(backend.store.checkpointed(id, step, fence))?;
            }
            last_checkpoint = (step, Instant::now());
        }
        step += 1;
    };
    let flow = run.flow();
    tracing::info!(outcome = outcome.name(), %reason, "flow ended");
    if step <= spec.steps {
        // Stopped before its last step (`step` was not taken).
        settle(step - 1);
    }
    // A run that took all its steps says nothing more; any other ending is the job's note
    // (`JobStatus::error_code` on a succeeded job, and so its `outcome`).
    let stopped_early = FailureCode::of_outcome(outcome).map(|code| (code, reason));
    debug_assert!(first_non_finite(flow.positions()).is_none());
    still_held()?;
    rt.block_on(backend.blobs.put(
        BlobKey::Result { id: id.clone() },
        f64s_to_bytes(flow.positions()).into(),
    ))?;
    let elapsed = started.elapsed();
    // Moving average with weight 1/4 for the newest job: reacts within a few jobs. The first
    // job sets it (0 is "none yet").
    let prev = inner.avg_job_ms.load(Ordering::Relaxed);
    let ms = (elapsed.as_millis() as u64).max(1);
    let avg = if prev == 0 { ms } else { (prev * 3 + ms) / 4 };
    inner.avg_job_ms.store(avg, Ordering::Relaxed);
    rt.block_on(finish(
        inner,
        id,
        JobState::Succeeded,
        stopped_early,
        Some(fence),
    ))?;
    // The checkpoint has served: a finished job is never resumed.
    let _ = rt.block_on(backend.blobs.delete(BlobKey::Checkpoint { id: id.clone() }));
    tracing::info!(elapsed_ms = ms, "job succeeded");
    Ok(Outcome::Done)
}

/// Ends the job failed with `code` and `reason` (the flow is over: nothing more to run).
/// [`fail`] with a flow error: its code ([`FailureCode::of_flow`]) and its message.
fn fail_flow(
    inner: &Arc<Inner>,
    rt: &Handle,
    id: &JobId,
    fence: &Fence,
    e: &willow::flow::FlowError,
) -> Result<Outcome, JobError> {
    fail(inner, rt, id, fence, FailureCode::of_flow(e), e.to_string())
}

fn fail(
    inner: &Arc<Inner>,
    rt: &Handle,
    id: &JobId,
    fence: &Fence,
    code: FailureCode,
    reason: String,
) -> Result<Outcome, JobError> {
    rt.block_on(finish(
        inner,
        id,
        JobState::Failed,
        Some((code, reason)),
        Some(fence),
    ))?;
    Ok(Outcome::Done)
}

/// The blob keys of a frame's positions: file order (f32) and welded (f64).
fn frame_keys(id: &JobId, step: usize) -> (BlobKey, BlobKey) {
    let key = |welded| BlobKey::Frame {
        id: id.clone(),
        step,
        welded,
    };
    (key(false), key(true))
}

/// The job's uploaded file, parsed.
fn read_asset(inner: &Inner, rt: &Handle, status: &JobStatus) -> Result<Asset, JobError> {
    let key = BlobKey::Input {
        id: status.id.clone(),
        format: status.input_format,
    };
    let bytes = rt.block_on(inner.backend.blobs.get(key))?.ok_or_else(|| {
        JobError::Internal(format!("the input of job `{}` is missing", status.id))
    })?;
    status.spec.read_asset(
        &bytes,
        status.input_format,
        &inner.config.limits.mesh_limits(),
    )
}

/// Put `flow` on the job's checkpoint, if it has a usable one; the checkpoint (its metrics
/// are those of the step it is at, its carried state the run's, [`Run::resumed`]).
/// A store that cannot answer now (NATS away: `Unavailable`, or full) is an error, so that
/// the job is handed back and resumed later instead of starting over from step 0.
fn resume(
    inner: &Inner,
    rt: &Handle,
    id: &JobId,
    flow: &mut dyn Flow,
) -> Result<Option<FlowState>, JobError> {
    let key = BlobKey::Checkpoint { id: id.clone() };
    let bytes = match rt.block_on(inner.backend.blobs.get(key)) {
        Ok(Some(b)) => b,
        Ok(None) => return Ok(None),
        Err(e @ (JobError::Unavailable(_) | JobError::StorageFull { .. })) => return Err(e),
        Err(e) => {
            tracing::warn!(error = %e, "checkpoint unreadable: the job starts from step 0");
            return Ok(None);
        }
    };
    let state = match decode_checkpoint(&bytes) {
        Ok(s) => s,
        Err(e) => {
            tracing::warn!(error = %e, "checkpoint refused: the job starts from step 0");
            return Ok(None);
        }
    };
    match flow.resume(&state) {
        Ok(()) => Ok(Some(state)),
        Err(e) => {
            tracing::warn!(error = %e, "checkpoint does not fit the flow: the job starts from step 0");
            Ok(None)
        }
    }
}

/// Write the run's state (its flow's and its stopping rules', [`Run::checkpoint`]) as the
/// job's checkpoint; whether the flow has one to write.
fn checkpoint(inner: &Inner, rt: &Handle, id: &JobId, run: &Run) -> Result<bool, JobError> {
    let Some(state) = run.checkpoint() else {
        return Ok(false);
    };
    let t = Instant::now();
    let key = BlobKey::Checkpoint { id: id.clone() };
    rt.block_on(
        inner
            .backend
            .blobs
            .put(key, encode_checkpoint(&state).into()),
    )?;
    inner
        .telemetry
        .checkpoint_seconds
        .observe(t.elapsed().as_secs_f64());
    Ok(true)
}

/// The first vertex with a non-finite coordinate, if any.
fn first_non_finite(positions: &[[f64; 3]]) -> Option<usize> {
    positions
        .iter()
        .position(|p| !p.iter().all(|c| c.is_finite()))
}

fn stopped(
    inner: &Arc<Inner>,
    rt: &Handle,
    id: &JobId,
    stop: Stop,
    status: &JobStatus,
    run: Option<&Run>,
    fence: &Fence,
) -> Result<Outcome, JobError> {
    match stop {
        Stop::Lost => return Ok(Outcome::Lost),
        Stop::Cancelled(step) => {
            rt.block_on(finish(
                inner,
                id,
                JobState::Cancelled,
                Some((
                    FailureCode::Cancelled,
                    format!("cancelled after step {step} of {}", status.total_steps),
                )),
                Some(fence),
            ))?;
        }
        Stop::Deadline(step) => {
            let secs = status
                .spec
                .deadline_secs
                .unwrap_or(inner.config.default_deadline.as_secs_f64());
            rt.block_on(finish(
                inner,
                id,
                JobState::Failed,
                Some((
                    FailureCode::DeadlineExceeded,
                    format!(
                        "deadline of {secs} s (from submission) exceeded after step {step} of {}",
                        status.total_steps
                    ),
                )),
                Some(fence),
            ))?;
        }
        Stop::Shutdown => {
            // Keep every step taken: the next worker resumes right here.
            if let Some(run) = run {
                if fence.lost.is_cancelled() {
                    return Ok(Outcome::Lost);
                }
                checkpoint(inner, rt, id, run)?;
            }
            let backend = &inner.backend;
            rt.block_on(backend.store.requeue(id, fence))?;
            if let Ok(s) = rt.block_on(backend.store.status(id, None)) {
                let _ = rt.block_on(backend.events.publish(id, JobEvent::State(s)));
            }
            tracing::info!("shutting down: job checkpointed and re-queued");
            return Ok(Outcome::Released);
        }
    }
    Ok(Outcome::Done)
}
