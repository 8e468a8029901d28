//! The embedded [`EventBus`] and [`CancelBus`]: in-process channels and tokens.
//!
//! Each live job has a `tokio::sync::broadcast` channel: the worker's `publish` never waits, so
//! a slow watcher cannot stall the flow. A watcher that falls more than [`LIVE_CAPACITY`]
//! events behind gets [`BusEvent::Lagged`] and catches up from the store, where every frame is
//! written before it is published. Frames travel with their positions (`Arc`, no copy).

use super::super::ports::{BusEvent, CancelBus, EventBus};
use super::super::{JobError, JobEvent};
use async_trait::async_trait;
use futures::stream::BoxStream;
use futures::StreamExt;
use std::collections::{HashMap, HashSet};
use std::sync::Mutex;
use tokio::sync::broadcast;
use tokio_stream::wrappers::errors::BroadcastStreamRecvError;
use tokio_stream::wrappers::BroadcastStream;
use tokio_util::sync::CancellationToken;

/// Live events buffered per job. A step takes milliseconds to seconds, so 128 events is
/// seconds to minutes of slack before a watcher has to fall back to the store; positions are
/// shared (`Arc`), so the buffer costs little memory.
pub const LIVE_CAPACITY: usize = 128;

/// The live channels of jobs that are not terminal.
#[derive(Default)]
pub struct Broadcast {
    channels: Mutex<HashMap<String, broadcast::Sender<JobEvent>>>,
}

impl Broadcast {
    fn map(&self) -> std::sync::MutexGuard<'_, HashMap<String, broadcast::Sender<JobEvent>>> {
        // The map is consistent after any panic (single insert/remove calls).
        self.channels.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Channels open now (for tests: a finished job leaves none behind).
    pub fn open_channels(&self) -> usize {
        self.map().len()
    }
}

#[async_trait]
impl EventBus for Broadcast {
    async fn publish(&self, id: &str, event: JobEvent) -> Result<(), JobError> {
        if let Some(tx) = self.map().get(id) {
            let _ = tx.send(event);
        }
        Ok(())
    }

    /// Channels are opened by their first subscriber, not at admission: a channel
    /// preallocates [`LIVE_CAPACITY`] slots, tens of KiB that a job nobody watches should not
    /// hold. Events published while nobody listens are in the store.
    async fn subscribe(&self, id: &str) -> Result<BoxStream<'static, BusEvent>, JobError> {
        let rx = self
            .map()
            .entry(id.to_string())
            .or_insert_with(|| broadcast::channel(LIVE_CAPACITY).0)
            .subscribe();
        Ok(BroadcastStream::new(rx)
            .map(|item| match item {
                Ok(event) => {
                    let has_positions =
                        matches!(&event, JobEvent::Frame(f) if f.positions.is_some());
                    BusEvent::Event {
                        event,
                        has_positions,
                    }
                }
                Err(BroadcastStreamRecvError::Lagged(_)) => BusEvent::Lagged,
            })
            .boxed())
    }

    async fn close(&self, id: &str) {
        self.map().remove(id);
    }
}

/// Tokens of the jobs running in this process, and cancels that came before their worker.
#[derive(Default)]
pub struct LocalCancels {
    state: Mutex<Cancels>,
}

#[derive(Default)]
struct Cancels {
    running: HashMap<String, CancellationToken>,
    /// Cancelled while between the queue and its worker's `watch`.
    early: HashSet<String>,
}

impl LocalCancels {
    fn state(&self) -> std::sync::MutexGuard<'_, Cancels> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }
}

#[async_trait]
impl CancelBus for LocalCancels {
    async fn cancel(&self, id: &str) -> Result<(), JobError> {
        let mut s = self.state();
        match s.running.get(id) {
            Some(token) => token.cancel(),
            None => {
                s.early.insert(id.to_string());
            }
        }
        Ok(())
    }

    async fn watch(&self, id: &str) -> CancellationToken {
        let mut s = self.state();
        let token = CancellationToken::new();
        if s.early.remove(id) {
            token.cancel();
        }
        s.running.insert(id.to_string(), token.clone());
        token
    }

    async fn forget(&self, id: &str) {
        let mut s = self.state();
        s.running.remove(id);
        s.early.remove(id);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn a_cancel_before_the_worker_watches_is_not_lost() {
        let c = LocalCancels::default();
        c.cancel("a").await.expect("cancel");
        assert!(c.watch("a").await.is_cancelled());
        let b = c.watch("b").await;
        assert!(!b.is_cancelled());
        c.cancel("b").await.expect("cancel");
        assert!(b.is_cancelled());
        c.forget("a").await;
        c.forget("b").await;
        assert!(!c.watch("a").await.is_cancelled(), "forgotten");
    }
}
