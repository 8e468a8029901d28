//! The bounded worker pool: `workers` async loops, each leasing one job at a time from the
//! [`WorkQueue`] and running its flow on a blocking thread.
//!
//! The pool size bounds CPU use, not the tokio blocking pool (which allows 512 threads): at most
//! `workers` flows run at once. Between steps a flow checks, in order, its cancellation token
//! (→ cancelled), the shutdown token (→ checkpointed and re-queued) and its deadline (→ failed,
//! `deadline_exceeded`); a step itself is never interrupted, so cancellation latency is one
//! step. While a job runs, a task heartbeats its lease, so a long step does not look like a
//! dead worker.
//!
//! Checkpoints: every [`Config::checkpoint_steps`] steps or [`Config::checkpoint_interval`],
//! whichever comes first, the flow's state ([`willow::flow::FlowState`]) goes to the blob store.
//! A job delivered again after its worker died (or after a restart, or a shutdown) resumes from
//! there instead of step 0: the store forgets the frames after the checkpoint, and the steps
//! after it are taken again (watchers skip the step numbers they have seen).
//!
//! [`WorkQueue`]: super::ports::WorkQueue
//! [`Config::checkpoint_steps`]: super::Config::checkpoint_steps
//! [`Config::checkpoint_interval`]: super::Config::checkpoint_interval

mod run;

use super::ports::{Fence, JobStore, Lease, LeaseControl, Started};
use super::{now_ms, FailureCode, Inner, JobError, JobEvent, JobState, JobStatus, Jobs};
use run::run_job;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;
use tokio::runtime::Handle;
use tokio_util::sync::CancellationToken;

/// Decrements the live-worker count however the loop ends (return or panic), so readiness
/// reports a dead pool.
struct AliveGuard<'a>(&'a Inner);

impl Drop for AliveGuard<'_> {
    fn drop(&mut self) {
        self.0.workers_alive.fetch_sub(1, Ordering::SeqCst);
    }
}

/// How a run ended, for the lease.
enum Outcome {
    /// Terminal (or found terminal): ack.
    Done,
    /// Stopped for shutdown, checkpointed and re-queued: give the lease back.
    Released,
    /// Another worker holds the job (its fence took over, or held it first): settle nothing,
    /// the holder acks it.
    Lost,
}

/// How often a worker given a job that another worker's live hold has looks again.
const HELD_POLL: Duration = Duration::from_millis(500);
/// How soon a failed renewal of a hold is tried again (a renewal right after a NATS outage
/// keeps the hold from being taken over).
const RENEW_RETRY: Duration = Duration::from_millis(250);

/// What taking a delivered job under a fence gave.
enum Acquired {
    Run(Box<JobStatus>),
    /// Terminal, deleted or unknown.
    Gone,
    /// Shutting down while another worker held it.
    Abandoned,
}

/// Take job `id` under `fence`. While another worker's live hold has it, wait (the delivery
/// is a duplicate: a redelivery while its first worker still runs it), until it is finished
/// (gone) or the hold lapses (its worker died: then it is ours).
async fn acquire(inner: &Inner, id: &str, fence: &Fence) -> Result<Acquired, JobError> {
    let mut waiting = false;
    loop {
        match inner.backend.store.start(id, fence, now_ms()).await? {
            Started::Run(s) => return Ok(Acquired::Run(s)),
            Started::Gone => return Ok(Acquired::Gone),
            Started::Held => {
                if !waiting {
                    tracing::info!(job_id = %id, "delivered while another worker holds it: not run, waiting for it to finish or lapse");
                    waiting = true;
                }
                tokio::select! {
                    _ = inner.shutdown.cancelled() => return Ok(Acquired::Abandoned),
                    _ = tokio::time::sleep(HELD_POLL) => {}
                }
            }
        }
    }
}

/// One worker: lease a job, run it to the end on a blocking thread, repeat until `stop`.
pub(crate) async fn worker_loop(jobs: Jobs, n: usize, stop: CancellationToken) {
    let inner = jobs.inner.clone();
    inner.workers_alive.fetch_add(1, Ordering::SeqCst);
    let _alive = AliveGuard(&inner);
    let backend = inner.backend.clone();
    loop {
        // Any job taken while the disk is full would stop at its first write: leave them queued.
        inner.storage.wait_for_room(&stop).await;
        let lease = tokio::select! {
            biased;
            _ = stop.cancelled() => break,
            lease = backend.queue.lease() => lease,
        };
        let lease = match lease {
            Ok(l) => l,
            Err(e) => {
                // The queue's server is away (NATS restarting): wait, then ask again.
                tracing::warn!(worker = n, error = %e, "could not lease a job");
                tokio::select! {
                    _ = stop.cancelled() => break,
                    _ = tokio::time::sleep(Duration::from_secs(1)) => continue,
                }
            }
        };
        inner
            .telemetry
            .queue_depth
            .set(backend.queue.depth() as i64);
        run_leased(&inner, n, lease).await;
    }
}

