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
//! the transport consumes that channel at its client's pace. A client slower than the
//! [`WatchFloor`] is cut off (issue 25 item 6): when an event finds the channel still full after
//! the floor's allowance, or the last events are not taken within it after `Done`, the task
//! drops the channel's receiving end, and with it the events queued there, and the stream
//! ends (SSE: a close the client reconnects from with `Last-Event-ID`; gRPC: a status). So a
//! watcher holds at most [`WATCHER_BUFFER`] events for at most the allowance, whatever its
//! client does, even an HTTP/2 client whose zero window means its stream is never polled.
//!
//! [`EventBus`]: super::ports::EventBus
//! [`JobStore`]: super::ports::JobStore
//! [`BlobStore`]: super::ports::BlobStore

use super::codec::decode_frame_positions;
use super::ports::{BlobKey, BusEvent};
use super::{Frame, FramePositions, JobError, JobEvent, JobId, JobStatus, Jobs};
use futures::stream::BoxStream;
use futures::{Stream, StreamExt};
use std::collections::VecDeque;
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll, Waker};
use std::time::Duration;
use tokio::sync::mpsc::error::SendTimeoutError;

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

/// The pace a watcher's client must keep: it must take each event within `timeout` plus the
/// bytes of the events queued ahead of it at `min_rate`. The default is `willow serve`'s
/// (`--write-timeout-secs 30`, `--write-min-rate-kib 64`), which the transports pass on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct WatchFloor {
    pub timeout: Duration,
    /// Bytes per second; 0: the timeout alone.
    pub min_rate: u64,
}

impl Default for WatchFloor {
    fn default() -> Self {
        WatchFloor {
            timeout: Duration::from_secs(30),
            min_rate: 64 << 10,
        }
    }
}

impl WatchFloor {
    /// `timeout + bytes / min_rate` (saturating).
    pub fn allowance(&self, bytes: usize) -> Duration {
        if self.min_rate == 0 {
            return self.timeout;
        }
        let earned = Duration::try_from_secs_f64(bytes as f64 / self.min_rate as f64)
            .unwrap_or(Duration::MAX);
        self.timeout.saturating_add(earned)
    }
}

/// About what an event weighs on the wire (SSE: positions as base64 of f32 xyz, ~16 bytes a
/// vertex, plus the metrics), for the floor's allowance.
fn event_bytes(ev: &JobEvent) -> usize {
    match ev {
        JobEvent::Frame(f) => {
            512 + f
                .positions
                .as_ref()
                .map_or(0, |p| p.relative.len().saturating_mul(16))
        }
        _ => 1024,
    }
}

/// The receiving end of a watcher's channel, shared with its task so that the task can drop
/// it (and the events queued in it) when the client is too slow.
struct Slot {
    rx: Option<tokio::sync::mpsc::Receiver<JobEvent>>,
    /// The transport's task, woken when the slot is emptied so that it sees the end.
    waker: Option<Waker>,
    /// Whether the watcher cut its client off ([`Tx::cut`]).
    cut: bool,
}

fn lock(slot: &Mutex<Slot>) -> std::sync::MutexGuard<'_, Slot> {
    // Nothing panics while holding it; a poisoned slot is still consistent.
    slot.lock().unwrap_or_else(|e| e.into_inner())
}

/// A job's events for one client ([`Jobs::watch`]); ends early when the client fell below the
/// [`WatchFloor`] ([`Watch::cut`]).
pub struct Watch {
    slot: Arc<Mutex<Slot>>,
    /// Frames travel without it (the bus carries metrics only): the spec says it.
    refined: bool,
}

impl Watch {
    /// A handle that tells, once the stream ended, whether it was cut for a slow client.
    pub fn cut(&self) -> WatchCut {
        WatchCut(self.slot.clone())
    }
}

/// See [`Watch::cut`].
#[derive(Clone)]
pub struct WatchCut(Arc<Mutex<Slot>>);

impl WatchCut {
    /// Whether the watcher dropped its client for being slower than the floor.
    pub fn is_cut(&self) -> bool {
        lock(&self.0).cut
    }
}

impl Drop for Watch {
    /// The client went away: drop the receiving end now (the task shares the slot), so that
    /// the watcher task sees its channel closed and stops at once, as it did before the slot.
    fn drop(&mut self) {
        lock(&self.slot).rx = None;
    }
}

