//! Fan-out of job events to watchers, with replay from the store.
//!
//! Each live job has a `tokio::sync::broadcast` channel: the worker's `send` never waits, so a
//! slow watcher cannot stall the flow. A watcher that falls more than [`LIVE_CAPACITY`] events
//! behind gets `Lagged` and catches up from the store, where every frame is written *before*
//! it is broadcast. Each watcher runs as a small task feeding a bounded channel of
//! [`WATCHER_BUFFER`] events; the transport consumes that channel at its client's pace.

use super::{join_err, Frame, JobError, JobEvent, JobId, JobStatus, Jobs};
use futures::Stream;
use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use tokio::sync::broadcast;
use tokio_stream::wrappers::ReceiverStream;

/// Live events buffered per job. A step takes milliseconds to seconds, so 128 events is
/// seconds to minutes of slack before a watcher has to fall back to the store; positions are
/// shared (`Arc`), so the buffer costs little memory.
pub const LIVE_CAPACITY: usize = 128;

/// Events queued between a watcher task and its transport: small, because the task reads the
/// store again when the client is slow rather than holding frames in memory.
pub const WATCHER_BUFFER: usize = 16;

/// Stored frames read from the store per batch during replay.
const REPLAY_BATCH: usize = 64;

/// The live channels of jobs that are not terminal.
#[derive(Default)]
pub struct EventHub {
    channels: Mutex<HashMap<JobId, broadcast::Sender<JobEvent>>>,
}

impl EventHub {
    fn map(&self) -> std::sync::MutexGuard<'_, HashMap<JobId, broadcast::Sender<JobEvent>>> {
        // The map is consistent after any panic (single insert/remove calls).
        self.channels.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Open the channel of a newly admitted (or recovered) job.
    pub fn open(&self, id: &str) {
        self.map()
            .entry(id.to_string())
            .or_insert_with(|| broadcast::channel(LIVE_CAPACITY).0);
    }

    /// Send to current watchers; nobody listening is fine.
    pub fn send(&self, id: &str, ev: JobEvent) {
        if let Some(tx) = self.map().get(id) {
            let _ = tx.send(ev);
        }
    }

    /// Close a terminal job's channel: watchers see `Closed` after the `Done` sent before.
    pub fn close(&self, id: &str) {
        self.map().remove(id);
    }

    /// Subscribe to a job's live events, opening its channel if needed. Channels are opened
    /// lazily (by the first watcher or when the job starts), not at admission: a channel
    /// preallocates [`LIVE_CAPACITY`] slots, tens of KiB that a queued job nobody watches
    /// should not hold.
    pub fn subscribe(&self, id: &str) -> broadcast::Receiver<JobEvent> {
        self.map()
            .entry(id.to_string())
            .or_insert_with(|| broadcast::channel(LIVE_CAPACITY).0)
            .subscribe()
    }

    /// Drop a channel nobody listens to (a watcher of a finished or unknown job opened it).
    pub fn close_if_idle(&self, id: &str) {
        let mut map = self.map();
        if map.get(id).is_some_and(|tx| tx.receiver_count() == 0) {
            map.remove(id);
        }
    }
}

/// See [`Jobs::watch`].
pub(super) async fn watch(
    jobs: Jobs,
    id: String,
    from_step: usize,
) -> Result<impl Stream<Item = JobEvent> + Send + 'static, JobError> {
    // Subscribe before reading the store: every frame is either already stored or still to
    // come on the channel, so none falls between the two.
    let live = jobs.inner.hub.subscribe(&id);
    let status = match jobs.get(&id).await {
        Ok(s) => s,
        Err(e) => {
            drop(live);
            jobs.inner.hub.close_if_idle(&id);
            return Err(e);
        }
    };
    let live = if status.state.is_terminal() {
        // Nothing more will be sent: replay from the store only.
        drop(live);
        jobs.inner.hub.close_if_idle(&id);
        None
    } else {
        Some(live)
    };
    let (tx, rx) = tokio::sync::mpsc::channel(WATCHER_BUFFER);
    tokio::spawn(async move {
        if let Err(e) = run_watcher(jobs, id.clone(), from_step, status, live, tx).await {
            tracing::debug!(job_id = %id, error = %e, "watcher ended");
        }
    });
    Ok(ReceiverStream::new(rx))
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

/// Send stored frames with step >= `next` and return the step expected after them.
async fn replay(jobs: &Jobs, id: &str, mut next: usize, tx: &Tx) -> Result<usize, WatchEnd> {
    loop {
        let inner = jobs.inner.clone();
        let id2 = id.to_string();
        let batch = tokio::task::spawn_blocking(move || {
            let rows = inner.store.frame_rows(&id2, next, REPLAY_BATCH)?;
            let mut frames = Vec::with_capacity(rows.len());
            for (metrics, has_positions) in rows {
                let positions = if has_positions {
                    // A frame file can be missing only if the job was requeued meanwhile.
                    inner
                        .store
                        .read_frame_positions(&id2, metrics.step)
                        .ok()
                        .map(Arc::new)
                } else {
                    None
                };
                frames.push(Frame {
                    step: metrics.step,
                    metrics,
                    positions,
                });
            }
            Ok::<_, JobError>(frames)
        })
        .await
        .map_err(join_err)??;
        let n = batch.len();
        for f in batch {
            next = f.step + 1;
            emit(tx, JobEvent::Frame(f)).await?;
        }
        if n < REPLAY_BATCH {
            return Ok(next);
        }
    }
}

async fn finish_from_store(jobs: &Jobs, id: &str, next: usize, tx: &Tx) -> Result<(), WatchEnd> {
    let status = jobs.get(id).await?;
    if next != usize::MAX {
        replay(jobs, id, next, tx).await?;
    }
    emit(tx, JobEvent::Done(status)).await
}

async fn run_watcher(
    jobs: Jobs,
    id: String,
    from_step: usize,
    status: JobStatus,
    live: Option<broadcast::Receiver<JobEvent>>,
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
    loop {
        let ev = tokio::select! {
            ev = live.recv() => ev,
            // Stop promptly when the client goes away, not at the job's next event.
            _ = tx.closed() => return Err(WatchEnd::Disconnected),
        };
        match ev {
            Ok(JobEvent::Frame(f)) => {
                if skip_frames || f.step < next {
                    continue; // already replayed
                }
                if f.step > next {
                    // Steps in between were stored before this one was sent.
                    next = replay(&jobs, &id, next, &tx).await?;
                    if f.step < next {
                        continue;
                    }
                }
                next = f.step + 1;
                emit(&tx, JobEvent::Frame(f)).await?;
            }
            Ok(JobEvent::State(s)) => {
                if !skip_frames && s.step == 0 && next > 0 && s.state == super::JobState::Queued {
                    // Re-queued (shutdown): the job restarts from step 0.
                    next = 0;
                }
                emit(&tx, JobEvent::State(s)).await?;
            }
            Ok(JobEvent::Done(s)) => {
                if !skip_frames {
                    replay(&jobs, &id, next, &tx).await?;
                }
                return emit(&tx, JobEvent::Done(s)).await;
            }
            Err(broadcast::error::RecvError::Lagged(missed)) => {
                tracing::debug!(job_id = %id, missed, "watcher lagged: resuming from the store");
                if !skip_frames {
                    next = replay(&jobs, &id, next, &tx).await?;
                }
            }
            Err(broadcast::error::RecvError::Closed) => {
                return finish_from_store(&jobs, &id, next, &tx).await;
            }
        }
    }
}