/// Run one leased job and settle its lease.
async fn run_leased(inner: &Arc<Inner>, n: usize, lease: Lease) {
    let backend = &inner.backend;
    let id = lease.id.clone();
    let fence = Fence::new(inner.config.heartbeat_interval * 3);
    // Heartbeats from the start (also while a duplicate delivery waits); the store's hold is
    // renewed by them once it is ours (`held`).
    let (beat, held) = (CancellationToken::new(), CancellationToken::new());
    let heartbeat = tokio::spawn(heartbeat_loop(
        lease.control.clone(),
        backend.store.clone(),
        id.clone(),
        fence.clone(),
        held.clone(),
        inner.config.heartbeat_interval,
        beat.clone(),
    ));
    let running = match acquire(inner, &id, &fence).await {
        Ok(Acquired::Run(s)) => Some(s),
        Ok(Acquired::Gone) => None,
        Ok(Acquired::Abandoned) => {
            beat.cancel();
            let _ = heartbeat.await;
            return;
        }
        Err(e) => {
            beat.cancel();
            let _ = heartbeat.await;
            settle(inner, &id, &lease, &fence, Err(e)).await;
            return;
        }
    };
    held.cancel();
    let outcome = match running {
        None => Ok(Outcome::Done), // cancelled, deleted or expired while waiting, or done
        Some(running) => match backend.store.delivered(&id, &fence).await {
            Ok(stalled) if stalled > inner.config.max_deliveries => {
                give_up(inner, &id, &fence, stalled, lease.attempt).await
            }
            Ok(_) => run_held(inner, n, &lease, &fence, *running).await,
            Err(e) => Err(e),
        },
    };
    beat.cancel();
    let _ = heartbeat.await;
    settle(inner, &id, &lease, &fence, outcome).await;
}

/// Fail a job whose last `stalled` deliveries each ended without a word and without a new
/// checkpoint (`Config::max_deliveries`): it kills its workers, and one more would die too.
/// Deliveries after progress do not count (`JobStore::delivered`), so a long job on
/// workers that get killed now and then still finishes.
async fn give_up(
    inner: &Inner,
    id: &str,
    fence: &Fence,
    stalled: u32,
    attempt: u32,
) -> Result<Outcome, JobError> {
    let reason = format!(
        "the job was delivered {stalled} times in a row without reaching a new checkpoint \
         ({} runs stopped without a word: killed, out of memory, or their node lost); it is \
         not tried again",
        stalled - 1
    );
    tracing::error!(job_id = %id, stalled, attempt, "giving up on a job");
    finish(
        inner,
        id,
        JobState::Failed,
        Some((FailureCode::Redelivered, reason)),
        Some(fence),
    )
    .await
    .map(|_| Outcome::Done)
}

/// Run a job this worker's fence holds, on a blocking thread.
async fn run_held(
    inner: &Arc<Inner>,
    n: usize,
    lease: &Lease,
    fence: &Fence,
    running: JobStatus,
) -> Result<Outcome, JobError> {
    let backend = &inner.backend;
    let id = running.id.clone();
    let token = backend.cancels.watch(&id).await;
    inner.running.fetch_add(1, Ordering::SeqCst);
    inner
        .telemetry
        .running
        .set(inner.running.load(Ordering::SeqCst) as i64);
    let span = tracing::info_span!("job", job_id = %id, worker = n, attempt = lease.attempt);
    let (run_inner, run_id, rt, run_fence) =
        (inner.clone(), id.clone(), Handle::current(), fence.clone());
    let outcome = tokio::task::spawn_blocking(move || {
        span.in_scope(|| run_job(&run_inner, &rt, &run_id, &token, &run_fence, running))
    })
    .await
    .map_err(super::join_err)
    .and_then(|r| r);
    inner.running.fetch_sub(1, Ordering::SeqCst);
    inner
        .telemetry
        .running
        .set(inner.running.load(Ordering::SeqCst) as i64);
    inner.last_progress_ms.store(now_ms(), Ordering::SeqCst);
    backend.cancels.forget(&id).await;
    outcome
}