impl Stream for Watch {
    type Item = JobEvent;

    fn poll_next(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<JobEvent>> {
        let refined = self.refined;
        let mut slot = lock(&self.slot);
        let Some(rx) = slot.rx.as_mut() else {
            return Poll::Ready(None);
        };
        let polled = rx.poll_recv(cx);
        if polled.is_pending() {
            slot.waker = Some(cx.waker().clone());
        }
        polled.map(|ev| {
            ev.map(|ev| match ev {
                JobEvent::Frame(mut f) => {
                    f.connectivity_changed = refined && f.step == 0;
                    JobEvent::Frame(f)
                }
                other => other,
            })
        })
    }
}

/// See [`Jobs::watch`].
pub(super) async fn watch(
    jobs: Jobs,
    tenant: &str,
    id: String,
    from_step: usize,
    floor: WatchFloor,
) -> Result<Watch, JobError> {
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
    let (watch, tx) = channel(floor, status.spec.changes_connectivity());
    tokio::spawn(async move {
        match run_watcher(jobs, id.clone(), from_step, status, live, &tx).await {
            // The last events must be taken in time too.
            Ok(()) => tx.linger().await,
            Err(e) => tracing::debug!(job_id = %id, error = %e, "watcher ended"),
        }
    });
    Ok(watch)
}

/// A watcher's channel: the client's end and the task's.
fn channel(floor: WatchFloor, refined: bool) -> (Watch, Tx) {
    let (tx, rx) = tokio::sync::mpsc::channel(WATCHER_BUFFER);
    let slot = Arc::new(Mutex::new(Slot {
        rx: Some(rx),
        waker: None,
        cut: false,
    }));
    let tx = Tx {
        tx,
        slot: slot.clone(),
        floor,
        recent: Mutex::new(VecDeque::with_capacity(WATCHER_BUFFER)),
    };
    (Watch { slot, refined }, tx)
}

/// Why a watcher stopped early (its client went away, or the store failed).
#[derive(Debug, thiserror::Error)]
enum WatchEnd {
    #[error("watcher disconnected")]
    Disconnected,
    #[error("the client took no event within {0:?}: cut off")]
    TooSlow(Duration),
    #[error(transparent)]
    Job(#[from] JobError),
}

/// A watcher task's sending end, with the floor its client must keep.
struct Tx {
    tx: tokio::sync::mpsc::Sender<JobEvent>,
    slot: Arc<Mutex<Slot>>,
    floor: WatchFloor,
    /// Sizes of the last [`WATCHER_BUFFER`] events sent: at most what is queued ahead of the
    /// next one.
    recent: Mutex<VecDeque<usize>>,
}

impl Tx {
    /// The allowance for taking what may be queued, plus `bytes` more.
    fn allowance(&self, bytes: usize) -> Duration {
        let mut recent = self.recent.lock().unwrap_or_else(|e| e.into_inner());
        if recent.len() == WATCHER_BUFFER {
            recent.pop_front();
        }
        recent.push_back(bytes);
        self.floor.allowance(recent.iter().sum())
    }

    /// Drop the client's queue: it falls below the floor.
    fn cut(&self, waited: Duration) -> WatchEnd {
        let mut slot = lock(&self.slot);
        slot.rx = None;
        slot.cut = true;
        if let Some(w) = slot.waker.take() {
            w.wake();
        }
        tracing::info!(secs = waited.as_secs_f64(), "watcher too slow: cut off");
        WatchEnd::TooSlow(waited)
    }

    async fn closed(&self) {
        self.tx.closed().await
    }

