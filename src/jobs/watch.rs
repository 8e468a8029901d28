//! Watching a job: its state, its stored frames (replay), then its live frames, on any node.
//!
//! Written once over the ports: the live events come from the [`EventBus`], the replay from
//! the [`JobStore`] (metrics) and the [`BlobStore`] (positions). Every frame is stored before
//! it is published, and a watcher subscribes before it reads the store, so no frame falls
//! between the two. A watcher that lags (or a frame that arrives after a gap) is caught up
//! from the store, so a watcher sees every step once and in order, and never slows the worker
//! down. Steps it has already sent are skipped: a job resumed from a checkpoint publishes the
//! steps after the checkpoint again, and nobody sees a step number twice.
//!
//! Each watcher runs as a small task feeding a bounded channel of [`WATCHER_BUFFER`] events;
//! the transport consumes that channel at its client's pace.
//!
//! [`EventBus`]: super::ports::EventBus
//! [`JobStore`]: super::ports::JobStore
//! [`BlobStore`]: super::ports::BlobStore

use super::codec::decode_frame_positions;
use super::ports::{BlobKey, BusEvent};
use super::{Frame, FramePositions, JobError, JobEvent, JobId, JobStatus, Jobs};
use futures::stream::BoxStream;
use futures::{Stream, StreamExt};
use std::sync::Arc;
use tokio_stream::wrappers::ReceiverStream;

/// Events queued between a watcher task and its transport: small, because the task reads the
/// store again when the client is slow rather than holding frames in memory.
pub const WATCHER_BUFFER: usize = 16;

/// How long a watcher whose live channel closed under a running job waits before it
/// subscribes again (a bus reconnecting).
const RESUBSCRIBE_PAUSE: std::time::Duration = std::time::Duration::from_millis(250);

/// How long a watcher's live channel may stay silent before it asks the store whether the
/// job has moved on without it.
const QUIET_CHECK: std::time::Duration = std::time::Duration::from_secs(5);

/// Stored frames read from the store per batch during replay.
const REPLAY_BATCH: usize = 64;

/// See [`Jobs::watch`].
pub(super) async fn watch(
    jobs: Jobs,
    tenant: &str,
    id: String,
    from_step: usize,
) -> Result<impl Stream<Item = JobEvent> + Send + 'static, JobError> {
    let backend = &jobs.inner.backend;
    let id = JobId::parse(&id)?;
    // Subscribe before reading the store: every frame is either already stored or still to
    // come on the bus, so none falls between the two.
    let live = backend.events.subscribe(&id).await?;
    let status = match backend.store.status(&id, Some(tenant)).await {
        Ok(s) => s,
        Err(e) => {
            drop(live);
            backend.events.close(&id).await;
            return Err(e);
        }
    };
    let live = if status.state.is_terminal() {
        // Nothing more will be sent: replay from the store only.
        drop(live);
        backend.events.close(&id).await;
        None
    } else {
        Some(live)
    };
    let (tx, rx) = tokio::sync::mpsc::channel(WATCHER_BUFFER);
    // Frames travel without it (the bus carries metrics only): the spec says it, for live and
    // replayed frames alike.
    let refined = status.spec.refine;
    tokio::spawn(async move {
        if let Err(e) = run_watcher(jobs, id.clone(), from_step, status, live, tx).await {
            tracing::debug!(job_id = %id, error = %e, "watcher ended");
        }
    });
    Ok(ReceiverStream::new(rx).map(move |ev| match ev {
        JobEvent::Frame(mut f) => {
            f.connectivity_changed = refined && f.step == 0;
            JobEvent::Frame(f)
        }
        other => other,
    }))
}