/// Settle the lease as the run ended. A worker whose fence was lost settles nothing: the job
/// is another worker's, and so is its delivery.
async fn settle(
    inner: &Inner,
    id: &str,
    lease: &Lease,
    fence: &Fence,
    outcome: Result<Outcome, JobError>,
) {
    // A run that made the job terminal, or handed it back, settles its delivery even if a
    // renewal racing its last write has since found the hold gone.
    let outcome = match outcome {
        Ok(o @ (Outcome::Done | Outcome::Released)) => Ok(o),
        _ if fence.lost.is_cancelled() => Ok(Outcome::Lost),
        other => other,
    };
    let settled = match outcome {
        Ok(Outcome::Done) => lease.control.ack().await,
        Ok(Outcome::Released) => lease.control.release().await,
        Ok(Outcome::Lost) => {
            tracing::warn!(job_id = %id, "another worker holds the job now: this run stopped, writing nothing more");
            Ok(())
        }
        Err(JobError::Unavailable(e)) => {
            // The backend went away under the job: not the job's fault. Leave it to be
            // delivered again (here or elsewhere) once the backend is back; it resumes from
            // its checkpoint. Letting go of the hold (best effort) spares the next worker
            // the wait for it to lapse.
            tracing::warn!(job_id = %id, error = %e, "backend unavailable: the job will be delivered again");
            let _ = inner.backend.store.requeue(id, fence).await;
            lease.control.release().await
        }
        Err(JobError::StorageFull { detail }) => {
            // A full disk is not the job's fault either: back to the queue, to resume from
            // its checkpoint once there is room (the re-queue writes into the reserve the
            // first full write released). Meanwhile this worker waits instead of taking the
            // job again at once.
            let _ = inner.storage.noted(JobError::StorageFull { detail });
            tracing::warn!(job_id = %id, "storage full: the job is re-queued and waits for room");
            let _ = inner.backend.store.requeue(id, fence).await;
            inner.storage.wait_for_room(&inner.shutdown).await;
            lease.control.release().await
        }
        Err(e) => {
            // The job could not even be recorded as failed (store error or a panic in the
            // flow): try once more to fail it alone, and keep the worker going.
            tracing::error!(job_id = %id, error = %e, "job aborted");
            let _ = finish(
                inner,
                id,
                JobState::Failed,
                Some((FailureCode::Internal, e.to_string())),
                Some(fence),
            )
            .await;
            if fence.lost.is_cancelled() {
                return;
            }
            lease.control.ack().await
        }
    };
    if let Err(e) = settled {
        // The queue delivers it again; the store says it is terminal, and `start` refuses it.
        tracing::warn!(job_id = %id, error = %e, "could not settle the lease");
    }
}

/// Keep the lease while the job runs (a step may take longer than the queue's `ack_wait`),
/// and, once `held`, the fence's hold on the record. A renewal that finds the hold taken
/// over cancels the fence's `lost` (the run stops at its next write) and ends the heartbeats.
async fn heartbeat_loop(
    control: Arc<dyn LeaseControl>,
    store: Arc<dyn JobStore>,
    id: String,
    fence: Fence,
    held: CancellationToken,
    every: Duration,
    stop: CancellationToken,
) {
    let mut pause = every;
    loop {
        tokio::select! {
            _ = stop.cancelled() => return,
            _ = tokio::time::sleep(pause) => {}
        }
        pause = every;
        if let Err(e) = control.heartbeat().await {
            tracing::warn!(error = %e, "lease heartbeat failed");
        }
        if !held.is_cancelled() {
            continue;
        }
        if let Err(e) = store.renew(&id, &fence).await {
            if fence.lost.is_cancelled() {
                tracing::info!(job_id = %id, "the job's hold is gone (finished here, or taken over): heartbeats stop");
                return;
            }
            tracing::warn!(job_id = %id, error = %e, "renewing the job's hold failed");
            pause = RENEW_RETRY.min(every);
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

/// Move a job to a terminal state, tell its watchers and close its channel. Idempotent: a job
/// that is already terminal is returned as it is.
pub(crate) async fn finish(
    inner: &Inner,
    id: &str,
    state: JobState,
    error: Option<(FailureCode, String)>,
    fence: Option<&Fence>,
) -> Result<JobStatus, JobError> {
    let backend = &inner.backend;
    let now = now_ms();
    let expires = now + inner.config.result_ttl.as_millis() as u64;
    let code = error.as_ref().map(|(c, _)| *c);
    let Some(status) = backend
        .store
        .finish(id, state, error, now, expires, fence)
        .await?
    else {
        return backend.store.status(id, None).await;
    };
    backend
        .events
        .publish(id, JobEvent::Done(status.clone()))
        .await?;
    backend.events.close(id).await;
    if status.spec.callback_url.is_some() {
        inner.callbacks_due.notify_one();
    }
    inner.telemetry.record_outcome(
        state,
        code,
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