    /// After the last event: wait until the client took everything queued (the whole channel
    /// can be reserved), or cut it off at the floor.
    async fn linger(&self) {
        let allowance = self.allowance(0);
        if tokio::time::timeout(allowance, self.tx.reserve_many(WATCHER_BUFFER))
            .await
            .is_err()
        {
            self.cut(allowance);
        }
    }
}

async fn emit(tx: &Tx, ev: JobEvent) -> Result<(), WatchEnd> {
    let allowance = tx.allowance(event_bytes(&ev));
    match tx.tx.send_timeout(ev, allowance).await {
        Ok(()) => Ok(()),
        Err(SendTimeoutError::Closed(_)) => Err(WatchEnd::Disconnected),
        Err(SendTimeoutError::Timeout(_)) => Err(tx.cut(allowance)),
    }
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
    tx: &Tx,
) -> Result<(), WatchEnd> {
    let terminal = status.state.is_terminal();
    emit(tx, JobEvent::State(status)).await?;
    // usize::MAX means "no frames, just states" (used by `Jobs::wait`).
    let skip_frames = from_step == usize::MAX;
    let mut next = if skip_frames {
        usize::MAX
    } else {
        replay(&jobs, &id, from_step, tx).await?
    };
    let mut live = match live {
        Some(rx) if !terminal => rx,
        _ => return finish_from_store(&jobs, &id, next, tx).await,
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
                    return finish_from_store(&jobs, &id, next, tx).await;
                }
                if !skip_frames && status.step >= next && status.latest.is_some() {
                    next = replay(&jobs, &id, next, tx).await?;
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
                    next = replay(&jobs, &id, next, tx).await?;
                    if f.step < next {
                        continue;
                    }
                }
                if has_positions && f.positions.is_none() {
                    f.positions = stored_positions(&jobs, &id, f.step).await?;
                }
                next = f.step + 1;
                emit(tx, JobEvent::Frame(f)).await?;
            }
            Some(BusEvent::Event {
                event: JobEvent::State(s),
                ..
            }) => emit(tx, JobEvent::State(s)).await?,
            Some(BusEvent::Event {
                event: JobEvent::Done(s),
                ..
            }) => {
                if !skip_frames {
                    replay(&jobs, &id, next, tx).await?;
                }
                return emit(tx, JobEvent::Done(s)).await;
            }
            Some(BusEvent::Lagged) => {
                tracing::debug!(job_id = %id, "watcher lagged: resuming from the store");
                if !skip_frames {
                    next = replay(&jobs, &id, next, tx).await?;
                }
            }
            None => {
                // The channel closed: after `Done` (embedded), or the bus connection dropped
                // (NATS). Only a terminal job ends the watch; otherwise subscribe again and
                // catch up on what went by meanwhile.
                let status = status_now(&jobs, &id).await?;
                if status.state.is_terminal() {
                    return finish_from_store(&jobs, &id, next, tx).await;
                }
                tokio::time::sleep(RESUBSCRIBE_PAUSE).await;
                live = jobs.read(jobs.inner.backend.events.subscribe(&id)).await?;
                if !skip_frames {
                    next = replay(&jobs, &id, next, tx).await?;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_floor_allows_the_timeout_plus_the_bytes_at_the_rate() {
        let floor = WatchFloor {
            timeout: Duration::from_secs(2),
            min_rate: 1 << 20,
        };
        assert_eq!(floor.allowance(3 << 20), Duration::from_secs(5));
        let timeout_only = WatchFloor {
            min_rate: 0,
            ..floor
        };
        assert_eq!(timeout_only.allowance(usize::MAX), Duration::from_secs(2));
    }

    #[tokio::test]
    async fn a_client_that_goes_away_closes_the_watchers_channel_at_once() {
        let (watch, tx) = channel(WatchFloor::default(), false);
        let cut = watch.cut();
        assert!(!tx.tx.is_closed());
        drop(watch);
        // The task sees it (`closed()` resolves) without waiting for the floor.
        tokio::time::timeout(Duration::from_secs(5), tx.closed())
            .await
            .expect("closed at once");
        assert!(!cut.is_cut(), "gone, not cut off");
    }

    #[tokio::test]
    async fn a_cut_empties_the_queue_and_ends_the_stream() {
        let floor = WatchFloor {
            timeout: Duration::from_millis(20),
            min_rate: 0,
        };
        let (mut watch, tx) = channel(floor, false);
        let cut = watch.cut();
        tx.linger().await;
        assert!(!cut.is_cut(), "nothing queued: nothing to cut");
        // Nobody takes what is queued: the linger after the last event cuts it off.
        let metrics = super::super::codec::decode_metrics(&[0; super::super::codec::METRICS_BYTES])
            .expect("zero metrics");
        for step in 0..WATCHER_BUFFER {
            tx.tx
                .try_send(JobEvent::Frame(Frame {
                    step,
                    metrics,
                    positions: None,
                    connectivity_changed: false,
                }))
                .expect("room");
        }
        tx.linger().await;
        assert!(cut.is_cut());
        assert!(
            tx.tx.is_closed(),
            "the queued events are dropped with the receiver"
        );
        assert!(watch.next().await.is_none(), "the stream ends");
    }
}
