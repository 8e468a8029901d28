//! The NATS [`EventBus`] and [`CancelBus`]: core subjects, no persistence (the frames are in
//! the store before they are published, and a cancel leaves a mark in KV).
//!
//! Live frames go to `willow.live.{id}` with the metrics only (`[has_positions][metrics]`):
//! positions are in the object store, and a 1M-vertex frame would exceed a message. States go
//! to `willow.events.{id}` as JSON (`{"state": status}` or `{"done": status}`). Core NATS drops
//! messages for a subscriber that cannot keep up; the watcher notices the gap in step numbers
//! and replays from the store.

use super::super::codec::{decode_metrics, encode_metrics};
use super::super::ports::{BusEvent, CancelBus, EventBus};
use super::super::{Frame, JobError, JobEvent, JobStatus};
use super::{nats_err, Nats};
use async_trait::async_trait;
use futures::stream::BoxStream;
use futures::StreamExt;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use tokio_util::sync::CancellationToken;

pub(crate) struct NatsBus {
    nats: Arc<Nats>,
}

impl NatsBus {
    pub fn new(nats: Arc<Nats>) -> NatsBus {
        NatsBus { nats }
    }
}

#[derive(Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
enum StateMessage {
    State(JobStatus),
    Done(JobStatus),
}

#[async_trait]
impl EventBus for NatsBus {
    async fn publish(&self, id: &str, event: JobEvent) -> Result<(), JobError> {
        let (subject, payload) = match event {
            JobEvent::Frame(f) => {
                let mut payload = Vec::with_capacity(97);
                payload.push(u8::from(f.positions.is_some()));
                payload.extend_from_slice(&encode_metrics(&f.metrics));
                (format!("willow.live.{id}"), payload)
            }
            JobEvent::State(s) => (
                format!("willow.events.{id}"),
                json(&StateMessage::State(without_latest(s)))?,
            ),
            JobEvent::Done(s) => (
                format!("willow.events.{id}"),
                json(&StateMessage::Done(without_latest(s)))?,
            ),
        };
        self.nats
            .client
            .publish(subject, payload.into())
            .await
            .map_err(|e| nats_err("publishing an event", e))
    }

    async fn subscribe(&self, id: &str) -> Result<BoxStream<'static, BusEvent>, JobError> {
        let live = self
            .nats
            .client
            .subscribe(format!("willow.live.{id}"))
            .await
            .map_err(|e| nats_err("subscribing", e))?;
        let states = self
            .nats
            .client
            .subscribe(format!("willow.events.{id}"))
            .await
            .map_err(|e| nats_err("subscribing", e))?;
        // The subscriptions must be registered with the server before the caller reads the
        // store, or a frame published in between would be neither stored-then-read nor seen.
        self.nats
            .client
            .flush()
            .await
            .map_err(|e| nats_err("subscribing", e))?;
        let frames = live.filter_map(|m| async move {
            let (&flag, metrics) = m.payload.split_first()?;
            let metrics = decode_metrics(metrics).ok()?;
            Some(BusEvent::Event {
                event: JobEvent::Frame(Frame {
                    step: metrics.step,
                    metrics,
                    positions: None,
                    connectivity_changed: false,
                }),
                has_positions: flag != 0,
            })
        });
        let states = states.filter_map(|m| async move {
            let event = match serde_json::from_slice::<StateMessage>(&m.payload).ok()? {
                StateMessage::State(s) => JobEvent::State(s),
                StateMessage::Done(s) => JobEvent::Done(s),
            };
            Some(BusEvent::Event {
                event,
                has_positions: false,
            })
        });
        Ok(futures::stream::select(frames, states).boxed())
    }

    async fn close(&self, _id: &str) {}
}

/// States travel without `latest` (JSON cannot carry a NaN metric); watchers get the metrics
/// from the frames.
fn without_latest(mut s: JobStatus) -> JobStatus {
    s.latest = None;
    s
}

fn json<T: Serialize>(v: &T) -> Result<Vec<u8>, JobError> {
    serde_json::to_vec(v).map_err(|e| JobError::Internal(format!("encoding an event: {e}")))
}

/// Tokens of the jobs this node runs; one subscription to `willow.cancel.*` feeds them.
pub(crate) struct NatsCancels {
    nats: Arc<Nats>,
    running: Arc<Mutex<HashMap<String, CancellationToken>>>,
}

impl NatsCancels {
    pub async fn start(nats: Arc<Nats>) -> Result<NatsCancels, JobError> {
        let running: Arc<Mutex<HashMap<String, CancellationToken>>> = Arc::default();
        let mut sub = nats
            .client
            .subscribe("willow.cancel.*")
            .await
            .map_err(|e| nats_err("subscribing to cancels", e))?;
        let map = Arc::downgrade(&running);
        tokio::spawn(async move {
            while let Some(m) = sub.next().await {
                let Some(map) = map.upgrade() else { return };
                let Some(id) = m.subject.as_str().strip_prefix("willow.cancel.") else {
                    continue;
                };
                let token = map
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .get(id)
                    .cloned();
                if let Some(t) = token {
                    t.cancel();
                }
            }
        });
        Ok(NatsCancels { nats, running })
    }

    fn map(&self) -> std::sync::MutexGuard<'_, HashMap<String, CancellationToken>> {
        self.running.lock().unwrap_or_else(|p| p.into_inner())
    }
}

#[async_trait]
impl CancelBus for NatsCancels {
    async fn cancel(&self, id: &str) -> Result<(), JobError> {
        // The mark first: a worker that starts the job after the message went by still sees
        // it (`watch` reads it).
        self.nats
            .kv
            .put(format!("cancel.{id}"), bytes::Bytes::from_static(b"1"))
            .await
            .map_err(|e| nats_err("marking a cancel", e))?;
        self.nats
            .client
            .publish(format!("willow.cancel.{id}"), bytes::Bytes::new())
            .await
            .map_err(|e| nats_err("publishing a cancel", e))
    }

    async fn watch(&self, id: &str) -> CancellationToken {
        let token = CancellationToken::new();
        self.map().insert(id.to_string(), token.clone());
        match self.nats.kv.get(format!("cancel.{id}")).await {
            Ok(Some(_)) => token.cancel(),
            Ok(None) => {}
            Err(e) => tracing::warn!(job_id = %id, error = %e, "could not read the cancel mark"),
        }
        token
    }

    async fn forget(&self, id: &str) {
        self.map().remove(id);
    }
}