/// Why a watcher stopped early (its client went away, or the store failed).
#[derive(Debug, thiserror::Error)]
enum WatchEnd {
    #[error("watcher disconnected")]
    Disconnected,
    #[error(transparent)]
    Job(#[from] JobError),
}

type Tx = tokio::sync::mpsc::Sender<JobEvent>;

async fn emit(tx: &Tx, ev: JobEvent) -> Result<(), WatchEnd> {
    tx.send(ev).await.map_err(|_| WatchEnd::Disconnected)
}

/// A frame's positions in the file's vertex order, from the blob store. `None` if they are
/// gone (the job expired, or a resumed job has not written that step again yet). A store
/// that cannot answer (NATS away) ends the watch, a close the client reconnects from with
/// `Last-Event-ID`, rather than sending the frame without the positions it kept.
async fn stored_positions(
    jobs: &Jobs,
    id: &JobId,
    step: usize,
) -> Result<Option<Arc<FramePositions>>, JobError> {
    let key = BlobKey::Frame {
        id: id.clone(),
        step,
        welded: false,
    };
    let Some(bytes) = jobs.on_request(jobs.inner.backend.blobs.get(key)).await? else {
        return Ok(None);
    };
    Ok(decode_frame_positions(&bytes).ok().map(Arc::new))
}

/// The job's status, bounded like a client's read ([`Jobs::read`]): a watcher whose store is
/// away ends (a reconnectable close) instead of going silent for the outage.
async fn status_now(jobs: &Jobs, id: &JobId) -> Result<JobStatus, JobError> {
    jobs.read(jobs.inner.backend.store.status(id, None)).await
}

/// Send stored frames with step >= `next` and return the step expected after them.
async fn replay(jobs: &Jobs, id: &JobId, mut next: usize, tx: &Tx) -> Result<usize, WatchEnd> {
    loop {
        let rows = jobs
            .read(jobs.inner.backend.store.frame_rows(id, next, REPLAY_BATCH))
            .await?;
        let n = rows.len();
        for (metrics, has_positions) in rows {
            if metrics.step < next {
                continue; // a store may repeat a step a resumed job took again
            }
            let positions = if has_positions {
                stored_positions(jobs, id, metrics.step).await?
            } else {
                None
            };
            next = metrics.step + 1;
            let frame = Frame {
                step: metrics.step,
                metrics,
                positions,
                connectivity_changed: false,
            };
            emit(tx, JobEvent::Frame(frame)).await?;
        }
        if n < REPLAY_BATCH {
            return Ok(next);
        }
    }
}

async fn finish_from_store(jobs: &Jobs, id: &JobId, next: usize, tx: &Tx) -> Result<(), WatchEnd> {
    let status = status_now(jobs, id).await?;
    if next != usize::MAX {
        replay(jobs, id, next, tx).await?;
    }
    emit(tx, JobEvent::Done(status)).await
}

async fn run_watcher(
    jobs: Jobs,
    id: JobId,
    from_step: usize,
    status: JobStatus,
    live: Option<BoxStream<'static, BusEvent>>,
    tx: Tx,
) -> Result<(), WatchEnd> {
    let terminal = status.state.is_terminal();
    emit(&tx, JobEvent::State(status)).await?;
    // usize::MAX means "no frames, just states" (used by `Jobs::wait`).
    let skip_frames = from_step == usize::MAX;
    let mut next = if skip_frames {
        usize::MAX
    } else {
        replay(&jobs, &id, from_step, &tx).await?
    };
    let mut live = match live {
        Some(rx) if !terminal => rx,
        _ => return finish_from_store(&jobs, &id, next, &tx).await,
    };
    let mut quiet = tokio::time::interval(QUIET_CHECK);
    quiet.reset();
    loop {
        let ev = tokio::select! {
            ev = live.next() => ev,
            // Stop promptly when the client goes away, not at the job's next event.
            _ = tx.closed() => return Err(WatchEnd::Disconnected),
            // A bus that lost messages (NATS while reconnecting) may have lost the `Done`:
            // a quiet channel is checked against the store now and then.
            _ = quiet.tick() => {
                let status = status_now(&jobs, &id).await?;
                if status.state.is_terminal() {
                    return finish_from_store(&jobs, &id, next, &tx).await;
                }
                if !skip_frames && status.step >= next && status.latest.is_some() {
                    next = replay(&jobs, &id, next, &tx).await?;
                }
                continue;
            }
        };
        quiet.reset();
        match ev {
            Some(BusEvent::Event {
                event: JobEvent::Frame(mut f),
                has_positions,
            }) => {
                if skip_frames || f.step < next {
                    continue; // already sent
                }
                if f.step > next {
                    // Steps in between were stored before this one was published.
                    next = replay(&jobs, &id, next, &tx).await?;
                    if f.step < next {
                        continue;
                    }
                }
                if has_positions && f.positions.is_none() {
                    f.positions = stored_positions(&jobs, &id, f.step).await?;
                }
                next = f.step + 1;
                emit(&tx, JobEvent::Frame(f)).await?;
            }
            Some(BusEvent::Event {
                event: JobEvent::State(s),
                ..
            }) => emit(&tx, JobEvent::State(s)).await?,
            Some(BusEvent::Event {
                event: JobEvent::Done(s),
                ..
            }) => {
                if !skip_frames {
                    replay(&jobs, &id, next, &tx).await?;
                }
                return emit(&tx, JobEvent::Done(s)).await;
            }
            Some(BusEvent::Lagged) => {
                tracing::debug!(job_id = %id, "watcher lagged: resuming from the store");
                if !skip_frames {
                    next = replay(&jobs, &id, next, &tx).await?;
                }
            }
            None => {
                // The channel closed: after `Done` (embedded), or the bus connection dropped
                // (NATS). Only a terminal job ends the watch; otherwise subscribe again and
                // catch up on what went by meanwhile.
                let status = status_now(&jobs, &id).await?;
                if status.state.is_terminal() {
                    return finish_from_store(&jobs, &id, next, &tx).await;
                }
                tokio::time::sleep(RESUBSCRIBE_PAUSE).await;
                live = jobs.read(jobs.inner.backend.events.subscribe(&id)).await?;
                if !skip_frames {
                    next = replay(&jobs, &id, next, &tx).await?;
                }
            }
        }
    }
}
